"""The driver against a second, independent model of the L8121 (tests/l8121_second_reading.py).

The model was written from ../shared/hardware/L8121.md alone, before the driver's emulator or tests
were read; where the notes allow a unit to do something, it does it here, and the driver must cope.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from l8121_second_reading import Controller, Knobs

from acquisition.errors import DeviceError, SourceFault
from acquisition.l8121 import L8121
from acquisition.transport import SerialTransport, exchange_longest_s, late_reply_wait_s


def _cli(*args: str, hook=None) -> subprocess.CompletedProcess:
    proc = subprocess.Popen(
        [sys.executable, "-m", "radiokit.cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    if hook is not None:
        hook(proc)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_the_spacing_counts_from_the_last_byte_of_a_cr_lf_reply(dialect):
    # L8121.md: replies end in CR or CR LF; a controller may need ~50 ms between commands. A unit
    # whose LF follows its CR 30 ms later has answered only at the LF: counted from the CR, the
    # driver's 60 ms left it 30 ms, and this model, like a unit that needs them, lost the command.
    knobs = Knobs(dialect=dialect, eol=b"\r\n", lf_pause_s=0.03)
    with Controller(knobs) as c, L8121(c.port, dialect=dialect) as src:
        for pause in (0, 0.04, 0, 0.04):
            # asked again at once, or once the LF is waiting (as a new link to the unit, the
            # guardian's, first asks): either way the LF is the reply's last byte
            time.sleep(pause)
            assert src.interlock_closed()
    assert c.breaches == []
    assert None not in [reply for _, _, reply in c.log]


def test_a_port_closed_during_the_spacing_is_a_lost_link():
    # the spacing's wait polls the port for bytes; a port closed under it (another thread's close)
    # has no descriptor, and pyserial's poll then raises TypeError: it must read as a lost link
    # (a DeviceError naming the command), not escape as a traceback. Real pty, real close.
    with Controller(Knobs(dialect="A")) as c:
        link = SerialTransport(c.port, timeout_s=0.5, min_interval_s=0.3, retries=0)
        try:
            link.open()
            assert link.query("STS") == "STS 2"
            closer = threading.Timer(0.1, link._serial.close)  # a third into the spacing
            closer.start()
            with pytest.raises(DeviceError, match="STS: link lost"):
                link.query("STS")
            closer.join()
        finally:
            link.close()
    assert c.sent() == ["STS"]  # nothing written to the closed port


def test_a_line_never_quiet_delays_a_command_within_one_exchange_at_its_longest():
    # bytes during the spacing restart it, up to a cap: a line that never falls quiet (a NUL every
    # 5 ms, a stuck line) delays the next command -- the switch-off's XOF too -- boundedly, and
    # exchange_longest_s (the guardian's kill bound adds these up) must count that delay
    spacing, reply_s = 0.1, 0.5
    noisy, seen = threading.Event(), {}

    def noise(c: Controller) -> None:
        while noisy.is_set():
            os.write(c.master, b"\x00")
            time.sleep(0.005)

    def arrived(c: Controller) -> None:  # the command reached the model: the delay it had
        noisy.clear()
        seen["gap"] = time.monotonic() - c._last_reply_end

    with Controller(Knobs(dialect="A")) as c:
        c.when("STS", 2, arrived)
        link = SerialTransport(c.port, timeout_s=reply_s, min_interval_s=spacing, retries=0)
        try:
            link.open()
            link.query("STS")
            noisy.set()
            writer = threading.Thread(target=noise, args=(c,), daemon=True)
            writer.start()
            link.query("STS")  # (its reply may begin with a NUL: only its timing is read)
            writer.join()
        finally:
            link.close()
    assert seen["gap"] >= 2 * spacing  # the noise did hold it back (up to the cap)
    assert late_reply_wait_s(reply_s) + seen["gap"] + reply_s <= exchange_longest_s(reply_s, spacing)


def test_b_waits_for_srb_ready_before_its_control_commands():
    # L8121.md lists B's SRB, READY or BUSY, "remote operation state", which the L8121-02 driver
    # polls in its cycle; a unit busy at first refuses control commands: the presets waited for
    # READY instead of failing at the first PHV.
    knobs = Knobs(dialect="B", b_busy_srb=2, ramp_s=0.05)
    with Controller(knobs) as c, L8121(c.port, dialect="B") as src:
        src.on(60, 250)
        assert c.emitting()
        src.off()
    assert c.xray_commands == [("XON", 60.0, 250)]
    assert not c.emitting()
    assert "BUSY" in [reply for _, cmd, reply in c.log if cmd == "SRB"]  # it did wait
    assert "ERROR" not in [reply for _, cmd, reply in c.log if cmd != "Enter"]


@pytest.mark.parametrize("call", ["on", "warm_up"])
def test_b_reads_the_state_again_after_waiting_for_srb(call):
    # the state (STS, DAG) was read before SRB said BUSY; the wait may last ready_timeout_s (30 s),
    # and what kept the unit busy may have changed it: an overload meanwhile -- L8121.md: never XON
    # in overload -- is found by reading the state again, before any preset or XON
    knobs = Knobs(dialect="B", b_busy_srb=3, warmup_needed=call == "warm_up")
    with Controller(knobs) as c, L8121(c.port, dialect="B") as src:
        c.when("SRB", 1, lambda c: c.overload())  # while it is BUSY
        with pytest.raises(SourceFault, match="overload"):
            src.on(60, 250) if call == "on" else src.warm_up(progress=False)
    assert "BUSY" in [reply for _, cmd, reply in c.log if cmd == "SRB"]  # it did wait
    assert not [cmd for cmd in c.sent() if cmd.split(" ")[0] in ("PHV", "PCU", "XON")]


def _hold(word: str, seconds: float):
    def act(c: Controller) -> None:
        c.hold_reply[word] = seconds

    return act


def _signal(proc_box: list, signum: int):
    def act(c: Controller) -> None:
        os.kill(proc_box[0].pid, signum)

    return act


ON = ["acquire", "source", "on", "--kv", "60", "--ua", "250", "--for", "0.3"]


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_source_on_through_every_link_quirk_the_notes_allow(dialect):
    # CR LF line ends, replies split across reads, junk waiting before the first command, a unit
    # still in its power-on checks, and the XON answered at the slowest legal time (B's driver
    # calls 2 s a missed reply): the beam comes on at the settings asked, and goes off, confirmed
    knobs = Knobs(dialect=dialect, eol=b"\r\n", split_s=0.002, junk_at_open=b"\x00\r\n", self_test_s=0.8, ramp_s=0.1)
    with Controller(knobs) as c:
        # (A's notes give no reply time: B's 2 s is the family's, a shorter hold keeps A's case quick)
        c.when("XON", 1, _hold("XON", 1.7 if dialect == "B" else 0.6))
        res = _cli(*ON, "--dialect", dialect, "--port", c.port)
    assert res.returncode == 0, res.stderr
    assert "tube off (confirmed by STS" in res.stdout.splitlines()[-1]
    assert c.xray_commands == [("XON", 60, 250)]
    assert not c.emitting()
    assert c.breaches == []


@pytest.mark.parametrize(
    "dialect, word, nth, signum",
    [("A", "XON", 1, signal.SIGINT), ("B", "STS", 4, signal.SIGTERM), ("B", "PHV", 1, signal.SIGINT)],
)
def test_a_stop_at_any_moment_ends_with_the_tube_confirmed_off(dialect, word, nth, signum):
    # the stop lands as the controller reads the command, before it answers: at the XON (the beam
    # coming on), at a beam poll (B's STS after XON), at a preset (nothing emitting yet)
    box: list = []
    with Controller(Knobs(dialect=dialect, ramp_s=0.1)) as c:
        c.when(word, nth, _signal(box, signum))
        res = _cli(*ON[:-1], "3", "--dialect", dialect, "--port", c.port, hook=box.append)
        assert not c.emitting()
    assert res.returncode == 128 + signum, res.stderr
    last = [out.strip().splitlines()[-1] for out in (res.stdout, res.stderr) if out.strip()]
    assert any("tube off (confirmed by STS" in line for line in last)
    assert c.sent()[-2:] == ["XOF", "STS"]
    assert c.breaches == []
