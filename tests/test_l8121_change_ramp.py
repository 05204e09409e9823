"""A setting changed while the beam is on (``L8121.set_values``): the ramp that follows, and a beam
that drops during it, through real pyserial on real pseudo-terminals, in both dialects.

``L8121.md`` says the measured values "ramp towards the set values over a few seconds after XON or
a change", not from where. The emulator's two readings (``L8121Model.ramp_after_change``): a unit
that ramps from the old values straight to the new ones ("here"), and one whose values fall to
nothing and ramp again from zero ("zero"), its current meter noisy (``meter_jitter``). A beam that
drops at the change (``drop_beam`` right after the change's last command) must be switched off
once no healthy ramp of either kind can still read it, long before the stable wait's time-out;
a healthy ramp of either kind must never be called dropped, by the wait or by a beam monitor's
``check()`` in another thread meanwhile.
"""

from __future__ import annotations

import os
import threading
import time

import pytest
from conftest import beam_monitor

from acquisition.emulators.l8121 import L8121Model, PtyServer
from acquisition.errors import DeviceError, SourceFault
from acquisition.l8121 import L8121

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals (POSIX)")

RAMP_S = 0.1  # the emulator's ramp, s: a few polls long, so a test stays well under a second
# the driver's timing for tests (the link stays real); the stable wait's time-out is long enough
# that a fault it alone catches fails the time bounds below by far, also on a loaded machine (at a
# load of 5.5 on 2 cores a B drop with a monitor polling took 1.5 s to its XOF)
TIMING = dict(poll_s=0.03, min_interval_s=0.01, stable_timeout_s=6.0)
# (before, after): down in current, the voltage alone (the current untouched), up in current
CHANGES = {"down": ((60, 250), (60, 100)), "kv_only": ((60, 250), (70, 250)), "up": ((60, 100), (60, 250))}


def _unit(dialect: str, start: str, *, fall_s: float = 0.0, jitter: float = 0.0, ramp_s=RAMP_S) -> L8121Model:
    model = L8121Model(dialect=dialect, warmed_up=True, warmup_s=0, ramp_s=ramp_s)
    model.ramp_after_change(start, fall_s=fall_s)
    model.meter_jitter(jitter)
    return model


def _xof_time(model: L8121Model) -> float:
    return next(e.t for e in model.log if e.command == "XOF")


@pytest.mark.parametrize("dialect", ["A", "B"])
@pytest.mark.parametrize("start", ["here", "zero"])
@pytest.mark.parametrize("change", ["down", "kv_only"])
def test_a_beam_that_drops_at_a_change_before_climbing_is_switched_off_before_the_stable_time_out(
    dialect, start, change
):
    """The beam drops as the change's last command is answered (an emitter failing mid-change):
    its current reads nothing from then on, while B's STS still reads XON. Before, a change down
    (250 -> 100 µA) or one of the voltage alone left it to the stable wait's time-out (15 s by
    default with the tube on): the fall rule needs a climb first. A healthy ramp of either kind
    brings the current over the drop bound within about the time the unit took after XON (its
    ramp from zero), so the switch-off comes within a small multiple of that, not the time-out."""
    before, after = CHANGES[change]
    model = _unit(dialect, start)
    dropped_at = []

    def drop():
        dropped_at.append(model.time)
        model.drop_beam()

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        t_on = src.on(*before)["seconds"]
        model.inject_after("CUR", drop)  # the change's last command (the power order sends CUR second)
        with pytest.raises(SourceFault, match=r"measured current 0 µA") as caught:
            src.set_values(*after)
        took = _xof_time(model) - dropped_at[0]
        assert "X-rays switched off" in str(caught.value) and not model.xray_on
    # the driver's own bound (twice the XON ramp, two reading gaps) is well inside this; the
    # stable wait's time-out is not
    assert took < min(TIMING["stable_timeout_s"] / 3, 4 * t_on + 1.0), (took, t_on, str(caught.value))


@pytest.mark.parametrize("dialect", ["A", "B"])
@pytest.mark.parametrize(("start", "fall_s"), [("here", 0.0), ("zero", 0.0), ("zero", RAMP_S)])
@pytest.mark.parametrize("change", ["down", "kv_only", "up"])
def test_a_healthy_ramp_on_a_jittery_meter_is_not_called_dropped_by_the_wait_nor_a_monitor(
    dialect, start, fall_s, change
):
    """A healthy unit, its current meter reading 1.9 % above and below the tube's current by turns
    (within the tolerance at every setting here), ramps to the new setting from the old values or
    again from zero (at once, or falling over as long as its ramp up takes), while a beam monitor
    polls check() in another thread. Neither the wait nor the monitor may call it dropped: the
    monitor judged a change by the lower setting's drop bound alone, and a unit that ramps from zero
    read under it at once (the closing note of session 55: untested)."""
    _changes_without_a_fault(_unit(dialect, start, fall_s=fall_s, jitter=0.019), dialect, *CHANGES[change])


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_unit_that_falls_to_nothing_slower_than_it_ramps_up_is_not_called_dropped(dialect):
    """The voltage alone changed (60 -> 70 kV) on a unit whose values fall to nothing over ten of
    its ramps up and then ramp again from zero: its current, untouched, reads under half of its
    250 µA for half the fall and half the ramp up, five ramps' time. L8121.md says nothing of how
    fast a unit falls; counted from the first reading under the drop bound, twice the ramp after
    XON called this fall a dropped beam. A value still falling is a fall under way, not a beam
    that has stopped where it dropped: the count starts where the fall ends."""
    model = _unit(dialect, "zero", fall_s=10 * RAMP_S / 2, jitter=0.019, ramp_s=RAMP_S / 2)
    _changes_without_a_fault(model, dialect, *CHANGES["kv_only"])


@pytest.mark.parametrize("change", [((60, 10), (70, 10)), ((60, 10), (60, 250))], ids=["kv_only", "up"])
def test_a_unit_falling_slowly_from_a_low_current_is_not_called_dropped(change):
    """The same slow fall as above (a unit that falls to nothing over many of its ramps up, then
    ramps again from zero), from a low current: 10 µA, its drop bound 5 µA. The count of a value
    under the bound started again only after a fall of two jitters (2 x 5 µA, the tolerance at
    the higher setting), more than the whole bound: the fall from 5 µA to nothing was counted as
    a beam stopped there, and a healthy unit was switched off (review s56rvacq: "below 50% of the
    set 10 µA for 0.21 s", allowed 0.10 s) where the same fall at 250 µA was not. Dialect A only:
    its short reading makes the allowance the tightest (the rule is the same in B)."""
    model = _unit("A", "zero", fall_s=0.8, jitter=0.019, ramp_s=RAMP_S / 4)
    _changes_without_a_fault(model, "A", *change)


@pytest.mark.parametrize("setting", [10, 20, 40, 250])
def test_the_count_under_the_drop_bound_starts_where_a_fall_ends_at_any_current(setting):
    """The ramp's judgement alone (``_RampWatch``), fed the whole-µA readings of a current that
    falls from ``setting`` to nothing over 10 s and climbs back to it over 1 s (a unit that ramps
    again from zero after a change of the voltage alone, falling over ten of its ramps), given 2 s
    under the drop bound (twice its ramp after XON): the fall
    is a fall under way however low the current, and only the time from its end counts (about
    half a second here, the climb to the bound). A beam that stays at nothing after the fall is
    still dropped once the 2 s are over."""
    from acquisition.l8121 import SourceConfig, _RampWatch

    c = SourceConfig()
    jitter = (c.tolerance_kv(60), c.tolerance_ua(setting))
    fall, climb, dt = 10.0, 1.0, 0.05

    def watch():
        return _RampWatch((60, setting), (60, setting), jitter, 0.5, after_xon=False, dwell_s=(2.0, 2.0))

    def current(t):
        return round(setting * max(0.0, 1 - t / fall) if t < fall else setting * min(1.0, (t - fall) / climb))

    healthy, stuck = watch(), watch()
    times = [k * dt for k in range(int((fall + climb) / dt) + 1)]
    assert [why for t in times if (why := healthy.see(60, current(t), t))] == []
    # stuck at nothing from the fall's end: dropped 2 s (and two reading gaps) after it, not later
    times = [k * dt for k in range(int((fall + 3.0) / dt) + 1)]
    said = [(t, why) for t in times if (why := stuck.see(60, current(t) if t < fall else 0, t))]
    assert said and "measured current 0 µA" in said[0][1]
    assert said[0][0] - fall <= 2.0 + 2 * dt + dt + 1e-9, said[0]


def _changes_without_a_fault(model: L8121Model, dialect: str, before, after) -> None:
    """on(*before), then set_values(*after) while a beam monitor polls check(): no fault from
    either, the beam stable at ``after``, then switched off."""
    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        src.on(*before)
        with beam_monitor(src, src.config.poll_s / 2) as faults:  # as a series' monitor, more often
            try:
                src.set_values(*after)
            except DeviceError as exc:
                faults.append(exc)
        _left_on_then_off(src, model, faults, after)


def _left_on_then_off(src, model: L8121Model, faults: list, after=None) -> None:
    """No fault from the change nor a monitor, the tube never switched off and (given ``after``)
    stable there; then ``off()``, the tube off."""
    try:
        assert faults == [] and model.xray_on and "XOF" not in model.commands, faults
        if after is not None:
            kv, ua = src.measured()
            assert abs(kv - after[0]) <= src.config.tolerance_kv(after[0])
            assert abs(ua - after[1]) <= src.config.tolerance_ua(after[1])
    finally:
        src.off()
    assert not model.xray_on


@pytest.mark.parametrize("dialect", ["A", "B"])
@pytest.mark.parametrize("start", ["here", "zero"])
def test_a_monitor_polling_while_a_change_drops_the_beam_leaves_the_tube_off_and_says_so_once(dialect, start):
    """A beam monitor's check() in another thread while a change (250 -> 100 µA) drops the beam:
    whichever thread sees it first switches off, the tube is off, confirmed by STS, and the change
    comes out of set_values() as that fault, before the stable wait's time-out."""
    before, after = CHANGES["down"]
    model = _unit(dialect, start)

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        src.on(*before)
        with beam_monitor(src, src.config.poll_s / 2) as faults:
            model.inject_after("CUR", model.drop_beam)
            t0 = time.monotonic()
            try:
                with pytest.raises(DeviceError) as caught:
                    src.set_values(*after)
            finally:
                took = time.monotonic() - t0
        assert not model.xray_on and src.confirmed_off is not None
        assert took < TIMING["stable_timeout_s"] / 2, (took, str(caught.value))
    # set_values() names the cause whichever thread saw it: it said "beam dropped: state STANDBY"
    # (the standby after the monitor's XOF), the current's fall said by the monitor alone
    assert "measured current 0 µA" in str(caught.value), (str(caught.value), faults)
    assert isinstance(caught.value, SourceFault) and "X-rays switched off" in str(caught.value)


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_monitors_reading_taken_during_a_change_is_judged_as_the_change_judges_it_when_late(dialect):
    """A beam monitor's check() reads the beam while set_values() ramps it (a unit that ramps
    again from zero: 0 µA of the old 250 and the new 100), and is judged only after the change has
    returned (the monitor's thread not run meanwhile: a loaded machine, the GIL). The reading was
    judged then by the new setting alone, the change's judgement gone with it: "beam dropped:
    measured current 5 µA, below 50% of the set 100 µA", a healthy unit switched off after a change
    that succeeded (review s56rvacq). The thread's delay is the one thing faked (no test can make a scheduler stall
    a thread between two lines): a wrapper holds the monitor's reading until the change is over."""
    model = _unit(dialect, "zero", ramp_s=0.2)
    held, done = [], threading.Event()

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        src.on(60, 250)
        reading = src._beam_reading

        def late_reading(**kw):
            state, kv, ua = reading(**kw)
            if threading.current_thread() is not threading.main_thread() and ua < 50 and not held:
                held.append(ua)  # a reading of the change's ramp, judged once the change is over
                done.wait(5)
            return state, kv, ua

        src._beam_reading = late_reading
        with beam_monitor(src, src.config.poll_s / 2, stop=done) as faults:
            src.set_values(60, 100)
        assert held, "the monitor read no value of the ramp"
        _left_on_then_off(src, model, faults)


@pytest.mark.parametrize("dialect", ["A", "B"])
@pytest.mark.parametrize("fault", ["open_interlock", "overload"])
def test_a_fault_a_monitor_trips_between_a_changes_commands_is_what_the_change_says(dialect, fault):
    """The interlock opens (or the tube overloads) as the change's first command is answered,
    and a beam monitor's check() switches off for it before the second goes. set_values() then
    sent its second command to the tube switched off, and said what that got: B's CUR, for a
    tube on only, "CUR 250 refused by the controller (ERROR)", the cause said by the monitor
    alone (review s56rvacq). It says the monitor's cause, and sends no setting after its XOF."""
    model = _unit(dialect, "here")

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        src.on(60, 250)
        with beam_monitor(src, 0.01):
            n = len(model.commands)
            model.inject_after("HIV", getattr(model, fault))
            # the first command's reply late: the monitor's next poll is queued by then, and goes
            # before the change's second command (one refused before any poll said only "refused")
            model.delay_once(0.15, "HIV")
            with pytest.raises(SourceFault) as caught:
                src.set_values(70, 250)
        sent = model.commands[n:]
        assert not model.xray_on and src.confirmed_off is not None, sent
    words = "interlock open" if fault == "open_interlock" else "overload"
    assert words in str(caught.value) and "X-rays switched off" in str(caught.value), (str(caught.value), sent)
    # nothing set after the switch-off (the monitor's XOF, or the change's own if it saw it first)
    after_off = sent[sent.index("XOF") :]
    assert not [c for c in after_off if c.split()[0] in ("HIV", "CUR")], sent


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_monitors_reading_judged_after_a_later_one_of_the_wait_is_not_a_fall(dialect):
    """During a change up (100 -> 250 µA, a unit that ramps again from zero), a beam monitor's
    reading of the climb's start (under the drop bound, 50 µA) is judged only after the change's
    wait has judged a later, higher one (the monitor's thread not run meanwhile). The shared watch
    took it for the latest and called the climb a fall: "beam dropped while ramping up: measured
    current 39 µA after 72 µA" (review s56rvacq). A reading is judged by when it was read. The thread's delay is the
    one thing faked, as above: a wrapper holds the monitor's reading until the wait is past it."""
    model = _unit(dialect, "zero", ramp_s=0.4)
    held, seen, done, passed = [], [], threading.Event(), threading.Event()

    with PtyServer(model) as server, L8121(server.url, dialect=dialect, **TIMING) as src:
        src.on(60, 100)
        reading = src._beam_reading

        def ordered_late(**kw):
            state, kv, ua = reading(**kw)
            if threading.current_thread() is threading.main_thread():
                seen.append(ua)
                if held and ua > held[0] + 2 * src.config.tolerance_ua(250) + 1:
                    passed.set()
                    time.sleep(2 * src.config.poll_s)  # the wait has judged it, not yet stable
            elif src._ramp_watch is not None and ua < 45 and not held:
                held.append(ua)
                passed.wait(5)  # judged after the wait's higher reading
            return state, kv, ua

        src._beam_reading = ordered_late
        with beam_monitor(src, src.config.poll_s / 2, stop=done) as faults:
            try:
                src.set_values(60, 250)
            except DeviceError as exc:
                faults.append(exc)
            finally:
                passed.set()  # a monitor's reading still held goes on before its thread is joined
        assert held and passed.is_set(), (held, seen)
        _left_on_then_off(src, model, faults)
