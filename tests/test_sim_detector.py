"""The model panel (sim.detector) against its signal chain's closed-form moments.

Per pixel, ``raw = rint(offset + gain q Poisson(b^2 I0 e^-L / q) + N(0, sigma^2))`` clipped to
12 bits: mean ``offset + gain b^2 I0 e^-L`` (``PanelModel.expected``), variance
``gain^2 q b^2 I0 e^-L + sigma^2 + 1/12`` (shot noise, read noise, the ADC's rounding). Each
frame's pixels are independent, so over ``n`` frames the per-pixel sample mean is off by
``sqrt(var / n)`` and the sample variance by ``sqrt(2 / (n - 1))`` relative (Gaussian; the Poisson
excess kurtosis ``1 / lambda`` adds under 1 %): averaged over ``m`` pixels, both are known to
``1 / sqrt(m)`` of that, and the tests allow five such standard errors.
"""

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
