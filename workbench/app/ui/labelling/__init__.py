"""Labelling ground truth in the browser: the Label tab, its controls, the pose editor and the choice of modes."""
