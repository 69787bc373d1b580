"""Benchmark: the record's coupled steps with one IR product per step against several per product (issue 24).

Run:  PYTHONPATH=$PWD python bench/grouped_record.py [--size 30000] [--samples 1 2 3] [--pairs 2]

The scale crater of ``bench/scale.py`` (10 km, 5 km surround, 86 S) at ``--size`` facets; its sunlight over
a year at 4 h is computed once, in memory. Then the year is stepped from the same equilibrium start by the
record's loop with ``[steps] ir_product_samples`` = each of ``--samples`` (1: one product per step, the
scheme below 10,000 facets; n > 1: :meth:`crater_thermal.radiosity.CoupledStepper.steps`), the variants
alternating ``--pairs`` times in this one process (this shared machine's load falls on all of them). Per
variant: seconds of the stepping (best and all), IR products, share of column-steps taken again; against
the one-product-per-step run: the largest and mean surface-temperature difference over all samples, at
night (no sunlight on the facet), in the report's night (no sunlight for 24 h, least-lit fallback) and in
the facet night (no direct sunlight for 24 h). ``--implicit``: every variant, the one-product-per-step
run included, also against the fully implicit exchange (the IR at every step's end iterated to its fixed
point, 6 iterations; ~4 times a year's stepping).
Writes ``bench/results/grouped_record_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import scale  # noqa: E402  (the scale crater's case text)


def step_year(stepper, t, solar, prompt, g) -> tuple[np.ndarray, float, int]:
    """Surface temperatures (nt, nf) float32 [K] of the year from the solver's state, ``g`` samples per
    IR product (:meth:`crater_thermal.radiosity.CoupledStepper.run`, as the runner's record takes them);
    seconds; IR products made."""
    nt = len(t)
    out = np.empty((nt, solar.shape[1]), np.float32)
    out[0] = stepper.solver.surface_temperature

    def keep(k, T, ir):
        out[k] = T

    t0 = time.perf_counter()
    stepper.run(t, solar, record=False, on_step=keep, product_samples=g, prompt=prompt)
    return out, time.perf_counter() - t0, -(-(nt - 1) // g)


def nights(solar, direct, t) -> tuple[np.ndarray, np.ndarray]:
    """(nt, nf) bool masks: the report's default night (:func:`crater_thermal.regions.dark_night_mask`: no
    sunlight for 24 h, least-lit fallback) and the facet night (no direct sunlight for 24 h,
    :func:`crater_thermal.regions.facet_night_mask`)."""
    from crater_thermal import regions

    times = np.datetime64("2019-01-01") + (np.asarray(t) * 1e9).astype("timedelta64[ns]")
    dark = regions.dark_night_mask(solar, direct, times)[0]
    return np.asarray(dark, bool), np.asarray(regions.facet_night_mask(direct, times), bool)


def differences(T, ref, night, dark, facet) -> dict:
    """Largest, mean and 99th/99.9th-percentile |T - ref| [K] over all samples, at night (no sunlight on
    the facet), in the report's night and in the facet night."""
    d = np.abs(T.astype(float) - ref.astype(float))
    out = {"max": float(d.max()), "mean": float(d.mean()), "p99": float(np.percentile(d, 99))}
    for name, m in (("night", night), ("report_night", dark), ("facet_night", facet)):
        if m.any():
            out[f"{name}_max"] = float(d[m].max())
            out[f"{name}_p999"] = float(np.percentile(d[m], 99.9))
            out[f"{name}_mean"] = float(d[m].mean())
    return out


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--samples", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--implicit", action="store_true", help="also against the fully implicit exchange")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if 1 not in args.samples:
        args.samples = [1, *args.samples]
    from crater_thermal import config, radiosity, runner, simulate, thermal

    with tempfile.TemporaryDirectory(prefix="grouped_") as tmp:
        os.environ.setdefault("CRATER_THERMAL_CACHE", str(Path(tmp) / "cache"))
        path = Path(tmp) / "case.toml"
        path.write_text(scale.case_text(args.size, "2020-01-01T00:00", spinup='spinup = "fixed"\nspinup_days = 0.0'))
        case = config.load_case(path)
        t0 = time.perf_counter()
        fc = simulate.compute_forcing(case, simulate.Timer())
        forcing_s = time.perf_counter() - t0
    _, solar = fc.split(fc.solar)
    _, direct = fc.split(fc.direct)
    t = simulate.seconds_since(fc.times, fc.times[0])
    prompt = radiosity.prompt_ir(solar, direct, case.surface.albedo)
    nominal = thermal.parse_profile(case.surface.nominal_profile)
    start = None
    runs: dict = {g: {"seconds": []} for g in args.samples}
    temps: dict = {}
    load = [list(os.getloadavg())]
    for _ in range(args.pairs):
        for g in args.samples:
            solver, stepper = runner._coupled_solver(case, nominal, fc, False)
            if start is None:
                solver.set_equilibrium(solar)
                start = solver.state()
            solver.set_state(start)
            T, sec, products = step_year(stepper, t, solar, prompt, g)
            runs[g]["seconds"].append(round(sec, 2))
            runs[g]["products"] = products
            runs[g]["redone_share"] = round(stepper.redone / max(stepper.stepped, 1), 4)
            temps[g] = T
            print(json.dumps({"samples_per_product": g, "seconds": round(sec, 2)}), flush=True)
    night = solar == 0.0
    dark, facet = nights(solar, direct, t)
    implicit_s = None
    if args.implicit:
        solver, stepper = runner._coupled_solver(case, nominal, fc, False)
        solver.set_state(start)
        t0 = time.perf_counter()
        implicit = radiosity.implicit_run(stepper, t, solar, iterations=6)
        implicit_s = round(time.perf_counter() - t0, 1)
    load.append(list(os.getloadavg()))
    for g in args.samples:
        runs[g]["best_s"] = min(runs[g]["seconds"])
        if g != 1:
            runs[g]["vs_one_product_per_step_K"] = differences(temps[g], temps[1], night, dark, facet)
            runs[g]["speedup_best"] = round(runs[1]["best_s"] / runs[g]["best_s"], 3)
        if args.implicit:
            runs[g]["vs_implicit_K"] = differences(temps[g], implicit, night, dark, facet)
    res = {
        "benchmark": "grouped_record",
        "facets": int(fc.mesh.n_facets),
        "samples": int(len(t)),
        "night_share": float(night.mean()),
        "report_night_share": float(dark.mean()),
        "facet_night_share": float(facet.mean()),
        "implicit_s": implicit_s,
        "forcing_s": round(forcing_s, 1),
        "operator_bytes": int(getattr(fc.F, "nbytes", 0)),
        "variants": {str(g): v for g, v in runs.items()},
        "pairs": args.pairs,
        "loadavg": load,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
    }
    out = Path(args.out) if args.out else HERE / "results" / f"grouped_record_{fc.mesh.n_facets}.json"
    out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
