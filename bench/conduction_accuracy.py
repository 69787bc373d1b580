"""Accuracy of the conduction defaults against a fine reference (the numbers quoted in
crater_thermal/thermal.py's docstring).

Half a year of synthetic 4-hour forcing (crater_thermal.reference.synthetic_absorbed_flux: 'floor' = no sun, IR of
0.3-16 W/m2 from lit walls; 'wall' = 500 W/m2 lunar-day pulses), nominal / loose / rock columns,
each started from its equilibrium estimate. Reference: dt = 450 s, first layer / 4, growth 1.03.
Reports the max |T - T_ref| of the surface over the last quarter year in settled nights (Sun, or
the walls' IR, down >= 1 day) and in the first day after sunset, for several configurations.

Prints one JSON object as the last stdout line and writes bench/results/conduction_accuracy.json.
Usage: PYTHONPATH=. python bench/conduction_accuracy.py   (~1 min on 2 cores)
"""

import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from crater_thermal import materials, thermal  # noqa: E402
from crater_thermal.constants import LUNAR_DAY, YEAR  # noqa: E402
from crater_thermal.reference import synthetic_absorbed_flux as forcing  # noqa: E402

KINDS = ["floor", "wall"] * 3
PROFS = ["1300/1800"] * 2 + ["800/1100"] * 2 + ["rock"] * 2


def run(first_layer_m, dt, growth, scheme, t, Q):
    g = thermal.make_grid(first_layer_m=first_layer_m, growth=growth)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", materials.DensityExtrapolationWarning)
        s = thermal.ColumnSolver(PROFS, grid=g, dt_max=dt, scheme=scheme)
    s.set_equilibrium(Q)
    return g.nz, s.run_series(t, Q)


def main():
    t = np.arange(0.0, 0.5 * YEAR, 14_400.0)
    Q = np.column_stack([forcing(k, t) for k in KINDS])
    f0 = thermal.make_grid().first_layer_m
    _, ref = run(f0 / 4, 450.0, 1.03, "trbdf2", t, Q)
    ph = (t % LUNAR_DAY) / LUNAR_DAY  # sunset at 0.25, sunrise at 0.75
    late = t > 0.25 * YEAR
    settled = (ph > 0.25 + 1 / 29.5) & (ph < 0.75) & late
    first_day = (ph > 0.25) & (ph <= 0.25 + 1 / 29.5) & late
    rows = []
    for frac, dt, growth, scheme in [
        (1, 14400.0, thermal.DEFAULT_GROWTH, "trbdf2"),
        (0.5, 7200.0, thermal.DEFAULT_GROWTH, "trbdf2"),
        (1, 14400.0, 1.2, "trbdf2"),
        (1, 14400.0, 1.1, "trbdf2"),
        (1, 14400.0, thermal.DEFAULT_GROWTH, "euler"),
        (1, 3600.0, thermal.DEFAULT_GROWTH, "euler"),
    ]:
        nz, T = run(f0 * frac, dt, growth, scheme, t, Q)
        err = np.abs(T - ref)
        rows.append(
            {
                "first_layer_m": f0 * frac,
                "dt_s": dt,
                "growth": growth,
                "scheme": scheme,
                "nz": nz,
                "columns": [f"{p} {k}" for p, k in zip(PROFS, KINDS)],
                "settled_night_max_err_K": [round(float(err[settled, j].max()), 4) for j in range(6)],
                "first_day_after_sunset_max_err_K": [round(float(err[first_day, j].max()), 4) for j in range(6)],
            }
        )
        print(rows[-1])
    result = {"reference": {"dt_s": 450.0, "first_layer_m": f0 / 4, "growth": 1.03}, "runs": rows}
    out = ROOT / "bench" / "results" / "conduction_accuracy.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
