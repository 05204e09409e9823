"""benchmarks/bench_register_bound.py: the posterior covariance it reports is the Bayesian
Cramer-Rao bound of the linear Gaussian model, ``(H + C^-1)^-1``."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_register_bound import posterior_blocks


def test_posterior_blocks_are_the_inverse_of_information_plus_prior_precision():
    """Against the textbook formula on a case small enough to invert directly (with a nuisance
    parameter: three per cell, the third's blocks marginalised away)."""
    rng = np.random.default_rng(1)
    n, cells, noise = 40, 4, 0.5
    feat = rng.standard_normal((3, n, n))
    priors = [(15.0, 4.0), (15.0, 4.0), (30.0, 0.01)]
    post = posterior_blocks(feat, noise, priors, cells)
    c = n // cells
    centre = (np.arange(cells) + 0.5) * c
    yy, xx = np.meshgrid(centre, centre, indexing="ij")
    p = np.stack([yy.ravel(), xx.ravel()], 1)
    r2 = ((p[:, None] - p[None]) ** 2).sum(-1)
    m = len(p)
    cov = np.zeros((3 * m, 3 * m))
    for q, (corr, var) in enumerate(priors):
        cov[q::3, q::3] = var * np.exp(-r2 / (4 * corr**2)) + 1e-10 * np.eye(m)
    info = np.zeros_like(cov)
    for k in range(m):
        i, j = divmod(k, cells)
        g = feat[:, i * c : (i + 1) * c, j * c : (j + 1) * c].reshape(3, -1)
        info[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = g @ g.T / (2 * noise**2)
    direct = np.linalg.inv(info + np.linalg.inv(cov))
    want = np.stack([direct[3 * k : 3 * k + 2, 3 * k : 3 * k + 2] for k in range(m)]).reshape(cells, cells, 2, 2)
    np.testing.assert_allclose(post, want, atol=1e-8 * np.abs(want).max())


def test_one_cell_without_a_prior_is_the_cramer_rao_bound_of_a_shift():
    """A single cell and a vague prior: the bound of a shift between two noisy copies, noise
    variance 2 sigma^2 over the sum of squared gradients (per axis, gradients uncorrelated)."""
    rng = np.random.default_rng(2)
    n, noise = 32, 0.1
    gy, gx = rng.standard_normal((2, n, n))
    gx -= gy * (gy * gx).sum() / (gy * gy).sum()  # uncorrelated axes: the bound is diagonal
    post = posterior_blocks(np.stack([gy, gx]), noise, [(1e3, 1e4), (1e3, 1e4)], 1)[0, 0]
    want = np.diag([2 * noise**2 / (gy * gy).sum(), 2 * noise**2 / (gx * gx).sum()])
    np.testing.assert_allclose(post, want, rtol=1e-4, atol=1e-12)


def test_wiener_posterior_mean_is_the_textbook_formula():
    """bench_register_wiener's posterior mean ``(H + C^-1)^-1 (H theta0 + g)`` against a direct
    dense inverse, on a case small enough for it (three parameters per cell)."""
    from bench_register_bound import prior_kernels
    from bench_register_wiener import posterior_mean

    rng = np.random.default_rng(2)
    n, cells, noise = 40, 4, 0.5
    feat = rng.standard_normal((3, n, n))
    resid = rng.standard_normal((n, n))
    priors = [(15.0, 4.0), (15.0, 4.0), (30.0, 0.01)]
    kern = prior_kernels(n, cells, priors)
    m = cells * cells
    theta0 = rng.standard_normal((m, 3))
    got = posterior_mean(feat, resid, noise, kern, cells, theta0)
    c = n // cells
    cov = np.zeros((3 * m, 3 * m))
    for q in range(3):
        cov[q::3, q::3] = kern[q] + 1e-10 * np.eye(m)
    info = np.zeros_like(cov)
    g = np.zeros(3 * m)
    for k in range(m):
        i, j = divmod(k, cells)
        f = feat[:, i * c : (i + 1) * c, j * c : (j + 1) * c].reshape(3, -1)
        info[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = f @ f.T / (2 * noise**2)
        g[3 * k : 3 * k + 3] = f @ resid[i * c : (i + 1) * c, j * c : (j + 1) * c].ravel() / (2 * noise**2)
    want = np.linalg.solve(info + np.linalg.inv(cov), info @ theta0.ravel() + g).reshape(m, 3)
    np.testing.assert_allclose(got, want, atol=1e-6 * np.abs(want).max())


def test_carter_share_is_the_closed_form_for_a_white_texture():
    """A texture as white as the noise has SNR = (texture / noise)^2 at every frequency, so the
    share is ``2 SNR / (1 + 2 SNR)`` exactly (up to the estimated spectrum's scatter)."""
    from bench_register_bound import carter_share

    rng = np.random.default_rng(3)
    for ratio in (0.5, 1.0, 3.0):
        tex = rng.standard_normal((256, 256)) * 0.01 * ratio
        snr = ratio**2
        assert abs(carter_share(tex, 0.01) - 2 * snr / (1 + 2 * snr)) < 0.02
