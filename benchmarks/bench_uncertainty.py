"""Do the standard errors `radiokit process` reports match the scatter over noise seeds?

A closed-form experiment (no sim/): a flat-topped disc body (line integral ``a_s * 0.5``, its
thickness scaled by 1, 0.95, 0.90 over three steps) holding a small sphere inclusion of radius
5 px whose own line integral does not change (0.3 at its centre in every step), 128 x 128 px,
Poisson counts of a 3000-count flat over a 100-count dark, 8 darks, 8 flats and 8 frames a step.
The ROIs are the pipeline's own on the first seed, then held fixed so that every seed measures
the same pixels. For each domain it prints the mean improvement factor (k = 1) and change ratio
(2 -> 3), their scatter over the seeds, the root-mean-square of the reported standard errors,
and the ratio of the two (1: the standard error is right; above: cautious; below: overconfident).

The closed form: the inclusion does not change, so in line integrals its change equals the
background's body change there and the change ratio is 1; IF(1) in line integrals is 1.

``--blur SIGMA``: each frame's noise (its counts less their mean) blurred by a Gaussian of SIGMA
pixels, as a scintillator's light spread correlates neighbouring pixels (the mean image is not
blurred: the question is the noise's correlation, not the resolution).

Run: ``python benchmarks/bench_uncertainty.py [SEEDS] [--blur SIGMA]`` (default 40 seeds, no blur;
~2-4 s a seed here).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage

from radiokit.io import ExperimentWriter, ImageKey
from radiokit.pipeline import Config, process

SHAPE = (128, 128)
DARK, FLAT = 100.0, 3000.0


def _chord(centre, radius, soft=None):
    rr, cc = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    d = np.hypot(rr - centre[0], cc - centre[1])
    if soft is None:  # a sphere's chord, 1 at its centre
        return np.sqrt(np.clip(radius**2 - d**2, 0, None)) / radius
    return 1.0 / (1 + np.exp((d - radius) / soft))  # a flat-topped disc with a soft edge


def experiment(path: Path, seed: int, frames: int = 8, blur: float = 0.0) -> None:
    rng = np.random.default_rng(seed)
    body = 0.5 * _chord((64, 64), 0.42 * 128, soft=3.0)
    inclusion = 0.3 * _chord((64, 64), 5)

    def counts(mean):
        noisy = rng.poisson(mean).astype(np.float64)
        if blur > 0:
            noisy = mean + ndimage.gaussian_filter(noisy - mean, blur, mode="reflect")
        return np.clip(np.rint(noisy), 0, 4095).astype(np.uint16)

    with ExperimentWriter(path, shape=SHAPE, pixel_size_mm=0.1) as w:
        for _ in range(8):
            w.append(counts(np.full(SHAPE, DARK)), image_key=ImageKey.DARK)
        for _ in range(8):
            w.append(counts(np.full(SHAPE, DARK + FLAT)), image_key=ImageKey.FLAT)
        for step, a in enumerate((1.0, 0.95, 0.90), start=1):
            line_integral = a * body + inclusion
            for _ in range(frames):
                w.append(
                    counts(DARK + FLAT * np.exp(-line_integral)),
                    image_key=ImageKey.PROJECTION,
                    step=step,
                    ratio=0.10 + 0.05 * step,
                )


def main(seeds: int = 40, blur: float = 0.0) -> None:
    rows, rois = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(seeds):
            path = Path(tmp) / f"e{seed}.h5"
            experiment(path, 100 + seed, blur=blur)
            fixed = {} if rois is None else {"inclusion": rois[0], "background": rois[1]}
            cfg = Config(progress=False, report=False, crop_mm=None, cross_check=None, **fixed)
            r = process(path, cfg, out_dir=Path(tmp) / f"o{seed}").results
            if rois is None:
                crop = r["rois"]["crop"]  # back to full-frame pixels, as Config takes them
                rois = tuple(
                    (b[0] + crop[0], b[1] + crop[0], b[2] + crop[2], b[3] + crop[2])
                    for b in (r["rois"]["inclusion"], r["rois"]["background"])
                )
                print("ROIs (full frame):", rois, flush=True)
            rows.append(
                {
                    d: (
                        r["domains"][d]["improvement_factor"]["1"],
                        r["domains"][d]["improvement_factor_se"]["1"],
                        r["change_ratio"]["2->3"][d],
                        (r.get("change_ratio_se") or {}).get("2->3", {}).get(d),
                    )
                    for d in ("log", "negative")
                }
            )
            path.unlink()
            shutil.rmtree(Path(tmp) / f"o{seed}", ignore_errors=True)
    print(f"{'domain':<9} {'quantity':<9} {'n':>3} {'mean':>7} {'scatter':>8} {'rms SE':>8} {'SE/scatter':>10}")
    for d in ("log", "negative"):
        a = np.array([[np.nan if v is None else v for v in row[d]] for row in rows], float)
        for name, value, se in (("IF(1)", a[:, 0], a[:, 1]), ("CR 2->3", a[:, 2], a[:, 3])):
            ok = np.isfinite(value) & np.isfinite(se)
            scatter, rms = value[ok].std(ddof=1), np.sqrt(np.mean(se[ok] ** 2))
            print(
                f"{d:<9} {name:<9} {ok.sum():>3} {value[ok].mean():>7.3f} {scatter:>8.4f} {rms:>8.4f} {rms / scatter:>10.2f}"
            )


if __name__ == "__main__":
    args = sys.argv[1:]
    sigma = float(args[args.index("--blur") + 1]) if "--blur" in args else 0.0
    rest = [a for i, a in enumerate(args) if a != "--blur" and (i == 0 or args[i - 1] != "--blur")]
    main(int(rest[0]) if rest else 40, sigma)
