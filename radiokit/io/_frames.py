"""The container every reader returns."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Frames", "BitDepthWarning"]


class BitDepthWarning(UserWarning):
    """Pixel values exceed the detector's ADC range: wrong bit order, byte order or model."""


@dataclass
class Frames:
    """Frames read from one file.

    Attributes
    ----------
    data : ndarray, shape (n, rows, cols)
        Pixels in the file's own dtype and order; row 0 is the first row stored.
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


def check_bit_depth(path, frame: np.ndarray, bits: int | None) -> bool:
    """Warn when a frame holds values the ADC cannot produce; whether it warned."""
    if bits is None or frame.dtype.kind not in "ui" or frame.size == 0:
        return False
    top = (1 << bits) - 1
    peak = int(frame.max())
    if peak <= top:
        return False
    hint = ""
    if frame.dtype.itemsize == 2:
        swapped = int(frame.byteswap().max())
        if swapped <= top:
            hint = " The byte-swapped values fit: try byteorder='>' (or '<')."
        elif int(frame.max() >> 4) <= top:
            hint = " Values look shifted left by 4 bits (MSB-aligned 12-bit data)."
    warnings.warn(
        f"{path}: pixel values up to {peak} exceed the {bits}-bit range 0..{top}; "
        f"wrong bit order, byte order, or another detector model (C9730DK/C9732DK are 14-bit).{hint}",
        BitDepthWarning,
        stacklevel=3,
    )
    return True
