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

Bars go to stderr, only on a terminal by default, never in CI (``CI`` set) or with
``CRATER_THERMAL_QUIET`` set; ``--progress/--quiet`` override.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from typing import Callable, ContextManager, Iterator, Optional

#: ``progress(done, total)``: work units finished so far, out of ``total``.
ProgressCallback = Callable[[int, int], None]
#: ``reporter(description)``: a context manager yielding the stage's :data:`ProgressCallback`.
Reporter = Callable[[str], ContextManager[ProgressCallback]]


def enabled(flag: Optional[bool] = None) -> bool:
    """Whether to draw progress bars: ``flag`` if given, else only on a terminal and not in CI."""
    if flag is not None:
        return bool(flag)
    if os.environ.get("CI") or os.environ.get("CRATER_THERMAL_QUIET"):
        return False
    return sys.stderr.isatty()


@contextlib.contextmanager
def bar(description: str, flag: Optional[bool] = None) -> Iterator[Optional[ProgressCallback]]:
    """A rich bar on stderr for one stage, yielding its :data:`ProgressCallback` (``None`` when disabled).

    The bar shows ``done/total``, the elapsed time and an estimate of the time left; it is removed
    when the stage ends.
    """
    if not enabled(flag):
        yield None
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
    """A :data:`Reporter` drawing one :func:`bar` per stage, or ``None`` when bars are disabled."""
    if not enabled(flag):
        return None
    return lambda description: bar(description, True)
