"""A port closed under an exchange: :meth:`SerialTransport.close` from another thread (it does not
take the exchange's lock) while the exchange still reads. pyserial's ``in_waiting`` on the closed
port raised ``TypeError`` (its descriptor None), not a link error, in every read path -- a
traceback to the user instead of the lost link it is. Each test closes the real pty port at a
known point of a real exchange with the emulator: between two read slices (a spy on the port's
``read`` holds the exchange there while the test's thread closes it), or, for the flush before
a command, in the spacing's sleep (the lock held, nothing read yet)."""

from __future__ import annotations

import signal
import sys
import threading
import time

import pytest

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError, NoReply, WriteTimedOut
from acquisition.transport import SerialTransport


def _run(call) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def run():
        try:
            out["reply"] = call()
        except BaseException as exc:  # the outcome looked at by the test
            out["raised"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


class _CloseAfterARead:
    """Close the link (:meth:`SerialTransport.close`, from the test's thread) once the port's next
    ``read`` has returned, before the exchange goes on: the exchange then finds its port closed
    under it at its next look, as when a close lands between two read slices. The read itself is
    the port's; the spy only waits for the close to be over before returning what it read."""

    def __init__(self, link: SerialTransport):
        self.link, self.read_once, self.closed = link, threading.Event(), threading.Event()
        ser, real = link._serial, link._serial.read

        def read(size: int = 1) -> bytes:
            data = real(size)
            if not self.read_once.is_set():
                self.read_once.set()
                self.closed.wait(2.0)
            return data

        ser.read = read

    def close_after_it(self) -> None:
        assert self.read_once.wait(2.0), "the exchange never read"
        try:
            self.link.close()
        finally:
            self.closed.set()


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
    link = SerialTransport(server.url, timeout_s=1.0, min_interval_s=0.0, retries=0)
    try:
        model.hold_once()  # no reply comes: the exchange stays in its read
        spy = _CloseAfterARead(link)
        thread, out = _run(lambda: link.query("STS"))
        spy.close_after_it()
        thread.join(3.0)
        assert not thread.is_alive()
        _assert_lost_link(out, "STS")
        # written whole before the port went: it may have reached the controller, its reply owed
        assert [command for command, _ in link._owed] == ["STS"]
    finally:
        link.close()


def test_a_port_closed_while_a_late_reply_is_awaited_is_a_lost_link(served):
    model, server = served
    link = SerialTransport(server.url, timeout_s=0.4, min_interval_s=0.0, retries=0)
    try:
        model.hold_once()
        with pytest.raises(NoReply):
            link.query("STS")
        # the next exchange first waits a quarter time-out for the late reply: closed in that read
        spy = _CloseAfterARead(link)
        thread, out = _run(lambda: link.query("TYP"))
        spy.close_after_it()
        thread.join(3.0)
        assert not thread.is_alive()
        _assert_lost_link(out, "TYP")
    finally:
        link.close()


def test_a_port_closed_while_an_interrupted_exchange_is_completed_is_a_lost_link(served):
    """The exchange before was cut short by Ctrl-C as it read its reply (Python's own, raised by a
    profile hook at the read's first call); the next exchange completes it first (its reply
    awaited), and the port is closed in that wait."""
    model, server = served
    link = SerialTransport(server.url, timeout_s=1.0, min_interval_s=0.0, retries=0)
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
        spy = _CloseAfterARead(link)
        thread, out = _run(lambda: link.query("TYP"))
        spy.close_after_it()
        thread.join(3.0)
        assert not thread.is_alive()
        _assert_lost_link(out, "TYP")
    finally:
        link.close()


def test_a_port_closed_before_the_flush_ahead_of_a_command_is_a_lost_link_and_nothing_sent(served):
    model, server = served
    link = SerialTransport(server.url, timeout_s=0.5, min_interval_s=0.3, retries=0)
    try:
        assert link.query("TYP") == "TYP L8121-01"
        before = len(model.commands)
        thread, out = _run(lambda: link.query("STS"))  # sleeps the spacing (0.3 s), lock held
        deadline = time.monotonic() + 2.0
        while not link._lock.locked() and time.monotonic() < deadline:
            time.sleep(0.005)
        link.close()
        thread.join(3.0)
        assert not thread.is_alive()
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
    link = SerialTransport(server.url, timeout_s=1.0, min_interval_s=0.0)  # retries: the default
    assert link.retries >= 1
    try:
        model.hold_once()
        spy = _CloseAfterARead(link)
        thread, out = _run(lambda: link.query("STS"))
        spy.close_after_it()
        thread.join(3.0)
        assert not thread.is_alive()
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
        assert "XON" in link.on_reconnect.not_resent
        model.hold_once()
        spy = _CloseAfterARead(link)
        thread, out = _run(lambda: link.query("XON"))
        spy.close_after_it()
        thread.join(3.0)
        assert not thread.is_alive()
        raised = out.get("raised")
        assert isinstance(raised, DeviceError) and "X-rays may be on" in str(raised), repr(raised)
