"""A late reply to a command resent under the same word is not read as the resent command's own.

Dialect B does not echo its queries (``L8121.md``): ``SRL`` answers ``REMOTE``, ``STS`` answers
``STANDBY``. After a time-out the controller may still answer, in order, so the first line that
fits a resent ``SRL`` or ``STS`` may be the late reply to the first one -- taken as the resent
command's, its own reply then came during the next command: B's ``STS`` read ``'REMOTE'`` after a
reconnect (review s55), and a resent ``STS`` read the ``STANDBY`` of a state since changed.

Real pyserial on a pseudo-terminal with radiokit's emulator. ``hold_once`` holds one reply until
the client's next line: a reply that comes after the client gave up on it, as a controller slower
than the time-out answers; ``slow`` gives every reply the latency that lets the resent command's
own reply come after the next command was written (the flush before a command clears only what
has arrived by then).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

import pytest

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError, NoReply
from acquisition.l8121 import DIALECT_B, L8121, SourceState
from acquisition.transport import SerialTransport

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

# the reply time-out, and each reply's latency: shorter than it (a reply in time is read), longer
# than the command spacing (the resent command's own reply is still on its way when the next
# command goes out, past the flush before it)
TIMEOUT_S = 0.25
LATENCY_S = 0.1
FAST = dict(poll_s=0.05, min_interval_s=0.02, timeout_s=TIMEOUT_S)


def _sts_owed_then_left_on(model, src, delay: float | None = None) -> None:
    """The unit answers every command ``LATENCY_S`` late, and one ``STS`` later still: held back
    until the next command comes (``hold_once``), or ``delay`` seconds (``delay_once``). The driver
    times out on it (so it owes that ``STS`` a reply), and then the tube is switched on behind its
    back: the state the owed reply reports is stale."""
    model.slow(LATENCY_S)
    if delay is None:
        model.hold_once("STS")
    else:
        model.delay_once(delay, "STS")
    with pytest.raises(DeviceError, match="no reply to STS"):
        src.status()
    model.left_on()


def _status_once_caught_up(src):
    """``status()``, asked again once if its ``STS`` was not sent: the barrier query before it was
    answered later than a late reply is waited for (the unit still busy with the late reply), and
    the ``STS`` is not written behind it (L8121.md: never pipeline; review s56rvtx). Its reply
    showed the controller caught up: the next ``status()`` reads its own reply."""
    try:
        return src.status()
    except DeviceError as exc:
        assert "STS not sent" in str(exc), exc
        return src.status()


def _unanswered(model, ask, word: str = "STS", *, execute: bool = False) -> None:
    """``ask()`` while the controller is silent (``execute``: it still acts on what it hears): it
    must fail, no reply to ``word``; the controller answers again after."""
    model.silence(True, execute=execute)
    with pytest.raises(DeviceError, match=f"no reply to {word}"):
        ask()
    model.silence(False)


def _status_stopped_then_off(src, model, wait_for_the_moment) -> None:
    """``status()`` stopped by a SIGINT sent from another thread once ``wait_for_the_moment()``
    returns there; then ``off()``, which must confirm the tube off."""

    def stop():
        wait_for_the_moment()
        os.kill(os.getpid(), signal.SIGINT)

    watcher = threading.Thread(target=stop, daemon=True)
    watcher.start()
    with pytest.raises(KeyboardInterrupt):
        src.status()
        time.sleep(TIMEOUT_S)
    watcher.join(timeout=2)
    assert src.off().confirms_off and not model.xray_on


def test_a_late_reconnect_check_reply_is_not_read_as_the_next_commands():
    """The reviewer's case: a read error during ``SIN`` reopens the port; the reconnect check's
    ``SRL`` is answered late (held); the next query reopens and asks ``SRL`` again. The first
    ``REMOTE`` on the line is the first ``SRL``'s: read as the second's, the second's own then
    came during ``STS`` ("unparseable reply ... 'REMOTE'"), and every later reply was one behind
    (the second ``STS`` read the first's ``STANDBY``, ``DAG`` read ``STANDBY``)."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            model.slow(LATENCY_S)
            model.hold_once("SRL")  # the reconnect check's: connect's SRL is done
            model.inject_after("SIN", server.read_error)
            with pytest.raises(DeviceError, match="did not answer SRL"):
                src.interlock_closed()
            # STS and then DAG (B's status reads both): each its own reply, none one behind
            assert src.status() == SourceState.STANDBY
        finally:
            src.close()


def test_a_stale_standby_is_not_read_as_the_state_of_a_tube_switched_on_since():
    """``STS`` times out with the tube off (its ``STANDBY`` held); the tube is then switched on
    (other software, the front panel) and ``STS`` is asked again. The held ``STANDBY`` comes first:
    read as the resent ``STS``'s, a tube emitting was reported off -- the false-safe reading a
    switch-off's confirmation must never get."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            _sts_owed_then_left_on(model, src)
            assert src.status() == SourceState.XRAY_ON
        finally:
            model.slow(0)
            src.close()


def test_a_stale_standby_never_confirms_a_switch_off():
    """As above, but the next thing the driver does is switch off: ``XOF``, then ``STS`` until it
    reads a state that cannot emit. The held ``STANDBY`` (from before the tube went on) comes at
    ``XOF``, and must not be taken as the confirmation: ``off()`` returns only once the controller
    itself says so, after the ``XOF`` -- every ``STS`` that confirmed was asked after it."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    model.ramp_down(0.15)  # the supply takes a while to fall: the first STS after XOF reads XON
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            _sts_owed_then_left_on(model, src)
            n = len(model.log)
            assert src.off() in (SourceState.STANDBY, SourceState.WARMUP_NEEDED)
            after = model.log[n:]
            first_xof = next(i for i, e in enumerate(after) if e.command == "XOF")
            confirming = [e for e in after[first_xof:] if e.command == "STS" and e.reply == "STANDBY"]
            assert confirming and not model.xray_on, [(e.command, e.reply) for e in after]
        finally:
            model.slow(0)
            src.close()


def test_a_reply_slower_than_the_time_out_is_not_read_as_the_resent_querys():
    """No held reply, only timing: one ``STS`` answered ``2 * TIMEOUT_S`` late (a controller busy
    for a moment), past the driver's time-out and its wait for a late reply, so it comes while the
    resent ``STS`` waits. The emulator answers in order, as L8121.md's controller does ("one
    command, one reply"): the case is not an artefact of ``hold_once``."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.1)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            _sts_owed_then_left_on(model, src, delay=2 * TIMEOUT_S)
            assert _status_once_caught_up(src) == SourceState.XRAY_ON
        finally:
            model.slow(0)
            src.close()


def test_a_stop_while_a_reply_is_held_back_switches_off_promptly(sigint_default):
    """One ``STS`` is never answered (the controller lost it); the next ``STS``'s own reply fits
    both it and the one owed, so the transport holds it back for a second line. A stop (SIGINT,
    raised as KeyboardInterrupt) landing in that wait must leave a switch-off as prompt as any
    other: the reply was already read, and the wait for it to complete cost the rest of a reply
    time-out, confirmation well past a quarter of one (review s55rvlate)."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        src._transport.late_barriers = ()  # the hold, as when the barrier query goes unanswered
        try:
            model.left_on()
            _unanswered(model, src.status, execute=True)
            n, kill = len(model.log), {}

            def stop_once_answered():
                while not any(e.command == "STS" for e in model.log[n:]):
                    time.sleep(0.002)
                time.sleep(TIMEOUT_S / 5)  # its reply read, held back for a second line
                kill["t"] = time.monotonic()
                os.kill(os.getpid(), signal.SIGINT)

            watcher = threading.Thread(target=stop_once_answered, daemon=True)
            watcher.start()
            with pytest.raises(KeyboardInterrupt):
                src.status()
                time.sleep(TIMEOUT_S)  # (the stop comes here when nothing was held back)
            watcher.join(timeout=2)
            assert src.off().confirms_off and not model.xray_on
            took = time.monotonic() - kill["t"]
            assert took < TIMEOUT_S / 4, f"switch-off confirmed {took:.3f} s after the stop"
        finally:
            src.close()


def test_a_stop_while_a_late_reply_is_held_back_leaves_the_resent_querys_own_reply_to_the_grammar(sigint_default):
    """As above, but the line held back is the late one (``hold_once``: the first ``STS``'s
    ``STANDBY``, from before the tube was switched on) and the resent ``STS``'s own ``XON`` is
    still on its way when the stop comes. The switch-off's ``XOF`` goes out at once; that ``XON``
    then comes during its read and is discarded as the ``STS``'s (it is no echo of ``XOF``): the
    switch-off is confirmed only by an ``STS`` asked after the ``XOF``, the tube off."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        src._transport.late_barriers = ()  # the hold, as when the barrier query goes unanswered
        try:
            _sts_owed_then_left_on(model, src)
            n = len(model.log)

            def within_the_hold():
                while not any(e.command == "STS" for e in model.log[n:]):
                    time.sleep(0.002)
                # the held STANDBY is sent as the STS arrives, its own reply LATENCY_S later
                time.sleep(LATENCY_S / 3)

            _status_stopped_then_off(src, model, within_the_hold)
            after = [(e.command, e.reply) for e in model.log[n:]]
            assert after[0] == ("STS", "XON") and after[1] == ("XOF", "XOF"), after
            assert all(c == "STS" for c, _ in after[2:]) and after[-1][1] != "XON", after
        finally:
            model.slow(0)
            src.close()


# -- session 56: what the guard costs, noise within it, a reply later than its window -----------


def _b_link(url):
    """A bare link with B's reply grammar and no barrier query (as the probe's, or a driver's
    whose barrier went unanswered): the same-word guard is the hold alone."""
    link = SerialTransport(url, timeout_s=TIMEOUT_S, min_interval_s=0.02)
    link.reply_fits = DIALECT_B.reply_fits
    return link


@contextlib.contextmanager
def _b_link_after_a_lost_sts(model, url):
    """``_b_link``, its first ``STS`` never answered (the controller silent meanwhile); closed
    after the block."""
    link = _b_link(url)
    try:
        model.silence(True)
        with pytest.raises(NoReply):
            link.query("STS")
        model.silence(False)
        yield link
    finally:
        link.close()


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_the_same_query_after_a_never_answered_one_costs_less_than_a_reply_time_out(dialect):
    """One ``STS`` the controller never answers (lost); the tube is then switched on and
    ``status()`` asked again. Its reply fits the ``STS`` still owed as well as the new one, so it
    cannot be taken on its own word; waiting a reply time-out for a second line cost ``status()``
    0.10 -> 0.42 s at T = 0.25 s (2.6 s at the dialects' 2 s). Once a query of another word has
    been answered the owed reply can no longer come (the controller answers in order): the new
    ``STS`` is then unambiguous, and read within one reply time-out, as the new state."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect=dialect, **FAST)
        try:
            _unanswered(model, src.status)
            model.left_on()
            t0 = time.monotonic()
            state = src.status()
            took = time.monotonic() - t0
            assert state == SourceState.XRAY_ON
            assert took < TIMEOUT_S, f"status() took {took:.3f} s after a never-answered STS"
        finally:
            src.close()


def test_noise_between_a_late_reply_and_the_resent_querys_own_does_not_take_its_place():
    """The late ``STANDBY`` (from before the tube went on) comes as the resent ``STS`` is sent,
    then noise on the line, then the resent ``STS``'s own ``XON``. The noise fits no reply: it is
    not the second line that decides the first was late -- read so, the noise was returned as the
    reply and ``XON`` came during the next command, one behind. ``XON`` tells them apart."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        link = _b_link(server.url)
        try:
            model.slow(LATENCY_S)
            model.hold_once("STS")
            with pytest.raises(NoReply):
                link.query("STS")
            model.left_on()
            model.inject_after("STS", lambda: server.line_noise(b"#~%\r"))
            assert link.query("STS") == "XON"
            assert link.query("SRL") == "REMOTE"
        finally:
            model.slow(0)
            link.close()


def test_noise_after_a_held_reply_is_a_clean_failure_never_a_wrong_pairing():
    """One ``STS`` is never answered; the resent ``STS``'s own ``STANDBY`` comes, then noise
    within the reply time-out. The noise may be a garbled own reply (the ``STANDBY`` then late)
    or noise (the ``STANDBY`` its own): nothing tells them apart. Either the ``STANDBY`` is
    returned or the query fails -- never the noise as the reply -- and the next queries read their
    own replies."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server, _b_link_after_a_lost_sts(model, server.url) as link:
        noise = threading.Timer(LATENCY_S / 3, server.line_noise, (b"#~%\r",))
        model.inject_after("STS", noise.start)
        try:
            assert link.query("STS") == "STANDBY"
        except DeviceError as exc:
            assert "#~%" in str(exc) and "STANDBY" in str(exc), exc
        noise.join()
        assert link.query("SRL") == "REMOTE"
        assert link.query("STS") == "STANDBY"


def test_a_reply_later_than_its_window_is_not_read_as_the_resent_querys():
    """L8121.md bounds no reply's lateness (B's driver calls 2 s a missed reply, 10 s of them a
    failure). One ``STS`` is answered four time-outs late -- past the window the transport keeps
    a timed-out command owed (one time-out from its time-out) -- and the tube is switched on
    meanwhile; ``status()`` is asked again after that window, before the late ``STANDBY`` comes.
    Read as the resent ``STS``'s, a tube emitting was reported off."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            model.delay_once(4 * TIMEOUT_S, "STS")
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match="no reply to STS"):
                src.status()
            model.left_on()
            time.sleep(max(0.0, t0 + 3 * TIMEOUT_S - time.monotonic()))
            assert _status_once_caught_up(src) == SourceState.XRAY_ON
            assert src.status() == SourceState.XRAY_ON
        finally:
            src.close()


def test_a_stop_during_the_barrier_query_leaves_its_reply_to_the_grammar(sigint_default):
    """A stop (SIGINT) lands while the transport reads the reply to the barrier query it sent
    before a resent ``STS`` (one ``STS`` never answered, the tube left on). The switch-off's
    ``XOF`` goes out at once, the barrier's reply coming during its read is discarded (it is no
    echo of ``XOF``), and the switch-off is confirmed only by an ``STS`` asked after the ``XOF``."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            model.left_on()
            _unanswered(model, src.status, execute=True)
            model.slow(LATENCY_S / 2)  # the barrier's reply still on its way when the stop comes
            n = len(model.log)

            def in_the_barrier():
                while not model.log[n:]:
                    time.sleep(0.002)

            _status_stopped_then_off(src, model, in_the_barrier)
            assert model.log[n].command != "STS"  # the barrier, not the STS, was in flight
            after = [(e.command, e.reply) for e in model.log[n + 1 :]]
            assert after[0] == ("XOF", "XOF"), after
            assert all(c == "STS" for c, _ in after[1:]) and after[-1][1] != "XON", after
        finally:
            model.slow(0)
            src.close()


def test_a_state_from_before_the_tube_went_on_is_never_read_however_late_it_comes():
    """The limit, shown: L8121.md bounds no reply's lateness. One ``STS`` is answered eight
    time-outs late, the controller answering nothing else meanwhile (in order: every command
    sent behind it waits), and the tube is switched on just after that ``STS`` was asked. A status
    loop keeps asking all along: every ``status()`` fails (no reply) until the controller answers
    again, and none reads the ``STANDBY`` from before the tube went on -- it comes while a
    question of the ``STS`` word is still unanswered, whatever its age, and that is cleared only
    by a reply that comes after it. Then the loop reads the tube on."""
    timeout_s = 0.1
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", poll_s=0.05, min_interval_s=0.02, timeout_s=timeout_s)
        try:
            model.delay_once(8 * timeout_s, "STS")
            t0, read = time.monotonic(), []
            with pytest.raises(DeviceError, match="no reply to STS"):
                src.status()
            model.left_on()
            while time.monotonic() < t0 + 12 * timeout_s and read[-2:] != [SourceState.XRAY_ON] * 2:
                try:
                    read.append(src.status())
                except DeviceError as exc:
                    read.append(str(exc).split(": ", 1)[-1][:40])
            assert SourceState.STANDBY not in read, read
            assert read[-2:] == [SourceState.XRAY_ON] * 2, read
        finally:
            src.close()


# -- review s56rvtx ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_switch_off_after_a_silent_one_is_not_held_back_a_reply_time_out(dialect):
    """The controller falls silent with the tube on (a dead receive line): ``off()`` cannot
    confirm (its ``XOF`` and ``STS`` unanswered). It answers again, and ``off()`` is called again.
    The ``XOF`` word was still counted unanswered, past its window, so the new ``XOF``'s echo was
    held back a whole reply time-out for a second line (confirmed 0.12 -> 0.42 s at T = 0.25 s, 2 s
    more at the dialects' 2 s) -- though an echo reports no state that a late one could make
    stale, and the ``STS`` asked after it is what confirms. The confirmation takes two short
    exchanges, well within one reply time-out."""
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect=dialect, off_attempts=1, **FAST)
        try:
            model.left_on()
            model.silence(True)
            with pytest.raises(DeviceError, match="could not confirm"):
                src.off()
            model.silence(False)
            n, t0 = len(model.log), time.monotonic()
            assert src.off().confirms_off and not model.xray_on
            took = time.monotonic() - t0
            assert [e.command for e in model.log[n:]] == ["XOF", "STS"]
            assert took < TIMEOUT_S, f"off() took {took:.3f} s after a silent one"
        finally:
            src.close()


def test_a_stop_in_the_reply_check_after_a_reply_past_its_window_costs_the_switch_off_no_time_out():
    """One ``STS`` is never answered and its window passes (nothing owed; the word still counted
    unanswered). The next query's reply is read, and a stop lands in the driver's reply check
    (``reply_fits``, the callback in which a stop can land: injected there, as
    tests/test_l8121_stop_anywhere.py does). The line had already left the receive buffer, so the
    ``XOF`` after the stop waited a whole reply time-out for the interrupted query's reply, read
    and gone (the s55 defect, back in this state); kept in the buffer until decided, it is
    discarded at once."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server, _b_link_after_a_lost_sts(model, server.url) as link:
        time.sleep(TIMEOUT_S + 0.05)  # past the STS's window (a time-out from its own): nothing owed
        grammar, armed = link.reply_fits, [True]

        def stop_in_the_check(command, reply):
            if armed and command == "SIN":
                armed.clear()
                raise KeyboardInterrupt
            return grammar(command, reply)

        link.reply_fits = stop_in_the_check
        with pytest.raises(KeyboardInterrupt):
            link.query("SIN")
        t0 = time.monotonic()
        assert link.query("XOF") == "XOF"
        took = time.monotonic() - t0
        assert took < TIMEOUT_S / 4, f"XOF answered {took:.3f} s after the stop"


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_slow_unit_is_never_sent_a_query_behind_an_unanswered_barrier(dialect):
    """A unit that answers every command within its reply time-out, but in nine tenths of it
    (B's driver allows 2 s; a unit answering in 1.5 s must not read as silent), one at a time (the
    emulator answers in order). One ``STS`` is lost; ``status()`` is asked again. The barrier query
    before it was given a quarter of a time-out (the wait for a late reply), and the ``STS`` was
    then written while the barrier was still being answered -- pipelined, against L8121.md ("one
    command, one reply ... never pipeline"): its reply, queued behind the barrier's, came past its
    own time-out, and the next three ``status()`` failed "no reply" (0.8 s each at T = 0.5 s).
    The barrier is a query, owed its reply time-out: no command is written before its reply.
    That ``status()`` may fail cleanly (its ``STS`` not sent: two slow replies would overrun the
    exchange's bound), and the next reads the state."""
    timeout_s, latency_s = 0.5, 0.45  # (the read slices' 0.1 s of slack would hide the pipelining at 0.25 s)
    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect=dialect, poll_s=0.05, min_interval_s=0.02, timeout_s=timeout_s)
        try:
            _unanswered(model, src.status)
            model.slow(latency_s)
            n = len(model.log)
            with pytest.raises(DeviceError, match="STS not sent"):
                src._read("state")
            assert src._read("state") == SourceState.STANDBY
            log = model.log[n:]
            # each line received once the reply before it was sent (model time: when received)
            assert all(b.t >= a.t + latency_s for a, b in zip(log, log[1:])), [(e.command, e.t) for e in log]
        finally:
            model.slow(0)
            src.close()


def test_a_barrier_is_a_query_whose_reply_tells_it_apart_in_any_state():
    """B's ``STS`` answers ``ERROR`` as a state (pre-heating, L8121.md's table), a reply that fits
    every command: as the barrier before another word's query (the first of B's readings), it
    told nothing apart while the unit pre-heated -- a ``SIN`` asked again after a lost one waited
    for it to no purpose. A barrier is one whose reply never reads as a refusal; the ``SIN`` is
    then read within a reply time-out, as in any other state."""
    model = L8121Model(dialect="B", warmed_up=True, ramp_s=0.0)
    with PtyServer(model) as server:
        src = L8121(server.url, dialect="B", **FAST)
        try:
            model.sts_error(True)  # pre-heating, as B reports it
            _unanswered(model, src.interlock_closed, "SIN")
            n, t0 = len(model.log), time.monotonic()
            assert src.interlock_closed() is True
            took = time.monotonic() - t0
            assert model.log[n].command != "STS", [(e.command, e.reply) for e in model.log[n:]]
            assert took < TIMEOUT_S, f"interlock_closed() took {took:.3f} s after a lost SIN"
        finally:
            src.close()
