"""Benchmark: the periodic start's quasi-Newton step on one thread against numba's threads (issue 24).

Each iteration of :func:`crater_thermal.thermal.periodic_state` applies ``(I - J)^-1`` to every column's
residual through the eigen-decomposition of its linearised one-step operator (numpy's batched ``eigh`` of
(nz x nz) matrices, in chunks of 4,096 columns, one BLAS thread). The chunks now go to numba's number of
threads (numpy's linear algebra releases the GIL). Measured here on ``--columns`` columns of the nominal
profile (default 100,000, a 100k-facet scale run) with a state and surface conductance spread as over a
crater (surface 40-300 K, deep 90-260 K): the same step through ``thermal._each`` on 1 thread and on
``--threads`` (default numba's), alternating ``--repeats`` times in one process, the steps compared bit for
bit. Writes ``bench/results/periodic_jacobian.json`` (``--out``).

Usage: ``python bench/periodic_jacobian.py [--columns 100000] [--repeats 3] [--threads 2] [--out PATH]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numba  # noqa: E402
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from crater_thermal import thermal  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--columns", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=numba.get_num_threads())
    ap.add_argument("--chunk", type=int, default=4096)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "periodic_jacobian.json")
    args = ap.parse_args()
    n = args.columns
    solver = thermal.ColumnSolver(["1300/1800"] * n)  # the nominal profile
    nz = solver.nz
    rng = np.random.default_rng(1)
    z = np.linspace(0.0, 1.0, nz)[None, :]
    surface, deep = rng.uniform(40.0, 300.0, (n, 1)), rng.uniform(90.0, 260.0, (n, 1))
    Tm = deep + (surface - deep) * np.exp(-z / 0.05)
    h = 4.0 * 0.95 * 5.670374419e-8 * rng.uniform(40.0, 300.0, n) ** 3  # [W m-2 K-1]
    dt = np.full(n, 14400.0)  # [s]
    nst = np.full(n, 2190.0)  # sub-steps in a year of 4-hour steps
    r = rng.normal(0.0, 1.0, (n, nz))  # [K]
    parts = [np.arange(c0, min(n, c0 + args.chunk)) for c0 in range(0, n, args.chunk)]

    def step(threads: int):
        dx = np.zeros_like(r)
        t = time.perf_counter()
        with threadpool_limits(1, user_api="blas"):
            thermal._each(lambda cols: thermal._newton_step(solver, Tm, h, dt, nst, r, dx, cols), parts, threads)
        return time.perf_counter() - t, dx

    step(args.threads)  # warm-up
    one, many, same = [], [], True
    for _ in range(args.repeats):
        t1, dx1 = step(1)
        tn, dxn = step(args.threads)
        one.append(t1)
        many.append(tn)
        same &= bool(np.array_equal(dx1, dxn))
    result = {
        "columns": n,
        "nodes_per_column": nz,
        "chunk": args.chunk,
        "threads": args.threads,
        "cpu_count": os.cpu_count(),
        "load_average_at_start": os.getloadavg()[0],
        "one_thread_s": [round(t, 3) for t in one],
        "threads_s": [round(t, 3) for t in many],
        "speedup_median": round(float(np.median(np.array(one) / np.array(many))), 2),
        "steps_equal_bit_for_bit": same,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
