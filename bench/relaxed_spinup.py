"""Benchmark: the periodic start of a relaxed run (``[steps] ir_coupling = "relaxed"``, in this process:
``waveform.LocalColumns``), with the code of another tree against this one's, alternating in one run.

The generator's crater of ``bench/scale.py`` (10 km, 5 km flat surround, 86 S) at ``--facets`` facets
(default 3,000), the periodic start over the year 2018 at 4 h and one recorded day. Each run is a fresh
process importing ``crater_thermal`` from its tree (``--old``, e.g. ``git archive 2c2c18a | tar -x -C
/tmp/old``, or this repository), after an untimed warm-up run of a small case (imports, numba). The
modes alternate (old, new, old, new, ...: ``--pairs``) so that both see the same machine load.

With ``--workers N`` the runs are on a local dask cluster of N one-thread workers (``run --workers``;
the cluster's start is outside the spin-up's seconds).

Recorded per run: the spin-up's seconds (the run's ``conduction_spinup``), the first (held) pass's
seconds (``held_pass_s``, one per call of ``waveform.SpinUp.held``), its passes (the periodic
start's ``spinup_iterations``), the rounds of the backend's ``solve`` during it (each a client<->worker
exchange on a cluster: the former first pass relaxed window by window; in this process the held pass
makes one per hold), the right-hand sides of the IR products they made (and in this process those made
between passes for the next pass, ``ir_rows``), the passes submitted whole to
the cluster (one exchange each), the next passes' inputs formed on the workers between passes (one
exchange each: the skipped columns' test), the load average, and the largest difference of the start
(the record's first sample) between the trees.

Usage: ``python bench/relaxed_spinup.py --old /tmp/old [--facets 3000] [--pairs 2] [--workers 0]
[--out bench/results/relaxed_spinup.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def child(tree: Path, facets: int, work: Path, out_json: Path, workers: int = 0) -> None:
    """One run with ``crater_thermal`` from ``tree`` (in a fresh process)."""
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
    sys.path.insert(0, str(tree))
    import importlib.util

    import numpy as np

    from crater_thermal import cluster_run, config, io, runner, waveform

    spec = importlib.util.spec_from_file_location("bench_scale", REPO / "bench" / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)

    def case(name, n, end, spinup):
        text = scale.CASE.format(
            facets=n, diameter_km=10.0, surround_km=5.0, lat_deg=-86.0, chunk_mb=256, extra="", end=end, spinup=spinup
        )
        text = text.replace("flux_step_hours = 4.0", 'flux_step_hours = 4.0\nir_coupling = "relaxed"')
        path = work / f"{name}.toml"
        path.write_text(text)
        return config.load_case(path)

    def columns():
        return cluster_run.distributed_columns(workers=workers) if workers else None

    runner.run_case(
        case("warm", 300, "2019-01-02T00:00", 'spinup = "periodic"\nspinup_days = 29.53'),
        work / "warm.nc",
        progress=False,
        overwrite=True,
        columns=columns(),
    )
    counts = {"rounds": 0, "rhs": 0, "whole_passes": 0, "next_inputs": 0}
    backend = cluster_run.DaskColumns if workers else waveform.LocalColumns
    solve = backend.solve

    def counted(self, state, times_s, solar, E, *args, **kwargs):
        counts["rounds"] += 1
        counts["rhs"] += len(E)
        return solve(self, state, times_s, solar, E, *args, **kwargs)

    backend.solve = counted
    ir_rows = getattr(backend, "ir_rows", None)
    if ir_rows is not None:  # the next pass's input IR formed between passes (products too)

        def counted_rows(self, T, *args, **kwargs):
            counts["rhs"] += len(T)
            return ir_rows(self, T, *args, **kwargs)

        backend.ir_rows = counted_rows
    for name in ("lagged_pass", "held_pass"):  # a pass submitted whole: one exchange
        whole = getattr(backend, name, None)
        if whole is not None:

            def counted_pass(self, *args, _whole=whole, **kwargs):
                counts["whole_passes"] += 1
                return _whole(self, *args, **kwargs)

            setattr(backend, name, counted_pass)
    next_inputs = getattr(backend, "next_inputs", None)
    if next_inputs is not None:  # the next pass's input formed on the workers between passes: one exchange

        def counted_next(self, *args, **kwargs):
            counts["next_inputs"] += 1
            return next_inputs(self, *args, **kwargs)

        backend.next_inputs = counted_next
    held = waveform.SpinUp.held
    held_s = []

    def held_timed(self, *args, **kwargs):  # the first (held) pass's seconds
        t0 = time.perf_counter()
        try:
            return held(self, *args, **kwargs)
        finally:
            held_s.append(time.perf_counter() - t0)

    waveform.SpinUp.held = held_timed
    spin_up = runner._spin_up_relaxed
    at_spin = {}

    def spin_up_counted(*args, **kwargs):
        out = spin_up(*args, **kwargs)
        at_spin.update(counts)
        return out

    runner._spin_up_relaxed = spin_up_counted
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    out = runner.run_case(
        case("run", facets, "2019-01-02T00:00", 'spinup = "periodic"\nspinup_years = 1.0'),
        work / "run.nc",
        progress=False,
        overwrite=True,
        columns=columns(),
    )
    wall = time.perf_counter() - t0
    with io.open_run(out) as ds:
        timing = ds.attrs["timing_s"]
        timing = json.loads(timing) if isinstance(timing, str) else timing
        start = ds["surface_temperature"].values[0].astype(float)
        result = {
            "tree": str(tree),
            "facets": int(ds.sizes["facet"]),
            "wall_s": wall,
            "spinup_s": float(timing["conduction_spinup"]),
            "held_pass_s": held_s,
            "passes": int(ds.attrs["spinup_iterations"]),
            "start_method": str(ds.attrs["start_method"]),
            "spinup_solve_rounds": at_spin["rounds"],
            "spinup_product_rhs": at_spin["rhs"],
            "spinup_whole_passes": at_spin["whole_passes"],
            "spinup_next_inputs": at_spin["next_inputs"],
            "workers": workers,
            "loadavg_start": load0,
            "loadavg_end": os.getloadavg()[0],
        }
    np.save(out_json.with_suffix(".npy"), start)
    out_json.write_text(json.dumps(result))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, required=True, help="the other tree (its crater_thermal is imported)")
    ap.add_argument("--facets", type=int, default=3000)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--workers", type=int, default=0, help="a local dask cluster of this many 1-thread workers")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "relaxed_spinup.json")
    ap.add_argument("--child", nargs=3, metavar=("TREE", "WORK", "JSON"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(Path(args.child[0]), args.facets, Path(args.child[1]), Path(args.child[2]), args.workers)
        return
    import numpy as np

    runs = []
    with tempfile.TemporaryDirectory(prefix="relaxed_spinup_") as tmp:
        tmp = Path(tmp)
        env = {**os.environ, "CRATER_THERMAL_CACHE": str(tmp / "cache"), "CRATER_THERMAL_QUIET": "1"}
        for i in range(args.pairs):
            for mode, tree in (("old", args.old.resolve()), ("new", REPO)):
                work = tmp / f"{mode}{i}"
                work.mkdir()
                js = work / "result.json"
                cmd = [sys.executable, __file__, "--facets", str(args.facets), "--old", str(args.old)]
                cmd += ["--workers", str(args.workers)]
                subprocess.run(cmd + ["--child", str(tree), str(work), str(js)], env=env, check=True)
                r = json.loads(js.read_text())
                r.update(mode=mode, pair=i, start_K=str(js.with_suffix(".npy")))
                print(json.dumps(r), flush=True)
                runs.append(r)
        starts = {(r["mode"], r["pair"]): np.load(r.pop("start_K")) for r in runs}
        diff = max(float(np.abs(starts[("old", i)] - starts[("new", i)]).max()) for i in range(args.pairs))
    summary = {
        m: {
            "spinup_s": [r["spinup_s"] for r in runs if r["mode"] == m],
            "held_pass_s": [r.get("held_pass_s") for r in runs if r["mode"] == m],
            "passes": sorted({r["passes"] for r in runs if r["mode"] == m}),
            "spinup_solve_rounds": sorted({r["spinup_solve_rounds"] for r in runs if r["mode"] == m}),
            "spinup_product_rhs": sorted({r["spinup_product_rhs"] for r in runs if r["mode"] == m}),
            "spinup_whole_passes": sorted({r["spinup_whole_passes"] for r in runs if r["mode"] == m}),
            "spinup_next_inputs": sorted({r.get("spinup_next_inputs", 0) for r in runs if r["mode"] == m}),
        }
        for m in ("old", "new")
    }
    ratios = [o["spinup_s"] / n["spinup_s"] for o, n in zip(runs[0::2], runs[1::2])]
    result = {
        "old_tree": str(args.old),
        "facets_requested": args.facets,
        "workers": args.workers,
        "cpus": os.cpu_count(),
        "runs": runs,
        "summary": summary,
        "spinup_speedup_old_over_new_per_pair": ratios,
        "max_start_difference_K": diff,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({"summary": summary, "ratios": ratios, "max_start_difference_K": diff}, indent=1))


if __name__ == "__main__":
    main()
