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

import math
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np
import scipy.sparse as sp

from crater_thermal.errors import InternalError, MeshError
from crater_thermal.geometry import Mesh

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

    return (f"{ALGORITHM_VERSION}-near{NEAR_DISTANCE_FACTOR:g}x{NEAR_SUBDIVISIONS}"
            f"-cos{COS_CUTOFF:g}-off{RAY_OFFSET_FRACTION:g}")


def _subtriangle_barycentrics(k: int) -> np.ndarray:
    """(k*k, 3) barycentric coordinates of the centroids of the k^2 congruent sub-triangles."""
    pts = []
    for a in range(k):
        for b in range(k - a):
            pts.append(((a + 1.0 / 3.0) / k, (b + 1.0 / 3.0) / k))  # "upright"
            if a + b <= k - 2:
                pts.append(((a + 2.0 / 3.0) / k, (b + 2.0 / 3.0) / k))  # "inverted"
    uv = np.array(pts)
    return np.ascontiguousarray(np.column_stack([1.0 - uv.sum(axis=1), uv]))


@numba.njit(nogil=True, cache=True)
def _clip_by_plane(V, Fc, j, n, c, out):
    """Part of triangle j in front of (or on) the plane (normal n through c); returns vertex count (0-4)."""
    m = 0
    for k in range(3):
        a = Fc[j, k]
        b = Fc[j, (k + 1) % 3]
        da = n[0] * (V[a, 0] - c[0]) + n[1] * (V[a, 1] - c[1]) + n[2] * (V[a, 2] - c[2])
        db = n[0] * (V[b, 0] - c[0]) + n[1] * (V[b, 1] - c[1]) + n[2] * (V[b, 2] - c[2])
        if da >= 0.0:  # vertices on the plane belong to the clipped polygon
            for q in range(3):
                out[m, q] = V[a, q]
            m += 1
        if (da > 0.0 and db < 0.0) or (da < 0.0 and db > 0.0):
            t = da / (da - db)
            for q in range(3):
                out[m, q] = V[a, q] + t * (V[b, q] - V[a, q])
            m += 1
    return m


@numba.njit(nogil=True, cache=True)
def _point_to_polygon(px, py, pz, n, poly, m):
    """Exact view factor from a differential area (point p, unit normal n) to a planar polygon that lies
    entirely in front of it (Lambert's contour formula: sum of edge angles times n . edge-plane normal,
    over 2 pi)."""
    acc = 0.0
    for k in range(m):
        ax = poly[k, 0] - px
        ay = poly[k, 1] - py
        az = poly[k, 2] - pz
        kk = (k + 1) % m
        bx = poly[kk, 0] - px
        by = poly[kk, 1] - py
        bz = poly[kk, 2] - pz
        cx = ay * bz - az * by
        cy = az * bx - ax * bz
        cz = ax * by - ay * bx
        cn = math.sqrt(cx * cx + cy * cy + cz * cz)
        if cn <= 0.0:
            continue
        gamma = math.atan2(cn, ax * bx + ay * by + az * bz)
        acc += gamma * (n[0] * cx + n[1] * cy + n[2] * cz) / cn
    return abs(acc) / (2.0 * math.pi)


@numba.njit(nogil=True, cache=True)
def _facet_to_facet(i, j, V, Fc, N, C, bary, poly):
    """F_ij: mean over quadrature points p of facet i of the exact point-to-facet view factor to facet j
    (j clipped to the half-space in front of i; zero where p is behind j's plane)."""
    m = _clip_by_plane(V, Fc, j, N[i], C[i], poly)
    if m < 3:
        return 0.0
    q = bary.shape[0]
    acc = 0.0
    for s in range(q):
        px = bary[s, 0] * V[Fc[i, 0], 0] + bary[s, 1] * V[Fc[i, 1], 0] + bary[s, 2] * V[Fc[i, 2], 0]
        py = bary[s, 0] * V[Fc[i, 0], 1] + bary[s, 1] * V[Fc[i, 1], 1] + bary[s, 2] * V[Fc[i, 2], 1]
        pz = bary[s, 0] * V[Fc[i, 0], 2] + bary[s, 1] * V[Fc[i, 1], 2] + bary[s, 2] * V[Fc[i, 2], 2]
        # p must be in front of j's plane: then every point of j faces p
        if N[j, 0] * (px - C[j, 0]) + N[j, 1] * (py - C[j, 1]) + N[j, 2] * (pz - C[j, 2]) <= 0.0:
            continue
        acc += _point_to_polygon(px, py, pz, N[i], poly, m)
    return acc / q


@numba.njit(nogil=True, cache=True)
def _near_kernel(i, j, V, Fc, N, C, A, bary, poly):
    """Symmetric mean kernel K_ij = (F_ij / A_j + F_ji / A_i) / 2 for a near pair (exact reciprocity)."""
    fij = _facet_to_facet(i, j, V, Fc, N, C, bary, poly)
    fji = _facet_to_facet(j, i, V, Fc, N, C, bary, poly)
    return 0.5 * (fij / A[j] + fji / A[i])


@numba.njit(nogil=True, cache=True)
def _candidate_pairs(i0, i1, C, N, S, A, P, V, Fc, bary, near_factor, cos_cut, o32, d32, pi_, pj_, kk, need):
    """Fill buffers with the candidate pairs (i, j > i) of rows i0..i1-1; returns their number.

    o32/d32: float32 ray origin (P_i) and unnormalised direction (P_j - P_i), so tfar = 1 reaches P_j.
    need: False for near pairs taken as visible without a ray.
    """
    nf = C.shape[0]
    n = 0
    cc2 = cos_cut * cos_cut
    poly = np.empty((4, 3))
    for i in range(i0, i1):
        cix = C[i, 0]
        ciy = C[i, 1]
        ciz = C[i, 2]
        nix = N[i, 0]
        niy = N[i, 1]
        niz = N[i, 2]
        si = S[i]
        for j in range(i + 1, nf):
            dx = C[j, 0] - cix
            dy = C[j, 1] - ciy
            dz = C[j, 2] - ciz
            d2 = dx * dx + dy * dy + dz * dz
            ci = nix * dx + niy * dy + niz * dz
            cj = -(N[j, 0] * dx + N[j, 1] * dy + N[j, 2] * dz)
            sm = si if si > S[j] else S[j]
            lim = near_factor * sm
            facing = ci > 0.0 and cj > 0.0 and ci * ci > cc2 * d2 and cj * cj > cc2 * d2
            if d2 < lim * lim:
                k = _near_kernel(i, j, V, Fc, N, C, A, bary, poly)
                if k <= 0.0:
                    continue
                need[n] = facing
            elif facing:
                k = ci * cj / (math.pi * d2 * d2)
                need[n] = True
            else:
                continue
            o32[n, 0] = P[i, 0]
            o32[n, 1] = P[i, 1]
            o32[n, 2] = P[i, 2]
            d32[n, 0] = P[j, 0] - P[i, 0]
            d32[n, 1] = P[j, 1] - P[i, 1]
            d32[n, 2] = P[j, 2] - P[i, 2]
            pi_[n] = i
            pj_[n] = j
            kk[n] = k
            n += 1
    return n


@numba.njit(nogil=True, cache=True)
def _compact(n, blocked, need, pi_, pj_, kk, nf):
    """Keep the visible pairs among the first n (in place, order kept); count entries per row.

    Returns (m, up, low): m visible pairs; up[r] pairs with first index r; low[r] with second index r.
    """
    up = np.zeros(nf, np.int64)
    low = np.zeros(nf, np.int64)
    m = 0
    for p in range(n):
        if blocked[p] and need[p]:
            continue
        pi_[m] = pi_[p]
        pj_[m] = pj_[p]
        kk[m] = kk[p]
        up[pi_[m]] += 1
        low[pj_[m]] += 1
        m += 1
    return m, up, low


@numba.njit(nogil=True, cache=True)
def _fill(pi_, pj_, kk, A, pos_up, pos_low, up_end, low_end, indices, data):
    """Write one chunk's pairs as (i, j) and (j, i) entries of the CSR arrays; returns False (and stops)
    if a pair would land outside the slots reserved for it (an internal counting error).

    pos_up[i]: next free slot of row i's upper part (rows of this chunk only, so chunks never share
    them); pos_low: this chunk's own start slots of the lower parts.  up_end / low_end: the first slot
    after row r's upper part / after this chunk's share of row r's lower part.  Pairs come sorted by
    (i, j).
    """
    for p in range(pi_.shape[0]):
        i = pi_[p]
        j = pj_[p]
        k = kk[p]
        q = pos_up[i]
        if q >= up_end[i]:
            return False
        indices[q] = j
        data[q] = k * A[j]
        pos_up[i] = q + 1
        q = pos_low[j]
        if q >= low_end[j]:
            return False
        indices[q] = i
        data[q] = k * A[i]
        pos_low[j] = q + 1
    return True


@numba.njit(nogil=True, cache=True)
def _rescale_rows(indptr, indices, data):
    """Scale entries by min(s_i, s_j), s = min(1, 1 / row sum); returns the largest excess rowsum - 1."""
    nf = indptr.shape[0] - 1
    s = np.ones(nf)
    excess = 0.0
    for r in range(nf):
        t = 0.0
        for q in range(indptr[r], indptr[r + 1]):
            t += data[q]
        if t > 1.0:
            s[r] = 1.0 / t
            excess = max(excess, t - 1.0)
    if excess > 0.0:
        for r in range(nf):
            for q in range(indptr[r], indptr[r + 1]):
                data[q] *= min(s[r], s[indices[q]])
    return excess


def _assemble(nf: int, results: list, A: np.ndarray, pool=None):
    """CSR arrays with sorted columns from the per-chunk visible pairs (chunks in row order).

    ``results`` holds, per chunk, ``(pi, pj, k, up, low)``: the visible pairs (i < j) and the per-row
    counts ``up[r]`` (pairs with first index r) and ``low[r]`` (pairs with second index r) that
    :func:`_compact` counted while keeping exactly these pairs.  Row r holds first the entries (r, i)
    of pairs (i, r), i < r, in increasing i (chunk by chunk), then the entries (r, j) of pairs (r, j),
    j > r: no sort is needed.  Each chunk gets its own start-slot array (never a shared one), chunks
    fill disjoint slots, so they are written concurrently.  Every write is checked against the end of
    its reserved slots, and every slot must be filled exactly once; otherwise :class:`InternalError`.
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
        starts.append(acc.copy())  # advanced in place by _fill: must not alias any end array
        ends.append(nxt)
        acc = nxt
    del acc

    def fill(c):
        pi_, pj_, kk = results[c][:3]
        return _fill(pi_, pj_, kk, A, pos_up, starts[c], up_end, ends[c], indices, data)

    if pool is None:
        ok = [fill(c) for c in range(len(results))]
    else:
        ok = list(pool.map(fill, range(len(results))))
    filled = all(ok) and np.array_equal(pos_up, up_end) and all(
        np.array_equal(s, e) for s, e in zip(starts, ends))
    if not filled:
        raise InternalError("view factors: the filled entries differ from the counted ones")
    excess = _rescale_rows(indptr, indices, data)
    return indptr, indices, data, excess


def _row_chunks(nf: int, chunk_pairs: int) -> list[tuple[int, int]]:
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
        with np.load(path, allow_pickle=False) as z:
            if str(z["mesh_hash"]) != mesh.hash or str(z["version"]) != _algorithm_key():
                return None
            F = sp.csr_matrix((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))
            F.rowsum_excess = float(z["rowsum_excess"])
            return F
    except (OSError, KeyError, ValueError):
        return None


def _save_cached(path: Path, F: sp.csr_matrix, mesh: Mesh) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, data=F.data, indices=F.indices, indptr=F.indptr, shape=np.array(F.shape),
                     mesh_hash=np.array(mesh.hash), version=np.array(_algorithm_key()),
                     rowsum_excess=np.array(getattr(F, "rowsum_excess", 0.0)))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def view_factor_matrix(mesh: Mesh, tracer=None, cache_dir=None, progress: bool = False,
                       chunk_pairs: int = CHUNK_PAIRS) -> sp.csr_matrix:
    """View-factor matrix with ray-traced visibility.

    Parameters
    ----------
    mesh : Mesh
    tracer : RayTracer, optional
        Built from ``mesh`` if not given (its thread count is used).
    cache_dir : path-like, optional
        Folder for the ``.npz`` cache keyed by ``mesh.hash`` and :data:`ALGORITHM_VERSION`.
    progress : bool
        Show a rich progress bar.
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
    bary = _subtriangle_barycentrics(NEAR_SUBDIVISIONS)
    chunks = _row_chunks(nf, int(chunk_pairs))
    ones = np.ones(max(1, min(int(chunk_pairs), nf * (nf - 1) // 2 + 1)) + nf, dtype=np.float32)

    def empty():
        # fresh arrays each time: _assemble derives per-chunk slots from them
        return (np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0),
                np.zeros(nf, np.int64), np.zeros(nf, np.int64))

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
        n = _candidate_pairs(i0, i1, C, N, S, A, P, V, Fc, bary, NEAR_DISTANCE_FACTOR, COS_CUTOFF,
                             o32, d32, pi_, pj_, kk, need)
        if n == 0:
            return empty()
        t = ones[:n] if n <= ones.shape[0] else np.ones(n, np.float32)
        blocked = tracer._scene.run(o32[:n], d32[:n], dists=t, query="OCCLUDED") != -1
        del o32, d32
        m, up, low = _compact(n, blocked, need, pi_, pj_, kk, nf)
        # copies, so that the chunk-sized buffers are freed
        return pi_[:m].copy(), pj_[:m].copy(), kk[:m].copy(), up, low

    results = []
    n_threads = max(1, tracer.n_threads)
    if progress:
        from rich.progress import Progress

        prog = Progress(transient=True)
        prog.start()
        task = prog.add_task(f"view factors ({nf} facets)", total=len(chunks))
    pool = ThreadPoolExecutor(n_threads) if n_threads > 1 and len(chunks) > 1 else None
    try:
        if pool is None:
            for c in chunks:
                results.append(work(c))
                if progress:
                    prog.advance(task)
        else:
            for r in pool.map(work, chunks):
                results.append(r)
                if progress:
                    prog.advance(task)
        indptr, indices, data, excess = _assemble(nf, results, A, pool)
    finally:
        if pool is not None:
            pool.shutdown()
        if progress:
            prog.stop()
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
