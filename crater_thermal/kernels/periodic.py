"""Numba kernel of the periodic start's quasi-Newton step (:func:`crater_thermal.thermal.periodic_state`).

Only numpy and numba are imported here; no I/O, nothing raised.

Per column the step is ``dx = C^-1/2 f(S) C^1/2 r``: ``S = C^-1/2 (L + H) C^-1/2`` is the symmetric
tridiagonal matrix of the linearised one-step operator (``L`` the conductances between nodes, ``H`` the
surface conductance, ``C`` the heat capacities over the mean sub-step, so that an eigenvalue is
``lambda dt``), and ``f(lambda) = 1 / max(1 - g(lambda)^n, 1e-8)`` with ``g`` the scheme's amplification
of one sub-step and ``n`` the sub-steps of the period. For every mode but the slow ones ``g^n`` is
negligible and ``f = 1``, so ``f(S) z = z + sum over the slow modes of (f_j - 1) (q_j . z) q_j``: only the
slowest eigenpairs are needed. They are found in ascending order, each eigenvalue by bisection on the
Sturm count (to the last bits) and its vector by inverse iteration with partial pivoting, made orthogonal
to the slower ones, until a mode's ``|g|^n`` falls below :data:`NEGLIGIBLE` on the decreasing branch of
``g`` (all modes where ``n`` is too small for that: the full decomposition). ``O(k nz)`` work per bisection
step instead of a dense ``O(nz^3)`` eigen-decomposition.
"""

import numpy as np
from numba import njit, prange

#: A mode whose one-period gain |g|^n is below this leaves the step as it is (f = 1 + O(NEGLIGIBLE)).
NEGLIGIBLE = 1e-13
_BISECT_MAX = 200
_INVERSE_ITERATIONS = 3


@njit(cache=True, error_model="numpy", inline="always")
def _gain(lam, scheme, gamma, w0, w1, beta):
    """Amplification of one sub-step of a linear mode with ``lam = lambda dt`` (0: Euler, 1: TR-BDF2)."""
    if scheme == 0:
        return 1.0 / (1.0 + lam)
    g1 = (1.0 - 0.5 * gamma * lam) / (1.0 + 0.5 * gamma * lam)
    return (w1 * g1 - w0) / (1.0 + beta * lam)


@njit(cache=True, error_model="numpy")
def _count_below(d, e2, sigma, pivmin):
    """Eigenvalues of the symmetric tridiagonal matrix (diagonal ``d``, squared off-diagonal ``e2``) below
    ``sigma`` (Sturm count of the LDL^T pivots)."""
    n = d.shape[0]
    q = d[0] - sigma
    if abs(q) < pivmin:
        q = -pivmin
    count = 1 if q < 0.0 else 0
    for i in range(1, n):
        q = d[i] - sigma - e2[i - 1] / q
        if abs(q) < pivmin:
            q = -pivmin
        if q < 0.0:
            count += 1
    return count


@njit(cache=True, error_model="numpy")
def _solve_shifted(d, e, mu, b, dd, du, du2, pivmin):
    """Solve ``(T - mu I) x = b`` in place of ``b`` for the symmetric tridiagonal T (diagonal ``d``,
    off-diagonal ``e``), Gaussian elimination with partial pivoting; zero pivots perturbed to ``pivmin``
    (inverse iteration wants the near-singular solve)."""
    n = d.shape[0]
    for i in range(n):
        dd[i] = d[i] - mu
    for i in range(n - 1):
        du[i] = e[i]
    lower = e  # the sub-diagonal equals the super-diagonal; read only
    for i in range(n - 1):
        sub = lower[i]
        if abs(dd[i]) >= abs(sub):
            if abs(dd[i]) < pivmin:
                dd[i] = pivmin
            fact = sub / dd[i]
            dd[i + 1] -= fact * du[i]
            b[i + 1] -= fact * b[i]
            du2[i] = 0.0
        else:
            fact = dd[i] / sub
            dd[i] = sub
            temp = dd[i + 1]
            dd[i + 1] = du[i] - fact * temp
            if i < n - 2:
                du2[i] = e[i + 1]
                du[i + 1] = -fact * du2[i]
            else:
                du2[i] = 0.0
            du[i] = temp
            temp = b[i]
            b[i] = b[i + 1]
            b[i + 1] = temp - fact * b[i + 1]
    if abs(dd[n - 1]) < pivmin:
        dd[n - 1] = pivmin
    b[n - 1] /= dd[n - 1]
    if n > 1:
        b[n - 2] = (b[n - 2] - du[n - 2] * b[n - 1]) / dd[n - 2]
    for i in range(n - 3, -1, -1):
        b[i] = (b[i] - du[i] * b[i + 1] - du2[i] * b[i + 2]) / dd[i]


@njit(cache=True, error_model="numpy")
def _column_step(d, e, z, nst, scheme, gamma, w0, w1, beta, g_neg, out, Q, dd, du, du2, v):
    """``out = f(S) z`` for one column (module docstring); ``Q`` (nz, nz) scratch for the slow vectors."""
    n = d.shape[0]
    e2 = np.empty(max(n - 1, 1))
    lo = np.inf
    hi = -np.inf
    scale = 0.0
    for i in range(n):
        r = 0.0
        if i > 0:
            r += abs(e[i - 1])
        if i < n - 1:
            r += abs(e[i])
        lo = min(lo, d[i] - r)
        hi = max(hi, d[i] + r)
        scale = max(scale, abs(d[i]) + r)
    for i in range(n - 1):
        e2[i] = e[i] * e[i]
    emax = 1.0
    for i in range(n - 1):
        emax = max(emax, e2[i])
    pivmin = 2.3e-308 * emax  # the Sturm count's smallest pivot (LAPACK's choice)
    solve_piv = 2.2e-16 * max(scale, 1e-300)  # inverse iteration's: a perturbation of the matrix's size
    lo = max(lo, 0.0) - 1e-12 * scale  # S is positive semi-definite
    hi = hi + 1e-12 * scale
    tiny_neg = g_neg**nst < NEGLIGIBLE  # the negative branch of g cannot hold a slow mode
    for i in range(n):
        out[i] = z[i]
    found = 0
    a = lo
    for j in range(n):
        # the j-th smallest eigenvalue, bisection from the last one found
        left, right = a, hi
        for _ in range(_BISECT_MAX):
            mid = 0.5 * (left + right)
            if mid <= left or mid >= right:
                break
            if _count_below(d, e2, mid, pivmin) > j:
                right = mid
            else:
                left = mid
        lam = 0.5 * (left + right)
        a = left
        g = _gain(max(lam, 0.0), scheme, gamma, w0, w1, beta)
        if g >= 0.0:
            G = g**nst
        else:  # (n is a whole number of sub-steps)
            G = (-g) ** nst
            if nst % 2.0 == 1.0:
                G = -G
        if tiny_neg and (g <= 0.0 or G < NEGLIGIBLE):
            break  # this mode and every faster one: |g|^n negligible (g decreases to 0, then |g| <= g_neg)
        # its vector: inverse iteration, kept orthogonal to the slower ones
        for i in range(n):
            v[i] = 1.0 + 0.37 * ((i * 7919) % 13) / 13.0
        for _ in range(_INVERSE_ITERATIONS):
            _solve_shifted(d, e, lam, v, dd, du, du2, solve_piv)
            for k in range(found):
                p = 0.0
                for i in range(n):
                    p += Q[k, i] * v[i]
                for i in range(n):
                    v[i] -= p * Q[k, i]
            nrm = 0.0
            for i in range(n):
                nrm += v[i] * v[i]
            nrm = np.sqrt(nrm)
            if nrm == 0.0 or not np.isfinite(nrm):
                break
            for i in range(n):
                v[i] /= nrm
        p = 0.0
        for i in range(n):
            Q[found, i] = v[i]
            p += v[i] * z[i]
        c = 1.0 / max(1.0 - G, 1e-8) - 1.0
        for i in range(n):
            out[i] += c * p * v[i]
        found += 1
    return found


@njit(cache=True, error_model="numpy", parallel=True)
def newton_steps(K, h, Cd, r, nst, scheme, gamma, w0, w1, beta, g_neg, dx, modes):
    """The quasi-Newton steps ``dx`` (ncol, nz) [K] of residuals ``r`` (ncol, nz) [K] (module docstring).

    ``K`` (ncol, nz - 1) link conductances [W m-2 K-1], ``h`` (ncol,) surface conductance [W m-2 K-1],
    ``Cd`` (ncol, nz) heat capacity over the mean sub-step [W m-2 K-1], ``nst`` (ncol,) sub-steps of the
    period; ``scheme`` 0 (backward Euler) or 1 (TR-BDF2, constants ``gamma``, ``w0``, ``w1``, ``beta``);
    ``g_neg``: the largest |g| on the scheme's negative branch (0 for Euler). ``modes`` (ncol,): the slow
    modes each column used."""
    ncol, nz = Cd.shape
    for c in prange(ncol):
        d = np.empty(nz)
        e = np.empty(max(nz - 1, 1))
        sc = np.empty(nz)
        z = np.empty(nz)
        out = np.empty(nz)
        Q = np.empty((nz, nz))
        dd = np.empty(nz)
        du = np.empty(max(nz - 1, 1))
        du2 = np.empty(max(nz - 2, 1))
        v = np.empty(nz)
        for i in range(nz):
            sc[i] = np.sqrt(Cd[c, i])
            z[i] = sc[i] * r[c, i]
            diag = 0.0
            if i < nz - 1:
                diag += K[c, i]
            if i > 0:
                diag += K[c, i - 1]
            if i == 0:
                diag += h[c]
            d[i] = diag / Cd[c, i]
        for i in range(nz - 1):
            e[i] = -K[c, i] / (sc[i] * sc[i + 1])
        modes[c] = _column_step(d, e, z, nst[c], scheme, gamma, w0, w1, beta, g_neg, out, Q, dd, du, du2, v)
        for i in range(nz):
            dx[c, i] = out[i] / sc[i]
