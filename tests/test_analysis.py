"""Tests of crater_thermal.analysis: masks, regions, differences, statistics (instrument: test_instrument.py)."""

import numpy as np
import pytest

from crater_thermal import analysis as an
from crater_thermal import io, regions
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
    assert regions.night_mask(s).tolist() == [True, False, False]
    assert regions.day_mask(s).tolist() == [False, True, True]


def test_shadow_mask_is_zero_direct_flux():
    e = np.array([[0.0, 3.2], [10.0, 0.0]])
    assert regions.shadow_mask(e).tolist() == [[True, False], [False, True]]


def test_synthetic_night_is_where_sun_below_horizon(pair):
    run, _ = pair
    night = regions.night_mask(run)
    z = run["sun_direction"].values[:, 2]
    assert np.array_equal(night, z < 0)
    # no direct sunlight anywhere at night (Sun's centre below the horizon: the synthetic
    # illumination uses a point Sun, so no facet can be lit)
    assert regions.shadow_mask(run)[night].all()
    # both occur over 1.5 lunar days at -86 deg
    assert 0.2 < night.mean() < 0.8


# ----------------------------------------------------------------------------------- regions

META = dict(kind="crater", floor_radius_m=100.0, rim_radius_m=400.0, rim_width_m=100.0)


def test_region_classes_hand_computed_south():
    c = np.array(
        [
            [0.0, 0.0, -50.0],  # axis -> floor
            [0.0, -200.0, 0.0],  # r=200 < mid 250, on the south (pole) side -> lower wall poleward
            [0.0, 300.0, 0.0],  # r=300 in (250, 400], north side -> upper wall equatorward
            [0.0, -390.0, 0.0],  # upper wall, pole side
            [450.0, -10.0, 0.0],  # r~450 in (400, 500] -> rim, pole side
            [-10.0, 450.0, 0.0],  # rim, equator side
            [0.0, 600.0, 0.0],  # beyond 500 -> surround
        ]
    )
    got = regions.classify_regions(c, META, lat_deg=-86.0).tolist()
    assert got == [
        "floor",
        "lower_wall_poleward",
        "upper_wall_equatorward",
        "upper_wall_poleward",
        "rim_poleward",
        "rim_equatorward",
        "surround",
    ]


def test_region_classes_north_flips_sides():
    c = np.array([[0.0, -200.0, 0.0], [0.0, 300.0, 0.0]])
    got = regions.classify_regions(c, META, lat_deg=80.0).tolist()
    assert got == ["lower_wall_equatorward", "upper_wall_poleward"]


def test_region_rim_width_defaults_to_pike():
    meta = dict(floor_radius_m=100.0, rim_radius_m=5000.0)
    # D = 10 km: rim width 0.257 * 10^1.011 km = 2.6303 km (hand: 10^1.011 = 10.2565)
    assert regions.rim_width_m(meta) == pytest.approx(2636.0, abs=1.0)


def test_region_bowl_and_flat_meta():
    c = np.array([[0.0, 0.0, -10.0], [0.0, -300.0, -5.0], [0.0, 450.0, 0.0]])
    # bowl, D = 1000 m: no floor; wall split at r = 250; r = 450 is upper wall (north side, equatorward)
    got = regions.classify_regions(c, {"kind": "bowl", "diameter_m": 1000.0}, lat_deg=-86.0).tolist()
    assert got == ["lower_wall_equatorward", "upper_wall_poleward", "upper_wall_equatorward"]
    assert regions.classify_regions(c, {"kind": "flat"}, lat_deg=-86.0).tolist() == ["surround"] * 3


def test_region_needs_meta_radii():
    with pytest.raises(FluxFileError, match="floor_radius_m"):
        regions.classify_regions(np.zeros((2, 3)), {"rim_radius_m": 10.0}, -86.0)
    with pytest.raises(ConfigError, match="wall_split"):
        regions.classify_regions(np.zeros((2, 3)), META, -86.0, wall_split=1.5)


def test_poleward_upper_wall_is_the_sunlit_one(pair):
    """At -86 deg the wall on the pole side faces the equator/Sun (docs/physics.md 'Where in the crater')."""
    run, _ = pair
    reg = regions.regions_of(run)
    lit = ~regions.shadow_mask(run)
    pole = lit[:, reg == "upper_wall_poleward"].mean()
    eq = lit[:, reg == "upper_wall_equatorward"].mean()
    assert pole > 3 * eq
    assert not lit[:, reg == "floor"].any()  # Sun <= ~5.5 deg: the floor of a d/D=0.2 bowl stays dark
    for r in regions.REGIONS:
        assert (reg == r).sum() > 0


# ------------------------------------------------------------------------------- differences


def test_differences_are_profile_minus_nominal(pair):
    run, rep = pair
    d = an.profile_differences(run, rep)
    labels = an.profile_labels(rep)
    assert "1300/1800" not in d and set(d) == set(labels) - {"1300/1800"}
    T = rep["surface_temperature"].values
    assert np.array_equal(d["800/1100"], T[labels.index("800/1100")] - T[labels.index("1300/1800")])
    night = regions.night_mask(run)
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
    assert st["floor"]["q1_K"] == pytest.approx(-2.0)  # numpy linear: -3 + 0.25*(1 - -3)
    assert st["floor"]["q3_K"] == pytest.approx(2.75)  # 2 + 0.75*(3-2)
    assert st["floor"]["frac_above_threshold"] == pytest.approx(4 / 6)  # |.|>2.5: -3,-3,3,5
    assert st["surround"]["median_K"] == pytest.approx(20.0)
    assert st["rim_poleward"]["n"] == 0 and st["rim_poleward"]["median_K"] is None


def test_density_grid(pair):
    run, rep = pair
    d = an.profile_differences(run, rep)
    night = regions.night_mask(run)
    reg = regions.regions_of(run)
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
        io.check_pair(run, bad)
    with pytest.raises(FluxFileError, match="time axis"):
        io.check_pair(run, rep.isel(time=slice(0, 10)))
    with pytest.raises(FluxFileError, match="sun_direction"):
        io.check_pair(run.drop_vars("sun_direction"), rep)


def test_latitude_statistics(pair):
    run, rep = pair
    run2 = make_run(lat_deg=-80.0, n_lunar_days=1.0, n_rings=8)
    out = an.latitude_statistics([(run, rep), (run2, make_replay(run2))])
    assert set(out) == {-86.0, -80.0}
    assert out[-80.0]["profile"] == "800/1100"
    assert set(out[-86.0]["night"]) == set(regions.region_names(-86.0))
    assert out[-86.0]["night_definition"] == "dark"  # the default since issue 25 (was "facet")
    centre = an.latitude_statistics([(run, rep)], night_definition="centre", region_names=["floor"])
    assert list(centre[-86.0]["night"]) == ["floor"]


def test_local_solar_time_from_sun_direction():
    # south pole: noon with the Sun due north, 18 h with it in the west, 6 h in the east
    s = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(an.local_solar_time_h(s, -90.0), [12.0, 18.0, 6.0, 0.0], atol=1e-12)
    # equator: Sun at the zenith is noon, on the eastern horizon 6 h; north pole: noon with the Sun south
    np.testing.assert_allclose(an.local_solar_time_h(np.array([[0, 0, 1.0], [1.0, 0, 0]]), 0.0), [12.0, 6.0])
    assert float(an.local_solar_time_h(np.array([[0.0, -1.0, 0.0]]), 90.0)[0]) == pytest.approx(12.0)


def test_lat_deg_is_required_never_guessed():
    """A run without ``lat_deg`` is refused (it used to be analysed as if at -90 deg in some places)."""
    run = make_run()
    assert io.latitude_deg(run) == -86.0
    del run.attrs["lat_deg"]
    for analyse in (regions.region_masks, regions.regions_of):
        with pytest.raises(FluxFileError, match="lat_deg"):
            analyse(run)
    run.attrs["lat_deg"] = 95.0
    with pytest.raises(FluxFileError, match="outside"):
        io.latitude_deg(run)
