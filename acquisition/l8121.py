"""The Hamamatsu L8121 microfocus X-ray source, driven over RS-232 (protocol: ``L8121.md``).

The controller is documented in two command dialects (``../shared/hardware/L8121.md``): dialect A,
the one public drivers use for Hamamatsu microfocus controllers of the same generation (L9181,
L9191, L9421, C8033: numeric ``STS n``, ``SAR``, ``SVI``, ``SIN 0/1``, ``WUP``, ``TYP``), and
dialect B, what a public Windows driver for the L8121-02 speaks (``STS`` answered by a word,
``INTER LOCK ON``, values with units, ``PHV``/``PCU`` presets, warm-up started by ``XON``, ``DAG``,
``SRL``/``SRB``, no ``TYP``). The dialect is configuration, not code:
``SourceConfig(dialect="A" | "B" | "auto", baudrate=..., voltage_scale=...)``.

The driver is mostly its command tables: :data:`DIALECT_A` and :data:`DIALECT_B` declare, for each
reading and each setting, the command string, the validator of its argument and the parser of its
reply (:class:`Query`, :class:`Command`, :class:`Choice`, in the manner of PyMeasure's
``Instrument.control``). On top sit the operations an experiment needs, the same in both dialects,
each keeping the safety rules of the hardware notes:

- :meth:`L8121.warm_up` starts the warm-up (A: ``WUP``; B: ``XON`` while ``DAG`` says ``YET``) only
  when it is needed and the interlock is closed, after setting the values it emits at (given, or
  the configuration's lowest) and reading them back, and waits for standby;
- :meth:`L8121.on` checks voltage, current and power against :meth:`SourceConfig.check_exposure`
  *before sending anything*, requires standby with the warm-up done (A: ``STS 2`` and ``SWE 0``;
  B: ``STS STANDBY`` and ``DAG ... END``) and a closed interlock, sets the values (A:
  ``HIV``/``CUR``; B: the presets ``PHV``/``PCU``) and reads them back (A: ``SVI``; B:
  ``SPV``/``SPC``), switches on and waits for a stable beam;
- :meth:`L8121.check` polls once while the beam is on (A: ``SAR``, ``SIN``; B: ``STS``, ``SHV``,
  ``SCU``, ``SIN``; ``SER`` at most every ``error_poll_s``) and, on overload, an open
  interlock, a dropped beam or a controller error code, switches off and raises
  :class:`~acquisition.errors.SourceFault`;
- :meth:`L8121.off` switches off and confirms it with ``STS``; :meth:`L8121.close` and the context
  manager switch off on every exit path (exception, Ctrl-C), and so does any reply that cannot be
  parsed while the beam may be on.

Warm-up emits X-rays: ``STS 1`` (A) and ``AGING`` (B) count as X-rays on for every rule (switched
off on exit, never taken as "off" after ``XOF``). In dialect B the same ``XON`` starts either a
warm-up or an exposure, depending on the controller's warm-up state; the driver never sends an
``XON`` meant as an exposure unless ``DAG`` has just said ``END``, never sends the warm-up ``XON``
unless it has just said ``YET``, and if the controller does the other thing all the same (``AGING``
after an exposure's ``XON``, ``XON`` after a warm-up's) it switches off and says so. A warm-up
that runs on from ``AGING`` into ``XON`` at its end is switched off too (confirmed) and counts as
done when ``DAG`` then says ``END``.

``dialect="auto"`` runs :func:`probe` at connect: harmless queries only (``STS``, ``SIN``, ``TYP``,
``SRL``, ``DAG``; never ``XON``, ``HIV``, ``CUR``, ``PHV``, ``PCU``, ``WUP`` or ``RST``) at each
configured baud rate, and refuses to go on when the replies fit neither dialect.

The driver never sends ``RST`` by itself (:meth:`L8121.reset` is for a person who has looked at the
tube). Every reply is checked: a command must be echoed, a query's reply must have the dialect's
shape; anything else raises :class:`~acquisition.errors.DeviceError` naming the port, the command
and the reply. The hardware ratings (:data:`RATINGS`: 40-150 kV, <= 500 µA, <= 75 W) are a ceiling
no configuration can raise: a :class:`SourceConfig` may only tighten them.

Why not PyMeasure: PyMeasure (``Instrument.control``, validators, ``expected_protocol``) is the
shape this module copies, but building on it would not make the driver simpler to read or to test.
Its properties bind one command string per class, so two dialects would be two instrument classes
(or dynamic properties for every command), while here one driver reads its commands from a table
chosen at connect -- which ``dialect="auto"`` needs, since the dialect is known only after the
probe. The safety rules need a hook around every exchange (switch off before reporting an
unparseable or refused reply while the beam may be on; accept ``ERROR`` as a value of dialect B's
``STS``), which PyMeasure's ``check_get_errors`` can express only per instrument, not per exchange.
And it would add pyvisa, pint and pandas to a lab PC for one serial instrument. What we take from
it instead: declarations (:class:`Query`, :class:`Command`), a swappable transport (the driver
accepts any object with ``query``), and expected-protocol tests (``tests/test_l8121_protocol.py``:
exact (sent, reply) pairs, no pseudo-terminal).

Examples
--------
>>> from acquisition.emulators.l8121 import L8121Model, PtyServer
>>> for dialect in ("A", "B"):
...     with PtyServer(L8121Model(dialect=dialect, warmup_s=0.2, ramp_s=0.2)) as server:
...         with L8121(server.url, dialect=dialect, poll_s=0.05) as source:
...             _ = source.warm_up(timeout_s=10, progress=False)
...             beam = source.on(60, 250)          # kV, µA: returns once the beam is stable
...             print(dialect, source.check()["state"].name, beam["set_voltage_kv"], beam["set_current_ua"])
...         print(server.model.xray_on)            # leaving the block switched the tube off
A XRAY_ON 60 250
False
B XRAY_ON 60 250
False
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import re
import threading
import time
import tomllib
from collections.abc import Callable, Iterable, Mapping
from enum import IntEnum
from pathlib import Path
from typing import Any

from acquisition.errors import DeviceError, GuardianLost, NoReply, PortUnavailable, SourceFault, WriteTimedOut
from acquisition.transport import SerialTransport
from radiokit.checks import is_integer, is_number, shown, shown_name, toml_loads

__all__ = [
    "L8121",
    "SourceConfig",
    "SourceState",
    "WarmupState",
    "Aging",
    "Ratings",
    "RATINGS",
    "Dialect",
    "DIALECT_A",
    "DIALECT_B",
    "DIALECTS",
    "ProbeResult",
    "ProbeExchange",
    "probe",
    "Query",
    "Command",
    "Choice",
    "SwitchedOff",
    "SettingRefused",
    "OffOutcome",
]

logger = logging.getLogger(__name__)

#: Set (True) on the log record of a switch-off the controller did not confirm. A command line
#: that ends by saying that failure itself, right above the X-RAYS warning, keeps these records off
#: the terminal (each layer that tried logged its own copy, and the operator read it three times).
OFF_FAILURE = "tube_off_failure"

#: The default of ``SourceConfig.error_poll_s`` (``[source] error_poll_s``): with the beam on
#: (check(), on()'s ramp, the warm-up's wait) ``SER`` is read at most this often,
#: after the poll's beam checks. Not every poll: each query costs the link's spacing (A 50 ms,
#: B 60 ms) and the beam checks (A ``SAR SIN``, B ``STS SHV SCU SIN``) keep their period. B's
#: public driver cycles SER in its poll, 20 ms apart; at radiokit's 60 ms a fifth query every
#: poll would stretch B's cycle by a quarter. Once a second bounds the time a relay or internal
#: fault goes unnoticed (L8121.md: a reason to stop) to about a second, for about one
#: exchange a second of link time.
ERROR_POLL_S = 1.0

#: The longest ``error_poll_s`` a configuration may set: a relay or internal fault (L8121.md: a
#: reason to stop high voltage) unnoticed for up to a minute of beam. A unit without ``SER`` is
#: ``error_query = false``, not a period nobody reaches.
ERROR_POLL_MAX_S = 60.0


class SettingRefused(ValueError):
    """A value or a configuration the driver refuses before anything is sent: ``str()`` names who
    refuses (``of``: "L8121" for a voltage or current, "L8121 configuration" for a setting), and
    ``detail`` is the rest, for a caller that says it in its own words (the command line, a
    protocol's ``[source]``) instead of cutting the speaker off the text."""

    def __init__(self, detail: str, *, of: str = "L8121 configuration"):
        super().__init__(f"{of}: {detail}")
        self.detail, self.of = detail, of

    def __reduce__(self):
        # copy and pickle rebuild an exception from its args, the whole text: its speaker was said twice
        return _setting_refused, (self.detail, self.of)


def _setting_refused(detail: str, of: str) -> SettingRefused:
    return SettingRefused(detail, of=of)


class SwitchedOff(DeviceError):
    """A routine reading (:meth:`L8121.check`) was cut short because another thread switched X-rays
    off meanwhile: its remaining queries were not sent -- they would have waited behind the ``XOF``
    and then measured a tube that is off -- so the reading vouches for nothing."""


class SourceState(IntEnum):
    """The controller's state, the same in both dialects.

    Dialect A's ``STS n`` gives 0-6 directly. Dialect B's ``STS`` word maps as: ``STANDBY`` to
    STANDBY (or WARMUP_NEEDED when ``DAG`` says ``YET``), ``XON`` to XRAY_ON, ``AGING`` to
    WARMING_UP, ``OVER`` to OVERLOAD, ``NOT READY`` to NOT_READY and ``ERROR`` to PREHEATING (the
    hardware notes read it as pre-heating; as it is also what a refused query looks like, it is
    never taken as confirmation that X-rays are off).
    """

    WARMUP_NEEDED = 0
    WARMING_UP = 1
    STANDBY = 2
    XRAY_ON = 3
    OVERLOAD = 4
    NOT_READY = 5
    SELF_TEST = 6
    PREHEATING = 7

    @property
    def emitting(self) -> bool:
        """Whether the tube may emit in this state: X-rays on, or warming up (B: ``AGING``)."""
        return self in (SourceState.XRAY_ON, SourceState.WARMING_UP)

    @property
    def said(self) -> str:
        """The state for an operator's message: its name, but B's ``STS ERROR`` with both of its
        readings, since the driver cannot tell which (called pre-heating alone, a refused query
        while the beam was on read as a beam that had dropped)."""
        if self is SourceState.PREHEATING:
            return "ERROR (PREHEATING, or a refused query: dialect B does not say which)"
        return self.name

    @property
    def confirms_off(self) -> bool:
        """Whether this state shows the tube cannot emit (what confirms a switch-off; B's
        ambiguous ``ERROR`` does not)."""
        return self in _OFF_STATES


# States that confirm X-rays are off after an XOF.
_OFF_STATES = frozenset(
    {SourceState.WARMUP_NEEDED, SourceState.STANDBY, SourceState.OVERLOAD, SourceState.NOT_READY, SourceState.SELF_TEST}
)


@dataclasses.dataclass(frozen=True)
class OffOutcome:
    """What the switch-off a fault called for found, carried by that fault's exception as its
    ``switch_off`` attribute (:meth:`L8121._switched_off`), so that a caller -- the command line --
    composes its own line from these fields instead of editing the driver's message (a reworded
    message silently broke the line it had spliced together).

    ``cause`` is why the driver switched off, without the port (``"interlock open"``); ``state``
    the state ``STS`` read that confirmed the tube off (None: not confirmed); ``failure`` the error
    :meth:`L8121.off` raised when it could not confirm; ``error_code`` the controller's error code
    ``SER`` read after a confirmed switch-off, when not 0 and asked (None otherwise). Every
    switch-off recorded here was attempted (``XOF`` sent) for this fault. The fail-safe's (a
    failed exchange, :meth:`L8121._fail_safe`) is not recorded here: its cause's message says no
    switch-off, and a caller reads the driver's state after it (:attr:`L8121.confirmed_off`).
    """

    port: str
    cause: str
    state: SourceState | None = None
    failure: Exception | None = None
    error_code: int | None = None

    @property
    def confirmed(self) -> bool:
        """Whether ``STS`` confirmed the tube off after this switch-off."""
        return self.state is not None

    @property
    def note(self) -> str:
        """The driver's own words for the outcome, after the cause in its message."""
        said = "X-rays switched off" if self.confirmed else OFF_NOT_CONFIRMED
        return said + (f"; controller error code {self.error_code}" if self.error_code else "")


class WarmupState(IntEnum):
    """The warm-up sequence (A: ``SWE``; B: derived from ``DAG`` and ``STS``)."""

    DONE = 0
    RUNNING = 1
    NOT_STARTED = 2


@dataclasses.dataclass(frozen=True)
class Aging:
    """Dialect B's ``DAG`` reply, ``AGING m s END|YET``: warm-up mode (0 none, 1 after 8 h idle,
    2 one month, 3 three months), step, and whether the warm-up is done."""

    mode: int
    step: int
    done: bool


@dataclasses.dataclass(frozen=True)
class Ratings:
    """The L8121's ratings (``L8121.md``): the ceiling every configuration stays under."""

    kv_min: float = 40.0
    kv_max: float = 150.0
    ua_max: float = 500.0
    watts_max: float = 75.0


RATINGS = Ratings()


# -- configuration --------------------------------------------------------------------------------
# The longest wait for one reply (timeout_s, probe_timeout_s, the CLI's --reply-timeout):
# L8121.md's L8121-02 driver calls 10 s without replies a failed link, so a longer wait waits for
# a controller that has failed; and a switch-off waits one reply time-out per XOF and STS of each
# attempt before it can tell the operator, so an absurd value (1e9) made it wait for ever with
# the tube possibly on.
REPLY_TIMEOUT_MAX_S = 10.0


#: The most switch-off attempts a configuration may ask for (``off_attempts``, default 3). Each
#: is an XOF and an STS, each a reply's wait: 10 at the longest reply wait (10 s) are 200 s of
#: "maybe on" before the operator is told to switch off at the controller; 10**9 never told.
OFF_ATTEMPTS_MAX = 10


@dataclasses.dataclass(frozen=True)
class TimeLimit:
    """The bound of one time of :class:`SourceConfig`: at most ``max_s``, ``zero`` whether 0 is
    a value (``xon_start_s = 0``: at once) or a time that must pass, and ``why``, said with a
    refusal."""

    max_s: float
    why: str
    zero: bool = False


#: Every time of :class:`SourceConfig`, bounded in this one place (its ``__post_init__``, the
#: driver's own time-out arguments, the command line's time-outs and a protocol's ``[source]``
#: all ask :func:`checked_time`). Why bounds at all: 1e300 passed ``finite``, and a wait that
#: long is a wait for ever -- with X-rays on, or about to be, for most of these.
TIME_LIMITS: dict[str, TimeLimit] = {
    name: TimeLimit(
        REPLY_TIMEOUT_MAX_S, "a controller silent that long has failed, L8121.md; each wait of a switch-off is one"
    )
    for name in ("timeout_s", "probe_timeout_s")
} | {
    # L8121.md gives the warm-up no duration, only schedules by the time the tube stood idle
    # (B's DAG: 8 h, a month, three months). The default, 30 min, is three times the dry run's
    # 10 min estimate; four times that still covers a schedule far longer than planned, and past
    # it a "warm-up" that never reports done is a fault -- while it emits. An extra zero typed
    # (18000) must not become five hours of X-rays nobody watches.
    "warmup_timeout_s": TimeLimit(
        7200.0, "a warm-up still running after 2 h, emitting all along, has failed: see to the controller"
    ),
    # the power-on checks (A's STS 6, B's ERROR, "not ready" with the door shut) and B's SRB BUSY:
    # queries only, but the operator's command waits on them; L8121.md gives no duration, and a
    # unit still checking itself after ten minutes (twenty times the default) needs a person
    "ready_timeout_s": TimeLimit(
        600.0, "a controller still in its power-on checks after 10 min needs looking at, not waiting for"
    ),
    # L8121.md: the measured values ramp to the set ones "over a few seconds" after XON; the
    # beam is on for the whole wait (default 15 s)
    "stable_timeout_s": TimeLimit(60.0, "the beam ramps in a few seconds, L8121.md, and is on for the whole wait"),
    # the start command was sent: X-rays may be on while the warm-up is waited for to show (default 5 s)
    "warmup_start_s": TimeLimit(60.0, "the warm-up's start command was sent: X-rays may be on for the whole wait"),
    # XON was sent and echoed: standby is let pass this long (default 1 s); 0: at once
    "xon_start_s": TimeLimit(60.0, "XON was sent: X-rays may be on for the whole wait", zero=True),
    # a switch-off's attempts spread over this window before the operator is told (default 3 s):
    # a supply ramps down in seconds; past a minute of "maybe on" the operator must hear of it
    "off_confirm_s": TimeLimit(
        60.0, "a switch-off not confirmed is told only after this window, the tube maybe on", zero=True
    ),
    # the driver's polls in its warm-up and ramp waits, each the reading that sees an interlock
    # opened or an overload (the L8121-02 driver's cycle reads them about every 0.25 s; default 0.2 s)
    "poll_s": TimeLimit(5.0, "an interlock opened or an overload goes unseen that long, X-rays maybe on"),
    "error_poll_s": TimeLimit(
        ERROR_POLL_MAX_S,
        "a controller fault unnoticed that long with the beam on; a unit without SER is error_query = false",
    ),
    # L8121.md: ~0.05 s between commands; every exchange waits it, a switch-off's XOF too
    "min_interval_s": TimeLimit(
        1.0,
        "the controller needs ~0.05 s between commands, and each switch-off waits this long before its XOF",
        zero=True,
    ),
}


def time_refusal(name: str, value) -> str | None:
    """What is wrong with ``value`` as the time ``name`` of :class:`SourceConfig` (a key of
    :data:`TIME_LIMITS`), or None: not a number, not finite, below 0 (or 0 where that is not a
    time), or past its bound. Said after the key (or the command line's option) and the value."""
    limit = TIME_LIMITS[name]
    if not is_number(value) or not math.isfinite(value) or value < 0 or (value == 0 and not limit.zero):
        return f"expected a finite number of seconds {'>= 0' if limit.zero else 'above 0'}"
    if value > limit.max_s:
        return f"at most {limit.max_s:g} s ({limit.why})"
    return None


def checked_time(name: str, value) -> float:
    """``value`` when :func:`time_refusal` finds nothing wrong with it as the time ``name``; else
    :class:`SettingRefused` naming the key, the value and the problem."""
    said = time_refusal(name, value)
    if said is not None:
        unit = " s" if is_number(value) and math.isfinite(value) and value > 0 else ""
        raise SettingRefused(f"{name} = {shown(value)}{unit}: {said}")
    return value if type(value) in (int, float) else float(value)  # a numpy number is not TOML's


@dataclasses.dataclass
class SourceConfig:
    """Dialect, link, ratings, tolerances and timing of one L8121 (defaults: ``L8121.md``).

    ``dialect`` is ``"A"``, ``"B"`` or ``"auto"`` (probe at connect, :func:`probe`). ``baudrate``
    ``None`` means the dialect's (9600 in both, the link default of ``L8121.md``; ``auto`` tries
    ``baudrate`` if set, then ``probe_baudrates``). ``voltage_scale`` is what a kV value is multiplied by in a command
    argument; ``None`` means the dialect's (A 1, B 10: ``PHV 600`` for 60 kV). ``min_interval_s``,
    the pause between two commands, ``None`` means the dialect's (0.06 s in both: ``L8121.md``'s
    link rule "a controller may need ~50 ms between commands" holds for both dialects, although
    the L8121-02 driver polls 20 ms apart; "~50" leaves room above 50, so 20 % is added).
    ``timeout_s``, the longest wait for a reply, ``None`` means the dialect's (2 s in both: the
    L8121-02 driver's wait before a missed reply; L8121.md gives A none). ``off_confirm_s``: how long a switch-off's
    attempts may take for ``STS`` to read off (a supply ramping down). ``ready_timeout_s``: how long
    :meth:`L8121.settled_status` (and so :meth:`L8121.warm_up` and :meth:`L8121.on`) waits for the
    controller's power-on checks to finish.

    ``kv_min``, ``kv_max``, ``ua_min``, ``ua_max`` and ``watts_max`` may only tighten
    :data:`RATINGS`; a value that would widen them is refused. Tolerances are absolute (kV, µA)
    when numbers, relative to the set value when strings such as ``"2%"``; None (the default) is
    the driver's, 1 kV and 5 µA, narrowed at a low setting (:meth:`tolerance_ua`). ``model`` is what
    dialect A's ``TYP`` must answer at connect; ``None`` (or ``""`` in TOML, which has no null)
    accepts any model. Dialect B has no identity query.

    Examples
    --------
    >>> SourceConfig.from_toml('[source]\\nkv_max = 90\\nua_tolerance = "2%"').tolerance_ua(250)
    5.0
    >>> SourceConfig(kv_max=1000)
    Traceback (most recent call last):
    ...
    acquisition.l8121.SettingRefused: L8121 configuration: kv_max = 1000 kV exceeds the L8121 rating of 150 kV; a configuration may only tighten the ratings
    """

    dialect: str = "A"
    baudrate: int | None = None
    probe_baudrates: tuple[int, ...] = (9600, 38400, 115200)
    voltage_scale: float | None = None
    model: str | None = "L8121-01"
    kv_min: float = RATINGS.kv_min
    kv_max: float = RATINGS.kv_max
    ua_min: float = 0.0
    ua_max: float = RATINGS.ua_max
    watts_max: float = RATINGS.watts_max
    # None: the driver's (_DEFAULT_TOLERANCES), narrowed at a low setting; a value written is the
    # user's, judged as given (a default equal to a written 5 was taken as unwritten, and narrowed)
    kv_tolerance: float | str | None = None
    ua_tolerance: float | str | None = None
    focus_modes: tuple[int, ...] = (0, 1, 2, 3)
    timeout_s: float | None = None
    # the probe's reply time-out at every baud rate; None: the longest dialect's (B's 2 s), so a
    # unit answering within its dialect's documented wait is found at any rate it may be set to
    probe_timeout_s: float | None = None
    min_interval_s: float | None = None
    stable_timeout_s: float = 15.0
    poll_s: float = 0.2
    warmup_timeout_s: float = 1800.0
    warmup_start_s: float = 5.0  # the start command answered, still "warm-up needed" after this: not started
    # L8121.md says XON is echoed and the measured values ramp over seconds after it, not that STS
    # reads X-rays on by the time the echo is in: standby is waited for this long after XON (the
    # interlock and an overload watched every poll) before the beam is called not come on -- as
    # off_confirm_s lets STS lag XOF. 0: at once
    xon_start_s: float = 1.0
    # the controller's power-on checks (A: STS 6 self-test; B: STS ERROR, pre-heating; either's "not
    # ready" with the interlock closed) may still run when a session starts: warm_up() and on() wait
    # this long for them to finish (L8121.md gives no duration)
    ready_timeout_s: float = 30.0
    off_attempts: int = 3
    # L8121.md does not say how soon STS reads off after XOF (a high-voltage supply ramps down): the
    # attempts spread over this window, STS asked every poll_s, before the operator is told
    off_confirm_s: float = 3.0
    beam_drop_fraction: float = 0.5
    # dialect A: STS 2 (standby) counts as warmed up only when SWE says 0 (done), as B's STANDBY
    # only with DAG's END. L8121.md does not relate A's STS and SWE; false is for a unit whose
    # SWE reads 2 ("not started") when no warm-up was needed (the configuration absorbs a unit
    # that differs, L8121.md), and then STS 2 alone lets XON go
    standby_needs_warmup_done: bool = True
    # SER is asked last before every X-ray command (L8121.md ties the code to no state, so a unit
    # may read standby with a fault standing). The notes give no unit's list of codes, so a unit
    # that reports a harmless condition there, or answers no SER at all, is absorbed here, as
    # L8121.md asks of a unit that differs: codes that still allow X-rays, and false for no SER
    allowed_error_codes: tuple[int, ...] = ()
    error_query: bool = True
    # with the beam on, SER is read at most this often, after a poll's beam checks (ERROR_POLL_S)
    error_poll_s: float = ERROR_POLL_S
    # not a field (no annotation), not configuration: the model L8121.resolved_config() put in
    # ``model`` from the probe's TYP when none was configured, so that a connect that finds
    # another says the unit changed, not "configure model=None" (which the user did)
    probed_model = None

    def __post_init__(self):
        if self.model == "":
            self.model = None
        dialect = str(self.dialect)
        self.dialect = dialect.upper() if dialect.upper() in ("A", "B") else dialect.lower()
        if self.dialect not in ("A", "B", "auto"):
            raise SettingRefused(f"dialect {dialect!r}: expected 'A', 'B' or 'auto'")
        self.focus_modes = _focus_modes(self.focus_modes)
        codes = self.allowed_error_codes
        if not isinstance(codes, (list, tuple)) or not all(type(c) is int and c > 0 for c in codes):
            raise SettingRefused(f"allowed_error_codes {codes!r}: expected a list of error codes above 0")
        self.allowed_error_codes = tuple(codes)
        if not isinstance(self.error_query, bool):
            raise SettingRefused(f"error_query {self.error_query!r}: expected true or false")
        self.probe_baudrates = tuple(_baud(b, "probe_baudrates") for b in self.probe_baudrates)
        if not self.probe_baudrates:
            raise SettingRefused("probe_baudrates is empty")
        if self.baudrate is not None:
            self.baudrate = _baud(self.baudrate, "baudrate")
        for name in (
            "kv_min",
            "kv_max",
            "ua_min",
            "ua_max",
            "watts_max",
            "beam_drop_fraction",
        ):
            setattr(self, name, _finite(getattr(self, name), name))
        if self.voltage_scale is not None:
            self.voltage_scale = _finite(self.voltage_scale, "voltage_scale")
        if self.voltage_scale == 0:
            raise SettingRefused("voltage_scale must be > 0")
        self._check_beam_drop()
        self._check_ceiling()
        if not (self.kv_min <= self.kv_max and self.ua_min <= self.ua_max):
            raise SettingRefused(f"empty range kv {self.kv_min}..{self.kv_max} or ua {self.ua_min}..{self.ua_max}")
        self._check_timeouts()
        if not isinstance(self.standby_needs_warmup_done, bool):
            raise SettingRefused(
                f"standby_needs_warmup_done must be true or false, got {self.standby_needs_warmup_done!r}"
            )
        # a true integer: int() took "3" as 3 and 2.5 as 2 attempts (is_integer refuses bools too)
        if not is_integer(self.off_attempts) or self.off_attempts < 1:
            raise SettingRefused(f"off_attempts must be a whole number >= 1, got {self.off_attempts!r}")
        if self.off_attempts > OFF_ATTEMPTS_MAX:
            raise SettingRefused(
                f"off_attempts = {self.off_attempts}: at most {OFF_ATTEMPTS_MAX} (each waits up to two replies, XOF's "
                "and STS's, before the operator hears that the switch-off failed)"
            )
        self.off_attempts = int(self.off_attempts)  # a numpy integer is not TOML's
        self.tolerance_kv(100.0), self.tolerance_ua(100.0)  # validates both
        self._check_given_tolerances()

    def _check_given_tolerances(self) -> None:
        """A tolerance given here that no setting this configuration allows could honour: judged at
        the one with the most room (the highest voltage and current allowed; a percentage is the
        same at every setting). The defaults are not the user's, and are not judged here:
        ``ua_max = 8`` alone was refused for the default 5 µA (review s42rr2). Every tolerance,
        given, is judged at the setting itself as it is made (:meth:`L8121.on`,
        :meth:`L8121.set_values`; a protocol at its own, ``_check_source``), a default narrowed
        there where it is too wide: judged here at ``kv_min``, 25 kV was refused for a unit run at
        60 kV (s43)."""
        given = [key for key in _DEFAULT_TOLERANCES if getattr(self, key) is not None]
        ua_hi = min(self.ua_max, RATINGS.ua_max)
        self.check_tolerances(min(self.kv_max, RATINGS.kv_max), ua_hi if ua_hi > 0 else None, keys=given)

    def _check_beam_drop(self) -> None:
        """L8121.md: stop the series on a dropped beam. 0 never called one dropped (a beam gone to
        nothing with STS still on passed every poll); 1 or more called every beam dropped."""
        if not 0 < self.beam_drop_fraction < 1:
            raise SettingRefused(
                f"beam_drop_fraction = {self.beam_drop_fraction!r}: expected a fraction "
                "above 0 and below 1 (of the set current or voltage, below which the beam counts as dropped)"
            )

    def _check_timeouts(self) -> None:
        """Every time within :data:`TIME_LIMITS` (None: the dialect's). Zero is refused where it
        is no time at all: a zero warm-up or stable time-out would switch the tube on only to
        switch it off again."""
        for name in TIME_LIMITS:
            if getattr(self, name) is not None:
                setattr(self, name, checked_time(name, getattr(self, name)))

    def _check_ceiling(self) -> None:
        r = RATINGS
        for name, value, rating, unit, above in (
            ("kv_min", self.kv_min, r.kv_min, "kV", False),
            ("kv_max", self.kv_max, r.kv_max, "kV", True),
            ("ua_max", self.ua_max, r.ua_max, "µA", True),
            ("watts_max", self.watts_max, r.watts_max, "W", True),
        ):
            if (value > rating) if above else (value < rating):
                raise SettingRefused(
                    f"{name} = {shown(value)} {unit} "
                    f"{'exceeds' if above else 'is below'} the L8121 rating of {rating:g} {unit}; "
                    f"a configuration may only tighten the ratings"
                )

    def check_exposure(self, voltage_kv: float, current_ua: float) -> None:
        """Refuse an exposure outside this configuration or the ratings; nothing is sent.

        The limits are this configuration's, each capped by :data:`RATINGS` (so even a
        configuration changed after construction cannot raise them).

        Raises
        ------
        ValueError
            Not a finite number, outside ``kv_min..kv_max`` or ``ua_min..ua_max``, or
            ``voltage_kv * current_ua / 1000`` above ``watts_max``; the message names the
            parameter and the limit.
        """
        for name, value, unit in (("voltage_kv", voltage_kv, "kV"), ("current_ua", current_ua, "µA")):
            if not is_number(value):
                raise SettingRefused(f"{name} must be a number of {unit}, got {value!r}", of="L8121")
            if not math.isfinite(value):
                raise SettingRefused(f"{name} must be finite, got {value!r} {unit}", of="L8121")
        r = RATINGS
        kv_lo, kv_hi = max(self.kv_min, r.kv_min), min(self.kv_max, r.kv_max)
        ua_lo, ua_hi = max(self.ua_min, 0.0), min(self.ua_max, r.ua_max)
        if not kv_lo <= voltage_kv <= kv_hi:
            raise SettingRefused(
                f"voltage_kv = {shown(voltage_kv)} kV is outside kv_min..kv_max = "
                f"{shown(kv_lo, voltage_kv)}..{shown(kv_hi, voltage_kv)} kV",
                of="L8121",
            )
        if not ua_lo <= current_ua <= ua_hi:
            raise SettingRefused(
                f"current_ua = {shown(current_ua)} µA is outside ua_min..ua_max = "
                f"{shown(ua_lo, current_ua)}..{shown(ua_hi, current_ua)} µA",
                of="L8121",
            )
        watts, w_hi = voltage_kv * current_ua / 1000, min(self.watts_max, r.watts_max)
        if watts > w_hi:
            raise SettingRefused(
                f"{shown(voltage_kv)} kV x {shown(current_ua)} µA = {shown(watts, w_hi)} W "
                f"exceeds watts_max = {shown(w_hi, watts)} W",
                of="L8121",
            )

    def check_tolerances(self, set_kv: float | None, set_ua: float | None, keys=("kv_tolerance", "ua_tolerance")):
        """Refuse a tolerance (of ``keys``) wider than ``1 - beam_drop_fraction`` of its set value
        (None: not checked). L8121.md calls the beam stable when the measured values are within
        tolerance of the set ones; the beam monitor calls it dropped below ``beam_drop_fraction``
        of them. A wider tolerance counts a beam the monitor calls dropped as stable (1000 kV:
        any beam, none included). A default is never refused: :meth:`tolerance_ua` narrows it."""
        room = 1 - self.beam_drop_fraction
        for key, spec, set_value, unit in (
            ("kv_tolerance", self.kv_tolerance, set_kv, "kV"),
            ("ua_tolerance", self.ua_tolerance, set_ua, "µA"),
        ):
            if key not in keys or set_value is None:
                continue
            tol = self._tolerance_at(key, spec, set_value)
            if tol > room * abs(set_value):
                raise SettingRefused(
                    f"{key} = {spec!r}: {shown(tol, room * abs(set_value))} {unit} at {shown(set_value)} {unit} counts as "
                    f"stable a beam the monitor calls dropped (below beam_drop_fraction = {self.beam_drop_fraction:g} "
                    f"of the set value): expected at most {room:.0%} of the set value, {shown(room * abs(set_value), tol)} {unit}"
                )

    def _tolerance_at(self, key: str, spec: float | str | None, set_value: float) -> float:
        if spec is not None:
            return _tolerance(spec, set_value, key)
        tol = _DEFAULT_TOLERANCES[key]
        room = (1 - self.beam_drop_fraction) * abs(set_value)
        if tol > room:
            # the default 5 µA is wider than the monitor's drop bound under 10 µA; refusing it left
            # `source on --ua 8` no way through (the command takes no tolerance), so a tolerance
            # nobody wrote is narrowed to half that room: a stable beam stays apart from a dropped
            # one. Not finer than a reading's step, though (whole kV and µA, L8121.md): 0.5 µA at
            # 2 µA never let a meter one count high read stable (review s43rr2). Never past the room
            return min(room, max(room / 2, _READING_STEP))
        return tol

    def tolerance_kv(self, set_kv: float) -> float:
        """The kV tolerance, absolute, around ``set_kv``."""
        return self._tolerance_at("kv_tolerance", self.kv_tolerance, set_kv)

    def tolerance_ua(self, set_ua: float) -> float:
        """The µA tolerance, absolute, around ``set_ua``: the default 5 µA, or a quarter of the set
        value where that is less (under 10 µA with ``beam_drop_fraction = 0.5``), but not under a
        reading's step, 1 µA, where half the set value allows it (2 and 3 µA).

        >>> SourceConfig().tolerance_ua(250), SourceConfig().tolerance_ua(8), SourceConfig().tolerance_ua(2)
        (5.0, 2.0, 1.0)
        """
        return self._tolerance_at("ua_tolerance", self.ua_tolerance, set_ua)

    @classmethod
    def from_dict(cls, mapping: Mapping[str, Any]) -> SourceConfig:
        """Build from a mapping; an unknown key is an error that names it and the known keys."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(mapping) - known)
        if unknown:
            raise SettingRefused(f"unknown key(s) {unknown}; known: {sorted(known)}")
        return cls(**mapping)

    @classmethod
    def from_toml(cls, source: str | Path, section: str = "source") -> SourceConfig:
        """Read the ``[section]`` table (dotted for nested tables) of a TOML file or TOML text.

        The link's ``url`` may sit in the same table; it is ignored here (see
        :meth:`L8121.from_config`).
        """
        table = _toml_section(source, section)
        return cls.from_dict({k: v for k, v in table.items() if k != "url"})

    def to_dict(self) -> dict[str, Any]:
        """The configuration as a TOML-friendly dict (``model=None`` becomes ``""``; unset
        ``baudrate`` and ``voltage_scale`` are left out)."""
        d = dataclasses.asdict(self)
        d["model"] = d["model"] or ""
        d["focus_modes"] = list(d["focus_modes"])
        d["probe_baudrates"] = list(d["probe_baudrates"])
        d["allowed_error_codes"] = list(d["allowed_error_codes"])
        return {k: v for k, v in d.items() if v is not None}


def _finite(value, name: str) -> float:
    if not is_number(value) or not math.isfinite(value) or value < 0:
        raise SettingRefused(f"{name} must be a finite number >= 0, got {value!r}")
    return value if type(value) in (int, float) else float(value)  # a numpy number is not TOML's


#: The rates L8121.md's link section lists for the controller. Another is used as configured, with
#: a warning: L8121.md says no manual of the L8121-01 exists and that a unit that differs is the
#: configuration's to absorb (a refusal stopped even `acquire source off` reaching such a unit)
BAUDRATES = (9600, 38400, 115200)


def _baud(value, name: str) -> int:
    if not is_integer(value) or value <= 0:
        raise SettingRefused(f"{name} = {value!r}: expected a whole number of baud > 0")
    if value not in BAUDRATES:
        logger.warning(
            "L8121 configuration: %s = %s is not a rate L8121.md lists (%s): used as configured",
            name,
            value,
            ", ".join(map(str, BAUDRATES)),
        )
    return int(value)  # a numpy integer is not TOML's


def _focus_modes(modes) -> tuple:
    """``focus_modes`` as a tuple of Python ints: whole numbers only, each (int() took "1" and 1.5
    as mode 1, and a string "0123" as four modes)."""
    if isinstance(modes, (str, bytes)) or not isinstance(modes, Iterable):
        raise SettingRefused(f"focus_modes must be a list of whole numbers >= 0, got {modes!r}")
    modes = list(modes)  # read twice below: a generator would be empty the second time
    if not all(is_integer(m) and m >= 0 for m in modes):
        raise SettingRefused(f"focus_modes must hold whole numbers >= 0, got {modes!r}")
    return tuple(int(m) for m in modes)  # a numpy integer is not TOML's


#: the tolerances a configuration has when none is written (None; :meth:`SourceConfig.tolerance_ua`
#: narrows them at a low setting)
_DEFAULT_TOLERANCES = {"kv_tolerance": 1.0, "ua_tolerance": 5.0}
#: a fault's note when its switch-off was not confirmed (:attr:`OffOutcome.note`; the command line
#: words its own line from the outcome's fields)
OFF_NOT_CONFIRMED = "switching X-rays off could not be confirmed"


def _not_remote(switch: str) -> str:
    """What a switch-off's error adds for B's operate switch at ``switch`` (not REMOTE)."""
    return f"; the operate switch is {switch} (SRL): remote commands are refused until it is turned to REMOTE"


#: the step of a measured kV and µA (A's SAR reads whole numbers; B's SCU whole µA): a narrowed
#: default tolerance is no finer, where the room allows
_READING_STEP = 1.0


def _tolerance(spec: float | str, set_value: float, name: str) -> float:
    if isinstance(spec, str):
        m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?|\.[0-9]+)\s*%\s*", spec)  # "1.2.3%" was float()'s traceback
        if not m:
            raise SettingRefused(f"{name} {spec!r} is neither a number nor a percentage like '2%'")
        return abs(set_value) * float(m.group(1)) / 100
    if not is_number(spec) or not 0 <= spec < math.inf:  # inf: any beam, even none, counts as stable
        raise SettingRefused(f"{name} must be a finite number >= 0, got {spec!r}")
    return float(spec)


def names_file(text: str) -> bool:
    """Whether ``text`` is the path of an existing file (a name too long or holding NUL is not)."""
    try:
        return Path(text).is_file()
    except (OSError, ValueError):
        return False


def _toml_section(source: str | Path, section: str) -> dict:
    text = source
    # a one-line string is a file when it has no "=" or names an existing one (runs/kv=60/source.toml)
    if isinstance(source, Path) or ("\n" not in source and ("=" not in source or names_file(source))):
        text = Path(source).read_text(encoding="utf-8")
    try:
        table: Any = toml_loads(text)
    except tomllib.TOMLDecodeError as exc:  # names no file: this reader's refusal does (s52)
        raise ValueError(f"{source if text is not source else 'TOML text'}: not TOML: {exc}") from None
    for part in section.split(".") if section else ():
        if not isinstance(table, dict) or part not in table:
            raise ValueError(f"{source if text is not source else 'TOML text'}: no [{section}] table")
        table = table[part]
    return dict(table)


# -- reply fields ---------------------------------------------------------------------------------
def _integer(text: str) -> int:
    if not re.fullmatch(r"[+-]?\d+", text):
        raise ValueError(f"{text!r} is not an integer")
    return int(text)


def _number(text: str) -> float:
    value = float(text)  # ValueError names the text
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a finite number")
    return value


def _closed_if_zero(text: str) -> bool:
    """Dialect A's ``SIN``: 0 closed (True), 1 open (False)."""
    if text not in ("0", "1"):
        raise ValueError(f"{text!r} is neither 0 nor 1")
    return text == "0"


def _flag(text: str) -> bool:
    if text not in ("0", "1"):
        raise ValueError(f"{text!r} is neither 0 nor 1")
    return text == "1"


def _enum(enum: type[IntEnum], allowed: range | None = None) -> Callable[[str], IntEnum]:
    def parse(text: str) -> IntEnum:
        value = _integer(text)
        if allowed is not None and value not in allowed:
            raise ValueError(f"{value} is not a known {enum.__name__}")
        try:
            return enum(value)
        except ValueError:
            raise ValueError(f"{value} is not a known {enum.__name__}") from None

    parse.__name__ = enum.__name__
    return parse


def _words(mapping: Mapping[str, Any]) -> Callable[[str], Any]:
    """A reply that is one of a few words (dialect B: ``STANDBY``, ``INTER LOCK ON``, ``REMOTE``)."""

    def parse(text: str) -> Any:
        key = " ".join(text.split())
        if key not in mapping:
            raise ValueError(f"{text!r} is none of {', '.join(mapping)}")
        return mapping[key]

    return parse


def _with_unit(unit: str) -> Callable[[str], float]:
    """Dialect B's measured values: ``60.0kV``, ``250uA`` (``µA`` and a space before the unit accepted)."""
    units = {"uA": "(?:uA|µA)"}.get(unit, re.escape(unit))
    # any case: the transport reads every reply in upper case (60.0KV), a unit may write kV
    pattern = re.compile(rf"([+-]?\d+(?:\.\d*)?)\s*{units}", re.IGNORECASE | re.ASCII)

    def parse(text: str) -> float:
        m = pattern.fullmatch(text.strip())
        if not m:
            raise ValueError(f"{text!r} is not a number of {unit}")
        return float(m.group(1))

    return parse


def _aging(text: str) -> Aging:
    m = re.fullmatch(r"AGING\s+(\d+)\s+(\d+)\s+(END|YET)", text.strip())
    if not m:
        raise ValueError(f"{text!r} is not 'AGING <mode> <step> END|YET'")
    return Aging(int(m.group(1)), int(m.group(2)), m.group(3) == "END")


def _beam_above(kv: float, ua: float, set_kv: float, set_ua: float, drop_fraction: float) -> str | None:
    """What a measured beam exceeds its setting by, as far past it as the drop bound is below it
    (``2 - drop_fraction`` of the set value, and a reading's step), or None. L8121.md calls only an
    overload state a fault; a regulator running the beam away while STS still reads XON was
    exposed on (review s47acq: 144 kV 600 µA at a set 60 kV 250 µA, past the 75 W rating)."""
    bound = 2 - drop_fraction
    if ua > bound * set_ua + _READING_STEP:
        return f"measured current {ua:g} µA, above {bound:.0%} of the set {set_ua} µA"
    if kv > bound * set_kv + _READING_STEP:
        return f"measured voltage {kv:g} kV, above {bound:.0%} of the set {set_kv} kV"
    return None


def _fallen_back(
    kv: float,
    ua: float,
    highest: tuple[float, float],
    tolerance: tuple[float, float],
    low: tuple[float, float],
    drop_fraction: float,
) -> str | None:
    """What shows a beam that fell back while it ramped (``highest``: the readings' highest so far
    in the ramp; ``low``: the lower of the setting and the one it ramps from; ``tolerance``: the
    one at the higher of the two, where a reading jitters most), or None.

    L8121.md: the measured values "ramp towards the set values" after XON or a change, so a ramp
    stays between the two settings. A reading may lie up to a tolerance either side of the tube's
    value (a beam whose readings do is stable), so one falls back from one before it by up to
    twice the tolerance with nothing changed in the beam: by one tolerance, a noisy meter at a
    low current (10 µA, 2.5 µA: readings 3 then 0 on a ramp through 1 and 2 µA) was called
    dropped (review s54rv). One that fell back further AND lies under the beam monitor's
    drop bound (``drop_fraction`` of the lower setting: what :meth:`L8121.check` calls dropped
    once the beam is stable) is a dropped beam, not a ramp still climbing: B's STS reads XON all
    the while (it names no dropped beam), and only the stable wait's time-out caught it, up to
    ``stable_timeout_s`` later. Both conditions: the two tolerances keep a reading's jitter from
    tripping, the bound a ramp that overshoots and settles. After XON the ramp starts from
    nothing, and ``highest`` counts every reading. After a setting changed while on, L8121.md
    leaves open where the ramp starts (a unit that ramps again from zero reads a fall from the
    old setting first, review s54rvsig), so ``highest`` counts a value only from when it has
    climbed more than two tolerances above its lowest reading (-inf before): a ramp of either
    kind climbs to the setting from there (:class:`_RampWatch`)."""
    for value, top, tol, setting, unit, what in (
        (ua, highest[1], tolerance[1], low[1], "µA", "current"),
        (kv, highest[0], tolerance[0], low[0], "kV", "voltage"),
    ):
        if value < drop_fraction * setting and top - value > 2 * tol:
            return (
                f"measured {what} {value:g} {unit} after {top:g} {unit}, below {drop_fraction:.0%} of the set "
                f"{setting} {unit}"
            )
    return None


class _RampWatch:
    """The judgement of a beam ramping to a setting, reading by reading: after XON (``after_xon``)
    or after a change while on (:meth:`L8121.set_values`), where its wait and a beam monitor's
    :meth:`L8121.check` in another thread feed it their readings (a lock: one reading at a time).

    ``lower``, ``higher``: the lower and the higher of the old and the new setting (after XON
    both the setting); ``jitter``: a reading's jitter, a tolerance (:meth:`L8121._watch_ramp`);
    ``dwell_s``: per kV and µA, the longest time a healthy ramp of this unit reads under the drop
    bound (``drop_fraction`` of ``lower``) after a change (inf: no bound).

    :meth:`see` names the first of, or returns None:

    - a beam above the setting (:func:`_beam_above`, by ``higher``): a ramp never passes it by the
      drop bound's margin;
    - a value that fell back after climbing (:func:`_fallen_back`). After XON the ramp starts
      from nothing, so every reading counts. After a change, L8121.md does not say where the ramp
      starts: a unit may ramp again from zero (tests/l8121_second_reading.py reads it so), its
      values falling from the old setting first -- every change while on was switched off as a
      dropped beam when a fall from the old setting counted (review s54rv). Either way the ramp,
      once it climbs, climbs to the setting: a value counts from when it has risen more than two
      jitters above its lowest reading;
    - after a change, a value under the drop bound for longer than ``dwell_s`` (plus two of the
      longest gaps between readings so far: a reading shows the beam only when taken). A change
      down (250 -> 100 µA) or of the other value (the voltage alone) whose beam drops reads no
      climb: before, only the stable wait's time-out caught it (up to ``stable_timeout_s``, 15 s
      by default, with the tube on), since a fall may be the start of a ramp from zero. The count
      starts again while the value still falls (by more than two jitters since it started, or a
      quarter of that value at a low one: a unit falling to nothing, at a speed L8121.md does not
      give), and ends at a reading at or over
      the bound (a ramp from zero crosses it once, upward)."""

    def __init__(self, lower, higher, jitter, drop_fraction: float, *, after_xon: bool, dwell_s):
        self._lock = threading.Lock()
        self.lower, self.higher, self.jitter = tuple(lower), tuple(higher), tuple(jitter)
        self.drop_fraction, self.after_xon, self.dwell_s = drop_fraction, after_xon, tuple(dwell_s)
        self.highest = (-math.inf, -math.inf)  # the readings' highest in this ramp
        self.lowest = (math.inf, math.inf)  # their lowest
        self.climbed = (-math.inf, -math.inf)  # their highest once climbed two jitters (-inf: not yet)
        # the count of a run of readings under the drop bound: when it (re)started, and the value then
        self.under_since: list[float | None] = [None, None]
        self.under_from = [math.inf, math.inf]
        self._last: float | None = None
        self.gap = 0.0  # the longest time between two readings

    def see(self, kv: float, ua: float, now: float) -> str | None:
        """Judge a reading (NaN: not read, left out) taken at ``now`` (``time.monotonic()``); one
        taken before a reading already judged, above the setting only."""
        with self._lock:
            above = _beam_above(kv, ua, *self.higher, self.drop_fraction)
            if above is not None:
                return f"beam above the setting: {above}"
            if self._last is not None and now < self._last:
                # read before one already judged (the other thread's, judged first): its values are
                # the past of the ramp. As the latest, a climb's start read after its later values
                # was called a fall ("measured current 39 µA after 72 µA", review s56rvacq)
                return None
            if self._last is not None:
                self.gap = max(self.gap, now - self._last)
            self._last = now
            values = (kv, ua)
            self.highest = tuple(max(top, v) for top, v in zip(self.highest, values))
            self.lowest = tuple(min(low, v) for low, v in zip(self.lowest, values))
            self.climbed = tuple(
                max(top, v) if top > -math.inf or v > low + 2 * tol else top
                for top, v, low, tol in zip(self.climbed, values, self.lowest, self.jitter)
            )
            fell = _fallen_back(
                kv, ua, self.highest if self.after_xon else self.climbed, self.jitter, self.lower, self.drop_fraction
            )
            if fell:
                return f"beam dropped while ramping up: {fell}"
            return None if self.after_xon else self._stayed_under(values, now)

    def _stayed_under(self, values, now: float) -> str | None:
        for i, (v, low, allowed, unit, what) in enumerate(
            zip(values, self.lower, self.dwell_s, ("kV", "µA"), ("voltage", "current"))
        ):
            bound = self.drop_fraction * low
            if not v < bound:  # (NaN: not read, the count goes on)
                if not math.isnan(v):
                    self.under_since[i] = None
                continue
            start = self.under_from[i]
            if self.under_since[i] is None or v < start - min(2 * self.jitter[i], max(_READING_STEP / 2, start / 4)):
                # (again while it still falls, by more than a reading's jitter: a fall under way,
                # of a unit that falls to nothing before its ramp from zero, not a beam stopped.
                # Low down, by a quarter of where it started again, or a reading's step there:
                # two jitters at the higher setting (2 x 5 µA) are the whole drop bound at 10 µA,
                # and a fall from 5 µA to nothing counted as a beam stopped there, called dropped
                # where the same fall from 250 µA was not (review s56rvacq). A quarter each time
                # still bounds how often a value stuck under the bound starts again: a few times,
                # the meter's flicker at its level smaller than that, then a step is more)
                self.under_since[i], self.under_from[i] = now, v
            under = now - self.under_since[i]
            if under > allowed + 2 * self.gap:
                return (
                    f"beam dropped during the change: measured {what} {v:g} {unit}, below "
                    f"{self.drop_fraction:.0%} of the set {low} {unit} for {under:.2f} s, longer than a ramp of this "
                    f"unit stays there ({allowed:.2f} s, from its ramp after XON)"
                )
        return None


# -- the declarations -----------------------------------------------------------------------------
class Query:
    """A query: ``command`` and the parser of its reply.

    Parameters
    ----------
    command : str
        The query, e.g. ``"SAR"``.
    *fields : callable
        One parser per reply field (``str -> value``, raising ``ValueError`` on bad text). A single
        field gives a value, several a tuple.
    echo : bool
        The reply starts with the command (``SAR 3 60 250 ...``); dialect B's ``STS``, ``SIN``,
        ``DAG``, ``SRL`` do not echo (``STANDBY``, ``INTER LOCK ON``).
    extra : bool
        Accept (and drop) further fields after the declared ones (``SAR``'s trailing zeros).
    rest : bool
        The last field takes the rest of the reply, spaces included (``TYP``'s model name,
        ``NOT READY``).
    error_is_value : bool
        ``ERROR`` is an answer, not a refusal (dialect B's ``STS``).
    doc : str
        What the reading is.
    """

    def __init__(
        self,
        command: str,
        *fields: Callable[[str], Any],
        echo: bool = True,
        extra: bool = False,
        rest: bool = False,
        error_is_value: bool = False,
        doc: str | None = None,
    ):
        self.command, self.fields, self.echo, self.extra, self.rest = command, fields, echo, extra, rest
        self.error_is_value = error_is_value
        self.__doc__ = doc

    def parse(self, reply: str) -> Any:
        """The value(s) in ``reply``; ``ValueError`` says why ``reply`` is not a valid answer."""
        words = reply.split()
        if self.echo:
            if not words or words[0] != self.command:
                raise ValueError(f"the reply does not start with {self.command}")
            words = words[1:]
        values, n = words, len(self.fields)
        if self.rest and len(values) >= n:
            values = values[: n - 1] + [" ".join(values[n - 1 :])]
        if len(values) < n or (len(values) > n and not self.extra):
            raise ValueError(f"expected {n} field(s){' after ' + self.command if self.echo else ''}, got {len(values)}")
        out = tuple(parse(v) for parse, v in zip(self.fields, values))
        return out[0] if n == 1 else out

    def __repr__(self) -> str:
        return f"Query({self.command!r})"


class Command:
    """A command the controller echoes, e.g. ``XON`` or ``HIV 60``.

    Parameters
    ----------
    command : str
        The command word.
    argument : callable, optional
        ``argument(driver, value) -> int``: validates the value (``ValueError`` naming the limit)
        and returns what is sent. ``None``: the command takes no argument.
    doc : str
        What it does.
    """

    def __init__(self, command: str, argument: Callable[[Any, Any], int] | None = None, doc: str | None = None):
        self.command, self.argument = command, argument
        self.__doc__ = doc

    def line(self, driver, value=None) -> str:
        """The line to send, after validating ``value``."""
        if self.argument is None:
            if value is not None:
                raise TypeError(f"{self.command} takes no argument, got {value!r}")
            return self.command
        return f"{self.command} {self.argument(driver, value)}"

    @staticmethod
    def is_echo(line: str, reply: str) -> bool:
        """Whether ``reply`` echoes ``line`` (numbers compared as numbers: ``HIV 060`` echoes ``HIV 60``)."""
        sent, got = line.split(), reply.split()
        if len(sent) != len(got) or sent[0] != got[0]:
            return False
        for a, b in zip(sent[1:], got[1:]):
            try:
                if _integer(a) != _integer(b):
                    return False
            except ValueError:
                return False
        return True

    def __repr__(self) -> str:
        return f"Command({self.command!r})"


class Choice(Command):
    """A setting sent as one of several argument-less commands (dialect B's focus: ``CFS``,
    ``CFM``, ``CFL``), chosen by value."""

    def __init__(self, choices: Mapping[int, str], doc: str | None = None):
        super().__init__("/".join(choices.values()), None, doc)
        self.choices = dict(choices)

    def line(self, driver, value=None) -> str:
        # a whole number, as dialect A's CFS n takes: 1.0 == 1 found the dict key, and B sent CFM
        if not is_integer(value) or value not in self.choices or value not in driver.config.focus_modes:
            allowed = tuple(v for v in self.choices if v in driver.config.focus_modes)
            raise ValueError(f"focus mode must be one of {allowed} (focus_modes, and {self.command}), got {value!r}")
        return self.choices[value]


def _whole(value: Any, what: str, unit: str) -> int:
    """Whole kV and µA, rounded half up, and said so in the log: dialect A's ``HIV``/``CUR`` take
    integers (L8121.md); B's voltage is in 0.1 kV units, but one setting for both dialects keeps a
    series' recorded values the same whichever the unit speaks."""
    whole = math.floor(value + 0.5)
    if whole != value:
        logger.warning(
            "%s %g %s rounded to %d %s: radiokit sets whole %s (dialect A's commands take integers)",
            what,
            value,
            unit,
            whole,
            unit,
            unit,
        )
    return whole


def _kv_argument(driver: L8121, value) -> int:
    """Whole kV within the limits, times the voltage scale (A 1: ``HIV 60``; B 10: ``PHV 600``)."""
    kv = _whole(value, "tube voltage", "kV")
    driver.config.check_exposure(kv, driver.config.ua_min)
    return round(kv * driver.voltage_scale)


def _ua_argument(driver: L8121, value) -> int:
    ua = _whole(value, "tube current", "µA")
    driver.config.check_exposure(max(driver.config.kv_min, RATINGS.kv_min), ua)
    return ua


def _focus_argument(driver: L8121, value) -> int:
    if not is_integer(value) or value not in driver.config.focus_modes:
        raise ValueError(f"focus mode must be one of focus_modes = {driver.config.focus_modes}, got {value!r}")
    return value


# -- the two dialects -----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Dialect:
    """One command dialect of the controller: the same readings and settings, other commands.

    ``readings`` and ``settings`` map the driver's names to declarations; a name a dialect lacks
    is simply absent. ``poll`` is what :meth:`L8121.check` reads while X-rays are on.
    """

    name: str
    baudrate: int
    voltage_scale: float
    min_interval_s: float
    timeout_s: float
    readings: Mapping[str, Query]
    settings: Mapping[str, Command]
    poll: tuple[str, ...]
    evidence: str

    def __repr__(self) -> str:
        return f"Dialect({self.name!r})"

    @property
    def late_barriers(self) -> tuple[str, ...]:
        """The queries a transport may send as a barrier
        (:attr:`acquisition.transport.SerialTransport.late_barriers`), those whose reply may read
        ``ERROR`` as a value last (B's ``STS``, pre-heating): an ``ERROR`` fits every command, and
        tells nothing apart -- first of B's readings, ``STS`` was the barrier of every other B
        query, waited for to no purpose while the unit pre-heated (review s56rvtx)."""
        queries = sorted(self.readings.values(), key=lambda query: query.error_is_value)
        return tuple(query.command for query in queries)

    def reply_fits(self, line: str, reply: str) -> bool:
        """Whether ``reply`` can be this dialect's answer to the command ``line``: a query's
        reply parses (``STS`` -> ``STS 2`` in A, ``STANDBY`` in B), a command's echoes it, and a
        refusal (``ERR``, ``ERROR``) fits any. What :class:`~acquisition.transport.SerialTransport`
        asks after a time-out, to tell the late reply of the command that timed out from the
        reply of the one it sent next (``L8121.md``: one command, one reply, in order). A command
        the dialect does not know fits anything (no opinion)."""
        if reply in ("ERR", "ERROR"):
            return True
        word = (line.split() or [""])[0]
        for query in self.readings.values():
            if query.command == word:
                try:
                    query.parse(reply)
                    return True
                except ValueError:
                    return False
        for command in self.settings.values():
            words = command.choices.values() if isinstance(command, Choice) else (command.command,)
            if word in words:
                return Command.is_echo(line, reply)
        return True

    def focus_modes(self, config: SourceConfig) -> tuple[int, ...]:
        """The focus modes ``config`` allows that this dialect can set (B has three commands)."""
        focus = self.settings["focus"]
        return tuple(m for m in config.focus_modes if not isinstance(focus, Choice) or m in focus.choices)


_STATES_A = _enum(SourceState, range(7))
_STATES_B = _words(
    {
        "STANDBY": SourceState.STANDBY,
        "XON": SourceState.XRAY_ON,
        "AGING": SourceState.WARMING_UP,
        "OVER": SourceState.OVERLOAD,
        "NOT READY": SourceState.NOT_READY,
        "ERROR": SourceState.PREHEATING,
    }
)
_FOCUS_B = {0: "SMALL", 1: "MIDDLE", 2: "LARGE"}

DIALECT_A = Dialect(
    name="A",
    # L8121.md: "default 9600" under Link, whose rules "hold for both dialects"
    baudrate=9600,
    voltage_scale=1,
    # L8121.md: "a controller may need ~50 ms between commands"; at exactly 50 ms a unit that
    # needs a little more (55 ms is "~50") loses commands, so the spacing has a margin
    min_interval_s=0.06,
    # L8121.md gives dialect A no reply time; B's driver, for the same source family, waits 2 s
    # before it calls a reply missed. 1 s read an A unit answering in 1.5 s, within what the notes
    # document for the family, as silent (the connect failed, and its switch-off could not be
    # confirmed); a unit slower still is [source] timeout_s (at most REPLY_TIMEOUT_MAX_S)
    timeout_s=2.0,
    evidence="public drivers for the L9181, L9181-02, L9191, L9421 and C8033 controllers",
    readings={
        "identity": Query("TYP", str, rest=True, doc="The controller's model (TYP L8121-01)."),
        "state": Query("STS", _STATES_A, doc="STS n: 0 warm-up needed ... 6 self-test."),
        "beam": Query(
            "SAR",
            _STATES_A,
            _number,
            _number,
            extra=True,
            doc="State, measured kV and µA in one exchange (SAR n kV uA 0 0 0 0).",
        ),
        "setpoint": Query("SVI", _number, _number, doc="Set kV and µA (SVI kV uA)."),
        "voltage_kv": Query("SHV", _number, doc="Measured tube voltage, kV (SHV 60)."),
        "current_ua": Query("SCU", _number, doc="Measured tube current, µA (SCU 250)."),
        "interlock_closed": Query("SIN", _closed_if_zero, doc="Interlock: SIN 0 closed, SIN 1 open."),
        "warmup": Query("SWE", _enum(WarmupState), doc="Warm-up: SWE 0 done, 1 running, 2 not started."),
        "preheating": Query("SPH", _flag, doc="SPH 1 while pre-heating."),
        "error": Query("SER", _integer, doc="Controller error code (SER n), 0 none."),
        "focus": Query("SFC", _integer, doc="Focus mode in use (SFC n)."),
    },
    settings={
        "voltage": Command("HIV", _kv_argument, doc="Tube voltage, whole kV (HIV 60)."),
        "current": Command("CUR", _ua_argument, doc="Tube current, whole µA (CUR 250)."),
        "preset_voltage": Command("HIV", _kv_argument, doc="Dialect A has no presets: HIV while off too."),
        "preset_current": Command("CUR", _ua_argument, doc="Dialect A has no presets: CUR while off too."),
        "xray_on": Command("XON", doc="X-rays on; refused unless standby with the interlock closed."),
        "xray_off": Command("XOF", doc="X-rays off; always accepted."),
        "warm_up": Command("WUP", doc="Start the warm-up sequence."),
        "reset": Command("RST", doc="Reset after an overload (never sent automatically)."),
        "focus": Command("CFS", _focus_argument, doc="Focus mode (CFS n)."),
    },
    poll=("beam", "interlock_closed"),
)

DIALECT_B = Dialect(
    name="B",
    baudrate=9600,
    voltage_scale=10,
    # not the L8121-02 driver's 20 ms: L8121.md's link rule (~50 ms, with A's margin) holds for both dialects
    min_interval_s=0.06,
    # L8121.md: the L8121-02 driver "treats 2 s without a reply as a missed reply"; a unit that
    # answers in 1.5 s is within what that driver allows and must not read as a silent controller
    timeout_s=2.0,
    evidence="a public Windows driver for the L8121-02 controller",
    readings={
        "state": Query(
            "STS",
            _STATES_B,
            echo=False,
            rest=True,
            error_is_value=True,
            doc="STS: STANDBY, XON, AGING (warming up: X-rays on), OVER, NOT READY, ERROR (pre-heating).",
        ),
        "voltage_kv": Query("SHV", _with_unit("kV"), rest=True, doc="Measured tube voltage (SHV 60.0kV)."),
        "current_ua": Query("SCU", _with_unit("uA"), rest=True, doc="Measured tube current (SCU 250uA)."),
        "set_voltage_kv": Query("SPV", _with_unit("kV"), rest=True, doc="Preset voltage (SPV 60.0kV)."),
        "set_current_ua": Query("SPC", _with_unit("uA"), rest=True, doc="Preset current (SPC 250uA)."),
        "interlock_closed": Query(
            "SIN",
            _words({"INTER LOCK ON": True, "INTER LOCK OFF": False}),
            echo=False,
            rest=True,
            doc="INTER LOCK ON (closed, safe) or INTER LOCK OFF (open).",
        ),
        "warmup": Query("DAG", _aging, echo=False, rest=True, doc="AGING m s END|YET: warm-up mode, step, done."),
        "error": Query("SER", _integer, doc="Control-board error (SER n): 0 none, 1-4 relay or internal faults."),
        "focus": Query(
            "SFS",
            _words({v: k for k, v in _FOCUS_B.items()}),
            echo=False,
            doc="SMALL, MIDDLE or LARGE (read as 0, 1, 2).",
        ),
        "operate_switch": Query(
            "SRL",
            _words({w: w for w in ("OFF", "REMOTE", "LOCAL")}),
            echo=False,
            doc="Operate switch: OFF, REMOTE or LOCAL; remote control needs REMOTE.",
        ),
        "remote_state": Query(
            "SRB", _words({w: w for w in ("READY", "BUSY")}), echo=False, doc="Remote operation: READY or BUSY."
        ),
    },
    settings={
        "voltage": Command("HIV", _kv_argument, doc="Tube voltage while X-rays are on, kV x voltage_scale."),
        "current": Command("CUR", _ua_argument, doc="Tube current while X-rays are on, µA."),
        "preset_voltage": Command("PHV", _kv_argument, doc="Preset voltage while X-rays are off (PHV 600: 60 kV)."),
        "preset_current": Command("PCU", _ua_argument, doc="Preset current while X-rays are off, µA."),
        "xray_on": Command("XON", doc="X-rays on -- or the warm-up, when DAG says YET."),
        "xray_off": Command("XOF", doc="X-rays off."),
        "warm_up": Command("XON", doc="Dialect B has no WUP: XON starts the warm-up while DAG says YET."),
        "reset": Command("RST", doc="Reset after an overload (never sent automatically)."),
        "focus": Choice({k: "CF" + v[0] for k, v in _FOCUS_B.items()}, doc="Focus small/middle/large: CFS, CFM, CFL."),
    },
    poll=("state", "voltage_kv", "current_ua", "interlock_closed"),
)

DIALECTS = {"A": DIALECT_A, "B": DIALECT_B}


# -- the probe ------------------------------------------------------------------------------------
# Harmless queries only: the probe must never change the tube (no XON, HIV, CUR, PHV, PCU, WUP, RST).
PROBE_QUERIES = frozenset({"STS", "SIN", "TYP", "SWE", "SRL", "DAG"})


@dataclasses.dataclass(frozen=True)
class ProbeExchange:
    """One query the probe sent: the baud rate, the query, the reply (None: none) and the error."""

    baudrate: int | None
    sent: str
    reply: str | None
    error: str = ""

    def __str__(self) -> str:
        got = repr(self.reply) if self.reply is not None else f"(no reply: {self.error})"
        return f"{self.baudrate or '-':>6} baud  > {self.sent:<4} < {got}"


@dataclasses.dataclass(frozen=True)
class ProbeResult:
    """What :func:`probe` found: the dialect and baud rate (None when nothing fits), the identity
    where the dialect has one (A's ``TYP``), what else the unit said, and the raw exchange."""

    port: str
    dialect: str | None
    baudrate: int | None
    identity: str | None
    details: tuple[tuple[str, str], ...]
    exchange: tuple[ProbeExchange, ...]
    notes: tuple[str, ...]

    @property
    def found(self) -> bool:
        """Whether the replies fit one dialect."""
        return self.dialect is not None

    @property
    def port_unavailable(self) -> bool:
        """The port could not be opened at any rate: not a byte was sent, so nothing is known of
        the controller (the summary says so, not that its replies fit neither dialect)."""
        return bool(self.exchange) and all(e.sent == "(open)" for e in self.exchange)

    @property
    def emitting(self) -> bool:
        """Whether the probe's ``STS`` read a state that emits (X-rays on, warming up): a unit
        left on, which an interrupted connect must still switch off."""
        state = dict(self.details).get("state")
        return state in SourceState.__members__ and SourceState[state].emitting

    def summary(self) -> str:
        """One line: what the unit speaks, or why the probe refuses."""
        if self.port_unavailable:
            return f"{self.exchange[-1].error}; nothing was sent"
        if not self.found:
            silent = [str(e.baudrate) for e in self.exchange if e.sent == "STS" and e.reply is None]
            why = "; ".join(([f"no reply (or junk) at {', '.join(silent)} baud"] if silent else []) + list(self.notes))
            return (
                f"{shown_name(self.port)}: the replies fit neither dialect A nor B at "
                f"{', '.join(str(b) for b in dict.fromkeys(e.baudrate for e in self.exchange))} baud ({why})"
            )
        ident = f", identity {self.identity!r}" if self.identity else ", no identity query in this dialect"
        typ = [e for e in self.exchange if e.sent == "TYP" and e.baudrate == self.baudrate]
        if not self.identity and typ:  # A asked TYP and got no identity: say what it answered
            got = f"answered {typ[-1].reply!r}" if typ[-1].reply is not None else "got no reply"
            ident = f", identity unknown (TYP {got})"
        more = "".join(f", {k} {v}" for k, v in self.details)
        return f"{shown_name(self.port)}: dialect {self.dialect} at {self.baudrate} baud{ident}{more}"

    def report(self) -> str:
        """The summary, then the raw exchange (for the lab notebook)."""
        lines = [self.summary(), "raw exchange:"] + [f"  {e}" for e in self.exchange]
        return "\n".join(lines + [f"note: {n}" for n in self.notes if self.found])


def probe(
    url,
    *,
    baudrates=(9600, 38400, 115200),
    timeout_s: float | None = None,
    min_interval_s: float = 0.06,
    keep_link_if_emitting: bool = False,
) -> ProbeResult:
    """Find which dialect (and baud rate) the controller on ``url`` speaks, with harmless queries.

    At each baud rate in turn: ``STS``; if its reply has the shape of one dialect, ``SIN`` must too
    (a unit that answers ``STS 2`` and ``INTER LOCK ON`` fits neither), then the identity or state
    queries of that dialect (A: ``TYP``, ``SWE``; B: ``SRL``, ``DAG``). An ``STS`` or ``SIN`` reply
    that fits no dialect (one garbled by noise) is asked again, once, before it counts. Stops at
    the first baud rate where the replies fit a dialect. Only queries in :data:`PROBE_QUERIES` are sent.

    Parameters
    ----------
    url : str or transport
        A port for :class:`SerialTransport`, or an open transport (then only its own baud rate,
        ``getattr(url, "baudrate", None)``, is tried).
    baudrates : sequence of int
        The rates to try, in order.
    timeout_s : float, optional
        The reply time-out per query, at every rate; ``None``: the longest dialect's (B's 2 s). A
        unit may be set to any listed rate, and one answering within its dialect's documented wait
        must be found there as at the first (a shorter wait at later rates refused a B unit at
        38400 answering in 0.8 s, and read its late reply at the next rate).
    min_interval_s : float
        The pause between queries.
    keep_link_if_emitting : bool
        For a driver that must switch off what the probe found (:meth:`L8121.connect`): when an
        interrupt (Ctrl-C, a stop signal) cuts the probe short after ``STS`` fitted a dialect and
        read X-rays on, the exception carries ``probe_emitting`` = (dialect name, baud rate, the
        still open link) instead of the link being closed (its interrupted reply is still on the
        way: the link completes it before the next command). Every interrupt carries
        ``probe_sent``: whether any query had been sent.

    After a rate whose last query went unanswered the probe waits a quarter of ``timeout_s``
    before the next rate's first query (whose input flush then discards a late reply), so a reply
    that comes after its time-out is not read as the next rate's. A silent port costs, at the
    defaults, 2 s per rate and 0.5 s between rates: about 7 s for the three listed rates.

    Returns
    -------
    ProbeResult
        ``dialect`` None when the replies fit neither dialect at any rate.
    """
    exchange: list[ProbeExchange] = []
    notes: list[str] = []
    rates = list(dict.fromkeys(baudrates)) if isinstance(url, str) else [getattr(url, "baudrate", None)]
    port = url if isinstance(url, str) else getattr(url, "port", str(url))
    # the waits of a configuration's probe (probe_timeout_s, min_interval_s), bounded as there,
    # before the port is opened: 1e300 was a probe that waited for ever on a silent port
    for key, name, value in (
        ("probe_timeout_s", "timeout_s", timeout_s),
        ("min_interval_s", "min_interval_s", min_interval_s),
    ):
        said = None if value is None else time_refusal(key, value)
        if said is not None:
            raise ValueError(f"{shown_name(port)}: probe {name} = {shown(value)} ({key}): {said}; nothing sent")
    wait = max(d.timeout_s for d in DIALECTS.values()) if timeout_s is None else float(timeout_s)
    try:
        return _probe_rates(url, port, rates, wait, min_interval_s, keep_link_if_emitting, exchange, notes)
    except BaseException as exc:
        if not isinstance(exc, Exception) and not hasattr(exc, "probe_sent"):  # interrupted between rates
            exc.probe_sent = any(e.sent != "(open)" for e in exchange)
        raise


def _probe_rates(url, port, rates, wait, min_interval_s, keep_link_if_emitting, exchange, notes):
    missed = False
    for baud in rates:
        if missed:
            time.sleep(wait / 4)  # a late reply arrives now, and the next query's flush discards it
        try:
            link = (
                SerialTransport(url, baudrate=baud, timeout_s=wait, min_interval_s=min_interval_s, retries=0)
                if isinstance(url, str)
                else url
            )
        except DeviceError as exc:
            exchange.append(ProbeExchange(baud, "(open)", None, str(exc)))
            notes.append(f"cannot open the port at {baud} baud")
            continue
        seen: dict[str, Any] = {}
        keep = False
        try:
            found = _probe_at(link, baud, exchange, notes, seen)
            missed = exchange[-1].reply is None
            dsr = missed and getattr(link, "dsr_low", str)()  # why a port may be silent (a pty: "")
            if dsr and dsr not in notes:
                notes.append(dsr)
        except BaseException as exc:
            if not isinstance(exc, Exception):  # an interrupt: say what is known of the tube
                # (a transport that does not count its writes is taken to have sent something)
                wrote = getattr(link, "commands_written", 1) > 0
                exc.probe_sent = wrote or any(e.sent != "(open)" for e in exchange)
                state = seen.get("state")
                if keep_link_if_emitting and isinstance(url, str) and state is not None and state.emitting:
                    exc.probe_emitting, keep = (seen["dialect"], baud, link), True
            raise
        finally:
            if isinstance(url, str) and not keep:
                link.close()
        if found is not None:
            dialect, identity, details = found
            return ProbeResult(port, dialect, baud, identity, details, tuple(exchange), tuple(notes))
    return ProbeResult(port, None, None, None, (), tuple(exchange), tuple(notes))


def _fits(dialect: Dialect, name: str, reply: str | None) -> bool:
    """Whether ``reply`` parses as ``dialect``'s reading ``name``."""
    if reply is None:
        return False
    try:
        dialect.readings[name].parse(reply)
        return True
    except ValueError:
        return False


def _probe_at(link, baud, exchange: list, notes: list, seen: dict | None = None):
    seen = {} if seen is None else seen  # for an interrupt: the dialect and state read

    def ask(command: str) -> str | None:
        assert command in PROBE_QUERIES, command  # never anything that changes the tube
        try:
            reply = link.query(command)
        except DeviceError as exc:
            exchange.append(ProbeExchange(baud, command, None, str(exc).split(": ", 1)[-1]))
            return None
        exchange.append(ProbeExchange(baud, command, reply))
        return reply

    def ask_fitting(command: str, name: str, dialects) -> str | None:
        """``ask``; a reply that fits none of ``dialects`` is asked again, once: one garbled reply
        (noise on the line) ended the probe as "neither dialect", and a connect with it. A second
        misfit is the answer (a silence is not asked again: a wrong rate would cost a time-out more)."""
        reply = ask(command)
        if reply is None or any(_fits(d, name, reply) for d in dialects):
            return reply
        again = ask(command)
        if any(_fits(d, name, again) for d in dialects):
            notes.append(f"{command} answered {reply!r} at {baud} baud, then {again!r} when asked again")
        return again

    sts = ask_fitting("STS", "state", (DIALECT_A, DIALECT_B))
    if sts is None:
        return None
    candidates = [d for d in (DIALECT_A, DIALECT_B) if _fits(d, "state", sts)]
    if not candidates:
        notes.append(f"STS answered {sts!r} at {baud} baud")
        return None
    dialect = candidates[0]
    seen["dialect"], seen["state"] = dialect.name, dialect.readings["state"].parse(sts)
    sin = ask_fitting("SIN", "interlock_closed", (dialect,))
    if not _fits(dialect, "interlock_closed", sin):
        other = [d.name for d in DIALECTS.values() if d is not dialect and _fits(d, "interlock_closed", sin)]
        mix = f" (dialect {other[0]}'s shape: a mix of dialects)" if other else ""
        notes.append(f"STS {sts!r} fits dialect {dialect.name} but SIN answered {sin!r}{mix} at {baud} baud")
        return None
    closed = dialect.readings["interlock_closed"].parse(sin)
    details = [("interlock", "closed" if closed else "OPEN")]
    details.append(("state", dialect.readings["state"].parse(sts).name))
    identity = None
    if dialect is DIALECT_A:
        typ = ask("TYP")
        if _fits(dialect, "identity", typ):
            identity = dialect.readings["identity"].parse(typ)
        else:
            notes.append(f"TYP answered {typ!r}: identity unknown")
        swe = ask("SWE")
        if _fits(dialect, "warmup", swe):
            details.append(("warm-up", dialect.readings["warmup"].parse(swe).name))
    else:
        srl = ask("SRL")
        if _fits(dialect, "operate_switch", srl):
            details.append(("operate switch", srl))
            if srl != "REMOTE":
                notes.append(f"the operate switch is {srl}: remote control needs REMOTE")
        dag = ask("DAG")
        if _fits(dialect, "warmup", dag):
            details.append(("warm-up", "done" if dialect.readings["warmup"].parse(dag).done else "needed (YET)"))
    return dialect.name, identity, tuple(details)


class Reidentify:
    """A transport's ``on_reconnect`` (:attr:`SerialTransport.on_reconnect`): after the link was
    lost and the port opened again, ask the identity query connect asked -- A's ``TYP``, B's
    ``SRL`` -- before any reply on the new link is trusted, above all an ``STS`` taken for a
    switch-off's confirmation. A re-plugged USB adapter, or a pty path handed to another process,
    may put another device behind the same path.

    Dialect A: ``TYP`` must name :attr:`identity` -- the model connect's ``TYP`` read, until then
    the probe's (``dialect="auto"``) or the configured one; None: any model, as connect accepts
    with ``model=None`` and nothing found yet. Neither dialect reports a serial number, so a second
    unit of the same model passes: commands that emit or change the beam are therefore never
    resent after a reconnect (:attr:`not_resent`), and a driver counts reconnects
    (:attr:`reconnects`) to tell the operator whose off confirmation it has. Dialect B has no identity query: ``SRL`` must answer in B's grammar
    (a B controller at this rate), the weaker check, and its position is not compared (a switch
    turned meanwhile is the same controller; the XOF it refuses says so).

    Raises
    ------
    DeviceError
        No fitting answer or another model (:class:`~acquisition.errors.NoReply` when silent):
        the transport closes the port and the exchange fails as a lost link.
    """

    #: written once all the same to a device silent at the check (a controller whose replies are
    #: lost may still act on it: it switched off so before the check existed); never confirmed by it
    blind = frozenset({"XOF"})

    def __init__(self, dialect: Dialect, identity: str | None, port: str):
        self.name = "identity" if "identity" in dialect.readings else "operate_switch"
        self.query = dialect.readings[self.name]
        self.dialect = dialect.name
        self.identity = identity
        self.port = port
        #: Command words a transport never sends again after a reconnect once the link was lost
        #: during them (:meth:`SerialTransport.query`): every control command but XOF -- XON, WUP,
        #: RST and the settings emit or change the beam, and the device behind the reopened port
        #: is only known to be of the model (no serial number): XON resent to a second unit of
        #: the model switched it on with settings this session never sent.
        self.not_resent = frozenset(
            word
            for command in dialect.settings.values()
            for word in (command.choices.values() if isinstance(command, Choice) else (command.command,))
        ) - {"XOF"}
        #: How often the check has been asked (each a reconnect): a driver compares it across an
        #: exchange to know that a confirmation may come from a unit other than the one switched on.
        self.reconnects = 0
        #: Set by a transport that takes the port over from an X-ray guardian that held it open until
        #: it died (acquisition.transport.PipeTransport): the next check is of a handover, not of a
        #: link lost and found again (no unplugged adapter in between), so it is not counted.
        self.handover = False

    def __call__(self, ask: Callable[[str], str]) -> None:
        if self.handover:
            self.handover = False
        else:
            self.reconnects += 1
        command = self.query.command
        refused = f"{shown_name(self.port)}: after a reconnect, the device at the port"
        try:
            reply = ask(command)
        except NoReply as exc:
            raise NoReply(f"{refused} did not answer {command} ({exc}): not trusted as the controller") from exc
        try:
            value = self.query.parse(reply)
        except ValueError:
            value = None
        if value is None or reply in ("ERR", "ERROR"):
            raise DeviceError(
                f"{refused} answered {command} with {reply!r}, not as the dialect-{self.dialect} controller "
                "connected to: not trusted"
            )
        if self.name == "identity" and self.identity is not None and value != self.identity:
            raise DeviceError(
                f"{refused} is {value!r} ({command}), not the {self.identity!r} connected to: not trusted"
            )
        logger.warning(
            "%s: reconnected; %s answered %r (the model connected to; no serial number tells the unit)",
            shown_name(self.port),
            command,
            reply,
        )


# -- the driver -----------------------------------------------------------------------------------
class L8121:
    """A Hamamatsu L8121 X-ray source on a serial link, in either dialect.

    Parameters
    ----------
    url : str or transport
        The controller's port for :func:`serial.serial_for_url` (``/dev/ttyUSB0``,
        ``socket://host:port``, an emulator's pty), or an object with ``query(str) -> str``,
        ``close()``, ``is_open`` and ``port`` (e.g. a configured :class:`SerialTransport`).
    baudrate : int, optional
        As set on the controller; overrides ``config.baudrate`` (default: the dialect's).
    connect : bool
        Open the link and check the controller now (default).
    control : bool
        Whether this session will control the tube (default). False (queries only, a status):
        a B unit whose operate switch is not on REMOTE is connected all the same, its position
        kept in :attr:`switch_at_connect`, and X-rays found on then are not switched off by
        :meth:`close` (the controller would refuse the ``XOF``): the caller must say so.
    config : SourceConfig or mapping, optional
        Dialect, ratings, tolerances and timing; keyword arguments override single fields
        (``L8121(url, dialect="B", kv_max=90, poll_s=0.1)``).

    Raises
    ------
    DeviceError
        The port cannot be opened, the controller does not answer, ``TYP`` names another model
        (A), the operate switch is not on REMOTE (B), or the probe found neither dialect (auto).

    Notes
    -----
    Readings, one name each and the same in both dialects: :meth:`status`, :meth:`measured`,
    :meth:`setpoint`, :meth:`interlock_closed`, :meth:`warmup_state`, :meth:`error_code`,
    :attr:`focus` (read-write), :attr:`identity` (A's ``TYP`` at connect; None in B) and, in B only,
    :meth:`operate_switch`. The commands that change the tube are private: use :meth:`on`,
    :meth:`set_values`, :meth:`off`, :meth:`warm_up` and :meth:`reset`, which keep the safety rules.

    The transport serialises exchanges, so :meth:`off` may be called from another thread (a
    watchdog) at any time, also while :meth:`on` waits for a stable beam. Its ``XOF`` goes right
    after the exchange on the link, before any other thread's next query (the rest of a
    :meth:`check` in flight is not sent: :class:`SwitchedOff`). Other threads' exchanges take the
    link in the order they asked for it, so a thread polling back to back delays another's
    :meth:`set_values` (or :meth:`on`) by at most one exchange per exchange.
    """

    def __init__(
        self,
        url,
        baudrate: int | None = None,
        *,
        connect: bool = True,
        config: SourceConfig | Mapping[str, Any] | None = None,
        control: bool = True,
        **overrides,
    ):
        if baudrate is not None:
            overrides["baudrate"] = baudrate
        base = config if isinstance(config, SourceConfig) else SourceConfig.from_dict(dict(config or {}))
        self.config = SourceConfig.from_dict({**dataclasses.asdict(base), **overrides}) if overrides else base
        if "model" not in overrides:  # (not a field: from_dict does not carry it)
            self.config.probed_model = base.probed_model
        self.url = url
        self.identity: str | None = None
        # False: a session of queries only (a status): B's operate switch need not be on REMOTE,
        # which the spec asks for remote control, not for queries; its position is kept here
        self.control = bool(control)
        self.switch_at_connect: str | None = None
        # X-rays found on at connect by a session that cannot switch them off (control=False)
        self.emitting_at_connect = False
        self.probe_result: ProbeResult | None = None
        self.dialect: Dialect | None = None
        self.baudrate: int | None = self.config.baudrate
        if self.config.dialect != "auto":
            self._use(DIALECTS[self.config.dialect], self.config.baudrate)
        self._transport = None
        self._reidentify: Reidentify | None = None  # the link's on_reconnect check (_give_grammar)
        self._may_be_on = False  # True from before XON (or the warm-up) until off() has confirmed
        # The link was reopened (Reidentify.reconnects) while X-rays may have been on: a later
        # confirmation comes from the unit now behind the port, which only its model vouches for
        # (no serial numbers): the tube this session switched on is not confirmed off by it
        self.unit_unverified = False
        # No state read yet on this driver's link: the tube may be on (left on by an earlier run), so
        # a reconnect before the first STS counts as one while X-rays may have been on -- that STS
        # is the unit's now at the port. Once a state is read, _may_be_on says (the guardian's
        # watch starts so too; the driver's did not: `source off` said "confirmed" with unit 1 on)
        self._state_unread = True
        # What this session knows of the tube, for the exit rule (README: exit codes): whether it
        # opened the port (the probe's included), and the state its last STS (or SAR) read
        self.port_opened = False
        self._last_state: SourceState | None = None
        self._beam: tuple[int, int] | None = None  # the set values while this driver keeps the beam on
        # when SER was last read (time.monotonic()), for error_poll_s's bound with the beam on
        self._error_read_at: float | None = None
        # time.time() just before the last SER read that found no fault: a beam's frames after it
        # are not vouched for once a later SER reads one (the code may have stood since)
        self._error_good_at: float | None = None
        # the previous ones while set_values() ramps the beam on to new ones (_beam_span)
        self._beam_from: tuple[int, int] | None = None
        # while set_values() changes the beam: the ramp's judgement, shared by its wait and a beam
        # monitor's check() in another thread (_RampWatch); None otherwise
        self._ramp_watch: _RampWatch | None = None
        self._changes = 0  # how many such changes have begun (check(): a reading that outlived one)
        # what the last on() saw of its ramp from zero: (seconds from XON's echo to the stable
        # reading, the (kV, µA) set, their tolerances), the unit's own measure of how fast it ramps
        self._xon_ramp: tuple[float, tuple[int, int], tuple[float, float]] | None = None
        # how many faults _trip() has begun to switch off for, and the last one's exception once
        # made, (its number, the exception or None): a wait whose beam another thread switches off
        # meanwhile says that thread's cause, not the standby it then reads (_tripped_elsewhere)
        self._trips, self._last_trip = 0, (0, None)
        self._trip_made = threading.Condition()
        # One switch-off at a time, and it goes first: the thread that owns it (_off_thread) sends
        # its XOF/STS before any other thread's queued exchange, and a second caller of off()
        # waits for its outcome instead of repeating it (a silent controller would cost each
        # repetition its time-outs before the operator hears anything).
        self._turns = threading.Condition()
        # The thread whose exchange holds the link (None: free). A thread runs one exchange at a
        # time, so the link (or a place in the queue) still held by the thread asking again was
        # left by an exception between taking it and the exchange's ``finally`` -- a signal's stop
        # is raised at any bytecode of the main thread -- and is free to it: before, the stop's
        # own switch-off then waited for it forever without a word (CI, session 50: ``source
        # warm-up`` on B, SIGTERM; tests/test_l8121_fairness.py, a stop at every line).
        self._busy: int | None = None
        # The threads waiting for the link, in the order they asked: it goes to the first (a switch-off's
        # thread excepted: before all). Without the order, a thread polling back to back (a user's
        # status loop, a beam monitor with no period) gave the link up and took it again before
        # the waiting thread had woken, and set_values() waited as long as the loop ran (seconds,
        # unbounded, in both dialects: benchmarks/bench_l8121_starve.py)
        self._queue: collections.deque = collections.deque()
        self._off_thread: int | None = None
        self._off_running = False
        self._off_state: SourceState | None = None
        # Counts the switch-offs begun and the stops announced (cancel_readings()); a routine
        # reading (check()) notes it in this thread-local when it starts and sends no further
        # query once another thread's switch-off has begun or a stop is on its way.
        self._routine_epoch = 0
        self._local = threading.local()
        #: The last :meth:`off` that could not be confirmed (None once one confirms). While set, a
        #: failed exchange does not start another switch-off by itself: the one that failed has
        #: said to switch off at the controller, and asking a silent controller again only delays
        #: that message.
        self.off_failed: DeviceError | None = None
        self._off_failure_logged: str | None = None  # the text last logged by _log_off_failure
        #: What the last :meth:`warm_up` set (and read back) before starting its warm-up: ``(kV,
        #: µA, given)``, given False for the configuration's lowest; None when it started none.
        self.warmup_values: tuple[int, int, bool] | None = None
        #: Whether the last :meth:`warm_up` found one already running (started by hand or by an
        #: earlier command) and waited for it: nothing set, nothing sent that emits.
        self.warmup_joined = False
        #: ``before_xon(kv, ua)``, called by :meth:`on` with the values set and read back, right
        #: before its ``XON``: a caller tells the operator there what the beam will do (``source on``:
        #: for how long), since a ``kill -9`` in the ramp that follows leaves it no word after.
        self.before_xon: Callable[[int, int], None] | None = None
        #: The focus last asked for (:attr:`focus`), set and read back again before every ``XON``
        #: of :meth:`on`: a controller reset between beam periods (a power cycle) puts the unit's
        #: own default back without a word, and the series would expose, and record, a focal spot
        #: nobody asked for (review s38b). None: never set, left as the unit has it.
        self.focus_wanted: int | None = None
        if connect:
            self.connect()

    def _use(self, dialect: Dialect, baudrate: int | None) -> None:
        self.dialect = dialect
        self.baudrate = int(baudrate or dialect.baudrate)

    @property
    def min_interval_s(self) -> float:
        """The pause between two commands (configuration, else the dialect's)."""
        return self.dialect.min_interval_s if self.config.min_interval_s is None else self.config.min_interval_s

    @property
    def timeout_s(self) -> float:
        """The longest wait for a reply (configuration, else the dialect's: 2 s in both)."""
        return self.dialect.timeout_s if self.config.timeout_s is None else self.config.timeout_s

    @property
    def voltage_scale(self) -> float:
        """kV are multiplied by this in a command argument (configuration, else the dialect's)."""
        return self.config.voltage_scale or self.dialect.voltage_scale

    @classmethod
    def from_config(
        cls, source: Mapping[str, Any] | str | Path, *, section: str = "source", connect: bool = True
    ) -> L8121:
        """A driver from a TOML table (file, text, or an already parsed mapping) holding ``url``
        and :class:`SourceConfig` keys (``dialect``, ``baudrate``, limits, ...)."""
        table = dict(source) if isinstance(source, Mapping) else _toml_section(source, section)
        if "url" not in table:
            raise SettingRefused(f"no 'url' in [{section}]")
        url = table.pop("url")
        return cls(url, connect=connect, config=SourceConfig.from_dict(table))

    # ---- link ----
    @property
    def port(self) -> str:
        """The port, as messages name it."""
        return getattr(self._transport, "port", None) or str(getattr(self.url, "port", self.url))

    @property
    def is_connected(self) -> bool:
        """Whether the link is open."""
        return self._transport is not None and self._transport.is_open

    def connect(self) -> L8121:
        """Open the link and check the controller; returns self.

        ``dialect="auto"``: :func:`probe` first (refused when nothing fits). Dialect A: ``TYP``
        must name ``config.model``. Dialect B: the operate switch (``SRL``) must be ``REMOTE``.
        If the tube is found emitting, it is noted (a warning) and :meth:`close` will switch it off.
        A connect that fails after the port opened (the identity, the operate switch, the state)
        sends ``XOF`` all the same in a session that controls the tube (``control``), confirmed by
        ``STS`` or kept in :attr:`off_failed`, before it raises (:meth:`_off_after_refused_connect`).
        An interrupt (``KeyboardInterrupt``, a stop signal) after the probe read X-rays on still
        sends ``XOF`` and confirms it before it propagates, carrying ``tube_state`` (confirmed) or
        ``off_failed``; so does one, in a session that controls the tube, once the port is open
        and before any ``STS`` read the tube off (:meth:`_off_for_unread_interrupt`: a crashed
        session may have left it on). Every interrupt here carries ``probe_sent`` (False: nothing
        was sent), and leaves the link closed.
        """
        if self.is_connected:
            return self
        if self.dialect is None:
            self._probe()
        if isinstance(self.url, str):
            try:
                self._transport = SerialTransport(
                    self.url, baudrate=self.baudrate, timeout_s=self.timeout_s, min_interval_s=self.min_interval_s
                )
            except PortUnavailable as exc:
                if self.probe_result is None:
                    raise  # not a byte sent: the caller says radiokit never reached the controller
                raise self._reopen_failed(exc) from exc
        else:
            self._transport = self.url
        self.port_opened = True
        try:
            # inside the try: a stop here leaves the link open and the tube untouched otherwise
            self._give_grammar(self._transport)
            self._check_identity()
            if self._read("state").emitting:
                if self.switch_at_connect not in (None, "REMOTE"):  # queries only (control=False)
                    # not switched off from here (refused): whoever ends this session must say so
                    self.emitting_at_connect = True
                    logger.warning(
                        "%s: X-rays are on at connect, operate switch %s", shown_name(self.port), self.switch_at_connect
                    )
                else:
                    logger.warning(
                        "%s: X-rays are ON at connect (left on by other software or a crash, or switched on at the controller); "
                        "radiokit switches them off before it lets the port go and says whether the controller "
                        "confirmed it: if no confirmation follows, switch off at the controller",
                        shown_name(self.port),
                    )
                    self._may_be_on = True
            elif self.unit_unverified and self._last_state.confirms_off:  # reopened before that STS
                logger.critical("%s", self.unverified_warning(self._last_state))
            # inside the try too: a stop here, once connect is raising, leaves its caller no driver
            # to close (``L8121(url)`` returns none), so it is switched off here or not at all
            logger.info(
                "%s: %s connected (dialect %s, %d baud)",
                shown_name(self.port),
                self.identity or "L8121",
                self.dialect.name,
                self.baudrate,
            )
        except BaseException as exc:
            self._after_failed_connect(exc)
            raise
        return self

    def _after_failed_connect(self, exc: BaseException) -> None:
        """What a connect that raised ``exc`` after the port opened does before ``exc`` goes on
        (:meth:`connect`): the switch-off its cause calls for, then the link closed -- also when a
        second stop cuts that switch-off short (a script's second Ctrl-C; the command line's guard
        defers it): that stop goes on instead, carrying ``off_failed`` (the switch-off not
        confirmed; before, it left the link open and read as if nothing had been sent)."""
        if isinstance(exc, KeyboardInterrupt) and not hasattr(exc, "probe_sent"):
            # (as the probe's: whether the controller has received anything from this connect)
            exc.probe_sent = self.probe_result is not None or getattr(self._transport, "commands_written", 1) > 0
        seen_on = (self.probe_result is not None and self.probe_result.emitting) or self._may_be_on
        try:
            if isinstance(exc, KeyboardInterrupt) and seen_on:
                self._off_for_interrupt(exc)  # X-rays were read on: an interrupt still switches off
            elif isinstance(exc, KeyboardInterrupt) and self.control and not self.tube_confirmed_off:
                self._off_for_unread_interrupt(exc)
            elif isinstance(exc, DeviceError) and self.control and not getattr(exc, "foreign", False):
                self._off_after_refused_connect()
        except KeyboardInterrupt as again:
            again.probe_sent = True  # (the XOF may have gone)
            if isinstance(exc, KeyboardInterrupt):  # the first stop's switch-off cut short by a second
                again.state_unread = getattr(exc, "state_unread", False)
                if self.off_failed is None:
                    self.off_failed = DeviceError(
                        f"{shown_name(self.port)}: could not confirm X-rays off: stopped again while switching "
                        "them off; switch the source off at the controller"
                    )
                again.off_failed = self.off_failed
                self._log_off_failure(self.off_failed)
            # else the first stop, in a refused connect's XOF: its caller switches off (off_anyway)
            raise
        finally:
            self._transport.close()
            self._transport = None

    def take_over(self, prober: L8121) -> None:
        """What ``prober``'s probe learnt of this controller -- its result, that it opened the port,
        the state its ``STS`` read -- for this driver, which goes on over another link to the same
        unit (the series' guardian): an interrupted connect and the exit rule
        (:attr:`tube_confirmed_off`) read it. Sends nothing."""
        self.probe_result = prober.probe_result
        self.port_opened = self.port_opened or prober.port_opened
        if self._last_state is None:
            self._last_state = prober._last_state

    @property
    def last_state(self) -> SourceState | None:
        """The state this session's last ``STS`` (or ``SAR``, or the probe's ``STS``) read; None:
        none read."""
        return self._last_state

    def port_lost_after_probe(self, exc: PortUnavailable) -> DeviceError:
        """The error for a port the probe had open that could not be opened again (see
        :meth:`_reopen_failed`)."""
        return self._reopen_failed(exc)

    def _reopen_failed(self, exc: PortUnavailable) -> DeviceError:
        """The port, which the probe had open and talked over, could not be opened again (another
        program took it, the adapter dropped out): not "never reached" -- the probe did reach the
        controller. When its ``STS`` read X-rays on, the error carries ``may_be_on`` so that the
        caller ends on the X-rays warning: nothing here could switch them off."""
        state = dict(self.probe_result.details).get("state", "unknown")
        err = DeviceError(
            f"{exc}; the probe had reached the controller (state {state}) but the port could not be "
            "opened again to control it"
        )
        err.may_be_on = self.probe_result.emitting
        return err

    def _give_grammar(self, transport) -> None:
        """Let a transport that can (``SerialTransport.reply_fits``) tell a late reply, after a
        time-out, from the reply to the command it sent next, by this dialect's reply grammar; and
        re-identify the controller after a reconnect (:class:`Reidentify`, ``on_reconnect``)."""
        if hasattr(transport, "reply_fits"):
            transport.reply_fits = self.dialect.reply_fits
        if hasattr(transport, "late_barriers"):  # the queries it may send to tell a late reply apart
            transport.late_barriers = self.dialect.late_barriers
        # a check already there is kept: the guardian's knows the model its client's connect read
        if hasattr(transport, "on_reconnect") and transport.on_reconnect is None:
            # the model the probe found (connect's TYP, _check_identity, updates it), else the configured one
            self._reidentify = Reidentify(self.dialect, self.identity or self.config.model, self.port)
            transport.on_reconnect = self._reidentify
        elif isinstance(getattr(transport, "on_reconnect", None), Reidentify):
            self._reidentify = transport.on_reconnect  # (the guardian's): its reconnects are counted

    def _off_after_probe(self, exc: KeyboardInterrupt) -> None:
        """An interrupt cut the probe short after ``STS`` read X-rays on (left on by other
        software or a crash, or by hand): the dialect is known, so switch off on the probe's link and
        confirm (``L8121.md``: off "on every exit path", Ctrl-C included) before the interrupt goes
        on. The exception then carries ``tube_state`` (the confirmed off state) or ``off_failed``;
        the caller's signal guard defers further signals meanwhile (it stays stopping)."""
        seen = getattr(exc, "probe_emitting", None)
        if seen is None:
            return
        name, baud, link = seen
        self._use(DIALECTS[name], baud)
        link.timeout_s = self.timeout_s  # the dialect's reply time, not the probe's
        self._give_grammar(link)
        self._transport = link
        try:
            self._off_for_interrupt(exc)
        finally:
            self._transport = None
            link.close()

    def _off_after_refused_connect(self) -> None:
        """A session that controls the tube (``control``) whose connect failed after the port
        opened -- the identity query unanswered, refused or naming another model, B's operate switch
        not on REMOTE, STS refused or garbled: ``XOF`` all the same on the link there is, then
        ``STS`` (:meth:`off`). Nobody has read the tube off, and other software or a crash may have
        left it on; the connect's refusal must not leave it so. ``XOF`` cannot emit in either
        dialect (``L8121.md``: A's is "always accepted"; B names no exception to "remote control
        needs REMOTE", so a B unit off REMOTE may refuse it -- a refused command changes nothing,
        and its ``STS`` may still show the tube off). The outcome is the exit rule's
        (:attr:`tube_confirmed_off`, or :attr:`off_failed`), never raised over the refusal."""
        if self.off_failed is not None:  # a switch-off in this connect failed and said so already
            return
        self._may_be_on = True  # unknown until STS reads a state that cannot emit
        logger.warning("%s: the connect failed; sending XOF all the same", shown_name(self.port))
        try:
            self.off()
        except DeviceError as err:
            self._log_off_failure(err)

    def off_unconnected(self, *, after_interrupt: bool = False) -> SourceState:
        """``radiokit acquire source off`` after a connect that failed: switch off with whatever
        link there is, and confirm with ``STS``. The port is opened again (it was opened before:
        :attr:`port_opened`; a port never opened raises at once). With the dialect known (given,
        or found by the probe) this is :meth:`off` in it; when the probe fitted neither dialect it
        is :meth:`_off_in_either_dialect`. Sends nothing that emits. ``after_interrupt``: the
        connect was cut short while a reply may still be on its way; the new link knows nothing of
        it, so it waits one reply time-out before its first command, whose input flush then
        discards that reply (read as the XOF's, it shifted every later reply by one).

        Raises
        ------
        DeviceError
            The port cannot be opened, or ``STS`` did not confirm the tube off (:attr:`off_failed`).
        """
        if not self.port_opened:
            raise DeviceError(f"{shown_name(self.port)}: the port was never opened: no switch-off could be sent")
        if self.is_connected:
            self._may_be_on = True
            return self.off()
        # a guardian's link (``source warm-up``) released the port when the connect failed: open it here
        url = self.url if isinstance(self.url, str) else getattr(self.url, "url", None)
        if not isinstance(url, str) or getattr(self.url, "is_open", False):
            raise DeviceError(f"{shown_name(self.port)}: the link is closed: no switch-off could be sent")
        if self.dialect is None:
            return self._off_in_either_dialect(after_interrupt)
        link = SerialTransport(
            url, baudrate=self.baudrate, timeout_s=self.timeout_s, min_interval_s=self.min_interval_s
        )
        if after_interrupt:
            time.sleep(self.timeout_s)
        self._give_grammar(link)
        self._transport = link
        try:
            self._may_be_on = True
            return self.off()
        finally:
            self._transport = None
            link.close()

    def _off_in_either_dialect(self, after_interrupt: bool = False) -> SourceState:
        """``XOF`` to a controller whose replies fitted neither dialect at the probe, then ``STS``.

        Both dialects' switch-off is the same line, ``XOF`` and CR (``L8121.md``: A "X-rays off;
        always accepted", B "XON / XOF: X-rays on / off"), so sending "both dialects' switch-off"
        is sending that one line, and neither dialect reads it as anything but off (the commands that
        emit, ``XON`` and A's ``WUP``, are other words; no dialect has an ``XOF`` that does more). What is unknown is the baud
        rate: it goes at the rates where the probe heard a reply (every rate it opened, if none),
        as the probe's own queries went. At a rate the controller is not set to, the line arrives
        as framing errors and junk bytes, which the controller refused or ignored as it did the
        probe's ``STS`` there; a command it would act on needs exact letters and a CR. Confirmed
        only by an ``STS`` reply that fits one dialect's grammar and reads a state that cannot
        emit (a tube that reads on, ramping down, is asked again ``poll_s`` apart for ``off_confirm_s``)."""
        c = self.config
        exchange = self.probe_result.exchange if self.probe_result is not None else ()  # None: interrupted
        heard = [e.baudrate for e in exchange if e.reply is not None]
        opened = [e.baudrate for e in exchange if e.sent != "(open)"]
        configured = ((c.baudrate,) if c.baudrate else ()) + c.probe_baudrates
        rates = list(dict.fromkeys(heard or opened or configured))
        wait = c.timeout_s or max(d.timeout_s for d in DIALECTS.values())
        spacing = DIALECT_A.min_interval_s if c.min_interval_s is None else c.min_interval_s
        said, sent = [], []
        if after_interrupt:  # see off_unconnected
            time.sleep(wait)
        for baud in rates:
            try:
                link = SerialTransport(self.url, baudrate=baud, timeout_s=wait, min_interval_s=spacing, retries=0)
            except DeviceError as exc:
                said.append(str(exc))
                continue
            # an XOF's reply that comes after its time-out is told from STS's by either dialect's
            # grammar, as on a driver's link by its own
            link.reply_fits = lambda line, reply: any(d.reply_fits(line, reply) for d in DIALECTS.values())
            try:
                # where the probe heard nothing, a silent XOF is not followed by STS: the same
                # silence again, one time-out per rate, delayed the warning by 12-15 s
                found = self._xof_and_read(link, time.monotonic() + c.off_confirm_s, said, sent, ask=bool(heard))
            finally:
                link.close()
            if found is not None:
                dialect, state = found
                self._use(dialect, baud)
                self._may_be_on, self.off_failed, self._off_state, self._last_state = False, None, state, state
                logger.info(
                    "%s: X-rays off at %d baud (dialect %s by STS: %s)", self.port, baud, dialect.name, state.name
                )
                return state
        self._may_be_on = True
        where = f"XOF sent at {', '.join(map(str, sent))} baud" if sent else "no XOF could be sent"
        self.off_failed = DeviceError(
            f"{shown_name(self.port)}: {where} (the dialect unknown: the probe's replies fitted neither), but no STS reply "
            f"read the tube off ({'; '.join(said) or 'none'}); switch the source off at the controller"
        )
        raise self.off_failed

    def _xof_and_read(self, link, until: float, said: list, sent: list, ask: bool = True):
        """``XOF`` on ``link``, then ``STS`` until a reply fits one dialect with a state that cannot
        emit (returned with its dialect) or ``until`` passes (None; what was heard goes in ``said``,
        the rate in ``sent`` once the XOF was written). ``ask`` False: no ``STS`` after an XOF that
        got no reply (a rate where the probe heard nothing)."""
        try:
            said.append(f"{link.baudrate} baud: XOF answered {link.query('XOF')!r}")
            sent.append(link.baudrate)
        except DeviceError as exc:
            said.append(str(exc))
            if not isinstance(exc, WriteTimedOut):  # anything else: the XOF may have arrived
                sent.append(link.baudrate)
            if not ask and isinstance(exc, NoReply):
                return None
            # otherwise still ask: the XOF may have arrived
        while True:
            try:
                reply = link.query("STS")
            except DeviceError as exc:
                said.append(str(exc))
                return None
            fits = []
            for dialect in (DIALECT_A, DIALECT_B):
                try:
                    fits.append((dialect, dialect.readings["state"].parse(reply)))
                except ValueError:
                    pass
            if len(fits) == 1 and fits[0][1].confirms_off:
                return fits[0]
            # asked again only while it reads a state that emits (a supply ramping down); junk, or
            # B's ambiguous ERROR, will not turn into a confirmation by asking
            if len(fits) != 1 or not fits[0][1].emitting or time.monotonic() + self.config.poll_s > until:
                said.append(f"{link.baudrate} baud: STS answered {reply!r}")
                return None
            time.sleep(self.config.poll_s)

    def _off_for_interrupt(self, exc: BaseException) -> None:
        """XOF and confirm on the open link for an interrupted connect that found X-rays on; the
        outcome goes on ``exc``: ``tube_state`` (confirmed) or ``off_failed``."""
        logger.warning(
            "%s: interrupted while X-rays were on (dialect %s): switching off", shown_name(self.port), self.dialect.name
        )
        self._may_be_on = True
        try:
            exc.tube_state = self.off()
        except DeviceError as err:
            exc.off_failed = err
            self._log_off_failure(err)

    def _off_for_unread_interrupt(self, exc: BaseException) -> None:
        """XOF and confirm on the open link for a connect interrupted before any ``STS`` read the
        tube off (its identity query, or the state's own, cut short): a crashed session may have
        left X-rays on, and the dialect is known. ``XOF`` cannot emit in either dialect
        (``L8121.md``: A's "X-rays off; always accepted"; B's ``XON`` / ``XOF`` "X-rays on / off",
        and a B unit off REMOTE refuses it, which changes nothing), so it goes as a refused
        connect's does (:meth:`_off_after_refused_connect`) rather than leaving the caller only
        the X-rays warning. The outcome goes on ``exc``: ``tube_state`` (confirmed) or
        ``off_failed`` (said loudly, as every unconfirmed switch-off); ``state_unread`` tells the
        last line that no X-rays were seen on; ``probe_sent`` becomes True (the XOF was)."""
        logger.warning(
            "%s: interrupted before the state was read (dialect %s): sending XOF all the same",
            shown_name(self.port),
            self.dialect.name,
        )
        exc.state_unread = True
        self._give_grammar(self._transport)  # (again: the stop may have cut it short; it only sets what it sets)
        self._may_be_on = True  # unknown until STS reads a state that cannot emit
        try:
            exc.tube_state = self.off()
        except DeviceError as err:
            exc.off_failed = err
            self._log_off_failure(err)
        finally:
            exc.probe_sent = True

    def _probe(self) -> None:
        c = self.config
        rates = ((c.baudrate,) if c.baudrate else ()) + c.probe_baudrates
        try:
            result = probe(
                self.url,
                baudrates=rates,
                timeout_s=c.probe_timeout_s,
                min_interval_s=DIALECT_A.min_interval_s if c.min_interval_s is None else c.min_interval_s,
                keep_link_if_emitting=True,
            )
        except KeyboardInterrupt as exc:  # connect() and resolve() alike
            # a query sent: the port was opened (the exit rule; `source off` switches off anyway)
            self.port_opened = getattr(exc, "probe_sent", True)
            self._off_after_probe(exc)
            raise
        self.probe_result = result
        self.port_opened = not result.port_unavailable
        state = dict(result.details).get("state")
        if state in SourceState.__members__:  # the probe's STS is this session's reading too
            self._last_state = SourceState[state]
        for e in result.exchange:
            logger.debug("%s probe: %s", shown_name(result.port), e)
        if not result.found:
            if result.port_unavailable:
                raise PortUnavailable(result.exchange[-1].error)  # no byte sent: say so, not "neither dialect"
            raise DeviceError(
                f"{result.summary()}; refusing to go on (`radiokit acquire source probe --port "
                f"{result.port}` prints the exchange)"
            )
        logger.info("%s", result.summary())
        self._use(DIALECTS[result.dialect], result.baudrate)
        # the model the probe's TYP found (None in B): with model=None, what a reconnect must find
        # (_give_grammar's Reidentify, and the guardian's through resolved_config) until connect's
        # TYP reads it again -- not "any model", which let another unit behind the path pass
        self.identity = result.identity

    def _check_identity(self) -> None:
        first = "identity" if "identity" in self.dialect.readings else "operate_switch"
        try:
            value = self._read(first)
        except GuardianLost:
            # the guardian died under the query (kill -9 right after READY): the controller was
            # not heard either way, and a baud rate or dialect to check would send the operator
            # after the wrong fault
            raise
        except DeviceError as exc:
            other = "B" if self.dialect is DIALECT_A else "A"
            err = DeviceError(
                f"{exc}; is this unit on {self.baudrate} baud and speaking dialect {self.dialect.name}? "
                f'If it speaks dialect {other}, set dialect = "{other}" or "auto" '
                f"(`radiokit acquire source probe --port {shown_name(self.port)}` tells)"
            )
            # an answer that fits neither dialect's grammar is another instrument on the port: the
            # refused connect sends it no XOF (as a probe that fits neither sends nothing more)
            reply = getattr(exc, "reply", None)
            command = self.dialect.readings[first].command
            knows = [d for d in DIALECTS.values() if command in {q.command for q in d.readings.values()}]
            err.foreign = reply is not None and not any(d.reply_fits(command, reply) for d in knows)
            raise err from None
        if first == "identity":
            self.identity = value
            if self._reidentify is not None:  # a reconnect from now on must find this model
                self._reidentify.identity = value
            if self.config.model is not None and self.identity != self.config.model:
                self._read_state_for_the_record()
                found = self.config.probed_model
                # the model expected is the one the probe found (resolve(), model=None): the unit
                # behind the port changed since; "configure model=None" was advice already taken
                why = (
                    f"the probe found {found!r} at this port moments before: another unit is behind it now"
                    if found is not None and found == self.config.model
                    else "configure model=None to accept any model"
                )
                raise DeviceError(
                    f"{shown_name(self.port)}: TYP answered {self.identity!r}, expected {self.config.model!r} ({why})"
                )
        else:
            switch = self.switch_at_connect = value
            if switch != "REMOTE" and self.control:
                self._read_state_for_the_record()
                err = DeviceError(
                    f"{shown_name(self.port)}: the controller's operate switch is {switch} (SRL): it refuses remote "
                    f"commands; turn it to REMOTE at the controller"
                )
                # the refused connect's XOF, refused alike, ends on an error naming the switch too:
                # a command line that says that one says everything this one does (one line, not two)
                err.operate_switch = switch
                raise err

    def _read_state_for_the_record(self) -> None:
        """Before a connect is refused (another model, B's operate switch off REMOTE): ``STS``
        once, a query, so that the command's end can say whether the controller showed the tube
        off (:attr:`tube_confirmed_off`, the exit rule) rather than know nothing of it."""
        try:
            state = self._read("state")
        except DeviceError as exc:
            logger.warning("%s: the state could not be read either: %s", shown_name(self.port), exc)
            return
        if state.emitting:
            logger.warning("%s: X-rays are on (state %s)", shown_name(self.port), state.name)

    def close(self) -> None:
        """Switch X-rays off if this session may have left them on (confirmed), then close the link.

        After a switch-off that failed (:attr:`off_failed`) this tries once more -- ``XOF`` and
        ``STS`` again, each waiting out its reply time-out with a silent controller (2 s each by
        default, in both dialects) -- before it raises; a caller that must not wait again uses
        :meth:`detach`.

        Raises
        ------
        DeviceError
            Switching off could not be confirmed (the link is closed anyway).
        """
        if self._transport is None:
            return
        try:
            if self._may_be_on:  # also over a link that dropped: the transport reopens it
                self.off()
        finally:
            port = shown_name(self.port)  # (said after the close)
            self._transport.close()
            self._transport = None
            logger.info("%s: closed", port)

    @property
    def may_be_on(self) -> bool:
        """Whether X-rays may be on by what this session knows (found on at connect, or switched
        on), until a switch-off confirms; :meth:`close` then switches off."""
        return self._may_be_on

    @property
    def tube_confirmed_off(self) -> bool:
        """Whether the controller confirmed the tube off in this session: its last ``STS`` (A's
        ``SAR`` too, the probe's included) read a state that cannot emit (not B's ambiguous
        ``ERROR``), nothing that emits was sent after it, no switch-off has failed since, and the
        link was not reopened while X-rays may have been on (:attr:`unit_unverified`: the
        confirmation is then the unit's now behind the port, known only by its model). A
        command that opened the port (:attr:`port_opened`) and ends without this ends on the
        X-rays warning, exit 3, whoever switched the tube on (README: exit codes)."""
        last = self._last_state
        if self.unit_unverified:  # confirmed by the unit now behind the port: maybe not the one switched on
            return False
        return self.off_failed is None and not self._may_be_on and last is not None and last.confirms_off

    @property
    def confirmed_off(self) -> SourceState | None:
        """The state ``STS`` read when this session's last switch-off was confirmed (None: none
        yet); while :attr:`off_failed` is set it vouches for nothing."""
        return None if self.off_failed is not None else self._off_state

    @property
    def watchdog_off(self) -> str | None:
        """What the X-ray guardian's watchdog said when it switched off the beam of this
        session's last XON because this process fell silent (suspended or hung); None when it
        did not (or no guardian). Told with the first reply after this process woke."""
        return getattr(self._transport, "watchdog_off", None)

    def detach(self) -> None:
        """Close the link and leave the source as it is -- X-rays on included. Only after a
        switch-off that could not be confirmed and was said loudly (a second round of attempts
        would only delay the operator's warning); scripts use :meth:`close`."""
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            if self.off_failed is None:
                logger.warning("%s: detached with X-rays possibly on", shown_name(self.port))
            else:
                # the same news as the switch-off's CRITICAL line: the notebook's, not a second warning
                logger.info("%s: detached with X-rays possibly on", shown_name(self.port), extra={OFF_FAILURE: True})

    def __enter__(self) -> L8121:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.close()
        except Exception as err:  # never mask the exception that ended the block
            if exc_type is None:
                raise
            if isinstance(err, DeviceError) and self.off_failed is not None:
                # as the driver says every unconfirmed switch-off: CRITICAL, and once (the
                # fail-safe that met the block's silence has said these words already)
                self._log_off_failure(err)
            else:
                logger.error(
                    "%s: while handling %s, switching off failed: %s", shown_name(self.port), exc_type.__name__, err
                )

    def __repr__(self) -> str:
        dialect = self.dialect.name if self.dialect else "auto"
        return f"L8121({self.port!r}, dialect {dialect}, {'connected' if self.is_connected else 'not connected'})"

    def resolved_config(self) -> SourceConfig:
        """This configuration with the dialect, baud rate and model in use (after ``auto``, what
        the probe found): what a second process talking to the same unit (a guardian) should use, so that it
        connects without probing again."""
        if self.dialect is None:
            raise DeviceError(f"{shown_name(self.port)}: dialect not known yet (connect() first)")
        resolved = dataclasses.replace(
            self.config,
            # the model found (the probe's or connect's TYP), so the guardian's reconnect check
            # asks for it, not for any model, when none was configured
            model=self.config.model or self.identity,
            dialect=self.dialect.name,
            baudrate=self.baudrate,
            voltage_scale=self.voltage_scale,
            min_interval_s=self.min_interval_s,
            timeout_s=self.timeout_s,
        )
        # dataclasses.replace drops it (not a field): carried by hand, also from an earlier resolve()
        resolved.probed_model = self.identity if self.config.model is None else self.config.probed_model
        return resolved

    def resolve(self) -> SourceConfig:
        """The dialect and baud rate before connecting: ``dialect="auto"`` runs :func:`probe` on
        the port (harmless queries only, the port closed again); returns :meth:`resolved_config`.
        For a port that another process will hold (the guardian), so that nobody probes twice.

        Raises
        ------
        DeviceError
            The replies fit neither dialect (:class:`~acquisition.errors.PortUnavailable` when the
            port could not be opened at any rate).
        """
        if self.dialect is None:
            self._probe()
        return self.resolved_config()

    def attach(self, transport) -> L8121:
        """Use an open ``transport`` as this driver's link, without the connect checks (identity,
        operate switch, state): for switching off a unit whose dialect is already known, when one
        more exchange with a silent controller would only delay that (the guardian)."""
        if self.dialect is None:
            raise DeviceError(f"{shown_name(self.port)}: attach() needs a known dialect (resolve() first)")
        self._give_grammar(transport)
        self._transport = transport
        return self

    def describe(self) -> dict[str, Any]:
        """What the experiment file records about the source link."""
        return {
            "port": self.port,
            "dialect": self.dialect.name if self.dialect else None,
            "baudrate": self.baudrate,
            "identity": self.identity,
            "voltage_scale": self.voltage_scale if self.dialect else None,
            "probe": self.probe_result.summary() if self.probe_result else None,
        }

    # ---- exchanges ----
    def _exchange(self, line: str, *, query: Query | None = None) -> str:
        if self._transport is None:
            raise DeviceError(f"{shown_name(self.port)}: not connected (call connect())")
        me = threading.get_ident()
        error, check, seen = None, self._reidentify, None
        try:
            # taken inside the try: a signal's stop lands after a call returns, and one landing as
            # _take_turn returns (the link taken) left it taken to every other thread until this
            # one asked again -- a caller that handles the stop without a switch-off never does
            # (tests/test_l8121_stop_anywhere.py, another thread's poll)
            self._take_turn(me, line)
            seen = check.reconnects if check is not None else None
            try:
                reply = self._transport.query(line)
                self._local.replied_at = time.monotonic()  # (a reading's time: _reading_time)
            except DeviceError as exc:
                error = exc
                self._claim_off(me)  # before another thread's queued exchange gets the link
        finally:
            if seen is not None and check.reconnects != seen and (self._may_be_on or self._state_unread):
                self.unit_unverified = True
            with self._turns:
                if self._busy == me:
                    self._busy = None
                self._turns.notify_all()
        if error is not None:
            self._fail_safe(error)
            raise error
        if reply in ("ERR", "ERROR") and not (query is not None and query.error_is_value):
            err = DeviceError(f"{shown_name(self.port)}: {line} refused by the controller ({reply})")
            err.refused = True  # the controller answered, and will not act (off() asks it why)
            if query is not None:  # a query is never refused by a working controller: as bad as garbage
                self._fail_safe(err)
            raise err
        return reply

    def _read(self, name: str) -> Any:
        """Send the dialect's query for the reading ``name`` and parse its reply."""
        query = self.dialect.readings.get(name)
        if query is None:
            raise DeviceError(f"{shown_name(self.port)}: dialect {self.dialect.name} has no {name} reading")
        value = self._parsed(query, self._exchange(query.command, query=query))
        if name in ("state", "beam"):
            self._last_state = value if name == "state" else value[0]
            self._state_unread = False
        return value

    def _parsed(self, query: Query, reply: str) -> Any:
        """``reply`` parsed by ``query``; an unparseable one fails safe and is raised."""
        try:
            return query.parse(reply)
        except ValueError as why:
            err = DeviceError(
                f"{shown_name(self.port)}: unparseable reply to {query.command} (dialect {self.dialect.name}): {reply!r} ({why})"
            )
            err.reply = reply  # what answered (the connect tells an L8121 from another instrument by it)
            self._fail_safe(err)
            raise err from None

    def _do(self, name: str, value=None) -> None:
        """Send the dialect's command for the setting or action ``name`` (validated first)."""
        command = self.dialect.settings[name]
        line = command.line(self, value)  # validates before anything is sent
        reply = self._exchange(line)
        if not Command.is_echo(line, reply):
            err = DeviceError(
                f"{shown_name(self.port)}: unexpected reply to {line}: {reply!r} (expected the echo {line!r})"
            )
            self._fail_safe(err)
            raise err

    def _take_turn(self, me: int, line: str) -> None:
        """Wait for the link, and for another thread's switch-off to finish. After a switch-off
        that met a silent controller, other threads' exchanges are not sent (each would wait out
        its time-out again before the run can report)."""
        with self._turns:
            # this thread's own place or hold left by an exception (see _busy): given up first
            stale = [t for t in self._queue if t[0] == me]
            for t in stale:
                self._queue.remove(t)
            if self._busy == me:
                self._busy = None
            ticket = (me, object())
            try:
                self._queue.append(ticket)
                # the switch-off's own exchanges go before every queued one; the others in turn
                while self._busy is not None or (
                    self._off_thread != me and (self._off_thread is not None or self._queue[0] is not ticket)
                ):
                    self._turns.wait()
            finally:
                if ticket in self._queue:  # taken, refused below, or interrupted: the next one's turn
                    self._queue.remove(ticket)
                self._turns.notify_all()
            if (
                self._off_thread != me
                and self.off_failed is not None
                and isinstance(self.off_failed.__cause__, NoReply)
            ):
                raise NoReply(f"{shown_name(self.port)}: {line} not sent: the controller did not answer the switch-off")
            trips = getattr(self._local, "trips", None)
            # (set_values()'s change while on; never this thread's own switch-off, a fail-safe's
            # inside a failed command of the change)
            if trips is not None and trips != self._trips and self._off_thread != me:
                raise DeviceError(
                    f"{shown_name(self.port)}: {line} not sent: another thread switched X-rays off for a fault"
                )
            epoch = getattr(self._local, "epoch", None)
            if epoch is not None and epoch != self._routine_epoch:
                raise SwitchedOff(
                    f"{shown_name(self.port)}: {line} not sent: X-rays are being switched off (or a stop was asked) "
                    f"during this reading (it cannot vouch for the beam)"
                )
            self._busy = me

    def _claim_off(self, me: int) -> None:
        """An exchange failed while the beam may be on: this thread will switch off (in
        :meth:`_fail_safe`), so it takes the switch-off before releasing the link."""
        with self._turns:
            if self._may_be_on and self.off_failed is None and self._off_thread is None:
                self._off_thread = me

    def _release_off(self, me: int) -> None:
        with self._turns:
            if self._off_thread == me and not self._off_running:
                self._off_thread = None
                self._turns.notify_all()

    def _fail_safe(self, cause: Exception) -> None:
        """A failed exchange while the beam may be on: switch off before reporting it -- unless
        this is inside a switch-off, another thread is switching off (it reports), or a
        switch-off has failed already and said so (one owner retries)."""
        me = threading.get_ident()
        if self._off_thread == me and self._off_running or self._off_thread not in (None, me):
            return
        if not self._may_be_on:
            self._release_off(me)
            return
        # INFO, as _trip's: ``cause`` is raised to the caller right after, and the caller's error
        # line is the one the operator reads; an ERROR here said "no reply to SAR" twice on the
        # terminal (s43). The notebook keeps both; an unconfirmed switch-off is logged on its own.
        # ``fail_safe`` marks the cause as a fault that switched off (a run names it when it
        # stopped on something else, as it names a trip)
        cause.fail_safe = True
        if self.off_failed is not None:  # one switch-off has failed already and said so: no second wait
            self._release_off(me)
            logger.info(
                "%s: %s; X-rays were not confirmed off before (%s)",
                shown_name(self.port),
                self._unported(cause),
                self._unported(self.off_failed),
            )
            return
        logger.info("%s: %s; switching X-rays off", shown_name(self.port), self._unported(cause))
        try:
            self.off()
        except DeviceError as exc:
            self._log_off_failure(exc)
        except BaseException:
            # a stop (Ctrl-C) cut this switch-off short: ``cause`` never reaches the caller, whose
            # line says only the stop -- the terminal read "stopped by SIGINT; tube off" and never
            # why the beam had gone off (review s43rr2). Said here, then, once
            logger.error(
                "%s: %s; X-rays were being switched off for it when stopped",
                shown_name(self.port),
                self._unported(cause),
            )
            raise

    def _unported(self, exc) -> str:
        """``exc``'s message without the port it begins with (the transport's and the driver's
        name it): a line that names the port itself names it once."""
        text = str(exc)
        said = shown_name(self.port)  # as the messages name it
        return text[len(said) + 2 :] if text.startswith(f"{said}: ") else text

    def tell_off_failure(self, exc) -> None:
        """Log a switch-off that was not confirmed (``exc``, what :meth:`off` raised), as this
        driver logs its own: for a caller that called :meth:`off` itself (the series, its beam
        monitor), so that the Python API's log says each failure once, CRITICAL, whoever met it."""
        self._log_off_failure(exc)

    def _log_off_failure(self, exc) -> None:
        """Log a switch-off that was not confirmed, loud (CRITICAL, marked :data:`OFF_FAILURE`),
        but not again in the same words: the fail-safe, an error path's best effort and close()
        may each try once more and fail alike, and the log then read as three failures."""
        text = self._off_not_confirmed(exc)
        if text == self._off_failure_logged:
            return
        self._off_failure_logged = text
        logger.critical("%s: %s", shown_name(self.port), text, extra={OFF_FAILURE: True})

    def _off_not_confirmed(self, exc) -> str:
        """A failed switch-off's line after the port (off_failed says it already)."""
        text = self._unported(exc)
        return text if text.startswith("could not confirm X-rays off") else f"could not confirm X-rays off: {text}"

    # ---- readings ----
    def status(self) -> SourceState:
        """The controller's state: ``STS``, and when it says standby the warm-up query too (A
        ``SWE``, B ``DAG``), so that a warm-up the controller reports not done reads WARMUP_NEEDED
        in both dialects. B's ``STS`` says ``STANDBY`` while ``DAG`` says ``YET``; L8121.md does not
        relate A's ``STS 2`` and ``SWE`` either (and a unit may mix the dialects), and its rule
        is never ``XON`` "before warm-up is done": standby alone is not taken as done (in A,
        unless ``config.standby_needs_warmup_done`` is false). A's ``STS 2`` beside ``SWE 1``
        (running) reads WARMING_UP: a warm-up ending, ``SWE`` a poll behind ``STS``."""
        state = self._read("state")
        asks = self.dialect is DIALECT_B or self.config.standby_needs_warmup_done
        if state == SourceState.STANDBY and asks:
            value = self._read("warmup")
            if isinstance(value, Aging):
                return state if value.done else SourceState.WARMUP_NEEDED
            if value == WarmupState.RUNNING:
                # A's SWE 1 beside STS 2: a warm-up ending, its two queries a poll apart (the
                # notes do not say they change together); read as needed, its wait took a
                # finished warm-up for one that stopped. Not standby either: no XON until SWE 0
                return SourceState.WARMING_UP
            if value != WarmupState.DONE:
                return SourceState.WARMUP_NEEDED
        return state

    def settled_status(self, timeout_s: float | None = None) -> SourceState:
        """The controller's state once its power-on checks are over (:meth:`status` otherwise).

        A controller switched on just before the session may still be checking itself: A's
        ``STS 6`` (self-test), B's ``STS ERROR`` (pre-heating), or either's "not ready" while the
        interlock reads closed (with it open, "not ready" is the door, not the checks, and is
        returned at once). These pass by themselves, so :meth:`warm_up` and :meth:`on` ask this
        instead of failing at the first ``STS``: it reads ``STS`` every ``poll_s`` until the state
        is another one, for at most ``timeout_s`` (default ``config.ready_timeout_s``, 30 s).
        Queries only: nothing here can switch X-rays on.

        Raises
        ------
        DeviceError
            Still checking after ``timeout_s`` (one line naming the state and the setting).
        """
        limit = self.config.ready_timeout_s if timeout_s is None else timeout_s
        said = time_refusal("ready_timeout_s", limit)  # the configuration's bound: queries only, but a wait
        if said is not None:
            raise ValueError(
                f"{shown_name(self.port)}: timeout_s = {shown(limit)} (ready_timeout_s): {said}; nothing sent"
            )
        limit = float(limit)
        t0 = time.monotonic()
        state = self.status()
        told = False
        while self._checking(state):
            waited = time.monotonic() - t0
            if waited >= limit:
                beam = self._beam_measured(state)
                raise DeviceError(
                    f"{shown_name(self.port)}: the controller's power-on checks did not finish within ready_timeout_s = "
                    f"{limit:g} s (still {state.said}{beam}); look at the controller (or raise [source] ready_timeout_s)"
                )
            if not told:
                logger.warning(
                    "%s: controller still in its power-on checks (state %s): waiting up to %g s",
                    shown_name(self.port),
                    state.said,
                    limit,
                )
                told = True
            time.sleep(min(self.config.poll_s, max(limit - waited, 0.0)))
            state = self.status()
        if told:
            logger.info(
                "%s: power-on checks over after %.1f s (state %s)", self.port, time.monotonic() - t0, state.name
            )
        return state

    def _beam_measured(self, state: SourceState) -> str:
        """For a state that does not show X-rays off (B's ``STS ERROR``: pre-heating by L8121.md,
        and how B refuses): whether the measured values show a beam (an earlier session left it
        on). If they do, or cannot be read, this session will switch off, confirmed, before it lets
        the link go (:meth:`close`, a series' exit); returns the words that say so, or ``""``."""
        if state.confirms_off:
            return ""
        try:
            kv, ua = self.measured()
        except DeviceError as exc:
            self._may_be_on = True
            return f", which does not show X-rays off, and the measured values cannot be read ({exc})"
        if kv > 0 or ua > 0:
            self._may_be_on = True
            return f", which does not show X-rays off, with {kv:g} kV {ua:g} µA measured: X-rays are switched off"
        return ""

    def _checking(self, state: SourceState) -> bool:
        """Whether ``state`` is one the controller leaves by itself after power-on."""
        if state in (SourceState.SELF_TEST, SourceState.PREHEATING):
            return True
        return state == SourceState.NOT_READY and self.interlock_closed()

    def _beam_reading(self, *, stop_early: bool = False) -> tuple[SourceState, float, float]:
        """State, measured kV and µA (A: one ``SAR``; B: ``STS``, ``SHV``, ``SCU``). ``stop_early``:
        in B, when ``STS`` already says the beam is not on, do not spend two more exchanges before
        switching off (the values are then NaN)."""
        if "beam" in self.dialect.readings:
            return self._read("beam")[:3]
        state = self._read("state")
        if stop_early and state != SourceState.XRAY_ON:
            return state, math.nan, math.nan
        return state, self._read("voltage_kv"), self._read("current_ua")

    def _reading_time(self) -> float:
        """When this thread's last reply came (``time.monotonic()``): a reading's time, for a ramp's
        judgement that two threads feed (:class:`_RampWatch`), not when it is judged."""
        return getattr(self._local, "replied_at", None) or time.monotonic()

    def measured(self) -> tuple[float, float]:
        """Measured tube voltage (kV) and current (µA) (A: ``SAR``; B: ``SHV``, ``SCU``)."""
        if "beam" in self.dialect.readings:
            return tuple(self._read("beam")[1:3])
        return self._read("voltage_kv"), self._read("current_ua")

    def setpoint(self) -> tuple[float, float]:
        """Set tube voltage (kV) and current (µA) (A: ``SVI``; B: ``SPV``, ``SPC``)."""
        if "setpoint" in self.dialect.readings:
            return self._read("setpoint")
        return self._read("set_voltage_kv"), self._read("set_current_ua")

    def interlock_closed(self) -> bool:
        """Whether the interlock is closed (A: ``SIN 0``; B: ``INTER LOCK ON``)."""
        return self._read("interlock_closed")

    def warmup_state(self) -> WarmupState:
        """The warm-up: DONE, RUNNING or NOT_STARTED (A: ``SWE``; B: ``DAG``, with ``STS AGING`` for
        RUNNING)."""
        value = self._read("warmup")
        if isinstance(value, WarmupState):
            return value
        if value.done:
            return WarmupState.DONE
        return WarmupState.RUNNING if self._read("state") == SourceState.WARMING_UP else WarmupState.NOT_STARTED

    def error_code(self) -> int:
        """The controller's error code (``SER``), 0 for none."""
        return self._read("error")

    def _require_no_controller_error(self, what: str) -> None:
        """Raise :class:`SourceFault` (``what``: "X-rays not switched on", "warm-up not started")
        when the controller reports an error (``SER`` not 0). Asked last before each X-ray command:
        L8121.md relates the code to no state and does not say ``XON`` is refused for it (B's
        1-4 are relay or internal faults of the control board), so a unit may read standby and
        emit with one standing. Nothing is reset: the notes give ``RST`` for an overload only and
        say nothing of how a code clears. The configuration's ``allowed_error_codes`` pass, and
        ``error_query = false`` (a unit without ``SER``) asks nothing."""
        if not self.config.error_query:
            return
        asked = time.time()
        try:
            code = self.error_code()
        except DeviceError as exc:
            if getattr(exc, "refused", False):
                raise DeviceError(
                    f"{exc}: this unit does not report an error code before X-rays; if it has no SER, "
                    "set error_query = false in its [source] configuration"
                ) from exc
            raise
        finally:
            self._error_read_at = time.monotonic()  # the beam's SER interval starts here (XON follows)
        if self._error_cleared(code, asked):
            return
        raise SourceFault(
            f"{shown_name(self.port)}: {what}: the controller reports error code {code} (SER {code}: {self._error_meaning(code)}); "
            f"no X-ray command was sent and nothing was reset. L8121.md does not say how the code clears: "
            f"see to the unit, then try again (a code the unit's manual calls harmless: allowed_error_codes "
            f"in its [source] configuration)"
        )

    def _error_cleared(self, code: int, asked: float) -> bool:
        """Whether ``code``, read by a ``SER`` asked at ``asked`` (``time.time()``), is no fault
        (0, or one the configuration allows); if so, frames up to ``asked`` are vouched for."""
        if code == 0 or code in self.config.allowed_error_codes:
            self._error_good_at = asked
            return True
        return False

    def _error_meaning(self, code: int) -> str:
        """What L8121.md says of the non-zero error ``code`` in this dialect."""
        if self.dialect is DIALECT_B:
            return (
                "a relay or internal fault of the control board, by L8121.md's dialect B notes"
                if 1 <= code <= 4
                else "not among L8121.md's dialect B codes (0 none, 1-4 relay or internal faults)"
            )
        return "L8121.md gives dialect A's error codes no meaning beyond 0, none"

    def _watch_error_code(self, when: str) -> None:
        """With the beam on: read ``SER`` when ``config.error_poll_s`` has passed since it was last
        read, and switch off (:meth:`_trip`, ``XOF`` confirmed by ``STS``) on a code the
        configuration does not allow, naming it and ``when`` ("with the beam on"). L8121.md: B's
        1-4 are relay or internal faults, a reason to stop high voltage; before s47ser a code that
        came up mid-exposure went unnoticed until the next on() refused. A garbled or refused
        reply is the fail-safe's, as any poll's (:meth:`_read`). ``error_query = false``: nothing.

        The :class:`SourceFault` carries ``vouched_until``, the ``time.time()`` of the last ``SER``
        that read no fault: the code may have stood since, so a series' beam monitor vouches for
        no frame after it (its other polls did not ask)."""
        if not self.config.error_query:
            return
        now = time.monotonic()
        if self._error_read_at is not None and now - self._error_read_at < self.config.error_poll_s:
            return
        self._error_read_at, asked, good = now, time.time(), self._error_good_at
        code = self.error_code()
        if self._error_cleared(code, asked):
            return
        try:  # the code is the cause: not asked again after the switch-off
            self._trip(f"controller error code {code} {when} (SER {code}: {self._error_meaning(code)})", ask_code=False)
        except SourceFault as err:
            err.vouched_until = good if good is not None else float("-inf")
            raise

    def error_code_after_beam(self) -> None:
        """After a beam period's normal ``XOF``: read ``SER`` once, the tube off, so that the
        period's last second (a poll within ``error_poll_s`` of the last read skips it, and
        after a series' last period nothing reads it again) is vouched for by a read too, without
        holding the switch-off back. A code not allowed raises :class:`SourceFault` naming it; it
        and a failed read carry ``vouched_until`` (see :meth:`_watch_error_code`). Nothing is
        switched or reset. ``error_query = false``: nothing."""
        if not self.config.error_query:
            return
        asked, good = time.time(), self._error_good_at
        vouched = good if good is not None else float("-inf")
        try:
            code = self.error_code()
        except DeviceError as err:
            err.vouched_until = vouched
            raise
        finally:
            self._error_read_at = time.monotonic()
        if self._error_cleared(code, asked):
            return
        err = SourceFault(
            f"{shown_name(self.port)}: controller error code {code} read after X-rays were switched off (SER {code}: "
            f"{self._error_meaning(code)}); it may have stood since the last read with the beam on"
        )
        err.vouched_until = vouched
        raise err

    def operate_switch(self) -> str:
        """Dialect B's operate switch (``SRL``): ``REMOTE``, ``LOCAL`` or ``OFF``."""
        return self._read("operate_switch")

    @property
    def focus(self) -> int:
        """Focus mode (A: ``SFC n`` / ``CFS n``; B: ``SFS`` / ``CFS``, ``CFM``, ``CFL`` as 0, 1, 2)."""
        return self._read("focus")

    @focus.setter
    def focus(self, value: int) -> None:
        self.check_focus(value)
        # remembered before it is sent: a setting that fails here is tried again, and refused
        # again, before the next XON rather than forgotten
        self.focus_wanted = value
        self._set_focus(value)

    def _set_focus(self, value: int) -> None:
        self._do("focus", value)
        # an echo says the command arrived, not that the unit took it: a series must not expose (and
        # record) a focal spot the unit is not using, so the setting is read back as kV and µA are
        got = self._read("focus")
        if got != value:
            raise DeviceError(f"{shown_name(self.port)}: focus: the controller reads back {got} after {value} was set")

    def check_focus(self, value: int) -> None:
        """Refuse a focus mode this dialect and configuration cannot set (``ValueError``); nothing
        is sent. For a caller that sets the focus after an X-ray command (the warm-up) and must
        know before it that the setting is valid."""
        self.dialect.settings["focus"].line(self, value)

    # ---- operations ----
    def validate(self, kv: float, ua: float, *, exposure: bool = False) -> tuple[int, int]:
        """Check a voltage and current against the configuration and the ratings; nothing is sent.

        Returns the whole numbers that would be sent (rounded half up, with a logged warning when
        rounding changed a value). Raises ``ValueError`` naming the parameter and the limit
        (:meth:`SourceConfig.check_exposure`). With ``exposure``, the values of a beam to be judged
        stable at them (:meth:`on`, :meth:`set_values` while on): the tolerances too, the defaults
        included, at the whole numbers that will be sent -- a tolerance wider than
        ``1 - beam_drop_fraction`` of the setting counts a beam the monitor calls dropped as
        stable. Not for a warm-up's values: no beam is judged against them. The command line
        checks its --kv and --ua with this before it opens the port, and hands the whole numbers
        on, so that the rounding is said once.
        """
        self.config.check_exposure(kv, ua)
        kv_i, ua_i = _whole(kv, "tube voltage", "kV"), _whole(ua, "tube current", "µA")
        self.config.check_exposure(kv_i, ua_i)
        if exposure:
            self.config.check_tolerances(kv_i, ua_i)
        return kv_i, ua_i

    def set_values(self, kv: float, ua: float) -> tuple[int, int]:
        """Set tube voltage (kV) and current (µA), whole numbers (rounded half up, with a warning).

        Validated first (:meth:`validate`). While X-rays are off dialect B sets the presets
        (``PHV``, ``PCU``), while on ``HIV``, ``CUR``; dialect A always ``HIV``, ``CUR``. The order is
        chosen so that no intermediate pair exceeds ``watts_max``. Returns the values sent.

        While this driver keeps the beam on, it then waits (as :meth:`on` does) until the measured
        values are within tolerance of the new ones, so that :meth:`check` judges the beam against
        the new setting; any failure switches off. From the first command until then, the wait and
        a beam monitor's :meth:`check` judge the ramp alike (:class:`_RampWatch`: above the higher
        setting, fallen back after climbing, or under the drop bound longer than this unit's ramp
        after XON allows), and a fault either one trips is what this raises.
        """
        beam_on = self._beam is not None
        # the tolerances only for a beam judged stable at these values (a warm-up's, and the
        # presets before on(), are not: on() judges its own)
        kv_i, ua_i = self.validate(kv, ua, exposure=beam_on)
        voltage, current = ("voltage", "current") if beam_on else ("preset_voltage", "preset_current")
        try:
            # while on, B's SPV/SPC read the presets (PHV/PCU), which HIV/CUR are not said to change
            # (L8121.md): the tube's values are the ones this driver last set and saw stable
            _, old_ua = self._beam if beam_on and self.dialect is DIALECT_B else self.setpoint()
            self._beam_from = self._beam  # (None while off)
            if beam_on:
                # the new setting and the ramp's judgement before the first command: a unit may start
                # its ramp at that one (from zero: at once under the old setting's drop bound), and a
                # beam monitor's check() meanwhile judges by both settings, as the wait does
                self._beam = (kv_i, ua_i)
                self._ramp_watch = self._watch_ramp((kv_i, ua_i), after_xon=False)
                self._changes += 1
            trips = self._trips  # (a beam monitor's trip meanwhile: _tripped_elsewhere)
            order = [(voltage, kv_i), (current, ua_i)]
            if kv_i * old_ua / 1000 > min(self.config.watts_max, RATINGS.watts_max):
                order.reverse()
            for name, value in order:
                # a beam monitor's check() switched off for a fault meanwhile: no setting sent to
                # the tube it switched off (_take_turn), and its cause said (B's CUR, for a tube
                # on only, said "refused by the controller", the cause said by the monitor alone)
                # (a DeviceError only: a stop, KeyboardInterrupt, stays a stop and waits for nothing)
                self._local.trips = trips if beam_on else None
                try:
                    self._do(name, value)
                except DeviceError:
                    if beam_on:
                        self._raise_tripped_elsewhere(trips)
                    raise
                finally:
                    self._local.trips = None
                if beam_on:
                    self._raise_tripped_elsewhere(trips)
            if not beam_on:
                # the next command may be an X-ray command (on(), a warm-up): it goes only after the
                # controller has read back what it will emit at (a wrong voltage_scale shows here)
                self._read_back(kv_i, ua_i)
            if beam_on:
                self._wait_stable(kv_i, ua_i, time.monotonic(), watch=self._ramp_watch, trips=trips)
        except BaseException:
            if beam_on:
                self._off_quietly()
            raise
        finally:
            self._beam_from, self._ramp_watch = None, None
        return kv_i, ua_i

    def _read_back(self, kv: int, ua: int) -> tuple[float, float]:
        """Read the set values back (A: ``SVI``; B: ``SPV``, ``SPC``) and require the whole
        ``kv``, ``ua`` just sent; raises :class:`DeviceError` otherwise (no X-ray command follows)."""
        got_kv, got_ua = self.setpoint()
        if abs(got_kv - kv) >= 0.5 or abs(got_ua - ua) >= 0.5:
            raise DeviceError(
                f"{shown_name(self.port)}: the controller reads back {got_kv:g} kV {got_ua:g} µA after {kv} kV {ua} µA were "
                f"set (voltage_scale {self.voltage_scale:g}); no X-ray command sent"
            )
        return got_kv, got_ua

    def warm_up(
        self,
        timeout_s: float | None = None,
        progress: bool | Callable[[float, SourceState], Any] = True,
        *,
        force: bool = False,
        kv: float | None = None,
        ua: float | None = None,
    ) -> float:
        """Run the controller's warm-up sequence and wait until it reports standby.

        Warm-up emits X-rays: it is started only when needed (or ``force``), with the interlock
        closed, and an interrupted or failed warm-up is switched off like an exposure. Dialect A
        sends ``WUP``; dialect B sends ``XON`` only while ``DAG`` says ``YET`` (an ``XON`` with the
        warm-up done would be an exposure), and switches off if the controller answers it with
        X-rays on instead of ``AGING``. A warm-up seen running that ends in X-rays on rather than
        standby is switched off (confirmed) and counts as done if the controller reports it done;
        one read done but never read running (shorter than a poll, or a unit whose ``STS`` never
        says so) is switched off too, confirmed, before it is called done -- but a forced one (A,
        from standby with the warm-up done, which is also what the unit reads until it begins) is
        waited for ``warmup_start_s`` first, and never read running is switched off and "did not
        start", not done. It waits first for the controller's power-on checks (:meth:`settled_status`).

        Parameters
        ----------
        timeout_s : float, optional
            Longest wait; default ``config.warmup_timeout_s``.
        progress : bool or callable
            ``True``: a tqdm bar of elapsed seconds; a callable gets ``(elapsed_s, state)`` at every
            poll; ``False``: quiet.
        force : bool
            Dialect A: send ``WUP`` even when the warm-up is done. Refused in dialect B.
        kv, ua : float, optional
            The tube voltage and current to set before the warm-up starts (both or neither).
            ``L8121.md`` does not say what a warm-up emits at; B's warm-up is an ``XON``, which
            emits at the presets, and a warm-up that runs on into X-rays on keeps them. So before
            the start command (A ``WUP``, B ``XON``) the set values are made valid in both
            dialects: given, they are checked (nothing sent when out of range), set (A ``HIV``,
            ``CUR``; B ``PHV``, ``PCU``) and read back (A ``SVI``; B ``SPV``, ``SPC``); not given,
            the lowest-power values the configuration allows (``kv_min``, ``ua_min``: 40 kV 0 µA
            by default) are set and read back the same way. A refusal or another read-back stops
            the warm-up before any X-ray command, and so does a controller error code (``SER`` not
            0, asked last, after the interlock: :class:`SourceFault`, nothing reset) and (B) a
            ``DAG`` read last that no longer says ``YET`` (its ``XON`` would be an exposure). What was set is kept in :attr:`warmup_values`
            (``(kv, ua, given)``; None: no warm-up was started).

        Returns
        -------
        float
            Seconds waited (0 when nothing was needed).

        Raises
        ------
        DeviceError
            Not ready, not in standby within ``timeout_s``, the sequence stopped, or X-rays came on
            as an exposure; X-rays have been switched off.
        SourceFault
            Overload (not reset automatically), the interlock is open, or the controller reports
            an error code before the start command.
        """
        timeout_s = self.config.warmup_timeout_s if timeout_s is None else timeout_s
        said = time_refusal("warmup_timeout_s", timeout_s)  # the configuration's bound, before the warm-up emits
        if said is not None:
            raise ValueError(
                f"{shown_name(self.port)}: warm-up timeout_s = {shown(timeout_s)} (warmup_timeout_s): {said}; nothing sent"
            )
        timeout_s = float(timeout_s)
        if (kv is None) != (ua is None):
            raise ValueError(f"{shown_name(self.port)}: warm_up() takes kv and ua together (or neither); nothing sent")
        wanted = None if kv is None else self.validate(kv, ua)  # checked before anything is sent
        self.warmup_values = None
        state = self.settled_status()
        self.warmup_joined = state == SourceState.WARMING_UP  # one already running: waited for, not set
        if not self._warm_up_needed(state, force):
            return 0.0
        seen = self._reconnects()
        if state != SourceState.WARMING_UP:  # a start command follows: its settings first
            if self._require_remote("warm-up not started"):  # B's start is XON, as on()'s
                # SRB said BUSY and was waited for (up to ready_timeout_s): the state that chose
                # to start is read again, as on()'s (an overload meanwhile: never XON then)
                again = self.settled_status()
                if again != state:
                    self._warm_up_needed(again, force)  # its refusal: overload, X-rays on, not ready
                    raise DeviceError(
                        f"{shown_name(self.port)}: warm-up not started: the state changed while SRB said BUSY "
                        f"({state.said} before, {again.said} now); run it again"
                    )
            self.warmup_values = self._warm_up_values(wanted)
            if not self.interlock_closed():  # again, last before the start command (as on())
                raise SourceFault(
                    f"{shown_name(self.port)}: warm-up not started: it emits X-rays and the interlock is open"
                )
            self._require_no_controller_error("warm-up not started")  # it emits (B's may run on into XON)
            self._require_warm_up_still_due()
        bar = None
        if progress is True:
            from radiokit.progress import tqdm

            bar = tqdm(total=round(timeout_s), desc=f"L8121 warm-up ({shown_name(self.port)})", unit="s", leave=False)
        t0 = time.monotonic()
        self._may_be_on = True  # the warm-up sequence runs the tube
        try:
            if state != SourceState.WARMING_UP:
                self._refuse_after_reconnect(seen, "warm-up not started", "start it again")
                self._do("warm_up")
                logger.info(
                    "%s: warm-up started with %s (timeout %g s)",
                    shown_name(self.port),
                    self.dialect.settings["warm_up"].command,
                    timeout_s,
                )
            # a forced start from standby with the warm-up done (A): those are also what the unit
            # reads until the warm-up begins, so they say nothing until warmup_start_s is over
            self._wait_warm(t0, timeout_s, bar, progress, from_done=state == SourceState.STANDBY)
        except BaseException:
            self._off_quietly()
            raise
        finally:
            if bar is not None:
                bar.close()
        self._may_be_on = False
        elapsed = time.monotonic() - t0
        logger.info("%s: warm-up done in %.1f s", shown_name(self.port), elapsed)
        return elapsed

    def _warm_up_values(self, wanted: tuple[int, int] | None) -> tuple[int, int, bool]:
        """Set, and read back, the values a warm-up will emit at, before its start command: the focus
        last asked for (:attr:`focus_wanted`), if any, and ``wanted`` (validated already), else the
        lowest-power ones the configuration allows (the tube off: A ``HIV``/``CUR``, B the presets
        ``PHV``/``PCU``). Raises before any X-ray command when the controller refuses them or reads
        back others."""
        given = wanted is not None
        if self.focus_wanted is not None:  # the warm-up emits at the unit's focal spot too (as every XON)
            try:
                self._set_focus(self.focus_wanted)
            except DeviceError as exc:
                raise DeviceError(f"{exc}; warm-up not started") from None
        if not given:
            c = self.config
            wanted = self.validate(math.ceil(max(c.kv_min, RATINGS.kv_min)), math.ceil(max(c.ua_min, 0.0)))
        try:
            self.set_values(*wanted)  # read back inside (_read_back)
        except DeviceError as exc:
            raise DeviceError(f"{exc}; warm-up not started") from None
        logger.info(
            "%s: warm-up settings %d kV %d µA (%s) set and read back",
            shown_name(self.port),
            *wanted,
            "given" if given else "the lowest the configuration allows",
        )
        return wanted[0], wanted[1], given

    def _warm_up_needed(self, state: SourceState, force: bool) -> bool:
        """Whether to start (or wait for) a warm-up; raises when one must not start now."""
        if state == SourceState.XRAY_ON:
            raise DeviceError(f"{shown_name(self.port)}: X-rays are on; call off() before warm_up()")
        if state == SourceState.OVERLOAD:
            raise SourceFault(f"{shown_name(self.port)}: overload; inspect the tube, then reset() by hand")
        if state not in (SourceState.WARMUP_NEEDED, SourceState.WARMING_UP, SourceState.STANDBY):
            raise DeviceError(f"{shown_name(self.port)}: warm-up not started: {self._not_ready()} (state {state.name})")
        if state == SourceState.STANDBY:
            if not force:
                return False
            if self.dialect is DIALECT_B:
                raise DeviceError(
                    f"{shown_name(self.port)}: warm-up not started: dialect B starts it with XON, and with the "
                    f"warm-up done (DAG ... END) that XON would be an exposure"
                )
        if state != SourceState.WARMING_UP and not self.interlock_closed():
            raise SourceFault(
                f"{shown_name(self.port)}: warm-up not started: it emits X-rays and the interlock is open"
            )
        return True

    def _wait_warm(self, t0: float, timeout_s: float, bar, progress, from_done: bool = False) -> None:
        seen_running = False
        while True:
            elapsed = time.monotonic() - t0
            state = self.status()
            seen_running |= state == SourceState.WARMING_UP
            if bar is not None:
                bar.n = min(round(elapsed), bar.total)
                bar.set_postfix_str(state.name, refresh=True)
            elif callable(progress):
                progress(elapsed, state)
            if state == SourceState.STANDBY and self.warmup_state() == WarmupState.DONE:
                if seen_running or self.warmup_joined:
                    return
                if not (from_done and elapsed <= self.config.warmup_start_s):
                    self._warm_up_unseen(elapsed, from_done)
                    return
            if state == SourceState.XRAY_ON:
                if not seen_running:  # the start command began an exposure, not a warm-up
                    self._trip("X-rays came on as an exposure instead of a warm-up (STS says X-rays on)")
                self._warm_up_ran_on(elapsed)
                return
            # the warm-up emits: the interlock rules of an exposure hold (a controller need not
            # stop by itself when it opens; L8121.md only says XON is refused then)
            if state.emitting and not self.interlock_closed():
                self._trip("interlock open during the warm-up")
            if state.emitting:
                self._watch_error_code("during the warm-up")
            if state == SourceState.OVERLOAD:
                raise SourceFault(
                    f"{shown_name(self.port)}: overload during warm-up; inspect the tube, then reset() by hand"
                )
            if state == SourceState.WARMUP_NEEDED and (seen_running or elapsed > self.config.warmup_start_s):
                # stopped, or never started although the start command was answered (the interlock
                # opened, the controller refused it silently): not a reason to wait out the time-out
                if seen_running or not self._warm_up_pending():
                    self._warm_up_stopped(elapsed, seen_running)
            if elapsed > timeout_s:
                # switched off here, as a beam not stable is: the line said "X-rays switched off"
                # before any XOF went, also when the switch-off then failed (s44)
                off, failed = self._off_for_fault()
                why = f"warm-up not done within {timeout_s:g} s (state {state.said})"
                raise self._switched_off(DeviceError, why, off, failed, ask_code=False) from failed
            time.sleep(self.config.poll_s)

    def _warm_up_ran_on(self, elapsed: float) -> None:
        """The warm-up (seen running) went on into X-rays on instead of back to standby: dialect B's
        ``AGING`` may end that way (L8121.md does not say it returns to ``STANDBY``). Nobody asked
        for that beam: switch off, confirmed (not confirmed, the error names the run-on first, then
        what the switch-off ran into), then the controller's own record says whether the warm-up
        counts as done (B ``DAG ... END``, A ``SWE 0``); if it does not, the warm-up failed."""
        logger.warning(
            "%s: the warm-up ran on into X-rays on after %.1f s (STS says X-rays on): switching off", self.port, elapsed
        )
        state, failed = self._off_for_fault()
        ran_on = f"the warm-up ran on into X-rays on after {elapsed:.1f} s"
        if failed is not None:  # its cause said with the failure, not the failure alone
            raise self._switched_off(DeviceError, ran_on, state, failed, ask_code=False) from failed
        if self.warmup_state() != WarmupState.DONE:
            why = f"{ran_on} and the controller does not report it done"
            raise self._switched_off(DeviceError, why, state, None, ask_code=False)
        logger.info(
            "%s: warm-up done (it ran on into X-rays on, switched off: state %s)", shown_name(self.port), state.name
        )

    def _warm_up_unseen(self, elapsed: float, from_done: bool) -> None:
        """The warm-up reads done (standby, A ``SWE 0`` / B ``DAG ... END``) but no poll read it
        running: shorter than a poll, or a unit whose ``STS`` never says warming up. Nothing read
        says the start command's beam is over -- L8121.md ties no state to its echo, and a state
        that follows late may yet start it (after A's forced ``WUP`` from standby, standby and done
        are also what a unit reads until it begins) -- so the tube is switched off (``XOF``, "always accepted"), confirmed by ``STS``,
        before the warm-up is called done and the tube off. That ``XOF`` is also what disarms
        the guardian's watchdog, which after a start command takes a standby as off only once
        the state has read on or an ``XOF`` passed (left by review s44rr2: its watchdog sent an
        unneeded ``XOF`` with a warning). Not confirmed: the warm-up fails, the operator told.
        ``from_done`` (A's forced ``WUP`` from standby, done): nothing changed since the start
        command for ``warmup_start_s`` -- no evidence a warm-up ran, so it is not called done
        (review s46rv: it was, on the first poll, and a unit that began late then emitted with the
        driver calling the tube off)."""
        state, failed = self._off_for_fault()
        if from_done:
            why = (
                f"warm-up did not start: {self.dialect.settings['warm_up'].command} was answered, but the "
                f"controller still read standby with the warm-up done after {elapsed:.1f} s, never running"
            )
            raise self._switched_off(DeviceError, why, state, failed, ask_code=False) from failed
        if failed is not None:
            why = f"the warm-up read done after {elapsed:.1f} s without ever reading it running"
            raise self._switched_off(DeviceError, why, state, failed, ask_code=False) from failed
        logger.info(
            "%s: warm-up read done, never running: switched off to be sure (%s)", shown_name(self.port), state.name
        )

    def _warm_up_pending(self) -> bool:
        """Whether a warm-up whose state still reads "needed" is under way all the same: dialect A's
        ``SPH 1`` (pre-heating; ``STS`` has no value for it) or its ``SWE 1`` (running). L8121.md
        does not say what ``STS`` reads while a unit pre-heats after ``WUP``: a unit answering
        ``STS 0`` then must not have every warm-up called "not started" after warmup_start_s."""
        if "preheating" in self.dialect.readings and self._read("preheating"):
            return True
        return self.warmup_state() == WarmupState.RUNNING

    def _warm_up_stopped(self, elapsed: float, started: bool):
        """Raise the error of a warm-up that stopped (``started``) or never started: a
        :class:`SourceFault` when the interlock is open, else a :class:`DeviceError` with the
        controller's error code."""
        what = (
            f"warm-up stopped after {elapsed:.1f} s"
            if started
            else (
                f"warm-up did not start: {self.dialect.settings['warm_up'].command} was answered, but the "
                f"controller still reports warm-up needed after {elapsed:.1f} s"
            )
        )
        if not self.interlock_closed():
            raise SourceFault(f"{shown_name(self.port)}: {what}: interlock open")
        # a unit configured without SER (error_query = false) would refuse the query here
        code = f", error code {self.error_code()}" if self.config.error_query else ""
        raise DeviceError(f"{shown_name(self.port)}: {what} (state WARMUP_NEEDED{code})")

    def on(self, kv: float, ua: float) -> dict[str, Any]:
        """Switch X-rays on at ``kv`` kV and ``ua`` µA and wait for a stable beam.

        Order: validate the values (:meth:`SourceConfig.check_exposure`; nothing sent yet); require
        standby with the warm-up done (A: ``STS 2`` and ``SWE 0``; B: ``STS STANDBY`` and ``DAG ... END``), a closed interlock
        and (B) the operate switch on REMOTE (queries only); set the values (A: ``HIV``, ``CUR``;
        B: ``PHV``, ``PCU``) and the focus last set (:attr:`focus_wanted`), each read back; the
        interlock again, the controller's error code (``SER``: anything but 0 refuses, nothing
        reset) and (B) ``DAG`` still ``END``; ``XON``; poll every ``poll_s`` until the measured values are within
        ``kv_tolerance`` / ``ua_tolerance`` of the set ones (the state may still read standby for
        ``xon_start_s`` after the echo, the interlock watched; past it, "X-rays did not come on").
        Any failure or interruption after ``XON`` switches off before the exception propagates,
        and so does a controller that answers the ``XON`` with a warm-up (``AGING``).

        Returns
        -------
        dict
            ``voltage_kv``, ``current_ua`` (measured), ``set_voltage_kv``, ``set_current_ua`` (sent,
            whole numbers), ``seconds`` (from ``XON`` to stable).

        Raises
        ------
        ValueError
            A value outside its range or the power limit (message names the limit), or a
            tolerance wider than ``1 - beam_drop_fraction`` of the setting (nothing sent).
        DeviceError
            Not in standby (warm-up needed, not ready), refused, or not stable within
            ``stable_timeout_s`` (X-rays switched off).
        SourceFault
            Interlock open, overload or a controller error code (``SER`` not 0, named with what
            L8121.md says it means) before switching on; overload, interlock, dropped beam or a
            warm-up instead of the exposure while waiting (X-rays switched off).
        """
        kv_i, ua_i = self.validate(kv, ua, exposure=True)
        self._require_ready()
        seen = self._reconnects()
        try:
            self.set_values(kv_i, ua_i)  # the beam is off: presets in B, no waiting
            if self.focus_wanted is not None:  # every XON, not the first: a reset says nothing
                self._set_focus(self.focus_wanted)
            # the interlock again, last before XON: the settings and their read-back took several
            # exchanges since _require_ready read it, and B's XON is not documented to refuse it open
            if not self.interlock_closed():
                raise SourceFault(f"{shown_name(self.port)}: X-rays not switched on: interlock open")
            self._require_no_controller_error("X-rays not switched on")  # last too: no fault standing
            self._require_warm_up_still_done()
            self._refuse_after_reconnect(seen, "X-rays not switched on", "switch on again")
            if self.before_xon is not None:
                self.before_xon(kv_i, ua_i)
            if getattr(self._transport, "watchdog_off", None):
                self._transport.watchdog_off = None  # told of the last beam, not of this one
            self._may_be_on = True
            self._do("xray_on")
            t0 = time.monotonic()
            self._beam = (kv_i, ua_i)
            reading = self._wait_stable(kv_i, ua_i, t0, after_xon=True)
        except BaseException:
            self._off_quietly()
            raise
        c = self.config
        self._xon_ramp = (reading["seconds"], (kv_i, ua_i), (c.tolerance_kv(kv_i), c.tolerance_ua(ua_i)))
        logger.info(
            "%s: X-rays on at %d kV %d µA: measured %g kV %g µA after %.2f s",
            shown_name(self.port),
            kv_i,
            ua_i,
            reading["voltage_kv"],
            reading["current_ua"],
            reading["seconds"],
        )
        return reading

    def _require_ready(self) -> None:
        self._require_standby()
        if self._require_remote("X-rays not switched on"):
            # B's SRB said BUSY and was waited for, up to ready_timeout_s: what kept the unit busy
            # may have changed the state read before (an overload, and L8121.md: never XON in
            # overload): read again, as the presets and XON follow
            self._require_standby()

    def _require_standby(self) -> None:
        """Standby with the warm-up done and the interlock closed, or the refusal saying why."""
        state = self.settled_status()
        reasons = {
            # which query said so: an A unit whose SWE reads 2 when none is due is configured, not
            # warmed up for nothing (standby_needs_warmup_done; review s30-h5)
            SourceState.WARMUP_NEEDED: "warm-up needed, "
            + (
                "as DAG says (YET)"
                if self.dialect is DIALECT_B
                else "as STS (0) or, at standby, SWE (not 0) says; [source] standby_needs_warmup_done = false "
                "for a unit whose SWE reads 2 when none is due"
            )
            + " (call warm_up())",
            SourceState.WARMING_UP: "warm-up still running",
            SourceState.XRAY_ON: "X-rays are already on (use set_values() or off())",
            SourceState.NOT_READY: None,  # asked below: the likeliest reason is the interlock
            SourceState.SELF_TEST: "controller in self-test",
            # B's ERROR is also how B refuses a query: called pre-heating alone, a refusal was misread
            SourceState.PREHEATING: "STS answers ERROR: pre-heating, or a refused query (dialect B does not say which)",
        }
        if state == SourceState.OVERLOAD:
            raise SourceFault(
                f"{shown_name(self.port)}: overload; X-rays not switched on. Inspect the tube, then reset() by hand"
            )
        if state != SourceState.STANDBY:
            why = reasons[state] or self._not_ready()
            raise DeviceError(f"{shown_name(self.port)}: X-rays not switched on: {why} (state {state.said})")
        if not self.interlock_closed():
            raise SourceFault(f"{shown_name(self.port)}: X-rays not switched on: interlock open")

    def _require_warm_up_still_done(self) -> None:
        """B: ``DAG`` still ``END``, read last before ``XON``. B's ``XON`` starts a warm-up when
        one is due (L8121.md), and :meth:`_require_ready`'s ``DAG`` came before the settings and
        their read-back (~0.7 s, ten exchanges, at the default spacing): the 8-hour rule falling
        due meanwhile turned the exposure's ``XON`` into a warm-up at the exposure's settings.
        A's ``XON`` is refused unless standby: it cannot start a warm-up."""
        if self.dialect is DIALECT_B and not self._read("warmup").done:
            raise DeviceError(
                f"{shown_name(self.port)}: X-rays not switched on: warm-up needed, as DAG now says (YET): the controller "
                "decided it while the settings were sent (call warm_up())"
            )

    def _require_warm_up_still_due(self) -> None:
        """B: ``DAG`` still ``YET``, read last before the warm-up's ``XON`` (the mirror of
        :meth:`_require_warm_up_still_done`): its first ``DAG`` came before the settings and their
        read-back, and a warm-up no longer due by then made that ``XON`` an exposure at the
        warm-up's settings (review s46rv; switched off only at the first poll)."""
        if self.dialect is DIALECT_B and self._read("warmup").done:
            raise DeviceError(
                f"{shown_name(self.port)}: warm-up not started: DAG now says it is done (END): its XON would be an "
                "exposure; nothing that emits was sent"
            )

    def _require_remote(self, what: str) -> bool:
        """B: the operate switch on REMOTE (``SRL``) before anything that leads to an ``XON``
        (L8121.md: "remote control needs REMOTE"); connect's check may be minutes old. Returns
        whether ``SRB`` said ``BUSY`` and was waited for (:meth:`_await_remote_ready`): what was
        read before is then that old."""
        if "operate_switch" in self.dialect.readings and (switch := self.operate_switch()) != "REMOTE":
            raise DeviceError(f"{shown_name(self.port)}: {what}: the operate switch is {switch}, not REMOTE")
        return self._await_remote_ready(what)

    def _await_remote_ready(self, what: str) -> bool:
        """B: wait while ``SRB`` says ``BUSY``, queries only, for at most ``ready_timeout_s``.
        L8121.md lists ``SRB`` (``READY`` or ``BUSY``, the remote operation state) and the L8121-02
        driver polls it; the notes do not say a busy unit refuses control commands, but a unit that
        did refused the presets at once (session 53, a second model of the notes). A unit that
        refuses ``SRB`` (a mix of dialects) is taken as ready: its control commands say if not.
        Returns whether it waited (``BUSY`` was read)."""
        query = self.dialect.readings.get("remote_state")
        if query is None:
            return False
        limit = self.config.ready_timeout_s
        t0 = time.monotonic()
        told = False
        while True:
            try:
                reply = self._exchange(query.command)
            except DeviceError as exc:
                if getattr(exc, "refused", False):
                    return told
                raise
            busy = self._parsed(query, reply) == "BUSY"
            waited = time.monotonic() - t0
            if not busy:
                if told:
                    logger.info("%s: remote operation READY after %.1f s", shown_name(self.port), waited)
                return told
            if waited >= limit:
                raise DeviceError(
                    f"{shown_name(self.port)}: {what}: the controller's remote operation stayed BUSY (SRB) for "
                    f"ready_timeout_s = {limit:g} s; look at the controller (or raise [source] ready_timeout_s)"
                )
            if not told:
                logger.warning("%s: remote operation BUSY (SRB): waiting up to %g s", shown_name(self.port), limit)
                told = True
            time.sleep(min(self.config.poll_s, max(limit - waited, 0.0)))

    def _not_ready(self) -> str:
        """Why a controller reports NOT_READY, where it can say: a unit may report state 5 while
        its interlock is open (L8121.md lists both without relating them), and "not ready" alone
        sends the operator looking at the controller rather than the door."""
        try:
            closed = self.interlock_closed()
        except DeviceError:
            return "controller not ready"
        return "controller not ready" if closed else "controller not ready: the interlock is open (close it first)"

    def _wait_stable(
        self,
        kv: int,
        ua: int,
        t0: float,
        *,
        after_xon: bool = False,
        watch: _RampWatch | None = None,
        trips: int | None = None,
    ) -> dict[str, Any]:
        """Poll until the measured values are within tolerance of ``kv``, ``ua``. ``after_xon``: the
        state may still read standby for ``xon_start_s`` (never once it has read X-rays on).
        ``watch``: the ramp's judgement (:class:`_RampWatch`), shared with a beam monitor's
        :meth:`check` meanwhile (set_values()'s); None: one of the wait's own. ``trips``: the count
        of trips (:attr:`_trips`) before the change began (another thread's since: its cause)."""
        c = self.config
        tol_kv, tol_ua = c.tolerance_kv(kv), c.tolerance_ua(ua)
        seen_on = False
        watch = watch if watch is not None else self._watch_ramp((kv, ua), after_xon=after_xon)
        trips = self._trips if trips is None else trips  # (another thread's trip meanwhile)
        while True:
            state, m_kv, m_ua = self._beam_reading(stop_early=True)
            seconds = time.monotonic() - t0
            # another thread (a beam monitor's check()) switches off for a fault meanwhile: its
            # cause, not the standby this reading may have found after its XOF ("beam dropped:
            # state STANDBY" was set_values()'s error, the real cause said by the monitor alone)
            self._raise_tripped_elsewhere(trips)
            seen_on |= state == SourceState.XRAY_ON
            if after_xon and not seen_on and self._coming_on(state, m_kv, m_ua, t0):
                time.sleep(c.poll_s)
                continue
            if state != SourceState.XRAY_ON:
                self._trip(self._reason_after_off(state, m_kv, m_ua, ramping=True))
            # a ramp that passes the setting, falls back after climbing, or stays under the drop
            # bound longer than any ramp of this unit could (_RampWatch): caught at that reading,
            # not by the stable wait's time-out (up to stable_timeout_s with the tube on)
            why = watch.see(m_kv, m_ua, self._reading_time())
            if why:
                self._trip(why)
            # the beam is on while it ramps: watch the interlock as check() does (B's poll has SIN)
            if not self.interlock_closed():
                self._trip("interlock open")
            self._watch_error_code("with the beam on")
            if abs(m_kv - kv) <= tol_kv and abs(m_ua - ua) <= tol_ua:
                return {
                    "voltage_kv": m_kv,
                    "current_ua": m_ua,
                    "set_voltage_kv": kv,
                    "set_current_ua": ua,
                    "seconds": seconds,
                }
            if seconds > c.stable_timeout_s:
                # switched off here, not by the caller's error path: the line then says what the
                # switch-off found (confirmed or not) and the controller's error code, as a trip's
                # does -- it said "X-rays switched off" before any XOF went (s43)
                off, failed = self._off_for_fault()
                why = (
                    f"beam not stable within stable_timeout_s = {c.stable_timeout_s:g} s: measured {m_kv:g} kV "
                    f"{m_ua:g} µA, set {kv} kV {ua} µA (tolerance {tol_kv:g} kV, {tol_ua:g} µA)"
                )
                raise self._switched_off(DeviceError, why, off, failed) from failed
            time.sleep(c.poll_s)

    def _watch_ramp(self, beam: tuple[int, int], *, after_xon: bool) -> _RampWatch:
        """The judgement of a ramp to ``beam`` (after XON, or set_values() from :attr:`_beam_from`).

        A reading's jitter is the tolerance at the higher of the old and the new setting
        (:meth:`_beam_span`), where the beam starts or ends: the new one alone, lower (250 -> 8 µA:
        2 µA, not 5), called a stable meter's two readings at the old setting a climb, and the fall
        of a unit that ramps again from zero a dropped beam (review s55rvacq).

        After a change, how long a value may stay under the drop bound before it climbs
        (:class:`_RampWatch`'s ``dwell_s``) comes from this unit's own ramp after XON
        (:attr:`_xon_ramp`, from zero to within tolerance of its setting in ``t_on``): L8121.md
        says the values ramp "after XON or a change" alike, not where from, nor how fast they fall.
        A ramp from zero to a new setting passes its drop bound no later than ``t_on`` if its
        duration is fixed, ``t_on * bound / reached`` if its rate is (``reached``: the XON
        setting less its tolerance). Its count starts where a fall ends (a unit may fall to
        nothing first, at a speed L8121.md does not give), up to two jitters above the bottom,
        and the ramp may wait there before it climbs, as XON's state may lag its echo (t_on holds
        that lag, a change's is not documented): twice that, ``2 * t_on * max(1, bound /
        reached)``, for each of kV and µA; the watch adds two of its longest gaps between
        readings (a reading shows the beam only when it is taken). A value the XON ramp did not
        raise (0 µA set) gives no bound."""
        c = self.config
        lower, higher = self._beam_span(beam)
        jitter = (
            max(c.tolerance_kv(beam[0]), c.tolerance_kv(higher[0])),
            max(c.tolerance_ua(beam[1]), c.tolerance_ua(higher[1])),
        )
        dwell = (math.inf, math.inf)
        if not after_xon and self._xon_ramp is not None:
            t_on, setting, tol = self._xon_ramp
            dwell = tuple(
                2 * t_on * max(1.0, c.beam_drop_fraction * low / (s - t)) if s - t > 0 else math.inf
                for low, s, t in zip(lower, setting, tol)
            )
        return _RampWatch(lower, higher, jitter, c.beam_drop_fraction, after_xon=after_xon, dwell_s=dwell)

    def _raise_tripped_elsewhere(self, trips: int) -> None:
        """Raise the fault another thread switched off for since :attr:`_trips` read ``trips``
        (:meth:`_tripped_elsewhere`), if it made one."""
        if self._trips != trips:
            elsewhere = self._tripped_elsewhere()
            if elsewhere is not None:
                raise elsewhere

    def _tripped_elsewhere(self) -> SourceFault | None:
        """The fault another thread switches off for while this one waits for a ramp, as this
        thread's exception (the same words and switch-off outcome), once that thread has made it:
        waited for as long as a switch-off may take (each attempt an XOF and an STS, a reply's wait
        each, and the controller's error code). None: not made by then (the switch-off itself
        failed with another error), and this thread goes on as before."""
        c = self.config
        wait_s = c.off_confirm_s + (2 * c.off_attempts + 1) * self.timeout_s
        with self._trip_made:
            self._trip_made.wait_for(lambda: self._last_trip[0] == self._trips, timeout=wait_s)
            number, other = self._last_trip
        if other is None or number != self._trips:
            return None
        err = SourceFault(str(other))
        err.switch_off = getattr(other, "switch_off", None)
        return err

    def _coming_on(self, state: SourceState, kv: float, ua: float, t0: float) -> bool:
        """Whether a reading after XON (answered at ``t0``), before the first X-rays-on one, is the
        state still following the echo: standby within ``xon_start_s`` (L8121.md ties no state to
        XON's echo; the values "ramp ... over a few seconds after XON"). The interlock is watched
        meanwhile; standby past ``xon_start_s`` is a beam that did not come on, switched off all the
        same."""
        if state != SourceState.STANDBY or getattr(self._transport, "watchdog_off", None):
            return False  # (a standby the guardian's watchdog made is its switch-off: _fault_reason names it)
        if not self.interlock_closed():
            self._trip(self._fault_reason(state, kv, ua, ramping=True, interlock_closed=False) or "interlock open")
        seconds = time.monotonic() - t0  # after SIN's exchange: the line says the time it waited in all
        if seconds > self.config.xon_start_s:
            self._trip(f"X-rays did not come on: state STANDBY {seconds:.1f} s after XON was answered")
        return True

    def _fault_reason(
        self,
        state: SourceState,
        kv: float,
        ua: float,
        *,
        ramping: bool = False,
        interlock_closed: bool | None = None,
        beam: tuple[int, int] | None = None,
    ) -> str | None:
        """Why the beam is not what this driver switched on (``beam``: its set kV and µA, default
        the ones kept now), or None when it is. Asks ``SIN`` when ``interlock_closed`` is None."""
        beam = self._beam if beam is None else beam
        if state == SourceState.OVERLOAD:
            return "overload"
        if state == SourceState.WARMING_UP:
            return "the controller is warming up (AGING) instead of emitting the exposure"
        if interlock_closed is None:
            interlock_closed = self.interlock_closed()
        if not interlock_closed:
            return "interlock open"
        if state == SourceState.PREHEATING:  # not a state the beam is known to be off in
            return f"STS {state.said} instead of XON: the beam may have dropped or be on still"
        if state != SourceState.XRAY_ON:
            # off because the guardian switched off for this process's silence: say so, not a fault of the tube
            told = getattr(self._transport, "watchdog_off", None)
            if told and state.confirms_off:
                return f"{told}; state {state.name}"
            return f"beam dropped: state {state.name} instead of XRAY_ON"
        if not ramping and beam is not None:
            f = self.config.beam_drop_fraction
            (set_kv, set_ua), high = self._beam_span(beam)
            dropped = None
            if ua < f * set_ua:
                dropped = f"measured current {ua:g} µA, below {f:.0%} of the set {set_ua} µA"
            elif kv < f * set_kv:
                dropped = f"measured voltage {kv:g} kV, below {f:.0%} of the set {set_kv} kV"
            above = _beam_above(kv, ua, *high, f)
            if dropped is None and above is not None:
                return f"beam above the setting: {above}"
            if dropped is not None:
                # B reads state, voltage and current in separate exchanges: a process stopped
                # after its STS read XON measures the beam the guardian's watchdog switched off
                # meanwhile (its word came with this reading's replies): the cause is known
                told = getattr(self._transport, "watchdog_off", None)
                return f"{told}; then {dropped}" if told else f"beam dropped: {dropped}"
        return None

    def _beam_span(self, beam: tuple[int, int]) -> tuple[tuple[int, int], tuple[int, int]]:
        """The lower and the higher of ``beam`` and the setting set_values() ramps the beam away
        from (each of kV and µA), or ``beam`` twice. While the beam ramps to a new setting
        (L8121.md: over a few seconds "after XON or a change") it lies between the two: a beam
        monitor's poll meanwhile judged it by the new one alone, and called 400 -> 100 µA "above
        the setting" and 100 -> 400 µA "dropped", switching off mid-hold (review s47rv3)."""
        was = self._beam_from
        if was is None:
            return beam, beam
        low, high = (min(a, b) for a, b in zip(beam, was)), (max(a, b) for a, b in zip(beam, was))
        return tuple(low), tuple(high)

    def _evident_fault(self, state: SourceState, kv: float, ua: float, *, ramping: bool = False) -> bool:
        """Whether a beam reading alone shows that the beam this driver keeps is not as set (a
        state other than X-rays on, or a measured value below ``beam_drop_fraction``): then it is
        switched off before anything else is asked (the interlock, for the message). ``ramping``:
        the state alone (the values are the ramp's judgement, :class:`_RampWatch`)."""
        return self._fault_reason(state, kv, ua, ramping=ramping, interlock_closed=True) is not None  # no SIN asked

    def _reason_after_off(self, state: SourceState, kv: float, ua: float, *, ramping: bool = False):
        """The fault's reason, to be worked out after the ``XOF`` (:meth:`_trip` calls it): ``SIN``
        (which tells an open interlock from a dropped beam) is asked only then, and only of a
        controller that confirmed the switch-off (``ask``); otherwise the reading names it."""
        beam = self._beam

        def reason(ask: bool) -> str:
            closed = None if ask else True
            try:
                why = self._fault_reason(state, kv, ua, ramping=ramping, interlock_closed=closed, beam=beam)
            except DeviceError:
                why = self._fault_reason(state, kv, ua, ramping=ramping, interlock_closed=True, beam=beam)
            return why or f"beam fault: state {state.said}, measured {kv:g} kV {ua:g} µA"

        return reason

    def _trip(self, reason: str | Callable[[bool], str], *, ask_code: bool = True):
        """Switch off and raise :class:`SourceFault` naming ``reason`` (or what ``reason(ask)``
        returns, called after the switch-off; see :meth:`_reason_after_off`). ``ask_code``: as
        :meth:`_switched_off`'s."""
        with self._trip_made:  # counted before its XOF: a wait that reads the tube off after it knows why
            self._trips += 1
            number = self._trips
        err = None
        try:
            state, failed = self._off_for_fault()
            if callable(reason):
                reason = reason(self.off_failed is None)
            if state == SourceState.OVERLOAD and not reason.startswith("overload"):
                # B reads state and current in separate exchanges: an overload between them looks
                # like a dropped beam until the STS after XOF says what it was
                reason = f"overload ({reason})"
            err = self._switched_off(SourceFault, reason, state, failed, ask_code=ask_code)
        finally:
            with self._trip_made:
                self._last_trip = (number, err)
                self._trip_made.notify_all()
        # the caller reports the SourceFault (the command line's error line; the series names a
        # fault it did not stop on): an ERROR here said the fault a second time on the terminal,
        # and for the guardian's watchdog a third. The notebook keeps it
        logger.info("%s", err)
        raise err from failed  # (its words: off_failed)

    def _off_for_fault(self) -> tuple[SourceState | None, DeviceError | None]:
        """Switch off for a fault: the state the switch-off confirmed (None: not confirmed) and
        the switch-off's error (:meth:`_switched_off` words the fault's exception from them)."""
        try:
            return self.off(), None
        except DeviceError as exc:
            # said as every unconfirmed switch-off is (CRITICAL, once; the command line says it
            # right above its X-RAYS warning), not only inside the fault's line
            self._log_off_failure(exc)
            return None, exc

    def _switched_off(self, kind: type[DeviceError], cause: str, state, failed, *, ask_code: bool = True):
        """The exception (of ``kind``) for a fault ``cause`` whose switch-off (:meth:`_off_for_fault`)
        confirmed ``state`` or failed with ``failed``: "<port>: <cause>; <what the switch-off
        found>", the outcome kept in its ``switch_off`` (:class:`OffOutcome`). With ``ask_code``,
        the controller's error code is asked after a confirmed switch-off (often why the beam is
        not what was set); not of a controller whose switch-off failed."""
        code = self._error_code_after_off() if ask_code else None
        outcome = OffOutcome(self.port, cause, state=state, failure=failed, error_code=code)
        err = kind(f"{shown_name(self.port)}: {cause}; {outcome.note}")
        err.switch_off = outcome
        return err

    def _error_code_after_off(self) -> int | None:
        """The code ``SER`` reads after a fault's switch-off, or None: 0, not asked (a controller
        whose switch-off failed), or not readable."""
        try:
            code = None if self.off_failed else self.error_code()
        except DeviceError:
            return None
        return code or None

    def check(self, *, error_code: bool = True) -> dict[str, Any]:
        """Poll once (A: ``SAR``, ``SIN``; B: ``STS``, ``SHV``, ``SCU``, ``SIN``) and stop on a fault.

        While this driver keeps the beam on (after :meth:`on`), an overload, an open interlock, a
        state other than X-rays on, or a measured current (or voltage) below
        ``beam_drop_fraction`` of the set value (or above it by as much: ``2 - beam_drop_fraction``
        of it) switches off and raises :class:`SourceFault` naming which; while :meth:`set_values`
        ramps the beam to a new setting, the measured values are judged as its wait judges them
        (:class:`_RampWatch`). Otherwise only an overload is a fault. A fault the beam reading shows by itself (the
        state, the measured values) is switched off before ``SIN`` is asked, for the message only.
        With the beam on, ``SER`` is read last, at most every ``error_poll_s``: a code not in
        ``allowed_error_codes`` switches off too (:meth:`_watch_error_code`). ``error_code=False``
        skips it: the poll just before a normal ``XOF``, whose ``SER`` (an exchange, or a reply
        time-out, more before the switch-off) is read after it instead (:meth:`error_code_after_beam`).

        A poll is routine: when another thread switches off meanwhile, that ``XOF`` goes right after
        the exchange on the link, and the poll sends nothing more and raises :class:`SwitchedOff`
        (it vouches for nothing).

        Returns
        -------
        dict
            ``state`` (:class:`SourceState`), ``voltage_kv``, ``current_ua`` (measured),
            ``interlock_closed``, ``time`` (``time.time()``), for the frame's metadata.
        """
        # routine: another thread's XOF goes before this poll's next query, and a poll begun while
        # one is pending or running sends nothing at all (it would read the tube switched off)
        with self._turns:
            pending = self._off_thread not in (None, threading.get_ident())
            self._local.epoch = -1 if pending else self._routine_epoch
        # the change under way as the reading starts, and how many have begun (set_values())
        changing, changes = self._ramp_watch, self._changes
        try:
            state, kv, ua = self._beam_reading(stop_early=self._beam is not None)
            # while set_values() ramps the beam to a new setting, its values are judged as its wait
            # judges them (the same watch): by the lower setting's drop bound alone, a unit that
            # ramps again from zero read dropped at once, and this poll switched it off
            watch = self._ramp_watch if self._beam is not None else None
            # a reading of a change's ramp that is judged once the change is over (this thread run
            # again only after set_values() returned, a change begun and over during a reading of
            # B's several exchanges) tells nothing of the beam the change then found stable: its
            # state alone. By the new setting alone, it was called dropped (review s56rvacq); by the
            # change's watch, out of order after the stable readings, fallen back
            stale = watch is None and (changing is not None or changes != self._changes)
            ramping = watch is not None or stale
            if self._beam is not None and self._evident_fault(state, kv, ua, ramping=ramping):
                # XOF first, then SIN for the message
                self._trip(self._reason_after_off(state, kv, ua, ramping=ramping))
            why = watch.see(kv, ua, self._reading_time()) if watch is not None else None
            if why:
                self._trip(why)
            if self._beam is None and state == SourceState.OVERLOAD:
                self._trip("overload")
            closed = self.interlock_closed()
            if self._beam is not None and not closed:
                self._trip("interlock open")
            if self._beam is not None and error_code:  # last: the beam checks above keep their period
                self._watch_error_code("with the beam on")
        finally:
            self._local.epoch = None
        return {"state": state, "voltage_kv": kv, "current_ua": ua, "interlock_closed": closed, "time": time.time()}

    def cancel_readings(self) -> None:
        """A stop is on its way: a routine reading in progress in another thread (:meth:`check`)
        sends nothing after the exchange on the link and raises :class:`SwitchedOff`, so the
        coming ``XOF`` is not queued behind it. Sends nothing; safe from any thread (a signal's
        watcher calls it before the main thread has begun to stop)."""
        with self._turns:
            self._routine_epoch += 1

    def off(self) -> SourceState:
        """Switch X-rays off (``XOF``) and confirm with ``STS`` that the tube no longer emits.

        Confirmed by a state that cannot emit (not X-rays on, not warming up / ``AGING``, not dialect
        B's ambiguous ``ERROR``). Tries ``off_attempts`` times: ``XOF``, then ``STS`` every
        ``poll_s`` while it still reads on, for ``off_confirm_s / off_attempts`` (a supply ramping
        down; an attempt that fails sooner, the port gone for a moment, waits that long before
        the next), but not again after an attempt that got no reply to either (a silent controller:
        each further attempt would cost two reply time-outs before the operator is told), nor
        after a refused ``XOF`` whose reason the controller gives (``SRL``, asked first, names
        B's operate switch off ``REMOTE``: it acts on no XOF until someone turns it; one ``STS``,
        no ramp-down). A refusal it does not explain (A, or B on ``REMOTE``) keeps the window: it
        may come while a first ``XOF`` ramps the supply down. Returns
        the state read after switching off. Until an ``off()`` confirms, a failed one is kept in
        :attr:`off_failed`.

        Raises
        ------
        DeviceError
            Not confirmed after ``off_attempts`` attempts: switch off at the controller.
        """
        me = threading.get_ident()
        self._local.epoch = None  # from here on this thread switches off: nothing it sends is routine
        attempts, last, silent, switch = int(self.config.off_attempts), None, False, None
        window = max(float(self.config.off_confirm_s), 0.0) / attempts
        # the ownership taken inside the try: a signal's stop landing as the with block is left
        # kept it taken, and every other thread's exchange waited until this one switched off
        # again (review s51rv; tests/test_l8121_stop_anywhere.py)
        try:
            with self._turns:
                waited = False
                while self._off_thread not in (None, me):  # another thread is switching off: its outcome
                    waited = True
                    self._turns.wait()
                if waited:
                    if self.off_failed is not None:
                        raise self.off_failed
                    return self._off_state
                self._off_thread, self._off_running = me, True
                self._routine_epoch += 1  # other threads' routine readings in progress send nothing more
            for attempt in range(attempts):
                if attempt:
                    time.sleep(self.config.poll_s)
                refused = False
                try:
                    self._do("xray_off")
                    silent = False
                except DeviceError as exc:
                    last, silent = exc, isinstance(exc, NoReply)  # still ask: the XOF may have arrived
                    refused = getattr(exc, "refused", False)
                # a refused XOF whose reason the controller gives (B's SRL off REMOTE) changed
                # nothing and will not: one STS says whether the tube was off already, no ramp-down
                # to wait for. A refusal it does not explain (A's ERR while a first XOF ramps the
                # supply down) keeps the window: the tube may still be going off
                told = self._switch_not_remote() if refused else None
                until = time.monotonic() + (0.0 if told is not None else window)
                state, last, silent = self._await_off(until, last, silent)
                if state is not None:
                    self._may_be_on, self._beam, self.off_failed, self._off_state = False, None, None, state
                    self._off_failure_logged = None  # a later failure is news again
                    logger.info("%s: X-rays off (state %s)", shown_name(self.port), state.name)
                    if self.unit_unverified:
                        logger.critical("%s", self.unverified_warning(state))
                    return state
                if silent:
                    # no reply to XOF nor STS: another attempt costs two more time-outs and
                    # reaches nobody; the operator must hear it now
                    break
                if told is not None:
                    # the controller says it will not act (B's operate switch off REMOTE): every
                    # further XOF is refused alike until someone turns it; the operator must hear it now
                    switch = told
                    break
                # an attempt that failed early (a port gone for a moment, a USB adapter coming back
                # under its name; a refused or garbled STS) waits its window out: the attempts span
                # off_confirm_s as a supply ramping down gets them, not 2 x poll_s all spent while
                # the node is still missing, the tube then left on although it could be reached
                if attempt + 1 < attempts:
                    time.sleep(max(0.0, until - time.monotonic() - self.config.poll_s))
            # still inside: a failed query here must not call off() again; a silent one is not asked
            if switch is None and not silent:
                switch = self._switch_not_remote()
            why = _not_remote(switch) if switch is not None else "; the controller does not answer" if silent else ""
            tried = f"{attempt + 1} attempt(s)"
            self.off_failed = DeviceError(
                f"{shown_name(self.port)}: could not confirm X-rays off after {tried} "
                f"(last: {self._unported(last)}){why}; switch the source off at the controller"
            )
            # the facts a caller decides on, as fields: its message is the operator's, free to be reworded
            self.off_failed.__cause__, self.off_failed.off_not_confirmed = last, True
            self.off_failed.operate_switch = switch  # the position it names (None: not named)
        finally:
            with self._turns:
                if self._off_thread == me:  # its own: a caller that waited for another's leaves it
                    self._off_thread, self._off_running = None, False
                self._turns.notify_all()
        raise self.off_failed from last

    def _reconnects(self) -> int:
        """How often the link has been reopened (its :class:`Reidentify`'s count; 0 without one)."""
        return self._reidentify.reconnects if self._reidentify is not None else 0

    def _refuse_after_reconnect(self, seen: int, what: str, then: str) -> None:
        """DeviceError when the link was reopened since ``seen`` (:meth:`_reconnects`), before a
        command that emits: a query retried on a reopened link passed a check of the unit's model
        only, and that unit may not hold the settings sent (or read back) before."""
        if self._reconnects() != seen:
            raise DeviceError(
                f"{shown_name(self.port)}: {what}: the link was lost and reopened after the settings were sent, and "
                f"the unit now at the port is known only by its model; {then}"
            )

    def unverified_warning(self, state: SourceState) -> str:
        """The operator's warning after an off confirmed by a unit known only by its model."""
        return (
            f"{shown_name(self.port)}: the link was lost and reopened while X-rays may have been on: STS "
            f"{state.name} confirms the unit now at the port, which the L8121 identifies only by its "
            "model (no serial number); if the adapter was re-plugged or the path moved, check by hand "
            "that the unit first connected is off"
        )

    def _await_off(self, until: float, last: Exception | None, silent: bool):
        """Ask ``STS`` (``poll_s`` apart) until it reads a state that cannot emit or ``until``
        (monotonic) has passed: a tube still ramping down reads on for a while after ``XOF``.
        Returns (the off state or None, the last error, whether neither XOF nor STS answered)."""
        while True:
            try:
                state = self._read("state")
            except DeviceError as exc:
                # a silent XOF and a silent STS: the caller stops; another error: the next attempt
                return None, exc, silent and isinstance(exc, NoReply)
            if state in _OFF_STATES:
                return state, last, False
            last = DeviceError(f"{shown_name(self.port)}: STS still {state.said} after XOF")
            if time.monotonic() + self.config.poll_s > until:
                return None, last, False
            time.sleep(self.config.poll_s)

    def _switch_not_remote(self) -> str | None:
        """B: the operate switch's position when not REMOTE (LOCAL, OFF), the likeliest reason a
        controller refuses XOF; None when it is REMOTE, unknown, or the dialect has none."""
        if self.dialect is None or "operate_switch" not in self.dialect.readings:
            return None
        try:
            switch = self.operate_switch()
        except DeviceError:
            return None
        return None if switch == "REMOTE" else switch

    def _off_quietly(self) -> None:
        """Best-effort off on an error path: log, never raise over the original exception."""
        if not self._may_be_on or self._transport is None:
            return
        if self.off_failed is not None and isinstance(self.off_failed.__cause__, NoReply):
            # the error being handled met a silent controller in its own switch-off, which said so:
            # another round cannot reach it and only delays the error by two time-outs
            return
        try:
            self.off()
        except Exception as exc:
            self._log_off_failure(exc)

    def reset(self) -> SourceState:
        """Send ``RST`` (clears an overload) and return the new state. Never called automatically:
        an overload needs a person to look at the tube first."""
        logger.warning("%s: RST sent by the user", shown_name(self.port))
        self._do("reset")
        return self.status()
