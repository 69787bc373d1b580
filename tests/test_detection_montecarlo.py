"""An independent Monte Carlo of the detection test that crater_thermal.instrument documents (issue 25).

Written from the module docstring's noise model, not from the code: its own band radiance (Gauss-Legendre
quadrature of the Planck function over wavelength, not the module's series), its own NETD(T) from the
instrument's stated NETD_ref and T_ref, its own mixing and radiance inversion, and draws of every term where
the model puts it:

* each footprint's true temperature ``T_scene + s z`` (natural scatter, one draw per footprint);
* one calibration gain ``g`` per comparison, common to all footprints, acting on band radiance: the reading
  is ``T_b((1 + g) L(T_true))``;
* white noise ``NETD(T_scene) w`` on every sample, one floor offset ``NETD sqrt(t_int / knee) f`` per
  footprint (stare) or per footprint and pass (passes), the footprint's value the mean of its samples;
* ``D`` = mean of the k candidate footprints minus the mean of the m references.

Under the null every footprint is at the nominal temperature; under the alternative the candidates are at
the mixed loose/nominal temperature. From the code only the quantities under test are taken: its threshold
(``detection_threshold``) and its P_D (``detection_probability``).

Tolerances: N = 100,000 comparisons per hypothesis and parameter set; the realized false-alarm rate must lie
within 3 binomial standard deviations of the nominal 1% (3 sqrt(0.01 x 0.99 / N) = 0.094 percentage points),
and the realized P_D within 3 sqrt(P_D (1 - P_D) / N) (at most 0.0047) of the code's. The terms the closed
form neglects (gain x scatter products, second order in g) are below 1e-4 in P_D at these gains (<= 10%).
"""

import math

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.special import ndtri

from crater_thermal import instrument as ins

H, C, KB = 6.62607015e-34, 299792458.0, 1.380649e-23  # CODATA 2018 exact SI values [J s], [m s-1], [J K-1]
N_DRAWS = 100_000
CHUNK = 5_000
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(256)


def _planck(lam_m, T):
    """B_lambda [W m-2 sr-1 m-1] at wavelengths lam_m [m] (last axis) and temperatures T [K] (first axis)."""
    x = H * C / (lam_m[None, :] * KB * T[:, None])
    return 2 * H * C**2 / lam_m[None, :] ** 5 / np.expm1(x)


def _dplanck_dT(lam_m, T):
    x = H * C / (lam_m[None, :] * KB * T[:, None])
    return 2 * H * C**2 / lam_m[None, :] ** 5 * (x / T[:, None]) * np.exp(x) / np.expm1(x) ** 2


def _band(f, lo_um, hi_um, T):
    """integral_lo^hi f(lambda, T) d lambda by 256-point Gauss-Legendre over wavelength [m]."""
    a, b = lo_um * 1e-6, hi_um * 1e-6
    lam = 0.5 * (b - a) * _NODES + 0.5 * (b + a)
    return 0.5 * (b - a) * (f(lam, np.atleast_1d(np.asarray(T, float))) @ _WEIGHTS)


class Band:
    """The MC's own band: radiance, its derivative, NETD scaling and an inverse on a tabulated range."""

    def __init__(self, inst, T_lo, T_hi):
        self.inst = inst
        self.T = np.arange(T_lo, T_hi, 0.02)
        self.logL = np.log(self.L(self.T))
        self._logL_of_T = CubicSpline(self.T, self.logL)
        self._T_of_logL = CubicSpline(self.logL, self.T)

    def L(self, T):
        return _band(_planck, self.inst.lo_um, self.inst.hi_um, T)

    def dL(self, T):
        return _band(_dplanck_dT, self.inst.lo_um, self.inst.hi_um, T)

    def netd(self, T):
        """Scene-independent noise-equivalent radiance NETD_ref L'(T_ref), over L'(T) [K]."""
        return float(self.inst.netd_ref_K * self.dL(self.inst.t_ref_K)[0] / self.dL(T)[0])

    def log_L(self, T):
        return self._logL_of_T(T)

    def T_of_log_L(self, logL):
        return self._T_of_logL(logL)

    def mix(self, T_a, T_b, frac):
        """Brightness temperature of a footprint mixing two surfaces in band radiance [K]."""
        L = frac * self.L(T_a)[0] + (1 - frac) * self.L(T_b)[0]
        return float(self.T_of_log_L(math.log(L)))


def _draw_D(rng, band, T_scene, k, n_per_pass, passes, scatter, gain_error, knee_s, int_s, netd_K=None):
    """N_DRAWS values of D: footprints 0..k-1 are candidates; T_scene [K] per footprint, shape (k + m,).

    ``netd_K`` [K] per footprint replaces NETD(T_scene) (only to draw the old, wrong null).
    """
    T_scene = np.asarray(T_scene, float)
    nf = T_scene.size
    netd = np.array([band.netd(t) for t in T_scene] if netd_K is None else netd_K, float)
    floor_sd = netd * math.sqrt(int_s / knee_s)
    out = []
    for _ in range(N_DRAWS // CHUNK):
        T_true = T_scene + scatter * rng.standard_normal((CHUNK, nf))
        if gain_error > 0:
            g = gain_error * rng.standard_normal((CHUNK, 1))
            T_true = band.T_of_log_L(np.log1p(g) + band.log_L(T_true))
        # every sample of every pass: white noise per sample, one floor offset per footprint and pass
        w = rng.standard_normal((CHUNK, nf, passes, n_per_pass), dtype=np.float32)
        f = rng.standard_normal((CHUNK, nf, passes, 1), dtype=np.float32)
        samples = netd[None, :, None, None] * w + floor_sd[None, :, None, None] * f
        T_meas = T_true + samples.reshape(CHUNK, nf, -1).astype(float).mean(axis=2)
        out.append(T_meas[:, :k].mean(axis=1) - T_meas[:, k:].mean(axis=1))
    return np.concatenate(out)


def monte_carlo(case, seed):
    """(realized false-alarm rate, realized P_D, code's P_D, code's threshold [K]) for one parameter set."""
    inst = ins.PRESETS[case["inst"]]
    if "gain" in case:
        inst = ins.Instrument(**{**inst.as_dict(), "gain_error": case["gain"]})
    obs = ins.Observation(
        candidate_footprints=case["k"],
        reference_footprints=case["m"],
        natural_scatter_K=case["scatter"],
        footprint_fraction=case.get("frac", 1.0),
        mode=case["mode"],
        pass_integration_s=case.get("t_pass"),
    )
    T_n, dT = case["T"], case["dT"]
    band = Band(inst, min(T_n, T_n + dT) - 15.0, max(T_n, T_n + dT) + 15.0)
    # the exposure in the MC's own terms: samples per pass and passes
    if case["mode"] == "passes":
        t_pass = case.get("t_pass", inst.pass_integration_s)
        n_per_pass, passes, exposure = round(t_pass / inst.integration_s), case["passes"], case["passes"]
    else:
        n_per_pass, passes, exposure = round(case["dwell"] / inst.integration_s), 1, case["dwell"]
    k, m = case["k"], case["m"]
    T_c = band.mix(T_n + dT, T_n, case.get("frac", 1.0))
    args = (k, n_per_pass, passes, case["scatter"], inst.gain_error, inst.knee_s, inst.integration_s)
    rng = np.random.default_rng(seed)
    D0 = _draw_D(rng, band, [T_n] * (k + m), *args)
    D1 = _draw_D(rng, band, [T_c] * k + [T_n] * m, *args)
    thr = float(ins.detection_threshold(T_n, exposure, inst, obs))
    s = math.copysign(1.0, T_c - T_n)
    pd_code = float(ins.detection_probability(dT, T_n, exposure, inst, obs))
    return float(np.mean(s * D0 > thr)), float(np.mean(s * D1 > thr)), pd_code, thr, (band, T_c, args, D0)


CASES = {
    # the -86 deg floor at the centre night (58.1 K, -2.77 K), a 3-footprint patch, Diviner in passes
    "ch9_floor_k3m3_passes": dict(
        inst="diviner_ch9", mode="passes", passes=20, T=58.1, dT=-2.77, k=3, m=3, scatter=0.94
    ),
    # issue 25: the old threshold's false-alarm rate was 0.82% here
    "ch7_58K_passes8": dict(inst="diviner_ch7", mode="passes", passes=8, T=58.0, dT=-2.77, k=1, m=1, scatter=0.3),
    "ch8_40K_stare": dict(inst="diviner_ch8", mode="stare", dwell=0.64, T=40.0, dT=-1.5, k=2, m=5, scatter=0.5),
    # a warmer candidate (loose regolith by day), three integrations per pass
    "ch7_80K_warm_tpass": dict(
        inst="diviner_ch7", mode="passes", passes=4, t_pass=0.384, T=80.0, dT=1.2, k=4, m=2, scatter=0.6
    ),
    # a large gain error, where the band-radiance gain term matters
    "ch9_110K_gain10pct": dict(
        inst="diviner_ch9", mode="stare", dwell=1.28, T=110.0, dT=-2.0, k=1, m=4, scatter=0.2, gain=0.1
    ),
    "ch8_70K_passes50_frac": dict(
        inst="diviner_ch8", mode="passes", passes=50, T=70.0, dT=-1.0, k=5, m=5, scatter=0.94, frac=0.6
    ),
    # issue 25: the old threshold's false-alarm rate was 0.2-0.4% for the microbolometer at 104 K
    "mb_104K_k5m5": dict(inst="microbolometer", mode="stare", dwell=2.0, T=104.0, dT=-3.0, k=5, m=5, scatter=0.5),
    "mb_110K_k2m3": dict(inst="microbolometer", mode="stare", dwell=1.0, T=110.0, dT=-4.0, k=2, m=3, scatter=0.3),
    "mb_85K_frac": dict(
        inst="microbolometer", mode="stare", dwell=3.0, T=85.0, dT=-6.0, k=3, m=1, scatter=0.2, frac=0.7, gain=0.05
    ),
    # issue 25: 1.4e-5 instead of 1% at 58 K (the candidate's NETD at 55 K is 2.3x the nominal's)
    "mb_58K": dict(inst="microbolometer", mode="stare", dwell=0.5, T=58.0, dT=-2.77, k=1, m=1, scatter=0.94),
}


def _seed(name):
    """One fixed seed per parameter set (the test is deterministic)."""
    return sorted(CASES).index(name) + 2025


@pytest.mark.parametrize("name", list(CASES))
def test_false_alarm_and_pd_match_an_independent_monte_carlo(name):
    case = CASES[name]
    fa, pd_mc, pd_code, thr, _ = monte_carlo(case, seed=_seed(name))
    alpha = 0.01
    tol_fa = 3 * math.sqrt(alpha * (1 - alpha) / N_DRAWS)
    assert fa == pytest.approx(alpha, abs=tol_fa), f"realized false-alarm rate {fa:.5f}, threshold {thr:.4g} K"
    tol_pd = 3 * math.sqrt(pd_code * (1 - pd_code) / N_DRAWS)
    assert pd_mc == pytest.approx(pd_code, abs=tol_pd), f"P_D: MC {pd_mc:.4f}, code {pd_code:.4f}"


def test_the_monte_carlo_rejects_the_old_threshold():
    """Power: the threshold of the code before issue 25 (the candidate's NETD at the loose temperature in the
    null) realizes about 0.6% here, which the false-alarm check above rejects (> 3 sigma from 1%)."""
    case = CASES["ch7_58K_passes8"]
    fa, _, _, _, (band, T_c, args, D0) = monte_carlo(case, seed=_seed("ch7_58K_passes8"))
    k, m, T_n = case["k"], case["m"], case["T"]
    assert band.netd(T_c) / band.netd(T_n) > 1.2  # the candidate is noisier: ch. 7 at 55 K vs 58 K
    # the old null: every footprint at the nominal temperature, the candidate's noise at its loose NETD
    netd_old = [band.netd(T_c)] * k + [band.netd(T_n)] * m
    D_old = _draw_D(np.random.default_rng(8), band, [T_n] * (k + m), *args, netd_K=netd_old)
    thr_old = float(np.quantile(-D_old, 0.99))  # its own 1% threshold on -D (the candidate is colder)
    fa_old = float(np.mean(-D0 > thr_old))
    tol_fa = 3 * math.sqrt(0.01 * 0.99 / N_DRAWS)
    assert fa_old < 0.01 - 2 * tol_fa, fa_old  # 2x: the old threshold is itself estimated (same N)
    assert fa == pytest.approx(0.01, abs=tol_fa)


def test_the_monte_carlo_band_is_the_planck_integral():
    """The MC's own radiance table inverts to 1e-6 K and its NETD ratio is a quadrature of dB/dT."""
    inst = ins.PRESETS["microbolometer"]
    band = Band(inst, 40.0, 120.0)
    T = np.array([41.3, 58.0, 104.0, 119.0])
    np.testing.assert_allclose(band.T_of_log_L(np.log(band.L(T))), T, atol=1e-6)
    assert band.netd(inst.t_ref_K) == pytest.approx(inst.netd_ref_K, rel=1e-12)
    z = float(ndtri(0.99))
    assert z == pytest.approx(2.3263478740, rel=1e-9)  # the one-sided 1% quantile the code uses
