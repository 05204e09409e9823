"""The saturation level (the ADC's top, at which a pixel is clipped): one rule for calibrate,
correct and info (radiokit.calibrate.saturation_level). Found by feeding radiokit other detectors'
files: 8-bit frames clipped at 255 and 10-bit ones at 1023 were never flagged (the guess knew only
4095, 16383 and 65535), info called every pixel of an MSB-aligned 12-bit TIFF saturated while
calibrate took 65520, and float frames were never counted against their calibration's level."""

import warnings

import numpy as np
import pytest
import tifffile
from conftest import info_items, run_cli

from radiokit.calibrate import Calibration, CalibrationWarning, PixelFlag, adc_top, saturation_level
from radiokit.correct import correct_frames

SHAPE = (64, 64)


def _darks(rng, n=6, level=10.0, dtype=np.uint16):
    return np.rint(level + rng.normal(0, 1.5, (n, *SHAPE))).clip(0).astype(dtype)


def _flats(rng, mean, top, n=6, spread=0.15, dtype=np.uint16):
    """Flats whose gain rises smoothly by +-``spread`` across the columns (a beam's heel), Poisson
    noise on top, clipped by an ADC at ``top``: the brightest columns pile up there."""
    gain = 1 + spread * np.linspace(-1, 1, SHAPE[1])[None, :]
    return np.minimum(rng.poisson(mean * np.broadcast_to(gain, SHAPE), (n, *SHAPE)), top).astype(dtype)


@pytest.mark.filterwarnings("ignore::radiokit.calibrate.CalibrationWarning")  # "N pixels ... saturated", then refused
def test_8_bit_flats_clipped_at_255_are_refused_as_their_12_bit_twins_are():
    """uint8 frames were judged against 4095: a flat with about half its pixels at 255 was
    accepted, while the same frames x16 as 12-bit counts were refused as saturated."""
    rng = np.random.default_rng(1)
    darks, flats = _darks(rng, dtype=np.uint8), _flats(rng, 260.0, 255, dtype=np.uint8)
    assert np.mean(flats == 255) > 0.4  # the reviewer's file: 47 %
    assert adc_top(darks, flats) == 255
    with pytest.raises(ValueError, match=r"saturated \(>= 255\)"):
        Calibration.from_frames(darks, flats)
    with pytest.raises(ValueError, match=r"saturated \(>= 4095\)"):  # the twin, as before
        Calibration.from_frames(darks.astype(np.uint16) * 16, np.minimum(flats.astype(np.uint16) * 16 + 15, 4095))


def test_an_8_bit_projection_counts_its_pixels_at_255():
    rng = np.random.default_rng(2)
    darks, flats = _darks(rng, dtype=np.uint8), _flats(rng, 150.0, 255, spread=0.05, dtype=np.uint8)
    cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 255
    frame = np.minimum(rng.poisson(120.0, SHAPE), 254).astype(np.uint8)
    frame[:10, :10] = 255  # 100 px clipped
    _, report = correct_frames(cal, frame, domain="linear", return_report=True)
    assert report.saturated.tolist() == [100]


def test_a_calibration_built_from_8_bit_arrays_saturates_at_255():
    """Calibration(dark, flat, mask) from uint8 arrays: converted to float32 before the ADC was
    judged, it guessed 4095, and a projection's pixels at 255 went uncounted."""
    rng = np.random.default_rng(4)
    dark = _darks(rng, n=1, dtype=np.uint8)[0]
    flat = _flats(rng, 150.0, 255, n=1, spread=0.05, dtype=np.uint8)[0]
    cal = Calibration(dark, flat, np.zeros(SHAPE, np.uint32))
    assert cal.thresholds.saturation == 255
    frame = np.minimum(rng.poisson(120.0, SHAPE), 254).astype(np.uint8)
    frame[:5, :8] = 255  # 40 px clipped
    _, report = correct_frames(cal, frame, domain="linear", return_report=True)
    assert report.saturated.tolist() == [40]


def test_a_10_bit_flat_clipped_at_1023_is_flagged():
    """A 10-bit camera's counts in uint16 words, most of the flat at 1023: accepted before."""
    rng = np.random.default_rng(3)
    darks, flats = _darks(rng), _flats(rng, 1200.0, 1023, spread=0.05)
    assert np.mean(flats == 1023) > 0.4
    assert adc_top(darks, flats) == 1023
    with pytest.raises(ValueError, match=r"saturated \(>= 1023\)"):
        Calibration.from_frames(darks, flats)
    # the brightest columns clipped in a few per cent of the values: calibrated at 1023, and a
    # projection's pixels there counted (at 960 counts, 11 % of the pixels clipped in 2 or more of
    # their 6 frames, and a flat so clipped is refused since review s42 judges every frame)
    flats = _flats(rng, 940.0, 1023, spread=0.05)
    assert 0.01 < np.mean(flats == 1023) < 0.1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)  # a few clipped in every flat: flagged
        cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 1023
    frame = np.minimum(rng.poisson(800.0, SHAPE), 1000).astype(np.uint16)
    frame[:10, :10] = 1023
    _, report = correct_frames(cal, frame, domain="linear", return_report=True)
    assert report.saturated.tolist() == [100]
    # review s40rr2: clipped in 0.15 % of the flats' values, a pile-up all the same; judged against
    # the darks' pixels too (as many frames), it fell under the 0.1 % share and went unflagged
    flats = _flats(rng, 600.0, 1023, spread=0.05)
    flats[:, :1, :6] = 1023
    assert 0.001 < np.mean(flats == 1023) < 0.002
    assert adc_top(flats) == 1023 and adc_top(darks, flats) == 1023


@pytest.mark.parametrize("mean, spread", [(600.0, 0.05), (900.0, 0.05), (960.0, 0.02)])
def test_a_12_bit_panels_dim_flat_under_1023_is_not_called_saturated(mean, spread):
    """The false flag the 1023 rule must not give: a 12-bit panel's flat at a low current whose
    brightest pixels reach 1023 or just under it, a tail thinning out (or, with little spread, a
    dense peak just under the top), not a pile-up. Its top stays 4095, as it was."""
    rng = np.random.default_rng(4)
    darks = _darks(rng)
    flats = _flats(rng, mean, 4095, spread=spread)
    keep = flats <= 1023
    flats = np.where(keep, flats, 1023 - rng.integers(0, 40, flats.shape)).astype(np.uint16)  # the tail below
    flats[0, 5, 5:8] = 1023  # and a few values at exactly 1023, as a tail gives
    assert flats.max() == 1023
    assert adc_top(darks, flats) == 4095
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 4095
    assert not np.any(cal.mask & PixelFlag.OVER_RESPONDING & (cal.flat >= 1000))


def test_twelve_bit_frames_under_4095_keep_4095():
    """The C7942's path (the demo's numbers): LSB-aligned uint16 counts under 4095 are 12-bit."""
    rng = np.random.default_rng(5)
    darks, flats = _darks(rng, level=150.0), _flats(rng, 3000.0, 4095, spread=0.05)
    assert flats.max() < 4095 and adc_top(darks, flats) == 4095
    assert saturation_level(darks, flats, bit_depth=12) == 4095
    assert saturation_level(darks, flats, bit_depth=14) == 16383  # what a file declares, first


def test_a_declared_depth_the_frames_pass_is_judged_as_undeclared():
    """12-bit counts MSB-aligned in a file saying 12 bits: its top is 65520, not 4095."""
    rng = np.random.default_rng(6)
    darks, flats = _darks(rng, level=150.0) << 4, _flats(rng, 3000.0, 4095, spread=0.05) << 4
    assert saturation_level(darks, flats, bit_depth=12) == 65520


def _msb_tiff(path, frames):
    """12-bit counts in the high bits of 16-bit words, the file declaring BitsPerSample 12 (as
    some frame grabbers' software writes them)."""
    tifffile.imwrite(path, frames, photometric="minisblack")
    with tifffile.TiffFile(path, mode="r+") as tif:
        for page in tif.pages:
            page.tags["BitsPerSample"].overwrite(12)


def test_info_calibrate_and_correct_agree_on_an_msb_aligned_12_bit_tiff(tmp_path):
    """info called every pixel of such a file saturated (against the declared 4095), while
    calibrate and correct took 65520 and counted the clipped ones."""
    rng = np.random.default_rng(7)
    darks = _darks(rng, n=4, level=150.0) << 4
    flats = _flats(rng, 3000.0, 4095, n=4, spread=0.05) << 4
    frames = (np.minimum(rng.poisson(2000.0, (3, *SHAPE)), 4000) << 4).astype(np.uint16)
    frames[:, :10, :10] = 65520  # 100 px a frame clipped
    for name, data in (("d.tif", darks), ("f.tif", flats), ("fr.tif", frames)):
        _msb_tiff(tmp_path / name, data)
    res = run_cli("info", tmp_path / "fr.tif")
    assert res.returncode == 0, res.stderr
    assert "saturated  300 pixel(s)" in info_items(res.stdout), res.stdout
    res = run_cli("calibrate", "--dark", tmp_path / "d.tif", "--flat", tmp_path / "f.tif", "-o", tmp_path / "c.h5")
    assert res.returncode == 0, res.stderr
    assert Calibration.load(tmp_path / "c.h5").thresholds.saturation == 65520
    res = run_cli("correct", tmp_path / "fr.tif", "--cal", tmp_path / "c.h5", "-o", tmp_path / "o.h5")
    assert res.returncode == 0, res.stderr
    assert "300 saturated" in res.stdout + res.stderr, res.stdout + res.stderr


def test_info_counts_an_8_bit_files_pixels_at_255(tmp_path):
    rng = np.random.default_rng(8)
    frames = np.minimum(rng.poisson(120.0, (2, *SHAPE)), 254).astype(np.uint8)
    frames[:, :10, :10] = 255
    tifffile.imwrite(tmp_path / "u8.tif", frames)
    res = run_cli("info", tmp_path / "u8.tif")
    assert res.returncode == 0, res.stderr
    assert "saturated  200 pixel(s) >= 255" in info_items(res.stdout), res.stdout


def test_float_frames_are_counted_against_their_calibrations_level():
    """A float32 twin of a uint16 projection reported 0 saturated, the calibration's 4095 unused."""
    rng = np.random.default_rng(9)
    cal = Calibration.from_frames(_darks(rng, level=150.0), _flats(rng, 3000.0, 4095, spread=0.05))
    assert cal.thresholds.saturation == 4095
    frame = np.minimum(150 + rng.poisson(2000.0, SHAPE), 4000).astype(np.uint16)
    frame[:10, :10] = 4095
    counts = []
    for raw in (frame, frame.astype(np.float32), frame.astype(np.float64)):
        _, report = correct_frames(cal, raw, domain="linear", return_report=True)
        counts.append(report.saturated.tolist())
    assert counts == [[100]] * 3
    holes = frame.astype(np.float32)
    holes[20, :5], holes[21, :5] = np.inf, np.nan  # no values: counted as NaN or inf, not saturated
    _, report = correct_frames(cal, holes, domain="linear", return_report=True)
    assert report.saturated.tolist() == [100]


@pytest.mark.filterwarnings("ignore::radiokit.io.BitDepthWarning")  # values above 4095: read() says MSB-aligned
def test_an_experiment_file_declaring_12_bits_over_msb_aligned_counts_is_judged_as_a_tiff_is(tmp_path):
    """from_experiment forced the recorded depth's 4095 whatever the frames held, so MSB-aligned
    12-bit counts were refused as darks "over half the ADC's range" and flats saturated in every
    pixel, while the same frames in TIFFs declaring 12 bits calibrated at 65520."""
    from radiokit.io import ExperimentWriter, ImageKey

    rng = np.random.default_rng(10)
    darks = _darks(rng, n=4, level=150.0) << 4
    flats = _flats(rng, 3000.0, 4095, n=4, spread=0.05) << 4
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=SHAPE, pixel_size_mm=0.05, bit_depth=12) as w:
        for frame in darks:
            w.append(frame, image_key=ImageKey.DARK)
        for frame in flats:
            w.append(frame, image_key=ImageKey.FLAT)
    assert Calibration.from_experiment(path).thresholds.saturation == 65520


@pytest.mark.filterwarnings("ignore::radiokit.calibrate.CalibrationWarning")  # "N pixels ... saturated", then refused
@pytest.mark.parametrize("bits", [10, 12])
def test_msb_aligned_flats_clipped_nearly_everywhere_are_refused(bits):
    """Found while writing the rule: flats clipped in nearly every pixel, stored in the high bits of
    16 (``counts << (16 - bits)``), hold 2 levels and quiet darks (2 counts rms, the C7942's) a
    dozen, under the 32 the unused-low-bits test wanted before believing them: the top stayed
    65535, the flats at 65520 (65472) were never saturated, and the calibration was accepted."""
    rng = np.random.default_rng(11)
    top = (1 << bits) - 1
    shift = 16 - bits
    darks = np.rint(60 + rng.normal(0, 2, (6, *SHAPE))).astype(np.uint16)
    flats = _flats(rng, 1.3 * top, top, spread=0.05)
    assert np.mean(flats == top) > 0.99 and np.unique(np.concatenate([darks, flats])).size < 32
    assert adc_top(darks << shift, flats << shift) == top << shift
    with pytest.raises(ValueError, match=rf"saturated \(>= {top << shift}\)"):
        Calibration.from_frames(darks << shift, flats << shift)


def _negatively_scaled_calibration(rng):
    """A calibration of a negatively scaled panel's values (value = 50 - stored / 100): its
    saturation level is not known (``Calibration.from_frames`` warns, s47)."""
    scaling = {"scale": -0.01, "offset": 50.0, "stored": np.dtype(np.uint16), "text": "stored * -0.01 + 50"}
    darks = (50 - rng.normal(4000, 3, (4, *SHAPE)).astype(np.uint16) / 100).astype(np.float32)
    flats = (50 - rng.normal(1000, 30, (4, *SHAPE)).astype(np.uint16) / 100).astype(np.float32)
    with pytest.warns(CalibrationWarning, match="saturation not checked"):
        cal = Calibration.from_frames(darks, flats, scaling=scaling)
    assert cal.thresholds.saturation is None
    # its flats' saturated pixels were not counted either: none said, not 0 (s47 review)
    assert cal.provenance["n_flat_saturated"] is None and "saturation_not_checked" in cal.provenance
    return cal


def test_frames_whose_saturation_was_not_checked_are_said_so_per_frame_not_counted_zero(tmp_path):
    """s47 review: the calibration of a negatively scaled panel holds no saturation level, so no
    frame is checked; correct's HDF5 output still wrote saturated = 0 for every frame, as for a
    frame checked and found clean. Now -1 there, the column's ``missing_value`` (as CF readers,
    xarray, mask it), with a description; the report of correct_frames says so too."""
    from radiokit.correct import correct_files
    from radiokit.io import read_stack

    rng = np.random.default_rng(8)
    cal = _negatively_scaled_calibration(rng)
    raw = np.full((2, *SHAPE), 30.0, np.float32)
    _, report = correct_frames(cal, raw, domain="linear", return_report=True, check=False)
    assert report.saturated.tolist() == [-1, -1]
    assert "saturation not checked in 2 of 2 frame(s)" in report.summary() and "saturated" not in report.summary()
    source = tmp_path / "p.tif"
    tifffile.imwrite(source, raw, photometric="minisblack")
    out = tmp_path / "out.h5"
    summary = correct_files([source], cal, out, domain="linear", progress=False)
    assert summary["saturated"] == "unknown", summary
    stack = read_stack(out)
    assert stack.series["saturated"].tolist() == [-1, -1]
    import h5py

    with h5py.File(out) as h5:
        attrs = dict(h5["entry/data/saturated"].attrs)
    assert attrs["missing_value"] == -1 and "not checked" in attrs["description"], attrs


def test_a_frame_above_every_adcs_top_is_not_checked_the_others_are_counted(tmp_path):
    """A 32-bit frame holding values above 65535 has no ADC top to count against
    (frame_saturation gives None): that frame is said unchecked (-1), not "0 saturated", while a
    frame of the same run within the calibration's 4095 is counted."""
    rng = np.random.default_rng(9)
    darks, flats = _darks(rng, dtype=np.uint32), _flats(rng, 2000.0, 4095, spread=0.05, dtype=np.uint32)
    cal = Calibration.from_frames(darks, flats)
    assert cal.thresholds.saturation == 4095
    frames = np.full((2, *SHAPE), 1500, np.uint32)
    frames[0, :3, :3] = 4095  # 9 px at the 12-bit top
    frames[1, :2, :2] = 70000  # no 12- or 16-bit ADC gives this
    _, report = correct_frames(cal, frames, domain="linear", return_report=True, check=False)
    assert report.saturated.tolist() == [9, -1]
    assert "9 saturated" in report.summary() and "not checked in 1 of 2" in report.summary()
    from radiokit.correct import correct_files
    from radiokit.io import read_stack

    tifffile.imwrite(tmp_path / "p.tif", frames, photometric="minisblack")
    summary = correct_files([tmp_path / "p.tif"], cal, tmp_path / "out.h5", domain="linear", progress=False)
    assert summary["saturated"] == 9 and "not checked in 1 of 2" in summary["saturation_from"], summary
    assert read_stack(tmp_path / "out.h5").series["saturated"].tolist() == [9, -1]
