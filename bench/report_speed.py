"""Benchmark: the report's detection statistics (crater_thermal.instrument) and the report and its test files,
two versions of the code alternating.

Run:  PYTHONPATH=$PWD python bench/report_speed.py --old-tree DIR [--repeat 3] [--tests tests/test_report.py ...]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). Each measurement
is a fresh process with that version first on ``PYTHONPATH`` (``--one``), the processes alternating old,
new, old, new ...; the remembered values of the instrument module (its ``functools`` caches) are cleared
before each timed round of calls (median of 7 rounds), so every timing starts cold. Per call [ms]:
``dwell_for_detection`` over 48 scenes (4 presets x 3 contrasts x 4 nominal temperatures, default
observation), ``detection_probability`` of one facet (the site map's former loop) and of 300 facets in one
call, ``noise_terms`` of one scene, ``band_radiance_derivative`` of one temperature; and one
``report.make_report`` [s] of the test suite's synthetic runs at -86 and -80 deg (tests/synthetic.py of this
tree, snapshots off). The outputs are compared between the versions: the dwell answers (every number) and
the report's summary.json, report.html and figures (bytes). With ``--tests`` each named test file is also
run by pytest in each tree (old, new alternating, ``--repeat`` times) and its wall time recorded. Writes
``bench/results/report_speed.json`` and prints it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: the synthetic runs of the report tests (tests/test_report.py's ``files`` and ``test_several_latitudes``)
RUNS = ((-86.0, 1.5), (-80.0, 1.0))


def _cold(ins) -> None:
    """Clear the instrument module's remembered values (every functools cache it has)."""
    for v in vars(ins).values():
        if hasattr(v, "cache_clear"):
            v.cache_clear()


def _per_call_ms(ins, f, calls) -> float:
    """Median over 7 rounds of the time per call [ms] of ``f`` over ``calls``, caches cleared each round."""
    out = []
    for _ in range(7):
        _cold(ins)
        t0 = time.perf_counter()
        for c in calls:
            f(*c)
        out.append(1e3 * (time.perf_counter() - t0) / len(calls))
    return float(np.median(out))


def one(out_dir: Path) -> dict:
    sys.path.insert(0, str(HERE.parent / "tests"))
    from crater_thermal import instrument as ins
    from crater_thermal import report as rp

    from synthetic import make_replay, make_run

    presets = [ins.PRESETS[n] for n in ("diviner_ch7", "diviner_ch8", "diviner_ch9", "microbolometer")]
    obs = ins.Observation()
    scenes = [(dT, Tn, i, obs) for i in presets for dT in (-3.0, -1.0, -0.3) for Tn in (40.0, 55.0, 70.0, 95.0)]
    rng = np.random.default_rng(1)
    Tn = 45.0 + 40.0 * rng.random(300)
    dT = -3.0 * rng.random(300)
    ch9 = ins.PRESETS["diviner_ch9"]
    facets = [(dT[k], Tn[k], np.array([100.0]), ch9, obs) for k in range(Tn.size)]
    res = {
        "dwell_for_detection_ms": _per_call_ms(ins, ins.dwell_for_detection, scenes),
        "detection_probability_one_facet_ms": _per_call_ms(ins, ins.detection_probability, facets),
        "detection_probability_300_facets_ms": _per_call_ms(
            ins, ins.detection_probability, [(dT, Tn, 100.0, ch9, obs)]
        ),
        "noise_terms_ms": _per_call_ms(ins, ins.noise_terms, [(55.0, 58.0, 100.0, ch9, obs)] * 300),
        "band_radiance_derivative_ms": _per_call_ms(ins, ins.band_radiance_derivative, [(58.0, ch9.band)] * 300),
    }
    _cold(ins)
    answers = [ins.dwell_for_detection(*s) for s in scenes]
    runs = [make_run(lat_deg=lat, n_lunar_days=days, n_rings=8) for lat, days in RUNS]
    reps = [make_replay(r) for r in runs]
    rp.make_report(runs[0], reps[0], out_dir / "warm", progress=False, snapshots=False)  # imports, fonts
    _cold(ins)
    t0 = time.perf_counter()
    rp.make_report(runs, reps, out_dir / "report", progress=False, snapshots=False)
    res["make_report_s"] = time.perf_counter() - t0
    pd_loop = [float(np.ravel(ins.detection_probability(*f))[0]) for f in facets]
    pd_vec = ins.detection_probability(dT, Tn, 100.0, ch9, obs)
    res["site_map_loop_equals_one_call"] = bool(np.array_equal(pd_loop, pd_vec))
    files = sorted(p for p in (out_dir / "report").rglob("*") if p.is_file())
    res["report_sha256"] = {
        str(p.relative_to(out_dir / "report")): hashlib.sha256(p.read_bytes()).hexdigest() for p in files
    }
    res["dwell_answers"] = json.loads(json.dumps(answers, default=float))
    return res


def _max_rel_diff(a, b) -> float:
    """Largest relative difference between the numbers of two equal-shaped JSON structures (0: identical)."""
    if isinstance(a, dict):
        assert set(a) == set(b)
        return max([_max_rel_diff(a[k], b[k]) for k in a] or [0.0])
    if isinstance(a, list):
        assert len(a) == len(b)
        return max([_max_rel_diff(x, y) for x, y in zip(a, b)] or [0.0])
    if isinstance(a, float) and isinstance(b, float) and a != b:
        return abs(a - b) / max(abs(a), abs(b))
    assert a == b or (a != a and b != b), (a, b)
    return 0.0


def _pytest_wall_s(tree: Path, test_file: str) -> tuple[float, str]:
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(tree))
    env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test_file]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: {test_file} failed:\n{proc.stdout[-3000:]}")
    return wall, proc.stdout.strip().splitlines()[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree", default=None)
    ap.add_argument("--old-label", default="old")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tests", nargs="*", default=[], help="test files (relative to the repository) to time")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(Path(args.one))))
        return
    if not args.old_tree:
        raise SystemExit("--old-tree DIR is required (a copy of the version to compare with)")
    trees = {"old": Path(args.old_tree).resolve(), "new": HERE.parent}
    runs = []
    keys = None
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            for which in ("old", "new"):
                env = dict(os.environ, PYTHONPATH=str(trees[which]), MPLBACKEND="Agg")
                out = Path(tmp) / f"{which}{r}"
                cmd = [sys.executable, str(HERE / "report_speed.py"), "--one", str(out)]
                proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
                if proc.returncode != 0:
                    raise SystemExit(f"{which}: failed: {proc.stderr[-3000:]}")
                res = json.loads(proc.stdout.strip().splitlines()[-1])
                runs.append({"version": which, "repeat": r, "loadavg": os.getloadavg(), **res})
                keys = [k for k, v in res.items() if isinstance(v, float)]
                print(json.dumps({k: v for k, v in runs[-1].items() if k not in ("dwell_answers", "report_sha256")}))
    old0 = next(x for x in runs if x["version"] == "old")
    new0 = next(x for x in runs if x["version"] == "new")
    med = {w: {k: float(np.median([x[k] for x in runs if x["version"] == w])) for k in keys} for w in ("old", "new")}
    tests = []
    for test_file in args.tests:
        for r in range(args.repeat):
            for which in ("old", "new"):
                wall, tail = _pytest_wall_s(trees[which], test_file)
                row = {"file": test_file, "version": which, "repeat": r, "wall_s": round(wall, 2), "pytest": tail}
                tests.append({**row, "loadavg": os.getloadavg()})
                print(json.dumps(tests[-1]), flush=True)
    test_med = {
        f: {w: float(np.median([t["wall_s"] for t in tests if t["file"] == f and t["version"] == w])) for w in trees}
        for f in args.tests
    }
    result = {
        "benchmark": "report_speed",
        "old": args.old_label,
        "median": med,
        "old_over_new": {k: round(med["old"][k] / med["new"][k], 2) for k in keys},
        "same_report_bytes": old0["report_sha256"] == new0["report_sha256"],
        "report_files_compared": len(new0["report_sha256"]),
        "dwell_answers_max_rel_diff": _max_rel_diff(old0["dwell_answers"], new0["dwell_answers"]),
        "site_map_loop_equals_one_call": new0["site_map_loop_equals_one_call"],
        "test_files_wall_s_median": test_med,
        "test_runs": tests,
        "runs": [{k: v for k, v in x.items() if k not in ("dwell_answers", "report_sha256")} for x in runs],
    }
    (HERE / "results" / "report_speed.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k not in ("runs", "test_runs")}))


if __name__ == "__main__":
    main()
