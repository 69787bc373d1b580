"""Benchmark of inversion.invert: one footprint (91-profile grid, 100 samples) and a 1k-footprint map
(extrapolated linearly to 10k). Synthetic grid temperatures (smooth in density and time), not a replay:
the cost does not depend on the values. Writes bench/results/invert.json."""

import json
import time
from pathlib import Path

import numpy as np

from crater_thermal import inversion as inv

dens = np.arange(800.0, 2001.0, 100.0)
pairs = [(a, b) for i, a in enumerate(dens) for b in dens[i:]]
nt, nf = 720, 50
times = np.datetime64("2025-01-01", "ns") + np.arange(nt) * np.timedelta64(3600, "s")
h = np.arange(nt)[None, :, None]
T = np.stack([np.broadcast_to(60 + 20 * np.exp(-h[0] / (10 + t / 200)) + (b - 800) / 60, (nt, nf)) for t, b in pairs])
fm = inv.ForwardModel(T, [p[0] for p in pairs], [p[1] for p in pairs], times)
rng = np.random.default_rng(0)


def table(n_fp, n_per):
    k = rng.integers(0, nt, n_fp * n_per)
    return inv.ObservationTable(
        time=times[k],
        facet=rng.integers(0, nf, k.size),
        footprint=np.repeat(np.arange(n_fp), n_per),
        T_b_K=70 + rng.normal(size=k.size),
        dwell_s=np.full(k.size, 1.0),
        instrument="diviner_ch7",
    )


inv.invert(fm, table(1, 100))  # warm-up (band table)
one = table(1, 100)
t0 = time.perf_counter()
for _ in range(5):
    p = inv.invert(fm, one)
t_one = (time.perf_counter() - t0) / 5
many = table(1000, 10)
t0 = time.perf_counter()
inv.invert(fm, many)
t_1k = time.perf_counter() - t0
out = {
    "grid_profiles": len(pairs),
    "refine": inv.DEFAULT_REFINE,
    "posterior_nodes": int((p.prior > 0).sum()),
    "one_footprint_100_samples_s": t_one,
    "map_1000_footprints_10_samples_s": t_1k,
    "map_10000_footprints_extrapolated_s": 10 * t_1k,
    "note": "one process on a shared 2-core machine; 10k extrapolated linearly from 1k (footprints are independent)",
}
Path(__file__).parent.joinpath("results", "invert.json").write_text(json.dumps(out, indent=1))
print(json.dumps(out, indent=1))
