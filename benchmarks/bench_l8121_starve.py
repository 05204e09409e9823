"""How long a tight-loop poller on another thread delays ``set_values`` and ``off`` (L8121).

A thread calls the driver's public readings back to back (``status()`` -- a user's own status
loop; or ``check()`` -- a beam monitor with no period) while the main thread calls
``set_values`` (X-rays off: presets and their read-back) or ``off()`` (X-rays on). The emulator
runs in a child process on a pty this script creates (so that its thread does not share this
process's GIL: a real controller is another device), with each reply held for ``--reply-ms``
(what ~10 characters take at 9600 baud). The driver's timing is the dialects' own (60 ms
between commands, 2 s reply time-out).

Each call's time is capped at ``--cap`` s: past it the poller is paused so the call can end, and
the figure reads ">= cap" (it was starved for that long at least).

    .venv/bin/python benchmarks/bench_l8121_starve.py --tries 20
"""

from __future__ import annotations

import argparse
import functools
import statistics
import subprocess
import sys
import threading
import time

from acquisition.l8121 import L8121

_SERVE = """
import sys, time
from acquisition.emulators.l8121 import L8121Model, PtyServer
model = L8121Model(dialect=sys.argv[1], warmed_up=True, ramp_s=0.05, warmup_s=0.1)
model.slow(float(sys.argv[2]))
with PtyServer(model) as server:
    print(server.url, flush=True)
    sys.stdin.read()
"""


class Poller:
    """A thread calling ``read()`` back to back while not paused."""

    def __init__(self, read):
        self.read, self.calls = read, 0
        self.run, self.quit = threading.Event(), threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self):
        while not self.quit.is_set():
            if not self.run.wait(0.05):
                continue
            try:
                self.read()
                self.calls += 1
            except Exception:
                pass  # a poll cut short by a switch-off (SwitchedOff): the loop goes on

    def stop(self):
        self.quit.set()
        self.thread.join(5)


def timed(call, poller: Poller | None, cap: float) -> float:
    """Seconds ``call()`` took; the poller paused once ``cap`` has passed (the figure is then >= cap)."""
    done = threading.Event()

    def release():
        if not done.wait(cap) and poller is not None:
            poller.run.clear()

    guard = threading.Thread(target=release, daemon=True)
    guard.start()
    t0 = time.monotonic()
    try:
        call()
    finally:
        elapsed = time.monotonic() - t0
        done.set()
        guard.join()
    return elapsed


def summary(name: str, times: list[float], cap: float) -> str:
    capped = sum(t >= cap for t in times)
    ms = sorted(t * 1000 for t in times)
    return (
        f"{name:38s} n={len(times):3d} median {statistics.median(ms):7.0f} ms  "
        f"p90 {ms[int(0.9 * (len(ms) - 1))]:7.0f} ms  max {ms[-1]:7.0f} ms  at cap {capped}"
    )


def bench(dialect: str, tries: int, cap: float, reply_s: float) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", _SERVE, dialect, str(reply_s)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        url = child.stdout.readline().strip()
        with L8121(url, dialect=dialect) as src:
            for label, read in (("none", None), ("status()", src.status), ("check()", src.check)):
                poller = Poller(read) if read is not None else None
                sets, offs = [], []
                for i in range(tries):
                    if poller:
                        poller.run.clear()
                        time.sleep(0.15)  # the poll in flight ends
                    src.set_values(60 + i % 2, 250)  # the setpoint read first differs each time
                    if poller:
                        poller.run.set()
                        time.sleep(0.2)
                    sets.append(timed(functools.partial(src.set_values, 50 + i % 3, 200), poller, cap))
                    if poller:
                        poller.run.clear()
                        time.sleep(0.15)
                    src.on(60, 250)
                    if poller:
                        poller.run.set()
                        time.sleep(0.2)
                    offs.append(timed(src.off, poller, cap))
                if poller:
                    poller.stop()
                print(f"{dialect} poller {label:9s} " + summary("set_values (X-rays off)", sets, cap), flush=True)
                print(f"{dialect} poller {label:9s} " + summary("off() (X-rays on)", offs, cap), flush=True)
    finally:
        child.stdin.close()
        child.wait(10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tries", type=int, default=20)
    parser.add_argument("--cap", type=float, default=5.0)
    parser.add_argument("--reply-ms", type=float, default=10.0)
    parser.add_argument("--dialect", choices=("A", "B"), nargs="*", default=["A", "B"])
    args = parser.parse_args()
    for dialect in args.dialect:
        bench(dialect, args.tries, args.cap, args.reply_ms / 1000)


if __name__ == "__main__":
    main()
