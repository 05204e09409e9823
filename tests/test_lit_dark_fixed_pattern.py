"""A dark's fixed pattern is not a lit image (review s54rvdark): a flat panel's offsets differ per
read-out block by a couple hundred counts, and a low-kV flat for a soft phantom lies only a few
hundred counts above them. The flats carry the same offsets, so the dark is judged by what it
holds beyond them; a projection given as the dark still is named lit."""

import numpy as np
import pytest

from radiokit.calibrate import Calibration, FrameLevelError

N = 128


def _panel(rng, *, blocks, block_sd, col_sd, gradient, base=1000):
    """A 16-bit panel's offset map: per-row read-out blocks, per-column offsets, a gradient down
    the panel, and hot pixels 3000 counts up (0.1 %)."""
    yy = np.arange(N)[:, None]
    offset = (
        base
        + np.repeat(rng.normal(0, block_sd, blocks), N // blocks)[:, None]
        + rng.normal(0, col_sd, N)[None, :]
        + gradient * yy / N
    )
    hot = rng.random((N, N)) < 1e-3
    return offset, hot


def _frames(rng, offset, hot, signal, n):
    """``n`` frames: the offsets, Poisson signal and 3 counts of read noise; hot pixels 3000 up."""
    frames = offset + rng.poisson(signal, (n, N, N)) + rng.normal(0, 3, (n, N, N))
    frames[:, hot] += 3000
    return frames.astype(np.float32)


def _field(level):
    """A cone beam's flat: 30 % lower at the corners than at the centre (heel and distance)."""
    yy, xx = np.mgrid[:N, :N]
    return level * (1 - 0.3 * ((yy - N / 2) ** 2 + (xx - N / 2) ** 2) / (N / 2) ** 2)


@pytest.mark.filterwarnings("ignore::radiokit.calibrate.CalibrationWarning")  # a single dark's, said
@pytest.mark.parametrize("n_darks", [1, 5])
def test_block_offsets_under_a_low_exposure_flat_are_not_a_lit_dark(n_darks):
    # offsets spread over ~500 counts (blocks of 200 counts' sd, a 200-count gradient), flats
    # 300 counts above them: the dark's 5th-95th percentile spans more than the flat's signal
    rng = np.random.default_rng(7)
    offset, hot = _panel(rng, blocks=8, block_sd=200, col_sd=50, gradient=200)
    darks = _frames(rng, offset, hot, 0, n_darks)
    flats = _frames(rng, offset, hot, _field(300), 5)
    spread = np.subtract(*np.percentile(darks[0], (95, 5)))
    assert spread > 0.5 * (np.median(flats) - np.percentile(darks[0], 5))  # the case the check met
    cal = Calibration.from_frames(darks, flats)
    # the dark kept is the offsets: each pixel's within its read noise (3 counts), their median
    # over the panel within a count
    assert abs(float(np.median(cal.dark - offset))) < 1


@pytest.mark.filterwarnings("ignore::radiokit.calibrate.CalibrationWarning")
def test_a_projection_as_the_dark_of_an_offset_panel_still_is_lit():
    rng = np.random.default_rng(8)
    offset, hot = _panel(rng, blocks=8, block_sd=200, col_sd=50, gradient=200)
    yy, xx = np.mgrid[:N, :N]
    phantom = (yy - N / 2) ** 2 + (xx - N / 2) ** 2 < (N / 3) ** 2
    proj = _frames(rng, offset, hot, np.where(phantom, 0.25, 1.0) * 3000, 1)
    flats = _frames(rng, offset, hot, np.full((N, N), 3000.0), 3)
    with pytest.raises(FrameLevelError, match="lit"):
        Calibration.from_frames(proj, flats)


@pytest.mark.filterwarnings("ignore::radiokit.calibrate.CalibrationWarning")
def test_the_flat_given_as_the_dark_too_is_named_lit():
    # one flat of a heeled beam given as both: the dark holds nothing beyond the flats' pattern,
    # but lies at their level, not under it as a dark's offsets do
    rng = np.random.default_rng(9)
    offset, hot = _panel(rng, blocks=8, block_sd=20, col_sd=5, gradient=0, base=300)
    heel = 10000 * (1 - 0.5 * np.arange(N) / N)[None, :] * np.ones((N, 1))
    flat = _frames(rng, offset, hot, heel, 1)
    with pytest.raises(FrameLevelError, match="lit"):
        Calibration.from_frames(flat, flat)
