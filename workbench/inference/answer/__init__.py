"""The answer of a run: the estimate polished (``polish``, ``assemble``), settled to the depth (``settle``), and the
posterior per object (``posterior``, ``carried_posterior`` for tracked frames)."""
