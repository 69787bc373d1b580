"""From measured brightness temperatures back to density: a grid posterior with uncertainty.

Arrays in, arrays out (numpy/scipy only; the readers and writers live in :mod:`crater_thermal.io`).
Units: SI inside (densities [kg m-3], temperatures [K], times datetime64[ns] UTC), as the names say.

The forward model
-----------------
A replay of a density grid gives surface temperatures ``T(profile, time, facet)`` [K] for two-layer
profiles ``top/bottom`` on a regular node grid (the thesis's 13 densities 800-2000 kg m-3 give 91
profiles with top <= bottom: a triangle of the top x bottom square). :class:`ForwardModel` predicts a
sample's brightness temperature at any (top, bottom) inside that triangle:

* in time, linearly between the replay's samples (the project's convention for fluxes, kept here);
* in density, bilinearly inside a grid cell whose four corners are profiles of the grid, and linearly
  (barycentric) in the half cell on the diagonal whose fourth corner (top > bottom) is not a profile.
  The posterior lives on the nodes of the grid refined by an integer factor ``refine``;
* through the band: a sample that sees several facets (footprint mixing, weights ``w``) has the band
  radiance ``sum w L(T_f)`` and the brightness temperature that radiance inverts to
  (:func:`instrument.mixed_band_temperature`); one facet has ``T_b = T`` (emissivity 1, as there).

The likelihood (noise model of :mod:`crater_thermal.instrument`)
-----------------------------------------------------------------
The samples of one footprint ``f`` (``y_i`` [K], i = 1..n) are ``y = m(rho) + e`` with ``e`` Gaussian of
covariance ::

    C = diag(d_i) + s^2 1 1^T + sigma_o^2 u u^T + gain_error^2 h h^T + V_m V_m^T

evaluated at the measured brightness temperatures ``y_i`` (the same for every grid node). The noise
is a radiance noise (NEdL does not depend on the scene); its size in kelvin, ``NETD(T) = NEdL / L'(T)``,
is the linearization at the scene's temperature. Evaluated at each node's model temperature instead, the
steep ``L'(T)`` of a far-IR band at 50 K would make ``log det C`` itself favour warmer nodes (smaller
NETD) when the noise swamps the signal: information that the radiance noise does not carry. At the
measurements, ``C`` is one matrix per footprint and only the residuals tell nodes apart (``y`` and ``m``
differ by the noise, so the two linearizations agree where the noise is small against ``L / L'``):

* ``d_i`` white: ``NETD(y_i)^2 (1 / n_i + t_int / knee_s)``, ``n_i = floor(dwell_i / t_int)``: the sample
  is the mean of one dwell's integrations plus the averaging floor of that reading (as in a stare of
  instrument.py, one floor offset per reading; readings hours apart are calibrated anew, as its passes).
  A stated per-sample uncertainty ``sigma_K`` replaces ``d_i`` by ``sigma_K^2``.
* ``s`` natural scatter (instrument.py's 0.94 K by default): the footprint's true temperature is off by
  ``s z``, one ``z`` per footprint, shared by all its samples at all times.
* calibration offset: a radiance offset ``o`` moves a brightness temperature by ``o / L'(T)``. It is given as
  ``offset_K``, its 1-sigma size in K at the instrument's ``t_ref_K``: ``u_i = NETD(y_i) / NETD_ref``.
  instrument.py states no offset (it cancels in its differences); the default here is 0, give one
  (e.g. an absolute accuracy) to marginalize it. One offset per footprint.
* calibration gain: a relative gain error ``g ~ N(0, gain_error)`` moves ``T`` by ``g h(T)``,
  ``h = L / L'`` (instrument.py's :func:`~crater_thermal.instrument.gain_lever`), one ``g`` per footprint
  (a map's footprints are inverted one by one, so a gain shared by the whole map is treated as
  independent between footprints: each footprint's posterior is right on its own, the joint map is not).

* model error: the forward model interpolates between the grid's densities (and linearly in time between the
  replay's samples); its error is not noise, but at low noise it dominates (measured ~0.03 K rms, 0.14 K
  max, against replays of off-node profiles on a 100 kg m-3 grid; ~0.065 K rms on a 200 kg m-3 grid).
  ``model_error_K="auto"`` (the default) adds ``V_m V_m^T`` estimated from the grid itself, leave one node
  out (:meth:`ForwardModel.model_error_levers`): every interior node interpolated from its two neighbours
  at double spacing along top, bottom and the diagonal; that residual, scaled to the grid's spacing (1/4:
  linear interpolation error grows as the spacing squared), is the largest error of an interpolation
  over one grid step; the covariance is twice the sum over the directions of the residual time series'
  mean outer product over the grid's nodes, at the footprint's samples. It is one matrix per footprint
  (the same at every node, like the rest), correlated over the samples as one density's error is.
  ``model_error_K`` a number: a white 1-sigma [K] per sample instead; 0: the interpolation taken as exact.
  ``tests/test_invert_run.py`` shows at 10x less than the stated noise the 90 % regions holding the
  independently replayed truths as often as their mass says with it, and under-covering without it;
  also for samples between the replay's times, against an independent run at half the time step.

The offset, gain, scatter and model-error coefficients are nuisance parameters with Gaussian priors,
integrated out analytically: that is the covariance above. The likelihood is evaluated through the
Woodbury identity and the matrix-determinant lemma with the low-rank part
``V = [s 1, sigma_o u, gain_error h, V_m]`` (``C = D + V V^T``)::

    r^T C^-1 r = r^T D^-1 r - b^T A^-1 b,   log det C = sum log d_i + log det A,
    A = I_q + V^T D^-1 V,  b = V^T D^-1 r,

so each grid node costs O(n q), never an n x n matrix (``A``, q x q with q <= 3 + n, is factored once per
footprint). Treating
every sample as independent (the shared terms on the diagonal, ``independent=True``, for comparison
only) is overconfident: ``tests/test_invert_run.py`` measures its 90 % regions holding the truth in about
half of 200 trials, against 90 % with the shared terms.

The prior
---------
``prior="uniform"``: uniform in (top, bottom) density over the refined nodes inside the grid's
triangle (top <= bottom, both within the grid's range); nodes outside have probability 0. An array
``(n_top, n_bottom)`` of non-negative weights on the refined nodes may be given instead. The posterior
is normalized to sum 1 over the nodes (probability masses, not densities).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from crater_thermal import instrument as ins
from crater_thermal.errors import ConfigError

#: Physical range of brightness temperatures accepted [K] (outside: most likely not kelvin)
T_B_RANGE_K = (10.0, 500.0)
#: Default threshold of "loose": bottom density below it [kg m-3]
LOOSE_BOTTOM_KG_M3 = 1500.0
#: Credible mass of the highest-posterior region [-]
CREDIBLE_MASS = 0.9
#: Default refinement of the density grid for the posterior (100 kg m-3 grid -> 25 kg m-3 nodes)
DEFAULT_REFINE = 4


# --------------------------------------------------------------------------------- observations


@dataclass
class ObservationTable:
    """Measured samples: one row per sample (a reading of one dwell).

    Attributes
    ----------
    time : (n,) datetime64[ns]          UTC time of each sample.
    facet : (n,) int or (n, k) int      facet seen (k facets: footprint mixing with ``facet_weight``);
                                        -1 only before positions are mapped to facets.
    footprint : (n,) int                id of the footprint the sample belongs to (its samples share the
                                        density, the natural scatter and the calibration offset/gain).
    T_b_K : (n,) float [K]              measured band brightness temperature.
    sigma_K : (n,) float [K]            stated white uncertainty of the sample; NaN: the instrument model.
    dwell_s : (n,) float [s]            time integrated for the sample.
    instrument : str or None            instrument preset name (:func:`instrument.get_instrument`).
    facet_weight : (n, k) float or None fractions of the footprint on each facet (rows sum to 1).
    """

    time: np.ndarray
    facet: np.ndarray
    footprint: np.ndarray
    T_b_K: np.ndarray
    sigma_K: Optional[np.ndarray] = None
    dwell_s: Optional[np.ndarray] = None
    instrument: Optional[str] = None
    facet_weight: Optional[np.ndarray] = None

    def __post_init__(self):
        self.time = np.asarray(self.time, "datetime64[ns]").reshape(-1)
        n = self.time.size
        self.facet = np.asarray(self.facet)
        self.footprint = np.asarray(self.footprint).reshape(-1)
        self.T_b_K = np.asarray(self.T_b_K, float).reshape(-1)
        self.sigma_K = np.full(n, np.nan) if self.sigma_K is None else np.asarray(self.sigma_K, float).reshape(-1)
        self.dwell_s = np.full(n, np.nan) if self.dwell_s is None else np.asarray(self.dwell_s, float).reshape(-1)
        for name in ("facet", "footprint", "T_b_K", "sigma_K", "dwell_s"):
            a = getattr(self, name)
            if a.shape[:1] != (n,):
                raise ConfigError(f"observations: {name} has {a.shape[0] if a.ndim else 1} rows, time has {n}")
        if self.facet.ndim == 1:
            self.facet = self.facet[:, None]
        if self.facet.ndim != 2:
            raise ConfigError("observations: facet must be one facet per sample, or (samples, k) for mixing")
        if not np.issubdtype(self.facet.dtype, np.integer):
            f = self.facet.astype(float)
            if np.any(~np.isfinite(f)) or np.any(f != np.round(f)):
                raise ConfigError("observations: facet must hold whole facet indices")
            self.facet = f.astype(np.int64)
        if not np.issubdtype(self.footprint.dtype, np.integer):
            f = self.footprint.astype(float)
            if np.any(~np.isfinite(f)) or np.any(f != np.round(f)):
                raise ConfigError("observations: footprint must hold whole footprint ids")
            self.footprint = f.astype(np.int64)
        k = self.facet.shape[1]
        if self.facet_weight is None:
            self.facet_weight = np.full(self.facet.shape, 1.0 / k)
        else:
            self.facet_weight = np.asarray(self.facet_weight, float).reshape(self.facet.shape)

    def __len__(self) -> int:
        return int(self.time.size)

    def validate(self, run_times, n_facets: int) -> "ObservationTable":
        """Check the samples against a run; raise :class:`ConfigError` (one line) on the first problem.

        Parameters
        ----------
        run_times : (nt,) datetime64   the run's (replay's) sample times; observations must lie inside.
        n_facets : int                 facets of the run's mesh.

        Returns
        -------
        self
        """
        n = len(self)
        if n == 0:
            raise ConfigError("observations: the table has no samples")
        rt = np.asarray(run_times, "datetime64[ns]")
        if np.any(np.isnat(self.time)):
            i = int(np.flatnonzero(np.isnat(self.time))[0])
            raise ConfigError(f"observations: sample {i} has no time (NaT); give every sample a UTC time")
        lo, hi = rt.min(), rt.max()
        out = (self.time < lo) | (self.time > hi)
        if np.any(out):
            i = int(np.flatnonzero(out)[0])
            raise ConfigError(
                f"observations: {int(out.sum())} sample(s) outside the run's times {lo} .. {hi} "
                f"(first: sample {i} at {self.time[i]}); observe within the run or run over the observations"
            )
        bad = (self.facet < 0) | (self.facet >= n_facets)
        if np.any(bad):
            i = int(np.flatnonzero(bad.any(axis=1))[0])
            raise ConfigError(
                f"observations: facet {int(self.facet[i][bad[i]][0])} of sample {i} is not a facet of the run "
                f"(0..{n_facets - 1}); map positions to facets of this mesh"
            )
        w = self.facet_weight
        if np.any(~np.isfinite(w)) or np.any(w < 0) or np.any(np.abs(w.sum(axis=1) - 1.0) > 1e-6):
            raise ConfigError("observations: facet_weight must be >= 0 with each sample's weights summing to 1")
        T = self.T_b_K
        if np.any(~np.isfinite(T)):
            i = int(np.flatnonzero(~np.isfinite(T))[0])
            raise ConfigError(f"observations: brightness temperature of sample {i} is {T[i]}; drop or fill the sample")
        lo_K, hi_K = T_B_RANGE_K
        if np.any((T < lo_K) | (T > hi_K)):
            i = int(np.flatnonzero((T < lo_K) | (T > hi_K))[0])
            raise ConfigError(
                f"observations: brightness temperature {T[i]:g} of sample {i} outside {lo_K:g}-{hi_K:g} K; "
                "wrong units? brightness temperatures are in K"
            )
        s = self.sigma_K
        if np.any(~np.isnan(s) & ~(np.isfinite(s) & (s > 0))):
            i = int(np.flatnonzero(~np.isnan(s) & ~(np.isfinite(s) & (s > 0)))[0])
            raise ConfigError(f"observations: sigma_K={s[i]} of sample {i} must be > 0 K (or empty: instrument model)")
        d = self.dwell_s
        need = np.isnan(s)
        if np.any(need & ~(np.isfinite(d) & (d > 0))):
            i = int(np.flatnonzero(need & ~(np.isfinite(d) & (d > 0)))[0])
            raise ConfigError(
                f"observations: dwell_s={d[i]} of sample {i} must be > 0 s (needed for the instrument's noise "
                "where no sigma_K is given)"
            )
        if np.any(self.footprint < 0):
            raise ConfigError("observations: footprint ids must be >= 0")
        return self


# ---------------------------------------------------------------------------------- the forward model


def _grid_axis(values: np.ndarray, what: str) -> np.ndarray:
    """Sorted unique densities; raises unless regularly spaced."""
    ax = np.unique(np.round(values, 6))
    if ax.size >= 3:
        step = np.diff(ax)
        if np.any(np.abs(step - step[0]) > 1e-6 * max(1.0, step[0])):
            raise ConfigError(f"grid replay: {what} densities {ax.tolist()} are not regularly spaced")
    return ax


class ForwardModel:
    """Predicted brightness temperatures of a replayed density grid at any density inside it.

    Parameters
    ----------
    T : (n_profile, n_time, n_facet) float [K]   surface temperatures of the grid replay.
    tops_kg_m3, bottoms_kg_m3 : (n_profile,) float [kg m-3]   each profile's top and bottom density;
        the pairs must lie on a regular top x bottom node grid (missing nodes allowed: the triangle
        top <= bottom of :func:`thermal.density_grid_profiles`).
    times : (n_time,) datetime64   replay sample times (UTC).
    """

    def __init__(self, T, tops_kg_m3, bottoms_kg_m3, times):
        T = np.asarray(T)
        if T.ndim != 3:
            raise ConfigError(f"grid replay: surface temperatures must be (profile, time, facet), got shape {T.shape}")
        tops = np.asarray(tops_kg_m3, float).reshape(-1)
        bots = np.asarray(bottoms_kg_m3, float).reshape(-1)
        times = np.asarray(times, "datetime64[ns]").reshape(-1)
        if tops.size != T.shape[0] or bots.size != T.shape[0]:
            raise ConfigError(f"grid replay: {T.shape[0]} profiles but {tops.size} top / {bots.size} bottom densities")
        if times.size != T.shape[1] or times.size < 2 or np.any(np.diff(times) <= np.timedelta64(0)):
            raise ConfigError("grid replay: need >= 2 increasing times, one per temperature sample")
        if np.any(~np.isfinite(tops)) or np.any(~np.isfinite(bots)):
            raise ConfigError(
                "grid replay: every profile needs finite top and bottom densities (drop rock/exponential)"
            )
        self.T = T
        self.times = times
        self._t_s = (times - times[0]).astype(np.int64) / 1e9
        self.top_nodes = _grid_axis(tops, "top")
        self.bottom_nodes = _grid_axis(bots, "bottom")
        it = np.searchsorted(self.top_nodes, np.round(tops, 6))
        ib = np.searchsorted(self.bottom_nodes, np.round(bots, 6))
        index = np.full((self.top_nodes.size, self.bottom_nodes.size), -1, np.int64)
        if np.any(index[it, ib] >= 0) or len(set(zip(it.tolist(), ib.tolist()))) != tops.size:
            raise ConfigError("grid replay: two profiles share the same top/bottom densities")
        index[it, ib] = np.arange(tops.size)
        #: (n_top_nodes, n_bottom_nodes) profile index of each node, -1 where the grid has none
        self.node_profile = index
        self.n_facets = T.shape[2]

    # -- density interpolation -------------------------------------------------------------------
    def density_axes(self, refine: int = DEFAULT_REFINE) -> tuple[np.ndarray, np.ndarray]:
        """Top and bottom density axes [kg m-3] of the grid refined by the integer ``refine``."""
        if isinstance(refine, bool) or int(refine) != refine or refine < 1:
            raise ConfigError(f"refine={refine} must be an integer >= 1")
        refine = int(refine)

        def fine(ax):
            if ax.size == 1:
                return ax.copy()
            return np.concatenate(
                [np.linspace(a, b, refine, endpoint=False) for a, b in zip(ax[:-1], ax[1:])] + [ax[-1:]]
            )

        return fine(self.top_nodes), fine(self.bottom_nodes)

    def weights(self, top_kg_m3, bottom_kg_m3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Interpolation weights of density points on the grid's profiles.

        Parameters
        ----------
        top_kg_m3, bottom_kg_m3 : (m,) float [kg m-3]

        Returns
        -------
        profile : (m, 4) int      profile indices (0 where unused).
        weight : (m, 4) float     weights (sum 1 inside the grid; 0 where unused).
        inside : (m,) bool        the point lies inside the grid (a full cell or the triangle of a diagonal one).
        """
        t = np.asarray(top_kg_m3, float).reshape(-1)
        b = np.asarray(bottom_kg_m3, float).reshape(-1)
        prof = np.zeros((t.size, 4), np.int64)
        wt = np.zeros((t.size, 4))
        inside = np.zeros(t.size, bool)
        P = self.node_profile
        (ti, tf), (bi, bf) = _locate(self.top_nodes, t), _locate(self.bottom_nodes, b)
        ok = (ti >= 0) & (bi >= 0)
        nt, nb = P.shape
        ti1 = np.minimum(ti + 1, nt - 1)
        bi1 = np.minimum(bi + 1, nb - 1)
        ti0, bi0 = np.maximum(ti, 0), np.maximum(bi, 0)
        corners = np.stack([P[ti0, bi0], P[ti1, bi0], P[ti0, bi1], P[ti1, bi1]], axis=1)
        bil = np.stack([(1 - tf) * (1 - bf), tf * (1 - bf), (1 - tf) * bf, tf * bf], axis=1)
        present = corners >= 0
        need = bil > 1e-12
        full = ok & np.all(present | ~need, axis=1)
        prof[full] = np.where(present[full], corners[full], 0)
        wt[full] = np.where(present[full], bil[full], 0.0)
        inside[full] = True
        # a diagonal cell lacking one corner: linear on the triangle of the three others
        tri = ok & ~full & (present.sum(axis=1) == 3)
        for miss in range(4):
            sel = tri & ~present[:, miss]
            if not np.any(sel):
                continue
            bw = _barycentric(miss, tf[sel], bf[sel])
            good = np.all(bw >= -1e-9, axis=1)
            idx = np.flatnonzero(sel)[good]
            bw = np.clip(bw[good], 0.0, None)
            prof[idx] = np.where(present[idx], corners[idx], 0)
            wt[idx] = bw / bw.sum(axis=1, keepdims=True)
            inside[idx] = True
        return prof, wt, inside

    # -- model (interpolation) error ------------------------------------------------------------
    @functools.cached_property
    def _second_differences(self) -> list[np.ndarray]:
        """Per direction (top, bottom, diagonal) the (K_d, n_profile) stencils ``(T_- - 2 T_0 + T_+) / 8``
        of every grid node whose two neighbours along that direction are profiles of the grid."""
        P = self.node_profile
        nt, nb = P.shape
        out = []
        for di, dj in ((1, 0), (0, 1), (1, 1)):
            rows = []
            for i in range(di, nt - di):
                for j in range(dj, nb - dj):
                    a, b, c = P[i - di, j - dj], P[i, j], P[i + di, j + dj]
                    if min(a, b, c) < 0:
                        continue
                    r = np.zeros(self.T.shape[0])
                    r[a], r[b], r[c] = 0.125, -0.25, 0.125
                    rows.append(r)
            if rows:
                out.append(np.array(rows))
        return out

    def model_error_levers(self, times, facets, facet_weight=None) -> np.ndarray:
        """Columns ``V_m`` (n, q) [K] of the density-interpolation error covariance ``V_m V_m^T`` of n samples.

        Estimated from the grid itself, leave one node out: each interior node's temperature is
        interpolated from its two neighbours at double spacing (along top, bottom and the diagonal);
        the residual ``T_0 - (T_- + T_+) / 2 = -D / 2`` (``D`` the second difference), scaled to the grid's
        spacing by 1/4 (linear interpolation error grows as the spacing squared), is ``D / 8``: the largest
        error of a linear interpolation over one grid step, at the cell's centre. The covariance is twice
        the sum over the three directions of the mean outer product of these residual time series over
        the grid's nodes (twice: a bilinear cell's centre error ``(D_t + D_b) / 8`` has a second moment
        <= 2 (D_t^2 + D_b^2) / 64). Conservative: the cell-centre (largest) error, kept correlated over the
        samples as the error of one density is (one set of coefficients per footprint). Mixed samples mix
        the residuals with the facet weights (linear in temperature: the error is small).

        Parameters
        ----------
        times : (n,) datetime64; facets : (n,) or (n, k) int; facet_weight : (n, k) float or None.

        Returns
        -------
        (n, q) float [K], q <= n (compressed by SVD; q = 0 for a grid without three nodes in a line).
        """
        fac = np.asarray(facets, np.int64)
        fac = fac[:, None] if fac.ndim == 1 else fac
        w = np.full(fac.shape, 1.0 / fac.shape[1]) if facet_weight is None else np.asarray(facet_weight, float)
        Tp = sum(w[:, j : j + 1] * self.profile_temperatures(times, fac[:, j]) for j in range(fac.shape[1]))
        cols = [Tp @ S.T * math.sqrt(2.0 / S.shape[0]) for S in self._second_differences]
        if not cols:
            return np.zeros((fac.shape[0], 0))
        u, sv, _ = np.linalg.svd(np.concatenate(cols, axis=1), full_matrices=False)
        keep = sv > 1e-9 * max(float(sv[0]), 1e-30)
        return u[:, keep] * sv[keep]

    # -- time interpolation ----------------------------------------------------------------------
    def _time_index(self, times) -> tuple[np.ndarray, np.ndarray]:
        ts = (np.asarray(times, "datetime64[ns]") - self.times[0]).astype(np.int64) / 1e9
        if np.any(ts < self._t_s[0]) or np.any(ts > self._t_s[-1]):
            raise ConfigError("observations: times outside the grid replay's times")
        k = np.clip(np.searchsorted(self._t_s, ts, side="right") - 1, 0, self._t_s.size - 2)
        a = (ts - self._t_s[k]) / (self._t_s[k + 1] - self._t_s[k])
        return k, a

    def profile_temperatures(self, times, facets) -> np.ndarray:
        """Surface temperatures [K] of every grid profile at sample times and facets, (n, n_profile).

        ``times`` (n,) datetime64, ``facets`` (n,) int; linear in time between the replay's samples.
        """
        k, a = self._time_index(times)
        f = np.asarray(facets, np.int64).reshape(-1)
        T0 = np.asarray(self.T[:, k, f], float)
        T1 = np.asarray(self.T[:, k + 1, f], float)
        return ((1 - a) * T0 + a * T1).T

    def predict(self, top_kg_m3, bottom_kg_m3, times, facets, facet_weight=None, band: ins.Band = ins.BOLOMETRIC):
        """Brightness temperatures [K] of samples, (n, m), at m density points (n samples).

        Parameters
        ----------
        top_kg_m3, bottom_kg_m3 : (m,) float [kg m-3]   points inside the grid (ConfigError otherwise).
        times : (n,) datetime64      sample times.
        facets : (n,) or (n, k) int  facets seen (k > 1: footprint mixing in the band's radiance).
        facet_weight : (n, k) float  fractions (rows sum to 1); default equal.
        band : Band                  the radiometer band (mixing only).
        """
        prof, wt, inside = self.weights(top_kg_m3, bottom_kg_m3)
        if not np.all(inside):
            raise ConfigError("densities outside the grid replay's (top, bottom) range")
        fac = np.asarray(facets, np.int64)
        fac = fac[:, None] if fac.ndim == 1 else fac
        w = np.full(fac.shape, 1.0 / fac.shape[1]) if facet_weight is None else np.asarray(facet_weight, float)
        Wd = _dense_weights(prof, wt, self.T.shape[0])  # (m, n_profile)
        return _mix(self, times, fac, w, Wd, band)


def _locate(ax: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell index (-1 outside) and fraction of points ``x`` on a sorted axis (a single node: fraction 0)."""
    tol = 1e-9 * max(1.0, float(np.abs(ax).max()))
    if ax.size == 1:
        return np.where(np.abs(x - ax[0]) <= tol, 0, -1), np.zeros_like(x)
    i = np.clip(np.searchsorted(ax, x, side="right") - 1, 0, ax.size - 2)
    f = (x - ax[i]) / (ax[i + 1] - ax[i])
    out = (x < ax[0] - tol) | (x > ax[-1] + tol)
    return np.where(out, -1, i), np.clip(f, 0.0, 1.0)


def _barycentric(missing: int, tf: np.ndarray, bf: np.ndarray) -> np.ndarray:
    """Linear weights on the 3 corners of a unit cell other than ``missing`` (order 00, 10, 01, 11)."""
    w = np.zeros((tf.size, 4))
    if missing == 1:  # corners 00, 01, 11: triangle tf <= bf
        w[:, 0], w[:, 2], w[:, 3] = 1 - bf, bf - tf, tf
    elif missing == 2:  # 00, 10, 11: tf >= bf
        w[:, 0], w[:, 1], w[:, 3] = 1 - tf, tf - bf, bf
    elif missing == 0:  # 10, 01, 11: tf + bf >= 1
        w[:, 1], w[:, 2], w[:, 3] = 1 - bf, 1 - tf, tf + bf - 1
    else:  # 00, 10, 01: tf + bf <= 1
        w[:, 0], w[:, 1], w[:, 2] = 1 - tf - bf, tf, bf
    return w


def _dense_weights(prof, wt, n_profile) -> np.ndarray:
    W = np.zeros((prof.shape[0], n_profile))
    np.add.at(W, (np.repeat(np.arange(prof.shape[0]), 4), prof.reshape(-1)), wt.reshape(-1))
    return W


def _mix(fm: ForwardModel, times, fac, w, Wd, band) -> np.ndarray:
    """(n, m) brightness temperatures: per facet, density-interpolated temperatures, mixed in band radiance."""
    if fac.shape[1] == 1:
        return fm.profile_temperatures(times, fac[:, 0]) @ Wd.T
    L = 0.0
    for j in range(fac.shape[1]):
        Tj = fm.profile_temperatures(times, fac[:, j]) @ Wd.T
        L = L + w[:, j : j + 1] * _table(band).radiance(Tj)
    return _table(band).brightness(L)


# ---------------------------------------------------------------------------------- band tables


class _BandTable:
    """log L, log L' on a fine log-temperature grid, 2-2000 K, for fast interpolation (rel. error < 1e-7)."""

    def __init__(self, band: ins.Band):
        self.logT = np.linspace(math.log(2.0), math.log(2000.0), 20001)
        T = np.exp(self.logT)
        with np.errstate(divide="ignore"):
            self.logL = np.log(ins.band_radiance(T, band))
            self.logdL = np.log(ins.band_radiance_derivative(T, band))
        ok = np.isfinite(self.logL) & np.isfinite(self.logdL)
        self.logT, self.logL, self.logdL = self.logT[ok], self.logL[ok], self.logdL[ok]

    def radiance(self, T):
        return np.exp(np.interp(np.log(T), self.logT, self.logL))

    def derivative(self, T):
        return np.exp(np.interp(np.log(T), self.logT, self.logdL))

    def brightness(self, L):
        return np.exp(np.interp(np.log(L), self.logL, self.logT))


@functools.lru_cache(maxsize=16)
def _table(band: ins.Band) -> _BandTable:
    return _BandTable(band)


def _noise_levers(T_b, instrument: ins.Instrument):
    """(NETD(T) [K], offset lever NETD(T)/NETD_ref [-], gain lever h(T) = L/L' [K]) via the band table."""
    tab = _table(instrument.band)
    dL = tab.derivative(T_b)
    ref = float(ins.band_radiance_derivative(instrument.t_ref_K, instrument.band))
    netd = instrument.netd_ref_K * ref / dL
    return netd, ref / dL, tab.radiance(T_b) / dL


# --------------------------------------------------------------------------------- the posterior


@dataclass
class Posterior:
    """Posterior over (top, bottom) density per footprint (module docstring: prior and likelihood).

    Attributes
    ----------
    footprint : (n_fp,) int                 footprint ids, in the order of the arrays.
    top_kg_m3, bottom_kg_m3 : (n_top,), (n_bottom,) float [kg m-3]   refined density axes.
    probability : (n_fp, n_top, n_bottom) float   posterior mass per node (sums to 1 per footprint;
                                            0 outside the grid's triangle).
    prior : (n_top, n_bottom) float          prior mass per node (sums to 1).
    log_evidence : (n_fp,) float             log of the marginal likelihood (up to the prior's node count).
    loose_bottom_kg_m3 : float [kg m-3]     threshold of ``p_loose``.
    n_samples : (n_fp,) int                  samples per footprint.
    model_error_K : (n_fp,) float [K]        rms over the footprint's samples of the model (interpolation)
                                            error's 1-sigma used in the likelihood.
    """

    footprint: np.ndarray
    top_kg_m3: np.ndarray
    bottom_kg_m3: np.ndarray
    probability: np.ndarray
    prior: np.ndarray
    log_evidence: np.ndarray
    loose_bottom_kg_m3: float = LOOSE_BOTTOM_KG_M3
    n_samples: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: (n_fp,) rms over a footprint's samples of the model-error 1-sigma in the likelihood [K]
    model_error_K: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def marginal_top(self) -> np.ndarray:
        """(n_fp, n_top) posterior mass of each top density."""
        return self.probability.sum(axis=2)

    @property
    def marginal_bottom(self) -> np.ndarray:
        """(n_fp, n_bottom) posterior mass of each bottom density."""
        return self.probability.sum(axis=1)

    @property
    def p_loose(self) -> np.ndarray:
        """(n_fp,) P(bottom < ``loose_bottom_kg_m3``) [-] (nodes strictly below the threshold)."""
        return self.marginal_bottom[:, self.bottom_kg_m3 < self.loose_bottom_kg_m3].sum(axis=1)

    def _moments(self, p):
        t = self.top_kg_m3[None, :, None]
        b = self.bottom_kg_m3[None, None, :]
        mt = (p * t).sum(axis=(1, 2))
        mb = (p * b).sum(axis=(1, 2))
        vt = (p * (t - mt[:, None, None]) ** 2).sum(axis=(1, 2))
        vb = (p * (b - mb[:, None, None]) ** 2).sum(axis=(1, 2))
        cov = (p * (t - mt[:, None, None]) * (b - mb[:, None, None])).sum(axis=(1, 2))
        return mt, mb, np.sqrt(vt), np.sqrt(vb), cov

    @property
    def mean_kg_m3(self) -> np.ndarray:
        """(n_fp, 2) posterior mean (top, bottom) [kg m-3]."""
        mt, mb, *_ = self._moments(self.probability)
        return np.column_stack([mt, mb])

    @property
    def sd_kg_m3(self) -> np.ndarray:
        """(n_fp, 2) posterior standard deviation of (top, bottom) [kg m-3]."""
        _, _, st, sb, _ = self._moments(self.probability)
        return np.column_stack([st, sb])

    @property
    def correlation(self) -> np.ndarray:
        """(n_fp,) posterior correlation of top and bottom density [-] (NaN where a sd is 0)."""
        _, _, st, sb, cov = self._moments(self.probability)
        with np.errstate(invalid="ignore", divide="ignore"):
            return cov / (st * sb)

    @property
    def prior_sd_kg_m3(self) -> np.ndarray:
        """(2,) prior standard deviation of (top, bottom) [kg m-3]."""
        _, _, st, sb, _ = self._moments(self.prior[None])
        return np.array([st[0], sb[0]])

    @property
    def width_ratio(self) -> np.ndarray:
        """(n_fp, 2) posterior sd over prior sd of (top, bottom) [-]: near 1, the data say little."""
        return self.sd_kg_m3 / self.prior_sd_kg_m3

    @property
    def map_kg_m3(self) -> np.ndarray:
        """(n_fp, 2) node of highest posterior mass (top, bottom) [kg m-3]."""
        flat = self.probability.reshape(len(self.footprint), -1).argmax(axis=1)
        i, j = np.unravel_index(flat, self.probability.shape[1:])
        return np.column_stack([self.top_kg_m3[i], self.bottom_kg_m3[j]])

    def credible_region(self, mass: float = CREDIBLE_MASS) -> np.ndarray:
        """(n_fp, n_top, n_bottom) bool: the highest-posterior nodes holding at least ``mass`` of it."""
        if not 0.0 < mass < 1.0:
            raise ConfigError(f"mass={mass} out of range (0, 1)")
        n = len(self.footprint)
        p = self.probability.reshape(n, -1)
        order = np.argsort(-p, axis=1, kind="stable")
        ps = np.take_along_axis(p, order, axis=1)
        before = np.cumsum(ps, axis=1) - ps  # mass of the nodes ranked above
        keep_sorted = before < mass
        keep = np.zeros_like(keep_sorted)
        np.put_along_axis(keep, order, keep_sorted, axis=1)
        return keep.reshape(self.probability.shape)

    @staticmethod
    def _step(ax) -> float:
        return float(np.min(np.diff(ax))) if ax.size > 1 else 1.0

    def degeneracy(self) -> list[str]:
        """One sentence per footprint on what the data cannot tell apart (correlation and width ratios)."""
        out = []
        for r, (wt, wb), (st, sb) in zip(self.correlation, self.width_ratio, self.sd_kg_m3):
            words = []
            if wt > 0.7 and wb > 0.7:
                words.append("the data barely constrain either density (marginals near the prior's width)")
            elif wt > 0.7:
                words.append("the top density is barely constrained (marginal near the prior's width)")
            elif wb > 0.7:
                words.append("the bottom density is barely constrained (marginal near the prior's width)")
            # a correlation means something only where both marginals span more than one node
            spread = min(st / self._step(self.top_kg_m3), sb / self._step(self.bottom_kg_m3)) > 0.5
            if spread and np.isfinite(r) and abs(r) >= 0.5:
                kind = "a denser top with a looser bottom" if r < 0 else "both denser or both looser"
                words.append(f"top and bottom trade off (correlation {r:+.2f}: {kind} fit alike)")
            lead = f"sd top {st:.0f}, bottom {sb:.0f} kg m-3 ({wt:.2f}, {wb:.2f} of the prior's)"
            out.append(lead + ("; " + "; ".join(words) if words else "; well constrained"))
        return out


def _prior_array(prior, inside_mask: np.ndarray) -> np.ndarray:
    if isinstance(prior, str):
        if prior != "uniform":
            raise ConfigError(f"prior={prior!r} unknown; allowed: 'uniform' or an (n_top, n_bottom) array of weights")
        p = inside_mask.astype(float)
    else:
        p = np.asarray(prior, float)
        if p.shape != inside_mask.shape:
            raise ConfigError(f"prior has shape {p.shape}; need {inside_mask.shape} (refined top x bottom nodes)")
        if np.any(~np.isfinite(p)) or np.any(p < 0):
            raise ConfigError("prior weights must be finite and >= 0")
        p = np.where(inside_mask, p, 0.0)
    if p.sum() <= 0:
        raise ConfigError("prior has no weight inside the grid")
    return p / p.sum()


def _resolve_instrument(instrument, obs: ObservationTable) -> ins.Instrument:
    if instrument is None:
        instrument = obs.instrument
    if instrument is None:
        raise ConfigError("no instrument: give one (e.g. 'diviner_ch7') or name it in the observations")
    if isinstance(instrument, str):
        return ins.get_instrument(instrument)
    return instrument


def log_likelihood(y, m, white_var, levers, *, independent: bool = False) -> np.ndarray:
    """Gaussian log likelihood of one footprint's samples at many model points (Woodbury, O(n) each).

    Parameters
    ----------
    y : (n,) float [K]            measured brightness temperatures.
    m : (n, P) float [K]          model brightness temperatures at P points.
    white_var : (n, P) or (n, 1) float [K^2]  diagonal (white) variances ((n, 1): the same at every point).
    levers : (n, P, q) or (n, 1, q) float [K]  columns of V (``C = diag(white_var) + V V^T``), per point.
    independent : put ``V V^T``'s diagonal on the diagonal and drop the correlations (comparison only).

    Returns
    -------
    (P,) log likelihood [-], including ``-n/2 log(2 pi)``.
    """
    r = y[:, None] - m
    n = r.shape[0]
    if independent:
        d = white_var + np.sum(levers**2, axis=2)
        return -0.5 * (np.sum(r * r / d, axis=0) + np.sum(np.log(d), axis=0) + n * math.log(2 * math.pi))
    if white_var.shape[1] == 1 and levers.shape[1] == 1:  # one covariance for all points: factor it once
        d, V = white_var[:, 0], levers[:, 0, :]
        Vd = V / d[:, None]
        A = np.eye(V.shape[1]) + V.T @ Vd
        Lc = np.linalg.cholesky(A)
        z = np.linalg.solve(Lc, Vd.T @ r)  # (q, P)
        quad = np.sum(r * r / d[:, None], axis=0) - np.sum(z * z, axis=0)
        logdet = np.sum(np.log(d)) + 2 * np.sum(np.log(np.diag(Lc)))
        return -0.5 * (quad + logdet + n * math.log(2 * math.pi))
    d = np.broadcast_to(white_var, r.shape)
    levers = np.broadcast_to(levers, r.shape + levers.shape[2:])
    Vd = levers / d[:, :, None]  # D^-1 V, (n, P, q)
    A = np.einsum("npi,npj->pij", levers, Vd)
    q = levers.shape[2]
    A[:, np.arange(q), np.arange(q)] += 1.0
    b = np.einsum("npi,np->pi", Vd, r)
    Lc = np.linalg.cholesky(A)
    z = np.linalg.solve(Lc, b[:, :, None])[:, :, 0]
    quad = np.sum(r * r / d, axis=0) - np.sum(z * z, axis=1)
    logdet = np.sum(np.log(d), axis=0) + 2 * np.sum(np.log(np.diagonal(Lc, axis1=1, axis2=2)), axis=1)
    return -0.5 * (quad + logdet + n * math.log(2 * math.pi))


def noise_model(m, obs_rows: ObservationTable, idx, instrument: ins.Instrument, *, natural_scatter_K, offset_K):
    """Covariance pieces of a footprint's samples at model temperatures (module docstring).

    Parameters
    ----------
    m : (n, P) float [K]     brightness temperatures at which the noise is evaluated: the footprint's n
                             samples at P points (``invert`` gives the measurements, P = 1).
    obs_rows, idx : the observation table and the footprint's row indices (n,).

    Returns
    -------
    white_var : (n, P) [K^2]; levers : (n, P, 3) [K] (scatter, offset, gain).
    """
    netd, u, h = _noise_levers(m, instrument)
    sig = obs_rows.sigma_K[idx][:, None]
    dwell = obs_rows.dwell_s[idx]
    has_sig = np.isfinite(sig)
    nsamp = ins.n_samples(np.where(np.isfinite(dwell), dwell, instrument.integration_s), instrument.integration_s)
    per = (1.0 / nsamp + instrument.integration_s / instrument.knee_s)[:, None]
    white = np.where(has_sig, sig**2, netd**2 * per)
    levers = np.stack(
        [np.full(m.shape, float(natural_scatter_K)), float(offset_K) * u, instrument.gain_error * h], axis=2
    )
    return white, levers


def invert(
    forward: ForwardModel,
    obs: ObservationTable,
    instrument: Union[ins.Instrument, str, None] = None,
    *,
    prior="uniform",
    loose_bottom_kg_m3: float = LOOSE_BOTTOM_KG_M3,
    refine: int = DEFAULT_REFINE,
    natural_scatter_K: float = ins.NATURAL_SCATTER_K,
    offset_K: float = 0.0,
    model_error_K: Union[str, float] = "auto",
    independent: bool = False,
    validate: bool = True,
) -> Posterior:
    """Posterior over (top, bottom) density of each footprint of ``obs``.

    Parameters
    ----------
    forward : ForwardModel         the grid replay.
    obs : ObservationTable          the samples (validated against the replay unless ``validate=False``).
    instrument : Instrument or preset name; None: ``obs.instrument``.
    prior : ``"uniform"`` (uniform in density on the refined nodes with top <= bottom inside the grid),
        or (n_top, n_bottom) non-negative weights on the refined nodes (:meth:`ForwardModel.density_axes`).
    loose_bottom_kg_m3 : float [kg m-3]   threshold of :attr:`Posterior.p_loose`.
    refine : int                   refinement of the grid's density step for the posterior nodes.
    natural_scatter_K : float [K]  footprint natural scatter (shared by the footprint's samples).
    offset_K : float [K]           1-sigma calibration offset, in K at the instrument's ``t_ref_K``
        (a radiance offset; shared by a footprint's samples). 0: none.
    model_error_K : ``"auto"`` or float [K]   the forward model's interpolation error between grid
        densities. ``"auto"``: estimated from the grid (:meth:`ForwardModel.model_error_levers`: leave one
        node out, correlated over a footprint's samples); a number: a white (per sample) error of that
        1-sigma size added to every sample's variance; 0: none (the grid interpolation taken as exact).
    independent : bool             treat samples as independent (overconfident; for comparison only).

    Returns
    -------
    Posterior
    """
    inst = _resolve_instrument(instrument, obs)
    if validate:
        obs.validate(forward.times, forward.n_facets)
    auto = isinstance(model_error_K, str)
    if auto and model_error_K != "auto":
        raise ConfigError(f"model_error_K={model_error_K!r} unknown; allowed: 'auto' or a number >= 0 [K]")
    me = 0.0 if auto else float(model_error_K)
    for key, v in (("natural_scatter_K", natural_scatter_K), ("offset_K", offset_K), ("model_error_K", me)):
        if not (math.isfinite(v) and v >= 0):
            raise ConfigError(f"{key}={v} out of range [0, inf)")
    extra_white = me**2
    if not (math.isfinite(loose_bottom_kg_m3) and loose_bottom_kg_m3 > 0):
        raise ConfigError(f"loose_bottom_kg_m3={loose_bottom_kg_m3} out of range (0, inf)")
    ta, ba = forward.density_axes(refine)
    TT, BB = np.meshgrid(ta, ba, indexing="ij")
    prof, wt, inside = forward.weights(TT.ravel(), BB.ravel())
    inside_mask = inside.reshape(TT.shape)
    prior_p = _prior_array(prior, inside_mask)
    use = np.flatnonzero(prior_p.ravel() > 0)
    Wd = _dense_weights(prof[use], wt[use], forward.T.shape[0])  # (P, n_profile)
    log_prior = np.log(prior_p.ravel()[use])
    fps, inverse = np.unique(obs.footprint, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(fps.size + 1))
    prob = np.zeros((fps.size, ta.size * ba.size))
    log_ev = np.zeros(fps.size)
    counts = np.diff(bounds)
    me_rms = np.zeros(fps.size)
    for f in range(fps.size):
        idx = order[bounds[f] : bounds[f + 1]]
        m = _mix(forward, obs.time[idx], obs.facet[idx], obs.facet_weight[idx], Wd, inst.band)
        y_ref = obs.T_b_K[idx][:, None]  # the covariance at the measurements (module docstring)
        white, levers = noise_model(y_ref, obs, idx, inst, natural_scatter_K=natural_scatter_K, offset_K=offset_K)
        if auto:
            vm = forward.model_error_levers(obs.time[idx], obs.facet[idx], obs.facet_weight[idx])
            levers = np.concatenate([levers, vm[:, None, :]], axis=2)
            me_rms[f] = math.sqrt(float(np.mean(np.sum(vm**2, axis=1))))
        else:
            white = white + extra_white
            me_rms[f] = math.sqrt(extra_white)
        ll = log_likelihood(obs.T_b_K[idx], m, white, levers, independent=independent) + log_prior
        top = ll.max()
        p = np.exp(ll - top)
        s = p.sum()
        prob[f, use] = p / s
        log_ev[f] = top + math.log(s)
    return Posterior(
        footprint=fps,
        top_kg_m3=ta,
        bottom_kg_m3=ba,
        probability=prob.reshape(fps.size, ta.size, ba.size),
        prior=prior_p,
        log_evidence=log_ev,
        loose_bottom_kg_m3=float(loose_bottom_kg_m3),
        n_samples=counts,
        model_error_K=me_rms,
    )


# ----------------------------------------------------------------------------- observation design


def expected_width(
    forward: ForwardModel,
    facet: int,
    times: Sequence,
    dwell_s,
    instrument: Union[ins.Instrument, str],
    *,
    truth_kg_m3: tuple[float, float] = (1300.0, 1800.0),
    refine: int = DEFAULT_REFINE,
    natural_scatter_K: float = ins.NATURAL_SCATTER_K,
    offset_K: float = 0.0,
    prior="uniform",
    loose_bottom_kg_m3: float = LOOSE_BOTTOM_KG_M3,
    model_error_K: Union[str, float] = "auto",
) -> dict:
    """Expected posterior widths of a design: sample times x dwell, on one facet.

    The expectation is approximated by the posterior of the noiseless ("Asimov") data ``y = m(truth)``:
    the posterior of the average data set, which carries the expected curvature and the grid's bounds.

    Parameters
    ----------
    forward : ForwardModel
    facet : int                    the facet observed.
    times : sequence of designs, each an array of sample times (datetime64): e.g. one time per design
        (a single sample versus time of night) or several local times.
    dwell_s : (n_dwell,) float [s] dwell of each sample.
    instrument : Instrument or preset name.
    truth_kg_m3 : (top, bottom) [kg m-3]   the profile assumed under the footprint.
    loose_bottom_kg_m3 : float [kg m-3]    threshold of the expected ``p_loose``.
    model_error_K : ``"auto"`` or float [K]   the grid's interpolation error in the likelihood (:func:`invert`).

    Returns
    -------
    dict with ``sd_top_kg_m3``, ``sd_bottom_kg_m3``, ``correlation``, ``p_loose`` each (n_design, n_dwell),
    ``dwell_s`` (n_dwell,), ``n_samples`` (n_design,), ``prior_sd_kg_m3`` (2,), ``prior_p_loose`` (the
    prior's P(loose)), ``truth_kg_m3``.
    """
    inst = ins.get_instrument(instrument) if isinstance(instrument, str) else instrument
    designs = [np.atleast_1d(np.asarray(t, "datetime64[ns]")) for t in times]
    dwells = np.atleast_1d(np.asarray(dwell_s, float))
    rows_t, rows_fp, rows_dw = [], [], []
    fp = 0
    for d in designs:
        for dw in dwells:
            rows_t.append(d)
            rows_fp.append(np.full(d.size, fp))
            rows_dw.append(np.full(d.size, dw))
            fp += 1
    t_all = np.concatenate(rows_t)
    facets = np.full(t_all.size, int(facet))
    y = forward.predict([truth_kg_m3[0]], [truth_kg_m3[1]], t_all, facets, band=inst.band)[:, 0]
    obs = ObservationTable(
        time=t_all,
        facet=facets,
        footprint=np.concatenate(rows_fp),
        T_b_K=y,
        dwell_s=np.concatenate(rows_dw),
        instrument=inst.name,
    )
    post = invert(
        forward,
        obs,
        inst,
        prior=prior,
        refine=refine,
        natural_scatter_K=natural_scatter_K,
        offset_K=offset_K,
        loose_bottom_kg_m3=loose_bottom_kg_m3,
        model_error_K=model_error_K,
    )
    shape = (len(designs), dwells.size)
    sd = post.sd_kg_m3
    return {
        "sd_top_kg_m3": sd[:, 0].reshape(shape),
        "sd_bottom_kg_m3": sd[:, 1].reshape(shape),
        "correlation": post.correlation.reshape(shape),
        "p_loose": post.p_loose.reshape(shape),
        "dwell_s": dwells,
        "n_samples": np.array([d.size for d in designs]),
        "prior_sd_kg_m3": post.prior_sd_kg_m3,
        "prior_p_loose": float(post.prior[:, post.bottom_kg_m3 < post.loose_bottom_kg_m3].sum()),
        "truth_kg_m3": tuple(float(v) for v in truth_kg_m3),
    }
