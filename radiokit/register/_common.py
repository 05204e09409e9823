"""Pieces every registration method shares: warping, det J, similarity measures."""

from __future__ import annotations

import numpy as np

from radiokit.checks import refuse_masked

#: OpenCV's remap asserts every side (source and map) under this, SHRT_MAX; register's MAX_SIDE is
#: one under it, and :func:`_warp_rows` samples a frame past it with scipy's bilinear
_REMAP_SIDES = 32767


def warp(image, displacement, order=1, cval=None) -> np.ndarray:
    """``image(x + d(x))`` on the displacement's grid; ``order`` 1 (bilinear, OpenCV) or 3.
    Samples outside ``image`` repeat its border, or with ``cval`` (e.g. ``np.nan``) take that
    value (``cval`` was once accepted and ignored).

    >>> import numpy as np
    >>> ramp = np.tile(np.arange(6, dtype=np.float32), (2, 1))
    >>> pull = np.zeros((2, 2, 6), np.float32); pull[1] = 2  # sample two columns to the right
    >>> warp(ramp, pull)[0].tolist()
    [2.0, 3.0, 4.0, 5.0, 5.0, 5.0]
    >>> warp(ramp, pull, cval=np.nan)[0].tolist()
    [2.0, 3.0, 4.0, 5.0, nan, nan]
    """
    refuse_masked(image, "image")
    d = _field(displacement)
    bad = d.size - int(np.count_nonzero(np.isfinite(d)))
    if bad:  # no position to sample: OpenCV gave NaN there, silently
        raise ValueError(f"displacement has {bad} non-finite value(s) (NaN or inf): no position to sample there")
    return _warp(image, d, order, cval)


def _warp(image, d, order=1, cval=None) -> np.ndarray:
    """:func:`warp` of a field ``d`` as :func:`_field` gives it, NaN or inf taken: the registration's
    own checks warp a field before they judge (and repair) a non-finite one."""
    image = np.asarray(image, np.float32)
    if image.ndim != 2:  # OpenCV took a (2, rows, cols) stack as 2 rows of many channels
        raise ValueError(f"image must be 2-D (rows, cols); got shape {image.shape}")
    return _warp_rows(image, d, 0, order, cval)


def binned_mask(fraction) -> np.ndarray:
    """A bool mask at a coarser grid, from the share of each bin it covered.

    Parameters
    ----------
    fraction : ndarray
        The mask area-averaged to the coarse grid: per bin, the share of its pixels masked
        (0 to 1).

    Returns
    -------
    ndarray of bool
        The bins over half masked, or, when no bin is, every bin the mask touches.

    Notes
    -----
    Over half keeps a broad mask's edge where it is. A mask of one row, one column or a few
    pixels (``register`` takes them, ``--roi``) covers no bin by half; without the bins it
    touches a coarse level would have no pixel to score (rc's mean over none) and the checks
    no object to judge.
    """
    kept = fraction > 0.5
    return kept if kept.any() else fraction > 0


def _warp_rows(image, d, row0, order=1, cval=None) -> np.ndarray:
    """:func:`warp` of the rows ``row0, row0 + 1, ...`` of a frame whose field there is ``d``
    (``image`` float32 and 2-D, ``d`` as :func:`_field` gives it): ``warp(image, full)[row0:row0 +
    len]`` to the bit, without the rest of the frame (a row's samples depend on its field alone)."""
    import cv2

    rows, cols = d.shape[1:]
    # pixel positions broadcast, not a frame-sized grid per axis (np.mgrid's int64 planes and
    # their conversion were most of a 2240 frame's warp); the same float32 sums
    rr = np.arange(row0, row0 + rows, dtype=np.float32)[:, None]
    cc = np.arange(cols, dtype=np.float32)[None, :]
    r, c = rr + d[0], cc + d[1]
    # OpenCV's remap asserts sides under SHRT_MAX (an 8 x 40000 strip was a cv2.error): past it,
    # scipy's bilinear, the same border (register() refuses such a pair; warp() samples it)
    if order == 1 and max(*image.shape, rows, cols) < _REMAP_SIDES:
        out = cv2.remap(image, c, r, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    else:
        from scipy import ndimage

        out = ndimage.map_coordinates(image, [r, c], order=order, mode="nearest").astype(np.float32)
    if cval is not None:  # by position, not a constant border: OpenCV blends it in at weight 0 (NaN * 0)
        out[(r < 0) | (r > image.shape[0] - 1) | (c < 0) | (c > image.shape[1] - 1)] = cval
    return out


def _field(displacement) -> np.ndarray:
    """``displacement`` as float32, checked to be ``(2, rows, cols)`` (OpenCV's per-pixel
    ``(rows, cols, 2)`` was read as 20 rows of 2 columns, silently)."""
    d = np.asarray(displacement, np.float32)
    if d.ndim != 3 or d.shape[0] != 2:
        raise ValueError(f"displacement must be (2, rows, cols) in pixels, (row, col) order; got shape {d.shape}")
    return d


def monomials(y, x, degree) -> np.ndarray:
    """``y^i x^j`` for every ``i + j <= degree``, stacked on a last axis: a polynomial's design
    matrix (the body-scale motion's and the interior thinning's)."""
    y, x = np.asarray(y, np.float64), np.asarray(x, np.float64)
    return np.stack([y**i * x**j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=-1)


def jacobian_determinant(displacement) -> np.ndarray:
    """det of the Jacobian of x -> x + d(x) per pixel (central differences, one-sided at the
    border; float32); <= 0 is a fold. Computed in row bands (each with a row of halo) on
    radiokit's threads: ``np.gradient``'s numbers, without four frame-sized temporaries (a
    tenth of ``rc fast``'s time at 2240 x 2240 otherwise)."""
    from radiokit._threads import pool, threads

    d = _field(displacement)
    rows = d.shape[1]
    out = np.empty(d.shape[1:], np.float32)

    def band(sl):
        lo, hi = max(sl.start - 1, 0), min(sl.stop + 1, rows)
        keep = slice(sl.start - lo, sl.stop - lo)  # the halo rows' one-sided differences are dropped
        drr = np.gradient(d[0, lo:hi], axis=0)[keep]
        dcr = np.gradient(d[1, lo:hi], axis=0)[keep]
        drc = np.gradient(d[0, sl], axis=1)
        dcc = np.gradient(d[1, sl], axis=1)
        drr += 1
        dcc += 1
        drr *= dcc
        drc *= dcr
        drr -= drc
        out[sl] = drr

    bands = [slice(a, min(a + 64, rows)) for a in range(0, rows, 64)]
    if len(bands) == 1 or threads() == 1:
        for b in bands:
            band(b)
    else:
        list(pool().map(band, bands))
    return out


def residual_complexity(residual, mask=None, alpha=0.05) -> float:
    """Myronenko & Song's residual complexity ``1/2 mean log(1 + (DCT r)^2 / alpha)`` of a
    residual image (outside ``mask`` set to 0), per pixel, with the orthonormal 2-D DCT (float32
    transform, float64 sum)."""
    r = np.asarray(residual, np.float32)
    if mask is not None:
        r = np.where(mask, r, np.float32(0))
    from scipy import fft as sfft  # here: importing radiokit.register is scipy-free (a refusal's cost)

    from radiokit._threads import threads

    q = sfft.dctn(r, norm="ortho", workers=threads())
    q *= q
    q *= np.float32(1.0 / alpha)
    np.log1p(q, out=q)
    return float(0.5 * np.mean(q, dtype=np.float64))


def ncc(a, b, mask=None) -> float:
    """Normalised cross-correlation of two images (inside ``mask``); 0 if either is constant."""
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    if mask is not None:
        a, b = a[mask], b[mask]
    a = (a - np.float32(a.mean(dtype=np.float64))).ravel().astype(np.float64)
    b = (b - np.float32(b.mean(dtype=np.float64))).ravel().astype(np.float64)
    den = np.sqrt(np.dot(a, a) * np.dot(b, b))
    return float(np.dot(a, b) / den) if den > 0 else 0.0
