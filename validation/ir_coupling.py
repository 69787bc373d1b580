"""How large is the thesis's replay approximation (off-nominal facets see the nominal crater's IR)?

Statistics are over facets inside the rim crest at night (Sun centre below the crater centre's
horizon). Runs one case twice, fully coupled: once with the nominal profile everywhere and once with the loose
profile everywhere (the loose crater's own, colder IR). Then replays the loose profile against the
nominal run's saved fluxes (the thesis approximation: a loose patch inside a nominal crater). The
difference between the replayed and the fully coupled loose temperatures bounds the approximation:
a single loose patch sits between the two (its surroundings stay nominal).

Usage: python validation/ir_coupling.py [CASE.toml]  (default: cases/default.toml)
Writes validation/results/ir_coupling.json and prints it.
"""

from __future__ import annotations

import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import (  # noqa: E402
    config,
    io,
    runner,  # noqa: E402
    simulate,
)


def main() -> None:
    case_path = Path(sys.argv[1]) if len(sys.argv) > 1 else REPO / "cases" / "default.toml"
    warnings.simplefilter("ignore")  # density extrapolation warnings for 800/1100 are expected
    nominal = config.load_case(case_path)
    loose = nominal.with_overrides({"surface.nominal_profile": "800/1100"}, name=nominal.name + "_loose")
    with tempfile.TemporaryDirectory() as tmp:
        run_nom = io.open_run(runner.run_case(nominal, Path(tmp) / "nom.nc", progress=False))
        run_loose = io.open_run(runner.run_case(loose, Path(tmp) / "loose.nc", progress=False))
    T_replay, _ = simulate.replay_fluxes(run_nom, runner.resolve_profiles(["1300/1800", "800/1100"]), progress=False)
    night = run_nom["sun_direction"].values[:, 2] < 0
    # inside the rim crest only: the outer flank sees little of the crater, so its IR hardly matters
    meta = json.loads(run_nom.attrs["mesh_meta"])
    c = run_nom["centroid"].values
    inside = np.hypot(c[:, 0], c[:, 1]) < meta["rim_radius_m"]
    night = night[:, None] & inside[None, :]
    coupled = run_loose["surface_temperature"].values
    d_replay = T_replay[1] - T_replay[0]  # loose - nominal, thesis approximation
    d_coupled = coupled - run_nom["surface_temperature"].values  # loose crater - nominal crater
    err = T_replay[1] - coupled
    ir_drop = run_nom["ir_incident"].values - run_loose["ir_incident"].values
    out = {
        "case": str(case_path.relative_to(REPO)) if case_path.is_relative_to(REPO) else str(case_path),
        "night_median_dT_replay_K": float(np.median(d_replay[night])),
        "night_median_dT_fully_coupled_K": float(np.median(d_coupled[night])),
        "night_median_replay_minus_coupled_K": float(np.median(err[night])),
        "night_max_abs_replay_minus_coupled_K": float(np.max(np.abs(err[night]))),
        "night_median_ir_drop_W_m2": float(np.median(ir_drop[night])),
        "night_median_ir_nominal_W_m2": float(np.median(run_nom["ir_incident"].values[night])),
        "facets_inside_rim": int(inside.sum()),
    }
    res = REPO / "validation" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "ir_coupling.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
