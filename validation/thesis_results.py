"""The headline numbers of thesis section 7.2, from a thesis sweep (and optionally its faithful twin).

Usage::

    crater-thermal sweep cases/thesis/*.toml -o results/thesis
    crater-thermal sweep cases/thesis/faithful/*.toml -o results/thesis_faithful
    python validation/thesis_results.py results/thesis [results/thesis_faithful]

For every crater latitude: night-time (Sun centre below the crater centre's horizon) medians over the
recorded year of the nominal floor temperature, loose - nominal on the floor and on the sunlit
(pole-side, equator-facing) upper wall, rock - nominal on the floor; daytime medians of |loose - nominal|;
and, with the faithful sweep, the same numbers after the thesis's 3-year fixed spin-up. The flat-surface
sweep (Fig. 7.9) gives night/day quartiles of loose - nominal per latitude.
Writes validation/results/thesis_results.json and prints a markdown table.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import analysis, io  # noqa: E402


def _case_numbers(folder: Path) -> dict | None:
    run_nc, rep_nc = folder / "run.nc", folder / "replay.nc"
    if not (run_nc.exists() and rep_nc.exists()):
        return None
    run, rep = io.open_run(run_nc), io.open_replay(rep_nc)
    night = analysis.night_mask(run)
    day = ~night
    regions = analysis.regions_of(run)
    T_nom = analysis.nominal_temperature(run, rep)
    loose = analysis.profile_temperature(rep, "800/1100") - T_nom
    rock = analysis.profile_temperature(rep, "rock") - T_nom if "rock" in list(rep["profile"].values) else None
    out = {"lat_deg": float(run.attrs["lat_deg"]), "start_method": run.attrs.get("start_method", ""),
           "start_residual_max_K": float(np.nanmax(run["start_residual"].values)) if "start_residual" in run else None}

    def med(a, tmask, region=None):
        sel = np.ones(a.shape[1], bool) if region is None else np.isin(regions, region)
        if not sel.any() or not tmask.any():
            return None
        return float(np.median(a[tmask][:, sel]))

    floor = ["floor"] if np.any(regions == "floor") else None
    out["night_T_nominal_floor_K"] = med(T_nom, night, floor)
    out["night_dT_loose_floor_K"] = med(loose, night, floor)
    out["night_dT_loose_upper_wall_sunlit_K"] = med(loose, night, ["upper_wall_poleward"])
    out["night_dT_loose_upper_wall_shaded_K"] = med(loose, night, ["upper_wall_equatorward"])
    out["day_abs_dT_loose_floor_K"] = med(np.abs(loose), day, floor)
    out["day_abs_dT_loose_upper_wall_sunlit_K"] = med(np.abs(loose), day, ["upper_wall_poleward"])
    if rock is not None:
        out["all_abs_dT_rock_floor_K"] = med(np.abs(rock), np.ones_like(night), floor)
        out["fraction_time_rock_floor_above_20K"] = (
            float(np.mean(np.abs(rock[:, np.isin(regions, floor or [])]) > 20.0)) if floor else None)
    q = lambda a, m: [float(v) for v in np.percentile(a[m].ravel(), [25, 50, 75])] if m.any() else None  # noqa: E731
    out["night_dT_loose_quartiles_K"] = q(loose, night)
    out["day_dT_loose_quartiles_K"] = q(loose, day)
    return out


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    conv_dir = Path(sys.argv[1])
    faith_dir = Path(sys.argv[2]) if len(sys.argv) > 2 else None
    result = {"converged": {}, "faithful": {}, "flat": {}}
    for folder in sorted(conv_dir.iterdir()):
        numbers = _case_numbers(folder)
        if numbers is None:
            continue
        key = "flat" if folder.name.startswith("flat") else "converged"
        result[key][folder.name] = numbers
    if faith_dir is not None and faith_dir.exists():
        for folder in sorted(faith_dir.iterdir()):
            numbers = _case_numbers(folder)
            if numbers is not None:
                result["faithful"][folder.name.replace("_faithful", "")] = numbers
    out = REPO / "validation" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "thesis_results.json").write_text(json.dumps(result, indent=2) + "\n")

    f = lambda v, n=2: "—" if v is None else f"{v:.{n}f}"  # noqa: E731
    print("| lat | night floor T nominal [K] | night loose−nominal floor [K] "
          "| night loose−nominal sunlit upper wall [K] | day \\|loose−nominal\\| floor / wall [K] "
          "| \\|rock−nominal\\| floor [K] | 3-yr spin-up: floor T, floor ΔT [K] |")
    print("|---|---|---|---|---|---|---|")
    for name, c in result["converged"].items():
        fa = result["faithful"].get(name)
        faith = f"{f(fa['night_T_nominal_floor_K'], 1)}, {f(fa['night_dT_loose_floor_K'])}" if fa else "—"
        print(f"| {c['lat_deg']:g}° | {f(c['night_T_nominal_floor_K'], 1)} | {f(c['night_dT_loose_floor_K'])} | "
              f"{f(c['night_dT_loose_upper_wall_sunlit_K'])} | {f(c['day_abs_dT_loose_floor_K'])} / "
              f"{f(c['day_abs_dT_loose_upper_wall_sunlit_K'])} | {f(c.get('all_abs_dT_rock_floor_K'), 1)} | {faith} |")
    print()
    print("| flat lat | night loose−nominal Q1 / median / Q3 [K] | day loose−nominal Q1 / median / Q3 [K] |")
    print("|---|---|---|")
    for c in result["flat"].values():
        n, d = c["night_dT_loose_quartiles_K"], c["day_dT_loose_quartiles_K"]
        fmt = lambda qs: "—" if qs is None else " / ".join(f(v) for v in qs)  # noqa: E731
        print(f"| {c['lat_deg']:g}° | {fmt(n)} | {fmt(d)} |")


if __name__ == "__main__":
    main()
