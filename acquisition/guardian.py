"""The tube-off guarantee: a guardian process that owns the source's port, and a signal guard.

A protocol that leaves X-rays on because its process died is the one failure the lab cannot
accept. Two mechanisms cover the two ways a process ends:

- **Signals it can handle** (Ctrl-C, ``kill``, a closed terminal or dropped ssh session, Ctrl-\\,
  Ctrl-Z: SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGTSTP): :class:`SignalGuard` turns the first one into :class:`StopSignal`
  (a ``KeyboardInterrupt``), so the protocol's own exit path switches the tube off and confirms
  it; every further signal, and any signal during that switch-off, is only acknowledged on
  stderr -- the switch-off sequence is never interrupted.
- **Deaths it cannot handle** (``kill -9``, the OOM killer, a crash in a C library) **and a
  process that stops** (SIGSTOP, a debugger, a hang): the port is
  owned by a small guardian process (``python -m acquisition.guardian``), started before the first
  command is sent. The acquiring process talks to the controller through a pipe
  (:class:`acquisition.transport.PipeTransport`, the interface of ``SerialTransport``). When that
  pipe closes without an orderly release, the guardian builds the driver on the port it holds
  with the configuration the acquiring process resolved (``L8121.resolved_config()``: dialect,
  baud rate, command spacing, time-outs -- no probe, no connect checks) and calls ``off()``
  (``XOF``, confirmed by ``STS``, in that dialect), writes the outcome to stderr and the lab
  notebook, and exits (also when it dies before the guardian is ready). While X-rays may be on it
  also watches the acquiring process's polls, once it has sent its first request (from the start
  when the caller says the tube may be on: ``radiokit acquire``): none for ``watchdog_s`` (the
  protocol's ``[source] watchdog_s``) and it switches off the same way, says so (a retry of an off
  it could not confirm in one short line), and keeps serving (the series or warm-up then stops
  when it next reads the source: a beam check, a warm-up poll) -- unless that off was confirmed
  only by another unit now at the port (the link reopened while X-rays may have been on): then it
  says so once and exits 3, and the acquiring
  process, if it runs again, switches off through the port itself. It runs in its own session and
  ignores SIGINT and SIGHUP, so the Ctrl-C of the terminal's process group, or the terminal closing,
  does not take it down with the acquiring process; SIGTERM and SIGQUIT sent to it are taken as
  the acquiring process gone (switch off, then exit).

The line protocol on the pipe (ASCII, one line each way; ``SEQ`` ties a reply to its request, so
a reply that arrives after its requester was interrupted is discarded)::

    Q SEQ COMMAND   ->  R SEQ REPLY  |  E SEQ MESSAGE     one exchange with the controller
                    |  N SEQ MESSAGE                      (N: the controller did not reply)
    X               ->  (exit)                            orderly release: close the port, no XOF
    O               ->  O 0 STATE  |  O 3 MESSAGE, (exit)  the start was cut short: switch off, say how
                                                          (0: confirmed by STS reading STATE; 3: not)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from radiokit.interrupts import (
    STOP_SIGNALS,
    Interrupted,
    after_import,
    deferred,
    note_after_the_end,
    raise_stop,
    redeliver,
)

__all__ = ["StopSignal", "SignalGuard", "start_guardian", "TUBE_WARNING", "main"]

#: The last line the operator reads when switching off could not be confirmed.
TUBE_WARNING = "WARNING: X-RAYS MAY STILL BE ON — switch off at the controller (key switch) now"


def guardian_gone(src, exc) -> bool:
    """Whether ``exc`` is a guardian's failed start that ended without a word on a tube that may
    be on: it held the port (it said READY, or was killed), perhaps cut short in its switch-off,
    or it never did (killed before READY) while the tube was not known off. The port is free
    again, and this process switches off through it, confirmed by STS, or ends on the warning
    (:func:`off_anyway`, the exit rule) -- also when neither the guardian nor a probe had opened
    it (the dialect given): a tube left on before (other software, a crash) is on still, and the command
    that was to warm up (or switch on) leaves it off. Counted as reached for that: the guardian
    may have opened the port before it died, so "never reached" would not be known true, and a
    switch-off that then fails ends on the warning (review s35r1: the tube was left on, and the
    last line said the port could not be opened). Not after the guardian's own word that the port
    cannot be opened (PortUnavailable): that one is "never reached", as for any such port."""
    from acquisition.errors import PortUnavailable

    gone = getattr(exc, "guardian_gone", False)
    if gone and not isinstance(exc, PortUnavailable):
        src.port_opened = True
    return gone


def off_anyway(src, interrupt: BaseException | None = None, *, blind: bool = True, describe=None, say=None) -> bool:
    """A source command whose connect failed (`off`) or was interrupted (`off`, `on`, `warm-up`),
    or a series whose guardian ended before READY (:func:`guardian_gone`):
    the switch-off is sent with whatever link there is and confirmed by STS -- by the connect
    itself when the port opened in a known dialect (its refusal sends XOF in a session that
    controls the tube), else here (:meth:`L8121.off_unconnected`: the port opened again; with
    ``blind``, the one XOF both dialects share when the probe found no dialect). Nothing when the
    port never opened, nor a second round after a switch-off that failed (its error is said; a
    silent controller would cost each round its time-outs). Says the outcome (an ``interrupt``
    gets it in ``tube``; ``describe`` words an error, by default its text on one line; ``say``
    writes a line, by default straight to stderr's descriptor -- the command line passes its own
    print to ``sys.stderr``, so that these lines keep their place among its others); returns
    whether STS confirmed it. The exit rule reads the driver. Shared by the source commands and a
    series (one switch-off through the freed port, not one each)."""
    from acquisition.errors import DeviceError

    say = say or _say
    if src is None or not src.port_opened or (src.dialect is None and not blind):
        return False
    state = src.confirmed_off
    if state is None and src.off_failed is None:
        # said now: with a silent controller the attempt takes its time-outs (seconds), and the
        # operator who pressed Ctrl-C or saw the connect fail would otherwise wait in silence
        why = "interrupted while connecting" if interrupt is not None else "the connect failed"
        say(f"{src.port}: {why}: sending XOF anyway and confirming by STS (a few seconds)")
        try:
            state = src.off_unconnected(after_interrupt=interrupt is not None)
        except DeviceError as exc:
            why = (describe or _one_line)(exc)
            if interrupt is None:
                say(f"error: switching off anyway: {why}")
            else:
                interrupt.tube = f"switching off anyway failed ({why})"
            return False
    if state is None:
        return False
    line = f"XOF sent anyway: X-rays off (confirmed by STS: {state.name})"
    if interrupt is not None:
        interrupt.tube = line
    else:
        say(f"{src.port}: {line}")
    return True


def _one_line(exc) -> str:
    """``exc``'s text on one line, for the operator."""
    return " ".join(str(exc).split()) or type(exc).__name__


# SIGTSTP (Ctrl-Z) too: its default suspends the process -- beam monitor and all -- with the tube
# on, and the guardian, whose pipe stays open, would not act
_SIGNALS = STOP_SIGNALS + tuple(getattr(signal, name) for name in ("SIGTSTP",) if hasattr(signal, name))


class StopSignal(Interrupted):
    """A signal asked the run to stop (SIGINT, SIGTERM, SIGHUP, SIGQUIT or SIGTSTP); ``signum`` says which.

    A ``KeyboardInterrupt`` (radiokit's :class:`~radiokit.interrupts.Interrupted`), so code that
    handles Ctrl-C handles them all alike, and ``radiokit demo`` exits 128 + ``signum`` on it."""


def _say(text: str) -> None:
    """Write to stderr from a signal handler: os.write, not print (print may be mid-call on the
    same buffered stream, and a closed terminal must not raise here)."""
    try:
        os.write(2, (text + "\n").encode("utf-8", "replace"))
    except OSError:
        pass


class SignalGuard:
    """SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGTSTP: the first raises :class:`StopSignal`; the rest are deferred.

    Ctrl-Z (SIGTSTP) stops the run like Ctrl-C instead of suspending it: a suspended process
    keeps the tube on and its beam monitor still.

    Use as a context manager around a run (handlers are installed only in the main thread, where
    Python delivers signals; elsewhere the guard does nothing). They are installed whatever the
    inherited disposition: a run started as a background job (``cmd &`` in a script) inherits
    SIGINT ignored, and a Ctrl-C sent to it must still stop the series with the tube off. Set :attr:`stopping` (or enter
    :meth:`cleanup`) before a switch-off sequence: from then on a signal only prints that the
    tube is being switched off. Once a signal has raised, the guard stays stopping, so the
    cleanup that follows it cannot be interrupted either. A stop lost in a finalizer is delivered
    again (:meth:`_unraisable`); one still on its way when the guard is left (or at
    :meth:`settle`) is raised there, before the switch-off only.

    Python runs a handler only when the main thread next executes bytecode, which may be a frame
    write or a C call later. Callbacks given to :meth:`on_signal` run at once instead, from a thread
    woken through :func:`signal.set_wakeup_fd` (the protocol uses this to stop routine beam polls,
    so that the switch-off is not queued behind them).

    Examples
    --------
    >>> import signal
    >>> with SignalGuard() as guard:
    ...     try:
    ...         signal.raise_signal(signal.SIGTERM)
    ...     except StopSignal as exc:
    ...         print(exc.name, guard.stopping)
    SIGTERM True
    """

    def __init__(self):
        self.stopping = False
        self._raised: int | None = None  # the signal of the stop this guard raised (raise_if_lost)
        self._old: dict[int, object] = {}
        self._depth = 0
        self._listeners: list = []
        self._wake = None  # (read fd, write fd, the previous wakeup fd, watcher thread)
        self._cleaning = False  # cleanup() entered: the switch-off owns the run
        self._old_hook = None  # sys.unraisablehook while the guard is installed
        self._redelivered: list = []  # stops lost in a finalizer, being delivered again
        self.left: dict[int, object] = {}  # the handlers replaced, once finish() records or ignores the signals
        # the first stop only acknowledged ("please wait"): a command whose switch-off it did not cut
        # short still says it was stopped (exit 128 + N, the tube confirmed off: `source probe`)
        self.acknowledged: int | None = None

    def __enter__(self) -> SignalGuard:
        self._depth += 1
        if self._depth == 1 and threading.current_thread() is threading.main_thread():
            for sig in _SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
            self._start_watch()
            self._old_hook, sys.unraisablehook = sys.unraisablehook, self._unraisable
        return self

    def __exit__(self, *exc_info) -> None:
        self._depth -= 1
        if self._depth == 0:
            # before the handlers go: a stop delivered again after them would reach the caller
            # after the run's own handling (its exit code and last line said), or not at all
            held = None
            try:
                held = self._held()
            finally:  # a delivery firing inside _held() raises there: the guard is still taken down
                self._stop_watch()
                for sig, old in self._old.items():
                    signal.signal(sig, old)
                self._old.clear()
                if self._old_hook is not None:
                    sys.unraisablehook, self._old_hook = self._old_hook, None
            raise_stop(held, exc_info[1])

    def settle(self) -> None:
        """Raise now a stop lost in a finalizer that is still on its way (:meth:`_unraisable`),
        unless the switch-off has begun. Call it before the run's outcome is decided (the tube
        left on, the last line said): leaving the guard raises it too, but only after those."""
        raise_stop(self._held())

    def _held(self) -> StopSignal | None:
        """The stop lost in a finalizer and not yet delivered again, its delivery cancelled."""
        pending = [delivery.signum for delivery in self._redelivered if delivery.cancel()]
        self._redelivered.clear()
        if not pending or self._cleaning:  # during the switch-off a stop is only acknowledged
            return None
        self.stopping, self._raised = True, pending[0]
        return StopSignal(pending[0])

    def raise_if_lost(self) -> None:
        """Raise again a stop this guard raised that never reached the run: the guard is
        stopping and the switch-off has not begun (:meth:`cleanup`). Only where no stop can be on
        its way up -- a point of the run's normal flow, whose stop path enters :meth:`cleanup`
        first thing (the series: at each phase, before the warm-up and each XON).

        Why: a stop that lands inside an import waits for its end, at most
        :data:`~radiokit.interrupts.IMPORT_WAIT_S`, and is then raised inside it, where a Cython
        module's bare ``except:`` may swallow it: the guard stayed stopping, the series went on
        to switch X-rays on, and every later Ctrl-C only said "please wait"."""
        if self.stopping and not self._cleaning and self._raised is not None:
            raise StopSignal(self._raised)

    def on_signal(self, callback) -> None:
        """Call ``callback()`` (no arguments, from the watcher thread) as soon as a guarded signal
        arrives, before the main thread's handler runs; again for every further signal. It must
        be quick, thread-safe and idempotent; what it raises is ignored. :meth:`forget` removes it."""
        self._listeners.append(callback)

    def forget(self, callback) -> None:
        if callback in self._listeners:
            self._listeners.remove(callback)

    def _start_watch(self) -> None:
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)  # set_wakeup_fd's requirement: the C handler never blocks
        try:
            # the only wakeup fd of the process is taken for the run and given back on exit
            previous = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        except ValueError:
            os.close(read_fd)
            os.close(write_fd)
            return
        watcher = threading.Thread(target=self._watch, args=(read_fd,), name="signal-watch", daemon=True)
        watcher.start()
        self._wake = (read_fd, write_fd, previous, watcher)

    def _stop_watch(self) -> None:
        if self._wake is None:
            return
        read_fd, write_fd, previous, watcher = self._wake
        self._wake = None
        signal.set_wakeup_fd(previous)
        os.close(write_fd)  # the watcher reads end-of-file and returns
        watcher.join(timeout=5.0)
        if not watcher.is_alive():
            os.close(read_fd)

    def _watch(self, read_fd: int) -> None:
        while True:
            try:
                data = os.read(read_fd, 64)
            except OSError:
                return
            if not data:
                return
            if not any(byte in _SIGNALS for byte in data):
                continue
            for callback in list(self._listeners):
                try:
                    callback()
                except Exception as exc:  # the main thread's handler still stops the run
                    _say(f"signal callback failed: {exc}")

    def reinstall(self) -> None:
        """Install the handlers again. C libraries may replace them behind Python's back (gmsh,
        building the virtual bench, resets SIGTERM to the default, which would kill the run
        with the tube on): the protocol calls this after building devices and at every phase."""
        if self._old and not self.left and threading.current_thread() is threading.main_thread():
            for sig in self._old:
                signal.signal(sig, self._handle)
            # gmsh also resets SIGPIPE to its default at the C level while Python still reports
            # it ignored: a write to the pipe of a guardian that died then killed this process
            # on the spot, without a word and with the tube on. Ignored again, the write fails
            # with EPIPE, and the run switches off or warns as for any lost link.
            if hasattr(signal, "SIGPIPE") and signal.getsignal(signal.SIGPIPE) == signal.SIG_IGN:
                signal.signal(signal.SIGPIPE, signal.SIG_IGN)

    def cleanup(self) -> SignalGuard:
        """Defer every signal from now on (returns self; usable as ``with guard.cleanup():``)."""
        self.stopping = self._cleaning = True
        return self

    def finish(self, record: bool = True) -> None:
        """The run's outcome is decided (the tube dealt with, the exit code chosen): from now on
        its signals are recorded, not acted on (``record``: :func:`~radiokit.interrupts.note_after_the_end`,
        which the command line turns into exit 128 + N in place of 0), or, without ``record``,
        ignored; either stays so when the guard is left. For a command line, whose last lines
        follow and whose process ends with them. A second call keeps what the first chose.

        Why: left as before, the guard gave the signals back to the command line's handler,
        which raises, and Python's own finalization sets a Python handler back to the default:
        a Ctrl-C in the 10-100 ms between a complete series' last line and the exit ended the
        process by SIGINT (exit -2), or said "interrupted; no partial output was left" under 8
        frames written (review s49). Nor a handler that says something: the tube's line stays the
        last, and "switching the X-ray tube off first, please wait" came after it. Recorded, not
        ignored, for a source command: ignored, a Ctrl-C in a probe's last 30-150 ms exited 0 and
        `probe && source on` switched X-rays on after it (review of s52). Ignored for a finished
        series (``record=False``): its summary line is said, and its exit 0 says the file is
        complete (tests/test_safety.py's storm). The console script sets the recorded ones to
        ignore for the interpreter's end (``radiokit.cli.script``). A caller that goes on in
        the same process puts back what it had (:attr:`left`: the handlers this guard replaced).
        A stop lost in a finalizer before it is still raised as the guard is left (:meth:`settle`)."""
        if not self._old or self.left:  # not installed (another thread): nothing to do; or finished
            return
        # the handlers the first call found (a second found only this guard's own, review s50rv2)
        self.left = dict(self._old)
        after = note_after_the_end if record else signal.SIG_IGN
        for sig in self._old:
            signal.signal(sig, after)
        self._old = dict.fromkeys(self._old, after)  # what __exit__ puts in place

    def _unraisable(self, unraisable) -> None:
        """Python drops an exception raised while a finalizer runs (h5py's weak references die
        during every frame write): a :class:`StopSignal` raised there was lost, and the guard,
        stopping already, only printed "please wait" at every later signal while the series
        went on. Before the switch-off has begun, the stop is delivered again to the main thread."""
        exc = unraisable.exc_value
        if isinstance(exc, StopSignal):
            if not self._cleaning:
                self.stopping = False  # the stop never reached the run: the next delivery raises
                self._redelivered.append(redeliver(exc))
            return  # during the switch-off a stop is only acknowledged, never raised again
        (self._old_hook or sys.__unraisablehook__)(unraisable)

    def _handle(self, signum, frame) -> None:
        if self.stopping:
            if self.acknowledged is None:
                self.acknowledged = signum
            _say(f"\n{signal.Signals(signum).name} received: switching the X-ray tube off first, please wait")
            return
        if after_import(signum, frame, self._redelivered):  # raised inside an import, a bare except swallowed it
            return
        self.stopping = True  # before raising: a second signal must not interrupt the cleanup
        self._raised = signum  # (past the import wait's cap, raised inside an import: raise_if_lost)
        raise StopSignal(signum)


# -- the client side --------------------------------------------------------------------------------


def start_guardian(
    url: str,
    config,
    *,
    notebook: str | Path | None = None,
    startup_timeout_s: float = 20.0,
    watchdog_s: float | None = None,
    armed: bool = False,
):
    """Start a guardian process on ``url`` and return the :class:`~acquisition.transport.PipeTransport`
    to talk through it.

    Parameters
    ----------
    url : str
        The controller's port, as :class:`~acquisition.transport.SerialTransport` opens it.
    config : SourceConfig
        The driver's configuration with the dialect, baud rate and command spacing resolved
        (:meth:`acquisition.l8121.L8121.resolved_config`, after any probe): the guardian opens the
        port at that rate and switches off in that dialect, with the same time-outs and attempts
        as the acquiring process, and never probes.
    notebook : path, optional
        The lab notebook (``<output>.log``) the guardian appends to when it has to act.
    watchdog_s : float, optional
        While X-rays may be on (from the start, an ``XON`` or ``WUP`` passed on, or an ``STS``
        reply that says so, and no ``STS`` reply since that says otherwise), the acquiring process polls the source
        every beam-monitor period; silent for this long, it is suspended or hung, and the
        guardian switches off (and says so). Armed by the acquiring process's first request:
        before it, its silence is a slow start, not a hang. None: no watchdog.
    armed : bool
        Arm the watchdog from the start, not at the first request: the caller knows the tube may
        be on now (its probe read it on, or nothing read it off) and sends its first request at
        once (``radiokit acquire``), so silence even before it is a process stopped (SIGSTOP, a
        debugger) with the tube on. A death in that window needs no watchdog: the pipe's end
        says it, armed or not.

    Raises
    ------
    PortUnavailable
        The guardian could not open the port (the message is the port's own): nothing was sent.
    DeviceError
        The guardian did not start.
    ValueError
        ``config`` leaves the dialect or the baud rate open.

    A stop signal (Ctrl-C) or an error while the guardian starts: the guardian launched switches
    off and exits before this raises (waited for, killed if it hangs), and the exception carries
    what it said (``guardian_off``, with ``tube_state`` or ``off_failed``): only one process holds
    the port at a time, and nothing the guardian says comes after the caller's last line.
    """
    from acquisition.errors import DeviceError
    from acquisition.transport import PipeTransport

    if (
        config.dialect not in ("A", "B")
        or config.baudrate is None
        or config.min_interval_s is None
        or config.timeout_s is None
    ):
        raise ValueError(
            f"{url}: the guardian needs a resolved configuration (dialect {config.dialect!r}, "
            f"baudrate {config.baudrate!r}, command spacing {config.min_interval_s!r}, reply time-out "
            f"{config.timeout_s!r}); pass driver.resolved_config()"
        )
    from acquisition.transport import hold_port

    # the port's lock before the guardian starts (PortBusy: another program holds it, nothing
    # sent), its descriptor inherited: one lock from this process's probe to the guardian's end
    hold = hold_port(str(url))
    cmd = [sys.executable, "-m", "acquisition.guardian", str(url), "--config", json.dumps(config.to_dict())]
    lock_fd = None if hold is None else hold.fd  # None: the node is gone (the guardian's open says so)
    if lock_fd is not None:
        cmd += ["--lock-fd", str(lock_fd)]
    if notebook is not None:
        cmd += ["--notebook", str(notebook)]
    if watchdog_s is not None:
        cmd += ["--watchdog", repr(float(watchdog_s))]
        if armed:
            cmd += ["--armed"]
    env = dict(os.environ)
    # the guardian imports acquisition from wherever this process did (a checkout, not only site-packages)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    # a stop signal is held until the guardian is in hand: raised inside Popen, after the fork, it
    # left a guardian nobody could stop or wait for (it switched off after the caller's last line)
    held = _Held()
    try:
        # its own session: the terminal's Ctrl-C (sent to the foreground process group) and its
        # hang-up do not reach it; stdin/stdout are the pipe, stderr the operator's terminal
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            start_new_session=True,
            close_fds=True,
            pass_fds=() if lock_fd is None else (lock_fd,),
        )
    except OSError as exc:
        held.release()
        if hold is not None:
            hold.release()
        raise DeviceError(f"{url}: cannot start the X-ray guardian process ({exc})") from exc
    except BaseException:
        held.release()
        if hold is not None:
            hold.release()
        raise
    link = PipeTransport(
        url, proc, timeout_s=config.timeout_s, baudrate=config.baudrate, min_interval_s=config.min_interval_s, hold=hold
    )
    try:
        held.release()  # a signal held meanwhile raises here
        link.wait_ready(startup_timeout_s)
    except BaseException as exc:
        # Ctrl-C while it starts (or a start that failed): the guardian launched must not live on
        # beside the caller's own switch-off on the same port, nor speak after its last line
        _end_start(link, config, exc, startup_timeout_s, armed=armed)
        raise
    return link


class _Held:
    """The stop signals recorded, not acted on, from now until :meth:`release`, which puts the
    handlers back and delivers the first one held through them (their own rules: the guard's
    raises, or defers once stopping). Python's handlers, in the main thread only (where they run):
    a mask (``pthread_sigmask``) holds a signal only from the thread that sets it, and a process's
    signal goes to any thread that does not (the guard's watcher)."""

    def __init__(self):
        self.held: list[int] = []
        self.old = {}
        if threading.current_thread() is threading.main_thread():
            # a handler installed outside Python (getsignal None) could not be put back: not held
            self.old = {sig: signal.signal(sig, self._record) for sig in _SIGNALS if signal.getsignal(sig) is not None}

    def _record(self, signum, frame) -> None:
        self.held.append(signum)

    def release(self) -> None:
        old, self.old = self.old, {}
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if old and self.held:
            signal.raise_signal(self.held[0])


def _end_start(link, config, exc: BaseException, startup_timeout_s: float, *, armed: bool = True) -> None:
    """Have the guardian whose start ``exc`` cut short switch off and exit, waited for; what it
    said goes on ``exc`` as a connect's outcome does (README's one rule): ``tube_state`` (the
    state its STS confirmed), or ``off_failed`` -- or, when it ended without a word on a tube that
    may be on (it held the port, or the caller had not found the tube off: ``armed``),
    ``guardian_gone``: the caller switches off through the port, now free, if it can."""
    from acquisition.errors import DeviceError, NoReply
    from acquisition.l8121 import SourceState

    bound = _end_start_bound_s(config, startup_timeout_s)
    if isinstance(exc, NoReply):  # a guardian silent past its start's time: the wait may be long
        _say(f"{link.port}: waiting up to {bound:.0f} s for the X-ray guardian to switch off and exit")
    # stops held off for the wait: a Ctrl-C there (the likeliest moment, after a silent failed
    # start) escaped it, and the guardian, neither waited for nor killed, held the port while the
    # caller's own switch-off opened it (review s32-r3); the start's end is what a stop asks for
    said = None
    try:
        with deferred(*_SIGNALS):
            said = link.end_start(bound)
    except Interrupted:  # held during the wait, raised after it: what it asks for is done
        pass
    if said is None:
        # it held the port (READY) or hung and was killed, perhaps in its switch-off, without a word
        # on the tube: the port is free again, and the caller switches off through it, or warns
        # (review s33-r2; recording that as a failed switch-off stopped the caller's, s33-r4)
        # (killed or crashed before READY -- the OOM killer -- it sent nothing, but a tube left
        # on before (other software, a crash) is still on: the caller's to switch off, review s34-r2)
        exc.guardian_gone, exc.guardian_sent = link.may_have_sent or armed, link.may_have_sent
        _advise(
            exc,
            "; if the last line does not confirm the tube off, switch it off at the controller "
            "before running the command again"
            if exc.guardian_gone
            else "; run the command again",
        )
        return
    code, _, text = said.partition(" ")
    exc.guardian_off = True  # the guardian's switch-off, not the caller's
    if code == "0" and text in SourceState.__members__:
        exc.tube_state = SourceState[text]
        _advise(exc, "; run the command again")
    else:
        exc.off_failed = DeviceError(f"{link.port}: the X-ray guardian's switch-off: {text or said}")
        _advise(exc, "; switch the source off at the controller before running the command again")


def _end_start_bound_s(config, startup_timeout_s: float) -> float:
    """How long a guardian whose start failed may take to switch off and exit before it is
    killed: its start again, then one ``off()`` at its longest on a link that stays up -- each
    attempt's ``XOF`` and last ``STS`` and B's closing ``SRL``, each exchange at its longest
    (:func:`~acquisition.transport.exchange_longest_s`: a late reply's wait, the spacing, the reply
    time-out), the confirmation window and the pauses between attempts -- and 2 s for a loaded
    machine. Not the worst case: a link lost in the switch-off (its reopening, the identity check,
    the exchange again) is not counted, and may get a guardian killed that was still working; the
    port is then free and the caller switches off through it itself (``guardian_gone``), confirmed
    by STS or the warning. (Each exchange counted as the pipe's wait -- two time-outs, a reconnect,
    slack: 8 s at 2 s -- a hung guardian was killed only after 52 s for a 1 s start.)

    Why not each exchange's worst by all its time-outs (:func:`~acquisition.transport.close_wait_s`,
    review s53rvclose): the reply wait of an exchange a signal cut short never comes here (the
    guardian's stop handlers, :func:`main`, never raise: no exchange of its is interrupted); and
    its write waits (an earlier command's unsent bytes, the write, the drain: three write
    time-outs, 3 s by default) come only on a port whose output does not drain, through which the
    guardian's XOF cannot reach the controller either: killed, it frees the port for the caller's
    own switch-off, which meets the same port and ends on the warning. Counted, they added 7 s at
    the dialects' 2 s reply time-out (17.5 s at 0.5 s: the write waits, not the reply, dominate)
    to the wait before a HUNG guardian is killed and the caller switches off itself -- the case
    this bound is for, the tube perhaps on all the while. One exchange that stalls for a moment
    fits in the exchanges a confirmed switch-off does not use."""
    from acquisition.transport import exchange_longest_s

    exchanges = 2 * config.off_attempts + 1
    per_exchange = exchange_longest_s(config.timeout_s, config.min_interval_s)
    pauses = config.off_attempts * config.poll_s
    return startup_timeout_s + exchanges * per_exchange + config.off_confirm_s + pauses + 2.0


def _advise(exc: BaseException, advice: str) -> None:
    """End a slow start's error (the start time-out, :class:`~acquisition.errors.NoReply`) with
    what to do, known only now: "run the command again" said before the X-RAYS MAY STILL BE ON
    warning told the operator to switch on again a tube that may be on."""
    from acquisition.errors import NoReply

    if isinstance(exc, NoReply) and exc.args and isinstance(exc.args[0], str):
        exc.args = (exc.args[0] + advice, *exc.args[1:])


# -- the guardian process ---------------------------------------------------------------------------


class _Notebook:
    """stderr and the lab notebook, best effort (a closed terminal must not stop the guardian)."""

    def __init__(self, path):
        self.path = path

    def __call__(self, level: str, text: str) -> None:
        if level in ("WARNING", "ERROR", "CRITICAL"):
            _say(f"X-ray guardian: {text}")
        self.record(level, text)

    def record(self, level: str, text: str) -> None:
        """The notebook only (a line the operator's terminal has had already)."""
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        if self.path:
            try:
                with open(self.path, "a", encoding="utf-8") as fh:
                    fh.write(f"{stamp} acquisition.guardian {level} {text}\n")
            except OSError:
                pass


def _switch_off(link, config, note, watch: _Watch, failure_note=None) -> str:
    """The acquiring process is gone: the driver's ``off()`` on the port this process holds, in the
    dialect the acquiring process resolved (``config``; no probe, no identity check: only what
    switching off needs). Returns ``"off"`` (``STS`` confirmed it), ``"unverified"`` (confirmed by
    the unit now at the port after the link was reopened while X-rays may have been on: the
    operator has been told) or ``"failed"``. ``watch``: what the exchanges passed on showed (X-rays
    may be on; the link reopened while they may have been). ``failure_note``: where a failure is
    said instead of ``note`` (a watchdog's retry: the notebook only)."""
    from acquisition.errors import DeviceError
    from acquisition.l8121 import L8121

    failed = failure_note or note

    driver = L8121(link, config=config, connect=False)
    driver.attach(link)
    # what the passed-on exchanges showed: X-rays may be on, so that a reconnect during this off
    # (the link's on_reconnect counts it) leaves the confirmation the unit's now at the port; and a
    # reconnect already passed on while they may have been on (reviews s28-h6, s28-h7: a fresh
    # driver thought the tube off, so either reconnect went unflagged and the off was "confirmed")
    driver._may_be_on = watch.may_be_on or watch.unverified
    # the watch's may_be_on starts unknown-means-on and ends only at an STS read through here: it
    # stands for the fresh driver's own "no state read yet" (X-rays read off stay off: s28-h7)
    driver._state_unread = False
    driver.unit_unverified = watch.unverified
    try:
        state = driver.off()
    except DeviceError as exc:
        failed("CRITICAL", str(exc) if str(exc).startswith(link.port) else f"{link.port}: {exc}")
        return "failed"
    if state.emitting:  # never the case after off() returns; kept as the one rule (AGING emits)
        failed("CRITICAL", f"{link.port}: XOF sent, but the controller reports {state.name}")
        return "failed"
    if driver.unit_unverified:  # reopened during this switch-off: the unit now at the port confirmed it
        note("CRITICAL", driver.unverified_warning(state))
        return "unverified"
    note("WARNING", f"{link.port}: X-rays off (confirmed by STS: {state.name})")
    watch.off_state = state.name
    return "off"


class _Watch:
    """What the guardian knows of the tube from the exchanges it passes on: X-rays may be on from
    the start (nothing read yet), an ``XON`` (or A's ``WUP``) sent, or an ``STS`` reply that says
    the tube emits, until an ``STS`` reply says it does not."""

    def __init__(self, config):
        from acquisition.l8121 import DIALECTS

        dialect = DIALECTS[config.dialect]
        self.state_query = dialect.readings["state"]
        # unknown until an STS read through here says off: a tube left on by an earlier run (``source
        # on``) may be on, and a reconnect before that read must be flagged (review s28-h8: it
        # started False, and the guardian's off, confirmed by a second unit, read "confirmed")
        self.may_be_on = True
        self.warned = False  # the watchdog's unconfirmed switch-off has been told to the operator
        # when the acquiring process fell silent with X-rays possibly on (the watchdog's first try
        # less watchdog_s), and the tries since: a retry's reminder says how long they may have been on
        self.silent_since: float | None = None
        self.retries = 0
        self.reidentify = None  # the link's on_reconnect (acquisition.l8121.Reidentify), if any
        # the link was reopened while X-rays may have been on: an STS that reads off afterwards is
        # the unit's now behind the port (the L8121 names only its model), told to the operator
        self.unverified = False
        # what XON (and A's WUP) emits at, sent while X-rays are off (L8121.md): the preset voltage
        # and current -- B's PHV and PCU, A's HIV and CUR -- by their command words, each with the
        # check's count when last accepted (refusal: both are needed since the last reconnect; a
        # focus setting is not enough). B's HIV and CUR set the beam while it is on: echoed after
        # a reconnect they say nothing of the presets an XON would emit at (review s29-h7)
        self.beam_settings = {what: {dialect.settings["preset_" + what].command} for what in ("voltage", "current")}
        self.settings_at: dict[str, int] = {}
        # reconnects of the guardian's own switch-offs (the watchdog's), not yet told to the
        # acquiring process: they go out with its next reply's C line (review s29-h4)
        self.untold = 0
        # the watchdog is armed only once the acquiring process has sent a request: its silence
        # before it ever spoke is a slow start (a Python-API user building its detector), not a
        # hang, and an XOF then went to a unit nobody had checked (review s29-h4)
        self.heard = False
        self.off_state = ""  # what the STS that confirmed this guardian's last switch-off read
        # the watchdog's confirmed switch-off, not yet told to the acquiring process: it goes out
        # with its next reply's W line, so that its error names the guardian, not a dropped beam
        self.watchdog_untold = ""
        # an XON (or WUP) sent, no XOF since, and the state not yet read on: the driver lets STS
        # read standby for xon_start_s after XON's echo (L8121.md ties no state to it), so a
        # standby then is a beam that may still come on, not "off" -- taken as off, it disarmed the
        # watchdog while the acquiring process waited (review s44rr2)
        self.starting = False

    def exchanged(self, seen: int, may_have_been_on: bool, note, port: str) -> None:
        """After an exchange: was the link reopened (``seen``: the check's count before) while X-rays
        may have been on? Then the next off confirmation is said loudly to be the unit's now at the port."""
        if getattr(self.reidentify, "reconnects", seen) != seen and (may_have_been_on or self.may_be_on):
            self.unverified = True
        if self.unverified and not self.may_be_on:
            self.unverified = False
            note(
                "CRITICAL",
                f"{port}: the link was lost and reopened while X-rays may have been on: the STS that reads "
                "off is the unit's now at the port, which the L8121 identifies only by its model (no serial "
                "number); if the adapter was re-plugged or the path moved, check by hand that the unit first "
                "connected is off",
            )

    def to_tell(self, seen: int) -> int:
        """The reconnects the acquiring process has not heard of (its next reply's ``C`` line):
        those since ``seen`` (the check's count before the exchange passed on), and those of the
        guardian's own switch-offs since the last reply."""
        moved = getattr(self.reidentify, "reconnects", seen) - seen + self.untold
        self.untold = 0
        return moved

    def sent(self, command: str) -> None:
        head = command.split(" ", 1)[0]
        if head in ("XON", "WUP"):
            self.may_be_on = self.starting = True
        elif head == "XOF":
            self.starting = False

    def refusal(self, command: str, port: str) -> str | None:
        """Why ``command`` (XON or WUP) is not passed on, or None: the link was reopened and the
        voltage and current have not both been passed on since, so the unit now at the port passed
        a check of its model only and may not hold them (the driver's own on()/warm_up() rule, which
        cannot see this process's reconnects; reviews s28-h7, s28-h8). The settings are recorded
        as the unit accepts them (:meth:`replied`)."""
        head, count = command.split(" ", 1)[0], getattr(self.reidentify, "reconnects", 0)
        if head in ("XON", "WUP"):
            if count and any(self.settings_at.get(what) != count for what in self.beam_settings):
                return (
                    f"{port}: {head} not sent: the link was lost and reopened after the settings were "
                    "sent (voltage and current not both sent since), and the unit now at the port is "
                    "known only by its model; switch on again"
                )
        return None

    def replied(self, command: str, reply: str) -> None:
        from acquisition.l8121 import Command

        head = command.split(" ", 1)[0]
        if head == "XOF":  # (as sent(): a standby read after it confirms the switch-off)
            self.starting = False
        for what, words in self.beam_settings.items():
            # the count as the unit echoed it (it holds the value): one it refused (ERROR; B's HIV
            # while off, without the PHV preset) set nothing, and counted, let XON through after a
            # reconnect (review s29-h4)
            if head in words and Command.is_echo(command, reply):
                self.settings_at[what] = getattr(self.reidentify, "reconnects", 0)

        check = self.reidentify
        if check is not None and check.name == "identity" and command == check.query.command:
            try:  # the model the acquiring process's connect read: what a reconnect must find
                check.identity = check.query.parse(reply)
            except ValueError:
                pass

        if command == self.state_query.command:
            try:
                state = self.state_query.parse(reply)
            except ValueError:  # not a state: it says nothing either way
                return
            if state.emitting:
                self.may_be_on, self.starting = True, False
            elif state.confirms_off and not self.starting:
                self.may_be_on = False
            # else B's ERROR (read as pre-heating, and also what a refused query looks like): the
            # driver never takes it as "off", so neither does the watchdog -- it stays as it was


def _read_request(rfd: int, watch: _Watch, watchdog_s: float | None) -> bytes | None:
    """The next bytes from the acquiring process (b"" when its end closed), or None when, with
    X-rays possibly on, it has sent nothing for ``watchdog_s``: it is suspended (SIGSTOP, a
    debugger) or hung, and its beam monitor no longer watches the tube."""
    import select

    while True:
        wait = watchdog_s if watch.may_be_on and watch.heard and watchdog_s else None
        try:
            ready, _, _ = select.select([rfd], [], [], wait)
        except InterruptedError:
            continue
        except OSError:
            return b""
        if not ready:
            return None
        try:
            return os.read(rfd, 4096)
        except OSError:
            return b""


def _watchdog_off(link, config, note, watch: _Watch, watchdog_s: float) -> bool:
    """Switch off for the silent acquiring process; returns whether this guardian must end on the
    warning (exit 3). A retry after a try that could not confirm is said in one short line on the
    terminal (the first try's lines went there; the notebook keeps every line): a stuck relay
    retried every watchdog_s filled the operator's terminal with the same WARNING and CRITICAL."""
    retry = watch.warned
    said = getattr(note, "record", note) if retry else note
    if watch.silent_since is None:
        watch.silent_since = time.monotonic() - watchdog_s
    said(
        "WARNING",
        f"{link.port}: the acquiring process has sent nothing for {watchdog_s:g} s with X-rays possibly on "
        f"(suspended or hung): switching X-rays off; the series or warm-up stops when it next reads the source",
    )
    before = getattr(watch.reidentify, "reconnects", 0)
    outcome = _switch_off(link, config, note, watch, said)
    moved = getattr(watch.reidentify, "reconnects", 0) - before
    if moved:
        # reopened during this off, X-rays possibly on (the watchdog runs only then): a try that
        # failed lost the fresh driver's record of it, and the next try -- another fresh driver --
        # called the unit now at the port's STS confirmed, as did the acquiring process's own off
        # later, with the first unit on (review s29-h4). Kept here, and told with the next reply
        watch.unverified = True
        watch.untold += moved
    if outcome == "off":
        watch.may_be_on, watch.warned, watch.silent_since, watch.retries = False, False, None, 0
        watch.starting = False  # (its XOF did not pass through sent())
        watch.watchdog_untold = (
            f"the X-ray guardian's watchdog switched X-rays off (confirmed by STS: {watch.off_state}): the "
            f"acquiring process had sent nothing for {watchdog_s:g} s with X-rays on (suspended or hung)"
        )
        return False
    if outcome == "unverified":
        # the unit now at the port is off; the one switched on may not be, and no XOF through this
        # port reaches it: tried again every watchdog_s, the same warning came for ever (review
        # s28-h8: 5 XOFs, 10 CRITICAL lines in 3 s), or a fresh driver called its next try
        # confirmed. Told once, the guardian ends on the warning; the acquiring process, if it runs
        # again, finds it gone and switches off through the port itself, warned as well
        # (PipeTransport counts that open as a reconnect after an exit 3)
        note(
            "CRITICAL",
            f"{link.port}: the X-ray guardian ends here; the acquiring process, if it runs again, "
            "switches off through the port itself",
        )
        _say(TUBE_WARNING)
        return True
    # not confirmed: the watchdog stays armed and tries again after every further watchdog_s of
    # silence (a controller silent for a second or two at the first attempt must not leave the
    # tube on for good); the operator's warning is printed once, then a reminder per retry
    if not watch.warned:
        _say(TUBE_WARNING)
        watch.warned = True
    else:
        watch.retries += 1
        _say(
            f"X-ray guardian: {link.port}: X-rays still not confirmed off (retry {watch.retries}, every "
            f"{watchdog_s:g} s); they may have been on for {time.monotonic() - watch.silent_since:.0f} s: "
            "switch off at the controller"
        )
    return False


def _admit(link, watch: _Watch, command: str) -> None:
    """Raise DeviceError when ``command`` is refused (:meth:`_Watch.refusal`), judged as of the
    moment it is written: an XON or WUP on a link left closed (a reopen that failed) reopens it
    first, so that the reconnect is counted before the refusal -- inside XON's own exchange it came
    after, and XON reached a second unit of the model (review s28-h8). On an open link the query
    writes at once, and a link lost during XON is never reopened for it (``not_resent``)."""
    from acquisition.errors import DeviceError

    if command.split(" ", 1)[0] in ("XON", "WUP") and not link.is_open:
        link.open()  # its check's refusal or a lost link: a DeviceError, the link left closed
    refused = watch.refusal(command, link.port)
    if refused:
        raise DeviceError(refused)
    watch.sent(command)


def _orphaned(link, config, note, watch: _Watch, why: str = "ended without releasing the port", tell=None) -> int:
    """The acquiring process is gone (or gives up the start, ``tell``: its pipe, which gets the
    outcome's ``O`` line): switch off, close the port, and return the exit status (0: confirmed
    off; 3: not, the operator warned)."""
    note("WARNING", f"{link.port}: the acquiring process {why}; switching X-rays off")
    ok = _switch_off(link, config, note, watch) == "off"
    link.close()
    if not ok:
        _say(TUBE_WARNING)
    if tell is not None:
        try:
            os.write(tell, (f"O 0 {watch.off_state}\n" if ok else "O 3 X-rays not confirmed off\n").encode())
        except OSError:
            pass  # it died meanwhile: the exit status is all there is
    return 0 if ok else 3


def _serve(link, config, note, watchdog_s: float | None = None, armed: bool = False) -> int:
    """Answer the acquiring process until it releases the port (0) or disappears (switch off);
    with ``watchdog_s``, switch off when it falls silent for that long while X-rays may be on
    (from its first request, or from the start when ``armed``)."""
    from acquisition.errors import DeviceError, NoReply

    rfd, wfd = sys.stdin.fileno(), sys.stdout.fileno()
    buf = b""
    watch = _Watch(config)
    watch.reidentify = getattr(link, "on_reconnect", None)
    watch.heard = armed
    while True:
        while b"\n" not in buf:
            data = _read_request(rfd, watch, watchdog_s)
            if data is None:
                if _watchdog_off(link, config, note, watch, watchdog_s):
                    link.close()
                    return 3
                continue
            if not data:  # the pipe closed without a release: the acquiring process is gone
                return _orphaned(link, config, note, watch)
            buf += data
        line, buf = buf.split(b"\n", 1)
        words = line.decode("ascii", "replace").split(" ", 2)
        if words[0] == "X":
            link.close()
            note("INFO", f"{link.port}: released by the acquiring process")
            return 0
        if words[0] == "O":  # its start was cut short (Ctrl-C): it waits to hear how the tube was left
            return _orphaned(
                link, config, note, watch, "gave up on the X-ray guardian's start (stopped, or it was slow)", tell=wfd
            )
        if words[0] != "Q" or len(words) < 3:
            continue
        seq, command = words[1], words[2]
        watch.heard = True
        was_on, seen = watch.may_be_on, getattr(watch.reidentify, "reconnects", 0)
        try:
            _admit(link, watch, command)
            reply = link.query(command)
            watch.replied(command, reply)
            out = f"R {seq} {reply}"
        except (DeviceError, ValueError) as exc:
            kind = "N" if isinstance(exc, NoReply) else "E"  # silence: the caller does not ask again
            out = f"{kind} {seq} {' '.join(str(exc).split())}"
        watch.exchanged(seen, was_on, note, link.port)
        moved = watch.to_tell(seen)
        if moved:
            # the acquiring driver counts reconnects to tell whose off confirmation it has and to
            # send no XON after one since its settings: it learns of this link's before the reply
            # (review s28-h8: an STS reading off cleared the guardian's warning and the driver's
            # off then read confirmed)
            out = f"C {seq} {moved}\n{out}"
        if watch.watchdog_untold:
            out, watch.watchdog_untold = f"W {seq} {watch.watchdog_untold}\n{out}", ""
        try:
            os.write(wfd, (out + "\n").encode("utf-8", "replace"))  # a reply may hold "µA"
        except OSError:
            pass  # the reader is gone: the next read sees the end of the pipe


def main(argv: list[str] | None = None) -> int:
    """``python -m acquisition.guardian URL --config JSON [--notebook PATH]`` (JSON: a resolved
    ``SourceConfig``, see :func:`start_guardian`)."""
    import argparse

    from acquisition.errors import DeviceError
    from acquisition.transport import SerialTransport, _write_no_sigpipe

    for sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)

    stoppers = [s for s in STOP_SIGNALS if s not in (signal.SIGINT, signal.SIGHUP)]

    def terminated(signum, frame):  # someone stops the guardian itself: behave as if orphaned
        # once: a second stop closed fd 0 again, an EBADF raised inside the switch-off the first
        # began (read as a lost link: reconnected, unverified, the warning; review s33-r4), or the
        # close of whatever reused fd 0 since
        for sig in stoppers:
            signal.signal(sig, signal.SIG_IGN)
        os.close(0)

    # SIGQUIT's default (a core dump) ended it as kill -9 does, with no switch-off of its own
    for sig in stoppers:
        signal.signal(sig, terminated)
    ap = argparse.ArgumentParser(prog="python -m acquisition.guardian")
    ap.add_argument("url")
    ap.add_argument("--config", required=True)
    ap.add_argument("--notebook")
    ap.add_argument("--watchdog", type=float, help="switch off after this many seconds of silence with X-rays on")
    ap.add_argument("--armed", action="store_true", help="the watchdog armed from the start, not at the first request")
    ap.add_argument("--lock-fd", type=int, help="the port's exclusive lock, inherited from the acquiring process")
    args = ap.parse_args(argv)
    if args.lock_fd is not None:
        from acquisition.transport import adopt_hold

        # the acquiring process's lock is this process's too: its links open the port without
        # taking another (which the inherited one would refuse), and it holds after that one dies
        adopt_hold(args.url, args.lock_fd)
    from acquisition.l8121 import SourceConfig

    config = SourceConfig.from_dict(json.loads(args.config))
    note = _Notebook(args.notebook)
    import logging

    # the driver's own log goes to the notebook only: the guardian speaks to the operator via note()
    root = logging.getLogger()
    root.addHandler(logging.NullHandler())
    if args.notebook:
        try:
            fh = logging.FileHandler(args.notebook, encoding="utf-8")
        except OSError:
            fh = None
        if fh is not None:
            fh.setFormatter(logging.Formatter("%(asctime)s guardian %(name)s %(levelname)s %(message)s"))
            logging.getLogger("acquisition.l8121").addHandler(fh)
            logging.getLogger("acquisition.l8121").setLevel(logging.INFO)
    try:
        link = SerialTransport(
            args.url, baudrate=config.baudrate, timeout_s=config.timeout_s, min_interval_s=config.min_interval_s
        )
    except (DeviceError, ValueError) as exc:
        os.write(1, f"E 0 {' '.join(str(exc).split())}\n".encode("ascii", "replace"))
        return 1
    from acquisition.l8121 import DIALECTS, Reidentify

    # the acquiring process's exchanges come through here: a late reply after a time-out is told
    # from the next command's by the dialect's reply grammar, as on the driver's own link
    link.reply_fits = DIALECTS[config.dialect].reply_fits
    link.late_barriers = DIALECTS[config.dialect].late_barriers
    # and a reconnect asks the controller who it is before its replies are passed on or its STS
    # confirms a switch-off (the model: configured, then what the connect's TYP read through here)
    link.on_reconnect = Reidentify(DIALECTS[config.dialect], config.model, args.url)
    try:
        _write_no_sigpipe(1, b"READY\n")
    except OSError:
        # the acquiring process died while this one started (kill -9 before READY): nobody reads
        # the pipe or will release the port, and the tube may be on (left on by an earlier run; a
        # run's probe may have read it so). The write's BrokenPipeError once ended this process
        # with a traceback and no XOF, the tube left on and nobody told
        watch = _Watch(config)
        watch.reidentify = link.on_reconnect
        return _orphaned(link, config, note, watch, "ended before the X-ray guardian was ready")
    return _serve(link, config, note, args.watchdog, args.armed)


if __name__ == "__main__":
    sys.exit(main())
