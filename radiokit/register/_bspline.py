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
units (MIRT's default is 0.05 for images in [0, 1]; ours 0.005, see PRESETS), then high-passed
(``highpass``: minus a Gaussian blur of 2 % of the frame): what is slower than that is the
body's smooth thickness and the intensity change, which observe no motion residual complexity
can tell from an intensity change.

Regularisation: ``regularisation * sum((L c)^2) / n_control``, ``L`` the discrete bending energy
of the control lattice (second differences; affine fields are free), added at every level.

Optimisation: L-BFGS (scipy) per pyramid level, coarse to fine (images halved by area averaging
until the smaller side is below ``min_size``), each level adding its own lattice on top of the
coarser ones' field, with control points ``spacing`` x max(1, factor / 2) apart: a few parameters
where the images are coarse (fast convergence of large, smooth motion, e.g. the expansion of a
textureless compressed body), fine ones only at the finest level. Where the structure is weak but there (texture near the
noise level), ``coarse_adapt=True`` runs the levels before the finest with a smaller alpha and a
much weaker bending energy (see PRESETS): they must capture the motion that the finest lattice,
pinned by little data, cannot (an option: it fails on simulated textureless bodies). Levels of more than
``max_pixels`` pixels are not run, and ``levels_skip`` stops that many levels earlier still
(the B-spline field is evaluated at full resolution all the same): the default preset works
up to about 1400 x 1400 pixels, the fast one up to about 300 x 300.
"""
from __future__ import annotations

import collections
import math

import numpy as np
import scipy.sparse as sp
from scipy import fft as sfft
from scipy.optimize import minimize

from radiokit.register import _method

__all__ = ["bspline_basis_matrix", "BSplineField"]

PRESETS = {
    # Chosen by benchmark (benchmarks/bench_register.py; regdata.analytic_pair at 2240 x 2240,
    # 1 % displacement, 10 % intensity change, 1 % noise, two cores; the issue note has the
    # tables). End-point error median / p95 inside the body, thinning pair then gain pair:
    # - alpha 0.005 (was MIRT's 0.05): the energy comes closer to counting DCT coefficients, so a
    #   smooth intensity change near the body's steep edge costs less than shifting the edge to
    #   explain it -- where the remaining error is (0.04 px in the body's core, 0.3-0.6 px at its
    #   edge). At 1120: 0.077 / 0.31 against 0.106 / 0.58 px.
    # - levels of more than max_pixels are not run (the field is still evaluated at full
    #   resolution): the 24 px lattice is 12 pixels of the half-resolution image, and at 2240
    #   the full-resolution level cost 4 s for 0.005 px of median; that time goes into coarse
    #   iterations instead (p95 0.85 -> 0.56 px).
    # - regularisation 3e-3: 0.082 / 0.62 and 0.041 / 0.21 px, against 1e-2: 0.093 / 0.56 and
    #   0.054 / 0.37, and 1e-3: 0.105 / 0.69 and 0.047 / 0.19.
    # - spacing 24 px beat 16 px and 32 px (too coarse: 0.30 / 1.4 px at 1120).
    # - converge_px: the finest level is "converged" when its last 5 iterations moved the field
    #   by less than 0.25 px (99th percentile); on these pairs they move 0.1 px.
    # - iterations (250, 120, 60): 8.7 s at 2240, the same error as (300, 150, 80) in 10.7 s.
    # - highpass 0.02 (issue 11; benchmarks/regdata.family, training seeds): both images minus
    #   their Gaussian blur of 2 % of the frame before the similarity, and regularisation 1e-3
    #   (was 3e-3 without it). On a nearly textureless gel phantom the body's smooth chord and
    #   the slow intensity change dominate the residual and the texture's pull on the field is
    #   tiny against a bending energy tuned on rich texture; removing the slow part leaves rc
    #   the structure that observes the motion (texture, the inclusion's and the body's edges).
    #   560 px, texture = noise to 10x noise, 2 seeds: EPE / identity geometric mean 0.40 -> 0.29
    #   (0.25 with 3e-4, which loses rich texture: 0.11 px at 2240); 1120: tex 3x noise 1.61
    #   -> 0.78 px; analytic_pair 2240 (rich): 0.077 / 0.060 px median (thinning / gain).
    # - adapt=True (an option, off by default; issue 11): alpha and regularisation divided by
    #   the image's "weakness", (median Cramer-Rao bound of the lattice windows / 0.02 px)^2
    #   clipped to 1-10 (_weakness): 1 on rich texture (analytic_pair 1120/2240: unchanged by
    #   construction), up to 10 where the texture is at the noise level. 560 family, training
    #   seeds 0-1: geometric mean 0.285 -> 0.24 (texture 3x noise, 1/10: 0.93 -> 0.38 px; no
    #   texture: worse); 2240, texture = noise: 4.77 -> 2.38 px (training seed 1), test seeds
    #   1000-1002: 4.94/5.87/3.70 -> 2.33/2.18/1.99 px. Not the default: on the textureless
    #   simulated cube of tests/test_pipeline.py it doubles the ROI error (0.62 px) -- a silent
    #   body wants the strong bending energy that weak texture does not.
    #   converge_px 0.35 (was 0.25): the weaker bending energy converges more slowly; the
    #   1120 analytic thinning pair (0.073 px median) still moved 0.27 px in its last 5 steps.
    #   finest level 80 iterations (was 60): at 60, the textureless cube of tests/test_pipeline.py
    #   sat on the converge_px boundary, so float32 rounding in the correction flipped its flag;
    #   costs about 0.8 s at 2240 (benchmarks/README.md), accuracy unchanged.
    # - coarse_adapt=True (issue 11, session 2): every level but the finest runs with alpha /
    #   relax^1.5 and the regularisation / relax^2.5, relax the image's weakness clipped to 1-10,
    #   gated (_coarse_relax): none for rich texture (unchanged by construction), for the
    #   noise-free textureless cube of tests/test_pipeline.py, or where nothing is observed.
    #   Why: at 2240 on weak texture the coarsest level (280 px) stalled (training seed 1:
    #   identity 6.69 -> 5.43 px after it, 4.77 final) and the finer lattices added little;
    #   with the coarse levels relaxed it alone reaches 1.0-1.4 px. The coefficients are in
    #   full-resolution pixels, so a 2240 frame's coarse levels carry 4x the bending energy of
    #   the same images at 1120. Exponents (training seed 1, 2240): 1.5/2.5 1.27 px, 1/2 1.60,
    #   1/1 2.40. 2240 training seeds, texture = noise / 2x noise: 4.77 -> 1.27, 3.48 -> 0.98 px;
    #   test seeds 1000-1002: 4.94/5.87/3.70 -> 1.30/1.40/1.10 px. 560 family training seeds
    #   (texture > 0, 2 seeds): EPE/identity geometric mean 0.43 -> 0.35 (texture 3x noise,
    #   correlation 1/10: 0.93 -> 0.38 px; correlation 1/4 loses: 0.20 -> 0.35 px).
    #   An option, not the default: on the simulated seed-breast pair (sim_pair, noisy; no
    #   texture, photon noise, weakness 27 on the binned pair) it wanders: 560 px 0.60 -> 1.84 px
    #   (bench_register's family run), 1120 px 2.88 -> 17.7 px; the weakness does not tell the
    #   family's weak texture from a simulated body's silence.
    "default": dict(spacing=24, alpha=0.005, regularisation=1e-3, iterations=(250, 120, 80), min_size=160,
                    max_pixels=2_000_000, levels_skip=0, converge_px=0.35, min_levels=3, coarse_alpha=1.0,
                    highpass=0.02, adapt=False, coarse_adapt=False),
    # levels of up to 100 kpx (at 2240: 140 and 280 px): 0.83-0.97 s at 2240, 0.20 / 0.96 and
    # 0.09 / 0.56 px (iterations (80, 40): 0.9-1.0 s, 0.21 / 0.94 and 0.09 / 0.48); regularisation 1e-3 against 1e-2: 0.60 / 3.6 px (the coarse lattice
    # needs the freedom); spacing 16 against 12: 0.21 / 0.94 against 0.16 / 1.2 px, 30 % faster.
    # coarse_adapt=True (its coarse level at 2240 is 140 px): 2240 training seeds, texture = noise /
    # 2x noise: 5.71 -> 2.87, 7.25 -> 5.23 px; 560 family training seeds (texture > 0, 2 seeds):
    # geomean EPE/identity 0.355 -> 0.299; analytic_pair 2240 unchanged (0.095 / 0.102 px).
    "fast": dict(spacing=16, alpha=0.005, regularisation=1e-3, iterations=(60, 40), min_size=96,
                 max_pixels=100_000, levels_skip=0, converge_px=0.5, min_levels=1, coarse_alpha=1.0,
                 highpass=0.02, adapt=False, coarse_adapt=False),
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
            Br = sp.csr_matrix(bspline_basis_matrix(rows, self.nr, self.spacing, factor, self.dtype))
            Bc = sp.csr_matrix(bspline_basis_matrix(cols, self.nc, self.spacing, factor, self.dtype))
            self._cache[factor] = (Br, Bc, Br.T.tocsr(), Bc.T.tocsr())
        return self._cache[factor]

    def field(self, c, factor=1, shape=None):
        """Displacement (2, rows, cols) float32 at a grid ``factor`` times coarser, in *its* pixels."""
        Br, Bc, _, _ = self.matrices(factor)
        C = c.reshape(2, self.nr, self.nc).astype(self.dtype)
        # D = Br C Bc^T with the sparse (4 per row) basis: 3-5x faster than dense BLAS at 2240
        d = np.stack([Br @ np.ascontiguousarray((Bc @ C[k].T).T) for k in range(2)])
        d *= np.float32(1.0 / factor)
        if shape is not None:
            d = d[:, :shape[0], :shape[1]]
        return d

    def adjoint(self, g, factor=1):
        """Gradient with respect to the coefficients of a gradient ``g`` (2, rows, cols) with
        respect to the field (in the grid's pixels)."""
        _, _, BrT, BcT = self.matrices(factor)
        g = g.astype(self.dtype, copy=False)
        rows, cols = g.shape[1:]
        # Br^T G Bc = (Bc^T (Br^T G)^T)^T, over the rows and columns the image has (a cropped
        # grid's missing pixels contribute nothing)
        out = np.stack([(BcT[:, :cols] @ (BrT[:, :rows] @ g[k]).T).T for k in range(2)])
        return out.ravel().astype(np.float64) / factor


def _threads():
    from radiokit._threads import threads

    return threads()


def _pool():
    from radiokit._threads import pool  # the one pool of radiokit's parallel loops

    return pool()


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
        if rows * self.shape[1] < 200_000:  # threads cost more than they gain
            return [slice(0, rows)]
        step = max(16, min(128, -(-rows // (4 * _threads()))))
        return [slice(a, min(a + step, rows)) for a in range(0, rows, step)]

    def _map(self, fn):
        """``fn(band)`` over the row bands, on the thread pool when there are several."""
        bands = self._bands()
        if len(bands) == 1 or _threads() == 1:  # one thread (a Dask worker): the bands in turn, in
            return [fn(b) for b in bands]  # cache (whole-frame temporaries: more CPU, page faults)
        return list(_pool().map(fn, bands))

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
        self._map(lambda sl: self._sample_band(d, sl, self._w, self._dy, self._dx))
        return self._w, self._dy, self._dx

    def energy(self, d):
        """Similarity energy and its gradient with respect to the field d (2, rows, cols)."""
        w, gy, gx = self.sample(d)
        r = self._r
        if self.similarity == "rc":
            q = sfft.dctn(r, norm="ortho", workers=_threads())
            alpha = self.alpha

            def band(sl):  # in place: q -> q / (q^2 + alpha); returns the band's energy
                qs = q[sl]
                q2 = qs * qs
                e = float(np.sum(np.log1p(q2 * (1.0 / alpha)), dtype=np.float64))
                q2 += alpha
                qs /= q2
                return e

            e = 0.5 * sum(self._map(band)) / self.n
            dr = sfft.idctn(q, norm="ortho", workers=_threads(), overwrite_x=True)
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

        self._map(band)
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
    step = max(1, int(np.sqrt(fixed.size / 250_000)))  # percentiles from ~250k samples
    lo, hi = np.percentile(fixed[::step, ::step], [1, 99])
    if hi <= lo:
        lo, hi = float(fixed.min()), float(fixed.max())
    scale = 1.0 / (hi - lo)
    return ((fixed - lo) * scale).astype(np.float32), ((moving - lo) * scale).astype(np.float32)


def _highpass(img, sigma):
    """``img`` minus its Gaussian blur of ``sigma`` px (the blur computed on a grid ``sigma / 8``
    times coarser: it is wide, and 20x cheaper at 2240)."""
    import cv2

    k = max(1, int(sigma / 8))
    small = _downsample(img, k)
    blur = cv2.GaussianBlur(small, (0, 0), sigma / k, borderType=cv2.BORDER_REFLECT)
    if k > 1:
        blur = cv2.resize(blur, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    return (img - blur).astype(np.float32)


def _weakness(fixed, mask, adapt, ref_px=0.02, most=10.0):
    """How much weaker than rich texture the fixed image's structure is: ``(b / ref_px)^2``
    clipped to [1, ``most``], ``b`` the median Cramer-Rao bound of the lattice-scale windows over
    the object (``radiokit.register._confidence``; on the pair binned to ~0.4 Mpx). alpha and the
    regularisation are divided by it, so the similarity keeps its pull against the bending
    energy where the texture is at the noise level; 1 (no change) for rich texture."""
    if not adapt:
        return 1.0
    from radiokit.register import _bin
    from radiokit.register._confidence import observability

    k = max(1, int(np.ceil(np.sqrt(fixed.size / 400_000))))
    mk = None if mask is None else _bin(mask.astype(np.float32), k) > 0.5
    ob = observability(_bin(fixed, k), 24.0, mk)
    if not ob.object.any():
        return 1.0
    b = float(np.median(ob.bound_px[ob.object]))
    return float(np.clip((b / ref_px) ** 2, 1.0, most))


_RELAX_ALPHA, _RELAX_REG = 1.5, 2.5


def _fade(x, lo, hi):
    """0 below ``lo``, 1 above ``hi``, log-linear between."""
    return float(np.clip(np.log(x / lo) / np.log(hi / lo), 0.0, 1.0))


def _coarse_relax(raw, per_pixel, most=10.0, weak=(3.0, 6.0), silent=(150.0, 450.0)):
    """How much to relax the coarse levels: ``min(raw, most)``, ``raw`` the weakness
    (``_weakness`` unclipped, on the pair binned to ~0.4 Mpx), where the structure is weak but
    there. The gates use ``per_pixel``, the same weakness at full resolution: faded (log-
    linearly) to 1 below ``weak[0]`` (richer structure, and the noise-free textureless cube of
    tests/test_pipeline.py, 2.2, whose silent interior wants the strong bending energy: ROI EPE
    0.33 -> 0.88 px relaxed) and above ``silent[1]``, where the windows observe nothing (no
    texture: a free coarse field wanders; 560 family training seeds: EPE 2.7 -> 3.7 px against
    an identity of 2.5)."""
    r = min(max(raw, 1.0), most)
    return float(r ** (_fade(per_pixel, *weak) * (1.0 - _fade(per_pixel, *silent))))


def bspline_register(fixed, moving, mask=None, **options):
    """B-spline registration; see the module docstring. Options default to ``PRESETS[preset]``.

    BLAS is held to one thread meanwhile: its matrices here are small, and OpenBLAS's threads
    spin between calls, starving the row-band threads and L-BFGS (measured: 3.1 s -> 0.64 s for
    a 60-iteration level on two cores)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _bspline_register(fixed, moving, mask, **options)


def _bspline_register(fixed, moving, mask=None, *, similarity="rc", preset="default", spacing=None, alpha=None,
                      regularisation=None, iterations=None, min_size=None, max_pixels=None, levels_skip=None, converge_px=None,
                      min_levels=None, coarse_alpha=None, coarse_regularisation=None, highpass=None,
                      adapt=None, coarse_adapt=None, callback=None):
    if preset not in PRESETS:
        raise ValueError(f"preset {preset!r}: expected one of {', '.join(PRESETS)}")
    o = dict(PRESETS[preset])
    for k, v in dict(spacing=spacing, alpha=alpha, regularisation=regularisation, iterations=iterations,
                     min_size=min_size, max_pixels=max_pixels, levels_skip=levels_skip,
                     converge_px=converge_px, min_levels=min_levels, coarse_alpha=coarse_alpha,
                     coarse_regularisation=coarse_regularisation, highpass=highpass, adapt=adapt,
                     coarse_adapt=coarse_adapt).items():
        if v is not None:
            o[k] = v
    if o["spacing"] < 4:
        raise ValueError(f"spacing={o['spacing']}: control points closer than 4 pixels cannot be resolved")
    raw = _weakness(fixed, mask, o.get("adapt") or o.get("coarse_adapt"), most=np.inf)
    weak = float(np.clip(raw, 1.0, 10.0))
    if o.get("adapt"):
        o["alpha"] /= weak
        o["regularisation"] /= weak
    if o.get("coarse_adapt"):
        # the gates in full-resolution terms: the bound was measured on the pair binned by k
        # (noise variance / k^2), so a pixel's own weakness is raw k^2
        k = max(1, int(np.ceil(np.sqrt(fixed.size / 400_000))))
        relax = _coarse_relax(raw, raw * k * k)
        o["coarse_alpha"] = o.get("coarse_alpha", 1.0) * relax ** -_RELAX_ALPHA
        o["coarse_regularisation"] = o.get("coarse_regularisation", 1.0) * relax ** -_RELAX_REG
    f, m = _normalise(fixed, moving)
    if o.get("highpass"):
        f, m = _highpass(f, o["highpass"] * min(f.shape)), _highpass(m, o["highpass"] * min(f.shape))
    factors = [1]
    while min(f.shape) / (factors[-1] * 2) >= o["min_size"]:
        factors.append(factors[-1] * 2)
    # small images: at least min_levels levels while the coarsest keeps 128 pixels (a 560 px
    # frame with a few pixels of motion needs its 140 px level: EPE 2.0 -> 0.3 px on a
    # simulated cube, tests/test_pipeline.py)
    while len(factors) < o["min_levels"] and min(f.shape) / (factors[-1] * 2) >= 128:
        factors.append(factors[-1] * 2)
    factors = factors[::-1]  # coarse to fine
    # levels with more than max_pixels pixels are not run (at least the coarsest is)
    size = f.shape[0] * f.shape[1]
    run = [k for k in factors if size / (k * k) <= o["max_pixels"]] or factors[:1]
    skip = min(int(o["levels_skip"]), len(run) - 1)
    run = run[:len(run) - skip]
    its = list(o["iterations"])
    its = (its + [its[-1]] * len(run))[:len(run)]  # coarse to fine; a small image runs the coarse budgets
    lam = lam_fine = float(o["regularisation"])
    total_its = 0
    converged = True
    message = ""
    history = []
    grids = []  # (BSplineField, coefficients): one lattice per level, spacing halving with the pixels
    for factor, n_it in zip(run, its):
        # coarse levels with a larger alpha (closer to SSD: a large coherent shift of smooth
        # structure is not explained away as intensity change), the finest with alpha itself
        alpha = o["alpha"] * (o["coarse_alpha"] if factor != run[-1] else 1.0)
        lam = lam_fine * (o.get("coarse_regularisation", 1.0) if factor != run[-1] else 1.0)
        level = _Level(f, m, mask, factor, similarity, alpha)
        base = np.zeros((2,) + level.shape, np.float32)
        for g_, c_ in grids:  # the coarser lattices' field, fixed at this level
            base += g_.field(c_, factor, level.shape)
        grid = BSplineField(f.shape, o["spacing"] * max(1, factor // 2))
        L = grid.L
        npts = grid.nr * grid.nc

        def fun(x, level=level, grid=grid, L=L, npts=npts, base=base, lam=lam, factor=factor):
            d = grid.field(x, factor, level.shape)
            d += base
            e, g = level.energy(d)
            grad = grid.adjoint(g, factor)
            X = x.reshape(2, -1)
            LX = np.stack([L @ X[0], L @ X[1]])
            e += lam * float(np.sum(LX * LX)) / npts
            grad += (2 * lam / npts) * np.concatenate([L.T @ LX[0], L.T @ LX[1]])
            return e, grad

        last = collections.deque(maxlen=6)  # the last iterates, for the convergence test

        def track(intermediate_result):  # scipy passes the iterate by this name (sole parameter)
            last.append(intermediate_result.x.copy())  # noqa: B023 (this level's deque, used before the next)

        res = minimize(fun, np.zeros(grid.n_params), jac=True, method="L-BFGS-B", callback=track,
                       options=dict(maxiter=int(n_it), maxcor=10, gtol=1e-9, ftol=1e-10))
        if not np.all(np.isfinite(res.x)):
            return np.zeros((2,) + f.shape, np.float32), dict(iterations=total_its, converged=False,
                                                              message="optimiser produced non-finite values",
                                                              regularisation=lam_fine)
        grids.append((grid, res.x))
        total_its += int(res.nit)
        # how far the last 5 iterations moved the field: 99th percentile of |change|, full-
        # resolution pixels (evaluated on the coarsest grid: the field is smooth on it)
        move = float("inf")
        if len(last) == last.maxlen:
            k = run[0]
            change = grid.field(last[-1] - last[0], k) * k
            move = float(np.percentile(np.sqrt((change * change).sum(axis=0)), 99))
        history.append(dict(factor=factor, spacing=grid.spacing, iterations=int(res.nit), energy=float(res.fun),
                            status=int(res.status), last_move_px=move))
        if callback is not None:
            callback(factor, res)
        if factor == run[-1]:
            message = str(res.message)
            # L-BFGS stops on its tolerances (0), at the precision limit of the line search (2), or
            # at the iteration budget (1): the last is "not converged" if the last 5 iterations
            # still moved the field by more than converge_px (99th percentile)
            converged = res.status in (0, 2) or move <= o["converge_px"]
            if not converged:
                message = (f"still moving: {move:.2g} px in the last 5 of {res.nit} iterations at the finest level "
                           f"run (more than converge_px={o['converge_px']}; raise iterations)")
    d = np.zeros((2,) + f.shape, np.float32)
    for g_, c_ in grids:  # B-splines are defined everywhere: full resolution even if levels were skipped
        d += g_.field(c_, 1, f.shape)
    return d, dict(iterations=total_its, converged=converged, message=message, regularisation=lam_fine,
                   levels=history, options=o)


@_method("rc")
def _rc(fixed, moving, mask, **options):
    """Residual complexity B-spline (the paper's method). Options: preset ('default', 'fast'),
    spacing (px), alpha, regularisation, iterations (per level, coarse to fine), min_size (px,
    the coarsest level's smaller side), min_levels (at least this many levels while the coarsest
    keeps 128 px), max_pixels (finer levels are not run), coarse_alpha (alpha x this at every
    level but the finest: closer to SSD there; 1 by default), levels_skip, converge_px (the
    finest level run is converged when its last 5 iterations moved the field less than this, in
    pixels, 99th percentile), highpass (fraction of the smaller side: both images minus their
    Gaussian blur of that width before the similarity; 0 or None: off), adapt (divide alpha and
    the regularisation by how much weaker than rich texture the image's structure is),
    coarse_regularisation (the regularisation x this at every level but the finest),
    coarse_adapt (relax alpha and the regularisation of every level but the finest by the
    image's weakness where the structure is weak but there; off by default)."""
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
