"""Throughput of illumination.direct_irradiance on the thesis crater (10 km, 502 facets).

Synthetic Sun track for a crater at latitude LAT (default -86 deg): hour angle sweeps one lunar
day per 29.53 days, declination +-1.54 deg over a year, 4-hour steps for 4 years (~8,800 steps).
Writes a JSON line: time steps, facets, patches, wall seconds, rays traced and
facet-time-patch evaluations per second.

    PYTHONPATH=$PWD python bench/direct_irradiance.py [--lat -86] [--rings 4] [--steps 8766]
"""

import argparse
import json
import time

import numpy as np

from crater_thermal import illumination as il
from crater_thermal.constants import AU, LUNAR_DAY, YEAR
from crater_thermal.geometry import crater_mesh
from crater_thermal.raytrace import RayTracer


def sun_track(lat_deg, n_steps, step_s=4 * 3600.0):
    t = np.arange(n_steps) * step_s
    lat = np.deg2rad(lat_deg)
    dec = np.deg2rad(1.54) * np.sin(2 * np.pi * t / YEAR)
    h = 2 * np.pi * t / LUNAR_DAY
    # ENU components of the Sun direction at latitude lat
    east = -np.cos(dec) * np.sin(h)
    north = np.cos(lat) * np.sin(dec) - np.sin(lat) * np.cos(dec) * np.cos(h)
    up = np.sin(lat) * np.sin(dec) + np.cos(lat) * np.cos(dec) * np.cos(h)
    s = np.stack([east, north, up], 1)
    return s / np.linalg.norm(s, axis=1)[:, None], AU * (1 + 0.017 * np.cos(2 * np.pi * t / YEAR))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--lat", type=float, default=-86.0)
    ap.add_argument("--rings", type=int, default=il.DEFAULT_N_RINGS)
    ap.add_argument("--steps", type=int, default=8766)
    a = ap.parse_args()
    mesh = crater_mesh(10.0, 502)
    tracer = RayTracer(mesh)
    s, r = sun_track(a.lat, a.steps)
    disk = il.sun_disk(a.rings)
    calls = {"rays": 0}
    orig = tracer.run_raw

    def counting(o, d, *args, **kw):
        calls["rays"] += len(o)
        return orig(o, d, *args, **kw)

    tracer.run_raw = counting
    t0 = time.perf_counter()
    E = il.direct_irradiance(mesh, tracer, s, r, disk=disk)
    wall = time.perf_counter() - t0
    evals = a.steps * mesh.n_facets * disk.n_patches
    print(
        json.dumps(
            {
                "lat_deg": a.lat,
                "steps": a.steps,
                "facets": mesh.n_facets,
                "patches": disk.n_patches,
                "wall_s": round(wall, 2),
                "rays_traced": calls["rays"],
                "evaluations_per_s": round(evals / wall),
                "rays_per_s": round(calls["rays"] / wall),
                "mean_direct_W_m2": float(E.mean()),
            }
        )
    )


if __name__ == "__main__":
    main()
