"""Numba kernels for 1-D nonlinear heat conduction in many independent columns.

Only numpy and numba are imported here; kernels never raise and never do I/O: problems are
reported through integer status codes (:data:`OK`, :data:`NEWTON_FAILED`, :data:`NONFINITE`)
plus the index of the time sample at which they happened; :mod:`crater_thermal.thermal` turns
them into :class:`~crater_thermal.errors.SolverError`.

Discretisation (see :mod:`crater_thermal.thermal` for the full description)
------------------------------------------------------------------------------
Vertex-centred finite volumes: node ``i`` at depth ``z[i]`` (``z[0] = 0`` is the surface,
``z[-1]`` the bottom) owns the control volume between the link mid-points (half cells at both
ends). Per node the areal mass ``m[i]`` [kg m-2]; per link ``l`` (between nodes l and l+1,
length ``dz[l]``) the conductivity coefficients of

    k(T) = b0 + b3 T^3 + c(T) (e0 + e1 / T)           (e0, e1 nonzero for rock only)

evaluated at the link's mean temperature. c(T) is the polynomial ``ccoef`` (ascending powers)
evaluated at ``max(T, ctmin)``.

Time stepping: TR-BDF2 (default) or backward Euler, both L-stable (rock columns have
kappa dt / dz^2 ~ 1e3 at the surface); properties (k, c) lagged within each stage; the
nonlinear surface emission ``eps sigma T^4`` implicit and solved exactly by a scalar Newton
iteration after eliminating the tridiagonal system from the bottom up (Thomas algorithm run
bottom-to-top, so that the only unknown left is the surface temperature). The absorbed flux is
linear in time between samples; the geothermal flux ``G`` enters the bottom half cell.
:data:`LANES` columns are advanced together per thread, interleaved, so that the serial Thomas
recurrences of different columns overlap and the inner loops vectorise.
"""

import numpy as np
from numba import njit, prange

OK = 0
NEWTON_FAILED = 1
NONFINITE = 2

#: Accumulator columns (per column): absorbed energy, emitted energy [J m-2] (with the scheme's
#: own time quadrature), sum of 4 eps sigma Ts^3 dt [J m-2 K-1], elapsed time [s], sub-steps.
ACC_ABSORBED, ACC_EMITTED, ACC_HDT, ACC_TIME, ACC_NSTEPS = 0, 1, 2, 3, 4
N_ACC = 5

_NEWTON_MAXIT = 60
_NEWTON_RTOL = 1e-12
_T_MAX = 1.0e5


@njit(cache=True, error_model="numpy", inline="always")
def _cpoly(T, ccoef, ctmin):
    x = T if T > ctmin else ctmin
    return ccoef[0] + x * (ccoef[1] + x * (ccoef[2] + x * (ccoef[3] + x * ccoef[4])))


#: Columns advanced together in one thread (interleaved so that the serial Thomas recurrences
#: of different columns overlap and the inner loops vectorise).
LANES = 32
#: Number of parts a sub-step flagged by the adaptive refinement is split into.
N_REFINE = 4

#: TR-BDF2 constants (Bank et al. 1985; Hosea & Shampine 1996): gamma = 2 - sqrt(2)
TRB_GAMMA = 2.0 - np.sqrt(2.0)
TRB_W1 = 1.0 / (TRB_GAMMA * (2.0 - TRB_GAMMA))
TRB_W0 = (1.0 - TRB_GAMMA) ** 2 / (TRB_GAMMA * (2.0 - TRB_GAMMA))
TRB_BETA = (1.0 - TRB_GAMMA) / (2.0 - TRB_GAMMA)
#: quadrature weights of f(t_n), f(t_n + gamma dt), f(t_n+1) implied by the scheme
TRB_QW0 = 1.0 / (2.0 * (2.0 - TRB_GAMMA))
TRB_QW1 = TRB_BETA

SCHEME_BE = 0
SCHEME_TRBDF2 = 1


@njit(cache=True, error_model="numpy")
def _props(T, m, b0, b3, e0, e1, anyrock, ccoef, ctmin, rdz, K, Cc):
    """Link conductances K [W m-2 K-1] and node heat capacities Cc = m c [J m-2 K-1] at T.

    All arrays (n, LANES) (links: nz-1 rows).
    """
    nz, nl = T.shape
    c0, c1, c2, c3, c4 = ccoef[0], ccoef[1], ccoef[2], ccoef[3], ccoef[4]
    for l in range(nz - 1):
        r = rdz[l]
        for j in range(nl):
            tl = 0.5 * (T[l, j] + T[l + 1, j])
            K[l, j] = (b0[l, j] + b3[l, j] * tl * tl * tl) * r
    if anyrock:
        for l in range(nz - 1):
            r = rdz[l]
            for j in range(nl):
                tl = 0.5 * (T[l, j] + T[l + 1, j])
                x = max(tl, ctmin)
                c = c0 + x * (c1 + x * (c2 + x * (c3 + x * c4)))
                K[l, j] += c * (e0[l, j] + e1[l, j] / tl) * r
    for i in range(nz):
        for j in range(nl):
            x = max(T[i, j], ctmin)
            Cc[i, j] = m[i, j] * (c0 + x * (c1 + x * (c2 + x * (c3 + x * c4))))


@njit(cache=True, error_model="numpy")
def _solve(X, R, K, Cc, rtau, theta, a4, tguess, p, q, st, alt_add, alt_used, act):
    """Solve (Cc/tau + theta L) X + a4 X0^4 e_0 = R for X (in place), lane by lane; L is the
    conduction operator with conductances K (no-flux ends: boundary fluxes are in R).

    Elimination runs bottom-up (X[i] = p[i] + q[i] X[i-1]) leaving the scalar surface equation
    alpha x + a4 x^4 = rhs per lane, solved by Newton. Lanes whose status ``st`` is already
    nonzero are skipped; failures set ``st``.

    Fallback (TR stage only, ``alt_add`` non-empty): where the trapezoidal treatment of the
    emission has no physical root (rhs <= 0) or drops the surface below half its start value
    (an extreme cooling transient, e.g. a hot uniform start), the lane's emission is taken
    implicit instead (a4 -> 2 a4, rhs -> rhs + alt_add[j]) and ``alt_used[j]`` is set to 1.
    """
    nz, nl = X.shape
    n1 = nz - 1
    for j in range(nl):
        kb = theta * K[n1 - 1, j]
        inv = 1.0 / (Cc[n1, j] * rtau + kb)
        p[n1, j] = R[n1, j] * inv
        q[n1, j] = kb * inv
    for i in range(n1 - 1, 0, -1):
        for j in range(nl):
            ku = theta * K[i - 1, j]
            kd = theta * K[i, j]
            inv = 1.0 / (Cc[i, j] * rtau + ku + kd * (1.0 - q[i + 1, j]))
            p[i, j] = (R[i, j] + kd * p[i + 1, j]) * inv
            q[i, j] = ku * inv
    # the surface equation per lane: alpha x + a4 x^4 = rhs, alpha in p[0], rhs in q[0] (rows free here)
    alpha = p[0]
    rhs = q[0]
    for j in range(nl):
        act[j] = 0
        if st[j] != OK:
            continue
        act[j] = 1
        k0 = theta * K[0, j]
        alpha[j] = Cc[0, j] * rtau + k0 * (1.0 - q[1, j])
        rhs[j] = R[0, j] + k0 * p[1, j]
        if a4 == 0.0:
            X[0, j] = rhs[j] / alpha[j]
        elif alt_add.shape[0] == 0 or rhs[j] > 0.0:
            act[j] = 2
    if a4 != 0.0:
        # every lane's Newton iteration at once (independent chains overlap: each lane's iterates are
        # those of _newton alone)
        _newton_lanes(alpha, a4, rhs, tguess, X[0], act, st)
        if alt_add.shape[0] > 0:
            # TR stage: the trapezoidal root, or the implicit fallback where it has none or is too cold
            for j in range(nl):
                if act[j] == 0:
                    continue
                alt_used[j] = 0
                if rhs[j] <= 0.0 or X[0, j] < 0.5 * tguess[j]:
                    alt_used[j] = 1
                    st[j] = OK
                    X[0, j] = _newton(alpha[j], 2.0 * a4, rhs[j] + alt_add[j], tguess[j], st, j)
    for j in range(nl):
        if act[j] != 0:
            x = X[0, j]
            if not (x > 0.0 and x < _T_MAX):
                st[j] = NONFINITE
                X[0, j] = 1.0
    for i in range(1, nz):
        for j in range(nl):
            X[i, j] = p[i, j] + q[i, j] * X[i - 1, j]


@njit(cache=True, error_model="numpy", inline="always")
def _newton_start(alpha, a4, rhs, tguess):
    """Newton's start for alpha x + a4 x^4 = rhs: the guess, raised to the lower bound
    min(rhs / alpha, (rhs / a4)^1/4) of the root where it lies below it (1 if not positive)."""
    x = tguess
    xl = rhs / alpha
    # the bound's quartic root (a pow) only where the guess may lie below it: x < xr <=> a4 x^4 < rhs
    if x < xl and (x <= 0.0 or a4 * (x * x) * (x * x) < rhs):
        xr = (rhs / a4) ** 0.25 if rhs > 0.0 else 0.0
        if xr < xl:
            xl = xr
        if x < xl:
            x = xl
    if not (x > 0.0):
        x = 1.0
    return x


@njit(cache=True, error_model="numpy")
def _newton_lanes(alpha, a4, rhs, tguess, x, act, st):
    """:func:`_newton` for every lane with ``act[j] == 2`` at once, the lanes' iterations interleaved (each
    lane's iterates are exactly those of :func:`_newton`); roots into ``x``, ``act[j]`` set to 3; lanes not
    converged get ``st[j] = NEWTON_FAILED``."""
    nl = x.shape[0]
    left = 0
    for j in range(nl):
        if act[j] == 2:
            x[j] = _newton_start(alpha[j], a4, rhs[j], tguess[j])
            left += 1
    for _ in range(_NEWTON_MAXIT):
        if left == 0:
            break
        for j in range(nl):
            if act[j] == 2:
                xj = x[j]
                x3 = xj * xj * xj
                f = alpha[j] * xj + a4 * x3 * xj - rhs[j]
                dx = f / (alpha[j] + 4.0 * a4 * x3)
                xj -= dx
                x[j] = xj
                if abs(dx) <= _NEWTON_RTOL * abs(xj) + 1e-300:
                    act[j] = 3
                    left -= 1
    for j in range(nl):
        if act[j] == 2:
            st[j] = NEWTON_FAILED
            act[j] = 3


@njit(cache=True, error_model="numpy")
def _newton(alpha, a4, rhs, tguess, st, j):
    """Positive root of alpha x + a4 x^4 = rhs (a4 > 0); sets st[j] = NEWTON_FAILED if not converged.

    f(x) = alpha x + a4 x^4 - rhs is increasing and convex for x > 0: Newton from a point right
    of the root decreases monotonically onto it; the root lies above min(rhs/alpha, (rhs/a4)^1/4).
    """
    x = _newton_start(alpha, a4, rhs, tguess)
    for _ in range(_NEWTON_MAXIT):
        x3 = x * x * x
        f = alpha * x + a4 * x3 * x - rhs
        dx = f / (alpha + 4.0 * a4 * x3)
        x -= dx
        if abs(dx) <= _NEWTON_RTOL * abs(x) + 1e-300:
            return x
    st[j] = NEWTON_FAILED
    return x


@njit(cache=True, error_model="numpy")
def _step(
    T,
    m,
    b0,
    b3,
    e0,
    e1,
    anyrock,
    ccoef,
    ctmin,
    rdz,
    es,
    G,
    scheme,
    dt,
    qa,
    qb,
    K,
    Cc,
    R,
    Tg,
    p,
    q,
    st,
    e_abs,
    e_emit,
    alt_add,
    alt_used,
    act,
):
    """One time step of a batch of columns (T: (nz, LANES)) in place; absorbed flux qa (LANES,)
    at the start, qb at the end. Adds the step's absorbed / emitted energy [J m-2] (with the
    scheme's quadrature) to e_abs, e_emit.

    scheme 0: backward Euler. scheme 1: TR-BDF2 (trapezoidal stage to t + gamma dt, then BDF2;
    L-stable and second order); properties at the start of the step for the first stage and,
    for the BDF2 stage (implicit at t + dt), at the end-of-step temperature predicted by linear
    extrapolation through T(t) and T(t + gamma dt) (floored at half the stage value). Against
    properties at the stage value this halves the settled night-time error on walls (measured).
    """
    nz, nl = T.shape
    n1 = nz - 1
    _props(T, m, b0, b3, e0, e1, anyrock, ccoef, ctmin, rdz, K, Cc)
    if scheme == SCHEME_BE:
        rtau = 1.0 / dt
        for i in range(nz):
            for j in range(nl):
                R[i, j] = Cc[i, j] * rtau * T[i, j]
        for j in range(nl):
            Tg[0, j] = T[0, j]
            R[0, j] += qb[j]
            R[n1, j] += G
        _solve(T, R, K, Cc, rtau, 1.0, es, Tg[0], p, q, st, alt_add[:0], alt_used, act)
        for j in range(nl):
            e_abs[j] += dt * qb[j]
            e_emit[j] += dt * es * T[0, j] ** 4
        return
    g = TRB_GAMMA
    # stage 1: trapezoidal rule over gamma dt
    rtau = 1.0 / (g * dt)
    for i in range(nz):
        for j in range(nl):
            R[i, j] = Cc[i, j] * rtau * T[i, j]
            Tg[i, j] = T[i, j]
    for l in range(nz - 1):
        for j in range(nl):
            fl = 0.5 * K[l, j] * (T[l + 1, j] - T[l, j])
            R[l, j] += fl
            R[l + 1, j] -= fl
    for j in range(nl):
        t0 = T[0, j]
        em0 = es * t0 * t0 * t0 * t0
        qg = qa[j] + g * (qb[j] - qa[j])
        R[0, j] += 0.5 * (qa[j] - em0) + 0.5 * qg
        R[n1, j] += G
        e_abs[j] += dt * (TRB_QW0 * (qa[j] + qg) + TRB_QW1 * qb[j])
        alt_add[j] = 0.5 * em0
    _solve(Tg, R, K, Cc, rtau, 0.5, 0.5 * es, T[0], p, q, st, alt_add, alt_used, act)
    for j in range(nl):
        tg = Tg[0, j]
        emg = es * tg * tg * tg * tg
        if alt_used[j]:
            e_emit[j] += dt * 2.0 * TRB_QW0 * emg
        else:
            e_emit[j] += dt * TRB_QW0 * (2.0 * alt_add[j] + emg)
    # stage 2: BDF2 from (T, Tg) over beta dt, properties at the predicted end temperature
    # (p is free scratch here: _solve overwrites it)
    xf = (1.0 - g) / g
    for i in range(nz):
        for j in range(nl):
            v = Tg[i, j] + xf * (Tg[i, j] - T[i, j])
            lo = 0.5 * Tg[i, j]
            p[i, j] = v if v > lo else lo
    _props(p, m, b0, b3, e0, e1, anyrock, ccoef, ctmin, rdz, K, Cc)
    rtau = 1.0 / (TRB_BETA * dt)
    for i in range(nz):
        for j in range(nl):
            R[i, j] = Cc[i, j] * rtau * (TRB_W1 * Tg[i, j] - TRB_W0 * T[i, j])
    for j in range(nl):
        R[0, j] += qb[j]
        R[n1, j] += G
    _solve(T, R, K, Cc, rtau, 1.0, es, Tg[0], p, q, st, alt_add[:0], alt_used, act)
    for j in range(nl):
        t1 = T[0, j]
        e_emit[j] += dt * es * TRB_QW1 * t1 * t1 * t1 * t1


#: Scratch of :func:`_refine`: (nz, nr) arrays (temperatures, 5 coefficients, 6 work arrays) and (nr,) vectors.
_REFINE_ARRAYS = 12
_REFINE_VECTORS = 8


@njit(cache=True, error_model="numpy")
def _refine(
    ridx,
    Tb,
    Ts,
    mb,
    b0b,
    b3b,
    e0b,
    e1b,
    anyrock,
    ccoef,
    ctmin,
    rdz,
    es,
    G,
    scheme,
    dt,
    qa,
    qb,
    st,
    st_s,
    e_abs,
    ea_s,
    e_emit,
    ee_s,
    a_h,
    nsteps,
    rbuf,
    r1,
    ri,
):
    """Redo one sub-step of the batch's lanes ``ridx`` in :data:`N_REFINE` equal parts, from their state
    before it (``Ts``, ``ea_s``, ``ee_s``, ``st_s``), gathered into one sub-batch of ``len(ridx)`` lanes
    (contiguous, so that the parts vectorise over the flagged lanes); results scattered back into ``Tb``,
    ``e_abs``, ``e_emit``, ``st``, ``a_h`` and ``nsteps``. ``rbuf``, ``r1``, ``ri``: scratch of at least
    :data:`_REFINE_ARRAYS` * nz * nr floats, (:data:`_REFINE_VECTORS`, nr) floats and (3, nr) ints."""
    nz = Tb.shape[0]
    nr = ridx.shape[0]
    nk = b0b.shape[0]  # link rows
    sz = nz * nr
    Tr = rbuf[0:sz].reshape((nz, nr))
    mr = rbuf[sz : 2 * sz].reshape((nz, nr))
    b0r = rbuf[2 * sz : 2 * sz + nk * nr].reshape((nk, nr))
    b3r = rbuf[3 * sz : 3 * sz + nk * nr].reshape((nk, nr))
    e0r = rbuf[4 * sz : 4 * sz + nk * nr].reshape((nk, nr))
    e1r = rbuf[5 * sz : 5 * sz + nk * nr].reshape((nk, nr))
    Kr = rbuf[6 * sz : 7 * sz].reshape((nz, nr))
    Cr = rbuf[7 * sz : 8 * sz].reshape((nz, nr))
    Rr = rbuf[8 * sz : 9 * sz].reshape((nz, nr))
    Tgr = rbuf[9 * sz : 10 * sz].reshape((nz, nr))
    pr = rbuf[10 * sz : 11 * sz].reshape((nz, nr))
    qr = rbuf[11 * sz : 12 * sz].reshape((nz, nr))
    q2a = r1[0, :nr]
    q2b = r1[1, :nr]
    ear = r1[2, :nr]
    eer = r1[3, :nr]
    aar = r1[4, :nr]
    hs = r1[5, :nr]
    str_ = ri[0, :nr]
    aur = ri[1, :nr]
    actr = ri[2, :nr]
    for c in range(nr):
        j = ridx[c]
        for i in range(nz):
            Tr[i, c] = Ts[i, j]
            mr[i, c] = mb[i, j]
        for i in range(nk):
            b0r[i, c] = b0b[i, j]
            b3r[i, c] = b3b[i, j]
            e0r[i, c] = e0b[i, j]
            e1r[i, c] = e1b[i, j]
        ear[c] = ea_s[j]
        eer[c] = ee_s[j]
        str_[c] = st_s[j]
        aur[c] = 0
        hs[c] = 0.0
    for r in range(N_REFINE):
        for c in range(nr):
            j = ridx[c]
            q2a[c] = qa[j] + (qb[j] - qa[j]) * (r / N_REFINE)
            q2b[c] = qa[j] + (qb[j] - qa[j]) * ((r + 1) / N_REFINE)
        _step(
            Tr,
            mr,
            b0r,
            b3r,
            e0r,
            e1r,
            anyrock,
            ccoef,
            ctmin,
            rdz,
            es,
            G,
            scheme,
            dt / N_REFINE,
            q2a,
            q2b,
            Kr,
            Cr,
            Rr,
            Tgr,
            pr,
            qr,
            str_,
            ear,
            eer,
            aar,
            aur,
            actr,
        )
        for c in range(nr):
            t0 = Tr[0, c]
            hs[c] += dt / N_REFINE * 4.0 * es * t0 * t0 * t0
    for c in range(nr):
        j = ridx[c]
        for i in range(nz):
            Tb[i, j] = Tr[i, c]
        e_abs[j] = ear[c]
        e_emit[j] = eer[c]
        st[j] = str_[c]
        a_h[j] += hs[c]
        nsteps[j] += N_REFINE


def interleave(a: np.ndarray) -> np.ndarray:
    """(ncol, k) per-column coefficients as (nb, k, LANES), C-contiguous, batch bi holding columns
    bi*LANES ... (the layout :func:`run_columns` reads); the last batch is padded with copies of the last
    column (never written back)."""
    ncol, k = a.shape
    nb = (ncol + LANES - 1) // LANES
    pad = np.empty((nb * LANES, k))
    pad[:ncol] = a
    pad[ncol:] = a[ncol - 1] if ncol else 0.0
    return np.ascontiguousarray(pad.reshape(nb, LANES, k).transpose(0, 2, 1))


@njit(cache=True, error_model="numpy")
def _run_batch(
    bi,
    T,
    m,
    b0,
    b3,
    e0,
    e1,
    rock,
    ccoef,
    ctmin,
    rdz,
    es,
    G,
    scheme,
    dt_max,
    adapt_K,
    times,
    absorbed,
    fidx,
    out,
    record,
    acc,
    status,
    fail_idx,
):
    """Advance columns bi*LANES ... (bi+1)*LANES-1 (see :func:`run_columns`)."""
    ncol, nz = T.shape
    nt = times.shape[0]
    c0 = bi * LANES
    nl = min(LANES, ncol - c0)
    Tb = np.empty((nz, nl))
    # the batch's coefficients, already interleaved (nz or nz-1, LANES): no copy per call
    sb = np.int64(bi) if m.shape[0] > 1 else np.int64(0)  # one batch of coefficients: every column alike
    mb = m[sb]
    b0b = b0[sb]
    b3b = b3[sb]
    e0b = e0[sb]
    e1b = e1[sb]
    anyrock = False
    for j in range(nl):
        if rock[c0 + j] != 0:
            anyrock = True
        for i in range(nz):
            Tb[i, j] = T[c0 + j, i]
    # work arrays: one allocation of each kind per batch (separate ones cost ~1/4 of a step at 16 lanes)
    w2 = np.empty((7, nz, nl))
    K = w2[0]  # (nz - 1 rows used)
    Cc = w2[1]
    R = w2[2]
    Tg = w2[3]
    p = w2[4]
    q = w2[5]
    Ts = w2[6]
    w1 = np.zeros((10, nl))
    qa = w1[0]
    qb = w1[1]
    alt_add = w1[2]
    ea_s = w1[3]
    ee_s = w1[4]
    e_abs = w1[5]
    e_emit = w1[6]
    a_h = w1[7]
    nsteps = w1[8]
    a_time = w1[9]
    wi = np.zeros((7, nl), np.int64)
    act = wi[5]
    ridx = wi[6]
    rbuf = np.empty(0)  # the adaptive refinement's scratch (made when first needed: see _refine)
    r1 = np.empty((0, 0))
    ri = np.empty((0, 0), np.int64)
    alt_used = wi[0]
    st_s = wi[1]
    refine = wi[2]
    st = wi[3]
    fail = wi[4]
    fail[:] = -1
    # the accumulators continue the columns' sums step after step (not a per-call sum added at the
    # end), so that they do not depend on how a series was cut into calls (a replay's time blocks)
    for j in range(nl):
        e_abs[j] = acc[c0 + j, 0]
        e_emit[j] = acc[c0 + j, 1]
        a_h[j] = acc[c0 + j, 2]
        a_time[j] = acc[c0 + j, 3]
        nsteps[j] = acc[c0 + j, 4]
    if record:
        for j in range(nl):
            out[0, c0 + j] = Tb[0, j]
    for k in range(nt - 1):
        span = times[k + 1] - times[k]
        nsub = int(np.ceil(span / dt_max - 1e-9))
        if nsub < 1:
            nsub = 1
        dt = span / nsub
        for s in range(nsub):
            for j in range(nl):
                fa = absorbed[k, fidx[c0 + j]]
                fb = absorbed[k + 1, fidx[c0 + j]]
                qa[j] = fa + (fb - fa) * (s / nsub)
                qb[j] = fa + (fb - fa) * ((s + 1) / nsub)
                if not (np.isfinite(fa) and np.isfinite(fb)) and st[j] == OK:
                    st[j] = NONFINITE
            adapt = adapt_K > 0.0 and scheme == SCHEME_TRBDF2
            if adapt:
                for i in range(nz):
                    for j in range(nl):
                        Ts[i, j] = Tb[i, j]
                for j in range(nl):
                    ea_s[j] = e_abs[j]
                    ee_s[j] = e_emit[j]
                    st_s[j] = st[j]
            _step(
                Tb,
                mb,
                b0b,
                b3b,
                e0b,
                e1b,
                anyrock,
                ccoef,
                ctmin,
                rdz,
                es,
                G,
                scheme,
                dt,
                qa,
                qb,
                K,
                Cc,
                R,
                Tg,
                p,
                q,
                st,
                e_abs,
                e_emit,
                alt_add,
                alt_used,
                act,
            )
            if adapt:
                # adaptive refinement, decided per column (so that a column's result never
                # depends on the other columns of its batch): where the surface curved strongly
                # within this sub-step (the kinks of sunrise / sunset), the sub-step is redone
                # in N_REFINE equal parts. Curvature indicator: the TR stage value against the
                # chord through the step's end points, ~ gamma (1 - gamma) dt^2 T'' / 2.
                for j in range(nl):
                    d = abs(Tg[0, j] - (Ts[0, j] + TRB_GAMMA * (Tb[0, j] - Ts[0, j])))
                    refine[j] = 1 if (d > adapt_K and st[j] == OK) else 0
            nr = 0
            for j in range(nl):
                if refine[j]:
                    ridx[nr] = j
                    nr += 1
                else:
                    t0 = Tb[0, j]
                    a_h[j] += dt * 4.0 * es * t0 * t0 * t0
                    nsteps[j] += 1
            if nr > 0:
                if rbuf.shape[0] == 0:  # the refinement's scratch, made at the batch's first refined sub-step
                    rbuf = np.empty(_REFINE_ARRAYS * nz * nl)
                    r1 = np.empty((_REFINE_VECTORS, nl))
                    ri = np.empty((3, nl), np.int64)
                # rewind the flagged columns and redo their sub-step together, gathered into a sub-batch
                # of nr lanes (each lane's arithmetic is the same as alone: no result depends on the batch)
                _refine(
                    ridx[:nr],
                    Tb,
                    Ts,
                    mb,
                    b0b,
                    b3b,
                    e0b,
                    e1b,
                    anyrock,
                    ccoef,
                    ctmin,
                    rdz,
                    es,
                    G,
                    scheme,
                    dt,
                    qa,
                    qb,
                    st,
                    st_s,
                    e_abs,
                    ea_s,
                    e_emit,
                    ee_s,
                    a_h,
                    nsteps,
                    rbuf,
                    r1,
                    ri,
                )
            for j in range(nl):
                a_time[j] += dt
        bad = False
        for j in range(nl):
            if st[j] == OK:
                for i in range(nz):
                    v = Tb[i, j]
                    if not (v > 0.0 and v < _T_MAX):
                        st[j] = NONFINITE
            if st[j] != OK:
                bad = True
                if fail[j] < 0:
                    fail[j] = k
        if bad:
            break
        if record:
            for j in range(nl):
                out[k + 1, c0 + j] = Tb[0, j]
    for j in range(nl):
        c = c0 + j
        if st[j] == OK:
            for i in range(nz):
                T[c, i] = Tb[i, j]
        status[c] = st[j]
        fail_idx[c] = fail[j]
        acc[c, 0] = e_abs[j]
        acc[c, 1] = e_emit[j]
        acc[c, 2] = a_h[j]
        acc[c, 3] = a_time[j]
        acc[c, 4] = nsteps[j]


@njit(parallel=True, cache=True, error_model="numpy")
def run_columns(
    T,
    m,
    b0,
    b3,
    e0,
    e1,
    rock,
    ccoef,
    ctmin,
    rdz,
    es,
    G,
    scheme,
    dt_max,
    adapt_K,
    times,
    absorbed,
    fidx,
    out,
    record,
    acc,
    status,
    fail_idx,
):
    """Advance every column through the forcing samples ``times``.

    Parameters
    ----------
    T : (ncol, nz) float64 [K], updated in place.
    m : (nb, nz, LANES) [kg m-2]; b0, b3, e0, e1 : (nb, nz-1, LANES): the columns' coefficients
    interleaved by batch of :data:`LANES` (:func:`interleave`; nb = ceil(ncol / LANES)), so that a
    call copies none of them; or (1, ., LANES), one batch read by every batch (columns alike);
    rock : (ncol,) uint8 (1: rock term).
    ccoef : (5,); ctmin [K]; rdz : (nz-1,) inverse link lengths [m-1]; es = eps sigma
    [W m-2 K-4]; G [W m-2]; scheme : SCHEME_BE or SCHEME_TRBDF2; dt_max [s];
    adapt_K [K]: local-error threshold (TR-BDF2 only; 0 disables). After each sub-step, a column
    whose surface curvature indicator |T_stage - chord through the step's end points|
    (~ gamma (1 - gamma) dt^2 T'' / 2) exceeds adapt_K has the sub-step redone in N_REFINE
    equal parts (error / 16). Decided per column: results never depend on the batch.
    times : (nt,) [s]; absorbed : (nt, nforce) [W m-2]; fidx : (ncol,) forcing column per column.
    out : (nt, ncol) surface temperatures at the samples (written when ``record``).
    acc : (ncol, N_ACC) accumulators (continued step by step). status, fail_idx : (ncol,) int64 outputs
    (status code, index of the forcing interval where the column failed or -1).
    """
    nb = (T.shape[0] + LANES - 1) // LANES
    for bi in prange(nb):
        _run_batch(
            bi,
            T,
            m,
            b0,
            b3,
            e0,
            e1,
            rock,
            ccoef,
            ctmin,
            rdz,
            es,
            G,
            scheme,
            dt_max,
            adapt_K,
            times,
            absorbed,
            fidx,
            out,
            record,
            acc,
            status,
            fail_idx,
        )


@njit(cache=True, error_model="numpy")
def run_columns_serial(
    T,
    m,
    b0,
    b3,
    e0,
    e1,
    rock,
    ccoef,
    ctmin,
    rdz,
    es,
    G,
    scheme,
    dt_max,
    adapt_K,
    times,
    absorbed,
    fidx,
    out,
    record,
    acc,
    status,
    fail_idx,
):
    """As :func:`run_columns` in the calling thread (no thread-pool start-up: for few columns,
    e.g. the per-step calls of a small coupled run on a busy machine)."""
    nb = (T.shape[0] + LANES - 1) // LANES
    for bi in range(nb):
        _run_batch(
            bi,
            T,
            m,
            b0,
            b3,
            e0,
            e1,
            rock,
            ccoef,
            ctmin,
            rdz,
            es,
            G,
            scheme,
            dt_max,
            adapt_K,
            times,
            absorbed,
            fidx,
            out,
            record,
            acc,
            status,
            fail_idx,
        )


@njit(parallel=True, cache=True, error_model="numpy")
def linear_sweeps(T, a, b, cc, h, Cd, nsteps, forcing):
    """Benchmark reference: ``nsteps`` backward-Euler steps of a *linear* constant-coefficient
    column (surface conductance ``h`` to a 0 K sink plus forcing), one plain Thomas sweep per step.

    T : (ncol, nz) in place; a, b, cc : (nz,) sub/main/super diagonals; Cd : (nz,) capacity/dt.
    """
    ncol, nz = T.shape
    for c in prange(ncol):
        cp = np.empty(nz)
        dp = np.empty(nz)
        Tc = T[c].copy()
        for _ in range(nsteps):
            bb = b[0] + h
            cp[0] = cc[0] / bb
            dp[0] = (Cd[0] * Tc[0] + forcing) / bb
            for i in range(1, nz):
                den = b[i] - a[i] * cp[i - 1]
                cp[i] = cc[i] / den
                dp[i] = (Cd[i] * Tc[i] - a[i] * dp[i - 1]) / den
            Tc[nz - 1] = dp[nz - 1]
            for i in range(nz - 2, -1, -1):
                Tc[i] = dp[i] - cp[i] * Tc[i + 1]
        T[c, :] = Tc
