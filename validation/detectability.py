"""The detectability answer for one scene: every instrument preset, with the sensitivity to the assumptions.

Usage::

    python validation/detectability.py [T_NOMINAL_K DT_K]

Defaults: the -86 deg crater floor of the results table in docs/results.md (night-time median nominal 58.1 K,
loose - nominal -2.77 K). For every preset (crater_thermal.instrument.PRESETS): band radiance and NETD at
the scene, the observed difference, the dwell for P_D >= 0.9 at 1% false alarms (one-sided) or "not
detectable at any dwell" with the limiting term, and the same with the natural scatter halved, with 10
reference footprints, and with both. Writes validation/results/detectability.json, prints a markdown table.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal import instrument as ins  # noqa: E402


def _dwell(res: dict) -> str:
    if res["detectable"]:
        return f"{res['dwell_s']:.3g} s"
    return f"never (P_D -> {res['pd_limit']:.2f}, {res['limiting_term'].replace('_', ' ')})"


def main(T_nom: float = 58.1, dT: float = -2.77) -> dict:
    variants = {
        "default": ins.Observation(),
        "scatter_0.47K": ins.Observation(natural_scatter_K=0.47),
        "m10": ins.Observation(reference_footprints=10),
        "scatter_0.47K_m10": ins.Observation(natural_scatter_K=0.47, reference_footprints=10),
        "no_scatter": ins.Observation(natural_scatter_K=0.0),
    }
    out = {
        "T_nominal_K": T_nom,
        "dT_K": dT,
        "observations": {k: v.as_dict() for k, v in variants.items()},
        "instruments": {},
    }
    rows = []
    for name, inst in ins.PRESETS.items():
        res = {k: ins.dwell_for_detection(dT, T_nom, inst, o) for k, o in variants.items()}
        band = ins.band_table([T_nom, 300.0], [inst])[name]
        out["instruments"][name] = {"instrument": inst.as_dict(), "band": band, "results": res}
        rows.append(
            f"| {name} | {inst.lo_um:g}-{inst.hi_um:g} | {band['band_radiance_W_m2_sr'][0]:.3g} | "
            f"{band['netd_K'][0]:.3g} | " + " | ".join(_dwell(res[k]) for k in variants) + " |"
        )
    (REPO / "validation" / "results").mkdir(exist_ok=True)
    (REPO / "validation" / "results" / "detectability.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"Scene: nominal {T_nom:g} K, loose - nominal {dT:g} K; P_D >= 0.9 at 1% false alarms, one-sided.\n")
    print(
        "| instrument | band [um] | band radiance at scene [W m-2 sr-1] | NETD at scene [K] | "
        "0.94 K scatter, 1 reference | 0.47 K, 1 ref. | 0.94 K, 10 ref. | 0.47 K, 10 ref. | no scatter |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return out


if __name__ == "__main__":
    args = [float(a) for a in sys.argv[1:3]]
    main(*args)
