"""Benchmark: a run with large temporaries reused from the heap (``crater_thermal.heap``, the default)
against glibc's default fresh memory maps (``CRATER_THERMAL_HEAP_REUSE=0``), alternating (issue 24).

Run:  PYTHONPATH=$PWD python bench/heap_reuse.py [--size 30000] [--pairs 2]

Each run is its own process: ``bench/spinup_passes.py --one SIZE`` (the scale crater of ``bench/scale.py``,
its periodic start over 2018, a two-day record), with the variable unset or ``0``, alternating off, on,
off, on ... so that this shared machine's load falls on both. Per run: the whole run and the spin-up [s],
each spin-up pass [s], the process's peak resident memory [MB] (its ``ru_maxrss``). Per pair:
off / on. Writes ``bench/results/heap_reuse_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


CHILD = """
import importlib.util, json, resource, sys
spec = importlib.util.spec_from_file_location("spinup_passes", sys.argv[1])
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
out = module.one(int(sys.argv[2]))
out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def one(reuse: bool, size: int) -> dict:
    """One run in its own process, with the heap reuse on or off."""
    env = dict(os.environ, PYTHONPATH=str(HERE.parent), CRATER_THERMAL_HEAP_REUSE="1" if reuse else "0")
    cmd = [sys.executable, "-c", CHILD, str(HERE / "spinup_passes.py"), str(size)]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"run failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--pairs", type=int, default=2)
    args = ap.parse_args()
    runs, pairs = [], []
    for p in range(args.pairs):
        got = {}
        for reuse in (False, True):
            got[reuse] = one(reuse, args.size)
            runs.append({"reuse": reuse, "pair": p, "result": got[reuse]})
            print(json.dumps(runs[-1]), flush=True)
        pairs.append(
            {
                "pair": p,
                "off_over_on": {
                    "total": got[False]["total_s"] / got[True]["total_s"],
                    "spinup": got[False]["spinup_s"] / got[True]["spinup_s"],
                },
            }
        )
    out = {"benchmark": "heap_reuse", "facets": args.size, "pairs": pairs, "runs": runs}
    (HERE / "results" / f"heap_reuse_{args.size}.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
