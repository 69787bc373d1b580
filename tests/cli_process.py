"""The command line run as the user runs it: ``python -m crater_thermal ...`` in a subprocess, for tests."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def cli(*args, timeout=600):
    """Run ``crater-thermal ARGS`` quietly (no progress lines) from this checkout; the CompletedProcess."""
    env = dict(os.environ, PYTHONPATH=str(REPO), CRATER_THERMAL_QUIET="1")
    return subprocess.run(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
