"""Large temporary arrays reused from the heap during a run, instead of fresh memory maps (glibc's malloc).

glibc's ``malloc`` serves every block above its mmap threshold (at most 32 MB) from a fresh anonymous
memory map and unmaps it when freed. A run at 100,000 facets makes thousands of numpy temporaries of
tens of MB (a block of 64 samples x 100,000 facets in float64 is 51 MB), so each one is faulted in
page by page, zero-filled by the kernel, on first touch, which can cost as much as the arithmetic on it
(measured in ``docs/performance.md``). Inside :func:`reuse_large_blocks` malloc maps nothing
(``M_MMAP_MAX`` 0) and keeps up to 2 GB freed at the heap's top (``M_TRIM_THRESHOLD``), so freed blocks
are handed out again without page faults; the price is a higher peak resident memory, since freed
memory stays with the process until the block ends and the heap is trimmed. A run and a replay hold the
block while they run; a dask session's workers hold it while the session lasts (``cluster.connect``).

The settings are the process's (every thread's), glibc has no call that reads them back: on leaving the
outermost block they are set to glibc's defaults (65,536 maps, 128 kB) and the heap is trimmed. Other C
libraries (musl, macOS) are left alone, as is everything when the environment variable
``CRATER_THERMAL_HEAP_REUSE`` is ``0``.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import threading

M_TRIM_THRESHOLD = -1  # mallopt parameters (malloc.h)
M_MMAP_MAX = -4
DEFAULT_MMAP_MAX = 65536  # glibc's defaults
DEFAULT_TRIM_THRESHOLD = 128 * 1024
#: Freed bytes kept at the heap's top inside :func:`reuse_large_blocks` [bytes] (mallopt takes an int).
KEEP_BYTES = 2**31 - 1

_lock = threading.Lock()
_depth = 0


def _glibc():
    """glibc's ``mallopt``/``malloc_trim`` through ctypes, or None (another C library, or switched off)."""
    if os.environ.get("CRATER_THERMAL_HEAP_REUSE", "1").strip() == "0":
        return None
    return _process_glibc()


@functools.cache
def _process_glibc():
    """The C library this process already runs on (its malloc is numpy's), if it is glibc; looked up once."""
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.malloc_trim.argtypes = (ctypes.c_size_t,)
        libc.gnu_get_libc_version  # glibc only  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


@contextlib.contextmanager
def reuse_large_blocks():
    """Inside the block, large allocations come from the heap and freed ones stay there to be reused (see
    the module's text); nested blocks share the outermost one's setting. Yields whether it applies."""
    global _depth
    libc = _glibc()
    if libc is None:
        yield False
        return
    with _lock:
        _depth += 1
        if _depth == 1:
            libc.mallopt(M_MMAP_MAX, 0)
            libc.mallopt(M_TRIM_THRESHOLD, KEEP_BYTES)
    try:
        yield True
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                libc.mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
                libc.mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
                libc.malloc_trim(0)
