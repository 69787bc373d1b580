"""Datasets on disk: the flux / run / replay / steady schemas, validation, checkpoints, and the one
atomic writer (:func:`atomic_output`) that every output of crater_thermal goes through.

This is the only module that imports xarray (inside the functions that need it, so that the writer
and the checks cost no xarray import). Files are netCDF4 with CF-style ``units``
attributes. The schemas are contracts (see ``ARCHITECTURE.md``):

Flux dataset (the minimum ``replay`` accepts)
    ``time`` (datetime64, UTC, strictly increasing), ``solar_incident(time, facet)`` and
    ``ir_incident(time, facet)`` [W m-2]; global attributes ``albedo`` and ``emissivity``.
    Between samples the fluxes are linear in time.
Run dataset
    The flux variables plus ``solar_direct``, ``surface_temperature(time, facet)`` [K],
    ``sun_direction(time, xyz)`` (crater frame, unit), ``sun_distance(time)`` [au], the mesh
    (``mesh_vertices(vertex, xyz)`` [m], ``mesh_faces(facet, corner)``, ``area`` [m2],
    ``normal``, ``centroid`` [m]) and attributes (case TOML text, version, mesh hash, ...).
Replay dataset
    ``surface_temperature(profile, time, facet)`` [K] with coordinates ``profile`` (labels),
    ``rho_top(profile)``, ``rho_bottom(profile)`` [kg m-3], plus the run's mesh and attributes.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import socket
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Mapping

import numpy as np

from crater_thermal._version import __version__
from crater_thermal.errors import ConfigError, FluxFileError, OutputExistsError, OutputLockedError, raise_if_interrupted

if TYPE_CHECKING:
    import xarray as xr

#: Accepted spellings of the irradiance unit.
FLUX_UNITS = ("W m-2", "W m**-2", "W m^-2", "W/m2", "W/m^2", "W m-2 ")
#: Accepted spellings of the temperature unit.
TEMPERATURE_UNITS = ("K", "kelvin")
#: Compression for large float variables (lossless): zlib level 1 after the byte shuffle. Measured on
#: a run's four (time, facet) float32 series, 20,000 facets x 361 samples, every setting in one process
#: (``bench/runnc_compression.py``, bench/results/runnc_compression.json): against level 1 without the
#: shuffle (the writer before issue 24) the write takes 2.1 s instead of 4.0 s, the file 49 MB instead of
#: 68 MB, and one facet's series reads in 0.07 s instead of 0.10 s; level 4 saves 2 % more of the size for
#: 80 % more write time. Writing is then 0.3 us per sample and facet, ~1 % of the run's own 22 us.
_ENCODING = {"zlib": True, "complevel": 1, "shuffle": True}
#: netCDF4 ``createVariable`` settings of each ``[output] compression`` (choices.OUTPUT_COMPRESSIONS) for the
#: streamed (time, facet) series. blosc_lz4 with blosc's byte shuffle, measured against zlib on a 10k year's
#: four series (``bench/runnc_compression.py --filters``): writes 7-8x faster, 9 % larger, one facet's
#: series reads 8x faster; it is an HDF5 plugin filter (netCDF4's wheels carry it).
SERIES_COMPRESSION = {
    "zlib": _ENCODING,
    "blosc_lz4": {"compression": "blosc_lz4", "complevel": 1, "blosc_shuffle": 1},
}
#: HDF5's blosc filter fails (``NetCDF: HDF error`` at close) on chunks under 512 bytes (measured with
#: netCDF4 1.7.5: 128 float32 values pass, 64 fail, for float64 64 pass, 32 fail: a run of a few
#: facets); a streamed variable whose chunks are smaller than this is written with ``"zlib"`` instead.
_BLOSC_MIN_CHUNK_BYTES = 1024


def check_compression(name: str) -> None:
    """Raise :class:`ConfigError` (one line) if this installation cannot write ``[output] compression = name``."""
    if name not in SERIES_COMPRESSION:
        raise ConfigError(f"[output] compression = {name!r}; allowed: {', '.join(SERIES_COMPRESSION)}")
    if name.startswith("blosc"):
        import netCDF4

        if not getattr(netCDF4, "__has_blosc_support__", False):
            raise ConfigError(
                f"[output] compression = {name!r} needs netCDF4 built with the blosc filter (pip's netCDF4 "
                'wheels have it); install one or use compression = "zlib"'
            )


# ----------------------------------------------------------------------------- writing


def check_output(path: str | os.PathLike, overwrite: bool = False, folder: bool = False, inputs: Iterable = ()) -> Path:
    """Check an output path before any work (nothing is created): refuse it if it exists (unless
    ``overwrite``) or has the wrong kind.

    Parameters
    ----------
    path : path-like
        The file (or, with ``folder``, the folder) to write.
    overwrite : bool
        Allow replacing an existing output.
    folder : bool
        The output is a folder (a file output must not be a folder, and the reverse).
    inputs : iterable of path-like
        The command's input files: the output may be none of them, even with ``overwrite``
        (see :func:`refuse_input_as_output`).

    Returns
    -------
    Path

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    ConfigError
        ``path`` is a folder where a file is written (or the reverse), or its parent is a file.
    """
    path = Path(path)
    refuse_input_as_output(path, inputs)
    if path.is_dir() and not folder:
        raise ConfigError(f"output {path} is a folder; give a file name (e.g. {path / 'out.nc'})")
    if path.exists() and folder and not path.is_dir():
        raise ConfigError(f"output {path} is a file; give a folder name")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"output {path} exists; pass --overwrite to replace it")
    if path.parent.exists() and not path.parent.is_dir():
        raise ConfigError(f"output {path}: {path.parent} is a file, not a folder")
    return path


def refuse_input_as_output(output: str | os.PathLike, inputs: Iterable) -> None:
    """Refuse an output that is one of the command's inputs, or (a folder output) holds one.

    Files are compared as the operating system sees them (device and inode, ``os.path.samefile``), so
    another spelling of the same file (``./run.nc``, a symbolic or hard link) is caught too. Applies
    even with ``--overwrite``: replacing an input with the result destroys the input.

    Parameters
    ----------
    output : path-like
        The file or folder about to be written.
    inputs : iterable of path-like or None
        The files the command reads (``None`` entries are skipped; inputs that do not exist are
        left to the readers' own errors).

    Raises
    ------
    ConfigError
        ``output`` is, or contains, one of ``inputs``.
    """
    output = Path(output)
    if not os.path.lexists(output):
        return
    for inp in inputs:
        if inp is None or not os.path.exists(inp):
            continue
        inp = Path(inp)
        if os.path.samefile(output, inp):
            raise ConfigError(
                f"output {output} is the input {inp}; write to another file (an output never replaces an input, "
                "even with --overwrite)"
            )
        if output.is_dir() and not output.is_symlink():
            parent = inp.resolve().parent
            if any(os.path.samefile(output, p) for p in (parent, *parent.parents) if p.exists()):
                raise ConfigError(
                    f"output folder {output} holds the input {inp}; write to another folder (an output never "
                    "replaces an input, even with --overwrite)"
                )


def lock_path(output: str | os.PathLike) -> Path:
    """The lock file of an output: ``OUT.lock`` beside it (a folder output ``report/`` -> ``report.lock``)."""
    output = Path(output)
    return output.with_name(output.name.rstrip("/") + ".lock")


def _process_start(pid: int) -> str:
    """Start time of process ``pid`` in clock ticks since boot (Linux ``/proc``), or '' where unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def _alive(pid: int, start: str) -> bool:
    """Whether process ``pid`` runs on this host (and, where known, is the one that started at ``start``)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    except OSError:
        return False
    now = _process_start(pid)
    return not start or not now or now == start


@contextlib.contextmanager
def output_lock(output: str | os.PathLike) -> Iterator[Path]:
    """Hold the lock of an output for the block: one writer per output.

    The lock is a small JSON file beside the output (:func:`lock_path`) naming the holder's process id,
    host, start time and command line, created atomically (``O_EXCL``). A second process asking for
    the same output while the holder lives is refused at once; a lock whose process is gone (killed,
    or the machine restarted) is taken over with a one-line warning. The lock is removed when the
    block ends, whether it ends normally, by an error or by an interruption.

    Raises
    ------
    OutputLockedError
        A live process (on this host, or any process on another host) holds the lock.
    ConfigError
        The lock cannot be created (the output's folder cannot be made or written).
    """
    lock = lock_path(output)
    me = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "process_start": _process_start(os.getpid()),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": " ".join(sys.argv),
    }
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the folder of output {output}: {exc.strerror or exc}") from None
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            _take_over_if_stale(lock, output, me["host"])
            continue
        except OSError as exc:
            raise ConfigError(f"cannot create the lock {lock} of output {output}: {exc.strerror or exc}") from None
        with os.fdopen(fd, "w") as f:
            json.dump(me, f)
        break
    else:  # pragma: no cover - three stale locks replaced by others in a row
        raise OutputLockedError(f"output {output}: its lock {lock} keeps being taken by other processes; try again")
    try:
        yield lock
    finally:
        try:
            with open(lock) as f:
                mine = json.load(f).get("pid") == me["pid"]
        except (OSError, ValueError):
            mine = False
        if mine:
            with contextlib.suppress(OSError):
                lock.unlink()


def _take_over_if_stale(lock: Path, output, host: str) -> None:
    """Remove ``lock`` if its process is gone (with a warning); refuse if it lives."""
    try:
        with open(lock) as f:
            holder = json.load(f)
        pid, holder_host = int(holder["pid"]), str(holder["host"])
    except FileNotFoundError:
        return  # released meanwhile: try again
    except (OSError, ValueError, KeyError, TypeError):
        holder, pid, holder_host = {}, -1, host  # unreadable (a crash while writing it): stale
        if time.time() - _mtime(lock) < 5.0:  # or being written right now
            raise OutputLockedError(
                f"output {output} is locked by another process ({lock} is being written); try again in a moment"
            ) from None
    if holder_host != host:
        raise OutputLockedError(
            f"output {output} is being written by process {pid} on host {holder_host} (lock {lock}); wait for it, "
            "or delete the lock if that process is gone"
        )
    if pid > 0 and _alive(pid, str(holder.get("process_start", ""))):
        raise OutputLockedError(
            f"output {output} is being written by process {pid} (since {holder.get('started_utc', '?')}, lock "
            f"{lock}); wait for it to finish or stop it, or write to another output"
        )
    warnings.warn(f"taking over the stale lock {lock} of process {pid}, which is no longer running", stacklevel=3)
    with contextlib.suppress(FileNotFoundError):
        lock.unlink()


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _temporary_sibling(path: Path, folder: bool) -> Path:
    """Create an empty file (or folder) beside ``path`` with a fresh hidden name and return it.

    Created with mode 0o666 (0o777 for a folder) so that the process umask alone sets the
    permissions: one policy for every output.
    """
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            if folder:
                os.mkdir(tmp, 0o777)
            else:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path}")  # pragma: no cover


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike, overwrite: bool = False, folder: bool = False, durable: bool = True
) -> Iterator[Path]:
    """Write an output atomically: the one writer every crater_thermal output goes through.

    Yields a temporary path in the same folder as ``path`` (an empty file, or with ``folder`` an empty
    folder; the name ends in ``path``'s suffix, so format-sniffing writers work). When the block ends
    normally the temporary is renamed onto ``path`` (``os.replace``: readers never see a half-written
    file, and an interrupted write never damages an earlier output); when it raises, the temporary is
    removed and ``path`` is untouched. Permissions follow the umask (files 0o666, folders 0o777, minus
    the umask).

    Parameters
    ----------
    path : path-like
        Final output path; its parent folders are created.
    overwrite : bool
        Replace an existing output (checked again at the rename, in case one appeared meanwhile).
    folder : bool
        The output is a folder; an existing one (with ``overwrite``) is replaced as a whole.
    durable : bool
        Flush a file to disk before the rename (survives a power cut). False for scratch files that
        only need to survive a killed process (a rename is atomic either way).

    Raises
    ------
    OutputExistsError, ConfigError
        As :func:`check_output`, before the block runs.

    Examples
    --------
    >>> with atomic_output("run.nc", overwrite=True) as tmp:  # doctest: +SKIP
    ...     ds.to_netcdf(tmp)
    """
    path = check_output(path, overwrite, folder)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the folder of output {path}: {exc.strerror or exc}") from None
    tmp = _temporary_sibling(path, folder)
    try:
        yield tmp
        raise_if_interrupted()  # a stop signal whose exception was swallowed still prevents the commit
        check_output(path, overwrite, folder)
        if folder and path.is_dir():
            old = _temporary_sibling(path, folder=True)
            os.replace(path, old)  # a folder cannot be renamed onto a non-empty one: swap
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            _remove(old)
        else:
            if durable:
                _fsync(tmp)  # the data reach the disk before the name does
            os.replace(tmp, path)
    finally:
        if os.path.lexists(tmp):
            _remove(tmp)


def write_dataset_atomic(ds: xr.Dataset, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``ds`` to netCDF4 at ``path`` through :func:`atomic_output`.

    An interrupted write never leaves a half-written file at ``path`` nor damages an earlier one.
    """
    with atomic_output(path, overwrite) as tmp:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=_encoding(ds))
    return Path(path)


def _encoding(ds: xr.Dataset) -> dict:
    """Compression for the large float variables of ``ds``."""
    return {name: dict(_ENCODING) for name, var in ds.data_vars.items() if var.dtype.kind == "f" and var.size > 1000}


def write_bytes_atomic(path: str | os.PathLike, data: bytes, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_output`.

    Raises :class:`OutputExistsError` if ``path`` exists and ``overwrite`` is False.
    """
    with atomic_output(path, overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_npz_atomic(path: str | os.PathLike, **arrays: Any) -> Path:
    """Save arrays to an ``.npz`` file through :func:`atomic_output`, replacing any earlier one
    (checkpoints and caches)."""
    with atomic_output(path, overwrite=True) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return Path(path)


# numpy parses an .npy header with ast.literal_eval, and CPython 3.11.7 (CI's Python) fails when two
# threads of one process parse at once ("SystemError: AST constructor recursion depth mismatch",
# CPython gh-106905). Every .npy/.npz read of the package goes through the two functions below, which
# parse under this lock (dask workers with several threads; the horizon map's thread reads nothing:
# simulate.case_operator_and_horizons reads its cache before starting it, as other code on the calling
# thread may parse too).
_NPY_HEADER_LOCK = threading.Lock()


def load_npy(path: str | os.PathLike, mmap_mode: str | None = None) -> np.ndarray:
    """One ``.npy`` array (no pickles), its header parsed under a process-wide lock (thread-safe on
    every Python 3.11); ``mmap_mode`` as :func:`numpy.load`'s."""
    with _NPY_HEADER_LOCK:
        return np.load(path, mmap_mode=mmap_mode, allow_pickle=False)


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read into memory (no pickles), thread-safe as :func:`load_npy`."""
    with _NPY_HEADER_LOCK, np.load(path, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


# ----------------------------------------------------------------------------- streaming (bounded memory)


def chunk_shape(shape: tuple, time_axis: int, time_rows: int, target_bytes: int = 1 << 20, itemsize: int = 8) -> tuple:
    """HDF5 chunk shape for a large variable: ``time_rows`` along time, about ``target_bytes`` of values
    of ``itemsize`` bytes per chunk along the last (facet) axis, 1 along any leading axis (e.g.
    ``profile``). A facet's whole series is then read from ``n_time / time_rows`` chunks and one time
    sample of every facet from ``n_facet / chunk`` chunks (run.nc: 24 rows, 1 MB)."""
    out = [1] * len(shape)
    out[time_axis] = max(1, min(int(time_rows), int(shape[time_axis])))
    out[-1] = max(1, min(int(shape[-1]), target_bytes // (int(itemsize) * out[time_axis])))
    return tuple(out)


def aligned_width(block: int, width: int) -> int:
    """A chunk's extent along facets for pieces of ``block`` facets: the largest divisor of ``block`` not
    above ``width`` (the size-based extent), or ``width`` itself when that divisor is under a quarter of it
    (a block with no divisor near it: smaller chunks would cost more than the chunks pieces share)."""
    block, width = int(block), int(width)
    if block <= width:
        return block
    best = max(d for d in range(1, width + 1) if block % d == 0)
    return best if 4 * best >= width else width


def _piece_chunks(shape: tuple, t_axis: int, time_rows: int, itemsize: int, facet_block: int | None) -> tuple:
    """:func:`chunk_shape`, its facet extent aligned to pieces of ``facet_block`` facets when given."""
    out = list(chunk_shape(shape, t_axis, time_rows, itemsize=itemsize))
    if facet_block:
        out[-1] = aligned_width(facet_block, out[-1])
    return tuple(out)


#: HDF5's filter codes of the byte shuffle and of deflate (zlib), the pipeline of ``"zlib"`` series.
_H5Z_SHUFFLE, _H5Z_DEFLATE = 2, 1
#: Most threads that compress a streamed series' chunks at once.
_MAX_COMPRESS_THREADS = 8


def _deflate_level1():
    """zlib-format deflate at level 1: ISA-L's (``isal``, the same format 3-10x faster) when installed,
    else the standard library's."""
    try:
        from isal import isal_zlib

        return lambda data: isal_zlib.compress(data, 1)
    except ImportError:  # pragma: no cover - isal has wheels for every platform we install on
        import zlib

        return lambda data: zlib.compress(data, 1)


def _h5py():
    """h5py, for :class:`_ChunkWriter`'s direct chunk writes; None where it is not installed (then netCDF4
    writes the zlib series itself, one chunk at a time: the same file, ~8x slower to write)."""
    try:
        import h5py
    except ImportError:
        return None
    return h5py


class _ChunkWriter:
    """Writes whole chunks of a shuffle + deflate HDF5 dataset: the shuffle (numpy) and the deflate
    (``isal``/``zlib``, both release the GIL) of a block's chunks run in a thread pool and the bytes go
    in with HDF5's direct chunk write, instead of the HDF5 library filtering chunk after chunk in one
    thread (measured: ``bench/runnc_compression.py --writers``). The file is the same as HDF5's own
    (same chunks, same filters, readable by any netCDF/HDF5 reader); only the deflate's byte stream
    may differ. A write that does not cover whole chunks goes through HDF5 (``dset[key] = values``)."""

    def __init__(self, dset, pool):
        self._dset, self._pool = dset, pool
        self._chunks = tuple(dset.chunks)
        self._fill = np.asarray(dset.fillvalue, dtype=dset.dtype)
        self._deflate = _deflate_level1()
        plist = dset.id.get_create_plist()
        codes = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
        self.direct = codes == [_H5Z_SHUFFLE, _H5Z_DEFLATE]

    def _encode(self, block: np.ndarray) -> bytes:
        if block.shape != self._chunks:  # an edge chunk is stored whole: pad it with the fill value
            full = np.full(self._chunks, self._fill)
            full[tuple(slice(0, n) for n in block.shape)] = block
            block = full
        width = block.dtype.itemsize
        shuffled = np.ascontiguousarray(block).view(np.uint8).reshape(-1, width).T.tobytes()
        return self._deflate(shuffled)

    def write(self, key: tuple, values: np.ndarray) -> None:
        shape, chunks = self._dset.shape, self._chunks
        bounds = [k.indices(n)[:2] if isinstance(k, slice) else (k, k + 1) for k, n in zip(key, shape)]
        whole = all(a % c == 0 and (b % c == 0 or b == n) and b > a for (a, b), c, n in zip(bounds, chunks, shape))
        values = np.asarray(values, dtype=self._dset.dtype).reshape([b - a for a, b in bounds])
        if not (self.direct and whole):
            self._dset[tuple(slice(a, b) for a, b in bounds)] = values
            return
        starts = list(np.ndindex(*[-(-(b - a) // c) for (a, b), c in zip(bounds, chunks)]))
        local = [tuple(i * c for i, c in zip(idx, chunks)) for idx in starts]

        def encode(origin):
            return self._encode(values[tuple(slice(o, o + c) for o, c in zip(origin, chunks))])

        for origin, data in zip(local, self._pool.map(encode, local)):
            offset = tuple(int(a + o) for (a, _), o in zip(bounds, origin))
            self._dset.id.write_direct_chunk(offset, data, filter_mask=0)


class _StreamWriter:
    """What :func:`stream_dataset` yields: ``writer(name, key, values)`` stores a block of a large
    variable; ``writer.set_attrs(mapping)`` adds global attributes known only at the end."""

    def __init__(self, variables, attrs: dict):
        self._vars, self._attrs = variables, attrs

    def __call__(self, name: str, key: tuple, values) -> None:
        var = self._vars[name]
        if isinstance(var, _ChunkWriter):
            var.write(key, values)
        else:
            var[key] = np.asarray(values, dtype=var.dtype)

    def set_attrs(self, attrs: Mapping[str, Any]) -> None:
        self._attrs.update(attrs)


def _set_global_attrs(nc, attrs: Mapping[str, Any]) -> None:
    for key, value in attrs.items():
        if value is None:
            continue
        if isinstance(value, bool):
            value = int(value)
        elif isinstance(value, dict):
            value = json.dumps(value, default=float)
        nc.setncattr(key, value)


@contextlib.contextmanager
def stream_dataset(
    ds: xr.Dataset,
    path: str | os.PathLike,
    variables: Mapping[str, tuple],
    *,
    overwrite: bool = False,
    time_rows: int = 24,
    compression: str = "zlib",
    facet_block: int | None = None,
) -> Iterator[_StreamWriter]:
    """Write a dataset whose large variables arrive in pieces, never whole in memory; atomic.

    ``ds`` holds everything small (coordinates, mesh, attributes) and is written first; each entry
    ``name: (dims, shape, attrs[, dtype])`` of ``variables`` becomes a variable (float64 unless
    ``dtype`` says otherwise) chunked along time (``time_rows`` samples) and facet (about 1 MB per
    chunk), compressed as ``compression`` says (:data:`SERIES_COMPRESSION`; ``"zlib"``: like every
    large variable, its chunks compressed in parallel by :class:`_ChunkWriter`; blosc only for chunks
    of at least :data:`_BLOSC_MIN_CHUNK_BYTES`, zlib below). ``facet_block``: the
    pieces are blocks of this many facets from facet 0 (a
    distributed replay's chunks), so the chunks' facet extent is made a divisor of it
    (:func:`aligned_width`): each piece then fills whole chunks, each compressed once, instead of
    HDF5 decompressing and compressing again a chunk that several pieces share. Yields a
    :class:`_StreamWriter`:
    ``write(name, key, values)`` stores ``values`` at ``var[key]`` (a tuple of slices). The file
    appears at ``path`` only when the block exits without an exception.
    """
    import netCDF4

    check_compression(compression)
    with atomic_output(path, overwrite) as tmp:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=_encoding(ds))
        nc = netCDF4.Dataset(tmp, "a")
        attrs: dict = {}
        try:
            created = {}
            for name, spec in variables.items():
                dims, shape, var_attrs = spec[:3]
                dtype = np.dtype(spec[3] if len(spec) > 3 else "f8")
                for dim, size in zip(dims, shape):
                    if dim not in nc.dimensions:
                        nc.createDimension(dim, size)
                    elif len(nc.dimensions[dim]) != size:
                        raise ValueError(f"{name}: dimension {dim} has {len(nc.dimensions[dim])}, not {size}")
                t_axis = list(dims).index("time") if "time" in dims else 0
                chunks = _piece_chunks(tuple(shape), t_axis, time_rows, dtype.itemsize, facet_block)
                filters = compression
                if compression.startswith("blosc") and int(np.prod(chunks)) * dtype.itemsize < _BLOSC_MIN_CHUNK_BYTES:
                    filters = "zlib"
                var = nc.createVariable(
                    name,
                    dtype,
                    dims,
                    fill_value=dtype.type(np.nan),
                    chunksizes=chunks,
                    **SERIES_COMPRESSION[filters],
                )
                var.setncatts(dict(var_attrs))
                created[name] = var
            h5py = _h5py() if compression == "zlib" else None
            if h5py is None:  # netCDF4 writes (and HDF5 filters) every piece
                yield _StreamWriter(created, attrs)
                _set_global_attrs(nc, attrs)
                return
        finally:
            nc.close()
        # zlib: the chunks go in through h5py (HDF5's direct chunk write); netCDF4 closed meanwhile
        # (two HDF5 libraries must never hold the file open at once), then adds the global attributes
        from concurrent.futures import ThreadPoolExecutor

        threads = max(1, min(_MAX_COMPRESS_THREADS, os.cpu_count() or 1))
        with ThreadPoolExecutor(threads, thread_name_prefix="deflate") as pool, h5py.File(tmp, "r+") as h5:
            yield _StreamWriter({name: _ChunkWriter(h5[name], pool) for name in created}, attrs)
        with netCDF4.Dataset(tmp, "a") as nc:
            _set_global_attrs(nc, attrs)


class SegmentStore:
    """Crash-safe scratch store for ``(rows, columns)`` series that grow block by block.

    A folder of ``.npy`` files, one per (series, block of ``block`` rows), each written to a temporary
    name and renamed: a process killed at any instant leaves every block whole or absent, never torn.
    (An HDF5/netCDF4 file killed while being written can lose its metadata and with it every earlier
    block, which is why an unfinished run keeps its results here and the netCDF file is written from
    these blocks at the end.) Writing a block again replaces it; a block may hold fewer rows than
    ``block`` (the last one, or a partial one saved at a checkpoint).
    """

    def __init__(self, folder: str | os.PathLike, block: int):
        self.folder = Path(folder)
        self.block = int(block)
        if self.block < 1:
            raise ValueError(f"block must be >= 1 row, got {block}")
        self.folder.mkdir(parents=True, exist_ok=True)
        self._dir = str(self.folder)

    def _file(self, name: str, b: int) -> str:
        # plain strings: pathlib interns every path part, a dictionary that grows with the block count
        return os.path.join(self._dir, f"{name}.{b:08d}.npy")

    def write(self, name: str, k0: int, rows: np.ndarray, in_place: bool = False) -> None:
        """Store ``rows`` as rows ``k0 ..`` of series ``name`` (``k0`` a multiple of ``block``).

        ``in_place``: when the block exists with the same shape and type, overwrite its values in the
        file instead of writing a new file and renaming it. The page cache's pages are then reused (a new
        file's are allocated afresh: measured 0.4-6 GB/s for new files, 2.6-5 GB/s for renamed
        rewrites, ~8 GB/s in place), but a process killed during the write can leave the block torn:
        only for series that nothing reads after an interruption (the spin-up windows' own series,
        which a resumed run computes again)."""
        if k0 % self.block or len(rows) > self.block:
            raise ValueError(f"{name}: rows {k0}..{k0 + len(rows)} do not fit block {self.block}")
        target = self._file(name, k0 // self.block)
        if in_place and self._overwrite(target, rows):
            return
        with atomic_output(target, overwrite=True, durable=False) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, np.ascontiguousarray(rows))

    @staticmethod
    def _overwrite(target: str, rows: np.ndarray) -> bool:
        """Overwrite an existing block file's values with ``rows`` if its shape and type are the same;
        False (nothing written) otherwise."""
        try:
            block = np.load(target, mmap_mode="r+")
        except (OSError, ValueError):
            return False
        try:
            if block.shape != rows.shape or block.dtype != rows.dtype:
                return False
            block[...] = rows
            return True
        finally:
            del block

    def write_rows(self, name: str, k0: int, rows: np.ndarray) -> None:
        """Store rows ``k0 .. k0 + len(rows) - 1`` of ``name``, split at block boundaries (any ``k0``;
        a block only partly covered is read, merged and written back)."""
        k, end = int(k0), int(k0) + len(rows)
        while k < end:
            b0 = k // self.block * self.block
            b1 = min(end, b0 + self.block)
            part = rows[k - k0 : b1 - k0]
            if k > b0:
                head = self.read(name, b0, k)
                part = np.concatenate([head, part])
            self.write(name, b0, part)
            k = b1

    def read(self, name: str, k0: int, k1: int, dtype=None) -> np.ndarray:
        """Rows ``k0 .. k1 - 1`` of series ``name`` (FluxFileError if a block is missing or short), as
        stored or converted to ``dtype``."""
        parts = []
        k = int(k0)
        while k < k1:
            b = k // self.block
            f = self._file(name, b)
            try:
                # mapped, so that a read of a few rows (a block's first row, read with the block
                # before it) loads those rows and not the whole block
                try:
                    arr = load_npy(f, mmap_mode="r")
                except ValueError:  # e.g. a block of no rows cannot be mapped
                    arr = load_npy(f)
            except (OSError, ValueError) as exc:
                raise FluxFileError(
                    f"scratch store {self.folder}: block {os.path.basename(f)} unreadable ({exc})"
                ) from None
            lo, hi = k - b * self.block, min(k1 - b * self.block, self.block)
            if arr.shape[0] < hi:
                raise FluxFileError(
                    f"scratch store {self.folder}: {os.path.basename(f)} has {arr.shape[0]} rows, need {hi}"
                )
            parts.append(arr[lo:hi])
            k = b * self.block + hi
        # a copy in memory: no view of a file that a later write of the block replaces
        return np.array(parts[0], dtype=dtype) if len(parts) == 1 else np.concatenate(parts, dtype=dtype)

    def _blocks(self, name: str) -> list[str]:
        """The block files of series ``name``, in block order."""
        prefix = f"{name}."
        return sorted(
            e.path
            for e in os.scandir(self._dir)
            if e.name.startswith(prefix) and e.name.endswith(".npy") and e.name[len(prefix) : -4].isdigit()
        )

    def drop(self, *names: str) -> None:
        """Delete series ``names`` (absent ones ignored): their disk space is given back at once."""
        for name in names:
            for path in self._blocks(name):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(path)

    def drop_before(self, k: int, *names: str) -> None:
        """Delete the blocks of series ``names`` that hold only rows before row ``k``."""
        for name in names:
            for b in range(int(k) // self.block):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self._file(name, b))

    def rename(self, name: str, new: str) -> None:
        """Series ``name`` becomes series ``new`` (any blocks of ``new`` are deleted first): no copy, each
        block file renamed. A process killed meanwhile can leave both names with part of the blocks: only
        for series that an interrupted run makes again (as ``write(in_place=True)``)."""
        self.drop(new)
        for path in self._blocks(name):
            b = os.path.basename(path)[len(name) + 1 : -4]
            os.replace(path, os.path.join(self._dir, f"{new}.{b}.npy"))

    def mark(self, name: str) -> None:
        """Record that a stage finished (an empty marker file, written atomically)."""
        (self.folder / f"{name}.done").touch()

    def marked(self, name: str) -> bool:
        return (self.folder / f"{name}.done").exists()

    def remove(self) -> None:
        """Delete the store and everything in it."""
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)


def mesh_variables(mesh) -> dict:
    """The mesh as dataset variables: vertices [m], faces, area [m2], unit normals, centroids [m]."""
    return {
        "mesh_vertices": (("vertex", "xyz"), np.asarray(mesh.vertices, float), {"units": "m"}),
        "mesh_faces": (("facet", "corner"), np.asarray(mesh.faces, np.int64), {}),
        "area": (("facet",), np.asarray(mesh.areas, float), {"units": "m2"}),
        "normal": (("facet", "xyz"), np.asarray(mesh.normals, float), {"units": "1"}),
        "centroid": (("facet", "xyz"), np.asarray(mesh.centroids, float), {"units": "m"}),
        "inner": (
            ("facet",),
            inner_flags(len(mesh.faces), getattr(mesh, "meta", None)).astype(np.int8),
            {
                "units": "1",
                "flag_values": np.array([0, 1], np.int8),
                "flag_meanings": "outer inner",
                "long_name": "facet of the analysed region (0: outer terrain for shadows and radiation only)",
            },
        ),
    }


def inner_flags(n_facets: int, meta: Mapping[str, Any] | None) -> np.ndarray:
    """(n_facets,) bool: facets of the analysed region. A DEM site mesh stores its inner facets first and
    their count as ``meta["n_inner"]``; every other mesh is all inner."""
    mask = np.ones(int(n_facets), dtype=bool)
    n_inner = (meta or {}).get("n_inner")
    if n_inner is not None:
        mask[int(n_inner) :] = False
    return mask


def dataset_inner(ds: xr.Dataset) -> np.ndarray:
    """(n_facets,) bool ``inner`` flags of a run/replay dataset (all True for files written before the flag)."""
    if "inner" in ds:
        return np.asarray(ds["inner"].values).astype(bool)
    return np.ones(ds.sizes["facet"], dtype=bool)


def base_attrs(mesh, **attrs: Any) -> dict:
    """Global attributes every dataset carries (version, mesh hash, mesh meta as JSON)."""
    out = {
        "software": "crater_thermal",
        "software_version": __version__,
        "mesh_hash": mesh.hash,
        "mesh_meta": json.dumps(mesh.meta, default=float),
        "Conventions": "CF-1.8",
    }
    for key, value in attrs.items():
        if value is None:
            continue
        if isinstance(value, bool):
            value = int(value)
        elif isinstance(value, (dict, list, tuple)):
            value = json.dumps(value, default=float)
        out[key] = value
    return out


def write_steady(
    path, mesh, results: Mapping[str, np.ndarray], attrs: Mapping[str, Any], overwrite: bool = False
) -> Path:
    """Write a steady-state (radiative equilibrium) result.

    Parameters
    ----------
    results : mapping with ``surface_temperature`` [K] and ``solar_direct``, ``solar_incident``,
        ``ir_incident`` [W m-2], each ``(n_facets,)``.
    attrs : global attributes (albedo, emissivity, sun elevation/azimuth, ...).
    """
    import xarray as xr

    units = {"surface_temperature": "K"}
    data_vars = {
        name: (("facet",), np.asarray(value, float), {"units": units.get(name, "W m-2")})
        for name, value in results.items()
    }
    data_vars.update(mesh_variables(mesh))
    ds = xr.Dataset(data_vars, attrs=base_attrs(mesh, **attrs))
    return write_dataset_atomic(ds, path, overwrite)


#: Storage type of run.nc's (time, facet) series (fluxes, surface temperature). float32 keeps 7
#: significant digits: 1e-4 W m-2 at 1,000 W m-2, 1e-5 K at 300 K, far below the model's accuracy;
#: against float64 it halves the file (measured after zlib: 0.24-0.33 of the float64 bytes instead of
#: 0.61-0.71) and the time spent compressing it. The run steps in float64; its scratch store keeps the
#: sunlight series and the record's rows in this type too (half the bytes to write; the conduction reads the
#: sunlight back as float64), so the run and a replay from run.nc are driven by the same sunlight. A replay
#: of the nominal profile from these series reproduces the run's stored temperatures to their float32
#: rounding (measured <= 3e-5 K on the test cases, fixed and periodic start).
RUN_SERIES_DTYPE = "f4"
#: Attributes of the run dataset's (time, facet) variables (shared by the in-memory and streamed writers).
RUN_SERIES_ATTRS = {
    "solar_incident": {"units": "W m-2", "long_name": "direct + scattered shortwave irradiance"},
    "ir_incident": {"units": "W m-2", "long_name": "longwave irradiance from the terrain"},
    "solar_direct": {"units": "W m-2", "long_name": "direct solar irradiance"},
    "surface_temperature": {"units": "K"},
    "solar_absorbed": {
        "units": "W m-2",
        "long_name": "absorbed shortwave flux (incidence-dependent albedo of direct light, albedo_model)",
    },
    "spinup_solar_absorbed": {
        "units": "W m-2",
        "long_name": "absorbed shortwave flux over the spin-up window (albedo_model)",
    },
}


def run_dataset(
    mesh,
    times,
    *,
    solar_incident=None,
    ir_incident=None,
    solar_direct=None,
    surface_temperature=None,
    sun_direction,
    sun_distance_au,
    attrs: Mapping[str, Any],
    extra: Mapping | None = None,
) -> xr.Dataset:
    """Assemble the run dataset (contract schema). Arrays are ``(n_times, n_facets)`` unless noted.

    ``extra`` adds variables as ``name: (dims, data, attrs)``. The (time, facet) series are stored as
    :data:`RUN_SERIES_DTYPE`, as in a streamed run. A (time, facet) variable given as None is
    left out (a streamed run adds it block by block with :func:`stream_dataset`, attributes from
    ``RUN_SERIES_ATTRS``).
    """
    import xarray as xr

    series = {
        "solar_incident": solar_incident,
        "ir_incident": ir_incident,
        "solar_direct": solar_direct,
        "surface_temperature": surface_temperature,
    }
    data_vars = {
        name: (("time", "facet"), np.asarray(value, RUN_SERIES_DTYPE), dict(RUN_SERIES_ATTRS[name]))
        for name, value in series.items()
        if value is not None
    }
    data_vars.update(
        {
            "sun_direction": (
                ("time", "xyz"),
                sun_direction,
                {"units": "1", "frame": "crater ENU (x east, y north, z up)"},
            ),
            "sun_distance": (("time",), sun_distance_au, {"units": "au"}),
        }
    )
    data_vars.update(mesh_variables(mesh))
    if extra:
        data_vars.update(extra)
    ds = xr.Dataset(data_vars, coords={"time": np.asarray(times, "datetime64[ns]")}, attrs=base_attrs(mesh, **attrs))
    ds.attrs["flux_interpolation"] = "linear in time between samples"
    return ds


def replay_dataset(
    run: xr.Dataset, labels, rho_top, rho_bottom, surface_temperature, attrs: Mapping[str, Any] | None = None
) -> xr.Dataset:
    """Assemble the replay dataset: ``surface_temperature(profile, time, facet)`` [K] plus the run's mesh
    (``surface_temperature=None`` leaves it out, for :func:`stream_dataset` to add block by block)."""
    import xarray as xr

    data_vars = {
        "rho_top": (("profile",), np.asarray(rho_top, float), {"units": "kg m-3"}),
        "rho_bottom": (("profile",), np.asarray(rho_bottom, float), {"units": "kg m-3"}),
    }
    if surface_temperature is not None:
        data_vars["surface_temperature"] = (("profile", "time", "facet"), surface_temperature, {"units": "K"})
    for name in ("mesh_vertices", "mesh_faces", "area", "normal", "centroid", "inner", "sun_direction", "sun_distance"):
        if name in run:
            data_vars[name] = run[name].variable
    out_attrs = dict(run.attrs)
    out_attrs.update({k: v for k, v in (attrs or {}).items() if v is not None})
    out_attrs["software_version"] = __version__
    return xr.Dataset(
        data_vars, coords={"profile": np.asarray(list(labels), dtype=str), "time": run["time"].values}, attrs=out_attrs
    )


# ----------------------------------------------------------------------------- reading


def _open(path, what: str, load: bool = True) -> xr.Dataset:
    import xarray as xr

    path = Path(path)
    if not path.is_file():
        raise FluxFileError(f"{what} file {path} does not exist")
    try:
        if not load:  # lazily, and without caching whole variables once touched
            return xr.open_dataset(path, engine="netcdf4", cache=False)
        return xr.open_dataset(path, engine="netcdf4").load()
    except Exception as exc:  # netCDF4/HDF5 raise many types for a corrupt file
        raise FluxFileError(f"cannot read {what} file {path}: {type(exc).__name__}: {exc}") from None


def _check_var(ds, path, name, dims, units) -> None:
    if name not in ds:
        raise FluxFileError(f"{path}: missing variable '{name}'")
    var = ds[name]
    if tuple(var.dims) != tuple(dims):
        raise FluxFileError(f"{path}: variable '{name}' has dims {tuple(var.dims)}, expected {tuple(dims)}")
    if units is not None:
        got = str(var.attrs.get("units", "")).strip()
        if got not in units:
            raise FluxFileError(f"{path}: variable '{name}' has units '{got}', expected '{units[0]}'")
    if var.dtype.kind not in "fc":
        return
    for values in _blocks(var):
        if not np.all(np.isfinite(values)):
            bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
            raise FluxFileError(f"{path}: variable '{name}' has {bad} NaN/inf values")


def _blocks(var, max_bytes: int = 64 << 20):
    """The values of a (lazily opened) variable, block by block along its first dimension, each block
    at most about ``max_bytes``: a multi-GB variable is never whole in memory."""
    if var.ndim == 0:
        yield np.asarray(var.values)
        return
    row = max(1, int(np.prod(var.shape[1:])) * var.dtype.itemsize)
    step = max(1, max_bytes // row)
    for i in range(0, var.shape[0], step):
        yield np.asarray(var[i : i + step].values)


def _check_time(ds, path, name: str = "time") -> None:
    if name not in ds.coords and name not in ds:
        raise FluxFileError(f"{path}: missing coordinate '{name}'")
    t = np.asarray(ds[name].values)
    if t.dtype.kind != "M":
        raise FluxFileError(f"{path}: '{name}' is not a datetime coordinate (dtype {t.dtype})")
    if t.size < 2:
        raise FluxFileError(f"{path}: '{name}' needs at least 2 samples, has {t.size}")
    if np.any(np.isnat(t)):
        raise FluxFileError(f"{path}: '{name}' has missing values")
    if np.any(np.diff(t) <= np.timedelta64(0, "ns")):
        i = int(np.argmax(np.diff(t) <= np.timedelta64(0, "ns")))
        raise FluxFileError(f"{path}: '{name}' is not strictly increasing at index {i + 1} ({t[i + 1]})")


def _check_attr_range(ds, path, name, lo, hi, default=None) -> None:
    if name not in ds.attrs:
        if default is None:
            raise FluxFileError(f"{path}: missing global attribute '{name}'")
        ds.attrs[name] = default
        return
    try:
        value = float(ds.attrs[name])
    except (TypeError, ValueError):
        raise FluxFileError(f"{path}: attribute '{name}' = {ds.attrs[name]!r} is not a number") from None
    if not (lo <= value <= hi):
        raise FluxFileError(f"{path}: attribute '{name}' = {value} outside [{lo}, {hi}]")


def read_flux_dataset(path, load: bool = True) -> xr.Dataset:
    """Open and validate a flux dataset (any file with ``time``, ``solar_incident``, ``ir_incident``).

    The optional spin-up window (``spinup_solar_incident``, ``spinup_ir_incident`` on ``spinup_time``,
    ending at the first ``time``) is checked the same way when present.

    ``load=False`` keeps the variables on disk (read when used; validation reads them block by block),
    for runs too large to hold in memory.

    Raises :class:`FluxFileError` naming the problem: unreadable file, missing variable, wrong dims or
    units, NaN/inf, negative irradiance, non-monotonic time, albedo/emissivity attributes out of range.
    """
    ds = _open(path, "flux", load=load)
    groups = [("time", ("solar_incident", "ir_incident"))]
    if "spinup_solar_incident" in ds or "spinup_ir_incident" in ds:
        groups.append(("spinup_time", ("spinup_solar_incident", "spinup_ir_incident")))
    for time_name, names in groups:
        _check_time(ds, path, time_name)
        for name in names:
            _check_var(ds, path, name, (time_name, "facet"), FLUX_UNITS)
            if any(np.any(v < 0) for v in _blocks(ds[name])):
                raise FluxFileError(f"{path}: negative irradiance in {name}")
    if len(groups) > 1 and ds["spinup_time"].values[-1] > ds["time"].values[0]:
        raise FluxFileError(
            f"{path}: 'spinup_time' must end at or before the first 'time' "
            f"({ds['spinup_time'].values[-1]} > {ds['time'].values[0]})"
        )
    for name in ("solar_absorbed", "spinup_solar_absorbed"):  # optional: incidence-dependent albedo
        if name in ds:
            if ds[name].attrs.get("units") not in FLUX_UNITS:
                raise FluxFileError(
                    f"{path}: '{name}' has units {ds[name].attrs.get('units')!r}, expected {FLUX_UNITS[0]!r}"
                )
            if any(not np.all(np.isfinite(v)) or np.any(v < 0) for v in _blocks(ds[name])):
                raise FluxFileError(f"{path}: '{name}' has NaN/inf or negative values")
    _check_attr_range(ds, path, "albedo", 0.0, 1.0)
    _check_attr_range(ds, path, "emissivity", 1e-6, 1.0)
    return ds


def file_stamp(path) -> tuple[int, int]:
    """``(size [B], modification time [ns])`` of a file: what tells whether it changed since it was checked."""
    st = os.stat(path)
    return (int(st.st_size), int(st.st_mtime_ns))


def open_checked(path, stamp) -> xr.Dataset:
    """Open lazily, without reading its values again, a flux dataset that :func:`read_flux_dataset` checked
    when its :func:`file_stamp` was ``stamp`` (a replay's workers: each task reads its facets only, not the
    whole file to validate it again).

    Raises :class:`FluxFileError` when the file changed since (size or modification time) or is gone.
    """
    try:
        now = file_stamp(path)
    except OSError as exc:
        raise FluxFileError(f"flux file {path} is not readable here: {exc.strerror or exc}") from None
    if now != tuple(stamp):
        raise FluxFileError(
            f"flux file {path} changed after the replay checked it (size or modification time differs): "
            "leave it unchanged while the replay runs, and run the replay again"
        )
    return _open(path, "flux", load=False)


def open_written(path) -> xr.Dataset:
    """Open a dataset crater_thermal has just written, lazily and without re-validating its values (a
    100k-facet run is GBs; :func:`open_run` / :func:`open_replay` check files of unknown origin)."""
    return _open(path, "output", load=False)


def open_run(path, load: bool = True) -> xr.Dataset:
    """Open and validate a run dataset (flux schema + surface temperatures + mesh); ``load`` as in
    :func:`read_flux_dataset`."""
    ds = read_flux_dataset(path, load=load)
    _check_var(ds, path, "surface_temperature", ("time", "facet"), TEMPERATURE_UNITS)
    for name in ("mesh_vertices", "mesh_faces", "area"):
        if name not in ds:
            raise FluxFileError(f"{path}: missing variable '{name}'")
    return ds


def open_replay(path) -> xr.Dataset:
    """Open and validate a replay dataset (lazily: a density-grid replay can be GBs; read per profile)."""
    ds = _open(path, "replay", load=False)
    _check_time(ds, path)
    _check_var(ds, path, "surface_temperature", ("profile", "time", "facet"), TEMPERATURE_UNITS)
    for name in ("rho_top", "rho_bottom"):
        if name not in ds:
            raise FluxFileError(f"{path}: missing variable '{name}'")
    return ds


# ----------------------------------------------------------------------------- analysed datasets

#: Variables every analysed run dataset needs.
RUN_VARIABLES = ("time", "surface_temperature", "sun_direction", "centroid", "mesh_faces", "mesh_vertices")
#: Variables every analysed replay dataset needs.
REPLAY_VARIABLES = ("time", "surface_temperature", "profile")


def has_variable(ds, name: str) -> bool:
    """Whether ``ds[name]`` exists (a variable or coordinate of a dataset, a key of a mapping)."""
    try:
        ds[name]
        return True
    except KeyError:
        return False


def check_run(ds, required: Iterable[str] = RUN_VARIABLES) -> None:
    """Raise :class:`FluxFileError` if the run dataset lacks a required variable."""
    missing = [v for v in required if not has_variable(ds, v)]
    if missing:
        raise FluxFileError(f"run dataset is missing variable(s) {', '.join(missing)}; required: {', '.join(required)}")


def check_pair(run, replay) -> None:
    """Check that ``replay`` was made from ``run``: variables present, same mesh hash and time axis.

    Raises
    ------
    FluxFileError
        One line naming what does not match.
    """
    check_run(run)
    missing = [v for v in REPLAY_VARIABLES if not has_variable(replay, v)]
    if missing:
        raise FluxFileError(
            f"replay dataset is missing variable(s) {', '.join(missing)}; required: {', '.join(REPLAY_VARIABLES)}"
        )
    h_run, h_rep = run.attrs.get("mesh_hash"), replay.attrs.get("mesh_hash")
    if h_run is None or h_rep is None:
        raise FluxFileError("mesh_hash attribute missing from run or replay dataset; cannot check they match")
    if str(h_run) != str(h_rep):
        raise FluxFileError(
            f"replay mesh_hash={h_rep} does not match run mesh_hash={h_run}; the replay must be made from this run"
        )
    t_run = np.asarray(run["time"].values)
    t_rep = np.asarray(replay["time"].values)
    if t_run.shape != t_rep.shape or not np.array_equal(t_run, t_rep):
        raise FluxFileError(
            f"replay time axis ({t_rep.size} samples) does not match the run's "
            f"({t_run.size} samples from {t_run[0] if t_run.size else '-'}); "
            "the replay must cover the run's times"
        )
    dims = tuple(replay["surface_temperature"].dims)
    if dims != ("profile", "time", "facet"):
        raise FluxFileError(f"replay surface_temperature has dims {dims}; expected (profile, time, facet)")
    nf_run = run["surface_temperature"].shape[1]
    if replay["surface_temperature"].shape[2] != nf_run:
        raise FluxFileError(f"replay has {replay['surface_temperature'].shape[2]} facets, run has {nf_run}")


def mesh_meta(ds) -> dict:
    """The ``mesh_meta`` attribute as a dict (JSON string or dict)."""
    meta = ds.attrs.get("mesh_meta", {})
    if isinstance(meta, (str, bytes)):
        try:
            meta = json.loads(meta)
        except ValueError as exc:
            raise FluxFileError(f"mesh_meta attribute is not valid JSON: {exc}") from None
    return dict(meta)


def latitude_deg(ds) -> float:
    """The site centre's planetocentric latitude [deg] of a run, flux or replay dataset: its required
    ``lat_deg`` attribute (no default: a file without it is refused, never analysed at a guessed latitude).

    Raises
    ------
    FluxFileError
        ``lat_deg`` is missing, not a number, or outside [-90, 90].
    """
    try:
        lat = float(ds.attrs["lat_deg"])
    except (KeyError, TypeError, ValueError):
        raise FluxFileError(
            "dataset has no valid 'lat_deg' attribute (the site centre's planetocentric latitude [deg]); runs of "
            "crater-thermal have it, a file from elsewhere needs it added (e.g. ds.attrs['lat_deg'] = -86.0)"
        ) from None
    if not -90.0 <= lat <= 90.0:
        raise FluxFileError(f"dataset attribute lat_deg = {lat} is outside [-90, 90] deg")
    return lat


# ----------------------------------------------------------------------------- observations and posteriors

#: Columns of an observation table (:func:`read_observations`); the required ones first.
OBSERVATION_COLUMNS = (
    "time",
    "facet",
    "x_m",
    "y_m",
    "brightness_temperature_K",
    "sigma_K",
    "dwell_s",
    "band",
    "instrument",
    "footprint",
)
_OTHER_TEMPERATURE_UNITS = ("_c", "_degc", "_celsius", "_f", "_mk", "_degf")


def _observation_columns(path: Path) -> dict:
    """Raw columns of a CSV or netCDF observation table: name (lower case) -> 1-d array."""
    if path.suffix.lower() in (".nc", ".nc4", ".netcdf"):
        ds = _open(path, "observations")
        cols = {}
        for name in list(ds.data_vars) + list(ds.coords):
            v = ds[name]
            if v.ndim != 1:
                continue
            values = v.values
            if name.lower() == "brightness_temperature" and str(v.attrs.get("units", "K")) not in TEMPERATURE_UNITS:
                raise ConfigError(
                    f"observations {path}: brightness_temperature has units {v.attrs.get('units')!r}; K is needed"
                )
            key = "brightness_temperature_K" if name.lower() == "brightness_temperature" else name
            cols[key.lower() if key != "brightness_temperature_K" else key] = values
        return cols
    import pandas as pd

    try:
        df = pd.read_csv(path, skipinitialspace=True, comment="#")
    except FileNotFoundError:
        raise ConfigError(f"observations file {path} does not exist") from None
    except Exception as exc:  # pandas raises several parser errors
        raise ConfigError(f"cannot read observations {path}: {type(exc).__name__}: {exc}") from None
    return {str(c).strip(): df[c].to_numpy() for c in df.columns}


def read_observations(path: str | os.PathLike) -> dict:
    """Read an observation table (CSV with a header row, or netCDF with 1-d variables on one dimension).

    Columns (names as written; units in the names):

    - ``time``: UTC time of the sample, ISO 8601 (``2024-01-05T03:00:00``; a ``Z`` or ``+00:00`` suffix is
      allowed, other offsets are converted to UTC).
    - ``facet``, or ``x_m`` and ``y_m``: the facet seen, or the position [m] in the mesh frame (the run's
      ``centroid`` x, y), mapped to the nearest facet by the caller.
    - ``brightness_temperature_K``: measured band brightness temperature [K].
    - ``sigma_K`` (optional): stated 1-sigma white uncertainty [K]; empty: the instrument's noise model.
    - ``dwell_s`` (optional): time integrated for the sample [s].
    - ``band`` or ``instrument`` (optional): instrument preset name (one per table).
    - ``footprint`` (optional): footprint id (default: one footprint per facet).
    - ``radius_m`` (optional, with ``x_m``/``y_m``): footprint radius [m]: the sample mixes, in band
      radiance, the facets whose centroids lie within it, weighted by facet area (the nearest facet always).

    Parameters
    ----------
    path : path-like
        ``.csv`` (or any text) or ``.nc``.

    Returns
    -------
    dict
        ``time`` (n,) datetime64[ns] UTC, ``T_b_K`` (n,) [K], ``facet`` (n,) int or None, ``x_m``/``y_m``
        (n,) [m] or None, ``sigma_K``, ``dwell_s`` (n,) or None, ``footprint`` (n,) int or None,
        ``radius_m`` (n,) [m] or None, ``instrument`` str or None.

    Raises
    ------
    ConfigError
        One line: the file is missing or unreadable, a column is missing, named in other units
        (e.g. ``brightness_temperature_C``), or holds unparsable times or numbers.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"observations file {path} does not exist")
    cols = _observation_columns(path)
    for name in cols:
        low = name.lower()
        if low.startswith("brightness_temperature") and low != "brightness_temperature_k":
            raise ConfigError(
                f"observations {path}: column {name!r} is in other units; give brightness_temperature_K in K"
            )
    if "brightness_temperature_K" not in cols:
        raise ConfigError(
            f"observations {path}: missing column 'brightness_temperature_K' [K]; columns: {', '.join(cols)}"
        )
    if "time" not in cols:
        raise ConfigError(f"observations {path}: missing column 'time' (ISO 8601 UTC); columns: {', '.join(cols)}")
    has_facet = "facet" in cols
    has_xy = "x_m" in cols and "y_m" in cols
    if not has_facet and not has_xy:
        raise ConfigError(f"observations {path}: give a 'facet' column or 'x_m' and 'y_m' [m] (mesh frame)")
    import pandas as pd

    raw_t = cols["time"]
    if np.issubdtype(np.asarray(raw_t).dtype, np.datetime64):
        time = np.asarray(raw_t, "datetime64[ns]")
    else:
        try:
            time = pd.to_datetime(pd.Series(raw_t).astype(str).str.strip(), utc=True, format="ISO8601")
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"observations {path}: unparsable time ({exc}); give ISO 8601 UTC times") from None
        time = time.dt.tz_localize(None).to_numpy("datetime64[ns]")

    def number(name, integer=False):
        if name not in cols:
            return None
        try:
            a = np.asarray(pd.to_numeric(pd.Series(cols[name]), errors="raise"), float)
        except (ValueError, TypeError):
            raise ConfigError(f"observations {path}: column {name!r} holds something that is not a number") from None
        if integer:
            if np.any(~np.isfinite(a)) or np.any(a != np.round(a)):
                raise ConfigError(f"observations {path}: column {name!r} must hold whole numbers")
            return a.astype(np.int64)
        return a

    inst = None
    for key in ("instrument", "band"):
        if key in cols:
            names = sorted({str(v).strip() for v in cols[key] if str(v).strip() not in ("", "nan")})
            if len(names) > 1:
                raise ConfigError(f"observations {path}: one instrument per table, found {', '.join(names)}")
            inst = names[0] if names else inst
    return {
        "time": time,
        "T_b_K": number("brightness_temperature_K"),
        "facet": number("facet", integer=True) if has_facet else None,
        "x_m": number("x_m") if has_xy else None,
        "y_m": number("y_m") if has_xy else None,
        "sigma_K": number("sigma_K"),
        "dwell_s": number("dwell_s"),
        "footprint": number("footprint", integer=True),
        "radius_m": number("radius_m") if has_xy else None,
        "instrument": inst,
    }


def read_prior(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a prior over (top, bottom) density for the inversion from netCDF.

    The file holds ``prior(top, bottom)`` (non-negative weights) with coordinates ``top_kg_m3(top)`` and
    ``bottom_kg_m3(bottom)`` [kg m-3], e.g. a ``posterior.nc`` of ``crater-thermal invert`` (its ``prior``)
    edited, or one written with xarray.

    Returns
    -------
    (weights (n_top, n_bottom), top_kg_m3 (n_top,), bottom_kg_m3 (n_bottom,))

    Raises
    ------
    ConfigError
        One line: missing file or variable, wrong dimensions.
    """
    import xarray as xr

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"prior file {path} does not exist")
    try:
        ds = xr.open_dataset(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"prior file {path} is not readable netCDF ({' '.join(str(exc).split())})") from None
    with ds:
        if "prior" not in ds or ds["prior"].dims != ("top", "bottom"):
            raise ConfigError(f"prior file {path}: needs a variable prior(top, bottom) (e.g. a posterior.nc's)")
        for name in ("top_kg_m3", "bottom_kg_m3"):
            if name not in ds.variables:
                raise ConfigError(f"prior file {path}: missing coordinate {name} [kg m-3]")
        return (
            np.asarray(ds["prior"].values, float),
            np.asarray(ds["top_kg_m3"].values, float),
            np.asarray(ds["bottom_kg_m3"].values, float),
        )


def write_posterior(
    post,
    path: str | os.PathLike,
    overwrite: bool = False,
    attrs: Mapping[str, Any] | None = None,
    footprint_facet=None,
):
    """Write an inversion's posterior (:class:`crater_thermal.inversion.Posterior`) to netCDF atomically.

    Dimensions ``footprint``, ``top``, ``bottom`` (densities [kg m-3] as coordinates ``top_kg_m3``,
    ``bottom_kg_m3``). Variables: ``probability(footprint, top, bottom)`` (posterior mass per node),
    ``prior(top, bottom)``, ``marginal_top``, ``marginal_bottom``, ``p_loose`` (P(bottom < threshold)),
    ``map_top_kg_m3``/``map_bottom_kg_m3``, ``mean_*``, ``sd_*``, ``correlation``, ``credible_90``
    (bool mask of the 90 % highest-posterior region), ``log_evidence``, ``n_samples``, ``model_error_K``, ``degeneracy``
    (one sentence per footprint), and ``facet`` (footprint): the facet at the centre of all of a footprint's
    samples, -1 where their centres differ (``footprint_facet``; all -1 when not given), which maps the footprints
    (``crater-thermal export posterior.nc --run run.nc --variable p_loose``). ``attrs`` (prior,
    instrument, inputs, the run's ``mesh_hash``) go into the file's attributes.

    Returns
    -------
    xarray.Dataset
        The dataset written (in memory).
    """
    import xarray as xr

    fp = ("footprint",)
    mp, mean, sd = post.map_kg_m3, post.mean_kg_m3, post.sd_kg_m3
    kg = {"units": "kg m-3"}
    data = {
        "probability": (
            ("footprint", "top", "bottom"),
            post.probability,
            {"units": "1", "long_name": "posterior mass"},
        ),
        "prior": (("top", "bottom"), post.prior, {"units": "1", "long_name": "prior mass"}),
        "marginal_top": (("footprint", "top"), post.marginal_top, {"units": "1"}),
        "marginal_bottom": (("footprint", "bottom"), post.marginal_bottom, {"units": "1"}),
        "p_loose": (fp, post.p_loose, {"units": "1", "threshold_bottom_kg_m3": float(post.loose_bottom_kg_m3)}),
        "map_top_kg_m3": (fp, mp[:, 0], kg),
        "map_bottom_kg_m3": (fp, mp[:, 1], kg),
        "mean_top_kg_m3": (fp, mean[:, 0], kg),
        "mean_bottom_kg_m3": (fp, mean[:, 1], kg),
        "sd_top_kg_m3": (fp, sd[:, 0], kg),
        "sd_bottom_kg_m3": (fp, sd[:, 1], kg),
        "correlation": (fp, post.correlation, {"units": "1"}),
        "credible_90": (("footprint", "top", "bottom"), post.credible_region(0.9).astype(np.int8), {"units": "1"}),
        "log_evidence": (fp, post.log_evidence, {"units": "1"}),
        "n_samples": (fp, np.asarray(post.n_samples, np.int64), {"units": "1"}),
        "model_error_K": (
            fp,
            np.asarray(post.model_error_K, float),
            {"units": "K", "long_name": "rms over the footprint's samples of the model (interpolation) error 1-sigma"},
        ),
        "degeneracy": (fp, np.asarray(post.degeneracy(), dtype=str)),
        "facet": (
            fp,
            np.full(len(post.footprint), -1, np.int64)
            if footprint_facet is None
            else np.asarray(footprint_facet, np.int64).reshape(-1),
            {"long_name": "facet at the centre of all the footprint's samples (-1: several)"},
        ),
    }
    coords = {
        "footprint": np.asarray(post.footprint, np.int64),
        "top_kg_m3": (("top",), post.top_kg_m3, kg),
        "bottom_kg_m3": (("bottom",), post.bottom_kg_m3, kg),
    }
    out_attrs = {"loose_bottom_kg_m3": float(post.loose_bottom_kg_m3), "credible_mass": 0.9}
    for k, v in (attrs or {}).items():
        out_attrs[k] = json.dumps(v) if isinstance(v, (dict, list, tuple)) else v
    out_attrs["software_version"] = __version__
    ds = xr.Dataset(data, coords=coords, attrs=out_attrs)
    write_dataset_atomic(ds, path, overwrite=overwrite)
    return ds
