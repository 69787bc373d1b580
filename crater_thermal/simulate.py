"""The time loop: coupled crater runs and replays of saved fluxes.

Coupled step (one flux step, ``t_k -> t_k+1``)
    Solar fluxes are known at every sample in advance (ephemeris -> direct -> scattered). The IR
    a facet receives depends on every facet's temperature; the absorbed flux is linear in time within
    a step, and its IR part at ``t_k+1`` comes from (``[steps] ir_coupling``,
    :class:`crater_thermal.radiosity.CoupledStepper`):

    * ``extrapolated`` (default): ``ir_k+1`` extrapolated linearly from the exact products
      ``F (eps sigma T^4)`` at ``t_k`` and ``t_k-1``; one conduction solve; then the exact product of
      the new temperatures, and the columns where it differs from ``ir_k+1`` by more than
      :data:`~crater_thermal.radiosity.IR_DEFECT_W_M2` (or ``IR_DEFECT_REL`` of their absorbed flux) take the step again
      with it. The first step of a sequence is a predictor-corrector step.
    * ``predictor``: conduct with IR held at ``ir_k`` -> ``T*``; ``ir_k+1 = F (eps sigma T*^4)``;
      from the same start, conduct again with ``ir_k+1`` at the end.

    Either way the saved ``ir_incident`` samples are exactly the ones the steps used, so replaying
    the nominal profile from the saved fluxes (linear between samples) reproduces the run.
Start of the recorded period
    ``periodic`` (default): the state at the start of the record is the periodic steady state of the
    forcing over the spin-up window that precedes it (``spinup_years``, default one year): the column
    profile ``x`` with ``Phi(x) = x``, ``Phi`` the coupled map over that window. The record then starts
    from ``Phi(x)``, consistent with the forcing just before it. ``fixed``: the thesis procedure,
    ``spinup_years`` of forcing from a uniform or equilibrium start.
"""

from __future__ import annotations

import contextlib
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from crater_thermal import (
    cache,
    ephemeris,
    geometry,
    io,
    radiosity,
    raytrace,
    sunlight,
    terrain,
    thermal,
    vfoperator,
    waveform,
)
from crater_thermal.constants import SIGMA

# ----------------------------------------------------------------------------- memory budget


#: Memory for (time, facet) blocks [MB] when a case does not set ``[output] chunk_mb`` (at least; see
#: :func:`default_chunk_mb`).
DEFAULT_CHUNK_MB = 256.0
#: Time samples per block that the default budget keeps up to :data:`MAX_DEFAULT_CHUNK_MB`: the
#: scattering solve and the lagged windows' IR products pass the whole operator once per block, so
#: blocks of a few samples (256 MB gives 5 at 1M facets) multiply those passes.
MIN_DEFAULT_BLOCK = 48
#: The largest default budget [MB] (48 samples up to ~1.8M facets).
MAX_DEFAULT_CHUNK_MB = 4096.0
#: Float64 (block, n_facets) arrays alive at once in the worst stage of a run (sunlight: direct,
#: scattered and the solver's work arrays; record: sunlight, T, IR and a block being merged).
_RUN_BUFFERS = 6
#: Time samples per HDF5 chunk of a written run (4 days at 4 h), and the block alignment.
TIME_CHUNK = 24


def block_rows(n_cols: int, budget_bytes: float, n_buffers: int = _RUN_BUFFERS, align: int = TIME_CHUNK) -> int:
    """Time samples per block so that ``n_buffers`` float64 (block, n_cols) arrays fit ``budget_bytes``
    (at least 1; a multiple of ``align`` when it is larger than that)."""
    rows = max(1, int(budget_bytes // (8.0 * n_buffers * max(1, n_cols))))
    return rows // align * align if rows >= align else rows


def default_chunk_mb(n_facets: int) -> float:
    """The budget [MB] for (time, facet) blocks when a case sets none: :data:`DEFAULT_CHUNK_MB`, or what
    blocks of :data:`MIN_DEFAULT_BLOCK` samples of ``n_facets`` columns need where that is more (above
    ~116k facets), at most :data:`MAX_DEFAULT_CHUNK_MB`. It depends on the mesh only, not on the machine,
    so a case gives the same blocks (and the same numbers) everywhere."""
    need = MIN_DEFAULT_BLOCK * _RUN_BUFFERS * 8.0 * max(1, int(n_facets)) / 2**20
    return float(min(MAX_DEFAULT_CHUNK_MB, max(DEFAULT_CHUNK_MB, need)))


def chunk_bytes(case, n_facets: int) -> float:
    """The case's memory budget for (time, facet) blocks [bytes] (``[output] chunk_mb``; when unset,
    :func:`default_chunk_mb` of the mesh's ``n_facets``)."""
    mb = case.output.chunk_mb
    return float(default_chunk_mb(n_facets) if mb is None else mb) * 2**20


# ----------------------------------------------------------------------------- progress


def stage(progress, description: str):
    """Context yielding the stage's ``(done, total)`` callback from a reporter, or None without one.

    ``progress`` is a reporter (``crater_thermal.progress``): ``progress(description)`` is a context
    manager yielding a ``ProgressCallback``. None (or False) means no progress reporting.
    """
    return progress(description) if progress else contextlib.nullcontext(None)


# ----------------------------------------------------------------------------- replay


def profile_densities(profile) -> tuple[float, float]:
    """(top, bottom) densities [kg m-3] of a profile, for the replay dataset's rho_top/rho_bottom."""
    dens = [float(d) for _, d in profile.layers]
    return dens[0], dens[-1]


def seconds_since(times: np.ndarray, t0: np.datetime64) -> np.ndarray:
    """Times [s] since ``t0``, float64."""
    return (np.asarray(times, "datetime64[ns]") - np.datetime64(t0, "ns")).astype(np.int64) / 1e9


def absorbed_solar_of(flux_ds, incident: str = "solar_incident", rows=slice(None), cols=slice(None)) -> np.ndarray:
    """Absorbed sunlight [W m-2] of a flux dataset (rows = samples, cols = facets): its ``solar_absorbed``
    (``spinup_solar_absorbed`` for ``incident="spinup_solar_incident"``) when present (runs with an
    incidence-dependent albedo), else ``(1 - albedo) incident`` (constant albedo, flux files of other tools)."""
    name = incident.replace("solar_incident", "solar_absorbed")
    if name in flux_ds:
        return np.asarray(flux_ds[name][rows, cols].values, float)
    return (1 - float(flux_ds.attrs["albedo"])) * flux_ds[incident][rows, cols].values


def replay_fluxes(
    flux_ds,
    profiles: Sequence,
    *,
    property_set: str | None = None,
    geothermal_flux: float | None = None,
    initial_temperature: float | None = None,
    fixed_spinup: bool = False,
    chunk_columns: int = 50_000,
    progress: Callable[[int, int], None] | None = None,
    tol_K: float = 0.01,
    chunk_mb: float = DEFAULT_CHUNK_MB,
    write: Callable | None = None,
):
    """Replay saved fluxes against several density profiles (no coupling: the IR is the saved one).

    Columns (profile x facet) are solved in batches of at most ``chunk_columns``; each batch reads the
    fluxes in blocks of time samples sized so that the forcing and temperature blocks stay within
    ``chunk_mb`` [MB] (the whole series is read once and kept when it fits). With ``write`` the
    temperatures are handed over block by block and never held whole.

    Parameters
    ----------
    flux_ds : validated flux / run dataset (``io.read_flux_dataset``; may be opened lazily).
    profiles : list of ``thermal.Profile``.
    initial_temperature : [K] uniform start, then the spin-up window's fluxes if the file has them
        (the thesis procedure). None (default): periodic steady state over the spin-up window (or over
        the record itself when the file has no spin-up fluxes).
    fixed_spinup : with no ``initial_temperature``: start from the equilibrium estimate and run the
        spin-up window once (the fixed spin-up of a run made with ``spinup = "fixed"``).
        The periodic start tests convergence column by column (``thermal.periodic_state``
        ``per_column``), so a column's result does not depend on the batching.
    write : ``write(profiles_slice, times_slice, facets_slice, T)`` receives float32 surface
        temperatures [K] of shape (profiles, times, facets); None: return them all.
    progress : optional ``progress(done, total)`` callback, in column-batch time steps (the total
        assumes about 5 periodic windows per batch and grows if more are needed).

    Returns
    -------
    T : (n_profiles, n_times, n_facets) float32 surface temperatures [K] (None with ``write``); info : dict
    """
    eps = float(flux_ds.attrs["emissivity"])
    pset = property_set or str(flux_ds.attrs.get("property_set", "apollo"))
    qgeo = float(flux_ds.attrs.get("geothermal_flux", 0.033) if geothermal_flux is None else geothermal_flux)
    times = flux_ds["time"].values
    t0 = times[0]
    t_rec = seconds_since(times, t0)
    has_spin = "spinup_solar_incident" in flux_ds
    t_spin = seconds_since(flux_ds["spinup_time"].values, t0) if has_spin else t_rec
    nt, nf = flux_ds.sizes["time"], flux_ds.sizes["facet"]
    n_prof = len(profiles)
    out = None
    if write is None:
        out = np.empty((n_prof, nt, nf), np.float32)
        write = _ArrayWriter(out)
    n_fb = max(1, min(nf, int(chunk_columns)))  # facets per batch
    per_chunk = max(1, int(chunk_columns) // n_fb)  # profiles per batch
    fixed = initial_temperature is not None or fixed_spinup
    start = (
        ("uniform" if initial_temperature is not None else "equilibrium") + " + fixed spin-up" if fixed else "periodic"
    )
    info = {"start": start, "periodic_iterations": [], "periodic_residual_K": []}
    n_batches = -(-nf // n_fb) * -(-n_prof // per_chunk)
    spin_windows = 1 if fixed else 5  # ETA: a periodic start usually takes about 4-6 windows
    work = n_batches * ((spin_windows * (len(t_spin) - 1) if (has_spin or not fixed) else 0) + nt - 1)
    counter = _WorkCounter(work, progress)
    for f0 in range(0, nf, n_fb):
        f1 = min(nf, f0 + n_fb)
        ncols_max = (f1 - f0) * min(per_chunk, n_prof)
        batch = _ReplayForcing(flux_ds, eps, f0, f1, t_rec, t_spin if has_spin else None, chunk_mb, ncols_max, counter)
        spin_which = "spin" if has_spin else "rec"
        for p0 in range(0, n_prof, per_chunk):
            chunk = list(profiles[p0 : p0 + per_chunk])
            # (nt, nfb) forcing serves every profile: column j of the solver uses forcing column j % nfb
            cols = [p for p in chunk for _ in range(f1 - f0)]
            solver = thermal.ColumnSolver(cols, property_set=pset, emissivity=eps, geothermal_flux=qgeo)
            eq = batch.equilibrium_surface(solver, spin_which) if initial_temperature is None else None
            if fixed:
                if initial_temperature is not None:
                    solver.set_uniform(float(initial_temperature))
                else:
                    solver.set_equilibrium(surface_K=eq)
                if has_spin:
                    batch.window(solver, "spin")
            else:
                solver.set_equilibrium(surface_K=eq)
                pinfo = thermal.periodic_state(
                    solver, batch.period_map(solver, spin_which), tol_K=tol_K, per_column=True
                )
                info["periodic_iterations"].append(int(pinfo["iterations"]))
                info["periodic_residual_K"].append(float(np.max(pinfo["residual_K"])))
            batch.window(solver, "rec", _ReplayRecorder(write, p0, len(chunk), f0, f1))
            del solver
    return out, info


class _ArrayWriter:
    """``write(profiles, times, facets, T)`` into a (profile, time, facet) array."""

    def __init__(self, out: np.ndarray):
        self.out = out

    def __call__(self, ps, ts, fs, T) -> None:
        self.out[ps, ts, fs] = T


class _WorkCounter:
    """Column-batch time steps done, reported as ``progress(done, total)`` (the total grows if needed)."""

    def __init__(self, total: int, progress):
        self.total, self.done, self.progress = total, 0, progress or None

    def add(self, steps: int) -> None:
        self.done += steps
        if self.progress is not None:
            self.progress(self.done, max(self.total, self.done))


class _ReplayRecorder:
    """Hands a batch's recorded block (time, profiles x facets) to ``write`` as (profiles, time, facets)
    float32 [K]; consecutive blocks overlap by one sample, which is written once."""

    def __init__(self, write, p0: int, n_profiles: int, f0: int, f1: int):
        self.write, self.p0, self.n, self.f0, self.f1 = write, p0, n_profiles, f0, f1

    def __call__(self, a: int, T) -> None:
        T = np.asarray(T, np.float32).reshape(len(T), self.n, self.f1 - self.f0).transpose(1, 0, 2)
        lo = 0 if a == 0 else 1  # blocks overlap by one sample
        self.write(slice(self.p0, self.p0 + self.n), slice(a + lo, a + len(T[0])), slice(self.f0, self.f1), T[:, lo:])


class _ReplayForcing:
    """The saved forcing of one batch of facets ``f0:f1``: absorbed flux [W m-2] of the spin-up window
    (``"spin"``) or the record (``"rec"``), read in blocks of samples sized to ``chunk_mb`` [MB] (a window
    that fits is read once and kept), and passes of a solver's columns through either window."""

    def __init__(self, flux_ds, eps, f0, f1, t_rec, t_spin, chunk_mb, ncols_max, counter: _WorkCounter):
        self.ds, self.eps, self.f0, self.f1, self.counter = flux_ds, eps, f0, f1, counter
        self.t = {"rec": t_rec, "spin": t_rec if t_spin is None else t_spin}
        self.names = {"rec": ("solar_incident", "ir_incident")}
        if t_spin is not None:
            self.names["spin"] = ("spinup_solar_incident", "spinup_ir_incident")
        # per sample: two float64 flux reads + absorbed (3 x 8 B per facet), float32 T per column
        self.rows = max(2, int(chunk_mb * 2**20 // (24 * (f1 - f0) + 8 * ncols_max)))
        self.cache: dict = {}

    def absorbed(self, which: str, k0: int, k1: int) -> np.ndarray:
        """Absorbed flux [W m-2] of samples k0..k1-1 of the window ``which``, this batch's facets."""
        sol, ir = self.names[which]
        cols = slice(self.f0, self.f1)
        if len(self.t[which]) <= self.rows:  # the whole window fits the budget: read it once
            if which not in self.cache:
                self.cache[which] = (
                    absorbed_solar_of(self.ds, sol, slice(None), cols) + self.eps * self.ds[ir][:, cols].values
                )
            return self.cache[which][k0:k1]
        return absorbed_solar_of(self.ds, sol, slice(k0, k1), cols) + self.eps * self.ds[ir][k0:k1, cols].values

    def equilibrium_surface(self, solver, which: str) -> np.ndarray:
        """The columns' equilibrium surface temperature [K], time-averaged over the window ``which``.

        The samples are summed one after the other whatever the size of the blocks read, so that the
        estimate (a column's start) does not depend on how many columns share the batch."""
        n, rows = len(self.t[which]), self.rows
        total = 0.0
        for a in range(0, n, rows):
            for q in solver.equilibrium_surface_samples(self.absorbed(which, a, min(n, a + rows))):
                total = total + q
        return total / n

    def window(self, solver, which: str, record_into=None) -> None:
        """Run the columns through a window block by block (blocks overlap by one sample)."""
        t, rows = self.t[which], self.rows
        n = len(t)
        for a in range(0, n - 1, rows - 1):
            b = min(n, a + rows)
            T = solver.run_series(t[a:b], self.absorbed(which, a, b), record=record_into is not None)
            if record_into is not None:
                record_into(a, T)
            self.counter.add(b - 1 - a)

    def period_map(self, solver, which: str):
        """The map x -> state after one pass through the window from state x (for thermal.periodic_state)."""

        def phi(x):
            solver.set_state(x)
            self.window(solver, which)
            return solver.state()

        return phi


# ----------------------------------------------------------------------------- coupled crater run


@dataclass
class Timer:
    """Accumulates wall-clock seconds per part of the computation (the benchmark's time split)."""

    split: dict = field(default_factory=dict)

    @contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.split[name] = self.split.get(name, 0.0) + time.perf_counter() - t


def case_mesh(case):
    """The mesh a case asks for: an idealized crater, a flat patch, a mesh file, or a DEM site [m]."""
    c = case.crater
    if c.mesh:
        location = (case.location.lat_deg, case.location.lon_deg)  # a DEM site mesh must be centred there
        return geometry.load_mesh(c.mesh, flip=c.flip, location=location)
    if c.kind == "flat":
        return geometry.flat_mesh()
    if c.kind == "dem":
        return terrain.site_mesh(
            c.dem,
            case.location.lat_deg,
            case.location.lon_deg,
            c.radius_km,
            resolution_m=c.resolution_m,
            outer_radius_km=c.outer_radius_km,
            outer_resolution_m=c.outer_resolution_m,
            height_kind=c.height_kind,
            max_facets=c.max_facets,
            crs=c.crs,
            xy_units=c.xy_units,
            z_units=c.z_units,
        )
    return geometry.crater_mesh(c.diameter_km, n_facets=c.facets, surround_km=c.surround_km)


def _view_factor_cache_dir():
    """Folder for cached view-factor matrices (see :mod:`crater_thermal.cache`), or None when unwritable."""
    return cache.folder("viewfactors")


@dataclass
class Forcing:
    """Everything a case's coupled run needs before conduction starts (all SI).

    The sunlight series (``direct``, ``solar``) run over spin-up + record, the join sample once:
    held in memory (``compute_forcing``), or kept on disk block by block in ``store`` (a streamed
    run: ``direct`` and ``solar`` are None, rows come from :meth:`rows`).
    """

    mesh: object
    F: object  # vfoperator.ViewFactorOperator or None (no exchange)
    spin_times: np.ndarray  # (ns,) datetime64[ns]; empty when there is no spin-up window
    times: np.ndarray  # (nt,) datetime64[ns], the recorded period
    sun_dirs: np.ndarray  # (ns + nt - 1, 3) over spin-up + record (shared sample once)
    sun_dist_m: np.ndarray
    direct: np.ndarray | None = None  # (ns + nt - 1, nf) [W m-2]
    solar: np.ndarray | None = None  # direct + scattered [W m-2]
    store: object = None  # io.SegmentStore with series "direct" and "solar" (streamed runs)
    drive: str = "solar"  # series the stepper consumes: "solar", or "absorbed" (incidence-dependent albedo)

    @property
    def n_spin(self) -> int:
        return len(self.spin_times)

    @property
    def record_offset(self) -> int:
        """Row of the record's first sample in the spin-up + record series."""
        return max(self.n_spin - 1, 0)

    def split(self, arr):
        """(spin-up part, record part) of a series over spin-up + record (the join sample is in both)."""
        ns = self.n_spin
        if ns == 0:
            return arr[:0], arr
        return arr[:ns], arr[ns - 1 :]

    def rows(self, name: str, k0: int, k1: int) -> np.ndarray:
        """Rows ``k0 .. k1 - 1`` of ``"direct"``, ``"solar"`` or ``"absorbed"`` over spin-up + record [W m-2],
        float64 (a store keeps them as :data:`crater_thermal.io.RUN_SERIES_DTYPE`)."""
        if self.store is not None:
            return self.store.read(name, k0, k1, dtype=np.float64)
        return getattr(self, name)[k0:k1]


def view_factor_settings(case) -> tuple[str, float]:
    """(method, tolerance) of a case's view factors: ``[radiation] view_factors`` and ``tolerance``."""
    method, tol = case.radiation.view_factors, case.radiation.tolerance
    return method, float(vfoperator.DEFAULT_TOLERANCE if tol is None else tol)


def case_geometry(case, timer: Timer, progress=None):
    """Mesh, ray tracer and radiation operator (None for flat ground or no visible pairs)."""
    mesh, tracer = case_scene(case, timer)
    return mesh, tracer, case_operator(case, mesh, tracer, timer, progress)


def case_scene(case, timer: Timer):
    """A case's mesh and its ray tracer."""
    with timer("geometry"):
        mesh = case_mesh(case)
        tracer = raytrace.RayTracer(mesh)
    return mesh, tracer


def case_operator(case, mesh, tracer, timer: Timer, progress=None, build=None):
    """A case's view-factor operator (``[radiation]``), None for flat ground or no visible pairs.

    ``build``: what builds it instead of :func:`vfoperator.view_factor_operator` (same arguments), e.g.
    a dask cluster's workers, each its own rows (:mod:`crater_thermal.cluster_run`).
    """
    with timer("viewfactors"):
        F = None
        if case.crater.kind != "flat":
            method, tol = view_factor_settings(case)
            kind = vfoperator.resolve_method(method, mesh.n_facets)
            with stage(progress, f"view factors ({mesh.n_facets} facets, {kind})") as report:
                F = (build or vfoperator.view_factor_operator)(
                    mesh, tracer, method=kind, tolerance=tol, cache_dir=_view_factor_cache_dir(), progress=report
                )
            if F.is_zero:
                F = None
    return F


class _Cancelled(Exception):
    """Raised inside a horizon-map thread whose caller has failed or been interrupted."""


def case_operator_and_horizons(case, mesh, tracer, timer: Timer, progress=None, build=None, horizons=True):
    """:func:`case_operator`, and at the same time, on a second thread, the case's horizon map
    (``[sun] method = "horizon"`` and ``horizons`` true; None otherwise). Returns ``(F, hmap)``.

    The two are independent and neither keeps both cores busy on its own (its Python parts hold the
    interpreter between the ray batches), so together they take less wall time than one after the other
    (docs/performance.md). The timer's "viewfactors" and "horizons" then overlap. Progress: the view
    factors' stage, then, if the horizon map is still being traced, its own stage. If the view factors
    fail or the process is interrupted, the horizon map stops at its next batch of facets (nothing of it
    is cached) and the error goes on.
    """
    if not horizons or case.sun.method != "horizon":
        return case_operator(case, mesh, tracer, timer, progress, build=build), None
    with timer("horizons"):  # read here: the second thread must not parse an .npz header (horizons.horizon_map)
        hmap = sunlight.cached_horizon_map(case.sun, mesh, tracer)
    if hmap is not None:
        return case_operator(case, mesh, tracer, timer, progress, build=build), hmap
    cancel, lock = threading.Event(), threading.Lock()
    shown: dict = {"report": None, "last": None}

    def report(done: int, total: int) -> None:
        if cancel.is_set():
            raise _Cancelled
        with lock:
            shown["last"] = (done, total)
            if shown["report"] is not None:
                shown["report"](done, total)

    def trace():
        with timer("horizons"):
            return sunlight.horizon_map(case.sun, mesh, tracer, report, read_cache=False)

    pool = ThreadPoolExecutor(1, thread_name_prefix="horizons")
    try:
        future = pool.submit(trace)
        F = case_operator(case, mesh, tracer, timer, progress, build=build)
        if future.done() or not progress:
            return F, future.result()
        with stage(progress, f"horizon map ({mesh.n_facets} facets)") as bar:
            with lock:
                shown["report"] = bar
                if bar is not None and shown["last"] is not None:
                    bar(*shown["last"])
            try:
                return F, future.result()
            finally:
                with lock:
                    shown["report"] = None
    except BaseException:
        cancel.set()
        raise
    finally:
        pool.shutdown(wait=True)


def case_sun(case, timer: Timer):
    """Spin-up and record times (datetime64[ns]) and the Sun's direction and distance [m] over both."""
    step_s = float(case.steps.flux_step_hours) * 3600.0
    with timer("ephemeris"):
        times = ephemeris.time_grid(case.period.start, case.period.end, step_s)
        spin_s = float(case.period.spinup_s)
        if spin_s > 0:
            n_spin = max(1, int(round(spin_s / step_s)))
            spin_times = times[0] - np.arange(n_spin, -1, -1) * np.timedelta64(int(step_s * 1e9), "ns")
        else:
            spin_times = times[:0]
        all_times = np.concatenate([spin_times[:-1], times]) if len(spin_times) else times
        sun_dirs, sun_dist = ephemeris.sun_in_crater_frame(
            all_times,
            case.location.lat_deg,
            case.location.lon_deg,
            moon_frame=case.sun.moon_frame,
            correction=case.sun.correction,
            moon_kernels=case.sun.moon_kernels,
        )
    return spin_times, times, sun_dirs, sun_dist


def case_sunlight(case, mesh, tracer, F, timer=None, progress=None, hmap=None) -> sunlight.Sunlight:
    """The :class:`crater_thermal.sunlight.Sunlight` of a case (its ``[sun]``, ``[surface]``, ``[scattering]``);
    ``hmap``: its horizon map when already traced (:func:`case_operator_and_horizons`)."""
    return sunlight.Sunlight(case.sun, case.surface, case.scattering, mesh, tracer, F, timer, progress, hmap=hmap)


def compute_forcing(case, timer: Timer, progress=None) -> Forcing:
    """Mesh, view factors, Sun directions, direct and scattered sunlight for a case's whole window,
    in memory (a run streams them instead: :func:`run_case`)."""
    mesh, tracer = case_scene(case, timer)
    F, hmap = case_operator_and_horizons(case, mesh, tracer, timer, progress)
    spin_times, times, sun_dirs, sun_dist = case_sun(case, timer)
    light = case_sunlight(case, mesh, tracer, F, timer, progress, hmap=hmap)
    with stage(progress, "direct sunlight") as report:
        direct, solar = light(sun_dirs, sun_dist, timer, report)
    return Forcing(mesh, F, spin_times, times, sun_dirs, sun_dist, direct, solar)


def run_window(
    stepper: radiosity.CoupledStepper,
    times_s: np.ndarray,
    solar_rows: Callable,
    block: int,
    ir0: np.ndarray | None = None,
    on_ir: Callable | None = None,
    on_step: Callable | None = None,
):
    """Coupled steps through a window of samples from the solver's state (at sample 0), block by block.

    Parameters
    ----------
    times_s : (n,) [s]
    solar_rows : ``solar_rows(k0, k1)`` -> (k1 - k0, nf) solar irradiance [W m-2] of samples k0..k1-1.
    block : samples per block (memory: a few (block, nf) float64 arrays).
    ir0 : IR at sample 0 [W m-2]; default the IR of the solver's surface temperatures.
    on_ir : ``on_ir(k0, rows)`` receives the IR [W m-2] of samples k0 .. k0 + len(rows) - 1, one call
        per block (k0 a multiple of ``block``), before the next block is computed.
    on_step : ``on_step(k)`` after sample k is computed.

    Returns
    -------
    IR [W m-2] at the last sample (the surface temperature is the solver's).
    """
    n = len(times_s)
    T = stepper.solver.surface_temperature.copy()
    ir = stepper.ir(T) if ir0 is None else ir0
    stepper.reset_history()  # the window's map depends on its start state only
    for b0 in range(0, n, block):
        b1 = min(n, b0 + block)
        sol = solar_rows(b0, min(n, b1 + 1))
        rows = np.empty((b1 - b0, len(ir))) if on_ir is not None else None
        if rows is not None:
            rows[0] = ir
        for k in range(b0, min(b1, n - 1)):
            T, ir = stepper.step(sol[k - b0], sol[k + 1 - b0], ir, times_s[k + 1] - times_s[k])
            if rows is not None and k + 1 < b1:
                rows[k + 1 - b0] = ir
            if on_step is not None:
                on_step(k + 1)
        if rows is not None:
            on_ir(b0, rows)
        del sol, rows
    return ir


def _mean_over_rows(fc: Forcing, k0: int, k1: int, block: int, fn: Callable) -> np.ndarray:
    """Time mean over sunlight rows k0..k1-1, block by block: ``fn(solar_rows)`` gives a block's mean (nf,)."""
    total = None
    for a in range(k0, k1, block):
        b = min(k1, a + block)
        part = fn(fc.rows(fc.drive, a, b)) * (b - a)
        total = part if total is None else total + part
    return total / max(1, k1 - k0)


#: ``[period] spinup_ir = "auto"`` drives the periodic spin-up windows by the previous window's IR
#: (one conduction solve per step, IR products a block at a time) from this many facets on.
LAGGED_SPINUP_MIN_FACETS = 10_000


#: ``[steps] ir_product_samples`` by default from 10,000 facets on (docs/model.md: accuracy and speed).
IR_PRODUCT_SAMPLES = 2


def ir_product_samples(case, n_facets: int) -> int:
    """Samples per IR product (``[steps] ir_product_samples``) of the record's extrapolated coupled steps
    and of the lagged spin-up windows (:meth:`_SpinUpWindow.lagged`): the default :data:`IR_PRODUCT_SAMPLES`
    from :data:`LAGGED_SPINUP_MIN_FACETS` facets on, 1 below; 1 for another coupling scheme or without
    exchange."""
    n = case.steps.ir_product_samples
    if case.steps.ir_coupling != "extrapolated":
        return 1
    if n is None:
        return IR_PRODUCT_SAMPLES if n_facets >= LAGGED_SPINUP_MIN_FACETS else 1
    return int(n)


def spinup_ir_method(method: str, F, n_facets: int) -> str:
    """ "coupled" or "lagged": the IR exchange of the periodic spin-up windows for ``[period] spinup_ir``
    ``method`` ("auto" | "coupled" | "lagged"), the operator ``F`` (None: no exchange) and the facet count."""
    if F is None:
        return "coupled"  # nothing to exchange: both are the same
    if method == "auto":
        return "lagged" if n_facets >= LAGGED_SPINUP_MIN_FACETS else "coupled"
    return method


def spin_up(case, fc, solver, stepper, spin_t, block, save_spin, progress):
    """Bring the columns to the start of the record, streaming the spin-up window in blocks.

    ``[period] spinup``: "periodic" (the periodic steady state over the window, with the window's IR
    coupled or lagged: :func:`spinup_ir_method`) or "fixed" (one pass, the thesis procedure); with no
    spin-up window, a uniform or equilibrium start. Writes the spin-up IR series to ``fc.store`` (series
    ``spin_ir``) when ``save_spin``. Returns (info, IR [W m-2] at the record's first sample, or None
    when there is no spin-up window).
    """
    period = case.period
    T0 = period.initial_temperature_K
    if len(spin_t) == 0:
        if T0 is not None:
            solver.set_uniform(float(T0))
            method = f"uniform {float(T0)} K, no spin-up"
        else:
            ts = _mean_over_rows(
                fc, 0, len(fc.sun_dirs), block, lambda sol: solver.equilibrium_surface(stepper.absorbed(sol, 0.0))
            )
            solver.set_equilibrium(surface_K=ts)
            method = "equilibrium estimate, no spin-up"
        return {"start_method": method, "iterations": 0, "residual": np.full(fc.mesh.n_facets, np.nan)}, None
    g = ir_product_samples(case, fc.mesh.n_facets) if fc.F is not None else 1
    window = _SpinUpWindow(fc, solver, stepper, spin_t, block, save_spin, period.periodic_tol_K, g)
    if T0 is not None:
        solver.set_uniform(float(T0))
    else:
        solver.set_equilibrium(surface_K=window.equilibrium_start())
    years, tol_K = period.spinup_years, period.periodic_tol_K
    if period.spinup == "periodic" and spinup_ir_method(period.spinup_ir, fc.F, fc.mesh.n_facets) == "lagged":
        with stage(progress, "spin-up (periodic state, lagged IR)") as report:
            # no Anderson mixing: successive windows have different forcing (the IR moves with them),
            # and mixing their steps cost a window (measured: 7 instead of 6 on a 1,500-facet crater)
            info = thermal.periodic_state(
                solver, window.period_map(window.lagged, report), tol_K=tol_K, anderson=False, skip=window.skip
            )
        window.save_lagged_spin_ir()
        method = (
            f"periodic steady state over {years} yr (tolerance {tol_K} K), "
            "each spin-up window driven by the previous window's IR "
            f"(columns run per window: {', '.join(map(str, window.columns_run))})"
        )
        return {
            "start_method": method,
            "iterations": int(info["iterations"]),
            "residual": info["residual_K"],
        }, window.ir_end
    if period.spinup == "periodic":
        # ETA: the shooting usually converges in about 4-6 windows; the bar grows if it needs more
        with stage(progress, "spin-up (periodic state)") as report:
            info = thermal.periodic_state(solver, window.period_map(window.coupled, report), tol_K=tol_K)
        method = f"periodic steady state over {years} yr (tolerance {tol_K} K)"
        return {
            "start_method": method,
            "iterations": int(info["iterations"]),
            "residual": info["residual_K"],
        }, window.ir_end
    # fixed spin-up, the thesis procedure
    start = f"uniform {float(T0)} K" if T0 is not None else "the equilibrium estimate"
    x0 = solver.state()
    with stage(progress, "spin-up (fixed)") as report:
        window.coupled(report, 1)
    residual = np.max(np.abs(solver.state() - x0), axis=1)
    return {
        "start_method": f"fixed spin-up {years} yr from {start}",
        "iterations": 1,
        "residual": residual,
    }, window.ir_end


def equilibrium_start(fc, solver, stepper, ns: int, block: int) -> np.ndarray:
    """Surface temperatures [K] of the equilibrium start over the first ``ns`` sunlight rows: sunlight plus
    the IR of a radiative-equilibrium crater as the first guess of the absorbed flux, averaged over them."""
    es = stepper.emissivity * SIGMA
    guess_T = _mean_over_rows(
        fc, 0, ns, block, lambda sol: np.mean((np.maximum(stepper.absorbed(sol, 0.0), 1e-3) / es) ** 0.25, axis=0)
    )
    guess_ir = stepper.ir(guess_T) if fc.F is not None else 0.0
    return _mean_over_rows(fc, 0, ns, block, lambda sol: solver.equilibrium_surface(stepper.absorbed(sol, guess_ir)))


class _SpinUpWindow:
    """Passes through the spin-up window from the solver's state, block by block, coupled or lagged.

    Coupled (:meth:`coupled`): every step exchanges IR with the current temperatures (:func:`run_window`).
    Lagged (:meth:`lagged`): every window is driven by a given IR series, so its columns are independent:
    one conduction solve per step instead of the coupled step's two, a block of samples per kernel call,
    and the IR products done a block of samples at a time. The first window holds each facet's IR for
    :data:`crater_thermal.waveform.FIRST_PASS_HOLD_S` and then takes the IR of the temperatures reached (a
    coupled window at a day's exchange interval), stepping :data:`crater_thermal.waveform.FIRST_PASS_STEP_S`
    at a time (a seed: the fixed point does not depend on it; the relaxed start's first pass,
    :meth:`crater_thermal.waveform.SpinUp.held`, is the same); every later window is driven by the IR series
    of the window before it (kept in the store as "lag_ir0" / "lag_ir1" alternately, the surface
    temperatures as "lag_T"). At the fixed point the IR is that of the periodic temperatures at every
    sample. The last window's input series is the saved spin-up IR (a replay re-runs it exactly).

    Converged columns are skipped (:meth:`skip`, the ``skip`` hook of :func:`thermal.periodic_state`):
    a column whose residual and quasi-Newton step are within the tolerance is not run again while the IR
    it receives has moved, since its last run, by less than what could move it by a quarter of the
    tolerance (the radiative bound: |dT| <= |dIR| / (4 sigma T_min^3), T_min its coldest surface
    temperature of that run); its last run's temperatures stand in the IR products.

    ``ir_end``: the IR [W m-2] at the window's last sample after the latest pass (the record's first).
    """

    def __init__(
        self, fc, solver, stepper, spin_t, block: int, save_spin: bool, tol_K: float = 0.01, product_samples: int = 1
    ):
        self.fc, self.solver, self.stepper, self.t, self.block, self.save_spin = (
            fc,
            solver,
            stepper,
            spin_t,
            block,
            save_spin,
        )
        self.n = len(spin_t)
        self.passes = 0
        self.ir_end = None
        self.lag_in, self.lag_out = None, "lag_ir0"
        self.tol_K = float(tol_K)
        self.product_samples = max(1, int(product_samples))
        nf = fc.mesh.n_facets
        self.skipped = np.zeros(nf, bool)  # columns the next lagged pass does not run
        self.drift = np.zeros(nf)  # max |IR change| [W m-2] of each column's input since its last run
        self.t_min = np.full(nf, np.inf)  # coldest surface temperature [K] of each column's last run
        #: columns run by each lagged pass (diagnostics)
        self.columns_run: list[int] = []
        #: the latest lagged pass's IR products are still to be made (:meth:`skip` makes them)
        self.products_due = False

    def equilibrium_start(self) -> np.ndarray:
        """Surface temperatures [K] of the equilibrium start (:func:`equilibrium_start`)."""
        return equilibrium_start(self.fc, self.solver, self.stepper, self.n, self.block)

    def period_map(self, one_pass, report):
        """The map x -> state after one pass from state x (what :func:`thermal.periodic_state` iterates)."""

        def phi(x):
            self.solver.set_state(x)
            one_pass(report, 5)
            return self.solver.state()

        return phi

    def _progress(self, report, expected: int):
        """A pass's ``on_step(k)`` in steps, out of ``expected`` passes (more if needed); None without a report."""
        self.passes += 1
        if report is None:
            return None
        done0 = (self.passes - 1) * (self.n - 1)
        total = max(expected, self.passes) * (self.n - 1)
        return lambda k: report(done0 + k, total)

    def _keep(self, series: str):
        def on_ir(k0, rows):
            self.fc.store.write(series, k0, rows.astype(io.RUN_SERIES_DTYPE))  # run.nc's type
            if k0 + len(rows) == self.n:
                self.ir_end = rows[-1].copy()

        return on_ir

    def coupled(self, report, expected: int) -> None:
        """One coupled pass; its IR series saved as ``spin_ir`` when ``save_spin``."""
        on_step = self._progress(report, expected)
        keep = self._keep("spin_ir") if self.save_spin else self._keep_end_only
        run_window(
            self.stepper,
            self.t,
            lambda a, b: self.fc.rows(self.fc.drive, a, b),
            self.block,
            on_ir=keep,
            on_step=on_step,
        )

    def _keep_end_only(self, k0, rows):
        if k0 + len(rows) == self.n:
            self.ir_end = rows[-1].copy()

    def _held_ir_block(self, b0: int, b1: int, ir: np.ndarray):
        """The first pass over samples b0..b1 - 1: each facet's IR held for
        :data:`crater_thermal.waveform.FIRST_PASS_HOLD_S` from ``ir`` [W m-2], then that of the temperatures
        reached (a one-vector product per hold; products of a few right-hand sides cost as much as those
        of a block, measured); stepped to the samples of :func:`crater_thermal.waveform.hold_samples` (up
        to :data:`crater_thermal.waveform.FIRST_PASS_STEP_S` apart, the solver's coarse steps set by the
        caller), the temperatures filled in so that their emission is linear in time
        (:func:`crater_thermal.waveform.between`: the relaxed start's first pass, the same numbers).
        Returns (input IR rows, surface temperature rows, the samples stepped to, their surface
        temperatures, the IR at the block's end); the IR of the samples stepped to is made by
        :meth:`_held_outputs`, a few blocks per product."""
        fc, ns, t = self.fc, self.n, self.t
        e = min(ns, b1 + 1)
        sol = fc.rows(fc.drive, b0, e)
        ir_in = np.empty((b1 - b0, len(ir)))
        known: list[int] = []  # the samples stepped to, b0 .. e - 1
        T_known: list[np.ndarray] = []
        for k, k1 in waveform.hold_spans(t, b0, b1):
            k2 = min(ns, k1 + 1)
            ir_in[k - b0 : k1 - b0] = ir
            sub = k + waveform.hold_samples(t[k:k2])
            T = self.solver.run_series(t[sub], self.stepper.absorbed(sol[sub - b0], ir[None, :]), record=True)
            known.extend(sub[:-1].tolist())
            T_known.extend(T[:-1])
            ir = self.stepper.ir(T[-1])
        known.append(int(sub[-1]))
        T_known.append(T[-1])
        Tk = np.asarray(T_known)
        rows = np.arange(b0, b1)
        T_out = waveform.between(t, known, Tk, rows, emission=True)
        return ir_in, T_out, known, Tk, ir

    def _held_outputs(self, pending: list, moved: np.ndarray) -> None:
        """The first pass's output IR of the blocks ``pending`` (``(b0, b1, known, Tk)``: the samples
        stepped to and their surface temperatures, :meth:`_held_ir_block`), from one product of all their
        ``Tk``, interpolated linearly in time between the samples stepped to: into the store
        (``lag_out``), ``moved`` (max |output - input| per column, against the input as stored) and
        :attr:`ir_end` at the window's end."""
        ir_k = self.stepper.ir_rows(np.concatenate([Tk for *_, Tk in pending]))
        o = 0
        for b0, b1, known, _ in pending:
            rows = waveform.between(self.t, known, ir_k[o : o + len(known)], np.arange(b0, b1))
            o += len(known)
            self._output_block(b0, b1, rows, moved)
            if b1 == self.n:
                self.ir_end = rows[-1].copy()
            del rows
        pending.clear()

    def _output_block(self, b0: int, b1: int, rows: np.ndarray, moved: np.ndarray) -> None:
        """Rows b0..b1-1 of a pass's output IR [W m-2] into the store (``lag_out``, in run.nc's type, in
        place) and into ``moved``: max |output - input| per column, against the input as stored."""
        self.fc.store.write(self.lag_out, b0, rows.astype(io.RUN_SERIES_DTYPE, copy=False), in_place=True)
        np.maximum(moved, np.max(np.abs(rows - self.fc.store.read(self.lag_in, b0, b1)), axis=0), out=moved)

    def _exact_samples(self, n: int) -> np.ndarray:
        """The samples (0 .. n - 1, from a block's first) whose IR :meth:`_lagged_ir_rows` takes from an exact
        product: every ``product_samples``-th and the last; all of them when ``product_samples`` is 1."""
        g = self.product_samples
        if g <= 1 or n <= 2:
            return np.arange(n)
        return np.unique(np.r_[np.arange(0, n, g), n - 1])

    def _lagged_ir_rows(self, b0: int, e: int, exact: np.ndarray) -> np.ndarray:
        """The IR rows [W m-2] of a lagged pass's surface temperatures at samples b0..e-1, from ``exact``
        ((len(idx), nf) [W m-2]), the products at the samples ``idx`` of :meth:`_exact_samples`. With
        ``product_samples`` g > 1 the IR between two of them is interpolated
        linearly in time less its prompt part (:func:`crater_thermal.radiosity.prompt_ir`, which carries
        the kinks at sunrise and sunset on the terrain a facet sees), that part added back, and kept
        within the IR of the two exact ends: the record's interpolation
        (:meth:`crater_thermal.radiosity.CoupledStepper.steps`), without its check, since a pass's
        input is only the next pass's guess and the fixed point's residual is tested on the state."""
        n = e - b0
        idx = self._exact_samples(n)
        if len(idx) == n:
            return exact
        fc = self.fc
        out = np.empty((n, exact.shape[1]))
        out[idx] = exact
        P = radiosity.prompt_ir(fc.rows("solar", b0, e), fc.rows("direct", b0, e), self.stepper.albedo)
        t = self.t[b0:e]
        for a, c in zip(idx[:-1], idx[1:]):
            if c - a < 2:
                continue
            w = ((t[a + 1 : c] - t[a]) / (t[c] - t[a]))[:, None]
            mid = P[a + 1 : c] + (1.0 - w) * (out[a] - P[a]) + w * (out[c] - P[c])
            np.clip(mid, np.minimum(out[a], out[c]), np.maximum(out[a], out[c]), out=mid)
            out[a + 1 : c] = mid
        return out

    def _product_batches(self) -> list[list[tuple[int, int]]]:
        """The blocks ``(b0, b1)`` of the window grouped so that one IR product serves each group
        (:meth:`_exact_products`): consecutive blocks while their distinct exact samples (a block's last
        is the next one's first) number at most a block's samples plus one, the right-hand sides of one
        product of every sample of a block. With ``product_samples`` 2 that is two blocks a product,
        ~49 right-hand sides instead of ~25: a product's cost grows much less than its right-hand sides
        (docs/performance.md)."""
        ns, block = self.n, self.block
        batches: list[list[tuple[int, int]]] = []
        count = 0
        for b0 in range(0, ns, block):
            b1 = min(ns, b0 + block)
            k = len(self._exact_samples(min(ns, b1 + 1) - b0))
            if batches and count + k - 1 <= block + 1:
                batches[-1].append((b0, b1))
                count += k - 1
            else:
                batches.append([(b0, b1)])
                count = k
        return batches

    def _exact_products(self, batch: list[tuple[int, int]]) -> list[np.ndarray]:
        """The exact IR [W m-2] of every block of ``batch`` at its :meth:`_exact_samples`, from one product
        of their distinct samples' surface temperatures ("lag_T")."""
        fc, ns = self.fc, self.n
        locs = [b0 + self._exact_samples(min(ns, b1 + 1) - b0) for b0, b1 in batch]
        samples = np.unique(np.concatenate(locs))
        T = np.empty((len(samples), self.skipped.size))
        for (b0, b1), loc in zip(batch, locs):
            rows = fc.store.read("lag_T", b0, min(ns, b1 + 1))  # as stored; only the rows taken become float64
            T[np.searchsorted(samples, loc)] = rows[loc - b0]
            del rows
        ir = self.stepper.ir_rows(T)
        del T
        return [ir[np.searchsorted(samples, loc)] for loc in locs]

    def lagged(self, report, expected: int) -> None:
        """One lagged pass (the first one with each facet's IR held a day at a time, in steps of up to
        :data:`crater_thermal.waveform.FIRST_PASS_STEP_S`, recording the IR series the next passes start
        from); converged columns whose input moved too little are skipped.

        A later pass only conducts: its temperatures go to the store ("lag_T") and the IR products of
        them, the next pass's input, are made by :meth:`skip`, which :func:`thermal.periodic_state`
        calls only when another pass follows; the last pass, which ends the iteration, makes none but
        that of its last sample (:attr:`ir_end`). (The relaxed start, :class:`crater_thermal.waveform.SpinUp`,
        forms its next input in its ``skip`` hook the same way.)"""
        on_step = self._progress(report, expected)
        fc, ns, block, t = self.fc, self.n, self.block, self.t
        first = self.lag_in is None
        if first:
            self.lag_in, self.lag_out = "lag_ir1", "lag_ir0"
            ir_held = self.stepper.ir(self.solver.surface_temperature)
        run = np.flatnonzero(~self.skipped)
        some = run.size < self.skipped.size
        self.columns_run.append(int(run.size))
        moved = np.zeros(self.skipped.size) if first else None  # the first pass's max |output - input|
        pending: list = []  # the first pass's blocks whose output IR is still to be made
        t_min = np.full(run.size, np.inf)
        # the first pass's coarse steps: one sub-step each, not refined
        with waveform.first_pass_steps(self.solver, first):
            for b0 in range(0, ns, block):
                b1 = min(ns, b0 + block)
                e = min(ns, b1 + 1)  # the block's samples plus the end of its last interval
                if first:
                    ir, T, known, Tk, ir_held = self._held_ir_block(b0, b1, ir_held)
                    # the windows' own series, written over the last window's (a resumed run starts the
                    # spin-up again): in place, in run.nc's type (the last input is the saved spin-up IR)
                    fc.store.write(self.lag_in, b0, ir.astype(io.RUN_SERIES_DTYPE), in_place=True)
                    del ir
                    # the output IR a few blocks per product: at most a block's samples plus one
                    # right-hand sides (as :meth:`_product_batches`), taking the next block's as this one's
                    pending.append((b0, b1, known, Tk))
                    if b1 == ns or sum(len(p[2]) for p in pending) + len(known) > block + 1:
                        self._held_outputs(pending, moved)
                    del known, Tk
                else:
                    ir = fc.store.read(self.lag_in, b0, e, dtype=np.float64)
                    sol = fc.rows(fc.drive, b0, e)
                    if some:  # the skipped columns' temperatures are those of their last run
                        T = fc.store.read("lag_T", b0, e, dtype=np.float64)
                        T[:, run] = self.solver.run_columns(
                            run, t[b0:e], self.stepper.absorbed(sol[:, run], ir[:, run])
                        )
                    else:
                        T = self.solver.run_series(t[b0:e], self.stepper.absorbed(sol, ir), record=True)
                    del sol, ir
                    if b1 == ns:  # the IR of the window's last state: the record's first sample
                        self.ir_end = self.stepper.ir_rows(T[-1:])[0]
                    T = T[: b1 - b0]
                fc.store.write("lag_T", b0, T.astype(io.RUN_SERIES_DTYPE), in_place=True)
                np.minimum(t_min, np.min(T[:, run], axis=0), out=t_min)
                del T
                if on_step is not None:
                    on_step(e - 1)
        self.t_min[run] = t_min
        if first:
            self._output_is_next_input(moved)
        self.products_due = not first

    def _next_input(self) -> None:
        """The IR products of the latest pass's temperatures ("lag_T"), a few blocks per product
        (:meth:`_product_batches`; the exact product at every ``product_samples``-th sample, interpolated
        between by :meth:`_lagged_ir_rows`): the next pass's input, and each column's input drift since its
        last run."""
        ns = self.n
        moved = np.zeros(self.skipped.size)
        for batch in self._product_batches():
            for (b0, b1), exact in zip(batch, self._exact_products(batch)):
                rows = self._lagged_ir_rows(b0, min(ns, b1 + 1), exact)[: b1 - b0].astype(io.RUN_SERIES_DTYPE)
                del exact
                self._output_block(b0, b1, rows, moved)
                del rows
        self._output_is_next_input(moved)
        self.products_due = False

    def _output_is_next_input(self, moved: np.ndarray) -> None:
        """The IR series just written (``lag_out``) becomes the next pass's input: each column's input
        drift since its last run grows by ``moved`` [W m-2] (max |output - input| per column)."""
        self.drift = np.where(self.skipped, self.drift, 0.0) + moved
        self.lag_in, self.lag_out = self.lag_out, self.lag_in

    def skip(self, converged: np.ndarray) -> np.ndarray:
        """The ``skip`` hook of :func:`thermal.periodic_state` (called when another pass follows): forms
        that pass's input (:meth:`_next_input`) and returns the converged columns it need not run (their
        input IR has moved by less than 4 sigma T_min^3 tol / 4 since their last run)."""
        if self.products_due:
            self._next_input()
        self.skipped = waveform.skippable(converged, self.drift, self.t_min, self.tol_K)
        return self.skipped

    def save_lagged_spin_ir(self) -> None:
        """Save as ``spin_ir`` the IR series the last lagged pass ran with (replays re-run the spin-up from
        it): a lagged pass's input, named ``lag_out`` after its swap; renamed, not copied, in run.nc's
        type as the passes were driven. The windows' other series are deleted (the record does not need
        them; a resumed run that starts the spin-up again makes them again)."""
        used = self.lag_in if self.products_due else self.lag_out  # (not swapped when no products followed)
        if self.save_spin:
            self.fc.store.rename(used, "spin_ir")
        self.fc.store.drop("lag_ir0", "lag_ir1", "lag_T")
