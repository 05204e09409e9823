"""The container every reader returns."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radiokit._names import shown

__all__ = ["Frames", "BitDepthWarning", "HalfFloatWarning"]


class BitDepthWarning(UserWarning):
    """Pixel values exceed the detector's ADC range: wrong bit order, byte order or model."""


class HalfFloatWarning(UserWarning):
    """Raw frames stored as float16: counts above 2048 were rounded when written."""


def warn_half_float(path) -> None:
    """Warn that raw frames stored as float16 lost counts when written. Why: float16 holds whole
    numbers exactly only to 2048 (its significand's 11 bits); a C7942's flats at 3000 counts were
    stored rounded to even counts, a 16-bit panel's counts above 65504 as inf, and read without a
    word. Said once a file on the command line (``path``), not at each of its opens."""
    message = HalfFloatWarning(
        f"{shown(path)}: frames stored as float16, which holds whole counts exactly only up to 2048: counts above it "
        "were rounded when written (to even counts up to 4096, to 4 up to 8192 ... to 32 up to 65504; above that "
        "inf); read as stored: store raw counts as uint16 or float32"
    )
    message.path = str(path)
    warnings.warn(message, stacklevel=4)


@dataclass
class Frames:
    """Frames read from one file.

    Attributes
    ----------
    data : ndarray, shape (n, rows, cols)
        Pixels in the file's own dtype and order; row 0 is the first row stored (a TIFF's
        Orientation tag applied: row 0 at the top as viewers show it).
    meta : dict
        Everything else the file says, nested where the file nests it. Always has ``format``.
    path : Path
        The file they came from.
    """

    data: np.ndarray
    meta: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

    @property
    def n(self) -> int:
        return self.data.shape[0]

    def __len__(self) -> int:
        return self.data.shape[0]

    def __repr__(self) -> str:
        return (
            f"Frames({self.meta.get('format', '?')}, n={self.n}, "
            f"shape={self.data.shape[1:]}, dtype={self.data.dtype}, path={str(self.path)!r})"
        )


def _words_as_float32(frame: np.ndarray) -> bool:
    """Whether a 16-bit frame's words, read two at a time, are float32 numbers: a float32 frame
    in a headerless file read as 16-bit words. Evidence needed on (nearly) every pair: the pair
    decodes to a number between about 1e-6 and 1e6 in size and mostly positive (as transmission,
    attenuation or counts are), and the two words of a pair do not look alike (a 16-bit image's
    neighbours do; a float's low word is its mantissa's tail, its high word sign and exponent).
    All-zero pairs carry no evidence either way and are left out."""
    words = np.ascontiguousarray(frame, dtype="<u2").reshape(-1)
    words = words[: words.size - words.size % 2]
    pairs = words.reshape(-1, 2)
    pairs = pairs[(pairs != 0).any(axis=1)]
    if len(pairs) < 16:
        return False
    high = pairs[:, 1]  # little-endian: sign, 8 exponent bits and the mantissa's top in word 2
    exponent = (high >> 7) & 0xFF
    plausible = (exponent >= 127 - 20) & (exponent <= 127 + 19)  # 2**-20 (1e-6) .. 2**20 (1e6)
    positive = (high >> 15) == 0
    differ = np.abs(pairs[:, 0].astype(np.int32) - pairs[:, 1].astype(np.int32)) > 4096
    return bool(np.mean(plausible) >= 0.99 and np.mean(positive) >= 0.9 and np.mean(differ) >= 0.5)


def _msb_aligned(frame: np.ndarray, bits: int) -> bool:
    """Whether a 16-bit frame looks like ``bits``-bit data shifted to the top of its words: the
    low ``16 - bits`` bits 0 in (nearly) every non-zero pixel, which in other data holds for one
    pixel in 2**(16 - bits). (The shifted values always fit: that alone is no evidence.)"""
    low = (1 << (16 - bits)) - 1
    nonzero = frame[frame != 0]
    if nonzero.size < 16:
        return False
    return bool(np.count_nonzero(nonzero & low) <= 0.01 * nonzero.size)


#: what a raw file's reader can do about big-endian words; other formats pass their own
RAW_SWAP_ADVICE = "try byteorder='>' (or '<')"


def bit_depth_cause(frame: np.ndarray, bits: int, *, swap_advice: str = RAW_SWAP_ADVICE) -> str | None:
    """Why a frame holds values above ``2**bits - 1``, when the frame itself shows it, else None.

    Named only on evidence: the words pair up into float32 numbers (a float file read as 16-bit),
    the byte-swapped values fit (byte order), or the low bits are 0 in (nearly) every pixel
    (MSB-aligned data). Shared by :func:`check_bit_depth` and the acquisition's detector folder.
    ``swap_advice`` follows the byte-order cause: only raw reads take ``byteorder=``, so a
    format with a header of its own says what works for it."""
    if frame.dtype.itemsize != 2 or frame.dtype.kind not in "ui" or frame.size == 0:
        return None
    top = (1 << bits) - 1
    # floats first: the swapped words of 0.5 (0x0000, 0x3F00) are 0 and 63, which "fit"
    if _words_as_float32(frame):
        return (
            "its 16-bit words pair up into float32 numbers: the file holds float32 pixels, not the "
            "panel's 16-bit counts; read it with dtype='<f4' and shape=(rows, cols) (--dtype '<f4' --shape ROWS COLS)"
        )
    if int(frame.byteswap().max()) <= top:
        return f"the byte-swapped values fit: the file is big-endian; {swap_advice}"
    if bits < 16 and _msb_aligned(frame, bits):
        return (
            f"the low {16 - bits} bits are 0 in (nearly) every pixel: {bits}-bit data stored MSB-aligned "
            f"(shifted left by {16 - bits}); divide by {1 << (16 - bits)} for ADC counts"
        )
    return None


def _fitting_adc(peak: int) -> str:
    """ "they fit a 14-bit ADC (0..16383): " -- the smallest usual ADC depth (12, 14, 16 bits)
    holding ``peak``, the one radiokit.calibrate.adc_top judges saturation at; "" past 16 bits.
    Why: the warning listed 14- and 16-bit detectors and left the reader to work out which the
    values fit, and so where calibrate and info would count them saturated."""
    bits = next((b for b in (12, 14, 16) if peak <= (1 << b) - 1), None)
    return f"they fit a {bits}-bit ADC (0..{(1 << bits) - 1}): " if bits else ""


def check_bit_depth(path, frame: np.ndarray, bits: int | None, *, swap_advice: str = RAW_SWAP_ADVICE) -> bool:
    """Warn when a frame holds values the ADC cannot produce; whether it warned.

    The warning names a cause only on evidence (:func:`bit_depth_cause`). Otherwise it says what
    the values may mean and gives no advice that would change good data (such as dividing 14-bit
    counts by 16)."""
    if bits is None or frame.dtype.kind not in "ui" or frame.size == 0:
        return False
    top = (1 << bits) - 1
    peak = int(frame.max())
    if peak <= top:
        return False
    cause = bit_depth_cause(frame, bits, swap_advice=swap_advice) or (
        f"{_fitting_adc(peak)}another detector (C9730DK/C9732DK are 14-bit, 0..16383; many cameras 16-bit), data "
        "rescaled before saving, or a wrong geometry, offset or byte order; the values are read as stored"
    )
    message = BitDepthWarning(
        f"{shown(path)}: pixel values up to {peak} exceed the {bits}-bit range 0..{top}; {cause}."
    )
    message.path = str(path)  # for callers that show one warning per file (the command line)
    warnings.warn(message, stacklevel=3)
    return True
