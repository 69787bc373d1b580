"""glibc's own heap accounting (``mallinfo2``), independent of ``crater_thermal.heap``: for the heap tests, in
this process and, shipped by value (``cloudpickle.register_pickle_by_value``), on dask workers."""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np


def mallinfo():
    """glibc's ``mallinfo2`` (call it for its fields, as attributes), or None (not glibc >= 2.33). The
    structure's class is made here, in the process that calls it: ctypes fields cannot be pickled."""

    names = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")
    fields = [(name, ctypes.c_size_t) for name in names]  # glibc's struct mallinfo2, all size_t

    class MallInfo2(ctypes.Structure):
        _fields_ = fields

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    try:
        f = libc.mallinfo2
    except AttributeError:
        return None
    f.restype = MallInfo2
    return f


def mapped_while_held(nbytes: int):
    """Bytes glibc holds in memory maps while an array of ``nbytes`` more than every free byte of the heap
    is alive, less those before; None without ``mallinfo2``. (glibc serves a request from a free heap chunk
    large enough before it maps anything, whatever its threshold; an earlier test's run can leave such a
    chunk below a block that outlives the run, which ``malloc_trim`` cannot hand back. The array is not
    touched: no memory is used.)"""
    info = mallinfo()
    if info is None:
        return None
    first = info()
    a = np.empty((nbytes + first.fordblks) // 8)
    during = info().hblkhd
    del a
    return during - first.hblkhd
