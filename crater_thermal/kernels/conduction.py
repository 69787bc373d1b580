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

Time stepping: the theta method (``theta = 1``: backward Euler, the default; L-stable, which
matters because rock columns have kappa dt / dz^2 ~ 1e3 at the surface), properties
(k, c) lagged to the start of each sub-step, the nonlinear surface emission ``eps sigma T^4``
treated implicitly (weight theta) and solved exactly by a scalar Newton iteration after
eliminating the tridiagonal system from the bottom up (Thomas algorithm run bottom-to-top, so
that the only unknown left is the surface temperature). The absorbed flux is linear in time
between samples; the geothermal flux ``G`` enters the bottom half cell.
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


@njit(cache=True, inline="always")
def _cpoly(T, ccoef, ctmin):
    x = T if T > ctmin else ctmin
    return ccoef[0] + x * (ccoef[1] + x * (ccoef[2] + x * (ccoef[3] + x * ccoef[4])))


@njit(cache=True)
def _props(T, m, b0, b3, e0, e1, rock, ccoef, ctmin, rdz, K, Cc):
    """Link conductances K [W m-2 K-1] and node heat capacities Cc = m c [J m-2 K-1] at T."""
    nz = T.shape[0]
    for l in range(nz - 1):
        tl = 0.5 * (T[l] + T[l + 1])
        k = b0[l] + b3[l] * tl * tl * tl
        if rock:
            k += _cpoly(tl, ccoef, ctmin) * (e0[l] + e1[l] / tl)
        K[l] = k * rdz[l]
    for i in range(nz):
        Cc[i] = m[i] * _cpoly(T[i], ccoef, ctmin)


@njit(cache=True)
def _solve(X, R, K, Cc, rtau, theta, a4, tguess, p, q):
    """Solve (Cc/tau + theta L) X + theta es X0^4 e_0 = R for X (in place), L the conduction
    operator with conductances K (no-flux ends; boundary fluxes are in R).

    Elimination runs bottom-up (X[i] = p[i] + q[i] X[i-1]) leaving the scalar surface equation
    alpha x + a4 x^4 = rhs, solved by Newton. Returns a status code.
    """
    nz = X.shape[0]
    n1 = nz - 1
    kb = theta * K[n1 - 1]
    b = Cc[n1] * rtau + kb
    p[n1] = R[n1] / b
    q[n1] = kb / b
    for i in range(n1 - 1, 0, -1):
        ku = theta * K[i - 1]
        kd = theta * K[i]
        den = Cc[i] * rtau + ku + kd * (1.0 - q[i + 1])
        p[i] = (R[i] + kd * p[i + 1]) / den
        q[i] = ku / den
    k0 = theta * K[0]
    alpha = Cc[0] * rtau + k0 * (1.0 - q[1])
    rhs = R[0] + k0 * p[1]
    status = OK
    if a4 == 0.0:
        x = rhs / alpha
    else:
        # f(x) = alpha x + a4 x^4 - rhs is increasing and convex for x > 0: Newton from a point
        # right of the root decreases monotonically onto it.
        x = tguess
        xl = rhs / alpha
        xr = (rhs / a4) ** 0.25 if rhs > 0.0 else 0.0
        if xr < xl:
            xl = xr
        if x < xl:
            x = xl
        if not (x > 0.0):
            x = 1.0
        conv = False
        for _ in range(_NEWTON_MAXIT):
            x3 = x * x * x
            f = alpha * x + a4 * x3 * x - rhs
            dx = f / (alpha + 4.0 * a4 * x3)
            x -= dx
            if abs(dx) <= _NEWTON_RTOL * abs(x) + 1e-300:
                conv = True
                break
        if not conv:
            status = NEWTON_FAILED
    if not (x > 0.0 and x < _T_MAX):
        return NONFINITE
    X[0] = x
    for i in range(1, nz):
        v = p[i] + q[i] * X[i - 1]
        if not (v > 0.0 and v < _T_MAX):
            return NONFINITE
        X[i] = v
    return status


#: TR-BDF2 constants (Bank et al. 1985; Hosea & Shampine 1996): gamma = 2 - sqrt(2)
TRB_GAMMA = 2.0 - np.sqrt(2.0)
TRB_W1 = 1.0 / (TRB_GAMMA * (2.0 - TRB_GAMMA))
TRB_W0 = (1.0 - TRB_GAMMA) ** 2 / (TRB_GAMMA * (2.0 - TRB_GAMMA))
TRB_BETA = (1.0 - TRB_GAMMA) / (2.0 - TRB_GAMMA)
#: quadrature weights of f(t_n), f(t_n + gamma dt), f(t_n+1) implied by the scheme
TRB_QW = (1.0 / (2.0 * (2.0 - TRB_GAMMA)), 1.0 / (2.0 * (2.0 - TRB_GAMMA)), TRB_BETA)

SCHEME_BE = 0
SCHEME_TRBDF2 = 1


@njit(cache=True)
def _column_step(T, m, b0, b3, e0, e1, rock, ccoef, ctmin, rdz, es, G, scheme, dt, qa, qb,
                 K, Cc, R, Tg, p, q):
    """One time step of one column in place (absorbed flux qa at the start, qb at the end).

    scheme 0: backward Euler. scheme 1: TR-BDF2 (trapezoidal stage to t + gamma dt, then BDF2;
    L-stable and second order); properties at the start of the step for the first stage and at
    the stage temperature for the second.
    Returns (status, absorbed energy, emitted energy) over the step [J m-2].
    """
    nz = T.shape[0]
    n1 = nz - 1
    t0 = T[0]
    _props(T, m, b0, b3, e0, e1, rock, ccoef, ctmin, rdz, K, Cc)
    if scheme == SCHEME_BE:
        rtau = 1.0 / dt
        for i in range(nz):
            R[i] = Cc[i] * rtau * T[i]
            Tg[i] = T[i]
        R[0] += qb
        R[n1] += G
        st = _solve(T, R, K, Cc, rtau, 1.0, es, t0, p, q)
        return st, dt * qb, dt * es * T[0] ** 4
    g = TRB_GAMMA
    qg = qa + g * (qb - qa)
    # stage 1: trapezoidal rule over gamma dt
    rtau = 1.0 / (g * dt)
    for i in range(nz):
        R[i] = Cc[i] * rtau * T[i]
    for l in range(nz - 1):
        fl = 0.5 * K[l] * (T[l + 1] - T[l])
        R[l] += fl
        R[l + 1] -= fl
    em0 = es * t0 * t0 * t0 * t0
    R[0] += 0.5 * (qa - em0) + 0.5 * qg
    R[n1] += G
    for i in range(nz):
        Tg[i] = T[i]
    st = _solve(Tg, R, K, Cc, rtau, 0.5, 0.5 * es, t0, p, q)
    if st != OK:
        return st, 0.0, 0.0
    emg = es * Tg[0] ** 4
    # stage 2: BDF2 from (T, Tg) over beta dt, properties at the stage temperature
    _props(Tg, m, b0, b3, e0, e1, rock, ccoef, ctmin, rdz, K, Cc)
    rtau = 1.0 / (TRB_BETA * dt)
    for i in range(nz):
        R[i] = Cc[i] * rtau * (TRB_W1 * Tg[i] - TRB_W0 * T[i])
    R[0] += qb
    R[n1] += G
    st = _solve(T, R, K, Cc, rtau, 1.0, es, Tg[0], p, q)
    em1 = es * T[0] ** 4
    e_abs = dt * (TRB_QW[0] * qa + TRB_QW[1] * qg + TRB_QW[2] * qb)
    e_emit = dt * (TRB_QW[0] * em0 + TRB_QW[1] * emg + TRB_QW[2] * em1)
    return st, e_abs, e_emit


@njit(parallel=True, cache=True)
def run_columns(T, m, b0, b3, e0, e1, rock, ccoef, ctmin, rdz, es, G, scheme, dt_max,
                times, absorbed, fidx, out, record, acc, status, fail_idx):
    """Advance every column through the forcing samples ``times``.

    Parameters
    ----------
    T : (ncol, nz) float64 [K], updated in place.
    m : (ncol, nz) [kg m-2]; b0, b3, e0, e1 : (ncol, nz-1); rock : (ncol,) uint8 (1: rock term).
    ccoef : (5,); ctmin [K]; rdz : (nz-1,) inverse link lengths [m-1]; es = eps sigma
    [W m-2 K-4]; G [W m-2]; scheme : SCHEME_BE or SCHEME_TRBDF2; dt_max [s].
    times : (nt,) [s]; absorbed : (nt, nforce) [W m-2]; fidx : (ncol,) forcing column per column.
    out : (nt, ncol) surface temperatures at the samples (written when ``record``).
    acc : (ncol, N_ACC) accumulators (added to). status, fail_idx : (ncol,) int64 outputs.
    """
    ncol, nz = T.shape
    nt = times.shape[0]
    for c in prange(ncol):
        K = np.empty(nz - 1)
        Cc = np.empty(nz)
        R = np.empty(nz)
        Tg = np.empty(nz)
        p = np.empty(nz)
        q = np.empty(nz)
        Tc = T[c].copy()
        f = fidx[c]
        isrock = rock[c] != 0
        a_abs = 0.0
        a_emit = 0.0
        a_h = 0.0
        a_time = 0.0
        nsteps = 0
        st = OK
        fail = -1
        if record:
            out[0, c] = Tc[0]
        for k in range(nt - 1):
            span = times[k + 1] - times[k]
            qa = absorbed[k, f]
            qb = absorbed[k + 1, f]
            if not (np.isfinite(qa) and np.isfinite(qb)):
                st = NONFINITE
                fail = k
                break
            nsub = int(np.ceil(span / dt_max - 1e-9))
            if nsub < 1:
                nsub = 1
            dt = span / nsub
            for s in range(nsub):
                q_old = qa + (qb - qa) * (s / nsub)
                q_new = qa + (qb - qa) * ((s + 1) / nsub)
                st, e_abs, e_emit = _column_step(Tc, m[c], b0[c], b3[c], e0[c], e1[c], isrock, ccoef,
                                                 ctmin, rdz, es, G, scheme, dt, q_old, q_new,
                                                 K, Cc, R, Tg, p, q)
                if st != OK:
                    break
                tn = Tc[0]
                a_abs += e_abs
                a_emit += e_emit
                a_h += dt * 4.0 * es * tn * tn * tn
                a_time += dt
                nsteps += 1
            if st != OK:
                fail = k
                break
            if record:
                out[k + 1, c] = Tc[0]
        T[c, :] = Tc
        status[c] = st
        fail_idx[c] = fail
        acc[c, 0] += a_abs
        acc[c, 1] += a_emit
        acc[c, 2] += a_h
        acc[c, 3] += a_time
        acc[c, 4] += nsteps


@njit(parallel=True, cache=True)
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
        for s in range(nsteps):
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
