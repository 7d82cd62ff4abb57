"""Measuring the estimator: the paper's Tables I and II over a generated suite (``tables``, `workbench bench`), the
speed of each stage (``speed``, `bench --speed`), a results CSV scored against the ground truth (``scoring``,
`workbench score`), how well the posterior's probabilities are calibrated (``calibration``), and the paper's ICP
baseline (``baseline``)."""
