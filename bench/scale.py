"""Benchmark: one recorded year of the same synthetic crater at ~10k, 30k and 100k facets (issue 13).

Run:  PYTHONPATH=$PWD python bench/scale.py [--sizes 10000 30000 100000] [--sun-method horizon]
                                              [--radiation METHOD] [--chunk-mb 256]

Each size runs in its own process (``--one N``): the idealized 10 km crater of the mesh generator
(thesis Table 7.1 profile) with a 5 km flat surround, N facets, at 86 S; one recorded year (2019) at 4 h
steps from the converged (periodic) start over the preceding year; everything from the mesh to run.nc
(``simulate.run_case``: mesh and ray-tracing scene, view factors / radiation operator, Sun directions,
direct sunlight, scattering, spin-up, record, I/O). Per stage: wall time and the peak resident set
reached inside it (the kernel's high-water mark, reset at each stage start through
``/proc/self/clear_refs``); per size: wall time and the process's peak resident set (``VmHWM``, with
``ru_maxrss`` of the finished child as a cross-check).

Growth exponents are fitted between the two largest sizes: ``log(t2 / t1) / log(N2 / N1)``, the same
for memory. The machine is shared: ``loadavg`` records ``os.getloadavg()`` at the start and end of each
size. Methods (``--sun-method``, ``--radiation``) are written into the case file when given, so the
script measures whatever the case schema offers; the defaults are the case defaults. The last stdout
line is one JSON object; it is also written to ``bench/results/scale.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

CASE = """
name = "scale_{facets}"
[crater]
kind = "crater"
diameter_km = {diameter_km}
facets = {facets}
surround_km = {surround_km}
[location]
lat_deg = {lat_deg}
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "{end}"
spinup = "periodic"
spinup_years = {spinup_years}
[steps]
flux_step_hours = 4.0
[surface]
albedo = 0.12
emissivity = 0.95
[sun]
{sun_extra}
[scattering]
{scattering_extra}
[output]
chunk_mb = {chunk_mb}
checkpoint_interval_steps = 0
"""


def _status_kb(key: str) -> float:
    """A ``/proc/self/status`` memory field [kB] (nan where there is no procfs)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1])
    except OSError:
        pass
    return math.nan


def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) to the current RSS; False where not supported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def run_one(args) -> dict:
    """One size, in this process: build the case, run it, report stage times and memory."""
    from crater_thermal import config, simulate

    class StageTimer(simulate.Timer):
        """The run's own time split, plus the peak RSS reached inside each stage [MB]."""

        def __init__(self):
            super().__init__()
            self.peak_mb: dict = {}
            self.can_reset = _reset_peak()

        @contextmanager
        def __call__(self, name):
            if self.can_reset:
                _reset_peak()
            with super().__call__(name):
                yield
            peak = _status_kb("VmHWM") / 1024.0
            self.peak_mb[name] = max(self.peak_mb.get(name, 0.0), peak)

    sun_extra = f'method = "{args.sun_method}"' if args.sun_method else ""
    scat_extra = f'method = "{args.radiation}"' if args.radiation else ""
    with tempfile.TemporaryDirectory(prefix="scale_", dir=args.workdir) as tmp:
        tmp = Path(tmp)
        case_path = tmp / "case.toml"
        case_path.write_text(CASE.format(facets=args.one, diameter_km=args.diameter_km, surround_km=args.surround_km,
                                         lat_deg=args.lat_deg, chunk_mb=args.chunk_mb, sun_extra=sun_extra,
                                         end=args.end, spinup_years=args.spinup_years,
                                         scattering_extra=scat_extra))
        os.environ.setdefault("CRATER_THERMAL_CACHE", str(tmp / "cache"))  # a cold cache: every stage is paid
        case = config.load_case(case_path)
        timer = StageTimer()
        rss0 = _status_kb("VmRSS") / 1024.0
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        out = simulate.run_case(case, tmp / "run.nc", progress=args.progress, timer=timer)
        total = time.perf_counter() - t0
        size_mb = out.stat().st_size / 2**20
        import xarray as xr

        with xr.open_dataset(out) as ds:
            nf, nt = ds.sizes["facet"], ds.sizes["time"]
            iterations = int(ds.attrs.get("spinup_iterations", -1))
    return {"facets": nf, "samples": nt, "total_s": total, "stages_s": dict(timer.split),
            "stage_peak_mb": timer.peak_mb, "peak_memory_mb": _status_kb("VmHWM") / 1024.0,
            "periodic_iterations": iterations, "run_nc_mb": size_mb, "rss_before_run_mb": rss0,
            "loadavg": [list(load0), list(os.getloadavg())]}


def exponent(x, y) -> float:
    """Growth exponent between the two largest sizes: log(y2 / y1) / log(x2 / x1)."""
    (x1, y1), (x2, y2) = sorted(zip(x, y))[-2:]
    return math.log(y2 / y1) / math.log(x2 / x1)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 30_000, 100_000])
    ap.add_argument("--diameter-km", type=float, default=10.0)
    ap.add_argument("--surround-km", type=float, default=5.0)
    ap.add_argument("--lat-deg", type=float, default=-86.0)
    ap.add_argument("--sun-method", default=None, help="[sun] method of the case (default: the case default)")
    ap.add_argument("--radiation", default=None, help="[scattering] method of the case (default: the case default)")
    ap.add_argument("--chunk-mb", type=float, default=256.0)
    ap.add_argument("--end", default="2020-01-01", help="end of the record (smoke tests only; default: one year)")
    ap.add_argument("--spinup-years", type=float, default=1.0, help="periodic window (smoke tests only)")
    ap.add_argument("--workdir", default=None, help="folder for the runs' files (default: the system temp)")
    ap.add_argument("--progress", action="store_true", help="progress bars of the runs (on stderr)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "scale.json"))
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.one is not None:
        print(json.dumps(run_one(args)))
        return {}

    results = []
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--one", str(n), "--diameter-km", str(args.diameter_km),
               "--surround-km", str(args.surround_km), "--lat-deg", str(args.lat_deg), "--chunk-mb", str(args.chunk_mb),
               "--end", args.end, "--spinup-years", str(args.spinup_years)]
        for flag, value in (("--sun-method", args.sun_method), ("--radiation", args.radiation),
                            ("--workdir", args.workdir)):
            if value:
                cmd += [flag, value]
        if args.progress:
            cmd.append("--progress")
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=dict(os.environ))
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"size {n}: the run failed (exit {proc.returncode})")
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        res["requested_facets"] = n
        res["process_wall_s"] = wall
        # every child so far: the largest peak RSS of any of them [MB] (a cross-check of VmHWM)
        res["ru_maxrss_children_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        results.append(res)
        print(f"# {res['facets']} facets: {res['total_s']:.1f} s, peak {res['peak_memory_mb']:.0f} MB, "
              f"stages {json.dumps({k: round(v, 1) for k, v in res['stages_s'].items()})}", file=sys.stderr)

    facets = [r["facets"] for r in results]
    total = [r["total_s"] for r in results]
    peak = [r["peak_memory_mb"] for r in results]
    summary = {
        "benchmark": "scale",
        "facets": facets,
        "total_s": total,
        "peak_memory_mb": peak,
        "time_exponent": exponent(facets, total) if len(results) >= 2 else None,
        "memory_exponent": exponent(facets, peak) if len(results) >= 2 else None,
        "stages_s": [r["stages_s"] for r in results],
        "stage_peak_mb": [r["stage_peak_mb"] for r in results],
        "periodic_iterations": [r["periodic_iterations"] for r in results],
        "samples": [r["samples"] for r in results],
        "run_nc_mb": [r["run_nc_mb"] for r in results],
        "rss_before_run_mb": [r["rss_before_run_mb"] for r in results],
        "loadavg": [r["loadavg"] for r in results],
        "case": {"diameter_km": args.diameter_km, "surround_km": args.surround_km, "lat_deg": args.lat_deg,
                 "record": f"2019-01-01 .. {args.end}", "flux_step_hours": 4.0,
                 "spinup_years": args.spinup_years, "start": "periodic over the preceding year",
                 "sun_method": args.sun_method or "case default", "radiation": args.radiation or "case default",
                 "chunk_mb": args.chunk_mb},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
        "targets": {"100k_total_s": 1800, "100k_peak_mb": 8192, "exponent_30k_100k": 1.2},
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
