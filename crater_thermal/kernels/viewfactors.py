"""Numba kernels of the view-factor matrix (:mod:`crater_thermal.viewfactors` wraps them).

Only numpy and numba (and math) are imported here; kernels never raise and never do I/O: a failed
consistency check is returned as a flag that the wrapper turns into an exception.

* :func:`clip_by_plane`, :func:`point_to_polygon`, :func:`facet_to_facet`, :func:`near_kernel`: the
  exact point-to-polygon view factor (Lambert's contour formula) and its sub-triangle quadrature for
  near pairs;
* :func:`block_pairs` (and :func:`candidate_pairs`, its exact-matrix form): the pairs of a block of rows
  (and columns, for the compressed operator's near blocks) that need a kernel value (and a visibility ray);
* :func:`compact_pairs`, :func:`fill_pairs`, :func:`rescale_rows`: assembly of the symmetric CSR matrix.
"""

import math

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def clip_by_plane(V, Fc, j, n, c, out):
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


@njit(nogil=True, cache=True)
def point_to_polygon(px, py, pz, n, poly, m):
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


@njit(nogil=True, cache=True)
def facet_to_facet(i, j, V, Fc, N, C, bary, poly):
    """F_ij: mean over quadrature points p of facet i of the exact point-to-facet view factor to facet j
    (j clipped to the half-space in front of i; zero where p is behind j's plane)."""
    m = clip_by_plane(V, Fc, j, N[i], C[i], poly)
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
        acc += point_to_polygon(px, py, pz, N[i], poly, m)
    return acc / q


@njit(nogil=True, cache=True)
def near_kernel(i, j, V, Fc, N, C, A, bary, poly):
    """Symmetric mean kernel K_ij = (F_ij / A_j + F_ji / A_i) / 2 for a near pair (exact reciprocity)."""
    fij = facet_to_facet(i, j, V, Fc, N, C, bary, poly)
    fji = facet_to_facet(j, i, V, Fc, N, C, bary, poly)
    return 0.5 * (fij / A[j] + fji / A[i])


@njit(nogil=True, cache=True)
def block_pairs(
    r0, r1, c0, c1, diag, C, N, S, A, P, V, Fc, bary, near_factor, cos_cut, o32, d32, pi_, pj_, kk, need, times_areas
):
    """Fill buffers with the candidate pairs of rows r0..r1-1 and columns c0..c1-1 (``diag``: only j > i);
    returns their number. One rule for the exact matrix and the compressed operator's near blocks.

    Pairs closer than ``near_factor`` facet sizes take the sub-facet quadrature (:func:`near_kernel`),
    the others the centroid kernel cos_i cos_j / (pi d^2) [m-2] when both facets face each other past
    ``cos_cut``. kk: the kernel K_ij [m-2], or G_ij = K_ij A_i A_j [m2] with ``times_areas``.
    o32/d32: float32 ray origin (P_i) and unnormalised direction (P_j - P_i), so tfar = 1 reaches P_j.
    need: False for near pairs taken as visible without a ray.
    """
    n = 0
    cc2 = cos_cut * cos_cut
    poly = np.empty((4, 3))
    for i in range(r0, r1):
        cix = C[i, 0]
        ciy = C[i, 1]
        ciz = C[i, 2]
        nix = N[i, 0]
        niy = N[i, 1]
        niz = N[i, 2]
        si = S[i]
        j0 = i + 1 if diag else c0
        for j in range(j0, c1):
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
                k = near_kernel(i, j, V, Fc, N, C, A, bary, poly)
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
            kk[n] = k * A[i] * A[j] if times_areas else k
            n += 1
    return n


@njit(nogil=True, cache=True)
def candidate_pairs(i0, i1, C, N, S, A, P, V, Fc, bary, near_factor, cos_cut, o32, d32, pi_, pj_, kk, need):
    """The exact matrix's candidate pairs (i, j > i) of rows i0..i1-1 with their kernel K_ij [m-2]
    (:func:`block_pairs` over all columns); returns their number."""
    return block_pairs(
        i0,
        i1,
        0,
        C.shape[0],
        True,
        C,
        N,
        S,
        A,
        P,
        V,
        Fc,
        bary,
        near_factor,
        cos_cut,
        o32,
        d32,
        pi_,
        pj_,
        kk,
        need,
        False,
    )


@njit(nogil=True, cache=True)
def compact_pairs(n, blocked, need, pi_, pj_, kk, nf):
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


@njit(nogil=True, cache=True)
def fill_pairs(pi_, pj_, kk, A, pos_up, pos_low, up_end, low_end, indices, data):
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


@njit(nogil=True, cache=True)
def rescale_rows(indptr, indices, data):
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
