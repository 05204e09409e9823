"""Compressed DICOM and JPEG files: the compression ratio and read() time of each syntax radiokit decodes.

A C7942-sized (2240 x 2240) 12-bit frame, a smooth field with Poisson noise (a flat-field-like
radiograph: its noise is what a lossless codec cannot remove), written as uncompressed DICOM and in
each lossless syntax by imagecodecs' encoders, then read with ``radiokit.io.read`` (median of
``--reps``); the lossy syntaxes for their error against the counts.

    python benchmarks/bench_codecs.py [--size 2240] [--reps 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import imagecodecs
import numpy as np
from pydicom import uid
from pydicom.encaps import encapsulate

from radiokit.io import read

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dicomdata import grey_dataset

CODECS = {
    "uncompressed": (uid.ExplicitVRLittleEndian, None),
    "JPEG Lossless SV1 (.70)": (uid.JPEGLosslessSV1, lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12)),
    "JPEG-LS lossless (.80)": (uid.JPEGLSLossless, imagecodecs.jpegls_encode),
    "JPEG 2000 lossless (.90)": (
        uid.JPEG2000Lossless,
        lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12),
    ),
    "HTJ2K lossless (.201)": (uid.HTJ2KLossless, lambda f: imagecodecs.htj2k_encode(f, level=0)),
    "JPEG-LS NEAR 2 (.81)": (uid.JPEGLSNearLossless, lambda f: imagecodecs.jpegls_encode(f, level=2)),
    "JPEG 12-bit q90 (.51)": (uid.JPEGExtended12Bit, lambda f: imagecodecs.jpeg8_encode(f, level=90, bitspersample=12)),
}


def _frame(size: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    y, x = np.mgrid[:size, :size] / size
    mean = 600 + 2400 * np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.2)
    return np.clip(rng.poisson(mean), 0, 4095).astype(np.uint16)


def _write(path: Path, frame: np.ndarray, syntax, encode) -> None:
    ds = grey_dataset(syntax, frame.shape, 16, 12)
    if encode is None:
        ds.PixelData = frame.astype("<u2").tobytes()
    else:
        ds.PixelData = encapsulate([encode(frame)])
        ds["PixelData"].VR = "OB"
    ds.save_as(path, enforce_file_format=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    frame = _frame(args.size)
    print(f"{'syntax':<26} {'MB':>6} {'ratio':>6} {'read ms':>8} {'max |err|':>9} {'rms err':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        raw_size = None
        for name, (syntax, encode) in CODECS.items():
            path = Path(tmp) / "f.dcm"
            _write(path, frame, syntax, encode)
            size = path.stat().st_size
            raw_size = raw_size or size
            times = []
            for _ in range(args.reps):
                t = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the lossy ones say so
                    got = read(path).data[0]
                times.append(time.perf_counter() - t)
            err = got.astype(np.int64) - frame
            rms = float(np.sqrt(np.mean(err.astype(float) ** 2)))
            print(
                f"{name:<26} {size / 1e6:6.2f} {raw_size / size:6.2f} {statistics.median(times) * 1e3:8.0f} "
                f"{int(np.abs(err).max()):9d} {rms:8.3f}"
            )


if __name__ == "__main__":
    main()
