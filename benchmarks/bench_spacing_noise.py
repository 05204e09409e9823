"""How long the command spacing holds a command back on a line that never falls quiet (L8121).

Since session 53 the spacing between commands counts from the controller's last byte: a byte during
the wait restarts it, but only within two spacings of the last exchange. This measures the wait
before a command -- the switch-off's ``XOF`` included -- on this script's own pty, a thread writing
one byte every ``--period-ms`` (a stuck line sending NULs), and on a quiet line for comparison.

    .venv/bin/python benchmarks/bench_spacing_noise.py --tries 40
"""

from __future__ import annotations

import argparse
import os
import pty
import statistics
import threading
import time
import tty

from acquisition.transport import SerialTransport


def waits(spacing_s: float, period_s: float | None, tries: int) -> list[float]:
    """The spacing's wait before each of ``tries`` commands; ``period_s`` None: a quiet line."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def noise() -> None:
        while not stop.is_set():
            os.write(master, b"\x00")
            time.sleep(period_s)

    link = SerialTransport(os.ttyname(slave), min_interval_s=spacing_s)
    link.open()
    if period_s is not None:
        threading.Thread(target=noise, daemon=True).start()
    took = []
    try:
        for _ in range(tries):
            link._serial.reset_input_buffer()
            t0 = link._last_exchange = time.monotonic()  # as a reply just read
            link._wait_spacing(link._serial)
            took.append(time.monotonic() - t0)
    finally:
        stop.set()
        link.close()
        os.close(master)
        os.close(slave)
    return took


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tries", type=int, default=40)
    parser.add_argument("--spacing-ms", type=float, default=60.0)
    parser.add_argument("--period-ms", type=float, default=5.0)
    args = parser.parse_args()
    spacing = args.spacing_ms / 1e3
    for name, period in (("quiet", None), (f"a byte every {args.period_ms:g} ms", args.period_ms / 1e3)):
        took = [1e3 * t for t in waits(spacing, period, args.tries)]
        print(
            f"{name:>22}: wait min {min(took):.1f} median {statistics.median(took):.1f} max {max(took):.1f} ms "
            f"(spacing {args.spacing_ms:g} ms; added at most {max(took) - args.spacing_ms:.1f} ms)"
        )


if __name__ == "__main__":
    main()
