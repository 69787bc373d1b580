"""Benchmark: the view-factor operator of a cluster run built by the workers vs by the client (issue 22
item 2: "the operator's blocks held by the workers that own their rows").

The generator crater of ``bench/scale.py`` (10 km crater, 5 km surround) at ``--facets`` facets, its
compressed operator for a local cluster of ``--workers`` one-thread processes cut in chunks of
``--chunk-facets`` rows (cluster order), as ``run --workers`` cuts them. Three modes, each in a fresh
Python process (so that its peak resident memory is its own):

* ``client``: the client builds the whole operator (``compressed_view_factors``, one thread per core),
  saves it and the workers load their rows (``load_row_block``): the path of a run before the workers
  built their rows;
* ``workers``: each worker builds its own chunks' rows from the mesh (``cluster_run``'s session,
  ``CompressedPlan.row_block``), the client holds a ``ClusterOperator`` (facet order and areas);
* ``run_local``, ``run_dask`` (not by default): a short coupled run of the crater (``--run-days``
  recorded after a fixed 2-day spin-up, the relaxed scheme, the compressed operator) in one process and
  on the local cluster: wall time and stages, the client's peak RSS, the largest temperature difference;
* ``single``: the whole build on one thread in one process (the reference of the duplicated work), the
  plan's (tree, partition) time, paid once per worker, and every chunk's rows built alone one after the
  other in that process (the duplicated work measured without the cluster's noise).

Recorded: the client's peak RSS (``ru_maxrss``; mesh, ray tracer and the dask client included in both
modes) and its growth from the build's start; each worker's held row-block bytes and peak RSS; build wall
time; one product with ``--samples`` right-hand sides through the client; and the work duplicated by
building alone (blocks meeting two chunks' rows are built by both): rays and block-build seconds summed
over chunks against the single-process build.

Usage: ``python bench/operator_workers.py [--facets 20000] [--workers 2] [--chunk-facets 4000]
[--samples 96] [--modes single client workers run_local run_dask] [--run-days 10]
[--out bench/results/operator_workers.json]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# bench/distributed.py would shadow the dask.distributed package: keep this folder off the path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import cluster, cluster_run, geometry, io, raytrace, vfoperator  # noqa: E402


def _maxrss() -> int:
    """Peak resident memory of this process [B] (Linux reports kB)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _worker_maxrss():
    return _maxrss()


def _stats(block):
    return {"nbytes": block.nbytes, "rows": len(block.facets), **block.stats}


def _mesh(args):
    return geometry.crater_mesh(10.0, n_facets=args.facets, surround_km=5.0)


def _bounds(nf: int, args):
    size = min(args.chunk_facets, -(-nf // args.workers))
    return [(a, min(nf, a + size)) for a in range(0, nf, size)]


def _per_worker(client, futures, stats) -> dict:
    """Row-block bytes held per worker [B]."""
    held: dict = {}
    who = client.who_has(futures)
    for f, s in zip(futures, stats):
        for w in who.get(f.key, ()):
            held[w] = held.get(w, 0) + s["nbytes"]
    return held


def mode_client(args) -> dict:
    mesh = _mesh(args)
    tracer = raytrace.RayTracer(mesh)
    client, cl = cluster.connect(None, args.workers)
    try:
        rss0 = _maxrss()
        t0 = time.perf_counter()
        F = vfoperator.compressed_view_factors(mesh, tracer)
        with tempfile.TemporaryDirectory() as tmp:
            vfoperator.save_operator(F, tmp)
            rows = [client.submit(cluster_run.load_rows, tmp, a, b) for a, b in _bounds(mesh.n_facets, args)]
            stats = client.gather([client.submit(_stats, r) for r in rows])
            build_s = time.perf_counter() - t0
            X = np.random.default_rng(0).uniform(20.0, 400.0, (mesh.n_facets, args.samples))
            t0 = time.perf_counter()
            F @ X
            product_s = time.perf_counter() - t0
            held = _per_worker(client, rows, stats)
            workers_rss = client.run(_worker_maxrss)
        return {
            "build_wall_s": build_s,
            "operator_bytes": int(F.nbytes),
            "client_operator_bytes": int(F.nbytes),
            "client_peak_rss_B": _maxrss(),
            "client_rss_growth_B": _maxrss() - rss0,
            "product_s": product_s,
            "held_bytes_per_worker": list(held.values()),
            "worker_peak_rss_B": list(workers_rss.values()),
            "chunks": len(stats),
        }
    finally:
        client.close()
        cl.close()


def mode_workers(args) -> dict:
    mesh = _mesh(args)
    tracer = raytrace.RayTracer(mesh)
    with tempfile.TemporaryDirectory() as tmp:
        store = io.SegmentStore(Path(tmp) / "run.nc.partial", 8)
        factory = cluster_run.distributed_columns(workers=args.workers, chunk_facets=args.chunk_facets)
        with factory(None, mesh, store) as session:
            client = session.client
            rss0 = _maxrss()
            t0 = time.perf_counter()
            F = session.view_factors(mesh, tracer, "compressed", vfoperator.DEFAULT_TOLERANCE)
            build_s = time.perf_counter() - t0
            stats = client.gather([client.submit(_stats, r) for r in F.rows])
            X = np.random.default_rng(0).uniform(20.0, 400.0, (mesh.n_facets, args.samples))
            t0 = time.perf_counter()
            F @ X
            product_s = time.perf_counter() - t0
            held = _per_worker(client, F.rows, stats)
            workers_rss = client.run(_worker_maxrss)
            return {
                "build_wall_s": build_s,
                "client_operator_bytes": int(F.nbytes),
                "client_peak_rss_B": _maxrss(),
                "client_rss_growth_B": _maxrss() - rss0,
                "product_s": product_s,
                "held_bytes_per_worker": list(held.values()),
                "held_bytes_all_chunks": int(F.held_bytes),
                "worker_peak_rss_B": list(workers_rss.values()),
                "chunks": len(stats),
                "chunk_rays": [s["rays"] for s in stats],
                "chunk_build_s": [s["build_s"] for s in stats],
                "chunk_build_cpu_s": [s["build_cpu_s"] + s["plan_cpu_s"] for s in stats],
                "chunk_units": [s["units"] for s in stats],
            }


def mode_single(args) -> dict:
    mesh = _mesh(args)
    tracer = raytrace.RayTracer(mesh, n_threads=1)
    c0 = time.process_time()
    plan = vfoperator.CompressedPlan(mesh, tracer)
    plan_cpu_s = time.process_time() - c0
    units = len(plan.units())
    del plan
    c0 = time.process_time()
    F = vfoperator.compressed_view_factors(mesh, tracer, n_threads=1)
    build_cpu_s = time.process_time() - c0
    # every chunk's rows built alone, one after the other in this process on one thread (its own plan,
    # as each worker makes one): the duplicated work without the cluster's noise
    c0 = time.process_time()
    plan = vfoperator.CompressedPlan(mesh, tracer)
    alone_rays = sum(plan.row_block(a, b, n_threads=1).stats["rays"] for a, b in _bounds(mesh.n_facets, args))
    alone_cpu_s = time.process_time() - c0
    return {
        "build_s_one_thread": F.stats["build_s"],
        "build_cpu_s": build_cpu_s,
        "chunks_alone_cpu_s": alone_cpu_s,
        "chunks_alone_rays": alone_rays,
        "plan_cpu_s": plan_cpu_s,
        "rays": F.stats["rays"],
        "units": units,
        "operator_bytes": int(F.nbytes),
        "peak_rss_B": _maxrss(),
    }


def _run_case(args, tmp: Path) -> Path:
    """A short coupled run of the crater (``--run-days`` recorded after a fixed spin-up of 2 days, the
    relaxed scheme, the compressed operator), its case file in ``tmp``."""
    spec = importlib.util.spec_from_file_location("bench_scale", REPO / "bench" / "scale.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    end = str(np.datetime64("2019-01-01T00:00") + np.timedelta64(int(round(args.run_days * 86400)), "s"))
    text = mod.CASE.format(
        facets=args.facets,
        diameter_km=10.0,
        surround_km=5.0,
        lat_deg=-86.0,
        chunk_mb=256,
        extra='[radiation]\nview_factors = "compressed"',
        end=end,
        spinup='spinup = "fixed"\nspinup_days = 2.0',
    )
    text = text.replace("flux_step_hours = 4.0", 'flux_step_hours = 4.0\nir_coupling = "relaxed"')
    path = tmp / "case.toml"
    path.write_text(text)
    return path


def _run(args, workers) -> dict:
    from crater_thermal import config, runner, simulate

    out = Path(args.run_dir) / ("dask.nc" if workers else "local.nc")
    case = config.load_case(_run_case(args, Path(args.run_dir)))
    timer = simulate.Timer()
    columns = cluster_run.distributed_columns(workers=args.workers, chunk_facets=args.chunk_facets) if workers else None
    t0 = time.perf_counter()
    runner.run_case(case, out, progress=False, timer=timer, columns=columns, overwrite=True)
    return {
        "wall_s": time.perf_counter() - t0,
        "stages_s": dict(timer.split),
        "client_peak_rss_B": _maxrss(),
        "out": str(out),
    }


def mode_run_local(args) -> dict:
    return _run(args, False)


def mode_run_dask(args) -> dict:
    return _run(args, True)


MODES = {
    "client": mode_client,
    "workers": mode_workers,
    "single": mode_single,
    "run_local": mode_run_local,
    "run_dask": mode_run_dask,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=20_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-facets", type=int, default=4000)
    ap.add_argument("--samples", type=int, default=96)
    ap.add_argument("--modes", nargs="+", default=["single", "client", "workers"], choices=list(MODES))
    ap.add_argument("--run-days", type=float, default=10.0)
    ap.add_argument("--run-dir", help=argparse.SUPPRESS)
    ap.add_argument("--mode", choices=list(MODES), help=argparse.SUPPRESS)  # one mode, in this process
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "operator_workers.json")
    args = ap.parse_args()
    if args.mode:
        print(json.dumps(MODES[args.mode](args)))
        return
    result = {
        "facets_requested": args.facets,
        "facets": _mesh(args).n_facets,
        "workers": args.workers,
        "chunk_facets": args.chunk_facets,
        "cpus": os.cpu_count(),
        "modes": {},
    }
    run_dir = tempfile.mkdtemp(prefix="operator_workers_")
    for mode in args.modes:
        cmd = [sys.executable, __file__, "--mode", mode, "--facets", str(args.facets), "--workers", str(args.workers)]
        cmd += ["--chunk-facets", str(args.chunk_facets), "--samples", str(args.samples)]
        cmd += ["--run-days", str(args.run_days), "--run-dir", run_dir]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        result["modes"][mode] = {**json.loads(out.strip().splitlines()[-1]), "process_wall_s": time.perf_counter() - t0}
        print(mode, json.dumps(result["modes"][mode])[:400], flush=True)
    m = result["modes"]
    if {"client", "workers"} <= m.keys():
        c, w = m["client"], m["workers"]
        result["client_peak_rss_workers_over_client"] = w["client_peak_rss_B"] / c["client_peak_rss_B"]
        result["client_rss_growth_workers_over_client"] = w["client_rss_growth_B"] / c["client_rss_growth_B"]
    if {"single", "workers"} <= m.keys():
        s, w = m["single"], m["workers"]
        result["duplication_rays"] = sum(w["chunk_rays"]) / s["rays"]
        # CPU seconds of the chunks' builds (their plans included) against the one-thread whole build
        # (CPU, not wall: the machine is shared)
        result["duplication_cpu_workers"] = sum(w["chunk_build_cpu_s"]) / s["build_cpu_s"]
        # the same chunks built alone in one process, one after the other: the duplication without the
        # cluster's noise (CPU seconds of all chunks, one plan, against the whole build's)
        result["duplication_cpu"] = s["chunks_alone_cpu_s"] / s["build_cpu_s"]
        result["build_wall_workers_over_single"] = w["build_wall_s"] / s["build_s_one_thread"]
    if {"client", "workers"} <= m.keys():
        result["build_wall_workers_over_client"] = m["workers"]["build_wall_s"] / m["client"]["build_wall_s"]
    if {"run_local", "run_dask"} <= m.keys():
        from crater_thermal import io

        with io.open_run(m["run_local"]["out"]) as a, io.open_run(m["run_dask"]["out"]) as b:
            d = np.abs(a["surface_temperature"].values.astype(float) - b["surface_temperature"].values)
        result["run_max_abs_dT_K"] = float(d.max())
        result["run_client_peak_rss_dask_over_local"] = (
            m["run_dask"]["client_peak_rss_B"] / m["run_local"]["client_peak_rss_B"]
        )
    shutil.rmtree(run_dir, ignore_errors=True)
    result["loadavg_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "modes"}))


if __name__ == "__main__":
    main()
