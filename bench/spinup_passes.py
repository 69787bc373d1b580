"""Benchmark: the periodic start of the scale crater, pass by pass, with two versions of the code (issue 24).

Run:  PYTHONPATH=$PWD python bench/spinup_passes.py --old-tree DIR [--size 10000] [--pairs 2]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). Each run is one
process (``--one``) with that version first on ``PYTHONPATH``: the generator crater of ``bench/scale.py``
(10 km, 5 km flat surround, 86 S, N facets, 4 h steps), its periodic start over 2018 as the case's
defaults choose it (the lagged-IR start from 10,000 facets), then a two-day record; the runs alternate
old, new, old, new ... so that this shared machine's load falls on both. Per run: the kind (lagged or
coupled) and wall time of each spin-up pass [s] and the columns it ran (None where the version does not
say; ``scale._watch_spinup``), the shooting's residual
history [K], the spin-up stage and the whole run [s], the load average. Per pair: old / new of the spin-up.
Writes ``bench/results/spinup_passes_<size>.json``; the last stdout line is the same JSON.
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

HERE = Path(__file__).resolve().parent


def one(size: int) -> dict:
    """One run in this process with whatever ``crater_thermal`` is first on the path."""
    spec = importlib.util.spec_from_file_location("scale", HERE / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    from crater_thermal import config, runner, simulate

    passes, info = scale._watch_spinup()
    with tempfile.TemporaryDirectory(prefix="spinup_") as tmp:
        tmp = Path(tmp)
        os.environ["CRATER_THERMAL_CACHE"] = str(tmp / "cache")
        case = tmp / "case.toml"
        case.write_text(scale.case_text(size, "2019-01-03T00:00"))
        timer = simulate.Timer()
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        runner.run_case(config.load_case(case), tmp / "run.nc", timer=timer, progress=False)
        total = time.perf_counter() - t0
    return {
        "total_s": total,
        "spinup_s": float(timer.split.get("conduction_spinup", float("nan"))),
        "passes": passes,
        "residual_history_K": [float(h) for h in info.get("history_K", [])],
        "loadavg": [list(load0), list(os.getloadavg())],
    }


def run(tree: Path, size: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, str(HERE / "spinup_passes.py"), "--one", str(size)]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree")
    ap.add_argument("--size", type=int, default=10_000)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one)))
        return
    if not args.old_tree:
        ap.error("--old-tree is required")
    runs, pairs = [], []
    for p in range(args.pairs):
        r = {}
        for version, tree in (("old", Path(args.old_tree).resolve()), ("new", HERE.parent)):
            r[version] = run(tree, args.size)
            runs.append({"version": version, "pair": p, "result": r[version]})
            print(json.dumps({"version": version, "pair": p, "spinup_s": r[version]["spinup_s"]}), flush=True)
        pairs.append({"pair": p, "old_over_new_spinup": r["old"]["spinup_s"] / r["new"]["spinup_s"]})
    out = {"benchmark": "spinup_passes", "size": args.size, "old_tree": str(args.old_tree)}
    out.update(pairs=pairs, runs=runs)
    path = HERE / "results" / f"spinup_passes_{args.size}.json"
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
