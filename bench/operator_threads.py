"""Benchmark: the scale crater's view-factor operator and horizon map, built together as a run builds them,
with two versions of the code, alternating (issue 24).

Run:  PYTHONPATH=$PWD python bench/operator_threads.py --old-tree DIR [--size 30000] [--pairs 2] [--label NAME]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). Each build runs in
its own process with that version first on ``PYTHONPATH``: the scale crater of ``bench/scale.py`` at
``--size`` facets, :func:`crater_thermal.simulate.case_operator_and_horizons` with a cold cache (after a
300-facet warm-up that compiles or loads the kernels), timed by the run's own stage timer. The builds
alternate old, new, old, new ... so that this shared machine's load falls on both. Per build: the wall
seconds of the two stages (they overlap) and of the whole call, the process CPU seconds, the load; per
pair the ratios old / new. The operators are compared through the product with one fixed vector (max
absolute difference [-]) and the horizon maps entry by entry. Writes
``bench/results/operator_threads_<label>.json``; the last stdout line is the same JSON.
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

import numpy as np

HERE = Path(__file__).resolve().parent


def child(size: int, out: Path) -> None:
    """One build in this process (the ``crater_thermal`` first on ``PYTHONPATH``)."""
    sys.path.insert(0, str(HERE))
    from scale import case_text

    from crater_thermal import config, simulate

    with tempfile.TemporaryDirectory(prefix="operator_threads_") as tmp:
        tmp = Path(tmp)
        os.environ["CRATER_THERMAL_CACHE"] = str(tmp / "cache")
        for n, name in ((300, "warm"), (size, "case")):
            (tmp / f"{name}.toml").write_text(case_text(n, "2019-01-02T00:00"))
            case = config.load_case(tmp / f"{name}.toml")
            timer = simulate.Timer()
            mesh, tracer = simulate.case_scene(case, timer)
            load0 = os.getloadavg()
            t0, c0 = time.perf_counter(), time.process_time()
            F, hmap = simulate.case_operator_and_horizons(case, mesh, tracer, timer)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        x = np.random.default_rng(0).random(mesh.n_facets)
        np.savez(
            out.with_suffix(".npz"),
            Fx=F @ x,
            **{f"h_{k}": np.asarray(v) for k, v in vars(hmap).items() if isinstance(v, np.ndarray)},
        )
        out.write_text(
            json.dumps(
                {
                    "facets": mesh.n_facets,
                    "wall_s": wall,
                    "cpu_s": cpu,
                    "stages_s": {k: timer.split[k] for k in ("viewfactors", "horizons") if k in timer.split},
                    "loadavg": [load0, os.getloadavg()],
                }
            )
        )


def run(tree: Path, size: int, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(size), "--out", str(out)]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: build failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(out.read_text())


def compare(a: Path, b: Path) -> dict:
    """Max |difference| of the operators' products with the fixed vector and of the horizon maps' arrays."""
    with np.load(a) as x, np.load(b) as y:
        diff = {k: float(np.max(np.abs(x[k].astype(float) - y[k].astype(float)))) for k in x.files if k in y.files}
    return diff


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree")
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--label", default="30k")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, Path(args.out))
        return
    if not args.old_tree:
        ap.error("--old-tree DIR is required")
    trees = {"old": Path(args.old_tree).resolve(), "new": HERE.parent}
    runs, pairs = [], []
    with tempfile.TemporaryDirectory(prefix="operator_threads_ab_") as tmp:
        for p in range(args.pairs):
            pair = {}
            for which in ("old", "new") if p % 2 == 0 else ("new", "old"):
                res = run(trees[which], args.size, Path(tmp) / f"{which}{p}.json")
                runs.append({"version": which, "pair": p, **res})
                pair[which] = res
                print(json.dumps(runs[-1]), flush=True)
            ratio = {"wall": pair["old"]["wall_s"] / pair["new"]["wall_s"]}
            for k in pair["new"]["stages_s"]:
                ratio[k] = pair["old"]["stages_s"][k] / pair["new"]["stages_s"][k]
            pairs.append({"pair": p, "old_over_new": ratio})
        same = compare(Path(tmp) / "old0.npz", Path(tmp) / "new0.npz")
    result = {
        "benchmark": "operator_threads",
        "facets": args.size,
        "old_tree": str(trees["old"]),
        "pairs": pairs,
        "runs": runs,
        "max_abs_difference": same,
    }
    out = HERE / "results" / f"operator_threads_{args.label}.json"
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
