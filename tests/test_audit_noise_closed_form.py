"""Closed-form audit (session 37): the noise the simulation predicts and the correction passes on,
the improvement bound's reach, and the paper's measures on a pair moved by a known affine map.

The closed forms, written down before reading ``sim.study`` and ``radiokit.correct``:

- bilinear interpolation at fractional offsets ``(fr, fc)`` is a weighted sum of four independent
  pixels, so it multiplies white noise's variance by ``((1 - fr)^2 + fr^2) ((1 - fc)^2 + fc^2)``:
  1 at whole pixels, 1/4 at half a pixel both ways. The registered moving image of a study is the
  noisy moving image pulled by its field, so the enhanced image ``R + k (R - M_reg - mean D)``
  has per-pixel variance ``(1 + k)^2 var_R + k^2 w var_M`` with ``w`` that factor, and over an ROI
  the mean of ``w`` (the CNR's denominator is the ROI's variance: structure plus mean noise
  variance);
- flat and dark correction ``T = (I - D) / (F - D)`` with ``D`` the mean of ``n_D`` darks and ``F``
  of ``n_F`` flats, signals ``a = g I0 T`` and ``b = g I0`` above the dark, read variance ``s^2``
  (with the ADC's 1/12), ``v_D = s^2 / n_D``: to first order
  ``var T = T^2 [(g q a + s^2 + v_D) / a^2 + ((g q b + s^2) / n_F + v_D) / b^2 - 2 v_D / (a b)]``
  (the dark is common to numerator and denominator: the covariance term), and
  ``var(-ln T) = var T / T^2``.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from conftest import square_pair


def _interp_variance_factor(field):
    f = np.asarray(field, np.float64) - np.floor(field)
    return ((1 - f[0]) ** 2 + f[0] ** 2) * ((1 - f[1]) ** 2 + f[1] ** 2)


@pytest.mark.parametrize("offset", [(0.5, 0.5), (0.3, 0.0)])
@pytest.mark.parametrize("domain", ["negative", "log"])
def test_predicted_cnr_counts_the_registrations_interpolation_of_the_moving_noise(domain, offset):
    """A pair registered with a field of fractional pixels: ``predicted_cnr`` must predict the CNR
    of noisy images registered with that field, as ``sim.study.images`` registers them (the
    moving image's noise pulled through bilinear interpolation, its variance times ``w``). At half
    a pixel both ways ``w = 1/4``, and without it the prediction of the k = 2 CNR is 14 % low
    (``sqrt(13 / 10)``); the measured CNR is compared within five standard errors of its mean."""
    from radiokit.enhance import compression_contrast, to_domain
    from radiokit.measure import cnr, contrast
    from radiokit.register import warp
    from sim import study

    n, counts, samples = 160, 2000.0, 24
    reference, moving, mask = square_pair(n)
    field = np.empty((2, n, n), np.float32)
    field[0], field[1] = offset
    registered = warp(moving.astype(np.float32), field).astype(np.float64)
    pair = study.ImagePair(reference, moving, registered, field, field, mask, 0.25, None, "side")
    h = study.headline(pair)
    predicted = study.predicted_cnr(pair, h, counts, domain)

    # the closed form, from the noise-free images and the field alone
    bg = h.background
    w = float(_interp_variance_factor(field[:, bg.slices[0], bg.slices[1]]).mean())
    assert w == pytest.approx(((1 - offset[0]) ** 2 + offset[0] ** 2) * ((1 - offset[1]) ** 2 + offset[1] ** 2))
    sign = 1.0 if domain == "log" else -1.0
    var_r = math.exp(sign * reference[bg.slices].mean()) / counts
    var_m = math.exp(sign * registered[bg.slices].mean()) / counts
    ref_d, reg_d = to_domain(reference, domain), to_domain(registered, domain)
    assert predicted["reference"] == pytest.approx(contrast(ref_d, h.inclusion, bg) / math.sqrt(var_r), rel=1e-9)
    for key in ("1", "2"):
        k = float(key)
        c_e = contrast(compression_contrast(ref_d, reg_d, k, domain=domain), h.inclusion, bg)
        expected = c_e / math.sqrt((1 + k) ** 2 * var_r + k * k * w * var_m)
        assert predicted[key] == pytest.approx(expected, rel=1e-6), key

    # and the sampled CNR agrees with it
    rng = np.random.default_rng(12)
    measured = {key: [] for key in predicted}
    for _ in range(samples):
        r = study.add_noise(reference, counts, rng)
        m = warp(study.add_noise(moving, counts, rng).astype(np.float32), field).astype(np.float64)
        r, m = to_domain(r, domain), to_domain(m, domain)
        measured["reference"].append(cnr(r, h.inclusion, bg))
        for key in ("1", "2"):
            measured[key].append(cnr(compression_contrast(r, m, float(key), domain=domain), h.inclusion, bg))
    for key, values in measured.items():
        standard_error = np.std(values, ddof=1) / np.sqrt(samples)
        assert np.mean(values) == pytest.approx(predicted[key], abs=5 * standard_error), key


def test_flat_and_dark_correction_passes_on_the_noise_of_its_three_inputs():
    """The model C7942 (shot noise ``q`` counts per quantum, read noise, 12-bit rounding) through
    ``Calibration.from_frames`` and ``correct_frames``: the per-pixel variance of the corrected
    transmission and line integral over repeated acquisitions (new darks, flats and projection
    each time) is the closed form above. 120 repetitions of 32 x 32 pixels: the pooled ratio's
    standard error is ``sqrt(2 / 119 / 1024)`` = 0.4 %, compared within 2 % (the first-order form's
    own error is ``var T / T^2`` = 0.2 % here). Leaving out the covariance term would be +3 %,
    leaving out the flats' noise -9 %."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames
    from sim.detector import PanelModel

    size, n_d, n_f, T, i0, q, reps = 32, 4, 4, 0.3, 2000.0, 1.5, 120
    panel = PanelModel(
        rows=size, cols=size, n_dead=0, n_under=0, n_noisy=0, defect_columns=(), counts_per_quantum=q, seed=3
    )
    line = np.full(panel.shape, -math.log(T), np.float32)
    rng = np.random.default_rng(4)
    lin, log = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # few calibration frames: the calibration says so
        for _ in range(reps):
            cal = Calibration.from_frames(panel.dark_frames(n_d, rng), panel.flat_frames(n_f, i0, rng))
            raw = panel.expose(line, i0, 1, rng)[0]
            lin.append(correct_frames(cal, raw, domain="linear"))
            log.append(correct_frames(cal, raw, domain="log"))
    g = panel.gain.astype(np.float64)
    s2 = float(panel.read_noise) ** 2 + 1 / 12
    a, b, v_d = g * i0 * T, g * i0, s2 / n_d
    var_t = T**2 * ((g * q * a + s2 + v_d) / a**2 + ((g * q * b + s2) / n_f + v_d) / b**2 - 2 * v_d / (a * b))
    lin, log = np.asarray(lin, np.float64), np.asarray(log, np.float64)
    assert abs(lin.mean() - T) < 5 * math.sqrt(var_t.mean() / lin.size) + T * var_t.mean() / T**2
    assert float(np.mean(lin.var(axis=0, ddof=1) / var_t)) == pytest.approx(1.0, abs=0.02)
    assert float(np.mean(log.var(axis=0, ddof=1) / (var_t / T**2))) == pytest.approx(1.0, abs=0.02)


# -- the improvement factor's bound holds for a monochromatic primary beam only ---------------------
def _rigid_pair_if(F, mu_b, dmu, gap_ref, dg, chord):
    """IF(1) in the log and negative domains of columns between rigid plates, a rigid inclusion of
    chord ``chord``, each column's line integral ``F(mu_b g + dmu c)``."""
    L = {g: (F(mu_b * g), F(mu_b * g + dmu * chord)) for g in (gap_ref, gap_ref + dg)}
    c_log = {g: inc - bg for g, (bg, inc) in L.items()}
    c_neg = {g: math.exp(-bg) - math.exp(-inc) for g, (bg, inc) in L.items()}
    return {
        "log": 2 - c_log[gap_ref + dg] / c_log[gap_ref],
        "negative": 2 - c_neg[gap_ref + dg] / c_neg[gap_ref],
    }


def test_beam_hardening_alone_lifts_a_rigid_inclusions_log_improvement_above_the_bound():
    """Through rigid plates a rigid inclusion reaches ``improvement_bound`` exactly for Beer-Lambert
    (one energy). The polychromatic line integral ``F(x) = -ln sum_E w_E exp(-a s_E x)`` is concave
    (beam hardening): the same density step behind a thinner column is worth more, so the log
    contrast grows as the gap closes and IF(1) passes 1 with no scatter, misregistration or noise:
    1.011 for seed-breast's tube (28 kV Mo, matched at its 50 mm). The bound is the monochromatic
    primary beam's (measure.improvement_bound's Notes; the pipeline's bound basis says so)."""
    from radiokit.measure import improvement_bound

    mu_b, dmu, gap_ref, dg, chord = 0.05, 0.05, 37.5, 2.5, 8.0
    mono = _rigid_pair_if(lambda x: x, mu_b, dmu, gap_ref, dg, chord)
    assert mono["log"] == pytest.approx(improvement_bound(1, mu_b, dg, "log"), abs=1e-12)
    assert mono["negative"] == pytest.approx(improvement_bound(1, mu_b, dg, "negative"), rel=1e-12)
    from sim.imaging import tube

    tube = tube(28.0, "Mo", 50.0)  # seed-breast's, matched at its gap
    a = tube.scale_for(mu_b)
    poly = _rigid_pair_if(
        lambda x: -math.log(float(tube.weights @ np.exp(-a * tube.shape * x))), mu_b, dmu, gap_ref, dg, chord
    )
    assert poly["log"] == pytest.approx(1.011, abs=1e-3)
    assert poly["log"] > improvement_bound(1, mu_b, dg, "log") + 0.005


def test_a_simulated_files_bound_says_when_its_imaging_can_pass_it(tmp_path):
    """``radiokit process`` prints the bound beside the measured IF; for a file simulated with the
    tube's spectrum or scatter (the presets' imaging) its basis must say the bound is the
    monochromatic primary beam's, or a log-domain IF of 1.03 reads as misregistration."""
    from radiokit.enhance import Domain
    from radiokit.io import ExperimentWriter, ImageKey
    from radiokit.pipeline import _bound
    from sim.scene import load_scene, with_imaging

    path, shape = tmp_path / "exp.h5", (8, 8)
    with ExperimentWriter(path, shape=shape) as w:
        w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
        w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, gap in enumerate((42.5, 40.0, 37.5), start=1):
            w.append(np.full(shape, 600, np.uint16), image_key=ImageKey.PROJECTION, step=step, gap_mm=gap)
    for imaging, caveat in (("experiment", True), ("paper", False)):
        scene = with_imaging(load_scene("seed-breast"), imaging)
        bound, per_domain = _bound(path, [1, 2, 3], {"scene_toml": scene.to_toml()}, 1.9, (1.0,))
        assert bound.mu_dg == pytest.approx(0.05 * 2.5)
        assert per_domain[Domain.LOG][1.0] == 1.0
        assert ("monochromatic primary beam" in bound.basis) == caveat, bound.basis
        assert ("beam hardening" in bound.basis and "scatter" in bound.basis) == caveat, bound.basis


# -- the paper's measures on a pair made by formula, registered through radiokit's warp -------------
def test_a_disc_under_a_known_affine_motion_gives_the_closed_form_contrast_if_and_change_ratio():
    """Columns between rigid plates through a compressed spheroidal inclusion (``L = mu_b g + dmu
    2 c sqrt(1 - rho^2 / a^2)``), the less compressed step moved by an affine map ``y = A x + b``
    (rotation, scale, shear, a non-integer shift). Registered by ``radiokit.register.warp`` with
    the exact pull ``d(x) = A x + b - x``, the registered image is the moving step's columns on the
    reference grid, so the pipeline's measures (``enhance_pair``, ``measure_domains``,
    ``change_ratio``) must give ``IF(k) = 1 + k (1 - C_M / C_R)`` and the change ratio of the two
    formula images, in both domains, to the interpolation's error: bilinear sampling errs by at
    most ``(|f_rr| + |f_cc|) / 8`` plus OpenCV's sample positions rounded to 1/32 px,
    ``(|f_r| + |f_c|) / 64``, per pixel, so an ROI mean by that ``eps`` and ``IF`` by
    ``2 k eps / C_R``. A pull of the wrong sign would put the disc 7 px off and miss by far more."""
    from radiokit.enhance import to_domain
    from radiokit.measure import ROI, change_ratio
    from radiokit.pipeline import enhance_pair, measure_domains
    from radiokit.register import warp

    n, px, mu_b, dmu = 400, 0.1, 0.05, 0.05
    cy, cx = 200.3, 197.6

    def columns(gap, a, c, r, col):
        rho2 = ((r - cy) * px) ** 2 + ((col - cx) * px) ** 2
        return mu_b * gap + dmu * 2 * c * np.sqrt(np.clip(1 - rho2 / a**2, 0, None))

    rr, cc = np.indices((n, n), dtype=np.float64)
    ref = columns(40.0, 4.2, 3.8, rr, cc)
    mov_on_ref = columns(42.5, 4.1, 3.9, rr, cc)  # the moving step's columns on the reference grid
    A, b = np.array([[0.97, 0.04], [-0.03, 1.02]]), np.array([3.3, -2.7])
    Ai = np.linalg.inv(A)

    def moving_at(r, c):  # the moving image, y = A x + b: its columns at x = A^-1 (y - b)
        return columns(
            42.5, 4.1, 3.9, Ai[0, 0] * (r - b[0]) + Ai[0, 1] * (c - b[1]), Ai[1, 0] * (r - b[0]) + Ai[1, 1] * (c - b[1])
        )

    moving = moving_at(rr, cc)
    pull = np.stack([A[0, 0] * rr + A[0, 1] * cc + b[0] - rr, A[1, 0] * rr + A[1, 1] * cc + b[1] - cc]).astype(
        np.float32
    )
    registered = warp(moving.astype(np.float32), pull).astype(np.float64)
    inc, bg = ROI.from_center((cy, cx), (31, 31)), ROI.from_center((cy, cx + 90), (31, 31))
    # where the inclusion ROI samples the moving image, and the derivatives there (one-pixel steps)
    sr, sc = (rr + pull[0])[inc.slices], (cc + pull[1])[inc.slices]
    measured = measure_domains(enhance_pair(ref.astype(np.float32), registered.astype(np.float32), (1.0, 2.0)), inc, bg)
    for dom, m in measured.items():
        R, M = (to_domain(x, dom.value).astype(np.float64) for x in (ref, mov_on_ref))

        def f(r, c, dom=dom):
            return to_domain(moving_at(r, c), dom.value).astype(np.float64)

        f0 = f(sr, sc)
        second = (
            np.abs(f(sr + 1, sc) - 2 * f0 + f(sr - 1, sc)).max() + np.abs(f(sr, sc + 1) - 2 * f0 + f(sr, sc - 1)).max()
        )
        first = np.abs(f(sr + 1, sc) - f(sr - 1, sc)).max() / 2 + np.abs(f(sr, sc + 1) - f(sr, sc - 1)).max() / 2
        eps = second / 8 + first / 64 + 4 * np.finfo(np.float32).eps * np.abs(f0).max()
        c_r = R[inc.slices].mean() - R[bg.slices].mean()
        c_m = M[inc.slices].mean() - M[bg.slices].mean()
        assert m.contrast_reference == pytest.approx(c_r, rel=1e-5)
        for km in m.per_k:
            assert km.improvement_factor == pytest.approx(1 + km.k * (1 - c_m / c_r), abs=2 * km.k * eps / abs(c_r))
        d = R - M
        expected_cr = d[inc.slices].mean() / d[bg.slices].mean()
        got = change_ratio(to_domain(registered, dom.value), to_domain(ref, dom.value), inc, bg)
        assert got == pytest.approx(expected_cr, abs=2 * eps / abs(d[bg.slices].mean()))
