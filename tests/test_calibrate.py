"""Calibration: robust averaging, defect maps on a synthetic panel, persistence, and the
calibrate-then-correct chain recovering a known line integral within the noise."""

import re
import warnings

import numpy as np
import pytest
import tifffile

from radiokit.calibrate import (
    MAX_DEFECTIVE_SHARE,
    Calibration,
    CalibrationWarning,
    PixelFlag,
    adc_top,
    robust_average,
)
from radiokit.correct import correct_frames
from radiokit.io import ExperimentWriter, ImageKey
from sim.detector import PanelModel

SHAPE = (256, 320)


def _panel(**kw):
    args = dict(rows=SHAPE[0], cols=SHAPE[1], defect_columns=(97,), n_dead=5, n_under=5, n_noisy=5)
    args.update(kw)
    return PanelModel(**args)


def _calibrate(panel, n=10, i0=2500.0, seed=1, **th):
    rng = np.random.default_rng(seed)
    return Calibration.from_frames(panel.dark_frames(n, rng), panel.flat_frames(n, i0, rng), **th)


def test_zinger_leaves_no_trace():
    rng = np.random.default_rng(0)
    frames = rng.normal(1000, 10, (7, 32, 32)).astype(np.float32)
    clean = frames.mean(axis=0)
    frames[3, 5, 6] = 4095  # a zinger
    avg = robust_average(frames)
    # the zinger's pixel is the mean of the six other frames: within noise of the clean mean
    others = np.delete(frames[:, 5, 6], 3).mean()
    assert avg[5, 6] == pytest.approx(others, abs=1e-3)
    assert abs(avg[5, 6] - clean[5, 6]) < 4 * 10 / np.sqrt(6)
    mask = np.ones((32, 32), bool)
    mask[5, 6] = False
    np.testing.assert_allclose(avg[mask], clean[mask], rtol=1e-5)


def test_a_zinger_is_dropped_from_frames_whose_squares_pass_float32s_range():
    """Flats read as 3e29 (a float TIFF scaled by a wrong factor): the panel's noise, a float32
    variance, overflowed to inf ("overflow encountered in square" and "invalid value" warnings
    from `radiokit calibrate`), and with an infinite window no zinger was an outlier. The same
    frames at any scale are averaged alike."""
    rng = np.random.default_rng(0)
    frames = rng.normal(1000, 10, (7, 32, 32))
    frames[3, 5, 6] = 4095  # a zinger
    scale = 1e26
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        big = robust_average((frames * scale).astype(np.float32))
    small = robust_average(frames.astype(np.float32))
    np.testing.assert_allclose(big / scale, small, rtol=1e-5)
    assert abs(big[5, 6] / scale - np.delete(frames[:, 5, 6], 3).mean()) < 4 * 10 / np.sqrt(6)


def test_zinger_with_two_frames_takes_the_smaller():
    rng = np.random.default_rng(5)
    frames = rng.normal(1000, 3, (2, 16, 16)).astype(np.float32)
    frames[1, 4, 4] = 3900
    avg = robust_average(frames)
    assert avg[4, 4] == pytest.approx(frames[0, 4, 4])
    np.testing.assert_allclose(avg[5:], frames[:, 5:].mean(axis=0), rtol=1e-6)


def test_robust_average_std_ignores_the_zinger_but_not_a_noisy_pixel():
    rng = np.random.default_rng(1)
    frames = rng.normal(100, 3, (12, 64, 64)).astype(np.float32)
    frames[4, 10, 10] = 4000
    frames[:, 20, 20] = rng.normal(100, 30, 12)
    _, std = robust_average(frames, return_std=True)
    typical = np.median(std)
    assert std[10, 10] < 2 * typical  # a zinger kept would make it ~300 times larger
    assert std[20, 20] > 5 * typical


@pytest.mark.parametrize("scale", [1e16, 1e19])
def test_robust_average_std_and_noisy_pixels_are_scale_invariant(scale):
    """Float frames in absurd units (counts x 1e19: within float32's range, 3.4e38) squared their
    deviations in float32, past 1.8e19 an overflow: every pixel's temporal std came out inf, the
    median with it, so the noisy pixel went unflagged, and `radiokit process` printed
    "RuntimeWarning: overflow encountered in square" (s50). The std is a length in counts: scaling
    the frames scales it, and leaves the defect map as it was."""
    rng = np.random.default_rng(1)
    darks = rng.normal(100, 3, (12, 64, 64))
    darks[:, 20, 20] = rng.normal(100, 30, 12)  # a noisy pixel
    flats = rng.normal(3000, 20, (6, 64, 64))
    _, std = robust_average(darks.astype(np.float32), return_std=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        _, std_k = robust_average((darks * scale).astype(np.float32), return_std=True)
        cal_k = Calibration.from_frames((darks * scale).astype(np.float32), (flats * scale).astype(np.float32))
    np.testing.assert_allclose(std_k / scale, std, rtol=1e-4)
    cal = Calibration.from_frames(darks.astype(np.float32), flats.astype(np.float32))
    assert cal.mask[20, 20] & PixelFlag.NOISY and np.count_nonzero(cal.mask) == 1, np.argwhere(cal.mask)
    np.testing.assert_array_equal(cal_k.mask, cal.mask)


def test_clean_panel_with_smooth_gain_has_no_defects():
    panel = _panel(n_dead=0, n_under=0, n_noisy=0, defect_columns=(), gain_variation=0.3)
    cal = _calibrate(panel)
    assert np.count_nonzero(cal.mask) == 0, cal
    assert cal.defect_rows.size == 0 and cal.defect_columns.size == 0


def test_planted_defects_found_without_false_positives():
    panel = _panel()
    panel.gain[180, :] *= 0.8  # and a defect row at 80 % response
    cal = _calibrate(panel)
    truth = panel.truth.mask(SHAPE)
    truth[180, :] = True
    found = cal.mask != 0
    assert not (found & ~truth).any(), f"false positives at {np.argwhere(found & ~truth)[:10]}"
    assert not (truth & ~found).any(), f"missed {np.argwhere(truth & ~found)[:10]}"
    t = panel.truth
    assert (cal.mask[t.dead[:, 0], t.dead[:, 1]] & PixelFlag.DEAD).all()
    assert (cal.mask[t.under[:, 0], t.under[:, 1]] & PixelFlag.UNDER_RESPONDING).all()
    assert (cal.mask[t.noisy[:, 0], t.noisy[:, 1]] & PixelFlag.NOISY).all()
    assert cal.defect_columns.tolist() == [97]
    assert cal.defect_rows.tolist() == [180]
    assert (cal.mask[:, 97] & PixelFlag.CLUSTER).all()


def test_zinger_in_flats_is_not_a_defect():
    panel = _panel(n_dead=0, n_under=0, n_noisy=0, defect_columns=())
    rng = np.random.default_rng(2)
    darks, flats = panel.dark_frames(8, rng), panel.flat_frames(8, 2500, rng)
    flats[2, 40, 40] = 4095
    darks[5, 41, 41] = 4000
    cal = Calibration.from_frames(darks, flats)
    assert np.count_nonzero(cal.mask) == 0


def test_correction_recovers_line_integral_within_noise():
    panel = _panel()
    i0 = 2500.0
    cal = _calibrate(panel, n=16, i0=i0)
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]]
    r2 = ((yy - 128) ** 2 + (xx - 160) ** 2) / 90.0**2
    truth = np.where(r2 < 1, 1.2 * np.sqrt(np.clip(1 - r2, 0, None)), 0.0).astype(np.float32) + 0.1
    frames = panel.expose(truth, i0, n=4, rng=np.random.default_rng(9))
    got = correct_frames(cal, frames, domain="log").mean(axis=0)
    err = got - truth
    valid = ~panel.truth.mask(SHAPE)
    # Expected noise of the 4-frame mean of -ln(I/I0): shot noise q/(g I0 e^-L) plus read noise,
    # plus the calibration's own (16 flats): error propagation of the log.
    g = panel.gain
    signal = g * i0 * np.exp(-truth)
    with np.errstate(divide="ignore", invalid="ignore"):  # dead pixels have no signal
        var_frame = (panel.counts_per_quantum * g * signal + panel.read_noise**2) / signal**2
        var_flat = (panel.counts_per_quantum * g * g * i0 + panel.read_noise**2) / (g * i0) ** 2
        sigma = np.sqrt(var_frame / 4 + var_flat / 16)
    z = err[valid] / sigma[valid]
    assert abs(np.mean(err[valid])) < 0.05 * np.mean(sigma[valid])  # no bias beyond a tenth of noise
    assert np.std(z) == pytest.approx(1.0, abs=0.1)  # the noise is what physics says, no more
    # Filled defects are plausible too: within 5 noise sigmas of the truth
    near = np.where(valid, sigma, np.nan)
    local_sigma = np.nanmax([np.roll(near, s, axis=a) for s in (-1, 1) for a in (0, 1)], axis=0)
    assert np.all(np.abs(err[~valid]) < 5 * local_sigma[~valid] + 0.02)


def test_save_load_round_trip(tmp_path):
    panel = _panel()
    cal = _calibrate(panel, n=4, dead_below=0.15)
    path = cal.save(tmp_path / "cal.h5")
    back = Calibration.load(path)
    for name in ("dark", "flat", "mask", "defect_rows", "defect_columns"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cal, name))
    assert back.c == cal.c
    assert back.thresholds.dead_below == 0.15
    assert back.provenance["n_darks"] == 4 and back.provenance["n_flats"] == 4
    raw = panel.flat_frames(1, 1200, np.random.default_rng(5))[0]
    np.testing.assert_array_equal(correct_frames(back, raw), correct_frames(cal, raw))


def test_load_rejects_other_files(tmp_path):
    import h5py

    from radiokit import FormatError

    with h5py.File(tmp_path / "x.h5", "w") as h5:
        h5["foo"] = 1
    with pytest.raises(FormatError, match="x.h5.*calibration"):
        Calibration.load(tmp_path / "x.h5")
    (tmp_path / "y.h5").write_bytes(b"not hdf5")
    with pytest.raises(FormatError, match="y.h5"):
        Calibration.load(tmp_path / "y.h5")


def test_from_experiment_matches_from_frames(tmp_path):
    panel = _panel(rows=64, cols=80, defect_columns=(20,), n_dead=1, n_under=1, n_noisy=1)
    rng = np.random.default_rng(4)
    darks, flats = panel.dark_frames(5, rng), panel.flat_frames(5, 2000, rng)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=panel.shape, pixel_size_mm=0.05) as w:
        for f in darks:
            w.append(f, image_key=ImageKey.DARK)
        for f in flats:
            w.append(f, image_key=ImageKey.FLAT, voltage_kv=60, current_ua=250)
        w.append(flats[0], image_key=ImageKey.PROJECTION, step=1, ratio=0.15)
    a = Calibration.from_experiment(path)
    b = Calibration.from_frames(darks, flats)
    np.testing.assert_array_equal(a.dark, b.dark)
    np.testing.assert_array_equal(a.mask, b.mask)
    assert a.provenance["source"] == str(path)
    assert len(a.provenance["dark_times"]) == 5


def _experiment_with_mask(path, panel, darks, flats, mask):
    with ExperimentWriter(path, shape=panel.shape, pixel_size_mm=0.05) as w:
        for f in darks:
            w.append(f, image_key=ImageKey.DARK)
        for f in flats:
            w.append(f, image_key=ImageKey.FLAT)
        w.set_pixel_mask(mask)


def test_from_experiment_honours_the_files_own_pixel_mask(tmp_path):
    """A NeXus pixel_mask recorded in the experiment file (a tiled panel's gap, a pixel its writer
    knew bad) joins the defect map, and correction fills those pixels from their neighbours: it
    was read and dropped, so a gap column reading three times the flat came out as data (session
    30's hostile-input review). Bit 31 (NeXus: a virtual pixel) counts as the user-defined bit."""
    from radiokit.calibrate import PixelFlag
    from radiokit.correct import correct_frames

    panel = _panel(rows=48, cols=64)
    rng = np.random.default_rng(7)
    darks, flats = panel.dark_frames(5, rng), panel.flat_frames(5, 2000, rng)
    recorded = np.zeros(panel.shape, np.uint32)
    recorded[:, 30] = PixelFlag.GAP
    recorded[10, 10] = np.uint32(1 << 31)
    path = tmp_path / "exp.h5"
    _experiment_with_mask(path, panel, darks, flats, recorded)
    cal = Calibration.from_experiment(path)
    plain = Calibration.from_frames(darks, flats)
    assert np.all(cal.mask[:, 30] & PixelFlag.GAP) and cal.mask[10, 10] & PixelFlag.USER
    np.testing.assert_array_equal(cal.mask[recorded == 0], plain.mask[recorded == 0])
    assert cal.provenance["defects"]["recorded in the file"] == 49
    # a projection through nothing, the gap column and the virtual pixel reading 3x the flat's signal
    raw = flats[0].astype(np.float32)
    raw[:, 30] = cal.dark[:, 30] + 3 * (cal.flat[:, 30] - cal.dark[:, 30])
    raw[10, 10] = cal.dark[10, 10] + 3 * (cal.flat[10, 10] - cal.dark[10, 10])
    out = correct_frames(cal, raw, domain="log")
    # filled from neighbours that read the open beam: line integral ~0, not -ln 3 = -1.10
    assert np.abs(out[:, 30]).max() < 0.1 and abs(out[10, 10]) < 0.1
    assert np.abs(correct_frames(plain, raw, domain="log")[:, 30] + np.log(3)).max() < 0.1  # as it was


def test_from_experiment_refuses_a_pixel_mask_that_cannot_be_one(tmp_path):
    """A recorded pixel_mask marking most of the panel bad (a mask of good pixels, NeXus's sense
    inverted) is one line naming the file and the mask; one of another shape (a native mask beside
    binned frames) is left out with a warning naming it, as it was ignored before."""
    import h5py

    from radiokit import FormatError
    from radiokit.calibrate import CalibrationWarning

    panel = _panel(rows=32, cols=40)
    rng = np.random.default_rng(8)
    darks, flats = panel.dark_frames(4, rng), panel.flat_frames(4, 2000, rng)
    path = tmp_path / "inverted.h5"
    _experiment_with_mask(path, panel, darks, flats, np.ones(panel.shape, np.uint32))
    with pytest.raises(FormatError, match=r"inverted.h5.*pixel_mask.*1280 of 1280 pixels"):
        Calibration.from_experiment(path)
    path = tmp_path / "shape.h5"
    _experiment_with_mask(path, panel, darks, flats, np.zeros(panel.shape, np.uint32))
    with h5py.File(path, "a") as h5:
        del h5["entry/instrument/detector/pixel_mask"]
        h5["entry/instrument/detector/pixel_mask"] = np.zeros((40, 32), np.uint32)
    with pytest.warns(CalibrationWarning, match=r"shape.h5.*pixel_mask \(40, 32\).*does not match.*not used"):
        cal = Calibration.from_experiment(path)
    np.testing.assert_array_equal(cal.mask, Calibration.from_frames(darks, flats).mask)


def test_from_experiment_without_darks(tmp_path):
    from radiokit import FormatError

    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(8, 8), pixel_size_mm=0.05) as w:
        w.append(np.ones((8, 8), np.uint16), image_key=ImageKey.FLAT)
    with pytest.raises(FormatError, match="no darks"):
        Calibration.from_experiment(path)


@pytest.mark.parametrize(
    "darks, flats, match",
    [
        (np.zeros((3, 8, 8)), np.zeros((3, 8, 9)), "darks are"),
        (np.zeros((3, 8, 8)), np.zeros((3, 8, 8)), "not brighter"),
        (np.full((3, 8, 8), np.nan), np.ones((3, 8, 8)), "NaN"),
        (np.zeros((0, 8, 8)), np.ones((3, 8, 8)), "n >= 1"),
    ],
)
def test_bad_calibration_input(darks, flats, match):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        with pytest.raises(ValueError, match=match):
            Calibration.from_frames(darks, flats)


def test_few_frames_warn():
    with pytest.warns(CalibrationWarning, match="fewer than 3"):
        Calibration.from_frames(np.zeros((2, 8, 8)), np.full((2, 8, 8), 1000.0))


def test_unknown_threshold_is_a_typeerror():
    with pytest.raises(TypeError, match="dead_belowx"):
        Calibration.from_frames(np.zeros((3, 8, 8)), np.full((3, 8, 8), 1000.0), dead_belowx=0.1)


def _sixteen_bit_experiment(path, bit_depth, rng):
    """Another lab's panel: 16-bit, flats at 40 000 counts over a 1 000-count pedestal, 384 x 250
    (non-square, odd-free but not the C7942's), a slab of line integral 0.8 with a saturated
    corner in the projection. Returns the exact transmission."""
    shape = (250, 384)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    L = 0.8 * ((rr > 40) & (rr < 210)) + 0.002 * cc  # a slab and a slow ramp
    kw = {} if bit_depth is None else {"bit_depth": bit_depth}
    with ExperimentWriter(path, shape=shape, **kw) as w:
        for _ in range(4):
            w.append(np.rint(1000 + rng.normal(0, 3, shape)).astype(np.uint16), image_key=ImageKey.DARK)
        for _ in range(4):
            w.append((1000 + rng.poisson(40000, shape)).astype(np.uint16), image_key=ImageKey.FLAT)
        proj = np.minimum(1000 + rng.poisson(40000 * np.exp(-L)), 65535).astype(np.uint16)
        proj[:10, :10] = 65535  # saturated
        w.append(proj, image_key=ImageKey.PROJECTION, step=1)
    return np.exp(-L)


@pytest.mark.filterwarnings("ignore::radiokit.io.BitDepthWarning")  # None: read as 12 bits, warned once
@pytest.mark.parametrize("bit_depth", [16, None])
def test_a_16_bit_panel_calibrates_and_corrects_to_the_exact_transmission(tmp_path, bit_depth):
    """A 16-bit panel's flats (40 000 counts) were all "saturated" against the C7942's fixed
    4095 and the calibration refused the lab's data. Its saturation is now the bit depth the file
    records (NeXus bit_depth_readout), or without it the smallest ADC range the frames fit."""
    from radiokit.io import open_frames

    path = tmp_path / "exp16.h5"
    exact = _sixteen_bit_experiment(path, bit_depth, np.random.default_rng(7))
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        cal = Calibration.from_experiment(path)
    assert cal.thresholds.saturation == 65535
    assert cal.c == pytest.approx(40000, rel=1e-3)
    with open_frames(path) as src:
        raw = src[len(src) - 1]
    t, report = correct_frames(cal, raw, domain="linear", return_report=True)
    assert report.saturated.tolist() == [100]  # the corner, and nothing else
    # Poisson noise of one frame: sqrt(40000 T) / 40000 <= 0.005 per pixel; means over 10^4 pixels
    err = (t - exact)[20:, 20:]
    assert abs(float(np.mean(err))) < 5e-4 and float(np.std(err)) < 0.0055


def test_a_frame_above_the_inferred_adc_top_is_not_reported_saturated():
    """Found in review: a 16-bit panel whose darks and flats stay under 4095 (flats at a lower
    tube current than the projections) was inferred 12-bit, and every pixel of a projection at
    5000 counts was reported saturated. A frame above the level cannot come from that ADC: its
    own range decides; a real 12-bit frame still counts its 4095s."""
    rng = np.random.default_rng(3)
    darks = np.rint(100 + rng.normal(0, 2, (4, 32, 32))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (4, 32, 32))).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 4095  # what the darks and flats imply
    bright = (100 + rng.poisson(5000, (32, 32))).astype(np.uint16)  # twice the flats' current
    bright[:2, :3] = 65535
    # brighter than the flats, refused unless the caller rescales for the current (check=False)
    _, report = correct_frames(cal, bright, domain="linear", return_report=True, check=False)
    assert report.saturated.tolist() == [6]  # the 16-bit top only
    twelve = (100 + rng.poisson(3000, (32, 32))).astype(np.uint16)
    twelve[:3, :3] = 4095
    _, report = correct_frames(cal, twelve, domain="linear", return_report=True)
    assert report.saturated.tolist() == [9]


def test_a_hot_pixel_above_the_adc_top_does_not_lift_the_saturation_level():
    """Found by trying other labs' files: one stuck pixel at 65535 (or a vendor's defect marker) in
    one flat of a 12-bit panel made the frames' ADC "16-bit", so flats clipped at 4095 everywhere
    were taken as a good calibration, silently (without it they are refused). A few values above
    a top are defects of that ADC; the top moves only when more of the frames pass it."""
    rng = np.random.default_rng(5)
    darks = np.rint(150 + rng.normal(0, 2, (6, 64, 64))).astype(np.uint16)
    clipped = np.clip(np.rint(150 + 4100 + rng.normal(0, 30, (6, 64, 64))), 0, 4095).astype(np.uint16)
    clipped[2, 40, 40] = 65535
    assert adc_top(darks, clipped) == 4095
    with pytest.raises(ValueError, match="saturated"):
        Calibration.from_frames(darks, clipped)
    flats = (150 + rng.poisson(3000, (6, 64, 64))).astype(np.uint16)
    flats[:, 10, 10] = 65535  # a stuck pixel, in every flat
    with pytest.warns(CalibrationWarning, match="1 pixels of the flats are saturated"):
        cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 4095 and cal.mask[10, 10] & PixelFlag.OVER_RESPONDING
    frame = (150 + rng.poisson(2000, (64, 64))).astype(np.uint16)
    frame[:4, :5] = 4095  # clipped where the beam is brightest
    frame[10, 10] = 65535
    _, report = correct_frames(cal, frame, domain="linear", return_report=True)
    # the 20 clipped; the stuck one is masked and filled, no measurement to count (review s42)
    assert report.saturated.tolist() == [20]


def test_the_outlier_share_is_taken_per_stack_not_over_darks_and_flats_together():
    """Found in review: the share of values allowed above a lower ADC top (ADC_OUTLIER_SHARE) was
    counted over darks and flats together, so 20 darks let a 16-bit panel's flats pass 4095 in
    0.4 % of their values and still be called 12-bit: the bright corner masked as saturated. The
    share is now each stack's own; a stuck pixel stays an outlier of its stack."""
    rng = np.random.default_rng(21)
    darks = np.rint(200 + rng.normal(0, 3, (20, 128, 128))).astype(np.uint16)
    flats = (200 + rng.poisson(3400, (4, 128, 128))).astype(np.uint16)
    flats[:, :8, :8] += 700  # a brighter corner (heel effect): ~4300 counts in 0.4 % of a flat
    assert np.count_nonzero(flats > 4095) > 2 * 1e-3 * flats.size
    assert np.count_nonzero(flats > 4095) < 1e-3 * (darks.size + flats.size)  # what hid it
    assert adc_top(darks, flats) == 16383  # the smallest top none of the values passes
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)  # no "lower the flat exposure"
        cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 16383 and not (cal.mask[:8, :8] & PixelFlag.OVER_RESPONDING).any()


def test_a_projection_passing_a_guessed_top_in_few_pixels_is_not_reported_saturated():
    """Found in review: the outlier share reached frame_saturation, so a projection of a 16-bit
    panel (calibrated 12-bit from flats under 4095) with a small bright patch at 9000 counts kept
    4095 and reported the patch saturated. A frame's own values above the calibration's top are
    outliers only where the calibration knows a defect; elsewhere the frame's range decides."""
    rng = np.random.default_rng(22)
    darks = np.rint(100 + rng.normal(0, 2, (4, 128, 128))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (4, 128, 128))).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 4095
    frame = (100 + rng.poisson(2000, (128, 128))).astype(np.uint16)
    frame[60:63, 60:63] = 9000  # 9 px of 16384: under the outlier share, above 4095
    _, report = correct_frames(cal, frame, domain="linear", return_report=True)
    assert report.saturated.tolist() == [0]


def test_a_stuck_pixel_does_not_hide_an_msb_aligned_panels_top():
    """Found in review: the unused low bits of MSB-aligned frames (``counts << 4``) were counted
    with every value, so one stuck pixel at 65535 left the top at 65535 and the flats' pixels
    clipped at 65520 unflagged. The low bits now ignore the same share of values as the top."""
    rng = np.random.default_rng(23)
    darks = np.rint(100 + rng.normal(0, 2, (4, 64, 64))).astype(np.uint16) << 4
    flats = (100 + rng.poisson(3000, (4, 64, 64))).astype(np.uint16)
    flats[:, :8, :8] = 4095  # 64 saturated pixels
    flats = flats << 4
    flats[1, 30, 30] = 65535  # a stuck pixel in one flat
    assert adc_top(darks, flats) == 65520
    with pytest.warns(CalibrationWarning, match="saturated"):
        cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 65520
    assert np.count_nonzero(cal.mask[:8, :8] & PixelFlag.OVER_RESPONDING) == 64


def test_flats_unexposed_outside_a_collimated_field_are_refused_naming_the_field():
    """Found by trying other labs' files: a collimator shading a 16-px border of a 256-px panel
    (24 % of it) was refused as darks and flats "not of one panel set-up (beam blocked for the
    flats? frames swapped ...)". The refusal now names the exposed field, to crop the frames to."""
    rng = np.random.default_rng(9)
    offset = 150 + rng.normal(0, 3, (256, 256))
    darks = np.rint(offset + rng.normal(0, 2, (4, 256, 256))).astype(np.uint16)
    lit = np.zeros((256, 256), bool)
    lit[16:240, 16:240] = True
    flats = np.rint(offset + np.where(lit, rng.poisson(3000, (4, 256, 256)), rng.normal(0, 2, (4, 256, 256))))
    with pytest.raises(ValueError, match=r"unexposed outside rows 16-239, columns 16-239 .*collimator") as info:
        Calibration.from_frames(darks, flats.astype(np.uint16))
    assert "frames swapped" not in str(info.value)


@pytest.mark.parametrize("shape", [(1, 300), (300, 1), (3, 3)])
def test_frames_too_small_for_lines_have_no_defect_lines(shape):
    """Found by trying other labs' files: a 1 x 300 line-scan frame (and a 3 x 3 one) was refused
    as darks and flats "not of one panel set-up": each 1-pixel column was judged as a defect line,
    its noise against 1.5x the panel's and its one pixel as more than half of it flagged. A line
    of a few pixels says nothing its pixels do not."""
    rng = np.random.default_rng(13)
    darks = np.rint(150 + rng.normal(0, 2, (6, *shape))).astype(np.uint16)
    flats = (150 + rng.poisson(3000, (6, *shape))).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    assert cal.defect_rows.size == cal.defect_columns.size == 0
    assert np.count_nonzero(cal.mask) <= MAX_DEFECTIVE_SHARE * cal.mask.size


def test_a_12_bit_panel_stored_in_the_top_bits_saturates_at_65520():
    """Found by trying other labs' files: frame grabbers often store a 12-bit panel's counts in the
    top bits of 16 (``value << 4``). Its top is 65520, under the 65535 of a 16-bit ADC, so the
    flat's saturated pixels were not flagged and the "lower the flat exposure" warning never came.
    The unused low bits now lower the top; an LSB-aligned frame (noise sets every bit) keeps it."""
    rng = np.random.default_rng(11)
    darks = np.rint(100 + rng.normal(0, 2, (4, 32, 32))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (4, 32, 32))).astype(np.uint16)
    flats[:, :8, :8] = 4095  # 64 saturated pixels
    with pytest.warns(CalibrationWarning, match="saturated"):
        cal = Calibration.from_frames(darks << 4, flats << 4)
    assert cal.thresholds.saturation == 65520
    assert np.count_nonzero(cal.mask & PixelFlag.OVER_RESPONDING) == 64
    bright = (100 + rng.poisson(3000, (32, 32))).astype(np.uint16)
    bright[20:22, 20:23] = 4095  # outside the flat's masked corner, where none count (review s42)
    _, report = correct_frames(cal, bright << 4, domain="linear", return_report=True)
    assert report.saturated.tolist() == [6]
    assert adc_top(darks, flats) == 4095 and adc_top(flats.astype(np.float32) * 16) == 65535
    # noise-free frames at round numbers leave low bits unused too (review): 4064 = 0xFE0 is a
    # flat's level, not the ADC's top
    flat = np.full((3, 16, 16), 4064, np.uint16)
    assert adc_top(np.full((3, 16, 16), 96, np.uint16), flat) == 4095


def test_a_16_bit_experiment_file_warns_of_its_bit_depth_once(tmp_path):
    """An experiment file that does not record its panel's bit depth is read as the C7942's 12
    bits: its 16-bit frames warned once per frame read (one line per frame on the command line);
    now once per open file. With ``bit_depth=16`` recorded, not at all."""
    from radiokit.io import BitDepthWarning, open_frames

    for bit_depth, expected in ((None, 1), (16, 0)):
        path = tmp_path / f"exp{bit_depth}.h5"
        _sixteen_bit_experiment(path, bit_depth, np.random.default_rng(8))
        with warnings.catch_warnings(record=True) as caught, open_frames(path) as src:
            warnings.simplefilter("always")
            frames = [src[i] for i in range(len(src))]
        assert len(frames) == 9
        assert sum(issubclass(w.category, BitDepthWarning) for w in caught) == expected, bit_depth


def test_flats_at_another_tube_current_than_the_projections(tmp_path):
    """Flats at 200 uA, projections at 100 uA (the tube's output proportional to its current):
    every transmission read half its value, the line integrals ln 2 too high, silently. Both
    `radiokit process`'s steps and `radiokit correct` now scale by the recorded currents; a
    voltage that differs is warned of (no factor corrects a spectrum)."""
    from radiokit.calibrate import exposure_factors
    from radiokit.correct import correct_files
    from radiokit.io import read
    from radiokit.pipeline import load_steps

    shape, rng = (96, 128), np.random.default_rng(9)
    L = np.tile(np.linspace(0.2, 1.2, shape[1]), (shape[0], 1))
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05, source={"voltage_kv": 40, "current_ua": 200}) as w:
        for _ in range(3):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(100 + rng.poisson(3000, shape), image_key=ImageKey.FLAT, voltage_kv=40, current_ua=200)
        for step, kv in ((1, 40), (2, 45)):  # step 2 also at another voltage
            raw = 100 + rng.poisson(1500 * np.exp(-L))  # half the flats' current: half the counts
            w.append(raw, image_key=ImageKey.PROJECTION, step=step, voltage_kv=kv, current_ua=100)
    with pytest.warns(CalibrationWarning, match=r"1 frame\(s\) at \[45.0\] kV, the flats at 40.0 kV"):
        steps = load_steps(path)
    # one frame's Poisson noise at >= 450 counts (sigma 0.05 in L) and the flats' (0.01)
    assert float(np.mean(steps.images[0] - L)) == pytest.approx(0, abs=2e-3)  # ln 2 = 0.69 before
    cal = Calibration.from_experiment(path)
    with pytest.warns(CalibrationWarning, match="45.0"):
        correct_files(path, cal, tmp_path / "t.h5", domain="linear", progress=False)
    t = read(tmp_path / "t.h5").data[0]
    assert float(np.mean(t / np.exp(-L))) == pytest.approx(1, abs=3e-3)  # 0.5 before
    # the controller's readback jitters by a uA or two: the same setting, not a factor of 200/201
    jitter = {"image_key": np.zeros(3), "current": np.array([201.0, 198.0, 100.0])}
    np.testing.assert_array_equal(exposure_factors(cal, jitter, path, [0, 1, 2]), [1.0, 1.0, 2.0])


def test_the_voltage_warning_counts_every_projection_at_another_voltage(tmp_path):
    """Flats at 40 kV, the one projection of each of three steps at 45 kV: `radiokit process` warned
    once per step, "1 frame(s) at [45.0] kV" each time (shown once: Python does not repeat a
    text), where all three were at another voltage. One warning now, counting them all."""
    from radiokit.pipeline import load_steps

    shape, rng = (16, 20), np.random.default_rng(11)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05, source={"voltage_kv": 40, "current_ua": 100}) as w:
        for _ in range(2):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
            w.append(100 + rng.poisson(3000, shape), image_key=ImageKey.FLAT, voltage_kv=40, current_ua=100)
        for step in (1, 2, 3):
            w.append(100 + rng.poisson(1500, shape), image_key=ImageKey.PROJECTION, step=step, voltage_kv=45)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_steps(path)
    said = [str(c.message) for c in caught if issubclass(c.category, CalibrationWarning) and " kV" in str(c.message)]
    assert len(said) == 1 and "3 frame(s) at [45.0] kV" in said[0], said


def _darks_and_flats(w, shape, rng, n):
    """``n`` darks at 100 counts and ``n`` flats at 3100 (Poisson noise of 5), appended to ``w``."""
    for key, level in ((ImageKey.DARK, 100), (ImageKey.FLAT, 3100)):
        for _ in range(n):
            w.append(level + rng.poisson(5, shape), image_key=key)


def test_process_refuses_a_projection_with_the_beam_off(tmp_path):
    """A projection at the dark level (the beam off, a shutter closed) was clamped, "filled" and
    averaged into its step: the step's mean was pulled halfway to a uniform image, silently."""
    from radiokit.errors import FormatError
    from radiokit.pipeline import load_steps

    shape, rng = (64, 80), np.random.default_rng(10)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        _darks_and_flats(w, shape, rng, 3)
        w.append(100 + rng.poisson(1500, shape), image_key=ImageKey.PROJECTION, step=1)
        w.append(100 + rng.poisson(5, shape), image_key=ImageKey.PROJECTION, step=2)  # beam off: the dark
        w.append(100 + rng.poisson(1400, shape), image_key=ImageKey.PROJECTION, step=2)
    with pytest.raises(FormatError, match=r"exp.h5: frame 7 \(step 2\): no signal above the dark"):
        load_steps(path)


def test_three_darks_of_a_clean_panel_flag_no_noisy_pixels():
    """Three darks of a panel with no noisy pixel (Gaussian read noise of 2.2 counts): about 1
    pixel in 1400 was flagged noisy (its std, after the most deviant sample was dropped, is one
    difference of two samples, whose tail passes 5x the median) and then filled in every frame."""
    rng = np.random.default_rng(12)
    shape = (512, 512)
    darks = np.rint(rng.normal(100, 2.2, (3, *shape))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (3, *shape))).astype(np.uint16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)  # "take 10 or more"
        cal = Calibration.from_frames(darks, flats)
    assert cal.provenance["defects"]["noisy"] == 0


def test_process_says_when_projections_hold_saturated_pixels(tmp_path):
    """A 20 x 20 patch at the ADC's top (4095) in every projection: nothing said so, and its
    pixels, whose intensity is unknown, entered the steps like any other."""
    from radiokit.pipeline import load_steps

    shape, rng = (64, 80), np.random.default_rng(13)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        for key, level in ((ImageKey.DARK, 100), (ImageKey.FLAT, 3100)):
            for _ in range(4):
                frame = level + rng.poisson(5, shape)
                frame[50, 5:8] = 4095  # stuck pixels (review s42): masked and filled, not counted
                w.append(frame, image_key=key)
        for step in (1, 2):
            for _ in range(2):
                raw = 100 + rng.poisson(1500, shape)
                raw[10:30, 20:40] = 4095
                raw[50, 5:8] = 4095
                w.append(raw, image_key=ImageKey.PROJECTION, step=step)
    with pytest.warns(
        CalibrationWarning,
        match=r"saturated pixels \(>= 4095\).*step 1: 800 in 2 of 2 frames, step 2: 800 in 2 of 2 frames",
    ):
        load_steps(path)


@pytest.mark.parametrize("domain", ["log", "linear"])
def test_a_recorded_gap_wider_than_the_fill_reach_takes_its_nearest_valid_value(domain, tmp_path):
    """A tiled panel's gap (10-37 px) recorded in the file's pixel_mask joins the defect map, and
    its pixels more than 8 px from a valid one were 'filled' with weight 0: 0 in either domain, an
    open-beam stripe in the log one through a body (and nothing through in the linear one). They
    take the nearest valid pixel's value; through a uniform body of transmission 1/2, that value."""
    from radiokit.calibrate import PixelFlag
    from radiokit.correct import correct_frames

    panel = _panel(rows=48, cols=256)  # a 20 px gap is 7.8 % of it, under the 10 % refused
    rng = np.random.default_rng(11)
    darks, flats = panel.dark_frames(5, rng), panel.flat_frames(5, 2000, rng)
    recorded = np.zeros(panel.shape, np.uint32)
    recorded[:, 100:120] = PixelFlag.GAP  # 20 px: its middle 4 columns lie over 8 px from data
    path = tmp_path / "gap.h5"
    _experiment_with_mask(path, panel, darks, flats, recorded)
    cal = Calibration.from_experiment(path)
    raw = cal.dark + 0.5 * (cal.flat - cal.dark)  # transmission 1/2 everywhere
    out = correct_frames(cal, raw, domain=domain)
    expected = np.log(2) if domain == "log" else 0.5
    # float32 arithmetic on ~2000 counts: exact to 1e-4; the gap's fill is the edge's value
    np.testing.assert_allclose(out[:, 100:120], expected, atol=1e-3)


def test_a_flat_saturated_in_a_fifth_of_the_panel_is_refused_for_its_saturation():
    """Found binning a simulated source set for 1x1 (session 31): a flat clipped at 4095 in 12 % of
    its pixels was refused as "not of one panel set-up (beam blocked for the flats? ...)", the
    wrong cause and the wrong fix. The refusal now names the saturation and the exposure; a defect
    map over the share for other reasons keeps the set-up message."""
    rng = np.random.default_rng(12)
    darks = np.rint(100 + rng.normal(0, 2, (4, 40, 40))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (4, 40, 40))).astype(np.uint16)
    flats[:, :, :8] = 4095  # a fifth of the panel clipped (the bright side of a heel effect)
    with pytest.raises(ValueError, match=r"saturated.*lower the flat exposure") as err:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CalibrationWarning)
            Calibration.from_frames(darks, flats)
    assert "beam blocked" not in str(err.value)
    flats = (100 + rng.poisson(3000, (4, 40, 40))).astype(np.uint16)
    flats[:, :, :8] = 110  # the same share dark: blocked, not saturated
    with pytest.raises(ValueError, match="beam blocked"), warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        Calibration.from_frames(darks, flats)


def test_judge_frames_refuses_and_warns_as_from_frames_does():
    """The acquisition judges its frames with this (no second set of rules): the same refusal
    text as a calibration from them, and its warnings returned rather than emitted."""
    from radiokit.calibrate import judge_frames

    rng = np.random.default_rng(3)
    darks = rng.normal(100, 2, (4, 64, 64)).astype(np.uint16)
    clipped = np.minimum(rng.normal(5000, 30, (4, 64, 64)), 4095).astype(np.uint16)  # 12-bit ADC top
    with pytest.raises(ValueError) as judged:
        judge_frames(darks, clipped)
    with pytest.raises(ValueError) as calibrated:
        Calibration.from_frames(darks, clipped)
    assert str(judged.value) == str(calibrated.value) and "saturated" in str(judged.value)
    flats = rng.normal(3000, 20, (4, 64, 64)).astype(np.uint16)
    flats[:, :2, :3] = 4095  # 6 pixels clipped: flagged, and warned of
    told = judge_frames(darks, flats)
    assert len(told) == 1 and "6 pixels of the flats are saturated" in told[0], told
    assert judge_frames(darks, rng.normal(3000, 20, (4, 64, 64)).astype(np.uint16)) == []


def test_judge_darks_refuses_darks_no_flat_could_be_brighter_than():
    from radiokit.calibrate import judge_darks

    rng = np.random.default_rng(4)
    lit = np.minimum(rng.normal(4200, 30, (4, 64, 64)), 4095).astype(np.uint16)  # darks at the ADC's top
    with pytest.raises(ValueError, match=r"darks read 4095 counts .*ADC's top \(4095\)"):
        judge_darks(lit)
    # the rule it anticipates: any flat the ADC can give is refused against these darks
    with pytest.raises(ValueError, match="not brighter than darks"):
        Calibration.from_frames(lit, np.full((4, 64, 64), 4095, np.uint16))
    judge_darks(rng.normal(100, 2, (4, 64, 64)).astype(np.uint16))  # real darks pass
    judge_darks(rng.normal(4000, 2, (4, 64, 64)).astype(np.uint16), saturation=16383)  # a 14-bit panel's


def _judged(darks, flats):
    """judge_frames' refusal of these frames (pytest.fail when it accepts them)."""
    from radiokit.calibrate import judge_frames

    with pytest.raises(ValueError) as refused:
        judge_frames(darks, flats)
    return refused.value


def test_a_refusal_names_the_darks_when_they_are_brighter_than_the_flats():
    """A light leak on the darks (the cabinet open, the beam on): the C7942's own darks read its
    hundred-odd count offset, these 1500 counts more, and the flats (1000 counts of beam over the
    offset) are darker than them. The refusal said "flats not brighter than darks: was the beam
    on for the flats?" and the acquisition retook the flats against the same darks, refused again
    at every resume. A flat reads at least the panel's dark: the darks are at fault."""
    panel = PanelModel(rows=64, cols=64, seed=3)
    rng = np.random.default_rng(0)
    leak = 1500.0
    darks = (panel.dark_frames(4, rng) + leak).astype(np.uint16)
    flats = panel.flat_frames(4, 1000.0, rng)
    assert np.median(flats) < np.median(darks) - 100  # the physics: flats under the lit darks
    refused = _judged(darks, flats)
    assert refused.culprits == ("darks",), str(refused)
    assert "darks read" in str(refused) and "light reached the panel" in str(refused), str(refused)
    # the same flats with the panel's own darks pass: the flats were never the fault
    from radiokit.calibrate import judge_frames

    judge_frames(panel.dark_frames(4, rng), flats)


def test_a_refusal_names_darks_and_flats_when_the_offset_leaves_no_room():
    """An offset near the 12-bit ADC's top (3950 counts: the read-out's offset set wrong, or light on
    the panel throughout): any beam clips the flats at 4095. The refusal said "lower the flat
    exposure", which cannot help while the darks leave 145 counts; both are taken again."""
    panel = PanelModel(rows=64, cols=64, dark_level=3950.0, seed=3)
    rng = np.random.default_rng(1)
    darks, flats = panel.dark_frames(4, rng), panel.flat_frames(4, 1000.0, rng)
    assert np.median(flats) == panel.saturation  # clipped, as the ADC does
    refused = _judged(darks, flats)
    assert refused.culprits == ("darks", "flats"), str(refused)
    assert "over half the ADC's range (0-4095)" in str(refused) and "offset" in str(refused), str(refused)
    assert "lower the flat exposure" not in str(refused)


def test_a_refusal_still_names_the_flats_when_the_beam_was_blocked():
    """Flats taken with the beam off read the panel's darks: the flats are at fault, as before."""
    panel = PanelModel(rows=64, cols=64, seed=3)
    rng = np.random.default_rng(2)
    refused = _judged(panel.dark_frames(4, rng), panel.dark_frames(4, rng))
    assert refused.culprits == ("flats",) and "was the beam on for the flats?" in str(refused), str(refused)
    clipped = _judged(panel.dark_frames(4, rng), panel.flat_frames(4, 5000.0, rng))
    assert clipped.culprits == ("flats",) and "lower the flat exposure" in str(clipped), str(clipped)


def test_judge_darks_warns_of_darks_over_half_the_adc_range():
    """Darks at 3000 counts on a 12-bit panel leave the flats 1095: said at once (the flats may
    still fit, so not refused); a C7942's own darks are not warned of."""
    from radiokit.calibrate import judge_darks

    rng = np.random.default_rng(5)
    told = judge_darks(PanelModel(rows=64, cols=64, dark_level=3000.0).dark_frames(4, rng), saturation=4095)
    assert len(told) == 1 and "over half the ADC's range (0-4095)" in told[0], told
    assert judge_darks(PanelModel(rows=64, cols=64).dark_frames(4, rng), saturation=4095) == []


def test_darks_are_not_called_bright_against_a_top_only_guessed_from_the_frames():
    """A 16-bit panel at a low dose: darks at 2500 counts, flats at 3800, nothing over 4095. The
    ADC's top guessed from the frames is then 4095 (adc_top), and the darks were called "over half
    the ADC's range ... a C7942's offset is a few hundred"; with flats taken through a blocked
    beam the refusal named the darks too ("no flat exposure helps"). Against a guessed top the
    half-range rule says nothing: its warning and blame need the top given (the panel's bits) or
    seen (frames clipped at it). Review s32-r1."""
    from radiokit.calibrate import judge_darks, judge_frames

    rng = np.random.default_rng(8)
    darks = rng.normal(2500, 5, (4, 64, 64)).astype(np.uint16)
    flats = rng.normal(3800, 20, (4, 64, 64)).astype(np.uint16)
    assert judge_frames(darks, flats) == [] and judge_darks(darks) == []
    assert any("over half" in w for w in judge_frames(darks, flats, saturation=4095))  # a 12-bit panel's: said
    blocked = _judged(darks, rng.normal(2500, 5, (4, 64, 64)).astype(np.uint16))
    assert blocked.culprits == ("flats",), str(blocked)


def _heel_corner_frames(rng, top=4095):
    """A 16-bit panel's darks and flats whose brighter corner (heel effect) passes ``top`` in
    16 pixels of 16 384 (0.098 %): within the share the ADC-top rule takes for stuck pixels."""
    darks = np.rint(200 + rng.normal(0, 3, (4, 128, 128))).astype(np.uint16)
    flats = (200 + rng.poisson(3400, (4, 128, 128))).astype(np.uint16)
    flats[:, :4, :4] += 700 + (top - 4095)  # ~4300 counts over a 12-bit ADC's top: no defect, no saturation
    assert 0 < np.count_nonzero(flats > top) <= 1e-3 * flats.size
    return darks, flats


def test_a_16_bit_experiment_given_as_dark_and_flat_files_keeps_its_recorded_bit_depth(tmp_path):
    """`calibrate --dark exp.h5 --flat exp.h5` of an experiment recording bit_depth_readout 16:
    the frames' own record was dropped on the way, and the ADC-top rule took the flats' bright
    corner (0.1 % of them above 4095) for a 12-bit panel's stuck pixels: saturation 4095, the
    corner masked as saturated. The files' bit depth now settles it, as --experiment does."""
    from conftest import run_cli

    darks, flats = _heel_corner_frames(np.random.default_rng(3))
    path = tmp_path / "exp16.h5"
    with ExperimentWriter(path, shape=darks.shape[1:], bit_depth=16) as w:
        for frame in darks:
            w.append(frame, image_key=ImageKey.DARK)
        for frame in flats:
            w.append(frame, image_key=ImageKey.FLAT)
    res = run_cli("calibrate", "--dark", path, "--flat", path, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    cal = Calibration.load(tmp_path / "cal.h5")
    assert cal.thresholds.saturation == Calibration.from_experiment(path).thresholds.saturation == 65535
    assert not cal.mask[:4, :4].any()


def test_tiff_frames_declaring_14_bits_in_16_bit_words_saturate_at_16383(tmp_path):
    """TIFF flats saying BitsPerSample 14 over 16-bit words whose bright corner passes 4095 in
    0.1 % of values: read() now says ``meta["bit_depth"] = 14`` and the calibration takes the
    frames' own word for their ADC (16383) over the share rule (which said 4095: the corner
    flagged saturated)."""

    darks, flats = _heel_corner_frames(np.random.default_rng(5))
    frames = {
        name: _words_tiff(tmp_path / f"{name}.tif", stack, 14) for name, stack in (("dark", darks), ("flat", flats))
    }
    assert frames["dark"].meta["bit_depth"] == frames["flat"].meta["bit_depth"] == 14
    cal = Calibration.from_frames(frames["dark"], frames["flat"])
    assert cal.thresholds.saturation == 16383
    assert not cal.mask[:4, :4].any()


def _words_tiff(path, stack, bits):
    """``stack`` written as 16-bit words saying BitsPerSample ``bits`` on every page, as some
    panels' software writes, and read back."""
    import struct

    from radiokit.io import read

    tifffile.imwrite(path, stack, photometric="minisblack")
    data = bytearray(path.read_bytes())
    ifd = struct.unpack_from("<I", data, 4)[0]
    while ifd:
        count = struct.unpack_from("<H", data, ifd)[0]
        for k in range(count):
            if struct.unpack_from("<H", data, ifd + 2 + 12 * k)[0] == 258:
                struct.pack_into("<H", data, ifd + 2 + 12 * k + 8, bits)
        ifd = struct.unpack_from("<I", data, ifd + 2 + 12 * count)[0]
    path.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "read as 16-bit words", and a BitDepthWarning for MSB-aligned data
        return read(path)


def test_a_declared_bit_depth_the_frames_contradict_is_not_taken(tmp_path):
    """Words saying BitsPerSample 12 that hold a 12-bit panel's counts MSB-aligned (``<< 4``, up
    to 65520: read() warns of it): the declared 4095 would call every flat pixel saturated and
    refuse the calibration; frames above the depth their files declare are judged by their own
    range, as without a declaration (65520, the clipped corner alone flagged)."""
    rng = np.random.default_rng(11)
    darks = np.rint(100 + rng.normal(0, 2, (4, 32, 32))).astype(np.uint16) << 4
    flats = (100 + rng.poisson(3000, (4, 32, 32))).astype(np.uint16)
    flats[:, :8, :8] = 4095  # 64 saturated pixels
    frames = [_words_tiff(tmp_path / f"{k}.tif", s, 12) for k, s in enumerate((darks, flats << 4))]
    with pytest.warns(CalibrationWarning, match="saturated"):
        cal = Calibration.from_frames(*frames)
    assert cal.thresholds.saturation == 65520
    assert np.count_nonzero(cal.mask & PixelFlag.OVER_RESPONDING) == 64


def _gapped(panel, gap_rows, fill, n=10, seed=1):
    """Darks and flats of ``panel`` (int32, as tiled detectors write them) with ``gap_rows`` reading
    ``fill`` in every frame: the gaps between a tiled detector's modules, or a dead band."""
    rng = np.random.default_rng(seed)
    darks = panel.dark_frames(n, rng).astype(np.int32)
    flats = panel.flat_frames(n, 2500.0, rng).astype(np.int32)
    darks[:, gap_rows] = fill
    flats[:, gap_rows] = fill
    return darks, flats


def test_a_wide_dead_band_flags_its_own_rows_and_no_others():
    """Found by a reviewer feeding other detectors' files (session 40): a 16-row band reading 0,
    half a 32-px tile, dragged those tiles' median response to half, so the good rows beside it
    read twice the "local" response: 58 rows flagged for 16, and 42 good rows refilled in every
    frame. The band's rows alone are defect lines now, and every other row keeps the defect map
    it has without the band (the planted defects, nothing more)."""
    panel = _panel()
    band = np.arange(96, 112)
    clean = Calibration.from_frames(*_gapped(panel, [], 0))
    cal = Calibration.from_frames(*_gapped(panel, band, 0))
    assert cal.defect_rows.tolist() == band.tolist()
    assert (cal.mask[band] & PixelFlag.DEAD).all()
    others = np.setdiff1d(np.arange(SHAPE[0]), band)
    assert np.array_equal(cal.mask[others] != 0, clean.mask[others] != 0)


def test_a_tiled_detectors_module_gaps_are_flagged_alone():
    """A Pilatus-300K-like layout: three modules of 195 rows with 17-row gaps between them
    reading -1 (5.5 % of the pixels). Refused at "12.4 %" as frames "not of one panel set-up",
    the gaps having spread to the rows around them; now the gaps are the defect lines, and the
    share flagged is theirs plus the planted defects."""
    panel = PanelModel(rows=619, cols=96, defect_columns=(), n_dead=5, n_under=5, n_noisy=0)
    gaps = np.r_[195:212, 407:424]
    cal = Calibration.from_frames(*_gapped(panel, gaps, -1))
    assert cal.defect_rows.tolist() == gaps.tolist()
    assert np.count_nonzero(cal.mask) <= gaps.size * 96 + 10


def test_a_refusal_over_the_defect_limit_names_the_gaps():
    """Gaps between modules taking 24 % of the frame are over the share a panel's defects may
    take: the refusal says they are whole rows without response (gaps), not frames "of another
    set-up (beam blocked?)", which sent the user looking for a fault that was not there."""
    panel = PanelModel(rows=211, cols=96, defect_columns=(), n_dead=5, n_under=5, n_noisy=0)
    gaps = np.r_[40:57, 97:114, 154:171]
    with pytest.raises(ValueError, match=r"51 whole rows.*gaps") as err:
        Calibration.from_frames(*_gapped(panel, gaps, -1))
    assert "beam blocked" not in str(err.value)


def test_a_circular_field_is_refused_with_advice_to_crop():
    """An image intensifier's round field on a square frame: the corners, unexposed, are 21 % of
    it. Refused at 47 % (the disc's edge spread into the good pixels beside it) as frames of
    another set-up; now the refusal names the disc, its centre and radius, and the square
    inside it to crop to (half its side 128 / sqrt 2 = 90.5 px about the centre 127.5)."""
    panel = PanelModel(rows=256, cols=256, defect_columns=(), n_dead=5, n_under=5, n_noisy=0)
    rr, cc = np.mgrid[:256, :256]
    outside = (rr - 127.5) ** 2 + (cc - 127.5) ** 2 > 128**2
    rng = np.random.default_rng(1)
    darks = panel.dark_frames(10, rng)
    flats = panel.expose(np.where(outside, 30.0, 0.0), 2500.0, n=10, rng=rng)
    with pytest.raises(ValueError, match=r"radius 12[6-9].*circular field.*crop.*rows 3[78]-21[78]"):
        Calibration.from_frames(darks, flats)


def _small_cal(level=3000.0):
    return Calibration(
        np.full((8, 8), 100.0, np.float32), np.full((8, 8), level, np.float32), np.zeros((8, 8), np.uint8)
    )


def test_save_refuses_an_existing_file_unless_overwrite_and_replaces_it_whole(tmp_path):
    """Saving twice replaced the first calibration silently (its group deleted in place)."""
    path = _small_cal(3000).save(tmp_path / "cal.h5")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match=r"cal\.h5: exists; pass --overwrite \(overwrite=True\)"):
        _small_cal(1500).save(path)
    assert path.read_bytes() == before
    _small_cal(1500).save(path, overwrite=True)
    assert Calibration.load(path).c == pytest.approx(1400)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.h5"]  # no temporary left beside it


def test_save_never_writes_into_an_experiment_file(tmp_path):
    """``cal.save("exp.h5")`` added a ``calibration`` group inside a raw experiment file."""
    exp = tmp_path / "exp.h5"
    with ExperimentWriter(exp, shape=(8, 8), pixel_size_mm=0.05) as w:
        w.append(np.full((8, 8), 100, np.uint16), image_key=ImageKey.DARK)
    before = exp.read_bytes()
    with pytest.raises(FileExistsError, match="exp.h5: exists"):
        _small_cal().save(exp)
    assert exp.read_bytes() == before


def test_save_onto_a_file_that_is_no_hdf5_names_it(tmp_path):
    """A text file as the target was h5py's "Unable to synchronously open file (file signature
    not found)", naming no file."""
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    with pytest.raises(OSError, match=r"notes\.txt: exists"):
        _small_cal().save(notes)
    assert notes.read_text() == "my notes"


def test_from_frames_refuses_masked_darks_or_flats():
    """A masked array's ``.data`` is its values: the mask was dropped, the masked pixels averaged."""
    darks = np.full((3, 8, 8), 100, np.uint16)
    flats = np.ma.masked_array(np.full((3, 8, 8), 3000, np.uint16), mask=np.zeros((3, 8, 8), bool))
    with pytest.raises(ValueError, match=r"^flats is a masked array, whose mask would be ignored"):
        Calibration.from_frames(darks, flats)


def _stepped_flats(step, n=8, rows=64, cols=256, at=120, seed=3):
    """Darks and flats of a healthy panel whose gain steps by ``step`` right of column ``at``, as
    between a flat panel's read-out blocks."""
    rng = np.random.default_rng(seed)
    signal = np.full((rows, cols), 2500.0)
    signal[:, at:] *= step
    darks = (100 + rng.poisson(4, (n, rows, cols))).astype(np.uint16)
    flats = (100 + rng.poisson(signal, (n, rows, cols))).astype(np.uint16)
    return darks, flats, signal


@pytest.mark.parametrize("step", [1.2, 0.85])
def test_a_gain_step_between_readout_blocks_is_no_defect_line(step):
    """Found by review s42: flat - dark 1.12-1.2 or 0.85 times higher right of a column (a flat
    panel's read-out blocks) flagged 8-29 columns beside the step as defect lines, measured
    against a 32-px block median the step drags; they were filled in every frame, and a 1-px wire
    of transmission 0.3 there came out 0.6. A defect line differs from the lines on both sides;
    a step's columns agree with one side. Lines near the step are still found (one at 0.9, 3 px
    from it; right beside a 1.2 step it reads 1.08, between the two sides, as the column of a
    binned step's straddling pixels does, and is not told from one)."""
    darks, flats, signal = _stepped_flats(step)
    cal = Calibration.from_frames(darks, flats)
    assert cal.defect_columns.size == 0 and cal.defect_rows.size == 0
    assert np.count_nonzero(cal.mask) == 0
    rng = np.random.default_rng(4)
    t = np.full(signal.shape, 0.6)
    t[:, [116, 119, 120, 124]] = 0.3  # wires either side of the step
    out = correct_frames(cal, (100 + rng.poisson(t * signal)).astype(np.uint16), domain="linear")
    # 64 rows of ~750-1500 counts: the column mean's noise is well under 0.01
    np.testing.assert_allclose(out[:, [116, 119, 120, 124]].mean(axis=0), 0.3, atol=0.01)
    darks, flats, _ = _stepped_flats(step, seed=5)
    flats[:, :, [123, 60]] = (100 + 0.9 * (flats[:, :, [123, 60]] - 100.0)).astype(np.uint16)
    assert Calibration.from_frames(darks, flats).defect_columns.tolist() == [60, 123]


def test_more_defect_lines_than_a_panel_has_are_warned_of():
    """The manual gives a panel up to 20 defect lines: more found (here 24 columns at 90 %) say the
    flats or the thresholds are at fault (a gain step, a non-uniform beam), and every such line is
    filled in every frame; the calibration says so."""
    darks, flats, _ = _stepped_flats(1.0)
    bad = np.arange(8, 248, 10)  # 24 columns
    flats[:, :, bad] = (100 + 0.9 * (flats[:, :, bad] - 100.0)).astype(np.uint16)
    with pytest.warns(CalibrationWarning, match=r"24 defect lines.*20") as caught:
        cal = Calibration.from_frames(darks, flats)
    assert cal.defect_columns.tolist() == bad.tolist()
    assert len([w for w in caught if "defect lines" in str(w.message)]) == 1


def _heel_flats(n=10, rows=64, cols=160, seed=5):
    """Darks and 12-bit flats (clipped at 4095) whose flat - dark rises along the columns from 1000
    to 4150 counts (a heel effect), and that signal: its last twelfth clips in most frames."""
    rng = np.random.default_rng(seed)
    signal = np.broadcast_to(np.linspace(1000.0, 4150.0, cols), (rows, cols)).copy()
    darks = (100 + rng.poisson(4, (n, rows, cols))).astype(np.uint16)
    flats = (100 + rng.poisson(signal, (n, rows, cols))).clip(0, 4095).astype(np.uint16)
    return darks, flats, signal


def test_a_flat_clipped_in_many_of_its_frames_is_flagged_and_warned_of():
    """Found by review s42 (t5b_flatclip.py): flats clipped at 4095 in most frames of a bright band
    were judged only by their average, which clipping keeps below 4095: 111 of 5120 band pixels
    flagged, the band's transmission 0.8 % high, no word of it. A pixel whose clipped samples are
    kept in its average (not a zinger's, which the average drops) is biased low: flagged, and the
    warning counts such pixels and their clipped samples."""
    darks, flats, signal = _heel_flats()
    clipped = (flats == 4095).sum(axis=0)
    with pytest.warns(
        CalibrationWarning, match=r"pixels of the flats are saturated.*in [\d-]+ of their 10 frames"
    ) as w:
        cal = Calibration.from_frames(darks, flats)
    told = [str(x.message) for x in w if "saturated" in str(x.message)]
    n_told = int(told[0].split()[0])
    # a pixel clipped in a third of its frames or more is biased by a good part of a count at least
    heavy = clipped >= 4
    assert heavy.sum() > 300 and (cal.mask[heavy] & PixelFlag.OVER_RESPONDING).all()
    assert heavy.sum() <= n_told <= np.count_nonzero(clipped)  # never one that was not clipped
    # the frame's expected counts (a Poisson frame's noise, filled into the band from one column
    # beside it, was 0.0015 of transmission: a seed passed or failed a tighter bound by luck)
    t = correct_frames(cal, (100 + 0.5 * signal).astype(np.float32), domain="linear")
    truth = (0.5 * signal - 4) / (signal - 4)  # the darks read 100 + 4 on average
    band = clipped.mean(axis=0) >= 1
    # before: 0.0042 high (0.8 %). Left: the band is filled from the columns beside it, whose flats
    # clipped in a few samples too: +0.0008 to +0.0018 over calibration seeds 3-12
    assert abs(float(t[:, band].mean() - truth[:, band].mean())) < 0.002


def test_a_flat_clipped_in_half_its_pixels_frame_by_frame_is_refused_for_its_saturation():
    """Review s42 (t5_flatclip.py): a flat reading 4090 on average over half the panel, clipped in
    about half of those frames' samples, was taken; once its clipped pixels are flagged, the refusal
    for flagging too much must name the saturation, not frames "not of one panel set-up"."""
    rng = np.random.default_rng(5)
    signal = np.full((64, 64), 3000.0)
    signal[:, 32:] = 3990.0
    darks = (100 + rng.poisson(4, (6, 64, 64))).astype(np.uint16)
    flats = (100 + rng.poisson(signal, (6, 64, 64))).clip(0, 4095).astype(np.uint16)
    with pytest.raises(ValueError, match=r"saturated.*lower the flat exposure") as err:
        Calibration.from_frames(darks, flats)
    assert "one panel set-up" not in str(err.value)


def _banded_flats(first, width, level, seed=5):
    """``_stepped_flats`` without a step, ``width`` adjacent columns from ``first`` responding at
    ``level`` of the others."""
    darks, flats, signal = _stepped_flats(1.0, seed=seed)
    band = np.arange(first, first + width)
    flats[:, :, band] = (100 + level * (flats[:, :, band] - 100.0)).astype(np.uint16)
    signal[:, band] *= level
    return darks, flats, signal, band


@pytest.mark.parametrize("width", [1, 2, 3, 4, 5, 8])
def test_a_band_of_lines_is_flagged_whole_or_not_at_all(width):
    """Review s42rr: 4 adjacent columns at 0.88 gave only the middle two as defect lines, 5 only
    the middle one: the band's edges were filled from lines inside it. Up to 3 adjacent lines off
    both sides are defect lines, whole; a wider band at one uniform response is a gain band (as a
    read-out block is), which the flat field corrects pixel by pixel: none of it is flagged, and a
    wire across it comes out at its transmission."""
    darks, flats, signal, band = _banded_flats(100, width, 0.88)
    cal = Calibration.from_frames(darks, flats)
    if width <= 3:
        assert cal.defect_columns.tolist() == band.tolist()
        return
    assert cal.defect_columns.size == 0 and np.count_nonzero(cal.mask) == 0
    rng = np.random.default_rng(4)
    t = np.full(signal.shape, 0.6)
    t[30:34, :] = 0.3  # a wire along the rows, across the band
    out = correct_frames(cal, (100 + rng.poisson(t * signal)).astype(np.uint16), domain="linear")
    # 4 rows x the band of ~660-1320 counts: the mean's noise is well under 0.01
    np.testing.assert_allclose(out[30:34, band].mean(), 0.3, atol=0.01)
    np.testing.assert_allclose(out[40:60, band].mean(), 0.6, atol=0.01)


@pytest.mark.parametrize("width", [4, 5, 8])
def test_a_wide_band_dead_or_noisy_is_flagged_whole(width):
    """What the flat field cannot correct -- a band reading nothing, or one whose dark noise is
    several times the panel's -- is a defect band of every width, flagged whole."""
    darks, flats, _, band = _banded_flats(100, width, 0.02)
    assert Calibration.from_frames(darks, flats).defect_columns.tolist() == band.tolist()
    darks, flats, _, band = _banded_flats(100, width, 0.88)
    rng = np.random.default_rng(7)
    noise = rng.normal(0, 8, (darks.shape[0], darks.shape[1], width))
    darks[:, :, band] = (darks[:, :, band] + noise).clip(0).astype(np.uint16)
    flats[:, :, band] = (flats[:, :, band] + noise).clip(0).astype(np.uint16)
    assert Calibration.from_frames(darks, flats).defect_columns.tolist() == band.tolist()


def test_columns_saturated_in_the_flats_are_saturation_not_defect_lines():
    """Review s42rr: a heel flat clipped at 4095 over its brightest 23 columns made them "23 defect
    lines ... check the flats (a gain step between read-out blocks ...)": advice for another fault,
    and counted against the manual's 20 defect lines. They are said with the saturation, whose
    advice is to lower the flat exposure, and still filled as lines (a mostly clipped column's few
    unclipped pixels are those whose flat read low); a real defect line among them is still one."""
    rng = np.random.default_rng(5)
    rows, cols, n = 64, 256, 10
    signal = np.broadcast_to(np.linspace(2000.0, 4120.0, cols), (rows, cols)).copy()
    darks = (100 + rng.poisson(4, (n, rows, cols))).astype(np.uint16)
    flats = (100 + rng.poisson(signal, (n, rows, cols))).clip(0, 4095).astype(np.uint16)
    flats[:, :, 60] = (100 + 0.9 * (flats[:, :, 60] - 100.0)).astype(np.uint16)  # a real one
    with pytest.warns(CalibrationWarning) as caught:
        cal = Calibration.from_frames(darks, flats)
    told = [str(w.message) for w in caught]
    assert not [m for m in told if "defect lines found" in m]
    sat = [m for m in told if "saturated" in m]
    assert len(sat) == 1 and "lower the flat exposure" in sat[0]
    # the columns clipped in most of their pixels (in 2 frames or more: clipped_floor) are named
    heavy = np.flatnonzero(((flats == 4095).sum(axis=0) >= 2).mean(axis=0) > 0.5)
    named = re.search(r"columns (\d+)-(\d+) are filled as lines for it \(saturated lines, not defect lines\)", sat[0])
    assert heavy.size > 20 and named and int(named[2]) == cols - 1 and abs(int(named[1]) - heavy[0]) <= 1
    assert cal.defect_columns.tolist() == [60, *range(int(named[1]), cols)]
    # kept apart, so that calibrate's and info's summaries name them as this warning does
    assert cal.provenance["saturated_lines"] == {"rows": [], "columns": list(range(int(named[1]), cols))}


@pytest.mark.parametrize("step", [1.15, 1.2, 0.85])
@pytest.mark.parametrize("planted", [(121,), (118, 122), (119, 122), (118, 121, 123)])
def test_a_defect_line_beside_a_gain_step_is_found(step, planted):
    """Review s42rr: a column at 0.9 one column right of a 1.15 step (the step between 119 and
    120) reads 1.035 of the lines left of the step: off the lines right of it only, as the step's
    own columns are, and it was missed. With the step fitted to its neighbours it is off the side
    it lies on; the step's own columns stay clean (test_a_gain_step_between_readout_blocks...).
    The limit: 119 at 0.9 right beside a 0.85 step reads between the two sides, as the step's edge
    would; it is not told from one."""
    darks, flats, _ = _stepped_flats(step, seed=5)
    cols = list(planted)
    flats[:, :, cols] = (100 + 0.9 * (flats[:, :, cols] - 100.0)).astype(np.uint16)
    found = [c for c in cols if not (step < 1 and c == 119)]
    assert Calibration.from_frames(darks, flats).defect_columns.tolist() == found


def _heel(rows, cols, fall, seed=2, n=8):
    """Darks and flats whose flat - dark falls smoothly by ``fall`` (a share) from the first column
    to the last, as the anode heel makes it across a panel, and that signal."""
    rng = np.random.default_rng(seed)
    signal = np.broadcast_to(np.linspace(3000.0, 3000.0 * (1 - fall), cols), (rows, cols)).copy()
    darks = (100 + rng.poisson(4, (n, rows, cols))).astype(np.uint16)
    flats = (100 + rng.poisson(signal, (n, rows, cols))).astype(np.uint16)
    return darks, flats, signal


@pytest.mark.parametrize("cols, fall", [(96, 0.65), (128, 0.7), (160, 0.5)])
@pytest.mark.parametrize("turn", ["falling", "rising", "along rows"])
def test_a_steep_smooth_heel_flags_no_edge_line(cols, fall, turn):
    """A flat falling smoothly by half or more across a few hundred pixels (a steep anode heel, or a
    small crop of one) flagged the edge line on its dim side as a defect line, and lines 4-12 from
    it: the local reference stayed flat over the outer half-block while the flat went on falling,
    so the edge's relative response ran 0.77-1 over 16 lines and the edge line, judged against the
    lines inside only, read 5 % under them. A smooth gradient is no defect."""
    darks, flats, _ = _heel(64, cols, fall)
    if turn == "rising":
        darks, flats = darks[..., ::-1], flats[..., ::-1]
    elif turn == "along rows":
        darks, flats = darks.transpose(0, 2, 1), flats.transpose(0, 2, 1)
    cal = Calibration.from_frames(darks, flats)
    assert cal.defect_columns.size == 0 and cal.defect_rows.size == 0
    assert np.count_nonzero(cal.mask) == 0


@pytest.mark.parametrize("edge", [0, -1])
@pytest.mark.parametrize(
    "gain, flag", [(0.02, PixelFlag.DEAD), (0.9, PixelFlag.UNDER_RESPONDING), (1.12, PixelFlag.OVER_RESPONDING)]
)
def test_a_dead_or_hot_edge_line_on_a_steep_heel_is_still_found(edge, gain, flag):
    """The edge lines of a heel flat are still judged: a dead, weak or hot first or last column is
    a defect line whichever side of the heel it lies on."""
    darks, flats, _ = _heel(64, 96, 0.65)
    flats[:, :, edge] = (100 + gain * (flats[:, :, edge] - 100.0)).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    assert cal.defect_columns.tolist() == [edge % 96] and cal.defect_rows.size == 0
    assert (cal.mask[:, edge] & flag).all()


@pytest.mark.parametrize("shift", [0, 4])
def test_the_unused_low_bits_are_found_without_a_copy_of_the_frames_at_8_bytes_a_pixel(shift):
    """s47: ``radiokit info`` of one 8000 x 8000 frame of MSB-aligned counts peaked at 870 MB, 7x
    the frame: ``np.bincount`` of every pixel's low byte made an int64 copy of them. Counted a block
    at a time, the temporaries are a fraction of the frames, and the bits found are the same."""
    import tracemalloc

    from radiokit.calibrate import _unused_low_bits

    frames = np.random.default_rng(5).integers(0, 4096, (2, 1024, 1024), dtype=np.uint16) << shift
    tracemalloc.start()
    try:
        bits = _unused_low_bits([frames])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert bits == shift
    assert peak < frames.nbytes, peak  # was 5x: the low bytes (1x), as uint8 (0.5x), as int64 (4x)
