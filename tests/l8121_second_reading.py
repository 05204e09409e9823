"""A second, independent model of the L8121 controller, written from ../shared/hardware/L8121.md alone.

It serves dialect A or B on a real pseudo-terminal (``pty.openpty`` and a thread), so the driver runs
through pyserial as it would on a USB adapter. Where the notes leave a choice, the model takes the
stricter reading by default and a knob gives the other (:class:`Knobs`); every choice is named there.

It records what a bench would want to know afterwards: every exchange, whether X-rays are on, what
was set when an X-ray command was accepted, and every breach of the link rules (a command less than
~50 ms after the previous reply, a command written before the previous one was answered).
"""

from __future__ import annotations

import os
import pty
import re
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

A_STATES = {"WARMUP_NEEDED": 0, "WARMING": 1, "STANDBY": 2, "XRAY_ON": 3, "OVERLOAD": 4, "NOT_READY": 5, "SELF_TEST": 6}
B_WORDS = {
    "WARMUP_NEEDED": "STANDBY",  # B has no such state word: warm-up is read through DAG
    "WARMING": "AGING",
    "STANDBY": "STANDBY",
    "XRAY_ON": "XON",
    "OVERLOAD": "OVER",
    "NOT_READY": "NOT READY",
    "SELF_TEST": "ERROR",  # the notes' "pre-heating"
}
EMITTING = {"WARMING", "XRAY_ON"}


@dataclass
class Knobs:
    """What the notes allow a unit to do, and which reading the model takes."""

    dialect: str = "A"
    eol: bytes = b"\r"  # "Replies end in CR or CR LF"
    refusal: str = "ERROR"  # A: "ERR" or "ERROR"; B is always "ERROR"
    reply_delay_s: float = 0.0  # every reply
    slow: dict[str, float] = field(default_factory=dict)  # command word -> its reply's delay
    split_s: float = 0.0  # > 0: each reply written a few bytes at a time, this far apart
    lf_pause_s: float = 0.0  # with eol CR LF: the LF written this long after the CR (a slow firmware)
    min_gap_s: float = 0.045  # "~50 ms between commands": closer is a breach ...
    drop_fast: bool = True  # ... and the command is lost (the controller was not ready for it)
    warmup_needed: bool = False
    warmup_s: float = 0.3
    ramp_s: float = 0.2  # measured values reach the set ones this long after XON
    interlock_closed: bool = True
    remote: bool = True  # A: remote mode; B: SRL REMOTE
    srl_word: str = "LOCAL"  # B: what SRL says when not remote
    typ: str = "L8121-01"
    voltage_scale: int = 10  # B: PHV/HIV argument per kV
    self_test_s: float = 0.0  # power-on checks still running this long after start ...
    power_on_state: str = "SELF_TEST"  # ... in this state: A's 6, B's ERROR; or "NOT_READY" (A: SPH 1, pre-heating)
    # B: HIV/CUR are for X-rays on; off, the strict unit refuses them ("refuse") or takes them as presets
    b_hiv_when_off: str = "refuse"
    b_phv_when_on: str = "refuse"  # B: PHV/PCU while on: refused, or "accept" (a preset for next time)
    b_xof_needs_remote: bool = True  # B: "remote control needs REMOTE", no exception named
    b_xon_checks_interlock: bool = True  # B: the notes do not say XON is refused with the interlock open
    b_aging_ends_in: str = "STANDBY"  # or "XON": the notes do not say how AGING ends
    b_value_format: str = "{:.1f}"  # SHV/SPV number format
    b_current_format: str = "{:.0f}"  # SCU/SPC number format
    b_aging_mode: int = 1  # DAG's m: 0 none, 1 after 8 h idle, 2 one month, 3 three months
    b_busy_s: float = 0.0  # SRB says BUSY this long after start, and control commands are refused
    b_busy_srb: int = 0  # ... or for this many SRB queries, however long they take (a loaded machine)
    initial_kv: float = 40.0  # what the presets hold at power-on (left from the last session)
    initial_ua: float = 10.0
    junk_at_open: bytes = b""  # bytes waiting in the driver's input before its first command
    start_on: bool = False  # X-rays left on by other software
    start_warming: bool = False  # a warm-up started at the controller's panel, running


class Controller:
    """The controller's state machine behind a pseudo-terminal; use as a context manager."""

    def __init__(self, knobs: Knobs | None = None) -> None:
        self.k = knobs or Knobs()
        self.log: list[tuple[float, str, str | None]] = []  # (time, command, reply or None if lost)
        self.breaches: list[str] = []
        self.xray_commands: list[tuple[str, float, float]] = []  # (command, set kV, set uA) when accepted
        self.hooks: list[tuple[str, int, Callable[[Controller], None]]] = []
        self._counts: dict[str, int] = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self.t0 = time.monotonic()
        self._srb_busy_left = self.k.b_busy_srb
        self.state = "WARMUP_NEEDED" if self.k.warmup_needed else "STANDBY"
        if self.k.self_test_s > 0:
            self.state = self.k.power_on_state
        self.set_kv = self.k.initial_kv
        self.set_ua = self.k.initial_ua
        self.on_since: float | None = None
        self.warm_since: float | None = None
        self.warm_done = not self.k.warmup_needed
        self.interlock_closed = self.k.interlock_closed
        self.focus = 1
        self.focus_b = "SMALL"
        self.error_code = 0
        self.beam_dropped = False
        self.xray_on_time = 0.0
        self.drop_next: set[str] = set()  # command words whose next reply is lost
        self.hold_reply: dict[str, float] = {}  # command word -> delay of its next reply only
        if self.k.start_on:
            self._switch_on()
        if self.k.start_warming:
            self.state, self.warm_since, self.on_since = "WARMING", time.monotonic(), time.monotonic()
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)  # no echo or CR translation before pyserial configures it
        self.port = os.ttyname(self.slave)
        self._last_reply_end = 0.0
        self._thread = threading.Thread(target=self._serve, daemon=True)

    # ---- the test's side --------------------------------------------------------------------
    def __enter__(self) -> Controller:
        if self.k.junk_at_open:
            os.write(self.master, self.k.junk_at_open)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        os.close(self.master)
        os.close(self.slave)

    def when(self, word: str, nth: int, action: Callable[[Controller], None]) -> None:
        """Call *action* as the *nth* (1-based) command *word* arrives, before it is answered."""
        self.hooks.append((word, nth, action))

    def emitting(self) -> bool:
        with self._lock:
            self._advance()
            return self.state in EMITTING

    def sent(self) -> list[str]:
        return [cmd for _, cmd, _ in self.log]

    def open_interlock(self) -> None:
        with self._lock:
            self.interlock_closed = False
            if self.state in EMITTING:
                self._switch_off(abort_warmup=True)
            self.state = "NOT_READY"

    def overload(self) -> None:
        with self._lock:
            if self.state in EMITTING:
                self._switch_off(abort_warmup=True)
            self.state = "OVERLOAD"

    # ---- the physics ------------------------------------------------------------------------
    def _switch_on(self) -> None:
        self.state = "XRAY_ON"
        self.on_since = time.monotonic()

    def _switch_off(self, abort_warmup: bool) -> None:
        if self.on_since is not None:
            self.xray_on_time += time.monotonic() - self.on_since
        self.on_since = None
        if self.state == "WARMING":
            self.warm_since = None
            self.state = "WARMUP_NEEDED" if abort_warmup else "STANDBY"
        elif self.state == "XRAY_ON":
            self.state = "STANDBY"

    def _advance(self) -> None:
        now = time.monotonic()
        if self.state == self.k.power_on_state and self.k.self_test_s and now - self.t0 >= self.k.self_test_s:
            self.state = "WARMUP_NEEDED" if not self.warm_done else "STANDBY"
        if self.state == "WARMING" and self.warm_since is not None and now - self.warm_since >= self.k.warmup_s:
            self.warm_done = True
            self.warm_since = None
            if self.k.dialect == "B" and self.k.b_aging_ends_in == "XON":
                self.state = "XRAY_ON"  # still emitting: on_since runs on
            else:
                self._switch_off(abort_warmup=False)
                self.state = "STANDBY"

    def _measured(self) -> tuple[float, float]:
        if self.state == "WARMING":
            return self.set_kv, self.set_ua
        if self.state != "XRAY_ON" or self.on_since is None or self.beam_dropped:
            return 0.0, 0.0
        f = 1.0 if self.k.ramp_s <= 0 else min(1.0, (time.monotonic() - self.on_since) / self.k.ramp_s)
        return self.set_kv * f, self.set_ua * f

    def _a_state(self) -> str:
        if self.state == "STANDBY" and not self.warm_done:
            return "WARMUP_NEEDED"
        return self.state

    # ---- dialect A --------------------------------------------------------------------------
    def _reply_a(self, cmd: str) -> str:
        err = self.k.refusal
        words = cmd.split(" ")
        head, arg = words[0], words[1:]
        state = self._a_state()
        code = A_STATES[state]
        if not arg:
            kv, ua = self._measured()
            queries = {
                "STS": f"STS {code}",
                "SAR": f"SAR {code} {round(kv)} {round(ua)} 0 0 0 0",
                "SVI": f"SVI {round(self.set_kv)} {round(self.set_ua)}",
                "SHV": f"SHV {round(kv)}",
                "SCU": f"SCU {round(ua)}",
                "SIN": f"SIN {0 if self.interlock_closed else 1}",
                "SWE": f"SWE {0 if self.warm_done else (1 if state == 'WARMING' else 2)}",
                "SPH": f"SPH {int(state == 'NOT_READY' and self.k.self_test_s > 0)}",
                "SFC": f"SFC {self.focus}",
                "SER": f"SER {self.error_code}",
                "TYP": f"TYP {self.k.typ}",
            }
            if head in queries:
                return queries[head]
        if head == "XOF" and not arg:  # "always accepted"
            if self.state in EMITTING:
                self._switch_off(abort_warmup=True)
            return "XOF"
        if not self.k.remote:
            return err
        if head in ("HIV", "CUR") and len(arg) == 1 and re.fullmatch(r"\d+", arg[0]):
            value = int(arg[0])
            kv, ua = (value, self.set_ua) if head == "HIV" else (self.set_kv, value)
            if not (40 <= kv <= 150 and 0 <= ua <= 500 and kv * ua <= 75_000):
                return err
            self.set_kv, self.set_ua = kv, ua
            return cmd
        if head == "CFS" and len(arg) == 1 and arg[0] in ("0", "1", "2", "3"):
            self.focus = int(arg[0])
            return cmd
        if arg:
            return err
        if head == "XON":
            if state != "STANDBY" or not self.interlock_closed:
                return err
            self.xray_commands.append(("XON", self.set_kv, self.set_ua))
            self._switch_on()
            return "XON"
        if head == "WUP":
            if state != "WARMUP_NEEDED" or not self.interlock_closed:
                return err
            self.xray_commands.append(("WUP", self.set_kv, self.set_ua))
            self.state, self.warm_since, self.on_since = "WARMING", time.monotonic(), time.monotonic()
            return "WUP"
        if head == "RST":
            if self.state != "OVERLOAD":
                return err
            self.state = "STANDBY" if self.interlock_closed else "NOT_READY"
            return "RST"
        return err

    def _busy(self) -> bool:
        return time.monotonic() - self.t0 < self.k.b_busy_s or self._srb_busy_left > 0

    # ---- dialect B --------------------------------------------------------------------------
    def _reply_b(self, cmd: str) -> str:
        fmt = self.k.b_value_format
        kv, ua = self._measured()
        word = B_WORDS[self.state]
        queries = {
            "STS": word,
            "SHV": f"SHV {fmt.format(kv)}kV",
            "SCU": f"SCU {self.k.b_current_format.format(ua)}uA",
            "SPV": f"SPV {fmt.format(self.set_kv)}kV",
            "SPC": f"SPC {self.k.b_current_format.format(self.set_ua)}uA",
            "SIN": "INTER LOCK ON" if self.interlock_closed else "INTER LOCK OFF",
            "DAG": f"AGING {self.k.b_aging_mode} {0 if self.warm_done else 1} {'END' if self.warm_done else 'YET'}",
            "SAG": "SAG 1" if self.state == "WARMING" else "SAG 0",
            "STX": "STX 1" if self.state in EMITTING else "STX 0",
            "SOV": "SOV 1" if self.state == "OVERLOAD" else "SOV 0",
            "SFS": self.focus_b,
            "SER": f"SER {self.error_code}",
            "SRL": "REMOTE" if self.k.remote else self.k.srl_word,
            "SRB": "BUSY" if self._busy() else "READY",
        }
        if cmd == "SRB":  # counted apart: the table above is built for every command
            self._srb_busy_left = max(0, self._srb_busy_left - 1)
        if cmd in queries:
            return queries[cmd]
        head, _, arg = cmd.partition(" ")
        if cmd == "XOF":
            if self.k.b_xof_needs_remote and not self.k.remote:
                return "ERROR"
            if self.state in EMITTING:
                self._switch_off(abort_warmup=True)
            return "XOF"
        if not self.k.remote or self._busy():
            return "ERROR"
        on = self.state == "XRAY_ON"
        if head in ("PHV", "PCU", "HIV", "CUR") and re.fullmatch(r"\d+", arg):
            if head in ("PHV", "PCU") and on and self.k.b_phv_when_on == "refuse":
                return "ERROR"
            if head in ("HIV", "CUR") and not on and self.k.b_hiv_when_off == "refuse":
                return "ERROR"
            if self.state == "WARMING":
                return "ERROR"
            value = int(arg)
            new_kv = value / self.k.voltage_scale if head in ("PHV", "HIV") else self.set_kv
            new_ua = value if head in ("PCU", "CUR") else self.set_ua
            if not (40 <= new_kv <= 150 and 0 <= new_ua <= 500 and new_kv * new_ua <= 75_000):
                return "ERROR"
            self.set_kv, self.set_ua = new_kv, new_ua
            if on:
                self.on_since = time.monotonic()  # the measured values ramp again
            return cmd
        if cmd in ("CFS", "CFM", "CFL"):
            self.focus_b = {"CFS": "SMALL", "CFM": "MIDDLE", "CFL": "LARGE"}[cmd]
            return cmd
        if cmd == "XON":
            if self.state not in ("STANDBY", "WARMUP_NEEDED"):
                return "ERROR"
            if self.k.b_xon_checks_interlock and not self.interlock_closed:
                return "ERROR"
            self.xray_commands.append(("XON", self.set_kv, self.set_ua))
            if not self.warm_done:  # "XON also starts the warm-up when warm-up is needed"
                self.state, self.warm_since, self.on_since = "WARMING", time.monotonic(), time.monotonic()
            else:
                self._switch_on()
            return "XON"
        if cmd == "RST":
            if self.state != "OVERLOAD":
                return "ERROR"
            self.state = "STANDBY" if self.interlock_closed else "NOT_READY"
            return "RST"
        return "ERROR"  # the bare word `Enter` included: B's link check

    # ---- the link ---------------------------------------------------------------------------
    def _write(self, reply: str) -> None:
        data = reply.encode("ascii") + self.k.eol
        if self.k.split_s > 0:
            # a reply split across reads, the CR and LF of a CR LF in separate writes
            pieces = [data[i : i + 3] for i in range(0, len(data) - len(self.k.eol), 3)]
            pieces += [bytes([b]) for b in self.k.eol]
            for i, p in enumerate(pieces):
                if i:
                    time.sleep(self.k.split_s)
                os.write(self.master, p)
        elif self.k.lf_pause_s > 0 and data.endswith(b"\r\n"):
            os.write(self.master, data[:-1])
            time.sleep(self.k.lf_pause_s)
            os.write(self.master, b"\n")
        else:
            os.write(self.master, data)
        self._last_reply_end = time.monotonic()  # the gap counts from the reply's last byte

    def _serve(self) -> None:
        buf = b""
        first_byte_at: float | None = None
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.01)
            if not r:
                continue
            try:
                chunk = os.read(self.master, 1024)
            except OSError:
                return
            if not buf and chunk:
                first_byte_at = time.monotonic()
            buf += chunk
            while b"\r" in buf:
                line, _, buf = buf.partition(b"\r")
                arrived = first_byte_at or time.monotonic()
                first_byte_at = time.monotonic() if buf else None
                self._handle(line, arrived)

    def _handle(self, raw: bytes, arrived: float) -> None:
        cmd = raw.decode("ascii", "replace")
        t = arrived - self.t0
        gap = arrived - self._last_reply_end
        if self._last_reply_end and gap < self.k.min_gap_s:
            prev = self.log[-1][1] if self.log else None
            self.breaches.append(f"{cmd!r} {gap * 1000:.0f} ms after the reply to {prev!r} (at {t:.3f} s)")
            if self.k.drop_fast:
                self.log.append((t, cmd, None))
                return
        word = cmd.split(" ")[0]
        self._counts[word] = self._counts.get(word, 0) + 1
        for w, nth, action in self.hooks:
            if w == word and nth == self._counts[word]:
                action(self)
        with self._lock:
            self._advance()
            if cmd != cmd.strip() or cmd != cmd.upper() or not cmd:
                reply = "ERROR" if self.k.dialect == "B" else self.k.refusal
            else:
                reply = self._reply_a(cmd) if self.k.dialect == "A" else self._reply_b(cmd)
        if word in self.drop_next:
            self.drop_next.discard(word)
            self.log.append((t, cmd, None))
            return
        delay = self.hold_reply.pop(word, self.k.slow.get(word, self.k.reply_delay_s))
        if delay > 0:
            # read on while the reply is on its way: a command written now was pipelined
            end = time.monotonic() + delay
            while (left := end - time.monotonic()) > 0:
                r, _, _ = select.select([self.master], [], [], left)
                if r:
                    self.breaches.append(f"bytes written while {cmd!r} was still unanswered")
                    break
            time.sleep(max(0.0, end - time.monotonic()))
        self.log.append((t, cmd, reply))
        self._write(reply)
