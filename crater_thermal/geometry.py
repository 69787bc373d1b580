"""Crater geometry: idealized lunar crater (thesis Table 7.1), spherical bowl, flat patch, sphere; mesh I/O.

Frame (the crater frame of ephemeris.sun_in_crater_frame): x east, y north, z up [m]; origin at the
crater centre on the level of the surrounding (pre-impact) plain, so the plain is ``z = 0``, the rim
crest is at ``+rim_height`` and the floor at ``rim_height - depth``.

Idealized crater (Pike 1977 via the Lunar Sourcebook; thesis Table 7.1, section 7.1.1)
--------------------------------------------------------------------------------------
Every dimension is ``y = a D^b`` with the rim diameter ``D`` in km and ``y`` in km:

=================  ======  ======
parameter          a       b
=================  ======  ======
depth              0.196   1.010
rim height         0.036   1.014
rim (flank) width  0.257   1.011
floor diameter     0.031   1.765
=================  ======  ======

*Depth* is measured from the rim crest down to the floor and *rim height* from the plain up to the
crest (Pike 1977), so the floor lies at ``rim_height - depth`` relative to the plain.  The cross-section
(a profile ``z(r)``, revolved about the z axis) is made of

* a straight, flat floor from the axis to the floor edge ``r = floor_diameter / 2``;
* the wall: a circular arc from the floor edge up to the inner rim crest ``r = D / 2``;
* the outer rim flank: a straight line from the crest down to the plain at ``r = D/2 + rim_width``;
* optionally a flat surround ring on the plain, ``surround_km`` wide, beyond the flank foot.

Two points do not fix a circle.  The default wall (``wall="thesis"``) follows the thesis text: "a
circle fitted to the inner endpoints of each side of the crater rim and the endpoints of the crater
floor".  Those four points (both crests, both floor edges of a diametral cross-section) form an
isosceles trapezoid, which always has a unique circumscribed circle; its centre lies on the crater
axis.  The wall is therefore a zone of a sphere centred on the axis, and meets the floor with a small
kink (about 7 deg for D = 10 km) and the crest at about 45 deg.  The alternative ``wall="tangent"``
uses the circle tangent to the floor at the floor edge (centre above the floor edge); its wall meets
the floor smoothly and is steeper at the crest (about 52 deg for D = 10 km).

Triangulation
-------------
Surfaces of revolution are triangulated in rings: the profile is cut at its corners (floor edge, crest,
flank foot, surround edge) and each piece is divided into equal arc-length steps close to the height
of an equilateral triangle of the target facet area; ring ``k`` carries ``n_k`` vertices, about
proportional to the area of the adjacent bands, and neighbouring rings are stitched by merging their
vertex azimuths.  A band between rings of ``n_{k-1}`` and ``n_k`` vertices holds ``n_{k-1} + n_k``
triangles, the central fan ``n_1``, so an open surface has ``2 sum(n_k) - n_K`` facets; the counts are
adjusted so that this equals the requested number exactly.  Each ring has enough vertices that no band
folds over (checked; a too-small request raises :class:`ConfigError` naming the smallest count that
works, e.g. 28 for D = 0.5 km).  A closed sphere has ``2 sum(n_k)`` facets, so an odd request gets the
next even count.  Facet areas are near-uniform: max/min area about 1.7 for the 502-facet 10 km crater
and below 4 for D >= 10 km and >= 300 facets.  Small craters have floors smaller than one facet
(D = 1 km: floor diameter 31 m), and their floor facets are correspondingly small (max/min area up to
~70 at D = 1 km): the floor edge is always a vertex ring so that the floor diameter is exact.
Every facet is oriented counter-clockwise seen from
outside (crater, bowl, flat: normals point up).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from crater_thermal import io
from crater_thermal.errors import ConfigError, MeshError

__all__ = [
    "Mesh",
    "CRATER_COEFFICIENTS",
    "MAX_SIMPLE_CRATER_DIAMETER_KM",
    "crater_dimensions",
    "crater_profile",
    "crater_mesh",
    "bowl_mesh",
    "flat_mesh",
    "sphere_mesh",
    "load_mesh",
    "check_upward",
    "save_mesh",
]

#: Table 7.1 of the thesis (Pike 1977): parameter -> (a, b) of ``y[km] = a * D[km] ** b``.
CRATER_COEFFICIENTS: dict[str, tuple[float, float]] = {
    "depth": (0.196, 1.010),
    "rim_height": (0.036, 1.014),
    "rim_width": (0.257, 1.011),
    "floor_diameter": (0.031, 1.765),
}

#: Largest rim diameter [km] accepted: Table 7.1 describes simple (bowl-shaped) craters, which on the
#: Moon give way to complex craters (central peaks, terraces) at about 15-20 km.
MAX_SIMPLE_CRATER_DIAMETER_KM = 15.0

#: Relative area below which a facet counts as degenerate (area < this * mean facet area).
DEGENERATE_AREA_FRACTION = 1e-10

#: A loaded mesh whose area-weighted mean normal has a vertical component below ``-DOWNWARD_LIMIT``
#: faces downward (reversed winding) and is refused (:func:`check_upward`). Terrain facing up has
#: about +0.9 (the cosine of its mean slope), the same terrain reversed about -0.9; a closed surface
#: has 0 (the normals of a closed surface sum to zero), so closed meshes always pass.
DOWNWARD_LIMIT = 0.1

_META_TAG = "crater_thermal_meta"


# ----------------------------------------------------------------------------------------------- Mesh


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in the crater frame.

    Parameters
    ----------
    vertices : (n_vertices, 3) float64 [m]
    faces : (n_facets, 3) int64
        Vertex indices, counter-clockwise seen from outside (from above for terrain).
    meta : dict
        JSON-serialisable description: ``kind`` ("crater", "bowl", "flat", "sphere", "file") and
        whatever dimensions are known (``diameter_m``, ``depth_m``, ``rim_height_m``,
        ``floor_radius_m``, ``rim_radius_m``, ``flank_outer_radius_m``, ``surround_m`` ...).

    The arrays are made read-only; derived per-facet quantities are cached properties.
    """

    vertices: np.ndarray
    faces: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = np.array(self.vertices, dtype=np.float64, order="C", copy=True)
        f = np.array(self.faces, dtype=np.int64, order="C", copy=True)
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices must have shape (n, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise MeshError(f"faces must have shape (n >= 1, 3), got {f.shape}")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise MeshError(f"face indices must lie in [0, {v.shape[0] - 1}], got [{f.min()}, {f.max()}]")
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "meta", dict(self.meta))

    # -- per-facet quantities
    @cached_property
    def _cross(self) -> np.ndarray:
        p = self.vertices[self.faces]
        return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])

    @cached_property
    def centroids(self) -> np.ndarray:
        """(n_facets, 3) float64 [m]: facet centroids."""
        c = self.vertices[self.faces].mean(axis=1)
        c.setflags(write=False)
        return c

    @cached_property
    def areas(self) -> np.ndarray:
        """(n_facets,) float64 [m2]: facet areas."""
        a = 0.5 * np.linalg.norm(self._cross, axis=1)
        a.setflags(write=False)
        return a

    @cached_property
    def normals(self) -> np.ndarray:
        """(n_facets, 3) float64 [unit]: facet normals (right-hand rule on the face's vertex order)."""
        n = self._cross / np.maximum(2.0 * self.areas, np.finfo(float).tiny)[:, None]
        n.setflags(write=False)
        return n

    @cached_property
    def facet_size(self) -> np.ndarray:
        """(n_facets,) float64 [m]: sqrt of the facet area, a length scale per facet."""
        s = np.sqrt(self.areas)
        s.setflags(write=False)
        return s

    @property
    def n_facets(self) -> int:
        """Number of facets."""
        return int(self.faces.shape[0])

    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return int(self.vertices.shape[0])

    @cached_property
    def hash(self) -> str:
        """First 16 hex characters of sha256(float64 vertex bytes + int64 face bytes)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        return h.hexdigest()[:16]

    @cached_property
    def centre(self) -> np.ndarray:
        """(3,) float64 [m]: centre of the vertices' bounding box."""
        c = 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))
        c.setflags(write=False)
        return c

    @cached_property
    def extent(self) -> float:
        """Largest bounding-box side [m]."""
        return float(np.ptp(self.vertices, axis=0).max())

    @cached_property
    def mean_normal(self) -> np.ndarray:
        """(3,) float64 [-]: area-weighted mean of the facet normals, ``sum(A n) / sum(A)``.

        Its length is 1 for a plane and 0 for a closed surface; its z component is the ratio of the
        surface's horizontal projection (up minus down) to its area.
        """
        m = (self.areas[:, None] * self.normals).sum(axis=0) / max(self.total_area, np.finfo(float).tiny)
        m.setflags(write=False)
        return m

    @property
    def total_area(self) -> float:
        """Sum of the facet areas [m2]."""
        return float(self.areas.sum())

    def __repr__(self) -> str:
        return f"Mesh(kind={self.meta.get('kind')!r}, n_facets={self.n_facets}, hash={self.hash})"


# ------------------------------------------------------------------------------------ crater profile


def _check_number(name: str, value: Any, lo: float, hi: float, lo_open: bool = True, hi_open: bool = False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(x) and (x > lo if lo_open else x >= lo) and (x < hi if hi_open else x <= hi)
    if not ok:
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise ConfigError(f"{name} = {value!r} is outside the allowed range {lb}{lo:g}, {hi:g}{rb}")
    return x


def _check_count(name: str, value: Any, lo: int, hi: int = 10_000_000) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise ConfigError(f"{name} = {value!r} must be an integer in [{lo}, {hi}]")
    return int(value)


def crater_dimensions(diameter_km: float) -> dict[str, float]:
    """Idealized simple-crater dimensions from thesis Table 7.1.

    Parameters
    ----------
    diameter_km : float [km]
        Rim (crest-to-crest) diameter, in (0, 15].

    Returns
    -------
    dict of float [km]
        ``diameter``, ``depth`` (crest to floor), ``rim_height`` (plain to crest), ``rim_width`` (outer
        flank, crest to plain, horizontal), ``floor_diameter``, and the derived ``floor_z`` (floor level
        relative to the plain, ``rim_height - depth``).

    Raises
    ------
    ConfigError
        For a diameter outside (0, 15] km (Table 7.1 covers simple craters only).
    """
    d = _check_number("diameter_km", diameter_km, 0.0, MAX_SIMPLE_CRATER_DIAMETER_KM)
    out = {"diameter": d}
    for key, (a, b) in CRATER_COEFFICIENTS.items():
        out[key] = a * d**b
    out["floor_z"] = out["rim_height"] - out["depth"]
    return out


class _Line:
    """Straight profile piece in the (r, z) half-plane [m]."""

    def __init__(self, p0, p1):
        self.p0 = np.asarray(p0, float)
        self.p1 = np.asarray(p1, float)
        self.length = float(np.hypot(*(self.p1 - self.p0)))

    def point(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)[:, None]
        return (1.0 - t) * self.p0 + t * self.p1


class _Arc:
    """Circular profile piece about ``centre`` from angle ``a0`` to ``a1`` [rad] (angles from +r axis)."""

    def __init__(self, centre, radius, a0, a1):
        self.centre = np.asarray(centre, float)
        self.radius = float(radius)
        self.a0, self.a1 = float(a0), float(a1)
        self.length = abs(self.a1 - self.a0) * self.radius

    def point(self, t: np.ndarray) -> np.ndarray:
        a = self.a0 + np.asarray(t, float) * (self.a1 - self.a0)
        return self.centre + self.radius * np.stack([np.cos(a), np.sin(a)], axis=1)


def _arc_between(centre, p0, p1) -> _Arc:
    c = np.asarray(centre, float)
    a0 = math.atan2(p0[1] - c[1], p0[0] - c[0])
    a1 = math.atan2(p1[1] - c[1], p1[0] - c[0])
    return _Arc(c, math.hypot(p0[0] - c[0], p0[1] - c[1]), a0, a1)


def crater_profile(diameter_km: float = 10.0, surround_km: float = 0.0, wall: str = "thesis"):
    """Cross-section of the idealized crater.

    Parameters
    ----------
    diameter_km : float [km]
        Rim diameter, (0, 15].
    surround_km : float [km]
        Width of a flat ring of plain beyond the foot of the outer flank, >= 0.
    wall : {"thesis", "tangent"}
        Circle of the wall arc: through both sides' crests and floor edges (centre on the axis; the
        thesis text), or tangent to the floor at the floor edge.

    Returns
    -------
    pieces : list
        Profile pieces (floor, wall, flank[, surround]) from the axis outwards, in metres.
    meta : dict
        Dimensions in metres (``diameter_m``, ``depth_m``, ``rim_height_m``, ``floor_z_m``,
        ``floor_radius_m``, ``rim_radius_m``, ``rim_width_m``, ``flank_outer_radius_m``,
        ``surround_m``, ``outer_radius_m``, ``wall_centre_m`` [r, z], ``wall_radius_m``).
    """
    dims = crater_dimensions(diameter_km)
    s_km = _check_number("surround_km", surround_km, 0.0, 10.0 * MAX_SIMPLE_CRATER_DIAMETER_KM, lo_open=False)
    if wall not in ("thesis", "tangent"):
        raise ConfigError(f"wall = {wall!r} must be one of 'thesis', 'tangent'")
    km = 1000.0
    r_rim = 0.5 * dims["diameter"] * km
    r_floor = 0.5 * dims["floor_diameter"] * km
    h = dims["rim_height"] * km
    z_floor = dims["floor_z"] * km
    r_foot = r_rim + dims["rim_width"] * km
    surround = s_km * km
    if wall == "thesis":
        # circle through (+-r_floor, z_floor) and (+-r_rim, h): centre on the axis at z = zc
        zc = (r_rim**2 + h**2 - r_floor**2 - z_floor**2) / (2.0 * (h - z_floor))
        centre = (0.0, zc)
    else:
        dz = h - z_floor
        rho = ((r_rim - r_floor) ** 2 + dz**2) / (2.0 * dz)
        centre = (r_floor, z_floor + rho)
    pieces = [
        _Line((0.0, z_floor), (r_floor, z_floor)),
        _arc_between(centre, (r_floor, z_floor), (r_rim, h)),
        _Line((r_rim, h), (r_foot, 0.0)),
    ]
    if surround > 0:
        pieces.append(_Line((r_foot, 0.0), (r_foot + surround, 0.0)))
    meta = {
        "kind": "crater",
        "wall": wall,
        "diameter_km": dims["diameter"],
        "diameter_m": 2.0 * r_rim,
        "depth_m": dims["depth"] * km,
        "rim_height_m": h,
        "floor_z_m": z_floor,
        "floor_radius_m": r_floor,
        "rim_radius_m": r_rim,
        "rim_width_m": dims["rim_width"] * km,
        "flank_outer_radius_m": r_foot,
        "surround_m": surround,
        "outer_radius_m": r_foot + surround,
        "wall_centre_m": [float(centre[0]), float(centre[1])],
        "wall_radius_m": pieces[1].radius,
    }
    return pieces, meta


# ------------------------------------------------------------------------------ ring triangulation


def _stitch(ia: np.ndarray, ta: np.ndarray, ib: np.ndarray, tb: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangulate the band between two closed rings by merging their vertex azimuths.

    Ring a is the inner one (nearer the start of the profile); azimuths increase counter-clockwise
    seen from +z.  Triangles come out counter-clockwise seen from the profile's left-normal side.
    """
    na, nb = len(ia), len(ib)
    two_pi = 2.0 * math.pi
    # start ring b at its vertex nearest in azimuth to a's first vertex, with azimuths unwrapped
    # relative to ta[0], so that both walks start together and close together
    wrapped = (tb - ta[0] + math.pi) % two_pi - math.pi
    j0 = int(np.argmin(np.abs(wrapped)))
    order = (j0 + np.arange(nb)) % nb
    ib = ib[order]
    tb = ta[0] + wrapped[j0] + (tb[order] - tb[j0]) % two_pi
    ta = ta[0] + (ta - ta[0]) % two_pi
    tris = []
    i = j = 0
    while i < na or j < nb:
        next_a = ta[i + 1] if i + 1 < na else ta[0] + two_pi
        next_b = tb[j + 1] if j + 1 < nb else tb[0] + two_pi
        if j >= nb or (i < na and next_a <= next_b):
            tris.append((ia[i % na], ib[j % nb], ia[(i + 1) % na]))
            i += 1
        else:
            tris.append((ia[i % na], ib[j % nb], ib[(j + 1) % nb]))
            j += 1
    return tris


def _ring_counts(targets: np.ndarray, n_facets: int, closed: bool, n_min: np.ndarray) -> np.ndarray:
    """Integer vertex counts per ring (each >= ``n_min``) whose facet total is exactly ``n_facets``."""
    K = len(targets)
    n = np.maximum(np.rint(targets).astype(np.int64), n_min)

    def total(n):
        return int(2 * n.sum() - (0 if closed else n[-1]))

    for _ in range(100 * (K + 10)):
        delta = n_facets - total(n)
        if delta == 0:
            break
        if not closed and delta % 2 != 0:
            # the last ring changes the total by 1
            step = 1 if delta > 0 else -1
            if n[-1] + step >= n_min[-1]:
                n[-1] += step
                continue
        step = 1 if delta > 0 else -1
        resid = (targets - n) * step  # how much each ring "wants" to move in this direction
        cand = np.arange(K - (0 if closed else 1)) if K > 1 or closed else np.arange(K)
        order = cand[np.argsort(-resid[cand])]
        moved = False
        for k in order:
            if n[k] + step >= n_min[k]:
                n[k] += step
                moved = True
                break
        if not moved:
            break
    return n


def _build_rings(prof, rings, s_prof, targets, n_min, n_facets, closed):
    """Vertices and faces for given ring minima; returns (V, F), or the indices of rings to enlarge
    when some band folds over (a triangle facing the wrong way in the revolved profile)."""
    K = len(rings)
    targets = np.maximum(targets, n_min)
    counts = _ring_counts(targets, n_facets, closed, n_min)
    total = int(2 * counts.sum() - (0 if closed else counts[-1]))
    if total != n_facets + (n_facets % 2 if closed else 0):
        raise ConfigError(f"n_facets = {n_facets} is too few to triangulate this surface: use at least {total}")

    verts = [np.array([[0.0, 0.0, prof[0, 1]]])]
    ring_idx, ring_theta = [], []
    start = 1
    phase_step = 0.5 * (math.sqrt(5.0) - 1.0)
    for k in range(K):
        nk = int(counts[k])
        phase = (k * phase_step) % 1.0
        th = 2.0 * math.pi * (np.arange(nk) + phase) / nk
        r, z = rings[k]
        verts.append(np.stack([r * np.cos(th), r * np.sin(th), np.full(nk, z)], axis=1))
        ring_idx.append(np.arange(start, start + nk))
        ring_theta.append(th)
        start += nk
    apex = start
    if closed:
        verts.append(np.array([[0.0, 0.0, prof[-1, 1]]]))
    V = np.concatenate(verts)
    ring_of = np.full(len(V), -1)
    for k in range(K):
        ring_of[ring_idx[k]] = k
    if closed:
        ring_of[apex] = K

    tris = []
    ia = ring_idx[0]
    for i in range(len(ia)):
        tris.append((0, ia[i], ia[(i + 1) % len(ia)]))
    for k in range(1, K):
        tris.extend(_stitch(ring_idx[k - 1], ring_theta[k - 1], ring_idx[k], ring_theta[k]))
    if closed:
        ia = ring_idx[-1]
        for i in range(len(ia)):
            tris.append((apex, ia[(i + 1) % len(ia)], ia[i]))
    F = np.array(tris, dtype=np.int64)

    # fold check: the face normal must lie on the side of the profile's left normal (-dz, dr), revolved
    P = V[F]
    nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    c = P.mean(axis=1)
    rho = np.hypot(c[:, 0], c[:, 1])
    rk = ring_of[F]  # (nf, 3) ring number per corner (-1 = axis start, K = apex)
    s_vert = s_prof[rk + 1]
    lo = np.argmin(s_vert, axis=1)
    hi = np.argmax(s_vert, axis=1)
    ar = np.arange(len(F))
    rv = np.hypot(P[:, :, 0], P[:, :, 1])
    dr = rv[ar, hi] - rv[ar, lo]
    dz = P[ar, hi, 2] - P[ar, lo, 2]
    safe = np.where(rho > 0, rho, 1.0)
    ref = np.stack([-dz * c[:, 0] / safe, -dz * c[:, 1] / safe, dr], axis=1)
    folded = np.einsum("ij,ij->i", nrm, ref) <= 0
    if closed:
        folded[:] = False  # the sphere is re-triangulated as a convex hull by the caller
    if folded.any():
        bad = np.unique(rk[folded].max(axis=1))
        bad = bad[(bad >= 0) & (bad < K)]
        return bad
    return V, F


def _revolve(pieces, n_facets: int, closed: bool, meta: dict) -> Mesh:
    """Triangulate the surface of revolution of a profile starting on the axis (see module docstring)."""
    # fine polyline for the area estimate
    fine = np.concatenate([p.point(np.linspace(0, 1, 401)) for p in pieces])
    seg_len = np.hypot(np.diff(fine[:, 0]), np.diff(fine[:, 1]))
    area = float(np.sum(math.pi * (fine[:-1, 0] + fine[1:, 0]) * seg_len))
    a_target = area / n_facets
    spacing = math.sqrt(math.sqrt(3.0) * a_target)  # height of the equilateral triangle of that area

    pts = [pieces[0].point(np.array([0.0]))]
    for p in pieces:
        m = max(1, int(round(p.length / spacing)))
        pts.append(p.point(np.arange(1, m + 1) / m))
    prof = np.concatenate(pts)  # (K+1[+1], 2): axis point, rings[, apex]
    if abs(prof[0, 0]) > 1e-9 * (1.0 + np.abs(prof).max()):
        raise MeshError("internal: profile must start on the axis")
    rings = prof[1:-1] if closed else prof[1:]
    if closed and abs(prof[-1, 0]) > 1e-9 * (1.0 + np.abs(prof).max()):
        raise MeshError("internal: closed profile must end on the axis")
    rings_r = rings[:, 0]
    K = len(rings)
    if K < 1:
        raise MeshError("internal: profile too short")
    # band areas (frusta between consecutive profile points)
    dl = np.hypot(np.diff(prof[:, 0]), np.diff(prof[:, 1]))
    bands = math.pi * (prof[:-1, 0] + prof[1:, 0]) * dl  # band b between prof[b] and prof[b+1]
    T = bands / bands.sum() * n_facets  # triangles wanted per band
    # band 0 (fan) has n_1 triangles; band k (1..K-1) has n_k + n_{k+1}; closing fan has n_K.
    # least squares for real ring counts, with light smoothing toward counts proportional to radius
    nb = len(bands)
    M = np.zeros((nb, K))
    M[0, 0] = 1.0
    for b in range(1, K):
        M[b, b - 1] = 1.0
        M[b, b] = 1.0
    if closed:
        M[K, K - 1] = 1.0
    lam = 0.3
    circ = rings_r / max(rings_r.sum(), 1e-300)
    ref = circ * (n_facets / 2.0)
    A = np.vstack([M, lam * np.eye(K)])
    rhs = np.concatenate([T, lam * ref])
    targets = np.linalg.lstsq(A, rhs, rcond=None)[0]
    # a ring's polygon must enclose the previous ring (else the band folds over in projection):
    # r_k cos(pi / n_k) > r_{k-1}, with a margin of 2 % of the radial gap r_k - r_{k-1}.  (The margin
    # was once 2 % of r_{k-1}, which no ring satisfies once the gap is below 2 % of the radius, i.e.
    # beyond ~50 rings: every request above ~10k facets then failed.)
    # A closed surface is re-triangulated as a convex hull by its caller: no minimum there.
    n_min = np.full(K, 3, dtype=np.int64)
    for k in range(1, K if not closed else 1):
        r_in, r_out = rings_r[k - 1], rings_r[k]
        if not r_out > r_in:
            raise MeshError("internal: profile radius must increase outwards")
        ratio = (r_in + 0.02 * (r_out - r_in)) / r_out
        n_min[k] = max(3, math.ceil(math.pi / math.acos(ratio)))
    s_prof = np.concatenate([[0.0], np.cumsum(dl)])
    for _attempt in range(200):
        tri = _build_rings(prof, rings, s_prof, targets, n_min, n_facets, closed)
        if isinstance(tri, tuple):
            V, F = tri
            break
        n_min[tri] += 1  # rings whose band folded over: more vertices
    else:  # pragma: no cover - the loop always converges for sane profiles
        raise MeshError("internal: could not triangulate the profile without folds")
    meta = dict(meta)
    meta["n_rings"] = int(K)
    return Mesh(V, F, meta)


# -------------------------------------------------------------------------------------- generators


def crater_mesh(diameter_km: float = 10.0, n_facets: int = 502, surround_km: float = 0.0, wall: str = "thesis") -> Mesh:
    """Idealized simple lunar crater (thesis Table 7.1), triangulated with near-uniform facet areas.

    Parameters
    ----------
    diameter_km : float [km]
        Rim diameter, (0, 15].
    n_facets : int
        Exact number of facets, >= 20 (502 in the thesis).
    surround_km : float [km]
        Width of a flat ring of plain beyond the flank foot (0: none, as in the thesis).
    wall : {"thesis", "tangent"}
        Choice of the wall circle, see the module docstring.

    Returns
    -------
    Mesh
        ``meta`` holds the dimensions [m] (see :func:`crater_profile`), ``n_facets`` and ``kind="crater"``.
    """
    n = _check_count("n_facets", n_facets, 20)
    pieces, meta = crater_profile(diameter_km, surround_km, wall)
    return _revolve(pieces, n, closed=False, meta=meta)


def bowl_mesh(depth_to_diameter: float = 0.2, n_facets: int = 3000, diameter_m: float = 1000.0) -> Mesh:
    """Spherical-cap bowl (Ingersoll, Svitek & Murray 1992), rim on the plain ``z = 0``.

    Parameters
    ----------
    depth_to_diameter : float
        gamma = depth / diameter, in (0, 0.5] (0.5 is a hemisphere).
    n_facets : int
        Exact number of facets, >= 20.
    diameter_m : float [m]
        Rim diameter, > 0.

    Returns
    -------
    Mesh
        ``meta``: kind "bowl", diameter_m, depth_m, depth_to_diameter, sphere_radius_m, half_angle_rad
        (beta, the cap half-angle), view_factor (Ingersoll's ``f = (1 - cos beta) / 2``), rim_radius_m.
    """
    g = _check_number("depth_to_diameter", depth_to_diameter, 0.0, 0.5)
    D = _check_number("diameter_m", diameter_m, 0.0, 1e8)
    n = _check_count("n_facets", n_facets, 20)
    r = 0.5 * D
    d = g * D
    R = (r * r + d * d) / (2.0 * d)
    centre = (0.0, R - d)
    arc = _arc_between(centre, (0.0, -d), (r, 0.0))
    beta = abs(arc.a1 - arc.a0)  # cap half-angle, from the lowest point to the rim seen from the centre
    meta = {
        "kind": "bowl",
        "diameter_m": D,
        "depth_m": d,
        "depth_to_diameter": g,
        "sphere_radius_m": R,
        "half_angle_rad": beta,
        "view_factor": (1.0 - math.cos(beta)) / 2.0,
        "rim_radius_m": r,
        "rim_height_m": 0.0,
        "floor_z_m": -d,
    }
    return _revolve([arc], n, closed=False, meta=meta)


def sphere_mesh(n_facets: int, radius_m: float = 1.0, inward: bool = True) -> Mesh:
    """Closed sphere centred on the origin (for view-factor tests).

    Parameters
    ----------
    n_facets : int
        Requested facet count, >= 20; an odd count gets ``n_facets + 1`` (a ring-triangulated closed
        surface has an even count).
    radius_m : float [m]
    inward : bool
        Normals point to the centre (a closed cavity: every row of F sums to 1) or away from it.
    """
    n = _check_count("n_facets", n_facets, 20)
    R = _check_number("radius_m", radius_m, 0.0, 1e9)
    n += n % 2
    arc = _Arc((0.0, 0.0), R, -0.5 * math.pi, 0.5 * math.pi)
    rings = _revolve([arc], n, closed=True, meta={"kind": "sphere", "radius_m": R, "inward": bool(inward)})
    # Re-triangulate the ring vertices as their convex hull (same count, 2 V - 4 = n): the ring
    # stitching is not guaranteed convex, and an outward sphere must see nothing of itself.
    from scipy.spatial import ConvexHull

    V = rings.vertices
    F = np.asarray(ConvexHull(V).simplices, dtype=np.int64)
    c = V[F].mean(axis=1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    outward = np.einsum("ij,ij->i", nrm, c) > 0
    want_out = not inward
    flip = outward != want_out
    F[flip] = F[flip][:, [0, 2, 1]]
    return Mesh(V, F, rings.meta)


def flat_mesh(size_m: float = 100.0, n_facets: int = 2) -> Mesh:
    """Square patch ``[-size/2, size/2]^2`` on ``z = 0``, normals up, split into a grid of triangle pairs.

    Parameters
    ----------
    size_m : float [m]
        Side of the square, > 0.
    n_facets : int
        Even counts ``2 nx ny`` with ``nx ny = n_facets / 2`` as square as possible (aspect <= 4) are
        exact; otherwise the closest ``2 m^2`` is used (recorded in ``meta["n_facets_requested"]``).
    """
    L = _check_number("size_m", size_m, 0.0, 1e9)
    n = _check_count("n_facets", n_facets, 2)
    nx = ny = None
    if n % 2 == 0:
        half = n // 2
        for a in range(int(math.isqrt(half)), 0, -1):
            if half % a == 0:
                if half // a <= 4 * a:
                    nx, ny = half // a, a
                break
    if nx is None:
        m = max(1, int(round(math.sqrt(n / 2.0))))
        nx = ny = m
    xs = np.linspace(-0.5 * L, 0.5 * L, nx + 1)
    ys = np.linspace(-0.5 * L, 0.5 * L, ny + 1)
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange(V.shape[0]).reshape(ny + 1, nx + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    meta = {"kind": "flat", "size_m": L, "n_facets_requested": n}
    return Mesh(V, F, meta)


# ------------------------------------------------------------------------------------------- I/O


def _validate(vertices: np.ndarray, faces: np.ndarray, source: str) -> None:
    """Checks for loaded meshes: finite vertices, no degenerate facets, consistent winding."""
    if not np.all(np.isfinite(vertices)):
        bad = int(np.argmax(~np.all(np.isfinite(vertices), axis=1)))
        raise MeshError(f"{source}: vertex {bad} is not finite ({vertices[bad].tolist()})")
    if faces.shape[0] == 0:
        raise MeshError(f"{source}: mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{source}: face indices outside [0, {len(vertices) - 1}]")
    p = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    tol = DEGENERATE_AREA_FRACTION * max(float(area.mean()), np.finfo(float).tiny)
    rep = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    bad = rep | (area <= tol)
    if bad.any():
        raise MeshError(
            f"{source}: {int(bad.sum())} degenerate face(s) (zero area or repeated vertex), "
            f"first is face {int(np.argmax(bad))}"
        )
    # duplicate faces (same vertex set)
    key = np.sort(faces, axis=1)
    uniq = np.unique(key, axis=0)
    if len(uniq) != len(faces):
        raise MeshError(f"{source}: {len(faces) - len(uniq)} duplicate face(s)")
    # winding consistency: every interior edge must be used once in each direction.
    # merge coincident vertices first (STL files repeat them per face)
    _, inv = np.unique(np.round(vertices, 12), axis=0, return_inverse=True)
    f = inv.reshape(-1)[faces]
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    ecode = e[:, 0].astype(np.int64) * (len(vertices) + 1) + e[:, 1]
    u, cnt = np.unique(ecode, return_counts=True)
    if (cnt > 1).any():
        raise MeshError(
            f"{source}: inconsistent face winding (normals): {int((cnt > 1).sum())} directed edge(s) "
            "are shared by two faces with the same orientation"
        )


def _read_meta_comment(path: Path) -> dict:
    """The ``crater_thermal_meta {json}`` comment written by :func:`save_mesh` (PLY header / OBJ), or {}."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return {}
    for line in head.split(b"\n"):
        text = line.decode("latin-1", "replace").strip()
        for prefix in ("comment " + _META_TAG + " ", "# " + _META_TAG + " "):
            if text.startswith(prefix):
                try:
                    meta = json.loads(text[len(prefix) :])
                    return meta if isinstance(meta, dict) else {}
                except ValueError:
                    return {}
        if text == "end_header":
            break
    return {}


def check_upward(mesh: Mesh, source: str = "mesh") -> Mesh:
    """Refuse a mesh whose surface faces downward (a reversed winding: no sunlight would ever reach it).

    The test is the z component of :attr:`Mesh.mean_normal` against the local up (+z in the crater
    frame): below ``-DOWNWARD_LIMIT`` the mesh faces down. Closed meshes (mean normal 0) and
    vertical ones pass: they have no up or down side to check.

    Raises
    ------
    MeshError
        One line naming the mean normal and suggesting ``--flip``.
    """
    nz = float(mesh.mean_normal[2])
    if nz < -DOWNWARD_LIMIT:
        raise MeshError(
            f"{source}: the surface faces downward (area-weighted mean normal z = {nz:.2f}; "
            "up is +z): its winding is reversed; load it with --flip (flip=True)"
        )
    return mesh


def _check_site_location(meta: dict, location: tuple[float, float], path: Path) -> None:
    """A site mesh's recorded centre against the case's (lat_deg, lon_deg) location [deg]."""
    from crater_thermal.config import check_site_centre

    site = []
    for key in ("center_lat_deg", "center_lon_deg"):
        v = meta.get(key)
        try:
            site.append(None if v is None else float(v))
        except (TypeError, ValueError):
            raise MeshError(f"{path}: its metadata's {key} = {v!r} is not a number [deg]") from None
    if site == [None, None]:
        return
    lat, lon = (float(x) for x in location)
    check_site_centre(
        str(path),
        "the mesh metadata's ",
        site[0],
        site[1],
        lat,
        lon,
        f"set [location] lat_deg = {site[0]:g}, lon_deg = {site[1]:g} for this mesh, or mesh the site again "
        "about the location (mesh dem --center-lat/--center-lon)"
        if None not in site
        else "mesh the site again about the location (mesh dem --center-lat/--center-lon)",
    )


def load_mesh(path: str | os.PathLike, flip: bool = False, location: tuple[float, float] | None = None) -> Mesh:
    """Read a triangle mesh (any format trimesh reads: PLY, OBJ, STL, ...) and check it.

    Parameters
    ----------
    path : path-like
        File in metres, in the crater frame.
    flip : bool
        Reverse every facet's winding (for files whose normals point down); ``meta["flipped"]``
        records it.
    location : (lat_deg, lon_deg) or None [deg]
        The case's location, where the mesh will be lit. A mesh whose metadata records a site centre
        (``center_lat_deg``, ``center_lon_deg``: a DEM site from ``mesh dem``, whose frame is the
        east/north/up frame of that centre) must have been made for this location; None: not checked.

    Returns
    -------
    Mesh
        ``meta`` is the one stored by :func:`save_mesh` (PLY/OBJ) if present, else ``{"kind": "file"}``;
        ``meta["source"]`` is the file name.

    Raises
    ------
    MeshError
        Unreadable file, non-finite vertices, degenerate or duplicate faces, inconsistent winding, a
        surface facing downward (:func:`check_upward`). (Closed / watertight meshes are not required.)
    ConfigError
        A site mesh made for another centre than ``location`` (:func:`crater_thermal.config.check_site_centre`,
        the check a ``kind = "dem"`` case gets).
    """
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise MeshError(f"mesh file {str(p)!r} does not exist")
    try:
        tm = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds
        raise MeshError(f"cannot read mesh {str(p)!r}: {type(exc).__name__}: {exc}") from None
    V = np.asarray(getattr(tm, "vertices", np.zeros((0, 3))), dtype=np.float64)
    F = np.asarray(getattr(tm, "faces", np.zeros((0, 3))), dtype=np.int64)
    if V.ndim != 2 or V.shape[0] == 0 or F.ndim != 2 or F.shape[0] == 0 or F.shape[1] != 3:
        raise MeshError(f"mesh {str(p)!r} has no triangles")
    if p.suffix.lower() == ".stl":
        # STL repeats vertices per face: merge exact duplicates
        V, inv = np.unique(V, axis=0, return_inverse=True)
        F = inv.reshape(-1)[F]
    _validate(V, F, str(p))
    meta = _read_meta_comment(p) or {"kind": "file"}
    meta["source"] = p.name
    if location is not None:
        _check_site_location(meta, location, p)
    if flip:
        F = F[:, [0, 2, 1]]
        meta["flipped"] = True
    return check_upward(Mesh(V, F, meta), str(p))


def _ply_bytes(mesh: Mesh) -> bytes:
    meta = json.dumps(mesh.meta, separators=(",", ":"), sort_keys=True)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {_META_TAG} {meta}\n"
        f"element vertex {mesh.n_vertices}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {mesh.n_facets}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    ).encode("ascii")
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
    fa = np.empty(mesh.n_facets, dtype=fdt)
    fa["n"] = 3
    fa["v"] = mesh.faces
    return header + np.ascontiguousarray(mesh.vertices, "<f8").tobytes() + fa.tobytes()


def _obj_bytes(mesh: Mesh) -> bytes:
    meta = json.dumps(mesh.meta, separators=(",", ":"), sort_keys=True)
    lines = [f"# {_META_TAG} {meta}"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in mesh.vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces.tolist()]
    return ("\n".join(lines) + "\n").encode("ascii")


def save_mesh(mesh: Mesh, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a mesh atomically (temporary file in the same folder, then rename).

    The format follows the suffix: ``.ply`` (binary, float64 vertices, ``meta`` as a JSON header
    comment: exact round trip), ``.obj`` (text, repr-exact floats, ``meta`` as a comment) or ``.stl``
    (binary float32 via trimesh: no meta, vertices rounded to float32).

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    MeshError
        Unsupported suffix.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".ply", ".obj", ".stl"):
        raise MeshError(f"mesh file suffix {p.suffix!r} not supported: use .ply, .obj or .stl")
    io.check_output(p, overwrite)
    if suffix == ".ply":
        data = _ply_bytes(mesh)
    elif suffix == ".obj":
        data = _obj_bytes(mesh)
    else:
        import trimesh

        data = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="stl")
    with io.atomic_output(p, overwrite) as tmp:
        tmp.write_bytes(data)
    return p
