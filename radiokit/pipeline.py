"""From an experiment file to compression-induced contrast, measurements and a report.

``process(path, config) -> Result`` runs the paper's chain on one experiment file (the lab's or a
simulated one; DESIGN.md's layout) as a few public steps, each returning a typed record:

1. :func:`load_steps` -> :class:`Steps`: calibrate from the file's own darks and flats, correct
   every projection, and take each step's line integral (``-ln(I/I0)``) of its frames' mean
   transmission, steps least compressed first (by their recorded ratios or gaps);
2. :func:`choose_rois` -> :class:`RoiChoice`: the inclusion and a background rectangle beside it
   on the reference (the most compressed step), or the configuration's, and the crop around them;
3. :func:`register_pairs` -> :class:`RegisteredPair` per pair: every step onto the reference and
   each step onto the next (residual complexity by default);
4. :func:`enhance_pair` -> :class:`radiokit.results.Enhancement` per domain: the reference enhanced with the step
   before it, for every k, in the log domain (line integrals) and the paper's negative domain
   (``-I/I0``, :class:`radiokit.enhance.Domain`; the paper's "linear" images);
5. :func:`measure_domains` -> :class:`radiokit.results.DomainMeasures` per domain: contrast, CNR,
   Weber contrast and the improvement factor per k (:func:`radiokit.measure.summary`);
6. :func:`check_pairs` -> :class:`radiokit.results.PairResult` per pair: the intensity-change
   ratio and the registration's checks; for a simulated file, its end-point error against the
   stored truth.

``process`` then writes ``results.h5`` (corrected steps, registered images, fields, differences,
enhanced images), ``results.json`` (:meth:`radiokit.results.Results.to_json`, read back with
:func:`radiokit.results.load_results`) and ``report.html`` with its figures.

``process_many(paths, config, scheduler=None)`` runs many files in parallel on Dask (a local
cluster by default, or the scheduler at an address), with one progress bar over all of them.

Example (a small synthetic experiment written here; real files come from ``radiokit acquire``)::

    >>> import numpy as np, os, tempfile
    >>> from radiokit.io import ExperimentWriter, ImageKey
    >>> from radiokit.pipeline import Config, process
    >>> d = tempfile.mkdtemp()
    >>> rr, cc = np.mgrid[0:160, 0:160]
    >>> def frame(t_body, t_incl):   # a slab thinned by compression, with a denser square
    ...     L = 0.08 * t_body + 0.03 * t_incl * ((abs(rr - 80) < 10) & (abs(cc - 80) < 10))
    ...     return (100 + 3000 * np.exp(-L)).astype(np.uint16)
    >>> with ExperimentWriter(os.path.join(d, "exp.h5"), shape=(160, 160), pixel_size_mm=0.05) as w:
    ...     for _ in range(3): _ = w.append(np.full((160, 160), 100, np.uint16), image_key=ImageKey.DARK)
    ...     for _ in range(3): _ = w.append(np.full((160, 160), 3100, np.uint16), image_key=ImageKey.FLAT)
    ...     for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
    ...         _ = w.append(frame(tb, ti), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    >>> res = process(os.path.join(d, "exp.h5"), Config(crop_mm=None, report=False,
    ...               inclusion=(75, 86, 75, 86), background=(75, 86, 40, 51)), out_dir=os.path.join(d, "results"))
    >>> factor = res.record.improvement_factor
    >>> factor[1.0] > 1, factor[2.0] > factor[1.0]
    (True, True)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from radiokit._json import dumps_readable
from radiokit._names import shown
from radiokit.checks import is_number, scalar, toml_loads
from radiokit.enhance import Domain
from radiokit.errors import FormatError, RadiokitError
from radiokit.interrupts import STOP_SIGNALS, deferred
from radiokit.measure import PAPER, ROI, NoBackgroundFits
from radiokit.results import Bound, DomainMeasures, Enhancement, Images, KMeasure, PairResult, Results, Rois, k_label

__all__ = [
    "Config",
    "Result",
    "Steps",
    "RoiChoice",
    "RegisteredPair",
    "Enhancement",
    "Images",
    "process",
    "load_steps",
    "choose_rois",
    "register_pairs",
    "enhance_pair",
    "measure_domains",
    "check_pairs",
    "rois_verdict",
    "ROI_MIN_OBSERVED",
    "process_many",
    "output_folders",
    "PAPER",
    "DOMAINS",
]

if TYPE_CHECKING:
    from radiokit.register import Registration

#: The domains every run computes: line integrals, and the paper's negative transmission -I/I0.
DOMAINS = (Domain.LOG, Domain.NEGATIVE)
#: The beam's directions :attr:`Config.view` names (sim.scene's ``[beam] direction``'s two geometries)
VIEWS = ("through_plates", "side")


def _ks(ks) -> tuple:
    """The enhancement factors as floats: one number is one k (``compression_contrast``'s ``k=1``
    raised "'int' object is not iterable" here), a 0-d array one number too ("iteration over a
    0-d array"), and anything else that is no number refused, text included ("12" ran k = 1 and 2)."""
    expected = "expected enhancement factors as numbers, e.g. ks=(1, 2) or ks=2"
    one = scalar(ks)
    if is_number(one):
        return (float(one),)
    if isinstance(ks, (str, bytes)) or not isinstance(ks, Iterable) or getattr(ks, "ndim", 1) == 0:
        raise ValueError(f"ks={ks!r}: {expected}")
    out = []
    for k in ks:
        if not is_number(scalar(k)):  # float("2") took text, float([1, 2]) raised a TypeError
            raise ValueError(f"ks={ks!r}: {k!r} is not a number; {expected}")
        out.append(float(scalar(k)))
    return tuple(out)


def _crop_mm(value) -> float | None:
    """``crop_mm`` as a float (a 0-d array is its number), or None; a ValueError naming anything else
    (text or a list reached numpy's ``isfinite`` and raised a TypeError, ``True`` ran as a 1 mm crop)."""
    if value is None:
        return None
    crop = scalar(value)
    if not (is_number(crop) and np.isfinite(crop) and crop > 0):
        raise ValueError(f"crop_mm={value!r}: expected the crop's side in mm, a number > 0 (None: the whole frame)")
    return float(crop)


@dataclass
class Config:
    """What :func:`process` does. ROIs are ``(row0, row1, col0, col1)`` half-open, in whole pixels
    of the full frame (``roi_units="px"``) or millimetres from the frame's top-left corner
    (``"mm"``: any number, rounded to pixels); ``None`` finds them automatically. Numbers may be
    numpy's, a 0-d array included; text is refused, not parsed. ``domain``: the headline domain, ``"negative"``
    (the paper's ``-I/I0``, default) or ``"log"``; both are computed. ``ks``: the enhancement
    factors k, each in (0, 100] (one number, or several: ``(1, 2)``, the paper's)."""

    ks: tuple = (1.0, 2.0)
    domain: Domain = Domain.NEGATIVE
    method: str = "rc"
    register_options: dict = field(default_factory=dict)  # B-spline methods: preset "auto" unless given
    crop_mm: float | None = 30.0  # side of the square around the inclusion kept in the outputs; None: all
    inclusion: tuple | None = None
    background: tuple | None = None
    roi_units: str = "px"
    use_truth_rois: bool = False  # simulated files: place the ROIs on the stored inclusion mask
    report: bool = True
    progress: bool = True
    control: str | None = None  # a control experiment (inclusion as soft as the background)
    cross_check: str | None = "ncc"  # register the main pair again with this similarity and flag disagreement
    # every pair registered a second time, differently regularised, and a trusted result flagged where the
    # two differ (register(..., regularisation_check=True); off by default: 0.3-1 s more per pair)
    regularisation_check: bool = False
    # the beam's direction, for the improvement factor's bound: "through_plates" or "side" (no
    # bound holds); None: a simulated file's scene says, else through the plates. A control takes
    # its experiment's (it is imaged as the experiment is)
    view: str | None = None

    def __post_init__(self):
        self.domain = Domain.parse(self.domain, "domain")
        if self.domain not in DOMAINS:
            raise ValueError(
                f"domain={self.domain.value!r}: the pipeline computes {' and '.join(repr(d.value) for d in DOMAINS)}"
            )
        if self.roi_units not in ("px", "mm"):
            raise ValueError(f"roi_units={self.roi_units!r}: expected 'px' or 'mm'")
        if self.view not in (None, *VIEWS):
            raise ValueError(
                f"view={self.view!r}: expected {' or '.join(map(repr, VIEWS))} (None: the file's scene says)"
            )
        for name in ("use_truth_rois", "report", "progress", "regularisation_check"):
            value = getattr(self, name)
            if not isinstance(value, (bool, np.bool_)):  # "no" is truthy: report="no" wrote the report
                raise ValueError(f"{name}={value!r}: expected True or False")
            setattr(self, name, bool(value))
        if self.control is not None:
            if not isinstance(self.control, (str, os.PathLike)):  # refused only after the file's run
                raise ValueError(f"control={self.control!r}: expected a control experiment file's path")
            self.control = os.fspath(self.control)
        self.ks = _ks(self.ks)
        typed = " ".join(f"{k:g}" for k in self.ks) or "()"  # as --k takes them (was a tuple in two of three lines)
        if not self.ks or not all(np.isfinite(self.ks)):
            raise ValueError(f"ks={typed}: expected finite enhancement factors")
        if len(set(self.ks)) != len(self.ks):
            raise ValueError(f"ks={typed}: each enhancement factor once")
        if not all(0 < k <= K_MAX for k in self.ks):  # k = 0 is the reference itself; IF(k) - 1 is linear in k
            raise ValueError(f"ks={typed}: enhancement factors lie in (0, {K_MAX:g}] (the paper's: 1 and 2)")
        self.crop_mm = _crop_mm(self.crop_mm)
        if not isinstance(self.register_options, Mapping):  # a str was read as option names, one per character
            raise ValueError(
                f"register_options={self.register_options!r}: expected a dict of option names and values, "
                "e.g. {'preset': 'fast'}"
            )
        self.register_options = {name: scalar(v) for name, v in self.register_options.items()}
        _check_methods(self.method, self.cross_check, self.register_options)
        self._check_rectangles()

    def _check_rectangles(self) -> None:
        """The ROIs given as numbers, refused now as :func:`choose_rois` would refuse them, not after
        the file's correction (``--inclusion nan 1 2 3`` cost the whole correction first), and the
        same rectangle twice (a "zero reference contrast" at the very end). In mm, whether a ROI
        rounds to no pixel waits for the file's pixel size."""
        given = {}
        for name in ("inclusion", "background"):
            value = getattr(self, name)
            if value is None or isinstance(value, ROI):
                continue
            if self.roi_units == "px":
                roi = _roi(value, "px", 1.0, name)
                given[name] = (roi.row0, roi.row1, roi.col0, roi.col1)
                continue
            r0, r1, c0, c1 = _roi_numbers(value, "mm", name)
            if not (r0 < r1 and c0 < c1):
                raise ValueError(f"{name} ROI {value!r} (mm): ROI is empty (need row1 > row0 and col1 > col0)")
            given[name] = (r0, r1, c0, c1)
        if len(given) == 2 and _overlap_bounds(given["inclusion"], given["background"]):
            raise ValueError(_overlap_words(self.background, f"the inclusion ROI {self.inclusion!r}"))


#: The largest enhancement factor: ``IF(k) - 1`` is linear in k, so a larger k shows nothing new,
#: while ``k (R - M)`` swamps the reference in float32 (1e308 overflowed after the registrations).
K_MAX = 100.0


def _check_methods(method, cross_check, options) -> None:
    """Refuse, before any work, an unknown method or cross-check, an option ``method`` does
    not take (a B-spline ``preset`` given to a peer) and a B-spline option's value of the wrong
    kind or range, as ``ValueError`` in one line: found only at the first registration they cost
    the correction, and a peer's ``TypeError`` a traceback."""
    from radiokit.register import check_options, load_methods

    methods = load_methods()
    for what, name in (("method", method), ("cross_check", cross_check)):
        if name is not None and not (isinstance(name, str) and name in methods):  # a list: TypeError unhashable
            raise ValueError(f"{what}={name!r}: unknown registration method; available: {', '.join(sorted(methods))}")
    check_options(method, options)


def _cross_check_options(cfg) -> dict:
    """The main method's options for the cross-check when both are B-spline methods (one
    option set); a peer takes its own defaults, since the B-spline options are not its own."""
    from radiokit.register import BSPLINE_METHODS, with_default_preset

    both = cfg.method in BSPLINE_METHODS and cfg.cross_check in BSPLINE_METHODS
    return with_default_preset(cfg.cross_check, cfg.register_options if both else {})


@dataclass(frozen=True)
class Steps:
    """The corrected line integral of each compression step (``-ln`` of its frames' mean
    transmission), least compressed first (by the recorded ratios, else gaps, else step
    numbers), with the step numbers, compression ratios, pixel size and the seconds spent;
    ``unknown`` maps a step number to where its frames held NaN or inf pixels (the correction
    filled them): ``(rows, cols)`` int32, the first such frame's index per pixel, -1 elsewhere
    (only steps that held any), and ``nonfinite`` per step (pixels, frames holding any, frames)."""

    images: np.ndarray
    numbers: tuple[int, ...]
    ratios: tuple[float, ...]
    pixel_size_mm: float
    timings: dict
    unknown: dict = field(default_factory=dict)
    nonfinite: dict = field(default_factory=dict)
    pixel_size_recorded: bool = True  #: False: the file records none, the C7942's was assumed


@dataclass(frozen=True)
class RoiChoice:
    """The inclusion and background ROIs and the crop, all in full-frame pixels."""

    inclusion: ROI
    background: ROI
    crop: tuple[int, int, int, int]

    def cropped(self) -> tuple[ROI, ROI]:
        """The two ROIs in the cropped image's pixels."""
        r0, c0 = self.crop[0], self.crop[2]
        return self.inclusion.shifted(-r0, -c0), self.background.shifted(-r0, -c0)

    def slices(self) -> tuple[slice, slice]:
        return slice(self.crop[0], self.crop[1]), slice(self.crop[2], self.crop[3])


@dataclass(frozen=True)
class RegisteredPair:
    """Step ``moving`` (an index into :attr:`Steps.images`) registered onto step ``reference``:
    the registration with its field and confidence cropped, the warped moving step (warped whole,
    then cropped: no border effects) and, for the cross-checked pair, :func:`cross_check`."""

    moving: int
    reference: int
    registration: Registration
    warped: np.ndarray
    cross_check: dict | None = None


@dataclass
class Result:
    """One run: the numbers (``record``, :class:`radiokit.results.Results`), the images, the files."""

    record: Results
    images: Images
    files: dict

    @property
    def results(self) -> dict:
        """The numbers as in ``results.json`` (:meth:`radiokit.results.Results.to_json`; a new dict each call)."""
        return self.record.to_json()

    @property
    def arrays(self) -> dict:
        """The images by name (:meth:`radiokit.results.Images.as_dict`)."""
        return self.images.as_dict(self.record)


def _roi_numbers(value, units, name) -> tuple[float, float, float, float]:
    """``Config``'s ``name`` ROI as four finite floats, or a ValueError naming it and what its
    bounds are in ``units`` (pixels whole numbers, mm any number); a bound given as text or a bool
    is refused (``float`` took ``"1"``, and ``True`` as row 1)."""
    what = f"{name} ROI {value!r}"
    bounds = "four whole numbers of pixels" if units == "px" else "four numbers in mm"
    expected = f"expected (row0, row1, col0, col1), {bounds}"
    try:
        if isinstance(value, dict):
            value = (value["row0"], value["row1"], value["col0"], value["col1"])
        if isinstance(value, (str, bytes)):
            raise TypeError
        items = list(value)
    except (TypeError, ValueError, KeyError):
        raise ValueError(f"{what}: {expected}") from None
    if len(items) != 4:
        raise ValueError(f"{what}: {expected}")
    numbers = [scalar(v) for v in items]
    for given, v in zip(items, numbers):
        if not is_number(v):
            raise ValueError(f"{what}: {given!r} is not a number; {expected}")
    r0, r1, c0, c1 = (float(v) for v in numbers)
    if not np.all(np.isfinite([r0, r1, c0, c1])):
        raise ValueError(f"{what}: its bounds must be finite")
    return r0, r1, c0, c1


def _roi(value, units, pixel_size_mm, name):
    """``Config``'s ``name`` ROI as an :class:`ROI` in pixels, or None; a ValueError naming it
    when it is not four finite numbers or rounds to an empty rectangle (it was a Python
    unpacking, conversion or key error)."""
    if value is None:
        return None
    if isinstance(value, ROI):
        return value
    what = f"{name} ROI {value!r}"
    r0, r1, c0, c1 = _roi_numbers(value, units, name)
    if units == "mm":
        # from the frame's corner, half up as ROI.from_mm: round() took halves to even, so a
        # rectangle 3 pixels wide on half-pixel edges became 2 or 4 by where it sat (review s42api)
        try:
            return ROI.from_mm_edges((r0, r1, c0, c1), pixel_size_mm)
        except ValueError as exc:
            raise ValueError(f"{what} ({units}): {exc}") from None
    # pixels: a fractional one was rounded without a word; mm are rounded to pixels (README). A
    # bound computed in floating point (0.1 * 300 = 30.000000000000004) is that whole number: the
    # tolerance is far above float64's rounding and far below any real fraction
    part = [repr(v) for v in (r0, r1, c0, c1) if abs(v - round(v)) > 1e-6 * max(1.0, abs(v))]
    if part:
        raise ValueError(
            f"{what}: pixel bounds are whole numbers, not {', '.join(part)}"
            " (for millimetres, rounded to pixels: roi_units='mm')"
        )
    return _checked_roi(what, units, *(int(round(v)) for v in (r0, r1, c0, c1)))


def _checked_roi(what, units, r0, r1, c0, c1) -> ROI:
    try:
        return ROI(r0, r1, c0, c1)
    except ValueError as exc:
        raise ValueError(f"{what} ({units}): {exc}") from None


def load_steps(path, progress: bool = False) -> Steps:
    """Calibrate from the file's darks and flats; the corrected line integral of each step
    (``-ln`` of its frames' mean transmission), least compressed first, step numbers, ratios,
    pixel size (:class:`Steps`)."""
    steps = _load_steps(path, progress)
    _warn_nonfinite(path, steps.nonfinite)
    return steps


def _too_few_steps(numbers: list, unnumbered: int) -> str:
    """What a file of fewer than two numbered compression steps holds (it said "found steps []" of
    projections written without a step number, as if there were none)."""
    found = f"found step {numbers[0]} only" if numbers else "found none"
    if unnumbered:
        found += f"; {unnumbered} projection(s) carry no step number (a negative step: not written)"
    return f"needs projections of at least two compression steps; {found}"


def _numbered_steps(path, meta, keys) -> tuple[np.ndarray, list[int]]:
    """The file's step of each frame (-1 where none is recorded) and its projections' step
    numbers, refusing a file of fewer than two numbered steps in words saying what it holds."""
    from radiokit.io import ImageKey

    steps = np.asarray(meta.get("step", np.full(len(keys), -1)))
    projection = keys == ImageKey.PROJECTION
    numbers = sorted(int(s) for s in np.unique(steps[projection & (steps >= 0)]))
    if "step" not in meta and projection.any():  # "a negative step" named one the file never wrote
        raise FormatError(
            path,
            f"needs projections of at least two compression steps; its {int(projection.sum())} projection(s) have "
            "none recorded (no /entry/sample/compression/step, which NXtomo and Data Exchange files lack): write "
            "each frame's step there, one per frame (-1 for darks and flats)",
        )
    if len(numbers) < 2:
        raise FormatError(path, _too_few_steps(numbers, int(np.sum(projection & (steps < 0)))))
    return steps, numbers


def _check_step_records(path, keys, steps, ratios, gaps, numbers) -> None:
    """Refuse, naming the first frame, what DESIGN.md's layout lets another program write but no
    series means, a projection with a negative step (-1 is the darks' and flats'), which was left
    out without a word (a whole step of a foreign file dropped, the run measured on the other two
    with exit code 0); and warn of a step whose frames record different ratios or gaps (0.2 and
    0.22 were averaged into one image at 0.21 without a word; 40 and 41 mm into the bound's 40.5),
    once a step, naming both where both differ: not refused, since radiokit's own series can write
    one (a step resumed on a manual frame records the gap the operator measured again, and its
    ratio, 1 - gap/h0). Frames with no record (NaN) are not compared."""
    from radiokit.io import ImageKey

    projection = keys == ImageKey.PROJECTION
    loose = np.flatnonzero(projection & (steps < 0))
    if loose.size:
        i = int(loose[0])
        more = f" (and {loose.size - 1} more)" if loose.size > 1 else ""
        raise FormatError(
            path,
            f"frame {i}{more} is a projection (image_key 0) with step {int(steps[i])}, in no compression step "
            f"beside steps {', '.join(map(str, numbers))} (a negative step is a dark's or a flat's): give it its "
            "step, or mark it invalid (image_key 3)",
        )
    # (values, what, shown as, tolerance): float32 storage of one value differs by < 1e-7 of it;
    # gaps are in m, said in mm
    records = (
        (ratios, "compression ratios", lambda v: f"{v:.6g}", lambda v: 1e-6),
        (gaps, "plate gaps", lambda v: f"{v * 1e3:.6g} mm", lambda v: 1e-6 * float(np.max(np.abs(v)))),
    )
    for s in numbers:
        spreads, means = [], []
        for values, what, say, tolerance in records:
            idx = np.flatnonzero(projection & (steps == s) & np.isfinite(values))
            if idx.size and np.ptp(values[idx]) > tolerance(values[idx]):
                lo, hi = int(idx[np.argmin(values[idx])]), int(idx[np.argmax(values[idx])])
                spreads.append(f"{what} from {say(values[lo])} (frame {lo}) to {say(values[hi])} (frame {hi})")
                means.append(say(float(np.mean(values[idx]))))
        if spreads:
            import warnings

            warnings.warn(
                f"{shown(path)}: step {s}'s frames record {' and '.join(spreads)}: averaged as one image at their "
                f"mean, {' and '.join(means)}; frames of another compression (a mislabelled step) should "
                "carry their own step, or image_key 3 (invalid)",
                UserWarning,
                stacklevel=4,
            )


def _load_steps(path, progress: bool) -> Steps:
    """:func:`load_steps` without its NaN warning: :func:`process` refuses such pixels inside a
    ROI (:func:`_check_unknown_in_rois`) and warns of them only once they pass."""
    from radiokit.calibrate import Calibration, exposure_factors
    from radiokit.io import C7942_PIXEL_SIZE_MM, ImageKey, open_frames
    from radiokit.progress import tqdm

    t = time.perf_counter()
    cal = Calibration.from_experiment(path)
    t_cal = time.perf_counter() - t
    t = time.perf_counter()
    with open_frames(path) as src:
        meta = src.meta
        _check_square_pixels(path, meta)  # Steps records one pitch (process checked before any work)
        keys = np.asarray(meta["image_key"])
        steps, numbers = _numbered_steps(path, meta, keys)
        ratios_all = np.asarray(meta.get("ratio", np.full(len(keys), np.nan)), float)
        gaps = np.asarray(meta.get("gap", np.full(len(keys), np.nan)), float)
        _check_step_records(path, keys, steps, ratios_all, gaps, numbers)
        numbers = _compression_order(numbers, keys, steps, ratios_all, gaps, path)
        images, ratios = [], []
        projections = np.flatnonzero((keys == ImageKey.PROJECTION) & (steps >= 0))
        # one call for them all: its voltage warning counts every frame (per step, it said "1
        # frame(s)" where three steps of one frame each were at another voltage)
        all_factors = exposure_factors(cal, meta, path, projections)
        bar = tqdm(total=projections.size, desc=f"correct {Path(path).name}", unit="frame", disable=not progress)
        saturated, nonfinite, unknown = {}, {}, {}
        for s in numbers:
            idx = projections[steps[projections] == s]
            factors = all_factors[steps[projections] == s]
            image, saturated[s], nonfinite[s], where = _step_image(cal, src, path, s, idx, factors, bar)
            if where is not None:
                unknown[s] = where
            _check_below_the_flats(path, s, image)
            images.append(image)
            ratios.append(float(np.nanmean(ratios_all[idx])) if np.isfinite(ratios_all[idx]).any() else float("nan"))
        bar.close()
        _warn_saturated(path, saturated, cal.thresholds.saturation)
        recorded = meta.get("pixel_size_mm")
        if recorded is None:
            import warnings

            # every length in mm rests on it (ROI sizes, the crop, the bound's plate gaps): said,
            # and the report says it was assumed (review s41proc: reported as the file's)
            warnings.warn(
                f"{shown(path)}: records no pixel size (x_pixel_size): taking the C7942's {C7942_PIXEL_SIZE_MM:g} mm; "
                "every length in mm (ROI sizes, the crop) assumes it",
                UserWarning,
                stacklevel=2,
            )
        pixel_size_mm = float(C7942_PIXEL_SIZE_MM if recorded is None else recorded)
    return Steps(
        np.stack(images),
        tuple(numbers),
        tuple(ratios),
        pixel_size_mm,
        dict(calibrate_s=t_cal, correct_s=time.perf_counter() - t),
        unknown,
        nonfinite,
        pixel_size_recorded=recorded is not None,
    )


def _check_unknown_in_rois(path, steps: Steps, rois: RoiChoice) -> None:
    """Refuse NaN or inf projection pixels inside the inclusion or background ROI, naming the
    first frame and the ROI. Why: the correction fills them from their neighbours, and a ROI on
    them measures the fill (a 10 x 10 NaN block in the inclusion moved the change ratio from
    -5.9 to -23.3, exit code 0, under a warning asking the user to check what radiokit knew).
    Checked where each step's frames hold them; a moving step's pixels shift by its field, a
    few pixels, when registered onto the reference."""
    for name, roi in (("inclusion", rois.inclusion), ("background", rois.background)):
        for s, where in steps.unknown.items():
            inside = where[roi.slices]
            hit = inside[inside >= 0]
            if hit.size:
                raise FormatError(
                    path,
                    f"frame {int(hit.min())} (step {s}): {hit.size} NaN or inf pixels inside the {name} ROI "
                    f"(rows {roi.row0}-{roi.row1}, cols {roi.col0}-{roi.col1}), which the correction fills from "
                    "their neighbours: the ROI would measure the fill, not the object; give ROIs clear of them",
                )


def _check_unknown_moved_into_rois(path, steps: Steps, rois: RoiChoice, pairs) -> None:
    """Refuse NaN or inf pixels of a moving step that its registration carries into a ROI, naming
    the steps and the ROI. Why: :func:`_check_unknown_in_rois` judges them where the file holds
    them, and the field moves them (a block 3 columns beside the inclusion was registered into
    it, its fill measured, exit code 0). A registered pixel counts as one when its nearest sample
    is one (the bilinear share of unknown pixels at least half): with no motion, the same pixels as
    the file's."""
    from radiokit.register import warp

    inc_c, bg_c = rois.cropped()
    offset = np.array([rois.crop[0], rois.crop[2]], np.float32)[:, None, None]
    for p in pairs:
        moving, reference = steps.numbers[p.moving], steps.numbers[p.reference]
        where = steps.unknown.get(moving)
        if where is None:
            continue
        # the fields are cropped: sample the whole frame's pixels at the crop's positions
        moved = warp((where >= 0).astype(np.float32), p.registration.displacement + offset) >= 0.5
        for name, roi, full in (("inclusion", inc_c, rois.inclusion), ("background", bg_c, rois.background)):
            hit = int(np.count_nonzero(moved[roi.slices]))
            if hit:
                raise FormatError(
                    path,
                    f"step {moving} registered onto step {reference}: its field moves {hit} NaN or inf pixels into "
                    f"the {name} ROI (rows {full.row0}-{full.row1}, cols {full.col0}-{full.col1}), which the "
                    "correction filled from their neighbours: the ROI would measure the fill, not the object; "
                    "give ROIs clear of them",
                )


def _check_below_the_flats(path, step, image) -> None:
    """Refuse a step whose line integral ``image`` says most of the frame is brighter than the
    flats. Why: flats at a quarter of the projections' tube current, no currents recorded, gave
    negative line integrals everywhere, an empty body, and a traceback in the cross-check."""
    from radiokit.correct import brighter_than_flats

    transmission = brighter_than_flats(image, "log")
    if transmission is not None:
        raise FormatError(
            path,
            f"step {step}'s projections are brighter than the flats, {transmission:.2f}x their level (median "
            "transmission), which no object makes them: the flats were taken at a lower exposure (tube current or time) than "
            "the projections, and no recorded currents correct it",
        )


def _compression_order(numbers, keys, steps, ratios, gaps, path=None) -> list[int]:
    """The step numbers least compressed first: by the recorded compression ratio when every
    step has one, else by the recorded plate gap (widest first) when every step has one, else
    by step number; ties keep the step numbers' order.

    Why: the reference is the *most compressed* step (DESIGN.md), not the highest-numbered. A
    series taken while releasing the plates (step 1 at 25 %, step 3 at 15 %) made the least
    compressed step the reference, registered 20 % onto 15 %, and reported "plate gaps not
    recorded: no bound" because the gaps, recorded, opened instead of closing."""
    from radiokit.io import ImageKey

    def per_step(values):
        out = []
        for s in numbers:
            v = values[(keys == ImageKey.PROJECTION) & (steps == s)]
            out.append(float(np.nanmean(v)) if np.isfinite(v).any() else float("nan"))
        return np.asarray(out)

    for values, name, sign in ((per_step(ratios), "compression ratio", 1.0), (per_step(gaps), "plate gap", -1.0)):
        if np.isfinite(values).all():
            order = np.argsort(sign * values, kind="stable")
            _warn_tied_reference(path, [numbers[i] for i in order[-2:]], values[order[-2:]], name)
            return [numbers[i] for i in order]
    return list(numbers)


def _warn_tied_reference(path, pair, values, name) -> None:
    """Warn when the two most compressed steps record one ``name``: the reference was a tie the
    step numbers broke without a word, and the main pair's compression-induced contrast is that
    of no compression (a ratio typed twice, or a repeat at one compression)."""
    if len(pair) == 2 and values[0] == values[1]:
        import warnings

        value = f"{values[0]:g}" if name == "compression ratio" else f"{values[0] * 1e3:g} mm"  # gaps are in m
        warnings.warn(
            f"{shown(path)}: steps {pair[0]} and {pair[1]} record one {name}, {value}: the main pair {pair[0]}->{pair[1]} "
            f"compares two images of one compression (the reference taken by step number); check the recorded {name}s",
            UserWarning,
            stacklevel=4,
        )


def _step_image(cal, src, path, step, idx, factors, bar):
    """The line integral of one step's frames ``idx`` (each at the flats' tube current,
    ``factors``), ``-ln`` of their mean transmission, and how many saturated pixels its frames
    held, and how many NaN or inf ones (filled by the correction), each as (pixels, frames holding
    any, frames): a per-frame average printed rounded said "0" of one such pixel in 4 frames.

    Why the transmissions are averaged, not the logs: the detector is linear in the dose, so N
    frames averaged are one N times longer exposure, and ``-ln`` of their mean is biased by
    ``1 / (2 N I0 T)`` (Jensen: ``var / (2 mean^2)``, ``I0 T`` in detected quanta; a panel's
    grey levels are ``g`` quanta-equivalents each, so ``g / (2 N counts)``). The mean of each frame's
    ``-ln`` keeps a single frame's bias, ``1 / (2 I0 T)``, however many frames are taken: 0.0125
    at 40 counts behind the object, 40 standard errors of a 128 x 128 ROI's mean of 16 frames.
    One frame is the same estimator either way; it takes the log domain's one compiled pass."""
    from radiokit.calibrate import frame_saturation
    from radiokit.correct import check_above_dark, correct_frames

    domain = "log" if len(idx) == 1 else "linear"
    acc, sat, bad_n, where = None, [0, 0, len(idx)], [0, 0, len(idx)], None
    for i, factor in zip(idx, factors):
        raw = src[i]
        try:  # a frame with the beam off would pull its step's mean towards nothing
            check_above_dark(cal, raw)
        except ValueError as exc:
            raise FormatError(path, f"frame {i} (step {step}): {exc}") from None
        top = frame_saturation(cal.thresholds.saturation, raw, cal.mask) if raw.dtype.kind in "uif" else None
        if top is not None:  # +inf passes any level: no value, counted below as NaN or inf
            over = (raw >= top) & np.isfinite(raw) if raw.dtype.kind == "f" else raw >= top
            # defect pixels are filled, no measurement: a stuck one was "saturated" in every frame
            n = int(np.count_nonzero(over & (cal.mask == 0)))
            sat[0], sat[1] = sat[0] + n, sat[1] + (n > 0)
        if raw.dtype.kind == "f":
            bad = ~np.isfinite(raw)
            if bad.any():
                bad_n[0], bad_n[1] = bad_n[0] + int(np.count_nonzero(bad)), bad_n[1] + 1
                where = np.full(raw.shape, -1, np.int32) if where is None else where
                where[bad & (where < 0)] = i
        try:  # its refusal names the frame (one of only NaN was "a raw frame" of dozens)
            # checked above (no signal) and as the step's mean (brighter than the flats): a frame
            # judged before its exposure is rescaled would be taken for one at another exposure
            image = correct_frames(cal, raw, domain=domain, check=False)
        except ValueError as exc:
            raise FormatError(path, f"frame {i} (step {step}): {exc}") from None
        if domain == "log":
            image = image - np.float32(np.log(factor))  # the flats' current
        else:
            image = image * np.float32(factor)
        acc = image.astype(np.float64) if acc is None else acc + image
        bar.update()
    if domain == "log":
        return acc.astype(np.float32), tuple(sat), tuple(bad_n), where
    # linear correction clamps raw - dark to half a count: every transmission and mean is > 0
    return (-np.log(acc / len(idx))).astype(np.float32), tuple(sat), tuple(bad_n), where


def _warn_per_step(path, counts: dict, what: str, advice: str) -> None:
    """One line when projections hold pixels of unknown intensity (``counts``: per step, (pixels,
    frames holding any, frames)): saturated ones (a lower bound) or NaN/inf ones (another lab's float frames mark masked
    regions and detector gaps so; the correction fills them from their neighbours). Why: a ROI or
    a registration that leans on them measures the ADC or the fill, not the object, and nothing
    said so."""
    import warnings

    from radiokit.calibrate import CalibrationWarning

    if any(n > 0 for n, _, _ in counts.values()):
        per_step = ", ".join(
            f"step {s}: {n} in {k} of {m} frame{'s' if m > 1 else ''}" for s, (n, k, m) in counts.items() if n > 0
        )
        warnings.warn(
            f"{shown(path)}: {what} in the projections ({per_step}): {advice}", CalibrationWarning, stacklevel=4
        )


def _warn_saturated(path, saturated: dict, level) -> None:
    _warn_per_step(
        path,
        saturated,
        "saturated pixels" if level is None else f"saturated pixels (>= {level:.7g})",  # (a scaled file's: float32)
        "their intensity is unknown; check that they lie outside the ROIs, or lower the exposure",
    )


def _warn_nonfinite(path, nonfinite: dict) -> None:
    _warn_per_step(
        path,
        nonfinite,
        "NaN or inf pixels",
        "filled from their neighbours (radiokit process refuses them inside a ROI)",
    )


def _sim_truth(path, numbers):
    """Simulated files: the inclusion mask of the last step and the truth fields, or None."""
    from radiokit.io import read_simulation

    pairs = [(a, b) for a in numbers for b in numbers if a < b]
    sim = read_simulation(path, steps=[-1], pairs=pairs)
    if sim is None:
        return None
    return {
        "fields": dict(sim.displacement),
        "scene": sim.scene_name,
        "scene_toml": sim.scene_toml,
        "inclusion_mask": sim.inclusion_mask[-1].astype(bool),
        "line_integral": sim.line_integral[-1],
    }


def _crop_box(inclusion, shape, side_px):
    """A square of ``side_px`` centred on the inclusion ROI, inside the frame."""
    rows, cols = shape
    side_r, side_c = min(side_px, rows), min(side_px, cols)
    cr, cc = (inclusion.row0 + inclusion.row1) // 2, (inclusion.col0 + inclusion.col1) // 2
    r0 = int(np.clip(cr - side_r // 2, 0, rows - side_r))
    c0 = int(np.clip(cc - side_c // 2, 0, cols - side_c))
    return r0, r0 + side_r, c0, c0 + side_c


def _body_mask(image):
    return image > 0.2 * float(np.percentile(image, 99.5))


def cross_check(field, other, body, method):
    """How far two registrations of one pair disagree inside ``body``: median and 95th percentile
    of ``|field - other|`` (px), and whether they agree: median disagreement under
    max(2 px, half the larger field's median magnitude).

    Why: a similarity can have its minimum away from the truth and still report success (its own
    energy dropped). Measured on the virtual experiment: seed-breast, rc against ncc 1.6 px
    apart with fields of 7 px (both within 1-4 px of the truth); the pva-phantom side view,
    22 px apart (rc 21 px off the truth, ncc 1.8 px)."""
    d = np.hypot(*(np.asarray(field) - np.asarray(other)))[body]
    mag = max(float(np.median(np.hypot(*field)[body])), float(np.median(np.hypot(*other)[body])))
    med = float(np.median(d))
    return {
        "method": method,
        "median_px": med,
        "p95_px": float(np.percentile(d, 95)),
        "agree": bool(med <= max(2.0, 0.5 * mag)),
    }


#: a ROI lies in an observed region when at least this share of it is observed (confidence
#: >= 0.5): the paper's contrast is the ROI's mean, so once half or more of its pixels were
#: registered by the regulariser's guess rather than by the images, so is the number; the same
#: line ``radiokit.register`` draws for the object as a whole (observed under half: not ok)
ROI_MIN_OBSERVED = 0.5


def rois_verdict(observed: dict | None) -> tuple[bool | None, str]:
    """Do the ROIs lie where the motion was observed? ``observed``: ROI name -> the share of it
    observed (:func:`radiokit.register.roi_observed`). Returns ``(ok, reason)``: None and ""
    without a confidence map; False, naming each ROI observed in under
    :data:`ROI_MIN_OBSERVED` of its area, otherwise True and ""."""
    if observed is None:
        return None, ""
    unseen = {name: share for name, share in observed.items() if share < ROI_MIN_OBSERVED}
    if not unseen:
        return True, ""
    which = " and ".join(f"the {name} ROI ({100 * (1 - s):.0f} % of it)" for name, s in unseen.items())
    verb = "lies" if len(unseen) == 1 else "lie"
    return False, (
        f"{which} {verb} where the motion was not observed (confidence map): the field there is the "
        "regulariser's guess, and so is the contrast measured there"
    )


def _step_gaps_mm(path, numbers):
    """Mean plate gap (mm) of each step's projections, NaN where the file does not record it."""
    from radiokit.io import ImageKey, open_frames

    with open_frames(path) as src:
        meta = src.meta
        keys = np.asarray(meta["image_key"])
        steps = np.asarray(meta.get("step", np.full(len(keys), -1)))
        gap = np.asarray(meta.get("gap", np.full(len(keys), np.nan)), float) * 1e3
    out = []
    for s in numbers:
        g = gap[(keys == ImageKey.PROJECTION) & (steps == s)]
        out.append(float(np.nanmean(g)) if np.isfinite(g).any() else float("nan"))
    return out


def _scene_view(truth) -> str | None:
    """The beam's direction a simulated file's scene states (``VIEWS``), or None."""
    import tomllib

    scene_text = truth.get("scene_toml") if truth else None
    try:
        beam = toml_loads(scene_text).get("beam", {}) if scene_text else None
    except tomllib.TOMLDecodeError:
        return None
    if not isinstance(beam, dict):
        return None if beam is None else "through_plates"
    return "side" if beam.get("direction", "y") in ("z", "side") else "through_plates"


def _bound(path, numbers, truth, bg_log_mean, ks, view=None) -> tuple[Bound, dict]:
    """The improvement factor's bound (:func:`radiokit.measure.improvement_bound`) for the main
    pair: ``mu_b`` from a simulated file's scene, else from the reference's background ROI
    (``mean L_bg / gap``: through the plates a background column spans the gap). Returns the
    :class:`Bound` and ``{Domain: {k: bound}}``, empty where the gaps are not recorded or the
    beam runs from the side (no bound holds there): ``view``, the run's (:func:`_scene_view`, else
    the configured one)."""
    import tomllib

    from radiokit.measure import improvement_bound

    gaps = _step_gaps_mm(path, numbers)
    dg = gaps[-2] - gaps[-1]
    mu_b = None
    scene_text = truth.get("scene_toml") if truth else None
    caveat = ""
    if scene_text:
        try:
            sc = toml_loads(scene_text)
            mu = sc["body"]["material"]["attenuation_per_cm"]
        except (tomllib.TOMLDecodeError, KeyError, TypeError, AttributeError):
            mu = None
        imaging = sc.get("imaging", {}) if mu is not None and isinstance(sc.get("imaging"), dict) else {}
        # The bound is Beer-Lambert's at one energy. A spectrum's line integral is concave in the
        # thickness (beam hardening): a rigid inclusion behind a thinner column gains log contrast,
        # IF(1) 1.011 for seed-breast's tube, and scatter is not thinned by the plates at all.
        poly = imaging.get("beam", "monochromatic") != "monochromatic"
        scatter = is_number(imaging.get("scatter_fraction", 0.0)) and imaging.get("scatter_fraction", 0.0) > 0
        if poly or scatter:
            caveat = (
                "; for a monochromatic primary beam: this scene's "
                + " and ".join(w for w, on in (("tube spectrum (beam hardening)", poly), ("scatter", scatter)) if on)
                + " can pass it"
            )
        if mu is not None:
            # TOML's `true` is Python's 1: float() took it for 1/cm, and "0.3" or nan too, a wrong bound in silence
            try:
                positive = is_number(mu) and math.isfinite(float(mu)) and mu > 0
            except OverflowError:  # a TOML integer past float's range (10**400): a traceback (s52)
                positive = False
            if not positive:
                raise FormatError(
                    path,
                    f"simulation truth: scene body.material.attenuation_per_cm = {json.dumps(mu)}: "
                    "expected a positive number (1/cm)",
                )
            mu_b = mu / 10
    if view == "side":
        return Bound(None, "beam from the side: columns lengthen as the body expands, no bound holds"), {}
    if not (np.isfinite(dg) and np.isfinite(gaps[-1]) and gaps[-1] > 0):
        return Bound(None, "plate gaps not recorded: no bound"), {}
    if dg < 0:  # the recorded ratios put the steps in another order than the gaps do
        return Bound(None, f"the plate gap opens by {-dg:.3g} mm towards the reference step: no bound"), {}
    if mu_b is not None:
        basis = "through the plates; mu_b from the simulated scene, gaps from the file" + caveat
    else:
        mu_b = max(bg_log_mean, 0.0) / gaps[-1]
        basis = (
            "assumes the beam through the plates; mu_b = background line integral of the reference "
            "/ its gap, gaps from the file"
        )
    return Bound(mu_b * dg, basis), {
        dom: {k: improvement_bound(k, mu_b, dg, dom.value) if k >= 0 else None for k in ks} for dom in DOMAINS
    }


def _epe(displacement, truth, mask):
    e = np.sqrt(((displacement - truth) ** 2).sum(axis=0))
    e = e[mask] if mask is not None and mask.any() else e.ravel()
    return float(np.median(e)), float(np.percentile(e, 95))


def _bounds(roi: ROI) -> tuple[int, int, int, int]:
    return roi.row0, roi.row1, roi.col0, roi.col1


def _within_inclusion(found, centre) -> bool:
    """Whether ``centre`` lies in the inclusion whose automatic ROI is ``found`` (None: none was
    found). That ROI is about the central half of the inclusion's width (find_rois), so the
    inclusion is taken as twice its size about its centre."""
    if found is None:
        return False
    (rc, cc), (h, w) = found.center, found.shape
    return abs(centre[0] - rc) <= h and abs(centre[1] - cc) <= w


def _overlap(a, b) -> bool:
    """Whether ROIs ``a`` and ``b`` share a pixel."""
    return _overlap_bounds((a.row0, a.row1, a.col0, a.col1), (b.row0, b.row1, b.col0, b.col1))


def _overlap_bounds(a, b) -> bool:
    """Whether rectangles ``(row0, row1, col0, col1)`` ``a`` and ``b`` (ends excluded) share area."""
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def _overlap_words(background, inclusion: str) -> str:
    """The refusal of a background on the inclusion (``inclusion`` says which): the contrast would
    compare the inclusion with itself (``--background`` inside ``--inclusion`` gave IF 0.60 / 0.20,
    exit code 0)."""
    return (
        f"background ROI {background!r}: overlaps {inclusion}; the contrast compares the inclusion with "
        "background beside it: give a background clear of the inclusion"
    )


#: what process offers where no automatic background fits: the background alone still needs the
#: inclusion found and its background placed, and the inclusion alone a background beside it
_BOTH_ROIS = "give both ROIs (radiokit process --inclusion R0 R1 C0 C1 --background R0 R1 C0 C1)"


def _background_beside(ref, inc, pixel_size_mm, named=None):
    """A background ROI of ``inc``'s shape beside the inclusion given as ``inc`` (where detection
    found none there, or none at all: it was placed beside the detected one, or the run stopped
    asking for the --inclusion it had been given). ``inc`` is taken as the automatic ROI would be,
    so the inclusion as twice its size about its centre."""
    from radiokit.measure import find_rois

    mask = np.zeros(ref.shape, bool)
    grow_r, grow_c = (inc.row1 - inc.row0 + 1) // 2, (inc.col1 - inc.col0 + 1) // 2
    mask[max(0, inc.row0 - grow_r) : inc.row1 + grow_r, max(0, inc.col0 - grow_c) : inc.col1 + grow_c] = True
    size = inc.shape if pixel_size_mm is None else tuple(np.multiply(inc.shape, pixel_size_mm))
    try:
        return find_rois(ref, inclusion_mask=mask, pixel_size_mm=pixel_size_mm, background_size=size)[1]
    except ValueError:  # find_rois names its grown inclusion, which the user never gave
        raise ValueError(
            f"{named or f'inclusion ROI {inc}'} given alone: no background of its shape fits beside it inside the frame and "
            "the body; give the background too (radiokit process --background R0 R1 C0 C1)"
        ) from None


def _given_roi(cfg, name, roi) -> str:
    """``name``'s ROI as the user gave it to ``cfg`` (in mm: ``(mm)`` after it), else as ``roi``."""
    given = getattr(cfg, name)
    if given is None or isinstance(given, ROI):
        return f"{name} ROI {roi}"
    return f"{name} ROI {given!r}" + (" (mm)" if cfg.roi_units == "mm" else "")


def _inside_frame(named_rois, shape, cfg=None, pixel_size_mm=None) -> None:
    """A ValueError naming the first ROI (None: not given) that does not lie inside ``shape``; one
    ``cfg`` gives is named as given, in mm with the frame's size in mm (it was named in pixels the
    user never typed: ``ROI(row0=0, row1=10000, ...)`` for ``--mm --inclusion 0 500 0 5``)."""
    for name, roi in named_rois:
        if roi is not None and not (0 <= roi.row0 < roi.row1 <= shape[0] and 0 <= roi.col0 < roi.col1 <= shape[1]):
            named = f"{name} ROI {roi}" if cfg is None else _given_roi(cfg, name, roi)
            if named.endswith("(mm)"):
                h, w = (n * pixel_size_mm for n in shape)
                named += f" lies outside the {shape} frame, {h:g} x {w:g} mm at {pixel_size_mm:g} mm per pixel"
                raise ValueError(named)
            raise ValueError(f"{named} lies outside the {shape} frame")


def choose_rois(steps: Steps, cfg: Config, truth=None) -> RoiChoice:
    """The inclusion and background ROIs (the configuration's, else :func:`radiokit.measure.find_rois`
    on the reference, on a simulated file's inclusion mask with ``use_truth_rois``) and the crop:
    a square of ``crop_mm`` around the inclusion, grown to hold both ROIs (whole frame
    without ``crop_mm``)."""
    from radiokit.measure import find_rois

    ref = steps.images[-1]
    inc = _roi(cfg.inclusion, cfg.roi_units, steps.pixel_size_mm, "inclusion")
    bg = _roi(cfg.background, cfg.roi_units, steps.pixel_size_mm, "background")
    # the given ones first: an inclusion off the frame given alone was told that no background fits beside it
    _inside_frame((("inclusion", inc), ("background", bg)), ref.shape, cfg, steps.pixel_size_mm)
    if inc is None or bg is None:
        mask = truth.get("inclusion_mask") if (truth and cfg.use_truth_rois) else None
        try:
            auto_inc, auto_bg = find_rois(ref, inclusion_mask=mask, pixel_size_mm=steps.pixel_size_mm)
        except ValueError as exc:
            if inc is None and bg is not None and isinstance(exc, NoBackgroundFits):
                auto_inc, auto_bg = exc.inclusion, None  # the inclusion was found; only its background was missing
            elif inc is None:  # find_rois's advice names its keywords, which process does not take (review s41proc)
                raise ValueError(
                    f"{exc.reason}; {_BOTH_ROIS}" if isinstance(exc, NoBackgroundFits) else str(exc)
                ) from None
            else:
                auto_inc = auto_bg = None
        if bg is None and inc is not None:
            # the detected inclusion's background where the given rectangle is in that inclusion
            # and clear of it (a rectangle drawn around the inclusion held it: review)
            if not _within_inclusion(auto_inc, inc.center) or _overlap(auto_bg, inc):
                auto_bg = _background_beside(ref, inc, steps.pixel_size_mm, _given_roi(cfg, "inclusion", inc))
        inc = inc or auto_inc
        bg = bg or auto_bg
    _inside_frame((("inclusion", inc), ("background", bg)), ref.shape)
    if cfg.background is not None and _overlap(inc, bg):  # given in mm, or beside a detected inclusion
        which = (
            f"the inclusion ROI {cfg.inclusion!r}"
            if cfg.inclusion is not None
            else f"the inclusion detected at rows {inc.row0}-{inc.row1}, cols {inc.col0}-{inc.col1} (px)"
        )
        raise ValueError(_overlap_words(cfg.background, which))
    if not cfg.crop_mm:
        return RoiChoice(inc, bg, (0, ref.shape[0], 0, ref.shape[1]))
    # clamped to the frame before int(): 1e308 mm / 0.05 mm is inf pixels (an OverflowError traceback)
    side_px = min(cfg.crop_mm / steps.pixel_size_mm, max(ref.shape))
    r0, r1, c0, c1 = _crop_box(inc, ref.shape, int(round(side_px)))
    # keep both rectangles inside the crop: a crop narrower than the inclusion (--crop-mm 0.01)
    # cut it, refused in the crop's pixels only after the registrations
    r0, r1 = min(r0, bg.row0, inc.row0), max(r1, bg.row1, inc.row1)
    c0, c1 = min(c0, bg.col0, inc.col0), max(c1, bg.col1, inc.col1)
    return RoiChoice(inc, bg, (r0, r1, c0, c1))


def register_pairs(steps: Steps, rois: RoiChoice, cfg: Config, label: str = "") -> tuple[RegisteredPair, ...]:
    """Register every step onto the reference and each onto the next, on the whole frame (the
    body's outline carries most of the motion of a smooth phantom: a crop inside the body leaves
    little but the inclusion to register on); fields, confidence and warped steps are then
    cropped. The main pair (the step before the reference) is registered again with
    ``cfg.cross_check`` and the two compared (:func:`cross_check`)."""
    from radiokit.progress import tqdm
    from radiokit.register import register, with_default_preset

    images, n = steps.images, len(steps.numbers)
    pairs = [(i, n - 1) for i in range(n - 1)] + [(i, i + 1) for i in range(n - 2)]
    body_full = _body_mask(images[-1])
    win = rois.slices()
    out = []
    for i, j in tqdm(pairs, desc=f"register {label}", unit="pair", disable=not cfg.progress):
        options = with_default_preset(cfg.method, cfg.register_options)
        reg = register(images[j], images[i], cfg.method, regularisation_check=cfg.regularisation_check, **options)
        check = None
        if cfg.cross_check and (i, j) == (n - 2, n - 1) and cfg.cross_check != cfg.method:
            other = register(images[j], images[i], cfg.cross_check, **_cross_check_options(cfg))
            check = cross_check(reg.displacement, other.displacement, body_full, cfg.cross_check)
        warped = reg.warp(images[i])[win]  # warped whole, then cropped: no border effects
        reg.displacement = np.ascontiguousarray(reg.displacement[(slice(None), *win)])
        if reg.confidence is not None:
            reg.confidence = np.ascontiguousarray(reg.confidence[win])
        reg.lattices = None  # the whole frame's, no longer this cropped field's (and ~10 MB at 2240)
        out.append(RegisteredPair(i, j, reg, warped, check))
    return tuple(out)


def enhance_pair(reference, registered, ks, domains=DOMAINS) -> dict:
    """The main pair in each domain (:class:`radiokit.results.Enhancement`): both line-integral images converted
    (:func:`radiokit.enhance.to_domain`), their difference and the enhanced image per k
    (:func:`radiokit.enhance.compression_contrast`)."""
    from radiokit.enhance import compression_contrast, difference, to_domain

    out = {}
    for dom in domains:
        ref_d, reg_d = to_domain(reference, dom), to_domain(registered, dom)
        images = tuple((k, compression_contrast(ref_d, reg_d, k, domain=dom)) for k in ks)
        out[dom] = Enhancement(dom, ref_d, reg_d, difference(ref_d, reg_d), images)
    return out


def measure_domains(enhanced: dict, inclusion: ROI, background: ROI, bounds=None, source="") -> dict:
    """Contrast, CNR and Weber contrast of the reference and each enhanced image, and the
    improvement factor per k, per domain (:func:`radiokit.measure.summary`), with each k's bound
    from ``bounds`` (``{Domain: {k: bound}}``).

    Raises
    ------
    ValueError
        If the reference contrast is zero in a domain (the improvement factor is undefined; see
        :func:`radiokit.measure.improvement_factor`), naming ``source`` and the domain.
    """
    from radiokit.measure import improvement_factor_se, summary

    out = {}
    for dom, e in enhanced.items():
        try:
            s = summary(e.reference, dict(e.images), inclusion, background)
        except ValueError as exc:
            raise ValueError(f"{shown(source)}: {dom.value} domain: {exc}") from None
        per_k = tuple(
            KMeasure(
                k,
                m["contrast"],
                m["cnr"],
                m["weber"],
                s["improvement_factor"][key],
                ((bounds or {}).get(dom) or {}).get(k),
                improvement_factor_se(e.reference, e.registered, k, inclusion, background),
            )
            for (k, _), (key, m) in zip(e.images, s["enhanced"].items())
        )
        r = s["reference"]
        out[dom] = DomainMeasures(dom, r["contrast"], r["cnr"], r["weber"], per_k)
    return out


def check_pairs(
    pairs, steps_c: np.ndarray, numbers, inclusion: ROI, background: ROI, truth=None, crop=None
) -> tuple[PairResult, ...]:
    """Per registered pair (:class:`radiokit.results.PairResult`): the intensity-change ratio in
    each domain with its standard error (NaN, with the reason, where the background did not
    measurably change: :func:`radiokit.measure.change_ratio_se`), the registration's quality, whether the motion was observed in the ROIs
    (:func:`rois_verdict`: a ROI mostly unobserved flags the pair), the cross-check (a
    disagreement flags the pair), and for a simulated file the end-point error against the truth
    (over the body, and over the two ROIs where the images carry the motion)."""
    from radiokit.enhance import to_domain
    from radiokit.measure import change_ratio_se
    from radiokit.register import roi_observed

    body = _body_mask(steps_c[-1])
    rois_mask = inclusion.mask(body.shape) | background.mask(body.shape)
    out = []
    for p in pairs:
        a, b = numbers[p.moving], numbers[p.reference]
        reg = p.registration
        # a background that did not measurably change leaves the ratio NaN with the reason, not a
        # refusal of the run: the improvement factor is still well defined (review s41proc)
        measured = {
            dom: change_ratio_se(to_domain(p.warped, dom), to_domain(steps_c[p.reference], dom), inclusion, background)
            for dom in DOMAINS
        }
        ratios = {dom: m[0] for dom, m in measured.items()}
        ses = {dom: m[1] for dom, m in measured.items()}
        reasons = {dom: m[2] for dom, m in measured.items() if m[2]}
        q = dataclasses.asdict(reg.quality)
        q.update(reg.run_record())
        observed = None
        if reg.confidence is not None:  # is the motion observed where the paper's numbers are measured?
            observed = {
                "inclusion": roi_observed(reg.confidence, inclusion),
                "background": roi_observed(reg.confidence, background),
            }
        whys = []
        if p.cross_check is not None and not p.cross_check["agree"]:
            whys.append(
                f"disagrees with {p.cross_check['method']} by {p.cross_check['median_px']:.1f} px (median over "
                f"the body): at least one of the two is wrong"
            )
        rois_ok, why = rois_verdict(observed)
        whys += [why] if rois_ok is False else []
        if whys:
            q["ok"], q["reason"] = False, "; ".join(([q["reason"]] if q.get("reason") else []) + whys)
        epe = None
        if truth and (a, b) in truth["fields"]:
            tf = truth["fields"][(a, b)][(slice(None), *crop)]
            epe = dict(zip(("epe_median", "epe_p95"), _epe(reg.displacement, tf, body)))
            # a uniform slab's interior moves unseen: there the field is the regulariser's guess
            epe.update(zip(("epe_roi_median", "epe_roi_p95"), _epe(reg.displacement, tf, rois_mask)))
        out.append(PairResult(a, b, reg.method, q, ratios, observed, p.cross_check, epe, rois_ok, ses, reasons or None))
    return tuple(out)


def process(path, config: Config | None = None, *, out_dir=None, overwrite=False) -> Result:
    """Run the chain on one experiment file; write results into ``out_dir`` (default: a folder
    named after the file, beside it). See the module docstring.

    The folder is assembled under a temporary name beside ``out_dir`` and swapped in when
    complete (:func:`radiokit.io.atomic_dir`): an interrupted run leaves the previous results or
    none. An existing ``out_dir`` is replaced only with ``overwrite=True`` and only if radiokit
    made it; one holding the input is always refused.
    """
    from radiokit.io import atomic_dir

    cfg = config or Config()
    path = Path(path)
    try:
        os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{shown(path)}: no such experiment file") from None
    except OSError as exc:  # a symbolic link in a loop, a folder on the way not searchable
        raise FormatError(path, f"cannot be opened: {exc.strerror or exc}") from None
    out_dir = Path(out_dir) if out_dir is not None else path.parent / _folder_name(path)
    inputs = [path] + ([Path(cfg.control)] if cfg.control else [])
    try:
        _check_inputs(path, cfg.control)  # before any work
        with atomic_dir(out_dir, overwrite=overwrite, inputs=inputs) as stage:
            res = _process(path, cfg, stage)
    except FormatError as exc:
        if not exc.advice:
            raise
        raise _in_process_words(exc) from exc
    res.files = {k: str(out_dir / Path(v).relative_to(stage)) for k, v in res.files.items()}
    return res


#: what process() says in place of a reader's advice (FormatError.advice) of an option it does not
#: take: it reads experiment files only, and no data outside them
_PROCESS_ADVICE = {
    "allow_external": "(process() reads no data outside the experiment file: copy the linked data into it first)",
    "dataset": "process() reads experiment files only (radiokit.io.read(path, dataset=...) reads one's frames; "
    "radiokit.io.ExperimentWriter writes them into an experiment file)",
}


def _in_process_words(exc: FormatError) -> FormatError:
    """``exc`` with its advice of reader options process() does not take in its own words, and
    those words as its advice (radiokit process says its own in their place)."""
    problem, advice = exc.problem, {}
    for option, said in exc.advice.items():
        advice[option] = _PROCESS_ADVICE.get(option, said)
        problem = problem.replace(said, advice[option])
    return type(exc)(exc.path, problem, advice=advice)


def _output_kind(dataset, kind) -> str:
    """What a file ``read`` opened at ``dataset`` holds: radiokit's own outputs by name ("holds
    hdf5 data" named none of them), else its format's."""
    from radiokit.io._registration import REGISTERED
    from radiokit.io._results import RESULTS_STEPS
    from radiokit.io._write import STACK_FRAMES

    return {
        f"/{RESULTS_STEPS}/line_integral": "radiokit process's results (results.h5)",
        f"/{REGISTERED}": "a registration (radiokit register)",
        f"/{STACK_FRAMES}": "a stack of frames without darks and flats (radiokit correct's output, or another program's)",
    }.get(dataset, f"{kind} data")


def _check_square_pixels(path, meta: dict) -> None:
    """Refuse an experiment whose pixels are not square (``x_pixel_size`` and ``y_pixel_size``
    differ). Why: the chain measures in square pixels: ROIs and the crop in mm are converted with
    one pitch, results.json records one, the report draws pixels square and scales rows and
    columns alike, and the registration smooths in pixels. x 0.05 mm, y 0.2 mm put
    ``--mm --inclusion 3.5 4.5 ...`` at rows 70-90, not 17.5-22.5, exit code 0. The panel bins
    square (1x1, 2x2, 4x4) and ExperimentWriter writes one pitch for both axes: such a file was
    written or edited by another program."""
    from radiokit.io._experiment import PIXEL_SIZE_RTOL

    x, y = meta.get("x_pixel_size"), meta.get("y_pixel_size")
    if x is None or y is None or math.isclose(x, y, rel_tol=PIXEL_SIZE_RTOL):
        return
    raise FormatError(
        path,
        f"pixels of {x * 1e3:g} x {y * 1e3:g} mm (x_pixel_size, y_pixel_size): process measures, records "
        "and reports square pixels (ROIs and the crop in mm, the report's scales, one pitch in results.json); "
        "resample the frames to square pixels first",
    )


def _check_inputs(path: Path, control) -> None:
    """An experiment file, and a control imaged on the same grid. A calibration or results file
    was read as frames (two warnings, then "no steps"); a control of another frame size or
    pixel size was measured in the main file's pixel ROIs, on whatever lay there."""
    from radiokit.io import check_same_pixel_size, open_frames

    shapes, metas = [], []
    for p, what in ((path, "experiment"), *(((Path(control), "control experiment"),) if control else ())):
        if not p.exists():
            raise FileNotFoundError(f"{shown(p)}: no such {what} file")
        with open_frames(p) as src:
            kind = src.meta.get("format", src.format)
            if kind != "experiment":
                kind = _output_kind(src.meta.get("dataset"), kind)
                raise FormatError(
                    p,
                    f"holds {kind}, not {'a' if what[0] == 'c' else 'an'} {what} (darks, flats and projections by step, as "
                    "radiokit acquire or radiokit.io.ExperimentWriter write them)",
                )
            _check_square_pixels(p, src.meta)
            _check_registrable(p, src.frame_shape)
            shapes.append(src.frame_shape)
            metas.append(src.meta)
    if len(shapes) == 2 and shapes[0] != shapes[1]:
        raise FormatError(
            control,
            f"frames are {shapes[1][0]}x{shapes[1][1]}, the experiment's {shapes[0][0]}x{shapes[0][1]}: "
            "the control must be imaged as the experiment",
        )
    if len(metas) == 2:
        check_same_pixel_size(control, metas[1], path, metas[0], "the control must be imaged as the experiment")


def _check_registrable(path, shape) -> None:
    """Frames register() can take. Why: a 3x3 experiment was told to pass its ROIs (no inclusion
    detectable in it), and given them, calibrated and corrected before "too small to register"."""
    from radiokit.register import MAX_SIDE, MIN_SIDE

    if min(shape) < MIN_SIDE:
        raise FormatError(
            path, f"frames are {shape[0]}x{shape[1]}: too small to register ({MIN_SIDE} px a side at least)"
        )
    if max(shape) > MAX_SIDE:
        raise FormatError(
            path,
            f"frames are {shape[0]}x{shape[1]}: too large to register ({MAX_SIDE} px a side at most, OpenCV's limit)",
        )


def _timed(timings, name, fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    timings[name] = time.perf_counter() - t
    return out


def _process(path: Path, cfg: Config, out_dir: Path) -> Result:
    """:func:`process` writing into ``out_dir``, a fresh folder: the steps composed."""
    t0 = time.perf_counter()
    steps = _load_steps(path, cfg.progress)
    timings = dict(steps.timings)
    truth = _sim_truth(path, list(steps.numbers))
    rois = choose_rois(steps, cfg, truth)
    _check_unknown_in_rois(path, steps, rois)
    _warn_nonfinite(path, steps.nonfinite)
    pairs = _timed(timings, "register_s", register_pairs, steps, rois, cfg, path.name)
    _check_unknown_moved_into_rois(path, steps, rois, pairs)
    steps_c = np.ascontiguousarray(steps.images[(slice(None), *rois.slices())])
    inc_c, bg_c = rois.cropped()
    n = len(steps.numbers)  # the paper's pair: the step before the reference, onto it
    main = next(p for p in pairs if (p.moving, p.reference) == (n - 2, n - 1))
    enhanced = _timed(timings, "enhance_s", enhance_pair, steps_c[-1], main.warped, cfg.ks)
    t = time.perf_counter()
    view = _scene_view(truth) or cfg.view  # the control's too: it is imaged as the experiment is
    bound, bounds = _bound(
        path,
        list(steps.numbers),
        truth,
        float(np.mean(enhanced[Domain.LOG].reference[bg_c.slices], dtype=np.float64)),
        cfg.ks,
        view,
    )
    domains = measure_domains(enhanced, inc_c, bg_c, bounds, str(path))
    checked = check_pairs(pairs, steps_c, steps.numbers, inc_c, bg_c, truth, rois.slices())
    mid = (inc_c.row0 + inc_c.row1) // 2
    images = _images(steps_c, steps.numbers, main, enhanced, truth, rois, mid)
    timings["measure_s"] = time.perf_counter() - t
    record = Results(
        source=os.fsencode(path).decode("utf-8", "backslashreplace"),  # a name's non-UTF-8 bytes as \\xNN
        scene=truth.get("scene") if truth else None,
        simulated=truth is not None,
        pixel_size_mm=steps.pixel_size_mm,
        pixel_size_recorded=steps.pixel_size_recorded,
        domain=cfg.domain,
        ks=cfg.ks,
        method=cfg.method,
        steps=steps.numbers,
        ratios=steps.ratios,
        rois=Rois(rois.crop, _bounds(inc_c), _bounds(bg_c)),
        domains=domains,
        pairs=checked,
        main_pair=f"{steps.numbers[-2]}->{steps.numbers[-1]}",
        profiles_row=mid,
        bound=bound,
        paper=PAPER,
        timings=timings,
        control=_control(dataclasses.replace(cfg, view=view), rois, out_dir),
    )
    files = _write(out_dir, record, images, cfg, t0)
    return Result(record, images, files)


def _images(steps_c, numbers, main: RegisteredPair, enhanced, truth, rois: RoiChoice, mid) -> Images:
    from radiokit.measure import profile
    from radiokit.register import jacobian_determinant

    disp = main.registration.displacement
    prof = {
        f"step {s}": profile(steps_c[k], (mid, 0), (mid, steps_c.shape[2] - 1))[1].tolist()
        for k, s in enumerate(numbers)
    }
    tf = epe = None
    key = (numbers[main.moving], numbers[main.reference])
    if truth and key in truth["fields"]:
        tf = truth["fields"][key][(slice(None), *rois.slices())].astype(np.float32)
        epe = np.sqrt(((disp - tf) ** 2).sum(axis=0)).astype(np.float32)
    return Images(
        steps_c,
        steps_c[-1],
        main.warped,
        steps_c[main.moving],
        disp,
        jacobian_determinant(disp),
        main.registration.confidence,
        enhanced,
        prof,
        tf,
        epe,
    )


def _control(cfg: Config, rois: RoiChoice, out_dir: Path) -> Results | None:
    """The control experiment processed with the same ROIs (full-frame pixels)."""
    if not cfg.control:
        return None
    ctrl_cfg = dataclasses.replace(
        cfg,
        control=None,
        report=False,
        progress=False,
        inclusion=_bounds(rois.inclusion),
        background=_bounds(rois.background),
        roi_units="px",
    )
    return process(cfg.control, ctrl_cfg, out_dir=out_dir / "control").record


def _write(out_dir, record: Results, images: Images, cfg, t0):
    from radiokit.io import EnhancedImages, ResultsRecord, write_results
    from radiokit.report import draw_figures, write_page
    from radiokit.results import MAX_JSON_BYTES

    files = {}
    figures = None
    if cfg.report:  # the figures, the report's time: the page is written below, with the total
        t = time.perf_counter()
        figures = draw_figures(out_dir, record, images)
        record.timings["report_s"] = time.perf_counter() - t
    # measured once, before any file is written, so the page, results.h5's copy of the numbers and
    # results.json show one total (the page's was 0.02 s short and results.h5's had none: review
    # s43); writing the files is after it
    record.timings["total_s"] = time.perf_counter() - t0
    h5path = out_dir / "results.h5"
    names = ("registered", "moving", "displacement", "det_j", "confidence", "truth_displacement")
    # confidence: where the motion was observed (>= 0.5); truth_displacement only in simulated files
    write_results(
        h5path,
        ResultsRecord(
            source=record.source,
            # inf/NaN: null, named; refused unwritten where results.json's reader would refuse it
            results_json=dumps_readable(record.to_json(), shown(h5path), "results.json", MAX_JSON_BYTES),
            line_integral=images.steps,
            step=np.asarray(record.steps),
            ratio=np.asarray(record.ratios, float),
            crop=np.asarray(record.rois.crop),
            pair=tuple(int(s) for s in record.main_pair.split("->")),
            registration={n: getattr(images, n) for n in names if getattr(images, n) is not None},
            enhanced={
                dom.value: EnhancedImages(e.reference, e.difference, {k_label(k): img for k, img in e.images})
                for dom, e in images.enhanced.items()
            },
            rois={key: np.asarray(roi) for key, roi in record.rois.to_json().items()},
            # NeXus's x_pixel_size states a pitch as the data's: an assumed one stays in results.json,
            # marked so (review s42rep: `radiokit info results.h5` printed it as the file's)
            pixel_size_mm=record.pixel_size_mm if record.pixel_size_recorded else None,
        ),
    )
    files["results_h5"] = str(h5path)
    if figures is not None:
        files["report"] = str(write_page(out_dir, record, figures))
    files["results_json"] = str(record.write_json(out_dir / "results.json"))
    return files


def _folder_name(path) -> str:
    """The name of ``path``'s results folder: its stem (``exp`` for ``exp.h5``). A stem of dots
    names no folder of its own (``..h5``'s is ``.``, ``...h5``'s ``..``: the output root or its
    parent, the other files' folders nested in it): those keep their suffix, its dot as ``_``
    (``._h5``, ``.._h5``)."""
    path = Path(path)
    stem = path.stem
    return f"{stem}_{path.suffix[1:]}" if stem in ("", ".", "..") else stem


def output_folders(paths, out_root=None) -> list[Path]:
    """One distinct results folder per input: ``out_root/STEM`` (default: beside each file, named
    after it; :func:`_folder_name`); inputs sharing a folder name get ``STEM-2``, ``STEM-3``, ...
    in the order given, so no run ever merges into or replaces another's folder."""
    from radiokit.io._atomic import resolved

    outs, taken = [], set()
    for p in map(Path, paths):
        base = (Path(out_root) if out_root is not None else p.parent) / _folder_name(p)
        out, k = base, 1
        while resolved(out) in taken:
            k += 1
            out = base.with_name(f"{base.name}-{k}")
        taken.add(resolved(out))
        outs.append(out)
    return outs


#: process's peak memory per pixel of a frame, beyond the interpreter's 380 MB, measured with
#: /usr/bin/time -v on tests' synthetic files (3 steps, one frame each, the default method and
#: preset): with the default 600 x 600 crop 488 MB at 1024 x 1024, 814 MB at 2048 x 2048, 106 bytes a
#: frame pixel; keeping the whole frame (--crop-mm 0) 649 MB and 1385 MB, 240 bytes, so 134 more a
#: kept pixel. tracemalloc's peak of the same runs (numpy's share) split them 71 + 162 (232); each
#: figure is the larger, rounded up. A file of more steps holds more: PROCESS_BYTES_PER_STEP_PIXEL.
PROCESS_BYTES_PER_PIXEL = 110
#: process's peak memory per pixel of the crop it keeps (the enhanced images, fields, figures)
PROCESS_BYTES_PER_KEPT_PIXEL = 170
#: the steps the two figures above were measured on (tests' synthetic files)
PROCESS_MEASURED_STEPS = 3
#: process's peak memory per frame pixel of each step beyond those 3 (a step's image, its pairs'
#: fields and crops), measured with /usr/bin/time -v on synthetic's slab and square over 3 and 12
#: steps, one frame each, --crop-mm 0 (the whole frame kept), -q --no-report --cross-check none:
#: 380 and 455 MB at 512 x 512 (32 bytes a pixel a step), 477 and 870 MB at 1024 x 1024 (42; review
#: s37r1 measured 537 and 896 MB there, 38); with the report and cross-check, 416 and 520 MB at
#: 512 x 512 (44): the largest, rounded up
PROCESS_BYTES_PER_STEP_PIXEL = 45


def _process_need(path, cfg) -> tuple[int, str] | None:
    """The memory ``process`` needs for ``path`` (bytes) and how it was reckoned, from the file's
    index (no frame read); None for a file that cannot be opened (process says why, in its order)."""
    from radiokit.io import C7942_PIXEL_SIZE_MM, human_bytes, open_frames

    try:
        with open_frames(path) as src:
            (rows, cols), pixel_mm = src.frame_shape, float(src.meta.get("pixel_size_mm", C7942_PIXEL_SIZE_MM))
            # the steps from the file's index (read with its metadata), no frame read
            keys, steps = (np.asarray(src.meta.get(k, [])) for k in ("image_key", "step"))
    except (OSError, ValueError, TypeError):  # the file's own error is said by process, in its order
        return None
    n_steps = len(set(steps[(keys == 0) & (steps >= 0)].tolist())) if steps.shape == keys.shape else 0
    more = max(0, n_steps - PROCESS_MEASURED_STEPS)
    # as choose_rois crops (None: the whole frame); a pixel size it would refuse, the whole frame
    side = cfg.crop_mm / pixel_mm if cfg.crop_mm is not None and pixel_mm > 0 else max(rows, cols)
    kept = min(side, rows) * min(side, cols)
    per_pixel = PROCESS_BYTES_PER_PIXEL + PROCESS_BYTES_PER_STEP_PIXEL * more
    need = int(per_pixel * rows * cols + PROCESS_BYTES_PER_KEPT_PIXEL * kept)
    words = (
        f"its {rows}x{cols} frames of {n_steps} steps need about {human_bytes(need)} ({PROCESS_BYTES_PER_PIXEL} bytes a pixel"
        + (f", {PROCESS_BYTES_PER_STEP_PIXEL} more for each step beyond {PROCESS_MEASURED_STEPS}" if more else "")
        + f", {PROCESS_BYTES_PER_KEPT_PIXEL} more a pixel of the {int(min(side, rows))}x{int(min(side, cols))} crop kept)"
    )
    return need, words


# Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536 (its pre-spawn-environ).
# Setting any malloc threshold turns off glibc's sliding mmap threshold, so every array over 128 kB
# is mmapped and unmapped on each allocation and its pages faulted in again: on a 560 x 560
# experiment the kernel time equalled the user time (benchmarks/README.md, "Dask"). Fixed
# thresholds above a 2240 x 2240 float32 frame keep frame-sized buffers in the heap for reuse.
_MALLOC_MMAP_THRESHOLD = 32 * 2**20  # glibc's largest allowed value on 64-bit
_MALLOC_TRIM_THRESHOLD = 256 * 2**20


@dataclass(frozen=True)
class WorkerThreads:
    """How one Dask worker uses its share of the cores: ``tasks`` files at a time (the worker's
    Dask threads), each with ``threads`` threads in radiokit's pools, OpenCV and the FFTs.

    BLAS stays at one thread in a worker: radiokit's heavy loops are its own pools and OpenCV's,
    and OpenBLAS's threads spin when called from a worker's task thread (measured: a one-worker
    cluster with two BLAS threads used 2.1x the CPU time of the same files processed in turn;
    with one, the same time; benchmarks/README.md)."""

    tasks: int
    threads: int
    #: the bytes its reads may take (its share of its host's memory budget, :func:`_memory_shares`);
    #: None: the host's whole budget
    memory: int | None = None

    def environ(self) -> dict:
        """Environment for a worker process started for this share (read by the libraries at load)."""
        return {
            "RADIOKIT_THREADS": str(self.threads),
            "OMP_NUM_THREADS": "1",
            "OPENBLAS_NUM_THREADS": "1",
            "MKL_NUM_THREADS": "1",
            "MALLOC_MMAP_THRESHOLD_": str(_MALLOC_MMAP_THRESHOLD),
            "MALLOC_TRIM_THRESHOLD_": str(_MALLOC_TRIM_THRESHOLD),
        }


def worker_threads(cores: int, workers: int, tasks_per_worker: int = 1) -> WorkerThreads:
    """Split ``cores`` between ``workers`` workers on one machine running ``tasks_per_worker`` files
    each: at least one thread per file, never more threads in all than cores (when there are
    more files at a time than cores, one each)."""
    if cores < 1 or workers < 1 or tasks_per_worker < 1:
        raise ValueError(f"cores={cores}, workers={workers}, tasks_per_worker={tasks_per_worker}: expected >= 1")
    return WorkerThreads(tasks_per_worker, max(1, cores // (workers * tasks_per_worker)))


def _scheduler_shares(client) -> dict:
    """Each connected worker's share, from the scheduler's view: the workers of one host split the
    cores that host reports (its CPU affinity)."""
    from radiokit._threads import cores

    info = _all_workers(client)
    if not info:
        raise ValueError(
            f"Dask scheduler {client.scheduler.address}: no workers connected (start some with `dask worker ADDRESS`)"
        )
    host_cores = client.run(cores)
    per_host: dict = {}
    for addr, w in info.items():
        per_host.setdefault(w["host"], []).append(addr)
    shares = {}
    for addrs in per_host.values():
        tasks_on_host = sum(int(info[a]["nthreads"]) for a in addrs)
        n_cores = min(host_cores.get(a, 1) for a in addrs)
        for a in addrs:
            shares[a] = WorkerThreads(int(info[a]["nthreads"]), max(1, n_cores // tasks_on_host))
    return shares


def _memory_shares(client) -> dict:
    """Each connected worker's share of memory for one file, ``(bytes, words saying how)``: its
    host's budget (:func:`radiokit.io._budget.host_budget` there: that host's ``RADIOKIT_MEMORY_BUDGET``
    or half its available memory; a budget given to this process stands for every host) divided
    among the files the host's workers process at once (their Dask threads), and no more than the
    worker's own Dask ``memory_limit`` divided among its threads (its nanny stops it past that)."""
    from radiokit.io import human_bytes
    from radiokit.io._budget import explicit_budget, host_budget

    info = _all_workers(client)
    given = host_budget() if explicit_budget() else None
    # measured there, not here: a scheduler's workers may run on other machines; their whole
    # budget, not the share an earlier run left them
    reported = {} if given is not None else client.run(host_budget, workers=list(info))
    per_host: dict = {}
    for addr, w in info.items():
        per_host.setdefault(w["host"], []).append(addr)
    shares = {}
    for host, addrs in per_host.items():
        at_once = max(1, sum(int(info[a]["nthreads"]) for a in addrs))  # a worker may report 0 threads
        seen = [reported[a] for a in addrs if a in reported]
        budget = given if given is not None else min(seen) if seen else host_budget()
        for a in addrs:
            share = budget // at_once
            words = f"the memory budget of {human_bytes(budget)} on host {host}" + (
                f", shared by the {at_once} files its Dask workers process at once ({human_bytes(share)} each)"
                if at_once > 1
                else ""
            )
            n, limit = max(1, int(info[a]["nthreads"])), int(info[a].get("memory_limit") or 0)
            if limit and limit // n < share:
                share = limit // n
                words = f"Dask's memory_limit of {human_bytes(limit)} for worker {a}" + (
                    f", shared by the {n} files it processes at once ({human_bytes(share)} each)" if n > 1 else ""
                )
            shares[a] = (share, words)
    return shares


def _check_worker_memory(paths, cfg: Config, shares: dict) -> None:
    """Refuse, before any work, a file whose processing would need more memory than the smallest
    worker's share (:func:`_memory_shares`; Dask may give any file to any worker), as ``radiokit
    process`` refuses one file over the budget."""
    from radiokit.io._budget import BUDGET_ENV

    share, budget = min(shares.values(), key=lambda s: s[0])
    advice = (
        f": raise {BUDGET_ENV} if the workers' hosts have that memory, process fewer files at once "
        "(fewer workers or Dask threads a host; on the command line --workers 1 takes one at a time), "
        "or process smaller frames, binned or cropped beforehand"
    )
    refuse_over_memory(paths, cfg, share, budget + advice, control_name="control=")


def refuse_over_memory(paths, cfg: Config, share: int, over: str, control_name: str) -> None:
    """A ``ValueError`` naming the first of ``paths`` whose processing (:func:`_process_need`) needs
    more than ``share`` bytes, ``over`` saying whose budget and what to do. A file's control is
    processed while the file's own images are held (the control's record is made last), so the two
    are charged together, and the control alone first, named ``control_name`` (``--control `` on
    the command line). A file that cannot be opened is passed: its own error is said in its turn."""
    from radiokit.io import human_bytes

    control = _process_need(cfg.control, cfg) if cfg.control else None
    if control is not None and control[0] > share:
        raise ValueError(f"{control_name}{shown(cfg.control)}: processing {control[1]}, over {over}")
    for path in paths:
        mine = _process_need(path, cfg)
        if mine is not None and mine[0] + (control[0] if control else 0) > share:
            beside = f", and its control {shown(cfg.control)} {human_bytes(control[0])} beside it" if control else ""
            raise ValueError(f"{shown(path)}: processing {mine[1]}{beside}, over {over}")


def _all_workers(client) -> dict:
    try:
        return client.scheduler_info(n_workers=-1)["workers"]  # recent Dask lists 5 by default
    except TypeError:  # older Dask: no n_workers, lists them all
        return client.scheduler_info()["workers"]


def _limit_this_process(share: WorkerThreads):
    """Hold this (worker) process to ``share``: radiokit's pools (through ``RADIOKIT_THREADS``),
    OpenCV, BLAS to one thread (threadpoolctl, on the libraries loaded by then; see
    :class:`WorkerThreads`), and glibc's malloc thresholds (for workers started without
    :meth:`WorkerThreads.environ`)."""
    import ctypes
    import os

    import cv2
    import scipy.linalg  # noqa: F401  (loads scipy's BLAS, so that threadpoolctl can limit it)
    from threadpoolctl import threadpool_limits

    from radiokit.io._budget import set_share

    os.environ["RADIOKIT_THREADS"] = str(share.threads)
    set_share(share.memory)
    cv2.setNumThreads(share.threads)
    threadpool_limits(limits=1, user_api="blas")
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, _MALLOC_MMAP_THRESHOLD)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, _MALLOC_TRIM_THRESHOLD)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc: its defaults, nothing set by Dask to undo
        pass


def process_many(
    paths,
    config: Config | None = None,
    *,
    out_root=None,
    scheduler=None,
    workers=None,
    overwrite=False,
    connect_timeout_s: float = 10.0,
) -> list:
    """Process many experiment files in parallel on Dask, one progress bar over all.

    ``scheduler``: ``None`` starts a local cluster (processes, ``workers`` of them, default one per
    core up to the number of files, one file at a time each), an address (``tcp://host:8786``)
    connects to a running one, waiting ``connect_timeout_s`` for it to answer (a ``ConnectionError``
    naming the address then). Each worker's threads are sized to its share of the cores
    (:func:`worker_threads`; for a scheduler, from the workers' hosts and Dask threads), so that
    the pools of correction and registration, BLAS and OpenCV do not oversubscribe the machine.
    Their memory is shared likewise: a file (with ``config.control``) whose processing would need
    more than a worker's share of its host's budget (:func:`_memory_shares`) refuses the whole run
    before any work, a ``ValueError`` naming it. Returns, per file, its results dict, or
    ``{"source": path, "error": message, "error_type": class name}`` for a file that failed (and
    ``"advice"``, the reader options its message advises, ``FormatError.advice``, where it has
    any); the others go on (:func:`_error_result`). Output folders are :func:`output_folders`; each is
    written as :func:`process` writes."""
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise ImportError("processing many files needs Dask: pip install 'radiokit[parallel]'") from None
    from radiokit._threads import cores
    from radiokit.io import missing_folders, recover_interrupted, remove_empty_folders
    from radiokit.progress import tqdm

    if out_root is not None:
        _check_out_root(Path(out_root))
    cfg = dataclasses.replace(config or Config(), progress=False)
    paths = [Path(p) for p in paths]
    outs = output_folders(paths, out_root)
    # the cluster is handed over in `ours` the moment it exists, and everything after is inside
    # the try: a Ctrl-C between _local_cluster's return and an assignment, or before a `try`,
    # would leave its workers running with no owner
    ours, client, made = {}, None, []
    restore = _process_limits()  # a worker in this process (processes=False) sets them for it
    try:
        if scheduler is None:
            _local_cluster(local_workers(workers, len(paths), cores()), ours)
        client = Client(ours["cluster"]) if ours else _connect(Client, scheduler, connect_timeout_s)
        if ours:  # a scheduler's workers outlive the run: their exit is not ours to change
            client.run(_exit_without_collecting)
        shares = _scheduler_shares(client)
        # each file against its worker's share of the memory, before any work: the workers of a
        # host each hold a file at once, and the command line sees neither a scheduler's hosts
        # nor the budget a worker's own environment gives
        memory = _memory_shares(client)
        _check_worker_memory(paths, cfg, memory)
        # and each worker's reads held to its share (the calibration's darks and flats, say)
        shares = {a: dataclasses.replace(s, memory=memory[a][0]) if a in memory else s for a, s in shares.items()}
        # made once connected (a scheduler that timed out left `-o`'s new folder behind, empty),
        # and here, not by the workers: one that fails must not remove it under the others
        made = missing_folders(out_root) if out_root is not None else []
        if made:
            Path(out_root).mkdir(parents=True)
        client.run(_limit_worker, shares)
        futures = {
            client.submit(_process_one, str(p), cfg, str(o), overwrite, shares, os.getpid(), pure=False): i
            for i, (p, o) in enumerate(zip(paths, outs))
        }
        results = [None] * len(paths)
        with tqdm(total=len(paths), desc="process", unit="file", disable=not (config or Config()).progress) as bar:
            for fut in as_completed(futures):
                results[futures[fut]] = _warn_again(*fut.result())
                bar.update()
        return results
    except BaseException:  # Ctrl-C, SIGTERM: the workers are stopped, not left running
        logging.getLogger("distributed").setLevel(logging.CRITICAL)  # the one line is the command's
        with deferred(*STOP_SIGNALS):
            if ours:  # stopped now, not after each busy worker's grace period
                _kill_workers(ours["cluster"])
            elif (
                client is not None
            ):  # a scheduler's workers are not ours to kill: their logs of the tasks cut short quiet
                with contextlib.suppress(Exception):
                    client.run(_quiet_worker)
        raise
    finally:
        # A signal while the workers stop is acted on once they have (see radiokit.interrupts.deferred)
        with deferred(*STOP_SIGNALS):
            if client is not None:
                client.close()
            if ours:
                ours["cluster"].close()
                # a worker stopped mid-file (its nanny kills it after a grace period) leaves its
                # results folder's temporary: removed once its process is gone, as the next run would
                for out in outs:
                    with contextlib.suppress(OSError):  # one stopped while its old folder was aside
                        recover_interrupted(out)
            remove_empty_folders(made)  # every file failed: no empty folder left behind
            restore()


def _process_limits():
    """A function putting back what :func:`_limit_this_process` sets, as it is now: a worker of an
    in-process cluster (``LocalCluster(processes=False)``) runs in the caller's process, and its
    share (a fraction of the memory budget, one thread) outlived the run, refusing the caller's
    later reads (review s40rr). It puts back the level of Dask's logger too, which an interrupt
    raises (review s44). glibc's malloc thresholds are left: they change speed only."""
    import cv2
    from threadpoolctl import ThreadpoolController

    from radiokit.io._budget import memory_share, set_share

    threads, share, cv_threads = os.environ.get("RADIOKIT_THREADS"), memory_share(), cv2.getNumThreads()
    libraries = [(lib, lib.num_threads) for lib in ThreadpoolController().lib_controllers]
    # an interrupt silences Dask's logger for the command's one line; a library caller's stays its own
    dask_log = logging.getLogger("distributed")
    dask_level = dask_log.level

    def restore():
        dask_log.setLevel(dask_level)
        if threads is None:
            os.environ.pop("RADIOKIT_THREADS", None)
        else:
            os.environ["RADIOKIT_THREADS"] = threads
        set_share(share)
        cv2.setNumThreads(cv_threads)
        for lib, n in libraries:
            with contextlib.suppress(Exception):
                lib.set_num_threads(n)

    return restore


def _check_out_root(out_root: Path) -> None:
    """Refuse a folder radiokit made as the root of several files' folders."""
    from radiokit.io._atomic import RESULTS_MARKER, OutputError, refuse_another_commands

    if (out_root / RESULTS_MARKER).exists():
        refuse_another_commands(out_root, "process")  # a demo's folder says so, not "one run's results"
        # one run's results folder: the files' folders would be written beside its report, a folder
        # mixing two runs that neither could then replace
        raise OutputError(
            out_root,
            f"holds the results of one run ({RESULTS_MARKER}); several files each get a folder under "
            "-o (out_root): choose another folder",
        )


def _connect(client_class, scheduler: str, timeout_s: float):
    """A client of the scheduler at ``scheduler``; one that does not answer within ``timeout_s`` is
    a ``ConnectionError`` naming it (Dask's own wait is 30 s, and its message names no remedy)."""
    if not timeout_s > 0:
        raise ValueError(f"a scheduler time-out of {timeout_s!r} s: expected a positive number of seconds")
    try:
        return client_class(scheduler, timeout=timeout_s)
    except OSError:  # Dask retries a refused or unreachable address until its time-out
        raise ConnectionError(
            f"Dask scheduler {scheduler}: did not answer within {timeout_s:g} s (is `dask scheduler` running "
            "there, and reachable from here?)"
        ) from None


def local_workers(asked: int | None, n_files: int, n_cores: int) -> int:
    """The local cluster's workers: ``asked`` (default one per core), never more than files. Each
    takes one file at a time, so more would only hold memory and a share of the cores that no file
    uses (``--workers 8`` on two files started eight, each with an eighth of the machine)."""
    return max(1, min(asked or n_cores, n_files))


#: The stops a terminal sends to its whole process group (Ctrl-C, Ctrl-\, the hang-up when it
#: closes): the workers start with them blocked, and leave them to this process
_GROUP_SIGNALS = {getattr(signal, name) for name in ("SIGINT", "SIGQUIT", "SIGHUP") if hasattr(signal, name)}


def _local_cluster(n_workers: int, made: dict | None = None):
    """A local cluster of ``n_workers`` single-threaded worker processes, each started with its
    share of this machine's cores in its environment; also put in ``made["cluster"]`` as soon as
    it exists (the caller's clean-up finds it there even if an interrupt comes before this
    returns), and taken out again if it is stopped here.

    Ctrl-C (and Ctrl-\\, and a closed terminal's SIGHUP) reaches the terminal's whole process group,
    the workers too: each died mid-file with tracebacks and left its temporary folder. So the workers start
    with both *blocked*: the cluster is started from a thread that blocks them, whose mask the
    threads Dask starts there inherit (its event loop, the ones that start the workers), and a
    process keeps its mask across exec. They leave the signal to this process, which stops them
    (process_many). This process is never made to ignore them: it was while the cluster started,
    and a Ctrl-C then was lost (the run went on to its end, exit code 0).

    A Ctrl-C while the cluster starts lets it finish starting, then stops it: Dask cut short
    half-way keeps workers it no longer knows how to close."""
    from dask.distributed import LocalCluster

    from radiokit._threads import cores

    share = worker_threads(cores(), n_workers)
    with _blocked(
        *_GROUP_SIGNALS - {signal.SIGINT}
    ):  # the tracker blocks, then ignores, SIGINT itself (and unblocks it here)
        _quiet_resource_tracker()
    made, done = ({} if made is None else made), threading.Event()

    def start():
        signal.pthread_sigmask(signal.SIG_BLOCK, _GROUP_SIGNALS)
        try:
            made["cluster"] = LocalCluster(
                n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None, env=share.environ()
            )
        except BaseException as exc:  # raised in the caller's thread
            made["error"] = exc
        finally:
            done.set()

    starter = threading.Thread(target=start, name="radiokit local cluster", daemon=True)
    starter.start()
    # an Event, not Thread.join: a join cut short by Ctrl-C marks the thread finished (CPython
    # 3.11 releases its lock on the way out), so a second join returned at once and the cluster,
    # started a moment later, was left running with no owner
    try:
        done.wait()  # the main thread keeps its signals: a Ctrl-C ends this wait at once
    except BaseException:
        with deferred(*STOP_SIGNALS):
            done.wait()
            if "cluster" in made:
                _kill_workers(made["cluster"])
                made.pop("cluster").close()
        raise
    if "error" in made:
        raise made.pop("error")
    return made["cluster"]


def _kill_workers(cluster) -> None:
    """Kill the worker processes of a started ``cluster`` on an interrupt, before closing it: a
    worker stopped mid-file has nothing worth the grace period Dask gives it (closing waited 4 s
    for each one busy with a file); its temporaries are removed once it is gone (process_many)."""
    logging.getLogger("distributed").setLevel(logging.CRITICAL)  # the one line is the command's
    nannies = list(cluster.workers.values())
    for nanny in nannies:
        with contextlib.suppress(Exception):
            nanny.close_gracefully()  # Dask's flag for "do not restart a worker that goes away"
    for nanny in nannies:
        pid = getattr(nanny, "pid", None)
        if pid:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


@contextlib.contextmanager
def _blocked(*signals):
    """Block ``signals`` in this thread while the block starts threads or processes, which inherit
    the mask; then unblock them, which delivers one sent meanwhile."""
    before = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _quiet_worker():
    """Run in each worker on an interrupt: the tasks closed under it are not warnings to show."""
    logging.getLogger("distributed").setLevel(logging.CRITICAL)


def _quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (the process that unlinks the semaphores of
    processes that did not) with its report of them silenced: a worker stopped mid-file on Ctrl-C
    leaves two, which the tracker removes, and its warning was two more lines after the command's
    one. Its filters come from ``sys.warnoptions`` when it starts; it is started once."""
    import sys
    from multiprocessing import resource_tracker

    option = "ignore:resource_tracker:UserWarning"
    sys.warnoptions.append(option)
    try:
        resource_tracker.ensure_running()
    finally:
        sys.warnoptions.remove(option)


def _exit_without_collecting():
    """Run in each worker of the local cluster by ``client.run``: its interpreter's exit skips the
    collections of every object it holds (``gc.freeze`` at exit, before the modules are torn down).

    A worker that has processed a file holds ~140 000 objects of ~1 200 modules, and its exit's
    collections (``Py_FinalizeEx``, ``finalize_modules``) went through them all: 0.4-0.6 s of CPU
    a worker after small files, 0.06 s frozen. The nanny waits 4 s for that exit once it has asked
    the worker to stop, then kills it with a warning: on two cores at load 10 it did in 5 of 6
    runs of three files, and closing the cluster took 4.0-4.6 s (0.1-0.4 s now). Only cycles are
    left uncollected, and only at exit, where Python promises no finalizer of an object still
    alive; the files are written and closed by then, and the other ``atexit`` handlers still run.
    (Dask has no setting for the nanny's wait; a longer one would hide the warning, not the wait.)"""
    import atexit
    import gc

    atexit.unregister(gc.freeze)  # once, however often it is asked
    atexit.register(gc.freeze)


def _limit_worker(shares, dask_worker=None):
    """Run in each worker by ``client.run``: apply its share (a worker that joined later: one
    thread per Dask thread is the safe guess), and stop the worker's statistical profiler, which
    samples every thread's stack 100 times a second on cores the files need (it shows in Dask's
    dashboard only; benchmarks/README.md, "Dask, second pass")."""
    share = shares.get(dask_worker.address) if dask_worker is not None else None
    _limit_this_process(share or WorkerThreads(1, 1))
    for name in ("profile", "profile-cycle"):
        callback = getattr(dask_worker, "periodic_callbacks", {}).get(name)
        if callback is not None:
            callback.stop()
    return share.threads if share else 1


def _process_one(path, cfg, out_dir, overwrite=False, shares=None, caller=None):
    """One file's result slot (:func:`process_many`), and the warnings it raised: ``(category,
    text, path)`` each, to be issued again in the caller (:func:`_warn_again`). Why: a local
    cluster's workers are processes, whose warnings went to the terminal in Python's two-line form
    (the worker's source file and line), not the command's one line, and once for each of the
    file's opens. A worker in the caller's own process (``caller``, its pid: a thread of an
    in-process cluster) leaves them as they are: they are the caller's already, and
    ``catch_warnings`` is not safe across threads."""
    if shares is not None:  # a worker that joined after client.run, or whose limits were reset
        from distributed import get_worker

        _limit_worker(shares, get_worker())
    if caller is None or caller == os.getpid():
        return _process_slot(path, cfg, out_dir, overwrite), []
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")  # once per place and text, as the caller's filter shows them
        slot = _process_slot(path, cfg, out_dir, overwrite)
    return slot, [(w.category, str(w.message), getattr(w.message, "path", None)) for w in caught]


def _process_slot(path, cfg, out_dir, overwrite) -> dict:
    try:
        res = process(path, cfg, out_dir=out_dir, overwrite=overwrite)
        return dict(res.results, output=str(out_dir))
    except Exception as exc:  # one bad file must not stop the others: reported in its slot
        return _error_result(path, exc)


def _warn_again(slot: dict, said) -> dict:
    """``slot``, once a worker's warnings (:func:`_process_one`) are issued here, each of its own
    category and carrying its file (``path``: the command line shows a file's warning once)."""
    import warnings

    for category, text, path in said:
        try:
            message = category(text)
        except Exception:  # a category built otherwise: its words still reach the user
            message = UserWarning(text)
        if path is not None:
            message.path = path
        warnings.warn(message, stacklevel=2)
    return slot


def _error_result(path, exc) -> dict:
    """A failed file's slot in :func:`process_many`'s results: its error's words as one file's
    :func:`process` raises them; the class named in ``error_type``, and in the words too where
    the error is no user's (a bug's ``KeyError: 'x'`` says nothing without it)."""
    kind = type(exc).__name__
    text = str(exc)
    user = isinstance(exc, (RadiokitError, ValueError, OSError, MemoryError))
    if not text:
        text = kind
    elif not user:
        text = f"{kind}: {text}"
    slot = {"source": path, "error": text, "error_type": kind}
    # the reader options the words advise (FormatError.advice), for a caller without them to reword
    return slot | ({"advice": dict(exc.advice)} if getattr(exc, "advice", None) else {})
