"""Write tests/data/sun_moon_me_de421.npz: reference Sun directions in the JPL MOON_ME_DE421 frame.

The reference is skyfield's own machinery, independent of crater_thermal's code paths: the
MOON_ME_DE421 frame built from the NAIF lunar kernels (moon_080317.tf, moon_pa_de421_1900-2050.bpc,
not distributed with crater_thermal), a site built with ``PlanetaryConstants.build_latlon_degrees`` on
a sphere of radius constants.MOON_RADIUS, and the Sun's apparent alt/az from
``site.at(t).observe(sun).apparent(deflectors=())``: light time + aberration, no deflection, the
definition of crater_thermal's default ``correction = "apparent"``. Positions: DE421 (de421.bsp from
the skyfield-data package).

Usage: python tests/data/make_sun_reference.py [KERNEL_FOLDER]   (default: ../shared/ephemeris)

Output arrays: ``times`` (datetime64[ns] UTC, 2016-01-01 to 2020-01-01 every 3.3 d: every phase of
the month and the year), ``sites`` ((n, 2) lat, lon [deg]), ``enu`` ((n_sites, n_times, 3) unit
vectors towards the Sun, x east, y north, z up), ``distance_m`` ((n_sites, n_times) [m]) and the
versions used. float64 throughout: the tests compare at the 1e-6 degree level.
"""

from __future__ import annotations

import datetime as dt
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
SITES = [(-80.0, 0.0), (-85.0, 37.0), (-88.0, -120.0), (-90.0, 0.0), (0.0, -45.0), (45.0, 10.0)]


def main(kernels: Path, out: Path = HERE / "sun_moon_me_de421.npz") -> Path:
    import skyfield
    from skyfield.api import PlanetaryConstants, load, load_file

    sys.path.insert(0, str(REPO))
    from crater_thermal import ephemeris as eph
    from crater_thermal.constants import MOON_RADIUS

    times = eph.time_grid("2016-01-01", "2020-01-01", 3.3 * 86400)
    pc = PlanetaryConstants()
    with open(kernels / "moon_080317.tf", "rb") as fh:
        pc.read_text(fh)
    with open(kernels / "moon_pa_de421_1900-2050.bpc", "rb") as bpc:
        pc.read_binary(bpc)
        pc.variables["BODY301_RADII"] = [MOON_RADIUS / 1e3] * 3  # the frame kernel has no radii [km]
        frame = pc.build_frame_named("MOON_ME_DE421")
        ts = load.timescale(builtin=True)
        kernel = load_file(str(eph.de421_path()))
        t = ts.from_datetimes(
            [x.replace(tzinfo=dt.timezone.utc) for x in times.astype("datetime64[us]").astype(object)]
        )
        enu, dist = [], []
        for lat, lon in SITES:
            site = kernel["moon"] + pc.build_latlon_degrees(frame, lat, lon)
            alt, az, d = site.at(t).observe(kernel["sun"]).apparent(deflectors=()).altaz()
            ca = np.cos(alt.radians)
            enu.append(np.stack([np.sin(az.radians) * ca, np.cos(az.radians) * ca, np.sin(alt.radians)], axis=-1))
            dist.append(d.m)
        kernel.close()
    np.savez_compressed(
        out,
        times=times,
        sites=np.array(SITES),
        enu=np.array(enu),
        distance_m=np.array(dist),
        skyfield_version=skyfield.__version__,
        numpy_version=np.__version__,
    )
    return out


if __name__ == "__main__":
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else REPO.parent / "shared" / "ephemeris"
    print(main(folder.resolve()))
