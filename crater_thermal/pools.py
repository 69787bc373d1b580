"""Thread pools kept for the whole process, one per purpose and thread count.

Starting threads for every batch of work costs more than some batches take (measured for the ray tracer
and the view-factor products, ``docs/performance.md``), so the modules that spread many small batches over
threads share a pool here instead. A pool belongs to the process that made it: a forked child has none of
its parent's threads, so it gets its own.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

_POOLS: dict = {}
_lock = threading.Lock()


def process_pool(name: str, n: int) -> ThreadPoolExecutor:
    """The process's pool of ``n`` threads named ``name`` (made on first use; per process id)."""
    key = (os.getpid(), name, n)
    with _lock:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(n, thread_name_prefix=name)
        return pool
