"""Where hypotheses come from: one module per proposal kind, and the mix that draws from them.

- ``scenepoints``: the observed points above the table, their clusters, and how well a scene explains them.
- ``resting``: each object's stable resting poses on a plane; moves to another face or a quarter/half turn.
- ``gaussian``: Gaussian steps, joint (the paper's diffusion) or of one object at a time.
- ``stacking``: onto another object, and off it again.
- ``datadriven``: candidate placements fitted to clusters of observed points; starts and moves drawn from them.
- ``refine``: ICP of one object against the observed points near it.
- ``moves``: the move kinds, the mix, and the per-kind counts.

Every proposal is a small pure function ``(rng, parents (B, K, 4, 4), ...) -> Proposal`` whose ``log_q_ratio``
(B,) is log q(X | X*) - log q(X* | X), so that PI-MCPF's Metropolis-Hastings acceptance stays exact for
data-driven moves. Every hypothesis still goes through physics projection and the likelihood.
"""
