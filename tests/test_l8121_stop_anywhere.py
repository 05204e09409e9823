"""A stop at any point of the L8121 driver's operations leaves the tube to the switch-off that follows.

A signal's stop (:class:`~acquisition.guardian.StopSignal`, or Ctrl-C's KeyboardInterrupt) is raised
in the main thread wherever it is, and the run's cleanup then calls ``off()`` in that same thread.
A stop that lands between the driver taking some shared state (the link, a place in its queue, the
switch-off's ownership) and the ``try`` that gives it back left it taken: CI hung on ``source
warm-up`` (dialect B, SIGTERM) with the switch-off waiting for a link nobody held.
tests/test_l8121_fairness.py stops ``status()`` at every line; here the operations a run calls
while a stop may come -- ``on()`` (``set_values()`` with the tube off is its first step),
``set_values()`` with the beam on, ``warm_up()``, ``off()`` itself, and ``check()`` while another
thread polls (the beam monitor's) -- in both dialects, and the driver's reply check, which the
transport calls.

A real signal cannot be aimed, so a trace function raises the stop by hand, at each point where
CPython runs a signal's handler (:func:`_stop_once_at_a_new_point`). Each point is tried once in
each state of the tube's bookkeeping (beam off/on, X-rays possibly on, switch-off running) in
which it runs -- a poll loop's tenth pass is its first again -- which keeps each test near a
second.

Real pyserial on a pty this test creates, the emulator answering at once (``min_interval_s=0``).
The bound on the switch-off is a quarter of a reply time-out: its two exchanges (XOF, STS) take
about a millisecond here, and a switch-off that waits for a reply which is not coming (a line
already read, a link nobody gives back) waits a whole reply time-out (2 s), or for ever.
"""

from __future__ import annotations

import dis
import inspect
import os
import signal
import sys
import threading
import time

import pytest

from acquisition import l8121 as driver
from acquisition import transport
from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.guardian import StopSignal
from acquisition.l8121 import L8121

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

REPLY_TIMEOUT_S = 2.0  # the driver's (both dialects'): what a reply waited for in vain costs
OFF_BOUND_S = REPLY_TIMEOUT_S / 4
WALL_S = 15.0  # the whole sweep, so that a hang fails the test instead of the suite


@pytest.fixture(params=["A", "B"])
def dialect(request):
    return request.param


_CODE: dict = {}


def _code_facts(code):
    """(exception table entries, offsets of the calls and backward jumps) of ``code``."""
    if code not in _CODE:
        checks = {
            i.offset for i in dis.get_instructions(code) if i.opname in ("CALL", "CALL_FUNCTION_EX", "JUMP_BACKWARD")
        }
        _CODE[code] = (dis.Bytecode(code).exception_entries, checks)
    return _CODE[code]


def _handler(code, offset: int):
    """Where an exception raised at ``offset`` of ``code`` goes (the exception table's target; None: out)."""
    return next((e.target for e in _code_facts(code)[0] if e.start <= offset < e.end), None)


def at_each_check_point(act):
    """A local trace function (opcode events) calling ``act(frame, place)`` just past each place
    of a frame where CPython 3.11 runs a pending signal's handler -- after a call, at a backward
    jump -- whose raise would go where one at the next instruction goes (one the ``try`` around it
    catches is that ``try``'s own business)."""
    last: dict = {}

    def local(frame, event, arg):
        if event == "opcode":
            code, offset = frame.f_code, frame.f_lasti
            before, last[frame] = last.get(frame), offset
            if (
                before is not None
                and before in _code_facts(code)[1]
                and _handler(code, offset) == _handler(code, before)
            ):
                act(frame, before)
        return local

    return local


def _stop_once_at_a_new_point(src, tried: set, *, into_transport: bool = False):
    """A trace function for this thread raising :class:`StopSignal` once, at the first point of the
    driver where a signal's handler can run -- (code, place, beam off/on, switch-off running) --
    that is not in ``tried`` yet (then added). ``into_transport``: only the driver's code the
    transport calls back (its reply check), instead of only the driver's own frames.

    The places are CPython's (3.11): a handler runs when a function starts, after each call
    returns (a method, a builtin, a C function alike) and at a loop's back edge -- never between
    two other instructions. Raised by a trace function at the instruction after such a call,
    handled as at the call; so a stop skips no ``with`` block's exit nor ``finally`` that a signal
    could not skip (raised at each line's start instead, one left a ``with``'s lock held at the
    NOP of a ``try:``: a hang no signal can cause)."""
    fired = {"at": None}

    def stop(frame, place):
        key = (frame.f_code, place, src._may_be_on, src._beam is not None, src._off_thread is not None)
        if fired["at"] is None and key not in tried:
            tried.add(key)
            fired["at"] = key
            raise StopSignal(signal.SIGTERM)

    local = at_each_check_point(stop)

    def tracer(frame, event, arg):
        if frame.f_code.co_filename != driver.__file__:
            return None
        caller, under_transport = frame.f_back, False
        while caller is not None and not under_transport:
            under_transport = caller.f_code.co_filename == transport.__file__
            caller = caller.f_back
        if under_transport != into_transport:
            return None
        frame.f_trace_opcodes = True
        if not frame.f_code.co_flags & inspect.CO_GENERATOR:  # (a generator's is also its close, in a finalizer)
            stop(frame, -1)  # as the function starts
        return local

    return tracer, fired


def _line_of(code, offset: int) -> int:
    return next(i.positions.lineno for i in dis.get_instructions(code) if i.offset == offset)


def _sweep(src, model, setup, call, *, into_transport=False, between=None):
    """For every new point: ``setup()``, ``call()`` stopped there, then (``between()``, if given,
    and) ``off()`` in the same thread, which must confirm within :data:`OFF_BOUND_S` with the emulated
    tube off. Returns (points tried, failures); a sweep still running after :data:`WALL_S` fails."""
    tried: set = set()
    failures: list = []

    def sweep():
        while True:
            setup()
            tracer, fired = _stop_once_at_a_new_point(src, tried, into_transport=into_transport)
            sys.settrace(tracer)
            try:
                call()
            except StopSignal:
                pass
            except Exception as exc:  # a stop must not turn into another error
                failures.append((fired["at"], "call", repr(exc)))
            finally:
                sys.settrace(None)
            if fired["at"] is None:  # the call ran through points all tried: done
                return
            code, place = fired["at"][:2]
            line = code.co_firstlineno if place < 0 else _line_of(code, place)
            where = (code.co_name, line, *fired["at"][2:])
            if between is not None:
                why = between()
                if why:
                    failures.append((where, why))
            t0 = time.monotonic()
            try:
                state = src.off()
            except Exception as exc:
                failures.append((where, "off", repr(exc)))
                continue
            took = time.monotonic() - t0
            if not state.confirms_off or model.state.emitting or took > OFF_BOUND_S:
                failures.append((where, state, model.state, f"{took:.3f} s"))

    worker = threading.Thread(target=sweep, daemon=True)
    worker.start()
    worker.join(timeout=WALL_S)
    if worker.is_alive():
        # close() would switch off through what the hung thread holds, and the test hang with it
        src.detach()
    assert not worker.is_alive(), f"hung after a stop (points tried: {len(tried)}; failures: {failures[:3]})"
    return tried, failures


def _source(dialect, **model_kw):
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0, **model_kw)
    server = PtyServer(model)
    return model, server


ENTRIES = {
    # name: (setup before each stopped call, the call). check() is swept by the test of another
    # thread's poll below, set_values() with the tube off by on() (its first step)
    "on": (None, lambda src: src.on(60, 250)),
    "set_values with the beam on": ("beam", lambda src: src.set_values(60, 200)),
    "off": ("beam", lambda src: src.off()),
}


@pytest.mark.parametrize("entry", list(ENTRIES))
def test_a_stop_at_any_point_of_an_operation_leaves_the_tube_to_the_switch_off(dialect, entry):
    """The operation stopped at each of its points in turn; the switch-off that follows in the same
    thread confirms the tube off within a quarter of a reply time-out, and the emulated tube is off."""
    setup_kind, call = ENTRIES[entry]
    model, server = _source(dialect)
    with server, L8121(server.url, dialect=dialect, poll_s=0.005, min_interval_s=0.0) as src:

        def setup():
            if setup_kind == "beam":
                src.on(60, 250)

        tried, failures = _sweep(src, model, setup, lambda: call(src))
    assert len(tried) > 30, len(tried)  # the operation ran through the driver's code
    assert not failures, (len(failures), failures[:5])


def test_a_stop_at_any_point_of_a_warm_up_leaves_the_tube_to_the_switch_off(dialect):
    """The same for ``warm_up()`` (it emits: ``WUP``, B's ``XON``), stopped before and during the
    sequence; the emulator's warm-up is a few polls long."""
    model, server = _source(dialect, warmup_s=0.01)
    with server, L8121(server.url, dialect=dialect, poll_s=0.002, min_interval_s=0.0) as src:
        tried, failures = _sweep(src, model, model.require_warm_up, lambda: src.warm_up(timeout_s=5, progress=False))
    assert len(tried) > 50, len(tried)
    assert not failures, (len(failures), failures[:5])


def _another_thread_reads(read):
    """None when ``read()`` in another thread ends within :data:`OFF_BOUND_S`, else why not."""
    done = threading.Event()

    def poll():
        try:
            read()
        except Exception:  # cut short by a switch-off this thread left pending: not blocked
            pass
        done.set()

    threading.Thread(target=poll, daemon=True).start()
    if not done.wait(OFF_BOUND_S):
        return f"another thread's {read.__name__}() waited for what this thread left taken"
    return None


@pytest.mark.parametrize("stopped, other", [("check", "check"), ("off", "status")])
def test_a_stop_in_one_thread_leaves_the_link_to_another_thread(dialect, stopped, other):
    """This thread's ``check()`` (or ``off()``) is stopped at each point in turn, then another
    thread reads (a beam monitor's ``check()``, a user's ``status()``): it gets the link at once,
    before this thread asks for it again -- a caller that handles the stop without a switch-off
    (the tube read off) may never ask again. Before, a stop landing as the link was taken
    (``_take_turn`` returning) left it taken until then, and one landing right after ``off()``
    took the switch-off's ownership (``_off_thread``), before its ``try``, left that taken (review
    s51rv). Then this thread's switch-off confirms, as above."""
    model, server = _source(dialect)
    with server, L8121(server.url, dialect=dialect, poll_s=0.005, min_interval_s=0.0) as src:
        read = getattr(src, other)
        tried, failures = _sweep(
            src, model, lambda: src.on(60, 250), getattr(src, stopped), between=lambda: _another_thread_reads(read)
        )
    assert len(tried) > 30, len(tried)
    assert not failures, (len(failures), failures[:5])


def test_a_stop_inside_the_reply_check_costs_the_switch_off_no_time_out(dialect):
    """The transport calls the driver back once a reply line is read (``reply_fits``: does the line
    fit the command?). A stop there, at each of its points in turn, during readings and settings
    with the beam on: the switch-off that follows confirms within a quarter of a reply time-out.
    Before, the line had left the transport's buffer before the check, and the switch-off waited
    a whole reply time-out (2 s, then a quarter more for a late reply) for the interrupted
    command's reply, which had come already."""
    model, server = _source(dialect)
    with server, L8121(server.url, dialect=dialect, poll_s=0.005, min_interval_s=0.0) as src:
        tried, failures = _sweep(
            src, model, lambda: src.on(60, 250), lambda: src.set_values(60, 200), into_transport=True
        )
    assert len(tried) > 5, len(tried)  # the check ran through the driver's grammar
    assert not failures, (len(failures), failures[:5])


def test_a_stop_at_any_point_of_a_connect_in_a_given_dialect_leaves_the_tube_off(dialect):
    """``connect()`` with the dialect given, at a unit left on by a crashed session, stopped at each
    of its points in turn (the link's open, the identity query, the state's): the stop goes on
    only once the tube is off, confirmed by ``STS`` and carried on the stop (``tube_state``) --
    by connect's own ``XOF``, before the state was read as after it read X-rays on. Before, a
    stop ahead of the state's reading let the link go with nothing sent, the tube on, and the
    caller could only warn."""
    model, server = _source(dialect)
    tried: set = set()
    failures: list = []
    with server:

        def sweep():
            while True:
                if not model.xray_on:
                    model.left_on(60, 250)
                src = L8121(server.url, dialect=dialect, poll_s=0.005, min_interval_s=0.0, connect=False)
                tracer, fired = _stop_once_at_a_new_point(src, tried)
                sys.settrace(tracer)
                stop = None
                try:
                    src.connect()
                except StopSignal as exc:
                    stop = exc
                except Exception as exc:
                    failures.append((fired["at"], "connect", repr(exc)))
                finally:
                    sys.settrace(None)
                if fired["at"] is None:
                    src.close()
                    return
                code, place = fired["at"][:2]
                where = (code.co_name, code.co_firstlineno if place < 0 else _line_of(code, place))
                state = getattr(stop, "tube_state", None)
                if not src.port_opened and not src.is_connected:
                    # stopped before the port was opened: nothing could be sent, and the stop says so
                    if getattr(stop, "probe_sent", False) or "XOF" in model.commands[-2:]:
                        failures.append((where, "a stop before the port opened said something was sent"))
                    continue
                if model.xray_on or state is None or not state.confirms_off:
                    failures.append((where, state, model.state, src.is_connected))
                if src.is_connected:  # a stop must not leave the port held
                    failures.append((where, "link left open"))
                    src.detach()

        worker = threading.Thread(target=sweep, daemon=True)
        worker.start()
        worker.join(timeout=WALL_S)
    assert not worker.is_alive(), f"hung after a stop (points tried: {len(tried)}; failures: {failures[:3]})"
    assert len(tried) > 10, len(tried)
    assert not failures, (len(failures), failures)
