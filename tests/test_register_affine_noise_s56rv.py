"""Review of session 56's noise share in the affine moments (benchmarks/README.md, "The affine
bound's noise share from a rim-blind estimate (session 56)"): where the noise level varies across
a window, the share taken out of each moment must be the noise's own there, or noise is read as
structure."""

import numpy as np

from radiokit.register import _confidence as C

S = 24.0


def test_the_noise_share_of_a_window_over_a_noise_step_is_its_weighted_mean_not_the_centres():
    # Pure noise, 3x louder on the right half (a body in transmission is quieter than the open
    # beam beside it: Poisson). A window 6-36 px left of the step reaches the loud half; each
    # weighted moment of a squared derivative holds the window's same weighted mean of the local
    # noise variance, so with the exact per-pixel noise share passed in, nothing is left of it: the
    # affine marginal is no more than pure noise's floor at the window's mean variance (99th
    # percentile of uniform noise). Taking the centre's variance left the loud half's excess as
    # structure: 3.6-9x that floor on the quiet side, the translation's block 14-20x
    n = 192
    rng = np.random.default_rng(21)
    sig = np.where(np.arange(n)[None, :] < n // 2, 1.0, 3.0) * np.ones((n, n))
    f = (sig * rng.standard_normal((n, n))).astype(np.float32)
    gy, gx, _ = C._map_gradients(f, S, 0.25)
    var = C._window(sig**2, S)
    prec = 2 * var / (C._window_area(S) * (0.01 * S) ** 2)  # observability's at a prior of 0.01
    lt, la = C.affine_lmins(gy, gx, S, C._deriv_noise_var(1.0) * sig**2, prec, project=False)
    floor = C._noise_lmin(S, 0.25) * var
    quiet = (slice(48, 144), slice(60, 90))
    assert np.percentile(la[quiet] / floor[quiet], 99) <= 1.0, np.percentile(la[quiet] / floor[quiet], [50, 99])
    assert np.percentile(lt[quiet] / floor[quiet], 99) <= 1.0, np.percentile(lt[quiet] / floor[quiet], [50, 99])


def test_the_robust_noise_estimate_reads_an_integer_frames_noise():
    # A raw detector frame is integers: its diagonal second difference takes levels half a count
    # apart, and a tile's median of |h| snaps to one of them (at 1 count of noise, 0.5x the
    # variance; at 2 counts, 1.2x). The noise is the Gaussian's and the rounding's (1/12 count^2):
    # over ~400 tiles the frame's median estimate is that within its sampling error (~0.5 %) and
    # what a level's values spread over its bin leave (<~5 % for noise of a count or more)
    rng = np.random.default_rng(31)
    for s in (1.0, 1.5, 2.0):
        f = np.round(1000 + s * rng.standard_normal((480, 480))).astype(np.float32)
        ratio = float(np.median(C.robust_noise_map(f, S) ** 2)) / (s * s + 1 / 12)
        assert abs(ratio - 1) < 0.08, (s, ratio)


def test_a_textureless_interior_of_an_integer_frame_stays_unobserved_under_the_affine_bound():
    # The consequence: a smooth disc of 200 counts on an integer frame with 1 count of noise, no
    # texture. The noise's share read at half its variance left the other half in the moments as
    # structure: 38-58 % of the interior read observed under the affine bound, where the rim's
    # curvature alone reaches it (the same disc at 2 counts: 0 %)
    n = 224
    yy, xx = np.mgrid[:n, :n].astype(np.float64)
    r = np.hypot(yy - n / 2, xx - n / 2)
    body = 1 / (1 + np.exp((r - 90) / 1.5))
    f = np.round(1000 + 200 * body + np.random.default_rng(41).standard_normal(body.shape)).astype(np.float32)
    ob = C.observability(f, S, affine_prior=0.01)
    inner = r < 85
    assert (ob.translation[inner] >= 0.5).mean() > 0.5  # the rim's credit, which the bound takes away
    share = float((ob.confidence[inner] >= 0.5).mean())
    assert share < 0.05, share
