"""How long an `acquire source` command lives after its outcome is decided, in three parts.

Run::

    python benchmarks/bench_exit_window.py probe off status [--runs 8]

Each action runs as the console script does (``sys.exit(script())``) in a subprocess, against the
L8121 emulator (dialect A) on this script's own pseudo-terminal, and prints, from timestamps on
the shared monotonic clock: the guard's first ``finish()`` to ``script()``'s return; that return
to the process's ``os._exit`` (the console script's last ``atexit`` callback, a source action's
end since s52lastms; "-" where the interpreter ends itself); and that to the parent seeing the
exit (the kernel ending the process, the parent's wait). A Ctrl-C in the first two parts is
recorded (exit 128 + N); in the last, no process can see it. Measured figures: benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import os, sys, time
from acquisition.guardian import SignalGuard
from radiokit.cli import script
stamp = lambda what: print("T", what, time.monotonic(), file=sys.stderr, flush=True)
finish, exit_now = SignalGuard.finish, os._exit
def finished(self, *args, **kwargs):
    if not getattr(self, "stamped", False):
        self.stamped = True
        stamp("finish")
    finish(self, *args, **kwargs)
def exiting(code):
    stamp("exit")
    exit_now(code)
SignalGuard.finish, os._exit = finished, exiting
sys.argv = ["radiokit", *sys.argv[1:]]
code = script()
stamp("return")
sys.exit(code)
"""


def one_run(action: str) -> dict[str, float]:
    from acquisition.emulators.l8121 import L8121Model, PtyServer

    with PtyServer(L8121Model(dialect="A", warmed_up=True)) as server:
        extra = [] if action == "probe" else ["--dialect", "A"]
        proc = subprocess.Popen(
            [sys.executable, "-c", CHILD, "acquire", "source", action, "--port", server.url, *extra],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        err = proc.communicate()[1]
        seen = time.monotonic()
    stamps = {ln.split()[1]: float(ln.split()[2]) for ln in err.splitlines() if ln.startswith("T ")}
    stamps["seen"] = seen
    return stamps


def _ms(runs, a: str, b: str) -> list[float]:
    return [(r[b] - r[a]) * 1000 for r in runs if a in r and b in r]


def _span(values: list[float]) -> str:
    if not values:
        return "-"
    v = sorted(values)
    return f"{v[0]:.0f}-{v[-1]:.0f} ms (median {v[len(v) // 2]:.0f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("actions", nargs="+", choices=("probe", "off", "status"))
    ap.add_argument("--runs", type=int, default=8)
    args = ap.parse_args()
    for action in args.actions:
        runs = [one_run(action) for _ in range(args.runs)]
        end = "exit" if all("exit" in r for r in runs) else "return"
        print(
            f"{action}: finish -> script() returns {_span(_ms(runs, 'finish', 'return'))}; "
            f"-> os._exit {_span(_ms(runs, 'return', 'exit'))}; -> exit seen {_span(_ms(runs, end, 'seen'))}"
        )


if __name__ == "__main__":
    main()
