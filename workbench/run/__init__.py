"""Running the estimator over dataset frames: the one frame loop, here or on Ray (``frames``), and ``estimate``'s
runner with its progress (``runner``)."""
