"""Benchmark: one recorded year of the same synthetic crater at ~10k, 30k and 100k facets (issue 13).

Run:  PYTHONPATH=$PWD python bench/scale.py [--sizes 10000 30000 100000] [--sun-method horizon]
                                              [--view-factors compressed] [--quick] [--chunk-mb MB]

Each size runs in its own process (``--one N``): the idealized 10 km crater of the mesh generator
(thesis Table 7.1 profile) with a 5 km flat surround, N facets, at 86 S; everything from the mesh to
run.nc through ``runner.run_case`` (mesh and ray-tracing scene, view factors / radiation operator,
horizon map, Sun directions, direct sunlight, scattering, spin-up, record, I/O). Per stage: wall time
and the peak resident set reached inside it (the kernel's high-water mark, reset at each stage start
through ``/proc/self/clear_refs``); per size: the process's peak resident set (``VmHWM``;
``ru_maxrss`` of the children as a cross-check), and the run's peak on disk (``disk_peak_mb``: the
scratch store and run.nc, the cache left out, sampled every second) beside ``runner.scratch_estimate``'s
count (``disk_estimate_mb``).

Full mode (default): one recorded year (2019) at 4 h steps from the converged start, the periodic
state over the preceding year; the numbers are measured, nothing is scaled.

``--quick``: the same meshes and every once-per-mesh stage (mesh, view factors / operator, horizon map)
in full, but a short record (``--record-days``, default 5) after a one-day fixed spin-up, and the year
is extrapolated from measured per-step costs at that size: sunlight, scattering, ephemeris and I/O per
flux sample x (spin-up year + record year); conduction per coupled step (from the record) x
(``--windows`` periodic windows + 1 record) x 2190 steps; plus ``--windows`` quasi-Newton passes of the
periodic shooting, each timed once on N columns (the eigen-decompositions of ``thermal.periodic_state``).
Each child first runs a 300-facet crater for a day, untimed (imports, numba compilation, ephemeris tables).
``--windows`` defaults to 5, what the periodic start took on these meshes in full and short runs
(1000-2000 facets: 5) and in ``bench/thesis.py`` (4 iterations + the final map). ``extrapolated`` says
which numbers were; ``measured_total_s`` / ``measured_stages_s`` keep the raw ones. Peak memory is as
measured: a streamed run holds blocks of the chunk budget and the per-mesh operators, not the run's
length, so a longer run does not raise it.

Growth exponents between the two largest sizes: ``log(y2 / y1) / log(N2 / N1)`` for the (year) time and
the peak memory; ``consecutive_exponents`` gives them between every pair of consecutive sizes (e.g.
``--sizes 100000 1000000``: the one pair the issue's target is about).

The fallback where a size cannot fit: before each size after the first, its peak memory is estimated
from the largest size measured so far with the memory exponent of the last two (or
``--memory-exponent``, default 1.75, the operator's measured growth, with one size measured). If the
estimate exceeds ``--max-memory-gb`` (default: the machine's physical memory), that size runs in the
quick mode with a lunar day recorded (``--fallback-days``, 29.53): the operator, the horizon map and
a lunar day are built and measured, the year extrapolated from them (``mode``, ``fallback_reason``,
``estimated_peak_mb`` in the JSON). A child that fails (killed for memory, an exception) is recorded
with its exit status and the tail of its stderr (``failed``) and the sizes after it still run.

The machine is shared: ``loadavg`` holds ``os.getloadavg()`` at the start and end of
each size. The last stdout line is one JSON object, also written to ``bench/results/scale.json``.
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

import numpy as np

YEAR_S = 365.25 * 86400.0
STEP_S = 4 * 3600.0
YEAR_STEPS = int(round(YEAR_S / STEP_S))  # coupled steps of a year at 4 h
#: Stages paid once per mesh, whatever the run's length; every other stage is time-stepped.
FIXED_STAGES = ("geometry", "viewfactors", "operator", "horizons")

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
{spinup}
[steps]
flux_step_hours = 4.0
[surface]
albedo = 0.12
emissivity = 0.95
{extra}
[output]
chunk_mb = {chunk_mb}
checkpoint_interval_steps = 0
"""


#: The periodic start over the year before the record that every scale run uses.
PERIODIC_SPINUP = 'spinup = "periodic"\nspinup_years = 1.0'


def format_case(chunk_mb: float | None, **fields) -> str:
    """:data:`CASE` with ``fields``; ``chunk_mb`` [MB] None leaves ``[output] chunk_mb`` out (the run's
    default budget, ``simulate.default_chunk_mb``)."""
    text = CASE.format(chunk_mb=chunk_mb, **fields)
    return text.replace("chunk_mb = None\n", "") if chunk_mb is None else text


def scale_mesh(facets: int):
    """The scale crater's mesh at ``facets`` facets (as a run of :func:`case_text` makes it)."""
    from crater_thermal import config, simulate

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "case.toml"
        path.write_text(case_text(facets, end="2019-01-02T00:00"))
        return simulate.case_mesh(config.load_case(path))


def case_text(facets: int, end: str, spinup: str = PERIODIC_SPINUP, chunk_mb: float | None = None) -> str:
    """The scale crater's case file (10 km crater, 5 km flat surround, 86 S, the defaults) at ``facets``
    facets, recorded from 2019-01-01 to ``end`` (ISO) after ``spinup`` (TOML lines of ``[period]``)."""
    return format_case(
        chunk_mb, facets=facets, diameter_km=10.0, surround_km=5.0, lat_deg=-86.0, extra="", end=end, spinup=spinup
    )


class DiskSampler:
    """The largest total size [B] of the files under ``folder`` (the run's scratch store and run.nc;
    ``skip``: top-level names not counted, e.g. the cache), sampled every ``every_s`` seconds on a thread
    while in the ``with`` block."""

    def __init__(self, folder: Path, skip=(), every_s: float = 1.0):
        import threading

        self.folder, self.skip, self.every_s = Path(folder), set(skip), every_s
        self.peak_B, self._stop = 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _size(self) -> int:
        total = 0
        for root, dirs, files in os.walk(self.folder):
            if root == str(self.folder):
                dirs[:] = [d for d in dirs if d not in self.skip]
            for f in files:
                try:
                    total += os.stat(os.path.join(root, f)).st_size
                except FileNotFoundError:  # renamed or deleted meanwhile
                    pass
        return total

    def _run(self):
        while not self._stop.is_set():
            self.peak_B = max(self.peak_B, self._size())
            self._stop.wait(self.every_s)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_B = max(self.peak_B, self._size())


def _disk_estimate_mb(case, nf: int, ns: int, nt: int) -> dict | None:
    """``runner.scratch_estimate`` of the run [MB] (None for code that has none)."""
    from crater_thermal import runner

    est = getattr(runner, "scratch_estimate", None)
    if est is None:
        return None
    from crater_thermal import simulate

    block = simulate.block_rows(nf, simulate.chunk_bytes(case, nf))
    return {k: v / 2**20 for k, v in est(case, nf, ns, nt, case.steps.ir_coupling, block=block).items()}


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


def quasi_newton_pass_s(n_cols: int) -> float:
    """Wall time [s] of one quasi-Newton pass of the periodic shooting over ``n_cols`` columns (the
    per-column eigen-decompositions of ``thermal.periodic_state``, one BLAS thread, same chunks)."""
    from threadpoolctl import threadpool_limits

    from crater_thermal import thermal
    from crater_thermal.constants import SIGMA

    solver = thermal.ColumnSolver(["1300/1800"] * n_cols)
    solver.set_uniform(100.0)
    Tm = solver.state()
    h = np.full(n_cols, 4 * 0.95 * SIGMA * 100.0**3)
    dt = np.full(n_cols, 1800.0)
    t0 = time.perf_counter()
    with threadpool_limits(1, user_api="blas"):
        for c0 in range(0, n_cols, 4096):
            cols = np.arange(c0, min(n_cols, c0 + 4096))
            solver.linear_modes(Tm, h[cols], dt[cols], cols)
    return time.perf_counter() - t0


def _watch_spinup():
    """Time each pass through the spin-up window (lagged or coupled) and keep the periodic shooting's
    diagnostics: returns (list filled with {"kind", "s", "columns"} per pass, dict filled with the last
    ``thermal.periodic_state`` result). Installed after the warm-up run, so only the measured run fills them;
    ``bench/spinup_passes.py`` installs it too."""
    from crater_thermal import simulate, thermal

    passes: list = []
    shooting: dict = {}
    for kind in ("lagged", "coupled"):
        inner = getattr(simulate._SpinUpWindow, kind)

        def timed(self, report, expected, inner=inner, kind=kind):
            t0 = time.perf_counter()
            inner(self, report, expected)
            ran = getattr(self, "columns_run", None)  # (older versions, run by bench/spinup_passes.py, lack it)
            cols = ran[-1] if kind == "lagged" and ran else None
            passes.append({"kind": kind, "s": time.perf_counter() - t0, "columns": cols})

        setattr(simulate._SpinUpWindow, kind, timed)
    periodic_state = thermal.periodic_state

    def keep(*a, **k):
        out = periodic_state(*a, **k)
        shooting.clear()
        shooting.update(out)
        return out

    simulate.thermal.periodic_state = keep
    return passes, shooting


def run_one(args) -> dict:
    """One size, in this process: build the case, run it, report stage times and memory."""
    from crater_thermal import config, progress, runner, simulate

    class StageTimer(simulate.Timer):
        """The run's own time split, plus the peak RSS reached inside each stage [MB]."""

        def __init__(self):
            super().__init__()
            self.peak_mb: dict = {}
            self.cpu_s: dict = {}  # process CPU seconds (all threads) inside each stage
            self.run_peak_mb = _status_kb("VmHWM") / 1024.0  # the whole run's, across the resets
            self.can_reset = _reset_peak()

        @contextmanager
        def __call__(self, name):
            if self.can_reset:
                self.run_peak_mb = max(self.run_peak_mb, _status_kb("VmHWM") / 1024.0)
                _reset_peak()
            c0 = time.process_time()
            with super().__call__(name):
                yield
            self.cpu_s[name] = self.cpu_s.get(name, 0.0) + time.process_time() - c0
            peak = _status_kb("VmHWM") / 1024.0
            self.peak_mb[name] = max(self.peak_mb.get(name, 0.0), peak)

    extra = f'[sun]\nmethod = "{args.sun_method}"\n' if args.sun_method else ""
    extra += f'[radiation]\nview_factors = "{args.view_factors}"\n' if args.view_factors else ""
    if args.quick:
        days = args.record_days
        spinup = 'spinup = "fixed"\nspinup_days = 1.0\ninitial_temperature_K = 100.0'
    else:
        days = 365.0
        spinup = 'spinup = "periodic"\nspinup_years = 1.0'
    end = str(np.datetime64("2019-01-01T00:00") + np.timedelta64(int(round(days * 86400)), "s"))
    with tempfile.TemporaryDirectory(prefix="scale_", dir=args.workdir) as tmp:
        tmp = Path(tmp)
        case_path = tmp / "case.toml"
        case_path.write_text(
            format_case(
                args.chunk_mb,
                facets=args.one,
                diameter_km=args.diameter_km,
                surround_km=args.surround_km,
                lat_deg=args.lat_deg,
                extra=extra,
                end=end,
                spinup=spinup,
            )
            + ("save_spinup_fluxes = false\n" if args.no_spinup_fluxes else "")
        )
        os.environ.setdefault("CRATER_THERMAL_CACHE", str(tmp / "cache"))  # a cold cache: every stage is paid
        # warm-up on a small crater (not timed): imports, numba compilation or cache loads, ephemeris tables
        warm = tmp / "warm.toml"
        warm.write_text(
            format_case(
                args.chunk_mb,
                facets=300,
                diameter_km=args.diameter_km,
                surround_km=args.surround_km,
                lat_deg=args.lat_deg,
                extra=extra,
                end="2019-01-02T00:00",
                spinup='spinup = "fixed"\nspinup_days = 1.0',
            )
        )
        runner.run_case(config.load_case(warm), tmp / "warm.nc")
        passes, shooting = _watch_spinup()
        case = config.load_case(case_path)
        timer = StageTimer()
        rss0 = _status_kb("VmRSS") / 1024.0
        load0 = os.getloadavg()
        reporter = progress.reporter(True) if args.progress else None
        t0 = time.perf_counter()
        with DiskSampler(tmp, skip=("cache",)) as disk:
            out = runner.run_case(case, tmp / "run.nc", progress=reporter, timer=timer)
        total = time.perf_counter() - t0
        # VmHWM is reset at each stage's start: the run's peak is the largest seen before any reset
        peak = max(timer.run_peak_mb, _status_kb("VmHWM") / 1024.0)
        size_mb = out.stat().st_size / 2**20
        import xarray as xr

        with xr.open_dataset(out) as ds:
            nf, nt = ds.sizes["facet"], ds.sizes["time"]
            ns = ds.sizes.get("spinup_time", 0)
            iterations = int(ds.attrs.get("spinup_iterations", -1))
    res = {
        "facets": nf,
        "samples": nt,
        "spinup_samples": ns,
        "total_s": total,
        "stages_s": dict(timer.split),
        "stage_peak_mb": timer.peak_mb,
        "stage_cpu_s": timer.cpu_s,
        "peak_memory_mb": peak,
        "periodic_iterations": iterations,
        "spinup_passes": passes,
        "residual_history_K": [float(h) for h in shooting.get("history_K", [])],
        "run_nc_mb": size_mb,
        "disk_peak_mb": disk.peak_B / 2**20,
        "disk_estimate_mb": _disk_estimate_mb(case, nf, ns, nt),
        "rss_before_run_mb": rss0,
        "loadavg": [list(load0), list(os.getloadavg())],
    }
    if args.quick:
        res["quasi_newton_pass_s"] = quasi_newton_pass_s(nf)
    return res


def extrapolate_year(res: dict, args, quick: bool | None = None) -> dict:
    """The year's stage times from a quick run (see the module docstring); a full run as measured."""
    if not (args.quick if quick is None else quick):
        return {"extrapolated": False, "year_s": res["total_s"], "year_stages_s": dict(res["stages_s"])}
    n_run = res["samples"] + max(res["spinup_samples"] - 1, 0)  # flux samples computed in the quick run
    n_year = 2 * YEAR_STEPS + 1  # spin-up year + recorded year, the join sample once
    conduction_step_s = res["stages_s"].get("conduction_record", 0.0) / max(1, res["samples"] - 1)
    stages = {}
    for name, secs in res["stages_s"].items():
        if name in FIXED_STAGES:
            stages[name] = secs
        elif name == "conduction_spinup":
            stages[name] = args.windows * YEAR_STEPS * conduction_step_s + args.windows * res["quasi_newton_pass_s"]
        elif name == "conduction_record":
            stages[name] = YEAR_STEPS * conduction_step_s
        else:  # sunlight, scattering, ephemeris, I/O: per flux sample
            stages[name] = secs * n_year / n_run
    untimed = res["total_s"] - sum(res["stages_s"].values())  # solver set-up, checkpoints outside timers
    return {
        "extrapolated": True,
        "year_s": sum(stages.values()) + untimed,
        "year_stages_s": stages,
        "conduction_step_s": conduction_step_s,
    }


def exponent(x, y) -> float:
    """Growth exponent between the two largest sizes: log(y2 / y1) / log(x2 / x1)."""
    (x1, y1), (x2, y2) = sorted(zip(x, y))[-2:]
    return math.log(y2 / y1) / math.log(x2 / x1)


def consecutive_exponents(facets, total, peak) -> list:
    """Growth exponents of the year's time and the peak memory between each pair of consecutive sizes."""
    order = sorted(range(len(facets)), key=lambda i: facets[i])
    out = []
    for i, j in zip(order, order[1:]):
        if facets[j] == facets[i]:
            continue
        d = math.log(facets[j] / facets[i])
        out.append(
            {
                "facets": [facets[i], facets[j]],
                "time_exponent": math.log(total[j] / total[i]) / d,
                "memory_exponent": math.log(peak[j] / peak[i]) / d,
            }
        )
    return out


def machine_memory_mb() -> float:
    """Physical memory of this machine [MB] (``/proc/meminfo`` MemTotal; nan where unknown)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemTotal:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def estimated_peak_mb(results: list, n: int, default_exponent: float) -> float | None:
    """Peak memory [MB] of ``n`` facets extrapolated from the sizes measured (None before the first)."""
    done = sorted((r["facets"], r["peak_memory_mb"]) for r in results)
    if not done:
        return None
    if len(done) >= 2 and done[-1][0] != done[-2][0]:
        (x1, y1), (x2, y2) = done[-2:]
        expo = max(math.log(y2 / y1) / math.log(x2 / x1), 1.0)
    else:
        expo = default_exponent
    x, y = done[-1]
    return y * (n / x) ** expo


def summarize(results: list, args, failed: list | None = None) -> dict:
    """The JSON summary of the sizes finished so far (``failed``: the sizes whose run did not finish)."""
    facets = [r["facets"] for r in results]
    total = [r["year_s"] for r in results]
    peak = [r["peak_memory_mb"] for r in results]
    summary = {
        "benchmark": "scale",
        "facets": facets,
        "total_s": total,
        "peak_memory_mb": peak,
        "time_exponent": exponent(facets, total) if len(results) >= 2 else None,
        "memory_exponent": exponent(facets, peak) if len(results) >= 2 else None,
        "consecutive_exponents": consecutive_exponents(facets, total, peak),
        "mode": [r["mode"] for r in results],
        "fallback_reason": [r.get("fallback_reason") for r in results],
        "estimated_peak_mb": [r.get("estimated_peak_mb") for r in results],
        "failed": failed or [],
        "stages_s": [r["year_stages_s"] for r in results],
        "extrapolated": [r["extrapolated"] for r in results],
        "measured_total_s": [r["total_s"] for r in results],
        "measured_stages_s": [r["stages_s"] for r in results],
        "stage_peak_mb": [r["stage_peak_mb"] for r in results],
        "stage_cpu_s": [r.get("stage_cpu_s") for r in results],
        "conduction_step_s": [r.get("conduction_step_s") for r in results],
        "quasi_newton_pass_s": [r.get("quasi_newton_pass_s") for r in results],
        "periodic_iterations": [r["periodic_iterations"] for r in results],
        "spinup_passes": [r.get("spinup_passes") for r in results],
        "residual_history_K": [r.get("residual_history_K") for r in results],
        "samples": [r["samples"] for r in results],
        "run_nc_mb": [r["run_nc_mb"] for r in results],
        "disk_peak_mb": [r.get("disk_peak_mb") for r in results],
        "disk_estimate_mb": [r.get("disk_estimate_mb") for r in results],
        "rss_before_run_mb": [r["rss_before_run_mb"] for r in results],
        "ru_maxrss_children_mb": [r["ru_maxrss_children_mb"] for r in results],
        "loadavg": [r["loadavg"] for r in results],
        "case": {
            "diameter_km": args.diameter_km,
            "surround_km": args.surround_km,
            "lat_deg": args.lat_deg,
            "flux_step_hours": 4.0,
            "mode": "quick (year extrapolated)" if args.quick else "full year",
            "record_days": args.record_days if args.quick else 365.0,
            "windows_assumed": args.windows if args.quick else None,
            "sun_method": args.sun_method or "case default",
            "view_factors": args.view_factors or "case default",
            "chunk_mb": args.chunk_mb if args.chunk_mb is not None else "case default",
            "save_spinup_fluxes": not args.no_spinup_fluxes,
        },
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
        "targets": {
            "issue_24": {"100k_total_s": 600, "100k_peak_mb": 4096, "1M_total_s": 7200, "1M_peak_mb": 16384},
            "exponent_100k_1M": 1.15,
        },
        "max_memory_mb": args.max_memory_gb * 1024.0,
    }
    return summary


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 30_000, 100_000])
    ap.add_argument("--diameter-km", type=float, default=10.0)
    ap.add_argument("--surround-km", type=float, default=5.0)
    ap.add_argument("--lat-deg", type=float, default=-86.0)
    ap.add_argument("--sun-method", default=None, help="[sun] method of the case (default: the case default)")
    ap.add_argument(
        "--view-factors", default=None, help="[radiation] view_factors of the case (default: the case default)"
    )
    ap.add_argument(
        "--no-spinup-fluxes",
        action="store_true",
        help="[output] save_spinup_fluxes = false (run.nc without the spin-up year's fluxes; less disk)",
    )
    ap.add_argument("--chunk-mb", type=float, default=None, help="[output] chunk_mb [MB] (default: the run's own)")
    ap.add_argument("--quick", action="store_true", help="short run, the year extrapolated (module docstring)")
    ap.add_argument("--record-days", type=float, default=5.0, help="--quick: recorded days")
    ap.add_argument("--windows", type=int, default=5, help="--quick: periodic windows assumed for the start")
    ap.add_argument(
        "--max-memory-gb",
        type=float,
        default=machine_memory_mb() / 1024.0,
        help="a size whose estimated peak exceeds this runs the fallback (module docstring)",
    )
    ap.add_argument("--memory-exponent", type=float, default=1.75, help="memory growth assumed with one size done")
    ap.add_argument("--fallback-days", type=float, default=29.53, help="recorded days of the fallback run")
    ap.add_argument("--workdir", default=None, help="folder for the runs' files (default: the system temp)")
    ap.add_argument("--progress", action="store_true", help="progress bars of the runs (on stderr)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "scale.json"))
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.one is not None:
        print(json.dumps(run_one(args)))
        return {}

    results, failed = [], []
    for n in args.sizes:
        estimate = estimated_peak_mb(results, n, args.memory_exponent)
        fallback = estimate is not None and not args.quick and estimate > args.max_memory_gb * 1024.0
        quick = args.quick or fallback
        record_days = args.fallback_days if fallback else args.record_days
        cmd = [
            sys.executable,
            __file__,
            "--one",
            str(n),
            "--diameter-km",
            str(args.diameter_km),
            "--surround-km",
            str(args.surround_km),
            "--lat-deg",
            str(args.lat_deg),
            "--record-days",
            str(record_days),
            "--windows",
            str(args.windows),
        ]
        for flag, value in (
            ("--sun-method", args.sun_method),
            ("--view-factors", args.view_factors),
            ("--workdir", args.workdir),
            ("--chunk-mb", None if args.chunk_mb is None else str(args.chunk_mb)),
        ):
            if value:
                cmd += [flag, value]
        cmd += ["--quick"] if quick else []
        cmd += ["--progress"] if args.progress else []
        cmd += ["--no-spinup-fluxes"] if args.no_spinup_fluxes else []
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
        wall = time.perf_counter() - t0
        sys.stderr.write(proc.stderr if args.progress else "")
        if proc.returncode != 0:
            failed.append(
                {
                    "requested_facets": n,
                    "exit_status": proc.returncode,
                    "wall_s": wall,
                    "estimated_peak_mb": estimate,
                    "mode": "fallback" if fallback else ("quick" if quick else "full year"),
                    "stderr_tail": proc.stderr[-2000:],
                }
            )
            print(f"# size {n}: the run failed (exit {proc.returncode})", file=sys.stderr, flush=True)
            if args.out:
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                Path(args.out).write_text(json.dumps(summarize(results, args, failed), indent=1) + "\n")
            continue
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        res["requested_facets"] = n
        res["process_wall_s"] = wall
        res["estimated_peak_mb"] = estimate
        if fallback:
            res["mode"] = f"fallback: operator, horizon map and {record_days:g} recorded days, year extrapolated"
            res["fallback_reason"] = (
                f"estimated peak {estimate:.0f} MB > --max-memory-gb {args.max_memory_gb:g} GB for a full year"
            )
        else:
            res["mode"] = "quick (year extrapolated)" if quick else "full year"
        res.update(extrapolate_year(res, args, quick))
        # the largest peak RSS of any child so far [MB] (a cross-check of VmHWM)
        res["ru_maxrss_children_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        results.append(res)
        if args.out:  # after every size: a run stopped before the largest one keeps the others
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(summarize(results, args, failed), indent=1) + "\n")
        stages = json.dumps({k: round(v, 1) for k, v in res["stages_s"].items()})
        print(
            f"# {res['facets']} facets: measured {res['total_s']:.1f} s, year {res['year_s']:.0f} s, "
            f"peak {res['peak_memory_mb']:.0f} MB, stages {stages}",
            file=sys.stderr,
            flush=True,
        )

    summary = summarize(results, args, failed)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
