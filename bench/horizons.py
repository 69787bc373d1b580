"""Benchmark: horizon-map direct sunlight against the ray-traced Sun disk, at ~10k and ~30k facets.

Run:  PYTHONPATH=$PWD python bench/horizons.py [--facets 10000 30000] [--steps 48] [--rough]

Per mesh (the 10 km Table 7.1 crater at each facet count; with ``--rough`` also the rough synthetic
site of crater_thermal.reference.rough_site at the first count), in one process, one after the other:

* ``build_s``: the horizon map (no cache), the occlusion rays it traced (per facet and azimuth: 15 for
  a plain bisection) and their rate;
* ``rays_step_s``: the reference :func:`illumination.direct_irradiance` (default 37-patch disk) per
  step, over ``--steps`` Sun positions spread evenly over a lunation at 85 deg S;
* ``horizon_step_s``: :func:`horizons.direct_irradiance_horizon` per step over the same positions
  (best of 3);
* ``step_speedup = rays_step_s / horizon_step_s`` and ``break_even_steps = build_s / (rays_step_s -
  horizon_step_s)`` (a year at 4 h steps is 2190 steps);
* accuracy on those steps: the mean over steps of the per-facet flux, max |difference| [W m-2] and the
  area-weighted relative difference.

The machine is shared: ratios are taken within one run.  The last stdout line is one JSON object,
also written to ``bench/results/horizons.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from crater_thermal import ephemeris, horizons, illumination
from crater_thermal.geometry import crater_mesh
from crater_thermal.raytrace import RayTracer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from crater_thermal.reference import rough_site  # noqa: E402


def _sun(n_steps: int):
    times = ephemeris.time_grid("2024-01-11", "2024-02-09T12:00", 3600.0)
    pick = np.linspace(0, len(times) - 1, n_steps).round().astype(int)
    return ephemeris.sun_in_crater_frame(times[pick], -85.0, 0.0)


def _one(name: str, mesh, s, r, n_az: int) -> dict:
    tracer = RayTracer(mesh)
    counted = [0]
    run_raw = tracer.run_raw

    def counting(o32, d32, t32=None, query="OCCLUDED"):
        counted[0] += len(o32)
        return run_raw(o32, d32, t32, query)

    tracer.run_raw = counting  # count the rays the build traces
    t0 = time.perf_counter()
    hmap = horizons.horizon_map(mesh, tracer, n_azimuths=n_az)
    build_s = time.perf_counter() - t0
    tracer.run_raw = run_raw
    n_rays = counted[0]
    t0 = time.perf_counter()
    E_rays = illumination.direct_irradiance(mesh, tracer, s, r, disk=illumination.sun_disk())
    rays_s = time.perf_counter() - t0
    hor = []
    for _ in range(3):
        t0 = time.perf_counter()
        E_hor = horizons.direct_irradiance_horizon(mesh, hmap, s, r)
        hor.append(time.perf_counter() - t0)
    nt = s.shape[0]
    rays_step, hor_step = rays_s / nt, min(hor) / nt
    I_r, I_h = E_rays.mean(axis=0), E_hor.mean(axis=0)
    w = mesh.areas
    return {
        "mesh": name,
        "facets": mesh.n_facets,
        "n_azimuths": n_az,
        "build_s": round(build_s, 3),
        "build_rays": int(n_rays),
        "build_rays_per_facet_azimuth": round(n_rays / (mesh.n_facets * n_az), 2),
        "build_rays_per_s": round(n_rays / build_s, 0),
        "horizon_map_mb": round(hmap.elevation.nbytes / 2**20, 2),
        "steps": nt,
        "rays_step_s": rays_step,
        "horizon_step_s": hor_step,
        "step_speedup": round(rays_step / hor_step, 1),
        "break_even_steps": round(build_s / max(rays_step - hor_step, 1e-12), 1),
        "year_4h_rays_s": round(2190 * rays_step, 1),
        "year_4h_horizon_s": round(build_s + 2190 * hor_step, 1),
        "max_abs_diff_mean_flux_W_m2": round(float(np.abs(I_h - I_r).max()), 3),
        "area_weighted_rel_diff": float((w * (I_h - I_r)).sum() / (w * I_r).sum()),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, nargs="+", default=[10_000, 30_000])
    ap.add_argument("--steps", type=int, default=48)
    ap.add_argument("--n-azimuths", type=int, default=horizons.DEFAULT_N_AZIMUTHS)
    ap.add_argument("--rough", action="store_true", help="also the rough synthetic site at the first count")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "horizons.json"))
    args = ap.parse_args(argv)

    s, r = _sun(args.steps)
    # warm up numba (compiled or loaded from cache) outside the timings
    small = crater_mesh(10.0, 200)
    tr = RayTracer(small)
    horizons.direct_irradiance_horizon(small, horizons.horizon_map(small, tr, n_azimuths=16), s[:2], r[:2])
    illumination.direct_irradiance(small, tr, s[:2], r[:2], disk=illumination.sun_disk())

    rows = []
    for n in args.facets:
        rows.append(_one(f"crater10km_{n}", crater_mesh(10.0, n), s, r, args.n_azimuths))
        print(json.dumps(rows[-1]), flush=True)
    if args.rough:
        rows.append(_one(f"rough_{args.facets[0]}", rough_site(args.facets[0]), s, r, args.n_azimuths))
        print(json.dumps(rows[-1]), flush=True)
    result = {"benchmark": "horizons", "python": platform.python_version(), "machine": platform.machine(), "rows": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
