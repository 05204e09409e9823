"""Correction against hand-computed values, and the guarantees: finite, flagged, counted."""

import json
import os
import subprocess
import sys
import warnings

import h5py
import numpy as np
import pytest
import tifffile
from conftest import run_cli

from radiokit.calibrate import Calibration, PixelFlag
from radiokit.correct import correct_frames


def _cal(rows=6, cols=7, dark=100.0, flat=1100.0, mask=None, **kw):
    d = np.full((rows, cols), dark, np.float32)
    f = np.full((rows, cols), flat, np.float32)
    m = np.zeros((rows, cols), np.uint32) if mask is None else mask
    return Calibration(d, f, m, **kw)


@pytest.mark.parametrize(
    "domain, expected",
    [
        ("linear", 0.5),  # (600 - 100) / (1100 - 100)
        ("log", np.log(2.0)),  # -ln(0.5)
        ("counts", 500.0),  # c * 0.5 with c = mean(flat - dark) = 1000
    ],
)
def test_hand_values(domain, expected):
    cal = _cal()
    raw = np.full(cal.shape, 600, np.uint16)
    out = correct_frames(cal, raw, domain=domain)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, expected, rtol=1e-6)


def test_matches_float64_reference_on_random_panel():
    rng = np.random.default_rng(3)
    shape = (101, 67)  # not a multiple of the block size
    dark = rng.uniform(80, 120, shape).astype(np.float32)
    flat = dark + rng.uniform(2000, 3000, shape).astype(np.float32)
    cal = Calibration(dark, flat, np.zeros(shape, np.uint32))
    raw = (dark + rng.uniform(50, 1900, shape)).astype(np.uint16)
    ref = -np.log((raw - dark.astype(np.float64)) / (flat - dark.astype(np.float64)))
    np.testing.assert_allclose(correct_frames(cal, raw, domain="log"), ref, atol=2e-6, rtol=1e-5)
    ref_lin = (raw - dark.astype(np.float64)) / (flat - dark)
    np.testing.assert_allclose(correct_frames(cal, raw, domain="linear"), ref_lin, rtol=1e-6)


def test_flat_equal_dark_is_filled_and_flagged():
    flat = np.full((5, 5), 1100.0, np.float32)
    flat[2, 2] = 100.0  # no response at all
    cal = Calibration(np.full((5, 5), 100.0, np.float32), flat, np.zeros((5, 5), np.uint32))
    assert cal.mask[2, 2] & PixelFlag.DEAD
    raw = np.full((5, 5), 600, np.uint16)
    raw[1, 1:4] = 350  # neighbours above: transmission 0.25
    out = correct_frames(cal, raw, domain="linear")
    # The 8 neighbours of (2, 2): three at 0.25, five at 0.5.
    assert out[2, 2] == pytest.approx((3 * 0.25 + 5 * 0.5) / 8, rel=1e-6)
    assert np.isfinite(out).all()


def test_raw_below_dark_is_filled_flagged_and_counted():
    cal = _cal()
    raw = np.full(cal.shape, 600, np.uint16)
    raw[3, 3] = 50  # below the dark of 100
    out, report = correct_frames(cal, raw, domain="log", return_report=True)
    assert np.isfinite(out).all()
    assert out[3, 3] == pytest.approx(np.log(2.0), rel=1e-6)
    assert report.nonpositive.tolist() == [1]
    assert report.flags[3, 3] & PixelFlag.NONPOSITIVE
    assert np.count_nonzero(report.flags & PixelFlag.NONPOSITIVE) == 1


def test_all_dark_frame_stays_finite():
    cal = _cal()
    raw = np.zeros(cal.shape, np.uint16)  # no signal: refused unless check=False, the repair tested here
    out, report = correct_frames(cal, raw, domain="log", return_report=True, check=False)
    assert np.isfinite(out).all()
    # No valid neighbour anywhere: clamped at half a count, i.e. -ln(0.5 / 1000).
    np.testing.assert_allclose(out, -np.log(0.5 / 1000.0), rtol=1e-6)
    assert report.nonpositive[0] == raw.size


def test_saturated_pixels_flagged_and_counted():
    cal = _cal()
    raw = np.full(cal.shape, 600, np.uint16)
    raw[0, :3] = 4095
    out, report = correct_frames(cal, raw, domain="linear", return_report=True)
    assert report.saturated.tolist() == [3]
    assert (report.flags[0, :3] & PixelFlag.SATURATED).all()
    assert out[0, 0] == pytest.approx((4095 - 100) / 1000)


def test_a_stuck_pixel_masked_and_filled_is_not_counted_saturated():
    """Review s42 (t9_stuck.py): 5 pixels stuck at 4095 in the darks, flats and frames are masked
    and filled from their neighbours in every frame, yet were counted "saturated" in every frame's
    report too: 15 over 3 frames where no value was clipped. Only unmasked pixels count."""
    mask = np.zeros((6, 7), np.uint32)
    mask[2, 1:4] = PixelFlag.OVER_RESPONDING
    cal = _cal(mask=mask)
    raw = np.full((3, *cal.shape), 600, np.uint16)
    raw[:, 2, 1:4] = 4095  # stuck, masked
    raw[1, 4, 5] = 4095  # clipped, a measurement
    out, report = correct_frames(cal, raw, domain="linear", return_report=True)
    assert report.saturated.tolist() == [0, 1, 0]
    assert not (report.flags[:, 2, 1:4] & PixelFlag.SATURATED).any()
    assert report.flags[1, 4, 5] & PixelFlag.SATURATED
    np.testing.assert_allclose(out[:, 2, 1:4], 0.5, rtol=1e-6)  # filled from the 0.5 around


def test_defect_column_is_mean_of_neighbours():
    mask = np.zeros((4, 9), np.uint32)
    mask[:, 4] = PixelFlag.DEAD | PixelFlag.CLUSTER
    cal = _cal(4, 9, mask=mask, defect_columns=[4])
    raw = (100 + 100 * np.arange(9)[None, :] + 10 * np.arange(4)[:, None]).astype(np.uint16)
    raw = np.broadcast_to(raw, (4, 9)).copy()
    raw[:, 4] = 4000  # garbage in the defect column
    out = correct_frames(cal, raw, domain="linear")
    np.testing.assert_allclose(out[:, 4], (out[:, 3] + out[:, 5]) / 2, rtol=1e-6)


def test_adjacent_defect_columns_interpolate_linearly():
    mask = np.zeros((3, 10), np.uint32)
    mask[:, [4, 5]] = PixelFlag.DEAD
    cal = _cal(3, 10, mask=mask, defect_columns=[4, 5])
    raw = np.tile((100 + 90 * np.arange(10)).astype(np.uint16), (3, 1))
    out = correct_frames(cal, raw, domain="linear")
    # columns 3 and 6 are valid; 4 and 5 lie a third and two thirds of the way between them.
    np.testing.assert_allclose(out[:, 4], out[:, 3] + (out[:, 6] - out[:, 3]) / 3, rtol=1e-6)
    np.testing.assert_allclose(out[:, 5], out[:, 3] + 2 * (out[:, 6] - out[:, 3]) / 3, rtol=1e-6)


def test_defect_row_and_edge_column():
    mask = np.zeros((6, 6), np.uint32)
    mask[2, :] = PixelFlag.UNDER_RESPONDING
    mask[:, 0] = PixelFlag.DEAD
    cal = _cal(6, 6, mask=mask, defect_rows=[2], defect_columns=[0])
    raw = (100 + 100 * np.arange(6)[:, None] + 5 * np.arange(6)[None, :]).astype(np.uint16)
    out = correct_frames(cal, raw, domain="linear")
    np.testing.assert_allclose(out[:, 0], out[:, 1], rtol=1e-6)  # edge: copied from the one side
    np.testing.assert_allclose(out[2, 1:], (out[1, 1:] + out[3, 1:]) / 2, rtol=1e-6)


def test_stack_equals_frames_and_out_is_used():
    rng = np.random.default_rng(0)
    cal = _cal(40, 33)
    stack = rng.integers(0, 4096, (3, 40, 33)).astype(np.uint16)  # twice the flats: check=False corrects them
    out = np.empty(stack.shape, np.float32)
    got, report = correct_frames(cal, stack, domain="log", out=out, return_report=True, check=False)
    assert got is out
    for i in range(3):
        np.testing.assert_array_equal(got[i], correct_frames(cal, stack[i], domain="log", check=False))
    assert np.isfinite(got).all()
    assert report.flags.shape == stack.shape
    assert report.saturated.tolist() == [int(np.count_nonzero(s >= 4095)) for s in stack]


def test_input_is_not_modified():
    cal = _cal()
    raw = np.full(cal.shape, 50, np.uint16)  # below the dark: every pixel clamped and filled
    before = raw.copy()
    correct_frames(cal, raw, check=False)
    np.testing.assert_array_equal(raw, before)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((3, 3), np.uint16), "do not match"),
        (np.full((6, 7), np.nan, np.float32), "NaN"),
        (np.zeros((6, 7), bool).astype(object), "numeric"),
    ],
)
def test_bad_input_raises_valueerror(bad, match):
    with pytest.raises(ValueError, match=match):
        correct_frames(_cal(), bad)


def test_unknown_domain():
    with pytest.raises(ValueError, match="domain"):
        correct_frames(_cal(), np.zeros((6, 7), np.uint16), domain="ln")


def test_correct_files_streams_and_a_write_failure_surfaces(tmp_path, monkeypatch):
    from radiokit.correct import correct_files
    from radiokit.io import StackWriter, read

    cal = _cal(16, 24)
    rng = np.random.default_rng(1)
    stack = rng.integers(300, 1000, (7, 16, 24)).astype("<u2")
    stack.tofile(tmp_path / "s.raw")
    summary = correct_files(tmp_path / "s.raw", cal, tmp_path / "out.h5", shape=(16, 24), progress=False)
    assert summary["frames"] == 7
    got = read(tmp_path / "out.h5", dataset="entry/data/data").data
    np.testing.assert_array_equal(got, correct_frames(cal, stack))

    calls = {"n": 0}
    real_append = StackWriter.append

    def failing_append(self, frame, **series):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(28, "No space left on device")
        return real_append(self, frame, **series)

    monkeypatch.setattr(StackWriter, "append", failing_append)  # a fake: a full disk cannot be caused here
    with pytest.raises(OSError, match="(?i)no space left"):
        correct_files(tmp_path / "s.raw", cal, tmp_path / "out2.h5", shape=(16, 24), progress=False)
    # the partial output was removed, temporary file included: nothing that looks complete
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.h5", "s.raw"]


@pytest.mark.parametrize("threads", ["1", "2"])
@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.int32, np.float32])
@pytest.mark.parametrize("domain", ["log", "linear", "counts"])
def test_scattered_repairs_match_a_whole_frame_reference(dtype, domain, threads, monkeypatch):
    """The compiled loop counts below-dark and saturated pixels per row and records where they
    are only in rows that hold some (64-column chunks), and the repairs work on those index
    lists: it must find exactly the pixels a whole-frame mask finds, on chunk edges and at the
    rows where the threads' ranges meet, and leave every other pixel as the float64 formula has
    it (float32 rounding)."""
    monkeypatch.setenv("RADIOKIT_THREADS", threads)
    rng = np.random.default_rng(11)
    shape = (300, 257)
    dark = rng.uniform(90, 110, shape).astype(np.float32)
    flat = dark + rng.uniform(2000, 3000, shape).astype(np.float32)
    cal = Calibration(dark, flat, np.zeros(shape, np.uint32))
    raw = np.rint(dark + rng.uniform(50, 1900, shape)).astype(np.float64)
    idx = rng.choice(raw.size, 160, replace=False)
    raw.ravel()[idx[:60]] = np.floor(dark.ravel()[idx[:60]]) - rng.integers(0, 20, 60)  # at or below the dark
    raw.ravel()[idx[60:100]] = 4095  # saturated
    raw[:, 200] = 0  # a whole column below the dark
    for r in (0, 15, 16, 127, 128, 287, 288, 299):  # band and block edges, the last (short) band
        raw[r, 3 + r % 50] = 0
    raw[16:32, 150] = 0  # a whole band of one column
    raw = raw.astype(dtype)
    out, report = correct_frames(cal, raw, domain=domain, return_report=True)
    assert np.isfinite(out).all()
    below = raw.astype(np.float64) - dark <= 0
    assert report.nonpositive.tolist() == [int(below.sum())]
    np.testing.assert_array_equal((report.flags & PixelFlag.NONPOSITIVE) != 0, below)
    if dtype != np.float32:  # saturation is counted for integer frames
        np.testing.assert_array_equal((report.flags & PixelFlag.SATURATED) != 0, raw >= 4095)
    ratio = (raw - dark.astype(np.float64)) / (flat - dark.astype(np.float64))
    ref = {"log": -np.log(np.where(below, 1, ratio)), "linear": ratio, "counts": cal.c * ratio}[domain]
    np.testing.assert_allclose(out[~below], ref[~below], rtol=2e-6, atol=2e-6)
    # the same frame without a report: the same image
    np.testing.assert_array_equal(correct_frames(cal, raw, domain=domain), out)


def test_the_kernel_is_cached_per_calibration_and_dropped_with_it():
    """Calibration is plain data: the kernel lives in radiokit.correct, one per live calibration,
    rebuilt when an array is replaced, gone when the calibration is."""
    import gc
    import pickle

    from radiokit.correct import _KERNELS, CorrectionKernel

    cal = _cal(20, 30)
    k = CorrectionKernel.of(cal)
    assert CorrectionKernel.of(cal) is k
    assert not hasattr(cal, "_kernel") and not hasattr(cal, "correct")
    assert "_kernel" not in pickle.dumps(cal).decode("latin-1")
    raw = np.full(cal.shape, 600, np.uint16)
    before = correct_frames(cal, raw, domain="linear")
    cal.flat = np.full(cal.shape, 2100.0, np.float32)  # a new array: a new kernel, a new result
    assert CorrectionKernel.of(cal) is not k
    np.testing.assert_allclose(correct_frames(cal, raw, domain="linear"), 0.25, rtol=1e-6)
    np.testing.assert_allclose(before, 0.5, rtol=1e-6)
    key = id(cal)
    del cal
    gc.collect()
    assert key not in _KERNELS


def test_one_pool_per_thread_budget(monkeypatch):
    """Correction and registration share one pool; a changed budget gets its own pool and the
    old one keeps working (a loop may still be using it)."""
    from radiokit._threads import pool

    monkeypatch.setenv("RADIOKIT_THREADS", "2")
    two = pool()
    assert pool() is two and two._max_workers == 2
    monkeypatch.setenv("RADIOKIT_THREADS", "1")
    one = pool()
    assert one is not two and one._max_workers == 1
    assert list(two.map(abs, [-1, -2])) == [1, 2]


@pytest.mark.parametrize("domain", ["log", "linear"])
def test_fills_near_the_thread_edge_equal_one_thread(domain, monkeypatch):
    """Each thread fills the defects whose neighbourhood lies in its rows, the rest are filled
    after the threads: the image must be exactly the one-thread image, defect lines, clusters and
    isolated pixels on either side of the edge (row 128 for 300 rows on two threads) included."""
    rng = np.random.default_rng(5)
    shape = (300, 90)
    dark = rng.uniform(90, 110, shape).astype(np.float32)
    flat = dark + rng.uniform(2000, 3000, shape).astype(np.float32)
    mask = np.zeros(shape, np.uint32)
    for r, c in [(127, 10), (128, 11), (126, 40), (129, 40), (130, 60), (5, 5), (299, 89)]:
        mask[r, c] = PixelFlag.DEAD
    mask[120:136, 70:74] = PixelFlag.DEAD  # a cluster across the edge
    mask[128, :] |= np.uint32(PixelFlag.CLUSTER)
    mask[:, 30] |= np.uint32(PixelFlag.CLUSTER)
    cal = Calibration(dark, flat, mask, defect_rows=[128], defect_columns=[30])
    raw = np.rint(dark + rng.uniform(50, 1900, shape)).astype(np.uint16)
    raw[[127, 129, 131], [12, 41, 61]] = 0  # below the dark beside the defects
    monkeypatch.setenv("RADIOKIT_THREADS", "1")
    one = correct_frames(cal, raw, domain=domain)
    monkeypatch.setenv("RADIOKIT_THREADS", "2")
    two = correct_frames(cal, raw, domain=domain)
    assert np.isfinite(one).all()
    np.testing.assert_array_equal(two, one)


def test_the_compiled_log_is_within_an_ulp_or_two_of_float64():
    """radiokit._correct_loop._ln is Cephes' logf (a polynomial, so that the loop vectorises):
    over every binade of positive normal float32, it must round like a correct log to 2 ulp."""
    import numba

    from radiokit._correct_loop import _ln

    rng = np.random.default_rng(5)
    x = np.concatenate(
        [
            np.ldexp(rng.uniform(1, 2, 200_000), rng.integers(-126, 128, 200_000)),
            rng.uniform(0.5, 2, 100_000),  # around 1, where ln is small and relative error shows
            [np.finfo(np.float32).tiny, np.finfo(np.float32).max, 1.0, 2.0, 0.5, np.sqrt(0.5), np.sqrt(2)],
        ]
    ).astype(np.float32)
    got = numba.njit(lambda a: np.array([_ln(v) for v in a], dtype=np.float32))(x)
    exact = np.log(x.astype(np.float64))
    ulp = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(got - exact) / ulp) <= 2.0


@pytest.mark.parametrize("threads", ["1", "2"])
def test_more_repairs_than_the_loop_records_are_all_found(threads, monkeypatch):
    """A thread records up to radiokit.correct._ROOM indices per frame, then searches its rows
    again: a frame with more below-dark and saturated pixels than that must be repaired alike."""
    from radiokit.correct import _ROOM

    monkeypatch.setenv("RADIOKIT_THREADS", threads)
    rng = np.random.default_rng(12)
    shape = (200, 160)
    cal = _cal(*shape)
    raw = rng.integers(150, 1000, shape).astype(np.uint16)
    below = rng.random(shape) < 0.3
    raw[below] = 100 - rng.integers(0, 50, int(below.sum()))
    saturated = ~below & (rng.random(shape) < 0.3)
    raw[saturated] = 4095
    assert below.sum() > _ROOM and saturated.sum() > _ROOM
    out, report = correct_frames(cal, raw, domain="log", return_report=True)
    assert np.isfinite(out).all()
    np.testing.assert_array_equal((report.flags & PixelFlag.NONPOSITIVE) != 0, below)
    np.testing.assert_array_equal((report.flags & PixelFlag.SATURATED) != 0, saturated)
    assert report.nonpositive.tolist() == [int(below.sum())]


@pytest.mark.parametrize(
    "dtype", [np.dtype(">u2"), np.dtype(">f4"), np.dtype(np.float16), np.dtype(np.float64), np.dtype(np.uint8)]
)
def test_byte_order_and_unusual_dtypes_give_the_native_result(dtype):
    """The compiled loop takes native, contiguous arrays: big-endian frames (raw files and some
    TIFFs), half floats and strided views are converted first and must give the same image."""
    rng = np.random.default_rng(13)
    cal = _cal(40, 30, dark=10.0, flat=250.0)
    values = rng.integers(0, 250, cal.shape)  # some at or below the dark
    ref, ref_report = correct_frames(cal, values.astype(np.float32), domain="log", return_report=True)
    raw = values.astype(dtype)
    out, report = correct_frames(cal, raw, domain="log", return_report=True)
    np.testing.assert_array_equal(out, ref)
    assert report.nonpositive.tolist() == ref_report.nonpositive.tolist()
    wide = np.zeros((40, 60), dtype)
    wide[:, ::2] = raw
    np.testing.assert_array_equal(correct_frames(cal, wide[:, ::2], domain="log"), ref)


def test_non_finite_float_raw_is_clamped_filled_and_counted():
    cal = _cal(8, 9)
    raw = np.full(cal.shape, 600.0, np.float64)
    raw[2, 3], raw[4, 4], raw[5, 1] = np.nan, np.inf, -np.inf
    raw[6, 6] = 100.0 + 1e-300  # float32(raw) - dark is 0: non-positive
    out, report = correct_frames(cal, raw, domain="log", return_report=True)
    assert np.isfinite(out).all()
    assert report.nonpositive.tolist() == [4]
    np.testing.assert_allclose(out, np.log(2.0), rtol=1e-6)  # filled from neighbours at -ln(0.5)


def test_below_dark_fills_are_the_mean_of_the_nearest_valid_square():
    """Each below-dark pixel becomes the mean of the valid pixels (not defects, not below the
    dark) of the smallest square (radius 1, else 2) around it that has any, computed from the
    frame before any fill; checked against a direct loop over a frame with clusters, a pixel
    surrounded at radius 1, defects beside them and the frame's edges."""
    rng = np.random.default_rng(14)
    shape = (30, 40)
    mask = np.zeros(shape, np.uint32)
    mask[rng.random(shape) < 0.03] = PixelFlag.DEAD
    cal = _cal(*shape, mask=mask)
    raw = rng.integers(300, 1000, shape).astype(np.uint16)
    raw[rng.random(shape) < 0.08] = 20
    raw[10:13, 10:13] = 20  # the centre's radius-1 square holds only below-dark pixels
    raw[0, 0] = raw[29, 39] = 20
    out = correct_frames(cal, raw, domain="linear")
    unfilled = (raw.astype(np.float64) - 100.0) / 1000.0
    below = raw <= 100
    for r, c in zip(*np.nonzero(below & (mask == 0))):
        for radius in (1, 2):
            rr, cc = slice(max(0, r - radius), r + radius + 1), slice(max(0, c - radius), c + radius + 1)
            valid = ~below[rr, cc] & (mask[rr, cc] == 0)
            if valid.any():
                assert out[r, c] == pytest.approx(unfilled[rr, cc][valid].mean(), rel=1e-5), (r, c)
                break
    assert below[11, 11] and out[11, 11] == pytest.approx(
        unfilled[9:14, 9:14][~below[9:14, 9:14] & (mask[9:14, 9:14] == 0)].mean(), rel=1e-5
    )


def test_out_must_be_contiguous():
    cal = _cal()
    raw = np.full(cal.shape, 600, np.uint16)
    with pytest.raises(ValueError, match="C-contiguous"):
        correct_frames(cal, raw, out=np.empty((cal.shape[1], cal.shape[0]), np.float32).T)


@pytest.mark.parametrize("seed", range(6))
def test_nearest_fill_on_the_holes_box_takes_a_nearest_pixel_of_the_whole_frame(seed):
    """_fill_nearest works on the holes' bounding box widened by 1 px (a NaN gap's column, not the
    frame: 0.3 s -> 0.025 s a frame at 2240): each hole takes a value from a pixel as near as the
    whole frame's nearest, wherever the holes lie (edges and corners included)."""
    from scipy import ndimage

    from radiokit.correct import _fill_nearest

    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(20, 60)), int(rng.integers(20, 60)))
    holes = np.zeros(shape, bool)
    for _ in range(int(rng.integers(1, 4))):  # a few rectangles, any size, anywhere
        r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        holes[r : r + rng.integers(1, 15), c : c + rng.integers(1, 15)] = True
    # each pixel's value is its own index: what a hole took names the pixel it came from
    image = np.arange(holes.size, dtype=np.float64).reshape(shape)
    _fill_nearest(image, np.flatnonzero(holes))
    src_r, src_c = np.divmod(image[holes].astype(np.int64), shape[1])
    assert not holes[src_r, src_c].any()
    hr, hc = np.nonzero(holes)
    taken = np.hypot(src_r - hr, src_c - hc)
    nearest = ndimage.distance_transform_edt(holes)[holes]
    np.testing.assert_allclose(taken, nearest, rtol=0, atol=1e-12)
    assert np.array_equal(image[~holes], np.arange(holes.size).reshape(shape)[~holes])


@pytest.mark.parametrize("domain", ["log", "linear", "counts"])
def test_correct_files_refuses_frames_brighter_than_the_flats(tmp_path, domain):
    """Found by trying other labs' files: a 12-bit panel's projections saved MSB-aligned
    (``counts << 4``, another frame grabber setting) against darks and flats saved LSB-aligned were
    corrected to a transmission of 16, a line integral of -2.77 everywhere, exit code 0. No object
    makes a frame brighter than the open beam: as radiokit process refuses such a step, correct
    refuses the frame, naming it and how much brighter; one within the tube's drift is corrected."""
    import tifffile

    from radiokit.correct import correct_files
    from radiokit.errors import FormatError

    rng = np.random.default_rng(21)
    dark = np.full((32, 40), 100.0, np.float32)
    cal = Calibration(dark, dark + 2000, np.zeros((32, 40), np.uint32))
    frames = (100 + rng.poisson(1000, (2, 32, 40))).astype(np.uint16)
    tifffile.imwrite(tmp_path / "lsb.tif", frames, photometric="minisblack")
    tifffile.imwrite(tmp_path / "msb.tif", frames << 4, photometric="minisblack")
    bright = (100 + rng.poisson(2100, (1, 32, 40))).astype(np.uint16)  # 5 % over the flats: drift
    tifffile.imwrite(tmp_path / "drift.tif", bright, photometric="minisblack")
    correct_files(
        [tmp_path / "lsb.tif", tmp_path / "drift.tif"], cal, tmp_path / "ok.h5", domain=domain, progress=False
    )
    with pytest.raises(FormatError, match=r"msb.tif: frame 0: brighter than the flats, 8.\d+x their level"):
        correct_files(tmp_path / "msb.tif", cal, tmp_path / "out.h5", domain=domain, progress=False)
    assert not (tmp_path / "out.h5").exists()


def test_correct_frames_given_a_file_name_says_to_read_it():
    """``correct_frames(cal, "frame.tif")`` -- a newcomer's first try -- was told "raw frames of
    shape () do not match the calibration's"; the line now says that it takes arrays and how to
    read a file into one."""
    from pathlib import Path

    cal = Calibration.from_frames(np.full((3, 16, 16), 100, np.uint16), np.full((3, 16, 16), 3100, np.uint16))
    for name in ("frame.tif", Path("frame.tif")):
        with pytest.raises(ValueError, match=r"frame\.tif.*radiokit\.io\.read"):
            correct_frames(cal, name)


# -- the orientation frames are read in, against the calibration's ------------------------------
def _orientation_files(tmp_path, dark_tag=1, flat_tag=1, frame_tag=1):
    """Darks, flats and one frame file of a small panel (48 x 64, a defect column at 10) as TIFFs
    carrying TIFF Orientation tags (1: none written); the frame reads half the flats' signal."""
    import tifffile

    from sim.detector import PanelModel

    panel = PanelModel(rows=48, cols=64, defect_columns=(10,), n_dead=3, n_under=0, n_noisy=0)
    rng = np.random.default_rng(5)
    stacks = {
        "d.tif": (panel.dark_frames(6, rng), dark_tag),
        "f.tif": (panel.flat_frames(6, 2500.0, rng), flat_tag),
        "fr.tif": (panel.expose(np.full(panel.shape, np.log(2), np.float32), 2500.0, 3, rng), frame_tag),
    }
    for name, (stack, tag) in stacks.items():
        extra = [(274, 3, 1, tag, True)] if tag != 1 else []
        with tifffile.TiffWriter(tmp_path / name) as tif:
            for frame in stack:  # each page tagged: tifffile writes a stack's extratags on page 0 only
                tif.write(frame, photometric="minisblack", extratags=extra)
    return tmp_path / "d.tif", tmp_path / "f.tif", tmp_path / "fr.tif"


@pytest.mark.parametrize("tag", [3, 6])
def test_frames_read_in_another_orientation_than_the_calibration_are_refused(tmp_path, tag):
    """Found by a reviewer (session 40): frames tagged TIFF Orientation 3 (a viewer's lossless
    180-degree turn) against a calibration of untagged darks and flats exited 0; read turned, each
    frame pixel met another sensor pixel's dark and flat (the defect column at 10 filled, its
    mirror at 53 left reading 1.9 for ln 2). The calibration records the orientation its frames
    were read in, and frames read otherwise are refused in one line naming both; turned a quarter
    (Orientation 6), as a turn, not as frames of another size."""

    d, f, fr = _orientation_files(tmp_path, frame_tag=tag)
    assert run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5", "-q").returncode == 0
    assert Calibration.load(tmp_path / "cal.h5").provenance["orientation"] == 1
    res = run_cli("correct", fr, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5", "-q")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert str(fr) in res.stderr and f"Orientation {tag}" in res.stderr and "Orientation 1" in res.stderr
    assert not (tmp_path / "out.h5").exists()


def test_frames_and_calibration_read_in_one_orientation_correct_as_untagged_ones_turned(tmp_path):
    """Darks, flats and frames all tagged Orientation 3 pair the same sensor pixels as untagged
    ones: the corrected frames are the untagged files' turned by 180 degrees (float rounding
    apart), every pixel at ln 2 within the noise."""

    from radiokit.io import read

    outs = {}
    for tag in (1, 3):
        sub = tmp_path / f"or{tag}"
        sub.mkdir()
        d, f, fr = _orientation_files(sub, tag, tag, tag)
        assert run_cli("calibrate", "--dark", d, "--flat", f, "-o", sub / "cal.h5", "-q").returncode == 0
        assert Calibration.load(sub / "cal.h5").provenance["orientation"] == tag
        res = run_cli("correct", fr, "--cal", sub / "cal.h5", "-o", sub / "out.tif", "-q")
        assert res.returncode == 0, res.stderr
        outs[tag] = read(sub / "out.tif").data
    np.testing.assert_allclose(outs[3], outs[1][:, ::-1, ::-1], atol=1e-5)
    assert abs(float(np.median(outs[3])) - np.log(2)) < 0.02


def test_darks_and_flats_read_in_different_orientations_are_refused(tmp_path):
    """Untagged darks with flats tagged Orientation 3 would pair each flat pixel with another
    sensor pixel's dark: refused, naming both files' orientations."""

    d, f, _ = _orientation_files(tmp_path, flat_tag=3)
    res = run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5", "-q")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "Orientation 3" in res.stderr and "Orientation 1" in res.stderr
    assert not (tmp_path / "cal.h5").exists()


def test_a_calibration_that_does_not_record_its_orientation_still_corrects_untagged_frames(tmp_path):
    """Calibrations written before the orientation was recorded load and correct untagged frames
    as before, without a word; frames declaring another orientation cannot be paired with them
    safely (their darks and flats may have been read either way) and are refused, saying to
    make the calibration again."""
    d, f, fr = _orientation_files(tmp_path)
    assert run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5", "-q").returncode == 0
    with h5py.File(tmp_path / "cal.h5", "a") as h5:
        prov = json.loads(h5["calibration"].attrs["provenance"])
        del prov["orientation"]
        h5["calibration"].attrs["provenance"] = json.dumps(prov)
    res = run_cli("correct", fr, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5", "-q")
    assert res.returncode == 0 and res.stderr == "", res.stderr
    (tmp_path / "t").mkdir()
    _, _, turned = _orientation_files(tmp_path / "t", frame_tag=3)
    res = run_cli("correct", turned, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out3.h5", "-q")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "Orientation 3" in res.stderr and "does not record" in res.stderr


def _itex(path, stack, x0=0, y0=0):
    """An ITEX .img of ``stack`` (n, rows, cols) uint16, a sub-array at ``x0``, ``y0`` on the sensor
    (HiPic's header fields)."""
    import struct

    n, rows, cols = stack.shape
    head = struct.pack("<2sHhhhhhihhd4s30s", b"IM", 0, cols, rows, x0, y0, 2, n, 0, 0, 0.0, b"", b"")
    path.write_bytes(head + stack.astype("<u2").tobytes())
    return path


def test_frames_cut_elsewhere_from_the_sensor_than_the_calibration_are_refused(tmp_path):
    """A sub-array of the calibration's size at another place on the sensor (an ITEX file's x and
    y offsets) holds other sensor pixels: the calibration records the darks' and flats' offset,
    and frames cut elsewhere are refused in one line naming both places; frames cut where the
    darks and flats were are corrected."""
    from sim.detector import PanelModel

    panel = PanelModel(rows=40, cols=48, defect_columns=(), n_dead=0, n_under=0, n_noisy=0)
    rng = np.random.default_rng(2)
    d = _itex(tmp_path / "d.img", panel.dark_frames(5, rng), 200, 100)
    f = _itex(tmp_path / "f.img", panel.flat_frames(5, 2500.0, rng), 200, 100)
    frame = panel.expose(np.full(panel.shape, np.log(2), np.float32), 2500.0, 1, rng)
    assert run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5", "-q").returncode == 0
    assert Calibration.load(tmp_path / "cal.h5").provenance["sensor_offset"] == [200, 100]
    same = _itex(tmp_path / "same.img", frame, 200, 100)
    assert run_cli("correct", same, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "a.h5", "-q").returncode == 0
    moved = _itex(tmp_path / "moved.img", frame, 0, 100)
    res = run_cli("correct", moved, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "b.h5", "-q")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "x 0, y 100" in res.stderr and "x 200, y 100" in res.stderr
    whole = _itex(tmp_path / "whole.img", frame)
    res = run_cli("correct", whole, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "c.h5", "-q")
    assert res.returncode == 2 and "the whole sensor" in res.stderr, res.stderr
    # review s40rr2: a TIFF says nothing of a sub-array; taken for the whole sensor, the same
    # sub-array's projections exported as TIFF were refused, and TIFF darks and flats against ITEX
    # frames, and ITEX darks beside TIFF flats
    tifffile.imwrite(tmp_path / "same.tif", frame)
    assert (
        run_cli(
            "correct", tmp_path / "same.tif", "--cal", tmp_path / "cal.h5", "-o", tmp_path / "d.h5", "-q"
        ).returncode
        == 0
    )
    tifffile.imwrite(tmp_path / "f.tif", panel.flat_frames(5, 2500.0, rng))
    res = run_cli("calibrate", "--dark", d, "--flat", tmp_path / "f.tif", "-o", tmp_path / "mixed.h5", "-q")
    assert res.returncode == 0, res.stderr
    assert Calibration.load(tmp_path / "mixed.h5").provenance["sensor_offset"] == [200, 100]
    tifffile.imwrite(tmp_path / "d.tif", panel.dark_frames(5, rng))
    res = run_cli(
        "calibrate", "--dark", tmp_path / "d.tif", "--flat", tmp_path / "f.tif", "-o", tmp_path / "tif.h5", "-q"
    )
    assert res.returncode == 0 and "sensor_offset" not in Calibration.load(tmp_path / "tif.h5").provenance
    assert run_cli("correct", moved, "--cal", tmp_path / "tif.h5", "-o", tmp_path / "e.h5", "-q").returncode == 0
    # review s40rr3: but frame files of two sub-arrays against it, together, hold other pixels
    res = run_cli("correct", moved, same, "--cal", tmp_path / "tif.h5", "-o", tmp_path / "g.h5", "-q")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "same.img" in res.stderr and "x 200, y 100" in res.stderr and "x 0, y 100" in res.stderr


@pytest.mark.parametrize(
    "key, value",
    [
        ("orientation", 9),
        ("orientation", "3"),
        ("orientation", True),
        ("orientation", {}),
        ("sensor_offset", 5),
        ("sensor_offset", [1, 2, 3]),
        ("sensor_offset", [-1, 0]),
        ("sensor_offset", [0.5, 0]),
    ],
)
def test_a_calibration_recording_no_orientation_or_offset_radiokit_writes_is_refused(tmp_path, key, value):
    """A calibration file's provenance says how its darks and flats were read; a value no reader
    gives (Orientation 9, a string, an offset of three numbers) is refused on load naming the
    field, never a traceback (a dict was unhashable in the message) nor compared as another."""
    from radiokit.errors import FormatError

    d, f, _ = _orientation_files(tmp_path)
    assert run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5", "-q").returncode == 0
    with h5py.File(tmp_path / "cal.h5", "a") as h5:
        prov = json.loads(h5["calibration"].attrs["provenance"])
        prov[key] = value
        h5["calibration"].attrs["provenance"] = json.dumps(prov)
    with pytest.raises(FormatError, match=f"provenance: {key} is"):
        Calibration.load(tmp_path / "cal.h5")


# -- the API checks what the command line checks ------------------------------------------------
def _noisy_cal(shape=(64, 64)):
    """A calibration from noisy darks (100 +- 2 counts: its dark noise is recorded) and flats at
    3100, so 1600 counts are a transmission of 0.5."""
    rng = np.random.default_rng(0)
    darks = rng.normal(100, 2, (5, *shape)).astype(np.uint16)
    flats = rng.normal(3100, 30, (5, *shape)).astype(np.uint16)
    return Calibration.from_frames(darks, flats), darks


@pytest.mark.parametrize("case", ["msb_aligned", "beam_off", "already_corrected", "display_copy_8bit"])
def test_correct_frames_refuses_the_frames_radiokit_correct_refuses(case):
    """``correct_frames`` gave a median I/I0 of 8.5 for MSB-aligned counts (<< 4), 0.0005 for a
    beam-off frame and 0.0002 for a frame already corrected, with no error and no warning, where
    ``radiokit correct`` refuses each: the API runs the same checks unless told the caller did."""
    cal, darks = _noisy_cal()
    raw = np.full(cal.shape, 1600, np.uint16)  # (1600 - 100) / (3100 - 100) = 0.5
    frame = {
        "msb_aligned": (raw.astype(np.uint32) << 4).astype(np.uint16),
        "beam_off": darks[0],
        "already_corrected": correct_frames(cal, raw, domain="linear"),
        "display_copy_8bit": (raw // 16).astype(np.uint8),
    }[case]
    for domain in ("log", "linear", "counts"):
        with pytest.raises(ValueError, match="brighter than the flats|no signal above the dark") as info:
            correct_frames(cal, frame, domain=domain)
        assert "\n" not in str(info.value) and "check=False" in str(info.value)
    # a caller that checked (or means it) still gets the arithmetic
    out = correct_frames(cal, frame, domain="linear", check=False)
    if case == "msb_aligned":  # (16 * 1600 - 100) / 3000
        assert float(np.median(out)) == pytest.approx((16 * 1600 - 100) / 3000, rel=0.02)
    else:
        assert float(np.median(out)) < 0.01


def test_correct_frames_names_the_refused_frame_of_a_stack_and_checks_the_good_ones_cheaply():
    cal, darks = _noisy_cal()
    raw = np.full(cal.shape, 1600, np.uint16)
    stack = np.stack([raw, darks[1], raw])
    with pytest.raises(ValueError, match=r"^frame 1 of 3: no signal above the dark"):
        correct_frames(cal, stack, domain="linear")
    np.testing.assert_allclose(correct_frames(cal, stack[[0, 2]], domain="linear"), 0.5, atol=0.02)


def test_correct_frames_refuses_an_out_that_is_no_array():
    cal = _cal()
    with pytest.raises(TypeError, match="out must be a numpy array"):
        correct_frames(cal, np.full(cal.shape, 600, np.uint16), out=[0])


def test_correct_frames_refuses_a_masked_array():
    """np.asarray drops a masked array's mask: its masked pixels were corrected as counts."""
    cal = _cal()
    raw = np.ma.masked_array(np.full(cal.shape, 600.0), mask=np.eye(*cal.shape, dtype=bool))
    with pytest.raises(ValueError, match="raw is a masked array, whose mask would be ignored: pass .*filled"):
        correct_frames(cal, raw)


def test_values_above_the_declared_adc_top_are_warned_of_with_their_count(tmp_path):
    """Review s42: a pixel above 4095 in a frame of a panel declared 12-bit (C7942.md: such a value
    means a wrong bit or byte order, or another panel, and is to be reported) was taken as data,
    L = -1.90, in silence where no reader had said so (an array, a 16-bit TIFF). The calibration
    keeps the depth its frames declared, and a correction names how many pixels passed it; a
    depth only guessed from the frames (a 16-bit panel whose flats stayed under 4095) says nothing."""
    from radiokit.io import BitDepthWarning

    rng = np.random.default_rng(8)
    darks = (100 + rng.poisson(4, (4, 64, 64))).astype(np.uint16)
    flats = (100 + rng.poisson(3000, (4, 64, 64))).astype(np.uint16)
    raw = (100 + rng.poisson(1500, (2, 64, 64))).astype(np.uint16)
    raw[1, 5, 5], raw[1, 9, 9] = 20000, 4096
    cal = Calibration.from_frames(darks, flats, bit_depth=12)
    cal.save(tmp_path / "cal.h5")
    cal = Calibration.load(tmp_path / "cal.h5")
    with pytest.warns(BitDepthWarning, match=r"2 pixels .*above 4095.*12-bit") as caught:
        correct_frames(cal, raw)
    assert len(caught) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", BitDepthWarning)
        correct_frames(Calibration.from_frames(darks, flats), raw)  # 12 bits guessed: a 16-bit panel's
        correct_frames(cal, raw[0])


def test_a_raw_frame_above_4095_read_with_the_c7942_preset_is_counted_on_the_command_line(tmp_path):
    """The command line of review s42's finding: darks, flats and a frame in raw files of the 12-bit
    C7942 (``--preset c7942-4x4``, 560 x 560); one pixel of the frame at 20000 was corrected to
    L = -1.90 and `correct` printed "0 saturated", exit 0. The preset names the ADC as an ITEX
    header does, the calibration keeps it, and `correct` says how many pixels passed its top."""
    rng = np.random.default_rng(9)
    shape = (3, 560, 560)
    paths = {name: tmp_path / f"{name}.raw" for name in ("darks", "flats", "frame")}
    (100 + rng.poisson(4, shape)).astype("<u2").tofile(paths["darks"])
    (100 + rng.poisson(3000, shape)).astype("<u2").tofile(paths["flats"])
    frame = (100 + rng.poisson(1500, shape[1:])).astype("<u2")
    frame[100, 100] = 20000
    frame.tofile(paths["frame"])
    preset = ("--preset", "c7942-4x4")
    cal = tmp_path / "cal.h5"
    assert (
        run_cli("calibrate", "--dark", paths["darks"], "--flat", paths["flats"], *preset, "-o", cal, "-q").returncode
        == 0
    )
    # a process of its own: in this one pytest records the warnings, and they never reach stderr
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    args = ["correct", paths["frame"], "--cal", cal, *preset, "-o", tmp_path / "out.h5", "-q"]
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", *map(str, args)], capture_output=True, text=True, env=env
    )
    assert res.returncode == 0, res.stderr
    assert "1 pixels of 1 frame(s) read above 4095, the top of the 12-bit ADC" in res.stderr, res.stderr


def test_correct_files_records_the_calibrations_defect_mask_beside_the_frames(tmp_path):
    """Review s42: the output of `radiokit correct` counted filled pixels per frame but not which
    ones; a user could not tell a filled defect line from the image. The calibration's pixel mask
    (NeXus NXdetector/pixel_mask) and its defect lines are written into the same file, within its
    atomic write, and the file still reads as the same stack."""
    from radiokit.correct import correct_files
    from radiokit.io import read, read_stack

    mask = np.zeros((16, 24), np.uint32)
    mask[:, 5] = PixelFlag.DEAD | PixelFlag.CLUSTER
    mask[3, 9] = PixelFlag.NOISY
    cal = _cal(16, 24, mask=mask, defect_columns=[5])
    np.random.default_rng(1).integers(300, 1000, (3, 16, 24)).astype("<u2").tofile(tmp_path / "s.raw")
    correct_files(tmp_path / "s.raw", cal, tmp_path / "out.h5", shape=(16, 24), progress=False)
    with h5py.File(tmp_path / "out.h5", "r") as h5:
        det = h5["entry/instrument/detector"]
        np.testing.assert_array_equal(det["pixel_mask"][()], mask)
        assert det.attrs["NX_class"] == "NXdetector"
        assert det["pixel_mask"].attrs["defect_columns"].tolist() == [5]
    assert read_stack(tmp_path / "out.h5").data.shape == (3, 16, 24)
    assert read(tmp_path / "out.h5").data.shape == (3, 16, 24)


@pytest.mark.parametrize("open_side", [76, 40, 26])  # 9 %, 2.4 %, 1 % of the frame open
def test_a_frame_mostly_behind_a_collimator_is_corrected_and_a_noisy_beam_off_frame_still_refused(open_side):
    """Review s42rr: a frame 91 % behind a collimator's lead has its median at the dark, and was
    refused "no signal above the dark" (by correct_frames's default check and radiokit correct)
    though its open field held the flats' counts. A beam-off frame noisier than the darks (its
    median at the dark, its top percent a few of its noise above) is still refused."""
    rng = np.random.default_rng(11)
    n = 256
    darks = (100 + rng.normal(0, 3, (8, n, n))).round().astype(np.uint16)
    flats = (100 + rng.poisson(2000, (8, n, n))).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    t = np.zeros((n, n))
    lo = (n - open_side) // 2
    t[lo : lo + open_side, lo : lo + open_side] = 0.5
    raw = (100 + rng.poisson(2000 * t) + rng.normal(0, 3, (n, n))).round().astype(np.uint16)
    out = correct_frames(cal, raw, domain="linear")
    inner = out[lo + 2 : lo + open_side - 2, lo + 2 : lo + open_side - 2]
    assert abs(float(np.median(inner)) - 0.5) < 0.02  # Poisson: 1000 counts, 3 % per pixel
    beam_off = (100 + rng.normal(0, 12, (n, n))).round().astype(np.uint16)  # 4x the darks' noise
    with pytest.raises(ValueError, match="no signal above the dark"):
        correct_frames(cal, beam_off)
    # review s42rr2: saturated rows on the check's sample grid (every 2nd row here) are no open
    # field: a beam-off frame with them passed as "collimated"
    beam_off = (100 + rng.normal(0, 3, (n, n))).round().astype(np.uint16)
    beam_off[[0, 2, 4, 6]] = 4095
    with pytest.raises(ValueError, match="no signal above the dark"):
        correct_frames(cal, beam_off)


@pytest.mark.parametrize("hot_share", [0.015, 0.03])
def test_a_beam_off_frame_with_hot_pixels_is_no_open_field_while_a_slit_is(hot_share):
    """Found (s43): a beam-off frame whose hot pixels (outside the calibration's defect mask) made
    1.5 % of it, at half the flats' level, passed as a collimated frame's open field (a percent
    of its samples in the beam's range). An open field is a region; hot pixels are isolated: a
    sample counts only beside another in range (4-neighbours on the check's grid), so hot pixels
    pass at about 4 x share^2 (0.4 % at 3 %). A slit two samples wide is still an open field."""
    rng = np.random.default_rng(5)
    n = 256
    darks = (100 + rng.normal(0, 3, (8, n, n))).round().astype(np.uint16)
    flats = (100 + rng.poisson(2000, (8, n, n))).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats)
    beam_off = (100 + rng.normal(0, 3, (n, n))).round().astype(np.uint16)
    beam_off[rng.random((n, n)) < hot_share] = 100 + 1000
    with pytest.raises(ValueError, match="no signal above the dark"):
        correct_frames(cal, beam_off)
    # a vertical slit 4 pixels wide (1.6 % of the frame; 2 columns of the check's samples)
    t = np.zeros((n, n))
    t[:, 100:104] = 0.5
    slit = (100 + rng.poisson(2000 * t) + rng.normal(0, 3, (n, n))).round().astype(np.uint16)
    out = correct_frames(cal, slit, domain="linear")
    assert abs(float(np.median(out[:, 101:103])) - 0.5) < 0.02  # Poisson: 1000 counts, 3 % per pixel


@pytest.mark.parametrize("grown", [False, True])
def test_correct_files_refuses_a_file_changed_after_its_header_was_checked(tmp_path, monkeypatch, grown):
    """`correct` judges every file's header one file at a time, then opens each again to read its
    frames (held open together, 300 files passed macOS's 256 open files). A file rewritten in
    between at another frame size is named, nothing written; one with frames appended since (an
    acquisition still writing) has the frames judged corrected, as when every file was held open."""
    import radiokit.correct as rc
    from radiokit.errors import FormatError
    from radiokit.io import read

    shape = (8, 8)
    cal = Calibration(np.full(shape, 100.0), np.full(shape, 3100.0), np.zeros(shape, np.uint32))
    a, b = tmp_path / "a.tif", tmp_path / "b.tif"
    tifffile.imwrite(a, np.full(shape, 1600, np.uint16))
    tifffile.imwrite(b, np.full(shape, 850, np.uint16))
    real = rc._correct_planned

    def rewrite_b_after_a(cal_, src, *args):
        if str(src.path) == str(a):
            tifffile.imwrite(b, np.full((2, *shape) if grown else (8, 9), 850, np.uint16))
        return real(cal_, src, *args)

    monkeypatch.setattr(rc, "_correct_planned", rewrite_b_after_a)
    if not grown:
        with pytest.raises(FormatError, match=f"^{b}: changed while being corrected"):
            rc.correct_files([a, b], cal, tmp_path / "out.h5", progress=False)
        assert not (tmp_path / "out.h5").exists()
        return
    rc.correct_files([a, b], cal, tmp_path / "out.h5", progress=False)
    out = read(tmp_path / "out.h5").data  # transmissions 0.5 and 0.25: -ln t
    np.testing.assert_allclose(out[:, 0, 0], [np.log(2), np.log(4)], rtol=1e-6)
    assert out.shape == (2, *shape) and len(read(b).data) == 2  # b grew, and its first frame was read
