"""What one never-answered query costs the next query of the same word (L8121, both dialects).

A query the controller never answers (lost, here: the emulator silent for it) times out; the
driver then asks the same word again (a status loop, a beam monitor's next poll). That next
exchange must not read a late reply to the first as its own (tests/test_l8121_late_pairing.py),
and what that guard costs is measured here: ``status()`` (both dialects) and A's beam reading
(``measured()``, ``SAR``) once normally and once right after the same call timed out, each
``--tries`` times, the emulator in this process on a pty this script creates.

    .venv/bin/python benchmarks/bench_l8121_late_pairing.py --timeout 0.25 --tries 10
"""

from __future__ import annotations

import argparse
import statistics
import time

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError
from acquisition.l8121 import L8121


def _timed(call) -> float:
    t0 = time.monotonic()
    call()
    return time.monotonic() - t0


def measure(dialect: str, reading: str, timeout_s: float, spacing_s: float, tries: int) -> tuple[list, list]:
    """(normal, after a time-out) wall times of ``reading`` (a driver method's name)."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    normal, after = [], []
    with PtyServer(model) as server:
        src = L8121(server.url, dialect=dialect, poll_s=0.05, min_interval_s=spacing_s, timeout_s=timeout_s)
        try:
            call = getattr(src, reading)
            for _ in range(tries):
                normal.append(_timed(call))
                model.silence(True)
                try:
                    call()
                except DeviceError:
                    pass
                model.silence(False)
                after.append(_timed(call))
                # the next try starts from a link that owes nothing
                time.sleep(2 * timeout_s)
                call()
        finally:
            src.close()
    return normal, after


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=0.25, help="reply time-out, s")
    parser.add_argument("--spacing", type=float, default=0.02, help="command spacing, s")
    parser.add_argument("--tries", type=int, default=10)
    args = parser.parse_args()
    for dialect, reading in (("B", "status"), ("A", "status"), ("A", "measured")):
        normal, after = measure(dialect, reading, args.timeout, args.spacing, args.tries)
        print(
            f"{dialect} {reading:9s} T={args.timeout:g} s: normal median {1e3 * statistics.median(normal):6.0f} ms, "
            f"after a never-answered one median {1e3 * statistics.median(after):6.0f} ms "
            f"max {1e3 * max(after):6.0f} ms"
        )


if __name__ == "__main__":
    main()
