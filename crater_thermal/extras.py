"""Optional dependencies (package extras) that fail cleanly where they are used.

A feature that needs an extra imports it through :func:`optional_import`; when the package is not
installed the user gets a one-line :class:`~crater_thermal.errors.MissingExtraError` naming the
extra to install (``pip install 'crater_thermal[viz]'``) instead of a traceback, and everything
that does not need the extra keeps working.

Extras (see ``pyproject.toml``): ``viz`` (pyvista, imageio, imageio-ffmpeg: 3-D views, report
snapshots, MP4 animations) and ``distributed`` (dask.distributed: ``sweep --scheduler``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from crater_thermal.errors import MissingExtraError


def missing_extra(package: str, extra: str, purpose: str) -> MissingExtraError:
    """The error for a missing optional ``package`` of ``extra``, needed for ``purpose``."""
    return MissingExtraError(f"{purpose} need {package}, which is not installed: "
                             f"pip install 'crater_thermal[{extra}]'")


def optional_import(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` or raise :class:`~crater_thermal.errors.MissingExtraError` naming ``extra``.

    Parameters
    ----------
    module : str
        Module to import, e.g. ``"pyvista"`` or ``"distributed"``.
    extra : str
        The crater_thermal extra that installs it.
    purpose : str
        What needs it, for the message (plural: "3-D views", "sweeps on a dask cluster").
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        package = module.split(".")[0]
        if exc.name is not None and exc.name.split(".")[0] != package:
            package = f"{package} (its dependency {exc.name.split('.')[0]} is missing)"
        raise missing_extra(package, extra, purpose) from None
