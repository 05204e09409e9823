"""Per-call time of ``roi_mean_se`` before and after session 44's speed-up, side by side.

The old implementation is the frozen copy kept as the reference in
``tests/test_roi_se_equivalence.py``. A 512 x 512 image of Gaussian noise, white or blurred by
1.5 px (correlated noise grows the window and runs the lags twice), a centred square ROI of 16, 64
and 256 px a side. Prints the best of 5 repeats of the mean time a call, and the ratio old / new.

Run: ``python benchmarks/bench_roi_se.py`` (~10 s).
"""

from __future__ import annotations

import sys
import timeit
from pathlib import Path

import numpy as np
from scipy import ndimage

from radiokit.measure import ROI, roi_mean_se

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_roi_se_equivalence import _old_roi_mean_se


def main() -> None:
    rng = np.random.default_rng(44)
    print(f"{'noise':>10} {'ROI px':>6} {'old ms':>7} {'new ms':>7} {'old/new':>7}")
    for blur in (0.0, 1.5):
        img = rng.normal(100.0, 5.0, (512, 512))
        if blur:
            img = ndimage.gaussian_filter(img, blur)
        for side in (16, 64, 256):
            r0 = (512 - side) // 2
            roi = ROI(r0, r0 + side, r0, r0 + side)
            assert roi_mean_se(img, roi) == _old_roi_mean_se(img, roi) or np.isclose(
                roi_mean_se(img, roi), _old_roi_mean_se(img, roi), rtol=1e-12, atol=0
            )
            n = max(3, 200 // side)
            t = {
                name: min(timeit.repeat(lambda f=f, img=img, roi=roi: f(img, roi), number=n, repeat=5)) / n * 1e3
                for name, f in (("old", _old_roi_mean_se), ("new", roi_mean_se))
            }
            label = f"blur {blur:g}" if blur else "white"
            print(f"{label:>10} {side:>6} {t['old']:>7.2f} {t['new']:>7.2f} {t['old'] / t['new']:>7.2f}")


if __name__ == "__main__":
    main()
