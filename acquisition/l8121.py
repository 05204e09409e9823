"""The Hamamatsu L8121 microfocus X-ray source, driven over RS-232 (protocol: ``L8121.md``).

The driver is mostly its command table: every controller command is declared once, with its
command string, the validator of its argument and the parser of its reply (:class:`Query`,
:class:`Command`, :class:`Setting`, in the manner of PyMeasure's ``Instrument.control``). On top
sit the few operations an experiment needs, each keeping the safety rules of the protocol:

- :meth:`L8121.warm_up` starts the warm-up sequence and waits for standby;
- :meth:`L8121.on` validates voltage, current and power *before sending anything*, requires
  standby and a closed interlock, sets the values, switches on and waits for a stable beam;
- :meth:`L8121.check` polls once while the beam is on and, on overload, an open interlock or a
  dropped beam, switches off and raises :class:`~acquisition.errors.SourceFault`;
- :meth:`L8121.off` switches off and confirms it with ``STS``; :meth:`L8121.close` and the context
  manager switch off on every exit path (exception, Ctrl-C), and so does any reply that cannot be
  parsed while the beam may be on.

The driver never sends ``RST`` by itself (:meth:`L8121.reset` is for a person who has looked at the
tube). Every reply is checked: a command must be echoed, a query's reply must start with the
query and hold numbers where numbers belong; anything else raises
:class:`~acquisition.errors.DeviceError` naming the port, the command and the reply.

Examples
--------
>>> from acquisition.emulators.l8121 import L8121Model, PtyServer
>>> with PtyServer(L8121Model(warmup_s=0.2, ramp_s=0.2)) as server:
...     with L8121(server.url, poll_s=0.05) as source:
...         _ = source.warm_up(timeout_s=10, progress=False)
...         beam = source.on(60, 250)          # kV, µA: returns once the beam is stable
...         print(source.check()["state"].name, beam["set_voltage_kv"], beam["set_current_ua"])
...     server.model.xray_on                   # leaving the block switched the tube off
XRAY_ON 60 250
False
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import math
import re
import time
import tomllib
from collections.abc import Callable, Mapping
from enum import IntEnum
from numbers import Real
from pathlib import Path
from typing import Any

from acquisition.errors import DeviceError, SourceFault
from acquisition.transport import SerialTransport

__all__ = ["L8121", "SourceConfig", "SourceState", "WarmupState", "Query", "Command", "Setting"]

logger = logging.getLogger(__name__)


class SourceState(IntEnum):
    """The controller's state, as ``STS`` (and the first field of ``SAR``) reports it."""
    WARMUP_NEEDED = 0
    WARMING_UP = 1
    STANDBY = 2
    XRAY_ON = 3
    OVERLOAD = 4
    NOT_READY = 5
    SELF_TEST = 6


class WarmupState(IntEnum):
    """The warm-up sequence, as ``SWE`` reports it."""
    DONE = 0
    RUNNING = 1
    NOT_STARTED = 2


# -- configuration --------------------------------------------------------------------------------
@dataclasses.dataclass
class SourceConfig:
    """Ratings, tolerances and timing of one L8121 (defaults: ``L8121.md``, confirm on the unit).

    Tolerances are absolute (kV, µA) when numbers, relative to the set value when strings such as
    ``"2%"``. ``model`` is what ``TYP`` must answer at connect; ``None`` (or ``""`` in TOML, which
    has no null) accepts any model.

    Examples
    --------
    >>> SourceConfig.from_toml('[source]\\nkv_max = 90\\nua_tolerance = "2%"').tolerance_ua(250)
    5.0
    """
    model: str | None = "L8121-01"
    kv_min: float = 40.0
    kv_max: float = 150.0
    ua_min: float = 0.0
    ua_max: float = 500.0
    watts_max: float = 75.0
    kv_tolerance: float | str = 1.0
    ua_tolerance: float | str = 5.0
    focus_modes: tuple[int, ...] = (0, 1, 2, 3)
    timeout_s: float = 1.0
    min_interval_s: float = 0.05
    stable_timeout_s: float = 15.0
    poll_s: float = 0.2
    warmup_timeout_s: float = 1800.0
    off_attempts: int = 3
    beam_drop_fraction: float = 0.5

    def __post_init__(self):
        if self.model == "":
            self.model = None
        self.focus_modes = tuple(int(m) for m in self.focus_modes)
        for name in ("kv_min", "kv_max", "ua_min", "ua_max", "watts_max", "timeout_s", "min_interval_s",
                     "stable_timeout_s", "poll_s", "warmup_timeout_s", "beam_drop_fraction"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value) or value < 0:
                raise ValueError(f"L8121 configuration: {name} must be a finite number >= 0, got {value!r}")
        if not (self.kv_min <= self.kv_max and self.ua_min <= self.ua_max):
            raise ValueError(f"L8121 configuration: empty range kv {self.kv_min}..{self.kv_max} "
                             f"or ua {self.ua_min}..{self.ua_max}")
        if self.timeout_s == 0 or self.poll_s == 0:
            raise ValueError("L8121 configuration: timeout_s and poll_s must be > 0")
        if int(self.off_attempts) < 1:
            raise ValueError(f"L8121 configuration: off_attempts must be >= 1, got {self.off_attempts}")
        self.tolerance_kv(100.0), self.tolerance_ua(100.0)  # validates both

    def tolerance_kv(self, set_kv: float) -> float:
        """The kV tolerance, absolute, around ``set_kv``."""
        return _tolerance(self.kv_tolerance, set_kv, "kv_tolerance")

    def tolerance_ua(self, set_ua: float) -> float:
        """The µA tolerance, absolute, around ``set_ua``."""
        return _tolerance(self.ua_tolerance, set_ua, "ua_tolerance")

    @classmethod
    def from_dict(cls, mapping: Mapping[str, Any]) -> SourceConfig:
        """Build from a mapping; an unknown key is an error that names it and the known keys."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(mapping) - known)
        if unknown:
            raise ValueError(f"L8121 configuration: unknown key(s) {unknown}; known: {sorted(known)}")
        return cls(**mapping)

    @classmethod
    def from_toml(cls, source: str | Path, section: str = "source") -> SourceConfig:
        """Read the ``[section]`` table (dotted for nested tables) of a TOML file or TOML text.

        The link settings ``url`` and ``baudrate`` may sit in the same table; they are ignored
        here (see :meth:`L8121.from_config`).
        """
        table = _toml_section(source, section)
        return cls.from_dict({k: v for k, v in table.items() if k not in ("url", "baudrate")})

    def to_dict(self) -> dict[str, Any]:
        """The configuration as a TOML-friendly dict (``model=None`` becomes ``""``)."""
        d = dataclasses.asdict(self)
        d["model"] = d["model"] or ""
        d["focus_modes"] = list(d["focus_modes"])
        return d


def _tolerance(spec: float | str, set_value: float, name: str) -> float:
    if isinstance(spec, str):
        m = re.fullmatch(r"\s*([0-9.]+)\s*%\s*", spec)
        if not m:
            raise ValueError(f"L8121 configuration: {name} {spec!r} is neither a number nor a percentage like '2%'")
        return abs(set_value) * float(m.group(1)) / 100
    if isinstance(spec, bool) or not isinstance(spec, Real) or not spec >= 0:
        raise ValueError(f"L8121 configuration: {name} must be >= 0, got {spec!r}")
    return float(spec)


def _toml_section(source: str | Path, section: str) -> dict:
    text = source
    if isinstance(source, Path) or ("\n" not in source and "=" not in source):
        text = Path(source).read_text(encoding="utf-8")
    table: Any = tomllib.loads(text)
    for part in section.split(".") if section else ():
        if not isinstance(table, dict) or part not in table:
            raise ValueError(f"{source if isinstance(source, Path) or '=' not in source else 'TOML text'}: "
                             f"no [{section}] table")
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


def _flag(text: str) -> bool:
    if text not in ("0", "1"):
        raise ValueError(f"{text!r} is neither 0 nor 1")
    return text == "1"


def _enum(enum: type[IntEnum]) -> Callable[[str], IntEnum]:
    def parse(text: str) -> IntEnum:
        value = _integer(text)
        try:
            return enum(value)
        except ValueError:
            raise ValueError(f"{value} is not a known {enum.__name__}") from None
    parse.__name__ = enum.__name__
    return parse


# -- the declarations -----------------------------------------------------------------------------
class Query:
    """A read-only property that sends ``command`` and parses the reply ``<command> <fields...>``.

    Parameters
    ----------
    command : str
        The query, e.g. ``"SAR"``; the reply must start with it.
    *fields : callable
        One parser per reply field (``str -> value``, raising ``ValueError`` on bad text). A single
        field gives a value, several a tuple.
    extra : bool
        Accept (and drop) further fields after the declared ones (``SAR``'s trailing zeros).
    rest : bool
        The last field takes the rest of the reply, spaces included (``TYP``'s model name).
    doc : str
        The property's docstring.
    """

    def __init__(self, command: str, *fields: Callable[[str], Any], extra: bool = False, rest: bool = False,
                 doc: str | None = None):
        self.command, self.fields, self.extra, self.rest = command, fields, extra, rest
        self.name = command
        self.__doc__ = doc

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, driver, owner=None):
        if driver is None:
            return self
        return driver._ask(self)

    def __set__(self, driver, value):
        raise AttributeError(f"{self.name} ({self.command}) is read-only")

    def parse(self, reply: str) -> Any:
        """The value(s) in ``reply``; ``ValueError`` says why ``reply`` is not a valid answer."""
        words = reply.split()
        if not words or words[0] != self.command:
            raise ValueError(f"the reply does not start with {self.command}")
        values, n = words[1:], len(self.fields)
        if self.rest and len(values) >= n:
            values = values[:n - 1] + [" ".join(values[n - 1:])]
        if len(values) < n or (len(values) > n and not self.extra):
            raise ValueError(f"expected {n} field(s) after {self.command}, got {len(values)}")
        out = tuple(parse(v) for parse, v in zip(self.fields, values))
        return out[0] if n == 1 else out


class Command:
    """A command the controller echoes, e.g. ``XON`` or ``HIV 60``; reading the attribute gives a
    function that sends it.

    Parameters
    ----------
    command : str
        The command word.
    argument : callable, optional
        ``argument(driver, value) -> int``: validates the value (``ValueError`` naming the limit)
        and returns what is sent. ``None``: the command takes no argument.
    doc : str
        Docstring.
    """

    def __init__(self, command: str, argument: Callable[[Any, Any], int] | None = None, doc: str | None = None):
        self.command, self.argument = command, argument
        self.__doc__ = doc

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, driver, owner=None):
        if driver is None:
            return self
        return functools.partial(driver._send, self)

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


class Setting:
    """A read-write property: reading sends ``query``, assigning sends ``command``."""

    def __init__(self, query: Query, command: Command, doc: str | None = None):
        self.query, self.command = query, command
        self.__doc__ = doc

    def __set_name__(self, owner, name):
        self.name = self.query.name = self.command.name = name

    def __get__(self, driver, owner=None):
        if driver is None:
            return self
        return driver._ask(self.query)

    def __set__(self, driver, value):
        driver._send(self.command, value)


def _whole(value: Any, what: str, unit: str) -> int:
    """The controller takes whole kV and µA: round half up, and say so in the log."""
    if isinstance(value, bool) or not isinstance(value, Real):
        raise TypeError(f"{what} must be a number of {unit}, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r} {unit}")
    whole = math.floor(value + 0.5)
    if whole != value:
        logger.warning("%s %g %s rounded to %d %s: the L8121 takes whole %s", what, value, unit, whole, unit, unit)
    return whole


def _in_range(value: int, lo: float, hi: float, what: str, unit: str, names: str) -> int:
    if not lo <= value <= hi:
        raise ValueError(f"{what} {value} {unit} is outside {names} = {lo:g}..{hi:g} {unit}")
    return value


def _kv_argument(driver: L8121, value) -> int:
    c = driver.config
    return _in_range(_whole(value, "tube voltage", "kV"), c.kv_min, c.kv_max, "tube voltage", "kV", "kv_min..kv_max")


def _ua_argument(driver: L8121, value) -> int:
    c = driver.config
    return _in_range(_whole(value, "tube current", "µA"), c.ua_min, c.ua_max, "tube current", "µA", "ua_min..ua_max")


def _focus_argument(driver: L8121, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value not in driver.config.focus_modes:
        raise ValueError(f"focus mode must be one of focus_modes = {driver.config.focus_modes}, got {value!r}")
    return value


# -- the driver -----------------------------------------------------------------------------------
class L8121:
    """A Hamamatsu L8121 X-ray source on a serial link.

    Parameters
    ----------
    url : str or transport
        The controller's port for :func:`serial.serial_for_url` (``/dev/ttyUSB0``,
        ``socket://host:port``, an emulator's pty), or an object with ``query(str) -> str``,
        ``close()``, ``is_open`` and ``port`` (e.g. a configured :class:`SerialTransport`).
    baudrate : int
        9600, 38400 (default) or 115200, as set on the controller.
    connect : bool
        Open the link and check ``TYP`` now (default).
    config : SourceConfig or mapping, optional
        Ratings, tolerances and timing; keyword arguments override single fields
        (``L8121(url, kv_max=90, poll_s=0.1)``).

    Raises
    ------
    DeviceError
        The port cannot be opened, the controller does not answer, or ``TYP`` names another model.

    Notes
    -----
    Attributes declared as :class:`Query` (``state``, ``interlock_open``, ``warmup``,
    ``preheating``, ``error``, ``voltage_kv``, ``current_ua``, ``model_name``) send their query on
    every read. ``focus`` is a :class:`Setting` (``SFC`` / ``CFS``). The commands that change the
    tube (``HIV``, ``CUR``, ``XON``, ``XOF``, ``WUP``, ``RST``) are private: use :meth:`on`,
    :meth:`set_values`, :meth:`off`, :meth:`warm_up` and :meth:`reset`, which keep the safety rules.

    The transport serialises exchanges, so :meth:`off` may be called from another thread (a
    watchdog) at any time, also while :meth:`on` waits for a stable beam.
    """

    # ---- the command table (L8121.md) ----
    model_name = Query("TYP", str, rest=True, doc="The controller's model (``TYP``).")
    state = Query("STS", _enum(SourceState), doc="The controller's state (``STS``), a :class:`SourceState`.")
    interlock_open = Query("SIN", _flag, doc="Whether the interlock is open (``SIN 1``).")
    warmup = Query("SWE", _enum(WarmupState), doc="The warm-up sequence (``SWE``), a :class:`WarmupState`.")
    preheating = Query("SPH", _flag, doc="Whether the tube is pre-heating (``SPH 1``).")
    error = Query("SER", _integer, doc="The controller's error code (``SER``), 0 for none.")
    voltage_kv = Query("SHV", _number, doc="Measured tube voltage, kV (``SHV``).")
    current_ua = Query("SCU", _number, doc="Measured tube current, µA (``SCU``).")
    _sar = Query("SAR", _enum(SourceState), _number, _number, extra=True,
                 doc="State, measured kV and µA in one exchange (``SAR n kV uA 0 0 0 0``).")
    _svi = Query("SVI", _number, _number, doc="Set kV and µA (``SVI kV uA``).")
    focus = Setting(Query("SFC", _integer), Command("CFS", _focus_argument),
                    doc="Focus mode: reading sends ``SFC``, assigning ``CFS n`` (one of ``focus_modes``).")
    _hiv = Command("HIV", _kv_argument, doc="Set the tube voltage, whole kV (``HIV 60``).")
    _cur = Command("CUR", _ua_argument, doc="Set the tube current, whole µA (``CUR 250``).")
    _xon = Command("XON", doc="X-rays on; the controller refuses unless standby with the interlock closed.")
    _xof = Command("XOF", doc="X-rays off; always accepted.")
    _wup = Command("WUP", doc="Start the warm-up sequence.")
    _rst = Command("RST", doc="Reset after an overload.")

    def __init__(self, url, baudrate: int = 38400, *, connect: bool = True,
                 config: SourceConfig | Mapping[str, Any] | None = None, **overrides):
        base = config if isinstance(config, SourceConfig) else SourceConfig.from_dict(dict(config or {}))
        self.config = SourceConfig.from_dict({**dataclasses.asdict(base), **overrides}) if overrides else base
        self.url = url
        self.baudrate = int(baudrate)
        self.identity: str | None = None
        self._transport = None
        self._may_be_on = False  # True from before XON until off() has confirmed
        self._beam: tuple[int, int] | None = None  # the set values while this driver keeps the beam on
        self._in_off = False
        if connect:
            self.connect()

    @classmethod
    def from_config(cls, source: Mapping[str, Any] | str | Path, *, section: str = "source",
                    connect: bool = True) -> L8121:
        """A driver from a TOML table (file, text, or an already parsed mapping) holding ``url``,
        optionally ``baudrate``, and :class:`SourceConfig` keys."""
        table = dict(source) if isinstance(source, Mapping) else _toml_section(source, section)
        if "url" not in table:
            raise ValueError(f"L8121 configuration: no 'url' in [{section}]")
        url, baudrate = table.pop("url"), table.pop("baudrate", 38400)
        return cls(url, baudrate, connect=connect, config=SourceConfig.from_dict(table))

    # ---- link ----
    @property
    def port(self) -> str:
        """The port, as messages name it."""
        return getattr(self._transport, "port", None) or str(self.url)

    @property
    def is_connected(self) -> bool:
        """Whether the link is open."""
        return self._transport is not None and self._transport.is_open

    def connect(self) -> L8121:
        """Open the link and check the controller's model (``TYP``); returns self.

        If the tube is found emitting, it is noted (a warning) and :meth:`close` will switch it off.
        """
        if self.is_connected:
            return self
        if isinstance(self.url, str):
            self._transport = SerialTransport(self.url, baudrate=self.baudrate, timeout_s=self.config.timeout_s,
                                              min_interval_s=self.config.min_interval_s)
        else:
            self._transport = self.url
        try:
            self.identity = self.model_name
            if self.config.model is not None and self.identity != self.config.model:
                raise DeviceError(f"{self.port}: TYP answered {self.identity!r}, expected {self.config.model!r} "
                                  f"(configure model=None to accept any model)")
            if self.state == SourceState.XRAY_ON:
                logger.warning("%s: X-rays are on at connect; close() will switch them off", self.port)
                self._may_be_on = True
        except BaseException:
            self._transport.close()
            self._transport = None
            raise
        logger.info("%s: %s connected", self.port, self.identity)
        return self

    def close(self) -> None:
        """Switch X-rays off if this session may have left them on (confirmed), then close the link.

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
            port = self.port
            self._transport.close()
            self._transport = None
            logger.info("%s: closed", port)

    def detach(self) -> None:
        """Close the link and leave the source as it is -- X-rays on included. Only for bench work
        from the command line (``radiokit acquire source on``), where the operator switches off
        with ``radiokit acquire source off``; scripts use :meth:`close`."""
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            logger.warning("%s: detached with X-rays possibly on", self.port)

    def __enter__(self) -> L8121:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.close()
        except Exception as err:  # never mask the exception that ended the block
            if exc_type is None:
                raise
            logger.error("%s: while handling %s, switching off failed: %s", self.port, exc_type.__name__, err)

    def __repr__(self) -> str:
        return f"L8121({self.port!r}, {'connected' if self.is_connected else 'not connected'})"

    # ---- exchanges ----
    def _exchange(self, line: str, *, query: bool = False) -> str:
        if self._transport is None:
            raise DeviceError(f"{self.port}: not connected (call connect())")
        try:
            reply = self._transport.query(line)
        except DeviceError as exc:
            self._fail_safe(exc)
            raise
        if reply in ("ERR", "ERROR"):
            err = DeviceError(f"{self.port}: {line} refused by the controller ({reply})")
            if query:  # a query is never refused by a working controller: as bad as garbage
                self._fail_safe(err)
            raise err
        return reply

    def _ask(self, query: Query) -> Any:
        reply = self._exchange(query.command, query=True)
        try:
            return query.parse(reply)
        except ValueError as why:
            err = DeviceError(f"{self.port}: unparseable reply to {query.command}: {reply!r} ({why})")
            self._fail_safe(err)
            raise err from None

    def _send(self, command: Command, value=None) -> None:
        line = command.line(self, value)  # validates before anything is sent
        reply = self._exchange(line)
        if not Command.is_echo(line, reply):
            err = DeviceError(f"{self.port}: unexpected reply to {line}: {reply!r} (expected the echo {line!r})")
            self._fail_safe(err)
            raise err

    def _fail_safe(self, cause: Exception) -> None:
        """A failed exchange while the beam may be on: switch off before reporting it."""
        if not self._may_be_on or self._in_off:
            return
        logger.error("%s: %s; switching X-rays off", self.port, cause)
        try:
            self.off()
        except DeviceError as exc:
            logger.critical("%s: could not confirm X-rays off: %s", self.port, exc)

    # ---- readings ----
    def status(self) -> SourceState:
        """The controller's state (``STS``)."""
        return self.state

    def measured(self) -> tuple[float, float]:
        """Measured tube voltage (kV) and current (µA), from one ``SAR``."""
        _, kv, ua = self._sar[:3]
        return kv, ua

    def setpoint(self) -> tuple[float, float]:
        """Set tube voltage (kV) and current (µA), from ``SVI``."""
        return self._svi

    def interlock_closed(self) -> bool:
        """Whether the interlock is closed (``SIN 0``)."""
        return not self.interlock_open

    def warmup_state(self) -> WarmupState:
        """The warm-up sequence (``SWE``): DONE, RUNNING or NOT_STARTED."""
        return self.warmup

    def error_code(self) -> int:
        """The controller's error code (``SER``), 0 for none."""
        return self.error

    # ---- operations ----
    def validate(self, kv: float, ua: float) -> tuple[int, int]:
        """Check a voltage and current against the configured ratings; nothing is sent.

        Returns the whole numbers that would be sent (rounded half up, with a logged warning when
        rounding changed a value).

        Raises
        ------
        ValueError
            Out of ``kv_min..kv_max`` or ``ua_min..ua_max``, or kV × µA / 1000 above ``watts_max``;
            the message names the limit.
        """
        kv_i, ua_i = _kv_argument(self, kv), _ua_argument(self, ua)
        watts = kv_i * ua_i / 1000
        if watts > self.config.watts_max:
            raise ValueError(f"{kv_i} kV x {ua_i} µA = {watts:g} W exceeds watts_max = {self.config.watts_max:g} W")
        return kv_i, ua_i

    def set_values(self, kv: float, ua: float) -> tuple[int, int]:
        """Set tube voltage (kV) and current (µA), whole numbers (rounded half up, with a warning).

        Validated first (:meth:`validate`). The order of ``HIV`` and ``CUR`` is chosen so that no
        intermediate pair exceeds ``watts_max``. Returns the values sent.

        While this driver keeps the beam on, it then waits (as :meth:`on` does) until the measured
        values are within tolerance of the new ones, so that :meth:`check` judges the beam against
        the new setting; any failure switches off.
        """
        kv_i, ua_i = self.validate(kv, ua)
        beam_on = self._beam is not None
        try:
            _, old_ua = self.setpoint()
            if kv_i * old_ua / 1000 <= self.config.watts_max:
                self._hiv(kv_i)
                self._cur(ua_i)
            else:
                self._cur(ua_i)
                self._hiv(kv_i)
            if beam_on:
                self._beam = (kv_i, ua_i)
                self._wait_stable(kv_i, ua_i, time.monotonic())
        except BaseException:
            if beam_on:
                self._off_quietly()
            raise
        return kv_i, ua_i

    def warm_up(self, timeout_s: float | None = None, progress: bool | Callable[[float, SourceState], Any] = True,
                *, force: bool = False) -> float:
        """Run the controller's warm-up sequence (``WUP``) and wait until it reports standby.

        Parameters
        ----------
        timeout_s : float, optional
            Longest wait; default ``config.warmup_timeout_s``.
        progress : bool or callable
            ``True``: a tqdm bar of elapsed seconds; a callable gets ``(elapsed_s, state)`` at every
            poll; ``False``: quiet.
        force : bool
            Send ``WUP`` even when the warm-up is already done.

        Returns
        -------
        float
            Seconds waited (0 when nothing was needed).

        Raises
        ------
        DeviceError
            Not in standby within ``timeout_s``, or the sequence stopped; ``XOF`` has been sent.
        SourceFault
            Overload (not reset automatically).
        """
        timeout_s = self.config.warmup_timeout_s if timeout_s is None else float(timeout_s)
        state = self.state
        if state == SourceState.XRAY_ON:
            raise DeviceError(f"{self.port}: X-rays are on; call off() before warm_up()")
        if state == SourceState.OVERLOAD:
            raise SourceFault(f"{self.port}: overload (state 4); inspect the tube, then reset() by hand")
        if not force and state == SourceState.STANDBY and self.warmup == WarmupState.DONE:
            return 0.0
        bar = None
        if progress is True:
            from tqdm.auto import tqdm
            bar = tqdm(total=round(timeout_s), desc=f"L8121 warm-up ({self.port})", unit="s", leave=False)
        t0 = time.monotonic()
        self._may_be_on = True  # the warm-up sequence runs the tube
        try:
            self._wup()
            logger.info("%s: warm-up started (timeout %g s)", self.port, timeout_s)
            seen_running = False
            while True:
                elapsed = time.monotonic() - t0
                state = self.state
                seen_running |= state == SourceState.WARMING_UP
                if bar is not None:
                    bar.n = min(round(elapsed), bar.total)
                    bar.set_postfix_str(state.name, refresh=True)
                elif callable(progress):
                    progress(elapsed, state)
                if state == SourceState.STANDBY and self.warmup == WarmupState.DONE:
                    break
                if state == SourceState.OVERLOAD:
                    raise SourceFault(f"{self.port}: overload (state 4) during warm-up; inspect the tube, "
                                      f"then reset() by hand")
                if seen_running and state == SourceState.WARMUP_NEEDED:
                    raise DeviceError(f"{self.port}: warm-up stopped after {elapsed:.1f} s (state WARMUP_NEEDED, "
                                      f"error code {self.error})")
                if elapsed > timeout_s:
                    raise DeviceError(f"{self.port}: warm-up not done within {timeout_s:g} s "
                                      f"(state {state.name}); X-rays switched off")
                time.sleep(self.config.poll_s)
        except BaseException:
            self._off_quietly()
            raise
        finally:
            if bar is not None:
                bar.close()
        self._may_be_on = False
        elapsed = time.monotonic() - t0
        logger.info("%s: warm-up done in %.1f s", self.port, elapsed)
        return elapsed

    def on(self, kv: float, ua: float) -> dict[str, Any]:
        """Switch X-rays on at ``kv`` kV and ``ua`` µA and wait for a stable beam.

        Order: validate the values (nothing sent yet); require standby and a closed interlock
        (queries only); ``HIV``, ``CUR``, ``XON``; poll ``SAR`` every ``poll_s`` until the measured
        values are within ``kv_tolerance`` / ``ua_tolerance`` of the set ones. Any failure or
        interruption after ``XON`` switches off before the exception propagates.

        Returns
        -------
        dict
            ``voltage_kv``, ``current_ua`` (measured), ``set_voltage_kv``, ``set_current_ua`` (sent,
            whole numbers), ``seconds`` (from ``XON`` to stable).

        Raises
        ------
        ValueError
            A value outside its range or the power limit (message names the limit).
        DeviceError
            Not in standby (warm-up needed, not ready), refused, or not stable within
            ``stable_timeout_s`` (X-rays switched off).
        SourceFault
            Interlock open or overload before switching on; overload, interlock or dropped beam
            while waiting (X-rays switched off).
        """
        kv_i, ua_i = self.validate(kv, ua)
        self._require_ready()
        try:
            self.set_values(kv_i, ua_i)  # the beam is off: no waiting
            self._may_be_on = True
            self._xon()
            t0 = time.monotonic()
            self._beam = (kv_i, ua_i)
            reading = self._wait_stable(kv_i, ua_i, t0)
        except BaseException:
            self._off_quietly()
            raise
        logger.info("%s: X-rays on at %d kV %d µA: measured %g kV %g µA after %.2f s", self.port, kv_i, ua_i,
                    reading["voltage_kv"], reading["current_ua"], reading["seconds"])
        return reading

    def _require_ready(self) -> None:
        state = self.state
        reasons = {
            SourceState.WARMUP_NEEDED: "warm-up needed (call warm_up())",
            SourceState.WARMING_UP: "warm-up still running",
            SourceState.XRAY_ON: "X-rays are already on (use set_values() or off())",
            SourceState.NOT_READY: "controller not ready",
            SourceState.SELF_TEST: "controller in self-test",
        }
        if state == SourceState.OVERLOAD:
            raise SourceFault(f"{self.port}: overload (state 4); X-rays not switched on. Inspect the tube, "
                              f"then reset() by hand")
        if state != SourceState.STANDBY:
            raise DeviceError(f"{self.port}: X-rays not switched on: {reasons[state]} (state {state.name})")
        if self.interlock_open:
            raise SourceFault(f"{self.port}: X-rays not switched on: interlock open (SIN 1)")

    def _wait_stable(self, kv: int, ua: int, t0: float) -> dict[str, Any]:
        c = self.config
        tol_kv, tol_ua = c.tolerance_kv(kv), c.tolerance_ua(ua)
        while True:
            state, m_kv, m_ua = self._sar[:3]
            seconds = time.monotonic() - t0
            if state != SourceState.XRAY_ON:
                self._trip(self._fault_reason(state, m_kv, m_ua, ramping=True))
            if abs(m_kv - kv) <= tol_kv and abs(m_ua - ua) <= tol_ua:
                return {"voltage_kv": m_kv, "current_ua": m_ua, "set_voltage_kv": kv, "set_current_ua": ua,
                        "seconds": seconds}
            if seconds > c.stable_timeout_s:
                raise DeviceError(f"{self.port}: beam not stable within stable_timeout_s = {c.stable_timeout_s:g} s: "
                                  f"measured {m_kv:g} kV {m_ua:g} µA, set {kv} kV {ua} µA "
                                  f"(tolerance {tol_kv:g} kV, {tol_ua:g} µA); X-rays switched off")
            time.sleep(c.poll_s)

    def _fault_reason(self, state: SourceState, kv: float, ua: float, *, ramping: bool = False,
                      interlock_open: bool | None = None) -> str | None:
        """Why the beam is not what this driver switched on, or None when it is."""
        if state == SourceState.OVERLOAD:
            return "overload (state 4)"
        if interlock_open is None:
            interlock_open = self.interlock_open
        if interlock_open:
            return "interlock open (SIN 1)"
        if state != SourceState.XRAY_ON:
            return f"beam dropped: state {state.name} instead of XRAY_ON"
        if not ramping and self._beam is not None:
            f = self.config.beam_drop_fraction
            set_kv, set_ua = self._beam
            if ua < f * set_ua:
                return f"beam dropped: measured current {ua:g} µA, below {f:.0%} of the set {set_ua} µA"
            if kv < f * set_kv:
                return f"beam dropped: measured voltage {kv:g} kV, below {f:.0%} of the set {set_kv} kV"
        return None

    def _trip(self, reason: str):
        """Switch off and raise :class:`SourceFault` naming ``reason``."""
        note = "X-rays switched off"
        try:
            self.off()
        except DeviceError as exc:
            note = f"switching X-rays off could not be confirmed ({exc})"
        try:
            code = self.error
            note += f"; controller error code {code}" if code else ""
        except DeviceError:
            pass
        logger.error("%s: %s; %s", self.port, reason, note)
        raise SourceFault(f"{self.port}: {reason}; {note}")

    def check(self) -> dict[str, Any]:
        """Poll once (``SAR``, ``SIN``) and stop on a fault.

        While this driver keeps the beam on (after :meth:`on`), an overload, an open interlock, a
        state other than X-rays on, or a measured current (or voltage) below
        ``beam_drop_fraction`` of the set value switches off and raises :class:`SourceFault` naming
        which. Otherwise only an overload is a fault.

        Returns
        -------
        dict
            ``state`` (:class:`SourceState`), ``voltage_kv``, ``current_ua`` (measured),
            ``interlock_closed``, ``time`` (``time.time()``), for the frame's metadata.
        """
        state, kv, ua = self._sar[:3]
        interlock_open = self.interlock_open
        if self._beam is not None:
            reason = self._fault_reason(state, kv, ua, interlock_open=interlock_open)
        else:
            reason = "overload (state 4)" if state == SourceState.OVERLOAD else None
        if reason:
            self._trip(reason)
        return {"state": state, "voltage_kv": kv, "current_ua": ua, "interlock_closed": not interlock_open,
                "time": time.time()}

    def off(self) -> SourceState:
        """Switch X-rays off (``XOF``) and confirm with ``STS`` that the state is no longer 3.

        Tries ``off_attempts`` times (``XOF`` then ``STS``, ``poll_s`` apart). Returns the state
        read after switching off.

        Raises
        ------
        DeviceError
            Not confirmed after ``off_attempts`` attempts: switch off at the controller.
        """
        attempts, last = int(self.config.off_attempts), None
        self._in_off = True
        try:
            for attempt in range(attempts):
                if attempt:
                    time.sleep(self.config.poll_s)
                try:
                    self._xof()
                except DeviceError as exc:
                    last = exc  # still ask: the XOF may have arrived
                try:
                    state = self.state
                except DeviceError as exc:
                    last = exc
                    continue
                if state != SourceState.XRAY_ON:
                    self._may_be_on, self._beam = False, None
                    logger.info("%s: X-rays off (state %s)", self.port, state.name)
                    return state
                last = DeviceError(f"{self.port}: STS still 3 (X-rays on) after XOF")
        finally:
            self._in_off = False
        raise DeviceError(f"{self.port}: could not confirm X-rays off after {attempts} attempt(s) "
                          f"(last: {last}); switch the source off at the controller") from last

    def _off_quietly(self) -> None:
        """Best-effort off on an error path: log, never raise over the original exception."""
        if not self._may_be_on or self._transport is None:
            return
        try:
            self.off()
        except Exception as exc:
            logger.critical("%s: could not confirm X-rays off: %s", self.port, exc)

    def reset(self) -> SourceState:
        """Send ``RST`` (clears an overload) and return the new state. Never called automatically:
        an overload needs a person to look at the tube first."""
        logger.warning("%s: RST sent by the user", self.port)
        self._rst()
        return self.state
