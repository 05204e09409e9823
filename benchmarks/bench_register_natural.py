"""Natural images at 2240 through ``auto`` (issue 11, session 16): rich texture of a kind
``regdata`` does not make.

Run (from the repository root)::

    python benchmarks/bench_register_natural.py --split train   # chooses _auto.ABANDON, EXTEND
    python benchmarks/bench_register_natural.py --split test    # reports: camera and moon

A scikit-image picture, grey, scaled to the frame and to 0-1, is ``moving``; ``fixed`` is it
pulled by a motion of 1 % of the frame, times a +-10 % gain across the frame, noise 0.004 on
both (``bench_register.natural_pair``'s recipe); scored on the central 80 %. Two motions: the
smooth one of ``natural_pair`` (``sine``: 2-3 periods across the frame) and ``regdata``'s local
one correlated over a tenth of the frame (``local``; its seed apart between the splits).

TRAINING pictures (the ones ``auto``'s lines were chosen on): astronaut, brick, coffee, rocket,
retina, chelsea, hubble_deep_field, grass, gravel; those of ``bench_register_abandon.MORE`` and
``bench_register_finest.WIDER`` (with :data:`MATPLOTLIB`'s) are TRAINING too, and ``sine2`` is a
TRAINING motion (session 27). TEST: camera, moon (the held-out check of
``bench_register.py --presets natural`` since session 6). ``--split train`` prints, per pair,
the residual's motion halfway through the level before the finest (what ``abandon_px`` reads),
``default`` at its budget and with ``extend`` (:data:`radiokit.register._auto.EXTEND`), ``weak``
and ``auto``; ``--split test`` only ``auto``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import random_motion, score

TRAIN = ("astronaut", "brick", "coffee", "rocket", "retina", "chelsea", "hubble_deep_field", "grass", "gravel")
TEST = ("camera", "moon")
MOTIONS = ("sine", "local")


# pictures bundled with matplotlib (its sample data, offline), by the name ``natural`` takes: a
# photograph, an MRI slice and two elevation maps (smooth relief with fine detail, as moon's)
MATPLOTLIB = {
    "grace_hopper": "grace_hopper.jpg",
    "mri_s1045": "s1045.ima.gz",
    "jacksboro_dem": "jacksboro_fault_dem.npz",
    "topobathy": "topobathy.npz",
}


def _matplotlib_sample(name):
    """The picture ``name`` of :data:`MATPLOTLIB`: an RGB photograph as it is, a map scaled to 0-1."""
    import matplotlib.image
    from matplotlib import cbook

    what = MATPLOTLIB[name]
    if what.endswith(".jpg"):
        return matplotlib.image.imread(cbook.get_sample_data(what))
    if what.endswith(".ima.gz"):  # 256 x 256 big-endian 16-bit (matplotlib's own example reads it so)
        with cbook.get_sample_data(what) as f:
            im = np.frombuffer(f.read(), ">u2").reshape(256, 256)
    else:
        data = cbook.get_sample_data(what)
        im = data["elevation" if "elevation" in data.files else "topo"]
    im = im.astype(np.float64)
    return (im - im.min()) / (im.max() - im.min())


def natural(name, size, motion, split, seed=1, truth=None):
    """``(fixed, moving, truth, mask)`` of the picture ``name`` (see the module docstring);
    ``seed`` the noise's; ``truth`` (2, size, size): this motion instead of ``motion``'s."""
    import cv2
    import skimage.color
    import skimage.data

    rng = np.random.default_rng(seed)
    im = _matplotlib_sample(name) if name in MATPLOTLIB else getattr(skimage.data, name)()
    if isinstance(im, tuple):  # stereo_motorcycle: (left, right, disparity); the left view
        im = im[0]
    if im.ndim == 3:
        im = skimage.color.rgb2gray(im[..., :3]) * 255.0
    elif im.dtype.kind == "f":  # shepp_logan_phantom, MATPLOTLIB's maps: 0-1 already
        im = im * 255.0
    im = cv2.resize(im.astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC) / 255.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    if truth is not None:
        dy, dx = truth
    elif motion == "sine":
        dy = 0.01 * size * np.sin(2 * np.pi * 3 * xx + 1.0) * np.cos(2 * np.pi * 2 * yy)
        dx = 0.01 * size * np.cos(2 * np.pi * 2 * xx) * np.sin(2 * np.pi * 3 * yy + 0.5)
    elif motion == "sine2":  # another smooth motion, its periods swapped (session 27, --pairs sine2)
        dy = 0.01 * size * np.sin(2 * np.pi * 2 * xx + 0.3) * np.cos(2 * np.pi * 3 * yy + 0.7)
        dx = 0.01 * size * np.cos(2 * np.pi * 3 * xx + 0.2) * np.sin(2 * np.pi * 2 * yy + 1.1)
    else:
        dy, dx = random_motion((size, size), np.random.default_rng(101 if split == "train" else 1101), 0.1, 0.01)
    mx, my = (xx * size + dx).astype(np.float32), (yy * size + dy).astype(np.float32)
    fixed = cv2.remap(im, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT) * (1 + 0.1 * xx)
    fixed += 0.004 * rng.standard_normal(im.shape).astype(np.float32)
    moving = im + 0.004 * rng.standard_normal(im.shape).astype(np.float32)
    mask = np.zeros(im.shape, bool)
    mask[size // 10 : -size // 10, size // 10 : -size // 10] = True
    return fixed, moving, np.stack([dy, dx]).astype(np.float32), mask


def _run(pair, **options):
    """``(median EPE, ok, seconds, registration)`` of ``register(..., **options)`` on ``pair``."""
    from radiokit.register import register

    fixed, moving, truth, mask = pair
    t = time.perf_counter()
    reg = register(fixed, moving, "rc", **options)
    return score(reg.displacement, truth, mask)["epe_median"], reg.quality.ok, time.perf_counter() - t, reg


def _cell(v):
    return f"{v[0]:.3f}{'' if v[1] else '!'}"


def row(name, size, motion, split):
    """One pair's line (``!``: ``quality.ok`` False)."""
    pair = natural(name, size, motion, split)
    auto = _run(pair, preset="auto")
    chose = auto[3].options["auto"].preset
    out = f"{name:<18} {motion:<5} auto {_cell(auto)} ({chose}, {auto[2]:.1f} s)"
    if split == "train":
        from radiokit.register._auto import EXTEND

        half = _run(pair, preset="default", levels_skip=1, iterations=(250, 60))[3].quality.residual_motion
        default, extended, weak = (
            _run(pair, preset=p, **o) for p, o in (("default", {}), ("default", {"extend": EXTEND}), ("weak", {}))
        )
        out += (
            f" | halfway {half:.2f} px | default {_cell(default)} ({default[3].quality.iterations} its)"
            f" extended {_cell(extended)} ({extended[3].quality.iterations} its) | weak {_cell(weak)}"
        )
    print(out, flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("train", "test"), default="test")
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--images", nargs="*", help="pictures (default: the split's)")
    args = ap.parse_args(argv)
    for motion in MOTIONS:
        for name in args.images or (TRAIN if args.split == "train" else TEST):
            row(name, args.size, motion, args.split)


if __name__ == "__main__":
    main()
