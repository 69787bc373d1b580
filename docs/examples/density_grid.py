"""A density-grid replay: how the night-time floor temperature depends on the densities of both layers.

One coupled run of a small crater (the default case, 60 facets, one lunation) saves its fluxes; the replay
conducts them into every two-layer profile of a density grid: the top 2 cm and the rest of the 2 m column
each from 800 to 2000 kg m-3 in steps of 300, top never denser than bottom (15 profiles). This is the
thesis's Fig. 7.7a: each cell is the night-time median, over the floor, of the profile's surface
temperature minus the nominal (1300/1800 kg m-3) one.

Usage: ``python docs/examples/density_grid.py [OUT_DIR]`` (default: this folder). Writes
``OUT_DIR/density_grid.png`` and prints the numbers, one ``name: value unit`` per line.
"""

import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import crater_thermal as ct

REPO = Path(__file__).resolve().parents[2]
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent

case = ct.load_case(
    REPO / "cases" / "default.toml",
    {"crater.facets": 60, "period.end": "2019-01-30", "period.spinup_days": 29.53},
)
run = ct.run(case)

# Every profile TOP/BOTTOM [kg m-3] of the grid START:STOP:STEP with TOP <= BOTTOM, each from its own
# periodic steady state, under the nominal run's fluxes (the IR of the crater stays the nominal one).
grid = ct.replay(run, density_grid="800:2000:300")
results = ct.analyse(run, grid)

table = results.summary["density_grid_floor_night_median_dT_K"]
top = np.array(table["rho_top_kg_m3"])
bottom = np.array(table["rho_bottom_kg_m3"])
dT = np.array([[np.nan if v is None else v for v in row] for row in table["dT_K"]])  # [top, bottom] [K]

fig, ax = plt.subplots(figsize=(6, 4.8), layout="constrained")
step = 300.0
edges = lambda rho: np.append(rho - step / 2, rho[-1] + step / 2)  # noqa: E731
lim = np.nanmax(np.abs(dT))
pc = ax.pcolormesh(edges(bottom), edges(top), dT, cmap="RdBu_r", vmin=-lim, vmax=lim)
fig.colorbar(pc, ax=ax, label="night median on the floor, profile - nominal [K]")
for i, j in zip(*np.nonzero(np.isfinite(dT))):
    colour = "w" if abs(dT[i, j]) > 0.6 * lim else "k"
    ax.text(bottom[j], top[i], f"{dT[i, j]:+.1f}", ha="center", va="center", fontsize=8, color=colour)
ax.plot(1800, 1300, "k*", ms=12, label="nominal 1300/1800")
ax.set(
    xlabel="bottom layer density [kg m-3]",
    ylabel="top 2 cm density [kg m-3]",
    title=f"{grid.sizes['profile']} profiles",
)
ax.legend(loc="upper left")
fig.savefig(OUT / "density_grid.png", dpi=100)

i_loose, j_loose = int(np.argmin(np.abs(top - 800))), int(np.argmin(np.abs(bottom - 1100)))
print(f"profiles: {grid.sizes['profile']}")
print(f"loosest 800/800: {dT[0, 0]:.2f} K")
print(f"loose 800/1100: {dT[i_loose, j_loose]:.2f} K")
print(f"densest 2000/2000: {dT[-1, -1]:.2f} K")
print(f"bottom 800 -> 2000 under an 800 top: {dT[0, -1] - dT[0, 0]:.2f} K")
print(f"top 800 -> 2000 over a 2000 bottom: {dT[-1, -1] - dT[0, -1]:.2f} K")
print(f"figure: {OUT / 'density_grid.png'}")
