"""Do the ROIs lie where the motion was observed? The window's map against a pinned one.

Run::

    python benchmarks/bench_roi_pinned.py [--seeds 3] [--preset fast] [--cube]

The confidence map's window (a Gaussian of the lattice spacing, cut at two) lets a strong edge
call a featureless band up to ~45 px beside it "observed", while the field there drifts as far as
where nothing is observed (review s42rep). ``observability(..., pinned=True)`` adds a map
observed only where structure above the noise lies within ``_confidence.PINNED_REACH``
spacings. This script prints, for both maps:

1. the reviewer's slab (200 px, a denser disc of radius 30, Poisson counts of a 3000-count beam,
   4 frames a step, no motion): the ROIs' observed shares, the field's median error in them, and
   the median error of rc against the distance from the disc's edge (the curve the reach is read
   from), for ``fast`` and ``default``;
2. textured pairs (``regdata.analytic_pair`` and the family at 320 px, texture-to-noise 0.3-10):
   two interior ROIs' observed shares and the field's error there;
3. with ``--cube``, tests/test_pipeline.py's simulated gel cube (560 px, an 8 mm sphere)
   through ``radiokit process`` (default preset, whole frame): each ROI's share in both maps of
   the main pair and the field's end-point error there (``PINNED_REACH`` 0.5, 1 and 1.5).
(``benchmarks/README.md``, "Featureless ROIs beside a strong edge".)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import Case, analytic_pair, family_pair

from radiokit.register import _confidence as C
from radiokit.register import register, roi_observed

INCLUSION = (85, 115, 85, 115)  # the review's: 9-30 px inside the disc's edge
BACKGROUND = (85, 115, 20, 50)  # 20-50 px outside it
BANDS = ((-30, -20), (-20, -10), (-10, -3), (-3, 3), (3, 6), (6, 10), (10, 15), (15, 20), (20, 30), (30, 45))


def slab_pair(seed, size=200, radius=30.0, step=0.39, frames=4):
    """The review's slab: ``(fixed, moving, distance from the disc's edge)``; line integrals of a
    slab thinned by an eighth between the steps (no motion), a disc ``step`` denser."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    dist = np.hypot(yy - (size - 1) / 2, xx - (size - 1) / 2) - radius
    out = []
    for mu_t in (2.25, 2.0):
        counts = 3000.0 * np.exp(-(mu_t + step * (dist <= 0)))
        mean = np.mean([rng.poisson(counts) for _ in range(frames)], axis=0)
        out.append((-np.log(mean / 3000.0)).astype(np.float32))
    return out[0], out[1], dist


def maps(fixed, moving, spacing=24.0):
    """``(window map, pinned map)``: the window's is the pinned one at a reach of the window's cut."""
    ob = C.observability(fixed, spacing, moving=moving, pinned=True)
    return ob.confidence, ob.pinned


def _share(conf, roi):
    return roi_observed(conf, roi)


def _box_err(err, roi):
    r0, r1, c0, c1 = roi
    return float(np.median(err[r0:r1, c0:c1]))


def slab(seeds, presets):
    print("## the review's slab (200 px, disc radius 30, step 11.5x the noise, no motion)")
    print("| seed | preset | inclusion obs. window -> pinned | error | background obs. window -> pinned | error |")
    print("|---|---|---|---|---|---|")
    curves = {p: [] for p in presets}
    for seed in seeds:
        f, m, dist = slab_pair(seed)
        win, pin = maps(f, m)
        for preset in presets:
            reg = register(f, m, "rc", preset=preset)
            err = np.hypot(*reg.displacement)
            curves[preset].append([float(np.median(err[(dist >= a) & (dist < b)])) for a, b in BANDS])
            print(
                f"| {seed} | {preset} | {_share(win, INCLUSION):.2f} -> {_share(pin, INCLUSION):.2f} | "
                f"{_box_err(err, INCLUSION):.2f} | {_share(win, BACKGROUND):.2f} -> {_share(pin, BACKGROUND):.2f} | "
                f"{_box_err(err, BACKGROUND):.2f} |"
            )
        for name, c in (("window", win), ("pinned", pin)):
            seen = (c >= 0.5) & (dist > 0)
            far = float(dist[seen].max()) if seen.any() else float("nan")
            print(f"seed {seed}: {name} map, farthest observed pixel outside the edge {far:.0f} px")
    print("\nmedian |error| (px) against the distance from the disc's edge (px; negative: inside), median over seeds")
    print("| preset | " + " | ".join(f"{a}..{b}" for a, b in BANDS) + " |")
    print("|---|" + "---|" * len(BANDS))
    for preset, rows in curves.items():
        print(f"| {preset} | " + " | ".join(f"{v:.2f}" for v in np.median(rows, axis=0)) + " |")


def textured(seeds, preset):
    print(f"\n## textured pairs (rc {preset}): two interior ROIs' observed share, window -> pinned, and error (px)")
    print("| pair | ROI A obs. | err | ROI B obs. | err | object obs. window -> pinned |")
    print("|---|---|---|---|---|---|")
    for seed in seeds:
        cases = [("analytic 256 tex0.08/noise0.01", lambda s=seed: analytic_pair(size=256, seed=s))]
        for t in (0.003, 0.01, 0.03, 0.1):
            case = Case(size=320, texture=t, noise=0.01, corr=0.1, seed=1000 + seed)
            cases.append((f"family 320 tex{t:g}/noise0.01", lambda c=case: family_pair(c)))
        for label, make in cases:
            f, m, truth, mask = make()
            n = f.shape[0]
            a = (int(0.35 * n), int(0.35 * n) + 30, int(0.35 * n), int(0.35 * n) + 30)
            b = (int(0.55 * n), int(0.55 * n) + 30, int(0.55 * n), int(0.55 * n) + 30)
            reg = register(f, m, "rc", preset=preset)
            err = np.hypot(*(reg.displacement - truth))
            ob = C.observability(f, 24.0, moving=m, pinned=True)
            obj = ob.object
            print(
                f"| {label} s{seed} | {_share(ob.confidence, a):.2f} -> {_share(ob.pinned, a):.2f} | "
                f"{_box_err(err, a):.2f} | {_share(ob.confidence, b):.2f} -> {_share(ob.pinned, b):.2f} | "
                f"{_box_err(err, b):.2f} | {np.mean(ob.confidence[obj] >= 0.5):.2f} -> {np.mean(ob.pinned[obj] >= 0.5):.2f} |"
            )


def cube(reaches=(0.5, 1.0, 1.5)):
    """tests/test_pipeline.py's gel cube through process(): each ROI's share in both maps of the
    main pair (the whole frame registered and kept) and the field's end-point error there."""
    import tempfile

    from radiokit.pipeline import Config, process
    from sim.lab import simulate_experiment
    from sim.scene import Body, Inclusion, Material, block_scene

    scene = block_scene(size_mm=20.0, E_kpa=5.0, nu=0.495, ratios=(0.15, 0.20, 0.25))
    gel = Material("gel", "neo-hookean", E_kpa=5.0, nu=0.495, attenuation_per_cm=0.5)
    scene.body = Body("box", size_mm=(20.0, 20.0, 20.0), material=gel)
    stiff = Material("stiff", "linear", E_kpa=30.0, nu=0.495, attenuation_per_cm=1.0)
    scene.inclusions = [Inclusion("sphere", centre_mm=(0.0, 0.0, 0.0), diameter_mm=8.0, material=stiff)]
    scene.mesh.size_inclusion_mm, scene.mesh.size_far_mm = 1.5, 4.0
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "cube.h5"
        simulate_experiment(scene, path, n_darks=6, n_flats=6, frames_per_step=2, progress=False)
        res = process(path, Config(progress=False, report=False, crop_mm=None), out_dir=Path(d) / "out")
    rec, im = res.record, res.images
    moving, reference = (rec.steps.index(int(s)) for s in rec.main_pair.split("->"))
    f, m = im.steps[reference], im.steps[moving]
    print(f"\n## the simulated gel cube (tests/test_pipeline.py), main pair {rec.main_pair}, ROIs {rec.rois.to_json()}")
    print(
        "| ROI | field's median EPE (px) | window map | " + " | ".join(f"pinned, reach {r:g}" for r in reaches) + " |"
    )
    print("|---|---|---|" + "---|" * len(reaches))
    shares, kept = {}, C.PINNED_REACH
    for r in reaches:
        C.PINNED_REACH = r
        ob = C.observability(f, 24.0, moving=m, pinned=True)
        shares[r] = ob
    for name, roi in (("inclusion", rec.rois.inclusion), ("background", rec.rois.background)):
        r0, r1, c0, c1 = roi
        epe = float(np.median(im.epe_map[r0:r1, c0:c1]))
        win = _share(shares[reaches[0]].confidence, roi)
        print(
            f"| {name} | {epe:.2f} | {win:.2f} | "
            + " | ".join(f"{_share(shares[r].pinned, roi):.2f}" for r in reaches)
            + " |"
        )
    C.PINNED_REACH = kept


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--preset", default="fast", help="rc's preset for the textured pairs")
    ap.add_argument("--cube", action="store_true", help="also the simulated gel cube through process() (~1 min)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    print(f"PINNED_REACH {C.PINNED_REACH} spacings (map spacing 24 px: reach {C.PINNED_REACH * 24:g} px)\n")
    slab(range(1, args.seeds + 1), ("fast", "default"))
    textured(range(1, min(args.seeds, 2) + 1), args.preset)
    if args.cube:
        cube()
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
