"""Height-field test terrains as triangle meshes (two triangles per grid cell, normals up).

``pcc_topo81()`` is our own rebuild of the Planetary-Code-Collection Topo3D test terrain
(nschorgh/Planetary-Code-Collection, ``Topo3D/Test/topo81.xyz``, made by its ``maketopo.f90``):
81 x 81 heights at 5 m spacing, a spherical bowl of depth/diameter 1:5 in an exactly flat plain.
Fitting a spherical cap to that file (commit 89905f2, fetched 2026-12-01) gives a rim diameter
of 344.83 m (10000/29 m); this rebuild, rounded to 1 mm as the file is, matches every one of its
6561 heights to 1 mm (the rounding).  The file itself is not copied here.  Triangulated it has
12,800 facets: the terrain on which view factors wrote out of bounds (issue 11).
"""

from __future__ import annotations

import numpy as np

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
    """The rebuilt PCC Topo3D test terrain (module docstring): 12,800 facets."""
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
