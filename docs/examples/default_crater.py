"""The default crater from Python: run, replay against loose regolith and rock, read the headline numbers.

The case is ``cases/default.toml`` (a 2 km simple crater at 85 deg S), made smaller here so that the example
runs in seconds: 100 facets instead of 150, one lunation recorded (January 2019) after the periodic steady
state of the lunation before it. The run keeps the fluxes of every facet (direct and scattered sunlight,
infrared from the rest of the crater); the replay conducts the same fluxes into other density profiles.

Usage: ``python docs/examples/default_crater.py [OUT_DIR]`` (default: this folder). Writes
``OUT_DIR/default_crater.png`` and prints the numbers, one ``name: value unit`` per line.
"""

import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import crater_thermal as ct

REPO = Path(__file__).resolve().parents[2]
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent

# 1. The case: the file's keys, three of them changed (dotted names, as in the case file's tables).
case = ct.load_case(
    REPO / "cases" / "default.toml",
    {"crater.facets": 100, "period.end": "2019-01-30", "period.spinup_days": 29.53},
)

# 2. The coupled run (nominal regolith, 1300 kg m-3 in the top 2 cm over 1800 below): an xarray.Dataset.
run = ct.run(case)

# 3. The same fluxes conducted into nominal, loose (800/1100 kg m-3) and rock (3070 kg m-3).
replay = ct.replay(run, profiles=["1300/1800", "800/1100", "rock"])

# 4. The report's numbers without writing a report: night medians per crater region.
results = ct.analyse(run, replay)

T = replay["surface_temperature"]  # (profile, time, facet) [K]
lit = run["solar_direct"].values > 0.0  # (time, facet): in direct sunlight
floor = int(np.argmin(run["centroid"].values[:, 2]))  # the lowest facet
dT = (T.sel(profile="800/1100") - T.sel(profile="1300/1800")).values  # loose - nominal [K]
dT_unlit = np.nanmean(np.where(lit, np.nan, dT), axis=0)  # per facet, over its samples without sunlight

fig, (ax_t, ax_map) = plt.subplots(1, 2, figsize=(10, 4), width_ratios=(1.4, 1), layout="constrained")
for profile in T["profile"].values:
    ax_t.plot(T["time"].values, T.sel(profile=profile).values[:, floor], label=str(profile))
ax_t.set(ylabel="surface temperature [K]", title="lowest floor facet, January 2019")
ax_t.legend(title="profile [kg m-3]")
ax_t.tick_params(axis="x", labelrotation=30)

xy = run["mesh_vertices"].values[:, :2] / 1e3  # [km], x east, y north
faces = run["mesh_faces"].values
pc = ax_map.tripcolor(xy[:, 0], xy[:, 1], faces, facecolors=dT_unlit, cmap="viridis")
fig.colorbar(pc, ax=ax_map, label="loose - nominal [K]")
ax_map.set(aspect="equal", xlabel="x east [km]", ylabel="y north [km]", title="mean while not sunlit")
fig.savefig(OUT / "default_crater.png", dpi=100)

print(f"facets: {run.sizes['facet']}")
print(f"samples: {run.sizes['time']}")
print(f"night median nominal temperature, floor: {results.night_median_T_nominal_K['floor']:.2f} K")
print(f"night median loose - nominal, floor: {results.night_median_dT_K['floor']:.2f} K")
print(f"night median loose - nominal, often lit: {results.night_median_dT_K['often_lit']:.2f} K")
print(f"maximum temperature, rock: {float(T.sel(profile='rock').max()):.1f} K")
print(f"figure: {OUT / 'default_crater.png'}")
