"""Registration benchmark data: image pairs with their true pull displacement.

``analytic_pair`` builds a phantom-like line-integral image (an elliptical body with texture and
a denser inclusion), a smooth random warp ``d`` (max ``displacement_frac`` of the frame), and
``fixed(x) = moving(x + d(x))`` changed in intensity the way compression and stale flats change
it, plus noise:

- ``kind="thinning"``: the line integral scaled by a smooth factor ``1 +- intensity_change``
  (the body gets thinner along the beam as it is compressed);
- ``kind="gain"``: a smooth multiplicative gain on the transmission, i.e. an additive smooth
  term ``-ln(gain)`` on the line integral (a stale flat field).

``sim_pair`` reads a simulated experiment file (``radiokit sim run``): fixed = the most
compressed step's noise-free line integral, moving = an earlier step, truth = the stored field.

``score`` gives the end-point error median and 95th percentile inside the object, and folds.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage


def _smooth(shape, scale, rng):
    f = ndimage.gaussian_filter(rng.standard_normal(shape), scale)
    return f / np.abs(f).max()


def analytic_pair(size=1120, displacement_frac=0.01, intensity_change=0.10, noise=0.01, seed=0, kind="thinning"):
    """``(fixed, moving, truth, mask)``: float32 images, (2, n, n) pull field, bool object mask."""
    from radiokit.register import warp

    if kind not in ("thinning", "gain"):
        raise ValueError(f"kind={kind!r}: expected 'thinning' or 'gain'")
    n = int(size)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] / n
    body = ((xx - 0.5) ** 2 / 0.16 + (yy - 0.5) ** 2 / 0.12) < 1
    chord = np.sqrt(np.clip(1 - ((xx - 0.5) ** 2 / 0.16 + (yy - 0.5) ** 2 / 0.12), 0, None))
    texture = ndimage.gaussian_filter(rng.standard_normal((n, n)), n / 150)
    texture /= texture.std()
    inclusion = np.exp(-((xx - 0.58) ** 2 + (yy - 0.45) ** 2) / 0.003)
    moving = (2.0 * chord * (1 + 0.08 * texture) + 0.4 * inclusion * body).astype(np.float32)
    moving = ndimage.gaussian_filter(moving, 1.0)
    d = np.stack([_smooth((n, n), n / 8, rng) for _ in range(2)]).astype(np.float32) * displacement_frac * n
    fixed = warp(moving, d, order=3)
    slow = _smooth((n, n), n / 4, rng).astype(np.float32)
    if kind == "thinning":
        fixed = fixed * (1 + intensity_change * slow)
    else:
        fixed = fixed - np.log1p(intensity_change * slow)
    fixed = fixed + noise * rng.standard_normal((n, n)).astype(np.float32)
    mask = ndimage.binary_erosion(body, iterations=max(2, n // 50))
    return fixed.astype(np.float32), moving.astype(np.float32), d, mask


def sim_pair(path, moving_step=None, erode=20):
    """``(fixed, moving, truth, mask)`` from a simulated experiment file."""
    import h5py

    with h5py.File(path, "r") as h5:
        g = h5["entry/simulation"]
        li = g["line_integral"][()]
        n = li.shape[0]
        a = (n - 1) if moving_step is None else int(moving_step)  # 1-based steps in the file
        truth = g[f"displacement/step{a}_to_step{n}"][()]
    fixed, moving = li[-1], li[a - 1]
    mask = ndimage.binary_erosion(fixed > 0.05 * fixed.max(), iterations=erode)
    return fixed, moving, truth, mask


def score(displacement, truth, mask) -> dict:
    from radiokit.register import jacobian_determinant

    e = np.sqrt(((np.asarray(displacement) - truth) ** 2).sum(axis=0))[mask]
    return {"epe_median": float(np.median(e)), "epe_p95": float(np.percentile(e, 95)),
            "folds": int((jacobian_determinant(displacement)[mask] <= 0).sum())}
