"""Benchmark: our side of ``bench/pcc_topo3d.py`` with two versions of the code, alternating (issue 24).

Whole ``python -m crater_thermal run`` processes on PCC's topo81 terrain (12,800 facets, 12 lunar days at
4-hour steps, the horizon-map cache cold for every run), the two trees taking turns (A B, B A, ...) after one
untimed warm-up run each (compiled-kernel caches).  ``--sleep`` seconds of idle before every run: in the side
by side each of our runs follows a ~260-s PCC run, by which time this VM has handed the memory freed by the
run before back to its host (free page reporting), and fresh pages cost ~9 us each to fault in again (0.45
GB/s, against 7-8 GB/s for pages freed a moment earlier); 10 s is enough for that (measured: pages freed 2 s
earlier are still fast, 4 s earlier slow).

Each tree runs with its own sources (``PYTHONPATH``) and this interpreter's packages.  Prints and writes
JSON: per run wall and CPU seconds, the minimum wall per tree and their ratio.

Usage: ``python bench/ab_pcc.py --old-tree DIR [--new-tree DIR] [--pairs 3] [--sleep 10] [--out PATH]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from pcc_topo3d import CASE, simulate_end  # noqa: E402

from crater_thermal import geometry  # noqa: E402
from crater_thermal.reference import pcc_topo81  # noqa: E402


def _run(tree: Path, work: Path, tag: str, sleep_s: float) -> dict:
    time.sleep(sleep_s)
    env = dict(os.environ, PYTHONPATH=str(tree), CRATER_THERMAL_CACHE=str(work / f"cache_{tag}"))
    cmd = [sys.executable, "-m", "crater_thermal", "run", "case.toml", "-o", "run.nc", "--overwrite", "--quiet"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: run failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "load": round(os.getloadavg()[0], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old-tree", type=Path, required=True)
    ap.add_argument("--new-tree", type=Path, default=REPO)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--sleep", type=float, default=10.0, help="idle seconds before every run")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "ab_pcc.json")
    args = ap.parse_args()
    trees = {"old": args.old_tree.resolve(), "new": args.new_tree.resolve()}
    runs: dict[str, list] = {"old": [], "new": []}
    with tempfile.TemporaryDirectory(prefix="ab_pcc_") as tmpdir:
        work = Path(tmpdir)
        geometry.save_mesh(pcc_topo81(), work / "topo81.ply")
        (work / "case.toml").write_text(CASE.format(end=simulate_end()))
        for name, tree in trees.items():
            _run(tree, work, f"{name}_warm", 0.0)
        for i in range(args.pairs):
            for name in ("old", "new") if i % 2 == 0 else ("new", "old"):
                r = _run(trees[name], work, f"{name}_{i}", args.sleep)
                runs[name].append(r)
                print(name, r, flush=True)
    best = {name: min(r["wall_s"] for r in rs) for name, rs in runs.items()}
    res = {
        "benchmark": "ab_pcc",
        "trees": {k: str(v) for k, v in trees.items()},
        "sleep_s": args.sleep,
        "runs": runs,
        "min_wall_s": best,
        "old_over_new_min_wall": round(best["old"] / best["new"], 3),
        "old_over_new_per_pair": [round(a["wall_s"] / b["wall_s"], 3) for a, b in zip(runs["old"], runs["new"])],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
