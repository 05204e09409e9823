"""What realistic frames compress to: the numbers behind ``radiokit.io._budget.BOMB_RATIO``.

Synthetic 2240 x 2240 uint16 frames of the C7942 (darks of 1-2 counts' read noise, a shaded flat,
a constant frame, zeros, a saturated frame with 1 % speckle, sparse photon-counting frames) and frame 0 of each vendor ITEX file
in /work/shared/data, compressed with deflate (with and without TIFF predictor 2), zstd (3, 19),
LZW and LZMA; prints decoded : stored for each. Slow (zstd 19 and LZMA: about 2 minutes).

    python benchmarks/bench_compression_ratios.py
"""

from __future__ import annotations

import glob
import zlib

import imagecodecs
import numpy as np

from radiokit.io import read

ITEX = "/work/shared/data/hamamatsu_itex/*.img"


def frames() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    shape = (2240, 2240)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    shading = 1 - 0.3 * ((xx - 1120) ** 2 + (yy - 1120) ** 2) / 1120**2
    out = {
        "dark (200 +- 2 counts, column pattern)": 200 + rng.normal(0, 2, shape) + rng.normal(0, 3, shape[1])[None],
        "dark (150 +- 1 count)": 150 + rng.normal(0, 1, shape),
        "flat (3000, shaded, +- 3)": 3000 * shading + rng.normal(0, 3, shape),
        "constant 1000": np.full(shape, 1000),
        "zeros": np.zeros(shape),
        "saturated 4095, 1 % at 4000": np.where(rng.random(shape) < 0.01, 4000, 4095),
        # photon counting at low flux: most pixels 0, a few hit once (review s36r3)
        "sparse, 0.2 % of pixels at 1": (rng.random(shape) < 0.002).astype(np.uint16),
        "sparse, 1 % of pixels at 1": (rng.random(shape) < 0.01).astype(np.uint16),
    }
    out = {name: np.round(a).astype(np.uint16) for name, a in out.items()}
    for path in sorted(glob.glob(ITEX)):
        data = read(path).data
        out[f"vendor {path.rsplit('/', 1)[-1]} {data.shape[1]}x{data.shape[2]}"] = np.ascontiguousarray(data[0])
    return out


def predicted(a: np.ndarray) -> np.ndarray:
    """TIFF predictor 2: each pixel less its left neighbour, modulo the word."""
    d = a.astype(np.int32)
    d[:, 1:] -= a[:, :-1].astype(np.int32)
    return d.astype(a.dtype)


def main() -> None:
    codecs = {
        "deflate": lambda a: zlib.compress(a.tobytes(), 6),
        "defl+p2": lambda a: zlib.compress(predicted(a).tobytes(), 9),
        "zstd3": lambda a: imagecodecs.zstd_encode(a.tobytes(), 3),
        "zstd19": lambda a: imagecodecs.zstd_encode(a.tobytes(), 19),
        "lzw": lambda a: imagecodecs.lzw_encode(a.tobytes()),
        "lzma": lambda a: imagecodecs.lzma_encode(a.tobytes()),
    }
    print(f"{'frame':45s} " + " ".join(f"{c:>8s}" for c in codecs))
    for name, a in frames().items():
        ratios = [a.nbytes / len(encode(a)) for encode in codecs.values()]
        print(f"{name[:45]:45s} " + " ".join(f"{r:8.1f}" for r in ratios))


if __name__ == "__main__":
    main()
