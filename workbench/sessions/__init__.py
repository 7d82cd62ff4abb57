"""Sessions: a run saved whole and continued later exactly where it stopped (``store``), the settled answer as JSON (``answer``), a sequence's position (``sequence_record``)."""
