"""Stop signals as exceptions that say which signal, the exit status they give, and a stop Python
dropped in a finalizer delivered again.

Every command unwinds on Ctrl-C, SIGTERM, SIGHUP and Ctrl-\\ (SIGQUIT) as on Ctrl-C
(:data:`STOP_SIGNALS`: its outputs are removed, not left half-written) and exits as a shell reports
a command a signal ended: 128 + the signal's number (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP, 131
SIGQUIT). ``acquisition.guardian.StopSignal`` is an
:class:`Interrupted` too.

Python drops an exception raised while a finalizer runs ("Exception ignored in: ...": h5py's
object registry is a ``WeakValueDictionary`` whose weak-reference callbacks run during every
dataset write), and a signal's handler runs wherever the main thread is: a Ctrl-C landing there
was lost, and the command went on to its end. :func:`redeliver` raises it again, a moment later.
A stop that lands while a module is being imported waits for the import's end
(:func:`after_import`): raised inside it, a library's bare ``except:`` swallowed it.
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import functools
import signal
import sys
import threading
import time
from collections.abc import Callable

__all__ = [
    "STOP_SIGNALS",
    "Interrupted",
    "exit_status",
    "redeliver",
    "after_import",
    "raise_stop",
    "lost_stops_redelivered",
    "settle",
    "deferred",
    "held",
    "die_with_parent",
    "note_after_the_end",
    "stop_after_the_end",
    "stops_after_the_end",
    "forget_stops_after_the_end",
]

#: The signals every command stops on as on Ctrl-C. SIGQUIT (Ctrl-\) too: the terminal sends it to
#: the foreground group as it sends Ctrl-C, and its default action (a core dump) ended ``acquire
#: source on`` in its ramp as ``kill -9`` does, X-rays left on, and other commands without their
#: clean-up. A stop the process can handle is handled; a core dump is kill -9's business.
STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, name)
)

#: How long after the drop a lost stop is raised again: long enough for the finalizer (and the
#: hook) to have returned, where it would be dropped again, and short beside a person's patience.
REDELIVER_AFTER_S = 0.05

#: How often a stop that landed inside an import looks again whether the import is done, and how
#: long it waits at most before it is raised inside it all the same (an import that hangs must
#: not keep a command from stopping). Imports take milliseconds to a second (matplotlib's first).
IMPORT_POLL_S = 0.01
IMPORT_WAIT_S = 5.0


class Interrupted(KeyboardInterrupt):
    """A signal asked the command to stop; ``signum`` says which.

    A ``KeyboardInterrupt``, so code that handles Ctrl-C handles them all alike."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def signal_number(exc: BaseException) -> int:
    """The signal behind an interrupt: its ``signum``, else the signal its message names (a
    ``KeyboardInterrupt("SIGTERM")`` raised after a deferred signal), else SIGINT (Python's own
    Ctrl-C, or one a library raised)."""
    signum = getattr(exc, "signum", None)
    if signum is not None:
        return int(signum)
    name = str(exc.args[0]) if exc.args else ""
    try:
        return int(signal.Signals[name]) if name.startswith("SIG") else int(signal.SIGINT)
    except KeyError:
        return int(signal.SIGINT)


def exit_status(exc: BaseException) -> int:
    """128 + the number of the signal that stopped the command (see :func:`signal_number`)."""
    return 128 + signal_number(exc)


class _Redelivery:
    """A stop raised again from a timer thread, unless cancelled first."""

    def __init__(self, signum: int, after_s: float | None = None):
        self.signum = signum
        self._handler = _kernel_handler(signum)  # Python's: its handler raised the stop just now
        self._lock = threading.Lock()
        self._done = False  # fired or cancelled
        self.fired_at: float | None = None  # when it was delivered (monotonic s)
        self._timer = threading.Timer(REDELIVER_AFTER_S if after_s is None else after_s, self._fire)
        self._timer.daemon = True  # dies with the process
        self._timer.start()

    def _fire(self) -> None:
        with self._lock:  # held while it sends: cancel() then knows the stop is on its way
            if not self._done:
                self._done = _deliver(self.signum, self._handler)
                if self._done:
                    self.fired_at = time.monotonic()

    def waiting(self) -> bool:
        """Neither delivered nor cancelled, and its timer still to run. Read without the lock: a
        signal handler asks, and a second handler that ran inside the first (at ``is_alive``'s
        first bytecode) would wait for it forever. Read as ``_fire`` sends, it says waiting,
        and the delivery that follows is handled as the wait's own."""
        return not self._done and self._timer.is_alive()

    def cancel(self) -> bool:
        """Keep it from firing; True if it had not fired, or could not be delivered (the stop is
        then the caller's to raise)."""
        with self._lock:
            pending, self._done = not self._done, True
            return pending


def _deliver(signum: int, handler: int | None) -> bool:
    """Deliver ``signum`` to the main thread, where its Python handler runs; False (nothing
    delivered) unless the process handles it in Python now. ``handler``: the kernel's handler
    for it when the stop was lost (Python's, which had just raised it).

    A real signal where the kernel still runs that handler, not only Python's flag
    (``_thread.interrupt_main``): a wait in C (``Event.wait``, ``as_completed``, a Dask cluster's
    ``done.wait()``) is cut short by the one and left to its end by the other (2.00 s late for a
    2 s wait). But a real signal runs the kernel's handler: the default (SIGTERM's and SIGHUP's
    kill the process, SIGTSTP's suspends it) or ignore, where Python's is that, or where a C
    library reset it behind Python's back (gmsh resets SIGTERM: ``SignalGuard.reinstall``). So
    the kernel's is read first; another than Python's, the flag alone; Python's the default or
    ignore, nothing, and the stop waits for its block's end. Left: a handler changed between
    that reading and the delivery, a few microseconds, which a signal from outside meets too."""
    if not callable(signal.getsignal(signum)):
        return False
    now = _kernel_handler(signum)
    if hasattr(signal, "pthread_kill") and now is not None and now == handler:
        signal.pthread_kill(threading.main_thread().ident, signum)
    else:
        _thread.interrupt_main(signum)
    return True


def _kernel_handler(signum: int) -> int | None:
    """The address of the handler the kernel runs for ``signum``; None where it is the default
    action or ignore, or cannot be asked."""
    try:
        action = ctypes.create_string_buffer(1024)  # struct sigaction, its handler first (Linux, macOS)
        if _libc().sigaction(int(signum), None, action) != 0:
            return None
    except (OSError, AttributeError):  # no sigaction to ask
        return None
    address = ctypes.c_void_p.from_buffer(action).value or 0
    return None if address in (int(signal.SIG_DFL), int(signal.SIG_IGN)) else address


@functools.cache
def _libc():
    return ctypes.CDLL(None)


def redeliver(exc: BaseException) -> _Redelivery | None:
    """Raise the stop ``exc`` again in the main thread, from a timer thread after
    :data:`REDELIVER_AFTER_S` (here, still inside the finalizer or the hook, it would be dropped
    again; should it land in another finalizer, this repeats). It runs the handler of its signal
    as the process has it then: a block that defers signals notes it. Returns the pending
    delivery (None if ``exc`` is not a stop): its owner cancels it when its block ends, and
    raises the stop if it was not delivered (too late, or its signal not handled in Python)."""
    if not isinstance(exc, KeyboardInterrupt):
        return None
    return _Redelivery(signal_number(exc))


#: the stop waiting for an import's end, if one is: when it came (monotonic s), and its delivery
_IMPORT_WAIT: dict[str, tuple[float, _Redelivery]] = {}


def after_import(signum: int, frame, pending: list | None = None) -> bool:
    """In a stop signal's handler: True if the signal landed inside an import, and is delivered
    again in :data:`IMPORT_POLL_S` (the handler then returns without raising); False if the
    handler should act on it now.

    Why: raised inside an import, a stop went to whatever the imported module's body was running,
    and Cython-built modules run theirs inside a bare ``except:`` (their memoryview's
    ``Sequence.register``): `radiokit demo`, interrupted as it first imported numpy.random, ran
    to its end and exited 0; under the acquisition's guard the stop was lost the same way, the
    guard stopping already, and the series went on. Inside a string ``exec`` (scipy's array-API
    modules build themselves so) a ``KeyboardInterrupt`` also made ``python -m`` end by SIGINT
    after the command's own handling. After :data:`IMPORT_WAIT_S` the stop is acted on anyway.

    One stop waits at a time: another that comes meanwhile (Ctrl-C, then ``kill``) joins it; each
    waiting on its own, the second was raised a poll after the first, into the command's
    clean-up, and its exit status replaced the first's. The wait is counted from the first
    stop's coming, however long the import's C calls keep the handler from running.

    ``pending``: the list the pending delivery joins, so that a block that ends first raises it
    (:func:`settle`); by default that of the innermost :func:`lost_stops_redelivered` block."""
    inside = False
    while frame is not None and not inside:
        inside = frame.f_code.co_filename.startswith("<frozen importlib._bootstrap")
        frame = frame.f_back
    now = time.monotonic()
    since, delivery = _IMPORT_WAIT.get("stop", (now, None))
    if delivery is not None and not delivery.waiting() and not _delivered_lately(delivery, now):
        since = now  # that wait is over (its block raised it, or it went elsewhere): this is a new stop
    if not inside or now - since > IMPORT_WAIT_S:
        _IMPORT_WAIT.clear()
        if delivery is not None:
            delivery.cancel()  # a stop that joined the wait is this one: raised once, not twice
        return False
    if delivery is not None and delivery.waiting():
        return True  # a stop comes while one waits: it joins that one
    delivery = _Redelivery(signum, IMPORT_POLL_S)
    _IMPORT_WAIT["stop"] = (since, delivery)
    if pending is None and _PENDING:
        pending = _PENDING[-1]
    if pending is not None:
        pending.append(delivery)
    return True


def _delivered_lately(delivery: _Redelivery, now: float) -> bool:
    """Whether ``delivery`` went out lately: the handler running now is then its own, late by the
    C call it waited for (counted as long as twice the cap: one longer than the cap finds the
    stop due). Later, it went to another handler meanwhile, and that wait is over."""
    return delivery.fired_at is not None and now - delivery.fired_at <= 2 * IMPORT_WAIT_S


def raise_stop(held: BaseException | None, error: BaseException | None = None) -> None:
    """Raise ``held``, a stop that came while a block ran (None: none came), once the block is
    done. ``error`` is what the block raised: an error is chained to the stop, which wins (the
    command was stopped, and its exit status must say so: a lost SIGTERM followed within
    :data:`REDELIVER_AFTER_S` by an error exited 2, not 143); a stop or an exit of the block's own
    goes out as it is."""
    if held is not None and (error is None or isinstance(error, Exception)):
        raise held from error


@contextlib.contextmanager
def _then_raise(undo: Callable[[], None], stop: Callable[[], BaseException | None]):
    """Run the block, then ``undo()``; then raise ``stop()`` (a stop the block's time held back,
    or None) as :func:`raise_stop` says."""
    error = None
    try:
        yield
    except BaseException as exc:
        error = exc
        raise
    finally:
        undo()
        raise_stop(stop(), error)


#: the pending deliveries of each :func:`lost_stops_redelivered` block now running (:func:`settle`)
_PENDING: list[list[_Redelivery]] = []


def settle() -> None:
    """Raise now a stop lost in a finalizer whose delivery is still waiting for its timer (an
    :class:`Interrupted`); nothing if none is. Called before an output is renamed into place:
    on a loaded machine the timer ran after `correct` had committed its output, and the command
    then said "interrupted; no partial output was left" beside it. The stop came first."""
    waiting = [delivery.signum for pending in _PENDING for delivery in pending if delivery.cancel()]
    if waiting:
        raise Interrupted(waiting[0])


def lost_stops_redelivered():
    """While the block runs, a stop (a ``KeyboardInterrupt``) Python dropped in a finalizer is
    delivered again (:func:`redeliver`); any other dropped exception goes to the hook as before.
    A stop still waiting for its timer when the block ends is raised as it leaves (the command
    finished meanwhile: the stop must not reach the caller after the command's own handling);
    :func:`settle` raises it sooner."""
    before, pending = sys.unraisablehook, []

    def hook(unraisable):
        delivery = redeliver(unraisable.exc_value)
        if delivery is None:
            before(unraisable)
        else:
            pending.append(delivery)

    def undo():
        sys.unraisablehook = before
        _PENDING[:] = [other for other in _PENDING if other is not pending]  # this block's, not an equal one

    def stop():
        waiting = [delivery.signum for delivery in pending if delivery.cancel()]
        return Interrupted(waiting[0]) if waiting else None

    sys.unraisablehook = hook
    _PENDING.append(pending)
    return _then_raise(undo, stop)


def deferred(*signals):
    """Hold ``signals`` off while the block cleans up, then act on them: one that arrived is an
    :class:`Interrupted` once the block is done (an error of the block's is chained to it:
    :func:`raise_stop`).

    Why not ignore them: an interrupt during the clean-up was lost, the run ended as if none had
    come (exit 0 after a Ctrl-C). Why not let them through: stopping the workers takes a moment,
    and a second signal (or a first one lost in a finalizer and delivered again) cut it short and
    left the workers' temporaries. Only the main thread may set handlers: elsewhere,
    nothing is held off."""
    if threading.current_thread() is not threading.main_thread():
        return contextlib.nullcontext()
    came = []

    def note(signum, frame):
        came.append(signum)

    # a signal the command was started ignoring (`make test &` starts it so) stays ignored
    before = {sig: signal.signal(sig, note) for sig in signals if signal.getsignal(sig) is not signal.SIG_IGN}

    def undo():
        for sig, handler in before.items():
            signal.signal(sig, handler)

    return _then_raise(undo, lambda: Interrupted(came[0]) if came else None)


@contextlib.contextmanager
def held(*signals):
    """Hold ``signals`` off while the block runs, then deliver the first that came through the
    handler in place as the block ends (``signal.raise_signal``): that handler's own rules apply
    -- Python's raises ``KeyboardInterrupt``, a guard already stopping only says "please wait", an
    ignored one stays ignored. For a step that must not be cut in two, such as taking a resource
    and recording it for release: a stop that lands between them leaked the resource.

    Why not :func:`deferred`: it raises an :class:`Interrupted` of its own, past the handler the
    command installed (acquisition's X-ray guard, which marks itself stopping so that a second
    signal cannot cut its switch-off short). Why not ``pthread_sigmask``: it holds a signal off
    this thread only, and a process's signal then goes to another thread, whose handler flag
    still raises in the main thread at once. Only the main thread runs Python's handlers: in any
    other, nothing can interrupt the block, and nothing is held."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []

    def note(signum, frame):
        came.append(signum)

    before = {}
    try:
        for sig in signals:
            handler = signal.getsignal(sig)
            if handler is not None and handler is not signal.SIG_IGN:  # None: set outside Python
                before[sig] = signal.signal(sig, note)
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
        if came:
            signal.raise_signal(came[0])


#: the stop signals that came after a command's outcome was decided, in order (:func:`note_after_the_end`)
_AFTER_THE_END: list[int] = []


def note_after_the_end(signum, frame) -> None:
    """A stop signal's handler once a command's outcome is decided (the X-ray guard's ``finish``):
    the stop is recorded, nothing else -- no line, no exception, no death by the signal. The
    command line turns its exit 0 into 128 + N at its very end (:func:`stop_after_the_end`).

    Why not ignore it: a Ctrl-C in a source command's last 20-150 ms was lost, and exit 0 let
    `radiokit acquire source probe ... && radiokit acquire source on ...` switch X-rays on after
    it (review of s52). Why not act on it: the tube's line is said and must stay the last, and a
    raise there cut the link's close short."""
    stops_after_the_end().append(int(signum))


def stop_after_the_end() -> int | None:
    """The first stop :func:`note_after_the_end` recorded since :func:`forget_stops_after_the_end`."""
    record = stops_after_the_end()
    return record[0] if record else None


def stops_after_the_end() -> list[int]:
    """The current command's record (a new list for each command: a hook holding one knows
    whether another command has begun since)."""
    return _AFTER_THE_END


def forget_stops_after_the_end() -> None:
    """A new command begins (``main()`` may run several in one process)."""
    global _AFTER_THE_END
    _AFTER_THE_END = []


#: prctl(2)'s option asking the kernel for a signal when this process's parent dies (linux/prctl.h).
_PR_SET_PDEATHSIG = 1

#: How often :func:`_watch_parent` asks who its parent is, s: an orphan's work runs on this long at most.
PARENT_POLL_S = 0.1


def die_with_parent(parent_pid: int) -> None:
    """End this process when ``parent_pid``, its parent, ends, however it ends: SIGKILL runs no
    handler, so a parent killed so never kills the child it would have killed on any other stop
    (``sim.mesh``'s gmsh meshed on to its end, an orphan). Call it first thing in the child.

    On Linux the kernel sends this process SIGKILL as its parent dies (``prctl(PR_SET_PDEATHSIG)``).
    The parent may have died before the request (between the fork and this call): no signal
    will come, so the parent is checked after it, and a process whose parent is no longer
    ``parent_pid`` (re-parented to init or a subreaper) ends at once, exit status 1. Elsewhere,
    or where the request fails, a daemon thread does the same every :data:`PARENT_POLL_S`
    (:func:`_watch_parent`): it needs the interpreter's lock, which ctypes gives up during a
    foreign call (gmsh's). On Linux the parent is the *thread* that started the child: it must
    outlive the child (``sim.mesh._in_child`` waits for it in that thread)."""
    import os

    asked = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            asked = libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):  # no libc or no prctl to call: the thread below
            asked = False
    if os.getppid() != parent_pid:
        os._exit(1)
    if not asked:
        _watch_parent(parent_pid)


def _watch_parent(parent_pid: int) -> None:
    """:func:`die_with_parent`'s fallback: a daemon thread ends the process (exit status 1) once its
    parent is no longer ``parent_pid``, within :data:`PARENT_POLL_S`. A POSIX orphan is adopted by
    init or a subreaper, so its parent pid changes; a pid reused by then is not its parent."""
    import os

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
