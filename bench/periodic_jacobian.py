"""Benchmark: the periodic start's quasi-Newton step, dense eigen-decomposition against slow modes (issue 24).

Each iteration of :func:`crater_thermal.thermal.periodic_state` applies ``(I - J)^-1`` to every column's
residual through its linearised one-step operator. Two ways, alternating ``--repeats`` times in one
process on ``--columns`` columns of the nominal profile (default 100,000, a 100k-facet scale run) with a
state and surface conductance spread as over a crater (surface 40-300 K, deep 90-260 K), a year of
4-hour sub-steps:

* ``dense``: ``thermal._newton_step_eigh``, numpy's batched ``eigh`` of the (nz x nz) matrices in chunks
  of 4,096 columns, one BLAS thread, the chunks on ``--threads`` threads (numpy releases the GIL);
* ``slow_modes``: ``thermal._newton_step`` (what ``periodic_state`` runs): the slow modes only, by bisection
  and inverse iteration in a numba kernel on numba's threads, the chunks one after the other.

Reports seconds, the ratio, the largest difference of the two steps relative to each column's step, and
the slow modes per column. Writes ``bench/results/periodic_jacobian.json`` (``--out``).

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

    def dense():
        dx = np.zeros_like(r)
        t = time.perf_counter()
        with threadpool_limits(1, user_api="blas"):
            thermal._each(
                lambda cols: thermal._newton_step_eigh(solver, Tm, h, dt, nst, r, dx, cols), parts, args.threads
            )
        return time.perf_counter() - t, dx

    def slow_modes():
        dx = np.zeros_like(r)
        t = time.perf_counter()
        for cols in parts:
            thermal._newton_step(solver, Tm, h, dt, nst, r, dx, cols)
        return time.perf_counter() - t, dx

    dense()  # warm-up
    slow_modes()
    t_dense, t_slow = [], []
    for _ in range(args.repeats):
        t1, dx1 = dense()
        t2, dx2 = slow_modes()
        t_dense.append(t1)
        t_slow.append(t2)
    rel = np.abs(dx2 - dx1).max(axis=1) / np.abs(dx1).max(axis=1)
    from crater_thermal.kernels import periodic as kp

    K, Cd = solver.linear_parts(Tm, dt, np.arange(n))
    modes = np.zeros(n, np.int64)
    kp.newton_steps(
        K,
        h,
        Cd,
        r,
        nst,
        1,
        thermal._k.TRB_GAMMA,
        thermal._k.TRB_W0,
        thermal._k.TRB_W1,
        thermal._k.TRB_BETA,
        thermal._negative_gain("trbdf2"),
        np.empty_like(Cd),
        modes,
    )
    result = {
        "columns": n,
        "nodes_per_column": nz,
        "chunk": args.chunk,
        "threads": args.threads,
        "cpu_count": os.cpu_count(),
        "load_average_at_start": os.getloadavg()[0],
        "dense_eigh_s": [round(t, 3) for t in t_dense],
        "slow_modes_s": [round(t, 3) for t in t_slow],
        "dense_over_slow_median": round(float(np.median(np.array(t_dense) / np.array(t_slow))), 2),
        "max_difference_relative_to_step": float(rel.max()),
        "median_difference_relative_to_step": float(np.median(rel)),
        "slow_modes_per_column": {"min": int(modes.min()), "median": float(np.median(modes)), "max": int(modes.max())},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
