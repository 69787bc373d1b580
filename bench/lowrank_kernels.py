"""Benchmark: the compressed operator's products with several right-hand sides, the far-field (low-rank)
kernels of this version against those of another commit, alternating in one process (issue 24).

Run:  PYTHONPATH=$PWD python bench/lowrank_kernels.py --old COMMIT [--size 30000] [--repeat 6]

Builds the scale crater of ``bench/scale.py`` (10 km, 5 km flat surround, 86 S, ``--size`` facets) and its
compressed operator (``--cache DIR`` keeps it for a second run; default: a temporary cache), then times
``F X`` for an emission-like X (eps sigma T^4, T drawn in 40-340 K) with 64 right-hand sides (scattering's
blocks) and 16 (a lagged window's rows at the product samples), float32 arithmetic as a run makes them,
with ``kernels.vfoperator.lowrank_matvec`` as shipped and as in ``--old`` (its source compiled in this
process), alternating, ``--repeat`` times each; and the low-rank kernel alone on one thread. Accuracy: the
largest relative difference of the two products (facets above 1e-6 of the column's largest). ``--old``
must have the kernels' present signature (int16 factors and their weights, ALGORITHM_VERSION c3 on). Writes
``bench/results/lowrank_kernels_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def old_kernels(commit: str, tmp: Path):
    """The kernels module of ``commit`` (its source from git), imported under another name."""
    src = subprocess.run(
        ["git", "show", f"{commit}:crater_thermal/kernels/vfoperator.py"],
        cwd=HERE.parent,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = tmp / "old_vfoperator_kernels.py"
    path.write_text(src.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location("old_vfoperator_kernels", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="commit whose low-rank kernel is the baseline")
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--repeat", type=int, default=6)
    ap.add_argument("--cache", help="cache folder for the operator (default: a temporary one)")
    args = ap.parse_args()
    spec = importlib.util.spec_from_file_location("scale", HERE / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    from crater_thermal import config, simulate, vfoperator
    from crater_thermal.kernels import vfoperator as kv

    with tempfile.TemporaryDirectory(prefix="lowrank_") as tmp:
        tmp = Path(tmp)
        os.environ["CRATER_THERMAL_CACHE"] = args.cache or str(tmp / "cache")
        path = tmp / "case.toml"
        path.write_text(scale.case_text(args.size, "2019-01-03T00:00"))
        mesh, _, F = simulate.case_geometry(config.load_case(path), simulate.Timer())
        old = old_kernels(args.old, tmp)
    if not isinstance(F, vfoperator.CompressedViewFactors):
        raise SystemExit(f"{args.size} facets gave a {type(F).__name__}; use >= 10,000 facets (compressed operator)")
    kernels = {"old": old.lowrank_matvec, "new": kv.lowrank_matvec}
    shipped = kv.lowrank_matvec
    rng = np.random.default_rng(1)
    X = 0.95 * 5.670374419e-8 * (40.0 + 300.0 * rng.random((mesh.n_facets, 64))) ** 4
    result = {
        "benchmark": "lowrank_kernels",
        "old": args.old,
        "facets": mesh.n_facets,
        "operator_mb": F.nbytes / 1e6,
        "lowrank_numbers": int(F.U.size + F.V.size),
        "sparse_pairs": int(len(F.data)),
        "cases": {},
        "loadavg": [list(os.getloadavg())],
    }
    try:
        for k in (64, 16):
            x = np.ascontiguousarray(X[:, :k])
            out, times = {}, {"old": [], "new": []}
            for label, fn in kernels.items():  # warm-up: compilation, the thread pool
                kv.lowrank_matvec = fn
                out[label] = F @ x
            for _ in range(args.repeat):
                for label, fn in kernels.items():
                    kv.lowrank_matvec = fn
                    t0 = time.perf_counter()
                    F @ x
                    times[label].append(time.perf_counter() - t0)
            ref = out["old"]
            lit = ref > 1e-6 * ref.max(axis=0)
            rel = float((np.abs(out["new"] - ref)[lit] / ref[lit]).max())
            # the low-rank kernel alone, one thread, float32 operands in cluster order
            lr = (F.r0, F.r1, F.c0, F.c1, F.rank, F.uoff, F.voff, F.woff, F.U, F.V, F.W)
            xc = np.ascontiguousarray(x[F.perm], np.float32)
            tmp_ = np.empty((2 * F._max_rank, k), np.float32)
            alone = {"old": [], "new": []}
            for _ in range(args.repeat):
                for label, fn in kernels.items():
                    y = np.zeros_like(xc)
                    t0 = time.perf_counter()
                    fn(*lr, xc, y, tmp_)
                    alone[label].append(time.perf_counter() - t0)
            result["cases"][str(k)] = {
                "product_s": {key: [round(v, 5) for v in val] for key, val in times.items()},
                "product_ratio_best": min(times["old"]) / min(times["new"]),
                "product_ratio_median": float(np.median(times["old"]) / np.median(times["new"])),
                "lowrank_one_thread_s": {key: [round(v, 5) for v in val] for key, val in alone.items()},
                "lowrank_ratio_best": min(alone["old"]) / min(alone["new"]),
                "max_rel_diff": rel,
            }
            print(k, json.dumps(result["cases"][str(k)]), file=sys.stderr, flush=True)
    finally:
        kv.lowrank_matvec = shipped
    result["loadavg"].append(list(os.getloadavg()))
    out_path = HERE / "results" / f"lowrank_kernels_{args.size}.json"
    out_path.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
