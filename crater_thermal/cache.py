"""The on-disk cache: view factors and horizon maps, kept by mesh hash so that a second run of the same
mesh skips their computation.

Where
    ``$CRATER_THERMAL_CACHE`` if set, else ``~/.cache/crater_thermal`` (``$XDG_CACHE_HOME/crater_thermal``
    where ``XDG_CACHE_HOME`` is set). One sub-folder per kind of entry (:data:`KINDS`).
What
    ``viewfactors/``: exact sparse view-factor matrices (``.npz``; the compressed operator of a large
    mesh is rebuilt each run, not cached); ``horizons/``: horizon maps (``.npz``, float32, 4 bytes per
    facet and azimuth). Each file name holds the mesh hash and the version of the algorithm that made
    it, so a changed mesh or algorithm never reads a stale entry.
Deleting it
    is always safe: every entry is recomputed when next needed (``crater-thermal cache clear``).
Unwritable
    A cache folder that cannot be created or written gives one warning and the run goes on uncached.
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

from crater_thermal.errors import ConfigError

#: Sub-folders of the cache, one per kind of entry.
KINDS = ("viewfactors", "horizons")

_warned: set = set()


def root() -> Path:
    """The cache folder: ``$CRATER_THERMAL_CACHE``, else ``$XDG_CACHE_HOME/crater_thermal``, else
    ``~/.cache/crater_thermal``."""
    env = os.environ.get("CRATER_THERMAL_CACHE")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "crater_thermal"


def folder(kind: str) -> Path | None:
    """A writable cache folder for ``kind`` (one of :data:`KINDS`), created if needed, or ``None``.

    ``None`` (with one warning per cache root and process) when the folder cannot be created or written:
    the caller then computes without a cache.
    """
    if kind not in KINDS:
        raise ConfigError(f"cache kind {kind!r} not one of {', '.join(KINDS)}")
    path = root() / kind
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".probe.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return path
    except OSError as exc:
        if str(root()) not in _warned:  # one warning per cache and process
            _warned.add(str(root()))
            warnings.warn(
                f"the cache {root()} is not writable ({exc.strerror or exc}); running without a cache (set "
                "CRATER_THERMAL_CACHE to a writable folder to keep view factors and horizon maps between runs)",
                stacklevel=2,
            )
        return None


def info() -> dict:
    """What the cache holds: ``{"root": str, "exists": bool, "kinds": {kind: {"files": n, "bytes": b}},
    "files": n, "bytes": b}`` (sizes in bytes)."""
    base = root()
    kinds = {}
    for kind in KINDS:
        files = [p for p in (base / kind).rglob("*") if p.is_file()] if (base / kind).is_dir() else []
        kinds[kind] = {"files": len(files), "bytes": sum(_size(p) for p in files)}
    return {
        "root": str(base),
        "exists": base.is_dir(),
        "kinds": kinds,
        "files": sum(k["files"] for k in kinds.values()),
        "bytes": sum(k["bytes"] for k in kinds.values()),
    }


def clear(kind: str | None = None) -> dict:
    """Delete the cache's entries (of one ``kind``, or all); returns ``{"files": n, "bytes": b}`` removed.

    Only the sub-folders in :data:`KINDS` are removed, never anything else that happens to sit in the
    cache's root (a ``CRATER_THERMAL_CACHE`` pointing at a shared folder stays safe).
    """
    before = info()
    kinds = KINDS if kind is None else (kind,)
    for k in kinds:
        if k not in KINDS:
            raise ConfigError(f"cache kind {k!r} not one of {', '.join(KINDS)}")
        shutil.rmtree(root() / k, ignore_errors=True)
    return {
        "files": sum(before["kinds"][k]["files"] for k in kinds),
        "bytes": sum(before["kinds"][k]["bytes"] for k in kinds),
    }


def _size(p: Path) -> int:
    try:
        return p.stat().st_size
    except OSError:
        return 0
