"""The estimation problem: what the estimator is given (``scene``), the table found in the depth (``support``), the
cropped observation a particle evaluation needs (``problem``), and building it from files (``build``)."""
