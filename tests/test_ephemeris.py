"""Tests for crater_thermal.ephemeris.

The reference is skyfield's own machinery, independent of our code paths: the
MOON_ME_DE421 frame built from the NAIF kernels in ../shared/ephemeris/
(skipped when that folder is absent), a site built with
``PlanetaryConstants.build_latlon_degrees`` and the Sun's apparent alt/az from
``site.at(t).observe(sun).apparent(deflectors=())`` -- the same "apparent"
definition (light time + aberration, no deflection) our default uses.
"""

from __future__ import annotations

import datetime as dt
import time

import numpy as np
import pytest

import os
from pathlib import Path

from conftest import REPO, SHARED_EPHEMERIS
from crater_thermal import ephemeris as eph
from crater_thermal.constants import AU, MOON_RADIUS
from crater_thermal.errors import ConfigError, EphemerisRangeError



def _find_kernels() -> Path:
    """The shared lunar kernels: $CRATER_THERMAL_MOON_KERNELS, ../shared/ephemeris of the
    checkout, or ../../shared/ephemeris (a git worktree under wt/)."""
    candidates = [os.environ.get("CRATER_THERMAL_MOON_KERNELS"), SHARED_EPHEMERIS,
                  REPO.parent.parent / "shared" / "ephemeris"]
    for c in candidates:
        if c and all((Path(c) / n).is_file() for n in eph.DE421_KERNEL_FILES):
            return Path(c)
    return SHARED_EPHEMERIS


SHARED_EPHEMERIS = _find_kernels()
KERNELS_PRESENT = all((SHARED_EPHEMERIS / n).is_file() for n in eph.DE421_KERNEL_FILES)
needs_kernels = pytest.mark.skipif(not KERNELS_PRESENT, reason=f"no lunar kernels in {SHARED_EPHEMERIS}")

SITES = [(-80.0, 0.0), (-85.0, 37.0), (-88.0, -120.0), (-90.0, 0.0), (0.0, -45.0), (45.0, 10.0)]


def _angle_deg(u, v):
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def skyfield_reference():
    """Function (times, lat, lon) -> (unit ENU vectors, distance [m]) from skyfield + MOON_ME_DE421."""
    from skyfield.api import PlanetaryConstants, load, load_file

    pc = PlanetaryConstants()
    with open(SHARED_EPHEMERIS / "moon_080317.tf", "rb") as fh:
        pc.read_text(fh)
    bpc = open(SHARED_EPHEMERIS / "moon_pa_de421_1900-2050.bpc", "rb")
    pc.read_binary(bpc)
    # the frame kernel has no radii; use the same sphere as crater_thermal [km]
    pc.variables["BODY301_RADII"] = [MOON_RADIUS / 1e3] * 3
    frame = pc.build_frame_named("MOON_ME_DE421")
    ts = load.timescale(builtin=True)
    kernel = load_file(str(eph.de421_path()))

    def reference(times, lat, lon):
        t = ts.from_datetimes(
            [x.replace(tzinfo=dt.timezone.utc) for x in times.astype("datetime64[us]").astype(object)]
        )
        site = kernel["moon"] + pc.build_latlon_degrees(frame, lat, lon)
        alt, az, dist = site.at(t).observe(kernel["sun"]).apparent(deflectors=()).altaz()
        ca = np.cos(alt.radians)
        enu = np.stack([np.sin(az.radians) * ca, np.cos(az.radians) * ca, np.sin(alt.radians)], axis=-1)
        return enu, dist.m

    yield reference
    bpc.close()
    kernel.close()


@pytest.fixture(scope="module")
def times_2016_2020():
    # 3.3-day steps sample all phases of the month and the year (443 samples)
    return eph.time_grid("2016-01-01", "2020-01-01", 3.3 * 86400)


@needs_kernels
@pytest.mark.parametrize("lat, lon", SITES)
def test_iau2009_matches_moon_me_de421(skyfield_reference, times_2016_2020, lat, lon):
    ref, ref_dist = skyfield_reference(times_2016_2020, lat, lon)
    u, d = eph.sun_in_crater_frame(times_2016_2020, lat, lon, moon_frame="iau2009")
    # IAU 2009 approximates ME_DE421 to ~0.004 deg (Archinal et al. 2011); 0.01 deg is
    # 1/27 of the Sun's angular radius, far below what the thermal model resolves.
    assert _angle_deg(u, ref).max() < 0.01
    # same DE421 positions and light time: distances agree to 1e-7 (15 m)
    assert np.allclose(d, ref_dist, rtol=1e-7, atol=0)


@needs_kernels
@pytest.mark.parametrize("lat, lon", SITES[:4])
def test_de421_frame_option_matches_reference(skyfield_reference, times_2016_2020, lat, lon):
    ref, _ = skyfield_reference(times_2016_2020, lat, lon)
    u, _ = eph.sun_in_crater_frame(times_2016_2020, lat, lon, moon_frame="de421",
                                   moon_kernels=SHARED_EPHEMERIS)
    # same frame: only the site's rotational aberration (4.6 m/s -> 9e-7 deg) and
    # rounding differ; 1e-5 deg is 1.7e-7 rad
    assert _angle_deg(u, ref).max() < 1e-5


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
    ref = np.array([np.cos(np.radians(66.54)) * np.cos(np.radians(270.0)),
                    np.cos(np.radians(66.54)) * np.sin(np.radians(270.0)), np.sin(np.radians(66.54))])
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


def test_speed_one_year_at_4h():
    times = eph.time_grid("2019-01-01", "2020-01-01", 4 * 3600)
    eph.sun_in_crater_frame(times[:2], -85.0, 0.0)  # warm-up: opens the kernel
    t0 = time.perf_counter()
    u, _ = eph.sun_in_crater_frame(times, -85.0, 0.0)
    elapsed = time.perf_counter() - t0
    assert u.shape == (2191, 3)
    # measured ~0.01 s; 1 s leaves room for a loaded 2-core machine
    assert elapsed < 1.0
