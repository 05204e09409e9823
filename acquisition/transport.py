"""Serial links to instruments: one locked command–reply exchange at a time.

:class:`SerialTransport` wraps :func:`serial.serial_for_url`, so the same driver talks to a device
path (``/dev/ttyUSB0``, ``COM3``), a terminal server (``socket://host:port``, ``rfc2217://host:port``),
a pseudo-terminal of an emulator or pyserial's ``loop://``. It knows nothing about any instrument:
it sends a line, reads a line, times the exchange and logs it.

Every exchange is logged on the ``acquisition.transport`` logger at DEBUG level, as
``<port> > <command>`` and ``<port> < <reply> (<ms> ms)``, so a lab notebook that sets that logger
to DEBUG records the whole conversation with the instrument. Reconnections are logged at WARNING.

Examples
--------
pyserial's ``loop://`` sends every byte back, so a query returns the command itself:

>>> with SerialTransport("loop://", min_interval_s=0) as link:
...     link.query("TYP")
'TYP'
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import select
import signal
import subprocess
import threading
import time

import serial
import serial.rfc2217

from acquisition.errors import DeviceError, GuardianLost, NoReply, PortBusy, PortUnavailable, WriteTimedOut
from radiokit.checks import shown_name
from radiokit.interrupts import STOP_SIGNALS, held

__all__ = ["SerialTransport", "PipeTransport", "PortHold", "hold_port", "adopt_hold"]

logger = logging.getLogger(__name__)

try:  # pyserial's posix backend lets termios.error escape from tcflush on a vanished pty
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - Windows

    class _TermiosError(Exception):
        pass


# What a lost link raises: close, reopen, retry.
_LINK_ERRORS = (serial.SerialException, OSError, _TermiosError)

# How long one low-level read may block before the exchange's own deadline is checked again.
_READ_SLICE_S = 0.05
_SPACING_SLICE_S = 0.005  # how often the spacing's wait looks for a byte that restarts it
_LINE_ENDS = (b"\r", b"\n")


def late_reply_wait_s(timeout_s: float) -> float:
    """The cap on :meth:`SerialTransport._await_late_reply`'s wait after a reply time-out of
    ``timeout_s``: a quarter of it for the late reply to begin, and one read slice more for it to
    end (a whole reply at 9600 baud takes about 20 ms). Its last read may overrun it by a slice."""
    return timeout_s / 4 + _READ_SLICE_S


def exchange_longest_s(timeout_s: float, min_interval_s: float) -> float:
    """One :meth:`SerialTransport.query` at its longest on a link that stays up (a reconnect
    repeats it, after the port's reopening and the identity check): the wait for a late reply after
    a time-out (:func:`late_reply_wait_s`, its last read a slice past it) or, in its place, a
    barrier query (:meth:`SerialTransport._cross`: its spacing, then a reply read as long; one
    answered later, or not within its own reply time-out, ends the exchange unsent), the
    command spacing at its longest (three spacings: bytes restart it for two, on a line that never
    falls quiet -- :meth:`SerialTransport._wait_spacing`), the reply time-out and two read slices
    past it (the grace for a stalled process, the last read's overrun)."""
    barrier = 3 * min_interval_s
    return barrier + late_reply_wait_s(timeout_s) + _READ_SLICE_S + 3 * min_interval_s + timeout_s + 2 * _READ_SLICE_S


def close_wait_s(timeout_s: float, write_timeout_s: float, min_interval_s: float) -> float:
    """The longest :meth:`SerialTransport.close` waits for another thread's exchange to end: one
    exchange at its worst by its own time-outs, a wedged port's included (unlike
    :func:`exchange_longest_s`, a responsive link's): an interrupted exchange's reply awaited up
    to its time-out (``_drain_pending``) and a read slice; the late reply's wait
    (:func:`late_reply_wait_s`) and a slice, or a barrier query in its place (``_cross``: its
    spacing, its write and drain, each up to ``write_timeout_s``, or its reply read as long as
    that wait, from its write -- read longer, up to a reply time-out and a slice, it ends the
    exchange, the command not sent); the spacing, three spacings at most (a byte in its
    second restarts it, ``_wait_spacing``) and a poll; from the command's start, the reply
    time-out or its three write waits (an earlier command's bytes, its write, its drain, each up
    to ``write_timeout_s``), whichever is longer, and two read slices past it (the stall grace,
    the last read's overrun). A reconnect (the port reopened, the device checked, the command
    sent again) is past it: a closed link is not reconnected anyway."""
    return (
        timeout_s
        + _READ_SLICE_S
        + 3 * min_interval_s  # a barrier's spacing (its poll and read slice are counted below)
        + _SPACING_SLICE_S
        + max(late_reply_wait_s(timeout_s), 2 * write_timeout_s)
        + _READ_SLICE_S
        + 3 * min_interval_s
        + _SPACING_SLICE_S
        + max(timeout_s, 3 * write_timeout_s)
        + 2 * _READ_SLICE_S
    )


#: What a port's (re)open may take within a switch-off's reconnect: a URL's, pyserial's socket://
#: connect time-out (5 s) and its RFC 2217 negotiation's (3 s); a local device's (a non-blocking
#: open, a flock that does not wait, the line settings), a second for a loaded machine.
_OPEN_WAIT_S = 8.0
_OPEN_WAIT_LOCAL_S = 1.0


#: the micro sign as a unit may write it: Latin-1/cp1252 (0xB5), UTF-8 (U+00B5, and U+03BC, the
#: Greek mu Unicode normalisation makes of it)
_MICRO = (b"\xc2\xb5", b"\xce\xbc", b"\xb5")


def _text(raw: bytes) -> str:
    """A reply line as text: ASCII, with the micro sign (``250µA``) in any of :data:`_MICRO`
    read as ``µ``, and every other byte above 127 a replacement character. Why not a permissive
    decoding: the parsers read digits and spaces with Unicode-aware patterns, so a garbled line
    decoded as UTF-8 or Latin-1 could read as a valid state (``STS \xd9\xa2`` is an Arabic-Indic
    2, "X-rays off"), and a confirmation must never come from a garbled reply.

    Upper case, the micro sign kept: L8121.md writes the commands in upper case and says nothing
    of the replies' case, and a unit answering ``sts 2`` was refused at every reading, its XOF's
    echo included, so that nothing could switch it off (review s38b). ASCII letters only change,
    so a garbled line stays garbled; the units' own case (``kV``, ``uA``) is read in any case."""
    for micro in _MICRO[:-1]:
        raw = raw.replace(micro, _MICRO[-1])
    return "µ".join(part.decode("ascii", "replace").upper() for part in raw.split(_MICRO[-1]))


class _Rfc2217(serial.rfc2217.Serial):
    """pyserial's RFC 2217 client, its reader thread's end told in one log line on ``link_log``.

    Why a subclass: that thread answers the server's telnet requests with socket sends, and one on
    a link shut or reset raised BrokenPipeError out of the thread -- threading's excepthook printed
    pyserial's traceback on stderr (the process lived). Its own end of the loop (a recv error)
    puts None in the read buffer, so the next read raises SerialException and the transport
    reopens the link; a failed send now ends the same way. A subclass, not a patch of pyserial's
    class: other users of pyserial in the process keep its behaviour."""

    link_log = logger

    def _telnet_read_loop(self):
        try:
            super()._telnet_read_loop()
        except OSError as exc:
            self._read_buffer.put(None)
            # while closing, a send racing the shutdown is expected: only a live link's loss is news
            self.link_log.log(
                logging.WARNING if self.is_open else logging.DEBUG,
                "%s: the RFC 2217 link's reader thread ended (%s): the next exchange finds the link lost",
                self.portstr,
                exc,
            )


# -- one process per controller: the port's exclusive lock ----------------------------------------
#
# Two processes on one controller's port each read what it sends, and a reply -- a "tube off"
# confirmation included -- may be consumed by the one that did not ask. So a local port is held
# with flock(LOCK_EX | LOCK_NB), the lock pyserial's ``exclusive=True`` takes (other programs that
# use it, or flock(1), are refused alike). It is taken on a descriptor of its own, not on
# pyserial's: a transport's reconnect closes and reopens its port, and the probe's links close
# before the guardian opens the port -- the lock must outlive both. One lock per process and
# device, shared by every link of the process (a process never refuses itself: its switch-off
# opens the port while its probe's or guardian's hold is there) and passed to the guardian, which
# inherits the descriptor (one lock: it outlives a kill -9 of the process that took it).
# Advisory: a program that opens the port without flock (screen, minicom) is not kept out. URLs
# (socket://, rfc2217://, loop://) have no device here to lock.


class _Lock:
    """This process's lock on one device: ``fd`` the descriptor holding it, or None while this
    process keeps none (its node gone with a lost link, or the lock handed to the guardian);
    ``key`` the node it was taken on; ``count`` the shares (:class:`PortHold`) using it."""

    def __init__(self, fd: int | None, key: str):
        self.fd, self.key, self.count = fd, key, 0


_LOCKS: dict[str, _Lock] = {}
# re-entrant: a share dropped unreferenced is released by its __del__, which the garbage collector
# may run inside a section that holds the guard (a plain Lock deadlocked there, in the thread
# taking the lock again after its guardian's death)
_LOCKS_GUARD = threading.RLock()

# The signals whose handlers may raise (a command's guard turns Ctrl-Z into a stop too): held off
# from the moment flock takes a lock to the moment the lock is recorded for release. Between the
# two, the descriptor holding it was a bare int: a Ctrl-C there left the lock held by nothing this
# process would close, and its next open of the port refused "another program (this pid)".
_STOPS = STOP_SIGNALS + tuple(getattr(signal, name) for name in ("SIGTSTP",) if hasattr(signal, name))


def _lock_key(url: str) -> str | None:
    """The device a local port names (symlinks resolved: /dev/serial/by-id/... and /dev/ttyUSB0
    are one lock), or None for a URL or where flock does not exist. Resolved again at every
    (re)open: a re-plugged adapter's by-id link names its new node."""
    if os.name != "posix" or "://" in url:
        return None
    return os.path.realpath(url)


def _holder_pid(fd: int) -> int | None:
    """The live process that took the flock on ``fd``'s file, from /proc/locks (Linux), or None."""
    try:
        st = os.fstat(fd)
        want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        with open("/proc/locks") as f:
            for line in f:
                words = line.split()
                if len(words) > 5 and words[1] == "FLOCK" and words[5] == want and os.path.exists(f"/proc/{words[4]}"):
                    return int(words[4])
    except (OSError, ValueError):
        pass
    return None


def _lock_device(url: str, key: str, *, again: bool = False) -> int | None:
    """A new descriptor of ``key`` holding its exclusive lock; None where there is nothing to lock
    (the port's own open then says why: missing, permission) or flock is not supported.
    ``again``: this process held the port before (a link lost, or its guardian's), said so.

    Raises
    ------
    PortBusy
        Another process holds the lock."""
    import errno
    import fcntl

    try:
        # O_NONBLOCK: a modem-control line must not hold the open; O_NOCTTY: never our terminal
        fd = os.open(key, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        pid = _holder_pid(fd) if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN) else None
        os.close(fd)
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
            return None
        who = f" (pid {pid})" if pid is not None else ""
        if again:  # mid-session: this process did send through it, before the link was lost
            raise PortBusy(
                f"{shown_name(url)}: another program{who} took this port while this radiokit process was not "
                "holding it (its link lost, or its X-ray guardian ending); nothing more was sent through it"
            ) from None
        raise PortBusy(
            f"{shown_name(url)}: another program{who} holds this port (a radiokit series or source command in "
            "another terminal, or its X-ray guardian); radiokit sent nothing through it"
        ) from None
    return fd


def _moved(fd: int, key: str) -> bool:
    """Whether the lock on ``fd`` is no longer on the device ``key`` names: the node is gone (an
    adapter unplugged) or is another device (plugged again)."""
    try:
        held, now = os.fstat(fd), os.stat(key)
    except OSError:
        return True
    return (held.st_dev, held.st_ino, held.st_rdev) != (now.st_dev, now.st_ino, now.st_rdev)


def _let_go(lock: _Lock) -> None:
    """Close this process's descriptor of ``lock`` (the shares stay counted; :meth:`PortHold.renew`
    takes it again)."""
    fd, lock.fd = lock.fd, None
    if fd is not None:
        os.close(fd)


class PortHold:
    """This process's share of the exclusive lock on a local port (:func:`hold_port`): the lock
    is let go when the last share is released (or at the process's end). A context manager.

    Why the lock's descriptor is closed when the link is lost with its node gone
    (:meth:`let_go_if_gone`): on Linux a USB serial adapter keeps its device minor until the last
    descriptor of its node closes, so an open lock made the re-plugged adapter come back under a
    new name (ttyUSB1), and the reconnect, and the operator's switch-off on the old name, failed."""

    def __init__(self, url: str, lock: _Lock):
        self.url, self._lock = url, lock
        lock.count += 1

    @property
    def fd(self) -> int | None:
        """The descriptor holding the lock (for a child to inherit: :func:`adopt_hold`); None
        while this process keeps none."""
        return None if self._lock is None else self._lock.fd

    def let_go_if_gone(self) -> None:
        """The link was lost: if the node the lock is on is gone, or the path names another device,
        close the lock's descriptor (every share's: one per process), so that the node is not
        pinned; :meth:`renew` takes the lock again before the port is reopened."""
        with _LOCKS_GUARD:
            lock = self._lock
            if lock is not None and lock.fd is not None and _moved(lock.fd, _lock_key(self.url)):
                _let_go(lock)

    def hand_over(self) -> None:
        """The guardian, which inherited the descriptor, holds the lock now: this process closes
        its copy (every share's), so that it does not pin the node should the adapter be
        unplugged; :meth:`renew` takes the lock again if this process opens the port itself."""
        with _LOCKS_GUARD:
            if self._lock is not None:
                _let_go(self._lock)

    def renew(self) -> None:
        """Before the port is opened again: the lock on the node the path names now (a by-id link
        resolved again), taken anew if this process keeps none or it is on another node --
        refused (:class:`PortBusy`) when another program took that one meanwhile."""
        with held(*_STOPS), _LOCKS_GUARD:  # taken and recorded in one step for a stop signal
            lock = self._lock
            if lock is None:
                return
            key = _lock_key(self.url)
            if lock.fd is not None and not _moved(lock.fd, key):
                return
            _let_go(lock)
            other = _LOCKS.get(key)
            if other is not None and other is not lock and other.fd is not None and not _moved(other.fd, key):
                # another link of this process (another spelling of the path) holds that node
                self._leave()
                self._lock = other
                other.count += 1
                return
            fd = _lock_device(self.url, key, again=True)
            if fd is None:
                return  # nothing to lock now: the port's own open says why
            if _LOCKS.get(lock.key) is lock:
                del _LOCKS[lock.key]
            lock.fd, lock.key = fd, key
            _LOCKS[key] = lock

    def _leave(self) -> None:
        """This share's end (:data:`_LOCKS_GUARD` held): the last one lets the lock go."""
        lock, self._lock = self._lock, None
        lock.count -= 1
        if lock.count <= 0:
            if _LOCKS.get(lock.key) is lock:
                del _LOCKS[lock.key]
            _let_go(lock)

    def release(self) -> None:
        with _LOCKS_GUARD:
            if self._lock is not None:
                self._leave()

    def __enter__(self) -> PortHold:
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()

    def __del__(self):
        try:
            if self._lock is not None:
                self.release()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


def hold_port(url: str) -> PortHold | None:
    """Take (or share, within this process) the exclusive lock on the local port ``url``; None
    for a URL, or a port that cannot be opened (its own open says why).

    Raises
    ------
    PortBusy
        Another process holds it: nothing was sent."""
    key = _lock_key(str(url))
    if key is None:
        return None
    hold = None
    try:
        # taken and recorded in one step for a stop signal, which comes after it: the share made
        # is then never returned, so it is let go here, not left to the garbage collector (the
        # traceback keeps this frame, and the lock, alive)
        with held(*_STOPS):
            with _LOCKS_GUARD:
                lock = _LOCKS.get(key)
                if lock is None:
                    fd = _lock_device(str(url), key)
                    if fd is None:
                        return None
                    lock = _LOCKS[key] = _Lock(fd, key)
                hold = PortHold(str(url), lock)
            hold.renew()
    except BaseException:
        if hold is not None:
            hold.release()
        raise
    return hold


def adopt_hold(url: str, fd: int) -> PortHold | None:
    """The lock on ``url`` inherited from the process that took it (the guardian's: the command
    passes its descriptor), as this process's own; kept for the process's life (but closed as
    any lock is when the link is lost with its node gone: :meth:`PortHold.let_go_if_gone`)."""
    key = _lock_key(str(url))
    if key is None:
        return None
    with _LOCKS_GUARD:
        os.set_inheritable(fd, False)
        lock = _LOCKS.setdefault(key, _Lock(fd, key))
        hold = PortHold(str(url), lock)
    _ADOPTED.append(hold)  # never released: a link's close must not let it go
    return hold


_ADOPTED: list[PortHold] = []


def _serial_for_url(url: str, log: logging.Logger) -> serial.SerialBase:
    """:func:`serial.serial_for_url` not yet opened, an ``rfc2217://`` link as :class:`_Rfc2217`."""
    if not url.lower().startswith("rfc2217://"):
        return serial.serial_for_url(url, do_not_open=True)
    ser = _Rfc2217(None)  # as serial_for_url builds it: no port, then the URL
    ser.port = url
    ser.link_log = log
    return ser


@contextlib.contextmanager
def _sigpipe_held():
    """SIGPIPE blocked in this thread for what runs inside, and one it raised taken off this
    thread's pending signals before it is unblocked: a write to a pipe or socket whose reader is
    gone then fails with EPIPE (``BrokenPipeError``; pyserial's socket:// link turns it into
    ``SerialException``) whatever this process's SIGPIPE disposition. A Python-API user whose
    process imported gmsh has it at its default (gmsh resets it), and such a write killed that
    process on the spot, before it could switch off (review s28-h8). Blocked, not ignored:
    ``signal.signal`` works only in the main thread."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - Windows has no SIGPIPE
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGPIPE})
    try:
        yield
    finally:
        # (blocked by the caller already: its own to take). sigpending and sigwait, not
        # sigtimedwait: macOS and OpenBSD have no sigtimedwait, and its AttributeError escaped
        # PipeTransport's `except OSError` (review s29-h4)
        if signal.SIGPIPE not in old and signal.SIGPIPE in signal.sigpending():
            signal.sigwait({signal.SIGPIPE})
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _write_no_sigpipe(fd: int, data: bytes) -> int:
    """``os.write`` to a pipe that fails with ``BrokenPipeError`` when the reader is gone, whatever
    this process's SIGPIPE disposition (:func:`_sigpipe_held`)."""
    with _sigpipe_held():
        return os.write(fd, data)


#: How often a close looks again whether the port's output has drained (s): bytes leave in ms.
_CLOSE_POLL_S = 0.01
#: The shortest look again after a command's bytes (s): about one byte's time at 9600 baud.
_DRAIN_POLL_MIN_S = 0.001


def _queued(ser) -> int | None:
    """The bytes the local port ``ser`` holds unsent in its output queue (the kernel's); None where
    it cannot say (a link that is gone) or for a URL (``loop://`` counts what is not read back yet)."""
    if not isinstance(getattr(ser, "fd", None), int):
        return None
    try:
        return int(ser.out_waiting or 0)
    except (serial.SerialException, OSError, ValueError, AttributeError, NotImplementedError, TypeError):
        return None


def _unsent(ser) -> int:
    """:func:`_queued`, 0 where it cannot say."""
    return _queued(ser) or 0


class _GoneMidDrain(serial.SerialException):
    """The port went while a command written whole drained (its queue's poll failed: an adapter
    unplugged, the port closed): the command may have reached the controller, or not."""


class _ClosedUnderIt(serial.SerialException):
    """The link was closed while an exchange ran (:meth:`SerialTransport.close` from another
    thread, past its wait for the exchange, or from a signal handler in the exchange's own
    thread): a lost link, like any other, but never reconnected."""


class _DrainTimedOut(serial.SerialTimeoutException):
    """A command written whole whose bytes did not leave the port within the write time-out (its
    output not draining): unlike a write time-out, it may still reach the controller."""


class _StillQueued(serial.SerialTimeoutException):
    """A command not written: an earlier one's bytes (its drain timed out) still held the port's
    queue after a further write time-out. Nothing of this command went."""

    def __init__(self, earlier: list[str]):
        super().__init__(" ".join(earlier))
        self.earlier = list(earlier)


class _SlowBarrier(DeviceError):
    """A barrier query (:meth:`SerialTransport._cross`) answered, but later than a late reply is
    waited for: the query it preceded was not sent (not a signal, nothing on its way)."""


class _Undecided(DeviceError):
    """A reply held back (it fits the command owed a late reply and the one sent now) and then a
    line that fits neither: which was this command's reply cannot be told, so neither is (not a
    signal: nothing of this exchange is still on its way)."""


def _said(exc: BaseException) -> str:
    """``exc``'s text with its control characters escaped: pyserial's repeats the port's name raw
    (an escape in a name typed for ``--port`` reached the terminal inside the refusal)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(exc))


class SerialTransport:
    """A line-oriented serial link with explicit time-outs and one exchange at a time.

    Parameters
    ----------
    url : str
        Anything :func:`serial.serial_for_url` opens: a device path, ``socket://host:port``,
        ``rfc2217://host:port``, ``loop://``.
    baudrate : int
        Bits per second; the frame is always 8 data bits, no parity, 1 stop bit (8N1).
    timeout_s : float
        Longest wait for a complete reply, from the moment the command was written. A silent device
        raises :class:`~acquisition.errors.DeviceError` after this, never hangs.
    write_timeout_s : float
        Longest wait for the command to leave the output buffer.
    min_interval_s : float
        Shortest time between the end of one exchange and the next command (controllers that need a
        pause between commands); the first command after the port is opened waits it too.
    terminator : str
        Appended to every command. Replies may end in CR, LF or CR LF; all are accepted and
        stripped, and empty lines (the LF of a CR LF) are skipped.
    retries : int
        How often an exchange is repeated after the link was lost (``SerialException`` or
        ``OSError``), each time after closing and reopening the port. Time-outs are not retried:
        a silent device is an error.
    log : logging.Logger
        Where exchanges are logged (DEBUG) and reconnections (WARNING).
    open : bool
        Open the port now (default); otherwise call :meth:`open` later.

    Raises
    ------
    DeviceError
        The port cannot be opened (message names the port and pyserial's reason).

    Notes
    -----
    DTR and RTS are asserted when the port opens (links where they mean nothing, such as
    ``socket://`` or a pseudo-terminal, ignore them).
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = 9600,
        timeout_s: float = 1.0,
        write_timeout_s: float = 1.0,
        min_interval_s: float = 0.06,  # the dialects' (acquisition.l8121.DIALECT_A)
        terminator: str = "\r",
        retries: int = 1,
        log: logging.Logger = logger,
        open: bool = True,
    ):
        if timeout_s <= 0 or write_timeout_s <= 0:
            raise ValueError(
                f"{shown_name(url)}: time-outs must be positive (timeout_s={timeout_s}, "
                f"write_timeout_s={write_timeout_s}); a link without a time-out can hang"
            )
        if min_interval_s < 0 or retries < 0:
            raise ValueError(
                f"{shown_name(url)}: min_interval_s ({min_interval_s}) and retries ({retries}) must be >= 0"
            )
        if not terminator:
            raise ValueError(f"{shown_name(url)}: empty terminator")
        self.url = str(url)
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.write_timeout_s = float(write_timeout_s)
        self.min_interval_s = float(min_interval_s)
        self.terminator = terminator
        self.retries = int(retries)
        self.log = log
        self._serial: serial.SerialBase | None = None
        self._lock = threading.Lock()
        # The thread holding _lock (None: free), and what it runs: (command, since) -- close()
        # waits for another thread's exchange, never for its own thread's (a signal handler), and
        # longer for a switch-off (_close_wait_over)
        self._owner: int | None = None
        self._running: tuple[str | None, float] | None = None
        self._closer: int | None = None  # the thread whose close() holds _lock
        # One step of an exchange that touches the port's descriptor (a read slice, a write, a
        # queue poll) holds _io, and a close detaches and closes the port only under it: closed
        # between two steps, the descriptor's number could be taken by an open() elsewhere before
        # the next step, and a command's bytes went into that file (session 53). Re-entrant: a
        # close from a signal handler that interrupted a step of its own thread. _steps counts
        # the steps in progress of _io's holder; such a close leaves its port to the step's end
        # (_after_step: the port, and the lock share to let go)
        self._io = threading.RLock()
        self._steps = 0
        self._after_step: list[tuple[serial.SerialBase | None, PortHold | None]] = []
        # A close that did not get the exchange's lock: the exchange stops at its next step, and
        # does not reopen the port (cleared when the next query or open takes the lock)
        self._closing = False
        # A close from a signal handler in the thread whose switch-off is the running exchange:
        # left to that query's end, which the handler must not cut short
        self._close_after_query = False
        self._last_exchange = float("-inf")
        # An exchange cut short by a signal after its command was written: (command, the reply's
        # deadline). The controller still answers it, and that late reply must not be read as the
        # next command's (the flush before a command only clears what has arrived by then)
        self._pending: tuple[str, float] | None = None
        # the command whose reply _read_line holds back (_undecided): a line of it was read
        self._held_for: str | None = None
        self._rx = bytearray()  # what the exchange in progress has read of its reply so far
        # The words of the commands written since the port's output last drained (a drain a stop
        # cut short, a write that timed out): close() keeps unsent bytes that hold the switch-off
        self._undrained: list[str] = []
        # The last exchange timed out (NoReply): the controller may still be answering it, and a
        # unit busy answering may lose the next command (L8121.md is silent); the next exchange
        # first waits, briefly, for that reply and a quiet line (_await_late_reply)
        self._timed_out = False
        # Commands whose reply was not read -- timed out (NoReply), or written before a link error
        # (a read error: the port is reopened) -- oldest first, each with the time after which its
        # late reply is no longer waited for: the controller answers in order, so the next lines
        # on the link may be theirs before the reply to the command sent next
        self._owed: list[tuple[str, float]] = []
        # The words of the commands owed a reply (as _owed), kept past their window: until a reply
        # shows the controller has answered everything sent before (the controller answers in
        # order): a reply of its own word read then (_is_late), a barrier's (_cross), or a held
        # line nothing followed (_read_line). L8121.md bounds no reply's lateness, and a reply four
        # time-outs late, past its window, was read as the same query's asked again: a STANDBY
        # from before the tube was switched on (session 56)
        self._unanswered: list[str] = []
        #: ``reply_fits(command, reply) -> bool``: whether a line can be the reply to ``command`` (a
        #: driver sets its dialect's grammar, :meth:`acquisition.l8121.Dialect.reply_fits`). With
        #: it, after a time-out, a line that does not fit the command just sent is taken for the
        #: late reply of the one that timed out and discarded (once per command owed); without it,
        #: only the flush before each command guards against late replies.
        self.reply_fits = None
        #: Queries (command words) that change nothing on the instrument, in order of preference,
        #: which the transport may send on its own as a *barrier*: before a query of a word still
        #: owed a reply (:meth:`_cross`), and only before a query of one of these words. Its reply,
        #: read and told apart by :attr:`reply_fits`, shows that every reply owed before it has
        #: come or never will (the controller answers in order), so the query's own reply cannot
        #: be taken for the late one -- at the cost of one short exchange, not of a reply time-out
        #: spent waiting for a second line. Empty (the default): no barrier, the hold alone.
        self.late_barriers: tuple[str, ...] = ()
        #: ``on_reconnect(ask)``: run right after the port was opened again (a reconnect within
        #: :meth:`query`, a query on a link closed since it was first opened, or an explicit
        #: :meth:`open` of such a link), before any command is sent. ``ask(command) -> reply`` is one exchange on the new link. It raises
        #: :class:`~acquisition.errors.DeviceError` to refuse the device now behind the port: the
        #: port is then closed and the query fails as a lost link. A driver sets it to re-identify
        #: its instrument (:class:`acquisition.l8121.Reidentify`): a re-plugged adapter, or another
        #: device given the same path, must not answer for the one it connected to. Its
        #: ``not_resent`` (command words), if any, are never sent again after the link was lost
        #: during them: the query fails instead (a check of the model cannot tell two units apart).
        self.on_reconnect = None
        self._opened_once = False  # a later open is a reconnect: on_reconnect checks the device
        # this link's share of the port's exclusive lock (hold_port): from its first open to close(),
        # kept across a reconnect's close and reopen, where another process must not get in
        self._hold: PortHold | None = None
        #: Commands this link has begun to write (counted before the write): 0 means the device
        #: has received nothing from it -- what an interrupted caller may tell the operator.
        self.commands_written = 0
        if open:
            self.open()

    # -- life cycle -------------------------------------------------------------------------------
    @property
    def port(self) -> str:
        """The url this transport was opened with (used in every message)."""
        return self.url

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        ser = self._serial  # read once: a close from another thread may set it None between two reads
        return ser is not None and ser.is_open

    def open(self) -> None:
        """Open the port (8N1, DTR and RTS asserted); a no-op when it is open. An open of a
        transport opened before is a reconnect, whoever closed it: :attr:`on_reconnect` checks the
        device now behind the port (the path may lead elsewhere since), and its refusal closes the
        port and is raised, as is a link lost during the check (a :class:`DeviceError`, the port
        left closed: pyserial's exception named no port and reached the operator as a traceback)."""
        me, since = threading.get_ident(), time.monotonic()
        with self._lock:  # the check is an exchange: not interleaved with another thread's
            # recorded with no call between, as query() does (see there)
            self._owner, self._running, self._closing, self._close_after_query = me, (None, since), False, False
            try:
                try:
                    if not self.is_open:
                        try:
                            self._reopen(None, None)
                        except _LINK_ERRORS as exc:
                            self._close_port()
                            raise DeviceError(
                                f"{shown_name(self.url)}: link failed (lost, or a write timed out) during the identity check on opening ({exc})"
                            ) from exc
                finally:
                    self._close_if_asked()
            finally:
                try:
                    if self._close_after_query:  # (checked here: no call when there is none to do)
                        self._close_left()
                finally:
                    self._owner = self._running = None

    def _close_if_asked(self) -> None:
        """At a query's end, the exchange's lock still held and recorded: a close a signal's
        handler left to it (:attr:`_close_after_query`) is done now. The exchange is over: a
        handler's close from here on (the calls that follow are where one runs) closes the port
        at once, not left to an end that has passed."""
        self._running = None
        if self._close_after_query:
            # the mark cleared only once the close is done: a second stop raising as _close_all
            # starts left it dropped, the port open and its lock share held after a close that had
            # returned; the caller's finally (_close_left) does it then (review s54rv)
            self._close_all()
            self._close_after_query = False

    def _close_left(self) -> None:
        """In a query's (or an open's) last finally, the lock still held and recorded: a close
        :meth:`_close_if_asked` was stopped before doing (a second stop at its start) is done."""
        if self._close_after_query:
            self._close_all()
            self._close_after_query = False

    def _open_port(self) -> None:
        if self._closing:  # closed meanwhile by another thread: not opened again behind its back
            raise _ClosedUnderIt("the link was closed before the port was reopened")
        # before pyserial opens the port (DTR, RTS, a flush): held by another process, nothing is touched
        self._renew_hold()
        try:
            ser = _serial_for_url(self.url, self.log)
            ser.baudrate = self.baudrate
            ser.bytesize = serial.EIGHTBITS
            ser.parity = serial.PARITY_NONE
            ser.stopbits = serial.STOPBITS_ONE
            ser.timeout = min(_READ_SLICE_S, self.timeout_s)
            if not self.url.lower().startswith("rfc2217://"):
                # pyserial's RFC 2217 client refuses a write time-out in open() (NotImplementedError:
                # a traceback); its writes are bounded by its socket's own 5 s time-out instead
                ser.write_timeout = self.write_timeout_s
            ser.xonxoff = ser.rtscts = ser.dsrdtr = False
            ser.dtr = True  # applied by open()
            ser.rts = True
            with _sigpipe_held():
                # rfc2217:// starts a reader thread here, which answers the server's telnet requests
                # (socket sends) for the link's life: it inherits this thread's mask, so SIGPIPE
                # stays blocked in it, and a send on a link closed or reset fails with EPIPE -- under
                # SIGPIPE at its default (gmsh) it killed the whole process, whatever the tube's state
                ser.open()
        except (serial.SerialException, OSError, ValueError, NotImplementedError) as exc:
            raise PortUnavailable(f"{shown_name(self.url)}: cannot open the port ({_said(exc)})") from exc
        try:
            self._hold_opened(ser)
        except BaseException:
            with contextlib.suppress(serial.SerialException, OSError):
                ser.close()
            raise
        with self._io:
            if self._closing:  # closed by another thread as it opened: that close is not undone
                with contextlib.suppress(serial.SerialException, OSError):
                    ser.close()
                hold, self._hold = self._hold, None  # (the close let its own go: this one is taken since)
                if hold is not None:
                    hold.release()
                raise _ClosedUnderIt("the link was closed while the port was being reopened")
            self._serial = ser
        self._opened_once = True
        if self._pending is not None:
            # an exchange a signal cut short: its reply is still on its way and may come on the
            # reopened port after the next command was written (dropped here, STS read SIN's reply;
            # review s28-h8): owed until its own deadline, as _drain_pending waits for it. Owed
            # for a time-out from a late reopen instead, a reply that fits any command (ERROR)
            # kept the next command waiting that long for a second line (review s29-h4)
            if self._pending[1] > time.monotonic():
                self._owe(*self._pending)
            self._pending = None
        # self._owed is kept: the same controller behind the port (a brief read error, a re-plugged
        # adapter, a terminal server) still answers the commands the old link wrote, and a reply
        # that comes now must not be read as the reconnect check's or the resent command's; each
        # is owed only within its window (_forget_overdue), and a device that is not the one
        # connected to is refused by the check, not by these
        # The spacing is the controller's need, not this object's: another link (the probe's, a
        # guardian's, this one before a reconnect) may have had a reply just before the port was
        # opened, so the first command waits min_interval_s as if one had ended now.
        self._last_exchange = time.monotonic()
        self.log.info("%s opened (%d baud, 8N1)", shown_name(self.url), self.baudrate)

    def _renew_hold(self) -> None:
        """This link's share of the port's lock taken, or renewed (:meth:`PortHold.renew`), before
        or after a (re)open -- under the step lock, and refused once the link is marked closing.
        Why: a close past its wait marks the link closing and lets the share go under that lock;
        renewed outside it, between the reopen's look at the mark and the renewal, the lock was
        taken again after the close had returned, and another program was refused the port until
        the reopen noticed (review s54).

        Raises
        ------
        _ClosedUnderIt
            The link was closed meanwhile: nothing taken."""
        with self._io:
            if self._closing:
                # the close let its own share go: one here was taken since (a close from a signal's
                # handler inside hold_port, before the share was recorded), so it goes too
                hold, self._hold = self._hold, None
                if hold is not None:
                    hold.release()
                raise _ClosedUnderIt("the link was closed before the port was reopened")
            if self._hold is None:
                self._hold = hold_port(self.url)
            else:
                self._hold.renew()

    def _hold_opened(self, ser) -> None:
        """The lock held on the very device ``ser`` opened, taken now if the lock found nothing to
        take before the open (the node, or its by-id link, came -- udev a moment late -- between
        the two: the link ran unlocked for its whole session and a second process got in; review
        s35r4).

        Raises
        ------
        PortBusy
            Another program took the port in that moment (nothing was sent on this open).
        PortUnavailable
            The path named another device by the time the lock was taken."""
        if _lock_key(self.url) is None:
            return
        try:
            opened = os.fstat(ser.fileno())
        except (AttributeError, OSError, ValueError, serial.SerialException):
            return
        if self._on(opened):
            return
        self._renew_hold()
        if self._hold is None or self._hold.fd is None:
            # still nothing to lock (the node gone again, or flock unsupported there): as before
            return
        if not self._on(opened):
            raise PortUnavailable(
                f"{shown_name(self.url)}: the port changed while it was being opened; nothing was sent"
            )

    def _on(self, opened: os.stat_result) -> bool:
        """Whether this link's lock is held on the device ``opened`` (an fstat) names."""
        fd = None if self._hold is None else self._hold.fd
        if fd is None:
            return False
        try:
            held = os.fstat(fd)
        except OSError:
            return False
        return (held.st_rdev, held.st_ino, held.st_dev) == (opened.st_rdev, opened.st_ino, opened.st_dev)

    def close(self) -> None:
        """Close the port and let go of this link's share of its lock; safe to call more than once.

        Another thread's exchange in progress is waited for, at most :func:`close_wait_s` (its own
        worst case by its time-outs) -- a switch-off (:attr:`on_reconnect`'s ``blind`` commands,
        XOF) for its whole query, reconnects included (:meth:`_switch_off_wait_s`): a close never
        cuts one short that is still within its time-outs. Past that, the link is marked closing
        and the port closed between two of the exchange's steps: the exchange stops at its next
        step without touching the port's descriptor (whose number an open() elsewhere may have
        taken by then) and fails as a lost link, not reconnected. Called from a signal handler in
        the thread whose exchange holds the link, it cannot wait: the exchange stops likewise --
        unless it is a switch-off, which goes on; the port is closed at its end."""
        me = threading.get_ident()
        if self._closer == me:
            # a signal handler's close inside this thread's own close, which holds the exchange's
            # lock and closes all as the handler returns (or, should the handler raise, in its
            # finally blocks): waiting for that lock waited close_wait_s for itself, then released
            # it under the outer close: another thread's exchange could take it and reopen the port meanwhile
            return
        if self._owner == me:
            if self._running is not None and self._is_switch_off(self._running[0]):
                self._close_after_query = True
                return
            self._close_under_exchange()
            return
        try:
            if self._wait_for_exchange():
                self._close_all()
            else:
                self._close_under_exchange()
        finally:
            if self._closer == me:
                self._closer = None
                self._lock.release()

    def _close_all(self) -> None:
        """Close the port and let go of the lock's share (the exchange's lock held, or its end)."""
        try:
            self._close_port()
        finally:  # a signal's handler raising in the port's close: the share goes all the same
            hold, self._hold = self._hold, None
            if hold is not None:
                hold.release()

    def _is_switch_off(self, command: str | None) -> bool:
        return command is not None and command.split(" ", 1)[0] in getattr(self.on_reconnect, "blind", ())

    def _switch_off_wait_s(self) -> float:
        """A switch-off's whole query at its longest by its time-outs: each attempt (the first,
        and one per reconnect allowed, ``retries``) may reopen the port (:data:`_OPEN_WAIT_S`; a
        local device's :data:`_OPEN_WAIT_LOCAL_S`), check the device (one exchange) and write the
        switch-off blind (a write and a drain), then exchange (:func:`close_wait_s`); a reconnect
        first waits out the old port's output."""
        one = close_wait_s(self.timeout_s, self.write_timeout_s, self.min_interval_s)
        opening = _OPEN_WAIT_S if "://" in self.url else _OPEN_WAIT_LOCAL_S
        attempt = opening + one + 2 * self.write_timeout_s + one
        return (self.retries + 1) * attempt + self.retries * self.write_timeout_s

    def _wait_for_exchange(self) -> bool:
        """Take the exchange's lock, waiting for another thread's exchange at most its worst case
        counted from this call (a switch-off's from its own start): True once taken."""
        start = time.monotonic()
        one = close_wait_s(self.timeout_s, self.write_timeout_s, self.min_interval_s)
        while True:
            limit = start + one
            running = self._running
            if running is not None and self._is_switch_off(running[0]):
                limit = max(limit, running[1] + self._switch_off_wait_s())
            left = limit - time.monotonic()
            if left <= 0:
                return False
            # in slices: an exchange that starts meanwhile may be a switch-off, waited for longer.
            # Taken and recorded in one step for a stop signal (close() releases what is
            # recorded): one landing between the two left the link locked for good
            with held(*_STOPS):
                if self._lock.acquire(timeout=min(left, _READ_SLICE_S)):
                    self._closer = threading.get_ident()
                    return True

    def _close_under_exchange(self) -> None:
        """Close the link under an exchange that holds its lock: marked closing, the port detached
        and closed between two of its steps (the one in progress, in another thread, ends first:
        a read slice at most), so that no step touches the descriptor again. A step of this very
        thread in progress (a signal handler interrupted it) touches it once more as the handler
        returns: the port is then closed at that step's end."""
        with self._io:
            self._closing = True
            ser, self._serial = self._serial, None
            hold, self._hold = self._hold, None
            if self._steps:
                self._after_step.append((ser, hold))
                return
            self._shut(ser, hold)

    def _shut(self, ser, hold: PortHold | None = None) -> None:
        """Close the detached port ``ser`` (its unsent output waited for, or discarded) and let go
        of ``hold``, this link's share of the port's lock."""
        try:
            if ser is not None:
                try:
                    self._await_output(ser)
                finally:  # a stop cuts the wait short: the bytes are discarded, the port closed all the same
                    self._discard_output(ser)
                    try:
                        ser.close()
                    except (serial.SerialException, OSError):  # closing a dead link: nothing left to do
                        pass
                self.log.info("%s closed", shown_name(self.url))
        finally:
            if hold is not None:
                hold.release()

    def _close_port(self) -> None:
        """Close the port, its lock kept (a reconnect reopens it) -- unless its node is gone (an
        adapter unplugged): then its descriptor is closed too, or the re-plugged adapter would
        come back under another name (:meth:`PortHold.let_go_if_gone`). Under the port's step
        lock: a close from another thread, past its wait, finds the port closed or whole."""
        with self._io:
            ser, self._serial = self._serial, None
            self._shut(ser)
        if self._hold is not None:
            self._hold.let_go_if_gone()

    def _await_output(self, ser) -> None:
        """Wait, at most ``write_timeout_s`` (as a command's write may), for bytes still unsent.

        Why: Linux's last close of a serial port waits for its unsent output up to the port's
        closing_wait, 30 s by default: an adapter whose output had stopped (wedged) held a
        command that close long after the tube's state was said, its stop signals ignored by
        then. Every command is drained as it is sent (:meth:`_drain`), so bytes left now are a
        wedged port's, not a command's still leaving."""
        deadline = time.monotonic() + self.write_timeout_s
        while _unsent(ser) and time.monotonic() < deadline:
            time.sleep(_CLOSE_POLL_S)

    def _discard_output(self, ser) -> None:
        """Drop the bytes still unsent, so that closing the port does not wait for them, and say so
        -- unless they hold the switch-off (the on_reconnect's ``blind`` command, XOF): it was not
        confirmed (its reply cannot come before it left), and the port's close, which waits for it
        (up to 30 s on Linux), sends it if the adapter moves again; discarded, a tube the operator
        was just warned of stayed on (review s52rvacq). Other bytes go: a delayed XON must not
        reach the controller once its command has ended."""
        left = _unsent(ser)
        undrained, self._undrained = self._undrained, []  # a port opened again starts with none
        off = sorted(set(undrained) & set(getattr(self.on_reconnect, "blind", ())))
        if left and off:
            self.log.warning(
                "%s: %d bytes still unsent after %.1f s (the port's output is not draining) hold %s, not "
                "confirmed: left for the port to send as it closes (Linux waits up to 30 s for them)",
                shown_name(self.url),
                left,
                self.write_timeout_s,
                " ".join(off),
            )
        elif left:
            with contextlib.suppress(serial.SerialException, OSError, ValueError, AttributeError):
                ser.reset_output_buffer()
            self.log.warning(
                "%s: %d bytes still unsent after %.1f s (the port's output is not draining) were "
                "discarded, so that closing the port does not wait for them (up to 30 s on Linux)",
                shown_name(self.url),
                left,
                self.write_timeout_s,
            )

    def __enter__(self) -> SerialTransport:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SerialTransport({self.url!r}, baudrate={self.baudrate}, {'open' if self.is_open else 'closed'})"

    # -- exchanges --------------------------------------------------------------------------------
    def query(self, command: str) -> str:
        """Send ``command`` and return the reply line, stripped of its terminator.

        The exchange holds the transport's lock from the pause before sending to the end of the
        reply, so threads sharing a transport never interleave or pipeline commands.

        Parameters
        ----------
        command : str
            The command without its terminator, e.g. ``"STS"``.

        Returns
        -------
        str
            The reply without CR/LF and surrounding blanks.

        Raises
        ------
        DeviceError
            No complete reply within ``timeout_s`` (message names port, command and any partial
            reply), or the link was lost and could not be re-established within ``retries``.
        """
        if any(end.decode() in command for end in _LINE_ENDS):
            raise ValueError(f"{shown_name(self.url)}: command {command!r} contains a line end")
        payload = self._payload(command)
        me, since = threading.get_ident(), time.monotonic()
        with self._lock:
            # The lock's holder recorded with no call between the lock taken and the record, nor
            # between the record cleared and the lock's release (the with block's end): CPython
            # runs a signal's handler only as a function starts, after a call, or at a loop's jump
            # back. A record made by a call (_taken, before) could be cut short as it started: the
            # lock then held by a thread not recorded (a handler's close waited a whole exchange
            # for its own thread, and the record that followed cleared its closing mark, the port
            # reopened) or recorded to a thread done with it (a close that followed took an
            # interrupted XOF for a switch-off still running, and left the port open). Review s54;
            # tests/test_transport_stop_taking.py
            self._owner, self._running, self._closing, self._close_after_query = me, (command, since), False, False
            try:
                try:
                    # the query's start once the lock is held (a switch-off's close waits from here)
                    self._running = (command, time.monotonic())
                    return self._query(command, payload)
                finally:
                    self._close_if_asked()
            finally:
                try:
                    if self._close_after_query:  # (checked here: no call when there is none to do)
                        self._close_left()
                finally:
                    self._owner = self._running = None

    def _query(self, command: str, payload: bytes) -> str:
        """:meth:`query`'s attempts, the exchange's lock held."""
        attempt, lost = 0, None
        while True:
            try:
                if not self.is_open:
                    self._reopen(command, lost)
                return self._exchange(command, payload)
            except _LINK_ERRORS as exc:
                # Write time-outs are a device that does not take data, not a lost link.
                if isinstance(exc, _DrainTimedOut):
                    # not WriteTimedOut, which says nothing went: a switch-off reads this XOF as sent
                    raise DeviceError(
                        f"{shown_name(self.url)}: {command}: write timed out after {self.write_timeout_s:g} s: written, "
                        "but the port's output is not draining (it may still reach the controller)"
                    ) from exc
                if isinstance(exc, _StillQueued):
                    raise WriteTimedOut(
                        f"{shown_name(self.url)}: {command}: not sent: the port's output still holds "
                        f"{' '.join(exc.earlier)} after {self.write_timeout_s:g} s (not draining)"
                    ) from exc
                if isinstance(exc, serial.SerialTimeoutException):
                    raise WriteTimedOut(
                        f"{shown_name(self.url)}: {command}: write timed out after {self.write_timeout_s:g} s"
                    ) from exc
                attempt += 1
                self._close_port()
                if command.split(" ", 1)[0] in getattr(self.on_reconnect, "not_resent", ()):
                    # it may have reached the controller, and the device behind the reopened
                    # port is known only to be of the model: resent, XON switched on a second
                    # unit with settings this session never sent. The caller switches off
                    # (XOF is resent: it reconnects, checked) and the tube is said to be on.
                    raise DeviceError(
                        f"{shown_name(self.url)}: {command}: link lost ({exc}) after it may have reached the "
                        "controller; not sent again after a reconnect: X-rays may be on"
                    ) from exc
                if isinstance(exc, _ClosedUnderIt):
                    # close() from another thread: reopened here, the link was open again, its
                    # port's lock held, after close() had returned -- the close undone (after the
                    # not-resent check above: its "X-rays may be on" is said first)
                    raise DeviceError(
                        f"{shown_name(self.url)}: {command}: link lost ({exc}); not reconnected: the link was closed"
                    ) from exc
                if attempt > self.retries:
                    raise DeviceError(
                        f"{shown_name(self.url)}: {command}: link lost ({exc}); gave up after {self.retries} reconnect(s)"
                    ) from exc
                self.log.warning(
                    "%s: link lost during %s (%s); reconnecting (%d/%d)",
                    shown_name(self.url),
                    command,
                    exc,
                    attempt,
                    self.retries,
                )
                lost = exc  # reopened at the top of the loop, where a link lost again is retried

    def _reopen(self, command: str | None, lost: BaseException | None) -> None:
        """Open the port (the lock held) and, when it was open before, let :attr:`on_reconnect`
        check the device now behind it before ``command`` (None: :meth:`open`'s) goes out.
        ``lost``: the error that closed the link within this query (named in the message), or None."""
        reconnect = self._opened_once
        try:
            self._open_port()
            if reconnect and self.on_reconnect is not None:
                try:
                    self.on_reconnect(self._ask)
                except BaseException as exc:  # a write time-out, a signal too: a link left open unchecked
                    if isinstance(exc, NoReply) and command in getattr(self.on_reconnect, "blind", ()):
                        self._send_blind(command)
                    check = " ".join(self._undrained) or "identity check"  # (the close clears it)
                    self._close_port()  # would be trusted by the next query; reopened, it is asked again
                    if isinstance(exc, _DrainTimedOut):
                        # the check's drain, not the command's: said as query()'s drain time-out,
                        # the error claimed the command written (review s53: "XOF ... written")
                        what = f"{command}: not sent: " if command else ""
                        raise WriteTimedOut(
                            f"{shown_name(self.url)}: {what}after the port was reopened, the identity check's "
                            f"{check} did not leave the port within {self.write_timeout_s:g} s (its output is "
                            "not draining)"
                        ) from exc
                    raise
        except DeviceError as reopen:
            self._close_port()
            if lost is None:
                raise
            # a silent device stays NoReply (a switch-off does not ask it again); a port that
            # cannot be opened any more is not PortUnavailable here: bytes went out before
            kind = NoReply if isinstance(reopen, NoReply) else DeviceError
            raise kind(
                f"{shown_name(self.url)}: {command}: link lost ({lost}) and reconnecting failed ({reopen})"
            ) from lost

    def _send_blind(self, command: str) -> None:
        """Write ``command`` once to a device that did not answer :attr:`on_reconnect`'s check,
        when the check names it ``blind`` (the switch-off): a controller that still acts on commands
        but whose replies are lost was switched off so before the check existed, and silence is not
        another device's answer. Its reply is never read: nothing on this link confirms it."""
        try:
            self.commands_written += 1  # before the write, as every command's: 0 means nothing went
            self._undrained.append(command.split(" ", 1)[0])
            self._write(self._serial, command, self._payload(command))
            self._drain(self._serial, command)
            self._undrained.clear()
        except _DrainTimedOut:
            self.log.warning(
                "%s: %s written to a device that did not answer the identity check, but the port's output "
                "is not draining (not confirmed; left for the port to send as it closes)",
                shown_name(self.url),
                command,
            )
            return
        except _GoneMidDrain as exc:
            self.log.warning(
                "%s: %s written to a device that did not answer the identity check, but the port was lost as it "
                "drained (%s): not known to have left (not confirmed)",
                shown_name(self.url),
                command,
                exc,
            )
            return
        except _LINK_ERRORS as exc:
            self.log.warning(
                "%s: %s could not be written to the unchecked device either (%s)", shown_name(self.url), command, exc
            )
            return
        self.log.warning(
            "%s: %s written to a device that did not answer the identity check (not confirmed)",
            shown_name(self.url),
            command,
        )

    def _ask(self, command: str) -> str:
        """One exchange for :attr:`on_reconnect`, within the query or :meth:`open` that reconnected
        (its lock held). No barrier (:meth:`_cross`): nothing but the check goes to a device not
        yet checked -- a query of the controller's may be a command to another instrument."""
        return self._exchange(command, self._payload(command), barrier_ok=False)

    def _payload(self, command: str) -> bytes:
        """The bytes of ``command`` on the wire (its terminator added)."""
        return (command + self.terminator).encode("ascii")

    def _exchange(self, command: str, payload: bytes, *, barrier_ok: bool = True) -> str:
        ser = self._serial
        self._drain_pending()
        barrier = self._barrier_for(command) if barrier_ok else None
        if barrier is None:
            self._await_late_reply()
        else:  # its exchange is the wait for a late reply, and more: an answer to "is it over?"
            self._cross(ser, barrier, command)
        self._wait_spacing(ser)
        self._flush_late(ser)  # a late reply to an earlier, timed-out command
        t0 = time.monotonic()
        self._rx = bytearray()
        self.log.debug("%s > %s", shown_name(self.url), command)
        written = False
        try:
            if self._undrained:
                # an earlier command's drain timed out and its bytes may still be queued: written
                # behind them this one would pipeline, and read their reply as its own once they
                # left (review s52rvdrain); it waits for them as a drain may, else is not written
                try:
                    self._drain(ser, " ".join(self._undrained))
                except _DrainTimedOut:
                    raise _StillQueued(self._undrained) from None
                self._undrained.clear()
            # counted before the write: a stop landing after the write, before a count after it,
            # would leave an interrupted caller saying the controller was never reached
            self.commands_written += 1
            self._undrained.append(command.split(" ", 1)[0])
            self._write(ser, command, payload)
            # its bytes are out: owed its reply from here, even if the drain below fails (the
            # controller may have the command; its reply then comes on the reopened port)
            written = True
            self._drain(ser, command)
            self._undrained.clear()  # the drain waits for the whole output: every byte has left
            reply = self._read_line(command, t0 + self.timeout_s)
        except BaseException as exc:
            if isinstance(exc, NoReply) or (written and isinstance(exc, _LINK_ERRORS)):
                # its reply may still come, after the next command is sent -- after a read error,
                # on the reopened port, before the reply to the reconnect check: owed for one more
                # reply time-out from now (not from the send: the wait's last slice and a stall
                # before the next command ate into a window counted from there)
                self._owe(command, time.monotonic() + self.timeout_s)
            self._timed_out = isinstance(exc, NoReply)
            if not isinstance(exc, (NoReply, _Undecided, *_LINK_ERRORS)):
                # a signal (Ctrl-C, a StopSignal) cut the wait short: the reply is still on its way
                self._pending = (command, t0 + self.timeout_s)
                self.log.debug(
                    "%s: %s interrupted (%s) before its reply", shown_name(self.url), command, type(exc).__name__
                )
            raise
        finally:
            self._last_exchange = time.monotonic()
        self.log.debug("%s < %s (%.1f ms)", shown_name(self.url), reply, 1e3 * (self._last_exchange - t0))
        return reply

    def _wait_spacing(self, ser) -> None:
        """Wait out the command spacing, counted from the controller's last byte: a byte that comes
        meanwhile restarts it. L8121.md allows replies ending in CR LF, and a line is read at its
        CR; a unit whose LF came 30 ms after its CR had answered only then, and a command 60 ms
        after the CR reached it 30 ms after its reply, and was lost by a controller model that
        needs its ~50 ms (session 53). A byte restarts it only within two spacings of the last
        exchange (a caller that paused finds the late LF waiting, and its time is not known): a
        line that never falls quiet (a stuck one sending NULs) is noise, left to the flush, and
        costs a command at most two spacings more, three in all (:func:`exchange_longest_s`
        counts three)."""
        cap = self._last_exchange + 2 * self.min_interval_s
        seen = 0  # bytes already waiting came after the last exchange too (the caller paused)
        while True:
            with self._closed_as_lost(ser, "it waited out the command spacing"):
                waiting = ser.in_waiting
            now = time.monotonic()
            if waiting != seen and now < cap:
                seen, self._last_exchange = waiting, now
            if (wait := self._last_exchange + self.min_interval_s - now) <= 0:
                return
            time.sleep(min(wait, _SPACING_SLICE_S))

    def _write(self, ser, command: str, payload: bytes) -> None:
        """Send ``payload``, timed out only while bytes are left unsent (the caller drains the
        output, :meth:`_drain`, once the command counts as written).

        pyserial checks its write time-out after ``os.write`` has returned, so a process stalled
        right there (a loaded machine, the GIL held by another thread past ``write_timeout_s``)
        read as a write time-out although the command had gone out, and its reply, then not read,
        came after the next command. On a POSIX port (its descriptor non-blocking, as pyserial
        opens it) the bytes are written here and counted: the deadline applies only to what is
        still unsent. pyserial's output queue cannot stand in for the count (a pty reports it 0
        even when the kernel takes nothing, and Windows drops what a timed-out write left).
        Other links (sockets, RFC 2217, Windows) use pyserial's write: a time-out there stays one."""
        fd = getattr(ser, "fd", None)
        doing = f"it wrote {command}"
        if os.name != "posix" or not isinstance(fd, int) or getattr(ser, "_rs485_mode", None) is not None:
            # socket:// and rfc2217:// write to a TCP socket: EPIPE, not death
            with self._closed_as_lost(ser, doing), _sigpipe_held():
                ser.write(payload)
        else:
            view, deadline = memoryview(payload), time.monotonic() + self.write_timeout_s
            while view:
                # each write and wait a step of its own: a close between two finds fd, the number,
                # perhaps another file's (session 53: the command went into it)
                with self._closed_as_lost(ser, doing):
                    try:
                        view = view[os.write(fd, view) :]
                    except BlockingIOError:
                        pass
                    except OSError as exc:
                        raise serial.SerialException(f"write failed: {exc}") from exc
                if not view:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    sent = len(payload) - len(view)
                    raise serial.SerialTimeoutException(f"Write timeout ({sent} of {len(payload)} bytes sent)")
                with self._closed_as_lost(ser, doing):
                    select.select([], [fd], [], min(left, 0.05))

    def _queue_left(self, ser, command: str) -> int:
        """The bytes still queued as ``command`` drains. Why not :func:`_unsent`: a port gone in the
        poll (its ioctl's EIO, an unplugged adapter; no descriptor, the port closed) read as an
        empty queue, the command drained, and the reply was then read from a port that was gone.

        Raises
        ------
        _GoneMidDrain
            The queue cannot be read: a lost link, the command's fate unknown."""
        fd = getattr(ser, "fd", None)
        try:
            with self._closed_as_lost(ser, f"{command} drained"):
                if not isinstance(fd, int):
                    raise OSError("the port was closed")
                return int(ser.out_waiting or 0)
        except _ClosedUnderIt as exc:
            if self._closing or ser is not self._serial:
                raise  # closed by close(): a lost link not reconnected, not a port gone by itself
            raise _GoneMidDrain(f"the port went while {command} drained: {exc.__cause__ or exc}") from exc
        except (serial.SerialException, OSError, ValueError, TypeError) as exc:
            raise _GoneMidDrain(f"the port went while {command} drained: {exc}") from exc

    def _drain(self, ser, command: str = "the command") -> None:
        """Wait until the command just written has left the port, at most ``write_timeout_s``
        (:class:`_DrainTimedOut` past it; its bytes stay queued, :meth:`close` decides on them).

        Why: ``ser.flush()`` (tcdrain) has no time limit: on a wedged adapter an exchange waited
        forever, the switch-off's ``XOF`` too, its stop signals held. A local port's queue is
        polled instead, as :meth:`_await_output` does; a link whose queue cannot be read (a URL)
        keeps ``ser.flush()``, whose wait is bounded by its own time-outs. A port that goes while
        its queue is polled is a lost link (:class:`_GoneMidDrain`), not a drained command."""
        with self._closed_as_lost(ser, f"{command} drained"):
            if _queued(ser) is None:
                ser.flush()  # a URL; or a local port gone already: tcdrain fails, the link's loss
                return
        deadline = time.monotonic() + self.write_timeout_s
        while left := self._queue_left(ser, command):
            wait = deadline - time.monotonic()
            if wait <= 0:
                raise _DrainTimedOut(f"Drain timeout ({left} bytes still unsent)")
            # about the bytes' time on the wire, a few ms at 9600 baud: a command goes out at once
            time.sleep(min(wait, _CLOSE_POLL_S, max(_DRAIN_POLL_MIN_S, 10 * left / self.baudrate)))

    def _flush_late(self, ser) -> None:
        """Discard what has arrived before a command is sent (nothing is owed to it yet): each
        whole line is the late reply of a command that timed out, which is then no longer owed.
        Commands whose late reply has not come within a further reply time-out are forgotten."""
        self._forget_overdue()
        with self._closed_as_lost(ser, "it flushed the input before a command"):
            waiting = ser.in_waiting
            stale = ser.read(waiting) if waiting else b""
            ser.reset_input_buffer()
        lines = [line for line in re.split(rb"[\r\n]", stale)[:-1] if line.strip()]
        for line in lines:
            late = self._owed.pop(0)[0] if self._owed else "an earlier command"
            self.log.debug("%s < %s (late reply to %s: discarded)", shown_name(self.url), _text(line).strip(), late)

    @contextlib.contextmanager
    def _closed_as_lost(self, ser, doing: str):
        """One step of the exchange that touches the port ``ser``'s descriptor, under the step
        lock (``_io``), which a :meth:`close` under the exchange takes to close the port: a link
        closed (marked closing, or ``ser`` no longer its port) raises the lost link it is
        (:class:`_ClosedUnderIt`) before the descriptor is touched -- its number may be another
        file's by now. A port found closed within the step (pyserial's ``in_waiting`` and
        ``read`` raise ``TypeError`` then, its descriptor None: a traceback, session 53) is read
        so too; on an open port the error is a bug, raised as such."""
        with self._io:
            self._steps += 1
            try:
                if self._closing or ser is None or ser is not self._serial:
                    raise _ClosedUnderIt(f"the link was closed under the exchange before {doing}")
                try:
                    yield
                except (TypeError, AttributeError, ValueError, *_LINK_ERRORS) as exc:
                    if isinstance(exc, _ClosedUnderIt) or (
                        ser is self._serial and not self._closing and getattr(ser, "is_open", False)
                    ):
                        raise
                    raise _ClosedUnderIt(f"the port was closed under the exchange as {doing}: {exc}") from exc
            finally:
                self._steps -= 1
                while not self._steps and self._after_step:  # a close from a handler in this step
                    self._shut(*self._after_step.pop())

    def _read_some(self, ser, doing: str) -> bytes:
        """What has come, or one read slice's wait for it (the port's read time-out)."""
        with self._closed_as_lost(ser, doing):
            return ser.read(max(1, ser.in_waiting))

    def _forget_overdue(self) -> None:
        """Drop the commands owed a late reply whose wait for it has passed."""
        now = time.monotonic()
        self._owed = [(c, until) for c, until in self._owed if until > now]

    def _is_late(self, command: str, text: str) -> bool:
        """Whether ``text``, read as the reply to ``command``, is instead the late reply of a
        command that timed out: one is owed, and ``text`` fits that command and not ``command``
        by the dialect's grammar. Then it is discarded (logged) and one fewer is owed. A line that
        fits neither is a bad reply, not a late one: it goes to the caller, which reports it (as
        "unexpected" or "unparseable") -- swallowed, it would read as a silent controller, which a
        switch-off stops retrying."""
        self._forget_overdue()
        if self.reply_fits is not None and self.reply_fits(command, text):
            self._answered()  # the controller answers in order: what was owed before is not coming
            return False
        if not self._owed or self.reply_fits is None:
            self._owed.clear()
            return False
        late = self._drop_owed_to(text)
        if late is None:
            return False
        self.log.debug("%s < %s (late reply to %s, not %s's: discarded)", shown_name(self.url), text, late, command)
        return True

    def _owe(self, command: str, until: float) -> None:
        """``command``'s reply was not read: owed until ``until`` (:attr:`_owed`), and its word
        unanswered until a reply shows the controller has caught up (:attr:`_unanswered`)."""
        self._owed.append((command, until))
        word = command.split(" ", 1)[0]
        if word in self._unanswered:
            self._unanswered.remove(word)
        self._unanswered.append(word)  # the last: the most recent

    def _answered(self) -> None:
        """A reply shows that the controller has answered everything sent before it."""
        self._owed.clear()
        self._unanswered.clear()

    def _drop_owed_to(self, text: str) -> str | None:
        """``text`` is the late reply of the first owed command it fits: that one and those owed
        before it are no longer owed (answered in order: theirs came, or will not come), and
        its command is returned; None when it fits none (nothing dropped)."""
        for i, (owed, _) in enumerate(self._owed):
            if self.reply_fits(owed, text):
                del self._owed[: i + 1]
                return owed
        return None

    def _barrier_for(self, command: str) -> str | None:
        """The barrier query to send before ``command`` (:meth:`_cross`), or None: ``command`` is
        one of :attr:`late_barriers` (a query) and the last command left unanswered was of its
        word (a poll or status loop asking again), so its own reply and the late one would read
        alike; the barrier is the first of the others not owed a reply either. Not after a
        command of another word went unanswered since (a switch-off's ``XOF`` to a silent
        controller): one more query into the silence, its ``STS`` then is held as before. None
        too while earlier bytes may still be queued (a drain that timed out): the command then
        waits for them, or is not sent."""
        word = command.split(" ", 1)[0]
        if self.reply_fits is None or word not in self.late_barriers or self._unanswered[-1:] != [word]:
            return None
        if self._undrained:
            return None
        avoid = {word, *self._unanswered, *(c.split(" ", 1)[0] for c, _ in self._owed)}
        return next((b for b in self.late_barriers if b not in avoid), None)

    def _cross(self, ser, barrier: str, command: str) -> None:
        """Send ``barrier`` before ``command``, a query whose word is still owed a reply, and read
        its reply: the controller answers in order, so once a line that
        can only be the barrier's has come, every reply owed before it has come or never will,
        and the query that follows reads its own -- however late the owed one was (L8121.md
        bounds no reply's lateness). Lines before it that fit an owed command and not the barrier
        are the late replies (discarded); a line that fits both (``ERROR``) or neither (noise)
        decides nothing. Without it the query's reply, fitting both, was held a reply time-out
        for a second line when the owed reply never came (``status()`` 0.10 -> 0.42 s at a
        0.25 s time-out, 2.6 s at the dialects' 2 s). It stands in for :meth:`_await_late_reply`
        (a late reply that comes is read and discarded here).

        The barrier is a query, owed its reply time-out like any: nothing is written behind it
        before its reply or that time-out (L8121.md: "one command, one reply ... never
        pipeline"). Given a quarter of one, the query was written while a unit answering in
        nine tenths of its time-out was still answering the barrier, and its reply, queued
        behind, came past its own time-out (three ``status()`` in a row failed, review s56rvtx).
        No reply within it: NoReply, ``command`` not sent (in order, its reply would queue behind
        the barrier's), the barrier owed. A reply later than :func:`late_reply_wait_s` (a slow
        unit): ``command`` is not sent either (DeviceError, the controller caught up: the next
        query reads its own reply at once) -- sent, the exchange would be two slow replies long,
        past :func:`exchange_longest_s`, on which the guardian's kill bound and the close waits
        rest."""
        self._wait_spacing(ser)
        self._flush_late(ser)
        self._timed_out = False  # this exchange is the wait for a late reply
        t0 = time.monotonic()
        deadline = t0 + self.timeout_s
        buf = self._rx = bytearray()
        owed, stalled = list(self._unanswered), False
        self.log.debug("%s > %s (barrier: a reply to %s is owed)", shown_name(self.url), barrier, self._unanswered)
        self.commands_written += 1
        self._undrained.append(barrier)
        try:
            try:
                self._write(ser, barrier, self._payload(barrier))
                self._drain(ser, barrier)
            except serial.SerialTimeoutException:
                raise _StillQueued([barrier]) from None  # the query is not written behind it
            self._undrained.clear()
            while True:
                lines = re.split(rb"[\r\n]", bytes(buf))
                buf = self._rx = bytearray(lines[-1])
                for raw in (line for line in lines[:-1] if line.strip()):
                    if not self._is_barriers(barrier, _text(raw).strip()):
                        continue
                    self._answered()
                    self._rx = bytearray()  # (what follows it is no reply: the flush takes it)
                    took = time.monotonic() - t0
                    if took <= late_reply_wait_s(self.timeout_s) + _READ_SLICE_S:
                        return
                    raise _SlowBarrier(
                        f"{shown_name(self.url)}: {command} not sent: the controller answered {barrier}, asked "
                        f"before it (a reply to {', '.join(owed)} was owed), only after {took:.2f} s; it has "
                        f"caught up, ask again"
                    )
                if time.monotonic() >= deadline and not stalled:
                    # one slice more, as _read_line waits for a reply due in time that a stall of
                    # this process kept from being read
                    stalled, deadline = True, time.monotonic() + _READ_SLICE_S
                elif time.monotonic() >= deadline:
                    self.log.debug(
                        "%s: no reply to the barrier %s within %g s", shown_name(self.url), barrier, self.timeout_s
                    )
                    self._owe(barrier, time.monotonic() + self.timeout_s)
                    self._timed_out = True  # the next command waits for its late reply, as after any time-out
                    raise NoReply(
                        f"{shown_name(self.url)}: no reply to {command}: not sent, the controller did not answer "
                        f"{barrier}, asked before it (a reply to {', '.join(owed)} was owed), within "
                        f"{self.timeout_s:g} s"
                    )
                buf += self._read_some(ser, f"it read the reply to {barrier}")
        except (NoReply, _SlowBarrier):
            raise  # (owed already, or answered)
        except BaseException:
            # written: its reply may still come (a stop, a lost link); told from the next
            # command's by the grammar, as any owed reply -- a switch-off does not wait for it
            self._owe(barrier, time.monotonic() + self.timeout_s)
            raise
        finally:
            self._last_exchange = time.monotonic()

    def _is_barriers(self, barrier: str, text: str) -> bool:
        """Whether ``text``, read after ``barrier`` was sent, is its reply: it fits the barrier
        and no command owed a reply (:meth:`_cross`). One that fits an owed command and not the
        barrier is a late reply (discarded); one that fits both or neither decides nothing."""
        fits = self.reply_fits(barrier, text)
        earlier = any(self.reply_fits(c, text) for c in self._unanswered) or any(
            self.reply_fits(c, text) for c, _ in self._owed
        )
        if fits and not earlier:
            self.log.debug("%s < %s (barrier: nothing owed before it is coming)", shown_name(self.url), text)
            return True
        late = self._drop_owed_to(text) if earlier and not fits else None
        self.log.debug(
            "%s < %s (before the barrier's reply: %s)",
            shown_name(self.url),
            text,
            f"late reply to {late}: discarded" if late else "decides nothing",
        )
        return False

    def _drain_pending(self) -> None:
        """Complete an exchange a signal cut short (``L8121.md``: "one command, one reply ... never
        pipeline"): wait for its reply, up to that reply's own deadline, and discard it, so the next
        command reads its own reply. A switch-off after Ctrl-C waits at most one reply time-out more;
        sent at once instead, each command read the previous one's reply (XOF read SIN's, STS read
        XOF's) and the switch-off could never be confirmed. No reply by then is that command's
        time-out: it is owed, and the wait for a late reply (:meth:`_await_late_reply`) follows,
        as after any time-out (review s35r1: a Ctrl-C in the read of a reply 1.2 time-outs late
        sent ``XOF`` at once, into the unit still answering: lost, the late reply read as its)."""
        if self._pending is None:
            return
        (command, deadline), self._pending = self._pending, None
        if self._held_for == command:
            # a line that fits it was read and held back when the signal came (_read_line): its
            # own reply, or the late one owed before it, then its own still to come. Waited for,
            # the switch-off waited the rest of a reply time-out for a line mostly already read
            # (review s55rvlate); owed instead, a line still to come is told from XOF's echo by
            # the grammar (_is_late), as after any time-out
            self._held_for = None
            self._owe(command, time.monotonic() + self.timeout_s)
            return
        ser, buf = self._serial, self._rx
        while not any(line.strip() for line in re.split(rb"[\r\n]", bytes(buf))[:-1]):
            if time.monotonic() >= deadline:
                self.log.debug(
                    "%s: no late reply to the interrupted %s within its time-out", shown_name(self.url), command
                )
                self._owe(command, time.monotonic() + self.timeout_s)
                self._timed_out = True
                return
            buf += self._read_some(ser, f"it awaited the interrupted {command}'s reply")
        late = next(line for line in re.split(rb"[\r\n]", bytes(buf)) if line.strip())
        self.log.debug(
            "%s < %s (late reply to the interrupted %s: discarded)", shown_name(self.url), _text(late).strip(), command
        )
        self._last_exchange = time.monotonic()  # the spacing counts from the controller's last reply

    def _await_late_reply(self) -> None:
        """After a reply time-out, before the next command: wait for the late reply to come (a
        quarter of ``timeout_s`` for its first byte, as the probe waits between rates) and the line
        to fall quiet for one read slice -- after a whole line or a fragment alike -- and discard
        it; at most :func:`late_reply_wait_s` in all (a line never quiet, a stuck one sending NULs,
        is noise, not a reply). Sent at once, 60 ms after the time-out, a command reached a unit
        still answering (a reply 0.3 s late): a unit that loses it then lost the switch-off's
        ``XOF``, confirmed only by a further attempt seconds later. A silent controller costs the
        quarter per command after a time-out; a reply later still is left to the flush before the
        command and to :meth:`_is_late`. (Waiting for a line end, a fragment then quiet was waited
        for until a whole time-out had passed, review s34-r2.)"""
        if not self._timed_out:
            return
        # the flag is cleared only once the wait is over: a Ctrl-C cutting it short left the
        # switch-off that follows to go out at once, into the unit still answering (review s34-r2)
        ser, buf = self._serial, self._rx  # a partial reply: the unit is mid-answer; kept on self,
        # what an interrupted wait read is there for the next one
        t0 = time.monotonic()
        first_by, cap = t0 + self.timeout_s / 4, t0 + late_reply_wait_s(self.timeout_s)
        heard = t0 if buf else None
        while True:
            data = self._read_some(ser, "it awaited a late reply")  # blocks one slice at most
            now = time.monotonic()
            if data:
                buf += data
                heard = now
            elif heard is not None:
                break  # what came, then a slice of quiet: the unit is done
            elif now >= first_by:
                self._timed_out = False
                return  # nothing came: a silent controller, not one still answering
            if now >= cap:
                break
        for line in (line for line in re.split(rb"[\r\n]", bytes(buf))[:-1] if line.strip()):
            self._forget_overdue()
            late = self._owed.pop(0)[0] if self._owed else "an earlier command"
            self.log.debug("%s < %s (late reply to %s: discarded)", shown_name(self.url), _text(line).strip(), late)
        self._rx, self._timed_out = bytearray(), False
        self._last_exchange = heard  # the spacing counts from the controller's last byte

    def _undecided(self, command: str, text: str) -> bool:
        """Whether ``text`` fits both the command owed a late reply and ``command``: a line that
        fits any command (a refusal, ``ERROR``) or two (B's ``XON``, the echo and a state), or a
        reply to the same command sent again (B's queries do not echo: ``SRL`` is ``REMOTE`` either
        way). Read as ``command``'s, a late refusal of a timed-out command made the reconnect check
        refuse the controller; and the late ``REMOTE`` of a reconnect check that timed out, read as
        the next check's, left that check's own ``REMOTE`` to be read as ``STS``'s, every later
        reply one command behind (a resent ``STS`` read a ``STANDBY`` from before the tube was
        switched on; review s55). So it is not decided on at once (:meth:`_read_line`): the cost,
        when the owed reply never comes, is the rest of this reply's time-out, once."""
        self._forget_overdue()
        if self.reply_fits is None:
            return False
        if self._owed and self.reply_fits(self._owed[0][0], text):
            return True
        # past its window too (session 56): L8121.md bounds no reply's lateness -- for a reply that
        # reports something (a state, a value) a late one would make stale. Not for the command's
        # own text echoed (XOF -> XOF): a late echo says what its own would; held, a switch-off after
        # a silent controller waited a whole reply time-out for nothing before its STS (review s56rvtx)
        return text != command and command.split(" ", 1)[0] in self._unanswered

    def _read_line(self, command: str, deadline: float) -> str:
        ser = self._serial
        buf = self._rx  # kept on self: an interrupted exchange's reply is completed from it (_drain_pending)
        drained = False
        # a line that may be the late reply owed or this command's own (_undecided): another line
        # within this reply's time-out is this command's (the controller answers in order), and
        # the first was the late one; none, and the first is this command's
        undecided = self._held_for = None
        noise = None  # a line that fits nothing, read while one was held: the reply garbled, or noise
        while True:
            cut = min((i for i in (buf.find(e) for e in _LINE_ENDS) if i >= 0), default=-1)
            if cut >= 0:
                line, rest = bytes(buf[:cut]), buf[cut + 1 :]
                # With nothing owed, the line is this command's reply whatever the driver's
                # reply_fits says: it stays in self._rx until returned, so that a stop landing in
                # that callback leaves it to _drain_pending, which discards it at once -- taken out
                # first, the switch-off after the stop waited a whole reply time-out (and a
                # quarter) for a reply that had come. A line that may be a late one leaves first,
                # as before: whether it was cannot be decided after a stop.
                # Past its window, only a reply to the word still unanswered may be a late one
                # (_undecided): a stop in the check of another's, its line gone, cost the
                # switch-off a whole reply time-out again (review s56rvtx).
                if (
                    self._owed
                    or command.split(" ", 1)[0] in self._unanswered
                    or undecided is not None
                    or not line.strip()
                ):
                    buf = self._rx = rest
                if line.strip():  # skip the empty line between the CR and LF of a CR LF
                    text = _text(line).strip()
                    if undecided is not None and not self.reply_fits(command, text):
                        noise = self._beside_held(text, undecided[0]) or noise
                        continue
                    if undecided is not None:
                        (first, late), undecided = undecided, None
                        self.log.debug(
                            "%s < %s (late reply to %s, not %s's: discarded)",
                            shown_name(self.url),
                            first,
                            late,
                            command,
                        )
                    elif (
                        self.reply_fits is not None
                        and self.reply_fits(command, text)
                        and self._undecided(command, text)
                    ):
                        undecided = self._hold_back(command, text)
                        continue
                    self._held_for = None
                    if self._is_late(command, text):
                        buf = self._rx = rest  # (out already: one was owed)
                        continue
                    self._rx = rest
                    return text
                continue
            left = deadline - time.monotonic()
            if left <= 0 and not drained:
                # This process may have been stalled across the deadline (a loaded machine, a long
                # garbage collection, a thread holding the GIL): this thread then wakes past it
                # before the device's reply, due in time, was delivered -- or, with a responder in
                # this process (an emulator's thread), before that thread ran again to write it.
                # Before calling the device silent, wait one more slice, blocking with the GIL
                # released: a silent device costs 50 ms more, a stalled reply is read
                drained = True
                deadline = time.monotonic() + _READ_SLICE_S
                continue
            if left <= 0 and undecided is not None:
                return self._release_held(command, undecided, noise)
            if left <= 0:
                got = f"; partial reply {_quoted(bytes(buf))}" if buf else ""
                self.log.debug("%s < (nothing within %g s)%s", shown_name(self.url), self.timeout_s, got)
                dsr = self.dsr_low()
                got += f"; {dsr}" if dsr else ""
                raise NoReply(f"{shown_name(self.url)}: no reply to {command} within {self.timeout_s:g} s{got}")
            # the port's read time-out is one slice, so the deadline is overshot by at most two
            # slices (one of them the grace above)
            buf += self._read_some(ser, f"it read the reply to {command}")

    def _hold_back(self, command: str, text: str) -> tuple[str, str]:
        """Hold back ``text``, which fits ``command`` and a command owed a reply (:meth:`_undecided`):
        returns it and the command whose late reply it may be, no longer owed either way (a signal
        may end the wait for a second line: nothing is left owed for a line already read)."""
        owed = self._owed and self.reply_fits(self._owed[0][0], text)
        self._held_for = command
        return text, self._owed.pop(0)[0] if owed else f"an earlier {command.split(' ', 1)[0]}"

    def _beside_held(self, text: str, held: str) -> str | None:
        """A line read while ``held`` is held back that does not fit the command: not the line that
        shows the held one was late. A late reply to another command owed (discarded: None), or
        noise -- or this command's reply garbled, the held one then late -- returned, for
        :meth:`_release_held` to decide on. Read as the deciding line, noise was returned as the
        reply and the reply itself came during the next command (session 56)."""
        late = self._drop_owed_to(text)
        why = f"late reply to {late}: discarded" if late else "no reply to it"
        self.log.debug("%s < %s (%s, while %r is held back)", shown_name(self.url), text, why, held)
        return None if late else text

    def _release_held(self, command: str, undecided: tuple[str, str], noise: str | None) -> str:
        """The reply time-out has passed with a line held back (``undecided``: it and the command
        whose late reply it may be) and no line of ``command``'s after it: it was ``command``'s,
        and the owed reply is not coming -- unless ``noise`` came after it, which may be the reply
        garbled (the held line then late): then neither is taken (:class:`_Undecided`), the
        caller's to ask again. Either way nothing more is owed."""
        self._answered()
        self._held_for = None
        if noise is not None:
            raise _Undecided(
                f"{shown_name(self.url)}: {command}: its reply is not known: {undecided[0]!r}, which may be "
                f"the late reply to {undecided[1]}, then {noise!r}, which fits no reply (noise, or the reply "
                "garbled); neither is taken"
            )
        return undecided[0]

    def dsr_low(self) -> str:
        """A note on a silent controller when the port reads DSR low, else "". L8121.md
        says the L8121-02's driver takes DSR dropping for a failed link, but gives no line state
        for the L8121-01, and a three-wire cable (or an adapter without the line) reads DSR low
        with a controller that answers: so DSR refuses nothing and is read only to say why a
        controller may be silent. A port without modem lines (a pty: ``OSError``; ``socket://``:
        always high) says nothing. Only a local port's line is read: a network link's modem lines
        are its terminal server's, which ``rfc2217://`` polls over the network, so each read could
        wait pyserial's network time-out (3 s) inside a switch-off's wait (review s46rv)."""
        ser = self._serial
        if not isinstance(ser, serial.Serial):  # serialposix / serialwin32: a local port
            return ""
        try:
            with self._closed_as_lost(ser, "it read DSR"):  # (a closed link raises: nothing said)
                low = ser.dsr is False
        except (serial.SerialException, OSError, ValueError, AttributeError, NotImplementedError):
            return ""
        if not low:
            return ""
        return "DSR low: the controller may be off or unplugged (a cable that does not carry DSR reads low too)"


def _quoted(data: bytes, head: int = 24) -> str:
    """``data`` quoted for an error line: whole when short, else its start and its length (a line
    streaming NULs sent hundreds)."""
    return repr(data) if len(data) <= head else f"{data[:head]!r}... ({len(data)} bytes)"


class PipeTransport:
    """The :class:`SerialTransport` interface over a pipe to the process that owns the port.

    The acquiring process talks to the X-ray source through the guardian process of
    :mod:`acquisition.guardian` (which started it and holds the real :class:`SerialTransport`):
    each :meth:`query` is one line down the pipe and one line back. :meth:`close` is the orderly
    release -- the guardian closes the port and exits without touching the source -- so a driver's
    ``close()`` (``off()`` first, then the transport's ``close()``) ends the session as over a
    serial port. If this process dies instead, the pipe closes without a release and the guardian
    switches the tube off.

    Parameters
    ----------
    url : str
        The port the guardian holds (named in every message).
    process : subprocess.Popen
        The guardian, with ``stdin`` and ``stdout`` pipes.
    timeout_s : float
        The guardian's reply time-out per exchange; this side waits for it plus the guardian's
        reconnect and a margin before calling the guardian lost.
    baudrate : int
        The port's rate (the guardian opened it): used only if this process must open the port
        itself because the guardian died.
    min_interval_s : float
        The command spacing, likewise.

    Notes
    -----
    If the guardian dies (``kill -9``, the OOM killer) the exchange in progress fails with
    :class:`DeviceError` (so the run stops and switches off), and every later exchange goes
    straight to the port, which the guardian's death has freed: the switch-off then reaches the
    controller, and is confirmed, instead of leaving the operator only a warning.
    """

    def __init__(
        self,
        url: str,
        process,
        *,
        timeout_s: float = 1.0,
        baudrate: int = 9600,
        min_interval_s: float = 0.06,  # the dialects' (acquisition.l8121.DIALECT_A)
        log: logging.Logger = logger,
        hold: PortHold | None = None,
    ):
        self.url = str(url)
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.min_interval_s = float(min_interval_s)
        self.log = log
        # the port's lock, shared with the guardian (it inherited the descriptor): this process's
        # descriptor closed once the guardian is READY (hand_over), the share kept until close():
        # the port this process opens if the guardian dies takes it again, or is refused
        self._hold = hold
        self._lost = False  # the guardian died (not released): the port is free for this process
        #: What the guardian's watchdog said when it switched X-rays off (its ``W`` line; the
        #: driver clears it at its next XON): the run's error names it, not a dropped beam.
        self.watchdog_off: str | None = None
        self._direct: SerialTransport | None = None
        self._process = process
        self._rfd = process.stdout.fileno()
        self._wfd = process.stdin.fileno()
        self._buf = b""
        self._seq = 0
        self._open = False
        #: The guardian said READY (it opened the port), or had to be killed at the end of a
        #: failed start: it may have sent to the controller (its switch-off), so without its word
        #: on the tube (:meth:`end_start` None) nobody vouches for the tube (the warning)
        self.may_have_sent = False
        self._lock = threading.Lock()
        #: The driver's reply grammar (as :attr:`SerialTransport.reply_fits`): the guardian applies
        #: its own; this one goes to the link this process opens if the guardian dies.
        self.reply_fits = None
        #: The driver's barrier queries (as :attr:`SerialTransport.late_barriers`): the same.
        self.late_barriers: tuple[str, ...] = ()
        #: The driver's re-identification (as :attr:`SerialTransport.on_reconnect`): the guardian
        #: checks its own reconnects; this one checks the port this process opens if the guardian
        #: dies (a new open of the port: the device behind it is asked before it is trusted).
        self.on_reconnect = None
        # the guardian's SerialTransport: write (1 s) + reply per attempt, one reconnect, and slack
        self._reply_wait_s = 2 * (self.timeout_s + 1.0) + 2.0

    @property
    def port(self) -> str:
        """The url the guardian holds (used in every message)."""
        return self.url

    @property
    def is_open(self) -> bool:
        """Whether the guardian is serving this process (or, after its death, the port is open here)."""
        return self._open or self._direct is not None

    @property
    def pid(self) -> int:
        """The guardian's process id."""
        return self._process.pid

    def wait_ready(self, timeout_s: float) -> None:
        """Wait for the guardian to report the port open (``READY``) or why not."""
        line = self._read_line(time.monotonic() + timeout_s, "start", timeout_s)
        self.may_have_sent = line == "READY"
        if line != "READY":
            self._finish()
            opened = not line.startswith("E 0 ")  # E 0: the guardian could not open the port at all
            why = repr(line) if opened else line[4:]
            error = DeviceError if opened else PortUnavailable
            raise error(why if why.startswith(self.url) else f"{shown_name(self.url)}: X-ray guardian: {why}")
        self._open = True
        if self._hold is not None:
            # the guardian's inherited copy holds the lock: this process's would pin the node of an
            # adapter unplugged, which then came back under another name. The share stays: a
            # port this process opens after the guardian's death takes the lock again (renew)
            self._hold.hand_over()
        self.log.info("%s opened through the X-ray guardian (pid %d)", shown_name(self.url), self._process.pid)

    def end_start(self, timeout_s: float) -> str | None:
        """The start was cut short (Ctrl-C in :meth:`wait_ready`, or it failed): ask the guardian
        to switch off and exit (``O``; before ``READY`` the request waits in the pipe), and wait up
        to ``timeout_s`` for it to say how it left the tube and exit -- killed if it has not: only
        then may the caller open the port itself, and what the guardian says (on stderr) comes
        before the caller's last line. Returns its ``O`` line's rest (``0 STATE``: off, confirmed
        by STS; ``3 MESSAGE``: not), or None: it never held the port, or died, or was killed."""
        self._open = False
        said = None
        try:
            said = self._ask_to_end(timeout_s)
        finally:  # whatever cut the wait short: the guardian must not hold the port after this
            try:
                self._process.wait(timeout=0.5 if said is None else 5.0)
            except subprocess.TimeoutExpired:
                self._process.kill()  # hung or stopped: it must not hold the port while the caller opens it
                self._process.wait()
                self.may_have_sent = True  # perhaps cut short in its switch-off, the port held
            self._finish()
        return said

    def _ask_to_end(self, timeout_s: float) -> str | None:
        """:meth:`end_start`'s request and wait: the ``O`` line's rest, or None."""
        said = None
        if not self._process.stdout.closed:  # (wait_ready's _finish closed it: the guardian is gone)
            try:
                _write_no_sigpipe(self._wfd, b"O\n")
            except OSError:
                pass
            try:
                self._process.stdin.close()  # and a guardian not yet serving reads its end after the O
            except OSError:
                pass
            deadline = time.monotonic() + timeout_s
            try:
                while said is None:
                    line = self._read_line(deadline, "start", timeout_s)
                    self.may_have_sent = self.may_have_sent or line == "READY"
                    said = line[2:] if line.startswith("O ") else None
            except DeviceError:  # its end of the pipe closed, or the deadline passed
                pass
        return said

    def open(self) -> None:
        """A no-op while the guardian serves; after :meth:`close` a new guardian is needed."""
        if not self._open:
            raise DeviceError(f"{shown_name(self.url)}: released; the X-ray guardian has exited")

    def close(self) -> None:
        """Release the port: the guardian closes it and exits, leaving the source as it is."""
        direct, self._direct, self._lost = self._direct, None, False
        if direct is not None:
            direct.close()
        hold, self._hold = self._hold, None
        if hold is not None:
            hold.release()  # the guardian's copy of the lock goes when it exits
        if not self._open:
            return
        self._open = False
        with self._lock:
            try:
                _write_no_sigpipe(self._wfd, b"X\n")
            except OSError:
                pass
            self._finish()
        self.log.info("%s released by this process (X-ray guardian exited)", shown_name(self.url))

    def _finish(self) -> None:
        for f in (self._process.stdin, self._process.stdout):
            try:
                f.close()
            except OSError:
                pass
        try:
            self._process.wait(timeout=5.0)
        except Exception:
            self.log.warning("%s: the X-ray guardian (pid %d) did not exit", shown_name(self.url), self._process.pid)

    def __enter__(self) -> PipeTransport:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"PipeTransport({self.url!r}, guardian pid {self._process.pid}, {'open' if self._open else 'closed'})"

    def query(self, command: str) -> str:
        """Send ``command`` through the guardian and return the reply line (as
        :meth:`SerialTransport.query`, whose errors the guardian passes back as ``DeviceError``)."""
        if any(end.decode() in command for end in _LINE_ENDS) or "\n" in command:
            raise ValueError(f"{shown_name(self.url)}: command {command!r} contains a line end")
        with self._lock:
            if self._lost:
                direct = self._take_over()
                try:
                    return direct.query(command)
                finally:
                    # the handover is the takeover's first open only: whether it was checked or
                    # failed (the port gone), a later reopen is a link lost and found again (s28-h7)
                    if getattr(self.on_reconnect, "handover", False):
                        self.on_reconnect.handover = False
            if not self._open:
                raise DeviceError(f"{shown_name(self.url)}: {command}: the port has been released")
            self._seq += 1
            seq = str(self._seq)
            self.log.debug("%s > %s (via guardian)", shown_name(self.url), command)
            t0 = time.monotonic()
            try:
                _write_no_sigpipe(self._wfd, f"Q {seq} {command}\n".encode("ascii"))
            except OSError as exc:
                self._open, self._lost = False, True
                raise GuardianLost(f"{shown_name(self.url)}: {command}: {self._died()} ({exc})") from exc
            deadline = t0 + self._reply_wait_s
            while True:  # replies to requests that were interrupted earlier carry older numbers
                kind, _, rest = self._read_line(deadline, command).partition(" ")
                got, _, text = rest.partition(" ")
                if kind == "C":  # the guardian's link was reopened (whichever request): counted here
                    self._count_reconnects(text)
                elif kind == "W":  # its watchdog switched off while this process was silent
                    self.watchdog_off = text
                elif got == seq:
                    break
            self.log.debug("%s < %s (%.1f ms)", shown_name(self.url), text, 1e3 * (time.monotonic() - t0))
            if kind == "R":
                return text
            raise NoReply(text) if kind == "N" else DeviceError(text)

    def _count_reconnects(self, text: str) -> None:
        """Add the guardian's reconnects (a ``C`` line) to :attr:`on_reconnect`'s count, as if this
        link had been reopened: the driver compares it across an exchange
        (acquisition.l8121.Reidentify.reconnects)."""
        check = self.on_reconnect
        try:
            if check is not None and hasattr(check, "reconnects"):
                check.reconnects += max(int(text), 0)
        except ValueError:
            self.log.warning("%s: the X-ray guardian's reconnect line %r is not a count", shown_name(self.url), text)

    def _take_over(self) -> SerialTransport:
        """The guardian died: open the port it held, here (once), so that the switch-off that
        follows reaches the controller. A kill -9 of this process is no longer covered, so the
        run that met the death stops."""
        if self._direct is None:
            try:  # the guardian is gone for good: reap it, so its end of the port is closed
                self._process.wait(timeout=5.0)
            except Exception:
                # alive but not serving (its stdin closed, e.g. a SIGTERM): two processes on one
                # port would discard each other's replies (each clears its input before an
                # exchange), so it is ended before this one opens the port
                try:
                    self._process.kill()
                    self._process.wait(timeout=5.0)
                except Exception:
                    pass
            self.log.warning(
                "%s: the X-ray guardian (pid %d) died; this process opens the port itself to switch off",
                shown_name(self.url),
                self._process.pid,
            )
            self._direct = SerialTransport(
                self.url,
                baudrate=self.baudrate,
                timeout_s=self.timeout_s,
                min_interval_s=self.min_interval_s,
                log=self.log,
                open=False,
            )
            self._direct.reply_fits = self.reply_fits
            self._direct.late_barriers = self.late_barriers
            self._direct.on_reconnect = self.on_reconnect
            # the guardian had the port open: this first open here is a reconnect (checked), but a
            # handover (the port held until the guardian died), not a link lost: not counted as one
            # whose confirmation may be another unit's (acquisition.l8121.Reidentify.handover) --
            # unless the guardian ended on the warning (exit 3): its own switch-off was confirmed
            # only by the unit now at the port, which this process's driver must hear of too
            self._direct._opened_once = True
            if hasattr(self.on_reconnect, "handover"):
                self.on_reconnect.handover = self._process.returncode != 3
        return self._direct

    def _died(self) -> str:
        """The guardian's death in an exchange, for the operator: which process, and how it ended
        (a signal by its name). Said as the cause: the exchange's own words (no reply, a baud rate
        or dialect to check) would blame the controller."""
        code = self._exit_code()
        if code is None:
            how = "its end of the pipe closed"
        elif code < 0:
            try:
                how = f"killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"killed by signal {-code}"
        else:
            how = f"exit code {code}"
        return (
            f"the X-ray guardian (pid {self._process.pid}), which held the port for this command, died "
            f"({how}); the port it freed is used directly from here"
        )

    def _exit_code(self) -> int | None:
        """The guardian's exit status, its end of the pipe closed: reaped first (the pipe closes as
        it dies, and polled at once, the error line said "code None" or "code -9" by a race; review
        s35r1). None: it has not exited within a second."""
        try:
            return self._process.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return None

    def _read_line(self, deadline: float, command: str, wait_s: float | None = None) -> str:
        """The guardian's next line, by ``deadline`` (``wait_s`` from its start: named in the error;
        ``command`` "start": its start or its end after a failed start)."""
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                who = f"the X-ray guardian (pid {self._process.pid})"
                wait_s = self._reply_wait_s if wait_s is None else wait_s
                if command == "start":
                    raise NoReply(
                        f"{shown_name(self.url)}: {who} did not report the port open within {wait_s:g} s of its start "
                        "(a slow start: the computer may be busy)"  # what to do: once the tube's state is known (_end_start)
                    )
                raise NoReply(f"{shown_name(self.url)}: {command}: no answer from {who} within {wait_s:g} s")
            ready, _, _ = select.select([self._rfd], [], [], left)
            if not ready:
                continue
            data = os.read(self._rfd, 4096)
            if not data:
                self._open = False
                self._lost = command != "start"  # (at start it could not open the port: nothing to take)
                if command != "start":
                    raise GuardianLost(f"{shown_name(self.url)}: {command}: {self._died()}")
                raise DeviceError(
                    f"{shown_name(self.url)}: the X-ray guardian exited as it started (code {self._exit_code()})"
                )
            self._buf += data
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("utf-8", "replace")  # the guardian writes UTF-8 (a reply's "µA")
