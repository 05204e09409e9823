"""From a beam that drops during a change while on (``L8121.set_values``) to the ``XOF`` that ends it.

The emulator (in process, on a pty this script creates; real pyserial) ramps over ``--ramp-s``
(its default, 1 s: L8121.md's "a few seconds" at the short end) either from the old values
(``here``) or again from zero (``zero``); the beam is switched on at the first setting (``on``),
and the change's last command (``CUR``) drops it (``drop_beam``: the current reads 0, B's STS still
XON). The driver's timing is the configuration's default (poll 0.2 s, the dialects' 60 ms between
commands, ``stable_timeout_s`` 15 s). The time is the emulator's, from the drop to the ``XOF``
it received, and what the driver said.

    .venv/bin/python benchmarks/bench_l8121_change_drop.py
    PYTHONPATH=/tmp/before .venv/bin/python benchmarks/bench_l8121_change_drop.py   # main's driver
"""

from __future__ import annotations

import argparse

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError
from acquisition.l8121 import L8121

CHANGES = {"250->100 uA": ((60, 250), (60, 100)), "60->70 kV": ((60, 250), (70, 250))}


def one(dialect: str, start: str, before, after, ramp_s: float) -> tuple[float, float, str]:
    model = L8121Model(dialect=dialect, warmed_up=True, warmup_s=0, ramp_s=ramp_s)
    model.ramp_after_change(start)
    dropped = []

    def drop():
        dropped.append(model.time)
        model.drop_beam()

    said = "no fault"
    with PtyServer(model) as server, L8121(server.url, dialect=dialect) as src:
        t_on = src.on(*before)["seconds"]
        model.inject_after("CUR", drop)
        try:
            src.set_values(*after)
        except DeviceError as exc:
            said = str(exc).split(": ", 1)[1]
        if model.xray_on:
            src.off()
    assert not model.xray_on, "the tube is on: switch it off at the controller"
    xof = next(e.t for e in model.log if e.command == "XOF")
    return t_on, xof - dropped[0], said


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ramp-s", type=float, default=1.0)
    args = parser.parse_args()
    print("| dialect | unit | change | XON ramp (s) | drop -> XOF (s) | said |")
    print("|---|---|---|---|---|---|")
    for dialect in ("A", "B"):
        for start in ("here", "zero"):
            for name, (before, after) in CHANGES.items():
                t_on, took, said = one(dialect, start, before, after, args.ramp_s)
                print(f"| {dialect} | {start} | {name} | {t_on:.2f} | {took:.2f} | {said} |", flush=True)


if __name__ == "__main__":
    main()
