"""The model panel (sim.detector) against its signal chain's closed-form moments.

Per pixel, ``raw = rint(offset + gain q Poisson(b^2 I0 e^-L / q) + N(0, sigma^2))`` clipped to
12 bits: mean ``offset + gain b^2 I0 e^-L`` (``PanelModel.expected``), variance
``gain^2 q b^2 I0 e^-L + sigma^2 + 1/12`` (shot noise, read noise, the ADC's rounding). Each
frame's pixels are independent, so over ``n`` frames the per-pixel sample mean is off by
``sqrt(var / n)`` and the sample variance by ``sqrt(2 / (n - 1))`` relative (Gaussian; the Poisson
excess kurtosis ``1 / lambda`` adds under 1 %): averaged over ``m`` pixels, both are known to
``1 / sqrt(m)`` of that, and the tests allow five such standard errors.
"""

import functools
import math

import numpy as np
import pytest
from conftest import square_pair

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
    reference, moving, mask = square_pair(n)
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


# -- the scene's dose under binning ----------------------------------------------------------------
# ``exposure.i0_counts`` is what the source gives one unbinned 50 µm pixel (tube current, exposure
# time, distance); binning sums the charge of b^2 such pixels into one read-out. At a fixed source
# a read-out pixel's open beam is therefore ``gain b^2 I0`` above its offset, with variance
# ``gain^2 q b^2 I0 + sigma^2 + 1/12``, and its SNR grows by about b where shot noise dominates.
I0_UNBINNED = 200.0  # counts per unbinned pixel: 3200 per 4x4 read-out, under the ADC's ceiling


def _scene_at(binning, i0_counts=I0_UNBINNED):
    """One source (60 kV, 250 µA giving ``i0_counts`` per unbinned pixel) read out at ``binning``."""
    from sim.scene import Detector, Exposure, block_scene

    scene = block_scene(size_mm=10, ratios=(0.1,))
    scene.detector = Detector("c7942", binning)
    scene.exposure = Exposure(i0_counts, 60.0, 250.0)
    return scene.validate()


@functools.cache
def _open_beam(binning):
    """Two open-beam frames of the scene's panel at ``binning`` (as ``sim.lab.simulate_experiment``
    exposes them): the pooled signal above the offset and the pooled variance (from the frames'
    difference, which cancels the fixed pattern) over the defect-free pixels, with the model's."""
    from sim.lab import make_panel, open_beam_counts

    scene = _scene_at(binning)
    panel = make_panel(scene)
    f1, f2 = panel.flat_frames(2, open_beam_counts(scene), rng=np.random.default_rng(10 + binning))
    good = ~panel.truth.mask(panel.shape) & (panel.noise == panel.read_noise)
    g, offset, noise = (a[good].astype(float) for a in (panel.gain, panel.offset, panel.noise))
    mean = (f1[good].astype(float) + f2[good]) / 2 - offset
    diff = f1[good].astype(float) - f2[good]
    model_var = g**2 * panel.counts_per_quantum * binning**2 * I0_UNBINNED + noise**2 + 1 / 12
    return {
        "m": int(good.sum()),
        "signal": float(mean.mean()),
        "var": float(np.mean(diff**2) / 2),
        "model_signal": float(g.mean() * binning**2 * I0_UNBINNED),
        "model_var": float(model_var.mean()),
        "gain": float(g.mean()),
    }


@pytest.mark.parametrize("binning", [1, 2, 4])
def test_at_a_fixed_source_the_open_beam_per_read_out_pixel_scales_as_binning_squared(binning):
    """The same kV and µA read out at 2x2 or 4x4: 4 or 16 times the counts per read-out pixel (the
    charge of that many unbinned pixels), and the variance-to-mean ratio the signal chain's
    ``gain q + sigma^2 / signal`` (shot noise grows with the summed charge, read noise once). The
    pooled mean over m pixels is known to ``sqrt(var / 2m)``, the pooled variance (half the mean
    squared difference of two frames) to ``sqrt(2 / m)`` relative; five standard errors."""
    s = _open_beam(binning)
    m = s["m"]
    assert s["signal"] / (s["gain"] * I0_UNBINNED) == pytest.approx(
        binning**2, abs=5 * math.sqrt(s["model_var"] / (2 * m)) / (s["gain"] * I0_UNBINNED)
    )
    assert s["signal"] == pytest.approx(s["model_signal"], abs=5 * math.sqrt(s["model_var"] / (2 * m)))
    assert s["var"] / s["model_var"] == pytest.approx(1.0, abs=5 * math.sqrt(2 / m))
    fano, model_fano = s["var"] / s["signal"], s["model_var"] / s["model_signal"]
    assert fano == pytest.approx(model_fano, rel=5 * math.sqrt(2 / m) + 5 * math.sqrt(1 / (2 * m)))


def test_binning_the_same_source_improves_the_open_beams_snr_by_about_the_binning():
    """SNR per read-out pixel ``gain b^2 I0 / sqrt(gain^2 q b^2 I0 + sigma^2)``: quantum-limited
    (shot variance b^2 I0 >= 200 counts against ~4 of read noise and rounding), so binning by b
    raises it by b to within 1 % (the read noise, counted once per read-out, adds the rest: b
    sqrt((I0 + s2) / (I0 + s2 / b^2)), 2.015 and 4.04 here). Measured within 2 % of b and within
    five standard errors (``sqrt(1 / 2m)`` relative, from the pooled variance) of the closed form."""
    snr = {}
    for b in (1, 2, 4):
        s = _open_beam(b)
        snr[b] = s["signal"] / math.sqrt(s["var"])
        model = s["model_signal"] / math.sqrt(s["model_var"])
        assert snr[b] == pytest.approx(model, rel=5 * math.sqrt(1 / (2 * s["m"])))
    for b in (2, 4):
        assert snr[b] / snr[1] == pytest.approx(b, rel=0.02)


def test_a_binned_open_beam_beyond_the_adc_is_refused_in_the_scene_naming_the_binning():
    """A scene is a planned exposure: as at 1x1 (``Exposure``'s own check), one whose summed open
    beam would clip is refused on loading, in one line naming i0_counts, the binning and the most
    it may be -- not written as a file of saturated flats that the calibration then refuses."""
    most = math.floor(PanelModel.open_beam_ceiling() / 4)
    _scene_at(1, most + 10)  # fits 1x1 ...
    _scene_at(2, most)  # ... and 2x2 up to a quarter of the ceiling
    with pytest.raises(ValueError) as err:
        _scene_at(2, most + 10)  # ... but not 2x2 above it
    msg = str(err.value)
    assert "\n" not in msg and "would saturate" in msg
    assert f"i0_counts {most + 10:g}" in msg and "binning 2" in msg and f"at most {most:d}" in msg


def test_binning_the_same_source_past_the_adc_clips_at_4095_and_the_calibration_says_so():
    """The virtual bench is the panel: a protocol that bins 2x2 a source set for 1x1 gets what the
    C7942 gives, clipped 12-bit frames (every responding pixel at 4095, none beyond), and the
    calibration's saturation checks speak: a warning naming the saturated pixels when a few of the
    brightest clip, a refusal when most do."""
    from radiokit.calibrate import Calibration, CalibrationWarning
    from sim.bench import VirtualBench

    ceiling = PanelModel.open_beam_ceiling()
    bench = VirtualBench(_scene_at(1, 1500.0), binning=2, seed=1)  # 4 x 1500 counts per read-out pixel
    bench.sample_in = False
    good = ~bench.panel.truth.mask(bench.panel.shape)
    darks, flats = bench.expose(3, xray_on=False), bench.expose(3)
    assert flats.max() == 4095 and np.all(flats[:, good] == 4095)
    with pytest.raises(ValueError, match="flats are saturated"):
        Calibration.from_frames(darks, flats)
    # just past the binned ceiling: the brightest pixels clip, the calibration flags them and warns
    bench = VirtualBench(_scene_at(1, 1.06 * ceiling / 4), binning=2, seed=1)
    bench.sample_in = False
    flats = bench.expose(3)
    assert 0 < np.mean(flats == 4095) < 0.1
    with pytest.warns(CalibrationWarning, match="pixels of the flats are saturated"):
        Calibration.from_frames(darks, flats)
