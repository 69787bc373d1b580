"""Numba kernels of the compressed view-factor operator (:mod:`crater_thermal.vfoperator`).

Only numpy and numba are imported here; the near blocks' candidate pairs come from the exact matrix's
kernel (:func:`crater_thermal.kernels.viewfactors.block_pairs`), so both paths compute the very same
entries.  Kernels never raise and never do I/O.

All arrays are in the operator's *cluster order* (facets permuted so that every cluster of the tree
is a contiguous index range).  The operator stores the symmetric matrix ``G_ij = A_i F_ij = A_i A_j
K_ij`` [m2]: far blocks as low-rank factors ``U D V^T`` (int16 factors whose columns are scaled to
the int16 range, D the diagonal of their float32 weights), everything else as the upper triangle
``i < j`` of a sparse matrix (float32 values, CSR rows).
"""

import math

import numpy as np
from numba import njit

#: LLVM flags of the one-right-hand-side product kernels (the coupled step's product, one per time step):
#: sums may be reassociated and multiply-adds fused, so that their reductions are unrolled and vectorized.
#: Their results then differ from the plain order's in the last bits only (a few 1e-16 relative); no flag
#: that assumes away NaN or infinity is set. Measured in ``bench/operator_products.py`` (docs/performance.md).
ONE_RHS_FASTMATH = {"reassoc", "contract"}


@njit(nogil=True, cache=True)
def far_block_rays(r0, r1, c0, c1, C, N, P, A, cos_cut, o32, d32, pos, val):
    """Candidate (facing) pairs of the far block rows r0..r1-1 x columns c0..c1-1.

    Writes, per pair, the float32 ray from ``P_i`` to ``P_j`` (tfar = 1 reaches ``P_j``), the flat
    position ``(i - r0) * (c1 - c0) + (j - c0)`` in the block and ``G_ij`` from the centroid kernel
    ``A_i A_j cos_i cos_j / (pi d^2) / d^2`` [m2].  Returns the number of pairs.
    """
    return far_rect_rays(r0, r1, c0, c1, r0, c0, c1 - c0, C, N, P, A, cos_cut, o32, d32, pos, val, 0)


@njit(nogil=True, cache=True)
def far_rect_rays(r0, r1, c0, c1, R0, C0, NC, C, N, P, A, cos_cut, o32, d32, pos, val, n0):
    """:func:`far_block_rays` for the rectangle rows r0..r1-1 x columns c0..c1-1 of a block whose first
    row and column are R0, C0 and whose width is NC: the pairs are written from index ``n0`` on, their
    positions ``(i - R0) * NC + (j - C0)`` in the whole block. Returns ``n0`` + the number of pairs."""
    n = n0
    nc = NC
    cc2 = cos_cut * cos_cut
    for i in range(r0, r1):
        cix = C[i, 0]
        ciy = C[i, 1]
        ciz = C[i, 2]
        nix = N[i, 0]
        niy = N[i, 1]
        niz = N[i, 2]
        for j in range(c0, c1):
            dx = C[j, 0] - cix
            dy = C[j, 1] - ciy
            dz = C[j, 2] - ciz
            d2 = dx * dx + dy * dy + dz * dz
            ci = nix * dx + niy * dy + niz * dz
            cj = -(N[j, 0] * dx + N[j, 1] * dy + N[j, 2] * dz)
            if ci > 0.0 and cj > 0.0 and ci * ci > cc2 * d2 and cj * cj > cc2 * d2:
                val[n] = A[i] * A[j] * ci * cj / (math.pi * d2 * d2)
                pos[n] = (i - R0) * nc + (j - C0)
                o32[n, 0] = P[i, 0]
                o32[n, 1] = P[i, 1]
                o32[n, 2] = P[i, 2]
                d32[n, 0] = P[j, 0] - P[i, 0]
                d32[n, 1] = P[j, 1] - P[i, 1]
                d32[n, 2] = P[j, 2] - P[i, 2]
                n += 1
    return n


@njit(nogil=True, cache=True)
def far_rects_rays(rects, q, a, R0, C0, NC, C, N, P, A, cos_cut, o32, d32, pos, val):
    """:func:`far_rect_rays` over the rectangles ``rects`` (rows ``r0, r1, c0, c1``) of one block, from
    rectangle ``q``, row ``a`` on (``a = -1``: its first row), row by row until the buffers are full.

    Returns ``(n, q, a)``: the pairs written, and where to go on (``q == len(rects)``: all written).
    """
    n = 0
    cap = o32.shape[0]
    while q < rects.shape[0]:
        c0 = rects[q, 2]
        c1 = rects[q, 3]
        if a < rects[q, 0]:
            a = rects[q, 0]
        while a < rects[q, 1]:
            if cap - n < c1 - c0:
                return n, q, a
            n = far_rect_rays(a, a + 1, c0, c1, R0, C0, NC, C, N, P, A, cos_cut, o32, d32, pos, val, n)
            a += 1
        q += 1
        a = -1
    return n, q, a


@njit(nogil=True, cache=True)
def scatter_visible(n, pos, val, blocked, out):
    """``out[pos[k]] = val[k]`` for the first n pairs that are not blocked (out: flat block, zeros)."""
    for k in range(n):
        if blocked[k] == -1:
            out[pos[k]] = val[k]


@njit(nogil=True, cache=True)
def keep_visible(n, blocked, need, pi_, pj_, gg):
    """Compact the first n pairs to the visible ones (in place); returns their number."""
    m = 0
    for k in range(n):
        if blocked[k] != -1 and need[k]:
            continue
        pi_[m] = pi_[k]
        pj_[m] = pj_[k]
        gg[m] = gg[k]
        m += 1
    return m


@njit(nogil=True, cache=True)
def sym_sparse_matvec(indptr, indices, data, x, y, i0, i1):
    """``y += (S + S^T) x`` over the rows i0..i1-1 of the strictly upper-triangular CSR ``S``
    (x, y: (n, k), float64 or float32: the arithmetic is in their type, the float32 values promoted for
    float64). Row ranges split the product between threads (each with its own y)."""
    k = x.shape[1]
    for i in range(i0, i1):
        for q in range(indptr[i], indptr[i + 1]):
            j = indices[q]
            g = data[q]
            for c in range(k):
                y[i, c] += g * x[j, c]
                y[j, c] += g * x[i, c]


#: LLVM flags of the several-right-hand-side low-rank kernels: multiply-adds fused (one rounding instead
#: of two; their grouped sums are written out in the source, nothing is reassociated by the compiler).
MULTI_RHS_FASTMATH = {"contract"}


@njit(nogil=True, cache=True, fastmath=MULTI_RHS_FASTMATH)
def _project(W, off, r, X, x0, count, tmp, t0, wb):
    """``tmp[t0 + q, :] += sum_jj W[off + jj * r + q] X[x0 + jj, :]`` for q < r, jj < count: the
    projection ``W^T X`` of a low-rank factor (row-major (count, r) at ``W[off:]``), four rows of X per
    update of ``tmp`` (a quarter of the loads and stores of one at a time: 1.3x with 64 right-hand
    sides, docs/performance.md). The four rows' numbers are converted to X's type at once into ``wb``
    (at least 4 r), not one by one in the updates."""
    k = X.shape[1]
    jj = 0
    while jj + 3 < count:
        j = x0 + jj
        base = off + jj * r
        for q in range(4 * r):
            wb[q] = W[base + q]
        for q in range(r):
            w0 = wb[q]
            w1 = wb[r + q]
            w2 = wb[2 * r + q]
            w3 = wb[3 * r + q]
            for c in range(k):
                tmp[t0 + q, c] += (w0 * X[j, c] + w1 * X[j + 1, c]) + (w2 * X[j + 2, c] + w3 * X[j + 3, c])
        jj += 4
    while jj < count:
        j = x0 + jj
        base = off + jj * r
        for q in range(r):
            w = W[base + q]
            for c in range(k):
                tmp[t0 + q, c] += w * X[j, c]
        jj += 1


@njit(nogil=True, cache=True, fastmath=MULTI_RHS_FASTMATH)
def _expand(W, off, r, tmp, t0, Y, y0, ii0, ii1, wb):
    """``Y[y0 + ii, :] += sum_q W[off + ii * r + q] tmp[t0 + q, :]`` for ii0 <= ii < ii1, four terms of q
    per update of a row of Y (the row's numbers converted at once into ``wb``, at least r). Each row's
    arithmetic does not depend on the range, so a row computed in any range is the same bit for bit."""
    k = Y.shape[1]
    for ii in range(ii0, ii1):
        i = y0 + ii
        base = off + ii * r
        for q in range(r):
            wb[q] = W[base + q]
        q = 0
        while q + 3 < r:
            w0 = wb[q]
            w1 = wb[q + 1]
            w2 = wb[q + 2]
            w3 = wb[q + 3]
            for c in range(k):
                Y[i, c] += (w0 * tmp[t0 + q, c] + w1 * tmp[t0 + q + 1, c]) + (
                    w2 * tmp[t0 + q + 2, c] + w3 * tmp[t0 + q + 3, c]
                )
            q += 4
        while q < r:
            w = wb[q]
            for c in range(k):
                Y[i, c] += w * tmp[t0 + q, c]
            q += 1


@njit(nogil=True, cache=True, fastmath=MULTI_RHS_FASTMATH)
def _weigh(wts, wo, r, tmp, t0):
    """``tmp[t0 + q, :] *= wts[wo + q]`` for q < r: the weights of a block's terms (the scales of its
    int16 factors' columns), applied between projection and expansion."""
    k = tmp.shape[1]
    for q in range(r):
        w = wts[wo + q]
        for c in range(k):
            tmp[t0 + q, c] *= w


@njit(nogil=True, cache=True, fastmath=MULTI_RHS_FASTMATH)
def lowrank_matvec(r0, r1, c0, c1, rank, uoff, voff, woff, U, V, W, x, y, tmp):
    """``y += sum_b (U_b D_b V_b^T) x[c] (into rows r) + (V_b D_b U_b^T) x[r] (into columns c)``.

    Block b covers rows r0[b]..r1[b]-1 and columns c0[b]..c1[b]-1; ``U_b`` is (m, rank) row-major at
    ``U[uoff[b]:]``, ``V_b`` (n, rank) at ``V[voff[b]:]`` (int16), ``D_b`` the diagonal of the rank
    weights at ``W[woff[b]:]`` (float32).  x, y: (n, k), float64 or float32 (the arithmetic in their type);
    tmp: a work array of their type, at least (2 * max rank, k).
    """
    k = x.shape[1]
    wb = np.empty(2 * tmp.shape[0], tmp.dtype)  # tmp has 2 * max rank rows
    for b in range(r0.shape[0]):
        r = rank[b]
        for q in range(2 * r):
            for c in range(k):
                tmp[q, c] = 0.0
        # tmp[:r] = D V^T x[c-range], tmp[r:2r] = D U^T x[r-range]
        _project(V, voff[b], r, x, c0[b], c1[b] - c0[b], tmp, 0, wb)
        _project(U, uoff[b], r, x, r0[b], r1[b] - r0[b], tmp, r, wb)
        _weigh(W, woff[b], r, tmp, 0)
        _weigh(W, woff[b], r, tmp, r)
        _expand(U, uoff[b], r, tmp, 0, y, r0[b], 0, r1[b] - r0[b], wb)
        _expand(V, voff[b], r, tmp, r, y, c0[b], 0, c1[b] - c0[b], wb)


@njit(nogil=True, cache=True, fastmath=MULTI_RHS_FASTMATH)
def lowrank_matvec_rows(r0, r1, c0, c1, rank, uoff, voff, woff, U, V, W, x, y, tmp, a, b):
    """The rows ``a .. b-1`` of :func:`lowrank_matvec`'s product, into ``y`` ((b - a, k), zeroed by the
    caller): of each block only the halves that land in those rows, ``U_b D_b (V_b^T x[c])`` where its rows
    meet them and ``V_b D_b (U_b^T x[r])`` where its columns do (a row block of a distributed run: a far
    block spanning two chunks is then applied half by each, not whole by both). Each row receives the same
    terms in the same order as from :func:`lowrank_matvec` (the same :func:`_project`, :func:`_weigh` and
    :func:`_expand`), so the rows equal its rows bit for bit. Arrays as :func:`lowrank_matvec`."""
    k = x.shape[1]
    wb = np.empty(2 * tmp.shape[0], tmp.dtype)  # tmp has 2 * max rank rows
    for blk in range(r0.shape[0]):
        r = rank[blk]
        row_lo, row_hi = max(r0[blk], a), min(r1[blk], b)
        col_lo, col_hi = max(c0[blk], a), min(c1[blk], b)
        rows_meet = row_lo < row_hi
        cols_meet = col_lo < col_hi
        if not (rows_meet or cols_meet):
            continue
        for q in range(2 * r):
            for c in range(k):
                tmp[q, c] = 0.0
        if rows_meet:  # tmp[:r] = D V^T x[c-range], into rows row_lo..row_hi-1
            _project(V, voff[blk], r, x, c0[blk], c1[blk] - c0[blk], tmp, 0, wb)
            _weigh(W, woff[blk], r, tmp, 0)
            _expand(U, uoff[blk], r, tmp, 0, y, r0[blk] - a, row_lo - r0[blk], row_hi - r0[blk], wb)
        if cols_meet:  # tmp[r:2r] = D U^T x[r-range], into columns col_lo..col_hi-1
            _project(U, uoff[blk], r, x, r0[blk], r1[blk] - r0[blk], tmp, r, wb)
            _weigh(W, woff[blk], r, tmp, r)
            _expand(V, voff[blk], r, tmp, r, y, c0[blk] - a, col_lo - c0[blk], col_hi - c0[blk], wb)


@njit(nogil=True, cache=True)
def aca_full(R, budget, rmax, U, V):
    """Adaptive cross approximation with full pivoting of a block held in memory.

    ``R`` (m, n) float64 is overwritten by the residual.  Each step takes the residual's largest entry
    as pivot, subtracts the cross ``u v^T`` through it (``u`` its column, ``v`` its row over the
    pivot) and recomputes ``||R||_F^2`` exactly.  Stops when ``||R||_F^2 <= budget`` [same units^2]:
    returns the rank r (columns ``U[:, :r]``, ``V[:, :r]`` hold the factors, ``M ~ U V^T``), or -1 if
    more than ``rmax`` crosses would be needed.
    """
    m, n = R.shape
    fro2 = 0.0
    best = -1.0
    bi = 0
    bj = 0
    for i in range(m):
        for j in range(n):
            x = R[i, j]
            fro2 += x * x
            if abs(x) > best:
                best = abs(x)
                bi = i
                bj = j
    r = 0
    while fro2 > budget:
        if r >= rmax:
            return -1
        p = R[bi, bj]
        if p == 0.0:
            return -1
        for i in range(m):
            U[i, r] = R[i, bj]
        for j in range(n):
            V[j, r] = R[bi, j] / p
        fro2 = 0.0
        best = -1.0
        for i in range(m):
            ui = U[i, r]
            for j in range(n):
                x = R[i, j] - ui * V[j, r]
                R[i, j] = x
                fro2 += x * x
                if abs(x) > best:
                    best = abs(x)
                    bi = i
                    bj = j
        r += 1
    return r


@njit(nogil=True, cache=True)
def csr_matmat(indptr, indices, data, X, Y):
    """``Y += A X`` for a general CSR matrix A (rows ``len(indptr) - 1``; float32 values) and X (n, k),
    Y (rows, k) of one type (float64 or float32): the sums are made in that type, row by row in the
    stored order (a distributed run's row block of the operator, :class:`crater_thermal.vfoperator.RowBlock`)."""
    k = X.shape[1]
    for i in range(len(indptr) - 1):
        for q in range(indptr[i], indptr[i + 1]):
            j = indices[q]
            g = data[q]
            for c in range(k):
                Y[i, c] += g * X[j, c]


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def sym_sparse_matvec1(indptr, indices, data, x, y, i0, i1):
    """One right-hand side of :func:`sym_sparse_matvec`: rows i0..i1-1 (x, y: (n,) float64 or float32)."""
    for i in range(i0, i1):
        xi = x[i]
        acc = 0.0
        for q in range(indptr[i], indptr[i + 1]):
            j = indices[q]
            g = data[q]
            acc += g * x[j]
            y[j] += g * xi
        y[i] += acc


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def _project1(F, off, r, wts, wo, x, x0, count, tmp, t0):
    """``tmp[t0 + q] = wts[wo + q] sum_jj F[off + jj * r + q] x[x0 + jj]`` for q < r, jj < count: one
    vector's weighted projection ``D F^T x`` on a low-rank factor (row-major (count, r) at ``F[off:]``)."""
    for q in range(r):
        tmp[t0 + q] = 0.0
    for jj in range(count):
        xj = x[x0 + jj]
        base = off + jj * r
        for q in range(r):
            tmp[t0 + q] += F[base + q] * xj
    for q in range(r):
        tmp[t0 + q] *= wts[wo + q]


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def _expand1(F, off, r, tmp, t0, y, y0, ii0, ii1):
    """``y[y0 + ii] += sum_q F[off + ii * r + q] tmp[t0 + q]`` for ii0 <= ii < ii1: one vector's expansion
    by a low-rank factor (row-major at ``F[off:]``)."""
    for ii in range(ii0, ii1):
        base = off + ii * r
        acc = 0.0
        for q in range(r):
            acc += F[base + q] * tmp[t0 + q]
        y[y0 + ii] += acc


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def _block_both_ways1(r0, r1, c0, c1, r, uo, vo, wo, U, V, W, x, y, tmp, a):
    """One far block (rows r0..r1-1, columns c0..c1-1, rank r, factors at ``uo``, ``vo``, weights at
    ``wo``) applied both ways to one vector: ``y[i - a] += (U D V^T x[c])_i`` over its rows and
    ``y[j - a] += (V D U^T x[r])_j`` over its columns, with one pass over U (``y`` starts at row ``a``).
    Written out, not through :func:`_project1` and :func:`_expand1`: the same numbers, but the whole
    operator's one-vector product (every coupled step's) took 1.14x as long through them."""
    for q in range(2 * r):
        tmp[q] = 0.0
    for jj in range(c1 - c0):
        xj = x[c0 + jj]
        base = vo + jj * r
        for q in range(r):
            tmp[q] += V[base + q] * xj
    for q in range(r):
        tmp[q] *= W[wo + q]
    # one pass over U: tmp[r:] = U^T x[r-range] and y[r-range] += U tmp[:r]
    for ii in range(r1 - r0):
        i = r0 + ii
        xi = x[i]
        base = uo + ii * r
        acc = 0.0
        for q in range(r):
            u = U[base + q]
            acc += u * tmp[q]
            tmp[r + q] += u * xi
        y[i - a] += acc
    for q in range(r):
        tmp[r + q] *= W[wo + q]
    for jj in range(c1 - c0):
        base = vo + jj * r
        acc = 0.0
        for q in range(r):
            acc += V[base + q] * tmp[r + q]
        y[c0 + jj - a] += acc


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def lowrank_matvec1(r0, r1, c0, c1, rank, uoff, voff, woff, U, V, W, x, y, tmp):
    """One right-hand side of :func:`lowrank_matvec` (x, y: (n,) float64 or float32; tmp: (2 * max rank,) of
    their type)."""
    for b in range(r0.shape[0]):
        _block_both_ways1(r0[b], r1[b], c0[b], c1[b], rank[b], uoff[b], voff[b], woff[b], U, V, W, x, y, tmp, 0)


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def csr_matvec1(indptr, indices, data, x, y):
    """One right-hand side of :func:`csr_matmat`: ``y += A x`` (x (n,), y (rows,) float64; A's float32
    values promoted), each row summed into one accumulator."""
    for i in range(len(indptr) - 1):
        acc = 0.0
        for q in range(indptr[i], indptr[i + 1]):
            acc += data[q] * x[indices[q]]
        y[i] += acc


@njit(nogil=True, cache=True, fastmath=ONE_RHS_FASTMATH)
def lowrank_matvec_rows1(r0, r1, c0, c1, rank, uoff, voff, woff, U, V, W, x, y, tmp, a, b):
    """One right-hand side of :func:`lowrank_matvec_rows`: the rows ``a .. b-1`` of the far-field product
    into ``y`` ((b - a,), zeroed by the caller); x (n,) float64, tmp (2 * max rank,) float64. A block
    wholly inside those rows and columns is applied both ways in one pass over ``U`` (as
    :func:`lowrank_matvec1`); a block that meets them only partly, by the half or halves that land in
    them. A distributed run's one-vector products (the periodic start's holds): 1.9-2.3x faster than the
    several-vector kernels called with one vector (30,000 facets, half the rows; bench/row_block_products.py)."""
    for blk in range(r0.shape[0]):
        r = rank[blk]
        if r0[blk] >= a and r1[blk] <= b and c0[blk] >= a and c1[blk] <= b:  # wholly inside: both ways
            _block_both_ways1(
                r0[blk], r1[blk], c0[blk], c1[blk], r, uoff[blk], voff[blk], woff[blk], U, V, W, x, y, tmp, a
            )
            continue
        if max(r0[blk], a) < min(r1[blk], b):  # y[rows met] += U D V^T x[c-range]
            _project1(V, voff[blk], r, W, woff[blk], x, c0[blk], c1[blk] - c0[blk], tmp, 0)
            _expand1(U, uoff[blk], r, tmp, 0, y, r0[blk] - a, max(r0[blk], a) - r0[blk], min(r1[blk], b) - r0[blk])
        if max(c0[blk], a) < min(c1[blk], b):  # y[columns met] += V D U^T x[r-range]
            _project1(U, uoff[blk], r, W, woff[blk], x, r0[blk], r1[blk] - r0[blk], tmp, r)
            _expand1(V, voff[blk], r, tmp, r, y, c0[blk] - a, max(c0[blk], a) - c0[blk], min(c1[blk], b) - c0[blk])


@njit(nogil=True, cache=True)
def recompress(U, V, R, budget):
    """Shortest truncated SVD of a cross approximation ``U V^T`` whose exact error stays in budget.

    ``U`` (m, r), ``V`` (n, r) C-contiguous float64: the factors of :func:`aca_full` for a block ``M``;
    ``R`` (m, n): its residual ``M - U V^T``; ``budget``: the allowed ``||M - M~||_F^2`` [same units^2].
    With ``U V^T = sum_l s_l a_l b_l^T`` (SVD through the QR factors of U and V), keeping the first k
    terms leaves the error ``R + sum_{l>=k} s_l a_l b_l^T`` whose squared norm is exactly
    ``||R||^2 + sum_{l>=k} s_l (s_l + 2 a_l^T R b_l)``.  Returns ``(k, A_k diag(s_k), B_k)``; k = r with
    the factors unchanged when no term can be dropped.
    """
    m, r = U.shape
    n = V.shape[0]
    if r <= 1:
        return r, U, V
    Qu, Ru = np.linalg.qr(U)
    Qv, Rv = np.linalg.qr(V)
    W, sv, Zt = np.linalg.svd(np.ascontiguousarray(Ru) @ np.ascontiguousarray(Rv.T))
    A = np.ascontiguousarray(Qu) @ np.ascontiguousarray(W)
    B = np.ascontiguousarray(Qv) @ np.ascontiguousarray(Zt.T)
    RB = R @ B
    e2 = 0.0
    for i in range(m):
        for j in range(n):
            e2 += R[i, j] * R[i, j]
    # err2 after keeping k terms, from k = r down to 0; keep the smallest k within budget
    best = r
    acc = e2
    for k in range(r - 1, 0, -1):
        cross = 0.0
        for i in range(m):
            cross += A[i, k] * RB[i, k]
        acc += sv[k] * (sv[k] + 2.0 * cross)
        if acc <= budget:
            best = k
    if best >= r:
        return r, U, V
    Uk = np.empty((m, best))
    Vk = np.empty((n, best))
    for i in range(m):
        for q in range(best):
            Uk[i, q] = A[i, q] * sv[q]
    for j in range(n):
        for q in range(best):
            Vk[j, q] = B[j, q]
    return best, Uk, Vk


@njit(nogil=True, cache=True)
def csr_scatter(rows, cols, vals, cursor, indices, data):
    """Place entries ``(rows[q], cols[q], vals[q])`` in CSR arrays whose row starts are ``cursor``
    (advanced past each placed entry): the counting sort of a CSR assembly from unsorted entries."""
    for q in range(len(rows)):
        p = cursor[rows[q]]
        indices[p] = cols[q]
        data[p] = vals[q]
        cursor[rows[q]] = p + 1


@njit(nogil=True, cache=True)
def csr_sort_merge(indptr, indices, data):
    """Make CSR arrays canonical in place: each row's entries sorted by column, entries of one column
    summed (in the values' type), the rows packed to the front; ``indptr`` is rewritten. Returns the
    entries kept (as scipy's ``sum_duplicates`` leaves them)."""
    n = len(indptr) - 1
    w = 0
    lo = indptr[0]
    for r in range(n):
        hi = indptr[r + 1]
        seg = indices[lo:hi]
        order = np.argsort(seg, kind="mergesort")
        ci = seg[order]
        cd = data[lo:hi][order]
        indptr[r] = w
        k = 0
        while k < len(ci):
            c = ci[k]
            v = cd[k]
            k += 1
            while k < len(ci) and ci[k] == c:
                v += cd[k]
                k += 1
            indices[w] = c
            data[w] = v
            w += 1
        lo = hi
    indptr[n] = w
    return w


# ------------------------------------------------------------------------------- occlusion by the terrain
# A proof that every segment between two clusters passes under a height field (``vfoperator._HeightFloor``).


@njit(nogil=True, cache=True)
def height_floor(V, F, x0, y0, h, nx, ny, zmin, cover):
    """For each cell ``[x0 + ix h, x0 + (ix + 1) h) x [y0 + iy h, ...)``: ``zmin[iy, ix]`` the lowest vertex
    height [m] of the triangles whose xy bounding box meets the cell (a lower bound of a height-field
    surface anywhere in the cell), ``cover[iy, ix]`` how many triangles hold the cell's centre strictly
    inside their xy projection (more than one: the mesh is not a height field)."""
    for f in range(F.shape[0]):
        a, b, c = F[f, 0], F[f, 1], F[f, 2]
        xa, ya, za = V[a, 0], V[a, 1], V[a, 2]
        xb, yb, zb = V[b, 0], V[b, 1], V[b, 2]
        xc, yc, zc = V[c, 0], V[c, 1], V[c, 2]
        zlow = min(za, zb, zc)
        ix0 = max(0, int(math.floor((min(xa, xb, xc) - x0) / h)))
        ix1 = min(nx - 1, int(math.floor((max(xa, xb, xc) - x0) / h)))
        iy0 = max(0, int(math.floor((min(ya, yb, yc) - y0) / h)))
        iy1 = min(ny - 1, int(math.floor((max(ya, yb, yc) - y0) / h)))
        det = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)
        for iy in range(iy0, iy1 + 1):
            py = y0 + (iy + 0.5) * h
            for ix in range(ix0, ix1 + 1):
                if zlow < zmin[iy, ix]:
                    zmin[iy, ix] = zlow
                if det != 0.0:
                    px = x0 + (ix + 0.5) * h
                    l1 = ((xb - px) * (yc - py) - (xc - px) * (yb - py)) / det
                    l2 = ((xc - px) * (ya - py) - (xa - px) * (yc - py)) / det
                    l3 = 1.0 - l1 - l2
                    if l1 > 1e-9 and l2 > 1e-9 and l3 > 1e-9:
                        cover[iy, ix] += 1


@njit(nogil=True, cache=True)
def floor_unknown(V, E, x0, y0, h, nx, ny, zmin):
    """Cells that the xy bounding box of an edge ``E[k]`` (the mesh's boundary) meets get ``-inf``: no
    lower bound where the surface may end."""
    for k in range(E.shape[0]):
        a, b = E[k, 0], E[k, 1]
        ix0 = max(0, int(math.floor((min(V[a, 0], V[b, 0]) - x0) / h)))
        ix1 = min(nx - 1, int(math.floor((max(V[a, 0], V[b, 0]) - x0) / h)))
        iy0 = max(0, int(math.floor((min(V[a, 1], V[b, 1]) - y0) / h)))
        iy1 = min(ny - 1, int(math.floor((max(V[a, 1], V[b, 1]) - y0) / h)))
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                zmin[iy, ix] = -np.inf


@njit(nogil=True, cache=True)
def node_discs(lo, hi, P, cx, cy, rho, ztop):
    """Per tree node: the xy centre [m] of its points ``P[lo:hi]``, the xy radius about it [m] and the
    highest z [m]."""
    for k in range(lo.shape[0]):
        a, b = lo[k], hi[k]
        sx = 0.0
        sy = 0.0
        zt = -np.inf
        for i in range(a, b):
            sx += P[i, 0]
            sy += P[i, 1]
            zt = max(zt, P[i, 2])
        mx = sx / (b - a)
        my = sy / (b - a)
        r2 = 0.0
        for i in range(a, b):
            r2 = max(r2, (P[i, 0] - mx) ** 2 + (P[i, 1] - my) ** 2)
        cx[k] = mx
        cy[k] = my
        rho[k] = math.sqrt(r2)
        ztop[k] = zt


@njit(nogil=True, cache=True)
def hidden(s, t, cx, cy, rho, ztop, x0, y0, h, floor, ncut, margin):
    """True if every segment from a point of node s to a point of node t (points within ``rho`` of the
    node's xy centre, no higher than ``ztop``) passes below the height field somewhere: on one of
    ``ncut`` lines across the corridor between the two nodes, the floor (``floor``: per cell of size
    ``h``, a lower bound of the surface) of every cell the line crosses exceeds, by ``margin`` [m], the
    highest such a segment can be where it crosses the line. A segment that starts and ends above a
    continuous height field and passes below it crosses it: the pair is occluded. False when not proven.
    The line is sampled every h / 4 and each sample checks the cells within h / 8 of it, so every cell
    that the line crosses is checked."""
    dx = cx[t] - cx[s]
    dy = cy[t] - cy[s]
    dist = math.sqrt(dx * dx + dy * dy)
    rs, rt = rho[s], rho[t]
    if dist <= rs + rt:
        return False
    ex, ey = dx / dist, dy / dist
    ny, nx = floor.shape
    zs, zt = ztop[s], ztop[t]
    e = 0.125 * h
    for c in range(1, ncut + 1):
        u = rs + (dist - rt - rs) * c / (ncut + 1.0)
        # a segment from u_p in [-rs, rs] to u_q in [dist - rt, dist + rt] crosses the line u at the
        # fraction a = (u - u_p) / (u_q - u_p) of its length, a in [amin, amax]; there its height is at
        # most (1 - a) zs + a zt and its offset across the axis at most (1 - a) rs + a rt
        amin = max(0.0, (u - rs) / (dist + rt - rs))
        amax = min(1.0, (u + rs) / (dist - rt + rs))
        zc = max((1.0 - amin) * zs + amin * zt, (1.0 - amax) * zs + amax * zt) + margin
        vmax = max((1.0 - amin) * rs + amin * rt, (1.0 - amax) * rs + amax * rt)
        ns = int(math.ceil(8.0 * vmax / h)) + 2  # samples at most h / 4 apart
        proven = True
        for k in range(ns):
            v = -vmax + 2.0 * vmax * k / (ns - 1)
            px = cx[s] + u * ex - v * ey - x0
            py = cy[s] + u * ey + v * ex - y0
            if not (px - e >= 0.0 and py - e >= 0.0 and px + e < nx * h and py + e < ny * h):
                proven = False
                break
            ix0 = int((px - e) / h)
            ix1 = int((px + e) / h)
            iy0 = int((py - e) / h)
            iy1 = int((py + e) / h)
            if min(floor[iy0, ix0], floor[iy0, ix1], floor[iy1, ix0], floor[iy1, ix1]) <= zc:
                proven = False
                break
        if proven:
            return True
    return False


@njit(nogil=True, cache=True)
def unproven_rects(s, t, left, right, lo, hi, cx, cy, rho, ztop, x0, y0, h, floor, ncut, margin, min_pairs, out):
    """The rectangles (r0, r1, c0, c1) of the far block (s, t) left after the sub-blocks proven occluded
    (:func:`hidden`, tried on the block and then on its children's pairs down to ``min_pairs`` pairs)
    are taken out. Writes them to ``out`` (rows of 4) and returns their number, or -1 if ``out`` is too
    short for them (then nothing is proven: the caller traces the whole block)."""
    stack = np.empty((512, 2), np.int64)
    stack[0, 0] = s
    stack[0, 1] = t
    top = 1
    n = 0
    while top > 0:
        top -= 1
        a = stack[top, 0]
        b = stack[top, 1]
        if hidden(a, b, cx, cy, rho, ztop, x0, y0, h, floor, ncut, margin):
            continue
        split_a = left[a] >= 0
        split_b = left[b] >= 0
        if (hi[a] - lo[a]) * (hi[b] - lo[b]) > min_pairs and (split_a or split_b) and top + 4 <= 512:
            if split_a and split_b:
                for p in (left[a], right[a]):
                    for q in (left[b], right[b]):
                        stack[top, 0] = p
                        stack[top, 1] = q
                        top += 1
            elif split_a:
                for p in (left[a], right[a]):
                    stack[top, 0] = p
                    stack[top, 1] = b
                    top += 1
            else:
                for q in (left[b], right[b]):
                    stack[top, 0] = a
                    stack[top, 1] = q
                    top += 1
            continue
        if n == out.shape[0]:
            return -1
        out[n, 0] = lo[a]
        out[n, 1] = hi[a]
        out[n, 2] = lo[b]
        out[n, 3] = hi[b]
        n += 1
    return n
