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
            _POOLS[n] = _started_pool(n)
        return _POOLS[n]


def _started_pool(n: int) -> ThreadPoolExecutor:
    """A pool of ``n`` threads whose first thread is made, and registered for the interpreter's
    exit, while stop signals are held (then delivered: :func:`radiokit.interrupts.held`).

    Why: the pool makes its threads on demand and registers each, to be woken at exit, only after
    ``Thread.start()`` returns; a stop that landed inside ``start()`` (it waits for the new thread)
    left a thread nobody wakes, and the process hung for good at its end, in
    ``threading._shutdown``, after printing "interrupted" (a stop lost in a finalizer, delivered
    again 50 ms later, at `correct`'s first frame). Threads made later share the registered
    one's queue, which the exit wakes in a chain."""
    from radiokit.interrupts import STOP_SIGNALS, held

    with held(*STOP_SIGNALS):
        executor = ThreadPoolExecutor(n, thread_name_prefix=f"radiokit-{n}")
        executor.submit(int).result()
    return executor
