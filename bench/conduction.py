"""Benchmark of the conduction kernel: nonlinear column solver vs a plain linear tridiagonal sweep.

10,000 columns on the default grid. The nonlinear solver (default TR-BDF2, temperature-dependent
k and c, Newton on the radiative surface) runs 4-hour steps of a floor-like forcing; the linear
reference runs plain backward-Euler Thomas sweeps with constant coefficients on the same grid
(the cheapest implicit step there is). A cell-update is one node advanced by one time step.

Prints one JSON object as the LAST stdout line (keys nonlinear_cell_updates_per_s,
linear_cell_updates_per_s, ratio, ...) and writes it to bench/results/conduction.json.

Usage: PYTHONPATH=. python bench/conduction.py [--columns 10000] [--steps 200]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--columns", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3, help="best of N timings")
    args = ap.parse_args(argv)

    import numba

    from crater_thermal import thermal
    from crater_thermal.constants import LUNAR_DAY
    from crater_thermal.kernels import conduction as kern

    ncol, nsteps = args.columns, args.steps
    solver = thermal.ColumnSolver(["1300/1800"] * ncol)
    nz = solver.nz
    t = np.arange(nsteps + 1) * thermal.DEFAULT_DT_MAX
    q = 0.3 + 12.0 * np.maximum(0.0, np.cos(2 * np.pi * t / LUNAR_DAY))
    solver.set_equilibrium(q)
    start = solver.state()
    solver.run_series(t[:3], q[:3], record=False)  # compile / warm up

    best_nl = np.inf
    for _ in range(args.repeats):
        solver.set_state(start)
        t0 = time.perf_counter()
        solver.run_series(t, q, record=False)
        best_nl = min(best_nl, time.perf_counter() - t0)
    nl_rate = ncol * nsteps * nz / best_nl

    # linear reference: constant k, rho c of the nominal column at 100 K, same grid and dt
    dt = thermal.DEFAULT_DT_MAX
    K = solver.conductivity(start)[0] / solver.dz
    Cd = solver.m[0] * 276.0 / dt
    a = np.zeros(nz)
    c = np.zeros(nz)
    a[1:] = -K
    c[:-1] = -K
    b = Cd.copy()
    b[:-1] += K
    b[1:] += K
    T = np.full((ncol, nz), 100.0)
    kern.linear_sweeps(T, a, b, c, 0.03, Cd, 2, 3.0)  # compile
    best_lin = np.inf
    for _ in range(args.repeats):
        T[:] = 100.0
        t0 = time.perf_counter()
        kern.linear_sweeps(T, a, b, c, 0.03, Cd, nsteps, 3.0)
        best_lin = min(best_lin, time.perf_counter() - t0)
    lin_rate = ncol * nsteps * nz / best_lin

    result = {
        "nonlinear_cell_updates_per_s": nl_rate,
        "linear_cell_updates_per_s": lin_rate,
        "ratio": nl_rate / lin_rate,
        "columns": ncol,
        "steps": nsteps,
        "nz": nz,
        "dt_s": dt,
        "scheme": solver.scheme,
        "threads": numba.get_num_threads(),
        "nonlinear_wall_s": best_nl,
        "linear_wall_s": best_lin,
    }
    out = Path(__file__).resolve().parent / "results" / "conduction.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
