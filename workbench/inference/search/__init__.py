"""Where hypotheses come from: the searches (``default_search``, ``paper_search``, ``track_search``), the objects'
geometry they share (``geometry``) and what they draw on (clusters, candidates fitted to them, leaning and hiding
places, ICP). Move kinds are in ``moves``."""
