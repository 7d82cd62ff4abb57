"""The generated depth sensor: its models (``model``: ideal, kinect-like, xtion) and the error statistics they are
fitted to and checked against on real frames (``stats``, run by ``benchmarks/sensor_stats.py``)."""
