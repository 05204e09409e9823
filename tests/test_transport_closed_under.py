"""A port closed under an exchange: :meth:`SerialTransport.close` from another thread while the
exchange still reads. pyserial's ``in_waiting`` on the closed port raised ``TypeError`` (its
descriptor None), not a link error, in every read path -- a traceback to the user instead of the
lost link it is. The close now waits for the exchange, at most its worst case
(:func:`acquisition.transport.close_wait_s`), then closes the port between two of its steps;
each test holds a real exchange with the emulator on a real pty at a known point, between two
steps (a spy on the transport's read slice, or on its spacing's wait, holds it there, stalled,
until the test's thread has closed the link), so that the close is past its wait. Short
time-outs keep that wait short."""

from __future__ import annotations

import signal
import sys
import threading
import time

import pytest
from conftest import in_thread

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError, NoReply, WriteTimedOut
from acquisition.transport import SerialTransport, close_wait_s

# the longest the close may wait for the exchange on these tests' links, and a loaded machine's slack
_TIMEOUTS = {"timeout_s": 0.25, "write_timeout_s": 0.05, "min_interval_s": 0.0}
_SLACK_S = 0.5


class _CloseAfterARead:
    """Close the link (:meth:`SerialTransport.close`, from the test's thread) once the exchange's
    next read slice (``step``: or another step) has returned, before the exchange goes on: the
    exchange, stalled there past the close's wait, then finds its link closed at its next step,
    as when a close lands between two read slices of an exchange slower than its time-outs. The
    step itself is the transport's; the spy only holds the exchange until the close is over."""

    def __init__(self, link: SerialTransport, step: str = "_read_some"):
        self.link, self.read_once, self.closed = link, threading.Event(), threading.Event()
        real = getattr(link, step)

        def spy(*args, **kwargs):
            out = real(*args, **kwargs)
            if not self.read_once.is_set():
                self.read_once.set()
                self.closed.wait(5.0)
            return out

        setattr(link, step, spy)

    def close_after_it(self) -> None:
        assert self.read_once.wait(2.0), "the exchange never read"
        link = self.link
        t0 = time.monotonic()
        try:
            link.close()
        finally:
            self.closed.set()
        # it waited for the exchange, at most its worst case, and not for the stalled exchange's end
        bound = close_wait_s(link.timeout_s, link.write_timeout_s, link.min_interval_s)
        assert time.monotonic() - t0 <= bound + _SLACK_S
        assert not link.is_open


def _closed_during(link: SerialTransport, command: str, step: str = "_read_some") -> dict:
    """``link.query(command)`` in a thread, the link closed from this one once the exchange has
    passed its ``step`` (:class:`_CloseAfterARead`): the query's outcome, the thread ended."""
    spy = _CloseAfterARead(link, step)
    thread, out = in_thread(lambda: link.query(command))
    spy.close_after_it()
    thread.join(3.0)
    assert not thread.is_alive()
    return out


def _assert_lost_link(out: dict, command: str) -> None:
    raised = out.get("raised")
    assert isinstance(raised, DeviceError) and not isinstance(raised, (NoReply, WriteTimedOut)), repr(raised)
    said = str(raised)
    assert f": {command}: link lost (" in said and "closed" in said, said


@pytest.fixture
def served():
    model = L8121Model(warmed_up=True)
    with PtyServer(model) as server:
        yield model, server


def test_a_port_closed_while_the_reply_is_read_is_a_lost_link_and_the_command_owed(served):
    model, server = served
    link = SerialTransport(server.url, **_TIMEOUTS, retries=0)
    try:
        model.hold_once()  # no reply comes: the exchange stays in its read
        out = _closed_during(link, "STS")
        _assert_lost_link(out, "STS")
        # written whole before the port went: it may have reached the controller, its reply owed
        assert [command for command, _ in link._owed] == ["STS"]
    finally:
        link.close()


def test_a_port_closed_while_a_late_reply_is_awaited_is_a_lost_link(served):
    model, server = served
    link = SerialTransport(server.url, **_TIMEOUTS, retries=0)
    try:
        model.hold_once()
        with pytest.raises(NoReply):
            link.query("STS")
        # the next exchange first waits a quarter time-out for the late reply: closed in that read
        out = _closed_during(link, "TYP")
        _assert_lost_link(out, "TYP")
    finally:
        link.close()


def test_a_port_closed_while_an_interrupted_exchange_is_completed_is_a_lost_link(served):
    """The exchange before was cut short by Ctrl-C as it read its reply (Python's own, raised by a
    profile hook at the read's first call); the next exchange completes it first (its reply
    awaited), and the port is closed in that wait."""
    model, server = served
    link = SerialTransport(server.url, **_TIMEOUTS, retries=0)
    try:
        model.hold_once()
        fired = []

        def hook(frame, event, arg):
            if event == "c_call" and frame.f_code.co_name == "_read_line" and not fired:
                fired.append(arg)
                raise KeyboardInterrupt("stopped in the read")

        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.setprofile(hook)
        try:
            with pytest.raises(KeyboardInterrupt, match="stopped in the read"):
                link.query("STS")
        finally:
            sys.setprofile(None)
            signal.signal(signal.SIGINT, previous)
        assert link._pending is not None and link._pending[0] == "STS"
        out = _closed_during(link, "TYP")
        _assert_lost_link(out, "TYP")
    finally:
        link.close()


def test_a_port_closed_before_the_flush_ahead_of_a_command_is_a_lost_link_and_nothing_sent(served):
    model, server = served
    link = SerialTransport(server.url, **{**_TIMEOUTS, "min_interval_s": 0.05}, retries=0)
    try:
        assert link.query("TYP") == "TYP L8121-01"
        before = len(model.commands)
        out = _closed_during(link, "STS", "_wait_spacing")  # stalled after the spacing, lock held
        _assert_lost_link(out, "STS")
        assert model.commands[before:] == [] and link._owed == []  # not written, nothing owed
    finally:
        link.close()


def test_a_link_closed_under_an_exchange_stays_closed(served):
    """With a reconnect allowed (the default, one), the exchange took the port closed under it
    for a lost link and reopened it: the link was open again, its port's lock held, after
    ``close()`` had returned -- a close from another thread (a shutdown, a guardian) undone. It is
    not reconnected: the command fails as a lost link, the link stays closed, its lock let go."""
    model, server = served
    link = SerialTransport(server.url, **_TIMEOUTS)  # retries: the default
    assert link.retries >= 1
    try:
        model.hold_once()
        out = _closed_during(link, "STS")
        _assert_lost_link(out, "STS")
        assert not link.is_open and link._hold is None
        assert [command for command, _ in link._owed] == ["STS"]  # it may have reached the controller
    finally:
        link.close()


def test_a_switch_on_whose_port_is_closed_under_it_still_says_x_rays_may_be_on(served):
    """A command not sent again after a reconnect (the switch-on, XON) whose port is closed under
    its read: it may have reached the controller, and the error says X-rays may be on -- not
    only that the link was closed. The driver's own link and reconnect check."""
    from acquisition.l8121 import L8121

    model, server = served
    with L8121(server.url, dialect="A", poll_s=0.05, min_interval_s=0.0) as src:
        link = src._transport
        link.timeout_s, link.write_timeout_s = _TIMEOUTS["timeout_s"], _TIMEOUTS["write_timeout_s"]
        assert "XON" in link.on_reconnect.not_resent
        model.hold_once()
        out = _closed_during(link, "XON")
        raised = out.get("raised")
        assert isinstance(raised, DeviceError) and "X-rays may be on" in str(raised), repr(raised)
