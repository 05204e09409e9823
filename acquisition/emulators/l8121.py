"""An emulated Hamamatsu L8121 controller, answering the protocol of ``L8121.md`` on a
pseudo-terminal, a TCP socket or in process.

:class:`L8121Model` is the controller: its states, the warm-up sequence, tube voltage and current
that ramp towards the set values after ``XON``, the interlock, overload and error codes, and
``ERR``/``ERROR`` for refused commands. It runs on an injectable clock and records every command it
receives. Faults are injected from any thread, now or at a given model time: :meth:`~L8121Model.open_interlock`,
:meth:`~L8121Model.overload`, :meth:`~L8121Model.drop_beam`, :meth:`~L8121Model.stuck_on`,
:meth:`~L8121Model.silence`, :meth:`~L8121Model.garbage`, :meth:`~L8121Model.slow`.

:class:`PtyServer` serves a model on a pseudo-terminal whose slave path pyserial opens like a
serial port; :class:`SocketServer` on ``socket://127.0.0.1:PORT``. From a shell::

    python -m acquisition.emulators.l8121 --pty --warmup-s 2     # prints /dev/pts/N, Ctrl-C ends

Error codes (``SER``) are this emulator's own; the real controller's are not documented:
0 none, 1 interlock open, 2 warm-up needed, 3 overload, 4 value out of range, 5 unknown command,
6 wrong state.

Examples
--------
>>> m = L8121Model(warmup_s=0, ramp_s=0)
>>> m.handle("TYP"), m.handle("XON"), m.handle("SER")
('TYP L8121-01', 'ERROR', 'SER 2')
>>> m.handle("WUP"), m.handle("STS"), m.handle("HIV 60"), m.handle("CUR 250"), m.handle("XON")
('WUP', 'STS 2', 'HIV 60', 'CUR 250', 'XON')
>>> m.handle("SAR"), m.xray_on
('SAR 3 60 250 0 0 0 0', True)
"""
from __future__ import annotations

import heapq
import itertools
import logging
import os
import random
import select
import socket
import sys
import threading
import time
import tty
from dataclasses import dataclass
from typing import Callable

__all__ = ["L8121Model", "PtyServer", "SocketServer", "Exchange", "main"]

logger = logging.getLogger(__name__)

# STS states
WARMUP_NEEDED, WARMING_UP, STANDBY, XRAY_ON, OVERLOAD, NOT_READY, SELF_TEST = range(7)
# SWE values
WARMUP_DONE, WARMUP_RUNNING, WARMUP_NOT_STARTED = range(3)
# SER codes (this emulator's own)
E_NONE, E_INTERLOCK, E_WARMUP, E_OVERLOAD, E_RANGE, E_UNKNOWN, E_STATE = range(7)

_JUNK = "#%&*?!~^@$+=<>0123456789abcdefxyz"


@dataclass(frozen=True)
class Exchange:
    """One command the model received: model time (s), the line, and its reply (None: none sent)."""
    t: float
    command: str
    reply: str | None


class L8121Model:
    """The controller's behaviour, independent of any link.

    Parameters
    ----------
    model : str
        What ``TYP`` answers.
    warmup_s : float
        Duration of the warm-up sequence started by ``WUP``.
    ramp_s : float
        Time for the measured voltage and current to ramp (linearly) from where they are to the set
        values, after ``XON`` or a change of setting while on.
    clock : callable
        Seconds, monotonic; model time is ``clock()`` minus its value at construction.
    kv_min, kv_max, ua_max, watts_max : float
        The ranges ``HIV`` and ``CUR`` accept (``ERR`` otherwise), and the power limit a pair of
        settings may not exceed.
    warmed_up : bool
        Start in standby (warm-up done) instead of "warm-up needed".
    seed : int
        Seed of the junk :meth:`garbage` replies with.

    Notes
    -----
    Measured values are reported as whole kV and µA. While X-rays are off they are 0.
    """

    def __init__(self, *, model: str = "L8121-01", warmup_s: float = 3.0, ramp_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic, kv_min: float = 40, kv_max: float = 150,
                 ua_max: float = 500, watts_max: float = 75, warmed_up: bool = False, seed: int = 0):
        self.model = model
        self.warmup_s = float(warmup_s)
        self.ramp_s = float(ramp_s)
        self.kv_min, self.kv_max, self.ua_max, self.watts_max = kv_min, kv_max, ua_max, watts_max
        self._clock = clock
        self._t0 = clock()
        self._lock = threading.RLock()
        self._events: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = itertools.count()
        self._rng = random.Random(seed)
        self._state = STANDBY if warmed_up else WARMUP_NEEDED
        self._warmup = WARMUP_DONE if warmed_up else WARMUP_NOT_STARTED
        self._set_kv, self._set_ua = int(kv_min), 0
        self._ramp_t0, self._ramp_from = 0.0, (0.0, 0.0)
        self._beam_dropped = False
        self._interlock_open = False
        self._focus = 0
        self._error = E_NONE
        self._silent = self._garbage = self._stuck = False
        self._silent_executes = False
        self._delay_s = 0.0
        self._log: list[Exchange] = []
        self._commands = {
            "HIV": self._hiv, "CUR": self._cur, "XON": self._xon, "XOF": self._xof, "WUP": self._wup,
            "RST": self._rst, "CFS": self._cfs,
            "STS": lambda t: f"STS {self._state}",
            "SAR": lambda t: "SAR {} {:.0f} {:.0f} 0 0 0 0".format(self._state, *self._measured(t)),
            "SVI": lambda t: f"SVI {self._set_kv} {self._set_ua}",
            "SHV": lambda t: "SHV {:.0f}".format(self._measured(t)[0]),
            "SCU": lambda t: "SCU {:.0f}".format(self._measured(t)[1]),
            "SIN": lambda t: f"SIN {int(self._interlock_open)}",
            "SWE": lambda t: f"SWE {self._warmup}",
            "SPH": lambda t: f"SPH {int(self._state == WARMING_UP)}",
            "SFC": lambda t: f"SFC {self._focus}",
            "SER": lambda t: f"SER {self._error}",
            "TYP": lambda t: f"TYP {self.model}",
        }
        self._takes_argument = {"HIV", "CUR", "CFS"}

    # -- read-only state for tests ----------------------------------------------------------------
    @property
    def time(self) -> float:
        """Model time, seconds since construction."""
        return self._clock() - self._t0

    @property
    def state(self) -> int:
        """The ``STS`` state now (0 warm-up needed … 6 self-test)."""
        with self._lock:
            self._advance()
            return self._state

    @property
    def xray_on(self) -> bool:
        """Whether the tube emits now (state 3)."""
        return self.state == XRAY_ON

    @property
    def set_kv(self) -> int:
        """The set tube voltage, kV."""
        return self._set_kv

    @property
    def set_ua(self) -> int:
        """The set tube current, µA."""
        return self._set_ua

    @property
    def interlock_is_open(self) -> bool:
        """Whether the interlock chain is open now."""
        with self._lock:
            self._advance()
            return self._interlock_open

    def measured(self) -> tuple[float, float]:
        """The measured (kV, µA) now, unrounded."""
        with self._lock:
            self._advance()
            return self._measured(self.time)

    @property
    def log(self) -> list[Exchange]:
        """Every command received so far, with model time and reply (a copy)."""
        with self._lock:
            return list(self._log)

    @property
    def commands(self) -> list[str]:
        """The command lines received so far, in order."""
        return [e.command for e in self.log]

    @property
    def reply_delay_s(self) -> float:
        """How long a server waits before sending each reply (see :meth:`slow`)."""
        return self._delay_s

    # -- fault injection --------------------------------------------------------------------------
    def open_interlock(self, at_s: float | None = None) -> None:
        """Open the interlock chain now, or at model time ``at_s``.

        With X-rays on, the controller drops the beam: state 2 (standby), ``SIN 1``, error code 1.
        """
        def fault(t):
            self._interlock_open = True
            if self._state == XRAY_ON:
                self._state, self._error = STANDBY, E_INTERLOCK
        self._at(at_s, fault)

    def close_interlock(self, at_s: float | None = None) -> None:
        """Close the interlock chain now, or at model time ``at_s``."""
        def fix(t):
            self._interlock_open = False
        self._at(at_s, fix)

    def overload(self, at_s: float | None = None) -> None:
        """Trip the overload protection now, or at model time ``at_s``: state 4, beam off, error 3.
        Only ``RST`` leaves the overload state."""
        def fault(t):
            self._state, self._error = OVERLOAD, E_OVERLOAD
        self._at(at_s, fault)

    def drop_beam(self, at_s: float | None = None) -> None:
        """Let the emitter fail now, or at model time ``at_s``: the measured current collapses to
        0 while the state stays 3 (until ``XOF``)."""
        def fault(t):
            if self._state == XRAY_ON:
                self._beam_dropped = True
        self._at(at_s, fault)

    def stuck_on(self, on: bool = True) -> None:
        """Acknowledge ``XOF`` but keep emitting (a failed high-voltage relay)."""
        with self._lock:
            self._stuck = bool(on)

    def silence(self, on: bool = True, *, execute: bool = False) -> None:
        """Stop answering. ``execute=False``: a dead controller, commands are recorded but neither
        executed nor answered (nothing the software sends can switch the tube off: only the
        hardware interlock can). ``execute=True``: the reply path is lost (a broken receive line)
        but commands still act, so an ``XOF`` sent on detecting the silence does switch off."""
        with self._lock:
            self._silent = bool(on)
            self._silent_executes = bool(execute)

    def garbage(self, on: bool = True) -> None:
        """Answer every command (executed as usual) with random junk instead of its reply."""
        with self._lock:
            self._garbage = bool(on)

    def slow(self, delay_s: float) -> None:
        """Delay every reply by ``delay_s`` seconds (in the servers; 0 restores)."""
        if delay_s < 0:
            raise ValueError(f"delay_s must be >= 0, got {delay_s}")
        with self._lock:
            self._delay_s = float(delay_s)

    # -- the protocol -----------------------------------------------------------------------------
    def handle(self, line: str) -> str | None:
        """Execute one command line and return its reply (no terminator), or None for no reply.

        Examples
        --------
        >>> L8121Model().handle("HIV 200")
        'ERR'
        """
        line = line.strip()
        if not line:
            return None
        with self._lock:
            self._advance()
            t = self.time
            if self._silent:
                reply = None
                if self._silent_executes:
                    self._execute(line, t)
            else:
                reply = self._execute(line, t)
                if self._garbage:
                    reply = "".join(self._rng.choice(_JUNK) for _ in range(self._rng.randint(1, 12)))
            self._log.append(Exchange(t, line, reply))
        logger.debug("L8121 emulator %.3f s: %s -> %s", t, line, reply)
        return reply

    def _execute(self, line: str, t: float) -> str:
        word, *args = line.split()
        action = self._commands.get(word)
        if action is None or len(args) != (word in self._takes_argument):
            self._error = E_UNKNOWN
            return "ERR"
        return action(t, *args)

    def _hiv(self, t, arg):
        kv = _whole(arg)
        if kv is None or not self.kv_min <= kv <= self.kv_max or kv * self._set_ua / 1000 > self.watts_max:
            self._error = E_RANGE
            return "ERR"
        self._retarget(t)
        self._set_kv = kv
        return f"HIV {kv}"

    def _cur(self, t, arg):
        ua = _whole(arg)
        if ua is None or not 0 <= ua <= self.ua_max or self._set_kv * ua / 1000 > self.watts_max:
            self._error = E_RANGE
            return "ERR"
        self._retarget(t)
        self._set_ua = ua
        return f"CUR {ua}"

    def _xon(self, t):
        if self._state != STANDBY or self._interlock_open:
            self._error = (E_INTERLOCK if self._interlock_open and self._state == STANDBY else
                           E_WARMUP if self._state in (WARMUP_NEEDED, WARMING_UP) else
                           E_OVERLOAD if self._state == OVERLOAD else E_STATE)
            return "ERROR"
        self._state, self._beam_dropped = XRAY_ON, False
        self._ramp_t0, self._ramp_from = t, (0.0, 0.0)
        return "XON"

    def _xof(self, t):
        if self._stuck:
            return "XOF"
        if self._state == XRAY_ON:
            self._state = STANDBY
        if self._state == WARMING_UP:  # the warm-up runs the tube: XOF ends it (L8121.md, Safety)
            self._state, self._warmup = WARMUP_NEEDED, WARMUP_NOT_STARTED
        self._beam_dropped = False
        return "XOF"

    def _wup(self, t):
        if self._state not in (WARMUP_NEEDED, STANDBY, WARMING_UP):
            self._error = E_STATE
            return "ERROR"
        if self._state != WARMING_UP:
            self._state, self._warmup = WARMING_UP, WARMUP_RUNNING

            def done(t_done):
                if self._state == WARMING_UP:
                    self._state, self._warmup = STANDBY, WARMUP_DONE
            self._schedule(t + self.warmup_s, done)
        return "WUP"

    def _rst(self, t):
        if self._state == OVERLOAD:
            self._state = STANDBY if self._warmup == WARMUP_DONE else WARMUP_NEEDED
        self._error = E_NONE
        return "RST"

    def _cfs(self, t, arg):
        mode = _whole(arg)
        if mode is None or not 0 <= mode <= 3:
            self._error = E_RANGE
            return "ERR"
        self._focus = mode
        return f"CFS {mode}"

    def _measured(self, t: float) -> tuple[float, float]:
        if self._state != XRAY_ON:
            return 0.0, 0.0
        f = 1.0 if self.ramp_s <= 0 else min(1.0, max(0.0, (t - self._ramp_t0) / self.ramp_s))
        kv0, ua0 = self._ramp_from
        kv, ua = kv0 + (self._set_kv - kv0) * f, ua0 + (self._set_ua - ua0) * f
        return kv, (0.0 if self._beam_dropped else ua)

    def _retarget(self, t):
        """A new setting while on ramps from where the tube is now."""
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
        return f"L8121Model({self.model!r}, state={self.state}, set {self._set_kv} kV {self._set_ua} µA)"


def _whole(text: str) -> int | None:
    return int(text) if text.isdigit() else None


# -- servers --------------------------------------------------------------------------------------
class _LineServer:
    """Reads CR- (or LF-) terminated lines, answers each with the model; replies end with
    ``reply_terminator`` (CR, as the controller; ``"\\r\\n"`` to test a client against CR LF)."""

    def __init__(self, model: L8121Model, *, reply_terminator: str = "\r"):
        self.model = model
        self.reply_terminator = reply_terminator
        self.url: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _answer(self, buf: bytearray, data: bytes, write: Callable[[bytes], object]) -> None:
        buf += data
        while True:
            cuts = [i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0]
            if not cuts:
                return
            line, buf[:] = bytes(buf[:min(cuts)]), buf[min(cuts) + 1:]
            reply = self.model.handle(line.decode("ascii", errors="replace"))
            if reply is None:
                continue
            delay = self.model.reply_delay_s
            if delay > 0 and self._stop.wait(delay):
                return
            write((reply + self.reply_terminator).encode("ascii", errors="replace"))

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
    ...     with serial.serial_for_url(server.url, timeout=1) as port:
    ...         _ = port.write(b"TYP\\r")
    ...         port.read_until(b"\\r")
    b'TYP L8121-01\\r'
    """

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

    def drop_connection(self) -> None:
        """Close the current client connection (fault injection: lost link)."""
        self._drop.set()

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

    parser = argparse.ArgumentParser(prog="python -m acquisition.emulators.l8121", description="Serve an emulated Hamamatsu L8121 controller until Ctrl-C; "
                                     "the first line on stdout is the url to open.")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal (default)")
    where.add_argument("--socket", type=int, metavar="PORT", help="serve on TCP 127.0.0.1:PORT (0: any free port)")
    parser.add_argument("--model", default="L8121-01", help="what TYP answers (default %(default)s)")
    parser.add_argument("--warmup-s", type=float, default=3.0, help="warm-up duration, s (default %(default)s)")
    parser.add_argument("--ramp-s", type=float, default=1.0, help="kV/µA ramp after XON, s (default %(default)s)")
    parser.add_argument("--warmed-up", action="store_true", help="start in standby, warm-up done")
    parser.add_argument("-v", "--verbose", action="store_true", help="log every exchange on stderr")
    args = parser.parse_args(argv)
    if args.verbose:
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr, format="%(asctime)s %(message)s")
    model = L8121Model(model=args.model, warmup_s=args.warmup_s, ramp_s=args.ramp_s, warmed_up=args.warmed_up)
    server = PtyServer(model) if args.socket is None else SocketServer(model, port=args.socket)

    def terminate(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, terminate)
    try:
        with server:
            print(server.url, flush=True)
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
