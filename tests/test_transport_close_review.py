"""Review s53rvclose of :meth:`SerialTransport.close`'s wait for an exchange, on a real pty.

A close from a signal handler that lands inside this thread's own close (a second Ctrl-C as the
link is let go)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import time

import pytest

from acquisition.transport import SerialTransport, close_wait_s


class _SignalOnClose(logging.Handler):
    """Send this process ``SIGUSR1`` once, as the link logs its port closed: the signal's handler
    then runs inside the close, while it holds the exchange's lock."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.sent = False

    def emit(self, record):
        if not self.sent and record.getMessage().endswith(" closed"):
            self.sent = True
            os.kill(os.getpid(), signal.SIGUSR1)


@pytest.fixture
def kicked(request):
    """A link on a pty whose close sends this process SIGUSR1 once (:class:`_SignalOnClose`), and
    its kick."""
    master, slave = os.openpty()
    log = logging.getLogger(f"test.transport.close_review.{request.node.name}")
    log.setLevel(logging.INFO)
    log.propagate = False
    kick = _SignalOnClose()
    log.addHandler(kick)
    link = SerialTransport(os.ttyname(slave), timeout_s=0.5, write_timeout_s=0.5, min_interval_s=0.0, log=log)
    try:
        yield link, kick
    finally:
        log.removeHandler(kick)
        os.close(master)
        os.close(slave)


@contextlib.contextmanager
def _on_sigusr1(handler):
    old = signal.signal(signal.SIGUSR1, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGUSR1, old)


def test_a_close_from_a_signal_handler_inside_a_close_neither_waits_for_itself_nor_lets_go_of_its_lock(kicked):
    """Found: the inner close waited for the exchange's lock, which its own thread's outer close
    held -- ``close_wait_s`` (2.4 s at these time-outs, 4.7 s at the defaults) spent waiting for
    itself -- and then released it: another thread's exchange could start and reopen the port while
    the outer close still let go of the port's lock."""
    link, kick = kicked
    seen: dict = {}

    def handler(signum, frame):
        t0 = time.monotonic()
        link.close()
        seen["inner_s"] = time.monotonic() - t0
        seen["held_after_inner"] = link._lock.locked()

    with _on_sigusr1(handler):
        link.close()
    assert kick.sent and "inner_s" in seen, "the handler never ran inside the close"
    # nothing to wait for: the outer close is doing it; a wait would be the close's own worst case
    bound = close_wait_s(link.timeout_s, link.write_timeout_s, link.min_interval_s)
    assert seen["inner_s"] < bound / 4, (seen["inner_s"], bound)
    assert seen["held_after_inner"], "the inner close let go of the outer close's lock"
    assert not link._lock.locked() and not link.is_open


def test_a_stop_raised_inside_a_close_still_lets_go_of_the_ports_lock(kicked):
    """A stop's handler that raises (Ctrl-C) as the close logs its port closed: the port is closed,
    and this link's share of the port's lock goes all the same -- kept, another program found the
    port held by a link that was closed."""
    link, kick = kicked
    assert link._hold is not None, "a local port's lock is taken on opening"

    def handler(signum, frame):
        raise KeyboardInterrupt

    with _on_sigusr1(handler), pytest.raises(KeyboardInterrupt):
        link.close()
    assert kick.sent
    assert link._hold is None and not link.is_open and not link._lock.locked()
