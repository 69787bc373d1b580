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
                  chunk_columns: int = 50_000, progress: bool | None = None, tol_K: float = 0.01):
    """Replay saved fluxes against several density profiles (no coupling: the IR is the saved one).

    Parameters
    ----------
    flux_ds : validated flux / run dataset (``io.read_flux_dataset``).
    profiles : list of ``thermal.Profile``.
    initial_temperature : [K] uniform start, then the spin-up window's fluxes if the file has them
        (the thesis procedure). None (default): periodic steady state over the spin-up window (or over
        the record itself when the file has no spin-up fluxes).

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
    info = {"start": "uniform" if initial_temperature is not None else "periodic",
            "periodic_iterations": [], "periodic_residual_K": []}
    with progress_bar("replay", n_prof, progress) as update:
        for p0 in range(0, n_prof, per_chunk):
            chunk = list(profiles[p0:p0 + per_chunk])
            cols = [p for p in chunk for _ in range(nf)]
            solver = thermal.ColumnSolver(cols, property_set=pset, emissivity=eps, geothermal_flux=qgeo)
            spin_t, spin_a = (t_spin, abs_spin) if has_spin else (t_rec, abs_rec)
            spin_a = np.tile(spin_a, (1, len(chunk)))
            if initial_temperature is not None:
                solver.set_uniform(float(initial_temperature))
                if has_spin:
                    solver.run_series(spin_t, spin_a)
            else:
                solver.set_equilibrium(spin_a)
                pinfo = solver.periodic_start(spin_t, spin_a, tol_K=tol_K)
                info["periodic_iterations"].append(int(pinfo["iterations"]))
                info["periodic_residual_K"].append(float(np.max(pinfo["residual_K"])))
            T = solver.run_series(t_rec, np.tile(abs_rec, (1, len(chunk))))
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
    """The mesh a case asks for: an idealized crater, a flat patch, or a mesh file [m]."""
    from crater_thermal import geometry

    c = case.crater
    if getattr(c, "mesh", None):
        return geometry.load_mesh(c.mesh)
    if getattr(c, "kind", "crater") == "flat":
        return geometry.flat_mesh()
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
                property_set=None, allow_inverted=False, output, overwrite=False, progress=None):
    """``crater-thermal replay``: validate inputs, replay, write the replay dataset atomically."""
    from crater_thermal import io

    io.check_output(output, overwrite)  # fail before any work
    if initial_temperature is not None and not (1.0 <= initial_temperature <= 1000.0):
        raise ConfigError(f"--initial-temperature {initial_temperature} K outside [1, 1000] K")
    profiles = resolve_profiles(labels, density_grid, allow_inverted)
    ds = io.read_flux_dataset(flux_path)
    T, info = replay_fluxes(ds, profiles, property_set=property_set, initial_temperature=initial_temperature,
                            progress=progress)
    tops, bottoms = zip(*(profile_densities(p) for p in profiles))
    out = io.replay_dataset(ds, [p.label for p in profiles], tops, bottoms, T,
                            attrs={"replay_start": info["start"],
                                   "periodic_iterations": info["periodic_iterations"] or None,
                                   "periodic_residual_K": info["periodic_residual_K"] or None,
                                   "initial_temperature_K": initial_temperature,
                                   "ir_assumption": "saved nominal IR (thesis 7.2)"})
    return io.write_dataset_atomic(out, output, overwrite)
