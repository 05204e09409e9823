"""A stop signal at any point where :meth:`SerialTransport.query` takes or gives back its exchange's
lock leaves the link's bookkeeping whole, on a real pty.

Why: the lock was taken by a ``with`` block, and the thread that holds it (``_owner``) and what it
runs (``_running``) were recorded by a call made after it, and cleared by one made before its
release. A signal's handler runs as such a call starts: one landing there left the link locked
by a thread not recorded (a handler's close then waited a whole exchange's worst case for its own
thread, and the query it interrupted undid that close as it recorded itself, reopening the port),
or recorded to a thread that no longer held it (a close that followed took an interrupted XOF
for a switch-off still running, and left the port open to the end of the next query).

A real signal cannot be aimed, so a trace function acts as the handler would, at each point where
CPython runs a signal's handler (the model of tests/test_l8121_stop_anywhere.py: a function's
start, after each call, a loop's jump back): a hook for the timing only, the link, the pty and
the emulated controller real.
"""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest
from test_l8121_stop_anywhere import at_each_check_point

from acquisition import transport
from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError
from acquisition.guardian import StopSignal
from acquisition.l8121 import L8121
from acquisition.transport import SerialTransport, close_wait_s

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

#: the transport's code that takes and gives back the exchange's lock (the helpers it called then
#: included, where they exist)
_TAKING = {"query", "open", "_taken", "_given_back", "_close_if_asked", "_close_left"}
REPLY_TIMEOUT_S = 2.0  # the driver's: what a reply waited for in vain costs
OFF_BOUND_S = REPLY_TIMEOUT_S / 4


def _once_at_a_new_point(tried: set, act):
    """A trace function for this thread calling ``act()`` once, as a signal's handler, at the first
    point of :data:`_TAKING`'s code (the transport's) not in ``tried`` yet (then added);
    ``fired["at"]`` the point, None when every point was tried."""
    fired = {"at": None}

    def at(frame, place):
        key = (frame.f_code.co_name, place)
        if fired["at"] is None and key not in tried:
            tried.add(key)
            fired["at"] = key
            act()

    local = at_each_check_point(at)

    def tracer(frame, event, arg):
        if frame.f_code.co_filename != transport.__file__ or frame.f_code.co_name not in _TAKING:
            return None
        frame.f_trace_opcodes = True
        at(frame, -1)  # as the function starts
        return local

    return tracer, fired


def _traced(tracer, call):
    sys.settrace(tracer)
    try:
        return call()
    finally:
        sys.settrace(None)


def _free(link: SerialTransport) -> bool:
    """Whether no thread holds the link's exchange lock, nor is recorded as holding it."""
    if not link._lock.acquire(blocking=False):
        return False
    link._lock.release()
    return link._owner is None and link._running is None


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_stop_as_the_link_is_taken_or_given_back_leaves_it_free_and_the_switch_off_whole(dialect):
    """The switch-off (``off()``) stopped by a signal (StopSignal, the guardian's SIGTERM) at each
    point of its queries' lock taking and giving back: the link is free and recorded free, the
    next ``off()`` in the same thread confirms within a quarter of a reply time-out with the
    emulated tube off, and the link's close that follows closes it (before: a close after an
    XOF stopped as it gave the link back took it for a switch-off still running in this thread,
    and left the port open)."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    failures, tried = [], set()

    def stop():
        raise StopSignal(signal.SIGTERM)

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, poll_s=0.005, min_interval_s=0.0) as src:
        link = src._transport
        while True:
            src.on(60, 250)
            tracer, fired = _once_at_a_new_point(tried, stop)
            try:
                _traced(tracer, src.off)
            except StopSignal:
                pass
            if fired["at"] is None:
                break
            where = fired["at"]
            if not _free(link):
                failures.append((where, "link left taken", link._owner, link._running))
                link._owner = link._running = None  # (so that the sweep goes on)
            t0 = time.monotonic()
            state = src.off()
            took = time.monotonic() - t0
            if not state.confirms_off or model.state.emitting or took > OFF_BOUND_S:
                failures.append((where, state, f"{took:.3f} s"))
            link.close()
            if link.is_open:
                failures.append((where, "the close left the port open"))
            link.open()
    assert len(tried) > 5, tried
    assert not failures, failures


@pytest.fixture
def served():
    model = L8121Model(warmed_up=True)
    with PtyServer(model) as server:
        yield model, server


_SHORT = {"timeout_s": 0.25, "write_timeout_s": 0.05, "min_interval_s": 0.0}


@pytest.mark.parametrize("command", ["STS", "XOF"])
def test_a_close_from_a_handler_as_the_link_is_taken_or_given_back_never_waits_for_its_own_thread(served, command):
    """A signal's handler that closes the link, run in the thread whose query is taking or giving
    back the link, at each of those points: the close does not wait for its own thread (before,
    at the lock taken but not yet recorded, it waited a whole exchange's worst case, then the
    query reopened the port it had closed), the link is closed once the query ends, and a
    switch-off (XOF) is not cut short: it reaches the controller and its reply is returned."""

    class _Off:  # the driver's switch-off word (acquisition.l8121.Reidentify's ``blind``)
        blind = frozenset({"XOF"})

        def __call__(self, ask):
            ask("TYP")

    model, server = served
    link = SerialTransport(server.url, **_SHORT, retries=0)
    link.on_reconnect = _Off()
    bound = close_wait_s(**_SHORT)
    failures, tried, closes = [], set(), []

    def close():
        held = link._lock.locked()  # (only this thread uses the link): taken, or not yet / given back
        t0 = time.monotonic()
        link.close()
        closes.append((time.monotonic() - t0, held))

    try:
        while True:
            before = len(model.commands)
            closes.clear()
            tracer, fired = _once_at_a_new_point(tried, close)
            out = {}
            try:
                out["reply"] = _traced(tracer, lambda: link.query(command))
            except DeviceError as exc:
                out["raised"] = exc
            if fired["at"] is None:
                break
            where = fired["at"]
            took, held = closes[0]
            if took > bound / 2:
                failures.append((where, f"the handler's close waited {took:.3f} s"))
            # (a close before the lock is taken is an ordinary one: the query then reopens the link)
            if held and (link.is_open or link._hold is not None):
                failures.append((where, "the link is open after its close", out))
            if held and command == "XOF" and (out.get("reply") != "XOF" or model.commands[before:][-1:] != ["XOF"]):
                failures.append((where, "the switch-off was cut short", out, model.commands[before:]))
            if "raised" in out and "link was closed" not in str(out["raised"]):
                failures.append((where, out))
            if not _free(link):
                failures.append((where, "link left taken", link._owner, link._running))
                link._owner = link._running = None
            link.open()
    finally:
        link.close()
    assert len(tried) > 5, tried
    assert not failures, failures


def test_a_switch_offs_close_left_to_its_end_is_done_when_a_second_stop_lands_as_that_end_starts(served):
    """Two stops in the thread whose switch-off (XOF) holds the link: the first's handler closes
    the link mid-query (left to the query's end: a switch-off is not cut short), the second
    raises as that end (``_close_if_asked``) starts, as a signal's handler runs at a function's
    start. The close the first asked for is done all the same: before, it was dropped (its flag
    cleared by the next query's start), the port left open and its lock share held after a close
    that had returned. A trace function stands in for the signals' timing (they cannot be aimed);
    the link and the pty are real."""

    class _Off:
        blind = frozenset({"XOF"})

        def __call__(self, ask):
            ask("TYP")

    _, server = served
    link = SerialTransport(server.url, **_SHORT, retries=0)
    link.on_reconnect = _Off()
    link.query("STS")  # opened, its lock share taken
    done = []

    def tracer(frame, event, arg):
        if event != "call" or frame.f_code.co_filename != transport.__file__:
            return None
        if frame.f_code.co_name == "_query" and "close" not in done:
            done.append("close")
            link.close()  # the first stop's handler
        elif frame.f_code.co_name == "_close_if_asked" and "close" in done:
            done.append("stop")
            raise StopSignal(signal.SIGTERM)  # the second's, as the query's end starts
        return None

    try:
        with pytest.raises(StopSignal):
            _traced(tracer, lambda: link.query("XOF"))
        assert done == ["close", "stop"], done
        assert _free(link)
        assert not link.is_open and link._hold is None, "the close the first stop asked for was dropped"
    finally:
        link.close()
