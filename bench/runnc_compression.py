"""Benchmark: how run.nc's (time, facet) series are compressed (issue 24): level, shuffle, chunk shape, dtype.

Run:  PYTHONPATH=$PWD python bench/runnc_compression.py RUN.nc [--tile 4] [--filters] [--out JSON]
      PYTHONPATH=$PWD python bench/runnc_compression.py RUN.nc --writers [--tile 2] [--repeat 3] --out JSON

Reads the four (time, facet) series of a real run (``solar_incident``, ``ir_incident``, ``solar_direct``,
``surface_temperature``), optionally side by side ``--tile`` times along facet (a wider block; the copies
are offset by a small per-copy noise so that zlib cannot match them), and writes them with netCDF4 in
each setting, in one process (ratios within one run; the machine is shared). Per setting: write time,
file size, and the time to read one facet's whole series and one time sample of every facet (how
replay and report read). ``--filters`` adds float32 with the zstd and blosc_lz4 filters (HDF5 plugins that
netCDF4's wheels carry; a reader without them cannot read such a file). Writes
``bench/results/runnc_compression.json`` (``--out``).

``--writers`` instead compares two writers of the same file (float32, zlib level 1 + shuffle, chunks of
24 samples x ~1 MB, blocks of 120 samples): netCDF4 assigning each block (HDF5 shuffles and deflates
chunk after chunk in one thread: the writer before this comparison) and ``io.stream_dataset`` as a run
writes (its chunks shuffled and deflated in a thread pool, ISA-L's deflate, HDF5's direct chunk write),
alternating ``--repeat`` times in one process, and ``io.stream_dataset`` with ``compression = "blosc_lz4"``
(netCDF4 writing, HDF5's blosc plugin); each file read back by netCDF4 and compared.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
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
    ap.add_argument("--writers", action="store_true", help="compare netCDF4's writer with io.stream_dataset")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    if args.writers:
        return writers(args)
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


def _load(run: str, tile: int) -> tuple[dict, dict]:
    import netCDF4

    rng = np.random.default_rng(0)
    data = {}
    with netCDF4.Dataset(run) as nc:
        for name in SERIES:
            x = np.asarray(nc[name][:], dtype=np.float32)
            copies = [x] + [
                (x * (1 + 1e-4 * rng.standard_normal(x.shape[1]))).astype(np.float32) for _ in range(tile - 1)
            ]
            data[name] = np.concatenate(copies, axis=1)
        timing = json.loads(nc.getncattr("timing_s"))
    return data, timing


#: netCDF4 assigning blocks (zlib), io.stream_dataset with zlib (the default), with ``compression = "blosc_lz4"``
WRITERS = ("netcdf4", "stream_dataset", "stream_dataset_blosc_lz4")


def writers(args) -> dict:
    """netCDF4's own chunk filtering against io.stream_dataset's parallel direct chunk writes."""
    import netCDF4
    import xarray as xr

    from crater_thermal import io

    data, timing = _load(args.run, args.tile)
    nt, nf = data[SERIES[0]].shape
    chunk = io.chunk_shape((nt, nf), 0, 24, itemsize=4)
    block = 120
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeat):
            for writer in WRITERS:
                path = Path(tmp) / f"{writer}_{rep}.nc"
                t0 = time.perf_counter()
                if writer == "netcdf4":
                    with netCDF4.Dataset(path, "w") as nc:
                        nc.createDimension("time", nt)
                        nc.createDimension("facet", nf)
                        for name, x in data.items():
                            v = nc.createVariable(
                                name,
                                "f4",
                                ("time", "facet"),
                                chunksizes=chunk,
                                fill_value=np.float32(np.nan),
                                zlib=True,
                                complevel=1,
                                shuffle=True,
                            )
                            for a in range(0, nt, block):
                                v[a : a + block] = x[a : a + block]
                else:
                    spec = {name: (("time", "facet"), (nt, nf), {"units": "K"}, "f4") for name in data}
                    how = "blosc_lz4" if writer.endswith("blosc_lz4") else "zlib"
                    with io.stream_dataset(xr.Dataset(), path, spec, time_rows=24, compression=how) as write:
                        for name, x in data.items():
                            for a in range(0, nt, block):
                                write(name, (slice(a, a + block), slice(None)), x[a : a + block])
                write_s = time.perf_counter() - t0
                with netCDF4.Dataset(path) as nc:
                    assert list(nc["surface_temperature"].chunking()) == list(chunk)
                    t0 = time.perf_counter()
                    col = np.asarray(nc["surface_temperature"][:, nf // 2])
                    column_s = time.perf_counter() - t0
                    equal = all(np.array_equal(np.asarray(nc[name][:]), x) for name, x in data.items())
                res = {
                    "writer": writer,
                    "repeat": rep,
                    "write_s": write_s,
                    "size_mb": path.stat().st_size / 2**20,
                    "read_one_facet_s": column_s,
                    "equal_to_source": equal,
                    "write_us_per_sample_facet": 1e6 * write_s / (nt * nf),
                }
                assert equal and np.isfinite(col).all()
                results.append(res)
                print(json.dumps(res), flush=True)
                path.unlink()
    best = {w: min(r["write_s"] for r in results if r["writer"] == w) for w in WRITERS}
    out = {
        "benchmark": "runnc_compression --writers",
        "source_run": str(args.run),
        "block": {"samples": nt, "facets": nf, "series": list(SERIES), "tile": args.tile, "chunk": list(chunk)},
        "threads": os.cpu_count(),
        "source_run_s_per_sample_facet_us": 1e6 * sum(timing.values()) / (nt * nf / args.tile),
        "best_write_s": best,
        "speedup": best["netcdf4"] / best["stream_dataset"],
        "results": results,
        "notes": "one process, alternating writers; float32 zlib 1 + shuffle both; read back by netCDF4",
    }
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
