"""A replay on a dask.distributed cluster: (profile x facet) columns in chunks, solved by workers.

Each chunk (a block of facets x a block of profiles) is one dask task, a pure function of the flux
store's path, the chunk's facet range, its profiles and the options: the worker opens the flux store
by path (so every worker must be able to read it at that path: a shared filesystem) and reads only its
facets (the command checked the whole file once; a task refuses a file whose size or modification time
changed since, :func:`crater_thermal.io.open_checked`), replays the
chunk's columns with :func:`crater_thermal.simulate.replay_fluxes` and returns the float32 surface
temperatures to the client. The client saves each chunk as it arrives, atomically, in the chunk
folder ``OUT.chunks/`` beside the output (workers write nothing), then assembles the chunks into the
same replay dataset a local replay writes and removes the folder.

Each column's periodic start converges on its own (``thermal.periodic_state(per_column=True)``) and
its equilibrium estimate sums the samples in the same order whatever the batch, so a column's
temperatures do not depend on which chunk it is in: the assembled replay equals a local one.

A worker that fails or is lost mid-task has its task re-run by the scheduler (``retries`` for errors
raised by the task; lost workers are rescheduled by dask itself). A client that is killed leaves its
finished chunks and the folder's fingerprint (inputs, profiles, options, chunking); the same command
with ``resume=True`` (``--resume``) keeps them and computes only the others.

dask is imported only here, inside the functions that need it; a local replay never imports it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from crater_thermal import heap, io, runner, simulate
from crater_thermal.errors import ConfigError, OutputExistsError
from crater_thermal.extras import connect_scheduler, missing_extra

#: Seconds to wait for a dask scheduler to answer before giving up [s].
CONNECT_TIMEOUT_S = 10.0
#: Default facets per chunk (one dask task).
CHUNK_FACETS = 2000
#: Default profiles per chunk (one dask task).
CHUNK_PROFILES = 8
#: dask settings of a local cluster's processes (``--workers``; a remote cluster's are its own): the
#: workers' statistical profiler off (a sample of each worker's stack every 10 ms, for a dashboard that a
#: local cluster does not serve), and dask's housekeeping (event-loop ticks, system and memory monitors)
#: less often. An idle local cluster of 2 workers took 2.4-3.0 CPU-seconds per 20 s with dask's defaults
#: and 0.4 with these (docs/cluster.md), CPU that the workers and the command share on one machine.
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "500ms",
}
#: Name of the worker plugin that has a session's workers reuse large temporaries from their heap.
HEAP_PLUGIN = "crater_thermal-heap-reuse"


def connect(
    scheduler: str | None = None,
    workers: int | None = None,
    purpose: str = "replays on a dask cluster (--scheduler, --workers)",
):
    """A dask.distributed client: of the scheduler at ``scheduler`` (``tcp://host:8786``), or of a new
    local cluster of ``workers`` processes with one thread each. ``purpose``: what needs it (plural),
    for the error when dask.distributed is missing.

    The workers reuse large temporaries from their heap while the client is open (:func:`_heap_plugin`).

    Returns
    -------
    (client, cluster) : the cluster is None for a remote scheduler (close both with :func:`disconnect`).

    Raises
    ------
    MissingExtraError
        dask.distributed is not installed.
    ConfigError
        The scheduler does not answer within :data:`CONNECT_TIMEOUT_S`, or ``workers`` < 1.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise missing_extra("dask.distributed", "distributed", purpose) from None
    if scheduler:
        client = connect_scheduler(scheduler, purpose, CONNECT_TIMEOUT_S, "leave out --scheduler")
        _register_heap_plugin(client)
        return client, None
    import dask

    with dask.config.set(LOCAL_CLUSTER_CONFIG):  # read as the processes start; the caller's config is kept
        cluster = LocalCluster(
            n_workers=int(workers),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": ":0"},  # its HTTP endpoints on a free port, not 8787
            silence_logs=logging.ERROR,  # not dask's warnings about the tasks an interrupted command cancels
        )
        client = Client(cluster)
    _register_heap_plugin(client)
    return client, cluster


def _register_heap_plugin(client) -> None:
    """Register :func:`_heap_plugin` with the client's scheduler; best effort: the plugin only saves time,
    and a scheduler or worker that refuses it (another dask version, a worker that cannot load it) leaves the
    workers as they were."""
    try:
        client.register_plugin(_heap_plugin(), name=HEAP_PLUGIN)
    except Exception:  # noqa: BLE001 - a speed-up only; the session works without it
        pass


def disconnect(client, cluster) -> None:
    """Close what :func:`connect` opened: a remote scheduler's workers get their own heap settings back
    (the plugin of :func:`_heap_plugin` is removed; best effort, a lost scheduler is not an error), then
    the client and a local cluster are closed."""
    try:
        if cluster is None:
            client.unregister_worker_plugin(HEAP_PLUGIN)
    except Exception:  # noqa: BLE001 - the scheduler or the plugin may be gone; closing goes on
        pass
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _heap_plugin():
    """A dask worker plugin: while it is registered, the worker process takes its large temporaries from
    its heap and reuses them (:func:`crater_thermal.heap.reuse_large_blocks`, as a local run does), instead
    of a fresh memory map per array. Measured on a coupled 30k year on a local cluster: the workers' busy
    seconds 165 -> 137 (docs/cluster.md). Removing the plugin restores glibc's defaults in the worker."""
    from distributed import WorkerPlugin

    class HeapReuse(WorkerPlugin):
        name = HEAP_PLUGIN

        def setup(self, worker):
            self._held = contextlib.ExitStack()
            self._held.enter_context(heap.reuse_large_blocks())

        def teardown(self, worker):
            held = getattr(self, "_held", None)
            if held is not None:
                held.close()

    return HeapReuse()


def chunk_folder(output) -> Path:
    """The folder of an unfinished distributed replay's chunks: ``OUT.chunks`` beside ``output``."""
    return Path(str(output) + ".chunks")


def chunk_path(folder, fb: int, pb: int) -> Path:
    """The saved result of chunk (facet block ``fb``, profile block ``pb``) in ``folder``."""
    return Path(folder) / f"chunk_f{fb:05d}_p{pb:04d}.npz"


@contextlib.contextmanager
def one_numba_thread():
    """Run the numba kernels on one thread inside the block (a dask task: the worker's threads are the
    parallelism, as dask sets one BLAS/OpenMP thread per worker thread); the count is restored after."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(threads)


def solve_chunk(flux_path: str, profiles: list, f0: int, f1: int, options: dict, stamp=None):
    """Replay facets ``f0:f1`` of the flux store at ``flux_path`` against ``profiles``. Runs on a worker.

    The conduction kernels run on one thread (the worker's threads are the parallelism, as dask sets
    one BLAS/OpenMP thread per worker thread). ``stamp``: the file's :func:`io.file_stamp` when the
    command checked it; the task then reads only its facets (:func:`io.open_checked`: no second check of
    the whole file, which costs every task a read of every facet) and refuses a file changed since.
    Without it the file is checked here (:func:`io.read_flux_dataset`).

    Returns
    -------
    T : (len(profiles), n_times, f1 - f0) float32 surface temperatures [K]
    info : dict (start, periodic iterations and residuals [K] of the chunk's batches)
    """
    with one_numba_thread():
        ds = io.read_flux_dataset(flux_path, load=False) if stamp is None else io.open_checked(flux_path, stamp)
        try:
            return simulate.replay_fluxes(ds.isel(facet=slice(f0, f1)), profiles, progress=None, **options)
        finally:
            ds.close()


def _fingerprint(flux_path, stamp, profiles, options, facet_block, profile_block) -> str:
    """The chunk folder's fingerprint: the flux file (path, and its :func:`io.file_stamp`), profiles,
    options and chunking."""
    size, mtime_ns = stamp
    text = json.dumps(
        [
            str(Path(flux_path).resolve()),
            size,
            mtime_ns,
            [repr(p) for p in profiles],
            options,
            facet_block,
            profile_block,
        ],
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _open_chunk_folder(folder: Path, fp: str, output, resume: bool, overwrite: bool) -> None:
    """Keep (``resume``, same fingerprint), discard (``overwrite``) or refuse an earlier chunk folder;
    leave ``folder`` existing with this replay's fingerprint."""
    stamp = folder / "fingerprint.json"
    if folder.exists():
        try:
            same = json.loads(stamp.read_text()).get("fingerprint") == fp
        except (OSError, ValueError):
            same = False
        if resume and not same:
            if not overwrite:
                raise ConfigError(
                    f"{folder} holds chunks of a different replay (other flux file, profiles, options or "
                    "chunking): repeat that replay's command, or pass --overwrite to discard them"
                )
            shutil.rmtree(folder)
        elif not resume:
            if not overwrite:
                raise OutputExistsError(
                    f"{folder} holds an unfinished replay of output {output}: pass --resume to continue it, or "
                    "--overwrite to discard it and start again"
                )
            shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if not stamp.exists():
        tmp = stamp.with_name(".fingerprint.json.tmp")
        tmp.write_text(json.dumps({"fingerprint": fp, "output": str(output)}))
        os.replace(tmp, stamp)


def _save_chunk(path: Path, T, info) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, T=np.asarray(T, np.float32), info=json.dumps(info))
    os.replace(tmp, path)


def replay_file(
    flux_path,
    labels,
    *,
    output,
    scheduler: str | None = None,
    workers: int | None = None,
    density_grid=None,
    initial_temperature=None,
    fixed_spinup=False,
    property_set=None,
    allow_inverted=False,
    overwrite=False,
    resume=False,
    progress=None,
    chunk_facets: int = CHUNK_FACETS,
    chunk_profiles: int = CHUNK_PROFILES,
    retries: int = 3,
):
    """``crater-thermal replay --scheduler/--workers``: the replay of :func:`runner.replay_file`, its
    columns solved in chunks of ``chunk_facets`` facets x ``chunk_profiles`` profiles on a dask cluster.

    Parameters
    ----------
    flux_path : path of the run or flux dataset; every worker must read it at this path.
    labels, density_grid, initial_temperature, fixed_spinup, property_set, allow_inverted, overwrite :
        as :func:`runner.replay_file` (``initial_temperature`` [K]).
    output : path of the replay dataset (netCDF), written by the client.
    scheduler : address of a dask scheduler (``tcp://host:8786``); or
    workers : the number of one-thread worker processes of a local cluster.
    resume : keep the finished chunks of an interrupted call with the same inputs, profiles, options
        and chunking (``OUT.chunks/``) and compute only the others.
    progress : optional reporter (:mod:`crater_thermal.progress`), in chunks.
    chunk_facets, chunk_profiles : size of one task (chunk); its result is
        ``chunk_profiles x n_times x chunk_facets x 4`` bytes.
    retries : times the scheduler re-runs a task that raised before giving up.

    Returns
    -------
    Path of the written replay; its attributes ``replay_chunks`` and ``replay_chunks_resumed`` count
    the chunks and those kept from an interrupted call. The temperatures equal a local replay's bit
    for bit.
    """
    if scheduler is None and workers is None:
        raise ConfigError("a replay on dask needs a scheduler address or a number of local workers")
    if scheduler is None and int(workers) < 1:
        raise ConfigError(f"--workers {workers}: need at least 1 worker process")
    if int(chunk_facets) < 1 or int(chunk_profiles) < 1:
        raise ConfigError(
            f"--chunk-facets {chunk_facets} / --chunk-profiles {chunk_profiles}: chunks need at least 1 of each"
        )
    io.check_output(output, overwrite, inputs=[flux_path])
    output = Path(output)
    with io.output_lock(output):
        if initial_temperature is not None and not (1.0 <= initial_temperature <= 1000.0):
            raise ConfigError(f"--initial-temperature {initial_temperature} K outside [1, 1000] K")
        profiles = runner.resolve_profiles(labels, density_grid, allow_inverted)
        options = {"initial_temperature": initial_temperature, "fixed_spinup": bool(fixed_spinup)}
        if property_set is not None:
            options["property_set"] = property_set
        # the stamp before the check: a change during it is seen by the tasks (a missing file: the check says so)
        stamp = io.file_stamp(flux_path) if Path(flux_path).is_file() else None
        ds = io.read_flux_dataset(flux_path, load=False)
        try:
            nf, npf = ds.sizes["facet"], len(profiles)
            fb, pb = int(chunk_facets), int(chunk_profiles)
            chunks = [
                (i, j, f0, min(nf, f0 + fb), p0, min(npf, p0 + pb))
                for i, f0 in enumerate(range(0, nf, fb))
                for j, p0 in enumerate(range(0, npf, pb))
            ]
            folder = chunk_folder(output)
            fp = _fingerprint(flux_path, stamp, profiles, options, fb, pb)
            _open_chunk_folder(folder, fp, output, resume, overwrite)
            todo = [c for c in chunks if not chunk_path(folder, c[0], c[1]).exists()]
            nt = ds.sizes["time"]
            pending = sum((p1 - p0) * nt * (f1 - f0) * np.dtype(np.float32).itemsize for *_, f0, f1, p0, p1 in todo)
            try:
                runner.check_replay_disk(output, npf, nt, nf, chunk_bytes=pending)  # before any chunk is solved
                if todo:
                    run = (flux_path, profiles, options, stamp)
                    _compute(run, todo, folder, fp, scheduler, workers, retries, progress)
            except BaseException:
                if not any(folder.glob("chunk_*.npz")):  # nothing finished: nothing to resume
                    shutil.rmtree(folder, ignore_errors=True)
                raise
            _assemble(ds, profiles, chunks, folder, output, overwrite, initial_temperature, len(chunks) - len(todo))
        finally:
            ds.close()
    shutil.rmtree(folder, ignore_errors=True)
    return output


def _compute(run, todo, folder, fp, scheduler, workers, retries, progress) -> None:
    """Solve the chunks ``todo`` of ``run`` = (flux path, profiles, options, the flux file's stamp) on the
    cluster, saving each result in ``folder`` as it arrives."""
    flux_path, profiles, options, stamp = run
    client, cluster = connect(scheduler, workers)
    try:
        from distributed import KilledWorker, as_completed  # present: connect imported distributed

        futures = {
            client.submit(
                solve_chunk,
                str(flux_path),
                profiles[p0:p1],
                f0,
                f1,
                options,
                stamp,
                key=f"crater-thermal-replay-{fp}-f{i}-p{j}",
                retries=retries,
                pure=False,
            ): chunk_path(folder, i, j)
            for i, j, f0, f1, p0, p1 in todo
        }
        with simulate.stage(progress, f"replay on dask ({len(todo)} chunks)") as report:
            for done, fut in enumerate(as_completed(futures), 1):
                try:
                    T, info = fut.result()
                except KilledWorker:
                    raise ConfigError(
                        f"dask gave up {futures[fut].stem}: the workers that ran it died (out of memory? see "
                        "their logs); smaller --chunk-facets/--chunk-profiles need less memory per worker; run "
                        "again with --resume to keep the finished chunks"
                    ) from None
                _save_chunk(futures[fut], T, info)
                fut.release()  # the worker may drop the chunk's result now
                del T
                if report is not None:
                    report(done, len(todo))
    finally:
        disconnect(client, cluster)


def _assemble(ds, profiles, chunks, folder, output, overwrite, initial_temperature, resumed) -> None:
    """Write the replay dataset from the saved chunks (the same schema a local replay writes)."""
    nf, nt, npf = ds.sizes["facet"], ds.sizes["time"], len(profiles)
    tops, bottoms = zip(*(simulate.profile_densities(p) for p in profiles))
    skeleton = io.replay_dataset(ds, [p.label for p in profiles], tops, bottoms, None)
    variables = {"surface_temperature": (("profile", "time", "facet"), (npf, nt, nf), {"units": "K"}, "f4")}
    iters, resid, start = [], [], None
    block = max(f1 - f0 for _, _, f0, f1, _, _ in chunks)  # the chunks' facets: whole HDF5 chunks each
    with io.stream_dataset(
        skeleton, output, variables, overwrite=overwrite, time_rows=simulate.TIME_CHUNK, facet_block=block
    ) as stream:
        for i, j, f0, f1, p0, p1 in chunks:
            z = io.load_npz(chunk_path(folder, i, j))
            info = json.loads(str(z["info"]))
            stream("surface_temperature", (slice(p0, p1), slice(0, nt), slice(f0, f1)), z["T"])
            start = info["start"]
            iters += info["periodic_iterations"]
            resid += info["periodic_residual_K"]
        stream.set_attrs(
            {
                "replay_start": start,
                "periodic_iterations": iters or None,
                "periodic_residual_K": resid or None,
                "initial_temperature_K": initial_temperature,
                "ir_assumption": "saved nominal IR (thesis 7.2)",
                "replay_chunks": len(chunks),
                "replay_chunks_resumed": resumed,
            }
        )
