"""One radiokit process per controller: a local serial port radiokit opens is held exclusively.

Two processes on one controller's port each read what the controller sends: a reply (a "tube
off" confirmation included) may be consumed by the process that did not ask. The first process
to open a local port holds an advisory lock on it (``flock(LOCK_EX | LOCK_NB)``, what pyserial's
``exclusive=True`` takes) from its probe to its end, its X-ray guardian included; a second is
refused in one line before it sends a byte. The controller here is the L8121 emulator on a real
pseudo-terminal; the holder is another process (a lock held by this one would not refuse it).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import guardian_of, run_cli

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.guardian import TUBE_WARNING

REPO = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(REPO))

_HOLDER = """
import sys
from acquisition.transport import SerialTransport
link = SerialTransport(sys.argv[1])
print("held", flush=True)
sys.stdin.read()
link.close()
"""


def _holder(url):
    """Another process holding ``url`` open through radiokit's transport (sending nothing)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, url], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=ENV, text=True
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


def _refusal(err, url):
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err, err
    assert lines, err
    assert url in lines[0] and "another program" in lines[0] and "holds" in lines[0], lines[0]
    return lines


@pytest.mark.parametrize("action", ["status", "probe"])
def test_a_second_process_on_a_held_port_is_refused_in_one_line_and_sends_nothing(action):
    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        holder = _holder(server.url)
        try:
            res = run_cli("acquire", "source", action, "--port", server.url)
            sent = model.commands
        finally:
            holder.stdin.close()
            holder.wait(timeout=10)
        assert res.returncode == 1, res.stderr
        assert len(_refusal(res.stderr, server.url)) == 1, res.stderr
        assert sent == [], sent
        # released with its holder: the port is radiokit's again
        res = run_cli("acquire", "source", "status", "--port", server.url, "--dialect", "A")
        assert res.returncode == 0, res.stderr
        assert "STS" in model.commands


def test_a_switch_off_refused_by_another_programs_hold_ends_on_the_warning():
    """`source off` from a second terminal while a run holds the port: not sent (its reply could
    be read by the run), and the operator told loudly that X-rays may be on."""
    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        holder = _holder(server.url)
        try:
            res = run_cli("acquire", "source", "off", "--port", server.url, "--dialect", "A")
            sent = model.commands
        finally:
            holder.stdin.close()
            holder.wait(timeout=10)
    lines = _refusal(res.stderr, server.url)
    assert res.returncode == 3 and lines[-1] == TUBE_WARNING and len(lines) == 2, res.stderr
    assert sent == [], sent


def test_the_guardian_keeps_the_commands_hold_and_its_switch_off_is_not_refused():
    """`source warm-up` (probe, then the port handed to its guardian): while it runs a second
    process is refused; kill -9 of the command, and the guardian, holding the same lock, switches
    off; once it has exited the port is free."""
    model = L8121Model(dialect="A", warmed_up=False, warmup_s=30.0, ramp_s=0.05)
    with PtyServer(model) as server:
        main = "import sys; from radiokit.cli import main; sys.exit(main())"
        cmd = [sys.executable, "-c", main, "acquire", "source", "warm-up", "--port", server.url]
        proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while "WUP" not in " ".join(model.commands):
                assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
                time.sleep(0.02)
            guardian = guardian_of(proc.pid)
            assert guardian is not None
            before = len(model.commands)
            res = run_cli("acquire", "source", "status", "--port", server.url, "--dialect", "A")
            assert res.returncode == 1 and len(_refusal(res.stderr, server.url)) == 1, res.stderr
            # the warm-up's own polls go on; a connect (status's) would have begun with TYP
            assert "TYP" not in model.commands[before:], model.commands[before:]
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
            deadline = time.monotonic() + 15
            while guardian_of(proc.pid) is not None or os.path.exists(f"/proc/{guardian}"):
                assert time.monotonic() < deadline
                time.sleep(0.02)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert not model.xray_on and "XOF" in model.commands
        res = run_cli("acquire", "source", "status", "--port", server.url, "--dialect", "A")
        assert res.returncode == 0, res.stderr


def test_one_process_never_refuses_itself_and_urls_are_not_locked():
    """Two links of one process on one port (a probe's and a switch-off's) share its hold; a
    ``loop://`` or ``socket://`` URL has no device to lock."""
    from acquisition.transport import SerialTransport

    with PtyServer(L8121Model(dialect="A", warmed_up=True)) as server:
        with SerialTransport(server.url) as first, SerialTransport(server.url) as second:
            assert first.is_open and second.is_open
    with SerialTransport("loop://") as a, SerialTransport("loop://") as b:
        assert a.is_open and b.is_open


def _series_protocol(tmp_path, url, kind):
    """A compression series on ``url``: the lab's (``kind="lab"``: the port in ``[source]``, the
    vendor folder, the manual frame) or the virtual bench's with ``[sim] source_port``. Its output
    folder, empty, is returned with it."""
    import tomli_w

    out = tmp_path / "out"
    out.mkdir()
    series = {"darks": 1, "flats": 1, "frames_per_step": 1, "steps": [0.1], "settle_s": 0.0}
    proto = {
        "output": str(out / "series.h5"),
        "name": "busy port",
        "source": {"voltage_kv": 60, "current_ua": 250, "dialect": "A"},
        "series": series,
    }
    if kind == "lab":
        frames = tmp_path / "frames"
        frames.mkdir()
        proto["source"]["port"] = url
        proto["detector"] = {"kind": "folder", "folder": str(frames), "shape": [8, 8]}
        proto["frame"] = {"kind": "manual", "initial_height_mm": 10.0}
    else:
        from sim.scene import block_scene

        scene = block_scene(size_mm=10.0, ratios=(0.1,))
        scene.detector.binning = 4
        scene.mesh.size_far_mm = 8.0
        scene_file = tmp_path / "scene.toml"
        scene_file.write_text(scene.to_toml())
        proto["detector"] = {"kind": "sim"}
        proto["frame"] = {"kind": "sim", "initial_height_mm": 10.0}
        proto["sim"] = {"scene": str(scene_file), "frame_period_s": 0.1, "source_port": url}
    path = tmp_path / "protocol.toml"
    path.write_text(tomli_w.dumps(proto))
    return path, out


def _acquire_on_a_held_port(model, server, *args):
    holder = _holder(server.url)
    try:
        res = run_cli("acquire", *args)
        return res, list(model.commands)
    finally:
        holder.stdin.close()
        holder.wait(timeout=10)


@pytest.mark.parametrize("kind", ["lab", "sim"])
def test_a_series_on_a_held_port_is_refused_in_one_line_and_leaves_nothing_behind(tmp_path, kind):
    """`radiokit acquire PROTOCOL` while another program holds the controller's port: one line
    naming the port, exit 1, and not a file in the output folder -- a notebook left there was a
    half series, and the re-run once that program ended needed --overwrite or a clean-up."""
    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        path, out = _series_protocol(tmp_path, server.url, kind)
        res, sent = _acquire_on_a_held_port(model, server, path, *(["--sim"] if kind == "sim" else []))
    assert res.returncode == 1, res.stderr
    assert len(_refusal(res.stderr, server.url)) == 1, res.stderr
    assert sent == [], sent
    assert sorted(p.name for p in out.iterdir()) == [], res.stderr


def test_a_resume_on_a_held_port_leaves_the_series_untouched(tmp_path):
    """`--resume` refused by another program's hold: the file and its notebook as they were."""
    from acquisition.protocols.compression_series import load_protocol
    from radiokit.io import ExperimentWriter, ImageKey

    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        path, out = _series_protocol(tmp_path, server.url, "lab")
        h5, notebook = out / "series.h5", out / "series.log"
        with ExperimentWriter(h5, shape=(8, 8)) as w:
            w.record_run(load_protocol(path).to_toml(), {})
            w.append(np.zeros((8, 8), np.uint16), image_key=ImageKey.DARK)
        notebook.write_text("2026-12-05 18:00:00.000 acquisition INFO phase darks\n")
        before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()}
        res, sent = _acquire_on_a_held_port(model, server, path, "--resume")
    assert res.returncode == 1, res.stderr
    assert len(_refusal(res.stderr, server.url)) == 1, res.stderr
    assert sent == [], sent
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()} == before
