"""The estimator process of the workbench: the ``Engine`` answering the server's commands, its evaluators, the
frame's observation, the snapshots it sends, and its labels, sequence and sessions."""
