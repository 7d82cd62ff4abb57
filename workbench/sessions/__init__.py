"""Sessions: a run saved whole and continued later exactly where it stopped (``store``: save, load, list, the
folder's lock), its JSON document with its format and migrations (``document``), the settled answer as JSON
(``answer``), a sequence's position (``sequence_record``)."""
