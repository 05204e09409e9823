"""The paper's headline numbers measured on a simulated pair, with the truth where it helps.

A study of the method (not of the processing chain) needs the headline numbers -- change ratio,
improvement factor IF(k), contrast-to-noise ratio, and the bound IF cannot exceed
(:func:`radiokit.measure.improvement_bound`) -- for a scene and a modelling choice, quickly and
without the registration's error unless that error is the point. :func:`image_pair` projects the
two most compressed states on a small detector, registers the moving one with the truth field
(or the truth plus a known error, :func:`degraded_field`), and :func:`headline` measures it the
way ``radiokit.pipeline`` measures a file: ROIs from :func:`radiokit.measure.find_rois` on the
inclusion's shadow, both domains, every k.

Example (an axisymmetric cylinder through the plates, about a second)::

    >>> from sim.mechanics import compress
    >>> from sim.scene import Body, Inclusion, Material, MeshSpec, Compression, Scene
    >>> gel = Material("gel", E_kpa=5.0, nu=0.495, attenuation_per_cm=0.5)
    >>> hard = Material("hard", E_kpa=5000.0, nu=0.495, attenuation_per_cm=1.0)
    >>> sc = Scene(body=Body("cylinder", height_mm=50.0, diameter_mm=50.0, material=gel),
    ...            inclusions=[Inclusion("sphere", diameter_mm=8.0, material=hard)],
    ...            compression=Compression((0.20, 0.25)), mesh=MeshSpec(1.0, 5.0))
    >>> h = headline(image_pair(sc, compress(sc), pixel_size_mm=0.25))
    >>> round(h.improvement["negative"]["1"], 3), round(h.bound["negative"]["1"], 3)
    (1.114, 1.118)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "DOMAINS",
    "ImagePair",
    "Headline",
    "Projected",
    "project_pair",
    "images",
    "study_geometry",
    "image_pair",
    "headline",
    "degraded_field",
    "add_noise",
    "bound_exponent",
    "with_field",
    "replace_materials",
    "find_inclusion_roi",
    "Signs",
    "step_images",
    "paper_signs",
    "predicted_cnr",
]


@dataclass
class ImagePair:
    """The paper's pair on one detector grid: line integrals ``-ln(I/I0)``.

    Attributes
    ----------
    reference, moving : (rows, cols) float64
        The most compressed step and the step before it.
    registered : (rows, cols) float64
        ``moving`` pulled onto the reference (``moving(x + d(x))``).
    field : (2, rows, cols) float32
        The pull field used, pixels.
    truth : (2, rows, cols) float32
        The truth field (:func:`sim.truth.truth_displacement`).
    inclusion_mask : (rows, cols) bool
        Rays through the inclusion in the reference.
    pixel_size_mm : float
    mu_dg : float or None
        ``mu_b * delta_g`` of :func:`bound_exponent`; None when the beam is not through the plates.
    view : str
        ``through_plates`` or ``side``.
    """

    reference: np.ndarray
    moving: np.ndarray
    registered: np.ndarray
    field: np.ndarray
    truth: np.ndarray
    inclusion_mask: np.ndarray
    pixel_size_mm: float
    mu_dg: float | None
    view: str


@dataclass
class Headline:
    """The numbers of one pair. Dictionaries are keyed by domain (``log``, ``negative``: the
    paper's -I/I0, never called "linear", which is +I/I0, DESIGN.md), then by k as a string
    (``"1"``, ``"2"``), as in ``results.json``."""

    change_ratio: dict
    improvement: dict
    contrast_reference: dict
    cnr_reference: dict = field(default_factory=dict)
    cnr: dict = field(default_factory=dict)
    bound: dict = field(default_factory=dict)
    inclusion: object = None
    background: object = None


def study_geometry(scene, pixel_size_mm=0.25, margin=1.35):
    """A square detector of ``pixel_size_mm`` pixels covering the body (expanded by ``margin`` for the
    lateral bulge and magnified for cone beams): the scene's beam, a small grid."""
    from sim.xray import Geometry, body_centre

    b = scene.body
    if b.geometry in ("hemi-ellipsoid", "ellipsoid"):
        extent = 2 * max(b.semi_axes_mm)
    elif b.geometry in ("truncated-cone", "cylinder"):
        extent = max(b.height_mm, b.bottom_diameter_mm, b.top_diameter_mm, b.diameter_mm)
    else:
        extent = max(b.size_mm)
    beam = scene.beam
    mag = (
        1.0
        if beam.kind == "parallel"
        else (beam.source_distance_mm + beam.detector_distance_mm) / beam.source_distance_mm
    )
    n = int(math.ceil(extent * margin * mag / pixel_size_mm))
    return Geometry(
        beam.kind,
        beam.direction,
        (n, n),
        pixel_size_mm,
        body_centre(scene),
        beam.source_distance_mm,
        beam.detector_distance_mm,
    )


def bound_exponent(scene, moving, reference) -> float | None:
    """``mu_b * delta_g``: the background's attenuation times how much the gap closed between two
    states; None when the beam does not run through the plates (the bound does not hold).

    The normal-incidence value: a cone beam's ray ``r`` off the axis at the isocentre, ``s`` from
    the source, crosses the plates obliquely and thins by ``dg sqrt(1 + (r / s)^2)``, which raises
    its bound's exponent by that factor (1e-3 at r = 18 mm, s = 400 mm: the pva-phantom through
    the plates), left out here."""
    if scene.beam.direction != "y":
        return None
    return scene.body.material.attenuation_per_mm * (moving.gap_mm - reference.gap_mm)


def degraded_field(truth, error_px, *, kind="smooth", seed=0, scale_px=None):
    """The truth field plus a known error of root-mean-square magnitude ``error_px`` (over the
    whole grid), for the registration's share of the headline.

    ``smooth``: a random field low-pass filtered on ``scale_px`` (default a tenth of the grid), the
    error a smooth registration makes; ``scale``: the truth times ``1 + error`` (a registration
    that under- or over-estimates the motion), ``error_px`` then being the relative error.
    """
    from scipy import ndimage

    truth = np.asarray(truth, np.float64)
    if kind == "scale":
        return (truth * (1.0 + error_px)).astype(np.float32)
    if kind != "smooth":
        raise ValueError(f"kind {kind!r}: expected 'smooth' or 'scale'")
    rng = np.random.default_rng(seed)
    s = scale_px if scale_px is not None else max(2.0, truth.shape[1] / 10)
    noise = np.stack([ndimage.gaussian_filter(rng.standard_normal(truth.shape[1:]), s, mode="wrap") for _ in range(2)])
    rms = float(np.sqrt((noise**2).sum(axis=0).mean()))
    return (truth + noise * (error_px / rms if rms > 0 else 0.0)).astype(np.float32)


def add_noise(line_integral, counts, rng):
    """Poisson noise of ``counts`` open-beam quanta per pixel: ``-ln(Poisson(counts e^-L) / counts)``
    (a zero count is kept at one quantum: no infinite line integral)."""
    q = rng.poisson(counts * np.exp(-np.asarray(line_integral, np.float64)))
    return -np.log(np.maximum(q, 1) / counts)


@dataclass
class Projected:
    """Both states' path lengths per region on one geometry, and the truth field between them:
    what every image model of an ablation shares (:func:`project_pair`)."""

    lengths: tuple  # (moving, reference), each (n_regions, rows, cols) mm
    mu_per_mm: np.ndarray
    truth: np.ndarray
    inclusion_mask: np.ndarray
    pixel_size_mm: float
    mu_dg: float | None
    view: str


def project_pair(scene, states, *, pixel_size_mm=0.25, geometry=None, truth_factor=4) -> Projected:
    """Path lengths of the last two states of ``states`` (one ``compress`` call) and the truth
    field (moving onto reference). ``truth_factor``: the truth's coarsening
    (:func:`sim.truth.truth_displacement`; smooth on the elements' scale, the full grid costs ten
    times more); ``None`` skips the truth (zeros: the identity registration)."""
    from sim.truth import truth_displacement
    from sim.xray import path_lengths

    moving, reference = states[-2], states[-1]
    solver = reference.solver
    geom = geometry if geometry is not None else study_geometry(scene, pixel_size_mm)
    fem = getattr(solver, "projection_mesh", None) or solver.fem
    thickness = float(scene.body.size_mm[2]) if fem.model == "plane-strain" else None
    mus = np.array([scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions])
    lengths = tuple(path_lengths(fem, geom, s.displacement, thickness_mm=thickness) for s in (moving, reference))
    if truth_factor is None:  # no truth wanted: the identity stands in for it
        truth = np.zeros((2,) + tuple(geom.shape), np.float32)
    else:
        truth = truth_displacement(scene, reference, moving, geometry=geom, factor=truth_factor)
    view = "through_plates" if geom.direction == "y" else "side"
    return Projected(
        lengths,
        mus[: len(lengths[0])],
        truth,
        lengths[1][1:].sum(axis=0) > 0,
        float(geom.pixel_size_mm),
        bound_exponent(scene, moving, reference),
        view,
    )


def images(projected: Projected, image_model=None, field=None) -> ImagePair:
    """The pair seen through ``image_model(lengths, mu_per_mm) -> -ln(I/I0)`` (default the
    monochromatic ``sum_m mu_m L_m``; see :mod:`sim.imaging`), registered with ``field``
    (default the truth)."""
    from radiokit.register import warp

    p = projected
    model = image_model or (lambda lengths, mu: np.tensordot(mu, lengths, axes=1))
    mov, ref = (np.asarray(model(ln, p.mu_per_mm), np.float64) for ln in p.lengths)
    used = p.truth if field is None else np.asarray(field, np.float32)
    registered = warp(mov.astype(np.float32), used).astype(np.float64)
    return ImagePair(ref, mov, registered, used, p.truth, p.inclusion_mask, p.pixel_size_mm, p.mu_dg, p.view)


def image_pair(
    scene, states, *, pixel_size_mm=0.25, geometry=None, field=None, image_model=None, truth_factor=4
) -> ImagePair:
    """:func:`project_pair` then :func:`images`: the last two states of ``states`` projected,
    seen through ``image_model`` and registered with ``field`` (default: the truth)."""
    return images(
        project_pair(scene, states, pixel_size_mm=pixel_size_mm, geometry=geometry, truth_factor=truth_factor),
        image_model,
        field,
    )


@dataclass
class Signs:
    """The paper's two qualitative observations on its experimental (negative, ``-I/I0``) images,
    measured per compression step (increasing): the mean negative intensity of a background
    rectangle beside the inclusion (``brightness``) and the contrast (inclusion minus
    background rectangle means), rectangles found on each step's own image."""

    ratios: list
    brightness: list
    contrast: list

    @property
    def least_compressed_brightest(self) -> bool:
        """ "the least compressed phantom image shows most brightness"."""
        return int(np.argmax(self.brightness)) == 0

    @property
    def most_compressed_most_contrast(self) -> bool:
        """ "the most compressed phantom image shows most contrast"."""
        return int(np.argmax(self.contrast)) == len(self.contrast) - 1


def step_images(scene, states, geometry):
    """Line integrals and inclusion masks of every state on ``geometry``."""
    from sim.xray import path_lengths

    solver = states[0].solver
    fem = getattr(solver, "projection_mesh", None) or solver.fem
    thickness = float(scene.body.size_mm[2]) if fem.model == "plane-strain" else None
    mus = np.array([scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions])
    out = []
    for s in states:
        lengths = path_lengths(fem, geometry, s.displacement, thickness_mm=thickness)
        out.append((np.tensordot(mus[: len(lengths)], lengths, axes=1), lengths[1:].sum(axis=0) > 0))
    return out


def paper_signs(scene, states, *, pixel_size_mm=0.25, geometry=None) -> Signs:
    """Measure the paper's two qualitative signs (:class:`Signs`) on ``states``, noise-free."""
    from radiokit.enhance import to_domain
    from radiokit.measure import contrast, find_rois

    geom = geometry if geometry is not None else study_geometry(scene, pixel_size_mm)
    bright, con = [], []
    for L, mask in step_images(scene, states, geom):
        neg = to_domain(L, "negative").astype(np.float64)
        inc, bg = find_rois(L, inclusion_mask=mask, pixel_size_mm=geom.pixel_size_mm)
        bright.append(float(neg[bg.slices].mean()))
        con.append(contrast(neg, inc, bg))
    return Signs([s.ratio for s in states], bright, con)


def with_field(pair: ImagePair, field) -> ImagePair:
    """The same pair registered with another pull ``field`` (e.g. :func:`degraded_field`)."""
    from radiokit.register import warp

    field = np.asarray(field, np.float32)
    registered = warp(pair.moving.astype(np.float32), field).astype(np.float64)
    return dataclasses.replace(pair, registered=registered, field=field)


def find_inclusion_roi(pair: ImagePair):
    """The inclusion ROI :func:`headline` uses by default."""
    from radiokit.measure import find_rois

    return find_rois(pair.reference, inclusion_mask=pair.inclusion_mask, pixel_size_mm=pair.pixel_size_mm)[0]


#: The domains measured: line integrals and the paper's negative transmission -I/I0 (as
#: radiokit.pipeline; until session 25 this module called -I/I0 "linear", radiokit's +I/I0).
DOMAINS = ("log", "negative")


def predicted_cnr(pair: ImagePair, h: Headline, counts: float, domain: str = "negative") -> dict:
    """CNR of the reference and of each enhanced image with Poisson noise of ``counts`` open-beam
    quanta per pixel, predicted rather than sampled (so noise-free studies have a CNR that
    responds to the model). As :func:`radiokit.measure.cnr`, the denominator is the background
    ROI's standard deviation: the noise-free image's own variation there (a side view's
    background is not flat) and the noise, added in quadrature. One exposure's per-pixel noise
    is ``sqrt(e^L / N)`` (log) or ``sqrt(e^-L / N)`` (negative), independent between the two
    exposures, and ``E = R + k (R - M - mean D)`` has ``var_E = (1 + k)^2 var_R + k^2 w var_M``.
    ``w`` is what the registration's bilinear interpolation leaves of the moving image's noise: a
    sample at fractional offsets ``(fr, fc)`` weighs four independent pixels, ``w = ((1 - fr)^2 +
    fr^2) ((1 - fc)^2 + fc^2)``, 1 at whole pixels, 1/4 at half a pixel both ways, averaged over
    the background ROI from ``pair.field`` (without it a registered pair's k = 1 and 2 CNRs were
    predicted 5-10 % low: tests/test_audit_noise_closed_form.py).
    Returns ``{"reference": CNR_R, "1": CNR_E(1), ...}``."""
    from radiokit.enhance import compression_contrast, to_domain
    from radiokit.measure import contrast

    if domain not in DOMAINS:
        raise ValueError(f"domain {domain!r}: expected one of {DOMAINS} (-I/I0 is 'negative')")
    bg = h.background
    L_r, L_m = (float(np.mean(im[bg.slices])) for im in (pair.reference, pair.registered))
    sign = 1.0 if domain == "log" else -1.0
    var_r, var_m = math.exp(sign * L_r) / counts, math.exp(sign * L_m) / counts
    frac = np.asarray(pair.field, np.float64)[(slice(None), *bg.slices)]
    frac = frac - np.floor(frac)
    var_m *= float(np.mean(((1 - frac[0]) ** 2 + frac[0] ** 2) * ((1 - frac[1]) ** 2 + frac[1] ** 2)))
    ref, reg = to_domain(pair.reference, domain), to_domain(pair.registered, domain)
    out = {
        "reference": contrast(ref, h.inclusion, bg) / math.sqrt(var_r + float(np.var(ref[bg.slices], dtype=np.float64)))
    }
    for key in h.improvement[domain]:
        k = float(key)
        enh = compression_contrast(ref, reg, k, domain=domain)
        structure = float(np.var(enh[bg.slices], dtype=np.float64))
        out[key] = contrast(enh, h.inclusion, bg) / math.sqrt((1 + k) ** 2 * var_r + k * k * var_m + structure)
    return out


def headline(pair: ImagePair, ks=(1.0, 2.0), rois=None) -> Headline:
    """Change ratio, IF(k), contrast and CNR (where the background has noise) in both domains,
    and the bound where the beam runs through the plates. ``rois``: (inclusion, background)
    ROIs, default :func:`radiokit.measure.find_rois` on the reference and its inclusion mask."""
    from radiokit.enhance import compression_contrast, to_domain
    from radiokit.measure import change_ratio, cnr, contrast, find_rois, improvement_bound, improvement_factor

    if rois is None:
        rois = find_rois(pair.reference, inclusion_mask=pair.inclusion_mask, pixel_size_mm=pair.pixel_size_mm)
    inc, bg = rois
    out = Headline({}, {}, {}, inclusion=inc, background=bg)
    for dom in DOMAINS:
        ref, reg = to_domain(pair.reference, dom), to_domain(pair.registered, dom)
        out.change_ratio[dom] = change_ratio(reg, ref, inc, bg)
        out.contrast_reference[dom] = contrast(ref, inc, bg)
        noisy = float(np.std(ref[bg.slices])) > 0
        out.cnr_reference[dom] = cnr(ref, inc, bg) if noisy else math.nan
        out.improvement[dom], out.cnr[dom], out.bound[dom] = {}, {}, {}
        for k in ks:
            key = f"{float(k):g}"
            enh = compression_contrast(ref, reg, float(k), domain=dom)
            out.improvement[dom][key] = improvement_factor(enh, ref, inc, bg)
            out.cnr[dom][key] = cnr(enh, inc, bg) if noisy else math.nan
            out.bound[dom][key] = improvement_bound(float(k), 1.0, pair.mu_dg, dom) if pair.mu_dg is not None else None
    return out


def replace_materials(scene, *, body=None, inclusion=None):
    """A copy of ``scene`` with the body's and/or every inclusion's material fields replaced
    (``dict`` of :class:`sim.scene.Material` fields)."""
    sc = dataclasses.replace(scene)
    if body:
        sc.body = dataclasses.replace(scene.body, material=dataclasses.replace(scene.body.material, **body))
    if inclusion:
        sc.inclusions = [
            dataclasses.replace(i, material=dataclasses.replace(i.material, **inclusion)) for i in scene.inclusions
        ]
    return sc
