"""How many threads radiokit's own pools (correction, registration, FFTs) may use in this process,
and the one pool they share.

``RADIOKIT_THREADS`` when set (``radiokit process`` sets it in each Dask worker to the worker's
share of the cores), else the cores this process may run on, at most 8.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor


def cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads() -> int:
    """The thread budget of radiokit's pools in this process (see the module docstring)."""
    env = os.environ.get("RADIOKIT_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n < 1:  # "0" or "-2" was quietly one thread
            raise ValueError(f"RADIOKIT_THREADS={env!r}: expected a whole number of threads, at least 1")
        return n
    return min(cores(), 8)


_POOLS: dict = {}
_POOLS_LOCK = threading.Lock()


def pool() -> ThreadPoolExecutor:
    """The thread pool of radiokit's parallel loops (correction, registration), of
    :func:`threads` threads. One pool per size, kept: a Dask worker changes ``RADIOKIT_THREADS``
    between tasks, and a pool shut down under a loop that is still using it would fail."""
    n = threads()
    with _POOLS_LOCK:
        if n not in _POOLS:
            _POOLS[n] = ThreadPoolExecutor(n, thread_name_prefix=f"radiokit-{n}")
        return _POOLS[n]
