"""Benchmark: a coupled run in one process vs on a local dask cluster (issue 22 item 2).

The generator's crater of ``bench/scale.py`` (10 km, 5 km flat surround, 86 S) at ``--facets`` facets
(default 30,000), a recorded period of ``--days`` (default a year) at 4 h after the periodic start over
the year before it, three ways, one after the other in this process (each after an untimed warm-up):

* ``stepper``: ``runner.run_case`` with the default coupled step (``ir_coupling = "extrapolated"``), the
  single-process run as users run it;
* ``relaxed``: the same case with ``ir_coupling = "relaxed"`` (waveform relaxation) in this process;
* ``dask``: the relaxed run on a local cluster of ``--workers`` processes x 1 thread, made as
  ``run --workers`` does (``cluster_run.distributed_columns``); its wall time counts the cluster's start
  and close.

Recorded per mode: wall seconds and the run's own time split, relaxation iterations per window (mean,
max) of the spin-up's first pass and of the record, the load average sampled during it (the machine is
shared), and the largest temperature differences between the modes (all samples, and night samples of
the facets in permanent shadow). Efficiencies: ``relaxed / dask`` wall (the cost of distribution, same
scheme; 1 = none) and ``stepper / dask`` (against the default single-process run).

The dask mode also records where its time goes: the command's own CPU seconds (it shares the cores with
the workers), and from the scheduler's task stream each worker's busy seconds per kind of task (the
function's name) and its idle seconds over the run, so that load imbalance between workers, scheduling
and the command's work can be told apart.

Usage: ``python bench/coupled_cluster.py [--facets 30000] [--days 365] [--workers 2]
[--chunk-facets 4000] [--modes stepper relaxed dask dask@15000 relaxed#2 dask#2]
[--out bench/results/coupled_cluster.json]``. A mode ``dask@N`` cuts chunks of at most N facets (``dask``:
one per worker); ``dask~N``: with N scattering solves in flight instead of ``radiosity.ASYNC_SOLVES``
(``dask@M~N`` both); ``dask%``: the local cluster with dask's default settings instead of
``cluster.LOCAL_CLUSTER_CONFIG``; ``relaxed#2``, ``dask#2``: a repeat, paired with the relaxed run of its number.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# bench/distributed.py would shadow the dask.distributed package: keep this folder off the path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import cluster, cluster_run, config, io, radiosity, runner, simulate  # noqa: E402


def _scale_case_template() -> str:
    spec = importlib.util.spec_from_file_location("bench_scale", REPO / "bench" / "scale.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.CASE


class LoadSampler(threading.Thread):
    """``os.getloadavg()[0]`` every ``every_s`` seconds while running."""

    def __init__(self, every_s: float = 10.0):
        super().__init__(daemon=True)
        self.every_s, self.samples, self.stop = every_s, [], threading.Event()

    def run(self):
        while not self.stop.is_set():
            self.samples.append(os.getloadavg()[0])
            self.stop.wait(self.every_s)


def write_case(tmp: Path, name: str, facets: int, days: float, scheme: str, spinup: str) -> Path:
    end = str(np.datetime64("2019-01-01T00:00") + np.timedelta64(int(round(days * 86400)), "s"))
    text = _scale_case_template().format(
        facets=facets, diameter_km=10.0, surround_km=5.0, lat_deg=-86.0, chunk_mb=256, extra="", end=end, spinup=spinup
    )
    text = text.replace("flux_step_hours = 4.0", f'flux_step_hours = 4.0\nir_coupling = "{scheme}"')
    path = tmp / f"{name}.toml"
    path.write_text(text)
    return path


def observed_columns(workers: int, chunk_facets: int, seen: dict):
    """``cluster_run.distributed_columns(workers=...)`` that also keeps the scheduler's task stream of the
    run in ``seen["tasks"]`` (one record per task: worker, function, compute start and stop)."""
    import contextlib

    from distributed import get_task_stream

    columns = cluster_run.distributed_columns(workers=workers, chunk_facets=chunk_facets)

    @contextlib.contextmanager
    def factory(case, mesh, store):
        with columns(case, mesh, store) as session:
            with get_task_stream(session.client) as ts:
                yield session
            seen["tasks"] = ts.data

    return factory


def task_summary(tasks: list, wall_s: float) -> dict:
    """Per worker: busy seconds per function (compute only) and in all, and idle seconds of ``wall_s``."""
    from dask.utils import key_split

    out = {}
    for t in tasks:
        w = out.setdefault(t["worker"], {"busy_s": 0.0, "tasks": 0, "by_function_s": {}})
        name = key_split(t["key"])
        for part in t.get("startstops", ()):
            if part.get("action") == "compute":
                dt = part["stop"] - part["start"]
                w["busy_s"] += dt
                w["by_function_s"][name] = w["by_function_s"].get(name, 0.0) + dt
        w["tasks"] += 1
    by_worker = {}
    for t in tasks:
        for part in t.get("startstops", ()):
            if part.get("action") == "compute":
                by_worker.setdefault(t["worker"], []).append((part["start"], part["stop"], key_split(t["key"])))
    for worker, spans in by_worker.items():
        # each gap between two computes of a worker, charged to the kind of task that ends it: the waits
        # of the spin-up's passes, the record's iterations, the scattering's products told apart
        spans.sort()
        waits = {}
        for (_, stop, _), (start, _, name) in zip(spans, spans[1:]):
            waits[name] = waits.get(name, 0.0) + max(start - stop, 0.0)
        out[worker]["idle_before_s"] = {k: round(v, 2) for k, v in sorted(waits.items(), key=lambda kv: -kv[1])}
    for w in out.values():
        w["idle_s"] = wall_s - w["busy_s"]
        w["by_function_s"] = {k: round(v, 2) for k, v in sorted(w["by_function_s"].items(), key=lambda kv: -kv[1])}
        w["busy_s"], w["idle_s"] = round(w["busy_s"], 2), round(w["idle_s"], 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=30_000)
    ap.add_argument("--days", type=float, default=365.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-facets", type=int, default=None, help="at most N facets a chunk (default: 1 per worker)")
    ap.add_argument("--modes", nargs="+", default=["stepper", "relaxed", "dask"])
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "coupled_cluster.json")
    args = ap.parse_args()
    spinup = 'spinup = "periodic"\nspinup_years = 1.0'
    result = {
        "facets_requested": args.facets,
        "record_days": args.days,
        "workers": args.workers,
        "chunk_facets": args.chunk_facets,
        "cpus": os.cpu_count(),
        "modes": {},
    }
    temps = {}
    default_solves = radiosity.ASYNC_SOLVES
    default_config = dict(cluster.LOCAL_CLUSTER_CONFIG)
    result["local_cluster_config"] = default_config
    result["async_solves_default"] = default_solves
    with tempfile.TemporaryDirectory(prefix="coupled_cluster_") as tmp:
        tmp = Path(tmp)
        os.environ.setdefault("CRATER_THERMAL_CACHE", str(tmp / "cache"))
        # untimed warm-up: imports, numba compilation, ephemeris tables, a local cluster's first start
        warm = write_case(tmp, "warm", 300, 2.0, "relaxed", 'spinup = "fixed"\nspinup_days = 1.0')
        runner.run_case(config.load_case(warm), tmp / "warm.nc", progress=False)
        runner.run_case(
            config.load_case(warm),
            tmp / "warm_dask.nc",
            progress=False,
            columns=cluster_run.distributed_columns(workers=args.workers),
        )
        for mode in args.modes:
            # every mode builds its horizon map and operator itself (a cache of its own): none inherits
            # another's stages
            os.environ["CRATER_THERMAL_CACHE"] = str(tmp / f"cache_{mode}")
            kind = mode.split("#")[0]  # "relaxed#2": the second run of a mode (repeats alternate in one run)
            scheme = "extrapolated" if kind == "stepper" else "relaxed"
            name = mode.replace("@", "_").replace("#", "_").replace("~", "_solves").replace("%", "_dask_defaults")
            case = config.load_case(write_case(tmp, name, args.facets, args.days, scheme, spinup))
            columns = None
            seen = {}
            kind, _, solves = kind.partition("~")  # "dask~2": 2 scattering solves in flight
            radiosity.ASYNC_SOLVES = int(solves) if solves else default_solves
            dask_defaults = kind.endswith("%")  # "dask%": dask's own settings for the local cluster
            kind = kind.rstrip("%")
            cluster.LOCAL_CLUSTER_CONFIG = {} if dask_defaults else default_config
            if kind.startswith("dask"):  # "dask", or "dask@N": chunks of at most N facets
                chunk_facets = int(kind.split("@")[1]) if "@" in kind else args.chunk_facets
                columns = observed_columns(args.workers, chunk_facets, seen)
            timer = simulate.Timer()
            load = LoadSampler()
            load.start()
            t0, c0 = time.perf_counter(), os.times()
            out = runner.run_case(case, tmp / f"{name}.nc", progress=False, timer=timer, columns=columns)
            wall = time.perf_counter() - t0
            c1 = os.times()
            load.stop.set()
            with io.open_run(out) as ds:
                temps[mode] = ds["surface_temperature"].values.astype(float)
                nf, nt = ds.sizes["facet"], ds.sizes["time"]
                night = (ds["solar_direct"].values == 0.0).all(axis=0)  # facets never in direct sunlight
                rel = ds.attrs.get("relaxation")
                rel = json.loads(rel) if isinstance(rel, str) else rel
                entry = {
                    "wall_s": wall,
                    "stages_s": dict(timer.split),
                    "periodic_iterations": int(ds.attrs.get("spinup_iterations", -1)),
                    "loadavg_mean": float(np.mean(load.samples)) if load.samples else None,
                    "loadavg_max": float(np.max(load.samples)) if load.samples else None,
                    "process_cpu_s": round((c1.user - c0.user) + (c1.system - c0.system), 2),
                }
                if "tasks" in seen:
                    entry["workers"] = task_summary(seen["tasks"], wall)
                if rel:
                    for key in ("spinup_iterations_per_window", "record_iterations_per_window"):
                        its = rel.get(key) or [0]
                        entry[key.replace("_per_window", "")] = {"mean": float(np.mean(its)), "max": int(max(its))}
                    entry["columns"] = rel["columns"]
            result["facets"], result["samples"] = nf, nt
            result["modes"][mode] = entry
            entry["async_solves"] = radiosity.ASYNC_SOLVES
            if columns is not None:
                entry["local_cluster_config"] = cluster.LOCAL_CLUSTER_CONFIG
            print(mode, json.dumps(entry), flush=True)
            out.unlink()
    diffs = {}
    for a in temps:
        for b in temps:
            if a < b:
                d = np.abs(temps[a] - temps[b])
                diffs[f"{a}-{b}"] = {"max_K": float(d.max()), "shadow_max_K": float(d[:, night].max())}
    result["max_differences"] = diffs
    m = result["modes"]
    for mode in m:
        kind, _, rep = mode.partition("#")
        base = "relaxed" + (f"#{rep}" if rep else "")  # a repeat pairs with the relaxed run of its number
        if kind.startswith("dask") and base in m:
            key = "efficiency_relaxed_over_dask" + kind[4:].replace("@", "_chunk_facets_") + (f"_{rep}" if rep else "")
            result[key] = m[base]["wall_s"] / m[mode]["wall_s"]
    if "dask" in m and "stepper" in m:
        result["efficiency_stepper_over_dask"] = m["stepper"]["wall_s"] / m["dask"]["wall_s"]
    if "relaxed" in m and "stepper" in m:
        result["relaxed_over_stepper_wall"] = m["relaxed"]["wall_s"] / m["stepper"]["wall_s"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
