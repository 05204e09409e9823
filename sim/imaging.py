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
polychromatic transmission through the body's own undeformed thickness ``match_mm`` equals the
monochromatic one: the scene's coefficients stay the effective ones where they were measured,
and what changes is only beam hardening (the effective coefficient falling with depth). The
detector integrates energy (a CsI scintillator absorbing everything: weight ``E * fluence``).

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

import numpy as np

__all__ = ["monochromatic", "Polychromatic", "scatter", "blur", "chain"]


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
        mu_water = np.array([xraydb.material_mu("H2O", e * 1e3, density=1.0) for e in self.energies_kev])  # 1/cm
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
        return float(brentq(lambda a: -np.log(self._transmission(target, a)) - target, 1e-6, 1e3, xtol=1e-12))

    def __call__(self, lengths, mu_per_mm):
        mono = monochromatic(lengths, mu_per_mm)
        return -np.log(self._transmission(mono, self.scale_for(float(mu_per_mm[0]))))


def _gauss(image, sigma_px):
    from scipy import ndimage

    return ndimage.gaussian_filter(image, sigma_px, mode="nearest") if sigma_px > 0 else image


def scatter(line_integral, fraction, sigma_mm, pixel_mm, reference_line_integral):
    """``-ln(P + fraction * G * (P L) / L_ref)``: scatter, a smooth additive term.

    Scatter is made where photons interact, in proportion to the primary times the line
    integral (``P L``, the first-order single-scatter amplitude of the scatter-kernel models;
    zero in air), and spread by a wide Gaussian ``G`` (``sigma_mm``). ``fraction`` is the
    scatter-to-primary ratio deep inside a large uniform slab of line integral
    ``reference_line_integral``; thinner parts scatter less."""
    L = np.asarray(line_integral, float)
    P = np.exp(-L)
    return -np.log(P + fraction / reference_line_integral * _gauss(P * L, sigma_mm / pixel_mm))


def blur(line_integral, sigma_mm, pixel_mm):
    """The detector's point spread (Gaussian, ``sigma_mm``) applied to the intensity."""
    P = np.exp(-np.asarray(line_integral, float))
    return -np.log(_gauss(P, sigma_mm / pixel_mm))


def chain(beam=monochromatic, *effects):
    """An ``image_model(lengths, mu)`` for :func:`sim.study.image_pair`: the beam, then each
    ``effect(line_integral) -> line_integral`` in turn."""
    def model(lengths, mu):
        L = beam(lengths, mu)
        for f in effects:
            L = f(L)
        return L
    return model
