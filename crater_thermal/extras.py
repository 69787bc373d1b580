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

from crater_thermal.errors import MissingExtraError


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
