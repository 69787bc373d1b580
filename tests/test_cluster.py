"""Replays on a dask cluster (issue 22 item 1): a real scheduler and worker processes started with dask's
own command line on 127.0.0.1, against the local replay of the same file (computed in this process,
one batch of all columns: the independent reference), bit for bit; a worker killed mid-replay; a
client killed mid-replay and resumed without recomputing its finished chunks; a local cluster
(``--workers``); dask stays unimported without it and a missing ``distributed`` is one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from dask_procs import free_port as _free_port

from crater_thermal import api, cluster, io, runner, simulate, thermal
from crater_thermal.errors import ConfigError, OutputExistsError

from synthetic import make_run

distributed = pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
ENV = {**os.environ, "PYTHONPATH": str(REPO), "CRATER_THERMAL_QUIET": "1"}
GRID = "1300:1900:300"  # 6 profiles (every top <= bottom pair of 1300, 1600, 1900 kg m-3)
CHUNKS = ["--chunk-facets", "8", "--chunk-profiles", "2"]  # 64 facets x 6 profiles: 8 x 3 = 24 chunks
N_CHUNKS = 24


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A 64-facet, one-lunar-day run file and its local replay (the reference)."""
    d = tmp_path_factory.mktemp("cluster")
    make_run(lat_deg=-86.0, n_lunar_days=1.0, n_rings=4).isel(facet=slice(0, 64)).to_netcdf(d / "run.nc")
    runner.replay_file(d / "run.nc", [], density_grid=GRID, output=d / "local.nc", progress=False)
    with io.open_replay(d / "local.nc") as ref:
        ref.load()
    return d, ref


def _cli(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=180,
        **kw,
    )


def _popen_cli(*args) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for_chunks(folder: Path, proc: subprocess.Popen, n: int = 1, timeout: float = 120.0) -> None:
    """Wait until ``folder`` holds ``n`` saved chunks (while ``proc`` runs)."""
    t0 = time.monotonic()
    while len(list(folder.glob("chunk_*.npz"))) < n:
        assert proc.poll() is None, f"the replay ended before {n} chunk(s) were saved: {proc.communicate()}"
        assert time.monotonic() - t0 < timeout, "no chunk saved in time"
        time.sleep(0.01)


def _assert_equals_local(path: Path, ref) -> None:
    """The distributed replay equals the local one: every variable and coordinate; temperatures to
    <= 1e-9 K (both are float32 of the same float64 computation, so in practice bit for bit)."""
    with io.open_replay(path) as got:
        assert got["surface_temperature"].shape == ref["surface_temperature"].shape
        diff = np.abs(got["surface_temperature"].values.astype(float) - ref["surface_temperature"].values)
        assert diff.max() <= 1e-9, diff.max()
        for name in ref.variables:
            if name != "surface_temperature":
                assert got[name].equals(ref[name]), name
        assert list(got["profile"].values) == list(ref["profile"].values)


def test_dask_cli_cluster_equals_local_replay(case, dask_cli, tmp_path):
    d, ref = case
    address, _ = dask_cli
    out = tmp_path / "replay.nc"
    r = _cli("replay", d / "run.nc", "--density-grid", GRID, "-o", out, "--scheduler", address, *CHUNKS)
    assert r.returncode == 0, r.stderr
    assert f"chunks: {N_CHUNKS} (0 resumed, {N_CHUNKS} computed)" in r.stdout
    _assert_equals_local(out, ref)
    assert not cluster.chunk_folder(out).exists()  # assembled, then removed


def test_killed_worker_mid_replay_still_equals_local(case, dask_cli, tmp_path):
    d, ref = case
    address, workers = dask_cli
    out = tmp_path / "replay.nc"
    proc = _popen_cli("replay", d / "run.nc", "--density-grid", GRID, "-o", out, "--scheduler", address, *CHUNKS)
    try:
        _wait_for_chunks(cluster.chunk_folder(out), proc)
        os.killpg(workers[0].pid, signal.SIGKILL)  # the worker and its nanny, at once: a lost machine
        saved = len(list(cluster.chunk_folder(out).glob("chunk_*.npz")))
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert saved < N_CHUNKS, "the replay was finished before the worker was killed: the test proves nothing"
    assert proc.returncode == 0, stderr
    assert f"chunks: {N_CHUNKS} (0 resumed" in stdout
    _assert_equals_local(out, ref)


def test_killed_client_resumes_without_recomputing_finished_chunks(case, dask_cli, tmp_path):
    d, ref = case
    address, _ = dask_cli
    out = tmp_path / "replay.nc"
    folder = cluster.chunk_folder(out)
    args = ["replay", d / "run.nc", "--density-grid", GRID, "-o", out, "--scheduler", address, *CHUNKS]
    proc = _popen_cli(*args)
    try:
        _wait_for_chunks(folder, proc)
        proc.send_signal(signal.SIGKILL)  # no handler runs: as a lost login node or an OOM kill
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists()  # an interrupted replay never looks finished
    kept = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in folder.glob("chunk_*.npz")}
    assert 1 <= len(kept) < N_CHUNKS

    # without --resume the unfinished replay is refused (one line, exit 2) and left as it was
    r = _cli(*args)
    lines = r.stderr.strip().splitlines()  # (first: the stale lock of the killed client taken over)
    assert r.returncode == 2 and lines[-1].startswith("error:") and "--resume" in lines[-1], r.stderr
    assert len(lines) == 1 or (len(lines) == 2 and "stale lock" in lines[0]), r.stderr
    assert {p.name for p in folder.glob("chunk_*.npz")} == set(kept)
    # another chunking is another replay: refused too (before any connection)
    with pytest.raises(ConfigError, match="different replay"):
        cluster.replay_file(
            d / "run.nc", [], density_grid=GRID, output=out, scheduler=address, chunk_facets=16, resume=True
        )

    # resume: watch the kept chunk files while it runs; none may be rewritten
    changed = []
    done = threading.Event()

    def watch():
        while not done.is_set():
            for name, stamp in kept.items():
                try:
                    st = (folder / name).stat()
                except FileNotFoundError:  # the folder is removed after the assembly
                    continue
                if (st.st_ino, st.st_mtime_ns) != stamp:
                    changed.append(name)
            time.sleep(0.005)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        r = _cli(*args, "--resume")
    finally:
        done.set()
        watcher.join()
    assert r.returncode == 0, r.stderr
    assert not changed, f"finished chunks recomputed: {sorted(set(changed))}"
    assert f"chunks: {N_CHUNKS} ({len(kept)} resumed, {N_CHUNKS - len(kept)} computed)" in r.stdout
    _assert_equals_local(out, ref)
    assert not folder.exists()


def test_local_cluster_workers_equals_local_replay(case, tmp_path):
    d, ref = case
    out = tmp_path / "replay.nc"
    ds = api.replay(d / "run.nc", density_grid=GRID, out=out, workers=2, chunk_facets=32, chunk_profiles=3)
    assert int(ds.attrs["replay_chunks"]) == 4 and int(ds.attrs["replay_chunks_resumed"]) == 0
    ds.close()
    _assert_equals_local(out, ref)


def test_interrupted_local_cluster_keeps_its_chunks(case, tmp_path):
    """Ctrl-C on a --workers replay: exit 130, one line saying how to resume, the finished chunks kept,
    no output."""
    d, _ = case
    out = tmp_path / "replay.nc"
    proc = _popen_cli("replay", d / "run.nc", "--density-grid", GRID, "-o", out, "--workers", "2", *CHUNKS)
    try:
        _wait_for_chunks(cluster.chunk_folder(out), proc)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("error: interrupted (SIGINT)") and "--resume" in last, stderr
    assert not out.exists() and any(cluster.chunk_folder(out).glob("chunk_*.npz"))


def test_columns_do_not_depend_on_their_batch(case):
    """Each column's periodic start converges on its own: a profile replayed alone, or a facet range
    alone, gives the same float32 temperatures as inside the batch of every column."""
    d, ref = case
    profiles = list(thermal.density_grid_profiles(GRID))
    with io.read_flux_dataset(d / "run.nc", load=False) as ds:
        T1, _ = simulate.replay_fluxes(ds, profiles[2:3])
        T2, _ = simulate.replay_fluxes(ds.isel(facet=slice(5, 12)), profiles[4:6], chunk_mb=0.01)
    assert np.array_equal(T1[0], ref["surface_temperature"].values[2])
    assert np.array_equal(T2, ref["surface_temperature"].values[4:6, :, 5:12])


def test_bad_cluster_options_are_one_line_errors(case, tmp_path, monkeypatch):
    d, _ = case
    out = tmp_path / "replay.nc"
    with pytest.raises(ConfigError, match="chunk"):
        api.replay(d / "run.nc", density_grid=GRID, out=out, workers=2, chunk_facets=0)
    with pytest.raises(ConfigError, match="give one"):
        api.replay(d / "run.nc", out=out, workers=2, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(ConfigError, match="--resume continues"):
        api.replay(d / "run.nc", out=out, resume=True)
    with pytest.raises(ConfigError, match="--workers 0"):
        api.replay(d / "run.nc", out=out, workers=0)
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    with pytest.raises(ConfigError, match="cannot reach a dask scheduler") as err:
        api.replay(d / "run.nc", density_grid=GRID, out=out, scheduler=address)
    assert "\n" not in str(err.value)
    assert not out.exists() and not cluster.chunk_folder(out).exists()  # nothing finished: nothing kept
    # an unfinished chunk folder is refused without --resume, discarded with --overwrite
    cluster.chunk_folder(out).mkdir()
    with pytest.raises(OutputExistsError, match="--resume"):
        api.replay(d / "run.nc", density_grid=GRID, out=out, scheduler=address)


def test_local_replay_imports_no_dask(case, tmp_path):
    """No crater_thermal module imports dask or distributed on a local replay (xarray itself does when
    they are installed: its chunked-array checks and to_netcdf's scheduler lookup), and a local replay
    works with both missing."""
    d, _ = case
    run = ["replay", str(d / "run.nc"), "--profile", "rock", "-o"]
    code = (
        "import builtins, sys\n"
        "seen = []\n"
        "real = builtins.__import__\n"
        "def spy(name, globals=None, *a, **k):\n"
        "    if name.split('.')[0] in ('dask', 'distributed'):\n"
        "        seen.append((globals or {}).get('__name__', '?'))\n"
        "    return real(name, globals, *a, **k)\n"
        "builtins.__import__ = spy\n"
        "from crater_thermal.cli import main\n"
        "try:\n"
        f"    main({run + [str(tmp_path / 'a.nc')]!r})\n"
        "except SystemExit as e:\n"
        "    assert not e.code, e.code\n"
        "print(sorted({m for m in seen if m.split('.')[0] == 'crater_thermal'}))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"
    assert (tmp_path / "a.nc").exists()
    code = (
        "import sys; sys.modules['dask'] = sys.modules['distributed'] = None\n"  # neither installed
        "from crater_thermal.cli import main\n"
        f"main({run + [str(tmp_path / 'b.nc')]!r})\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 0, r.stderr
    with io.open_replay(tmp_path / "a.nc") as a, io.open_replay(tmp_path / "b.nc") as b:
        assert np.array_equal(a["surface_temperature"].values, b["surface_temperature"].values)


@pytest.mark.parametrize("where", [["--scheduler", "tcp://127.0.0.1:8786"], ["--workers", "2"]])
def test_missing_distributed_is_one_line(case, tmp_path, where):
    d, _ = case
    out = tmp_path / "r.nc"
    code = (
        "import sys; sys.modules['distributed'] = None\n"  # as if the extra were not installed
        "from crater_thermal.cli import main\n"
        f"main(['replay', {str(d / 'run.nc')!r}, '--profile', 'rock', '-o', {str(out)!r}, *{where!r}])\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error:") and r.stderr.count("\n") == 1, r.stderr
    assert "pip install 'crater_thermal[distributed]'" in r.stderr
    assert not out.exists() and not cluster.chunk_folder(out).exists()


def test_accumulators_do_not_depend_on_call_boundaries(case):
    """A series run in one call or cut into three calls (as a replay's time blocks are, whose size
    depends on the batch) leaves the same state and the same accumulators (the periodic start's
    Jacobian uses them) bit for bit."""
    d, _ = case
    with io.read_flux_dataset(d / "run.nc") as ds:
        t = simulate.seconds_since(ds["time"].values, ds["time"].values[0])
        a = simulate.absorbed_solar_of(ds) + float(ds.attrs["emissivity"]) * ds["ir_incident"].values
    profiles = list(thermal.density_grid_profiles(GRID))[:2]
    solvers = [thermal.ColumnSolver([p for p in profiles for _ in range(a.shape[1])]) for _ in range(2)]
    for s in solvers:
        s.set_equilibrium(a)
    solvers[0].run_series(t, a, record=False)
    for k0, k1 in ((0, 40), (39, 101), (100, len(t))):  # consecutive calls share their end sample
        solvers[1].run_series(t[k0:k1], a[k0:k1], record=False)
    assert np.array_equal(solvers[0].state(), solvers[1].state())
    assert np.array_equal(solvers[0].acc, solvers[1].acc)


def test_worker_deaths_beyond_dask_allowance_are_one_line(case, tmp_path):
    """A task whose workers keep dying (dask's KilledWorker: here a scheduler that allows no failure, and
    the only worker SIGKILLed while it runs a chunk) stops the replay with one line naming the cause and
    --resume, exit 2; the finished chunks are kept for the resume."""
    import dask_procs

    d, _ = case
    out = tmp_path / "replay.nc"
    proc = None
    try:
        with dask_procs.fragile_cluster(tmp_path) as (address, worker):
            args = ("replay", d / "run.nc", "--density-grid", GRID, "-o", out, "--scheduler", address, *CHUNKS)
            proc = _popen_cli(*args)
            _wait_for_chunks(cluster.chunk_folder(out), proc)
            # mid-chunk: the worker always has the next chunk running
            dask_procs.kill_worker_expect_one_line_error(proc, worker, ("error: dask gave up",))
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
    assert not out.exists() and any(cluster.chunk_folder(out).glob("chunk_*.npz"))


def test_chunk_tasks_read_their_facets_without_checking_the_whole_file_again(case, tmp_path, monkeypatch):
    """A replay's task with the command's stamp of the flux file opens it without a second check of every
    value (which read the whole file in every task: ~7 s a task at 20k facets against ~1.3 s for its own
    2,000 facets), gives the same temperatures as a task that checks the file itself (independent: the
    local replay's reference), and refuses a file that changed after the stamp, in one line."""
    import shutil

    d, ref = case
    run = tmp_path / "run.nc"
    shutil.copy(d / "run.nc", run)
    stamp = io.file_stamp(run)
    profiles = runner.resolve_profiles([], GRID, False)[:2]

    def no_value_checks(*a, **k):
        raise AssertionError("the task read the flux values to check them again")

    with monkeypatch.context() as m:
        m.setattr(io, "_blocks", no_value_checks)
        T, _ = cluster.solve_chunk(str(run), profiles, 8, 24, {}, stamp)
    np.testing.assert_array_equal(T, ref["surface_temperature"].values[:2, :, 8:24])
    with pytest.raises(AssertionError, match="check them again"):  # the check without a stamp reads them
        with monkeypatch.context() as m:
            m.setattr(io, "_blocks", no_value_checks)
            cluster.solve_chunk(str(run), profiles, 8, 24, {})

    os.utime(run, ns=(stamp[1] + 10**9, stamp[1] + 10**9))  # touched after the command checked it
    with pytest.raises(io.FluxFileError, match="changed after the replay checked it") as err:
        cluster.solve_chunk(str(run), profiles, 8, 24, {}, stamp)
    assert "\n" not in str(err.value)
    run.unlink()
    with pytest.raises(io.FluxFileError, match="not readable here"):
        cluster.solve_chunk(str(run), profiles, 8, 24, {}, stamp)


def test_session_workers_reuse_their_heap_and_get_the_defaults_back(dask_cli):
    """While a session's client is open, its workers take a large array from their heap (glibc's own
    accounting, ``mallinfo2``: no bytes in new memory maps), as a local run does; once the session is closed,
    a remote scheduler's workers map such an array again (glibc's default, the setting they had)."""
    from crater_thermal import heap

    if heap._glibc() is None:
        pytest.skip("glibc's mallopt is not available here")

    import cloudpickle
    import heap_probe

    address, _ = dask_cli
    n = 64 << 20
    cloudpickle.register_pickle_by_value(heap_probe)  # the workers cannot import the tests' folder
    try:
        client, cl = cluster.connect(address)
        try:
            inside = client.run(heap_probe.mapped_while_held, n)
        finally:
            cluster.disconnect(client, cl)
        with distributed.Client(address, timeout=60) as c:
            after = c.run(heap_probe.mapped_while_held, n)
    finally:
        cloudpickle.unregister_pickle_by_value(heap_probe)
    if None in inside.values():
        pytest.skip("not glibc >= 2.33 (no mallinfo2)")
    # (an earlier test of this module may have killed one of the two workers)
    assert inside and all(v == 0 for v in inside.values()), inside
    assert after and all(v >= n for v in after.values()), after


def _worker_settings():
    import dask

    return {k: dask.config.get(k) for k in cluster.LOCAL_CLUSTER_CONFIG}


def test_local_cluster_quiets_dask_housekeeping_and_keeps_the_callers_config():
    """A local cluster's workers run with :data:`cluster.LOCAL_CLUSTER_CONFIG` (their profiler off, the
    monitors less often: read by each worker process as it started), and the caller's dask settings are
    what they were before and after."""
    import dask

    assert cluster.LOCAL_CLUSTER_CONFIG["distributed.worker.profile.enabled"] is False
    before = {k: dask.config.get(k) for k in cluster.LOCAL_CLUSTER_CONFIG}
    assert before != cluster.LOCAL_CLUSTER_CONFIG  # the test would prove nothing with dask's defaults equal
    client, cl = cluster.connect(None, 2)
    try:
        seen = client.run(_worker_settings)
        assert {k: dask.config.get(k) for k in cluster.LOCAL_CLUSTER_CONFIG} == before
    finally:
        cluster.disconnect(client, cl)
    assert len(seen) == 2 and all(v == cluster.LOCAL_CLUSTER_CONFIG for v in seen.values()), seen
