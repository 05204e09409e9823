"""The compression series of the paper: darks, flats, then radiographs at 15 / 20 / 25 % compression.

The protocol is data (TOML), the devices are swappable (the lab's L8121, vendor-software folder
and manual frame, or the virtual bench with the L8121 emulator on a pseudo-terminal), and the
order of work is fixed::

    connect -> checks (TYP, interlock, warm-up state, room for a frame) -> warm up if needed
    (after a frame from the panel, tube off, not stored: no X-rays before the panel delivers)
    -> darks (tube off), judged -> flats (phantom out, tube on, tube off), judged, phantom in
    -> for each step: compress (tube off), settle, tube on, acquire, tube off
    -> close

Each phase is a small function over one ``_Run`` state; :func:`run` drives them in one loop,
and that loop owns the tube-off guarantee.

Safety and data, as ``../shared/hardware/L8121.md`` and DESIGN.md ask:

- the protocol is checked at load: every number finite, the exposure within the protocol's limits
  and the L8121's ratings (which a protocol may only tighten), no unknown key -- so a dry run
  refuses what a run would;
- the first thing a run or resume does is ask ``STS`` and switch X-rays off if they are on (a
  resume of a complete file opens no device);
- the tube is switched off (``XOF``, confirmed by ``STS``) on every exit path -- normal end,
  exception, Ctrl-C, Ctrl-\\, Ctrl-Z, SIGTERM, SIGHUP, lost detector, full disk, unparseable reply -- and before
  every wait for a person (moving the screws, taking the phantom out). No signal interrupts the
  switch-off (:class:`acquisition.guardian.SignalGuard`). ``Result.tube_off`` says whether it was
  confirmed. On the lab's port (and ``[sim] source_port``), a guardian process holds the link and
  switches off if this process is killed outright (:mod:`acquisition.guardian`);
- while X-rays are on a monitor thread polls the source (``SAR``/``SIN`` every ``poll_s``, ``SER``
  at most every second) and on overload, interlock, a dropped beam (or one far above its setting)
  or a controller error code switches the tube off at once and stops the series;
- every serial exchange, phase and fault is logged to ``<output>.log`` beside the file (the lab
  notebook);
- every frame is appended and flushed to the experiment file as it arrives, with image_key,
  step, ratio, measured gap, the measured kV and uA at that moment and its time stamp. It is
  labelled invalid until its pixels are on disk, so a crash or a full disk leaves at most one
  invalid frame, never a blank one labelled complete;
- the darks, then the darks with the flats, are judged as soon as they are taken by the rules
  ``radiokit calibrate`` applies (:func:`radiokit.calibrate.judge_frames`): a warning is told; a
  refusal (a flat clipped at the ADC's top, flats not brighter than the darks, most of the panel
  defective) labels the frames it names invalid (kept) -- the flats, the darks when they read
  brighter than the flats, both when the darks fill over half the ADC's range -- and stops the
  series before any compression step, the tube off, with :class:`~acquisition.errors.FramesRefused`
  saying what to change;
- ``resume=True`` reopens an interrupted file, checks that it was written by the same protocol
  (the stored TOML, never read as a path), and takes only what is missing: frames labelled
  invalid are taken again.

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
    >>> pl.n_frames, round(pl.beam_on_s)  # the warm-up's 600 s estimate emits too
    (14, 625)
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import os
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import tomli_w

from acquisition.errors import DetectorTimeout, DeviceError
from radiokit.checks import is_integer, is_number, shown, shown_name, toml_loads

__all__ = [
    "Protocol",
    "SourceSettings",
    "DetectorSettings",
    "FrameSettings",
    "SeriesSettings",
    "SimSettings",
    "load_protocol",
    "plan",
    "Plan",
    "run",
    "Result",
    "Devices",
    "lab_devices",
    "check_lab",
    "check_sim",
    "sim_devices",
    "ProtocolError",
    "PHASES",
]

log = logging.getLogger("acquisition.protocol")

PHASES = ("connect", "warm-up", "darks", "flats", "steps", "close")

#: What a series on the virtual bench first imported with X-rays on (the frames' projection, at
#: the first frame with the phantom in the beam), imported as its connect begins instead
#: (:func:`_import_ahead`). Why: a stop signal that lands inside an import waits for the import's
#: end (:func:`radiokit.interrupts.after_import`), the tube on if it is. A lab series, a tube found
#: on at the connect, ``source on`` and ``source warm-up`` import nothing while X-rays may be on
#: (session 49); what a series imports between its beam periods (the judgement's numpy.ma, OpenCV,
#: scipy.ndimage) waits with the tube off, and a stop swallowed there is raised again before the
#: next X-ray command (:meth:`~acquisition.guardian.SignalGuard.raise_if_lost`).
#: tests/test_safety.py records what a run first imports with X-rays possibly on: nothing.
_SIM_IMPORTS = ("sim.imaging", "sim.xray")


class ProtocolError(DeviceError):
    """A protocol that cannot run as written (bad TOML, a file that belongs to another protocol)."""


# -- the protocol as data ---------------------------------------------------------------------------


@dataclass
class SourceSettings:
    """The X-ray source: link, exposure and limits (``acquisition.l8121.L8121`` configuration)."""

    port: str = ""  # device path, socket://host:port or rfc2217://...; --sim ignores it
    baudrate: int | None = None  # None: the dialect's (9600 in both, L8121.md); [source] dialect = "A" | "B" | "auto"
    voltage_kv: float = 60.0  # the paper: 60 kV, 250 uA
    current_ua: float = 250.0
    focus: int | None = None  # CFS mode, None = leave as is
    warmup_timeout_s: float = 1800.0
    warmup_estimate_s: float = 600.0  # for the dry run's duration only
    poll_s: float = 0.25  # beam monitor period while X-rays are on
    # the guardian switches off when no poll has come for this long while X-rays may be on (the
    # process suspended or hung); at least 4 poll periods; 0: no watchdog (a debugger's pauses)
    watchdog_s: float = 5.0
    limits: dict = field(default_factory=dict)  # kv_max, ua_max, watts_max, ... (driver config)


@dataclass
class DetectorSettings:
    """Where frames come from: ``folder`` (the vendor software writes files) or ``sim``."""

    kind: str = "folder"
    folder: str = ""
    pattern: str = "*.tif"
    shape: tuple | None = None  # (rows, cols), checked on every frame when given
    preset: str | None = None  # raw-file geometry preset (radiokit.io.PRESETS)
    timeout_s: float = 30.0
    discard_first: bool = False  # the C7942's first frame after an external-trigger start is invalid
    # frames dropped at the start of every batch (darks, flats, each step), after the frames the
    # folder already holds: the vendor software may save continuously, and the frame in flight
    # when the tube or the phantom changed saw both states (1: it writes each frame on read-out)
    discard_after_change: int = 1
    # a frame file is complete once its size and time stamp have held this long (and it reads):
    # longer on a network share whose writes pause
    settle_s: float = 0.2
    # the panel's ADC depth: a value beyond it stops the run (C7942: 12; C9730DK/C9732DK: 14),
    # and the experiment file records it (NeXus bit_depth_readout) when it is not 12
    bits: int = 12
    frame_period_s: float = 0.5  # 2 fps at 1x1; the dry run's estimate and SimDetector's pace
    # the panel's pitch at the frames' binning; None: the preset's, else 0.05 mm times the binning
    # a 2240 / 1120 / 560 column width implies (a cropped frame needs it given)
    pixel_size_mm: float | None = None
    # the panel's rated tube voltage (C7942.md: 20-100 kVp for the C7942SK-02); the L8121 goes to
    # 150 kV, so the source's ratings alone would let a protocol expose the panel beyond its own
    kvp_max: float = 100.0


@dataclass
class FrameSettings:
    """The compression frame: ``manual`` (operator turns the screws) or ``sim``."""

    kind: str = "manual"
    initial_height_mm: float = 40.0
    interactive: bool = True
    move_estimate_s: float = 60.0  # operator time per step, for the dry run


@dataclass
class SeriesSettings:
    darks: int = 10
    flats: int = 10
    frames_per_step: int = 5
    steps: tuple = (0.15, 0.20, 0.25)  # compression ratios, 1 - gap / initial height
    settle_s: float = 60.0  # gel relaxation after each compression, tube off


@dataclass
class SimSettings:
    """The virtual bench used with ``--sim``."""

    scene: str = "seed-breast"  # preset name or TOML path
    # the virtual panel's binning (None: the scene's) at [source]'s kV and uA: a binned pixel sums
    # binning^2 pixels' charge and clips at 4095 as the C7942 does, so bin at a lower current
    binning: int | None = None
    seed: int = 0
    warmup_s: float = 2.0  # the emulated source's warm-up
    # the wait after each compression on the virtual bench, in place of [series] settle_s: a solved
    # scene is in equilibrium at once (nothing relaxes), so none unless a rehearsal of the lab's waits
    settle_s: float = 0.0
    ramp_s: float = 0.3  # its kV / uA ramp after XON
    warmed_up: bool = False  # start the emulator already warm
    frame_period_s: float = 0.0  # SimDetector's pace (0: as fast as it renders)
    source_port: str = ""  # drive the emulator already serving here (tests), through the guardian


#: The exposure a protocol's ``[source]`` may leave out: it then runs at :class:`SourceSettings`'
#: defaults, the paper's 60 kV and 250 uA (taken, not refused: protocols written so rely on it),
#: and ``radiokit acquire`` says so before anything is sent (:attr:`Protocol.unstated_exposure`).
EXPOSURE_KEYS = ("voltage_kv", "current_ua")


@dataclass
class Protocol:
    #: the keys of :data:`EXPOSURE_KEYS` the protocol's text left to the defaults
    #: (:func:`load_protocol` sets it; not a setting: never written back, never compared)
    unstated_exposure: ClassVar[tuple] = ()

    output: str = "experiment.h5"
    name: str = "compression-series"
    source: SourceSettings = field(default_factory=SourceSettings)
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    frame: FrameSettings = field(default_factory=FrameSettings)
    series: SeriesSettings = field(default_factory=SeriesSettings)
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self):
        if isinstance(self.output, os.PathLike):  # the Python API's Path: the TOML stores text
            self.output = os.fspath(self.output)
        if not isinstance(self.output, str) or not self.output:
            raise ProtocolError(f"output = {self.output!r}: expected a file name (a string)")
        if not isinstance(self.name, str):
            raise ProtocolError(f"name = {self.name!r}: expected a string")
        for name, section in (
            ("source", self.source),
            ("detector", self.detector),
            ("frame", self.frame),
            ("series", self.series),
            ("sim", self.sim),
        ):
            _check_numbers(name, section)
        s = self.series
        if s.frames_per_step < 1:  # (darks and flats < 0: refused with every number above)
            raise ProtocolError(f"[series] frames_per_step = {s.frames_per_step!r}: expected at least 1")
        self._check_batches()
        self._check_times()
        s.steps = _checked_steps(s.steps)
        if self.detector.kind not in ("folder", "sim"):
            raise ProtocolError(f"detector.kind {self.detector.kind!r}: expected 'folder' or 'sim'")
        if self.frame.kind not in ("manual", "sim"):
            raise ProtocolError(f"frame.kind {self.frame.kind!r}: expected 'manual' or 'sim'")
        if self.frame.initial_height_mm <= 0:
            raise ProtocolError(f"frame.initial_height_mm {self.frame.initial_height_mm}: expected > 0")
        _check_geometry(self.detector)
        d = self.detector
        if d.kind == "folder" and d.folder and d.shape is None and d.preset is None:
            # the experiment file is sized before the first frame arrives, and after the warm-up,
            # which emits: an unknown frame size must stop the run before any X-ray command
            raise ProtocolError(
                f"[detector] folder = {d.folder!r} needs the frame size: shape = [rows, cols] or a "
                f'preset (e.g. preset = "c7942" for 2240 x 2240 raw or TIFF frames)'
            )
        if not 1 <= d.bits <= 16:
            raise ProtocolError(
                f"[detector] bits = {d.bits!r}: expected the panel's ADC bits, 1 to 16 (frames are uint16)"
            )
        if d.pixel_size_mm is not None:
            from radiokit.io import PIXEL_SIZE_RANGE_M

            # the experiment file refuses the same range when the run opens it: a dry run must too
            lo, hi = (v * 1e3 for v in PIXEL_SIZE_RANGE_M)
            size = d.pixel_size_mm  # already a finite number (bools and text refused where it was read)
            if not lo <= size <= hi:
                raise ProtocolError(
                    f"[detector] pixel_size_mm = {size!r}: expected the panel's pitch in mm, {lo:g} to {hi:g} "
                    "(the C7942's is 0.05)"
                )
        _check_source(self.source)
        if _whole(self.source.voltage_kv) > d.kvp_max:  # what the driver sends
            raise ProtocolError(
                f"[source] voltage_kv = {shown(self.source.voltage_kv)} exceeds the panel's rating "
                f"([detector] kvp_max = {shown(d.kvp_max)} kVp; the C7942SK-02 is rated 20-100 kVp)"
            )

    def _check_batches(self) -> None:
        """Each batch's counts within :data:`FRAMES_PER_BATCH_MAX`, and its wait for a frame within
        :data:`WATCHDOG_MAX_S`."""
        for section, key in _BATCH_COUNTS:
            n = getattr(getattr(self, section), key)
            if n > FRAMES_PER_BATCH_MAX:
                raise ProtocolError(
                    f"[{section}] {key} = {n}: at most {FRAMES_PER_BATCH_MAX} frames in one batch (at the C7942's "
                    "full resolution 83 min of read-out, for flats and steps of X-rays, and 100 GB; the paper "
                    "took 5 a step)"
                )
        wait = self.detector.timeout_s
        if wait == 0:  # every frame of a flat's batch "timed out" at once, the tube switched on for it
            raise ProtocolError(
                "[detector] timeout_s = 0: expected a number of seconds above 0 (the wait for each frame)"
            )
        if wait > WATCHDOG_MAX_S:
            # each frame of a flat's or a step's batch is waited for with X-rays on, the beam
            # monitor's polls feeding the watchdog: a lost panel must end the beam no later than
            # a hung run's would (1e300 kept it on for ever; the C7942's slowest frame is 10 s)
            raise ProtocolError(
                f"[detector] timeout_s = {shown(wait)} s: at most {WATCHDOG_MAX_S:g} s (each frame is waited "
                "for with X-rays on; the longest a hung run may keep them on, as [source] watchdog_s)"
            )

    def _check_times(self) -> None:
        """Each wait and estimate of the protocol's own within :data:`PROTOCOL_TIME_LIMITS` (the
        source's are :data:`acquisition.l8121.TIME_LIMITS`'), and a frame file's settle within the
        wait for it."""
        for (section, key), limit in PROTOCOL_TIME_LIMITS.items():
            value = getattr(getattr(self, section), key)  # a finite number >= 0 (_check_numbers)
            if value > limit.max_s:
                raise ProtocolError(f"[{section}] {key} = {shown(value)} s: at most {limit.max_s:g} s ({limit.why})")
        d = self.detector
        if d.settle_s >= d.timeout_s:
            # a file is taken once it has held still for settle_s, and waited for timeout_s: one
            # that settles no sooner than the wait ends timed out every frame, X-rays on
            raise ProtocolError(
                f"[detector] settle_s = {shown(d.settle_s)} s: expected less than [detector] timeout_s = "
                f"{shown(d.timeout_s)} s (a frame file is taken once it has held still this long, and "
                "waited for no longer than timeout_s)"
            )

    def settle_s(self, virtual: bool) -> float:
        """The wait after each compression, tube off: the gel's relaxation in the lab (``[series]``),
        the virtual bench's own (``[sim]``)."""
        return self.sim.settle_s if virtual else self.series.settle_s

    def to_toml(self) -> str:
        """The protocol as TOML (what the experiment file stores, and what ``--resume`` checks)."""
        return tomli_w.dumps(dataclasses.asdict(self, dict_factory=_without_none))


def _checked_steps(steps) -> tuple:
    """``[series] steps`` as a tuple of floats, or ProtocolError naming the key ("x" among them
    ended in float()'s words, naming neither file nor key)."""
    said = f"[series] steps = {steps!r}: expected increasing compression ratios in [0, 0.9)"
    if not isinstance(steps, (list, tuple)):
        raise ProtocolError(said)
    if not all(is_number(r) for r in steps):
        raise ProtocolError(f"[series] steps = {list(steps)!r}: expected increasing compression ratios in [0, 0.9)")
    ratios = tuple(float(r) for r in steps)
    if not ratios or any(not 0 <= r < 0.9 for r in ratios) or list(ratios) != sorted(set(ratios)):
        hint = ""
        if ratios and all(1 <= r <= 100 for r in ratios if math.isfinite(r)):  # 15 meant 15 %
            hint = f" (percentages? write {[round(r / 100, 6) for r in ratios]})"
        raise ProtocolError(
            f"[series] steps = {list(steps)!r}: expected increasing compression ratios in [0, 0.9){hint}"
        )
    return ratios


def _without_none(items) -> dict:
    """A dataclass's fields as a dict, unset (``None``) ones left out: TOML has no null."""
    return {k: v for k, v in items if v is not None}


def _check_numbers(section: str, settings) -> None:
    """Every number of a settings section: the right type, finite, and >= 0 (no setting of a
    protocol is negative; ``inf`` would overflow a timer or a duration estimate); every switch
    true or false and every name a string (``interactive = "false"`` read as true)."""
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        kind = str(f.type).replace(" | None", "")
        if value is None and "None" in str(f.type):
            continue
        if kind == "bool" and isinstance(value, np.bool_):  # the Python API's numpy switch
            setattr(settings, f.name, value := bool(value))
        if kind == "bool" and not isinstance(value, bool):
            raise ProtocolError(f"[{section}] {f.name} = {value!r}: expected true or false")
        if kind == "str" and isinstance(value, os.PathLike):  # the Python API's Path (a folder, a scene)
            setattr(settings, f.name, value := os.fspath(value))
        if kind == "str" and not isinstance(value, str):
            raise ProtocolError(f"[{section}] {f.name} = {value!r}: expected a string")
        if kind not in ("float", "int"):
            continue
        if not (is_integer(value) if kind == "int" else is_number(value)):
            raise ProtocolError(
                f"[{section}] {f.name} = {value!r}: expected {'an integer' if kind == 'int' else 'a number'}"
            )
        if not math.isfinite(value) or value < 0:
            raise ProtocolError(f"[{section}] {f.name} = {value!r}: expected a finite number >= 0")
        if type(value) not in (int, float):  # a numpy number (the Python API): TOML cannot write it
            setattr(settings, f.name, int(value) if kind == "int" else float(value))


def _check_geometry(d: DetectorSettings) -> None:
    """``[detector] shape`` and ``preset`` as the watcher will take them, so a dry run refuses
    what the run would: an unknown preset or a shape that contradicts it passed ``--dry-run``
    and stopped the run at connect."""
    from radiokit.io import PRESETS

    if d.shape is not None:
        shape = d.shape
        if isinstance(shape, (str, bytes)) or not hasattr(shape, "__len__") or len(shape) != 2:
            raise ProtocolError(f"[detector] shape = {shape!r}: expected [rows, cols]")
        if not all(is_integer(v) and v > 0 for v in shape):
            raise ProtocolError(f"[detector] shape = {list(shape)!r}: expected two whole numbers > 0")
        d.shape = tuple(int(v) for v in shape)
    if d.preset is None:
        return
    if d.preset not in PRESETS:
        raise ProtocolError(f"[detector] preset = {d.preset!r}: unknown; known: {', '.join(PRESETS)}")
    p = PRESETS[d.preset]
    if d.shape is not None and d.shape != (p.rows, p.cols):
        raise ProtocolError(
            f"[detector] shape = {list(d.shape)} contradicts preset = {d.preset!r} ({p.rows} x {p.cols}); give one of them"
        )


def _source_limits(s: SourceSettings):
    """The driver configuration a protocol's ``[source]`` asks for (``SourceConfig``), checked:
    known keys only, and limits that stay within the L8121's ratings (``SourceConfig`` refuses a
    limit beyond :data:`acquisition.l8121.RATINGS`: a protocol may only tighten them)."""
    from acquisition.l8121 import SourceConfig

    if not isinstance(s.limits, dict):  # (the Python API's SourceSettings)
        raise ProtocolError(f"[source] limits = {s.limits!r}: expected a table of driver settings")
    fields = {f.name: str(f.type) for f in dataclasses.fields(SourceConfig)}
    unknown = sorted(set(s.limits) - set(fields))
    if unknown:
        names = sorted(set(fields) | {f.name for f in dataclasses.fields(SourceSettings)} - {"limits"})
        raise ProtocolError(f"unknown key(s) in [source]: {', '.join(unknown)}; expected some of {', '.join(names)}")
    for key, value in s.limits.items():
        said = _limit_type_error(fields[key], value)
        if said:
            raise ProtocolError(f"[source] {key} = {value!r}: {said}")
        if isinstance(value, np.bool_):  # the Python API's numpy switch: the driver takes bool only
            s.limits[key] = bool(value)
    try:
        cfg = SourceConfig.from_dict(
            {
                **s.limits,
                "poll_s": s.limits.get("poll_s", min(0.2, s.poll_s)),
                "warmup_timeout_s": s.limits.get("warmup_timeout_s", s.warmup_timeout_s),
            }
        )
    except (TypeError, ValueError, OverflowError) as exc:
        raise ProtocolError(f"[source] {_refusal(exc)}") from None
    return cfg


def _refusal(exc: Exception) -> str:
    """What the driver refused, in ``[source]``'s words: a :class:`~acquisition.l8121.SettingRefused`'s
    ``detail`` (its text without "L8121 configuration: "), else the exception's own text."""
    return getattr(exc, "detail", str(exc))


def _limit_type_error(kind: str, value) -> str:
    """What is wrong with the type of a driver setting in ``[source]`` (``kind``: its
    ``SourceConfig`` annotation), or "": said in the protocol's words, naming the key, as for its
    own keys (the driver's check behind "[source]: L8121 configuration:" named the key last, and
    took ``model = 5``, compared with the controller's TYP only after connecting). Ranges and
    the ratings stay the driver's check, the one implementation of them."""
    if value is None and kind.endswith("| None"):  # (the Python API: the dialect's, any model)
        return ""
    if is_number(value) and not math.isfinite(value):
        return "expected a finite number"
    if kind in ("float", "float | None"):
        if not is_number(value):
            return "expected a number"
        if value < 0:
            return "expected a finite number >= 0"
    if kind in ("float | str", "float | str | None") and not (is_number(value) or isinstance(value, str)):
        return 'expected a number, or a percentage such as "2%"'
    if kind == "bool" and not isinstance(value, (bool, np.bool_)):
        return "expected true or false"
    if kind in ("str", "str | None") and not isinstance(value, str):
        return "expected a string"
    return ""


def _whole(value: float) -> int:
    """The whole kV or uA the driver sends (``acquisition.l8121``: round half up)."""
    return math.floor(value + 0.5)


def _check_source(s: SourceSettings) -> None:
    """Exposure, focus and limits of ``[source]`` against the protocol's limits and the ratings,
    before anything is sent: the dry run refuses what the run would refuse."""
    from acquisition.l8121 import DIALECTS, SourceConfig, checked_time

    cfg = _source_limits(s)
    if s.baudrate is not None:  # [source] baudrate is the protocol's own key, not a limit: the driver's check
        try:
            SourceConfig(baudrate=s.baudrate)
        except ValueError as exc:
            raise ProtocolError(f"[source] {_refusal(exc)}") from None
    try:  # the driver's own check (the one implementation of the ratings), before anything is sent
        cfg.check_exposure(s.voltage_kv, s.current_ua)
        # ... and on the whole numbers the driver will send (it rounds half up): 60.5 kV x 165 uA
        # passed a 10 W limit here, warmed the tube up, and was refused only at XON
        cfg.check_exposure(_whole(s.voltage_kv), _whole(s.current_ua))
    except ValueError as exc:
        raise ProtocolError(f"[source] {_refusal(exc)}") from None
    try:  # the tolerances, given or the driver's defaults, at this protocol's setting (as on() judges them)
        cfg.check_tolerances(_whole(s.voltage_kv), _whole(s.current_ua))
    except ValueError as exc:
        raise ProtocolError(f"[source] {_refusal(exc)}") from None
    modes = cfg.focus_modes
    if cfg.dialect in DIALECTS:  # "auto": checked at connect, once the dialect is known (_phase_warm_up)
        modes = DIALECTS[cfg.dialect].focus_modes(cfg)
    if s.focus is not None and (not is_integer(s.focus) or s.focus not in modes):
        raise ProtocolError(f"[source] focus = {s.focus!r}: expected one of {list(modes)} (dialect {cfg.dialect})")
    if not isinstance(s.port, str):
        raise ProtocolError(f"[source] port = {s.port!r}: expected a string (device path or URL)")
    try:  # the beam monitor's period, bounded as the driver's polls are
        checked_time("poll_s", s.poll_s)
    except ValueError as exc:
        raise ProtocolError(f"[source] {_refusal(exc)}") from None
    # a run that polls as asked must never trip it: the beam monitor polls every poll_s, the
    # driver's warm-up and ramp waits every limits.poll_s
    period = max(s.poll_s, cfg.poll_s)
    if s.watchdog_s > WATCHDOG_MAX_S:
        # the guardian waits for the next poll this long with X-rays possibly on: 1e300 passed
        # here and overflowed its select() after the connect had begun
        raise ProtocolError(
            f"[source] watchdog_s = {shown(s.watchdog_s)}: expected at most {WATCHDOG_MAX_S:g} s "
            "(the longest a hung run may keep X-rays on), or 0 for none"
        )
    if 0 < s.watchdog_s < 4 * period:
        raise ProtocolError(
            f"[source] watchdog_s = {s.watchdog_s!r}: expected at least 4 poll periods "
            f"({shown(4 * period, s.watchdog_s)} s), or 0 for none"
        )


#: The most frames one batch of a series may take (``[series] darks``, ``flats``,
#: ``frames_per_step``; ``[detector] discard_after_change``, read out and dropped in the same
#: batch). Why this ceiling: a batch is one stretch of the run with nobody needed -- for the flats
#: and each step one continuous exposure. At the C7942's full resolution (2 frames a second, a
#: 2240 x 2240 uint16 frame of 10 MB, C7942.md) 10 000 frames are 83 min of beam and 100 GB; at
#: its fastest read-out (4 x 4 binning, 9 a second) still 18 min; on the external trigger's slowest
#: (0.1 a second) 28 h, a bound no lab meets by accident either. That is 2000 times the paper's
#: 5 frames a step, and averaging that many already lowers a frame's noise a hundredfold. Past
#: it a count is a typo (an extra zero or three), which was taken: the run warned that the disk
#: would fill only after connecting, then warmed the tube up and exposed until it did.
FRAMES_PER_BATCH_MAX = 10_000

#: The counts :data:`FRAMES_PER_BATCH_MAX` bounds, as (section, key).
_BATCH_COUNTS = (
    ("series", "darks"),
    ("series", "flats"),
    ("series", "frames_per_step"),
    ("detector", "discard_after_change"),
)

#: The longest wait for a poll before the guardian switches off (``[source] watchdog_s``).
WATCHDOG_MAX_S = 600.0


@dataclass(frozen=True)
class _TimeLimit:
    max_s: float
    why: str


#: L8121.md: dialect B's DAG names a warm-up mode "after 8 h idle", and a series warms the tube
#: up once, at its start: a step reached after longer with the tube off found it needing a
#: warm-up it never gets (``on()`` refuses: "warm-up needed").
_IDLE_MAX_S = 8 * 3600.0
_IDLE_WHY = "the tube is off meanwhile, and after 8 h idle the L8121 needs a warm-up the series takes only at its start"

#: ``acquisition.l8121.TIME_LIMITS``' bounds this table's estimates stand for (equal, tested):
#: not imported, as this module imports the driver only when a run needs it.
_WARMUP_MAX_S = 7200.0  # warmup_timeout_s: no run waits for a longer warm-up
_RAMP_MAX_S = 60.0  # stable_timeout_s: no run waits longer for the beam to ramp

#: The bound of every wait and estimate a protocol's own sections hold (the source's driver
#: times: ``acquisition.l8121.TIME_LIMITS``; ``[detector] timeout_s``: :data:`WATCHDOG_MAX_S`).
#: Why: 1e300 passed "finite", and a settle that long was a series stalled for ever after its
#: darks and flats; an estimate that long a dry run's plan of ``inf`` minutes. Each bound is the
#: longest the run could use: past it the run fails (or the plan says what cannot happen).
PROTOCOL_TIME_LIMITS: dict[tuple[str, str], _TimeLimit] = {
    # gel relaxation, tube off: hours are legitimate, past the idle warm-up they are not
    ("series", "settle_s"): _TimeLimit(_IDLE_MAX_S, _IDLE_WHY),
    ("sim", "settle_s"): _TimeLimit(_IDLE_MAX_S, "a rehearsal of the lab's [series] settle_s, bounded as it is"),
    ("frame", "move_estimate_s"): _TimeLimit(_IDLE_MAX_S, _IDLE_WHY),
    ("source", "warmup_estimate_s"): _TimeLimit(
        _WARMUP_MAX_S, "the longest warm-up a run waits for, [source] warmup_timeout_s's bound"
    ),
    ("sim", "warmup_s"): _TimeLimit(
        _WARMUP_MAX_S, "the longest warm-up a run waits for, [source] warmup_timeout_s's bound"
    ),
    ("sim", "ramp_s"): _TimeLimit(
        _RAMP_MAX_S, "the longest a run waits for the beam to ramp, stable_timeout_s's bound"
    ),
    # C7942.md: the slowest read-out, external trigger at 0.1 fps, is a 10 s frame
    ("detector", "frame_period_s"): _TimeLimit(
        WATCHDOG_MAX_S, "the longest wait for a frame, [detector] timeout_s's bound; the C7942's slowest is 10 s"
    ),
    ("sim", "frame_period_s"): _TimeLimit(WATCHDOG_MAX_S, "the longest wait for a frame, [detector] timeout_s's bound"),
    # ([detector] settle_s: below [detector] timeout_s, Protocol._check_times)
}

_SECTIONS = {
    "source": SourceSettings,
    "detector": DetectorSettings,
    "frame": FrameSettings,
    "series": SeriesSettings,
    "sim": SimSettings,
}


def load_protocol(source, *, text: bool = False, where: str = "protocol") -> Protocol:
    """A :class:`Protocol` from a TOML file path, TOML text, or a dict. Unknown keys are errors
    (a typo must not silently fall back to a default exposure), and so is every setting the run
    would refuse (exposure outside the limits or the L8121's ratings, non-finite times), so a dry
    run refuses it too. ``text=True``: ``source`` is TOML text, never a path (a protocol stored in
    a file is not a name of another file to open). A :class:`~pathlib.Path` is always a file: a
    path may hold ``=`` (``runs/kv=60/protocol.toml``), so a one-line string is a file when it has
    no ``=`` or names an existing file, and TOML text otherwise."""
    if isinstance(source, dict):
        data = source
    else:
        from acquisition.l8121 import names_file  # the source config's rule, one place

        text_ = str(source)
        one_line = not text and "\n" not in text_
        if isinstance(source, Path) or (one_line and ("=" not in text_ or names_file(text_))):
            where = shown_name(text_)  # the file's name as names print (a newline, an escape)
            try:
                text_ = Path(text_).read_text()
            except IsADirectoryError:
                raise ProtocolError(f"{where}: is a folder, not a protocol file (TOML)") from None
            except UnicodeDecodeError:  # the experiment file itself, a TIFF: the codec's words helped no one
                raise ProtocolError(f"{where}: not TOML text (binary data): not a protocol file") from None
            except OSError as exc:
                raise ProtocolError(f"{where}: cannot read the protocol ({exc.strerror or exc})") from None
        try:
            data = toml_loads(text_)
        except tomllib.TOMLDecodeError as exc:
            raise ProtocolError(f"{where}: not valid TOML: {exc}") from None
        if not data:  # an empty file ran every default exposure and series, as a typo must not
            raise ProtocolError(f"{where}: the protocol holds no settings; write at least [source] and [series]")
    top = {}
    for key, value in data.items():
        if key in _SECTIONS:
            cls = _SECTIONS[key]
            names = {f.name for f in dataclasses.fields(cls)}
            if not isinstance(value, dict):
                raise ProtocolError(f"{where}: [{key}] must be a table")
            if key == "source":  # driver limits may sit in the section itself
                limits = {k: v for k, v in value.items() if k not in names}
                value = {k: v for k, v in value.items() if k in names}
                if not isinstance(value.setdefault("limits", {}), dict):  # `limits = 5`: a traceback
                    raise ProtocolError(
                        f"{where}: [source] limits = {value['limits']!r}: expected a table of driver "
                        "settings ([source.limits]), or those keys in [source] itself"
                    )
                value["limits"] = {**value["limits"], **limits}
            unknown = set(value) - names
            if unknown:
                raise ProtocolError(
                    f"{where}: unknown key(s) in [{key}]: {', '.join(sorted(unknown))}; "
                    f"expected some of {', '.join(sorted(names))}"
                )
            top[key] = cls(**value)
        elif key in ("output", "name"):
            top[key] = value
        else:
            raise ProtocolError(
                f"{where}: unknown key {key!r}; expected output, name or a section [{'], ['.join(_SECTIONS)}]"
            )
    try:
        p = Protocol(**top)
    except (TypeError, ProtocolError) as exc:
        raise ProtocolError(f"{where}: {exc}") from None
    stated = data.get("source", {})
    p.unstated_exposure = tuple(key for key in EXPOSURE_KEYS if key not in stated)
    return p


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


RAMP_ESTIMATE_S = 5.0  # XON until the measured kV/uA are stable, per beam-on period (estimate)
# a beam-on period longer than this many times its plan, and by at least OVERRUN_S, is told to the
# operator: X-rays stay on longer than the dry run said (a slow controller: L8121.md's dialect B
# counts a reply as missed only after 2 s; 1.2 s replies kept a 3-frame step on 24 s, planned 6.5 s)
OVERRUN_FACTOR, OVERRUN_S = 2.0, 10.0


def plan(protocol: Protocol, done: dict | None = None, *, warm: bool = False, sim: bool = False) -> Plan:
    """The run's phases with estimated durations and beam-on time. ``done`` (from a file being
    resumed) removes what is already there; ``warm=True`` leaves out the warm-up; ``sim=True``
    plans the virtual bench, whose source warms up in ``[sim] warmup_s`` and whose steps settle in
    ``[sim] settle_s``."""
    p = protocol
    done = done or {}
    period = p.detector.frame_period_s
    ramp = RAMP_ESTIMATE_S
    rows = []
    if not warm:
        # the warm-up emits X-rays (dialect B reports it as AGING): it counts as beam-on time
        # wherever X-rays on is counted (README), here as the time it may take
        w = p.sim.warmup_s if sim else p.source.warmup_estimate_s
        rows.append(("warm-up", "if the source needs it: X-rays on", 0, w, w))
    nd = max(0, p.series.darks - done.get("darks", 0))
    if nd:
        rows.append(("darks", "tube off", nd, nd * period, 0.0))
    nf = max(0, p.series.flats - done.get("flats", 0))
    if nf:
        t = nf * period + ramp
        person = 2 * p.frame.move_estimate_s if p.frame.kind == "manual" else 0.0
        rows.append(
            (
                "flats",
                f"phantom out, {p.source.voltage_kv:g} kV {p.source.current_ua:g} uA, phantom in",
                nf,
                t + person,
                t,
            )
        )
    h0, settle = p.frame.initial_height_mm, p.settle_s(sim)
    for i, r in enumerate(p.series.steps, start=1):
        n = max(0, p.series.frames_per_step - done.get("steps", {}).get(i, 0))
        if n:
            t = n * period + ramp
            rows.append(
                (
                    f"step {i}",
                    f"{100 * r:g} %: gap {h0 * (1 - r):.3f} mm, settle {settle:g} s",
                    n,
                    p.frame.move_estimate_s + settle + t,
                    t,
                )
            )
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
    off_done: bool = False  # the run's final switch-off has been attempted
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
    """The driver's configuration (``SourceConfig`` keys): checked against the ratings at load."""
    return _source_limits(p.source).to_dict()


def _guarded_source(url: str, p: Protocol):
    """The L8121 on ``url``, its port held by a guardian process (:mod:`acquisition.guardian`)
    that switches the tube off if this process dies without releasing it.

    The dialect and baud rate are resolved first (``dialect = "auto"`` probes the port with
    harmless queries), and the guardian gets that resolved configuration: it opens the port at
    the right rate and switches off in the right dialect without probing again.

    An error follows README's one rule for the exit: ``port_never_opened`` when nothing opened
    the port (not a byte was sent), ``nothing_sent`` when an interrupt came before the first
    query, else the port was opened -- by the probe, or through the guardian -- and the error
    carries ``tube_state`` when the controller's last ``STS`` (the probe's included) read a state
    that cannot emit with nothing that emits sent after it, ``source_unreached`` (the tube not
    confirmed off: the warning) otherwise. A connect refused through the guardian (identity,
    operate switch, state) sends ``XOF`` first (the driver's, ``control``); an interrupt after
    the probe read X-rays on still switches off, confirmed."""
    from acquisition.errors import PortUnavailable
    from acquisition.guardian import start_guardian
    from acquisition.l8121 import L8121
    from acquisition.transport import hold_port

    driver = L8121(url, baudrate=p.source.baudrate, connect=False, config=_source_config(p))
    hold = None
    try:
        # the port's lock from before the probe until the guardian holds it too (the link's own
        # share, inherited by the guardian): no other process gets in between the probe's links
        # and the guardian's open. PortBusy (another program holds it): nothing sent, "never reached".
        # This process lets its copy go at the guardian's READY: between the guardian's end (or
        # death) and this process's next open the port is unlocked, and a program that takes it
        # then gets the switch-off refused, which ends loudly (not confirmed off: the tube warning)
        hold = hold_port(url)
        resolved = driver.resolve()
        # the watchdog armed from the start unless the probe read the tube off: left on by an
        # earlier run, it stays on until the run's first phase switches it off, and connect's
        # requests (which arm it anyway) follow at once: silence before them is a process
        # stopped (SIGSTOP) with the tube on, not a slow start (a death there closes the pipe)
        link = start_guardian(
            url,
            resolved,
            notebook=Path(p.output).with_suffix(".log"),
            watchdog_s=p.source.watchdog_s or None,
            armed=not driver.tube_confirmed_off,
        )
    except BaseException as exc:
        if isinstance(exc, PortUnavailable) and driver.probe_result is not None and driver.probe_result.found:
            # the probe reached the controller, then the guardian could not take the port (another
            # program took it, the adapter dropped out): not "never reached" -- say what it read
            lost = driver.port_lost_after_probe(exc)
            _what_was_reached(lost, driver)
            raise lost from exc
        _what_was_reached(exc, driver)
        raise
    finally:
        if hold is not None:
            hold.release()
    source = L8121(link, connect=False, config=resolved)
    try:
        # what "auto" found, for the file's record -- and for connect(): interrupted after the
        # probe read X-rays on, it switches off through the guardian (confirmed) before it lets
        # the link go -- and the probe's reading for the exit rule
        source.take_over(driver)
        source.connect()
    except BaseException as exc:
        _what_was_reached(exc, source)
        link.close()
        raise
    return source


def _what_was_reached(exc: BaseException, driver) -> None:
    """README's one rule on ``exc`` (see :func:`_guarded_source`), from what ``driver`` knows."""
    from acquisition.errors import PortUnavailable

    exc.port_never_opened = isinstance(exc, PortUnavailable) and not driver.port_opened
    exc.nothing_sent = getattr(exc, "probe_sent", None) is False
    if getattr(exc, "off_failed", None) is not None or getattr(exc, "guardian_gone", False):
        # a later switch-off (the guardian's, after its failed start) was not confirmed, or the
        # guardian held the port and ended without a word: the tube may have been switched on
        # since the probe's reading, which then vouches for nothing
        exc.tube_state = None
        if getattr(exc, "guardian_gone", False):
            exc.left_by_guardian = driver  # for the switch-off through the port it freed (_stop)
    elif getattr(exc, "tube_state", None) is None and driver.tube_confirmed_off:
        # the last STS (the probe's, or the refused connect's after its XOF) read the tube off and
        # nothing that emits went out after it: confirmed, as the source commands say it
        exc.tube_state = driver.last_state
    exc.source_unreached = getattr(exc, "tube_state", None) is None


def check_lab(p: Protocol) -> None:
    """What the lab's bench needs of a protocol (a port, the vendor software's folder, the manual
    frame): checked by the run before it writes anything (its notebook included) and by the dry
    run without ``--sim``, so a dry run refuses what the run would (README). A protocol with a
    port but the virtual panel dry-ran "on source /dev/..." and the run then refused it."""
    if not p.source.port:
        raise ProtocolError("[source] port is empty: name the serial port (e.g. /dev/ttyUSB0) or run with --sim")
    if p.detector.kind != "folder" or not p.detector.folder:
        raise ProtocolError(
            f'[detector] kind = "{p.detector.kind}"{", no folder" if not p.detector.folder else ""}: the lab needs '
            'kind = "folder" and the folder the vendor software writes to (kind = "sim" needs --sim)'
        )
    if p.frame.kind != "manual":
        raise ProtocolError(
            f'[frame] kind = "{p.frame.kind}": the lab\'s frame is kind = "manual" (a motorised stage has no '
            'driver yet; kind = "sim" needs --sim)'
        )


def check_sim(p: Protocol) -> None:
    """What the virtual bench needs of a protocol: a scene it can load, a binning the panel has,
    and a ``[detector]`` that describes the simulated panel (a C7942 preset binned as the scene
    or ``[sim] binning`` says, 12-bit). Checked before anything is written or sent, as
    :func:`check_lab` is for the lab: a shape or bits that contradicted the panel switched X-rays
    on and then stopped the run at its first frame (bits 8), or wrote a file that mislabelled it
    (bits 14, a shape the frames do not have)."""
    from radiokit.io import PRESETS
    from sim.detector import PanelModel
    from sim.scene import Detector, load_scene

    if p.sim.frame_period_s > p.detector.timeout_s:  # SimDetector would time out on every frame
        raise ProtocolError(
            f"[sim] frame_period_s = {shown(p.sim.frame_period_s)} exceeds [detector] timeout_s = "
            f"{shown(p.detector.timeout_s)}: every frame would time out"
        )
    b = p.sim.binning
    if b is not None and b not in (1, 2, 4):
        raise ProtocolError(f"[sim] binning = {b!r}: expected 1, 2 or 4 (the C7942's)")
    try:
        scene = load_scene(p.sim.scene)
    except (ValueError, OSError) as exc:
        raise ProtocolError(f"[sim] scene = {p.sim.scene!r:.80}: {exc}") from None
    panel = PRESETS[scene.detector.preset]
    b = b or scene.detector.binning
    rows, cols = panel.rows // b, panel.cols // b
    what = f"the virtual bench's panel is {rows} x {cols} ({scene.detector.preset} at binning {b})"
    d = p.detector
    if d.shape is not None and tuple(d.shape) != (rows, cols):
        raise ProtocolError(f"[detector] shape = {list(d.shape)}: {what}; give its shape or none")
    if d.preset is not None and (PRESETS[d.preset].rows, PRESETS[d.preset].cols) != (rows, cols):
        raise ProtocolError(f"[detector] preset = {d.preset!r}: {what}; give its preset or none")
    pitch = Detector(scene.detector.preset, b).pixel_size_mm
    if d.pixel_size_mm is not None and not math.isclose(d.pixel_size_mm, pitch, rel_tol=1e-9):
        # refused, not warned of: the file records the panel's pitch (the frames are the virtual
        # panel's), so a run that went on named another length than the protocol's in every
        # millimetre measured from it -- what shape and bits are refused for above; and a
        # warning is a line among the run's, after the warm-up has begun
        raise ProtocolError(
            f"[detector] pixel_size_mm = {shown(d.pixel_size_mm)}: the virtual bench's panel has a pitch of "
            f"{pitch:g} mm ({scene.detector.preset} at binning {b}); give {pitch:g} or none"
        )
    if d.bits != PanelModel.bits:
        raise ProtocolError(
            f"[detector] bits = {d.bits!r}: the virtual bench's panel is {PanelModel.bits}-bit (a C7942); "
            f"give {PanelModel.bits} or none"
        )


def lab_devices(p: Protocol) -> Devices:
    """The real bench: the L8121 on ``source.port`` (through the guardian), the folder the vendor
    software writes, the manual frame."""
    from acquisition.detector import FolderWatcher
    from acquisition.frame import ManualFrame

    check_lab(p)
    detector = FolderWatcher(
        p.detector.folder,
        p.detector.pattern,
        shape=p.detector.shape,
        preset=p.detector.preset,
        timeout_s=p.detector.timeout_s,
        settle_s=p.detector.settle_s,
        bits=p.detector.bits,
        discard_first=p.detector.discard_first,
        pixel_size_mm=p.detector.pixel_size_mm,
    )
    frame = ManualFrame(p.frame.initial_height_mm, interactive=p.frame.interactive)
    source = _guarded_source(p.source.port, p)
    return Devices(source, detector, frame)


def sim_devices(p: Protocol, *, progress=False, bench=None) -> Devices:
    """The virtual bench: the L8121 emulator served on a pseudo-terminal and driven through the
    real serial stack, a :class:`sim.bench.VirtualBench` of ``sim.scene`` (or ``bench``, reused)
    behind a ``SimDetector`` (which sees the emulated tube's state) and a ``SimFrame``.

    With ``[sim] source_port`` set, the source is the emulator (or controller) already serving on
    that port, driven through the guardian as in the lab, and the simulated panel sees the beam
    the source measures (``SAR``) -- how tests kill the acquiring process and read the
    emulator's state afterwards."""
    from acquisition.detector import SimDetector
    from acquisition.frame import SimFrame
    from acquisition.l8121 import L8121
    from sim.bench import VirtualBench
    from sim.scene import load_scene

    if bench is None:
        scene = load_scene(p.sim.scene)
        bench = VirtualBench(scene, binning=p.sim.binning, seed=p.sim.seed, progress=progress)
    bench.prepare(p.series.steps)  # one incremental solve for all steps (cached: a no-op when done)
    model, closers = None, []
    if p.sim.source_port:
        source = _guarded_source(p.sim.source_port, p)

        def beam():
            kv, ua = source.measured()
            return kv > 0 and ua > 0, float(kv), float(ua)
    else:
        from acquisition.emulators.l8121 import L8121Model, PtyServer

        dialect = str(p.source.limits.get("dialect", "A")).upper()  # the emulator speaks the configured dialect
        model = L8121Model(
            dialect=dialect if dialect == "B" else "A",
            baudrate=p.source.baudrate,
            warmup_s=p.sim.warmup_s,
            ramp_s=p.sim.ramp_s,
            warmed_up=p.sim.warmed_up,
        )
        server = PtyServer(model)
        server.start()
        closers = [server.stop]
        try:  # the emulator lives and dies with this process: no guardian
            source = L8121(server.url, baudrate=p.source.baudrate, **_source_config(p))
        except BaseException:  # a Ctrl-C in the connect too: its serving thread and pty go with it
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
        self.written = []  # (file index, frame time) of the frames taken in this beam period
        self.off_failed = False
        # this beam period's SER after its XOF not read yet (confirm_error_code): a stop landing
        # before or in that read leaves it to the stop path (_stop), the tube then off
        self.error_code_due = False
        self._stop = threading.Event()
        self._thread = None

    def start(self, kv, ua):
        self.kv, self.ua = kv, ua
        self.error = None
        self.written = []
        self.error_code_due = True
        self.last_ok = time.time()  # on() has just confirmed the beam
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="beam-monitor", daemon=True)
        self._thread.start()

    def _loop(self):
        while not self._stop.wait(self.period_s):
            t = time.time()
            try:
                reading = self.source.check()
                if self._stop.is_set():  # the run is stopping: this poll may have read the tube after its XOF
                    return
                self.last_ok = t
            except BaseException as exc:  # a fault, a silent controller, garbage: stop the series
                self.error = exc
                self._unvouch(exc)
                from acquisition.l8121 import SwitchedOff

                if isinstance(exc, SwitchedOff):  # another thread switched off during the poll
                    return
                if getattr(self.source, "off_failed", None) is not None:
                    # the driver's own switch-off (its fail-safe) failed and said so: one owner
                    # retries, so the operator's warning is not delayed by a second full budget
                    self.off_failed = True
                    return
                try:
                    self.source.off()
                except Exception as off_exc:
                    self.off_failed = True
                    _tell_off_failure(self.source, off_exc)
                return
            self.kv, self.ua = _kv_ua(reading, self.kv, self.ua)

    def raise_if_failed(self):
        if self.error is not None:
            raise self.error

    def confirm(self, error_code: bool = True):
        """One synchronous poll: if the beam is still good, every frame so far is vouched for; if
        not, the error is recorded (and raised) like the thread's. ``error_code=False``: the
        beam checks only (the driver's ``check``), ``SER`` being read after the ``XOF``
        (:meth:`confirm_error_code`)."""
        t = time.time()
        try:
            reading = self.source.check(error_code=error_code)
        except Exception as exc:
            # (a stop landing in this thread's poll -- KeyboardInterrupt, StopSignal -- is no
            # reading of the beam: recorded here, the stop path took it for a fault and read no
            # SER after its XOF; it cut the poll short, which then vouches for nothing, as
            # SwitchedOff does)
            self.error = exc
            self._unvouch(exc)
            raise
        self.last_ok = t
        self.kv, self.ua = _kv_ua(reading, self.kv, self.ua)

    def confirm_error_code(self):
        """The tube off after this beam period: the controller's error code read once more (the
        driver's ``error_code_after_beam``); a code not allowed, or no reading, takes the vouching
        back to the last good ``SER`` and is recorded (and raised) like a poll's fault. A stop
        landing in it (KeyboardInterrupt, StopSignal) is no reading: not recorded, the read left
        to the stop path (``error_code_due``)."""
        try:
            self.source.error_code_after_beam()
        except Exception as exc:
            self.error_code_due = False
            self.error = exc
            self._unvouch(exc)
            raise
        self.error_code_due = False

    def _unvouch(self, exc):
        """A fault that may have stood since before the last good poll (a controller error code,
        read less often than the beam: the driver's ``vouched_until``) moves the vouched-for time
        back to when it was last read good."""
        self.last_ok = min(self.last_ok, getattr(exc, "vouched_until", self.last_ok))

    def suspect(self):
        """File indices of this beam period's frames taken after the last good poll: once the
        beam has failed, nobody can say they were exposed as asked."""
        return [i for i, t in self.written if t > self.last_ok]

    def halt(self):
        """No further poll (one in flight goes on until the driver cuts it short)."""
        self._stop.set()

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
    """What a run did: the file, frames written this run and in all, timings, the phase reached,
    and whether ``STS`` confirmed the tube off at the end (``None``: the source was never reached)."""

    output: str
    frames_written: int
    frames_total: int
    seconds: float
    beam_on_s: float
    phase: str
    per_frame_overhead_s: list = field(default_factory=list)
    resumed: bool = False
    tube_off: bool | None = None
    tube_state: str = ""
    port_never_opened: bool = False  # the source's port could not be opened: not a byte was sent
    nothing_sent: bool = False  # stopped before the first byte to the source: its state was not touched
    #: stopped while connecting to the virtual bench's own emulated controller: queries at most
    queries_only: bool = False
    already_complete: bool = False  # resume=True on a file holding every frame: nothing was touched
    previous_kept: bool = False  # overwrite=True stopped before its first frame: the old file is as it was
    file_removed: bool = False  # stopped before its first frame, the new file it made was removed (held none)
    #: overwrite=True stopped before its first frame, and the old file could not be put back under
    #: its name (the folder turned unwritable): where it is kept, hidden
    previous_aside: Path | None = None
    #: the switch-off that was not confirmed, in the driver's words ("" when none, or not known):
    #: the command line says it once, above the X-rays warning (the log lines repeating it are
    #: marked :data:`acquisition.l8121.OFF_FAILURE`)
    off_failure: str = ""
    #: the experiment file was removed while the run wrote it: the frames it held are lost
    file_lost: bool = False


#: The settings a resume must share with the run the file records: what shapes the recorded frames
#: (the panel, its depth and pitch, the series, the frame) or the beam (exposure, focal spot, the
#: controller's dialect), as ``(section, key)``; ``source.dialect`` lives in its limits. The
#: virtual bench's own ("sim") count on ``--sim`` only. Links, periods and time-outs may change.
_RESUME_SAME = (
    ("series", "darks"),
    ("series", "flats"),
    ("series", "frames_per_step"),
    ("series", "steps"),
    ("series", "settle_s"),
    ("frame", "kind"),
    ("frame", "initial_height_mm"),
    ("source", "voltage_kv"),
    ("source", "current_ua"),
    ("source", "focus"),
    ("source", "dialect"),
    ("detector", "kind"),
    ("detector", "shape"),
    ("detector", "preset"),
    ("detector", "bits"),
    ("detector", "pixel_size_mm"),
)
_RESUME_SAME_SIM = (("sim", "scene"), ("sim", "binning"), ("sim", "seed"))


def _setting(p: Protocol, section: str, key: str):
    if (section, key) == ("source", "dialect"):
        return p.source.limits.get("dialect")
    return getattr(getattr(p, section), key)


def _same_setting(section: str, key: str, a, b) -> bool:
    """Whether a file's setting ``a`` and the resume's ``b`` are the same, however written: a
    dialect left to detection ("auto", or unset) matches the one named, in either case (the
    pitch: :func:`_recorded_pitch`)."""
    if (section, key) == ("source", "dialect"):
        a, b = (None if v is None or str(v).lower() == "auto" else str(v).upper() for v in (a, b))
        return a is None or b is None or a == b
    return a == b


def _recorded_pitch(p: Protocol, sim: bool) -> float | None:
    """The pitch a run of ``p`` records (:func:`_open_experiment`, the detector's): the stated
    one, else the virtual panel's at its binning (``sim``), else the one the lab's frames imply
    (:func:`acquisition.detector.implied_pixel_size_mm`). Why: an unset pitch was compared as
    0.05 mm, and a resume that stated the 0.2 mm a binned panel's file recorded was refused.
    None when the scene cannot be read (then the scenes differ, and that is said)."""
    d = p.detector
    if d.pixel_size_mm is not None:
        return d.pixel_size_mm
    if sim and d.kind == "sim":
        from sim.scene import Detector, load_scene

        try:
            scene = load_scene(p.sim.scene)
            return Detector(scene.detector.preset, p.sim.binning or scene.detector.binning).pixel_size_mm
        except (ValueError, OSError):
            return None
    from acquisition.detector import implied_pixel_size_mm

    return implied_pixel_size_mm(d.preset, d.shape)


def _stored_protocol(path, text: str, now: Protocol) -> Protocol:
    """The file's stored protocol as far as a resume compares it (:data:`_RESUME_SAME`), the rest
    taken from ``now``: validated by today's rules, a setting that may change (a link's spacing,
    a time-out) recorded under the previous release's kept the file from ever being resumed
    (``min_interval_s = 1.5``, capped at 1 s since; review s41rr)."""
    try:
        # the rule every TOML radiokit reads keeps (checks.toml_loads): one nested 100 000 deep
        # was a RecursionError traceback (review s52rvoff)
        stored = toml_loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProtocolError(f"{shown_name(path)} (its stored protocol): not valid TOML: {exc}") from None
    merged = tomllib.loads(now.to_toml())
    for section, key in _RESUME_SAME + _RESUME_SAME_SIM:
        old = stored.get(section) if isinstance(stored.get(section), dict) else {}
        target = merged.setdefault(section, {})
        if (section, key) == ("source", "dialect"):  # a driver limit: in [source] or its limits table
            if key not in old and isinstance(old.get("limits"), dict):
                old = old["limits"]
            target.pop(key, None)
            target = target.setdefault("limits", {})
        if key in old:
            target[key] = old[key]
        else:
            target.pop(key, None)
    return load_protocol(merged, where=f"{shown_name(path)} (its stored protocol)")


def _resume_differences(stored: Protocol, now: Protocol, sim: bool) -> list[str]:
    """The settings of :data:`_RESUME_SAME` that differ, each as "[section] key = now (file)"."""
    said = []
    for section, key in _RESUME_SAME + (_RESUME_SAME_SIM if sim else ()):
        a, b = _setting(stored, section, key), _setting(now, section, key)
        if (section, key) == ("detector", "pixel_size_mm"):
            was, will = _recorded_pitch(stored, sim), _recorded_pitch(now, sim)
            same = None not in (was, will) and math.isclose(was, will, rel_tol=1e-9)  # (0.05 * 3, 0.15)
        else:
            same = _same_setting(section, key, a, b)
        if not same:
            then = "not set in the file" if a is None else f"{a!r} in the file"
            said.append(f"[{section}] {key} = {'unset' if b is None else repr(b)} ({then})")
    return said


def _existing(path: Path, protocol: Protocol, *, sim: bool = False) -> dict:
    """What an interrupted file already holds: {'darks': n, 'flats': n, 'steps': {i: n}}; checks
    it was written by the same protocol in every setting that shapes the frames or the beam
    (:data:`_RESUME_SAME`; ``sim``: a ``--sim`` resume, the virtual bench's too). Frames labelled
    invalid (cut short by a full disk, or taken after the beam monitor's last good reading) do
    not count: they are taken again."""
    from radiokit.io import ImageKey, read_progress

    try:
        progress = read_progress(path)
        if progress.protocol is None:
            raise ProtocolError(
                f"{shown_name(path)}: no protocol recorded in the file; not a compression series to resume"
            )
        # the stored text is a protocol, never the name of a file to open
        stored = _stored_protocol(path, progress.protocol, protocol)
        differ = _resume_differences(stored, protocol, sim)
        if differ:
            # one series, one set of settings: a resumed 12-bit series recorded 14 bits for its
            # 12-bit darks, and a new pitch was dropped without a word (review s41acq)
            raise ProtocolError(
                f"{shown_name(path)}: written by a protocol that differs in {'; '.join(differ)}; resume with the "
                "file's settings (its /entry@protocol), or start a new file with -o"
            )
        keys, steps = progress.image_key, progress.step
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise ProtocolError(f"{shown_name(path)}: cannot resume from this file ({exc})") from None
    done = {"darks": int(np.sum(keys == ImageKey.DARK)), "flats": int(np.sum(keys == ImageKey.FLAT)), "steps": {}}
    for i in range(1, len(protocol.series.steps) + 1):
        done["steps"][i] = int(np.sum((keys == ImageKey.PROJECTION) & (steps == i)))
    return done


@dataclass
class _Run:
    """One run's state, handed from phase to phase."""

    p: Protocol
    out: Path
    sim: bool
    resume: bool
    overwrite: bool
    progress: bool
    guard: object
    res: Result
    bar: object
    user_notify: object
    writer_factory: object
    devices: Devices | None = None
    replacing: bool = False  # an overwrite of an existing file: the old one is kept until the first frame
    previous_aside: Path | None = None  # the old file, left hidden: another program took the name meanwhile
    stopped_by: BaseException | None = None  # what stopped the run (_stop), for the notes of its end
    writer: object = None
    monitor: _BeamMonitor | None = None
    done: dict = field(default_factory=lambda: {"darks": 0, "flats": 0, "steps": {}})
    phase: str = "connect"
    beam_since: float | None = None  # perf_counter at XON of the beam period in progress
    beam_planned: tuple = (0.0, 0, "")  # the plan's seconds, frames and name of that period
    overrun_told: bool = False
    panel_seen: bool = False  # the panel delivered a frame in this run (_panel_check)
    began_file: bool = False  # the experiment file is this run's own, made under a free name
    discard_file: bool = False  # ... and stopped before its first frame: removed as it closes
    origins: dict = field(default_factory=dict)  # (frame file, time) -> its index in the experiment file
    beam_on_s: float = 0.0
    t0: float = field(default_factory=time.perf_counter)

    def enter(self, phase, info=None):
        self.guard.reinstall()
        self.guard.raise_if_lost()  # a stop a library swallowed: the series goes no further
        self.phase = phase
        log.info("phase %s", phase)  # the notebook says where a run was when it stopped
        self.bar.set_description(phase)
        self.user_notify(phase, info)

    @property
    def source(self):
        return self.devices.source

    def on_signal(self):
        """Called from the signal guard's watcher thread the moment a stop signal arrives, while
        the main thread may still be inside a frame: no further beam poll, and a poll in flight
        sends nothing after its exchange on the link, so the XOF that follows waits for one
        exchange at most (A: not SAR then SIN; B: not STS, SHV, SCU, SIN at 0.3 s each)."""
        if self.monitor is not None:
            self.monitor.halt()
        cancel = getattr(getattr(self.devices, "source", None), "cancel_readings", None)
        if cancel is not None:
            cancel()


def _emitting(state) -> bool:
    """X-rays on, for every safety rule: the beam, and the warm-up sequence, which runs the tube
    (dialect A's ``STS 1``, dialect B's ``AGING``: both WARMING_UP, ``SourceState.emitting``)."""
    return bool(getattr(state, "emitting", False))


def _phase_connect(r: _Run):
    """Devices, then the source's state first of all: X-rays left on (by a run that was killed, or
    by hand) are switched off, and confirmed, before anything else and before any person is asked
    to do anything."""
    _import_ahead(r)
    if r.devices is None:
        r.devices = sim_devices(r.p, progress=r.progress) if r.sim else lab_devices(r.p)
    r.guard.reinstall()  # building the devices may have loaded a C library that took the signals
    src = r.source
    r.monitor = _BeamMonitor(src, r.p.source.poll_s)
    state = src.status()
    log.info("source state %s", getattr(state, "name", state))
    if _emitting(state):
        log.warning(
            "X-rays were on at the start (state %s): switching off before anything else", getattr(state, "name", state)
        )
        src.off()
    if not src.interlock_closed():
        log.warning("interlock open: close the cabinet before X-rays are needed")


def _import_ahead(r: _Run) -> None:
    """Import now, before anything is sent, what the series would first import with X-rays on
    (:data:`_SIM_IMPORTS`, on the virtual bench only)."""
    import importlib

    if r.sim or getattr(r.devices, "bench", None) is not None:  # (the demo passes its virtual bench's devices)
        for name in _SIM_IMPORTS:
            importlib.import_module(name)


def _phase_warm_up(r: _Run):
    """Open the experiment file, set the focus, arm the panel, then warm up if the source needs
    it. The file comes first: the warm-up emits X-rays, and a run that cannot store a frame (a
    full disk, a read-only folder) must not have started it; nor one whose panel delivers none
    (:func:`_panel_check`)."""
    src, p = r.source, r.p
    if p.source.focus is not None:  # a setting: checked before anything is opened or sent
        src.check_focus(int(p.source.focus))
    _open_experiment(r)
    # before the warm-up, which emits, and before a resume's first XON: a disk without room for
    # the next frame stopped the run only at that frame, after the X-rays (review s41acq)
    _refuse_without_room(r, "no X-ray command was sent")
    needed = _needs_warm_up(src)  # after the controller's power-on checks: a setting sent during them may be refused
    if p.source.focus is not None:  # before the warm-up, which emits (B's is an XON); set again before each XON
        src.focus = int(p.source.focus)
    r.devices.detector.arm()
    if needed:
        _panel_check(r)
        r.guard.raise_if_lost()  # no warm-up after a stop that never reached the run
        t = time.perf_counter()
        try:
            # the exposure's own kV and µA: a warm-up emits (B's is an XON at the presets), so it
            # starts only after the values it runs at are set and read back valid
            src.warm_up(
                timeout_s=p.source.warmup_timeout_s,
                progress=r.progress,
                kv=p.source.voltage_kv,
                ua=p.source.current_ua,
            )
        finally:  # the warm-up emits: X-rays on, as the plan counts it (an interrupted one too)
            r.beam_on_s += time.perf_counter() - t


def _panel_check(r: _Run) -> None:
    """One frame from the panel, the tube off, before this run's first X-ray command when no
    frame has come yet (the warm-up, or a resume's first XON): a panel that delivers nothing was
    found only when the darks timed out after the warm-up, or the flats with X-rays on (review
    s41acq). The frame is not stored: the darks stay just before the exposures (C7942.md: the
    dark drifts), not up to the warm-up's half hour before them."""
    if r.panel_seen:
        return
    detector = r.devices.detector
    detector.begin_batch(r.p.detector.discard_after_change)
    check = getattr(detector, "check", None)  # a virtual panel's keeps its series' noise as it was
    try:
        frames = (
            [check(timeout_s=r.p.detector.timeout_s)]
            if check
            else detector.acquire(1, timeout_s=r.p.detector.timeout_s)
        )
        for frame in frames:
            log.info("panel check: a frame from %s, tube off (not stored): the panel delivers", frame.origin)
    except DeviceError as exc:
        exc.args = (f"{exc}; the panel is checked before X-rays: no X-ray command was sent",) + exc.args[1:]
        raise
    r.panel_seen = True


def _refuse_without_room(r: _Run, said: str) -> None:
    """Stop before X-rays when the experiment file could not store the next frame: the writer's
    own rule (:meth:`~radiokit.io.ExperimentWriter.check_room`, the one its append applies), one
    line naming the file, with ``said`` (what was, or was not, sent) and what to do."""
    try:
        r.writer.check_room()
    except OSError as exc:
        what = exc.strerror or str(exc)
        raise OSError(
            exc.errno or errno.ENOSPC, f"{what}; {said}: free space on that disk or choose another output"
        ) from None


def _warn_if_short_of_room(r: _Run, existed: bool) -> None:
    """Say before the warm-up when the disk cannot hold the whole series (uint16 frames: an upper
    bound). A warning, not a refusal: the bound may overstate, and a series that fills the disk
    stops safely and resumes; but a warm-up of up to 30 min should not be spent unannounced."""
    import shutil

    p = r.p
    series = p.series.darks + p.series.flats + p.series.frames_per_step * len(p.series.steps)
    # resumed, the file holds part of the series; overwritten, the old file is freed with the
    # first frame (the writer refuses one that would not fit beside it)
    held = r.out.stat().st_size if (r.resume or r.overwrite) and existed else 0
    need = series * 2 * int(np.prod(r.devices.detector.shape)) - held
    try:
        free = shutil.disk_usage(r.out.parent).free
    except OSError:
        return
    if need > free:
        log.warning(
            "%s: the series needs up to %.0f MB and %.0f MB are free: it will stop when the disk fills "
            "(--resume completes it on a disk with room)",
            shown_name(r.out),
            need / 1e6,
            free / 1e6,
        )


def _open_experiment(r: _Run):
    """The experiment file, created (or reopened to resume) and the run recorded in it."""
    src, p, det = r.source, r.p, r.devices.detector
    # the pitch and the panel's name only where the detector knows them, and where the pitch came
    # from: a pitch merely assumed (a folder of frames of no C7942 width) had been recorded as the
    # panel's own, and every file named the C7942
    origin = getattr(det, "pixel_size_from", "the detector's")
    pitch = getattr(det, "pixel_size_mm", p.detector.pixel_size_mm)
    kw = dict(
        pixel_size_mm=pitch if origin is not None else None,
        pixel_size_from=origin if pitch is not None else None,
        detector_name=getattr(det, "panel_name", None),
        source={
            "name": "Hamamatsu L8121-01" + (" (emulated)" if r.sim else ""),
            "voltage_kv": p.source.voltage_kv,
            "current_ua": p.source.current_ua,
        },
        title=f"radiokit compression series: {p.name}",
        bit_depth=p.detector.bits if p.detector.bits != 12 else None,  # 12: the readers' default
        # the file is the run's journal: a run killed part-way must leave its frames under the
        # name --resume continues (built beside it and renamed at the end, they were in a hidden
        # temporary the next run removes). The old file is kept aside until the first frame: a
        # run stopped before it (the warm-up failed, Ctrl-C, no panel) leaves it as it was
        in_place=True,
    )
    existed = r.out.exists()
    _warn_if_short_of_room(r, existed)
    try:
        r.writer = r.writer_factory(r.out, tuple(det.shape), mode="a" if r.resume else "w", overwrite=r.overwrite, **kw)
    except OSError as exc:
        from radiokit.io import OutputError, discard_unbegun

        r.previous_aside = getattr(exc, "previous_kept_in", None)
        if not existed:  # a file this run began and could not finish: it would block the next run
            discard_unbegun(r.out)
        code = exc.errno or errno.EIO
        # the writer's own line (open in another program, a folder it cannot rename in)
        if isinstance(exc, OutputError):
            raise OSError(code, str(exc)) from None
        raise OSError(code, f"{shown_name(r.out)}: cannot create the experiment file ({os.strerror(code)})") from None
    r.began_file = not existed and not r.resume
    if not r.resume:
        r.writer.record_run(p.to_toml(), {"detector": det.describe(), "source": getattr(src, "describe", lambda: {})()})


def _take(r: _Run, n, image_key, step=-1, ratio=None, gap=None, beam=False):
    """``n`` frames from the panel, each appended (and flushed) as it arrives. Only frames made
    after the devices reached this batch's state: none the folder already holds (made while the
    operator turned the screws, the gel settled or the beam ramped up), nor the one in flight."""
    detector = r.devices.detector
    detector.begin_batch(r.p.detector.discard_after_change)
    try:
        _append_frames(r, detector.acquire(n, timeout_s=r.p.detector.timeout_s), image_key, step, ratio, gap, beam)
    except DeviceError as exc:
        # frames whose files changed after they were stored (FrameLost): nobody can vouch for them
        lost = sorted(r.origins[o] for o in getattr(exc, "origins", ()) if o in r.origins)
        if lost:
            try:
                r.writer.mark_invalid(lost)
                log.warning("frames %s kept as image_key 3 (invalid): their files changed afterwards", lost)
            except Exception as mark_exc:
                log.error("could not mark frames %s invalid: %s", lost, mark_exc)
        raise


def _append_frames(r: _Run, frames, image_key, step, ratio, gap, beam):
    monitor, writer = r.monitor, r.writer
    for frame in frames:
        t = time.perf_counter()
        if beam:
            monitor.raise_if_failed()
        index = writer.append(
            frame.data,
            image_key=image_key,
            step=step,
            ratio=ratio,
            gap_mm=gap,
            time_s=frame.time_s,
            voltage_kv=monitor.kv if beam else 0.0,
            current_ua=monitor.ua if beam else 0.0,
        )
        log.debug("frame %d written (image_key %d, step %d) from %s", index, int(image_key), step, frame.origin)
        r.panel_seen = True
        r.origins[(frame.origin, frame.time_s)] = index  # FrameLost names a stored frame so
        if beam:
            monitor.written.append((index, frame.time_s))
        r.res.frames_written += 1
        r.bar.update()
        r.res.per_frame_overhead_s.append(time.perf_counter() - t)
        r.user_notify("frame", writer.n_frames - 1)
        if beam:
            monitor.raise_if_failed()


def _beam_on(r: _Run, n: int, what: str):
    """X-rays on for ``n`` frames of ``what`` (the plan's estimate of this period is kept for
    :func:`_beam_off`)."""
    # the disk may have filled since (the vendor software writes to it too): no XON for frames
    # the file would refuse
    _refuse_without_room(r, f"X-rays were not switched on for {what}")
    _panel_check(r)
    r.guard.raise_if_lost()  # no XON after a stop that never reached the run
    r.beam_planned = (n * r.p.detector.frame_period_s + RAMP_ESTIMATE_S, n, what)
    r.beam_since = time.perf_counter()
    reading = r.source.on(r.p.source.voltage_kv, r.p.source.current_ua)
    r.monitor.start(*_kv_ua(reading, r.p.source.voltage_kv, r.p.source.current_ua))


def _beam_off(r: _Run):
    r.monitor.stop()
    r.monitor.raise_if_failed()  # the fault itself, not what switching off then ran into
    # the beam was good up to the last frame (faults latch); SER after the XOF, not before it
    r.monitor.confirm(error_code=False)
    r.source.off()
    took = time.perf_counter() - r.beam_since
    r.beam_on_s += took
    r.beam_since = None
    planned, n, what = r.beam_planned
    if not r.overrun_told and took > OVERRUN_FACTOR * planned and took - planned >= OVERRUN_S:
        r.overrun_told = True  # once a run: the cause (the link, the panel) is the same every period
        log.warning(
            "X-rays were on %.1f s for %s (%d frame%s), planned %.1f s (%g s a frame + %g s to stabilise): "
            "a slow controller or detector keeps the tube on longer than the dry run said",
            took,
            what,
            n,
            "" if n == 1 else "s",
            planned,
            r.p.detector.frame_period_s,
            RAMP_ESTIMATE_S,
        )
    r.monitor.confirm_error_code()  # the tube off: the period's frames since the last SER read


def _phase_darks(r: _Run):
    """Darks, the tube off (confirmed)."""
    from radiokit.io import ImageKey

    n = r.p.series.darks - r.done["darks"]
    if n > 0:
        r.source.off()
        _take(r, n, ImageKey.DARK)
        _judge(r, "darks")


def _phase_flats(r: _Run):
    """Flats: phantom out, beam on, frames, beam off, phantom back in (the tube off while a person
    handles the phantom)."""
    from radiokit.io import ImageKey

    n = r.p.series.flats - r.done["flats"]
    if n > 0:
        frm = r.devices.frame
        frm.sample_out()
        _beam_on(r, n, "the flats")
        _take(r, n, ImageKey.FLAT, beam=True)
        _beam_off(r)
        # judged with the tube off and before the phantom goes back in: a refusal stops here
        _judge(r, "flats")
        frm.sample_in()
    elif r.resume and r.p.series.flats and not any(r.done["steps"].values()):
        # the flats are in the file and no projection: nothing records that the phantom went
        # back in after them (a Ctrl-C at that request), and a resume went straight to the
        # screws, the projections then taken without it (review s41acq); asked again, tube off
        r.devices.frame.sample_in()


def _judge(r: _Run, what: str) -> None:
    """Judge the darks (``what`` "darks") or the darks and flats ("flats") just taken by the rules
    ``radiokit calibrate`` and ``process`` will apply (:func:`radiokit.calibrate.judge_frames`):
    a warning goes to the operator and the notebook; a refusal labels the frames it names invalid
    (image_key 3: kept, never used, and taken again by ``--resume``) and stops the series with
    :class:`FramesRefused` -- the tube off -- before any compression step. Why: a flat clipped
    at the ADC's top or taken with the beam blocked was found only at processing, after the
    phantom had been compressed and the session was over. Darks taken by a resume that kept the
    flats (a refusal that named the darks) are judged with those flats, as processing will."""
    from radiokit.calibrate import judge_darks, judge_frames
    from radiokit.io import ImageKey

    bits = r.p.detector.bits
    top = (1 << bits) - 1 if bits != 12 else None  # as the file records it and processing reads it
    dark_idx, darks = r.writer.frames_labelled(ImageKey.DARK)
    if not dark_idx.size:  # a protocol without darks: its calibration needs darks taken elsewhere
        log.info("%s not judged: the file holds no darks", what)
        return
    flat_idx, flats = r.writer.frames_labelled(ImageKey.FLAT)
    try:
        # the darks alone against the panel's own top when they fit in its bits: the half-range
        # warning needs a top known, not guessed (calibrate._known_top); darks over it are a
        # read-out storing counts in the top bits of 16, whose top processing infers
        own = (1 << bits) - 1 if top is None and int(darks.max()) <= (1 << bits) - 1 else top
        told = judge_frames(darks, flats, saturation=top) if flat_idx.size else judge_darks(darks, saturation=own)
    except ValueError as exc:
        frames = {"darks": dark_idx, "flats": flat_idx}
        named = [c for c in getattr(exc, "culprits", (what,)) if frames[c].size]
        if what == "darks" and named == ["darks"] and flat_idx.size:
            # new darks named again against the flats a refusal of darks kept: flats that read
            # under any darks (the beam blocked while the offset drifts) were never retaken, and
            # each resume took darks only, refused forever; both are taken again
            named = ["darks", "flats"]
        raise _refused(r, what, exc, named, np.concatenate([frames[c] for c in named]), flat_idx.size) from None
    judged = f"{darks.shape[0]} darks" + (f" and {flats.shape[0]} flats" if flat_idx.size else "")
    for line in told:
        log.warning("%s: the %s: %s", shown_name(r.out), judged, line)
    log.info("%s: %s judged usable for calibration", r.out, judged)


def _refused(r: _Run, what: str, exc: ValueError, named, bad, n_flats: int) -> Exception:
    """The frames ``bad`` (the ``named`` kinds: "darks", "flats") labelled invalid, and the
    operator's one line (:func:`_judge`; ``n_flats``: the flats the file holds)."""
    from acquisition.errors import FramesRefused

    retake = " and ".join(named)
    try:
        r.writer.mark_invalid(bad.tolist())
        kept = f"the {retake} kept labelled invalid (image_key 3)"
    except Exception as mark_exc:  # the refusal is what the operator must read; the file's fault is logged
        log.error("could not mark frames %s invalid: %s", bad.tolist(), mark_exc)
        kept = f"the {retake} kept but NOT labelled invalid (see the notebook)"
    later = "no compression step" if n_flats else "no flat and no compression step"
    with_flats = ", with the flats the file holds," if what == "darks" and n_flats else ""
    # the resume rule (_existing): the protocol's exposure is the file's, recorded once with its
    # first frames (NXsource, @protocol); README says why a resume does not change it
    change = (
        " (for another tube current or voltage, edit the protocol and start a new file with -o)"
        if named == ["flats"]
        else ""
    )
    # the notebook gets this line from _stop; logged here too it would show twice on the console
    return FramesRefused(
        f"{shown_name(r.out)}: the {what} just taken{with_flats} would be refused by radiokit calibrate: {exc}; {kept}, {later} "
        f"taken; then `--resume` takes new {retake}{change}"
    )


def _phase_steps(r: _Run):
    """Each compression step: compress and settle with the tube off, beam on, frames, beam off."""
    from radiokit.io import ImageKey

    p, frm = r.p, r.devices.frame
    h0 = frm.initial_height_mm
    before = None  # (step, measured ratio) of the step moved to before this one
    for i, ratio in enumerate(p.series.steps, start=1):
        n = p.series.frames_per_step - r.done["steps"].get(i, 0)
        if n <= 0:
            continue
        r.enter(f"step {i}", ratio)
        gap = frm.move_to(h0 * (1 - ratio))
        if before is not None and 1 - gap / h0 <= before[1]:
            # processing takes the steps in their numbers' order, the last as the most compressed
            log.warning(
                "step %d: measured compression %.4f (gap %.3f mm) is not above step %d's %.4f: "
                "the series is not in increasing compression",
                i,
                1 - gap / h0,
                gap,
                *before,
            )
        before = (i, 1 - gap / h0)
        _settle(p.settle_s(r.devices.bench is not None), r.bar, r.progress)
        _beam_on(r, n, f"step {i}")
        _take(r, n, ImageKey.PROJECTION, step=i, ratio=1 - gap / h0, gap=gap, beam=True)
        _beam_off(r)


def _phase_close(r: _Run):
    """The frame released, the tube off and confirmed (a tube that cannot be confirmed off ends
    the run in an error even when every frame is in)."""
    r.devices.frame.stop()
    r.guard.cleanup()
    if not _tube_off(r):
        raise DeviceError(
            f"{r.source.port if hasattr(r.source, 'port') else 'source'}: the series is complete "
            f"but switching X-rays off could not be confirmed"
        )


# The order of work; "steps" enters one phase per compression step itself.
_PHASES = (
    ("connect", _phase_connect),
    ("warm-up", _phase_warm_up),
    ("darks", _phase_darks),
    ("flats", _phase_flats),
    ("steps", _phase_steps),
    ("close", _phase_close),
)


def run(
    protocol,
    *,
    sim=False,
    resume=False,
    devices: Devices | None = None,
    progress=True,
    on_phase=None,
    writer_factory=None,
    overwrite=False,
    guard=None,
) -> Result:
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
    guard : acquisition.guardian.SignalGuard, optional
        The signal guard to run under (the command line keeps one until its last line is
        printed); by default the run installs its own: SIGINT, SIGTERM, SIGHUP, SIGQUIT and SIGTSTP stop the series
        with :class:`~acquisition.guardian.StopSignal`, and none interrupts the switch-off.

    Raises
    ------
    SourceFault, DeviceError, DetectorTimeout, OSError, KeyboardInterrupt (StopSignal)
        After the tube is off and the file is closed with every completed frame in it; the message
        names the fault, and the exception carries ``.result`` (what was saved, and whether the
        tube was confirmed off: ``result.tube_off``).
    PortBusy
        Another program holds the controller's port: raised before the run writes anything (its
        notebook included) or sends a byte, without ``.result``.
    """
    from acquisition.guardian import SignalGuard
    from radiokit.io import ExperimentWriter
    from radiokit.progress import tqdm

    p = protocol if isinstance(protocol, Protocol) else load_protocol(protocol)
    if sim and devices is None:  # the Python API as the command line: before any file or byte
        check_sim(p)
    out = Path(p.output)
    resume, done, complete, hold = _begin(p, out, resume=resume, overwrite=overwrite, sim=sim, devices=devices)
    if complete is not None:
        return complete
    try:
        notebook = _open_notebook(out)
        # a resume stopped before it reopens the file (while connecting) still holds the file's
        # frames: "0 frames saved" of a file holding them invited its deletion (review s48rv2)
        res = Result(str(out), 0, _frames_in(out) if resume else 0, 0.0, 0.0, "connect", resumed=bool(resume))
        bar = tqdm(total=plan(p, done, warm=True).n_frames, desc="acquire", unit="frame", disable=not progress)
        r = _Run(
            p,
            out,
            sim,
            resume,
            overwrite,
            progress,
            guard or SignalGuard(),
            res,
            bar,
            on_phase or (lambda phase, info=None: None),
            writer_factory or ExperimentWriter,
            devices=devices,
            replacing=bool(overwrite and not resume and out.exists()),
        )
        if done:
            r.done = done
        with r.guard:
            watch = getattr(r.guard, "on_signal", None)
            if watch is not None:
                watch(r.on_signal)
            try:
                for name, phase in _PHASES:
                    if name != "steps":
                        r.enter(name)
                    phase(r)
            except BaseException as exc:
                r.stopped_by = exc
                cause = _stop(r, exc)
                if cause is not exc:
                    raise cause from exc
                raise
            finally:
                _release(r, notebook)
                if watch is not None:
                    r.guard.forget(r.on_signal)
        res.phase = "done"
        res.frames_total = r.writer.n_frames if r.writer is not None else 0
        res.seconds = time.perf_counter() - r.t0
        res.beam_on_s = r.beam_on_s
        return res
    finally:
        if hold is not None:
            hold.release()


def _hold_source_port(p: Protocol, *, sim, devices):
    """This process's hold on the controller's local port (:func:`acquisition.transport.hold_port`),
    when the run opens one: the lab's ``[source] port``, or ``[sim] source_port``; None otherwise.

    Raises
    ------
    PortBusy
        Another program holds it: nothing was sent, and nothing written."""
    port = p.sim.source_port if sim else p.source.port
    if devices is not None or not port:
        return None
    from acquisition.transport import hold_port

    return hold_port(port)


def _begin(p: Protocol, out: Path, *, resume, overwrite, sim, devices):
    """:func:`_what_to_take`'s ``(resume, done, complete)``, and the source's port held (None
    when ``complete``). A stop here gets the result of a run not begun (:func:`_not_begun`)."""
    try:
        resume, done, complete = _what_to_take(p, out, resume=resume, overwrite=overwrite, sim=sim, devices=devices)
        # the source's port held before the first file is written (the notebook is): refused by
        # another program's hold (PortBusy), the run leaves no notebook of a series that never
        # began, which a re-run would then meet, nor a line in a resumed one's. The devices'
        # links share it
        hold = None if complete is not None else _hold_source_port(p, sim=sim, devices=devices)
    except KeyboardInterrupt as exc:
        exc.result = _not_begun(out, resume)
        raise
    return resume, done, complete, hold


def _not_begun(out: Path, resume: bool) -> Result:
    """The result of a run stopped before it sent anything or touched its file (while it checked
    the file or took the source's port): the file, if there, as it was. Without one the command
    line said "nothing saved; `... --resume` completes it" of an --overwrite's previous series,
    which that resume would go on with, and no "never reached the X-ray controller" line."""
    there = out.exists()
    try:
        n = _frames_in(out) if there and resume else 0
    except Exception:  # not a series (the check that refuses it was cut short): its count unknown
        n = 0
    kept = there and not resume  # an --overwrite's previous series, or a file the run would refuse
    return Result(str(out), 0, n, 0.0, 0.0, "connect", resumed=there and resume, nothing_sent=True, previous_kept=kept)


def _frames_in(out: Path) -> int:
    """The complete frames of the experiment file ``out`` (a resume's, checked by _existing)."""
    from radiokit.io import read_progress

    return int(read_progress(out).frames_complete)


def _what_to_take(p: Protocol, out: Path, *, resume, overwrite, sim, devices):
    """The checks before a run writes or opens anything: ``(resume, done, complete)``, where
    ``done`` is what a resumed file holds and ``complete`` the :class:`Result` of a resume that
    has nothing to take (then nothing was touched)."""
    from radiokit.io import restore_previous

    # an --overwrite killed before its first frame left the old file aside: put back first, it is
    # the file every check below is about (the command line has said this already)
    for restored, line in restore_previous(out):
        log.log(logging.WARNING if restored else logging.INFO, "%s", line)
    if resume and not out.exists():
        log.warning("%s: nothing to resume (no file: the series stopped before its first frame); starting it", out)
        resume = False
    done = _existing(out, p, sim=sim) if resume else None
    if done is not None and plan(p, done, warm=True).n_frames == 0:
        # nothing to take: no device is opened, no notebook line and no end time written (raw data
        # is never modified after acquisition, DESIGN.md; a resume rewrote /entry@end_time)
        from radiokit.io import read_progress

        n = read_progress(out).frames_complete
        log.info("%s: already complete (%d frames); nothing to resume", out, n)
        if devices is not None:  # handed in: closed at the end all the same (the docstring's promise)
            devices.close()
        return resume, done, Result(str(out), 0, n, 0.0, 0.0, "done", resumed=True, already_complete=True)
    if not resume and out.exists() and not overwrite:
        raise FileExistsError(
            f"{shown_name(out)}: exists; raw data is never overwritten (--resume completes it; --overwrite replaces it)"
        )
    if not sim and devices is None:
        check_lab(p)  # before the notebook: a refused protocol leaves no file behind
    return resume, done, None


class _Notebook(logging.FileHandler):
    """The lab notebook's file. On a full disk it falls silent rather than print a traceback per
    record or replace the error that ends the run with its own."""

    broken = False

    def emit(self, record):
        if not self.broken:
            super().emit(record)

    def handleError(self, record):
        self.broken = True

    def flush(self):
        try:
            super().flush()
        except OSError:
            self.broken = True

    def close(self):
        try:
            super().close()
        except OSError:
            self.broken = True


def _open_notebook(out: Path) -> logging.Handler:
    """The lab notebook: every serial exchange, phase and fault, beside the experiment file."""
    try:
        notebook = _Notebook(out.with_suffix(".log"), encoding="utf-8")
    except OSError as exc:  # the first file a run writes: say which, and that nothing was sent
        where = f"no folder {shown_name(out.parent)}" if not out.parent.is_dir() else exc.strerror or str(exc)
        raise OSError(
            exc.errno or errno.EIO,
            f"{shown_name(out)}: cannot write the experiment file's lab notebook {shown_name(out.with_suffix('.log').name)} "
            f"({where}); nothing was sent to the devices",
        ) from None
    notebook.setLevel(logging.DEBUG)
    notebook.setFormatter(
        logging.Formatter("%(asctime)s.%(msecs)03d %(name)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S")
    )
    acq_log = logging.getLogger("acquisition")
    notebook.old_level = acq_log.level
    acq_log.addHandler(notebook)
    if acq_log.getEffectiveLevel() > logging.DEBUG:
        acq_log.setLevel(logging.DEBUG)
    return notebook


def _stop(r: _Run, exc: BaseException):
    """The series stopped (fault, error, signal): tube off first, then the bookkeeping of what was
    saved; the exception gets ``.result`` and a note saying what the operator can do next."""
    r.guard.cleanup()  # nothing may interrupt what follows
    res, monitor = r.res, r.monitor
    res.phase = r.phase
    beam_period = r.beam_since is not None
    unvouched = False
    if beam_period and monitor is not None:
        # A poll the stop itself cut short (SwitchedOff) saw no fault. The signal's watcher thread
        # cancels routine readings at once (on_signal), so the monitor's poll in flight may record
        # its SwitchedOff before this thread, still raising the stop, gets here: taken for a fault,
        # it left the stop's SER unread (make test on a loaded machine, session 52)
        no_fault = _only_cut_short(monitor.error)
        if no_fault and not _source_error(exc) or isinstance(exc, DetectorTimeout):
            # stopped for another reason (a signal, the disk, the detector): X-rays off first. A poll
            # to vouch for the frames since the last one would keep the beam on for its exchanges
            # (A: SAR, SIN; B: STS, SHV, SCU, SIN); those frames are labelled invalid instead
            unvouched = True
        elif no_fault:
            monitor.error = exc  # a source error raised in this thread (on(), check())
    _tube_off(r)  # halts the monitor, switches off before the rest of its poll, then joins it
    exc = r.stopped_by = _file_lost_cause(r, _watchdog_cause(r, exc))
    _beam_fault_not_stopped_on(monitor, exc)
    # (a stop after a period's normal XOF but before or in its SER read: unvouched is not set, the
    # period having ended, and the read is still due)
    due = unvouched or monitor is not None and monitor.error_code_due
    if due and res.tube_off and _only_cut_short(monitor.error):
        _error_code_after_stop(monitor)
    _stop_frame(r)
    if res.tube_off is None:
        _off_where_the_guardian_left(exc)
    if res.tube_off is None and getattr(exc, "tube_state", None) is not None:
        # not connected, but the controller's last STS read the tube off (README's one rule): an
        # interrupted connect that switched a unit found on off, a refused connect's XOF, or the
        # probe's reading with nothing that emits sent after it (the guardian could not take the port)
        res.tube_off, res.tube_state = True, exc.tube_state.name
    elif (
        res.tube_off is None
        and isinstance(exc, KeyboardInterrupt)
        and (getattr(exc, "nothing_sent", False) or r.devices is None and _before_source(r, exc))
    ):
        res.nothing_sent = True  # interrupted before the first byte to the source
    elif res.tube_off is None and getattr(exc, "port_never_opened", False):
        res.port_never_opened = True  # nothing was sent: radiokit cannot have switched X-rays on
    elif res.tube_off is None and getattr(exc, "source_unreached", False):
        res.tube_off = False  # the port opened but the source did not answer: nobody knows its state
    elif res.tube_off is None and isinstance(exc, KeyboardInterrupt) and r.devices is None and _own_emulator(r):
        # the virtual bench's own emulator, stopped in its connect (queries: TYP, STS): not a unit
        # anyone must check, and the stop line said nothing of the tube (review s48rv2)
        res.queries_only = True
    if beam_period:
        r.beam_on_s += time.perf_counter() - r.beam_since
    if monitor is not None and (monitor.error is not None or unvouched) and r.writer is not None and not res.file_lost:
        _mark_invalid(r.writer, monitor.suspect())
    if r.writer is not None:
        res.frames_total = r.writer.n_frames
    # a file this run made that took no frame holds nothing to resume, and left it only blocked
    # the rerun ("exists; raw data is never overwritten"): removed as the writer closes (_release)
    r.discard_file = r.began_file and r.writer is not None and r.writer.n_frames == 0
    res.seconds = time.perf_counter() - r.t0
    res.beam_on_s = r.beam_on_s
    kept = r.replacing and r.previous_aside is None
    kept = kept and (r.writer is None or getattr(r.writer, "previous", None) is not None)
    what = (
        f"stopped by {exc.name}"
        if hasattr(exc, "signum")
        else "interrupted (Ctrl-C)"
        if isinstance(exc, KeyboardInterrupt)
        else f"stopped by {type(exc).__name__}"
    )
    tube = {True: "tube off", False: "tube NOT confirmed off", None: "source not contacted"}[res.tube_off]
    tube = "queries only sent to the source" if res.queries_only else tube
    # INFO: the caller reports the exception itself (one line on the console); the notebook keeps it
    log.info("%s in phase %s: %s; %s; %d frames in %s", what, r.phase, exc, tube, res.frames_total, r.out)
    exc.result = res
    if hasattr(exc, "add_note"):
        exc.add_note(_stop_note(r, what, tube, kept))
    return exc


def _only_cut_short(error) -> bool:
    """Whether the beam monitor saw no fault: none, or its poll in flight cut short by the stop's
    own switch-off (:class:`~acquisition.l8121.SwitchedOff`, which vouches for nothing)."""
    from acquisition.l8121 import SwitchedOff

    return error is None or isinstance(error, SwitchedOff)


def _source_error(exc: BaseException) -> bool:
    """Whether ``exc`` is the source's own error, not this thread's reading cut short by the
    stop's switch-off (:class:`~acquisition.l8121.SwitchedOff`, which vouches for nothing)."""
    return isinstance(exc, DeviceError) and not _only_cut_short(exc)


def _error_code_after_stop(monitor) -> None:
    """A beam period stopped before its end (a signal, the disk, the detector), the tube confirmed
    off: ``SER`` read once, as a period's normal end reads it after its ``XOF``
    (:meth:`_BeamMonitor.confirm_error_code`). Read at most every ``error_poll_s`` (up to 60 s)
    with the beam on, it had vouched for nothing since its last read, and a stop labels invalid only
    the frames since the last good poll: a controller code that came up meanwhile left the rest
    valid, and a stop after a series' last frame was said complete (review s50rv2). A code not
    allowed, or no reading, moves the vouching back to the last good read (those frames are then
    labelled invalid) and is said; the stop remains what the run raises."""
    try:
        monitor.confirm_error_code()
    except Exception as exc:  # (recorded as the monitor's error: the frames since are labelled invalid)
        log.warning("%s; the frames taken since its last good read are labelled invalid", exc)


def _beam_fault_not_stopped_on(monitor, exc: BaseException) -> None:
    """The beam monitor's trip, said when the run stopped on something else (the panel's
    time-out as the door opened, a Ctrl-C): the driver logs a trip for the notebook only, the
    caller's error line being the one the operator reads, and this run's line names ``exc``. A
    poll that failed (no reply, garbage) and switched off is said too: the driver's fail-safe
    logs it for the notebook only (``fail_safe``), as a trip (s43)."""
    from acquisition.errors import SourceFault

    fault = getattr(monitor, "error", None)
    # (a SourceFault stopping the run is that trip, or the guardian's watchdog named for the
    # detector's time-out, which the trip would repeat)
    stopped_beam = isinstance(fault, SourceFault) or getattr(fault, "fail_safe", False)
    if stopped_beam and fault is not exc and not isinstance(exc, SourceFault):
        log.error("the beam monitor had stopped the beam: %s", fault)


def _file_lost_cause(r: _Run, exc: BaseException) -> BaseException:
    """``exc``, or, when the experiment file was removed while the run wrote it (another program,
    a clean-up script), an error saying so: the next frame's check of the file's size ended the
    run on "[Errno 2] No such file or directory: ...", and the command then said "8 frames saved
    in series.h5", a file that no longer existed, and offered --resume. ``result.file_lost`` tells
    the caller; the frames go with the file's last open handle as the writer closes."""
    if r.writer is None or r.out.exists():
        return exc
    r.res.file_lost = True
    if not isinstance(exc, FileNotFoundError):
        return exc
    n = r.writer.n_frames
    return OSError(
        errno.ENOENT,
        f"{shown_name(r.out)}: removed while the series was writing it (by another program or by hand): the {n} "
        f"frame(s) it held are lost with it",
    )


def _watchdog_cause(r: _Run, exc: BaseException) -> BaseException:
    """``exc``, or, when it is the detector's time-out and the guardian's watchdog switched the
    beam off while this process was silent, a :class:`SourceFault` naming the watchdog. A stop
    (SIGSTOP, a debugger) longer than the watchdog's 5 s and the detector's time-out woke the
    folder's wait already past its deadline: the line said "0 of 4 frames arrived ... still
    being written", blaming the panel, and the guardian's word came only in a log line above."""
    src = getattr(r.devices, "source", None)
    told = getattr(src, "watchdog_off", None)
    if not isinstance(exc, DetectorTimeout) or not isinstance(told, str) or not told:
        return exc
    from acquisition.errors import SourceFault

    return SourceFault(
        f"{src.port}: {told}; the wait for the detector's frames ran out in that time too (not a panel fault)"
    )


def _stop_note(r: _Run, what: str, tube: str, kept: bool) -> str:
    """What the operator can do next, after :func:`_stop` (for the exception's note)."""
    if r.previous_aside is not None:
        return (
            f"{what} in phase '{r.phase}': {tube}; no frame taken: another program made {shown_name(r.out)} meanwhile, and the "
            f"previous series is kept in {r.previous_aside}"
        )
    if kept:
        return f"{what} in phase '{r.phase}': {tube}; no frame taken: {shown_name(r.out)} holds the previous series, unchanged"
    if r.discard_file:
        return f"{what} in phase '{r.phase}': {tube}; no frame taken, {shown_name(r.out)} not kept: the run can start again"
    return (
        f"{what} in phase '{r.phase}': {tube}; {r.res.frames_total} frames are saved in {shown_name(r.out)}; "
        f"`radiokit acquire PROTOCOL --resume` completes the series"
    )


def _off_where_the_guardian_left(exc: BaseException) -> None:
    """A guardian that ended before READY (killed: the OOM killer) said nothing of the tube, which
    other software or a crash may have left on: switched off through the port it freed, confirmed by
    STS, as the source commands do (:func:`acquisition.guardian.off_anyway`); confirmed, the error
    carries that state (README's one rule: "tube off"), else the warning stays. Under this run's
    own lock on the port (:func:`run` holds it to the end): the switch-off's link shares it (one
    process), so it is never refused by it. Before READY this process never let its copy go
    (``hand_over``), so no other program got in between; after READY the link takes the lock
    again, refused -- the warning -- only if another program took the port meanwhile."""
    from acquisition.guardian import guardian_gone, off_anyway

    src = getattr(exc, "left_by_guardian", None)
    if src is None or not guardian_gone(src, exc):
        return
    interrupt = exc if isinstance(exc, KeyboardInterrupt) else None
    if off_anyway(src, interrupt):
        exc.tube_state = src.confirmed_off
        exc.source_unreached = False
    elif interrupt is not None and getattr(exc, "tube", None):
        log.warning("%s: %s", src.port, exc.tube)  # why not confirmed: said before the warning


def _before_source(r: _Run, exc: BaseException) -> bool:
    """Whether ``exc`` stopped the building of the devices before the source's link was touched:
    a controller on a port (the lab's, or ``[sim] source_port``) is reached only through
    :func:`_guarded_source`, whose errors all carry ``source_unreached``. (The virtual bench's own
    emulator is not a controller anyone must check.)"""
    return not _own_emulator(r) and not hasattr(exc, "source_unreached")


def _own_emulator(r: _Run) -> bool:
    """Whether the run's source is the virtual bench's own emulator (``--sim`` without ``[sim]
    source_port``): it lives in this process, and nothing but this run can switch it on."""
    return r.sim and not r.p.sim.source_port


def _stop_frame(r: _Run) -> None:
    """Halt the compression frame once the tube is off: a stopped series must not leave a
    motorised stage closing on the phantom (``MotorisedStage.stop``: safe at any time). Only the
    normal end stopped it, so a fault or Ctrl-C in a move left the axis running."""
    frame = getattr(r.devices, "frame", None)
    if frame is None:
        return
    try:
        frame.stop()
    except Exception as exc:  # the error that ended the run is the one to report
        log.error("stopping the compression frame: %s", exc)


def _release(r: _Run, notebook):
    """Close everything, whatever happened: the file, the tube (if not done yet), the devices."""
    r.bar.close()
    if r.writer is not None:
        try:
            r.writer.close()
        except Exception as exc:
            log.error("closing %s: %s", r.out, exc)
        else:
            if r.discard_file:
                from radiokit.io import discard_unbegun

                discard_unbegun(r.out)  # (not if another program holds it open by now)
                r.res.file_removed = not r.out.exists()
                if r.res.file_removed:
                    log.info("%s: no frame taken; the file is not kept (a rerun starts the series)", r.out)
    aside = getattr(r.writer, "previous_kept_in", None)
    if aside is not None and r.previous_aside is None:
        # the put-back failed as the writer closed, after _stop's note said "unchanged"
        r.previous_aside = aside
        notes = getattr(r.stopped_by, "__notes__", None)
        if notes:
            notes[-1] = (
                f"no frame taken: the previous series could not be put back under {shown_name(r.out)}; it is kept in "
                f"{shown_name(aside)} (the next run of this file puts it back first, once the folder is writable)"
            )
    r.res.previous_aside = r.previous_aside
    # no frame of its own: the writer put the old file back (or never set it aside)
    r.res.previous_kept = (
        r.replacing and r.previous_aside is None and (r.writer is None or getattr(r.writer, "restored_previous", False))
    )
    if r.devices is not None:
        _tube_off(r)
        r.devices.close()
    acq_log = logging.getLogger("acquisition")
    acq_log.removeHandler(notebook)
    acq_log.setLevel(notebook.old_level)
    notebook.close()


def _tube_off(r: _Run) -> bool | None:
    """Tube off, confirmed by ``STS``; once per run, and not at all when a switch-off already failed
    (the driver's fail-safe or the beam monitor's): one owner retries, as a controller that cannot
    confirm -- silent, dead, stuck on -- costs the retry budget each time, and the operator's
    warning would wait for every layer's. Records the outcome in ``r.res.tube_off``."""
    monitor, dev = r.monitor, r.devices
    if monitor is not None:
        # no new poll, and none waited for: the driver sends the XOF right after the exchange on
        # the link and cuts the rest of a poll in flight short (SwitchedOff); joined afterwards
        monitor.halt()
    try:
        return _switch_off_once(r, dev)
    finally:
        if monitor is not None:
            monitor.stop()  # nothing prints after the command's last line


def _switch_off_once(r: _Run, dev) -> bool | None:
    monitor = r.monitor
    if dev is None or dev.off_done:
        return r.res.tube_off
    dev.off_done = True
    if monitor is not None and monitor.off_failed or getattr(dev.source, "off_failed", None) is not None:
        dev.off_failed = True
        r.res.tube_off = False
        r.res.off_failure = str(getattr(dev.source, "off_failed", None) or "")
        # the failure was logged loud where it happened (the driver's fail-safe, the beam
        # monitor): this line is the notebook's, not a second warning of it (the Python API's
        # log said it three times, the command line once)
        log.info(
            "not switching off again: the last XOF could not be confirmed (%s)",
            getattr(dev.source, "off_failed", None) or "beam monitor",
            extra=_said_by_driver(),
        )
        return False
    try:
        state = dev.source.off()
    except Exception as exc:
        dev.off_failed = True
        r.res.tube_off = False
        r.res.off_failure = str(getattr(dev.source, "off_failed", None) or exc)
        _tell_off_failure(dev.source, exc)
        return False
    name = getattr(state, "name", str(state))
    if _emitting(state):  # off() accepts any state but X-rays on; a warm-up still running emits too
        dev.off_failed = True
        r.res.tube_off, r.res.tube_state = False, name
        log.error("XOF sent, but the controller reports %s: the tube still emits", name)
        return False
    if getattr(dev.source, "unit_unverified", False):
        # confirmed over a link reopened while X-rays may have been on: the unit now at the port
        # said so, known by its model only (the driver logged the operator's CRITICAL line)
        dev.off_failed = True
        r.res.tube_off, r.res.tube_state = False, name
        log.error("X-rays off confirmed only by the unit now at the port (the link was reopened): check by hand")
        return False
    r.res.tube_off, r.res.tube_state = True, name
    return True


def _tell_off_failure(source, exc) -> None:
    """Log a switch-off of ``source`` that ``exc`` says was not confirmed, once: through the
    driver, which says each failure once however many layers meet it (the beam monitor and the
    run's end may both wait on one ``XOF``); a source without it (a test's) gets one CRITICAL line."""
    tell = getattr(source, "tell_off_failure", None)
    if tell is not None:
        tell(exc)
    else:
        log.critical("could not confirm the tube is off: %s", exc, extra=_said_by_driver())


def _said_by_driver() -> dict:
    """The ``extra`` of a log line repeating the driver's unconfirmed switch-off (its own
    CRITICAL line said it): a terminal that says the failure once leaves these out."""
    from acquisition.l8121 import OFF_FAILURE

    return {OFF_FAILURE: True}


def _mark_invalid(writer, indices):
    """Label frames invalid (image_key 3): kept, never taken for a projection or a flat."""
    if not indices:
        return
    try:
        writer.mark_invalid(indices)
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
    from acquisition.l8121 import SourceState

    # settled: a controller still in its power-on checks (A's self-test, B's pre-heating) reads
    # neither "warm-up needed" nor standby yet; asked now, the warm-up was skipped and on() refused
    # it after the darks and flats ("warm-up needed")
    return src.settled_status() in (SourceState.WARMUP_NEEDED, SourceState.WARMING_UP)


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
