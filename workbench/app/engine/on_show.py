"""What the engine's helpers (``labels``, ``sequence``) may read of the run on show: a read-only ``RunOnShow``,
made afresh by ``Engine.on_show`` each time it is asked for. The helpers never change the engine's fields: they
return what is to change, and the engine applies it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RunOnShow:
    """The engine's run as it is now: its ``frame`` (scene.Frame), ``problem`` and ``estimator`` (None before
    anything is loaded), the panel's ``config``, whether it is ``running`` and whether a Run stops on convergence
    (``stop_on_convergence``)."""

    frame: object
    problem: object
    estimator: object
    config: object
    running: bool
    stop_on_convergence: bool
