"""Reference terrains and forcings shared by the tests and the benchmarks (no physics lives here).

* :func:`grid_mesh`: a height field on a rectangular grid as a triangle mesh (two triangles per cell,
  normals up).
* :func:`spherical_bowl`: heights [m] of Ingersoll's spherical-cap bowl in a flat plain.
* :func:`pcc_topo81`: our own rebuild of the Planetary-Code-Collection Topo3D test terrain
  (nschorgh/Planetary-Code-Collection, ``Topo3D/Test/topo81.xyz``, made by its ``maketopo.f90``): 81 x 81
  heights at 5 m spacing, a spherical bowl of depth/diameter 1:5 in an exactly flat plain. Fitting a
  spherical cap to that file (commit 89905f2, fetched 2026-12-01) gives a rim diameter of 344.83 m
  (10000/29 m); this rebuild, rounded to 1 mm as the file is, matches every one of its 6561 heights to
  1 mm (the rounding). The file itself is not copied here. Triangulated it has 12,800 facets.
* :func:`terrace_mesh`: two plains joined by a vertical cliff (coplanar and right-angle facet pairs).
* :func:`rough_site`: a crater in self-affine random terrain (Hurst exponent 0.8, RMS slope ~12 deg at
  the grid scale, the order of lunar highland roughness at 50-100 m baselines), from a fixed seed: many
  small hills that cast and receive shadows at all azimuths. Not a physics reference.
* :func:`synthetic_absorbed_flux`: half-analytic absorbed-flux series of a shadowed floor and a sunlit
  wall, for conduction tests and benchmarks.

Lengths in metres, fluxes in W m-2, times in seconds.
"""

from __future__ import annotations

import math

import numpy as np

from crater_thermal.constants import LUNAR_DAY, YEAR
from crater_thermal.geometry import Mesh


def grid_mesh(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> Mesh:
    """Mesh of the height field ``z[iy, ix]`` [m] on the grid ``x`` (nx,), ``y`` (ny,) [m].

    Each cell is split into two triangles along its (0,0)-(1,1) diagonal, counter-clockwise seen
    from above, so every normal has a positive z component.
    """
    ny, nx = z.shape
    X, Y = np.meshgrid(np.asarray(x, float), np.asarray(y, float))
    V = np.column_stack([X.ravel(), Y.ravel(), np.asarray(z, float).ravel()])
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return Mesh(V, F)


def spherical_bowl(r: np.ndarray, diameter_m: float, depth_to_diameter: float) -> np.ndarray:
    """Heights [m] of a spherical-cap bowl (rim at z = 0, flat plain outside) at radii ``r`` [m]."""
    d = depth_to_diameter * diameter_m
    rs = (diameter_m**2 / 4 + d**2) / (2 * d)  # sphere radius
    inside = r < diameter_m / 2
    z = rs - d - np.sqrt(np.clip(rs**2 - r**2, 0.0, None))
    return np.where(inside, np.minimum(z, 0.0), 0.0)


def pcc_topo81() -> Mesh:
    """The rebuilt PCC Topo3D test terrain (see the module docstring): 12,800 facets."""
    x = (np.arange(81) - 40) * 5.0
    X, Y = np.meshgrid(x, x)
    z = np.round(spherical_bowl(np.hypot(X, Y), 10000.0 / 29.0, 0.2), 3)
    return grid_mesh(x, x, z)


def terrace_mesh(nx: int, ny: int, step_m: float, size_m: float = 100.0) -> Mesh:
    """Two flat plains joined by a vertical cliff: z = 0 for x < 0 and z = ``step_m`` for x > 0.

    The cliff is a strip of vertical facets at x = 0 facing the low plain (normal -x).  Every facet
    is exactly flat or exactly vertical: coplanar pairs and pairs at right angles everywhere.
    """
    x_lo = np.linspace(-size_m / 2, 0.0, nx)
    x_hi = np.linspace(0.0, size_m / 2, nx)
    y = np.linspace(-size_m / 2, size_m / 2, ny)
    lo = grid_mesh(x_lo, y, np.zeros((ny, nx)))
    hi = grid_mesh(x_hi, y, np.full((ny, nx), float(step_m)))
    # wall: the low plain's x = 0 edge (bottom) to the high plain's x = 0 edge (top)
    bottom = np.column_stack([np.zeros(ny), y, np.zeros(ny)])
    top = np.column_stack([np.zeros(ny), y, np.full(ny, float(step_m))])
    V = np.concatenate([lo.vertices, hi.vertices, bottom, top])
    nb = lo.vertices.shape[0] + hi.vertices.shape[0]
    b = nb + np.arange(ny)
    t = b + ny
    # quads (b_k, b_k+1, t_k+1, t_k); winding chosen so that the normal points to -x
    wall = np.concatenate([np.column_stack([b[:-1], t[1:], b[1:]]), np.column_stack([b[:-1], t[:-1], t[1:]])])
    F = np.concatenate([lo.faces, hi.faces + lo.vertices.shape[0], wall])
    return Mesh(V, F)


def rough_site(
    n_facets: int = 2000,
    size_m: float = 6000.0,
    crater_diameter_m: float = 3000.0,
    rms_slope_deg: float = 12.0,
    seed: int = 7,
) -> Mesh:
    """Mesh of ``2 n^2 ~ n_facets`` facets over a ``size_m`` square centred on the origin [m]."""
    n = max(4, int(round(math.sqrt(n_facets / 2.0))))
    xs = np.linspace(-0.5 * size_m, 0.5 * size_m, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="xy")
    r = np.hypot(X, Y) / (0.5 * crater_diameter_m)
    depth = 0.2 * crater_diameter_m
    rim = 0.04 * crater_diameter_m
    z = np.where(r < 1.0, (rim + depth) * r**2 - depth, rim * np.exp(-(((r - 1.0) / 0.35) ** 2)))
    # self-affine roughness: spectral synthesis, amplitude ~ k^-(1 + H)
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n + 1)
    K = np.hypot(*np.meshgrid(k, k, indexing="xy"))
    K[0, 0] = np.inf
    amp = K ** -(1.0 + 0.8)
    field = np.real(np.fft.ifft2(amp * np.exp(2j * np.pi * rng.random(K.shape))))
    dx = xs[1] - xs[0]
    gy, gx = np.gradient(field, dx)
    field *= math.tan(math.radians(rms_slope_deg)) / math.sqrt(np.mean(gx**2 + gy**2))
    Z = z + field
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(V.shape[0]).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(V, F, {"kind": "file", "source": "rough_site", "size_m": size_m, "seed": seed})


def synthetic_absorbed_flux(kind: str, t: np.ndarray) -> np.ndarray:
    """Synthetic absorbed flux [W m-2] at times ``t`` [s]: ``"floor"`` (no sun: IR of a few W m-2 from
    walls lit during the lunar day, with a seasonal modulation) or ``"wall"`` (lunar-day solar pulses)."""
    ph = 2 * np.pi * np.asarray(t, float) / LUNAR_DAY
    season = 1 + 0.3 * np.sin(2 * np.pi * np.asarray(t, float) / YEAR)
    if kind == "floor":
        return (0.3 + 12.0 * np.maximum(0.0, np.cos(ph))) * season
    return 500.0 * np.maximum(0.0, np.cos(ph)) * season + 3.0 + 0.5 * np.sin(ph)
