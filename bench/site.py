"""Benchmark: a synthetic polar site from a DEM (issue 9), wall-time split and peak memory.

A 30 km synthetic site (``dem synth``: 87 S, rough terrain, a 10 km and a 4 km crater, 100 m pixels) meshed
by ``mesh dem`` at the resolution that gives ~``--facets`` facets (default 20,000) over a 15 km radius, then
``--record-days`` (default one year, 365 d) recorded after the converged (periodic) start over the year
before it, 4-hour flux steps. Measured in one process:

* ``split_s``: meshing (DEM -> mesh), view factors, direct sunlight, scattering/IR (radiosity), conduction
  (spin-up and record), ephemeris, I/O, from ``simulate.Timer`` (``geometry`` includes the meshing and the
  ray-tracer set-up; ``meshing`` is timed on its own first);
* ``peak_rss_GB``: the process's peak resident memory (``ru_maxrss``);
* ``per_facet``: with ``--compare``, the same period for the idealized crater generator at the same facet
  count, and the ratio site / crater of the run time per facet (issue 9: must not be slower per facet).

Prints one JSON object on its last stdout line and writes bench/results/site.json (``--out`` to change).
Usage: ``python bench/site.py [--facets 20000] [--record-days 365] [--spinup-days 365.25]
[--sun-method rays|horizon] [--compare] [--terrain site|crater] [--out PATH]``. With ``--terrain crater`` the DEM is
the generator's 10 km crater rasterized (25 m pixels) and meshed out to the generator mesh's outer edge (rim
plus outer flank, 7.64 km): ``--compare`` then times the DEM path and the generator path on the same terrain
and area.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import config, geometry, io, simulate, terrain  # noqa: E402

LAT, LON = -87.0, 45.0
RADIUS_KM = 15.0

CASE = """
name = "{name}"
[crater]
{crater}
[location]
lat_deg = {lat}
lon_deg = {lon}
[period]
start = "2019-01-01T00:00:00"
end = "{end}"
spinup = "periodic"
spinup_days = {spinup_days!r}
[steps]
flux_step_hours = 4.0
[sun]
method = "{sun_method}"
"""


def _run(tmp: Path, name: str, crater: str, end: str, spinup_days: float, sun_method: str) -> dict:
    path = tmp / f"{name}.toml"
    path.write_text(
        CASE.format(name=name, crater=crater, lat=LAT, lon=LON, end=end, spinup_days=spinup_days, sun_method=sun_method)
    )
    case = config.load_case(path)
    timer = simulate.Timer()
    t = time.perf_counter()
    out = simulate.run_case(case, tmp / f"{name}.nc", progress=False, timer=timer)
    total = time.perf_counter() - t
    ds = io.open_run(out)
    res = {
        "total_s": round(total, 2),
        "n_facets": int(ds.sizes["facet"]),
        "n_times": int(ds.sizes["time"]),
        "spinup_iterations": int(ds.attrs.get("spinup_iterations", -1)),
        "split_s": {k: round(v, 2) for k, v in timer.split.items()},
    }
    ds.close()
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=20_000)
    ap.add_argument("--record-days", type=float, default=365.0)
    ap.add_argument("--spinup-days", type=float, default=365.25, help="periodic spin-up window [d]")
    ap.add_argument("--sun-method", default="rays", choices=("rays", "horizon"))
    ap.add_argument("--compare", action="store_true", help="also run the idealized crater at the same count")
    ap.add_argument(
        "--terrain",
        default="site",
        choices=("site", "crater"),
        help="site: the 30 km rough synthetic site; crater: the generator's 10 km crater rasterized into a DEM "
        "(25 m pixels) and meshed out to the generator mesh's outer edge, so that --compare times the two paths "
        "on the same terrain",
    )
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "site.json")
    args = ap.parse_args()
    os.environ.setdefault("CRATER_THERMAL_QUIET", "1")
    end = str(np.datetime64("2019-01-01T00:00:00") + np.timedelta64(int(round(args.record_days * 86400)), "s"))
    # resolution for ~facets over the 15 km disk: n ~ 7.26 (R / H)^2 (terrain's equilateral lattice)
    H = RADIUS_KM * 1e3 * math.sqrt(4.0 * math.pi / math.sqrt(3.0) / args.facets)
    result = {
        "description": f"synthetic site at {LAT} deg, {LON} deg: 30 km across (radius {RADIUS_KM} km), "
        "100 m DEM pixels, 10 km and 4 km craters, 15 m RMS roughness",
        "resolution_m": round(H, 1),
        "record_days": args.record_days,
        "spinup_days": args.spinup_days,
        "sun_method": args.sun_method,
        "cpu_count": os.cpu_count(),
        "load_average_at_start": os.getloadavg()[0],
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        os.environ.setdefault("CRATER_THERMAL_CACHE", str(tmp / "cache"))  # a cold cache: every stage is paid
        radius_km = RADIUS_KM
        if args.terrain == "crater":
            # out to where the generator's mesh ends (the outer rim flank), so that both paths mesh the
            # same terrain over the same area
            radius_km = 5.0 + geometry.crater_dimensions(10.0)["rim_width"]
            H = radius_km * 1e3 * math.sqrt(4.0 * math.pi / math.sqrt(3.0) / args.facets)
            result["description"] = (
                f"the 10 km Table 7.1 crater as a DEM (25 m pixels) at {LAT} deg, {LON} deg, meshed to "
                f"{radius_km:.2f} km (the generator mesh's outer edge)"
            )
            result["resolution_m"] = round(H, 1)
            z, tr, wkt = terrain.synthetic_heights(LAT, LON, 2 * radius_km + 2.0, 25.0, craters=[(10.0, 0.0, 0.0)])
        else:
            z, tr, wkt = terrain.synthetic_heights(
                LAT, LON, 40.0, 100.0, craters=[(10.0, 0.0, 0.0), (4.0, 8.0, -6.0)], roughness_m=15.0, seed=1
            )
        dem = terrain.write_geotiff(tmp / "site.tif", z, tr, wkt)
        # warm-up: numba compilation is not what we measure
        warm = 'kind = "dem"\ndem = "site.tif"\nradius_km = 2.0\nresolution_m = 400.0'
        _run(tmp, "warm", warm, "2019-01-02T00:00:00", 29.53, args.sun_method)
        t = time.perf_counter()
        mesh = terrain.site_mesh(dem, LAT, LON, radius_km, H)
        result["meshing_s"] = round(time.perf_counter() - t, 2)
        crater = f'kind = "dem"\ndem = "site.tif"\nradius_km = {radius_km}\nresolution_m = {H!r}'
        site = _run(tmp, "site", crater, end, args.spinup_days, args.sun_method)
        result["site"] = site
        result["n_facets"] = mesh.n_facets
        if args.compare:
            gen = geometry.crater_mesh(10.0, mesh.n_facets)
            geometry.save_mesh(gen, tmp / "crater.ply")
            cr = _run(tmp, "crater", 'kind = "mesh"\nmesh = "crater.ply"', end, args.spinup_days, args.sun_method)
            result["crater"] = cr
            result["per_facet_ratio_site_over_crater"] = round(
                (site["total_s"] / site["n_facets"]) / (cr["total_s"] / cr["n_facets"]), 3
            )
    result["peak_rss_GB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 3)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
