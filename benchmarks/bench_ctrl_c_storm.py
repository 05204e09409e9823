"""Ctrl-C at the end of `radiokit acquire`: how often the command's last lines or exit go wrong.

Run::

    python benchmarks/bench_ctrl_c_storm.py [--dialect A] [--trigger summary] [--runs 10]

`radiokit acquire PROTOCOL --sim` (2 darks, 3 flats, one step of 3 frames) in a subprocess of its
own process group, against the L8121 emulator that this script serves on a pseudo-terminal
(``[sim] source_port``). From the trigger on -- ``summary``: the "N frames written" line (the
series complete); ``last``: the notebook's line for the last frame (in its exposure); ``on``:
`source on --for 0.3`'s "over: tube off" line instead of a series; ``probe``: `source probe`'s
report line (a probe run instead: a run is bad then when it exits 0 after a Ctrl-C) -- a Ctrl-C (SIGINT to the
group, as a terminal sends it) every 2 ms until the command exits; with ``--delays 0,5,10``, one
Ctrl-C per run instead, that many ms after the trigger (a run per delay). A run is bad when it exits
other than 0 or 130 (-2: ended by the signal itself), says "no partial output" or prints a
traceback, does not end on the tube's confirmed line, or leaves the emulator's X-rays on.
Measured figures: benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIRMED = re.compile(r"tube off \(confirmed by STS: \w+\)$")


def _protocol(folder: Path, port: str, dialect: str) -> Path:
    import tomli_w

    from sim.scene import block_scene

    scene = block_scene(size_mm=10.0, ratios=(0.15, 0.25))
    scene.detector.binning = 4
    scene.mesh.size_far_mm = 8.0
    (folder / "scene.toml").write_text(scene.to_toml())
    path = folder / "protocol.toml"
    source = {"voltage_kv": 60, "current_ua": 250, "poll_s": 0.1, "timeout_s": 1.0, "dialect": dialect}
    source |= {"off_attempts": 2, "min_interval_s": 0.01}
    sim = {"scene": str(folder / "scene.toml"), "frame_period_s": 0.1, "source_port": port}
    series = {"darks": 2, "flats": 3, "frames_per_step": 3, "steps": [0.0], "settle_s": 0.0}
    path.write_text(
        tomli_w.dumps(
            {
                "output": str(folder / "series.h5"),
                "name": "storm",
                "source": source,
                "detector": {"kind": "sim", "timeout_s": 2.0},
                "frame": {"kind": "sim", "initial_height_mm": 10.0},
                "series": series,
                "sim": sim,
            }
        )
    )
    return path


def one_run(
    folder: Path, dialect: str, trigger: str, delay_s: float | None = None
) -> tuple[int, int, list[str], list[str]]:
    """(exit code, Ctrl-Cs sent, what was wrong, the output's lines)."""
    from acquisition.emulators.l8121 import L8121Model, PtyServer

    model = L8121Model(dialect=dialect, warmup_s=3.0, ramp_s=0.05, warmed_up=True)
    with PtyServer(model) as server:
        if trigger == "on":
            args = ["source", "on", "--port", server.url, "--dialect", dialect, "--kv", "60", "--ua", "250"]
            args += ["--for", "0.3"]
        elif trigger == "probe":
            args = ["source", "probe", "--port", server.url]
        else:
            args = [str(_protocol(folder, server.url, dialect)), "--sim"]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
        if trigger == "probe":  # its report goes to stdout, line by line as at a terminal (a pipe holds it to the exit)
            env["PYTHONUNBUFFERED"] = "1"
        code = "import sys; from radiokit.cli import script; sys.exit(script())"  # the console script
        proc = subprocess.Popen(
            [sys.executable, "-c", code, "acquire", *args, "-q"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        lines: list[str] = []
        reader = threading.Thread(
            target=lambda: lines.extend(ln.decode(errors="replace").rstrip() for ln in proc.stdout)
        )
        reader.start()
        notebook = folder / "series.log"

        def started() -> bool:
            if trigger == "summary":
                return any("frames written" in ln for ln in lines)
            if trigger == "on":
                return any(" s over: tube off" in ln for ln in lines)
            if trigger == "probe":  # its report: the state the probe's STS read
                return any(" state " in ln for ln in lines)
            return notebook.exists() and "frame 7 written" in notebook.read_text(errors="replace")

        end = time.monotonic() + 120
        while not started() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.001)
        sent = 0
        if delay_s is not None:  # one Ctrl-C, delay_s after the trigger
            time.sleep(delay_s)
            try:
                os.killpg(proc.pid, signal.SIGINT)
                sent = 1
            except ProcessLookupError:
                pass
        while delay_s is None and proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGINT)
            except ProcessLookupError:
                break
            sent += 1
            time.sleep(0.002)
        status = proc.wait()
        reader.join(timeout=10)
        xray_on = model.xray_on
    text = "\n".join(lines)
    last = next((ln.strip() for ln in reversed(lines) if ln.strip()), "")
    # a probe a Ctrl-C reached before its end must not exit 0 (`probe && source on` goes on)
    bad = [f"exit {status}"] if status not in ((130,) if trigger == "probe" and sent else (0, 130)) else []
    bad += ["'no partial output'"] if "no partial output" in text else []
    bad += ["traceback"] if "Traceback" in text or "Exception ignored" in text else []
    if trigger != "probe":  # (the probe's last line is its report's raw exchange)
        bad += [] if CONFIRMED.search(last) else [f"last line {last[-60:]!r}"]
    bad += ["X-RAYS ON"] if xray_on else []
    return status, sent, bad, lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dialect", choices=("A", "B"), default="A")
    ap.add_argument("--trigger", choices=("summary", "last", "on", "probe"), default="summary")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--delays", help="one Ctrl-C a run, this many ms after the trigger (comma-separated)")
    args = ap.parse_args()
    tally: dict = {}
    base = Path(tempfile.mkdtemp(prefix="storm-"))
    delays = [float(d) / 1000 for d in args.delays.split(",")] if args.delays else [None] * args.runs
    args.runs = len(delays)
    for i, delay_s in enumerate(delays):
        folder = base / f"run{i}"
        folder.mkdir()
        status, sent, bad, lines = one_run(folder, args.dialect, args.trigger, delay_s)
        key = (status, ", ".join(bad) or "ok")
        tally[key] = tally.get(key, 0) + 1
        when = "" if delay_s is None else f" at {delay_s * 1000:g} ms"
        print(f"run {i}: exit {status}, {sent} Ctrl-C sent{when}: {', '.join(bad) or 'ok'}", flush=True)
    print(f"dialect {args.dialect}, trigger {args.trigger}, {args.runs} runs:")
    for (status, what), n in sorted(tally.items(), key=lambda kv: -kv[1]):
        print(f"  {n:3d} x exit {status}: {what}")


if __name__ == "__main__":
    main()
