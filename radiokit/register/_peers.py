"""Peer registration methods under radiokit's API, for comparison (and for users who prefer them).

Every peer returns radiokit's field: ``(2, rows, cols)`` in pixels, (row, col) order, pulling,
``moving(x + d(x)) ~ fixed(x)``. How each tool's own convention is converted:

- ``tvl1``, ``ilk``: ``skimage.registration.optical_flow_*(reference_image=fixed,
  moving_image=moving)`` returns ``(v, u)`` = (row, col) such that ``moving`` sampled at
  ``x + (v, u)`` matches ``fixed``: already radiokit's field, taken as is.
- ``dis``, ``farneback``: OpenCV's ``calc(prev=fixed, next=moving)`` returns per pixel
  ``flow[y, x] = (dx, dy)`` with ``prev(y, x) ~ next(y + dy, x + dx)``: a pull field in
  (col, row) order per pixel, so the two channels are swapped and moved first.
- ``sitk-bspline``, ``sitk-demons`` (SimpleITK), ``elastix`` (itk-elastix), the optional extra
  ``radiokit[register-peers]``: images go in with ``GetImageFromArray`` (index (x, y) = (col,
  row), spacing 1, origin 0, so physical units are pixels); the registration transform maps
  points of the fixed image to the moving image, ``T(x) = x + d(x)``, which is a pull field;
  the displacement-field images (``TransformToDisplacementField``, the demons' output field and
  ``transformix_deformation_field``) hold per pixel ``(dx, dy)``: swapped to (row, col).

The tests in ``tests/test_register_peers.py`` pin sign and axis order of each peer on a known
sub-pixel translation and a known smooth warp.

Shared options of every peer:

``prefilter="none" | "highpass"``: ``"highpass"`` subtracts a wide Gaussian blur (sigma
``highpass_sigma`` x the image's larger side, default 1/20) from both images first. On line
integrals (log images) this removes slow intensity change by hand -- a stale flat's gain is
an additive slow term there; a body thinning under compression scales the line integral, whose
slow part goes, leaving a change of a few % in the texture's contrast: the "tuned"
configuration that lets these intensity-blind peers compete on compressed phantoms. The default
is ``"none"``: the peers as a user would first call them, and how they fail under an
intensity change (``benchmarks/README.md``, "The peers' defaults", has the errors with and
without the prefilter).

Intensity scaling: every peer sees the pair scaled together, ``(a - lo) / (hi - lo)`` with
``lo, hi`` the 0.5 and 99.5 percentiles of both images (after the prefilter), so its parameters
(TV-L1's attachment, demons' thresholds) mean the same for counts, transmissions or line
integrals. The 8-bit peer (DIS) gets the same scaling clipped to 0-255 (1/255 of the pair's
range per grey level; the 1 % of pixels outside the percentiles saturate); Farneback takes the
same scaling as float32 (no quantisation).

``working_size`` (the four optical flows): register the pair area-averaged by the integer
``k = round(larger side / working_size)`` and interpolate the field back (times ``k``), or
``None`` for full resolution. These flows were made for video: their windows and polynomial
fits see a few pixels, too few for the smooth texture of a 2240 x 2240 radiograph; averaging
is also faster. Each method's defaults were chosen with ``benchmarks/bench_register.py``
(highpass prefilter, 1 % displacement, 10 % intensity change); the errors that chose them are in
``benchmarks/README.md``, "The peers' defaults".

``mask``: SimpleITK's B-spline and elastix limit their metric to it; the optical flows and
demons (dense, local) ignore it.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import re
import tempfile
import threading
from pathlib import Path

import numpy as np

from radiokit.checks import is_integer, is_number
from radiokit.errors import RadiokitError
from radiokit.register import _method

__all__ = ["MissingPeer", "highpass"]


class MissingPeer(RadiokitError, ImportError):
    """An optional registration peer is not installed (``pip install radiokit[register-peers]``)."""


def _require(module, method, package, attr=None):
    """Import ``module`` or raise :class:`MissingPeer` naming ``package`` and the extra."""
    msg = f"method {method!r} needs {package}: pip install radiokit[register-peers] (or pip install {package})"
    if importlib.util.find_spec(module) is None:
        raise MissingPeer(msg)
    mod = importlib.import_module(module)
    if attr is not None and not hasattr(mod, attr):  # e.g. plain itk without itk-elastix
        raise MissingPeer(msg)
    return mod


# -- shared preprocessing ---------------------------------------------------------------------


def highpass(image, sigma):
    """``image - G_sigma * image`` (float32; borders reflected). A wide blur is computed on the
    image area-averaged by ``k ~ sigma / 8`` and interpolated back (the blur is smooth at that
    scale; the box adds ``k^2 / 12`` to its variance, under 0.2 %), a small fraction of the cost
    of blurring at full resolution."""
    import cv2

    image = np.asarray(image, np.float32)
    k = int(sigma // 8)
    if k < 2:
        return image - cv2.GaussianBlur(image, (0, 0), float(sigma), borderType=cv2.BORDER_REFLECT)
    rows, cols = image.shape
    small = cv2.resize(image, (max(1, round(cols / k)), max(1, round(rows / k))), interpolation=cv2.INTER_AREA)
    blur = cv2.GaussianBlur(small, (0, 0), float(sigma) * small.shape[1] / cols, borderType=cv2.BORDER_REFLECT)
    return image - cv2.resize(blur, (cols, rows), interpolation=cv2.INTER_LINEAR)


def _shrink(f, m, working_size):
    """The pair area-averaged by ``k = round(larger side / working_size)`` (none when ``k <= 1``
    or ``working_size`` is None): ``(f, m, k)``."""
    import cv2

    k = 1 if working_size is None else max(1, int(round(max(f.shape) / float(working_size))))
    if k == 1:
        return f, m, 1
    size = (max(8, round(f.shape[1] / k)), max(8, round(f.shape[0] / k)))
    return cv2.resize(f, size, interpolation=cv2.INTER_AREA), cv2.resize(m, size, interpolation=cv2.INTER_AREA), k


def _expand(d, shape):
    """A field computed on a smaller grid, interpolated to ``shape`` and rescaled to its pixels
    (pixel centres aligned as ``cv2.resize`` aligns them)."""
    import cv2

    if d.shape[1:] == tuple(shape):
        return d
    scale = (shape[0] / d.shape[1], shape[1] / d.shape[2])
    return np.stack(
        [
            cv2.resize(d[i], (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR) * np.float32(scale[i])
            for i in range(2)
        ]
    )


def _prepare(fixed, moving, prefilter, highpass_sigma):
    """The prefilter, then the pair scaled together to about [0, 1] (see the module docstring)."""
    if prefilter in (None, "none"):
        f, m = fixed, moving
    elif prefilter == "highpass":
        if not 0 < highpass_sigma:
            raise ValueError(f"highpass_sigma={highpass_sigma}: expected > 0 (a fraction of the image's size)")
        sigma = highpass_sigma * max(fixed.shape)
        f, m = highpass(fixed, sigma), highpass(moving, sigma)
    else:
        raise ValueError(f"prefilter={prefilter!r}: expected 'none' or 'highpass'")
    from radiokit.register._confidence import sample_step

    step = sample_step(f.size)  # percentiles from ~2 x 250k samples
    lo, hi = np.percentile(np.concatenate([f[::step, ::step].ravel(), m[::step, ::step].ravel()]), [0.5, 99.5])
    scale = 1.0 / max(float(hi - lo), 1e-12)
    return ((f - np.float32(lo)) * np.float32(scale)).astype(np.float32), (
        (m - np.float32(lo)) * np.float32(scale)
    ).astype(np.float32)


_POSITIVE = float(np.finfo(float).tiny)  # a lower bound that means "> 0"
_BELOW_ONE = float(np.nextafter(1.0, 0.0))  # an upper bound that means "< 1"


def _check_ranges(method, **ranges):
    """ValueError naming the first of ``method``'s options outside its range, before its library
    runs: ``name=(value, low, high)``, both ends included, an int ``low`` asking for an integer;
    None (an automatic choice) passes. Out of range, OpenCV's DIS killed the interpreter (a zero
    patch size or stride), other values were OpenCV, SimpleITK or elastix errors, a division by
    zero, or a silent garbage field."""
    for name, (value, low, high) in ranges.items():
        integer = isinstance(low, int)
        if value is None or ((is_integer if integer else is_number)(value) and low <= value <= high):
            continue
        lo = "> 0" if low == _POSITIVE else f">= {low}"
        hi = "" if high == np.inf else (" and < 1" if high == _BELOW_ONE else f" and <= {high}")
        raise ValueError(f"{method} {name}={value!r}: expected {'an integer' if integer else 'a number'} {lo}{hi}")


def _to_u8(a):
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def _levels(shape, coarsest=32):
    """Pyramid levels (factor 2) until the smaller side would drop below ``coarsest`` pixels."""
    return max(1, int(np.floor(np.log2(min(shape) / coarsest))) + 1)


def _from_xy(a):
    """``(rows, cols, 2)`` per-pixel ``(dx, dy)`` -> ``(2, rows, cols)`` (row, col)."""
    a = np.asarray(a)
    return np.stack([a[..., 1], a[..., 0]]).astype(np.float32)


def _size_relative(value, fraction, shape, minimum):
    """``value``, or when ``None`` ``fraction`` of the image's larger side (at least ``minimum``)."""
    return max(minimum, fraction * max(shape)) if value is None else value


# -- scikit-image -----------------------------------------------------------------------------


@_method("tvl1")
def _tvl1(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    working_size=512,
    attachment=5.0,
    tightness=0.3,
    num_warp=5,
    num_iter=10,
    tol=1e-4,
):
    """scikit-image TV-L1 optical flow (``optical_flow_tvl1``) on the pair scaled to [0, 1].

    ``attachment`` 5 (scikit-image's default is 15): a smoother field, more accurate on
    radiographs' smooth texture. ``tightness``, ``num_warp``, ``num_iter``, ``tol``:
    scikit-image's. ``working_size`` 512 (see the module docstring): as accurate as full
    resolution at a fraction of the time. ``mask`` is ignored."""
    from skimage.registration import optical_flow_tvl1

    _check_ranges(
        "tvl1",
        working_size=(working_size, _POSITIVE, np.inf),
        attachment=(attachment, _POSITIVE, np.inf),
        tightness=(tightness, _POSITIVE, np.inf),
        num_warp=(num_warp, 1, np.inf),
        num_iter=(num_iter, 1, np.inf),
        tol=(tol, _POSITIVE, np.inf),
    )
    f, m, _ = _shrink(*_prepare(fixed, moving, prefilter, highpass_sigma), working_size)
    flow = optical_flow_tvl1(
        f,
        m,
        attachment=float(attachment),
        tightness=float(tightness),
        num_warp=int(num_warp),
        num_iter=int(num_iter),
        tol=float(tol),
    )
    return _expand(np.asarray(flow, np.float32), fixed.shape), {"iterations": int(num_warp) * int(num_iter)}


@_method("ilk")
def _ilk(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    working_size=None,
    radius=None,
    num_warp=10,
    gaussian=False,
):
    """scikit-image iterative Lucas-Kanade (``optical_flow_ilk``): a uniform (or with
    ``gaussian=True`` Gaussian) window of ``radius`` pixels, ``num_warp`` warps per pyramid level.

    ``radius=None``: 1/40 of the image's larger side, at least 7 (scikit-image's fixed 7): the
    window must span the texture and stay below the warp's scale at every binning.
    ``working_size`` ``None`` (full resolution): averaging is much faster but less accurate for
    this method. ``mask`` is ignored."""
    from skimage.registration import optical_flow_ilk

    _check_ranges(
        "ilk",
        working_size=(working_size, _POSITIVE, np.inf),
        radius=(radius, 1.0, np.inf),
        num_warp=(num_warp, 1, np.inf),
    )
    f, m, _ = _shrink(*_prepare(fixed, moving, prefilter, highpass_sigma), working_size)
    r = int(round(_size_relative(radius, 1 / 40, f.shape, 7)))
    flow = optical_flow_ilk(f, m, radius=r, num_warp=int(num_warp), gaussian=bool(gaussian))
    return _expand(np.asarray(flow, np.float32), fixed.shape), {"iterations": int(num_warp)}


# -- OpenCV ----------------------------------------------------------------------------------

_DIS_PRESETS = ("ultrafast", "fast", "medium")


@_method("dis")
def _dis(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    working_size=768,
    preset="medium",
    finest_scale=None,
    patch_size=None,
    patch_stride=None,
    refinement_iterations=None,
    refinement_alpha=80.0,
    mean_normalization=True,
):
    """OpenCV Dense Inverse Search optical flow on the pair scaled to 8 bits (see the module
    docstring).

    ``preset`` 'medium' (of 'ultrafast', 'fast', 'medium'); ``None`` options keep the preset's
    value (medium: finest_scale 1, patch_size 8, patch_stride 3, 5 variational refinement
    iterations). ``refinement_alpha`` (smoothness of the variational refinement) 80, not
    OpenCV's 20: radiographs' texture is smooth, and a smoother field is more accurate on it.
    ``mean_normalization``: OpenCV's patch-mean normalisation (on), which already absorbs part
    of a slow intensity change. ``working_size`` 768: full resolution up to 1152 px; a 2240 image
    averaged by 3, more accurate than at full resolution or at 512. ``mask`` is ignored."""
    import cv2

    if preset not in _DIS_PRESETS:
        raise ValueError(f"dis preset {preset!r}: expected one of {', '.join(_DIS_PRESETS)}")
    _check_ranges(
        "dis",
        working_size=(working_size, _POSITIVE, np.inf),
        finest_scale=(finest_scale, 0, np.inf),
        patch_size=(patch_size, 1, np.inf),
        patch_stride=(patch_stride, 1, np.inf),
        refinement_iterations=(refinement_iterations, 0, np.inf),
        refinement_alpha=(refinement_alpha, 0.0, np.inf),
    )
    f, m, _ = _shrink(*_prepare(fixed, moving, prefilter, highpass_sigma), working_size)
    dis = cv2.DISOpticalFlow_create(getattr(cv2, f"DISOPTICAL_FLOW_PRESET_{preset.upper()}"))
    for setter, value in (
        (dis.setFinestScale, finest_scale),
        (dis.setPatchSize, patch_size),
        (dis.setPatchStride, patch_stride),
        (dis.setVariationalRefinementIterations, refinement_iterations),
    ):
        if value is not None:
            setter(int(value))
    if refinement_alpha is not None:
        dis.setVariationalRefinementAlpha(float(refinement_alpha))
    dis.setUseMeanNormalization(bool(mean_normalization))
    _dis_fits(dis, f.shape)
    flow = dis.calc(_to_u8(f), _to_u8(m), None)
    return _expand(_from_xy(flow), fixed.shape), {}


def _dis_fits(dis, shape):
    """ValueError unless DIS's pyramid fits a working image of ``shape``: its finest level's smaller
    side must hold a patch, and its coarsest level index (OpenCV's ``log2(larger side / (4 patch))
    + 1/2``, truncated) must not be negative. Below that OpenCV crashed the interpreter (10 x 40:
    a segmentation fault), returned NaN or raised; found on a grid of sizes, presets and patches."""
    ps, fs = dis.getPatchSize(), dis.getFinestScale()
    if min(shape) < ps * 2**fs or max(shape) <= ps * np.sqrt(2):
        raise ValueError(
            f"dis: the working image {shape} is too small for patch_size {ps} at finest_scale {fs}: "
            f"its smaller side must be at least {ps * 2**fs} px and its larger over {ps * np.sqrt(2):.1f} "
            "(a smaller patch_size or finest_scale, a larger working_size, or another method)"
        )


@_method("farneback")
def _farneback(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    working_size=512,
    pyr_scale=0.5,
    levels=None,
    winsize=None,
    iterations=5,
    poly_n=5,
    poly_sigma=1.1,
    gaussian=True,
):
    """OpenCV Farneback dense optical flow on the float32 pair scaled to 0-255 (its polynomial
    fit's regularisation assumes 8-bit grey levels: on [0, 1] it returns zero flow).

    ``working_size`` 512 (see the module docstring): the polynomial expansion sees a few pixels
    only, and at full resolution the texture of a 1120 or 2240 image is too smooth for it (at
    2240 it fails). ``levels=None``: halve the working image until its smaller side is about 32
    pixels. ``winsize=None``: 1/12 of the working image's larger side (odd, at least 15), a
    Gaussian window (``gaussian``), wider than OpenCV's usual 15 for the same reason.
    ``iterations``, ``poly_n``, ``poly_sigma``: OpenCV's documented choice (5, 5, 1.1).
    ``mask`` is ignored."""
    import cv2

    _check_ranges(
        "farneback",
        working_size=(working_size, _POSITIVE, np.inf),
        pyr_scale=(pyr_scale, _POSITIVE, _BELOW_ONE),
        levels=(levels, 0, np.inf),
        winsize=(winsize, 1, np.inf),
        iterations=(iterations, 1, np.inf),
        poly_n=(poly_n, 1, np.inf),
        poly_sigma=(poly_sigma, _POSITIVE, np.inf),
    )
    f, m, _ = _shrink(*_prepare(fixed, moving, prefilter, highpass_sigma), working_size)
    n_levels = _levels(f.shape) if levels is None else int(levels)
    win = int(_size_relative(winsize, 1 / 12, f.shape, 15)) // 2 * 2 + 1 if winsize is None else int(winsize)
    flags = cv2.OPTFLOW_FARNEBACK_GAUSSIAN if gaussian else 0
    flow = cv2.calcOpticalFlowFarneback(
        f * np.float32(255),
        m * np.float32(255),
        None,
        float(pyr_scale),
        n_levels,
        win,
        int(iterations),
        int(poly_n),
        float(poly_sigma),
        flags,
    )
    return _expand(_from_xy(flow), fixed.shape), {"iterations": int(iterations) * n_levels}


# -- SimpleITK (optional) -------------------------------------------------------------------------


def _sitk_image(sitk, a):
    return sitk.GetImageFromArray(np.ascontiguousarray(a, np.float32))  # spacing 1, origin 0


#: the blocks inside :func:`_itk_warnings_off` now, and the display as the first found it. The
#: display is one switch for the process: two registrations on two threads (SimpleITK releases the
#: GIL) each saving and restoring it left it off for good when the second outlived the first
#: (it found it off), and turned it back on under the second
_ITK_QUIET = {"depth": 0, "was": True}
_ITK_QUIET_LOCK = threading.Lock()


@contextlib.contextmanager
def _itk_warnings_off(sitk):
    """SimpleITK's global warning display off for the block, restored after. Its warnings are C++
    writes to the process's stderr: a field the optimiser carried out of an 8 x 8 frame wrote "No
    valid points were found" six lines at a time, 234 lines under the command line's one; the
    result is judged by radiokit's checks instead (which flag that field). Blocks overlapping on
    threads share it: off from the first's start to the last's end, then as the first found it."""
    with _ITK_QUIET_LOCK:
        if not _ITK_QUIET["depth"]:
            _ITK_QUIET["was"] = sitk.ProcessObject.GetGlobalWarningDisplay()
            sitk.ProcessObject.SetGlobalWarningDisplay(False)
        _ITK_QUIET["depth"] += 1
    try:
        yield
    finally:
        with _ITK_QUIET_LOCK:
            _ITK_QUIET["depth"] -= 1
            if not _ITK_QUIET["depth"]:
                sitk.ProcessObject.SetGlobalWarningDisplay(_ITK_QUIET["was"])


@_method("sitk-bspline")
def _sitk_bspline(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    spacing=None,
    metric="correlation",
    iterations=100,
    shrink=None,
    sampling=None,
    seed=0,
):
    """SimpleITK free-form B-spline (``ImageRegistrationMethod``, L-BFGS), optional extra.

    Control points ``spacing`` pixels apart at the finest level (``None``: 1/24 of the image's
    larger side, at least 16), the mesh halved at each coarser level of ``shrink`` (``None``:
    factors 2^k down to about 128 px; images shrunk and smoothed with sigma = factor / 2);
    ``metric`` 'correlation' (normalised correlation: 'meansquares' is not invariant to an
    intensity change), 'meansquares', or 'mattes' (mutual information); ``iterations`` per
    level; ``sampling`` a fraction of the pixels for the metric (random, ``seed``) or ``None``
    for all. ``mask`` limits the metric."""
    sitk = _require("SimpleITK", "sitk-bspline", "SimpleITK")
    _check_ranges(
        "sitk-bspline",
        spacing=(spacing, _POSITIVE, np.inf),
        iterations=(iterations, 1, np.inf),
        sampling=(sampling, _POSITIVE, 1.0),
    )
    f, m = _prepare(fixed, moving, prefilter, highpass_sigma)
    F, M = _sitk_image(sitk, f), _sitk_image(sitk, m)
    spacing = float(_size_relative(spacing, 1 / 24, f.shape, 16))
    if shrink is None:
        shrink = [2**k for k in reversed(range(_levels(f.shape, 128)))]
    shrink = [int(s) for s in shrink]
    coarse = max(shrink)
    mesh = [max(1, int(round((n - 1) / (spacing * coarse)))) for n in F.GetSize()]
    tx = sitk.BSplineTransformInitializer(F, mesh, 3)
    reg = sitk.ImageRegistrationMethod()
    metrics = {
        "correlation": reg.SetMetricAsCorrelation,
        "meansquares": reg.SetMetricAsMeanSquares,
        "mattes": lambda: reg.SetMetricAsMattesMutualInformation(32),
    }
    if metric not in metrics:
        raise ValueError(f"sitk-bspline metric {metric!r}: expected one of {', '.join(metrics)}")
    metrics[metric]()
    if sampling is not None:
        reg.SetMetricSamplingStrategy(reg.RANDOM)
        reg.SetMetricSamplingPercentage(float(sampling), int(seed))
    if mask is not None:
        reg.SetMetricFixedMask(sitk.GetImageFromArray(mask.astype(np.uint8)))
    # L-BFGS-B cannot follow the mesh refinement between levels (its scales keep the coarse
    # mesh's size); L-BFGS (libLBFGS, "LBFGS2") can
    reg.SetOptimizerAsLBFGS2(solutionAccuracy=1e-5, numberOfIterations=int(iterations))
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetInitialTransformAsBSpline(tx, inPlace=True, scaleFactors=[coarse // s for s in shrink])
    reg.SetShrinkFactorsPerLevel(shrink)
    reg.SetSmoothingSigmasPerLevel([s / 2 for s in shrink])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    its = []
    reg.AddCommand(sitk.sitkIterationEvent, lambda: its.append(reg.GetOptimizerIteration()))
    with _itk_warnings_off(sitk):
        out = reg.Execute(F, M)
    conv = sitk.TransformToDisplacementFieldFilter()
    conv.SetReferenceImage(F)
    conv.SetOutputPixelType(sitk.sitkVectorFloat64)
    field = sitk.GetArrayFromImage(conv.Execute(out))  # (rows, cols, 2): (dx, dy)
    return _from_xy(field), {"iterations": len(its), "message": reg.GetOptimizerStopConditionDescription()}


_DEMONS = {
    "fast-symmetric": "FastSymmetricForcesDemonsRegistrationFilter",
    "symmetric": "SymmetricForcesDemonsRegistrationFilter",
    "diffeomorphic": "DiffeomorphicDemonsRegistrationFilter",
    "classic": "DemonsRegistrationFilter",
}


@_method("sitk-demons")
def _sitk_demons(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    variant="fast-symmetric",
    iterations=50,
    smoothing=None,
    levels=None,
    max_step=2.0,
):
    """SimpleITK demons, optional extra, coarse to fine: the pair area-averaged by 2^k
    (``levels=None``: down to about 64 pixels), each level's field upsampled to start the next.

    ``variant`` 'fast-symmetric' (default), 'symmetric', 'diffeomorphic' (slower, no more
    accurate) or 'classic'; ``iterations`` per level; ``smoothing``: Gaussian sigma (pixels of
    each level) of the field after each update, ``None``: 1/85 of the image's larger side (it
    scales with the binning, unlike a fixed few pixels), at most 1/16 of the level's smaller side
    (a wider kernel erases a coarse level's field); ``max_step``: largest update per iteration,
    pixels. ``mask`` is ignored."""
    import cv2

    sitk = _require("SimpleITK", "sitk-demons", "SimpleITK")
    if variant not in _DEMONS:
        raise ValueError(f"sitk-demons variant {variant!r}: expected one of {', '.join(_DEMONS)}")
    _check_ranges(
        "sitk-demons",
        iterations=(iterations, 1, np.inf),
        levels=(levels, 1, np.inf),
        max_step=(max_step, _POSITIVE, np.inf),
        smoothing=(smoothing, _POSITIVE, np.inf),
    )
    f, m = _prepare(fixed, moving, prefilter, highpass_sigma)
    sigma = float(_size_relative(smoothing, 1 / 85, f.shape, 1.0))
    n_levels = _levels(f.shape, 64) if levels is None else int(levels)
    d = None
    for level in reversed(range(n_levels)):
        k = 2**level
        size = (max(1, round(f.shape[1] / k)), max(1, round(f.shape[0] / k)))
        fl = cv2.resize(f, size, interpolation=cv2.INTER_AREA) if k > 1 else f
        ml = cv2.resize(m, size, interpolation=cv2.INTER_AREA) if k > 1 else m
        if d is None:
            d = np.zeros((2,) + fl.shape, np.float32)
        else:
            scale = np.array(fl.shape, np.float32) / np.array(d.shape[1:], np.float32)
            d = np.stack([cv2.resize(d[i], size, interpolation=cv2.INTER_LINEAR) * scale[i] for i in range(2)])
        demons = getattr(sitk, _DEMONS[variant])()
        demons.SetNumberOfIterations(int(iterations))
        demons.SetStandardDeviations(min(sigma, min(fl.shape) / 16) if smoothing is None else sigma)
        if variant != "classic":
            demons.SetMaximumUpdateStepLength(float(max_step))
        init = sitk.GetImageFromArray(np.stack([d[1], d[0]], axis=-1).astype(np.float64), isVector=True)
        with _itk_warnings_off(sitk):
            out = demons.Execute(_sitk_image(sitk, fl), _sitk_image(sitk, ml), init)
        d = _from_xy(sitk.GetArrayFromImage(out))
    return d, {"iterations": int(iterations) * n_levels}


# -- itk-elastix (optional) -------------------------------------------------------------------------


@_method("elastix")
def _elastix(
    fixed,
    moving,
    mask,
    *,
    prefilter="none",
    highpass_sigma=0.05,
    spacing=None,
    metric="AdvancedNormalizedCorrelation",
    iterations=256,
    resolutions=None,
    samples=4096,
    bending_weight=0.0,
    seed=0,
    parameters=None,
):
    """elastix B-spline (itk-elastix), optional extra: elastix's default ``bspline`` map
    (adaptive stochastic gradient descent, random samples, grid halved per resolution) with:

    ``spacing``: final control-point spacing, pixels; ``None``: 1/16 of the image's larger side,
    at least 16 (elastix's default is 10 px; relative, so it scales with the binning).
    ``metric``: ``AdvancedNormalizedCorrelation`` (elastix's default,
    ``AdvancedMattesMutualInformation``, is the "default B-spline" that fails under intensity
    change). ``iterations`` per resolution (elastix's 256), ``samples`` per iteration (4096),
    ``resolutions`` (``None``: halve down to ~64 px, at most
    5), ``bending_weight`` (the bending-energy penalty; 0 = off), ``seed``; ``parameters``: a
    dict of further elastix parameters (values: strings or lists) that override all of these.
    ``mask`` limits the metric (elastix's fixed mask; one its erosion would leave empty, a ROI
    a few pixels across, is used uneroded: ``ErodeMask`` false, unless ``parameters`` set it)."""
    _check_ranges(
        "elastix",
        spacing=(spacing, _POSITIVE, np.inf),
        iterations=(iterations, 1, np.inf),
        resolutions=(resolutions, 1, np.inf),
        samples=(samples, 1, np.inf),
    )
    # a string or a list of pairs was an AttributeError from .items() once itk had loaded
    if parameters is not None and not (isinstance(parameters, dict) and all(isinstance(k, str) for k in parameters)):
        raise ValueError(
            f"elastix: parameters={parameters!r}: expected a dict of elastix parameter names to values "
            "(strings or lists), e.g. {'Optimizer': 'QuasiNewtonLBFGS'}"
        )
    # after the checks: reaching elastix_registration_method loads all of itk (12 s here)
    itk = _require("itk", "elastix", "itk-elastix", attr="elastix_registration_method")
    f, m = _prepare(fixed, moving, prefilter, highpass_sigma)
    F = itk.GetImageFromArray(np.ascontiguousarray(f, np.float32))
    M = itk.GetImageFromArray(np.ascontiguousarray(m, np.float32))
    spacing = float(_size_relative(spacing, 1 / 16, f.shape, 16))
    n_res = min(5, _levels(f.shape, 64)) if resolutions is None else int(resolutions)
    po = itk.ParameterObject.New()
    p = po.GetDefaultParameterMap("bspline", n_res, spacing)
    p["Metric"] = [metric, "TransformBendingEnergyPenalty"] if bending_weight else [metric]
    p["Metric0Weight"], p["Metric1Weight"] = ["1.0"], [str(float(bending_weight))]
    p["MaximumNumberOfIterations"] = [str(int(iterations))]
    p["NumberOfSpatialSamples"] = [str(int(samples))]
    p["RandomSeed"] = [str(int(seed))]
    p["WriteResultImage"] = ["false"]
    for k, v in (parameters or {}).items():
        p[k] = [str(x) for x in v] if isinstance(v, (list, tuple)) else [str(v)]
    kw = {}
    if mask is not None:
        kw["fixed_mask"] = itk.GetImageFromArray(mask.astype(np.uint8))
    # elastix and transformix write files (transformix its deformationField.nii) into the
    # current directory unless told otherwise: a temporary one
    with tempfile.TemporaryDirectory(prefix="radiokit-elastix-") as tmp:
        tp = _elastix_transform(itk, F, M, p, kw, tmp)
        field = itk.transformix_deformation_field(M, tp, output_directory=tmp)
        d = _from_xy(np.asarray(field))
    return d, {"iterations": int(iterations) * n_res}


#: What elastix's log says when its eroded fixed mask left no pixel to sample: the ASGD
#: optimizer's (the default) and the sampler's under the others (RegularStepGradientDescent,
#: QuasiNewtonLBFGS, ...)
_MASK_EMPTIED = ("No valid voxels", "Could not find enough image samples")


def _elastix_transform(itk, F, M, p, kw, tmp):
    """elastix's transform parameters for the map ``p`` (``kw``: its fixed mask, if any), logging
    into ``tmp``. elastix erodes a fixed mask at each resolution (``ErodeMask``, on by default),
    and a ROI a few pixels across vanished: its sampler found no pixel (:data:`_MASK_EMPTIED`)
    and itk raised "Internal elastix error: See elastix log" (a traceback of `radiokit register
    --roi`). Such a mask is used once more uneroded; a map that sets ``ErodeMask`` itself keeps
    it. A failure is a ValueError with the log's description (the log goes with ``tmp``)."""
    try:
        return _elastix_run(itk, F, M, p, kw, tmp)
    except RuntimeError as exc:
        why = _elastix_description(tmp)
        if "fixed_mask" not in kw or "ErodeMask" in p or not any(s in why for s in _MASK_EMPTIED):
            raise ValueError(f"elastix failed: {why}") from exc
    p["ErodeMask"] = ["false"]
    try:
        return _elastix_run(itk, F, M, p, kw, tmp)
    except RuntimeError as exc:
        raise ValueError(f"elastix failed with its mask uneroded: {_elastix_description(tmp)}") from exc


def _elastix_run(itk, F, M, p, kw, tmp):
    po = itk.ParameterObject.New()
    po.AddParameterMap(p)
    return itk.elastix_registration_method(
        F, M, parameter_object=po, log_to_console=False, log_to_file=True, output_directory=tmp, **kw
    )[1]


def _elastix_description(tmp) -> str:
    """The last ``Description:`` of elastix's log in ``tmp`` (itk's own error only says "See
    elastix log"), without itk's "ITK ERROR: Class(0x...):" prefix."""
    log = Path(tmp, "elastix.log")
    lines = log.read_text(errors="replace").splitlines() if log.is_file() else []
    found = [x.split("Description:", 1)[1] for x in lines if "Description:" in x]
    return re.sub(r"^\s*ITK ERROR: \w+\(0x[0-9a-f]+\):", "", found[-1]).strip() if found else "see its log"
