"""Registration benchmark data: image pairs with their true pull displacement, and scoring.

Every pair is ``(fixed, moving, truth, mask)``: float32 ``(rows, cols)`` images, a float32
``(2, rows, cols)`` pull field in pixels, (row, col) order, with ``moving(x + truth(x))``
matching ``fixed(x)`` (radiokit's convention), and a bool mask of the object where errors are
scored.

``analytic_pair`` (any size, 2240 x 2240 in about 5 s): a phantom-like line-integral image
(an elliptical body's chord, faint texture, a few denser inclusions), a smooth random warp ``d``
(low-order sine modes, largest ``|d|`` exactly ``displacement_frac`` x size) and::

    fixed(x) = moving(x + d(x)) changed in intensity + noise

where ``moving(x + d(x))`` is the cubic-spline interpolant of ``moving`` (so the truth holds
exactly, to float32 rounding, before the intensity change and noise), and the intensity change
is a slow smooth field ``s(x)`` with ``max |s| = 1`` (one or two cycles across the frame):

- ``kind="thinning"``: the line integral scaled by ``1 + intensity_change * s`` (the body gets
  thinner along the beam as it is compressed);
- ``kind="gain"``: transmission multiplied by ``1 + intensity_change * s``, i.e.
  ``- ln(1 + intensity_change * s)`` added to the line integral (a stale flat field).

Noise is Gaussian, standard deviation ``noise`` in line-integral units (the body's line
integral peaks near 2.2, transmission ~ 0.1), independent in both images.

``sim_pair`` reads (or first writes) a simulated experiment (``sim.lab.simulate_experiment``):
fixed = the most compressed step, moving = an earlier step, truth = the stored field; the
noise-free line integrals, or with ``noisy=True`` the raw frames corrected with the file's own
darks and flats (``radiokit.calibrate.Calibration``); optionally block-averaged to a smaller size.

``family`` / ``family_pair`` (issue 11): nearly textureless gel phantoms -- a smooth body with a
denser disc, texture stated against the noise, motion by correlation length and amplitude or
physically shaped, both intensity changes, Gaussian or Poisson-like noise, line-integral or
transmission domain -- on disjoint ``TRAIN_SEEDS`` (choose presets) and ``TEST_SEEDS`` (report).

``score`` gives the end-point error median, 95th percentile and mean inside the mask, and the
folds (pixels of the mask where ``det J <= 0``); ``evaluate`` runs a method on a pair, timed.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

__all__ = [
    "analytic_pair",
    "sim_pair",
    "score",
    "evaluate",
    "smooth_field",
    "phantom",
    "Case",
    "family",
    "family_pair",
    "family_thinning",
    "gel_phantom",
    "block_mean",
    "TRAIN_SEEDS",
    "TEST_SEEDS",
]

# the body: an ellipse centred in the frame, semi-axes as fractions of the frame (cols, rows)
_BODY = (0.40, 0.346)


def smooth_field(shape, rng, cycles=2.0, n_modes=6) -> np.ndarray:
    """A smooth random field on ``shape``, ``max |f| = 1``: ``n_modes`` plane sine waves with
    at most ``cycles`` periods across the frame (wave vectors drawn in the disc of that radius,
    amplitudes falling as 1/(1 + |k|)). Evaluated separably: cheap at 2240 x 2240."""
    rows, cols = shape
    y = np.arange(rows) / rows
    x = np.arange(cols) / cols
    out = np.zeros(shape, np.float64)
    for _ in range(int(n_modes)):
        r = cycles * np.sqrt(rng.uniform(0.05, 1.0))
        a = rng.uniform(0, 2 * np.pi)
        ky, kx = r * np.sin(a), r * np.cos(a)
        amp = rng.standard_normal() / (1 + r)
        py = 2 * np.pi * ky * y + rng.uniform(0, 2 * np.pi)
        px = 2 * np.pi * kx * x
        # sin(py + px) = sin py cos px + cos py sin px
        out += amp * (np.outer(np.sin(py), np.cos(px)) + np.outer(np.cos(py), np.sin(px)))
    return out / np.abs(out).max()


def _ellipse_r2(n, cx=0.5, cy=0.5, ax=_BODY[0], ay=_BODY[1]):
    y = (np.arange(n)[:, None] + 0.5) / n
    x = (np.arange(n)[None, :] + 0.5) / n
    return ((x - cx) / ax) ** 2 + ((y - cy) / ay) ** 2


def phantom(size, rng, texture=0.08, n_inclusions=3):
    """``(image, body)``: a line-integral-like image (float32, peak ~2.2) and its body mask.

    The body is an ellipse's chord ``2 sqrt(1 - r^2)``; ``texture`` is the relative amplitude of
    band-limited noise (scale size/150: fibre-like structure that makes the problem well
    posed); inclusions are Gaussian blobs of 3-6 % of the frame, 10-25 % denser, inside the body.
    Slightly blurred (sigma 1 px), like a detector's point spread."""
    n = int(size)
    r2 = _ellipse_r2(n)
    body = r2 < 1
    img = 2.0 * np.sqrt(np.clip(1 - r2, 0, None))
    if texture:
        t = ndimage.gaussian_filter(rng.standard_normal((n, n)).astype(np.float32), n / 150)
        img *= 1 + texture * t / t.std()
    y = (np.arange(n)[:, None] + 0.5) / n
    x = (np.arange(n)[None, :] + 0.5) / n
    for _ in range(int(n_inclusions)):
        rr, aa = 0.6 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        cx, cy = 0.5 + rr * _BODY[0] * np.cos(aa), 0.5 + rr * _BODY[1] * np.sin(aa)
        w = rng.uniform(0.03, 0.06)
        img += rng.uniform(0.2, 0.5) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w)) * body
    img = ndimage.gaussian_filter(img.astype(np.float32), 1.0)
    return img, body


def analytic_pair(
    size=1120, displacement_frac=0.01, intensity_change=0.10, noise=0.01, seed=0, kind="thinning", texture=0.08
):
    """``(fixed, moving, truth, mask)`` at ``size`` x ``size`` (see the module docstring).

    ``displacement_frac``: the largest ``|truth|`` over the frame, as a fraction of ``size``.
    ``intensity_change``: amplitude of the slow multiplicative change (0.10: +-10 %).
    ``noise``: Gaussian noise, line-integral units, in both images. The mask is the body shrunk
    by 3 % of the frame (the body's edge, where the chord's slope is infinite, is left out)."""
    if kind not in ("thinning", "gain"):
        raise ValueError(f"kind={kind!r}: expected 'thinning' or 'gain'")
    if not 0 <= intensity_change < 1:
        raise ValueError(f"intensity_change={intensity_change}: expected 0 <= change < 1")
    n = int(size)
    rng = np.random.default_rng(seed)
    moving, body = phantom(n, rng, texture=texture)
    d = np.stack([smooth_field((n, n), rng, cycles=1.5), smooth_field((n, n), rng, cycles=1.5)])
    d *= displacement_frac * n / np.sqrt((d * d).sum(axis=0)).max()
    d = d.astype(np.float32)
    rr, cc = np.mgrid[0:n, 0:n].astype(np.float32)
    fixed = ndimage.map_coordinates(moving, [rr + d[0], cc + d[1]], order=3, mode="nearest").astype(np.float32)
    del rr, cc
    s = smooth_field((n, n), rng, cycles=1.0, n_modes=4).astype(np.float32)
    if kind == "thinning":
        fixed *= 1 + intensity_change * s
    else:
        fixed -= np.log1p(intensity_change * s)
    if noise:
        fixed += noise * rng.standard_normal((n, n), dtype=np.float32)
        moving = moving + noise * rng.standard_normal((n, n), dtype=np.float32)
    mask = _ellipse_r2(n, ax=_BODY[0] - 0.03, ay=_BODY[1] - 0.03) < 1
    return fixed, moving.astype(np.float32), d, mask


# -- simulated experiments ---------------------------------------------------------------------


def _simulated_file(scene, cache_dir):
    """An experiment file for ``scene`` (Scene, preset name or TOML), simulated once and cached
    under ``cache_dir`` by the hash of the scene's TOML."""
    from sim.lab import simulate_experiment
    from sim.scene import load_scene

    sc = load_scene(scene)
    key = hashlib.sha1(sc.to_toml().encode()).hexdigest()[:12]
    path = Path(cache_dir) / f"{sc.name}-{key}.h5"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.h5")
        simulate_experiment(sc, tmp, overwrite=True, progress=False)
        tmp.replace(path)
    return path


def block_mean(a, k):
    """Mean over ``k`` x ``k`` blocks of the last two axes (trailing rows and columns that do not
    fill a block dropped); float32."""
    from skimage.measure import block_reduce

    if k == 1:
        return a
    r, c = (a.shape[-2] // k) * k, (a.shape[-1] // k) * k
    a = np.asarray(a)[..., :r, :c]
    return block_reduce(a, (1,) * (a.ndim - 2) + (k, k), np.mean, func_kwargs={"dtype": np.float64}).astype(np.float32)


def _corrected(path, steps):
    """Noisy line integrals of ``steps`` (1-based): each step's raw projections corrected with
    the file's darks and flats, averaged over the step's frames."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames
    from radiokit.io import ImageKey, open_frames

    cal = Calibration.from_experiment(path)
    out = {}
    with open_frames(path) as src:
        keys = np.asarray(src.meta["image_key"])
        step = np.asarray(src.meta["step"])
        for s in steps:
            idx = np.flatnonzero((keys == ImageKey.PROJECTION) & (step == s))
            if idx.size == 0:
                raise ValueError(f"{path}: no projection of step {s}")
            out[s] = np.mean([correct_frames(cal, src[i], domain="log") for i in idx], axis=0).astype(np.float32)
    return out


def sim_pair(
    path_or_scene, *, fixed_step=None, moving_step=1, noisy=False, size=None, erode=0.01, cache_dir="out/regdata_cache"
):
    """``(fixed, moving, truth, mask)`` from a simulated experiment.

    ``path_or_scene``: an experiment file written by ``sim.lab.simulate_experiment`` (``radiokit
    sim run``), or a scene (a :class:`sim.scene.Scene`, preset name such as ``"seed-breast"``,
    or TOML) to simulate first (cached in ``cache_dir``; a full-size scene takes about a minute).
    ``fixed_step``: default the last (most compressed); ``moving_step``: default 1, the least
    compressed (the largest motion), or negative counting back from ``fixed_step`` (-1: the step
    before, the paper's pair). Steps are 1-based as in the file.
    ``noisy``: use the raw frames corrected with the file's darks and flats (photon noise,
    detector defects filled) instead of the noise-free line integrals.
    ``size``: block-average images and field by the integer factor ``rows // size`` (the field
    divided by it, in pixels of the smaller grid).
    The mask: where the fixed line integral exceeds 5 % of its maximum (the body), eroded by
    ``erode`` x the frame's size, and where the truth is defined (non-zero on the body)."""
    import cv2
    import h5py

    x = path_or_scene
    if isinstance(x, Path) or (
        isinstance(x, str) and "\n" not in x and (x.endswith((".h5", ".hdf5", ".nxs")) or os.path.exists(x))
    ):
        p = Path(x)
    else:
        p = _simulated_file(x, cache_dir)
    with h5py.File(p, "r") as h5:
        g = h5["entry/simulation"]
        n_steps = g["line_integral"].shape[0]
        b = n_steps if fixed_step is None else int(fixed_step)
        a = int(moving_step) if int(moving_step) > 0 else b + int(moving_step)  # -1: the step before
        if not 1 <= a < b <= n_steps:
            raise ValueError(f"steps moving={a}, fixed={b}: expected 1 <= moving < fixed <= {n_steps}")
        truth = g[f"displacement/step{a}_to_step{b}"][()].astype(np.float32)
        if noisy:
            li = _corrected(p, (a, b))
            fixed, moving = li[b], li[a]
        else:
            fixed = g["line_integral"][b - 1].astype(np.float32)
            moving = g["line_integral"][a - 1].astype(np.float32)
        clean = g["line_integral"][b - 1]
    k = 1 if size is None else max(1, fixed.shape[0] // int(size))
    fixed, moving, clean = (block_mean(x, k) for x in (fixed, moving, clean))
    truth = block_mean(truth, k) / k
    body = (clean > 0.05 * clean.max()).astype(np.uint8)
    r = max(1, int(round(erode * max(body.shape))))
    mask = cv2.erode(body, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))).astype(bool)
    return fixed, moving, truth, mask


# -- scoring ------------------------------------------------------------------------------------


def score(displacement, truth, mask) -> dict:
    """End-point error ``|d - truth|`` (pixels) inside ``mask``: median, 95th percentile, mean;
    and folds, the pixels of ``mask`` where ``det J <= 0``."""
    from radiokit.register import jacobian_determinant

    d = np.asarray(displacement, np.float32)
    mask = np.asarray(mask, bool)
    e = np.sqrt(((d - truth) ** 2).sum(axis=0))[mask]
    return {
        "epe_median": float(np.median(e)),
        "epe_p95": float(np.percentile(e, 95)),
        "epe_mean": float(e.mean()),
        "folds": int((jacobian_determinant(d)[mask] <= 0).sum()),
    }


def evaluate(method, pair, **options) -> dict:
    """Register ``pair`` = ``(fixed, moving, truth, mask)`` with ``method`` (a name of
    ``radiokit.register.METHODS``); its :func:`score`, ``seconds`` (wall) and ``ok``."""
    from radiokit.register import register

    fixed, moving, truth, mask = pair
    t = time.perf_counter()
    reg = register(fixed, moving, method, **options)
    seconds = time.perf_counter() - t
    return dict(score(reg.displacement, truth, mask), method=method, seconds=seconds, ok=bool(reg.quality.ok))


# -- the textureless-phantom family (issue 11) --------------------------------------------------
#
# A homogeneous gel phantom in X-rays is a smooth body with a denser inclusion and almost no
# texture: the motion is observable at the body's edge, at the inclusion and through whatever
# texture (and noise) there is. The family spans that regime with texture from none to rich,
# stated against the noise; motion of several correlation lengths and amplitudes and a
# physically shaped case; both kinds of intensity change; Gaussian and Poisson-like noise; the
# line-integral ("log") and transmission ("intensity") domains. Training seeds (presets are
# chosen on them) and test seeds (every table is reported on them) never overlap.

TRAIN_SEEDS = tuple(range(0, 100))
TEST_SEEDS = tuple(range(1000, 1100))


@dataclass(frozen=True)
class Case:
    """One pair of the family. ``texture``: the texture's standard deviation in line-integral
    units (the body peaks at 2.0, so 0.01 is 0.5 % of it); ``noise``: the noise's (Gaussian:
    uniform; ``poisson``: proportional to ``1 / sqrt(transmission)``, the same mean over the
    body); ``corr``: the motion's correlation length as a fraction of the frame (``0`` with
    ``motion="physical"``); ``amplitude``: the largest ``|d|`` as a fraction of the frame;
    ``intensity``: amplitude of the slow intensity change (``kind`` thinning or gain, sign
    alternating with the seed); ``domain``: ``log`` (line integral) or ``intensity``
    (transmission ``exp(-p)``)."""

    size: int = 1120
    texture: float = 0.01
    noise: float = 0.01
    corr: float = 0.1
    amplitude: float = 0.01
    motion: str = "random"  # or "physical"
    intensity: float = 0.10
    kind: str = "thinning"
    noise_kind: str = "gaussian"
    domain: str = "log"
    seed: int = 1000

    @property
    def t2n(self) -> float:
        return self.texture / self.noise if self.noise else float("inf")

    def label(self) -> str:
        mot = "phys" if self.motion == "physical" else f"L1/{round(1 / self.corr)}"
        return (
            f"{self.size} tex{self.texture:g}/noise{self.noise:g}({self.noise_kind[0]}) {mot} "
            f"a{100 * self.amplitude:g}% {self.kind[0]}{100 * self.intensity:+g}% {self.domain} s{self.seed}"
        )


def gel_phantom(size, rng, texture=0.0, inclusion=0.3):
    """``(image, body, disc)``: a smooth body (an ellipse's chord, peak 2.0) with a denser,
    soft-edged disc inclusion (``inclusion`` x the chord: a 12 %-of-frame disc), plus a band-
    limited texture of standard deviation ``texture`` (line-integral units, scale frame/150)
    inside the body; blurred by 1 px like a detector. ``disc``: (row, col, radius) in pixels."""
    n = int(size)
    r2 = _ellipse_r2(n)
    body = r2 < 1
    chord = np.sqrt(np.clip(1 - r2, 0, None))
    img = 2.0 * chord
    y = (np.arange(n)[:, None] + 0.5) / n
    x = (np.arange(n)[None, :] + 0.5) / n
    rr, aa = 0.45 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
    cx, cy = 0.5 + rr * _BODY[0] * np.cos(aa), 0.5 + rr * _BODY[1] * np.sin(aa)
    rad = rng.uniform(0.05, 0.07)
    dist = np.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    disc_profile = np.sqrt(np.clip(1 - (dist / rad) ** 2, 0, None))  # a sphere's chord
    img += inclusion * 2.0 * rad / (_BODY[1]) * disc_profile * body
    if texture:
        t = ndimage.gaussian_filter(rng.standard_normal((n, n)).astype(np.float32), n / 150)
        img += (texture / t.std()) * t * chord  # fades to 0 at the body's edge, like a gel's thickness
    img = ndimage.gaussian_filter(img.astype(np.float32), 1.0)
    return img, body, (cy * n, cx * n, rad * n)


def random_motion(shape, rng, corr, amplitude):
    """A smooth random pull field: white noise filtered by a Gaussian of sigma ``corr`` x the
    frame / 2 (``corr`` the correlation length), each component, scaled so the largest ``|d|`` is
    ``amplitude`` x the frame. Filtered on a coarse grid and upsampled (cheap at 2240)."""
    import cv2

    n = shape[0]
    k = max(1, int(corr * n / 8))  # the coarse grid resolves the field (sigma >= 4 coarse px)
    m = -(-n // k)
    d = np.stack([ndimage.gaussian_filter(rng.standard_normal((m, m)), corr * m / 2, mode="wrap") for _ in range(2)])
    d = np.stack([cv2.resize(c.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC) for c in d])
    d *= amplitude * n / np.sqrt((d * d).sum(axis=0)).max()
    return d.astype(np.float32)


def physical_motion(shape, rng, disc, amplitude):
    """A compressed body's in-plane motion: uniform expansion about the frame's centre (the
    largest ``|d|`` over the body ``amplitude`` x the frame) plus a local lag around a stiffer
    disc: the disc expands 3-5x less and moves with its centre, the lag fading over about one
    radius outside it. A pull field: ``moving(x + d(x)) = fixed(x)`` where the expanded body
    is the fixed image, so ``d = -e (x - c)`` (e > 0)."""
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float32)
    cy, cx = (rows - 1) / 2, (cols - 1) / 2
    e = amplitude / _BODY[0]  # |d| = e r reaches amplitude x n at the tip of the body's long axis
    dr, dc, rad = disc
    soft = rng.uniform(0.2, 0.33)
    # the disc's own field: its centre's motion plus a smaller strain about it
    d_disc = np.stack([-e * (dr - cy) - soft * e * (yy - dr), -e * (dc - cx) - soft * e * (xx - dc)])
    d_free = np.stack([-e * (yy - cy), -e * (xx - cx)])
    dist = np.hypot(yy - dr, xx - dc) / rad
    w = np.clip(2.0 - dist, 0, 1)  # 1 inside the disc, fading to 0 one radius outside
    w = w * w * (3 - 2 * w)
    return (w * d_disc + (1 - w) * d_free).astype(np.float32)


def family_pair(case: Case):
    """``(fixed, moving, truth, mask)`` for a :class:`Case` (see the module's family comment).
    ``fixed(x) = moving(x + truth(x))``, changed in intensity, plus noise; both in ``case.domain``.
    The mask is the body shrunk by 3 % of the frame."""
    return _family(case)[:4]


def family_thinning(case: Case) -> np.ndarray:
    """The relative change ``b`` of ``case``'s fixed line integral (``fixed = (1 + b) moving(x +
    truth)`` before the noise; zeros for ``kind="gain"``), as :func:`family_pair` makes it: what
    registering with the true thinning divided out is measured with (benchmarks/README.md,
    session 20). Makes the pair again."""
    return _family(case)[4]


def _family(case: Case):
    """:func:`family_pair`'s four arrays and the thinning ``b`` (float32)."""
    if case.kind not in ("thinning", "gain"):
        raise ValueError(f"kind={case.kind!r}: expected 'thinning' or 'gain'")
    n = int(case.size)
    rng = np.random.default_rng(case.seed)
    moving, body, disc = gel_phantom(n, rng, case.texture)
    if case.motion == "physical":
        d = physical_motion((n, n), rng, disc, case.amplitude)
    else:
        d = random_motion((n, n), rng, case.corr, case.amplitude)
    rr, cc = np.mgrid[0:n, 0:n].astype(np.float32)
    fixed = ndimage.map_coordinates(moving, [rr + d[0], cc + d[1]], order=3, mode="nearest").astype(np.float32)
    del rr, cc
    s = smooth_field((n, n), rng, cycles=1.0, n_modes=4).astype(np.float32)
    change = case.intensity * (1 if case.seed % 2 else -1)  # both signs over the seeds
    thinning = np.zeros((n, n), np.float32)
    if case.kind == "thinning":
        thinning = (change * s).astype(np.float32)
        fixed *= 1 + thinning
    else:
        fixed -= np.log1p(change * s)
    pair = []
    for img in (fixed, moving):
        if case.noise:
            z = rng.standard_normal((n, n), dtype=np.float32)
            if case.noise_kind == "poisson":  # photon noise: std of -ln(I) ~ 1/sqrt(counts) ~ exp(p/2)
                z *= np.exp((img - float(img[body].mean())) / 2)
            img = img + case.noise * z
        pair.append(np.exp(-img).astype(np.float32) if case.domain == "intensity" else img.astype(np.float32))
    mask = _ellipse_r2(n, ax=_BODY[0] - 0.03, ay=_BODY[1] - 0.03) < 1
    return pair[0], pair[1], d, mask, thinning


def family(split="test", size=1120, *, n_seeds=1, grid="map"):
    """The family's cases on ``split`` ("train" or "test") seeds.

    ``grid="map"``: texture-to-noise {0, 0.3, 1, 3, 10} x correlation length {1/4, 1/10, 1/20}
    (1 % amplitude, +-10 % change, Gaussian noise 0.01, log domain) -- the maps' cells;
    ``grid="spread"``: the other axes one at a time around the weak-texture case (texture 0.01 =
    noise): amplitude 0.5-4 %, the physical motion, gain/thinning at 20 %, Poisson-like noise,
    the intensity domain, the noise at 2x and 1/4 (texture with it; and at 1/4 without texture);
    ``grid="all"``: both."""
    seeds = TRAIN_SEEDS if split == "train" else TEST_SEEDS
    if split not in ("train", "test"):
        raise ValueError(f"split={split!r}: expected 'train' or 'test'")
    out = []
    for s in seeds[:n_seeds]:
        if grid in ("map", "all"):
            for t2n in (0.0, 0.3, 1.0, 3.0, 10.0):
                for corr in (1 / 4, 1 / 10, 1 / 20):
                    out.append(Case(size=size, texture=0.01 * t2n, noise=0.01, corr=corr, seed=s))
        if grid in ("spread", "all"):
            base = Case(size=size, texture=0.01, noise=0.01, corr=0.1, seed=s)
            out += [
                replace(base, amplitude=0.005),
                replace(base, amplitude=0.04, corr=0.25),
                replace(base, motion="physical", corr=0.0, amplitude=0.01),
                replace(base, motion="physical", corr=0.0, amplitude=0.01, texture=0.0),
                replace(base, intensity=0.2, kind="gain"),
                replace(base, intensity=0.2),
                replace(base, noise_kind="poisson"),
                replace(base, domain="intensity"),
                replace(base, texture=0.02, noise=0.02),
                replace(base, texture=0.0025, noise=0.0025),  # a quieter exposure (session 12)
                # ... and a quiet one without texture: the map's window once let the body's edge
                # call its silent interior observed at this noise (session 13)
                replace(base, texture=0.0, noise=0.0025),
                replace(base, texture=0.1),
            ]
    return out
