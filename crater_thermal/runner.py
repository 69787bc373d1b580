"""Drivers of a run and a replay: files, checkpoints, locks and the scratch store around the time loop.

The loop itself (coupled steps, the periodic start, replays of saved fluxes) is :mod:`crater_thermal.simulate`,
which works on arrays and callbacks. Here a case becomes files:

``run_case`` (``crater-thermal run``, :func:`crater_thermal.api.run`)
    refuses an output that is one of its inputs, takes the output's lock (:func:`crater_thermal.io.output_lock`),
    then: sunlight block by block into a crash-safe scratch store ``OUT.partial/``; the spin-up to the
    start of the record; the recorded period, checkpointed to ``OUT.checkpoint.npz`` every
    ``[output] checkpoint_interval_steps`` steps (``resume=True`` continues from it and gives the same numbers
    as an uninterrupted run); ``run.nc`` written from the store block by block (temporary name, then rename).
``replay_file`` (``crater-thermal replay``, :func:`crater_thermal.api.replay`)
    the profiles resolved (defaults, density grid, duplicates), the replay streamed into ``replay.nc``.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from crater_thermal import heap, io, profiles, radiosity, simulate, thermal, waveform
from crater_thermal.constants import AU
from crater_thermal.errors import ConfigError, DiskSpaceError, FluxFileError, OutputExistsError


def checkpoint_path(out_path) -> str:
    """The checkpoint file of a run writing ``out_path``: ``OUT.checkpoint.npz`` beside it."""
    return str(out_path) + ".checkpoint.npz"


def resolve_profiles(labels: Sequence[str], density_grid: str | None = None, allow_inverted: bool = False):
    """Profiles from labels and an optional density grid, without duplicates (order kept)."""

    labels = list(labels)
    if not labels and not density_grid:
        labels = list(profiles.DEFAULT_REPLAY_PROFILES)
    chosen = [thermal.parse_profile(lab, allow_inverted=allow_inverted) for lab in labels]
    if density_grid:
        chosen += list(thermal.density_grid_profiles(density_grid))
    return profiles.unique_profiles(chosen)


def replay_file(
    flux_path,
    labels: Sequence[str],
    *,
    density_grid=None,
    initial_temperature=None,
    fixed_spinup=False,
    property_set=None,
    allow_inverted=False,
    output,
    overwrite=False,
    progress=None,
    chunk_mb: float = simulate.DEFAULT_CHUNK_MB,
):
    """``crater-thermal replay``: validate inputs, replay, write the replay dataset atomically.

    The fluxes are read and the temperatures written block by block (memory about ``chunk_mb`` [MB]
    plus the solver's columns, whatever the run's length and size). Large temporary arrays are reused
    from the heap meanwhile (:mod:`crater_thermal.heap`).
    ``progress``: optional reporter (see :mod:`crater_thermal.progress`) for the "replay" stage.
    """
    io.check_output(output, overwrite, inputs=[flux_path])  # fail before any work
    with io.output_lock(output), heap.reuse_large_blocks():
        if initial_temperature is not None and not (1.0 <= initial_temperature <= 1000.0):
            raise ConfigError(f"--initial-temperature {initial_temperature} K outside [1, 1000] K")
        profiles = resolve_profiles(labels, density_grid, allow_inverted)
        ds = io.read_flux_dataset(flux_path, load=False)
        tops, bottoms = zip(*(simulate.profile_densities(p) for p in profiles))
        skeleton = io.replay_dataset(ds, [p.label for p in profiles], tops, bottoms, None)
        shape = (len(profiles), ds.sizes["time"], ds.sizes["facet"])
        check_replay_disk(output, *shape)
        variables = {"surface_temperature": (("profile", "time", "facet"), shape, {"units": "K"}, "f4")}
        with io.stream_dataset(
            skeleton, output, variables, overwrite=overwrite, time_rows=simulate.TIME_CHUNK
        ) as stream:
            with simulate.stage(progress, f"replay ({len(profiles)} profiles x {shape[2]} facets)") as report:
                _, info = simulate.replay_fluxes(
                    ds,
                    profiles,
                    property_set=property_set,
                    initial_temperature=initial_temperature,
                    fixed_spinup=fixed_spinup,
                    progress=report,
                    chunk_mb=chunk_mb,
                    write=lambda ps, ts, fs, T: stream("surface_temperature", (ps, ts, fs), T),
                )
            stream.set_attrs(
                {
                    "replay_start": info["start"],
                    "periodic_iterations": info["periodic_iterations"] or None,
                    "periodic_residual_K": info["periodic_residual_K"] or None,
                    "initial_temperature_K": initial_temperature,
                    "ir_assumption": "saved nominal IR (thesis 7.2)",
                }
            )
        ds.close()
        return Path(output)


def _case_fingerprint(case) -> str:
    return hashlib.sha256(case.toml_text.encode()).hexdigest()[:16]


def _scratch_path(out_path) -> str:
    return str(out_path) + ".partial"


def scratch_estimate(
    case, n_facets: int, n_spin: int, n_record: int, coupling: str, remote: bool = False, block: int = 1
) -> dict:
    """What a run of ``case`` writes to disk, at most [B]: ``{"store": the scratch store's peak (sunlight of
    every sample, the spin-up windows' series, then the record's rows), "run_nc": run.nc's series
    uncompressed (what compression then shrinks), "total": both, as they are while run.nc is written}``.

    ``n_spin`` / ``n_record``: samples of the spin-up window and of the record; ``coupling``: the run's IR
    coupling ("relaxed" keeps its passes' series in float64); ``remote``: the relaxed passes run on a
    cluster's workers (their series stay there). The lagged spin-up is counted wherever it may be chosen
    (an operator assumed): three series of the window. Every series of ``n`` samples takes ``n x
    n_facets`` values of its type (:data:`crater_thermal.io.RUN_SERIES_DTYPE`, or float64). Without saved
    spin-up fluxes the spin-up's sunlight is deleted in whole blocks of ``block`` samples when the start
    ends, before run.nc is written."""
    f4 = np.dtype(io.RUN_SERIES_DTYPE).itemsize
    nf, ns, nr = int(n_facets), int(n_spin), int(n_record)
    incidence = case.surface.albedo_model != "constant"
    save_spin = bool(case.output.save_spinup_fluxes) and ns > 0
    sun = (2 + incidence) * (ns + nr) * nf * f4  # direct, solar (, absorbed) of every sample
    if ns == 0:
        spin, spin_ir = 0, 0
    elif coupling == "relaxed":
        spin_ir = save_spin * ns * nf * (f4 if remote else 8)
        spin = (0 if remote else 4 * ns * nf * 8) + spin_ir  # wr_T0, wr_T1, wr_irc, wr_irn
    else:
        spin_ir = save_spin * ns * nf * f4
        lagged = (
            case.period.spinup == "periodic" and simulate.spinup_ir_method(case.period.spinup_ir, True, nf) == "lagged"
        )
        spin = 3 * ns * nf * f4 if lagged else spin_ir  # lag_ir0, lag_ir1, lag_T (one becomes spin_ir)
    record = spin_ir + 2 * nr * nf * f4  # T and IR rows
    store = sun + max(spin, record)
    run_nc = ((2 + incidence + 2) * nr + save_spin * (2 + incidence) * ns) * nf * f4
    # without saved spin-up fluxes the spin-up's sunlight goes when the start ends (whole blocks of it)
    sun_kept = sun if save_spin or ns == 0 else (2 + incidence) * nf * f4 * (ns + nr - ns // block * block)
    return {"store": int(store), "run_nc": int(run_nc), "total": int(sun_kept + record + run_nc)}


def _check_disk(
    case, out_path: Path, n_facets: int, n_spin: int, n_record: int, coupling: str, remote: bool, block: int
):
    """Refuse a run whose scratch store cannot fit on the output's disk (``DiskSpaceError``, before any
    ray is traced); warn when the store and run.nc together may not (run.nc is compressed, so it usually
    takes less than counted). A resumed run's store already holds part of it."""
    need = scratch_estimate(case, n_facets, n_spin, n_record, coupling, remote, block)
    folder = out_path.parent  # made by the output's lock
    free = shutil.disk_usage(folder).free
    scratch = Path(_scratch_path(out_path))
    if scratch.is_dir():
        free += sum(e.stat().st_size for e in os.scandir(scratch) if e.is_file())
    gb = 1e9
    if need["store"] > free:
        raise DiskSpaceError(
            f"this run needs ~{need['store'] / gb:.1f} GB of scratch space beside {out_path} "
            f"({scratch}, {n_facets} facets x {n_spin + n_record} samples) and run.nc up to "
            f"{need['run_nc'] / gb:.1f} GB more, but {folder.resolve()} has {free / gb:.1f} GB free: free some "
            "space, write the output to a larger disk (-o), or record a shorter period"
        )
    if need["total"] > free:
        warnings.warn(
            f"{out_path}: the scratch store (~{need['store'] / gb:.1f} GB) and run.nc (up to "
            f"{need['run_nc'] / gb:.1f} GB before compression) may not fit in the {free / gb:.1f} GB free; "
            "if the disk fills, the run stops with its checkpoint kept: free space and run it again with --resume",
            stacklevel=2,
        )


def check_replay_disk(output, n_profiles: int, n_times: int, n_facets: int, chunk_bytes: int = 0) -> None:
    """Before a replay's work: refuse one whose chunk files cannot fit on the output's disk
    (``DiskSpaceError``; ``chunk_bytes`` [B]: the unfinished chunks of a distributed replay, kept
    uncompressed for ``--resume``), and warn when the replay dataset may not fit beside them: at most
    ``n_profiles x n_times x n_facets`` float32 values [4 B] before compression (netCDF's zlib usually
    makes it smaller, so this is a warning). A disk that fills later stops the replay with its temporary file
    removed, an existing output kept, and a distributed replay's finished chunks kept for ``--resume``."""
    output = Path(output)
    folder = output.resolve().parent
    free = shutil.disk_usage(folder).free
    nc = int(n_profiles) * int(n_times) * int(n_facets) * np.dtype(np.float32).itemsize
    gb = 1e9
    if chunk_bytes > free:
        raise DiskSpaceError(
            f"this replay's chunks need ~{chunk_bytes / gb:.1f} GB beside {output} ({n_profiles} profiles x "
            f"{n_times} samples x {n_facets} facets) and the replay up to {nc / gb:.1f} GB more, but {folder} has "
            f"{free / gb:.1f} GB free: free some space, write the replay to a larger disk (-o), or replay fewer "
            "profiles"
        )
    if chunk_bytes + nc > free:
        warnings.warn(
            f"{output}: the replay ({n_profiles} profiles x {n_times} samples x {n_facets} facets, up to "
            f"{nc / gb:.1f} GB before compression"
            + (f", after {chunk_bytes / gb:.1f} GB of chunks" if chunk_bytes else "")
            + f") may not fit in the {free / gb:.1f} GB free; if the disk fills, the replay stops and "
            + ("its finished chunks are kept for --resume" if chunk_bytes else "an existing output is kept"),
            stacklevel=2,
        )


def run_case(
    case,
    out_path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress=None,
    timer: simulate.Timer | None = None,
    columns=None,
):
    """``crater-thermal run``: the coupled crater simulation of a case, written to ``out_path``.

    Memory stays bounded by ``[output] chunk_mb`` (default :func:`simulate.default_chunk_mb`: 256 MB up to
    ~116k facets) for the (time, facet) series, not by
    run length x facets: sunlight is computed, and temperatures and IR are kept, in blocks of time
    samples, in a crash-safe scratch store ``OUT.partial/`` (one file per block, written atomically);
    the netCDF file is written from it block by block at the end (temporary name, then rename).
    The solver state is checkpointed every ``case.output.checkpoint_interval_steps`` flux steps (and
    when the spin-up ends) to ``OUT.checkpoint.npz``; ``resume=True`` continues from it and gives the
    same numbers as an uninterrupted run. Returns the output path.

    Large temporary arrays are reused from the heap during the run (:mod:`crater_thermal.heap`).

    ``progress``: optional reporter (:mod:`crater_thermal.progress`): one bar per stage (view factors,
    horizon map, sunlight, spin-up windows, recorded period, writing); None (or False) for none.

    ``columns``: where the columns are conducted with ``[steps] ir_coupling = "relaxed"`` (waveform
    relaxation, :mod:`crater_thermal.waveform`): None for this process, or a factory
    ``columns(case, mesh, store)`` -> context manager yielding a session, open from the view factors to
    the end of the record, with ``session.columns(fc)`` -> the backend and, optionally,
    ``session.view_factors(...)`` that builds the operator (arguments of
    :func:`crater_thermal.vfoperator.view_factor_operator`); the dask cluster of
    :mod:`crater_thermal.cluster_run` (which forces the relaxed scheme) builds it on its workers.
    """
    out_path = Path(out_path)
    io.refuse_input_as_output(out_path, case_inputs(case))
    with io.output_lock(out_path), heap.reuse_large_blocks():
        try:
            return _run_case(
                case, out_path, resume=resume, overwrite=overwrite, progress=progress, timer=timer, columns=columns
            )
        except BaseException:  # failed or interrupted: the scratch store is kept only for a checkpoint
            if not Path(checkpoint_path(out_path)).exists():
                shutil.rmtree(_scratch_path(out_path), ignore_errors=True)
            raise


def case_inputs(case) -> list:
    """The files a case reads: the case file itself, its mesh or its DEM (absent ones left out)."""
    c = case.crater
    return [p for p in (case.path, c.mesh, c.dem) if p]


def _run_case(case, out_path, *, resume: bool, overwrite: bool, progress, timer, columns=None):
    """The steps of a run, in order: checkpoint, geometry and Sun, sunlight, start of the record, record, write."""
    ckpt_path = Path(checkpoint_path(out_path))
    ckpt = _read_checkpoint(case, out_path, ckpt_path, resume, overwrite)
    coupling = "relaxed" if (case.steps.ir_coupling == "relaxed" or columns is not None) else case.steps.ir_coupling
    if ckpt is not None and str(ckpt.get("coupling", coupling)) != coupling:
        raise ConfigError(
            f"checkpoint {ckpt_path} was written by a run with the {ckpt['coupling']} IR coupling, this one "
            f"uses {coupling} (a run on a dask cluster is relaxed): resume it as it was started"
        )
    nominal = thermal.parse_profile(case.surface.nominal_profile)  # before any ray is traced
    io.check_compression(case.output.compression)  # before hours of work, not when run.nc is written
    timer = timer or simulate.Timer()
    mesh, tracer = simulate.case_scene(case, timer)
    spin_times, times, sun_dirs, sun_dist = simulate.case_sun(case, timer)
    block = simulate.block_rows(mesh.n_facets, simulate.chunk_bytes(case, mesh.n_facets))
    _check_disk(case, out_path, mesh.n_facets, len(spin_times), len(times), coupling, columns is not None, block)
    if ckpt is not None and int(ckpt.get("block", -1)) != block:
        raise ConfigError(
            f"checkpoint {ckpt_path} was written with blocks of {int(ckpt.get('block', -1))} "
            f"samples, this run uses {block}; run again without --resume"
        )
    store = io.SegmentStore(_scratch_path(out_path), block)
    if ckpt is None:  # a fresh start: nothing of an earlier attempt is reused
        store.remove()
        store = io.SegmentStore(_scratch_path(out_path), block)
    incidence = case.surface.albedo_model != "constant"
    with contextlib.ExitStack() as stack:
        # a cluster's session is open from the operator (its workers build their rows) to the record's end
        session = None if columns is None else stack.enter_context(columns(case, mesh, store))
        build = getattr(session, "view_factors", None)
        need_sunlight = not store.marked("sunlight")
        F, hmap = simulate.case_operator_and_horizons(
            case, mesh, tracer, timer, progress, build=build, horizons=need_sunlight
        )
        fc = simulate.Forcing(
            mesh, F, spin_times, times, sun_dirs, sun_dist, store=store, drive="absorbed" if incidence else "solar"
        )
        if need_sunlight:
            _sunlight_into_store(case, fc, tracer, store, block, timer, progress, hmap)
        del tracer
        solver, stepper = _coupled_solver(case, nominal, fc, incidence)
        checkpoints = _Checkpoints(ckpt_path, _case_fingerprint(case), block, solver, stepper, timer, coupling)
        cols = None
        if coupling == "relaxed":
            if session is None:
                cols = waveform.LocalColumns(
                    column_solver(nominal, fc.mesh.n_facets, column_settings(case)),
                    fc.F,
                    float(case.surface.albedo),
                    float(case.surface.emissivity),
                    incidence,
                )
            else:
                cols = session.columns(fc)
        spin_info, k0, ir_k = _start_of_record(
            case, fc, solver, stepper, store, block, ckpt, checkpoints, timer, progress, cols
        )
        if cols is None:
            _record(case, fc, stepper, store, block, k0, ir_k, checkpoints, spin_info, timer, progress)
        else:
            _record_relaxed(case, fc, cols, solver, store, block, k0, ir_k, checkpoints, spin_info, timer, progress)
    _write_run(
        case, fc, store, block, out_path, nominal, spin_info, incidence, ckpt is not None or overwrite, timer, progress
    )
    if ckpt_path.exists():
        ckpt_path.unlink()
    store.remove()
    return out_path


def _read_checkpoint(case, out_path, ckpt_path: Path, resume: bool, overwrite: bool):
    """The checkpoint to continue from (``resume``), or None for a fresh start (output checked then).

    A plain run over an unfinished run's checkpoint is refused (``--resume`` continues it, ``--overwrite``
    discards it); a checkpoint of another case, or unreadable, is refused.
    """
    if ckpt_path.exists() and not resume:
        if not overwrite:
            raise OutputExistsError(
                f"{ckpt_path} holds an unfinished run of output {out_path}: pass --resume to continue it, or "
                "--overwrite to discard it and start again"
            )
        ckpt_path.unlink()
    ckpt = None
    if resume and ckpt_path.exists():
        try:
            ckpt = io.load_npz(ckpt_path)
        except Exception as exc:
            raise FluxFileError(
                f"checkpoint {ckpt_path} is unreadable ({type(exc).__name__}); run again without --resume"
            ) from None
        if str(ckpt["fingerprint"]) != _case_fingerprint(case):
            raise ConfigError(f"checkpoint {ckpt_path} belongs to a different case; run without --resume")
    if ckpt is None:
        io.check_output(out_path, overwrite)
    return ckpt


def _sunlight_into_store(case, fc, tracer, store, block: int, timer, progress, hmap=None) -> None:
    """Direct, scattered (and absorbed) sunlight [W m-2] of every sample, block by block into the store
    (``hmap``: the horizon map when already traced)."""
    nf, n_all = fc.mesh.n_facets, len(fc.sun_dirs)
    sunlight = simulate.case_sunlight(case, fc.mesh, tracer, fc.F, timer, progress, hmap=hmap)
    with simulate.stage(progress, f"sunlight ({nf} facets)") as report:
        for k0 in range(0, n_all, block):
            k1 = min(n_all, k0 + block)
            direct, solar, absorbed = sunlight.with_absorbed(fc.sun_dirs[k0:k1], fc.sun_dist_m[k0:k1], timer)
            with timer("io"):  # at run.nc's precision, which the record and the replays are then driven with
                store.write("direct", k0, direct.astype(io.RUN_SERIES_DTYPE))
                store.write("solar", k0, solar.astype(io.RUN_SERIES_DTYPE))
                if absorbed is not None:
                    store.write("absorbed", k0, absorbed.astype(io.RUN_SERIES_DTYPE))
            del direct, solar, absorbed
            if report is not None:
                report(k1, n_all)
    store.mark("sunlight")


def column_settings(case) -> dict:
    """The solver settings of a case's columns as plain values (what a cluster's workers are sent):
    ``property_set``, ``emissivity`` [-], ``geothermal_flux`` [W m-2], ``dt_max`` [s] or None."""
    dt = case.steps.conduction_step_s
    return {
        "property_set": case.surface.property_set,
        "emissivity": float(case.surface.emissivity),
        "geothermal_flux": float(case.surface.geothermal_flux_W_m2),
        "dt_max": float(dt) if dt else None,
    }


def column_solver(profile, n: int, settings: dict) -> thermal.ColumnSolver:
    """``n`` columns of one profile (a Profile or its label) with :func:`column_settings`."""
    kw = {"dt_max": settings["dt_max"]} if settings.get("dt_max") else {}
    return thermal.ColumnSolver(
        [profile] * n,
        property_set=settings["property_set"],
        emissivity=settings["emissivity"],
        geothermal_flux=settings["geothermal_flux"],
        **kw,
    )


def _coupled_solver(case, nominal, fc, incidence: bool):
    """The columns (one per facet, the nominal profile) and the coupled stepper of a case."""
    solver = column_solver(nominal, fc.mesh.n_facets, column_settings(case))
    stepper = radiosity.CoupledStepper(
        solver,
        fc.F,
        float(case.surface.albedo),
        float(case.surface.emissivity),
        solar_is_absorbed=incidence,
        # a relaxed run steps nothing: its stepper only gives the start's IR products
        ir_scheme="extrapolated" if case.steps.ir_coupling == "relaxed" else case.steps.ir_coupling,
    )
    return solver, stepper


class _Checkpoints:
    """Writes the run's checkpoint: the solver's state at record sample ``k``, the IR extrapolation's history
    (so that a resumed run steps exactly as the uninterrupted one) and the start's diagnostics."""

    def __init__(self, path: Path, fingerprint: str, block: int, solver, stepper, timer, coupling: str):
        self.path, self.fingerprint, self.block, self.coupling = path, fingerprint, block, coupling
        self.solver, self.stepper, self.timer = solver, stepper, timer

    def save(self, k: int, info: dict, ir_k: np.ndarray) -> None:
        """Checkpoint at record sample ``k`` with ``ir_k`` [W m-2], the IR that drove it (float64: the
        store keeps the record's IR rounded to :data:`crater_thermal.io.RUN_SERIES_DTYPE`)."""
        hist = self.stepper.history()
        extra = {} if hist is None else {f"history_{name}": np.asarray(v) for name, v in hist.items()}
        with self.timer("io"):
            io.save_npz_atomic(
                self.path,
                fingerprint=np.array(self.fingerprint),
                phase=np.array("record"),
                coupling=np.array(self.coupling),
                k=np.array(k),
                ir_k=np.asarray(ir_k, np.float64),
                block=np.array(self.block),
                state=self.solver.state(),
                start_method=np.array(info["start_method"]),
                iterations=np.array(info["iterations"]),
                residual=np.asarray(info["residual"], float),
                **extra,
            )


def _start_of_record(case, fc, solver, stepper, store, block, ckpt, checkpoints, timer, progress, cols=None):
    """The state at the first sample to compute: from the checkpoint, or the spin-up (then checkpointed).

    Returns ``(spin_info, k0, ir_k0)``: the start's diagnostics, the record sample the state belongs to,
    and the IR [W m-2] at it.
    """
    if ckpt is not None:
        spin_info = {
            "start_method": str(ckpt["start_method"]),
            "iterations": int(ckpt["iterations"]),
            "residual": ckpt["residual"],
        }
        k0 = int(ckpt["k"])
        solver.set_state(ckpt["state"])
        if "history_ir_now" in ckpt:
            names = ("ir_now", "ir_before", "dt_before", "prompt_now", "prompt_before")
            stepper.set_history({name: ckpt[f"history_{name}"] for name in names if f"history_{name}" in ckpt})
        ir_k = ckpt["ir_k"] if "ir_k" in ckpt else store.read("ir", k0, k0 + 1, dtype=np.float64)[0]
        return spin_info, k0, np.asarray(ir_k, np.float64)
    spin_t = simulate.seconds_since(fc.spin_times, fc.times[0])
    save_spin = case.output.save_spinup_fluxes and fc.n_spin > 0
    with timer("conduction_spinup"):
        if cols is None or fc.n_spin == 0:
            spin_info, ir_start = simulate.spin_up(case, fc, solver, stepper, spin_t, block, save_spin, progress)
        else:
            spin_info, ir_start = _spin_up_relaxed(case, fc, cols, solver, stepper, spin_t, block, save_spin, progress)
    ir_k = stepper.ir(solver.surface_temperature) if ir_start is None else ir_start
    with timer("io"):
        store.write("T", 0, solver.surface_temperature[None, :].astype(io.RUN_SERIES_DTYPE))
        store.write("ir", 0, ir_k[None, :].astype(io.RUN_SERIES_DTYPE))
    checkpoints.save(0, spin_info, ir_k)
    if not save_spin:  # the spin-up's sunlight is read no more (a resumed run starts from the checkpoint)
        store.drop_before(fc.record_offset, "direct", "solar", "absorbed")
    return spin_info, 0, ir_k


class _RecordRows:
    """Buffers the record's surface temperatures and IR, row by row, and flushes them to the store in blocks
    (as :data:`crater_thermal.io.RUN_SERIES_DTYPE`, run.nc's type: nothing computes from them afterwards)."""

    def __init__(self, store, block: int, nf: int, first: int, timer):
        self.store, self.block, self.timer = store, block, timer
        self.T = np.empty((block, nf), io.RUN_SERIES_DTYPE)
        self.ir = np.empty((block, nf), io.RUN_SERIES_DTYPE)
        self.first, self.n = first, 0  # first buffered row, rows buffered

    def append(self, T, ir) -> None:
        self.T[self.n], self.ir[self.n] = T, ir
        self.n += 1
        if (self.first + self.n) % self.block == 0:
            self.flush()

    def flush(self) -> None:
        if self.n:
            with self.timer("io"):
                self.store.write_rows("T", self.first, self.T[: self.n])
                self.store.write_rows("ir", self.first, self.ir[: self.n])
        self.first, self.n = self.first + self.n, 0


def _record(case, fc, stepper, store, block, k0, ir_k, checkpoints, spin_info, timer, progress) -> None:
    """The recorded period from sample ``k0``: coupled steps
    (:func:`crater_thermal.simulate.ir_product_samples` of them per IR product), rows into the store, a
    checkpoint every ``[output] checkpoint_interval_steps`` steps (at the end of the group of steps that
    reaches it)."""
    nt, off = len(fc.times), fc.record_offset
    rec_t = simulate.seconds_since(fc.times, fc.times[0])
    every = case.output.checkpoint_interval_steps
    g = simulate.ir_product_samples(case, fc.mesh.n_facets) if fc.F is not None else 1
    rows = _RecordRows(store, block, fc.mesh.n_facets, k0 + 1, timer)
    sol, prompt, w0 = None, None, 0
    with simulate.stage(progress, f"record {case.name}") as report:
        k = k0
        while k < nt - 1:
            e = min(k + g, nt - 1)
            if sol is None or e >= w0 + len(sol):
                sol = prompt = None
                w0 = k
                with timer("io"):
                    sol = fc.rows(fc.drive, off + k, off + min(nt, k + block + g))
                    if g > 1:  # the prompt IR of these samples (radiosity.prompt_ir)
                        rows_in = (off + k, off + min(nt, k + block + g))
                        solar = sol if fc.drive == "solar" else fc.rows("solar", *rows_in)
                        prompt = radiosity.prompt_ir(solar, fc.rows("direct", *rows_in), stepper.albedo)
                        del solar
            with timer("conduction_record"):
                if g == 1:
                    T1, ir_k = stepper.step(sol[k - w0], sol[k + 1 - w0], ir_k, rec_t[k + 1] - rec_t[k])
                    Ts, irs = (T1,), (ir_k,)
                else:
                    i0, i1 = k - w0, e + 1 - w0
                    Ts, irs = stepper.steps(rec_t[k : e + 1], sol[i0:i1], ir_k, prompt[i0:i1])
                    ir_k = irs[-1]
            for T1, ir1 in zip(Ts, irs):
                rows.append(T1, ir1)
            if every and e // every > k // every and e < nt - 1:
                rows.flush()
                checkpoints.save(e, spin_info, ir_k)
            k = e
            if report is not None:
                report(k - k0, nt - 1 - k0)
        rows.flush()


def _spin_up_relaxed(case, fc, cols, solver, stepper, spin_t, block, save_spin, progress):
    """:func:`simulate.spin_up` with the passes through the spin-up window relaxed (:class:`waveform.SpinUp`):
    the periodic state over lagged passes (the first one holding each facet's IR a day at a time, as
    the local lagged start's), or one relaxed pass (fixed spin-up). Returns (info, IR [W m-2] at the
    record's first sample)."""
    period = case.period
    T0 = period.initial_temperature_K
    if T0 is not None:
        solver.set_uniform(float(T0))
    else:
        solver.set_equilibrium(surface_K=simulate.equilibrium_start(fc, solver, stepper, len(spin_t), block))
    eps = float(case.surface.emissivity)
    spin = waveform.SpinUp(
        cols,
        solver,
        lambda a, b: fc.rows(fc.drive, a, b),
        fc.store,
        spin_t,
        block,
        eps,
        # the relaxation of a fixed spin-up's one pass (a periodic start's passes are held or lagged)
        waveform.DEFAULT_TOL_K,
        waveform.window_samples(block),
        save_spin,
    )
    years, tol_K = period.spinup_years, period.periodic_tol_K
    if period.spinup == "periodic":
        with simulate.stage(progress, "spin-up (periodic state, relaxed IR)") as report:
            info = spin.periodic(tol_K, report)
        method = (
            f"periodic steady state over {years} yr (tolerance {tol_K} K), each spin-up window driven by the "
            f"previous window's IR, the first holding each facet's IR {waveform.FIRST_PASS_HOLD_S / 86400:g} d "
            f"at a time ({spin.holds} holds; columns run per window: {', '.join(map(str, spin.columns_run))})"
        )
        return {
            "start_method": method,
            "iterations": int(info["iterations"]),
            "residual": info["residual_K"],
            "relaxation_iterations": spin.iterations,
        }, spin.ir_end
    start = f"uniform {float(T0)} K" if T0 is not None else "the equilibrium estimate"
    x0 = solver.state()
    with simulate.stage(progress, "spin-up (fixed, relaxed IR)") as report:
        spin.coupled(None if report is None else (lambda k: report(k, len(spin_t) - 1)))
    return {
        "start_method": f"fixed spin-up {years} yr from {start}, IR relaxed to {waveform.DEFAULT_TOL_K} K",
        "iterations": 1,
        "residual": np.max(np.abs(solver.state() - x0), axis=1),
        "relaxation_iterations": spin.iterations,
    }, spin.ir_end


def _record_relaxed(case, fc, cols, solver, store, block, k0, ir_k, checkpoints, spin_info, timer, progress) -> None:
    """The recorded period from sample ``k0`` by waveform relaxation, in windows of
    :func:`waveform.window_samples` samples aligned on multiples of it (a resumed run cuts the same
    windows); rows into the store, a checkpoint at the first window end past every
    ``[output] checkpoint_interval_steps`` steps."""
    nt, off, W = len(fc.times), fc.record_offset, waveform.window_samples(block)
    rec_t = simulate.seconds_since(fc.times, fc.times[0])
    every = case.output.checkpoint_interval_steps
    eps = float(case.surface.emissivity)
    rows = _RecordRows(store, block, fc.mesh.n_facets, k0 + 1, timer)
    state = solver.state()
    its = spin_info.setdefault("record_relaxation_iterations", [])
    k = k0
    with simulate.stage(progress, f"record {case.name} (relaxed IR)") as report:
        while k < nt - 1:
            k1 = min(nt - 1, (k // W + 1) * W)
            with timer("io"):
                sol = fc.rows(fc.drive, off + k, off + k1 + 1)
            with timer("conduction_record"):
                win, it, _ = waveform.relax(cols, state, rec_t[k : k1 + 1], sol, ir_k, eps)
            its.append(it)
            for j in range(1, len(win.T)):
                rows.append(win.T[j], win.ir[j])
            state, ir_k = win.end, win.ir[-1]
            if every and k1 // every > k // every and k1 < nt - 1:
                rows.flush()
                solver.set_state(state)
                checkpoints.save(k1, spin_info, ir_k)
            k = k1
            if report is not None:
                report(k - k0, nt - 1 - k0)
        rows.flush()
    solver.set_state(state)
    spin_info["relaxation"] = {
        "columns": getattr(cols, "description", "this process"),
        "tolerance_K": waveform.DEFAULT_TOL_K,
        "window_samples": W,
        "spinup_iterations_per_window": spin_info.get("relaxation_iterations", []),
        "record_iterations_per_window": its,
    }


def _write_run(case, fc, store, block, out_path, nominal, spin_info, incidence, overwrite, timer, progress) -> None:
    """``run.nc`` from the store, block by block (series as ``io.RUN_SERIES_DTYPE``)."""
    nt, ns, off, nf = len(fc.times), fc.n_spin, fc.record_offset, fc.mesh.n_facets
    save_spin = case.output.save_spinup_fluxes and ns > 0
    with timer("io"):
        _, rec_dirs = fc.split(fc.sun_dirs)
        _, rec_dist = fc.split(fc.sun_dist_m)
        extra_vars = {
            "start_residual": (
                ("facet",),
                np.asarray(spin_info["residual"], float),
                {
                    "units": "K",
                    "long_name": "max over the column of |T(end) - T(start)| of the spin-up window's last period",
                },
            )
        }
        attrs = {
            "case_name": case.name,
            "case_toml": case.toml_text,
            "albedo": float(case.surface.albedo),
            "emissivity": float(case.surface.emissivity),
            "lat_deg": float(case.location.lat_deg),
            "lon_deg": float(case.location.lon_deg),
            "property_set": case.surface.property_set,
            "nominal_profile": nominal.label,
            "geothermal_flux": float(case.surface.geothermal_flux_W_m2),
            "start_method": spin_info["start_method"],
            "spinup_iterations": int(spin_info["iterations"]),
            "spinup_years": float(case.period.spinup_years),
            "initial_temperature_K": case.period.initial_temperature_K,
            "timing_s": dict(timer.split),
            "ir_coupling": case.steps.ir_coupling if "relaxation" not in spin_info else "relaxed",
        }
        if "relaxation" in spin_info:  # waveform relaxation: where, and its iterations per window
            attrs["relaxation"] = spin_info["relaxation"]
        elif fc.F is not None:
            attrs["ir_product_samples"] = simulate.ir_product_samples(case, fc.mesh.n_facets)
        ds = io.run_dataset(
            fc.mesh, fc.times, sun_direction=rec_dirs, sun_distance_au=rec_dist / AU, attrs=attrs, extra=extra_vars
        )
        if ns:
            ds = ds.assign_coords(spinup_time=fc.spin_times)
        # (name, dims, rows, store series, offset of its rows)
        series = [
            ("solar_incident", "time", nt, "solar", off),
            ("ir_incident", "time", nt, "ir", 0),
            ("solar_direct", "time", nt, "direct", off),
            ("surface_temperature", "time", nt, "T", 0),
        ]
        if incidence:
            series.append(("solar_absorbed", "time", nt, "absorbed", off))
        if save_spin:
            series += [
                ("spinup_solar_incident", "spinup_time", ns, "solar", 0),
                ("spinup_ir_incident", "spinup_time", ns, "spin_ir", 0),
            ]
            if incidence:
                series.append(("spinup_solar_absorbed", "spinup_time", ns, "absorbed", 0))
        variables = {
            name: ((dim, "facet"), (n, nf), io.RUN_SERIES_ATTRS.get(name, {"units": "W m-2"}), io.RUN_SERIES_DTYPE)
            for name, dim, n, _, _ in series
        }
        with io.stream_dataset(
            ds,
            out_path,
            variables,
            overwrite=overwrite,
            time_rows=min(simulate.TIME_CHUNK, block),
            compression=case.output.compression,
        ) as write:
            n_blocks = sum(-(-n // block) for _, _, n, _, _ in series)
            with simulate.stage(progress, f"write {out_path.name}") as report:
                done = 0
                for name, _, n, stored, shift in series:
                    for a in range(0, n, block):
                        b = min(n, a + block)
                        write(name, (slice(a, b), slice(None)), store.read(stored, shift + a, shift + b))
                        done += 1
                        if report is not None:
                            report(done, n_blocks)
