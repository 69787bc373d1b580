"""Benchmark: the compressed operator's low-rank kernels with its int16 factors against the same factors
as float32 (issue 24), alternating in one process.

Run:  PYTHONPATH=$PWD python bench/lowrank_factor_types.py [--size 30000] [--repeat 7]

Builds the operator of ``bench/viewfactor_operator.py``'s terrain at ``--size`` facets, then times the
far field's product alone (``kernels.vfoperator.lowrank_matvec`` with 16 and 64 right-hand sides, float32
arithmetic as a run makes them; ``lowrank_matvec1`` with one, float64), one thread, with the stored int16
factors and with the same factors converted to float32 (the same numbers, twice the bytes), alternating,
``--repeat`` times each (minimum and median). The two products must be equal to float32 round-off (the
int16 numbers are exact in float32); their largest relative difference is recorded. Writes
``bench/results/lowrank_factor_types_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from viewfactor_operator import terrain

    from crater_thermal import vfoperator as vo
    from crater_thermal.kernels import vfoperator as kv

    op = vo.compressed_view_factors(terrain(args.size))
    head = (op.r0, op.r1, op.c0, op.c1, op.rank, op.uoff, op.voff, op.woff)
    kinds = {
        "int16": (*head, op.U, op.V, op.W),
        "float32": (*head, op.U.astype(np.float32), op.V.astype(np.float32), op.W),
    }
    n = op.shape[0]
    rng = np.random.default_rng(0)
    out = {}
    for k in (1, 16, 64):
        dtype = np.float64 if k == 1 else np.float32
        X = np.ascontiguousarray(rng.random(n) if k == 1 else rng.random((n, k)), dtype)
        tmp = np.empty((2 * int(op.rank.max()),) + X.shape[1:], dtype)
        fn = kv.lowrank_matvec1 if k == 1 else kv.lowrank_matvec
        times = {name: [] for name in kinds}
        ys = {}
        for _ in range(args.repeat + 1):  # the first round compiles
            for name, lr in kinds.items():
                Y = np.zeros_like(X)
                t = time.perf_counter()
                fn(*lr, X, Y, tmp)
                times[name].append(time.perf_counter() - t)
                ys[name] = Y
        ref = ys["float32"]
        out[str(k)] = {
            **{f"{name}_min_s": float(min(v[1:])) for name, v in times.items()},
            **{f"{name}_median_s": float(np.median(v[1:])) for name, v in times.items()},
            "float32_over_int16_median": float(np.median(times["float32"][1:]) / np.median(times["int16"][1:])),
            "max_rel_diff": float(np.abs(ys["int16"] - ref).max() / np.abs(ref).max()),
        }
        print(k, json.dumps(out[str(k)]), file=sys.stderr, flush=True)
    result = {
        "facets": n,
        "lowrank_blocks": int(len(op.rank)),
        "lowrank_numbers": int(op.U.size + op.V.size),
        "repeat": args.repeat,
        "right_hand_sides": out,
        "load_average": os.getloadavg(),
    }
    path = Path(args.out or HERE / "results" / f"lowrank_factor_types_{args.size}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
