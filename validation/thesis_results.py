"""The headline numbers of thesis section 7.2, from a thesis sweep (and optionally its faithful twin).

Usage::

    crater-thermal sweep cases/thesis/*.toml -o results/thesis
    crater-thermal sweep cases/thesis/faithful/*.toml -o results/thesis_faithful
    python validation/thesis_results.py results/thesis [results/thesis_faithful] [--albedo results/hayne]

For every crater latitude, medians over the recorded year, with **per-facet night** (issue 10: a sample
is night for a facet after 24 h without direct sunlight on it; ``regions.night_day_masks``) and the
regions of ``regions.region_masks`` (sectors by the azimuth the slope faces, +-45 deg):
the nominal floor temperature at night; loose - nominal at night on the floor, the equator-facing upper
wall (the wall on the pole side, facing the Sun), its top ring, and the often-lit facets; |loose - nominal|
while directly lit; |rock - nominal| on the floor at all times; and, for the thesis comparison, the floor
and the thesis-style "sunlit upper wall" (pole-side half of the wall's outer half in radius) with the
thesis's night (Sun below the crater centre's horizon). With the faithful sweep: the same after the
thesis's 3-year fixed spin-up. The flat-surface cases give night/day quartiles of loose - nominal.
With ``--albedo DIR`` (the same cases run with ``albedo_model = "hayne2017"``): what the incidence-dependent
albedo changes (nominal temperatures and loose - nominal, floor / walls / flat).
Writes validation/results/thesis_results.json and prints markdown tables.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import analysis, io, regions  # noqa: E402

WALL = "upper_wall_equator_facing"
TOP = "top_wall_ring_equator_facing"
WALL_POLE = "upper_wall_pole_facing"


def _region(masks: dict, name: str) -> np.ndarray | None:
    """A region mask; at the pole the Sun-named sector in the same place of regions.SECTORS."""
    if name in masks:
        return masks[name]
    for s, p in zip(regions.SECTORS, regions.POLAR_SECTORS_SOUTH):
        if name.endswith(s) and name.replace(s, p) in masks:
            return masks[name.replace(s, p)]
    return None


def _case_numbers(folder: Path) -> dict | None:
    run_nc, rep_nc = folder / "run.nc", folder / "replay.nc"
    if not (run_nc.exists() and rep_nc.exists()):
        return None
    run, rep = io.open_run(run_nc), io.open_replay(rep_nc)
    night, day = regions.night_day_masks(run, "facet")
    centre = regions.night_mask(run)
    masks = regions.region_masks(run)
    thesis_regions = regions.regions_of(run)
    T_nom = analysis.nominal_temperature(run, rep)
    loose = analysis.profile_temperature(rep, "800/1100") - T_nom
    rock = analysis.profile_temperature(rep, "rock") - T_nom if "rock" in list(rep["profile"].values) else None
    nf = T_nom.shape[1]
    out = {
        "lat_deg": float(run.attrs["lat_deg"]),
        "start_method": run.attrs.get("start_method", ""),
        "albedo_model": str(run.attrs.get("albedo_model", "constant")),
        "start_residual_max_K": float(np.nanmax(run["start_residual"].values)) if "start_residual" in run else None,
        "night_definition": "facet, 24 h without direct sunlight",
    }

    def med(a, smask, region):
        m = np.ones(nf, bool) if region is None else region
        return None if m is None else analysis.masked_median(a, smask, m)

    floor = masks.get("floor") if masks.get("floor") is not None and masks["floor"].any() else None
    wall, top, wall_pole = _region(masks, WALL), _region(masks, TOP), _region(masks, WALL_POLE)
    out["night_T_nominal_floor_K"] = med(T_nom, night, floor)
    out["night_T_nominal_upper_wall_equator_facing_K"] = med(T_nom, night, wall)
    out["mean_T_nominal_floor_K"] = None if floor is None else float(T_nom[:, floor].mean())
    out["mean_T_nominal_upper_wall_equator_facing_K"] = None if wall is None else float(T_nom[:, wall].mean())
    out["max_T_nominal_upper_wall_equator_facing_K"] = None if wall is None else float(T_nom[:, wall].max())
    out["night_dT_loose_floor_K"] = med(loose, night, floor)
    out["night_dT_loose_upper_wall_equator_facing_K"] = med(loose, night, wall)
    out["night_dT_loose_top_wall_ring_equator_facing_K"] = med(loose, night, top)
    out["night_dT_loose_upper_wall_pole_facing_K"] = med(loose, night, wall_pole)
    out["night_dT_loose_often_lit_K"] = med(loose, night, masks.get("often_lit"))
    out["night_fraction_upper_wall_equator_facing"] = None if wall is None else float(night[:, wall].mean())
    out["lit_fraction_upper_wall_equator_facing"] = None if wall is None else float(day[:, wall].mean())
    out["lit_abs_dT_loose_upper_wall_equator_facing_K"] = med(np.abs(loose), day, wall)
    out["facets"] = {k: int(v.sum()) for k, v in masks.items()}
    # thesis comparison: night at the crater centre, thesis-style regions
    sunlit_thesis = thesis_regions == "upper_wall_poleward"
    out["centre_night_T_nominal_floor_K"] = med(T_nom, centre, floor)
    out["centre_night_dT_loose_floor_K"] = med(loose, centre, floor)
    out["centre_night_dT_loose_upper_wall_sunlit_thesis_K"] = med(loose, centre, sunlit_thesis)
    out["centre_day_abs_dT_loose_floor_K"] = med(np.abs(loose), ~centre, floor)
    if rock is not None and floor is not None:
        out["all_abs_dT_rock_floor_K"] = float(np.median(np.abs(rock[:, floor])))
        out["fraction_time_rock_floor_above_20K"] = float(np.mean(np.abs(rock[:, floor]) > 20.0))
    every = np.ones(nf, bool)
    q = lambda a, m: [float(v) for v in np.percentile(a[:, every][m], [25, 50, 75])] if m.any() else None  # noqa: E731
    out["night_dT_loose_quartiles_K"] = q(loose, night)
    out["day_dT_loose_quartiles_K"] = q(loose, day)
    out["mean_T_nominal_K"] = float(T_nom.mean())
    out["night_T_nominal_median_K"] = med(T_nom, night, None)
    out["day_T_nominal_median_K"] = med(T_nom, day, None)
    run.close()
    rep.close()
    return out


def _collect(folder: Path, result: dict, crater_key: str, flat_key: str, suffix: str = "") -> None:
    for sub in sorted(folder.iterdir()):
        numbers = _case_numbers(sub) if sub.is_dir() else None
        if numbers is not None:
            key = flat_key if sub.name.startswith("flat") else crater_key
            result[key][sub.name.replace(suffix, "")] = numbers


def main() -> None:
    args = sys.argv[1:]
    albedo_dir = None
    if "--albedo" in args:
        i = args.index("--albedo")
        albedo_dir = Path(args[i + 1])
        del args[i : i + 2]
    if not args:
        sys.exit(__doc__)
    conv_dir = Path(args[0])
    faith_dir = Path(args[1]) if len(args) > 1 else None
    result = {"converged": {}, "faithful": {}, "flat": {}, "hayne2017": {}, "hayne2017_flat": {}}
    _collect(conv_dir, result, "converged", "flat")
    if faith_dir is not None and faith_dir.exists():
        _collect(faith_dir, result, "faithful", "faithful", "_faithful")
    # keep earlier numbers of cases not re-run here (the faithful sweep, flat latitudes), marked as such
    # (they may use the crater-centre night of the thesis: see their keys)
    old = REPO / "validation" / "results" / "thesis_results.json"
    previous = json.loads(old.read_text()) if old.exists() else {}
    for key in ("faithful", "flat"):
        for name, c in previous.get(key, {}).items():
            if name not in result[key]:
                result[key][name] = dict(c, carried_over="from an earlier run of this script")
    if albedo_dir is not None and albedo_dir.exists():
        _collect(albedo_dir, result, "hayne2017", "hayne2017_flat")
    out = REPO / "validation" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "thesis_results.json").write_text(json.dumps(result, indent=2) + "\n")

    f = lambda v, n=2: "—" if v is None else f"{v:.{n}f}"  # noqa: E731
    print(
        "| lat | night floor T, nominal [K] | night loose − nominal: floor / equator-facing upper wall / its top "
        "ring / often lit [K] | lit \\|loose − nominal\\|, equator-facing upper wall [K] "
        "| \\|rock − nominal\\| floor [K] "
        '| thesis night (crater centre): floor T, floor ΔT / thesis "sunlit upper wall" ΔT [K] '
        "| 3-yr spin-up: floor T, floor ΔT [K] |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, c in result["converged"].items():
        fa = result["faithful"].get(name)
        faith = f"{f(fa['night_T_nominal_floor_K'], 1)}, {f(fa['night_dT_loose_floor_K'])}" if fa else "—"
        print(
            f"| {c['lat_deg']:g}° | {f(c['night_T_nominal_floor_K'], 1)} | {f(c['night_dT_loose_floor_K'])} / "
            f"{f(c['night_dT_loose_upper_wall_equator_facing_K'])} / "
            f"{f(c['night_dT_loose_top_wall_ring_equator_facing_K'])} / {f(c['night_dT_loose_often_lit_K'])} | "
            f"{f(c['lit_abs_dT_loose_upper_wall_equator_facing_K'])} | {f(c.get('all_abs_dT_rock_floor_K'), 1)} | "
            f"{f(c['centre_night_T_nominal_floor_K'], 1)}, {f(c['centre_night_dT_loose_floor_K'])} / "
            f"{f(c['centre_night_dT_loose_upper_wall_sunlit_thesis_K'])}"
            f" | {faith} |"
        )
    print()
    print("| flat lat | night loose−nominal Q1 / median / Q3 [K] | lit loose−nominal Q1 / median / Q3 [K] |")
    print("|---|---|---|")
    fmt = lambda qs: "—" if qs is None else " / ".join(f(v) for v in qs)  # noqa: E731
    for c in result["flat"].values():
        print(f"| {c['lat_deg']:g}° | {fmt(c['night_dT_loose_quartiles_K'])} | {fmt(c['day_dT_loose_quartiles_K'])} |")
    if result["hayne2017"] or result["hayne2017_flat"]:
        print()
        print(
            "| case | mean T nominal, constant → hayne2017 [K] | night floor T [K] | equator-facing upper wall: "
            "mean T / max T [K] | night loose − nominal floor [K] | night loose − nominal eq.-facing upper wall [K] |"
        )
        print("|---|---|---|---|---|---|")
        pairs = [(k, result["converged"].get(k), v) for k, v in result["hayne2017"].items()]
        pairs += [(k, result["flat"].get(k), v) for k, v in result["hayne2017_flat"].items()]
        for name, c, h in pairs:
            if c is None:
                continue
            arrow = lambda key, n=2, c=c, h=h: f"{f(c.get(key), n)} → {f(h.get(key), n)}"  # noqa: E731
            print(
                f"| {name} | {arrow('mean_T_nominal_K', 1)} | {arrow('night_T_nominal_floor_K', 1)} | "
                f"{arrow('mean_T_nominal_upper_wall_equator_facing_K', 1)} / "
                f"{arrow('max_T_nominal_upper_wall_equator_facing_K', 1)} | {arrow('night_dT_loose_floor_K')} | "
                f"{arrow('night_dT_loose_upper_wall_equator_facing_K')} |"
            )
        for name, c, h in pairs:
            if c is not None and name.startswith("flat"):
                print(
                    f"| {name} night/day median T [K] | {f(c['night_T_nominal_median_K'], 1)} → "
                    f"{f(h['night_T_nominal_median_K'], 1)} / {f(c['day_T_nominal_median_K'], 1)} → "
                    f"{f(h['day_T_nominal_median_K'], 1)}; night ΔT quartiles "
                    f"{fmt(c['night_dT_loose_quartiles_K'])} → {fmt(h['night_dT_loose_quartiles_K'])} |"
                )


if __name__ == "__main__":
    main()
