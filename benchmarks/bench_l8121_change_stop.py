"""From a stop (a real SIGINT to this process) during a change while on (``L8121.set_values``,
60 kV 250 µA -> 90 kV 100 µA) to the ``XOF`` the emulator receives, a beam monitor polling
``check()`` in another thread meanwhile, under the command line's signal guard (``SignalGuard``,
the series' ``on_signal``: halt the monitor, ``cancel_readings``).

The emulator (in process, on a pty this script creates; real pyserial) ramps over 1 s; the signal
lands ``--at`` seconds after the change's call (staggered by 13 ms a run), during its commands or
its ramp. The driver's timing is the configuration's default but ``poll_s`` 0.05 s. The time is the
emulator's, from the signal to the ``XOF``; median and max of ``--runs``.

    .venv/bin/python benchmarks/bench_l8121_change_stop.py
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import threading
import time

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.guardian import SignalGuard, StopSignal
from acquisition.l8121 import L8121


def one(dialect: str, delay: float) -> float:
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=1.0, warmed_up=True)
    halt = threading.Event()

    def poll(src):
        while not halt.wait(src.config.poll_s / 2):
            try:
                src.check()
            except Exception:  # the stop's SwitchedOff, or a fault: the monitor ends
                return

    with PtyServer(model) as server:
        src = L8121(server.url, dialect=dialect, poll_s=0.05)
        try:
            src.on(60, 250)
            n = len(model.commands)
            poller = threading.Thread(target=poll, args=(src,), daemon=True)
            poller.start()
            sent: list[float] = []

            def fire():
                time.sleep(delay)
                sent.append(model.time)
                os.kill(os.getpid(), signal.SIGINT)

            with SignalGuard() as guard:
                guard.on_signal(lambda: (halt.set(), src.cancel_readings()))
                threading.Thread(target=fire, daemon=True).start()
                try:
                    src.set_values(90, 100)
                except StopSignal:
                    pass
                guard.cleanup()
            poller.join(5)
        finally:
            halt.set()
            src.detach()
    return next(e.t for e in model.log[n:] if e.command == "XOF" and e.t >= sent[0]) - sent[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--at", type=float, nargs="+", default=[0.05, 0.4])
    parser.add_argument("--runs", type=int, default=8)
    args = parser.parse_args()
    for dialect in "AB":
        for at in args.at:
            took = [one(dialect, at + 0.013 * k) for k in range(args.runs)]
            print(
                f"{dialect} at {at:.2f} s: SIGINT -> XOF median {statistics.median(took) * 1e3:.0f} ms, max {max(took) * 1e3:.0f} ms"
            )


if __name__ == "__main__":
    main()
