"""Inference: the particle filter, where its hypotheses come from, and the answer it gives.

- ``estimator``: the estimator a user runs (``Estimator``): a filter with a search, its settled answer, its
  state for sessions; ``config``: its settings (``EstimatorConfig``).
- ``smc``: the sequential Monte Carlo core: ``filter.ParticleFilter`` (PI-PF / PI-MCPF, tempering, the
  Metropolis-Hastings step, the estimate, convergence), the one owner of the filter's state; the particle set;
  log-weights; random starts.
- ``search``: the searches behind the filter's hooks (the paper's, the default data-driven one, a tracked
  frame's), the per-object geometry they share (``geometry.SearchGeometry``) and the geometry they draw on
  (clusters of observed points, fitted candidates, leaning and hiding places, ICP); ``search.moves``: the move
  kinds, their registry and mix.
- ``answer``: what a run answers: the estimate polished (``polish``, ``assemble``), settled to the depth
  (``settle``), and its posterior per object (``posterior``, ``carried_posterior`` for tracked frames).

Every proposal is a small pure function ``(rng, parents (B, K, 4, 4), ...) -> Proposal`` whose ``log_q_ratio``
(B,) is log q(X | X*) - log q(X* | X), so that PI-MCPF's Metropolis-Hastings acceptance stays exact for
data-driven moves. Every hypothesis still goes through physics projection and the likelihood.
"""
