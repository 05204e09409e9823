"""The compression series of the paper: darks, flats, then radiographs at 15 / 20 / 25 % compression.

The protocol is data (TOML), the devices are swappable (the lab's L8121, vendor-software folder
and manual frame, or the virtual bench with the L8121 emulator on a pseudo-terminal), and the
order of work is fixed::

    connect -> checks (TYP, interlock, warm-up state) -> warm up if needed
    -> darks (tube off) -> flats (phantom out, tube on, tube off, phantom in)
    -> for each step: compress (tube off), settle, tube on, acquire, tube off
    -> close

Safety and data, as ``../shared/hardware/L8121.md`` and DESIGN.md ask:

- the tube is switched off (``XOF``, confirmed by ``STS``) on every exit path -- normal end,
  exception, Ctrl-C, lost detector, full disk, unparseable reply -- and before every wait for a
  person (moving the screws, taking the phantom out);
- while X-rays are on a monitor thread polls the source (``SAR``/``SIN`` every ``poll_s``) and on
  overload, interlock or a dropped beam switches the tube off at once and stops the series;
- every serial exchange, phase and fault is logged to ``<output>.log`` beside the file (the lab
  notebook);
- every frame is appended and flushed to the experiment file as it arrives, with image_key,
  step, ratio, measured gap, the measured kV and uA at that moment and its time stamp; a crash
  loses at most the frame in flight;
- ``resume=True`` reopens an interrupted file, checks that it was written by the same protocol,
  and takes only what is missing.

Example (the virtual bench, seconds; a dry run needs no devices)::

    >>> from acquisition.protocols import load_protocol, plan
    >>> p = load_protocol('''
    ... output = "exp.h5"
    ... [source]
    ... voltage_kv = 60
    ... current_ua = 250
    ... [series]
    ... darks = 4
    ... flats = 4
    ... frames_per_step = 2
    ... steps = [0.15, 0.20, 0.25]
    ... settle_s = 30
    ... ''')
    >>> pl = plan(p)
    >>> pl.n_frames, round(pl.beam_on_s)
    (14, 25)
"""
from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acquisition.errors import DetectorTimeout, DeviceError, SourceFault

__all__ = ["Protocol", "SourceSettings", "DetectorSettings", "FrameSettings", "SeriesSettings", "SimSettings",
           "load_protocol", "plan", "Plan", "run", "Result", "Devices", "lab_devices", "sim_devices",
           "ProtocolError", "PHASES"]

log = logging.getLogger("acquisition.protocol")

PHASES = ("connect", "warm-up", "darks", "flats", "steps", "close")


class ProtocolError(DeviceError):
    """A protocol that cannot run as written (bad TOML, a file that belongs to another protocol)."""


# -- the protocol as data ---------------------------------------------------------------------------

@dataclass
class SourceSettings:
    """The X-ray source: link, exposure and limits (``acquisition.l8121.L8121`` configuration)."""
    port: str = ""                  # device path, socket://host:port or rfc2217://...; --sim ignores it
    baudrate: int | None = None     # None: the dialect's (A 38400, B 9600); [source] dialect = "A" | "B" | "auto"
    voltage_kv: float = 60.0        # the paper: 60 kV, 250 uA
    current_ua: float = 250.0
    focus: int | None = None        # CFS mode, None = leave as is
    warmup_timeout_s: float = 1800.0
    warmup_estimate_s: float = 600.0  # for the dry run's duration only
    poll_s: float = 0.25            # beam monitor period while X-rays are on
    limits: dict = field(default_factory=dict)  # kv_max, ua_max, watts_max, ... (driver config)


@dataclass
class DetectorSettings:
    """Where frames come from: ``folder`` (the vendor software writes files) or ``sim``."""
    kind: str = "folder"
    folder: str = ""
    pattern: str = "*.tif"
    shape: tuple | None = None      # (rows, cols), checked on every frame when given
    preset: str | None = None       # raw-file geometry preset (radiokit.io.PRESETS)
    timeout_s: float = 30.0
    discard_first: bool = False     # the C7942's first frame after an external-trigger start is invalid
    frame_period_s: float = 0.5     # 2 fps at 1x1; the dry run's estimate and SimDetector's pace
    pixel_size_mm: float = 0.05


@dataclass
class FrameSettings:
    """The compression frame: ``manual`` (operator turns the screws) or ``sim``."""
    kind: str = "manual"
    initial_height_mm: float = 40.0
    interactive: bool = True
    move_estimate_s: float = 60.0   # operator time per step, for the dry run


@dataclass
class SeriesSettings:
    darks: int = 10
    flats: int = 10
    frames_per_step: int = 5
    steps: tuple = (0.15, 0.20, 0.25)  # compression ratios, 1 - gap / initial height
    settle_s: float = 60.0          # gel relaxation after each compression, tube off


@dataclass
class SimSettings:
    """The virtual bench used with ``--sim``."""
    scene: str = "seed-breast"      # preset name or TOML path
    binning: int | None = None
    seed: int = 0
    warmup_s: float = 2.0           # the emulated source's warm-up
    ramp_s: float = 0.3             # its kV / uA ramp after XON
    warmed_up: bool = False         # start the emulator already warm
    frame_period_s: float = 0.0     # SimDetector's pace (0: as fast as it renders)


@dataclass
class Protocol:
    output: str = "experiment.h5"
    name: str = "compression-series"
    source: SourceSettings = field(default_factory=SourceSettings)
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    frame: FrameSettings = field(default_factory=FrameSettings)
    series: SeriesSettings = field(default_factory=SeriesSettings)
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self):
        s = self.series
        if s.darks < 0 or s.flats < 0 or s.frames_per_step < 1:
            raise ProtocolError(f"series: darks {s.darks} and flats {s.flats} must be >= 0, "
                                f"frames_per_step {s.frames_per_step} >= 1")
        steps = tuple(float(r) for r in s.steps)
        if not steps or any(not 0 <= r < 0.9 for r in steps) or list(steps) != sorted(set(steps)):
            raise ProtocolError(f"series.steps {list(s.steps)}: expected increasing compression ratios in [0, 0.9)")
        s.steps = steps
        if s.settle_s < 0:
            raise ProtocolError(f"series.settle_s {s.settle_s}: expected >= 0")
        if self.detector.kind not in ("folder", "sim"):
            raise ProtocolError(f"detector.kind {self.detector.kind!r}: expected 'folder' or 'sim'")
        if self.frame.kind not in ("manual", "sim"):
            raise ProtocolError(f"frame.kind {self.frame.kind!r}: expected 'manual' or 'sim'")
        if self.frame.initial_height_mm <= 0:
            raise ProtocolError(f"frame.initial_height_mm {self.frame.initial_height_mm}: expected > 0")
        if self.detector.shape is not None:
            self.detector.shape = tuple(int(v) for v in self.detector.shape)

    def to_toml(self) -> str:
        """The protocol as TOML (what the experiment file stores, and what ``--resume`` checks)."""
        return _to_toml(dataclasses.asdict(self))


_SECTIONS = {"source": SourceSettings, "detector": DetectorSettings, "frame": FrameSettings,
             "series": SeriesSettings, "sim": SimSettings}


def load_protocol(source) -> Protocol:
    """A :class:`Protocol` from a TOML file path, TOML text, or a dict. Unknown keys are errors
    (a typo must not silently fall back to a default exposure)."""
    where = "protocol"
    if isinstance(source, dict):
        data = source
    else:
        text = str(source)
        if "\n" not in text and "=" not in text:
            where = text
            try:
                text = Path(text).read_text()
            except OSError as exc:
                raise ProtocolError(f"{where}: cannot read the protocol ({exc.strerror or exc})") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ProtocolError(f"{where}: not valid TOML: {exc}") from None
    top = {}
    for key, value in data.items():
        if key in _SECTIONS:
            cls = _SECTIONS[key]
            names = {f.name for f in dataclasses.fields(cls)}
            if key == "source":  # driver limits may sit in the section itself
                limits = {k: v for k, v in value.items() if k not in names}
                value = {k: v for k, v in value.items() if k in names}
                value.setdefault("limits", {}).update(limits)
            unknown = set(value) - names
            if unknown:
                raise ProtocolError(f"{where}: unknown key(s) in [{key}]: {', '.join(sorted(unknown))}; "
                                    f"expected some of {', '.join(sorted(names))}")
            top[key] = cls(**value)
        elif key in ("output", "name"):
            top[key] = value
        else:
            raise ProtocolError(f"{where}: unknown key {key!r}; expected output, name or a section "
                                f"[{'], ['.join(_SECTIONS)}]")
    try:
        return Protocol(**top)
    except TypeError as exc:
        raise ProtocolError(f"{where}: {exc}") from None


def _to_toml(d: dict) -> str:
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        raise TypeError(v)

    def table(prefix, t):  # a table's values, then its sub-tables
        lines = [f"{k} = {val(v)}" for k, v in t.items() if not isinstance(v, dict) and v is not None]
        for k, v in t.items():
            if isinstance(v, dict):
                name = f"{prefix}.{k}" if prefix else k
                lines += [f"\n[{name}]"] + table(name, v)
        return lines

    lines = table("", d)
    return "\n".join(lines) + "\n"


# -- the plan (and the dry run) ------------------------------------------------------------------

@dataclass
class Plan:
    """What a run will do: ``rows`` of (phase, what, frames, seconds, beam-on seconds)."""
    rows: list
    n_frames: int
    duration_s: float
    beam_on_s: float

    def table(self) -> str:
        out = [f"{'phase':<10} {'what':<48} {'frames':>6} {'time':>9} {'beam on':>9}"]
        for phase, what, n, secs, beam in self.rows:
            out.append(f"{phase:<10} {what:<48} {n:>6} {_hms(secs):>9} {_hms(beam):>9}")
        out.append(f"{'total':<10} {'':<48} {self.n_frames:>6} {_hms(self.duration_s):>9} {_hms(self.beam_on_s):>9}")
        return "\n".join(out)


def _hms(s):
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def plan(protocol: Protocol, done: dict | None = None, *, warm: bool = False) -> Plan:
    """The run's phases with estimated durations and beam-on time. ``done`` (from a file being
    resumed) removes what is already there; ``warm=True`` leaves out the warm-up."""
    p = protocol
    done = done or {}
    period = p.detector.frame_period_s
    ramp = 5.0  # XON until the measured kV/uA are stable, per beam-on period (estimate)
    rows = []
    if not warm:
        rows.append(("warm-up", "if the source needs it", 0, p.source.warmup_estimate_s, 0.0))
    nd = max(0, p.series.darks - done.get("darks", 0))
    if nd:
        rows.append(("darks", "tube off", nd, nd * period, 0.0))
    nf = max(0, p.series.flats - done.get("flats", 0))
    if nf:
        t = nf * period + ramp
        person = 2 * p.frame.move_estimate_s if p.frame.kind == "manual" else 0.0
        rows.append(("flats", f"phantom out, {p.source.voltage_kv:g} kV {p.source.current_ua:g} uA, phantom in",
                     nf, t + person, t))
    h0 = p.frame.initial_height_mm
    for i, r in enumerate(p.series.steps, start=1):
        n = max(0, p.series.frames_per_step - done.get("steps", {}).get(i, 0))
        if n:
            t = n * period + ramp
            rows.append((f"step {i}", f"{100 * r:g} %: gap {h0 * (1 - r):.3f} mm, settle {p.series.settle_s:g} s",
                         n, p.frame.move_estimate_s + p.series.settle_s + t, t))
    return Plan(rows, sum(r[2] for r in rows), sum(r[3] for r in rows), sum(r[4] for r in rows))


# -- devices ---------------------------------------------------------------------------------------

@dataclass
class Devices:
    """The three instruments a series needs, and what to close after it (emulator servers)."""
    source: object
    detector: object
    frame: object
    closers: list = field(default_factory=list)
    emulator: object = None  # the emulated controller's model, when simulated (for tests and the demo)
    bench: object = None
    off_done: bool = False    # the run's final switch-off has been attempted
    off_failed: bool = False  # ... and could not be confirmed

    def close(self):
        src_close = getattr(self.source, "close", None)
        if self.off_failed and hasattr(self.source, "detach"):
            src_close = self.source.detach  # XOF was tried and not confirmed: do not wait it out again
        for fn in (src_close, getattr(self.detector, "close", None), *self.closers[::-1]):
            if fn is None:
                continue
            try:
                fn()
            except Exception as exc:  # closing must not hide the error that ended the run
                log.warning("closing %s: %s", fn, exc)


def _source_config(p: Protocol) -> dict:
    cfg = dict(p.source.limits)
    cfg.setdefault("poll_s", min(0.2, p.source.poll_s))
    cfg.setdefault("warmup_timeout_s", p.source.warmup_timeout_s)
    return cfg


def lab_devices(p: Protocol) -> Devices:
    """The real bench: the L8121 on ``source.port``, the folder the vendor software writes, the
    manual frame."""
    from acquisition.detector import FolderWatcher
    from acquisition.frame import ManualFrame
    from acquisition.l8121 import L8121

    if not p.source.port:
        raise ProtocolError("source.port is empty: name the serial port (e.g. /dev/ttyUSB0) or run with --sim")
    if p.detector.kind != "folder" or not p.detector.folder:
        raise ProtocolError("detector: the lab needs kind = \"folder\" and the folder the vendor software writes to")
    if p.frame.kind != "manual":
        raise ProtocolError("frame: the lab's frame is kind = \"manual\" (a motorised stage has no driver yet)")
    detector = FolderWatcher(p.detector.folder, p.detector.pattern, shape=p.detector.shape, preset=p.detector.preset,
                             timeout_s=p.detector.timeout_s, discard_first=p.detector.discard_first)
    frame = ManualFrame(p.frame.initial_height_mm, interactive=p.frame.interactive)
    source = L8121(p.source.port, baudrate=p.source.baudrate, **_source_config(p))
    return Devices(source, detector, frame)


def sim_devices(p: Protocol, *, progress=False, bench=None) -> Devices:
    """The virtual bench: the L8121 emulator served on a pseudo-terminal and driven through the
    real serial stack, a :class:`sim.bench.VirtualBench` of ``sim.scene`` (or ``bench``, reused)
    behind a ``SimDetector`` (which sees the emulated tube's state) and a ``SimFrame``."""
    from acquisition.detector import SimDetector
    from acquisition.emulators.l8121 import L8121Model, PtyServer
    from acquisition.frame import SimFrame
    from acquisition.l8121 import L8121
    from sim.bench import VirtualBench
    from sim.scene import load_scene

    if bench is None:
        scene = load_scene(p.sim.scene)
        bench = VirtualBench(scene, binning=p.sim.binning, seed=p.sim.seed, progress=progress)
    bench.prepare(p.series.steps)  # one incremental solve for all steps (cached: a no-op when done)
    dialect = str(p.source.limits.get("dialect", "A")).upper()  # the emulator speaks the configured dialect
    model = L8121Model(dialect=dialect if dialect == "B" else "A", baudrate=p.source.baudrate,
                       warmup_s=p.sim.warmup_s, ramp_s=p.sim.ramp_s, warmed_up=p.sim.warmed_up)
    server = PtyServer(model)
    server.start()
    closers = [server.stop]
    try:
        source = L8121(server.url, baudrate=p.source.baudrate, **_source_config(p))
    except Exception:
        server.stop()
        raise

    def beam():
        kv, ua = model.measured()
        return bool(model.xray_on), float(kv), float(ua)

    detector = SimDetector(bench, beam, frame_time_s=p.sim.frame_period_s, seed=p.sim.seed)
    frame = SimFrame(bench)
    return Devices(source, detector, frame, closers, emulator=model, bench=bench)


# -- the beam monitor ----------------------------------------------------------------------------

class _BeamMonitor:
    """Polls ``source.check()`` every ``period_s`` while X-rays are on, from a thread, so a fault
    switches the tube off within a poll period whatever the main thread is doing (waiting for a
    frame, writing one). The latest measured (kV, uA) go into each frame's metadata. The driver's
    ``check()`` itself switches the tube off before raising :class:`SourceFault`."""

    def __init__(self, source, period_s):
        self.source = source
        self.period_s = float(period_s)
        self.error = None
        self.kv = self.ua = float("nan")
        self.last_ok = 0.0  # time.time() just before the last poll that found the beam good
        self.written = []   # (file index, frame time) of the frames taken in this beam period
        self.off_failed = False
        self._stop = threading.Event()
        self._thread = None

    def start(self, kv, ua):
        self.kv, self.ua = kv, ua
        self.error = None
        self.written = []
        self.last_ok = time.time()  # on() has just confirmed the beam
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="beam-monitor", daemon=True)
        self._thread.start()

    def _loop(self):
        while not self._stop.wait(self.period_s):
            t = time.time()
            try:
                reading = self.source.check()
                self.last_ok = t
            except BaseException as exc:  # a fault, a silent controller, garbage: stop the series
                self.error = exc
                try:
                    self.source.off()
                except Exception as off_exc:
                    self.off_failed = True
                    log.error("switching the tube off after %s failed: %s", exc, off_exc)
                return
            self.kv, self.ua = _kv_ua(reading, self.kv, self.ua)

    def raise_if_failed(self):
        if self.error is not None:
            raise self.error

    def confirm(self):
        """One synchronous poll: if the beam is still good, every frame so far is vouched for; if
        not, the error is recorded (and raised) like the thread's."""
        t = time.time()
        try:
            reading = self.source.check()
        except BaseException as exc:
            self.error = exc
            raise
        self.last_ok = t
        self.kv, self.ua = _kv_ua(reading, self.kv, self.ua)

    def suspect(self):
        """File indices of this beam period's frames taken after the last good poll: once the
        beam has failed, nobody can say they were exposed as asked."""
        return [i for i, t in self.written if t > self.last_ok]

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            # a monitor that found a fault may be switching off through a slow controller: wait for
            # it rather than race it for the link
            self._thread.join(timeout=120.0)
            self._thread = None


# -- the run ---------------------------------------------------------------------------------------

@dataclass
class Result:
    """What a run did: the file, frames written this run and in all, timings, the phase reached."""
    output: str
    frames_written: int
    frames_total: int
    seconds: float
    beam_on_s: float
    phase: str
    per_frame_overhead_s: list = field(default_factory=list)
    resumed: bool = False


def _existing(path: Path, protocol: Protocol) -> dict:
    """What an interrupted file already holds: {'darks': n, 'flats': n, 'steps': {i: n}}; checks
    it was written by the same protocol."""
    import h5py

    with h5py.File(path, "r") as h5:
        stored = h5["entry"].attrs.get("protocol") if "entry" in h5 else None
        if stored is None:
            raise ProtocolError(f"{path}: no protocol recorded in the file; not a compression series to resume")
        stored = stored.decode() if isinstance(stored, bytes) else str(stored)
        a, b = load_protocol(stored), protocol
        if (a.series != b.series or a.frame.initial_height_mm != b.frame.initial_height_mm
                or (a.source.voltage_kv, a.source.current_ua) != (b.source.voltage_kv, b.source.current_ua)):
            raise ProtocolError(f"{path}: written by a different protocol (series, frame height or exposure differ); "
                                f"resume with the protocol stored in the file")
        n = int(h5["entry"].attrs.get("frames_complete", 0))
        keys = h5["entry/instrument/detector/image_key"][:n]
        steps = h5["entry/sample/compression/step"][:n]
    from radiokit.io import ImageKey

    done = {"darks": int(np.sum(keys == ImageKey.DARK)), "flats": int(np.sum(keys == ImageKey.FLAT)), "steps": {}}
    for i in range(1, len(protocol.series.steps) + 1):
        done["steps"][i] = int(np.sum((keys == ImageKey.PROJECTION) & (steps == i)))
    return done


def run(protocol, *, sim=False, resume=False, devices: Devices | None = None, progress=True, on_phase=None,
        writer_factory=None, overwrite=False) -> Result:
    """Run a compression series (see the module docstring).

    Parameters
    ----------
    protocol : Protocol, path or TOML text
    sim : bool
        Use the virtual bench (:func:`sim_devices`) instead of the lab's devices.
    resume : bool
        Complete an interrupted file instead of starting a new one.
    devices : Devices, optional
        Instruments already built (tests, the demo); closed at the end all the same.
    on_phase : callable(phase, info), optional
        Called as each phase starts (``"connect"``, ``"warm-up"``, ``"darks"``, ``"flats"``,
        ``"step 1"``, ..., ``"close"``) and after every frame (``"frame"``, with the index).
    writer_factory : callable(path, shape, mode, **kw) -> ExperimentWriter, optional
        How the experiment file is opened (tests pass one whose disk fills).

    Raises
    ------
    SourceFault, DeviceError, DetectorTimeout, OSError, KeyboardInterrupt
        After the tube is off and the file is closed with every completed frame in it; the message
        names the fault, and the exception carries ``.result`` (what was saved).
    """
    from tqdm.auto import tqdm

    from radiokit.io import ExperimentWriter, ImageKey

    p = protocol if isinstance(protocol, Protocol) else load_protocol(protocol)
    out = Path(p.output)
    done = None
    if resume and not out.exists():
        log.warning("%s: nothing to resume (no file: the series stopped before its first frame); starting it", out)
        resume = False
    if resume:
        done = _existing(out, p)
    elif out.exists() and not overwrite:
        raise FileExistsError(f"{out}: exists; raw data is never overwritten (--resume completes it)")
    writer_factory = writer_factory or ExperimentWriter
    # the lab notebook: every serial exchange, phase and fault, beside the experiment file
    notebook = logging.FileHandler(out.with_suffix(".log"), encoding="utf-8")
    notebook.setLevel(logging.DEBUG)
    notebook.setFormatter(logging.Formatter("%(asctime)s.%(msecs)03d %(name)s %(levelname)s %(message)s",
                                            "%Y-%m-%d %H:%M:%S"))
    acq_log = logging.getLogger("acquisition")
    acq_log.addHandler(notebook)
    old_level = acq_log.level
    if acq_log.getEffectiveLevel() > logging.DEBUG:
        acq_log.setLevel(logging.DEBUG)
    user_notify = on_phase or (lambda phase, info=None: None)

    def notify(phase_name, info=None):
        if phase_name != "frame":
            bar.set_description(phase_name)
        user_notify(phase_name, info)

    t0 = time.perf_counter()
    beam_on = 0.0
    phase = "connect"
    writer = None
    res = Result(str(out), 0, 0, 0.0, 0.0, phase, resumed=bool(resume))
    pending = plan(p, done, warm=True)
    bar = tqdm(total=pending.n_frames, desc="acquire", unit="frame", disable=not progress)
    monitor = None
    t_on_ref = None
    try:
        notify("connect", None)
        if devices is None:
            devices = sim_devices(p, progress=progress) if sim else lab_devices(p)
        src, det, frm = devices.source, devices.detector, devices.frame
        monitor = _BeamMonitor(src, p.source.poll_s)
        # checks
        state = src.status()
        log.info("source state %s", state)
        if not src.interlock_closed():
            log.warning("interlock open: close the cabinet before X-rays are needed")
        phase = "warm-up"
        notify(phase, None)
        if _needs_warm_up(src):
            src.warm_up(timeout_s=p.source.warmup_timeout_s, progress=progress)
        if p.source.focus is not None:
            src.focus = int(p.source.focus)
        shape = tuple(det.shape)
        kw = dict(pixel_size_mm=getattr(det, "pixel_size_mm", p.detector.pixel_size_mm),
                  source={"name": "Hamamatsu L8121-01" + (" (emulated)" if sim else ""),
                          "voltage_kv": p.source.voltage_kv, "current_ua": p.source.current_ua},
                  title=f"radiokit compression series: {p.name}")
        writer = writer_factory(out, shape, mode="a" if resume else "w", overwrite=overwrite, **kw)
        if not resume:
            writer.h5["entry"].attrs["protocol"] = p.to_toml()
            writer.h5["entry"].attrs["devices"] = json.dumps(
                {"detector": det.describe(), "source": getattr(src, "describe", lambda: {})()}, default=str)
            writer.h5.flush()
        done = done or {"darks": 0, "flats": 0, "steps": {}}
        h0 = frm.initial_height_mm
        det.arm()

        def take(n, image_key, step=-1, ratio=None, gap=None, beam=False):
            for frame in det.acquire(n, timeout_s=p.detector.timeout_s):
                t = time.perf_counter()
                if beam:
                    monitor.raise_if_failed()
                index = writer.append(frame.data, image_key=image_key, step=step, ratio=ratio, gap_mm=gap,
                                      time_s=frame.time_s, voltage_kv=monitor.kv if beam else 0.0,
                                      current_ua=monitor.ua if beam else 0.0)
                if beam:
                    monitor.written.append((index, frame.time_s))
                res.frames_written += 1
                bar.update()
                res.per_frame_overhead_s.append(time.perf_counter() - t)
                notify("frame", writer.n_frames - 1)
                if beam:
                    monitor.raise_if_failed()

        t_on = t_on_ref = [None]

        def beam_on_(kv, ua):
            t_on[0] = time.perf_counter()
            reading = src.on(kv, ua)
            kv_m, ua_m = _kv_ua(reading, kv, ua)
            monitor.start(kv_m, ua_m)

        def beam_off():
            nonlocal beam_on
            monitor.stop()
            monitor.raise_if_failed()  # the fault itself, not what switching off then ran into
            monitor.confirm()          # the beam was good up to the last frame (faults latch)
            src.off()
            beam_on += time.perf_counter() - t_on[0]
            t_on[0] = None

        # darks, tube off
        phase = "darks"
        notify(phase, None)
        n = p.series.darks - done["darks"]
        if n > 0:
            src.off()
            take(n, ImageKey.DARK)
        # flats: phantom out, beam on, phantom back in with the tube off
        phase = "flats"
        notify(phase, None)
        n = p.series.flats - done["flats"]
        if n > 0:
            frm.sample_out()
            beam_on_(p.source.voltage_kv, p.source.current_ua)
            take(n, ImageKey.FLAT, beam=True)
            beam_off()
            frm.sample_in()
        # the compression steps
        for i, ratio in enumerate(p.series.steps, start=1):
            n = p.series.frames_per_step - done["steps"].get(i, 0)
            if n <= 0:
                continue
            phase = f"step {i}"
            notify(phase, ratio)
            gap = frm.move_to(h0 * (1 - ratio))
            measured_ratio = 1 - gap / h0
            _settle(p.series.settle_s, bar, progress)
            beam_on_(p.source.voltage_kv, p.source.current_ua)
            take(n, ImageKey.PROJECTION, step=i, ratio=measured_ratio, gap=gap, beam=True)
            beam_off()
        phase = "close"
        notify(phase, None)
        frm.stop()
    except BaseException as exc:
        res.phase = phase
        beam_period = t_on_ref is not None and t_on_ref[0] is not None
        if beam_period and monitor is not None:
            monitor._stop.set()
            if monitor.error is None and not isinstance(exc, DeviceError) or isinstance(exc, DetectorTimeout):
                # stopped for another reason (Ctrl-C, the disk, the detector): vouch for the
                # frames taken since the last poll with one more, before switching off
                try:
                    monitor.confirm()
                except BaseException as confirm_exc:
                    log.error("the source failed too: %s", confirm_exc)
            elif monitor.error is None:
                monitor.error = exc  # a source error raised in this thread (on(), check())
        _safe_off(devices, monitor)
        if beam_period:
            beam_on += time.perf_counter() - t_on_ref[0]
        if monitor is not None and monitor.error is not None and writer is not None:
            _mark_invalid(writer, monitor.suspect())
        if writer is not None:
            res.frames_total = writer.n_frames
        res.seconds = time.perf_counter() - t0
        res.beam_on_s = beam_on
        what = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else f"stopped by {type(exc).__name__}"
        log.error("%s in phase %s: %s; tube off; %d frames in %s", what, phase, exc, res.frames_total, out)
        exc.result = res
        if hasattr(exc, "add_note"):
            exc.add_note(f"{what} in phase '{phase}': the tube is off; {res.frames_total} frames are saved in {out}; "
                         f"`radiokit acquire PROTOCOL --resume` completes the series")
        raise
    finally:
        bar.close()
        acq_log.removeHandler(notebook)
        acq_log.setLevel(old_level)
        notebook.close()
        if writer is not None:
            try:
                writer.close()
            except Exception as exc:
                log.error("closing %s: %s", out, exc)
        if devices is not None:
            _safe_off(devices, monitor)
            devices.close()
    res.phase = "done"
    res.frames_total = writer.n_frames if writer is not None else 0
    res.seconds = time.perf_counter() - t0
    res.beam_on_s = beam_on
    return res


def _mark_invalid(writer, indices):
    """Label frames image_key 3 (invalid): kept, never taken for a projection or a flat."""
    if not indices:
        return
    try:
        ds = writer.h5["entry/instrument/detector/image_key"]
        for i in indices:
            ds[i] = 3
        writer.h5.flush()
        log.warning("frames %s taken after the last good beam reading: kept as image_key 3 (invalid)", indices)
    except Exception as exc:
        log.error("could not mark frames %s invalid: %s", indices, exc)


def _kv_ua(reading, kv, ua):
    if isinstance(reading, dict):  # L8121.on() / check(): measured values
        return float(reading.get("voltage_kv", kv)), float(reading.get("current_ua", ua))
    if isinstance(reading, (tuple, list)) and len(reading) >= 2:
        return float(reading[0]), float(reading[1])
    return float(kv), float(ua)


def _needs_warm_up(src) -> bool:
    state = int(src.status())
    return state in (0, 1)  # warm-up needed, warming up


def _settle(seconds, bar, progress):
    """Wait for the gel to relax, tube off, showing the countdown."""
    end = time.monotonic() + seconds
    while True:
        left = end - time.monotonic()
        if left <= 0:
            break
        if progress:
            bar.set_postfix_str(f"settling {left:.0f} s")
        time.sleep(min(0.5, left))
    if progress:
        bar.set_postfix_str("")


def _safe_off(devices, monitor):
    """Tube off, whatever happened: stop the monitor, send XOF (the driver confirms with STS).
    Once per run: a controller that could not confirm it (silent, dead) costs the driver's full
    retry budget each time, and the monitor has usually tried already."""
    if monitor is not None:
        monitor._stop.set()
    if devices is None or devices.off_done:
        return
    devices.off_done = True
    if monitor is not None and monitor.off_failed:
        devices.off_failed = True
        log.error("not switching off again: the monitor's XOF could not be confirmed either")
        return
    try:
        devices.source.off()
    except Exception as exc:
        devices.off_failed = True
        log.error("could not confirm the tube is off: %s", exc)
