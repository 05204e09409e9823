"""Cubic B-spline free-form deformation with residual complexity (and SSD, NCC) similarity.

The transform
-------------
Control points on a regular lattice ``spacing`` pixels apart (full resolution) carry a
displacement each; the field at pixel ``(y, x)`` is the tensor-product cubic B-spline
``d(y, x) = sum_ij B_i(y / s) B_j(x / s) c_ij``. It is evaluated as two matrix products,
``D = B_r C B_c^T`` (sparse ``B_r``: rows x control rows, 4 weights a row), and its
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
units (MIRT's default is 0.05 for images in [0, 1]; ours 0.005, see PRESETS).

An unbiased data term (issue 11; each part's effect measured in benchmarks/README.md, "The data
term's bias"). At the true field the data term must be smallest; on a weak-texture phantom
three things moved its minimum off the truth by more than the texture could pull it back:

- *The high-pass* (``highpass``: what is slower than a Gaussian of 2 % of the frame is the
  body's smooth thickness and the intensity change, which observe no motion residual complexity
  can tell from an intensity change). Applied to each image it does not commute with a
  non-uniform warp: the blurred body moves with the field averaged over the blur, so the two
  high-passed images disagree at the truth. ``highpass_on="residual"`` (every preset) applies
  it to the residual instead, as the DCT's diagonal ``1 - exp(-sigma^2 omega^2 / 2)`` (the
  Gaussian's response under the DCT's symmetric extension): ``Q r`` is weighted by it inside
  the log and in the gradient, and the residual is exactly zero at the truth.
- *Under-sampled levels.* Area averaging leaves the body's edge (a square-root cusp, the
  sharpest structure in a phantom's radiograph) and fine texture under-sampled at coarse
  levels, and a bilinear warp of an under-sampled edge does not match its shifted self: at the
  truth, 99 % of a coarse level's residual lay in the band around the body's edge. ``smooth``
  (1 level pixel in every preset) blurs both of a level's images by a Gaussian after averaging.
- *Thinning.* A compressed body's line integrals scale by ``1 + b(x)`` with ``b`` smooth
  (``regdata``'s "thinning"). Residual complexity absorbs an additive smooth change, but a scaled
  body edge is not smooth, and it was read as motion at the edge. The residual is
  ``(1 + b) warped - fixed``, ``b`` a cubic B-spline on a lattice ``gain`` x the frame apart
  (coefficients in percent, bending energy ``gain_regularisation``), fitted with the motion's
  lattice by the same L-BFGS; at the finest level it is refitted (``gain_fine``, presets
  ``weak``) or kept from the coarser levels (``default``, ``fast``: refitting costs that
  level's iterations and changed nothing measurable). An additive smooth change (a gain of the
  source) is still residual complexity's. ``ncc`` and ``mi`` keep high-passed images and no ``b``.
  Because the residual is high-passed, ``b`` is seen only at the body's edge, where a scaled edge
  and a shifted one look alike; ``refit_thinning`` (preset ``weak``) measures ``b`` again after
  a first pass in the body's interior, divides it out and runs the finest level once more from
  the first pass's lattices with the term off (``REFIT_INTERIOR``, ``REFIT_ITERATIONS``);
  ``refit_again`` measures it once more from that pass's field, nearer the edge, and runs again.
  ``rim`` (preset ``weak``) leaves the body's outermost rim out of those passes' data term:
  there the body's square-root edge is under-sampled at the level's pixels, and its model error
  pulls the faded texture's tangential motion beside it (benchmarks/README.md, session 24).

Energy balance. ``balance="lattice"`` (presets ``default``, ``fast``): the similarity's mean
over the level's pixels plus ``regularisation * sum((L c)^2) / n_control``, ``L`` the lattice's
second differences (affine fields are free), c in full-resolution pixels. For the same motion
this charges a coarse lattice ``(spacing ratio)^4`` more than a fine one, and a 2240 frame 4x
more than the same images at 1120: tuned on rich texture, it pins weak texture's motion at the
coarse levels. ``balance="frame"`` (presets ``weak``, ``weak-fast``) is scale-invariant: the
similarity *summed* over the level's pixels per million full-resolution pixels, rc's alpha
divided by the level's factor^2 (area averaging by f divides the noise variance by f^2, so a
structure resolved at two levels costs the same at both), and ``regularisation`` x the mean
squared second derivative of the field in frame fractions against position in frame
fractions, ``sum((L c)^2) / n_control * frame^2 / spacing^4``; the same motion then costs the
same at every lattice, level and image size, and the prior weighs less as the image carries
more information. The coarsest level runs ``regularisation`` itself, finer ones
``x (coarsest factor / factor)^stiffen``: on weak texture the coarse level pins the motion the
data observe, and the fine lattices, pinned by little data, would refit the noise.

A global start. ``init="silhouette"`` (presets ``silent``, ``silent-fast``) adds the affine map
between the two images' silhouettes (``radiokit.register._global``: centroid and second
moments, refined on the images) under every level's lattices: a compressed phantom's slab moves tens of pixels at its
ends with nothing inside to see it by, and the lattices, which the bending energy never charges
for an affine field, then refine around it. Dropped, and said so in the result's
``options["initial"]``, when the body is not wholly inside the frame or the silhouettes disagree;
a body cut by the frame starts instead from the affine map refined on the images from no motion
(``_global.frame_cut_affine``) where that beats no motion by more than the noise could.

Optimisation: L-BFGS (scipy) per pyramid level, coarse to fine (images halved by area averaging
until the smaller side is below ``min_size``), each level adding its own lattice on top of the
coarser ones' field, with control points ``spacing`` x max(1, factor / 2) apart. Levels of more
than ``max_pixels`` pixels are not run, and ``levels_skip`` stops that many levels earlier
still (the B-spline field is evaluated at full resolution all the same). ``polish`` (preset
``default`` only, rc only) then refits the finest lattice on the full-resolution images for that
many iterations, when the pyramid stopped short of them (``max_pixels`` or ``levels_skip``), the
interior is not silent and the field already passes the checks' residual line: the full-resolution images see what the half-resolution ones hide on rich
texture, and a field the checks would flag is not worth the time. With ``joint``
(presets ``weak``, ``weak-fast``) the finest level refits every coarser lattice with its own,
each keeping the bending weight it was fitted with: the prior is the same sum of lattices, but
its minimum is taken over all of them at once, so what a coarse level got wrong where only the
coarse images could see (a weak texture's body edge, where the texture fades) is corrected
where the finest images see better, at the coarse lattice's own (low) price. Each evaluation
then adds one adjoint per coarser lattice (``joint`` off: each level's lattice alone, on top of
the frozen coarser field).
``abandon_px`` stops a run before its finest level when, after the level before it, the
residual still moves by more than that (measured as ``register``'s checks measure it), and at
its finest level when ``ABANDON_FINEST`` iterations in it still moves by more than the checks'
own line: ``auto`` uses it so that a plain run already far off does not spend its most costly
level (``radiokit.register._auto.ABANDON``). ``extend`` is the converse: a finest level that ends its
budget with the field still moving (``converge_px``) while the residual, measured the same way,
already passes the checks' line is slow, not lost, and runs up to that many iterations more from
where it stands (``auto`` sets it on its plain run: natural images at 2240, ``_auto.EXTEND``).

Computation. One evaluation of a level's energy runs in row bands on radiokit's threads: a
band's field rows (``B_r`` rows times ``C B_c^T``), the bilinear warp and its derivatives (one
gather per coefficient plane of a table built once per level), the residual and, after the
whole-frame DCT, the gradient; the adjoint ``B_r^T G`` by blocks of lattice rows. Every sum is
taken in the order the frame-at-once code took it, so the energy, gradient and the optimiser's
path are the same to the bit, for a given thread count (benchmarks/README.md, "rc speed at
2240 (session 5)").
"""

from __future__ import annotations

import collections
import contextlib
import functools
import math
import numbers
from typing import TYPE_CHECKING

import numpy as np

from radiokit.checks import is_integer, is_number, scalar
from radiokit.register import _method
from radiokit.register._common import _field, _warp_rows, binned_mask
from radiokit.register._confidence import MODEL_FLOOR, object_noise, sample_step

# scipy's sparse matrices, DCT and L-BFGS are imported where a registration uses them: importing
# this module (radiokit.pipeline.Config checks the method names and options with it) is then
# scipy-free, and a refused command line or input does not load them (~0.3 CPU s; session 46)
if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["bspline_basis_matrix", "BSplineField"]

# Chosen on benchmarks (analytic_pair and regdata.family TRAINING seeds); the measurements and
# the history of every value are in benchmarks/README.md ("Registration on nearly textureless
# phantoms (issue 11)" and "rc presets").
PRESETS = {
    "default": dict(
        spacing=24,
        alpha=0.005,
        regularisation=1e-3,
        iterations=(250, 120, 80),
        min_size=160,
        max_pixels=2_000_000,
        levels_skip=0,
        converge_px=0.35,
        min_levels=3,
        coarse_alpha=1.0,
        coarse_regularisation=1.0,
        highpass=0.02,
        balance="lattice",
        stiffen=0.0,
        init="none",
        highpass_on="residual",
        smooth=1.0,
        gain=0.125,
        gain_regularisation=1e-5,
        gain_fine=False,
        joint=False,
        noise_alpha=0.0,
        bin_pixels=0,
        refit_thinning=False,
        refit_again=0,
        abandon_px=0.0,
        extend=0,
        grid_jitter=False,
        polish=10,
        rim=0.0,
    ),
    "fast": dict(
        spacing=16,
        alpha=0.005,
        regularisation=1e-3,
        iterations=(60, 40),
        min_size=96,
        max_pixels=100_000,
        levels_skip=0,
        converge_px=0.5,
        min_levels=1,
        coarse_alpha=1.0,
        coarse_regularisation=1.0,
        highpass=0.02,
        balance="lattice",
        stiffen=0.0,
        init="none",
        highpass_on="residual",
        smooth=1.0,
        gain=0.125,
        gain_regularisation=1e-5,
        gain_fine=False,
        joint=False,
        noise_alpha=0.0,
        bin_pixels=0,
        refit_thinning=False,
        refit_again=0,
        abandon_px=0.0,
        extend=0,
        grid_jitter=False,
        polish=0,
        rim=0.0,
    ),
}
# weak texture (a gel phantom's, near the noise): the scale-invariant energy balance, free coarse
# levels, stiffer fine ones (module docstring); not the default: a simulated silent body's edges
# carry thickness change that free coarse levels follow (benchmarks/README.md). Stiffening 2^2
# a level (was 2^6) and the thinning field refitted at every level, chosen with the unbiased
# data term on TRAINING seeds 1-3 at 2240 (texture = noise): mean median EPE 0.51 px at 2^6,
# 0.49 at 2^2, 0.54 at 2^0; refitting against keeping the thinning at the finest level (seeds 4-6) 0.52 /
# 0.55 px, rich texture 0.08 / 0.12 px (benchmarks/README.md, session 8)
#
# joint (session 10): the finest level refits the coarser lattices with its own (each with the
# bending weight it was fitted with: the MAP of the same prior, not the greedy coarse-to-fine
# path, whose coarse lattices froze where only the coarse images had seen them). TRAINING seeds,
# `bench_register.py --regimes`, geometric means of the median EPE, without -> with: weak 2240
# weak texture 0.515 -> 0.494 px, 560 map 0.375 -> 0.367, natural 0.113 -> 0.111, rich 0.081 ->
# 0.081, physical 2.38 -> 2.40; weak-fast 0.988 -> 0.701, 0.366 -> 0.342, 0.366 -> 0.353, 0.144
# -> 0.144, 1.86 -> 1.75. With joint, stiffen 1 / 0 and regularisation 3e-7 were tried and lost
# at 2240 (0.505, 0.549, 0.555 px; benchmarks/README.md, session 10)
#
# noise_alpha (session 12): alpha follows the pair's measured noise (alpha = noise_alpha x
# sigma^2), so the data term weighs a residual against the noise as a likelihood does and the
# bending weight stays a prior on the motion. With a fixed alpha, less noise made weak worse
# (texture = noise at 1120, training seeds 1-2: 0.45 px at noise 0.01, 0.63 at 0.005, 1.27 at
# 0.0025: the residual of a misfit shrank with the texture while alpha did not, so the prior
# took over). 210 keeps alpha = 0.005 at the family's noise (sigma = 0.0049 of the range), where
# the rest of the preset was chosen (benchmarks/README.md, "rc's alpha follows the noise").
_WEAK = dict(regularisation=1e-6, balance="frame", stiffen=2.0, gain_fine=True, joint=True, noise_alpha=210.0)
# weak stops at levels of ~0.4 Mpx (the 560 px level at 2240): finer levels added nothing on
# weak texture at twice the time (training seeds 0-5 at 2240: 0.88 px in 5.5 s with the
# default's levels, 0.91 px in 2.7 s with these; with the unbiased data term, at 2^6, 0.507 /
# 0.508 px on seeds 1-3); stopping at ~0.1 Mpx lost 2.5-3x on natural images (benchmarks/README.md)
# refit_thinning only in weak: weak-fast with it 0.8-0.9 -> 1.6-1.7 s at 2240 (its 1 s budget)
# grid_jitter only in weak (session 19, TRAINING rows: the 2240 weak-texture regime 0.445 -> 0.403
# px, the flag family's weak 0.553 -> 0.531, auto 0.463 -> 0.444, the flag's rows unchanged;
# benchmarks/README.md "Interpolation pulls a noisy pair off the pixel grid"); weak-fast without
# it: 1.11 -> 1.38 s at 2240 side by side (its 1 s budget), default: no gain
# refit_again 1 in weak (session 20): the thinning measured once more from the second pass's field,
# nearer the edge (REFIT_AGAIN_INTERIOR), and a third pass; chosen on TRAINING seeds at 2240
# (benchmarks/README.md, "`weak` with the jitter: ..., the thinning measured twice (session 20)")
# rim 0.004 in weak (session 24): the refit's passes leave the body's outermost 9 px (at 2240) out
# of the data term, where the under-sampled square-root edge pulled the faded texture's
# tangential motion beside it; the first pass keeps it (it finds the thinning there, and its
# steep slope pins the normal motion). Chosen on TRAINING pairs at 2240 by the median, over 0 and
# 0.0075 (benchmarks/README.md, "The edge band on weak texture (session 24)")
PRESETS["weak"] = {
    **PRESETS["default"],
    **_WEAK,
    "max_pixels": 400_000,
    "refit_thinning": True,
    "refit_again": 1,
    "grid_jitter": True,
    "polish": 0,
    "rim": 0.004,
}
# weak-fast runs two levels (1/16 and 1/8 at 2240), its finer lattice 64 px there
PRESETS["weak-fast"] = {**PRESETS["fast"], **_WEAK}
# a silent body (no texture inside: a homogeneous gel phantom) observes its motion only at its
# edges and inclusions; a compressed body moves mostly as one affine map, so the field starts
# from the silhouette's and the lattices are stiff: the least-bent field the edges allow
#
# bin_pixels (the pair area-averaged to at most that many pixels, the field upsampled) is not
# in the preset, though it helps the family: the lattice spacing is in full-resolution pixels,
# so at 2240 the preset is a 4x finer lattice in frame units than at 560, a looser guess between
# a silent body's edges; TRAINING seeds 1-6 at 2240 (physical motion, no texture) 0.74-2.63 px
# unbinned, 0.36-0.64 binned to 0.4 Mpx. But on the simulated pva-phantom side view at 2240 (the
# paper's phantom; `radiokit demo --preset pva-phantom --imaging paper`, `auto` returns silent)
# it loses: 1.36 px unbinned, 1.76 by 2, 2.60 by 4, where the straight, sharp plate edges carry
# the motion and binning blurs them (benchmarks/README.md, "A silent body registered at 0.4 Mpx")
_SILENT = dict(init="silhouette", regularisation=0.1, polish=0)
PRESETS["silent"] = {**PRESETS["default"], **_SILENT}
PRESETS["silent-fast"] = {**PRESETS["fast"], **_SILENT}


def bspline_basis_matrix(n_pixels, n_ctrl, spacing, factor=1, dtype=np.float32) -> scipy.sparse.csr_matrix:
    """(n_pixels, n_ctrl) sparse cubic B-spline weights (4 per row): pixel ``k`` of a grid
    ``factor`` times coarser than full resolution sits at full-resolution coordinate
    ``factor k + (factor - 1) / 2``; control point ``j`` at ``(j - 1) spacing``. A padded last
    row of a coarse grid beyond the lattice's span gets the end polynomials extrapolated."""
    from scipy.interpolate import BSpline

    y = factor * np.arange(n_pixels) + (factor - 1) / 2
    knots = (np.arange(n_ctrl + 4) - 3.0) * spacing  # control point j is the B-spline on knots j..j+4
    return BSpline.design_matrix(y, knots, 3, extrapolate=True).astype(dtype).tocsr()


def _laplacian(nr, nc):
    """Discrete bending energy of a control lattice as a stacked operator ``L``:
    ``||L c||^2 = sum (c_rr^2 + c_cc^2 + 2 c_rc^2)`` with second differences taken only where
    they exist, so affine fields (a uniform expansion, a shear) cost nothing."""
    import scipy.sparse as sp

    def d2(n):
        if n < 3:
            return sp.csr_matrix((0, n))
        return sp.diags([np.ones(n - 2), -2 * np.ones(n - 2), np.ones(n - 2)], [0, 1, 2], shape=(n - 2, n))

    def d1(n):
        return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))

    return sp.vstack(
        [sp.kron(d2(nr), sp.identity(nc)), sp.kron(sp.identity(nr), d2(nc)), np.sqrt(2.0) * sp.kron(d1(nr), d1(nc))]
    ).tocsr()


class BSplineField:
    """The control lattice of a ``shape`` image with control points ``spacing`` pixels apart."""

    def __init__(self, shape, spacing, dtype=np.float32):
        self.dtype = np.dtype(dtype)
        self.shape = tuple(shape)
        self.spacing = float(spacing)
        self.nr = int(math.ceil((shape[0] - 1) / spacing)) + 3
        self.nc = int(math.ceil((shape[1] - 1) / spacing)) + 3
        self.L = _laplacian(self.nr, self.nc)
        self.lam = None  # the bending weight the lattice was fitted with (set by the level that fits it)
        self._cache = {}

    def drop_caches(self):
        """Forget the basis matrices and bands (rebuilt when used): a lattice kept with a result
        (``Registration.lattices``) then holds its coefficients' size, not a level's matrices."""
        self._cache.clear()

    @property
    def n_params(self):
        return 2 * self.nr * self.nc

    def matrices(self, factor):
        if factor not in self._cache:
            rows = -(-self.shape[0] // factor)
            cols = -(-self.shape[1] // factor)
            Br = bspline_basis_matrix(rows, self.nr, self.spacing, factor, self.dtype)
            Bc = bspline_basis_matrix(cols, self.nc, self.spacing, factor, self.dtype)
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
            d = d[:, : shape[0], : shape[1]]
        return d

    def columns(self, c, factor=1):
        """``(2, nr, cols)``: the lattice interpolated along the columns of a grid ``factor``
        times coarser, ``(B_c C^T)^T`` per component; ``B_r`` times it is the field."""
        _, Bc, _, _ = self.matrices(factor)
        C = c.reshape(2, self.nr, self.nc).astype(self.dtype)
        return np.stack([(Bc @ C[k].T).T for k in range(2)])

    def bands(self, factor, slices):
        """``(slice, j0, j1, B)`` per row band: the rows ``slice`` of ``B_r`` on the only control
        rows ``j0:j1`` they weigh (cached: the same bands every evaluation)."""
        key = (factor, tuple((s.start, s.stop) for s in slices))
        if key not in self._cache:
            Br = self.matrices(factor)[0]
            out = []
            for sl in slices:
                b = Br[sl]
                j0, j1 = int(b.indices.min()), int(b.indices.max()) + 1
                b = b[:, j0:j1].tocsr()
                b.sort_indices()
                out.append((sl, j0, j1, b))
            self._cache[key] = out
        return self._cache[key]

    def adjoint_rows(self, gy, gx, factor=1):
        """``adjoint(np.stack([gy, gx]), factor)`` to the last bit, ``B_r^T G`` computed by
        blocks of lattice rows on the thread pool (each row's sum over its pixel rows is the
        one ``adjoint`` runs)."""
        _, _, BrT, BcT = self.matrices(factor)
        rows, cols = gy.shape
        key = ("rows", factor, rows)
        if key not in self._cache:
            BrT = BrT[:, :rows] if BrT.shape[1] != rows else BrT
            step = max(4, -(-self.nr // (4 * _threads())))
            self._cache[key] = [(slice(a, a + step), BrT[a : a + step]) for a in range(0, self.nr, step)]
        acc = np.empty((2, self.nr, cols), self.dtype)
        gy, gx = gy.astype(self.dtype, copy=False), gx.astype(self.dtype, copy=False)

        def block(b):
            js, B = b
            acc[0, js] = B @ gy
            acc[1, js] = B @ gx

        _parallel(block, self._cache[key])
        BcT = BcT[:, :cols] if BcT.shape[1] != cols else BcT
        out = np.stack([(BcT @ acc[k].T).T for k in range(2)])
        return out.ravel().astype(np.float64) / factor

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
    if (R * f, C * f) != (rows, cols):  # (a copy of the whole frame otherwise)
        img = np.pad(img, ((0, R * f - rows), (0, C * f - cols)), mode="edge")
    return cv2.resize(img, (C, R), interpolation=cv2.INTER_AREA)


def _row_bands(rows, step=128):
    return [slice(a, min(a + step, rows)) for a in range(0, rows, step)]


def _parallel(fn, items):
    """``[fn(item) for item in items]``, on the thread pool when it has several threads: a
    whole-frame pass at 2240 x 2240 run band by band stays in cache, without frame-sized
    temporaries (page faults)."""
    if len(items) == 1 or _threads() == 1:
        return [fn(b) for b in items]
    return list(_pool().map(fn, items))


def _fields(grids, factor, shape):
    """``sum(grid.field(c, factor, shape) for grid, c in grids)`` (float32, the same to the bit),
    computed band by band: no frame-sized temporaries."""
    out = np.zeros((2,) + tuple(shape), np.float32)
    if not grids:
        return out
    Ts = [g.columns(c, factor)[:, :, : shape[1]] for g, c in grids]
    slices = _row_bands(shape[0])
    parts = [g.bands(factor, slices) for g, _ in grids]
    scale = np.float32(1.0 / factor)

    def band(i):
        sl = slices[i]
        for T, p in zip(Ts, parts):
            _, j0, j1, Bs = p[i]
            for k in range(2):
                v = Bs @ T[k, j0:j1]
                if factor != 1:  # (x 1.0 changes no bit)
                    v *= scale
                out[k, sl] += v

    _parallel(band, range(len(slices)))
    return out


class _Level:
    """Images and similarity at one pyramid level.

    The energy of a lattice runs in row bands (``lattice_energy``): a band's field, warp,
    residual, gradient and adjoint stay in cache, and the only frame-sized arrays are buffers
    kept from one evaluation to the next (the residual, which the DCT needs whole, and the
    warped image's derivatives, which wait for it)."""

    def __init__(self, fixed, moving, mask, factor, similarity, alpha, hp_sigma=0.0, smooth=0.0, jitter=False):
        self.factor = factor
        self.gain = None  # a smooth thinning field b (this level's pixels): residual (1 + b) w - f
        self.fit_gain = False  # whether b is being fitted (its gradient wanted) or kept
        self.gain_grad = None
        self.fixed = _downsample(fixed, factor)
        self.moving = _downsample(moving, factor)
        if smooth:
            import cv2

            self.fixed = cv2.GaussianBlur(self.fixed, (0, 0), smooth, borderType=cv2.BORDER_REFLECT)
            self.moving = cv2.GaussianBlur(self.moving, (0, 0), smooth, borderType=cv2.BORDER_REFLECT)
        # (a float32 mask is not copied: the caller converts it once for all levels)
        self.mask = None if mask is None else binned_mask(_downsample(mask.astype(np.float32, copy=False), factor))
        self.shape = self.fixed.shape
        dt = self.fixed.dtype
        self._row = np.arange(self.shape[0], dtype=dt)[:, None]  # pixel positions, broadcast
        self._col = np.arange(self.shape[1], dtype=dt)
        if jitter:
            self._jitter()
        self._maskf = None if self.mask is None else self.mask.astype(dt)
        self._table = _bilinear_table(self.moving)
        self._w, self._dy, self._dx, self._r = (np.empty(self.shape, dt) for _ in range(4))
        self.similarity = similarity
        # samples warped out of the frame leave the residual terms (rc, ssd); ncc and mi read the
        # warped image's statistics and keep the replicated border
        self.exclude_outside = similarity in ("rc", "ssd")
        self._first_off = {}
        self._off_band = None  # {band's first row: where the level's first field carries a pixel out}
        self.alpha = alpha
        self.n = float(self.mask.sum()) if self.mask is not None else float(self.fixed.size)
        self.hp = None
        if hp_sigma:  # the residual's high-pass as the DCT's diagonal: 1 - the Gaussian's response
            wy = (np.pi * np.arange(self.shape[0]) / self.shape[0]) ** 2
            wx = (np.pi * np.arange(self.shape[1]) / self.shape[1]) ** 2
            self.hp = (-np.expm1(-0.5 * hp_sigma**2 * (wy[:, None] + wx[None, :]))).astype(dt)

    def _jitter(self):
        """``grid_jitter``: both images sampled at the pixels moved by a fixed uniform offset in
        [-1/2, 1/2) each, ``fixed`` once here, ``moving`` at each warp. Linear interpolation at a
        fractional offset ``f`` lowers the noise variance by ``(1 - f)^2 + f^2`` per axis, so on
        the pixel grid a field gains by moving a noisy image off it (half a pixel: a quarter of the
        variance; benchmarks/README.md, "Interpolation pulls a noisy pair off the pixel grid").
        Off the grid, every displacement sees the same mixture of offsets: the residual's noise no
        longer depends on the field (elastix's random sampler avoids the same artefact)."""
        import cv2

        rng = np.random.default_rng(0)  # the same offsets every run: a registration is repeatable
        dt = self.fixed.dtype
        self._row = (self._row + rng.uniform(-0.5, 0.5, self.shape)).astype(dt)
        self._col = (self._col + rng.uniform(-0.5, 0.5, self.shape)).astype(dt)
        # (OpenCV's 1/32-pixel positions are fine for the fixed image, sampled once)
        self.fixed = cv2.remap(self.fixed, self._col, self._row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def _bands(self):
        rows = self.shape[0]
        if rows * self.shape[1] < 200_000:  # threads cost more than they gain
            return [slice(0, rows)]
        step = max(16, min(128, -(-rows // (4 * _threads()))))
        return [slice(a, min(a + step, rows)) for a in range(0, rows, step)]

    def _map(self, fn, items=None):
        """``fn(item)`` over the row bands (or ``items``, one per band), on the thread pool when
        there are several."""
        items = self._bands() if items is None else items
        if len(items) == 1 or _threads() == 1:  # one thread (a Dask worker): the bands in turn, in
            return [fn(b) for b in items]  # cache (whole-frame temporaries: more CPU, page faults)
        return list(_pool().map(fn, items))

    def _sample_band(self, sl, y, x):
        """Bilinear ``moving(pixel + d)`` and its exact derivatives along rows and columns on rows
        ``sl`` into ``_w``, ``_dy``, ``_dx``, the masked residual into ``_r``; ``y``, ``x`` the
        band's displacement (overwritten). The derivative is the interpolant's own, so the
        energy's gradient is exact; border replicated, no derivative where clamped, and the pixels
        ``_outside`` names left out (no residual, no derivative). Numpy rather
        than OpenCV's remap, whose 1/32-pixel fixed-point positions make the energy a staircase
        at fine scales. One gather of the cell's four coefficients (``_bilinear_table``) per
        pixel; the arithmetic is the textbook one, operation for operation."""
        import cv2

        rows, cols = self.shape
        y += self._row[sl]
        x += self._col if self._col.ndim == 1 else self._col[sl]
        off = self._outside(sl, y, x)
        yc, y0, outside_y = _cell(y, rows)  # b and its cell's row
        xc, x0, outside_x = _cell(x, cols)  # a and its column
        # the cell's I00, I10 - I00, I01, I11 - I01, gathered plane by plane by OpenCV's
        # nearest-pixel remap (exact at these whole-pixel positions; 2-3x faster than an index
        # array and numpy's take, and contiguous planes: 4x faster arithmetic than the strided
        # columns of one (n, 4) gather; OpenCV's remap takes images under 32767 px a side)
        mx, my = x0.astype(np.float32, copy=False), y0.astype(np.float32, copy=False)  # its map type
        c = [cv2.remap(t, mx, my, cv2.INTER_NEAREST) for t in self._table]
        top = c[1] * xc
        top += c[0]
        bottom = c[3] * xc
        bottom += c[2]
        dy = self._dy[sl]
        np.subtract(bottom, top, out=dy)
        w = self._w[sl]
        np.multiply(yc, dy, out=w)
        w += top
        np.subtract(c[3], c[1], out=bottom)
        bottom *= yc
        np.add(c[1], bottom, out=self._dx[sl])
        if outside_y is not None:
            np.copyto(dy, 0, where=outside_y)
        if outside_x is not None:
            np.copyto(self._dx[sl], 0, where=outside_x)
        r = np.subtract(w, self.fixed[sl], out=self._r[sl])
        if self._maskf is not None:
            r *= self._maskf[sl]
        if off is not None:  # no data there: left out as the mask leaves a pixel out (w for the gain)
            for a in (r, w, dy, self._dx[sl]):
                np.copyto(a, 0, where=off)

    def _outside(self, sl, y, x):
        """The pixels of rows ``sl`` left out of the data term (None: none): those the level's
        first field carried out of the frame, decided at its first evaluation (``y``, ``x`` the
        band's positions) and kept for the level. Kept, not redrawn at each evaluation: a pixel
        left out has no residual, so a set redrawn as the field moves would pay the field to
        carry pixels out (and make the energy jump where one crosses)."""
        if not self.exclude_outside:
            return None
        if self._off_band is None:  # the first evaluation: its bands fill this
            return self._first_off.setdefault(sl.start, _beyond(y, self.shape[0], _beyond(x, self.shape[1])))
        return self._off_band.get(sl.start)

    def _decided(self):
        """After an evaluation: the first one's pixels out of the frame are the level's."""
        if self._off_band is None and self.exclude_outside:
            self._off_band = self._first_off

    def _similarity(self):
        """Energy and its derivative with respect to the warped image (frame-sized; may be the
        residual buffer itself), from ``_w`` and ``_r``."""
        w, r = self._w, self._r
        wm = None
        from scipy import fft as sfft  # here, not at the module's import (see the imports)

        if self.gain is not None:
            wm = w if self._maskf is None else w * self._maskf
            r += self.gain * wm
        if self.similarity == "rc":
            # in place: the residual buffer is refilled by the next evaluation's warp
            q = sfft.dctn(r, norm="ortho", workers=_threads(), overwrite_x=True)
            alpha = self.alpha
            hp = self.hp

            def band(sl):  # in place: q -> q / (q^2 + alpha); returns the band's energy
                qs = q[sl]
                if hp is not None:
                    qs *= hp[sl]
                q2 = qs * qs
                e = float(np.sum(np.log1p(q2 * (1.0 / alpha)), dtype=np.float64))
                q2 += alpha
                qs /= q2
                if hp is not None:
                    qs *= hp[sl]
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
                return 1.0, None
            c = float(np.sum(a * b, dtype=np.float64)) / (na * nb)
            e = 1.0 - c
            dr = -(b / (na * nb) - c * a / (na * na))
        elif self.similarity == "mi":
            e, dr = self._mutual_information(w)
        else:
            raise ValueError(f"unknown similarity {self.similarity!r}")
        if wm is not None:
            if self.fit_gain:
                self.gain_grad = dr * wm
            dr = dr * (1 + self.gain)
        return e, dr.astype(self.fixed.dtype, copy=False)

    def _band_gradient(self, dr, sl):
        """``(dE/dd_row, dE/dd_col)`` on rows ``sl``: the similarity's derivative (masked) times
        the warped image's."""
        if self._maskf is None:
            return dr[sl] * self._dy[sl], dr[sl] * self._dx[sl]
        g = dr[sl] * self._maskf[sl]
        gy = g * self._dy[sl]
        g *= self._dx[sl]
        return gy, g

    def energy(self, d):
        """Similarity energy and its gradient with respect to the field d (2, rows, cols)."""
        self._map(lambda sl: self._sample_band(sl, d[0, sl].copy(), d[1, sl].copy()))
        self._decided()
        e, dr = self._similarity()
        out = np.zeros((2,) + self.shape, self.fixed.dtype)
        if dr is None:
            return e, out

        def band(sl):
            out[0, sl], out[1, sl] = self._band_gradient(dr, sl)

        self._map(band)
        return e, out

    def lattice_energy(self, grid, x, base, factor):
        """``(energy, gradient)``: the similarity of the lattice coefficients ``x`` of ``grid``
        on top of the field ``base`` (this level's pixels), and its gradient with respect to
        ``x`` (float64). The same as ``energy(grid.field(x, factor) + base)`` followed by
        ``grid.adjoint``, to the last bit: the field, warp, residual and gradient band by band,
        the adjoint by blocks of lattice rows (each row's sum over pixel rows in the same order)."""
        T = grid.columns(x, factor)
        bands = grid.bands(factor, self._bands())
        scale = np.float32(1.0 / factor)

        def sample(b):
            sl, j0, j1, Bs = b
            y, xx = (Bs @ T[k, j0:j1] for k in range(2))
            if factor != 1:  # (x 1.0 changes no bit)
                y *= scale
                xx *= scale
            y += base[0, sl]
            xx += base[1, sl]
            self._sample_band(sl, y, xx)

        self._map(sample, bands)
        self._decided()
        e, dr = self._similarity()
        if dr is None:  # no gradient: dE/dd (left in _dy, _dx, which ``joint`` reads) is zero
            self._dy.fill(0)
            self._dx.fill(0)
            return e, np.zeros(grid.n_params)

        def gradient(sl):  # dE/dd in place of the warped image's derivatives
            g = dr[sl] * self._maskf[sl] if self._maskf is not None else dr[sl]
            np.multiply(g, self._dy[sl], out=self._dy[sl])
            np.multiply(g, self._dx[sl], out=self._dx[sl])

        self._map(gradient)
        return e, grid.adjoint_rows(self._dy, self._dx, factor)


# how far (px) past the frame's outer pixel centres a warped position may fall and still be
# sampled: within half a pixel the replicated border is the nearest pixel (grid_jitter's offsets
# reach that far at no motion); beyond, the border's replica is no observation of the moving image
_OUTSIDE_MARGIN = 0.5


def _beyond(v, n, also=None):
    """Where positions ``v`` on an axis of ``n`` pixels fall more than ``_OUTSIDE_MARGIN`` outside
    it, or'ed with ``also``; None when nowhere (the band's extremes tell)."""
    m = _OUTSIDE_MARGIN
    if float(v.min()) >= -m and float(v.max()) <= n - 1 + m:
        return also
    out = (v < -m) | (v > n - 1 + m)
    return out if also is None else out | also


def _cell(v, n):
    """``(fraction, cell, outside)`` of positions ``v`` (overwritten) on an axis of ``n`` pixels:
    clamped to the image (``outside`` marks where, or is None when nothing was), the cell's
    first pixel (the last pixel's cell is the one before: weight 1 on its far side), and the
    position less it (exact: a float minus the whole number below it). The clamp and the last
    cell's test only run when the band's extremes need them."""
    lo, hi = float(v.min()), float(v.max())
    outside = None
    if lo < 0 or hi > n - 1:
        c = np.clip(v, 0, n - 1)
        outside = c != v
        v, hi = c, min(hi, n - 1)
    v0 = np.floor(v)
    if hi >= n - 1:
        np.minimum(v0, n - 2, out=v0)
    v -= v0
    return v, v0, outside


def _bilinear_table(m):
    """``(4, rows, cols)``: for the cell whose top-left pixel is ``k``, ``m[k]``, the step to
    its right neighbour, the pixel below and that pixel's step to its right (the last row and
    column are never a cell's top-left: zeros)."""
    rows, cols = m.shape
    t = np.zeros((4, rows, cols), m.dtype)
    t[0, :-1, :-1] = m[:-1, :-1]
    np.subtract(m[:-1, 1:], m[:-1, :-1], out=t[1, :-1, :-1])
    t[2, :-1, :-1] = m[1:, :-1]
    np.subtract(m[1:, 1:], m[1:, :-1], out=t[3, :-1, :-1])
    return t


def _cubic_bspline(t):
    """Cubic B-spline kernel and its derivative (support |t| < 2)."""
    a = np.abs(t)
    out = np.where(a < 1, (4 - 6 * a**2 + 3 * a**3) / 6, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))
    d = np.where(a < 1, (-12 * a + 9 * a**2) / 6, np.where(a < 2, -3 * (2 - a) ** 2 / 6, 0.0)) * np.sign(t)
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
    step = sample_step(fixed.size)  # percentiles from ~250k samples
    lo, hi = np.percentile(fixed[::step, ::step], [1, 99])
    if hi <= lo:
        lo, hi = float(fixed.min()), float(fixed.max())
    scale = 1.0 / (hi - lo)
    out = np.empty(fixed.shape, np.float32), np.empty(moving.shape, np.float32)

    def band(sl):  # (x - lo) * scale as before (in double when lo is), rounded to float32
        for a, o in zip((fixed, moving), out):
            o[sl] = (a[sl] - lo) * scale

    _parallel(band, _row_bands(fixed.shape[0], 32))  # float64 temporaries of a band in cache
    return out


def _highpass(img, sigma, out=None, scratch=None):
    """``img`` (float32) minus its Gaussian blur of ``sigma`` px (the blur computed on a grid
    ``sigma / 8`` times coarser: it is wide, and 20x cheaper at 2240), into ``out`` (may be
    ``img``); ``scratch``, an array of ``img``'s shape and type, takes the upsampled blur."""
    import cv2

    k = max(1, int(sigma / 8))
    small = _downsample(img, k)
    blur = cv2.GaussianBlur(small, (0, 0), sigma / k, borderType=cv2.BORDER_REFLECT)
    if k > 1:
        blur = cv2.resize(blur, (img.shape[1], img.shape[0]), dst=scratch, interpolation=cv2.INTER_LINEAR)
    return np.subtract(img, blur, out=out)


def bspline_register(fixed, moving, mask=None, **options):
    """B-spline registration; see the module docstring. Options default to ``PRESETS[preset]``.

    BLAS is held to one thread meanwhile: its matrices here are small, and OpenBLAS's threads
    spin between calls, starving the row-band threads and L-BFGS (measured: 3.1 s -> 0.64 s for
    a 60-iteration level on two cores). OpenCV too: its calls run inside the row bands, which
    are the parallelism; with its own pool each remap of a band cost two cores' CPU time
    (`radiokit process` on one 2240 file, one radiokit thread: 31 s of CPU against 28 s)."""
    import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS, so that the limit below reaches it)
    from threadpoolctl import threadpool_limits

    # OpenCV first: its import loads its own OpenBLAS, which a limit set before it does not reach
    with _opencv_threads(1), threadpool_limits(limits=1, user_api="blas"):
        return _bspline_register(fixed, moving, mask, **options)


@contextlib.contextmanager
def _opencv_threads(n):
    """OpenCV's thread count set to ``n`` meanwhile (process-wide), then put back."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


# the data term is a sum over pixels per this many full-resolution pixels, so the bending
# energy's weight against it is fixed by the image's information, not its size
_N_REF = 1_000_000


def _options(preset, overrides) -> dict:
    """``PRESETS[preset]`` with the overrides that are not None (``highpass=None``: off); validated."""
    if preset not in PRESETS:
        raise ValueError(
            f"preset {preset!r}: expected one of {', '.join(PRESETS)} (or, through register(), auto, auto-fast)"
        )
    overrides = {k: scalar(v) for k, v in overrides.items()}  # np.array(16) is the number 16
    o = dict(PRESETS[preset])
    if overrides.get("alpha") is not None and overrides.get("noise_alpha") is None:
        o["noise_alpha"] = 0.0  # an alpha asked for is used as it is
    o.update({k: v for k, v in overrides.items() if v is not None})
    if "highpass" in overrides and overrides["highpass"] is None:  # documented: "0 or None: off"
        o["highpass"] = 0.0
    _check_choices(o)
    _check_values(o)
    if overrides.get("refit_again") and not o["refit_thinning"]:  # asked for, it would do nothing
        raise ValueError(f"refit_again={o['refit_again']!r}: needs refit_thinning=True (it repeats that refit)")
    if overrides.get("rim") and not o["refit_thinning"]:  # measured only in the refit's passes
        raise ValueError(f"rim={o['rim']!r}: needs refit_thinning=True (the rim is left out of its passes)")
    _check_rim(o)
    return o


def _check_rim(o):
    """ValueError when ``o``'s rim leaves no data: no pixel lies half the smaller side from every edge."""
    if not o["rim"] < 0.5:
        raise ValueError(f"rim={o['rim']!r}: must be under 0.5 (a fraction of the smaller side)")


def _check_choices(o):
    """ValueError naming the first of ``o``'s text options that is none of its choices."""
    if o["balance"] not in ("lattice", "frame"):
        raise ValueError(f"balance={o['balance']!r}: expected 'lattice' or 'frame'")
    if o["init"] not in ("none", "silhouette"):
        raise ValueError(f"init={o['init']!r}: expected 'none' or 'silhouette'")
    if o["highpass_on"] not in ("images", "residual"):
        raise ValueError(f"highpass_on={o['highpass_on']!r}: expected 'images' or 'residual'")


def check_option_values(options) -> None:
    """ValueError naming the first of ``options`` (register's, a preset's name among them) whose value
    is of the wrong kind or out of its range, each checked alone: for a caller to refuse it before
    any work (``radiokit.pipeline.Config``: ``spacing="8"`` was found at the first registration,
    after the whole correction). Whether an option goes with the preset (``rim`` needs
    ``refit_thinning``) waits for the preset ``auto`` picks."""
    from radiokit.register._auto import AUTO_PRESETS

    preset = options.get("preset")
    if preset is not None and not (isinstance(preset, str) and (preset in PRESETS or preset in AUTO_PRESETS)):
        raise ValueError(f"preset {preset!r}: expected one of {', '.join([*PRESETS, *AUTO_PRESETS])}")
    given = {k: scalar(v) for k, v in options.items() if k in PRESETS["default"] and v is not None}
    o = dict(PRESETS["default"], **given)  # the defaults pass: what fails is an option given
    _check_choices(o)
    _check_values(o)
    _check_rim(o)


# each numeric option's least value and whether it may equal it; every one must be a finite real
# number (a NaN compared False with every bound and ran; min_size 0 halved the pyramid forever)
_LOWEST = {
    "spacing": (4, True),
    "alpha": (0, False),
    "regularisation": (0, True),
    "min_size": (1, True),
    "max_pixels": (0, True),
    "converge_px": (0, True),
    "coarse_alpha": (0, False),
    "coarse_regularisation": (0, True),
    "highpass": (0, True),
    "stiffen": (-math.inf, True),
    "smooth": (0, True),
    "gain": (0, True),
    "gain_regularisation": (0, True),
    "noise_alpha": (0, True),
    "bin_pixels": (0, True),
    "abandon_px": (0, True),
    "rim": (0, True),
}
_COUNTS = {"levels_skip": 0, "min_levels": 1, "extend": 0, "refit_again": 0, "polish": 0}  # integers, at least this
_FLAGS = ("gain_fine", "joint", "refit_thinning", "grid_jitter")


def _check_values(o):
    """ValueError naming the first option of ``o`` outside its range (``_LOWEST``, ``_COUNTS``,
    ``_FLAGS``, ``iterations``); ``iterations`` given as one count becomes that count's tuple."""
    for key, (lowest, equal) in _LOWEST.items():
        v = o[key]
        if not (is_number(v) and math.isfinite(v) and (v >= lowest if equal else v > lowest)):
            what = "control points closer than 4 pixels cannot be resolved" if key == "spacing" else ""
            raise ValueError(
                f"{key}={v!r}: expected a finite number {'>=' if equal else '>'} {lowest:g} {what}".rstrip()
            )
    for key, lowest in _COUNTS.items():
        if not (is_integer(o[key]) and o[key] >= lowest):
            raise ValueError(f"{key}={o[key]!r}: expected an integer >= {lowest}")
    for key in _FLAGS:
        if not isinstance(o[key], (bool, np.bool_)):
            raise ValueError(f"{key}={o[key]!r}: expected True or False")
    its = o["iterations"]
    its = (its,) if isinstance(its, numbers.Integral) else its
    if not (isinstance(its, (tuple, list)) and its and all(is_integer(n) and n >= 1 for n in its)):
        raise ValueError(f"iterations={o['iterations']!r}: expected a count >= 1, or one per level (coarse to fine)")
    o["iterations"] = tuple(its)


def _bin_factor(shape, bin_pixels) -> int:
    """The least integer ``k`` that brings a ``shape`` image under ``bin_pixels`` pixels when
    area-averaged by ``k`` (1 when it is under already, or ``bin_pixels`` is 0)."""
    size = shape[0] * shape[1]
    if not bin_pixels or size <= bin_pixels:
        return 1
    return int(math.ceil(math.sqrt(size / bin_pixels)))


def _upsample_field(d, k, shape) -> np.ndarray:
    """A field of the pair area-averaged by ``k`` (binned pixel ``i`` centred on full-resolution
    ``k i + (k - 1) / 2``, which OpenCV's linear resize keeps) in full-resolution pixels over
    ``shape``; the rows and columns the binning cropped take the edge's values."""
    import cv2

    r, c = d.shape[1] * k, d.shape[2] * k
    up = np.stack([cv2.resize(np.ascontiguousarray(x), (c, r), interpolation=cv2.INTER_LINEAR) for x in d]) * k
    return np.pad(up, ((0, 0), (0, shape[0] - r), (0, shape[1] - c)), mode="edge").astype(np.float32)


def _pyramid(shape, o) -> list:
    """``(factor, iterations)`` of the levels run, coarse to fine: images halved until the
    smaller side is below ``min_size``; at least ``min_levels`` levels while the coarsest keeps
    128 px (a 560 px frame with a few pixels of motion needs its 140 px level); levels of more
    than ``max_pixels`` pixels not run (at least the coarsest is), ``levels_skip`` fewer still."""
    factors = [1]
    while min(shape) / (factors[-1] * 2) >= o["min_size"]:
        factors.append(factors[-1] * 2)
    while len(factors) < o["min_levels"] and min(shape) / (factors[-1] * 2) >= 128:
        factors.append(factors[-1] * 2)
    factors = factors[::-1]
    size = shape[0] * shape[1]
    run = [k for k in factors if size / (k * k) <= o["max_pixels"]] or factors[:1]
    run = run[: len(run) - min(int(o["levels_skip"]), len(run) - 1)]
    its = list(o["iterations"])
    its = (its + [its[-1]] * len(run))[: len(run)]  # a small image runs the coarse budgets
    return list(zip(run, its))


# the thinning field's coefficients are in percent: a 1 % change of a line integral and a 1 px
# shift of a structure of ~100 px change the residual alike, so L-BFGS sees both on one scale
_GAIN_UNIT = 0.01


def _thinning_basis(g_grid, factor, shape):
    """The thinning lattice's row and column B-spline matrices at a level of ``shape``."""
    Br, Bc, _, _ = g_grid.matrices(factor)
    return Br[: shape[0]], Bc[: shape[1]]


def _thinning_field(g_grid, coeffs, factor, shape):
    """The thinning field ``b`` (float32, a level of ``shape``) of coefficients in percent."""
    Br, Bc = _thinning_basis(g_grid, factor, shape)
    C = (coeffs * _GAIN_UNIT).reshape(g_grid.nr, g_grid.nc).astype(np.float32)
    return np.ascontiguousarray((Br @ (Bc @ C.T).T).astype(np.float32))


def _objective(level, grid, base, lam, factor, balance, gain=None, coarse=()):
    """``fun(c) -> (energy, gradient)`` of one level's lattice on top of the coarser ``base``.

    ``balance="frame"``: data: the similarity summed over the level's pixels per ``_N_REF`` full-resolution pixels
    (rc's alpha divided by factor^2 by the caller: area averaging divides the noise variance
    by it, so a structure costs the same at every level). Bending energy: the mean squared
    second derivative of the field in frame fractions over the frame in frame fractions,
    ``lam * sum((L c)^2) / n_control * frame^2 / spacing^4`` (c in full-resolution pixels),
    the same for a given motion at every lattice, level and image size. ``"lattice"``: the
    mean similarity and ``lam * sum((L c)^2) / n_control``.

    ``coarse``: ``(grid, lam)`` of coarser lattices refitted with this one (``joint``): their
    coefficients follow this lattice's in ``x`` (before the thinning field's), their field is
    added to ``base`` and each keeps the bending weight it was fitted with."""
    if balance == "frame":
        frame = float(min(grid.shape))
        data_w = level.n * (1.0 if level.similarity == "rc" else factor * factor) / _N_REF

        def bend_weight(g, lam_g):
            return lam_g * frame**2 / (g.spacing**4 * g.nr * g.nc)

    else:  # "lattice": the mean similarity; the bending energy per control point, in pixels
        data_w = 1.0

        def bend_weight(g, lam_g):
            return lam_g / (g.nr * g.nc)

    lattices = [(grid, bend_weight(grid, lam))] + [(g, bend_weight(g, lam_g)) for g, lam_g in coarse]
    n_d = sum(g.n_params for g, _ in lattices)
    if gain is not None:  # (gain lattice, its bending weight): the thinning field's coefficients follow
        g_grid, g_lam = gain
        Br, Bc = _thinning_basis(g_grid, factor, level.shape)
        BrT = Br.T.tocsr()
        Lg = g_grid.L
        w_gbend = g_lam / (g_grid.nr * g_grid.nc)
        level.fit_gain = True

    def fun(x):
        if gain is not None:
            level.gain = _thinning_field(g_grid, x[n_d:], factor, level.shape)
        xs, _ = _split(x, [g for g, _ in lattices])
        total = base
        if coarse:  # the coarser lattices' field, as they stand
            total = base + _fields([(g, c) for (g, _), c in zip(lattices[1:], xs[1:])], factor, base.shape[1:])
        e, g0 = level.lattice_energy(grid, xs[0], total, factor)
        # lattice_energy leaves dE/dd in level._dy, level._dx: each coarser lattice's adjoint of it
        grads = [g0] + [g.adjoint_rows(level._dy, level._dx, factor) for g, _ in lattices[1:]]
        e *= data_w
        for (g, w), xg, gg in zip(lattices, xs, grads):
            gg *= data_w
            X = xg.reshape(2, -1)
            LX = np.stack([g.L @ X[0], g.L @ X[1]])
            e += w * float(np.sum(LX * LX))
            gg += (2 * w) * np.concatenate([g.L.T @ LX[0], g.L.T @ LX[1]])
        grad = np.concatenate(grads)
        if gain is not None:
            gC = (BrT @ (Bc.T @ level.gain_grad.T).T).astype(np.float64).ravel() * (data_w * _GAIN_UNIT)
            LC = Lg @ x[n_d:]
            e += w_gbend * float(LC @ LC)
            gC += (2 * w_gbend) * (Lg.T @ LC)
            grad = np.concatenate([grad, gC])
        return e, grad

    return fun


# a level stops once its last 5 iterations moved the field by less than this (99th percentile,
# full-resolution px): L-BFGS's own tolerances are absolute for energies under 1 (scipy divides
# by max(|f|, 1)), so on a noise-free pair, where rc's energy goes to ~0 and the thinning field
# keeps refining, every level ran its whole budget (a 160 px synthetic slab: 250 iterations
# instead of 84, three times the time), for changes of the field no measure here can see
_STILL_PX = 0.01


def _split(x, lattices):
    """``x`` cut into each lattice's coefficients (in ``lattices``' order) and what follows."""
    cuts = np.cumsum([0] + [g.n_params for g in lattices])
    return [x[a:b] for a, b in zip(cuts[:-1], cuts[1:])], x[cuts[-1] :]


def _p99_below(v, limit) -> bool:
    """``np.percentile(v, 99) < limit`` (linear interpolation between the order statistics ``i``
    and ``i + 1``, ``i = floor(0.99 (n - 1))``), decided by counting the values at or over
    ``limit`` wherever that count settles it (both order statistics under the limit, or the lower
    one at or over it) and by the percentile only when the limit falls between them: the same
    answer, without a partial sort at every iteration (a tenth of the time)."""
    n = v.size
    i = int(0.99 * (n - 1))
    above = int(np.count_nonzero(v >= limit))
    if above < n - i - 1:
        return True
    if above >= n - i:
        return False
    return bool(np.percentile(v, 99) < limit)


def _fit_level(fun, grid, n_it, coarsest, x0=None, coarse=(), check=None, extend=None):
    """L-BFGS on one level; ``(result, move)``, ``move`` how far the last 5 iterations moved the
    field (99th percentile of |change|, full-resolution pixels, evaluated on the ``coarsest``
    level's grid: the field is smooth on it; with ``coarse`` lattices refitted alongside, whose
    coefficients follow ``grid``'s in ``x``, their change counts too). Stops early when that is
    under ``_STILL_PX``. ``check``: ``(iteration, fn)``, ``fn(x)`` called at that iteration (it
    does not change the path); a message from it stops the level there, in
    ``result["abandoned"]``. ``extend``: ``(more, converge_px, settles)``: at the budget's end
    (``n_it`` iterations) the run goes on, up to ``more`` iterations more, only if the field still
    moves by more than ``converge_px`` and ``settles(x)`` (the residual passes the checks); else it
    stops there, where the budget alone would have stopped it (the same iterate: L-BFGS's path
    does not depend on its budget)."""
    from scipy.optimize import minimize  # here, not at the module's import (see the imports)

    last = collections.deque(maxlen=6)
    stopped, count = [], [0]
    lattices = [grid, *coarse]

    def change():
        steps, _ = _split(last[-1] - last[0], lattices)
        d = sum(g.field(c, coarsest) for g, c in zip(lattices, steps)) * coarsest
        return np.sqrt((d * d).sum(axis=0)).ravel()

    def moved():
        return float(np.percentile(change(), 99))

    def moved_now():  # as the level's end measures it (``inf`` before 6 iterates)
        return moved() if len(last) == last.maxlen else float("inf")

    def track(intermediate_result):  # scipy passes the iterate by this name (sole parameter)
        last.append(intermediate_result.x.copy())
        count[0] += 1  # (the iterate carries no iteration number)
        if check is not None and count[0] == check[0] and (why := check[1](last[-1])):
            stopped.append(why)
            raise StopIteration
        if extend is not None and count[0] == n_it and not (moved_now() > extend[1] and extend[2](last[-1])):
            raise StopIteration  # converged by the budget's measure, or lost: no more iterations
        if len(last) == last.maxlen and _p99_below(change(), _STILL_PX):
            raise StopIteration  # scipy ends the minimisation with the current iterate

    res = minimize(
        fun,
        np.zeros(grid.n_params) if x0 is None else x0,
        jac=True,
        method="L-BFGS-B",
        callback=track,
        options=dict(
            maxiter=int(n_it) + (int(extend[0]) if extend is not None else 0), maxcor=10, gtol=1e-9, ftol=1e-10
        ),
    )
    move = moved() if len(last) == last.maxlen else float("inf")
    if stopped:
        res["abandoned"] = stopped[0]
    return res, move


def _prepare(fixed, moving, o):
    """Both images normalised by the fixed one's 1-99 % range, high-passed if asked."""
    f, m = _normalise(fixed, moving)
    if o.get("highpass") and o["highpass_on"] == "images":  # in place, one scratch frame: slow to touch the first time
        sigma = o["highpass"] * min(f.shape)
        scratch = np.empty_like(f)
        _highpass(f, sigma, out=f, scratch=scratch)
        _highpass(m, sigma, out=m, scratch=scratch)
    return f, m


def _noise_alpha(f, m, o):
    """``o["alpha"] = noise_alpha x sigma^2`` (in place), ``sigma`` the normalised pair's noise
    over the body (the mean of the two images' variances; ``_confidence.object_noise``), floored
    at the model error no similarity fits (``MODEL_FLOOR`` of the range): a noise-free pair still
    leaves interpolation's residual."""
    sigma = max(float(np.sqrt((object_noise(f) ** 2 + object_noise(m) ** 2) / 2)), MODEL_FLOOR)
    o["noise_sigma"] = sigma
    o["alpha"] = o["noise_alpha"] * sigma * sigma


def _register_binned(fixed, moving, mask, k, how, overrides):
    """:func:`_bspline_register` of the pair area-averaged by ``k`` (``how``: its similarity,
    preset and callback; ``bin_pixels`` off), the field upsampled to ``fixed``'s shape;
    ``info["binned"]`` is ``k``."""
    from radiokit.register import _bin, _bin_mask

    shape = (fixed.shape[0] // k, fixed.shape[1] // k)
    if min(shape) < 8:  # register()'s own least size: OpenCV asserted on an empty pair
        raise ValueError(
            f"bin_pixels={overrides.get('bin_pixels')}: bins the {fixed.shape} pair by {k} to {shape}, "
            "too small to register (8 px a side at least)"
        )
    small = None if mask is None else _bin_mask(mask, k)
    d, info = _bspline_register(_bin(fixed, k), _bin(moving, k), small, **how, **dict(overrides, bin_pixels=0))
    info["binned"] = k
    return _upsample_field(d, k, fixed.shape), info


# refit_thinning: the thinning field measured again after a first pass, from the interior
# (REFIT_INTERIOR of the smaller side inside the body: there the body's line integral is smooth,
# so the first pass's error there hardly moves the ratio of fixed to warped moving), as a
# polynomial of degree REFIT_DEGREE over the frame, and the pair registered again with it
# divided out and the thinning term off. Why: rc's residual is high-passed, so inside the body a
# slow thinning is invisible to it and the thinning term is pinned only at the body's edge, where
# a scaled edge and a shifted one look alike (b P ~ grad P . d): at 2240 with texture = noise the
# edge band carried 0.6-0.7 px of normal error; with the true thinning divided out, 0.13-0.16.
# Both values chosen on TRAINING seeds 1-2 at 2240 (texture = noise, 1/10, +-10 % thinning):
# interior 0.067 / 0.134 of the side and degree 3 / 4 (benchmarks/README.md, "The thinning
# measured in the interior").
REFIT_INTERIOR = 0.134
REFIT_DEGREE = 4
# The second pass starts from the first's lattices and runs the finest level only, for this many
# iterations (joint refits the coarser lattices there all the same): the first pass's field is
# within a pixel or so, which is what the coarse levels exist to reach. TRAINING seeds 1-3 at
# 2240, 1/10, texture = noise and 0.3x noise, mean median EPE: run again from scratch 0.380 /
# 1.569 px, warm with 120 iterations 0.384 / 1.558, 60: 0.383 / 1.542, 40: 0.378 / 1.613, 30:
# 0.384 / 1.659; iterations in all 740, 490, 430, 410, 400 (benchmarks/README.md, "`auto` under
# 10 s on weak texture at 2240 ... (session 15)")
REFIT_ITERATIONS = 60
# refit_again (preset weak): the second pass's field is nearer the truth at the body's edge than
# the first's, so the ratio there is biased less and the interior may come closer to the edge,
# where the polynomial otherwise extrapolates (what was left of the edge band's error). Interior
# and iterations chosen on TRAINING seeds at 2240 (benchmarks/README.md, "`weak` with the
# jitter: ..., the thinning measured twice (session 20)"), where each pass keeps its own budget
# (60 + 30): splitting the same 60 iterations 30 + 30 saved ~0.2 s of CPU at 2240 but lost on
# both sets of training rows (0.448 against 0.446 px; the flag family's one good result a cut
# second pass left "still moving"; session 21)
REFIT_AGAIN_INTERIOR = 0.067
REFIT_AGAIN_ITERATIONS = 30
# abandon_px checks the level before the finest at this share of its iterations as well as at its
# end: a run far off at the end was far off halfway (the 55 textured TRAINING pairs of
# _auto.ABANDON: the residual's motion after 60 of default's 120 iterations there read at most
# 0.28 px on the 17 runs that settled, 0.28 on one that fell back to weak (1120, polished anyway)
# and 0.62 or more on the other 37; half chosen before the data, not tuned; benchmarks/README.md,
# session 15). The check does not change the path of a run it lets go on.
ABANDON_AT = 0.5
# ... and once more this many iterations into the finest level, against the checks' own line
# (_MAX_RESIDUAL_MOTION): a run that passes the level before the finest a little off (abandon_px is
# a pixel in ``auto``: natural images read up to 0.96 px there and settle after their finest level)
# but cannot mend it there is still over the line after a few of its iterations. TRAINING pairs at
# 2240, the residual's motion after 10 / 20 / 40 finest iterations: natural images that settle
# (astronaut, brick, coffee, chelsea, retina, rocket; benchmarks/README.md, session 16) at most
# 0.24 / 0.17 / 0.12 px; the family's pairs under the pixel that do not (physical motion, texture =
# noise; texture 0.3x the noise, correlation 1/4) at least 0.45 / 0.45 / 0.46 px. 20 its: about a
# second at 2240, against the finest level's 3-4 s
ABANDON_FINEST = 20


def _register_refit(fixed, moving, mask, how, overrides):
    """``refit_thinning``: a first pass as asked, the thinning measured in the interior
    (:func:`_interior_thinning`), and a second pass on ``fixed`` with it divided out and the
    thinning term off; ``refit_again`` times more, the thinning measured again from the last
    pass's field nearer the edge (``REFIT_AGAIN_INTERIOR``) and a pass of
    ``REFIT_AGAIN_ITERATIONS`` from its lattices; a thinning declined ends the refit there.
    ``info["thinning_refit"]`` says what was done."""
    first = dict(overrides, refit_thinning=False, refit_again=0, rim=0.0)  # the rim helps the first pass find b
    d, info = _bspline_register(fixed, moving, mask, **how, **first)
    if "abandoned" in info:  # stopped short of its finest level (abandon_px): nothing to refine
        return d, info
    n_again = _options(how["preset"], overrides)["refit_again"]
    rounds = [(REFIT_INTERIOR, REFIT_ITERATIONS)] + [(REFIT_AGAIN_INTERIOR, REFIT_AGAIN_ITERATIONS)] * n_again
    again = dict(overrides, refit_thinning=False, refit_again=0, gain=0.0, rim=0.0)
    notes = []
    side = _fixed_side(fixed, mask)  # the same for every round: measured once
    rim = _options(how["preset"], overrides)["rim"]
    data_mask = _without_rim(side, mask, rim) if rim else mask
    if rim and np.count_nonzero(data_mask) < 0.25 * (side[2] > 0).sum():
        # a small body (or a wide rim) would lose most of its data to it: the passes keep the rim
        rim, data_mask = 0.0, mask
    ran = False
    for interior, n_it in rounds:
        b, level, note = _interior_thinning(fixed, moving, d, mask, interior, side)
        notes.append(note if not notes else f"measured again: {note}")
        if b is None:  # declined (at a later round: the last pass, which ran its full budget, stands)
            break
        f2 = (level + (side[0] - level) / (1.0 + b)).astype(np.float32)  # side[0]: fixed as float32
        d2, info2 = _bspline_register(f2, moving, data_mask, **how, start=(info["lattices"], n_it), **again)
        info2["iterations"] += info["iterations"]
        d, info, ran = d2, info2, True
    info["thinning_refit"] = "; ".join(notes)
    info["options"]["rim"] = rim if ran else 0.0  # what the passes ran with (none ran: not used)
    return d, info


def _without_rim(side, mask, rim):
    """``mask`` (None: the frame) less the body's outermost ``rim`` x the smaller side, ``side``
    from :func:`_fixed_side` (its distance to the edge of the body, within ``mask``: a mask's own
    edge counts as the body's)."""
    dist = side[2]
    keep = dist >= rim * min(dist.shape)
    return keep if mask is None else keep & np.asarray(mask, bool)


def _fixed_side(fixed, mask):
    """What :func:`_interior_thinning` measures on ``fixed`` alone, the same for every round of
    :func:`_register_refit`: ``(fixed as float32, the open beam's level, the distance to the
    body's edge, fixed smoothed by 2 px)``."""
    import cv2

    from radiokit.register._confidence import _gauss, _object, noise_sigma

    f = np.asarray(fixed, np.float32)
    level = float(np.median(np.concatenate([f[0], f[-1], f[:, 0], f[:, -1]])))
    # the registration as before: session 20 changed only the checks' object (benchmarks/README.md)
    body = _object(f, noise_sigma(f), collimator=False)
    if mask is not None:
        body &= np.asarray(mask, bool)
    # the interior by the distance to the body's edge (an erosion by a disc of 300 px is slow)
    return f, level, cv2.distanceTransform(body.astype(np.uint8), cv2.DIST_L2, 5), _gauss(f, _THINNING_BLUR)


def _interior_thinning(fixed, moving, d, mask, interior=REFIT_INTERIOR, side=None):
    """``(b, level, note)``: the thinning ``fixed - level = (1 + b) (warped moving - level)``
    (``level`` the open beam's, the frame's border median), ``b`` a polynomial of degree
    ``REFIT_DEGREE`` in frame coordinates fitted by least squares over the body's interior
    (``interior`` x the smaller side inside its edge; both images smoothed by 2 px, ~150k
    samples). ``b`` None, with why, when the interior is under 5 %
    of the frame, when an additive change (``fixed = warped moving + a``, ``a`` a polynomial of the
    same degree: a stale flat field's, which rc's high-passed residual tolerates as it is) fits the
    interior better, or when the thinning found is implausible (over 50 % anywhere on the body).
    The two models are told apart by where the change falls: a thinning scales the body's line
    integral, an additive change does not follow it. ``side``: :func:`_fixed_side` of ``fixed``
    and ``mask`` if already measured."""
    from radiokit.register._confidence import _gauss

    f, level, dist, f_smooth = _fixed_side(fixed, mask) if side is None else side
    body = dist > 0
    inner = dist >= interior * min(f.shape)
    if inner.mean() < 0.05:
        return None, level, f"not refitted: the body's interior is {100 * inner.mean():.1f} % of the frame (< 5 %)"
    step = max(1, int(np.sqrt(inner.sum() / 150_000)))
    yy, xx = np.nonzero(inner[::step, ::step])
    yy, xx = yy * step, xx * step
    fs = f_smooth[yy, xx] - level
    # the warped moving image smoothed on the sampled rows alone (and the blur's reach around
    # them): the same numbers as over the whole frame, in about half the time (the interior is
    # 40-60 % of the rows at 2240)
    r0, r1 = max(int(yy.min()) - _BLUR_REACH, 0), min(int(yy.max()) + 1 + _BLUR_REACH, f.shape[0])
    warped = _warp_rows(np.asarray(moving, np.float32), _field(d)[:, r0:r1], r0)
    ws = _gauss(np.nan_to_num(warped), _THINNING_BLUR)[yy - r0, xx] - level
    vy, vx = _frame_powers(f.shape, 2 * REFIT_DEGREE + 1)
    py, px = vy.take(yy, axis=1), vx.take(xx, axis=1)  # the samples' powers, gathered
    c, rss_b = _poly_fit(py, px, ws, fs - ws, REFIT_DEGREE)
    rss_a = _poly_fit(py, px, None, fs - ws, REFIT_DEGREE)[1]
    if rss_a is not None and rss_b is not None and rss_a <= rss_b:
        return None, level, "not refitted: an additive change fits the interior better than a thinning"
    n = REFIT_DEGREE + 1
    # separable: sum c_ij y^i x^j, in double as before (a float32 product moved b by an ulp in two
    # thirds of the frame, and the second pass follows such changes; benchmarks/README.md), by
    # bands of rows: no frame of doubles (3x faster at 2240 on one thread; on the pool, slower)
    b, rows_c = np.empty(f.shape, np.float32), vy[:n].T @ c
    for sl in _row_bands(f.shape[0]):
        b[sl] = rows_c[sl] @ vx[:n]
    on_body = b[body]
    lo, hi = float(on_body.min()), float(on_body.max())
    if not (-0.5 < lo and hi < 0.5):
        return None, level, f"not refitted: the thinning found, {100 * lo:.0f} to {100 * hi:.0f} %, is implausible"
    note = (
        f"thinning refitted from the interior ({100 * inner.mean():.0f} % of the frame, degree {REFIT_DEGREE}): "
        f"{100 * lo:.1f} to {100 * hi:.1f} % over the body"
    )
    return b, level, note


# the interior thinning's blur (px) and how far OpenCV's Gaussian of that sigma reaches on
# float32 (its kernel: 2 x round(4 sigma) + 1 taps), with a row to spare: rows further than
# this from a band's edge are blurred as in the whole frame
_THINNING_BLUR = 2.0
_BLUR_REACH = int(round(4 * _THINNING_BLUR)) + 1


@functools.lru_cache(maxsize=4)
def _frame_powers(shape, n):
    """``(vy, vx)``: the frame's row and column coordinates in [-0.5, 0.5) raised to the
    powers ``0 .. n - 1``, ``vy[i]`` the rows' ``y^i`` (``np.vander``, increasing, transposed: a
    power's values contiguous), built once per frame size."""
    rows, cols = shape
    vy = np.vander(np.arange(rows) / rows - 0.5, n, increasing=True).T.copy()
    vx = np.vander(np.arange(cols) / cols - 0.5, n, increasing=True).T.copy()
    vy.flags.writeable = vx.flags.writeable = False  # cached: shared by every call
    return vy, vx


# the largest condition number of the column-scaled normal equations solved as they are: their
# error is then under cond x 1e-16 relative, far below the float32 thinning field's rounding
# (the interior's degree-4 monomials read ~300 at 2240, whatever the coordinates' scale: the
# columns' scaling takes it out; lstsq's own error there is ~2e-14, the normal equations' 2e-13)
_NORMAL_COND = 1e8


def _poly_fit(py, px, w, t, degree):
    """``(c, rss)``: ``np.linalg.lstsq(A, t)`` for the design ``A[k] = w_k y_k^i x_k^j`` (every
    ``i + j <= degree``; ``w`` None: 1), ``c[i, j]`` its coefficient of ``y^i x^j`` (0 where ``i +
    j > degree``), ``rss`` the residual sum of squares (None where lstsq gives none: rank
    deficient). ``py``, ``px``: the samples' powers ``y^0 .. y^(2 degree)`` and of ``x``, one
    power a row (``_frame_powers``). Solved by the normal equations, whose matrix needs only the
    samples' moments ``sum w^2 y^p x^q`` (one (2 degree + 1)^2 product instead of the SVD of the
    ~150k x 15 design: ~6x less time at 2240); conditioned worse than ``_NORMAL_COND`` (columns
    scaled to unit norm), by lstsq on the design itself."""
    n = degree + 1
    terms = [(i, j) for i in range(n) for j in range(n - i)]  # monomials' order
    # in double: float32 samples squared in float32 would round the moments at 6e-8
    w = None if w is None else np.asarray(w, np.float64)
    t = np.asarray(t, np.float64)
    w2 = None if w is None else w * w
    moments = (py if w2 is None else py * w2) @ px.T
    gram = np.array([[moments[i + k, j + m] for k, m in terms] for i, j in terms])
    wt = t if w is None else w * t
    rhs = (py[:n] * wt) @ px[:n].T
    rhs = np.array([rhs[i, j] for i, j in terms])
    scale = np.sqrt(np.diag(gram))
    c = np.zeros((n, n))
    if len(t) > len(terms) and np.all(scale > 0) and np.linalg.cond(gram / np.outer(scale, scale)) < _NORMAL_COND:
        coef = np.linalg.solve(gram / np.outer(scale, scale), rhs / scale) / scale
        for (i, j), v in zip(terms, coef):
            c[i, j] = v
        # the residual itself, not an expansion of it: sum_i y^i (sum_j c_ij x^j) at the samples
        fit = (py[:n] * (c @ px[:n])).sum(axis=0)
        r = (fit if w is None else w * fit) - t
        return c, float(r @ r)
    design = np.stack([py[i] * px[j] for i, j in terms], axis=-1)
    coef, rss = np.linalg.lstsq(design if w is None else design * w[:, None], t, rcond=None)[:2]
    for (i, j), v in zip(terms, coef):
        c[i, j] = v
    return c, (float(rss[0]) if rss.size else None)


def _bspline_register(
    fixed,
    moving,
    mask=None,
    *,
    similarity="rc",
    preset="default",
    callback=None,
    start=None,
    start_lattices=None,
    **overrides,
):
    """Long because the pyramid's loop carries the lattices, the thinning field and the
    history from level to level. ``start``: ``(lattices, iterations)``, another run's
    ``info["lattices"]`` on a pair of the same shape and options: only the finest level is run,
    from them, for that many iterations. ``start_lattices``: another run's lattices (a pair of the
    same shape and binning; not with silent or refit presets: :func:`_checked_start`): their field
    stays as it is, and only this preset's finest level (with its own lattice, from zero, and
    budget) and its polish run on top of it (``auto``: the plain preset's finest level after the
    weak run, ``_auto.FINEST_FROM_WEAK``)."""
    o = _options(preset, overrides)
    k = _bin_factor(fixed.shape, o["bin_pixels"])
    # start_lattices go with the pair to a binned run (the lattices of a run binned alike) and a refit's first pass
    how = dict(similarity=similarity, preset=preset, callback=callback, start_lattices=start_lattices)
    if k > 1:  # the pair area-averaged by k, registered, the field upsampled (presets' comment)
        # abandon_px is in full-resolution pixels; the binned run measures in its own
        d, info = _register_binned(fixed, moving, mask, k, how, dict(overrides, abandon_px=o["abandon_px"] / k))
        info["options"].update(bin_pixels=o["bin_pixels"], abandon_px=o["abandon_px"])
        return d, info
    if o["refit_thinning"] and similarity == "rc" and o["gain"]:
        if start_lattices is not None:  # its passes refit the field from their own start
            raise ValueError(f"start_lattices: not with refit_thinning (preset {preset!r}); use a preset without it")
        return _register_refit(fixed, moving, mask, how, overrides)
    if similarity != "rc":  # the residual's high-pass and the thinning term act on rc's residual
        # (polish was measured for rc only)
        o.update(highpass_on="images", gain=0.0, polish=0)
    f, m = _prepare(fixed, moving, o)
    if o["noise_alpha"]:
        _noise_alpha(f, m, o)
    levels = _pyramid(f.shape, o)
    maskf = None if mask is None else mask.astype(np.float32)  # once, not per level
    affine, init_note = _initial(fixed, moving, o)
    coarsest, finest = levels[0][0], levels[-1][0]
    grids, history = [], []  # one lattice per level, spacing halving with the pixels
    x_start = None
    if start is not None:  # the coarser lattices as another run left them, its finest as the start
        lattices, n_it = start
        grids, x_start = list(lattices[:-1]), lattices[-1][1]
        levels = [(levels[-1][0], n_it)]
    elif start_lattices is not None:  # another run's field as the coarser levels': the finest level on top
        grids, levels = _checked_start(start_lattices, f.shape, affine), levels[-1:]
    # the thinning field: one coarse lattice for all levels, its coefficients carried down
    gain = None if not o["gain"] else [BSplineField(f.shape, o["gain"] * min(f.shape)), None]
    total_its, converged, message, abandoned, still = 0, True, "", {}, {}
    # the checks' measure of a field's residual (coarse_residual_motion): built once, when first needed
    measured = functools.cache(lambda: _coarse_measure(fixed, moving, mask))
    for factor, n_it in levels:
        # joint: the coarser lattices are refitted with the finest's, so their field is not in base
        # (not another run's lattices, kept as they are: start_lattices)
        coarse = grids if o["joint"] and factor == finest and start_lattices is None else []
        base = _fields([] if coarse else grids, factor, tuple(-(-n // factor) for n in f.shape))
        if affine is not None:
            base += affine.field(base.shape[1:], factor)
        where = (factor, n_it, coarsest, finest)
        # abandon_px: the level before the finest is checked partway (ABANDON_AT) and at its end
        last_coarse = factor != finest and factor == levels[-2:][0][0] and _abandons(fixed, o, finest)
        check = None
        if start_lattices is not None and o["abandon_px"]:  # on another run's field: checked against its line
            at = int(n_it * ABANDON_AT)
            when = f"after {at} of {n_it} iterations on the field it started from"
            check = (at, lambda lat, when=when: _far_off(measured(), grids + [lat], affine, o, when, "at"))
        elif last_coarse:
            at = int(n_it * ABANDON_AT)
            when = f"after {at} of {n_it} iterations of the level before it"
            check = (at, lambda lat, when=when: _far_off(measured(), grids + [lat], affine, o, when))
        elif factor == finest and not coarse and n_it > ABANDON_FINEST and _abandons(fixed, o, finest):
            when = f"after {ABANDON_FINEST} of {n_it} iterations"
            check = (ABANDON_FINEST, lambda lat, when=when: _far_off(measured(), grids + [lat], affine, None, when))
        extend = None
        if factor == finest and o["extend"]:  # past its budget only while slow, not lost (``extend``)
            fixed_part = [] if coarse else grids  # joint: the coarser lattices are in what it is given
            settles = lambda lats, fp=fixed_part: _settles(measured(), fp + lats, affine)
            extend = (o["extend"], o["converge_px"], settles)
        grid, res, move = _run_level(f, m, maskf, similarity, o, where, base, gain, coarse, x_start, check, extend)
        if not np.all(np.isfinite(res.x)):
            return np.zeros((2,) + f.shape, np.float32), dict(
                iterations=total_its, converged=False, options=o, message="optimiser produced non-finite values"
            )
        grids.append((grid, res.x))
        total_its += int(res.nit)
        history.append(
            dict(
                factor=factor,
                spacing=grid.spacing,
                iterations=int(res.nit),
                energy=float(res.fun),
                status=int(res.status),
                last_move_px=move,
            )
        )
        if callback is not None:
            callback(factor, res)
        if factor == finest and (why := res.get("abandoned")):
            converged, message, abandoned = False, why, {"abandoned": why}
        elif (
            factor == finest
            and start_lattices is not None
            and o["abandon_px"]
            and (
                why := _far_off(
                    measured(), grids, affine, o, f"after its {res.nit} iterations on the field it started from", "at"
                )
            )
        ):
            converged, message, abandoned = False, why, {"abandoned": why}
        elif factor == finest:
            converged, message = _converged(res, move, o["converge_px"])
            # the budget ended with the field still moving: register()'s checks judge whether that
            # is slow or lost (radiokit.register._slow_not_lost), so they are told it was this and
            # no other stop, and how coarse the level that moved was
            still = {} if converged else {"still_moving_px": float(move), "finest_binning": int(finest)}
        elif last_coarse and (
            why := res.get("abandoned") or _far_off(measured(), grids, affine, o, "after the level before it")
        ):
            converged, message, abandoned = False, why, {"abandoned": why}
            break
    # polish: only on a textured interior, and a field that passes the checks' residual line
    asked = finest > 1 and o["polish"] and start is None and not abandoned
    if asked and _textured(fixed, mask) and _settles(measured(), grids, affine):
        res, move = _polish(f, m, maskf, similarity, o, coarsest, grids, affine, gain)
        total_its += int(res.nit)
        history.append(
            dict(
                factor=1,
                spacing=grids[-1][0].spacing,
                iterations=int(res.nit),
                energy=float(res.fun),
                status=int(res.status),
                last_move_px=move,
                polish=True,
            )
        )
        if callback is not None:
            callback(1, res)
        # converged and message stay the pyramid's: a finest level still moving is a field not
        # found (the rocket's sky at 2240: 3.99 px flagged "still moving", a polish's 20
        # iterations then settled at 3.86 px), and a polish cut by its budget refines a field
        # that had converged (TRAINING pictures: never worse than without it)
    d = _fields(grids, 1, f.shape)  # B-splines are defined everywhere: full resolution even if levels were skipped
    if affine is not None:
        d += affine.field(f.shape)
    return d, dict(
        init=init_note,
        iterations=total_its,
        converged=converged,
        message=message,
        regularisation=o["regularisation"],
        levels=history,
        lattices=grids,
        lattices_whole=affine is None,  # the field is theirs alone (not a silhouette's map added)
        options=o,
        **abandoned,
        **still,
    )


def _checked_start(start_lattices, shape, affine) -> list:
    """``start_lattices`` as a list, if they are lattices of a pair of ``shape`` (after binning)
    and this run adds no silhouette map to them; else ValueError (another shape's or binning's
    lattices gave a wrong field, trusted)."""
    if affine is not None:
        raise ValueError("start_lattices: not with a preset that starts from the silhouette's map (silent)")
    try:
        lattices = list(start_lattices)
        ok = all(isinstance(g, BSplineField) and np.size(c) == g.n_params for g, c in lattices)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError("start_lattices: expected a Registration.lattices list of (lattice, coefficients) pairs")
    if any(g.shape != tuple(shape) for g, _ in lattices):
        got = sorted({g.shape for g, _ in lattices})
        raise ValueError(
            f"start_lattices: lattices of a {got} frame, this run's is {tuple(shape)} (another pair or binning)"
        )
    return lattices


def _textured(fixed, mask) -> bool:
    """Whether the body's interior is not silent, as ``auto`` judges it (``_auto.choose`` does not
    fall back to ``silent``: the interior's texture-to-noise ratio at least ``TEXTURE_LOW`` with
    noise, or no interior to judge, as in a picture that fills the frame): a silent body has
    nothing for ``polish``'s full-resolution images to see (the family's textureless pairs at
    2240: 8.469 -> 8.471 px for 3 s more)."""
    from radiokit.register._auto import AUTO_PRESETS, choose

    return choose(fixed, "auto", mask).preset != AUTO_PRESETS["auto"][2]


def _polish(f, m, maskf, similarity, o, coarsest, grids, affine, gain):
    """``polish``: the finest lattice refitted on the full-resolution images for ``o["polish"]``
    iterations from where the pyramid left it (the same lattice and bending weight: a second
    lattice of that spacing on top would halve the prior's weight there, and fitted the noise of
    analytic_pair at 2240, 0.036 -> 0.044 px); ``grids[-1]`` replaced; ``(result, move)``.
    Run only on a non-silent interior and a field whose residual already passes the checks' line
    (the caller's gates, :func:`_textured` and :func:`_settles`): the pyramid stops at
    ``max_pixels`` (the 1120 px level at 2240) for time, and on rich texture the half-resolution
    images leave 0.1-0.17 px that the full-resolution ones see (natural pictures at 2240,
    TRAINING: benchmarks/README.md, "A full-resolution polish (session 23)"); a field the checks
    would flag is not worth the time (``auto`` moves on to its fallback)."""
    last, x0 = grids[-1]
    base = _fields(grids[:-1], 1, f.shape)
    if affine is not None:
        base += affine.field(base.shape[1:], 1)
    where = (1, o["polish"], coarsest, 1)
    grid, res, move = _run_level(f, m, maskf, similarity, o, where, base, gain, [], x0, spacing=last.spacing)
    if np.all(np.isfinite(res.x)):  # else the pyramid's field stands
        grids[-1] = (grid, res.x)
    return res, move


def _abandons(fixed, o, finest) -> bool:
    """Whether ``abandon_px`` applies: asked for, and the finest level finer than the quality
    checks' binning (a frame over ~0.4 Mpx), so that a level before it is where they look."""
    from radiokit.register import _assess_binning

    return bool(o["abandon_px"]) and finest < _assess_binning(fixed.size)


def _far_off(measure, lattices, affine, o, when, where="before"):
    """Why the run stops (``abandon_px``), or None: the field of ``lattices`` (and ``affine``) at
    the checks' binning, its residual's motion measured as they would measure it (``measure``:
    ``coarse_residual_motion``'s ``(k, shape, motion)``), over ``abandon_px`` before the finest
    level (``o`` the options: a misalignment the finer level is not there to mend) or, with ``o``
    None, over the checks' own line at the finest level (``ABANDON_FINEST`` iterations in): ``auto``
    then goes to its fallback. ``when``: for the message; ``where``: "before" the finest level, or
    "at" it (``start_lattices``: its one level checked against ``o``'s line)."""
    from radiokit.register import _MAX_RESIDUAL_MOTION

    line, where, why = (
        (_MAX_RESIDUAL_MOTION, "at", f"> {_MAX_RESIDUAL_MOTION:g}")
        if o is None
        else (o["abandon_px"], where, f"abandon_px={o['abandon_px']:.3g}")
    )
    motion = _motion(measure, lattices, affine)
    if not motion > line:
        return None
    return f"abandoned {where} the finest level: the residual still moves {motion:.2f} px {when} ({why})"


def _coarse_measure(fixed, moving, mask):
    """``coarse_residual_motion`` (imported here: the register package imports this module)."""
    from radiokit.register import coarse_residual_motion

    return coarse_residual_motion(fixed, moving, mask)


def _motion(measure, lattices, affine) -> float:
    """The residual's motion of the field of ``lattices`` (and ``affine``) as the checks measure
    it (``measure``: ``coarse_residual_motion``'s ``(k, shape, motion)``), full-resolution px."""
    k, shape, motion_of = measure
    d = _fields(lattices, k, shape)
    if affine is not None:
        d += affine.field(shape, k)
    return motion_of(d)


def _settles(measure, lattices, affine) -> bool:
    """Whether that motion is within the checks' line (``_MAX_RESIDUAL_MOTION``): a field still
    moving there is slow to converge, not lost (``extend``)."""
    from radiokit.register import _MAX_RESIDUAL_MOTION

    return bool(_motion(measure, lattices, affine) <= _MAX_RESIDUAL_MOTION)


def _run_level(
    f, m, maskf, similarity, o, where, base, gain, coarse=(), x_start=None, check=None, extend=None, spacing=None
):
    """``(grid, result, move)`` of one pyramid level: its lattice fitted on top of ``base``
    (and, with ``gain`` = [lattice, coefficients], the thinning field refitted from the
    coarser level's, which is left in ``gain[1]``); ``result.x`` the lattice's coefficients.
    ``coarse`` (``joint``): the coarser levels' ``[(grid, coefficients)]``, refitted with this
    lattice from where they stand, each with its own bending weight; updated in place.
    ``x_start``: this lattice's first coefficients (None: zero). ``check``: ``(iteration, fn)``,
    ``fn((grid, coefficients))`` at that iteration, whose message (not None) stops the level
    there, left in ``result["abandoned"]``. ``extend``: ``(iterations, converge_px, fn)``, see
    :func:`_fit_level`; ``fn`` gets the lattices refitted here (``coarse``'s and this one).
    ``spacing``: the lattice's (None: ``spacing`` x max(1, factor / 2), the pyramid's)."""
    factor, n_it, coarsest, finest = where
    fine = factor == finest
    # coarse levels may run a larger alpha (closer to SSD) and another bending energy;
    # each coarser level's lattice stiffer by (coarsest / factor)^stiffen
    alpha = o["alpha"] * (1.0 if fine else o["coarse_alpha"]) / (factor**2 if o["balance"] == "frame" else 1)
    lam = o["regularisation"] * (1.0 if fine else o["coarse_regularisation"]) * (coarsest / factor) ** o["stiffen"]
    hp_sigma = o["highpass"] * min(f.shape) / factor if o["highpass_on"] == "residual" else 0.0
    level = _Level(f, m, maskf, factor, similarity, alpha, hp_sigma, o["smooth"], o["grid_jitter"])
    grid = BSplineField(f.shape, spacing or o["spacing"] * max(1, factor // 2))
    if gain is not None and gain[1] is not None and fine and not o["gain_fine"]:
        level.gain = _thinning_field(gain[0], gain[1], factor, level.shape)  # kept as the coarser levels left it
        gain = None
    # x: this lattice, the coarser ones refitted with it (as they stand), the thinning field
    parts = [np.zeros(grid.n_params) if x_start is None else x_start] + [c for _, c in coarse]
    if gain is not None:
        g_grid = gain[0]
        parts.append(np.zeros(g_grid.nr * g_grid.nc) if gain[1] is None else gain[1])
    x0 = np.concatenate(parts) if len(parts) > 1 or x_start is not None else None
    thinning = None if gain is None else (gain[0], o["gain_regularisation"])
    grid.lam = lam  # what ``joint`` refits it with at the finest level
    fun = _objective(level, grid, base, lam, factor, o["balance"], thinning, [(g, g.lam) for g, _ in coarse])
    if check is not None:
        check = (check[0], lambda x, fn=check[1]: fn((grid, x[: grid.n_params].copy())))
    if extend is not None:
        lattices = [grid] + [g for g, _ in coarse]
        extend = (
            *extend[:2],
            lambda x, fn=extend[2]: fn([(g, c.copy()) for g, c in zip(lattices, _split(x, lattices)[0])]),
        )
    res, move = _fit_level(fun, grid, n_it, coarsest, x0, [g for g, _ in coarse], check, extend)
    xs, rest = _split(res.x, [grid] + [g for g, _ in coarse])
    coarse[:] = [(g, c) for (g, _), c in zip(coarse, xs[1:])]
    if gain is not None:
        gain[1] = rest
    res.x = xs[0]
    return grid, res, move


def _initial(fixed, moving, o):
    """``(affine or None, note)``: the global first guess asked for by ``init``."""
    if o["init"] != "silhouette":
        return None, "none"
    from radiokit.register._global import CUT, frame_cut_affine, silhouette_affine

    affine, why = silhouette_affine(fixed, moving)
    if affine is not None:
        return affine, "silhouette: " + affine.describe()
    if CUT in why:  # only a cut body's moments are refused: the images may still show its motion
        affine, cut_why = frame_cut_affine(fixed, moving)
        if affine is not None:
            return affine, f"from no motion ({why}): {affine.describe()}"
        why = f"{why}; {cut_why}"
    return None, f"none (silhouette not used: {why})"


def _converged(res, move, converge_px):
    """L-BFGS stops on its tolerances (0), at the precision limit of the line search (2), or at
    the iteration budget (1): the last is "not converged" if the last 5 iterations still moved
    the field by more than ``converge_px`` (99th percentile)."""
    if res.status in (0, 2) or move <= converge_px:
        return True, str(res.message)
    return False, (
        f"still moving: {move:.2g} px in the last 5 of {res.nit} iterations at the finest level run "
        f"(more than converge_px={converge_px}; raise iterations)"
    )


@_method("rc")
def _rc(fixed, moving, mask, **options):
    """Residual complexity B-spline (the paper's method). Options: preset ('default', 'fast';
    'weak', 'weak-fast' for texture near the noise level; 'silent', 'silent-fast' for a
    textureless body; through ``register()``, 'auto', 'auto-fast' run 'default' ('fast') and
    retry a flagged result with 'weak' ('weak-fast') on a textured interior or 'silent'
    ('silent-fast') on a silent body, see ``radiokit.register._auto``; the choice is in the
    result's ``options["auto"]``), init ('none', or 'silhouette': start from the silhouettes'
    affine map, module docstring), spacing (px), alpha, regularisation,
    balance ('lattice' or 'frame': see the module docstring), stiffen (balance 'frame': level
    ``k`` halvings finer than the coarsest is 2^(k stiffen) times stiffer), iterations (per
    level, coarse to fine), min_size (px, the coarsest level's smaller side), min_levels (at
    least this many levels while the coarsest keeps 128 px), max_pixels (finer levels are not
    run), coarse_alpha and coarse_regularisation (alpha and the regularisation x these at every
    level but the finest; 1 by default), levels_skip,
    converge_px (the finest level run is converged when its last 5 iterations moved the field
    less than this, in pixels, 99th percentile), highpass (fraction of the smaller side: the
    residual, or with highpass_on='images' both images, minus its Gaussian blur of that width;
    0 or None: off), smooth (level pixels: each level's images blurred by a Gaussian that wide),
    gain (the thinning field's lattice spacing, fraction of the smaller side; 0: no thinning
    term), gain_regularisation, gain_fine (refit the thinning field at the finest level), joint (the finest level refits
    the coarser lattices with its own), noise_alpha (> 0: alpha = noise_alpha x the pair's
    measured noise variance in the normalised units, presets 'weak', 'weak-fast'; an explicit
    alpha turns it off; the alpha used and the noise are in the result's ``options``), bin_pixels
    (a pair of more pixels is registered area-averaged by the least integer factor that brings it
    under this many and the field upsampled; 0, every preset's: off), refit_thinning (a second
    pass with the thinning measured in the body's interior divided out; see REFIT_INTERIOR),
    refit_again (that many more passes, the thinning measured again from the last pass's field
    nearer the edge; see REFIT_AGAIN_INTERIOR; 1 in ``weak``), rim (fraction of the smaller side:
    the refit's passes leave the body's outermost rim that wide out of the data term; needs
    refit_thinning; 0.004 in ``weak``, 0 elsewhere; benchmarks/README.md, session 24),
    grid_jitter (both images sampled off the pixel grid at fixed random offsets, so that the
    interpolation's smoothing of the noise does not depend on the field; on in ``weak`` only,
    see :meth:`_Level._jitter`), abandon_px (> 0: stop before the finest level, not converged, when after the level before it
    the residual still moves by more than this, measured as the quality checks do, or at the
    finest level when ABANDON_FINEST iterations in it still moves by more than their own line;
    only when the finest level is finer than their binning; ``auto`` sets it on its plain run, see
    ``radiokit.register._auto.ABANDON``), extend (iterations the finest level may add when its
    budget ends with the field still moving more than converge_px while the residual, measured as
    the quality checks do, is within their line; 0, every preset's: off; ``auto`` sets it on its
    plain run, see ``radiokit.register._auto.EXTEND``), start_lattices (another rc
    ``Registration.lattices`` on a pair of this shape and binning: their field is kept as it is and
    only this preset's finest level, from zero, and its polish run on top of it; with abandon_px,
    that level is stopped halfway or at its end, not converged, while its residual moves by more
    than that; ``auto`` runs its plain preset's finest level so on the weak field, see
    ``radiokit.register._auto.FINEST_FROM_WEAK``)."""
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
