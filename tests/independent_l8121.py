"""An L8121 controller written from ``../shared/hardware/L8121.md`` alone, both dialects.

A test asset, kept apart from ``acquisition.emulators`` on purpose: it was written before reading
radiokit's driver or emulator, so the two cannot share a misreading. Where the notes leave a choice
it takes the reading that is harder on a driver, and says so (``# harder:``):

- every reply comes ``reply_s`` late (once its command word's delay in ``slow``) and in ``chunks``
  separate writes;
- a command that follows the previous reply by less than ``gap_s`` ("may need ~50 ms between
  commands") is lost, unanswered, and one sent before the last reply went out ("never pipeline")
  too -- a unit still answering (a reply late past the driver's time-out) loses the command sent
  meanwhile. An assumption: the notes say only what a driver must not do, not what a unit does
  with such a command. Both are judged by when the bytes reached the unit against the reply's
  last write, never by when this thread got to look (on a loaded machine it looked late and lost
  a command the driver had sent 60 ms after the reply, as the notes ask);
- A refuses with ``ERR`` (settings) or ``ERROR`` (state), both allowed; replies end in CR LF in A
  and CR in B ("accept both");
- after power-on the unit checks itself and pre-heats (A ``STS 6`` then ``STS 5`` with ``SPH 1``;
  B ``STS ERROR``) and then needs a warm-up;
- the retained settings at power-on are the ratings' top (150 kV, 500 uA): an ``XON``/``WUP``
  before the session set both would emit at them;
- B's warm-up (``AGING``) runs on into X-rays on at its end (``aging_then = "XON"``), and B's
  ``XON`` is not refused for an open interlock (the notes do not say it is);
- an open interlock cuts the beam and aborts a warm-up (warm-up needed again);
- a controller error (``error_code``, what ``SER`` answers) leaves ``STS`` as it was and does not
  make the unit refuse ``XON`` or ``WUP``: the notes say neither.

``Controller.log`` holds every exchange and ``Controller.emissions`` every X-ray command the
controller acted on, with the settings it acted at, so a test can check what was sent when.
"""

from __future__ import annotations

import os
import select
import termios
import threading
import time
from dataclasses import dataclass, field

KV_RANGE, UA_RANGE = (40, 150), (0, 500)  # the ratings; at most 150 kV x 500 uA = 75 W
A_STATES = {"needs_warmup": 0, "warming": 1, "standby": 2, "on": 3, "overload": 4}
A_STATES |= {"not_ready": 5, "self_test": 6, "preheat": 5}
B_STATES = {"needs_warmup": "STANDBY", "warming": "AGING", "standby": "STANDBY", "on": "XON"}
B_STATES |= {"overload": "OVER", "not_ready": "NOT READY", "self_test": "ERROR", "preheat": "ERROR"}
EMITTING = ("warming", "on")


@dataclass
class Emission:
    """An X-ray command the controller acted on, and what it knew then."""

    command: str
    kv: float
    ua: float
    set_this_session: bool
    interlock_open: bool


@dataclass
class Controller:
    """One controller on a pseudo-terminal; ``port`` is the path a driver opens."""

    dialect: str = "A"
    reply_s: float = 0.12
    chunks: int = 3
    chunk_gap_s: float = 0.01
    gap_s: float = 0.045
    self_test_s: float = 0.3
    preheat_s: float = 0.3
    warmup_s: float = 1.0
    ramp_s: float = 0.6
    aging_then: str = "XON"
    voltage_scale: int = 10
    baudrate: int = 9600
    remote: str = "REMOTE"
    silent: bool = False
    # what SER answers. L8121.md: A's "controller error code, 0 none"; B's "control-board error:
    # 0 none, 1-4 relay or internal faults". The notes relate it to no state and name no way to
    # clear it. harder: STS reads on as if nothing were wrong and XON is not refused for it
    error_code: int = 0
    # command word -> the delay of its next reply only, in place of reply_s (a unit busy for a
    # moment: a reply that comes just after the driver's time-out must not be read as the next
    # command's)
    slow: dict = field(default_factory=dict)
    log: list = field(default_factory=list)
    emissions: list = field(default_factory=list)
    lost: list = field(default_factory=list)

    def __post_init__(self):
        if self.dialect == "A":
            self.voltage_scale = 1
        self.kv, self.ua, self.set_kv, self.set_ua = 150.0, 500.0, False, False
        self.interlock_open, self.warm = False, "needed"
        self.state, self.since = "self_test", time.monotonic()
        self.beam_since = 0.0
        self.aging_step = 0
        self._lock = threading.RLock()
        self._master, slave = os.openpty()
        self.port = os.ttyname(slave)
        self._slave = slave  # kept open so the line exists before and between a driver's opens
        self._last_reply_end = 0.0
        self._stop = False
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    # -- what a test does to the unit -------------------------------------------------------
    def open_interlock(self):
        with self._lock:
            self._advance()
            self.interlock_open = True
            if self.state == "warming":
                self.warm = "needed"
            if self.dialect == "A" and self.state in EMITTING + ("standby", "needs_warmup"):
                self._to("not_ready")
            elif self.state in EMITTING:  # harder: B's STS shows no door, only the beam gone
                self._to(self._warm_state())

    def close_interlock(self):
        with self._lock:
            self.interlock_open = False
            if self.state == "not_ready":
                self._to(self._warm_state())

    def overload(self):
        with self._lock:
            self._to("overload")

    def ready(self, warmed=False):
        """Skip the power-on checks (and the warm-up, if ``warmed``)."""
        with self._lock:
            self.warm = "done" if warmed else "needed"
            self._to(self._warm_state())

    @property
    def emitting(self) -> bool:
        with self._lock:
            self._advance()
            return self.state in EMITTING

    def close(self):
        self._stop = True
        self._thread.join(2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- the state machine ------------------------------------------------------------------
    def _to(self, state):
        self.state, self.since = state, time.monotonic()
        if state in EMITTING:
            self.beam_since = self.since

    def _warm_state(self):
        return "standby" if self.warm == "done" else "needs_warmup"

    def _advance(self):
        elapsed = time.monotonic() - self.since
        if self.state == "self_test" and elapsed >= self.self_test_s:
            self._to("preheat")
        elif self.state == "preheat" and elapsed >= self.preheat_s:
            self._to("not_ready" if self.interlock_open else "needs_warmup")
        elif self.state == "warming" and elapsed >= self.warmup_s:
            self.warm = "done"
            self._to("on" if self.dialect == "B" and self.aging_then == "XON" else "standby")

    def _measured(self):
        if self.state not in EMITTING:
            return 0.0, 0.0
        frac = min(1.0, (time.monotonic() - self.beam_since) / self.ramp_s)
        return self.kv * frac, self.ua * frac

    def _emit(self, command):
        if self.state not in ("standby", "needs_warmup"):
            return False
        if self.dialect == "A" and command == "XON" and self.state != "standby":
            return False  # A: XON only from standby (interlock open is STS 5 there)
        warming = self.warm != "done" and (command == "WUP" or self.dialect == "B")
        session = self.set_kv and self.set_ua
        self.emissions.append(Emission(command, self.kv, self.ua, session, self.interlock_open))
        self._to("warming" if warming or command == "WUP" else "on")
        return True

    def _setting(self, word, arg):
        kv_word = word in ("HIV", "PHV")
        if self.dialect == "B" and (word in ("HIV", "CUR")) != (self.state == "on"):
            return False  # B: HIV/CUR while on, PHV/PCU (presets) while off
        if not arg.isdigit():
            return False
        value = int(arg) / (self.voltage_scale if kv_word else 1)
        lo, hi = KV_RANGE if kv_word else UA_RANGE
        if not lo <= value <= hi:
            return False
        if kv_word:
            self.kv = value
        else:
            self.ua = value
        self.set_kv, self.set_ua = self.set_kv or kv_word, self.set_ua or not kv_word
        return True

    def _control(self, line):
        word, _, arg = line.partition(" ")
        if self.dialect == "B" and self.remote != "REMOTE":
            return False  # harder: "remote control needs REMOTE", XOF named as no exception
        if line == "XOF":
            if self.state == "warming":
                self.warm = "needed"  # an interrupted warm-up is not done
            if self.state in EMITTING:
                self._to(self._warm_state())
            return True
        if self.state in ("self_test", "preheat"):
            return False
        if line in ("XON", "WUP") and (line == "XON" or self.dialect == "A"):
            return self._emit(line)
        if line == "RST":
            ok = self.state == "overload"
            if ok:
                self._to(self._warm_state())
            return ok
        if word in ("HIV", "CUR") or (self.dialect == "B" and word in ("PHV", "PCU")):
            return self._setting(word, arg)
        return line in ("CFS", "CFM", "CFL") if self.dialect == "B" else word == "CFS" and arg.isdigit()

    def _query_a(self, line):
        kv, ua = self._measured()
        swe = {"done": 0, "needed": 2}[self.warm] if self.state != "warming" else 1
        return {
            "STS": f"STS {A_STATES[self.state]}",
            "SAR": f"SAR {A_STATES[self.state]} {kv:.0f} {ua:.0f} 0 0 0 0",
            "SVI": f"SVI {self.kv:.0f} {self.ua:.0f}",
            "SHV": f"SHV {kv:.0f}",
            "SCU": f"SCU {ua:.0f}",
            "SIN": f"SIN {int(self.interlock_open)}",
            "SWE": f"SWE {swe}",
            "SPH": f"SPH {int(self.state == 'preheat')}",
            "SFC": "SFC 1",
            "SER": f"SER {self.error_code}",
            "TYP": "TYP L8121-01",
        }.get(line)

    def _query_b(self, line):
        kv, ua = self._measured()
        if self.state == "warming":
            self.aging_step = 1 + int(4 * (time.monotonic() - self.since) / self.warmup_s)
        ramping = self.state in EMITTING and ua < self.ua
        return {
            "STS": B_STATES[self.state],
            "SHV": f"SHV {kv:.1f}kV",
            "SCU": f"SCU {ua:.1f}uA",
            "SPV": f"SPV {self.kv:.1f}kV",
            "SPC": f"SPC {self.ua:.1f}uA",
            "SIN": "INTER LOCK OFF" if self.interlock_open else "INTER LOCK ON",
            "DAG": f"AGING 1 {self.aging_step} {'END' if self.warm == 'done' else 'YET'}",
            "SAG": "SAG 0",
            "STX": "STX 0",
            "SOV": "SOV 0",
            "SFS": "SMALL",
            "SER": f"SER {self.error_code}",
            "SRL": self.remote,
            "SRB": "BUSY" if self.state == "warming" or ramping else "READY",
        }.get(line)

    def _reply(self, line):
        with self._lock:
            self._advance()
            query = self._query_a if self.dialect == "A" else self._query_b
            reply = query(line)
            if reply is not None:
                return reply
            if self._control(line):
                return line
            word = line.partition(" ")[0]
            settings = ("HIV", "CUR") if self.dialect == "A" else ()
            return "ERR" if word in settings else "ERROR"

    # -- the link ---------------------------------------------------------------------------
    def _link_ok(self):
        """The client's line settings: 8N1 at the unit's rate (a pty carries any, so look)."""
        attrs = termios.tcgetattr(self._slave)
        speed = getattr(termios, f"B{self.baudrate}")
        cflag = attrs[2]
        eight_n_one = cflag & termios.CSIZE == termios.CS8 and not cflag & (termios.PARENB | termios.CSTOPB)
        return attrs[4] == attrs[5] == speed and eight_n_one

    def _serve(self):
        buf, drop = b"", None
        while not self._stop:
            if not select.select([self._master], [], [], 0.05)[0]:
                continue
            arrived = time.monotonic()
            data = os.read(self._master, 4096)
            if not buf and drop is None and arrived - self._last_reply_end < self.gap_s:
                drop = "too soon after the last reply"
            buf += data
            while b"\r" in buf:
                raw, buf = buf.split(b"\r", 1)
                line = raw.decode("ascii", "replace")
                if drop:
                    self.lost.append((line, drop))
                    drop = None
                    continue
                if self._exchange(line) or buf:
                    drop = "sent before the last reply (pipelined)"

    def _exchange(self, line) -> bool:
        """Answer ``line``; whether the next command had arrived before the reply's last write."""
        t = time.monotonic()
        if self.silent:
            self.log.append((t, line, None))
            return False
        good_link = self._link_ok()
        reply = self._reply(line) if good_link else None
        self.log.append((t, line, reply))
        text = reply.encode() if good_link else b"\xfe\x7f\x80"  # a baud mismatch: junk, no line end
        end = (b"\r\n" if self.dialect == "A" else b"\r") if good_link else b""
        time.sleep(self.slow.pop(line.partition(" ")[0], self.reply_s))
        # the text in pieces; the line end with the last one (a UART sends CR LF back to back)
        step = max(1, -(-len(text) // self.chunks))
        pieces = [text[i : i + step] for i in range(0, len(text), step)]
        pieces[-1] += end
        pipelined = False
        for i, piece in enumerate(pieces):
            if i:
                time.sleep(self.chunk_gap_s)
            if i == len(pieces) - 1:
                # looked at before the reply ends, and its end timed before the write: a pause of
                # this thread after the write must not make the driver's next command look early
                pipelined = bool(select.select([self._master], [], [], 0)[0])
                self._last_reply_end = time.monotonic()
            os.write(self._master, piece)
        return pipelined
