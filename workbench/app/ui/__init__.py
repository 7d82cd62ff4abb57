"""The server process of the workbench: the viser server and one folder per feature (``run``, ``labelling``,
``sequence``, ``sessions``) with shared ``widgets``."""
