"""Which modules a ``radiokit acquire`` process first imports while its X-rays may be on.

Installed in the command's own process (``tests/test_safety.py``'s ``Acquire(record_imports=...)``)
before ``radiokit.cli`` runs: a ``sys.meta_path`` finder notes every module not yet in
``sys.modules`` that is imported while any driver's ``may_be_on`` is true (from before an XON or
a warm-up, or a tube found on, until a switch-off is confirmed) and no signal guard is stopping
(the switch-off then owns the run: a stop is only acknowledged, never waited for). At exit the
list goes to a JSON file: ``[[seconds since install, module, thread], ...]``.

Why: a stop signal that lands inside an import waits for the import's end
(``radiokit.interrupts.after_import``), the tube on meanwhile.
"""

from __future__ import annotations

import atexit
import json
import sys
import threading
import time
import weakref


def install(path: str) -> None:
    """Record into ``path`` (written at exit) what is first imported while X-rays may be on."""
    import acquisition.guardian as guardian
    import acquisition.l8121 as l8121

    t0 = time.monotonic()
    guards = weakref.WeakSet()
    drivers = weakref.WeakSet()
    seen: list = []

    class MayBeOn:
        """``L8121._may_be_on`` kept where it was, its driver noted."""

        def __get__(self, obj, cls=None):
            return self if obj is None else obj.__dict__.get("_may_be_on_recorded", False)

        def __set__(self, obj, value):
            drivers.add(obj)
            obj.__dict__["_may_be_on_recorded"] = value

    l8121.L8121._may_be_on = MayBeOn()
    guard_init = guardian.SignalGuard.__init__

    def init(self, *args, **kwargs):
        guard_init(self, *args, **kwargs)
        guards.add(self)

    guardian.SignalGuard.__init__ = init

    class Finder:
        def find_spec(self, name, path=None, target=None):
            on = any(d.__dict__.get("_may_be_on_recorded") for d in list(drivers))
            if on and not any(g.stopping for g in list(guards)):
                seen.append([round(time.monotonic() - t0, 4), name, threading.current_thread().name])
            return None  # the other finders find it

    sys.meta_path.insert(0, Finder())

    def write():
        with open(path, "w") as fh:
            json.dump(seen, fh)

    atexit.register(write)
