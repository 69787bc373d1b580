"""Exceptions. All subclass :class:`CraterThermalError` (a ``ValueError``).

The command line turns any of them into a one-line message and exit code 2.
"""


class CraterThermalError(ValueError):
    """Base class: a problem with the user's input or with a computation's result."""


class ConfigError(CraterThermalError):
    """A case file or command-line value is malformed or out of range."""


class ProfileError(CraterThermalError):
    """A density profile is impossible or not allowed."""


class MeshError(CraterThermalError):
    """A mesh is degenerate, inconsistent, or cannot be read."""


class DEMError(CraterThermalError):
    """A digital elevation model cannot be used: no or wrong CRS, holes, site off the raster, too large."""


class EphemerisRangeError(CraterThermalError):
    """A date lies outside the span of the loaded ephemeris."""


class FluxFileError(CraterThermalError):
    """A flux / run / replay dataset is missing variables, has bad units, NaNs, or does not match."""


class OutputExistsError(CraterThermalError):
    """An output exists and ``--overwrite`` was not given."""


class SolverError(CraterThermalError):
    """The conduction solver produced NaN/inf or its Newton iteration failed."""


class InternalError(RuntimeError):
    """A consistency check inside crater_thermal failed: a bug, not a problem with the input.

    Deliberately not a :class:`CraterThermalError`: the command line reports it as an internal error
    (exit code 3) and asks for a bug report, instead of blaming the user's input.
    """
