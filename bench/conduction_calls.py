"""Benchmark: cost of the conduction solver per call, a coupled run's way (one step per call) and a
replay's way (many steps per call), two versions of the code alternating (issue 24).

Run:  PYTHONPATH=$PWD python bench/conduction_calls.py --old-tree DIR [--columns 10000] [--repeat 3]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). Each
measurement is a fresh process with that version first on ``PYTHONPATH`` (``--one``): ``--columns``
nominal regolith columns at their equilibrium under a steady absorbed flux of 5 W m-2 (+1 % noise:
no sunrise, so no adaptive refinement; or with ``--forcing diurnal`` half the columns sunlit, a 300 W m-2
peak cosine over the 29.53-day lunar day at random phases, the other half at 2 W m-2: sunrises and sunsets,
so the default adaptive refinement works as in a crater), 100 four-hour steps as ``ColumnSolver.advance`` calls (one
step each: the coupled step) and as one ``run_series`` call, after a warm-up (numba compilation or
cache load). The processes alternate old, new, old, new ... Writes ``bench/results/conduction_calls.json``
(``--out`` to name another file)
(ms per step, per run and the medians) and prints it as the last stdout line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def one(n: int, forcing: str = "steady") -> dict:
    from crater_thermal import thermal

    s = thermal.ColumnSolver(["1300/1800"] * n)
    rng = np.random.default_rng(0)
    t = np.arange(101) * 14400.0
    if forcing == "diurnal":
        phase = 2.0 * np.pi * rng.random(n)
        lit = rng.random(n) < 0.5
        a = 2.0 + lit * np.maximum(0.0, 300.0 * np.cos(2.0 * np.pi * t[:, None] / (29.53 * 86400.0) + phase))
        s.set_equilibrium(np.broadcast_to(a.mean(axis=0), (2, n)))
    else:
        a = 5.0 + 0.05 * rng.random((101, n))
        s.set_equilibrium(np.full((2, n), 5.0))
    s.run_series(t[:3], a[:3], record=False)
    s.advance(a[0], a[1], 14400.0)
    x = s.state()
    t0 = time.perf_counter()
    s.run_series(t, a, record=False)
    t1 = time.perf_counter()
    s.set_state(x)
    for k in range(100):
        s.advance(a[k], a[k + 1], 14400.0)
    t2 = time.perf_counter()
    return {"run_series_ms_per_step": 10.0 * (t1 - t0), "advance_ms_per_step": 10.0 * (t2 - t1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree", default=None)
    ap.add_argument("--old-label", default="old")
    ap.add_argument("--columns", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--forcing", choices=("steady", "diurnal"), default="steady")
    ap.add_argument("--out", default="conduction_calls.json", help="file name under bench/results/")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.columns, args.forcing)))
        return
    if not args.old_tree:
        raise SystemExit("--old-tree DIR is required (a copy of the version to compare with)")
    trees = {"old": Path(args.old_tree).resolve(), "new": HERE.parent}
    runs = []
    for r in range(args.repeat):
        for which in ("old", "new"):
            env = dict(os.environ, PYTHONPATH=str(trees[which]))
            cmd = [sys.executable, str(HERE / "conduction_calls.py"), "--one", "--columns", str(args.columns)]
            cmd += ["--forcing", args.forcing]
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            if proc.returncode != 0:
                raise SystemExit(f"{which}: failed: {proc.stderr[-2000:]}")
            res = json.loads(proc.stdout.strip().splitlines()[-1])
            runs.append({"version": which, "repeat": r, "loadavg": os.getloadavg(), **res})
            print(json.dumps(runs[-1]), flush=True)
    med = {
        w: {
            k: float(np.median([x[k] for x in runs if x["version"] == w]))
            for k in ("run_series_ms_per_step", "advance_ms_per_step")
        }
        for w in ("old", "new")
    }
    result = {
        "benchmark": "conduction_calls",
        "columns": args.columns,
        "forcing": args.forcing,
        "old": args.old_label,
        "median_ms_per_step": med,
        "old_over_new": {k: round(med["old"][k] / med["new"][k], 3) for k in med["old"]},
        "runs": runs,
    }
    (HERE / "results" / args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
