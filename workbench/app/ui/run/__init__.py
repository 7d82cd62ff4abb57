"""The run's display: the 3D view, the estimate with its modes, status, truth, plots and the estimator's settings."""
