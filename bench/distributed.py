"""Benchmark: a replay in one local process vs on a local dask cluster (issue 22, replay part).

The 91-profile density grid 800:2000:100 replayed against the thesis crater's fluxes (10 km, 502 facets,
-86 deg, a recorded year of 4-hour samples after a saved year of spin-up fluxes), in one run:

* ``local``: ``runner.replay_file`` in this process (numba's threads on every core);
* ``dask``: ``cluster.replay_file`` on a local cluster of ``--workers`` processes x 1 thread, made with
  the same call as ``replay --workers`` (``cluster.connect``); its wall time counts the cluster's start,
  the replay (tasks, transfers of the results, the chunk files, the assembly) and the cluster's close.

Both write replay.nc; the temperatures are compared (they must be equal bit for bit). Recorded: wall
and CPU seconds of each (the workers' CPU from inside them), the efficiency (local wall / dask wall on
the same cores: 1 is no overhead; the issue's target is an overhead <= 10 %), the load average sampled
during each phase (the machine is shared: the ratios are honest only at a similar load), the chunks
(bytes of flux read and of results returned per chunk), the workers' peak memory, and the model of a
1M-facet grid replay over N machines built from these measured numbers.

The ~20k-facet site variant: 91 profiles x 20k facets is 40x the 502-facet grid, ~6 h per mode on this
2-core machine, so it is run with fewer profiles: ``--run`` a site's run.nc (the synthetic site of
``bench/site.py`` at 20k facets, run first) with ``--grid 800:900:100`` (3 profiles) and ``--out
bench/results/distributed_site20k.json`` (docs/cluster.md).

Usage: ``python bench/distributed.py [--run RUN.nc] [--grid 800:2000:100] [--workers 2]
[--chunk-facets 2000] [--chunk-profiles 2] [--out bench/results/distributed.json]``. Without ``--run``
the thesis case ``cases/thesis/crater_lat86S.toml`` is run first (not timed).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# this file's name would shadow the dask.distributed package when run as a script: not on the path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import cluster, config, io, runner, thermal  # noqa: E402


class LoadSampler:
    """Samples ``os.getloadavg()`` (1-minute) every ``every_s`` seconds while running."""

    def __init__(self, every_s: float = 5.0):
        self.every_s, self.samples, self._stop = every_s, [], threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            self.samples.append(os.getloadavg()[0])
            self._stop.wait(self.every_s)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def summary(self) -> dict:
        s = np.array(self.samples or [float("nan")])
        return {"mean": round(float(s.mean()), 2), "min": round(float(s.min()), 2), "max": round(float(s.max()), 2)}


def _worker_stats():
    """In a worker: its peak resident memory [bytes] and CPU seconds (user + system)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return {"maxrss_bytes": r.ru_maxrss * 1024, "cpu_s": r.ru_utime + r.ru_stime}


PROBE = """
import json, os, resource, sys
import psutil
sys.path.insert(0, {repo!r})
from crater_thermal import cluster, thermal
profiles = list(thermal.density_grid_profiles({grid!r}))[: {n_prof}]
cluster.solve_chunk({run!r}, profiles[:1], 0, 1, {{}})  # imports and kernels loaded: the idle worker
idle = psutil.Process().memory_info().rss
cluster.solve_chunk({run!r}, profiles, 0, {n_fac}, {{}})
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({{"idle_rss_bytes": idle, "peak_rss_bytes": peak}}))
"""


def chunk_memory_probe(run: Path, grid: str, n_fac: int, n_prof: int) -> dict:
    """Peak memory of one chunk (``n_fac`` facets x ``n_prof`` profiles) solved in a fresh process, as a
    worker does, against that process's resident memory once imports and kernels are loaded."""
    import subprocess

    code = PROBE.format(repo=str(REPO), grid=grid, n_prof=n_prof, run=str(run), n_fac=n_fac)
    env = {**os.environ, "CRATER_THERMAL_QUIET": "1", "PYTHONWARNINGS": "ignore"}
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out.update(facets=n_fac, profiles=n_prof, columns=n_fac * n_prof, wall_s=round(time.perf_counter() - t, 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, default=None, help="run.nc to replay (default: run the thesis case)")
    ap.add_argument("--grid", default="800:2000:100")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-facets", type=int, default=2000)
    ap.add_argument("--chunk-profiles", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "distributed.json")
    ap.add_argument(
        "--probe-only",
        action="store_true",
        help="only measure one chunk's memory (502 facets x 8 profiles of --run) into the existing --out JSON",
    )
    args = ap.parse_args()
    if args.probe_only:
        result = json.loads(args.out.read_text())
        result["chunk_memory_probe"] = chunk_memory_probe(args.run, args.grid, 502, 8)
        result["model_1M_facets"] = model_1m(result)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps(result["chunk_memory_probe"]))
        return
    os.environ.setdefault("CRATER_THERMAL_QUIET", "1")
    import warnings

    warnings.simplefilter("ignore")  # density-extrapolation notes of the grid's loose profiles
    result = {"cpu_count": os.cpu_count(), "grid": args.grid, "workers": args.workers, "threads_per_worker": 1}
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        tmp = Path(tmp)
        run = args.run
        if run is None:
            run = tmp / "run.nc"
            t = time.perf_counter()
            runner.run_case(config.load_case(REPO / "cases" / "thesis" / "crater_lat86S.toml"), run, progress=False)
            result["thesis_run_s (not compared)"] = round(time.perf_counter() - t, 1)
        result["run"] = str(args.run) if args.run else "cases/thesis/crater_lat86S.toml (run here)"
        with io.read_flux_dataset(run, load=False) as ds:
            nf, nt = ds.sizes["facet"], ds.sizes["time"]
            nt_spin = ds.sizes.get("spinup_time", 0)
            flux_bytes_per_facet = sum(
                ds[v].dtype.itemsize * ds[v].shape[0] for v in ds.data_vars if v.endswith("_incident")
            )
        n_prof = len(thermal.density_grid_profiles(args.grid))
        result.update(facets=nf, samples=nt, spinup_samples=nt_spin, profiles=n_prof, columns=nf * n_prof)
        grid_profiles = thermal.density_grid_profiles(args.grid)
        result["cells_per_column"] = thermal.ColumnSolver([grid_profiles[0]]).nz

        # --- local: one process, numba's threads on every core
        t0, c0 = time.perf_counter(), os.times()
        with LoadSampler() as load:
            runner.replay_file(run, [], density_grid=args.grid, output=tmp / "local.nc", progress=False)
        c1 = os.times()
        local = {
            "wall_s": round(time.perf_counter() - t0, 2),
            "cpu_s": round((c1.user - c0.user) + (c1.system - c0.system), 2),
            "load_avg_1min": load.summary(),
        }
        with io.open_replay(tmp / "local.nc") as ds:
            local["periodic_iterations"] = [int(i) for i in np.atleast_1d(ds.attrs["periodic_iterations"])]
        result["local"] = local
        print(json.dumps({"local": local}), flush=True)

        # --- dask: a local cluster of `workers` one-thread processes (as `replay --workers`)
        c0 = os.times()
        with LoadSampler() as load:
            t0 = time.perf_counter()
            client, lc = cluster.connect(workers=args.workers)
            t_start = time.perf_counter() - t0
            base = client.run(_worker_stats)
            t1 = time.perf_counter()
            cluster.replay_file(
                run,
                [],
                density_grid=args.grid,
                output=tmp / "dask.nc",
                scheduler=lc.scheduler_address,
                chunk_facets=args.chunk_facets,
                chunk_profiles=args.chunk_profiles,
            )
            t_replay = time.perf_counter() - t1
            after = client.run(_worker_stats)
            t2 = time.perf_counter()
            client.close()
            lc.close()
            t_close = time.perf_counter() - t2
        c1 = os.times()
        wall = t_start + t_replay + t_close
        worker_cpu = sum(after[w]["cpu_s"] - base[w]["cpu_s"] for w in after)
        chunk_cols = min(nf, args.chunk_facets) * min(n_prof, args.chunk_profiles)
        n_chunks = -(-nf // args.chunk_facets) * -(-n_prof // args.chunk_profiles)
        dask = {
            "wall_s": round(wall, 2),
            "cluster_start_s": round(t_start, 2),
            "replay_s": round(t_replay, 2),
            "cluster_close_s": round(t_close, 2),
            "client_cpu_s": round((c1.user - c0.user) + (c1.system - c0.system), 2),
            "workers_cpu_s": round(worker_cpu, 2),
            "chunks": n_chunks,
            "chunk_facets": min(nf, args.chunk_facets),
            "chunk_profiles": min(n_prof, args.chunk_profiles),
            "chunk_flux_read_bytes": min(nf, args.chunk_facets) * flux_bytes_per_facet,
            "chunk_result_bytes": chunk_cols * nt * 4,
            "worker_peak_rss_bytes": max(a["maxrss_bytes"] for a in after.values()),
            "worker_idle_rss_bytes": max(b["maxrss_bytes"] for b in base.values()),
            "load_avg_1min": load.summary(),
        }
        result["dask"] = dask
        with io.open_replay(tmp / "local.nc") as a, io.open_replay(tmp / "dask.nc") as b:
            d = np.abs(a["surface_temperature"].values.astype(float) - b["surface_temperature"].values)
            result["max_abs_diff_K"] = float(d.max())

    # efficiency on the same cores: 1 = no distribution overhead; the target: overhead <= 10 %
    result["efficiency_wall"] = round(local["wall_s"] / dask["wall_s"], 3)
    result["overhead_wall_fraction"] = round(dask["wall_s"] / local["wall_s"] - 1.0, 3)
    result["efficiency_cpu"] = round(local["cpu_s"] / (dask["workers_cpu_s"] + dask["client_cpu_s"]), 3)
    result["target_overhead_fraction"] = 0.10
    result["model_1M_facets"] = model_1m(result)
    result["site_variant"] = (
        "91 profiles x ~20k facets is ~40x the 502-facet grid's columns, ~6 h per mode on this 2-core machine: "
        "the site is run with --run SITE/run.nc and a 3-profile --grid (bench/results/distributed_site20k.json)"
    )
    result["note"] = (
        "2 cores shared with other agents: both phases ran one after the other, their 1-minute load "
        "averages are recorded; CPU seconds are less sensitive to the load than wall seconds"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


def model_1m(r: dict, facets: int = 1_000_000, chunk_facets: int = 2000, chunk_profiles: int = 8) -> dict:
    """A 91-profile grid replay of a 1M-facet site (a year of 4-hour samples after a year of spin-up
    fluxes) over N machines, from this run's measured per-column CPU cost and worker memory."""
    cols = facets * r["profiles"]
    core_s_per_column = r["local"]["cpu_s"] / r["columns"]  # one column: periodic start + the recorded year
    per_facet_flux = r["dask"]["chunk_flux_read_bytes"] / r["dask"]["chunk_facets"]
    chunk_cols = chunk_facets * chunk_profiles
    d = r["dask"]
    nz, nt = r["cells_per_column"], r["samples"]
    probe = r.get("chunk_memory_probe")
    idle = probe["idle_rss_bytes"] if probe else d["worker_idle_rss_bytes"]

    # a worker: its measured idle RSS + the periodic start's mode blocks (4 (n, nz, nz) float64 arrays of
    # at most 4096 columns) + the forcing and float64 records (at most chunk_mb = 256 MB) + the float32
    # result held and pickled once (2x) + ~20 float64 state arrays of nz per column
    def chunk_memory(columns, facets):
        return (
            idle
            + 4 * min(4096, columns) * nz * nz * 8
            + min(256 * 2**20, (nt + r["spinup_samples"]) * facets * 8 + nt * columns * 8)
            + 2 * columns * nt * 4
            + 20 * nz * 8 * columns
        )

    chunk_mem = chunk_memory(chunk_cols, chunk_facets)
    out_bytes = cols * r["samples"] * 4
    machines = {}
    for n, cores in ((1, 32), (4, 32), (16, 32), (64, 32)):
        compute = cols * core_s_per_column / (n * cores) / r["efficiency_cpu"]
        machines[f"{n}x{cores}_cores"] = {
            "compute_h": round(compute / 3600, 2),
            # every result passes through the client and its disk: ~1 GB/s of network and disk assumed
            "client_io_h_at_1GB_s": round(out_bytes / 1e9 / 3600, 2),
        }
    checked = {}
    if probe:  # the same formula for the probed chunk, against its measured peak
        formula = chunk_memory(probe["columns"], probe["facets"])
        checked = {"probe_formula_bytes": int(formula), "probe_measured_peak_bytes": probe["peak_rss_bytes"]}
    return {
        **checked,
        "facets": facets,
        "columns": cols,
        "measured_core_s_per_column": round(core_s_per_column, 5),
        "chunk": f"{chunk_facets} facets x {chunk_profiles} profiles = {chunk_cols} columns",
        "chunks": -(-facets // chunk_facets) * -(-r["profiles"] // chunk_profiles),
        "chunk_core_s": round(chunk_cols * core_s_per_column, 1),
        "chunk_flux_read_bytes": int(chunk_facets * per_facet_flux),
        "chunk_result_bytes": chunk_cols * r["samples"] * 4,
        "flux_store_bytes": int(facets * per_facet_flux),
        "flux_read_total_bytes (each facet block once per profile block)": int(
            facets * per_facet_flux * -(-r["profiles"] // chunk_profiles)
        ),
        "replay_nc_bytes": out_bytes,
        "worker_memory_bytes (measured idle RSS + the chunk's arrays, see model_1m)": int(chunk_mem),
        "wall_time_by_machines": machines,
    }


if __name__ == "__main__":
    main()
