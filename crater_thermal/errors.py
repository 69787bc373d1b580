"""Exceptions: what went wrong, and whose move it is.

Two families, told apart by the command line:

Problems with the input (:class:`CraterThermalError`, a ``ValueError``; exit code 2)
    A case file, command-line value, mesh, flux file, density profile, date, output path or
    installation the user can fix. The message is one line naming the parameter, the value and
    what is allowed: :class:`ConfigError`, :class:`ProfileError`, :class:`MeshError`,
    :class:`EphemerisRangeError`, :class:`FluxFileError`, :class:`OutputExistsError`,
    :class:`DiskSpaceError`, :class:`MissingExtraError`. Inputs are checked at the edge, before
    any ray is traced, so these come early.
Failures inside crater_thermal (:class:`InternalError`, a ``RuntimeError``; exit code 3)
    A consistency check or a numerical method failed on input that passed the checks: a bug (or
    a limit of a method) to report, not the user's fault. :class:`SolverError` (the conduction
    solver produced NaN/inf, its Newton iteration did not converge, or it was called
    inconsistently) belongs here: bad user input is refused before it reaches the solver, so
    it must never surface as a SolverError.

The command line prints ``error: ...`` (one line) for the first family and ``internal error:
...`` (one line, asking for a bug report) for the second, never a traceback.
"""

import sys


class CraterThermalError(ValueError):
    """Base class of the problems with the user's input (exit code 2)."""


class ConfigError(CraterThermalError):
    """A case file or command-line value is malformed or out of range."""


class ProfileError(CraterThermalError):
    """A density profile is impossible or not allowed."""


class MeshError(CraterThermalError):
    """A mesh is degenerate, inconsistent, faces downward, or cannot be read."""


class DEMError(CraterThermalError):
    """A digital elevation model cannot be used: no or wrong CRS, holes, site off the raster, too large."""


class EphemerisRangeError(CraterThermalError):
    """A date lies outside the span of the loaded ephemeris."""


class FluxFileError(CraterThermalError):
    """A flux / run / replay dataset is missing variables, has bad units, NaNs, or does not match."""


class OutputExistsError(CraterThermalError):
    """An output exists and ``--overwrite`` was not given."""


class OutputLockedError(CraterThermalError):
    """Another live process is writing the same output (its lock file is beside the output)."""


class DiskSpaceError(CraterThermalError):
    """The output's disk cannot hold what a run would write (refused before the work starts)."""


class MissingExtraError(CraterThermalError):
    """An optional dependency (a package extra such as ``viz`` or ``distributed``) is not installed."""


class InternalError(RuntimeError):
    """A consistency check inside crater_thermal failed: a bug, not a problem with the input.

    Deliberately not a :class:`CraterThermalError`: the command line reports it as an internal error
    (exit code 3) and asks for a bug report, instead of blaming the user's input.
    """


class SolverError(InternalError):
    """The conduction solver produced NaN/inf, its Newton iteration failed, or it was called inconsistently.

    An internal failure (exit code 3): user input is validated before it reaches the solver.
    """


class Interrupted(BaseException):
    """The command was stopped by a signal: SIGINT (Ctrl-C, exit code 130) or SIGTERM (exit code 143).

    A ``BaseException`` like ``KeyboardInterrupt``, so that no ``except Exception`` swallows it, but a
    class of its own, so that nothing mistakes it for a finished command. Raised in the main thread by
    the handlers the command line installs; every writer then removes its temporary files and leaves
    existing outputs untouched. ``hint`` (set by a command on its way out) tells how to resume.
    """

    def __init__(self, signum: int, hint: str = ""):
        super().__init__(signum)
        self.signum = int(signum)
        self.hint = hint

    @property
    def exit_code(self) -> int:
        """128 + the signal number (the shell's convention): 130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        """``SIGINT``, ``SIGTERM``, ..."""
        import signal

        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"


#: Signal numbers received by the command line's handlers, oldest first (see :func:`raise_if_interrupted`).
_RECEIVED_SIGNALS: list = []


def note_interrupt(signum: int) -> None:
    """Record that signal ``signum`` asked the process to stop (called by the signal handlers just before they
    raise :class:`Interrupted`).

    From then on the process's unraisable exceptions are dropped: the raise can land inside a library's
    constructor (llvmlite's ``OutputString`` while numba compiles, seen in CI), whose destructor then fails
    on the half-built object when it is freed, and Python would print that failure as a traceback after
    the one-line message. It is a consequence of the interruption already reported, not a separate problem.
    """
    _RECEIVED_SIGNALS.append(int(signum))
    sys.unraisablehook = _drop_unraisable


def _drop_unraisable(unraisable) -> None:
    """``sys.unraisablehook`` after a stop signal (see :func:`note_interrupt`): print nothing."""


def raise_if_interrupted() -> None:
    """Raise :class:`Interrupted` if a stop signal was received, even where its first raise was lost.

    A signal handler's exception surfaces wherever Python happens to be; C code that calls back into Python
    and clears every error (some attribute probes do) can swallow it, and the command would then run to
    the end and write its output as if never interrupted. Writers call this just before an output's
    final rename (the commit point), so a received signal always prevents the commit.
    """
    if _RECEIVED_SIGNALS:
        raise Interrupted(_RECEIVED_SIGNALS[0])
