"""How far dark, flat and constant frames compress in each codec radiokit decodes, and whether a
file of one reads under the default budget (the proportion rule refuses past 1:200 only a frame
over 1 GiB or a read over 4 GiB: radiokit.io._budget).

A C7942-sized (2240 x 2240) uint16 frame: all zero, constant, a dark (offset 100, Gaussian read
noise of 1 and 3 counts) and a flat (Poisson, 3000 counts), each encoded by imagecodecs' encoders,
its ratio printed, then written as a plain file and read by ``radiokit.io.read`` without a budget.

    python benchmarks/bench_codec_dark_ratios.py [--size 2240]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import warnings
from pathlib import Path

import imagecodecs
import numpy as np

from radiokit.io import BUDGET_ENV, FormatError, read

CODECS = {
    "ljpeg SV1": (".jpg", lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12)),
    "JPEG-LS": (".jls", imagecodecs.jpegls_encode),
    "J2K 5/3": (".j2k", lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12)),
    "HTJ2K": (".jph", lambda f: imagecodecs.htj2k_encode(f, level=0)),
    "JPEG12 q90": (".jpg", lambda f: imagecodecs.jpeg8_encode(f, level=90, bitspersample=12)),
}


def frames(size: int) -> dict:
    rng = np.random.default_rng(0)
    shape = (size, size)
    return {
        "all zero": np.zeros(shape, np.uint16),
        "constant 100": np.full(shape, 100, np.uint16),
        "dark 100+N(0,1)": np.clip(np.round(100 + rng.normal(0, 1, shape)), 0, 4095).astype(np.uint16),
        "dark 100+N(0,3)": np.clip(np.round(100 + rng.normal(0, 3, shape)), 0, 4095).astype(np.uint16),
        "flat Poisson 3000": rng.poisson(3000, shape).astype(np.uint16),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=2240)
    args = parser.parse_args()
    os.environ.pop(BUDGET_ENV, None)  # the default budget, as a user has it
    print(f"{'frame':20s}" + "".join(f"{name:>12s}" for name in CODECS))
    with tempfile.TemporaryDirectory() as tmp:
        for label, frame in frames(args.size).items():
            cells = []
            for ext, encode in CODECS.values():
                stream = encode(frame)
                path = Path(tmp) / f"f{ext}"
                path.write_bytes(stream)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    try:
                        read(path)
                        said = ""
                    except FormatError:
                        said = " REFUSED"
                cells.append(f"1:{frame.nbytes / len(stream):.0f}{said}")
            print(f"{label:20s}" + "".join(f"{c:>12s}" for c in cells))


if __name__ == "__main__":
    main()
