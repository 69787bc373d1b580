"""The coupled run by waveform relaxation (``[steps] ir_coupling = "relaxed"``) and on a dask cluster
(issue 22 item 2).

References: the fully implicit exchange of ``test_simulate`` (the IR at every step's end iterated to its
fixed point, step by step: a separate implementation of the coupling the relaxation converges to), an
exact view-factor matrix built here for the saved IR, the whole operator's product for its row blocks,
and the single-process relaxed run for the distributed one (a real scheduler and two worker processes
started with dask's own command line on 127.0.0.1)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
from test_simulate import _implicit_run, small_case

from crater_thermal import api, cluster_run, config, io, radiosity, runner, simulate, thermal, vfoperator, waveform
from crater_thermal import viewfactors as vf
from crater_thermal.errors import ConfigError

distributed = pytest.importorskip("distributed")

import dask_procs  # noqa: E402
from test_cluster import _cli, _popen_cli  # noqa: E402

# the relaxation's stopping rule: no surface temperature changes by more than 1e-3 K between iterations
# (waveform.DEFAULT_TOL_K); each iteration shrinks an error by a factor q <= 0.3 on crater terrain, so the
# error left per window is <= 1e-3 q / (1 - q) < 5e-4 K, and windows pass it on through a decaying state:
# 0.005 K bounds the difference to the implicit reference with a margin of 10.
IMPLICIT_TOL_K = 0.005
# the bound for a distributed run against the single-process run
DISTRIBUTED_TOL_K = 0.01


def _case_file(tmp: Path, name: str, *, end="2019-02-15", every=0, compressed=True) -> Path:
    """A 300-facet 2 km crater at 85 S, one lunation of periodic spin-up, the relaxed scheme (the
    compressed operator, so that its row blocks are what the workers hold)."""
    path = small_case(tmp, name=name, facets=300, end=end, spinup_days=29.53, tol=0.001, every=every)
    text = path.read_text().replace("flux_step_hours = 4.0", 'flux_step_hours = 4.0\nir_coupling = "relaxed"')
    if compressed:
        text += '[radiation]\nview_factors = "compressed"\n'
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """The single-process relaxed run (the reference of the distributed ones)."""
    tmp = tmp_path_factory.mktemp("relaxed")
    path = _case_file(tmp, "relaxed")
    out = runner.run_case(config.load_case(path), tmp / "local.nc", progress=False)
    with io.open_run(out) as ds:
        ds.load()
    return tmp, path, ds


def test_relaxation_matches_the_implicit_exchange(tmp_path):
    """Windows of 6, 24 and 96 samples relaxed to 1e-3 K against the step-by-step implicit reference over
    20 days of a 300-facet crater (sunrise and sunset on its walls every day); the default extrapolated
    scheme differs from both by up to 0.26 K at sunrise (docs/model.md), the relaxation by < 0.005 K."""
    case = config.load_case(small_case(tmp_path, facets=300, end="2019-01-21", spinup="fixed", spinup_days=0.0))
    fc = simulate.compute_forcing(case, simulate.Timer())
    _, solar = fc.split(fc.solar)
    t = simulate.seconds_since(fc.times, fc.times[0])
    nf = fc.mesh.n_facets
    solver = thermal.ColumnSolver(["1300/1800"] * nf)
    solver.set_equilibrium(solar)
    x0 = solver.state()
    stepper = radiosity.CoupledStepper(solver, fc.F, 0.12, 0.98, ir_scheme="predictor")
    ref = _implicit_run(stepper, t, solar)
    cols = waveform.LocalColumns(thermal.ColumnSolver(["1300/1800"] * nf), fc.F, 0.12, 0.98)
    for W in (6, 24, 96):
        state, ir, rows, its = x0, None, [x0[:, 0][None]], []
        for w0 in range(0, len(t) - 1, W):
            w1 = min(len(t) - 1, w0 + W)
            win, it, change = waveform.relax(cols, state, t[w0 : w1 + 1], solar[w0 : w1 + 1], ir, 0.98)
            assert change <= waveform.DEFAULT_TOL_K
            rows.append(win.T[1:])
            state, ir, its = win.end, win.ir[-1], its + [it]
        err = np.abs(np.concatenate(rows) - ref)
        assert err.max() <= IMPLICIT_TOL_K, (W, err.max())
        assert max(its) <= 10, its  # measured: 5-8 (docs/cluster.md)


class _CountingClient:
    """A dask client that records what each ``gather`` brings back to this process (element counts)."""

    def __init__(self, client):
        self._client, self.gathered = client, []

    def __getattr__(self, name):
        return getattr(self._client, name)

    def gather(self, futures, *args, **kwargs):
        out = self._client.gather(futures, *args, **kwargs)
        sizes = [sum(np.size(x) for x in (r if isinstance(r, tuple) else (r,))) for r in out]
        self.gathered.append(sum(sizes))
        return out


def test_sunlight_goes_to_the_workers_in_float32_only_where_that_is_exact():
    """``_compact``: rows that float32 holds exactly (a store's sunlight) are sent in float32, any other in
    float64, unchanged; a window's first emission goes as one row that the task makes into the window's."""
    exact = np.array([[0.0, 1361.0, 0.5], [2.0**-20, 3.0, 1e3]])
    sent = cluster_run._compact(exact)
    assert sent.dtype == np.float32 and np.array_equal(sent.astype(float), exact)
    inexact = exact + np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.0]])  # 0.6 is not a float32
    sent = cluster_run._compact(inexact)
    assert sent.dtype == np.float64 and np.array_equal(sent, inexact)
    row = np.array([1.0, 2.5, 3.0], np.float32)
    whole = cluster_run._Broadcast(row, 4).array()
    assert whole.shape == (4, 3) and whole.dtype == np.float32 and whole.flags.c_contiguous
    assert np.array_equal(whole, np.tile(row, (4, 1)))


def test_the_latest_pass_ir_is_gathered_from_only_the_blocks_and_rows_asked():
    """``DaskColumns.pass_ir(k0, k1)``: the IR rows of a spin-up pass kept on the workers as blocks of chunk
    windows (consecutive blocks share a sample, owned by the later one) equal the series they were cut
    from for every range, and each call brings back only the rows asked (before, every call gathered
    every block up to ``k1`` whole: the spin-up's saved IR cost blocks^2 / 2 block gathers)."""
    rng = np.random.default_rng(5)
    n, nf = 13, 7
    series = rng.uniform(0.0, 50.0, (n, nf))  # the pass's IR [W m-2]
    chunks = [np.array([0, 3, 5]), np.array([1, 2]), np.array([4, 6])]  # not contiguous facets
    blocks = [(0, 5), (5, 10), (10, 12)]  # samples b0..b1, the last shared with the next block
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False) as cl:
        with distributed.Client(cl) as raw:
            client = _CountingClient(raw)
            remote = cluster_run.DaskColumns(client, chunks, [None] * 3, {}, nf, 2)
            remote._pass = {
                b0: [
                    raw.scatter(waveform.Window(series[b0 : b1 + 1, idx], series[b0 : b1 + 1, idx], None, None))
                    for idx in chunks
                ]
                for b0, b1 in blocks
            }
            for k0 in range(n):
                for k1 in range(k0 + 1, n + 1):
                    client.gathered.clear()
                    got = remote.pass_ir(k0, k1)
                    np.testing.assert_array_equal(got, series[k0:k1].astype(io.RUN_SERIES_DTYPE))
                    assert sum(client.gathered) == (k1 - k0) * nf, (k0, k1, client.gathered)


def test_a_window_relaxed_on_the_workers_equals_the_local_relaxation(tmp_path, monkeypatch):
    """Two windows (48 and 24 samples, a sunrise on the walls in each) of a 300-facet crater relaxed by the
    columns of this process and by a cluster's (two one-thread workers in this process, so that the
    patched product type holds there too, and two tasks run at once in one process as on a worker of
    several threads; three chunks holding their rows of the exact matrix): the same iterations, the same
    temperatures, IR and end state to the products' round-off (both pinned to float64), and per
    iteration one number per chunk comes back to the client; the temperatures come back once, with the
    converged window."""
    monkeypatch.setattr(vfoperator, "PRODUCT_DTYPE", np.float64)
    case = config.load_case(small_case(tmp_path, facets=300, end="2019-01-13", spinup="fixed", spinup_days=0.0))
    fc = simulate.compute_forcing(case, simulate.Timer())
    _, solar = fc.split(fc.solar)
    solar = solar.astype(np.float32).astype(float)  # as a run's store gives it: sent to the workers in float32
    t = simulate.seconds_since(fc.times, fc.times[0])
    assert len(t) > 72
    nf = fc.mesh.n_facets
    settings = runner.column_settings(case)
    solver = runner.column_solver("1300/1800", nf, settings)
    solver.set_equilibrium(solar)
    x0 = solver.state()
    local = waveform.LocalColumns(runner.column_solver("1300/1800", nf, settings), fc.F, 0.12, 0.98)
    folder = tmp_path / "operator"
    vfoperator.save_operator(fc.F, folder)
    order = vfoperator.row_order(fc.F)
    bounds = [(0, 100), (100, 200), (200, nf)]
    options = {
        "profile": "1300/1800",
        **settings,
        "albedo": 0.12,
        "solar_is_absorbed": False,
    }
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False) as cl:
        with distributed.Client(cl) as raw:
            client = _CountingClient(raw)
            rows = [raw.submit(cluster_run.load_rows, str(folder), a, b) for a, b in bounds]
            chunks = [order[a:b] for a, b in bounds]
            remote = cluster_run.DaskColumns(client, chunks, rows, options, nf, 2)
            state_l = state_r = x0
            ir_l = ir_r = None
            for w0, w1 in ((0, 48), (48, 72)):
                got_l = waveform.relax(local, state_l, t[w0 : w1 + 1], solar[w0 : w1 + 1], ir_l, 0.98)
                client.gathered.clear()
                got_r = waveform.relax(remote, state_r, t[w0 : w1 + 1], solar[w0 : w1 + 1], ir_r, 0.98)
                (wl, it_l, ch_l), (wr, it_r, ch_r) = got_l, got_r
                # iterations 2..n: one change per chunk each; then the converged window's temperatures
                assert client.gathered[:-1] == [len(chunks)] * (it_r - 1)
                assert client.gathered[-1] >= (w1 - w0 + 1) * nf
                assert it_r == it_l >= 2 and abs(ch_r - ch_l) <= 1e-9
                np.testing.assert_allclose(wr.T, wl.T, rtol=0, atol=1e-9)
                np.testing.assert_allclose(wr.ir, wl.ir, rtol=0, atol=1e-9)
                np.testing.assert_allclose(wr.end, wl.end, rtol=0, atol=1e-9)
                state_l, ir_l, state_r, ir_r = wl.end, wl.ir[-1], wr.end, wr.ir[-1]


def test_relaxed_run_saves_the_exchange_of_its_temperatures(local_run):
    """A relaxed run's saved IR is F e(T) of its saved temperatures (exact matrix built here, not the
    run's compressed operator) at every sample, to what the 1e-3 K stopping rule leaves: the IR changes by
    <= 4 eps sigma T^3 x 1e-3 K x rowsum <= 0.02 W m-2 at the hottest (~390 K) facets, plus the
    compressed operator's own error (tolerance 1e-3 of the IR, ~0.01 W m-2 on sunlit walls)."""
    _, path, ds = local_run
    case = config.load_case(path)
    mesh = simulate.case_mesh(case)
    F = vf.view_factor_matrix(mesh)
    T = ds["surface_temperature"].values.astype(float)
    exact = np.asarray(F @ radiosity.emitted(T, 0.98).T).T
    assert np.abs(ds["ir_incident"].values - exact).max() <= 0.05
    rel = ds.attrs["relaxation"]
    rel = rel if isinstance(rel, dict) else __import__("json").loads(rel)
    assert rel["columns"] == "this process" and ds.attrs["ir_coupling"] == "relaxed"
    assert 1 <= min(rel["record_iterations_per_window"]) and max(rel["record_iterations_per_window"]) <= 10


def test_row_blocks_equal_the_whole_operator(tmp_path, monkeypatch):
    """Each worker's rows of the exact and the compressed operator (saved, then loaded row block by row
    block from the files) give the whole operator's product on those rows, to round-off (both pinned to
    float64 arithmetic here; their float32 products are checked against float64 in tests/test_vfoperator.py)."""
    monkeypatch.setattr(vfoperator, "PRODUCT_DTYPE", np.float64)
    mesh = simulate.case_mesh(config.load_case(small_case(tmp_path, facets=1500)))
    X = np.random.default_rng(1).random((mesh.n_facets, 3)) * 400.0
    for method in ("exact", "compressed"):
        F = vfoperator.view_factor_operator(mesh, method=method)
        vfoperator.save_operator(F, tmp_path / method)
        ref = F @ X
        seen = []
        for a in range(0, mesh.n_facets, 400):
            block = vfoperator.load_row_block(tmp_path / method, a, min(mesh.n_facets, a + 400))
            np.testing.assert_allclose(block.apply(X), ref[block.facets], rtol=1e-12, atol=1e-12 * np.abs(ref).max())
            seen.append(block.facets)
        assert np.array_equal(np.sort(np.concatenate(seen)), np.arange(mesh.n_facets))  # every row once
    with pytest.raises(ConfigError, match="outside"):
        vfoperator.load_row_block(tmp_path / "exact", 0, mesh.n_facets + 1)


def _spy(cls, made: list):
    """A subclass of ``cls`` whose instances are appended to ``made``."""

    class Spy(cls):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    return Spy


def _assert_close_to_local(path, ref, tol=DISTRIBUTED_TOL_K) -> dict:
    with io.open_run(path) as got:
        d = np.abs(got["surface_temperature"].values.astype(float) - ref["surface_temperature"].values)
        assert d.max() <= tol, d.max()
        assert np.abs(got["ir_incident"].values - ref["ir_incident"].values).max() <= 0.05
        rel = got.attrs["relaxation"]
        return rel if isinstance(rel, dict) else __import__("json").loads(rel)


def test_dask_cli_cluster_run_equals_single_process(local_run, dask_cli, tmp_path):
    tmp, path, ref = local_run
    address, _ = dask_cli
    out = tmp_path / "run.nc"
    r = _cli("run", path, "-o", out, "--scheduler", address)
    assert r.returncode == 0, r.stderr
    rel = _assert_close_to_local(out, ref)
    assert rel["columns"].startswith("dask: 2 chunks on 2 worker(s)")  # the default: one chunk per worker
    assert "operator rows built by the workers" in rel["columns"]
    assert not Path(str(out) + ".partial").exists()


def test_killed_client_resumes_from_its_checkpoint(local_run, dask_cli, tmp_path):
    """SIGKILL the client mid-record (no handler runs); ``--resume`` continues from the last checkpoint:
    the windows before it are not computed again (counted) and the result equals the single-process run."""
    tmp, _, ref = local_run
    address, _ = dask_cli
    path = _case_file(tmp_path, "ckpt", every=24)  # a checkpoint at every window's end (96 samples)
    out = tmp_path / "run.nc"
    ckpt = Path(runner.checkpoint_path(out))
    proc = _popen_cli("run", path, "-o", out, "--scheduler", address, "--chunk-facets", "100")
    try:
        dask_procs.wait_for(lambda: ckpt.exists() and int(np.load(ckpt)["k"]) > 0, proc, "a record checkpoint")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists()
    k = int(np.load(ckpt)["k"])
    r = _cli("run", path, "-o", out, "--scheduler", address, "--chunk-facets", "100", "--resume")
    assert r.returncode == 0, r.stderr
    rel = _assert_close_to_local(out, ref)
    W = rel["window_samples"]
    n_windows = -(-(ref.sizes["time"] - 1) // W)
    assert len(rel["record_iterations_per_window"]) == n_windows - k // W < n_windows
    assert not ckpt.exists()


def test_resume_with_another_coupling_is_refused(tmp_path):
    """A run started on a cluster (relaxed, whatever the case says) and resumed without one (the case's
    extrapolated scheme) is refused: the record would mix two couplings under one attribute. The cluster
    is stood in for by a backend of this process through the same ``columns`` hook."""
    path = _case_file(tmp_path, "mix", every=24)
    path.write_text(path.read_text().replace('ir_coupling = "relaxed"', 'ir_coupling = "extrapolated"'))
    case = config.load_case(path)
    out = tmp_path / "run.nc"
    ckpt = Path(runner.checkpoint_path(out))

    class Here:
        def columns(self, fc):
            solver = thermal.ColumnSolver([case.surface.nominal_profile] * fc.mesh.n_facets, emissivity=0.98)
            return waveform.LocalColumns(solver, fc.F, 0.12, 0.98)

    @contextlib.contextmanager
    def here(case, mesh, store):
        yield Here()

    class Stop(Exception):
        pass

    def stop_once_recording(done, total):
        if ckpt.exists():
            raise Stop

    with pytest.raises(Stop):
        runner.run_case(case, out, progress=lambda name: contextlib.nullcontext(stop_once_recording), columns=here)
    assert ckpt.exists() and not out.exists()
    with pytest.raises(ConfigError, match="relaxed IR coupling"):
        runner.run_case(case, out, resume=True, progress=False)
    assert ckpt.exists()  # refused, not damaged


def test_local_cluster_run_through_the_api(local_run, tmp_path, monkeypatch):
    """A local cluster through the API equals the single-process run; this process (the client) never
    builds the compressed operator nor any block of it: the whole operator's constructor, its build and
    the block builder raise here (the workers are other processes), and the run still completes."""
    tmp, path, ref = local_run

    def not_here(*args, **kwargs):
        raise AssertionError("the client built (part of) the view-factor operator")

    monkeypatch.setattr(vfoperator, "compressed_view_factors", not_here)
    monkeypatch.setattr(vfoperator.CompressedViewFactors, "__init__", not_here)
    monkeypatch.setattr(vfoperator._Builder, "__init__", not_here)
    made = []
    monkeypatch.setattr(cluster_run, "ClusterOperator", _spy(cluster_run.ClusterOperator, made))
    out = tmp_path / "run.nc"
    api.run(path, out, workers=2, chunk_facets=64).close()
    assert len(made) == 1 and made[0].nbytes == 16 * made[0].shape[0] < made[0].held_bytes  # its rows are there
    rel = _assert_close_to_local(out, ref)
    assert rel["columns"].startswith("dask: 5 chunks on 2 worker(s)")
    with pytest.raises(ConfigError, match="give one"):
        api.run(path, tmp_path / "a.nc", workers=2, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(ConfigError, match="--workers 0"):
        api.run(path, tmp_path / "a.nc", workers=0)
    with pytest.raises(ConfigError, match="needs out"):
        api.run(path, workers=2)
    with pytest.raises(ConfigError, match="chunk"):
        api.run(path, tmp_path / "a.nc", workers=2, chunk_facets=0)
    assert not (tmp_path / "a.nc").exists()


def test_killed_worker_mid_run_still_equals_single_process(local_run, dask_cli, tmp_path):
    """SIGKILL one worker (and its nanny: a lost machine) during the recorded period: the scheduler runs
    its tasks again on the other, the rows it held are loaded again, and the run completes unchanged.
    Last in the module: the cluster has one worker after it."""
    tmp, path, ref = local_run
    address, workers = dask_cli
    out = tmp_path / "run.nc"
    ckpt = Path(runner.checkpoint_path(out))
    proc = _popen_cli("run", path, "-o", out, "--scheduler", address, "--chunk-facets", "100")
    try:
        dask_procs.wait_for(ckpt.exists, proc, "the record began")  # its start is checkpointed after the spin-up
        os.killpg(workers[0].pid, signal.SIGKILL)
        running = proc.poll() is None
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert running, "the run finished before the worker was killed: the test proves nothing"
    assert proc.returncode == 0, stderr
    _assert_close_to_local(out, ref)


def test_worker_deaths_beyond_dask_allowance_keep_the_checkpoint(local_run, tmp_path):
    """dask's KilledWorker (a scheduler that allows no failure, its only worker SIGKILLed mid-record):
    one line naming the cause and --resume, exit 2, no output, the checkpoint kept."""
    import subprocess

    _, path, _ = local_run
    out = tmp_path / "run.nc"
    ckpt = Path(runner.checkpoint_path(out))
    proc = None
    try:
        with dask_procs.fragile_cluster(tmp_path) as (address, worker):
            cmd = [sys.executable, "-m", "crater_thermal", "run", str(path), "-o", str(out), "--scheduler", address]
            # no worker comes back here: wait 2 s for one, not the default 30 s
            env = {**dask_procs.ENV, "CRATER_THERMAL_WORKER_WAIT_S": "2"}
            proc = subprocess.Popen(cmd + ["--chunk-facets", "100"], env=env, stderr=subprocess.PIPE, text=True)
            dask_procs.wait_for(ckpt.exists, proc, "the record began")
            # dask's KilledWorker, or (when the death shows first at the next scatter) no worker left after
            # cluster_run.WORKER_WAIT_S: either way one line that says what to do
            starts = ("error: dask gave up", "error: the dask cluster failed the run")
            dask_procs.kill_worker_expect_one_line_error(proc, worker, starts)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
    assert not out.exists() and ckpt.exists()


class _Waiting:
    """A stand-in for a dask client in :func:`cluster_run._resending`: ``wait_for_workers`` answers at once."""

    def __init__(self, workers: bool):
        self.workers = workers

    def wait_for_workers(self, n, timeout=None):
        if not self.workers:
            raise TimeoutError("no workers")


def test_resend_rule_lost_inputs_again_task_errors_at_once():
    from crater_thermal.errors import SolverError

    calls, forgotten = [], []

    def fails_with(exc, times):
        def attempt():
            calls.append(1)
            if len(calls) <= times:
                raise exc
            return "done"

        return attempt

    # a lost input (any other exception): sent again after forget(), up to RESENDS times
    assert (
        cluster_run._resending(_Waiting(True), fails_with(OSError("lost"), 2), forget=lambda: forgotten.append(1))
        == "done"
    )
    assert len(calls) == 3 and len(forgotten) == 2
    calls.clear()
    with pytest.raises(ConfigError, match="dask cluster failed the run"):
        cluster_run._resending(_Waiting(True), fails_with(OSError("lost"), 99))
    assert len(calls) == cluster_run.RESENDS + 1
    # no worker left: given up at once
    calls.clear()
    with pytest.raises(ConfigError, match="are any workers left"):
        cluster_run._resending(_Waiting(False), fails_with(OSError("lost"), 99))
    assert len(calls) == 1
    # a task's own error (a solver's, a user's) is not a lost input: raised as it is, not sent again
    for exc in (SolverError("column diverged"), ConfigError("bad"), MemoryError()):
        calls.clear()
        with pytest.raises(type(exc)):
            cluster_run._resending(_Waiting(True), fails_with(exc, 99))
        assert len(calls) == 1
    # dask's KilledWorker: the one-line error of a task whose workers kept dying
    calls.clear()
    with pytest.raises(ConfigError, match="workers that ran it died"):
        cluster_run._resending(_Waiting(True), fails_with(distributed.KilledWorker("t", "w", 3), 99))


def test_a_worker_with_several_threads_builds_one_plan(monkeypatch):
    """Build tasks running at once on one worker's threads share one compressed plan (one built, the
    others wait for it) instead of each tracing its own."""
    import threading
    import time

    built = []

    def slow_plan(folder, settings):
        built.append(threading.current_thread().name)
        time.sleep(0.2)
        return object()

    monkeypatch.setattr(cluster_run, "_new_plan", slow_plan)
    monkeypatch.setattr(cluster_run, "_PLANS", {})
    got = []
    threads = [
        threading.Thread(target=lambda: got.append(cluster_run._plan("/mesh", {"mesh_hash": "h"}))) for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(built) == 1 and len(got) == 4 and all(p is got[0] for p in got)
    # another mesh: a plan of its own
    other = cluster_run._plan("/other", {"mesh_hash": "k"})
    assert len(built) == 2 and other is not got[0]
