"""A close from another thread while a query reopens the port: the port's lock, once the close has
let it go, is not taken again by the reopening, on a real pty.

Why: the reopen renewed the link's share of the port's exclusive lock (``_open_port``, and
``_hold_opened`` after the open) without the port's step lock (``_io``), which a close past its
wait takes to mark the link closing and let the share go. A close between the reopen's check of
that mark and the renewal let go of the share, and the renewal took the lock again, after the
close had returned: another program opening the port then was refused ("held by this pid") until
the reopening noticed the close."""

from __future__ import annotations

import errno
import fcntl
import os
import threading

import pytest
from conftest import in_thread

from acquisition import transport
from acquisition.errors import DeviceError
from acquisition.transport import SerialTransport

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")


class _Watched:
    """The link's step lock (an RLock), telling ``contended`` when a thread must wait for it: how
    the test knows the close has reached it (a hook for the timing only; the lock is the real one)."""

    def __init__(self, inner, contended: threading.Event):
        self._inner, self._contended = inner, contended

    def acquire(self, blocking=True, timeout=-1):
        if self._inner.acquire(blocking=False):
            return True
        self._contended.set()
        return self._inner.acquire(blocking, timeout) if blocking else False

    def release(self):
        self._inner.release()

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def _lock_free(path: str) -> bool:
    """Whether the port's flock can be taken now (a descriptor of its own: another program's view)."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as exc:
        assert exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN), exc
        return False
    finally:
        os.close(fd)


def test_a_close_as_the_reopen_renews_the_lock_never_lets_it_be_taken_again(monkeypatch):
    """The query on a lost link reopens the port; as it renews its share of the lock, another
    thread's close (past its wait for the exchange) runs to its end or to the step lock. Then no
    flock is taken for the link once it is marked closing, the query fails (as a link closed, or unanswered where it took the step lock first), and
    the port's lock is free once both are done."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    link = SerialTransport(path, timeout_s=0.02, write_timeout_s=0.02, min_interval_s=0.0, retries=0)
    settled = threading.Event()  # the close returned, or waits for the step lock
    closer = {}
    taken_while_closing = []
    real_lock_device = transport._lock_device

    def lock_device(url, key, **kw):
        taken_while_closing.append(link._closing)
        return real_lock_device(url, key, **kw)

    try:
        link._close_port()  # as a lost link leaves it: the next query reopens, its lock's share kept
        share = link._hold
        assert share is not None and share.fd is not None
        real_renew = share.renew

        def renew():
            if not closer:
                closer["thread"], closer["out"] = in_thread(link.close)

                def done():
                    closer["thread"].join()
                    settled.set()

                threading.Thread(target=done, daemon=True).start()
                assert settled.wait(10.0), "the close neither returned nor reached the step lock"
            real_renew()

        share.renew = renew
        link._io = _Watched(link._io, settled)
        monkeypatch.setattr(transport, "_lock_device", lock_device)
        query, out = in_thread(lambda: link.query("STS"))
        query.join(10.0)
        assert closer, "the reopen never renewed the lock"
        closer["thread"].join(10.0)
        assert not query.is_alive() and not closer["thread"].is_alive()
        assert True not in taken_while_closing, "the port's lock was taken again after the close let it go"
        raised = out.get("raised")
        # which the query meets first is the scheduler's: the close marks the link closing once the
        # query lets the step lock go, and a query thread that takes it again first (a lock is not
        # fair; a loaded machine) reopens and writes STS, whose reply this silent pty never sends
        assert isinstance(raised, DeviceError), out
        assert "link was closed" in str(raised) or "no reply to STS" in str(raised), out
        assert not link.is_open and link._hold is None
        assert _lock_free(path)
    finally:
        link.close()
        os.close(master)
        os.close(slave)
