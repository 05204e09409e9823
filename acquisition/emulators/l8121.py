"""An emulated Hamamatsu L8121 controller, answering either dialect of ``L8121.md`` on a
pseudo-terminal, a TCP socket or in process.

:class:`L8121Model` is one controller -- its states, the warm-up sequence, tube voltage and
current that ramp towards the set values after ``XON``, the interlock, overload and error codes --
behind one of two front ends, ``dialect="A"`` (numeric ``STS n``, ``SAR``, ``WUP``, ``TYP``; refused
commands ``ERR``/``ERROR``) or ``dialect="B"`` (``STS`` words, ``INTER LOCK ON``, values with units,
``PHV``/``PCU`` presets while off and ``HIV``/``CUR`` while on, warm-up started by ``XON`` while
``DAG`` says ``YET`` and reported as ``AGING``, ``SRL``/``SRB``, no ``TYP`` or ``WUP``; every refusal
``ERROR``). It runs on an injectable clock and records every line it receives.

Faults, injected from any thread, now or at a given model time, in both dialects:
:meth:`~L8121Model.open_interlock`, :meth:`~L8121Model.overload`, :meth:`~L8121Model.drop_beam`,
:meth:`~L8121Model.stuck_on`, :meth:`~L8121Model.silence`, :meth:`~L8121Model.garbage`
(:meth:`~L8121Model.garble_once`: one reply),
:meth:`~L8121Model.sts_error` (``STS`` answered ``ERROR``: B's pre-heating word, A's refusal),
:meth:`~L8121Model.slow`, :meth:`~L8121Model.delay_once` (one reply after the client's time-out), :meth:`~L8121Model.hold_once` (one reply held until the client's next line),
:meth:`~L8121Model.require_warm_up` (the controller decides a warm-up is
due, as B's 8-hour idle rule does) and :meth:`~L8121Model.warm` (the reverse),
:meth:`~L8121Model.inject_after` (any of these right after a given command),
:meth:`PtyServer.line_noise` (bytes on the line that no command answered),
:meth:`~L8121Model.controller_error` (``SER`` reports a control-board fault that nothing sent clears),
:meth:`~L8121Model.set_operate_switch` (``LOCAL``: remote
control commands refused with ``ERROR``, A's always accepted ``XOF`` excepted; B reports it with
``SRL``) and
:meth:`~L8121Model.foreign` (answers like some other instrument: speaks neither dialect).

The baud rate. A pseudo-terminal moves bytes at any speed, so a wrong baud rate would go unnoticed.
The model is configured with the controller's ``baudrate`` (default: 9600 in both
dialects, the link default of ``L8121.md``) and :class:`PtyServer` reads the rate the client set on the terminal (``termios``): when they
differ, the line is taken as what a UART would make of it -- not understood, not executed -- and
the reply as what the client's UART would make of the controller's ``ERROR``: a few bytes of junk
with no line end. This is a model of a baud mismatch, not a measurement of one.

:class:`PtyServer` serves a model on a pseudo-terminal whose slave path pyserial opens like a
serial port; :class:`SocketServer` on ``socket://127.0.0.1:PORT`` (no baud rate there). From a
shell::

    python -m acquisition.emulators.l8121 --pty --dialect B --warmup-s 2   # prints /dev/pts/N

Error codes (``SER``) follow ``L8121.md``: dialect B's ``SER n`` is the control-board error, 0
none, 1-4 relay or internal faults; dialect A's is the "controller error code, 0 none", its other
codes given no meaning. ``SER`` reads 0 unless such a fault is injected
(:meth:`~L8121Model.controller_error`: in B one of 1-4, in A any code). Where ``L8121.md`` is
silent, the emulator does nothing of its own: it ties no command, refusal, interlock or overload
to ``SER`` (a refused command answers ``ERR``/``ERROR`` and leaves ``SER`` as it was), and nothing
sent clears a fault -- not ``RST``, not a setting -- only ``controller_error(0)``. (Before session
52 it used 1-4 for interlock, warm-up, overload and range and added 5-7 of its own, and its
docstring called the real codes undocumented.)

Examples
--------
>>> m = L8121Model(warmup_s=0, ramp_s=0)
>>> m.handle("TYP"), m.handle("XON"), m.handle("SER")
('TYP L8121-01', 'ERROR', 'SER 0')
>>> m.handle("WUP"), m.handle("STS"), m.handle("HIV 60"), m.handle("CUR 250"), m.handle("XON")
('WUP', 'STS 2', 'HIV 60', 'CUR 250', 'XON')
>>> m.handle("SAR"), m.xray_on
('SAR 3 60 250 0 0 0 0', True)
>>> b = L8121Model(dialect="B", warmup_s=0, ramp_s=0)
>>> b.handle("STS"), b.handle("DAG"), b.handle("XON"), b.handle("STS"), b.handle("DAG")
('STANDBY', 'AGING 1 0 YET', 'XON', 'STANDBY', 'AGING 0 0 END')
>>> b.handle("PHV 600"), b.handle("PCU 250"), b.handle("XON"), b.handle("SHV"), b.handle("SIN")
('PHV 600', 'PCU 250', 'XON', 'SHV 60.0kV', 'INTER LOCK ON')
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import os
import random
import select
import socket
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

from acquisition.l8121 import SourceState, WarmupState

__all__ = ["L8121Model", "PtyServer", "SocketServer", "Exchange", "main", "DEFAULT_BAUD"]

logger = logging.getLogger(__name__)


#: Dialect B's ``SER`` codes other than 0 (L8121.md: "1-4 relay or internal faults").
B_FAULT_CODES = (1, 2, 3, 4)


DEFAULT_BAUD = {"A": 9600, "B": 9600}
_B_STATES = {
    SourceState.WARMUP_NEEDED: "STANDBY",
    SourceState.WARMING_UP: "AGING",
    SourceState.STANDBY: "STANDBY",
    SourceState.XRAY_ON: "XON",
    SourceState.OVERLOAD: "OVER",
    SourceState.NOT_READY: "NOT READY",
    SourceState.SELF_TEST: "NOT READY",
}
_B_FOCUS = ("SMALL", "MIDDLE", "LARGE")
# What a remote operate switch other than REMOTE refuses: everything that acts on the tube.
_CONTROL = {"HIV", "CUR", "PHV", "PCU", "XON", "XOF", "WUP", "RST", "CFS", "CFM", "CFL"}
_SETTINGS = {"HIV", "CUR", "PHV", "PCU", "CFS", "CFM", "CFL"}
_AGING_STEPS = 4
_JUNK = "#%&*?!~^@$+=<>0123456789abcdefxyz"


@dataclass(frozen=True)
class Exchange:
    """One line the model received: model time (s), the line, its reply (None: none sent), and
    whether it was understood (False: it arrived at the wrong baud rate)."""

    t: float
    command: str
    reply: str | None
    understood: bool = True


class L8121Model:
    """The controller's behaviour, independent of any link.

    Parameters
    ----------
    dialect : {"A", "B"}
        The command dialect it speaks (``L8121.md``).
    model : str
        What dialect A's ``TYP`` answers.
    warmup_s : float
        Duration of the warm-up sequence (A: started by ``WUP``; B: by ``XON`` while a warm-up is
        due).
    ramp_s : float
        Time for the measured voltage and current to ramp (linearly) from where they are to the set
        values, after ``XON`` or a change of setting while on.
    clock : callable
        Seconds, monotonic; model time is ``clock()`` minus its value at construction.
    kv_min, kv_max, ua_max, watts_max : float
        The ranges the voltage and current settings accept (refused otherwise), and the power limit
        a pair of settings may not exceed.
    warmed_up : bool
        Start in standby (warm-up done) instead of "warm-up needed".
    baudrate : int, optional
        The controller's baud rate (default: the dialect's); see the module docstring.
    voltage_scale : float, optional
        kV per unit of a voltage argument is ``1 / voltage_scale`` (default A 1, B 10:
        ``PHV 600`` is 60 kV).
    seed : int
        Seed of the junk :meth:`garbage` and a baud mismatch reply with.

    Notes
    -----
    Measured values are reported as whole kV and µA in A, with one decimal and units in B. While
    X-rays are off they are 0. ``XOF`` also stops a running warm-up (it emits X-rays): the warm-up
    is then needed again.
    """

    def __init__(
        self,
        *,
        dialect: str = "A",
        model: str = "L8121-01",
        warmup_s: float = 3.0,
        ramp_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        kv_min: float = 40,
        kv_max: float = 150,
        ua_max: float = 500,
        watts_max: float = 75,
        warmed_up: bool = False,
        baudrate: int | None = None,
        voltage_scale: float | None = None,
        seed: int = 0,
    ):
        dialect = str(dialect).upper()
        if dialect not in DEFAULT_BAUD:
            raise ValueError(f"L8121 emulator: dialect {dialect!r}: expected 'A' or 'B'")
        self.dialect = dialect
        self.model = model
        self.warmup_s = float(warmup_s)
        self._ramp_s = float(ramp_s)
        self.kv_min, self.kv_max, self.ua_max, self.watts_max = kv_min, kv_max, ua_max, watts_max
        self.baudrate = int(baudrate or DEFAULT_BAUD[dialect])
        self.voltage_scale = float(voltage_scale or (10 if dialect == "B" else 1))
        self._clock = clock
        self._t0 = clock()
        self._lock = threading.RLock()
        self._events: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = itertools.count()
        self._rng = random.Random(seed)
        self._state = SourceState.STANDBY if warmed_up else SourceState.WARMUP_NEEDED
        self._warmup = WarmupState.DONE if warmed_up else WarmupState.NOT_STARTED
        self._warmup_t0 = 0.0
        self._set_kv, self._set_ua = int(kv_min), 0
        self._ramp_t0, self._ramp_from = 0.0, (0.0, 0.0)
        # how a change while on ramps (ramp_after_change): "here" from where the tube is, or "zero"
        # down to nothing over a fall time, then up from zero; _falling: (start, from, fall_s) of a fall
        self._change_start, self._change_fall_s = "here", 0.0
        self._falling: tuple[float, tuple[float, float], float] | None = None
        self._meter_noise, self._meter_sign = 0.0, 1.0  # the current meter's noise (meter_jitter)
        self._beam_dropped = False
        self._runaway = (1.0, 1.0)  # measured kV, µA factors of a runaway beam (runaway())
        self._interlock_open = False
        self._focus = 0
        self._fault = 0  # the control-board fault SER reports (controller_error); 0 none
        self._switch = "REMOTE"
        self._silent = self._garbage = self._stuck = self._foreign = self._sts_error = False
        self._lower_case = False
        self._silent_executes = False
        self._standby_when_due = False  # A's STS reads 2 while a warm-up is due (standby_when_warm_up_due)
        self._swe_lag_s = 0.0  # A's SWE still reads 1 this long after the warm-up ended (swe_lags)
        self._start_lag_s = 0.0  # A's warm-up begins this long after WUP is answered (warm_up_starts_late)
        self._delay_s = 0.0
        self._delay_once: tuple[float, str | None] | None = None
        self._hold_once: tuple[str | None] | None = None  # (command or None for any), once
        self._garble_once: tuple[str | None] | None = None  # (command or None for any), once
        self._off_delay_s, self._ramping_down = 0.0, False
        self._log: list[Exchange] = []
        self._after: dict[str, Callable[[], object]] = {}
        self._after_refused: set[str] = set()  # commands whose _after fault fires on a refusal too
        self._commands, self._takes_argument = self._front_end_a() if dialect == "A" else self._front_end_b()

    # -- the two front ends -----------------------------------------------------------------------
    def _front_end_a(self):
        commands = {
            "HIV": self._hiv,
            "CUR": self._cur,
            "XON": self._xon_a,
            "XOF": self._xof,
            "WUP": self._wup,
            "RST": self._rst,
            "CFS": self._cfs,
            "STS": lambda t: f"STS {self._state_a():d}",
            "SAR": lambda t: "SAR {:d} {:.0f} {:.0f} 0 0 0 0".format(self._state_a(), *self._meter(t)),
            "SVI": lambda t: f"SVI {self._set_kv} {self._set_ua}",
            "SHV": lambda t: f"SHV {self._measured(t)[0]:.0f}",
            "SCU": lambda t: f"SCU {self._meter(t)[1]:.0f}",
            "SIN": lambda t: f"SIN {int(self._interlock_open)}",
            "SWE": lambda t: f"SWE {self._warmup:d}",
            "SPH": lambda t: f"SPH {int(self._state == SourceState.WARMING_UP)}",
            "SFC": lambda t: f"SFC {self._focus}",
            "SER": lambda t: f"SER {self._fault:d}",
            "TYP": lambda t: f"TYP {self.model}",
        }
        return commands, {"HIV", "CUR", "CFS"}

    def _front_end_b(self):
        def on_only(fn):  # HIV, CUR: while X-rays are on
            return lambda t, arg: fn(t, arg) if self._state == SourceState.XRAY_ON else self._refuse()

        def off_only(fn):  # the presets PHV, PCU: while the tube does not emit
            return lambda t, arg: fn(t, arg) if not self._state.emitting else self._refuse()

        commands = {
            "HIV": on_only(self._hiv),
            "CUR": on_only(self._cur),
            "PHV": off_only(lambda t, arg: self._hiv(t, arg, "PHV")),
            "PCU": off_only(lambda t, arg: self._cur(t, arg, "PCU")),
            "XON": self._xon_b,
            "XOF": self._xof,
            "RST": self._rst,
            "CFS": lambda t: self._cf(0, "CFS"),
            "CFM": lambda t: self._cf(1, "CFM"),
            "CFL": lambda t: self._cf(2, "CFL"),
            "STS": lambda t: _B_STATES[self._state],
            "SHV": lambda t: f"SHV {self._measured(t)[0]:.1f}kV",
            "SCU": lambda t: f"SCU {self._meter(t)[1]:.0f}uA",
            "SPV": lambda t: f"SPV {self._set_kv:.1f}kV",
            "SPC": lambda t: f"SPC {self._set_ua}uA",
            "SIN": lambda t: "INTER LOCK OFF" if self._interlock_open else "INTER LOCK ON",
            "DAG": self._dag,
            "SFS": lambda t: _B_FOCUS[self._focus],
            "SER": lambda t: f"SER {self._fault:d}",
            "SRL": lambda t: self._switch,
            "SRB": lambda t: "BUSY" if self._state == SourceState.WARMING_UP else "READY",
        }
        return commands, {"HIV", "CUR", "PHV", "PCU"}

    @property
    def ramp_s(self) -> float:
        """The ramp's duration, s (see the class's ``ramp_s``)."""
        return self._ramp_s

    @ramp_s.setter
    def ramp_s(self, value: float) -> None:
        # A new duration applies from now, from where the tube is: set while on, it rescaled the
        # ramp under way or done (a beam stable at 60 kV read 25 kV once 0.2 s became 0.6 s, and
        # a test of a ramp between two settings saw one from a quarter of the first; s52)
        with self._lock:
            if self._state == SourceState.XRAY_ON:
                self._advance()
                self._ramp_from, self._ramp_t0 = self._measured(self.time), self.time
                self._falling = None  # (a fall under way ends where it is: the new ramp starts there)
            self._ramp_s = float(value)

    # -- read-only state for tests ----------------------------------------------------------------
    @property
    def time(self) -> float:
        """Model time, seconds since construction."""
        return self._clock() - self._t0

    @property
    def state(self) -> SourceState:
        """The state now, as dialect A's ``STS`` numbers it (0 warm-up needed ... 6 self-test)."""
        with self._lock:
            self._advance()
            return self._state

    @property
    def xray_on(self) -> bool:
        """Whether the tube emits now: X-rays on (state 3) or warming up (state 1; B's ``AGING``)."""
        return self.state.emitting

    @property
    def set_kv(self) -> int:
        """The set tube voltage, kV."""
        return self._set_kv

    @property
    def set_ua(self) -> int:
        """The set tube current, µA."""
        return self._set_ua

    def measured(self) -> tuple[float, float]:
        """The measured (kV, µA) now, unrounded."""
        with self._lock:
            self._advance()
            return self._measured(self.time)

    @property
    def log(self) -> list[Exchange]:
        """Every line received so far, with model time and reply (a copy)."""
        with self._lock:
            return list(self._log)

    @property
    def commands(self) -> list[str]:
        """The lines received so far, in order (understood or not)."""
        return [e.command for e in self.log]

    @property
    def reply_delay_s(self) -> float:
        """How long a server waits before sending each reply (see :meth:`slow`)."""
        return self._delay_s

    # -- fault injection --------------------------------------------------------------------------
    def open_interlock(self, at_s: float | None = None) -> None:
        """Open the interlock chain now, or at model time ``at_s``.

        With X-rays on, the controller drops the beam: standby, interlock open, ``SER`` as it was
        (L8121.md ties no code to it). A running warm-up stops (warm-up needed again).
        """

        def fault(t):
            self._interlock_open = True
            if self._state == SourceState.XRAY_ON:
                self._state = SourceState.STANDBY
            elif self._state == SourceState.WARMING_UP:
                self._state, self._warmup = SourceState.WARMUP_NEEDED, WarmupState.NOT_STARTED

        self._at(at_s, fault)

    def close_interlock(self, at_s: float | None = None) -> None:
        """Close the interlock chain now, or at model time ``at_s``."""

        def fix(t):
            self._interlock_open = False

        self._at(at_s, fix)

    def overload(self, at_s: float | None = None) -> None:
        """Trip the overload protection now, or at model time ``at_s``: state 4 (B ``OVER``), beam
        off, ``SER`` as it was (L8121.md ties no code to it). Only ``RST`` leaves the overload state."""

        def fault(t):
            self._state = SourceState.OVERLOAD

        self._at(at_s, fault)

    def controller_error(self, code: int = 1, at_s: float | None = None) -> None:
        """Let ``SER`` report the controller error ``code`` from now, or from model time ``at_s``;
        0 ends it. ``L8121.md`` gives B's codes 1-4 as relay or internal faults of the control
        board, A's none; it relates them to no state and names no way to clear one. So the state
        stays as it was, ``XON`` (and ``WUP``) are not refused for it, and nothing sent clears it
        -- not ``RST`` ("reset after overload"), not a setting: only ``controller_error(0)``, a
        service at the unit."""
        if int(code) < 0:
            raise ValueError(f"controller error code {code}: expected 0 (none) or more")
        if self.dialect == "B" and int(code) not in (0, *B_FAULT_CODES):
            raise ValueError(
                f"controller error code {code}: L8121.md gives dialect B's SER 0 (none) and 1-4 (relay or "
                "internal faults) only"
            )

        def fault(t):
            self._fault = int(code)

        self._at(at_s, fault)

    def drop_beam(self, at_s: float | None = None) -> None:
        """Let the emitter fail now, or at model time ``at_s``: the measured current collapses to
        0 while the state stays X-rays on (until ``XOF``)."""

        def fault(t):
            if self._state == SourceState.XRAY_ON:
                self._beam_dropped = True

        self._at(at_s, fault)

    def runaway(self, kv_factor: float = 1.0, ua_factor: float = 1.0, at_s: float | None = None) -> None:
        """Let the measured beam run away now, or at model time ``at_s``: kV and µA read
        ``kv_factor`` and ``ua_factor`` times the setting while the state stays X-rays on and no
        overload trips (an emission regulator gone wrong; L8121.md names only the overload state)."""

        def fault(t):
            self._runaway = (float(kv_factor), float(ua_factor))

        self._at(at_s, fault)

    def require_warm_up(self, at_s: float | None = None) -> None:
        """Decide that a warm-up is due (B: the 8-hour idle rule, ``DAG`` says ``YET``): from
        standby the state becomes warm-up needed, so B's next ``XON`` starts a warm-up."""

        def fault(t):
            self._warmup = WarmupState.NOT_STARTED
            if self._state == SourceState.STANDBY:
                self._state = SourceState.WARMUP_NEEDED

        self._at(at_s, fault)

    def warm(self, at_s: float | None = None) -> None:
        """Mark the warm-up done now, or at model time ``at_s`` (someone ran it at the controller):
        from warm-up needed the state becomes standby, so B's next ``XON`` is an exposure."""

        def fix(t):
            self._warmup = WarmupState.DONE
            if self._state == SourceState.WARMUP_NEEDED:
                self._state = SourceState.STANDBY

        self._at(at_s, fix)

    def inject_after(self, command: str, fault: Callable[[], object], *, refused: bool = False) -> None:
        """Call ``fault()`` once, right after the controller next executes ``command`` (a command
        word such as ``"PCU"``): a state change that lands between two of the driver's commands.
        ``refused``: after it next answers ``command`` at all, a refusal (``ERROR``) included --
        a read error while a refusal is on its way."""
        with self._lock:
            self._after[command] = fault
            self._after_refused.discard(command)
            if refused:
                self._after_refused.add(command)

    def standby_when_warm_up_due(self, on: bool = True) -> None:
        """Let dialect A's ``STS`` (and ``SAR``) read 2, standby, while a warm-up is due, with ``SWE``
        saying it is not done: what B's ``STS`` always does (``STANDBY`` beside ``DAG``'s ``YET``).
        ``L8121.md`` lists both A queries without relating them, and says a real unit may speak a
        mix of the dialects. The controller itself still refuses ``XON`` until the warm-up is done."""
        with self._lock:
            self._standby_when_due = bool(on)

    def swe_lags(self, seconds: float) -> None:
        """Let dialect A's ``SWE`` read 1 (running) for ``seconds`` of model time after a warm-up
        ends, while ``STS`` already reads 2: two queries a real unit need not update together
        (``L8121.md`` does not relate them)."""
        with self._lock:
            self._swe_lag_s = float(seconds)

    def warm_up_starts_late(self, seconds: float) -> None:
        """Let dialect A's warm-up begin ``seconds`` of model time after ``WUP`` is answered (``inf``:
        never), the state meanwhile unchanged; an ``XOF`` in between does not cancel it (it stops a
        warm-up running, as :meth:`_xof` does). ``L8121.md`` ties no state to ``WUP``'s echo, and
        says nothing of what ``XOF`` does to a start not yet begun."""
        with self._lock:
            self._start_lag_s = float(seconds)

    def _state_a(self) -> SourceState:
        """The state dialect A's ``STS`` and ``SAR`` report."""
        if self._standby_when_due and self._state == SourceState.WARMUP_NEEDED:
            return SourceState.STANDBY
        return self._state

    def set_operate_switch(self, position: str = "LOCAL") -> None:
        """Turn the operate switch (``REMOTE``, ``LOCAL`` or ``OFF``). Other than ``REMOTE``, every
        command that acts on the tube is refused with ``ERROR`` -- in B ``XOF`` included (its notes
        say remote control needs ``REMOTE``, and name no exception), in A not (``L8121.md``: ``XOF``
        is "always accepted"); queries are answered. Dialect B reports the position with ``SRL``."""
        if position not in ("REMOTE", "LOCAL", "OFF"):
            raise ValueError(f"operate switch {position!r}: expected REMOTE, LOCAL or OFF")
        with self._lock:
            self._switch = position

    def left_on(self, kv: int = 60, ua: int = 250) -> None:
        """X-rays on at ``kv`` kV and ``ua`` µA, the ramp done: a unit as other software, a crash or
        a power cut mid-exposure leaves it for the next command to find. Sent as a session would
        (the settings, then ``XON``; logged like any exchange); a refusal raises.

        Examples
        --------
        >>> m = L8121Model(warmed_up=True)
        >>> m.left_on(60, 250); m.handle("SAR")
        'SAR 3 60 250 0 0 0 0'
        """
        settings = ("HIV", "CUR") if self.dialect == "A" else ("PHV", "PCU")
        lines = (f"{settings[0]} {round(kv * self.voltage_scale)}", f"{settings[1]} {ua}", "XON")
        for line in lines:
            if self.handle(line) in (None, "ERR", "ERROR"):
                raise RuntimeError(f"L8121 emulator: {line!r} refused ({self!r}): not left on")
        with self._lock:
            self._ramp_t0 -= self.ramp_s

    def ramp_after_change(self, start: str = "here", fall_s: float = 0.0) -> None:
        """How the measured values ramp after a setting changed while X-rays are on. L8121.md: they
        "ramp towards the set values over a few seconds after XON or a change", not from where.
        ``"here"`` (the default): from where the tube is, straight to the new setting. ``"zero"``:
        down to nothing over ``fall_s`` (a supply discharging; 0: at once), then up from zero to the
        new setting over :attr:`ramp_s`, as after ``XON`` (the reading of
        ``tests/l8121_second_reading.py``). A change during a fall falls again from where it is."""
        if start not in ("here", "zero"):
            raise ValueError(f"start {start!r}: expected 'here' or 'zero'")
        if not 0 <= fall_s < math.inf:
            raise ValueError(f"fall_s must be >= 0 and finite, got {fall_s}")
        with self._lock:
            self._change_start, self._change_fall_s = start, float(fall_s)

    def meter_jitter(self, fraction: float) -> None:
        """Let the current meter read ``fraction`` of the tube's current above it and below it by
        turns, one reply that reports the current after another (A's ``SAR`` and ``SCU``, B's
        ``SCU``): a meter whose noise grows with the value it reads, in a fixed order (no timing
        in a test). 0 restores. :meth:`measured` stays the tube's own value."""
        if not 0 <= fraction < 1:
            raise ValueError(f"fraction must be >= 0 and < 1, got {fraction}")
        with self._lock:
            self._meter_noise = float(fraction)

    def stuck_on(self, on: bool = True) -> None:
        """Acknowledge ``XOF`` but keep emitting (a failed high-voltage relay)."""
        with self._lock:
            self._stuck = bool(on)

    def ramp_down(self, delay_s: float) -> None:
        """After ``XOF``, keep reading X-rays on for ``delay_s`` seconds (a high-voltage supply
        ramping down; L8121.md does not say how long a real one takes). 0 restores."""
        if delay_s < 0:
            raise ValueError(f"delay_s must be >= 0, got {delay_s}")
        with self._lock:
            self._off_delay_s = float(delay_s)

    def silence(self, on: bool = True, *, execute: bool = False) -> None:
        """Stop answering. ``execute=False``: a dead controller, commands are recorded but neither
        executed nor answered (nothing the software sends can switch the tube off: only the
        hardware interlock can). ``execute=True``: the reply path is lost (a broken receive line)
        but commands still act, so an ``XOF`` sent on detecting the silence does switch off."""
        with self._lock:
            self._silent = bool(on)
            self._silent_executes = bool(execute)

    def sts_error(self, on: bool = True) -> None:
        """Answer ``STS`` with ``ERROR`` whatever the state (every other command as usual, so an
        ``XOF`` still switches off). Dialect B lists ``ERROR`` among ``STS``'s words (pre-heating,
        by L8121.md's table), which is also how B refuses a command: a state that shows nothing
        about the tube. In A it is a refused query. Either way no switch-off can be confirmed
        while it lasts."""
        with self._lock:
            self._sts_error = bool(on)

    def garbage(self, on: bool = True) -> None:
        """Answer every command (executed as usual) with random junk instead of its reply."""
        with self._lock:
            self._garbage = bool(on)

    def lower_case(self, on: bool = True) -> None:
        """Answer every command in lower case (``sts 2``, ``standby``, ``spv 60.0kv``): L8121.md
        says commands are upper case and does not say what case a reply is in."""
        with self._lock:
            self._lower_case = bool(on)

    def garble_once(self, command: str | None = None) -> None:
        """Answer one command (the next one, or the next ``command``, a command word such as
        ``"STS"``) with random junk instead of its reply, executed as usual: noise on the line,
        once (:meth:`garbage` garbles every reply)."""
        with self._lock:
            self._garble_once = (command,)

    def foreign(self, on: bool = True) -> None:
        """Answer every line with ``OK`` and execute nothing: another instrument on the port, which
        speaks neither dialect."""
        with self._lock:
            self._foreign = bool(on)

    def delay_once(self, delay_s: float, command: str | None = None) -> None:
        """Delay one reply by ``delay_s`` seconds (in the servers): the next one, or the next reply
        to ``command`` (a command word such as ``"SIN"``). Later commands are answered after it, in
        order, as a controller's are: a reply that comes after the client's time-out, once."""
        if delay_s < 0:
            raise ValueError(f"delay_s must be >= 0, got {delay_s}")
        with self._lock:
            self._delay_once = (float(delay_s), command)

    def hold_once(self, command: str | None = None) -> None:
        """Hold one reply (the next one, or the next reply to ``command``) until the client's next
        line arrives, and send it then, before that line's reply: a reply that comes after the
        client's time-out *and* after its next command was written. An event, not a delay
        (:meth:`delay_once`): on a loaded machine a delayed reply can reach the client before its
        next command, where the flush before that command discards it, and a test meant for the
        late-reply grammar then passes without reaching it. The client must time out first."""
        with self._lock:
            self._hold_once = (command,)

    def holds_reply(self, line: str) -> bool:
        """Whether the servers hold the reply to ``line`` (a pending :meth:`hold_once` that
        matches; used up)."""
        with self._lock:
            once = self._hold_once
            if once is not None and once[0] in (None, (line.split() or [""])[0]):
                self._hold_once = None
                return True
            return False

    def reply_delay(self, line: str) -> float:
        """How long a server waits before sending the reply to ``line``: :meth:`slow`'s delay, or a
        pending :meth:`delay_once` that matches (used up)."""
        with self._lock:
            once = self._delay_once
            if once is not None and once[1] in (None, (line.split() or [""])[0]):
                self._delay_once = None
                return once[0]
            return self._delay_s

    def slow(self, delay_s: float) -> None:
        """Delay every reply by ``delay_s`` seconds (in the servers; 0 restores)."""
        if delay_s < 0:
            raise ValueError(f"delay_s must be >= 0, got {delay_s}")
        with self._lock:
            self._delay_s = float(delay_s)

    # -- the protocol -----------------------------------------------------------------------------
    def handle(self, line: str, baudrate: int | None = None) -> str | None:
        """Execute one command line and return its reply (no terminator), or None for no reply.

        ``baudrate`` is the rate the line was sent at, when the link knows it (a pty); at a rate
        other than :attr:`baudrate` the line is not understood and the reply is junk (see the
        module docstring).

        Examples
        --------
        >>> L8121Model().handle("HIV 200")
        'ERR'
        >>> L8121Model(dialect="B").handle("STS", baudrate=38400) == "STANDBY"
        False
        """
        exchange = self.receive(line, baudrate)
        return None if exchange is None else exchange.reply

    def receive(self, line: str, baudrate: int | None = None) -> Exchange | None:
        """As :meth:`handle`, returning the whole :class:`Exchange` (None for an empty line)."""
        line = line.strip(" \t")  # not CR or LF: the link's line end is CR alone (L8121.md)
        if not line:
            return None
        with self._lock:
            self._advance()
            t = self.time
            understood = baudrate is None or baudrate == self.baudrate
            if not understood:
                reply = "".join(chr(self._rng.randint(0x80, 0xFE)) for _ in range(self._rng.randint(2, 6)))
            elif self._silent:
                reply = None
                if self._silent_executes:
                    self._execute(line, t)
            elif self._foreign:
                reply = "OK"
            else:
                reply = self._execute(line, t)
                once = self._garble_once
                if once is not None and once[0] in (None, (line.split() or [""])[0]):
                    self._garble_once = None
                    reply = "".join(self._rng.choice(_JUNK) for _ in range(self._rng.randint(1, 12)))
                if self._garbage:
                    reply = "".join(self._rng.choice(_JUNK) for _ in range(self._rng.randint(1, 12)))
                if self._lower_case:
                    reply = reply.lower()
            exchange = Exchange(t, line, reply, understood)
            self._log.append(exchange)
        logger.debug("L8121 emulator %.3f s: %s -> %s", t, line, reply)
        return exchange

    def _execute(self, line: str, t: float) -> str:
        reply, acted = self._act(line, t)
        word = (line.split() or [""])[0]
        if acted or word in self._after_refused:
            self._after_refused.discard(word)
            fault = self._after.pop(word, None)
            if fault is not None:
                fault()
        return reply

    def _act(self, line: str, t: float) -> tuple[str, bool]:
        """The reply to ``line``, and whether its action ran (not refused before it)."""
        # an LF or another control character inside the line (CR alone ends one: a CR LF client's LF
        # begins its next line, or is all of it) makes no command the unit knows
        word, *args = (line.split() if line.isprintable() else None) or [""]
        if word == "STS" and not args and self._sts_error:
            return "ERROR", False
        action = self._commands.get(word)
        if action is None or len(args) != (word in self._takes_argument):
            return self._refuse("ERR" if self.dialect == "A" else "ERROR"), False
        # L8121.md, dialect A: "XOF ... always accepted" -- not in remote mode too. B's notes say
        # only that remote control needs REMOTE, with no exception: B refuses its XOF there
        if word in _CONTROL and self._switch != "REMOTE" and not (word == "XOF" and self.dialect == "A"):
            return self._refuse(), False
        return action(t, *args), True

    def _refuse(self, reply: str = "ERROR") -> str:
        """A refusal: its reply alone. L8121.md ties no refusal to ``SER``, which stays as it was."""
        return reply

    def _range_error(self) -> str:
        return self._refuse("ERR" if self.dialect == "A" else "ERROR")

    def _hiv(self, t, arg, word="HIV"):
        raw = _whole(arg)
        kv = None if raw is None else raw / self.voltage_scale
        if kv is None or not self.kv_min <= kv <= self.kv_max or kv * self._set_ua / 1000 > self.watts_max:
            return self._range_error()
        self._retarget(t)
        self._set_kv = kv if kv != int(kv) else int(kv)
        return f"{word} {raw}"

    def _cur(self, t, arg, word="CUR"):
        ua = _whole(arg)
        if ua is None or not 0 <= ua <= self.ua_max or self._set_kv * ua / 1000 > self.watts_max:
            return self._range_error()
        self._retarget(t)
        self._set_ua = ua
        return f"{word} {ua}"

    def _xon_a(self, t):
        if self._state != SourceState.STANDBY or self._interlock_open:
            return self._refuse()
        self._switch_on(t)
        return "XON"

    def _xon_b(self, t):
        """Dialect B: ``XON`` starts the warm-up when one is due, the exposure otherwise."""
        if self._interlock_open or self._state not in (SourceState.STANDBY, SourceState.WARMUP_NEEDED):
            return self._refuse()
        if self._state == SourceState.WARMUP_NEEDED:
            self._start_warm_up(t)
        else:
            self._switch_on(t)
        return "XON"

    def _switch_on(self, t):
        self._state, self._beam_dropped = SourceState.XRAY_ON, False
        self._ramp_t0, self._ramp_from, self._falling = t, (0.0, 0.0), None

    def _xof(self, t):
        if self._stuck:
            return "XOF"
        if self._state == SourceState.XRAY_ON and self._off_delay_s > 0:
            if not self._ramping_down:  # a repeated XOF does not restart the ramp
                self._ramping_down = True
                self._schedule(t + self._off_delay_s, self._ramped_down)
            return "XOF"
        if self._state == SourceState.XRAY_ON:
            self._state = SourceState.STANDBY
        elif self._state == SourceState.WARMING_UP:  # the warm-up runs the tube: XOF ends it, and must be run again
            self._state, self._warmup = SourceState.WARMUP_NEEDED, WarmupState.NOT_STARTED
        self._beam_dropped = False
        return "XOF"

    def _ramped_down(self, t):
        self._ramping_down = False
        if self._state == SourceState.XRAY_ON:
            self._state, self._beam_dropped = SourceState.STANDBY, False

    def _wup(self, t):
        if self._state not in (SourceState.WARMUP_NEEDED, SourceState.STANDBY, SourceState.WARMING_UP):
            return self._refuse()
        if self._interlock_open:
            return self._refuse()
        if self._state != SourceState.WARMING_UP and self._start_lag_s > 0:
            if math.isfinite(self._start_lag_s):
                self._schedule(t + self._start_lag_s, self._start_late)
        elif self._state != SourceState.WARMING_UP:
            self._start_warm_up(t)
        return "WUP"

    def _start_late(self, t):
        if self._state in (SourceState.STANDBY, SourceState.WARMUP_NEEDED):  # not over an overload
            self._start_warm_up(t)

    def _start_warm_up(self, t):
        self._state, self._warmup, self._warmup_t0 = SourceState.WARMING_UP, WarmupState.RUNNING, t
        started = self._warmup_t0

        def done(t_done):
            if self._state == SourceState.WARMING_UP and self._warmup_t0 == started:
                self._state = SourceState.STANDBY
                if self._swe_lag_s > 0:  # STS first, SWE a while later (swe_lags)
                    self._schedule(t_done + self._swe_lag_s, lambda _t: setattr(self, "_warmup", WarmupState.DONE))
                else:
                    self._warmup = WarmupState.DONE

        self._schedule(t + self.warmup_s, done)

    def _dag(self, t):
        if self._warmup == WarmupState.DONE:
            return "AGING 0 0 END"
        step = 0
        if self._state == SourceState.WARMING_UP and self.warmup_s > 0:
            step = 1 + min(_AGING_STEPS - 1, int(_AGING_STEPS * (t - self._warmup_t0) / self.warmup_s))
        return f"AGING 1 {step} YET"

    def _rst(self, t):
        if self._state == SourceState.OVERLOAD:
            self._state = SourceState.STANDBY if self._warmup == WarmupState.DONE else SourceState.WARMUP_NEEDED
        return "RST"  # a control-board fault stays (L8121.md gives RST for an overload only)

    def _cfs(self, t, arg):
        mode = _whole(arg)
        if mode is None or not 0 <= mode <= 3:
            return self._range_error()
        self._focus = mode
        return f"CFS {mode}"

    def _cf(self, mode: int, word: str) -> str:
        self._focus = mode
        return word

    def _measured(self, t: float) -> tuple[float, float]:
        if self._state != SourceState.XRAY_ON:
            return 0.0, 0.0
        fall = self._falling
        if fall is not None and t < fall[0] + fall[2]:  # falling to nothing (ramp_after_change("zero"))
            g = 1 - (t - fall[0]) / fall[2]
            kv, ua = fall[1][0] * g, fall[1][1] * g
        else:
            f = 1.0 if self.ramp_s <= 0 else min(1.0, max(0.0, (t - self._ramp_t0) / self.ramp_s))
            kv0, ua0 = self._ramp_from
            kv, ua = kv0 + (self._set_kv - kv0) * f, ua0 + (self._set_ua - ua0) * f
        kv, ua = kv * self._runaway[0], ua * self._runaway[1]
        return kv, (0.0 if self._beam_dropped else ua)

    def _meter(self, t: float) -> tuple[float, float]:
        """The measured values a reply reports: the current with the meter's noise (meter_jitter),
        its sign turned at each report."""
        kv, ua = self._measured(t)
        if self._meter_noise and ua:
            ua *= 1 + self._meter_noise * self._meter_sign
            self._meter_sign = -self._meter_sign
        return kv, ua

    def _retarget(self, t):
        """A new setting while on ramps from where the tube is now, or (ramp_after_change("zero"))
        falls from there to nothing and ramps again from zero."""
        if self._change_start == "zero" and self._state == SourceState.XRAY_ON:
            # from the tube's values, without a runaway's factors (_measured applies them after)
            kv, ua = self._measured(t)
            kv, ua = kv / (self._runaway[0] or 1.0), ua / (self._runaway[1] or 1.0)
            self._falling = (t, (kv, ua), self._change_fall_s) if self._change_fall_s > 0 else None
            self._ramp_from, self._ramp_t0 = (0.0, 0.0), t + self._change_fall_s
            return
        self._ramp_from, self._ramp_t0 = self._measured(t), t

    # -- model time -------------------------------------------------------------------------------
    def _schedule(self, at: float, fn: Callable[[float], None]) -> None:
        heapq.heappush(self._events, (at, next(self._seq), fn))

    def _at(self, at_s: float | None, fn: Callable[[float], None]) -> None:
        with self._lock:
            self._advance()
            if at_s is None or at_s <= self.time:
                fn(self.time)
            else:
                self._schedule(float(at_s), fn)

    def _advance(self) -> None:
        """Apply, in time order, everything scheduled up to now."""
        now = self.time
        while self._events and self._events[0][0] <= now:
            t, _, fn = heapq.heappop(self._events)
            fn(t)

    def __repr__(self) -> str:
        return (
            f"L8121Model(dialect {self.dialect}, {self.baudrate} baud, state={self.state}, "
            f"set {self._set_kv} kV {self._set_ua} µA)"
        )


def _whole(text: str) -> int | None:
    return int(text) if text.isdigit() else None


_SPEEDS = {
    getattr(termios, f"B{b}"): b
    for b in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)
    if hasattr(termios, f"B{b}")
}


# -- servers --------------------------------------------------------------------------------------
class _LineServer:
    """Reads CR-terminated lines, answers each with the model; replies end with
    ``reply_terminator`` (CR, as the controller; ``"\\r\\n"`` to test a client against CR LF).
    L8121.md ends commands in CR only: an LF is part of the line it comes in (a command the
    controller does not know), so a client that sent LF or CR LF fails here as at a unit."""

    def __init__(self, model: L8121Model, *, reply_terminator: str = "\r"):
        self.model = model
        self.reply_terminator = reply_terminator
        self.url: str | None = None
        self._held: bytes | None = None  # a reply held back until the next line (hold_once)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _answer(self, buf: bytearray, data: bytes, write: Callable[[bytes], object]) -> None:
        buf += data
        while True:
            cut = buf.find(b"\r")
            if cut < 0:
                return
            line, buf[:] = bytes(buf[:cut]), buf[cut + 1 :]
            if self._held is not None and line.strip():  # the next command is here: the late reply goes first
                write(self._held)
                self._held = None
            exchange = self.model.receive(line.decode("ascii", errors="replace"), self._baudrate())
            if exchange is None or exchange.reply is None:
                continue
            # a reply garbled by a baud mismatch has no recognisable line end
            end = self.reply_terminator if exchange.understood else ""
            reply = (exchange.reply + end).encode("latin-1", errors="replace")
            if self.model.holds_reply(exchange.command):
                self._held = reply
                continue
            delay = self.model.reply_delay(exchange.command)
            if delay > 0 and self._stop.wait(delay):
                return
            write(reply)

    def _baudrate(self) -> int | None:
        """The baud rate the client set, where the link has one (a pty); None otherwise."""
        return None

    def start(self):
        """Start serving in a daemon thread; returns self."""
        if self._thread is not None:
            return self
        self._stop.clear()
        self._open()
        self._thread = threading.Thread(target=self._serve, name=f"{type(self).__name__} {self.url}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and release the pty or socket."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"


class PtyServer(_LineServer):
    """Serve ``model`` on a pseudo-terminal; :attr:`url` is the slave's path (e.g. ``/dev/pts/3``),
    which :func:`serial.serial_for_url` opens like a serial port.

    Examples
    --------
    >>> import serial
    >>> with PtyServer(L8121Model()) as server:
    ...     with serial.serial_for_url(server.url, baudrate=9600, timeout=1) as port:
    ...         _ = port.write(b"TYP\\r")
    ...         port.read_until(b"\\r")
    b'TYP L8121-01\\r'
    """

    def _baudrate(self) -> int | None:
        """The output speed the client set on the terminal (pyserial sets it when it opens the port)."""
        try:
            return _SPEEDS.get(termios.tcgetattr(self._slave)[5])
        except (termios.error, TypeError):
            return None

    def read_error(self) -> None:
        """Make the client's next read of the port fail once while the port stays (a brief read
        error, as a USB adapter's glitch): pyserial raises "device reports readiness to read but
        returned no data". How, on a real pty: the terminal's line discipline is made canonical
        and sent its end-of-file character, which a read returns as nothing; pyserial sets raw mode
        again when it reopens the port, and the link then works as before. A reply held by
        :meth:`L8121Model.hold_once` is still sent before the reply to the client's next line,
        on the reopened port: the controller answering the command in flight at the error, late."""
        attrs = termios.tcgetattr(self._slave)
        attrs[3] |= termios.ICANON
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        os.write(self._master, attrs[6][termios.VEOF])

    def line_noise(self, data: bytes) -> None:
        """Put ``data`` on the line to the client now, between the controller's replies: noise (a
        glitch, a discharge nearby), not a reply of the controller's. A fault the model cannot make:
        its replies are its own (:meth:`L8121Model.garble_once` garbles one of them instead)."""
        os.write(self._master, data)

    def _open(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes pass as sent
        self.url = os.ttyname(self._slave)

    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:  # EIO while no one holds the slave open (we do, but be safe)
                time.sleep(0.01)
                continue
            self._answer(buf, data, lambda b: os.write(self._master, b))

    def _close(self) -> None:
        for fd in (getattr(self, "_master", None), getattr(self, "_slave", None)):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None


class SocketServer(_LineServer):
    """Serve ``model`` on TCP, one client at a time; :attr:`url` is ``socket://127.0.0.1:PORT``.

    :meth:`drop_connection` closes the current client's connection (a lost link; the client may
    reconnect).
    """

    def __init__(self, model: L8121Model, *, host: str = "127.0.0.1", port: int = 0, reply_terminator: str = "\r"):
        super().__init__(model, reply_terminator=reply_terminator)
        self.host, self.port = host, port
        self._drop = threading.Event()
        self._dropped = threading.Event()

    def drop_connection(self, wait_s: float = 10.0) -> None:
        """Close the current client connection (fault injection: lost link), and return once it is
        closed (at most ``wait_s``): a caller that slept for the server's next look instead lost
        the race on a loaded machine, its next command answered on the old connection."""
        self._dropped.clear()
        self._drop.set()
        self._dropped.wait(wait_s)

    def _open(self) -> None:
        self._listener = socket.create_server((self.host, self.port))
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{self.host}:{self.port}"

    def _serve(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listener], [], [], 0.05)
            if not ready:
                continue
            conn, _ = self._listener.accept()
            self._drop.clear()
            with conn:
                buf = bytearray()
                while not self._stop.is_set() and not self._drop.is_set():
                    ready, _, _ = select.select([conn], [], [], 0.05)
                    if not ready:
                        continue
                    try:
                        data = conn.recv(4096)
                    except OSError:
                        break
                    if not data:
                        break
                    self._answer(buf, data, conn.sendall)
            if self._drop.is_set():
                self._dropped.set()
            self._drop.clear()

    def _close(self) -> None:
        listener = getattr(self, "_listener", None)
        if listener is not None:
            listener.close()
            self._listener = None


def main(argv: list[str] | None = None) -> int:
    """``python -m acquisition.emulators.l8121``: serve an emulated controller until Ctrl-C.

    The first line on stdout is the url to open (a device path with ``--pty``, the default, or
    ``socket://127.0.0.1:PORT`` with ``--socket``).
    """
    import argparse
    import signal

    parser = argparse.ArgumentParser(
        prog="python -m acquisition.emulators.l8121",
        description="Serve an emulated Hamamatsu L8121 controller until Ctrl-C; "
        "the first line on stdout is the url to open.",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal (default)")
    where.add_argument("--socket", type=int, metavar="PORT", help="serve on TCP 127.0.0.1:PORT (0: any free port)")
    parser.add_argument("--dialect", choices=("A", "B"), default="A", help="command dialect (default %(default)s)")
    parser.add_argument("--baudrate", type=int, help="the controller's baud rate (default: 9600, both dialects)")
    parser.add_argument("--model", default="L8121-01", help="what TYP answers in dialect A (default %(default)s)")
    parser.add_argument("--warmup-s", type=float, default=3.0, help="warm-up duration, s (default %(default)s)")
    parser.add_argument("--ramp-s", type=float, default=1.0, help="kV/µA ramp after XON, s (default %(default)s)")
    parser.add_argument("--warmed-up", action="store_true", help="start in standby, warm-up done")
    parser.add_argument("--local", action="store_true", help="operate switch on LOCAL: remote commands refused")
    parser.add_argument("--foreign", action="store_true", help="answer OK to everything (speaks neither dialect)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log every exchange on stderr")
    args = parser.parse_args(argv)
    if args.verbose:
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr, format="%(asctime)s %(message)s")
    model = L8121Model(
        dialect=args.dialect,
        model=args.model,
        warmup_s=args.warmup_s,
        ramp_s=args.ramp_s,
        warmed_up=args.warmed_up,
        baudrate=args.baudrate,
    )
    if args.local:
        model.set_operate_switch("LOCAL")
    if args.foreign:
        model.foreign()
    server = PtyServer(model) if args.socket is None else SocketServer(model, port=args.socket)

    def terminate(signum, frame):
        raise KeyboardInterrupt

    # given back as it returns: a Python program that serves an emulator for a while goes on after it
    before = signal.signal(signal.SIGTERM, terminate)
    try:
        with server:
            print(server.url, flush=True)
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, before)
    return 0


if __name__ == "__main__":
    sys.exit(main())
