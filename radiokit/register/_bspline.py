"""Cubic B-spline free-form deformation with residual complexity (and SSD, NCC) similarity.

The transform
-------------
Control points on a regular lattice ``spacing`` pixels apart (full resolution) carry a
displacement each; the field at pixel ``(y, x)`` is the tensor-product cubic B-spline
``d(y, x) = sum_ij B_i(y / s) B_j(x / s) c_ij``. It is evaluated as two matrix products,
``D = B_r C B_c^T`` (dense ``B_r``: rows x control rows), which BLAS runs on every core, and its
adjoint ``B_r^T G B_c`` gives the gradient with respect to the control points. The coefficients
are in full-resolution pixels at every pyramid level, so one parameter vector runs through the
whole pyramid.

The similarity
--------------
Residual complexity (Myronenko & Song, IEEE TMI 29(11) 2010): for the residual
``r = warped - fixed`` (inside the mask), ``E = 1/2 sum_i log(1 + (Q r)_i^2 / alpha)``, ``Q`` the
orthonormal 2-D DCT. A slowly varying intensity change makes ``r`` smooth, i.e. sparse in the DCT
basis, and the log barely charges a few large coefficients, so such a change costs little while
misalignment (broadband residual) costs a lot. Its gradient is
``dE/dr = Q^T (Q r / ((Q r)^2 + alpha))``; through the warp, ``dE/dd = dE/dr * grad(moving)(x + d)``.
``ssd`` (1/2 mean r^2), ``ncc`` (1 - normalised cross-correlation) and ``mi`` (negative Mattes
mutual information, 32 bins, cubic B-spline Parzen window) use the same transform.
Images are normalised by the fixed image's 1st-99th percentile range, so ``alpha`` is in those
units (MIRT's default 0.05 for images in [0, 1]).

Regularisation: ``regularisation * sum((L c)^2) / n_control``, ``L`` the discrete bending energy
of the control lattice (second differences; affine fields are free), added at every level.

Optimisation: L-BFGS (scipy) per pyramid level, coarse to fine (images halved by area averaging
until the smaller side is below ``min_size``), each level adding its own lattice on top of the
coarser ones' field, with control points ``spacing`` x max(1, factor / 2) apart: a few parameters
where the images are coarse (fast convergence of large, smooth motion, e.g. the expansion of a
textureless compressed body), fine ones only at full resolution. ``levels_skip`` stops before
the finest levels (the B-spline field is still evaluated at full resolution): the fast preset.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy import fft as sfft
from scipy.optimize import minimize

from radiokit.register import _method

__all__ = ["bspline_basis_matrix", "BSplineField"]

PRESETS = {
    # Measured on two cores, 2240^2 (this session; the issue note has the table):
    # - analytic pair (1 % displacement, 10 % smooth intensity change, noise; the generator of
    #   tests/test_register.py::_pair): default 8.3 s, end-point error median 0.19 / p95 0.61 px;
    #   fast 0.7 s, 0.57 / 2.2 px.
    # - seed-breast simulated projections 20 % -> 25 % (noise-free, textureless; truth 13 px):
    #   default 1.6 px median. Textureless interiors leave the motion to the regulariser; more
    #   coarse iterations helped most (80 -> 200 at the coarsest level: 2.4 -> 1.6 px).
    # spacing 24 px with regularisation 1e-3 beat 32 px / 1e-2 (0.7 px: too stiff). Each level's
    # lattice is spacing x max(1, factor / 2) apart (see bspline_register).
    "default": dict(spacing=24, alpha=0.05, regularisation=1e-3, iterations=(200, 80, 30, 15), min_size=160,
                    levels_skip=0),
    "fast": dict(spacing=12, alpha=0.05, regularisation=1e-3, iterations=(80,), min_size=160, levels_skip=3),
}


def bspline_basis_matrix(n_pixels, n_ctrl, spacing, factor=1, dtype=np.float32) -> np.ndarray:
    """(n_pixels, n_ctrl) cubic B-spline weights: pixel ``k`` of a grid ``factor`` times coarser
    than full resolution sits at full-resolution coordinate ``factor k + (factor - 1) / 2``;
    control point ``j`` at ``(j - 1) spacing``."""
    y = factor * np.arange(n_pixels) + (factor - 1) / 2
    t = y / spacing + 1.0
    i = np.floor(t).astype(np.int64)
    u = t - i
    w = np.stack([(1 - u) ** 3 / 6, (3 * u ** 3 - 6 * u ** 2 + 4) / 6, (-3 * u ** 3 + 3 * u ** 2 + 3 * u + 1) / 6,
                  u ** 3 / 6], axis=1)
    B = np.zeros((n_pixels, n_ctrl), dtype)
    for k in range(4):
        j = np.clip(i - 1 + k, 0, n_ctrl - 1)
        np.add.at(B, (np.arange(n_pixels), j), w[:, k])
    return B


def _laplacian(nr, nc):
    """Discrete bending energy of a control lattice as a stacked operator ``L``:
    ``||L c||^2 = sum (c_rr^2 + c_cc^2 + 2 c_rc^2)`` with second differences taken only where
    they exist, so affine fields (a uniform expansion, a shear) cost nothing."""
    def d2(n):
        if n < 3:
            return sp.csr_matrix((0, n))
        return sp.diags([np.ones(n - 2), -2 * np.ones(n - 2), np.ones(n - 2)], [0, 1, 2], shape=(n - 2, n))

    def d1(n):
        return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))

    return sp.vstack([sp.kron(d2(nr), sp.identity(nc)), sp.kron(sp.identity(nr), d2(nc)),
                      np.sqrt(2.0) * sp.kron(d1(nr), d1(nc))]).tocsr()


class BSplineField:
    """The control lattice of a ``shape`` image with control points ``spacing`` pixels apart."""

    def __init__(self, shape, spacing, dtype=np.float32):
        self.dtype = np.dtype(dtype)
        self.shape = tuple(shape)
        self.spacing = float(spacing)
        self.nr = int(math.ceil((shape[0] - 1) / spacing)) + 3
        self.nc = int(math.ceil((shape[1] - 1) / spacing)) + 3
        self.L = _laplacian(self.nr, self.nc)
        self._cache = {}

    @property
    def n_params(self):
        return 2 * self.nr * self.nc

    def matrices(self, factor):
        if factor not in self._cache:
            rows = -(-self.shape[0] // factor)
            cols = -(-self.shape[1] // factor)
            self._cache[factor] = (bspline_basis_matrix(rows, self.nr, self.spacing, factor, self.dtype),
                                   bspline_basis_matrix(cols, self.nc, self.spacing, factor, self.dtype))
        return self._cache[factor]

    def field(self, c, factor=1, shape=None):
        """Displacement (2, rows, cols) float32 at a grid ``factor`` times coarser, in *its* pixels."""
        Br, Bc = self.matrices(factor)
        C = c.reshape(2, self.nr, self.nc).astype(self.dtype)
        d = np.stack([Br @ C[k] @ Bc.T for k in range(2)]) / factor
        if shape is not None:
            d = d[:, :shape[0], :shape[1]]
        return d

    def adjoint(self, g, factor=1):
        """Gradient with respect to the coefficients of a gradient ``g`` (2, rows, cols) with
        respect to the field (in the grid's pixels)."""
        Br, Bc = self.matrices(factor)
        g = g.astype(self.dtype, copy=False)
        full = np.zeros((2, Br.shape[0], Bc.shape[0]), self.dtype)
        full[:, :g.shape[1], :g.shape[2]] = g
        return np.stack([Br.T @ full[k] @ Bc for k in range(2)]).ravel().astype(np.float64) / factor


_POOL = None


def _threads():
    import os

    return max(1, int(os.environ.get("RADIOKIT_THREADS", os.cpu_count() or 1)))


def _pool():
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=_threads(), thread_name_prefix="radiokit-register")
    return _POOL


def _downsample(img, f):
    if f == 1:
        return img
    import cv2

    rows, cols = img.shape
    R, C = -(-rows // f), -(-cols // f)
    pad = np.pad(img, ((0, R * f - rows), (0, C * f - cols)), mode="edge")
    return cv2.resize(pad, (C, R), interpolation=cv2.INTER_AREA)


def _gradient(img):
    gy = np.empty_like(img)
    gx = np.empty_like(img)
    gy[1:-1] = (img[2:] - img[:-2]) * 0.5
    gy[0], gy[-1] = img[1] - img[0], img[-1] - img[-2]
    gx[:, 1:-1] = (img[:, 2:] - img[:, :-2]) * 0.5
    gx[:, 0], gx[:, -1] = img[:, 1] - img[:, 0], img[:, -1] - img[:, -2]
    return gy, gx


class _Level:
    """Images and similarity at one pyramid level."""

    def __init__(self, fixed, moving, mask, factor, similarity, alpha):
        self.factor = factor
        self.fixed = _downsample(fixed, factor)
        self.moving = _downsample(moving, factor)
        self.mask = None if mask is None else _downsample(mask.astype(np.float32), factor) > 0.5
        self.shape = self.fixed.shape
        rr, cc = np.mgrid[0:self.shape[0], 0:self.shape[1]].astype(self.fixed.dtype)
        self.rr, self.cc = rr, cc
        self.similarity = similarity
        self.alpha = alpha
        self.n = float(self.mask.sum()) if self.mask is not None else float(self.fixed.size)

    def _bands(self):
        rows = self.shape[0]
        step = max(16, min(128, -(-rows // (4 * _threads()))))
        return [slice(a, min(a + step, rows)) for a in range(0, rows, step)]

    def _sample_band(self, d, sl, w, dy, dx):
        """Bilinear ``moving(x + d)`` and its exact derivatives along rows and columns on rows
        ``sl`` (the derivative of the interpolant itself, so the energy's gradient is exact;
        border replicated, no derivative where clamped). Numpy rather than OpenCV's remap, whose
        1/32-pixel fixed-point positions make the energy a staircase at fine scales."""
        rows, cols = self.shape
        y = self.rr[sl] + d[0, sl]
        x = self.cc[sl] + d[1, sl]
        outside_y = (y < 0) | (y > rows - 1)
        outside_x = (x < 0) | (x > cols - 1)
        np.clip(y, 0, rows - 1, out=y)
        np.clip(x, 0, cols - 1, out=x)
        y0 = np.minimum(y.astype(np.int32), rows - 2)  # the last row/column: weight 1 on the far side
        x0 = np.minimum(x.astype(np.int32), cols - 2)
        y -= y0  # b
        x -= x0  # a
        i = y0 * cols + x0
        flat = self.moving.ravel()
        I00 = flat.take(i)
        I10 = flat.take(i + 1)
        I01 = flat.take(i + cols)
        I11 = flat.take(i + cols + 1)
        I10 -= I00  # d_top
        I11 -= I01  # d_bottom
        top = I00 + x * I10
        bottom = I01 + x * I11
        np.subtract(bottom, top, out=dy[sl])
        np.multiply(y, dy[sl], out=w[sl])
        w[sl] += top
        I11 -= I10
        I11 *= y
        np.add(I10, I11, out=dx[sl])
        dy[sl][outside_y] = 0
        dx[sl][outside_x] = 0
        r = w[sl] - self.fixed[sl]
        if self.mask is not None:
            r *= self.mask[sl]
        self._r[sl] = r

    def sample(self, d):
        """``(w, dy, dx)``: the warped moving image and its derivatives, computed in row bands on
        all cores (numpy releases the GIL); ``self._r`` gets the masked residual."""
        if not hasattr(self, "_w"):
            self._w, self._dy, self._dx, self._r = (np.empty(self.shape, self.fixed.dtype) for _ in range(4))
        list(_pool().map(lambda sl: self._sample_band(d, sl, self._w, self._dy, self._dx), self._bands()))
        return self._w, self._dy, self._dx

    def energy(self, d):
        """Similarity energy and its gradient with respect to the field d (2, rows, cols)."""
        w, gy, gx = self.sample(d)
        r = self._r
        if self.similarity == "rc":
            q = sfft.dctn(r, norm="ortho", workers=-1)
            alpha = self.alpha

            def band(sl):  # in place: q -> q / (q^2 + alpha); returns the band's energy
                qs = q[sl]
                q2 = qs * qs
                e = float(np.sum(np.log1p(q2 * (1.0 / alpha)), dtype=np.float64))
                q2 += alpha
                qs /= q2
                return e

            e = 0.5 * sum(_pool().map(band, self._bands())) / self.n
            dr = sfft.idctn(q, norm="ortho", workers=-1, overwrite_x=True)
            dr *= 1.0 / self.n
        elif self.similarity == "ssd":
            e = 0.5 * float(np.sum(r * r, dtype=np.float64)) / self.n
            dr = r / self.n
        elif self.similarity == "ncc":
            sel = self.mask if self.mask is not None else np.ones(self.shape, bool)
            a = np.where(sel, w - w[sel].mean(), 0)
            b = np.where(sel, self.fixed - self.fixed[sel].mean(), 0)
            na, nb = float(np.sqrt(np.sum(a * a, dtype=np.float64))), float(np.sqrt(np.sum(b * b, dtype=np.float64)))
            if na == 0 or nb == 0:
                return 1.0, np.zeros((2,) + self.shape, self.fixed.dtype)
            c = float(np.sum(a * b, dtype=np.float64)) / (na * nb)
            e = 1.0 - c
            dr = -(b / (na * nb) - c * a / (na * na))
        elif self.similarity == "mi":
            e, dr = self._mutual_information(w)
        else:
            raise ValueError(f"unknown similarity {self.similarity!r}")
        out = np.empty((2,) + self.shape, self.fixed.dtype)
        dr = dr.astype(self.fixed.dtype, copy=False)

        def band(sl):
            g = dr[sl] * self.mask[sl] if self.mask is not None else dr[sl]
            np.multiply(g, gy[sl], out=out[0, sl])
            np.multiply(g, gx[sl], out=out[1, sl])

        list(_pool().map(band, self._bands()))
        return e, out


def _cubic_bspline(t):
    """Cubic B-spline kernel and its derivative (support |t| < 2)."""
    a = np.abs(t)
    out = np.where(a < 1, (4 - 6 * a ** 2 + 3 * a ** 3) / 6, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))
    d = np.where(a < 1, (-12 * a + 9 * a ** 2) / 6, np.where(a < 2, -3 * (2 - a) ** 2 / 6, 0.0)) * np.sign(t)
    return out, d


def _mi_setup(level, bins=32):
    sel = level.mask if level.mask is not None else np.ones(level.shape, bool)
    f = level.fixed[sel]
    lo, hi = np.percentile(level.fixed[sel], [0.5, 99.5])
    level._mi_sel = sel
    level._mi_k = np.clip(((f - lo) / max(hi - lo, 1e-12) * (bins - 1)).astype(np.int64), 0, bins - 1)
    mlo, mhi = np.percentile(level.moving, [0.5, 99.5])
    level._mi_scale = (bins - 4) / max(mhi - mlo, 1e-12)  # moving intensities -> Parzen bin units
    level._mi_lo = mlo
    level._mi_bins = bins


def _mutual_information(self, w):
    """Negative Mattes mutual information (box window on the fixed image, cubic B-spline on the
    warped one) and its derivative with respect to the warped image."""
    if not hasattr(self, "_mi_k"):
        _mi_setup(self)
    bins = self._mi_bins
    sel = self._mi_sel
    k = self._mi_k
    raw = (w[sel] - self._mi_lo) * self._mi_scale + 1.5
    t = np.clip(raw, 1.0, bins - 2.0)
    inside = (raw > 1.0) & (raw < bins - 2.0)  # clamped intensities have no derivative
    l0 = np.floor(t).astype(np.int64)
    n = float(k.size)
    P = np.zeros((bins, bins))
    weights = []
    for o in (-1, 0, 1, 2):
        b, db = _cubic_bspline(t - (l0 + o))
        weights.append((l0 + o, b, db))
        idx = k * bins + np.clip(l0 + o, 0, bins - 1)
        P.ravel()[:] += np.bincount(idx, b, minlength=bins * bins)
    P /= n
    pf = P.sum(axis=1, keepdims=True)
    pw = P.sum(axis=0, keepdims=True)
    nz = P > 0
    mi = float(np.sum(P[nz] * np.log(P[nz] / (pf @ pw)[nz])))
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.where(nz, np.log(P / np.maximum(pw, 1e-300)), 0.0)  # d MI / d P(k, l), up to terms summing to 0
    g = np.zeros(k.size)
    for l, _, db in weights:
        g += L[k, np.clip(l, 0, bins - 1)] * db
    dr = np.zeros(self.shape, self.fixed.dtype)
    dr[sel] = -(g * inside * self._mi_scale / n)
    return -mi, dr


_Level._mutual_information = _mutual_information


def _normalise(fixed, moving):
    lo, hi = np.percentile(fixed, [1, 99])
    if hi <= lo:
        lo, hi = float(fixed.min()), float(fixed.max())
    scale = 1.0 / (hi - lo)
    return ((fixed - lo) * scale).astype(np.float32), ((moving - lo) * scale).astype(np.float32)


def bspline_register(fixed, moving, mask=None, **options):
    """B-spline registration; see the module docstring. Options default to ``PRESETS[preset]``.

    BLAS is held to one thread meanwhile: its matrices here are small, and OpenBLAS's threads
    spin between calls, starving the row-band threads and L-BFGS (measured: 3.1 s -> 0.64 s for
    a 60-iteration level on two cores)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _bspline_register(fixed, moving, mask, **options)


def _bspline_register(fixed, moving, mask=None, *, similarity="rc", preset="default", spacing=None, alpha=None,
                      regularisation=None, iterations=None, min_size=None, levels_skip=None, callback=None):
    if preset not in PRESETS:
        raise ValueError(f"preset {preset!r}: expected one of {', '.join(PRESETS)}")
    o = dict(PRESETS[preset])
    for k, v in dict(spacing=spacing, alpha=alpha, regularisation=regularisation, iterations=iterations,
                     min_size=min_size, levels_skip=levels_skip).items():
        if v is not None:
            o[k] = v
    if o["spacing"] < 4:
        raise ValueError(f"spacing={o['spacing']}: control points closer than 4 pixels cannot be resolved")
    f, m = _normalise(fixed, moving)
    factors = [1]
    while min(f.shape) / (factors[-1] * 2) >= o["min_size"]:
        factors.append(factors[-1] * 2)
    factors = factors[::-1]  # coarse to fine
    skip = min(int(o["levels_skip"]), len(factors) - 1)
    run = factors[:len(factors) - skip]
    its = list(o["iterations"])
    its = (its + [its[-1]] * len(run))[:len(run)]  # coarse to fine; a small image runs the coarse budgets
    lam = float(o["regularisation"])
    total_its = 0
    converged = True
    message = ""
    history = []
    grids = []  # (BSplineField, coefficients): one lattice per level, spacing halving with the pixels
    for factor, n_it in zip(run, its):
        level = _Level(f, m, mask, factor, similarity, o["alpha"])
        base = np.zeros((2,) + level.shape, np.float32)
        for g_, c_ in grids:  # the coarser lattices' field, fixed at this level
            base += g_.field(c_, factor, level.shape)
        grid = BSplineField(f.shape, o["spacing"] * max(1, factor // 2))
        L = grid.L
        npts = grid.nr * grid.nc

        def fun(x, level=level, grid=grid, L=L, npts=npts, base=base):
            d = grid.field(x, factor, level.shape)
            d += base
            e, g = level.energy(d)
            grad = grid.adjoint(g, factor)
            X = x.reshape(2, -1)
            LX = np.stack([L @ X[0], L @ X[1]])
            e += lam * float(np.sum(LX * LX)) / npts
            grad += (2 * lam / npts) * np.concatenate([L.T @ LX[0], L.T @ LX[1]])
            return e, grad

        trace = []

        def track(intermediate_result):  # scipy passes the iterate by this name (sole parameter)
            trace.append(float(intermediate_result.fun))

        res = minimize(fun, np.zeros(grid.n_params), jac=True, method="L-BFGS-B", callback=track,
                       options=dict(maxiter=int(n_it), maxcor=10, gtol=1e-9, ftol=1e-10))
        if not np.all(np.isfinite(res.x)):
            return np.zeros((2,) + f.shape, np.float32), dict(iterations=total_its, converged=False,
                                                              message="optimiser produced non-finite values",
                                                              regularisation=lam)
        grids.append((grid, res.x))
        total_its += int(res.nit)
        history.append(dict(factor=factor, spacing=grid.spacing, iterations=int(res.nit), energy=float(res.fun),
                            status=int(res.status)))
        if callback is not None:
            callback(factor, res)
        if factor == run[-1]:
            message = str(res.message)
            # L-BFGS stops on its tolerances (0), at the precision limit of the line search (2), or
            # at the iteration budget (1): the last is "not converged" only if the last 5
            # iterations still gained more than 5 % of what the whole level gained
            converged = res.status in (0, 2)
            if res.status == 1 and len(trace) > 6:
                converged = (trace[-6] - trace[-1]) <= 0.05 * max(trace[0] - trace[-1], 0.0)
            if res.status == 1 and not converged:
                message = f"still improving after {res.nit} iterations at the finest level run (raise iterations)"
    d = np.zeros((2,) + f.shape, np.float32)
    for g_, c_ in grids:  # B-splines are defined everywhere: full resolution even if levels were skipped
        d += g_.field(c_, 1, f.shape)
    return d, dict(iterations=total_its, converged=converged, message=message, regularisation=lam,
                   levels=history, options=o)


@_method("rc")
def _rc(fixed, moving, mask, **options):
    """Residual complexity B-spline (the paper's method). Options: preset ('default', 'fast'),
    spacing (px), alpha, regularisation, iterations (per level, coarse to fine), min_size,
    levels_skip."""
    return bspline_register(fixed, moving, mask, similarity="rc", **options)


@_method("ssd")
def _ssd(fixed, moving, mask, **options):
    """Sum of squared differences, same B-spline transform and options as 'rc' (alpha unused)."""
    return bspline_register(fixed, moving, mask, similarity="ssd", **options)


@_method("mi")
def _mi(fixed, moving, mask, **options):
    """Mattes mutual information (32 bins), same B-spline transform and options as 'rc'."""
    return bspline_register(fixed, moving, mask, similarity="mi", **options)


@_method("ncc")
def _ncc(fixed, moving, mask, **options):
    """Normalised cross-correlation, same B-spline transform and options as 'rc'."""
    return bspline_register(fixed, moving, mask, similarity="ncc", **options)
