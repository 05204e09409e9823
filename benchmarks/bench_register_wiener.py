"""Where does rc ``weak`` lose to the bound on weak texture? One Wiener step from its field.

Run::

    python benchmarks/bench_register_wiener.py [--split train] [--seeds 1 2 4] [--texture 0.01] [--unknown K]
        [--evidence] [--spline INTERVALS ...]

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

Session 32 (benchmarks/README.md, "Can the pair tell the prior, and where the thinning goes"):
``--evidence`` chooses the prior's length and variance by the marginal likelihood of the
linearised model (``log_evidence``) on a grid about the generator's, with the thinning rc's own
(``weak``'s interior polynomial, ``_interior_thinning``) divided out, and steps with the choice;
``--spline`` instead estimates the thinning with the motion, a cubic B-spline surface of
``INTERVALS`` per side (coefficients ``N(0, 0.1^2)``) marginalised out of the cells' information
(``spline_step``; a rank-``(INTERVALS+3)^2`` downdate of the block-diagonal information).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import linalg, ndimage
from scipy.interpolate import BSpline

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_bound import _cell_sums, cell_information, information_roots, prior_kernels
from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair, family_thinning, score


def _information_form(features, residual, noise, kern, cells, theta0):
    """``(S, y, C y, A)`` of the linear model of :func:`posterior_mean`: the roots ``S`` of the
    cells' information ``H``, ``y = H theta0 + g``, and ``A = I + S^T C S`` (p*cells^2 square)."""
    p, m = len(features), cells * cells
    h = cell_information(features, noise, cells)
    g = np.stack([_cell_sums(f * residual, cells).ravel() for f in features], 1) / (2.0 * noise**2)
    s = information_roots(h)
    y = np.einsum("kab,kb->ka", h, theta0) + g
    cy = np.einsum("akl,la->ka", kern, y)
    a = np.einsum("kca,ckl,lcb->kalb", s, kern, s).reshape(p * m, p * m)
    a[np.diag_indices_from(a)] += 1.0
    return s, y, cy, a


def posterior_mean(features, residual, noise, kern, cells, theta0):
    """``(cells^2, p)``: the posterior mean ``(H + C^-1)^-1 (H theta0 + g)`` of the linear model
    ``residual = sum_c features[c] (theta_c - theta0_c) + noise`` about ``theta0`` (cells^2, p),
    each parameter a Gaussian process with covariance ``kern[c]`` (cells^2, cells^2).

    Through ``C y - C S (I + S^T C S)^-1 S^T C y`` with ``H = S S^T`` cell by cell (the Gaussian
    kernel's ``C`` is far too ill-conditioned to invert; ``I + S^T C S`` is >= I)."""
    p, m = len(features), cells * cells
    s, y, cy, a = _information_form(features, residual, noise, kern, cells, theta0)
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


def log_evidence(features, residual, noise, kern, cells, theta0):
    """The log marginal likelihood (up to a constant of the data) of :func:`posterior_mean`'s
    model under the prior ``kern``: ``-log|A| / 2 + y^T (H + C^-1)^-1 y / 2``, ``A = I + S^T C S``
    and ``y = H theta0 + g`` (the likelihood in information form, ``theta`` integrated out)."""
    s, y, cy, a = _information_form(features, residual, noise, kern, cells, theta0)
    chol = linalg.cholesky(a, lower=True, check_finite=False)
    b = np.einsum("kba,kb->ka", s, cy).ravel()
    z = linalg.cho_solve((chol, True), b, check_finite=False)
    return float(-np.log(np.diag(chol)).sum() + 0.5 * ((y * cy).sum() - z @ b))


def bspline_basis(n, intervals):
    """``(n, intervals + 3)``: the cubic B-splines of ``intervals`` equal spans over ``n`` pixels."""
    t = np.concatenate([np.zeros(3), np.linspace(0, n, intervals + 1), np.full(3, n)])
    x = np.arange(n) + 0.5
    eye = np.eye(intervals + 3)
    return np.nan_to_num(np.stack([BSpline(t, eye[j], 3, extrapolate=False)(x) for j in range(len(eye))], 1))


def _spline_terms(gradients, ws, residual, basis, cells, s2):
    """The thinning surface's cross information with the cells' motion ``(cells^2 * 2, q)``, its
    own information ``(q, q)`` and score ``(q,)``, ``q = nb^2`` (rows of ``ws`` times the tensor
    B-splines ``basis`` (n, nb) are its regressors)."""
    nn, nb = cells * (ws.shape[0] // cells), basis.shape[1]
    c = nn // cells
    bc, b = basis[:nn].reshape(cells, c, nb), basis[:nn]
    k = np.empty((cells, cells, 2, nb, nb))
    for a, ga in enumerate(gradients):
        rows = np.einsum("ykc,kcq->ykq", (ga * ws)[:nn, :nn].reshape(nn, cells, c), bc)
        k[:, :, a] = np.einsum("rcp,rckq->rkpq", bc, rows.reshape(cells, c, cells, nb))
    along = np.einsum("yx,xq,xs->yqs", (ws * ws)[:nn, :nn], b, b)
    hb = np.einsum("yp,yr,yqs->pqrs", b, b, along).reshape(nb * nb, nb * nb)
    gb = (b.T @ (residual * ws)[:nn, :nn] @ b).ravel()
    return k.reshape(cells * cells * 2, nb * nb) / s2, hb / s2, gb / s2


def spline_step(fixed, moving, u0, noise, kern, cells, smooth, intervals, sigma_b=0.1):
    """``u0`` plus the posterior mean's increment, the thinning a B-spline surface of
    ``intervals`` spans per side estimated with the motion (``fixed - warped ~ grad . delta + b
    warped``) and marginalised: ``H' = H - K M^-1 K^T``, ``M`` its information plus ``sigma_b^-2``;
    then ``theta = C (H' C + I)^-1 (H' theta0 + g')`` (dense: 4608 unknowns at 48 cells)."""
    from radiokit.register._common import warp

    n, m = fixed.shape[0], cells * cells
    w = warp(moving, u0).astype(np.float64)
    ws = ndimage.gaussian_filter(w, smooth)
    grads, residual, s2 = np.gradient(ws), fixed - w, 2.0 * noise**2
    h = cell_information(grads, noise, cells)
    g = np.stack([_cell_sums(f * residual, cells).ravel() for f in grads], 1).ravel() / s2
    c = n // cells
    theta0 = np.stack([_cell_sums(u0[a], cells).ravel() / c**2 for a in range(2)], 1).ravel()
    k, hb, gb = _spline_terms(grads, ws, residual, bspline_basis(n, intervals), cells, s2)
    mb = linalg.cho_factor(hb + np.eye(len(hb)) / sigma_b**2)
    hp = -k @ linalg.cho_solve(mb, k.T)
    cov = np.zeros_like(hp)
    for a in range(2):  # the index of parameter a of cell j is 2 j + a
        hp[2 * np.arange(m) + a, 2 * np.arange(m) + a] += h[:, a, a]
        hp[2 * np.arange(m) + a, 2 * np.arange(m) + 1 - a] += h[:, a, 1 - a]
        cov[np.ix_(2 * np.arange(m) + a, 2 * np.arange(m) + a)] = kern[a]
    y = hp @ theta0 + g - k @ linalg.cho_solve(mb, gb)
    theta = cov @ linalg.solve(hp @ cov + np.eye(len(hp)), y, check_finite=False)
    inc = (theta - theta0).reshape(m, 2)
    return u0 + np.stack([upsample(inc[:, a].reshape(cells, cells), n) for a in range(2)])


def _evidence_rows(case, u0, args):
    """``--evidence``: the grid's log evidence with ``weak``'s own thinning divided out, and the
    step at its best point; ``[(label, median EPE)]``."""
    from radiokit.register._bspline import _interior_thinning
    from radiokit.register._common import warp

    f, m, d, mask = family_pair(case)
    n, cells = case.size, args.cells
    length, var = case.corr * n / 2, float((d.astype(np.float64) ** 2).mean())
    b, level, note = _interior_thinning(f, m, u0, None)
    own = f if b is None else level + (f - level) / (1.0 + b)
    w = warp(m, u0).astype(np.float64)
    grads = np.gradient(ndimage.gaussian_filter(w, args.smooth))
    c = n // cells
    theta0 = np.stack([_cell_sums(u0[a], cells).ravel() / c**2 for a in range(2)], 1)
    grid = [(lf, vf) for lf in (0.35, 0.5, 0.7, 1.0, 1.4, 2.0) for vf in (0.25, 1.0, 4.0)]
    ev = [
        log_evidence(grads, own - w, case.noise, prior_kernels(n, cells, [(length * lf, var * vf)] * 2), cells, theta0)
        for lf, vf in grid
    ]
    lf, vf = grid[int(np.argmax(ev))]
    rows = []
    for label, (lk, vk) in (
        ("the generator's prior", (1, 1)),
        (f"the evidence's choice, length x{lf:g}, variance x{vf:g}", (lf, vf)),
    ):
        u, _ = wiener_step(
            own, m, u0, case.noise, prior_kernels(n, cells, [(length * lk, var * vk)] * 2), cells, args.smooth
        )
        s = score(u, d, mask)
        rows.append(
            (f"weak's own thinning ({note.split(':')[0]}), {label}", f"{s['epe_median']:.3f} p95 {s['epe_p95']:.3f}")
        )
    return rows


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
    for intervals in args.spline:
        kern = prior_kernels(n, cells, [(length, var)] * 2)
        u = spline_step(f, m, u0, case.noise, kern, cells, args.smooth, intervals)
        rows.append(
            (
                f"thinning a B-spline of {intervals} spans marginalised, the generator's prior",
                score(u, d, mask)["epe_median"],
            )
        )
    return rows + (_evidence_rows(case, u0, args) if args.evidence else [])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=["train", "test"], default="train")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--texture", type=float, default=0.01, help="texture std (noise 0.01)")
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--cells", type=int, default=48, help="the prior's grid (cells per side)")
    ap.add_argument("--smooth", type=float, default=5.0, help="the regressors' Gaussian blur (px)")
    ap.add_argument("--unknown", type=int, default=0, metavar="K", help="also K steps with the thinning unknown")
    ap.add_argument(
        "--evidence", action="store_true", help="also the prior chosen by the marginal likelihood, weak's thinning"
    )
    ap.add_argument(
        "--spline",
        type=int,
        nargs="*",
        default=[],
        metavar="N",
        help="also the thinning a B-spline of N spans, marginalised",
    )
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
            print(f"s{seed} + Wiener, {label}: {med if isinstance(med, str) else f'{med:.3f}'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
