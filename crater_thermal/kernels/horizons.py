"""Numba kernels for horizon maps: bisection of the horizon elevation and the per-step direct flux.

Only numpy and numba are imported; no I/O, no raising.  Angles are radians; azimuths are measured from
north (+y) clockwise toward east (+x), elevations from the crater frame's horizontal plane (z up), the
convention of :func:`crater_thermal.illumination.sun_direction_from_angles`.  See
:mod:`crater_thermal.horizons` for the method and its accuracy.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def bisection_directions(lo, hi, sin_az, cos_az, n_az, dirs):
    """Unit float32 directions at the mid-elevation of each bracket.

    Parameters
    ----------
    lo, hi : (n,) float64 [rad]
        Elevation brackets of rays ``i = facet * n_az + azimuth`` (blocked at ``lo``, free at ``hi``).
    sin_az, cos_az : (n_az,) float64
        Sine and cosine of the sampled azimuths.
    n_az : int
    dirs : (n, 3) float32, output
    """
    for i in range(lo.shape[0]):
        a = i % n_az
        e = 0.5 * (lo[i] + hi[i])
        ce = math.cos(e)
        dirs[i, 0] = ce * sin_az[a]
        dirs[i, 1] = ce * cos_az[a]
        dirs[i, 2] = math.sin(e)


@njit(cache=True, nogil=True)
def elevation_directions(el, sin_az, cos_az, dirs):
    """Unit float32 directions at elevations ``el`` [rad] and per-ray azimuths (their sine, cosine)."""
    for i in range(el.shape[0]):
        ce = math.cos(el[i])
        dirs[i, 0] = ce * sin_az[i]
        dirs[i, 1] = ce * cos_az[i]
        dirs[i, 2] = math.sin(el[i])


@njit(cache=True, nogil=True)
def bisection_update(lo, hi, hit):
    """Halve each bracket: the mid-elevation becomes ``lo`` where its ray was blocked, else ``hi``.

    ``hit`` is embreex's OCCLUDED result (int32: -1 free, anything else blocked).
    """
    for i in range(lo.shape[0]):
        e = 0.5 * (lo[i] + hi[i])
        if hit[i] != -1:
            lo[i] = e
        else:
            hi[i] = e


@njit(cache=True, nogil=True)
def _table_lookup(table, theta, dtheta):
    """Linear interpolation of ``table`` sampled at ``theta = k * dtheta``, k = 0..len-1."""
    u = theta / dtheta
    k = int(u)
    last = table.shape[0] - 1
    if k >= last:
        return table[last]
    w = u - k
    return (1.0 - w) * table[k] + w * table[k + 1]


@njit(cache=True, nogil=True)
def horizon_direct(horizon, sun_dirs, alpha, normals, frac_table, moment_table, out):
    """Direct flux factor per step and facet from a horizon map (multiply by ``S0 (1 au / r)^2``).

    For the Sun's azimuth ``phi`` and elevation ``E`` the facet's horizon is interpolated linearly
    between the two neighbouring sampled azimuths, ``H(phi) = H0 + H' (phi - phi0)``.  On the sky,
    with ``x = cos(E) dphi`` (along the horizontal unit vector ``e_az``) and ``y = dE`` (along
    ``e_el``), the horizon near the Sun is the line ``y = (H - E) + k x`` with ``k = H' / cos E``; the
    visible part of the disk lies on the side of its unit normal ``m = (-k, 1) / sqrt(1 + k^2)``, at
    signed distance ``d = (H - E) / sqrt(1 + k^2)`` from the disk centre, i.e. ``h = d / alpha`` disk
    radii.  The flux factor is then

        F(h) (n . s) + alpha G(h) (n . m3),   m3 = m_x e_az + m_y e_el,

    with ``F`` the visible fraction of the limb-darkened disk and ``G`` its first moment along ``m``
    [disk radii] (the cosine ``n . d`` is linear in the offset on the disk, so this integrates the
    incidence cosine over the visible segment exactly to first order in ``alpha``); clipped at 0.

    Parameters
    ----------
    horizon : (n_az, nf) float32 [rad]
        Horizon elevation at azimuths ``a * 2 pi / n_az``.
    sun_dirs : (nt, 3) float64 [unit]
    alpha : (nt,) float64 [rad]
        Angular radius of the Sun (0: a point Sun, lit where ``E > H``).
    normals : (nf, 3) float64 [unit]
    frac_table, moment_table : (m,) float64
        ``F`` and ``G`` sampled at ``theta = arccos(h) = k pi / (m - 1)``.
    out : (nt, nf) float64, output [-]
    """
    n_az = horizon.shape[0]
    nf = horizon.shape[1]
    dphi = 2.0 * math.pi / n_az
    dtheta = math.pi / (frac_table.shape[0] - 1)
    for t in range(sun_dirs.shape[0]):
        sx, sy, sz = sun_dirs[t, 0], sun_dirs[t, 1], sun_dirs[t, 2]
        el = math.asin(min(1.0, max(-1.0, sz)))
        ce = math.cos(el)
        phi = math.atan2(sx, sy)
        if phi < 0.0:
            phi += 2.0 * math.pi
        u = phi / dphi
        i0 = int(u)
        w = u - i0
        i0 = i0 % n_az
        i1 = (i0 + 1) % n_az
        # sky basis at the Sun: e_az horizontal (increasing azimuth), e_el (increasing elevation)
        sp, cp = math.sin(phi), math.cos(phi)
        ax, ay = cp, -sp
        se = math.sin(el)
        bx, by, bz = -se * sp, -se * cp, ce
        a = alpha[t]
        for f in range(nf):
            nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
            h0 = horizon[i0, f]
            h1 = horizon[i1, f]
            hz = (1.0 - w) * h0 + w * h1
            k = 0.0
            if ce > 1e-6:
                k = (h1 - h0) / (dphi * ce)
            norm = math.sqrt(1.0 + k * k)
            cosc = nx * sx + ny * sy + nz * sz
            if a <= 0.0:  # point Sun: lit when above the horizon
                out[t, f] = cosc if (el > hz and cosc > 0.0) else 0.0
                continue
            h = (hz - el) / (norm * a)
            if h >= 1.0:
                out[t, f] = 0.0
                continue
            if h <= -1.0:
                out[t, f] = cosc if cosc > 0.0 else 0.0
                continue
            theta = math.acos(h)
            frac = _table_lookup(frac_table, theta, dtheta)
            mom = _table_lookup(moment_table, theta, dtheta)
            mx, my = -k / norm, 1.0 / norm
            nm = mx * (nx * ax + ny * ay) + my * (nx * bx + ny * by + nz * bz)
            val = frac * cosc + a * mom * nm
            out[t, f] = val if val > 0.0 else 0.0


@njit(cache=True, nogil=True)
def segment_tables(coeffs, beta, n):
    """Visible fraction ``F`` and first moment ``G`` of a limb-darkened disk above the chord ``y = cos(theta)``.

    With ``I(mu) = sum_k c_k mu^k`` and ``mu = sqrt(1 - x^2 - y^2)`` (disk radius 1), the intensity
    integrated along the chord at height ``y`` is ``sum_k c_k beta_k (1 - y^2)^((k+1)/2)`` with
    ``beta_k = int_{-1}^{1} (1 - t^2)^(k/2) dt``.  Substituting ``y = cos t``:

        int_{y>cos(theta)} I dA   = sum_k c_k beta_k S_{k+2}(theta),   S_n(theta) = int_0^theta sin^n t dt,
        int_{y>cos(theta)} y I dA = sum_k c_k beta_k sin(theta)^(k+3) / (k + 3),

    and ``S_n`` follows from ``S_0 = theta``, ``S_1 = 1 - cos(theta)`` and
    ``S_n = -sin^(n-1) cos / n + (n-1)/n S_(n-2)``: closed form, exact to rounding.

    Parameters
    ----------
    coeffs, beta : (K,) float64
    n : int
        Number of samples, ``theta = j pi / (n - 1)``.

    Returns
    -------
    frac, moment : (n,) float64
        Divided by the disk total ``sum_k c_k beta_k S_{k+2}(pi)``.
    """
    K = coeffs.shape[0]
    frac = np.zeros(n)
    mom = np.zeros(n)
    total = 0.0
    for j in range(n):
        th = math.pi * j / (n - 1)
        s, c = math.sin(th), math.cos(th)
        if j == n - 1:
            s, c = 0.0, -1.0
        # S_n for n = 0 .. K + 1
        S = np.zeros(K + 2)
        S[0] = th
        S[1] = 1.0 - c
        for m in range(2, K + 2):
            S[m] = -(s ** (m - 1)) * c / m + (m - 1) / m * S[m - 2]
        a = 0.0
        g = 0.0
        for k in range(K):
            a += coeffs[k] * beta[k] * S[k + 2]
            g += coeffs[k] * beta[k] * s ** (k + 3) / (k + 3)
        frac[j] = a
        mom[j] = g
        if j == n - 1:
            total = a
    for j in range(n):
        frac[j] /= total
        mom[j] /= total
    return frac, mom
