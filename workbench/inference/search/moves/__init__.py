"""The move kinds of the default search: the registry and the mix (``registry``), what a move is and sees
(``context``), and one module per kind's geometry."""
