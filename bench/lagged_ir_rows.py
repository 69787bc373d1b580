"""Benchmark: the lagged spin-up windows' IR rows three ways, paired window by window in one run (issue 24).

Run:  PYTHONPATH=$PWD python bench/lagged_ir_rows.py [--size 30000] [--out FILE]

Runs the periodic start of ``bench/spinup_passes.py``'s case (the scale crater of ``bench/scale.py``,
``--size`` facets, then a two-day record) once. Each time a lagged window's IR rows are formed from its
surface temperatures (``simulate._SpinUpWindow._next_input``: the next window's input), the rows of every
block of the window are first made three ways on the same temperatures, the variants' order rotating from
window to window so that this shared machine's load falls on all of them:

* ``per_sample``: one exact product per sample, a block per product (``product_samples`` 1);
* ``per_block``: the exact product at every second sample, a block per product (~25 right-hand sides at
  48 samples a block), the IR between interpolated (the default from 10,000 facets until the batching);
* ``batched``: the same samples and interpolation, a few blocks per product
  (``_SpinUpWindow._product_batches``: ~49 right-hand sides), the default.

Then the run goes on with the default's own ``_next_input``. Per variant: the seconds of all windows (the
products and the interpolation, not the store's writes); the largest difference of ``per_block`` and
``batched`` rows [W m-2] (the same arithmetic; only a product's number of right-hand sides differs) and
of ``per_sample`` and ``batched`` (the interpolation's effect). Writes
``bench/results/lagged_ir_rows_<size>.json`` (or ``--out``); the last stdout line is the same JSON.
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
VARIANTS = ("per_sample", "per_block", "batched")


def window_rows(window, variant: str) -> dict:
    """The IR rows of every block of ``window``'s latest temperatures [W m-2], made as ``variant`` says."""
    kept, ns = window.product_samples, window.n
    batches = window._product_batches()
    if variant == "per_sample":
        window.product_samples = 1
    if variant != "batched":
        batches = [[span] for batch in batches for span in batch]
    try:
        rows = {}
        for batch in batches:
            for (b0, b1), exact in zip(batch, window._exact_products(batch)):
                rows[b0] = window._lagged_ir_rows(b0, min(ns, b1 + 1), exact)[: b1 - b0]
        return rows
    finally:
        window.product_samples = kept


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    from crater_thermal import simulate

    original = simulate._SpinUpWindow._next_input
    seconds: dict = {v: [] for v in VARIANTS}
    diffs: dict = {"per_block_vs_batched": [], "per_sample_vs_batched": []}
    calls = [0]

    def paired(self):
        k = calls[0]
        calls[0] += 1
        order = VARIANTS[k % 3 :] + VARIANTS[: k % 3]
        rows = {}
        for v in order:
            t0 = time.perf_counter()
            rows[v] = window_rows(self, v)
            seconds[v].append(time.perf_counter() - t0)
        for name, a in (("per_block_vs_batched", "per_block"), ("per_sample_vs_batched", "per_sample")):
            diffs[name].append(max(float(np.max(np.abs(rows[a][b] - rows["batched"][b]))) for b in rows["batched"]))
        del rows
        return original(self)

    simulate._SpinUpWindow._next_input = paired
    spec = importlib.util.spec_from_file_location("spinup_passes", HERE / "spinup_passes.py")
    spinup_passes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(spinup_passes)
    run = spinup_passes.one(args.size)
    out = {
        "benchmark": "lagged_ir_rows",
        "facets": args.size,
        "windows": calls[0],
        "seconds": {v: sum(s) for v, s in seconds.items()},
        "seconds_by_window": seconds,
        "per_block_over_batched": sum(seconds["per_block"]) / max(sum(seconds["batched"]), 1e-12),
        "per_sample_over_batched": sum(seconds["per_sample"]) / max(sum(seconds["batched"]), 1e-12),
        "max_abs_row_difference_W_m2": {k: (max(v) if v else None) for k, v in diffs.items()},
        "spinup_s": run["spinup_s"],
        "passes": run["passes"],
        "residual_history_K": run["residual_history_K"],
        "loadavg": run["loadavg"],
        "cpus": os.cpu_count(),
    }
    path = args.out or HERE / "results" / f"lagged_ir_rows_{args.size}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
