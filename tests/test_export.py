"""GIS export (issue 25, item 5): ``crater-thermal export`` writes a GeoTIFF whose pixel at each facet
centroid holds that facet's statistic, computed here independently with numpy from the run's arrays; the
CRS is the DEM's for a DEM site and a crater-centred lunar azimuthal equidistant one for a crater; NaN
outside the mesh (and on a site's outer ring); provenance in the tags; bad inputs exit 2 with one line."""

import warnings

import numpy as np
import pyproj
import pytest
import rasterio

import crater_thermal as ct
from crater_thermal import cli, config, io, regions, runner, terrain

LAT, LON = -85.0, 0.0
MOON_R_M = 1_737_400.0  # the IAU 2015 lunar sphere [m]

# A few days of the first week of 2019 after a short fixed spin-up: a smoke-sized run, not physics.
CASE = """
name = "{name}"
[crater]
{crater}
[location]
lat_deg = {lat}
lon_deg = {lon}
[period]
start = "2019-01-01"
end = "2019-01-04"
spinup = "fixed"
spinup_days = 3.0
[steps]
flux_step_hours = 4.0
"""


def _run(tmp, name, crater, lat=LAT, lon=LON):
    (tmp / f"{name}.toml").write_text(CASE.format(name=name, crater=crater, lat=lat, lon=lon))
    return runner.run_case(config.load_case(tmp / f"{name}.toml"), tmp / f"{name}.nc", progress=False)


@pytest.fixture(scope="module")
def crater(tmp_path_factory):
    """An idealized 2 km crater (60 facets) at 85 S, its run and a replay with the loose profile."""
    tmp = tmp_path_factory.mktemp("export_crater")
    run = _run(tmp, "crater", 'kind = "crater"\ndiameter_km = 2.0\nfacets = 60')
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 800 kg m-3 lies below Table 7.2 (DensityExtrapolationWarning)
        rep = runner.replay_file(run, ["1300/1800", "800/1100"], fixed_spinup=True, output=tmp / "rep.nc")
    return tmp, run, rep


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A small synthetic DEM site at 87 S (south polar stereographic DEM) with an outer ring."""
    tmp = tmp_path_factory.mktemp("export_site")
    z, tr, wkt = terrain.synthetic_heights(-87.0, 45.0, 7.0, 40.0, craters=[(1.2, 0.0, 0.0)], roughness_m=4.0, seed=2)
    terrain.write_geotiff(tmp / "site.tif", z, tr, wkt)
    crater = (
        'kind = "dem"\ndem = "site.tif"\nradius_km = 1.2\nresolution_m = 200.0\n'
        "outer_radius_km = 2.5\nouter_resolution_m = 600.0"
    )
    return tmp, _run(tmp, "site", crater, lat=-87.0, lon=45.0), wkt


def _arrays(path):
    ds = io.open_run(path)
    out = {k: np.asarray(ds[k].values) for k in ("surface_temperature", "solar_incident", "mesh_vertices")}
    out["faces"] = np.asarray(ds["mesh_faces"].values, np.int64)
    out["centroid"] = np.asarray(ds["centroid"].values, float)
    out["time"] = np.asarray(ds["time"].values)
    out["night"], _ = regions.night_day_masks(ds)
    out["inner"] = io.dataset_inner(ds)
    out["meta"] = io.mesh_meta(ds)
    ds.close()
    return out


def _night_median(values, night):
    """Per-facet median over that facet's night samples, NaN without any (written out, not analysis's)."""
    return np.array(
        [np.median(values[night[:, j], j]) if night[:, j].any() else np.nan for j in range(values.shape[1])]
    )


def _inradius_min(xy, faces):
    """Smallest inscribed-circle radius of the projected triangles [map units]."""
    p = xy[faces]
    sides = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2)
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return float(np.min(2.0 * area / sides.sum(axis=1)))


def _sample(tif, x, y):
    with rasterio.open(tif) as src:
        return np.array([v[0] for v in src.sample(list(zip(x, y)), indexes=1)], float)


def _export(*args) -> int:
    """``crater-thermal export ARGS`` in this process; its exit code."""
    try:
        cli.main(["export", *map(str, args)])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_crater_night_median_at_centroids(crater):
    """Fine pixels (half the smallest inscribed radius: a centroid lies at least 2/3 of it from every side,
    so the pixel containing it has its centre in the same facet): the value at every centroid is the
    facet's night median to float32 rounding; the CRS is the crater-centred lunar AEQD; NaN outside."""
    tmp, run, _ = crater
    a = _arrays(run)
    xy = a["mesh_vertices"][:, :2]  # the crater frame's east, north [m] are the local CRS's x, y
    pixel = 0.5 * _inradius_min(xy, a["faces"])
    tif = tmp / "T_night.tif"
    assert _export(run, "-o", tif, "--pixel-m", pixel) == 0
    want = _night_median(a["surface_temperature"].astype(float), a["night"])
    got = _sample(tif, a["centroid"][:, 0], a["centroid"][:, 1])
    assert np.isfinite(want).sum() > want.size // 2  # facets without night are NaN in both
    np.testing.assert_allclose(got, want.astype(np.float32), rtol=0, atol=1e-4)
    with rasterio.open(tif) as src:
        crs = pyproj.CRS.from_wkt(src.crs.to_wkt())
        assert src.nodata is not None and np.isnan(src.nodata)
        tags = src.tags()
        grid = src.read(1)
        assert src.units[0] == "K"
        res = src.res
    params = {p.name: p.value for p in crs.coordinate_operation.params}
    assert "Azimuthal Equidistant" in crs.coordinate_operation.method_name
    assert params["Latitude of natural origin"] == pytest.approx(LAT)
    assert params["Longitude of natural origin"] == pytest.approx(LON)
    assert crs.ellipsoid.semi_major_metre == pytest.approx(MOON_R_M)
    assert crs.ellipsoid.semi_minor_metre == pytest.approx(MOON_R_M)
    assert res == pytest.approx((pixel, pixel))
    # outside: the corners of the bounding grid lie outside the round crater
    assert np.isnan(grid[0, 0]) and np.isnan(grid[-1, -1])
    for key, value in {"variable": "surface_temperature", "statistic": "night_median", "units": "K"}.items():
        assert tags[key] == value
    assert tags["source"] == str(run.resolve()) and tags["night_definition"]


def test_crater_default_pixel_and_other_statistics(crater):
    """Default pixel = the mean projected facet edge [m]; mean / max / at TIME of a flux through the API."""
    tmp, run, _ = crater
    a = _arrays(run)
    xy = a["mesh_vertices"][:, :2]
    edges = xy[a["faces"]] - xy[np.roll(a["faces"], -1, axis=1)]
    mean_edge = np.hypot(edges[..., 0], edges[..., 1]).mean()
    with rasterio.open(ct.export_map(run, tmp / "default.tif", "solar_incident", "mean")) as src:
        assert src.res[0] == pytest.approx(mean_edge, rel=1e-6)
        assert src.units[0] == "W m-2"
    pixel = 0.5 * _inradius_min(xy, a["faces"])
    E = a["solar_incident"].astype(float)
    k = 7
    when = np.datetime_as_string(a["time"][k] + np.timedelta64(20, "m"), unit="m")  # nearest sample: k
    for stat, time, want in (("mean", None, E.mean(0)), ("max", None, E.max(0)), ("at", when, E[k])):
        tif = ct.export_map(run, tmp / f"E_{stat}.tif", "solar_incident", stat, time=time, pixel_m=pixel)
        got = _sample(tif, a["centroid"][:, 0], a["centroid"][:, 1])
        np.testing.assert_allclose(got, want.astype(np.float32), rtol=1e-6, atol=1e-4)
    p = xy[a["faces"]]
    u, v = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum()
    with rasterio.open(tmp / "E_mean.tif") as src:  # every facet has a mean: drawn area = projected area
        assert np.isfinite(src.read(1)).sum() * pixel**2 == pytest.approx(area, rel=0.02)
    with rasterio.open(tmp / "E_at.tif") as src:
        assert src.tags()["time_utc"] == np.datetime_as_string(a["time"][k], unit="s") + "Z"


def test_replay_loose_minus_nominal(crater):
    """--profile 800/1100 of a replay: loose - nominal [K], night median with the run's per-facet night."""
    tmp, run, rep = crater
    a = _arrays(run)
    r = io.open_replay(rep)
    labels = [str(p) for p in r["profile"].values]
    T = np.asarray(r["surface_temperature"].values, float)
    r.close()
    dT = T[labels.index("800/1100")] - T[labels.index("1300/1800")]
    pixel = 0.5 * _inradius_min(a["mesh_vertices"][:, :2], a["faces"])
    tif = tmp / "dT.tif"
    args = ["--variable", "profile_minus_nominal", "--profile", "800/1100", "--pixel-m", pixel]
    assert _export(rep, "--run", run, "-o", tif, *args) == 0
    got = _sample(tif, a["centroid"][:, 0], a["centroid"][:, 1])
    np.testing.assert_allclose(got, _night_median(dT, a["night"]).astype(np.float32), rtol=0, atol=1e-4)
    with rasterio.open(tif) as src:
        tags = src.tags()
    assert tags["profile"] == "800/1100" and tags["nominal_profile"] == "1300/1800" and tags["units"] == "K"


def test_site_in_the_dem_crs_inner_facets_only(site):
    """A DEM site: the DEM's own CRS; inner facets at their centroids (projected with pyproj here) carry
    their night median; the outer ring's centroids are nodata."""
    tmp, run, wkt = site
    a = _arrays(run)
    dem_crs = pyproj.CRS.from_wkt(wkt)
    to_map = pyproj.Transformer.from_crs(dem_crs.geodetic_crs, dem_crs, always_xy=True)

    def project(points):
        lat, lon, _ = terrain.local_to_geographic(points, a["meta"])
        return to_map.transform(lon, lat)

    vx, vy = project(a["mesh_vertices"])
    inner = a["inner"]
    assert 0 < inner.sum() < inner.size
    pixel = 0.5 * _inradius_min(np.stack([vx, vy], 1), a["faces"])
    tif = tmp / "site.tif.out.tif"
    ct.export_map(run, tif, pixel_m=pixel)
    cx, cy = project(a["centroid"])
    got = _sample(tif, cx, cy)
    want = _night_median(a["surface_temperature"].astype(float), a["night"])
    np.testing.assert_allclose(got[inner], want[inner].astype(np.float32), rtol=0, atol=1e-4)
    assert np.isnan(got[~inner]).all()
    with rasterio.open(tif) as src, rasterio.open(tmp / "site.tif") as dem:
        assert src.crs == dem.crs  # the DEM's CRS as GDAL reads both files
        out_crs = pyproj.CRS.from_wkt(src.crs.to_wkt())
        assert src.tags()["source_kind"] == "run"
    # and the same map coordinates as the CRS the DEM was written with (GeoTIFF keys store IAU_2015:30135's
    # polar stereographic variant A as the equivalent variant B)
    lon, lat = np.array([30.0, 45.0, 60.0]), np.array([-86.5, -87.0, -87.5])
    back = pyproj.Transformer.from_crs(out_crs.geodetic_crs, out_crs, always_xy=True).transform(lon, lat)
    np.testing.assert_allclose(back, to_map.transform(lon, lat), atol=1e-3)


@pytest.mark.parametrize(
    "args, text",
    [
        (["--variable", "albedo"], "variable = 'albedo'"),
        (["--statistic", "median"], "statistic = 'median'"),
        (["--statistic", "at"], "needs a time"),
        (["--statistic", "at", "--time", "2031-01-01T00:00"], "outside the record"),
        (["--statistic", "at", "--time", "yesterday"], "not an ISO"),
        (["--profile", "800/1100"], "applies to a replay"),
        (["--pixel-m", "-5"], "pixel_m"),
        (["--night", "twilight"], "twilight"),
    ],
)
def test_bad_inputs_exit_2_with_one_line(crater, capsys, args, text):
    tmp, run, _ = crater
    code = _export(run, "-o", tmp / "bad.tif", *args)
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("error:") and text in err, err
    assert not (tmp / "bad.tif").exists()


def test_replay_errors_and_input_as_output(crater, capsys):
    tmp, run, rep = crater
    for args, text in (
        ([rep, "-o", tmp / "bad.tif"], "needs its run"),
        ([rep, "-o", tmp / "bad.tif", "--variable", "solar_incident", "--statistic", "mean"], "replay quantity"),
        ([rep, "-o", tmp / "bad.tif", "--statistic", "mean", "--profile", "999/999"], "not in the replay"),
        ([run, "-o", run, "--overwrite"], "GeoTIFF"),
    ):
        code = _export(*args)
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and text in err, err
