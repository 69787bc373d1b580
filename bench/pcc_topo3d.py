"""Benchmark: side by side with Planetary-Code-Collection Topo3D on its RUN 3 test terrain (issue 13).

PCC's Topo3D test (``Topo3D/Test/README_testcase.txt``, RUN 3): ``topo81.xyz`` (81 x 81 heights at 5 m, a
bowl of depth/diameter 1:5 in a flat plain), latitude 80 deg, 12 lunar days with subsurface conduction, 100
steps per lunar day.  Our side runs the same heights (``crater_thermal.reference.pcc_topo81``: 12,800 facets) through
``crater-thermal run`` as a whole process (start-up, ephemeris, horizon map with a cold cache, view-factor operator,
scattering, coupled conduction + IR, writing ``run.nc``): 12 synodic months (354.37 d) recorded at 4-hour flux
steps from the equilibrium estimate (fixed spin-up of 0 days, as PCC starts from its own initial state).

Figure of merit: column-lunar-days per second = columns x lunar days / wall seconds (PCC: 6,241 pixel
columns; ours: 12,800 facet columns), and the same per CPU second (user + system of the child process).

PCC is not vendored: build it yourself (gfortran; ``shadows``, ``fieldofviews`` and ``cratersQ_moon`` set up
for RUN 3) and pass a script that runs the three from scratch with ``--pcc-script``.  Runs alternate (ours,
PCC, ours, ...) ``--repeat`` times in this one process, so both see the same machine load; the minimum and the
median of each are reported.  Without ``--pcc-script`` only our side is timed.  ``--compression blosc_lz4``
also times our run with that ``[output] compression`` (run.nc's series written with the blosc filter instead
of zlib), alternating with the default one (``ours_blosc_lz4`` and ``ratio_wall_blosc_lz4`` in the JSON).

Also, once, an in-process run for our stage split (``simulate.Timer``).

Prints one JSON object on its last stdout line and writes bench/results/pcc_topo3d.json (``--out``).
Usage: ``python bench/pcc_topo3d.py [--pcc-script /path/run3.sh] [--repeat 1] [--compression blosc_lz4]
[--out PATH]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import (  # noqa: E402
    choices,
    config,
    geometry,
    runner,  # noqa: E402
    simulate,
)
from crater_thermal.reference import pcc_topo81  # noqa: E402

LUNAR_DAYS = 12
SYNODIC_DAYS = 29.530589
PCC_PIXELS = 79 * 79  # the 81 x 81 grid's interior: the pixels cratersQ_moon computes (6,241)

CASE = """
name = "pcc_topo81"
description = "PCC Topo3D RUN 3 terrain (topo81), 12 lunar days at 80 N"
[crater]
kind = "mesh"
mesh = "topo81.ply"
[location]
lat_deg = 80.0
lon_deg = 0.0
[period]
start = "2019-01-01T00:00:00"
end = "{end}"
spinup = "fixed"
spinup_days = 0.0
[steps]
flux_step_hours = 4.0
"""


def _timed(cmd: list[str], cwd: Path, env: dict | None = None) -> tuple[float, float]:
    """Wall and CPU (user + system) seconds of one child process; raises on failure."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _summary(xs: list[float]) -> dict:
    return {"min": round(min(xs), 2), "median": round(statistics.median(xs), 2), "all": [round(x, 2) for x in xs]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pcc-script", type=Path, default=None, help="script that runs PCC RUN 3 from scratch")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "pcc_topo3d.json")
    ap.add_argument(
        "--compression",
        choices=[c for c in choices.OUTPUT_COMPRESSIONS if c != "zlib"],
        default=None,
        help="also time our run with this [output] compression, alternating with the default (ours_<name>)",
    )
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="pcc_topo3d_") as tmpdir:
        tmp = Path(tmpdir)
        mesh = pcc_topo81()
        geometry.save_mesh(mesh, tmp / "topo81.ply")
        end = simulate_end()
        (tmp / "case.toml").write_text(CASE.format(end=end))
        exe = str(Path(sys.executable).with_name("crater-thermal"))
        ours_cmd = [exe, "run", "case.toml", "-o", "run.nc", "--overwrite", "--quiet"]
        if args.compression:
            (tmp / "case_c.toml").write_text(CASE.format(end=end) + f'[output]\ncompression = "{args.compression}"\n')
        alt_cmd = [exe, "run", "case_c.toml", "-o", "run_c.nc", "--overwrite", "--quiet"]
        alt_wall, alt_cpu = [], []

        def cold(i: int) -> dict:
            # a fresh horizon-map cache for every run: each pays every stage, as PCC does
            return dict(os.environ, CRATER_THERMAL_CACHE=str(tmp / f"cache{i}"))

        # warm-up (compiled-kernel cache, page cache), untimed
        _timed(ours_cmd, tmp, cold(-1))
        ours_wall, ours_cpu, pcc_wall, pcc_cpu = [], [], [], []
        for i in range(args.repeat):
            w, c = _timed(ours_cmd, tmp, cold(i))
            ours_wall.append(w)
            ours_cpu.append(c)
            if args.compression:
                w, c = _timed(alt_cmd, tmp, cold(1000 + i))
                alt_wall.append(w)
                alt_cpu.append(c)
            if args.pcc_script is not None:
                w, c = _timed(["bash", str(args.pcc_script)], tmp)
                pcc_wall.append(w)
                pcc_cpu.append(c)

        os.environ["CRATER_THERMAL_CACHE"] = str(tmp / "cache_split")
        case = config.load_case(tmp / "case.toml")
        timer = simulate.Timer()
        t = time.perf_counter()
        runner.run_case(case, tmp / "split.nc", progress=False, timer=timer, overwrite=True)
        in_process = time.perf_counter() - t

    n = int(mesh.faces.shape[0])
    res = {
        "terrain": "PCC Topo3D topo81 (81 x 81 at 5 m), rebuilt: crater_thermal.reference.pcc_topo81",
        "lunar_days": LUNAR_DAYS,
        "ours": {
            "facets": n,
            "flux_step_hours": 4.0,
            "wall_s": _summary(ours_wall),
            "cpu_s": _summary(ours_cpu),
            "column_lunar_days_per_s": round(n * LUNAR_DAYS / min(ours_wall), 1),
            "in_process_s": round(in_process, 2),
            "split_s": {k: round(v, 2) for k, v in timer.split.items()},
        },
        "load_average": os.getloadavg()[0],
    }
    if alt_wall:
        res[f"ours_{args.compression}"] = {
            "wall_s": _summary(alt_wall),
            "cpu_s": _summary(alt_cpu),
            "column_lunar_days_per_s": round(n * LUNAR_DAYS / min(alt_wall), 1),
            "default_over_this_wall": round(min(ours_wall) / min(alt_wall), 3),
        }
    if pcc_wall:
        pcc_rate = PCC_PIXELS * LUNAR_DAYS / min(pcc_wall)
        res["pcc"] = {
            "pixels": PCC_PIXELS,
            "steps_per_lunar_day": 100,
            "wall_s": _summary(pcc_wall),
            "cpu_s": _summary(pcc_cpu),
            "column_lunar_days_per_s": round(pcc_rate, 1),
        }
        res["ratio_wall"] = round(res["ours"]["column_lunar_days_per_s"] / pcc_rate, 2)
        res["ratio_cpu"] = round((n / min(ours_cpu)) / (PCC_PIXELS / min(pcc_cpu)), 2)
        if alt_wall:
            res[f"ratio_wall_{args.compression}"] = round(
                res[f"ours_{args.compression}"]["column_lunar_days_per_s"] / pcc_rate, 2
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))


def simulate_end() -> str:
    """End instant of 12 synodic months recorded from 2019-01-01 (ISO, UTC, to the second)."""
    import datetime as dt

    end = dt.datetime(2019, 1, 1) + dt.timedelta(days=LUNAR_DAYS * SYNODIC_DAYS)
    return end.replace(microsecond=0).isoformat()


if __name__ == "__main__":
    main()
