"""Tests for crater_thermal.ephemeris.

The reference for the Sun direction is skyfield's own machinery, independent of our code paths: the
JPL MOON_ME_DE421 frame built from the NAIF lunar kernels, a site built with
``PlanetaryConstants.build_latlon_degrees`` and the Sun's apparent alt/az from
``site.at(t).observe(sun).apparent(deflectors=())`` -- the same "apparent" definition (light time +
aberration, no deflection) our default uses. Its output is committed as tests/data/sun_moon_me_de421.npz
(written by tests/data/make_sun_reference.py), so the comparison runs on a fresh clone; the lunar
kernels themselves (not distributed) are needed only to test the ``moon_frame = "de421"`` option and
to check that the committed data is what the script writes.
"""

from __future__ import annotations

import datetime as dt
import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

from crater_thermal import ephemeris as eph
from crater_thermal.constants import AU
from crater_thermal.errors import ConfigError, EphemerisRangeError

from conftest import REPO, SHARED_EPHEMERIS

DATA = REPO / "tests" / "data"
REFERENCE = DATA / "sun_moon_me_de421.npz"


def _find_kernels() -> Path:
    """The shared lunar kernels: $CRATER_THERMAL_MOON_KERNELS, ../shared/ephemeris of the
    checkout, or ../../shared/ephemeris (a git worktree under wt/)."""
    candidates = [
        os.environ.get("CRATER_THERMAL_MOON_KERNELS"),
        SHARED_EPHEMERIS,
        REPO.parent.parent / "shared" / "ephemeris",
    ]
    for c in candidates:
        if c and all((Path(c) / n).is_file() for n in eph.DE421_KERNEL_FILES):
            return Path(c)
    return SHARED_EPHEMERIS


KERNELS = _find_kernels()
KERNELS_PRESENT = all((KERNELS / n).is_file() for n in eph.DE421_KERNEL_FILES)
needs_kernels = pytest.mark.skipif(not KERNELS_PRESENT, reason=f"no lunar kernels in {KERNELS}")

SITES = [(-80.0, 0.0), (-85.0, 37.0), (-88.0, -120.0), (-90.0, 0.0), (0.0, -45.0), (45.0, 10.0)]


def _angle_deg(u, v):
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def jpl_reference():
    """The committed reference: times, and per site (lat, lon) the unit ENU Sun vectors and distances [m]."""
    with np.load(REFERENCE) as d:
        ref = {k: d[k] for k in ("times", "sites", "enu", "distance_m")}
    assert [tuple(s) for s in ref["sites"]] == SITES
    return ref


@pytest.mark.parametrize("i", range(len(SITES)), ids=[f"{lat:g},{lon:g}" for lat, lon in SITES])
def test_iau2009_matches_moon_me_de421(jpl_reference, i):
    lat, lon = SITES[i]
    u, d = eph.sun_in_crater_frame(jpl_reference["times"], lat, lon, moon_frame="iau2009")
    # IAU 2009 approximates ME_DE421 (Archinal et al. 2011): measured max 0.00351 deg at every site over
    # 2016-2020 (the frames' offset, the same seen from any site); 0.004 deg leaves 15 % for another
    # skyfield / numpy. It is 1/67 of the Sun's angular radius, far below what the thermal model resolves.
    assert _angle_deg(u, jpl_reference["enu"][i]).max() < 0.004
    # same DE421 positions and light time: measured max relative difference 1.8e-9 (270 m) at the
    # equatorial sites, <= 7e-10 at the polar ones; 5e-9 is 750 m of 1.5e11 m
    np.testing.assert_allclose(d, jpl_reference["distance_m"][i], rtol=5e-9, atol=0)


@needs_kernels
@pytest.mark.parametrize("i", range(4), ids=[f"{lat:g},{lon:g}" for lat, lon in SITES[:4]])
def test_de421_frame_option_matches_reference(jpl_reference, i):
    lat, lon = SITES[i]
    u, _ = eph.sun_in_crater_frame(jpl_reference["times"], lat, lon, moon_frame="de421", moon_kernels=KERNELS)
    # same frame: measured max 1.5e-6 deg, i.e. the resolution of arccos of a float64 dot product near 1
    # (sqrt(2 eps) rad = 1.2e-6 deg) plus the site's rotational aberration (4.6 m/s -> 9e-7 deg)
    assert _angle_deg(u, jpl_reference["enu"][i]).max() < 3e-6


@needs_kernels
def test_reference_data_is_what_its_script_writes(tmp_path, jpl_reference):
    spec = importlib.util.spec_from_file_location("make_sun_reference", DATA / "make_sun_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    with np.load(mod.main(KERNELS, tmp_path / "ref.npz")) as fresh:
        assert np.array_equal(fresh["times"], jpl_reference["times"])
        # bit-for-bit with the same skyfield and numpy; 1e-12 allows for other versions' rounding
        np.testing.assert_allclose(fresh["enu"], jpl_reference["enu"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(fresh["distance_m"], jpl_reference["distance_m"], rtol=1e-12)


def test_de421_frame_without_kernels_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="moon_kernels"):
        eph.sun_in_crater_frame(["2019-01-01"], -85.0, 0.0, moon_frame="de421")
    with pytest.raises(ConfigError, match="moon_080317.tf"):
        eph.sun_in_crater_frame(["2019-01-01"], -85.0, 0.0, moon_frame="de421", moon_kernels=tmp_path)


def test_corrections_differ_by_at_most_aberration():
    times = eph.time_grid("2019-01-01", "2019-03-01", 6 * 3600)
    app, _ = eph.sun_in_crater_frame(times, -85.0, 0.0)
    lt, _ = eph.sun_in_crater_frame(times, -85.0, 0.0, correction="light_time")
    geo, _ = eph.sun_in_crater_frame(times, -85.0, 0.0, correction="geometric")
    # annual aberration for v ~ 29.8 km/s (+1 km/s lunar orbit): v/c <= 1.04e-4 rad = 0.0059 deg
    ab = _angle_deg(app, lt)
    assert 0.004 < ab.max() < 0.0062
    # the Sun moves ~ 0.01 km/s about the barycentre: light-time shift < 1e-5 deg
    assert _angle_deg(lt, geo).max() < 1e-4


def test_unit_vectors_and_distance_range():
    times = eph.time_grid("2016-01-01", "2020-01-01", 86400.0)
    u, d = eph.sun_in_crater_frame(times, -86.0, 0.0)
    assert u.shape == (times.size, 3) and d.shape == (times.size,)
    assert np.allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-12)
    # Earth-Moon orbit eccentricity 0.0167 plus the lunar orbit (0.0026 au): 0.98-1.02 au
    assert 0.98 < d.min() / AU < 0.985 and 1.015 < d.max() / AU < 1.02


def test_subsolar_latitude_is_small():
    times = eph.time_grid("2016-01-01", "2020-01-01", 12 * 3600)
    lat = eph.subsolar_latitude_deg(times)
    # lunar equator is inclined 1.54 deg to the ecliptic (Cassini's laws), plus the
    # Sun's ecliptic latitude seen from the Moon (< 0.01 deg): within +-1.6 deg
    assert np.abs(lat).max() < 1.6
    # ...and it reaches close to that bound within the 4 years (one draconic-year swing)
    assert np.abs(lat).max() > 1.4


@pytest.mark.parametrize("lat", [-80.0, -86.0, -90.0, 88.0])
def test_polar_elevation_bound(lat):
    times = eph.time_grid("2016-01-01", "2020-01-01", 4 * 3600)
    elev, _ = eph.sun_elevation_azimuth_deg(times, lat, 15.0)
    bound = 90.0 - abs(lat) + 1.6
    assert elev.max() < bound
    # ...and the Sun really gets near it at noon (within the 1.6 deg seasonal swing + 0.05)
    assert elev.max() > 90.0 - abs(lat) - 1.65


def test_south_pole_sun_circles_the_horizon():
    times = eph.time_grid("2019-01-01", "2019-02-01", 3600)
    elev, az = eph.sun_elevation_azimuth_deg(times, -90.0, 0.0)
    assert np.abs(elev).max() < 1.6 + 0.02  # + parallax / crude margin
    # the azimuth covers the full circle in a synodic month
    hist, _ = np.histogram(az, bins=12, range=(0, 360))
    assert np.all(hist > 0)


def test_morning_sun_is_in_the_east():
    """At lat 0 the Sun rises in the east: elevation increasing <=> x (east) > 0."""
    times = eph.time_grid("2019-01-01", "2019-02-01", 3600)
    u, _ = eph.sun_in_crater_frame(times, 0.0, 0.0)
    rising = np.diff(u[:, 2]) > 0
    up = (u[:-1, 2] > 0.1) & (u[:-1, 2] < 0.95)  # away from the horizon and from noon
    assert np.all(u[:-1][rising & up, 0] > 0)
    assert np.all(u[:-1][~rising & up, 0] < 0)


def test_rotation_matrices_are_rotations():
    R = eph.moon_rotation_iau2009(eph.time_grid("1950-01-01", "2050-01-01", 365.25 * 86400))
    eye = np.broadcast_to(np.eye(3), R.shape)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), eye, atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # the lunar pole is within 2 deg of (alpha, delta) = (270, 66.5) deg
    pole = R[:, 2, :]
    ref = np.array(
        [
            np.cos(np.radians(66.54)) * np.cos(np.radians(270.0)),
            np.cos(np.radians(66.54)) * np.sin(np.radians(270.0)),
            np.sin(np.radians(66.54)),
        ]
    )
    assert _angle_deg(pole, ref).max() < 4.5  # 3.9 deg libration amplitude in alpha0 cos(delta0)


def test_enu_basis_right_handed():
    for lat, lon in SITES:
        B = eph.enu_basis(lat, lon)
        assert np.allclose(B @ B.T, np.eye(3), atol=1e-15)
        assert np.allclose(np.cross(B[0], B[1]), B[2], atol=1e-15)


def test_time_grid_forms_and_inclusion():
    a = eph.time_grid("2019-01-01", "2019-01-02", 4 * 3600)
    assert a.dtype == np.dtype("datetime64[ns]") and a.size == 7 and a[-1] == np.datetime64("2019-01-02")
    b = eph.time_grid(np.datetime64("2019-01-01"), np.datetime64("2019-01-02"), 4 * 3600, include_end=False)
    assert b.size == 6
    c = eph.time_grid("2019-01-01T00:00Z", dt.datetime(2019, 1, 1, 10), 4 * 3600)
    assert c.size == 3 and c[-1] == np.datetime64("2019-01-01T08:00")
    assert np.all(np.diff(a) == np.timedelta64(4, "h"))


@pytest.mark.parametrize(
    "args, match",
    [
        (("2019-01-02", "2019-01-01", 3600), "end="),
        (("2019-01-01", "2019-01-02", 0), "step_s"),
        (("2019-01-01", "2019-01-02", "x"), "step_s"),
        (("2019-13-01", "2019-01-02", 3600), "start="),
    ],
)
def test_time_grid_errors(args, match):
    with pytest.raises(ConfigError, match=match):
        eph.time_grid(*args)


@pytest.mark.parametrize("start, end", [("1899-01-01", "1900-01-01"), ("2053-01-01", "2054-01-01")])
def test_outside_ephemeris_raises_naming_range(start, end):
    with pytest.raises(EphemerisRangeError, match="1899-07-30 to 2053-10-08"):
        eph.time_grid(start, end, 86400)
    with pytest.raises(EphemerisRangeError, match="DE421"):
        eph.sun_in_crater_frame(np.array([start, end], dtype="datetime64[ns]"), -85.0, 0.0)


def test_range_constants_inside_de421():
    seg = eph._de421().segments[0].spk_segment
    ts = eph._timescale()
    start = ts.utc(*[int(x) for x in str(eph.EPHEMERIS_START)[:10].split("-")])
    end = ts.utc(*[int(x) for x in str(eph.EPHEMERIS_END)[:10].split("-")])
    # >= 0.5 day inside the kernel: light time (499 s) and TDB-UTC (~70 s) fit easily
    assert start.tdb - seg.start_jd > 0.5 and seg.end_jd - end.tdb > 0.5
    # the edges themselves evaluate without error
    eph.sun_in_crater_frame(np.array([eph.EPHEMERIS_START, eph.EPHEMERIS_END]), -85.0, 0.0)


def test_bad_inputs():
    with pytest.raises(ConfigError, match="lat_deg"):
        eph.sun_in_crater_frame(["2019-01-01"], -91.0, 0.0)
    with pytest.raises(ConfigError, match="moon_frame"):
        eph.sun_in_crater_frame(["2019-01-01"], -85.0, 0.0, moon_frame="iau2015")
    with pytest.raises(ConfigError, match="correction"):
        eph.sun_in_crater_frame(["2019-01-01"], -85.0, 0.0, correction="true")
    with pytest.raises(ConfigError, match="times"):
        eph.sun_in_crater_frame(["not a date"], -85.0, 0.0)
