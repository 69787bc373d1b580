"""Benchmark: how run.nc's (time, facet) series are compressed (issue 24): level, shuffle, chunk shape, dtype.

Run:  PYTHONPATH=$PWD python bench/runnc_compression.py RUN.nc [--tile 4] [--filters] [--out JSON]

Reads the four (time, facet) series of a real run (``solar_incident``, ``ir_incident``, ``solar_direct``,
``surface_temperature``), optionally side by side ``--tile`` times along facet (a wider block; the copies
are offset by a small per-copy noise so that zlib cannot match them), and writes them with netCDF4 in
each setting, in one process (ratios within one run; the machine is shared). Per setting: write time,
file size, and the time to read one facet's whole series and one time sample of every facet (how
replay and report read). ``--filters`` adds float32 with the zstd and blosc_lz4 filters (HDF5 plugins that
netCDF4's wheels carry; a reader without them cannot read such a file). Writes
``bench/results/runnc_compression.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
import time
from pathlib import Path

import numpy as np

SERIES = ("solar_incident", "ir_incident", "solar_direct", "surface_temperature")


def main(argv=None) -> dict:
    import netCDF4

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--tile", type=int, default=4)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "runnc_compression.json"))
    ap.add_argument(
        "--filters",
        action="store_true",
        help="also float32 with HDF5 plugin filters (zstd, blosc_lz4: in netCDF4's wheels; readers need the plugins)",
    )
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    data = {}
    with netCDF4.Dataset(args.run) as nc:
        for name in SERIES:
            x = np.asarray(nc[name][:], dtype=np.float64)
            copies = [x] + [x * (1 + 1e-4 * rng.standard_normal(x.shape[1])) for _ in range(args.tile - 1)]
            data[name] = np.concatenate(copies, axis=1)
        timing = json.loads(nc.getncattr("timing_s"))
    nt, nf = data[SERIES[0]].shape
    raw_f8 = sum(v.nbytes for v in data.values())
    results = []
    settings = itertools.product(("f4", "f8"), (1, 4), (False, True), ((24, 1 << 20), (24, 4 << 20), (96, 4 << 20)))
    settings = [(d, lv, sh, ch) for d, lv, sh, ch in settings if d == "f4" or (lv == 1 and ch == (24, 1 << 20))]
    # the writer before issue 24: float32, level 1, no shuffle, 24 rows x (1 MB of float64) facets
    settings = [("f4", 0, False, (24, 1 << 20)), ("f4", 1, False, (24, 1 << 19))] + settings
    settings = [(*s, "zlib") for s in settings]
    if args.filters:
        settings += [("f4", 1, True, (24, 4 << 20), name) for name in ("zstd", "blosc_lz4")]
    with tempfile.TemporaryDirectory() as tmp:
        for i, (dtype, level, shuffle, (rows, target), filt) in enumerate(settings):
            path = Path(tmp) / f"s{i}.nc"
            item = np.dtype(dtype).itemsize
            chunk = (min(rows, nt), max(1, min(nf, target // (item * rows))))
            t0 = time.perf_counter()
            with netCDF4.Dataset(path, "w") as nc:
                nc.createDimension("time", nt)
                nc.createDimension("facet", nf)
                for name, x in data.items():
                    if filt == "zlib":
                        how = {"zlib": level > 0, "complevel": max(level, 1), "shuffle": shuffle}
                    elif filt.startswith("blosc"):  # blosc's own byte shuffle
                        how = {"compression": filt, "complevel": level, "blosc_shuffle": 1 if shuffle else 0}
                    else:
                        how = {"compression": filt, "complevel": level, "shuffle": shuffle}
                    v = nc.createVariable(
                        name,
                        dtype,
                        ("time", "facet"),
                        chunksizes=chunk,
                        fill_value=np.dtype(dtype).type(np.nan),
                        **how,
                    )
                    for a in range(0, nt, 120):  # streamed blocks as a run writes them
                        v[a : a + 120] = x[a : a + 120].astype(dtype)
            write_s = time.perf_counter() - t0
            with netCDF4.Dataset(path) as nc:
                t0 = time.perf_counter()
                col = nc["surface_temperature"][:, nf // 2]
                column_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                row = nc["surface_temperature"][nt // 2, :]
                row_s = time.perf_counter() - t0
                err = float(np.abs(np.asarray(nc["surface_temperature"][:], float) - data["surface_temperature"]).max())
            assert np.isfinite(col).all() and np.isfinite(row).all()
            res = {
                "filter": filt,
                "dtype": dtype,
                "complevel": level,
                "shuffle": shuffle,
                "chunk": list(chunk),
                "write_s": write_s,
                "size_mb": path.stat().st_size / 2**20,
                "ratio_to_raw_f8": path.stat().st_size / raw_f8,
                "read_one_facet_s": column_s,
                "read_one_sample_s": row_s,
                "max_abs_err_T_K": err,
                "write_us_per_sample_facet": 1e6 * write_s / (nt * nf),
            }
            results.append(res)
            print(json.dumps(res), flush=True)
    run_s = sum(timing.values())
    out = {
        "benchmark": "runnc_compression",
        "source_run": str(args.run),
        "block": {"samples": nt, "facets": nf, "series": list(SERIES), "tile": args.tile, "raw_f8_mb": raw_f8 / 2**20},
        "source_run_s_per_sample_facet_us": 1e6 * run_s / (nt * nf / args.tile),
        "results": results,
        "notes": "one process, same data; the tiled copies carry 1e-4 relative noise (no exact repeats for zlib)",
    }
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
