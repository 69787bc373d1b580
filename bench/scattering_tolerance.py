"""Benchmark: the scattered-sunlight solve's stopping rule (``radiosity.ITERATIVE_RTOL``) at scale (issue 24).

Run:  PYTHONPATH=$PWD python bench/scattering_tolerance.py [--size 10000] [--rtol 1e-6 1e-5 1e-4 1e-3]
                                                          [--every 4] [--years 1e-6 1e-4]

The scale crater of ``bench/scale.py`` (10 km, 5 km surround, 86 S, ``--size`` facets, compressed operator),
in one process:

* ``solve``: the direct sunlight of every ``--every``-th sample of the spin-up year and the record year,
  scattered by ``ScatteringSolver.solar_incident`` with each ``--rtol`` and with 1e-10 (the reference):
  products made (each with up to 64 samples), seconds, the largest and 99th-percentile error of the
  scattered irradiance [W m-2], and its largest relative error where it exceeds 0.1 W m-2;
* ``year``: the whole scale run (periodic start over 2018, a recorded year at 4 h) with each of ``--years``
  (the first is the reference), through ``runner.run_case``; the largest difference of the surface
  temperature, over all samples and over the samples where a facet has no direct sunlight (night).

Writes ``bench/results/scattering_tolerance_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _case(tmp: Path, scale, size: int) -> Path:
    path = tmp / "case.toml"
    path.write_text(scale.case_text(size, "2019-12-31T20:00"))
    return path


def solve_sweep(case, rtols: list[float], every: int) -> dict:
    from crater_thermal import radiosity, simulate

    timer = simulate.Timer()
    mesh, tracer, F = simulate.case_geometry(case, timer)
    _, _, sun_dirs, sun_dist = simulate.case_sun(case, timer)
    light = simulate.case_sunlight(case, mesh, tracer, F, timer)
    scat, light.scat = light.scat, None  # direct sunlight only; scattered below
    idx = np.arange(0, len(sun_dirs), every)
    direct, _ = light(sun_dirs[idx], sun_dist[idx])
    out = {"samples": len(idx), "lit_samples": int(np.any(direct > 0, axis=1).sum()), "facets": mesh.n_facets}
    matvec = scat.F.matvec
    ref = None
    default = radiosity.ITERATIVE_RTOL
    try:
        for rtol in [1e-10, *rtols]:
            radiosity.ITERATIVE_RTOL = rtol
            count = [0]

            def counting(x, count=count):
                count[0] += 1
                return matvec(x)

            scat.F.matvec = counting
            t0 = time.perf_counter()
            scattered = scat.solar_incident(direct) - direct
            seconds = time.perf_counter() - t0
            scat.F.matvec = matvec
            if ref is None:
                ref = scattered
            err = np.abs(scattered - ref)
            big = ref > 0.1
            out[f"{rtol:g}"] = {
                "products": count[0],
                "seconds": seconds,
                "max_err_W_m2": float(err.max()),
                "p99_err_W_m2": float(np.percentile(err, 99)),
                "max_rel_err_above_0.1_W_m2": float((err[big] / ref[big]).max()) if big.any() else 0.0,
                "largest_scattered_W_m2": float(ref.max()),
            }
            print(json.dumps({"rtol": rtol, **out[f"{rtol:g}"]}), flush=True)
    finally:
        radiosity.ITERATIVE_RTOL = default
        scat.F.matvec = matvec
    return out


def year_runs(path: Path, tmp: Path, rtols: list[float]) -> dict:
    import xarray as xr

    from crater_thermal import config, radiosity, runner, simulate

    default = radiosity.ITERATIVE_RTOL
    runs = {}
    try:
        for rtol in rtols:
            radiosity.ITERATIVE_RTOL = rtol
            timer = simulate.Timer()
            t0 = time.perf_counter()
            runner.run_case(config.load_case(path), tmp / f"run_{rtol:g}.nc", timer=timer)
            runs[f"{rtol:g}"] = {"total_s": time.perf_counter() - t0, "stages_s": dict(timer.split)}
            print(json.dumps({"rtol": rtol, **runs[f"{rtol:g}"]}), flush=True)
    finally:
        radiosity.ITERATIVE_RTOL = default
    with xr.open_dataset(tmp / f"run_{rtols[0]:g}.nc") as ref:
        T0 = ref["surface_temperature"].values
        night = ref["solar_direct"].values == 0
    for rtol in rtols[1:]:
        with xr.open_dataset(tmp / f"run_{rtol:g}.nc") as ds:
            d = np.abs(ds["surface_temperature"].values - T0)
        runs[f"{rtol:g}"].update(
            max_diff_K=float(d.max()),
            max_diff_night_K=float(d[night].max()),
            p99_diff_night_K=float(np.percentile(d[night], 99)),
        )
        print(json.dumps({"rtol": rtol, **{k: v for k, v in runs[f"{rtol:g}"].items() if "diff" in k}}), flush=True)
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=10_000)
    ap.add_argument("--rtol", type=float, nargs="+", default=[1e-6, 1e-5, 1e-4, 1e-3])
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--years", type=float, nargs="*", default=[1e-6, 1e-4])
    args = ap.parse_args()
    spec = importlib.util.spec_from_file_location("scale", HERE / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    from crater_thermal import config, radiosity

    result = {"benchmark": "scattering_tolerance", "size": args.size, "default_rtol": radiosity.ITERATIVE_RTOL}
    with tempfile.TemporaryDirectory(prefix="scat_tol_") as tmp:
        tmp = Path(tmp)
        os.environ["CRATER_THERMAL_CACHE"] = str(tmp / "cache")
        path = _case(tmp, scale, args.size)
        result["solve"] = solve_sweep(config.load_case(path), args.rtol, args.every)
        if len(args.years) >= 2:
            result["year"] = year_runs(path, tmp, args.years)
    result["loadavg"] = os.getloadavg()
    (HERE / "results" / f"scattering_tolerance_{args.size}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
