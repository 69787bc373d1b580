"""Sun position seen from a site on the Moon, in a crater-local frame.

This is the only module that imports :mod:`skyfield`.

Data and models
---------------
* **Sun and Moon positions**: JPL DE421 (``de421.bsp``), the copy shipped by the
  ``skyfield-data`` package, opened with :func:`skyfield.api.load_file` (never
  downloaded). UTC to TT/TDB uses skyfield's built-in leap-second and Delta T
  tables (``load.timescale(builtin=True)``); nothing is fetched from the network.
* **Moon orientation** (``moon_frame``):

  - ``"iau2009"`` (default, no kernel files): the IAU/WGCCRE 2009 lunar rotation
    model (Archinal et al. 2011, Celest. Mech. Dyn. Astr. 109, 101-135, Table 2:
    pole right ascension alpha0, declination delta0 and prime meridian W with the
    13 libration arguments E1..E13). Its body-fixed frame approximates the lunar
    Mean Earth/polar axis (ME) frame; it agrees with MOON_ME_DE421 to about
    0.004 deg over 2016-2020 (measured by ``tests/test_ephemeris.py``).
  - ``"de421"``: the DE421 numerically integrated libration angles (frame
    MOON_PA_DE421 from ``moon_pa_de421_1900-2050.bpc``) followed by the constant
    PA->ME rotation of ``moon_080317.tf``, i.e. the frame MOON_ME_DE421 the thesis
    used. These NAIF kernels are not distributed with crater_thermal: pass the
    folder holding both files as ``moon_kernels``. The binary PCK covers
    1900-01-01 to 2050-01-01 only.

* **Which Sun direction** (``correction``): the default ``"apparent"`` is the
  direction from which sunlight arrives at the Moon at the given time: the Sun's
  position at emission (light-time corrected, ~499 s earlier) plus the stellar
  aberration due to the Moon's barycentric velocity (~30 km/s, shifts the
  direction by up to ~20.5 arcsec = 0.0057 deg). Gravitational deflection is not
  applied (for the Sun's own centre the Sun's deflection is zero by symmetry;
  planets' is < 1e-7 deg). This is the physically relevant direction for
  shadows and incidence angles in the Moon's rest frame. ``"light_time"`` omits
  the aberration and ``"geometric"`` uses the instantaneous Sun-Moon vector; the
  three differ by less than 0.006 deg, far below the Sun's 0.27 deg angular
  radius. The distance returned is the light-time corrected distance in every
  case except ``"geometric"`` (they differ by < 1e-7 relative).
* **Crater frame**: the site lies on a sphere of radius
  :data:`~crater_thermal.constants.MOON_RADIUS` at planetocentric latitude
  ``lat_deg`` and east longitude ``lon_deg`` of the body-fixed frame; the frame is
  local East-North-Up (x east, y north, z up along the sphere's normal). The
  Sun vector is taken from the site (topocentric), not from the Moon's centre
  (parallax <= 0.0007 deg). At a pole (lat = +-90 deg) East and North are the
  usual formulas evaluated there, i.e. the limits along the meridian ``lon_deg``:
  at -90 deg, y (north) points along the body-fixed direction of longitude
  ``lon_deg`` and x (east) 90 deg east of it; the frame stays right-handed.

Times are numpy ``datetime64`` (UTC) at the edges; they are converted to TDB for
the ephemeris and the rotation model.
"""

from __future__ import annotations

import atexit
import datetime as _dt
import functools
import threading
from pathlib import Path
from typing import Iterable, Tuple, Union

import numpy as np

from crater_thermal.choices import (
    EPHEMERIS_END,
    EPHEMERIS_START,
    MOON_FRAMES,
    SUN_CORRECTIONS,
    ephemeris_span,
)
from crater_thermal.constants import AU, MOON_RADIUS
from crater_thermal.errors import ConfigError, EphemerisRangeError

__all__ = [
    "EPHEMERIS_START",
    "EPHEMERIS_END",
    "MOON_FRAMES",
    "SUN_CORRECTIONS",
    "DE421_KERNEL_FILES",
    "de421_path",
    "to_datetime64",
    "time_grid",
    "check_time_range",
    "ephemeris_range",
    "moon_rotation_iau2009",
    "moon_rotation",
    "sun_position_moon_fixed",
    "enu_basis",
    "sun_in_crater_frame",
    "sun_elevation_azimuth_deg",
    "subsolar_latitude_deg",
    "subsolar_point_deg",
]

# The usable spans and the allowed frames / corrections are declared in crater_thermal.choices (the
# case schema validates against them without importing this module) and re-exported here.
#: Kernel files needed by ``moon_frame="de421"`` (text frame kernel, binary PCK).
DE421_KERNEL_FILES = ("moon_080317.tf", "moon_pa_de421_1900-2050.bpc")

_J2000_JD = 2451545.0
_lock = threading.Lock()
_open_files: list = []  # kernels kept open for the life of the process


@atexit.register
def _close_kernels() -> None:
    while _open_files:
        try:
            _open_files.pop().close()
        except Exception:  # pragma: no cover - best effort at shutdown
            pass


TimeLike = Union[str, np.datetime64, _dt.datetime, Iterable]


# --------------------------------------------------------------------------- data
def de421_path() -> Path:
    """Path of ``de421.bsp`` inside the installed ``skyfield-data`` package.

    ``skyfield_data.get_skyfield_data_path()`` is avoided on purpose: it warns
    about the (unused) expired ``finals2000A.all`` file.
    """
    import skyfield_data

    path = Path(skyfield_data.__file__).resolve().parent / "data" / "de421.bsp"
    if not path.is_file():  # pragma: no cover - broken installation
        raise FileNotFoundError(f"de421.bsp not found in the skyfield-data package at {path}")
    return path


@functools.lru_cache(maxsize=1)
def _timescale():
    from skyfield.api import load

    return load.timescale(builtin=True)


@functools.lru_cache(maxsize=1)
def _de421():
    """The DE421 kernel, opened once per process and kept open (read-only)."""
    from skyfield.api import load_file

    kernel = load_file(str(de421_path()))
    _open_files.append(kernel)
    return kernel


@functools.lru_cache(maxsize=4)
def _de421_moon_frame(kernel_dir: str):
    from skyfield.api import PlanetaryConstants

    folder = Path(kernel_dir)
    missing = [n for n in DE421_KERNEL_FILES if not (folder / n).is_file()]
    if missing:
        raise ConfigError(
            f"moon_kernels={str(folder)!r} lacks {', '.join(missing)}; "
            f"moon_frame='de421' needs {' and '.join(DE421_KERNEL_FILES)} in that folder"
        )
    pc = PlanetaryConstants()
    with open(folder / DE421_KERNEL_FILES[0], "rb") as fh:
        pc.read_text(fh)
    # read_binary keeps the file open for later reads: it lives for the process.
    fh = open(folder / DE421_KERNEL_FILES[1], "rb")
    _open_files.append(fh)
    pc.read_binary(fh)
    return pc.build_frame_named("MOON_ME_DE421")


# -------------------------------------------------------------------------- times
def to_datetime64(value: TimeLike, name: str = "time") -> np.ndarray:
    """Convert times to ``datetime64[ns]`` (UTC).

    Parameters
    ----------
    value : str, datetime64, datetime.datetime, or a sequence/array of these
        ISO 8601 strings ("2019-01-01", "2019-01-01T04:00"), numpy datetime64
        of any unit, or naive (taken as UTC) / aware ``datetime`` objects.
    name : str
        Parameter name used in error messages.

    Returns
    -------
    times : ndarray of datetime64[ns]
        Same shape as ``value`` (0-d for a scalar).

    Raises
    ------
    ConfigError
        If a value cannot be read as a date.
    """
    try:
        if isinstance(value, _dt.datetime) and value.tzinfo is not None:
            value = value.astimezone(_dt.timezone.utc).replace(tzinfo=None)
        if isinstance(value, (list, tuple)):
            value = [
                v.astimezone(_dt.timezone.utc).replace(tzinfo=None)
                if isinstance(v, _dt.datetime) and v.tzinfo is not None
                else v
                for v in value
            ]
        arr = np.asarray(value)
        if arr.dtype.kind in "US":
            arr = np.array([np.datetime64(str(s).strip().rstrip("Zz")) for s in arr.ravel()]).reshape(arr.shape)
        out = arr.astype("datetime64[ns]")
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(
            f"{name}={value!r} is not a date/time; use ISO 8601 such as '2019-01-01' or "
            f"'2019-01-01T04:00:00', or numpy datetime64 ({exc})"
        ) from None
    if out.dtype.kind != "M" or np.any(np.isnat(out)):
        raise ConfigError(f"{name}={value!r} is not a date/time (NaT or non-date values)")
    return out


def ephemeris_range(moon_frame: str = "iau2009") -> Tuple[np.datetime64, np.datetime64, str]:
    """Usable time span (UTC) and a description of its source.

    Returns
    -------
    start, end : datetime64[ns]
    what : str
        e.g. "DE421 (de421.bsp)".
    """
    return ephemeris_span(moon_frame)


def check_time_range(times: np.ndarray, moon_frame: str = "iau2009", name: str = "times") -> None:
    """Raise :class:`EphemerisRangeError` if any time lies outside the ephemeris.

    Parameters
    ----------
    times : ndarray of datetime64[ns]
    moon_frame : {"iau2009", "de421"}
        ``"de421"`` also requires the libration kernel's 1900-2050 span.
    name : str
        Parameter name for the message.
    """
    t = np.asarray(times, dtype="datetime64[ns]")
    if t.size == 0:
        return
    lo, hi = t.min(), t.max()
    start, end, what = ephemeris_range(moon_frame)
    if lo < start or hi > end:
        bad = lo if lo < start else hi
        raise EphemerisRangeError(
            f"{name}: {np.datetime_as_string(bad, unit='s')} is outside the range of {what}: "
            f"{np.datetime_as_string(start, unit='D')} to {np.datetime_as_string(end, unit='D')} (UTC)"
        )


def time_grid(start: TimeLike, end: TimeLike, step_s: float, include_end: bool = True) -> np.ndarray:
    """Regular grid of UTC times.

    Parameters
    ----------
    start, end : str or datetime64 or datetime
        First and last instant (ISO 8601 strings are accepted).
    step_s : float
        Spacing [s]; must be positive. Rounded to whole nanoseconds.
    include_end : bool
        If true (default), ``end`` is the last sample when ``end - start`` is a
        whole number of steps; otherwise the grid stops before ``end``. A grid
        never goes past ``end``.

    Returns
    -------
    times : (nt,) ndarray of datetime64[ns]
        ``start + k * step_s``.

    Raises
    ------
    ConfigError
        For an unreadable date, ``end <= start`` or ``step_s <= 0``.
    EphemerisRangeError
        If the grid leaves the DE421 range.
    """
    t0 = to_datetime64(start, "start")
    t1 = to_datetime64(end, "end")
    if t0.ndim or t1.ndim:
        raise ConfigError("start and end must be single dates, not arrays")
    try:
        step = float(step_s)
    except (TypeError, ValueError):
        raise ConfigError(f"step_s={step_s!r} is not a number; allowed: > 0 seconds") from None
    if not np.isfinite(step) or step <= 0:
        raise ConfigError(f"step_s={step_s!r} out of range; allowed: > 0 seconds")
    if t1 <= t0:
        raise ConfigError(
            f"end={np.datetime_as_string(t1, unit='s')} must be after start={np.datetime_as_string(t0, unit='s')}"
        )
    step_ns = np.timedelta64(int(round(step * 1e9)), "ns")
    if step_ns <= np.timedelta64(0, "ns"):
        raise ConfigError(f"step_s={step_s!r} out of range; allowed: >= 1e-9 seconds")
    span = (t1 - t0).astype(np.int64)
    n = span // step_ns.astype(np.int64)
    if not include_end and n * step_ns.astype(np.int64) == span:
        n -= 1
    times = t0 + np.arange(n + 1, dtype=np.int64) * step_ns
    check_time_range(times[[0, -1]], name="time grid")
    return times


def _skyfield_time(times: np.ndarray):
    """datetime64[ns] UTC array -> skyfield ``Time`` (vectorised, exact to ~1 us)."""
    ts = _timescale()
    days = times.astype("datetime64[D]")
    sod = (times - days).astype(np.int64) * 1e-9  # second of day, 0 <= sod < 86400
    y = days.astype("datetime64[Y]").astype(np.int64) + 1970
    m = days.astype("datetime64[M]").astype(np.int64) % 12 + 1
    d = (days - days.astype("datetime64[M]")).astype(np.int64) + 1
    return ts.utc(y, m, d, 0, 0, sod)


def _prepare_times(times: TimeLike, moon_frame: str) -> np.ndarray:
    t = np.atleast_1d(to_datetime64(times, "times"))
    if t.ndim != 1:
        raise ConfigError(f"times must be one-dimensional, got shape {t.shape}")
    if moon_frame not in MOON_FRAMES:
        raise ConfigError(f"moon_frame={moon_frame!r} is not one of {', '.join(MOON_FRAMES)}")
    check_time_range(t, moon_frame)
    return t


# ------------------------------------------------------------- Moon orientation
# IAU/WGCCRE 2009 lunar model (Archinal et al. 2011, Table 2). Angles in degrees,
# d = days and T = Julian centuries (36525 d) of TDB from J2000.0.
_E_CONST = np.array(
    [125.045, 250.089, 260.008, 176.625, 357.529, 311.589, 134.963, 276.617, 34.226, 15.134, 119.743, 239.961, 25.053]
)
_E_RATE = np.array(
    [
        -0.0529921,
        -0.1059842,
        13.0120009,
        13.3407154,
        0.9856003,
        26.4057084,
        13.0649930,
        0.3287146,
        1.7484877,
        -0.1589763,
        0.0036096,
        0.1643573,
        12.9590088,
    ]
)  # [deg/day]
_RA_SIN = np.array([-3.8787, -0.1204, 0.0700, -0.0172, 0.0, 0.0072, 0.0, 0.0, 0.0, -0.0052, 0.0, 0.0, 0.0043])
_DEC_COS = np.array([1.5419, 0.0239, -0.0278, 0.0068, 0.0, -0.0029, 0.0009, 0.0, 0.0, 0.0008, 0.0, 0.0, -0.0009])
_W_SIN = np.array(
    [3.5610, 0.1208, -0.0642, 0.0158, 0.0252, -0.0066, -0.0047, -0.0046, 0.0028, 0.0052, 0.0040, 0.0019, -0.0044]
)


def _rot_z(a: np.ndarray) -> np.ndarray:
    """Frame rotations about z by angles ``a`` [rad], shape (n, 3, 3)."""
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, s], -1), np.stack([z, -s, c], -1)], -2)


def _iau2009_angles(d_tdb: np.ndarray):
    """alpha0, delta0, W [deg] of the IAU 2009 Moon model at TDB days ``d_tdb`` from J2000."""
    d = np.asarray(d_tdb, dtype=float)
    T = d / 36525.0
    E = np.deg2rad(_E_CONST + np.multiply.outer(d, _E_RATE))  # (n, 13)
    sinE, cosE = np.sin(E), np.cos(E)
    ra = 269.9949 + 0.0031 * T + sinE @ _RA_SIN
    dec = 66.5392 + 0.0130 * T + cosE @ _DEC_COS
    w = 38.3213 + 13.17635815 * d - 1.4e-12 * d * d + sinE @ _W_SIN
    return ra, dec, w


def _iau2009_rotation_from_days(d_tdb: np.ndarray) -> np.ndarray:
    ra, dec, w = _iau2009_angles(d_tdb)
    return _rot_z(np.deg2rad(w % 360.0)) @ _rot_x(np.deg2rad(90.0 - dec)) @ _rot_z(np.deg2rad(90.0 + ra))


def moon_rotation_iau2009(times: TimeLike) -> np.ndarray:
    """Rotation matrices ICRF -> lunar body-fixed frame, IAU/WGCCRE 2009 model.

    Parameters
    ----------
    times : (nt,) datetime64 (UTC) or ISO strings

    Returns
    -------
    R : (nt, 3, 3) float
        ``v_moon = R @ v_icrf``: R = Rz(W) Rx(90 deg - delta0) Rz(90 deg + alpha0).
    """
    t = _prepare_times(times, "iau2009")
    st = _skyfield_time(t)
    d = (np.asarray(st.whole, dtype=float) - _J2000_JD) + np.asarray(st.tdb_fraction, dtype=float)
    return _iau2009_rotation_from_days(np.atleast_1d(d))


def moon_rotation(times: TimeLike, moon_frame: str = "iau2009", moon_kernels=None) -> np.ndarray:
    """Rotation matrices ICRF -> lunar body-fixed (ME) frame.

    Parameters
    ----------
    times : (nt,) datetime64 (UTC) or ISO strings
    moon_frame : {"iau2009", "de421"}
        Orientation model, see the module docstring.
    moon_kernels : str or Path, optional
        Folder with ``moon_080317.tf`` and ``moon_pa_de421_1900-2050.bpc``;
        required for ``moon_frame="de421"``.

    Returns
    -------
    R : (nt, 3, 3) float
    """
    t = _prepare_times(times, moon_frame)
    if moon_frame == "iau2009":
        return moon_rotation_iau2009(t)
    frame = _de421_frame_or_error(moon_kernels)
    with _lock:
        R = np.asarray(frame.rotation_at(_skyfield_time(t)), dtype=float)
    return np.moveaxis(R.reshape(3, 3, -1), -1, 0)


def _de421_frame_or_error(moon_kernels):
    if moon_kernels is None:
        raise ConfigError(
            "moon_frame='de421' needs moon_kernels=<folder with "
            f"{' and '.join(DE421_KERNEL_FILES)}> (not shipped); use moon_frame='iau2009' otherwise"
        )
    return _de421_moon_frame(str(Path(moon_kernels).resolve()))


# ----------------------------------------------------------------- Sun vectors
def _sun_from_moon_icrf(t: np.ndarray, correction: str) -> np.ndarray:
    """Sun position relative to the Moon's centre, ICRF axes [au], shape (nt, 3)."""
    if correction not in SUN_CORRECTIONS:
        raise ConfigError(f"correction={correction!r} is not one of {', '.join(SUN_CORRECTIONS)}")
    eph = _de421()
    st = _skyfield_time(t)
    with _lock:
        moon, sun = eph["moon"], eph["sun"]
        if correction == "geometric":
            xyz = (sun - moon).at(st).xyz.au
        else:
            astrometric = moon.at(st).observe(sun)
            if correction == "apparent":
                # aberration only: no deflection (see module docstring)
                astrometric = astrometric.apparent(deflectors=())
            xyz = astrometric.xyz.au
    return np.asarray(xyz, dtype=float).reshape(3, -1).T


def sun_position_moon_fixed(
    times: TimeLike, moon_frame: str = "iau2009", *, correction: str = "apparent", moon_kernels=None
) -> np.ndarray:
    """Sun position relative to the Moon's centre in the lunar body-fixed frame.

    Parameters
    ----------
    times : (nt,) datetime64 (UTC) or ISO strings
    moon_frame : {"iau2009", "de421"}
    correction : {"apparent", "light_time", "geometric"}
    moon_kernels : str or Path, optional
        Needed for ``moon_frame="de421"``.

    Returns
    -------
    r : (nt, 3) float [m]
        Body-fixed Cartesian coordinates (x toward lon 0, z toward the north pole).
    """
    t = _prepare_times(times, moon_frame)
    R = moon_rotation(t, moon_frame, moon_kernels)
    r_icrf = _sun_from_moon_icrf(t, correction) * AU
    return np.einsum("nij,nj->ni", R, r_icrf)


def enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Local East-North-Up unit vectors in body-fixed coordinates.

    Parameters
    ----------
    lat_deg, lon_deg : float [deg]
        Planetocentric latitude (-90..90) and east longitude.

    Returns
    -------
    B : (3, 3) float
        Rows are east, north, up: ``v_enu = B @ v_body``.
    """
    lat, lon = _check_latlon(lat_deg, lon_deg)
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    if abs(lat_deg) == 90.0:
        cp = 0.0  # exact pole: keep the up vector exactly polar
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def _check_latlon(lat_deg, lon_deg):
    try:
        lat, lon = float(lat_deg), float(lon_deg)
    except (TypeError, ValueError):
        raise ConfigError(f"lat_deg={lat_deg!r}, lon_deg={lon_deg!r} must be numbers [deg]") from None
    if not np.isfinite(lat) or not -90.0 <= lat <= 90.0:
        raise ConfigError(f"lat_deg={lat_deg!r} out of range; allowed: -90 to 90 [deg]")
    if not np.isfinite(lon):
        raise ConfigError(f"lon_deg={lon_deg!r} must be a finite number [deg]")
    return np.deg2rad(lat), np.deg2rad(lon)


def sun_in_crater_frame(
    times: TimeLike,
    lat_deg: float,
    lon_deg: float,
    moon_frame: str = "iau2009",
    *,
    correction: str = "apparent",
    moon_kernels=None,
    moon_radius_m: float = MOON_RADIUS,
) -> Tuple[np.ndarray, np.ndarray]:
    """Sun direction and distance in the crater frame (x east, y north, z up).

    Parameters
    ----------
    times : (nt,) datetime64 (UTC), or ISO strings
        Sample times; all are computed at once (a year at 4 h steps takes a few
        tens of milliseconds).
    lat_deg, lon_deg : float [deg]
        Crater centre, planetocentric latitude and east longitude.
    moon_frame : {"iau2009", "de421"}
        Moon orientation model (see the module docstring).
    correction : {"apparent", "light_time", "geometric"}
        Which Sun direction; default ``"apparent"`` (light time + aberration).
    moon_kernels : str or Path, optional
        Folder with the DE421 lunar kernels, needed for ``moon_frame="de421"``.
    moon_radius_m : float [m]
        Radius of the sphere the crater centre lies on.

    Returns
    -------
    sun_dirs : (nt, 3) float [unit]
        Unit vectors from the crater centre toward the Sun's centre.
    sun_distance_m : (nt,) float [m]
        Distance from the crater centre to the Sun's centre.

    Raises
    ------
    EphemerisRangeError
        If a time is outside the ephemeris (names the allowed range).
    ConfigError
        For bad latitude, frame name, correction or missing kernels.
    """
    t = _prepare_times(times, moon_frame)
    B = enu_basis(lat_deg, lon_deg)
    r_body = sun_position_moon_fixed(t, moon_frame, correction=correction, moon_kernels=moon_kernels)
    site = float(moon_radius_m) * B[2]
    v = (r_body - site) @ B.T
    dist = np.linalg.norm(v, axis=1)
    return v / dist[:, None], dist


def sun_elevation_azimuth_deg(
    times: TimeLike, lat_deg: float, lon_deg: float, moon_frame: str = "iau2009", **kwargs
) -> Tuple[np.ndarray, np.ndarray]:
    """Sun elevation above the local horizontal and azimuth (from north, toward east).

    Returns
    -------
    elevation_deg, azimuth_deg : (nt,) float [deg]
        Azimuth in [0, 360).
    """
    u, _ = sun_in_crater_frame(times, lat_deg, lon_deg, moon_frame, **kwargs)
    elev = np.rad2deg(np.arcsin(np.clip(u[:, 2], -1.0, 1.0)))
    az = np.rad2deg(np.arctan2(u[:, 0], u[:, 1])) % 360.0
    return elev, az


def subsolar_point_deg(times: TimeLike, moon_frame: str = "iau2009", **kwargs) -> Tuple[np.ndarray, np.ndarray]:
    """Planetocentric latitude and east longitude of the sub-solar point [deg].

    Returns
    -------
    lat_deg : (nt,) float in [-90, 90]
    lon_deg : (nt,) float in (-180, 180]
    """
    r = sun_position_moon_fixed(times, moon_frame, **kwargs)
    lat = np.rad2deg(np.arctan2(r[:, 2], np.hypot(r[:, 0], r[:, 1])))
    lon = np.rad2deg(np.arctan2(r[:, 1], r[:, 0]))
    return lat, lon


def subsolar_latitude_deg(times: TimeLike, moon_frame: str = "iau2009", **kwargs) -> np.ndarray:
    """Planetocentric latitude of the sub-solar point [deg], shape (nt,).

    It stays within about +-1.6 deg (the lunar equator's tilt to the ecliptic).
    """
    return subsolar_point_deg(times, moon_frame, **kwargs)[0]
