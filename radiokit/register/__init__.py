"""Non-rigid registration of radiographs: residual complexity B-spline (the paper's) and peers.

``register(fixed, moving, method="rc")`` returns a :class:`Registration` whose ``displacement``
is a ``(2, rows, cols)`` float32 field in pixels, (row, col) order, that *pulls*:
``moving(x + d(x))`` matches ``fixed(x)`` (DESIGN.md). ``Registration.confidence`` maps where
the images observe the motion (a homogeneous phantom's smooth interior does not: there the field
is the regulariser's guess). ``Registration.quality`` says whether to trust it: similarity
before and after (residual complexity, the same yardstick for every method, and normalised
cross-correlation), folding (det J <= 0) and the smallest det J, iterations, time, the share of
the object observed and of its observed part left misaligned, and ``ok`` with a ``reason`` when
not.

Methods: ``rc`` (cubic B-spline free-form deformation, residual complexity, Myronenko & Song
2010), the same transform with ``ssd``, ``ncc`` and ``mi``; peers under the same API: ``tvl1``,
``ilk`` (scikit-image), ``dis``, ``farneback`` (OpenCV), and, when installed, ``sitk-bspline``,
``sitk-demons`` (SimpleITK) and ``elastix`` (itk-elastix).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from radiokit.register._auto import AUTO_PRESETS
from radiokit.register._common import jacobian_determinant, ncc, residual_complexity, warp
from radiokit.register._confidence import roi_observed

__all__ = [
    "register",
    "Registration",
    "Quality",
    "METHODS",
    "BSPLINE_METHODS",
    "with_default_preset",
    "warp",
    "jacobian_determinant",
    "roi_observed",
]

#: the methods on the B-spline transform, which take rc's presets (``preset=``)
BSPLINE_METHODS = ("rc", "ssd", "ncc", "mi")


def with_default_preset(method, options) -> dict:
    """``options`` with ``preset="auto"`` added for a B-spline method that names none: what the
    command line and ``radiokit.pipeline`` run (``default``, and on a flagged result ``weak``
    for a textured interior or ``silent`` for a silent body: ``radiokit.register._auto``); the
    paper's phantoms are the silent bodies ``default`` alone cannot register (benchmarks/README.md,
    issue 11). ``register()`` itself runs what it is given."""
    if method in BSPLINE_METHODS and "preset" not in options:
        return {**options, "preset": "auto"}
    return dict(options)


@dataclass
class Quality:
    """How far to trust a registration.

    ``rc_before``/``rc_after``: residual complexity of ``moving - fixed`` and ``warped - fixed``
    (lower is better; insensitive to slow intensity change). ``ncc_before``/``ncc_after``:
    normalised cross-correlation (higher is better); all four measured on the pair area-averaged
    to at most ~0.4 Mpx (by 4 at 2240 x 2240). ``folds``: pixels with det J <= 0 (full
    resolution, inside the mask); ``min_det_j``. ``iterations``; ``seconds``: the method's own
    time (without this assessment). ``observed_fraction``: the share of the object (the mask, or
    the pixels that differ from the frame's border level) where the motion is observable
    (``Registration.confidence`` >= 0.5, see ``radiokit.register._confidence``);
    ``misaligned_fraction``: the share of its observed part where the high-passed residual
    exceeds the noise's expected share by more than a tenth (structure left misaligned, see
    ``radiokit.register._confidence``); ``noise``: the noise level
    estimated from the fixed image (its units). ``ok`` is False, with a ``reason``, on folding (over 0.1 % of the object),
    divergence (similarity worse than not registering), non-convergence, too little of the
    object observed (under half: the field there is the regulariser's guess, whatever the
    similarity says), or too much of the observed part misaligned (over a fifth).
    """

    rc_before: float = float("nan")
    rc_after: float = float("nan")
    ncc_before: float = float("nan")
    ncc_after: float = float("nan")
    folds: int = 0
    min_det_j: float = float("nan")
    iterations: int = 0
    seconds: float = 0.0
    converged: bool = True
    observed_fraction: float = float("nan")
    misaligned_fraction: float = float("nan")
    noise: float = float("nan")
    ok: bool = True
    reason: str = ""


@dataclass
class Registration:
    displacement: np.ndarray
    method: str
    quality: Quality
    options: dict = field(default_factory=dict)
    confidence: np.ndarray | None = None  # (rows, cols) float32 in [0, 1]; >= 0.5: motion observed

    def warp(self, image, order=1) -> np.ndarray:
        """``image(x + d(x))``: an image on the moving grid brought onto the fixed grid."""
        return warp(image, self.displacement, order=order)


METHODS: dict = {}  # name -> function(fixed, moving, mask, **options) -> (displacement, info dict)


def _method(name):
    def deco(fn):
        METHODS[name] = fn
        return fn

    return deco


_LOADED = []  # the method modules imported so far (each once)


def _load_methods():
    """Import the method modules (they fill METHODS), once."""
    import importlib

    for name in ("_bspline", "_peers"):
        if name in _LOADED:
            continue
        try:
            importlib.import_module(f"radiokit.register.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"radiokit.register.{name}":
                raise
        else:
            _LOADED.append(name)


def _check(fixed, moving, mask):
    f = np.asarray(fixed)
    m = np.asarray(moving)
    for name, a in (("fixed", f), ("moving", m)):
        if a.ndim != 2:
            raise ValueError(f"{name} image must be 2-D (rows, cols); got shape {a.shape}")
        if a.dtype.kind not in "uif":
            raise ValueError(f"{name} image must be numeric; got dtype {a.dtype}")
        if min(a.shape) < 8:
            raise ValueError(f"{name} image is too small to register: {a.shape}")
    if f.shape != m.shape:
        raise ValueError(f"fixed {f.shape} and moving {m.shape} images differ in shape")
    f = f.astype(np.float32, copy=False)
    m = m.astype(np.float32, copy=False)
    for name, a in (("fixed", f), ("moving", m)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} image contains NaN or inf ({int(np.sum(~np.isfinite(a)))} pixels)")
        if float(a.max()) == float(a.min()):
            raise ValueError(f"{name} image is constant: nothing to register")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != f.shape:
            raise ValueError(f"mask {mask.shape} does not match the images {f.shape}")
        if not mask.any():
            raise ValueError("mask selects no pixel")
    return f, m, mask


def register(fixed, moving, method="rc", mask=None, *, retry=False, **options) -> Registration:
    """Register ``moving`` onto ``fixed`` (2-D arrays of one shape).

    Input domain: line integrals (``-ln(I / I0)``, ``radiokit.calibrate``'s ``domain="log"``),
    which is what ``radiokit.pipeline`` feeds. There a thickness change is a scale of the image
    (residual complexity's smooth residual) and the noise is nearly uniform over the body;
    transmission images (``domain="linear"``) register too, worse on nearly textureless
    phantoms (``benchmarks/README.md``, the family's intensity-domain rows).

    ``mask`` (bool) limits the similarity to the object. ``retry=True`` repeats a failed
    ``rc``/``ssd``/``ncc``/``mi`` registration with 10x stronger regularisation. ``options`` go
    to the method (see ``radiokit.register.METHODS[name].__doc__``).

    The result carries ``confidence`` (where the motion is observable from these images, see
    ``radiokit.register._confidence``) and ``quality`` (``ok`` and a ``reason``, decided without
    the truth); ``roi_observed(reg.confidence, roi)`` says how much of a ROI was observed."""
    _load_methods()
    if method not in METHODS:
        raise ValueError(f"unknown registration method {method!r}; available: {', '.join(sorted(METHODS))}")
    f, m, mask = _check(fixed, moving, mask)
    if options.get("preset") in AUTO_PRESETS:  # the plain preset, then weak or silent if it fails
        from radiokit.register._auto import register_auto

        return register_auto(register, f, m, method, mask, retry, options)
    t0 = time.perf_counter()
    disp, info = METHODS[method](f, m, mask, **options)
    seconds = time.perf_counter() - t0
    reg = Registration(np.ascontiguousarray(disp, dtype=np.float32), method, Quality(), dict(options))
    if "init" in info:  # what the field started from (the silhouette's map, or why not)
        reg.options["initial"] = info["init"]
    _assess(reg, f, m, mask, info, seconds)
    if retry and not reg.quality.ok and "regularisation" in info:
        opts = dict(options, regularisation=10 * info["regularisation"])
        again = register(f, m, method, mask, retry=False, **opts)
        again.quality.seconds += seconds
        return again
    return reg


_ASSESS_PIXELS = 400_000


def _bin(a, k):
    """``a`` area-averaged by ``k`` (cropped to a multiple of k). Equal to
    ``skimage.measure.block_reduce(a, (k, k), np.mean)`` on the crop, but 5x faster at 2240 x 2240
    (benchmarks/README.md), which counts against rc fast's 1 s there."""
    if k == 1:
        return a
    import cv2

    a = np.asarray(a, np.float32)
    if a.ndim == 3:
        return np.stack([_bin(x, k) for x in a])
    r, c = a.shape[0] // k, a.shape[1] // k
    return cv2.resize(a[: r * k, : c * k], (c, r), interpolation=cv2.INTER_AREA)  # exact k x k means


def _assess(reg, f, m, mask, info, seconds):
    """Fill ``reg.quality``. The similarities are measured on the pair (and field) area-averaged
    to at most ~0.4 Mpx (these are diagnostics, and a fraction of the full-resolution cost; the
    field itself is not binned); det J at full resolution."""
    q = reg.quality
    k = max(1, int(np.ceil(np.sqrt(f.size / _ASSESS_PIXELS))))
    if k > 1:
        fb, mb = _bin(f, k), _bin(m, k)
        db = _bin(reg.displacement, k) / np.float32(k)
        w = warp(mb, db)
        maskb = None if mask is None else _bin(mask.astype(np.float32), k) > 0.5
        f, m, mask_s = fb, mb, maskb
    else:
        w = reg.warp(m)
        db = reg.displacement
        mask_s = mask
    q.rc_before = residual_complexity(m - f, mask_s)
    q.rc_after = residual_complexity(w - f, mask_s)
    q.ncc_before = ncc(m, f, mask_s)
    q.ncc_after = ncc(w, f, mask_s)
    det = jacobian_determinant(reg.displacement)
    if mask is not None:
        det = det[mask]
    q.folds = int(np.count_nonzero(det <= 0))
    q.min_det_j = float(det.min())
    q.iterations = int(info.get("iterations", 0))
    q.converged = bool(info.get("converged", True))
    q.seconds = seconds
    reasons, n_object = _observed(reg, f, m, np.nan_to_num(w), np.nan_to_num(db), mask_s)
    n_object = mask.sum() if mask is not None else n_object * k * k  # full-resolution pixels
    if not np.all(np.isfinite(reg.displacement)):
        reasons.append("non-finite displacement")
        reg.displacement = np.nan_to_num(reg.displacement, nan=0.0, posinf=0.0, neginf=0.0)
    if q.folds > _MAX_FOLDS * max(int(n_object), 1):
        reasons.append(f"folding: {q.folds} pixels with det J <= 0 (min {q.min_det_j:.3g})")
    if q.rc_after > q.rc_before:
        reasons.append(f"diverged: residual complexity {q.rc_after:.6g} after > {q.rc_before:.6g} before")
    if not q.converged:
        reasons.append(info.get("message", "did not converge"))
    q.ok = not reasons
    q.reason = "; ".join(reasons)


# The confidence map and the consistency check are computed on the pair binned to ~0.4 Mpx
# with a window of _WINDOW binned pixels (the default lattice spacing at that size, 1/23 of a
# 560 px frame). The Cramer-Rao bound is what an ideal estimator reaches from one window with
# the intensity change known; residual complexity must also explain that change away, and a
# field that varies over a length L is pinned by windows of that size, so the map charges the
# bound x _BOUND_SCALE x _WINDOW / L, L the correlation length of the estimate smoothed over the
# window (clipped to 0.5-4 windows): what varies faster is the method's own estimation noise
# (a flow's patch-scale ripple), not motion the window could observe, and it must not make a
# smooth, right field look unobservable. A method that reaches less than the data allow is
# caught by the consistency check (misaligned structure), not by a map tuned to one method.
# _BOUND_SCALE, _EXCESS and _MAX_MISALIGNED were chosen on the training seeds of
# benchmarks/regdata.family at 560 px, all four methods of bench_register_flag.py, and checked
# against a grid of alternatives (with _MIN_OBSERVED and _MAX_LENGTH) on 4 training seeds and all
# six methods (`bench_register_flag.py --split train --seeds 4 --sweep`: none does better; numbers
# in benchmarks/README.md, "The flag"); _EXCESS is 6 standard deviations of a window's noise mean
# square (see radiokit.register._confidence).
_WINDOW = 24.0
_BOUND_SCALE = 4.0
_MAX_LENGTH = 4.0  # windows: the longest correlation length the map credits
_MIN_OBSERVED = 0.5
_EXCESS = 0.1
_MAX_MISALIGNED = 0.2
# folding flags when it exceeds this share of the object: a compressed body cannot fold, but a
# flow's few folded pixels (patch-scale noise, often in the empty beam or at the body's edge)
# are a local defect, reported in quality.folds, not a failed registration; on the training
# seeds every failed result that folded was flagged for another reason as well
_MAX_FOLDS = 1e-3


def _correlation_length(d, obj):
    """``sqrt(var d / (2 var grad d))`` over ``obj`` (px): the Gaussian width of a smooth random
    field; a uniform field's is infinite."""
    if not obj.any():
        return float("inf")
    v = sum(float(c[obj].var()) for c in d)
    g = sum(float((a * a)[obj].mean()) for c in d for a in np.gradient(c))
    return float(np.sqrt(v / (2 * g))) if g > 0 else float("inf")


def _observed(reg, f, m, w, d, mask):
    """Fill ``reg.confidence`` (full resolution) and the quality's observability fields from
    the binned fixed, moving and warped moving images ``f``, ``m``, ``w``; the reasons for not
    ok, and the object's size (binned pixels)."""
    import cv2

    from radiokit.register import _confidence as C

    q = reg.quality
    ob = C.observability(f, _WINDOW, mask)
    smooth = np.stack([C._gauss(c, _WINDOW) for c in d])
    length = np.clip(_correlation_length(smooth, ob.object), _WINDOW / 2, _MAX_LENGTH * _WINDOW)
    ob.bound_px *= np.float32(_BOUND_SCALE * _WINDOW / length)
    ob.confidence = (1.0 / (1.0 + (ob.bound_px / C.OBSERVED_PX) ** 2)).astype(np.float32)
    rows, cols = reg.displacement.shape[1:]
    conf = ob.confidence
    if conf.shape != (rows, cols):
        conf = cv2.resize(conf, (cols, rows), interpolation=cv2.INTER_LINEAR)
    reg.confidence = np.clip(conf, 0, 1).astype(np.float32)
    obs = (ob.confidence >= 0.5) & ob.object
    n_obj = int(ob.object.sum())
    q.noise = ob.sigma
    q.observed_fraction = float(obs.sum() / n_obj) if n_obj else 0.0
    q.misaligned_fraction = _misaligned(f, m, w, d, obs)
    reasons = []
    if q.observed_fraction < _MIN_OBSERVED:
        reasons.append(
            f"motion observable in only {100 * q.observed_fraction:.0f} % of the object (confidence map; "
            f"noise {q.noise:.3g}): elsewhere the field is the regulariser's guess"
        )
    if obs.any() and q.misaligned_fraction > _MAX_MISALIGNED:
        reasons.append(
            f"structure left misaligned in {100 * q.misaligned_fraction:.0f} % of the observed object "
            f"(residual above the noise's by more than {100 * _EXCESS:.0f} %)"
        )
    return reasons, n_obj


def _misaligned(f, m, w, d, obs):
    """Share of ``obs`` where the residual ``w - f`` exceeds the noise's expected share by more
    than _EXCESS of it, and by more than a quarter of the excess before registering (which keeps
    interpolation error on noise-free data from counting); NaN when nothing is observed."""
    from radiokit.register import _confidence as C

    if not obs.any():
        return float("nan")
    sig = C.noise_map(f, _WINDOW)
    factor = 1.0 + C.interpolation_variance(d, _WINDOW)
    after = C.consistency(f, w, _WINDOW, sig, factor) - 1.0
    before = C.consistency(f, m, _WINDOW, sig) - 1.0
    bad = (after > _EXCESS) & (after * factor > 0.25 * 2.0 * np.maximum(before, 0))
    return float(np.mean(bad[obs]))
