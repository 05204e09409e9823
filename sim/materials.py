"""Choosing hyperelastic parameters from measured stiffness ranges.

Gels are usually characterised by a Young's modulus that changes with strain ("E 20-30 kPa over
0-20 % strain"). For FEBio's neo-Hookean energy, nearly incompressible, the nominal stress in
uniaxial compression to stretch ``s = 1 - strain`` is ``P = mu (s - s^-2)`` (incompressible
limit), so the tangent modulus is

    E_t(strain) = dP/d(strain) = mu (1 + 2 s^-3) = E0 (1 + 2 s^-3) / 3,

rising by a factor 1.64 between 0 and 20 % strain whatever ``E0 = 3 mu``. :func:`fit_neo_hookean`
picks the ``E0`` whose tangent modulus is closest, in the log (relative) least-squares sense, to
a modulus rising linearly across a strain range, and reports the worst relative misfit. A
neo-Hookean solid cannot follow a steeper stiffening (the 20 % w/v inclusion's 100 -> 250 kPa,
a factor 2.5); a Yeoh or Ogden term would, and is left out until a measurement needs it: the
inclusion's own strain stays below about 10 % in the phantom (see ``State.inclusion_strain``),
where the fit's misfit is what :func:`fit_neo_hookean` reports.

>>> E0, misfit = fit_neo_hookean((0.0, 0.2), (20.0, 30.0))
>>> round(E0, 1), round(misfit, 3)
(19.7, 0.075)
"""

from __future__ import annotations

import numpy as np

__all__ = ["neo_hookean_tangent_modulus", "fit_neo_hookean"]


def neo_hookean_tangent_modulus(E0_kpa, strain):
    """Tangent modulus (kPa) in uniaxial compression at ``strain`` of an incompressible neo-Hookean
    solid whose small-strain Young's modulus is ``E0_kpa``."""
    s = 1.0 - np.asarray(strain, dtype=float)
    if np.any(s <= 0):
        raise ValueError("strain must be below 1")
    return E0_kpa * (1.0 + 2.0 * s**-3) / 3.0


def fit_neo_hookean(strain_range, modulus_range_kpa, n=41) -> tuple[float, float]:
    """Small-strain Young's modulus ``E0`` (kPa) of the neo-Hookean solid closest to a tangent
    modulus rising linearly from ``modulus_range_kpa[0]`` to ``[1]`` across ``strain_range``, and
    the largest relative misfit over the range.

    The log least-squares optimum has a closed form: ``ln E0`` is the mean of
    ``ln(E_target / f)`` with ``f = E_t / E0``.
    """
    (e0, e1), (m0, m1) = strain_range, modulus_range_kpa
    if not (0 <= e0 < e1 < 1) or m0 <= 0 or m1 <= 0:
        raise ValueError(
            f"need 0 <= strain_range[0] < strain_range[1] < 1 and positive moduli, "
            f"got {strain_range}, {modulus_range_kpa}"
        )
    strain = np.linspace(e0, e1, n)
    target = m0 + (m1 - m0) * (strain - e0) / (e1 - e0)
    shape = neo_hookean_tangent_modulus(1.0, strain)
    E0 = float(np.exp(np.mean(np.log(target / shape))))
    misfit = float(np.max(np.abs(E0 * shape / target - 1.0)))
    return E0, misfit
