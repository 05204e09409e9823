"""How long a Ctrl-C's switch-off and close wait behind a beam monitor's poll, the controller silent.

The CLI's Ctrl-C path (``acquire source``) calls ``off()`` then ``close()`` (``detach()`` after a
switch-off that failed). A thread polls ``check()`` back to back (a beam monitor with no period)
while the tube is on; the controller then goes silent (the emulator, in a child process on a pty
this script creates, stops answering), and after a random delay the main thread switches off and
closes the link, as that path does. Printed: ``off()``'s whole time, and the close's (``SerialTransport.close``'s wait for the
poller's exchange included). Then the transport alone: ``close()`` from one thread while another's
``STS`` waits out its reply time-out on a silent pty (the bound is ``close_wait_s``).
The dialects' timing (2 s reply time-out, 60 ms spacing, 1 s write time-out).

    .venv/bin/python benchmarks/bench_close_behind_poll.py --tries 8
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import subprocess
import sys
import threading
import time

from acquisition.errors import DeviceError
from acquisition.l8121 import L8121
from acquisition.transport import SerialTransport, close_wait_s

_SERVE = """
import sys, time
from acquisition.emulators.l8121 import L8121Model, PtyServer
model = L8121Model(dialect=sys.argv[1], warmed_up=True, ramp_s=0.05, warmup_s=0.1)
with PtyServer(model) as server:
    print(server.url, flush=True)
    for line in sys.stdin:
        if line.strip() == "silent":
            model.silence(True)
            print("ok", flush=True)
"""


def _ms(values: list[float]) -> str:
    ms = sorted(v * 1000 for v in values)
    return f"median {statistics.median(ms):6.0f} ms  max {ms[-1]:6.0f} ms"


def driver(dialect: str, tries: int) -> None:
    offs, closes, totals = [], [], []
    for _ in range(tries):
        child = subprocess.Popen(
            [sys.executable, "-c", _SERVE, dialect], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        try:
            url = child.stdout.readline().strip()
            src = L8121(url, dialect=dialect)
            src.on(60, 250)
            quit_ = threading.Event()

            def poll(src=src, quit_=quit_):
                while not quit_.is_set():
                    try:
                        src.check()
                    except Exception:
                        pass  # a poll the silence or the switch-off cut short: the monitor goes on

            poller = threading.Thread(target=poll, daemon=True)
            poller.start()
            time.sleep(0.3)
            child.stdin.write("silent\n")
            child.stdin.flush()
            child.stdout.readline()
            time.sleep(random.uniform(0.0, 2.5))  # the Ctrl-C lands anywhere in a poll
            t0 = time.monotonic()
            try:
                src.off()
            except DeviceError:
                pass  # silent: not confirmed, as expected
            t1 = time.monotonic()
            src.detach()  # the CLI's after an unconfirmed switch-off: the transport's close()
            t2 = time.monotonic()
            quit_.set()
            poller.join(10)
            offs.append(t1 - t0)
            closes.append(t2 - t1)
            totals.append(t2 - t0)
        finally:
            child.stdin.close()
            child.wait(10)
    print(f"{dialect} off() behind a polling monitor, silent:   {_ms(offs)}")
    print(f"{dialect} close (detach) after it:                {_ms(closes)}")
    print(f"{dialect} Ctrl-C path, off() + close:              {_ms(totals)}")


def transport_alone(tries: int) -> None:
    waits = []
    for _ in range(tries):
        master, slave = os.openpty()  # nobody answers: a silent controller
        link = SerialTransport(os.ttyname(slave), timeout_s=2.0, min_interval_s=0.06)
        out = {}
        poll = threading.Thread(target=lambda link=link, out=out: out.update(r=_try(link.query, "STS")), daemon=True)
        poll.start()
        time.sleep(random.uniform(0.05, 2.0))
        t0 = time.monotonic()
        link.close()
        waits.append(time.monotonic() - t0)
        poll.join(10)
        os.close(master)
        os.close(slave)
    bound = close_wait_s(2.0, 1.0, 0.06)
    print(f"transport close() behind a silent STS:      {_ms(waits)}  (close_wait_s {bound * 1000:.0f} ms)")


def _try(call, *args):
    try:
        return call(*args)
    except DeviceError as exc:
        return exc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tries", type=int, default=8)
    parser.add_argument("--dialect", choices=("A", "B"), default="A")
    args = parser.parse_args()
    transport_alone(args.tries)
    driver(args.dialect, args.tries)


if __name__ == "__main__":
    main()
