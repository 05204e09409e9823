"""Closed-form audit of the Poisson noise of ``sim.study``, the flat/dark correction
(``radiokit.correct``) and the paper's measures (``radiokit.measure``, ``radiokit.enhance``).

The closed forms, written down before the project's own tests were read (session 33's audit):

- Poisson counts ``n ~ P(N T)``: ``-ln(n / N)`` has variance ``1 / (N T)`` to first order;
- flat/dark on a linear detector ``raw = d + g I0 T``: ``(raw - d) / (flat - d) = T`` exactly, the
  log domain ``-ln T``, the manual's grey levels ``mean(flat - dark) T``;
- contrast ``C = mean_incl - mean_bg``; ``IF = C(enhanced) / C(reference)``; change ratio
  ``(incl_after - incl_before) / (bg_after - bg_before)``; with ``E = R + k (D - mean D)``,
  ``D = R - M``: ``IF(k) = 1 + k (1 - C_M / C_R)``;
- columns between rigid plates (gap ``g``, inclusion chord ``c``, ``dmu = mu_i - mu_b``):
  ``L = mu_b g + dmu c``; in ``-I/I0`` the contrast is ``e^(-mu_b g) (1 - e^(-dmu c))``, so a rigid
  inclusion (``c`` unchanged) over a plate step ``dg`` gives ``IF(k) = 1 + k (1 - e^(-mu_b dg))``,
  and in the log domain ``C = dmu c``, so ``IF = 1 + k (1 - c_mov / c_ref)``.

The panel's law (mean ``o + g b^2 I0 e^-L``, variance ``g^2 q b^2 I0 e^-L + r^2 + 1/12``, the clip
at 4095, binning's charge sum) is already checked pixel by pixel in tests/test_sim_detector.py,
and the tube-current factor in tests/test_calibrate.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from radiokit.calibrate import Calibration
from radiokit.correct import correct_frames
from radiokit.enhance import compression_contrast, to_domain
from radiokit.measure import ROI, change_ratio, contrast, improvement_bound, improvement_factor
from sim.study import add_noise


def test_log_of_poisson_counts_has_variance_one_over_the_counts():
    # the noise predicted_cnr assumes: var(-ln(n / N)) = 1 / (N T) to first order (the next term
    # is 3 / (2 (N T)^2), 0.15 % here); the sample variance's standard error is sqrt(2 / n)
    N, L = 2000.0, 0.7
    x = add_noise(np.full(200_000, L), N, np.random.default_rng(7))
    lam = N * math.exp(-L)
    assert x.var() == pytest.approx(1 / lam, rel=5 * math.sqrt(2 / x.size) + 3 / (2 * lam))
    assert x.mean() == pytest.approx(L + 1 / (2 * lam), abs=5 * math.sqrt(1 / lam / x.size))


def _linear_detector(shape=(64, 64), i0=3000.0, seed=8):
    rng = np.random.default_rng(seed)
    dark = 100.0 + 5.0 * rng.standard_normal(shape)
    gain = 1.0 + 0.03 * rng.standard_normal(shape)
    T = rng.uniform(0.05, 1.0, shape)
    stack = lambda a: np.repeat(a[None].astype(np.float32), 4, axis=0)
    cal = Calibration.from_frames(stack(dark), stack(dark + gain * i0))
    raw = (dark + gain * i0 * T).astype(np.float32)
    return cal, raw, T, gain * i0


def test_flat_and_dark_correction_is_exact_on_a_linear_detector():
    cal, raw, T, response = _linear_detector()
    assert not cal.mask.any()
    # float32 arithmetic: a few ulps of the raw value over the smallest signal
    atol = 8 * np.finfo(np.float32).eps * float(raw.max()) / float((response * T).min())
    np.testing.assert_allclose(correct_frames(cal, raw, domain="log"), -np.log(T), rtol=0, atol=atol)
    np.testing.assert_allclose(correct_frames(cal, raw, domain="linear"), T, rtol=atol, atol=0)
    # the manual's gain correction keeps the grey scale: c (raw - d) / (flat - d), c = mean(flat - d)
    counts = correct_frames(cal, raw, domain="counts")
    np.testing.assert_allclose(counts, np.mean(response) * T, rtol=atol + 1e-6)


def test_the_paper_measures_by_hand_on_tiny_arrays():
    incl, bg = ROI(0, 2, 0, 2), ROI(0, 2, 2, 4)
    before = np.array([[5.0, 7.0, 1.0, 3.0], [5.0, 7.0, 1.0, 3.0]])  # incl mean 6, bg mean 2
    after = np.array([[4.0, 5.0, -2.0, -1.0], [4.0, 5.0, -2.0, -1.0]])  # incl 4.5, bg -1.5
    assert contrast(before, incl, bg) == 4.0
    assert change_ratio(before, after, incl, bg) == pytest.approx(-1.5 / -3.5)
    # E = R + k (D - mean D): D = after - before = [[-1, -2, -3, -4]] * 2 rows, mean -2.5
    for k in (1.0, 2.0):
        e = compression_contrast(after, before, k)
        np.testing.assert_allclose(e[0], after[0] + k * (np.array([-1.0, -2.0, -3.0, -4.0]) + 2.5))
        # C_E = 6 + k (-1.5 + 3.5) = 6 + 2 k; IF = 1 + k (1 - C_M / C_R) = 1 + k (1 - 4 / 6)
        assert improvement_factor(e, after, incl, bg) == pytest.approx(1 + k / 3)


def _columns(mu_b, dmu, gap, chord, n=40):
    """Line integrals of columns between rigid plates: the left half through the inclusion."""
    L = np.full((n, n), mu_b * gap)
    L[:, : n // 2] += dmu * chord
    return L


@pytest.mark.parametrize("shrink", [0.0, 0.03, 0.0625])
def test_improvement_between_rigid_plates_is_the_beer_lambert_closed_form(shrink):
    # the gap closes by dg = 2.5 of 40 mm; the inclusion's chord by the fraction `shrink` (0 rigid,
    # 0.0625 as soft as the gel): IF(k) = 1 + k (1 - C_M / C_R) with each contrast in closed form
    mu_b, dmu, gap, dg, c = 0.05, 0.05, 37.5, 2.5, 8.0
    ref = _columns(mu_b, dmu, gap, c * (1 - shrink))
    mov = _columns(mu_b, dmu, gap + dg, c)
    incl, bg = ROI(0, 40, 0, 20), ROI(0, 40, 20, 40)
    c_neg = lambda g, ch: math.exp(-mu_b * g) * (1 - math.exp(-dmu * ch))
    for k in (1.0, 2.0):
        neg = [to_domain(x, "negative") for x in (ref, mov)]
        enh = compression_contrast(neg[0], neg[1], k, domain="negative")
        expected = 1 + k * (1 - c_neg(gap + dg, c) / c_neg(gap, c * (1 - shrink)))
        assert improvement_factor(enh, neg[0], incl, bg) == pytest.approx(expected, rel=1e-5)
        assert expected <= improvement_bound(k, mu_b, dg, "negative") + 1e-12
        if shrink == 0:  # the bound is reached by a rigid inclusion
            assert expected == pytest.approx(improvement_bound(k, mu_b, dg, "negative"), rel=1e-12)
        enh_log = compression_contrast(ref, mov, k, domain="log")
        assert improvement_factor(enh_log, ref, incl, bg) == pytest.approx(1 - k * shrink / (1 - shrink), rel=1e-5)
