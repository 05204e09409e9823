"""What caps rc on the natural pictures' local motion at 2240 (issue 11, session 24): the lattice, or the
truth's own shape.

Run (from the repository root)::

    python benchmarks/bench_register_floor.py                      # the floors only (~1 min)
    python benchmarks/bench_register_floor.py --register astronaut coffee brick retina
    python benchmarks/bench_register_floor.py --split test --register camera moon   # held out, run once

``bench_register_natural.py``'s local motion is ``regdata.random_motion``: white noise filtered on
a grid 28 px apart (at 2240) and brought to the frame by OpenCV's cubic resize, a cubic convolution
whose second derivative jumps on every line of that grid. rc's finest lattice (``default``'s
24 px, which ``polish`` refits at full resolution) is a C2 cubic B-spline: it cannot follow those
kinks. The floor printed is the median, over the central 80 % (the benchmark's score), of
``|truth - P truth|``, ``P`` the least-squares projection on a lattice of that spacing (the
tensor product's pseudo-inverse, axis by axis), for the TRAINING motion as the benchmark makes
it and for the same coarse noise brought up by a C2 cubic B-spline at the same sample positions
(``smooth``: no kinks, the same statistics). ``--register``: ``auto`` on the named pictures of
``--split`` (``natural``'s recipe and seeds) under either motion, median EPE px.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_natural import natural
from regdata import random_motion, score


def motions(n, split="train"):
    """``{"benchmark": truth, "smooth": truth}`` (2, n, n): ``random_motion``'s field for the
    split's seed (``natural``'s), and the same coarse noise (drawn again here as it draws it)
    upsampled by a C2 cubic B-spline, scaled by the same factor."""
    import cv2
    from scipy import ndimage

    rng = np.random.default_rng(101 if split == "train" else 1101)  # natural()'s seeds
    corr, amp = 0.1, 0.01
    k = max(1, int(corr * n / 8))  # random_motion's coarse grid
    m = -(-n // k)
    d = np.stack([ndimage.gaussian_filter(rng.standard_normal((m, m)), corr * m / 2, mode="wrap") for _ in range(2)])
    cubic = np.stack([cv2.resize(c.astype(np.float32), (n, n), interpolation=cv2.INTER_CUBIC) for c in d])
    pos = (np.arange(n) + 0.5) / k - 0.5  # cv2.resize's sample positions on the coarse grid
    yy, xx = np.meshgrid(pos, pos, indexing="ij")
    spline = np.stack([ndimage.map_coordinates(c, [yy, xx], order=3, mode="mirror") for c in d])
    scale = amp * n / np.sqrt((cubic * cubic).sum(axis=0)).max()
    benchmark = random_motion((n, n), np.random.default_rng(101 if split == "train" else 1101), corr, amp)
    return {"benchmark": benchmark, "smooth": (spline * scale).astype(np.float32)}


def floor(truth, spacing, mask):
    """Median ``|truth - P truth|`` over ``mask``, ``P`` the least-squares fit by rc's lattice."""
    from radiokit.register._bspline import BSplineField

    Br, Bc, _, _ = BSplineField(truth.shape[1:], spacing).matrices(1)
    Br, Bc = (b.toarray().astype(np.float64) for b in (Br, Bc))
    Pr, Pc = np.linalg.pinv(Br), np.linalg.pinv(Bc)
    fit = np.stack([Br @ (Pr @ t.astype(np.float64) @ Pc.T) @ Bc.T for t in truth])
    return float(np.median(np.sqrt(((fit - truth) ** 2).sum(axis=0))[mask]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--spacings", type=float, nargs="+", default=[24, 16, 12])
    ap.add_argument("--register", nargs="*", default=[], help="pictures of --split to register under both motions")
    ap.add_argument("--split", choices=["train", "test"], default="train", help="the motion's seed and the pictures'")
    args = ap.parse_args(argv)
    n = args.size
    mask = np.zeros((n, n), bool)
    mask[n // 10 : -n // 10, n // 10 : -n // 10] = True
    truths = motions(n, args.split)
    for kind, t in truths.items():
        cells = ", ".join(f"{s:g} px {floor(t, s, mask):.4f}" for s in args.spacings)
        print(f"lattice floor, {args.split.upper()} local motion ({kind}): {cells}", flush=True)
    from radiokit.register import register

    for name in args.register:
        for kind, t in truths.items():
            fixed, moving, _, m = natural(name, n, "local", args.split, truth=t)
            t0 = time.perf_counter()
            reg = register(fixed, moving, "rc", preset="auto")
            e = score(reg.displacement, t, m)["epe_median"]
            flag = "" if reg.quality.ok else "!"
            print(
                f"{name:<12} {kind:<9} auto {e:.4f}{flag} ({reg.options['auto'].preset}, {time.perf_counter() - t0:.1f} s)"
            )


if __name__ == "__main__":
    main()
