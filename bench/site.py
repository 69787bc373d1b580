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

``--roughness-m`` sets the site's RMS roughness (default 15 m; 0 gives the same craters on smooth ground).

``--operator-only`` runs no year: it builds the compressed view-factor operator of the site and of the
generator crater at the same facet count, at each ``--tolerances`` value (default 1e-3 and 1e-2), and
reports what it stores (entries, mean far-block rank, bytes), its build time and the time of one product
with 1 and with 8 right-hand sides (median of repeats), so that the radiative coupling's share of the
per-facet cost can be read per terrain (default output bench/results/site_operator.json).

Prints one JSON object on its last stdout line and writes bench/results/site.json (``--out`` to change).
Usage: ``python bench/site.py [--facets 20000] [--record-days 365] [--spinup-days 365.25]
[--sun-method rays|horizon] [--compare] [--terrain site|crater] [--roughness-m 15]
[--operator-only [--tolerances 1e-3 1e-2]] [--out PATH]``. With ``--terrain crater`` the DEM is
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

from crater_thermal import (  # noqa: E402
    config,
    geometry,
    io,
    runner,  # noqa: E402
    simulate,
    terrain,
)

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
    out = runner.run_case(case, tmp / f"{name}.nc", progress=False, timer=timer)
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


def _operator_stats(mesh, tolerances) -> list[dict]:
    """Compressed operator of ``mesh`` at each tolerance: what it stores and what a product costs [s]."""
    from crater_thermal import vfoperator
    from crater_thermal.raytrace import RayTracer

    tracer = RayTracer(mesh)
    rng = np.random.default_rng(0)
    x1 = rng.random(mesh.n_facets)
    x8 = rng.random((mesh.n_facets, 8))
    out = []
    for tol in tolerances:
        t = time.perf_counter()
        op = vfoperator.compressed_view_factors(mesh, tracer, tolerance=tol)
        build = time.perf_counter() - t
        times = {}
        for name, x, reps in (("product_1rhs_s", x1, 40), ("product_8rhs_s", x8, 10)):
            op @ x  # first call: thread pool, work split
            samples = []
            for _ in range(reps):
                t = time.perf_counter()
                op @ x
                samples.append(time.perf_counter() - t)
            times[name] = float(np.median(samples))
        st = op.stats
        out.append(
            {
                "tolerance": tol,
                "build_s": round(build, 2),
                "stored_entries": int(st["lowrank_numbers"] + st["sparse_pairs"]),
                "lowrank_numbers": int(st["lowrank_numbers"]),
                "sparse_pairs": int(st["sparse_pairs"]),
                "lowrank_blocks": int(st["lowrank_blocks"]),
                "mean_rank": round(float(st["mean_rank"]), 2),
                "MB": round(op.nbytes / 1e6, 1),
                **{k: round(v, 5) for k, v in times.items()},
            }
        )
    return out


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
    ap.add_argument("--roughness-m", type=float, default=15.0, help="site's RMS roughness [m]")
    ap.add_argument("--operator-only", action="store_true", help="compare the view-factor operators only")
    ap.add_argument("--tolerances", type=float, nargs="+", default=[1e-3, 1e-2])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.out is None:
        args.out = REPO / "bench" / "results" / ("site_operator.json" if args.operator_only else "site.json")
    os.environ.setdefault("CRATER_THERMAL_QUIET", "1")
    end = str(np.datetime64("2019-01-01T00:00:00") + np.timedelta64(int(round(args.record_days * 86400)), "s"))
    # resolution for ~facets over the 15 km disk: n ~ 7.26 (R / H)^2 (terrain's equilateral lattice)
    H = RADIUS_KM * 1e3 * math.sqrt(4.0 * math.pi / math.sqrt(3.0) / args.facets)
    result = {
        "description": f"synthetic site at {LAT} deg, {LON} deg: 30 km across (radius {RADIUS_KM} km), "
        f"100 m DEM pixels, 10 km and 4 km craters, {args.roughness_m:g} m RMS roughness",
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
                LAT,
                LON,
                40.0,
                100.0,
                craters=[(10.0, 0.0, 0.0), (4.0, 8.0, -6.0)],
                roughness_m=args.roughness_m,
                seed=1,
            )
        dem = terrain.write_geotiff(tmp / "site.tif", z, tr, wkt)
        if args.operator_only:
            mesh = terrain.site_mesh(dem, LAT, LON, radius_km, H)
            gen = geometry.crater_mesh(10.0, mesh.n_facets)
            _operator_stats(geometry.crater_mesh(10.0, 2000), args.tolerances[:1])  # numba warm-up
            result["n_facets"] = mesh.n_facets
            result["site"] = _operator_stats(mesh, args.tolerances)
            result["crater"] = _operator_stats(gen, args.tolerances)
            result["ratio_site_over_crater"] = [
                {
                    "tolerance": a["tolerance"],
                    "stored_entries": round(a["stored_entries"] / b["stored_entries"], 2),
                    "product_1rhs": round(a["product_1rhs_s"] / b["product_1rhs_s"], 2),
                    "product_8rhs": round(a["product_8rhs_s"] / b["product_8rhs_s"], 2),
                }
                for a, b in zip(result["site"], result["crater"])
            ]
            _finish(result, args.out)
            return
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
    _finish(result, args.out)


def _finish(result: dict, out: Path) -> None:
    result["peak_rss_GB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 3)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
