"""Direct sunlight from horizon maps: per facet, the terrain's horizon elevation at ``n`` azimuths.

The reference method (:func:`crater_thermal.illumination.direct_irradiance`) casts one ray per Sun patch
per facet per step.  A horizon map is built once per mesh instead (Mazarico et al. 2011 build them for
LOLA illumination studies), and each step's direct flux is then a table lookup per facet.

Horizon map
-----------
For every facet and every azimuth ``phi_a = a * 360 / n`` deg (from north, clockwise toward east), the
horizon elevation ``H`` is the boundary between blocked and free occlusion rays from the facet's ray
origin (its centroid lifted along the normal, :mod:`crater_thermal.raytrace`), found by bisection on
the elevation between -90 and +90 deg.  The rays run against the whole mesh, so any outer terrain that
only casts shadows counts.  For terrain that is a height field in z (craters, DEM sites: no
overhangs) a ray is blocked at every elevation below a blocked one, so the bisection finds *the*
horizon; elsewhere it finds one blocked/free transition.  ``k = ceil(log2(180 / tolerance_deg))``
bisection steps leave a bracket of ``180 / 2^k`` deg (0.0055 deg for the default 0.01); the midpoint is
kept, within half of that.  :func:`horizon_map` bisects the full range only at a coarse subset of the
azimuths (every 16th of 720); each finer level predicts the horizon as the mean of its two neighbours
and checks a bracket of the final width around it with two rays.  Where the horizon lies outside, the
bracket steps outward from the failed end by widths growing 2x per ray (:func:`_expand_brackets`)
until a ray brackets it (or the step reaches -90 / +90 deg), then is bisected to the final width.
Rays per facet and azimuth at 20k facets: 3.2 (10 km crater), 4.2 (the same crater as a DEM lattice),
3.5 (rough site), instead of 15 for a full bisection everywhere (and 5.5 / 7.4 / 6.0 with the previous
scheme, a 0.01 deg bracket reset to -90 / +90 deg on a miss), with the same result: within the final
bracket of a full bisection at every facet and azimuth measured (``tests/test_horizons.py``).

Number of azimuths (measured with ``trace_horizons`` against 1440 reference azimuths at 0.0005 deg on
150 random facets; error of the linear interpolation, deg):

====================  ===========================  ===========================
mesh                  360 azimuths max / p99 / rms  720 azimuths max / p99 / rms
====================  ===========================  ===========================
10 km crater, 502     0.077 / 0.006 / 0.002         0.030 / 0.003 / 0.001
10 km crater, 5000    0.053 / 0.005 / 0.002         0.020 / 0.003 / 0.001
rough site, 5000      1.02 / 0.052 / 0.013          0.86 / 0.020 / 0.005
====================  ===========================  ===========================

The maxima on the rough site are near-field horizon jumps (a hill's edge one or two facets away: the
horizon changes by degrees within 0.1 deg of azimuth), which any finite sampling interpolates across
one interval.  Everywhere else the error is far below the Sun's 0.27 deg radius.  The default of 720
(0.5 deg) comes from the lunation-mean flux criterion (1 %, or 1 W m-2 where the flux is tiny, against a
169-patch ray-traced disk, 4 h steps): met on every facet of the craters at 360 and 720; on the rough
site a few facets miss it (2000 facets, 360 azimuths: worst 1.2 W m-2; 1500 facets, 720: < 1 % of the
facets, worst 2.4 W m-2, a step with the Sun on a horizon jump; 1440: none; ``tests/test_horizons.py``).
Memory: 720 float32 per facet, 2.9 kB (290 MB at 100k facets).

Frame: elevations and azimuths are taken in the crater frame (x east, y north, z up) for every
facet, also on meshes that carry the Moon's curvature (the DEM sites' local east/north/up frame).
The Sun is one direction for the whole mesh, so its elevation and azimuth are also one pair per step
in that frame, and the comparison of the Sun with the horizon is exact in any frame: the only
frame-dependent error is the linear interpolation between sampled azimuths.  On a curved site the
horizon of a facet ``x`` km from the centre is tilted by ``x / 1737`` rad against that facet's own
horizontal, i.e. a sinusoid of that amplitude in azimuth, whose interpolation error at 1 deg spacing
is ``amplitude * (pi / 180)^2 / 8``: 6e-5 deg at 50 km.  Keeping one frame makes the per-step work a
single azimuth interpolation weight for all facets, and keeps the height-field argument above valid
(a sphere cap of < 90 deg is a height field in z).  The azimuth parameterisation is singular only at
the zenith, where no horizon lies.

Direct flux
-----------
``E = S0 (1 au / r)^2 [F(h) (n . s) + alpha G(h) (n . m)]`` per facet and step
(:func:`crater_thermal.kernels.horizons.horizon_direct`): the horizon near the Sun is the line through
the interpolated ``H`` with the interpolated azimuthal slope, ``h`` the signed distance of the disk
centre below it in solar radii (``alpha = asin(R_sun / r)``), ``F(h)`` the fraction of the
limb-darkened disk's flux above the line and ``G(h)`` its first moment along the line's normal ``m``
[disk radii].  The incidence cosine is linear in the position on the disk, so this is the disk
integral of ``I cos i`` over the visible segment to first order in ``alpha`` (the second-order
remainder is ``alpha^2 / 2 ~ 1e-5`` relative).  Where the Sun is entirely above the horizon it is the
disk centre's cosine.  ``F`` and ``G`` come from closed-form integrals of the polynomial limb-darkening
laws of :mod:`crater_thermal.illumination` (:func:`segment_tables`), tabulated at ``SEGMENT_SAMPLES``
values of ``theta = arccos(h)`` (uniform in ``theta``: smooth there, where ``F(h)`` has square-root
ends) and interpolated linearly: within 2e-7 of the closed form.

Cache: with ``cache_dir`` the map is stored as ``horizons_<mesh.hash>_<version, n, tolerance>.npz``
(atomic write via :func:`crater_thermal.io.save_npz_atomic`) and read back for the same mesh.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from crater_thermal import io
from crater_thermal.choices import SUN_METHODS
from crater_thermal.constants import AU, SOLAR_CONSTANT, SUN_RADIUS
from crater_thermal.errors import ConfigError, MeshError
from crater_thermal.illumination import DEFAULT_LAW, LawLike, law_coefficients
from crater_thermal.kernels import horizons as kern

__all__ = [
    "DEFAULT_N_AZIMUTHS",
    "DEFAULT_TOLERANCE_DEG",
    "HORIZON_VERSION",
    "SEGMENT_SAMPLES",
    "SUN_METHODS",
    "HorizonMap",
    "direct_irradiance_horizon",
    "disk_segment",
    "horizon_map",
    "segment_tables",
    "trace_horizons",
]

#: Sampled azimuths per facet (see the module docstring and ``bench/horizons.py`` for the measurement).
DEFAULT_N_AZIMUTHS = 720
#: Bisection bracket [deg]: the horizon is kept within half of it.
DEFAULT_TOLERANCE_DEG = 0.01
#: Samples of the disk-segment tables in ``theta = arccos(h)`` over [0, pi].
SEGMENT_SAMPLES = 4097
#: Coarsest level of :func:`horizon_map`: at least this many azimuths get a full bisection.
MIN_COARSE_AZIMUTHS = 32
#: Finer levels start from the bracket ``mean +- BRACKET_MARGIN * final bracket`` around the mean of the
#: two neighbours' horizons (checked by two rays): just under half the final bracket, so that where the
#: prediction holds the two rays are the whole search (measured: 3.2-4.2 rays per facet and azimuth
#: on craters and the rough site, against 4.8-5.4 at 4x this margin and 5.5-7.4 at 0.01 deg).
BRACKET_MARGIN = 0.49
#: Where that bracket misses, it grows outward from the failed end by this factor per ray
#: (:func:`_expand_brackets`; measured best of 2, 3, 4, 8, 16, 32).
BRACKET_GROWTH = 2.0
#: Part of the cache key: bump when the algorithm changes the numbers.
HORIZON_VERSION = "v2"
#: Occlusion rays per batch (memory: ~40 bytes per ray).
CHUNK_RAYS = 1 << 20

ProgressFn = Callable[[int, int], None]


# ------------------------------------------------------------------------------- disk segment tables


def _chord_betas(n_coeffs: int) -> np.ndarray:
    """``beta_k = int_{-1}^{1} (1 - t^2)^(k/2) dt = sqrt(pi) Gamma(k/2 + 1) / Gamma(k/2 + 3/2)``."""
    k = np.arange(n_coeffs, dtype=float)
    return np.array([math.sqrt(math.pi) * math.gamma(x / 2 + 1) / math.gamma(x / 2 + 1.5) for x in k])


@lru_cache(maxsize=16)
def _tables_cached(coeffs: tuple, n: int) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(coeffs, dtype=float)
    frac, mom = kern.segment_tables(c, _chord_betas(c.size), n)
    frac.setflags(write=False)
    mom.setflags(write=False)
    return frac, mom


def segment_tables(law: LawLike = DEFAULT_LAW, n: int = SEGMENT_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Disk-segment tables of a limb-darkening law.

    Parameters
    ----------
    law : str or sequence of float
        A law of :mod:`crater_thermal.illumination` or its polynomial coefficients in ``mu``.
    n : int
        Samples, at ``theta_j = j pi / (n - 1)``; the chord lies at ``h = cos(theta)`` disk radii.

    Returns
    -------
    frac : (n,) float64 [-]
        Fraction of the disk's flux at ``y > h`` (0 at ``theta = 0``, 1 at ``theta = pi``).
    moment : (n,) float64 [disk radii]
        ``int_{y > h} y I dA / int I dA``.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        raise ConfigError(f"segment table samples n = {n!r} must be an integer >= 3")
    coeffs = tuple(float(x) for x in law_coefficients(law))
    return _tables_cached(coeffs, int(n))


def disk_segment(h, law: LawLike = DEFAULT_LAW) -> tuple[np.ndarray, np.ndarray]:
    """Visible fraction and first moment of the disk above the chord ``y = h``, interpolated from the tables.

    Parameters
    ----------
    h : array of float [disk radii]
        Signed distance of the chord above the disk centre (clipped to [-1, 1]).
    law : str or sequence of float

    Returns
    -------
    frac : array like ``h`` [-]
    moment : array like ``h`` [disk radii]
    """
    frac_t, mom_t = segment_tables(law)
    theta = np.arccos(np.clip(np.asarray(h, dtype=float), -1.0, 1.0))
    grid = np.linspace(0.0, math.pi, frac_t.size)
    return np.interp(theta, grid, frac_t), np.interp(theta, grid, mom_t)


# --------------------------------------------------------------------------------------- horizon map


@dataclass(frozen=True)
class HorizonMap:
    """Horizon elevations of every facet of one mesh.

    Attributes
    ----------
    elevation : (n_azimuths, n_facets) float32 [rad]
        Horizon elevation at azimuth ``a * 2 pi / n_azimuths`` (from north, clockwise toward east), in
        the crater frame.
    mesh_hash : str
        :attr:`crater_thermal.geometry.Mesh.hash` of the mesh it belongs to.
    tolerance_deg : float [deg]
        Bisection bracket (the elevations are within half of it of the traced boundary).
    build_s : float [s]
        Wall time of the build (0 when read from the cache).
    """

    elevation: np.ndarray
    mesh_hash: str
    tolerance_deg: float
    build_s: float = 0.0

    @property
    def n_azimuths(self) -> int:
        """Number of sampled azimuths."""
        return int(self.elevation.shape[0])

    @property
    def n_facets(self) -> int:
        """Number of facets."""
        return int(self.elevation.shape[1])

    @property
    def azimuths(self) -> np.ndarray:
        """(n_azimuths,) float64 [rad]: the sampled azimuths."""
        return np.arange(self.n_azimuths) * (2.0 * math.pi / self.n_azimuths)

    def at(self, azimuth_rad: float) -> np.ndarray:
        """(n_facets,) float64 [rad]: horizon at one azimuth, linear between the sampled ones."""
        u = (float(azimuth_rad) % (2.0 * math.pi)) / (2.0 * math.pi / self.n_azimuths)
        i0 = int(u) % self.n_azimuths
        w = u - int(u)
        e = self.elevation
        return (1.0 - w) * e[i0].astype(float) + w * e[(i0 + 1) % self.n_azimuths].astype(float)


def _cache_file(cache_dir, mesh_hash: str, n_az: int, tol_deg: float, offset_key: str) -> Path:
    return Path(cache_dir) / f"horizons_{mesh_hash}_{HORIZON_VERSION}_n{n_az}_t{tol_deg:g}_{offset_key}.npz"


def _load(path: Path, mesh_hash: str, n_az: int, nf: int) -> Optional[np.ndarray]:
    try:
        z = io.load_npz(path)
        if str(z["mesh_hash"]) != mesh_hash or str(z["version"]) != HORIZON_VERSION:
            return None
        elev = np.asarray(z["elevation"], dtype=np.float32)
    except (OSError, KeyError, ValueError):
        return None
    return elev if elev.shape == (n_az, nf) else None


def _cache_path(mesh, tracer, n_az: int, tol: float, cache_dir) -> Optional[Path]:
    if cache_dir is None:
        return None
    offsets = np.asarray(tracer.offsets, dtype=float)
    offset_key = f"o{float(np.median(offsets / np.asarray(mesh.facet_size))):.3g}"
    return _cache_file(cache_dir, mesh.hash, n_az, tol, offset_key)


def _cached(path: Optional[Path], mesh, n_az: int, tol: float) -> Optional[HorizonMap]:
    if path is None or not path.is_file():
        return None
    elev = _load(path, mesh.hash, n_az, mesh.n_facets)
    if elev is None:
        return None
    elev.setflags(write=False)
    return HorizonMap(elev, mesh.hash, tol, 0.0)


def cached(
    mesh, tracer, n_azimuths: int = DEFAULT_N_AZIMUTHS, tolerance_deg: float = DEFAULT_TOLERANCE_DEG, cache_dir=None
) -> Optional[HorizonMap]:
    """The map :func:`horizon_map` would read from ``cache_dir`` with these settings, or None (no
    folder, no file, or a file for another mesh or version). Arguments as :func:`horizon_map`'s
    (``tolerance_deg`` [deg])."""
    return _cached(
        _cache_path(mesh, tracer, int(n_azimuths), float(tolerance_deg), cache_dir),
        mesh,
        int(n_azimuths),
        float(tolerance_deg),
    )


def horizon_map(
    mesh,
    tracer,
    n_azimuths: int = DEFAULT_N_AZIMUTHS,
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG,
    cache_dir=None,
    progress: Optional[ProgressFn] = None,
    chunk_rays: int = CHUNK_RAYS,
    read_cache: bool = True,
) -> HorizonMap:
    """Trace the horizon of every facet at ``n_azimuths`` azimuths.

    Parameters
    ----------
    mesh : geometry.Mesh
    tracer : raytrace.RayTracer
        Built on ``mesh`` (its facet ray origins and scene are used).
    n_azimuths : int
        Azimuths per facet, 8..4096.
    tolerance_deg : float [deg]
        Bisection bracket, in [1e-4, 1]: ``ceil(log2(180 / tolerance_deg))`` occlusion rays per facet
        and azimuth.
    cache_dir : path-like, optional
        Folder of the cache (read if a map for this mesh and settings is there, else written).
    progress : callable(done, total), optional
        Called after each batch with the facets done so far and the total.
    chunk_rays : int
        Rays traced per batch (memory control).
    read_cache : bool
        False: trace even if the cache holds a map (it is still written). A map traced on a second
        thread is asked for this way after the calling thread has looked in the cache (:func:`cached`):
        reading a cached ``.npz`` parses its header with ``ast.literal_eval``, which CPython 3.11.7 does
        not allow on two threads at once (gh-106905: "AST constructor recursion depth mismatch").

    Returns
    -------
    HorizonMap
    """
    import time

    if isinstance(n_azimuths, bool) or not isinstance(n_azimuths, (int, np.integer)) or not 8 <= n_azimuths <= 4096:
        raise ConfigError(f"n_azimuths = {n_azimuths!r} must be an integer in [8, 4096]")
    try:
        tol = float(tolerance_deg)
    except (TypeError, ValueError):
        raise ConfigError(f"tolerance_deg = {tolerance_deg!r} must be a number") from None
    if not 1e-4 <= tol <= 1.0:
        raise ConfigError(f"tolerance_deg = {tolerance_deg!r} must be in [1e-4, 1] deg")
    if getattr(tracer, "mesh", None) is not None and tracer.mesh.hash != mesh.hash:
        raise MeshError("horizon_map: the ray tracer was built on a different mesh")
    n_az = int(n_azimuths)
    nf = mesh.n_facets
    path = _cache_path(mesh, tracer, n_az, tol, cache_dir)
    if read_cache:
        found = _cached(path, mesh, n_az, tol)
        if found is not None:
            return found

    t0 = time.perf_counter()
    elev = np.empty((n_az, nf), dtype=np.float32)
    per_chunk = max(1, int(chunk_rays) // n_az)
    for f0 in range(0, nf, per_chunk):
        f1 = min(nf, f0 + per_chunk)
        elev[:, f0:f1] = _trace_hierarchical(tracer, np.arange(f0, f1), n_az, tol, chunk_rays).T
        if progress is not None:
            progress(f1, nf)
    elev.setflags(write=False)
    build_s = time.perf_counter() - t0
    if path is not None:
        try:
            io.save_npz_atomic(path, elevation=elev, mesh_hash=np.array(mesh.hash), version=np.array(HORIZON_VERSION))
        except OSError as exc:  # a full or read-only cache costs the next run time, never this run
            warnings.warn(f"horizon map not cached in {path.parent} ({exc.strerror or exc})", stacklevel=2)
    return HorizonMap(elev, mesh.hash, tol, build_s)


def _trace_hierarchical(tracer, idx: np.ndarray, n_az: int, tol_deg: float, chunk_rays: int) -> np.ndarray:
    """Horizons at ``n_az`` uniform azimuths, coarse to fine (see :func:`horizon_map`); (len(idx), n_az) [rad]."""
    az = np.arange(n_az) * (2.0 * math.pi / n_az)
    stride = 1
    while n_az % (2 * stride) == 0 and n_az // (2 * stride) >= MIN_COARSE_AZIMUTHS:
        stride *= 2
    H = np.empty((idx.size, n_az))
    H[:, ::stride] = trace_horizons(tracer, idx, az[::stride], tol_deg, chunk_rays)
    n_iter = max(1, math.ceil(math.log2(180.0 / float(tol_deg))))
    final_width = math.pi / 2.0**n_iter * (1.0 + 1e-9)  # the bracket a full bisection ends with
    origins32 = np.ascontiguousarray(tracer.facet_origins(idx) - np.asarray(tracer.centre), dtype=np.float32)
    margin = BRACKET_MARGIN * final_width
    while stride > 1:
        half = stride // 2
        new = np.arange(half, n_az, stride)
        left, right = H[:, new - half], H[:, (new + half) % n_az]
        mid = 0.5 * (left + right)
        lo = np.maximum(mid - margin, -0.5 * math.pi).ravel()
        hi = np.minimum(mid + margin, 0.5 * math.pi).ravel()
        n = lo.size
        org = np.repeat(origins32, new.size, axis=0)
        sa = np.tile(np.sin(az[new]), idx.size)
        ca = np.tile(np.cos(az[new]), idx.size)
        # check the bracket's ends; where the horizon lies outside, extend it to -90 or +90 deg
        dirs = np.empty((2 * n, 3), dtype=np.float32)
        kern.elevation_directions(np.concatenate([lo, hi]), np.concatenate([sa, sa]), np.concatenate([ca, ca]), dirs)
        hit = tracer.run_raw(np.concatenate([org, org]), dirs) != -1
        lo_free, hi_blocked = ~hit[:n], hit[n:]
        both = lo_free & hi_blocked  # inconsistent (not a height field here): search everything
        _expand_brackets(tracer, org, sa, ca, lo, hi, lo_free & ~both, hi_blocked & ~both, margin)
        lo[both], hi[both] = -0.5 * math.pi, 0.5 * math.pi
        act = np.nonzero(hi - lo > final_width)[0]
        while act.size:
            la, ha = lo[act], hi[act]
            d = np.empty((act.size, 3), dtype=np.float32)
            kern.elevation_directions(0.5 * (la + ha), sa[act], ca[act], d)
            hit_a = tracer.run_raw(np.ascontiguousarray(org[act]), d)
            kern.bisection_update(la, ha, hit_a)
            lo[act], hi[act] = la, ha
            act = act[ha - la > final_width]
        H[:, new] = (0.5 * (lo + hi)).reshape(idx.size, new.size)
        stride = half
    return H


def _expand_brackets(tracer, org, sa, ca, lo, hi, below, above, margin: float) -> None:
    """Re-bracket the horizons that fell outside their predicted bracket ``[lo, hi]`` (in place).

    ``below``: the ray at ``lo`` was free (the horizon is lower); ``above``: the ray at ``hi`` was
    blocked (the horizon is higher).  The bracket steps outward from the failed end by widths
    ``margin * BRACKET_GROWTH**k`` (one ray each) until a ray on the far side brackets the horizon or
    the step reaches -90 / +90 deg, so a prediction that missed by a little costs a few rays and a short
    bisection instead of one over the whole half range.  Valid wherever the blocked elevations are
    the ones below the horizon (a height field), like the bisection itself.
    """
    half_pi = 0.5 * math.pi
    # below: the free ray at lo becomes the upper end; above: the blocked ray at hi becomes the lower end
    hi[below] = lo[below]
    lo[above] = hi[above]
    act = np.nonzero(below | above)[0]
    down = below[act]
    step = margin * BRACKET_GROWTH
    while act.size:
        cand = np.where(down, hi[act] - step, lo[act] + step)
        at_end = np.where(down, cand <= -half_pi, cand >= half_pi)
        # reached the end of the range: -90 deg counts as blocked and +90 deg as free, as in a full bisection
        lo[act[at_end & down]] = -half_pi
        hi[act[at_end & ~down]] = half_pi
        keep = ~at_end
        act, down, cand = act[keep], down[keep], cand[keep]
        if not act.size:
            break
        d = np.empty((act.size, 3), dtype=np.float32)
        kern.elevation_directions(cand, sa[act], ca[act], d)
        blocked = tracer.run_raw(np.ascontiguousarray(org[act]), d) != -1
        # a blocked ray is a new lower end, a free one a new upper end; a blocked ray below (or a free
        # one above) closes the bracket, otherwise the search goes on from the moved near end
        lo[act[blocked]] = cand[blocked]
        hi[act[~blocked]] = cand[~blocked]
        open_ = np.where(down, ~blocked, blocked)
        act, down = act[open_], down[open_]
        step *= BRACKET_GROWTH


def trace_horizons(
    tracer, facet_idx, azimuths_rad, tolerance_deg: float = DEFAULT_TOLERANCE_DEG, chunk_rays: int = CHUNK_RAYS
) -> np.ndarray:
    """Horizon elevation of some facets at arbitrary azimuths (bisection on occlusion rays).

    Parameters
    ----------
    tracer : raytrace.RayTracer
    facet_idx : (n,) int
    azimuths_rad : (m,) float [rad]
        From north, clockwise toward east.
    tolerance_deg : float [deg]
        Final bisection bracket.
    chunk_rays : int
        Rays per batch.

    Returns
    -------
    (n, m) float64 [rad]
    """
    idx = np.asarray(facet_idx, dtype=np.int64).ravel()
    az = np.asarray(azimuths_rad, dtype=float).ravel()
    n_az = az.size
    n_iter = max(1, math.ceil(math.log2(180.0 / float(tolerance_deg))))
    sin_az, cos_az = np.sin(az), np.cos(az)
    origins32 = np.ascontiguousarray(tracer.facet_origins(idx) - np.asarray(tracer.centre), dtype=np.float32)
    out = np.empty((idx.size, n_az))
    per_chunk = max(1, int(chunk_rays) // max(1, n_az))
    for f0 in range(0, idx.size, per_chunk):
        f1 = min(idx.size, f0 + per_chunk)
        n_rays = (f1 - f0) * n_az
        org = np.ascontiguousarray(np.repeat(origins32[f0:f1], n_az, axis=0))
        lo = np.full(n_rays, -0.5 * math.pi)
        hi = np.full(n_rays, 0.5 * math.pi)
        dirs = np.empty((n_rays, 3), dtype=np.float32)
        for _ in range(n_iter):
            kern.bisection_directions(lo, hi, sin_az, cos_az, n_az, dirs)
            hit = tracer.run_raw(org, dirs)
            kern.bisection_update(lo, hi, hit)
        out[f0:f1] = (0.5 * (lo + hi)).reshape(f1 - f0, n_az)
    return out


# ------------------------------------------------------------------------------------------ direct flux


def direct_irradiance_horizon(
    mesh,
    hmap: HorizonMap,
    sun_dirs: np.ndarray,
    sun_distance_m: np.ndarray,
    solar_constant: float = SOLAR_CONSTANT,
    law: LawLike | None = DEFAULT_LAW,
    chunk_steps: int = 256,
) -> np.ndarray:
    """Direct solar irradiance on every facet at every time, from a horizon map.

    Parameters
    ----------
    mesh : geometry.Mesh
        The mesh of ``hmap`` (normals are used).
    hmap : HorizonMap
    sun_dirs : (nt, 3) float [unit]
        Direction toward the Sun's centre, crater frame.
    sun_distance_m : (nt,) float [m]
    solar_constant : float [W m-2]
        At 1 au.
    law : str, sequence of float or None
        Limb-darkening law (``None``: a point Sun).
    chunk_steps : int
        Steps per kernel call (no effect on the result).

    Returns
    -------
    E : (nt, nf) float64 [W m-2]
    """
    if hmap.mesh_hash != mesh.hash:
        raise MeshError(f"horizon map was built for mesh {hmap.mesh_hash}, not {mesh.hash}")
    s = np.asarray(sun_dirs, dtype=float)
    if s.ndim == 1:
        s = s[None, :]
    if s.ndim != 2 or s.shape[1] != 3 or not np.all(np.isfinite(s)):
        raise ConfigError(f"sun_dirs must be finite with shape (nt, 3), got shape {np.shape(sun_dirs)}")
    norms = np.linalg.norm(s, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-6):
        raise ConfigError(f"sun_dirs must be unit vectors; norms range {norms.min():.6g} to {norms.max():.6g}")
    s = np.ascontiguousarray(s / norms[:, None])
    r = np.broadcast_to(np.asarray(sun_distance_m, dtype=float), (s.shape[0],))
    if not np.all(np.isfinite(r)) or np.any(r <= SUN_RADIUS):
        raise ConfigError(f"sun_distance_m must be finite and > {SUN_RADIUS:g} m")
    if not np.isfinite(solar_constant) or solar_constant < 0:
        raise ConfigError(f"solar_constant = {solar_constant!r} W m-2 must be finite and >= 0")
    nt, nf = s.shape[0], mesh.n_facets
    if law is None:
        alpha = np.zeros(nt)
        frac_t, mom_t = segment_tables(DEFAULT_LAW)
    else:
        alpha = np.arcsin(SUN_RADIUS / r)
        frac_t, mom_t = segment_tables(law)
    normals = np.ascontiguousarray(mesh.normals, dtype=float)
    out = np.empty((nt, nf))
    step = max(1, int(chunk_steps))
    for t0 in range(0, nt, step):
        t1 = min(nt, t0 + step)
        kern.horizon_direct(hmap.elevation, s[t0:t1], alpha[t0:t1], normals, frac_t, mom_t, out[t0:t1])
    out *= (solar_constant * (AU / r) ** 2)[:, None]
    return out
