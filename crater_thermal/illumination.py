"""Direct sunlight on crater facets: the Sun as an extended, limb-darkened disk.

The Sun is sampled into patches on its apparent disk. A patch is a cell of a
polar grid on the disk (``n_rings`` rings of equal radial width; the centre
ring is one cell, ring ``k >= 1`` has ``6 k`` equal sectors, so all cells are
roughly square). Each patch carries the *exact* integral of the limb-darkening
law over its cell and sits at the cell's intensity-weighted centroid, so

* the weights sum to one exactly (times ``S0 (1 au / r)^2`` in
  :func:`direct_irradiance`): limb darkening only redistributes the flux;
* the first moments of the disk are exact, so a facet that sees the whole
  disk gets the flux of the extended Sun up to second order in the disk's
  angular radius (~1e-5 relative).

Limb darkening laws ``I(mu) / I(1)``, ``mu = sqrt(1 - (rho / R)^2)`` the cosine
of the emergence angle on the solar surface (``rho`` the projected distance from
the disk centre, ``R`` the solar radius). All of them are polynomials in ``mu``,
so cell integrals are computed in closed form (``rho d rho = -mu d mu``):

``"uniform"``
    ``I = 1``.
``"linear"`` (default)
    ``I = 1 - u (1 - mu)`` with ``u = 0.54`` (Allen 1973, *Astrophysical
    Quantities*; used by Ingersoll et al. 1992).
``"quadratic"``
    ``I = a0 + a1 mu + a2 mu^2`` with ``a0 = 0.30, a1 = 0.93, a2 = -0.23``
    (Allen's Astrophysical Quantities, 4th ed., Cox 2000, 550 nm).
``"neckel_labs"``
    a fifth-order polynomial ``sum_k A_k mu^k``. Neckel & Labs (1994, Solar
    Phys. 153, 91, Table of ``A_0..A_5`` at 30 continuum wavelengths 303-1099 nm)
    give one polynomial per wavelength; no broadband fit exists. As a
    band-integrated *approximation* the coefficients used here are the average
    of the tabulated ones weighted by a 5772 K Planck spectrum (trapezoid rule
    over the tabulated wavelengths), renormalised so that ``I(1) = 1``. It is an
    approximation: limb darkening is strongest in the blue, and the table stops
    at 1.1 um (the remaining ~25% of the solar flux, in the infrared, darkens
    less). Any other polynomial law can be passed as coefficients to
    :func:`sun_disk` (``law=(c0, c1, ...)``).

Shadows are cast by the crater mesh through a ray tracer (see
:mod:`crater_thermal.raytrace`): a patch lights a facet when the facet faces
it (``cos i > 0``) and the ray from the facet's offset origin toward it is not
occluded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence, Union

import numpy as np

from crater_thermal.choices import ALBEDO_MODELS, LIMB_DARKENING_LAWS
from crater_thermal.constants import ALBEDO, AU, HAYNE2017_ALBEDO_A, HAYNE2017_ALBEDO_B, SOLAR_CONSTANT, SUN_RADIUS
from crater_thermal.errors import ConfigError
from crater_thermal.kernels import illumination as _kern

# --------------------------------------------------------------------- limb darkening

#: Linear limb-darkening coefficient u (Allen 1973; Ingersoll et al. 1992).
LINEAR_U = 0.54
#: Allen/Cox (2000) quadratic law coefficients a0, a1, a2 (550 nm).
QUADRATIC_COEFFS = (0.30, 0.93, -0.23)

# Neckel & Labs (1994), Solar Phys. 153, 91: wavelength [nm] and A0..A5 of
# I(mu)/I(1) = sum_k A_k mu^k for the continuum, 303-1099 nm.
_NECKEL_LABS_1994 = np.array(
    [
        [303.327, 0.08011, 0.70695, 0.49910, -0.31080, -0.02177, 0.04642],
        [310.843, 0.08160, 0.71609, 0.69685, -0.87703, 0.47008, -0.08760],
        [320.468, 0.08833, 0.77285, 0.65382, -1.04647, 0.72921, -0.19775],
        [329.897, 0.09188, 0.92459, 0.19604, -0.39546, 0.23599, -0.05303],
        [349.947, 0.11012, 1.02168, -0.10924, -0.00055, -0.08688, 0.06487],
        [365.875, 0.12828, 1.04969, 0.17482, -1.13371, 1.23882, -0.45990],
        [374.086, 0.12579, 0.85402, 0.54601, -1.15048, 0.88928, -0.26462],
        [390.915, 0.12995, 0.91836, -0.07566, 0.19149, -0.28712, 0.12298],
        [401.970, 0.12323, 1.08648, -0.43974, 0.45912, -0.32759, 0.09850],
        [416.319, 0.12814, 1.19947, -0.84407, 1.07201, -0.79537, 0.23982],
        [427.930, 0.14249, 1.28796, -1.19564, 1.68603, -1.36658, 0.44572],
        [443.885, 0.16220, 1.24893, -0.92165, 0.89978, -0.50148, 0.11220],
        [445.125, 0.15248, 1.38517, -1.49615, 1.99886, -1.48155, 0.44119],
        [457.345, 0.16604, 1.38544, -1.52275, 2.00232, -1.45969, 0.42864],
        [477.427, 0.19571, 1.30551, -1.25845, 1.50626, -1.05472, 0.30570],
        [492.905, 0.20924, 1.30798, -1.20411, 1.21505, -0.67196, 0.14381],
        [519.930, 0.23695, 1.29927, -1.28034, 1.37760, -0.85054, 0.21706],
        [541.760, 0.26073, 1.27428, -1.30352, 1.47085, -0.96618, 0.26384],
        [559.950, 0.26892, 1.34319, -1.58427, 1.91271, -1.31350, 0.37295],
        [579.880, 0.28392, 1.36896, -1.75998, 2.22154, -1.56074, 0.44630],
        [610.975, 0.30854, 1.36620, -1.83572, 2.33221, -1.63082, 0.45959],
        [640.970, 0.33644, 1.30590, -1.79238, 2.45040, -1.89979, 0.59943],
        [669.400, 0.34685, 1.37539, -2.04425, 2.70493, -1.94290, 0.55999],
        [700.875, 0.37885, 1.25553, -1.70908, 2.19647, -1.59554, 0.47378],
        [748.710, 0.40627, 1.22842, -1.67877, 2.05535, -1.39972, 0.38845],
        [811.760, 0.42977, 1.25182, -1.85164, 2.31949, -1.59101, 0.44155],
        [869.600, 0.45396, 1.25101, -2.02958, 2.75410, -2.02287, 0.59338],
        [948.850, 0.47855, 1.19813, -1.86296, 2.36939, -1.64367, 0.46056],
        [1046.60, 0.49870, 1.21429, -2.06976, 2.80703, -2.05247, 0.60221],
        [1098.95, 0.51149, 1.19354, -2.00174, 2.66936, -1.94981, 0.57715],
    ]
)

#: Effective temperature used to weight the Neckel & Labs table [K].
_SUN_TEFF = 5772.0


def _neckel_labs_band_coeffs() -> tuple:
    """Planck-weighted mean of the Neckel & Labs (1994) polynomials, I(1) = 1."""
    lam = _NECKEL_LABS_1994[:, 0] * 1e-9  # [m]
    coeffs = _NECKEL_LABS_1994[:, 1:]
    coeffs = coeffs / coeffs.sum(axis=1, keepdims=True)  # each row: I(1) = 1
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    planck = 1.0 / (lam**5 * np.expm1(h * c / (lam * k * _SUN_TEFF)))
    # trapezoid weights over the (unevenly spaced) tabulated wavelengths
    dl = np.diff(lam)
    tw = np.zeros_like(lam)
    tw[:-1] += dl / 2
    tw[1:] += dl / 2
    w = planck * tw
    mean = (w[:, None] * coeffs).sum(axis=0) / w.sum()
    mean = mean / mean.sum()
    return tuple(float(x) for x in mean)


#: Polynomial coefficients c_k of I(mu)/I(1) = sum_k c_k mu^k, per named law.
LIMB_DARKENING_COEFFS = {
    "uniform": (1.0,),
    "linear": (1.0 - LINEAR_U, LINEAR_U),
    "quadratic": QUADRATIC_COEFFS,
    "neckel_labs": _neckel_labs_band_coeffs(),
}
# LIMB_DARKENING_LAWS, the names of these laws, is declared in crater_thermal.choices (the case
# schema's list) and re-exported here; tests/test_choices.py checks it names exactly these laws.
#: Default law.
DEFAULT_LAW = "linear"
#: Default number of rings of the sampled disk (see :func:`sun_disk`; 37 patches).
DEFAULT_N_RINGS = 4

LawLike = Union[str, Sequence[float]]


def law_coefficients(law: LawLike) -> np.ndarray:
    """Polynomial coefficients ``c_k`` of ``I(mu)/I(1) = sum_k c_k mu^k``.

    Parameters
    ----------
    law : str or sequence of float
        A name from :data:`LIMB_DARKENING_LAWS`, or the coefficients themselves.

    Returns
    -------
    coeffs : (k,) float
    """
    if isinstance(law, str):
        if law not in LIMB_DARKENING_COEFFS:
            raise ConfigError(f"limb_darkening = {law!r} is not a known law; allowed: {', '.join(LIMB_DARKENING_LAWS)}")
        return np.asarray(LIMB_DARKENING_COEFFS[law], dtype=float)
    coeffs = np.asarray(law, dtype=float).ravel()
    if coeffs.size == 0 or not np.all(np.isfinite(coeffs)):
        raise ConfigError(f"limb_darkening coefficients = {law!r} must be a non-empty list of finite numbers")
    mu = np.linspace(0.0, 1.0, 101)
    if np.any(np.polynomial.polynomial.polyval(mu, coeffs) < 0):
        raise ConfigError(f"limb_darkening coefficients = {law!r} give a negative intensity for mu in [0, 1]")
    return coeffs


def limb_darkening(mu: np.ndarray, law: LawLike = DEFAULT_LAW) -> np.ndarray:
    """Relative intensity ``I(mu)/I(1)`` of the solar disk.

    Parameters
    ----------
    mu : array of float [-]
        Cosine of the emergence angle on the solar surface, in [0, 1].
    law : str or sequence of float
        Limb-darkening law (see module docstring).

    Returns
    -------
    intensity : array like ``mu`` [-]
    """
    return np.polynomial.polynomial.polyval(np.asarray(mu, dtype=float), law_coefficients(law))


def _annulus_integral(coeffs: np.ndarray, rho_in: float, rho_out: float) -> float:
    """``int_{rho_in}^{rho_out} I(mu(rho)) rho d rho`` in closed form (rho in disk radii)."""
    mu_in = np.sqrt(max(0.0, 1.0 - rho_in**2))
    mu_out = np.sqrt(max(0.0, 1.0 - rho_out**2))
    k = np.arange(coeffs.size)
    # rho d rho = -mu d mu  ->  int_{mu_out}^{mu_in} c_k mu^(k+1) d mu
    return float(np.sum(coeffs * (mu_in ** (k + 2) - mu_out ** (k + 2)) / (k + 2)))


def disk_fraction_above(law: LawLike, h: float) -> float:
    """Fraction of the disk's flux above the chord ``y = h`` (``h`` in disk radii).

    Exact to quadrature precision (64-point Gauss-Legendre in ``mu``); used by tests
    and by convergence checks.
    """
    coeffs = law_coefficients(law)
    h = float(np.clip(h, -1.0, 1.0))
    x, w = np.polynomial.legendre.leggauss(256)
    # integrate over rho in [0,1] via mu in [0,1]: rho = sqrt(1 - mu^2), rho d rho = mu d mu
    mu = 0.5 * (x + 1.0)
    wm = 0.5 * w
    rho = np.sqrt(1.0 - mu**2)
    intensity = np.polynomial.polynomial.polyval(mu, coeffs)
    # angular fraction of the circle of radius rho (> 0 at every node) lying at y > h
    frac = np.arccos(np.clip(h / rho, -1.0, 1.0)) / np.pi
    total = np.sum(wm * intensity * mu)
    return float(np.sum(wm * intensity * mu * frac) / total)


@dataclass(frozen=True)
class SunDisk:
    """A sampled solar disk.

    Attributes
    ----------
    offsets : (m, 2) float [disk radii]
        Patch positions on the disk, relative to its centre, in units of the
        disk's radius (so the angular offset is ``offsets * asin(R_sun / r)``).
    weights : (m,) float [-]
        Fraction of the Sun's flux carried by each patch; they sum to 1.
    law : str
        Name of the limb-darkening law (or ``"custom"``).
    n_rings : int
        Number of rings of the polar grid.
    """

    offsets: np.ndarray
    weights: np.ndarray
    law: str
    n_rings: int

    @property
    def n_patches(self) -> int:
        """Number of patches ``m``."""
        return int(self.weights.size)


def sun_disk(n_rings: int = DEFAULT_N_RINGS, law: LawLike = DEFAULT_LAW) -> SunDisk:
    """Sample the solar disk into ``1 + 3 n (n - 1)`` limb-darkened patches.

    Ring ``k`` spans ``k/n <= rho < (k+1)/n`` (disk radii); ring 0 is one cell,
    ring ``k >= 1`` is cut into ``6 k`` equal sectors. A patch's weight is the
    exact integral of the law over its cell divided by the disk total; it sits
    at the cell's intensity-weighted centroid.

    Parameters
    ----------
    n_rings : int
        Number of rings, >= 1 (1 = a single patch at the centre, i.e. a point Sun).
        The default (4 rings, 37 patches) is justified in ``bench/sun_disk_convergence.py``.
    law : str or sequence of float
        Limb-darkening law name or polynomial coefficients in ``mu``.

    Returns
    -------
    SunDisk
    """
    if isinstance(n_rings, bool) or not isinstance(n_rings, (int, np.integer)) or not 1 <= n_rings <= 200:
        raise ConfigError(f"n_rings = {n_rings!r} must be an integer in [1, 200]")
    coeffs = law_coefficients(law)
    n = int(n_rings)
    total = _annulus_integral(coeffs, 0.0, 1.0)
    xg, wg = np.polynomial.legendre.leggauss(64)
    offsets = []
    weights = []
    for k in range(n):
        r0, r1 = k / n, (k + 1) / n
        ring = _annulus_integral(coeffs, r0, r1)
        m = 1 if k == 0 else 6 * k
        if k == 0:
            offsets.append((0.0, 0.0))
            weights.append(ring / total)
            continue
        # intensity-weighted mean radius of the annulus (numerical, smooth inside the ring)
        rho = r0 + (r1 - r0) * 0.5 * (xg + 1.0)
        wr = (r1 - r0) * 0.5 * wg
        inten = np.polynomial.polynomial.polyval(np.sqrt(np.clip(1.0 - rho**2, 0.0, None)), coeffs)
        rbar = np.sum(wr * inten * rho**2) / np.sum(wr * inten * rho)
        dphi = 2.0 * np.pi / m
        # centroid of a sector of angular width dphi: factor sin(dphi/2)/(dphi/2)
        rc = rbar * np.sin(dphi / 2) / (dphi / 2)
        phi = dphi * (np.arange(m) + 0.5)
        for p in phi:
            offsets.append((rc * np.cos(p), rc * np.sin(p)))
            weights.append(ring / total / m)
    weights = np.asarray(weights)
    weights = weights / weights.sum()  # exact to rounding
    name = law if isinstance(law, str) else "custom"
    return SunDisk(offsets=np.asarray(offsets, dtype=float), weights=weights, law=name, n_rings=n)


# --------------------------------------------------------------------- directions


def _perpendicular_basis(s: np.ndarray) -> tuple:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, s)`` right-handed orthonormal.

    ``s`` : (nt, 3) unit vectors. ``e1`` is horizontal (``z x s`` normalised) unless
    ``s`` is within ~0.01 rad of the vertical, where ``x x s`` is used instead.
    """
    z = np.array([0.0, 0.0, 1.0])
    x = np.array([1.0, 0.0, 0.0])
    e1 = np.cross(z, s)
    norm = np.linalg.norm(e1, axis=1)
    near_vertical = norm < 1e-2
    if np.any(near_vertical):
        e1[near_vertical] = np.cross(x, s[near_vertical])
        norm[near_vertical] = np.linalg.norm(e1[near_vertical], axis=1)
    e1 /= norm[:, None]
    e2 = np.cross(s, e1)
    return e1, e2


def patch_directions(sun_dirs: np.ndarray, sun_distance_m: np.ndarray, disk: SunDisk | None) -> np.ndarray:
    """Unit directions toward every patch of the solar disk.

    Parameters
    ----------
    sun_dirs : (nt, 3) float [unit]
        Directions toward the Sun's centre.
    sun_distance_m : (nt,) float [m]
        Distances to the Sun.
    disk : SunDisk or None
        ``None`` for a point Sun (one patch, the centre).

    Returns
    -------
    dirs : (nt, m, 3) float [unit]
        Patch ``j`` is the centre rotated by the angle ``|offset_j| * asin(R_sun / r)``
        toward ``offset_j`` (components along ``e1, e2``, see :func:`_perpendicular_basis`).
    """
    s = np.asarray(sun_dirs, dtype=float)
    if disk is None:
        return s[:, None, :].copy()
    alpha = np.arcsin(np.clip(SUN_RADIUS / np.asarray(sun_distance_m, dtype=float), 0.0, 1.0))  # (nt,)
    e1, e2 = _perpendicular_basis(s)
    off = disk.offsets  # (m, 2)
    rho = np.hypot(off[:, 0], off[:, 1])  # (m,)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(rho > 0, off[:, 0] / np.where(rho > 0, rho, 1.0), 0.0)
        uy = np.where(rho > 0, off[:, 1] / np.where(rho > 0, rho, 1.0), 0.0)
    theta = alpha[:, None] * rho[None, :]  # (nt, m)
    ct, st = np.cos(theta), np.sin(theta)
    dirs = (
        ct[:, :, None] * s[:, None, :]
        + (st * ux[None, :])[:, :, None] * e1[:, None, :]
        + (st * uy[None, :])[:, :, None] * e2[:, None, :]
    )
    return dirs


# --------------------------------------------------------------------- irradiance


def _check_inputs(sun_dirs, sun_distance_m, solar_constant):
    s = np.asarray(sun_dirs, dtype=float)
    if s.ndim == 1:
        s = s[None, :]
    if s.ndim != 2 or s.shape[1] != 3:
        raise ConfigError(f"sun_dirs has shape {np.shape(sun_dirs)}; expected (nt, 3)")
    if not np.all(np.isfinite(s)):
        raise ConfigError("sun_dirs contains NaN or inf; expected finite unit vectors")
    norms = np.linalg.norm(s, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-6):
        raise ConfigError(
            f"sun_dirs must be unit vectors; norms range {norms.min():.6g} to {norms.max():.6g} (allowed 1 +- 1e-6)"
        )
    r = np.broadcast_to(np.asarray(sun_distance_m, dtype=float), (s.shape[0],)).copy()
    if not np.all(np.isfinite(r)) or np.any(r <= SUN_RADIUS):
        raise ConfigError(f"sun_distance_m must be finite and > {SUN_RADIUS:g} m; got min {np.min(r):.6g}")
    if not np.isfinite(solar_constant) or solar_constant < 0:
        raise ConfigError(f"solar_constant = {solar_constant!r} W m-2 must be finite and >= 0")
    return s / norms[:, None], r


def direct_irradiance(
    mesh,
    tracer,
    sun_dirs: np.ndarray,
    sun_distance_m: np.ndarray,
    solar_constant: float = SOLAR_CONSTANT,
    disk: SunDisk | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk_rays: int = 2_000_000,
) -> np.ndarray:
    """Direct solar irradiance on every facet at every time.

    ``E[t, f] = S0 (1 au / r_t)^2 * sum_j w_j max(0, n_f . d_tj) * visible(f, d_tj)``
    over the disk's patches ``j`` (weights ``w_j`` summing to 1).

    No ray is cast for a patch that the facet does not face (``n . d <= 0``), and
    a ray that starts above the mesh's highest vertex and points upward is known
    to escape (exact). The remaining rays of many time steps are traced together
    in batches of about ``chunk_rays``.

    Parameters
    ----------
    mesh : geometry.Mesh
        Needs ``normals (nf, 3)`` and ``vertices``.
    tracer : raytrace.RayTracer
        Needs ``occluded(origins, directions)`` and ``facet_origins(idx)``.
    sun_dirs : (nt, 3) float [unit]
        Direction toward the Sun's centre in the crater frame.
    sun_distance_m : (nt,) float [m]
        Sun distance (scales the flux as ``(1 au / r)^2`` and sets the disk's size).
    solar_constant : float [W m-2]
        Solar irradiance at 1 au.
    disk : SunDisk or None
        Sampled disk (:func:`sun_disk`); ``None`` for a point Sun.
    progress : callable, optional
        ``progress(done, total)``, called with the batches of time steps finished so far.
    chunk_rays : int
        Upper bound on the candidate rays prepared per batch (memory control).

    Returns
    -------
    E : (nt, nf) float [W m-2]
    """
    s, r = _check_inputs(sun_dirs, sun_distance_m, solar_constant)
    nt = s.shape[0]
    normals = np.asarray(mesh.normals, dtype=float)
    nf = normals.shape[0]
    flux = solar_constant * (AU / r) ** 2  # (nt,)
    weights = np.ones(1) if disk is None else np.asarray(disk.weights, dtype=float)
    m = weights.size
    out = np.zeros((nt, nf))
    if nt == 0 or nf == 0:
        return out

    origins = np.asarray(tracer.facet_origins(np.arange(nf)), dtype=float)  # (nf, 3)
    z_top = float(np.max(np.asarray(mesh.vertices)[:, 2]))
    above_all = origins[:, 2] > z_top  # rays from here going up escape: no trace needed
    # Fast path: the geometry helper's RayTracer takes pre-centred float32 rays (run_raw).
    use_raw = hasattr(tracer, "run_raw") and hasattr(tracer, "centre")
    shift = np.asarray(tracer.centre, dtype=float) if use_raw else np.zeros(3)
    origins32 = np.ascontiguousarray(origins - shift, dtype=np.float32)

    # Time steps at which no patch can be above any facet's plane are skipped:
    # n.d >= n.s - sin(alpha) for every patch, so the disk is behind facet f if n.s <= -sin(alpha).
    alpha = np.arcsin(SUN_RADIUS / r) if disk is not None else np.zeros(nt)
    max_ns = (s @ normals.T).max(axis=1)  # (nt,)
    active = np.nonzero(max_ns > -np.sin(alpha) - 1e-12)[0]
    # batches of time steps: the dense (steps * patches * facets) cosine block stays ~chunk_rays
    nb = max(1, int(chunk_rays // max(1, m * nf)))
    batches = [active[i : i + nb] for i in range(0, active.size, nb)]

    for n_done, tsel in enumerate(batches, 1):
        dirs = patch_directions(s[tsel], r[tsel], disk).reshape(-1, 3)  # (nb*m, 3)
        block = np.zeros(tsel.size * nf)
        cell, wcos, ray_org, ray_dir = _kern.ray_candidates(dirs, normals, weights, origins32, above_all, block)
        if cell.size:
            if use_raw:
                visible = tracer.run_raw(ray_org, ray_dir) == -1
            else:
                visible = ~np.asarray(tracer.occluded(ray_org.astype(float), ray_dir.astype(float)), dtype=bool)
            _kern.accumulate_visible(block, cell, wcos, visible)
        out[tsel] += block.reshape(tsel.size, nf)
        if progress is not None:
            progress(n_done, len(batches))
    out *= flux[:, None]
    return out


def sun_direction_from_angles(elevation_deg: float, azimuth_deg: float = 180.0) -> np.ndarray:
    """Unit vector toward the Sun in the crater frame (x east, y north, z up).

    Parameters
    ----------
    elevation_deg : float [deg]
        Elevation above the horizontal plane, in [-90, 90].
    azimuth_deg : float [deg]
        Azimuth from north, clockwise (toward east); any finite value (taken modulo 360).

    Returns
    -------
    (3,) float [unit]
    """
    try:
        el = float(elevation_deg)
        az = float(azimuth_deg)
    except (TypeError, ValueError):
        raise ConfigError(f"sun elevation/azimuth must be numbers, got {elevation_deg!r}, {azimuth_deg!r}") from None
    if not np.isfinite(el) or not -90.0 <= el <= 90.0:
        raise ConfigError(f"sun_elevation_deg = {elevation_deg!r} is outside [-90, 90]")
    if not np.isfinite(az):
        raise ConfigError(f"sun_azimuth_deg = {azimuth_deg!r} must be finite (degrees from north, clockwise)")
    e, a = np.deg2rad(el), np.deg2rad(az % 360.0)
    return np.array([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)])


# ------------------------------------------------------------------------- incidence-dependent albedo


def albedo_hayne2017(
    incidence_rad, albedo0: float = ALBEDO, a: float = HAYNE2017_ALBEDO_A, b: float = HAYNE2017_ALBEDO_B
) -> np.ndarray:
    """Directional albedo of regolith for direct sunlight, Hayne et al. (2017) / Keihm (1984).

    ``A(i) = A0 + a (i / 45 deg)^3 + b (i / 90 deg)^8``, with i clipped to [0, 90 deg] and A capped
    at 1.

    Parameters
    ----------
    incidence_rad : array [rad]
        Solar incidence angle from the facet normal.
    albedo0 : float [-]
        Albedo at normal incidence, A0, in [0, 1).
    a, b : float [-]
        Coefficients (Hayne et al. 2017: 0.06, 0.25), >= 0.

    Returns
    -------
    array [-], the shape of ``incidence_rad``.
    """
    if not 0.0 <= albedo0 < 1.0:
        raise ConfigError(f"albedo0={albedo0} out of range [0, 1)")
    if not (a >= 0.0 and b >= 0.0):
        raise ConfigError(f"albedo coefficients a={a}, b={b} must be >= 0")
    i = np.clip(np.asarray(incidence_rad, float), 0.0, 0.5 * np.pi)
    return np.minimum(albedo0 + a * (i / (0.25 * np.pi)) ** 3 + b * (i / (0.5 * np.pi)) ** 8, 1.0)


def direct_albedo(
    normals,
    sun_dirs,
    albedo0: float = ALBEDO,
    model: str = "constant",
    a: float = HAYNE2017_ALBEDO_A,
    b: float = HAYNE2017_ALBEDO_B,
) -> np.ndarray:
    """(nt, nf) albedo [-] each facet applies to direct sunlight at each time.

    The incidence angle is that of the Sun's centre, ``cos i = n . s``; a facet that sees only the
    part of the disk above its horizon (centre below it) is at i = 90 deg. ``model="constant"`` gives
    ``albedo0`` everywhere; ``"hayne2017"`` :func:`albedo_hayne2017`.

    Parameters
    ----------
    normals : (nf, 3) float [unit]
    sun_dirs : (nt, 3) float [unit], crater frame
    """
    if model not in ALBEDO_MODELS:
        raise ConfigError(f"albedo_model={model!r} not one of {', '.join(ALBEDO_MODELS)}")
    n = np.asarray(normals, float)
    s = np.asarray(sun_dirs, float)
    if model == "constant":
        return np.full((s.shape[0], n.shape[0]), float(albedo0))
    cos_i = np.clip(s @ n.T, -1.0, 1.0)
    return albedo_hayne2017(np.arccos(np.maximum(cos_i, 0.0)), albedo0, a, b)
