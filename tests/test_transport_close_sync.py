""":meth:`SerialTransport.close` from another thread while an exchange runs, on a real pty.

Why: a close that did not wait for the exchange freed the port's descriptor NUMBER under it; an
``open()`` elsewhere in the process (a file, a socket) could take that number before the
exchange's next ``os.write``, and the command's bytes went into that file. The close now waits
for the exchange (at most :func:`acquisition.transport.close_wait_s`); past it, it marks the link
closing and the exchange stops at its next step without touching the descriptor."""

from __future__ import annotations

import contextlib
import os
import threading
import time

import pytest
from conftest import in_thread

from acquisition.errors import DeviceError, NoReply, WriteTimedOut
from acquisition.transport import SerialTransport, close_wait_s

# a loaded CI machine's scheduling slack on a wait measured from outside
_SLACK_S = 0.5


def _wait_for(predicate, within_s: float = 2.0) -> None:
    deadline = time.monotonic() + within_s
    while not predicate():
        assert time.monotonic() < deadline, "the exchange never got there"
        time.sleep(0.002)


def _files_on(number: int, folder) -> list[tuple[int, str]]:
    """Files opened until one gets the descriptor ``number`` (open takes the lowest free one)."""
    opened = []
    for i in range(256):
        path = str(folder / f"reuse{i}")
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        opened.append((fd, path))
        if fd == number:
            return opened
    return opened


@pytest.fixture
def stuck_pty():
    """A pty whose output nobody reads, its buffer filled: a command's write waits in its loop."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield master, slave, path
    os.close(master)
    os.close(slave)


def _fill(path: str) -> None:
    """Fill the pty's output until it takes nothing more, even after the kernel has moved what it
    holds on to the other side's buffer (it does so a moment after a write)."""
    fd = os.open(path, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        while True:
            taken = 0
            try:
                while True:
                    taken += os.write(fd, b"\0" * 4096)
            except BlockingIOError:
                pass
            if not taken:
                return
            time.sleep(0.05)
    finally:
        os.close(fd)


def test_a_close_during_a_write_never_lets_the_command_into_a_file_that_took_its_descriptor(stuck_pty, tmp_path):
    _, _, path = stuck_pty
    link = SerialTransport(path, timeout_s=0.2, write_timeout_s=0.3, min_interval_s=0.0, retries=0)
    opened = []
    try:
        _fill(path)  # after the open: pyserial's raw mode set, the output buffer full
        number = link._serial.fd
        thread, out = in_thread(lambda: link.query("STS"))
        _wait_for(lambda: link.commands_written == 1)  # in its write loop, the descriptor in hand
        time.sleep(0.02)
        t0 = time.monotonic()
        link.close()
        closed_s = time.monotonic() - t0
        opened = _files_on(number, tmp_path)  # right after close: the descriptor's number reused
        assert opened[-1][0] == number
        thread.join(3.0)
        assert not thread.is_alive()
        for _, file in opened:
            with open(file, "rb") as f:
                assert b"STS" not in f.read(), "the command went into a file that took the port's descriptor"
        # the close waited for the exchange, which ended on its own write time-out: nothing sent
        assert isinstance(out.get("raised"), WriteTimedOut), out
        assert closed_s <= close_wait_s(0.2, 0.3, 0.0) + _SLACK_S
        assert not link.is_open
    finally:
        for fd, _ in opened:
            os.close(fd)
        link.close()


def test_a_write_stalled_past_the_close_s_wait_never_writes_into_a_file_that_took_its_descriptor(stuck_pty, tmp_path):
    """The write loop holds the port's descriptor NUMBER from its start. Stalled between two of its
    steps past the close's wait (a loaded machine; here a spy holds it after its first wait for the
    port to take bytes), the close closes the port under it and a file opened right after takes the
    number: the loop's next ``os.write`` must not go into that file. Review s53rvclose: with the
    step's check removed, no other test failed (the close above waits the write out, and the
    reconnect check's exchange picks up the closed port, not the number)."""
    _, _, path = stuck_pty
    link = SerialTransport(path, timeout_s=0.05, write_timeout_s=0.1, min_interval_s=0.0, retries=0)
    bound = close_wait_s(link.timeout_s, link.write_timeout_s, link.min_interval_s)
    real, steps = link._closed_as_lost, []
    stalled, closed = threading.Event(), threading.Event()

    @contextlib.contextmanager
    def spy(ser, doing):
        with real(ser, doing):
            yield
        steps.append(doing)
        if doing.startswith("it wrote") and steps.count(doing) == 2 and not stalled.is_set():
            stalled.set()  # its first write and its first wait done: the next step writes again
            assert closed.wait(bound + 5.0)

    link._closed_as_lost = spy
    opened = []
    try:
        _fill(path)
        number = link._serial.fd
        thread, out = in_thread(lambda: link.query("STS"))
        assert stalled.wait(2.0), "the write never waited for the port"
        t0 = time.monotonic()
        link.close()
        closed_s = time.monotonic() - t0
        opened = _files_on(number, tmp_path)
        assert opened[-1][0] == number
        closed.set()
        thread.join(3.0)
        assert not thread.is_alive()
        for _, file in opened:
            with open(file, "rb") as f:
                assert f.read() == b"", "the command went into a file that took the port's descriptor"
        raised = out.get("raised")
        assert isinstance(raised, DeviceError) and "link was closed" in str(raised), out
        assert bound <= closed_s <= bound + _SLACK_S  # waited its bound, not for the stalled write
        assert not link.is_open
    finally:
        closed.set()
        for fd, _ in opened:
            os.close(fd)
        link.close()


def test_a_close_past_its_wait_during_a_reopen_leaves_the_link_closed_and_its_lock_let_go(tmp_path):
    """A query on a link lost before reopens the port. Stalled in that open past the close's wait
    (a loaded machine; a spy holds it once the port is opened, before its lock is checked), the close
    closes the link under it: the port just opened must not become the link's, nor its lock's share
    stay held after the close returned. Review s53rvclose: with the check removed, no test failed."""
    master, slave = os.openpty()
    link = SerialTransport(os.ttyname(slave), timeout_s=0.05, write_timeout_s=0.05, min_interval_s=0.0, retries=0)
    bound = close_wait_s(link.timeout_s, link.write_timeout_s, link.min_interval_s)
    real, stalled, closed = link._hold_opened, threading.Event(), threading.Event()

    def spy(ser):  # the port opened, its lock not yet checked (and taken again) on it
        stalled.set()
        assert closed.wait(bound + 5.0)
        real(ser)

    try:
        link._close_port()  # as a lost link leaves it: the next query reopens it
        link._hold_opened = spy
        thread, out = in_thread(lambda: link.query("STS"))
        assert stalled.wait(2.0), "the query never reopened the port"
        link.close()
        closed.set()
        thread.join(3.0)
        assert not thread.is_alive()
        raised = out.get("raised")
        assert isinstance(raised, DeviceError) and "link was closed" in str(raised), out
        assert not link.is_open and link._hold is None
    finally:
        closed.set()
        link.close()
        os.close(master)
        os.close(slave)


@pytest.fixture
def served():
    from acquisition.emulators.l8121 import L8121Model, PtyServer

    model = L8121Model(warmed_up=True)
    with PtyServer(model) as server:
        yield model, server


class _StalledCheck:
    """A reconnect check (:attr:`SerialTransport.on_reconnect`) stalled until the test says go --
    a process stalled past its time-outs -- then one real exchange (TYP). ``blind``: the commands
    a driver names its switch-off (acquisition.l8121.Reidentify's XOF)."""

    blind = frozenset({"XOF"})

    def __init__(self):
        self.entered, self.go, self.reply = threading.Event(), threading.Event(), None

    def __call__(self, ask):
        self.entered.set()
        self.go.wait(5.0)
        self.reply = ask("TYP")


_SHORT = {"timeout_s": 0.25, "write_timeout_s": 0.05, "min_interval_s": 0.0}


def test_an_exchange_past_the_close_s_wait_stops_without_touching_the_descriptor(served, tmp_path):
    """A query on a closed link reopens it and checks the device: two exchanges, past one's worst
    case. The close, past its wait, closes the port under it; a file opened right after takes the
    port's descriptor number; the check's exchange then stops at its next step: nothing goes into
    that file, nothing to the controller, and the query fails as a lost link, not reconnected."""
    model, server = served
    link = SerialTransport(server.url, **_SHORT, retries=0)
    opened, check = [], _StalledCheck()
    try:
        assert link.query("TYP") == "TYP L8121-01"
        link._close_port()  # as a lost link leaves it: the next query reopens and checks
        link.on_reconnect = check
        thread, out = in_thread(lambda: link.query("STS"))
        assert check.entered.wait(2.0)
        number = link._serial.fd
        before = len(model.commands)
        t0 = time.monotonic()
        link.close()
        closed_s = time.monotonic() - t0
        opened = _files_on(number, tmp_path)
        assert opened[-1][0] == number
        check.go.set()
        thread.join(3.0)
        assert not thread.is_alive()
        for _, file in opened:
            with open(file, "rb") as f:
                assert f.read() == b"", "a command went into a file that took the port's descriptor"
        assert model.commands[before:] == []
        raised = out.get("raised")
        assert isinstance(raised, DeviceError) and not isinstance(raised, NoReply), out
        assert "link was closed" in str(raised), str(raised)
        bound = close_wait_s(**_SHORT)
        assert bound <= closed_s <= bound + _SLACK_S  # waited its bound, not for the stalled check
        assert not link.is_open and link._hold is None
    finally:
        check.go.set()
        for fd, _ in opened:
            os.close(fd)
        link.close()


def test_a_running_switch_off_is_not_cut_short_by_a_close(served):
    """The switch-off (XOF) as the running exchange, in a reconnect longer than one exchange's
    worst case: the close waits for it to reach the controller and end, then closes."""
    model, server = served
    link = SerialTransport(server.url, **_SHORT, retries=0)
    check = _StalledCheck()
    try:
        assert link.query("TYP") == "TYP L8121-01"
        link._close_port()
        link.on_reconnect = check
        thread, out = in_thread(lambda: link.query("XOF"))
        assert check.entered.wait(2.0)
        stall_s = close_wait_s(**_SHORT) + 0.2  # past a plain exchange's wait
        t0 = time.monotonic()  # before the timer: the check is let go no sooner than stall_s after it
        threading.Timer(stall_s, check.go.set).start()
        link.close()
        closed_s = time.monotonic() - t0
        thread.join(3.0)
        assert out.get("reply") == "XOF", out
        assert model.commands[-1] == "XOF"
        assert closed_s >= stall_s
        assert not link.is_open
    finally:
        check.go.set()
        link.close()


def test_a_close_from_a_signal_handler_in_the_exchange_s_own_thread_does_not_deadlock(served):
    """A signal handler that closes the link, run in the very thread whose exchange holds it (in
    its read): the close does not wait for its own thread; the exchange stops at its next step
    as a lost link, and the port is closed."""
    import signal

    model, server = served
    link = SerialTransport(server.url, timeout_s=2.0, write_timeout_s=0.05, min_interval_s=0.0, retries=0)
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: link.close())
    try:
        model.hold_once()  # no reply: the exchange reads until its time-out
        timer = threading.Timer(0.2, signal.pthread_kill, (threading.main_thread().ident, signal.SIGUSR1))
        timer.start()
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="link was closed|closed under") as caught:
            link.query("STS")
        assert not isinstance(caught.value, NoReply)
        assert time.monotonic() - t0 < 2.0  # stopped at its next step, not at its 2 s time-out
        assert not link.is_open and link._hold is None
    finally:
        signal.signal(signal.SIGUSR1, previous)
        link.close()


def test_a_close_from_a_signal_handler_during_its_own_thread_s_switch_off_leaves_it_to_its_end(served):
    """The handler's close lands in the running switch-off's reconnect check, in the same thread:
    the switch-off is not cut short (XOF reaches the controller, its reply read); the port is
    closed as its query ends."""
    import signal

    model, server = served
    link = SerialTransport(server.url, **_SHORT, retries=0)
    check = _StalledCheck()
    handled = []

    def handler(signum, frame):
        handled.append(link.is_open)
        link.close()

    previous = signal.signal(signal.SIGUSR1, handler)
    try:
        assert link.query("TYP") == "TYP L8121-01"
        link._close_port()
        link.on_reconnect = check

        def fire():
            if check.entered.wait(2.0):
                signal.pthread_kill(threading.main_thread().ident, signal.SIGUSR1)
                time.sleep(0.1)
            check.go.set()

        threading.Thread(target=fire, daemon=True).start()
        assert link.query("XOF") == "XOF"
        assert handled == [True]  # the handler ran within the switch-off, the port open
        assert model.commands[-1] == "XOF" and check.reply == "TYP L8121-01"
        assert not link.is_open and link._hold is None
    finally:
        check.go.set()
        signal.signal(signal.SIGUSR1, previous)
        link.close()
