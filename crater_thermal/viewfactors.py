"""Sparse view-factor matrix with visibility (thesis Eq. 7.6).

``F[i, j]`` is the fraction of the radiation leaving facet ``i`` (Lambertian) that reaches facet ``j``;
the irradiance on ``i`` from exitances ``B`` [W m-2] is ``E = F @ B``  (``A_i E_i = sum_j A_j B_j F_ji``
and reciprocity ``A_i F_ij = A_j F_ji`` give ``E_i = sum_j F_ij B_j``).

Method
------
``F_ij = K_ij A_j`` with the symmetric mean kernel ``K_ij = cos(theta_i) cos(theta_j) / (pi d_ij^2)``,
evaluated

* between centroids for well-separated facets, and
* for near pairs (``d_ij < NEAR_DISTANCE_FACTOR * max(size_i, size_j)``, ``size = sqrt(area)``),
  where the centroid formula is poor, from the facet-to-facet view factor
  ``F_ij = (1/A_i) int_i F_dA(p)->j dA_p``: the inner integral is exact (Lambert's contour formula for
  the view factor from a point to a polygon, with j clipped to the half-space in front of i, and zero
  where p lies behind j's plane), the outer one is the mean over the centroids of the
  ``NEAR_SUBDIVISIONS^2`` congruent sub-triangles of i.  The kernel is then symmetrised,
  ``K_ij = (F_ij / A_j + F_ji / A_i) / 2``.  The exact inner integral removes the 1/d^2 singularity of
  facets sharing an edge (the outer integrand stays bounded), so the 16-point outer rule is enough:
  refining it to 64 points changes crater row sums by ~1e-4, and two perpendicular squares sharing an
  edge, each one triangle pair, come out 0.16 % from the exact 0.20004.

Pairs with ``cos(theta_i) <= COS_CUTOFF`` or ``cos(theta_j) <= COS_CUTOFF`` (centroid test, far pairs)
need no ray.  The others are tested for visibility with one occlusion ray per unordered pair, from
``i``'s offset origin to ``j``'s offset origin (both lifted along their normals, see
:mod:`crater_thermal.raytrace`), with ``tfar`` at the target point: the target itself cannot block it.
Visibility is binary (centroid to centroid) and symmetric by construction.  Near pairs whose
centroids fail the cosine test (but whose sub-triangles see each other, e.g. straddling a plane) are
taken as visible without a ray.

Because ``K`` is symmetric, ``A_i F_ij = A_i A_j K_ij = A_j F_ji`` holds to rounding: reciprocity is
exact.  Row sums are at most 1 physically; discretisation can push a closed cavity's rows slightly
above 1.  Then (and only then) pairs are scaled by ``min(s_i, s_j)`` with ``s_i = min(1, 1 / rowsum_i)``,
which keeps ``K`` symmetric (reciprocity intact) and every row sum <= 1; the largest excess before the
scaling is reported in the returned matrix's ``rowsum_excess`` attribute (0 when nothing was scaled).

Cache: with ``cache_dir`` the matrix is stored as ``viewfactors_<mesh.hash>_<version and constants>.npz``
(atomic write; the key also holds the tuning constants) and read back on the next call with the
same mesh.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse as sp

from crater_thermal import io
from crater_thermal.errors import InternalError, MeshError
from crater_thermal.geometry import Mesh
from crater_thermal.kernels import viewfactors as _kern

__all__ = [
    "ALGORITHM_VERSION",
    "NEAR_DISTANCE_FACTOR",
    "NEAR_SUBDIVISIONS",
    "COS_CUTOFF",
    "view_factor_matrix",
    "check_reciprocity",
    "row_sums",
]

#: Pairs closer than this many facet sizes (``max(sqrt(A_i), sqrt(A_j))``) use sub-facet quadrature.
NEAR_DISTANCE_FACTOR = 3.0
#: Each triangle of a near pair is cut into ``NEAR_SUBDIVISIONS ** 2`` sub-triangles.
NEAR_SUBDIVISIONS = 4
#: Pairs whose centroid cosines are not above this need no ray (their view factor is < 1e-9 of the
#: solid-angle term, i.e. coplanar or facing away).
COS_CUTOFF = 1e-9
#: Upper bound of candidate pairs per work chunk (memory: about 45 bytes per pair).
CHUNK_PAIRS = 1 << 20
#: Part of the cache key: bump the leading number when the algorithm changes the numbers.
ALGORITHM_VERSION = "v2"


def _algorithm_key() -> str:
    """Cache key part: algorithm version plus the current tuning constants and ray offset."""
    from crater_thermal.raytrace import RAY_OFFSET_FRACTION

    return (
        f"{ALGORITHM_VERSION}-near{NEAR_DISTANCE_FACTOR:g}x{NEAR_SUBDIVISIONS}"
        f"-cos{COS_CUTOFF:g}-off{RAY_OFFSET_FRACTION:g}"
    )


def subtriangle_barycentrics(k: int) -> np.ndarray:
    """(k*k, 3) barycentric coordinates of the centroids of the k^2 congruent sub-triangles."""
    pts = []
    for a in range(k):
        for b in range(k - a):
            pts.append(((a + 1.0 / 3.0) / k, (b + 1.0 / 3.0) / k))  # "upright"
            if a + b <= k - 2:
                pts.append(((a + 2.0 / 3.0) / k, (b + 2.0 / 3.0) / k))  # "inverted"
    uv = np.array(pts)
    return np.ascontiguousarray(np.column_stack([1.0 - uv.sum(axis=1), uv]))


def _assemble(nf: int, results: list, A: np.ndarray, pool=None):
    """CSR arrays with sorted columns from the per-chunk visible pairs (chunks in row order).

    ``results`` holds, per chunk, ``(pi, pj, k, up, low)``: the visible pairs (i < j) and the per-row
    counts ``up[r]`` (pairs with first index r) and ``low[r]`` (pairs with second index r) that
    :func:`~crater_thermal.kernels.viewfactors.compact_pairs` counted while keeping exactly these pairs.
    Row r holds first the entries (r, i) of pairs (i, r), i < r, in increasing i (chunk by chunk), then
    the entries (r, j) of pairs (r, j), j > r: no sort is needed.  Each chunk gets its own start-slot
    array (never a shared one), chunks fill disjoint slots, so they are written concurrently.  Every
    write is checked against the end of its reserved slots, and every slot must be filled exactly
    once; otherwise :class:`InternalError`.
    Rows summing above 1 are then rescaled (module docstring).
    """
    up = np.zeros(nf, np.int64)
    low_total = np.zeros(nf, np.int64)
    for r in results:
        if len(r[0]) != int(r[3].sum()) or len(r[0]) != int(r[4].sum()):
            raise InternalError("view factors: a chunk's pair count differs from its row counts")
        up += r[3]
        low_total += r[4]
    indptr = np.zeros(nf + 1, np.int64)
    np.cumsum(up + low_total, out=indptr[1:])
    nnz = int(indptr[-1])
    indices = np.empty(nnz, np.int32)
    data = np.empty(nnz, np.float64)
    pos_up = indptr[:-1] + low_total
    up_end = indptr[1:]
    # each chunk's own start and end slots in every row's lower part
    starts, ends = [], []
    acc = indptr[:-1].copy()
    for r in results:
        nxt = acc + r[4]
        starts.append(acc.copy())  # advanced in place by fill_pairs: must not alias any end array
        ends.append(nxt)
        acc = nxt
    del acc

    def fill(c):
        pi_, pj_, kk = results[c][:3]
        return _kern.fill_pairs(pi_, pj_, kk, A, pos_up, starts[c], up_end, ends[c], indices, data)

    if pool is None:
        ok = [fill(c) for c in range(len(results))]
    else:
        ok = list(pool.map(fill, range(len(results))))
    filled = all(ok) and np.array_equal(pos_up, up_end) and all(np.array_equal(s, e) for s, e in zip(starts, ends))
    if not filled:
        raise InternalError("view factors: the filled entries differ from the counted ones")
    excess = _kern.rescale_rows(indptr, indices, data)
    return indptr, indices, data, excess


def row_chunks(nf: int, chunk_pairs: int) -> list[tuple[int, int]]:
    """Row ranges whose upper-triangle pair counts stay below ``chunk_pairs`` (at least one row each)."""
    chunks = []
    i0 = 0
    while i0 < nf:
        n = 0
        i1 = i0
        while i1 < nf and (i1 == i0 or n + (nf - 1 - i1) <= chunk_pairs):
            n += nf - 1 - i1
            i1 += 1
        chunks.append((i0, i1))
        i0 = i1
    return chunks


def _cache_path(cache_dir, mesh: Mesh) -> Path:
    return Path(cache_dir) / f"viewfactors_{mesh.hash}_{_algorithm_key()}.npz"


def _load_cached(path: Path, mesh: Mesh):
    try:
        z = io.load_npz(path)
        if str(z["mesh_hash"]) != mesh.hash or str(z["version"]) != _algorithm_key():
            return None
        F = sp.csr_matrix((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))
        F.rowsum_excess = float(z["rowsum_excess"])
        return F
    except (OSError, KeyError, ValueError):
        return None


def _save_cached(path: Path, F: sp.csr_matrix, mesh: Mesh) -> None:
    try:
        _write_cache(path, F, mesh)
    except OSError as exc:  # a full or read-only cache costs the next run time, never this run
        warnings.warn(f"view factors not cached in {path.parent} ({exc.strerror or exc})", stacklevel=2)


def _write_cache(path: Path, F: sp.csr_matrix, mesh: Mesh) -> None:
    io.save_npz_atomic(
        path,
        data=F.data,
        indices=F.indices,
        indptr=F.indptr,
        shape=np.array(F.shape),
        mesh_hash=np.array(mesh.hash),
        version=np.array(_algorithm_key()),
        rowsum_excess=np.array(getattr(F, "rowsum_excess", 0.0)),
    )


def view_factor_matrix(
    mesh: Mesh,
    tracer=None,
    cache_dir=None,
    progress: Callable[[int, int], None] | None = None,
    chunk_pairs: int = CHUNK_PAIRS,
) -> sp.csr_matrix:
    """View-factor matrix with ray-traced visibility.

    Parameters
    ----------
    mesh : Mesh
    tracer : RayTracer, optional
        Built from ``mesh`` if not given (its thread count is used).
    cache_dir : path-like, optional
        Folder for the ``.npz`` cache keyed by ``mesh.hash`` and :data:`ALGORITHM_VERSION`.
    progress : callable, optional
        ``progress(done, total)``, called with the row chunks finished so far (not for a cached matrix).
    chunk_pairs : int
        Candidate pairs per work chunk (memory about 45 bytes each, per worker thread).

    Returns
    -------
    scipy.sparse.csr_matrix, (n_facets, n_facets) float64 [dimensionless]
        ``F[i, j]``, sorted column indices, zero diagonal.  Attribute ``rowsum_excess`` (float): the
        largest row sum minus 1 before the reciprocity-preserving rescaling (0 if none was needed).
    """
    if not isinstance(mesh, Mesh):
        raise MeshError(f"view_factor_matrix needs a geometry.Mesh, got {type(mesh).__name__}")
    cpath = None
    if cache_dir is not None:
        cpath = _cache_path(cache_dir, mesh)
        if cpath.is_file():
            F = _load_cached(cpath, mesh)
            if F is not None:
                return F
    if tracer is None:
        from crater_thermal.raytrace import RayTracer

        tracer = RayTracer(mesh)
    elif tracer.mesh.hash != mesh.hash:
        raise MeshError("tracer was built for a different mesh")

    nf = mesh.n_facets
    C = np.ascontiguousarray(mesh.centroids - tracer.centre)
    N = np.ascontiguousarray(mesh.normals)
    S = np.ascontiguousarray(mesh.facet_size)
    P = np.ascontiguousarray(tracer.origins - tracer.centre)
    V = np.ascontiguousarray(mesh.vertices - tracer.centre)
    Fc = np.ascontiguousarray(mesh.faces)
    A = np.ascontiguousarray(mesh.areas)
    bary = subtriangle_barycentrics(NEAR_SUBDIVISIONS)
    chunks = row_chunks(nf, int(chunk_pairs))
    ones = np.ones(max(1, min(int(chunk_pairs), nf * (nf - 1) // 2 + 1)) + nf, dtype=np.float32)

    def empty():
        # fresh arrays each time: _assemble derives per-chunk slots from them
        return (
            np.empty(0, np.int32),
            np.empty(0, np.int32),
            np.empty(0),
            np.zeros(nf, np.int64),
            np.zeros(nf, np.int64),
        )

    def work(rows):
        i0, i1 = rows
        cap = sum(nf - 1 - i for i in range(i0, i1))
        if cap == 0:
            return empty()
        o32 = np.empty((cap, 3), np.float32)
        d32 = np.empty((cap, 3), np.float32)
        pi_ = np.empty(cap, np.int32)
        pj_ = np.empty(cap, np.int32)
        kk = np.empty(cap, np.float64)
        need = np.empty(cap, np.bool_)
        n = _kern.candidate_pairs(
            i0, i1, C, N, S, A, P, V, Fc, bary, NEAR_DISTANCE_FACTOR, COS_CUTOFF, o32, d32, pi_, pj_, kk, need
        )
        if n == 0:
            return empty()
        t = ones[:n] if n <= ones.shape[0] else np.ones(n, np.float32)
        blocked = tracer.run_raw(o32[:n], d32[:n], t, parallel=False) != -1
        del o32, d32
        m, up, low = _kern.compact_pairs(n, blocked, need, pi_, pj_, kk, nf)
        # copies, so that the chunk-sized buffers are freed
        return pi_[:m].copy(), pj_[:m].copy(), kk[:m].copy(), up, low

    results = []
    n_threads = max(1, tracer.n_threads)
    pool = ThreadPoolExecutor(n_threads) if n_threads > 1 and len(chunks) > 1 else None
    try:
        for r in map(work, chunks) if pool is None else pool.map(work, chunks):
            results.append(r)
            if progress is not None:
                progress(len(results), len(chunks))
        indptr, indices, data, excess = _assemble(nf, results, A, pool)
    finally:
        if pool is not None:
            pool.shutdown()
    del results
    F = sp.csr_matrix((data, indices, indptr), shape=(nf, nf))
    F.has_sorted_indices = True
    F.rowsum_excess = float(excess)
    if cpath is not None:
        _save_cached(cpath, F, mesh)
    return F


def row_sums(F: sp.spmatrix) -> np.ndarray:
    """(n,) float: ``sum_j F_ij`` (the fraction of facet i's emission that stays in the scene)."""
    return np.asarray(F.sum(axis=1)).ravel()


def check_reciprocity(F: sp.spmatrix, areas) -> float:
    """Largest reciprocity violation ``|A_i F_ij - A_j F_ji| / max(A_i F_ij)`` (0 = exact).

    Parameters
    ----------
    F : (n, n) sparse matrix
    areas : (n,) float [m2] or Mesh

    Returns
    -------
    float
        Relative to the largest exchanged ``A_i F_ij``.
    """
    a = np.asarray(areas.areas if isinstance(areas, Mesh) else areas, dtype=np.float64)
    if a.shape != (F.shape[0],):
        raise MeshError(f"areas must have shape ({F.shape[0]},), got {a.shape}")
    AF = sp.csr_matrix(sp.diags(a) @ F)
    if AF.nnz == 0:
        return 0.0
    D = (AF - AF.T).tocsr()
    scale = float(np.abs(AF.data).max())
    return float(np.abs(D.data).max() / scale) if D.nnz else 0.0
