"""Per-facet night, crater regions that hold what their names say, illumination/slope/facing classes,
and the incidence-dependent albedo (issue 10, items 4-6)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from crater_thermal import config, ephemeris, geometry, illumination, io, raytrace, regions, runner, simulate, sunlight
from crater_thermal.errors import ConfigError

from synthetic import make_run


@pytest.fixture(scope="module")
def crater86():
    """Direct sunlight on the thesis crater (10 km, 502 facets) at -86 deg over 40 days of 2019, 4-h steps.

    Only illumination (no conduction: the masks need solar_direct, the Sun and the mesh), so it is fast.
    The dataset has the run schema, with zero temperatures and IR.
    """
    mesh = geometry.crater_mesh(10.0, n_facets=502)
    tracer = raytrace.RayTracer(mesh)
    times = ephemeris.time_grid("2019-01-01", "2019-02-10", 4 * 3600.0)
    sun, dist = ephemeris.sun_in_crater_frame(times, -86.0, 0.0)
    direct = illumination.direct_irradiance(mesh, tracer, sun, dist, disk=illumination.sun_disk())
    zeros = np.zeros_like(direct)
    return io.run_dataset(
        mesh,
        times,
        solar_incident=direct,
        ir_incident=zeros,
        solar_direct=direct,
        surface_temperature=zeros + 50.0,
        sun_direction=sun,
        sun_distance_au=dist / 1.495978707e11,
        attrs={"lat_deg": -86.0, "albedo": 0.12, "emissivity": 0.98},
    )


# ----------------------------------------------------------------------------------- per-facet night


def test_facet_night_hand_computed():
    # 4-h samples; the Sun is below the crater centre's horizon throughout (centre "night" everywhere).
    # Facet 0 is lit at sample 3, facet 1 never, facet 2 at samples 0..1.
    t = np.arange(16) * 4 * 3600.0
    e = np.zeros((16, 3))
    e[3, 0] = 2.5
    e[0:2, 2] = 100.0
    night = regions.facet_night_mask(e, t, min_dark_hours=24.0)
    # facet 0: lit at sample 3, light lasts (linear fluxes) until sample 4; 24 h of darkness at sample 10
    assert night[:, 0].tolist() == [False] * 10 + [True] * 6
    # facet 1: the history before the record counts as lit, so dark for 24 h from sample 6 on
    assert night[:, 1].tolist() == [False] * 6 + [True] * 10
    # facet 2: dark from sample 2, night from sample 8
    assert night[:, 2].tolist() == [False] * 8 + [True] * 8
    # no darkness required: every unlit sample is night
    assert np.array_equal(regions.facet_night_mask(e, t, 0.0), e <= 0)
    with pytest.raises(ConfigError):
        regions.facet_night_mask(e, t, -1.0)


def test_facet_lit_at_centre_night_is_excluded(crater86):
    run = crater86
    centre_night = regions.night_mask(run)
    lit = regions.lit_mask(run)
    night, day = regions.night_day_masks(run, "facet")
    # at -86 deg the outer flank on the pole side is lit while the Sun is below the crater centre's horizon
    lit_at_centre_night = lit & centre_night[:, None]
    assert lit_at_centre_night.any()
    assert not (night & lit_at_centre_night).any()
    # the centre definition is still available, the same for every facet
    cn, cd = regions.night_day_masks(run, "centre")
    assert np.array_equal(cn, np.repeat(centre_night[:, None], cn.shape[1], axis=1))
    assert np.array_equal(cd, ~cn)
    with pytest.raises(ConfigError):
        regions.night_day_masks(run, "sunset")


def test_region_night_has_no_direct_sunlight(crater86):
    """No (time, facet) sample that any region counts as night has direct sunlight on that facet,
    and none has had any in the 24 h before."""
    run = crater86
    e = run["solar_direct"].values
    night, _ = regions.night_day_masks(run)
    t_h = (run["time"].values - run["time"].values[0]).astype("timedelta64[s]").astype(float) / 3600.0
    # any direct sunlight on the facet in [t - 28 h, t]: 24 h of darkness plus the 4-h step after the last
    # lit sample (fluxes are linear between samples), by a cumulative count over time
    lit = e > 0
    count = np.vstack([np.zeros((1, lit.shape[1])), np.cumsum(lit, axis=0)])
    lo = np.searchsorted(t_h, t_h - 28.0 + 1e-9)
    lit_recently = (count[np.arange(len(t_h)) + 1] - count[lo]) > 0
    for name, m in regions.region_masks(run).items():
        assert not (night[:, m] & lit[:, m]).any(), name
        assert not (night[:, m] & lit_recently[:, m]).any(), name
        assert not night[t_h < 24.0][:, m].any(), name  # before the record: unknown, taken as lit
    assert night.any()


# ------------------------------------------------------------------------------------------ regions


def _normal_azimuth_deg(normals):
    return np.degrees(np.arctan2(normals[:, 0], normals[:, 1]))  # from north (+y) toward east (+x)


def _angle_between_deg(a, b):
    return np.abs((np.asarray(a) - b + 180.0) % 360.0 - 180.0)


def test_crater_regions_hold_what_their_names_say(crater86):
    run = crater86
    masks = regions.region_masks(run)
    meta = io.mesh_meta(run)
    c = run["centroid"].values
    n = run["normal"].values
    z_floor, z_rim = meta["floor_z_m"], meta["rim_height_m"]
    mid = 0.5 * (z_floor + z_rim)
    upper = np.any([masks[f"upper_wall_{s}"] for s in regions.SECTORS], axis=0)
    lower = np.any([masks[f"lower_wall_{s}"] for s in regions.SECTORS], axis=0)
    top = np.any([masks[f"top_wall_ring_{s}"] for s in regions.SECTORS], axis=0)
    assert upper.sum() > 20 and lower.sum() > 20 and top.sum() > 10
    assert np.all(c[upper, 2] >= mid) and np.all(c[lower, 2] < mid)  # the wall's mid-height, in z
    assert not (upper & lower).any()
    assert np.all(upper[top])  # the top ring is part of the upper wall
    # the top ring's facets touch the crest (r = rim radius at a vertex)
    v = run["mesh_vertices"].values
    f = run["mesh_faces"].values
    rv = np.hypot(v[:, 0], v[:, 1])
    assert np.all(np.isclose(rv[f[top]], meta["rim_radius_m"], rtol=1e-6).any(axis=1))
    # sectors: the facet's slope faces within +-45 deg of the named direction (pole = south = 180 deg)
    az = _normal_azimuth_deg(n)
    for sector, want in zip(regions.SECTORS, (180.0, 0.0, 90.0, 270.0)):
        for part in regions.SECTORED_PARTS:
            m = masks[f"{part}_{sector}"]
            assert m.any(), f"{part}_{sector}"
            assert np.all(_angle_between_deg(az[m], want) <= 45.0 + 1e-9), f"{part}_{sector}"
    # the equator-facing upper wall is on the pole side of the crater and is the lit one
    lit = regions.lit_mask(run).mean(axis=0)
    assert np.all(c[masks["upper_wall_equator_facing"], 1] < 0)
    assert lit[masks["upper_wall_equator_facing"]].mean() > 3 * lit[masks["upper_wall_pole_facing"]].mean()


def test_illumination_classes(crater86):
    run = crater86
    e = run["solar_direct"].values
    cls = regions.illumination_classes(e)
    assert set(cls) == set(regions.ILLUMINATION_CLASSES)
    assert np.array_equal(cls["never_lit"] | cls["rarely_lit"] | cls["often_lit"], np.ones(e.shape[1], bool))
    assert cls["never_lit"].any() and cls["often_lit"].any()
    assert np.all(e[:, cls["never_lit"]] == 0.0)  # zero direct flux at every sample
    frac = (e > 0).mean(axis=0)
    assert np.all((frac[cls["rarely_lit"]] > 0) & (frac[cls["rarely_lit"]] < regions.RARELY_LIT_MAX_FRACTION))
    assert np.all(frac[cls["often_lit"]] >= regions.RARELY_LIT_MAX_FRACTION)
    masks = regions.region_masks(run)
    assert masks["floor"].any() and np.all(cls["never_lit"][masks["floor"]])  # the floor of a -86 deg PSR


def test_slope_and_facing_classes_any_mesh():
    # a tilted-plane "terrain": four facets facing S, N, E, W at 20 deg, and one level facet
    s20, c20 = math.sin(math.radians(20)), math.cos(math.radians(20))
    normals = np.array([[0, -s20, c20], [0, s20, c20], [s20, 0, c20], [-s20, 0, c20], [0, 0, 1.0]])
    slopes = regions.slope_classes(normals)
    assert slopes["slope_15_25_deg"].tolist() == [True] * 4 + [False]
    assert slopes["slope_0_5_deg"].tolist() == [False] * 4 + [True]
    facing = regions.facing_classes(normals, -45.0)
    assert facing["pole_facing"].tolist() == [True, False, False, False, False]
    assert facing["equator_facing"].tolist() == [False, True, False, False, False]
    assert facing["east_facing"].tolist() == [False, False, True, False, False]
    assert facing["west_facing"].tolist() == [False, False, False, True, False]
    assert facing["level"].tolist() == [False] * 4 + [True]
    north = regions.facing_classes(normals, 45.0)
    assert north["pole_facing"].tolist() == [False, True, False, False, False]
    with pytest.raises(ConfigError):
        regions.slope_classes(normals, (10.0, 5.0))


def test_polar_sectors_named_by_mean_sun_azimuth():
    run = make_run(lat_deg=-90.0, n_lunar_days=1.0, n_rings=8)
    masks = regions.region_masks(run)
    assert "upper_wall_sun_facing" in masks and "upper_wall_pole_facing" not in masks
    s, weight = regions.mean_sun_azimuth(run)
    assert 0.0 < weight <= 1.0
    n = run["normal"].values if "normal" in run else None
    if n is None:
        n = regions.mesh_normals(run["mesh_vertices"].values, run["mesh_faces"].values)
    az = _normal_azimuth_deg(n)
    want = math.degrees(math.atan2(s[0], s[1]))
    for part in regions.SECTORED_PARTS:
        m = masks[f"{part}_sun_facing"]
        assert np.all(_angle_between_deg(az[m], want) <= 45.0 + 1e-9)
        m = masks[f"{part}_antisun_facing"]
        assert np.all(_angle_between_deg(az[m], want + 180.0) <= 45.0 + 1e-9)
    assert regions.region_names(-90.0)[:3] == ("floor", "lower_wall_antisun_facing", "lower_wall_sun_facing")
    with pytest.raises(ConfigError):
        regions.sector_axes(-89.9)  # needs the Sun


# ----------------------------------------------------------------------------------- albedo A(i)


def _hayne(i_deg, a0=0.12, a=0.06, b=0.25):
    return a0 + a * (i_deg / 45.0) ** 3 + b * (i_deg / 90.0) ** 8


def test_albedo_hayne2017_matches_published_formula():
    assert float(illumination.albedo_hayne2017(0.0, 0.12)) == 0.12
    for i in (45.0, 60.0, 80.0, 89.0):
        assert float(illumination.albedo_hayne2017(math.radians(i), 0.12)) == pytest.approx(_hayne(i), rel=1e-12)
    # hand values: 45 deg adds a + b/256; 89 deg
    assert float(illumination.albedo_hayne2017(math.pi / 4, 0.12)) == pytest.approx(0.12 + 0.06 + 0.25 / 256)
    assert float(illumination.albedo_hayne2017(math.radians(89.0), 0.12)) == pytest.approx(0.81280015, abs=1e-8)
    assert float(illumination.albedo_hayne2017(math.radians(120.0), 0.12)) == pytest.approx(0.85)  # clipped
    with pytest.raises(ConfigError):
        illumination.albedo_hayne2017(0.1, 1.0)


def test_direct_albedo_uses_sun_centre_incidence():
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    sun = np.array([[0.0, math.sin(math.radians(30)), math.cos(math.radians(30))]])  # i = 30 deg on the level facet
    A = illumination.direct_albedo(normals, sun, 0.12, "hayne2017")
    assert A.shape == (1, 2)
    assert A[0, 0] == pytest.approx(_hayne(30.0))
    assert A[0, 1] == pytest.approx(_hayne(60.0))
    assert np.all(illumination.direct_albedo(normals, sun, 0.12, "constant") == 0.12)
    with pytest.raises(ConfigError):
        illumination.direct_albedo(normals, sun, 0.12, "lommel")


def test_absorbed_sunlight_flat_and_scattering():
    """Flat ground: absorbed = (1 - A(i)) E. With scattering: the A0 solver on A(i) E / A0 equals a direct
    solve of B = A(i) E + A0 F B, and absorbed + reflected-out balances."""
    from scipy import sparse

    from crater_thermal import radiosity

    surf = config.Surface(albedo=0.12, albedo_model="hayne2017")
    mesh = SimpleNamespace(normals=np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, -0.6, 0.8]]))
    sun = np.array([[0.0, 0.5, math.sqrt(0.75)], [0.0, 0.1, math.sqrt(0.99)]])
    direct = np.array([[100.0, 120.0, 10.0], [20.0, 30.0, 0.0]])
    solar, absorbed = sunlight.absorbed_sunlight(surf, mesh, sun, direct, None, None)
    A = illumination.direct_albedo(mesh.normals, sun, 0.12, "hayne2017")
    assert np.allclose(solar, direct) and np.allclose(absorbed, (1 - A) * direct)
    F = sparse.csr_matrix(np.array([[0.0, 0.2, 0.1], [0.15, 0.0, 0.2], [0.1, 0.25, 0.0]]))
    scat = radiosity.ScatteringSolver(F, 0.12, method="exact")
    solar, absorbed = sunlight.absorbed_sunlight(surf, mesh, sun, direct, scat, F)
    Fd = F.toarray()
    for k in range(2):
        B = np.linalg.solve(np.eye(3) - 0.12 * Fd, A[k] * direct[k])
        # 1e-9 W m-2: round-off of a 3x3 solve on ~100 W m-2
        assert np.allclose(solar[k] - direct[k], Fd @ B, atol=1e-9)
        assert np.allclose(absorbed[k], (1 - A[k]) * direct[k] + 0.88 * (Fd @ B), atol=1e-9)


HAYNE_CASE = """
name = "hayne_tiny"
[crater]
kind = "crater"
diameter_km = 2.0
facets = 40
[location]
lat_deg = -85.0
[period]
start = "2019-01-01"
end = "2019-01-04"
spinup = "fixed"
spinup_days = 1.0
initial_temperature_K = 100.0
[surface]
albedo = 0.12
albedo_model = "hayne2017"
[replay]
profiles = ["1300/1800"]
[output]
save_spinup_fluxes = true
"""


def test_hayne2017_streamed_run_saves_absorbed_sunlight_and_replays_exactly(tmp_path):
    """albedo_model = "hayne2017" in a streamed run: run.nc carries solar_absorbed (and its spin-up
    series) equal to (1 - A(i)) direct + (1 - A0) scattered for the saved Sun directions; sunlit ground
    absorbs less than with the constant albedo; a replay of the nominal profile from the same uniform
    start re-traces the run (it is driven by the saved absorbed sunlight, not (1 - A0) incident)."""
    from crater_thermal import config

    path = tmp_path / "hayne.toml"
    path.write_text(HAYNE_CASE)
    case = config.load_case(path)
    ds = io.open_run(runner.run_case(case, tmp_path / "run.nc", progress=False))
    for name in ("solar_absorbed", "spinup_solar_absorbed"):
        assert name in ds and ds[name].attrs["units"] == "W m-2"
    direct = ds["solar_direct"].values
    solar = ds["solar_incident"].values
    absorbed = ds["solar_absorbed"].values
    mesh = simulate.case_mesh(case)
    A = illumination.direct_albedo(mesh.normals, ds["sun_direction"].values, 0.12, "hayne2017")
    # the identity of absorbed_sunlight(); 1e-3 W m-2: float32 storage of ~1e3 W m-2 values (6e-5 relative)
    np.testing.assert_allclose(absorbed, (1 - A) * direct + 0.88 * (solar - direct), atol=1e-3, rtol=1e-6)
    lit = direct > 10.0
    assert lit.any()
    assert np.all(absorbed[lit] < 0.88 * solar[lit])  # A(i) > A0 away from normal incidence (i > 0 here)
    T, _ = simulate.replay_fluxes(
        ds, runner.resolve_profiles(["1300/1800"]), initial_temperature=100.0, fixed_spinup=True, progress=False
    )
    # same columns, same forcing, same uniform start: only float32 storage of the fluxes differs
    assert np.max(np.abs(T[0] - ds["surface_temperature"].values)) <= 1e-3


def test_replay_uses_saved_absorbed_sunlight():
    """A flux file with solar_absorbed is driven by it, not by (1 - albedo) solar_incident."""
    import xarray as xr

    t = np.array(["2019-01-01T00", "2019-01-01T04"], "datetime64[ns]")
    inc = np.full((2, 1), 100.0)
    ds = xr.Dataset(
        {
            "solar_incident": (("time", "facet"), inc, {"units": "W m-2"}),
            "solar_absorbed": (("time", "facet"), inc * 0.5, {"units": "W m-2"}),
        },
        coords={"time": t},
        attrs={"albedo": 0.12},
    )
    assert np.allclose(simulate.absorbed_solar_of(ds), 50.0)
    assert np.allclose(simulate.absorbed_solar_of(ds.drop_vars("solar_absorbed")), 88.0)
