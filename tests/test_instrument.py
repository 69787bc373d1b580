"""Tests of crater_thermal.instrument: band radiance, band mixing, NETD(T), detection statistics."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from crater_thermal import instrument as ins
from crater_thermal.constants import SIGMA
from crater_thermal.errors import ConfigError

H, C, K = ins.H_PLANCK, ins.C_LIGHT, ins.K_BOLTZMANN
BANDS = [ins.Band(25, 41), ins.Band(50, 100), ins.Band(100, 400), ins.Band(7.5, 14)]


def planck(lam_m, T):
    return 2 * H * C**2 / lam_m**5 / math.expm1(H * C / (lam_m * K * T))


def quad_band(f, band, T):
    """Independent band integral by adaptive quadrature over wavelength [um grid, per m]."""
    return quad(lambda l_um: f(l_um * 1e-6, T) * 1e-6, band.lo_um, band.hi_um, epsabs=0, epsrel=1e-12, limit=200)[0]


def test_bolometric_band_radiance_is_sigma_T4_over_pi():
    T = np.array([20.0, 58.0, 300.0])
    # exact series: agreement to double rounding (1e-12 relative)
    np.testing.assert_allclose(ins.band_radiance(T, ins.BOLOMETRIC), SIGMA * T**4 / np.pi, rtol=1e-12)


@pytest.mark.parametrize("band", BANDS, ids=lambda b: b.label())
@pytest.mark.parametrize("T", [40.0, 58.0, 85.0, 300.0])
def test_band_radiance_and_derivative_match_quadrature(band, T):
    # the series are exact; quad's own relative error is ~1e-12, so 1e-9 leaves margin
    assert float(ins.band_radiance(T, band)) == pytest.approx(quad_band(planck, band, T), rel=1e-9)
    assert float(ins.band_radiance_derivative(T, band)) == pytest.approx(
        quad_band(lambda lam, t: float(ins.planck_dB_dT(lam, t)), band, T), rel=1e-9
    )


@pytest.mark.parametrize("name", list(ins.PRESETS))
def test_netd_scaling_reproduces_independent_dBdT_ratios(name):
    inst = ins.PRESETS[name]
    d = {T: quad_band(lambda lam, t: float(ins.planck_dB_dT(lam, t)), inst.band, T) for T in (40.0, 58.0, 85.0)}
    ref = quad_band(lambda lam, t: float(ins.planck_dB_dT(lam, t)), inst.band, inst.t_ref_K)
    for T in (40.0, 58.0, 85.0):
        # NETD x dL/dT is the scene-independent noise-equivalent radiance: ratios to quadrature precision
        assert float(inst.netd(T)) == pytest.approx(inst.netd_ref_K * ref / d[T], rel=1e-8)
    assert float(inst.netd(40.0) / inst.netd(85.0)) == pytest.approx(d[85.0] / d[40.0], rel=1e-8)


@settings(max_examples=30, deadline=None)
@given(T=st.floats(20.0, 400.0), frac=st.floats(0.0, 1.0), b=st.sampled_from(BANDS + [ins.BOLOMETRIC]))
def test_equal_temperatures_mix_to_that_temperature(T, frac, b):
    # the inversion converges to 1e-14 relative; 1e-9 K is float noise at these temperatures
    assert float(ins.mixed_band_temperature(T, T, frac, b)) == pytest.approx(T, abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(Ta=st.floats(20.0, 400.0), Tb=st.floats(20.0, 400.0), frac=st.floats(0.0, 1.0))
def test_whole_spectrum_band_is_eq_8_2(Ta, Tb, frac):
    # issue requirement: the bolometric limit reproduces Eq. 8.2 to 1e-6 K
    eq82 = (frac * Ta**4 + (1 - frac) * Tb**4) ** 0.25
    assert float(ins.mixed_band_temperature(Ta, Tb, frac, ins.BOLOMETRIC)) == pytest.approx(eq82, abs=1e-6)
    assert float(ins.mixed_temperature_bolometric(Ta, Tb, frac)) == pytest.approx(eq82, abs=1e-9)


def test_narrow_band_at_10um_mixes_as_planck_says():
    lam = 10e-6
    Ta, Tb, frac = 60.0, 40.0, 0.5
    # monochromatic Planck mixing, inverted in closed form: T = hc/(lam k) / ln(1 + 2hc^2/(lam^5 B))
    B = frac * planck(lam, Ta) + (1 - frac) * planck(lam, Tb)
    T_planck = H * C / (lam * K) / math.log1p(2 * H * C**2 / (lam**5 * B))
    got = float(ins.mixed_band_temperature(Ta, Tb, frac, ins.Band(9.999, 10.001)))
    # a 2 nm wide band differs from the monochromatic value by the band's curvature, << 1e-4 K here
    assert got == pytest.approx(T_planck, abs=1e-4)
    eq82 = float(ins.mixed_temperature_bolometric(Ta, Tb, frac))
    # on the Wien side the warm part dominates the radiance: 57.4 K vs Eq. 8.2's 52.8 K
    assert got - eq82 > 4.0


def test_microbolometer_sees_almost_nothing_at_58K():
    mb = ins.PRESETS["microbolometer"]
    L58, L300 = float(ins.band_radiance(58.0, mb.band)), float(ins.band_radiance(300.0, mb.band))
    assert L58 < 1e-5 and L300 > 50  # W m-2 sr-1: 4e-6 at 58 K vs ~59 at 300 K
    assert float(mb.netd(58.0)) > 1e4  # K: 50 mK at 303 K becomes tens of thousands of K
    res = ins.dwell_for_detection(-2.77, 58.0, mb)
    assert not res["detectable"] and res["limiting_term"] == "allan_floor"


def _monte_carlo(dT, T_nom, dwell, inst, obs, n_draws=100_000, seed=12345):
    """Draw the stated noise model term by term; returns (false-alarm rate, detection rate)."""
    rng = np.random.default_rng(seed)
    mu, T_c = ins.observed_difference(dT, T_nom, inst, obs)
    mu, T_c = float(mu), float(T_c)
    m = obs.reference_footprints
    n = int(ins.n_samples(dwell, inst.integration_s))
    e_c, e_r = float(inst.netd(T_c)), float(inst.netd(T_nom))
    fr = math.sqrt(inst.integration_s / inst.knee_s)

    def draw(mean):
        # candidate: its scatter, n white samples averaged, its floor offset
        cand = mean + obs.natural_scatter_K * rng.standard_normal(n_draws)
        cand += e_c * rng.standard_normal((n_draws, n)).mean(axis=1) + e_c * fr * rng.standard_normal(n_draws)
        ref = obs.natural_scatter_K * rng.standard_normal((n_draws, m))
        ref += e_r * rng.standard_normal((n_draws, m, n)).mean(axis=2) + e_r * fr * rng.standard_normal((n_draws, m))
        gain = 1.0 + inst.gain_error * rng.standard_normal(n_draws)
        return cand - ref.mean(axis=1), gain

    sig0 = float(ins.sigma_null(T_c, T_nom, dwell, inst, obs))
    thr = ins.ndtri(1 - obs.false_alarm) * sig0
    noise0, _ = draw(0.0)
    noise1, gain = draw(0.0)
    d1 = gain * mu + noise1  # the gain error scales the true difference of band radiances
    s = np.sign(mu)
    return float(np.mean(s * noise0 > thr)), float(np.mean(s * d1 > thr))


@pytest.mark.parametrize(
    "case",
    [
        {"dT": -2.77, "T": 58.1, "dwell": 0.6, "inst": "diviner_ch9", "m": 1, "scatter": 0.5, "gain": 0.01},
        {"dT": -2.0, "T": 45.0, "dwell": 2.0, "inst": "diviner_ch8", "m": 3, "scatter": 0.3, "gain": 0.2},
        {"dT": 1.2, "T": 80.0, "dwell": 0.13, "inst": "diviner_ch7", "m": 2, "scatter": 0.94, "gain": 0.1},
    ],
)
def test_detection_probability_matches_monte_carlo(case):
    inst = ins.PRESETS[case["inst"]]
    inst = ins.Instrument(**{**inst.as_dict(), "gain_error": case["gain"]})
    obs = ins.Observation(reference_footprints=case["m"], natural_scatter_K=case["scatter"], footprint_fraction=0.8)
    pd = float(ins.detection_probability(case["dT"], case["T"], case["dwell"], inst, obs))
    fa, pd_mc = _monte_carlo(case["dT"], case["T"], case["dwell"], inst, obs)
    assert 0.05 < pd < 0.97  # a case that tests something
    # 1e5 draws: binomial standard error <= 0.0016, so 0.01 is > 6 sigma (issue requirement)
    assert pd_mc == pytest.approx(pd, abs=0.01)
    assert fa == pytest.approx(obs.false_alarm, abs=0.01)


def test_dwell_is_the_shortest_that_reaches_the_target():
    inst = ins.PRESETS["diviner_ch9"]
    obs = ins.Observation(natural_scatter_K=0.3)
    res = ins.dwell_for_detection(-2.77, 58.1, inst, obs)
    assert res["detectable"] and res["n_samples"] > 1
    n = res["n_samples"]
    assert ins.detection_probability(-2.77, 58.1, n * inst.integration_s, inst, obs) >= 0.9
    assert ins.detection_probability(-2.77, 58.1, (n - 1) * inst.integration_s, inst, obs) < 0.9
    # with the 0.94 K scatter in both footprints no dwell is enough, and the scatter is named
    res = ins.dwell_for_detection(-2.77, 58.1, inst)
    assert not res["detectable"] and res["limiting_term"] == "natural_scatter"
    assert "not detectable at any dwell" in res["answer"] and res["pd_limit"] < 0.9


def test_bad_input_is_a_config_error():
    with pytest.raises(ConfigError, match="band"):
        ins.Band(14.0, 8.0)
    with pytest.raises(ConfigError, match="netd_ref_K"):
        ins.custom_instrument(8, 14, -1.0, 300.0)
    with pytest.raises(ConfigError, match="reference_footprints"):
        ins.Observation(reference_footprints=0)
    with pytest.raises(ConfigError, match="false_alarm"):
        ins.Observation(false_alarm=1.5)
    with pytest.raises(ConfigError, match="allowed"):
        ins.get_instrument("nope")
