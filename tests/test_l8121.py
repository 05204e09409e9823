"""The L8121 source: transport, driver and emulator, through real pyserial on a real pseudo-terminal.

Read like the controller's manual: a driver call, the command the emulator received, the reply.
Fault tests inject a fault into the emulator (interlock, overload, dropped beam, silence, junk,
slow replies) and check that the driver stops with the right error and the tube ends up off.
"""
from __future__ import annotations

import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import serial

from acquisition.emulators.l8121 import L8121Model, PtyServer, SocketServer
from acquisition.errors import DeviceError, SourceFault
from acquisition.l8121 import Command, L8121, Query, SourceConfig, SourceState, WarmupState
from acquisition.transport import SerialTransport

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

REPO = Path(__file__).resolve().parents[1]
WARMUP_S = 0.3
RAMP_S = 0.2
FAST = dict(poll_s=0.05, min_interval_s=0.02)  # driver timing for tests; the link stays real


@pytest.fixture
def cold():
    """An emulator that needs warming up, served on a pty."""
    model = L8121Model(warmup_s=WARMUP_S, ramp_s=RAMP_S)
    with PtyServer(model) as server:
        yield model, server


@pytest.fixture
def warm():
    """An emulator in standby (warm-up done), served on a pty."""
    model = L8121Model(warmup_s=WARMUP_S, ramp_s=RAMP_S, warmed_up=True)
    with PtyServer(model) as server:
        yield model, server


@pytest.fixture
def source(warm):
    model, server = warm
    with L8121(server.url, **FAST) as src:
        yield src, model


def commands_after(model: L8121Model, command: str) -> list[str]:
    """The commands the model received after the last ``command``."""
    cmds = model.commands
    assert command in cmds, f"{command} never sent: {cmds}"
    return cmds[len(cmds) - cmds[::-1].index(command):]


# -- the link -------------------------------------------------------------------------------------
@pytest.mark.parametrize("ending", ["\r", "\r\n"])
def test_transport_reads_cr_and_crlf_replies(ending):
    model = L8121Model(warmed_up=True)
    with PtyServer(model, reply_terminator=ending) as server, SerialTransport(server.url) as link:
        assert link.is_open
        replies = [link.query(c) for c in ("TYP", "STS", "HIV 60", "SVI")]
    assert replies == ["TYP L8121-01", "STS 2", "HIV 60", "SVI 60 0"]
    assert model.commands == ["TYP", "STS", "HIV 60", "SVI"]
    assert not link.is_open


def test_transport_logs_every_exchange(warm, caplog):
    model, server = warm
    caplog.set_level(logging.DEBUG, logger="acquisition.transport")
    with SerialTransport(server.url) as link:
        link.query("TYP")
    messages = [r.getMessage() for r in caplog.records if r.name == "acquisition.transport"]
    assert f"{server.url} > TYP" in messages
    assert any(m.startswith(f"{server.url} < TYP L8121-01 (") and m.endswith(" ms)") for m in messages), messages


def test_transport_keeps_min_interval_and_never_interleaves(warm):
    """Two threads share a link: every reply matches its own command, and commands are spaced."""
    model, server = warm
    interval = 0.03
    replies: dict[str, list[tuple[str, str]]] = {"HIV": [], "CUR": []}
    with SerialTransport(server.url, min_interval_s=interval) as link:
        def worker(word, values):
            for v in values:
                replies[word].append((f"{word} {v}", link.query(f"{word} {v}")))
        threads = [threading.Thread(target=worker, args=("HIV", range(50, 58))),
                   threading.Thread(target=worker, args=("CUR", range(100, 108)))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    for pairs in replies.values():
        assert [sent for sent, _ in pairs] == [got for _, got in pairs]
    times = [e.t for e in model.log]
    assert len(times) == 16
    assert min(b - a for a, b in zip(times, times[1:])) >= 0.8 * interval


def test_transport_reconnects_after_a_lost_link(caplog):
    model = L8121Model(warmed_up=True)
    caplog.set_level(logging.WARNING, logger="acquisition.transport")
    with SocketServer(model) as server, SerialTransport(server.url, retries=1) as link:
        assert link.query("STS") == "STS 2"
        server.drop_connection()
        time.sleep(0.3)  # the server notices within its 0.05 s poll
        assert link.query("SIN") == "SIN 0"
    assert any("reconnecting" in r.getMessage() for r in caplog.records), caplog.text


def test_transport_gives_up_when_the_device_is_gone(warm):
    model, server = warm
    link = SerialTransport(server.url)
    assert link.query("STS") == "STS 2"
    server.stop()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=rf"{server.url}: (no reply to SER|SER: link lost)"):
        link.query("SER")
    assert time.monotonic() - t0 < 3
    link.close()


def test_transport_discards_a_late_reply(warm):
    """A reply that arrives after its command timed out must not be taken for the next one's."""
    model, server = warm
    model.slow(0.6)
    with SerialTransport(server.url, timeout_s=0.3) as link:
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="no reply to STS within 0.3 s"):
            link.query("STS")
        model.slow(0)
        time.sleep(max(0.0, t0 + 0.9 - time.monotonic()))  # the late "STS 2" is now in our buffer
        assert link.query("SIN") == "SIN 0"


def test_transport_rejects_a_missing_port():
    with pytest.raises(DeviceError, match="/dev/nonexistent-l8121: cannot open"):
        SerialTransport("/dev/nonexistent-l8121")


# -- reading like the manual ----------------------------------------------------------------------
@pytest.mark.parametrize("call, sent, expected", [
    (lambda s: s.status(), "STS", SourceState.STANDBY),
    (lambda s: s.measured(), "SAR", (0.0, 0.0)),
    (lambda s: s.setpoint(), "SVI", (40.0, 0.0)),
    (lambda s: s.interlock_closed(), "SIN", True),
    (lambda s: s.warmup_state(), "SWE", WarmupState.DONE),
    (lambda s: s.error_code(), "SER", 0),
    (lambda s: s.focus, "SFC", 0),
    (lambda s: s.voltage_kv, "SHV", 0.0),
    (lambda s: s.current_ua, "SCU", 0.0),
    (lambda s: s.preheating, "SPH", False),
    (lambda s: s.model_name, "TYP", "L8121-01"),
])
def test_queries_read_like_the_manual(source, call, sent, expected):
    src, model = source
    value = call(src)
    assert value == expected and type(value) is type(expected)
    assert model.commands[-1] == sent


def test_settings_read_like_the_manual(source):
    src, model = source
    src.focus = 2
    assert model.commands[-1] == "CFS 2" and src.focus == 2
    assert src.set_values(60, 250) == (60, 250)
    assert model.commands[-3:] == ["SVI", "HIV 60", "CUR 250"]
    assert src.setpoint() == (60.0, 250.0) and (model.set_kv, model.set_ua) == (60, 250)
    with pytest.raises(ValueError, match="focus_modes"):
        src.focus = 7
    with pytest.raises(AttributeError, match="read-only"):
        src.state = 3


def test_set_values_orders_hiv_and_cur_to_stay_within_power(source):
    """From 60 kV 500 µA (30 W) to 150 kV 400 µA (60 W): HIV 150 first would ask for 75 W with the
    old current — fine — but from 60 kV 500 µA to 150 kV 100 µA, HIV first would be 75 W; at
    watts_max 40 the driver must send CUR first."""
    src, model = source
    src.config.watts_max = model.watts_max = 40
    src.set_values(60, 500)
    src.set_values(150, 100)
    assert model.commands[-2:] == ["CUR 100", "HIV 150"]
    assert (model.set_kv, model.set_ua) == (150, 100)


def test_typ_is_checked_at_connect(warm):
    model, server = warm
    model.model = "L8121-02"
    with pytest.raises(DeviceError, match=r"TYP answered 'L8121-02', expected 'L8121-01'"):
        L8121(server.url)
    with L8121(server.url, model=None) as src:
        assert src.identity == "L8121-02"
    with L8121(server.url, model="L8121-02") as src:
        assert src.status() == SourceState.STANDBY


def test_unparseable_replies_raise(source):
    src, model = source
    model.garbage()
    for call, command in [(L8121.status, "STS"), (L8121.measured, "SAR"), (L8121.setpoint, "SVI"),
                          (L8121.interlock_closed, "SIN"), (L8121.error_code, "SER")]:
        with pytest.raises(DeviceError, match=rf"reply to {command}: '[^']*'"):
            call(src)
    with pytest.raises(DeviceError, match=r"unexpected reply to CFS 1: '[^']*' \(expected the echo 'CFS 1'\)"):
        src.focus = 1


@pytest.mark.parametrize("query, reply", [
    (Query("STS", int), "SVI 2"),                      # wrong echo
    (Query("STS", int), "STS"),                        # no value
    (Query("STS", int), "STS 2 2"),                    # one field too many
    (L8121.state, "STS 9"),                            # no such state
    (L8121.state, "STS 2.5"),
    (L8121._sar, "SAR 3 60 nan 0 0 0 0"),
    (L8121._sar, "SAR 3 6O 250 0 0 0 0"),              # letter O for zero
    (L8121.interlock_open, "SIN 2"),
])
def test_query_parse_rejects(query, reply):
    with pytest.raises(ValueError):
        query.parse(reply)


def test_parse_and_echo_accept():
    assert L8121._sar.parse("SAR 3 60 250 0 0 0 0") == (SourceState.XRAY_ON, 60.0, 250.0)
    assert L8121.model_name.parse("TYP L8121 01") == "L8121 01"
    assert Command.is_echo("HIV 60", "HIV 060") and Command.is_echo("XON", "XON")
    assert not Command.is_echo("HIV 60", "HIV 61") and not Command.is_echo("XON", "XOF")


def test_refused_command_raises(source):
    src, model = source
    with pytest.raises(DeviceError, match=r"XON refused by the controller \(ERROR\)"):
        model.open_interlock()
        src._xon()  # bypassing on()'s own checks, as a manual XON from a script would
    assert not model.xray_on


# -- on(): limits first, then state ---------------------------------------------------------------
@pytest.mark.parametrize("kv, ua, limit", [
    (200, 100, "kv_min..kv_max"),
    (30, 100, "kv_min..kv_max"),
    (60, 600, "ua_min..ua_max"),
    (60, -1, "ua_min..ua_max"),
    (100, 400, "watts_max = 30 W"),
    (float("nan"), 100, "finite"),
])
def test_on_validates_before_sending(warm, kv, ua, limit):
    model, server = warm
    with L8121(server.url, watts_max=30, **FAST) as src:
        n = len(model.log)
        with pytest.raises(ValueError, match=limit):
            src.on(kv, ua)
        assert model.log[n:] == []  # not a single byte went to the controller
    assert not model.xray_on


def test_on_rounds_to_whole_numbers_and_says_so(source, caplog):
    src, model = source
    with caplog.at_level(logging.WARNING, logger="acquisition.l8121"):
        beam = src.on(60.4, 249.6)
    assert (beam["set_voltage_kv"], beam["set_current_ua"]) == (60, 250)
    assert ["HIV 60", "CUR 250"] == [c for c in model.commands if c[:3] in ("HIV", "CUR")]
    assert "rounded to 60 kV" in caplog.text and "rounded to 250 µA" in caplog.text


def test_xon_refused_before_warmup(cold):
    model, server = cold
    with L8121(server.url, **FAST) as src:
        with pytest.raises(DeviceError, match="warm-up needed"):
            src.on(60, 250)
    assert "XON" not in model.commands and not model.xray_on
    # the emulator itself refuses too, and says why
    with SerialTransport(server.url) as link:
        assert [link.query(c) for c in ("XON", "SER", "STS")] == ["ERROR", "SER 2", "STS 0"]


def test_xon_refused_with_interlock_open(warm):
    model, server = warm
    model.open_interlock()
    with L8121(server.url, **FAST) as src:
        with pytest.raises(SourceFault, match="interlock open"):
            src.on(60, 250)
    assert "XON" not in model.commands and not model.xray_on
    with SerialTransport(server.url) as link:
        assert [link.query(c) for c in ("SIN", "XON", "SER")] == ["SIN 1", "ERROR", "SER 1"]


def test_xon_refused_in_overload(warm):
    model, server = warm
    model.overload()
    with L8121(server.url, **FAST) as src:
        with pytest.raises(SourceFault, match="overload"):
            src.on(60, 250)
        with pytest.raises(SourceFault, match="overload"):
            src.warm_up(progress=False)
        assert model.state == 4  # never reset automatically
        assert "RST" not in model.commands
        assert src.reset() == SourceState.STANDBY  # a person can
    assert "XON" not in model.commands


# -- warm-up --------------------------------------------------------------------------------------
def test_warm_up_completes(cold):
    model, server = cold
    seen = []
    with L8121(server.url, **FAST) as src:
        assert src.warmup_state() == WarmupState.NOT_STARTED
        seconds = src.warm_up(timeout_s=10, progress=lambda t, state: seen.append(state))
        assert src.status() == SourceState.STANDBY and src.warmup_state() == WarmupState.DONE
        assert src.warm_up(progress=False) == 0.0  # done already: no second WUP
    assert model.commands.count("WUP") == 1
    assert seconds >= 0.9 * WARMUP_S
    assert SourceState.WARMING_UP in seen and not model.xray_on


def test_warm_up_with_a_progress_bar(cold, capsys):
    model, server = cold
    with L8121(server.url, **FAST) as src:
        assert src.warm_up(timeout_s=10, progress=True) >= 0.9 * WARMUP_S
    assert "warm-up" in capsys.readouterr().err


def test_warm_up_times_out(cold):
    model, server = cold
    model.warmup_s = 30
    with L8121(server.url, **FAST) as src:
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="warm-up not done within 0.3 s"):
            src.warm_up(timeout_s=0.3, progress=False)
        assert time.monotonic() - t0 < 3
    assert "XOF" in commands_after(model, "WUP") and not model.xray_on


# -- on, off --------------------------------------------------------------------------------------
def test_on_returns_when_measured_within_tolerance(source):
    src, model = source
    kv, ua = 60, 250
    tol_kv, tol_ua = src.config.tolerance_kv(kv), src.config.tolerance_ua(ua)
    beam = src.on(kv, ua)
    assert abs(beam["voltage_kv"] - kv) <= tol_kv and abs(beam["current_ua"] - ua) <= tol_ua
    assert model.xray_on
    cmds = model.commands
    assert cmds.index("HIV 60") < cmds.index("CUR 250") < cmds.index("XON")
    # the emulator ramps linearly over RAMP_S and reports whole numbers: "within tolerance" cannot
    # come before this fraction of the ramp (model time, so CPU load does not matter)
    t_xon = next(e.t for e in model.log if e.command == "XON")
    t_stable = [e.t for e in model.log if e.command == "SAR"][-1]
    earliest = RAMP_S * (1 - min((tol_kv + 0.5) / kv, (tol_ua + 0.5) / ua))
    assert t_stable - t_xon >= earliest
    assert src.check()["state"] == SourceState.XRAY_ON


def test_set_values_while_on_waits_for_the_new_beam(source):
    src, model = source
    src.on(60, 100)
    assert src.set_values(60, 400) == (60, 400)
    kv, ua = src.measured()
    assert abs(ua - 400) <= src.config.tolerance_ua(400) and model.xray_on
    assert src.check()["current_ua"] >= 0.9 * 400  # judged against the new current: no false "dropped"


def test_unknown_setting_is_named():
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['kv_maximum'\]"):
        L8121("loop://", connect=False, kv_maximum=90)


def test_on_refuses_when_already_on(source):
    src, model = source
    src.on(60, 250)
    with pytest.raises(DeviceError, match="already on"):
        src.on(70, 250)
    assert model.xray_on and model.set_kv == 60


def test_on_switches_off_when_not_stable(warm):
    model, server = warm
    model.ramp_s = 30
    with L8121(server.url, stable_timeout_s=0.3, **FAST) as src:
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="not stable within stable_timeout_s = 0.3 s"):
            src.on(60, 250)
        assert time.monotonic() - t0 < 3
        assert not model.xray_on and "XOF" in commands_after(model, "XON")


def test_off_is_confirmed(source):
    src, model = source
    src.on(60, 250)
    assert src.off() == SourceState.STANDBY
    assert commands_after(model, "XON") [-2:] == ["XOF", "STS"]
    assert not model.xray_on and model.measured() == (0.0, 0.0)


def test_off_is_not_confirmed_while_sts_says_on(source):
    src, model = source
    src.on(60, 250)
    model.stuck_on()
    with pytest.raises(DeviceError, match=r"could not confirm X-rays off after 3 attempt.*STS still 3"):
        src.off()
    assert commands_after(model, "XON").count("XOF") == 3
    model.stuck_on(False)


def test_off_raises_when_it_cannot_confirm(source):
    src, model = source
    src.on(60, 250)
    model.silence()
    src.config.timeout_s = 0.2
    src._transport.timeout_s = 0.2
    with pytest.raises(DeviceError, match="could not confirm X-rays off after 3 attempt"):
        src.off()
    model.silence(False)


# -- faults while on ------------------------------------------------------------------------------
@pytest.mark.parametrize("inject, reason", [
    (L8121Model.open_interlock, "interlock open"),
    (L8121Model.overload, "overload"),
    (L8121Model.drop_beam, "beam dropped: measured current 0 µA"),
])
def test_check_stops_on_a_fault(source, inject, reason):
    src, model = source
    src.on(60, 250)
    assert src.check()["current_ua"] == pytest.approx(250, abs=src.config.tolerance_ua(250) + 1)
    t_fault = model.time + 0.2
    inject(model, at_s=t_fault)
    deadline = time.monotonic() + 3
    with pytest.raises(SourceFault, match=reason) as info:
        while time.monotonic() < deadline:
            src.check()
            time.sleep(0.05)
    assert "X-rays switched off" in str(info.value)
    assert not model.xray_on
    assert model.time - t_fault < 1.0  # fault to tube off, on the model's clock
    if reason != "overload":
        assert "XOF" in [e.command for e in model.log if e.t >= t_fault]
    assert "RST" not in model.commands


def test_garbage_while_on_switches_off(source):
    src, model = source
    src.on(60, 250)
    model.garbage()
    with pytest.raises(DeviceError, match="unparseable reply to SAR"):
        src.measured()
    model.garbage(False)
    assert not model.xray_on  # the XOF was executed even though its reply was junk


# -- a controller that misbehaves -----------------------------------------------------------------
def test_silent_controller_times_out(warm):
    model, server = warm
    with L8121(server.url, **FAST) as src:
        model.silence()
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=rf"{server.url}: no reply to STS within 1 s"):
            src.status()
        elapsed = time.monotonic() - t0
    assert 0.9 <= elapsed < 3
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="no reply to TYP"):
        L8121(server.url, timeout_s=0.5)
    assert time.monotonic() - t0 < 3


def test_slow_replies(warm):
    model, server = warm
    model.slow(0.3)
    with L8121(server.url, timeout_s=1.0, **FAST) as src:
        assert src.status() == SourceState.STANDBY
    model.slow(1.0)
    with L8121(server.url, timeout_s=0.4, connect=False, **FAST) as src:
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="no reply to TYP within 0.4 s"):
            src.connect()
        assert time.monotonic() - t0 < 3
    model.slow(0)


# -- every exit path leaves the tube off ----------------------------------------------------------
def test_context_manager_switches_off_on_an_exception(warm):
    model, server = warm
    with pytest.raises(RuntimeError, match="detector lost"):
        with L8121(server.url, **FAST) as src:
            src.on(60, 250)
            assert model.xray_on
            raise RuntimeError("detector lost")
    assert not model.xray_on and commands_after(model, "XON")[-2:] == ["XOF", "STS"]
    assert not src.is_connected


def test_context_manager_switches_off_on_keyboard_interrupt(warm):
    model, server = warm
    with pytest.raises(KeyboardInterrupt):
        with L8121(server.url, **FAST) as src:
            src.on(60, 250)
            raise KeyboardInterrupt
    assert not model.xray_on and "XOF" in commands_after(model, "XON")


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals")
def test_ctrl_c_while_waiting_for_the_beam_switches_off(warm):
    model, server = warm
    model.ramp_s = 30

    def interrupt(signum, frame):
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        with L8121(server.url, **FAST) as src:
            signal.setitimer(signal.ITIMER_REAL, 0.4)
            with pytest.raises(KeyboardInterrupt):
                src.on(60, 250)
            assert not model.xray_on
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert "XOF" in commands_after(model, "XON")


def test_exit_does_not_mask_the_original_exception(warm):
    model, server = warm
    with pytest.raises(RuntimeError, match="original"):
        with L8121(server.url, timeout_s=0.2, off_attempts=1, **FAST) as src:
            src.on(60, 250)
            model.silence()
            raise RuntimeError("original")
    model.silence(False)


# -- configuration --------------------------------------------------------------------------------
def test_config_from_toml_and_dict(tmp_path):
    path = tmp_path / "lab.toml"
    path.write_text('[source]\nurl = "/dev/ttyUSB0"\nbaudrate = 9600\nkv_max = 90\nua_tolerance = "2%"\n'
                    'model = ""\n')
    config = SourceConfig.from_toml(path)
    assert (config.kv_max, config.model, config.tolerance_ua(250), config.tolerance_kv(60)) == (90, None, 5.0, 1.0)
    assert SourceConfig.from_dict(config.to_dict()) == config
    src = L8121.from_config(path, connect=False)
    assert (src.url, src.baudrate, src.config.kv_max) == ("/dev/ttyUSB0", 9600, 90)
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['kv_maximum'\]"):
        SourceConfig.from_dict({"kv_maximum": 90})
    with pytest.raises(ValueError, match="kv_tolerance"):
        SourceConfig(kv_tolerance="two")
    with pytest.raises(ValueError, match="tube voltage 100 kV is outside kv_min..kv_max = 40..90 kV"):
        src.validate(100, 100)


# -- the emulator in process ----------------------------------------------------------------------
class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_emulator_ramps_and_warms_up_on_its_clock():
    clock = Clock()
    m = L8121Model(warmup_s=2, ramp_s=1, clock=clock)
    assert [m.handle(c) for c in ("STS", "SWE", "WUP", "STS", "SWE", "SPH")] == \
        ["STS 0", "SWE 2", "WUP", "STS 1", "SWE 1", "SPH 1"]
    clock.t += 2
    assert [m.handle(c) for c in ("STS", "SWE", "HIV 60", "CUR 250", "XON")] == \
        ["STS 2", "SWE 0", "HIV 60", "CUR 250", "XON"]
    clock.t += 0.5
    assert m.handle("SAR") == "SAR 3 30 125 0 0 0 0"
    clock.t += 0.5
    assert (m.handle("SHV"), m.handle("SCU"), m.handle("SVI")) == ("SHV 60", "SCU 250", "SVI 60 250")
    assert m.handle("XOF") == "XOF" and m.handle("SAR") == "SAR 2 0 0 0 0 0 0" and not m.xray_on
    assert [e.t for e in m.log][:3] == [0.0, 0.0, 0.0]


def test_emulator_refuses():
    m = L8121Model(warmed_up=True, watts_max=30)
    assert [m.handle(c) for c in ("HIV 151", "HIV 39", "HIV 6O", "CUR 501", "CFS 9", "FOO", "STS 1", "XON 1")] == \
        ["ERR"] * 8
    assert (m.handle("HIV 100"), m.handle("CUR 400"), m.handle("SER")) == ("HIV 100", "ERR", "SER 4")  # 40 W
    assert m.handle("") is None and m.set_ua == 0


def test_emulator_scheduled_faults():
    clock = Clock()
    m = L8121Model(ramp_s=0, warmed_up=True, clock=clock)
    m.handle("HIV 60"), m.handle("CUR 250"), m.handle("XON")
    m.open_interlock(at_s=1.0)
    clock.t += 0.9
    assert m.xray_on and m.handle("SIN") == "SIN 0"
    clock.t += 0.2
    assert (m.handle("STS"), m.handle("SIN"), m.handle("XON")) == ("STS 2", "SIN 1", "ERROR")
    m.close_interlock()
    m.handle("XON")
    m.drop_beam()
    assert m.handle("SAR") == "SAR 3 60 0 0 0 0 0"
    m.overload(at_s=m.time + 1)
    clock.t += 1
    assert (m.handle("STS"), m.handle("XON"), m.handle("SER")) == ("STS 4", "ERROR", "SER 3")
    assert (m.handle("RST"), m.handle("STS")) == ("RST", "STS 2")
    m.silence()
    assert m.handle("STS") is None and m.log[-1].reply is None
    m.silence(False)
    m.garbage()
    junk = {m.handle("STS") for _ in range(20)}
    assert all(j and not j.startswith("STS") and "\r" not in j for j in junk)


# -- the command line -----------------------------------------------------------------------------
def test_command_line_serves_a_pty():
    proc = subprocess.Popen([sys.executable, "-m", "acquisition.emulators.l8121", "--pty", "--warmup-s", "0.1"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 10)
        assert ready, "the emulator printed no path within 10 s"
        url = proc.stdout.readline().strip()
        assert url.startswith("/dev/"), url
        with serial.serial_for_url(url, timeout=1):
            pass  # pyserial opens it as a serial port
        with SerialTransport(url) as link:
            assert link.query("TYP") == "TYP L8121-01"
            assert link.query("WUP") == "WUP"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, proc.stderr.read()
