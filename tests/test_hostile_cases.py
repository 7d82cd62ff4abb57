"""CI's quick form of benchmarks/hostile_cases.py: every case that runs no real estimate (damaged inputs, outputs
that must not be written, counts beyond their bounds) is handled, and there are at least the 220 that issue 67
asks for. The cases that run a real estimate are `hostile_cases.py --slow-only`'s."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # ~260 commands, each a fresh process on a fresh copy of the demo: minutes

ROOT = Path(__file__).resolve().parent.parent


def test_every_quick_hostile_case_is_handled():
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "hostile_cases.py"), "--quick", "--jobs", "2"],
                         capture_output=True, text=True, cwd=ROOT, timeout=3600)
    bad = [line for line in run.stdout.splitlines() if " BAD " in line]
    summary = re.search(r"(\d+) of (\d+) handled", run.stdout)
    assert summary is not None, run.stdout[-2000:] + run.stderr[-2000:]
    handled, total = int(summary[1]), int(summary[2])
    assert run.returncode == 0 and handled == total and not bad, "\n".join(bad)
    assert total >= 220
