"""Many cases: runs and their replays in parallel local processes, or on a dask.distributed cluster.

Each case ``NAME.toml`` writes ``OUT/NAME/run.nc`` and, when the case lists profiles to replay,
``OUT/NAME/replay.nc``. A case whose outputs already exist is skipped, so an interrupted sweep
restarted with the same command finishes only what is missing (a half-finished run resumes from
its checkpoint).

Local workers are started with the ``spawn`` method (fresh interpreters): forking a process whose
numba/GNU OpenMP thread pool is already running is not safe. A cluster needs the ``distributed``
extra; an unreachable scheduler is reported in one line after :data:`SCHEDULER_TIMEOUT_S`.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Sequence

from crater_thermal.errors import ConfigError
from crater_thermal.extras import connect_scheduler
from crater_thermal.progress import bar

#: Seconds to wait for a dask scheduler to answer before giving up [s].
SCHEDULER_TIMEOUT_S = 5.0


def case_outputs(case_path, out_dir) -> tuple[Path, Path]:
    """``(run.nc, replay.nc)`` paths of a case inside the sweep's output folder."""
    folder = Path(out_dir) / Path(case_path).stem
    return folder / "run.nc", folder / "replay.nc"


def run_one(case_path: str, out_dir: str) -> dict:
    """Run one case and its replays; skip the parts already written. Returns a summary dict."""
    import warnings

    from crater_thermal import config, runner
    from crater_thermal.progress import one_line_warning

    warnings.showwarning = one_line_warning  # a worker's warnings read as the command's own: one line each
    if multiprocessing.parent_process() is not None:  # a local worker: SIGTERM from the sweep cleans up
        _clean_exit_on_sigterm()
    t0 = time.perf_counter()
    case = config.load_case(case_path)
    run_nc, replay_nc = case_outputs(case_path, out_dir)
    done = []
    if not run_nc.exists():
        ckpt = Path(runner.checkpoint_path(run_nc))
        runner.run_case(case, run_nc, resume=ckpt.exists(), progress=False)
        done.append("run")
    labels = list(case.replay.profiles)
    grid = case.replay.density_grid
    if (labels or grid) and not replay_nc.exists():
        fixed = case.period.spinup == "fixed"  # replay as the run started (thesis procedure)
        runner.replay_file(
            run_nc,
            labels,
            density_grid=grid,
            output=replay_nc,
            progress=False,
            initial_temperature=case.period.initial_temperature_K if fixed else None,
            fixed_spinup=fixed,
        )
        done.append("replay")
    return {
        "case": str(case_path),
        "run": str(run_nc),
        "replay": str(replay_nc) if (labels or grid) else None,
        "done": done,
        "skipped": not done,
        "seconds": time.perf_counter() - t0,
    }


def sweep(
    case_paths: Sequence[str],
    out_dir,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool | None = None,
) -> list[dict]:
    """Run every case (and its replays) into ``out_dir``.

    Parameters
    ----------
    scheduler : address of an existing dask.distributed scheduler (``tcp://host:8786``); None runs
        local processes.
    workers : local processes (default: the number of cores, at most the number of cases).
    """
    from crater_thermal import config

    paths = [str(p) for p in case_paths]
    if not paths:
        raise ConfigError("sweep: no case files given")
    names = [Path(p).stem for p in paths]
    if len(set(names)) != len(names):
        raise ConfigError("sweep: case file names must be unique (they name the output folders)")
    for p in paths:  # validate every case before starting any work
        config.load_case(p)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    results = []
    client = _connect(scheduler) if scheduler else None
    with bar("sweep", progress) as report:
        if client is not None:
            from distributed import as_completed as dask_completed  # present: _connect imported it

            with client:
                futures = client.map(run_one, paths, [str(out_dir)] * len(paths), pure=False)
                for fut in dask_completed(futures):
                    results.append(fut.result())
                    if report is not None:
                        report(len(results), len(paths))
        else:
            n = workers or min(len(paths), os.cpu_count() or 1)
            if n <= 1:
                for p in paths:
                    results.append(run_one(p, str(out_dir)))
                    if report is not None:
                        report(len(results), len(paths))
            else:
                spawn = multiprocessing.get_context("spawn")
                with ProcessPoolExecutor(max_workers=n, mp_context=spawn) as pool:
                    try:
                        futs = [pool.submit(run_one, p, str(out_dir)) for p in paths]
                        for fut in as_completed(futs):
                            results.append(fut.result())
                            if report is not None:
                                report(len(results), len(paths))
                    except BaseException:  # interrupted or failed: stop the workers now, each cleaning up
                        _stop_workers(pool)
                        raise
    return sorted(results, key=lambda r: paths.index(r["case"]))


def _connect(scheduler: str):
    """A dask.distributed client of the scheduler at ``scheduler`` (``tcp://host:8786``).

    Raises
    ------
    MissingExtraError
        dask.distributed is not installed.
    ConfigError
        No scheduler answers at that address within :data:`SCHEDULER_TIMEOUT_S`.
    """
    return connect_scheduler(
        scheduler,
        "sweeps on a dask cluster (--scheduler)",
        SCHEDULER_TIMEOUT_S,
        "leave out --scheduler to run on local processes",
    )


def _clean_exit_on_sigterm() -> None:
    """In a worker process: SIGTERM raises :class:`~crater_thermal.errors.Interrupted`, so that the case's
    writers remove their temporaries and release their locks (a checkpoint stays for the restart)."""
    import signal

    from crater_thermal.errors import Interrupted, note_interrupt

    def handler(signum, frame):
        note_interrupt(signum)
        raise Interrupted(signum)

    try:
        signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # not the main thread
        pass


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel the queued cases and send SIGTERM to the running workers, then wait for them to exit."""
    procs = list(getattr(pool, "_processes", {}).values())  # no public handle on the worker processes
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=30)
