"""Ray casting against a :class:`~crater_thermal.geometry.Mesh` with Embree (the only embreex importer).

Precision
---------
Embree works in float32 (24-bit mantissa, relative spacing 6e-8).  The scene is built from vertex
coordinates *relative to the mesh's bounding-box centre*, so a 20 km wide scene has a coordinate
resolution of about 20e3 m * 6e-8 = 1.2 mm, instead of being limited by a far-away origin.  Ray origins
are lifted off their facet along its normal by ``RAY_OFFSET_FRACTION * facet_size`` (0.1 % of the
facet's length scale: 13 cm for the 134 m facets of a 10 000-facet 10 km crater), and never by less than
``MIN_OFFSET_ULPS`` float32 spacings of the scene's extent, so that a ray never re-hits its own facet
through rounding.  The offset is small against the facet, so view factors and shadows it changes are
changed by O(offset / facet size) = O(1e-3) only, for grazing rays to adjacent facets.

Threads
-------
embreex's ``EmbreeScene.run`` releases the GIL while tracing, so batches are cut into chunks that a
``ThreadPoolExecutor`` with ``os.cpu_count()`` workers traces concurrently. The pool is kept for the
process (:func:`crater_thermal.pools.process_pool`, one per thread count), not started per batch:
callers such as the horizon map trace thousands of small batches, and starting two threads for each
cost more than tracing some of them on a busy machine. Callers that already spread their batches over
threads (the compressed operator's build) trace with ``parallel=False``.
"""

from __future__ import annotations

import os

import numpy as np
from embreex import mesh_construction, rtcore_scene

from crater_thermal.errors import MeshError
from crater_thermal.geometry import Mesh
from crater_thermal.pools import process_pool

__all__ = ["RAY_OFFSET_FRACTION", "MIN_OFFSET_ULPS", "RayTracer"]

#: Ray origins are lifted off their facet along the normal by this fraction of ``facet_size``
#: (sqrt of the facet area) [dimensionless].
RAY_OFFSET_FRACTION = 1e-3

#: Lower bound of the origin offset in float32 spacings of the scene extent (``eps32 * extent``).
MIN_OFFSET_ULPS = 64.0

#: Rays per chunk handed to one thread.
CHUNK_RAYS = 65536

_F32_EPS = float(np.finfo(np.float32).eps)


def _n_threads(n_threads: int | None) -> int:
    return max(1, int(n_threads) if n_threads else (os.cpu_count() or 1))


class RayTracer:
    """Occlusion and first-hit queries against one mesh.

    Parameters
    ----------
    mesh : Mesh
        The scene.  All facets are opaque and two-sided.
    n_threads : int, optional
        Worker threads (default ``os.cpu_count()``).

    Notes
    -----
    Inputs are in the crater frame [m] (float64 is fine: they are shifted to the mesh centre and
    converted to C-contiguous float32 here).  Directions need not be normalised for
    :meth:`occluded` without ``tfar`` and :meth:`first_hit`; with ``tfar`` the distance is in units of
    the direction's length (normalise them to get metres).
    """

    def __init__(self, mesh: Mesh, n_threads: int | None = None):
        if not isinstance(mesh, Mesh):
            raise MeshError(f"RayTracer needs a geometry.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.n_threads = _n_threads(n_threads)
        self.centre = np.asarray(mesh.centre, dtype=np.float64)
        verts = np.ascontiguousarray(mesh.vertices - self.centre, dtype=np.float32)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
        self._scene = rtcore_scene.EmbreeScene()
        # keep a reference: the geometry must live as long as the scene
        self._geometry = mesh_construction.TriangleMesh(self._scene, verts, faces)
        extent = max(float(np.abs(verts).max()), 1e-30)
        self.min_offset = MIN_OFFSET_ULPS * _F32_EPS * extent
        self.offsets = np.maximum(RAY_OFFSET_FRACTION * mesh.facet_size, self.min_offset)
        #: (n_facets, 3) float64 [m]: centroids lifted along their normals by ``offsets``
        self.origins = mesh.centroids + self.offsets[:, None] * mesh.normals

    # ----------------------------------------------------------------------------------- helpers
    def facet_origins(self, facet_idx) -> np.ndarray:
        """Ray origins for facets: centroids offset along the normals.

        Parameters
        ----------
        facet_idx : (n,) int

        Returns
        -------
        (n, 3) float64 [m], crater frame.
        """
        idx = np.asarray(facet_idx, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self.mesh.n_facets):
            raise MeshError(f"facet index out of range [0, {self.mesh.n_facets - 1}]")
        return self.origins[idx]

    def _prepare(self, origins, directions, tfar):
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise MeshError(f"origins and directions must both have shape (n, 3), got {o.shape} and {d.shape}")
        o32 = np.ascontiguousarray(o - self.centre, dtype=np.float32)
        d32 = np.ascontiguousarray(d, dtype=np.float32)
        t32 = None
        if tfar is not None:
            t = np.broadcast_to(np.asarray(tfar, dtype=np.float64), (o.shape[0],))
            t32 = np.ascontiguousarray(t, dtype=np.float32)
        return o32, d32, t32

    def _run(self, o32, d32, t32, query: str) -> np.ndarray:
        """Trace float32 rays (already centred) in chunks across threads; raw embreex output (int32)."""
        n = o32.shape[0]
        out = np.empty(n, dtype=np.int32)
        if n == 0:
            return out
        step = max(1024, min(CHUNK_RAYS, -(-n // self.n_threads)))
        starts = range(0, n, step)

        def work(s):
            e = min(n, s + step)
            dists = None if t32 is None else t32[s:e]
            out[s:e] = self._scene.run(o32[s:e], d32[s:e], dists=dists, query=query)

        if self.n_threads == 1 or len(starts) == 1:
            for s in starts:
                work(s)
        else:
            list(process_pool("raytrace", self.n_threads).map(work, starts))
        return out

    def run_raw(
        self,
        o32: np.ndarray,
        d32: np.ndarray,
        t32: np.ndarray | None = None,
        query: str = "OCCLUDED",
        parallel: bool = True,
    ) -> np.ndarray:
        """Low-level: trace C-contiguous float32 rays whose origins are already relative to ``self.centre``.

        ``parallel=False`` traces in the calling thread with one call (for callers that already spread
        their batches over threads). Returns embreex's int32 result (OCCLUDED: -1 = free, otherwise
        blocked; INTERSECT: primID or -1).
        """
        if not parallel:
            return self._scene.run(o32, d32, dists=t32, query=query)
        return self._run(o32, d32, t32, query)

    # ------------------------------------------------------------------------------------ queries
    def occluded(self, origins, directions, tfar=None) -> np.ndarray:
        """Is anything hit along each ray?

        Parameters
        ----------
        origins : (n, 3) float [m]
            Crater frame; use :meth:`facet_origins` for rays leaving facets.
        directions : (n, 3) float
        tfar : float or (n,) float, optional
            Only hits closer than ``tfar`` direction lengths count (default: infinite rays).

        Returns
        -------
        (n,) bool
        """
        o32, d32, t32 = self._prepare(origins, directions, tfar)
        return self._run(o32, d32, t32, "OCCLUDED") != -1

    def first_hit(self, origins, directions, tfar=None) -> np.ndarray:
        """Index of the first facet hit by each ray.

        Parameters
        ----------
        origins, directions : (n, 3) float
        tfar : float or (n,) float, optional

        Returns
        -------
        (n,) int64 facet index, -1 where nothing is hit.
        """
        o32, d32, t32 = self._prepare(origins, directions, tfar)
        return self._run(o32, d32, t32, "INTERSECT").astype(np.int64)
