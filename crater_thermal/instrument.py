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
The observation: a candidate footprint (fraction ``C`` loose regolith, the rest nominal, mixed in
band radiance) and ``m`` reference footprints of nominal regolith, each observed for ``dwell_s``.
The observed difference ``D = T_cand - mean(T_ref)`` [K] carries these terms (all Gaussian,
independent, standard deviations in K):

1. **Instrument noise** of one footprint, ``NETD(T) / sqrt(n)`` with n = floor(dwell / integration)
   independent samples. ``NETD(T) = NETD_ref * L'(T_ref) / L'(T)`` with L' = dL/dT of the band:
   a detector-noise-limited radiometer has a scene-independent noise-equivalent radiance
   (thermopiles, microbolometers), so its NETD grows as the band's dB/dT falls at cold scenes.
2. **Averaging floor** (1/f noise and drift; the minimum of the Allan deviation), set by the knee
   time ``knee_s``: the instrument variance of one footprint is ``NETD^2 (1/n + t_int / knee_s)``, so
   the white part falls as 1/n until the dwell reaches the knee and the floor
   ``NETD sqrt(t_int / knee_s)`` remains. Like the NETD it is a radiance noise, so in kelvin it
   scales with 1/dB/dT of the band.
3. **Two scenes**: the candidate's and the references' instrument variances add; the references'
   are divided by m (m = 1: the sqrt(2) of a plain two-scene difference).
4. **Natural scatter** of regolith temperatures between footprints, ``natural_scatter_K`` per
   footprint, in the candidate and in each reference: variance ``s^2 (1 + 1/m)``. It does not
   average with dwell. Default 0.94 K: the thesis (7.2/7.3, refs [16, 112]) quotes it as the standard
   deviation of rock-free lunar regolith temperatures; by the thesis's context ref. [16] is Bandfield et
   al. 2011 (JGR 116, E00H02), Diviner night-time temperatures of the regolith fines between 60 N and
   60 S (scenes of roughly 70-120 K, footprints of ~250 m); the paper itself was not read here. At 40-80 K
   inside polar craters it has not been measured; what
   sets temperatures there (scattered and re-emitted light, geothermal flux) differs from the
   equatorial night, so take it as uncertain by a factor of about 2 either way (the report shows the
   answer at 0.5x and 2x).
5. **Calibration gain error** ``gain_error`` (relative, 1 sigma) multiplies the difference of band
   radiances, so it scales D: standard deviation ``gain_error * |mu|`` (mu = expected D). It is zero
   under the null hypothesis (no difference), so it widens only the detection distribution.
   An absolute offset is common to both scenes and cancels in D; it does not enter.

The test is **one-sided** in the direction of the expected difference (loose regolith is colder at
night, warmer by day): declare "different" when ``sign(mu) D > z_{1-a} sigma_0``, with a the false-alarm
rate (default 1%), sigma_0 the standard deviation of D without a difference, sigma_1 with it. Then
``P_D = Phi((|mu| - z_{1-a} sigma_0) / sigma_1)``. :func:`dwell_for_detection` gives the shortest dwell
with ``P_D >= 0.9`` or, when even infinite dwell (sigma_0 -> the floors and the scatter) cannot reach
it, "not detectable at any dwell" and the term that limits.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

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
    return _C_BAND * T**4 * planck_integral(x1, x2)


def band_radiance_derivative(T_K, band: Band) -> np.ndarray:
    """dL/dT [W m-2 sr-1 K-1] = C T^3 (4 I - x2 f(x2) + x1 f(x1)), f(x) = x^3/(e^x - 1), exact."""
    T = _check_T(T_K)
    x1, x2 = band.x_edges(T)

    def xf(x):
        out = np.zeros_like(x)
        ok = np.isfinite(x) & (x > 0)
        with np.errstate(over="ignore", under="ignore"):
            out[ok] = x[ok] ** 4 / np.expm1(x[ok])
        return out

    return _C_BAND * T**3 * (4 * planck_integral(x1, x2) - xf(x2) + xf(x1))


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
        Lt = band_radiance(T, band)
        g = np.log(Lt) - logL
        lo = np.where(g < 0, T, lo)
        hi = np.where(g > 0, T, hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = g / (band_radiance_derivative(T, band) / Lt)
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
    gain_error : float [-]           relative 1-sigma calibration gain error on radiance differences.
    source : str                     where the numbers come from.
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

    def __post_init__(self):
        Band(self.lo_um, self.hi_um)
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
        ref = _ref_derivative(self.t_ref_K, self.lo_um, self.hi_um)
        with np.errstate(divide="ignore", over="ignore"):
            return self.netd_ref_K * ref / band_radiance_derivative(T_K, self.band)

    def noise_equivalent_radiance(self) -> float:
        """NEdL [W m-2 sr-1] of one integration (scene-independent): NETD_ref x L'(T_ref)."""
        return float(self.netd_ref_K * band_radiance_derivative(self.t_ref_K, self.band))

    def as_dict(self) -> dict:
        return asdict(self)


#: Diviner's far-IR passbands (Paige et al. 2010, Space Sci. Rev. 150, 125-160, channels 7-9) share one
#: telescope design and the same 21-element thermopile arrays, detector-noise limited: the noise-equivalent
#: radiance is taken equal for the three channels, anchored on channel 9's NETD of about 2 K at a 50 K
#: scene (thesis 7.3, citing Paige et al. 2010). Integration 0.128 s (Paige et al. 2010). Absolute
#: accuracy 0.5-1% of a 300 K scene (Paige, UCLA ESS 265 lecture 2010): gain error 1%. 1/f knee 60 s: an
#: assumption (no published figure found). The per-channel NETDs of Paige et al. 2010 could not be read in
#: this work; the equal-radiance-noise assumption should be replaced by them.
_DIVINER_NEDL_SOURCE = (
    "Paige et al. 2010 (Space Sci. Rev. 150:125) passbands and 0.128 s integration; NETD from "
    "the thesis's 2 K at 50 K for channel 9, same noise-equivalent radiance assumed for "
    "channels 7-8 (same thermopile arrays); gain error 1% (0.5-1% accuracy at 300 K); "
    "1/f knee 60 s assumed"
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
) -> Instrument:
    """A user-defined band/NETD (band edges [um], NETD [K] at ``t_ref_K`` [K], integration [s])."""
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
    )


def get_instrument(name: str) -> Instrument:
    """Preset by name (:data:`PRESETS`); :class:`ConfigError` lists the allowed names."""
    if name not in PRESETS:
        raise ConfigError(f"instrument={name!r} unknown; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]


# ------------------------------------------------------------------------------ observation


@dataclass(frozen=True)
class Observation:
    """How the candidate is compared with nominal regolith (module docstring).

    Attributes
    ----------
    footprint_fraction : float [-]   fraction of the candidate footprint that is loose (rest nominal).
    reference_footprints : int       m nominal footprints averaged as the reference.
    natural_scatter_K : float [K]    footprint-to-footprint scatter of true temperatures (each footprint).
    false_alarm : float [-]          false-alarm rate of the one-sided test.
    target_pd : float [-]            detection probability the dwell is computed for.
    """

    footprint_fraction: float = 1.0
    reference_footprints: int = 1
    natural_scatter_K: float = NATURAL_SCATTER_K
    false_alarm: float = FALSE_ALARM
    target_pd: float = TARGET_PD

    def __post_init__(self):
        if not 0.0 <= self.footprint_fraction <= 1.0:
            raise ConfigError(f"footprint_fraction={self.footprint_fraction} out of range [0, 1]")
        if int(self.reference_footprints) != self.reference_footprints or self.reference_footprints < 1:
            raise ConfigError(f"reference_footprints={self.reference_footprints} must be an integer >= 1")
        if not (math.isfinite(self.natural_scatter_K) and self.natural_scatter_K >= 0):
            raise ConfigError(f"natural_scatter_K={self.natural_scatter_K} out of range [0, inf)")
        for key in ("false_alarm", "target_pd"):
            v = getattr(self, key)
            if not 0.0 < v < 1.0:
                raise ConfigError(f"{key}={v} out of range (0, 1)")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["test"] = "one-sided Gaussian, in the direction of the expected difference"
        return d

    def with_scatter(self, natural_scatter_K: float) -> Observation:
        return replace(self, natural_scatter_K=float(natural_scatter_K))


#: Names of the noise terms (variances of D) in :func:`noise_terms`
TERMS = ("instrument_white", "allan_floor", "natural_scatter", "gain_error")


def n_samples(dwell_s, integration_s: float) -> np.ndarray:
    """Independent samples in a dwell: floor(dwell / integration), at least 1."""
    d = np.asarray(dwell_s, float)
    if integration_s <= 0:
        raise ConfigError(f"integration_s={integration_s} out of range (0, inf)")
    if np.any(d < 0):
        raise ConfigError(f"dwell_s={d.min()} out of range [0, inf)")
    return np.maximum(1, np.floor(d / integration_s + 1e-9))  # 1e-9: dwell = n x integration is n


def observed_difference(dT_K, T_nominal_K, instrument: Instrument, obs: Observation = Observation()):
    """Expected observed difference and scene temperatures of candidate minus reference.

    Returns
    -------
    mu_K : array [K]         band brightness temperature of the mixed candidate minus the nominal's.
    T_cand_K : array [K]     band brightness temperature of the candidate footprint.
    """
    T_nom = _check_T(T_nominal_K)
    T_off = _check_T(T_nom + np.asarray(dT_K, float))
    T_cand = mixed_band_temperature(T_off, T_nom, obs.footprint_fraction, instrument.band)
    return T_cand - T_nom, T_cand


def noise_terms(
    mu_K, T_cand_K, T_ref_K, dwell_s, instrument: Instrument, obs: Observation = Observation()
) -> dict[str, np.ndarray]:
    """Variances [K^2] of the observed difference D, by term (:data:`TERMS`), at a dwell [s].

    ``instrument_white`` = NETD(T_cand)^2/n + NETD(T_ref)^2/(n m); ``allan_floor`` = the same with
    1/n replaced by t_int / knee_s;
    ``natural_scatter`` = s^2 (1 + 1/m); ``gain_error`` = (g mu)^2 (present only with a difference).
    """
    m = float(obs.reference_footprints)
    n = n_samples(dwell_s, instrument.integration_s)
    e_c = instrument.netd(T_cand_K)
    e_r = instrument.netd(T_ref_K)
    with np.errstate(over="ignore"):
        white = e_c**2 / n + e_r**2 / (n * m)
        floor = (e_c**2 + e_r**2 / m) * (instrument.integration_s / instrument.knee_s)
    shape = np.broadcast(white, np.asarray(mu_K, float)).shape
    return {
        "instrument_white": np.broadcast_to(white, shape).astype(float),
        "allan_floor": np.broadcast_to(floor, shape).astype(float),
        "natural_scatter": np.full(shape, obs.natural_scatter_K**2 * (1 + 1 / m)),
        "gain_error": np.broadcast_to((instrument.gain_error * np.asarray(mu_K, float)) ** 2, shape).astype(float),
    }


def _pd_from_terms(mu, terms, false_alarm):
    var0 = terms["instrument_white"] + terms["allan_floor"] + terms["natural_scatter"]
    var1 = var0 + terms["gain_error"]
    z = ndtri(1.0 - false_alarm)
    with np.errstate(invalid="ignore", divide="ignore"):
        arg = (np.abs(mu) - z * np.sqrt(var0)) / np.sqrt(var1)
    return np.where(np.isfinite(arg), ndtr(arg), np.where(np.isinf(var0), false_alarm, 0.0))


def detection_probability(
    dT_K, T_nominal_K, dwell_s, instrument: Instrument, obs: Observation = Observation()
) -> np.ndarray:
    """P_D [-] of the one-sided test at false-alarm rate ``obs.false_alarm``, per dwell [s].

    Parameters
    ----------
    dT_K : float [K]             true loose minus nominal temperature (the loose part of the footprint).
    T_nominal_K : float [K]      nominal scene temperature.
    dwell_s : array [s]          dwell on each footprint.
    """
    mu, T_cand = observed_difference(dT_K, T_nominal_K, instrument, obs)
    terms = noise_terms(mu, T_cand, T_nominal_K, dwell_s, instrument, obs)
    return _pd_from_terms(mu, terms, obs.false_alarm)


def dwell_for_detection(
    dT_K: float, T_nominal_K: float, instrument: Instrument, obs: Observation = Observation(), max_dwell_s: float = 1e6
) -> dict:
    """Shortest dwell [s] on each footprint for P_D >= ``obs.target_pd``, or why there is none.

    Returns
    -------
    dict with ``mu_K`` (expected observed difference [K]), ``T_candidate_K``, ``netd_candidate_K`` and
    ``netd_reference_K`` (one integration [K]), ``detectable`` (bool), ``dwell_s`` ([s] or None),
    ``n_samples`` (int or None), ``pd_at_dwell`` (P_D at that dwell), ``pd_limit`` (P_D at infinite dwell),
    ``limiting_term`` (largest variance term at the answer's dwell, or at infinite dwell when not
    detectable), ``sigma_terms_K`` ({term: standard deviation [K]} at that dwell), ``answer`` (a sentence).
    """
    mu_a, T_cand_a = observed_difference(dT_K, T_nominal_K, instrument, obs)
    mu, T_cand = float(mu_a), float(T_cand_a)
    inst = instrument
    out = {
        "mu_K": mu,
        "T_candidate_K": T_cand,
        "netd_candidate_K": float(inst.netd(T_cand)),
        "netd_reference_K": float(inst.netd(T_nominal_K)),
        "detectable": False,
        "dwell_s": None,
        "n_samples": None,
        "pd_at_dwell": None,
        "pd_limit": None,
        "limiting_term": None,
        "sigma_terms_K": None,
        "answer": "",
    }

    def terms_at(n):
        return noise_terms(mu, T_cand, T_nominal_K, n * inst.integration_s, inst, obs)

    inf_terms = {k: float(v) for k, v in terms_at(np.inf).items()}
    inf_terms["instrument_white"] = 0.0
    pd_inf = float(_pd_from_terms(mu, inf_terms, obs.false_alarm))
    out["pd_limit"] = pd_inf
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
                f"not detectable at any dwell: P_D <= {pd_inf:.2f} < {obs.target_pd:g} at "
                f"{100 * obs.false_alarm:g}% false alarms; limited by {why}"
            ),
        )
        return out
    n_max = max(1.0, math.floor(max_dwell_s / inst.integration_s))

    def pd(n):
        return float(_pd_from_terms(mu, {k: float(v) for k, v in terms_at(n).items()}, obs.false_alarm))

    if pd(n_max) < obs.target_pd:
        t = terms_at(n_max)
        out.update(
            limiting_term="instrument_white",
            pd_at_dwell=pd(n_max),
            sigma_terms_K={k: math.sqrt(float(v)) for k, v in t.items()},
            answer=(
                f"not detectable within {max_dwell_s:g} s: instrument noise NETD "
                f"{out['netd_candidate_K']:.3g} K per {inst.integration_s:g} s integration"
            ),
        )
        return out
    lo, hi = 1.0, 1.0
    if pd(1.0) < obs.target_pd:  # bisection on the integer sample count (P_D increases with n)
        lo, hi = 1.0, 2.0
        while pd(hi) < obs.target_pd:
            lo, hi = hi, min(2 * hi, n_max)
        while hi - lo > 1:
            mid = math.floor(0.5 * (lo + hi))
            lo, hi = (mid, hi) if pd(mid) < obs.target_pd else (lo, mid)
    n = hi
    t = {k: float(v) for k, v in terms_at(n).items()}
    lim = max(t, key=t.get)
    dwell = n * inst.integration_s
    out.update(
        detectable=True,
        dwell_s=dwell,
        n_samples=int(n),
        pd_at_dwell=pd(n),
        limiting_term=lim,
        sigma_terms_K={k: math.sqrt(v) for k, v in t.items()},
        answer=(
            f"P_D >= {obs.target_pd:g} at {100 * obs.false_alarm:g}% false alarms after {dwell:.3g} s "
            f"on each footprint; largest noise term there: {lim.replace('_', ' ')}"
        ),
    )
    return out


def dwell_grid(instrument: Instrument, max_s: float = 3600.0, n: int = 60) -> np.ndarray:
    """Log-spaced dwell times [s] from one integration to ``max_s`` (for P_D versus dwell curves)."""
    return np.geomspace(instrument.integration_s, max(max_s, 2 * instrument.integration_s), n)


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


def sigma_null(T_cand_K, T_ref_K, dwell_s, instrument: Instrument, obs: Observation = Observation()) -> np.ndarray:
    """Standard deviation [K] of D without a difference (instrument, floor, scatter) at a dwell [s]."""
    t = noise_terms(0.0, T_cand_K, T_ref_K, dwell_s, instrument, obs)
    return np.sqrt(t["instrument_white"] + t["allan_floor"] + t["natural_scatter"])
