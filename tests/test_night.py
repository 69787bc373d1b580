"""The "dark" night (issue 25, item 1): no sunlight at all, direct or scattered, for min_dark_hours,
with the least-lit fallback where a facet is never dark that long."""

import numpy as np
import pytest

from crater_thermal import analysis as an
from crater_thermal import api, regions
from crater_thermal.errors import ConfigError
from crater_thermal.materials import DensityExtrapolationWarning

from synthetic import make_run

# The thesis crater (10 km, 502 facets, -86 deg, 4-h steps, exact scattering) over two lunar days after a
# one-lunar-day periodic spin-up: about 10 s of run and replay on one core.
CASE86 = """
name = "night86"
[crater]
kind = "crater"
diameter_km = 10.0
facets = 502
surround_km = 0.0
[location]
lat_deg = -86.0
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "2019-03-01"
spinup = "periodic"
spinup_days = 29.53
periodic_tol_K = 0.01
[steps]
flux_step_hours = 4.0
[surface]
albedo = 0.12
emissivity = 0.98
property_set = "apollo"
geothermal_flux_W_m2 = 0.033
nominal_profile = "1300/1800"
[scattering]
method = "exact"
[replay]
profiles = ["1300/1800", "800/1100"]
[output]
checkpoint_interval_steps = 0
"""


@pytest.fixture(scope="module")
def crater86(tmp_path_factory):
    """(run, floor mask, nominal T (nt, nf) [K], loose - nominal (nt, nf) [K]) of the -86 deg thesis crater."""
    d = tmp_path_factory.mktemp("night86")
    (d / "case.toml").write_text(CASE86)
    run = api.run(d / "case.toml", d / "run.nc", progress=False)
    with pytest.warns(DensityExtrapolationWarning):  # 800 kg m-3 lies below Table 7.2, as in the thesis
        rep = api.replay(run, ["1300/1800", "800/1100"], out=d / "replay.nc", progress=False)
    T = an.nominal_temperature(run, rep)
    dT = an.profile_temperature(rep, "800/1100") - T
    floor = regions.region_masks(run)["floor"]
    assert floor.sum() >= 3
    return run, floor, T, dT


def test_floor_night_median_agrees_with_centre_night(crater86):
    """The floor is a PSR: by "dark" its night median equals the thesis's centre-night one within the
    discretization of the two definitions, while the direct-only "facet" night (all year) does not.

    The dark night of a floor facet starts when the last sunlit wall in its view goes dark, plus
    min_dark_hours (24 h), plus up to one 4-h step (fluxes are linear between samples); it ends at the
    first sample in which a wall in view is lit, which lies at most one step from the centre's sunrise
    (the Sun's limb reaches the wall's highest facet, half a facet below the crest, within a step). The two
    nights' edges therefore differ by at most dt = 24 h + 2 steps = 32 h per edge, during which the floor
    changes temperature at its night-time rate |dT/dt| (median over the centre-night samples, measured
    here: about 0.03 K/h), so the medians may differ by |dT/dt| x dt (about 1 K). Measured: 0.56 K here,
    0.38 K over the thesis year (57.70 K dark vs 58.08 K centre; 64.98 K by "facet").
    """
    run, floor, T, _ = crater86
    t_h = regions.seconds_of(run["time"].values) / 3600.0
    step_h = float(np.median(np.diff(t_h)))
    centre = regions.night_mask(run)
    rate = np.abs(np.gradient(T[:, floor], t_h, axis=0))[centre]
    tol_K = float(np.median(rate)) * (regions.MIN_DARK_HOURS + 2 * step_h)
    med = {d: an.masked_median(T, regions.night_day_masks(run, d)[0], floor) for d in ("dark", "centre", "facet")}
    assert regions.night_selection(run).fallback[floor].sum() == 0  # the -86 deg floor is dark for days
    assert abs(med["dark"] - med["centre"]) <= tol_K, (med, tol_K)
    # the defect: the direct-only night counts the weeks of scattered light and IR from sunlit walls
    assert med["facet"] - med["centre"] > 3 * tol_K, (med, tol_K)


def test_night_quartiles_keep_one_sign(crater86):
    """Loose regolith (lower thermal inertia) is colder than nominal at night: both quartiles of
    loose - nominal over the floor's dark night are negative. With the direct-only "facet" night the third
    quartile is positive: part of that "night" is the floor's scattered-light day, when loose is warmer."""
    run, floor, _, dT = crater86
    dark = an.masked_statistics(dT, regions.night_day_masks(run, "dark")[0], {"floor": floor})["floor"]
    facet = an.masked_statistics(dT, regions.night_day_masks(run, "facet")[0], {"floor": floor})["floor"]
    assert dark["q1_K"] < 0 and dark["q3_K"] < 0, dark
    assert facet["q1_K"] < 0 < facet["q3_K"], facet  # the defect of the old default


def test_dark_night_hand_computed():
    # 4-h samples. Facet 0: scattered light 0.5 W m-2 at sample 3 only (no direct light): dark night from
    # 24 h + one step later, as for direct light. Facet 1: never any light. Facet 2: scattered light below the
    # threshold (2e-4 W m-2) throughout: dark.
    t = np.arange(16) * 4 * 3600.0
    inc = np.zeros((16, 3))
    inc[3, 0] = 0.5
    inc[:, 2] = 2e-4
    direct = np.zeros_like(inc)
    night, fallback = regions.dark_night_mask(inc, direct, t, 24.0)
    assert night[:, 0].tolist() == [False] * 10 + [True] * 6
    assert night[:, 1].tolist() == [False] * 6 + [True] * 10
    assert night[:, 2].tolist() == [False] * 6 + [True] * 10
    assert not fallback.any()
    # the direct-only night does not see scattered light
    assert regions.facet_night_mask(direct, t, 24.0)[:, 0].tolist() == [False] * 6 + [True] * 10
    with pytest.raises(ConfigError):
        regions.dark_night_mask(inc, direct, t, 24.0, threshold_W_m2=-1.0)
    with pytest.raises(ConfigError):
        regions.dark_night_mask(inc, direct, t, 24.0, fallback_fraction=0.0)


def test_fallback_takes_least_lit_samples_never_lit_ones():
    """A facet never dark for 24 h gets the 10% of the record with the least sunlight among its samples
    without direct sunlight for 24 h, and the flag; deterministic (ties: earliest first)."""
    rng = np.random.default_rng(7)
    nt = 120
    t = np.arange(nt) * 4 * 3600.0
    inc = np.zeros((nt, 3))
    direct = np.zeros((nt, 3))
    # facet 0: scattered light always above the threshold, smallest on a known set of samples
    inc[:, 0] = 0.5 + rng.uniform(0.0, 1.0, nt)
    least = np.arange(30, nt, 7)[:12]  # 12 = 10% of 120 samples, after the first 24 h
    inc[least, 0] = 0.01 + 1e-3 * np.arange(12)
    # facet 1: directly lit (and brightly) in samples 100..109; its least scattered samples are lit ones
    inc[:, 1] = 0.3 + rng.uniform(0.0, 1.0, nt)
    direct[100:110, 1] = 300.0
    inc[100:110, 1] = 1e-4  # absurdly dark while "directly lit": the fallback must still refuse them
    # facet 2: dark for most of the record
    inc[:10, 2] = 1.0
    night, fallback = regions.dark_night_mask(inc, direct, t, 24.0, fallback_fraction=0.1)
    assert fallback.tolist() == [True, True, False]
    assert np.flatnonzero(night[:, 0]).tolist() == least.tolist()
    # facet 1: 12 samples, none directly lit nor within 24 h + one step after direct light, and no
    # candidate left out has less sunlight than one chosen
    cand = regions.facet_night_mask(direct, t, 24.0)[:, 1]
    chosen = night[:, 1]
    assert chosen.sum() == 12 and not (chosen & ~cand).any()
    assert not chosen[100:117].any()
    assert inc[chosen, 1].max() <= inc[cand & ~chosen, 1].min()
    # deterministic, and ties broken by time
    again, _ = regions.dark_night_mask(inc, direct, t, 24.0, fallback_fraction=0.1)
    assert np.array_equal(night, again)
    flat = np.full((nt, 1), 0.5)
    pick = regions.least_lit_mask(flat, np.ones((nt, 1), bool), 0.1)
    assert np.flatnonzero(pick[:, 0]).tolist() == list(range(12))


def test_fallback_on_a_polar_synthetic_run_is_flagged():
    """A synthetic run whose floor always receives scattered light (a sunlit rim, as at Shackleton):
    the floor falls back, the selection says so, and its night has no directly lit sample."""
    run = make_run(lat_deg=-89.7, n_lunar_days=1.5, n_rings=8)
    floor = regions.region_masks(run)["floor"]
    inc = run["solar_incident"].values.copy()
    inc[:, floor] += 0.05 * (1.0 + np.sin(np.arange(inc.shape[0]) / 7.0))[:, None] + 1e-2
    run["solar_incident"] = (("time", "facet"), inc)
    sel = regions.night_selection(run)
    assert sel.definition == "dark" and sel.fallback_fraction == regions.NIGHT_FALLBACK_FRACTION
    assert sel.threshold_W_m2 == regions.DARK_THRESHOLD_W_M2
    assert sel.fallback[floor].all()
    k = int(np.ceil(regions.NIGHT_FALLBACK_FRACTION * inc.shape[0]))
    assert (sel.night[:, floor].sum(axis=0) <= k).all() and sel.night[:, floor].any()
    assert not (sel.night & (run["solar_direct"].values > 0)).any()
    assert not (sel.night & sel.day).any()
