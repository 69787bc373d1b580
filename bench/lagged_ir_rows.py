"""Benchmark: the lagged spin-up windows' IR rows with one exact product per sample against two samples
per product (the default from 10,000 facets), paired call by call in one run (issue 24).

Run:  PYTHONPATH=$PWD python bench/lagged_ir_rows.py [--size 30000]

Runs the periodic start of ``bench/spinup_passes.py``'s case (the scale crater of ``bench/scale.py``,
``--size`` facets, then a two-day record) once. Every call of ``simulate._SpinUpWindow._lagged_ir_rows``
(one block of a lagged window's samples) is made twice on the same surface temperatures, with
``product_samples`` 1 and 2, their order alternating from call to call, and the run goes on with the
default's rows. So the two variants see the same inputs and this shared machine's load at the same time.
Per variant: the seconds of all calls; also the largest difference of the two variants' IR rows
[W m-2] (at the samples between two exact products). Writes ``bench/results/lagged_ir_rows_<size>.json``;
the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    args = ap.parse_args()

    from crater_thermal import simulate

    original = simulate._SpinUpWindow._lagged_ir_rows
    seconds: dict = {1: [], 2: []}
    diffs: list = []

    def paired(self, b0, e, T):
        kept, rows = self.product_samples, {}
        for g in (1, 2) if len(seconds[1]) % 2 == 0 else (2, 1):
            self.product_samples = g
            t0 = time.perf_counter()
            rows[g] = original(self, b0, e, T)
            seconds[g].append(time.perf_counter() - t0)
        self.product_samples = kept
        diffs.append(float(np.max(np.abs(rows[1] - rows[2]))))
        return rows[kept]

    simulate._SpinUpWindow._lagged_ir_rows = paired
    spec = importlib.util.spec_from_file_location("spinup_passes", HERE / "spinup_passes.py")
    spinup_passes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(spinup_passes)
    run = spinup_passes.one(args.size)
    out = {
        "benchmark": "lagged_ir_rows",
        "facets": args.size,
        "calls": len(seconds[1]),
        "one_product_per_sample_s": sum(seconds[1]),
        "two_samples_per_product_s": sum(seconds[2]),
        "ratio": sum(seconds[1]) / sum(seconds[2]),
        "max_abs_row_difference_W_m2": max(diffs) if diffs else None,
        "spinup_s": run["spinup_s"],
        "passes": run["passes"],
        "residual_history_K": run["residual_history_K"],
        "loadavg": run["loadavg"],
        "cpus": os.cpu_count(),
    }
    path = HERE / "results" / f"lagged_ir_rows_{args.size}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
