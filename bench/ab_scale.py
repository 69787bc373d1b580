"""Benchmark: one size of ``bench/scale.py`` with two versions of the code, alternating (issue 24).

Run:  PYTHONPATH=$PWD python bench/ab_scale.py --old-tree DIR [--size 10000] [--pairs 1] [--label NAME]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). Each run is
``bench/scale.py --sizes SIZE`` of that version, in its own process with that version first on
``PYTHONPATH`` (the same virtual environment), the full year from the mesh to ``run.nc`` with cold
caches; the runs alternate old, new, old, new ... so that this shared machine's load falls on both.
Per run: the scale benchmark's own record (total, stages, peak memory, load); per pair: the ratios
old / new of the total and of every stage. Writes ``bench/results/ab_scale_<label>.json``; the last stdout
line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run(tree: Path, size: int, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, str(tree / "bench" / "scale.py"), "--sizes", str(size), "--out", str(out)]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: scale.py failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(out.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree", required=True)
    ap.add_argument("--old-label", default="old")
    ap.add_argument("--size", type=int, default=10_000)
    ap.add_argument("--pairs", type=int, default=1)
    ap.add_argument("--label", default="10k")
    args = ap.parse_args()
    trees = {"old": Path(args.old_tree).resolve(), "new": HERE.parent}
    runs, pairs = [], []
    with tempfile.TemporaryDirectory(prefix="ab_scale_") as tmp:
        for p in range(args.pairs):
            pair = {}
            for which in ("old", "new"):
                res = run(trees[which], args.size, Path(tmp) / f"{which}{p}.json")
                size = {k: v[0] for k, v in res.items() if isinstance(v, list) and v}  # the one size's entries
                runs.append({"version": which, "pair": p, "result": size})
                pair[which] = size
                print(json.dumps({"version": which, "pair": p, "total_s": size.get("total_s")}), flush=True)
            ratio = {}
            for key in ("total_s",):
                if pair["old"].get(key) and pair["new"].get(key):
                    ratio[key] = round(pair["old"][key] / pair["new"][key], 3)
            so, sn = pair["old"].get("stages_s", {}), pair["new"].get("stages_s", {})
            ratio["stages"] = {k: round(so[k] / sn[k], 3) for k in so if k in sn and sn[k] > 0}
            pairs.append({"pair": p, "old_over_new": ratio})
    result = {
        "benchmark": "ab_scale",
        "size": args.size,
        "old": args.old_label,
        "new": "this tree",
        "pairs": pairs,
        "runs": runs,
    }
    out = HERE / "results" / f"ab_scale_{args.label}.json"
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
