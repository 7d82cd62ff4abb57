"""Sequences in the browser: the Sequence folder with its timeline, and plots across frames."""
