"""Peer registration methods under radiokit's API, for comparison (and for users who prefer them).

Every peer returns a pull field in (row, col) order, ``moving(x + d(x)) ~ fixed(x)``:

- ``tvl1``, ``ilk``: ``skimage.registration.optical_flow_*(reference_image=fixed,
  moving_image=moving)`` return ``(v, u)`` = (row, col) with ``moving(x + flow) ~ fixed(x)``: as is.
- ``dis``, ``farneback``: OpenCV's ``calc(prev=fixed, next=moving)`` returns per pixel
  ``(dx, dy)`` with ``fixed(y, x) ~ moving(y + dy, x + dx)``: swapped to (row, col).
  Both want 8-bit images: the pair is scaled together by the fixed image's 0.5-99.5 percentiles.
- ``sitk-bspline``, ``sitk-demons`` (SimpleITK) and ``elastix`` (itk-elastix), optional: the
  transform maps fixed-image points to moving-image points, which is a pull field; SimpleITK's
  displacement fields are (x, y) per pixel: swapped.

``prefilter="highpass"`` (every peer) subtracts a wide Gaussian blur (sigma = 1/20 of the image)
from both images first, removing slow intensity change by hand: the tuning that makes these
peers competitive under the intensity changes of compressed phantoms. Default ``"none"``: the
peers as a user would first call them.
"""
from __future__ import annotations

import importlib.util

import numpy as np

from radiokit.errors import RadiokitError
from radiokit.register import _method


class MissingPeer(RadiokitError, ImportError):
    """An optional registration peer is not installed."""


def _require(module, method, package):
    if importlib.util.find_spec(module) is None:
        raise MissingPeer(f"method {method!r} needs {package}: pip install {package} "
                          f"(or pip install 'radiokit[register-peers]')")
    return importlib.import_module(module)


def _prefilter(fixed, moving, prefilter):
    if prefilter in (None, "none"):
        return fixed, moving
    if prefilter != "highpass":
        raise ValueError(f"prefilter={prefilter!r}: expected 'none' or 'highpass'")
    import cv2

    sigma = max(fixed.shape) / 20
    return (fixed - cv2.GaussianBlur(fixed, (0, 0), sigma), moving - cv2.GaussianBlur(moving, (0, 0), sigma))


def _to_u8(fixed, moving):
    lo, hi = np.percentile(fixed, [0.5, 99.5])
    scale = 255.0 / max(float(hi - lo), 1e-12)
    return tuple(np.clip((a - lo) * scale, 0, 255).astype(np.uint8) for a in (fixed, moving))


@_method("tvl1")
def _tvl1(fixed, moving, mask, *, prefilter="none", attachment=15, tightness=0.3, num_warp=5, num_iter=10, tol=1e-4):
    """scikit-image TV-L1 optical flow (its defaults)."""
    from skimage.registration import optical_flow_tvl1

    f, m = _prefilter(fixed, moving, prefilter)
    flow = optical_flow_tvl1(f, m, attachment=attachment, tightness=tightness, num_warp=num_warp,
                             num_iter=num_iter, tol=tol)
    return flow.astype(np.float32), {}


@_method("ilk")
def _ilk(fixed, moving, mask, *, prefilter="none", radius=7, num_warp=10, gaussian=False):
    """scikit-image iterative Lucas-Kanade (its defaults)."""
    from skimage.registration import optical_flow_ilk

    f, m = _prefilter(fixed, moving, prefilter)
    flow = optical_flow_ilk(f, m, radius=radius, num_warp=num_warp, gaussian=gaussian)
    return flow.astype(np.float32), {}


@_method("dis")
def _dis(fixed, moving, mask, *, prefilter="none", preset="medium"):
    """OpenCV DIS optical flow (preset 'ultrafast', 'fast' or 'medium')."""
    import cv2

    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    if preset not in presets:
        raise ValueError(f"dis preset {preset!r}: expected one of {', '.join(presets)}")
    f, m = _to_u8(*_prefilter(fixed, moving, prefilter))
    flow = cv2.DISOpticalFlow_create(presets[preset]).calc(f, m, None)
    return np.stack([flow[..., 1], flow[..., 0]]).astype(np.float32), {}


@_method("farneback")
def _farneback(fixed, moving, mask, *, prefilter="none", pyr_scale=0.5, levels=5, winsize=21, iterations=5,
               poly_n=7, poly_sigma=1.5):
    """OpenCV Farneback dense optical flow."""
    import cv2

    f, m = _to_u8(*_prefilter(fixed, moving, prefilter))
    flow = cv2.calcOpticalFlowFarneback(f, m, None, pyr_scale, levels, winsize, iterations, poly_n, poly_sigma, 0)
    return np.stack([flow[..., 1], flow[..., 0]]).astype(np.float32), {}


def _sitk_field(sitk, transform, shape):
    ref = sitk.Image(int(shape[1]), int(shape[0]), sitk.sitkFloat32)
    conv = sitk.TransformToDisplacementFieldFilter()
    conv.SetReferenceImage(ref)
    disp = sitk.GetArrayFromImage(conv.Execute(transform))  # (rows, cols, 2): (x, y)
    return np.stack([disp[..., 1], disp[..., 0]]).astype(np.float32)


@_method("sitk-bspline")
def _sitk_bspline(fixed, moving, mask, *, prefilter="none", mesh_size=16, iterations=100, metric="correlation"):
    """SimpleITK B-spline (LBFGSB, correlation metric by default), optional extra."""
    sitk = _require("SimpleITK", "sitk-bspline", "SimpleITK")
    f, m = _prefilter(fixed, moving, prefilter)
    F, M = sitk.GetImageFromArray(f.astype(np.float32)), sitk.GetImageFromArray(m.astype(np.float32))
    tx = sitk.BSplineTransformInitializer(F, [int(mesh_size)] * 2)
    reg = sitk.ImageRegistrationMethod()
    {"correlation": reg.SetMetricAsCorrelation, "meansquares": reg.SetMetricAsMeanSquares}[metric]()
    reg.SetOptimizerAsLBFGSB(numberOfIterations=int(iterations))
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetInitialTransform(tx, inPlace=True)
    reg.SetShrinkFactorsPerLevel([4, 2, 1])
    reg.SetSmoothingSigmasPerLevel([2, 1, 0])
    out = reg.Execute(F, M)
    return _sitk_field(sitk, out, f.shape), {"iterations": reg.GetOptimizerIteration()}


@_method("sitk-demons")
def _sitk_demons(fixed, moving, mask, *, prefilter="none", iterations=50, smoothing=1.5):
    """SimpleITK fast-symmetric-forces demons, optional extra."""
    sitk = _require("SimpleITK", "sitk-demons", "SimpleITK")
    f, m = _prefilter(fixed, moving, prefilter)
    F, M = sitk.GetImageFromArray(f.astype(np.float32)), sitk.GetImageFromArray(m.astype(np.float32))
    demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
    demons.SetNumberOfIterations(int(iterations))
    demons.SetStandardDeviations(float(smoothing))
    field = demons.Execute(F, M)
    disp = sitk.GetArrayFromImage(field)
    return np.stack([disp[..., 1], disp[..., 0]]).astype(np.float32), {"iterations": int(iterations)}


@_method("elastix")
def _elastix(fixed, moving, mask, *, prefilter="none", grid_spacing=32, iterations=256,
             metric="AdvancedNormalizedCorrelation"):
    """itk-elastix B-spline (normalised correlation), optional extra."""
    itk = _require("itk", "elastix", "itk-elastix")
    f, m = _prefilter(fixed, moving, prefilter)
    F = itk.GetImageFromArray(np.ascontiguousarray(f, np.float32))
    M = itk.GetImageFromArray(np.ascontiguousarray(m, np.float32))
    params = itk.ParameterObject.New()
    p = params.GetDefaultParameterMap("bspline")
    p["FinalGridSpacingInPhysicalUnits"] = [str(grid_spacing)]
    p["MaximumNumberOfIterations"] = [str(iterations)]
    p["Metric"] = [metric]
    params.AddParameterMap(p)
    _, tp = itk.elastix_registration_method(F, M, parameter_object=params, log_to_console=False)
    field = itk.transformix_deformation_field(M, tp)
    disp = np.asarray(field)  # (rows, cols, 2): (x, y)
    return np.stack([disp[..., 1], disp[..., 0]]).astype(np.float32), {}
