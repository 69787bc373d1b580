"""Sweeps: local processes, restart skips finished cases, and a dask.distributed LocalCluster."""

import concurrent.futures
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crater_thermal import io, sweep
from crater_thermal.errors import ConfigError, MissingExtraError

REPO = Path(__file__).resolve().parents[1]

CASE = """
name = "{name}"
[crater]
kind = "flat"
[location]
lat_deg = {lat}
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "2019-01-20"
spinup = "fixed"
spinup_days = 5.0
initial_temperature_K = 150.0
[steps]
flux_step_hours = 6.0
[replay]
profiles = ["rock"]
"""


def _cases(tmp_path, lats=(-60.0, -80.0)):
    paths = []
    for lat in lats:
        p = tmp_path / f"flat_{abs(int(lat))}.toml"
        p.write_text(CASE.format(name=p.stem, lat=lat))
        paths.append(p)
    return paths


def test_local_sweep_and_restart_skips_finished(tmp_path):
    paths = _cases(tmp_path)
    out = tmp_path / "out"
    res = sweep.sweep(paths, out, workers=2, progress=False)
    assert [r["done"] for r in res] == [["run", "replay"], ["run", "replay"]]
    for p in paths:
        run_nc, replay_nc = sweep.case_outputs(p, out)
        ds = io.open_run(run_nc)
        rep = io.open_replay(replay_nc)
        assert list(rep["profile"].values) == ["rock"]
        assert np.all(np.isfinite(rep["surface_temperature"].values))
        assert ds.attrs["lat_deg"] == float(p.stem.split("_")[1]) * -1
    # the equator-ward case is warmer on average than the pole-ward one
    t60 = io.open_run(sweep.case_outputs(paths[0], out)[0])["surface_temperature"].values.mean()
    t80 = io.open_run(sweep.case_outputs(paths[1], out)[0])["surface_temperature"].values.mean()
    assert t60 > t80
    # interrupted sweep: one case lost its replay; a restart redoes only that
    sweep.case_outputs(paths[1], out)[1].unlink()
    stamp = sweep.case_outputs(paths[0], out)[0].stat().st_mtime_ns
    res = sweep.sweep(paths, out, workers=1, progress=False)
    assert res[0]["skipped"] and res[1]["done"] == ["replay"]
    assert sweep.case_outputs(paths[0], out)[0].stat().st_mtime_ns == stamp


def test_sweep_on_dask_local_cluster(tmp_path):
    distributed = pytest.importorskip("distributed")
    paths = _cases(tmp_path, lats=(-70.0,))
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        res = sweep.sweep(paths, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False)
    assert res[0]["done"] == ["run", "replay"]
    assert sweep.case_outputs(paths[0], tmp_path / "out")[0].exists()


def test_sweep_rejects_bad_case_before_any_work(tmp_path):
    paths = _cases(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text(CASE.format(name="bad", lat=-100.0))
    with pytest.raises(ConfigError, match="lat_deg"):
        sweep.sweep(paths + [bad], tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line_config_error(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr(sweep, "SCHEDULER_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    with pytest.raises(ConfigError, match="cannot reach a dask scheduler") as err:
        sweep.sweep(_cases(tmp_path, lats=(-70.0,)), tmp_path / "out", scheduler=address, progress=False)
    assert address in str(err.value) and "\n" not in str(err.value)


def test_cli_unreachable_scheduler_exit_2(tmp_path):
    pytest.importorskip("distributed")
    address = f"tcp://127.0.0.1:{_free_port()}"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "crater_thermal",
            "sweep",
            *map(str, _cases(tmp_path, lats=(-70.0,))),
            "-o",
            str(tmp_path / "out"),
            "--scheduler",
            address,
        ],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error:") and r.stderr.strip().count("\n") == 0 and address in r.stderr


def test_scheduler_without_dask_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask.distributed were not installed
    with pytest.raises(MissingExtraError, match=r"pip install 'crater_thermal\[distributed\]'"):
        sweep.sweep(_cases(tmp_path, lats=(-70.0,)), tmp_path / "out", scheduler="tcp://127.0.0.1:8786", progress=False)


def test_local_workers_are_spawned(tmp_path, monkeypatch):
    """GNU OpenMP (numba's threading layer) is not fork-safe: workers must start with 'spawn'."""
    seen = {}

    class Recorder:  # stands in for ProcessPoolExecutor; runs the jobs inline
        def __init__(self, max_workers, mp_context):
            seen["method"] = mp_context.get_start_method()

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args):
            fut = concurrent.futures.Future()
            fut.set_result({"case": args[0], "skipped": True, "done": []})
            return fut

    monkeypatch.setattr(sweep, "ProcessPoolExecutor", Recorder)
    res = sweep.sweep(_cases(tmp_path), tmp_path / "out", workers=2, progress=False)
    assert seen["method"] == "spawn" and len(res) == 2
