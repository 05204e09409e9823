"""The error line `radiokit acquire source on` and `warm-up` end on after a fault that switched
the tube off, in both dialects, through the command line and the emulator on a pseudo-terminal;
and the lines of `source on --for SECONDS`, which holds the beam that long and switches it off.

The line says the fault, then what the switch-off found: "X-rays switched off, confirmed by STS:
<state>" (and the controller's error code), or what the switch-off ran into, and then the X-rays
warning (exit 3). The command line composes it from what the driver's exception carries
(``switch_off``), not by editing the driver's message: a cause worded otherwise still gives a
right line. The driver's timings are shortened (stable_timeout_s, the switch-off's window) through
the class the command line builds; the link and the commands stay real.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import sys
import threading

import pytest

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.guardian import TUBE_WARNING

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

#: short enough for a test, long enough for the emulator's replies (its ramp is 0.1 s)
FAST = dict(stable_timeout_s=0.3, off_confirm_s=0.2, off_attempts=1, poll_s=0.02, min_interval_s=0.02)
#: the command dialect's warm-up start command (L8121.md: A WUP, B an XON while DAG says YET)
WARM_UP = {"A": "WUP", "B": "XON"}


@pytest.fixture(params=["A", "B"])
def dialect(request):
    """The controller's command dialect: every test that takes it runs in both."""
    return request.param


@pytest.fixture
def fast(monkeypatch):
    """The command line's driver with :data:`FAST` timings (it imports the class when it runs)."""
    import acquisition.l8121 as l8121

    class Fast(l8121.L8121):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **{**FAST, **kwargs})

    monkeypatch.setattr(l8121, "L8121", Fast)
    return Fast


def _source(model, action, capsys, inject=None, *extra) -> tuple[int, list[str], str]:
    """Run ``radiokit acquire source ACTION`` against ``model`` in its dialect: the exit code, the
    non-empty stderr lines, and the port's name."""
    code, _, err, port = _source_said(model, action, capsys, inject, *extra)
    return code, err, port


def _source_said(model, action, capsys, inject=None, *extra) -> tuple[int, list[str], list[str], str]:
    """:func:`_source`, with the non-empty stdout lines too (before the stderr lines)."""
    from radiokit.cli import main

    with PtyServer(model) as server:
        if inject is not None:
            inject(model)
        args = ["acquire", "source", action, "--port", server.url, "--dialect", model.dialect, *extra]
        try:
            code = main(args)
        finally:
            model.stuck_on(False)  # the server's own end must be able to close
    out, err = ([ln for ln in text.splitlines() if ln.strip()] for text in capsys.readouterr())
    return code, out, err, server.url


def _not_stable(kv=60, ua=250) -> str:
    """The cause the driver names for a beam that never reached ``kv``, ``ua`` (the emulator's
    dropped emitter: the set voltage, no current), at the default tolerances (1 kV, 5 µA)."""
    return (
        f"beam not stable within stable_timeout_s = {FAST['stable_timeout_s']:g} s: measured {kv} kV 0 µA, "
        f"set {kv} kV {ua} µA (tolerance 1 kV, 5 µA)"
    )


def _unconfirmed(state: str) -> str:
    """What the driver's one attempt (:data:`FAST`) says when ``STS`` still reads ``state``."""
    return (
        f"could not confirm X-rays off after 1 attempt(s) (last: STS still {state} after XOF); "
        "switch the source off at the controller"
    )


ON = ("--kv", "60", "--ua", "250", "--for", "5")  # the faults below come in the ramp: no hold


# an interlock opening or an overload sets no SER code (L8121.md ties none to them): the line
# ends on the confirmed state; a control-board fault's code is named (the next test)
@pytest.mark.parametrize(
    "fault, cause, state",
    [("open_interlock", "interlock open", "STANDBY"), ("overload", "overload", "OVERLOAD")],
)
def test_a_trip_in_the_ramp_ends_on_the_state_sts_confirmed_and_the_error_code(
    dialect, fast, capsys, fault, cause, state
):
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    code_, err, port = _source(model, "on", capsys, lambda m: m.inject_after("XON", getattr(m, fault)), *ON)
    assert code_ == 1 and not model.xray_on, err
    assert err[-1] == f"error: {port}: {cause}; X-rays switched off, confirmed by STS: {state}"


def test_a_beam_never_stable_ends_on_the_confirmed_switch_off_and_the_error_code(dialect, fast, capsys):
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    inject = lambda m: m.inject_after("XON", lambda: (m.drop_beam(), m.controller_error(2)))
    code, err, port = _source(model, "on", capsys, inject, *ON)
    assert code == 1 and not model.xray_on, err
    told = "; controller error code 2"  # (no code: the warm-up's line below)
    assert err[-1] == f"error: {port}: {_not_stable()}; X-rays switched off, confirmed by STS: STANDBY{told}"


def test_a_beam_never_stable_whose_switch_off_fails_says_the_cause_then_the_failure(dialect, fast, capsys):
    """A relay stuck on: the fault, then what switching off ran into (the last try, as the link
    closed), each once; then the warning, exit 3."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    inject = lambda m: m.inject_after("XON", lambda: (m.stuck_on(), m.drop_beam()))
    code, err, port = _source(model, "on", capsys, inject, *ON)
    assert code == 3 and err[-1] == TUBE_WARNING, err
    assert err[-2] == f"error: {port}: {_not_stable()}; switching X-rays off: {_unconfirmed('XRAY_ON')}"
    assert [ln for ln in err if ln.startswith("error:")] == [err[-2]], err


def test_a_switch_off_confirmed_only_by_its_second_try_says_both(dialect, fast, capsys):
    """A relay that sticks for one XOF: the switch-off for the fault was not confirmed, the error
    path's next one was (the first XOF changed nothing; the second is executed)."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)

    def inject(m):
        unstick = lambda: m.inject_after("XOF", lambda: m.stuck_on(False))
        m.inject_after("XON", lambda: (m.stuck_on(), m.drop_beam(), unstick()))

    code, err, port = _source(model, "on", capsys, inject, *ON)
    assert code == 1 and not model.xray_on, err
    assert err[-1] == (
        f"error: {port}: {_not_stable()}; switching X-rays off could not be confirmed; "
        "X-rays off, confirmed by STS: STANDBY"
    )


def test_b_a_trip_on_sts_error_whose_switch_off_fails_says_the_cause_then_the_failure(fast, capsys):
    """B's STS ERROR in the ramp does not show the beam off, before nor after the XOF."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    inject = lambda m: m.inject_after("XON", lambda: (m.stuck_on(), m.sts_error()))
    code, err, port = _source(model, "on", capsys, inject, *ON)
    assert code == 3 and err[-1] == TUBE_WARNING, err
    error = "ERROR (PREHEATING, or a refused query: dialect B does not say which)"
    assert err[-2] == (
        f"error: {port}: STS {error} instead of XON: the beam may have dropped or be on still; "
        f"switching X-rays off: {_unconfirmed(error)}"
    )


def test_a_warm_up_past_its_time_out_ends_on_the_confirmed_switch_off(dialect, fast, capsys):
    model = L8121Model(dialect=dialect, warmup_s=5.0, ramp_s=0.1)
    code, err, port = _source(model, "warm-up", capsys, None, "--timeout", "0.3", "-q")
    assert code == 1 and model.state.name == "WARMUP_NEEDED", err
    # B's STS reads STANDBY while a warm-up is due (its DAG says YET); A's reads warm-up needed
    after = "STANDBY" if dialect == "B" else "WARMUP_NEEDED"
    assert err[-1] == (
        f"error: {port}: warm-up not done within 0.3 s (state WARMING_UP); X-rays switched off, "
        f"confirmed by STS: {after}"
    )


def test_a_warm_up_past_its_time_out_whose_switch_off_fails_does_not_say_switched_off(dialect, fast, capsys):
    """Found (s44): the line said "X-rays switched off; switching X-rays off: could not confirm X-rays
    off": the driver wrote "X-rays switched off" into the time-out's message before any XOF went,
    and a relay stuck on then made it false. The switch-off happens where the time-out is met, and
    the line says what it found."""
    model = L8121Model(dialect=dialect, warmup_s=5.0, ramp_s=0.1)
    inject = lambda m: m.inject_after(WARM_UP[dialect], m.stuck_on)
    code, err, port = _source(model, "warm-up", capsys, inject, "--timeout", "0.3", "-q")
    assert code == 3 and err[-1] == TUBE_WARNING, err
    assert err[-2] == (
        f"error: {port}: warm-up not done within 0.3 s (state WARMING_UP); switching X-rays off: "
        f"{_unconfirmed('WARMING_UP')}"
    )
    assert "switched off" not in err[-2]


class _RunsOn(L8121Model):
    """A warm-up that runs on into X-rays on at its end, and is not recorded done (A's SWE reads
    running, B's DAG YET): L8121.md says nothing of how B's AGING ends."""

    def _start_warm_up(self, t):
        from acquisition.l8121 import SourceState, WarmupState

        self._state, self._warmup, self._warmup_t0 = SourceState.WARMING_UP, WarmupState.RUNNING, t
        self._schedule(t + self.warmup_s, self._switch_on)  # not back to standby: on, at the set values


def test_a_warm_up_that_runs_on_says_its_confirmed_switch_off_once(dialect, fast, capsys):
    """Found (s44): "...does not report it done; X-rays switched off, confirmed by STS: STANDBY
    (state STANDBY)": the confirmation spliced in before the driver's own "(state ...)"."""
    model = _RunsOn(dialect=dialect, warmup_s=0.2, ramp_s=0.1)
    code, err, port = _source(model, "warm-up", capsys, None, "--timeout", "5", "-q")
    assert code == 1 and not model.xray_on, err
    assert re.fullmatch(
        rf"error: {re.escape(port)}: the warm-up ran on into X-rays on after \d+\.\d s and the controller does "
        r"not report it done; X-rays switched off, confirmed by STS: STANDBY",
        err[-1],
    ), err


@pytest.mark.parametrize(
    "cause",
    [
        "interlock open; X-rays switched off by the interlock chain",  # the old splice's marker, in a cause
        "the door was opened",  # a cause worded otherwise
    ],
)
def test_a_cause_worded_otherwise_still_gives_the_right_line(dialect, fast, capsys, monkeypatch, cause):
    """The command line composed its line by editing the driver's message (splicing the
    confirmation after "; X-rays switched off", cutting the driver's "not confirmed" note out):
    a cause that held those words had the confirmation spliced into its middle, and the driver's
    note reworded would have been said twice. The line comes from the exception's fields."""
    monkeypatch.setattr(fast, "_fault_reason", lambda self, *a, **k: cause)
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    code, err, port = _source(model, "on", capsys, lambda m: m.inject_after("XON", m.open_interlock), *ON)
    assert code == 1 and not model.xray_on, err
    assert err[-1] == f"error: {port}: {cause}; X-rays switched off, confirmed by STS: STANDBY"


def test_source_on_warns_of_its_rounding_once_and_sends_the_whole_numbers(dialect, capsys, caplog):
    """`source on` checks --kv/--ua before the port is opened with the driver's own check, and
    on() checks them again: the rounding is said once."""
    from radiokit.cli import main

    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    with caplog.at_level(logging.WARNING), PtyServer(model) as server:
        port = ["--port", server.url, "--dialect", dialect]
        assert main(["acquire", "source", "on", *port, "--kv", "60.4", "--ua", "249.6", "--for", "0.2"]) == 0
        assert not model.xray_on and (model.set_kv, model.set_ua) == (60, 250)
    said = [r.getMessage() for r in caplog.records if "rounded to" in r.getMessage()]
    assert sorted(said) == [
        "tube current 249.6 µA rounded to 250 µA: radiokit sets whole µA (dialect A's commands take integers)",
        "tube voltage 60.4 kV rounded to 60 kV: radiokit sets whole kV (dialect A's commands take integers)",
    ], said


@pytest.mark.parametrize(
    ("action", "values", "said"),
    [
        ("on", ("200", "250"), "voltage_kv = 200 kV is outside kv_min..kv_max"),
        ("on", ("60", "600"), "current_ua = 600 µA is outside ua_min..ua_max"),
        ("warm-up", ("20", "0"), "voltage_kv = 20 kV is outside kv_min..kv_max"),
    ],
)
def test_source_values_out_of_range_are_refused_before_the_port_is_opened(capsys, action, values, said):
    from radiokit.cli import main

    kv, ua = values
    held = ["--for", "1"] if action == "on" else []
    code = main(["acquire", "source", action, "--port", "/dev/null/none", "--kv", kv, "--ua", ua, *held])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"error: --kv {float(kv):g} --ua {float(ua):g}: ") and said in err[0], err
    assert err[0].endswith("; nothing was sent"), err


def test_a_refused_value_is_said_from_the_refusals_field_not_by_cutting_its_speaker(capsys, monkeypatch):
    """The command line and a protocol's ``[source]`` say the driver's refusal of a value in their
    own words: they read ``SettingRefused.detail``, where they cut "L8121: " or "L8121
    configuration: " off its text (a speaker worded otherwise came through whole, doubled in the
    line). The refusal is faked with another speaker; its detail is all either line says of it."""
    from acquisition.l8121 import SettingRefused, SourceConfig
    from acquisition.protocols.compression_series import ProtocolError, SourceSettings, _check_source
    from radiokit.cli import main

    detail = "voltage_kv = 60 kV is outside this unit's range"

    def refuse(self, voltage_kv, current_ua):
        raise SettingRefused(detail, of="L8121-01 (unit 2)")

    monkeypatch.setattr(SourceConfig, "check_exposure", refuse)
    code = main(["acquire", "source", "on", "--port", "/dev/null/none", "--kv", "60", "--ua", "250", "--for", "1"])
    assert code == 2 and capsys.readouterr().err.splitlines() == [
        f"error: --kv 60 --ua 250: {detail}; nothing was sent"
    ]
    with pytest.raises(ProtocolError) as err:
        _check_source(SourceSettings())
    assert str(err.value) == f"[source] {detail}"


# -- `source on --for SECONDS`: the beam held, then switched off ---------------------------------

HOLD = ("--kv", "60", "--ua", "250")
#: the hold's line: the set values, the measured ones, and when it ends
HELD = r"{port}: X-rays ON at 60 kV 250 uA \(measured [\d.]+ kV [\d.]+ uA\) until \d\d:\d\d:\d\d \({s} s\); Ctrl-C switches them off"


def test_source_on_holds_the_beam_for_its_time_then_ends_on_the_confirmed_switch_off(dialect, capsys):
    """`source on` left the beam on when it ended (L8121.md: never on while waiting for a person).
    Now it says before XON how long, holds the beam that long polling it, and ends on XOF
    confirmed by STS, exit 0."""
    from acquisition.protocols.compression_series import SourceSettings

    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    code, out, err, port = _source_said(model, "on", capsys, None, *HOLD, "--for", "0.3")
    assert code == 0 and not model.xray_on and err == [], (out, err)
    assert out[0] == f"{port}: switching X-rays ON at 60 kV 250 uA for 0.3 s: switched off at its end, or at Ctrl-C"
    assert re.fullmatch(HELD.format(port=re.escape(port), s=r"0\.3"), out[1]), out
    assert out[2:] == [f"{port}: 0.3 s over: tube off (confirmed by STS: STANDBY)"], out
    # one XON; the beam held at least the time asked and polled meanwhile; then XOF, confirmed by STS
    commands, times = [e.command for e in model.log], [e.t for e in model.log]
    xon, xof = commands.index("XON"), commands.index("XOF")
    assert commands.count("XON") == 1 and commands[xof:] == ["XOF", "STS"], commands
    assert times[xof] - times[xon] >= 0.3
    assert commands[xon:xof].count("SIN") >= 0.3 // SourceSettings.poll_s, commands  # the interlock watched


def test_source_on_counts_the_hold_down_on_a_terminal_and_ends_it(capsys, monkeypatch):
    """The operator's terminal (stderr a real pseudo-terminal) shows the hold as a bar named for
    the port, from 0 to its end, cleared when the hold is over; the line after it says the tube
    is off. Found writing this: a hold under half a second had a bar of round(0.3) = 0 s, which
    tqdm drew as a bare "0s" that never moved."""
    import fcntl
    import pty
    import struct
    import sys
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a new pty is 0 x 0
    try:
        with open(slave, "w") as tty:  # closes the terminal's end: the read below then ends
            monkeypatch.setattr(sys, "stderr", tty)  # the bar is drawn only where stderr is a terminal
            model = L8121Model(dialect="A", warmed_up=True, ramp_s=0.1)
            code, out, _, port = _source_said(model, "on", capsys, None, *HOLD, "--for", "0.3")
            monkeypatch.undo()
        drawn = b""
        # what the command wrote reaches this end a moment later (the kernel passes it on), and
        # then EIO: read until then, not until the first empty moment
        with contextlib.suppress(OSError):
            while chunk := os.read(master, 65536):
                drawn += chunk
    finally:
        os.close(master)
    assert code == 0 and out[-1] == f"{port}: 0.3 s over: tube off (confirmed by STS: STANDBY)", out
    frames = [f for f in drawn.decode(errors="replace").split("\r") if f.strip()]
    assert frames and all(f.startswith(f"X-rays on ({port}):") for f in frames), frames
    counts = [m.groups() if (m := re.search(r"\| (\d+)/(\d+) \[", f)) else None for f in frames]
    assert counts[0] == ("0", "1") and counts[-1] == ("1", "1"), frames  # from 0 to its end
    assert drawn.endswith(b"\r") and not drawn.rsplit(b"\r", 2)[-2].strip(), drawn  # then cleared


@pytest.mark.parametrize(
    "given, said",
    [
        ((), "'on' needs --for SECONDS: how long X-rays stay on (switched off at its end, or at Ctrl-C)"),
        (
            ("--for", "0"),
            "--for 0: expected a positive number of seconds, at most 3600 (longer exposures are a protocol's)",
        ),
        (
            ("--for", "nan"),
            "--for nan: expected a positive number of seconds, at most 3600 (longer exposures are a protocol's)",
        ),
        (
            ("--for", "3601"),
            "--for 3601: expected a positive number of seconds, at most 3600 (longer exposures are a protocol's)",
        ),
    ],
)
def test_source_on_without_a_time_is_refused_before_the_port_is_opened(capsys, given, said):
    """No open-ended beam from a command line: `on` without --for (or with one that is not a
    positive time within the bound) is one line, exit 2, and the controller hears nothing."""
    model = L8121Model(dialect="A", warmed_up=True)
    code, out, err, _ = _source_said(model, "on", capsys, None, *HOLD, *given)
    assert code == 2 and out == [] and err == [f"error: {said}; nothing was sent"], err
    assert model.log == [] and not model.xray_on


@pytest.mark.parametrize(
    "fault, cause, state",
    [("open_interlock", "interlock open", "STANDBY"), ("overload", "overload", "OVERLOAD")],
)
def test_a_fault_in_the_hold_ends_on_the_confirmed_switch_off(dialect, fast, capsys, fault, cause, state):
    """The hold polls as a series' beam monitor does: an interlock opened (or an overload) while
    the beam is held switches off, confirmed, and the line says why, exit 1 -- the same line as a
    fault in the ramp. The fault lands between two polls (right after one's last exchange, SER):
    at a model time instead (0.5 s after XON) it landed, under load, between B's STS and SCU once,
    and the line was the overload seen as a dropped beam first (the next test)."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.1)
    # 0.5 s after XON: past the ramp (0.1 s) and the wait for a stable beam (at most 0.3 s, FAST)
    code_, out, err, port = _source_said(model, "on", capsys, _in_the_hold(fault, "SER"), *HOLD, "--for", "5")
    assert code_ == 1 and not model.xray_on, (out, err)
    assert re.fullmatch(HELD.format(port=re.escape(port), s="5"), out[-1]), out  # it came in the hold
    assert err[-1] == f"error: {port}: {cause}; X-rays switched off, confirmed by STS: {state}"


def _in_the_hold(fault: str, after: str):
    """An ``inject`` for :func:`_source_said`: the model's ``fault`` (a method name) right after
    the first ``after`` exchange 0.5 s (wall clock) or more after XON, in the hold's polls."""

    def inject(m):
        def arm():
            m.inject_after(after, getattr(m, fault))

        def later():
            timer = threading.Timer(0.5, arm)
            timer.daemon = True
            timer.start()

        m.inject_after("XON", later)

    return inject


def test_an_overload_between_b_state_and_current_readings_is_named_with_what_the_poll_saw(fast, capsys):
    """B reads the state (STS), then kV (SHV) and µA (SCU) in separate exchanges: an overload
    after a poll's STS read X-rays on is seen as the current dropped, and named an overload by
    the STS after the XOF, with that reading kept -- the wording the hold's test met once under
    load, made certain here (the fault right after the poll's STS). Exit 1, tube off confirmed."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    code_, out, err, port = _source_said(model, "on", capsys, _in_the_hold("overload", "STS"), *HOLD, "--for", "5")
    assert code_ == 1 and not model.xray_on, (out, err)
    assert re.fullmatch(HELD.format(port=re.escape(port), s="5"), out[-1]), out
    assert err[-1] == (
        f"error: {port}: overload (beam dropped: measured current 0 µA, below 50% of the set 250 µA); "
        "X-rays switched off, confirmed by STS: OVERLOAD"
    ), err


@pytest.mark.parametrize("sig, stuck", [("SIGINT", False), ("SIGTERM", False), ("SIGTERM", True)])
def test_a_stop_in_the_hold_switches_off_as_every_source_command_stops(fast, capsys, monkeypatch, sig, stuck):
    """Ctrl-C or kill in the hold: XOF, and the stop's line with the state STS confirmed, exit
    128 + N; a relay stuck on (the switch-off not confirmed): the switch-off's failure, then the
    X-rays warning last, exit 3."""
    import acquisition.cli

    signum, hold = getattr(signal, sig), acquisition.cli._hold_beam
    model = L8121Model(dialect="A", warmed_up=True, ramp_s=0.1)

    def stop():
        if stuck:
            model.stuck_on()
        os.kill(os.getpid(), signum)

    def stopped(*args):
        timer = threading.Timer(0.3, stop)  # a real signal, 0.3 s into the hold
        timer.start()
        try:
            return hold(*args)
        finally:
            timer.cancel()  # (the hold ended otherwise: no signal after the command)

    monkeypatch.setattr(acquisition.cli, "_hold_beam", stopped)
    code, out, err, port = _source_said(model, "on", capsys, None, *HOLD, "--for", "5")
    assert re.fullmatch(HELD.format(port=re.escape(port), s="5"), out[-1]), out
    if stuck:
        assert code == 3 and err[-1] == TUBE_WARNING, err
        # (as every source command whose stop's switch-off is not confirmed: that failure, then the warning)
        assert err[-2] == f"error: {port}: {_unconfirmed('XRAY_ON')}", err
        return
    assert code == 128 + signum and not model.xray_on, err
    assert err[-1] == f"stopped by {sig}; tube off (confirmed by STS: STANDBY)", err


def test_a_hold_whose_switch_off_is_not_confirmed_ends_on_the_warning(fast, capsys, monkeypatch):
    """The hold's own end is an exit path too: a relay stuck on as the time runs out (XOF answered,
    STS still reads X-rays on) ends on that failure, then the X-rays warning, exit 3 -- never on
    "tube off"."""
    import acquisition.cli

    hold = acquisition.cli._hold_beam
    model = L8121Model(dialect="A", warmed_up=True, ramp_s=0.1)

    def held_then_stuck(*args):
        hold(*args)
        model.stuck_on()

    monkeypatch.setattr(acquisition.cli, "_hold_beam", held_then_stuck)
    code, out, err, port = _source_said(model, "on", capsys, None, *HOLD, "--for", "0.2")
    assert code == 3 and err[-1] == TUBE_WARNING, (out, err)
    assert err[-2] == f"error: {port}: {_unconfirmed('XRAY_ON')}", err
    assert not any("tube off" in line for line in out + err), (out, err)


def _stop_in_the_last_moments(monkeypatch, where: str) -> None:
    """A real SIGINT to this process in a command's last moments, hit deterministically (no sleep):
    right after its guard's ``finish()`` (the outcome decided, the tube's line said or about to be),
    or right after the guard is left (the command returned, the process not yet ended)."""
    import acquisition.cli
    from acquisition.guardian import SignalGuard

    ctrl_c = lambda: os.kill(os.getpid(), signal.SIGINT)
    if where == "after finish":
        finish = SignalGuard.finish

        def finished(self, *args, **kwargs):
            finish(self, *args, **kwargs)
            ctrl_c()

        monkeypatch.setattr(SignalGuard, "finish", finished)
    else:
        guarded = acquisition.cli._guarded

        def left(*args):
            code = guarded(*args)
            ctrl_c()
            return code

        monkeypatch.setattr(acquisition.cli, "_guarded", left)


@pytest.mark.parametrize("where", ["after finish", "after the guard"])
@pytest.mark.parametrize("action", ["probe", "off"])
@pytest.mark.parametrize("entry", ["script", "main"])
def test_a_ctrl_c_in_a_source_command_s_last_moments_exits_130_not_0(
    dialect, capsys, monkeypatch, action, where, entry
):
    """Found (review of s52): once a source command's outcome was decided its stop signals were
    ignored, and a Ctrl-C in the 20-150 ms to the process's end was lost: exit 0, and `radiokit
    acquire source probe ... && radiokit acquire source on ...` switched X-rays on after the
    operator's Ctrl-C. Now such a stop is recorded, not acted on: the lines stay as they were (the
    tube's state last), the exit code is 130 -- through the console script (``script()``, which
    records them to its exit, then ignores them: it must not die by the signal then) and
    through ``main()`` (which gives a calling program its handlers back). Real emulator on a
    pseudo-terminal, a real SIGINT."""
    import atexit

    import radiokit.cli
    from radiokit.cli import _TAKEN, main, script
    from radiokit.interrupts import note_after_the_end

    def mine(signum, frame):  # the calling program's own handler: never run inside the command
        raise AssertionError("the caller's handler ran inside the command")

    before = {sig: signal.signal(sig, mine) for sig in _TAKEN}
    try:
        _stop_in_the_last_moments(monkeypatch, where)
        model = L8121Model(dialect=dialect, warmed_up=True)
        with PtyServer(model) as server:
            dialect_given = [] if action == "probe" else ["--dialect", dialect]
            argv = ["acquire", "source", action, "--port", server.url, *dialect_given]
            if entry == "script":
                monkeypatch.setattr(sys, "argv", ["radiokit", *argv])
                code = script()
            else:
                code = main(argv)
            after = {sig: signal.getsignal(sig) for sig in _TAKEN}
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
        if radiokit.cli._AT_THE_EXIT is not None:  # the console script's hook: not pytest's exit
            atexit.unregister(radiokit.cli._AT_THE_EXIT)
    out, err = capsys.readouterr()
    assert code == 128 + signal.SIGINT, (code, out, err)
    assert not model.xray_on and "state STANDBY" in out, (out, err)  # the probe's report, or the tube's line
    # nothing said of the stop: the command's lines stay as they were, the tube's state the last
    said = out + err
    assert not any(word in said for word in ("Traceback", "stopped by", "interrupted", "please wait")), said
    # the console script's process records them to its exit (ignored for the interpreter's end,
    # which would turn a handler back into the default: death by SIGINT; the next test); main()
    # gives the caller's back
    assert after == dict.fromkeys(_TAKEN, note_after_the_end if entry == "script" else mine), after


#: a console script's process whose probe gets a real Ctrl-C right after its guard's finish(), or
#: after script() returned, or as the interpreter ends (an atexit callback registered first, so run
#: last; argv: the port, where)
_PROBE_STOPPED_AT_ITS_END = """
import atexit, os, signal, sys
from acquisition.guardian import SignalGuard
from radiokit.cli import script
port, where = sys.argv[1:]
ctrl_c = lambda: os.kill(os.getpid(), signal.SIGINT)
if where == "as Python ends":
    atexit.register(ctrl_c)
finish = SignalGuard.finish
def finished(self, *args, **kwargs):
    finish(self, *args, **kwargs)
    if where == "after finish":
        ctrl_c()
SignalGuard.finish = finished
sys.argv = ["radiokit", "acquire", "source", "probe", "--port", port]
code = script()
if where == "after script() returned":
    ctrl_c()
sys.exit(code)
"""


@pytest.mark.parametrize("where", ["after finish", "after script() returned", "as Python ends"])
def test_a_console_script_stopped_at_its_end_is_not_killed_by_the_signal(where):
    """The whole process, as the shell sees it: a Ctrl-C after the probe's outcome was decided,
    or after ``script()`` returned (the 20-45 ms the interpreter takes to end: most of the window),
    gives exit 130 (0 before: `probe && source on` went on). One as Python's last callbacks
    run, when the handlers are set to ignore (the interpreter's end would turn a Python handler
    back into the default) does not kill it by SIGINT (exit -2): exit 0, the probe done. Real
    emulator on a pseudo-terminal, real signals."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    model = L8121Model(dialect="A", warmed_up=True)
    with PtyServer(model) as server:
        res = subprocess.run(
            [sys.executable, "-c", _PROBE_STOPPED_AT_ITS_END, server.url, where],
            capture_output=True,
            text=True,
            cwd=root,
            timeout=60,
        )
    expected = 0 if where == "as Python ends" else 128 + signal.SIGINT
    assert res.returncode == expected, (res.returncode, res.stdout, res.stderr)
    assert "state STANDBY" in res.stdout and "Traceback" not in res.stderr, (res.stdout, res.stderr)
