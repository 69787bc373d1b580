"""Benchmark: how far a change moves a run's results: the scale crater run by two versions of the code.

Run:  PYTHONPATH=$PWD python bench/ab_run_difference.py --old-tree DIR [--facets 2000] [--days 29.53]
                                                        [--spinup-ir lagged] [--label NAME]

``DIR`` holds another version of the repository (``git archive COMMIT | tar -x -C DIR``). The case is
``bench/scale.py``'s crater (10 km, 5 km flat surround, 86 S) at ``--facets``, the periodic start over
2018 (``[period] spinup_ir`` as given) and ``--days`` recorded from 2019-01-01, run once by each version
in its own process (that version first on ``PYTHONPATH``, a cache of its own). Compared: the start's
residuals, and the surface temperatures [K] of every recorded sample: the largest difference, and at night
on permanently shadowed or night-time facets (direct sunlight zero at the sample), the quantity the
answer is made of. Writes ``bench/results/ab_run_difference_<label>.json``; the last stdout line is the
same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RUN = """
import sys
sys.path.insert(0, {bench!r})
import scale
from crater_thermal import config, runner
from pathlib import Path
p = Path({case!r})
p.write_text(scale.case_text({facets}, {end!r}, spinup=scale.PERIODIC_SPINUP + '\\nspinup_ir = "{ir}"'))
runner.run_case(config.load_case(p), {out!r}, progress=False)
"""


def run(tree: Path, tmp: Path, name: str, facets: int, end: str, ir: str) -> Path:
    out = tmp / f"{name}.nc"
    code = RUN.format(
        bench=str(tree / "bench"), case=str(tmp / f"{name}.toml"), facets=facets, end=end, ir=ir, out=str(out)
    )
    env = dict(os.environ, PYTHONPATH=str(tree), CRATER_THERMAL_CACHE=str(tmp / f"cache_{name}"))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: the run failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-tree", required=True)
    ap.add_argument("--new-tree", default=str(HERE.parent))
    ap.add_argument("--facets", type=int, default=2000)
    ap.add_argument("--days", type=float, default=29.53)
    ap.add_argument("--spinup-ir", default="lagged", choices=["lagged", "coupled", "auto"])
    ap.add_argument("--label", default="change")
    args = ap.parse_args()
    end = str(np.datetime64("2019-01-01T00:00") + np.timedelta64(int(round(args.days * 86400)), "s"))
    import xarray as xr

    with tempfile.TemporaryDirectory(prefix="abdiff_") as tmp:
        tmp = Path(tmp)
        paths = {
            side: run(Path(tree), tmp, side, args.facets, end, args.spinup_ir)
            for side, tree in (("old", args.old_tree), ("new", args.new_tree))
        }
        with xr.open_dataset(paths["old"]) as a, xr.open_dataset(paths["new"]) as b:
            Ta, Tb = a["surface_temperature"].values, b["surface_temperature"].values
            night = (a["solar_direct"].values == 0) & (b["solar_direct"].values == 0)
            d = np.abs(Ta.astype(np.float64) - Tb)
            res = {
                "benchmark": "ab_run_difference",
                "label": args.label,
                "old_tree": str(args.old_tree),
                "facets": int(a.sizes["facet"]),
                "samples": int(a.sizes["time"]),
                "spinup_ir": args.spinup_ir,
                "start_method": [a.attrs.get("start_method"), b.attrs.get("start_method")],
                "start_residual_max_K": [float(a["start_residual"].max()), float(b["start_residual"].max())],
                "max_abs_dT_K": float(d.max()),
                "night_max_abs_dT_K": float(d[night].max()) if night.any() else None,
                "night_fraction": float(night.mean()),
                "max_abs_dT_first_sample_K": float(d[0].max()),
            }
    out = HERE / "results" / f"ab_run_difference_{args.label}.json"
    out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
