"""Benchmark: the view factors and the horizon map one after the other against at the same time (issue 24).

Run:  PYTHONPATH=$PWD python bench/geometry_overlap.py [--case scale --size 30000 | --case pcc] [--pairs 2]

A run builds the radiation operator and traces the horizon map once per mesh; the two are independent and
each keeps the two cores busy only part of the time, so ``simulate.case_operator_and_horizons`` runs them
together (the map on a second thread). This script times, in one process and alternating, the two stages one
after the other (``case_operator`` then ``Sunlight``'s own map) and together, with nothing cached (a fresh
cache folder for every build), and checks that both give the same operator products and map.

Meshes: ``--case scale``: the scale crater of ``bench/scale.py`` at ``--size`` facets; ``--case pcc``: PCC's
topo81 terrain of ``bench/pcc_topo3d.py`` (12,800 facets). Wall and CPU seconds (the process's user +
system) per variant and pair; the 1-minute load average before each. Writes
``bench/results/geometry_overlap_<case>[_<size>].json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from crater_thermal import config, geometry, simulate, sunlight  # noqa: E402


def _case(kind: str, size: int, tmp: Path):
    if kind == "pcc":
        import pcc_topo3d

        from crater_thermal.reference import pcc_topo81

        geometry.save_mesh(pcc_topo81(), tmp / "topo81.ply")
        text = pcc_topo3d.CASE.format(end=pcc_topo3d.simulate_end())
    else:
        import scale

        text = scale.case_text(size, "2019-01-02")
    (tmp / "case.toml").write_text(text)
    return config.load_case(tmp / "case.toml")


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", choices=["scale", "pcc"], default="scale")
    ap.add_argument("--size", type=int, default=30000, help="facets of the scale crater")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    label = "pcc" if args.case == "pcc" else f"scale_{args.size}"
    out = args.out or REPO / "bench" / "results" / f"geometry_overlap_{label}.json"

    with tempfile.TemporaryDirectory(prefix="geometry_overlap_") as d:
        tmp = Path(d)
        os.chdir(tmp)
        case = _case(args.case, args.size, tmp)
        mesh, tracer = simulate.case_scene(case, simulate.Timer())
        runs = {"sequential": [], "together": []}
        count = [0]

        def fresh_cache():
            count[0] += 1
            os.environ["CRATER_THERMAL_CACHE"] = str(tmp / f"cache{count[0]}")

        def sequential():
            F = simulate.case_operator(case, mesh, tracer, simulate.Timer())
            light = sunlight.Sunlight(case.sun, case.surface, case.scattering, mesh, tracer, F)
            return F, light.hmap

        def together():
            return simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer())

        fresh_cache()
        sequential()  # warm-up: compiled kernels, page cache (untimed)
        results = {}
        for _ in range(args.pairs):
            for name, fn in (("sequential", sequential), ("together", together)):
                fresh_cache()
                load = os.getloadavg()[0]
                results[name], wall, cpu = _timed(fn)
                runs[name].append({"wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "load_before": round(load, 2)})
                print(name, runs[name][-1], flush=True)
        (Fs, hs), (Ft, ht) = results["sequential"], results["together"]
        x = np.linspace(1.0, 2.0, mesh.n_facets)
        same = bool(np.array_equal(hs.elevation, ht.elevation) and np.array_equal(Fs @ x, Ft @ x))

    def best(name):
        return min(r["wall_s"] for r in runs[name])

    res = {
        "case": label,
        "facets": int(mesh.n_facets),
        "pairs": args.pairs,
        "runs": runs,
        "same_operator_and_map": same,
        "min_wall_s": {k: best(k) for k in runs},
        "speedup_min_wall": round(best("sequential") / best("together"), 3),
        "speedup_per_pair": [round(s["wall_s"] / t["wall_s"], 3) for s, t in zip(runs["sequential"], runs["together"])],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
