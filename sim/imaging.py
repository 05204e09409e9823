"""What the detector sees beyond a monochromatic line integral: the models an ablation switches on.

Each model maps path lengths per material region (``(n_regions, rows, cols)`` mm, from
:func:`sim.xray.path_lengths`) and the scene's attenuation coefficients (1/mm) to the observed
line integral ``-ln(I/I0)`` after flat-field correction; :func:`chain` composes one beam model
with image-side effects (scatter, blur, noise), in that physical order.

Beam
----
:func:`monochromatic` is the paper's model, ``sum_m mu_m L_m``. :class:`Polychromatic` takes a tube
spectrum from SpekPy (the tube's bremsstrahlung and characteristic lines from the anode, kV,
anode angle and filtration; a maintained, validated tube-spectrum model) and the energy
dependence of attenuation from XrayDB (tabulated cross sections, the Elam/Ravel/Sieber database).
The scene gives one coefficient per material, an effective one (the paper's are measured
transmission values at the operating voltage). Each material's ``mu(E)`` is water's shape
(tissues and gels are water-like, Z_eff 6.5-7.5, between 15 and 60 keV) times a factor, the same
relative factor for every material (``mu_m(E) / mu_b(E) = mu_m / mu_b``), chosen so that the
polychromatic transmission through ``match_mm`` (:func:`for_scene`: :func:`match_thickness_mm`,
the undeformed body's thickness along the beam, the longest chord the view's rays cross) equals the
monochromatic one: the scene's coefficients stay the effective ones where they were measured,
and what changes is only beam hardening (the effective coefficient falling with depth). The
detector integrates energy, its scintillator taken to absorb every photon (weight ``E * fluence``):
the C7942's is GOS on a fibre-optic plate (../shared/hardware/C7942.md), whose absorption falls
with energy and jumps at gadolinium's K edge (50.2 keV); its thickness is not in the vendor facts,
so that efficiency is not modelled.

Image side
----------
Scatter: an additive, smooth term, ``I = P + SPR * G_s * (P L) / L_ref`` with a wide Gaussian
``G_s`` (object scatter is smooth on the scale of centimetres): made in proportion to the
interactions (``P L`` to first order), so it vanishes in air, and scaled so that the
scatter-to-primary ratio is ``SPR`` in a uniform slab of line integral ``L_ref``. The flat field
has no object and so no scatter. Blur: the scintillator's point spread, a Gaussian on the intensity.
Noise: Poisson quanta, :func:`sim.study.add_noise`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

__all__ = ["monochromatic", "Polychromatic", "scatter", "blur", "chain", "for_scene", "match_thickness_mm", "tube"]


def monochromatic(lengths, mu_per_mm):
    """``sum_m mu_m L_m``: the paper's monochromatic beam."""
    return np.tensordot(np.asarray(mu_per_mm, float), lengths, axes=1)


@dataclass
class Polychromatic:
    """A tube spectrum (SpekPy) through water-shaped attenuation (XrayDB), energy-integrating.

    Parameters
    ----------
    kv : float
        Tube voltage.
    target : str
        Anode: ``"W"`` (the L8121-01's), ``"Mo"`` (a mammography tube).
    anode_angle_deg : float
    filters : tuple of (material, mm)
        Inherent and added filtration (the L8121-01: 150 um beryllium) and the air on the way.
    match_mm : float
        The thickness of background at which mono- and polychromatic transmissions agree.
    step_kev : float
        Energy bin width.
    """

    kv: float = 60.0
    target: str = "W"
    anode_angle_deg: float = 12.0
    filters: tuple = (("Be", 0.15), ("Air", 500.0))
    match_mm: float = 50.0
    step_kev: float = 1.0
    energies_kev: np.ndarray = field(init=False, repr=False)
    weights: np.ndarray = field(init=False, repr=False)
    shape: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        try:
            import spekpy
            import xraydb
        except ImportError:
            raise ImportError("the polychromatic beam needs SpekPy and XrayDB: pip install 'radiokit[study]'") from None
        s = spekpy.Spek(kvp=self.kv, th=self.anode_angle_deg, targ=self.target, dk=self.step_kev)
        for mat, mm in self.filters:
            s.filter(mat, mm)
        k, fluence = s.get_spectrum()
        keep = fluence > 0
        self.energies_kev = np.asarray(k[keep], float)
        w = fluence[keep] * self.energies_kev  # energy-integrating detector
        self.weights = w / w.sum()
        mu_water = np.asarray(xraydb.material_mu("H2O", self.energies_kev * 1e3, density=1.0), float)  # 1/cm
        self.shape = mu_water / float(self.weights @ mu_water)  # mean 1 over the open-beam spectrum

    @property
    def mean_energy_kev(self) -> float:
        return float(self.weights @ self.energies_kev)

    def _transmission(self, mono, scale):
        out = np.zeros(np.shape(mono))
        for w, s in zip(self.weights, self.shape):
            out += w * np.exp(-scale * s * mono)  # mu_m(E) = scale shape(E) mu_m: one shape, it factors
        return out

    def scale_for(self, mu_b_per_mm) -> float:
        """The factor on water's shape that makes ``match_mm`` of background transmit as the
        monochromatic beam does."""
        from scipy.optimize import brentq

        target = mu_b_per_mm * self.match_mm
        if target <= 0:
            return 1.0
        # the upper end of the bracket transmits nothing: clipped, not log(0)
        return float(
            brentq(lambda a: -np.log(max(float(self._transmission(target, a)), 1e-300)) - target, 1e-6, 1e3, xtol=1e-12)
        )

    def __call__(self, lengths, mu_per_mm):
        mono = monochromatic(lengths, mu_per_mm)
        scale = self.scale_for(float(mu_per_mm[0]))
        if mono.size <= 1 << 16:
            return -np.log(self._transmission(mono, scale))
        # a panel: the transmission depends on the monochromatic line integral x alone, so it is
        # tabulated and interpolated. Not -ln T itself on an even grid: its second derivative is
        # minus the spectral variance of the coefficient, largest on the thinnest rays (the open
        # beam's soft photons), where that erred by 4e-2 of the value. Instead -ln T / x, which
        # tends to the open-beam mean coefficient at x = 0, on a grid dense near 0 (even in
        # sqrt(x)): below 1e-6 of the value up to x = 25 (tests/test_sim_imaging.py).
        top = max(float(np.max(mono)), 1e-9)
        grid = top * np.linspace(0.0, 1.0, 16385) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            per_unit = -np.log(self._transmission(grid, scale)) / grid
        per_unit[0] = scale * float(self.weights @ self.shape)  # d(-ln T)/dx at 0: the mean coefficient
        return mono * np.interp(mono, grid, per_unit)


def _gauss(image, sigma_px):
    """Gaussian filter; a wide one (scatter: 200 px on the full panel) on a grid coarsened to
    about sigma / 8 per cell and interpolated back: the result is smooth on that scale, and a
    direct filter that wide costs seconds per frame."""
    from scipy import ndimage

    if not sigma_px > 0:
        return image
    f = int(sigma_px // 8)
    if f < 2:
        return ndimage.gaussian_filter(image, sigma_px, mode="nearest")
    rows, cols = image.shape
    m = f * int(np.ceil(4 * sigma_px / f))  # the edge extended as the direct filter's "nearest" does
    padded = np.pad(image, ((m, m - rows % f + f), (m, m - cols % f + f)), mode="edge")
    coarse = padded.reshape(padded.shape[0] // f, f, padded.shape[1] // f, f).mean(axis=(1, 3))
    coarse = ndimage.gaussian_filter(coarse, sigma_px / f, mode="nearest")
    # bilinear interpolation back, separable: two small dense matrices
    out = _interp_matrix(rows + m, f, coarse.shape[0]) @ coarse @ _interp_matrix(cols + m, f, coarse.shape[1]).T
    return out[m:, m:]


def _interp_matrix(n, f, m):
    """(n, m) linear interpolation from m cells of f pixels (centres at (i + 0.5) f - 0.5) to n
    pixels, clamped at the ends."""
    x = np.clip((np.arange(n) + 0.5) / f - 0.5, 0, m - 1)
    i0 = np.minimum(np.floor(x).astype(int), m - 2) if m > 1 else np.zeros(n, int)
    t = x - i0
    W = np.zeros((n, m))
    W[np.arange(n), i0] = 1 - t
    if m > 1:
        W[np.arange(n), i0 + 1] += t
    return W


def scatter(line_integral, fraction, sigma_mm, pixel_size_mm, reference_line_integral):
    """``-ln(P + fraction * G * (P L) / L_ref)``: scatter, a smooth additive term.

    Scatter is made where photons interact, in proportion to the primary times the line
    integral (``P L``, the first-order single-scatter amplitude of the scatter-kernel models;
    zero in air), and spread by a wide Gaussian ``G`` (``sigma_mm``). ``fraction`` is the
    scatter-to-primary ratio deep inside a large uniform slab of line integral
    ``reference_line_integral``; thinner parts scatter less."""
    L = np.asarray(line_integral, float)
    P = np.exp(-L)
    return -np.log(P + fraction / reference_line_integral * _gauss(P * L, sigma_mm / pixel_size_mm))


def blur(line_integral, sigma_mm, pixel_size_mm):
    """The detector's point spread (Gaussian, ``sigma_mm``) applied to the intensity."""
    P = np.exp(-np.asarray(line_integral, float))
    return -np.log(_gauss(P, sigma_mm / pixel_size_mm))


def chain(beam=monochromatic, *effects):
    """An ``image_model(lengths, mu)`` for :func:`sim.study.image_pair`: the beam, then each
    ``effect(line_integral) -> line_integral`` in turn."""

    def model(lengths, mu):
        L = beam(lengths, mu)
        for f in effects:
            L = f(L)
        return L

    return model


def tube(kv: float, anode: str, match_mm: float) -> Polychromatic:
    """The polychromatic beam of a scene's tube: ``anode`` ``Mo`` (a mammography tube: 30 um Mo
    filter) or ``W`` (the L8121-01: 150 um Be window), ``auto`` being Mo up to 35 kV; 500 mm
    of air; matched at ``match_mm`` of background. Cached: SpekPy takes a fraction of a second."""
    from sim.scene import anode_for

    return _tube(float(kv), anode_for(kv, anode), float(match_mm))


@lru_cache(maxsize=8)
def _tube(kv, anode, match_mm):
    filters = (("Be", 0.15), ("Mo", 0.03), ("Air", 500.0)) if anode == "Mo" else (("Be", 0.15), ("Air", 500.0))
    return Polychromatic(kv, anode, filters=filters, match_mm=match_mm)


def match_thickness_mm(scene) -> float:
    """The background thickness the polychromatic beam is matched at and scatter's reference slab:
    the undeformed body's extent along the beam, the longest chord a ray of the view crosses (to
    the cone beam's obliquity: 0.2 % for ``pva-phantom``). Through the plates the plate gap; from
    the side the body's width across the beam: the pva-phantom's 50 mm top face, not its 60 mm
    height, which no side ray crosses."""
    return 2 * scene.body.half_extent_mm(scene.beam.direction)


def for_scene(scene, pixel_size_mm: float):
    """The image model ``model(lengths, mu) -> -ln(I/I0)`` of ``scene.imaging`` on pixels of
    ``pixel_size_mm`` (see :class:`sim.scene.Imaging`): the beam, then scatter, then blur; both
    referred to :func:`match_thickness_mm` of background."""
    im = scene.imaging
    thickness = match_thickness_mm(scene)
    beam = monochromatic if im.beam == "monochromatic" else tube(scene.exposure.voltage_kv, im.anode, thickness)
    effects = []
    if im.scatter_fraction > 0:
        l_ref = scene.body.material.attenuation_per_mm * thickness
        effects.append(lambda L: scatter(L, im.scatter_fraction, im.scatter_sigma_mm, pixel_size_mm, l_ref))
    if im.blur_sigma_mm > 0:
        effects.append(lambda L: blur(L, im.blur_sigma_mm, pixel_size_mm))
    return chain(beam, *effects)
