"""Expected-protocol tests of the L8121 driver: the exact command sequence, per dialect, with no
pseudo-terminal and no emulator.

In the manner of ``pymeasure.test.expected_protocol``: a scripted in-memory transport lists the
(sent, reply) pairs the driver must exchange, in order; any other command, a command too many or
a pair left over fails the test. Each test reads like a page of the controller's manual: connect,
warm-up, on, off and the faults, in dialect A and in dialect B. A reply of ``None`` is a
controller that does not answer (the transport raises the time-out the serial link would).
"""

from __future__ import annotations

import contextlib

import pytest

from acquisition.errors import DeviceError, SourceFault
from acquisition.l8121 import L8121, PROBE_QUERIES, SourceState, probe


class ScriptedTransport:
    """A transport that answers from a script of exact (sent, reply) pairs and fails on anything
    else. It is a test double for the serial link, not for the controller: the test writes the
    controller's side by hand."""

    def __init__(self, pairs, port="scripted", baudrate=None):
        self.pairs, self.port, self.baudrate = list(pairs), port, baudrate
        self.sent: list[str] = []
        self.is_open = True

    def query(self, command: str) -> str:
        self.sent.append(command)
        i = len(self.sent) - 1
        assert i < len(self.pairs), f"command {command!r} sent after the script ended; sent: {self.sent}"
        expected, reply = self.pairs[i]
        assert command == expected, f"command {i}: sent {command!r}, the script expects {expected!r}; sent: {self.sent}"
        if reply is None:
            raise DeviceError(f"{self.port}: no reply to {command} within 1 s")
        return reply

    def close(self) -> None:
        self.is_open = False

    def done(self) -> bool:
        return len(self.sent) == len(self.pairs)


@contextlib.contextmanager
def expected_protocol(dialect, pairs, **config):
    """A connected driver on a :class:`ScriptedTransport`; on leaving, every pair must have been
    exchanged."""
    link = ScriptedTransport(pairs)
    # one STS per XOF (off_confirm_s 0): a script lists each exchange, not a ramp-down's polls
    src = L8121(link, dialect=dialect, **{"poll_s": 0.001, "off_confirm_s": 0.0, **config})
    yield src
    assert link.done(), f"left in the script: {link.pairs[len(link.sent) :]}"


CONNECT = {"A": [("TYP", "TYP L8121-01"), ("STS", "STS 2")], "B": [("SRL", "REMOTE"), ("STS", "STANDBY")]}
ON_60_250 = {
    "A": [
        ("STS", "STS 2"),
        ("SWE", "SWE 0"),  # standby is not taken for the warm-up done (as B's DAG)
        ("SIN", "SIN 0"),
        ("SVI", "SVI 40 0"),
        ("HIV 60", "HIV 60"),
        ("CUR 250", "CUR 250"),
        ("SVI", "SVI 60 250"),  # read back before any X-ray command
        ("SIN", "SIN 0"),  # the interlock again, last before XON
        ("SER", "SER 0"),  # and no controller error standing
        ("XON", "XON"),
        ("SAR", "SAR 3 60 250 0 0 0 0"),
        ("SIN", "SIN 0"),  # the beam is on: the interlock is watched from the first poll
    ],
    "B": [
        ("STS", "STANDBY"),
        ("DAG", "AGING 0 0 END"),
        ("SIN", "INTER LOCK ON"),
        ("SRL", "REMOTE"),
        ("SRB", "READY"),  # remote operation not BUSY (L8121.md lists SRB)
        ("SPV", "SPV 40.0kV"),
        ("SPC", "SPC 0uA"),
        ("PHV 600", "PHV 600"),
        ("PCU 250", "PCU 250"),
        ("SPV", "SPV 60.0kV"),  # read back before any X-ray command
        ("SPC", "SPC 250uA"),
        ("SIN", "INTER LOCK ON"),  # the interlock again, last before XON
        ("SER", "SER 0"),  # and no controller error standing
        ("DAG", "AGING 0 0 END"),  # and still no warm-up due: this XON would start one
        ("XON", "XON"),
        ("STS", "XON"),
        ("SHV", "SHV 60.0kV"),
        ("SCU", "SCU 250uA"),
        ("SIN", "INTER LOCK ON"),
    ],
}
OFF = {"A": [("XOF", "XOF"), ("STS", "STS 2")], "B": [("XOF", "XOF"), ("STS", "STANDBY")]}


# -- connect --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dialect", ["A", "B"])
def test_connect(dialect):
    with expected_protocol(dialect, CONNECT[dialect]) as src:
        assert src.identity == {"A": "L8121-01", "B": None}[dialect]


@pytest.mark.parametrize(
    "dialect, pairs, message",
    [
        # a connect refused for the model or the operate switch asks STS once first (a query), so
        # that the command's end knows whether the tube showed off (README: exit codes); then every
        # refused connect of a session that controls the tube sends XOF all the same, confirmed by
        # STS (other software or a crash may have left the tube on, and nobody has read it off)
        (
            "A",
            [("TYP", "TYP L8121-02"), ("STS", "STS 2"), *OFF["A"]],
            "TYP answered 'L8121-02', expected 'L8121-01'",
        ),
        (
            "A",
            [("TYP", "ERROR"), *OFF["A"]],
            r"TYP refused by the controller \(ERROR\); is this unit on 9600 baud and "
            r"speaking dialect A\? If it speaks dialect B",
        ),
        # B off REMOTE refuses its XOF (no exception to "remote control needs REMOTE"): STS shows off
        # the refused XOF: SRL first (it names LOCAL: no ramp-down window), then one STS
        (
            "B",
            [("SRL", "LOCAL"), ("STS", "STANDBY"), ("XOF", "ERROR"), ("SRL", "LOCAL"), ("STS", "STANDBY")],
            r"operate switch is LOCAL",
        ),
        ("B", [("SRL", "ERR"), *OFF["B"]], r"SRL refused by the controller \(ERR\)"),
        ("B", [("SRL", "REMOTE"), ("STS", "STS 2"), *OFF["B"]], r"unparseable reply to STS \(dialect B\): 'STS 2'"),
        (
            "A",
            [("TYP", "TYP L8121-01"), ("STS", "STANDBY"), *OFF["A"]],
            r"unparseable reply to STS \(dialect A\): 'STANDBY'",
        ),
    ],
)
def test_connect_refuses(dialect, pairs, message):
    link = ScriptedTransport(pairs)
    src = L8121(link, dialect=dialect, poll_s=0.001, off_confirm_s=0.0, connect=False)
    with pytest.raises(DeviceError, match=message):
        src.connect()
    assert link.done(), f"left in the script: {link.pairs[len(link.sent) :]}"
    assert src.tube_confirmed_off and src.confirmed_off is not None  # by the XOF's STS


def test_a_refused_connect_of_a_session_of_queries_sends_no_xof():
    """`source status` (control=False) sends queries only: its refused connect sends no XOF."""
    link = ScriptedTransport([("TYP", "TYP L8121-02"), ("STS", "STS 3")])
    src = L8121(link, dialect="A", control=False, connect=False)
    with pytest.raises(DeviceError, match="expected 'L8121-01'"):
        src.connect()
    assert link.done() and not src.tube_confirmed_off


@pytest.mark.parametrize(
    "dialect, pairs",
    [
        ("A", [("TYP", "TYP L8121-01"), ("STS", "STS 3")]),
        ("B", [("SRL", "REMOTE"), ("STS", "AGING")]),  # a warm-up someone started: X-rays on
    ],
)
def test_connect_to_an_emitting_tube_then_close_switches_off(dialect, pairs):
    with expected_protocol(dialect, pairs + OFF[dialect]) as src:
        src.close()


# -- warm-up --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "dialect, pairs",
    [
        (
            "A",
            [
                ("TYP", "TYP L8121-01"),
                ("STS", "STS 0"),
                ("STS", "STS 0"),
                ("SIN", "SIN 0"),
                # the values the warm-up emits at, set and read back first (default: the lowest)
                ("SVI", "SVI 0 0"),
                ("HIV 40", "HIV 40"),
                ("CUR 0", "CUR 0"),
                ("SVI", "SVI 40 0"),
                ("SIN", "SIN 0"),  # the interlock again, last before the start command
                ("SER", "SER 0"),  # and no controller error standing
                ("WUP", "WUP"),
                ("STS", "STS 1"),
                ("SIN", "SIN 0"),  # the warm-up emits: the interlock is watched
                ("STS", "STS 2"),
                ("SWE", "SWE 0"),  # status(): standby with the warm-up done
                ("SWE", "SWE 0"),
            ],
        ),
        (
            "B",
            [
                ("SRL", "REMOTE"),
                ("STS", "STANDBY"),
                ("STS", "STANDBY"),
                ("DAG", "AGING 1 0 YET"),
                ("SIN", "INTER LOCK ON"),
                ("SRL", "REMOTE"),  # B's warm-up starts with XON: remote control needs REMOTE
                ("SRB", "READY"),  # remote operation not BUSY (L8121.md lists SRB)
                # the XON emits at the presets: set and read back first (default: the lowest)
                ("SPV", "SPV 0.0kV"),
                ("SPC", "SPC 0uA"),
                ("PHV 400", "PHV 400"),
                ("PCU 0", "PCU 0"),
                ("SPV", "SPV 40.0kV"),
                ("SPC", "SPC 0uA"),
                ("SIN", "INTER LOCK ON"),  # the interlock again, last before the start command
                ("SER", "SER 0"),  # and no controller error standing
                ("DAG", "AGING 1 0 YET"),  # and the warm-up still due: else this XON is an exposure
                ("XON", "XON"),
                ("STS", "AGING"),
                ("SIN", "INTER LOCK ON"),
                ("STS", "STANDBY"),
                ("DAG", "AGING 0 0 END"),
                ("DAG", "AGING 0 0 END"),
            ],
        ),
    ],
)
def test_warm_up(dialect, pairs):
    with expected_protocol(dialect, pairs) as src:
        assert src.warm_up(progress=False) > 0


@pytest.mark.parametrize(
    "dialect, pairs",
    [
        ("A", CONNECT["A"] + [("STS", "STS 2"), ("SWE", "SWE 0")]),
        ("B", CONNECT["B"] + [("STS", "STANDBY"), ("DAG", "AGING 0 0 END")]),
    ],
)
def test_warm_up_when_done_only_asks(dialect, pairs):
    with expected_protocol(dialect, pairs) as src:
        assert src.warm_up(progress=False) == 0.0


def test_b_a_warm_up_xon_answered_by_an_exposure_is_switched_off():
    pairs = CONNECT["B"] + [
        ("STS", "STANDBY"),
        ("DAG", "AGING 1 0 YET"),
        ("SIN", "INTER LOCK ON"),
        ("SRL", "REMOTE"),
        ("SRB", "READY"),  # remote operation not BUSY (L8121.md lists SRB)
        ("SPV", "SPV 40.0kV"),
        ("SPC", "SPC 0uA"),
        ("PHV 400", "PHV 400"),
        ("PCU 0", "PCU 0"),
        ("SPV", "SPV 40.0kV"),
        ("SPC", "SPC 0uA"),
        ("SIN", "INTER LOCK ON"),
        ("SER", "SER 0"),
        ("DAG", "AGING 1 0 YET"),
        ("XON", "XON"),
        ("STS", "XON"),  # an exposure, not AGING
        ("XOF", "XOF"),
        ("STS", "STANDBY"),
        ("SER", "SER 0"),
    ]
    with expected_protocol("B", pairs) as src:
        with pytest.raises(
            SourceFault,
            match=r"X-rays came on as an exposure instead of a warm-up "
            r"\(STS says X-rays on\); X-rays switched off",
        ):
            src.warm_up(progress=False)


def test_b_force_warm_up_is_refused_before_any_xon():
    with expected_protocol("B", CONNECT["B"] + [("STS", "STANDBY"), ("DAG", "AGING 0 0 END")]) as src:
        with pytest.raises(DeviceError, match="that XON would be an exposure"):
            src.warm_up(force=True, progress=False)


@pytest.mark.parametrize(
    "dialect, pairs",
    [
        ("A", CONNECT["A"][:1] + [("STS", "STS 0"), ("STS", "STS 0"), ("SIN", "SIN 1")]),
        (
            "B",
            CONNECT["B"][:1]
            + [("STS", "STANDBY"), ("STS", "STANDBY"), ("DAG", "AGING 1 0 YET"), ("SIN", "INTER LOCK OFF")],
        ),
    ],
)
def test_warm_up_with_the_interlock_open_sends_no_command(dialect, pairs):
    with expected_protocol(dialect, pairs) as src:
        with pytest.raises(SourceFault, match="interlock is open"):
            src.warm_up(progress=False)


# -- on, off --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dialect", ["A", "B"])
def test_on_then_off(dialect):
    with expected_protocol(dialect, CONNECT[dialect] + ON_60_250[dialect] + OFF[dialect]) as src:
        beam = src.on(60, 250)
        assert (beam["voltage_kv"], beam["current_ua"], beam["set_voltage_kv"]) == (60.0, 250.0, 60)
        assert src.off() == SourceState.STANDBY


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_on_refuses_900_kv_before_any_byte(dialect):
    with expected_protocol(dialect, CONNECT[dialect]) as src:
        with pytest.raises(ValueError, match="voltage_kv = 900 kV is outside kv_min..kv_max = 40..150 kV"):
            src.on(900, 250)


@pytest.mark.parametrize(
    "dialect, ready, message",
    [
        ("A", [("STS", "STS 0")], "warm-up needed"),
        ("B", [("STS", "STANDBY"), ("DAG", "AGING 1 0 YET")], "warm-up needed"),  # STS alone looks ready
        # power-on checks (A self-test, B pre-heating) pass by themselves: waited for, every poll_s
        # up to ready_timeout_s (settled_status), then the state they leave is what refuses
        ("A", [("STS", "STS 6"), ("STS", "STS 6"), ("STS", "STS 0")], "warm-up needed"),
        ("B", [("STS", "ERROR"), ("STS", "ERROR"), ("STS", "STANDBY"), ("DAG", "AGING 1 0 YET")], "warm-up needed"),
        (
            "B",
            [("STS", "STANDBY"), ("DAG", "AGING 0 0 END"), ("SIN", "INTER LOCK ON"), ("SRL", "LOCAL")],
            "operate switch is LOCAL",
        ),
        ("A", [("STS", "STS 4")], "overload"),
        ("B", [("STS", "OVER")], "overload"),
    ],
)
def test_on_refused_by_queries_alone(dialect, ready, message):
    with expected_protocol(dialect, CONNECT[dialect] + ready) as src:
        with pytest.raises(DeviceError, match=message):
            src.on(60, 250)


def test_b_an_exposure_xon_answered_by_aging_is_switched_off():
    pairs = (
        CONNECT["B"]
        + ON_60_250["B"][: ON_60_250["B"].index(("XON", "XON")) + 1]
        + [
            ("STS", "AGING"),  # the controller started a warm-up instead
            ("XOF", "XOF"),
            ("STS", "STANDBY"),
            ("SER", "SER 0"),
        ]
    )
    with expected_protocol("B", pairs) as src:
        with pytest.raises(SourceFault, match=r"warming up \(AGING\) instead of emitting the exposure"):
            src.on(60, 250)


_STANDBY_READING = {
    "A": [("SAR", "SAR 2 0 0 0 0 0 0"), ("SIN", "SIN 0")],
    "B": [("STS", "STANDBY"), ("SIN", "INTER LOCK ON")],
}


def _on_with_after_xon(dialect, after):
    """ON_60_250 with ``after`` put right after the XON's echo, before the first beam reading."""
    on = ON_60_250[dialect]
    i = on.index(("XON", "XON")) + 1
    return on[:i] + after + on[i:]


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_on_waits_for_a_state_that_follows_the_xon_echo(dialect):
    """L8121.md: XON is echoed, and the measured values "ramp towards the set values over a few
    seconds after XON"; it does not say STS reads X-rays on by the time the echo is in. A unit
    whose state follows a poll later (as the switch-off allows STS to lag XOF: off_confirm_s) was
    switched off at once, "beam dropped: state STANDBY", a beam that never came on."""
    pairs = CONNECT[dialect] + _on_with_after_xon(dialect, _STANDBY_READING[dialect]) + OFF[dialect]
    with expected_protocol(dialect, pairs) as src:
        beam = src.on(60, 250)
        assert (beam["voltage_kv"], beam["current_ua"]) == (60.0, 250.0)
        assert src.off() == SourceState.STANDBY


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_beam_that_does_not_come_on_after_xon_is_said_so_and_switched_off(dialect):
    """Standby still after ``xon_start_s``: the XON was echoed and nothing came on. Switched off
    (the tube may yet follow), named for what it is, not a dropped beam."""
    on = ON_60_250[dialect]
    pairs = CONNECT[dialect] + on[: on.index(("XON", "XON")) + 1] + _STANDBY_READING[dialect]
    pairs += OFF[dialect] + [("SER", "SER 0")]
    with expected_protocol(dialect, pairs, xon_start_s=0.0) as src:
        with pytest.raises(
            SourceFault, match=r"X-rays did not come on: state STANDBY .*after XON.*X-rays switched off"
        ):
            src.on(60, 250)


@pytest.mark.parametrize("dialect", ["A", "B"])
def test_a_beam_read_on_then_standby_while_ramping_is_a_dropped_beam_at_once(dialect):
    """The wait for the state to follow XON ends with its first X-rays-on reading: standby after
    that is the beam dropping, switched off at once (xon_start_s is long here)."""
    ramping = {
        "A": [("SAR", "SAR 3 10 10 0 0 0 0"), ("SIN", "SIN 0"), ("SAR", "SAR 2 0 0 0 0 0 0")],
        "B": [("STS", "XON"), ("SHV", "SHV 10.0kV"), ("SCU", "SCU 10uA"), ("SIN", "INTER LOCK ON"), ("STS", "STANDBY")],
    }[dialect]
    on = ON_60_250[dialect]
    pairs = CONNECT[dialect] + on[: on.index(("XON", "XON")) + 1] + ramping + OFF[dialect]
    pairs += [_STANDBY_READING[dialect][1], ("SER", "SER 0")]  # SIN after the XOF, for the message
    with expected_protocol(dialect, pairs, xon_start_s=10.0) as src:
        with pytest.raises(SourceFault, match="beam dropped: state STANDBY instead of XRAY_ON; X-rays switched off"):
            src.on(60, 250)


@pytest.mark.parametrize(
    "dialect, pairs, message",
    [
        ("A", [("XOF", "XOF"), ("STS", "STS 3")] * 3, "3 attempt.*STS still XRAY_ON after XOF"),
        ("A", [("XOF", "XOF"), ("STS", "STS 1")] * 3, "3 attempt.*STS still WARMING_UP after XOF"),
        (
            "B",
            [("XOF", "XOF"), ("STS", "AGING")] * 3 + [("SRL", "REMOTE")],
            "3 attempt.*STS still WARMING_UP after XOF",
        ),
        (
            "B",
            [("XOF", "XOF"), ("STS", "ERROR")] * 3 + [("SRL", "REMOTE")],
            r"3 attempt.*STS still ERROR \(PREHEATING, or a refused query: dialect B does not say which\) after XOF",
        ),
        # a refused XOF, and SRL says why: the controller will not act, so no further attempt
        ("B", [("XOF", "ERROR"), ("SRL", "LOCAL"), ("STS", "XON")], "1 attempt.*the operate switch is LOCAL"),
        ("B", [("XOF", None), ("STS", None)] * 3 + [("SRL", None)], "3 attempt.*no reply to STS"),
    ],
)
def test_off_not_confirmed(dialect, pairs, message):
    """Only a state that cannot emit confirms ``off``; B's ``ERROR`` (pre-heating, or a refusal)
    is not one."""
    with expected_protocol(dialect, CONNECT[dialect] + pairs) as src:
        with pytest.raises(DeviceError, match=f"could not confirm X-rays off after {message}"):
            src.off()


@pytest.mark.parametrize(
    "dialect, refusal, told", [("A", [("XOF", "ERR")], []), ("B", [("XOF", "ERROR")], [("SRL", "REMOTE")])]
)
def test_a_refused_xof_without_a_reason_keeps_the_ramp_down_window(dialect, refusal, told):
    """A refused XOF whose reason the controller does not give (A has no SRL; B's says REMOTE)
    may come while a first XOF ramps the supply down: the switch-off asked one STS and went on to
    the next attempt, and a tube that went off a moment later ended on "could not confirm". Now
    the window is kept; only SRL naming another position ends it at once. (A script: the emulator
    never refuses A's XOF, which L8121.md says is always accepted.)"""
    on, off = {"A": ("STS 3", "STS 2"), "B": ("XON", "STANDBY")}[dialect]
    pairs = CONNECT[dialect] + refusal + told + [("STS", on), ("STS", off)]
    # the window (off_confirm_s / off_attempts, 10 s) is left at the second STS: no wait in the test
    with expected_protocol(dialect, pairs, off_confirm_s=30.0) as src:
        assert src.off() == SourceState.STANDBY


# -- faults while on ------------------------------------------------------------------------------
# ``poll``: what is asked before the XOF; ``after``: what is asked after the switch-off, before
# ``SER``. A fault the beam reading shows by itself (a state other than X-rays on, a collapsed
# current) is switched off at once; the interlock is asked after the XOF, for the message only.
# ``SER`` reads 0 after each: L8121.md ties no code to an interlock or an overload (session 53;
# they read SER 1 and SER 3, B's relay or internal faults).
FAULTS = [
    ("A", [("SAR", "SAR 3 60 250 0 0 0 0"), ("SIN", "SIN 1")], [], "SER 0", "interlock open"),
    (
        "B",
        [("STS", "XON"), ("SHV", "SHV 60.0kV"), ("SCU", "SCU 250uA"), ("SIN", "INTER LOCK OFF")],
        [],
        "SER 0",
        "interlock open",
    ),
    # the controller drops the beam when the interlock opens: seen in the reading, off at once
    ("A", [("SAR", "SAR 2 0 0 0 0 0 0")], [("SIN", "SIN 1")], "SER 0", "interlock open"),
    ("B", [("STS", "STANDBY")], [("SIN", "INTER LOCK OFF")], "SER 0", "interlock open"),
    ("A", [("SAR", "SAR 4 0 0 0 0 0 0")], [], "SER 0", "overload"),
    ("B", [("STS", "OVER")], [], "SER 0", "overload"),  # no SHV/SCU/SIN: off at once
    ("A", [("SAR", "SAR 3 60 0 0 0 0 0")], [("SIN", "SIN 0")], "SER 0", "beam dropped: measured current 0 µA"),
    (
        "B",
        [("STS", "XON"), ("SHV", "SHV 60.0kV"), ("SCU", "SCU 0uA")],
        [("SIN", "INTER LOCK ON")],
        "SER 0",
        "beam dropped: measured current 0 µA",
    ),
    ("B", [("STS", "STANDBY")], [("SIN", "INTER LOCK ON")], "SER 0", "beam dropped: state STANDBY"),
    # an overload between B's STS and its SCU: named by the STS after the XOF
    (
        "B",
        [("STS", "XON"), ("SHV", "SHV 0.0kV"), ("SCU", "SCU 0uA")],
        [("SIN", "INTER LOCK ON")],
        "SER 0",
        r"overload \(beam dropped: measured current 0 µA",
    ),
]


@pytest.mark.parametrize("dialect, poll, after, code, message", FAULTS)
def test_check_switches_off_on_a_fault(dialect, poll, after, code, message):
    overload = "overload" in message
    off = OFF[dialect] if not overload else [("XOF", "XOF"), ("STS", {"A": "STS 4", "B": "OVER"}[dialect])]
    pairs = CONNECT[dialect] + ON_60_250[dialect] + poll + off + after + [("SER", code)]
    with expected_protocol(dialect, pairs) as src:
        src.on(60, 250)
        with pytest.raises(SourceFault, match=f"{message}.*X-rays switched off"):
            src.check()


@pytest.mark.parametrize("dialect, poll, after, code, message", FAULTS)
def test_the_fault_scripts_ser_is_what_l8121_md_gives_the_emulator(dialect, poll, after, code, message):
    """The scripts above paired an open interlock with ``SER 1`` and an overload with ``SER 3``:
    L8121.md ties no ``SER`` code to either -- dialect A's is a "controller error code, 0 none",
    B's "1-4 relay or internal faults" of the control board -- and the emulator, which follows
    it, leaves ``SER`` as it was (0). Each script's ``SER`` is the emulator's after the same
    fault: a script must not teach the driver a code the document does not give."""
    from acquisition.emulators.l8121 import L8121Model

    model = L8121Model(dialect=dialect, warmed_up=True, ramp_s=0.0)
    for command, _ in ON_60_250[dialect]:
        model.handle(command)
    assert model.handle("STS") in ("STS 3", "XON")  # on, as the script's driver found it
    if "overload" in message:
        model.overload()
    elif "interlock" in message:
        model.open_interlock()
    else:
        model.drop_beam()
    model.handle("XOF")
    assert model.handle("SER") == code


@pytest.mark.parametrize(
    "dialect, bad",
    [
        ("A", [("SAR", "SAR 3 6O 250 0 0 0 0")]),
        ("B", [("STS", "XON"), ("SHV", "SHV 60.0")]),
        ("B", [("STS", "STS 3")]),
    ],
)
def test_an_unparseable_reply_while_on_switches_off_first(dialect, bad):
    pairs = CONNECT[dialect] + ON_60_250[dialect] + bad + OFF[dialect]
    with expected_protocol(dialect, pairs) as src:
        src.on(60, 250)
        with pytest.raises(DeviceError, match="unparseable reply"):
            src.check()


# -- the probe ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "pairs, dialect, identity",
    [
        ([("STS", "STS 2"), ("SIN", "SIN 0"), ("TYP", "TYP L8121-01"), ("SWE", "SWE 0")], "A", "L8121-01"),
        ([("STS", "STANDBY"), ("SIN", "INTER LOCK ON"), ("SRL", "REMOTE"), ("DAG", "AGING 1 0 YET")], "B", None),
        ([("STS", "ERROR"), ("SIN", "INTER LOCK OFF"), ("SRL", "LOCAL"), ("DAG", "AGING 0 0 END")], "B", None),
        # a reply that fits no dialect is asked again, once (one garbled by noise): a second misfit counts
        ([("STS", "STS 2"), ("SIN", "INTER LOCK ON"), ("SIN", "INTER LOCK ON")], None, None),  # a mix: refused
        ([("STS", "OK"), ("STS", "OK")], None, None),  # another instrument
        ([("STS", "ERROR"), ("SIN", "ERROR"), ("SIN", "ERROR")], None, None),  # refuses everything
        ([("STS", None)], None, None),  # silent: not asked again (a wrong rate would cost a time-out more)
        (
            [("STS", "S#?S"), ("STS", "STS 2"), ("SIN", "SIN 0"), ("TYP", "TYP L8121-01"), ("SWE", "SWE 0")],
            "A",
            "L8121-01",
        ),
        (
            [
                ("STS", "STANDBY"),
                ("SIN", "INTER~"),
                ("SIN", "INTER LOCK ON"),
                ("SRL", "REMOTE"),
                ("DAG", "AGING 1 0 END"),
            ],
            "B",
            None,
        ),
        ([("STS", "x7?"), ("STS", None)], None, None),  # garbled, then silent
    ],
)
def test_probe_sends_harmless_queries_only(pairs, dialect, identity):
    link = ScriptedTransport(pairs, baudrate=9600)
    result = probe(link)
    assert link.done() and set(link.sent) <= PROBE_QUERIES
    assert (result.dialect, result.identity) == (dialect, identity)
    assert [(e.sent, e.reply) for e in result.exchange] == pairs


def test_auto_probes_then_connects_in_the_dialect_found():
    pairs = [("STS", "STANDBY"), ("SIN", "INTER LOCK ON"), ("SRL", "REMOTE"), ("DAG", "AGING 0 0 END")]
    with expected_protocol("auto", pairs + CONNECT["B"]) as src:
        assert src.dialect.name == "B" and src.voltage_scale == 10


# -- the reply grammar: what tells a late reply from the next command's ----------------------------
@pytest.mark.parametrize(
    "dialect, sent, reply, fits",
    [
        ("A", "STS", "STS 2", True),
        ("A", "STS", "SIN 0", False),  # SIN's late reply, read after STS was sent
        ("A", "XOF", "XOF", True),
        ("A", "XOF", "SAR 3 60 250 0 0 0 0", False),
        ("A", "HIV 60", "HIV 060", True),
        ("A", "HIV 60", "HIV 50", False),
        ("A", "XON", "ERR", True),  # a refusal answers any command
        ("B", "STS", "STANDBY", True),
        ("B", "STS", "INTER LOCK ON", False),
        ("B", "STS", "ERROR", True),
        ("B", "SIN", "INTER LOCK ON", True),
        ("B", "XOF", "XON", False),  # XON's (or STS's) late reply is not XOF's echo
        ("B", "PHV 600", "PHV 600", True),
        ("B", "CFM", "CFM", True),
        ("B", "CFM", "MIDDLE", False),
        ("B", "SPV", "SPV 60.0kV", True),
        ("B", "SPV", "SPC 250uA", False),
        ("B", "Enter", "ERROR", True),  # a command the table does not know: no opinion
    ],
)
def test_reply_fits_the_command_by_the_dialects_grammar(dialect, sent, reply, fits):
    from acquisition.l8121 import DIALECTS

    assert DIALECTS[dialect].reply_fits(sent, reply) is fits


class _BPresetsApart:
    """Dialect B as L8121.md gives it: ``PHV``/``PCU`` set the presets (read by ``SPV``/``SPC``)
    while X-rays are off, ``HIV``/``CUR`` the tube's values while on; the notes do not say that
    one changes the other, so here neither does. Records the highest power the tube was set to."""

    def __init__(self):
        self.preset, self.tube, self.on, self.peak_w = [40.0, 0.0], [0.0, 0.0], False, 0.0
        self.port, self.baudrate, self.is_open = "b-presets", None, True

    def _set(self, values, word, arg):
        values[word in ("PCU", "CUR")] = int(arg) / (10 if word in ("PHV", "HIV") else 1)
        if self.on:
            self.peak_w = max(self.peak_w, self.tube[0] * self.tube[1] / 1000)
        return f"{word} {arg}"

    def query(self, line):
        word, _, arg = line.partition(" ")
        if word in ("PHV", "PCU") and not self.on:
            return self._set(self.preset, word, arg)
        if word in ("HIV", "CUR") and self.on:
            return self._set(self.tube, word, arg)
        if word in ("XON", "XOF"):
            self.on, self.tube = word == "XON", list(self.preset)
            self.peak_w = max(self.peak_w, self.tube[0] * self.tube[1] / 1000 if self.on else 0)
            return word
        kv, ua = self.tube if self.on else (0, 0)
        replies = {
            "SRL": "REMOTE",
            "STS": "XON" if self.on else "STANDBY",
            "DAG": "AGING 1 0 END",
            "SIN": "INTER LOCK ON",
            "SER": "SER 0",
            "SPV": f"SPV {self.preset[0]:.1f}kV",
            "SPC": f"SPC {self.preset[1]:.0f}uA",
            "SHV": f"SHV {kv:.1f}kV",
            "SCU": f"SCU {ua:.0f}uA",
        }
        return replies.get(word, "ERROR")

    def close(self):
        self.is_open = False


def test_b_a_change_while_on_orders_its_commands_by_the_tube_values_not_the_presets():
    """At watts_max 30: on at 60 kV 250 µA, then 60 kV 500 µA (30 W), then 100 kV 200 µA (20 W).
    The order of HIV and CUR was chosen from SPV/SPC, which in B read the presets (still 250 µA),
    not the 500 µA HIV/CUR had set: HIV 1000 went first and asked the tube for 100 kV at 500 µA,
    50 W, beyond the configured 30 W."""
    link = _BPresetsApart()
    with L8121(link, dialect="B", poll_s=0.001, off_confirm_s=0.0, watts_max=30) as src:
        src.on(60, 250)
        src.set_values(60, 500)
        src.set_values(100, 200)
        assert link.tube == [100, 200]
    assert not link.on and link.peak_w <= 30 + 1e-9, link.peak_w
