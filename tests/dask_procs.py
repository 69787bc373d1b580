"""A dask scheduler and workers started with dask's own command line on 127.0.0.1, for the cluster tests
(the ``dask_cli`` fixture of conftest.py)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
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


def process_of(client, address: str, workers: list) -> subprocess.Popen:
    """The process of ``workers`` (started by :func:`start_worker`, each in its own session) that runs the
    dask worker at ``address``: the worker process is its nanny's child, in the nanny's process group."""
    pid = client.run(os.getpid, workers=[address])[address]
    group = os.getpgid(pid)
    for proc in workers:
        if proc.pid in (pid, group):
            return proc
    raise LookupError(f"no started worker process runs {address} (pid {pid}, group {group})")


@contextmanager
def cli_cluster(folder: Path, n_workers: int = 2, env: dict | None = None):
    """A scheduler and ``n_workers`` one-thread workers started with dask's command line on 127.0.0.1
    (``env``: the scheduler's extra environment); yields ``(address, worker processes)``; all stopped at
    the end."""
    import distributed

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    cmd = [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]
    with open(folder / "scheduler.log", "wb") as fh:
        sched = subprocess.Popen(
            cmd, env={**ENV, **(env or {})}, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True
        )
    workers = [start_worker(address, folder / f"worker{k}.log") for k in range(n_workers)]
    try:
        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(n_workers, timeout=90)
        yield address, workers
    finally:
        for p in (*workers, sched):
            stop(p)


@contextmanager
def fragile_cluster(folder: Path):
    """A scheduler that allows no failure of a task's worker (dask's ``allowed-failures`` 0) and one
    worker, on 127.0.0.1; yields ``(address, worker process)``; both stopped at the end."""
    with cli_cluster(folder, 1, {"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"}) as (address, workers):
        yield address, workers[0]


def wait_for(ready, proc: subprocess.Popen, what: str, timeout: float = 180.0) -> None:
    """Wait until ``ready()`` while ``proc`` runs (assertion errors naming ``what`` otherwise)."""
    t0 = time.monotonic()
    while not ready():
        assert proc.poll() is None, f"the command ended before {what}: {proc.communicate()}"
        assert time.monotonic() - t0 < timeout, f"{what}: not in {timeout} s"
        time.sleep(0.01)


def kill_worker_expect_one_line_error(proc: subprocess.Popen, worker: subprocess.Popen, starts) -> str:
    """SIGKILL ``worker`` (and its nanny) while the command ``proc`` runs; the command must end with exit
    2 and one stderr line that starts with one of ``starts`` and names ``--resume``. Returns that line."""
    try:
        os.killpg(worker.pid, signal.SIGKILL)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    lines = stderr.strip().splitlines()
    assert proc.returncode == 2, stderr
    assert len(lines) == 1 and lines[0].startswith(tuple(starts)) and "--resume" in lines[0], stderr
    return lines[0]
