"""The model panel (sim.detector) against its signal chain's closed-form moments.

Per pixel, ``raw = rint(offset + gain q Poisson(b^2 I0 e^-L / q) + N(0, sigma^2))`` clipped to
12 bits: mean ``offset + gain b^2 I0 e^-L`` (``PanelModel.expected``), variance
``gain^2 q b^2 I0 e^-L + sigma^2 + 1/12`` (shot noise, read noise, the ADC's rounding). Each
frame's pixels are independent, so over ``n`` frames the per-pixel sample mean is off by
``sqrt(var / n)`` and the sample variance by ``sqrt(2 / (n - 1))`` relative (Gaussian; the Poisson
excess kurtosis ``1 / lambda`` adds under 1 %): averaged over ``m`` pixels, both are known to
``1 / sqrt(m)`` of that, and the tests allow five such standard errors.
"""

import math

import numpy as np
import pytest

from sim.detector import PanelModel

N_FRAMES, SIDE = 400, 64


def clean_panel(**kw):
    return PanelModel(rows=SIDE, cols=SIDE, n_dead=0, n_under=0, n_noisy=0, defect_columns=(), **kw)


@pytest.mark.parametrize("binning", [1, 2])
def test_mean_and_variance_of_exposed_frames(binning):
    """Binning sums charge: ``b^2`` times the signal and the shot variance, one read noise."""
    q, i0, L = 2.0, 300.0, 0.7
    panel = clean_panel(binning=binning, counts_per_quantum=q)
    line = np.full(panel.shape, L, np.float32)
    frames = panel.expose(line, i0=i0, n=N_FRAMES, rng=np.random.default_rng(1)).astype(float)
    signal = binning**2 * i0 * np.exp(-L)
    assert frames.max() < panel.saturation  # no clipping here
    var = panel.gain.astype(float) ** 2 * q * signal + panel.read_noise**2 + 1 / 12
    z = (frames.mean(axis=0) - panel.expected(line, i0)) / np.sqrt(var / N_FRAMES)
    m = z.size
    assert abs(z.mean()) < 5 / np.sqrt(m)
    assert z.std() == pytest.approx(1.0, abs=5 * np.sqrt(1 / (2 * m)))
    ratio = frames.var(axis=0, ddof=1) / var
    assert ratio.mean() == pytest.approx(1.0, abs=5 * np.sqrt(2 / (N_FRAMES - 1) / m))


def test_dark_frames_are_offset_plus_read_noise_and_bright_ones_clip_at_12_bits():
    panel = clean_panel()
    dark = panel.dark_frames(N_FRAMES, rng=np.random.default_rng(2)).astype(float)
    var = panel.read_noise**2 + 1 / 12
    m = panel.offset.size
    z = (dark.mean(axis=0) - panel.offset) / np.sqrt(var / N_FRAMES)
    assert abs(z.mean()) < 5 / np.sqrt(m)
    assert (dark.var(axis=0, ddof=1) / var).mean() == pytest.approx(1.0, abs=5 * np.sqrt(2 / (N_FRAMES - 1) / m))
    # 4x the 12-bit range above the offset: every pixel at 4095 (the C7942's ADC), none beyond
    bright = panel.flat_frames(3, i0=4.0 * panel.saturation, rng=np.random.default_rng(3))
    assert bright.dtype == np.uint16 and np.all(bright == 4095) and panel.saturation == 4095


@pytest.mark.parametrize("domain", ["negative", "log"])
def test_predicted_cnr_matches_sampled_poisson_noise(domain):
    """``sim.study.predicted_cnr`` against CNRs measured on images with Poisson noise
    (``sim.study.add_noise``). Uniform background and inclusion, registration exact (the moving
    image is already on the reference): the only background variance is the noise. In the
    paper's linear domain ``-q / N`` has variance ``e^-L / N`` exactly; in the log domain
    ``e^L / N`` to first order (the next term is ``e^L / N`` smaller: 0.1 % here). The enhanced
    image ``R + k (R - M - mean D)`` then has ``(1 + k)^2 var_R + k^2 var_M``. Each sampled CNR
    scatters by its background's ``1 / sqrt(2 m)`` and its ROI means; the mean of n samples is
    compared within five of its standard errors, taken from the samples themselves."""
    from radiokit.enhance import compression_contrast, to_domain
    from radiokit.measure import cnr
    from sim import study

    n, counts, samples = 160, 2000.0, 24
    inside = (slice(60, 100), slice(60, 100))
    reference, moving = np.full((n, n), 1.0), np.full((n, n), 0.9)
    reference[inside], moving[inside] = 1.3, 1.25
    mask = np.zeros((n, n), bool)
    mask[inside] = True
    zero = np.zeros((2, n, n), np.float32)
    pair = study.ImagePair(reference, moving, moving.copy(), zero, zero, mask, 0.25, None, "side")
    h = study.headline(pair)
    predicted = study.predicted_cnr(pair, h, counts, domain)
    assert set(predicted) == {"reference", "1", "2"}
    rng = np.random.default_rng(11)
    pixels = domain
    measured = {key: [] for key in predicted}
    for _ in range(samples):
        r = to_domain(study.add_noise(reference, counts, rng), pixels)
        m = to_domain(study.add_noise(moving, counts, rng), pixels)
        measured["reference"].append(cnr(r, h.inclusion, h.background))
        for k in ("1", "2"):
            enhanced = compression_contrast(r, m, float(k), domain=pixels)
            measured[k].append(cnr(enhanced, h.inclusion, h.background))
    for key, values in measured.items():
        standard_error = np.std(values, ddof=1) / np.sqrt(samples)
        assert np.mean(values) == pytest.approx(predicted[key], abs=5 * standard_error), key


def test_the_exposure_ceiling_keeps_the_flats_below_the_adc_top():
    """``Exposure`` accepts an open beam only up to ``PanelModel.open_beam_ceiling()``: there the
    brightest pixels' mean plus three standard deviations (gain peak, dark offset, shot and read
    noise) stays under 4095, so a full-size panel's flats clip in about 0.1 % of pixels or fewer
    (3 sigma's one-sided 0.13 % bounds the tail at the very brightest pixels; most sit further
    down). The mean-only rule it replaced accepted 3974 counts, where half the flats clip."""
    from sim.scene import Exposure

    ceiling = PanelModel.open_beam_ceiling()
    panel = PanelModel(rows=1120, cols=1120, n_dead=0, n_under=0, n_noisy=0, defect_columns=())
    flats = panel.flat_frames(2, i0=ceiling, rng=np.random.default_rng(4))
    assert np.mean(flats == panel.saturation) < 0.0013
    # and the ceiling is not needlessly low: 10 % above it, the panel's bright part clips
    over = panel.flat_frames(2, i0=1.1 * ceiling, rng=np.random.default_rng(5))
    assert np.mean(over == panel.saturation) > 0.1
    Exposure(i0_counts=math.floor(ceiling))
    with pytest.raises(ValueError, match="would saturate"):
        Exposure(i0_counts=3974.0)
