"""How much does the geothermal flux set the night-time floor temperature? (docs/results.md, issue 12)

Usage::

    python validation/geothermal_floor.py [RUN.nc]

Without RUN.nc it first runs ``cases/thesis/crater_lat86S.toml`` (10 km crater, 86 S, 2019 recorded,
converged start) into results/geothermal_floor/run.nc. It then replays the nominal 1300/1800 profile on
that run's saved fluxes with the thesis's 0.033 W m-2 and with 0.018 W m-2 (Hayne et al. 2017's value;
modern estimates are 0.014-0.021) and prints the night-time
(Sun centre below the crater centre's horizon) median floor temperature of each, and the floor's median
night-time absorbed infrared from the walls, eps * ir_incident [W m-2], for comparison with the
geothermal flux, and the year-mean flux the floor absorbs. Writes validation/results/geothermal_floor.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import (  # noqa: E402
    config,
    io,
    regions,
    runner,  # noqa: E402
    simulate,
    thermal,
)

FLUXES_W_M2 = (0.033, 0.018)


def _shown(path: Path) -> str:
    """``path`` relative to the repository when inside it (for the committed JSON)."""
    p = path.resolve()
    return str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p)


def main() -> None:
    if len(sys.argv) > 1:
        run_nc = Path(sys.argv[1])
    else:
        run_nc = REPO / "results" / "geothermal_floor" / "run.nc"
        if not run_nc.exists():
            case = config.load_case(REPO / "cases" / "thesis" / "crater_lat86S.toml")
            runner.run_case(case, run_nc, progress=False)
    ds = io.read_flux_dataset(run_nc)
    run = io.open_run(run_nc)
    night = regions.night_mask(run)
    floor = regions.regions_of(run) == "floor"
    eps = float(ds.attrs["emissivity"])
    out = {
        "run": _shown(run_nc),
        "lat_deg": float(run.attrs["lat_deg"]),
        "night_floor_absorbed_ir_median_W_m2": float(np.median(eps * ds["ir_incident"].values[night][:, floor])),
        # year mean of what the floor absorbs: sunlight (direct and scattered) and the walls' IR
        "floor_absorbed_year_mean_W_m2": float(
            np.mean(
                ((1 - float(ds.attrs["albedo"])) * ds["solar_incident"].values + eps * ds["ir_incident"].values)[
                    :, floor
                ]
            )
        ),
        "night_floor_T_median_K": {},
    }
    nominal = thermal.parse_profile("1300/1800")
    for q in FLUXES_W_M2:
        T, _ = simulate.replay_fluxes(ds, [nominal], geothermal_flux=q, progress=False)
        out["night_floor_T_median_K"][f"{q:g}"] = float(np.median(T[0][night][:, floor]))
    T = out["night_floor_T_median_K"]
    out["difference_K"] = T[f"{FLUXES_W_M2[0]:g}"] - T[f"{FLUXES_W_M2[1]:g}"]
    dest = REPO / "validation" / "results" / "geothermal_floor.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
