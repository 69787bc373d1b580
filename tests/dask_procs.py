"""A dask scheduler and workers started with dask's own command line on 127.0.0.1, for the cluster tests
(the ``dask_cli`` fixture of conftest.py)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
ENV = {**os.environ, "PYTHONPATH": str(REPO), "CRATER_THERMAL_QUIET": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM the process group of a process started in its own session, then SIGKILL."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=10)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait(timeout=10)


def start_worker(address: str, log: Path) -> subprocess.Popen:
    cmd = [str(BIN / "dask"), "worker", address, "--nworkers", "1", "--nthreads", "1"]
    cmd += ["--host", "127.0.0.1", "--no-dashboard"]
    with open(log, "wb") as fh:
        return subprocess.Popen(cmd, env=ENV, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
