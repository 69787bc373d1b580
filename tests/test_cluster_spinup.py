"""The periodic start of a relaxed or distributed run (:class:`crater_thermal.waveform.SpinUp`, issue 22): its
first pass holds each facet's IR a day at a time and steps 12 h at a time, as the local lagged start's does
(both with the default ``waveform.FIRST_PASS_STEP_S``).

References: the local lagged start of :mod:`crater_thermal.simulate` (a separate implementation of the same
passes; of the first pass's coarse steps the two share only the choice of samples and the filling between
them, ``waveform.hold_samples`` and ``waveform.between``, tested against hand-worked samples and
``np.interp`` in ``test_simulate``), the local coupled start (the other fixed point, the coupling
stepped), the relaxed start with the first pass it had before (relaxed window by window to 0.05 K: its
pass count is the "before"), and, for the distributed start, the single-process relaxed run (a real
scheduler and two worker processes started with dask's own command line on 127.0.0.1)."""

from __future__ import annotations

import contextlib
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from test_simulate import small_case

from crater_thermal import cluster_run, config, io, runner, waveform
from crater_thermal.kernels.conduction import ACC_NSTEPS

distributed = pytest.importorskip("distributed")

import dask_procs  # noqa: E402

# the periodic start's tolerance of these cases (small_case: periodic_tol_K = 0.001)
TOL_K = 1e-3
# the bound for a distributed run against the single-process run
DISTRIBUTED_TOL_K = 0.01


def _case(tmp: Path, name: str, *, facets=300, relaxed=True, spinup_ir="lagged", compressed=False) -> Path:
    """A 2 km crater at 85 S, a lunation of periodic spin-up and 8 recorded days."""
    path = small_case(tmp, name=name, facets=facets, end="2019-01-09", extra_period=f'spinup_ir = "{spinup_ir}"')
    text = path.read_text()
    if relaxed:
        text = text.replace("flux_step_hours = 4.0", 'flux_step_hours = 4.0\nir_coupling = "relaxed"')
    if compressed:
        text += '[radiation]\nview_factors = "compressed"\n'
    path.write_text(text)
    return path


def _run(path: Path, out: Path, **kwargs):
    ds = io.open_run(runner.run_case(config.load_case(path), out, progress=False, **kwargs))
    ds.load()
    return ds


def _start(ds) -> np.ndarray:
    """The surface temperatures [K] at the record's first sample: the periodic start's."""
    return ds["surface_temperature"].values[0].astype(float)


def _spy_spinups(monkeypatch) -> list:
    """The SpinUps made from now on; each records ``held_substeps``, the conduction sub-steps of every
    column in its held (first) pass (the pass's accumulators, gathered from the workers on a cluster)."""
    made = []

    class Spy(waveform.SpinUp):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.held_substeps = None
            made.append(self)

        def held(self, on_step=None):
            super().held(on_step)
            self.held_substeps = self.solver.acc[:, ACC_NSTEPS].copy()

    monkeypatch.setattr(waveform, "SpinUp", Spy)
    return made


def _coarse_steps(spin) -> int:
    """The first pass's conduction steps when it steps 12 h at a time (one sub-step each): the 12-hour
    intervals of its holds, counted from the spin-up window's times (4-hour samples)."""
    t = spin.t
    return sum(
        int(np.ceil((t[k1] - t[k]) / 43200.0 - 1e-9))
        for b0, b1 in spin._blocks()
        for k, k1 in waveform.hold_spans(t, b0, b1)
    )


def _columns_run(ds) -> list[int]:
    return [int(n) for n in ds.attrs["start_method"].split("columns run per window: ")[1].rstrip(")").split(", ")]


def test_relaxed_start_is_the_local_lagged_start(tmp_path, monkeypatch):
    """The relaxed run's periodic start (this process) against three references on a 300-facet crater:

    * the local lagged start (:mod:`crater_thermal.simulate`): the same passes (the same holds stepped 12 h
      at a time, then each pass driven by the IR of the previous one's temperatures, the same converged
      columns skipped) in another implementation (the local one takes the IR products on the stepped
      samples and interpolates them; the relaxed one forms them from the filled-in temperatures, whose
      emission is linear in time), so the same columns run in every pass and the same start to round-off
      amplified by the shooting (1e-4 K);
    * the local coupled start: another fixed point (the IR of the step's predictor instead of that of the
      periodic temperatures), measured <= 0.05 K apart on 1,500-4,000-facet craters (test_simulate);
    * the relaxed start with its former first pass (relaxed window by window to 0.05 K): no more passes
      than that, and the same fixed point: both starts lie within the tolerance of it (residual and
      quasi-Newton step <= 1e-3 K, a skipped column tol/4 more), so within 2.5 x 1e-3 K of each other.
    """
    made = _spy_spinups(monkeypatch)
    relaxed = _run(_case(tmp_path, "relaxed"), tmp_path / "relaxed.nc")
    spin = made[-1]
    assert spin.holds == 30 and spin.iterations == []  # a lunation held a day at a time, nothing relaxed
    # the held pass stepped 12 h at a time, one sub-step each (every 4-hour sample: 177 or more)
    assert np.all(spin.held_substeps == _coarse_steps(spin)) and _coarse_steps(spin) < 60
    assert "holding each facet's IR 1 d at a time (30 holds;" in relaxed.attrs["start_method"]

    def the_old_first_pass(self, on_step=None):
        self.tol, self.window = 0.05, self.block  # waveform.SEED_TOL_K over whole blocks, as before
        self.coupled(on_step)

    with monkeypatch.context() as m:
        m.setattr(waveform.SpinUp, "held", the_old_first_pass)
        before = _run(_case(tmp_path, "before"), tmp_path / "before.nc")
    assert made[-1].iterations and made[-1].holds == 0  # the old seed did run
    # both first passes with their default steps (12 h, waveform.FIRST_PASS_STEP_S)
    lagged = _run(_case(tmp_path, "lagged", relaxed=False), tmp_path / "lagged.nc")
    coupled = _run(_case(tmp_path, "coupled", relaxed=False, spinup_ir="coupled"), tmp_path / "coupled.nc")

    runs = _columns_run(relaxed)
    assert runs == _columns_run(lagged) and runs[0] == 300 and min(runs) < 300, runs  # columns were skipped
    passes = {name: int(ds.attrs["spinup_iterations"]) for name, ds in (("relaxed", relaxed), ("before", before))}
    passes["lagged"] = int(lagged.attrs["spinup_iterations"])
    assert passes["relaxed"] == passes["lagged"] <= passes["before"], passes
    assert np.abs(_start(relaxed) - _start(lagged)).max() <= 1e-4
    assert np.abs(_start(relaxed) - _start(coupled)).max() <= 0.05
    assert np.abs(_start(relaxed) - _start(before)).max() <= 2.5 * TOL_K
    # the record after either start: a decaying difference of starts, the same relaxed record
    dT = relaxed["surface_temperature"].values - before["surface_temperature"].values
    assert np.abs(dT).max() <= 2.5 * TOL_K


@pytest.fixture(scope="module")
def local_relaxed(tmp_path_factory):
    """The single-process relaxed run of the exact-matrix case (the reference of the distributed ones)."""
    tmp = tmp_path_factory.mktemp("local")
    path = _case(tmp, "local")
    return path, _run(path, tmp / "local.nc")


def _close_to(ds, ref) -> float:
    d = np.abs(ds["surface_temperature"].values.astype(float) - ref["surface_temperature"].values)
    assert d.max() <= DISTRIBUTED_TOL_K, d.max()
    return float(d.max())


def test_distributed_start_holds_on_the_workers_and_equals_the_relaxed_one(
    local_relaxed, dask_cli, tmp_path, monkeypatch
):
    """The distributed start (3 chunks on 2 workers) runs its held pass and its lagged passes whole on the
    workers, with the same holds, passes and skipped columns as in one process, and the run equals the
    single-process one (the issue's 0.01 K; the chunks conduct the same columns with the same IR:
    round-off)."""
    path, ref = local_relaxed
    address, _ = dask_cli
    made = _spy_spinups(monkeypatch)
    ds = _run(path, tmp_path / "run.nc", columns=cluster_run.distributed_columns(address, chunk_facets=100))
    spin = made[-1]
    assert spin.remote_pass and not spin.remote_lost and spin.holds == 30
    assert np.all(spin.held_substeps == _coarse_steps(spin))  # the workers' holds stepped 12 h at a time
    assert ds.attrs["spinup_iterations"] == ref.attrs["spinup_iterations"]
    # the same converged columns skipped on the workers as in one process
    assert _columns_run(ds) == _columns_run(ref) and min(_columns_run(ds)) < 300, _columns_run(ds)
    assert _close_to(ds, ref) <= 1e-4


def test_a_held_pass_lost_on_the_workers_runs_through_the_client(local_relaxed, dask_cli, tmp_path, monkeypatch):
    """Data of the held pass lost with a worker (stood in for by an error of the pass on the cluster, which
    the backend turns into ``PassLost``): the pass runs again through ``solve`` with held IR (a round per
    hold), the later passes through the store (every column run: the skip needs the products on the
    workers), and the run still equals the single-process one."""
    path, ref = local_relaxed
    address, _ = dask_cli
    calls = []

    def lost(self, *args, **kwargs):
        calls.append(1)
        raise OSError("stand-in for a lost worker's data")

    monkeypatch.setattr(cluster_run.DaskColumns, "_held_pass", lost)
    made = _spy_spinups(monkeypatch)
    ds = _run(path, tmp_path / "run.nc", columns=cluster_run.distributed_columns(address, chunk_facets=100))
    spin = made[-1]
    assert calls == [1] and spin.remote_lost and not spin.remote_pass and spin.holds == 30
    assert np.all(spin.held_substeps == _coarse_steps(spin))  # through ``solve``: stepped 12 h at a time too
    assert set(_columns_run(ds)) == {300}
    assert ds.attrs["spinup_iterations"] == ref.attrs["spinup_iterations"]
    _close_to(ds, ref)


def test_killed_worker_while_building_rows_still_equals_single_process(tmp_path, monkeypatch):
    """SIGKILL one worker (and its nanny: a lost machine) while the workers build the compressed operator's
    row blocks (6 chunks, when the first chunk's row sums are in and the killed worker is building or
    holding a block): every block ends up built by the surviving worker (the scheduler's task stream) and
    the run completes equal to the single-process relaxed run."""
    path = _case(tmp_path, "rows", compressed=True)
    ref = _run(path, tmp_path / "local.nc")
    seen = {}  # the session's client, what the workers built or held at the kill, the workers after it
    build = cluster_run._Session._build_on_workers

    def watched(self, *args, **kwargs):
        seen["client"] = self.client
        with distributed.get_task_stream(self.client) as stream:
            F = build(self, *args, **kwargs)  # returns once every chunk's rows are in memory
        seen["stream"], seen["alive"] = stream.data, set(self.client.scheduler_info()["workers"])
        return F

    monkeypatch.setattr(cluster_run._Session, "_build_on_workers", watched)
    with dask_procs.cli_cluster(tmp_path, 2) as (address, workers):

        def kill_at_first_block(done, total):
            if "at_kill" not in seen:
                client = seen["client"]
                seen["at_kill"] = {w: [*client.processing()[w], *client.has_what()[w]] for w in client.processing()}
                # the victim builds or holds a block (the scheduler may have given them all to one worker)
                busy = sorted(w for w, keys in seen["at_kill"].items() if any("ct-build-" in str(k) for k in keys))
                victim = dask_procs.process_of(client, busy[0], workers) if busy else workers[0]
                os.killpg(victim.pid, signal.SIGKILL)

        def progress(description):
            return contextlib.nullcontext(kill_at_first_block if description.startswith("view factors") else None)

        factory = cluster_run.distributed_columns(address, chunk_facets=50)
        out = runner.run_case(config.load_case(path), tmp_path / "run.nc", progress=progress, columns=factory)
    lost = set(seen["at_kill"]) - seen["alive"]
    assert len(lost) == 1 and len(seen["alive"]) == 1
    building = [k for k in seen["at_kill"][lost.pop()] if str(k).startswith("ct-build-")]
    assert building, f"the killed worker had no block to build: the test proves nothing ({seen['at_kill']})"
    survivor = seen["alive"].pop()
    rebuilt = {t["key"] for t in seen["stream"] if str(t["key"]).startswith("ct-build-") and t["worker"] == survivor}
    assert set(building) <= rebuilt and len(rebuilt) == 6
    with io.open_run(out) as ds:
        _close_to(ds, ref)
