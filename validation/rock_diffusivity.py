"""The rock column of the thesis table in docs/results.md before and after the rock-diffusivity reading of issue 12.

Usage::

    python validation/rock_diffusivity.py RUN.nc

Replays the nominal 1300/1800 profile and rock on RUN.nc's saved fluxes (a thesis crater run, e.g. the
one validation/geothermal_floor.py writes for 86 S) with the adopted rock diffusivity
(materials.ROCK_D1 = 4.0e-6 m2 K s-1) and with the earlier 4.0e-5, and prints the median over the
recorded year of |rock - nominal| on the floor (the docs/results.md table's column, as in
validation/thesis_results.py). Writes validation/results/rock_diffusivity.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import io, materials, regions, simulate, thermal  # noqa: E402

OLD_D1 = 4.0e-5  # [m2 K s-1] rock diffusivity's 1/T coefficient before issue 12


def _shown(path: Path) -> str:
    """``path`` relative to the repository when inside it (for the committed JSON)."""
    p = path.resolve()
    return str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p)


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    run_nc = Path(sys.argv[1])
    ds = io.read_flux_dataset(run_nc)
    run = io.open_run(run_nc)
    floor = regions.regions_of(run) == "floor"
    nominal, rock = thermal.parse_profile("1300/1800"), thermal.parse_profile("rock")
    out = {"run": _shown(run_nc), "lat_deg": float(run.attrs["lat_deg"]), "floor_abs_rock_minus_nominal_median_K": {}}
    adopted = materials.ROCK_D1
    for d1 in (adopted, OLD_D1):
        materials.ROCK_D1 = d1  # read when the solver builds its coefficients
        try:
            T, _ = simulate.replay_fluxes(ds, [nominal, rock], progress=False)
        finally:
            materials.ROCK_D1 = adopted
        out["floor_abs_rock_minus_nominal_median_K"][f"{d1:g}"] = float(np.median(np.abs(T[1] - T[0])[:, floor]))
    dest = REPO / "validation" / "results" / "rock_diffusivity.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
