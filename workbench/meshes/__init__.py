"""Meshes as the estimator needs them: heavy meshes simplified (``heavy``) and checked cache files (``cache``)."""
