"""Benchmark: the lagged periodic spin-up with coarse first windows against the plain one (issue 24).

Run:  PYTHONPATH=$PWD python bench/spinup_coarse.py [--facets 10000] [--coarse 3] [--pairs 1]

The case of ``bench/scale.py`` (the generator's 10 km crater with a 5 km surround at 86 S, one recorded
year at 4 h after the periodic start over the year before), run alternating in this one process:
``[period] spinup_coarse_steps = 1`` (plain: every window at full resolution) and ``= --coarse``
(the first windows on every n-th sample, ``simulate.spin_up``), each with its own cold cache folder,
after one untimed warm-up run on a 300-facet crater. Per run: the whole run and its stages
(``simulate.Timer``), the windows taken, the start's residual. Accuracy: the recorded surface
temperatures of each coarse run against the plain run of its pair (max and 99.9th percentile of |dT| over
every sample, and over night samples only: Sun below the horizon of the crater centre). Writes
``bench/results/spinup_coarse.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import scale  # noqa: E402  (the case text of the scale benchmark)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=10_000)
    ap.add_argument("--coarse", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=1)
    ap.add_argument("--days", type=float, default=365.0, help="recorded days")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "spinup_coarse.json"))
    args = ap.parse_args()
    from crater_thermal import config, io, runner, simulate

    end = str(np.datetime64("2019-01-01T00:00") + np.timedelta64(int(round(args.days * 86400)), "s"))
    runs = []
    with tempfile.TemporaryDirectory(prefix="spinup_coarse_") as tmp:
        tmp = Path(tmp)

        def case(facets, end, spinup, name):
            path = tmp / f"{name}.toml"
            text = scale.CASE.format(
                facets=facets,
                diameter_km=10.0,
                surround_km=5.0,
                lat_deg=-86.0,
                chunk_mb=256.0,
                extra="",
                end=end,
                spinup=spinup,
            )
            path.write_text(text)
            return config.load_case(path)

        os.environ["CRATER_THERMAL_CACHE"] = str(tmp / "cache_warm")
        runner.run_case(case(300, "2019-01-02T00:00", 'spinup = "fixed"\nspinup_days = 1.0', "warm"), tmp / "warm.nc")
        for p in range(args.pairs):
            pair = {}
            for label, n in (("plain", 1), ("coarse", args.coarse)):
                name = f"{label}{p}"
                os.environ["CRATER_THERMAL_CACHE"] = str(tmp / f"cache_{name}")  # cold caches every run
                c = case(
                    args.facets, end, f'spinup = "periodic"\nspinup_years = 1.0\nspinup_coarse_steps = {n}', name
                )
                timer = simulate.Timer()
                load0 = os.getloadavg()
                t0 = time.perf_counter()
                out = runner.run_case(c, tmp / f"{name}.nc", timer=timer)
                total = time.perf_counter() - t0
                ds = io.open_run(out)
                T = ds["surface_temperature"].values
                night = ds["sun_direction"].values[:, 2] < 0
                run = {
                    "label": label,
                    "pair": p,
                    "spinup_coarse_steps": n,
                    "total_s": round(total, 2),
                    "stages_s": {k: round(v, 2) for k, v in timer.split.items()},
                    "start_method": str(ds.attrs["start_method"]),
                    "start_residual_max_K": float(ds["start_residual"].values.max()),
                    "loadavg": [load0, os.getloadavg()],
                }
                pair[label] = (T, night)
                if label == "coarse":
                    d = np.abs(T - pair["plain"][0])
                    dn = d[night]
                    run["vs_plain_max_K"] = float(d.max())
                    run["vs_plain_p999_K"] = float(np.quantile(d, 0.999))
                    run["vs_plain_night_max_K"] = float(dn.max()) if dn.size else None
                    run["speedup_total"] = round(runs[-1]["total_s"] / total, 3)
                    run["speedup_spinup"] = round(
                        runs[-1]["stages_s"]["conduction_spinup"] / timer.split["conduction_spinup"], 3
                    )
                ds.close()
                runs.append(run)
                print(json.dumps(run), flush=True)
    result = {"benchmark": "spinup_coarse", "facets": args.facets, "recorded_days": args.days, "runs": runs}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
