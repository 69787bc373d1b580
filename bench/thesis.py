"""Benchmark: one latitude of the thesis setup (10 km crater, 502 facets, 4-hour flux steps, 86 S).

Measures, in one process:

* ``nominal_run_s``: the thesis procedure (cases/thesis/faithful/crater_lat86S_faithful.toml: three years
  of spin-up from a uniform start, then the recorded year) - target <= 60 s on 2 cores;
* ``converged_run_s``: the default procedure (periodic steady state over the year before the record,
  then the record), with ``converged_start_in_years`` = the spin-up's conduction time divided by the
  conduction time of the recorded year (issue 6 target: <= 10);
* ``density_grid_replay_s``: replay of the 91-profile density grid 800:2000:100 against the converged
  run's saved fluxes (periodic start per profile) - target <= 600 s;
* ``split_s``: where the time of the converged run went (geometry, view factors, ephemeris, direct
  sunlight, radiosity, conduction, io).

Prints one JSON object on its last stdout line and writes bench/results/thesis.json.
Usage: ``python bench/thesis.py [--skip-grid]``.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import config, io, runner, simulate, thermal  # noqa: E402


def main() -> None:
    skip_grid = "--skip-grid" in sys.argv
    os.environ.setdefault("CRATER_THERMAL_QUIET", "1")
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # warm-up: numba compilation and the view-factor cache are not what we measure
        warm = config.load_case(REPO / "cases" / "default.toml")
        runner.run_case(warm, tmp / "warm.nc", progress=False)

        faithful = config.load_case(REPO / "cases" / "thesis" / "faithful" / "crater_lat86S_faithful.toml")
        timer = simulate.Timer()
        t = time.perf_counter()
        runner.run_case(faithful, tmp / "faithful.nc", progress=False, timer=timer)
        result["nominal_run_s"] = time.perf_counter() - t
        result["nominal_run_split_s"] = {k: round(v, 3) for k, v in timer.split.items()}

        converged = config.load_case(REPO / "cases" / "thesis" / "crater_lat86S.toml")
        timer = simulate.Timer()
        t = time.perf_counter()
        out = runner.run_case(converged, tmp / "converged.nc", progress=False, timer=timer)
        result["converged_run_s"] = time.perf_counter() - t
        result["split_s"] = {k: round(v, 3) for k, v in timer.split.items()}
        ds = io.open_run(out)
        result["spinup_iterations"] = int(ds.attrs["spinup_iterations"])
        # the record phase is one plain year of coupled simulation; the spin-up is the rest of "conduction"
        plain_year = timer.split.get("conduction_record", None)
        if plain_year:
            result["plain_year_s"] = round(plain_year, 3)
            result["converged_start_in_years"] = round(timer.split["conduction_spinup"] / plain_year, 2)

        if not skip_grid:
            profiles = list(thermal.density_grid_profiles("800:2000:100"))
            t = time.perf_counter()
            T, info = simulate.replay_fluxes(ds, profiles, progress=False)
            result["density_grid_replay_s"] = time.perf_counter() - t
            result["profiles"] = len(profiles)
            result["replay_periodic_iterations_max"] = max(info["periodic_iterations"])
    result["targets"] = {"nominal_run_s": 60, "density_grid_replay_s": 600, "converged_start_in_years": 10}
    result["cpu_count"] = os.cpu_count()
    for k, v in list(result.items()):
        if isinstance(v, float):
            result[k] = round(v, 3)
    out_dir = REPO / "bench" / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "thesis.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
