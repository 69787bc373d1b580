"""Benchmark of inversion.invert (issue 23's targets): one footprint's posterior over the thesis's 91-profile
grid (800:2000:100, refine 4: 1,225 posterior nodes) with 100 observations, and a 10k-footprint site map
measured directly (one footprint per facet of a 10,000-facet grid replay, 10 samples each: an orbital map
at several local times). The API's reading of the run, replay and table and the writing of posterior.nc
are not timed here. Each is timed with the model-error term estimated from the grid (the default,
model_error_K="auto") and without it (0), in the same run.

The grid temperatures are synthetic (smooth in density and time; float32 like a replay file), not a
replay: the cost does not depend on the values. Writes bench/results/invert.json.

Usage: ``python bench/invert.py``
"""

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from crater_thermal import inversion as inv

dens = np.arange(800.0, 2001.0, 100.0)
pairs = [(a, b) for i, a in enumerate(dens) for b in dens[i:]]
nt, nf = 180, 10_000  # a lunation at 4 h steps; 10k facets (91 x 180 x 10k float32 = 655 MB)
times = np.datetime64("2025-01-01", "ns") + np.arange(nt) * np.timedelta64(4 * 3600, "s")
h = np.arange(nt, dtype=np.float32)[:, None]
facet_shift = np.linspace(0.0, 20.0, nf, dtype=np.float32)[None, :]
T = np.empty((len(pairs), nt, nf), np.float32)
for p, (t, b) in enumerate(pairs):
    T[p] = 50 + facet_shift + 20 * np.exp(-h / (10 + t / 200)) + (b - 800) / 60
fm = inv.ForwardModel(T, [p[0] for p in pairs], [p[1] for p in pairs], times)
rng = np.random.default_rng(0)


def table(n_fp, n_per, one_facet_each=True):
    k = rng.integers(0, nt, n_fp * n_per)
    facet = np.repeat(np.arange(n_fp) % nf, n_per) if one_facet_each else rng.integers(0, nf, k.size)
    return inv.ObservationTable(
        time=times[k],
        facet=facet,
        footprint=np.repeat(np.arange(n_fp), n_per),
        T_b_K=70 + rng.normal(size=k.size),
        dwell_s=np.full(k.size, 1.0),
        instrument="diviner_ch7",
    )


inv.invert(fm, table(1, 100))  # warm-up (band table)
one = table(1, 100)
reps = 10
t0 = time.perf_counter()
for _ in range(reps):
    p = inv.invert(fm, one)
t_one = (time.perf_counter() - t0) / reps
t0 = time.perf_counter()
for _ in range(reps):
    inv.invert(fm, one, model_error_K=0.0)
t_one_exact = (time.perf_counter() - t0) / reps
many = table(10_000, 10)
t0 = time.perf_counter()
post = inv.invert(fm, many)
t_10k = time.perf_counter() - t0
assert post.probability.shape[0] == 10_000
t0 = time.perf_counter()
inv.invert(fm, many, model_error_K=0.0)
t_10k_exact = time.perf_counter() - t0
out = {
    "grid_profiles": len(pairs),
    "refine": inv.DEFAULT_REFINE,
    "posterior_nodes": int((p.prior > 0).sum()),
    "one_footprint_100_samples_s": t_one,
    "map_10000_footprints_10_samples_s": t_10k,
    "map_per_footprint_ms": 1e3 * t_10k / 10_000,
    "model_error": "auto (the default) in the two timings above; *_model_error_0_s: model_error_K=0 (no term)",
    "one_footprint_100_samples_model_error_0_s": t_one_exact,
    "map_10000_footprints_10_samples_model_error_0_s": t_10k_exact,
    "ratio_auto_over_0_one_footprint": t_one / t_one_exact,
    "ratio_auto_over_0_map": t_10k / t_10k_exact,
    "replay_facets": nf,
    "replay_times": nt,
    "load_average_1min_at_end": os.getloadavg()[0],
    "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared); one process",
    "note": "measured directly (not extrapolated); synthetic smooth grid temperatures (cost is value-independent)",
}
Path(__file__).parent.joinpath("results", "invert.json").write_text(json.dumps(out, indent=1) + "\n")
print(json.dumps(out, indent=1))
