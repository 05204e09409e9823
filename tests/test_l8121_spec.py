"""The L8121 driver against a second, independent model of the controller, written from
``L8121.md`` alone (not from ``acquisition.emulators.l8121``), on a real pseudo-terminal.

The project's emulator and driver were written together, so they can share a misreading of the
hardware notes; this model is deliberately separate and small. It keeps the link rules of
``L8121.md`` that hold for both dialects -- the default of 9600 baud (a line at another rate is
not understood), and a controller that may need ~50 ms between commands (a command that comes
sooner is lost) -- and, as an option, a controller that reports an open interlock without
switching the tube off itself (``L8121.md`` says only that ``XON`` is refused then).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import termios
import threading
import time
import tty

import pytest

from acquisition.errors import DeviceError, SourceFault
from acquisition.guardian import TUBE_WARNING
from acquisition.l8121 import L8121, SourceConfig

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

_SPEEDS = {termios.B9600: 9600, termios.B38400: 38400, termios.B115200: 115200}
_A_CODES = {"WUPNEED": 0, "WARMING": 1, "STANDBY": 2, "XON": 3, "OVER": 4, "NOTREADY": 5}
_B_FOCUS = ("CFS", "CFM", "CFL")
_B_WORDS = {"WUPNEED": "STANDBY", "WARMING": "AGING", "STANDBY": "STANDBY", "XON": "XON", "OVER": "OVER"}


class SpecModel:
    """One L8121 controller in dialect ``"A"`` or ``"B"``, as ``L8121.md`` describes it."""

    def __init__(self, dialect, *, baud=9600, warm=False, warmup_s=0.3, ramp_s=0.2, min_gap_s=0.045, checking_s=0.0):
        self.dialect, self.baud, self.min_gap_s = dialect, baud, min_gap_s
        self.warmup_s, self.ramp_s = warmup_s, ramp_s
        # power-on checks still running for checking_s after the first command (the unit was
        # switched on just before the session): A's STS 6 (self-test), B's STS ERROR (pre-heating);
        # XON and WUP are refused meanwhile ("wrong state")
        self.checking_s, self.checks_end = checking_s, None
        # B: the warm-up (AGING) runs on into X-rays on at its end instead of back to STANDBY;
        # L8121.md says AGING is X-rays on and nothing of how it ends
        self.warm_up_ends_on = False
        self.state = "STANDBY" if warm else "WUPNEED"
        self.interlock_closed = True
        self.interlock_stops_beam = True  # False: the controller only reports the open interlock
        self.relay_stuck = False  # True: XOF is answered but the tube stays on (a fault)
        self.silent = False  # True: commands are carried out but never answered
        # B writes currents as "uA" (L8121.md's table); a unit may write the micro sign instead,
        # in this encoding ("latin-1" or "utf-8"), as the notes' own prose does ("µA")
        self.micro_sign: str | None = None
        self.set_kv = self.set_ua = 0
        self.focus = 0  # A: CFS n / SFC n; B: CFS, CFM, CFL / SFS SMALL, MIDDLE, LARGE (0, 1, 2)
        # a unit that refuses a focus command during its power-on checks ("wrong state": L8121.md
        # says nothing of which commands a unit takes then)
        self.focus_waits_for_checks = False
        self.t_on = self.t_warm = 0.0
        self.received: list[str] = []  # what was understood, in order
        self.lost: list[str] = []  # what arrived at the wrong rate or too soon
        self.lock = threading.Lock()

    @property
    def emitting(self) -> bool:
        with self.lock:
            self._tick()
            return self.state in ("XON", "WARMING")

    def _tick(self):
        if self.state == "WARMING" and time.monotonic() - self.t_warm >= self.warmup_s:
            self.state = "STANDBY"
            if self.warm_up_ends_on and self.dialect == "B":
                self.state, self.t_on = "XON", self.t_warm + self.warmup_s
        if not self.interlock_closed and self.interlock_stops_beam and self.state in ("XON", "WARMING"):
            self.state = "STANDBY" if self.state == "XON" else "WUPNEED"

    def _measured(self):
        if self.state != "XON":
            return 0.0, 0.0
        f = min(1.0, (time.monotonic() - self.t_on) / self.ramp_s) if self.ramp_s else 1.0
        return self.set_kv * f, self.set_ua * f

    def handle(self, line: str) -> str:
        with self.lock:
            self._tick()
            self.received.append(line)
            if self.checks_end is None:
                self.checks_end = time.monotonic() + self.checking_s
            word, *args = line.split() or [""]
            value = int(args[0]) if len(args) == 1 and args[0].isdigit() else None
            refused = "ERR" if self.dialect == "A" else "ERROR"
            reply = self._setting(word, value, line) if args else self._action(word)
            return refused if reply is None else reply

    def _setting(self, word, value, line):
        b = self.dialect == "B"
        if value is None:
            return None
        if word in (("PHV", "HIV") if b else ("HIV",)):
            if b and (word == "HIV") != (self.state == "XON"):
                return None  # B: HIV/CUR while on, the presets PHV/PCU while off
            kv = value / 10 if b else value
            if not 40 <= kv <= 150:
                return None
            self.set_kv = kv
            return line
        if word in (("PCU", "CUR") if b else ("CUR",)):
            if b and (word == "CUR") != (self.state == "XON"):
                return None
            if not 0 <= value <= 500:
                return None
            self.set_ua = value
            return line
        if word == "CFS" and not b and value <= 3 and not self._checking_refuses_focus():
            self.focus = value
            return line
        return None

    def _checking_refuses_focus(self) -> bool:
        return self.focus_waits_for_checks and time.monotonic() < self.checks_end

    def _action(self, word):
        if word == "XOF":
            if self.relay_stuck:
                return "XOF"
            self.state = {"XON": "STANDBY", "WARMING": "WUPNEED"}.get(self.state, self.state)
            return "XOF"
        if word in ("XON", "WUP") and time.monotonic() < self.checks_end:
            return None
        if word == "XON":
            if not self.interlock_closed:
                return None
            if self.dialect == "B" and self.state == "WUPNEED":
                self.state, self.t_warm = "WARMING", time.monotonic()  # B: XON starts the warm-up
                return "XON"
            if self.state != "STANDBY":
                return None
            self.state, self.t_on = "XON", time.monotonic()
            return "XON"
        if self.dialect == "B" and word in _B_FOCUS and not self._checking_refuses_focus():
            self.focus = _B_FOCUS.index(word)
            return word
        if word == "WUP" and self.dialect == "A":
            if self.state not in ("WUPNEED", "STANDBY") or not self.interlock_closed:
                return None
            self.state, self.t_warm = "WARMING", time.monotonic()
            return "WUP"
        return (self._query_a if self.dialect == "A" else self._query_b)(word)

    def _query_a(self, word):
        kv, ua = self._measured()
        done = 1 if self.state == "WARMING" else 2 if self.state == "WUPNEED" else 0
        code = 6 if time.monotonic() < self.checks_end else _A_CODES[self.state]
        return {
            "STS": f"STS {code}",
            "SAR": f"SAR {code} {kv:.0f} {ua:.0f} 0 0 0 0",
            "SVI": f"SVI {self.set_kv} {self.set_ua}",
            "SIN": f"SIN {0 if self.interlock_closed else 1}",
            "SWE": f"SWE {done}",
            "SER": "SER 0",
            "SFC": f"SFC {self.focus}",
            "TYP": "TYP L8121-01",
        }.get(word)

    def _query_b(self, word):
        kv, ua = self._measured()
        done = self.state not in ("WUPNEED", "WARMING")
        return {
            "STS": "ERROR" if time.monotonic() < self.checks_end else _B_WORDS[self.state],
            "SHV": f"SHV {kv:.1f}kV",
            "SCU": f"SCU {ua:.0f}{'µA' if self.micro_sign else 'uA'}",
            "SPV": f"SPV {self.set_kv:.1f}kV",
            "SPC": f"SPC {self.set_ua}{'µA' if self.micro_sign else 'uA'}",
            "SIN": "INTER LOCK ON" if self.interlock_closed else "INTER LOCK OFF",
            "DAG": f"AGING 1 {3 if done else 0} {'END' if done else 'YET'}",
            "SER": "SER 0",
            "SRL": "REMOTE",
            "SRB": "READY",
            "SFS": ("SMALL", "MIDDLE", "LARGE")[self.focus],
        }.get(word)


class SpecPty:
    """``model`` on a pseudo-terminal: CR-terminated lines in, replies ending in CR out."""

    def __init__(self, model: SpecModel):
        self.model = model
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.url = os.ttyname(self._slave)
        self._last = float("-inf")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self):
        buf = b""
        while not self._stop.is_set():
            if not select.select([self._master], [], [], 0.02)[0]:
                continue
            try:
                buf += os.read(self._master, 1024)
            except OSError:
                continue
            while b"\r" in buf:
                raw, buf = buf.split(b"\r", 1)
                line = raw.decode("ascii", "replace").strip()
                speed = _SPEEDS.get(termios.tcgetattr(self._master)[4])
                if speed != self.model.baud or time.monotonic() - self._last < self.model.min_gap_s:
                    self.model.lost.append(line)  # a UART at another rate, or a controller not ready
                    continue
                reply = self.model.handle(line)
                # the gap is counted from before the reply goes out: a stamp taken after the write
                # runs late when this thread is descheduled there (a loaded machine), and the
                # driver's next command, spaced from its receipt of the reply, looked too soon
                self._last = time.monotonic()
                if not self.model.silent:
                    os.write(self._master, reply.encode(self.model.micro_sign or "ascii") + b"\r")

    def close(self):
        self._stop.set()
        self._thread.join(2)
        os.close(self._master)
        os.close(self._slave)


@pytest.fixture(params=["A", "B"])
def dialect(request):
    return request.param


@contextlib.contextmanager
def served(model):
    """``model`` on a pty, closed on leaving."""
    pty = SpecPty(model)
    try:
        yield pty
    finally:
        pty.close()


# -- the link rules of L8121.md, which hold for both dialects ---------------------------------------
def test_the_default_baud_rate_is_the_link_default_9600_in_both_dialects(dialect):
    """``L8121.md``, Link: "baud configurable (9600, 38400 or 115200; default 9600 ...)" and
    "These link rules hold for both dialects": a driver configured with the dialect alone must
    reach a controller left at its default rate."""
    model = SpecModel(dialect, min_gap_s=0)
    with served(model) as pty, L8121(pty.url, dialect=dialect, poll_s=0.05) as src:
        assert src.baudrate == 9600
        src.warm_up(timeout_s=10, progress=False)
        src.on(60, 250)
    assert model.lost == [] and not model.emitting


@pytest.mark.parametrize("gap_s", [0.045, 0.055])
def test_commands_are_spaced_for_a_controller_that_needs_50_ms(dialect, gap_s):
    """``L8121.md``, Link: "A controller may need ~50 ms between commands" (for both dialects): a
    controller that drops a command sent sooner must lose none of the driver's. "~50" is not
    "at most 50": a unit that needs 55 ms is within it, and a spacing of exactly 50 ms lost its
    commands (the second one already)."""
    model = SpecModel(dialect, min_gap_s=gap_s)
    with served(model) as pty, L8121(pty.url, dialect=dialect, baudrate=9600, poll_s=0.05) as src:
        src.warm_up(timeout_s=10, progress=False)
        src.on(60, 250)
        src.check()
    assert model.lost == [] and not model.emitting


def test_the_spacing_holds_across_a_new_link_to_the_same_controller(dialect):
    """The ~50 ms between commands is the controller's need, whichever link object sends them:
    ``dialect = "auto"`` probes the port over one link, closes it and connects over a new one (the
    guardian, or a run taking over from a dead guardian, likewise opens the port afresh). A new
    link's first command sent at once after the probe's last reply was lost (``TYP`` in A, ``SRL``
    in B), and the connect failed, blaming the baud rate or the dialect."""
    model = SpecModel(dialect, min_gap_s=0.045)
    with served(model) as pty, L8121(pty.url, dialect="auto", poll_s=0.05) as src:
        assert src.dialect.name == dialect
        src.warm_up(timeout_s=10, progress=False)
        src.on(60, 250)
        src.check()
    assert model.lost == [] and not model.emitting


@pytest.mark.parametrize("encoding", ["latin-1", "utf-8"])
def test_a_b_unit_that_writes_the_micro_sign_is_understood(encoding, tmp_path):
    """Dialect B's currents are ``250uA`` in ``L8121.md``'s table, ``µA`` in its prose, and the
    driver's parser takes both; but the link read replies as ASCII and the guardian passed them
    on as ASCII, so ``SPC 250µA`` reached the parser as ``250\ufffdA`` (or ``250?A``) and a unit
    writing the micro sign, in either 8-bit encoding, could not be used: the run stopped before
    the first exposure. Both, directly and through the guardian (``radiokit acquire``)."""
    from acquisition.protocols.compression_series import load_protocol, run

    model = SpecModel("B", warm=True)
    model.micro_sign = encoding
    with served(model) as pty:
        with L8121(pty.url, dialect="B", poll_s=0.05) as src:
            beam = src.on(60, 250)
            assert src.setpoint() == (60.0, 250.0)
        assert abs(beam["current_ua"] - 250) <= 5  # the driver's default tolerance, 5 µA
        series = _series(pty.url, "B", None)
        del series["source"]["focus"]  # (this model has no focus commands in B)
        p = load_protocol(series)
        p.output = str(tmp_path / "series.h5")
        result = run(p, sim=True, progress=False)
    assert result.frames_written == 3 and result.tube_off
    assert not model.emitting and model.lost == []


# -- a controller still in its power-on checks, a warm-up that runs on ------------------------------
# (acquisition.emulators.l8121 can do neither -- it starts checked and its B warm-up always ends in
# STANDBY -- so this spec model does)
def test_warm_up_and_on_wait_for_the_power_on_checks(dialect):
    """``L8121.md`` lists states a controller passes through by itself after power-on: A's ``STS 6``
    (self-test), B's ``STS ERROR`` (pre-heating). A session started meanwhile failed at its first
    ``STS`` ("warm-up not started: controller not ready (state SELF_TEST)"); the driver waits for
    them (``ready_timeout_s``) and sends no X-ray command before they end: this model refuses
    ``WUP`` and ``XON`` meanwhile, so one sent too soon fails the warm-up or the exposure."""
    model = SpecModel(dialect, checking_s=0.5)
    with served(model) as pty, L8121(pty.url, dialect=dialect, poll_s=0.05) as src:
        assert src.warm_up(timeout_s=10, progress=False) > 0
        src.on(60, 250)
    started = [c for c in model.received if c in ("WUP", "XON")]
    assert started == (["WUP", "XON"] if dialect == "A" else ["XON", "XON"])  # the warm-up, then the exposure
    assert not model.emitting and model.lost == []


def test_power_on_checks_that_do_not_end_are_one_clear_error(dialect):
    """Checks that outlast ``ready_timeout_s`` are an error of one line naming the state and the
    setting, before any setting or X-ray command is sent, for the warm-up and the exposure alike."""
    model = SpecModel(dialect, checking_s=60.0)
    # B's ERROR with both its readings: called PREHEATING alone, a refused STS read as pre-heating (review s38b)
    still = "SELF_TEST" if dialect == "A" else "ERROR (PREHEATING, or a refused query: dialect B does not say which)"
    with served(model) as pty, L8121(pty.url, dialect=dialect, poll_s=0.05, ready_timeout_s=0.3) as src:
        for action in (lambda: src.warm_up(timeout_s=10, progress=False), lambda: src.on(60, 250)):
            with pytest.raises(DeviceError) as err:
                action()
            assert str(err.value) == (
                f"{pty.url}: the controller's power-on checks did not finish within ready_timeout_s = 0.3 s "
                f"(still {still}); look at the controller (or raise [source] ready_timeout_s)"
            )
    # queries only (B asks SHV, SCU too: its ERROR does not show X-rays off, so a measured beam would be)
    assert [c for c in model.received if c not in ("STS", "SIN", "TYP", "SRL", "SHV", "SCU")] == []


def test_b_a_warm_up_that_runs_on_into_x_rays_on_is_switched_off_and_counts_as_done():
    """B's warm-up is ``AGING``, X-rays on; ``L8121.md`` does not say it returns to ``STANDBY``
    when it ends. One that runs on into ``XON`` left the driver calling it "an exposure instead of
    a warm-up": the warm-up failed although the controller had finished it. The driver switches
    that beam off (confirmed by ``STS``) and counts the warm-up done, as the controller's ``DAG``
    does; the exposure that follows goes ahead."""
    from acquisition.l8121 import SourceState, WarmupState

    model = SpecModel("B", warmup_s=0.3)
    model.warm_up_ends_on = True
    with served(model) as pty, L8121(pty.url, dialect="B", poll_s=0.05) as src:
        assert src.warm_up(timeout_s=10, progress=False) > 0
        assert not model.emitting  # switched off, before warm_up() returned
        after = model.received[model.received.index("XON") :]
        assert after[after.index("XOF") + 1] == "STS"  # ... and confirmed
        assert src.warmup_state() == WarmupState.DONE and src.status() == SourceState.STANDBY
        src.on(60, 250)
        assert model.emitting and model.state == "XON"
    assert not model.emitting


@pytest.mark.parametrize("case", ["A checking", "B checking", "B runs on"])
def test_a_series_warms_up_after_the_power_on_checks_and_through_a_warm_up_that_runs_on(case, tmp_path):
    """The same through ``run()`` and the guardian: the series asked whether a warm-up was needed
    while the controller was still checking itself, skipped it, and was refused at the first
    exposure ("warm-up needed"); and a B warm-up that ran on into X-rays on stopped the series."""
    from acquisition.protocols.compression_series import load_protocol, run

    dialect = case[0]
    # checks of 0.5 s from the first command outlast the connect and the question "warm-up needed?"
    model = SpecModel(dialect, checking_s=0.5 if "checking" in case else 0.0, warmup_s=0.2, ramp_s=0.05)
    model.warm_up_ends_on = case == "B runs on"
    with served(model) as pty:
        series = _series(pty.url, dialect, None)
        del series["source"]["focus"]
        series["series"].update(darks=0, flats=0)  # one exposure: the warm-up is what is tried here
        p = load_protocol(series)
        p.output = str(tmp_path / "series.h5")
        result = run(p, sim=True, progress=False)
    assert result.frames_written == 1 and result.tube_off
    assert ("WUP" if dialect == "A" else "XON") in model.received
    assert not model.emitting and model.lost == []


# -- X-rays on means the interlock is watched, the warm-up and the ramp included -------------------
def _open_interlock_once_emitting(model, after_s=0.2):
    """Open the interlock ``after_s`` after the model starts emitting; returns a dict whose
    ``"n"`` is then how many commands the model had received (under its lock: the opening and
    the count are one instant of the controller)."""
    opened = {}

    def watch():
        deadline = time.monotonic() + 10
        while not model.emitting and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(after_s)
        with model.lock:
            opened["n"] = len(model.received)
            model.interlock_closed = False

    threading.Thread(target=watch, daemon=True).start()
    return opened


@pytest.mark.parametrize("phase", ["warm-up", "ramp"])
def test_an_interlock_opening_while_emitting_stops_the_tube(dialect, phase):
    """``L8121.md``: "Warm-up emits X-rays: it is started only on purpose, with the same interlock
    ... rules as any exposure", and while X-rays are on the driver polls (B: ``STS``, ``SHV``,
    ``SCU``, ``SIN``) and stops on "an interlock opening". A controller that only reports the open
    interlock (the notes do not say it switches off by itself) must be switched off by the driver
    within a few polls, not when the warm-up ends or the beam is stable."""
    # The warm-up and the ramp take 20 s, and the driver is given longer to wait for them (its
    # warm-up and stability time-outs 60 s): a driver that waited either out would be seen after
    # 20 s. A bound of 2 s on a 3 s ramp measured the machine's load (2.19 s at load 15).
    model = SpecModel(dialect, warm=phase == "ramp", warmup_s=20.0, ramp_s=20.0)
    model.interlock_stops_beam = False
    with served(model) as pty, L8121(pty.url, dialect=dialect, poll_s=0.05, stable_timeout_s=60) as src:
        opened = _open_interlock_once_emitting(model)
        t0 = time.monotonic()
        with pytest.raises(SourceFault, match="interlock open"):
            if phase == "warm-up":
                src.warm_up(timeout_s=60, progress=False)
            else:
                src.on(60, 250)
        assert time.monotonic() - t0 < 10.0  # half the 20 s it would take to wait out either
        assert not model.emitting
    # "within a few polls", counted in the controller's own commands rather than in seconds: from
    # the opening to the XOF only the rest of the polling round in flight (no query twice), and
    # the first SIN to read the interlock open is the last command before the XOF
    after = model.received[opened["n"] :]
    assert "XOF" in after, after
    before = after[: after.index("XOF")]
    polled = {"A": {"STS", "SWE", "SAR", "SIN"}, "B": {"STS", "DAG", "SHV", "SCU", "SIN"}}[dialect]
    assert set(before) <= polled and len(set(before)) == len(before), before
    assert before[-1:] == ["SIN"], before


# -- no X-ray command before every setting is valid ------------------------------------------------
@pytest.mark.parametrize("timeout_s", [0, -5, float("nan"), float("inf")])
def test_an_invalid_warm_up_time_out_is_refused_before_the_warm_up_starts(dialect, timeout_s):
    """``L8121.md``: "Time-outs are explicit and short", and the warm-up emits X-rays, so it may
    only start once its settings are valid: a time-out that is not a positive finite number of
    seconds (one that ends the warm-up at once, or never) is refused before ``WUP`` (A) or the
    warm-up's ``XON`` (B) is sent."""
    model = SpecModel(dialect)
    with served(model) as pty, L8121(pty.url, dialect=dialect, poll_s=0.05) as src:
        with pytest.raises(ValueError, match="timeout_s"):
            src.warm_up(timeout_s=timeout_s, progress=False)
    assert not {"WUP", "XON"} & set(model.received)


@pytest.mark.parametrize("key", ["warmup_timeout_s", "stable_timeout_s", "ready_timeout_s"])
def test_a_zero_time_out_is_not_a_configuration(key):
    """A warm-up or an exposure that may not last at all would switch the tube on only to switch it
    off again: refused with the other time-outs that must be > 0."""
    with pytest.raises(ValueError, match=key):
        SourceConfig(**{key: 0})


# -- the bench-top commands: a signal switches the tube off too ------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT, signal.SIGQUIT])
def test_a_signal_during_source_warm_up_switches_the_tube_off(dialect, sig):
    """``L8121.md``: X-rays are switched off "on every exit path" and "an interrupted warm-up is
    switched off like an exposure". ``radiokit acquire source warm-up`` killed (SIGTERM), hung up
    on (SIGHUP) or interrupted (Ctrl-C, Ctrl-\\) while the warm-up runs must leave the tube off, confirmed,
    and say so in one line, without a traceback."""
    model = SpecModel(dialect, warmup_s=60.0)
    code = "import sys; from radiokit.cli import script; sys.exit(script())"
    with served(model) as pty:
        argv = ["acquire", "source", "warm-up", "--port", pty.url, "--dialect", dialect, "-q"]
        proc = subprocess.Popen(
            [sys.executable, "-c", code, *argv], stderr=subprocess.PIPE, text=True, start_new_session=True
        )
        try:
            deadline = time.monotonic() + 30
            while not model.emitting and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            assert model.emitting, f"the warm-up never started: {proc.poll()}"
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert not model.emitting, f"left warming up after {sig.name}: {model.received[-4:]}"
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith(f"stopped by {sig.name}; tube off (confirmed by STS"), err


# -- a protocol's focus is a setting too -------------------------------------------------------------
def _series(port, dialect, focus):
    from sim.scene import block_scene

    scene = block_scene(size_mm=10.0, ratios=(0.15,))
    scene.detector.binning = 4
    scene.mesh.size_far_mm = 8.0
    return {
        "output": "unused.h5",
        "name": "focus",
        # timeout_s 3: the model answers from this process, which also solves the scene meanwhile
        "source": {"voltage_kv": 60, "current_ua": 250, "dialect": dialect, "focus": focus, "timeout_s": 3.0},
        "detector": {"kind": "sim", "timeout_s": 2.0},
        "frame": {"kind": "sim", "initial_height_mm": 10.0},
        "series": {"darks": 1, "flats": 1, "frames_per_step": 1, "steps": [0.15], "settle_s": 0.0},
        "sim": {"scene": scene.to_toml(), "frame_period_s": 0.1, "source_port": port},
    }


def test_a_focus_dialect_b_lacks_is_refused_when_the_protocol_is_loaded():
    """Dialect B has three focus commands (``CFS``/``CFM``/``CFL``: 0, 1, 2); ``focus = 3`` is a
    setting it cannot take, refused with the protocol's other settings, before anything is sent."""
    from acquisition.protocols.compression_series import ProtocolError, load_protocol

    with pytest.raises(ProtocolError, match="focus = 3"):
        load_protocol(_series("/dev/null", "B", 3))
    assert load_protocol(_series("/dev/null", "A", 3)).source.focus == 3


def test_a_focus_the_probed_dialect_lacks_is_refused_before_the_warm_up(tmp_path):
    """``dialect = "auto"``: the dialect is known only at connect, so the focus is checked then --
    before the warm-up, which emits X-rays (B starts it with ``XON``), not after it."""
    from acquisition.protocols.compression_series import load_protocol, run

    model = SpecModel("B")  # warm-up needed
    with served(model) as pty:
        p = load_protocol(_series(pty.url, "auto", 3))
        p.output = str(tmp_path / "series.h5")
        with pytest.raises(ValueError, match="focus"):
            run(p, sim=True, progress=False)
    assert "XON" not in model.received, model.received


def test_a_series_sets_and_reads_back_its_focus_before_the_warm_up_emits(dialect, tmp_path):
    """The series set its focus only after the warm-up, which emits (B's is an XON): the warm-up
    ran at whatever focal spot the unit had. The focus is now a setting like kV and µA: set and
    read back before the warm-up's start command, and again before every XON."""
    from acquisition.protocols.compression_series import load_protocol, run

    # warm-up needed, just switched on: its checks run for 1 s, and it takes no focus meanwhile
    model = SpecModel(dialect, checking_s=1.0)
    model.focus_waits_for_checks = True
    with served(model) as pty:
        p = load_protocol(_series(pty.url, dialect, 1))
        p.output = str(tmp_path / "series.h5")
        run(p, sim=True, progress=False)
    got = model.received
    focus, read, start = {"A": ("CFS 1", "SFC", "WUP"), "B": ("CFM", "SFS", "XON")}[dialect]
    assert focus in got and start in got, got
    assert got.index(focus) < got.index(read, got.index(focus)) < got.index(start), got
    assert not model.emitting


@pytest.mark.parametrize("nth_xof", [4, 7])
def test_a_signal_during_a_failing_switch_off_never_reports_the_tube_off(dialect, nth_xof):
    """The interlock opens during ``source warm-up`` and the tube does not switch off (XOF answered,
    STS still warming up): whenever SIGTERM comes -- during the failing switch-off after the fault
    (the 4th XOF) or during the one on the way out (the 7th) -- the last line must say to switch
    off at the controller, never that the tube is off or that no X-ray command was sent."""
    model = SpecModel(dialect, warmup_s=60.0)
    model.interlock_stops_beam = False
    code = "import sys; from radiokit.cli import script; sys.exit(script())"
    with served(model) as pty:
        argv = ["acquire", "source", "warm-up", "--port", pty.url, "--dialect", dialect, "-q"]
        proc = subprocess.Popen([sys.executable, "-c", code, *argv], stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while not model.emitting and time.monotonic() < deadline:
                time.sleep(0.02)
            model.relay_stuck, model.interlock_closed = True, False
            while model.received.count("XOF") < nth_xof and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.002)
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert model.emitting and proc.returncode != 0
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and "switch the source off at the controller" in err, err
    assert last == TUBE_WARNING, err  # the last line, as a series ends (and exit code 3)
    assert proc.returncode == 3, err


# -- a silent controller is told once ----------------------------------------------------------------
def _silence_after_xon(model, deadline_s=30.0):
    end = time.monotonic() + deadline_s
    while "XON" not in model.received and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.1)
    model.silent = True


def _on_silenced_after_xon(model, pty, dialect, timeout_s):
    """An ``on()`` whose controller falls silent once the ``XON`` is in, while the beam ramps (a
    fixed 0.5 s fell before B's nine commands to XON on a loaded machine: no XON, rightly no XOF);
    it must fail with "no reply". The driver, for the caller to go on with."""
    src = L8121(pty.url, dialect=dialect, poll_s=0.05, timeout_s=timeout_s)
    threading.Thread(target=_silence_after_xon, args=(model,), daemon=True).start()
    with pytest.raises(DeviceError, match="no reply"):
        src.on(60, 250)
    return src


def test_a_silent_controller_gets_one_switch_off_before_the_error(dialect):
    """The controller falls silent while the beam ramps: one switch-off (``XOF``, ``STS``, both
    unanswered) and the error -- not a second round on the way out of ``on()``, which cannot
    reach a silent controller and only delays the operator's message by two more time-outs
    (``L8121.md``: "Time-outs are explicit and short; a silent controller is an error")."""
    model = SpecModel(dialect, warm=True, ramp_s=5.0)
    with served(model) as pty:
        src = _on_silenced_after_xon(model, pty, dialect, timeout_s=0.5)
        n_xof = model.received.count("XOF")
        src.detach()
    assert n_xof == 1, model.received[-8:]
    assert src.off_failed is not None and "does not answer" in str(src.off_failed)


def test_close_after_a_failed_switch_off_tries_once_more(dialect):
    """What the README says of ``L8121.close()`` (the end of a ``with`` block, the bench-top source
    commands): after a switch-off that met a silent controller it sends ``XOF`` and ``STS`` once
    more -- one attempt, not ``off_attempts`` -- and then raises the error that says to switch off
    at the controller; ``detach()`` is the way out without that round."""
    model = SpecModel(dialect, warm=True, ramp_s=5.0)
    with served(model) as pty:
        src = _on_silenced_after_xon(model, pty, dialect, timeout_s=0.3)
        assert model.received.count("XOF") == 1
        with pytest.raises(DeviceError, match="switch the source off at the controller"):
            src.close()
    after = model.received[model.received.index("XOF") + 1 :]
    assert after[after.index("XOF") :] == ["XOF", "STS"]  # one more round, and only one
    assert not src.is_connected


def test_a_source_command_whose_switch_off_is_not_confirmed_ends_as_a_series_does(dialect, capsys, monkeypatch):
    """README: ``radiokit acquire`` exits 3 "when the tube may still be on", its last line the
    warning. ``source off`` against a tube that stays on (``XOF`` answered, ``STS`` still on)
    ended as a plain error, exit code 1, its last line the driver's message."""
    import functools

    import acquisition.l8121
    from radiokit.cli import main

    model = SpecModel(dialect, warm=True)
    model.state, model.t_on = "XON", time.monotonic()  # left on (other software, a crash)
    model.relay_stuck = True
    # the real driver, giving up sooner than its 3 s per switch-off (off_confirm_s)
    monkeypatch.setattr(acquisition.l8121, "L8121", functools.partial(L8121, off_confirm_s=0.3, poll_s=0.05))
    with served(model) as pty:
        code = main(["acquire", "source", "off", "--port", pty.url, "--dialect", dialect, "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert (code, err[-1]) == (3, TUBE_WARNING), err
    assert "could not confirm X-rays off" in err[-2] and model.emitting
