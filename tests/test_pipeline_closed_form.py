"""`radiokit process` on experiments built from closed forms: every number it reports is known.

The object is a slab (background attenuation ``MU_B`` per mm across the plate gap) with a disc of
extra attenuation ``DMU`` over a chord, imaged monochromatically, so each step's line integral is
``L = MU_B g + DMU c disc`` and its transmission ``exp(-L)``. Between steps the object does not
move (the registration's ideal answer is the identity), so the contrast, the improvement factor
``IF(k) = 1 + k (1 - C_moving / C_reference)`` and the change ratio follow from ``L`` alone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

N = 160
I0, DARK = 3000.0, 100
MU_B, DMU = 0.05, 0.05  # per mm
GAPS = (42.5, 40.0, 37.5)  # mm: 15, 20, 25 % of a 50 mm body
CHORDS = (8.0, 7.9, 7.8)  # mm: the disc's chord thins less than the gap (a stiff inclusion)
INC = (70, 91, 70, 91)  # ROIs, half-open pixels: inside the disc, and beside it
BG = (70, 91, 20, 41)


def _line_integral(step: int) -> np.ndarray:
    rr, cc = np.mgrid[:N, :N]
    disc = np.hypot(rr - 80, cc - 80) < 25
    return MU_B * GAPS[step] + DMU * CHORDS[step] * disc


def _mean(img, roi):
    r0, r1, c0, c1 = roi
    return float(np.mean(img[r0:r1, c0:c1], dtype=np.float64))


def _contrast(img):
    return _mean(img, INC) - _mean(img, BG)


def _write(path, order, frames_per_step=1, counts=None, record=("ratio", "gap")):
    """Darks, flats and one projection per step; steps numbered 1, 2, ... in the order
    ``order`` (indices into GAPS), each recorded with its compression ratio and gap."""
    from radiokit.io import ExperimentWriter, ImageKey

    rng = np.random.default_rng(0)
    with ExperimentWriter(path, shape=(N, N), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full((N, N), DARK, np.uint16), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(np.full((N, N), DARK + I0, np.uint16), image_key=ImageKey.FLAT)
        for number, s in enumerate(order, start=1):
            for _ in range(frames_per_step):
                mean = I0 * np.exp(-_line_integral(s)) if counts is None else counts(s)
                signal = np.round(mean) if counts is None else rng.poisson(mean)
                w.append(
                    (DARK + signal).astype(np.uint16),
                    image_key=ImageKey.PROJECTION,
                    step=number,
                    ratio=0.15 + 0.05 * s if "ratio" in record else None,
                    gap_mm=GAPS[s] if "gap" in record else None,
                )


def test_a_series_taken_while_releasing_the_plates_keeps_the_most_compressed_step_as_reference(tmp_path):
    """Steps 1, 2, 3 recorded at 25, 20, 15 % (the plates released step by step): the reference
    is step 1, the most compressed, and the main pair 2 -> 1; the improvement factors are the
    closed form's and the bound is reported (the gaps are recorded and close towards step 1).
    It took step 3 (15 %) as the reference, registered 20 % onto it and reported IF 0.88 where
    the closed form gives 1.108, and no bound ("plate gaps not recorded")."""
    from radiokit.enhance import to_domain
    from radiokit.measure import improvement_bound
    from radiokit.pipeline import Config, process

    path = tmp_path / "release.h5"
    _write(path, order=(2, 1, 0))
    cfg = Config(
        progress=False, report=False, crop_mm=None, method="ncc", cross_check=None, inclusion=INC, background=BG
    )
    r = process(path, cfg, out_dir=tmp_path / "out").results
    assert r["steps"] == [3, 2, 1] and r["ratios"] == pytest.approx([0.15, 0.20, 0.25])
    assert r["main_pair"] == "2->1" and set(r["change_ratio"]) == {"3->1", "2->1", "3->2"}

    # Counts are rounded to integers: |dL| <= 0.5 / (fewest counts) per pixel, so a contrast
    # is off by at most 2 eps and IF(k) by k (|dC_M| + |C_M / C_R| |dC_R|) / |C_R|.
    eps = 0.5 / (I0 * math.exp(-float(_line_integral(0).max())))
    for dom in ("log", "negative"):
        c_ref = _contrast(to_domain(_line_integral(2), dom))
        c_mov = _contrast(to_domain(_line_integral(1), dom))
        scale = 1.0 if dom == "log" else math.exp(-MU_B * GAPS[2])  # dT = T dL <= dL
        for k in (1, 2):
            want = 1 + k * (1 - c_mov / c_ref)
            tol = k * 2 * eps * scale * (1 + abs(c_mov / c_ref)) / abs(c_ref)
            assert r["domains"][dom]["improvement_factor"][str(k)] == pytest.approx(want, abs=tol)
    assert r["bound"]["mu_dg"] is not None
    mu_b = r["bound"]["mu_dg"] / (GAPS[1] - GAPS[2])  # estimated from the reference's background
    assert mu_b == pytest.approx(MU_B, abs=eps / GAPS[2])
    for k in (1, 2):
        assert r["domains"]["negative"]["bound"][str(k)] == pytest.approx(
            improvement_bound(k, mu_b, GAPS[1] - GAPS[2], "negative"), rel=1e-12
        )


@pytest.mark.parametrize(
    "record, numbers",
    [(("ratio",), (3, 2, 1)), (("gap",), (3, 2, 1)), ((), (1, 2, 3))],
)
def test_steps_are_ordered_by_ratio_else_gap_else_number(tmp_path, record, numbers):
    """The same release series with only the ratios, only the gaps, or neither recorded: the
    first two put the least compressed step (3) first; without either the step numbers decide."""
    from radiokit.pipeline import load_steps

    path = tmp_path / "release.h5"
    _write(path, order=(2, 1, 0), record=record)
    steps = load_steps(path)
    assert steps.numbers == numbers
    # the images follow their labels: step 1 holds the most compressed (thinnest) object
    means = {n: float(img.mean(dtype=np.float64)) for n, img in zip(steps.numbers, steps.images)}
    assert means[1] < means[2] < means[3]


@pytest.mark.parametrize(
    "record, said", [("ratio", r"compression ratio, 0\.2\b"), ("gap", r"plate gap, \d+(\.\d+)? mm")]
)
def test_a_main_pair_recorded_at_one_compression_is_warned_of(record, said, tmp_path):
    """Steps 2 and 3 both recorded at 20 % (a ratio typed twice, or a repeat): the reference,
    "the most compressed", is a tie that the step numbers broke without a word, and the pair's
    compression-induced contrast is that of no compression. Said, naming the steps and the ratio;
    a series of three ratios says nothing."""
    import warnings

    from radiokit.pipeline import load_steps

    _write(tmp_path / "tie.h5", order=(0, 1, 1), record=(record,))
    with pytest.warns(UserWarning, match=r"tie\.h5: steps 2 and 3 record one " + said):
        assert load_steps(tmp_path / "tie.h5").numbers == (1, 2, 3)
    _write(tmp_path / "three.h5", order=(0, 1, 2), record=(record,))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_steps(tmp_path / "three.h5")
    assert not [w for w in caught if "one compression" in str(w.message)]


def test_a_steps_line_integral_is_the_log_of_its_frames_mean_transmission(tmp_path):
    """16 Poisson frames of 40 counts per pixel behind the object (noise-free flats): the step's
    line integral is ``-ln`` of the mean transmission, whose bias is ``1 / (2 N lambda)`` (the
    16 frames are one 16 times longer exposure), and its noise ``1 / sqrt(N lambda)``.
    Averaging each frame's ``-ln`` instead kept one frame's bias, ``1 / (2 lambda)`` = 0.0125,
    about 50 standard errors of the frame's mean here."""
    from radiokit.pipeline import load_steps

    lam, n_frames = 40.0, 16
    t = lam / I0
    path = tmp_path / "dim.h5"
    _write(path, order=(0, 1), frames_per_step=n_frames, counts=lambda s: np.full((N, N), lam))
    steps = load_steps(path)
    m = n_frames * lam  # counts summed over the step's frames
    # E[-ln(n / m)] for n ~ Poisson(m): 1 / (2 m) + 1 / (3 m^2) + O(m^-3); var 1 / m + O(m^-2)
    bias = 1 / (2 * m) + 1 / (3 * m**2)
    sigma = math.sqrt(1 / m)
    for image in steps.images:
        li = image.astype(np.float64)
        se = sigma / math.sqrt(li.size)
        assert li.mean() == pytest.approx(-math.log(t) + bias, abs=5 * se + 1 / m**2)
        # the sample standard deviation's relative standard error is 1 / sqrt(2 n)
        assert li.std() == pytest.approx(sigma, rel=5 / math.sqrt(2 * li.size) + 1 / m)
