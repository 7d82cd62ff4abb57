"""pybullet, imported without the line its C module prints on import ("pybullet build time: ..."), which would
otherwise open the output of every command, each worker process's included. Modules use
``from workbench.physics.bullet import pybullet``."""

from __future__ import annotations

import ctypes
import os
import sys


def _import_quietly():
    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        import pybullet
        # C's stdio may still hold the line (stdout to a file or pipe): flush it into /dev/null, not after.
        ctypes.CDLL(None).fflush(None)
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)
    return pybullet


pybullet = _import_quietly()
