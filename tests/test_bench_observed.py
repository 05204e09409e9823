"""benchmarks/bench_register_observed.py: the window bound with the field's local gradient as a
nuisance. Its translation-only form is the library's confidence map; eliminating more nuisance
never adds information; a circle's tangential shift is a rotation about its centre, so with the
local gradient free a circular edge observes only its normal component; a fine texture's
gradients do not correlate with position, so there the nuisance costs almost nothing."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_register_observed import _moment, window_bound, window_lmin

from radiokit.register import _confidence as C

W = 24.0


def _disc(radius, noise, seed=0, border=150):
    # the reflected border stays beyond the window's reach of the edge (two 24 px sigmas); the
    # circular edge's 5th percentile needs the full 150 px (at 70 it fell to 26 of the 100 asked)
    n = 2 * (radius + border)
    y, x = np.mgrid[0:n, 0:n]
    r = np.hypot(y - n / 2, x - n / 2)
    # drawn from r, not blurred from a binary disc: a binary disc's staircase is texture along
    # its edge, which does pin a tangential shift
    img = (0.5 - 0.5 * np.tanh((r - radius) / 2.0)).astype(np.float32)
    img += noise * np.random.default_rng(seed).standard_normal((n, n)).astype(np.float32)
    return img, np.abs(r - radius) < 1.5


def _texture(n=400, seed=1):
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.standard_normal((n, n)), 1.5)
    return (0.05 * t / t.std() + 0.01 * rng.standard_normal((n, n))).astype(np.float32)


def test_the_translation_bound_is_the_library_confidence_maps():
    img, edge = _disc(100, 0.05, border=70)  # agree to 3.1e-6 at 70 px as at 150 (0.4 CPU s, not 1.5)
    lib = C.observability(img, W).bound_px
    ours = window_bound(img, W, affine=False)
    # the library sums its windows in float32, this script in float64: 1.4e-4 apart on the texture
    np.testing.assert_allclose(ours[edge], lib[edge], rtol=5e-4)
    tex = _texture()
    np.testing.assert_allclose(
        window_bound(tex, W, affine=False)[60:-60, 60:-60], C.observability(tex, W).bound_px[60:-60, 60:-60], rtol=5e-4
    )


def test_eliminating_the_local_gradient_never_adds_information():
    for img in (_disc(100, 0.05, border=70)[0], _texture()):  # an inequality that holds for any image
        zero = np.zeros(img.shape, np.float32)  # no noise correction: the bare Schur complements
        t, a = window_lmin(img, W, 0.25, zero, affine=False), window_lmin(img, W, 0.25, zero, affine=True)
        assert np.all(a <= t * (1 + 1e-6) + 1e-12)


def test_a_circular_edge_observes_only_its_normal_component():
    """Translation: the arc's curvature pins the tangential shift (bound well under 0.5 px).
    With the local gradient free, a rotation about the window's centre plus that shift is a
    rotation about the circle's centre, which leaves the circle where it was: no information is
    left above the noise floor (the bound is capped, 1e6 px)."""
    for radius in (75, 150):
        # noise 1 % of the edge's step: at 5 %, with the window cut at two sigmas, the noise's
        # cross-terms with a strong edge leave 3-22 % of the edge's windows (seeds 0-2) above the
        # floor measured on noise alone (a statistical, not a geometric, residue)
        img, edge = _disc(radius, 0.01)
        t, a = window_bound(img, W, affine=False)[edge], window_bound(img, W, affine=True)[edge]
        assert np.median(t) < 0.5
        assert np.percentile(a / t, 5) > 100, (radius, np.median(t), np.median(a))


def test_a_fine_texture_pays_almost_nothing_for_the_local_gradient():
    """Gradients of a texture 1.5 px in scale are uncorrelated with the position in a 24 px
    window: the cross-information of shift and gradient averages to zero (to ~1/sqrt of the
    window's ~3600 independent pixels), so the bound rises by a few percent at most."""
    tex = _texture()
    ratio = (window_bound(tex, W, affine=True) / window_bound(tex, W, affine=False))[60:-60, 60:-60]
    assert 1.0 <= np.median(ratio) < 1.05 and ratio.max() < 1.15


def test_a_moment_weighs_by_the_offset_from_the_window_centre():
    """``_moment(a, s, 0, 1)`` at x0 is ``sum_u w(u) u_col a(x0 + u)``: a unit point 5 px to the
    right of x0 gives ``w(5) * 5``, w the normalised Gaussian; one 5 px below, with the row power."""
    a = np.zeros((41, 41))
    a[20, 25] = 1.0
    r = np.arange(-6, 7)  # the window is cut at WINDOW_REACH (2) sigmas
    assert C.WINDOW_REACH == 2.0
    w = np.exp(-0.5 * (r / 3.0) ** 2)
    w5 = np.exp(-0.5 * (5 / 3.0) ** 2) / w.sum() * (1 / w.sum())  # row weight at 0 times column weight at 5
    assert _moment(a, 3.0, 0, 1)[20, 20] == pytest.approx(5 * w5, rel=1e-9)
    assert _moment(a.T, 3.0, 1, 0)[20, 20] == pytest.approx(5 * w5, rel=1e-9)
    assert _moment(a, 3.0, 0, 2)[20, 20] == pytest.approx(25 * w5, rel=1e-9)
