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

import contextvars
import functools
import time
from dataclasses import dataclass, field

import numpy as np

from radiokit.checks import image_hint, refuse_masked
from radiokit.register._auto import AUTO_PRESETS
from radiokit.register._common import (
    _field,
    _warp,
    binned_mask,
    jacobian_determinant,
    monomials,
    ncc,
    residual_complexity,
    warp,
)
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
    "load_methods",
    "check_options",
    "MIN_SIDE",
    "MAX_SIDE",
]

#: the least side, in pixels, of an image register() takes (OpenCV asserted on smaller pairs)
MIN_SIDE = 8

#: the largest side register() takes: OpenCV's remap, which rc's sampling and the OpenCV peers
#: use, asserts sides under SHRT_MAX (32767); a line-scan strip 8 x 40000 was a cv2.error from
#: inside rc, a traceback on the command line (``warp`` itself samples such a frame)
MAX_SIDE = 32766

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
    in units of the fixed image's 1-99 % range (lower is better; insensitive to slow intensity
    change; the same for any intensity unit; both leave out the pixels the field carries out of
    the frame, as rc's data term does). ``ncc_before``/``ncc_after``:
    normalised cross-correlation (higher is better); all four measured on the pair area-averaged
    to at most ~0.4 Mpx (by 4 at 2240 x 2240). ``folds``: pixels with det J <= 0 (full
    resolution, inside the mask); ``min_det_j``. ``iterations``; ``seconds``: the method's own
    time (without this assessment). ``observed_fraction``: the share of the object (the mask, or
    the pixels that differ from the frame's border level) where the motion is observable
    (``Registration.confidence`` >= 0.5, see ``radiokit.register._confidence``), less the pixels
    the field carries out of the frame (the checks leave them out, :func:`_judged`);
    ``interior_observed``: the same share of the object's interior (two map windows, about 1/12
    of the frame, inside its edge; the whole object when it is narrower), read from a stricter map
    than ``confidence``: each window's bound under a local affine motion (``_confidence.AFFINE_PRIOR``,
    ``AFFINE_INTERIOR_ONLY``), where a rim's curvature no longer credits the motion along it (a field
    free at the window's scale turns that slide into a rotation the rim cannot show; session 55);
    every other share and ``confidence`` keep the translation bound, since the whole outline does
    pin a body-scale motion that no single window does;
    ``misaligned_fraction``: the share of its observed part where the high-passed residual
    exceeds the noise's expected share by more than a tenth (structure left misaligned; a lone
    row or column of one image, a detector's dead line, left out; see
    ``radiokit.register._confidence``); ``residual_motion``: the median over the observed part
    of what one Gauss-Newton step on the residual would still move (full-resolution px, a
    detection statistic that underestimates large misalignments); ``excess_kept``: the mean
    excess of that residual over the noise's share after registering against before, over the
    observed windows that showed over a tenth before (0: all the misaligned structure explained;
    1 or more: none of it, or made worse; NaN when under 1 % of the observed part showed any); ``noise``: the noise level
    the confidence map used (its units): the fixed image's estimate, or, where lower, the residual's
    where the registered images agree (a texture both hold is not noise; ``_confidence.pair_noise_map``). ``ok`` is False, with a ``reason``, on folding (over 0.1 % of the
    object), divergence (residual complexity worse than not registering, and than the noise alone
    leaves a perfect registration: an image registered to itself starts from 0), non-convergence (but not when the
    budget merely ended with the field still moving at a finest level coarser than these checks'
    binning while the residual passes their line: slow, not lost; ``converged`` stays False and
    ``note`` says so), too little of
    the interior observed (under half: the field there is the regulariser's guess, whatever the
    similarity says) unless a silent preset's field is body-scale (``body_scale``), a residual that still
    moves (a step over 0.35 px), too much of the observed part misaligned (over half), or over half
    of the pair's misaligned structure kept (``excess_kept``: the motion was not found), or an object
    whose structure does not determine its affine motion (``affine_bound``).
    ``body_scale``: when the interior is under half observed, how far (RMS, full-resolution px)
    the field departs from a quadratic motion fitted to its observed rim, over that rim and over
    the unobserved interior (the larger); at most 0.3 px, a silent preset's field (``silent``,
    ``silent-fast``: stiff lattices started from the silhouettes) is trusted there: a compressed
    homogeneous body moves smoothly at its own scale, its observed edges test that and the
    stiff regulariser fills the interior accordingly. NaN when the interior is observed, or
    when the observed rim is too small to fit a quadratic to. ``affine_bound``: measured for every result (NaN
    for an object under 100 binned pixels or a flat image), the Cramer-Rao bound (full-resolution
    px) of the worst-determined affine motion of the object from the fixed image alone
    (``_confidence.affine_bound``; once per register() call); over 0.5 px (``OBSERVED_PX``) the
    result is flagged, whatever else it passed: a round body shows no turn about its centre, an
    ellipse no shear along its axes, and a field that fits such a body is judged the same whatever
    the truth (an inclusion off the centre, or corners, pin it). Not a complete test: the bound
    falls with the noise, as a rendered rim's pixel steps read a turn "determined" that no
    registration finds (a sphere turned 2 degrees, returned at the identity's error: 0.88 px at
    noise 0.01, 0.25-0.36 at 0.002; benchmarks/README.md, "The affine bound for every result").
    ``note``: what is worth knowing of a result not
    flagged for it (empty, or the finest level still moving at the end of its budget).
    ``disagreement`` (``register(..., regularisation_check=True)`` only; NaN otherwise): the median over
    the object's interior of ``|d - d2|`` (full-resolution px), ``d2`` the field of a second
    registration regularised differently (rc, preset ``weak`` area-averaged to 0.1 Mpx with a
    quarter of its iterations; ``fast`` for a ``weak`` result, ``auto``'s included; not run, NaN,
    for a result already flagged); over 0.6 px, with
    the second run passing its own checks, a trusted result is flagged: two fields that each pass the checks but differ there are the regularisers'
    guesses, not the images'.
    ``rim_share`` and ``inconsistency`` (``register(..., rim_check=True)`` only; NaN otherwise):
    ``rim_share`` is the share of the object's observed interior (the observed object when it has
    no interior) whose map window holds structure of one direction only
    (``_confidence.one_directional``: a rim, a plate's or a slab's edge, straight or gently curved;
    the fixed image's alone). There the map credits the rim's curvature with the motion along it,
    which a field free at the window's scale slides unseen. Over a half (``_RIM_GATE``), a result
    the other checks trust is registered backward (``fixed`` onto ``moving``, its own method and
    preset) and ``inconsistency`` is the median over the object of ``|d(x) + e(x + d(x))|``
    (full-resolution px, ``e`` the backward field); over ``OBSERVED_PX`` (0.5 px) the result is
    flagged: the field along the rim is the prior's guess, and the two directions guessed
    differently. ``inconsistency`` is NaN where the gate stayed shut or the result was already
    flagged. It costs the backward registration's time (``options["rim_check"]``), only where the
    gate opens: textured pairs never pay it. Not the default: on the phantom pairs it flagged 3
    more of 44 failed results on the training seeds and moved no verdict on the test seeds or the
    held-out generator; and it is not a complete test, two registrations that guess alike pass
    (benchmarks/README.md, "The along-rim slide: a gated forward-backward test").
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
    interior_observed: float = float("nan")
    misaligned_fraction: float = float("nan")
    excess_kept: float = float("nan")
    residual_motion: float = float("nan")
    body_scale: float = float("nan")
    affine_bound: float = float("nan")
    disagreement: float = float("nan")
    rim_share: float = float("nan")
    inconsistency: float = float("nan")
    noise: float = float("nan")
    ok: bool = True
    reason: str = ""
    note: str = ""


@dataclass
class Registration:
    displacement: np.ndarray
    method: str
    quality: Quality
    options: dict = field(default_factory=dict)
    # (rows, cols) float32 in [0, 1]; >= 0.5: motion observed; 0 where the field carries the pixel out
    # of the frame (the moving image holds nothing there: _full_confidence)
    confidence: np.ndarray | None = None
    # B-spline methods: the lattices the field is the sum of, coarse to fine ((lattice, coefficients));
    # what rc's ``start_lattices`` takes (``auto`` runs its plain preset's finest level on them);
    # None where the field is not theirs alone (a silent preset adds the silhouette's map)
    lattices: list | None = field(default=None, repr=False, compare=False)

    def warp(self, image, order=1) -> np.ndarray:
        """``image(x + d(x))``: an image on the moving grid brought onto the fixed grid.

        Raises ValueError for an image not of the registered pair's shape (``warp`` samples any
        image on the field's grid: a transposed or binned one came back the pair's shape, the
        wrong pixels in it)."""
        shape = np.shape(image)
        if len(shape) == 2 and shape != self.displacement.shape[1:]:
            raise ValueError(
                f"image {shape} is not of the registered pair's shape {self.displacement.shape[1:]}: "
                "the field maps that grid only"
            )
        return warp(image, self.displacement, order=order)

    def run_record(self) -> dict:
        """What a B-spline registration ran: ``preset`` (with ``preset="auto"``, the one it
        returned) and ``preset_reason`` (auto's why), ``initial`` (what the field started from);
        nothing for the flow peers, which have no presets. Any method: ``clipped_fixed``,
        ``clipped_moving``, the extreme pixels register() clipped before registering (only when
        it clipped any); ``regularisation_check`` and its seconds where one was asked for. Written
        beside :class:`Quality` by ``radiokit register`` and ``radiokit process``, so that the file
        alone says how to reproduce the field."""
        out = {}
        if self.method in BSPLINE_METHODS:
            chosen = self.options.get("auto")
            out["preset"] = chosen.preset if chosen is not None else self.options.get("preset", "default")
            if chosen is not None:
                out["preset_reason"] = chosen.reason
        if "initial" in self.options:
            out["initial"] = self.options["initial"]
        out.update({f"clipped_{k}": v for k, v in self.options.get("clipped", {}).items()})
        second = self.options.get("regularisation_check")
        if second is not None:  # register(..., regularisation_check=True): the second run's preset and time
            out["regularisation_check"] = second["preset"] + ("" if second["run"] else " (not run: already flagged)")
            out["regularisation_check_seconds"] = second["seconds"]
        return out


METHODS: dict = {}  # name -> function(fixed, moving, mask, **options) -> (displacement, info dict)


def _method(name):
    def deco(fn):
        METHODS[name] = fn
        return fn

    return deco


_LOADED = []  # the method modules imported so far (each once)


def load_methods() -> dict:
    """:data:`METHODS` with every method in it: the modules that fill it are imported on first
    use (here, or by :func:`register`), once, so a caller listing or checking names before any
    registration calls this first."""
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
    return METHODS


def _check(fixed, moving, mask):
    for name, a in (("fixed", fixed), ("moving", moving)):
        # its masked pixels (dead ones, a NaN border filled with anything) were registered as
        # data, and no mask limited the similarity
        refuse_masked(a, name, "mask")
    refuse_masked(mask, "mask")
    f = np.asarray(fixed)
    m = np.asarray(moving)
    for name, a, given in (("fixed", f, fixed), ("moving", m, moving)):
        if a.ndim != 2:
            raise ValueError(f"{name} image must be 2-D (rows, cols); got shape {a.shape}{image_hint(given, a.shape)}")
        # bool is 0/1, as the command line reads a bool TIFF (into float32); it was refused here
        if a.dtype.kind not in "buif":
            raise ValueError(f"{name} image must be numeric (or bool, as 0/1); got dtype {a.dtype}")
        if min(a.shape) < MIN_SIDE:
            raise ValueError(f"{name} image is too small to register: {a.shape}")
        if max(a.shape) > MAX_SIDE:
            raise ValueError(
                f"{name} image is too large to register: {a.shape}, over {MAX_SIDE} px a side "
                "(OpenCV's limit); crop or bin it"
            )
    if f.shape != m.shape:
        raise ValueError(f"fixed {f.shape} and moving {m.shape} images differ in shape")
    cast = []
    for name, a in (("fixed", f), ("moving", m)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} image contains NaN or inf ({int(np.sum(~np.isfinite(a)))} pixels)")
        with np.errstate(over="ignore"):  # refused just below, in the user's terms
            a32 = a.astype(np.float32, copy=False)
        # finite float64 past float32's range became inf here, once called "NaN or inf" pixels
        if a32 is not a and not np.all(np.isfinite(a32)):
            big = int(np.sum(~np.isfinite(a32)))
            raise ValueError(f"{name} image has values beyond float32's range ({big} pixels over 3.4e38): rescale it")
        cast.append(a32)
    f, m = cast
    for name, a in (("fixed", f), ("moving", m)):
        if float(a.max()) == float(a.min()):
            raise ValueError(f"{name} image is constant: nothing to register")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype != bool:  # a float mask of weights was cast to all True
            raise ValueError(f"mask must be a bool array (True on the object); got dtype {mask.dtype}")
        if mask.shape != f.shape:
            raise ValueError(f"mask {mask.shape} does not match the images {f.shape}")
        if not mask.any():
            raise ValueError("mask selects no pixel")
    return f, m, mask


# A pixel this many of the pair's 0.1-99.9 % ranges beyond that range is clipped to it. The range
# is the 0.1-99.9 %, not the 1-99 % of rc's unit: a body under 1 % of the frame in the open beam
# lies beyond the beam's 1-99 % (its noise alone), and would have been clipped as an outlier; what
# is clipped is under a thousandth of the frame (hot pixels, a zinger, a defect left uncorrected).
# Not chosen on any benchmark: the farthest any pixel of the benchmark generators lies beyond
# even the 1-99 % range is 0.6 of it (sharp inclusions of bench_register_phantoms' seeds
# 6000-6059, every third; the family's 0.08), and a 4x4 static cluster of hot pixels 75 ranges out
# already cost a textured 1 px shift 20x its error (0.003 -> 0.055 px), 235 ranges out all of it
# (rc's L-BFGS stopped after one iteration with a zero field, its gradient all the cluster's
# edges; the checks' noise map, a windowed mean square, read the cluster as the noise and
# trusted that field).
_CLIP_RANGES = 10.0
_CLIP_PERCENTILES = (0.1, 99.9)


def _clip_extremes(f, m, lo, hi):
    """``(f, m, counts)``: the checked pair with pixels beyond ``_CLIP_RANGES`` of the pair's range
    ``lo``-``hi`` (:func:`_pair_range`) from that range clipped to that line, the same line for
    both images (a static hot pixel stays static); each image itself when nothing of it is
    clipped. ``counts``: the pixels clipped, per image (``Registration.options["clipped"]`` when
    any)."""
    counts = {"fixed": 0, "moving": 0}
    if not hi > lo:  # no range to measure by (a frame nearly all one level): nothing is an outlier
        return f, m, counts
    a, b = np.float32(lo - _CLIP_RANGES * (hi - lo)), np.float32(hi + _CLIP_RANGES * (hi - lo))
    out = []
    for name, x in (("fixed", f), ("moving", m)):
        if x.min() < a or x.max() > b:
            counts[name] = int(np.count_nonzero((x < a) | (x > b)))
            x = np.clip(x, a, b)
        out.append(x)
    return out[0], out[1], counts


# A pair whose 0.1-99.9 % range lies beyond 2^+-24 is registered and checked scaled by a power of
# two (exact in floating point) to a range near 1: the confidence map's gradient covariance goes
# as the intensity to the fourth power, past float32's range (a pair in counts per square metre,
# ~1e12, read 1 % observed; at 1e-12, 0 %), and the checks' floors are absolute. Nothing met in
# practice comes near (counts, transmissions and line integrals span ~1e-3 to ~1e6), and a pair
# within the bounds is not touched.
_SAFE_RANGE = (2.0**-24, 2.0**24)


def _pair_range(f, m, percentiles):
    """The lower of the two images' lower and the higher of their upper ``percentiles``
    (~250k samples each)."""
    from radiokit.register._confidence import sample_step

    step = sample_step(f.size)
    (f1, f99), (m1, m99) = (np.percentile(a[::step, ::step], percentiles) for a in (f, m))
    return min(f1, m1), max(f99, m99)


def _rescale(f, m, lo, hi):
    """``(f, m, scale)``: the pair times ``scale``, a power of two that brings its range ``lo``-``hi``
    (:func:`_pair_range`; clipping leaves it as it was) near 1 when it lies beyond
    ``_SAFE_RANGE``; else the very arrays and 1 (see ``_SAFE_RANGE``)."""
    span = float(hi) - float(lo)
    if not span > 0 or _SAFE_RANGE[0] <= span <= _SAFE_RANGE[1]:
        return f, m, 1.0
    scale = 2.0 ** -round(np.log2(span))
    # in float64: a subnormal pair's factor (2^146 at 1e-44) is past float32's range
    return (f.astype(np.float64) * scale).astype(np.float32), (m.astype(np.float64) * scale).astype(np.float32), scale


def _check_option_names(method, options):
    """TypeError (Python's for an unexpected keyword) naming an option ``method`` does not take
    and the ones it does: the B-spline methods (``**options``) ignored a misspelt one, the peers'
    own TypeError named a private function."""
    import inspect

    if method in BSPLINE_METHODS:
        from radiokit.register._bspline import PRESETS

        known = {"preset", "callback", "start_lattices", *PRESETS["default"]}
    else:
        params = list(inspect.signature(METHODS[method]).parameters.values())[3:]  # after fixed, moving, mask
        if any(p.kind is p.VAR_KEYWORD for p in params):
            return
        known = {p.name for p in params}
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"unknown option {unknown[0]!r} for method {method!r}; its options: {', '.join(sorted(known))}")


def check_options(method, options) -> None:
    """Refuse, before any work, an option ``method`` (one of :func:`load_methods`) does not take,
    naming the ones it does, and for a B-spline method an option's value of the wrong kind or
    range: a ValueError in one line each, for a caller that checks a configuration before the
    work preceding its first registration (``radiokit.pipeline.Config``: ``spacing="8"`` was found
    after the whole correction). :func:`register` itself raises Python's TypeError for an unknown
    option's name."""
    load_methods()
    try:
        _check_option_names(method, options)
    except TypeError as exc:
        raise ValueError(str(exc)) from None
    if method in BSPLINE_METHODS:
        from radiokit.register._bspline import check_option_values

        check_option_values(options)


def register(
    fixed, moving, method="rc", mask=None, *, retry=False, regularisation_check=False, rim_check=False, **options
) -> Registration:
    """Register ``moving`` onto ``fixed`` (2-D arrays of one shape).

    Input domain: line integrals (``-ln(I / I0)``, ``radiokit.calibrate``'s ``domain="log"``),
    which is what ``radiokit.pipeline`` feeds. There a thickness change is a scale of the image
    (residual complexity's smooth residual) and the noise is nearly uniform over the body;
    transmission images (``domain="linear"``) register too, worse on nearly textureless
    phantoms (``benchmarks/README.md``, the family's intensity-domain rows).

    Pixels more than ten of the pair's 0.1-99.9 % ranges beyond that range (a hot pixel, a
    zinger, an uncorrected defect: a few of them once stalled rc with a zero field) are clipped
    to that line for the registration and its checks; ``options["clipped"]`` counts them per image.
    A pair whose range lies beyond 2^+-24 (counts per square metre, ~1e12) is registered and
    checked scaled by a power of two (the checks' fourth powers left float32's range);
    ``quality.noise`` stays in the image's units.

    ``mask`` (bool) limits the similarity to the object. A region exactly flat at one value in
    both images whose edge stays put (an opaque strip on the detector, a range clipped in both:
    ``_confidence.flat_common``) is unobserved in ``confidence``: it holds nothing of the object.
    It stays in the similarity (left out with a margin, it took the edges of a textureless body
    clipped around, or held by plates, out of the data: benchmarks/README.md, "A flat band fixed
    to the detector"). ``retry=True`` repeats a failed
    ``rc``/``ssd``/``ncc``/``mi`` registration with 10x stronger regularisation. ``regularisation_check=True``
    registers the pair a second time, regularised differently, and flags a trusted result whose
    field differs from that one's over the object's interior (``Quality.disagreement``; it costs
    the second registration's time, a cheap one's: 1-2x ``fast``'s at 560 px;
    ``options["regularisation_check"]``). ``rim_check=True`` (off by default: it flagged 3 more of 44 failed phantom results on the
    training seeds, none more on the test seeds or the held-out generator) registers the pair
    backward where the observed interior is mostly one-directional structure and a trusted result
    could be sliding along a rim (``Quality.rim_share``, ``Quality.inconsistency``). ``options`` go
    to the method (see ``radiokit.register.METHODS[name].__doc__``).

    The result carries ``confidence`` (where the motion is observable from these images, a
    translation of each window's bounded, see ``radiokit.register._confidence``; the flag's test of
    the interior's observed share reads the stricter local-affine map, which is not returned) and ``quality`` (``ok`` and a ``reason``, decided without
    the truth); ``roi_observed(reg.confidence, roi)`` says how much of a ROI was observed.

    Bool images register as 0/1 (as ``radiokit register`` reads a bool TIFF).

    Raises ValueError, in one line naming the problem, for images that are not 2-D, numeric,
    finite (and within float32's range), non-constant, of one shape and 8 to 32766 px a side, a
    mask that is not a bool array of that shape selecting a pixel, a masked array (``np.ma``), an unknown method or preset,
    or an option value out of its range; TypeError for an option the method does not take; ``MissingPeer`` (ImportError) for a
    peer whose package is not installed.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy import ndimage
    >>> from radiokit.register import register, roi_observed, warp
    >>> moving = ndimage.gaussian_filter(np.random.default_rng(0).random((96, 96)), 2).astype(np.float32)
    >>> fixed = warp(moving, np.full((2, 96, 96), 1.0, np.float32))  # moving pulled by one pixel
    >>> reg = register(fixed, moving, preset="fast")
    >>> reg.quality.ok, np.median(reg.displacement, axis=(1, 2)).round(1).tolist()
    (True, [1.0, 1.0])
    >>> roi_observed(reg.confidence, (20, 70, 20, 70))  # textured: observed everywhere
    1.0
    """
    load_methods()
    if method not in METHODS:
        raise ValueError(f"unknown registration method {method!r}; available: {', '.join(sorted(METHODS))}")
    _check_option_names(method, options)
    f, m, mask = _check(fixed, moving, mask)
    # within a call that registers this pair again (auto, retry): the outer call's arrays, already
    # clipped and scaled (its range was measured there, not again per preset)
    if _memo_of(f, m, mask) is not None:
        return _register(f, m, method, mask, retry, options)
    given = (f, m)  # in the user's units, for the reason's ranges (_scales_reason)
    lo, hi = _pair_range(f, m, _CLIP_PERCENTILES)
    f, m, clipped = _clip_extremes(f, m, lo, hi)
    f, m, scale = _rescale(f, m, lo, hi)
    token = _PAIRS.set(_Memo((f, m, mask), scale=scale))
    try:
        reg = _register(f, m, method, mask, retry, options)
        if rim_check:
            _rim_check(reg, f, m, mask, options)
        if regularisation_check:
            _regularisation_check(reg, f, m, mask)
        if any(clipped.values()):
            reg.options["clipped"] = clipped
        if not reg.quality.ok:
            reg.quality.reason += _scales_reason(*given, reg.quality)
        return reg
    finally:
        _PAIRS.reset(token)


#: the ratio of the two images' 1-99 % ranges over which a flagged pair is said to be of two
#: value scales: twice the factor of 2 either way the checks' global gain explains (README,
#: "Register"), so a pair the gain could explain is never told so
_SCALES_RATIO = 4.0

#: the least NCC of the registered pair (gain- and offset-blind) at which two ranges are named: a
#: copy at another scale registered is one picture, correlated over half; a pair of one scale whose
#: contents differ (a body grazing one frame, filling the other: 12-fold ranges, NCC 0.19) was told
#: "counts against transmission, or a rescaled copy?" (s53rvreg)
_SCALES_NCC = 0.5


def _scales_reason(fixed, moving, q) -> str:
    """What a flagged pair shows of why it may be unregistrable as given: counts against
    transmission or a unit scale (s53: uint16 12-bit counts against a float32 copy in 0-1, moved
    2 px, registered at NCC 0.99 and flagged "did not find the motion" with no word of why). The
    checks compare intensities and explain a gain of at most 2 either way; the flag stays (no check
    judges intensities of two scales) and the two ranges (``fixed``, ``moving`` in the user's
    units) are named, only where they differ by over :data:`_SCALES_RATIO` and the registered pair
    is one picture (NCC at least :data:`_SCALES_NCC`). In the reason, not only on the command
    line: a script, and the result file, read that (s53rvreg)."""
    if not q.ncc_after >= _SCALES_NCC:  # NaN: not measured, nothing said
        return ""
    from radiokit.register._confidence import sample_step

    spans = []
    for a in (fixed, moving):
        step = sample_step(a.size)
        spans.append(np.percentile(a[::step, ::step].astype(np.float64), [1, 99]))
    widths = [hi - lo for lo, hi in spans]
    if min(widths) <= 0 or max(widths) / min(widths) <= _SCALES_RATIO:
        return ""
    (a, b), (c, d) = spans
    return (
        f"; the images' 1-99 % ranges differ {max(widths) / min(widths):.0f}-fold (fixed {a:.4g} to {b:.4g}, "
        f"moving {c:.4g} to {d:.4g}), which the checks compare with a gain of at most 2: counts against "
        "transmission, or a rescaled copy? register two images of one scale"
    )


def _register(f, m, method, mask, retry, options) -> Registration:
    """:func:`register` on checked images (``_check``'s)."""
    if method in BSPLINE_METHODS and options.get("preset") in AUTO_PRESETS:  # plain, then weak or silent
        from radiokit.register._auto import register_auto

        return register_auto(register, f, m, method, mask, retry, options)
    t0 = time.perf_counter()
    disp, info = METHODS[method](f, m, mask, **options)
    seconds = time.perf_counter() - t0
    kept = {k: v for k, v in options.items() if k != "start_lattices"}  # arrays, not a setting to report
    reg = Registration(np.ascontiguousarray(disp, dtype=np.float32), method, Quality(), kept)
    if info.get("lattices_whole"):  # a silent preset's field adds the silhouette's map to them
        reg.lattices = info["lattices"]
        for grid, _ in reg.lattices:
            grid.drop_caches()
    if "init" in info:  # what the field started from (the silhouette's map, or why not)
        reg.options["initial"] = info["init"]
    if "binned" in info:  # registered area-averaged by this factor (``bin_pixels``), the field upsampled
        reg.options["binned"] = info["binned"]
    if "abandoned" in info:  # abandon_px: the run stopped before its finest level, and why
        reg.options["abandoned"] = info["abandoned"]
    if "thinning_refit" in info:  # refit_thinning: what the second pass divided out
        reg.options["thinning_refit"] = info["thinning_refit"]
    if "noise_sigma" in info.get("options", {}):  # alpha set from the pair's noise: what it measured and used
        reg.options.update(alpha=info["options"]["alpha"], noise_sigma=info["options"]["noise_sigma"])
    _assess(reg, f, m, mask, info, seconds)
    if retry and not reg.quality.ok and "regularisation" in info:
        opts = dict(options, regularisation=10 * info["regularisation"])
        again = register(f, m, method, mask, retry=False, **opts)
        again.quality.seconds += seconds
        return again
    return reg


_ASSESS_PIXELS = 400_000


def _assess_binning(n_pixels) -> int:
    """The factor the checks bin an image of ``n_pixels`` by: to at most ~``_ASSESS_PIXELS``."""
    return max(1, int(np.ceil(np.sqrt(n_pixels / _ASSESS_PIXELS))))


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


def _bin_mask(mask, k):
    """``mask`` binned by ``k`` to :func:`_bin`'s shape by
    :func:`~radiokit.register._common.binned_mask`'s rule, the rows and columns :func:`_bin`
    crops folded into the last bin: a mask only there (the last row of an odd-sized frame) was
    gone before the rule saw it, and no bin was left."""
    m = np.asarray(mask, np.float32)
    if k == 1:
        return m > 0.5
    if not (m.shape[0] % k or m.shape[1] % k):  # nothing cropped: _bin's means, 5x faster at 2240
        return binned_mask(_bin(m, k))
    starts = [np.arange(n // k) * k for n in m.shape]
    sums = np.add.reduceat(np.add.reduceat(m, starts[0], axis=0), starts[1], axis=1)  # exact: counts
    sizes = [np.diff(s, append=n) for s, n in zip(starts, m.shape, strict=True)]
    return binned_mask(sums / np.outer(*sizes))


def _bin_pair(f, m, mask, k):
    """``(fixed, moving, mask)`` area-averaged by ``k`` as the checks see them (the mask by
    :func:`_bin_mask`)."""
    maskb = None if mask is None else _bin_mask(mask, k)
    return _bin(f, k), _bin(m, k), maskb


def _range_unit(f, mask):
    """``1 / (p99 - p1)`` of ``f`` (inside ``mask``; its full range when those tie; 1 when it is
    constant there): residual complexity's alpha (0.05, Myronenko & Song's for images in [0, 1])
    then means the same for line integrals, transmissions and counts, as in rc's own data term."""
    from radiokit.register._confidence import sample_step

    v = f[mask] if mask is not None else f[:: sample_step(f.size), :: sample_step(f.size)]
    lo, hi = np.percentile(v, [1, 99]) if v.size else (0.0, 0.0)
    if hi <= lo:
        lo, hi = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)
    return np.float32(1.0 / (hi - lo)) if hi > lo else np.float32(1.0)


def _rounding_rc(f, unit) -> float:
    """The residual complexity float32 rounding of ``f`` can make (in ``unit``s): a residual of
    ``eps |f|`` costs at most ``mean(r^2) / (2 alpha)`` (``log(1 + x) <= x``, an orthonormal DCT;
    alpha 0.05, ``residual_complexity``'s).
    A change below it is not a divergence (identical images: a 1e-7 px step from 0 to 1e-16)."""
    eps = float(np.finfo(np.float32).eps) * float(unit)
    return 0.5 * eps * eps * float(np.mean(np.square(f, dtype=np.float64))) / 0.05


#: A field whose 99th percentile |d| is under this (full-resolution px) may leave a residual up to
#: the noise's share without "diverging" (:func:`_noise_rc`: an image registered to itself starts
#: from 0); a larger one may not: on a pixel-scale texture, which the fixed image's noise estimate
#: counts as noise, a wrong field of 2-3 px stayed under that share (review, session 31).
_NOISE_RC_PX = 1.0


def _diverged(q, p, db, k) -> str:
    """``diverged``'s reason, or "": residual complexity after worse than before and, for a field
    under :data:`_NOISE_RC_PX`, than the noise alone leaves (the images may share their noise)."""
    tol = _rounding_rc(p.f, p.unit)
    if q.rc_after <= q.rc_before + tol:
        return ""
    if k * float(np.percentile(np.hypot(*db), 99)) > _NOISE_RC_PX:
        return f"diverged: residual complexity {q.rc_after:.6g} after > {q.rc_before:.6g} before"
    noise_rc = _noise_rc(p, db)
    if q.rc_after <= noise_rc + tol:
        return ""
    return (
        f"diverged: residual complexity {q.rc_after:.6g} after > {q.rc_before:.6g} before "
        f"(and > {noise_rc:.3g}, the noise's alone)"
    )


def _noise_rc(p, d) -> float:
    """The residual complexity the noise alone leaves a perfect registration of two
    independently noisy images of the pair (``p``: :class:`_PairChecks`, binned) by the field
    ``d`` (binned px): white noise of the fixed image's local level (``model_floor`` under it)
    times ``1 + interpolation_variance``, the moving image's share after bilinear
    interpolation. Its orthonormal DCT coefficients are Gaussian of the mean variance, so the
    measure is ``1/2 E log(1 + c z^2)`` (``c`` that variance over alpha, 0.05), taken on 2000
    quantiles of the normal (within 1e-3 of the integral).

    Why. ``diverged`` compares the residual after with the one before; when the images share
    their noise (an image registered to itself) the one before is exactly 0, and a near-identity
    field (a peer's 0.004-0.24 px) makes any interpolation of the noise and of the structure a
    "divergence". A residual within what the noise leaves a perfect registration is not worse
    than not registering; a field that moves a textured image by pixels leaves far more."""
    from scipy.special import ndtri

    from radiokit.register import _confidence as C

    sigma = p.consistency.sigma
    s2 = (sigma * sigma + C.model_floor(p.f) ** 2) * (1.0 + C.interpolation_variance(d, _WINDOW))
    if p.mask is not None:
        s2 = np.where(p.mask, s2, 0)
    c = float(np.mean(s2, dtype=np.float64)) * float(p.unit) ** 2 / 0.05
    z = ndtri((np.arange(2000) + 0.5) / 2000)
    return float(0.5 * np.mean(np.log1p(c * z * z)))


def _assess(reg, f, m, mask, info, seconds):
    """Fill ``reg.quality``. The similarities are measured on the pair (and field) area-averaged
    to at most ~0.4 Mpx (these are diagnostics, and a fraction of the full-resolution cost; the
    field itself is not binned); det J at full resolution."""
    q = reg.quality
    reasons = _non_finite(reg)
    p = _pair_checks(f, m, mask)
    k = p.k
    if k > 1:
        db = _bin(reg.displacement, k) / np.float32(k)
        w = _warp(p.m, _field(db))
    else:
        w = _warp(m, _field(reg.displacement))
        db = reg.displacement
    q.ncc_before = p.ncc_before
    q.ncc_after = ncc(w, p.f, p.mask)  # a report, not a check: the whole warped image
    w, out = _judged(p, w, db)
    # the residual before over the same pixels: a strip the field carries out is not "removed"
    q.rc_before = p.rc_before if out is None else residual_complexity(np.where(out, 0, p.m - p.f) * p.unit, p.mask)
    q.rc_after = residual_complexity((w - p.f) * p.unit, p.mask)
    det = jacobian_determinant(reg.displacement)
    if mask is not None:
        det = det[mask]
    q.folds = int(np.count_nonzero(det <= 0))
    q.min_det_j = float(det.min())
    q.iterations = int(info.get("iterations", 0))
    q.converged = bool(info.get("converged", True))
    q.seconds = seconds
    memo = _memo_of(f, m, mask)
    observed, n_object = _observed(reg, p, w, db, 1.0 if memo is None else memo.scale, out)
    reasons += observed
    n_object = mask.sum() if mask is not None else n_object * k * k  # full-resolution pixels
    if q.folds > _MAX_FOLDS * max(int(n_object), 1):
        reasons.append(f"folding: {q.folds} pixels with det J <= 0 (min {q.min_det_j:.3g})")
    diverged = _diverged(q, p, db, k)
    if diverged:
        reasons.append(diverged)
    if not q.converged and _slow_not_lost(info, q, k):
        q.note = (
            f"{info.get('message', 'did not converge')}; not flagged for it: the residual moves "
            f"{q.residual_motion:.2f} px, within the checks' {_MAX_RESIDUAL_MOTION:g} (slow, not lost)"
        )
    elif not q.converged:
        reasons.append(info.get("message", "did not converge"))
    q.ok = not reasons
    q.reason = "; ".join(reasons)


def _non_finite(reg) -> list:
    """The reason (a list of at most one) for a field with NaN or inf pixels (a diverging solve),
    whose non-finite pixels are set to 0 in ``reg.displacement``: the field returned, which the
    other checks then measure. Measured on the NaN field itself, they read "residual complexity
    nan after", "460 % of the structure left" and the like, reasons that hid this one."""
    bad = ~np.isfinite(reg.displacement).all(axis=0)
    if not bad.any():
        return []
    reg.displacement = np.where(bad, np.float32(0), reg.displacement).astype(np.float32)
    return [
        f"non-finite displacement: {int(bad.sum())} of {bad.size} pixels NaN or inf (the method diverged; "
        "set to 0 in the field returned)"
    ]


def _slow_not_lost(info, q, k) -> bool:
    """Whether a run that is not converged only because its finest level's budget ended with the
    field still moving (``info["still_moving_px"]``; not an abandoned or non-finite run) is slow,
    not lost: that level was coarser than the checks' binning ``k`` (``info["finest_binning"]``,
    times a ``bin_pixels`` run's ``binned``) and the residual is within their line
    (``_MAX_RESIDUAL_MOTION``; NaN, nothing observed: not within), rc's ``extend`` test
    (``_bspline._settles``).

    Why. The move is the 99th percentile of the field's change over the last iterations in
    full-resolution pixels, and a coarse level's steps are coarse: a fast preset's finest level at
    2240 is binned by 8, so 0.07 of its own pixels reads 0.55 px, over ``converge_px``, on
    results within 0.5 px (the family's TRAINING pairs; benchmarks/README.md, "The flag at 2240
    (session 28)"). The checks then see the pair at a finer grid than the run did, and their
    residual is the better judge. Where the run's finest level is as fine as the checks' grid or
    finer, its own verdict stands: it sees what the binned checks miss (``default`` at 2240,
    binned by 2, on a TRAINING picture's blank sky: pixels off, its residual within the line, flagged
    only by this verdict; same section). The move stays reported (``converged`` False,
    ``Quality.note``)."""
    coarser = info.get("finest_binning", 1) * info.get("binned", 1) > k
    return "still_moving_px" in info and coarser and bool(q.residual_motion <= _MAX_RESIDUAL_MOTION)


# One register() call may check one pair several times: ``auto`` registers it two or three
# times, ``retry`` twice, and rc's abandon_px measures fields of it while it runs. What the
# checks compute from the pair alone (_PairChecks: at 2240 a third of rc fast's checks) is then
# computed once: register() holds it for the call, for the pair it checked only (the very
# arrays: a binned run's pair, or another pair a callback registers, is checked afresh, and
# nothing of it is kept past its use).
@dataclass
class _Memo:
    pair: tuple
    checks: _PairChecks | None = None
    scale: float = (
        1.0  # what register() multiplied the pair by (``_rescale``): the checks report noise in the image's units
    )


_PAIRS: contextvars.ContextVar[_Memo | None] = contextvars.ContextVar("radiokit_register_pair", default=None)


def _memo_of(f, m, mask) -> _Memo | None:
    """The memo of this register() call when it is for these very arrays, else None."""
    memo = _PAIRS.get()
    if memo is not None and all(a is b for a, b in zip(memo.pair, (f, m, mask))):
        return memo
    return None


def _pair_checks(f, m, mask) -> _PairChecks:
    """The checks' pair-only part for ``f``, ``m``, ``mask`` (full resolution): the call's, when
    it is the pair register() checked (computed the first time)."""
    memo = _memo_of(f, m, mask)
    if memo is None:
        return _PairChecks(f, m, mask)
    if memo.checks is None:
        memo.checks = _PairChecks(f, m, mask)
    return memo.checks


class _PairChecks:
    """What the checks measure on the pair alone, before any field: the pair binned as the
    checks see it (``k``; ``f``, ``m``, ``mask`` binned), the range's unit, the confidence map
    (``ob``, ``obs`` its observed object, ``inner`` the object's interior), and, when first
    needed, the similarities before, the fixed image's part of the residual tests and the
    moving image's excess (``before``)."""

    def __init__(self, f, m, mask):
        from radiokit.register import _confidence as C

        self.k = k = _assess_binning(f.size)
        self.f, self.m, self.mask = _bin_pair(f, m, mask, k) if k > 1 else (f, m, mask)
        # the bound in full-resolution pixels, as the field's error is judged: binning by k divides
        # a bound in binned pixels by k (a 2240 frame's textureless interior read 65 % observed in
        # binned pixels, 27 % in its own)
        self.ob = C.observability(self.f, _WINDOW, self.mask, bound_scale=k, moving=self.m, affine_prior=C.AFFINE_PRIOR)
        # ``map``: what the result carries (Registration.confidence, the ROIs' verdict) and every check
        # but the interior's observed share reads; under AFFINE_INTERIOR_ONLY the translation map,
        # because the whole outline pins a body-scale motion no single window does (session 55,
        # benchmarks/README.md, "Local affine observability"), and ``obs_interior`` the affine one
        self.map = self.ob.confidence
        if self.ob.translation is not None and C.AFFINE_INTERIOR_ONLY:
            self.map = self.ob.translation
        self.obs = (self.map >= 0.5) & self.ob.object
        # the same array when the maps are one (the reason names the affine map only when it differs)
        self.obs_interior = self.obs if self.map is self.ob.confidence else (self.ob.confidence >= 0.5) & self.ob.object

    @functools.cached_property
    def unit(self) -> np.float32:
        """Alpha is in the range's units, whatever the image's (:func:`_range_unit`)."""
        return _range_unit(self.f, self.mask)

    @functools.cached_property
    def inner(self) -> np.ndarray:
        return _interior(self.ob.object)

    @functools.cached_property
    def affine_bound(self) -> float:
        """``Quality.affine_bound``: the fixed image's alone, so once per register() call."""
        from radiokit.register import _confidence as C

        return self.k * C.affine_bound(self.f, self.ob.object, self.ob.sigma)

    @functools.cached_property
    def rim_share(self) -> float:
        """``Quality.rim_share``: the share of the observed interior whose window holds structure of
        one direction only (``_confidence.one_directional``); the fixed image's alone."""
        from radiokit.register import _confidence as C

        # the interior's observed part (the object's when it has no interior): there the map's
        # "observed" comes from structure within the window's reach, and a rim's curvature is
        # credited with the motion along it; the body's own rim band is one-directional on any
        # body (0.45-0.5 of a textured family body's observed object) and says nothing of texture
        where = self.obs & (self.inner if self.inner.any() else self.ob.object)
        if not where.any():
            return float("nan")
        return float(np.mean(C.one_directional(self.f, _WINDOW)[where]))

    @functools.cached_property
    def rc_before(self) -> float:
        return residual_complexity((self.m - self.f) * self.unit, self.mask)

    @functools.cached_property
    def ncc_before(self) -> float:
        return ncc(self.m, self.f, self.mask)

    @functools.cached_property
    def consistency(self):
        from radiokit.register import _confidence as C

        return C.Consistency(self.f, _WINDOW, moving=self.m)

    @functools.cached_property
    def before(self) -> np.ndarray:
        """The moving image's excess over the noise (``consistency - 1``), unwarped."""
        return self.consistency(self.m, support=self.mask) - 1.0

    @functools.cached_property
    def motion(self):
        from radiokit.register import _confidence as C

        return C.ResidualMotion(self.f, _STEP_WINDOW)


# The confidence map and the checks are computed on the pair binned to ~0.4 Mpx with a window of
# _WINDOW binned pixels (the default lattice spacing at that size, 1/23 of a 560 px frame).
# "Observed" is where the Cramer-Rao bound of one window is at most 0.5 px (radiokit.register.
# _confidence). Whether the field is right there is judged by the residual's own motion: one
# Gauss-Newton step of the residual against the fixed image's gradient (with a local gain), its
# median over the observed part (``Quality.residual_motion``). A matched estimate like this
# sees a misalignment the residual's mean square (the misaligned share, kept as a second check)
# cannot: at texture = noise a 1.5 px misalignment raises a 24 px window's mean square by about
# 1 %, under its noise scatter, while the step is several times larger than for a field within
# 0.5 px.
# _MIN_OBSERVED, _MAX_RESIDUAL_MOTION, _EXCESS and _MAX_MISALIGNED were chosen on the training
# seeds of benchmarks/regdata.family at 560 px (2 per case), all eight methods of
# bench_register_flag.py, over a grid (the bound's scale 0.5-4, with and without crediting the
# field's correlation length, the least observed share 0.5-0.8, the step's median 0.1-0.5 px in
# windows of 12 and 24 px;
# `bench_register_flag.py --split train --sweep`; numbers in benchmarks/README.md, "The flag").
# The misaligned share's line was then checked on 4 training seeds (800 results): at a fifth it
# flagged 7 more good results than at a half and no more failed ones (all 428 flagged either
# way), so it is a half; at 2 seeds the two had tied.
# What must be observed is the object's interior, _INTERIOR windows inside its edge (beyond
# the window's reach from the edge): a textureless body's edges observe the motion in a band
# (0.47-0.56 of the object on the training pairs, 0.62 for a smooth dome with a sharp rim),
# while its interior is the regulariser's guess, and a smooth wrong field aligns the edges as
# well as a right one. On the training pairs a textureless body's interior is 13-25 % observed
# (7-16 % since the map's window is cut at two spacings, session 13; 34 % on a quiet exposure),
# and any share from 0.3 to 0.7 flags the same results (the observed share of the whole object
# worked only in 0.6 +- 0.05). _EXCESS is 6 standard deviations of a window's noise mean square
# (see radiokit.register._confidence).
_WINDOW = 24.0
_INTERIOR = 2.0  # windows inside the object's edge
_MIN_OBSERVED = 0.5  # of the interior
# ... unless the field is body-scale (Quality.body_scale): a silent interior is the regulariser's
# fill, right when the motion is smooth at the body's scale (a compressed homogeneous body: an
# expansion and a barrelling, a quadratic), wrong under a local motion the edges cannot see
# inside. The observed rim tests which: a local motion moves it by more than a quadratic can
# follow. 0.3 px chosen on the family's TRAINING seeds (560, 2 seeds, every method; results
# flagged for the interior alone): good results <= 0.21 px, failed ones >= 0.52
# (benchmarks/README.md, "A silent interior that moves at the body's scale"). Until session 49
# the rim had to surround the interior (3/4 of 16 directions from the centroid): that called
# textureless slabs, whose straight edges observe only their normal component (the map calls
# the corners observed), "not body-scale" though their edges pin the body's affine motion; the
# affine bound (below) now decides that (benchmarks/README.md, "The silent waiver without the
# surround test"). A fit on one side's rim extrapolates into the interior; a fill that departs
# from the extrapolation reads as not body-scale, so the error is towards flagging.
_BODY_SCALE_PX = 0.3
# ... and only for the silent presets, whose stiff, silhouette-started lattices are that prior: a
# free lattice's fill can look body-scale while its thinning term took the edge's normal motion
# (a dome not moved at all, 256 px: `default` 0.64 px off, body_scale 0.05 px, residual clean;
# `silent` 0.03 px; tests/test_cli.py)
_BODY_SCALE_PRESETS = ("silent", "silent-fast")
# ... and only where the object's edges determine a body-scale motion at all
# (Quality.affine_bound <= _confidence.OBSERVED_PX, the map's own line): a textureless sphere
# turned 4 degrees was trusted 5.5 px off (session 33), its rim moving along itself. Since
# session 49 the bound flags every result, not only this waiver's: at low noise a dome's curved
# contours make the map call its interior observed, so the interior rule never fired (a
# textureless ellipsoid turned 2 degrees trusted 2.84 px off; benchmarks/README.md, "The affine
# bound for every result"). The
# gradients' smoothing (2 px) chosen on TRAINING seeds of benchmarks/bench_register_turned.py
# (1, 2 and 3 px gave the same confusion there; 1 px credits a sampled rim's aliasing), where
# it took failed results flagged 6/14 -> 9/14 for good trusted 8/8 -> 7/8 (an unturned round
# body, whose turn no rim shows); on the family's textureless physical pairs (TRAINING, 100
# seeds at 560, an off-centre disc) the bound reads 0.13-0.36 px, none over the line
# (benchmarks/README.md, "A textureless body turned in the image plane")
_MAX_RESIDUAL_MOTION = 0.35  # px: the step's median; it underestimates a larger misalignment


def _past(value: float, line: float) -> str:
    """``value`` (above ``line``) with the fewest decimals, two at least, that print it above
    the line: 0.354 at two read "0.35 px (...; > 0.35)", a reason that contradicts itself.

    >>> _past(0.354, 0.35), _past(0.64, 0.35), _past(0.35004, 0.35)
    ('0.354', '0.64', '0.35004')
    """
    for decimals in range(2, 7):
        text = f"{value:.{decimals}f}"
        if float(text) > line:
            return text
    return f"{value:.7g}"


# the step's window: half the map's, so that motion varying over the family's shortest
# correlation length (1/20 of the frame, 28 px at 560) is not averaged away inside it (on the
# training seeds 12 px flagged 205/205 failed results where 24 px flagged 201/205)
_STEP_WINDOW = 12.0
_EXCESS = 0.1
_MAX_MISALIGNED = 0.5  # the share of the observed object (see above: 0.2 until session 9)
# Quality.excess_kept: a registration that removes less than half of the misaligned structure the
# pair showed (its residual's excess over the noise, before against after) has not found the
# motion. Found on pairs nothing was chosen on (session 18): a 100 px shift, beyond any capture
# range, was trusted at 98 px of error (`silent` moved little; the residual's step underestimates
# so large a misalignment, 0.30 px, and 44 % misaligned is under the half); it kept 159 % of the
# excess. On the family's TRAINING seeds (560, 2 seeds, every method) good results keep at most
# 0.12 (median 0.013), failed ones 0.001-1.18 (a quarter above 0.5): a half lies 4x above every
# good result; it reads like the "no better than a small fraction of the way". Only when
# what is kept is itself over the misalignment line (_EXCESS): a small local change that is not
# motion (a marker, a zinger cluster of 8-24 px) raised good fields' ratio to 0.2-0.4 (review,
# 256 px textured pairs), so the margin there is under 2x, and a ratio of two excesses each under
# the line says nothing.
_MAX_KEPT = 0.5
# folding flags when it exceeds this share of the object: a compressed body cannot fold, but a
# flow's few folded pixels (patch-scale noise, often in the empty beam or at the body's edge)
# are a local defect, reported in quality.folds, not a failed registration; on the training
# seeds every failed result that folded was flagged for another reason as well
_MAX_FOLDS = 1e-3


def _observed(reg, p, w, d, scale=1.0, out=None):
    """Fill ``reg.confidence`` (full resolution) and the quality's observability fields from
    the pair's checks ``p`` (:class:`_PairChecks`, binned by ``p.k``) and the warped moving image
    ``w`` and field ``d`` binned as they are (``w`` and ``out``: :func:`_judged`'s); the reasons
    for not ok, and the object's size (binned pixels). The residual's motion is reported in
    full-resolution pixels, as the error it stands for is judged (a 2240 frame's step is taken on
    the pair binned by 4); the noise in the image's units, ``scale`` what register() multiplied
    the pair by (``_rescale``)."""
    q = reg.quality
    ob, k = p.ob, p.k
    reg.confidence = _full_confidence(p.map, out, reg.displacement.shape[1:])
    obs, inner = p.obs, p.inner
    n_obj = int(ob.object.sum())
    q.noise = ob.sigma / scale  # the image's units (register() registered the pair times ``scale``)
    # what the field carries out of the frame is not observed: the moving image holds nothing there
    judged = obs if out is None else obs & ~out
    q.observed_fraction = float(judged.sum() / n_obj) if n_obj else 0.0

    def interior_share(seen):  # the whole object's when it has no interior
        return float(seen[inner].mean()) if inner.any() else (float(seen.sum() / n_obj) if n_obj else 0.0)

    # the interior's share alone reads the affine map (p.obs_interior; the same as obs without it)
    q.interior_observed = interior_share(p.obs_interior if out is None else p.obs_interior & ~out)
    q.misaligned_fraction, q.excess_kept, left = _misaligned(p, w, d, judged)
    q.residual_motion = _residual_step(p, w, judged)
    reasons = _left_in_frame(obs, judged)
    from radiokit.register._confidence import OBSERVED_PX

    q.affine_bound = p.affine_bound
    unpinned = q.affine_bound > OBSERVED_PX  # NaN (a flat image, a tiny object): not flagged for it
    if q.interior_observed < _MIN_OBSERVED:
        # on the judged set: the field's values where it carries pixels out are unjudged (a strip
        # carried 8 px further out, nothing the checks see changed, read 1.74 px from body-scale)
        q.body_scale = k * _body_scale(d, ob.object, judged, inner)
        waived = q.body_scale <= _BODY_SCALE_PX and reg.options.get("preset") in _BODY_SCALE_PRESETS
        if not waived or unpinned:
            # a silent body-scale field's only fault is the unpinned affine motion: said here once
            affine = q.affine_bound if waived else float("nan")
            unpinned = unpinned and not waived
            # the share is the local-affine map's when that differs from the returned one: name it and
            # give the returned map's own, or the text contradicts the map a user reads (session 55's
            # review: "2 % of the interior (92 % of the object; confidence map)", the map 69 %)
            where, of_it = "the object's interior", ""
            if p.obs_interior is not p.obs:
                share = interior_share(judged)
                where += " under a local affine motion of each window"
                of_it = f"{100 * share:.0f} % of it and "
            reasons.append(
                f"motion observable in only {100 * q.interior_observed:.0f} % of {where} "
                f"({of_it}{100 * q.observed_fraction:.0f} % of the object on the confidence map, noise {q.noise:.3g}"
                f"{'' if out is None else ', less what the field carries out of the frame'}) "
                f"and {_body_scale_text(q.body_scale, reg.options.get('preset'), affine)}: elsewhere "
                "the field is the regulariser's guess"
            )
    if unpinned:
        reasons.append(_affine_text(q.affine_bound))
    if judged.any() and q.residual_motion > _MAX_RESIDUAL_MOTION:
        reasons.append(
            f"the residual still moves: a Gauss-Newton step on it gives {_past(q.residual_motion, _MAX_RESIDUAL_MOTION)} px "
            f"(median over the observed object; > {_MAX_RESIDUAL_MOTION:g})"
        )
    if q.excess_kept > _MAX_KEPT and left > _EXCESS:
        reasons.append(
            f"the registration left {100 * q.excess_kept:.0f} % of the structure the pair showed misaligned "
            "before it (residual above the noise's, observed object): it did not find the motion"
        )
    if judged.any() and q.misaligned_fraction > _MAX_MISALIGNED:
        reasons.append(
            f"structure left misaligned in {100 * q.misaligned_fraction:.0f} % of the observed object "
            f"(residual above the noise's by more than {100 * _EXCESS:.0f} %)"
        )
    return reasons, n_obj


def _full_confidence(conf, out, shape) -> np.ndarray:
    """``Registration.confidence``: the checks' map ``conf`` (their grid) upsampled to ``shape``
    (linear interpolation), in [0, 1], and 0 where the field carries the pixel out of the frame
    (``out``, the checks' grid, :func:`_judged`'s; None: nowhere). Why: the moving image holds
    nothing there, so the motion is not observed, as the checks' shares already count it
    (:func:`_observed`); the map is what is saved, drawn and read for the ROIs (``roi_observed``).
    A pixel is out where the binned pixel nearest to it is, on the grid the map is interpolated
    from (cv2's pixel centres: full-resolution x at binned ``(x + 0.5) * n / N - 0.5``): on a
    grid binned by k, each binned pixel's own k x k block, the block it averages."""
    import cv2

    rows, cols = shape
    if conf.shape != (rows, cols):
        if out is not None:
            nearest = [
                np.minimum(((np.arange(full) + 0.5) * (n / full)).astype(np.intp), n - 1)
                for n, full in zip(conf.shape, shape, strict=True)
            ]
            out = out[np.ix_(*nearest)]
        conf = cv2.resize(conf, (cols, rows), interpolation=cv2.INTER_LINEAR)
    conf = np.clip(conf, 0, 1).astype(np.float32)
    return conf if out is None else np.where(out, np.float32(0), conf)


# The checks judge a field on the observed object it keeps in the frame (:func:`_judged`); one
# that carries more than this share of it out leaves the rest to judge it on, and under half of
# what the pair showed is too little to trust it by (the interior's observed share has the same
# line, _MIN_OBSERVED; not tuned: it fired on no TRAINING result of the turned and phantom
# benches, session 47; benchmarks/README.md, "Pixels carried out of the frame leave the data term").
_MIN_IN_FRAME = 0.5


def _left_in_frame(obs, judged) -> list:
    """The reason (a list of at most one) for a field that keeps under ``_MIN_IN_FRAME`` of the
    observed object ``obs`` in the frame (``judged``: what it keeps)."""
    n = int(obs.sum())
    if n == 0 or judged.sum() >= _MIN_IN_FRAME * n:
        return []
    return [
        f"the field carries {100 * (1 - judged.sum() / n):.0f} % of the observed object out of the frame, "
        f"where the moving image is not observed: too little is left in it to judge the field "
        f"(under {100 * _MIN_IN_FRAME:.0f} %)"
    ]


def _carried_out(d):
    """Where the field ``d`` (px of its own grid) carries a pixel more than
    ``_bspline._OUTSIDE_MARGIN`` past the frame's outer pixel centres, the lattices' rule
    (``_bspline._beyond``); None when nowhere."""
    from radiokit.register._bspline import _beyond

    rows, cols = d.shape[1:]
    y = d[0] + np.arange(rows, dtype=d.dtype)[:, None]
    x = d[1] + np.arange(cols, dtype=d.dtype)
    return _beyond(y, rows, _beyond(x, cols))


def _judged(p, w, d):
    """``(w, out)``: the warped moving image ``w`` (field ``d``, both on the checks' grid) as the
    checks judge it, and ``out``, the pixels left out (:func:`_carried_out`; None: none). There
    ``w`` is the frame's border replicated, no observation of the moving image, and read as
    structure left misaligned it flagged right fields (the true field of a body shifted 12 px
    across the frame's edge: its residual "still moving" 0.53 px; tests/test_register.py). rc's
    and ssd's data term leave those pixels out (``_bspline._Level._outside``), and so do the
    checks: ``w`` takes the fixed image's value there (no residual, as in the data term, and none
    spread into the windows around them), and they are left out of the observed part they judge
    (:func:`_left_in_frame`: too little left is no verdict of ok)."""
    out = _carried_out(d)
    if out is not None:
        out = _explained(p, d, out)
    if out is None:
        return w, None
    return np.where(out, p.f, w).astype(w.dtype, copy=False), out


#: How near the frame's edge (full-resolution px) the motion of the rest of the object must carry
#: a pixel for the checks to leave it out where the field carries it out (:func:`_explained`).
_CARRIED_OUT_PX = 2.0


def _explained(p, d, out):
    """Of the pixels ``out`` that the field ``d`` (the checks' grid) carries out of the frame, those
    that the motion it gives the rest of the observed object also carries out, to within
    ``_CARRIED_OUT_PX`` of the edge: the least-squares affine fit of ``d`` over the observed pixels
    it keeps in the frame, extrapolated (None: none left). Why: a pixel left out is not judged, so
    a field wrong only where it carries pixels out would pass; a field that shoved the frame's
    right 20 % outward where the truth moves the body 6 px inward was trusted (review, session 47;
    tests/test_register.py). A shift, a scaling or a rotation across the edge, the fields that
    rightly carry a strip out, are affine: their strip stays left out."""
    from scipy import ndimage

    from radiokit.register._bspline import _OUTSIDE_MARGIN

    keep = p.obs & ~out
    # not the window next to the pixels carried out: a field wrong there ramps up to them (fitted
    # with them, a 12 px ramp carried its own band out)
    far = keep & (ndimage.distance_transform_edt(~out) > _WINDOW)
    ky, kx = np.nonzero(far if far.sum() >= 0.25 * keep.sum() else keep)
    if ky.size < 3:  # nothing to fit on: _left_in_frame's reason judges the field
        return out
    step = max(1, ky.size // 20000)  # a subsample: an affine fit needs few points
    ky, kx = ky[::step], kx[::step]
    a = np.column_stack([np.ones(ky.size), ky, kx])
    coef = np.linalg.lstsq(a, np.stack([d[0][ky, kx], d[1][ky, kx]], axis=1), rcond=None)[0]
    oy, ox = np.nonzero(out)
    b = np.column_stack([np.ones(oy.size), oy, ox]) @ coef
    y, x = oy + b[:, 0], ox + b[:, 1]
    rows, cols = d.shape[1:]
    m = _OUTSIDE_MARGIN - _CARRIED_OUT_PX / p.k
    beyond = (y < -m) | (y > rows - 1 + m) | (x < -m) | (x > cols - 1 + m)
    if not beyond.any():
        return None
    kept = np.zeros_like(out)
    kept[oy[beyond], ox[beyond]] = True
    return kept


def _residual_step(p, w, obs) -> float:
    """``Quality.residual_motion``: the median over ``obs`` of one Gauss-Newton step on the
    residual of the warped moving image ``w`` against the pair's fixed image (``p``, binned by
    ``p.k``), in full-resolution pixels; NaN when nothing is observed."""
    if not obs.any():
        return float("nan")
    return p.k * float(np.median(p.motion(w)[obs]))


def coarse_residual_motion(fixed, moving, mask):
    """``(k, shape, motion)``: the checks' binning of this pair, the binned shape, and
    ``motion(d)``, the ``Quality.residual_motion`` of a field ``d`` of that shape (in its pixels), as
    ``register``'s checks measure it. rc's ``abandon_px`` stops a run with it before its finest
    level, where the checks would see the same misalignment at several times the cost; the binned
    pair and its observed part are computed once (:func:`_pair_checks`), for every field measured."""
    p = _pair_checks(fixed, moving, mask)

    def motion(d):
        d = np.nan_to_num(d)
        w, out = _judged(p, np.nan_to_num(_warp(p.m, _field(d))), d)
        return _residual_step(p, w, p.obs if out is None else p.obs & ~out)

    return p.k, p.f.shape, motion


def _body_scale(d, obj, obs, inner) -> float:
    """How far the field ``d`` (binned px) departs from a body-scale motion: a quadratic in
    ``x, y`` per component, least squares over the observed rim (``obs`` outside ``inner``; the
    checks pass the part they judge, less what the field carries out of the frame); the
    RMS of ``|d - fit|`` over that rim and over the unobserved interior, the larger. NaN when
    the observed rim is too small to fit a quadratic to (under 100 pixels, or rank-deficient).
    The rim need not surround the interior (until session 49 NaN when it left a quarter of the
    directions around the centroid empty): a slab's straight edges observe only their normal
    component, so the map calls its corners observed and nothing between, yet those edges pin
    the body's affine motion, and ``Quality.affine_bound`` decides whether they do."""
    rim = obs & ~inner
    ry, rx = np.nonzero(rim)
    if ry.size < 100:
        return float("nan")
    oy, ox = np.nonzero(obj)
    cy, cx = oy.mean(), ox.mean()
    scale = max(np.ptp(oy), np.ptp(ox), 1) / 2.0  # for the fit's conditioning only

    def basis(y, x):  # a quadratic, in coordinates scaled for the fit's conditioning
        return monomials((y - cy) / scale, (x - cx) / scale, 2)

    coef, _, rank, _ = np.linalg.lstsq(basis(ry, rx), d[:, ry, rx].T.astype(np.float64), rcond=None)
    if rank < coef.shape[0]:  # a rim on one line or conic: no quadratic is fitted to it
        return float("nan")
    dev = [np.hypot(*(d[:, ry, rx] - (basis(ry, rx) @ coef).T))]
    fy, fx = np.nonzero(inner & ~obs)
    if fy.size:
        dev.append(np.hypot(*(d[:, fy, fx] - (basis(fy, fx) @ coef).T)))
    return float(max(np.sqrt(np.mean(np.square(v))) for v in dev))


def _affine_text(bound) -> str:
    """Why a result is flagged whose object's structure does not pin its affine motion
    (``Quality.affine_bound`` over ``OBSERVED_PX``)."""
    from radiokit.register._confidence import OBSERVED_PX

    return (
        "the object's structure does not determine its affine motion: a turn or a shear of it would show "
        f"nothing (the worst affine mode's bound {bound:.2g} px, > {OBSERVED_PX:g}; fixed image, whole object)"
    )


def _body_scale_text(v, preset, affine=float("nan")) -> str:
    """Why the silent interior is not trusted for a body-scale field (``Quality.body_scale``;
    ``affine``: ``Quality.affine_bound`` when a silent preset's field is body-scale, so that the
    bound is the one fault, said here once; NaN otherwise)."""
    from radiokit.register._confidence import OBSERVED_PX

    if affine > OBSERVED_PX:
        return (
            f"the field is body-scale ({v:.2f} px), but the object's edges do not determine a body-scale motion: "
            f"a turn or a shear of it would show nothing (the worst affine mode's bound {affine:.2g} px, > {OBSERVED_PX:g})"
        )
    if np.isnan(v):
        return "the field is not body-scale (too little of the object's rim is observed to fit a quadratic motion to)"
    if v > _BODY_SCALE_PX:
        return f"the field is not body-scale ({v:.2f} px from a quadratic motion fitted to the observed edges, > {_BODY_SCALE_PX:g})"
    return f"the field is body-scale ({v:.2f} px) but from a free lattice (preset {preset or 'default'}), not a silent preset"


# Quality.disagreement (register(..., regularisation_check=True)). Inside a silent interior the
# field is the regulariser's interpolation of what the edges pin, and the checks cannot tell a
# right fill from a wrong one (benchmarks/README.md, "Phantom-like pairs from an independent
# generator"). Two fields that each pass the checks yet differ there cannot both be right: at
# least one is a guess. (Agreement does not certify a fill: two wrong fills can agree, and on the
# held-out generator right ones differed by up to 1.2 px; so this only flags, it never trusts.)
# A disagreement with a second run that fails its own checks says nothing of this one, so only a
# trusted second run counts. 0.6 px chosen on TRAINING rows (the phantom seeds 6000-6029 and the
# family's training seeds at 560, every preset and method) with rc's full ``weak`` (``default``
# for a weak result) as the second run: the phantoms' failed results flagged 35/46 -> 40/46 for
# 55/66 -> 53/66 good trusted, the family's unchanged (262/262, 170/174); on the test rows the
# phantoms' 29/36 -> 33/36 (good 68/71 both), the family's 156/158 -> 158/158 and 102/106 ->
# 100/106 (benchmarks/README.md, "Two registrations' disagreement (session 29)").
_CROSS_PX = 0.6
# The second run (session 29, review s29-h8): ``weak`` area-averaged to at most 0.1 Mpx with a
# quarter of its iterations, ``fast`` for a weak result: a fifth to a quarter of the full runs'
# time (phantom training pairs median 0.31 s against 1.39 s, the family's at 560 0.83 s against
# 3.41 s). Chosen among ``weak-fast``, this and ``silent-fast`` on the TRAINING rows at the same
# 0.6 px (phantoms 41/46, 54/66 against the full runs' 40/46, 53/66; ``weak-fast`` 37/46,
# ``silent-fast`` 36/46; the family's unchanged for all), then read once on the test rows:
# phantoms 32/36, 68/71 (the full runs' 33/36, 68/71), the family's the same as the full runs'
# (benchmarks/README.md, "A cheaper second run for the disagreement").
_SECOND_RUN = {"preset": "weak", "bin_pixels": 100_000, "iterations": (60, 30, 20)}
_SECOND_RUN_FOR_WEAK = {"preset": "fast"}


def _regularisation_check(reg, f, m, mask) -> None:
    """Register ``f``, ``m`` again with rc (``_SECOND_RUN``: ``weak`` binned to 0.1 Mpx with a
    quarter of its iterations; ``fast`` when ``reg`` is a weak result) and fill
    ``reg.quality.disagreement``; flag a trusted ``reg`` whose field differs from the second one,
    itself trusted, by more than ``_CROSS_PX`` (median over the object's interior as the checks
    see it, full-resolution px). ``reg.options["regularisation_check"]`` records the second run's
    preset, options, verdict and time."""
    opts = _SECOND_RUN_FOR_WEAK if _base_preset(reg) == "weak" else _SECOND_RUN
    if not reg.quality.ok:  # it can only flag a trusted result: not worth a second registration
        reg.options["regularisation_check"] = {
            "preset": opts["preset"],
            "options": dict(opts),
            "ok": False,
            "seconds": 0.0,
            "run": False,
        }
        return
    _judge_disagreement(reg, _register(f, m, "rc", mask, False, dict(opts)), _pair_checks(f, m, mask))


# The along-rim slide (benchmarks/README.md, "The along-rim slide: a gated forward-backward test
# (session 52)"): where over _RIM_GATE of the observed interior is one-directional structure
# (Quality.rim_share: a rim, a plate's or a slab's edge, _confidence.one_directional), the map
# credits the rim's curvature with the tangential component, which a field free at the window's
# scale slides unseen; a trusted result there is registered backward (fixed onto moving, its own
# method and preset) and flagged when ``d + e o (id + d)`` exceeds OBSERVED_PX (median over the
# object as the checks see it). Where texture makes the windows 2-D nothing extra runs.
# "mostly": over half the observed interior, not tuned. Measured on TRAINING rows
# (bench_register_rim.py): the phantoms' trusted failures read 0.35-0.67 (6015's three 0.67, 6005
# 0.51, 6011's four 0.45, 6012's two 0.35), their good results at most 0.54; the family's textured
# pairs at most 0.48 (a 20 % gain), its 2240 weak-texture pairs 0.13-0.20. A line of 0.4 would
# also flag 6011's four but costs the family's gain pair (weak-fast = auto-fast, 0.37 px, read 1.22
# px inconsistent), so the rule (no training bench worse by more than one verdict) keeps
# the half.
_RIM_GATE = 0.5
_DERIVED_OPTIONS = ("alpha", "noise_sigma")  # set by the run from the pair's noise, not asked for


def _rim_check(reg, f, m, mask, options) -> None:
    """Fill ``reg.quality.rim_share`` and, for a trusted result over :data:`_RIM_GATE`,
    ``reg.quality.inconsistency`` from a backward registration; flag the result when that is
    over ``OBSERVED_PX``. ``reg.options["rim_check"]`` records whether it ran, the backward run's
    options, verdict and time."""
    from scipy import ndimage

    from radiokit.register._confidence import OBSERVED_PX

    p = _pair_checks(f, m, mask)
    q = reg.quality
    q.rim_share = p.rim_share
    if not (q.ok and q.rim_share > _RIM_GATE):
        reg.options["rim_check"] = {"run": False, "seconds": 0.0}
        return
    opts = {k: v for k, v in options.items() if k != "preset"}
    if reg.method in BSPLINE_METHODS:
        from radiokit.register._bspline import PRESETS

        made = {k: v for k, v in reg.options.items() if k in PRESETS["default"] and k not in _DERIVED_OPTIONS}
        opts = dict(made, **{k: v for k, v in opts.items() if k in _DERIVED_OPTIONS}, preset=_base_preset(reg))
    t = time.perf_counter()
    back = register(m, f, reg.method, mask, rim_check=False, **opts)
    seconds = time.perf_counter() - t
    d, e = reg.displacement, back.displacement
    rr, cc = np.mgrid[0 : d.shape[1], 0 : d.shape[2]].astype(np.float32)
    at = [rr + d[0], cc + d[1]]
    fb = np.stack([d[i] + ndimage.map_coordinates(e[i], at, order=1, mode="nearest") for i in range(2)]).astype(
        np.float32
    )
    if p.k > 1:
        fb = _bin(fb, p.k)
    obj = p.ob.object
    q.inconsistency = float(np.median(np.hypot(*fb)[obj])) if obj.any() else float("nan")
    reg.options["rim_check"] = {"run": True, "options": opts, "ok": back.quality.ok, "seconds": seconds}
    if q.inconsistency > OBSERVED_PX:
        q.ok = False
        q.reason = (
            f"{100 * q.rim_share:.0f} % of the observed interior is one-directional structure (a rim, an edge), "
            "whose motion along itself the map credits but no window pins, and registering the pair backward "
            f"({reg.method}{', preset ' + str(opts['preset']) if 'preset' in opts else ''}) does not undo this "
            f"field: {q.inconsistency:.2f} px "
            f"(median of d + e(x + d) over the object; > {OBSERVED_PX:g}): the field along the rim is the prior's guess"
        )


def _base_preset(reg) -> str:
    """The preset whose lattice and regularisation made ``reg``'s field: ``auto``'s choice up to its
    ``+`` (``weak+default-finest`` is ``weak``'s field polished at the finest level: checked against
    a ``weak`` run it would be compared with itself; review s29-h6), else the preset asked for."""
    chosen = reg.options.get("auto")
    if chosen is not None:
        return chosen.preset.split("+")[0]
    return reg.options.get("preset") or "default"


def _judge_disagreement(reg, second, p) -> None:
    """:func:`_regularisation_check`'s verdict on ``reg`` from the ``second`` registration (its preset in
    ``second.options``) and the pair's checks ``p`` (:class:`_PairChecks`)."""
    preset = second.options.get("preset")
    # the overrides of the preset the second run was given (``_SECOND_RUN``'s binning, iterations)
    extra = {k: v for k, v in second.options.items() if k in ("bin_pixels", "iterations")}
    inner = p.inner if p.inner.any() else p.ob.object
    diff = reg.displacement - second.displacement
    if p.k > 1:
        diff = _bin(diff, p.k)
    q = reg.quality
    q.disagreement = float(np.median(np.hypot(*diff)[inner])) if inner.any() else float("nan")
    reg.options["regularisation_check"] = {
        "preset": preset,
        "options": {"preset": preset, **extra},
        "ok": second.quality.ok,
        "seconds": second.quality.seconds,
        "run": True,
    }
    if q.ok and second.quality.ok and q.disagreement > _CROSS_PX:
        named = preset + "".join(f", {k} {v}" for k, v in extra.items())
        q.ok = False
        q.reason = (
            f"a second registration (rc, preset {named}), which passes its own checks, differs from this one "
            f"by {q.disagreement:.2f} px over the object's interior (median; > {_CROSS_PX:g}): the field there "
            "is the regularisers' guess, not the images'"
        )


def _erode(mask, radius):
    """``mask`` (bool) eroded by a disc of ``radius`` pixels, outside the frame counting as
    outside the mask."""
    import cv2

    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.erode(mask.astype(np.uint8), disc, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def _interior(obj):
    """``obj`` eroded by ``_INTERIOR`` windows: the part beyond the window's reach from the
    object's edge; empty for an object narrower than that."""
    return _erode(obj, int(round(_INTERIOR * _WINDOW)))


def _misaligned(p, w, d, obs):
    """``(share, kept, left)``: the share of ``obs`` where the residual of the warped moving image
    ``w`` (field ``d``) against the pair's fixed image (``p``: :class:`_PairChecks`, its images
    binned) exceeds the noise's expected share by more than _EXCESS of it, and by more than a
    quarter of the excess before registering (which keeps interpolation error on noise-free data
    from counting); and the mean excess after registering against before over the part of ``obs``
    whose excess before was over _EXCESS (``Quality.excess_kept``), and that mean excess after;
    NaN when that part is under 1 % of ``obs`` (nothing misaligned to keep) or nothing is
    observed."""
    from radiokit.register import _confidence as C

    if not obs.any():
        return float("nan"), float("nan"), float("nan")
    factor = 1.0 + C.interpolation_variance(d, _WINDOW)
    after = p.consistency(w, factor, support=p.mask) - 1.0
    before = p.before
    bad = (after > _EXCESS) & (after * factor > 0.25 * 2.0 * np.maximum(before, 0))
    # kept: over the windows that showed misaligned structure before (a static structure the
    # field moves, such as a collimator's edge at a mask's border, adds excess where there was
    # none: a good field at 0.29 px read 10x); the floor on ``left`` is _MAX_KEPT's rule
    showed = obs & (before > _EXCESS) & np.isfinite(after)
    kept = left = float("nan")
    # 1 % of the observed part, as documented: a share of the whole frame left a small body's
    # kept structure unjudged (a 24 px patch in a 320 px frame shifted beyond reach read NaN)
    if showed.sum() > 0.01 * obs.sum():
        left = float(np.mean(np.maximum(after[showed], 0)))
        kept = left / float(np.mean(before[showed]))
    return float(np.mean(bad[obs])), kept, left
