"""The sequential Monte Carlo core: ``filter.ParticleFilter`` (PI-PF / PI-MCPF) over one ``particleset.ParticleSet``,
log-weights (``resampling``), random starts and Sigma (``particles``)."""
