"""Which modules a ``radiokit acquire`` process first imports once its series may have X-rays on.

Installed in the command's own process (``tests/test_safety.py``'s ``Acquire(record_imports=...)``)
before ``radiokit.cli`` runs: a ``sys.meta_path`` finder notes every module not yet in
``sys.modules`` that is imported from the moment any driver's ``may_be_on`` first turns true (the
first X-ray command: a warm-up, an XON, or a tube found on) until a signal guard is stopping
(the switch-off owns the run from then on: a stop is only acknowledged, never waited for). At exit
the list goes to a JSON file: ``[[seconds since install, module, thread, X-rays may be on now], ...]``.

Why: a stop signal that lands inside an import waits for the import's end
(``radiokit.interrupts.after_import``), with the tube on if it is; and one held past the wait's
cap is raised inside the import, where a Cython module's bare ``except:`` may swallow it.
"""

from __future__ import annotations

import atexit
import json
import sys
import threading
import time
import weakref


def install(path: str) -> None:
    """Record into ``path`` (written at exit) what is first imported while the series may emit."""
    import acquisition.guardian as guardian
    import acquisition.l8121 as l8121

    t0 = time.monotonic()
    armed = []  # set once any driver's may_be_on turned true
    guards = weakref.WeakSet()
    drivers = weakref.WeakSet()
    seen: list = []

    class MayBeOn:
        """``L8121._may_be_on`` kept where it was, and the first time it turns true noted."""

        def __get__(self, obj, cls=None):
            return self if obj is None else obj.__dict__.get("_may_be_on_recorded", False)

        def __set__(self, obj, value):
            drivers.add(obj)
            if value and not armed:
                armed.append(time.monotonic() - t0)
            obj.__dict__["_may_be_on_recorded"] = value

    l8121.L8121._may_be_on = MayBeOn()
    guard_init = guardian.SignalGuard.__init__

    def init(self, *args, **kwargs):
        guard_init(self, *args, **kwargs)
        guards.add(self)

    guardian.SignalGuard.__init__ = init

    class Finder:
        def find_spec(self, name, path=None, target=None):
            if armed and not any(g.stopping for g in list(guards)):
                on = any(d.__dict__.get("_may_be_on_recorded") for d in list(drivers))
                seen.append([round(time.monotonic() - t0, 4), name, threading.current_thread().name, on])
            return None  # the other finders find it

    sys.meta_path.insert(0, Finder())

    def write():
        with open(path, "w") as fh:
            json.dump(seen, fh)

    atexit.register(write)
