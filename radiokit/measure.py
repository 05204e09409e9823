"""Contrast measurements after the paper: rectangles inside the inclusion and in nearby background.

The paper measures "the difference of average pixel intensity of small rectangular regions inside
the inclusion and in the nearby background" and reports how much compression-induced contrast
(:func:`radiokit.enhance.compression_contrast`) improves it. This module holds the rectangle
(:class:`ROI`, half-open pixel bounds, convertible to and from millimetres), the measurements
(:func:`contrast`, :func:`cnr`, :func:`weber`, :func:`improvement_factor`, :func:`improvement_bound`,
:func:`change_ratio`,
:func:`summary`), line profiles (:func:`profile`) and automatic ROIs (:func:`find_rois`).

Every measurement takes the image first and the regions after; a region is an :class:`ROI` or a
boolean mask of the image's shape. Manual ROIs override the automatic ones simply by being
passed; ROIs given in millimetres are built with :meth:`ROI.from_mm`. Means are taken in float64
and returned as Python floats.
"""

from __future__ import annotations

import math
import operator
import warnings
from dataclasses import dataclass

import numpy as np

from radiokit.checks import image_hint, is_number, refuse_masked

# scipy.ndimage is imported in the functions that use it: radiokit.pipeline imports this module, and
# `radiokit process` refused on its command line or its output (no frame read) need not load scipy

__all__ = [
    "ROI",
    "contrast",
    "cnr",
    "weber",
    "improvement_factor",
    "improvement_bound",
    "change_ratio",
    "roi_mean_se",
    "improvement_factor_se",
    "change_ratio_se",
    "MIN_Z",
    "profile",
    "find_rois",
    "summary",
    "body_mask",
    "PAPER",
    "NoBackgroundFits",
]

#: The paper's numbers, what every table compares with: contrast improvement of about 1.4
#: (k = 1) and 2 (k = 2), keyed by k as :func:`summary` and ``Results.improvement_factor`` are
#: (results.json writes the keys as text, "1"), and the inclusion/background intensity-change
#: ratio of the authors' earlier study, 0.66-0.84.
PAPER = {"improvement_factor": {1.0: 1.4, 2.0: 2.0}, "change_ratio": [0.66, 0.84]}


# -- the rectangle -----------------------------------------------------------------------------
def _pair(value, name, *, positive=False) -> tuple[float, float]:
    """A scalar or a (row, col) pair as two finite floats."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.array([arr, arr])
    if arr.shape != (2,):
        raise ValueError(f"{name} must be a number or a (row, col) pair, got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and not np.all(arr > 0):
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return float(arr[0]), float(arr[1])


def _round_half_up(x: float) -> int:
    return int(math.floor(x + 0.5))


def _mm_to_px(mm: float, pixel_size_mm: float) -> float:
    """``mm / pixel_size_mm`` snapped to 1e-9 pixel: a bound typed on a half pixel stays one (0.35 /
    0.1 is 3.4999999999999996, which rounds half up to 3 where 0.45 / 0.1 gives 4.5 and 5)."""
    return round(mm / pixel_size_mm, 9)


@dataclass(frozen=True)
class ROI:
    """An axis-aligned rectangle of pixels: rows ``row0 <= r < row1``, cols ``col0 <= c < col1``.

    Bounds are half-open integers as in numpy slicing, so ``image[roi.slices]`` is the region.
    An ROI may be built anywhere (``shifted`` can move it off an image); every function that
    applies one to an image checks that it lies inside and says so when it does not.

    Parameters
    ----------
    row0, row1, col0, col1 : int
        Half-open bounds in pixels; ``row1 > row0`` and ``col1 > col0``.

    Raises
    ------
    ValueError
        If a bound is not an integer or the rectangle is empty.

    Examples
    --------
    >>> roi = ROI(2, 6, 10, 14)
    >>> roi.shape, roi.center
    ((4, 4), (3.5, 11.5))
    >>> ROI.from_center((3.5, 11.5), 4) == roi
    True
    >>> ROI.from_mm((0.35, 1.15), 0.4, pixel_size_mm=0.1) == roi
    True
    """

    row0: int
    row1: int
    col0: int
    col1: int

    def __post_init__(self):
        for name in ("row0", "row1", "col0", "col1"):
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, operator.index(value))
            except TypeError:
                raise ValueError(f"ROI {name} must be an integer pixel index, got {value!r}") from None
        if self.row1 <= self.row0 or self.col1 <= self.col0:
            raise ValueError(
                f"ROI is empty: rows [{self.row0}, {self.row1}) x cols [{self.col0}, {self.col1}) "
                "(need row1 > row0 and col1 > col0)"
            )

    # geometry
    @property
    def slices(self) -> tuple[slice, slice]:
        """``(slice(row0, row1), slice(col0, col1))``, for ``image[roi.slices]``."""
        return slice(self.row0, self.row1), slice(self.col0, self.col1)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the rectangle."""
        return self.row1 - self.row0, self.col1 - self.col0

    @property
    def center(self) -> tuple[float, float]:
        """``(row, col)`` of the centre, in pixel coordinates (pixel ``i`` is centred on ``i``)."""
        return (self.row0 + self.row1 - 1) / 2, (self.col0 + self.col1 - 1) / 2

    def contains(self, item) -> bool:
        """Whether a point ``(row, col)`` or another :class:`ROI` lies inside this one.

        A point belongs to pixel ``i`` when ``i - 0.5 <= x < i + 0.5``.
        """
        if isinstance(item, ROI):
            return (
                self.row0 <= item.row0 and item.row1 <= self.row1 and self.col0 <= item.col0 and item.col1 <= self.col1
            )
        r, c = _pair(item, "point")
        return self.row0 - 0.5 <= r < self.row1 - 0.5 and self.col0 - 0.5 <= c < self.col1 - 0.5

    def shifted(self, drow: int, dcol: int) -> ROI:
        """The same rectangle moved by ``(drow, dcol)`` pixels."""
        drow, dcol = operator.index(drow), operator.index(dcol)
        return ROI(self.row0 + drow, self.row1 + drow, self.col0 + dcol, self.col1 + dcol)

    def clip(self, shape) -> ROI:
        """The part of the rectangle inside an image of ``shape``; ValueError if nothing is."""
        rows, cols = _shape2(shape)
        r0, r1 = max(self.row0, 0), min(self.row1, rows)
        c0, c1 = max(self.col0, 0), min(self.col1, cols)
        if r1 <= r0 or c1 <= c0:
            raise ValueError(f"{self} lies entirely outside the {rows}x{cols} image")
        return ROI(r0, r1, c0, c1)

    def check(self, shape, name: str = "roi") -> ROI:
        """Return self if it lies inside an image of ``shape``, else raise ValueError naming ``name``."""
        rows, cols = _shape2(shape)
        if self.row0 < 0 or self.col0 < 0 or self.row1 > rows or self.col1 > cols:
            raise ValueError(f"{name} {self} lies (partly) outside the {rows}x{cols} image")
        return self

    def mask(self, shape) -> np.ndarray:
        """A boolean image of ``shape``, True inside the rectangle (which must lie inside)."""
        self.check(shape)
        out = np.zeros(_shape2(shape), bool)
        out[self.slices] = True
        return out

    # conversions
    def to_dict(self) -> dict:
        """``{"row0": ..., "row1": ..., "col0": ..., "col1": ...}`` (JSON-ready ints)."""
        return {"row0": self.row0, "row1": self.row1, "col0": self.col0, "col1": self.col1}

    @classmethod
    def from_dict(cls, d: dict) -> ROI:
        """Inverse of :meth:`to_dict`."""
        missing = [k for k in ("row0", "row1", "col0", "col1") if k not in d]
        if missing:
            raise ValueError(f"ROI dict is missing {', '.join(missing)}: got keys {sorted(d)}")
        return cls(d["row0"], d["row1"], d["col0"], d["col1"])

    @classmethod
    def from_center(cls, center_rc, size_rc) -> ROI:
        """The ``size_rc`` rectangle (pixels; a number for a square) centred on ``center_rc``.

        Bounds are rounded so that an integer centre with an odd size, or a half-integer centre
        with an even size, is exact; otherwise (a tie) the rectangle sits half a pixel further
        down or right.
        """
        cr, cc = _pair(center_rc, "center_rc")
        hr, wc = _pair(size_rc, "size_rc", positive=True)
        h, w = _round_half_up(hr), _round_half_up(wc)
        if h < 1 or w < 1:
            raise ValueError(f"ROI size {size_rc!r} rounds to an empty rectangle ({h}x{w} pixels)")
        r0 = _round_half_up(cr - (h - 1) / 2)
        c0 = _round_half_up(cc - (w - 1) / 2)
        return cls(r0, r0 + h, c0, c0 + w)

    @classmethod
    def from_mm(cls, center_mm, size_mm, pixel_size_mm, origin_rc=(0.0, 0.0)) -> ROI:
        """A rectangle given in millimetres.

        Parameters
        ----------
        center_mm : (float, float)
            Centre (row direction, col direction) in mm from ``origin_rc``; rows grow downwards.
        size_mm : float or (float, float)
            Height and width in mm.
        pixel_size_mm : float or (float, float)
            Pixel pitch (row, col) in mm.
        origin_rc : (float, float)
            Pixel coordinates of the mm origin (default: the centre of pixel (0, 0)). ``(-0.5,
            -0.5)`` is the frame's top-left corner, the origin of ``radiokit process --mm`` and
            ``Config(roi_units="mm")``. Those take the edges ``(row0, row1, col0, col1)`` in mm
            and round each to the nearest pixel edge (:meth:`from_mm_edges`); this rounds a size and a centre, so the two
            can differ by a pixel (a 2.34 mm side is 23 pixels here, 23 or 24 there by where it
            sits).

        Bounds are rounded half up, as :meth:`from_center` rounds: a width stays the same
        wherever the rectangle sits.
        """
        pr, pc = _pair(pixel_size_mm, "pixel_size_mm", positive=True)
        cr, cc = _pair(center_mm, "center_mm")
        sr, sc = _pair(size_mm, "size_mm", positive=True)
        orr, occ = _pair(origin_rc, "origin_rc")
        px = (_mm_to_px(cr, pr), _mm_to_px(cc, pc)), (_mm_to_px(sr, pr), _mm_to_px(sc, pc))
        return cls.from_center((orr + px[0][0], occ + px[0][1]), px[1])

    @classmethod
    def from_mm_edges(cls, edges_mm, pixel_size_mm) -> ROI:
        """The rectangle whose edges ``(row0, row1, col0, col1)`` lie these millimetres from the
        frame's top-left corner, as ``radiokit process --mm`` and ``Config(roi_units="mm")`` take
        it: each edge goes to the nearest pixel edge, a tie half up (after snapping to 1e-9 pixel,
        so that 0.35 mm at 0.1 mm is the tie 3.5, not 3.4999999999999996). ``pixel_size_mm``: a
        number, or the (row, col) pitch. A ValueError where the rectangle rounds to nothing.
        """
        pr, pc = _pair(pixel_size_mm, "pixel_size_mm", positive=True)
        r0, r1, c0, c1 = edges_mm
        return cls(*(_round_half_up(_mm_to_px(v, p)) for v, p in ((r0, pr), (r1, pr), (c0, pc), (c1, pc))))

    def to_mm(self, pixel_size_mm, origin_rc=(0.0, 0.0)) -> tuple[tuple[float, float], tuple[float, float]]:
        """``(center_mm, size_mm)`` such that ``ROI.from_mm(*roi.to_mm(p, o), p, o) == roi``."""
        pr, pc = _pair(pixel_size_mm, "pixel_size_mm", positive=True)
        orr, occ = _pair(origin_rc, "origin_rc")
        r, c = self.center
        return ((r - orr) * pr, (c - occ) * pc), (self.shape[0] * pr, self.shape[1] * pc)


def _shape2(shape) -> tuple[int, int]:
    shape = tuple(int(s) for s in shape)
    if len(shape) != 2:
        raise ValueError(f"expected a 2-D (rows, cols) shape, got {shape}")
    return shape


# -- validation --------------------------------------------------------------------------------
def _image(image, name="image", mask_keyword=None) -> np.ndarray:
    refuse_masked(image, name, mask_keyword)
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(
            f"{name} must be a 2-D (rows, cols) array, got shape {arr.shape}{image_hint(image, arr.shape)}"
        )
    if arr.size == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape})")
    if not (np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating)):
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    return arr


def _region(image: np.ndarray, region, name: str, image_name: str = "image") -> np.ndarray:
    """The float64 pixel values of ``region`` (ROI or boolean mask), checked non-empty and finite."""
    if isinstance(region, ROI):
        region.check(image.shape, name)
        values = image[region.slices]
    else:
        refuse_masked(region, name)
        m = np.asarray(region)
        if m.dtype != bool:
            # four numbers are how Config and --inclusion take a rectangle: show the ROI to write
            hint = f": write ROI{tuple(m.tolist())}" if m.shape == (4,) and m.dtype.kind in "iu" else ""
            raise ValueError(
                f"{name} must be an ROI or a boolean mask, got {type(region).__name__} "
                f"of dtype {getattr(m, 'dtype', None)}{hint}"
            )
        if m.shape != image.shape:
            raise ValueError(f"{name} mask has shape {m.shape}, {image_name} has {image.shape}")
        if not m.any():
            raise ValueError(f"{name} mask is empty (no True pixel)")
        values = image[m]
    values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{image_name} has non-finite values (NaN or inf) inside {name}")
    return values


def _rectangle(roi, name: str = "roi") -> ROI:
    """``roi`` if it is an :class:`ROI`; TypeError otherwise (a bool mask, as ``contrast`` takes,
    was an AttributeError here): the standard errors' noise model reads a rectangle's lags."""
    if not isinstance(roi, ROI):
        raise TypeError(
            f"{name} must be an ROI (a rectangle), got {type(roi).__name__}: the noise model reads its rows and "
            "columns; for a mask, its bounding box: ROI(row0, row1, col0, col1)"
        )
    return roi


def _ratio(num: float, den: float) -> float:
    """num / den as a Python float; +-inf for den == 0 (nan for 0 / 0), without warnings."""
    if den != 0:
        return float(num / den)
    return math.copysign(math.inf, num) if num != 0 else math.nan


# -- measurements ------------------------------------------------------------------------------
def contrast(image, inclusion, background) -> float:
    """The paper's contrast: mean over the inclusion ROI minus mean over the background ROI.

    Parameters
    ----------
    image : (rows, cols) array
        Any domain; more attenuation brighter (line integrals, or the paper's negative
        intensities) makes the contrast of an attenuating inclusion positive.
    inclusion, background : ROI or (rows, cols) bool array
        A rectangle inside the inclusion and one of nearby background.

    Returns
    -------
    float
        ``mean(image[inclusion]) - mean(image[background])``.

    Raises
    ------
    ValueError
        If a region is empty, lies outside the image or covers non-finite pixels.

    References
    ----------
    .. [1] The paper, "Results": "difference of average pixel intensity of small rectangular
       regions inside the inclusion and in the nearby background".

    Examples
    --------
    >>> img = np.zeros((6, 6)); img[1:3, 1:3] = 5.0; img[3:5, 3:5] = [[1, 2], [3, 4]]
    >>> contrast(img, ROI(1, 3, 1, 3), ROI(3, 5, 3, 5))
    2.5
    """
    img = _image(image)
    return float(_region(img, inclusion, "inclusion").mean() - _region(img, background, "background").mean())


def cnr(image, inclusion, background) -> float:
    """Contrast-to-noise ratio: :func:`contrast` over the background's standard deviation.

    The standard deviation is the population one (``ddof=0``) over the background region.
    A noiseless background gives ``+-inf`` (``nan`` when the contrast is 0 as well).

    Examples
    --------
    >>> img = np.zeros((6, 6)); img[1:3, 1:3] = 5.0; img[3:5, 3:5] = [[1, 2], [3, 4]]
    >>> round(cnr(img, ROI(1, 3, 1, 3), ROI(3, 5, 3, 5)), 6)  # 2.5 / sqrt(1.25)
    2.236068
    """
    img = _image(image)
    bg = _region(img, background, "background")
    return _ratio(_region(img, inclusion, "inclusion").mean() - bg.mean(), bg.std())


def weber(image, inclusion, background) -> float:
    """Weber contrast: :func:`contrast` over ``|mean(background)|``.

    Meaningful for images with a physical zero (line integrals; the paper's negative
    intensities, where ``|mean|`` is the background's transmitted intensity). A zero background
    mean gives ``+-inf`` (``nan`` for zero contrast).

    Examples
    --------
    >>> img = np.zeros((6, 6)); img[1:3, 1:3] = 5.0; img[3:5, 3:5] = [[1, 2], [3, 4]]
    >>> weber(img, ROI(1, 3, 1, 3), ROI(3, 5, 3, 5))  # 2.5 / 2.5
    1.0
    """
    img = _image(image)
    bg = _region(img, background, "background").mean()
    return _ratio(_region(img, inclusion, "inclusion").mean() - bg, abs(bg))


def improvement_factor(enhanced, reference, inclusion, background) -> float:
    """How much enhancement multiplied the contrast: ``contrast(enhanced) / contrast(reference)``.

    The paper reports about 1.4 for ``k = 1`` and 2 for ``k = 2``. For
    ``enhanced = reference + k (D - mean D)`` (:func:`radiokit.enhance.compression_contrast`) it
    equals ``1 + k (mean_incl D - mean_bg D) / contrast(reference)``: the mean of D drops out.

    Parameters
    ----------
    enhanced : (rows, cols) array
        The enhanced image. **It comes first, before the reference**: the opposite of
        :func:`improvement_factor_se`, which takes the pair the enhancement was made of
        (``reference, registered``). Swapped, the images give ``1 / IF``, and nothing can tell
        (both orders are two images of one shape): pass them by keyword, as in the example.
    reference : (rows, cols) array
        The reference (the most compressed step), in the same domain.
    inclusion, background : ROI or (rows, cols) bool array

    Raises
    ------
    ValueError
        If the shapes differ, or the reference contrast is zero (the ratio is undefined).

    Examples
    --------
    >>> ref = np.zeros((4, 4)); ref[:, :2] = 2.0
    >>> enh = ref * 1.5
    >>> improvement_factor(enh, ref, ROI(0, 4, 0, 2), ROI(0, 4, 2, 4))
    1.5

    With its standard error, every image named (the two functions take different images):

    >>> from radiokit.enhance import compression_contrast
    >>> rng = np.random.default_rng(0)
    >>> ref = 1 + 0.2 * ROI(8, 16, 8, 16).mask((24, 24)) + 0.01 * rng.standard_normal((24, 24))
    >>> reg = ref + 0.05 - 0.02 * ROI(8, 16, 8, 16).mask((24, 24))    # it darkened less on compression
    >>> enh = compression_contrast(ref, reg, k=1.0)
    >>> inc, bg = ROI(10, 14, 10, 14), ROI(10, 14, 2, 6)
    >>> f = improvement_factor(enhanced=enh, reference=ref, inclusion=inc, background=bg)
    >>> se = improvement_factor_se(reference=ref, registered=reg, k=1.0, inclusion=inc, background=bg)
    >>> abs(f - 1.1) < 3 * se < 0.05                                # 1 + k C_D / C_R = 1 + 0.02 / 0.2
    True
    """
    enh, ref = _image(enhanced, "enhanced"), _image(reference, "reference")
    if enh.shape != ref.shape:
        raise ValueError(f"enhanced has shape {enh.shape}, reference has {ref.shape}")
    c_ref = contrast(ref, inclusion, background)
    if c_ref == 0:
        raise ValueError(
            "the reference contrast is zero: the improvement factor is undefined "
            "(is the inclusion ROI on the inclusion?)"
        )
    return float(contrast(enh, inclusion, background) / c_ref)


def improvement_bound(k, mu_b_per_mm, delta_gap_mm, domain: str) -> float:
    r"""The largest improvement factor compression alone allows through rigid plates.

    Intensity domains (``"linear"``, ``I/I0``, and ``"negative"``, the paper's ``-I/I0``):
    ``1 + k (1 - exp(-mu_b delta_g))``; ``"log"``: ``1``. The two intensity domains share one
    bound because the improvement factor is a ratio of contrasts, blind to their common sign.

    Parameters
    ----------
    k : float
        Multiplying factor of the compression-induced contrast (>= 0).
    mu_b_per_mm : float
        Linear attenuation coefficient of the background, 1/mm (>= 0).
    delta_gap_mm : float
        How much the plate gap closes from the moving (less compressed) step to the reference
        (the most compressed one), mm (>= 0).
    domain : {"log", "linear", "negative"}
        ``"log"``: line integrals ``-ln(I/I0)``; ``"linear"``: intensities ``I/I0``;
        ``"negative"``: the paper's negative intensities ``-I/I0`` (see
        :class:`radiokit.enhance.Domain`).

    Returns
    -------
    float

    Raises
    ------
    ValueError
        If an argument is negative or not finite, or ``domain`` is unknown.

    Notes
    -----
    Assumptions: the beam runs through the (rigid, parallel) plates, normal to them; it is
    monochromatic primary radiation (Beer-Lambert at one energy, no scatter); both ROIs
    lie where the body touches both plates; the inclusion attenuates more than the background
    (``dmu = mu_i - mu_b > 0``); the registration maps each column onto the same material; the
    contrast is the paper's difference of ROI means and ``k >= 0``.

    *Every column in contact thins by the plate step.* A ray normal to the plates through a
    region in contact with both runs from plate to plate: its length is the gap ``g``. Between
    the moving step (gap ``g + dg``) and the reference (gap ``g``) it shortens by ``dg``, whatever
    the material does in between. *A denser inclusion's chord can only shrink*: the inclusion
    is compressed too, so its chord ``c`` along the beam satisfies ``c_ref <= c_mov`` (equality
    for a rigid one). The background column has line integral ``mu_b g``; a column through the
    inclusion ``mu_b g + dmu c``.

    For the paper's contrast (a difference of ROI means) and ``E = R + k (D - mean D)`` with
    ``D = R - M`` the registered difference, ``C_E = C_R + k (C_R - C_M)``, so

    .. math:: IF(k) = 1 + k\,(1 - C_M / C_R).

    *log domain*: ``C = dmu c``, so ``C_M / C_R = c_mov / c_ref >= 1`` and ``IF <= 1``.

    *intensity domains* (here ``-I/I0``, more attenuation brighter; ``I/I0`` flips both
    contrasts' sign and leaves their ratio):
    ``C = exp(-mu_b g) (1 - exp(-dmu c))``, so

    .. math:: \frac{C_M}{C_R} = e^{-\mu_b \Delta g}\,
              \frac{1 - e^{-\Delta\mu\, c_{mov}}}{1 - e^{-\Delta\mu\, c_{ref}}}
              \ge e^{-\mu_b \Delta g}

    pixel by pixel (the first factor is common to every column in contact), hence for the ROI
    means too, and ``IF(k) <= 1 + k (1 - exp(-mu_b dg))``, with equality for a rigid inclusion.
    Two consequences: ``IF(k) - 1`` is linear in ``k`` for any one pair (the paper's 1.4 and 2
    are not: 2 would need 1.5 at k = 1), and a stiffness-driven excess over the bound is
    impossible; only misregistration, noise, a beam that is not normal to the plates, or
    physics outside the assumptions can exceed it: a tube's spectrum (the polychromatic line
    integral is concave in the thickness, so a rigid inclusion behind a thinner column gains log
    contrast: log IF(1) 1.011 for seed-breast's 28 kV Mo tube) and scatter, which the plates do
    not thin. Seen from the side (beam along the plates) the column through the background
    lengthens as the body expands sideways and no such bound holds.

    Examples
    --------
    The seed-breast scene, 20 % -> 25 % of a 50 mm gap (dg = 2.5 mm), mu_b = 0.05 /mm:

    >>> round(improvement_bound(1, 0.05, 2.5, "negative"), 4), round(improvement_bound(2, 0.05, 2.5, "negative"), 4)
    (1.1175, 1.235)
    >>> improvement_bound(2, 0.05, 2.5, "log")
    1.0
    """
    if domain not in ("log", "linear", "negative"):
        raise ValueError(f"domain must be 'log', 'linear' or 'negative', got {domain!r}")
    for name, v in (("k", k), ("mu_b_per_mm", mu_b_per_mm), ("delta_gap_mm", delta_gap_mm)):
        if not is_number(v) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if domain == "log":
        return 1.0
    return float(1.0 + k * (1.0 - math.exp(-float(mu_b_per_mm) * float(delta_gap_mm))))


def change_ratio(before, after, inclusion, background) -> float:
    """How much the inclusion's intensity changes between two steps relative to the background's.

    ``[mean_incl(after) - mean_incl(before)] / [mean_bg(after) - mean_bg(before)]``.
    ``after`` is the more compressed (reference) image and ``before`` the less compressed one
    registered onto it, so both ROIs cover the same tissue. A stiff inclusion gives a ratio
    below 1; the paper's earlier study found 0.66-0.84 ("the intensity changes at the tumor are
    less than those at the background").

    Raises
    ------
    ValueError
        If the shapes differ or the background does not change (the ratio is undefined).

    Examples
    --------
    >>> before = np.zeros((2, 4)); after = before.copy()
    >>> after[:, :2] += 3.0; after[:, 2:] += 4.0
    >>> change_ratio(before, after, ROI(0, 2, 0, 2), ROI(0, 2, 2, 4))
    0.75
    """
    b, a = _image(before, "before"), _image(after, "after")
    if a.shape != b.shape:
        raise ValueError(f"before has shape {b.shape}, after has {a.shape}")
    d_in = _region(a, inclusion, "inclusion", "after").mean() - _region(b, inclusion, "inclusion", "before").mean()
    d_bg = _region(a, background, "background", "after").mean() - _region(b, background, "background", "before").mean()
    if d_bg == 0:
        raise ValueError(
            "the background intensity does not change between before and after: the change ratio is undefined"
        )
    return float(d_in / d_bg)


# -- uncertainty -------------------------------------------------------------------------------
#: A change ratio is measured only where the background's change stands this many standard
#: errors from zero: below, the ratio's denominator is noise (a flat background read "the
#: inclusion changed 126.59 times as much": review s41proc), and the delta method's standard
#: error, which assumes a denominator far from zero, means nothing either.
MIN_Z = 3.0

_MAD_SIGMA = 1.482602218505602  # sigma / MAD of a normal distribution
_CLIPPED_VAR = 0.9733369246625415  # variance of a unit normal kept within +-3
#: the longest lag, in pixels, at which the noise's correlation is looked for: a scintillator's
#: light spread (Gaussian of sigma up to ~2 px) correlates pixels to ~8 px
_MAX_LAG = 8
#: past the correlation's reach, a semivariance this much above the plateau is structure
_STILL_RISING = 1.25


#: lags (row, col) of one half-plane: next neighbours, where bilinear resampling correlates
#: pixels, and the ring two pixels out, where it no longer does
_NEAR = ((0, 1), (1, 0), (1, 1), (1, -1))
_RING2 = ((0, 2), (1, 2), (2, 2), (2, 1), (2, 0), (2, -1), (2, -2), (1, -2))


#: lags of more differences than this are read one at a time: the batch's padded passes and sorts
#: cost more than numpy's per-call overhead saves from about a 50 x 50 px window
#: (benchmarks/bench_roi_se.py)
_BATCH_BELOW = 2500


def _robust_vars(e: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust variances of the rows of ``e`` (one row of differences ``x(p + h) - x(p)`` per lag,
    padded) over the pairs ``use`` marks, and their centres: of the differences within three
    standard deviations of their centre (a few rounds from the median absolute deviation), so an
    edge crossing some of them does not count, and about their centre, so the object's slope does
    not either. First differences, not second: on a window crossing an inclusion's edge a second
    difference spans twice the pixels, and read a step's noise 20-70 % high (first: 0-20 %). All
    lags in one call: a window holds a few hundred differences a lag, and numpy's per-call cost was
    most of the time (benchmarks/bench_roi_se.py). ``nan`` for a row of fewer than 8 pairs."""
    if e.shape[1] > _BATCH_BELOW:
        return tuple(np.array(v) for v in zip(*(_robust_var(r, u) for r, u in zip(e, use))))
    n_use = use.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = _row_medians(e, use, n_use)
        scale = _MAD_SIGMA * _row_medians(np.abs(e - centre[:, None]), use, n_use)
        live = n_use >= 8
        for _ in range(5):
            kept = use & (np.abs(e - centre[:, None]) <= 3 * scale[:, None])
            n_kept = kept.sum(axis=1)
            live &= (n_kept >= 8) & (scale != 0)
            if not live.any():
                break
            mean = np.where(kept, e, 0.0).sum(axis=1) / n_kept
            d = np.where(kept, e - mean[:, None], 0.0)
            std = np.sqrt((d * d).sum(axis=1) / n_kept)
            centre = np.where(live, mean, centre)
            scale = np.where(live, std / math.sqrt(_CLIPPED_VAR), scale)
    return np.where(n_use >= 8, scale**2, np.nan), centre


def _robust_var(ev: np.ndarray, use: np.ndarray) -> tuple[float, float]:
    """:func:`_robust_vars` of one lag's differences ``ev`` (1-d) over the pairs ``use`` marks:
    the variance and the centre."""
    if use.sum() < 8:
        return math.nan, math.nan
    centre = np.median(ev[use])
    scale = _MAD_SIGMA * np.median(np.abs(ev[use] - centre))
    # then clipped at 3 scales, a few rounds: a median absolute deviation alone read 20-40 % high
    # where an inclusion's edge crossed a sixth of a window's differences
    for _ in range(5):
        kept = use & (np.abs(ev - centre) <= 3 * scale)
        if kept.sum() < 8 or scale == 0:
            break
        centre, scale = ev[kept].mean(), ev[kept].std() / math.sqrt(_CLIPPED_VAR)
    return float(scale**2), float(centre)


def _row_medians(e: np.ndarray, use: np.ndarray, n_use: np.ndarray) -> np.ndarray:
    """The median of each row of ``e`` over the entries ``use`` marks (as ``np.median`` reads it:
    the mean of the two middle values for an even count); the unused sort last as ``inf``."""
    if e.shape[1] == 0:
        return np.full(len(e), np.nan)
    s = np.sort(np.where(use, e, np.inf), axis=1)
    i = np.arange(len(e))
    lo, hi = np.maximum((n_use - 1) // 2, 0), np.maximum(n_use // 2, 0)
    return (s[i, lo] + s[i, hi]) / 2


def _one_pixel_se(x: np.ndarray, h: int, w: int) -> float:
    """The standard error of an ``h x w`` ROI's mean with the noise correlated between next
    neighbours only (frame means, bilinear resampling): its variance from the ring of lags two
    pixels out, the correlation from the next neighbours'. The differences ``x(p + h) - x(p)``,
    one lag a row, are trimmed by ``|h|`` on each side, so each lag reads the same pixels."""
    rows, cols = x.shape
    lags = _RING2 + _NEAR
    e = np.zeros((len(lags), rows, cols))
    use = np.zeros(e.shape, bool)
    for i, (dr, dc) in enumerate(lags):
        ar, ac = abs(dr), abs(dc)
        r, c = rows - 2 * ar, cols - 2 * ac
        if r > 0 and c > 0:
            e[i, :r, :c] = x[ar + dr : ar + dr + r, ac + dc : ac + dc + c] - x[ar : ar + r, ac : ac + c]
            use[i, :r, :c] = True
    var, _ = _robust_vars(e.reshape(len(lags), -1), use.reshape(len(lags), -1))
    ring = [float(v) for v in var[: len(_RING2)] if math.isfinite(v)]
    if not ring:
        return math.nan
    s2 = float(np.median(ring)) / 2.0
    n = h * w
    if s2 <= 0:
        return 0.0
    f = 1.0
    for (dr, dc), v in zip(_NEAR, var[len(_RING2) :]):
        if not math.isfinite(v):
            continue
        rho = min(1.0, max(-1.0, 1.0 - float(v) / (2.0 * s2)))
        f += 2 * rho * max(0.0, 1 - abs(dr) / h) * max(0.0, 1 - abs(dc) / w)
    # an estimate's noise must not claim more than n independent pixels' worth of quiet
    f = min(max(f, 0.25), float(n))
    return math.sqrt(s2 * f / n)


def _semivariances(x: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """``Var(x(p + k) - x(p)) / 2`` for ``k = 1..max_lag`` along ``x``'s rows (first axis) and
    along its columns, all lags of both axes in one :func:`_robust_vars` call.

    Pairs that straddle an edge are left out: an edge is where a next-neighbour difference stands
    far (5 standard deviations) from the noise's. Clipping alone does not do: at a lag of ``k``
    pixels a step spoils ``k`` pairs a row, most of a window's at the lags correlated noise needs.
    """
    axes = (x.T, x)
    crossed = _edges_crossed(axes)
    e = np.zeros((2, max_lag) + x.shape)
    use = np.zeros(e.shape, bool)
    for a, (y, cr) in enumerate(zip(axes, crossed)):
        rows, cols = y.shape
        if cols < 2:
            continue
        for k in range(1, min(max_lag, cols - 1) + 1):
            ek, uk = e[a, k - 1].reshape(rows, cols), use[a, k - 1].reshape(rows, cols)
            ek[:, : cols - k] = y[:, k:] - y[:, :-k]
            keep = (cr[:, k:] - cr[:, :-k]) == 0
            # too few pairs clear of edges: all of them, the clipping alone
            uk[:, : cols - k] = keep if keep.sum() >= max(8, keep.size // 4) else True
    var, _ = _robust_vars(e.reshape(2 * max_lag, -1), use.reshape(2 * max_lag, -1))
    return var[:max_lag] / 2, var[max_lag:] / 2


def _edges_crossed(axes) -> list[np.ndarray]:
    """For each of ``axes`` (the same window, transposed or not), the number of edges crossed
    from each row's start to each pixel: where a next-neighbour difference stands 5 standard
    deviations from the noise's."""
    diffs = [y[:, 1:] - y[:, :-1] if y.shape[1] >= 2 else np.zeros((y.shape[0], 0)) for y in axes]
    size = max(d.size for d in diffs)
    e, use = np.zeros((len(diffs), size)), np.zeros((len(diffs), size), bool)
    for i, d in enumerate(diffs):
        e[i, : d.size], use[i, : d.size] = d.ravel(), True
    var, centre = _robust_vars(e, use)
    out = []
    for d, s1, c in zip(diffs, var, centre):
        edge = np.abs(d - c) > 5 * math.sqrt(s1) if s1 > 0 else np.zeros(d.shape, bool)
        out.append(np.concatenate([np.zeros((d.shape[0], 1)), np.cumsum(edge, axis=1)], axis=1))
    return out


def roi_mean_se(image, roi: ROI, *, min_side: int = 16) -> float:
    """The standard error of ``image``'s mean over ``roi``, estimated from the image alone.

    The noise is read in a window around the ROI (the ROI grown to at least ``min_side`` pixels a
    side and two more each way, within the image). Noise correlated between next neighbours only
    (frame means corrected pixel by pixel; the registered step, resampled bilinearly): its variance
    ``s2`` from robust variances of differences two pixels apart, its correlation ``rho(h)`` from
    those of next neighbours (``Var = 2 s2 (1 - rho(h))``), and ``SE^2 = s2 f / n`` with the
    effective-size factor ``f = sum_h rho(h) (1 - |h_r|/H) (1 - |h_c|/W)`` over the ``H x W``
    ROI's lags (``n / f`` independent pixels). Read per pixel, a resampled image looks up to four
    times quieter than it is over a region; ``f`` puts that back.

    Noise correlated further (a scintillator's light spread, Gaussian of ~1-2 px: review s41rr
    found the next-neighbour model's SE 0.56 of the scatter at 1 px, 0.20 at 2 px, and an unchanged
    background "measurable" in 25 % of runs): the reach of the correlation is read from the
    semivariances at 1 and 2 px (a Gaussian correlation's ratio); where it passes 3 px the
    semivariances ``gamma(k)`` along rows and along columns, ``k = 1..8`` (the window grown to
    hold four reaches), give ``s2`` (their plateau at the reach) and a separable correlation
    ``rho(k_r, k_c) = (1 - gamma_r(k_r)/s2) (1 - gamma_c(k_c)/s2)`` (exact for a Gaussian spread and
    for bilinear weights), summed over the ROI's lags within the reach. Pairs straddling an edge (a
    next-neighbour difference 5 standard deviations out) are left out. Validated on flat
    backgrounds with Gaussian-blurred noise of 0-2 px: reported / observed 0.9-1.05.

    Assumptions, and where they fail: the noise is stationary over the window and its correlation
    is near-Gaussian in shape and dies within 8 px. A structure that curves within the window (a
    small inclusion's own dome, in a step but not in a difference of steps) keeps the semivariance
    rising past the reach; there, and wherever the long lags give less than the next-neighbour
    model, the next-neighbour model's estimate is returned, which such a structure makes larger,
    never smaller (review s41rr: 1.3-1.4 x beside a dome at low noise, up to 4 x for a change
    ratio). Correlated noise on such a structure is then under-read as before.

    Returns ``nan`` when the window is too small to hold the differences (an image of a few
    pixels).
    """
    img = _image(image)
    _rectangle(roi).check(img.shape)
    h, w = roi.shape
    margin = 2
    while True:
        gr = max(0, (min_side - h + 1) // 2) + margin
        gc = max(0, (min_side - w + 1) // 2) + margin
        win = ROI(roi.row0 - gr, roi.row1 + gr, roi.col0 - gc, roi.col1 + gc).clip(img.shape)
        x = np.asarray(img[win.slices], np.float64)
        if not np.all(np.isfinite(x)):
            x = np.where(np.isfinite(x), x, np.nanmedian(x[np.isfinite(x)]) if np.isfinite(x).any() else 0.0)
        if margin == 2:
            first = x
        g_r, g_c = _semivariances(x, _MAX_LAG)
        # the two axes' mean where both are read (np.nanmean's arithmetic), else the one read
        fr, fc = np.isfinite(g_r), np.isfinite(g_c)
        g = np.where(fr & fc, (g_r + g_c) / 2, np.where(fr, g_r, g_c))
        if not (np.isfinite(g[0]) and np.isfinite(g[1])):
            return math.nan
        lag, a = _correlation_reach(g[0], g[1])
        # the window must hold a few times the lags the correlation reaches; grown once
        if margin > 2 or min(x.shape) >= 4 * lag or min(x.shape) >= min(img.shape):
            break
        margin = lag + 2
    lag = min(lag, int(np.flatnonzero(np.isfinite(g))[-1]) + 1)
    s2 = float(np.nanmean(g[lag - 1 : lag + 1]))
    # past the correlation's reach the semivariance stays flat; still rising, it is an object's
    # structure (a dome's curvature), not noise, and the longer lags would read it as correlation
    # (and the plateau stands where the first two lags' Gaussian correlation puts it)
    far = g[min(2 * lag, _MAX_LAG) - 1]
    if lag <= 3 or far > _STILL_RISING * s2 or s2 * (1 - a) > _STILL_RISING * g[0]:
        return _one_pixel_se(first, h, w)
    n = h * w
    if not s2 > 0:
        return 0.0 if s2 == 0 else math.nan
    f = 1.0
    for ga, side in ((g_r, h), (g_c, w)):
        fa = 1.0
        for k in range(1, min(lag, side)):
            if math.isfinite(ga[k - 1]):
                rho = min(1.0, max(-1.0, 1.0 - ga[k - 1] / s2))
                fa += 2 * rho * (1 - k / side)
        f *= fa
    # an estimate's noise must not claim more than n independent pixels' worth of quiet
    f = min(max(f, 0.25), float(n))
    # correlation that reaches further only adds to a mean's noise: below the next-neighbour
    # model, the long lags saw an object's structure (a dome, whose pixels the edge test left
    # out), not the noise
    return max(math.sqrt(s2 * f / n), _one_pixel_se(first, h, w))


def _correlation_reach(g1: float, g2: float) -> tuple[int, float]:
    """The lag (px) at which the noise's correlation has died, from the semivariances at 1 and 2
    px: for a Gaussian correlation ``rho(k) = a^(k^2)`` their ratio is ``1 / ((1 + a)(1 + a^2))``,
    and ``rho < 0.02`` from ``k = 4 tau`` (``a = exp(-1 / (4 tau^2))``). Read from the first two
    lags only, where a structure's slope or curvature adds least: the longer lags keep rising over
    a dome, and would read it as correlation."""
    if not (g2 > 0) or g1 >= g2:
        return 2, 0.0
    target = g2 / max(g1, 1e-300)
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if (1 + mid) * (1 + mid * mid) < target else (lo, mid)
    a = (lo + hi) / 2
    if a <= 0:
        return 2, a
    if a >= 1:
        return _MAX_LAG, a
    tau = math.sqrt(-1 / (4 * math.log(a)))
    return int(min(_MAX_LAG, max(2, math.ceil(4 * tau) + 1))), a


def _se_inputs(first, second, inclusion, background) -> tuple[np.ndarray, np.ndarray]:
    """The two ``(name, image)`` of a standard error's pair as arrays, checked: ROIs that are
    rectangles, images of one shape."""
    (n1, x), (n2, y) = first, second
    x, y = _image(x, n1), _image(y, n2)
    for roi, name in ((inclusion, "inclusion"), (background, "background")):
        _rectangle(roi, name)
    if x.shape != y.shape:
        raise ValueError(f"{n1} has shape {x.shape}, {n2} has {y.shape}")
    return x, y


def _warn_if_enhanced(d: np.ndarray, ref: np.ndarray, reg: np.ndarray) -> None:
    """Warn when ``d = reference - registered`` is an enhanced image minus its reference: not zero,
    but zero-mean to float32's rounding of the images (half an ulp a pixel at most), where a
    compressed pair's difference is the thinning's, orders of magnitude above that."""
    rounding = float(np.finfo(np.float32).eps) * (np.mean(np.abs(ref)) + np.mean(np.abs(reg)))
    if abs(d.mean()) <= rounding < 1e-3 * d.std():
        warnings.warn(
            "improvement_factor_se: reference - registered has zero mean to rounding, as an enhanced image "
            "minus its reference does (k (D - mean D)): it takes the pair the enhancement was made of, "
            "improvement_factor_se(reference=..., registered=..., k=...), where improvement_factor takes "
            "(enhanced, reference); or the two images differ by nothing but noise or a shift (no change "
            "between the steps), which the mean alone cannot tell apart",
            UserWarning,
            stacklevel=3,
        )


def improvement_factor_se(reference, registered, k, inclusion: ROI, background: ROI) -> float:
    """The standard error of :func:`improvement_factor` for ``enhanced = reference + k (D - mean D)``.

    It takes the pair the enhanced image was made of, **reference first, then registered**, and
    ``k``; :func:`improvement_factor` takes ``(enhanced, reference)``: name the images by keyword
    (its example has both). An enhanced image given as either image is caught where it can be: an
    enhanced image minus its reference, ``k (D - mean D)``, has zero mean to rounding, which the
    difference of two compression steps does not; a UserWarning says so (the number returned is
    then not the standard error of anything measured).

    ``IF = 1 + k C_D / C_R`` with ``D = reference - registered`` (``C`` the contrast of an image),
    so by the delta method ``Var IF = k^2 / C_R^2 [Var C_D - 2 q Cov(C_D, C_R) + q^2 Var C_R]``,
    ``q = C_D / C_R``. Each variance is of a difference of two ROI means (:func:`roi_mean_se`; the
    ROIs are disjoint and the noise correlates over a pixel, so the two means are independent);
    ``Cov(mean D, mean R) = (Var mean R + Var mean D - Var mean registered) / 2`` over each ROI,
    which keeps the noise the two steps share (the flat field's, where the tissue did not move).
    ``nan`` where the reference contrast is zero.
    """
    ref, reg = _se_inputs(("reference", reference), ("registered", registered), inclusion, background)
    d = np.asarray(ref, np.float64) - np.asarray(reg, np.float64)
    _warn_if_enhanced(d, ref, reg)
    c_r = contrast(ref, inclusion, background)
    if c_r == 0:
        return math.nan
    c_d = contrast(d, inclusion, background)
    var_r = var_d = cov = 0.0
    for roi in (inclusion, background):
        vr, vd, vw = (roi_mean_se(img, roi) ** 2 for img in (ref, d, reg))
        var_r, var_d = var_r + vr, var_d + vd
        c = (vr + vd - vw) / 2
        cov += max(-math.sqrt(vr * vd), min(math.sqrt(vr * vd), c))  # a covariance matrix's bound
    q = c_d / c_r
    var = float(k) ** 2 / c_r**2 * (var_d - 2 * q * cov + q * q * var_r)
    return math.sqrt(max(var, 0.0))


def change_ratio_se(before, after, inclusion: ROI, background: ROI, *, min_z: float = MIN_Z):
    """:func:`change_ratio` with its standard error, or why it is not measurable.

    Returns ``(ratio, se, reason)``. With ``d_X`` the change of ROI ``X``'s mean
    (``after - before``) and its standard error from ``D = after - before`` (:func:`roi_mean_se`),
    ``se^2 = (se_i^2 + ratio^2 se_b^2) / d_b^2`` (delta method; the ROIs' noise is independent).
    Where ``|d_b| < min_z se_b`` (or the background's change is below float32's resolution of its
    level) the background did not measurably change: the ratio is ``nan`` and ``reason`` says so,
    with the background's change and its standard error; ``reason`` is ``""`` otherwise.
    """
    b, a = _se_inputs(("before", before), ("after", after), inclusion, background)
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    d_in = float(_region(d, inclusion, "inclusion", "after - before").mean())
    d_bg = float(_region(d, background, "background", "after - before").mean())
    se_in, se_bg = roi_mean_se(d, inclusion), roi_mean_se(d, background)
    level = max(abs(float(np.mean(a[background.slices], dtype=np.float64))), abs(float(np.mean(b[background.slices]))))
    if not abs(d_bg) > max(min_z * se_bg, 8 * float(np.finfo(np.float32).eps) * level):
        reason = (
            f"not measurable: the background changed {d_bg:.3g} \u00b1 {se_bg:.2g}, "
            f"not significantly different from 0 (|change| < {min_z:g} standard errors)"
        )
        return math.nan, math.nan, reason
    ratio = d_in / d_bg
    se = math.sqrt(se_in**2 + ratio**2 * se_bg**2) / abs(d_bg)
    return float(ratio), float(se), ""


def _k_key(k) -> float:
    """An enhancement factor as the number it is (``1``, ``1.0`` and ``"1"`` -> ``1.0``)."""
    try:
        return float(k)
    except (TypeError, ValueError):
        raise ValueError(f"enhanced_by_k: k = {k!r} is not a number") from None


def summary(reference, enhanced_by_k: dict, inclusion, background) -> dict:
    """Contrast, CNR and Weber contrast of the reference and of each enhanced image.

    Parameters
    ----------
    reference : (rows, cols) array
    enhanced_by_k : dict
        ``{k: enhanced image}``; keys become floats (``1``, ``1.0`` and ``"1"`` -> ``1.0``), as
        ``radiokit.results.Results.improvement_factor``'s and :data:`PAPER`'s.
    inclusion, background : ROI or bool mask

    Returns
    -------
    dict
        ``{"reference": {"contrast", "cnr", "weber"}, "enhanced": {1.0: {...}, ...},
        "improvement_factor": {1.0: ..., ...}, "inclusion": ..., "background": ...}`` where the
        regions are :meth:`ROI.to_dict` (or ``None`` for masks). For JSON, whose keys are text,
        write k as ``radiokit.results.k_label`` does (``"1"``), as results.json does.

    Examples
    --------
    >>> ref = np.zeros((4, 4)); ref[:, :2] = 2.0
    >>> s = summary(ref, {1: ref * 1.4, 2: ref * 2}, ROI(0, 4, 0, 2), ROI(0, 4, 2, 4))
    >>> s["improvement_factor"]
    {1.0: 1.4, 2.0: 2.0}
    >>> s["improvement_factor"][1] == s["improvement_factor"][1.0] == PAPER["improvement_factor"][1]
    True
    """
    ref = _image(reference, "reference")

    def three(img):
        return {
            "contrast": contrast(img, inclusion, background),
            "cnr": cnr(img, inclusion, background),
            "weber": weber(img, inclusion, background),
        }

    out = {
        "reference": three(ref),
        "enhanced": {},
        "improvement_factor": {},
        "inclusion": inclusion.to_dict() if isinstance(inclusion, ROI) else None,
        "background": background.to_dict() if isinstance(background, ROI) else None,
    }
    for k, enh in enhanced_by_k.items():
        key = _k_key(k)
        if key in out["enhanced"]:
            raise ValueError(f"enhanced_by_k has two entries for k = {key:g}")
        enh = _image(enh, f"enhanced_by_k[{key:g}]")
        if enh.shape != ref.shape:
            raise ValueError(f"enhanced_by_k[{key:g}] has shape {enh.shape}, reference has {ref.shape}")
        out["enhanced"][key] = three(enh)
        out["improvement_factor"][key] = improvement_factor(enh, ref, inclusion, background)
    return out


# -- profiles ----------------------------------------------------------------------------------
def profile(image, start_rc, end_rc, *, width: int = 1):
    """Intensity along a line, e.g. through the inclusion (the paper's Fig. 6).

    :func:`skimage.measure.profile_line` with the arguments checked and the distances returned:
    both end points included, ``ceil(length + 1)`` samples, bilinear interpolation, ``width``
    samples one pixel apart across the line averaged.

    Parameters
    ----------
    image : (rows, cols) array
    start_rc, end_rc : (float, float)
        End points in pixel coordinates; they must lie inside the image.
    width : int
        Pixels averaged perpendicular to the line (odd keeps the line centred).

    Returns
    -------
    distance_px : (n,) float64 array
        Distance of each sample from ``start_rc``, in pixels.
    values : (n,) float64 array

    Notes
    -----
    Samples beyond the image (only possible across a wide line near the edge) take the nearest
    edge pixel.

    Examples
    --------
    >>> img = np.tile(np.arange(5.0), (3, 1))
    >>> d, v = profile(img, (1, 0), (1, 4))
    >>> d.tolist(), v.tolist()
    ([0.0, 1.0, 2.0, 3.0, 4.0], [0.0, 1.0, 2.0, 3.0, 4.0])
    """
    from skimage.measure import profile_line

    img = _image(image)
    rows, cols = img.shape
    src, dst = np.array(_pair(start_rc, "start_rc")), np.array(_pair(end_rc, "end_rc"))
    for name, p in (("start_rc", src), ("end_rc", dst)):
        if not (0 <= p[0] <= rows - 1 and 0 <= p[1] <= cols - 1):
            raise ValueError(f"{name} {tuple(p)} lies outside the {rows}x{cols} image")
    try:
        width = operator.index(width)
    except TypeError:
        raise ValueError(f"width must be an integer number of pixels, got {width!r}") from None
    if width < 1:
        raise ValueError(f"width must be >= 1, got {width}")
    # float64 in: profile_line keeps a float32 image's precision, and measurements here are float64
    values = profile_line(np.asarray(img, np.float64), src, dst, linewidth=width, order=1, mode="nearest")
    return np.linspace(0.0, float(np.hypot(*(dst - src))), values.size), values


# -- automatic ROIs ----------------------------------------------------------------------------
def body_mask(image, *, fraction: float = 0.2, erode_px: int = 2) -> np.ndarray:
    """Pixels of the object, not air: attenuation above ``fraction`` of its maximum, eroded.

    The attenuation is measured from the air level: 0 for line integrals (images with no clearly
    negative values), -1 for the paper's negative normalised intensities (``-I/I0`` >= -1), and
    the image minimum otherwise (negative counts; this assumes some air is in the image). Holes
    are filled and the largest connected part kept.

    Examples
    --------
    >>> img = np.zeros((7, 7)); img[1:6, 1:6] = 1.0
    >>> int(body_mask(img, erode_px=1).sum())
    9
    """
    img = np.asarray(_image(image), np.float64)
    if not np.all(np.isfinite(img)):  # one NaN made every threshold False: an empty body, silently
        raise ValueError(f"image has {int(np.count_nonzero(~np.isfinite(img)))} non-finite value(s) (NaN or inf)")
    return _body(img, fraction, erode_px)


def _body(img: np.ndarray, fraction: float, erode_px: int) -> np.ndarray:
    from scipy import ndimage as ndi

    if not 0 < fraction < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction!r}")
    lo, hi = float(img.min()), float(img.max())
    scale = max(abs(lo), abs(hi), np.finfo(float).tiny)
    if lo >= -0.05 * scale:
        air = 0.0
    elif lo >= -1.05 and hi <= 0.05:
        air = -1.0
    else:
        air = lo
    att = img - air
    top = att.max()
    if top <= 0:
        return np.zeros(img.shape, bool)
    body = _largest_component(ndi.binary_fill_holes(att > fraction * top))
    if erode_px > 0 and not body.all():
        body = ndi.binary_erosion(body, iterations=int(erode_px), border_value=1)
    return body


def _largest_component(mask: np.ndarray) -> np.ndarray:
    from scipy import ndimage as ndi

    labels, n = ndi.label(mask)
    if n <= 1:
        return mask
    return labels == (np.argmax(np.bincount(labels.ravel())[1:]) + 1)


def _bbox(mask: np.ndarray) -> ROI:
    """The bounding box of a non-empty boolean mask."""
    from scipy import ndimage as ndi

    rows, cols = ndi.find_objects(mask.astype(np.uint8))[0]
    return ROI(rows.start, rows.stop, cols.start, cols.stop)


def _inscribed_square(region: np.ndarray, shrink: float) -> ROI:
    """The largest square inside ``region`` (chessboard distance), shrunk about its centre."""
    from scipy import ndimage as ndi

    cdt = ndi.distance_transform_cdt(np.pad(region, 1), metric="chessboard")[1:-1, 1:-1]
    d = int(cdt.max())  # the (2d-1) x (2d-1) square centred on a pixel with cdt == d fits
    cand = np.argwhere(cdt == d)
    centroid = np.argwhere(region).mean(axis=0)
    r, c = cand[np.argmin(((cand - centroid) ** 2).sum(axis=1))]
    half = max(0, _round_half_up(shrink * (d - 0.5) - 0.5))  # side 2 half + 1 ~ shrink (2d - 1)
    return ROI(int(r) - half, int(r) + half + 1, int(c) - half, int(c) + half + 1)


_MIN_T = 8.0
#: A blob fit's surroundings (the ring its quadratic is fitted to) start this many radii out; the
#: blob's half-maximum region is kept inside them (:func:`_half_maximum_window`).
_RING_INNER = 1.5
#: The scales, in a neighbour's radii, :meth:`_Neighbours._extent` fits at, up to the last.
_EXTENT_SCALES = (1, 2, 4)
#: A neighbour's extent grown about its centre by this (:meth:`_Neighbours._extent_overlaps`).
_EXTENT_GROWTH = 1.2
#: How far, in its radii, a neighbour's grown extent can reach: the widest region it can have
#: (up to the ring at its largest scale), grown.
_EXTENT_REACH = _EXTENT_GROWTH * _RING_INNER * max(_EXTENT_SCALES)  # 7.2


def _blob_fit(img: np.ndarray, body: np.ndarray, center, radius: float):
    """Fit a quadratic surface to the annulus 1.5-3 radii around ``center`` (inside the body);
    return (mean residual within half a radius, the residual window, its origin, distances).

    The quadratic takes out the body's own shape (a compressed breast is a dome), so a blob's
    score is its height above the surrounding tissue, not the curvature of the tissue.
    """
    rows, cols = img.shape
    pr, pc = center
    reach = int(np.ceil(3 * radius)) + 1
    r0, r1 = max(0, int(round(pr)) - reach), min(rows, int(round(pr)) + reach + 1)
    c0, c1 = max(0, int(round(pc)) - reach), min(cols, int(round(pc)) + reach + 1)
    # open grids and the quadratic evaluated term by term: a window reaches 3 radii (up to 1443 px
    # square at 2240), and full coordinate grids and an (N, 6) basis cost ~100 MB and 1.3 s a candidate
    v = ((np.arange(r0, r1) - pr) / radius)[:, None]
    u = ((np.arange(c0, c1) - pc) / radius)[None, :]
    dist = np.hypot(v, u)
    ring = (dist >= _RING_INNER) & (dist <= 3.0) & body[r0:r1, c0:c1]
    idx = np.flatnonzero(ring)
    if idx.size < 24:
        return -np.inf, None
    idx = idx[:: max(1, idx.size // 20000)]
    vi, ui = np.unravel_index(idx, ring.shape)
    vs, us = v[vi, 0], u[0, ui]
    basis = np.stack([np.ones_like(vs), vs, us, vs * vs, vs * us, us * us], axis=-1)
    win = img[r0:r1, c0:c1]
    coef, *_ = np.linalg.lstsq(basis, win.flat[idx], rcond=None)
    resid = win - (coef[0] + coef[1] * v + coef[2] * u + coef[3] * v * v + coef[4] * v * u + coef[5] * u * u)
    core = dist <= max(0.5, 1.0 / radius)
    # at least float32's step at the window's level: on a constant image the fit's rounding
    # (1e-16) stood "8 standard errors" above a rounding-sized scatter
    noise = max(resid.flat[idx].std(), np.finfo(np.float32).eps * np.abs(win.flat[idx]).max())
    score = resid[core].mean()
    # a real inclusion stands many standard errors above its surroundings; noise spikes picked
    # as the largest of ~1e6 candidates stand ~5
    if not score > _MIN_T * max(noise / np.sqrt(core.sum()), _clutter(resid, ring, int(core.sum()))):
        return -np.inf, None
    return float(score), (resid, (r0, c0), dist)


def _clutter(resid: np.ndarray, ring: np.ndarray, n_core: int) -> float:
    """The scatter of a core-sized mean of the residual over the ring: what a blob of the core's
    size in the surroundings reads as.

    Why: for white noise it is ``noise / sqrt(n_core)``, the standard error above; a gel's smooth
    thickness or density texture is correlated over the core, so there the standard error is far
    too small and the texture's strongest bump "stood 8 standard errors" above it (a
    near-uniform phantom with 1 % thickness ripple under noise got an invented inclusion). Means
    over squares of the core's area, of ring pixels only (normalised by the ring's share)."""
    from scipy import ndimage as ndi

    side = max(1, int(round(np.sqrt(n_core))))
    w = ndi.uniform_filter(ring.astype(np.float64), side, mode="constant")
    m = ndi.uniform_filter(np.where(ring, resid, 0.0), side, mode="constant")
    full = ring & (w >= 0.999)  # windows wholly in the ring: their mean is of ring pixels only
    if full.sum() < 24:
        return 0.0
    return float((m[full] / w[full]).std())


def _detect_inclusion(img: np.ndarray, body: np.ndarray, pixel_size_mm) -> np.ndarray:
    """The inclusion's mask of :func:`_detect_blobs` (``benchmarks/bench_detect.py`` times it)."""
    return _detect_blobs(img, body, pixel_size_mm)[0]


def _detect_blobs(img: np.ndarray, body: np.ndarray, pixel_size_mm) -> tuple[np.ndarray, _Neighbours]:
    """The strongest compact blob inside the body, brighter or darker than its surroundings, as a
    boolean mask (its half-maximum extent), and the other blobs that stand out as it must
    (:class:`_Neighbours`): what a background ROI must keep clear of.

    Candidates: local maxima of the scale-normalised Laplacian of Gaussian over radii of
    1.5-12 mm (or 3 px to a sixth of the image when the pixel size is unknown), whole with their
    surroundings inside the body. Each is scored by its height above a quadratic fitted to its
    surroundings (1.5-3 radii), which ignores the smooth shape of the body; the best one's
    extent is the connected region above half its height. Dark blobs are searched the same way
    on the negated image and taken when no bright one stands out: an inclusion less dense than the
    gel (a cyst, a foam) is as much an inclusion, and a detector of bright blobs alone picked the
    gel's texture instead of it; its contrast is then negative. Negative images (the paper's
    ``-I/I0`` or ``-counts``) are searched as ``-ln(-image)``, a line integral up to a constant,
    where the body's shape is smooth.

    The inclusion is the best of the three strongest candidates a scale and sign. The others are
    the candidates of either sign (every peak of every scale: with three a scale, a fourth blob of a
    neighbour's scale was never seen; with sixteen, a seventeenth) that pass the same test, less
    the chosen blob seen again at another scale (its centre in the chosen one's extent, or the
    chosen one's centre within its radius: at coarse scales a blob merges with its neighbours),
    each structure once, at the scale of its strongest response (the scale-normalised LoG peaks
    at about a disc's radius). A second inclusion, a cyst or an air bubble beside the inclusion
    read as background: a sphere of 0.2 under the background ROI took 28 % off the contrast,
    silently. A neighbour is kept clear by 1.2 of its radii, or 1.2 times its half-maximum extent
    (:meth:`_Neighbours._extent`: a neighbour larger than the largest scale, or elongated).

    Not :func:`skimage.feature.blob_log`: it filters every scale at full resolution, with no
    per-scale mask of the body's edge, and on a once-averaged image it is slower and moves the
    demo's ROI (``benchmarks/bench_detect.py``; numbers in ``benchmarks/README.md``).
    """
    from scipy import ndimage as ndi
    from skimage.measure import block_reduce

    if img.max() < 0:  # negative intensities (-I/I0, -counts): detect on line integrals + const
        img = -np.log(-img)
    rows, cols = img.shape
    small = min(rows, cols)
    if pixel_size_mm is not None:
        p = float(np.mean(pixel_size_mm))
        r_lo, r_hi = 1.5 / p, 12.0 / p
    else:
        r_lo, r_hi = 3.0, small / 6
    r_hi = min(r_hi, small / 6)
    r_lo = min(r_lo, r_hi)
    if r_hi < 1.5:
        raise ValueError(
            f"image {rows}x{cols} is too small to detect an inclusion in; pass inclusion_mask or ROIs (radiokit process --inclusion R0 R1 C0 C1)"
        )
    radii = np.geomspace(r_lo, r_hi, max(2, int(np.ceil(np.log2(r_hi / r_lo) * 3)) + 1))
    depths = {}  # distance to the body's edge (or the image's) on the block-reduced grid, in px

    def depth(f, h, w):
        if f not in depths:
            b = block_reduce(body[:h, :w], f, np.all) if f > 1 else body
            depths[f] = ndi.distance_transform_edt(np.pad(b, 1))[1:-1, 1:-1] * f
        return depths[f]

    # the best bright blob and the best dark one; a dark one is taken only when no bright one
    # stands out: the paper's inclusion is denser than the gel, and a darker feature of a real
    # phantom (an air bubble) may stand out more than it
    best = {1: (-np.inf, None, None, None), -1: (-np.inf, None, None, None)}
    found = []  # every candidate: (response, centre, radius, sign, whether it stood out; None: not tested)
    signed = {1: img, -1: -img}
    for radius in radii:
        sigma = radius / np.sqrt(2)
        f = max(1, int(sigma // 3))  # work on a block-averaged image: sigma >= 3 px there
        h, w = rows // f * f, cols // f * f
        im = block_reduce(img[:h, :w], f, np.mean) if f > 1 else img
        dp = depth(f, h, w)
        resp = -((sigma / f) ** 2) * ndi.gaussian_laplace(im, sigma / f, mode="nearest")
        resp[dp <= 3 * radius] = 0  # the blob and the ring fitted around it inside the body
        for sign, image in signed.items():
            # the strongest three are scored for the inclusion; the rest are neighbours only, fitted
            # when a background ROI comes near one (three alone lost the weakest of four blobs)
            for k, (rr, cc) in enumerate(_log_peaks(sign * resp, max(1, int(radius / f)))):
                centre = (rr * f + (f - 1) / 2, cc * f + (f - 1) / 2)
                if k >= 3:
                    found.append((float(sign * resp[rr, cc]), centre, radius, sign, None))
                    continue
                score, fit = _blob_fit(image, body, centre, radius)
                found.append((float(sign * resp[rr, cc]), centre, radius, sign, fit is not None))
                if score > best[sign][0]:
                    best[sign] = (score, fit, radius, centre)
    score, fit, radius, centre = best[1] if best[1][1] is not None else best[-1]
    if fit is None:
        raise ValueError(
            "no inclusion found: no compact blob inside the body stands out from its surroundings "
            "(brighter or darker, beyond their noise and texture; none is searched within three of its radii "
            "of the body's or the frame's edge); "
            "pass inclusion_mask or the ROIs yourself (on the command line: radiokit process --inclusion R0 R1 C0 C1)"
        )
    out = _half_maximum(fit, radius, img.shape)
    return out, _Neighbours(signed, body, found, out, centre, radius)


def _log_peaks(resp: np.ndarray, min_distance: int) -> np.ndarray:
    """Every local maximum of a scale's LoG response above zero, strongest first.

    Why every one: they are the neighbours a background ROI keeps clear of, and any count cap
    over the whole body can be filled elsewhere (the 16 strongest of a phantom with 120 air
    bubbles lay away from the inclusion, and the background ROI sat on the bubbles beside it).
    Only the few a ROI comes near are ever fitted (:meth:`_Neighbours.near`)."""
    from skimage.feature import peak_local_max

    return peak_local_max(resp, min_distance=min_distance, threshold_abs=0.0, exclude_border=False)


def _half_maximum(fit, radius: float, shape) -> np.ndarray:
    """A blob's extent from its :func:`_blob_fit`: the connected region above half its height."""
    region, (r0, c0) = _half_maximum_window(fit, radius)
    out = np.zeros(shape, bool)
    out[r0 : r0 + region.shape[0], c0 : c0 + region.shape[1]] = region
    return out


def _half_maximum_window(fit, radius: float, keep=None):
    """:func:`_half_maximum` over the fit's window only, as (region, its origin); pixels outside
    ``keep`` (the window's share of a mask) are never in it."""
    from scipy import ndimage as ndi

    resid, origin, dist = fit
    resid = ndi.gaussian_filter(resid, max(1.0, radius / 8), mode="nearest")
    core = dist <= max(0.5, 1.0 / radius)
    peak_idx = int(np.argmax(np.where(core, resid, -np.inf)))
    above = (resid >= resid.flat[peak_idx] / 2) & (dist <= _RING_INNER)
    if keep is not None:
        above &= keep
    if not above.flat[peak_idx]:
        return np.zeros_like(above), origin
    labels, _ = ndi.label(above)
    return labels == labels.flat[peak_idx], origin


class _Neighbours:
    """The blobs ``found`` beside the ``chosen`` one that a background ROI must keep clear of: the
    candidates that stand out and are not the chosen blob, each structure once (its strongest
    scale).

    A candidate whose surroundings held the chosen blob failed the test for it (a sphere of 0.2 in
    L 38 px beside an inclusion of 0.3: the inclusion in its ring is clutter), so it is tested
    again with the chosen blob (1.5 of its radii, as its own fit keeps out of its ring) out of its
    surroundings, when its core is clear of the chosen one's extent. Only when a background ROI
    would touch it: each such fit is a window of up to 3 radii, and fitting all of them cost the
    demo's detection 40 % more."""

    def __init__(self, signed: dict, body: np.ndarray, found: list, chosen: np.ndarray, centre, radius: float):
        self._signed, self._body, self._centre, self._reach = signed, body, centre, _RING_INNER * radius
        self._clear = None
        self._cands = []  # ((row, col), radius, sign), the strongest response first
        self._stands: dict[int, bool] = {}  # by index: whether it stands out (None: not yet tested)
        self._kept: dict[int, bool] = {}
        self._extents: dict[int, list] = {}  # by index: its half-maximum regions (_extent)
        for _, (pr, pc), r_c, sign, stood_out in sorted(found, key=lambda t: -t[0]):
            d = np.hypot(pr - centre[0], pc - centre[1])
            if chosen[int(round(pr)), int(round(pc))] or d <= r_c:  # the chosen blob at another scale
                continue
            if stood_out is False and d >= self._reach + 3 * r_c:
                continue  # its ring was clear of the chosen blob: it failed on its own
            if not stood_out and _touches(chosen, (pr, pc), 0.5 * r_c):
                continue  # its core is on the chosen blob
            if stood_out:
                self._stands[len(self._cands)] = True
            self._cands.append(((pr, pc), r_c, sign))
        # (row, col, radius) of each candidate: near() and _structure() look through thousands of
        # peaks (every one of every scale) for the few within reach
        self._at = np.array([(pr, pc, r_c) for (pr, pc), r_c, _ in self._cands], float).reshape(-1, 3)

    def _clear_body(self) -> np.ndarray:
        """The body less the chosen blob (1.5 of its radii): a neighbour's surroundings without it."""
        if self._clear is None:
            rows, cols = self._body.shape
            (cr, cc), reach = self._centre, self._reach
            lo_r, hi_r = max(0, int(cr - reach)), min(rows, int(np.ceil(cr + reach)) + 1)
            lo_c, hi_c = max(0, int(cc - reach)), min(cols, int(np.ceil(cc + reach)) + 1)
            yy, xx = np.ogrid[lo_r:hi_r, lo_c:hi_c]
            self._clear = self._body.copy()
            self._clear[lo_r:hi_r, lo_c:hi_c] &= np.hypot(yy - cr, xx - cc) > reach
        return self._clear

    def _stands_out(self, i: int) -> bool:
        if i not in self._stands:
            centre, r_c, sign = self._cands[i]
            self._stands[i] = _blob_fit(self._signed[sign], self._clear_body(), centre, r_c)[1] is not None
        return self._stands[i]

    def _extent(self, i: int) -> list:
        """Candidate ``i``'s half-maximum regions, each (region, origin): its fit's, and while the
        region reaches the fit's limit (1.5 radii), a fit at twice the radius's, up to four times
        its scale. The scales end at 12 mm and follow a blob's narrow side: a sphere of 20 mm or
        an ellipsoid 30 mm long reaches beyond its scale's disc. All are kept: a wider fit's
        surroundings may take in the body's edge, and its region then falls short of the last."""
        if i not in self._extents:
            centre, r_c, sign = self._cands[i]
            self._extents[i] = []
            for radius in (scale * r_c for scale in _EXTENT_SCALES):
                fit = _blob_fit(self._signed[sign], self._clear_body(), centre, radius)[1]
                if fit is None:
                    break
                (r0, c0), shape = fit[1], fit[0].shape
                keep = self._clear_body()[r0 : r0 + shape[0], c0 : c0 + shape[1]]
                self._extents[i].append(_half_maximum_window(fit, radius, keep))
                if not (self._extents[i][-1][0] & (fit[2] > 1.4)).any():
                    break
        return self._extents[i]

    def _extent_overlaps(self, i: int, roi: ROI) -> bool:
        """Whether ``roi`` overlaps candidate ``i``'s extent grown 1.2 times about its centre (a
        sphere's half maximum lies at sqrt(3)/2 of its radius, an ellipsoid's likewise on each axis)."""
        (pr, pc), _, _ = self._cands[i]
        for region, (r0, c0) in self._extent(i):
            rows = np.rint(pr + (np.arange(roi.row0, roi.row1) - pr) / _EXTENT_GROWTH).astype(int) - r0
            cols = np.rint(pc + (np.arange(roi.col0, roi.col1) - pc) / _EXTENT_GROWTH).astype(int) - c0
            rows = rows[(rows >= 0) & (rows < region.shape[0])]
            cols = cols[(cols >= 0) & (cols < region.shape[1])]
            if region[np.ix_(rows, cols)].any():
                return True
        return False

    def _structure(self, i: int) -> bool:
        """Whether candidate ``i`` stands out and is no structure found at a stronger scale."""
        if i not in self._kept:
            (pr, pc), _, _ = self._cands[i]
            r, c, r_j = self._at[:i].T
            inside = np.flatnonzero(np.hypot(pr - r, pc - c) <= r_j)
            self._kept[i] = self._stands_out(i) and not any(self._structure(int(j)) for j in inside)
        return self._kept[i]

    def near(self, roi: ROI) -> list:
        """The centres of the structures whose disc of 1.2 radii ``roi`` overlaps (a sphere's edge,
        where the LoG's radius ends, still adds to the line integral), or, for one known to stand
        out, its extent (:meth:`_extent_overlaps`; at most :func:`_reach_px` of its centre)."""
        out = []
        rows, cols, radii = self._at.T
        dist = np.hypot(np.clip(rows, roi.row0, roi.row1 - 1) - rows, np.clip(cols, roi.col0, roi.col1 - 1) - cols)
        for i in np.flatnonzero(dist < _reach_px(radii)):  # the strongest first, as _cands
            i, d, ((r, c), r_c, _) = int(i), dist[i], self._cands[i]
            if d < 1.2 * r_c and self._structure(i):
                out.append((r, c))
            elif self._stands.get(i) and self._structure(i) and self._extent_overlaps(i, roi):
                out.append((r, c))
        return out


def _reach_px(radius):
    """How far (px) from a neighbour of ``radius`` a ROI's nearest pixel can lie and overlap its
    grown extent: :data:`_EXTENT_REACH` radii and one pixel more, as :meth:`_Neighbours._extent_overlaps`
    takes each ROI pixel to the region's nearest, up to half a pixel a side (0.85 px once grown):
    a ROI 0.4-0.7 px beyond 7.2 radii overlapped an extent that near() passed by (review s44)."""
    return _EXTENT_REACH * radius + 1.0


def _length_px(value, name, pixel_size_mm):
    """A length given in mm (when pixel_size_mm is known) or pixels, as pixels (row, col)."""
    if value is None:
        return None
    vr, vc = _pair(value, name, positive=True)
    if pixel_size_mm is not None:
        vr, vc = vr / pixel_size_mm[0], vc / pixel_size_mm[1]
    return vr, vc


def find_rois(
    image,
    *,
    inclusion_mask=None,
    pixel_size_mm=None,
    inclusion_size=None,
    gap=None,
    background_size=None,
    body_mask=None,
) -> tuple[ROI, ROI]:
    """Automatic inclusion and background rectangles, after the paper's Figs. 7-8.

    Parameters
    ----------
    image : (rows, cols) array
        More attenuation brighter: line integrals or the paper's negative intensities.
    inclusion_mask : (rows, cols) bool array, optional
        Where the inclusion is (e.g. a simulation's truth). Without it the inclusion is
        detected: the strongest compact blob inside the body brighter than its surroundings beyond
        their noise and texture, or, when there is none, the strongest darker one (an inclusion
        less dense than the gel).
    pixel_size_mm : float or (float, float), optional
        Pixel pitch. When given, ``inclusion_size``, ``gap`` and ``background_size`` are in mm and
        detection looks for blobs of 1.5-12 mm radius; otherwise they are in pixels.
    inclusion_size : float or (float, float), optional
        Size of the inclusion ROI, centred where the automatic one would be. Default: the
        largest square inside the inclusion, shrunk to 70 % of its side (for a disk of radius R,
        a square of side ~R: the central half of its bounding box).
    gap : float, optional
        Distance between the inclusion's edge (its bounding box) and the background ROI.
        Default: half the inclusion's width (bounding box), at least 2 pixels.
    background_size : float or (float, float), optional
        Default: the inclusion ROI's shape.
    body_mask : (rows, cols) bool array, optional
        Where the object is (the background ROI must lie inside it). Default:
        :func:`radiokit.measure.body_mask` of ``image``.

    Returns
    -------
    inclusion, background : ROI
        Both inside the image. The background sits level with the inclusion ROI, to its left or,
        if that leaves the body or the image or lies on another compact structure detection found
        beside the inclusion (a second inclusion, a bubble: a blob that stands out as the
        inclusion must, within 1.2 of its radii or of its half-maximum extent), to its right
        (then above, then below). With
        ``inclusion_mask`` nothing is detected, and only the mask is kept clear of.

    Raises
    ------
    ValueError
        If no inclusion is found or the mask is empty.
    NoBackgroundFits
        A ValueError, if no background rectangle fits beside the inclusion found (the line says
        why for each side; the exception holds that inclusion).

    Notes
    -----
    Manual ROIs need no function: pass them to :func:`contrast` and friends; build them in mm
    with :meth:`ROI.from_mm`.

    Examples
    --------
    >>> yy, xx = np.mgrid[:64, :64]
    >>> img = 1.0 + 0.5 * (np.hypot(yy - 32, xx - 40) < 6)
    >>> inc, bg = find_rois(img)
    >>> inc.contains((32, 40)), bg.col1 <= 40 - 6
    (True, True)
    """
    img = np.asarray(_image(image, mask_keyword="body_mask"), np.float64)
    if not np.all(np.isfinite(img)):
        raise ValueError("image has non-finite values (NaN or inf)")
    px = None if pixel_size_mm is None else _pair(pixel_size_mm, "pixel_size_mm", positive=True)
    body = _body(img, 0.2, 2) if body_mask is None else _bool_mask(body_mask, img.shape, "body_mask")
    if inclusion_mask is not None:
        region = _bool_mask(inclusion_mask, img.shape, "inclusion_mask")
        if not region.any():
            raise ValueError("inclusion_mask is empty (no True pixel)")
        region = _largest_component(region)
        others = None  # the caller's mask says where the inclusion is; detection (~1 s at 2240) is not run
    else:
        if not body.any():
            raise ValueError("the body mask is empty: is the image all air? pass body_mask or ROIs")
        region, others = _detect_blobs(img, body, px)

    inclusion = _inscribed_square(region, 0.7)
    size = _length_px(inclusion_size, "inclusion_size", px)
    if size is not None:
        inclusion = ROI.from_center(inclusion.center, size)
    inclusion.check(img.shape, "inclusion ROI")

    extent = _bbox(region)
    g = _length_px(gap, "gap", px)
    g_r, g_c = (
        (max(2, _round_half_up(extent.shape[0] / 2)), max(2, _round_half_up(extent.shape[1] / 2)))
        if g is None
        else (_round_half_up(g[0]), _round_half_up(g[1]))
    )
    bs = _length_px(background_size, "background_size", px)
    h, w = inclusion.shape if bs is None else (_round_half_up(bs[0]), _round_half_up(bs[1]))
    if h < 1 or w < 1:
        raise ValueError(f"background_size {background_size!r} rounds to an empty rectangle")
    ic_r, ic_c = inclusion.center
    r0 = _round_half_up(ic_r - (h - 1) / 2)
    c0 = _round_half_up(ic_c - (w - 1) / 2)
    candidates = {
        "left": ROI(r0, r0 + h, extent.col0 - g_c - w, extent.col0 - g_c),
        "right": ROI(r0, r0 + h, extent.col1 + g_c, extent.col1 + g_c + w),
        "above": ROI(extent.row0 - g_r - h, extent.row0 - g_r, c0, c0 + w),
        "below": ROI(extent.row1 + g_r, extent.row1 + g_r + h, c0, c0 + w),
    }
    try:
        background = _first_fitting(candidates, img.shape, body, region, others, f"{h}x{w}", f"{g_c} px", extent)
    except ValueError as exc:
        raise NoBackgroundFits(str(exc), inclusion) from None
    return inclusion, background


class NoBackgroundFits(ValueError):
    """:func:`find_rois`'s refusal where the inclusion was found and only its background does not
    fit: ``inclusion``, the ROI found, rides along for a caller holding a background of its own
    (``radiokit process --background`` alone was refused "give both ROIs" though detection had
    found the inclusion), and ``reason``, the message without its closing :data:`ADVICE` (which
    names find_rois's keywords), for a caller whose user has other means to end it with."""

    #: what the message ends with: find_rois's keywords that would let a background fit
    ADVICE = "pass a smaller gap or background_size, body_mask, or the ROIs"

    def __init__(self, reason: str, inclusion: ROI):
        super().__init__(f"{reason}; {self.ADVICE}")
        self.reason = reason
        self.inclusion = inclusion


def _touches(mask: np.ndarray, centre, radius: float) -> bool:
    """Whether ``mask`` holds a pixel within ``radius`` of ``centre``."""
    rows, cols = mask.shape
    lo_r, hi_r = max(0, int(centre[0] - radius)), min(rows, int(np.ceil(centre[0] + radius)) + 1)
    lo_c, hi_c = max(0, int(centre[1] - radius)), min(cols, int(np.ceil(centre[1] + radius)) + 1)
    yy, xx = np.ogrid[lo_r:hi_r, lo_c:hi_c]
    return bool((mask[lo_r:hi_r, lo_c:hi_c] & (np.hypot(yy - centre[0], xx - centre[1]) <= radius)).any())


def _bool_mask(mask, shape, name) -> np.ndarray:
    refuse_masked(mask, name)
    arr = np.asarray(mask)
    if arr.dtype != bool or arr.shape != shape:
        raise ValueError(f"{name} must be a bool array of shape {shape}, got {arr.dtype} {arr.shape}")
    return arr


def _first_fitting(candidates: dict, shape, body, region, others, size: str, gap: str, extent) -> ROI:
    """The first candidate background ROI inside the image and the body, clear of the inclusion
    and of the ``others`` detection found (:class:`_Neighbours`; None: the inclusion was given);
    else a ValueError saying why each was refused (find_rois ends it with its advice)."""
    rows, cols = shape
    tried = []
    for side, roi in candidates.items():
        if roi.row0 < 0 or roi.col0 < 0 or roi.row1 > rows or roi.col1 > cols:
            tried.append(f"{side}: outside the image")
        elif not body[roi.slices].all():
            tried.append(f"{side}: leaves the body")
        elif region[roi.slices].any():
            tried.append(f"{side}: overlaps the inclusion")
        elif others is not None and (near := others.near(roi)):
            tried.append(f"{side}: overlaps another structure at ({near[0][0]:.0f}, {near[0][1]:.0f})")
        else:
            return roi
    raise ValueError(f"no {size} background ROI fits {gap} beside the inclusion {extent} ({'; '.join(tried)})")
