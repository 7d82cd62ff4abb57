"""workbench: physically plausible scene estimation (PI-PF / PI-MCPF) from one depth image."""

__version__ = "0.1.0"
