"""Where the motion is observable, and whether a registration is consistent with its images.

Observability (the confidence map)
----------------------------------
A pair observes a displacement at ``x`` through the fixed image's gradient there: for a
residual ``m(x + d) - f(x)`` with independent noise of standard deviation ``sigma`` in both
images, the Fisher information of ``d`` from a window ``W`` is
``F = sum_W grad t grad t^T / (2 sigma^2)`` (``t`` the noise-free image), and no unbiased
estimate of ``d`` does better than ``1 / sqrt(lambda_min(F))`` (the Cramer-Rao bound; the
smaller eigenvalue, because an edge observes only its normal component). We estimate it from
the data alone:

- ``t``'s gradient from the fixed image high-passed at the lattice scale (residual complexity,
  like any similarity that tolerates a slow intensity change, cannot tell a slow residual from
  motion, so the slow part of the image observes nothing) and smoothed by 1 px, with the noise's
  own contribution to ``grad f grad f^T`` subtracted;
- ``sigma`` per pixel from the diagonal second difference ``(f00 - f01 - f10 + f11) / 2``, whose
  standard deviation is ``sigma`` for white noise and which a texture coarser than ~2 px hardly
  reaches; its square averaged over the window, so Poisson-like noise gives a local level;
- with a mask (``register(..., mask=)``), the gradients inside it alone: the similarity scores
  nothing else, and a flat band beside a texture read observed through the window's reach;
- ``W`` a Gaussian window of the lattice spacing (the scale at which the B-spline field is free),
  cut at ``WINDOW_REACH`` (2) spacings: structure farther away pins the field here only through
  the regulariser (the field is free to vary over a few spacings), and a full Gaussian's tails
  let a body's strong edge reach deep into a silent interior -- on a textureless 560 px body at
  noise 0.0025, 66 % of the interior two windows inside the edge read "observed" through the
  tails alone, 34 % with the cut (the disc's neighbourhood), while a textured interior reads
  100 % either way (``benchmarks/README.md``, "The map's window reach");
- with the moving image (``register()`` passes it), none where both images are exactly flat at
  one value in a region whose edge stays put (``flat_common``: an opaque strip fixed on the
  detector, a range clipped in both): the structure within the window's reach there is that
  region's own edge, which does not move with the object (session 41's review: 84 % of a 120-row
  band across a moving body read observed, its field worse than none). A noise-free body's
  constant interior moves, so its edge leaves a strip flat in one image alone and the window's
  reach stands there as designed;
- less a noise-only floor: a window's gradient covariance of pure noise fluctuates by about
  ``1 / sqrt(window area)`` of the noise's share, and what pure noise of the estimated level
  shows as structure 99 % of the time (measured once on a white-noise image) is not information.

``confidence = 1 / (1 + (s / 0.5 px)^2)``, ``s`` the bound: 0.5 where the bound is 0.5 px,
near 1 where the motion is pinned, near 0 where the image is silent (a textureless interior).
``observed`` means confidence >= 0.5. ``register()`` computes all of it on the pair binned to
about 0.4 Mpx and converts the bound to full-resolution pixels (binning by ``k`` leaves the
information per area nearly unchanged for structure coarser than the bin, so a bound in binned
pixels is the full-resolution one over ``k``), then upsamples the map.

Where the field is pinned
-------------------------
The window bounds a translation of the whole window, but the field is free over less: beside a
strong edge it is pinned only near the edge. On review s42rep's slab (200 px, a disc of radius
30 whose step is 11.5x the noise, Poisson noise, no motion) rc's median error against the
distance from the disc's edge is 0.15 px within 3 px, 0.39 at 6-10, 0.56 at 10-15, 0.73 at
15-20, 1.0 at 20-30 (``fast``, a 16 px lattice; ``default``'s 24 px lattice 0.06, 0.23, 0.34,
0.46, 0.60), while the window (cut at 48 px) calls a ROI 20-50 px from the edge 77-83 %
observed. ``observability(..., pinned=True)`` adds ``Observability.pinned``: observed only
where structure above the noise lies within ``PINNED_REACH`` (half) a spacing (the window's
information at the density found in a window of the same shape cut at that reach, with its own
noise floor, whichever is less; nowhere more observed than ``confidence``). It is NOT the map a
registration carries: on the simulated gel cube of ``tests/test_pipeline.py`` it calls the
background ROI 0 % and the inclusion ROI 48 % observed where the field is 0.15 and 0.12 px off
(the regulariser interpolates a smooth compression between the sphere's and the cube's edges
correctly), so ``radiokit process`` would flag every pair of it; no reach read from the data
tells that interpolation from the slab's drift (``benchmarks/README.md``, "Featureless ROIs
beside a strong edge"; ``benchmarks/bench_roi_pinned.py``).

Consistency (no truth)
----------------------
After registration the residual ``warped - fixed``, high-passed like the image and less the
part a local thinning or gain explains, should be noise where the motion is observed: its local
mean square against the noise's expected share, ``(1 + a)^2 sigma_f^2 + v sigma_m^2``, each
image's noise estimated on its own (each image's local ``noise_map``: a radiograph's noise
varies with the body's density), ``a`` the
local gain removed and ``v`` the variance that bilinear interpolation leaves of the moving
image's noise (``interpolation_variance``: 1 on whole-pixel shifts, 1/4 at half a pixel in both
directions; without it a perfect registration looks better than noise). The gain is fitted with
the fixed image's noise taken out of its moments, one global gain (the median of the windows'
gains: an exposure or an overall thinning, bounded to a factor of 2 either way,
``MAX_GLOBAL_GAIN``: past it the gain is a texture the motion inverted) and each window's departure from it bounded
to +-``MAX_GAIN`` (a local thinning): a least-squares gain is diluted by that noise towards -1,
and where the fixed image is far noisier than its texture it took the fixed image's whole content
out of the residual, misaligned structure included (session 34). A window's mean square of pure noise
scatters by ``sqrt(2 / N)`` around its expectation, ``N = 4 pi window^2`` the Gaussian window's
effective number of pixels (about 7000 at 24 px: 1.7 %), so an excess of a tenth of the expectation (6 such standard
deviations) is structure the pair carries left misaligned, not noise. A lone row or column of
the residual that one image alone holds (a detector's dead or stuck line: ``lone_lines``) is a
defect of that image, not misalignment: it is left out of the residual and of the fixed image's
high-pass (normalised blurs over the rest), else its energy, hundreds of times the noise's,
reaches every window within ~100 px of it (``LINE_NOISE``). ``quality.ok`` is False
when too little of the object's interior is observed (the field there is the regulariser's
guess, whatever the similarity says), when the residual still moves (below), or when too much
of the observed part is left misaligned.

Residual motion (no truth)
--------------------------
The mean-square test above is an energy detector: it needs a misalignment ``d`` to raise a
window's residual by a tenth of the noise's share, ``|d| ~ sqrt(0.1 N) x`` the window's bound
(about 19x it at 24 px). A matched estimate needs only a few bounds: one Gauss-Newton
(Lucas-Kanade) step of the residual against the fixed image's gradient, with a local gain and
offset fitted alongside (a thinning or a slow intensity change), is an estimate of what is left
of the motion, scattered by about the bound. Its median over the observed object is
``quality.residual_motion``, in a window of half the map's (a motion varying over a short
correlation length is not averaged away). The step is taken on images band-passed around 20
px wavelengths, so that a misalignment larger than a fine texture's correlation length still
correlates with the gradient; it underestimates such a misalignment (the texture decorrelates,
and the gradient's own noise shrinks the step), so it is a detection statistic with a threshold
chosen on training seeds, not an error bar.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "observability",
    "Observability",
    "roi_observed",
    "consistency",
    "Consistency",
    "residual_motion",
    "ResidualMotion",
    "interpolation_variance",
    "noise_sigma",
    "object_noise",
    "OBSERVED_PX",
    "affine_bound",
    "affine_step",
    "AffineStep",
    "flat_common",
]

OBSERVED_PX = 0.5  # the bound (px) at which confidence is 0.5: "observed"
# A floor under the noise, as a fraction of the image's 1st-99th percentile range: the part of
# the residual no similarity models exactly (interpolation, an intensity change that is not
# exactly slow at a body's curved edge). Without it a noise-free image of a smooth body calls
# its curvature alone "observed".
MODEL_FLOOR = 3e-4
# the window is cut this many spacings from its centre: the part of the object the flag calls the
# interior (radiokit.register._INTERIOR windows inside its edge) is then beyond the edge's reach
WINDOW_REACH = 2.0
# where the field is pinned: structure above the noise within this many spacings of a pixel (see
# the module docstring, "Where the field is pinned")
PINNED_REACH = 0.5
_NOISE_DERIV = {}  # smoothing sigma -> variance of the derivative filter on unit white noise; and _noise_lmin's


@dataclass
class Observability:
    """``confidence`` (rows, cols) float32 in [0, 1]; ``bound_px`` the Cramer-Rao bound (px);
    ``sigma`` the noise level estimated from the data (image units, median over the object);
    ``object`` the pixels that are not background (bool)."""

    confidence: np.ndarray
    bound_px: np.ndarray
    sigma: float
    object: np.ndarray
    #: with ``observability(..., pinned=True)``: the confidence with the information found
    #: within :data:`PINNED_REACH` spacings of the pixel (see the module docstring, "Where the
    #: field is pinned"; measured, not what a registration carries)
    pinned: np.ndarray | None = None
    #: with the affine bound (``affine_prior``), the map without it (translation alone)
    translation: np.ndarray | None = None


def _gauss(a, s):
    import cv2

    return cv2.GaussianBlur(np.asarray(a, np.float32), (0, 0), float(s), borderType=cv2.BORDER_REFLECT)


def _window_kernel(s) -> np.ndarray:
    """One axis of the map's window: a Gaussian of sigma ``s`` cut at ``WINDOW_REACH`` sigmas,
    peak 1 (float64)."""
    r = int(round(WINDOW_REACH * s))
    u = np.arange(-r, r + 1, dtype=np.float64)
    return np.exp(-0.5 * (u / s) ** 2)


def _window(a, s):
    """The window mean of ``a`` at every pixel (the normalised :func:`_window_kernel`)."""
    import cv2

    k = _window_kernel(s)
    k = (k / k.sum()).astype(np.float32)
    # float32: 3x faster than float64 (3.7 against 10.8 ms at 560 x 560); the covariance is a
    # difference of two means, and on a body's slope float32 leaves ~1e-4 of it (the bound within
    # 1.4e-4 of a float64 computation on a texture), far under the noise floor subtracted from it
    return cv2.sepFilter2D(np.asarray(a, np.float32), cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT)


def _window_area(s) -> float:
    """The sum of the window's weights with a peak of 1 (``2 pi s^2`` uncut)."""
    return float(_window_kernel(s).sum() ** 2)


def _deriv_noise_var(s):
    """Variance of ``d/dx`` (central difference after a Gaussian of ``s`` px) of unit white
    noise: measured once on a noise image (exact enough, and it stays true to the filters used)."""
    if s not in _NOISE_DERIV:
        z = np.random.default_rng(0).standard_normal((256, 256)).astype(np.float32)
        g = _gauss(z, s) if s > 0 else z
        _NOISE_DERIV[s] = float(np.var(np.gradient(g, axis=1)[16:-16, 16:-16]))
    return _NOISE_DERIV[s]


def sample_step(n_pixels) -> int:
    """The stride that leaves about 250k samples of an image of ``n_pixels`` (in each
    direction): enough for a percentile or a median, and cheap at 2240 x 2240."""
    return max(1, int(np.sqrt(n_pixels / 250_000)))


def noise_sigma(f, where=None) -> float:
    """The image's typical noise standard deviation: the median absolute diagonal second
    difference (see ``noise_map``) x 1.4826, the median-absolute-deviation scale of a
    Gaussian, from ~250k samples. The median, not the mean: a body's edge or an inclusion
    reaches the second difference in a few pixels, which the median ignores. Blocks whose four
    pixels are equal are left out: a collimated, masked or saturated part of the frame holds no
    noise to measure, and where it is over half the frame it would read the noise as 0.
    ``where`` (bool, ``f``'s shape): only the blocks whose first pixel it holds."""
    f = np.asarray(f, np.float32)
    step = sample_step(f.size)
    a, b = f[: f.shape[0] - 1 : step, : f.shape[1] - 1 : step], f[: f.shape[0] - 1 : step, 1::step]
    c, d = f[1::step, : f.shape[1] - 1 : step], f[1::step, 1::step]
    n0, n1 = min(map(len, (a, b, c, d))), min(x.shape[1] for x in (a, b, c, d))
    a, b, c, d = a[:n0, :n1], b[:n0, :n1], c[:n0, :n1], d[:n0, :n1]
    live = (a != b) | (a != c) | (a != d)
    if where is not None:
        live &= np.asarray(where, bool)[: f.shape[0] - 1 : step, : f.shape[1] - 1 : step][:n0, :n1]
    h = 0.5 * (a - b - c + d)[live]
    return float(1.4826 * np.median(np.abs(h))) if h.size else 0.0


def object_noise(f) -> float:
    """``noise_sigma`` over the object (``_object``: what differs from the frame's border level),
    or over the frame when the object is under a twentieth of it. A radiograph's noise is
    Poisson-like, so the open beam around a body is quieter (in line integrals) or louder (in
    transmission) than the body, where the motion is seen: on the simulated pairs the frame's
    median read 0.25-0.5 of the body's noise."""
    import cv2

    frame = noise_sigma(f)
    # less a rim: the 4 px blur spreads the object past a sharp edge into the beam
    # the registration's noise (rc's alpha) as before session 20: the collimator's test is the checks'
    obj = cv2.erode(_object(f, frame, collimator=False).astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    return noise_sigma(f, obj) if obj.mean() >= 0.05 else frame


def noise_map(f, window):
    """Local noise standard deviation from the diagonal second difference, averaged over
    ``window`` (Gaussian sigma, px)."""
    h = 0.5 * (f[:-1, :-1] - f[:-1, 1:] - f[1:, :-1] + f[1:, 1:])
    h = np.pad(h, ((0, 1), (0, 1)), mode="edge")
    return np.sqrt(np.maximum(_gauss(h * h, window), 1e-30))


def robust_noise_map(f, window):
    """Local noise standard deviation that a strong rim or an edge does not reach: the median of
    ``|h|`` (``h`` the diagonal second difference of ``noise_map``, ``sigma`` for white noise) x
    1.4826 over square tiles of side ``window`` (px), then the median of each tile's 3 x 3
    neighbourhood, bilinear back to every pixel (float32, ``f``'s shape).

    ``noise_map``'s window mean of ``h^2`` takes in a rim's ``h`` (about half its step on every
    pixel along it) with the noise: many times the true variance beside a strong rim (its window spreads the rim's energy over the texture beside it). A median ignores
    a share ``e < 1/2`` of outliers up to reading the clean ``|h|``'s quantile ``1 / (2 (1 - e))``:
    a rim a few px wide crossing a tile of a window's sigma is ``e`` ~ 0.1-0.2 (``sigma`` read
    1.1-1.3x), and the 3 x 3 median leaves the tiles a line crosses (at most 5 of 9, mostly 3) out.
    Blocks whose four pixels are equal hold no noise (a collimated, clipped or masked part, as
    ``noise_sigma`` leaves them out): they enter the median as 0 and a huge value in equal numbers, which
    leaves a tile's median the live pixels' own; a tile with under a quarter live takes the
    noise map's value. Its cost and what it changed: benchmarks/README.md, "The affine bound's noise
    share from a rim-blind estimate (session 56)"."""
    f = np.asarray(f, np.float32)
    a, b, c, d = f[:-1, :-1], f[:-1, 1:], f[1:, :-1], f[1:, 1:]
    h = np.abs(0.5 * (a - b - c + d))
    live = (a != b) | (a != c) | (a != d)
    checker = (np.indices(h.shape).sum(axis=0) % 2).astype(bool)
    # (a finite stand-in for +inf: a tile's median is never one while a quarter of it is live)
    h = np.where(live, h, np.where(checker, np.float32(3e38), np.float32(0)))
    h = np.pad(h, ((0, 1), (0, 1)), mode="edge")
    live = np.pad(live, ((0, 1), (0, 1)), mode="edge")
    side = max(4, int(round(window)))
    n0, n1 = h.shape
    t0, t1 = -(-n0 // side), -(-n1 // side)
    pad = ((0, t0 * side - n0), (0, t1 * side - n1))

    def tiles(x):
        return np.pad(x, pad, mode="symmetric").reshape(t0, side, t1, side).transpose(0, 2, 1, 3).reshape(t0, t1, -1)

    th = tiles(h)
    med = np.median(th, axis=-1)
    # a quantised image's |h| takes a few levels (steps of half a count): the median snaps to one,
    # and the variance read is the level's, not the noise's (underestimated: noise read as
    # structure; benchmarks/README.md, "Review of the rim-blind noise share"). Where the median is a level many values hold, the grouped median: the
    # level's values spread evenly over its bin (half-way to the next level either side, from 0 at 0)
    m = med[..., None]
    eq = np.count_nonzero(th == m, axis=-1)
    tied = eq > 1
    if tied.any():
        below = np.count_nonzero(th < m, axis=-1)
        step = np.min(np.where(th > m, th, np.float32(np.inf)), axis=-1) - med
        ok = tied & (step < 1e37)  # (not the flat blocks' stand-in)
        lo = np.maximum(med - 0.5 * step, 0)
        grouped = lo + (med + 0.5 * step - lo) * (0.5 * th.shape[-1] - below) / np.maximum(eq, 1)
        med = np.where(ok, grouped, med)
    med = 1.4826 * med
    share = tiles(live).mean(axis=-1)
    if (share < 0.25).any():
        # the noise map's value at the tiles' centres (computed only here: it costs about as much
        # as this whole map)
        fallback = noise_map(f, window)
        cy = np.minimum(np.arange(t0) * side + side // 2, n0 - 1)
        cx = np.minimum(np.arange(t1) * side + side // 2, n1 - 1)
        med = np.where(share < 0.25, fallback[np.ix_(cy, cx)], med)
    if min(t0, t1) >= 3:
        from scipy import ndimage

        med = ndimage.median_filter(med, size=3, mode="nearest")
    import cv2

    # cv2's resize puts tile i's value at its centre ((i + 0.5) side - 0.5), as the tiles lie
    out = cv2.resize(med.astype(np.float32), (t1 * side, t0 * side), interpolation=cv2.INTER_LINEAR)
    return out[:n0, :n1]


# the ring inside a collimator's aperture whose level is the open beam's (px from the border
# region, beyond the object's 4 px blur: 3 sigmas), and the share of the aperture that may lie
# beyond that level (the open beam is an extreme: nothing attenuates less than nothing)
_APERTURE_RING = (12.0, 16.0)
_BEYOND_OPEN = 0.01
_OPEN_QUANTILE = 10.0
_COLLIMATOR_COVER = 0.9  # the share of the frame's edge at the border's level
_COLLIMATOR_AREA = 0.25  # the most of the frame a collimator's border may cover
_MIN_KEPT = 0.3  # the least share of the object a collimator's open beam may take away (see _object)


def _object(f, sigma, collimator=True):
    """Pixels that differ from the frame's border level by more than 5 noise levels after a
    4 px blur (the body; the empty beam outside it observes nothing and is not scored), and,
    with ``collimator``, from the open beam inside a collimator (:func:`_open_beam_level`)."""
    border = np.concatenate([f[0], f[-1], f[:, 0], f[:, -1]])
    level = float(np.median(border))
    fs = _gauss(f, 4.0)
    line = 5 * sigma / 4.0 + 1e-12
    obj = np.abs(fs - level) > line
    if collimator:
        beam = _open_beam_level(fs, obj, level, line)
        if beam is not None:
            body = obj & (np.abs(fs - beam) > line)
            # two levels alone cannot tell an open field in a collimator from a flat body filling
            # most of the frame in the open beam (the domain is not known here); the latter would
            # lose its whole plateau, keeping only its rim, so an object cut below _MIN_KEPT of
            # itself is kept as it was (a body inside a collimator keeps more: the phantoms' kept
            # 49-94 % of the frame, benchmarks/README.md, session 20)
            obj = body if body.sum() >= _MIN_KEPT * obj.sum() else obj
    return obj


def _open_beam_level(fs, obj, level, line):
    """The open beam's level inside a collimator, or None. A collimator's static border sets the
    frame's border level, and then everything inside its aperture (the empty beam too) differs
    from it and would count as the object, its edges as observed structure. Inside the aperture
    the open beam lies along the collimator's edge (which covers ``_COLLIMATOR_COVER`` of the
    frame's edge); it is recognised by physics, not shape: the
    least attenuated part of the image, so no more than ``_BEYOND_OPEN`` of the aperture lies
    beyond its level on the side away from the collimator's (log or linear input alike). The
    level is the extreme tenth (``_OPEN_QUANTILE``, on that side) of ``fs`` (the blurred image)
    in a ring ``_APERTURE_RING`` px inside the aperture's edge, taken half-way between the
    border's level and the aperture's median (a strong step's blur reaches far past the
    object's own line). A body seen through the frame's edge, around which the border is the
    open beam, fails the test: its inclusions, texture or centre lie beyond its edge's level."""
    import cv2

    if obj.all() or not obj.any():
        return None
    side = np.sign(float(np.median(fs[obj])) - level)  # beyond: away from the border's level
    if side == 0:
        return None
    mid = 0.5 * (level + float(np.median(fs[obj])))
    # the border region: the pixels on the border's side of ``mid`` connected to the frame's edge
    n, lab = cv2.connectedComponents((side * (fs - mid) < 0).astype(np.uint8), connectivity=4)
    edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    outer = np.isin(lab, edge[edge > 0])
    # a collimator surrounds the aperture: the frame's edge nearly all on its side (a body or
    # plates running off the frame make it a mixture, whose extremes need not be the beam)
    if np.concatenate([outer[0], outer[-1], outer[:, 0], outer[:, -1]]).mean() < _COLLIMATOR_COVER:
        return None
    # ... and frames the field, it does not fill it: a flat slab in the open beam looks like an
    # open field in a collimator, but its border (the beam) is most of the frame
    if outer.mean() > _COLLIMATOR_AREA:
        return None
    dist = cv2.distanceTransform((~outer).astype(np.uint8), cv2.DIST_L2, 5)
    ring = obj & (dist >= _APERTURE_RING[0]) & (dist < _APERTURE_RING[1])
    if ring.sum() < 50:
        return None
    # the ring's extreme tenth: the open beam need only hold part of the ring (a body and the
    # plates may cover most of the collimator's edge)
    beam = side * float(np.percentile(side * fs[ring], 100.0 - _OPEN_QUANTILE))
    if np.mean(side * (fs[obj] - beam) > line) > _BEYOND_OPEN:
        return None
    return beam


def _lmin(f, spacing, highpass, sig2, mask=None, window=None):
    """The smaller eigenvalue of the window's gradient covariance of ``f`` high-passed at
    ``highpass x spacing`` and smoothed by 1 px, less the noise's own share (``sig2`` its
    variance per pixel); with ``mask`` (bool), of the gradients inside it alone. ``window``: the
    window's sigma (px; None: ``spacing``)."""
    return _lmins(f, spacing, highpass, sig2, mask, (window,))[0]


def _map_gradients(f, spacing, highpass, mask=None):
    """``(gy, gx, inside)``: the map's gradients of ``f`` (high-passed at ``highpass x spacing``,
    smoothed by 1 px), zero outside ``mask``; ``inside``: the mask as float32 (None without one)."""
    hp = f - _gauss(f, highpass * spacing)
    gy, gx = np.gradient(_gauss(hp, 1.0))
    inside = None
    if mask is not None:
        # a masked similarity sees no structure outside the mask: a flat band beside a texture
        # read 100 % observed through the windows' reach, and a field 2 px off was trusted there
        inside = np.asarray(mask, np.float32)
        gy, gx = gy * inside, gx * inside
    return gy, gx, inside


def _lmins(f, spacing, highpass, sig2, mask=None, windows=(None,), grads=None):
    """:func:`_lmin` for each of ``windows`` (sigmas, px; None: ``spacing``), the gradients
    computed once (``grads``: :func:`_map_gradients`' of the same arguments, already computed)."""
    gy, gx, inside = _map_gradients(f, spacing, highpass, mask) if grads is None else grads
    bias = _deriv_noise_var(1.0) * sig2  # noise's share of each squared derivative
    out = []
    for window in windows:
        s = spacing if window is None else window
        b = bias if inside is None else bias * _window(inside, s)
        # the gradient's local covariance, not its mean square: a gradient that is the same across
        # the window (a smooth body's slope) moves the window's residual by a constant, which an
        # intensity change explains as well as motion does
        my, mx = _window(gy, s), _window(gx, s)
        jyy = _window(gy * gy, s) - my * my - b
        jxx = _window(gx * gx, s) - mx * mx - b
        jxy = _window(gy * gx, s) - my * mx
        tr, det = jxx + jyy, jxx * jyy - jxy * jxy
        out.append(np.maximum(0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0)), 0))
    return out


def _noise_lmin(spacing, highpass, window=None):
    """The 99th percentile of :func:`_lmin` on unit white noise (a window's gradient covariance
    fluctuates by about ``1 / sqrt(window area)`` of the noise's share): measured once per
    window, like :func:`_deriv_noise_var`."""
    key = ("lmin", float(spacing), float(highpass)) + (() if window is None else (float(window),))
    if key not in _NOISE_DERIV:
        n = int(max(256, 16 * spacing))
        z = np.random.default_rng(0).standard_normal((n, n)).astype(np.float32)
        lm = _lmin(z, spacing, highpass, np.ones_like(z), window=window)
        m = int(3 * spacing)
        _NOISE_DERIV[key] = float(np.percentile(lm[m:-m, m:-m], 99))
    return _NOISE_DERIV[key]


def one_directional(f, spacing, highpass=0.25) -> np.ndarray:
    """Where the map's window holds structure of one direction only (bool): a rim, a plate's or
    a slab's edge. The window's gradient covariance (the map's: ``f`` high-passed at
    ``highpass x spacing``, smoothed by 1 px, the noise's share and its 99 % floor taken out) has
    a smaller eigenvalue under ``1 / WINDOW_REACH^2`` of the larger. An arc of radius ``R`` seen
    through the map's Gaussian window (sigma ``spacing``) turns its normal by about
    ``spacing / R`` across it, ``lambda_min / lambda_max ~ (spacing / R)^2``: under the line the
    structure is no more curved than an arc as wide as the window's cut (``WINDOW_REACH``
    spacings), and the window's tangential information is that curvature's. It credits a
    translation of the whole window, but a field free at the window's scale slides such a rim
    along itself (a rotation about its centre of curvature) unseen (benchmarks/README.md, "Why
    the error is large where the map says observed on a textureless body"). A texture, a corner
    or a small inclusion inside the window gives a ratio near 1."""
    f = np.asarray(f, np.float32)
    spacing = max(2.0, float(spacing))
    sig2 = noise_map(f, spacing) ** 2
    hp = f - _gauss(f, highpass * spacing)
    gy, gx = np.gradient(_gauss(hp, 1.0))
    bias = _deriv_noise_var(1.0) * sig2
    my, mx = _window(gy, spacing), _window(gx, spacing)
    jyy = _window(gy * gy, spacing) - my * my - bias
    jxx = _window(gx * gx, spacing) - mx * mx - bias
    jxy = _window(gy * gx, spacing) - my * mx
    tr, det = jxx + jyy, jxx * jyy - jxy * jxy
    root = np.sqrt(np.maximum(0.25 * tr * tr - det, 0))
    floor = _noise_lmin(spacing, highpass) * sig2
    lmin = np.maximum(0.5 * tr - root - floor, 0)
    lmax = np.maximum(0.5 * tr + root - floor, 0)
    return lmin * WINDOW_REACH**2 < lmax


#: ``observability``'s local affine bound (session 55; measured, see benchmarks/README.md, "Local
#: affine observability"): None (off), or the prior standard deviation ``s`` of each element of a
#: window's displacement gradient (px per px; see :func:`affine_lmins`). The default since session
#: 55's adoption: it flags the along-rim slides a rim's curvature was credited with
AFFINE_PRIOR = 0.01
#: with AFFINE_PRIOR: the affine map for the interior's observed share alone; the translation map
#: (``Observability.translation``) is what register() returns and every other check reads
#: (misaligned share, residual motion, the body-scale waiver, the ROIs' verdict): the whole
#: outline pins a body-scale motion no single window does
AFFINE_INTERIOR_ONLY = True


def _moment_kernel(s, a) -> np.ndarray:
    """One axis of the map's window times ``(u / s)^a`` (``u`` the offset from the window's centre,
    px), normalised by the window's sum (float32)."""
    k = _window_kernel(s)
    u = np.arange(-(len(k) // 2), len(k) // 2 + 1, dtype=np.float64) / s
    return (k * u**a / k.sum()).astype(np.float32)


def affine_lmins(gy, gx, spacing, bias, precision, step=1, project=True) -> tuple[np.ndarray, np.ndarray]:
    """``(lmin_translation, lmin_affine)``: the smaller eigenvalue of a window's information on its
    centre's translation, (1) the map's (the gradients' covariance over the window: a translation
    with an intensity offset beside it) and (2) the same translation's *marginal* information when
    the window moves by a local affine field about its centre, ``d(c + u) = t + A u`` (6
    parameters; the offset still beside): the Schur complement of ``A``'s block in the 7 x 7
    Fisher matrix, ``F_tt - F_tA (F_AA + P)^-1 F_At``. Both per unit noise variance and per unit
    window weight (the map's normalised window means), so ``window area x lmin / (2 sigma^2)`` is
    the information. ``gy, gx``: the gradients the map uses; ``bias``: the noise's share of each
    squared derivative (per pixel, each moment taking its window mean of it, or a scalar); ``precision``: ``P``'s diagonal, the prior
    precision of each element of ``A`` in units of ``(px per window sigma)^-2`` per unit window
    weight and noise variance (per pixel, or a scalar; 0: no prior). ``step``: both on every
    ``step``-th pixel from ``step // 2`` in each direction (the 6 x 6 systems cost 10x the filters
    at every pixel; the window's moments vary over its sigma, not a pixel). ``project``: an
    indefinite estimate projected onto its nearest PSD matrix (see below).

    A window moving as a whole is a translation; a field free at the window's scale moves it by a
    translation and a gradient. On a rim of radius ``R`` the window sees only the normal
    displacement along the arc, ``n(s) ~ n0 + s (t_tangential / R + A_normal,tangential) + ...``:
    the tangential translation is aliased with the displacement's tangential gradient, and its
    marginal bound is ``R`` times that gradient's (its prior's) standard deviation. A disc seen
    whole at the window's centre, a corner or a texture keep it.

    Every moment is a filtered image: ``sum_u w(u) u^a v^b h(c + u)`` is a separable filter with
    the kernel ``w(u) u^a`` along one axis and ``w(v) v^b`` along the other (``u`` in window
    sigmas, so the moments are O(1) in float32). 24 filters (three gradient products at six
    moments, two gradients at three) and a batched 4 x 4 solve."""
    import cv2

    s = float(spacing)
    ks = [_moment_kernel(s, a) for a in range(3)]
    moments = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))  # (a along y, b along x)

    def filt(h, a, b):
        out = cv2.sepFilter2D(h, cv2.CV_32F, ks[b], ks[a], borderType=cv2.BORDER_REFLECT)
        return out[o::step, o::step].astype(np.float64)

    o = step // 2
    sub = (slice(o, None, step), slice(o, None, step))

    gy, gx = np.asarray(gy, np.float32), np.asarray(gx, np.float32)
    prods = {("y", "y"): gy * gy, ("y", "x"): gy * gx, ("x", "x"): gx * gx}
    mom = {(p, ab): filt(h, *ab) for p, h in prods.items() for ab in moments}
    first = {(c, ab): filt(h, *ab) for c, h in (("y", gy), ("x", gx)) for ab in moments[:3]}
    # parameters: t_y, t_x, A_yu, A_yv, A_xu, A_xv (u along y, v along x): sensitivities g_c poly
    params = (("y", (0, 0)), ("x", (0, 0)), ("y", (1, 0)), ("y", (0, 1)), ("x", (1, 0)), ("x", (0, 1)))
    mu20 = float(ks[2].sum() * ks[0].sum())  # the window's second moment along one axis (u in sigmas)
    shape = gy[sub].shape
    # the noise's share of a weighted moment is the window's same weighted mean of the local
    # variance, not the centre's: where the noise varies across a window (a body quieter than the
    # air beside it, Poisson-like) the centre's left the louder part's excess in the moments as
    # structure, and a textureless interior beside a rim read observed
    bias_moment = {}
    if np.ndim(bias):
        b32 = np.asarray(bias, np.float32)
        bias_moment = {ab: filt(b32, *ab) for ab in ((0, 0), (2, 0), (0, 2))}
    if np.ndim(precision):
        precision = np.asarray(precision, np.float64)[sub]
    F = np.empty(shape + (6, 6))
    for i, (ci, pi) in enumerate(params):
        for j, (cj, pj) in enumerate(params):
            if j < i:
                continue
            key = (ci, cj) if (ci, cj) in prods else (cj, ci)
            ab = (pi[0] + pj[0], pi[1] + pj[1])
            v = mom[(key, ab)] - first[(ci, pi)] * first[(cj, pj)]
            if ci == cj and pi == pj:  # the noise's share of a squared derivative
                v = v - (bias_moment[ab] if bias_moment else bias * (1.0 if pi == (0, 0) else mu20))
            F[..., i, j] = F[..., j, i] = v
    eye = np.eye(4)
    prec = np.asarray(precision, np.float64)
    prec = prec[..., None, None] if prec.ndim else prec

    def schur(F, prec):
        Ftt, FtA, FAA = F[..., :2, :2], F[..., :2, 2:], F[..., 2:, 2:]
        ridge = 1e-9 * (np.trace(FAA, axis1=-2, axis2=-1)[..., None, None] + 1e-30)
        return Ftt - FtA @ np.linalg.solve(FAA + prec * eye + ridge * eye, np.swapaxes(FtA, -1, -2))

    def smaller(m, clip=True):
        tr, det = m[..., 0, 0] + m[..., 1, 1], m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] ** 2
        low = 0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0))
        return np.maximum(low, 0) if clip else low

    S = schur(F, prec)
    # an unbiased estimate of a PSD matrix is not PSD: where the window's structure is near the
    # noise's sampling error (the noise's share taken out exactly, its fluctuation left), the 6 x 6
    # matrix is indefinite and its Schur complement negative, clipped to "unobserved" (how much of
    # an object: benchmarks/README.md, session 56). There its nearest information matrix (the negative
    # eigenvalues set to 0) keeps the marginal an information's. Found where the complement is
    # negative or exceeds the translation's own block (a marginal of a PSD matrix never does); only
    # there, since a 6 x 6 eigendecomposition at every sample doubles the cost (``project``: False,
    # the clipped complement, to measure it)
    Ftt = F[..., :2, :2]
    bad = (smaller(S, clip=False) < 0) | (np.trace(S, axis1=-2, axis2=-1) > np.trace(Ftt, axis1=-2, axis2=-1))
    if project and bad.any():
        w, v = np.linalg.eigh(F[bad])
        Fp = (v * np.maximum(w, 0)[..., None, :]) @ np.swapaxes(v, -1, -2)
        S[bad] = schur(Fp, prec[bad] if np.ndim(prec) else prec)
    return smaller(Ftt), smaller(S)


def model_floor(f) -> float:
    """``MODEL_FLOOR`` of the image's range (1st to 99th percentile, from ~250k samples): the
    noise level below which nothing counts as noise (see MODEL_FLOOR)."""
    step = sample_step(f.size)
    lo, hi = np.percentile(f[::step, ::step], [1, 99])
    return MODEL_FLOOR * float(hi - lo)


def _flat(a) -> np.ndarray:
    """Where ``a`` is exactly constant over the pixel's 3 x 3 neighbourhood."""
    import cv2

    a = np.asarray(a, np.float32)
    k = np.ones((3, 3), np.uint8)
    return cv2.dilate(a, k, borderType=cv2.BORDER_REPLICATE) == cv2.erode(a, k, borderType=cv2.BORDER_REPLICATE)


#: a flat region common to both images is fixed on the detector when under this share of the ring
#: around it is flat in one image alone: a region whose edge moves with the object by a pixel or
#: more leaves a strip of that width flat in one image only (a moving body's constant interior, an
#: exact background around a moving body)
FLAT_MOVING_RING = 0.1
FLAT_MIN_PIXELS = 64  # smaller common flat patches are left alone (chance, in a quantised image)


def flat_common(fixed, moving) -> np.ndarray:
    """Where both images are exactly constant at one value over a pixel's 3 x 3 neighbourhood,
    in a region of at least ``FLAT_MIN_PIXELS`` whose edge does not move between the images
    (:data:`FLAT_MOVING_RING`): an opaque strip fixed on the detector, a range clipped in both.
    Such a region holds no structure of the object in either image, and its edge, fixed on the
    detector, pulls a field towards zero (bool)."""
    import cv2

    f, m = np.asarray(fixed, np.float32), np.asarray(moving, np.float32)
    equal = f == m
    if np.count_nonzero(equal) < FLAT_MIN_PIXELS:  # a noisy pair: 0.27 -> 0.03 s at 2240 px
        return np.zeros(f.shape, bool)
    ff, fm = _flat(f), _flat(m)
    common = ff & fm & equal
    if np.count_nonzero(common) < FLAT_MIN_PIXELS:
        return np.zeros(f.shape, bool)
    n, lab = cv2.connectedComponents(common.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    # the ring 2 px around each region, labelled by its region (the larger label where two meet)
    grown = cv2.dilate(lab.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.int64)
    ring = (grown > 0) & ~common
    n_ring = np.bincount(grown[ring], minlength=n)
    n_odd = np.bincount(grown[ring & (ff ^ fm)], minlength=n)
    area = np.bincount(lab.ravel(), minlength=n)
    keep = (area >= FLAT_MIN_PIXELS) & (n_odd <= FLAT_MOVING_RING * np.maximum(n_ring, 1))
    keep[0] = False
    return keep[lab]


def observability(
    fixed, spacing, mask=None, bound_scale=1.0, highpass=0.25, moving=None, pinned=False, affine_prior=None
) -> Observability:
    """The confidence map of registering onto ``fixed`` with a lattice ``spacing`` px apart
    (see the module docstring); ``bound_scale`` multiplies the bound (``register()`` passes the
    binning factor: the bound in full-resolution pixels). With ``moving``, the pixels where both
    images are flat at one value (:func:`flat_common`) are unobserved, whatever structure lies
    within the window's reach: that structure is the flat region's own edge, fixed on the
    detector, and it would call a band of two windows' width observed (session 41's review: 84 %
    of a 120-row band across a moving body, whose field there was worse than none). ``pinned``:
    also ``Observability.pinned`` (see the module docstring, "Where the field is pinned").
    ``affine_prior`` (None: :data:`AFFINE_PRIOR` when not :data:`AFFINE_INTERIOR_ONLY`, else off):
    also bound each window's centre under a local affine motion (:func:`_affine_info`), the map's
    information the smaller of the two, the translation's map in ``translation``. Under the
    interior-only rule the map is the translation's unless asked (register()'s checks ask, for the
    interior's share alone): it is the map register() returns."""
    f = np.asarray(fixed, np.float32)
    spacing = max(2.0, float(spacing))
    sig_map = noise_map(f, spacing)
    floor2 = model_floor(f) ** 2
    sig2 = sig_map * sig_map
    # what pure noise of this level shows as structure 99 % of the time is not information
    near = PINNED_REACH * spacing / WINDOW_REACH  # the pinned map's window (sigma, px)
    grads = _map_gradients(f, spacing, highpass, mask)  # (the affine bound's too)
    lmin, *lmin_near = _lmins(f, spacing, highpass, sig2, mask, (None, near) if pinned else (None,), grads)
    lmin = np.maximum(lmin - _noise_lmin(spacing, highpass) * sig2, 0)
    info = _window_area(spacing) * lmin / (2 * (sig2 + floor2))
    flat = flat_common(f, moving) if moving is not None else None
    prior = affine_prior
    if prior is None and not AFFINE_INTERIOR_ONLY:
        prior = AFFINE_PRIOR
    translation = None
    if prior is not None:
        translation = _confidence(info, bound_scale, flat)[0]
        # the noise's share in the gradients from an estimate a rim does not reach (the noise map
        # reads a strong rim as noise: the 6 x 6 information made indefinite)
        bias2 = robust_noise_map(f, spacing) ** 2
        info = np.minimum(info, _affine_info(grads, spacing, highpass, sig2, floor2, prior, bias2))
    conf, bound = _confidence(info, bound_scale, flat)
    pinned_conf = None
    if pinned:
        info_near = _pinned_info(lmin_near[0], near, spacing, highpass, sig2) / (2 * (sig2 + floor2))
        pinned_conf, _ = _confidence(np.minimum(info, info_near), bound_scale, flat)
    obj = _object(f, float(np.median(sig_map)))
    if mask is not None:
        obj &= np.asarray(mask, bool)
    sigma = float(np.median(sig_map[obj])) if obj.any() else float(np.median(sig_map))
    return Observability(conf, bound, sigma, obj, pinned_conf, translation)


def _affine_info(grads, spacing, highpass, sig2, floor2, prior, bias_sig2):
    """A window centre's information on its translation when the window moves by a local affine
    field (:func:`affine_lmins`), in the map's units; ``grads``: the map's (:func:`_map_gradients`);
    ``prior``: the prior standard deviation of each element of the displacement's gradient (px
    per px; a field of amplitude ``a`` and correlation length ``L`` has gradients of about
    ``a / L``). The noise-only floor is the
    translation's (:func:`_noise_lmin`): a marginal of pure noise is no larger, so this errs
    towards unobserved.

    Two noise levels, for two things. ``bias_sig2``: the pixel noise's variance,
    whose share of each squared derivative is taken out of the moments: ``E[g g^T] = T + b I``
    for the noise alone, so an estimate ``b' > b`` leaves ``T - (b' - b) D``, indefinite wherever
    ``T`` is nearly singular (a rim's rotation about its centre of curvature), and the Schur
    complement of an indefinite matrix is no information (:func:`robust_noise_map`: a rim does not
    reach it). ``sig2``: the residual's variance per pixel that the information is counted against,
    and the floor's scale: the noise map's, which at a sharp rim also holds what warping it leaves
    (interpolation error, of the order of the second difference the map reads; a sampled oblique
    edge's gradients also wobble along it by ~1e-4 of the normal's, which it absorbs), the
    translation map's own units."""
    gy, gx, inside = grads
    bias = _deriv_noise_var(1.0) * bias_sig2
    if inside is not None:
        bias = bias * inside  # (affine_lmins takes its window means: none outside the mask)
    area = _window_area(spacing)
    s2 = sig2 + floor2
    precision = 2 * s2 / (area * (float(prior) * spacing) ** 2)  # 1 / (prior x spacing)^2 in the moments' units
    step = max(1, int(spacing) // 6)
    _, la = affine_lmins(gy, gx, spacing, bias, precision, step)
    if step > 1:  # back to every pixel: the coarse samples at step // 2 + i step
        import cv2

        n0, n1 = gy.shape
        la = cv2.resize(la.astype(np.float32), (la.shape[1] * step, la.shape[0] * step), interpolation=cv2.INTER_LINEAR)
        la = np.pad(la, ((0, max(0, n0 - la.shape[0])), (0, max(0, n1 - la.shape[1]))), mode="edge")[:n0, :n1]
    la = np.maximum(la - _noise_lmin(spacing, highpass) * sig2, 0)
    return (area * la / (2 * s2)).astype(np.float32)


def _confidence(info, bound_scale, flat=None):
    """``(confidence, bound)`` float32 from a window's Fisher information ``info`` (per squared
    binned px); ``flat`` (bool): where nothing is observed (:func:`flat_common`)."""
    bound = bound_scale / np.sqrt(np.maximum(info, 1e-12))
    if flat is not None:
        bound = np.where(flat, np.float32(np.inf), bound)
    conf = 1.0 / (1.0 + (bound / OBSERVED_PX) ** 2)
    return conf.astype(np.float32), bound.astype(np.float32)


def _pinned_info(lmin_near, near, spacing, highpass, sig2):
    """The information (times ``2 sigma^2``) a window of the map's area would hold at the
    density found within :data:`PINNED_REACH` spacings of each pixel: ``lmin_near`` the
    :func:`_lmin` of the window's Gaussian shrunk to cut at that reach (sigma ``near``, ``PINNED_REACH x
    spacing / WINDOW_REACH``), less its own noise floor, scaled up to the map window's area. A
    uniform texture reads as in the full window; a pixel with no structure within the reach
    reads none, however strong an edge the full window holds."""
    lmin = np.maximum(lmin_near - _noise_lmin(spacing, highpass, window=near) * sig2, 0)
    return _window_area(spacing) * lmin


def interpolation_variance(displacement, spacing):
    """``v``: the share of white noise's variance that bilinear interpolation at ``x + d(x)``
    keeps, ``((1 - a)^2 + a^2) ((1 - b)^2 + b^2)`` with ``a``, ``b`` the fractional parts of
    ``d``, averaged over a Gaussian window of ``spacing`` px."""
    d = np.asarray(displacement, np.float32)
    a, b = d[0] - np.floor(d[0]), d[1] - np.floor(d[1])
    return _gauss(((1 - a) ** 2 + a * a) * ((1 - b) ** 2 + b * b), spacing)


def consistency(fixed, warped, spacing, sigma_map=None, noise_factor=2.0, support=None, moving=None):
    """Local mean square of the residual ``warped - fixed`` that a slow intensity change cannot
    explain, over the noise's expected share (about 1 for noise alone): ``(1 + a)^2 sigma^2 +
    (noise_factor - 1) sigma_m^2``, ``noise_factor`` 2 for two images unwarped, ``1 +
    interpolation_variance`` for a warped one; ``sigma_m`` the moving image's noise (``moving``:
    ``sigma`` times the ratio of the two images' ``noise_sigma``; without it ``sigma``). Both
    high-passed at ``spacing`` px, then, in a Gaussian window of ``spacing`` px, the part ``a``
    times the high-passed fixed image removed (a thinning or gain change locally scales the
    image's structure; a misalignment ``d . grad f`` is not proportional to it; ``a`` from
    :func:`_gain`). ``support`` (bool, optional): the residual outside it is taken as 0, so
    that what the caller's mask excludes (a collimator's static edge, which a field warps out of
    place) does not reach the windows inside it. :class:`Consistency` keeps the fixed image's
    part for several warped images."""
    return Consistency(fixed, spacing, sigma_map, moving)(warped, noise_factor, support)


# A lone line (a dead, stuck or miscalibrated detector column or row in one image of the pair):
# the residual along it stands out from its neighbours 2 px to either side by over LINE_NOISE
# noise levels, consistently (the line's mean, over a Gaussian of LINE_LENGTH px along it,
# squared, is over half its mean square: a texture's residual changes sign along any line), and
# it is one image's line: the other shows no line half as strong within LINE_SHIFT px across (a
# misaligned straight edge is a line of the residual too, but both images hold it, shifted; at
# 320 px the family's body edges, where they run along a row or column, read as lines without
# this; on the family's 27 TRAINING pairs at 560 unregistered, 25 read edge lines with 3 px, up
# to 2.2 % of the frame, two with 8 px: 0.4 % of the 4 % amplitude pair, whose edges move up to
# 22 px, and 0.02 % of another; none with the true field). Below 3 noise levels a line cannot reach the misalignment line on its own (a line is
# 1/60 of a 24 px window's weight: 3^2 / 60 is about 0.15, at the line only); above it one column
# of a body's whole line integral (~200x the noise) read 72-77 % of the object misaligned.
LINE_NOISE = 3.0
LINE_LENGTH = 6.0
LINE_SHIFT = 8


_LINE_DEV = np.array([-0.5, 0, 1, 0, -0.5], np.float32)  # a pixel less its neighbours 2 px away
_LINE_SIDE = np.array([-1, 0, 0, 0, 1], np.float32)  # its neighbour 2 px after less the one before


def _line_filter(a, axis, dev, along):
    """``a`` filtered by ``dev`` across ``axis`` (1: across columns) and ``along`` along it."""
    import cv2

    kx, ky = (dev, along) if axis == 1 else (along, dev)
    return cv2.sepFilter2D(np.asarray(a, np.float32), cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT_101)


def _line_kernel() -> np.ndarray:
    """The mean along a line: a Gaussian of ``LINE_LENGTH`` px (cut as the map's window is)."""
    g = _window_kernel(LINE_LENGTH)
    return (g / g.sum()).astype(np.float32)


def _line_mean(a, axis):
    """The mean along each line (1: each column) of ``a`` less the mean of its neighbours 2 px to
    either side across it."""
    return _line_filter(a, axis, _LINE_DEV, _line_kernel())


#: How far across (px of the checked images) a lone line's opposite-signed partner is looked for:
#: a thin feature (a wire, a plate gap) misplaced by a failed registration is a positive line of
#: the residual at one place and a negative one at the other, each image holding only its own; a
#: detector's dead line has no partner. Two opposite defects of the two images this close are rare.
LINE_PARTNER = 64


def _partnered(line, mean, axis):
    """Where a candidate lone line (``line``, its along-line mean ``mean``) has a line of the
    opposite sign and at least half its strength within :data:`LINE_PARTNER` px across ``axis``."""
    import cv2

    across = np.ones((1, 2 * LINE_PARTNER + 1) if axis == 1 else (2 * LINE_PARTNER + 1, 1), np.uint8)
    strength = np.abs(mean).astype(np.float32)
    pos = cv2.dilate(np.where(line & (mean > 0), strength, 0).astype(np.float32), across)
    neg = cv2.dilate(np.where(line & (mean < 0), strength, 0).astype(np.float32), across)
    return np.where(mean > 0, neg, pos) > 0.5 * strength


def _held(a, axis):
    """How strongly ``a`` holds a line or an edge at each pixel, across ``axis`` (1: a column):
    the larger of its line response and its step (the neighbours 2 px after less before), each
    averaged along the line."""
    k = _line_kernel()
    return np.maximum(np.abs(_line_filter(a, axis, _LINE_DEV, k)), np.abs(_line_filter(a, axis, _LINE_SIDE, k)))


def lone_lines(r, noise, images=()):
    """Pixels (bool) on a lone column or row of the residual ``r`` (see ``LINE_NOISE``), and the
    pixel on either side of it (bilinear interpolation spreads a moving image's line over two
    columns) and ``2 LINE_LENGTH`` px on along it (over its weak ends); ``noise`` the residual's
    noise standard deviation (per pixel or a number); ``images`` the pair (``r`` their
    difference): a line both hold within ``LINE_SHIFT`` px is not lone."""
    import cv2

    out = np.zeros(r.shape, bool)
    for axis in (1, 0):  # across columns (lines along y), then across rows
        mean = _line_mean(r, axis)
        line = np.abs(mean) > LINE_NOISE * noise
        if not line.any():  # nearly always: the rest is not needed
            continue
        dev = _line_filter(r, axis, _LINE_DEV, np.ones(1, np.float32))
        line &= mean * mean > 0.5 * _line_filter(dev * dev, axis, np.ones(1, np.float32), _line_kernel())
        # a line stands out on both sides alike; a step (an edge misaligned by more than
        # LINE_SHIFT: a plate's, along a row in the side view) is high on one side only, and its
        # response here is half the step, the two sides' difference the whole of it
        line &= np.abs(_line_filter(r, axis, _LINE_SIDE, _line_kernel())) < 0.5 * np.abs(mean)
        across = np.ones((1, 2 * LINE_SHIFT + 1) if axis == 1 else (2 * LINE_SHIFT + 1, 1), np.uint8)
        # what an image holds there: a line, or an edge (a step reads half its height as a line,
        # its whole height across): two straight edges a pixel or two apart leave a bar in the
        # residual that stands out on both sides like a line, but each image holds an edge there
        # (a cube's or a plate's edges along the rows; review of the merge: the golden cube's
        # misaligned edges were left out of the residual before registering)
        held = [cv2.dilate(_held(a, axis), across) for a in images]
        if held:
            line &= ~np.all([h > 0.5 * np.abs(mean) for h in held], axis=0)
        line &= ~_partnered(line, mean, axis)
        reach = 2 * int(round(2 * LINE_LENGTH)) + 1
        kernel = np.ones((reach, 3) if axis == 1 else (3, reach), np.uint8)
        out |= cv2.dilate(line.astype(np.uint8), kernel).astype(bool)
    return out


class Consistency:
    """:func:`consistency` against one fixed image: its high-pass, window power and noise map
    computed once (the checks judge the moving image and every run's warped image against it);
    ``moving``, the pair's moving image, for its noise level."""

    def __init__(self, fixed, spacing, sigma_map=None, moving=None):
        f = np.asarray(fixed, np.float32)
        self.fixed, self.spacing = f, spacing
        self.fh = f - _gauss(f, spacing)
        self.ff = _gauss(self.fh * self.fh, spacing) + 1e-30
        self.sigma = noise_map(f, spacing) if sigma_map is None else sigma_map
        # the moving image's own local noise map; None without a moving image (its noise taken
        # as the fixed image's, as before session 34)
        self.moving_sigma = None if moving is None else noise_map(np.asarray(moving, np.float32), spacing)

    def _moving_noise(self, s2):
        """The moving image's noise variance map, from the moving image itself: its local,
        Poisson-like shape and level. The fixed image's map scaled by the ratio of the two
        images' levels amplified the fixed map's texture leakage where the fixed image is the
        quieter (a stuck field hidden), and one level for the whole moving image missed the
        bright body's noise where it is the noisier (a right field distrusted; review s34-r6).
        The moving image is not yet aligned, but its map varies over the window's scale."""
        return s2 if self.moving_sigma is None else self.moving_sigma * self.moving_sigma

    def __call__(self, warped, noise_factor=2.0, support=None):
        s2 = self.sigma * self.sigma
        # the noise's expected share: the fixed image's (scaled by the gain removed, below) and
        # the warped moving image's, ``noise_factor - 1`` of its own (interpolation_variance)
        moving2 = (noise_factor - 1) * self._moving_noise(s2)
        r = np.asarray(warped, np.float32) - self.fixed
        if support is not None:
            r = np.where(support, r, np.float32(0))
        # a lone line is a defect of one image, not structure left misaligned: left out of the
        # residual and of the fixed image's part (whose high-pass it would offset over a window)
        lines = lone_lines(r, np.sqrt(s2 + moving2), (warped, self.fixed))
        if lines.any():
            r, fh, ff = _highpass_over(r, ~lines, self.spacing), *self._fixed_part(~lines)
        else:
            r, fh, ff = r - _gauss(r, self.spacing), self.fh, self.ff
        rf = _gauss(r * fh, self.spacing)
        a = _gain(rf, ff, s2, support)
        left = np.maximum(_gauss(r * r, self.spacing) - 2 * a * rf + a * a * ff, 0)
        return left / ((1 + a) ** 2 * s2 + moving2)

    def _fixed_part(self, keep):
        """The fixed image's high-pass and window power over ``keep`` only."""
        fh = _highpass_over(self.fixed, keep, self.spacing)
        return fh, _gauss(fh * fh, self.spacing) + 1e-30


# The most a local gain may scale the fixed image's structure: a thinning or an intensity change
# of up to 20 % (the bound on the slow intensity change).
MAX_GAIN = 0.2
#: the most a global gain may scale the texture by, up (1 + 1) or down (1 - 1/2): a factor of 2
MAX_GLOBAL_GAIN = 1.0


def _gain(rf, ff, s2, support=None):
    """The local gain ``a`` of the residual on the high-passed fixed image (``r ~ a fh``), from
    their window moments ``rf``, ``ff`` and the fixed image's noise variance ``s2``. The least-
    squares gain ``rf / ff`` is diluted by the fixed image's own noise, which is in both ``r`` and
    ``fh``: where that noise outweighs the texture it tends to -1 whatever the alignment, and
    takes the fixed image's whole content (noise and misaligned structure alike) out of the
    residual. So the noise's share is taken out of both moments (errors in variables). A global
    change of intensity (an exposure, a body thinner overall) is one gain over the whole image,
    any size: the median of the windows' gains where the texture outweighs the noise (over
    ``support``), bounded only to a factor of 2 either way (``MAX_GLOBAL_GAIN``); each window's
    departure from it is bounded to what a local
    thinning can do (``MAX_GAIN``). The residual's expected noise share then keeps ``(1 + a)^2``
    of the fixed image's noise."""
    num, den = rf + s2, ff - s2
    textured = den > s2
    if support is not None:
        textured &= support
    local = num / np.where(den > 0, den, 1)
    step = sample_step(local.size)
    sample = local[::step, ::step][textured[::step, ::step]]
    # an exposure or overall thinning changes the texture by a factor of 2 at most either way;
    # a gain past it is a pattern the motion inverted (a periodic one shifted by half a period
    # fits -2), not an intensity change (review s34-r6)
    g = float(np.clip(np.median(sample), -MAX_GLOBAL_GAIN / 2, MAX_GLOBAL_GAIN)) if sample.size else 0.0
    a = np.where(den > 0, local, g + np.sign(num - g * den) * MAX_GAIN)
    return np.clip(a, g - MAX_GAIN, g + MAX_GAIN).astype(np.float32)


def _highpass_over(a, keep, spacing):
    """``a`` less its Gaussian blur of ``spacing`` px, both over ``keep`` only (a normalised blur;
    0 outside ``keep``): a line left out neither leaves a notch nor offsets its neighbours."""
    k = keep.astype(np.float32)
    blur = _gauss(a * k, spacing) / np.maximum(_gauss(k, spacing), np.float32(1e-6))
    return (a - blur) * k


def _window_mean(a, window):
    """:func:`_gauss` of ``window`` px, computed on ``a`` area-averaged by ``window / 6`` and
    interpolated back: a window of 24 px varies slowly on the 4 px grid (within 0.1 % of the
    full-resolution blur), at a twentieth of the cost."""
    import cv2

    k = max(1, int(window // 6))
    rows, cols = a.shape
    if k == 1 or min(rows, cols) < 8 * k:
        return _gauss(a, window)
    small = cv2.resize(np.asarray(a, np.float32), (cols // k, rows // k), interpolation=cv2.INTER_AREA)
    return cv2.resize(_gauss(small, window / k), (cols, rows), interpolation=cv2.INTER_LINEAR)


def residual_motion(fixed, warped, window, highpass=0.25, smooth=3.0):
    """``|delta|`` per pixel (px): the displacement one Gauss-Newton (Lucas-Kanade) step on the
    residual ``warped - fixed`` would still add, fitted with a local gain in a Gaussian window of
    ``window`` px (see the module docstring, "Residual motion").

    Both images are high-passed at ``highpass x window`` and smoothed by ``smooth`` px (at the
    flag's 12 px window a band around 20 px wavelengths: a texture near the noise still
    correlates there after a misalignment of a pixel or two, and the noise is damped); in each
    window the residual is fitted as ``delta . grad f + a f + c``. The gain ``a`` takes a
    thinning or gain change, the constant ``c`` what the high-pass left of a slow one; ``delta``
    follows in closed form (the 2 x 2 Schur complement of the gain). :class:`ResidualMotion`
    keeps the fixed image's part for several warped images."""
    return ResidualMotion(fixed, window, highpass, smooth)(warped)


class ResidualMotion:
    """:func:`residual_motion` against one fixed image: its filtered image, gradient and their
    window moments (the step's 2 x 2 system) computed once; a call adds the residual's."""

    def __init__(self, fixed, window, highpass=0.25, smooth=3.0):
        self.window, self.highpass, self.smooth = window, highpass, smooth
        f = np.asarray(fixed, np.float32)
        fs = _gauss(f - _gauss(f, highpass * window), smooth)
        gy, gx = np.gradient(fs)
        self.fs, self.gy, self.gx = fs, gy, gx
        my, mx, mf = (_window_mean(a, window) for a in (gy, gx, fs))
        self.my, self.mx, self.mf = my, mx, mf
        syy, sxx, sxy = self._cov(gy, my, gy, my), self._cov(gx, mx, gx, mx), self._cov(gy, my, gx, mx)
        sff, syf, sxf = self._cov(fs, mf, fs, mf) + 1e-30, self._cov(gy, my, fs, mf), self._cov(gx, mx, fs, mf)
        # the gain eliminated: (J - c c^T / s) delta = u - c v / s
        self.jyy, self.jxx, self.jxy = syy - syf * syf / sff, sxx - sxf * sxf / sff, sxy - syf * sxf / sff
        self.syf, self.sxf, self.sff = syf, sxf, sff
        det = self.jyy * self.jxx - self.jxy * self.jxy
        # silent: no step
        self.det = np.where(np.abs(det) > 1e-12 * (self.jyy + self.jxx) ** 2 + 1e-30, det, np.inf)

    def _cov(self, a, ma, b, mb):
        """The window's covariance of ``a`` and ``b`` (window means ``ma``, ``mb``): their means
        removed, the fit's constant ``c``."""
        return _window_mean(a * b, self.window) - ma * mb

    def __call__(self, warped):
        w = np.asarray(warped, np.float32)
        r = _gauss(w - _gauss(w, self.highpass * self.window), self.smooth) - self.fs
        mr = _window_mean(r, self.window)
        ry, rx, rf = (self._cov(a, ma, r, mr) for a, ma in ((self.gy, self.my), (self.gx, self.mx), (self.fs, self.mf)))
        uy, ux = ry - self.syf * rf / self.sff, rx - self.sxf * rf / self.sff
        jyy, jxx, jxy, det = self.jyy, self.jxx, self.jxy, self.det
        return np.hypot((jxx * uy - jxy * ux) / det, (jyy * ux - jxy * uy) / det).astype(np.float32)


def affine_basis(yy, xx) -> np.ndarray:
    """(3, n) float64: 1, y and x about the centroid of the pixels ``(yy, xx)``, scaled so that a
    linear mode moves the farthest of them by 1 px."""
    cy, cx = yy.mean(), xx.mean()
    reach = max(float(np.sqrt(((yy - cy) ** 2 + (xx - cx) ** 2).max())), 1.0)
    return np.stack([np.ones(yy.size), (yy - cy) / reach, (xx - cx) / reach])


def affine_bound(f, obj, sigma, smooth=2.0) -> float:
    """How well the fixed image ``f`` determines an affine motion of the object ``obj`` (bool):
    the Cramer-Rao bound (px) of its worst-determined mode, a translation or a linear map scaled
    to move the object's farthest pixel from its centroid by 1 px. The same Fisher information as
    the map's (``grad t grad t^T / (2 sigma^2)``, the noise's own share of each pixel's tensor
    taken out), summed over the whole object instead of a window. A round body without inner
    structure determines no turn about its centre (its rim moves along itself), an ellipse no
    "elliptic rotation" and no shear along its axes: the bound there is large however sharp the
    rim, while an inclusion off the centre, or texture, pins every mode.

    ``smooth``: the gradients' Gaussian (px). A sampled rim is not band-limited, and at 1 px its
    pixel steps show a turn of a round body through aliasing that no registration's
    interpolation models (session 33: 0.14-0.4 px "determined"); at 2 px that leaves the
    structure a registration can use (benchmarks/README.md, "A textureless body turned in the
    image plane"). ``sigma``: the noise; the information is charged with it and the map's
    ``model_floor`` together, as the map's is (a noise-free image read NaN here, its silent
    body-scale field flagged). NaN for an object of under 100 pixels, or a flat image."""
    f = np.asarray(f, np.float32)
    obj = np.asarray(obj, bool)
    yy, xx = np.nonzero(obj)
    total = float(np.hypot(sigma, model_floor(f)))
    if yy.size < 100 or not total > 0:
        return float("nan")
    g = _gauss(f, smooth) if smooth > 0 else f
    gy, gx = (a[obj].astype(np.float64) for a in np.gradient(g))
    floor = _deriv_noise_var(smooth) * sigma**2
    basis = affine_basis(yy, xx)
    info = np.zeros((6, 6))
    for (i, a), (j, b) in ((p, q) for p in enumerate((gy, gx)) for q in enumerate((gy, gx))):
        tensor = a * b - (floor if i == j else 0.0)
        info[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = (basis * tensor) @ basis.T
    weakest = float(np.linalg.eigvalsh(info / (2 * total**2))[0])
    return float(1 / np.sqrt(weakest)) if weakest > 0 else float("inf")


def roi_observed(confidence, roi) -> float:
    """Fraction of ``roi`` where the motion was observed (confidence >= 0.5). ``roi``: an object
    with ``row0, row1, col0, col1`` (``radiokit.measure.ROI``), a (row0, row1, col0, col1)
    tuple, or a bool mask of the confidence map's shape.

    >>> import numpy as np
    >>> confidence = np.zeros((10, 10)); confidence[:, :5] = 1  # the left half observed
    >>> roi_observed(confidence, (0, 10, 3, 7))
    0.5
    """
    c = np.asarray(confidence)
    if isinstance(roi, np.ndarray) and roi.dtype == bool:
        if roi.shape != c.shape:
            raise ValueError(f"ROI mask {roi.shape} does not match the confidence map {c.shape}")
        sel = c[roi]
    else:
        r0, r1, c0, c1 = (roi.row0, roi.row1, roi.col0, roi.col1) if hasattr(roi, "row0") else roi
        if not (0 <= r0 < r1 <= c.shape[0] and 0 <= c0 < c1 <= c.shape[1]):
            raise ValueError(f"ROI {(r0, r1, c0, c1)} lies outside the {c.shape} confidence map")
        sel = c[r0:r1, c0:c1]
    return float(np.mean(sel >= 0.5)) if sel.size else 0.0


def _poly_basis(u, v, degree) -> np.ndarray:
    """(n_terms, n) float64: the monomials of ``(u, v)`` up to ``degree`` (none for -1)."""
    terms = [u**i * v ** (d - i) for d in range(degree + 1) for i in range(d + 1)]
    return np.stack(terms) if terms else np.zeros((0, u.size))


@dataclass
class AffineStep:
    """:func:`affine_step`'s result (px of the images given): ``largest`` and ``median`` of the
    step's displacement over the object; ``bound`` the Cramer-Rao bound of the worst-determined
    affine mode with the intensity modes eliminated (``affine_bound``'s, less what they take);
    ``score`` the step in its own scatter, ``sqrt(delta^T F delta)`` (``F`` those modes'
    information): about ``sqrt(6)`` for noise alone."""

    largest: float
    median: float
    bound: float
    score: float


def affine_step(f, w, obj, sigma, smooth=2.0, gain_degree=1, offset_degree=1) -> AffineStep:
    """One Gauss-Newton step of the residual ``w - f`` (``w`` the warped moving image) for the six
    affine modes of the object ``obj`` (bool; :func:`affine_basis`), pooled over all of it: the
    affine motion left between the images, however little of it each window shows (a turn that
    slides along a dome's rim is seen across the rim only, window by window). Both images smoothed
    by ``smooth`` px (``affine_bound``'s gradients, the noise's share of their squares taken out
    alike); the residual fitted as ``delta . grad f + a(x) f + c(x)``, the gain ``a`` and the
    offset ``c`` polynomials in space of ``gain_degree`` and ``offset_degree`` (-1: none), and
    no high-pass: a body's own slope is what shows a textureless dome's turn, and a high-passed
    gain field reads as motion (benchmarks/README.md, "A slow multiplicative field read as
    misalignment"). ``sigma``: the noise (the information charged as ``affine_bound``'s).

    A measurement, not one of the checks: on the TRAINING benches a good result's step read up to
    17 px (the family's gain and thinning fields, which no low-order gain models, look like affine
    motion of a smooth body) while no failed result the checks trusted read over 1 px
    (benchmarks/README.md, "A pooled affine step (session 50, s50aff)"). All-NaN for an object
    of under 100 pixels or a flat image."""
    f = np.asarray(f, np.float32)
    obj = np.asarray(obj, bool)
    nan = AffineStep(*(float("nan"),) * 4)
    total = float(np.hypot(sigma, model_floor(f)))
    yy, xx = np.nonzero(obj)
    if yy.size < 100 or not total > 0:
        return nan
    fs, ws = ((_gauss(a, smooth) if smooth > 0 else a) for a in (f, np.asarray(w, np.float32)))
    gy, gx = (a[obj].astype(np.float64) for a in np.gradient(fs))
    basis = affine_basis(yy, xx)
    u, v = basis[1], basis[2]
    fo = fs[obj].astype(np.float64)
    a = np.concatenate(
        [basis * gy, basis * gx, _poly_basis(u, v, gain_degree) * fo, _poly_basis(u, v, offset_degree)]
    ).T
    ata, atr = a.T @ a, a.T @ (ws - fs)[obj].astype(np.float64)
    floor = _deriv_noise_var(smooth) * sigma**2
    for i in range(2):
        ata[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] -= floor * (basis @ basis.T)
    scale = np.sqrt(np.maximum(np.diag(ata), 1e-30))  # columns of very different sizes
    try:
        inv = np.linalg.inv(ata / np.outer(scale, scale)) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return nan
    delta = (inv @ atr)[:6]
    d = np.hypot(delta[:3] @ basis, delta[3:] @ basis)
    # the affine modes' information with the intensity modes eliminated (a Schur complement)
    info = np.linalg.inv(inv[:6, :6]) / (2 * total**2)
    weakest = float(np.linalg.eigvalsh(0.5 * (info + info.T))[0])
    return AffineStep(
        largest=float(d.max()),
        median=float(np.median(d)),
        bound=float(1 / np.sqrt(weakest)) if weakest > 0 else float("inf"),
        score=float(np.sqrt(max(float(delta @ info @ delta), 0.0))),
    )
