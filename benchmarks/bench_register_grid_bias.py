"""Does rc pull a pair that did not move off the pixel grid? (session 19; measured, not fixed)

Identity pairs of the issue-11 family (``regdata.family_pair`` with a vanishing motion and no
intensity change: the two images differ by their noise alone) and, for contrast, one with a 1 %
local motion; rc ``default`` and ``weak``. Linear interpolation at a fractional offset f averages
neighbouring pixels, so the warped image's noise variance falls by ``((1 - f)^2 + f^2)`` per axis
(to a quarter at half a pixel in both): any similarity that rewards a smaller residual gains by
moving a noisy image off the grid, and a uniform shift costs the smoothness prior nothing.

    python benchmarks/bench_register_grid_bias.py            # 560 px, seed 1 (~1 min)
    python benchmarks/bench_register_grid_bias.py --size 1120 --seed 2

Prints, per case, the mean error of the field (row, col) over the body, its median end-point
error and ``quality.ok``. Table and reading: benchmarks/README.md, "Interpolation pulls a noisy
pair off the pixel grid".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import Case, family_pair

from radiokit.register import register

CASES = (  # (texture, amplitude): texture in line-integral units against a noise of 0.01
    (0.0, 1e-9),
    (0.01, 1e-9),
    (0.03, 1e-9),
    (0.01, 0.01),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    print("| texture / noise | motion | preset | mean error (row, col) px | median EPE px | ok |")
    print("|---|---|---|---|---|---|")
    for texture, amplitude in CASES:
        case = Case(
            size=args.size, texture=texture, noise=0.01, corr=0.1, amplitude=amplitude, intensity=0.0, seed=args.seed
        )
        fixed, moving, d, mask = family_pair(case)
        for preset in ("default", "weak"):
            reg = register(fixed, moving, "rc", preset=preset)
            err = reg.displacement - d
            epe = np.hypot(*err)[mask]
            motion = "none" if amplitude < 1e-6 else f"{100 * amplitude:g} %, L 1/10"
            print(
                f"| {texture / 0.01:g} | {motion} | {preset} | {err[0][mask].mean():+.3f}, {err[1][mask].mean():+.3f} "
                f"| {np.median(epe):.3f} | {reg.quality.ok} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
