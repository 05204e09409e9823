"""Benchmark: radiokit's inclusion detection (``measure._detect_inclusion``) against
``skimage.feature.blob_log`` for its candidates, side by side in one run.

Run (about 20 s; with a 2240 x 2240 ``--experiment`` two minutes more, nearly all of it in
``blob_log`` at full resolution)::

    python benchmarks/bench_detect.py [--sizes 560 1120] [--experiment out/demo/experiment.h5]

For each case: a synthetic dome in line integrals (a compressed breast seen through the plates,
a 9.6 mm sphere, noise 0.005) at ``size`` pixels over 112 mm, or the reference step of an
experiment file (``radiokit.pipeline``'s corrected line integral). Three ways to find the
candidate blobs, each scored by radiokit's quadratic-surround fit:

* ``own``: radiokit, the scale-normalised LoG at each radius on the image block-averaged so that
  sigma is >= 3 px there, the body's edge masked per scale, three peaks per scale;
* ``blob_log full``: ``blob_log`` on the image itself (the LoG only, without scoring: already
  the slowest);
* ``blob_log avg``: ``blob_log`` on the image block-averaged once (the smallest sigma >= 3 px),
  candidates inside the body scored as radiokit does.

Prints seconds, candidate counts and whether the inclusion ROI (``find_rois``'s) is radiokit's.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage as ndi

from radiokit import measure as M


def _dome(n: int, pixel_size_mm: float, seed: int = 0) -> np.ndarray:
    yy, xx = (np.mgrid[:n, :n] - (n - 1) / 2) * pixel_size_mm
    q = 1 - (yy / (0.43 * n * pixel_size_mm)) ** 2 - (xx / (0.45 * n * pixel_size_mm)) ** 2
    thickness = 50 * np.sqrt(np.clip(q, 0, None))
    chord = 2 * np.sqrt(np.clip(4.8**2 - (yy**2 + (xx - 6.0) ** 2), 0, None))
    return 0.05 * thickness + 0.05 * chord + np.random.default_rng(seed).normal(0, 0.005, (n, n))


def _radii(shape, pixel_size_mm):
    small = min(shape)
    r_lo, r_hi = 1.5 / pixel_size_mm, min(12.0 / pixel_size_mm, small / 6)
    return np.geomspace(r_lo, r_hi, max(2, int(np.ceil(np.log2(r_hi / r_lo) * 3)) + 1))


def _blob_log_avg(img, body, pixel_size_mm):
    """blob_log once on the averaged image; the best candidate's half-maximum region, as radiokit."""
    from skimage.feature import blob_log
    from skimage.measure import block_reduce

    radii = _radii(img.shape, pixel_size_mm)
    f = max(1, int(radii[0] / np.sqrt(2) // 3))
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    im = block_reduce(img[:h, :w], f, np.mean) if f > 1 else img
    blobs = blob_log(
        im,
        min_sigma=radii[0] / np.sqrt(2) / f,
        max_sigma=radii[-1] / np.sqrt(2) / f,
        num_sigma=len(radii),
        log_scale=True,
        threshold=0.0,
        overlap=1.0,
        exclude_border=False,
    )
    depth = ndi.distance_transform_edt(np.pad(body, 1))[1:-1, 1:-1]
    best, inside = (-np.inf, None, None), 0
    for rr, cc, s in blobs:
        centre, radius = (rr * f + (f - 1) / 2, cc * f + (f - 1) / 2), s * f * np.sqrt(2)
        if (
            depth[min(int(round(centre[0])), img.shape[0] - 1), min(int(round(centre[1])), img.shape[1] - 1)]
            <= 3 * radius
        ):
            continue
        inside += 1
        score, fit = M._blob_fit(img, body, centre, radius)
        if score > best[0]:
            best = (score, fit, radius)
    _, (resid, (r0, c0), dist), radius = best
    resid = ndi.gaussian_filter(resid, max(1.0, radius / 8), mode="nearest")
    peak = int(np.argmax(np.where(dist <= max(0.5, 1.0 / radius), resid, -np.inf)))
    labels, _ = ndi.label((resid >= resid.flat[peak] / 2) & (dist <= 1.5))
    region = np.zeros(img.shape, bool)
    region[r0 : r0 + resid.shape[0], c0 : c0 + resid.shape[1]] = labels == labels.flat[peak]
    return region, len(blobs), inside


def _case(name, img, pixel_size_mm):
    from skimage.feature import blob_log

    body = M._body(img, 0.2, 2)
    t = time.perf_counter()
    own = M._inscribed_square(M._detect_inclusion(img, body, (pixel_size_mm, pixel_size_mm)), 0.7)
    t_own = time.perf_counter() - t
    t = time.perf_counter()
    region, n_avg, inside = _blob_log_avg(img, body, pixel_size_mm)
    t_avg = time.perf_counter() - t
    avg = M._inscribed_square(region, 0.7)
    radii = _radii(img.shape, pixel_size_mm)
    t = time.perf_counter()
    n_full = len(
        blob_log(
            img,
            min_sigma=radii[0] / np.sqrt(2),
            max_sigma=radii[-1] / np.sqrt(2),
            num_sigma=len(radii),
            log_scale=True,
            threshold=0.0,
            overlap=1.0,
        )
    )
    t_full = time.perf_counter() - t
    print(
        f"{name:<28} own {t_own:6.2f} s | blob_log full {t_full:6.2f} s ({n_full} candidates, not scored) | "
        f"blob_log avg {t_avg:6.2f} s ({n_avg} candidates, {inside} in the body) | "
        f"ROI {'same' if avg == own else f'differs: {avg} against {own}'}"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[560, 1120])
    ap.add_argument("--experiment", help="also the reference step of this experiment file")
    args = ap.parse_args(argv)
    for n in args.sizes:
        _case(f"dome {n} px", _dome(n, 112.0 / n), 112.0 / n)
    if args.experiment:
        from radiokit.pipeline import _load_steps

        steps = _load_steps(args.experiment, False)
        ref = np.asarray(steps.images[-1], np.float64)  # the pipeline's reference (choose_rois)
        _case(f"{args.experiment} step {len(steps.images)}", ref, float(steps.pixel_size_mm))


if __name__ == "__main__":
    main()
