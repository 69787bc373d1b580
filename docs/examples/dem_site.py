"""A real site: Shoemaker crater on LOLA topography, meshed from a DEM and run for one lunation.

The DEM is ``tests/data/lola_south_pole_2560m.grd`` (a 73 x 73 GMT netCDF grid at 2.56 km of the
lunar south pole, derived from LOLA; see ``tests/data/README.md``). The file says nothing about
itself: its x/y and heights are in km, it has no coordinate reference system, and its heights already
have the Moon's curvature applied (z in a frame tangent at the pole). The overrides say so: the Moon's
south polar stereographic CRS (``IAU_2015:30135``), km for x/y and z, ``height_kind="tangent"``.

Shoemaker (88.1 deg S, 44.9 deg E, 51 km across) has a permanently shadowed floor. The site is the disk
of 35 km radius about its centre, meshed with 5 km facets (about 340 facets: coarse, and fast).

Usage: ``python docs/examples/dem_site.py [OUT_DIR]`` (default: this folder). Writes
``OUT_DIR/dem_site.png`` and prints the numbers, one ``name: value unit`` per line.
"""

import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import crater_thermal as ct

REPO = Path(__file__).resolve().parents[2]
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent
DEM = REPO / "tests" / "data" / "lola_south_pole_2560m.grd"

# What the file does not say about itself, and the site: the same keys for the mesh and the case.
overrides = {"crs": "IAU_2015:30135", "xy_units": "km", "z_units": "km", "height_kind": "tangent"}
lat_deg, lon_deg, radius_km, resolution_m = -88.1, 44.9, 35.0, 5000.0

# 1. The mesh alone: vertices [m] in the centre's east/north/up frame, the Moon's curvature included.
mesh = ct.mesh_dem(DEM, lat_deg, lon_deg, radius_km, resolution_m=resolution_m, **overrides)

# 2. A case on the same site (the run meshes the DEM again, identically), one lunation after the
#    periodic steady state of the lunation before it.
case = ct.case_from_dict(
    {
        "crater": {"kind": "dem", "dem": str(DEM), "radius_km": radius_km, "resolution_m": resolution_m, **overrides},
        "location": {"lat_deg": lat_deg, "lon_deg": lon_deg},
        "period": {"start": "2019-01-01", "end": "2019-01-30", "spinup": "periodic", "spinup_days": 29.53},
        "steps": {"flux_step_hours": 4.0},
    },
    name="shoemaker",
)
run = ct.run(case)

c = run["centroid"].values  # (facet, 3) [m]
T = run["surface_temperature"].values  # (time, facet) [K]
direct = run["solar_direct"].values  # (time, facet) [W m-2]
floor = np.hypot(c[:, 0], c[:, 1]) < 10e3  # within 10 km of the centre: Shoemaker's floor

xy = mesh.vertices[:, :2] / 1e3  # [km]
fig, (ax_h, ax_t) = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
pc = ax_h.tripcolor(xy[:, 0], xy[:, 1], mesh.faces, facecolors=mesh.centroids[:, 2] / 1e3, cmap="terrain")
fig.colorbar(pc, ax=ax_h, label="height above the centre's tangent plane [km]")
ax_h.set(title=f"Shoemaker site, {mesh.n_facets} facets", xlabel="x east [km]", ylabel="y north [km]")
pc = ax_t.tripcolor(xy[:, 0], xy[:, 1], mesh.faces, facecolors=T.max(axis=0), cmap="inferno")
fig.colorbar(pc, ax=ax_t, label="maximum surface temperature, January 2019 [K]")
ax_t.set(title="nominal regolith", xlabel="x east [km]")
for ax in (ax_h, ax_t):
    ax.set_aspect("equal")
    ax.add_patch(plt.Circle((0, 0), 10, fill=False, color="w", ls="--", lw=1))
fig.savefig(OUT / "dem_site.png", dpi=100)

print(f"facets: {mesh.n_facets}")
print(f"relief: {np.ptp(mesh.vertices[:, 2]) / 1e3:.2f} km")
print(f"floor facets: {int(floor.sum())}")
print(f"maximum direct sunlight on the floor: {direct[:, floor].max():.1f} W m-2")
print(f"mean floor temperature: {T[:, floor].mean():.1f} K")
print(f"warmest facet: {T.max():.1f} K")
print(f"figure: {OUT / 'dem_site.png'}")
