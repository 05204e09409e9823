"""The results file ``radiokit process`` writes into its results folder (``results.h5``).

``/`` (``@default = "entry"``)
``/entry`` (NXentry, ``@default = "steps"``; ``@source``: the experiment file;
``@results_json``: the numbers, as ``results.json`` holds them)
``/entry/steps`` (NXdata, ``@signal = "line_integral"``)
    ``line_integral`` (n_steps, rows, cols) float32: each step's mean corrected frame, cropped
    (the plot); ``step`` (n_steps,) the lab's step numbers; ``ratio`` (n_steps,); ``@crop``
    (row0, row1, col0, col1) of the crop in the detector frame.
``/entry/registration`` (NXcollection, ``@pair``: the (moving, fixed) steps)
    ``registered``, ``moving``, ``displacement``, ``det_j``, ``confidence``, and in simulated
    files ``truth_displacement``: whichever the run made.
``/entry/enhanced/{domain}`` (NXcollection, one per domain: ``log``, ``negative``)
    ``reference``, ``difference`` and ``k{k}``: the enhanced image for each factor ``k``.
``/entry/measurements`` (NXcollection): one attribute per region of interest.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import h5py
import numpy as np

from radiokit._names import shown
from radiokit.errors import FormatError
from radiokit.io._atomic import atomic_h5
from radiokit.io._experiment import ENTRY, check_links, checked_dataset
from radiokit.io._layout import ReadBudget, check_finite, open_layout, path_text, text

__all__ = ["RESULTS_STEPS", "ResultsRecord", "EnhancedImages", "write_results", "read_results"]

RESULTS_STEPS = f"{ENTRY}/steps"
RESULTS_REGISTRATION = f"{ENTRY}/registration"
RESULTS_ENHANCED = f"{ENTRY}/enhanced"
RESULTS_MEASUREMENTS = f"{ENTRY}/measurements"
_SIGNAL = "line_integral"
_OPTS = dict(compression="gzip", shuffle=True)


@dataclass(frozen=True)
class EnhancedImages:
    """One domain's enhancement: the reference, the difference and ``{k: enhanced image}``."""

    reference: np.ndarray
    difference: np.ndarray
    enhanced: Mapping = field(default_factory=dict)


@dataclass(frozen=True)
class ResultsRecord:
    """The arrays of one processed experiment, and its numbers as JSON text.

    Attributes
    ----------
    source : str
        The experiment file processed.
    results_json : str
        The numbers (``results.json``'s text).
    line_integral : (n_steps, rows, cols) float32
        Each step's mean corrected frame, cropped.
    step : (n_steps,) int
        The lab's step numbers.
    ratio : (n_steps,) float
        Each step's compression ratio (NaN where the file did not record it).
    crop : (4,) int
        ``(row0, row1, col0, col1)`` of the crop in the detector frame.
    pair : (2,) int
        The (moving, fixed) steps of ``registration``.
    registration : mapping name -> array
        ``registered``, ``moving``, ``displacement``, ``det_j``, ``confidence``,
        ``truth_displacement``: whichever the run made.
    enhanced : mapping domain -> EnhancedImages
    rois : mapping name -> array
        The regions of interest measured, in pixels of the crop.
    pixel_size_mm : float, optional
        The pixel pitch, written as ``x_pixel_size`` and ``y_pixel_size`` (metres) beside the
        steps. ``radiokit process`` gives it only where the experiment recorded it: a pitch it
        assumed is in the results' JSON alone, marked ``pixel_size_recorded: false``.

    Every array carries its ``@units`` (DESIGN.md): ``"1"`` for line integrals, transmissions,
    ratios, Jacobians and the confidence; ``"pixel"`` for displacements.
    """

    source: str
    results_json: str
    line_integral: np.ndarray
    step: np.ndarray
    ratio: np.ndarray
    crop: np.ndarray
    pair: tuple = ()
    registration: Mapping = field(default_factory=dict)
    enhanced: Mapping = field(default_factory=dict)
    rois: Mapping = field(default_factory=dict)
    pixel_size_mm: float | None = None


#: the ``@units`` of a registration array (NeXus spells a pixel count "pixel"); others are "1"
_REGISTRATION_UNITS = {"displacement": "pixel", "truth_displacement": "pixel"}


def write_results(path, record: ResultsRecord, *, overwrite=False, inputs=()) -> None:
    """Write ``record`` to ``path`` atomically (see :func:`radiokit.io.atomic_h5`); an existing
    ``path`` is replaced only with ``overwrite=True``.

    ``path`` is normally inside a results folder :func:`radiokit.io.atomic_dir` is assembling,
    new, so nothing needs replacing (the default was once True, unlike every other writer's).
    """
    with atomic_h5(path, overwrite=overwrite, inputs=inputs) as h5:
        h5.attrs["default"] = ENTRY
        entry = h5.create_group(ENTRY)
        entry.attrs["NX_class"] = "NXentry"
        entry.attrs["default"] = RESULTS_STEPS.rsplit("/", 1)[1]
        entry.attrs["source"] = path_text(record.source)
        entry.attrs["results_json"] = record.results_json
        steps = _group(h5, RESULTS_STEPS, "NXdata")
        steps.attrs["signal"] = _SIGNAL
        steps.create_dataset(_SIGNAL, data=np.asarray(record.line_integral, np.float32), **_OPTS)
        steps[_SIGNAL].attrs["interpretation"] = "image"
        steps[_SIGNAL].attrs["units"] = "1"  # a line integral, -ln(I/I0)
        steps["step"] = np.asarray(record.step, np.int64)
        steps["ratio"] = np.asarray(record.ratio, np.float64)
        steps["ratio"].attrs["units"] = "1"
        if record.pixel_size_mm is not None:
            for axis in ("x_pixel_size", "y_pixel_size"):
                steps[axis] = float(record.pixel_size_mm) * 1e-3
                steps[axis].attrs["units"] = "m"
        steps.attrs["crop"] = np.asarray(record.crop, np.int64)
        reg = _group(h5, RESULTS_REGISTRATION, "NXcollection")
        reg.attrs["pair"] = np.asarray(record.pair, np.int64)
        for name, values in record.registration.items():
            reg.create_dataset(name, data=np.asarray(values), **_OPTS).attrs["units"] = _REGISTRATION_UNITS.get(
                name, "1"
            )
        for domain, images in record.enhanced.items():
            g = _group(h5, f"{RESULTS_ENHANCED}/{domain}", "NXcollection")
            g.create_dataset("reference", data=np.asarray(images.reference), **_OPTS).attrs["units"] = "1"
            g.create_dataset("difference", data=np.asarray(images.difference), **_OPTS).attrs["units"] = "1"
            for k, image in images.enhanced.items():
                g.create_dataset(f"k{k}", data=np.asarray(image), **_OPTS).attrs["units"] = "1"
        m = _group(h5, RESULTS_MEASUREMENTS, "NXcollection")
        for name, roi in record.rois.items():
            m.attrs[name] = np.asarray(roi)


def _group(h5, name, nx_class):
    g = h5.require_group(name)
    g.attrs["NX_class"] = nx_class
    return g


def read_results(path, *, allow_external=False) -> ResultsRecord:
    """Read a file :func:`write_results` wrote.

    Raises
    ------
    FormatError
        The file lacks the results layout, or holds what that layout cannot: arrays of another
        type, rank or length, a ``crop`` or ``pair`` that is not integers, inf in ``ratio``,
        sizes over the memory budget, or data outside the file (unless ``allow_external``).
    """
    budget = ReadBudget(path)
    with open_layout(path, "a radiokit results file") as h5:

        def array(name, ndims=range(1, 5), kinds="buif"):
            return budget.read(checked_dataset(path, h5, name, kinds, ndims, allow_external))

        check_links(path, h5, f"{RESULTS_STEPS}/{_SIGNAL}", allow_external)
        if f"{RESULTS_STEPS}/{_SIGNAL}" not in h5:
            raise FormatError(path, f"lacks /{RESULTS_STEPS}/{_SIGNAL}: not a radiokit results file")
        line_integral = array(f"{RESULTS_STEPS}/{_SIGNAL}", (3,), "f")
        step, ratio = array(f"{RESULTS_STEPS}/step", (1,), "iu"), array(f"{RESULTS_STEPS}/ratio", (1,), "f")
        for name, values in (("step", step), ("ratio", ratio)):
            if len(values) != len(line_integral):
                raise FormatError(
                    path, f"/{RESULTS_STEPS}/{name} holds {len(values)} values for {len(line_integral)} step images"
                )
        check_finite(path, f"{RESULTS_STEPS}/ratio", ratio, nan_ok=True)  # NaN: a step without a ratio
        crop = _integers(path, h5[RESULTS_STEPS], "crop", 4)
        groups = {}
        for name in (RESULTS_REGISTRATION, RESULTS_ENHANCED, RESULTS_MEASUREMENTS):
            check_links(path, h5, name, allow_external)
            groups[name] = h5.get(name)
            if groups[name] is not None and not isinstance(groups[name], h5py.Group):
                raise FormatError(path, f"/{name} is not a group")
        reg, meas = groups[RESULTS_REGISTRATION], groups[RESULTS_MEASUREMENTS]
        enhanced = {}
        for domain in groups[RESULTS_ENHANCED] or {}:
            g = f"{RESULTS_ENHANCED}/{domain}"
            if not isinstance(h5[g], h5py.Group):
                raise FormatError(path, f"{shown('/' + g)} is not a group")  # a name the file holds (s53)
            ks = {name[1:]: array(f"{g}/{name}") for name in h5[g] if name.startswith("k")}
            enhanced[domain] = EnhancedImages(array(f"{g}/reference"), array(f"{g}/difference"), ks)
        attrs = h5[ENTRY].attrs
        return ResultsRecord(
            source=text(attrs.get("source", "")),
            results_json=text(attrs.get("results_json", "")),
            line_integral=line_integral,
            step=step,
            ratio=ratio,
            crop=crop,
            pair=_pair(path, reg),
            registration={name: array(f"{RESULTS_REGISTRATION}/{name}") for name in (reg or {})},
            enhanced=enhanced,
            rois={k: np.asarray(v) for k, v in meas.attrs.items() if k != "NX_class"} if meas is not None else {},
            pixel_size_mm=_pixel_size_mm(path, h5),
        )


def _pixel_size_mm(path, h5) -> float | None:
    """``x_pixel_size`` beside the steps, in mm; None where the file (written before it was) has none."""
    name = f"{RESULTS_STEPS}/x_pixel_size"
    if name not in h5:
        return None
    value = np.asarray(checked_dataset(path, h5, name, "f", (0,), False)[()], np.float64)
    check_finite(path, name, value)
    if not value > 0:
        raise FormatError(path, f"/{name} is {float(value)!r}: not a pixel pitch")
    return float(value) * 1e3


def _pair(path, reg) -> tuple:
    """``@pair`` of the registration group: (moving, fixed), or () where the run registered none."""
    if reg is None or np.size(reg.attrs.get("pair", ())) == 0:
        return ()
    return tuple(_integers(path, reg, "pair", 2).tolist())


def _integers(path, group, key, n) -> np.ndarray:
    """The attribute ``key`` of ``group``: exactly ``n`` integers."""
    if key not in group.attrs:
        raise FormatError(path, f"{group.name} lacks @{key}: expected {n} integers")
    value = np.asarray(group.attrs[key])
    if value.dtype.kind not in "iu" or value.shape != (n,):
        raise FormatError(path, f"{group.name}@{key} is {value.tolist()!r} ({value.dtype}); expected {n} integers")
    return value
