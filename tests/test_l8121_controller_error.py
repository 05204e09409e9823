"""No X-ray command while the controller reports an error (``SER`` not 0), in both dialects.

``L8121.md``: dialect A's ``SER n`` is the "controller error code, 0 none"; dialect B's is the
"control-board error: 0 none, 1-4 relay or internal faults". Neither dialect relates the code to
``STS``, and neither says the controller refuses ``XON`` for it, so a unit may read standby, accept
``XON`` and emit with a relay fault standing: the driver has to ask before each X-ray command
(``on()``'s ``XON``, the warm-up's ``WUP``/``XON``) and refuse, the tube left off and nothing
reset. Against radiokit's emulator (its ``controller_error`` fault) and ``independent_l8121``
(its ``error_code``, written from the notes alone), each on a real pseudo-terminal.
"""

from __future__ import annotations

import os
import time

import pytest
from independent_l8121 import Controller

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError, SourceFault
from acquisition.l8121 import DIALECTS, ERROR_POLL_S, L8121, SourceState

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

FAST = dict(poll_s=0.05, min_interval_s=0.02)
X_RAY_COMMANDS = ("XON", "WUP")
# what the message must say the code means: B's notes give 1-4 a meaning, A's give none
MEANING = {"A": "gives dialect A's error codes no meaning", "B": "relay or internal fault"}


@pytest.fixture(params=["A", "B"])
def dialect(request):
    return request.param


def _refusal_names_the_fault(exc: SourceFault, dialect: str, code: int) -> None:
    text = str(exc)
    assert f"error code {code}" in text and MEANING[dialect] in text, text
    assert "not switched on" in text or "not started" in text, text


@pytest.mark.parametrize("code", [2, 4])
def test_on_refuses_before_xon_while_the_emulator_reports_a_controller_error(dialect, code):
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    model.controller_error(code)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        with pytest.raises(SourceFault) as err:
            src.on(60, 250)
        _refusal_names_the_fault(err.value, dialect, code)
        assert not model.xray_on and src.tube_confirmed_off
    sent = model.commands
    assert "SER" in sent and not set(sent) & {*X_RAY_COMMANDS, "RST"}, sent
    # asked after the values were set and read back: the last word before the XON that did not go
    assert sent.index("SER") > max(i for i, c in enumerate(sent) if c.startswith(("HIV", "PHV"))), sent


def test_the_warm_up_is_not_started_while_the_emulator_reports_a_controller_error(dialect):
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1)
    model.controller_error(3)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        with pytest.raises(SourceFault) as err:
            src.warm_up(timeout_s=5, progress=False)
        _refusal_names_the_fault(err.value, dialect, 3)
        assert not model.xray_on
    assert not set(model.commands) & {*X_RAY_COMMANDS, "RST"}, model.commands


def test_once_the_fault_is_cleared_at_the_unit_the_same_driver_switches_on(dialect):
    """The refusal is the fault's, not a latch of the driver's: cleared at the unit, on() goes on."""
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    model.controller_error(1)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        with pytest.raises(SourceFault):
            src.on(60, 250)
        model.controller_error(0)
        reading = src.on(60, 250)
        assert reading["current_ua"] == pytest.approx(250, abs=src.config.tolerance_ua(250))
        assert model.xray_on
        src.off()
    assert "RST" not in model.commands


def test_the_emulators_ser_follows_l8121_md(dialect):
    """L8121.md: B's ``SER n`` is the control-board error, 0 none, 1-4 relay or internal faults;
    A's the "controller error code, 0 none". The emulator used 1-4 for interlock, warm-up, overload
    and range, added 5-7 of its own, and set them at every refusal: a unit the notes do not
    describe. Now SER reads 0 through refusals, an interlock opening and an overload (the notes tie
    no command or state to it); an injected fault reads as itself, B's only among 1-4, and nothing
    sent clears it (not RST, not a setting) until it is cleared at the unit."""
    model = L8121Model(dialect=dialect, warmup_s=0, ramp_s=0, warmed_up=True)
    refused = "ERR" if dialect == "A" else "ERROR"
    voltage = {"A": "HIV", "B": "PHV"}[dialect]
    assert model.handle("XON") == "XON" and model.handle("XOF") == "XOF"
    model.open_interlock()
    assert model.handle("XON") == "ERROR" and model.handle("SER") == "SER 0"
    assert model.handle(f"{voltage} 9999") == refused and model.handle("NOPE") == refused
    model.close_interlock()
    assert model.handle("XON") == "XON"
    model.open_interlock()  # the beam dropped by the interlock
    assert not model.xray_on and model.handle("SER") == "SER 0"
    model.close_interlock()
    model.overload()
    assert model.handle("SER") == "SER 0" and model.handle("RST") == "RST"
    for code in (1, 2, 3, 4):
        model.controller_error(code)
        assert model.handle("SER") == f"SER {code}"
    for cleared_by_nothing in ("RST", f"{voltage} 600" if dialect == "B" else f"{voltage} 60", "XOF"):
        model.handle(cleared_by_nothing)
        assert model.handle("SER") == "SER 4", cleared_by_nothing
    if dialect == "B":
        for code in (5, 7):
            with pytest.raises(ValueError, match="1-4"):
                model.controller_error(code)
    else:  # A's codes have no table: any is what the unit may report
        model.controller_error(9)
        assert model.handle("SER") == "SER 9"
    model.controller_error(0)
    assert model.handle("SER") == "SER 0"


def test_a_refused_xon_is_no_fault(dialect):
    """A refused XON (the interlock was open) must not block the next on() once the interlock is
    closed: the refusal leaves SER at 0."""
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    assert model.handle("XON") == "XON" and model.handle("XOF") == "XOF"
    model.open_interlock()
    assert model.handle("XON") == "ERROR"
    model.close_interlock()
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        src.on(60, 250)
        assert model.xray_on
        src.off()


# 7: beyond B's 1-4 in L8121.md (a unit may differ): the driver stays generic, any code not 0 and
# not allowed by the configuration refuses (the independent model reports what it is given)
@pytest.mark.parametrize("code", [1, 3, 7])
def test_on_refuses_while_the_independent_model_reports_a_controller_error(dialect, code):
    with Controller(dialect, warmup_s=0.3, ramp_s=0.2, error_code=code) as unit:
        unit.ready(warmed=True)
        with L8121(unit.port, dialect=dialect, poll_s=0.05) as src:
            with pytest.raises(SourceFault) as err:
                src.on(60, 250)
            _refusal_names_the_fault(err.value, dialect, code)
            assert ("not among L8121.md's dialect B codes" in str(err.value)) == (dialect == "B" and code > 4)
            assert not unit.emitting
        assert unit.emissions == [] and not unit.lost
        assert "RST" not in [line for _, line, _ in unit.log]


def test_the_independent_models_warm_up_is_not_started_with_a_controller_error(dialect):
    with Controller(dialect, warmup_s=0.3, ramp_s=0.2, error_code=2) as unit:
        unit.ready()
        with L8121(unit.port, dialect=dialect, poll_s=0.05) as src:
            with pytest.raises(SourceFault) as err:
                src.warm_up(timeout_s=5, progress=False)
            _refusal_names_the_fault(err.value, dialect, 2)
        assert unit.emissions == [] and not unit.emitting


def test_a_code_the_configuration_allows_and_a_unit_without_ser(dialect):
    """Review s40rr2: the check had no configuration, so a unit whose manual calls a code harmless,
    or one that answers no SER, could never be switched on. ``allowed_error_codes`` lets those
    codes through (any other still refuses); a refused SER says to set ``error_query = false``,
    and with it nothing is asked and on() goes on."""
    from acquisition.errors import DeviceError
    from acquisition.l8121 import SourceConfig

    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    model.controller_error(4)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, allowed_error_codes=[4], **FAST) as src:
        src.on(60, 250)
        assert model.xray_on
        src.off()
        model.controller_error(2)
        with pytest.raises(SourceFault, match="error code 2"):
            src.on(60, 250)
        assert not model.xray_on
    refuse = "ERR" if dialect == "A" else "ERROR"
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    model._commands["SER"] = lambda t: refuse  # a unit without SER (no emulator knob: its front end)
    with PtyServer(model) as server:
        with L8121(server.url, dialect=dialect, **FAST) as src:
            with pytest.raises(DeviceError, match="set error_query = false"):
                src.on(60, 250)
            assert not model.xray_on
        with L8121(server.url, dialect=dialect, error_query=False, **FAST) as src:
            src.on(60, 250)
            assert model.xray_on
            src.off()
    for bad in ([0], 3, "5", [True], [2.0]):
        with pytest.raises(ValueError, match="allowed_error_codes"):
            SourceConfig(allowed_error_codes=bad)
    assert SourceConfig.from_toml("[source]\nallowed_error_codes = [5, 7]").allowed_error_codes == (5, 7)


# -- a controller error while the beam is on ------------------------------------------------------
# L8121.md: B's 1-4 are relay or internal faults of the control board; "a relay or internal fault
# with high voltage on" is a reason to stop. Before s47ser, SER was asked only before an X-ray
# command: a code that came up mid-exposure went unnoticed for the whole exposure (review s47).


def _poll_until_fault(src, budget_s: float = 3.0) -> None:
    """``check()`` every ``poll_s`` for at most ``budget_s``, as the series' beam monitor does."""
    deadline = time.monotonic() + budget_s
    while time.monotonic() < deadline:
        src.check()
        time.sleep(src.config.poll_s)
    pytest.fail(f"no fault within {budget_s:g} s of polling")


def _ser_times(model, since: int = 0) -> list[float]:
    return [e.t for e in model.log[since:] if e.command == "SER"]


@pytest.mark.parametrize("code", [2, 4])
def test_a_controller_error_with_the_beam_on_switches_off(dialect, code):
    """The code comes up mid-exposure (the emulator's state stays X-rays on, as L8121.md relates
    it to no state): the polls read SER at most every ERROR_POLL_S, between their beam checks,
    and the first one that reads it switches off (XOF, confirmed by STS) and names the code."""
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        src.on(60, 250)
        src.check()
        n, t_fault = len(model.log), model.time
        model.controller_error(code)
        with pytest.raises(SourceFault) as err:
            _poll_until_fault(src)
        assert src.tube_confirmed_off
    text = str(err.value)
    assert f"controller error code {code}" in text and MEANING[dialect] in text, text
    assert "X-rays switched off" in text, text
    assert not model.xray_on and "RST" not in model.commands
    after = [e.command for e in model.log[n:]]
    first = after.index("XOF")
    poll = [DIALECTS[dialect].readings[r].command for r in DIALECTS[dialect].poll]
    # the beam checks went on meanwhile: only the poll's queries and the one SER that read the code
    assert set(after[:first]) <= {*poll, "SER"} and after[:first].count("SER") == 1, after
    assert after[first - 1] == "SER" and "STS" in after[first + 1 :], after
    xof_t = next(e.t for e in model.log[n:] if e.command == "XOF")
    # at most one SER interval and one poll cycle (its queries, poll_s) from the fault to XOF
    assert xof_t - t_fault <= ERROR_POLL_S + 0.5, xof_t - t_fault
    # a bounded rate: on()'s SER before XON, then one every ERROR_POLL_S at most
    sers = _ser_times(model)
    assert all(b - a >= ERROR_POLL_S * 0.99 for a, b in zip(sers[-2:-1], sers[-1:])), sers


@pytest.mark.parametrize("period_s", [0.3, 2.0])
def test_the_error_poll_period_is_the_configurations(dialect, period_s):
    """``error_poll_s`` (``[source] error_poll_s``; was the constant ERROR_POLL_S, 1 s) sets how
    often the polls read SER with the beam on: 1.5 s of polls every 50 ms read it about
    1.5 / period_s times, each gap at least the period (and at most the period and one poll cycle:
    A's SAR SIN, B's STS SHV SCU SIN, 20 ms apart, then poll_s)."""
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, error_poll_s=period_s, **FAST) as src:
        assert src.config.error_poll_s == period_s
        src.on(60, 250)
        n = len(model.log)
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            src.check()
            time.sleep(FAST["poll_s"])
        src.off()
    sers = [e.t for e in model.log[n:] if e.command == "SER" and e.t < model.log[-1].t]
    sers = [t for t in sers if not any(e.command == "XOF" and e.t <= t for e in model.log[n:])]
    gaps = [b - a for a, b in zip(sers, sers[1:])]
    cycle = 5 * FAST["min_interval_s"] + FAST["poll_s"] + 0.1  # one poll's queries and its pause, with room
    assert all(period_s * 0.99 <= g <= period_s + cycle for g in gaps), (period_s, gaps)
    expected = 1.5 / period_s
    assert expected - 2 <= len(sers) <= expected + 1, (period_s, sers)


def test_a_garbled_ser_reply_with_the_beam_on_is_as_bad_as_any_garbled_poll(dialect):
    """An unreadable SER mid-exposure is what an unreadable SAR or SIN is (check()'s reading):
    the fail-safe switches off, confirmed, and the error names the reply."""
    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        src.on(60, 250)
        model.garble_once("SER")
        with pytest.raises(DeviceError, match="unparseable reply to SER"):
            _poll_until_fault(src)
        assert src.tube_confirmed_off and not model.xray_on
    assert "XOF" in commands_after_ser(model)


def commands_after_ser(model) -> list[str]:
    cmds = model.commands
    return cmds[len(cmds) - cmds[::-1].index("SER") :]


def test_a_controller_error_during_the_warm_up_switches_it_off(dialect):
    """The warm-up emits (B reports it as AGING): a code that comes up while it runs stops it as
    an open interlock does, switched off and named, long before the warm-up would have ended."""
    model = L8121Model(dialect=dialect, warmup_s=5.0, ramp_s=0.1)
    start = "WUP" if dialect == "A" else "XON"
    model.inject_after(start, lambda: model.controller_error(3, at_s=model.time + 0.1))
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **FAST) as src:
        t0 = time.monotonic()
        with pytest.raises(SourceFault) as err:
            src.warm_up(timeout_s=10, progress=False)
        assert time.monotonic() - t0 < ERROR_POLL_S + 1.0
        assert src.tube_confirmed_off
    assert "controller error code 3" in str(err.value) and "warm-up" in str(err.value), str(err.value)
    assert model.state != SourceState.WARMING_UP and not model.xray_on and "RST" not in model.commands


def test_cli_source_on_for_stops_on_a_controller_error(dialect, capsys):
    """``radiokit acquire source on --for``: the hold's polls read SER too; a code that comes up
    0.2 s after XON ends the hold (exit 1), the tube off, confirmed, the line naming the code."""
    from radiokit.cli import main

    model = L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.1, warmed_up=True)
    model.inject_after("XON", lambda: model.controller_error(2, at_s=model.time + 0.2))
    with PtyServer(model) as server:
        args = ["--port", server.url, "--dialect", dialect, "--kv", "60", "--ua", "250", "--for", "10"]
        t0 = time.monotonic()
        assert main(["acquire", "source", "on", *args]) == 1
        assert time.monotonic() - t0 < 4.0  # not the 10 s hold
    err = capsys.readouterr().err.strip().splitlines()
    assert any("controller error code 2" in line for line in err), err
    assert not model.xray_on and "XOF" in model.commands and "RST" not in model.commands
