"""How well could any registration do? A Bayesian bound on the end-point error of the family.

Run::

    python benchmarks/bench_register_bound.py [--size 2240] [--split test] [--seeds 2] [--cells 48]

``regdata.family_pair`` draws its motion from a known Gaussian process (white noise filtered by
a Gaussian of sigma ``corr * n / 2``, so each component's covariance is
``s^2 exp(-r^2 / (4 sigma^2))``) and its noise is Gaussian, ``noise`` in each image. Linearised
about the truth, ``fixed - moving(x + d) ~ -grad(moving) . delta_d + noise``, so the error of
the best estimator of the field, one that knows the prior, has the posterior covariance
``(H + C^-1)^-1`` (the Bayesian Cramer-Rao, or Van Trees, bound; for a linear Gaussian model
it is attained by the Wiener estimate):

- ``C`` the prior's covariance on a grid of ``--cells`` x ``--cells`` cells (the field taken as
  constant over a cell: at 2240 and correlation 1/10, cells of 47 px against sigma 112 px),
  ``s^2`` the truth's own mean square (an oracle's prior: a lower bound needs the best prior);
- ``H`` the Fisher information of the cell, ``sum grad grad^T / (2 noise^2)`` over its pixels
  (noise in both images), ``grad`` taken on the noise-free moving image.

Two versions. **known intensity**: ``grad`` of the whole noise-free image, as if the smooth
intensity change were known; the body's smooth slope then observes the motion across it, so
this is a lower bound for any method (it knows more than any method can). **unknown intensity**
(approximate, not a strict bound): ``grad`` of the image less its Gaussian blur of 2 % of the
frame (rc's own ``highpass``), what is left to a method that must let a smooth intensity change
of +-10-20 % go unmodelled: the texture, the inclusion and the body's edge.

The posterior covariance of each cell is sampled once per pixel of the scored mask (a 2-D
Gaussian error), so the tables give the best estimator's median and 95th percentile EPE, over
the mask and by distance from its edge, beside rc ``weak`` on the same noisy pair.
(``benchmarks/README.md``, "How well could any method do (session 10)".)
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy import linalg, ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair, gel_phantom

BANDS = ((0, 50), (50, 100), (100, 200), (200, 400), (400, 10**6))


def _cell_sums(a, cells):
    """``a`` (rows, cols) summed over ``cells`` x ``cells`` blocks (the frame cropped to fit)."""
    n = a.shape[0] // cells * cells
    c = n // cells
    return a[:n, :n].reshape(cells, c, cells, c).sum(axis=(1, 3))


def prior_kernels(n, cells, priors):
    """``(p, cells^2, cells^2)``: each parameter's prior covariance between the cells' centres
    of an ``n``-pixel frame's ``cells`` x ``cells`` grid, ``var exp(-r^2 / (4 sigma^2))`` for
    ``priors`` p pairs ``(sigma px, var)`` (the covariance of white noise filtered by a Gaussian
    of that sigma, ``regdata.random_motion``'s)."""
    centre = (np.arange(cells) + 0.5) * (n // cells * cells) / cells
    yy, xx = np.meshgrid(centre, centre, indexing="ij")
    pos = np.stack([yy.ravel(), xx.ravel()], 1)
    r2 = ((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1)
    return np.stack([var * np.exp(-r2 / (4.0 * corr**2)) for corr, var in priors])


def cell_information(features, noise, cells):
    """``(cells^2, p, p)``: each cell's Fisher information ``sum f f^T / (2 noise^2)`` about the
    ``p`` parameters whose unit changes do ``features`` (p, rows, cols) to the image (noise
    ``noise`` in each of the two images)."""
    p = len(features)
    h = np.empty((cells * cells, p, p))
    for a in range(p):
        for b in range(a, p):
            h[:, a, b] = h[:, b, a] = _cell_sums(features[a] * features[b], cells).ravel() / (2.0 * noise**2)
    return h


def information_roots(h):
    """``S`` with ``H_k = S_k S_k^T`` for each cell's information block (clipped at 0)."""
    vals, vecs = np.linalg.eigh(h)
    return vecs * np.sqrt(np.clip(vals, 0, None))[:, None, :]


def posterior_blocks(features, noise, priors, cells):
    """``(cells, cells, 2, 2)``: the posterior covariance (px^2) of each cell's displacement
    (rows, cols) for a linear model ``residual = sum_c features[c] * theta_c + noise``.

    ``features`` (p, rows, cols): what a unit change of each parameter does to the image (the
    gradient's two components for the displacement, first; the image itself for a thinning);
    Gaussian ``noise`` in each image; ``priors`` p pairs ``(correlation sigma px, variance)``:
    each parameter a Gaussian process over the cells, the parameters independent a priori.

    ``(H + C^-1)^-1 = C - C S (I + S^T C S)^-1 S^T C`` with ``H = S S^T`` cell by cell: the
    Gaussian kernel's ``C`` is far too ill-conditioned to invert, ``I + S^T C S`` is >= I."""
    n = features.shape[1]
    p = len(features)
    h = cell_information(features, noise, cells)
    s = information_roots(h)
    kern = prior_kernels(n, cells, priors)
    m = cells * cells
    # (S^T C)[(k, a), (l, b)] = S_k[b, a] K^b_kl; (S^T C S)[(k, a), (l, b)] = sum_c K^c_kl S_k[c, a] S_l[c, b]
    stc = np.einsum("kba,bkl->kalb", s, kern).reshape(p * m, p * m)
    a = np.einsum("kca,ckl,lcb->kalb", s, kern, s).reshape(p * m, p * m)
    a[np.diag_indices_from(a)] += 1.0
    chol = linalg.cholesky(a, lower=True, overwrite_a=True, check_finite=False)
    del a
    wm = linalg.solve_triangular(chol, stc, lower=True, overwrite_b=True, check_finite=False)
    wm = wm.reshape(p * m, m, p)[:, :, :2]
    reduce = np.einsum("jlb,jlc->lbc", wm, wm)
    prior = np.stack([np.diag(kern[0]), np.diag(kern[1])], -1)[:, :, None] * np.eye(2)[None]
    return (prior - reduce).reshape(cells, cells, 2, 2)


def carter_share(texture, noise):
    """The share of a texture's shift information that is left when the moving image is as noisy
    as the fixed one (Carter's time-delay bound: each frequency's ``k^2 P`` scaled by ``2 SNR /
    (1 + 2 SNR)``, ``SNR = P / noise^2``; the bound above takes the moving image noise-free).
    ``texture``: a noise-free texture image, windowed to its support (no edge leakage)."""
    n = texture.shape[0]
    power = np.abs(np.fft.fft2(texture)) ** 2 / texture.size  # white noise of variance s^2 reads s^2
    power = np.fft.ifftshift(ndimage.gaussian_filter(np.fft.fftshift(power), 3))  # the expected spectrum
    k = np.fft.fftfreq(n)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    snr = power / noise**2
    return float((k2 * power * 2 * snr / (1 + 2 * snr)).sum() / (k2 * power).sum())


def sampled_epe(post, shape, rng):
    """One draw of the best estimator's error per pixel: ``(rows, cols)`` |e|, e ~ N(0, post)
    of the pixel's cell (pixels beyond the cropped grid take the last cell's)."""
    cells = post.shape[0]
    c = shape[0] // cells
    idx = np.minimum(np.arange(shape[0]) // c, cells - 1)
    vals, vecs = np.linalg.eigh(post)
    root = vecs * np.sqrt(np.clip(vals, 0, None))[..., None, :]
    root = root[idx][:, idx]  # (rows, cols, 2, 2)
    z = rng.standard_normal((*shape, 2))
    e = np.einsum("rcij,rcj->rci", root, z)
    return np.sqrt((e * e).sum(-1))


def band_table(epe, mask):
    """``"all m / p95 | band m / p95 ..."``: EPE median / p95 over ``mask`` and by distance
    from its edge (``BANDS``: px at 2240, scaled with the frame)."""
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5) * (2240 / mask.shape[0])
    out = [f"{np.median(epe[mask]):5.2f}/{np.percentile(epe[mask], 95):5.2f}"]
    for lo, hi in BANDS:
        v = epe[mask & (dist >= lo) & (dist < hi)]
        out.append(f"{np.median(v):5.2f}/{np.percentile(v, 95):5.2f}" if v.size else "    -     ")
    return " | ".join(out)


def bound_row(case, cells, rng):
    """The pair's two bounds as EPE maps: ``(known, unknown, truth, mask)``."""
    if case.kind != "thinning":
        raise ValueError("the bound models the thinning intensity change only")
    quiet = replace(case, noise=0.0)  # the same draws: family_pair adds the noise last
    fixed, moving, truth, mask = family_pair(quiet)
    plain = family_pair(replace(quiet, intensity=0.0))[0]
    body = plain > 0.05 * plain.max()
    thinning = fixed[body] / plain[body] - 1  # the pair's own b: an oracle's prior variance
    n = moving.shape[0]
    motion = ((case.corr * n / 2), float((truth.astype(np.float64) ** 2).mean()))
    # smooth_field: plane waves of <= 1 cycle across the frame; a Gaussian kernel of the same
    # curvature at 0 for ~0.7 cycles has sigma n / (2 sqrt 2 pi 0.7) ~ n / 6
    gain = (n / 6.0, float((thinning.astype(np.float64) ** 2).mean()))
    img = moving.astype(np.float64)
    grad = np.stack(np.gradient(img))
    known = posterior_blocks(grad, case.noise, [motion, motion], cells)
    unknown = posterior_blocks(np.concatenate([grad, img[None]]), case.noise, [motion, motion, gain], cells)
    return sampled_epe(known, moving.shape, rng), sampled_epe(unknown, moving.shape, rng), truth, mask


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--split", choices=["train", "test"], default="test")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--cells", type=int, default=48, help="the prior's grid (cells per side)")
    ap.add_argument("--texture", type=float, nargs="*", default=[0.01], help="texture std (noise 0.01)")
    ap.add_argument("--no-rc", action="store_true", help="only the bounds")
    ap.add_argument("--carter", action="store_true", help="only the information a noisy moving image keeps")
    args = ap.parse_args(argv)
    from radiokit.register import register

    seeds = (TRAIN_SEEDS if args.split == "train" else TEST_SEEDS)[: args.seeds]
    rng = np.random.default_rng(0)
    if args.carter:
        for tex in args.texture:
            q = (
                gel_phantom(args.size, np.random.default_rng(seeds[0]), tex)[0]
                - gel_phantom(args.size, np.random.default_rng(seeds[0]))[0]
            )
            share = carter_share(q, 0.01)
            print(
                f"texture {tex:g}: a noisy moving image keeps {share:.4f} of the information (EPE x{share**-0.5:.4f})"
            )
        return 0
    head = "all | " + " | ".join(f"{lo}-{hi if hi < 10**6 else ''} px" for lo, hi in BANDS)
    print(f"EPE median/p95 (px) over the scored body, by distance from its edge (px at 2240): {head}")
    for tex in args.texture:
        for seed in seeds:
            case = Case(size=args.size, texture=tex, noise=0.01, corr=0.1, seed=seed)
            t = time.perf_counter()
            known, unknown, truth, mask = bound_row(case, args.cells, rng)
            print(f"{case.label()} ({time.perf_counter() - t:.0f} s)")
            print(f"  bound, intensity known    {band_table(known, mask)}")
            print(f"  bound, intensity unknown  {band_table(unknown, mask)}", flush=True)
            if not args.no_rc:
                f, m, d, mask = family_pair(case)
                for preset in ("weak", "auto"):
                    t = time.perf_counter()
                    reg = register(f, m, "rc", preset=preset)
                    e = np.sqrt(((reg.displacement - d) ** 2).sum(0))
                    took = time.perf_counter() - t
                    print(f"  rc {preset:<4} ({took:4.1f} s)     {band_table(e, mask)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
