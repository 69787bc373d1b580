"""Large temporaries reused from the heap during a run (``crater_thermal.heap``), checked with glibc's own
accounting (``mallinfo2``: bytes in memory maps, bytes free in the heap), independent of our code."""

import ctypes
import ctypes.util

import numpy as np
import pytest

from crater_thermal import heap


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def _mallinfo():
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    try:
        f = libc.mallinfo2
    except AttributeError:
        pytest.skip("not glibc >= 2.33 (no mallinfo2)")
    f.restype = _MallInfo2
    return f


MB = 1 << 20


def _mapped_while_held(nbytes: int) -> int:
    """Bytes glibc holds in memory maps while an array of ``nbytes`` more than every free byte of the heap
    is alive, less those before. (glibc serves a request from a free heap chunk large enough before it
    maps anything, whatever its threshold; an earlier test's run can leave such a chunk below a block that
    outlives the run, which ``malloc_trim`` cannot hand back. The array is not touched: no memory is used.)"""
    info = _mallinfo()
    first = info()
    a = np.empty((nbytes + first.fordblks) // 8)
    during = info().hblkhd
    del a
    return during - first.hblkhd


def test_large_arrays_come_from_the_heap_inside_and_from_maps_outside():
    if heap._glibc() is None:
        pytest.skip("glibc's mallopt is not available here")
    assert _mapped_while_held(64 * MB) >= 64 * MB  # glibc's default: a block this large is a fresh map
    with heap.reuse_large_blocks() as applies:
        assert applies
        assert _mapped_while_held(64 * MB) == 0
        info = _mallinfo()
        a = np.ones(64 * MB // 8)
        del a
        assert info().fordblks >= 64 * MB  # freed, kept in the heap for the next temporary
        with heap.reuse_large_blocks():  # nested: the outer setting holds after the inner block
            pass
        assert _mapped_while_held(64 * MB) == 0
    assert _mapped_while_held(64 * MB) >= 64 * MB  # defaults back after the outermost block
    assert _mallinfo()().keepcost < MB  # and the heap trimmed: its top's free memory given back


def test_switched_off_by_the_environment(monkeypatch):
    monkeypatch.setenv("CRATER_THERMAL_HEAP_REUSE", "0")
    with heap.reuse_large_blocks() as applies:
        assert not applies


def test_default_maps_even_after_a_run_left_a_large_free_chunk_in_the_heap():
    """The state the first test met in CI: a block allocated during a run outlives it, above a freed large
    one; glibc then serves the next large request from that chunk (no map), so the probe asks for more than
    every free byte of the heap to see glibc's default."""
    if heap._glibc() is None:
        pytest.skip("glibc's mallopt is not available here")
    with heap.reuse_large_blocks():
        big = np.ones(100 * MB // 8)
        kept = np.ones(300_000)  # above ``big`` in the heap, alive after the block
        del big
    assert _mallinfo()().fordblks >= 64 * MB  # the freed chunk is still in the heap
    assert _mapped_while_held(64 * MB) >= 64 * MB
    del kept
