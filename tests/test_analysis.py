"""Tests of crater_thermal.analysis: masks, regions, differences, statistics, instrument model."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crater_thermal import analysis as an
from crater_thermal.errors import ConfigError, FluxFileError

from synthetic import make_replay, make_run


@pytest.fixture(scope="module")
def pair():
    run = make_run(lat_deg=-86.0, n_lunar_days=1.5, n_rings=10)
    return run, make_replay(run)


# ------------------------------------------------------------------------------------- masks


def test_night_day_mask_by_sun_elevation():
    s = np.array([[0.0, 0.99, -0.1], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    assert an.night_mask(s).tolist() == [True, False, False]
    assert an.day_mask(s).tolist() == [False, True, True]


def test_shadow_mask_is_zero_direct_flux():
    e = np.array([[0.0, 3.2], [10.0, 0.0]])
    assert an.shadow_mask(e).tolist() == [[True, False], [False, True]]


def test_synthetic_night_is_where_sun_below_horizon(pair):
    run, _ = pair
    night = an.night_mask(run)
    z = run["sun_direction"].values[:, 2]
    assert np.array_equal(night, z < 0)
    # no direct sunlight anywhere at night (Sun's centre below the horizon: the synthetic
    # illumination uses a point Sun, so no facet can be lit)
    assert an.shadow_mask(run)[night].all()
    # both occur over 1.5 lunar days at -86 deg
    assert 0.2 < night.mean() < 0.8


# ----------------------------------------------------------------------------------- regions

META = dict(kind="crater", floor_radius_m=100.0, rim_radius_m=400.0, rim_width_m=100.0)


def test_region_classes_hand_computed_south():
    c = np.array([
        [0.0, 0.0, -50.0],     # axis -> floor
        [0.0, -200.0, 0.0],    # r=200 < mid 250, on the south (pole) side -> lower wall poleward
        [0.0, 300.0, 0.0],     # r=300 in (250, 400], north side -> upper wall equatorward
        [0.0, -390.0, 0.0],    # upper wall, pole side
        [450.0, -10.0, 0.0],   # r~450 in (400, 500] -> rim, pole side
        [-10.0, 450.0, 0.0],   # rim, equator side
        [0.0, 600.0, 0.0],     # beyond 500 -> surround
    ])
    got = an.classify_regions(c, META, lat_deg=-86.0).tolist()
    assert got == ["floor", "lower_wall_poleward", "upper_wall_equatorward", "upper_wall_poleward",
                   "rim_poleward", "rim_equatorward", "surround"]


def test_region_classes_north_flips_sides():
    c = np.array([[0.0, -200.0, 0.0], [0.0, 300.0, 0.0]])
    got = an.classify_regions(c, META, lat_deg=80.0).tolist()
    assert got == ["lower_wall_equatorward", "upper_wall_poleward"]


def test_region_rim_width_defaults_to_pike():
    meta = dict(floor_radius_m=100.0, rim_radius_m=5000.0)
    # D = 10 km: rim width 0.257 * 10^1.011 km = 2.6303 km (hand: 10^1.011 = 10.2565)
    assert an.rim_width_m(meta) == pytest.approx(2636.0, abs=1.0)


def test_region_bowl_and_flat_meta():
    c = np.array([[0.0, 0.0, -10.0], [0.0, -300.0, -5.0], [0.0, 450.0, 0.0]])
    # bowl, D = 1000 m: no floor; wall split at r = 250; r = 450 is upper wall (north side, equatorward)
    got = an.classify_regions(c, {"kind": "bowl", "diameter_m": 1000.0}, lat_deg=-86.0).tolist()
    assert got == ["lower_wall_equatorward", "upper_wall_poleward", "upper_wall_equatorward"]
    assert an.classify_regions(c, {"kind": "flat"}, lat_deg=-86.0).tolist() == ["surround"] * 3


def test_region_needs_meta_radii():
    with pytest.raises(FluxFileError, match="floor_radius_m"):
        an.classify_regions(np.zeros((2, 3)), {"rim_radius_m": 10.0}, -86.0)
    with pytest.raises(ConfigError, match="wall_split"):
        an.classify_regions(np.zeros((2, 3)), META, -86.0, wall_split=1.5)


def test_poleward_upper_wall_is_the_sunlit_one(pair):
    """At -86 deg the wall on the pole side faces the equator/Sun (PHYSICS.md 'Where in the crater')."""
    run, _ = pair
    reg = an.regions_of(run)
    lit = ~an.shadow_mask(run)
    pole = lit[:, reg == "upper_wall_poleward"].mean()
    eq = lit[:, reg == "upper_wall_equatorward"].mean()
    assert pole > 3 * eq
    assert not lit[:, reg == "floor"].any()  # Sun <= ~5.5 deg: the floor of a d/D=0.2 bowl stays dark
    for r in an.REGIONS:
        assert (reg == r).sum() > 0


# ------------------------------------------------------------------------------- differences


def test_differences_are_profile_minus_nominal(pair):
    run, rep = pair
    d = an.profile_differences(run, rep)
    labels = an.profile_labels(rep)
    assert "1300/1800" not in d and set(d) == set(labels) - {"1300/1800"}
    T = rep["surface_temperature"].values
    assert np.array_equal(d["800/1100"], T[labels.index("800/1100")] - T[labels.index("1300/1800")])
    night = an.night_mask(run)
    # loose regolith is colder at night in the synthetic replay (as in the thesis)
    assert np.median(d["800/1100"][night]) < -1.0
    assert an.loose_label(rep, "1300/1800") == "800/1100"
    assert an.rock_label(rep) == "rock"


def test_region_statistics_hand_computed():
    dT = np.array([[1.0, 10.0, -3.0], [2.0, 20.0, -3.0], [3.0, 30.0, 5.0], [4.0, 40.0, 7.0]])
    tm = np.array([True, True, True, False])
    reg = np.array(["floor", "surround", "floor"])
    st = an.region_statistics(dT, tm, reg, threshold_K=2.5, region_names=("floor", "surround", "rim_poleward"))
    # floor samples at selected times: 1, 2, 3, -3, -3, 5 -> sorted -3 -3 1 2 3 5, median 1.5
    assert st["floor"]["median_K"] == pytest.approx(1.5)
    assert st["floor"]["q1_K"] == pytest.approx(-2.0)   # numpy linear: -3 + 0.25*(1 - -3)
    assert st["floor"]["q3_K"] == pytest.approx(2.75)   # 2 + 0.75*(3-2)
    assert st["floor"]["frac_above_threshold"] == pytest.approx(4 / 6)  # |.|>2.5: -3,-3,3,5
    assert st["surround"]["median_K"] == pytest.approx(20.0)
    assert st["rim_poleward"]["n"] == 0 and st["rim_poleward"]["median_K"] is None


def test_density_grid(pair):
    run, rep = pair
    d = an.profile_differences(run, rep)
    night = an.night_mask(run)
    reg = an.regions_of(run)
    tops, bottoms, grid = an.density_grid_medians(rep, d, night, reg == "floor", nominal="1300/1800")
    it, ib = list(tops).index(1300.0), list(bottoms).index(1800.0)
    assert grid[it, ib] == 0.0
    il = list(tops).index(800.0), list(bottoms).index(1100.0)
    assert grid[il] == pytest.approx(np.median(d["800/1100"][night][:, reg == "floor"]))
    assert np.isnan(grid[list(tops).index(1800.0), list(bottoms).index(1100.0)])  # top > bottom: not replayed


def test_check_pair_rejects_foreign_replay(pair):
    run, rep = pair
    bad = rep.copy()
    bad.attrs["mesh_hash"] = "0123456789abcdef"
    with pytest.raises(FluxFileError, match="mesh_hash"):
        an.check_pair(run, bad)
    with pytest.raises(FluxFileError, match="time axis"):
        an.check_pair(run, rep.isel(time=slice(0, 10)))
    with pytest.raises(FluxFileError, match="sun_direction"):
        an.check_pair(run.drop_vars("sun_direction"), rep)


def test_latitude_statistics(pair):
    run, rep = pair
    run2 = make_run(lat_deg=-80.0, n_lunar_days=1.0, n_rings=8)
    out = an.latitude_statistics([(run, rep), (run2, make_replay(run2))])
    assert set(out) == {-86.0, -80.0}
    assert out[-80.0]["profile"] == "800/1100"
    assert set(out[-86.0]["night"]) == set(an.REGIONS)


# -------------------------------------------------------------------------- instrument model


def test_netd_equals_reference_at_reference_temperature():
    inst = an.Instrument()
    assert float(an.netd(50.0, inst)) == pytest.approx(2.0, rel=1e-12)


def test_netd_narrow_band_matches_hand_planck_ratio():
    # a 0.01%-wide band at 200 um: the ratio is that of the monochromatic dB/dT
    inst = an.Instrument(band_um=(200.0, 200.02), netd_ref_K=2.0, t_ref_K=50.0)
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    lam = 200.01e-6

    def dbdt(T):
        x = h * c / (lam * k * T)
        return x * math.exp(x) / (T * (math.exp(x) - 1) ** 2)

    hand = 2.0 * dbdt(50.0) / dbdt(30.0)
    # band width 1e-4: the ratio varies across it by < 1e-4 relative
    assert float(an.netd(30.0, inst)) == pytest.approx(hand, rel=1e-4)
    assert hand > 2.0  # colder scenes are noisier


def test_netd_rayleigh_jeans_band_is_temperature_independent():
    # 1-10 cm at 30-50 K: x = hc/(lambda k T) < 0.05, dB/dT ~ 2ck/lambda^4 (1 - x^2/12): < 1e-3 change
    inst = an.Instrument(band_um=(1e4, 1e5))
    assert float(an.netd(30.0, inst)) == pytest.approx(2.0, rel=1e-3)


def test_netd_diviner_band_increases_when_colder():
    v = an.netd(np.array([25.0, 50.0, 100.0]))
    assert v[0] > v[1] > v[2]


def test_sqrt_n_averaging_hand():
    # one minute at 128 ms: n = floor(60 / 0.128) = floor(468.75) = 468; sqrt(468) = 21.633
    assert int(an.n_samples(60.0, 0.128)) == 468
    assert float(an.averaged_netd(2.0, 60.0, 0.128)) == pytest.approx(2.0 / 21.6333, rel=1e-4)
    assert math.sqrt(468) > 20  # thesis: "more than a factor of 20"
    assert int(an.n_samples(0.128 * 3, 0.128)) == 3   # exact multiples are not rounded down
    assert int(an.n_samples(0.05, 0.128)) == 1        # shorter than one integration: one sample
    with pytest.raises(ConfigError, match="integration_s"):
        an.n_samples(1.0, 0.0)


def test_pixel_mixing_eq_8_2():
    # hand: 0.5*60^4 + 0.5*40^4 = 0.5*(12 960 000 + 2 560 000) = 7 760 000; ^(1/4) = 52.779 K
    assert float(an.mixed_temperature(60.0, 40.0, 0.5)) == pytest.approx(52.779, abs=1e-3)
    assert float(an.mixed_temperature(60.0, 40.0, 1.0)) == pytest.approx(60.0)
    assert float(an.mixed_temperature(60.0, 40.0, 0.0)) == pytest.approx(40.0)
    # radiance-weighted: the mix leans towards the warmer material (above the arithmetic mean)
    assert float(an.mixed_temperature(60.0, 40.0, 0.5)) > 50.0
    with pytest.raises(ConfigError, match="fraction_a"):
        an.mixed_temperature(60.0, 40.0, 1.2)


@settings(max_examples=60, deadline=None)
@given(dT=st.floats(-20.0, 20.0), T_nom=st.floats(25.0, 300.0), fraction=st.floats(0.05, 1.0),
       offset=st.floats(0.0, 10.0))
def test_calibration_offset_does_not_enter_detectability(dT, T_nom, fraction, offset):
    """Thesis 7.3: an absolute calibration offset shifts both scenes alike, so the detectability of a
    difference does not depend on it; what is observed is the Eq. 8.2 pixel mix minus nominal."""
    a = an.detectability(dT, T_nom, an.Instrument(calibration_offset_K=offset), footprint_fraction=fraction)
    b = an.detectability(dT, T_nom, an.Instrument(calibration_offset_K=0.0), footprint_fraction=fraction)
    assert a["detectable"] == b["detectable"] and a["n_samples"] == b["n_samples"]
    if T_nom + dT > 0:
        mixed = (fraction * (T_nom + dT) ** 4 + (1 - fraction) * T_nom**4) ** 0.25
        # float64 rounding of sums of T ~ 300 K and offsets <= 10 K: ~1e-13 K
        assert a["dT_observed_K"] == pytest.approx(mixed - T_nom, abs=1e-9)
        assert b["dT_observed_K"] == pytest.approx(mixed - T_nom, abs=1e-9)


def test_detectability_hand():
    inst = an.Instrument()
    res = an.detectability(-2.5, 50.0, inst)
    assert res["detectable"] and res["T_scene_K"] == pytest.approx(47.5)
    e = float(an.netd(47.5, inst))
    n = math.ceil((3 * e / 2.5) ** 2)
    assert res["n_samples"] == n and res["dwell_time_s"] == pytest.approx(n * 0.128)
    # below the 0.94 K natural scatter: never, whatever the dwell
    low = an.detectability(0.5, 50.0, inst)
    assert not low["detectable"] and low["dwell_time_s"] is None and "scatter" in low["reason"]
    cold = an.detectability(-3.0, 19.0, inst)
    assert not cold["detectable"] and "20" in cold["reason"]
    # a half-filled pixel (Eq. 8.2) shrinks the observed difference, so it needs longer
    mixed = an.detectability(-4.0, 50.0, inst, footprint_fraction=0.5)
    full = an.detectability(-4.0, 50.0, inst)
    assert abs(mixed["dT_observed_K"]) < abs(full["dT_observed_K"])
    assert mixed["dwell_time_s"] >= full["dwell_time_s"]


def test_detectability_scatter_in_quadrature_hand():
    inst = an.Instrument(scatter_in_quadrature=True)
    # 3 x 0.94 = 2.82 K: a 2.5 K difference can never reach 3 sigma
    assert not an.detectability(-2.5, 50.0, inst)["detectable"]
    res = an.detectability(-4.0, 50.0, inst)
    e = float(an.netd(46.0, inst))
    n = math.ceil(9 * e**2 / (16.0 - 2.82**2))  # hand: k^2 NETD^2 / (dT^2 - (k sc)^2)
    assert res["detectable"] and res["n_samples"] == n
    # and then the criterion holds: 3 sqrt(NETD^2/n + 0.94^2) <= 4 K
    assert 3 * math.sqrt(e**2 / n + 0.94**2) <= 4.0


def test_instrument_validation():
    with pytest.raises(ConfigError, match="netd_ref_K"):
        an.Instrument(netd_ref_K=-1.0)
    with pytest.raises(ConfigError, match="band_um"):
        an.Instrument(band_um=(400.0, 100.0))
