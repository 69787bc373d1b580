"""Inversion: from a night traverse's brightness temperatures back to the regolith density, with uncertainty.

The thesis's 86 S crater (10 km, cases/thesis/crater_lat86S.toml), coarse and short to run in seconds: 150
facets, one lunation (its periodic steady state), and a density grid of 800:2000:200 kg m-3 (28 profiles,
the thesis's is 800:2000:100). A loose patch (800/1100 kg m-3) lies on the floor; the rest is nominal
(1300/1800). Neither profile is a node of the grid: their temperatures come from their own replay, the
inversion interpolates the grid.

A rover carrying a radiometer with Diviner channel 7's band and noise crosses the floor three times in one
night (early, middle, late), staring 10 s at each footprint. The noise is drawn from the stated noise model
(white noise of the dwell and the 1/f floor per sample, the footprint's natural scatter and calibration
gain shared by its samples). ``ct.invert`` gives each footprint's posterior and P(loose) = P(bottom <
1500 kg m-3); ``ct.observation_design`` the expected posterior width versus time of night and dwell, for
Diviner ch7 and for the thesis's rover camera (the ``microbolometer`` preset, 7.5-14 um).

Usage: ``python docs/examples/inversion.py [OUT_DIR]`` (default: this folder). Writes
``OUT_DIR/inversion.png``, and run.nc, grid.nc, traverse.csv, posterior.nc in a new temporary folder; prints
the numbers, one ``name: value unit`` per line.
"""

import sys
import tempfile
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.tri import Triangulation

import crater_thermal as ct
from crater_thermal.instrument import band_brightness_temperature, band_radiance, get_instrument

warnings.simplefilter("ignore")  # 800 kg m-3 is outside Table 7.2: conductivity extrapolated (as the thesis)
REPO = Path(__file__).resolve().parents[2]
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent
DATA = Path(tempfile.mkdtemp(prefix="inversion_"))  # run.nc, grid.nc, traverse.csv, posterior.nc
rng = np.random.default_rng(1)

case = ct.load_case(
    REPO / "cases" / "thesis" / "crater_lat86S.toml",
    {"crater.facets": 150, "period.end": "2019-01-31", "period.spinup_years": 29.53 / 365.25},
)
run = ct.run(case, DATA / "run.nc", overwrite=True)
grid = ct.replay(run, density_grid="800:2000:200", out=DATA / "grid.nc", overwrite=True)
truth = ct.replay(run, profiles=["1300/1800", "800/1100"])  # nominal, loose: the truth's own replay

# --- the site: a loose patch on the floor, a traverse across it --------------------------------------
xyz = run["centroid"].values  # [m], crater-centred
r = np.hypot(xyz[:, 0], xyz[:, 1])
floor = r < 0.3 * 10_000.0
loose = floor & (np.hypot(xyz[:, 0] - 1000.0, xyz[:, 1]) < 1200.0)
path = np.flatnonzero(floor & (np.abs(xyz[:, 1]) < 1500.0))
path = path[np.argsort(xyz[path, 0])]
sun = run["solar_incident"].values  # (time, facet) [W m-2]
night = np.flatnonzero((sun[:, path] == 0).all(axis=1))  # samples dark on the whole traverse
crossings = night[np.linspace(0, night.size - 1, 5).round().astype(int)[1:4]]  # early, middle, late

# --- the measurements: truth + the stated noise, drawn in band radiance ------------------------------
inst = get_instrument("diviner_ch7")
dwell = 10.0
T_true = truth["surface_temperature"].values[
    np.where(loose, 1, 0)[None, :], np.arange(sun.shape[0])[:, None], np.arange(sun.shape[1])[None, :]
]
rows = []
for f in path:
    z, g = 0.94 * rng.standard_normal(), inst.gain_error * rng.standard_normal()  # shared by the footprint
    for k in crossings:
        n = int(dwell // inst.integration_s)
        white = inst.noise_equivalent_radiance() * (
            rng.standard_normal() / np.sqrt(n) + np.sqrt(inst.integration_s / inst.knee_s) * rng.standard_normal()
        )
        L = (1 + g) * band_radiance(T_true[k, f] + z, inst.band) + white
        t = np.datetime_as_string(run["time"].values[k], unit="s")
        rows.append(f"{t},{f},{float(band_brightness_temperature(L, inst.band)):.3f},{dwell}")
(DATA / "traverse.csv").write_text("time,facet,brightness_temperature_K,dwell_s\n" + "\n".join(rows) + "\n")

post = ct.invert(DATA / "run.nc", DATA / "grid.nc", DATA / "traverse.csv", instrument="diviner_ch7",
                 loose_bottom_kg_m3=1500.0, output=DATA / "posterior.nc", overwrite=True)  # fmt: skip
p_loose = np.full(sun.shape[1], np.nan)
p_loose[post["footprint"].values] = post["p_loose"].values

# --- observation design: expected width versus time of night and dwell --------------------------------
f0 = path[np.argmin(np.abs(xyz[path, 0] - 1000.0))]  # a footprint in the patch
dwells = np.array([0.128, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 1000.0])
by_time = ct.observation_design(run, grid, f0, instrument="diviner_ch7", dwell_s=[dwell])
need = {}
for name in ("diviner_ch7", "microbolometer"):
    d = ct.observation_design(run, grid, f0, instrument=name, dwell_s=dwells, local_times=3)
    p, p_long = d["p_loose"][0], d["p_loose"][0, -1]
    # dwell needed: the shortest whose expected P(loose) reaches 95 % of a 1000 s stare's (longer stares add
    # little: the footprint's natural scatter and the 1/f floor do not average down); none if the data say
    # nothing (P(loose) stays the prior's)
    informative = abs(p_long - d["prior_p_loose"]) > 0.05
    d["needed_s"] = dwells[np.flatnonzero(p >= 0.95 * p_long)[0]] if informative else None
    need[name] = d

# --- figure ------------------------------------------------------------------------------------------
fig, ax = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained")
v = run["mesh_vertices"].values
tri = Triangulation(v[:, 0] / 1e3, v[:, 1] / 1e3, run["mesh_faces"].values)
ax[0].triplot(tri, color="0.8", lw=0.5)
seen = np.isfinite(p_loose)
tri_seen = Triangulation(v[:, 0] / 1e3, v[:, 1] / 1e3, run["mesh_faces"].values, mask=~seen)
pc = ax[0].tripcolor(tri_seen, facecolors=np.nan_to_num(p_loose), cmap="magma_r", vmin=0, vmax=1)
ax[0].plot(xyz[loose, 0] / 1e3, xyz[loose, 1] / 1e3, "c*", ms=9, label="loose patch (truth, 800/1100)")
ax[0].plot(xyz[path, 0] / 1e3, xyz[path, 1] / 1e3, "w--", lw=1, label="traverse (3 night crossings)")
fig.colorbar(pc, ax=ax[0], label="P(bottom < 1500 kg m-3)")
ax[0].set(xlabel="x [km]", ylabel="y [km]", aspect="equal", title="posterior P(loose) along the traverse")
ax[0].legend(loc="lower left", fontsize=8)
h = by_time["hours_after_sunset"]
order = np.argsort(h)
ax[1].plot(h[order], by_time["sd_bottom_kg_m3"][order, 0], ".-", label="bottom layer")
ax[1].plot(h[order], by_time["sd_top_kg_m3"][order, 0], ".-", label="top 2 cm")
ax[1].axhline(by_time["prior_sd_kg_m3"][1], color="k", ls=":", label="prior sd (bottom)")
ax[1].set(xlabel="hours after sunset (sample time) [h]", ylabel="expected posterior sd [kg m-3]",
          title=f"one {dwell:g} s Diviner ch7 sample, facet {f0}")  # fmt: skip
ax[1].legend(fontsize=8)
for name, d in need.items():
    ax[2].semilogx(dwells, d["p_loose"][0], "o-", label=name)
    if d["needed_s"] is not None:
        ax[2].axvline(d["needed_s"], color="C0", ls="--", lw=0.8)
ax[2].axhline(need["diviner_ch7"]["prior_p_loose"], color="k", ls=":", label="prior")
ax[2].set(xlabel="dwell per sample [s]", ylabel="expected P(loose), loose truth", ylim=(0, 1),
          title="three local times: dwell needed")  # fmt: skip
ax[2].legend(fontsize=8)
fig.savefig(OUT / "inversion.png", dpi=90)

inside, outside = p_loose[path][loose[path]], p_loose[path][~loose[path]]
print(f"facets: {sun.shape[1]}")
print(f"profiles: {grid.sizes['profile']}")
print(f"traverse footprints: {path.size}")
print(f"loose footprints on the traverse: {inside.size}")
print(f"mean P(loose) in the patch: {inside.mean():.2f}")
print(f"mean P(loose) outside the patch: {outside.mean():.2f}")
print(f"night floor temperature, nominal: {np.median(T_true[np.ix_(crossings, path[~loose[path]])]):.1f} K")
print(f"best single-sample sd of the bottom density: {by_time['sd_bottom_kg_m3'].min():.0f} kg m-3")
print(f"prior sd of the bottom density: {by_time['prior_sd_kg_m3'][1]:.0f} kg m-3")
for name, d in need.items():
    print(f"expected P(loose) with 1000 s stares, {name}: {d['p_loose'][0, -1]:.2f}")
    if d["needed_s"] is None:
        print(f"{name}: no information at any dwell (P(loose) stays the prior's {d['prior_p_loose']:.2f})")
    else:
        print(f"dwell needed, {name}: {d['needed_s']:g} s")
print(f"prior P(loose): {need['diviner_ch7']['prior_p_loose']:.2f}")
print(f"NETD of one integration at 50 K, microbolometer: {get_instrument('microbolometer').netd(50.0):.0f} K")
print(f"NETD of one integration at 50 K, diviner_ch7: {inst.netd(50.0):.2f} K")
print(f"files: {DATA}")
print(f"figure: {OUT / 'inversion.png'}")
