"""``roi_mean_se`` against a frozen copy of its implementation before session 44's speed-up
(radiokit/measure.py at main 1e91e1c: ``_difference_var``, ``_one_pixel_se``, ``_robust_var``,
``_semivariances``, ``roi_mean_se``, ``_correlation_reach``, copied below unchanged but for the
name ``_old_roi_mean_se``). The rewrite batches all lags into one robust-variance call; the
values must agree to 1e-12 relative (summation order moves the last bits only) on flat and
blurred noise, edges, domes, non-finite pixels, tiny images, ROIs at the border, float32 and
float64, and ``min_side`` variations. Do not edit the frozen copy: it is the reference.
"""

import math

import numpy as np
import pytest
from scipy import ndimage as ndi

from radiokit.measure import (
    _CLIPPED_VAR,
    _MAD_SIGMA,
    _MAX_LAG,
    _NEAR,
    _RING2,
    _STILL_RISING,
    ROI,
    _correlation_reach,  # unchanged by the batching: the current one
    _image,
    _rectangle,
    roi_mean_se,
)


# fmt: off
# ---- frozen copy of the old implementation (reference; do not edit) --------------------------
def _difference_var(x: np.ndarray, dr: int, dc: int) -> float:
    """Robust variance of ``x(p + h) - x(p)``: of the differences within three standard
    deviations of their centre (a few rounds from the median absolute deviation), so an edge
    crossing some of them does not count, and about their centre, so the object's slope does not
    either. First differences, not second: on a window crossing an inclusion's edge a second
    difference spans twice the pixels, and read a step's noise 20-70 % high (first: 0-20 %)."""
    rows, cols = x.shape
    ar, ac = abs(dr), abs(dc)

    def part(tr, tc):
        return x[ar + tr : rows - ar + tr, ac + tc : cols - ac + tc]

    return _robust_var(part(dr, dc) - part(0, 0))[0]


def _one_pixel_se(x: np.ndarray, h: int, w: int) -> float:
    """The standard error of an ``h x w`` ROI's mean with the noise correlated between next
    neighbours only (frame means, bilinear resampling): its variance from the ring of lags two
    pixels out, the correlation from the next neighbours'."""
    ring = [_difference_var(x, *lag) for lag in _RING2]
    ring = [v for v in ring if math.isfinite(v)]
    if not ring:
        return math.nan
    s2 = float(np.median(ring)) / 2.0
    n = h * w
    if s2 <= 0:
        return 0.0
    f = 1.0
    for dr, dc in _NEAR:
        v = _difference_var(x, dr, dc)
        if not math.isfinite(v):
            continue
        rho = min(1.0, max(-1.0, 1.0 - v / (2.0 * s2)))
        f += 2 * rho * max(0.0, 1 - abs(dr) / h) * max(0.0, 1 - abs(dc) / w)
    # an estimate's noise must not claim more than n independent pixels' worth of quiet
    f = min(max(f, 0.25), float(n))
    return math.sqrt(s2 * f / n)


def _robust_var(e: np.ndarray, keep: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Robust variance of the differences ``e`` (one per pixel pair), and their residuals: of the
    differences within three standard deviations of their centre, as :func:`_difference_var`
    reads them, over the pairs ``keep`` marks (all without)."""
    ev = e.ravel()
    use = np.ones(ev.size, bool) if keep is None else keep.ravel()
    if use.sum() < 8:
        return math.nan, np.zeros_like(e)
    centre = np.median(ev[use])
    scale = _MAD_SIGMA * np.median(np.abs(ev[use] - centre))
    # then clipped at 3 scales, a few rounds: a median absolute deviation alone read 20-40 % high
    # where an inclusion's edge crossed a sixth of a window's differences
    for _ in range(5):
        kept = use & (np.abs(ev - centre) <= 3 * scale)
        if kept.sum() < 8 or scale == 0:
            break
        centre, scale = ev[kept].mean(), ev[kept].std() / math.sqrt(_CLIPPED_VAR)
    return float(scale**2), (ev - centre).reshape(e.shape)


def _semivariances(x: np.ndarray, max_lag: int) -> np.ndarray:
    """``Var(x(p + k) - x(p)) / 2`` along the columns (``x``'s last axis) for ``k = 1..max_lag``.

    Pairs that straddle an edge are left out: an edge is where a next-neighbour difference stands
    far (5 standard deviations) from the noise's. Clipping alone does not do: at a lag of ``k``
    pixels a step spoils ``k`` pairs a row, most of a window's at the lags correlated noise needs.
    """
    rows, cols = x.shape
    out = np.full(max_lag, np.nan)
    if cols < 2:
        return out
    s1, r1 = _robust_var(x[:, 1:] - x[:, :-1])
    edge = np.abs(r1) > 5 * math.sqrt(s1) if s1 > 0 else np.zeros(r1.shape, bool)
    crossed = np.concatenate([np.zeros((rows, 1)), np.cumsum(edge, axis=1)], axis=1)
    for k in range(1, min(max_lag, cols - 1) + 1):
        e = x[:, k:] - x[:, :-k]
        keep = (crossed[:, k:] - crossed[:, :-k]) == 0
        v, _ = _robust_var(e, keep if keep.sum() >= max(8, keep.size // 4) else None)
        out[k - 1] = v / 2
    return out


def _old_roi_mean_se(image, roi: ROI, *, min_side: int = 16) -> float:
    """The standard error of ``image``'s mean over ``roi``, estimated from the image alone.

    The noise is read in a window around the ROI (the ROI grown to at least ``min_side`` pixels a
    side and two more each way, within the image). Noise correlated between next neighbours only
    (frame means corrected pixel by pixel; the registered step, resampled bilinearly): its variance
    ``s2`` from robust variances of differences two pixels apart, its correlation ``rho(h)`` from
    those of next neighbours (``Var = 2 s2 (1 - rho(h))``), and ``SE^2 = s2 f / n`` with the
    effective-size factor ``f = sum_h rho(h) (1 - |h_r|/H) (1 - |h_c|/W)`` over the ``H x W``
    ROI's lags (``n / f`` independent pixels). Read per pixel, a resampled image looks up to four
    times quieter than it is over a region; ``f`` puts that back.

    Noise correlated further (a scintillator's light spread, Gaussian of ~1-2 px: review s41rr
    found the next-neighbour model's SE 0.56 of the scatter at 1 px, 0.20 at 2 px, and an unchanged
    background "measurable" in 25 % of runs): the reach of the correlation is read from the
    semivariances at 1 and 2 px (a Gaussian correlation's ratio); where it passes 3 px the
    semivariances ``gamma(k)`` along rows and along columns, ``k = 1..8`` (the window grown to
    hold four reaches), give ``s2`` (their plateau at the reach) and a separable correlation
    ``rho(k_r, k_c) = (1 - gamma_r(k_r)/s2) (1 - gamma_c(k_c)/s2)`` (exact for a Gaussian spread and
    for bilinear weights), summed over the ROI's lags within the reach. Pairs straddling an edge (a
    next-neighbour difference 5 standard deviations out) are left out. Validated on flat
    backgrounds with Gaussian-blurred noise of 0-2 px: reported / observed 0.9-1.05.

    Assumptions, and where they fail: the noise is stationary over the window and its correlation
    is near-Gaussian in shape and dies within 8 px. A structure that curves within the window (a
    small inclusion's own dome, in a step but not in a difference of steps) keeps the semivariance
    rising past the reach; there, and wherever the long lags give less than the next-neighbour
    model, the next-neighbour model's estimate is returned, which such a structure makes larger,
    never smaller (review s41rr: 1.3-1.4 x beside a dome at low noise, up to 4 x for a change
    ratio). Correlated noise on such a structure is then under-read as before.

    Returns ``nan`` when the window is too small to hold the differences (an image of a few
    pixels).
    """
    img = _image(image)
    _rectangle(roi).check(img.shape)
    h, w = roi.shape
    margin = 2
    while True:
        gr = max(0, (min_side - h + 1) // 2) + margin
        gc = max(0, (min_side - w + 1) // 2) + margin
        win = ROI(roi.row0 - gr, roi.row1 + gr, roi.col0 - gc, roi.col1 + gc).clip(img.shape)
        x = np.asarray(img[win.slices], np.float64)
        if not np.all(np.isfinite(x)):
            x = np.where(np.isfinite(x), x, np.nanmedian(x[np.isfinite(x)]) if np.isfinite(x).any() else 0.0)
        if margin == 2:
            first = x
        g_r, g_c = _semivariances(x.T, _MAX_LAG), _semivariances(x, _MAX_LAG)
        g = np.array([np.nanmean(v) if np.isfinite(v).any() else np.nan for v in zip(g_r, g_c)])
        if not (np.isfinite(g[0]) and np.isfinite(g[1])):
            return math.nan
        lag, a = _correlation_reach(g[0], g[1])
        # the window must hold a few times the lags the correlation reaches; grown once
        if margin > 2 or min(x.shape) >= 4 * lag or min(x.shape) >= min(img.shape):
            break
        margin = lag + 2
    lag = min(lag, int(np.flatnonzero(np.isfinite(g))[-1]) + 1)
    s2 = float(np.nanmean(g[lag - 1 : lag + 1]))
    # past the correlation's reach the semivariance stays flat; still rising, it is an object's
    # structure (a dome's curvature), not noise, and the longer lags would read it as correlation
    # (and the plateau stands where the first two lags' Gaussian correlation puts it)
    far = g[min(2 * lag, _MAX_LAG) - 1]
    if lag <= 3 or far > _STILL_RISING * s2 or s2 * (1 - a) > _STILL_RISING * g[0]:
        return _one_pixel_se(first, h, w)
    n = h * w
    if not s2 > 0:
        return 0.0 if s2 == 0 else math.nan
    f = 1.0
    for ga, side in ((g_r, h), (g_c, w)):
        fa = 1.0
        for k in range(1, min(lag, side)):
            if math.isfinite(ga[k - 1]):
                rho = min(1.0, max(-1.0, 1.0 - ga[k - 1] / s2))
                fa += 2 * rho * (1 - k / side)
        f *= fa
    # an estimate's noise must not claim more than n independent pixels' worth of quiet
    f = min(max(f, 0.25), float(n))
    # correlation that reaches further only adds to a mean's noise: below the next-neighbour
    # model, the long lags saw an object's structure (a dome, whose pixels the edge test left
    # out), not the noise
    return max(math.sqrt(s2 * f / n), _one_pixel_se(first, h, w))


# ---- end of frozen copy ------------------------------------------------------------------------
# fmt: on


def _case(rng):
    """A random image and ROI: noise blurred 0-3 px, on flat, a step edge, a dome or a slope,
    sometimes with NaN/inf pixels, of 1-60 px a side (windows past ``_BATCH_BELOW`` differences a
    lag too), float32 or float64; the ROI anywhere, the border too."""
    rows, cols = (int(v) for v in rng.integers(3, 61, 2))
    if rng.random() < 0.15:
        rows, cols = (int(v) for v in rng.integers(1, 8, 2))
    x = rng.normal(0, rng.choice([0.01, 1.0, 30.0]), (rows, cols))
    blur = rng.choice([0.0, 0.5, 1.0, 2.0, 3.0])
    if blur:
        x = ndi.gaussian_filter(x, blur) * (1 + blur)
    r, c = np.mgrid[:rows, :cols]
    kind = rng.integers(4)
    if kind == 1:
        x = x + rng.uniform(-50, 50) * (c > rng.integers(0, cols + 1))
    elif kind == 2:
        r0, c0, rad = rng.uniform(0, rows), rng.uniform(0, cols), rng.uniform(2, 20)
        x = x + rng.uniform(1, 20) * np.sqrt(np.clip(1 - ((r - r0) ** 2 + (c - c0) ** 2) / rad**2, 0, None))
    elif kind == 3:
        x = x + rng.uniform(-1, 1) * r + rng.uniform(-1, 1) * c
    x = x.astype(rng.choice([np.float32, np.float64]))
    if rng.random() < 0.2:
        bad = rng.random(x.shape) < rng.uniform(0.01, 0.3)
        x[bad] = rng.choice([np.nan, np.inf, -np.inf])
    r0, c0 = int(rng.integers(0, rows)), int(rng.integers(0, cols))
    roi = ROI(r0, int(rng.integers(r0 + 1, rows + 1)), c0, int(rng.integers(c0 + 1, cols + 1)))
    return x, roi, int(rng.choice([1, 4, 16, 16, 24, 40]))


def _same(new, old):
    return (math.isnan(new) and math.isnan(old)) or new == pytest.approx(old, rel=1e-12, abs=0.0)


@pytest.mark.parametrize("seed", range(3))
def test_roi_mean_se_matches_the_frozen_implementation(seed):
    rng = np.random.default_rng(4400 + seed)
    checked = 0
    for _ in range(70):
        x, roi, min_side = _case(rng)
        try:
            old = _old_roi_mean_se(x, roi, min_side=min_side)
        except ValueError:
            # the old code broke on 3-pixel-wide windows (a lag two columns back sliced past the
            # start); the new one reads no pairs there: nan or a finite value, never an error
            roi_mean_se(x, roi, min_side=min_side)
            continue
        new = roi_mean_se(x, roi, min_side=min_side)
        assert _same(new, old), (x.shape, x.dtype, roi, min_side, new, old)
        checked += 1
    assert checked > 55
