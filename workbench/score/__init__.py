"""Scoring estimates against ground truth: pose errors up to symmetry (``metrics``), ``workbench score``
(``scoring``), BOP's VSD (``vsd``) and average recall (``ar``), the posterior's calibration (``calibration``) and what a
dataset says of its ground truth (``gt_info``)."""
