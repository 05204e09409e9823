"""Dark, flat and defect calibration of a flat panel, as the C7942 manual prescribes.

The manual's corrections (Hamamatsu KR1-I50006): offset ``Ic1 = Ir - Id``; gain
``Ic2 = c * Ic1 / (If - Id)`` with ``c = mean(If - Id)``; defect lines replaced by the mean of the
two neighbouring lines and isolated defect pixels by their valid neighbours.
:class:`Calibration` holds the averaged dark and flat and a NeXus ``pixel_mask``: plain data, built
here, kept with :meth:`Calibration.save`; :func:`radiokit.correct.correct_frames` applies it.
"""

from __future__ import annotations

import enum
import json
import os
import time
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from datetime import UTC
from pathlib import Path

import h5py
import numpy as np

from radiokit import _json as strict_json
from radiokit._names import shown
from radiokit._version import __version__
from radiokit.checks import is_number, refuse_masked
from radiokit.errors import FormatError

__all__ = [
    "PixelFlag",
    "Thresholds",
    "Calibration",
    "CalibrationInput",
    "input_lines",
    "robust_average",
    "CalibrationWarning",
    "CalibrationRefused",
    "FrameLevelError",
    "exposure_factors",
    "adc_top",
    "declared_bit_depth",
    "declared_range",
    "declared_signed",
    "declared_levels",
    "declared_scaling",
    "pixel_layout",
    "declared_layout",
    "check_layout",
    "frame_saturation",
    "value_scaling",
    "judge_frames",
    "judge_darks",
]


class CalibrationWarning(UserWarning):
    """The calibration frames are too few or partly unusable; the result may be poor."""


class CalibrationRefused(ValueError):
    """Darks and flats no calibration can be made from. ``culprits`` names the frames to take again
    -- ``("flats",)``, ``("darks",)`` or both -- as the frames themselves show it (:func:`_blame`);
    the message says what to change. Why: the acquisition invalidates and retakes what this names,
    and a refusal that always named the flats had a ``--resume`` retake good flats against bright
    darks, refused again every time."""

    def __init__(self, message: str, culprits=("flats",)):
        super().__init__(message)
        self.culprits = tuple(culprits)


class PixelFlag(enum.IntFlag):
    """Bits of the NeXus ``pixel_mask`` (NXdetector), plus two per-frame bits of radiokit's.

    Bits 0-6 are NeXus's meaning; bits 9 and 10 lie in NeXus's detector-specific range and are
    only ever set in per-frame flags returned by :func:`radiokit.correct.correct_frames`, never in the
    calibration's static mask.
    """

    GAP = 1 << 0
    DEAD = 1 << 1
    UNDER_RESPONDING = 1 << 2
    OVER_RESPONDING = 1 << 3
    NOISY = 1 << 4
    CLUSTER = 1 << 6  #: part of a defect line
    USER = 1 << 8  #: NeXus's "user-defined mask": a recorded pixel_mask's bits beyond NeXus's 0-8
    SATURATED = 1 << 9  #: per frame: raw value at the ADC's top
    NONPOSITIVE = 1 << 10  #: per frame: raw - dark <= 0, value filled


@dataclass
class Thresholds:
    """What counts as a defect. Responses are relative to the local (32-pixel block) median
    response ``flat - dark``, so smooth gain variations never count.

    Attributes
    ----------
    dead_below : float
        Relative response below which a pixel is dead.
    under_below, over_above : float
        Relative response outside ``[under_below, over_above]`` is under-/over-responding.
    noisy_factor : float
        Temporal dark noise above this multiple of the panel's median is noisy (tested from 4 darks on).
    line_deviation : float
        A row or column whose median relative response is off by more than this is a defect line.
    line_noise_factor : float
        A row or column whose median dark noise exceeds this multiple of the panel's is a line.
    line_fraction : float
        A row or column with more than this fraction of flagged pixels is a defect line.
    clip_sigma : float
        Frames deviating from the per-pixel median by more than this many noise sigmas are
        dropped from the average (zingers).
    eps : float
        ``flat - dark`` at or below this many counts is dead whatever its neighbours do.
    saturation : int or None
        ADC value flagged as saturated. None (the default): the top of the ADC the darks and
        flats imply, the smallest of 4095 (12-bit, the C7942), 16383 (14-bit) and 65535 (16-bit)
        that none of their values exceeds; float frames above 65535: none counted.
    smooth_block : int
        Block size (pixels) of the local median response.
    """

    dead_below: float = 0.1
    under_below: float = 0.7
    over_above: float = 1.3
    noisy_factor: float = 5.0
    line_deviation: float = 0.05
    line_noise_factor: float = 1.5
    line_fraction: float = 0.5
    clip_sigma: float = 5.0
    eps: float = 1.0
    saturation: int | None = None
    smooth_block: int = 32

    def __post_init__(self):
        """Each threshold in its domain (ValueError naming it): ``dead_below = 5`` once marked every
        pixel dead and wrote a calibration that ``correct`` could only refuse."""
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None and f.name == "saturation":  # the ADC's top, implied by the darks and flats
                continue
            if not is_number(v) or not np.isfinite(v):
                raise ValueError(f"threshold {f.name}={v!r}: expected a finite number")
        rules = [
            ("dead_below", 0 <= self.dead_below <= self.under_below, "0 <= dead_below <= under_below"),
            ("under_below", self.under_below < 1, "under_below < 1 (relative to the local response)"),
            ("over_above", self.over_above > 1, "over_above > 1 (relative to the local response)"),
            ("line_fraction", 0 < self.line_fraction <= 1, "0 < line_fraction <= 1"),
            (
                "saturation",
                # a non-integer level is a scaled file's top in its values (value_scaling)
                self.saturation is None or not float(self.saturation).is_integer() or 0 < self.saturation < 1 << 16,
                "an ADC value, 1-65535",
            ),
            ("smooth_block", float(self.smooth_block).is_integer() and self.smooth_block >= 2, "a whole block >= 2 px"),
            ("eps", self.eps >= 0, "eps >= 0 counts"),
        ]
        rules += [
            (n, getattr(self, n) > 0, f"{n} > 0")
            for n in ("noisy_factor", "line_deviation", "line_noise_factor", "clip_sigma")
        ]
        for name, ok, rule in rules:
            if not ok:
                raise ValueError(f"threshold {name}={getattr(self, name)!r}: expected {rule}")

    @classmethod
    def from_kwargs(cls, **kwargs) -> Thresholds:
        known = {f.name for f in fields(cls)}
        unknown = set(kwargs) - known
        if unknown:
            raise TypeError(f"unknown thresholds {sorted(unknown)}; known: {sorted(known)}")
        return cls(**kwargs)


#: the largest float32: calibration and correction compute in float32, where a float64 frame's
#: larger values become inf
FLOAT32_MAX = float(np.finfo(np.float32).max)


def beyond_float32(frames) -> float | None:
    """The largest magnitude among float64 ``frames``' finite values when it is past
    :data:`FLOAT32_MAX`, else None. Why: cast, they became inf, with a flood of numpy's
    RuntimeWarnings, and then a flat "saturated (>= None)" or projections filled as non-positive."""
    if frames.dtype.kind != "f" or frames.dtype.itemsize <= 4:
        return None
    top = float(np.max(np.abs(frames), initial=0, where=np.isfinite(frames)))
    return top if top > FLOAT32_MAX else None


def _as_stack(frames, what) -> np.ndarray:
    refuse_masked(frames, what)  # before .data: a masked array's is its values, the mask dropped
    data = getattr(frames, "data", frames)
    data = np.asarray(data)
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3 or data.shape[0] == 0 or min(data.shape[1:]) == 0:
        raise ValueError(f"{what}: expected a stack (n, rows, cols) with n >= 1, got shape {data.shape}")
    if data.dtype.kind not in "uif":
        raise ValueError(f"{what}: expected numeric frames, got dtype {data.dtype}")
    if data.dtype.kind == "f" and not np.isfinite(data).all():
        raise ValueError(f"{what}: frames contain NaN or inf")
    top = beyond_float32(data)
    if top is not None:
        raise ValueError(
            f"{what}: frames hold values up to {top:.3g}, beyond float32's range ({FLOAT32_MAX:.2g}) the "
            "calibration computes in: no detector's counts; rescale them"
        )
    return data


def robust_average(frames, *, clip_sigma=5.0, block_rows=128, return_std=False, callback=None):
    """Average a stack so that a zinger in one frame leaves no trace.

    Each pixel's samples further than ``clip_sigma`` noise sigmas from the pixel's median are
    dropped and the rest averaged. The noise sigma is the panel's: the pooled temporal variance over
    pixels (the noisiest 1 % left out), floored at half a count, so one frame's outlier cannot widen
    its own acceptance window. Where every sample is rejected (two frames, one with a zinger)
    the smallest sample is used: zingers are positive. Works in row blocks to bound memory.

    Parameters
    ----------
    frames : array_like, shape (n, rows, cols)
    clip_sigma : float
    return_std : bool
        Also return each pixel's temporal standard deviation, leaving out its most deviant
        sample when that one is an outlier against the others (a zinger does not count, a noisy
        pixel does); NaN with fewer than 3 frames.
    callback : callable, optional
        Called with the number of rows averaged after each block (a progress bar's ``update``).

    Returns
    -------
    mean : ndarray (rows, cols) float32
    std : ndarray (rows, cols) float32, if ``return_std``
    """
    data = _as_stack(frames, "robust_average")
    n, rows, cols = data.shape
    mean = np.empty((rows, cols), np.float32)
    std = np.full((rows, cols), np.nan, np.float32) if return_std else None
    if n == 1:
        mean[...] = data[0]
        return (mean, std) if return_std else mean
    sigma = _panel_sigma(data)
    for r0 in range(0, rows, block_rows):
        blk = data[:, r0 : r0 + block_rows].astype(np.float32)
        if n <= 32:  # sorting a few samples beats np.median's strided partitions, same value
            srt = np.sort(blk, axis=0)
            med = srt[n // 2] if n % 2 else 0.5 * (srt[n // 2 - 1] + srt[n // 2])
            del srt
        else:
            med = np.median(blk, axis=0)
        keep = np.abs(blk - med) <= clip_sigma * sigma
        count = keep.sum(axis=0)
        total = np.where(keep, blk, 0).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            m = np.where(count > 0, total / np.maximum(count, 1), blk.min(axis=0))
        mean[r0 : r0 + block_rows] = m
        if return_std and n >= 3:
            # Temporal noise for the noisy-pixel test. A zinger must not count, but clipping at
            # the panel's window would hide noisy pixels; so drop each pixel's most deviant
            # sample only if it is an outlier against the pixel's other samples.
            dev = np.abs(blk - med)
            worst = dev.argmax(axis=0)
            others = np.ones(blk.shape, bool)
            np.put_along_axis(others, worst[None], False, axis=0)
            m_o = blk.mean(axis=0, where=others)
            # Squared in units of the panel's noise: in counts, float32 squares overflow past
            # 1.8e19 (float frames in absurd units, 1e20), every std came out inf, its median too,
            # and a noisy pixel went unflagged (s50). Scaling the frames now scales the std alone.
            unit = np.float32(sigma)
            s_o = unit * np.sqrt((((blk - m_o) / unit) ** 2).sum(axis=0, where=others) / max(n - 2, 1))
            x_w = np.take_along_axis(blk, worst[None], axis=0)[0]
            outlier = np.abs(x_w - m_o) > clip_sigma * np.maximum(s_o, sigma / 4)
            s_all = unit * (blk / unit).std(axis=0, ddof=1)
            std[r0 : r0 + block_rows] = np.where(outlier, s_o, s_all)
        if callback is not None:
            callback(blk.shape[1])
    return (mean, std) if return_std else mean


def _panel_sigma(data) -> float:
    """One frame's noise (counts rms) over the panel, for :func:`robust_average`'s window: the
    pooled temporal variance of a sample of rows, trimmed of the top 1 % of pixels (zingers, noisy
    pixels), floored at half a count. A MAD would quantise on integer counts and clip real noise."""
    pick = data[:, :: max(1, data.shape[1] // 64)].astype(np.float32)
    # in float64: float32 squares overflow past 1.8e19 counts (a float file scaled by a wrong
    # factor), and an infinite window took no zinger for an outlier
    var = pick.var(axis=0, ddof=1, dtype=np.float64).ravel()
    var = var[var <= np.quantile(var, 0.99)]
    return max(float(np.sqrt(var.mean())) if var.size else 0.0, 0.5)


def clipped_samples(frames, saturation, *, clip_sigma=5.0, block_rows=128) -> np.ndarray:
    """Per pixel, how many of its samples in ``frames`` read ``saturation`` or more and are kept in
    its :func:`robust_average` (within ``clip_sigma`` panel noise sigmas of its median), as uint16.

    Why: a pixel clipped in some of its frames averages low, below the top, so judging the averaged
    flat alone (``flat >= saturation``) missed it: flats clipped in 57 % of a bright band's samples
    had 111 of its 5120 pixels flagged, and its transmission came out 0.8 % high, unsaid (review
    s42). A zinger's clipped sample is dropped from the average, and not counted here."""
    data = _as_stack(frames, "clipped_samples")
    n, rows, cols = data.shape
    count = np.zeros((rows, cols), np.uint16)
    if saturation is None or n == 0:
        return count
    sigma = _panel_sigma(data) if n > 1 else 0.0
    for r0 in range(0, rows, block_rows):
        blk = data[:, r0 : r0 + block_rows]
        r, c = np.nonzero((blk >= saturation).any(axis=0))  # few: only they are sorted
        if not r.size:
            continue
        samples = blk[:, r, c].astype(np.float32)
        med = np.median(samples, axis=0)
        kept = (samples >= saturation) & (np.abs(samples - med) <= clip_sigma * sigma)
        count[r0 + r, c] = kept.sum(axis=0)
    return count


def _local_median(image: np.ndarray, block: int, valid: np.ndarray | None = None) -> np.ndarray:
    """Median over ``block``-sized tiles, interpolated back to full size: a smooth model that
    isolated defects and single lines cannot pull.

    ``valid``: the pixels the medians are taken over (all by default). A tile with fewer than an
    eighth of its pixels valid takes the median of the nearest tile that has enough. Why: a band
    of dead pixels filling half a tile (a tiled detector's gap between modules) dragged the
    tile's median to half the response, and the good rows beside it were flagged as twice it."""
    rows, cols = image.shape
    block = max(1, min(block, rows, cols))
    nr, nc = -(-rows // block), -(-cols // block)
    pad = ((0, nr * block - rows), (0, nc * block - cols))

    def tiled(a):
        return np.pad(a, pad, mode="edge").reshape(nr, block, nc, block).transpose(0, 2, 1, 3).reshape(nr, nc, -1)

    tiles = tiled(image)
    if valid is None or valid.all():
        med = np.median(tiles, axis=2).astype(np.float32)
    else:
        ok = tiled(valid)
        count = ok.sum(axis=2)
        med = np.median(tiles, axis=2).astype(np.float32)
        part = count < ok.shape[2]  # sorted only where needed: a full sort of every tile took 1 s at 2240
        # invalid pixels sorted past the valid ones: the median of the first ``count`` of each tile
        srt = np.sort(np.where(ok[part], tiles[part].astype(np.float32), np.inf), axis=1)
        n = count[part]
        lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
        hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[:, None], axis=1)[:, 0]
        med[part] = (0.5 * (lo.astype(np.float64) + hi)).astype(np.float32)
        enough = count >= max(1, block * block // 8)
        if not enough.any():  # nothing to go on: the plain median, as before
            med = np.median(tiles, axis=2).astype(np.float32)
        elif not enough.all():
            from scipy.ndimage import distance_transform_edt

            idx = distance_transform_edt(~enough, return_distances=False, return_indices=True)
            med = med[idx[0], idx[1]]
    if nr == 1 and nc == 1:
        return np.full((rows, cols), med[0, 0], np.float32)
    # One ghost tile around the grid, on the outer tiles' trend (_edge_trend): between the outer
    # tile's centre and the frame's edge the model goes on with a smooth gradient, where INTER_LINEAR
    # alone holds it flat for half a block. Tile centres sit at block/2; INTER_LINEAR maps centres
    # to centres, so the frame starts one block into the padded grid.
    med = _edge_trend(_edge_trend(med, 0), 1)
    import cv2  # late: only this smoothing needs it; a command that judges no frames never imports it

    up = cv2.resize(med, ((nc + 2) * block, (nr + 2) * block), interpolation=cv2.INTER_LINEAR)
    return up[block : block + rows, block : block + cols]


def _edge_trend(med: np.ndarray, axis: int) -> np.ndarray:
    """``med`` (tile medians) with one ghost tile before and after along ``axis``, each the outer
    tile's median less the step to its neighbour, limited as a slope limiter limits it (minmod):
    the smaller of the outer two steps when they go the same way, else none (the outer tile's own
    median, as before). Why: a steep heel (flat - dark falling 55 % over 64 px) left the outer
    half-block's reference flat while the flat went on falling, so the edge lines read 0.77-1 of
    it, the edge line was a defect line and lines 4-12 from it too; a step between the outer tiles
    (a read-out block's) is no trend, and the limiter leaves it alone. Fewer than 3 tiles: no
    trend can be told from a step."""
    m = np.moveaxis(med, axis, 0)
    if m.shape[0] < 3:
        lo, hi = m[:1], m[-1:]
    else:
        lo = m[:1] - _minmod(m[1:2] - m[:1], m[2:3] - m[1:2])
        hi = m[-1:] + _minmod(m[-1:] - m[-2:-1], m[-2:-1] - m[-3:-2])
    return np.moveaxis(np.concatenate([lo, m, hi]), 0, axis).astype(np.float32)


def _minmod(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smaller of ``a`` and ``b`` in magnitude where they share a sign, else 0."""
    return np.where(a * b > 0, np.sign(a) * np.minimum(np.abs(a), np.abs(b)), 0)


#: The fewest pixels a row or column must have to be judged as a line: a line's median response
#: and noise over a few pixels are those pixels' own (each 1-pixel column of a 1 x 300 frame was
#: judged a line by its own noise, and the calibration refused), and its pixels are judged anyway.
MIN_LINE_PIXELS = 16


#: How many lines on each side a line is compared with (:func:`_line_flags`): the median of the
#: LINE_REACH lines on one side is that side's reference, so up to 3 adjacent defect lines (2 of 5
#: on a side) are found whole; a wider band is a block of its own, as a read-out block is.
LINE_REACH = 5

#: The widest band of adjacent lines off both sides that is a band of defect lines: the most whose
#: edge line's reference on the band's side is still the lines beyond it (LINE_REACH // 2 + 1).
MAX_LINE_BAND = LINE_REACH // 2 + 1

#: The most defect lines a panel has: "up to 20 per panel" (C7942.md, "Corrections the manual
#: prescribes"); a line stays a line when binned, so this holds at every binning.
MAX_DEFECT_LINES = 20


def _nanmedian(a, axis):
    """np.nanmedian without its "All-NaN slice" warning: a line or window of saturated pixels only
    has no median, and is judged by nothing but its dark noise."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)


def _whole_bands(off, med, left, right, limit, more=None):
    """``off(values, references)`` (a line's median off a reference, one direction) turned into the
    lines of bands up to ``limit`` wide: each run of lines off both sides grown by the adjacent lines
    off both the reference beyond them and the one beyond the band's other end; a wider band is
    dropped whole."""
    core = off(med, left) & off(med, right)
    if more is not None:
        core |= more
    out = np.zeros(med.size, bool)
    j = 0
    while j < med.size:
        if not core[j]:
            j += 1
            continue
        a = b = j
        while b + 1 < med.size and core[b + 1]:
            b += 1
        j = b + 1
        while a > 0 and off(med[a - 1], left[a - 1]) and off(med[a - 1], right[b]):
            a -= 1
        while b + 1 < med.size and off(med[b + 1], right[b + 1]) and off(med[b + 1], left[a]):
            b += 1
        if b - a + 1 <= limit:
            out[a : b + 1] = True
    return out


def _off_fitted_step(off, med, padded, k, candidates):
    """Of the ``candidates`` (lines off one side only), those ``off`` the level of their side of a
    step fitted to the line and the ``k`` lines on each side (``padded``: ``med`` padded by ``k``).
    Why: a defect line at 0.9 one line right of a 1.15 gain step reads 1.035 of the lines left of
    the step, off the right side only, as the step's own lines are, and was missed (review s42rr).
    The step is the split of the 2k + 1 lines into two runs with the least absolute deviation from
    their medians: the line itself counted, so that a defect line beside the step is not taken for
    the step's edge and a healthy line of the step called a defect. Limit: a defect line right at
    the step reading between the two sides fits as the step's edge, and is not found."""
    out = np.zeros(med.size, bool)
    for j in np.flatnonzero(candidates):
        v = padded[j : j + 2 * k + 1]
        if np.isnan(v).any():
            continue
        best, split = np.inf, 0
        for s in range(1, 2 * k + 1):
            a, b = v[:s], v[s:]
            cost = np.abs(a - np.median(a)).sum() + np.abs(b - np.median(b)).sum()
            if cost < best:
                best, split = cost, s
        side = v[split:] if split <= k else v[:split]
        out[j] = off(med[j], np.median(side))
    return out


def _edge_padded(med, k):
    """``med`` (lines' median responses) padded by ``k`` lines at each end: the trend of the ``2k``
    lines inside each edge line carried on past it (the medians of two runs of ``k``, the edge line
    left out), so that an edge line is judged against the lines inside it and where they lead.
    Why: mirrored, an edge line on a steep smooth gradient (an anode heel, falling 40 % over 96 px
    of a curved flat) stood below or above all of its mirrored neighbours alike and was a defect
    line. Frames of fewer than ``2k + 1`` lines are mirrored (at one line, repeated)."""
    n = med.size
    if n < 2 * k + 1:
        return np.pad(med, k, mode="reflect" if n > 1 else "edge")
    steps = np.arange(k, 0, -1, dtype=np.float64)  # how far each padded line lies past the edge line
    ends = []
    for inner in (med[1 : 2 * k + 1], med[-2 : -2 * k - 2 : -1]):  # from the edge inwards
        near, far = _nanmedian(inner[:k], 0), _nanmedian(inner[k:], 0)
        slope = (far - near) / k  # per line, inwards; the near run's centre (k + 1) / 2 lines in
        ends.append(near - slope * (steps + (k + 1) / 2))
    return np.concatenate([ends[0], med, ends[1][::-1]]).astype(med.dtype)


def _line_flags(rel, std, flagged, th: Thresholds, axis, skip=None):
    """Indices of defect lines along ``axis`` (0: rows, 1: columns) and their flag bits; none
    when a line has fewer than :data:`MIN_LINE_PIXELS` pixels. ``skip``: pixels left out of the
    judgement (the flats' saturated ones).

    A line's median relative response is judged against the median of the :data:`LINE_REACH`
    lines on each side of it, and must differ from both. Why: a gain step between a flat panel's
    read-out blocks (flat - dark 1.12-1.2 times higher right of a column) drags the block median
    ``rel`` is relative to, and 8-29 healthy columns beside the step read 5 % off 1: flagged as
    defect lines and filled in every frame (a 1-px wire of transmission 0.3 there came out 0.6).
    A defect line differs from its neighbours on both sides; a step's line agrees with one side
    (a centred running median does not do: a defect line beside the step is the median there).

    Adjacent lines are judged as one band, flagged whole or not at all: up to
    :data:`MAX_LINE_BAND` (3) lines off both the lines beyond each end are defect lines; a wider
    band at its own response is a gain band, as a read-out block is, and is not flagged for its
    response. Why: 4 lines at 0.88 gave only the middle two, 5 only the middle one (review s42rr),
    their edges then filled from lines inside the band. Physics and the manual: the gain correction
    ``c * Ic1 / (If - Id)`` is per pixel, so a band responding linearly at a lower gain comes out
    right once flat-fielded, while the manual's fill (the mean of the two neighbouring lines) is
    made for single lines and erases 4-5 lines' worth of the image (a 1-px wire across the band).
    What the flat field cannot correct is flagged whole at any width: lines reading nothing (dead,
    judged absolutely: a wide band reading nothing is its own neighbours), with a dark noise over
    ``line_noise_factor`` times the panel's, or with most of their pixels flagged.

    A line off one side only is a step's line or a defect line beside a step (at 0.9, the second
    column of a 1.15 step reads 1.035 of the low side): it is judged against its side of a step
    fitted to it and its neighbours (:func:`_off_fitted_step`). Limit: a defect line right at the
    step, reading between the two sides, is the step's edge to the fit and is not found."""
    other = 1 - axis
    if rel.shape[other] < MIN_LINE_PIXELS:
        return np.zeros(0, np.intp), np.zeros(0, np.uint32)
    if skip is not None and skip.any():
        rel = np.where(skip, np.float32(np.nan), rel)
        med = _nanmedian(rel, other)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            frac = np.nanmean(np.where(skip, np.nan, flagged.astype(np.float32)), axis=other)
    else:
        med = np.median(rel, axis=other)
        frac = flagged.mean(axis=other)
    n, k = med.size, LINE_REACH
    padded = _edge_padded(med, k)
    windows = np.lib.stride_tricks.sliding_window_view(padded, k)
    left, right = _nanmedian(windows[:n], 1), _nanmedian(windows[k + 1 : k + 1 + n], 1)
    bits = np.zeros(n, np.uint32)
    low, high = 1 - th.line_deviation, 1 + th.line_deviation
    for off, bit in (
        (lambda v, r: v < low * r, PixelFlag.UNDER_RESPONDING),
        (lambda v, r: v > high * r, PixelFlag.OVER_RESPONDING),
    ):
        one_sided = off(med, left) != off(med, right)
        beside_step = _off_fitted_step(off, med, padded, k, one_sided)
        bits[_whole_bands(off, med, left, right, MAX_LINE_BAND, beside_step)] |= np.uint32(bit)
    bits[med < th.dead_below] |= np.uint32(PixelFlag.DEAD)
    if std is not None:
        line_std = np.nanmedian(std, axis=other)
        bits[line_std > th.line_noise_factor * np.nanmedian(std)] |= np.uint32(PixelFlag.NOISY)
    bits[frac > th.line_fraction] |= np.uint32(PixelFlag.CLUSTER)
    lines = np.flatnonzero(bits)
    return lines, bits[lines] | np.uint32(PixelFlag.CLUSTER)


def _too_many_lines(rows_idx, cols_idx) -> str | None:
    """What to say of more defect lines than :data:`MAX_DEFECT_LINES` (None: no more). Why: each
    is filled in every frame, erasing what lies there, and more than a panel has means the flats
    or the thresholds found lines that are none (a gain step found 8-29 once, unsaid)."""
    n = rows_idx.size + cols_idx.size
    if n <= MAX_DEFECT_LINES:
        return None
    found = " and ".join(
        f"{idx.size} {name} ({_runs(idx)})" for name, idx in (("rows", rows_idx), ("columns", cols_idx)) if idx.size
    )
    return (
        f"{n} defect lines found ({found}), more than the {MAX_DEFECT_LINES} the C7942's manual gives a panel "
        "at most; each is filled in every frame, erasing what lies there: check the flats (a non-uniform "
        "beam, a gain step between read-out blocks, module gaps) and the line thresholds"
    )


def _what_instead(h5) -> str:
    """An experiment file given where a calibration belongs (``--cal exp.h5``) holds what one is
    made from: say how, rather than only what it is not."""
    from radiokit.io._experiment import IMAGE_KEY

    if h5.get(IMAGE_KEY, getlink=True) is None:
        return ""
    return (
        " (an experiment file: make one from its darks and flats with radiokit calibrate --experiment FILE "
        "-o cal.h5, or correct the file itself without --cal)"
    )


@dataclass
class Calibration:
    """Averaged dark and flat of one panel set-up, with its defect map.

    Build one with :meth:`from_frames` (or :meth:`from_experiment`), apply it with
    :func:`radiokit.correct.correct_frames`, keep it with :meth:`save` / :meth:`load`.

    Attributes
    ----------
    dark, flat : ndarray (rows, cols) float32
        Robust averages of the dark and flat frames (counts).
    mask : ndarray (rows, cols) uint32
        NeXus ``pixel_mask`` bits (:class:`PixelFlag`); non-zero pixels are filled on correction.
    defect_rows, defect_columns : ndarray of int
        Whole defect lines, filled from the neighbouring valid lines.
    c : float
        ``mean(flat - dark)`` over valid pixels: the manual's grey-level scale.
    thresholds : Thresholds
    provenance : dict
        Frame counts, times, software version, averaging method; ``saturation_not_checked``, why
        the darks' and flats' saturation level is not known (a negative scale: ``thresholds.
        saturation`` stays None, not the ADC top the scaled averages would imply).

    Examples
    --------
    >>> import numpy as np
    >>> from radiokit.calibrate import Calibration
    >>> from radiokit.correct import correct_frames
    >>> rng = np.random.default_rng(0)
    >>> darks = rng.normal(100, 2, (5, 64, 64)).astype(np.uint16)
    >>> flats = rng.normal(3000, 20, (5, 64, 64)).astype(np.uint16)
    >>> cal = Calibration.from_frames(darks, flats)
    >>> raw = np.full((64, 64), 100 + 2900 // 2, np.uint16)  # half the flat's signal
    >>> line_integral = correct_frames(cal, raw, domain="log")
    >>> bool(abs(float(np.median(line_integral)) - np.log(2)) < 0.02)
    True
    """

    dark: np.ndarray
    flat: np.ndarray
    mask: np.ndarray
    defect_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    defect_columns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    c: float = float("nan")
    thresholds: Thresholds = field(default_factory=Thresholds)
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        # the ADC is judged on the arrays as given: converted to float32 first, 8-bit frames lost
        # their type, and their saturation was guessed 4095 (a flat clipped at 255 passed unflagged)
        given = (np.asarray(self.dark), np.asarray(self.flat))
        self.dark = np.ascontiguousarray(self.dark, np.float32)
        self.flat = np.ascontiguousarray(self.flat, np.float32)
        self.mask = np.ascontiguousarray(self.mask, np.uint32)
        if not (self.dark.shape == self.flat.shape == self.mask.shape) or self.dark.ndim != 2:
            raise ValueError(
                f"dark {self.dark.shape}, flat {self.flat.shape} and mask {self.mask.shape} "
                "must be the same (rows, cols) shape"
            )
        # built from plain data: the ADC its averages imply (not where the level is known to be unknown)
        if self.thresholds.saturation is None and not self.provenance.get("saturation_not_checked"):
            self.thresholds = replace(self.thresholds, saturation=adc_top(*given))
        # A pixel without response cannot be corrected, whoever built the mask: always fill it.
        unusable = ~((self.flat - self.dark) > self.thresholds.eps)
        if unusable.any():
            self.mask = self.mask.copy()
            self.mask[unusable] |= np.uint32(PixelFlag.DEAD)
        self.defect_rows = np.asarray(self.defect_rows, np.int64)
        self.defect_columns = np.asarray(self.defect_columns, np.int64)
        if not np.isfinite(self.c):
            good = self.mask == 0
            self.c = float(np.mean((self.flat - self.dark)[good])) if good.any() else 1.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.dark.shape

    # -- building -----------------------------------------------------------------------------
    @classmethod
    def from_frames(
        cls,
        darks,
        flats,
        *,
        dark_times=None,
        flat_times=None,
        progress=False,
        bit_depth=None,
        layout=None,
        scaling=None,
        signed=None,
        **thresholds,
    ) -> Calibration:
        """Average darks and flats robustly and map the panel's defects.

        Parameters
        ----------
        darks, flats : array_like (n, rows, cols) or :class:`radiokit.io.Frames`
            Frames with the beam off and with the open beam (no object), raw counts.
        dark_times, flat_times : sequence of float, optional
            Acquisition times (s since the epoch), kept in the provenance.
        progress : bool
            A progress bar on stderr over the rows averaged and mapped (a 2240 x 2240 panel's
            averages take seconds per ten frames of each).
        bit_depth : int, optional
            The ADC bits the frames' files declare (:func:`declared_bit_depth`); by default
            those :class:`radiokit.io.Frames` give say (``meta["bit_depth"]``). Without
            ``saturation``, :func:`saturation_level` decides (``2**bit_depth - 1`` unless the
            frames pass it, else the frames' own values).
        signed : bool, optional
            Whether those ADC counts are signed (:func:`declared_signed`, :func:`declared_range`:
            a signed 12-bit ADC's top is 2047); by default what :class:`radiokit.io.Frames` say
            (``meta["bit_depth_signed"]``, a DICOM's PixelRepresentation), unsigned for arrays.
        layout : dict, optional
            Where the frames' pixels lie on the sensor as their files were read
            (:func:`pixel_layout`, :func:`declared_layout`); by default what :class:`radiokit.io.Frames`
            say, nothing for plain arrays. Kept in the provenance (``orientation``,
            ``sensor_offset``): frames read otherwise are refused on correction (:func:`check_layout`).
        scaling : dict, optional
            How the frames' stored counts became their values (:func:`value_scaling`); by default
            what :class:`radiokit.io.Frames` say. The saturation level is then the stored top's
            value (:func:`saturation_level`).
        **thresholds
            Any field of :class:`Thresholds`.

        Returns
        -------
        Calibration

        Notes
        -----
        With ``R = flat - dark`` and ``S`` its local median (``smooth_block`` tiles, bilinear), the
        relative response ``R / S`` classifies pixels: dead below ``dead_below`` (or ``R <= eps``),
        under-responding below ``under_below``, over-responding above ``over_above``; a pixel
        whose temporal dark noise exceeds ``noisy_factor`` times the panel median is noisy; a
        pixel whose flat is saturated (on average, or in :func:`clipped_floor` of the flats whose
        samples its average kept, :func:`clipped_samples`) is over-responding. Rows and columns are
        defect lines when their median relative response deviates by more than ``line_deviation``
        from the lines on both sides (:data:`LINE_REACH` each), their median
        dark noise exceeds ``line_noise_factor`` times the panel's, or more than
        ``line_fraction`` of their pixels are flagged.
        """
        if bit_depth is None:  # the frames' own word for their ADC, where they give one
            bit_depth = declared_bit_depth(_frames_say(darks, flats, lambda meta: meta.get("bit_depth")))
        if signed is None:
            signed = declared_signed(_frames_say(darks, flats, lambda meta: meta.get("bit_depth_signed")))
        low, top = (0, None) if bit_depth is None else declared_range(bit_depth, signed)  # the file's word
        if layout is None:  # as the frames' files were read, where the frames say
            layout = declared_layout(_frames_say(darks, flats, pixel_layout))
        if scaling is None:
            scaling = _frames_scaling(darks, flats)
        th = Thresholds.from_kwargs(**thresholds)
        # the Frames' files, recorded in the provenance: refused now where it could not be saved
        given = {"darks": darks, "flats": flats}
        inputs = _frames_inputs(given, {k: len(v) if hasattr(v, "meta") else 0 for k, v in given.items()})
        refuse_unnameable(_named_frames(darks, flats), {"inputs": inputs}, len({i["path"] for i in inputs}))
        darks, flats = _check_stacks(darks, flats)
        _check_levels(darks, flats, th.eps)
        given = th.saturation is not None
        if not given:
            level = saturation_level(darks, flats, bit_depth=bit_depth, scaling=scaling or None, signed=signed)
            th = replace(th, saturation=level)
            if scaling and th.saturation is None:  # said, never a silent "none saturated"
                warnings.warn(
                    f"saturation not checked: the darks' and flats' values are scaled ({scaling['text']}) "
                    "and their stored top cannot be told from them; pass saturation= in their values",
                    CalibrationWarning,
                    stacklevel=2,
                )
            # the file's word, not a guess (a depth the frames pass is no ADC of theirs: guessed)
            given = top is not None and th.saturation == top
        rows = darks.shape[1]
        with _bar(progress, 3 * rows, "calibrate darks", "row") as bar:
            dark, dark_std = robust_average(darks, clip_sigma=th.clip_sigma, return_std=True, callback=bar.update)
            bar.set_description("calibrate flats")
            flat = robust_average(flats, clip_sigma=th.clip_sigma, callback=bar.update)
            bar.set_description("calibrate defects")
            clipped = clipped_samples(flats, th.saturation, clip_sigma=th.clip_sigma)
            cal = cls._from_averages(
                darks, flats, dark, dark_std, flat, th, dark_times, flat_times, given, clipped, scaling, low
            )
            bar.update(rows)
        cal.provenance.update(layout or {})
        # the files' word for their ADC (a raw preset's: the panel named), kept so that a frame
        # passing its top is reported (radiokit.correct.declared_top): C7942.md, a value above 4095
        # is a wrong bit or byte order or another panel
        if top is not None and th.saturation == top:
            cal.provenance["bit_depth"] = int(bit_depth)
            if signed:  # (its top 2**(bits - 1) - 1: radiokit.correct.declared_top)
                cal.provenance["bit_depth_signed"] = True
        cal.provenance["inputs"] = inputs
        return cal

    @classmethod
    def _from_averages(
        cls, darks, flats, dark, dark_std, flat, th, dark_times, flat_times, given, clipped=None, scaled=False, low=0
    ) -> Calibration:
        """The defect map and the calibration of the averaged dark and flat (:meth:`from_frames`;
        ``given``: ``th.saturation`` was the caller's, not guessed from the frames; ``clipped``:
        each pixel's clipped flat samples kept in its average, :func:`clipped_samples`; ``scaled``:
        the frames' scaling (:func:`value_scaling`), if any: scaled values, whose range does not
        start at 0 as the half-range rule of :func:`_bright_darks` assumes, so it is not applied: a
        GDAL OFFSET of 100 called 1-count darks bright; their saturation, where ``th.saturation``
        is None, is said unjudged in the provenance); ``low``: the ADC's lowest count, where the range
        starts for that rule (a signed ADC's -2**(bits - 1), :func:`declared_range`; else 0)."""
        low = low if th.saturation == -low - 1 else 0  # a signed ADC's bottom where its top is the level
        top = None if scaled else _known_top(th.saturation, given, dark, flat)
        if darks.shape[0] < 4:
            # No noisy-pixel test: with 3 darks the std left after the most deviant sample is
            # dropped is a 1-degree-of-freedom estimate whose tail passes noisy_factor (5x) its
            # median in 1 pixel of 1400 on a clean panel (578 of 1M flagged, then filled in
            # every frame); from 4 darks on, none.
            dark_std = None
        response = flat - dark
        try:
            if float(np.median(response)) <= th.eps:
                raise ValueError(
                    f"flats are not brighter than darks (median flat - dark = {np.median(response):.3g} "
                    "counts): was the beam on for the flats?"
                )
            mask, rows_idx, cols_idx, n_flat_saturated, (sat_rows, sat_cols) = _defect_map(
                flat, dark_std, response, th, clipped, n_flats=flats.shape[0]
            )
            _check_defect_share(mask, n_flat_saturated, th.saturation, response, th.dead_below)
        except ValueError as exc:
            raise _blame(str(exc), dark, flat, _dark_noise(darks), th, top, low) from None
        bright = _bright_darks(float(np.median(dark)), top, low)
        if bright:
            warnings.warn(bright, CalibrationWarning, stacklevel=3)
        # after the refusals: a refused map needs no more words; the saturation's lines are said
        # with the saturation, and are none of the manual's 20
        many = _too_many_lines(np.setdiff1d(rows_idx, sat_rows), np.setdiff1d(cols_idx, sat_cols))
        if many:
            warnings.warn(many, CalibrationWarning, stacklevel=3)
        good = mask == 0
        provenance = _provenance(darks, flats, dark_times, flat_times, mask, n_flat_saturated)
        # filled as lines, but the flats' saturation's: kept apart so that every summary says so
        provenance["saturated_lines"] = {"rows": sat_rows.tolist(), "columns": sat_cols.tolist()}
        if scaled and th.saturation is None:  # (from_frames warned) kept, so that correct says "not checked"
            provenance["saturation_not_checked"] = f"values scaled ({scaled['text']})"
            provenance["n_flat_saturated"] = None  # not counted: no 0 beside it
        return cls(
            dark,
            flat,
            mask,
            rows_idx,
            cols_idx,
            c=float(np.mean(response[good])) if good.any() else float(np.mean(response)),
            thresholds=th,
            provenance=provenance,
        )

    @classmethod
    def from_experiment(
        cls, path, *, allow_external=False, progress=False, narrow_frames=False, **thresholds
    ) -> Calibration:
        """Calibrate from the darks (image_key 2) and flats (image_key 1) of an experiment file
        (``allow_external``: its frames may lie in other files, see :func:`radiokit.io.read`;
        ``progress``: bars on stderr over the frames read and the rows averaged;
        ``narrow_frames``: a stack of frames far narrower than they are many read as stored, see
        :func:`radiokit.io.read`)."""
        from radiokit.io import ImageKey, open_frames

        with open_frames(path, allow_external=allow_external, narrow_frames=narrow_frames) as src:
            if src.meta.get("format") == "calibration":  # its averages read as one dark and one flat
                raise FormatError(
                    path, "is a radiokit calibration, not an experiment file: use it as it is (radiokit correct --cal)"
                )
            if not len(src):  # as `radiokit info` says it, not "holds no darks"
                raise FormatError(path, "no frames")
            keys = np.asarray(src.meta.get("image_key", []))
            times = np.asarray(src.meta.get("time", np.full(len(keys), np.nan)))
            sel = {k: np.flatnonzero(keys == k) for k in (ImageKey.DARK, ImageKey.FLAT)}
            for k, what in ((ImageKey.DARK, "darks (image_key 2)"), (ImageKey.FLAT, "flats (image_key 1)")):
                if sel[k].size == 0:
                    raise FormatError(path, f"holds no {what}: cannot calibrate")
            from radiokit.io import check_budget

            n_cal = sel[ImageKey.DARK].size + sel[ImageKey.FLAT].size
            check_budget(path, n_cal * src.frame_bytes, f"{n_cal} dark and flat frames of {src.frame_shape}")
            bit_depth = src.meta.get("bit_depth")  # the panel's, as recorded (saturation_level)
            scaling = value_scaling(src.meta) or {}  # ({}: none, not to be asked of plain arrays)
            with _bar(progress, n_cal, f"read {Path(path).name}", "frame") as bar:
                darks, flats = (_read_counted(src, sel[k], bar) for k in (ImageKey.DARK, ImageKey.FLAT))
        try:
            cal = cls.from_frames(
                darks,
                flats,
                dark_times=times[sel[ImageKey.DARK]],
                flat_times=times[sel[ImageKey.FLAT]],
                progress=progress,
                bit_depth=bit_depth,
                scaling=scaling,
                **thresholds,
            )
        except FrameLevelError as exc:  # named by its frame in the file
            frame = sel[ImageKey.DARK if exc.kind == "dark" else ImageKey.FLAT][exc.index]
            raise FormatError(path, f"frame {frame} ({exc})") from exc
        except ValueError as exc:  # its darks and flats are this file's: name it
            raise FormatError(path, str(exc)) from exc
        _merge_recorded_mask(cal, path, src.meta.get("pixel_mask"))
        cal.provenance.update(pixel_layout(src.meta))
        cal.provenance["source"] = str(path)
        read_from = CalibrationInput.of(path, src.meta)
        read_from.darks, read_from.flats = int(sel[ImageKey.DARK].size), int(sel[ImageKey.FLAT].size)
        cal.provenance["inputs"] = [read_from.record()]
        check_currents(path, src.meta, sel[ImageKey.FLAT])
        for name, unit in (("current", "ua"), ("voltage", "kv")):  # what the flats saw, where recorded
            values = np.asarray(src.meta.get(name, np.full(len(keys), np.nan)), float)[sel[ImageKey.FLAT]]
            if np.isfinite(values).any():
                cal.provenance[f"flat_{name}_{unit}"] = float(np.nanmean(values))
        return cal

    # -- persistence --------------------------------------------------------------------------
    def save(self, path, group="calibration", *, overwrite=False, name=None) -> Path:
        """Write to a new HDF5 file ``path`` (the calibration in ``group``), or into a binary file
        object (``io.BytesIO``: ``radiokit calibrate`` then writes the bytes, of a known size,
        atomically).

        The file is built beside ``path`` and renamed into place when complete
        (:func:`radiokit.io.atomic_h5`): an interrupted save leaves the previous file or none.
        An existing ``path`` is replaced, whole, only with ``overwrite=True``; never written
        into. Why: a second save replaced the first calibration silently, and ``cal.save("exp.h5")``
        added a group inside a raw experiment file. ``name``: the file a file object's bytes are
        for, as a refusal names it (``radiokit calibrate``'s output; else "the calibration").

        Raises
        ------
        radiokit.io.OutputError
            ``path`` exists (without ``overwrite``; a ``FileExistsError`` too), is a folder, is
            read-only or cannot be written, named in the message.
        """
        from radiokit._names import shown

        # what Calibration.load refuses is never written: nested past its depth (s51), or longer
        # than it reads (s53: the provenance of 30 000 files); judged before the file is made
        where = shown(path) if isinstance(path, (str, os.PathLike)) else shown(name) if name else "the calibration"
        texts = {
            "thresholds": strict_json.dumps_readable(asdict(self.thresholds), where, "the calibration's thresholds"),
            "provenance": strict_json.dumps_readable(self.provenance, where, "the calibration's provenance"),
        }
        if not isinstance(path, (str, os.PathLike)):  # a file object: the caller places the bytes
            with h5py.File(path, "w") as h5:
                self._write(h5.create_group(group), texts)
            return path
        from radiokit.io import atomic_h5

        path = Path(path)
        with atomic_h5(path, overwrite=overwrite) as h5:
            self._write(h5.create_group(group), texts)
        return path

    def _write(self, g, texts: dict) -> None:
        """The calibration's datasets and attributes into the new HDF5 group ``g``; ``texts``:
        its thresholds' and provenance's JSON."""
        g.attrs["NX_class"] = "NXcollection"
        for name in ("dark", "flat"):
            g.create_dataset(name, data=getattr(self, name), compression="gzip", shuffle=True).attrs["units"] = "counts"
        g.create_dataset("pixel_mask", data=self.mask, compression="gzip")
        g["defect_rows"] = self.defect_rows
        g["defect_columns"] = self.defect_columns
        g.attrs["c"] = self.c
        # strict JSON (radiokit._json): a NaN current or noise is null, named in "not_finite"
        g.attrs["thresholds"] = texts["thresholds"]
        g.attrs["provenance"] = texts["provenance"]
        g.attrs["software"] = f"radiokit {__version__}"

    @classmethod
    def load(cls, path, group="calibration") -> Calibration:
        """Read a calibration written by :meth:`save`.

        Raises
        ------
        FormatError
            The file is not a calibration, is corrupt, or holds values out of its contract.
        """
        from radiokit.io._budget import check_budget
        from radiokit.io._experiment import checked_dataset
        from radiokit.io._layout import open_layout

        with open_layout(path, "a radiokit calibration file") as h5:
            if group not in h5:
                raise FormatError(path, f"no /{group} group: not a radiokit calibration file{_what_instead(h5)}")
            g = h5[group]
            missing = [n for n in ("dark", "flat", "pixel_mask") if n not in g]
            if missing:
                raise FormatError(path, f"/{group} lacks {', '.join(missing)}")
            # local plain numbers within the memory budget; the defect lists too (read unchecked, a
            # 127 KB file's 400 million zstd zeros took 3 GB)
            lists = [(n, (1,)) for n in ("defect_rows", "defect_columns") if n in g]
            for name, ndims in (("dark", (2,)), ("flat", (2,)), ("pixel_mask", (2,)), *lists):
                ds = checked_dataset(path, h5, f"{group}/{name}", "iuf", ndims)
                check_budget(path, ds.size * ds.dtype.itemsize, f"/{group}/{name} {ds.shape}")
            try:
                thresholds = Thresholds.from_kwargs(**_json_attr(path, g, "thresholds"))
            except (TypeError, ValueError) as exc:
                raise FormatError(path, f"/{group}@thresholds: {exc}") from None
            provenance = _json_attr(path, g, "provenance")
            _check_numbers(path, g, provenance)
            return cls(
                g["dark"][()],
                g["flat"][()],
                g["pixel_mask"][()],
                g["defect_rows"][()] if "defect_rows" in g else (),
                g["defect_columns"][()] if "defect_columns" in g else (),
                c=float(g.attrs.get("c", np.nan)),
                thresholds=thresholds,
                provenance=provenance,
            )

    def __repr__(self) -> str:
        d = self.provenance.get("defects", {})
        return (
            f"Calibration(shape={self.shape}, c={self.c:.1f}, defect pixels={int(np.count_nonzero(self.mask))}, "
            f"rows={self.defect_rows.tolist()}, columns={self.defect_columns.tolist()}, {d})"
        )


#: The provenance entries :func:`exposure_factors` computes with: a number, NaN or null each.
_PROVENANCE_NUMBERS = {"flat_current_ua": "uA", "flat_voltage_kv": "kV"}


def _check_numbers(path, group, provenance: dict) -> None:
    """Refuse, naming the file and the field, a number of the calibration that is not one: the
    gain ``c`` (``true`` read as 1 and scaled ``--domain counts`` by 1/3000) and the flats' tube
    current and voltage (``"flat_current_ua": true`` scaled every transmission by 1/200 in
    silence; ``"200"``, a string, was a TypeError traceback)."""
    c = group.attrs.get("c", np.nan)
    if not is_number(c) or float(c) <= 0 or np.isinf(c):  # NaN: not recorded, computed again
        value = c.item() if isinstance(c, np.generic) else c
        raise FormatError(path, f"{group.name}@c is {value!r}: expected a positive finite number of counts")
    for key, unit in _PROVENANCE_NUMBERS.items():
        value = provenance.get(key)
        if value is not None and not is_number(value):
            raise FormatError(
                path, f"{group.name}@provenance: {key} is {json.dumps(value)}: expected a number ({unit}) or null"
            )
    value = provenance.get("flat_current_ua")
    if value is not None and not np.isnan(value) and not _TUBE_UA[0] <= value <= _TUBE_UA[1]:
        raise FormatError(path, f"{group.name}@provenance: flat_current_ua is {value!r} uA: {_NO_TUBE}")
    # how the darks and flats were read (pixel_layout), compared with every frame file's: a value no
    # reader gives would be compared as another layout, or fail in the message (a dict, unhashable)
    for key, ok, expected in (
        ("orientation", lambda v: type(v) is int and v in _ORIENTATION_NAMES, "a TIFF Orientation, 1 to 8"),
        (
            "sensor_offset",
            lambda v: isinstance(v, list) and len(v) == 2 and all(type(x) is int and x >= 0 for x in v),
            "[x, y], whole pixels >= 0",
        ),
    ):
        if key in provenance and not ok(provenance[key]):
            raise FormatError(
                path, f"{group.name}@provenance: {key} is {json.dumps(provenance[key])}: expected {expected}"
            )


def _json_attr(path, group, name) -> dict:
    """A JSON object stored as the text attribute ``name`` (``{}`` when absent)."""
    raw = group.attrs.get(name, "{}")
    try:
        # refused past radiokit's depth, which is walked again by recursion (s51); the nulled
        # non-finite numbers put back (radiokit._json)
        value = strict_json.loads_record(raw.decode() if isinstance(raw, bytes) else raw, f"{group.name}@{name}")
    except (TypeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(path, f"{group.name}@{name} is not JSON text: {type(exc).__name__}") from None
    except strict_json.Refused as exc:  # not radiokit's record: its maker can say nothing of it
        raise FormatError(path, f"{exc}: make the calibration again (radiokit calibrate)") from None
    except ValueError as exc:  # a not_finite map naming no null
        raise FormatError(path, str(exc)) from None
    if not isinstance(value, dict):
        raise FormatError(path, f"{group.name}@{name} must be a JSON object, got {type(value).__name__}")
    return value


#: Tube currents of a frame and of the flats closer than this (relative) are one setting.
CURRENT_TOLERANCE = 0.05
#: The tube currents, uA, a recorded value may be: 1 nA to 1 A, far beyond any X-ray tube's at
#: either end (the L8121 gives up to 500 uA; a CT tube's peak is about 1 A). Outside, the value is
#: corrupt or in other units, and scaling transmissions by it ends in nonsense (a "zero reference
#: contrast" after 1e308 uA).
_TUBE_UA = (1e-3, 1e6)
_NO_TUBE = "no X-ray tube gives that (a recorded current is between 1 nA and 1 A, NaN where not recorded)"


def check_currents(path, meta: dict, frames) -> None:
    """Refuse, naming the file, the field and the frame, a tube current recorded for ``frames``
    (flats or projections: the tube on) outside :data:`_TUBE_UA`; NaN is not recorded."""
    from radiokit.io._experiment import CONTROL

    if "current" not in meta:
        return
    frames = np.asarray(frames, int)
    cur = np.asarray(meta["current"], float)[frames]
    bad = np.flatnonzero(~np.isnan(cur) & ~((cur >= _TUBE_UA[0]) & (cur <= _TUBE_UA[1])))
    if bad.size:
        k = int(frames[bad[0]])
        keys = meta.get("image_key")
        kind = {0: "projection", 1: "flat"}.get(int(keys[k]), "frame") if keys is not None else "frame"
        raise FormatError(
            path,
            f"/{CONTROL}/current of frame {k} (a {kind}) is {float(cur[bad[0]])!r} uA"
            f"{f' ({bad.size} such frames)' if bad.size > 1 else ''}: {_NO_TUBE}",
        )


def exposure_factors(cal: Calibration, meta: dict, path, frames) -> np.ndarray:
    """Per frame of an experiment file (indices ``frames``), the factor its transmission
    ``(raw - dark) / (flat - dark)`` must be multiplied by for the flats' tube current: the
    flats' current over the frame's, 1 where either is not recorded. The tube's output is
    proportional to its current at a given voltage, so a flat at 200 uA and projections at 100 uA
    read every transmission half its value; without this the log images were off by ln 2 and the
    paper's negative contrasts by half, silently. A voltage that differs (the spectrum: no
    factor corrects it) is warned of, once.

    Currents within :data:`CURRENT_TOLERANCE` of the flats' count as the same setting: the file
    records the controller's readback (whole uA, polled during the frame), whose jitter would
    otherwise move every frame by its own few tenths of a per cent.
    """
    frames = np.asarray(frames, int)
    out = np.ones(frames.size)
    if "current" not in meta and "voltage" not in meta:  # not an experiment file, or nothing recorded
        return out
    n = int(frames.max()) + 1 if frames.size else 0
    check_currents(path, meta, frames)
    flat_ua = cal.provenance.get("flat_current_ua")
    cur = np.asarray(meta.get("current", np.full(n, np.nan)), float)[frames]
    if flat_ua is not None and np.isfinite(flat_ua) and flat_ua > 0:
        ok = np.isfinite(cur) & (cur > 0)
        ok[ok] &= np.abs(cur[ok] - flat_ua) > CURRENT_TOLERANCE * flat_ua  # another setting, not readback jitter
        out[ok] = flat_ua / cur[ok]
    flat_kv = cal.provenance.get("flat_voltage_kv")
    kv = np.asarray(meta.get("voltage", np.full(n, np.nan)), float)[frames]
    if flat_kv is not None and np.isfinite(flat_kv):
        off = np.isfinite(kv) & (np.abs(kv - flat_kv) > 0.01 * flat_kv)
        if off.any():
            warnings.warn(
                f"{shown(path)}: {int(off.sum())} frame(s) at {np.unique(np.round(kv[off], 1)).tolist()} kV, the flats at "
                f"{flat_kv:.1f} kV: their transmission is not the object's alone (no factor corrects a spectrum); "
                "take flats at the projections' voltage",
                CalibrationWarning,
                stacklevel=2,
            )
    return out


#: The ADC ranges a panel's frames come in: 12-bit (the C7942), 14-bit (C9730DK, C9732DK), 16-bit.
ADC_TOPS = (4095, 16383, 65535)
#: ADC tops under the 12-bit one (10-bit panels and cameras: 1023) that the guess takes only where
#: the values pile up at them (:func:`_piled_up`). Why not as ADC_TOPS are: a 12-bit panel's flats
#: at a low tube current stay under 1023, and against 1023 their brightest pixels -- a tail thinning
#: out towards it, not a clip -- were called saturated.
CLIPPED_TOPS = (1023,)
#: A clipped top holds at least this many times the values of each of the :data:`PILEUP_LEVELS`
#: levels just under it: every value the ADC would have given above it lands on it. A tail that
#: merely reaches it holds no more than its neighbours (a wide code of the ADC's differential
#: non-linearity, +-0.5 LSB, at most about twice as many).
PILEUP_RATIO = 3
PILEUP_LEVELS = 4
#: The share of values above an ADC's top that a stack of frames of that ADC may hold: stuck or
#: hot pixels, a vendor's defect marker (65535), up to two marked defect lines of a 2240-px panel.
#: A 16-bit panel's frames pass 4095 in most of their pixels once its flats reach a sixteenth of
#: its range. Taken per stack: over darks and flats together, more darks meant more tolerance, and
#: a 16-bit panel's flats passing 4095 in a bright corner (0.3 % of them) were called 12-bit.
ADC_OUTLIER_SHARE = 1e-3
#: The fewest distinct levels (of the counts, low bits dropped) frames must hold for their unused
#: low bits to be taken for MSB alignment, not noise-free frames at round numbers (:func:`_unused_low_bits`).
_MSB_LEVELS = 8
#: Trailing zero bits of each byte value (8 for 0): the low bits a value leaves unused.
_TRAILING_ZEROS = np.array([8] + [(i & -i).bit_length() - 1 for i in range(1, 256)], np.uint8)


def _covering_top(peak: float) -> int | None:
    """The smallest of :data:`ADC_TOPS` that ``peak`` does not exceed (None above 65535)."""
    return next((top for top in ADC_TOPS if peak <= top), None)


#: TIFF 6.0's Orientation values as the reader applies them (radiokit.io's ``_ORIENT``)
_ORIENTATION_NAMES = {
    1: "as stored",
    2: "mirrored left-right",
    3: "turned 180 degrees",
    4: "mirrored top-bottom",
    5: "transposed",
    6: "turned 90 degrees clockwise",
    7: "transposed across the other diagonal",
    8: "turned 90 degrees counter-clockwise",
}


def pixel_layout(meta: dict) -> dict:
    """Where a frame file's pixels lie on the sensor, as its reader placed them (``meta``, a
    :class:`radiokit.io.Frames`' or a source's): ``orientation``, the TIFF Orientation applied (1:
    row 0 as stored), and ``sensor_offset``, a sub-array's ``[x, y]`` on the sensor (an ITEX
    file's; ``[0, 0]``: the whole frame). Why: a dark/flat correction is pixel by pixel, and frames
    read turned (a viewer's lossless turn only tags them) or cut elsewhere from the sensor, at the
    calibration's size, met other sensor pixels' darks and flats, silently. A MATLAB array read
    transposed is not here: that restores the array MATLAB held (and shows), the sensor's grid,
    from its column-major storage; it does not move pixels. ``sensor_offset`` only where the file
    says it (an ITEX header): a TIFF or HDF5 file does not, and taking it for the whole sensor
    refused ITEX sub-array darks and flats against projections exported from that sub-array
    (review s40rr2)."""
    layout: dict = {"orientation": int(meta.get("orientation", 1))}
    if "x_offset" in meta or "y_offset" in meta:
        layout["sensor_offset"] = [int(meta.get("x_offset", 0)), int(meta.get("y_offset", 0))]
    return layout


def _layout_text(key: str, value) -> str:
    if key == "orientation":
        return f"TIFF Orientation {value} ({_ORIENTATION_NAMES.get(value, 'unknown')})"
    return "the whole sensor" if not any(value) else f"a sub-array at x {value[0]}, y {value[1]} on the sensor"


def declared_layout(layouts: dict) -> dict | None:
    """The one :func:`pixel_layout` of the darks' and flats' files (``layouts``: each file's name
    and its layout), else None (no file named: plain arrays). Files read differently are refused
    (ValueError naming each): averaged together, or flats against darks, they pair different
    sensor pixels."""
    found = {name.strip(): lay for name, lay in layouts.items() if lay is not None}
    for key in ("orientation", "sensor_offset"):
        values = {name: lay[key] for name, lay in found.items() if key in lay}
        if len({json.dumps(v) for v in values.values()}) > 1:
            named = ", ".join(f"{name} {_layout_text(key, v)}" for name, v in values.items())
            raise ValueError(
                f"the darks' and flats' files are read differently ({named}): their pixels would pair different "
                "sensor pixels; give darks and flats written alike"
            )
    if not found:
        return None
    # what any file declares (an ITEX file's offset beside TIFF flats, which say none)
    return {key: lay[key] for lay in found.values() for key in lay}


def check_layout(cal: Calibration, meta: dict, path, stated: dict | None = None) -> None:
    """Refuse (:class:`FormatError` naming ``path``) frames whose :func:`pixel_layout` differs
    from the one the calibration's darks and flats were read in: corrected, each pixel would take
    another sensor pixel's dark and flat. Refused rather than corrected in the stored grid: a
    tag-only turn (a viewer's) leaves the stored grids alike, but a turn baked into the pixels
    with the tag reset leaves the viewed ones alike, and a file cannot say which. A calibration
    recording none (written before radiokit recorded it, or built from plain arrays) is taken for
    frames read as stored; frames declaring otherwise are refused, as their darks and flats may
    have been read either way. ``stated``: shared by the frame files of one run, which, where the
    calibration states no sub-array, must then agree among themselves (review s40rr3: ITEX frames
    of two sub-arrays against a calibration from TIFFs were corrected together silently)."""
    layout = pixel_layout(meta)
    for key, default in (("orientation", 1), ("sensor_offset", [0, 0])):
        if key not in layout:  # the frames' file does not say (a TIFF's or HDF5's sub-array)
            continue
        mine, theirs = layout[key], cal.provenance.get(key)
        if theirs is None and "orientation" in cal.provenance:  # recorded: its files did not say (TIFF, HDF5)
            if stated is None:
                continue
            first = stated.setdefault(key, (path, mine))
            if list(first[1]) != list(mine):
                raise FormatError(
                    path,
                    f"frames read in {_layout_text(key, mine)}, those of {first[0]} in {_layout_text(key, first[1])}: "
                    "they hold other sensor pixels, and one calibration cannot serve both; correct each with "
                    "darks and flats of its own sub-array",
                )
            continue
        if theirs is None and mine != default:
            raise FormatError(
                path,
                f"frames read in {_layout_text(key, mine)}, and the calibration does not record how its darks and "
                "flats were read (made before radiokit recorded it): make it again with radiokit calibrate from "
                "darks and flats read as these frames",
            )
        if theirs is not None and list(np.atleast_1d(theirs)) != list(np.atleast_1d(mine)):
            raise FormatError(
                path,
                f"frames read in {_layout_text(key, mine)}, the calibration's darks and flats in "
                f"{_layout_text(key, theirs if key == 'orientation' else list(theirs))}: each pixel would be corrected "
                "with another sensor pixel's dark and flat; calibrate from darks and flats written as these frames "
                "(or write the frames as the darks and flats: a viewer's turn may have only tagged them)",
            )


def declared_bit_depth(bit_depths: dict) -> int | None:
    """The ADC bits the frames' files declare (``bit_depths``: each file's name and its
    ``meta["bit_depth"]``, None where it says nothing), else None: :func:`adc_top` guesses.

    Why first: the guess keeps a lower top while no stack passes it in more than
    :data:`ADC_OUTLIER_SHARE` of its values, so a 16-bit panel's flats passing 4095 in a bright
    corner of 0.1 % were taken for a 12-bit panel's with stuck pixels, the corner masked as
    saturated. An experiment's ``bit_depth_readout`` and a TIFF's BitsPerSample below its word
    (12 in 16-bit words, or packed) say which; a TIFF's BitsPerSample 16 does not (12-bit panels
    write 16-bit TIFFs), nor does a raw file. Files declaring different depths are refused;
    frames passing the declared top (MSB-aligned counts) are judged by their own range."""
    found = {name: int(bits) for name, bits in bit_depths.items() if bits is not None}
    if len(set(found.values())) > 1:
        named = ", ".join(f"{name.strip()} {bits}-bit" for name, bits in found.items())
        raise ValueError(f"the darks' and flats' files declare different ADC bit depths ({named}): not one panel")
    return found.popitem()[1] if found else None


def declared_signed(signs: dict) -> bool:
    """Whether the ADC counts the frames' files declare are signed (``signs``: each file's name and
    its ``meta["bit_depth_signed"]``, a DICOM's PixelRepresentation 1; None or False where it says
    nothing or unsigned). Files saying both are refused, as different depths are."""
    said = {name: bool(v) for name, v in signs.items() if v is not None}
    if len(set(said.values())) > 1:
        named = ", ".join(f"{name.strip()} {'signed' if v else 'unsigned'}" for name, v in said.items())
        raise ValueError(f"the darks' and flats' files declare signed and unsigned counts ({named}): not one panel")
    return any(said.values())


def declared_range(bit_depth, signed=False) -> tuple[int, int]:
    """The lowest and highest count of an ADC of ``bit_depth`` bits: 0 and ``2**bits - 1``, or, its
    counts signed (two's complement in ``bit_depth`` bits: a DICOM's PixelRepresentation 1),
    ``-2**(bits - 1)`` and ``2**(bits - 1) - 1``. Why: a signed 12-bit panel clips at 2047 and
    -2048; judged as unsigned, against 4095, its clipped pixels were never saturated."""
    bits = int(bit_depth)
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)


def declared_levels(bit_depth, signed=False, scaling=None, dtype=np.float32) -> tuple:
    """:func:`declared_range`'s lowest and highest count as the values read them: scaled
    (``scaling``, :func:`value_scaling`) in the values' own type (``dtype``'s with float32 at
    least), as :func:`saturation_level` gives a scaled top; the counts themselves where not scaled."""
    low, high = declared_range(bit_depth, signed)
    if scaling is None:
        return low, high
    values = np.result_type(np.float32, dtype)
    scale, offset = values.type(scaling["scale"]), values.type(scaling["offset"])
    return float(values.type(low) * scale + offset), float(values.type(high) * scale + offset)


def value_scaling(meta: dict) -> dict | None:
    """How a file's stored counts became the values read (``value = stored * scale + offset``):
    a GDAL TIFF's SCALE/OFFSET (``meta["gdal_scaling"]``) or an HDF5 dataset's CF packing
    (``meta["cf_packing"]``), with the stored type (``meta["stored_dtype"]``); None where the
    values are the stored counts. Why: the saturation rules are in ADC counts, and judged on
    the values a 12-bit panel's clipped flats (4095 stored, 35.95 after SCALE 0.01 OFFSET -5)
    were never saturated (review s46rio)."""
    g, cf, dicom = meta.get("gdal_scaling"), meta.get("cf_packing"), meta.get("dicom_rescale")
    if dicom:  # a DICOM's Modality LUT as the file states it (RescaleSlope / RescaleIntercept)
        scale, offset, name = dicom["slope"], dicom["intercept"], "DICOM RescaleSlope/Intercept"
    elif g:
        scale, offset, name = g.get("scale", 1.0), g.get("offset", 0.0), "GDAL SCALE/OFFSET"
    elif cf:
        scale, offset, name = cf["scale_factor"], cf["add_offset"], "CF scale_factor/add_offset"
    else:
        return None
    if (float(scale), float(offset)) == (1.0, 0.0) or "stored_dtype" not in meta:
        return None  # (a NODATA or fill code alone: the values are the counts)
    text = f"{name} stored * {float(scale):g} + {float(offset):g}"
    return {"scale": float(scale), "offset": float(offset), "stored": np.dtype(meta["stored_dtype"]), "text": text}


def _scaled_level(stacks, bit_depth, scaling, signed=False) -> float | None:
    """:func:`saturation_level` of scaled ``stacks`` (:func:`value_scaling`): the top judged on the
    stored counts recovered from the values, given back as a value computed as the reader computes
    them, in the values' own type (a pixel stored at the top reads exactly the level: computed in
    float64, 4095 * 0.01 + 100 passed the float32 pixels' 140.95). None for a negative scale (the
    top would be a floor: not judged) or float storage (no ADC's counts)."""
    scale, offset, stored = (scaling[k] for k in ("scale", "offset", "stored"))
    values = np.result_type(np.float32, *(np.asarray(s).dtype for s in stacks))
    if scale < 0 or stored.kind not in "ui":
        return None
    counts = [_stored_counts(s, scale, offset, stored) for s in stacks]
    top = saturation_level(*counts, bit_depth=bit_depth, signed=signed) if all(c.size for c in counts) else None
    if top is None:
        return None
    return float(values.type(top) * values.type(scale) + values.type(offset))


def _stored_counts(stack, scale, offset, stored) -> np.ndarray:
    """The finite values of ``stack`` (fill codes read NaN) as the stored counts they were, 1-D in
    the stored type; a frame at a time, so that no float64 copy of the whole stack is made (a
    calibration's darks and flats: 20 frames of 2240 x 2240 were ~2.4 GB of temporaries)."""
    info = np.iinfo(stored)
    frames = np.asarray(stack)
    frames = frames.reshape(-1, *frames.shape[-2:]) if frames.ndim >= 2 else frames[None]
    out = []
    for f in frames:
        v = f[np.isfinite(f)].astype(np.float64)
        out.append(np.clip(np.rint((v - offset) / scale), info.min, info.max).astype(stored))
    return np.concatenate(out) if out else np.empty(0, stored)


def saturation_level(*stacks, bit_depth=None, scaling=None, signed=False) -> int | float | None:
    """The saturation level of frames ``stacks`` (the ADC value at and above which a pixel is
    clipped): radiokit's one rule, applied by ``calibrate`` (recorded in the calibration, which
    ``correct`` counts every frame against, integer or float), and ``info``.

    1. The bit depth the frames' file declares (``bit_depth``: a TIFF's BitsPerSample or
       MaxSampleValue below its word, an ITEX header's panel, an experiment file's or NXdetector's
       ``bit_depth_readout``; :func:`declared_bit_depth`): ``2**bit_depth - 1`` (``signed``, a
       DICOM's PixelRepresentation 1: ``2**(bit_depth - 1) - 1``, :func:`declared_range`), unless
       the frames pass it (MSB-aligned counts: ``read()`` warned), when they are judged as
       undeclared ones.
    2. Else :func:`adc_top`: 8-bit integers the type's top (255), wider frames the smallest usual
       ADC top their values fit (all but :data:`ADC_OUTLIER_SHARE` of each stack's), 1023 only
       where the values pile up there, less the low bits MSB-aligned frames leave unused (65520).

    Float frames of no declared depth get the top their values fit, as wider integers do
    (``info`` shows no saturation for them: floats are no ADC's words; ``correct`` counts them
    against their calibration's level). None: no level (floats beyond 65535).

    Scaled values (``scaling``, :func:`value_scaling`): the level of their stored counts, as a value
    (``top * scale + offset``); None for a negative scale (said by each command: not checked)."""
    if scaling is not None:
        return _scaled_level(stacks, bit_depth, scaling, signed)
    if bit_depth is not None:
        declared = declared_range(bit_depth, signed)[1]
        if max(float(np.max(s)) for s in stacks) <= declared:
            return declared
    return adc_top(*stacks)


def adc_top(*stacks) -> int | None:
    """The saturation level the frames imply (:func:`saturation_level` without a declared depth).

    8-bit integer frames (every stack): the type's top, 255 (127 signed): such files come from
    8-bit ADCs and cameras, and against the 12-bit 4095 a flat clipped at 255 in half its pixels
    was accepted, its projections' clipped pixels uncounted.

    Else the smallest of :data:`ADC_TOPS` that none of their values exceeds (None above 65535:
    float frames of no ADC), less the low bits that integer frames never set
    (:func:`_unused_low_bits`), or a lower one of :data:`CLIPPED_TOPS` (1023) that the values fit
    and pile up at (:func:`_piled_up`).

    Why: a fixed 4095 called every pixel of a 16-bit panel's flat saturated, and the calibration
    refused the lab's data ("lower the flat exposure"). And a 12-bit panel whose software stores
    its counts in the top bits of 16 (``value << 4``: TIFFs from several frame grabbers) saturates
    at 65520, never 65535: against 65535 its saturated flat pixels were not flagged at all.
    A lower top is kept while no stack has more than :data:`ADC_OUTLIER_SHARE` of its values above
    it: one stuck pixel at 65535 made a 12-bit panel's clipped flats "16-bit", never saturated."""
    stacks = [np.asarray(s) for s in stacks]
    if stacks and all(s.dtype.kind in "ui" and s.dtype.itemsize == 1 for s in stacks):
        return max(int(np.iinfo(s.dtype).max) for s in stacks)
    top = _covering_top(max(float(np.max(s)) for s in stacks))
    for lower in (t for t in ADC_TOPS if top is None or t < top):  # only when the peak passed 4095
        if _fits(stacks, lower):
            top = lower
            break
    if top is None:
        return None
    top &= ~((1 << _unused_low_bits(stacks)) - 1)
    if top == ADC_TOPS[0]:  # LSB-aligned counts under 4096: a 10-bit ADC's only if clipped
        return next((t for t in CLIPPED_TOPS if _fits(stacks, t) and _piled_up(stacks, t)), top)
    return top


def _fits(stacks, top) -> bool:
    """No stack has more than :data:`ADC_OUTLIER_SHARE` of its values above ``top``."""
    return all(np.count_nonzero(s > top) <= ADC_OUTLIER_SHARE * s.size for s in stacks)


def _piled_up(stacks, top) -> bool:
    """Whether one of ``stacks`` piles up at ``top``, as values clipped there do: more of its values
    there than :data:`ADC_OUTLIER_SHARE` of its own (a stuck pixel or two are not a clip) and than
    :data:`PILEUP_RATIO` times the most at any of the :data:`PILEUP_LEVELS` levels just below, plus
    five Poisson sigmas of that (a handful of values at a top their neighbours miss is chance).
    Each stack on its own: the flats clip, and counted against the darks' pixels too, a flat clipped
    in 0.15 % of its pixels was not (review s40rr2)."""
    for s in stacks:
        near = s[(s >= top - PILEUP_LEVELS) & (s <= top)].ravel()
        counts = [int(np.count_nonzero(near == top - k)) for k in range(PILEUP_LEVELS + 1)]
        at, below = counts[0], max(counts[1:])
        if at > max(PILEUP_RATIO * below + 5 * np.sqrt(below + 1), ADC_OUTLIER_SHARE * s.size):
            return True
    return False


def _unused_low_bits(stacks, most=8) -> int:
    """How many low bits the integer ``stacks`` leave 0 in all but :data:`ADC_OUTLIER_SHARE` of
    each stack's values (at most ``most``, so that 8 significant bits remain; 0 for float stacks
    or all-zero ones). Real frames' noise sets every bit of an LSB-aligned ADC, so only MSB-aligned
    data (``counts << b``) leaves low bits unused. The share: one stuck pixel at 65535 hid a 12-bit
    MSB-aligned panel's top (65520), as it hid a 12-bit one's (:func:`adc_top`)."""
    stacks = [np.asarray(s) for s in stacks]
    if any(s.dtype.kind not in "ui" for s in stacks):
        return 0
    sample = np.concatenate([s.ravel()[:: max(1, s.size // 50_000)] for s in stacks])
    if np.count_nonzero(sample & 1) > 10 * ADC_OUTLIER_SHARE * sample.size:  # LSB-aligned: no full count
        return 0
    bits = most
    for s in stacks:
        zeros = np.bincount(_TRAILING_ZEROS, weights=_low_bytes(s), minlength=9)
        bits = min(bits, next(b for b in range(most, -1, -1) if zeros[:b].sum() <= ADC_OUTLIER_SHARE * s.size))
    # Noise-free frames (synthetic, or a constant flat at a round number such as 4064 = 0xFE0)
    # leave low bits unused too, and would put the top at their own level: every pixel
    # "saturated". MSB-aligned frames of a real panel vary over several levels of their counts:
    # quiet darks (2 counts rms, the C7942's) over a dozen, whatever the flats do. 32 levels were
    # asked for once, and flats clipped in nearly every pixel (2 levels) beside such darks kept
    # the top at 65535: never saturated, the calibration accepted.
    return bits if bits and np.unique(sample >> bits).size >= _MSB_LEVELS else 0


def _low_bytes(stack, block=1 << 18) -> np.ndarray:
    """How many of integer ``stack``'s values have each low byte (256 counts), ``block`` values at
    a time: ``np.bincount`` of the whole stack's bytes made an int64 copy of it, 8 bytes a pixel
    (one 8000 x 8000 frame: 488 MiB; ``radiokit info`` peaked at 870 MB, benchmarks/README.md)."""
    flat = np.ravel(stack)
    counts = np.zeros(256, np.int64)
    for start in range(0, flat.size, block):
        counts += np.bincount((flat[start : start + block] & 0xFF).astype(np.uint8), minlength=256)
    return counts


def frame_saturation(saturation, raw, defects=None) -> int | None:
    """The saturation level to count ``raw``'s pixels against: ``saturation``, unless the frame
    holds values above it, which no ADC of that depth gives -- the level was inferred from darks
    and flats that never reached the top (flats at a lower current than the projections on a
    16-bit panel read as 12-bit), and the frame's own range then decides. Without this every pixel
    of such a projection was reported saturated.

    Values above ``saturation`` only at the calibration's defects (``defects``, its mask: a stuck
    pixel at 65535) keep it. No share of the frame's own values is ignored: a 16-bit projection
    with a small patch above 4095 kept a guessed 4095 and reported the patch saturated.

    Float frames alike, their NaN and inf pixels no values (counted and filled apart)."""
    if saturation is None or not raw.size or (raw.dtype.kind in "ui" and raw.max() <= saturation):
        return saturation
    over = raw > saturation  # NaN: False
    if raw.dtype.kind == "f":
        over &= np.isfinite(raw)
    if not over.any() or (defects is not None and not np.any(over & (defects == 0))):
        return saturation
    top = _covering_top(float(raw[over].max()))
    return None if top is None else top & ~((1 << _unused_low_bits([raw])) - 1)


def _bar(progress: bool, total, desc: str, unit: str):
    """A tqdm bar on stderr, or one that shows nothing (``progress`` False), as radiokit process's."""
    from radiokit.progress import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not progress)


def _read_counted(src, indices, bar) -> np.ndarray:
    """Frames ``indices`` of ``src`` stacked, the bar advanced by one per frame read."""
    frames = []
    for i in indices:
        frames.append(src[i])
        bar.update()
    return np.stack(frames)


class FrameLevelError(CalibrationRefused):
    """A dark or flat frame at the other kind's level: ``kind`` ("dark" or "flat") and ``index``
    (0-based, in its stack) say which, for a caller that knows its file; its kind's frames are
    the ones to take again (``culprits``)."""

    def __init__(self, kind: str, index: int, message: str):
        super().__init__(message, (f"{kind}s",))
        self.kind, self.index = kind, index


#: A flat refused by :func:`_check_levels` reading over this share of the brightest flat's signal
#: is lit (another exposure), not a dark: a dark among flats reads ~0 of it, within its noise, and
#: a flat caught in a tube's warm-up or a current spike reads a fair share of it
LIT_SHARE = 0.1

#: A dark whose pixels span over this share of the flats' signal above it holds an image
#: (:func:`_check_lit_darks`): a lit image's background reads the flat's level, its object less
LIT_SPAN = 0.5

#: ... and spans over this many times its pixel noise: a dark's 5th-95th percentile spans ~3.3 of
#: it (Gaussian), an image its contrast (a round phantom passing a quarter of a 12000-count flat: ~100)
LIT_NOISE = 10.0

#: ... and either spans over :data:`LIT_SPAN` beyond the flats' pattern or lies under the flats by
#: less than this share of that level (its pixels' median): a dark's offsets lie under a usable
#: flat by its signal, a flat given as the dark at the flats' level
LIT_GAP = 0.1


def _check_levels(darks, flats, eps) -> None:
    """Refuse a flat frame closer to the darks' level than to the brightest flat's, or a dark frame
    closer to the flats' than to the darkest dark's (each frame's median).

    Why: a dark file among the flats (a glob) gave each pixel samples 2900 counts apart, none
    clipped by :func:`robust_average`, and a flat halfway up: every transmission twice too high,
    exit 0. The darkest dark and the brightest flat anchor the levels, not the medians, which half
    the frames of the wrong kind would move. A refused flat that is lit (:data:`LIT_SHARE`) is
    named as one of another exposure, not as a dark."""
    sample = (slice(None), slice(None, None, 4), slice(None, None, 4))
    sampled = {"dark": darks[sample], "flat": flats[sample]}
    levels = {k: np.median(s.reshape(len(s), -1), axis=1) for k, s in sampled.items()}
    dark = float(levels["dark"].min())
    signal = float(levels["flat"].max()) - dark
    if signal > eps:  # else no flat level to compare with: refused as "not brighter" further on
        _check_stack_levels(levels, dark, signal)
    _check_lit_darks(sampled["dark"], sampled["flat"], float(levels["flat"].max()), eps)


def _check_lit_darks(darks, flats, flat: float, eps) -> None:
    """Refuse a dark frame that holds an image: its pixels (5th to 95th percentile) spanning over
    :data:`LIT_SPAN` of the brightest flat's level above its own lowest, and over :data:`LIT_NOISE`
    times its noise; and beyond the flats' median frame spanning over that share too or lying
    under it by less than :data:`LIT_GAP` of the level (the pixels' median). Why: a projection
    given as the only dark passed :func:`_check_levels` (no other dark to compare it with), and the flats'
    response, lit only where the phantom absorbed, was refused as an image intensifier's circular
    field. A dark's pixels differ by their noise and offsets, a small share of any usable flat's
    signal; a lit image's by its contrast, up to the flat's whole level. The second test: a
    panel's offsets (read-out blocks a couple hundred counts apart, a gradient) under a low-kV
    flat a few hundred counts above them spanned more than the flat's signal, and a true dark
    was refused; the flats carry the same offsets, so what the dark holds beyond them (less the
    flats' signal) spans the field's unevenness, a lit image's the contrast still; a flat given
    as the dark holds no more than the flats do, but at their level, not under it."""
    reference = np.median(flats, axis=0)  # the flats' offsets and field, their noise averaged
    for i, frame in enumerate(darks):
        finite = frame[np.isfinite(frame)]
        if not finite.size:  # no value to judge (refused as such further on)
            continue
        lo, hi = (float(v) for v in np.percentile(finite, (5, 95)))
        room = flat - lo
        # its noise, from neighbouring samples' differences (a scene's edges are few of them):
        # flats taken with the beam off span their darks' noise, as a dark does -- not an image
        steps = np.abs(np.diff(frame.astype(np.float64), axis=-1))
        noise = float(np.median(steps[np.isfinite(steps)])) / 0.954 if steps.size else 0.0
        if room <= eps or hi - lo <= max(LIT_SPAN * room, LIT_NOISE * noise):
            continue  # a dark's span (the flats' pattern judged only past it)
        # a float64 difference: an unsigned frame less its flat would wrap
        beyond = frame.astype(np.float64) - reference
        beyond = beyond[np.isfinite(beyond)]
        own = float(np.subtract(*np.percentile(beyond, (95, 5)))) if beyond.size else 0.0
        under = -float(np.median(beyond)) if beyond.size else 0.0
        if own > LIT_SPAN * room or under < LIT_GAP * room:
            raise FrameLevelError(
                "dark",
                i,
                f"dark {i + 1} of {len(darks)} spans {hi - lo:.0f} counts between its pixels (5th to "
                f"95th percentile), {100 * (hi - lo) / room:.0f} % of the brightest flat's "
                f"{room:.0f} above its lowest: it is lit (a projection or flat given as the dark, or the beam on), "
                "not a dark; take the darks with the beam off",
            )


def _check_stack_levels(levels: dict, dark: float, signal: float) -> None:
    """:func:`_check_levels`' comparison of each frame's median with the darkest dark's and the
    brightest flat's."""
    why = {
        "flat": "a dark, not a flat (a dark file among the flats, a closed shutter or the beam off)",
        "dark": "a flat, not a dark (a flat file among the darks, or the beam on)",
    }
    for kind, wrong in (("flat", levels["flat"] - dark < signal / 2), ("dark", levels["dark"] - dark > signal / 2)):
        if wrong.any():
            i = int(np.argmax(wrong))
            share = (levels[kind][i] - dark) / signal
            if kind == "flat" and share > LIT_SHARE:  # lit, at another exposure: not a dark
                reason = (
                    f"{100 * share:.0f} % of the brightest: flats of another exposure (another tube current "
                    "or time, a current spike), whose average mixes two; take the flats at one exposure"
                )
            else:
                reason = why[kind]
            raise FrameLevelError(
                kind,
                i,
                f"{kind} {i + 1} of {len(wrong)} reads {levels[kind][i] - dark:.0f} counts above the darkest dark, "
                f"the brightest flat {signal:.0f}: {reason}",
            )


def _check_stacks(darks, flats):
    """Both stacks as 3-D arrays of one frame shape; a warning for fewer than 3 frames."""
    darks = _as_stack(darks, "darks")
    flats = _as_stack(flats, "flats")
    if darks.shape[1:] != flats.shape[1:]:
        raise ValueError(f"darks are {darks.shape[1:]} but flats are {flats.shape[1:]}")
    for name, stack in (("darks", darks), ("flats", flats)):
        if stack.shape[0] < 3:
            warnings.warn(
                f"only {stack.shape[0]} {name}: with fewer than 3 frames a zinger can be "
                "rejected only by taking the smaller value; take 10 or more",
                CalibrationWarning,
                stacklevel=3,
            )
    return darks, flats


def _reference_response(response, th: Thresholds) -> np.ndarray:
    """The local response each pixel is judged against (:func:`_local_median`), taken over the
    pixels that are not already defects by a first look: those with a response (over ``eps`` and
    over ``dead_below`` of the lit level, the 90th percentile, as :func:`_exposed_field` says lit),
    then of those the ones within ``[under_below, over_above]`` of that first reference. Why: the
    defects were part of their own reference, so a gap or dead band filling half a tile pulled the
    tile's median to half, and the good rows beside it, at twice "the local response", were
    flagged (58 rows for a 16-row band, a Pilatus's module gaps refused at 12.4 % for 5.5 %)."""
    lit = float(np.percentile(response, 90))
    valid = response > max(th.eps, th.dead_below * lit)
    first = _local_median(response, th.smooth_block, valid)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(first > th.eps, response / first, 0)
    valid &= (rel >= th.under_below) & (rel <= th.over_above)
    return _local_median(response, th.smooth_block, valid)


def _defect_map(flat, dark_std, response, th, clipped=None, n_flats=None):
    """The pixel mask (:class:`PixelFlag` bits), the rows and columns filled as lines, how many
    pixels of the flat are saturated (see :meth:`Calibration.from_frames`' notes): at the top in the
    average or, ``clipped`` (:func:`clipped_samples`, of ``n_flats`` frames), in any frame whose
    sample the average kept; and (rows, columns) of those lines that are lines only by the flats'
    saturation, no defect lines."""
    mask = np.zeros(flat.shape, np.uint32)
    local = _reference_response(response, th)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(local > th.eps, response / local, 0).astype(np.float32)
    mask[(rel < th.under_below)] |= np.uint32(PixelFlag.UNDER_RESPONDING)
    mask[(rel < th.dead_below) | (response <= th.eps)] = np.uint32(PixelFlag.DEAD)
    mask[rel > th.over_above] |= np.uint32(PixelFlag.OVER_RESPONDING)
    sat = np.inf if th.saturation is None else th.saturation
    saturated = flat >= sat
    if clipped is not None and n_flats:
        saturated |= clipped >= clipped_floor(n_flats)
    # a pixel stuck at the top in the darks too is dead (no response), not over-exposed: "lower
    # the flat exposure" was said of stuck pixels (review s42)
    saturated &= response > th.eps
    n_flat_saturated = int(np.count_nonzero(saturated))
    if n_flat_saturated > flat.size // 2:
        raise ValueError(
            f"the flats are saturated (>= {th.saturation:.7g}) in {n_flat_saturated} of "
            f"{flat.size} pixels: lower the flat exposure (current or time)"
        )
    mask[saturated] |= np.uint32(PixelFlag.OVER_RESPONDING)
    if dark_std is not None:
        ref = float(np.nanmedian(dark_std))
        if ref > 0:
            mask[np.nan_to_num(dark_std, nan=0) > th.noisy_factor * ref] |= np.uint32(PixelFlag.NOISY)
    flagged = mask != 0
    rows_idx, rows_bits = _line_flags(rel, dark_std, flagged, th, axis=0)
    cols_idx, cols_bits = _line_flags(rel, dark_std, flagged, th, axis=1)
    sat_lines = (np.zeros(0, np.intp), np.zeros(0, np.intp))
    if n_flat_saturated:
        # Lines are judged again without the flats' saturated pixels: those found only with them
        # are the saturation's, not defect lines. Why: a heel flat clipped over its brightest 23-28
        # columns made them "defect lines", counted against the manual's 20 with a gain step's
        # advice (review s42rr). They are still filled as lines: a mostly clipped line's few
        # unclipped pixels are those whose flat read low, and filled from them a 0.5 transmission
        # came out 0.5 % high where the line beside it gives it unbiased.
        real_rows, real_row_bits = _line_flags(rel, dark_std, flagged, th, axis=0, skip=saturated)
        real_cols, real_col_bits = _line_flags(rel, dark_std, flagged, th, axis=1, skip=saturated)
        sat_lines = (np.setdiff1d(rows_idx, real_rows), np.setdiff1d(cols_idx, real_cols))
        rows_idx, rows_bits = _merge_lines(rows_idx, rows_bits, real_rows, real_row_bits)
        cols_idx, cols_bits = _merge_lines(cols_idx, cols_bits, real_cols, real_col_bits)
    mask[rows_idx, :] |= rows_bits[:, None]
    mask[:, cols_idx] |= cols_bits[None, :]
    if n_flat_saturated:
        warnings.warn(
            f"{n_flat_saturated} pixels of the flats are saturated (>= {th.saturation:.7g})"
            f"{_clipped_text(clipped, n_flats)}{_saturated_lines_text(*sat_lines)}; "
            "they are flagged, but lower the flat exposure",
            CalibrationWarning,
            stacklevel=4,  # _defect_map, _from_averages, from_frames: the caller's line
        )
    return mask, rows_idx, cols_idx, n_flat_saturated, sat_lines


def _merge_lines(idx, bits, idx2, bits2):
    """The union of two sets of lines (indices, flag bits), bits of a line in both OR-ed."""
    lines = np.union1d(idx, idx2)
    out = np.zeros(lines.size, np.uint32)
    for i, b in ((idx, bits), (idx2, bits2)):
        out[np.searchsorted(lines, i)] |= b
    return lines, out


def line_summary(defect_rows, defect_columns, provenance: dict) -> dict:
    """What a calibration fills as lines, in words, for ``radiokit calibrate`` and ``info``:
    ``{"defect lines": "rows [...], columns [...]", "saturated lines": "columns [...] (flats
    clipped, ...)"}``, each only where there are any. The lines filled only for the flats'
    saturation (``provenance["saturated_lines"]``, :func:`_defect_map`) are named as the
    calibration's warning names them, not as defect lines: listed among those, a heel flat's
    clipped columns read as a panel fault, beside the manual's 20 at most."""
    sat = provenance.get("saturated_lines") or {}
    sat_rows, sat_cols = (np.asarray(sat.get(k, []), np.int64) for k in ("rows", "columns"))
    rows = np.setdiff1d(np.asarray(defect_rows, np.int64), sat_rows)
    cols = np.setdiff1d(np.asarray(defect_columns, np.int64), sat_cols)
    out = {}
    if rows.size or cols.size:
        out["defect lines"] = f"rows {rows.tolist()}, columns {cols.tolist()}"
    if sat_rows.size or sat_cols.size:
        named = ", ".join(
            f"{name} {idx.tolist()}" for name, idx in (("rows", sat_rows), ("columns", sat_cols)) if idx.size
        )
        out["saturated lines"] = f"{named} (flats clipped, not defect lines: lower the flat exposure)"
    return out


def _saturated_lines_text(rows, cols) -> str:
    """ "; columns 233-255 are filled as lines for it (saturated lines, not defect lines)"
    for the warning of saturated flat pixels; "" where there are none."""
    found = [f"{name} {_runs(idx)}" for name, idx in (("rows", rows), ("columns", cols)) if idx.size]
    if not found:
        return ""
    return f"; {' and '.join(found)} are filled as lines for it (saturated lines, not defect lines)"


def clipped_floor(n_frames: int) -> int:
    """How many of a pixel's ``n_frames`` flat samples, clipped and kept in its average, make it
    saturated (:func:`clipped_samples`): 2, or a tenth of the frames if that is more. Why not 1: a pixel
    clipped in a tenth of its frames (its mean 1.3 noise sigmas under the top) averages 0.05 sigma
    low, a few counts, under the average's own noise; and one clipped sample of ten happens by
    chance two sigmas under the top, where the bias is nil: counting those grew a heel's clipped
    band by a third (review s42's t5b_flatclip.py: 13.3 % of the panel against 10.4 %, where
    5.1 % average above the top)."""
    return max(2, -(-int(n_frames) // 10))


def _clipped_text(clipped, n_flats) -> str:
    """ " in 2-10 of their 10 frames (4121 samples): their averages are biased low" for the warning
    of saturated flat pixels; "" where no frame's count is known."""
    if clipped is None or not n_flats or not (clipped >= clipped_floor(n_flats)).any():
        return ""
    hit = clipped[clipped >= clipped_floor(n_flats)]
    lo, hi = int(hit.min()), int(hit.max())
    frames = f"{lo}-{hi}" if lo < hi else f"{hi}"
    low = ": their averages are biased low" if lo < n_flats else ""
    return f" in {frames} of their {n_flats} frames ({int(hit.sum(dtype=np.int64))} samples){low}"


#: The largest share of the panel a defect map may mark defective. The C7942 has up to 20 defect
#: lines (the hardware facts, shared/hardware/C7942.md, "Corrections the manual prescribes"): at 1x1 that is
#: 20 lines of 2240-2368 px in a 2240 x 2240-2368 frame, 0.9 %; a line stays a line when binned, so
#: at 4x4 (560 px) it is 20 / 560 = 3.6 %, and isolated defects and the thresholds' statistical
#: flags add a fraction of a percent. 10 % is nearly three times that worst honest case, while frames
#: that are not a dark and flat of one set-up (the beam blocked for most of the flats, a flat taken
#: as a dark, another panel's frames) flag half the panel or more (line_fraction then turns every
#: row and column into a line).
MAX_DEFECTIVE_SHARE = 0.10


#: A recorded pixel_mask marking more of the panel than this is not a mask of bad pixels (NeXus's
#: sense inverted: a mask of good ones). Not MAX_DEFECTIVE_SHARE: a large tiled panel's gaps alone
#: are 7-8 % of it, and the mask is the writer's statement, not a measurement to doubt.
MAX_RECORDED_SHARE = 0.5


def _merge_recorded_mask(cal: Calibration, path, recorded) -> None:
    """Add the experiment file's own NeXus ``pixel_mask`` (NXdetector: the pixels its writer knew
    bad, a tiled panel's gaps) to the defect map the darks and flats gave, so that correction fills
    them as it fills its own defects. Why: a lab that records a mask expects it honoured; it was
    read and dropped, and a gap's pixels were measured as data. NeXus's bits 0-8 are kept as they
    are; any higher bit (bit 31: a virtual pixel, interpolated) counts as :attr:`PixelFlag.USER`.
    All zeros (what radiokit's writers record) changes nothing. One of another shape (a native
    mask beside binned frames) is left out with a warning: it was ignored before, and a file that
    calibrated then calibrates now."""
    if recorded is None:
        return
    m = np.asarray(recorded)
    where = f"its pixel_mask {m.shape} {m.dtype}"
    if m.shape != cal.shape:
        warnings.warn(
            f"{shown(path)}: {where} does not match the frames ({cal.shape[0]}x{cal.shape[1]}): not used",
            CalibrationWarning,
            stacklevel=3,
        )
        return
    if m.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            if not (np.isfinite(m).all() and (m == np.round(m)).all() and (m >= 0).all() and (m < 2**32).all()):
                raise FormatError(path, f"{where}: not whole numbers from 0 to 2^32 - 1 (NeXus bit flags)")
    elif m.dtype.kind == "i" and (m < 0).any():
        m = m.astype(np.int64) & 0xFFFFFFFF  # a signed int32 carries bit 31 as its sign
    elif m.dtype.kind not in "iub":
        raise FormatError(path, f"{where}: not integer bit flags")
    m = m.astype(np.uint32)
    if not m.any():
        return
    nexus = m & np.uint32(0x1FF)
    added = np.where((m != 0) & (nexus == 0), np.uint32(PixelFlag.USER), nexus) | np.where(
        m > 0x1FF, np.uint32(PixelFlag.USER), np.uint32(0)
    )
    n = int(np.count_nonzero(m))
    if n > MAX_RECORDED_SHARE * m.size:
        raise FormatError(
            path,
            f"{where} marks {n} of {m.size} pixels ({100 * n / m.size:.1f} %) bad, over "
            f"{100 * MAX_RECORDED_SHARE:g} %: is it a mask of good pixels (NeXus marks the bad ones)?",
        )
    cal.mask = (cal.mask | added).astype(cal.mask.dtype)
    good = cal.mask == 0
    cal.c = float(np.mean((cal.flat - cal.dark)[good]))
    # the CLI's "defects:" line and the report read this count
    cal.provenance.setdefault("defects", {})["recorded in the file"] = n


def _exposed_field(response, dead_below) -> tuple[int, int, int, int] | None:
    """The rectangle ``(r0, r1, c0, c1)`` (inclusive) outside which the flats are unexposed, as
    behind a collimator, else None (the beam reached the whole panel, or not as one rectangle).
    Unexposed: a response under ``dead_below`` of the lit level (the 90th percentile, in the field
    whatever share of the panel the shadow takes)."""
    exposed = response > dead_below * float(np.percentile(response, 90))
    rows, cols = np.flatnonzero(exposed.mean(axis=1) > 0.5), np.flatnonzero(exposed.mean(axis=0) > 0.5)
    if not rows.size or not cols.size:
        return None
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])
    inside = np.zeros(exposed.shape, bool)
    inside[r0 : r1 + 1, c0 : c1 + 1] = True
    if inside.all() or exposed[~inside].mean() > 0.1 or (~exposed[inside]).mean() > MAX_DEFECTIVE_SHARE:
        return None
    return r0, r1, c0, c1


def _exposed_disc(response, dead_below):
    """``((row, col, radius), (r0, r1, c0, c1))``: the disc outside which the flats are unexposed
    (as :func:`_exposed_field` judges it), as an image intensifier's round field leaves a square
    frame, and the square inside it (inclusive, within the frame); None when the lit pixels are no
    disc (within 3 % of the frame). The radius is the lit pixels' furthest from their centroid
    (the 99.9th percentile: a few hot pixels outside do not count), so a disc the frame cuts off
    is measured whole."""
    exposed = response > dead_below * float(np.percentile(response, 90))
    if exposed.sum() < 16 or exposed.all():
        return None
    rr, cc = np.nonzero(exposed)
    cy, cx = float(rr.mean()), float(cc.mean())
    radius = float(np.percentile(np.hypot(rr - cy, cc - cx), 99.9))
    gy, gx = np.ogrid[: response.shape[0], : response.shape[1]]
    disc = (gy - cy) ** 2 + (gx - cx) ** 2 <= radius**2
    if disc.all() or (disc != exposed).mean() > 0.03:
        return None
    half = radius / np.sqrt(2)
    rows, cols = response.shape
    square = (
        max(0, int(np.ceil(cy - half))),
        min(rows - 1, int(np.floor(cy + half))),
        max(0, int(np.ceil(cx - half))),
        min(cols - 1, int(np.floor(cx + half))),
    )
    return (cy, cx, radius), square


def _runs(index) -> str:
    """``[3, 4, 5, 9]`` as "3-5, 9"; the first eight runs, then how many more."""
    runs = np.split(index, np.flatnonzero(np.diff(index) != 1) + 1)
    text = [f"{r[0]}-{r[-1]}" if r.size > 1 else f"{r[0]}" for r in runs[:8]]
    return ", ".join(text) + (f" and {len(runs) - 8} more" if len(runs) > 8 else "")


def _dead_lines(mask) -> str | None:
    """What whole rows and columns of dead pixels (nine tenths of them or more) the defect map
    holds -- "51 whole rows (40-56, 97-113, 154-170)" -- when they are at least half of its flagged
    pixels, else None. Dead lines that wide are no panel's defect lines but the gaps between a
    tiled detector's modules, and the refusal says so."""
    dead = (mask & np.uint32(PixelFlag.DEAD)) != 0
    rows, cols = np.flatnonzero(dead.mean(axis=1) >= 0.9), np.flatnonzero(dead.mean(axis=0) >= 0.9)
    lines = np.zeros(mask.shape, bool)
    lines[rows] = True
    lines[:, cols] = True
    if not (rows.size or cols.size) or 2 * np.count_nonzero(lines & (mask != 0)) < np.count_nonzero(mask):
        return None
    parts = [f"{idx.size} whole {name} ({_runs(idx)})" for name, idx in (("rows", rows), ("columns", cols)) if idx.size]
    return " and ".join(parts)


def _check_defect_share(mask, n_saturated=0, saturation=None, response=None, dead_below=0.0) -> None:
    """Refuse a defect map that marks more than :data:`MAX_DEFECTIVE_SHARE` of the panel: such a
    calibration "corrects" by filling most pixels from their neighbours, and was exiting 0. When
    the flat's saturated pixels are most of it, the refusal says so: a flat clipped in 12 % of the
    panel (a source set for 1x1, binned) was sent looking for a blocked beam. So it does when the
    flats are unexposed outside a rectangle (:func:`_exposed_field` of ``response``, the flat's
    response and ``dead_below``): a collimator's shadow was called frames of another set-up."""
    n = int(np.count_nonzero(mask))
    over = n > MAX_DEFECTIVE_SHARE * mask.size
    field = _exposed_field(response, dead_below) if over and response is not None else None
    if field is not None:
        r0, r1, c0, c1 = field
        raise ValueError(
            f"the flats are unexposed outside rows {r0}-{r1}, columns {c0}-{c1} ({100 * n / mask.size:.1f} % of the "
            f"panel flagged, over the {100 * MAX_DEFECTIVE_SHARE:g} % a defect map may mark): the beam blocked "
            "there (a collimator's shadow, the frame or a shutter in the way?); clear its path, or crop the darks, "
            "flats and frames to that field"
        )
    disc = _exposed_disc(response, dead_below) if over and response is not None and field is None else None
    if disc is not None:
        (cy, cx, radius), (r0, r1, c0, c1) = disc
        raise ValueError(
            f"the flats are lit only inside a disc of radius {radius:.0f} px centred at row {cy:.0f}, column "
            f"{cx:.0f} ({100 * n / mask.size:.1f} % of the panel flagged, over the {100 * MAX_DEFECTIVE_SHARE:g} % a "
            "defect map may mark): an image intensifier's circular field? crop the darks, flats and frames to the "
            f"square inside it, rows {r0}-{r1}, columns {c0}-{c1}"
        )
    gaps = _dead_lines(mask) if over else None
    if gaps is not None:
        raise ValueError(
            f"the defect map marks {n} of {mask.size} pixels ({100 * n / mask.size:.1f} %) defective, over the "
            f"{100 * MAX_DEFECTIVE_SHARE:g} % a panel has at most (up to 20 defect lines), {gaps} reading no "
            "response in the darks and flats: the gaps between a tiled detector's modules? a defect map is one "
            "panel's; crop the darks, flats and frames to one module"
        )
    if n > MAX_DEFECTIVE_SHARE * mask.size and 2 * n_saturated >= n:
        raise ValueError(
            f"the flats are saturated (>= {saturation:.7g}) in {n_saturated} of {mask.size} pixels "
            f"({100 * n_saturated / mask.size:.1f} %), over the {100 * MAX_DEFECTIVE_SHARE:g} % of the panel a defect "
            "map may mark: lower the flat exposure (tube current or time, or less binning)"
        )
    if n > MAX_DEFECTIVE_SHARE * mask.size:
        raise ValueError(
            f"the defect map marks {n} of {mask.size} pixels ({100 * n / mask.size:.1f} %) defective, over the "
            f"{100 * MAX_DEFECTIVE_SHARE:g} % a panel has at most (up to 20 defect lines): these darks and flats "
            "are not of one panel set-up (beam blocked for the flats? frames swapped or of another panel?)"
        )


def _dark_noise(darks) -> float | None:
    """One dark frame's temporal noise (counts rms, the median over a sample of rows; None from a
    single dark)."""
    if darks.shape[0] < 2:
        return None
    sample = darks[:, :: max(1, darks.shape[1] // 64)]
    return float(np.median(np.std(sample, axis=0, ddof=1, dtype=np.float64)))  # float32 squares overflow past 1.8e19


@dataclass
class CalibrationInput:
    """One file a calibration's darks and flats were read from, as its provenance records it
    (``provenance["inputs"]``, :meth:`record`). Why: a calibration named its files at most as
    given (``dark_files``), neither the HDF5 dataset read in them nor which file that was, so a
    user could not tell later which frames had made it. The file's size and modification time
    tell a file replaced since from the one read; no content hash: an experiment file's
    projections are never read to calibrate, and hashing them would read them all.

    Attributes
    ----------
    path : str
        The file as given (on the command line, or to the library).
    resolved : str
        Its absolute path, symbolic links resolved.
    format : str
        How it was read (``"hdf5"``, ``"tiff"``, ``"experiment"``, ...).
    dataset : str or None
        The HDF5 dataset its frames were read from; None for other formats.
    option : str or None
        The option that named ``dataset`` (``"--dark-dataset"``, ``"--dataset"``); None where the
        reader found it by the file's own layout.
    darks, flats : int
        Frames of it averaged as darks and as flats.
    size_bytes : int or None
        Its size when read.
    modified : str or None
        Its modification time when read, ISO 8601 in UTC.
    """

    path: str
    resolved: str
    format: str
    dataset: str | None = None
    option: str | None = None
    darks: int = 0
    flats: int = 0
    size_bytes: int | None = None
    modified: str | None = None

    @classmethod
    def of(cls, path, meta: dict, option: str | None = None) -> CalibrationInput:
        """The file ``path`` as its reader's ``meta`` (a source's or a :class:`radiokit.io.Frames`')
        describes it, no frames counted yet."""
        from datetime import datetime

        from radiokit.io._experiment import FRAMES

        fmt = str(meta.get("format", "unknown"))
        dataset = meta.get("dataset") or (f"/{FRAMES}" if fmt == "experiment" else None)
        try:
            st = os.stat(path)
            size = int(st.st_size)
            modified = datetime.fromtimestamp(st.st_mtime, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        except OSError:  # (read a moment ago: gone since, or never a plain file)
            size = modified = None
        return cls(
            str(path), str(Path(path).resolve()), fmt, dataset, option if dataset else None, 0, 0, size, modified
        )

    def record(self) -> dict:
        """This input as the provenance's JSON object."""
        return asdict(self)


def refuse_unnameable(where: str, names: dict, n_files: int) -> None:
    """Refuse dark and flat files more than a calibration's provenance can name: ``names``, its
    items that name them (``inputs``, and the command's ``dark_files`` and ``flat_files``), whose
    JSON would pass what radiokit reads back (:data:`radiokit._json.MAX_CHARS`); a ValueError of
    one line, ``where`` first, naming ``n_files``, the files (each once: a file's two datasets, or
    one given as darks and flats, are one). The one rule of the command (before it opens a file) and of
    :meth:`Calibration.from_frames` (before it averages a frame). Why: either made the calibration
    and then refused its save (review s53rvoff; from an HDF5 dataset's 4 MB name, s54)."""
    size = len(strict_json.dumps(names))
    if size > strict_json.MAX_CHARS:
        raise ValueError(
            f"{where}: {n_files} dark and flat file(s) would be named in the calibration's provenance in at least "
            f"{size} characters of JSON, past the {strict_json.MAX_CHARS} radiokit reads back; calibrate from fewer "
            "files (or datasets of shorter names), or from one HDF5 stack of their frames"
        )


def _named_frames(darks, flats) -> str:
    """``darks FILE, flats FILE`` for a message on :meth:`Calibration.from_frames`' frames, each
    named where it is :class:`radiokit.io.Frames` of a file (``the darks``, ``the flats`` else)."""

    def one(kind, frames):
        path = getattr(frames, "meta", {}).get("path") if isinstance(getattr(frames, "meta", None), dict) else None
        return f"{kind} {shown(path)}" if path else f"the {kind}"

    return f"{one('darks', darks)}, {one('flats', flats)}"


def _frames_inputs(given: dict, counts: dict) -> list[dict]:
    """The files :meth:`Calibration.from_frames`' darks and flats (``given``, by kind) were read
    from, where they are :class:`radiokit.io.Frames` naming one (``meta["path"]``), as
    ``provenance["inputs"]``; one entry per file and dataset, its frames of each kind
    (``counts``). Plain arrays name none: ``[]``. Why: the README's Python way,
    ``from_frames(read(...), read(...))``, recorded nothing, and ``info`` said of a calibration
    made that minute that it was made before radiokit recorded its inputs (s50rv1). The commands
    record their own (each file of a kind read into one stack)."""
    inputs: dict = {}
    for kind, frames in given.items():
        meta = getattr(frames, "meta", None)
        if not isinstance(meta, dict) or not meta.get("path"):
            continue
        one = inputs.setdefault((meta["path"], meta.get("dataset")), CalibrationInput.of(meta["path"], meta))
        setattr(one, kind, getattr(one, kind) + int(counts[kind]))
    return [one.record() for one in inputs.values()]


def input_lines(provenance: dict) -> list[str]:
    """What a calibration was read from, one line per file, for ``radiokit info``: its
    ``provenance["inputs"]`` (:class:`CalibrationInput`), or, for a calibration made before they
    were recorded, the files it names (``dark_files``, ``flat_files``, ``source``) and that the
    rest is not recorded. The file's JSON is anyone's: what is not as radiokit writes it is said
    as unreadable, never raised. Every text of it as a name prints (:func:`radiokit._names.shown`:
    a newline quoted and escaped, a byte that is not UTF-8 left to the command's output, ``\\xe9``):
    they escaped control characters unquoted and printed such a byte ``\\udce9`` (s51)."""
    from radiokit._names import shown

    inputs = provenance.get("inputs")
    if inputs is None:
        named = [
            f"{what} {', '.join(map(shown, files))}"
            for what, files in (("darks", provenance.get("dark_files")), ("flats", provenance.get("flat_files")))
            if isinstance(files, list) and files
        ]
        if isinstance(provenance.get("source"), str):
            named.append(f"darks and flats of {shown(provenance['source'])}")
        said = "; ".join(named) + " (as given; " if named else "not recorded ("
        return [f"{said}made before radiokit recorded its datasets, sizes and times)"]
    if not isinstance(inputs, list) or not all(isinstance(i, dict) for i in inputs):
        return ["unreadable: provenance inputs is not a list of objects"]
    if not inputs:  # Calibration.from_frames of plain arrays
        return ["arrays, no files (Calibration.from_frames of frames in memory)"]
    lines = []
    for i in inputs:
        # (a hand-made non-text value prints as str() of it: a container's texts are repr'd, escaped)
        i = {k: shown(v) if isinstance(v, str) else v for k, v in i.items()}
        counts = " and ".join(
            f"{i[k]} {k}"
            for k in ("darks", "flats")
            if isinstance(i.get(k), int) and not isinstance(i[k], bool) and i[k]
        )
        where = f"dataset {i['dataset']}" if i.get("dataset") else str(i.get("format", "?"))
        where += f" ({i['option']})" if i.get("option") else ""
        file = f"{i.get('size_bytes')} bytes, modified {i.get('modified')}" if i.get("size_bytes") is not None else ""
        resolved = f"; {i['resolved']}" if i.get("resolved") not in (None, i.get("path")) else ""
        lines.append(f"{i.get('path')}: {where}, {counts or 'no frames'}" + (f"; {file}" if file else "") + resolved)
    return lines


def _provenance(darks, flats, dark_times, flat_times, mask, n_flat_saturated) -> dict:
    """What a calibration was made from, and how many pixels of each defect it found."""
    flags = (PixelFlag.DEAD, PixelFlag.UNDER_RESPONDING, PixelFlag.OVER_RESPONDING, PixelFlag.NOISY, PixelFlag.CLUSTER)
    return {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "software": f"radiokit {__version__}",
        "n_darks": int(darks.shape[0]),
        "n_flats": int(flats.shape[0]),
        "averaging": "median-clipped mean",
        "dark_times": [float(t) for t in dark_times] if dark_times is not None else [],
        "flat_times": [float(t) for t in flat_times] if flat_times is not None else [],
        "dark_noise_counts": _dark_noise(darks),
        "n_flat_saturated": n_flat_saturated,
        "defects": {flag.name.lower(): int(np.count_nonzero(mask & flag)) for flag in flags},
    }


def _frames_say(darks, flats, said) -> dict:
    """What each of the darks' and flats' files says, ``said(meta)`` of a :class:`radiokit.io.Frames`
    (None for an array: it says nothing), by its name, as the ``declared_*`` functions take it."""
    return {
        f"{what} {getattr(f, 'path', '')}": said(f.meta) if hasattr(f, "meta") else None
        for what, f in (("darks", darks), ("flats", flats))
    }


def _frames_scaling(darks, flats) -> dict:
    """The scaling the darks' and flats' :class:`radiokit.io.Frames` share (:func:`declared_scaling`)."""
    return declared_scaling(_frames_say(darks, flats, value_scaling))


def declared_scaling(scalings: dict) -> dict:
    """The scaling the darks' and flats' files share (``scalings``: each file's name and its
    :func:`value_scaling`, None where unscaled); {} where none is. Files scaled otherwise (or only
    some of them) are refused: their values are not one panel's counts, and the dark/flat
    correction cancels only a scaling they share."""
    texts = {name.strip(): (s or {}).get("text", "unscaled") for name, s in scalings.items()}
    if len(set(texts.values())) > 1:
        named = ", ".join(f"{name} {text}" for name, text in texts.items())
        raise ValueError(f"the darks' and flats' files are scaled differently ({named}): not one panel's counts")
    return next((s for s in scalings.values() if s), {})


def _bright_darks(dark_median: float, top: int | None, low: int = 0) -> str | None:
    """What to say of darks whose median is over half the ADC's range, ``low`` to ``top`` (None:
    they are not). A signed ADC's range starts at its bottom (``low``, -2048 of 12 bits): judged
    from 0, darks 2548 counts above it (500) were not bright.

    Why half: the C7942's ~2.2 Me- full well over its ~1100 e- noise (dynamic range ~2000, C7942.md)
    fills its 12-bit range at about 2 counts rms, so the panel's own offset -- a hundred-odd
    counts, +200 after 1 MR of dose -- is a small part of the range. Darks over half of it carry
    light (a leak, the beam on), or the read-out's offset or bit depth is set wrong: either way
    they leave the flats less than half the panel's range."""
    if top is None or dark_median <= (low + top) / 2:
        return None
    span = f"{low}-{top}" if low >= 0 else f"{low} to {top}"
    return (
        f"the darks read {dark_median:.0f} counts (median), over half the ADC's range ({span}), leaving the "
        f"flats {max(top - dark_median, 0):.0f} counts: a C7942's offset is a few hundred; light reached the "
        "panel for the darks (a leak, the beam on) or the read-out's offset or bit depth is set wrong"
    )


def _known_top(top: int | None, given: bool, *averages) -> int | None:
    """``top`` if the caller gave it or the averaged frames reach it (clipped there), else None.

    Why: :func:`adc_top` guesses the smallest top the frames do not exceed, so a 16-bit panel's
    frames that stay under 4095 are guessed 12-bit; the half-range rule (:func:`_bright_darks`)
    against that guess called a 16-bit panel's 2500-count darks bright and blamed them. The
    saturation rules keep the guess (a pixel can only clip at a top it reaches)."""
    if top is None or given or max(float(np.max(a)) for a in averages) >= top:
        return top
    return None


def _blame(
    refusal: str, dark, flat, noise: float | None, th: Thresholds, top: int | None, low: int = 0
) -> CalibrationRefused:
    """The refusal ``refusal`` of these averaged darks and flats, naming the frames at fault.

    A flat reads the panel's dark plus the beam's signal, never less. So flats darker than the
    darks by more than ``eps`` plus five single-frame noise sigmas (``noise``, counts rms) mean the
    darks are not the panel's dark now (light on them, or an offset that drifted): new darks, the
    flats kept and judged again with them. Darks over half the ADC's range (:func:`_bright_darks`)
    leave flats no room whatever their exposure: new darks and flats once the light or offset is
    fixed. Otherwise the flats are at fault, as the refusal says (beam off or blocked, clipped)."""
    d, f = float(np.median(dark)), float(np.median(flat))
    if d - f > th.eps + 5 * (noise or 0.0):  # one dark: eps alone
        return CalibrationRefused(
            f"the darks read {d:.0f} counts (median), brighter than the flats' {f:.0f}: a flat reads at least "
            "the panel's dark, so light reached the panel for the darks (a leak, the beam on) or its offset "
            "drifted since: shield the panel, then take new darks",
            ("darks",),
        )
    bright = _bright_darks(d, top, low)
    if bright:
        return CalibrationRefused(
            f"{bright}; hence {refusal.split(':')[0]} (median {f:.0f}): fix that, then take new darks and flats",
            ("darks", "flats"),
        )
    return CalibrationRefused(refusal, ("flats",))


def judge_frames(darks, flats, *, saturation=None) -> list[str]:
    """Judge darks and flats by the rules a calibration from them applies, before anything else is
    done with them: raises the ValueError :meth:`Calibration.from_frames` would (flats not brighter
    than darks, a flat saturated at the ADC's top, a defect map over :data:`MAX_DEFECTIVE_SHARE`),
    else returns the messages of the :class:`CalibrationWarning` s it would give. Why: the
    acquisition judges its flats as they are taken (acquisition.protocols.compression_series), and
    a second set of rules there would drift from the ones ``radiokit process`` applies later.
    ``saturation``: the panel's ADC top when known (None: inferred, as from_frames does)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CalibrationWarning)
        Calibration.from_frames(darks, flats, saturation=saturation)
    return [str(w.message) for w in caught if issubclass(w.category, CalibrationWarning)]


def judge_darks(darks, *, saturation=None) -> list[str]:
    """Refuse darks that no flat could be brighter than: :meth:`Calibration.from_frames` refuses
    flats whose median ``flat - dark`` is at most ``eps``, and no pixel reads above the ADC's top,
    so darks whose median is within ``eps`` of it are refused (:class:`CalibrationRefused`, the
    darks named) whatever flats follow. Judged right after the darks, that saves the flats'
    X-rays and names the darks, not the flats (a light leak or the beam on for them). Returns what
    to warn of: darks over half the ADC's range (:func:`_bright_darks`), which leave the flats
    little room but are not refused here (the flats may still fit). ``saturation``: the panel's
    ADC top (None: inferred from the darks)."""
    darks = _as_stack(darks, "darks")
    th = Thresholds(saturation=saturation)
    top = adc_top(darks) if th.saturation is None else th.saturation
    if top is None:
        return []
    median = float(np.median(robust_average(darks, clip_sigma=th.clip_sigma)))
    if median >= top - th.eps:
        raise CalibrationRefused(
            f"the darks read {median:.0f} counts (median), at the ADC's top ({top}): no flat can be brighter "
            "than these darks; was the beam on or light reaching the panel for the darks?",
            ("darks",),
        )
    bright = _bright_darks(median, top if saturation is not None else None)  # a guessed top: _known_top
    return [bright] if bright else []
