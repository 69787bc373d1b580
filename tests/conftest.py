import atexit
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import dask_procs
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
# A cache of view factors and horizon maps of this test session only (CLI subprocesses inherit it): the
# tests never read maps another checkout or code version wrote into the user's ~/.cache, nor fill it.
if "CRATER_THERMAL_CACHE" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="crater_thermal_tests_")
    os.environ["CRATER_THERMAL_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

REPO = Path(__file__).resolve().parents[1]
SHARED_EPHEMERIS = REPO.parent / "shared" / "ephemeris"


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="module")
def dask_cli(tmp_path_factory):
    """(module scope) A scheduler and two workers started with dask's command line on 127.0.0.1 (killed at teardown)."""
    d = tmp_path_factory.mktemp("dask")
    port = dask_procs.free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = []
    try:
        with open(d / "scheduler.log", "wb") as fh:
            cmd = [
                str(dask_procs.BIN / "dask"),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--no-dashboard",
            ]
            procs.append(
                subprocess.Popen(cmd, env=dask_procs.ENV, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
            )
        workers = [dask_procs.start_worker(address, d / f"worker{k}.log") for k in range(2)]
        procs += workers
        import distributed

        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=90)
        yield address, workers
    finally:
        for p in reversed(procs):
            dask_procs.stop(p)
