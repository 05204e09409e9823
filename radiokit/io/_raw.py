"""Headerless raw frames as the C7942's vendor software writes them (16-bit little-endian)."""

from __future__ import annotations

import operator
import os
import sys
from dataclasses import dataclass

import numpy as np

from radiokit.errors import FormatError

__all__ = ["RawPreset", "PRESETS", "DEFAULT_PRESET", "raw_geometry"]


@dataclass(frozen=True)
class RawPreset:
    """A frame geometry of the C7942 family.

    ``rows`` x ``cols`` as stored (the vendor's "width x height" is ``cols x rows``).
    """

    name: str
    rows: int
    cols: int
    binning: int = 1
    bits: int = 12
    pixel_size_mm: float = 0.05

    @property
    def frame_bytes(self) -> int:
        return self.rows * self.cols * 2


def _family() -> dict[str, RawPreset]:
    out = {}
    # The paper's 2240 x 2240, and the two effective areas the manuals give (width 2240).
    for name, rows in (("c7942", 2240), ("c7942-2344", 2344), ("c7942-2368", 2368)):
        for b in (1, 2, 4):
            key = name if b == 1 else f"{name}-{b}x{b}"
            out[key] = RawPreset(key, rows // b, 2240 // b, binning=b, pixel_size_mm=0.05 * b)
    return out


PRESETS: dict[str, RawPreset] = _family()
DEFAULT_PRESET = "c7942"


def _parse_dtype(path, dtype, byteorder) -> np.dtype:
    """``dtype`` (None: 16-bit words, little-endian unless ``byteorder`` says otherwise) in ``byteorder``."""
    if dtype is None:
        return _parse_dtype(path, "u2", byteorder or "<")
    try:
        dt = np.dtype(dtype)
    except TypeError as exc:
        raise FormatError(path, f"dtype={dtype!r} is not a numpy dtype") from exc
    if dt.kind not in "uif":  # an object dtype would take the file's bytes for pointers
        raise FormatError(path, f"dtype={dtype!r}: pixels are integers or real numbers (e.g. '<u2', '<f4')")
    if byteorder is not None:
        order = {"<": "<", "little": "<", ">": ">", "big": ">", "=": "=", "native": "="}.get(byteorder)
        if order is None:
            raise FormatError(path, f"byteorder={byteorder!r}: expected '<', '>', 'little' or 'big'")
        typed = _typed_order(dtype)
        if typed is not None and order in "<>" and typed != order and dt.itemsize > 1:
            # the byteorder won in silence: '<u2' read big-endian
            raise FormatError(
                path,
                f"dtype={dtype!r} and byteorder={byteorder!r} contradict ({_ENDIAN[typed]}-endian against "
                f"{_ENDIAN[order]}-endian): give the byte order once",
            )
        dt = dt.newbyteorder(order)
    return dt


_ENDIAN = {"<": "little", ">": "big"}


def _typed_order(dtype) -> str | None:
    """The byte order ``dtype`` names itself ('<' or '>'), or None where it names none ('u2', a
    native dtype object)."""
    if isinstance(dtype, str):
        native = "<" if sys.byteorder == "little" else ">"
        return {"<": "<", ">": ">", "!": ">", "=": native}.get(dtype.strip()[:1])
    order = getattr(dtype, "byteorder", None)
    return order if order in ("<", ">") else None


def _frame_count(path, n) -> int:
    """Validate an ``n=`` hint: a whole number of frames, at least one."""
    try:
        n = operator.index(n)
    except TypeError:
        raise FormatError(path, f"n={n!r}: expected a whole number of frames") from None
    if n < 1:
        raise FormatError(path, f"n={n}: expected at least one frame")
    return n


def _packed_note(payload: int) -> str:
    """The unbinned panels whose 12-bit-packed frames (two pixels in three bytes, as some
    frame grabbers store them) fill ``payload``: such a file's size also fits 16-bit binned
    frames, and reading it so gives garbage. radiokit has no packed raw reader."""
    fits = [
        (payload // (p.rows * p.cols * 3 // 2), p)
        for p in PRESETS.values()
        if p.binning == 1 and p.bits == 12 and payload % (p.rows * p.cols * 3 // 2) == 0
    ]
    if not fits:
        return ""
    named = " or ".join(f"{k} 12-bit-packed frame{'s' * (k > 1)} of {p.rows}x{p.cols} ({p.name})" for k, p in fits)
    return f"; it also fits {named}, which radiokit does not read: unpack the file to 16-bit words first"


def _preset_for(path, payload: int, preset, panel_shape=None) -> RawPreset:
    """The preset named, else the one the payload's size implies, else the one of those it fits
    whose frames are ``panel_shape`` (see :func:`raw_geometry`)."""
    if preset is not None:
        if preset not in PRESETS:
            raise FormatError(path, f"unknown preset {preset!r}; known: {', '.join(PRESETS)}")
        return PRESETS[preset]
    dividing = [p for p in PRESETS.values() if payload % p.frame_bytes == 0]
    if len(dividing) == 1:
        return dividing[0]
    full = PRESETS[DEFAULT_PRESET]
    if not dividing:
        raise FormatError(
            path,
            f"size {payload} bytes matches no C7942 geometry (one 2240x2240 frame is "
            f"{full.frame_bytes} bytes); pass shape=(rows, cols) or preset= (on the command line --shape ROWS COLS or --preset)"
            + _packed_note(payload),
        )
    # One 2240 x 2240 frame has the bytes of four 2x2-binned and sixteen 4x4-binned ones: the size
    # cannot tell them apart, and the hardware notes ask for inference only where it is unambiguous.
    # The panel's frame shape known from elsewhere (a calibration's) is such a word, where it picks one.
    known = ""
    if panel_shape is not None:
        panel_shape = tuple(int(v) for v in panel_shape)
        same = [p for p in dividing if (p.rows, p.cols) == panel_shape]
        if len(same) == 1:
            return same[0]
        known = f"; the panel's frames are {panel_shape[0]}x{panel_shape[1]} (the calibration's shape), which {'several' if same else 'none'} of these {'are' if same else 'is'}"
    counts = [(payload // p.frame_bytes, p) for p in dividing]
    fits = ", ".join(f"{k} frame{'s' * (k > 1)} of {p.rows}x{p.cols} ({p.name})" for k, p in counts)
    raise FormatError(
        path,
        f"size {payload} bytes is ambiguous, it fits {fits}{known}; name the panel's geometry with preset= or "
        f"shape= (on the command line e.g. --preset {dividing[0].name}, or --shape ROWS COLS)" + _packed_note(payload),
    )


def raw_geometry(
    path, size: int, *, preset=None, shape=None, dtype=None, byteorder=None, offset=0, n=None, panel_shape=None
) -> dict:
    """Decide the geometry of a headerless raw file of ``size`` bytes.

    Rules, in order: an explicit ``shape`` wins; an explicit ``preset`` is used as given; a size
    that is a whole number of frames of exactly one preset is a stack of that preset; a size that
    fits several (one 2240 x 2240 frame is four 2x2-binned frames and sixteen 4x4-binned ones) is
    the one of them whose frames are ``panel_shape`` (rows, cols), the panel's frame shape known
    from elsewhere (the calibration the frames are corrected with), where exactly one is. Else
    :class:`FormatError` names them: geometry is inferred only where nothing leaves a doubt.
    """
    dt = _parse_dtype(path, dtype, byteorder)
    if offset < 0:
        raise FormatError(path, f"offset={offset} is negative")
    if n is not None:
        n = _frame_count(path, n)
    payload = size - offset
    if size == 0:
        raise FormatError(path, "file is empty")
    if payload <= 0:
        raise FormatError(path, f"offset={offset} is at or beyond the end of the {size}-byte file")
    bits = None
    pixel_size_mm = None
    if shape is not None:
        shape = tuple(int(s) for s in np.atleast_1d(shape))
        if len(shape) not in (2, 3) or min(shape) <= 0:
            raise FormatError(path, f"shape={shape}: expected (rows, cols) or (n, rows, cols), all > 0")
        rows, cols = shape[-2:]
        frame_bytes = rows * cols * dt.itemsize
        if len(shape) == 3:
            n = shape[0]
        name = "custom"
    else:
        if dt.itemsize != 2:
            raise FormatError(path, f"presets hold 16-bit words; dtype {dt} needs an explicit shape=")
        p = _preset_for(path, payload, preset, panel_shape)
        name, rows, cols, bits, pixel_size_mm = p.name, p.rows, p.cols, p.bits, p.pixel_size_mm
        frame_bytes = p.frame_bytes
    if n is None:
        if payload % frame_bytes:
            raise FormatError(
                path,
                f"size {payload} bytes is not a whole number of {rows}x{cols} {dt} frames "
                f"({frame_bytes} bytes each): truncated or wrong geometry",
            )
        n = payload // frame_bytes
    elif n * frame_bytes > payload:
        raise FormatError(
            path,
            f"{n} frames of {rows}x{cols} {dt} need {n * frame_bytes} bytes "
            f"after offset {offset}; the file has {payload}: truncated",
        )
    if n == 0:
        raise FormatError(path, f"file holds less than one {rows}x{cols} frame")
    return dict(
        format="raw",
        preset=name,
        n=int(n),
        rows=int(rows),
        cols=int(cols),
        dtype=dt,
        offset=int(offset),
        bits=bits,
        pixel_size_mm=pixel_size_mm,
        file_size=size,
    )


def read_raw_frame(fh, geo: dict, index: int) -> np.ndarray:
    """Read one frame from an open file into a fresh native-order array."""
    dt = geo["dtype"]
    count = geo["rows"] * geo["cols"]
    fh.seek(geo["offset"] + index * count * dt.itemsize, os.SEEK_SET)
    buf = np.empty(count, dtype=dt)
    got = fh.readinto(memoryview(buf).cast("B"))
    if got != buf.nbytes:
        raise FormatError(getattr(fh, "name", "?"), f"frame {index} is truncated ({got} of {buf.nbytes} bytes)")
    out = buf.reshape(geo["rows"], geo["cols"])
    return out if dt.isnative else out.astype(dt.newbyteorder("="))
