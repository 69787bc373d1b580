"""Thermal instruments and detection statistics: can a radiometer tell loose from nominal regolith?

Arrays in, arrays out (numpy/scipy only). Units: SI inside; band edges in um and temperatures in K
at the edges, as the names say.

Band radiance and band brightness temperature
---------------------------------------------
A radiometer channel with a flat response between ``lo_um`` and ``hi_um`` measures the band radiance
``L(T) = integral B_lambda(lambda, T) d lambda`` [W m-2 sr-1]. With x = h c / (lambda k T),
``L = C T^4 (F(x2) - F(x1))``, C = 2 k^4 / (h^3 c^2), F(x) = integral_0^x u^3 / (e^u - 1) du,
x1 = x(hi), x2 = x(lo). F is evaluated to double precision by two series (no quadrature grid):
the Bernoulli power series for x < 2 and the exponential series
``integral_x^inf = sum_k e^{-kx} (x^3/k + 3x^2/k^2 + 6x/k^3 + 6/k^4)`` for x >= 2.
A band (0, inf) gives ``L = sigma T^4 / pi``: footprint mixing in band radiance then reduces exactly
to thesis Eq. 8.2 (bolometric T^4 mixing), which is this module's special case
:data:`BOLOMETRIC`. Emissivity is 1 (as Eq. 8.2), so brightness temperature = temperature.

Detection statistics (one criterion)
------------------------------------
**The observation.** A candidate patch of ``k`` footprints, each a fraction ``C`` loose regolith (the
rest nominal, mixed in band radiance: brightness temperature ``T_c``), against ``m`` reference
footprints of nominal regolith (``T_n``). A patch of area ``A`` seen with footprints of area ``a``
gives ``k = max(1, floor(A / a))`` whole footprints, and for ``A < a`` one footprint with
``C = A / a`` (:class:`Observation`). Each footprint is observed in one of two modes:

* **stare** (a rover or lander): a dwell ``t`` [s] on each footprint, ``n = floor(t / t_int)``
  samples of one integration ``t_int``;
* **passes** (an orbiting pushbroom such as Diviner): ``P`` overflights, each integrating the
  footprint for ``t_pass`` [s] (Diviner 0.128 s, one integration), so ``n = P floor(t_pass / t_int)``
  samples. "6.7 s" of Diviner data on one footprint is about 52 overflights.

Exposures are given in the mode's unit, dwell [s] or passes [-] (:func:`exposure_unit`);
:func:`exposure_seconds` gives the total time on each footprint [s] in either mode.

**The noise model** (what :func:`detection_probability` states and the tests' independent Monte Carlo
draws). Per comparison and footprint ``i`` with scene temperature ``T_i`` (``T_c`` or ``T_n``):

1. **Natural scatter**: the footprint's true brightness temperature is ``T_i + s z_i``,
   ``z_i ~ N(0, 1)`` per footprint, shared by all its samples and passes (it does not average with
   exposure). Default ``s`` 0.94 K: the thesis (7.2/7.3, refs [16, 112]) quotes it as the standard
   deviation of rock-free lunar regolith temperatures; by the thesis's context ref. [16] is Bandfield et
   al. 2011 (JGR 116, E00H02), Diviner night-time temperatures of the regolith fines between 60 N and
   60 S (scenes of roughly 70-120 K, footprints of ~250 m); the paper itself was not read here. At 40-80 K
   inside polar craters it has not been measured; what sets temperatures there (scattered and re-emitted
   light, geothermal flux) differs from the equatorial night, so take it as uncertain by a factor of
   about 2 either way (the report shows the answer at 0.5x and 2x).
2. **Calibration gain**: the instrument reports the band radiance ``(1 + g) L`` with one relative gain
   error ``g ~ N(0, gain_error)`` per comparison, common to all its footprints and passes (a systematic
   error of the radiometric scale; it does not average), and the footprint's brightness temperature
   is inverted from that radiance: ``T_b((1 + g) L(T_i + s z_i))``.
3. **White instrument noise**: each sample adds ``NETD(T_i) w``, ``w ~ N(0, 1)`` independent per
   sample, with ``NETD(T) = NETD_ref L'(T_ref) / L'(T)`` (L' = dL/dT of the band): a
   detector-noise-limited radiometer has a scene-independent noise-equivalent radiance (thermopiles,
   microbolometers), so its NETD grows as the band's dB/dT falls at cold scenes. The footprint's
   reading is the mean of its samples.
4. **Averaging floor** (1/f noise and drift; the minimum of the Allan deviation): one offset
   ``NETD(T_i) sqrt(t_int / knee_s) f``, ``f ~ N(0, 1)``, per footprint in a stare and per footprint
   and pass with passes (overflights hours apart are calibrated anew), added to every sample of it.
   The instrument variance of one footprint is therefore ``NETD^2 (1/n + t_int / knee_s)`` in a stare
   (the white part falls until the dwell reaches the knee, the floor ``NETD sqrt(t_int/knee_s)``
   remains) and ``NETD^2 (1/n + t_int / (knee_s P))`` with passes.

The statistic is ``D = mean_k(T_b,cand) - mean_m(T_b,ref)`` [K], with expectation ``mu = T_c - T_n``.
Its variance is the sum of (:func:`noise_terms`, variances in K^2)

* ``instrument_white`` ``NETD(T_c)^2 / (n k) + NETD(T_n)^2 / (n m)``,
* ``allan_floor`` ``(NETD(T_c)^2 / k + NETD(T_n)^2 / m) t_int / knee_s`` (``/ P`` with passes),
* ``natural_scatter`` ``s^2 (1/k + 1/m)``,
* ``gain_error`` ``(gain_error (h(T_c) - h(T_n)))^2`` with ``h = L / L'`` [K] (derivation below).

**Gain error on band radiances.** With ``L_hat = (1 + g) L`` the inferred temperature is
``T_hat = T_b((1 + g) L(T))``; to first order in ``g``, ``L(T_hat) = L(T) + L'(T) (T_hat - T)``, so
``T_hat = T + g L(T) / L'(T) = T + g h(T)``. The difference of two footprints then reads
``D_hat = mu + g (h(T_c) - h(T_n))``, and for ``|mu|`` small against the scale on which ``h`` bends,
``D_hat = mu (1 + g dh/dT)`` with ``dh/dT = d(L/L')/dT = 1 - L L'' / L'^2``. The code keeps the
difference ``h(T_c) - h(T_n)`` (exact to first order in ``g`` for any ``mu``). ``dh/dT`` is 1 in the
Rayleigh-Jeans limit (L proportional to T: the former model's ``g mu``, a gain acting on the
temperature difference), 1/4 for the whole spectrum (L proportional to T^4: h = T / 4) and about
``2 / x`` on the Wien side (x = h c / (lambda k T) >> 1). At 58 K: 0.10 (microbolometer, 7.5-14 um),
0.26 (Diviner ch. 7), 0.48 (ch. 8), 0.74 (ch. 9). Under the null hypothesis ``T_c = T_n``, the term
vanishes. A common radiance offset ``o`` cancels in the radiance difference, but not quite in the
temperature difference: ``D_hat = mu + o (1/L'(T_c) - 1/L'(T_n))``, a relative error
``-o L'' / L'^2`` of ``mu``. It is not modelled here; an offset of 5 K at a 50 K scene (Diviner's
absolute accuracy there, thesis 7.3) would make it about 0.05 of ``mu`` in ch. 9 and 0.5 in ch. 7
at 58 K.

**The test** is one-sided in the direction of the expected difference (loose regolith is colder at
night, warmer by day): declare "different" when ``sign(mu) D > z_{1-a} sigma_0``, with ``a`` the
false-alarm rate (default 1%). The threshold comes from the null hypothesis, "no loose regolith":
every footprint, candidate and references, at the nominal temperature ``T_n``, so ``sigma_0`` is the
standard deviation above with ``T_c = T_n`` (NETD(T_n) for both scenes, no gain term;
:func:`sigma_null`, :func:`detection_threshold`). Under the alternative the candidate is at ``T_c``
(its NETD there, and the gain term): ``sigma_1``. Then
``P_D = Phi((|mu| - z_{1-a} sigma_0) / sigma_1)``, and ``P_D -> a`` as ``mu -> 0``.
P_D increases with the exposure, with ``k`` and with ``m`` wherever ``P_D >= 1/2``; below 1/2 a
candidate noisier than the references (colder, on the Wien side of its band) can lose P_D with
averaging, since a noisier alternative crosses a fixed threshold more often. :func:`dwell_for_detection`
gives the shortest exposure with ``P_D >= 0.9`` (the set where it holds is one interval from infinite
exposure down) or, when even infinite exposure (white noise gone; in a stare the floor remains) cannot
reach it, "not detectable" and the term that limits.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Optional

import numpy as np
import scipy.constants as _sc
from scipy.special import bernoulli, ndtr, ndtri

from crater_thermal.errors import ConfigError

H_PLANCK = _sc.h
C_LIGHT = _sc.c
K_BOLTZMANN = _sc.k
#: 2 k^4 / (h^3 c^2) [W m-2 sr-1 K-4]: band radiance = this x T^4 x the dimensionless Planck integral
_C_BAND = 2.0 * K_BOLTZMANN**4 / (H_PLANCK**3 * C_LIGHT**2)
#: h c / k [m K]
_HC_K = H_PLANCK * C_LIGHT / K_BOLTZMANN
#: integral_0^inf u^3 / (e^u - 1) du
_PI4_15 = math.pi**4 / 15.0
_X_SPLIT = 2.0
_N_BERN = 40
_BERN = bernoulli(_N_BERN)
_N_EXP = 40

#: Natural scatter of rock-free regolith temperatures [K] (thesis 7.3; Bandfield et al. 2011, see above)
NATURAL_SCATTER_K = 0.94
#: Default false-alarm rate of the one-sided test [-]
FALSE_ALARM = 0.01
#: Detection probability the dwell time is computed for [-]
TARGET_PD = 0.9


# ------------------------------------------------------------------------------------ Planck


def _power_coefficients() -> np.ndarray:
    """c_j with integral_0^x u^3/(e^u - 1) du = x^3 sum_j c_j x^j (c_n = B_n / ((n + 3) n!))."""
    c = np.zeros(_N_BERN + 1)
    fact = 1.0
    for n in range(_N_BERN + 1):
        fact *= max(n, 1)
        c[n] = _BERN[n] / ((n + 3) * fact)
    return c


_POWER_C = _power_coefficients()
_KS = np.arange(1, _N_EXP + 1, dtype=float)


def _power_series(x: np.ndarray) -> np.ndarray:
    """integral_0^x u^3/(e^u - 1) du for 0 <= x <= 2 (Bernoulli series, converges for x < 2 pi)."""
    return x**3 * np.polynomial.polynomial.polyval(x, _POWER_C)


def _tail_series(x: np.ndarray) -> np.ndarray:
    """integral_x^inf u^3/(e^u - 1) du for x >= 2 (exponential series; 40 terms: e^-80 < 1e-34)."""
    xk = x[..., None] * _KS
    with np.errstate(under="ignore"):
        e = np.exp(-xk)
    return np.sum(e * (((xk + 3) * xk + 6) * xk + 6) / _KS**4, axis=-1)


def planck_integral(x1, x2) -> np.ndarray:
    """integral_{x1}^{x2} u^3 / (e^u - 1) du [-] for 0 <= x1 <= x2 <= inf, to double precision.

    Differences are formed between quantities of the same size (both from the power series below
    x = 2, both tails above), so narrow bands lose only the digits the band's width implies.
    """
    x1, x2 = np.broadcast_arrays(np.asarray(x1, float), np.asarray(x2, float))
    lo = np.minimum(x1, _X_SPLIT)
    hi = np.minimum(x2, _X_SPLIT)
    low_part = _power_series(hi) - _power_series(lo)  # the part of [x1, x2] below 2
    a = np.maximum(x1, _X_SPLIT)
    b = np.maximum(x2, _X_SPLIT)
    fin_b = np.isfinite(b)
    tail_b = np.zeros_like(b)
    tail_b[fin_b] = _tail_series(b[fin_b])
    fin_a = np.isfinite(a)
    tail_a = np.zeros_like(a)
    tail_a[fin_a] = _tail_series(a[fin_a])
    return low_part + (tail_a - tail_b)  # the part above 2


def planck_dB_dT(wavelength_m, T_K) -> np.ndarray:
    """Temperature derivative of the Planck spectral radiance B_lambda.

    Parameters
    ----------
    wavelength_m : array [m]
    T_K : array [K] (broadcast with ``wavelength_m``), > 0

    Returns
    -------
    dB_lambda/dT [W m-2 sr-1 m-1 K-1] = (2 h c^2 / lambda^5) (x / T) e^-x / (1 - e^-x)^2, x = h c / (lambda k T)
    """
    lam = np.asarray(wavelength_m, float)
    T = np.asarray(T_K, float)
    x = _HC_K / (lam * T)
    with np.errstate(over="ignore", under="ignore"):
        em = np.exp(-x)
        return 2 * H_PLANCK * C_LIGHT**2 / lam**5 * (x / T) * em / (-np.expm1(-x)) ** 2


@dataclass(frozen=True)
class Band:
    """A flat spectral band [um]; ``Band(0, inf)`` is the whole spectrum (bolometric)."""

    lo_um: float
    hi_um: float

    def __post_init__(self):
        if not (self.lo_um >= 0 and self.hi_um > self.lo_um and not math.isnan(self.hi_um)):
            raise ConfigError(f"band ({self.lo_um}, {self.hi_um}) um must satisfy 0 <= low < high")

    def x_edges(self, T_K) -> tuple[np.ndarray, np.ndarray]:
        """(x1, x2) = h c / (lambda k T) at the long- and short-wavelength edges [-]."""
        T = np.asarray(T_K, float)
        x1 = np.zeros_like(T) if math.isinf(self.hi_um) else _HC_K / (self.hi_um * 1e-6 * T)
        with np.errstate(divide="ignore"):
            x2 = np.full_like(T, np.inf) if self.lo_um == 0 else _HC_K / (self.lo_um * 1e-6 * T)
        return x1, x2

    def label(self) -> str:
        return "bolometric" if self.lo_um == 0 and math.isinf(self.hi_um) else f"{self.lo_um:g}-{self.hi_um:g} um"


#: The whole spectrum: band-radiance mixing here is thesis Eq. 8.2
BOLOMETRIC = Band(0.0, math.inf)


def _check_T(T_K) -> np.ndarray:
    T = np.asarray(T_K, float)
    if np.any(~np.isfinite(T)) or np.any(T <= 0):
        raise ConfigError(f"temperatures must be finite and > 0 K, got min {np.nanmin(T) if T.size else T}")
    return T


def band_radiance(T_K, band: Band) -> np.ndarray:
    """Band radiance L(T) [W m-2 sr-1] of a blackbody at ``T_K`` [K] (exact series, see module doc)."""
    T = _check_T(T_K)
    x1, x2 = band.x_edges(T)
    return _radiance(T, planck_integral(x1, x2))


def band_radiance_derivative(T_K, band: Band) -> np.ndarray:
    """dL/dT [W m-2 sr-1 K-1] = C T^3 (4 I - x2 f(x2) + x1 f(x1)), f(x) = x^3/(e^x - 1), exact."""
    T = _check_T(T_K)
    x1, x2 = band.x_edges(T)
    return _derivative(T, x1, x2, planck_integral(x1, x2))


def band_radiance_and_derivative(T_K, band: Band) -> tuple[np.ndarray, np.ndarray]:
    """Band radiance and its temperature derivative at ``T_K`` [K] from one evaluation of the Planck integral.

    Returns
    -------
    L : array [W m-2 sr-1]           :func:`band_radiance`.
    dL_dT : array [W m-2 sr-1 K-1]   :func:`band_radiance_derivative` (the same numbers as the two calls).
    """
    T = _check_T(T_K)
    x1, x2 = band.x_edges(T)
    integral = planck_integral(x1, x2)
    return _radiance(T, integral), _derivative(T, x1, x2, integral)


def _radiance(T, integral):
    return _C_BAND * T**4 * integral


def _derivative(T, x1, x2, integral):
    def xf(x):
        out = np.zeros_like(x)
        ok = np.isfinite(x) & (x > 0)
        with np.errstate(over="ignore", under="ignore"):
            out[ok] = x[ok] ** 4 / np.expm1(x[ok])
        return out

    return _C_BAND * T**3 * (4 * integral - xf(x2) + xf(x1))


def band_brightness_temperature(
    L, band: Band, bracket_K: tuple[float, float] = (1.0, 2000.0), rtol: float = 1e-13
) -> np.ndarray:
    """Invert :func:`band_radiance`: the temperature [K] whose band radiance is ``L`` [W m-2 sr-1].

    Safeguarded Newton on log L (bisection when a step leaves the bracket). Raises
    :class:`ConfigError` when ``L`` lies outside the bracket's radiances.
    """
    L = np.asarray(L, float)
    lo = np.full(L.shape, float(bracket_K[0]))
    hi = np.full(L.shape, float(bracket_K[1]))
    return _invert(L, band, lo, hi, rtol)


def _invert(L, band, lo, hi, rtol):
    L, lo, hi = np.broadcast_arrays(np.asarray(L, float), lo, hi)
    lo, hi = lo.astype(float).copy(), hi.astype(float).copy()
    if np.any(~(L > 0)):
        raise ConfigError("band radiance must be > 0 to invert to a brightness temperature")
    Llo, Lhi = band_radiance(lo, band), band_radiance(hi, band)
    if np.any(L < Llo * (1 - 1e-12)) or np.any(L > Lhi * (1 + 1e-12)):
        raise ConfigError(
            f"band radiance outside the range of the bracket {float(lo.min()):g}-{float(hi.max()):g} K "
            f"in band {band.label()}"
        )
    lo0, hi0 = lo.copy(), hi.copy()
    at_lo, at_hi = L <= Llo, L >= Lhi  # the answer is an end of the bracket (e.g. a fraction of 0 or 1)
    T = np.where(hi > lo, 0.5 * (lo + hi), lo)
    logL = np.log(L)
    for _ in range(200):
        Lt, dLt = band_radiance_and_derivative(T, band)  # one Planck integral for both
        g = np.log(Lt) - logL
        lo = np.where(g < 0, T, lo)
        hi = np.where(g > 0, T, hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = g / (dLt / Lt)
        Tn = T - step
        bad = ~np.isfinite(Tn) | (Tn <= lo) | (Tn >= hi)
        Tn = np.where(bad, 0.5 * (lo + hi), Tn)
        done = np.abs(Tn - T) <= rtol * T
        T = Tn
        if np.all(done | (hi - lo <= rtol * T) | at_lo | at_hi):
            break
    return np.where(at_lo, lo0, np.where(at_hi, hi0, T))


def mixed_band_temperature(T_a_K, T_b_K, fraction_a, band: Band = BOLOMETRIC) -> np.ndarray:
    """Brightness temperature [K] of a footprint mixing two surfaces, in the band's radiance.

    ``L_mix = C L(T_a) + (1 - C) L(T_b)``, inverted to a band brightness temperature; C =
    ``fraction_a`` in [0, 1]. For :data:`BOLOMETRIC` this is thesis Eq. 8.2,
    ``(C T_a^4 + (1 - C) T_b^4)^(1/4)``. Unit emissivity.
    """
    C = np.asarray(fraction_a, float)
    if np.any(C < 0) or np.any(C > 1):
        raise ConfigError(f"fraction_a={C.min() if np.any(C < 0) else C.max()} out of range [0, 1]")
    Ta, Tb = _check_T(T_a_K), _check_T(T_b_K)
    Ta, Tb, C = np.broadcast_arrays(Ta, Tb, C)
    if np.all(C == 1.0):  # a pure footprint needs no mixing
        return Ta.astype(float).copy()
    if np.all(C == 0.0):
        return Tb.astype(float).copy()
    Lmix = C * band_radiance(Ta, band) + (1 - C) * band_radiance(Tb, band)
    lo, hi = np.minimum(Ta, Tb), np.maximum(Ta, Tb)
    return _invert(Lmix, band, lo, hi, 1e-14)


def mixed_temperature_bolometric(T_a_K, T_b_K, fraction_a) -> np.ndarray:
    """Thesis Eq. 8.2 in closed form: ``(C T_a^4 + (1 - C) T_b^4)^(1/4)`` [K]."""
    C = np.asarray(fraction_a, float)
    if np.any(C < 0) or np.any(C > 1):
        raise ConfigError("fraction_a out of range [0, 1]")
    Ta, Tb = np.asarray(T_a_K, float), np.asarray(T_b_K, float)
    return (C * Ta**4 + (1 - C) * Tb**4) ** 0.25


# -------------------------------------------------------------------------------- instruments


@functools.lru_cache(maxsize=64)
def _ref_derivative(t_ref_K: float, lo_um: float, hi_um: float) -> float:
    return float(band_radiance_derivative(t_ref_K, Band(lo_um, hi_um)))


@dataclass(frozen=True)
class Instrument:
    """A radiometer channel and the noise terms of a relative measurement (module docstring).

    Attributes
    ----------
    name : str
    lo_um, hi_um : float [um]        band edges (flat response assumed).
    netd_ref_K : float [K]           NETD of one integration at ``t_ref_K``.
    t_ref_K : float [K]              scene temperature at which ``netd_ref_K`` is specified.
    integration_s : float [s]        one integration; samples in a dwell are independent.
    knee_s : float [s]               1/f knee: dwell at which white noise equals the averaging floor.
    gain_error : float [-]           relative 1-sigma calibration gain error of band radiances.
    source : str                     where the numbers come from.
    pass_integration_s : float [s]   orbital pushbroom: time one footprint is integrated per overflight;
                                     None for a staring instrument. Sets the default mode (``passes``).
    """

    name: str
    lo_um: float
    hi_um: float
    netd_ref_K: float
    t_ref_K: float
    integration_s: float
    knee_s: float
    gain_error: float
    source: str = ""
    pass_integration_s: Optional[float] = None

    def __post_init__(self):
        Band(self.lo_um, self.hi_um)
        p = self.pass_integration_s
        if p is not None and not (math.isfinite(p) and p > 0):
            raise ConfigError(f"pass_integration_s={p} out of range (0, inf)")
        for key in ("netd_ref_K", "t_ref_K", "integration_s", "knee_s"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{key}={v} out of range (0, inf)")
        for key in ("gain_error",):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{key}={v} out of range [0, inf)")

    @property
    def band(self) -> Band:
        return Band(self.lo_um, self.hi_um)

    def netd(self, T_K) -> np.ndarray:
        """NETD [K] of one integration at scene temperature ``T_K`` [K]: NETD_ref L'(T_ref) / L'(T)."""
        return self._netd_of_derivative(band_radiance_derivative(T_K, self.band))

    def _netd_of_derivative(self, dL_dT) -> np.ndarray:
        """NETD [K] at a scene whose band's dL/dT is ``dL_dT`` [W m-2 sr-1 K-1]."""
        ref = _ref_derivative(self.t_ref_K, self.lo_um, self.hi_um)
        with np.errstate(divide="ignore", over="ignore"):
            return self.netd_ref_K * ref / dL_dT

    def noise_equivalent_radiance(self) -> float:
        """NEdL [W m-2 sr-1] of one integration (scene-independent): NETD_ref x L'(T_ref)."""
        return float(self.netd_ref_K * band_radiance_derivative(self.t_ref_K, self.band))

    def as_dict(self) -> dict:
        return asdict(self)


#: Diviner's far-IR passbands (Paige et al. 2010, Space Sci. Rev. 150, 125-160, channels 7-9) share one
#: telescope design and the same 21-element thermopile arrays, detector-noise limited: the noise-equivalent
#: radiance is taken equal for the three channels, anchored on channel 9's NETD of about 2 K at a 50 K
#: scene (thesis 7.3, citing Paige et al. 2010). Integration 0.128 s (Paige et al. 2010). Absolute
#: accuracy 0.5-1% of a 300 K scene (Paige, UCLA ESS 265 lecture 2010): gain error 1%. A pushbroom on LRO: each
#: footprint is seen for one integration per overflight (thesis 7.3: integration kept short against smearing
#: at LRO's ground speed), so the presets observe in passes of 0.128 s. 1/f knee 60 s: an
#: assumption (no published figure found). The per-channel NETDs of Paige et al. 2010 could not be read in
#: this work; the equal-radiance-noise assumption should be replaced by them.
_DIVINER_NEDL_SOURCE = (
    "Paige et al. 2010 (Space Sci. Rev. 150:125) passbands and 0.128 s integration; NETD from "
    "the thesis's 2 K at 50 K for channel 9, same noise-equivalent radiance assumed for "
    "channels 7-8 (same thermopile arrays); gain error 1% (0.5-1% accuracy at 300 K); "
    "1/f knee 60 s assumed; orbital pushbroom: 0.128 s on each footprint per pass"
)


def _diviner(ch: int, lo: float, hi: float) -> Instrument:
    ch9 = Band(100.0, 400.0)
    nedl = 2.0 * float(band_radiance_derivative(50.0, ch9))
    netd50 = nedl / float(band_radiance_derivative(50.0, Band(lo, hi)))
    return Instrument(
        name=f"diviner_ch{ch}",
        lo_um=lo,
        hi_um=hi,
        netd_ref_K=netd50,
        t_ref_K=50.0,
        integration_s=0.128,
        knee_s=60.0,
        gain_error=0.01,
        source=_DIVINER_NEDL_SOURCE,
        pass_integration_s=0.128,
    )


def _presets() -> dict[str, Instrument]:
    return {
        "diviner_ch7": _diviner(7, 25.0, 41.0),
        "diviner_ch8": _diviner(8, 50.0, 100.0),
        "diviner_ch9": _diviner(9, 100.0, 400.0),
        # FLIR A615 (the thesis's field camera, section 5.2/8.5: 640 x 480, NETD 50 mK, +-2 K): uncooled
        # VOx microbolometer, 7.5-14 um, NETD < 50 mK at a 30 C scene (FLIR A615 data sheet), 50-60 Hz frames.
        # Uncooled microbolometers drift between shutter corrections: 1/f knee 10 s assumed; gain error 2%
        # (data sheet accuracy +-2 % of reading).
        "microbolometer": Instrument(
            name="microbolometer",
            lo_um=7.5,
            hi_um=14.0,
            netd_ref_K=0.05,
            t_ref_K=303.15,
            integration_s=1.0 / 60.0,
            knee_s=10.0,
            gain_error=0.02,
            source="FLIR A615 data sheet (7.5-14 um, NETD < 50 mK at 30 C, +-2 % accuracy); "
            "thesis 5.2/8.5; 1/f knee 10 s assumed",
        ),
    }


#: Instrument presets by name (``crater-thermal report --instrument NAME``)
PRESETS: dict[str, Instrument] = _presets()


def custom_instrument(
    lo_um: float,
    hi_um: float,
    netd_K: float,
    t_ref_K: float,
    integration_s: float = 0.128,
    knee_s: float = 60.0,
    gain_error: float = 0.01,
    name: str = "custom",
    pass_integration_s: Optional[float] = None,
) -> Instrument:
    """A user-defined band/NETD (band edges [um], NETD [K] at ``t_ref_K`` [K], integration [s]).

    ``pass_integration_s`` [s]: an orbital pushbroom's time on each footprint per pass (None: staring).
    """
    return Instrument(
        name=name,
        lo_um=lo_um,
        hi_um=hi_um,
        netd_ref_K=netd_K,
        t_ref_K=t_ref_K,
        integration_s=integration_s,
        knee_s=knee_s,
        gain_error=gain_error,
        source="user-defined",
        pass_integration_s=pass_integration_s,
    )


def get_instrument(name: str) -> Instrument:
    """Preset by name (:data:`PRESETS`); :class:`ConfigError` lists the allowed names."""
    if name not in PRESETS:
        raise ConfigError(f"instrument={name!r} unknown; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]


# ------------------------------------------------------------------------------ observation

#: Observing modes: a stare (dwell [s]) or repeated orbital passes (number of passes [-])
MODES = ("stare", "passes")
#: Passes of the stated observation when none are given [-]: an assumed campaign of 100 overflights
DEFAULT_PASSES = 100


@dataclass(frozen=True)
class Observation:
    """How the candidate is compared with nominal regolith (module docstring).

    Attributes
    ----------
    footprint_fraction : float [-]   fraction of each candidate footprint that is loose (rest nominal).
    reference_footprints : int [-]   m nominal footprints averaged as the reference.
    natural_scatter_K : float [K]    footprint-to-footprint scatter of true temperatures (each footprint).
    false_alarm : float [-]          false-alarm rate of the one-sided test.
    target_pd : float [-]            detection probability the exposure is computed for.
    candidate_footprints : int [-]   k footprints spanned by the loose patch, averaged as the candidate.
    patch_area_m2 : float [m2]       area of the loose patch (with ``footprint_area_m2``: sets
                                     ``candidate_footprints = max(1, floor(A / a))`` and, for a patch
                                     smaller than one footprint, ``footprint_fraction = A / a``).
    footprint_area_m2 : float [m2]   area of one footprint (Diviner ~240 m x 480 m = 1.15e5 m2, thesis 7.3).
    mode : str                       ``stare``, ``passes`` or ``auto`` (each instrument's own: passes for an
                                     orbital pushbroom, one with ``pass_integration_s``, else stare).
    passes : int [-]                 overflights of the stated observation in pass mode (where one exposure
                                     is evaluated, e.g. the report's P_D maps; the exposure needed is searched).
    pass_integration_s : float [s]   time on each footprint per pass (None: the instrument's, else its
                                     ``integration_s``).
    """

    footprint_fraction: float = 1.0
    reference_footprints: int = 1
    natural_scatter_K: float = NATURAL_SCATTER_K
    false_alarm: float = FALSE_ALARM
    target_pd: float = TARGET_PD
    candidate_footprints: int = 1
    patch_area_m2: Optional[float] = None
    footprint_area_m2: Optional[float] = None
    mode: str = "auto"
    passes: int = DEFAULT_PASSES
    pass_integration_s: Optional[float] = None

    def __post_init__(self):
        if not 0.0 <= self.footprint_fraction <= 1.0:
            raise ConfigError(f"footprint_fraction={self.footprint_fraction} out of range [0, 1]")
        for key in ("reference_footprints", "candidate_footprints", "passes"):
            v = getattr(self, key)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise ConfigError(f"{key}={v} must be an integer >= 1")
            object.__setattr__(self, key, int(v))
        if not (math.isfinite(self.natural_scatter_K) and self.natural_scatter_K >= 0):
            raise ConfigError(f"natural_scatter_K={self.natural_scatter_K} out of range [0, inf)")
        for key in ("false_alarm", "target_pd"):
            v = getattr(self, key)
            if not 0.0 < v < 1.0:
                raise ConfigError(f"{key}={v} out of range (0, 1)")
        if self.mode not in ("auto",) + MODES:
            raise ConfigError(f"mode={self.mode!r} unknown; allowed: auto, {', '.join(MODES)}")
        p = self.pass_integration_s
        if p is not None and not (math.isfinite(p) and p > 0):
            raise ConfigError(f"pass_integration_s={p} out of range (0, inf)")
        if (self.patch_area_m2 is None) != (self.footprint_area_m2 is None):
            raise ConfigError("patch_area_m2 and footprint_area_m2 go together: give both or neither")
        if self.patch_area_m2 is not None:
            A, a = self.patch_area_m2, self.footprint_area_m2
            for key, v in (("patch_area_m2", A), ("footprint_area_m2", a)):
                if not (math.isfinite(v) and v > 0):
                    raise ConfigError(f"{key}={v} out of range (0, inf)")
            k = max(1, math.floor(A / a + 1e-9))  # 1e-9: a patch of exactly k footprints is k
            frac = min(1.0, A / a)
            if self.candidate_footprints not in (1, k):
                raise ConfigError(
                    f"candidate_footprints={self.candidate_footprints} conflicts with patch_area_m2/footprint_area_m2 "
                    f"(which give {k}); give one or the other"
                )
            if self.footprint_fraction not in (1.0, frac):
                raise ConfigError(
                    f"footprint_fraction={self.footprint_fraction} conflicts with a patch smaller than one "
                    f"footprint (fraction {frac:.3g}); give one or the other"
                )
            object.__setattr__(self, "candidate_footprints", k)
            object.__setattr__(self, "footprint_fraction", float(frac))

    def as_dict(self, instruments: Sequence[Instrument] = ()) -> dict:
        """The fields, the test, and for each of ``instruments`` the mode and time per pass [s] it resolves to."""
        d = asdict(self)
        d["test"] = "one-sided Gaussian, in the direction of the expected difference; threshold from the null"
        if instruments:
            d["mode_by_instrument"] = {i.name: observing_mode(i, self) for i in instruments}
            d["pass_integration_s_by_instrument"] = {
                i.name: pass_integration(i, self) if observing_mode(i, self) == "passes" else None for i in instruments
            }
        return d

    def with_scatter(self, natural_scatter_K: float) -> Observation:
        return replace(self, natural_scatter_K=float(natural_scatter_K))


def observing_mode(instrument: Instrument, obs: Observation) -> str:
    """``stare`` or ``passes``: the observation's mode, or with ``auto`` the instrument's own."""
    if obs.mode != "auto":
        return obs.mode
    return "passes" if instrument.pass_integration_s is not None else "stare"


def pass_integration(instrument: Instrument, obs: Observation) -> float:
    """Time on each footprint per pass [s]: the observation's, else the instrument's, else one integration."""
    for v in (obs.pass_integration_s, instrument.pass_integration_s):
        if v is not None:
            return float(v)
    return float(instrument.integration_s)


def exposure_unit(instrument: Instrument, obs: Observation) -> str:
    """Unit of an exposure in this mode: ``"s"`` (dwell, stare) or ``"passes"``."""
    return "passes" if observing_mode(instrument, obs) == "passes" else "s"


def stated_exposure(instrument: Instrument, obs: Observation, stare_dwell_s: float) -> float:
    """The exposure of a stated observation in the mode's unit: ``stare_dwell_s`` [s], or ``obs.passes``."""
    return float(obs.passes) if observing_mode(instrument, obs) == "passes" else float(stare_dwell_s)


def exposure_seconds(exposure, instrument: Instrument, obs: Observation) -> np.ndarray:
    """Total time on each footprint [s] of an exposure (dwell [s], or passes x time per pass)."""
    e = np.asarray(exposure, float)
    if observing_mode(instrument, obs) == "passes":
        return _whole_passes(e) * pass_integration(instrument, obs)
    return e


#: Names of the noise terms (variances of D) in :func:`noise_terms`
TERMS = ("instrument_white", "allan_floor", "natural_scatter", "gain_error")


def n_samples(dwell_s, integration_s: float) -> np.ndarray:
    """Independent samples in a dwell [s] of integrations [s]: floor(dwell / integration), at least 1."""
    d = np.asarray(dwell_s, float)
    if integration_s <= 0:
        raise ConfigError(f"integration_s={integration_s} out of range (0, inf)")
    if np.any(d < 0):
        raise ConfigError(f"dwell_s={d.min()} out of range [0, inf)")
    return np.maximum(1, np.floor(d / integration_s + 1e-9))  # 1e-9: dwell = n x integration is n


def _whole_passes(passes) -> np.ndarray:
    p = np.asarray(passes, float)
    if np.any(~(p >= 1)):
        raise ConfigError(f"passes={p.min() if p.size else p} out of range [1, inf)")
    return np.floor(p + 1e-9)


def averaging(exposure, instrument: Instrument, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
    """(n, r): white-noise samples per footprint, and independent floor offsets averaged per footprint [-].

    Stare (exposure = dwell [s]): ``n = floor(dwell / t_int)``, ``r = 1``. Passes (exposure = passes):
    ``n = P floor(t_pass / t_int)``, ``r = P``. Infinite exposure gives ``n = inf`` (and ``r = inf``
    with passes).
    """
    if observing_mode(instrument, obs) == "passes":
        P = _whole_passes(exposure)
        return P * n_samples(pass_integration(instrument, obs), instrument.integration_s), P
    n = n_samples(exposure, instrument.integration_s)
    return n, np.ones_like(n)


def gain_lever(T_K, band: Band) -> np.ndarray:
    """h(T) = L / L' [K]: a relative radiance gain error g moves a brightness temperature by g h (module doc)."""
    return _lever(*band_radiance_and_derivative(T_K, band))


def _lever(L, dL_dT):
    with np.errstate(divide="ignore", invalid="ignore"):
        return L / dL_dT


def observed_difference(dT_K, T_nominal_K, instrument: Instrument, obs: Observation = Observation()):
    """Expected observed difference and scene temperature of the candidate minus the reference.

    Returns
    -------
    mu_K : array [K]         band brightness temperature of a (mixed) candidate footprint minus the nominal's.
    T_cand_K : array [K]     band brightness temperature of a candidate footprint.
    """
    T_nom = _check_T(T_nominal_K)
    T_off = _check_T(T_nom + np.asarray(dT_K, float))
    if T_off.ndim == 0 and T_nom.ndim == 0:  # one scene (the report asks for it once per exposure search)
        T_cand = np.asarray(_mixed_one(float(T_off), float(T_nom), float(obs.footprint_fraction), instrument.band))
    else:
        T_cand = mixed_band_temperature(T_off, T_nom, obs.footprint_fraction, instrument.band)
    return T_cand - T_nom, T_cand


@functools.lru_cache(maxsize=4096)
def _mixed_one(T_a_K: float, T_b_K: float, fraction_a: float, band: Band) -> float:
    """:func:`mixed_band_temperature` of one footprint [K], remembered (deterministic in its arguments)."""
    return float(mixed_band_temperature(T_a_K, T_b_K, fraction_a, band))


def noise_terms(T_cand_K, T_ref_K, exposure, instrument: Instrument, obs: Observation = Observation()) -> dict:
    """Variances [K^2] of D, by term (:data:`TERMS`), with the candidate at ``T_cand_K`` [K].

    ``exposure``: dwell [s] (stare) or passes [-] (:func:`observing_mode`). With ``T_cand_K = T_ref_K``
    these are the null hypothesis's (no gain term). ``instrument_white`` = NETD(T_c)^2/(n k) +
    NETD(T_r)^2/(n m); ``allan_floor`` = (NETD(T_c)^2/k + NETD(T_r)^2/m) t_int / (knee_s r);
    ``natural_scatter`` = s^2 (1/k + 1/m); ``gain_error`` = (g (h(T_c) - h(T_r)))^2, h = L/L'
    (:func:`averaging` gives n and r).
    """
    band = instrument.band
    cand, ref = band_radiance_and_derivative(T_cand_K, band), band_radiance_and_derivative(T_ref_K, band)
    return _scene(cand, ref, instrument, obs).terms(exposure, instrument, obs)


@dataclass(frozen=True)
class _Scene:
    """The exposure-independent parts of :func:`noise_terms` for one candidate and reference scene.

    ``netd_cand``, ``netd_ref`` [K] one integration's NETD at the two scenes; ``per`` [K^2]
    NETD_c^2 / k + NETD_r^2 / m; ``floor_per`` [K^2] ``per`` x t_int / knee_s; ``natural`` and ``gain`` [K^2]
    the natural-scatter and gain-error variances. An exposure only divides ``per`` by n and ``floor_per`` by r.
    """

    netd_cand: np.ndarray
    netd_ref: np.ndarray
    per: np.ndarray
    floor_per: np.ndarray
    natural: float
    gain: np.ndarray

    def terms(self, exposure, instrument: Instrument, obs: Observation) -> dict:
        """:func:`noise_terms` [K^2] at an exposure (dwell [s] or passes [-]), arrays of the broadcast shape."""
        n, r = averaging(exposure, instrument, obs)
        white, floor = self._white_floor(n, r)
        shape = np.broadcast(white, floor, self.gain).shape
        return {
            "instrument_white": np.broadcast_to(white, shape).astype(float),
            "allan_floor": np.broadcast_to(floor, shape).astype(float),
            "natural_scatter": np.full(shape, self.natural),
            "gain_error": np.broadcast_to(self.gain, shape).astype(float),
        }

    def variance(self, n, r):
        """Variance of D [K^2] (the sum of :meth:`terms`, same order) with n samples and r floor offsets [-]."""
        white, floor = self._white_floor(n, r)
        return white + floor + self.natural + self.gain

    def _white_floor(self, n, r):
        with np.errstate(over="ignore", invalid="ignore"):
            return self.per / n, self.floor_per / r


def _scene(cand_radiance: tuple, ref_radiance: tuple, instrument: Instrument, obs: Observation) -> _Scene:
    """:class:`_Scene` from (L, dL/dT) of the band at the candidate's and the reference's temperatures
    (:func:`band_radiance_and_derivative`)."""
    (L_c, d_c), (L_r, d_r) = cand_radiance, ref_radiance
    e_c, e_r = instrument._netd_of_derivative(d_c), instrument._netd_of_derivative(d_r)
    k, m = float(obs.candidate_footprints), float(obs.reference_footprints)
    with np.errstate(over="ignore", invalid="ignore"):
        lever = _lever(L_c, d_c) - _lever(L_r, d_r)
        per = e_c**2 / k + e_r**2 / m
        floor_per = per * (instrument.integration_s / instrument.knee_s)
        gain = (instrument.gain_error * lever) ** 2
    return _Scene(e_c, e_r, per, floor_per, obs.natural_scatter_K**2 * (1 / k + 1 / m), gain)


def _total(terms) -> np.ndarray:
    return terms["instrument_white"] + terms["allan_floor"] + terms["natural_scatter"] + terms["gain_error"]


def sigma_null(T_nominal_K, exposure, instrument: Instrument, obs: Observation = Observation()) -> np.ndarray:
    """Standard deviation [K] of D under the null (every footprint at ``T_nominal_K`` [K]) at an exposure.

    ``exposure``: dwell [s] or passes [-] (:func:`exposure_unit`).
    """
    return np.sqrt(_total(noise_terms(T_nominal_K, T_nominal_K, exposure, instrument, obs)))


def detection_threshold(T_nominal_K, exposure, instrument: Instrument, obs: Observation = Observation()):
    """Threshold [K] on ``sign(mu) D``: ``z_{1-a} sigma_0`` (false-alarm rate ``obs.false_alarm`` under the null)."""
    return ndtri(1.0 - obs.false_alarm) * sigma_null(T_nominal_K, exposure, instrument, obs)


def _pd(mu, var0, var1, false_alarm):
    z = ndtri(1.0 - false_alarm)
    with np.errstate(invalid="ignore", divide="ignore"):
        arg = (np.abs(mu) - z * np.sqrt(var0)) / np.sqrt(var1)
    return np.where(np.isfinite(arg), ndtr(arg), np.where(np.isinf(var0), false_alarm, 0.0))


def detection_probability(
    dT_K, T_nominal_K, exposure, instrument: Instrument, obs: Observation = Observation()
) -> np.ndarray:
    """P_D [-] of the one-sided test at false-alarm rate ``obs.false_alarm`` (module docstring).

    Parameters
    ----------
    dT_K : float [K]             true loose minus nominal temperature (the loose part of each candidate footprint).
    T_nominal_K : float [K]      nominal scene temperature.
    exposure : array             dwell on each footprint [s] (stare) or number of passes [-] (passes).
    """
    mu, T_cand = observed_difference(dT_K, T_nominal_K, instrument, obs)
    null, alt = _null_and_alternative(T_cand, T_nominal_K, instrument, obs)
    var0 = _total(null.terms(exposure, instrument, obs))
    var1 = _total(alt.terms(exposure, instrument, obs))
    return _pd(mu, var0, var1, obs.false_alarm)


def _null_and_alternative(T_cand_K, T_nominal_K, instrument: Instrument, obs: Observation) -> tuple:
    """:class:`_Scene` under the null (candidate at ``T_nominal_K``) and the alternative (at ``T_cand_K``) [K]."""
    nominal = _radiance_pair(T_nominal_K, instrument.band)
    cand = _radiance_pair(T_cand_K, instrument.band)
    return _scene(nominal, nominal, instrument, obs), _scene(cand, nominal, instrument, obs)


def _radiance_pair(T_K, band: Band) -> tuple:
    """:func:`band_radiance_and_derivative`; one temperature's is remembered (the report asks for the same
    scenes across instruments' observations and scatter values)."""
    T = np.asarray(T_K, float)
    return _radiance_one(float(T), band) if T.ndim == 0 else band_radiance_and_derivative(T, band)


@functools.lru_cache(maxsize=4096)
def _radiance_one(T_K: float, band: Band) -> tuple:
    return band_radiance_and_derivative(T_K, band)


def _exposure_words(exposure: float, instrument: Instrument, obs: Observation) -> str:
    if observing_mode(instrument, obs) == "passes":
        t = pass_integration(instrument, obs)
        word = "pass" if round(exposure) == 1 else "passes"
        return f"{exposure:.0f} {word} ({t:.3g} s on each footprint per pass, {exposure * t:.3g} s in all)"
    return f"{exposure:.3g} s on each footprint (stare)"


def dwell_for_detection(
    dT_K: float,
    T_nominal_K: float,
    instrument: Instrument,
    obs: Observation = Observation(),
    max_dwell_s: float = 1e6,
    max_passes: int = 100_000,
) -> dict:
    """Shortest exposure for P_D >= ``obs.target_pd``: a dwell [s] (stare) or a number of passes, or why none.

    Returns
    -------
    dict with ``mu_K`` (expected observed difference [K]), ``T_candidate_K`` [K], ``netd_candidate_K`` and
    ``netd_reference_K`` (one integration [K]), ``mode`` (stare | passes), ``exposure_unit`` ("s" |
    "passes"), ``pass_integration_s`` ([s] per pass, None in a stare), ``detectable`` (bool),
    ``exposure`` (in ``exposure_unit``, or None), ``dwell_s`` (total time on each footprint [s], either
    mode, or None), ``passes`` (int or None), ``n_samples`` (per footprint, or None), ``threshold_K``
    (z sigma_0 at that exposure [K], or None), ``pd_at_dwell`` (P_D there), ``pd_limit`` (P_D at infinite
    exposure), ``limiting_term`` (largest variance term at the answer's exposure, or at infinite exposure
    when not detectable), ``sigma_terms_K`` ({term: standard deviation [K]} there, under the alternative),
    ``answer`` (a sentence). The search stops at ``max_dwell_s`` [s] or ``max_passes``.
    """
    mu_a, T_cand_a = observed_difference(dT_K, T_nominal_K, instrument, obs)
    mu, T_cand = float(mu_a), float(T_cand_a)
    inst = instrument
    # the scene's NETDs and gain levers do not depend on the exposure: evaluated once for the whole search
    null, alt = _null_and_alternative(T_cand, T_nominal_K, inst, obs)
    mode = observing_mode(inst, obs)
    passes = mode == "passes"
    t_pass = pass_integration(inst, obs) if passes else None
    out = {
        "mu_K": mu,
        "T_candidate_K": T_cand,
        "netd_candidate_K": float(alt.netd_cand),  # inst.netd(T_cand) and inst.netd(T_nominal_K)
        "netd_reference_K": float(alt.netd_ref),
        "mode": mode,
        "exposure_unit": exposure_unit(inst, obs),
        "pass_integration_s": t_pass,
        "detectable": False,
        "exposure": None,
        "dwell_s": None,
        "passes": None,
        "n_samples": None,
        "threshold_K": None,
        "pd_at_dwell": None,
        "pd_limit": None,
        "limiting_term": None,
        "sigma_terms_K": None,
        "answer": "",
    }
    # the search runs over whole steps: samples (stare: exposure = steps x t_int) or passes
    step_s = inst.integration_s

    def exposure_of(steps):
        return steps if passes else steps * step_s

    def terms_at(steps):
        return {k: float(v) for k, v in alt.terms(exposure_of(steps), inst, obs).items()}

    def var0_at(steps):
        return float(null.variance(*averaging(exposure_of(steps), inst, obs)))

    def pd(steps):
        n, r = averaging(exposure_of(steps), inst, obs)
        return float(_pd(mu, null.variance(n, r), float(alt.variance(n, r)), obs.false_alarm))

    inf_terms = terms_at(np.inf)
    inf_terms["instrument_white"] = 0.0
    pd_inf = pd(np.inf)
    out["pd_limit"] = pd_inf
    never = "with any number of passes" if passes else "at any dwell"
    if pd_inf < obs.target_pd:
        lim = max(("allan_floor", "natural_scatter", "gain_error"), key=lambda k: inf_terms[k])
        why = lim.replace("_", " ")
        if lim == "allan_floor":
            why = (
                f"the instrument's averaging floor (NETD {out['netd_candidate_K']:.3g} K at "
                f"{T_cand:.1f} K per integration)"
            )
        out.update(
            limiting_term=lim,
            sigma_terms_K={k: math.sqrt(v) for k, v in inf_terms.items()},
            answer=(
                f"not detectable {never}: P_D {pd_inf:.2f} < {obs.target_pd:g} even at infinite exposure "
                f"({100 * obs.false_alarm:g}% false alarms); limited by {why}"
            ),
        )
        return out
    n_max = float(max_passes) if passes else max(1.0, math.floor(max_dwell_s / step_s))
    if pd(n_max) < obs.target_pd:
        within = f"{n_max:.0f} passes" if passes else f"{max_dwell_s:g} s"
        out.update(
            limiting_term="instrument_white",
            pd_at_dwell=pd(n_max),
            sigma_terms_K={k: math.sqrt(v) for k, v in terms_at(n_max).items()},
            answer=(
                f"not detectable within {within}: instrument noise NETD "
                f"{out['netd_candidate_K']:.3g} K per {inst.integration_s:g} s integration"
            ),
        )
        return out
    lo, hi = 1.0, 1.0
    if pd(1.0) < obs.target_pd:  # bisection on whole steps (P_D >= target on one interval, module doc)
        lo, hi = 1.0, 2.0
        while pd(hi) < obs.target_pd:
            lo, hi = hi, min(2 * hi, n_max)
        while hi - lo > 1:
            mid = math.floor(0.5 * (lo + hi))
            lo, hi = (mid, hi) if pd(mid) < obs.target_pd else (lo, mid)
    steps = hi
    t = terms_at(steps)
    lim = max(t, key=t.get)
    expo = exposure_of(steps)
    n, _ = averaging(expo, inst, obs)
    out.update(
        detectable=True,
        exposure=float(expo),
        dwell_s=float(exposure_seconds(expo, inst, obs)),
        passes=int(steps) if passes else None,
        n_samples=int(n),
        threshold_K=float(ndtri(1.0 - obs.false_alarm) * math.sqrt(var0_at(steps))),
        pd_at_dwell=pd(steps),
        limiting_term=lim,
        sigma_terms_K={k: math.sqrt(v) for k, v in t.items()},
        answer=(
            f"P_D >= {obs.target_pd:g} at {100 * obs.false_alarm:g}% false alarms after "
            f"{_exposure_words(expo, inst, obs)}; largest noise term there: {lim.replace('_', ' ')}"
        ),
    )
    return out


def dwell_grid(instrument: Instrument, max_s: float = 3600.0, n: int = 60) -> np.ndarray:
    """Log-spaced dwell times [s] from one integration to ``max_s`` [s] (stare: P_D versus dwell curves)."""
    return np.geomspace(instrument.integration_s, max(max_s, 2 * instrument.integration_s), n)


def exposure_grid(
    instrument: Instrument, obs: Observation, max_s: float = 3600.0, max_passes: int = 10_000, n: int = 60
) -> np.ndarray:
    """Exposures for P_D curves in the mode's unit: :func:`dwell_grid` [s], or whole passes 1..``max_passes``."""
    if observing_mode(instrument, obs) == "passes":
        return np.unique(np.round(np.geomspace(1.0, max(2.0, float(max_passes)), n)))
    return dwell_grid(instrument, max_s, n)


def band_table(T_K: Sequence[float], instruments: Sequence[Instrument]) -> dict[str, dict]:
    """Band radiance [W m-2 sr-1], dL/dT [W m-2 sr-1 K-1] and NETD [K] per instrument at temperatures [K]."""
    T = np.asarray(T_K, float)
    return {
        i.name: {
            "band_um": [i.lo_um, i.hi_um],
            "T_K": T.tolist(),
            "band_radiance_W_m2_sr": band_radiance(T, i.band).tolist(),
            "dL_dT_W_m2_sr_K": band_radiance_derivative(T, i.band).tolist(),
            "netd_K": i.netd(T).tolist(),
            "netd_ref_K": i.netd_ref_K,
            "t_ref_K": i.t_ref_K,
        }
        for i in instruments
    }
