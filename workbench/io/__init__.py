"""Data in and out at the edges: BOP datasets in (``bop``), a plain single frame (``plainframe``), results out (the
rows, the BOP results CSV and the posterior JSON: ``results``) and the guards of every file written (``outputs``);
all input validation, millimetres converted to metres here."""
