"""Benchmark: a run with large temporaries reused from the heap (``crater_thermal.heap``, the default)
against glibc's default fresh memory maps (``CRATER_THERMAL_HEAP_REUSE=0``), alternating (issue 24).

Run:  PYTHONPATH=$PWD python bench/heap_reuse.py [--size 30000] [--pairs 2] [--replay]

Each run is its own process: ``bench/spinup_passes.py --one SIZE`` (the scale crater of ``bench/scale.py``,
its periodic start over 2018, a two-day record), with the variable unset or ``0``, alternating off, on,
off, on ... so that this shared machine's load falls on both. Per run: the whole run and the spin-up [s],
each spin-up pass [s], the process's peak resident memory [MB] (its ``ru_maxrss``). Per pair:
off / on. Writes ``bench/results/heap_reuse_<size>.json``; the last stdout line is the same JSON.

``--replay``: instead, one run of the same crater recording 2019-01-01 to 01-21 is made first (heap reuse
on), then its fluxes are replayed (``runner.replay_file``, four density profiles, each with its periodic
start) off and on alternating; writes ``bench/results/heap_reuse_replay_<size>.json``.
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


CHILD = """
import importlib.util, json, resource, sys
spec = importlib.util.spec_from_file_location("spinup_passes", sys.argv[1])
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
out = module.one(int(sys.argv[2]))
out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


REPLAY = """
import json, os, resource, sys, tempfile, time
from crater_thermal import runner
profiles = ["1300/1800", "1100/1800", "800/1100", "1500/1900"]
with tempfile.TemporaryDirectory(prefix="heap_replay_") as tmp:
    t0 = time.perf_counter()
    runner.replay_file(sys.argv[1], profiles, output=os.path.join(tmp, "replay.nc"))
    total = time.perf_counter() - t0
print(json.dumps({"total_s": total, "profiles": profiles, "loadavg": os.getloadavg(),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def make_run(size: int, folder: Path) -> Path:
    """The scale crater's run recording 20 days (the replay's input), made once."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("scale", HERE / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    from crater_thermal import config, runner

    case = folder / "case.toml"
    case.write_text(scale.case_text(size, "2019-01-21T00:00"))
    return runner.run_case(config.load_case(case), folder / "run.nc")


def one(reuse: bool, size: int, flux: Path | None = None) -> dict:
    """One run (or with ``flux`` one replay of it) in its own process, with the heap reuse on or off."""
    env = dict(os.environ, PYTHONPATH=str(HERE.parent), CRATER_THERMAL_HEAP_REUSE="1" if reuse else "0")
    cmd = [sys.executable, "-c", CHILD, str(HERE / "spinup_passes.py"), str(size)]
    if flux is not None:
        cmd = [sys.executable, "-c", REPLAY, str(flux)]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"run failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--replay", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="heap_reuse_") as tmp:
        flux = make_run(args.size, Path(tmp)) if args.replay else None
        runs, pairs = compare(args, flux)
    name = f"heap_reuse_replay_{args.size}" if args.replay else f"heap_reuse_{args.size}"
    out = {"benchmark": "heap_reuse", "facets": args.size, "replay": args.replay, "pairs": pairs, "runs": runs}
    (HERE / "results" / f"{name}.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


def compare(args, flux) -> tuple[list, list]:
    """Off and on alternating, ``args.pairs`` times: (every run, each pair's off / on ratios)."""
    runs, pairs = [], []
    for p in range(args.pairs):
        got = {}
        for reuse in (False, True):
            got[reuse] = one(reuse, args.size, flux)
            runs.append({"reuse": reuse, "pair": p, "result": got[reuse]})
            print(json.dumps(runs[-1]), flush=True)
        pairs.append(
            {
                "pair": p,
                "off_over_on": {
                    key: got[False][key] / got[True][key] for key in ("total_s", "spinup_s") if key in got[True]
                },
            }
        )
    return runs, pairs


if __name__ == "__main__":
    main()
