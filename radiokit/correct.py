"""Apply a :class:`~radiokit.calibrate.Calibration` fast: one fused float32 pass on all cores.

The work per frame is one compiled pass per row (:mod:`radiokit._correct_loop`: subtract the
dark, clamp, log, count the bad pixels), the rows split between threads (the loop releases the
GIL). Only rows that hold a non-positive or saturated pixel are searched afterwards, and the
defect fill plan touches only its pixels. Everything that does not depend on the frame
(``ln(flat - dark)``, ``1 / (flat - dark)``, the fill plan) is computed once per calibration.
"""

from __future__ import annotations

import functools
import hashlib
import os
import queue
import sys
import threading
import time
import warnings
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radiokit import _json as strict_json
from radiokit._names import shown
from radiokit._threads import pool, threads
from radiokit.calibrate import FLOAT32_MAX, Calibration, PixelFlag, beyond_float32, declared_range, frame_saturation
from radiokit.checks import is_number, refuse_masked
from radiokit.errors import FormatError

__all__ = [
    "correct_frames",
    "correct_files",
    "check_above_dark",
    "no_signal_level",
    "check_below_flats",
    "brighter_than_flats",
    "CorrectionReport",
    "CorrectionKernel",
    "DOMAINS",
    "fill_plan",
]

DOMAINS = ("log", "linear", "counts")
#: raw - dark at or below zero is clamped to this many counts before the log.
FLOOR_COUNTS = 0.5


@dataclass
class CorrectionReport:
    """What correction had to repair, per frame.

    Attributes
    ----------
    saturated, nonpositive : ndarray (n,) int
        Pixels at the ADC's top, or :data:`NOT_CHECKED` (-1) for a frame with no level to count
        against (:func:`radiokit.calibrate.frame_saturation` None: a negatively scaled panel's
        calibration, values above 65535); pixels with ``raw - dark <= 0`` or a non-finite raw
        value (clamped and filled).
    defects_filled : int
        Pixels of the calibration's defect map filled in every frame.
    flags : ndarray uint32, (rows, cols) or (n, rows, cols)
        The calibration mask with the per-frame ``SATURATED`` and ``NONPOSITIVE`` bits.
    """

    saturated: np.ndarray
    nonpositive: np.ndarray
    defects_filled: int
    flags: np.ndarray | None = None

    def summary(self) -> str:
        unchecked = int(np.count_nonzero(self.saturated == NOT_CHECKED))
        n = len(self.saturated)
        saturated = f"{int(self.saturated[self.saturated != NOT_CHECKED].sum())} saturated" if unchecked < n else ""
        if unchecked:  # never "0 saturated" of frames not checked
            saturated += f"{' (' if saturated else ''}saturation not checked in {unchecked} of {n} frame(s)"
            saturated += ")" if unchecked < n else ""
        return (
            f"{n} frame(s): {self.defects_filled} defect pixels filled per frame, "
            f"{saturated}, {int(self.nonpositive.sum())} non-positive or non-finite (filled)"
        )


#: the saturated count of a frame that had no saturation level to be counted against (the
#: HDF5 output's ``saturated`` column, its ``missing_value``; :class:`CorrectionReport`)
NOT_CHECKED = -1


# -- fill plans --------------------------------------------------------------------------------
@dataclass
class _Stage:
    dst: np.ndarray  # (m,) flat indices
    src: np.ndarray  # (m, k) flat indices
    w: np.ndarray  # (m, k) float32 weights summing to 1

    def apply(self, flat_image: np.ndarray):
        from radiokit._correct_loop import gather

        if self.dst.size:
            gather(flat_image, self.dst, self.src, self.w)


@functools.lru_cache(maxsize=16)
def _offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets ``(1, n)`` of the square ring-and-inside of ``radius``, centre excluded."""
    d = np.arange(-radius, radius + 1)
    dr, dc = np.meshgrid(d, d, indexing="ij")
    keep = (dr != 0) | (dc != 0)
    return dr[keep][None], dc[keep][None]


def _neighbour_stage(todo: np.ndarray, flat_invalid, shape, max_radius=4) -> tuple[_Stage, np.ndarray]:
    """Fill each pixel of ``todo`` (flat indices) with the mean of the valid pixels
    (not ``flat_invalid``, the flattened defect map) in the smallest square neighbourhood (radius 1,
    then 2, ...) that has any. Returns the stage and the pixels left without a valid neighbour
    within ``max_radius``."""
    rows, cols = shape
    dsts, srcs, ws = [], [], []
    for radius in range(1, max_radius + 1):
        if todo.size == 0:
            break
        r, c = np.divmod(todo, cols)
        dr, dc = _offsets(radius)
        rr = r[:, None] + dr
        cc = c[:, None] + dc
        inside = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        idx = np.where(inside, rr.clip(0, rows - 1) * cols + cc.clip(0, cols - 1), 0)
        ok = inside & ~flat_invalid[idx]
        count = ok.sum(axis=1)
        done = count > 0
        w = np.where(ok, 1.0, 0.0)[done] / count[done, None]
        dsts.append(todo[done])
        srcs.append(idx[done])
        ws.append(w.astype(np.float32))
        todo = todo[~done]
    if not dsts:
        return _Stage(np.zeros(0, np.int64), np.zeros((0, 1), np.int64), np.zeros((0, 1), np.float32)), todo
    if len(dsts) == 1:  # the usual case: every pixel had a valid neighbour at radius 1
        return _Stage(dsts[0], srcs[0], ws[0]), todo
    k = max(s.shape[1] for s in srcs)
    pad = lambda a, v: np.pad(a, ((0, 0), (0, k - a.shape[1])), constant_values=v)
    return _Stage(
        np.concatenate(dsts), np.concatenate([pad(s, 0) for s in srcs]), np.concatenate([pad(w, 0) for w in ws])
    ), todo


def _line_stage(lines: np.ndarray, n_lines: int, n_along: int, axis: int, shape) -> _Stage:
    """Fill whole rows (axis 0) or columns (axis 1) from the nearest valid lines on either side,
    linearly weighted: the manual's ``(V(p-1) + V(p+1)) / 2`` when both neighbours are valid."""
    bad = np.zeros(n_lines, bool)
    bad[lines] = True
    valid = np.flatnonzero(~bad)
    if valid.size == 0:
        raise ValueError("every line of the panel is a defect line: the calibration is unusable")
    dst, src, w = [], [], []
    along = np.arange(n_along)
    cols = shape[1]
    for p in np.flatnonzero(bad):
        pos = np.searchsorted(valid, p)
        lo = valid[pos - 1] if pos > 0 else None
        hi = valid[pos] if pos < valid.size else None
        if lo is None:
            lo, wl, wh = hi, 1.0, 0.0
        elif hi is None:
            hi, wl, wh = lo, 1.0, 0.0
        else:
            wl, wh = (hi - p) / (hi - lo), (p - lo) / (hi - lo)
        if axis == 0:
            dst.append(p * cols + along)
            src.append(np.stack([lo * cols + along, hi * cols + along], 1))
        else:
            dst.append(along * cols + p)
            src.append(np.stack([along * cols + lo, along * cols + hi], 1))
        w.append(np.tile(np.float32([wl, wh]), (n_along, 1)))
    return _Stage(np.concatenate(dst), np.concatenate(src), np.concatenate(w))


def fill_plan(cal: Calibration) -> list[_Stage]:
    """The ordered fill stages of a calibration: isolated defect pixels from valid neighbours,
    then defect columns, then defect rows (each line stage may read pixels an earlier one filled)."""
    rows, cols = cal.shape
    on_line = np.zeros(cal.shape, bool)
    on_line[cal.defect_rows, :] = True
    on_line[:, cal.defect_columns] = True
    invalid = cal.mask != 0
    isolated = invalid & ~on_line
    flat_invalid = invalid.ravel()
    stage, left = _neighbour_stage(np.flatnonzero(isolated), flat_invalid, cal.shape, max_radius=8)
    stages = [stage]
    if left.size:
        # Clusters wider than 16 px (a tiled panel's gaps, 10-37 px, from a recorded pixel_mask):
        # the nearest valid pixel's value, read after the neighbour stage. Weight 0 left them 0 in
        # either domain: open beam in the log one, nothing through in the linear one
        from scipy import ndimage

        if (~invalid).any():
            near = ndimage.distance_transform_edt(invalid, return_distances=False, return_indices=True)
            src = np.ravel_multi_index((near[0].ravel()[left], near[1].ravel()[left]), cal.shape)
            stages.append(_Stage(left, src[:, None].astype(np.int64), np.ones((left.size, 1), np.float32)))
        else:
            stages.append(_Stage(left, np.zeros((left.size, 1), np.int64), np.zeros((left.size, 1), np.float32)))
    if cal.defect_columns.size:
        stages.append(_line_stage(cal.defect_columns, cols, rows, 1, cal.shape))
    if cal.defect_rows.size:
        stages.append(_line_stage(cal.defect_rows, rows, cols, 0, cal.shape))
    return stages


@dataclass(eq=False)
class CorrectionKernel:
    """What correcting frames with one calibration needs that no frame changes, built once.

    Use :meth:`of`, which keeps one kernel per live :class:`~radiokit.calibrate.Calibration`
    (the calibration itself stays plain data).

    Attributes
    ----------
    dark : ndarray (rows, cols) float32
    response : ndarray (rows, cols) float32
        ``flat - dark`` where usable, 1 elsewhere (those pixels are filled anyway).
    stages : list
        The defect fill plan (:func:`fill_plan`).
    invalid : ndarray (rows, cols) bool
        The calibration's defect pixels.
    n_defects : int
    """

    dark: np.ndarray
    response: np.ndarray
    stages: list
    invalid: np.ndarray
    n_defects: int
    _log_i0: np.ndarray | None = None
    _inv_gain: np.ndarray | None = None

    @classmethod
    def build(cls, cal: Calibration) -> CorrectionKernel:
        """A new kernel for ``cal`` (uncached: see :meth:`of`)."""
        response = cal.flat - cal.dark
        ok = (cal.mask == 0) & (response > cal.thresholds.eps)
        response[~ok] = 1.0
        return cls(
            dark=np.ascontiguousarray(cal.dark, np.float32),
            response=np.ascontiguousarray(response, np.float32),
            stages=fill_plan(cal),
            invalid=cal.mask != 0,
            n_defects=int(np.count_nonzero(cal.mask)),
        )

    @classmethod
    def of(cls, cal: Calibration) -> CorrectionKernel:
        """The kernel of ``cal``: built on first use, kept while ``cal`` lives, rebuilt when one of
        its arrays (or ``thresholds``) is replaced by another object. Arrays changed in place
        are not noticed: build a new :class:`~radiokit.calibrate.Calibration` instead."""
        key = id(cal)
        parts = (cal.dark, cal.flat, cal.mask, cal.defect_rows, cal.defect_columns, cal.thresholds)
        with _KERNELS_LOCK:
            held = _KERNELS.get(key)
        if held is not None and held[0]() is cal and all(a is b for a, b in zip(held[1], parts)):
            return held[2]
        kernel = cls.build(cal)
        with _KERNELS_LOCK:  # the entry goes when the calibration does
            _KERNELS[key] = (weakref.ref(cal, lambda _ref, key=key: _KERNELS.pop(key, None)), parts, kernel)
        return kernel

    @property
    def log_i0(self) -> np.ndarray:
        """ln(flat - dark): the log domain needs only this and the dark."""
        if self._log_i0 is None:
            self._log_i0 = np.log(self.response)
        return self._log_i0

    @property
    def inv_gain(self) -> np.ndarray:
        """1 / (flat - dark), for the linear and counts domains."""
        if self._inv_gain is None:
            self._inv_gain = np.reciprocal(self.response)
        return self._inv_gain


#: id(calibration) -> (weak reference to it, the objects the kernel was built from, the kernel)
_KERNELS: dict[int, tuple] = {}
_KERNELS_LOCK = threading.Lock()


def _native(raw2d: np.ndarray) -> np.ndarray:
    """``raw2d`` as the compiled loop takes it: C-contiguous, native byte order, and a dtype numba
    computes with (float16 widened to float32)."""
    if raw2d.dtype == np.float16:
        return np.ascontiguousarray(raw2d, np.float32)
    if not raw2d.dtype.isnative:
        raw2d = raw2d.astype(raw2d.dtype.newbyteorder("="))
    return np.ascontiguousarray(raw2d)


def _saturation_in(dtype, saturation) -> tuple:
    """``(threshold in raw's dtype, whether to count)``: nothing counts when the dtype cannot
    reach the threshold (or saturation is not counted). Float frames count against the
    calibration's level as integer ones do: a float32 copy of a projection reported none of the
    pixels its uint16 twin counted."""
    if saturation is None:
        return dtype.type(0), False
    if dtype.kind == "f":
        return dtype.type(saturation), True
    if dtype.kind not in "ui" or saturation > np.iinfo(dtype).max:
        return dtype.type(0), False
    return dtype.type(max(saturation, np.iinfo(dtype).min)), True


#: flat indices of clamped / saturated pixels one thread records per frame before it falls back to
#: a second search of its rows (32 KB each; a realistic frame has a few hundred)
_ROOM = 4096


def _correct_range(raw2d, k: CorrectionKernel, coef, out2d, r0, r1, log_domain, scale, sat_value, count_sat):
    """Rows r0..r1 through the compiled loop; the clamped and saturated pixels' flat indices."""
    from radiokit._correct_loop import correct_rows, find

    bad, sat = np.empty(_ROOM, np.int64), np.empty(_ROOM, np.int64)
    n_bad, n_sat = correct_rows(raw2d, k.dark, coef, out2d, r0, r1, log_domain, scale, sat_value, count_sat, bad, sat)
    if n_bad > _ROOM or n_sat > _ROOM:  # many: search the rows again (the same tests)
        return find(raw2d, k.dark, r0, r1, sat_value, count_sat, n_bad, n_sat)
    return bad[:n_bad], sat[:n_sat]


def _correct_one(raw2d, k: CorrectionKernel, out2d, domain, scale, saturation):
    raw2d = _native(raw2d)
    rows = raw2d.shape[0]
    coef = k.log_i0 if domain == "log" else k.inv_gain
    args = (domain == "log", np.float32(scale), *_saturation_in(raw2d.dtype, saturation))  # the loop's settings
    nt = min(threads(), max(1, rows // 64))
    edges = [rows * i // nt for i in range(nt + 1)]
    # the compiled loop releases the GIL: one row range per thread
    parts = list(pool().map(lambda i: _correct_range(raw2d, k, coef, out2d, edges[i], edges[i + 1], *args), range(nt)))
    nonpos = np.concatenate([p[0] for p in parts])
    sat = np.concatenate([p[1] for p in parts])
    if raw2d.dtype.kind == "f" and sat.size:  # +inf passes any level: no value, counted as NaN or inf
        sat = sat[np.isfinite(raw2d.ravel()[sat])]
    if sat.size:  # defect pixels: filled by the plan, no measurement (a stuck pixel was "saturated" in every frame)
        sat = sat[~k.invalid.ravel()[sat]]
    flat_out = out2d.reshape(-1)
    for stage in k.stages:
        stage.apply(flat_out)
    if nonpos.size:
        from radiokit._correct_loop import fill_from_neighbours

        nonpos = nonpos[~k.invalid.ravel()[nonpos]]  # defect pixels: filled by the plan, counted as defects
        unknown = _beyond_reach(raw2d, nonpos, k.invalid, 2)
        fill_from_neighbours(out2d, nonpos, k.invalid, 2)
        _fill_nearest(out2d, unknown)
    return nonpos, sat


def _beyond_reach(raw2d, nonpos, invalid, radius) -> np.ndarray:
    """The non-finite raw pixels among ``nonpos`` with no valid pixel within ``radius``, which
    :func:`fill_from_neighbours` leaves at their clamp.

    Why apart from the other non-positive pixels: a finite ``raw - dark <= 0`` is a measurement
    (nothing came through: opaque, and the clamp says as much), a NaN or inf is none. Float frames
    mark masked regions and a tiled detector's gaps (10-37 px) NaN; clamped, they were bright
    opaque blobs to the registration and the ROIs."""
    if raw2d.dtype.kind != "f":
        return nonpos[:0]
    holes = nonpos[~np.isfinite(raw2d.ravel()[nonpos])]
    if not holes.size:
        return holes
    from scipy import ndimage

    known = ~invalid
    known.ravel()[nonpos] = False
    # on the holes' bounding box and ``radius`` around it, not the frame: a gap's column is a
    # sliver of it (a 37 px NaN gap at 2240 cost 0.3 s a frame over the frame)
    box, (r, c) = _box(holes, known.shape, radius)
    near = ndimage.maximum_filter(known[box], size=2 * radius + 1, mode="constant", cval=False)
    return holes[~near[r, c]]


def _box(idx, shape, margin):
    """The slices of the bounding box of flat indices ``idx`` widened by ``margin`` (within
    ``shape``), and ``idx``'s (row, col) in that box."""
    r, c = np.divmod(idx, shape[1])
    r0, c0 = max(int(r.min()) - margin, 0), max(int(c.min()) - margin, 0)
    box = (slice(r0, min(int(r.max()) + margin + 1, shape[0])), slice(c0, min(int(c.max()) + margin + 1, shape[1])))
    return box, (r - r0, c - c0)


def _fill_nearest(out2d, idx) -> None:
    """Give each pixel ``idx`` (flat) the value of the nearest pixel not in ``idx`` (Euclidean)."""
    if not idx.size:
        return
    from scipy import ndimage

    # on the bounding box widened by 1 px: that margin holds none of ``idx``, so no pixel beyond it
    # is nearer to one inside than the margin is (the frame's EDT cost 0.35 s at 2240)
    box, (r, c) = _box(idx, out2d.shape, 1)
    sub = out2d[box]
    mask = np.zeros(sub.shape, bool)
    mask[r, c] = True
    if mask.all():  # every pixel of the frame: no value to take (the caller refuses such frames)
        return
    rows, cols = ndimage.distance_transform_edt(mask, return_distances=False, return_indices=True)
    sub[r, c] = sub[rows[r, c], cols[r, c]]


def declared_top(cal: Calibration) -> int | None:
    """The top of the ADC the calibration's darks and flats declared (``provenance["bit_depth"]``,
    recorded by :meth:`Calibration.from_frames` from the files' word), None where it was guessed."""
    bits = cal.provenance.get("bit_depth")
    signed = cal.provenance.get("bit_depth_signed") is True  # a signed ADC's: 2**(bits - 1) - 1
    return declared_range(bits, signed)[1] if type(bits) is int and 1 <= bits <= 16 else None


def above_top(cal: Calibration, raw2d, top) -> int:
    """How many of ``raw2d``'s pixels outside the calibration's mask read above ``top`` (finite
    ones; 0 where ``top`` is None). A stuck pixel already masked is no news."""
    if top is None or raw2d.dtype.kind not in "uif" or not raw2d.size:
        return 0
    if raw2d.dtype.kind in "ui" and (np.iinfo(raw2d.dtype).max <= top or raw2d.max() <= top):
        return 0
    over = raw2d > top  # NaN: False; +inf is no value (counted as non-finite)
    if raw2d.dtype.kind == "f":
        over &= np.isfinite(raw2d)
    return int(np.count_nonzero(over & (cal.mask == 0)))


def warn_above_top(cal: Calibration, n_pixels: int, n_frames: int, stacklevel=3) -> None:
    """The warning for ``n_pixels`` (in ``n_frames`` frames) above :func:`declared_top`. Why:
    C7942.md, a value above 4095 means a wrong bit or byte order or another panel, to be said;
    such a pixel was corrected as data (L = -1.90) in silence where no reader had warned (review s42)."""
    if not n_pixels:
        return
    from radiokit.io import BitDepthWarning

    top = declared_top(cal)
    warnings.warn(
        BitDepthWarning(
            f"{n_pixels} pixels of {n_frames} frame(s) read above {top}, the top of the "
            f"{cal.provenance['bit_depth']}-bit{' signed' if cal.provenance.get('bit_depth_signed') is True else ''} ADC the calibration's darks and flats declared: a wrong bit or "
            "byte order, or another panel's frames (C9730DK/C9732DK are 14-bit); corrected as stored"
        ),
        stacklevel=stacklevel,
    )


def _correct_checked(cal: Calibration, raw2d, out2d, domain, count_saturated=True):
    """Correct one frame; the non-positive pixels met and, if ``count_saturated``, the saturated
    ones (only reported, never repaired: a caller that reports nothing does not pay for them), or
    None where the frame has no level to count them against: not checked, which is no "0"."""
    k = CorrectionKernel.of(cal)
    scale = cal.c if domain == "counts" else 1.0
    saturation = None
    if raw2d.dtype.kind == "f" and raw2d.size and not np.isfinite(raw2d).any():
        raise ValueError("a raw frame holds only NaN or inf: nothing to correct or fill from")
    if raw2d.dtype.kind in "uif" and count_saturated:
        saturation = frame_saturation(cal.thresholds.saturation, raw2d, cal.mask)
    top = beyond_float32(raw2d)
    if top is not None:  # cast, they became inf and were filled as non-positive: a bright frame made opaque
        raise ValueError(
            f"a raw frame holds values up to {top:.3g}, beyond float32's range ({FLOAT32_MAX:.2g}) the "
            "correction computes in: no detector's counts; rescale them"
        )
    nonpos, sat = _correct_one(raw2d, k, out2d, domain, scale, saturation)
    return nonpos, (None if count_saturated and saturation is None else sat)


#: A frame whose brightest tenth (its 90th percentile above the dark) stands no higher than this
#: many of one dark frame's noise sigmas (the calibration's ``dark_noise_counts``) holds no signal:
#: with the beam off a frame's 90th percentile lies 1.3 sigmas above the dark. The brightest
#: tenth, not the median: a collimated frame (60 % behind lead) has its median at the dark and its
#: open field far above it. Sigmas of a pixel, not of the median: a low-dose frame (flats 200
#: counts above the dark, noise 14, 30 % transmission) holds 60 counts, 4 sigmas, and 5 sigmas on
#: the median refused it (review s36r4).
NO_SIGNAL_SIGMAS = 3.0
# Not also a share of the flats' level: a whole-frame attenuator at 1.3 % transmission (40 counts
# under flats of 3000) is a real, dim radiograph, and 2 % of the flats refused it. So a beam-off
# frame whose dark has drifted (the panel's offset drifts for about an hour after power-on,
# C7942.md) by more than about 1.7 sigmas passes this check: by its counts alone it cannot be
# told from a dim frame.
#: the share of a frame's pixels judged by their highest: its brightest tenth
NO_SIGNAL_QUANTILE = 0.9
#: a frame whose median is at the dark still holds signal where this share of its pixels lies in
#: the beam's range, ``OPEN_FIELD_SHARE`` to ``MAX_OPEN_FIELD`` of the flats' level
#: (``Calibration.c``) and below the ADC's top: an open field of a percent of the frame beside a
#: collimator's lead
OPEN_FIELD_FRACTION = 0.01
OPEN_FIELD_SHARE = 0.1
MAX_OPEN_FIELD = 1.5  #: an open field above this share of the flats' level is no beam's


def no_signal_level(cal: Calibration) -> float | None:
    """Counts above the dark at or below which a frame's 90th percentile is no signal:
    ``thresholds.eps`` plus :data:`NO_SIGNAL_SIGMAS` of the dark's recorded noise; None where none
    is recorded (a calibration from one dark, or from plain arrays)."""
    noise = cal.provenance.get("dark_noise_counts")
    if not is_number(noise) or not np.isfinite(noise) or noise < 0:
        return None
    return cal.thresholds.eps + NO_SIGNAL_SIGMAS * float(noise)


def _in_a_region(beam):
    """How many of ``beam``'s True samples have a True 4-neighbour: an open field is a region (a
    slit one sample wide still is), hot pixels outside the defect mask are isolated, and 1.5 % of
    a beam-off frame passed as a collimated frame's open field (s43). Isolated at a share ``h``,
    about ``4 h^2`` of the samples still count (0.4 % at 3 %, under :data:`OPEN_FIELD_FRACTION`)."""
    beside = np.zeros_like(beam)
    beside[1:] |= beam[:-1]
    beside[:-1] |= beam[1:]
    beside[:, 1:] |= beam[:, :-1]
    beside[:, :-1] |= beam[:, 1:]
    return int(np.count_nonzero(beam & beside))


def check_above_dark(cal: Calibration, raw2d) -> None:
    """Refuse a frame that holds no signal: its 90th percentile (defects and NaN aside; about 128 x
    128 pixels sampled) no more than :func:`no_signal_level` above the dark, or its median no
    more than ``thresholds.eps`` above it (the only test where the dark's noise is not recorded)
    unless a percent of it lies in the beam's range as a region (an open field beside a
    collimator, :data:`OPEN_FIELD_FRACTION`; isolated hot pixels are none, :func:`_in_a_region`).

    :func:`correct_frames` clamps and fills such a frame (a beam-off frame stays finite); a caller
    that takes the frame for data calls this (``radiokit correct`` and ``process`` each frame).
    Why: float32 frames already corrected (transmission about 0.5 against a dark of 100 counts),
    darks given as the frames and all-zero frames were written as a uniform image with exit code
    0, and a beam-off projection was averaged into its step."""
    step = max(1, min(raw2d.shape) // 128)  # as brighter_than_flats: a fraction of a frame's budget
    s = (slice(None, None, step), slice(None, None, step))
    with np.errstate(over="ignore"):  # float64 past float32's range: refused as such by the correction
        raw_grid = np.asarray(raw2d[s], np.float32)
        signal_grid = raw_grid - cal.dark[s]
    # defects aside; a NaN made the median NaN, and the frame passed
    ok = (cal.mask[s] == 0) & np.isfinite(signal_grid)
    signal = signal_grid[ok]
    if not signal.size:
        return
    level = no_signal_level(cal)
    # the median at the dark is no signal whatever the noise (as before the tenth was judged: a
    # beam-off frame noisier than the darks, 98 % of it at or below the dark, passed the tenth)
    seen, what = float(np.median(signal)), "its median"
    if seen > cal.thresholds.eps and level is not None:
        seen, what = float(np.quantile(signal, NO_SIGNAL_QUANTILE)), "its brightest tenth"
    else:
        level = cal.thresholds.eps
        # a frame mostly behind a collimator or a dense object: the median at the dark, but an
        # open field at a tenth of the flats' level or more (review s42rr: 91 % behind lead was
        # refused); a noisy beam-off frame's top percent is a few of its noise above the dark.
        # The open field is the beam's: below the ADC's top and not far above the flats (two
        # saturated rows of a beam-off frame passed, review s42rr2)
        sat = cal.thresholds.saturation
        beam = ok & (signal_grid > OPEN_FIELD_SHARE * cal.c) & (signal_grid <= MAX_OPEN_FIELD * cal.c)
        if sat is not None:
            beam &= raw_grid < sat
        if _in_a_region(beam) >= OPEN_FIELD_FRACTION * signal.size:
            return
    if seen <= level:
        raise ValueError(
            f"no signal above the dark (frame {raw2d.dtype}, {float(np.nanmin(raw2d)):.4g} .. "
            f"{float(np.nanmax(raw2d)):.4g}: {what} {seen:+.3g} counts from a dark of about "
            f"{float(np.median(cal.dark)):.4g}, not above its noise, {level:.3g} counts): raw counts were "
            "expected, not frames already corrected, a frame with the beam off, darks, nor another set-up's frames"
        )


def correct_frames(cal: Calibration, raw, *, domain="log", out=None, return_report=False, check=True):
    """Correct a raw frame or stack with ``cal``: offset, gain, defects, then transmission or line integral.

    Parameters
    ----------
    cal : Calibration
    raw : array_like (rows, cols) or (n, rows, cols)
        Raw counts (any integer or float dtype).
    domain : {"log", "linear", "counts"}
        ``"log"``: line integral ``-ln(I / I0)``, more attenuation brighter. ``"linear"``:
        transmission ``I / I0 = (raw - dark) / (flat - dark)``. ``"counts"``: the manual's
        gain-corrected grey levels ``c * (raw - dark) / (flat - dark)``.
    out : ndarray float32, optional
        Where to write the result (same shape as ``raw``).
    return_report : bool
        Also return a :class:`CorrectionReport` with per-frame counts of saturated and
        non-positive pixels and the per-pixel flags.
    check : bool
        Refuse, as ``radiokit correct`` does, a frame that holds no signal
        (:func:`check_above_dark`: a beam-off frame, darks, a frame already corrected, an 8-bit
        display copy) or whose result is brighter than the flats (:func:`check_below_flats`:
        counts MSB-aligned, ``<< 4``, or at another exposure than the flats). Each judges about
        128 x 128 pixels whatever the frame's size: together under a millisecond at 2240 x 2240,
        a tenth of the correction or less. ``False`` for a caller that checks the frames itself
        (``radiokit process`` judges a step's mean, after each frame's exposure is rescaled) or
        means to correct such frames.

    Returns
    -------
    ndarray float32, and the report if asked.

    Raises
    ------
    ValueError
        ``raw`` or ``out`` of another shape or a non-numeric dtype, ``raw`` a masked array (its
        mask would be ignored), a frame of only NaN or inf, or, with ``check``, a frame refused
        as above (named by its index in a stack; ``out`` then holds the frames before it, and
        the refused one when it was brighter than the flats).
    TypeError
        ``out`` is no numpy array.

    Notes
    -----
    Never NaN or inf: pixels of the defect map are filled from valid neighbours within 8 px,
    farther ones (a wide recorded gap) from the nearest valid pixel (lines from the two
    neighbouring valid lines, linearly weighted); pixels whose ``raw - dark <= 0``
    are clamped to half a count, filled from valid neighbours where they have any (within
    2 px), flagged ``NONPOSITIVE`` and counted. NaN or inf raw pixels are flagged and counted
    so too; beyond 2 px of a valid pixel they take the nearest filled value (unknown, not
    opaque as a finite value at or below the dark is). Raw values at or above ``thresholds.saturation`` are
    flagged ``SATURATED`` and counted; raw values above the top of the ADC the calibration's frames
    declared (:func:`declared_top`) are warned of with their count (``BitDepthWarning``), and
    corrected as stored. Filling happens in the output domain. What does not
    depend on the frame is computed once per calibration (:class:`CorrectionKernel`).

    Examples
    --------
    >>> import numpy as np
    >>> from radiokit.calibrate import Calibration
    >>> from radiokit.correct import correct_frames
    >>> darks = np.full((3, 64, 64), 100, np.uint16)
    >>> flats = np.full((3, 64, 64), 3100, np.uint16)
    >>> cal = Calibration.from_frames(darks, flats)
    >>> raw = np.full((64, 64), 1600, np.uint16)  # (1600 - 100) / (3100 - 100): I/I0 = 0.5
    >>> float(correct_frames(cal, raw, domain="linear")[10, 10])
    0.5
    >>> round(float(correct_frames(cal, raw)[10, 10]), 4)  # -ln(0.5)
    0.6931

    Frames that cannot be this calibration's counts are refused; ``check=False`` corrects them:

    >>> msb = raw * 16  # 12-bit counts saved MSB-aligned, the darks and flats not
    >>> correct_frames(cal, msb, domain="linear")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: brighter than the flats, 8.50x their level ...
    >>> round(float(correct_frames(cal, msb, domain="linear", check=False)[10, 10]), 2)
    8.5
    """
    if domain not in DOMAINS:
        raise ValueError(f"domain={domain!r}: expected one of {DOMAINS}")
    if isinstance(raw, (str, os.PathLike)):  # was "raw frames of shape () do not match ..."
        raise ValueError(f"raw={str(raw)!r}: expected frames (an array), not a file name: radiokit.io.read(path).data")
    refuse_masked(raw, "raw")
    raw = np.asarray(raw)
    if raw.ndim not in (2, 3) or raw.shape[-2:] != cal.shape:
        raise ValueError(f"raw frames of shape {raw.shape} do not match the calibration's {cal.shape}")
    if raw.dtype.kind not in "uif":
        raise ValueError(f"raw frames must be numeric, got dtype {raw.dtype}")
    if out is None:
        out = np.empty(raw.shape, np.float32)
    elif not isinstance(out, np.ndarray):
        raise TypeError(
            f"out must be a numpy array (C-contiguous float32 of shape {raw.shape}), got {type(out).__name__}"
        )
    elif out.shape != raw.shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be C-contiguous float32 of shape {raw.shape}, got {out.dtype} {out.shape}")
    stack = raw if raw.ndim == 3 else raw[None]
    ostack = out if out.ndim == 3 else out[None]
    n = stack.shape[0]
    sat_counts = np.zeros(n, np.int64)
    np_counts = np.zeros(n, np.int64)
    flags = np.broadcast_to(cal.mask, stack.shape).copy() if return_report else None
    top, n_over = declared_top(cal), 0
    for i in range(n):
        where = f"frame {i} of {n}: " if raw.ndim == 3 else ""
        checking = check
        try:
            if check:
                check_above_dark(cal, stack[i])
            checking = False
            nonpos, sat = _correct_checked(cal, stack[i], ostack[i], domain, count_saturated=return_report)
            checking = check
            if check:
                check_below_flats(cal, ostack[i], domain)
        except ValueError as exc:  # one line naming the frame, and, for a check, the way past it
            how = "; correct_frames(..., check=False) corrects it regardless" if checking else ""
            raise ValueError(f"{where}{exc}{how}") from None
        np_counts[i], sat_counts[i] = nonpos.size, NOT_CHECKED if sat is None else sat.size
        n_over += above_top(cal, stack[i], top)
        if return_report:
            flags[i].ravel()[nonpos] |= np.uint32(PixelFlag.NONPOSITIVE)
            if sat is not None:
                flags[i].ravel()[sat] |= np.uint32(PixelFlag.SATURATED)
    warn_above_top(cal, n_over, n)
    if not return_report:
        return out
    report = CorrectionReport(
        sat_counts, np_counts, CorrectionKernel.of(cal).n_defects, flags if raw.ndim == 3 else flags[0]
    )
    return out, report


#: How long an interrupted run waits for its background writer to finish the frame it is writing
#: before it is left behind (a daemon thread: it ends with the process); a frame of 2240 x 2240
#: float32 is written in well under a second.
STOP_WAIT_S = 10.0


#: How often the background writer looks at its queue without being woken (see ``_run``).
_WAKE_S = 0.1


class _BackgroundWriter:
    """Write frames on a second thread while the next one is corrected; errors (a full disk)
    surface in the producer at the next ``put`` or at exit. Three rotating buffers: one being
    corrected, one queued, one being written."""

    def __init__(self, writer, depth=1, stop_wait_s=STOP_WAIT_S):
        self._writer = writer
        self._stop_wait_s = stop_wait_s
        self._queue = queue.Queue(maxsize=depth)
        self._buffers = [np.empty(writer.frame_shape, writer.dtype) for _ in range(depth + 2)]
        self._next = 0
        self._error = None
        self._thread = threading.Thread(target=self._run, name="radiokit-writer", daemon=True)
        self._thread.start()

    def _run(self):
        while True:
            try:
                # a bounded wait, then a look at the queue: a Ctrl-C inside the producer's put(),
                # after the item was queued and before the wake-up, left this thread asleep beside
                # it for good (the stop's sentinel then found the queue full: 10 s, "did not stop")
                item = self._queue.get(timeout=_WAKE_S)
            except queue.Empty:
                continue
            if item is None:
                return
            if self._error is None:
                try:
                    self._writer.append(item[0], **item[1])
                except BaseException as exc:  # handed to the producer
                    self._error = exc

    def buffer(self) -> np.ndarray:
        buf = self._buffers[self._next]
        self._next = (self._next + 1) % len(self._buffers)
        return buf

    def put(self, frame, **series):
        if self._error is not None:
            raise self._error
        self._queue.put((frame, series))

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self._error = self._error or exc  # the writer skips what is still queued
        # The writer thread must have stopped before its file is closed and removed: a second
        # Ctrl-C or SIGTERM arriving here waits for it too, then is raised.
        interrupt, sent = None, False
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
            interrupt = exc
        while True:
            try:
                if not sent:
                    self._queue.put(None, timeout=self._stop_wait_s if interrupt is not None else None)
                    sent = True
                # after an interrupt the wait is bounded (STOP_WAIT_S): a writer stuck for good (an
                # HDF5 lock left taken where the interrupt landed held a `correct` for minutes)
                self._thread.join(self._stop_wait_s if interrupt is not None else None)
                break
            except KeyboardInterrupt as again:
                interrupt = again
                self._error = self._error or again
            except queue.Full:  # the writer never took its last frame: it is stuck too
                break
        if self._thread.is_alive():
            print(
                f"radiokit: the frame writer did not stop within {self._stop_wait_s:g} s of the interrupt; "
                "left behind (the output being written is removed)",
                file=sys.stderr,
            )
        if interrupt is not None:
            raise interrupt
        if self._error is not None and exc_type is None:
            raise self._error


def _mask_attrs(cal: Calibration) -> dict:
    """The attributes of a corrected stack's ``pixel_mask`` (:func:`correct_files`)."""
    return {
        "description": "the calibration's defect map (PixelFlag bits): filled in every frame",
        "defect_rows": np.asarray(cal.defect_rows, np.int64),
        "defect_columns": np.asarray(cal.defect_columns, np.int64),
    }


def _correct_planned(cal, src, fi, frame, domain, factor):
    """Frame ``fi`` of ``src`` corrected into ``frame``, at the flats' tube current (``factor``),
    and its pixels above :func:`declared_top`; errors name the file and the frame (a run reads many)."""
    raw = src[fi]
    over = above_top(cal, raw, declared_top(cal))
    try:
        check_above_dark(cal, raw)  # as process does: darks, a beam-off frame, frames already corrected
        nonpos, sat = _correct_checked(cal, raw, frame, domain)
        if factor != 1:
            _rescale(frame, domain, factor)
        check_below_flats(cal, frame, domain)
    except ValueError as exc:
        raise FormatError(src.path, f"frame {fi}: {exc}") from exc
    return nonpos, sat, over


#: a frame whose median transmission is above this is brighter than the open beam, which no
#: object can make it: a tube's drift between flats and projections is a few per cent
MAX_MEDIAN_TRANSMISSION = 1.1


def brighter_than_flats(corrected, domain, c=1.0) -> float | None:
    """The median transmission of a corrected image (in ``domain``; ``c`` the flats' level, for
    ``"counts"``) when it passes :data:`MAX_MEDIAN_TRANSMISSION`, else None. The median is taken
    over about 128 x 128 pixels: every 4th row and column took 5 ms of a 2240 x 2240 frame, a
    fifth of the streaming budget. Shared by :func:`check_below_flats` (a frame) and ``radiokit
    process`` (a step's mean line integral), each of which says why in its own words."""
    step = max(1, min(corrected.shape) // 128)
    median = float(np.median(corrected[::step, ::step]))
    transmission = {"log": float(np.exp(-median)), "linear": median, "counts": median / c}[domain]
    return transmission if transmission > MAX_MEDIAN_TRANSMISSION else None


def check_below_flats(cal: Calibration, corrected, domain) -> None:
    """Refuse a corrected frame (in ``domain``) whose median transmission passes
    :data:`MAX_MEDIAN_TRANSMISSION` (:func:`brighter_than_flats`). Why: a 12-bit panel's
    projections saved MSB-aligned (``counts << 4``) against LSB-aligned darks and flats were
    written as a line integral of -2.77 everywhere, exit code 0; so were frames at a higher
    exposure than the flats."""
    transmission = brighter_than_flats(corrected, domain, cal.c)
    if transmission is not None:
        raise ValueError(
            f"brighter than the flats, {transmission:.2f}x their level (median transmission), which no object makes "
            "a frame: frames of another exposure (tube current or time) or bit alignment (counts << 4: 16x) than "
            "the darks and flats"
        )


def _rescale(frame, domain, factor) -> None:
    """Multiply a corrected frame's transmission by ``factor``, in its domain, in place."""
    if domain == "log":
        frame -= np.float32(np.log(factor))
    else:
        frame *= np.float32(factor)


def _planned(segments):
    """(source, frame, step, factor) of each frame to correct, one at a time (see correct_files)."""
    for si, picked, steps, factors in segments:
        for j, fi in enumerate(picked):
            fi = int(fi)
            step = int(steps[fi]) if steps is not None else -1
            yield si, fi, step, (1.0 if factors is None else float(factors[j]))


def _stack_pitch(pitch: dict, src) -> None:
    """Keep in ``pitch`` the first pitch a frame file states (``sizes``, ``path``); refuse a file
    stating another. Why: the stack keeps it (a 0.139 mm panel's corrected frames said nothing),
    and one calibration corrects one panel's frames."""
    from radiokit.io import check_same_pixel_size

    sizes = {k: src.meta[k] for k in ("x_pixel_size", "y_pixel_size") if src.meta.get(k) is not None}
    # a DICOM's PixelSpacing (no ImagerPixelSpacing) is at the patient, the pitch over the
    # magnification: kept as the stack's detector pitch, object sizes were divided by it twice,
    # and the same panel's file stating ImagerPixelSpacing was refused as another panel's
    if not sizes or src.meta.get("pixel_size_source") == "PixelSpacing":
        return
    if "sizes" in pitch:
        check_same_pixel_size(
            src.path, sizes, pitch["path"], pitch["sizes"], "frames of one panel are corrected together"
        )
    else:
        pitch.update(sizes=sizes, path=src.path)


def _judge_segments(inputs, cal: Calibration, image_keys, hints, pitch=None) -> tuple[list, list]:
    """Per source of ``inputs``, ``(index, frames, steps, exposure factors)`` of the frames to
    correct, and ``(frames, frame shape, dtype, image keys)`` of its header as judged: every frame
    of a file without image keys as a range, not a list -- a 14 kB HDF5 file declaring 10**8
    frames made a list of 10**8 tuples (GBs) before the output's size could be refused. Keyed
    files' records fit the memory budget. Every file is judged from its header before any frame
    is read, every bad one named, one file open at a time (:func:`radiokit.io.judge_all`)."""
    from radiokit.calibrate import check_layout, exposure_factors
    from radiokit.io import judge_all

    segments, headers = [], []
    stated: dict = {}  # the first frame file's own sub-array, where the calibration states none
    pitch = {} if pitch is None else pitch  # filled with the frames' pitch (_stack_pitch)

    def judge(src):
        if not len(src):  # as `radiokit info` and `calibrate` say it
            raise FormatError(src.path, "no frames")
        _stack_pitch(pitch, src)
        check_layout(cal, src.meta, src.path, stated)  # first: a quarter turn is no other frame size
        if src.frame_shape != cal.shape:
            raise FormatError(src.path, f"frames are {src.frame_shape}, the calibration is {cal.shape}")
        _check_type_reaches_flats(src, cal)
        keys = src.meta.get("image_key")
        steps = src.meta.get("step")
        si = len(segments)  # the source's index once every file is good (else nothing is kept)
        headers.append((len(src), src.frame_shape, np.dtype(src.dtype), None if keys is None else np.asarray(keys)))
        if keys is None:
            segments.append((si, range(len(src)), steps, None))
            return
        picked = np.flatnonzero(np.isin(np.asarray(keys), list(image_keys)))
        factors = exposure_factors(cal, src.meta, src.path, picked)  # 1 unless both currents are recorded
        segments.append((si, picked, steps, factors))

    judge_all(inputs, check=judge, **hints)
    return segments, headers


class _OneOpen:
    """The sources of ``paths`` opened again one at a time, as the frames to correct reach them
    (:func:`_planned` goes through them in order): each is closed before the next opens. Why:
    held open together, 300 single-frame TIFFs passed macOS's default limit of 256 open files.
    A file that no longer has the header it was judged by is refused, not read."""

    def __init__(self, paths, headers, hints):
        self._paths, self._headers, self._hints = paths, headers, hints
        self._index, self._src = None, None

    def __getitem__(self, si):
        from radiokit.io import open_frames

        if si != self._index:
            self.close()
            src = open_frames(self._paths[si], **self._hints)
            if not self._as_judged(src, *self._headers[si]):
                src.close()
                raise FormatError(src.path, "changed while being corrected: its header is not the one checked")
            self._index, self._src = si, src
        return self._src

    @staticmethod
    def _as_judged(src, n, shape, dtype, keys) -> bool:
        """Whether ``src`` holds the frames judged: more frames appended since (an acquisition
        still writing) leave those judged as they were."""
        now = src.meta.get("image_key")
        if len(src) < n or src.frame_shape != shape or np.dtype(src.dtype) != dtype or (now is None) != (keys is None):
            return False
        return keys is None or np.array_equal(np.asarray(now)[:n], keys)

    def close(self):
        if self._src is not None:
            self._src.close()
        self._index, self._src = None, None


def _check_type_reaches_flats(src, cal: Calibration) -> None:
    """Refuse integer frames whose type cannot hold the flats' level.

    Why: an 8-bit copy of a radiograph (a viewer's export) corrected against the panel's
    calibration clamped every pixel at the dark and was written as a uniform image, exit code 0;
    no such frame can be the calibration's counts."""
    dtype = np.dtype(src.dtype)
    if dtype.kind not in "biu":
        return
    top = 1 if dtype.kind == "b" else np.iinfo(dtype).max  # bool: a 1-bit TIFF, a mask
    level = float(np.median(cal.flat[::4, ::4]))
    if top < level:
        raise FormatError(
            src.path,
            f"{dtype} pixels (at most {top}) cannot reach the calibration's flats (about "
            f"{level:.0f} counts): frames of another bit depth than the darks and flats (an 8-bit display copy?)",
        )


_KINDS = {0: "projection", 1: "flat", 2: "dark", 3: "invalid frame"}


def _nothing_to_correct(headers, image_keys) -> str:
    """What the files hold instead of the frames asked for: "(image_keys=(0,))" named no kind,
    and a calibration file given as the frames (its dark and flat) read as an empty stack."""
    wanted = " or ".join(f"{_KINDS.get(int(k), 'frame')} (image_key {int(k)})" for k in image_keys)
    held = sorted({int(k) for *_, keys in headers for k in ([] if keys is None else keys)})
    kinds = ", ".join(f"{_KINDS.get(k, f'image_key {k}')}s" for k in held)
    return f"no {wanted} to correct" + (f"; only {kinds}" if kinds else "")


#: The longest list of sources (as JSON text) a corrected stack names one by one: a quarter of
#: what radiokit reads of a description (radiokit._json.MAX_CHARS), the rest left to the
#: calibration's provenance beside it in a TIFF's one description. About 11 000 names of 90
#: characters; past it, the list is summarised.
SOURCES_LISTED_CHARS = strict_json.MAX_CHARS // 4


def stack_meta(domain: str, provenance: dict, inputs, listed_in: str | None = None) -> dict:
    """The metadata :func:`correct_files` writes with its stack: the domain, the calibration's
    provenance and the input files (``sources``, which the ``source_index`` column counts into).
    A list whose JSON passes :data:`SOURCES_LISTED_CHARS`, or the room the rest leaves in
    radiokit's bound (:data:`radiokit._json.MAX_CHARS`), is summarised:
    ``{"count", "first", "last", "sha256"}``, the digest of the names' bytes each ended by NUL
    but the last (no path holds one; a newline, a path can). Why: 50 000 projection files, one
    per TIFF, are 4.6 MB of names, past what radiokit reads back, and the stack's description
    and ``sources`` were kept as text by its own readers (s53). ``listed_in``: where the stack
    lists every name whatever this says (an HDF5 stack's ``/entry/sources``, which its frames'
    ``source_index`` resolves against: a summary dropped the middle names they counted into),
    named in the summary."""
    names = [str(p) for p in inputs]
    # a TIFF's one description holds the provenance too: the list gets the room it leaves (a
    # calibration of 10 000 files, 3.3 MB, beside 9 000 names made a .tif output refused: s53rvoff)
    rest = len(strict_json.dumps({"domain": domain, "calibration": provenance, "sources": []}))
    if names and len(strict_json.dumps(names)) > min(SOURCES_LISTED_CHARS, strict_json.MAX_CHARS - rest):
        digest = hashlib.sha256(b"\0".join(os.fsencode(n) for n in names)).hexdigest()
        names = {"count": len(names), "first": names[0], "last": names[-1], "sha256": digest}
        if listed_in:
            names["listed_in"] = listed_in
    return {"domain": domain, "calibration": provenance, "sources": names}


def _listed_in(output) -> str | None:
    """Where a stack written to ``output`` lists every input whatever its meta says: an HDF5
    stack's ``/entry/sources``, which its frames' ``source_index`` counts into; None for a TIFF
    stack (no ``source_index``: its meta's ``sources``, listed or summarised, are all it says)."""
    from radiokit.io._write import SOURCES

    return f"/{SOURCES}" if Path(output).suffix.lower() in (".h5", ".hdf5", ".nxs") else None


def correct_files(
    inputs, cal: Calibration, output, *, domain="log", progress=True, image_keys=(0,), overwrite=False, **hints
) -> dict:
    """Stream frames from ``inputs`` through ``cal`` into ``output`` (``.h5`` or ``.tif``).

    One raw frame and one corrected frame are in memory at a time, whatever the stack length.
    From experiment files only frames whose ``image_key`` is in ``image_keys`` (projections by
    default) are corrected; other formats have no keys and every frame is. The HDF5 output
    records, per frame, the source file and frame index, the compression step where known, and
    the saturated (:data:`NOT_CHECKED`, -1, where not checked) and non-positive counts, and the calibration's defect map (the pixels filled in
    every frame) as ``/entry/instrument/detector/pixel_mask``; its metadata (a TIFF's description)
    names the domain, the calibration's provenance and the input files, ``sources`` (:func:`stack_meta`:
    past about 11 000 files, a count and a digest); the HDF5 output lists every one in
    ``/entry/sources``, which ``source_index`` counts into (``read_stack(...).sources``). Returns a
    summary dict.

    ``output`` is written atomically (a temporary file renamed into place when complete); an
    existing one is replaced only with ``overwrite=True``, and never when it is one of ``inputs``.
    """
    from radiokit.io import StackWriter
    from radiokit.progress import tqdm

    inputs = [Path(p) for p in ([inputs] if isinstance(inputs, (str, Path)) else inputs)]
    # the calibration's shape is the panel's: a raw size fitting several presets (one 2240 x 2240
    # frame is four 2x2-binned ones) is read at it, where it was refused as ambiguous
    hints = {"panel_shape": cal.shape, **hints}
    segments, headers = _judge_segments(inputs, cal, image_keys, hints, pitch := {})  # pitch: the frames' own
    if not (n_plan := sum(len(picked) for _, picked, _, _ in segments)):
        raise ValueError(f"{', '.join(map(shown, inputs))}: {_nothing_to_correct(headers, image_keys)}")
    sources = _OneOpen(inputs, headers, hints)
    try:
        meta = stack_meta(domain, cal.provenance, inputs, listed_in=_listed_in(output))
        t0 = time.perf_counter()
        sat_total = np_total = over_total = unchecked = 0
        with (
            StackWriter(
                output,
                cal.shape,
                np.float32,
                meta=meta,
                n_frames=n_plan,
                overwrite=overwrite,
                inputs=inputs,
                pixel_mask=cal.mask,  # which pixels every frame had filled: the counts did not say where
                pixel_mask_attrs=_mask_attrs(cal),
                series_attrs={"saturated": _SATURATED_ATTRS},
                sources=[str(p) for p in inputs],
                pixel_sizes=pitch.get("sizes"),
            ) as writer,
            tqdm(total=n_plan, unit="frame", desc="correct", disable=not progress) as bar,
            _BackgroundWriter(writer) as bg,
        ):
            for si, fi, step, factor in _planned(segments):
                frame = bg.buffer()
                nonpos, sat, over = _correct_planned(cal, sources[si], fi, frame, domain, factor)
                over_total += over
                unchecked += sat is None
                sat_total += 0 if sat is None else sat.size
                np_total += nonpos.size
                bg.put(
                    frame,
                    source_index=np.int32(si),
                    frame_index=np.int32(fi),
                    step=np.int16(step),
                    saturated=np.int64(NOT_CHECKED if sat is None else sat.size),
                    nonpositive=np.int64(nonpos.size),
                )
                bar.update(1)
        elapsed = time.perf_counter() - t0
        warn_above_top(cal, over_total, n_plan)
    finally:
        sources.close()
    return {
        "frames": n_plan,
        "output": str(output),
        "domain": domain,
        "seconds": elapsed,
        "frames_per_second": n_plan / elapsed if elapsed else float("inf"),
        **_saturation_summary(cal, sat_total, unchecked, n_plan),
        "nonpositive": np_total,
        "defects_filled_per_frame": CorrectionKernel.of(cal).n_defects,
    }


def _saturation_summary(cal: Calibration, counted: int, unchecked: int, frames: int) -> dict:
    """``saturated``, the pixels counted at or above the calibration's level, or "unknown" with
    ``saturation_from`` saying why where it has none (a negatively scaled panel's): "0 saturated"
    was said of frames never checked, as ``info`` says "unknown" of them. Frames of values above
    every ADC's top (``unchecked`` of ``frames``) are not checked either: the count is of the others."""
    if cal.thresholds.saturation is None:
        why = cal.provenance.get("saturation_not_checked") or "the calibration holds no saturation level"
        return {"saturated": "unknown", "saturation_from": f"not checked: {why}"}
    if unchecked == frames:
        return {"saturated": "unknown", "saturation_from": "not checked: values above 65535, no ADC's top"}
    if unchecked:
        return {
            "saturated": counted,
            "saturation_from": f"not checked in {unchecked} of {frames} frame(s): values above 65535",
        }
    return {"saturated": counted}


#: the HDF5 output's ``saturated`` column says which frames were not checked, as a reader of
#: that file expects to be told: CF's ``missing_value`` (xarray and netCDF readers mask it)
_SATURATED_ATTRS = {
    "description": "pixels at or above the frame's saturation level (the calibration's defects aside); "
    f"{NOT_CHECKED}: not checked, no level for that frame (a negatively scaled panel's calibration; "
    "values above 65535, no ADC's top)",
    "missing_value": np.int64(NOT_CHECKED),
}
