"""Where does rc ``weak`` lose to the bound on weak texture? One Wiener step from its field.

Run::

    python benchmarks/bench_register_wiener.py [--split train] [--seeds 1 2 4] [--texture 0.01] [--unknown]

``bench_register_bound.py`` says the best estimator that knows the family's prior (the motion a
Gaussian process of known length and variance, the thinning one of frame scale) reaches a median
EPE of 0.24-0.25 px on the 2240 weak-texture pairs (texture = noise = 0.01), where ``weak`` reads
0.33-0.43. This script asks which of the bound's assumptions the gap is made of, by taking
``weak``'s field ``u0`` and applying the estimator the bound describes, linearised about it:

- per cell of ``--cells`` x ``--cells``, the information ``H`` and score ``g`` of the residual
  ``fixed - moving(x + u0) ~ grad . delta + b moving`` (gradients and the thinning regressor taken
  on the warped moving image smoothed by ``--smooth`` px: a noisy regressor correlates with the
  residual's own noise, which with the thinning free biased the field by 2 px);
- the posterior mean under a Gaussian-process prior, ``(H + C^-1)^-1 (H theta0 + g)``, upsampled
  cubically and added to ``u0`` as an increment (the field's detail within a cell kept).

Rows: the thinning known (the true one divided out of ``fixed``; two parameters per cell) with
the generator's own prior, and with its length or variance misstated; with ``--unknown``, the
thinning a third parameter per cell (its prior frame-scale, as in the bound), iterated with the
thinning found so far divided out. Seeds are TRAINING seeds by default: this chooses nothing,
it measures (benchmarks/README.md, "What the bound knows that rc does not (session 31)").
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import linalg, ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_bound import _cell_sums, cell_information, information_roots, prior_kernels
from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair, family_thinning, score


def posterior_mean(features, residual, noise, kern, cells, theta0):
    """``(cells^2, p)``: the posterior mean ``(H + C^-1)^-1 (H theta0 + g)`` of the linear model
    ``residual = sum_c features[c] (theta_c - theta0_c) + noise`` about ``theta0`` (cells^2, p),
    each parameter a Gaussian process with covariance ``kern[c]`` (cells^2, cells^2).

    Through ``C y - C S (I + S^T C S)^-1 S^T C y`` with ``H = S S^T`` cell by cell (the Gaussian
    kernel's ``C`` is far too ill-conditioned to invert; ``I + S^T C S`` is >= I)."""
    p, m = len(features), cells * cells
    h = cell_information(features, noise, cells)
    g = np.stack([_cell_sums(f * residual, cells).ravel() for f in features], 1) / (2.0 * noise**2)
    s = information_roots(h)
    y = np.einsum("kab,kb->ka", h, theta0) + g
    cy = np.einsum("akl,la->ka", kern, y)
    a = np.einsum("kca,ckl,lcb->kalb", s, kern, s).reshape(p * m, p * m)
    a[np.diag_indices_from(a)] += 1.0
    z = linalg.solve(a, np.einsum("kba,kb->ka", s, cy).ravel(), assume_a="pos", check_finite=False)
    sz = np.einsum("kab,kb->ka", s, z.reshape(m, p))
    return cy - np.einsum("akl,la->ka", kern, sz)


def upsample(values, n):
    """A ``(cells, cells)`` grid of cell values at every pixel of an ``n`` x ``n`` frame (cubic)."""
    c = n // values.shape[0]
    coords = (np.arange(n) + 0.5) / c - 0.5
    rr, cc = np.meshgrid(coords, coords, indexing="ij")
    return ndimage.map_coordinates(values, [rr, cc], order=3, mode="nearest")


def wiener_step(fixed, moving, u0, noise, kern, cells, smooth):
    """``(field, b)``: ``u0`` plus the posterior mean's increment, and the cells' thinning
    upsampled (zeros with two parameters); ``kern`` 2 or 3 kernels (the third the thinning's)."""
    from radiokit.register._common import warp

    n = fixed.shape[0]
    w = warp(moving, u0).astype(np.float64)
    ws = ndimage.gaussian_filter(w, smooth)
    features = [*np.gradient(ws), ws][: len(kern)]
    c = n // cells
    theta0 = np.zeros((cells * cells, len(kern)))
    for a in range(2):
        theta0[:, a] = _cell_sums(u0[a], cells).ravel() / c**2
    theta = posterior_mean(features, fixed - w, noise, kern, cells, theta0)
    inc = np.stack([upsample((theta[:, a] - theta0[:, a]).reshape(cells, cells), n) for a in range(2)])
    b = upsample(theta[:, 2].reshape(cells, cells), n) if len(kern) > 2 else np.zeros((n, n))
    return u0 + inc, b


def _rows(case, u0, args):
    """The printed rows of one pair: ``[(label, median EPE)]``."""
    f, m, d, mask = family_pair(case)
    thin = family_thinning(case)
    n, cells = case.size, args.cells
    length, var = case.corr * n / 2, float((d.astype(np.float64) ** 2).mean())
    known = f / (1 + thin)
    rows = []
    for lf, vf in ((1, 1), (0.5, 1), (2, 1), (1, 0.25), (1, 4)):
        kern = prior_kernels(n, cells, [(length * lf, var * vf)] * 2)
        u, _ = wiener_step(known, m, u0, case.noise, kern, cells, args.smooth)
        rows.append((f"one step, thinning known, length x{lf:g}, variance x{vf:g}", score(u, d, mask)["epe_median"]))
    if args.unknown:
        body = family_pair(replace(case, noise=0.0, intensity=0.0))[0]
        body = body > 0.05 * body.max()
        kern = prior_kernels(n, cells, [(length, var)] * 2 + [(n / 6.0, float((thin[body] ** 2).mean()))])
        u, b = u0.astype(np.float64), np.zeros((n, n))
        for _ in range(args.unknown):
            u, db = wiener_step(f / (1 + b), m, u, case.noise, kern, cells, args.smooth)
            b = (1 + b) * (1 + db) - 1
        rows.append((f"thinning unknown, {args.unknown} steps", score(u, d, mask)["epe_median"]))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=["train", "test"], default="train")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--texture", type=float, default=0.01, help="texture std (noise 0.01)")
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--cells", type=int, default=48, help="the prior's grid (cells per side)")
    ap.add_argument("--smooth", type=float, default=5.0, help="the regressors' Gaussian blur (px)")
    ap.add_argument("--unknown", type=int, default=0, metavar="K", help="also K steps with the thinning unknown")
    args = ap.parse_args(argv)
    from radiokit.register import register

    pool = TRAIN_SEEDS if args.split == "train" else TEST_SEEDS
    if any(s not in pool for s in args.seeds):
        ap.error(f"--seeds {args.seeds}: not all {args.split} seeds")
    print(f"{args.size} px, texture {args.texture:g}, {args.split} seeds {args.seeds}: median EPE (px)")
    for seed in args.seeds:
        case = Case(size=args.size, texture=args.texture, noise=0.01, corr=0.1, seed=seed)
        f, m, d, mask = family_pair(case)
        t = time.perf_counter()
        u0 = register(f, m, "rc", preset="weak").displacement.astype(np.float64)
        print(f"s{seed} rc weak: {score(u0, d, mask)['epe_median']:.3f} ({time.perf_counter() - t:.1f} s)", flush=True)
        for label, med in _rows(case, u0, args):
            print(f"s{seed} + Wiener, {label}: {med:.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
