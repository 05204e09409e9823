"""One radiokit process per controller: a local serial port radiokit opens is held exclusively.

Two processes on one controller's port each read what the controller sends: a reply (a "tube
off" confirmation included) may be consumed by the process that did not ask. The first process
to open a local port holds an advisory lock on it (``flock(LOCK_EX | LOCK_NB)``, what pyserial's
``exclusive=True`` takes) from its probe to its end, its X-ray guardian included; a second is
refused in one line before it sends a byte. The controller here is the L8121 emulator on a real
pseudo-terminal; the holder is another process (a lock held by this one would not refuse it).
"""

from __future__ import annotations

import contextlib
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
        main = "import sys; from radiokit.cli import script; sys.exit(script())"
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


# -- a link lost with its device node gone: the lock must not pin the node ------------------------
#
# On Linux a USB serial adapter (usb-serial, cdc-acm) keeps its device minor until the last
# descriptor of its node closes: a lock descriptor kept open after the adapter was unplugged made
# the re-plugged adapter come back under a new name (ttyUSB1), and the recovery on the old name
# (`radiokit acquire source off --port /dev/ttyUSB0`) failed while the tube might be on (review
# s35r2). A pseudo-terminal behaves alike: its index is reused only once no descriptor pins it.
# The observable here is the descriptor table (a held node reads "/dev/pts/N (deleted)"): the
# pty index itself may be taken by another test's pty meanwhile.

_TRY = """
import sys
from acquisition.errors import PortBusy
from acquisition.transport import SerialTransport
try:
    SerialTransport(sys.argv[1], timeout_s=0.5).close()
    print("opened")
except PortBusy as exc:
    print("refused:", exc)
"""


def _fds_on(pid, node, but=()):
    """The descriptors of process ``pid`` open on the device node ``node``, gone or not, but
    ``but`` (the emulator's own end, in this process)."""
    found = []
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        if fd.name in {str(b) for b in but}:
            continue
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target in (node, f"{node} (deleted)"):
            found.append(fd.name)
    return found


def _other_process(url):
    """What another process gets on ``url``: "opened" or "refused: MESSAGE"."""
    res = subprocess.run([sys.executable, "-c", _TRY, url], capture_output=True, text=True, env=ENV, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout.strip()


def _replug(byid, server):
    """The adapter plugged in again: udev points the by-id link at its (new) node."""
    os.unlink(byid)
    os.symlink(server.url, byid)


def test_a_lost_link_whose_node_vanished_keeps_no_descriptor_on_it():
    from acquisition.errors import DeviceError
    from acquisition.transport import SerialTransport

    a = PtyServer(L8121Model(dialect="A", warmed_up=True)).__enter__()
    node = a.url
    link = SerialTransport(node, timeout_s=0.5, retries=1)
    try:
        assert link.query("STS") == "STS 2"
        a.__exit__(None, None, None)  # unplugged
        with pytest.raises(DeviceError):
            link.query("STS")
        assert _fds_on(os.getpid(), node) == []
    finally:
        link.close()


def test_a_replugged_adapter_behind_a_by_id_link_is_locked_again_on_its_new_node(tmp_path):
    """The link reopens the node the by-id link now names, and holds its lock there: another
    process is refused (the lock once stayed on the vanished node, and one got in)."""
    with _replugged_behind_a_by_id_link(tmp_path) as (byid, link, model, b):
        assert link.query("XOF") == "XOF"
        assert _other_process(byid).startswith("refused:")
        assert _other_process(b.url).startswith("refused:")
        assert model.commands == ["XOF"], model.commands  # the others were refused before sending


@contextlib.contextmanager
def _replugged_behind_a_by_id_link(tmp_path):
    """A link opened through a by-id link whose controller went away (the link lost) and came
    back on another pty, the by-id link moved to it: yields (by-id path, link, new model, new
    server); the link closed at the end."""
    from acquisition.errors import DeviceError
    from acquisition.transport import SerialTransport

    byid = str(tmp_path / "usb-ctl-if00-port0")
    a = PtyServer(L8121Model(dialect="A", warmed_up=True)).__enter__()
    os.symlink(a.url, byid)
    link = SerialTransport(byid, timeout_s=0.5, retries=1)
    try:
        assert link.query("STS") == "STS 2"
        a.__exit__(None, None, None)
        with pytest.raises(DeviceError):
            link.query("STS")
        model = L8121Model(dialect="A", warmed_up=True)
        with PtyServer(model) as b:
            _replug(byid, b)
            yield byid, link, model, b
    finally:
        link.close()


def test_a_port_taken_while_the_link_was_lost_is_refused_in_words_true_mid_session(tmp_path):
    from acquisition.errors import PortBusy

    with _replugged_behind_a_by_id_link(tmp_path) as (byid, link, model, _):
        holder = _holder(byid)
        try:
            with pytest.raises(PortBusy) as refused:
                link.query("XOF")
            sent = list(model.commands)
        finally:
            holder.stdin.close()
            holder.wait(timeout=10)
    message = str(refused.value)
    assert byid in message and "took this port while" in message, message
    assert "sent nothing" not in message, message
    assert sent == [], sent


def test_neither_the_command_nor_its_guardian_pins_a_vanished_node_and_the_guardian_relocks(tmp_path):
    """After READY the command's copy of the lock is closed (its guardian's holds); the guardian,
    its link lost with the node gone, closes the inherited descriptor before it reconnects, and
    reopens the port the by-id link names once it is back, its lock taken again there."""
    from acquisition.errors import DeviceError
    from acquisition.guardian import start_guardian
    from acquisition.l8121 import L8121

    byid = str(tmp_path / "usb-ctl-if00-port0")
    a = PtyServer(L8121Model(dialect="A", warmed_up=True)).__enter__()
    node = a.url
    os.symlink(node, byid)
    resolved = L8121(byid, dialect="A", connect=False, poll_s=0.05, min_interval_s=0.02).resolved_config()
    link = start_guardian(byid, resolved)
    try:
        assert link.query("STS") == "STS 2"
        assert _fds_on(os.getpid(), node, but=[a._slave]) == []
        a.__exit__(None, None, None)
        with pytest.raises(DeviceError):
            link.query("STS")
        assert _fds_on(link.pid, node) == []
        model = L8121Model(dialect="A", warmed_up=True)
        with PtyServer(model) as b:
            _replug(byid, b)
            assert link.query("STS") == "STS 2"
            assert _other_process(byid).startswith("refused:")
            assert _fds_on(os.getpid(), b.url, but=[b._slave]) == []
            link.close()
            assert _other_process(byid) == "opened"
    finally:
        link.close()


def test_after_its_guardians_death_the_command_takes_the_lock_again_or_is_refused_in_one_line():
    """The command closed its copy of the lock at READY: once its guardian is dead it takes the
    lock again before its own exchanges -- refused, sending nothing, if another program took the
    port in between (the caller's switch-off then ends on the tube warning)."""
    from acquisition.errors import DeviceError, PortBusy
    from acquisition.guardian import start_guardian
    from acquisition.l8121 import L8121

    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        resolved = L8121(server.url, dialect="A", connect=False, poll_s=0.05, min_interval_s=0.02).resolved_config()
        for taken in (False, True):
            link = start_guardian(server.url, resolved)
            try:
                assert link.query("STS") == "STS 2"
                os.kill(link.pid, signal.SIGKILL)
                with pytest.raises(DeviceError):
                    link.query("STS")
                holder = _holder(server.url) if taken else None
                try:
                    before = len(model.commands)
                    if taken:
                        with pytest.raises(PortBusy, match="took this port while"):
                            link.query("XOF")
                        assert model.commands[before:] == []
                    else:
                        assert link.query("XOF") == "XOF"
                        assert _other_process(server.url).startswith("refused:")
                finally:
                    if holder is not None:
                        holder.stdin.close()
                        holder.wait(timeout=10)
            finally:
                link.close()


def test_a_share_collected_while_the_lock_table_is_busy_does_not_deadlock():
    """The garbage collector may run a dropped share's __del__ inside a section holding the lock
    table's guard (it did, in _lock_device, while a command took its lock again after its
    guardian's death: the process hung). A daemon thread: a regression fails, never hangs."""
    import threading

    from acquisition import transport

    with PtyServer(L8121Model(dialect="A", warmed_up=True)) as server:
        hold = transport.hold_port(server.url)
        done = []

        def collect():
            with transport._LOCKS_GUARD:
                hold.__del__()
            done.append(True)

        worker = threading.Thread(target=collect, daemon=True)
        worker.start()
        worker.join(10)
        assert done
        assert transport._lock_key(server.url) not in transport._LOCKS


@pytest.mark.parametrize("taken", [False, True])
def test_a_node_appearing_after_the_lock_was_tried_is_locked_once_open(tmp_path, monkeypatch, taken):
    """The re-plugged adapter's by-id link appears (udev, a moment late) after the lock found
    nothing to take but before the port's own open: the link once ran unlocked for the rest of
    its session and a second process got in (review s35r4). It holds the lock on the device it
    opened -- or, another program having taken it in that moment, is refused sending nothing."""
    from acquisition import transport
    from acquisition.errors import PortBusy

    with _replugged_behind_a_by_id_link(tmp_path) as (byid, link, model, b):
        os.unlink(byid)  # the link not there yet when the lock is tried
        real, holder = transport._serial_for_url, []

        def late(url, log):
            if not os.path.lexists(byid):
                os.symlink(b.url, byid)
                if taken:
                    holder.append(_holder(byid))
            return real(url, log)

        monkeypatch.setattr(transport, "_serial_for_url", late)
        try:
            if taken:
                with pytest.raises(PortBusy, match="took this port while") as refused:
                    link.query("XOF")
                assert "sent nothing" not in str(refused.value)
                assert not link.is_open
                assert model.commands == [], model.commands
            else:
                assert link.query("XOF") == "XOF"
                assert _other_process(byid).startswith("refused:")
                assert _other_process(b.url).startswith("refused:")
        finally:
            for proc in holder:
                proc.stdin.close()
                proc.wait(timeout=10)


@contextlib.contextmanager
def _ctrl_c_as_the_lock_is_taken(monkeypatch):
    """A real SIGINT, raised in this process the moment ``flock`` has taken a port's lock, before
    radiokit has recorded it for release: the window a terminal's Ctrl-C can hit, made certain.
    The signal and its handler (Python's own, raising KeyboardInterrupt) are real; only the moment
    is chosen, by wrapping ``fcntl.flock``. Yields the number of locks taken."""
    import fcntl

    real, taken = fcntl.flock, []

    def flock_then_ctrl_c(fd, operation):
        real(fd, operation)
        if operation & fcntl.LOCK_EX:
            taken.append(fd)
            signal.raise_signal(signal.SIGINT)

    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    monkeypatch.setattr(fcntl, "flock", flock_then_ctrl_c)
    try:
        yield taken
    finally:
        monkeypatch.setattr(fcntl, "flock", real)
        signal.signal(signal.SIGINT, old)


@pytest.mark.parametrize("where", ["hold_port", "renew"])
def test_a_ctrl_c_as_the_lock_is_taken_leaks_neither_lock_nor_descriptor(monkeypatch, where):
    """Found (s36): a Ctrl-C between ``flock`` and the lock's recording (the descriptor a bare
    int in _lock_device) left the lock held by a descriptor nothing would close: every later
    open of the port in this process (the Python API's next session, or the command's own
    switch-off after its guardian's death, which renews the lock) was refused as "another
    program (pid <this one>) holds this port", and another process was kept out for good. The
    taking and its recording are one step for a stop signal now: it comes after, with the lock
    recorded (``renew``: held by its share, released with it) or let go (``hold_port``: the
    share it made was never returned)."""
    from acquisition import transport

    with PtyServer(L8121Model(dialect="A", warmed_up=True)) as server:
        node, mine = server.url, [server._slave]
        hold = transport.hold_port(node) if where == "renew" else None
        if hold is not None:
            hold.hand_over()  # its guardian holds the lock now: renew() takes it again
        with _ctrl_c_as_the_lock_is_taken(monkeypatch) as taken:
            with pytest.raises(KeyboardInterrupt):
                if hold is None:
                    transport.hold_port(node)
                else:
                    hold.renew()
        assert taken, "the lock was not taken"
        if hold is not None:
            assert hold.fd is not None and _fds_on(os.getpid(), node, but=mine) == [str(hold.fd)]
            hold.release()
        assert _fds_on(os.getpid(), node, but=mine) == []
        assert _other_process(node) == "opened"
        again = transport.hold_port(node)  # and this process opens it again, as its API would
        try:
            assert again is not None and again.fd is not None
        finally:
            again.release()
