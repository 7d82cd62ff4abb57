"""Data in and out at the edges: BOP datasets in and BOP results CSV out (``bop``), a plain single frame
(``plainframe``); all input validation, millimetres converted to metres here."""
