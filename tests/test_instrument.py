"""Tests of crater_thermal.instrument: band radiance, band mixing, NETD(T), detection statistics."""

import math
from dataclasses import replace

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


def test_dwell_is_the_shortest_that_reaches_the_target():
    inst = ins.PRESETS["diviner_ch9"]
    stare = ins.Observation(natural_scatter_K=0.3, mode="stare")
    res = ins.dwell_for_detection(-2.77, 58.1, inst, stare)
    assert res["detectable"] and res["n_samples"] > 1 and res["mode"] == "stare" and res["passes"] is None
    n = res["n_samples"]
    assert res["dwell_s"] == res["exposure"] == pytest.approx(n * inst.integration_s)
    assert ins.detection_probability(-2.77, 58.1, n * inst.integration_s, inst, stare) >= 0.9
    assert ins.detection_probability(-2.77, 58.1, (n - 1) * inst.integration_s, inst, stare) < 0.9
    # the same in passes (Diviner's own mode): a whole number of passes, the total time in dwell_s
    passes = ins.Observation(natural_scatter_K=0.3)
    res = ins.dwell_for_detection(-2.77, 58.1, inst, passes)
    P = res["passes"]
    assert res["mode"] == "passes" and res["exposure_unit"] == "passes" and res["exposure"] == P
    assert res["dwell_s"] == pytest.approx(P * 0.128) and f"{P} passes" in res["answer"]
    assert ins.detection_probability(-2.77, 58.1, P, inst, passes) >= 0.9
    assert ins.detection_probability(-2.77, 58.1, P - 1, inst, passes) < 0.9
    # with the 0.94 K scatter in both footprints no exposure is enough, and the scatter is named
    for obs, words in (
        (ins.Observation(mode="stare"), "at any dwell"),
        (ins.Observation(), "with any number of passes"),
    ):
        res = ins.dwell_for_detection(-2.77, 58.1, inst, obs)
        assert not res["detectable"] and res["limiting_term"] == "natural_scatter"
        assert f"not detectable {words}" in res["answer"] and res["pd_limit"] < 0.9


# ------------------------------------------------------------------------ detection statistics (issue 25)

FLOOR = dict(dT_K=-2.77, T_nominal_K=58.1)  # the -86 deg thesis crater's floor at the centre night
PRESET_NAMES = list(ins.PRESETS)


def test_threshold_comes_from_the_null():
    """sigma_0 is the spread of D with every footprint nominal: the candidate's loose temperature never enters."""
    for name in PRESET_NAMES:
        inst = ins.PRESETS[name]
        obs = ins.Observation(candidate_footprints=2, reference_footprints=3, natural_scatter_K=0.5)
        e = ins.stated_exposure(inst, obs, 2.0)
        null = ins.noise_terms(58.0, 58.0, e, inst, obs)
        assert float(null["gain_error"]) == 0.0
        sigma0 = math.sqrt(sum(float(v) for v in null.values()))
        assert float(ins.sigma_null(58.0, e, inst, obs)) == pytest.approx(sigma0, rel=1e-14)
        thr = float(ins.detection_threshold(58.0, e, inst, obs))
        assert thr == pytest.approx(2.3263478740408408 * sigma0, rel=1e-12)  # z_0.99 (scipy.stats.norm.ppf)
        # no difference: P_D is the false-alarm rate exactly
        assert float(ins.detection_probability(0.0, 58.0, e, inst, obs)) == pytest.approx(0.01, rel=1e-12)


def test_old_threshold_false_alarm_rates_are_gone():
    """Issue 25's points: the candidate's NETD at the loose temperature in sigma_0 realized 0.82% (Diviner ch. 7,
    58 K, 1 s), 0.40% (microbolometer, 104 K) and 1.4e-5 (microbolometer, 58 K). With the null's sigma_0 the
    realized rate 1 - Phi(thr / sigma_true) is 1% (the Monte Carlo in test_detection_montecarlo.py checks it)."""
    from scipy.special import ndtr

    for name, T, old in (
        ("diviner_ch7", 58.0, 0.0082),
        ("microbolometer", 104.0, 0.0040),
        ("microbolometer", 58.0, 1.4e-5),
    ):
        inst, obs = ins.PRESETS[name], ins.Observation(mode="stare")
        _, T_c = ins.observed_difference(-2.77, T, inst, obs)
        true = math.sqrt(sum(float(v) for v in ins.noise_terms(T, T, 1.0, inst, obs).values()))
        # the old sigma_0: the candidate's terms at its loose temperature, without the gain term
        t_old = ins.noise_terms(T_c, T, 1.0, inst, obs)
        as_before = math.sqrt(sum(float(v) for key, v in t_old.items() if key != "gain_error"))
        z = 2.3263478740408408
        assert 1 - ndtr(z * as_before / true) == pytest.approx(old, rel=0.06)
        assert 1 - ndtr(float(ins.detection_threshold(T, 1.0, inst, obs)) / true) == pytest.approx(0.01, rel=1e-12)


@pytest.mark.parametrize("name", PRESET_NAMES + ["bolometric", "rayleigh_jeans"])
@pytest.mark.parametrize("T", [40.0, 58.0, 104.0])
def test_gain_error_acts_on_band_radiance(name, T):
    """The gain term's standard deviation is g times d(D_hat)/dg, D_hat the difference of brightness
    temperatures inverted from (1 + g) L: derived in the module docstring, checked here by inverting."""
    band = {"bolometric": ins.BOLOMETRIC, "rayleigh_jeans": ins.Band(1e4, 1e5)}.get(name)
    inst = ins.PRESETS.get(name) or ins.custom_instrument(band.lo_um, min(band.hi_um, 1e9), 0.1, 58.0)
    if band is not None:
        inst = ins.Instrument(**{**inst.as_dict(), "lo_um": band.lo_um, "hi_um": band.hi_um})
    obs = ins.Observation(mode="stare")
    mu, T_c = (float(v) for v in ins.observed_difference(-2.0, T, inst, obs))
    g = 1e-6
    L_c, L_n = ins.band_radiance(T_c, inst.band), ins.band_radiance(T, inst.band)
    bracket = (T - 10.0, T + 10.0)
    D_hat = ins.band_brightness_temperature((1 + g) * L_c, inst.band, bracket) - ins.band_brightness_temperature(
        (1 + g) * L_n, inst.band, bracket
    )
    dD_dg = float(D_hat - mu) / g
    sd = math.sqrt(float(ins.noise_terms(T_c, T, 1.0, inst, obs)["gain_error"])) / inst.gain_error
    # central-difference-free: the inversion is good to 1e-13 K, so 1e-6 x (a few K) leaves 1e-5 relative
    assert sd == pytest.approx(abs(dD_dg), rel=1e-4)
    lever = sd / abs(mu)  # ~ d(L/L')/dT: 1 for L ~ T, 1/4 for L ~ T^4, about 2/x on the Wien side
    if name == "rayleigh_jeans":
        assert lever == pytest.approx(1.0, abs=1e-3)
    elif name == "bolometric":
        assert lever == pytest.approx(0.25, abs=1e-9)
    else:
        assert 0.05 < lever < 0.95


def test_gain_lever_at_58K_as_the_issue_states():
    """d(L/L')/dT at 58 K: 0.10 (microbolometer) to 0.74 (Diviner ch. 9), by central differences of L/L'."""
    got = {}
    for name in PRESET_NAMES:
        band = ins.PRESETS[name].band
        got[name] = float((ins.gain_lever(58.001, band) - ins.gain_lever(57.999, band)) / 0.002)
    assert got["microbolometer"] == pytest.approx(0.102, abs=0.002)
    assert got["diviner_ch7"] == pytest.approx(0.256, abs=0.002)
    assert got["diviner_ch9"] == pytest.approx(0.740, abs=0.002)


def test_patch_of_k_footprints_lifts_the_scatter_cap():
    """One loose footprint: scatter caps P_D at 0.40 (m = 1) and 0.73 (m -> inf) on the floor whatever the
    exposure; a patch of k = m = 3 footprints reaches 0.90 (scatter s^2 (1/k + 1/m))."""
    inst = ins.PRESETS["diviner_ch9"]
    caps = {
        (k, m): ins.dwell_for_detection(
            **FLOOR, instrument=inst, obs=ins.Observation(candidate_footprints=k, reference_footprints=m)
        )["pd_limit"]
        for k, m in ((1, 1), (1, 10**6), (3, 3))
    }
    assert caps[(1, 1)] == pytest.approx(0.40, abs=0.01)
    assert caps[(1, 10**6)] == pytest.approx(0.73, abs=0.01)
    assert caps[(3, 3)] == pytest.approx(0.90, abs=0.005)
    obs = ins.Observation(candidate_footprints=3, reference_footprints=3)
    t = ins.noise_terms(58.1, 58.1, np.inf, inst, obs)
    assert float(t["natural_scatter"]) == pytest.approx(0.94**2 * (2 / 3), rel=1e-14)


def test_patch_area_gives_the_footprints():
    a = 240.0 * 480.0  # Diviner footprint [m2] (thesis 7.3)
    obs = ins.Observation(patch_area_m2=3.5 * a, footprint_area_m2=a)
    assert obs.candidate_footprints == 3 and obs.footprint_fraction == 1.0
    small = ins.Observation(patch_area_m2=0.25 * a, footprint_area_m2=a)
    assert small.candidate_footprints == 1 and small.footprint_fraction == pytest.approx(0.25)
    assert ins.Observation(patch_area_m2=3 * a, footprint_area_m2=a).candidate_footprints == 3
    assert obs.with_scatter(0.5).candidate_footprints == 3  # replace() keeps the resolved patch
    d = obs.as_dict([ins.PRESETS["diviner_ch9"], ins.PRESETS["microbolometer"]])
    assert d["candidate_footprints"] == 3 and d["patch_area_m2"] == 3.5 * a
    assert d["mode_by_instrument"] == {"diviner_ch9": "passes", "microbolometer": "stare"}
    assert d["pass_integration_s_by_instrument"] == {"diviner_ch9": 0.128, "microbolometer": None}
    with pytest.raises(ConfigError, match="candidate_footprints"):
        ins.Observation(patch_area_m2=3.5 * a, footprint_area_m2=a, candidate_footprints=2)
    with pytest.raises(ConfigError, match="go together"):
        ins.Observation(patch_area_m2=a)


def test_passes_and_stare():
    """Diviner presets observe in passes of 0.128 s; with a negligible 1/f floor P passes equal a stare of P
    integrations, and with a floor repeated passes (calibrated anew) average below the stare's floor."""
    ch9 = ins.PRESETS["diviner_ch9"]
    assert ins.observing_mode(ch9, ins.Observation()) == "passes"
    assert ins.observing_mode(ins.PRESETS["microbolometer"], ins.Observation()) == "stare"
    assert ins.observing_mode(ch9, ins.Observation(mode="stare")) == "stare"
    assert float(ins.exposure_seconds(52, ch9, ins.Observation())) == pytest.approx(6.656)  # "6.7 s" = 52 passes
    no_knee = ins.Instrument(**{**ch9.as_dict(), "knee_s": 1e15})
    for P in (1, 7, 52, 400):
        pp = ins.detection_probability(
            **FLOOR, exposure=P, instrument=no_knee, obs=ins.Observation(natural_scatter_K=0.2)
        )
        st = ins.detection_probability(
            **FLOOR, exposure=P * 0.128, instrument=no_knee, obs=ins.Observation(natural_scatter_K=0.2, mode="stare")
        )
        assert float(pp) == pytest.approx(float(st), rel=1e-9)
    # three integrations per pass: n = 3 P
    obs3 = ins.Observation(pass_integration_s=0.384)
    n, r = ins.averaging(10, ch9, obs3)
    assert (float(n), float(r)) == (30.0, 10.0)
    # the stare keeps its floor at infinite dwell, passes do not
    stare_inf = ins.noise_terms(58.1, 58.1, np.inf, ch9, ins.Observation(mode="stare"))
    pass_inf = ins.noise_terms(58.1, 58.1, np.inf, ch9, ins.Observation())
    assert float(stare_inf["allan_floor"]) > 0 and float(pass_inf["allan_floor"]) == 0.0
    grid = ins.exposure_grid(ch9, ins.Observation())
    assert grid[0] == 1 and np.all(grid == np.round(grid)) and np.all(np.diff(grid) > 0)


# property-based: the space of instruments, temperatures, scatter, patch sizes and exposures is large
_CASE = dict(
    name=st.sampled_from(PRESET_NAMES),
    T=st.floats(40.0, 110.0),
    dT=st.one_of(st.floats(-5.0, -0.05), st.floats(0.05, 3.0)),
    s=st.floats(0.0, 2.0),
    k=st.integers(1, 5),
    m=st.integers(1, 5),
    steps=st.integers(1, 2000),
    more=st.integers(1, 2000),
)


def _exposure(inst, obs, steps):
    """``steps`` integrations of dwell (stare) or ``steps`` passes."""
    return steps if ins.observing_mode(inst, obs) == "passes" else steps * inst.integration_s


@settings(max_examples=150, deadline=None)
@given(**_CASE)
def test_pd_grows_with_exposure_k_and_m(name, T, dT, s, k, m, steps, more):
    """Where P_D >= 1/2 (the module docstring's regime; 0.9 is the target) P_D does not fall with a longer
    exposure, a larger patch (k) or more references (m); where the candidate is no noisier than the reference
    (warmer, NETD(T_c) <= NETD(T_n)) it does not fall anywhere."""
    inst = ins.PRESETS[name]
    obs = ins.Observation(candidate_footprints=k, reference_footprints=m, natural_scatter_K=s)
    e1, e2 = _exposure(inst, obs, steps), _exposure(inst, obs, steps + more)
    pd = float(ins.detection_probability(dT, T, e1, inst, obs))
    quieter = float(inst.netd(ins.observed_difference(dT, T, inst, obs)[1])) <= float(inst.netd(T))
    if pd >= 0.5 or quieter:
        assert float(ins.detection_probability(dT, T, e2, inst, obs)) >= pd - 1e-12
    if pd >= 0.5:
        for bigger in (dict(candidate_footprints=k + 1), dict(reference_footprints=m + 1)):
            o = replace(obs, **bigger)
            assert float(ins.detection_probability(dT, T, _exposure(inst, o, steps), inst, o)) >= pd - 1e-12


@settings(max_examples=100, deadline=None)
@given(**_CASE)
def test_pd_tends_to_the_false_alarm_rate(name, T, dT, s, k, m, steps, more):
    """As dT -> 0 the alternative becomes the null: P_D -> the false-alarm rate (1%)."""
    inst = ins.PRESETS[name]
    obs = ins.Observation(candidate_footprints=k, reference_footprints=m, natural_scatter_K=s)
    e = _exposure(inst, obs, steps)
    tiny = math.copysign(1e-7, dT)
    assert float(ins.detection_probability(tiny, T, e, inst, obs)) == pytest.approx(0.01, abs=1e-5)
    assert float(ins.detection_probability(0.0, T, e, inst, obs)) == pytest.approx(0.01, rel=1e-12)


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
    with pytest.raises(ConfigError, match="mode"):
        ins.Observation(mode="orbit")
    with pytest.raises(ConfigError, match="passes"):
        ins.Observation(passes=0)
    with pytest.raises(ConfigError, match="candidate_footprints"):
        ins.Observation(candidate_footprints=1.5)
    with pytest.raises(ConfigError, match="pass_integration_s"):
        ins.Observation(pass_integration_s=-1.0)
