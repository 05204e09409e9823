"""Compression-induced contrast: add the difference between two compression steps to the reference.

The paper registers the second compression step onto the third (the most compressed, the
*reference*), takes the difference ``D = reference - registered``, subtracts its mean and adds it,
times a factor ``k``, to the reference. :func:`compression_contrast` does exactly that;
:func:`difference` gives ``D`` alone and :func:`to_domain` turns line integrals into the other
pixel conventions.

Three pixel conventions (:class:`Domain`) are supported; the formula is the same in all:

``Domain.LOG`` (``"log"``)
    Line integrals ``L = -ln(I / I0)``, more attenuation brighter (``radiokit.correct`` with
    ``domain="log"``).
``Domain.LINEAR`` (``"linear"``)
    Flat-field-corrected transmission ``I / I0``, more attenuation darker (``radiokit.correct``
    with ``domain="linear"``).
``Domain.NEGATIVE`` (``"negative"``)
    The paper's experimental images, which the paper calls its linear images: the *negative*
    transmission ``-I / I0`` (or ``-counts``), more attenuation brighter.
    ``to_domain(L, "negative")`` gives ``-exp(-L)``.

``NEGATIVE`` is ``-LINEAR``, so contrasts, CNRs and Weber contrasts change sign between the two
while improvement factors and change ratios (ratios of contrasts) do not.
"""

from __future__ import annotations

import enum

import numpy as np

from radiokit.checks import image_hint, is_number, refuse_masked
from radiokit.measure import ROI

__all__ = ["Domain", "compression_contrast", "difference", "to_domain", "DOMAINS"]


class Domain(enum.StrEnum):
    """A pixel convention: what a pixel value means (see the module docstring)."""

    LOG = "log"  #: line integral -ln(I/I0)
    LINEAR = "linear"  #: transmission I/I0
    NEGATIVE = "negative"  #: negative transmission -I/I0, the paper's experimental images

    @classmethod
    def parse(cls, value, name: str = "domain") -> Domain:
        """``value`` as a :class:`Domain`; ValueError naming ``name`` and the choices otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"{name} must be one of {DOMAINS}, got {value!r}") from None


#: Every domain's name, for messages and argument choices.
DOMAINS = tuple(d.value for d in Domain)


def _image(image, name, mask_keyword=None) -> np.ndarray:
    refuse_masked(image, name, mask_keyword)
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(
            f"{name} must be a 2-D (rows, cols) array, got shape {arr.shape}{image_hint(image, arr.shape)}"
        )
    if arr.size == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has {int(np.count_nonzero(~np.isfinite(arr)))} non-finite value(s) (NaN or inf)")
    return arr


def _pair(reference, registered, mask_keyword=None):
    ref = _image(reference, "reference", mask_keyword)
    reg = _image(registered, "registered", mask_keyword)
    if ref.shape != reg.shape:
        raise ValueError(
            f"reference has shape {ref.shape}, registered has {reg.shape}: "
            "register the moving image onto the reference grid first"
        )
    return ref, reg


def _check_sign(image, name, domain: Domain):
    # The formula is the same in every convention, but +I/I0 given as -I/I0 (or the reverse)
    # turns every brightness and contrast upside down: transmission is positive, its negative not.
    med = np.median(image)
    if domain is Domain.NEGATIVE and med > 0:
        raise ValueError(
            f"{name}: domain='negative' expects the paper's negative intensities "
            "(pixel = -I/I0 or -counts, more attenuation brighter), but most pixels "
            "are positive; for transmission I/I0 (radiokit.correct's 'linear') pass "
            "domain='linear'"
        )
    if domain is Domain.LINEAR and med < 0:
        raise ValueError(
            f"{name}: domain='linear' expects transmission I/I0 (positive), but most "
            "pixels are negative; for the paper's negative intensities -I/I0 pass "
            "domain='negative'"
        )


def difference(reference, registered) -> np.ndarray:
    """The compression-induced difference ``D = reference - registered`` (float32).

    Parameters
    ----------
    reference : (rows, cols) array
        The most compressed step.
    registered : (rows, cols) array
        A less compressed step registered onto the reference's grid.

    Returns
    -------
    (rows, cols) float32 array

    Raises
    ------
    ValueError
        If the shapes differ or a value is not finite.

    Examples
    --------
    >>> difference([[3.0, 2.0]], [[4.0, 4.0]])
    array([[-1., -2.]], dtype=float32)
    """
    ref, reg = _pair(reference, registered)
    return (np.asarray(ref, np.float64) - reg).astype(np.float32)


def to_domain(line_integral, domain: Domain | str) -> np.ndarray:
    """A line-integral image ``L = -ln(I/I0)`` in ``domain`` (float32).

    ``"log"``: unchanged; ``"linear"``: ``I/I0 = exp(-L)``; ``"negative"``: ``-I/I0 = -exp(-L)``,
    the paper's experimental convention (more attenuation brighter). ValueError for a value that
    is not finite, or so negative (below about -88.7) that ``exp(-L)`` overflows float32.

    Examples
    --------
    >>> to_domain([[0.0, np.log(2.0)]], "negative")
    array([[-1. , -0.5]], dtype=float32)
    >>> to_domain([[0.0, np.log(2.0)]], Domain.LINEAR)
    array([[1. , 0.5]], dtype=float32)
    """
    domain = Domain.parse(domain)
    L = np.asarray(_image(line_integral, "line_integral"), np.float64)
    if domain is Domain.LOG:
        return L.astype(np.float32)
    if L.min() < _MIN_LOG:  # exp(-L) would be inf in float32, silently
        raise ValueError(
            f"line_integral has values down to {L.min():.4g}: exp(-L) overflows float32 below {_MIN_LOG:.4g} "
            "(a transmission above 1e38; is this a line-integral image?)"
        )
    t = np.exp(-L)
    return (t if domain is Domain.LINEAR else -t).astype(np.float32)


_MIN_LOG = -float(np.log(np.finfo(np.float32).max))  # the least L whose exp(-L) float32 holds


def compression_contrast(
    reference, registered, k: float = 1.0, *, domain: Domain | str = "log", mask=None
) -> np.ndarray:
    """The paper's enhanced image: ``reference + k (D - mean D)`` with ``D = reference - registered``.

    Parameters
    ----------
    reference : (rows, cols) array
        The most compressed step (the paper's third), in ``domain``.
    registered : (rows, cols) array
        A less compressed step registered onto ``reference`` (``moving(x + d(x))``), same domain.
    k : float
        Multiplying factor of the compression-induced contrast (the paper: 1 and 2).
    domain : Domain or {"log", "linear", "negative"}
        ``"log"``: line integrals ``-ln(I/I0)``. ``"linear"``: transmission ``I/I0``.
        ``"negative"``: the paper's negative intensities ``-I/I0`` or ``-counts``. The formula
        is the same in all three; the domain is checked against the image's sign.
    mask : (rows, cols) bool array or ROI, optional
        Where ``mean D`` is taken; default the whole image (the paper: "mean intensity of
        difference image").

    Returns
    -------
    enhanced : (rows, cols) float32 array

    Raises
    ------
    ValueError
        If the shapes differ, a value or ``k`` is not finite, ``domain`` is unknown, the mask is
        empty, of another shape or outside the image, or the image's sign contradicts the domain
        (a mostly positive ``"negative"`` image, a mostly negative ``"linear"`` one).

    Notes
    -----
    **Sign conventions.** In ``"log"`` and ``"negative"`` a brighter pixel means more
    attenuation (``"linear"`` is ``"negative"`` upside down: every contrast changes sign, every
    ratio of contrasts stays), so an
    attenuating inclusion has a positive contrast (inclusion minus background) and
    ``D = reference - registered`` is the change of brightness from the less compressed step to
    the most compressed one. Compression thins every column, so ``D < 0`` nearly everywhere:
    ``D = L_ref - L_reg`` in ``"log"``, ``D = I_reg - I_ref`` (in units of ``I0``) in
    ``"negative"``. Subtracting ``mean D`` keeps the overall level (``D - mean D`` is positive
    where the image darkened less than on average and negative where it darkened more) and does
    not change any contrast: for ROI means,

    .. math:: C_{enh} = C_{ref} + k\\,(\\bar D_{incl} - \\bar D_{bg})
              = C_{ref} + k\\,(C_{ref} - C_{reg}),
              \\quad \\text{improvement} = 1 + k\\,(1 - C_{reg} / C_{ref}),

    so the improvement exceeds 1 exactly when the inclusion's contrast grew from the less
    compressed step to the reference, and grows linearly with ``k``.

    **Why D carries elasticity.** The reference is the most compressed step. A stiff inclusion
    thins less than the soft tissue around it, so its column loses less of its extra
    attenuation than it would if it were as soft as the background: its ``D`` is less negative
    than that of an equally soft inclusion, and that part of ``D - mean D`` is positive at the
    inclusion and adds to its brightness. With rigid plates and a parallel beam through them
    (mammography) every column thins by the same amount between the two steps, a fraction ``r``
    of the less compressed step's gap ``t`` (20 % to 25 % compression: ``r = 0.05 / 0.80``). If
    the inclusion's chord ``c`` thins by a fraction ``r_i`` and its attenuation exceeds the
    background's by ``dmu``, and the registration is perfect:

    - ``"log"``: line integrals are linear in thickness, ``D_incl - D_bg = -dmu c r_i`` and the
      improvement is ``1 - k r_i / (1 - r_i)``: 1 for a rigid inclusion, ``1 - k r / (1 - r)``
      for one as soft as the background. The elasticity signal is the difference between the
      two; in this model the factor itself does not exceed 1.
    - ``"negative"`` (and ``"linear"``): the intensity is exponential in the line integral,
      ``I = I0 exp(-L)``, so
      part of ``D`` needs no stiffness at all. Thinning the background by ``r t`` multiplies the
      transmitted intensity, and with it the inclusion-background intensity difference, by
      ``exp(mu_bg r t)`` whatever the inclusion's stiffness; to first order in ``dmu c`` the
      improvement is ``1 + k (1 - exp(-mu_bg r t) / (1 - r_i))``. An inclusion as soft as the
      background (``r_i = r``) already gives more than 1 once ``mu_bg t > -ln(1 - r) / r``
      (about one attenuation length); a stiffer one (smaller ``r_i``) gives more.

    Imaged from the side (beam across the compression axis), paths lengthen with the lateral
    expansion instead and these signs change; the identity above holds in any geometry. To say
    how much of an improvement is elasticity, compare with a control whose inclusion is as soft
    as the background (in simulation), in both domains.

    References
    ----------
    .. [1] The paper, "Results": "subtracting the second step compression registered image from
       the third step compression (reference) image ... the subtracted value of mean intensity
       of difference image ... added with the reference image ... a multiplying factor".

    Examples
    --------
    >>> ref = np.array([[4.0, 4.0], [6.0, 4.0]])      # inclusion at (1, 0)
    >>> reg = np.array([[5.0, 5.0], [6.5, 5.0]])      # it darkened less on compression
    >>> compression_contrast(ref, reg, k=2.0)         # D - mean D = [[-.125, -.125], [.375, -.125]]
    array([[3.75, 3.75],
           [6.75, 3.75]], dtype=float32)
    """
    domain = Domain.parse(domain)
    ref, reg = _pair(reference, registered, "mask")
    if not is_number(k) or not np.isfinite(k):
        raise ValueError(f"k must be a finite real number, got {k!r}")
    _check_sign(ref, "reference", domain)
    _check_sign(reg, "registered", domain)
    # D is the one float64 work image, turned in place into the enhanced image: with the float32
    # result, 3 frames at the peak where a temporary per operation held 7 (80 MB more at 2240 px,
    # per k and domain); the same float64 operations in the same order, so the same result
    d = np.subtract(ref, reg, dtype=np.float64)
    mean_d = _mean_over(d, mask)
    d -= mean_d
    d *= float(k)
    d += ref
    return d.astype(np.float32)


def _mean_over(d: np.ndarray, mask) -> float:
    """``mean D`` over ``mask`` (None: the whole image; an ROI; a bool image), without copying the
    selected pixels (``d[m]`` is up to 2 more frames)."""
    if mask is None:
        return float(d.mean())
    if isinstance(mask, ROI):
        return float(d[mask.check(d.shape, "mask").slices].mean())
    refuse_masked(mask, "mask")
    m = np.asarray(mask)
    if m.dtype != bool:
        raise ValueError(f"mask must be a boolean array or an ROI, got dtype {m.dtype}")
    if m.shape != d.shape:
        raise ValueError(f"mask has shape {m.shape}, reference has {d.shape}")
    if not m.any():
        raise ValueError("mask is empty (no True pixel): mean D is undefined")
    return float(np.mean(d, where=m))
