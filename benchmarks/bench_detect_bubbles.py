"""Does the background ROI keep off a phantom's air bubbles? ``find_rois`` on a crowded scene.

Run::

    python benchmarks/bench_detect_bubbles.py [--size 2240] [--bubbles 120] [--ring 9 25] [--max-radius 3]

A smooth elliptical body (112 mm across the frame), a denser sphere of 4.8 mm radius 6 mm right of
its centre, a texture of 1 % and white noise of 0.5 % of the line integral, and ``--bubbles`` air
bubbles of 1.5 to ``--max-radius`` mm placed at random ``--ring`` mm from the sphere's centre
(seed 1). Prints the time of :func:`radiokit.measure.find_rois` and the ROIs it chose, or the
one-line refusal when no background fits clear of every structure: 120 bubbles 9-25 mm out leave no
clean place, and the right answer is that refusal (review s43rr3; ``benchmarks/README.md``,
"Then no cap"). ``--bubbles 0`` is the demo-like scene.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage as ndi

from radiokit.measure import find_rois


def scene(n: int, bubbles: int, ring: tuple[float, float], max_radius: float) -> tuple[np.ndarray, float]:
    """The line-integral image (float32) and its pixel size in mm."""
    px = 112.0 / n
    rng = np.random.default_rng(1)
    yy, xx = (np.mgrid[:n, :n] - (n - 1) / 2) * px
    q = 1 - (yy / (0.43 * n * px)) ** 2 - (xx / (0.45 * n * px)) ** 2
    img = 2.5 * np.sqrt(np.clip(q, 0, None))
    img += 0.1 * np.sqrt(np.clip(4.8**2 - (yy**2 + (xx - 6.0) ** 2), 0, None))
    tex = ndi.gaussian_filter(rng.normal(0, 1, (n, n)), 2.0 / px)
    img += 0.01 * tex / tex.std()
    placed = 0
    while placed < bubbles:
        cy, cx = rng.uniform(-40, 40, 2)
        if (cy / 48) ** 2 + (cx / 50) ** 2 > 0.8 or not ring[0] < np.hypot(cy, cx - 6) < ring[1]:
            continue
        r = rng.uniform(1.5, max_radius)
        img -= 0.1 * np.sqrt(np.clip(r**2 - ((yy - cy) ** 2 + (xx - cx) ** 2), 0, None))
        placed += 1
    img += rng.normal(0, 0.005, (n, n))
    return img.astype(np.float32), px


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--bubbles", type=int, default=120)
    ap.add_argument("--ring", type=float, nargs=2, default=(9.0, 25.0), metavar=("MIN_MM", "MAX_MM"))
    ap.add_argument("--max-radius", type=float, default=3.0, help="largest bubble radius, mm")
    args = ap.parse_args(argv)
    img, px = scene(args.size, args.bubbles, tuple(args.ring), args.max_radius)
    t = time.perf_counter()
    try:
        inc, bg = find_rois(img, pixel_size_mm=px)
        said = f"inclusion {inc}, background {bg}"
    except ValueError as exc:  # no background fits: the answer for a crowded ring
        said = f"refused: {exc}"
    print(f"{args.size} px, {args.bubbles} bubbles: find_rois {time.perf_counter() - t:.2f} s; {said}")


if __name__ == "__main__":
    main()
