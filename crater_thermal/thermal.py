"""Subsurface heat conduction under every facet: density profiles, grid, column solver,
periodic steady state.

Model (thesis 7.1.2, with the conventions of docs/physics.md)
--------------------------------------------------------
Each facet has an independent 1-D column, z positive downward, 2 m deep:

    rho c(T) dT/dt = d/dz (k(rho, T) dT/dz)
    surface (z = 0):  absorbed(t) - eps sigma Ts^4 + k dT/dz|0 = 0
    bottom (z = 2 m): the geothermal flux G enters the column (k dT/dz = G).

``absorbed = (1 - A) Q_solar + eps Q_ir`` is linear in time between flux samples.

Discretisation
--------------
* Space: vertex-centred finite volumes on a geometric grid (:func:`make_grid`): node 0 at the
  surface (a half cell with heat capacity), nodes exactly on every layer interface (2 cm), the
  last node at the bottom. Link conductances use k at the link's mean temperature and the
  link's mean density; node masses integrate the density profile exactly.
* Time: TR-BDF2 (a trapezoidal stage to t + (2 - sqrt 2) dt, then BDF2 to t + dt; Bank et al.
  1985), the default; backward Euler as an option. Both are implicit and L-stable, which
  matters: rock columns have kappa dt / dz0^2 ~ 1e3 at the 4-hour flux step, where
  Crank-Nicolson rings (amplification -> -1). Properties (k, c) are lagged: the TR stage uses
  them at the start of the step, the BDF2 stage at the end-of-step temperature extrapolated
  from the two known levels. The surface emission is implicit and solved exactly by a scalar
  Newton iteration after a bottom-up Thomas elimination. In the TR stage a column whose
  trapezoidal emission has no physical root (an extreme cooling transient, e.g. a 250 K start in
  the dark) takes the emission implicit for that stage instead.
  Accuracy at the defaults (dt = 4 h, 35 nodes), against a fine reference (dt = 450 s, first
  layer / 4, growth 1.03), half a year of synthetic forcing (bench/conduction_accuracy.py):
  settled nights (Sun, or for the floor the lit walls' IR, down >= 1 day) within 0.03 K on
  regolith floors and walls, 0.08 K on sunlit rock; in the first day after sunset on sunlit
  walls <= 0.18 K (0.6 K without the adaptive refinement of the sunrise / sunset kink steps,
  :data:`DEFAULT_ADAPT_K`, decided and done per column, +18% wall time on a half-sunlit
  synthetic crater). Backward Euler at 4 h: 0.15-0.31 K in settled nights.
  Hayne et al. 2017 equator validation (tests/test_periodic.py): 385.2 / 100.3 / 93.8 K vs
  heat1d 388.5 / 100.2 / 93.7 K (noon / midnight / night minimum).
  The scheme conserves energy exactly for its lagged capacities; against the true enthalpy
  (:meth:`ColumnSolver.stored_heat`) the defect is O(c' dT^2) per step: <= 5.3e-4 of the absorbed
  energy over a year (sunlit rock), <= 4e-4 on regolith (tests/test_thermal.py).
* Defaults (:data:`DEFAULT_SKIN_FRACTION` = 0.1 of the 3.6 cm diurnal skin depth, i.e. a 3.6 mm
  first layer; :data:`DEFAULT_GROWTH` = 1.15, giving 35 nodes; :data:`DEFAULT_DT_MAX` = 4 h, the
  flux step) come from the convergence study kept as a test (halving dt and the first layer, or
  growth 1.1, changes settled night-time surface temperatures by < 0.05 K) and from
  bench/conduction_accuracy.py (growth 1.2 leaves 0.12 K on sunlit rock, 1.15 0.08 K).

Periodic steady state
---------------------
:func:`periodic_state` (quasi-Newton shooting with a per-column linearised Jacobian and Anderson
mixing) reaches max |Phi(x) - x| <= 0.01 K in 4-5 periods from the equilibrium estimate, 100 K or
250 K starts (a plain spin-up needs 300-400 years for the same accuracy on sunlit walls: the 2 m
column's slowest mode decays over ~30-80 years). Its cost is a few plain periods plus the linear
algebra of the Jacobians; the measured times are in ``docs/performance.md``.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence

# Numba's OpenMP threading layer spin-waits between parallel regions by default; on a shared,
# oversubscribed machine that turns a 0.4 ms advance() of 502 columns into ~9 ms (measured).
# Passive waiting costs one thread wake-up per parallel call instead. The user's setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from crater_thermal import materials, profiles
from crater_thermal.constants import (
    COLUMN_DEPTH,
    EMISSIVITY,
    GEOTHERMAL_FLUX,
    LUNAR_DAY,
    SIGMA,
    TOP_LAYER_THICKNESS,
)
from crater_thermal.errors import ConfigError, ProfileError, SolverError
from crater_thermal.kernels import conduction as _k
from crater_thermal.profiles import HAYNE_LABEL, Profile

__all__ = [
    "Profile",
    "parse_profile",
    "density_grid_profiles",
    "Grid",
    "make_grid",
    "skin_depth",
    "ColumnSolver",
    "periodic_state",
    "DEFAULT_DT_MAX",
    "DEFAULT_SKIN_FRACTION",
    "DEFAULT_GROWTH",
]

#: Default maximum conduction sub-step [s]: the thesis's 4-hour flux step (convergence study).
DEFAULT_DT_MAX = 14_400.0
#: Default local-error threshold [K] of the adaptive sub-step refinement (kernel ``run_columns``):
#: at 0.5 K it redoes 2-4% of the sub-steps of a sunlit wall in 4 parts (the sunrise / sunset
#: kinks), almost none in shadow, and cuts the first-day-after-sunset error on walls from 0.6 to
#: 0.15-0.18 K (bench/conduction_accuracy.py); wall time +18% on a synthetic crater with half
#: its facets sunlit at random phases (only the flagged columns are recomputed).
DEFAULT_ADAPT_K = 0.5
#: Default first-layer thickness as a fraction of the diurnal skin depth [-] (convergence study).
DEFAULT_SKIN_FRACTION = 0.1
#: Default geometric growth factor of layer thickness with depth [-] (convergence study).
DEFAULT_GROWTH = 1.15
#: Temperature [K] at which the nominal top-layer properties set the skin depth for the grid.
GRID_T_REF = 250.0

#: time schemes of the kernel
SCHEMES = {"euler": _k.SCHEME_BE, "trbdf2": _k.SCHEME_TRBDF2}


# ----------------------------------------------------------------------------- profiles


# Profile, its labels and their limits are defined in crater_thermal.profiles (base layer: the case
# file is validated with the same parser at load time); here the regolith densities outside thesis
# Table 7.2 also get materials' DensityExtrapolationWarning.


def _check_profile(p: Profile, allow_inverted: bool, warn: bool = True, checked: bool = False) -> Profile:
    if not checked:  # a Profile built elsewhere; profiles.parse_profile has already checked its own
        profiles.check_profile(p, allow_inverted)
    if warn and p.material == "regolith":
        materials.check_density([r for _, r in p.layers], name=f"profile {p.label!r} density", warn=True)
    return p


def parse_profile(spec, allow_inverted: bool = False, label: str | None = None, warn: bool = True) -> Profile:
    """:func:`crater_thermal.profiles.parse_profile` (labels such as ``"1300/1800"``, ``"rock"``,
    ``"hayne2017"``, or a layer list of (bottom_depth_m, density_kg_m3); same ``allow_inverted`` and
    ``label``) plus the density checks of the thermal model.

    ``warn``: emit :class:`~crater_thermal.materials.DensityExtrapolationWarning` for regolith densities
    outside Table 7.2 (1300-1970 kg m-3). Densities outside 500-3500 kg m-3 raise ProfileError.
    """
    p = profiles.parse_profile(spec, allow_inverted, label)
    # the built-in hayne2017 label never warns (its set's conductivity is not Table 7.2)
    builtin_hayne = isinstance(spec, str) and spec.strip().lower() == HAYNE_LABEL
    return _check_profile(p, allow_inverted, warn=warn and not builtin_hayne, checked=True)


def density_grid_profiles(spec: str) -> tuple:
    """All two-layer profiles ``top/bottom`` with top <= bottom on a density grid.

    Parameters
    ----------
    spec : ``"start:stop:step"`` [kg m-3], stop inclusive (``"800:2000:100"`` gives 13 densities
        and 91 profiles).

    Returns
    -------
    tuple of Profile, ordered by top density then bottom density. One
    DensityExtrapolationWarning is emitted if any density lies outside 1300-1970.
    """
    dens = profiles.grid_densities(spec)
    materials.check_density(dens, name=f"density_grid {spec!r} density", warn=True)
    return profiles.density_grid_profiles(spec)


# ----------------------------------------------------------------------------- grid


def skin_depth(rho: float = 1300.0, T: float = GRID_T_REF, property_set="apollo", period_s: float = LUNAR_DAY) -> float:
    """Diurnal skin depth sqrt(kappa P / pi) [m] of regolith of density ``rho`` [kg m-3] at ``T`` [K]."""
    ps = materials.get_property_set(property_set)
    b0, b3, _, _ = materials.conductivity_coefficients(rho, "regolith", ps)
    if ps.regolith_model == "constant":
        k, rho, c = ps.constant
    else:
        k = float(b0 + b3 * T**3)
        c = float(ps.heat_capacity(T))
    return math.sqrt(k / (rho * c) * period_s / math.pi)


@dataclass(frozen=True)
class Grid:
    """Node depths of the conduction column.

    Attributes
    ----------
    z : (nz,) float [m], z[0] = 0 (surface) ... z[-1] = depth; nodes sit on every interface.
    first_layer_m, growth : the construction parameters.
    """

    z: np.ndarray
    first_layer_m: float
    growth: float
    interfaces: tuple = field(default=())

    @property
    def nz(self) -> int:
        return int(self.z.size)

    @property
    def dz(self) -> np.ndarray:
        """(nz-1,) link lengths [m]."""
        return np.diff(self.z)

    @property
    def depth(self) -> float:
        return float(self.z[-1])

    def cell_bounds(self):
        """(top, bottom) of each node's control volume [m], each (nz,)."""
        mid = 0.5 * (self.z[1:] + self.z[:-1])
        return np.concatenate([[0.0], mid]), np.concatenate([mid, [self.z[-1]]])


def make_grid(
    first_layer_m: float | None = None,
    growth: float = DEFAULT_GROWTH,
    depth_m: float = COLUMN_DEPTH,
    interfaces: Sequence[float] = (TOP_LAYER_THICKNESS,),
    skin_fraction: float = DEFAULT_SKIN_FRACTION,
    property_set="apollo",
) -> Grid:
    """Geometric grid: layer thickness grows by ``growth`` with depth; a node on every interface.

    Parameters
    ----------
    first_layer_m : float, optional
        Thickness of the first layer [m]; default ``skin_fraction`` x the diurnal skin depth of
        the nominal top layer (1300 kg m-3 at 250 K, lunar day 29.53 d; ~3.6 mm for 0.1).
    growth : float
        Ratio of successive layer thicknesses (>= 1).
    depth_m : float
        Column depth [m].
    interfaces : sequence of float
        Depths [m] that must be nodes (layer interfaces).

    Within each segment between interfaces the geometric series is shrunk slightly so that it
    ends exactly on the interface.
    """
    if first_layer_m is None:
        first_layer_m = skin_fraction * skin_depth(1300.0, GRID_T_REF, property_set)
    if not (first_layer_m > 0 and first_layer_m < depth_m):
        raise ConfigError(f"first_layer_m={first_layer_m!r} must be in (0, {depth_m}) m")
    if not (1.0 <= growth <= 3.0):
        raise ConfigError(f"growth={growth!r} must be in 1-3")
    if not (depth_m > 0):
        raise ConfigError(f"depth_m={depth_m!r} must be > 0")
    ifc = sorted({float(d) for d in interfaces if 0.0 < float(d) < depth_m})
    bounds = [0.0] + ifc + [float(depth_m)]
    z = [0.0]
    dz = float(first_layer_m)
    for a, b in zip(bounds[:-1], bounds[1:]):
        L = b - a
        if growth == 1.0:
            n = max(1, math.ceil(L / dz - 1e-9))
        else:
            n = max(1, math.ceil(math.log(1.0 + L * (growth - 1.0) / dz) / math.log(growth) - 1e-9))
        steps = dz * growth ** np.arange(n)
        steps *= L / steps.sum()
        z.extend((a + np.cumsum(steps))[:-1].tolist())
        z.append(b)
        dz = steps[-1] * growth
    return Grid(np.array(z), float(first_layer_m), float(growth), tuple(ifc))


# ----------------------------------------------------------------------------- solver


def _as_profiles(profiles) -> list:
    if isinstance(profiles, (Profile, str)):
        profiles = [profiles]
    out = []
    cache = {}
    for p in profiles:
        if isinstance(p, Profile):
            if id(p) not in cache:  # ranges only: inverted profiles were allowed (or not) upstream
                cache[id(p)] = _check_profile(p, allow_inverted=True, warn=False)
            out.append(p)
        else:
            key = str(p)
            if key not in cache:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", materials.DensityExtrapolationWarning)
                    cache[key] = parse_profile(p, allow_inverted=True)
            out.append(cache[key])
    if not out:
        raise ProfileError("profiles: need at least one column")
    return out


class ColumnSolver:
    """Many independent nonlinear conduction columns advanced together (numba, parallel).

    Parameters
    ----------
    profiles : sequence of Profile (or labels), one per column (ncol of them).
    property_set : ``"apollo"`` (default), ``"hayne2017"`` or a :class:`materials.PropertySet`
        (e.g. :func:`materials.constant_set` for analytic tests).
    emissivity : [-]
    geothermal_flux : [W m-2], entering at the bottom.
    grid : Grid, optional (default :func:`make_grid` with a node on every profile interface; with
        a user grid, a link that straddles an interface uses its mean density).
    dt_max : float [s]
        Largest sub-step; each forcing interval is split into equal sub-steps <= dt_max.
    scheme : ``"trbdf2"`` (default: TR-BDF2, L-stable, second order) or ``"euler"`` (backward
        Euler, first order; for studies and the benchmark).
    adapt_K : float [K]
        Local-error threshold of the adaptive refinement: a sub-step whose surface curvature
        indicator exceeds it is redone in 4 parts (0: off; decided per column). In practice only the
        sunrise / sunset steps of sunlit facets are split.
    column_labels : sequence of str, optional
        A name per column for error messages (e.g. ``"facet 17"``).

    Initial state: :meth:`set_uniform`, :meth:`set_equilibrium` or :meth:`set_state`; when none
    was called, the first :meth:`run_series` / :meth:`advance` / :meth:`periodic_start` starts
    from :meth:`set_equilibrium` of its own forcing (the default start).

    Attributes
    ----------
    T : (ncol, nz) float [K] the state; ``grid.z`` gives the node depths.
    time_s : float [s] the solver clock (advanced by :meth:`advance` / :meth:`run_series`).
    """

    def __init__(
        self,
        profiles,
        property_set="apollo",
        emissivity: float = EMISSIVITY,
        geothermal_flux: float = GEOTHERMAL_FLUX,
        grid: Grid | None = None,
        dt_max: float = DEFAULT_DT_MAX,
        scheme: str = "trbdf2",
        adapt_K: float = DEFAULT_ADAPT_K,
        column_labels: Sequence[str] | None = None,
    ):
        self.profiles = _as_profiles(profiles)
        if column_labels is not None:
            column_labels = [str(c) for c in column_labels]
            if len(column_labels) != len(self.profiles):
                raise ConfigError(
                    f"column_labels has {len(column_labels)} entries; need one per column ({len(self.profiles)})"
                )
        self.column_labels = column_labels
        self.pset = materials.get_property_set(property_set)
        if not (0.0 <= emissivity <= 1.0):
            raise ConfigError(f"emissivity={emissivity!r} must be in 0-1")
        if not (np.isfinite(geothermal_flux) and abs(geothermal_flux) < 10):
            raise ConfigError(f"geothermal_flux={geothermal_flux!r} W/m2 must be finite, |G| < 10")
        if not (np.isfinite(dt_max) and dt_max > 0):
            raise ConfigError(f"dt_max={dt_max!r} s must be > 0")
        if scheme not in SCHEMES:
            raise ConfigError(f"scheme={scheme!r} is unknown; allowed: {sorted(SCHEMES)}")
        self.emissivity = float(emissivity)
        self.geothermal_flux = float(geothermal_flux)
        self.dt_max = float(dt_max)
        self.scheme = scheme
        if not (np.isfinite(adapt_K) and adapt_K >= 0):
            raise ConfigError(f"adapt_K={adapt_K!r} K must be >= 0 (0: no adaptive refinement)")
        self.adapt_K = float(adapt_K)
        if grid is None:
            ifc = {TOP_LAYER_THICKNESS}
            for p in self.profiles:
                ifc.update(p.interfaces)
            grid = make_grid(
                interfaces=sorted(ifc), property_set=self.pset if self.pset.regolith_model == "constant" else "apollo"
            )
        self.grid = grid
        self._build_coefficients()
        self.T = np.full((self.ncol, self.nz), 200.0)
        self._initialised = False
        self.time_s = 0.0
        self.acc = np.zeros((self.ncol, _k.N_ACC))
        self._snap = None
        self._snap_buf = None  # (T, acc) buffers of :meth:`snapshot`

    # -- set-up ------------------------------------------------------------------------------
    def _build_coefficients(self):
        g = self.grid
        nz = g.nz
        top, bot = g.cell_bounds()
        za, zb = g.z[:-1], g.z[1:]
        uniq = {}
        idx = np.empty(len(self.profiles), np.int64)
        for i, p in enumerate(self.profiles):
            key = id(p)
            if key not in uniq:
                uniq[key] = (len(uniq), p)
            idx[i] = uniq[key][0]
        nu = len(uniq)
        m = np.empty((nu, nz))
        co = np.empty((4, nu, nz - 1))
        rock = np.empty(nu, np.uint8)
        for j, p in uniq.values():
            if self.pset.regolith_model == "constant":
                m[j] = self.pset.constant[1] * (bot - top)
            else:
                m[j] = p.mass_between(top, bot)
            rho_link = p.mean_density(za, zb)
            co[:, j] = materials.conductivity_coefficients(rho_link, p.material, self.pset, warn=False)
            rock[j] = 1 if np.any(co[2, j] != 0) or np.any(co[3, j] != 0) else 0
        self._uidx = idx
        self.m = np.ascontiguousarray(m[idx])
        self.b0, self.b3, self.e0, self.e1 = (np.ascontiguousarray(a[idx]) for a in co)
        self.rock = np.ascontiguousarray(rock[idx])
        self.ccoef = np.asarray(self.pset.c_coeffs, dtype=float)
        self.dz = np.ascontiguousarray(g.dz)
        self.rdz = 1.0 / self.dz
        self._batched = None
        self._alike = False  # every column has the same coefficients (set with _batched)

    def _interleaved(self) -> tuple:
        """The coefficients ``m, b0, b3, e0, e1`` in the kernel's batch layout (``kernels.conduction.interleave``),
        made once: a call then copies none of them (at 10,000 columns the copies cost as much as one step)."""
        if self._batched is None:
            coef = (self.m, self.b0, self.b3, self.e0, self.e1)
            self._alike = self.ncol > 1 and all(np.array_equal(x, np.broadcast_to(x[:1], x.shape)) for x in coef)
            if self._alike:
                # every column alike (one profile, the usual run): one batch's worth, read by every batch
                # (the kernel's convention for a single batch of coefficients): 140 MB less memory at
                # 100,000 columns; the calls' speed did not change (docs/performance.md)
                coef = tuple(x[:1] for x in coef)
            self._batched = tuple(_k.interleave(x) for x in coef)
        return self._batched

    @property
    def ncol(self) -> int:
        return len(self.profiles)

    @property
    def nz(self) -> int:
        return self.grid.nz

    @property
    def surface_temperature(self) -> np.ndarray:
        """(ncol,) surface temperatures [K] (a copy)."""
        return self.T[:, 0].copy()

    def conductivity(self, T=None) -> np.ndarray:
        """(ncol, nz-1) link conductivities [W m-1 K-1] at link-mean temperatures of ``T`` (default state)."""
        T = self.T if T is None else np.asarray(T, float)
        tl = 0.5 * (T[:, 1:] + T[:, :-1])
        k = self.b0 + self.b3 * tl**3
        k = k + self.pset.heat_capacity(tl) * (self.e0 + self.e1 / tl)
        return k

    def stored_heat(self, T=None) -> np.ndarray:
        """(ncol,) heat content sum_i m_i h(T_i) [J m-2], h the specific enthalpy from 0 K."""
        T = self.T if T is None else np.asarray(T, float)
        return np.sum(self.m * materials.enthalpy(T, self.pset), axis=1)

    def energy_budget(self) -> dict:
        """Energies since the last :meth:`reset_accumulators` [J m-2], each (ncol,), with the
        scheme's own quadrature: ``absorbed``, ``emitted``, ``geothermal``; and ``time_s``."""
        return {
            "absorbed": self.acc[:, _k.ACC_ABSORBED].copy(),
            "emitted": self.acc[:, _k.ACC_EMITTED].copy(),
            "geothermal": self.geothermal_flux * self.acc[:, _k.ACC_TIME],
            "time_s": self.acc[:, _k.ACC_TIME].copy(),
        }

    def reset_accumulators(self) -> None:
        self.acc[:] = 0.0

    # -- state -------------------------------------------------------------------------------
    def state(self) -> np.ndarray:
        """A copy of the state T (ncol, nz) [K] (for checkpoints and predictor-corrector)."""
        T = self.T.copy()
        self._snap = (T, self.acc.copy(), self.time_s)
        return T

    def snapshot(self) -> np.ndarray:
        """The state T (ncol, nz) [K] copied into a buffer this solver reuses (no allocation per call), for
        :meth:`redo_columns` within one step: valid only until the next :meth:`snapshot`, so hold no
        reference to it beyond the step (:meth:`state` gives a copy to keep). Measured at 100k columns
        of 35 cells: 1.8 ms instead of :meth:`state`'s 5.5 ms (a fresh 28 MB array's page faults)."""
        buf = self._snap_buf
        if buf is None or buf[0].shape != self.T.shape or buf[1].shape != self.acc.shape:
            buf = self._snap_buf = (np.empty_like(self.T), np.empty_like(self.acc))
        np.copyto(buf[0], self.T)
        np.copyto(buf[1], self.acc)
        self._snap = (buf[0], buf[1], self.time_s)
        return buf[0]

    def set_state(self, T) -> None:
        """Restore a state (ncol, nz) [K]. Passing the array returned by the latest :meth:`state`
        also rewinds the clock and the accumulators (so a predictor step leaves no trace)."""
        T = np.asarray(T, dtype=float)
        if T.shape != (self.ncol, self.nz):
            raise SolverError(f"set_state: shape {T.shape} != (ncol, nz) = {(self.ncol, self.nz)}")
        if not np.all(np.isfinite(T)) or np.any(T <= 0):
            raise SolverError("set_state: temperatures must be finite and > 0 K")
        if self._snap is not None and T is self._snap[0]:
            self.acc[:] = self._snap[1]
            self.time_s = self._snap[2]
        self.T = np.ascontiguousarray(T.copy())
        self._initialised = True

    def set_uniform(self, T0: float) -> None:
        """Uniform start temperature ``T0`` [K]."""
        if not (np.isfinite(T0) and 0 < T0 < 2000):
            raise SolverError(f"initial temperature T0={T0!r} K must be in (0, 2000) K")
        self.T = np.full((self.ncol, self.nz), float(T0))
        self._initialised = True

    def _forcing(self, absorbed, nt_expected=None):
        a = np.asarray(absorbed, dtype=np.float64)
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2:
            raise SolverError(f"absorbed: expected (nt, ncol) array, got shape {np.shape(absorbed)}")
        if nt_expected is not None and a.shape[0] != nt_expected:
            raise SolverError(f"absorbed has {a.shape[0]} samples, times_s has {nt_expected}")
        nf = a.shape[1]
        if nf == 0 or self.ncol % nf:
            raise SolverError(
                f"absorbed has {nf} columns; need ncol={self.ncol} or a divisor of it "
                "(forcing of column j is column j % n)"
            )
        fidx = np.arange(self.ncol, dtype=np.int64) % nf
        return np.ascontiguousarray(a), fidx

    def equilibrium_surface(self, absorbed) -> np.ndarray:
        """Time mean of ((absorbed + G) / (eps sigma))^1/4 [K] per forcing column of an absorbed-flux
        series (nt, n) [W m-2]; the surface of :meth:`equilibrium_profile`. Means of consecutive blocks
        of a long series, weighted by their lengths, give the same estimate without holding it whole."""
        return np.mean(self.equilibrium_surface_samples(absorbed), axis=0)

    def equilibrium_surface_samples(self, absorbed) -> np.ndarray:
        """((absorbed + G) / (eps sigma))^1/4 [K] of every sample (nt, n) of an absorbed-flux series
        (nt, n) [W m-2]: the terms of :meth:`equilibrium_surface`'s mean."""
        a = np.asarray(absorbed, dtype=np.float64)
        es = max(self.emissivity, 1e-3) * SIGMA
        return ((np.maximum(a, 0.0) + max(self.geothermal_flux, 0.0)) / es) ** 0.25

    def equilibrium_profile(self, absorbed=None, surface_K=None) -> np.ndarray:
        """Equilibrium estimate (ncol, nz) [K] from an absorbed-flux series (nt, ncol or divisor).

        Surface: time mean of ((absorbed + G) / (eps sigma))^1/4 (or ``surface_K`` (n,) [K], that mean
        computed block by block with :meth:`equilibrium_surface`); below, the steady geothermal
        profile of the discrete column, dT/dz = G / k(T) integrated link by link (Picard, 4 passes).
        """
        if surface_K is None:
            a, fidx = self._forcing(absorbed)
            ts = self.equilibrium_surface(a)
        else:
            ts = np.asarray(surface_K, dtype=np.float64)
            _, fidx = self._forcing(ts[None, :])
        ts = np.maximum(ts[fidx], 10.0)
        T = np.empty((self.ncol, self.nz))
        T[:, 0] = ts
        G = self.geothermal_flux
        for l in range(self.nz - 1):
            t1 = T[:, l].copy()
            for _ in range(4):
                tl = 0.5 * (T[:, l] + t1)
                k = (
                    self.b0[:, l]
                    + self.b3[:, l] * tl**3
                    + self.pset.heat_capacity(tl) * (self.e0[:, l] + self.e1[:, l] / tl)
                )
                t1 = T[:, l] + G * self.dz[l] / k
            T[:, l + 1] = np.maximum(t1, 1.0)
        return T

    def set_equilibrium(self, absorbed=None, surface_K=None) -> None:
        """Start from :meth:`equilibrium_profile` of the forcing series (the default start)."""
        self.T = self.equilibrium_profile(absorbed, surface_K)
        self._initialised = True

    # -- time stepping -----------------------------------------------------------------------
    def _run(self, times, a, fidx, record, t_offset, out=None, cols=None):
        nt = times.shape[0]
        if cols is None:
            T, rock, acc = self.T, self.rock, self.acc
            m, b0, b3, e0, e1 = self._interleaved()
        else:  # a subset of the columns (copies, written back below)
            T, rock, acc = (np.ascontiguousarray(x[cols]) for x in (self.T, self.rock, self.acc))
            batched = self._interleaved()
            if self._alike:
                m, b0, b3, e0, e1 = batched
            else:
                m, b0, b3, e0, e1 = (_k.interleave(x[cols]) for x in (self.m, self.b0, self.b3, self.e0, self.e1))
        ncol = T.shape[0]
        if out is None:
            out = np.empty((nt, ncol)) if record else np.empty((1, 1))
        status = np.zeros(ncol, np.int64)
        fail = np.full(ncol, -1, np.int64)
        nb = -(-ncol // _k.LANES)
        kern = _k.run_columns if nb >= 2 * numba.get_num_threads() else _k.run_columns_serial
        kern(
            T,
            m,
            b0,
            b3,
            e0,
            e1,
            rock,
            self.ccoef,
            float(self.pset.c_t_min),
            self.rdz,
            self.emissivity * SIGMA,
            self.geothermal_flux,
            SCHEMES[self.scheme],
            self.dt_max,
            self.adapt_K,
            times,
            a,
            fidx,
            out,
            record,
            acc,
            status,
            fail,
        )
        if cols is not None:
            self.T[cols] = T
            self.acc[cols] = acc
        if np.any(status != _k.OK):
            j = int(np.flatnonzero(status != _k.OK)[0])  # in the columns run
            c = j if cols is None else int(cols[j])  # in the solver
            k = int(fail[j])
            t0 = t_offset + times[k] if k >= 0 else t_offset
            what = (
                "the Newton iteration for the surface temperature did not converge"
                if status[j] == _k.NEWTON_FAILED
                else "non-finite forcing or temperature (NaN/inf, or T outside 0-1e5 K)"
            )
            n_bad = int(np.count_nonzero(status != _k.OK))
            name = f", {self.column_labels[c]}" if self.column_labels is not None else ""
            raise SolverError(
                f"conduction solver: {what} in column {c} (profile "
                f"{self.profiles[c].label!r}{name}) during the step starting at "
                f"t={t0:.6g} s ({n_bad} column(s) failed)"
            )
        return out if record else None

    def advance(self, absorbed_start, absorbed_end, duration_s: float) -> np.ndarray:
        """Advance all columns by ``duration_s`` [s] with absorbed flux [W m-2] varying linearly
        from ``absorbed_start`` (ncol,) to ``absorbed_end`` (ncol,). Returns surface T (ncol,) [K]."""
        if not (np.isfinite(duration_s) and duration_s > 0):
            raise SolverError(f"duration_s={duration_s!r} must be > 0")
        a = np.empty((2, self.ncol))
        a[0] = absorbed_start
        a[1] = absorbed_end
        if not self._initialised:
            self.set_equilibrium(a)
        times = np.array([0.0, float(duration_s)])
        self._run(times, a, np.arange(self.ncol, dtype=np.int64), False, self.time_s)
        self.time_s += float(duration_s)
        return self.T[:, 0].copy()

    def _rewind_columns(self, cols, start, caller: str) -> np.ndarray:
        """Restore the columns ``cols`` (state and energy accumulators) from ``start``, the array of the latest
        :meth:`state` or :meth:`snapshot`; returns ``cols`` as int64 (``caller`` names the method in errors)."""
        if self._snap is None or start is not self._snap[0]:
            raise SolverError(f"{caller}: start must be the array returned by the latest state() or snapshot()")
        cols = np.asarray(cols, np.int64)
        T0, acc0, _ = self._snap
        self.T[cols] = T0[cols]
        self.acc[cols] = acc0[cols]
        return cols

    def redo_columns(self, cols, start, absorbed_start, absorbed_end, duration_s: float) -> np.ndarray:
        """Advance again the columns ``cols`` (int array) of the step just taken, from ``start`` (the
        :meth:`state` or :meth:`snapshot` taken before it) with other forcing [W m-2] (``cols``-long
        arrays). The clock and the other columns are untouched; those columns' energy accumulators are
        rewound with their state. Returns the surface T [K] of those columns."""
        cols = self._rewind_columns(cols, start, "redo_columns")
        a = np.empty((2, len(cols)))
        a[0] = absorbed_start
        a[1] = absorbed_end
        times = np.array([0.0, float(duration_s)])
        self._run(times, a, np.arange(len(cols), dtype=np.int64), False, self.time_s - duration_s, cols=cols)
        return self.T[cols, 0].copy()

    def rerun_columns(self, cols, start, times_s, absorbed) -> np.ndarray:
        """Run again the columns ``cols`` (int array) through the samples just run by :meth:`run_series`,
        from ``start`` (the :meth:`state` or :meth:`snapshot` taken before it) with other forcing: the
        several-step :meth:`redo_columns`. The clock and the other columns are untouched; those columns'
        energy accumulators are rewound with their state.

        Parameters
        ----------
        cols : (m,) column indices.
        times_s : (nt,) the samples of that run [s].
        absorbed : (nt, m) absorbed flux [W m-2] of those columns.

        Returns
        -------
        (nt, m) surface temperature [K] of those columns (first row: their start).
        """
        cols = np.asarray(cols, np.int64)
        times = np.ascontiguousarray(np.asarray(times_s, dtype=np.float64))
        a = np.ascontiguousarray(np.asarray(absorbed, dtype=np.float64))
        if a.shape != (times.size, cols.size):
            raise SolverError(f"absorbed has shape {a.shape}; need (times, columns) = {(times.size, cols.size)}")
        cols = self._rewind_columns(cols, start, "rerun_columns")
        t_offset = self.time_s - float(times[-1] - times[0]) - times[0]
        return self._run(times, a, np.arange(cols.size, dtype=np.int64), True, t_offset, cols=cols)

    def run_columns(self, columns, times_s, absorbed) -> np.ndarray:
        """Run only the columns ``columns`` (int array) through forcing samples from their current state;
        the other columns, and the clock, are left as they are.

        Parameters
        ----------
        columns : (m,) column indices.
        times_s : (nt,) increasing [s].
        absorbed : (nt, m) absorbed flux [W m-2] of those columns.

        Returns
        -------
        (nt, m) surface temperature [K] of those columns (first row: their current state).
        """
        cols = np.asarray(columns, np.int64)
        times = np.ascontiguousarray(np.asarray(times_s, dtype=np.float64))
        a = np.ascontiguousarray(np.asarray(absorbed, dtype=np.float64))
        if a.shape != (times.size, cols.size):
            raise SolverError(f"absorbed has shape {a.shape}; need (times, columns) = {(times.size, cols.size)}")
        if cols.size == 0:
            return np.empty((times.size, 0))
        return self._run(times, a, np.arange(cols.size, dtype=np.int64), True, 0.0, cols=cols)

    def run_series(self, times_s, absorbed, record: bool = True, out=None):
        """Run through forcing samples from the current state (taken to be at ``times_s[0]``).

        Parameters
        ----------
        times_s : (nt,) increasing [s]
        absorbed : (nt, ncol) [W m-2], or (nt, n) with ncol a multiple of n (column j uses j % n)
        record : return the surface temperatures at every sample (first row: current state).
        out : optional preallocated (nt, ncol) C-contiguous float32 or float64 array for them
            (float32 halves the memory of a 45,682-column year: 400 MB instead of 800 MB).

        Returns
        -------
        (nt, ncol) surface temperature [K] (or None when not ``record``).
        """
        times = np.ascontiguousarray(np.asarray(times_s, dtype=np.float64))
        if times.ndim != 1 or times.size < 1 or np.any(np.diff(times) <= 0):
            raise SolverError("times_s must be a 1-D strictly increasing array")
        a, fidx = self._forcing(absorbed, times.size)
        if not self._initialised:
            self.set_equilibrium(a)
        if out is not None:
            if (
                not isinstance(out, np.ndarray)
                or out.shape != (times.size, self.ncol)
                or out.dtype not in (np.float32, np.float64)
                or not out.flags.c_contiguous
            ):
                raise SolverError(
                    f"out must be a C-contiguous float32/float64 array of shape {(times.size, self.ncol)}"
                )
            record = True
        out = self._run(times, a, fidx, record, self.time_s - times[0], out)
        self.time_s += float(times[-1] - times[0])
        return out

    def periodic_start(
        self, times_s, absorbed, tol_K: float = 0.01, max_iter: int = 30, start: str | None = None
    ) -> dict:
        """Set the state to the periodic steady state of an uncoupled forcing period.

        The period is ``times_s[0] .. times_s[-1]`` (the forcing should be periodic over it).
        Starts from the current state, or from :meth:`set_equilibrium` with ``start="equilibrium"``
        or when no state was set. Returns :func:`periodic_state`'s info.
        """
        times = np.asarray(times_s, dtype=np.float64)
        a, _ = self._forcing(absorbed, times.size)
        if start == "equilibrium" or not self._initialised:
            self.set_equilibrium(a)

        def period_map(x):
            self.set_state(x)
            self.run_series(times, a, record=False)
            return self.state()

        return periodic_state(self, period_map, tol_K=tol_K, max_iter=max_iter)

    # -- linearisation (public: periodic_state uses it) ---------------------------------------------------
    def step_gain(self, lam):
        """Amplification factor of one sub-step for a linear mode with lam = lambda dt."""
        if self.scheme == "euler":
            return 1.0 / (1.0 + lam)
        g1 = (1.0 - 0.5 * _k.TRB_GAMMA * lam) / (1.0 + 0.5 * _k.TRB_GAMMA * lam)
        return (_k.TRB_W1 * g1 - _k.TRB_W0) / (1.0 + _k.TRB_BETA * lam)

    def linear_modes(self, Tmean, h, dt, cols):
        """Eigen-decomposition of the linearised one-step operator for columns ``cols``.

        Returns (sqrt_c (n, nz), Q (n, nz, nz), lam (n, nz)) with
        (L + H) v = lam Cd v, Cd = m c(Tmean)/dt; one sub-step multiplies mode j by
        ``step_gain(lam_j)``.
        """
        T = Tmean[cols]
        n, nz = T.shape
        tl = 0.5 * (T[:, 1:] + T[:, :-1])
        k = self.b0[cols] + self.b3[cols] * tl**3 + self.pset.heat_capacity(tl) * (self.e0[cols] + self.e1[cols] / tl)
        K = k / self.dz
        Cd = self.m[cols] * self.pset.heat_capacity(T) / dt[:, None]
        A = np.zeros((n, nz, nz))
        ii = np.arange(nz)
        diag = np.zeros((n, nz))
        diag[:, :-1] += K
        diag[:, 1:] += K
        diag[:, 0] += h
        A[:, ii, ii] = diag
        A[:, ii[:-1], ii[1:]] = -K
        A[:, ii[1:], ii[:-1]] = -K
        s = 1.0 / np.sqrt(Cd)
        S = A * s[:, :, None] * s[:, None, :]
        lam, Q = np.linalg.eigh(S)
        return np.sqrt(Cd), Q, np.maximum(lam, 0.0)


# ----------------------------------------------------------------------------- periodic state


def _newton_step(solver, Tm, h, dt, nst, r, dx, cols) -> None:
    """The quasi-Newton step ``dx[cols]`` [K] of :func:`periodic_state` for columns ``cols``: the residual
    ``r`` [K] through ``(I - J)^-1``, J from the linearised one-step operator's modes at ``Tm`` [K]
    (surface conductance ``h`` [W m-2 K-1], mean sub-step ``dt`` [s], ``nst`` sub-steps per period)."""
    sc, Q, lam = solver.linear_modes(Tm, h[cols], dt[cols], cols)
    g = solver.step_gain(lam) ** nst[cols, None]
    w = np.einsum("nij,ni->nj", Q, sc * r[cols])
    w /= np.maximum(1.0 - g, 1e-8)
    dx[cols] = np.einsum("nij,nj->ni", Q, w) / sc


def _each(work: Callable, items, threads: int) -> None:
    """``work(item)`` for every item, on ``threads`` threads (in this thread when 1)."""
    if threads <= 1:
        for item in items:
            work(item)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads) as pool:
        for _ in pool.map(work, items):  # re-raises a chunk's error here
            pass


def periodic_state(
    solver: ColumnSolver,
    period_map: Callable,
    tol_K: float = 0.01,
    max_iter: int = 30,
    chunk: int = 4096,
    anderson: bool = True,
    per_column: bool = False,
    skip: Callable | None = None,
) -> dict:
    """Find the periodic steady state x = period_map(x) and leave the solver in it.

    Quasi-Newton shooting: x <- x + (I - J)^-1 (Phi(x) - x), with J a block-diagonal approximation
    of the one-period map's Jacobian: per column, linear diffusion with properties at the mean of
    x and Phi(x), the surface emission linearised as h = time mean of 4 eps sigma Ts^3 over the
    period, and the period's backward-Euler sub-steps (J = M^n with M the one-step matrix, applied
    through the eigen-decomposition of the symmetric generalised problem). The deep, slow modes
    (time constants of ~100 yr, which a plain spin-up needs centuries for) are thereby jumped over
    in one or two iterations; fast near-surface modes are forgotten within a period anyway.

    Parameters
    ----------
    solver : ColumnSolver (its clock and accumulators record the sub-steps period_map takes)
    period_map : callable (ncol, nz) -> (ncol, nz) [K]: state after one period of forcing from the
        given start state (may be a coupled-crater map; treated as a black box, but it must
        advance ``solver``).
    tol_K : converged when max |Phi(x) - x| <= tol_K at every depth of every column [K] and the
        quasi-Newton step (the predicted distance to the fixed point) is <= tol_K as well.
    max_iter : maximum number of period maps.
    anderson : bool
        Per-column Anderson(1) mixing of successive quasi-Newton steps (default True; saves one
        of ~5 iterations in about half the cases measured, never cost one).
    per_column : bool
        Test convergence column by column and freeze a converged column at its start state (its
        map is then re-run from the same state, so it keeps its converged result) while the others
        iterate (default False). Only valid when ``period_map`` is column-separable (a replay: no
        coupling between columns); it makes each column's result independent of which other
        columns share its batch (a distributed replay in chunks equals a local one bit for bit).
    skip : callable, optional
        ``skip(converged) -> skipped`` (bool arrays (ncol,)): called after each period map that did not
        end the iteration with the columns that met both criteria (residual and step <= ``tol_K``);
        returns the columns the next period map will not run (it must leave their state as given).
        Their previous map's result, accumulators, residual and step are kept and their start state is
        not moved; a column not named again is run and iterated as before. For coupled maps whose
        caller can bound how far a column's forcing has moved since it was last run (the lagged
        spin-up: ``simulate``). Default: every column is run every time.

    Returns
    -------
    dict: ``iterations`` (period maps run), ``converged`` (bool), ``residual_K`` (ncol,)
    max |Phi(x) - x| per column of the last map, ``history_K`` (list of max residuals),
    ``step_K`` (ncol,) the last quasi-Newton step, ``step_history_K``.
    The solver is left in Phi(x) (the state one period after the converged start, i.e. the
    periodic state at the start of the period), its clock reset to its value at the call and its
    accumulators holding the last period's energies.
    """
    x = solver.T.copy()  # (not state(): no snapshot that the period map's set_state would rewind)
    t_start = solver.time_s
    history = []
    step_hist = []
    prev = None
    step = np.full(solver.ncol, np.inf)
    res = np.full(solver.ncol, np.inf)
    converged = False
    y = x
    frozen = np.zeros(solver.ncol, bool)
    skipped = np.zeros(solver.ncol, bool)  # columns the current map does not run (``skip``)
    y_last = acc_last = None
    for it in range(1, max_iter + 1):
        solver.reset_accumulators()
        y = np.asarray(period_map(x), dtype=float)
        if skipped.any():  # their last map's result and energies stand
            y[skipped] = y_last[skipped]
            solver.acc[skipped] = acc_last[skipped]
        r = y - x
        res = np.max(np.abs(r), axis=1)
        history.append(float(res.max()))
        if it == max_iter:
            break
        tsum = solver.acc[:, _k.ACC_TIME]
        nst = solver.acc[:, _k.ACC_NSTEPS]
        run = np.flatnonzero(~skipped)
        if np.all(tsum[run] > 0) and np.all(nst[run] > 0):
            dt = np.where(nst > 0, tsum / np.maximum(nst, 1), 1.0)
            h = np.where(tsum > 0, solver.acc[:, _k.ACC_HDT] / np.where(tsum > 0, tsum, 1.0), 0.0)
            Tm = 0.5 * (x + y)
            dx = np.zeros_like(r)
            parts = [run[c0 : c0 + chunk] for c0 in range(0, len(run), chunk)]
            # one BLAS thread: LAPACK's threads on thousands of tiny (nz x nz) problems cost 30x the
            # work on a busy 2-core machine (measured: 17 s instead of 0.5 s for 1000 columns); the
            # chunks instead go to numba's number of threads (numpy's eigh releases the GIL: 1.9-2.0x on
            # 2 cores at 100k columns, bench/periodic_jacobian.py), each column's numbers unchanged
            with threadpool_limits(1, user_api="blas"):
                _each(
                    lambda cols: _newton_step(solver, Tm, h, dt, nst, r, dx, cols),  # noqa: B023 (used at once)
                    parts,
                    min(numba.get_num_threads(), len(parts)),
                )
        else:
            dx = np.where(skipped[:, None], 0.0, r)
        step = np.where(skipped, step, np.max(np.abs(dx), axis=1))
        step_hist.append(float(step.max()))
        # converged: the period map moves the state by <= tol_K and the predicted distance to
        # the fixed point (the quasi-Newton step) is <= tol_K too (a small residual alone can
        # hide a slow deep mode: its residual is (1 - g) times its distance, g ~ 0.99 per year)
        if per_column:
            frozen |= (res <= tol_K) & (step <= tol_K)
            if frozen.all():
                converged = True
                break
        elif history[-1] <= tol_K and step_hist[-1] <= tol_K:
            converged = True
            break
        x_new = x + dx
        if anderson and prev is not None:
            # Anderson(1) mixing per column on the preconditioned fixed-point map x -> x + dx:
            # removes the dominant error mode left by the approximate Jacobian.
            x_old, dx_old = prev
            df = dx - dx_old
            den = np.sum(df * df, axis=1)
            gam = np.where(den > 0, np.sum(df * dx, axis=1) / np.where(den > 0, den, 1.0), 0.0)
            gam = np.clip(gam, -2.0, 2.0)
            x_new = x_new - gam[:, None] * ((x - x_old) + df)
        prev = (x, dx)
        x_new = np.maximum(x_new, 2.0)
        if skip is not None:  # the columns the next map skips keep their start state
            y_last, acc_last = y, solver.acc.copy()
            skipped = np.asarray(skip((res <= tol_K) & (step <= tol_K)), bool)
            frozen_now = skipped | frozen if per_column else skipped
            x = np.where(frozen_now[:, None], x, x_new)
        else:
            x = np.where(frozen[:, None], x, x_new) if per_column else x_new
    solver.set_state(y)
    solver.time_s = t_start
    return {
        "iterations": it,
        "converged": converged,
        "residual_K": res,
        "history_K": history,
        "step_K": step,
        "step_history_K": step_hist,
    }
