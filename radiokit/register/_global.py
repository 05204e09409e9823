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

It is only a guess, so it is dropped when the silhouette cannot be trusted:

- the body is not wholly inside the frame (over 2 % of the frame's edge is body): a body cut
  by the frame, a chest or a textured plate, has moments of the frame's cut, not of its motion;
- either silhouette covers under 2 % or over 85 % of the frame;
- the map stretches by more than a third or shifts by more than a fifth of the frame: no
  compression step does, so the silhouettes disagree about what the body is.

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


@dataclass(frozen=True)
class Affine:
    """``x -> moving_centre + matrix (x - fixed_centre)`` in full-resolution (row, col) pixels."""

    matrix: np.ndarray
    fixed_centre: np.ndarray
    moving_centre: np.ndarray

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
            f"shift ({t[0]:+.1f}, {t[1]:+.1f}) px"
        )


def _silhouette(img):
    """``(body, factor, reason)``: the body's pixels on the image binned by ``factor``, or
    ``None`` and why not."""
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
    if edge.mean() > EDGE_SHARE:
        return None, k, f"the body is not inside the frame ({100 * edge.mean():.0f} % of the frame's edge is body)"
    n, labels, stats, _ = cv2.connectedComponentsWithStats(body.astype(np.uint8), connectivity=8)
    if n > 2:
        body = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    share = body.mean()
    if not AREA_RANGE[0] <= share <= AREA_RANGE[1]:
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
    one's (module docstring), and ``""``; or ``None`` and why it was not trusted."""
    parts = []
    for name, img in (("fixed", fixed), ("moving", moving)):
        body, k, why = _silhouette(img)
        if body is None:
            return None, f"{name}: {why}"
        parts.append(_moments(body, k))
    (cf, sf), (cm, sm) = parts
    a = _sqrtm(sm) @ np.linalg.inv(_sqrtm(sf))
    frame = float(min(np.shape(fixed)))
    stretch = np.linalg.svd(a, compute_uv=False)
    if stretch.max() > 1 + MAX_STRETCH or stretch.min() < 1 / (1 + MAX_STRETCH):
        return None, f"the silhouettes differ by a stretch of {stretch.min():.2f}-{stretch.max():.2f}"
    shift = float(np.hypot(*(cm - cf)))
    if shift > MAX_SHIFT * frame:
        return None, f"the silhouettes are {shift:.0f} px apart"
    return Affine(a, cf, cm), ""
