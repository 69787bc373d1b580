"""Progress bars for the commands: the only module that imports rich.progress.

Computations never draw anything: a function with long-running work takes an optional
``progress`` argument and reports through it. There is one contract:

``ProgressCallback = Callable[[int, int], None]``
    ``progress(done, total)``: ``done`` of ``total`` work units (chunks, batches, time steps,
    profiles, frames) are finished. Called with ``done = 0`` at the start is allowed, never with
    ``done > total``; a computation may call it from worker threads, in order.

A function that runs several stages one after the other (a coupled run: view factors, direct
sunlight, spin-up, recorded period) takes a ``Reporter`` instead: a callable that, given the
stage's description, returns a context manager yielding that stage's ``ProgressCallback``.
:func:`reporter` makes one for a command; ``None`` (the default everywhere) means no progress.

Where progress goes (stderr always): on a terminal, a rich bar per stage; elsewhere (a log file, a
batch job, CI) plain lines, at most one every :data:`LINE_INTERVAL_S` seconds per stage
(``CRATER_THERMAL_PROGRESS_INTERVAL_S`` sets another interval), each with
the stage, the work done, the elapsed time and the estimated time left, and one closing line for a
stage that printed any. ``--quiet`` (or ``CRATER_THERMAL_QUIET`` set) prints nothing;
``--progress`` forces progress even where the default would be quiet.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from typing import Callable, ContextManager, Iterator, Optional

#: ``progress(done, total)``: work units finished so far, out of ``total``.
ProgressCallback = Callable[[int, int], None]
#: ``reporter(description)``: a context manager yielding the stage's :data:`ProgressCallback`.
Reporter = Callable[[str], ContextManager[ProgressCallback]]


def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A ``warnings.showwarning`` printing ``warning: MESSAGE`` on one line, without the source line."""
    print(f"warning: {' '.join(str(message).split())}", file=sys.stderr if file is None else file)


#: Least time between two progress lines of one stage outside a terminal [s].
LINE_INTERVAL_S = 30.0


def enabled(flag: Optional[bool] = None) -> bool:
    """Whether to report progress at all: ``flag`` if given, else unless ``CRATER_THERMAL_QUIET`` is set."""
    if flag is not None:
        return bool(flag)
    return not os.environ.get("CRATER_THERMAL_QUIET")


def _on_terminal() -> bool:
    return sys.stderr.isatty() and not os.environ.get("CI")


def _duration(seconds: float) -> str:
    """``'42 s'``, ``'12 min 5 s'``, ``'3 h 20 min'``."""
    s = int(round(max(0.0, seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60} min"


class LineProgress:
    """A :data:`ProgressCallback` writing plain progress lines (for logs, batch jobs and CI).

    ``progress(done, total)`` prints ``progress: DESCRIPTION: done/total (P %), T elapsed, eta E`` when
    at least ``interval_s`` seconds have passed since the stage began or since its last line;
    :meth:`close` prints ``progress: DESCRIPTION: done in T`` if any line was printed. ``clock`` and
    ``stream`` are for tests (defaults: ``time.monotonic`` and ``sys.stderr``).
    """

    def __init__(self, description: str, interval_s: float = LINE_INTERVAL_S, clock=time.monotonic, stream=None):
        self.description = description
        self.interval_s = float(interval_s)
        self.clock = clock
        self.stream = stream
        self.t0 = self.last = clock()
        self.printed = 0
        self._lock = threading.Lock()

    def _print(self, text: str) -> None:
        print(f"progress: {self.description}: {text}", file=self.stream or sys.stderr, flush=True)
        self.printed += 1

    def __call__(self, done: int, total: int) -> None:
        with self._lock:
            now = self.clock()
            if now - self.last < self.interval_s:
                return
            self.last = now
            elapsed = now - self.t0
            line = f"{done}/{total}"
            if total > 0:
                line += f" ({100.0 * done / total:.0f} %), {_duration(elapsed)} elapsed"
                if 0 < done < total:
                    line += f", eta {_duration(elapsed * (total - done) / done)}"
            else:
                line += f", {_duration(elapsed)} elapsed"
            self._print(line)

    def close(self) -> None:
        """End of the stage: a closing line if the stage printed any."""
        with self._lock:
            if self.printed:
                self._print(f"done in {_duration(self.clock() - self.t0)}")


@contextlib.contextmanager
def bar(description: str, flag: Optional[bool] = None) -> Iterator[Optional[ProgressCallback]]:
    """Progress of one stage on stderr, yielding its :data:`ProgressCallback` (``None`` when quiet).

    On a terminal: a rich bar with ``done/total``, the elapsed time and an estimate of the time left,
    removed when the stage ends. Elsewhere: :class:`LineProgress` lines.
    """
    if not enabled(flag):
        yield None
        return
    if not _on_terminal():
        lines = LineProgress(
            description, float(os.environ.get("CRATER_THERMAL_PROGRESS_INTERVAL_S") or LINE_INTERVAL_S)
        )
        try:
            yield lines
        finally:
            lines.close()
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
    )
    lock = threading.Lock()
    with Progress(*columns, console=Console(stderr=True), transient=True) as prog:
        task = prog.add_task(description, total=None)

        def callback(done: int, total: int) -> None:
            with lock:
                prog.update(task, completed=done, total=total)

        yield callback


def reporter(flag: Optional[bool] = None) -> Optional[Reporter]:
    """A :data:`Reporter` reporting each stage through :func:`bar`, or ``None`` when quiet."""
    if not enabled(flag):
        return None
    return lambda description: bar(description, True)
