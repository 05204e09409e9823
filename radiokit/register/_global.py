"""A global first guess for rc from the body's silhouette (option ``init="silhouette"``).

A phantom compressed between plates moves mostly as one affine map: its slab gets shorter along
the compression and wider across it. In the side view (``sim`` preset ``pva-phantom``) that is
tens of pixels at the body's ends, over a slab with no structure inside: rc's coarsest lattice,
which sees the motion only through the high-passed edges, stalls or walks the wrong way
(benchmarks/README.md, issue 11). The silhouette sees it directly. Its centroid gives the
shift and its second moments the stretch: the map ``x -> c_m + A (x - c_f)`` with
``A = S_m^(1/2) S_f^(-1/2)`` (``S`` the silhouette's covariance) takes the fixed silhouette's
moments to the moving one's. Of the maps that do, it is the one without a rotation: compression
does not turn the body, and second moments cannot tell a rotation from a stretch. The B-spline
levels then refine the field on top of it, the affine part itself never charged by the bending
energy.

But a body whose corners or off-centre inclusions do determine a turn or a shear is then
started off by all of it, and the stiff lattices keep most of that: a textureless body turned 1-8
degrees was registered 0.7-12 px off by ``silent``, and the flag trusted several
(benchmarks/bench_register_turned.py). So the moments' map is refined on the images
(:func:`refine`: Gauss-Newton over the fixed silhouette dilated by a twentieth of the frame, both
images blurred by a binned pixel, a gain and an offset each quadratic in space fitted alongside,
as a compressed body thins by +-20 % over its extent in the flag family), in two nested steps:

- the shift and the symmetric part of the linear map (five parameters, no turn), taken when the
  fit beats the moments' map's by more than the noise could: the residual's sum of squares drops
  by over ``REFINE_CHI2`` (chi-square of 5 at 0.999) times the pair's noise variance. This only
  corrects the moments (an Otsu threshold's silhouette is not affine-invariant): on the family's
  compressed bodies the start came from 0.5-3.1 px to 0.01-0.30 px of the truth;
- then all six, the turn freed, taken when the drop is over ``REFINE_TURN_F`` times what the
  fit leaves per independent residual (the residual's own variance, at least the noise's). Not
  the noise: the family's lagging inclusion and its thinning are not affine, and a turn fitted
  to them (0.1-0.8 degrees, none there) beat the noise 10-70x. On TRAINING pairs the score read
  at most 24 on the family's 20 seeds (560 px, no turn) and at least 371 for a turn or shear
  the corners or an inclusion determine (206 where the turn was none and it moved the map by
  0.08 px); the line is between (benchmarks/README.md). A round body's rim determines no turn:
  its score stays under 16.

A search of the turn alone on top of the moments' map (session 37) invented turns of 7-9
degrees on the family: the unrefined map misfits the lagging disc and the rim by more than the
turn does. Each refined map is held to the same limits as the moments'.

It is only a guess, so it is dropped when the silhouette cannot be trusted:

- the body is not wholly inside the frame (over 2 % of the frame's edge is body): a body cut
  by the frame, a chest or a textured plate, has moments of the frame's cut, not of its motion;
- either silhouette covers under 2 % or over 85 % of the frame;
- the map stretches by more than a third or shifts by more than a fifth of the frame: no
  compression step does, so the silhouettes disagree about what the body is.

A body cut by the frame keeps a start all the same where the images show its motion
(:func:`frame_cut_affine`, session 46): the same two nested refinements and tests, from no motion
(about the cut body's centroid) rather than the moments', over the fixed image's body taken
without the edge and area checks and dilated as above, less a band along the frame's edge as wide
as the dilation (where the motion carries a point out of the frame, the moving image there is its
edge replicated, not the body). No motion is kept where neither step beats it by more than the
noise could, and only the cut's refusal is overridden (not the area's, nor a flat image's).

The silhouette is Otsu's threshold of the image binned to about 0.1 Mpx and blurred by a
hundredth of the frame; the side that does not hold the frame's edge is the body (line
integrals or transmission alike), its largest connected part kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_PIXELS = 100_000  # the silhouette's moments need no more: the edge is sampled a few hundred times
EDGE_SHARE = 0.02
AREA_RANGE = (0.02, 0.85)
MAX_STRETCH = 1 / 3
MAX_SHIFT = 0.2
CUT = "the body is not inside the frame"
# the refinement (module docstring): the blur, the gain's degree and the dilation are the first
# values tried (a gain of degree 3 or 4, on three of the family's TRAINING seeds with the turn
# free, made its invented turns smaller on two and larger on one); the turn's line chosen on
# TRAINING seeds (benchmarks/README.md)
REFINE_SMOOTH = 1.0
REFINE_GAIN_DEGREE = 2
REFINE_DILATE = 0.05
REFINE_ITERATIONS = 20
REFINE_CHI2 = 20.52  # chi2(5)'s 0.999 quantile
REFINE_TURN_F = 100.0


@dataclass(frozen=True)
class Affine:
    """``x -> moving_centre + matrix (x - fixed_centre)`` in full-resolution (row, col) pixels."""

    matrix: np.ndarray
    fixed_centre: np.ndarray
    moving_centre: np.ndarray
    refined: bool = False  # the moments' map refined on the images (:func:`refine`)

    def field(self, shape, factor=1) -> np.ndarray:
        """The displacement ``(2, rows, cols)`` float32 on a grid ``factor`` times coarser than
        full resolution (pixel ``k`` at ``factor k + (factor - 1) / 2``, as the B-spline
        levels), in that grid's pixels."""
        rows, cols = shape
        y = (factor * np.arange(rows) + (factor - 1) / 2 - self.fixed_centre[0]).astype(np.float32)
        x = (factor * np.arange(cols) + (factor - 1) / 2 - self.fixed_centre[1]).astype(np.float32)
        t = (self.moving_centre - self.fixed_centre) / factor
        a = (self.matrix - np.eye(2)) / factor
        d = np.empty((2, rows, cols), np.float32)  # float32 throughout: no frame-sized doubles
        for k in range(2):
            np.multiply(np.float32(a[k, 1]), x[None, :], out=d[k])
            d[k] += (np.float32(t[k]) + np.float32(a[k, 0]) * y)[:, None]
        return d

    def describe(self) -> str:
        t = self.moving_centre - self.fixed_centre
        return (
            f"stretch {self.matrix[0, 0]:.3f} x {self.matrix[1, 1]:.3f} (shear {self.matrix[0, 1]:+.3f}), "
            f"shift ({t[0]:+.1f}, {t[1]:+.1f}) px{', refined on the images' if self.refined else ''}"
        )


def _silhouette(img, inside=True):
    """``(body, factor, reason)``: the body's pixels on the image binned by ``factor``, or
    ``None`` and why not; without ``inside`` a body cut by the frame is kept (and the share of
    the frame it covers not checked): a region to fit over, not a shape's moments."""
    import cv2
    from skimage.filters import threshold_otsu

    from radiokit.register import _bin

    k = max(1, int(np.ceil(np.sqrt(img.size / _PIXELS))))
    g = _bin(np.asarray(img, np.float32), k)
    g = cv2.GaussianBlur(g, (0, 0), max(1.0, min(g.shape) / 100))
    if not np.isfinite(g).all() or float(g.max() - g.min()) <= 0:
        return None, k, "the image is flat or not finite"
    body = g > threshold_otsu(g)
    edge = np.concatenate([body[0], body[-1], body[:, 0], body[:, -1]])
    if edge.mean() > 0.5:  # the bright side holds the frame's edge: the body is the dark side
        body = ~body
        edge = ~edge
    if inside and edge.mean() > EDGE_SHARE:
        return None, k, f"{CUT} ({100 * edge.mean():.0f} % of the frame's edge is body)"
    n, labels, stats, _ = cv2.connectedComponentsWithStats(body.astype(np.uint8), connectivity=8)
    if n > 2:
        body = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    share = body.mean()
    if not AREA_RANGE[0] <= share <= (AREA_RANGE[1] if inside else 1.0):
        return None, k, f"the body covers {100 * share:.0f} % of the frame"
    return body, k, ""


def _moments(body, k):
    """Centroid and covariance of the silhouette, in full-resolution pixels."""
    yy, xx = np.nonzero(body)
    pos = np.vstack([yy, xx]).astype(np.float64) * k + (k - 1) / 2
    # a binned pixel is a k x k square: its own second moment, k^2 / 12 per axis, belongs to the body
    return pos.mean(axis=1), np.cov(pos) + np.eye(2) * (k * k / 12)


def _sqrtm(c):
    w, v = np.linalg.eigh(c)
    return (v * np.sqrt(np.maximum(w, 0))) @ v.T


def silhouette_affine(fixed, moving) -> tuple[Affine | None, str]:
    """The affine map taking the fixed silhouette's centroid and second moments to the moving
    one's, refined on the images where that fits them better than the noise could make it
    (module docstring), and ``""``; or ``None`` and why it was not trusted."""
    parts = []
    for name, img in (("fixed", fixed), ("moving", moving)):
        body, k, why = _silhouette(img)
        if body is None:
            return None, f"{name}: {why}"
        parts.append(_moments(body, k))
    (cf, sf), (cm, sm) = parts
    a = _sqrtm(sm) @ np.linalg.inv(_sqrtm(sf))
    frame = float(min(np.shape(fixed)))
    why = _implausible(a, cf, cm, frame)
    if why:
        return None, why
    best = Affine(a, cf, cm)
    details = {}
    for turn in (False, True):  # the stretch first, then the turn on top of it (module docstring)
        refined = refine(fixed, moving, best, turn=turn, details=details)
        if refined is not None and not _implausible(refined.matrix, cf, refined.moving_centre, frame):
            best = refined
    return best, ""


def frame_cut_affine(fixed, moving) -> tuple[Affine | None, str]:
    """Where the silhouettes were refused only because the body is cut by the frame: the affine
    map refined on the images (:func:`refine`, the same two nested steps and tests) from no
    motion, over the fixed image's cut body (the frame's edge band left out); ``None`` where
    neither step fits the pair better than no motion by more than the noise could, and why
    (module docstring, "A body cut by the frame")."""
    for name, img in (("fixed", fixed), ("moving", moving)):
        why = _silhouette(img)[2]
        if why and not why.startswith(CUT):
            return None, f"{name}: {why}"
    body, k, why = _silhouette(fixed, inside=False)
    if body is None:
        return None, f"fixed: {why}"
    centre = _moments(body, k)[0]
    best = Affine(np.eye(2), centre, centre.copy())
    frame = float(min(np.shape(fixed)))
    for turn in (False, True):
        refined = refine(fixed, moving, best, turn=turn, inside=False)
        if refined is not None and not _implausible(refined.matrix, centre, refined.moving_centre, frame):
            best = refined
    if not best.refined:
        return None, "no affine map fits the pair better than no motion by more than the noise could"
    return best, ""


def _implausible(a, cf, cm, frame) -> str:
    """Why no compression step makes the map ``a`` with that shift, or ``""``."""
    stretch = np.linalg.svd(a, compute_uv=False)
    if stretch.max() > 1 + MAX_STRETCH or stretch.min() < 1 / (1 + MAX_STRETCH):
        return f"the silhouettes differ by a stretch of {stretch.min():.2f}-{stretch.max():.2f}"
    shift = float(np.hypot(*(cm - cf)))
    if shift > MAX_SHIFT * frame:
        return f"the silhouettes are {shift:.0f} px apart"
    return ""


def _solve(design, y):
    """Least squares by the normal equations, columns scaled alike (they differ by orders of
    magnitude); an SVD of the tall design took 0.5 s per solve under load."""
    scale = np.sqrt((design**2).sum(axis=0)) + 1e-30
    d = design / scale
    return np.linalg.lstsq(d.T @ d, d.T @ y, rcond=None)[0] / scale


def _refine_rss(fv, mw, poly):
    """The residual's sum of squares with the gain and offset (polynomials ``poly``) fitted, and
    the gain at each pixel."""
    design = np.concatenate([poly * mw[:, None], poly], axis=1)
    coef = _solve(design, fv)
    n = poly.shape[1]
    r = fv - design @ coef
    return float(r @ r), poly @ coef[:n]


def _significance(turn, rss0, rss, noise2, n, smooth):
    """``(score, significant)``: whether a refinement's drop in the residual's sum of squares,
    from ``rss0`` to ``rss`` over ``n`` pixels blurred by ``smooth``, is more than what it could
    fit without a motion there (module docstring)."""
    if turn:
        # against what the fit leaves, not the noise: the family's lagging inclusion and thinning
        # are not affine, and a turn fitted to them beat the noise up to 70x (module docstring);
        # the blur leaves about one independent residual per 4 pi smooth^2 pixels
        left = max(rss / (n / (4 * np.pi * smooth**2)), noise2)
        score = (rss0 - rss) / left
        significant = score > REFINE_TURN_F
    else:
        # a linear model's fit improves by about noise2 chi2(5) from the noise alone; the blur only
        # correlates it (each mode's share at most the unblurred pixel's variance), so the line holds
        score = (rss0 - rss) / max(noise2, 1e-30)
        significant = score > REFINE_CHI2
    return score, significant


def _region(body, inside):
    """The pixels :func:`refine` fits over: the (binned) body dilated by ``REFINE_DILATE`` of the
    frame; for a body cut by the frame (not ``inside``) less a band of that width along the frame's
    edge."""
    from scipy import ndimage

    reach_px = max(1, int(round(REFINE_DILATE * min(body.shape))))
    region = ndimage.binary_dilation(body, np.ones((3, 3), bool), iterations=reach_px)
    if not inside:
        # where the motion carries a point out of the frame, the moving image is its edge
        # replicated, not the body (turned TRAINING s8, a turn of 14 px at the median: the start 1.25 px off
        # without the band, 0.04 with it)
        region[:reach_px] = region[-reach_px:] = False
        region[:, :reach_px] = region[:, -reach_px:] = False
    return region


def refine(
    fixed,
    moving,
    start: Affine,
    smooth=REFINE_SMOOTH,
    gain_degree=REFINE_GAIN_DEGREE,
    details=None,
    turn=True,
    inside=True,
):
    """The affine map of ``start``'s form refined on the images themselves (a gain and an offset
    each a polynomial of ``gain_degree`` in space fitted alongside, over the fixed silhouette
    dilated by ``REFINE_DILATE`` of the frame, both images binned as the silhouette is and blurred
    by ``smooth`` binned px), by Gauss-Newton: all six parameters with ``turn``, else the shift and
    a symmetric change of the linear part. ``None`` when its fit is not better than ``start``'s by
    more than the noise (without ``turn``) or the fit's own misfit (with it) could make it (module
    docstring). ``details``: a dict, filled with what was measured under the key ``turn``."""
    from scipy import ndimage

    from radiokit.register import _bin
    from radiokit.register._common import monomials
    from radiokit.register._confidence import noise_sigma

    body, k, _ = _silhouette(fixed, inside)
    if body is None:
        return None
    f, m = (_bin(np.asarray(a, np.float32), k) for a in (fixed, moving))
    noise2 = noise_sigma(f) ** 2 + noise_sigma(m) ** 2
    fs, ms = (ndimage.gaussian_filter(a, smooth) for a in (f, m))
    # cubic splines, their coefficients computed once: linear interpolation's kinks made the steps
    # creep (each iteration's drop under the noise's variance after the first)
    gy, gx = (ndimage.spline_filter(g) for g in np.gradient(ms))
    ms = ndimage.spline_filter(ms)
    yy, xx = np.nonzero(_region(body, inside))
    if yy.size <= 6 + (gain_degree + 1) * (gain_degree + 2):  # fewer pixels than the fit's parameters
        return None  # (a frame binned to two rows keeps none once its edge band is left out)
    pos = np.vstack([yy, xx]).astype(np.float64) * k + (k - 1) / 2  # full-resolution (row, col)
    d = pos - start.fixed_centre[:, None]
    reach = max(float(np.sqrt((d**2).sum(axis=0)).max()), 1.0)
    u = d / reach
    poly = monomials(u[0], u[1], gain_degree)
    fv = fs[yy, xx].astype(np.float64)

    def sample(img, a, t):
        q = t[:, None] + a @ d
        return ndimage.map_coordinates(img, (q - (k - 1) / 2) / k, order=3, mode="nearest", prefilter=False).astype(
            np.float64
        )

    a, t = np.array(start.matrix, np.float64), np.array(start.moving_centre, np.float64)
    rss0, gain = _refine_rss(fv, sample(ms, a, t), poly)
    rss = rss0
    for _ in range(REFINE_ITERATIONS):
        mw = sample(ms, a, t)
        grads = [gain * sample(g, a, t) / k for g in (gy, gx)]  # per full-resolution px
        motion = np.concatenate([g[:, None] * np.stack([np.ones_like(g), u[0], u[1]], axis=1) for g in grads], axis=1)
        if not turn:  # the linear part's change symmetric: (1, 2) and (2, 1) together
            motion = np.concatenate([motion[:, :2], motion[:, 2:3] + motion[:, 4:5], motion[:, 3:4], motion[:, 5:]], 1)
        design = np.concatenate([motion, poly * mw[:, None], poly], axis=1)
        coef = _solve(design, fv)
        if not turn:
            coef = np.concatenate([coef[:3], coef[3:4], coef[2:3], coef[4:]])
        # the gain and offset are fitted with the step, not held: a thinning body's gain trades
        # against its stretch, and a held gain made the steps overshoot
        step = coef[:6].reshape(2, 3)
        moved = False
        for _ in range(6):
            a1 = a + step[:, 1:] / reach
            t1 = t + step[:, 0]
            rss1, gain1 = _refine_rss(fv, sample(ms, a1, t1), poly)
            if rss1 < rss:
                moved = True
                break
            step = step / 2
        if not moved:
            break
        a, t, rss, gain, drop = a1, t1, rss1, gain1, rss - rss1
        if drop < noise2:  # what is left to gain is within the noise
            break
    score, significant = _significance(turn, rss0, rss, noise2, fv.size, smooth)
    if details is not None:
        details[turn] = dict(rss0=rss0, rss=rss, noise2=noise2, n=fv.size, score=score, significant=bool(significant))
    if not significant:
        return None
    return Affine(a, start.fixed_centre, t, refined=True)
