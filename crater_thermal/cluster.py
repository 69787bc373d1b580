"""A replay on a dask.distributed cluster: (profile x facet) columns in chunks, solved by workers.

Each chunk (a block of facets x a block of profiles) is one dask task, a pure function of the
flux store's path, the chunk's indices and the options: the worker opens the flux store by path
(it must be readable there: a shared filesystem), replays its columns with
:func:`crater_thermal.simulate.replay_fluxes` and writes the result atomically into the chunk folder
``OUT.chunks/`` next to the output. The client then assembles the chunks into the same replay
dataset a local replay writes and removes the folder. A lost worker's task is re-run by the
scheduler (``retries``); a re-run chunk is identical. A killed client is resumed by running the
same command again: the chunk folder's fingerprint (inputs, profiles, options, chunking) must match,
then the finished chunks are kept and counted, never recomputed; a folder with another
fingerprint is discarded.

dask is imported only here, inside the functions that need it; a local replay never imports it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from crater_thermal import io, runner, simulate
from crater_thermal.errors import ConfigError
from crater_thermal.extras import missing_extra

#: Seconds to wait for a dask scheduler to answer before giving up [s].
CONNECT_TIMEOUT_S = 10.0


def connect(scheduler: str | None = None, workers: int | None = None):
    """A dask.distributed client: of the scheduler at ``scheduler`` (``tcp://host:8786``), or of a new
    local cluster of ``workers`` processes with one thread each. Returns ``(client, cluster)``
    (cluster None for a remote scheduler).

    Raises
    ------
    MissingExtraError
        dask.distributed is not installed.
    ConfigError
        The scheduler cannot be reached.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise missing_extra("dask.distributed", "distributed", "replays on a dask cluster (--scheduler)") from None
    if scheduler:
        try:
            return Client(scheduler, timeout=CONNECT_TIMEOUT_S), None
        except (OSError, TimeoutError) as exc:
            raise ConfigError(
                f"--scheduler {scheduler}: cannot reach a dask scheduler there ({exc}); start one "
                "(dask scheduler) or leave out --scheduler"
            ) from None
    if workers is None or workers < 1:
        raise ConfigError(f"--workers {workers}: need at least 1 worker process")
    cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster), cluster


def chunk_path(folder: Path, fb: int, pb: int) -> Path:
    """The result file of chunk (facet block ``fb``, profile block ``pb``) in ``folder``."""
    return Path(folder) / f"chunk_f{fb:05d}_p{pb:04d}.npz"


def solve_chunk(flux_path, labels, f0, f1, p0, p1, options, folder, name) -> dict:
    """Replay columns facets ``f0:f1`` x profiles ``p0:p1`` of ``labels`` from the flux store at
    ``flux_path``; the float32 temperatures [K] go atomically to ``folder/name``. Runs on a worker.

    Returns the chunk's info (start, periodic iterations and residual [K]).
    """
    profiles = runner.resolve_profiles(list(labels[p0:p1]), None, True)
    ds = io.read_flux_dataset(flux_path, load=False)
    try:
        sub = ds.isel(facet=slice(f0, f1))
        T, info = simulate.replay_fluxes(sub, profiles, progress=None, **options)
    finally:
        ds.close()
    out = Path(folder) / name
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, T=T, info=json.dumps(info))
    os.replace(tmp, out)
    return info


def _fingerprint(flux_path, labels, options, facet_block, profile_block) -> str:
    st = os.stat(flux_path)
    text = json.dumps(
        [str(Path(flux_path).resolve()), st.st_size, st.st_mtime_ns, list(labels), options, facet_block, profile_block],
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


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
    progress=None,
    facet_block: int = 2000,
    profile_block: int = 8,
    retries: int = 3,
    log=None,
):
    """``crater-thermal replay --scheduler/--workers``: the replay of :func:`runner.replay_file`, its
    columns solved in chunks of ``facet_block`` facets x ``profile_block`` profiles on a dask cluster.

    Writes the same ``output`` as a local replay (the same temperatures bit for bit: each column's
    periodic start converges on its own). Finished chunks of an interrupted call with the same
    inputs and options are kept in ``OUT.chunks/`` and not recomputed. ``log(message)``: optional
    callable for one-line notes (chunks resumed, computed). Returns the output path.
    """
    io.check_output(output, overwrite, inputs=[flux_path])
    if initial_temperature is not None and not (1.0 <= initial_temperature <= 1000.0):
        raise ConfigError(f"--initial-temperature {initial_temperature} K outside [1, 1000] K")
    profiles = runner.resolve_profiles(labels, density_grid, allow_inverted)
    names = [p.label for p in profiles]
    options = {"initial_temperature": initial_temperature, "fixed_spinup": bool(fixed_spinup)}
    if property_set is not None:
        options["property_set"] = property_set
    ds = io.read_flux_dataset(flux_path, load=False)
    nf, nt, npf = ds.sizes["facet"], ds.sizes["time"], len(profiles)
    fb, pb = max(1, int(facet_block)), max(1, int(profile_block))
    chunks = [
        (i, j, f0, min(nf, f0 + fb), p0, min(npf, p0 + pb))
        for i, f0 in enumerate(range(0, nf, fb))
        for j, p0 in enumerate(range(0, npf, pb))
    ]
    folder = Path(str(output) + ".chunks")
    fp = _fingerprint(flux_path, names, options, fb, pb)
    stamp = folder / "fingerprint.json"
    if folder.exists() and not (stamp.exists() and json.loads(stamp.read_text()).get("fingerprint") == fp):
        shutil.rmtree(folder)  # another replay's (or an unreadable) chunk folder: never reused
    folder.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps({"fingerprint": fp}))
    todo = [c for c in chunks if not chunk_path(folder, c[0], c[1]).exists()]
    note = log or (lambda _m: None)
    note(f"replay on dask: {len(chunks)} chunks, {len(chunks) - len(todo)} resumed, {len(todo)} to compute")
    with io.output_lock(output):
        if todo:
            client, cluster = connect(scheduler, workers)
            try:
                from distributed import as_completed

                futures = [
                    client.submit(
                        solve_chunk,
                        str(flux_path),
                        names,
                        f0,
                        f1,
                        p0,
                        p1,
                        options,
                        str(folder),
                        chunk_path(folder, i, j).name,
                        key=f"replay-chunk-{fp}-{i}-{j}",
                        retries=retries,
                        pure=False,
                    )
                    for i, j, f0, f1, p0, p1 in todo
                ]
                for done, fut in enumerate(as_completed(futures), 1):
                    fut.result()
                    if progress:
                        progress(done, len(futures))
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
        tops, bottoms = zip(*(simulate.profile_densities(p) for p in profiles))
        skeleton = io.replay_dataset(ds, names, tops, bottoms, None)
        variables = {"surface_temperature": (("profile", "time", "facet"), (npf, nt, nf), {"units": "K"}, "f4")}
        iters, resid, start = [], [], None
        with io.stream_dataset(
            skeleton, output, variables, overwrite=overwrite, time_rows=simulate.TIME_CHUNK
        ) as stream:
            for i, j, f0, f1, p0, p1 in chunks:
                with np.load(chunk_path(folder, i, j)) as z:
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
                    "replay_chunks_resumed": len(chunks) - len(todo),
                }
            )
    ds.close()
    shutil.rmtree(folder, ignore_errors=True)
    return Path(output)
