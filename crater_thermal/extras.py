"""Optional dependencies (package extras) that fail cleanly where they are used.

A feature that needs an extra imports it inside the function that uses it and turns an ``ImportError``
into :func:`missing_extra`'s one-line :class:`~crater_thermal.errors.MissingExtraError`, which names
the extra to install (``pip install 'crater_thermal[viz]'``) instead of a traceback; everything that
does not need the extra keeps working (trimesh's pattern)::

    try:
        import pyvista as pv
    except ImportError:
        raise missing_extra("pyvista", "viz", "3-D views") from None

(The import stays a plain ``import`` statement so that the import-linter contracts see it.)

Extras (see ``pyproject.toml``): ``viz`` (pyvista, imageio, imageio-ffmpeg: 3-D views, report
snapshots, MP4 animations) and ``distributed`` (dask.distributed: ``sweep --scheduler``).
"""

from __future__ import annotations

from crater_thermal.errors import ConfigError, MissingExtraError


def missing_extra(package: str, extra: str, purpose: str) -> MissingExtraError:
    """The error for a missing optional ``package`` of ``extra``, needed for ``purpose``.

    Parameters
    ----------
    package : str
        What is missing, e.g. ``"pyvista"``.
    extra : str
        The crater_thermal extra that installs it, e.g. ``"viz"``.
    purpose : str
        What needs it, plural, for the message: ``"3-D views"``, ``"MP4 animations"``.
    """
    return MissingExtraError(f"{purpose} need {package}, which is not installed: pip install 'crater_thermal[{extra}]'")


def connect_scheduler(scheduler: str, purpose: str, timeout_s: float, otherwise: str):
    """A dask.distributed ``Client`` of the scheduler at ``scheduler`` (``tcp://host:8786``).

    Parameters
    ----------
    scheduler : str
        The scheduler's address.
    purpose : str
        What needs dask.distributed, plural, for the missing-extra message (``"sweeps on a dask cluster"``).
    timeout_s : float [s]
        How long to wait for the scheduler to answer.
    otherwise : str
        The alternative the error offers, e.g. ``"leave out --scheduler"``.

    Raises
    ------
    MissingExtraError
        dask.distributed is not installed.
    ConfigError
        No scheduler answers at that address within ``timeout_s`` (refused, unreachable, malformed).
    """
    try:
        from distributed import Client
    except ImportError:
        raise missing_extra("dask.distributed", "distributed", purpose) from None
    try:
        return Client(scheduler, timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:  # refused, unreachable, timed out, malformed
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise ConfigError(
            f"--scheduler {scheduler}: cannot reach a dask scheduler there ({reason}); start one "
            f"(dask scheduler) or {otherwise}"
        ) from None
