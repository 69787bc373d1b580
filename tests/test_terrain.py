"""Real sites from DEMs (issue 9): reading, the site frame and curvature, PDS3 = GeoTIFF, bad DEMs, CLI.

The idealized-crater comparison (DEM path vs generator) and the end-to-end site run live in
test_terrain_site.py (they run the simulator).
"""

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
import rasterio

from crater_thermal import cli, config, ephemeris, geometry, io, terrain
from crater_thermal.constants import MOON_RADIUS
from crater_thermal.errors import ConfigError, DEMError

LAT, LON = -85.0, 30.0


def _flat_site(tmp_path, size_km=70.0, pixel_m=250.0, name="flat.tif", **kw):
    z, tr, wkt = terrain.synthetic_heights(LAT, LON, size_km, pixel_m, **kw)
    return terrain.write_geotiff(tmp_path / name, z, tr, wkt), z, tr, wkt


def _plane(x, y):
    """Heights [m] linear in the DEM's map coordinates (bilinear resampling reproduces a plane exactly)."""
    return 150.0 + 4e-3 * (x - 80e3) - 6e-3 * (y - 140e3)


def _plane_site(tmp_path):
    z, tr, wkt = terrain.synthetic_heights(LAT, LON, 30.0, 50.0)
    a, _, c, _, e, f = tr
    rows, cols = z.shape
    xs = c + (np.arange(cols) + 0.5) * a
    ys = f + (np.arange(rows) + 0.5) * e
    X, Y = np.meshgrid(xs, ys)
    return terrain.write_geotiff(tmp_path / "plane.tif", _plane(X, Y).astype(np.float32), tr, wkt)


def test_enu_basis_matches_the_ephemeris_frame():
    # the site frame must be the frame the Sun vectors are expressed in, also at the pole
    for lat, lon in ((-85.0, 30.0), (-90.0, 0.0), (-90.0, 123.0), (89.5, -40.0)):
        np.testing.assert_allclose(terrain.enu_basis(lat, lon), ephemeris.enu_basis(lat, lon), atol=1e-15)


def test_spherical_dem_meshes_onto_the_sphere_with_the_right_tilt(tmp_path):
    dem, *_ = _flat_site(tmp_path)
    m = terrain.site_mesh(dem, LAT, LON, radius_km=31.0, resolution_m=1500.0)
    R = m.meta["reference_radius_m"]
    assert R == MOON_RADIUS
    # every vertex on the sphere: distance from the Moon's centre (0, 0, -R) in the site frame
    r = np.linalg.norm(m.vertices + np.array([0.0, 0.0, R]), axis=1)
    assert np.abs(r - R).max() <= 0.1  # issue: <= 0.1 m (float64 gives ~1e-9 m)
    # the surface drops below the tangent plane as d^2 / (2 R): 0.26 km at 30 km
    d = np.hypot(m.vertices[:, 0], m.vertices[:, 1])
    far = d > 29e3
    np.testing.assert_allclose(-m.vertices[far, 2], R - np.sqrt(R * R - d[far] ** 2), atol=0.1)
    # a facet ~30 km from the centre is tilted by its angular distance, 30 / 1737.4 rad = 0.989 deg
    c = m.centroids
    dist = R * np.arctan2(np.hypot(c[:, 0], c[:, 1]), c[:, 2] + R)
    k = int(np.argmin(np.abs(dist - 30e3)))
    tilt = math.degrees(math.acos(m.normals[k, 2]))
    # the normal of a flat chord triangle points at its circumcentre: within ~half a facet (0.025 deg) of d/R
    assert tilt == pytest.approx(math.degrees(dist[k] / R), abs=0.03)
    assert tilt == pytest.approx(math.degrees(30e3 / R), abs=0.05)


def test_coordinate_round_trip_through_the_dem_is_within_a_metre(tmp_path):
    dem = _plane_site(tmp_path)
    m = terrain.site_mesh(dem, LAT, LON, radius_km=8.0, resolution_m=400.0)
    meta = m.meta
    # vertex -> (lat, lon, h) -> DEM map coordinates -> the DEM's own height there -> vertex again
    lat, lon, h = terrain.local_to_geographic(m.vertices, meta)
    x, y = terrain.local_to_dem_xy(m.vertices, meta)
    np.testing.assert_allclose(h, _plane(np.asarray(x), np.asarray(y)), atol=0.05)  # float32 DEM storage
    back = terrain.dem_xy_to_local(x, y, _plane(np.asarray(x), np.asarray(y)), meta)
    assert np.abs(back - m.vertices).max() <= 1.0  # issue: <= 1 m
    again = terrain.geographic_to_local(lat, lon, h, meta)
    assert np.abs(again - m.vertices).max() <= 1e-6
    # and a chosen point: the centre node is at the centre's latitude/longitude
    k = int(np.argmin(np.hypot(m.vertices[:, 0], m.vertices[:, 1])))
    assert lat[k] == pytest.approx(LAT, abs=1e-9) and lon[k] == pytest.approx(LON, abs=1e-9)


def test_pds3_img_lbl_reads_as_the_geotiff(tmp_path):
    dem, z, tr, wkt = _flat_site(
        tmp_path, size_km=12.0, pixel_m=40.0, craters=[(4.0, 0.5, -0.5)], roughness_m=8.0, seed=3
    )
    lbl = terrain.write_pds3(tmp_path / "site.lbl", z, tr)
    h_tif, info_tif, kind_tif = terrain.read_heights(dem)
    h_pds, info_pds, kind_pds = terrain.read_heights(lbl)
    assert (kind_tif, kind_pds) == ("height", "radius")  # LOLA convention: DN * 0.5 m + 1737.4 km
    assert info_pds.transform == pytest.approx(info_tif.transform)
    assert np.abs(h_pds - h_tif).max() <= 0.25 + 1e-6  # int16 at 0.5 m steps
    m_tif = terrain.site_mesh(dem, LAT, LON, 4.0, 150.0)
    m_pds = terrain.site_mesh(lbl, LAT, LON, 4.0, 150.0)
    np.testing.assert_array_equal(m_tif.faces, m_pds.faces)
    assert np.abs(m_tif.vertices - m_pds.vertices).max() <= 0.25 + 1e-6
    assert m_pds.meta["height_kind"] == "radius" and m_tif.meta["height_kind"] == "height"


def test_site_mesh_outer_ring_inner_first_and_metadata_round_trip(tmp_path):
    dem, *_ = _flat_site(tmp_path, size_km=40.0, pixel_m=200.0, roughness_m=20.0, seed=1)
    m = terrain.site_mesh(dem, LAT, LON, 5.0, 500.0, outer_radius_km=15.0, outer_resolution_m=2000.0)
    n_in = m.meta["n_inner"]
    est = terrain.estimate_site(5.0, 500.0, 15.0, 2000.0)
    assert 0 < n_in < m.n_facets
    assert abs(m.meta["n_facets"] - est["n_facets"]) / est["n_facets"] < 0.15  # estimate good to ~10 %
    R = m.meta["reference_radius_m"]
    geo = R * np.arctan2(np.hypot(m.centroids[:, 0], m.centroids[:, 1]), m.centroids[:, 2] + R)
    assert geo[:n_in].max() <= 5e3 and geo[n_in:].min() > 4.5e3
    assert np.all(m.normals[:, 2] > 0.5)  # oriented up
    p = geometry.save_mesh(m, tmp_path / "site.ply")
    back = geometry.load_mesh(p)
    assert back.hash == m.hash
    for key in ("n_inner", "crs_wkt", "center_lat_deg", "resolution_m", "outer_resolution_m", "dem_source"):
        assert back.meta[key] == m.meta[key]
    flags = io.inner_flags(back.n_facets, back.meta)
    assert flags.sum() == n_in and flags[:n_in].all()
    ds_vars = io.mesh_variables(back)
    assert ds_vars["inner"][1].sum() == n_in


def _cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    err = capsys.readouterr().err.strip()
    return exc.value.code, err


def _write_raw(path, z, crs, transform, nodata=None):
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=z.shape[1],
        height=z.shape[0],
        count=1,
        dtype="float32",
        crs=crs,
        transform=transform,
        nodata=nodata,
    ) as dst:
        dst.write(z.astype(np.float32), 1)
    return path


@pytest.mark.parametrize(
    "case, needle",
    [
        ("no_crs", "no coordinate reference system"),
        ("earth", "not the Moon"),
        ("geographic", "geographic CRS"),
        ("equirectangular", "not a projection for a site"),
        ("holes", "nodata holes"),
        ("outside", "outside DEM"),
        ("beyond", "beyond the edge"),
        ("absurd_fine", "absurd"),
        ("absurd_zero", "absurd"),
        ("huge", "site too large"),
    ],
)
def test_bad_dems_give_one_line_errors_and_write_nothing(tmp_path, capsys, case, needle):
    z = np.zeros((200, 200))
    good = terrain.polar_crs(LAT).to_wkt()
    z0, tr0, _ = terrain.synthetic_heights(LAT, LON, 10.0, 50.0)
    tr = rasterio.Affine(*tr0)
    args = dict(lat=LAT, radius="3", res="100")
    if case == "no_crs":
        dem = _write_raw(tmp_path / "d.tif", z, None, tr)
    elif case == "earth":
        dem = _write_raw(tmp_path / "d.tif", z, "EPSG:3031", rasterio.Affine(50, 0.0, 0, 0.0, -50, 0))
    elif case == "geographic":
        dem = _write_raw(tmp_path / "d.tif", z, "IAU_2015:30100", rasterio.Affine(0.1, 0.0, 20, 0.0, -0.01, -84))
    elif case == "equirectangular":
        # simple cylindrical around the site: inside the raster, but 11x stretched east-west at 85 S
        x0 = math.radians(25.0) * MOON_RADIUS
        y0 = math.radians(-84.0) * MOON_RADIUS
        dem = _write_raw(tmp_path / "d.tif", z, "IAU_2015:30110", rasterio.Affine(1500.0, 0.0, x0, 0.0, -300.0, y0))
    elif case == "holes":
        zz = np.array(z0, dtype=float)
        zz[90:110, 95:105] = -9999.0
        dem = _write_raw(tmp_path / "d.tif", zz, good, tr, nodata=-9999.0)
    else:
        dem = _write_raw(tmp_path / "d.tif", z0, good, tr)
        if case == "outside":
            args["lat"] = -80.0
        elif case == "beyond":
            args["radius"] = "8"
        elif case == "absurd_fine":
            args["res"] = "0.5"
        elif case == "absurd_zero":
            args["res"] = "0"
        elif case == "huge":
            args["res"] = "5"
            args["radius"] = "4.9"
    out = tmp_path / "site.ply"
    code, err = _cli(
        [
            "mesh",
            "dem",
            str(dem),
            "--center-lat",
            str(args["lat"]),
            "--center-lon",
            str(LON),
            "--radius-km",
            args["radius"],
            "--resolution-m",
            args["res"],
            "-o",
            str(out),
        ],
        capsys,
    )
    assert code == 2
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    assert needle in err
    assert not out.exists()
    if case == "huge":
        assert "GB" in err


def test_cli_synth_and_mesh_dem(tmp_path, capsys):
    tif = tmp_path / "s.tif"
    cli.app(
        [
            "dem",
            "synth",
            "--lat-deg",
            "-85",
            "--lon-deg",
            "30",
            "--size-km",
            "8",
            "--pixel-m",
            "40",
            "--crater",
            "3",
            "--crater",
            "1@2,-2",
            "--roughness",
            "3",
            "-o",
            str(tif),
        ],
        standalone_mode=False,
    )
    lbl = tmp_path / "s.lbl"
    cli.app(
        [
            "dem",
            "synth",
            "--lat-deg",
            "-85",
            "--lon-deg",
            "30",
            "--size-km",
            "8",
            "--pixel-m",
            "40",
            "--crater",
            "3",
            "-o",
            str(lbl),
        ],
        standalone_mode=False,
    )
    assert (tmp_path / "s.IMG").exists() and (tmp_path / "s.LBL").exists()
    ply = tmp_path / "s.ply"
    cli.app(
        [
            "mesh",
            "dem",
            str(tif),
            "--center-lat",
            "-85",
            "--center-lon",
            "30",
            "--radius-km",
            "2",
            "--resolution-m",
            "200",
            "--outer-radius-km",
            "3",
            "-o",
            str(ply),
        ],
        standalone_mode=False,
    )
    m = geometry.load_mesh(ply)
    assert m.meta["kind"] == "dem" and m.meta["outer_resolution_m"] == 800.0
    before = ply.read_bytes()
    code, err = _cli(
        ["mesh", "dem", str(tif), "--center-lat", "-85", "--center-lon", "30", "--radius-km", "2", "-o", str(ply)],
        capsys,
    )
    assert code == 2 and "exists" in err and ply.read_bytes() == before
    code, err = _cli(["dem", "synth", "--lat-deg", "-85", "--crater", "x@1", "-o", str(tmp_path / "b.tif")], capsys)
    assert code == 2 and "--crater" in err


def test_synthetic_crater_follows_the_generator_profile(tmp_path):
    # the rasterized crater is the Table 7.1 profile: floor depth and rim height at the right radii
    z, tr, _ = terrain.synthetic_heights(LAT, LON, 6.0, 10.0, craters=[(4.0, 0.0, 0.0)])
    dims = geometry.crater_dimensions(4.0)
    assert z.min() == pytest.approx(dims["floor_z"] * 1e3, abs=0.5)
    assert z.max() == pytest.approx(dims["rim_height"] * 1e3, abs=2.0)  # crest sampled at 10 m pixels
    with pytest.raises(ConfigError):
        terrain.synthetic_heights(-30.0, 0.0, 6.0, 10.0)
    with pytest.raises(ConfigError):
        terrain.synthetic_heights(LAT, LON, 6.0, 10.0, craters=[(40.0, 0.0, 0.0)])  # beyond simple craters


def test_height_kind_override_and_errors(tmp_path):
    dem, *_ = _flat_site(tmp_path, size_km=10.0, pixel_m=100.0)
    with pytest.raises(DEMError, match="heights reach"):
        terrain.site_mesh(dem, LAT, LON, 2.0, 200.0, height_kind="radius")
    with pytest.raises(ConfigError, match="height_kind"):
        terrain.site_mesh(dem, LAT, LON, 2.0, 200.0, height_kind="nope")
    with pytest.raises(DEMError, match="does not exist"):
        terrain.open_dem(tmp_path / "missing.tif")


SITE_CASES = sorted((Path(__file__).resolve().parents[1] / "cases" / "sites").glob("*.toml"))


@pytest.mark.parametrize("path", SITE_CASES, ids=lambda p: p.name)
def test_site_cases_name_their_dem_and_load_with_it(tmp_path, path):
    text = path.read_text()
    dem_name = tomllib.loads(text)["crater"]["dem"]
    if not (path.parent / dem_name).exists():  # not downloaded: a one-line error naming the key and file
        with pytest.raises(ConfigError, match=f"crater.dem.*{dem_name}"):
            config.load_case(path)
    (tmp_path / dem_name).write_bytes(b"stand-in")  # the loader checks existence; the mesher reads it
    case = config.loads_case(text, base_dir=tmp_path, name=path.stem)
    assert case.crater.kind == "dem" and case.crater.dem == (tmp_path / dem_name).resolve()
    est = terrain.estimate_site(
        case.crater.radius_km, case.crater.resolution_m, case.crater.outer_radius_km, case.crater.outer_resolution_m
    )
    assert est["n_facets"] < 30_000  # the README's "fits 2 cores" sizes


def test_dem_case_keys_are_validated(tmp_path):
    (tmp_path / "d.tif").write_bytes(b"x")
    base = (
        '[crater]\nkind = "dem"\ndem = "d.tif"\nradius_km = 3.0\n{extra}[location]\nlat_deg = -85.0\n'
        '[period]\nstart = "2019-01-01"\nend = "2019-02-01"\n'
    )
    ok = config.loads_case(base.format(extra=""), base_dir=tmp_path)
    assert ok.crater.height_kind == "auto" and ok.crater.max_facets == terrain.MAX_FACETS
    for extra, needle in (
        ("center_lat_deg = -80.0\n", "differs from location.lat_deg"),
        ("resolution_m = -5.0\n", "resolution_m"),
        ('height_kind = "feet"\n', "height_kind"),
        ("outer_resolution_m = 500.0\n", "needs crater.outer_radius_km"),
        ("outer_radius_km = 2.0\n", "must exceed"),
        ("diameter_km = 2.0\n", "diameter_km"),
    ):
        with pytest.raises(ConfigError, match=needle):
            config.loads_case(base.format(extra=extra), base_dir=tmp_path)
