"""Enhancement and contrast measurements against hand-computed values and a column model.

Every expected number below is computed by hand in the test (or in the comment beside it), not
by the code under test.
"""

import doctest
import math
import re
import subprocess
import sys

import numpy as np
import pytest
from skimage.measure import profile_line

import radiokit.enhance
import radiokit.measure
from radiokit.enhance import Domain, compression_contrast, difference, to_domain
from radiokit.measure import ROI, change_ratio, cnr, contrast, find_rois, improvement_factor, profile, summary, weber


# -- contrast, CNR, Weber on a 6x6 image ---------------------------------------------------------
def _six(inclusion_values, background_values):
    img = np.full((6, 6), 9.0)  # everything outside the two ROIs is ignored
    img[1:3, 1:3] = inclusion_values
    img[3:5, 3:5] = background_values
    return img


INC, BG = ROI(1, 3, 1, 3), ROI(3, 5, 3, 5)


@pytest.mark.parametrize(
    "inc_vals, bg_vals, c, c_nr, w",
    [
        # incl mean 5, bg mean 2.5, bg std sqrt(((1.5)^2 + .5^2 + .5^2 + 1.5^2) / 4) = sqrt(1.25)
        (5.0, [[1, 2], [3, 4]], 2.5, 2.5 / math.sqrt(1.25), 1.0),
        # the paper's negative intensities: incl -0.2, bg mean -0.4, std 0.1 -> 0.2, 2, 0.5
        (-0.2, [[-0.5, -0.3], [-0.3, -0.5]], 0.2, 2.0, 0.5),
        # an inclusion darker than the background: negative contrast, |mean bg| = 4
        ([[1, 1], [1, 3]], [[4, 6], [2, 4]], 1.5 - 4.0, -2.5 / math.sqrt(2.0), -2.5 / 4),
    ],
)
def test_contrast_cnr_weber_hand_values(inc_vals, bg_vals, c, c_nr, w):
    img = _six(inc_vals, bg_vals)
    assert contrast(img, INC, BG) == pytest.approx(c, rel=1e-12)
    assert cnr(img, INC, BG) == pytest.approx(c_nr, rel=1e-12)
    assert weber(img, INC, BG) == pytest.approx(w, rel=1e-12)
    # the same with boolean masks, and float32 input
    assert contrast(img.astype(np.float32), INC.mask(img.shape), BG.mask(img.shape)) == pytest.approx(c, rel=1e-6)


def test_noiseless_background_gives_infinite_cnr_and_zero_mean_infinite_weber():
    img = _six(3.0, 0.0)
    assert cnr(img, INC, BG) == math.inf
    assert weber(img, INC, BG) == math.inf
    assert math.isnan(cnr(np.zeros((6, 6)), INC, BG))


# -- enhancement -------------------------------------------------------------------------------
# Values are multiples of 1/4 so float32 holds every intermediate exactly and equality is exact.
REF = np.array([[4.0, 4.0, 4.0, 4.0], [4.0, 6.0, 6.0, 4.0], [4.0, 6.0, 6.0, 4.0], [4.0, 4.0, 4.0, 4.0]])
D = np.array(
    [[-1.0, -1.0, -1.0, -1.0], [-1.0, -0.5, -0.5, -1.0], [-1.0, -0.5, -0.5, -1.0], [-1.0, -1.0, -1.0, -1.0]]
)  # mean D = (12 * -1 + 4 * -0.5) / 16 = -0.875
# D - mean D: -0.125 outside, +0.375 at the inclusion


@pytest.mark.parametrize(
    "k, outside, inside",
    [
        (1.0, 4.0 - 0.125, 6.0 + 0.375),
        (2.0, 4.0 - 0.25, 6.0 + 0.75),
        (0.0, 4.0, 6.0),
        (-1.0, 4.0 + 0.125, 6.0 - 0.375),
    ],
)
def test_enhanced_equals_reference_plus_k_centred_difference(k, outside, inside):
    registered = REF - D
    out = compression_contrast(REF.astype(np.float32), registered.astype(np.float32), k)
    expected = np.full((4, 4), outside)
    expected[1:3, 1:3] = inside
    assert out.dtype == np.float32 and out.shape == (4, 4)
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(difference(REF, registered), D)


@pytest.mark.parametrize("k", [1.0, 2.0])
def test_negative_domain_same_formula(k):
    # negative intensities: background -0.5, inclusion -0.25 (brighter); D / 8: mean -0.109375,
    # D / 8 - mean = -0.015625 outside, +0.046875 at the inclusion
    ref = (REF - 8) / 8
    out = compression_contrast(ref, ref - D / 8, k, domain="negative")
    expected = np.full((4, 4), -0.5 - k * 0.015625)
    expected[1:3, 1:3] = -0.25 + k * 0.046875
    np.testing.assert_array_equal(out, expected)
    # transmission I/I0 is the same image upside down: the enhanced image is too
    lin = compression_contrast(-ref, -(ref - D / 8), k, domain=Domain.LINEAR)
    np.testing.assert_array_equal(lin, -expected)


@pytest.mark.parametrize("make_mask", [lambda: ROI(0, 1, 0, 4), lambda: ROI(0, 1, 0, 4).mask((4, 4))])
def test_mean_of_difference_taken_over_the_mask(make_mask):
    # mean D over the top row is -1: D - mean D = 0 outside, +0.5 at the inclusion
    out = compression_contrast(REF, REF - D, 1.0, mask=make_mask())
    expected = REF.copy()
    expected[1:3, 1:3] += 0.5
    np.testing.assert_array_equal(out, expected)


def test_inputs_are_not_modified():
    ref, reg = REF.copy(), REF - D
    reg0 = reg.copy()
    compression_contrast(ref, reg, 2.0, mask=np.ones((4, 4), bool))
    np.testing.assert_array_equal(ref, REF)
    np.testing.assert_array_equal(reg, reg0)


@pytest.mark.parametrize("mask", [None, ROI(0, 64, 0, 256), np.arange(256 * 256).reshape(256, 256) % 3 == 0])
def test_enhancement_peaks_near_three_frames(mask):
    """Review s43: the enhancement held ~7 float32 frames at once (a float64 copy of the
    reference, D, D - mean D, k (D - mean D), their sum: 2 frames each), 140 MB at 2240 px
    and per k, per domain; the float32 result and one float64 work image are 3 frames."""
    import tracemalloc

    rng = np.random.default_rng(0)
    ref = (1.0 + rng.random((256, 256))).astype(np.float32)
    reg = (1.2 + rng.random((256, 256))).astype(np.float32)
    tracemalloc.start()
    try:
        out = compression_contrast(ref, reg, 2.0, mask=mask)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / ref.nbytes < 3.3  # 3 frames and the bookkeeping of a few small arrays
    # the formula in float64, then rounded once to float32: equal to within that rounding
    d = ref.astype(np.float64) - reg
    sel = np.ones(d.shape, bool) if mask is None else mask.mask(d.shape) if isinstance(mask, ROI) else mask
    expected = ref + 2.0 * (d - d[sel].mean())
    np.testing.assert_allclose(out, expected, rtol=np.finfo(np.float32).eps, atol=0)


def test_to_domain():
    L = np.array([[0.0, np.log(2.0), np.log(4.0)]])
    np.testing.assert_allclose(to_domain(L, "negative"), [[-1.0, -0.5, -0.25]], rtol=1e-7)
    np.testing.assert_allclose(to_domain(L, "linear"), [[1.0, 0.5, 0.25]], rtol=1e-7)  # I/I0, as in correct
    np.testing.assert_array_equal(to_domain(L, "log"), L.astype(np.float32))
    assert all(to_domain(L, d).dtype == np.float32 for d in Domain)


# -- improvement factor and change ratio -------------------------------------------------------
@pytest.mark.parametrize("c_ref, dd, k", [(2.0, 0.5, 1.0), (2.0, 0.5, 2.0), (0.3, -0.1, 1.0), (-1.0, 0.25, 2.0)])
def test_improvement_factor_closed_form(c_ref, dd, k):
    """improvement = 1 + k (D_incl - D_bg) / C_ref; the mean of D and any offset drop out."""
    ref = np.full((8, 8), 1.0)
    ref[2:5, 2:5] += c_ref
    d = np.full((8, 8), -0.7)
    d[2:5, 2:5] += dd
    d[7, :] = 5.0  # shifts mean D, outside both ROIs: must not matter
    inc, bg = ROI(2, 5, 2, 5), ROI(2, 5, 5, 8)
    enh = compression_contrast(ref, ref - d, k)
    assert improvement_factor(enh, ref, inc, bg) == pytest.approx(1 + k * dd / c_ref, rel=1e-6)


@pytest.mark.parametrize("rho", [0.66, 0.75, 0.84, 1.0, 1.3])
@pytest.mark.parametrize("bg_change", [-0.2, 0.05])
def test_change_ratio_recovers_the_planted_ratio(rho, bg_change):
    rng = np.random.default_rng(5)
    before = rng.uniform(1.0, 2.0, (10, 12))
    after = before + bg_change
    after[2:6, 1:5] = before[2:6, 1:5] + rho * bg_change  # inclusion changes rho times as much
    assert change_ratio(before, after, ROI(2, 6, 1, 5), ROI(2, 6, 7, 11)) == pytest.approx(rho, rel=1e-9)


# -- the column model: what compression does to an inclusion in each domain --------------------
MU_BG, MU_INC, T, C, R = 0.05, 0.10, 40.0, 8.0, 0.05 / 0.80  # per mm, mm, mm; 20 % -> 25 %


def _column_pair(r_inc, *, thinning=R, mu_bg=MU_BG):
    """Line integrals before (already registered) and after a compression step, parallel beam,
    rigid plates: every column thins by ``thinning * T``; the inclusion's chord by ``r_inc``."""
    inside = np.zeros((12, 12), bool)
    inside[4:8, 2:6] = True
    before = np.full((12, 12), mu_bg * T)
    before[inside] += (MU_INC - mu_bg) * C
    after = np.full((12, 12), mu_bg * T * (1 - thinning))
    after[inside] += (MU_INC - mu_bg) * C * (1 - r_inc)
    return before, after, ROI(4, 8, 2, 6), ROI(4, 8, 7, 11)


def _improvement(r_inc, k, domain, **kw):
    before, after, inc, bg = _column_pair(r_inc, **kw)
    ref, reg = to_domain(after, domain), to_domain(before, domain)
    return improvement_factor(compression_contrast(ref, reg, k, domain=domain), ref, inc, bg)


@pytest.mark.parametrize("r_inc", [0.0, R / 4, R / 2, R])
@pytest.mark.parametrize("k", [1.0, 2.0])
def test_log_domain_column_model_closed_form(r_inc, k):
    """Line integrals: D_incl - D_bg = -dmu c r_inc and C_ref = dmu c (1 - r_inc), so the
    improvement is 1 - k r_inc / (1 - r_inc): 1 for a rigid inclusion, below 1 otherwise."""
    assert _improvement(r_inc, k, "log") == pytest.approx(1 - k * r_inc / (1 - r_inc), rel=1e-5)


@pytest.mark.parametrize("r_inc", [0.0, R / 4, R / 2, R])
@pytest.mark.parametrize("k", [1.0, 2.0])
def test_linear_domain_column_model_closed_form(r_inc, k):
    """-I/I0: C = I_bg - I_incl; improvement = 1 + k (1 - C_before / C_after), by hand."""
    lb, li = MU_BG * T, MU_BG * T + (MU_INC - MU_BG) * C
    lb2, li2 = MU_BG * T * (1 - R), MU_BG * T * (1 - R) + (MU_INC - MU_BG) * C * (1 - r_inc)
    c_before, c_after = math.exp(-lb) - math.exp(-li), math.exp(-lb2) - math.exp(-li2)
    assert _improvement(r_inc, k, "negative") == pytest.approx(1 + k * (1 - c_before / c_after), rel=1e-4)
    # I/I0 is -(-I/I0): every contrast changes sign, their ratios do not
    assert _improvement(r_inc, k, "linear") == pytest.approx(_improvement(r_inc, k, "negative"), rel=1e-6)


@pytest.mark.parametrize("domain", ["log", "negative"])
def test_stiffer_inclusion_improves_more_and_the_gain_scales_with_k(domain):
    """Elasticity's share: a stiff inclusion (thins a fifth as much as the tissue) against a
    control as soft as the background. Stiffer is better in both domains; the gain doubles
    from k = 1 to k = 2."""
    stiff = {k: _improvement(R / 5, k, domain) for k in (1.0, 2.0)}
    soft = {k: _improvement(R, k, domain) for k in (1.0, 2.0)}
    assert stiff[1.0] > soft[1.0] and stiff[2.0] > soft[2.0]
    assert stiff[2.0] - soft[2.0] == pytest.approx(2 * (stiff[1.0] - soft[1.0]), rel=1e-4)


def test_linear_domain_gains_without_any_stiffness_log_domain_does_not():
    """Intensity is exponential in the line integral: thinning the background raises the
    inclusion-background intensity difference by exp(mu t r) whatever the stiffness. With
    mu t = 2 an inclusion as soft as the background already improves (1.07 at k = 1 by the
    closed form); in line integrals the same control loses contrast."""
    soft_lin = {k: _improvement(R, k, "negative") for k in (1.0, 2.0)}
    assert 1.0 < soft_lin[1.0] < soft_lin[2.0]
    assert soft_lin[1.0] == pytest.approx(1.069, abs=0.001)
    soft_log = {k: _improvement(R, k, "log") for k in (1.0, 2.0)}
    assert soft_log[2.0] < soft_log[1.0] < 1.0
    # with a thin background (mu t < 1) the linear domain loses contrast too: exp is then no help
    assert _improvement(R, 1.0, "negative", mu_bg=0.01) < 1.0


@pytest.mark.parametrize("domain", ["log", "negative"])
def test_sign_convention_inclusion_that_loses_less_attenuation_gets_brighter(domain):
    """Where the inclusion's column loses less attenuation than the background's (its D is
    less negative), D - mean D is positive there: improvement > 1 at k = 1, larger at k = 2."""
    before, after, inc, bg = _column_pair(0.0)
    after[inc.slices] += 0.5 * MU_BG * T * R  # the inclusion column thins half as much
    ref, reg = to_domain(after, domain), to_domain(before, domain)
    d = difference(ref, reg)
    assert d[inc.slices].mean() > d[bg.slices].mean() and d.max() < 0
    f1, f2 = (improvement_factor(compression_contrast(ref, reg, k, domain=domain), ref, inc, bg) for k in (1.0, 2.0))
    assert 1.0 < f1 < f2
    assert f2 - 1 == pytest.approx(2 * (f1 - 1), rel=1e-4)


def _noisy_pair(rng, n=48):
    """A reference (a brighter square in a noisy slab) and the step before it, which every pixel
    of darkened less on compression (mean D = -0.05), its square less still."""
    ref = 1.0 + 0.2 * ROI(16, 32, 16, 32).mask((n, n)) + 0.01 * rng.standard_normal((n, n))
    d = -0.05 + 0.02 * ROI(16, 32, 16, 32).mask((n, n)) + 0.01 * rng.standard_normal((n, n))
    return ref.astype(np.float32), (ref - d).astype(np.float32)


def test_improvement_factor_se_warns_when_handed_an_enhanced_image():
    """Review s43: improvement_factor takes (enhanced, reference), improvement_factor_se
    (reference, registered, k); the same order given to both returned a wrong number in silence.
    An enhanced image minus its reference is k (D - mean D), zero-mean to rounding, which the
    difference of a compressed pair never is: that is caught wherever the enhanced image went."""
    import warnings

    from radiokit.measure import improvement_factor_se

    ref, reg = _noisy_pair(np.random.default_rng(5))
    inc, bg = ROI(20, 28, 20, 28), ROI(20, 28, 4, 12)
    enh = compression_contrast(ref, reg, 2.0)
    for pair in ((enh, ref), (ref, enh)):
        with pytest.warns(UserWarning, match=r"improvement_factor_se: reference - registered has zero mean.*enhanced"):
            improvement_factor_se(*pair, 2.0, inc, bg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        se = improvement_factor_se(reference=ref, registered=reg, k=2.0, inclusion=inc, background=bg)
        by_keyword = improvement_factor(reference=ref, enhanced=enh, inclusion=inc, background=bg)
    assert by_keyword == improvement_factor(enh, ref, inc, bg)
    # the two agree on the pair: IF = 1 + k C_D / C_R, C_D = 0.02, C_R = 0.2, within a few SEs
    assert abs(by_keyword - 1.2) < 4 * se and 0 < se < 0.1


# -- summary -----------------------------------------------------------------------------------
def test_summary_keys_and_values():
    ref = _six(5.0, [[1, 2], [3, 4]])
    enh = {1: ref * 1.5, 2.0: ref * 2}
    s = summary(ref, enh, INC, BG)
    # k keyed by number, as Results.improvement_factor and PAPER are (review s43: they were "1")
    assert set(s["enhanced"]) == {1.0, 2.0} and set(s["improvement_factor"]) == {1.0, 2.0}
    assert all(type(k) is float for k in s["improvement_factor"])
    assert s["reference"]["contrast"] == pytest.approx(2.5)
    assert s["enhanced"][1.0]["contrast"] == pytest.approx(3.75)
    assert s["enhanced"][2]["cnr"] == pytest.approx(5.0 / math.sqrt(5.0))  # std doubles too
    assert s["improvement_factor"] == pytest.approx({1.0: 1.5, 2.0: 2.0})
    assert set(radiokit.measure.PAPER["improvement_factor"]) == set(s["improvement_factor"])
    assert s["inclusion"] == {"row0": 1, "row1": 3, "col0": 1, "col1": 3}
    with pytest.raises(ValueError, match="two entries for k = 1"):
        summary(ref, {1: ref, 1.0: ref, "1": ref}, INC, BG)  # noqa: F601 (the duplicate key is the point)


# -- ROI -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pixel_size_mm", [0.05, 0.2, (0.1, 0.15)])
@pytest.mark.parametrize("origin_rc", [(0, 0), (120.5, -3.0)])
@pytest.mark.parametrize("roi", [ROI(10, 30, 40, 45), ROI(0, 1, 0, 1), ROI(-5, 6, 7, 1000)])
def test_roi_mm_round_trip(roi, pixel_size_mm, origin_rc):
    center_mm, size_mm = roi.to_mm(pixel_size_mm, origin_rc)
    assert ROI.from_mm(center_mm, size_mm, pixel_size_mm, origin_rc) == roi


def test_roi_from_mm_hand_values():
    # 0.1 mm pixels, origin at pixel (100, 200): centre (1 mm, -2 mm) -> pixel (110, 180);
    # 0.5 x 0.3 mm -> 5 x 3 pixels centred there
    assert ROI.from_mm((1.0, -2.0), (0.5, 0.3), 0.1, origin_rc=(100, 200)) == ROI(108, 113, 179, 182)
    center_mm, size_mm = ROI(108, 113, 179, 182).to_mm(0.1, (100, 200))
    assert center_mm == pytest.approx((1.0, -2.0)) and size_mm == pytest.approx((0.5, 0.3))


def test_roi_from_mm_edges_rounds_each_edge_half_up():
    """Edges in mm from the frame's corner (``radiokit process --mm``): an edge typed on a half
    pixel goes half up however its division rounds (0.35 / 0.1 is 3.4999999999999996), so a
    rectangle's width does not depend on where it sits; whole-pixel edges give what
    :meth:`ROI.from_mm` gives from the corner for the same rectangle."""
    assert ROI.from_mm_edges((0.35, 0.65, 0.45, 0.75), 0.1) == ROI(4, 7, 5, 8)
    assert ROI.from_mm_edges((0.35, 0.65, 0.45, 0.75), (0.1, 0.2)) == ROI(4, 7, 2, 4)  # 2.25 -> 2, 3.75 -> 4
    edges = (1.0, 1.5, 2.0, 2.3)
    assert ROI.from_mm_edges(edges, 0.1) == ROI.from_mm((1.25, 2.15), (0.5, 0.3), 0.1, (-0.5, -0.5))
    with pytest.raises(ValueError, match="empty"):
        ROI.from_mm_edges((0.1, 0.12, 0.0, 1.0), 0.1)


def test_find_rois_refusal_of_a_background_carries_the_inclusion_found():
    """Where only the background does not fit, :class:`NoBackgroundFits` holds the inclusion found
    and the reason without find_rois's advice, for a caller with ROIs of its own to offer."""
    from radiokit.measure import NoBackgroundFits

    img, _, _ = _dome_with_blob()
    with pytest.raises(NoBackgroundFits) as refused:
        find_rois(img, gap=200)
    exc = refused.value
    assert exc.inclusion.contains((70, 96)) and str(exc) == f"{exc.reason}; {NoBackgroundFits.ADVICE}"
    assert exc.reason.startswith("no ") and "background_size" not in exc.reason


def test_roi_geometry():
    roi = ROI(2, 6, 10, 13)
    assert roi.shape == (4, 3) and roi.center == (3.5, 11.0)
    assert roi.slices == (slice(2, 6), slice(10, 13))
    assert roi.contains((2, 10)) and roi.contains((5, 12)) and not roi.contains((6, 12))
    assert roi.contains(ROI(3, 5, 10, 11)) and not roi.contains(ROI(3, 7, 10, 11))
    assert roi.shifted(-2, 1) == ROI(0, 4, 11, 14)
    assert roi.clip((4, 12)) == ROI(2, 4, 10, 12)
    assert ROI.from_dict(roi.to_dict()) == roi
    assert ROI.from_center((3.5, 11.0), (4, 3)) == roi
    assert ROI.from_center((3, 11), 3) == ROI(2, 5, 10, 13)
    assert ROI.from_center((3, 11), 2) == ROI(3, 5, 11, 13)  # ties: half a pixel down/right
    assert ROI.from_center((2.5, 10.5), (3, 5)) == ROI(2, 5, 9, 14)  # 1.0 and 8.5 -> 9
    m = roi.mask((8, 14))
    assert m.sum() == 12 and m[2:6, 10:13].all()
    assert ROI(np.int64(1), np.int32(2), 0, 1).row0 == 1 and type(ROI(np.int64(1), 2, 0, 1).row0) is int


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ROI(3, 3, 0, 2), "empty"),
        (lambda: ROI(0, 2, 5, 4), "empty"),
        (lambda: ROI(0, 2.5, 0, 2), "integer"),
        (lambda: ROI.from_center((3, 3), 0.2), "empty"),
        (lambda: ROI.from_mm((1, 1), 1.0, 0.0), "pixel_size_mm"),
        (lambda: ROI.from_dict({"row0": 1, "row1": 2}), "missing col0, col1"),
        (lambda: ROI(0, 2, 0, 2).shifted(10, 10).clip((5, 5)), "outside"),
        (lambda: ROI(-1, 2, 0, 2).mask((5, 5)), "outside the 5x5 image"),
    ],
)
def test_roi_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


# -- bad inputs --------------------------------------------------------------------------------
def _nan_ref():
    ref = REF.copy()
    ref[0, 0] = np.nan
    return ref


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: compression_contrast(REF, np.zeros((4, 5))), "reference has shape .* registered has"),
        (lambda: compression_contrast(_nan_ref(), REF), "reference has 1 non-finite"),
        (lambda: compression_contrast(REF, np.full((4, 4), np.inf)), "registered has 16 non-finite"),
        (lambda: compression_contrast(REF, REF, np.nan), "k must be a finite"),
        (lambda: compression_contrast(REF, REF, "2"), "k must be a finite"),
        (lambda: compression_contrast(REF, REF, domain="counts"), "domain must be one of"),
        (lambda: compression_contrast(REF, REF, domain="negative"), "negative intensities"),
        (lambda: compression_contrast(-REF, -REF, domain="linear"), "expects transmission I/I0"),
        (lambda: compression_contrast(REF, REF, mask=np.zeros((4, 4), bool)), "mask is empty"),
        (lambda: compression_contrast(REF, REF, mask=np.ones((4, 4))), "boolean"),
        (lambda: compression_contrast(REF, REF, mask=np.ones((3, 4), bool)), "mask has shape"),
        (lambda: compression_contrast(REF, REF, mask=ROI(0, 5, 0, 1)), "mask ROI.* outside"),
        (lambda: compression_contrast(REF[0], REF[0]), "2-D"),
        (lambda: to_domain(REF, "exp"), "domain must be one of"),
        (lambda: contrast(REF, ROI(0, 2, 0, 2), ROI(3, 5, 0, 2)), "background ROI.* outside the 4x4"),
        (lambda: contrast(REF, ROI(-1, 2, 0, 2), ROI(0, 2, 0, 2)), "inclusion ROI.* outside"),
        (lambda: contrast(_nan_ref(), ROI(0, 2, 0, 2), ROI(2, 4, 2, 4)), "non-finite .* inside inclusion"),
        (lambda: contrast(REF, np.zeros((4, 4), bool), ROI(0, 2, 0, 2)), "inclusion mask is empty"),
        (lambda: contrast(REF, [[1, 2]], ROI(0, 2, 0, 2)), "inclusion must be an ROI or a boolean mask"),
        (
            lambda: improvement_factor(REF, np.ones((4, 4)), ROI(1, 3, 1, 3), ROI(0, 1, 0, 4)),
            "reference contrast is zero",
        ),
        (lambda: improvement_factor(REF, REF[:3], ROI(1, 3, 1, 3), ROI(0, 1, 0, 4)), "enhanced has shape"),
        (
            lambda: change_ratio(REF, REF + 1.0 * (REF > 5), ROI(1, 3, 1, 3), ROI(0, 1, 0, 4)),
            "background .* does not change",
        ),
        (lambda: change_ratio(REF, REF[:, :3], ROI(1, 3, 1, 3), ROI(0, 1, 0, 3)), "before has shape"),
        (lambda: profile(REF, (0, 0), (4, 0)), "end_rc .* outside"),
        (lambda: profile(REF, (0, 0), (3, 0), width=0), "width must be >= 1"),
    ],
)
def test_bad_inputs_raise_clear_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# -- profiles ------------------------------------------------------------------------------------
@pytest.mark.parametrize("width", [1, 3, 4])
@pytest.mark.parametrize("start, end", [((5, 3), (30, 40)), ((20, 2), (20, 45)), ((35, 10), (4, 12.5))])
def test_profile_matches_scikit_image(start, end, width):
    img = np.random.default_rng(2).normal(size=(40, 50))
    d, v = profile(img, start, end, width=width)
    np.testing.assert_allclose(v, profile_line(img, start, end, linewidth=width, mode="nearest"), atol=1e-12)
    assert d[0] == 0 and d[-1] == pytest.approx(math.hypot(end[0] - start[0], end[1] - start[1]))


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.uint16, np.int32])
def test_profile_through_a_ramp_interpolates_in_float(dtype):
    img = np.tile(np.arange(11) * 2, (5, 1)).astype(dtype)  # value = 2 * col
    d, v = profile(img, (2, 0.5), (2, 9.5), width=3)  # samples between pixels: odd values
    assert v.dtype == np.float64
    np.testing.assert_allclose(d, np.arange(10.0))
    np.testing.assert_allclose(v, 1 + 2 * np.arange(10.0), atol=1e-6)


# -- automatic ROIs ------------------------------------------------------------------------------
def _dome_with_blob(domain="log", noise=0.005, centre=(70, 96), radius=12.0, seed=0):
    """A compressed-breast-like dome in line integrals with a spherical inclusion, air around."""
    rows, cols = 150, 180
    yy, xx = np.mgrid[:rows, :cols].astype(float)
    q = 1 - ((yy - 75) / 65) ** 2 - ((xx - 90) / 80) ** 2
    thickness = 50 * np.sqrt(np.clip(q, 0, None))
    r = np.hypot(yy - centre[0], xx - centre[1])
    chord = 2 * np.sqrt(np.clip(radius**2 - r**2, 0, None)) * 0.4  # 0.4 mm pixels
    L = 0.05 * thickness + 0.05 * chord
    L = L + np.random.default_rng(seed).normal(0, noise, L.shape)
    return to_domain(L, domain), r < radius, thickness > 0


@pytest.mark.parametrize("domain", ["log", "negative"])
@pytest.mark.parametrize("pixel_size_mm", [None, 0.4])
@pytest.mark.parametrize("centre", [(70, 96), (60, 40), (80, 140)])
def test_find_rois_on_a_blob(domain, pixel_size_mm, centre):
    img, blob, body = _dome_with_blob(domain, centre=centre)
    inc, bg = find_rois(img, pixel_size_mm=pixel_size_mm)
    assert blob[inc.slices].all(), "inclusion ROI must lie inside the blob"
    assert inc.shape[0] >= 6, "and be a useful size (the blob is 24 px across)"
    assert not blob[bg.slices].any() and body[bg.slices].all(), "background outside the blob, inside the body"
    assert bg.shape == inc.shape
    assert abs(bg.center[0] - inc.center[0]) <= 0.5  # level with it, beside it
    # default gap: half the width of the half-maximum extent (0.87 of the sphere's), from its edge
    gap = max(bg.col0 - (centre[1] + 12), centre[1] - 12 - bg.col1)
    assert 6 <= gap <= 12


@pytest.mark.parametrize("radius, centre", [(3.0, (40.0, 40.0)), (4.0, (50.25, 49.75)), (5.5, (60.5, 60.5))])
def test_a_neighbours_reach_covers_the_widest_extent_it_can_have(radius, centre):
    """Review s44: near() looks only at candidates within 7.2 of their radii of a ROI, a number
    that was 1.2 x 1.5 x 4 of the extent's factors written out. Every one-pixel ROI that the
    widest extent overlaps (its half-maximum region filling the fit's limit at the largest
    scale, grown) must be within that reach: the growth maps each ROI pixel to the region's
    nearest, and ROIs up to 0.7 px beyond 7.2 radii overlapped it unseen."""
    M = radiokit.measure
    big = max(M._EXTENT_SCALES) * radius
    pr, pc = centre
    reach = int(np.ceil(3 * big)) + 1  # the window _blob_fit takes at that scale
    r0, c0 = round(pr) - reach, round(pc) - reach
    v = (np.arange(r0, round(pr) + reach + 1) - pr) / big
    u = (np.arange(c0, round(pc) + reach + 1) - pc) / big
    dist = np.hypot(v[:, None], u[None, :])
    # a residual above half its peak everywhere: the region is all the fit's limit lets it be
    region = M._half_maximum_window((np.ones_like(dist), (r0, c0), dist), big)
    assert region[0].sum() == np.count_nonzero(dist <= M._RING_INNER)
    near = M._Neighbours.__new__(M._Neighbours)  # one candidate, its extent given
    near._cands, near._extents = [(centre, radius, 1)], {0: [region]}
    yy, xx = np.mgrid[round(pr - 9 * radius) : round(pr + 9 * radius), round(pc - 9 * radius) : round(pc + 9 * radius)]
    d = np.hypot(yy - pr, xx - pc)
    ring = (d > 6 * radius) & (d < 9 * radius)
    hit = [dd for y, x, dd in zip(yy[ring], xx[ring], d[ring]) if near._extent_overlaps(0, ROI(y, y + 1, x, x + 1))]
    # the grown extent reaches 1.2 x 1.5 x 4 radii, give or take the pixel it is sampled on
    assert max(hit) == pytest.approx(M._EXTENT_REACH * radius, abs=1.0)
    assert max(hit) < M._reach_px(radius)


def test_find_rois_goes_right_when_left_leaves_the_body():
    img, blob, body = _dome_with_blob(centre=(75, 40))
    inc, bg = find_rois(img)
    assert bg.col0 > 40 and body[bg.slices].all() and not blob[bg.slices].any()


@pytest.mark.parametrize("mask_kind", ["disk", "rectangle"])
def test_find_rois_with_an_inclusion_mask(mask_kind):
    img, blob, body = _dome_with_blob()
    if mask_kind == "rectangle":
        blob = np.zeros_like(blob)
        blob[60:80, 86:116] = True  # 20 x 30: the largest square is 20, shrunk to 70 % -> 13 or 15
    inc, bg = find_rois(img, inclusion_mask=blob)
    assert blob[inc.slices].all() and not blob[bg.slices].any() and body[bg.slices].all()
    if mask_kind == "rectangle":
        assert inc.shape in ((13, 13), (15, 15))


@pytest.mark.parametrize("use_mask", [True, False])
def test_find_rois_sizes_and_gap_in_mm(use_mask):
    img, blob, body = _dome_with_blob()
    inc, bg = find_rois(
        img,
        pixel_size_mm=0.4,
        inclusion_size=2.0,
        gap=4.0,
        background_size=(2.0, 4.0),
        inclusion_mask=blob if use_mask else None,
    )
    assert inc.shape == (5, 5) and bg.shape == (5, 10)  # 2 mm = 5 px, 4 mm = 10 px
    assert blob[inc.slices].all() and inc.contains((70, 96))
    # 4 mm = 10 px from the blob's bounding box, cols [85, 108) (the mask), or from the
    # detected half-maximum extent, up to 2 px inside it
    gap = max(bg.col0 - 108, 85 - bg.col1)
    assert (gap == 10) if use_mask else (8 <= gap <= 10)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(inclusion_mask=np.zeros((150, 180), bool)), "inclusion_mask is empty"),
        (dict(inclusion_mask=np.ones((10, 10), bool)), "inclusion_mask must be a bool array"),
        (dict(gap=200), "no .* background ROI fits"),
    ],
)
def test_find_rois_errors(kw, match):
    img, _, _ = _dome_with_blob()
    with pytest.raises(ValueError, match=match):
        find_rois(img, **kw)


def test_find_rois_featureless_image_says_no_inclusion():
    with pytest.raises(ValueError, match="no inclusion found"):
        find_rois(np.random.default_rng(0).normal(2.0, 0.01, (80, 80)))


@pytest.mark.parametrize("level", [1.0, -0.5, 2.0e4])
def test_find_rois_on_a_constant_image_says_no_inclusion(level):
    """A constant image has no blob brighter than its surroundings: the fit's rounding (1e-16)
    stood "8 standard errors" above a rounding-sized scatter, and an inclusion was returned."""
    with pytest.raises(ValueError, match="no inclusion found"):
        find_rois(np.full((64, 64), level))


def _slab(extra_l, ripple, seed, shape=(192, 256)):
    """A gel slab (line integral 0.8) with a smooth thickness ripple (std ``ripple`` of it,
    correlated over ~6 px) under Poisson noise at 3000 counts, and a disc of ``extra_l`` (radius
    14 px) at (96, 120); ``-ln(counts / 3000)``."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    t = ndimage.gaussian_filter(rng.standard_normal(shape), 6.0)
    body = (rr >= 20) & (rr < shape[0] - 20) & (cc >= 24) & (cc < shape[1] - 24)
    L = body * (0.8 * (1 + ripple * t / t.std()) + extra_l * (np.hypot(rr - 96, cc - 120) <= 14))
    return (-np.log(np.maximum(rng.poisson(3000 * np.exp(-L)), 1) / 3000)).astype(np.float32)


@pytest.mark.parametrize("seed", [3, 4])
def test_find_rois_near_uniform_slab_says_no_inclusion(seed):
    """A slab whose thickness ripples by 1 % (0.008 in L, under the pixel noise of 0.027) has no
    inclusion: its strongest ripple was "8 standard errors" above white noise (the ripple is
    correlated over the blob, the standard error assumed it is not) and an inclusion was invented."""
    with pytest.raises(ValueError, match="no inclusion found"):
        find_rois(_slab(0.0, 0.01, seed), pixel_size_mm=0.1)


@pytest.mark.parametrize("extra", [0.2, -0.2])
def test_find_rois_finds_a_denser_or_a_less_dense_inclusion(extra):
    """The same slab with a disc 0.2 denser or 0.2 less dense (in L) than the gel: found where
    it is, with the contrast's sign its density's (a less dense one was passed over for the
    ripple's strongest bump)."""
    img = _slab(extra, 0.01, 5)
    inc, bg = find_rois(img, pixel_size_mm=0.1)  # a 2x2-binned panel: blobs of 1.5-3.2 mm
    assert inc.contains((96, 120)) and np.hypot(*np.subtract(inc.center, (96, 120))).max() <= 2
    assert contrast(img, inc, bg) == pytest.approx(extra, abs=0.03)  # the ripple's 0.008 and noise


def test_find_rois_prefers_a_denser_inclusion_to_a_stronger_dark_bubble():
    """The paper's inclusion is denser than the gel; an air bubble (less dense, here standing out
    twice as much) must not take its place: a dark blob is taken only when no bright one stands out."""
    rr, cc = np.mgrid[0:192, 0:256]
    img = _slab(0.2, 0.01, 6)
    img[np.hypot(rr - 100, cc - 190) <= 12] -= 0.4  # the bubble, clear of the inclusion's ring
    inc, bg = find_rois(img, pixel_size_mm=0.1)
    assert inc.contains((96, 120)) and contrast(img, inc, bg) > 0.15


def _with_spheres(body, spheres, noise=0.01, seed=7):
    """``body`` (line integrals) with spheres on it, each ``((row, col), radius, peak line
    integral)`` (a negative peak: less dense than the body), and Gaussian noise; as a panel's
    reference at 0.1 mm pixels."""
    rr, cc = np.mgrid[: body.shape[0], : body.shape[1]].astype(float)
    img = body.astype(float)
    for (r, c), radius, peak in spheres:
        img += peak * np.sqrt(np.clip(radius**2 - (rr - r) ** 2 - (cc - c) ** 2, 0, None)) / radius
    return img + np.random.default_rng(seed).normal(0, noise, img.shape)


def _assert_clean_background(img, bg, clear_of, radius):
    """The background ROI reads the clean body, 0.5, within 5 standard errors of its mean (noise
    about 0.01 in L a pixel), and lies wholly outside ``radius`` of ``clear_of``."""
    n = bg.shape[0] * bg.shape[1]
    assert img[bg.slices].mean() == pytest.approx(0.5, abs=5 * 0.01 / math.sqrt(n))
    rows, cols = np.mgrid[bg.slices]
    assert np.hypot(rows - clear_of[0], cols - clear_of[1]).min() > radius


@pytest.mark.parametrize("peak", [0.2, -0.2])
def test_find_rois_keeps_the_background_off_a_second_inclusion(peak):
    """Review s41proc: a second, smaller sphere (denser or less dense) 38 px left of the
    inclusion lay under the background ROI (it was kept clear of the chosen inclusion only): the
    log contrast read 28 % low and the CNR 2.5 instead of ~30, exit code 0. The background must
    read the clean body, 0.5, within the noise of its mean."""
    rr, cc = np.mgrid[:256, :256]
    disc = 0.5 / (1 + np.exp((np.hypot(rr - 128, cc - 128) - 107.5) / 3.0))  # a 3 px soft edge
    img = _with_spheres(disc, [((128, 150), 20, 0.3), ((128, 112), 8, peak)])
    inc, bg = find_rois(img, pixel_size_mm=0.1)
    assert inc.contains((128, 150))
    _assert_clean_background(img, bg, clear_of=(128, 112), radius=8)  # not on the second sphere at all


def test_find_rois_keeps_the_background_off_a_weak_neighbour_among_several():
    """Review s43det: detection kept three LoG peaks a scale and sign, so with three stronger
    blobs of a neighbour's scale beside the inclusion (inclusions, bubbles) the weakest one was
    never seen and the background ROI was placed on it: the contrast read 0.265 for 0.288 (8 %
    low), silently. Counts under Poisson noise (about 0.01 in L); the background must read the
    clean body, 0.5, within the noise of its mean."""
    rr, cc = np.mgrid[:192, :192]
    disc = 0.5 / (1 + np.exp((np.hypot(rr - 95.5, cc - 95.5) - 86) / 3.0))
    weak = ((96, 82), 4, 0.08)  # where the default (left) background ROI lies
    strong = [((r, c), 4, 0.2) for r, c in [(70, 75), (122, 75), (70, 135)]]
    truth = _with_spheres(disc, [((96, 107), 10, 0.3), weak, *strong], noise=0.0)
    counts = np.random.default_rng(8).poisson(16500 * np.exp(-truth))
    img = -np.log(counts / 16500)
    inc, bg = find_rois(img, pixel_size_mm=0.4)
    assert inc.contains((96, 107))
    _assert_clean_background(img, bg, clear_of=(96, 82), radius=4)  # not on the weak sphere at all


def test_find_rois_keeps_the_background_off_a_weak_neighbour_among_many():
    """Review s43bub: detection kept the 16 strongest LoG peaks a scale and sign over the whole
    body, so with more stronger blobs of a neighbour's scale elsewhere (a phantom of many air
    bubbles) the weak one beside the inclusion was never seen and the background ROI was placed
    on it, silently. The background must read the clean body, 0.5, within the noise of its mean."""
    rr, cc = np.mgrid[:256, :256]
    disc = 0.5 / (1 + np.exp((np.hypot(rr - 127.5, cc - 127.5) - 118) / 3.0))
    weak = ((128, 114), 4, 0.08)  # where the default (left) background ROI lies
    far = [((r, c), 4, 0.2) for r in (64, 84, 172, 192) for c in range(80, 200, 24)]  # 20, all stronger
    truth = _with_spheres(disc, [((128, 139), 10, 0.3), weak, *far], noise=0.0)
    img = -np.log(np.random.default_rng(8).poisson(16500 * np.exp(-truth)) / 16500)
    inc, bg = find_rois(img, pixel_size_mm=0.4)
    assert inc.contains((128, 139))
    _assert_clean_background(img, bg, clear_of=(128, 114), radius=4)  # not on the weak sphere at all


@pytest.mark.parametrize(
    "centre, semi_axes",
    [((120, 89), (40, 40)), ((120, 103), (6, 30))],
    ids=["sphere-beyond-the-largest-scale", "elongated"],
)
def test_find_rois_keeps_the_background_off_a_big_or_elongated_neighbour(centre, semi_axes):
    """Review s43det: a neighbour was kept clear by a disc of 1.2 of its LoG scale's radius, and
    the scales end at 12 mm: a sphere of 20 mm radius (40 px at 0.5 mm, the largest scale 24 px)
    or an ellipsoid 3 mm across and 30 mm long got a disc short of its rim, and the background ROI
    sat on it: the contrast read 0.259 and 0.222 for 0.288, silently. The background must read
    the clean body, 0.5, within the noise of its mean, off the neighbour."""
    rr, cc = np.mgrid[:240, :240]
    (r, c), (a, b) = centre, semi_axes
    truth = 0.5 / (1 + np.exp((np.hypot(rr - 119.5, cc - 119.5) - 110) / 3.0))
    truth = truth + 0.3 * np.sqrt(np.clip(1 - ((rr - 120) ** 2 + (cc - 150) ** 2) / 100, 0, None))
    truth = truth + 0.2 * np.sqrt(np.clip(1 - ((rr - r) / a) ** 2 - ((cc - c) / b) ** 2, 0, None))
    img = -np.log(np.random.default_rng(9).poisson(16500 * np.exp(-truth)) / 16500)
    inc, bg = find_rois(img, pixel_size_mm=0.5)
    assert inc.contains((120, 150))
    n = bg.shape[0] * bg.shape[1]
    assert img[bg.slices].mean() == pytest.approx(0.5, abs=5 * 0.01 / math.sqrt(n))
    rows, cols = np.mgrid[bg.slices]
    assert (((rows - r) / a) ** 2 + ((cols - c) / b) ** 2).min() > 1  # not on the neighbour at all


def test_find_rois_refuses_when_other_structures_take_every_side():
    """A denser sphere left of the inclusion, a less dense one right of it, and the body too low
    for a background above or below: no background is placed on either; the refusal says where
    they are."""
    rr, cc = np.mgrid[:200, :320]
    edge = np.minimum.reduce([rr - 52, 148 - rr, cc - 20, 300 - cc])
    band = 0.5 / (1 + np.exp(-edge / 3.0))
    img = _with_spheres(band, [((100, 160), 20, 0.3), ((100, 122), 8, 0.2), ((100, 198), 8, -0.2)])
    with pytest.raises(ValueError) as err:
        find_rois(img, pixel_size_mm=0.1)
    words = str(err.value)
    assert re.search(
        r"left: overlaps another structure at \(100, 12\d\); right: overlaps another structure at \(100, 19\d\)", words
    ), words
    assert "above: leaves the body; below: leaves the body" in words and "\n" not in words


def test_body_mask_refuses_non_finite_pixels():
    """One NaN pixel made every comparison False: an empty body, silently (find_rois refuses NaN)."""
    img = np.zeros((32, 32))
    img[8:24, 8:24] = 1.0
    img[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        radiokit.measure.body_mask(img)


# -- the examples in the docstrings run, and the core does not reach into sim/acquisition -------
@pytest.mark.parametrize("module", [radiokit.enhance, radiokit.measure])
def test_docstring_examples(module):
    result = doctest.testmod(module, extraglobs={"np": np}, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 4 and result.failed == 0


def test_core_imports_neither_sim_nor_acquisition():
    code = (
        "import sys, radiokit.enhance, radiokit.measure; "
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('sim', 'acquisition')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("domain", ["linear", "negative"])
def test_to_domain_refuses_line_integrals_whose_transmission_overflows(domain):
    """``exp(-L)`` of L = -100 (a transmission of e^100, no radiograph's) is beyond float32: it
    came back inf, silently."""
    with pytest.raises(ValueError, match="overflows"):
        to_domain(np.array([[0.0, -100.0]]), domain)


def test_a_rectangle_given_as_a_tuple_is_told_how_to_write_it():
    """``contrast(img, (r0, r1, c0, c1), ...)`` -- how Config, --inclusion and roi_observed take
    a rectangle -- was told "got tuple of dtype int64"; the line now shows the ROI to write."""
    img = np.zeros((8, 8))
    with pytest.raises(ValueError, match=r"inclusion .*ROI\(0, 2, 0, 2\)"):
        contrast(img, (0, 2, 0, 2), ROI(4, 6, 4, 6))


def test_a_one_frame_stack_or_a_file_name_where_an_image_belongs_is_told_what_to_pass():
    """``radiokit.io.read`` gives ``(n, rows, cols)`` always, so a newcomer's first call passes
    ``read(path).data`` -- a stack of one frame -- or the path itself where one image belongs,
    and was told only "must be a 2-D (rows, cols) array, got shape (1, 8, 8)" (or ``()``)."""
    from radiokit.register import register

    stack = np.random.default_rng(0).random((1, 16, 16))
    for call in (
        lambda: contrast(stack, ROI(0, 2, 0, 2), ROI(4, 6, 4, 6)),
        lambda: compression_contrast(stack, stack, 1),
        lambda: register(stack, stack),
    ):
        with pytest.raises(ValueError, match=r"\.data\[0\]"):
            call()
    for call in (lambda: compression_contrast("ref.tif", "reg.tif", 1), lambda: register("f.tif", "m.tif")):
        with pytest.raises(ValueError, match=r"file name.*radiokit\.io\.read"):
            call()


# -- masked arrays: refused, never their mask dropped ------------------------------------------
_MASKED = np.ma.masked_array(
    np.where(np.pad(np.ones((6, 6), bool), ((2, 24), (2, 24))), 1e6, 1.0),
    mask=np.pad(np.ones((6, 6), bool), ((2, 24), (2, 24))),
)
_INC, _BG = ROI(2, 8, 2, 9), ROI(20, 28, 20, 28)
_PLAIN = np.ones((32, 32))


@pytest.mark.parametrize(
    "call, keyword",
    [
        (lambda: contrast(_MASKED, _INC, _BG), None),
        (lambda: cnr(_MASKED, _INC, _BG), None),
        (lambda: weber(_MASKED, _INC, _BG), None),
        (lambda: improvement_factor(_MASKED, _PLAIN, _INC, _BG), None),
        (lambda: change_ratio(_PLAIN, _MASKED, _INC, _BG), None),
        (lambda: summary(_MASKED, {1: _PLAIN}, _INC, _BG), None),
        (lambda: profile(_MASKED, (0, 0), (5, 5)), None),
        (lambda: radiokit.measure.body_mask(_MASKED), None),
        (lambda: find_rois(_MASKED), "body_mask"),
        (lambda: compression_contrast(_MASKED, _PLAIN), "mask"),
        (lambda: compression_contrast(_PLAIN, _MASKED), "mask"),
        (lambda: difference(_MASKED, _PLAIN), None),
        (lambda: to_domain(_MASKED, "linear"), None),
        (lambda: contrast(_PLAIN, np.ma.masked_array(_INC.mask((32, 32)), mask=~_INC.mask((32, 32))), _BG), None),
        (lambda: compression_contrast(_PLAIN, _PLAIN, mask=np.ma.masked_array(_PLAIN > 0)), None),
    ],
)
def test_masked_arrays_are_refused_not_their_mask_dropped(call, keyword):
    """``contrast(ma.masked_array(img, mask=dead), ...)`` returned 857142.0: the dead pixels'
    values (1e6) averaged in, the mask dropped by np.asarray."""
    with pytest.raises(ValueError, match="is a masked array, whose mask would be ignored: pass .*filled") as info:
        call()
    assert "\n" not in str(info.value)
    if keyword:
        assert f"{keyword}=" in str(info.value)
