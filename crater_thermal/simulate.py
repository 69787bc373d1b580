"""The time loop: coupled crater runs and replays of saved fluxes.

Coupled step (one flux step, ``t_k -> t_k+1``)
    Solar fluxes are known at every sample in advance (ephemeris -> direct -> scattered). The IR
    a facet receives depends on every facet's temperature, so each step is a predictor-corrector:

    1. predictor: conduct with IR held at ``ir_k`` (from ``T_k``) -> ``T*``;
    2. ``ir_k+1 = F (eps sigma T*^4)``;
    3. corrector: from the same start, conduct with absorbed flux linear from sample k to k+1,
       using ``ir_k+1`` -> ``T_k+1``.

    The saved ``ir_incident`` samples are exactly the ones the corrector used, so replaying the
    nominal profile from the saved fluxes (linear between samples) reproduces the run.
Start of the recorded period
    ``periodic`` (default): the state at the start of the record is the periodic steady state of the
    forcing over the spin-up window that precedes it (``spinup_years``, default one year): the column
    profile ``x`` with ``Phi(x) = x``, ``Phi`` the coupled map over that window. The record then starts
    from ``Phi(x)``, consistent with the forcing just before it. ``fixed``: the thesis procedure,
    ``spinup_years`` of forcing from a uniform or equilibrium start.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from crater_thermal.constants import SIGMA
from crater_thermal.errors import ConfigError, FluxFileError


# ----------------------------------------------------------------------------- progress


def progress_enabled(flag: bool | None = None) -> bool:
    """Progress bars on a terminal, quiet in CI or when piped (``flag`` overrides)."""
    if flag is not None:
        return flag
    if os.environ.get("CI") or os.environ.get("CRATER_THERMAL_QUIET"):
        return False
    return sys.stderr.isatty()


@contextmanager
def progress_bar(description: str, total: float, enabled: bool | None = None):
    """A rich progress bar (with ETA) yielding ``update(advance, info)``; a no-op when disabled."""
    if not progress_enabled(enabled):
        yield lambda advance=1, info="": None
        return
    from rich.progress import (BarColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                  TextColumn("{task.fields[info]}"), transient=False) as prog:
        task = prog.add_task(description, total=total, info="")

        def update(advance=1, info=""):
            prog.update(task, advance=advance, info=info)

        yield update


# ----------------------------------------------------------------------------- coupled stepping


def emitted(T: np.ndarray, emissivity: float) -> np.ndarray:
    """Emitted flux eps sigma T^4 [W m-2]."""
    return emissivity * SIGMA * T**4


@dataclass
class CoupledStepper:
    """Advance every facet's column one flux step at a time, with IR exchange between facets.

    Parameters
    ----------
    solver : thermal.ColumnSolver with one column per facet.
    F : (nf, nf) sparse view-factor matrix, or None for no exchange (flat ground).
    albedo, emissivity : [-]
    """

    solver: object
    F: object
    albedo: float
    emissivity: float

    def ir(self, T_surface: np.ndarray) -> np.ndarray:
        """IR irradiance [W m-2] on every facet from the others' emission."""
        if self.F is None:
            return np.zeros_like(T_surface)
        return np.asarray(self.F @ emitted(T_surface, self.emissivity))

    def absorbed(self, solar: np.ndarray, ir: np.ndarray) -> np.ndarray:
        return (1.0 - self.albedo) * solar + self.emissivity * ir

    def step(self, solar_k, solar_k1, ir_k, duration_s):
        """One coupled step. Returns ``(T_surface_k1, ir_k1)``."""
        a_k = self.absorbed(solar_k, ir_k)
        if self.F is None:
            T1 = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k), duration_s)
            return T1, ir_k
        start = self.solver.state()
        T_pred = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k), duration_s)
        ir_k1 = self.ir(T_pred)
        self.solver.set_state(start)
        T1 = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k1), duration_s)
        return T1, ir_k1

    def run(self, times_s: np.ndarray, solar: np.ndarray, ir0: np.ndarray | None = None,
            record: bool = True, on_step: Callable | None = None, first_step: int = 0):
        """Run over all samples from the solver's current state (at ``times_s[first_step]``).

        Returns ``(T_surface (nt, nf), ir (nt, nf))`` when ``record``; else ``(None, ir_last)``.
        """
        nt, nf = solar.shape
        T = self.solver.surface_temperature.copy()
        ir = self.ir(T) if ir0 is None else ir0
        out_T = out_ir = None
        if record:
            out_T = np.empty((nt, nf))
            out_ir = np.empty((nt, nf))
            out_T[first_step] = T
            out_ir[first_step] = ir
        for k in range(first_step, nt - 1):
            T, ir = self.step(solar[k], solar[k + 1], ir, times_s[k + 1] - times_s[k])
            if record:
                out_T[k + 1] = T
                out_ir[k + 1] = ir
            if on_step is not None:
                on_step(k + 1, T, ir)
        return out_T, (out_ir if record else ir)


# ----------------------------------------------------------------------------- replay


def profile_densities(profile) -> tuple[float, float]:
    """(top, bottom) densities [kg m-3] of a profile, for the replay dataset's rho_top/rho_bottom."""
    dens = [float(d) for _, d in profile.layers]
    return dens[0], dens[-1]


def seconds_since(times: np.ndarray, t0: np.datetime64) -> np.ndarray:
    """Times [s] since ``t0``, float64."""
    return (np.asarray(times, "datetime64[ns]") - np.datetime64(t0, "ns")).astype(np.int64) / 1e9


def replay_fluxes(flux_ds, profiles: Sequence, *, property_set: str | None = None,
                  geothermal_flux: float | None = None, initial_temperature: float | None = None,
                  fixed_spinup: bool = False, chunk_columns: int = 50_000, progress: bool | None = None,
                  tol_K: float = 0.01):
    """Replay saved fluxes against several density profiles (no coupling: the IR is the saved one).

    Parameters
    ----------
    flux_ds : validated flux / run dataset (``io.read_flux_dataset``).
    profiles : list of ``thermal.Profile``.
    initial_temperature : [K] uniform start, then the spin-up window's fluxes if the file has them
        (the thesis procedure). None (default): periodic steady state over the spin-up window (or over
        the record itself when the file has no spin-up fluxes).
    fixed_spinup : with no ``initial_temperature``: start from the equilibrium estimate and run the
        spin-up window once (the fixed spin-up of a run made with ``spinup = "fixed"``).

    Returns
    -------
    T : (n_profiles, n_times, n_facets) float32 surface temperatures [K]; info : dict
    """
    from crater_thermal import thermal

    albedo = float(flux_ds.attrs["albedo"])
    eps = float(flux_ds.attrs["emissivity"])
    pset = property_set or str(flux_ds.attrs.get("property_set", "apollo"))
    qgeo = float(flux_ds.attrs.get("geothermal_flux", 0.033) if geothermal_flux is None else geothermal_flux)
    times = flux_ds["time"].values
    t0 = times[0]
    t_rec = seconds_since(times, t0)
    abs_rec = (1 - albedo) * flux_ds["solar_incident"].values + eps * flux_ds["ir_incident"].values
    has_spin = "spinup_solar_incident" in flux_ds
    if has_spin:
        t_spin = seconds_since(flux_ds["spinup_time"].values, t0)
        abs_spin = ((1 - albedo) * flux_ds["spinup_solar_incident"].values
                    + eps * flux_ds["spinup_ir_incident"].values)
    nt, nf = abs_rec.shape
    n_prof = len(profiles)
    out = np.empty((n_prof, nt, nf), np.float32)
    per_chunk = max(1, chunk_columns // nf)
    fixed = initial_temperature is not None or fixed_spinup
    start = ("uniform" if initial_temperature is not None else "equilibrium") + " + fixed spin-up" if fixed \
        else "periodic"
    info = {"start": start,
            "periodic_iterations": [], "periodic_residual_K": []}
    with progress_bar("replay", n_prof, progress) as update:
        for p0 in range(0, n_prof, per_chunk):
            chunk = list(profiles[p0:p0 + per_chunk])
            cols = [p for p in chunk for _ in range(nf)]
            solver = thermal.ColumnSolver(cols, property_set=pset, emissivity=eps, geothermal_flux=qgeo)
            spin_t, spin_a = (t_spin, abs_spin) if has_spin else (t_rec, abs_rec)
            # (nt, nf) forcing serves every profile: column j of the solver uses forcing column j % nf
            if fixed:
                if initial_temperature is not None:
                    solver.set_uniform(float(initial_temperature))
                else:
                    solver.set_equilibrium(spin_a)
                if has_spin:
                    solver.run_series(spin_t, spin_a, record=False)
            else:
                solver.set_equilibrium(spin_a)
                pinfo = solver.periodic_start(spin_t, spin_a, tol_K=tol_K)
                info["periodic_iterations"].append(int(pinfo["iterations"]))
                info["periodic_residual_K"].append(float(np.max(pinfo["residual_K"])))
            T = solver.run_series(t_rec, abs_rec)
            out[p0:p0 + len(chunk)] = T.reshape(nt, len(chunk), nf).transpose(1, 0, 2)
            update(len(chunk), info=f"{p0 + len(chunk)}/{n_prof} profiles")
    return out, info


# ----------------------------------------------------------------------------- coupled crater run


@dataclass
class Timer:
    """Accumulates wall-clock seconds per part of the computation (the benchmark's time split)."""

    split: dict = field(default_factory=dict)

    @contextmanager
    def __call__(self, name: str):
        import time

        t = time.perf_counter()
        try:
            yield
        finally:
            self.split[name] = self.split.get(name, 0.0) + time.perf_counter() - t


def case_mesh(case):
    """The mesh a case asks for: an idealized crater, a flat patch, a mesh file, or a DEM site [m]."""
    from crater_thermal import geometry

    c = case.crater
    if getattr(c, "mesh", None):
        return geometry.load_mesh(c.mesh)
    if getattr(c, "kind", "crater") == "flat":
        return geometry.flat_mesh()
    if getattr(c, "kind", "crater") == "dem":
        from crater_thermal import terrain

        return terrain.site_mesh(c.dem, case.location.lat_deg, case.location.lon_deg, c.radius_km,
                                 resolution_m=c.resolution_m, outer_radius_km=c.outer_radius_km,
                                 outer_resolution_m=c.outer_resolution_m, height_kind=c.height_kind,
                                 max_facets=c.max_facets)
    return geometry.crater_mesh(c.diameter_km, n_facets=c.facets, surround_km=c.surround_km)


def _checkpoint_path(out_path) -> str:
    return str(out_path) + ".checkpoint.npz"


DEFAULT_REPLAY_PROFILES = ("1300/1800", "800/1100", "rock")


def resolve_profiles(labels: Sequence[str], density_grid: str | None = None, allow_inverted: bool = False):
    """Profiles from labels and an optional density grid, without duplicates (order kept)."""
    from crater_thermal import thermal

    labels = list(labels)
    if not labels and not density_grid:
        labels = list(DEFAULT_REPLAY_PROFILES)
    profiles = [thermal.parse_profile(lab, allow_inverted=allow_inverted) for lab in labels]
    if density_grid:
        profiles += list(thermal.density_grid_profiles(density_grid))
    seen, unique = set(), []
    for p in profiles:
        if p.label not in seen:
            seen.add(p.label)
            unique.append(p)
    return unique


def replay_file(flux_path, labels: Sequence[str], *, density_grid=None, initial_temperature=None,
                fixed_spinup=False, property_set=None, allow_inverted=False, output, overwrite=False,
                progress=None):
    """``crater-thermal replay``: validate inputs, replay, write the replay dataset atomically."""
    from crater_thermal import io

    io.check_output(output, overwrite)  # fail before any work
    if initial_temperature is not None and not (1.0 <= initial_temperature <= 1000.0):
        raise ConfigError(f"--initial-temperature {initial_temperature} K outside [1, 1000] K")
    profiles = resolve_profiles(labels, density_grid, allow_inverted)
    ds = io.read_flux_dataset(flux_path)
    T, info = replay_fluxes(ds, profiles, property_set=property_set, initial_temperature=initial_temperature,
                            fixed_spinup=fixed_spinup, progress=progress)
    tops, bottoms = zip(*(profile_densities(p) for p in profiles))
    out = io.replay_dataset(ds, [p.label for p in profiles], tops, bottoms, T,
                            attrs={"replay_start": info["start"],
                                   "periodic_iterations": info["periodic_iterations"] or None,
                                   "periodic_residual_K": info["periodic_residual_K"] or None,
                                   "initial_temperature_K": initial_temperature,
                                   "ir_assumption": "saved nominal IR (thesis 7.2)"})
    return io.write_dataset_atomic(out, output, overwrite)


def _view_factor_cache_dir() -> str:
    """Folder for cached view-factor matrices (``CRATER_THERMAL_CACHE`` or ~/.cache/crater_thermal)."""
    base = os.environ.get("CRATER_THERMAL_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "crater_thermal")
    return os.path.join(base, "viewfactors")


def _horizon_cache_dir() -> str:
    """Folder for cached horizon maps (next to the view factors)."""
    return os.path.join(os.path.dirname(_view_factor_cache_dir()), "horizons")


def direct_sunlight(sun, mesh, tracer, sun_dirs, sun_dist, progress=None, timer: Timer | None = None) -> np.ndarray:
    """Direct irradiance (nt, nf) [W m-2] with the case's ``[sun]`` settings (``method`` "rays" or "horizon").

    The horizon map's build (or cache read) is timed as "horizons", the per-step fluxes as "direct".
    """
    from crater_thermal import illumination

    timer = timer or Timer()
    method = getattr(sun, "method", "horizon")
    if method == "horizon":
        from crater_thermal import horizons

        with timer("horizons"), progress_bar("horizon map", mesh.n_facets, progress_enabled(progress)) as bar:
            done = [0]

            def report(n_done, total):
                bar(n_done - done[0])
                done[0] = n_done

            hmap = horizons.horizon_map(mesh, tracer, n_azimuths=getattr(sun, "horizon_azimuths", None)
                                        or horizons.DEFAULT_N_AZIMUTHS, cache_dir=_horizon_cache_dir(),
                                        progress=report)
        with timer("direct"):
            return horizons.direct_irradiance_horizon(mesh, hmap, sun_dirs, sun_dist,
                                                      solar_constant=sun.solar_constant_W_m2,
                                                      law=None if sun.point_sun else sun.limb_darkening)
    disk = None if sun.point_sun else illumination.sun_disk(
        **({"n_rings": sun.n_rings} if getattr(sun, "n_rings", None) else {}), law=sun.limb_darkening)
    with timer("direct"):
        return illumination.direct_irradiance(mesh, tracer, sun_dirs, sun_dist,
                                              solar_constant=sun.solar_constant_W_m2, disk=disk,
                                              progress=progress_enabled(progress))


@dataclass
class Forcing:
    """Everything a case's coupled run needs before conduction starts (all SI)."""

    mesh: object
    F: object  # sparse (nf, nf) or None
    spin_times: np.ndarray  # (ns,) datetime64[ns]; empty when there is no spin-up window
    times: np.ndarray  # (nt,) datetime64[ns], the recorded period
    sun_dirs: np.ndarray  # (ns + nt - 1, 3) over spin-up + record (shared sample once)
    sun_dist_m: np.ndarray
    direct: np.ndarray  # (ns + nt - 1, nf) [W m-2]
    solar: np.ndarray  # direct + scattered [W m-2]

    @property
    def n_spin(self) -> int:
        return len(self.spin_times)

    def split(self, arr):
        """(spin-up part, record part) of a series over spin-up + record (the join sample is in both)."""
        ns = self.n_spin
        if ns == 0:
            return arr[:0], arr
        return arr[:ns], arr[ns - 1:]


def compute_forcing(case, timer: Timer, progress=None) -> Forcing:
    """Mesh, view factors, Sun directions, direct and scattered sunlight for a case's whole window."""
    from crater_thermal import ephemeris, geometry, illumination, radiosity, raytrace, viewfactors  # noqa: F401

    with timer("geometry"):
        mesh = case_mesh(case)
        tracer = raytrace.RayTracer(mesh)
    with timer("viewfactors"):
        F = None
        if getattr(case.crater, "kind", "crater") != "flat":
            F = viewfactors.view_factor_matrix(mesh, tracer, cache_dir=_view_factor_cache_dir(),
                                               progress=progress_enabled(progress))
            if F.nnz == 0:
                F = None
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
            all_times, case.location.lat_deg, case.location.lon_deg, moon_frame=case.sun.moon_frame,
            correction=case.sun.correction, moon_kernels=case.sun.moon_kernels)
    direct = direct_sunlight(case.sun, mesh, tracer, sun_dirs, sun_dist, progress, timer)  # "horizons", "direct"
    with timer("radiosity"):
        if F is None:
            solar = direct
        else:
            scat = radiosity.ScatteringSolver(F, case.surface.albedo, method=case.scattering.method,
                                              n_bounces=case.scattering.n_bounces)
            solar = scat.solar_incident(direct)
    return Forcing(mesh, F, spin_times, times, sun_dirs, sun_dist, direct, solar)


def _case_fingerprint(case) -> str:
    import hashlib

    return hashlib.sha256(case.toml_text.encode()).hexdigest()[:16]


def run_case(case, out_path, *, resume: bool = False, overwrite: bool = False, progress: bool | None = None,
             timer: Timer | None = None):
    """``crater-thermal run``: the coupled crater simulation of a case, written to ``out_path``.

    The state is checkpointed every ``case.output.checkpoint_interval_steps`` flux steps (and when
    the spin-up ends) to ``OUT.checkpoint.npz``; ``resume=True`` continues from it and gives the same
    numbers as an uninterrupted run. Returns the output path.
    """
    from pathlib import Path

    from crater_thermal import io, thermal

    out_path = Path(out_path)
    ckpt_path = Path(_checkpoint_path(out_path))
    fingerprint = _case_fingerprint(case)
    ckpt = None
    if resume and ckpt_path.exists():
        try:
            ckpt = dict(np.load(ckpt_path, allow_pickle=False))
        except Exception as exc:
            raise FluxFileError(f"checkpoint {ckpt_path} is unreadable ({type(exc).__name__}); "
                                "run again without --resume") from None
        if str(ckpt["fingerprint"]) != fingerprint:
            raise ConfigError(f"checkpoint {ckpt_path} belongs to a different case; run without --resume")
    if ckpt is None:
        io.check_output(out_path, overwrite)
    nominal = thermal.parse_profile(case.surface.nominal_profile)  # before any ray is traced
    timer = timer or Timer()
    fc = compute_forcing(case, timer, progress)
    mesh, nf = fc.mesh, fc.mesh.n_facets
    albedo, eps = float(case.surface.albedo), float(case.surface.emissivity)
    solver_kw = {}
    if getattr(case.steps, "conduction_step_s", None):
        solver_kw["dt_max"] = float(case.steps.conduction_step_s)
    solver = thermal.ColumnSolver([nominal] * nf, property_set=case.surface.property_set, emissivity=eps,
                                  geothermal_flux=case.surface.geothermal_flux_W_m2, **solver_kw)
    stepper = CoupledStepper(solver, fc.F, albedo, eps)
    spin_solar, rec_solar = fc.split(fc.solar)
    t0 = fc.times[0]
    spin_t = seconds_since(fc.spin_times, t0)
    rec_t = seconds_since(fc.times, t0)
    nt = len(fc.times)
    every = int(getattr(case.output, "checkpoint_interval_steps", 0) or 0)
    mode = case.period.spinup
    T0 = case.period.initial_temperature_K
    tol_K = case.period.periodic_tol_K

    def save_ckpt(phase, k, out_T, out_ir, extra):
        with timer("io"):
            io.save_npz_atomic(ckpt_path, fingerprint=np.array(fingerprint), phase=np.array(phase), k=np.array(k),
                               state=solver.state(), out_T=out_T[:k + 1], out_ir=out_ir[:k + 1], **extra)

    spin_info: dict = {}
    spin_ir = None
    if ckpt is not None:
        spin_ir = ckpt.get("spin_ir")
        spin_info = {"start_method": str(ckpt["start_method"]), "iterations": int(ckpt["iterations"]),
                     "residual": ckpt["residual"]}
    else:
        with timer("conduction_spinup"):
            spin_info, spin_ir = _spin_up(case, fc, solver, stepper, spin_t, spin_solar, mode, T0, tol_K,
                                          progress)
    # ---- recorded period
    out_T = np.empty((nt, nf))
    out_ir = np.empty((nt, nf))
    if ckpt is not None:
        k0 = int(ckpt["k"])
        out_T[:k0 + 1] = ckpt["out_T"]
        out_ir[:k0 + 1] = ckpt["out_ir"]
        solver.set_state(ckpt["state"])
    else:
        k0 = 0
        out_T[0] = solver.surface_temperature
        out_ir[0] = spin_ir[-1] if spin_ir is not None and len(spin_ir) else stepper.ir(out_T[0])
    extra = {"start_method": np.array(spin_info["start_method"]), "iterations": np.array(spin_info["iterations"]),
             "residual": np.asarray(spin_info["residual"], float)}
    if spin_ir is not None:
        extra["spin_ir"] = spin_ir
    if ckpt is None:
        save_ckpt("record", 0, out_T, out_ir, extra)
    with progress_bar("run " + case.name, nt - 1 - k0, progress) as update:
        with timer("conduction_record"):
            for k in range(k0, nt - 1):
                out_T[k + 1], out_ir[k + 1] = stepper.step(rec_solar[k], rec_solar[k + 1], out_ir[k],
                                                           rec_t[k + 1] - rec_t[k])
                if every and (k + 1) % every == 0 and k + 1 < nt - 1:
                    save_ckpt("record", k + 1, out_T, out_ir, extra)
                update(1, info=str(fc.times[k + 1])[:16])
    # ---- write
    with timer("io"):
        spin_direct, rec_direct = fc.split(fc.direct)
        spin_dirs, rec_dirs = fc.split(fc.sun_dirs)
        _, rec_dist = fc.split(fc.sun_dist_m)
        from crater_thermal.constants import AU

        extra_vars = {"start_residual": (("facet",), np.asarray(spin_info["residual"], float),
                                         {"units": "K", "long_name": "max over the column of |T(end) - T(start)| "
                                          "of the spin-up window's last period"})}
        if getattr(case.output, "save_spinup_fluxes", True) and fc.n_spin:
            extra_vars["spinup_solar_incident"] = (("spinup_time", "facet"), spin_solar, {"units": "W m-2"})
            extra_vars["spinup_ir_incident"] = (("spinup_time", "facet"), spin_ir, {"units": "W m-2"})
        ds = io.run_dataset(
            mesh, fc.times, solar_incident=rec_solar, ir_incident=out_ir, solar_direct=rec_direct,
            surface_temperature=out_T, sun_direction=rec_dirs, sun_distance_au=rec_dist / AU,
            attrs={"case_name": case.name, "case_toml": case.toml_text, "albedo": albedo, "emissivity": eps,
                   "lat_deg": float(case.location.lat_deg), "lon_deg": float(case.location.lon_deg),
                   "property_set": case.surface.property_set, "nominal_profile": nominal.label,
                   "geothermal_flux": float(case.surface.geothermal_flux_W_m2),
                   "start_method": spin_info["start_method"], "spinup_iterations": int(spin_info["iterations"]),
                   "spinup_years": float(case.period.spinup_years),
                   "initial_temperature_K": T0, "timing_s": dict(timer.split)},
            extra=extra_vars)
        if fc.n_spin:
            ds = ds.assign_coords(spinup_time=fc.spin_times)
        io.write_dataset_atomic(ds, out_path, overwrite=True if ckpt is not None else overwrite)
    if ckpt_path.exists():
        ckpt_path.unlink()
    return out_path


def _spin_up(case, fc, solver, stepper, spin_t, spin_solar, mode, T0, tol_K, progress):
    """Bring the columns to the start of the record. Returns (info, spin-up IR series or None)."""
    from crater_thermal import thermal

    ns = len(spin_t)
    if ns == 0:
        if T0 is not None:
            solver.set_uniform(float(T0))
            method = f"uniform {float(T0)} K, no spin-up"
        else:
            solver.set_equilibrium(stepper.absorbed(fc.solar, 0.0 * fc.solar))
            method = "equilibrium estimate, no spin-up"
        return {"start_method": method, "iterations": 0, "residual": np.full(fc.mesh.n_facets, np.nan)}, None
    # first guess of the absorbed flux: sunlight plus the IR of a radiative-equilibrium crater
    guess_T = (np.maximum(stepper.absorbed(spin_solar, 0.0), 1e-3) / (stepper.emissivity * SIGMA)) ** 0.25
    guess_ir = stepper.ir(guess_T.mean(axis=0)) if fc.F is not None else 0.0
    absorbed_guess = stepper.absorbed(spin_solar, guess_ir)
    holder = {}

    def period_map(x):
        solver.set_state(x)
        _, ir = stepper.run(spin_t, spin_solar, record=True)
        holder["ir"] = ir
        return solver.state()

    if mode == "periodic":
        if T0 is not None:
            solver.set_uniform(float(T0))
        else:
            solver.set_equilibrium(absorbed_guess)
        info = thermal.periodic_state(solver, period_map, tol_K=tol_K)
        x_end = period_map(solver.state()) if "ir" not in holder else None
        if x_end is not None:
            solver.set_state(x_end)
        residual = np.asarray(info["residual_K"], float)
        return {"start_method": f"periodic steady state over {case.period.spinup_years} yr "
                                f"(tolerance {tol_K} K)", "iterations": int(info["iterations"]),
                "residual": residual}, holder["ir"]
    # fixed spin-up, the thesis procedure
    if T0 is not None:
        solver.set_uniform(float(T0))
        method = f"fixed spin-up {case.period.spinup_years} yr from uniform {float(T0)} K"
    else:
        solver.set_equilibrium(absorbed_guess)
        method = f"fixed spin-up {case.period.spinup_years} yr from the equilibrium estimate"
    x0 = solver.state()
    _, ir = stepper.run(spin_t, spin_solar, record=True)
    residual = np.max(np.abs(solver.state() - x0), axis=1)
    return {"start_method": method, "iterations": 1, "residual": residual}, ir
