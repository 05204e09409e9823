"""Closed-form audit of the mechanics (``sim.mechanics``), and of the projection and truth field of
its homogeneous solution (``sim.xray``, ``sim.truth``).

The closed forms, written down before the project's own tests were read (session 33's audit). A
block between frictionless plates, sides free, deforms homogeneously: ``F = diag(t, s, t)``, axial
stretch ``s = 1 - ratio``, lateral ``t``, ``J = s t^2``. Quadratic elements hold that field exactly,
so the finite elements must reproduce it to the solver's tolerance, whatever the mesh:

- FEBio's neo-Hookean, Cauchy stress ``sigma = mu (B - I) / J + lambda ln J I / J``: free sides
  need ``mu (t^2 - 1) + lambda ln J = 0``, and the plate force (Cauchy stress times the deformed
  area ``t^2 A``) is ``mu A (s^2 - t^2) / s`` once ``lambda ln J`` is eliminated;
- incompressible limit ``t^2 = 1 / s``: ``F = mu A (1 / s^2 - s)``, so the small-strain modulus is
  ``3 mu`` (``F / (A e) = 3 mu (1 + e + ...)``);
- ANSYS's uncoupled form, ``sigma = mu dev(J^-2/3 B) / J + kappa (J - 1) I``: free sides need
  ``mu J^-5/3 (t^2 - s^2) / 3 + kappa (J - 1) = 0`` and ``F = mu J^-5/3 (s^2 - t^2) t^2 A``;
- St Venant-Kirchhoff in uniaxial stress: ``S = E E_yy`` for any ``nu`` (``E_xx = -nu E_yy``),
  so ``P = E s (s^2 - 1) / 2`` and ``t^2 = 1 - nu (s^2 - 1)``;
- the block's projection: through the plates every column is ``s a`` long over a ``t a`` square,
  from the side ``t a`` long over a ``t a`` by ``s a`` rectangle; the pull field registering one
  state onto another is affine, ``d = (x - centre) (t_mov / t_ref - 1)`` across the compression
  axis and ``(x - centre) (s_mov / s_ref - 1)`` along it.

Already covered elsewhere, against the code's own ``uniaxial_block_force``: the block's force
(tests/test_sim_mechanics.py), SVK's limit point, the Eshelby inclusion, Hertz contact and mesh
convergence (tests/test_mechanics_closed_form.py); the force here is the Cauchy-stress form,
derived apart from that function.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage
from scipy.optimize import brentq

from sim.mechanics import compress
from sim.scene import Material, block_scene
from sim.truth import truth_displacement
from sim.xray import Geometry, path_lengths

A_MM, E_KPA = 10.0, 5.0
AREA = A_MM * A_MM
# Newton's tolerance on a field the elements hold exactly: the only error left
SOLVER_RTOL = 1e-6


def _moduli(E_kpa, nu):
    """(mu, lambda, kappa) in MPa."""
    mu = E_kpa / (2 * (1 + nu)) * 1e-3
    lam = E_kpa * nu / ((1 + nu) * (1 - 2 * nu)) * 1e-3
    return mu, lam, lam + 2 * mu / 3


def _block(model, nu, ratios):
    sc = block_scene(A_MM, E_KPA, nu, ratios)
    sc.body = dataclasses.replace(sc.body, material=Material("block", model, E_kpa=E_KPA, nu=nu))
    return sc, compress(sc)


@pytest.fixture(scope="module")
def gel_block():
    """The paper's gel (nu = 0.495) at 15, 20 and 25 %."""
    return _block("neo-hookean", 0.495, (0.15, 0.20, 0.25))


def test_neo_hookean_block_force_and_volume_are_the_cauchy_closed_form(gel_block):
    _, states = gel_block
    mu, lam, _ = _moduli(E_KPA, 0.495)
    for st in states:
        s = 1 - st.ratio
        t = brentq(lambda t, s=s: mu * (t * t - 1) + lam * math.log(s * t * t), 1.0, 2.0, xtol=1e-15)
        assert st.plate_force_n == pytest.approx(mu * AREA * (t * t - s * s) / s, rel=SOLVER_RTOL)
        assert st.volume_ratio == pytest.approx(s * t * t, rel=SOLVER_RTOL)
        assert st.gap_mm == pytest.approx(s * A_MM, rel=1e-12)


def test_nearly_incompressible_block_has_modulus_three_mu_and_the_incompressible_force():
    # nu = 0.4999 (lambda / mu = 5000): the incompressible forms hold to O(mu / lambda) = 2e-4
    nu = 0.4999
    mu, lam, _ = _moduli(E_KPA, nu)
    _, (small, large) = _block("neo-hookean", nu, (0.001, 0.25))
    e = small.ratio
    # F / (A e) = 3 mu (1 + e + ...): the next term and the compressibility bound the difference
    assert small.plate_force_n / (AREA * e) == pytest.approx(3 * mu, rel=1.5 * e + 3 * mu / lam)
    s = 1 - large.ratio
    assert large.plate_force_n == pytest.approx(mu * AREA * (1 / s**2 - s), rel=3 * mu / lam)
    assert large.volume_ratio == pytest.approx(1.0, abs=3 * mu / lam)


def test_uncoupled_neo_hookean_block_is_its_closed_form():
    nu = 0.45
    mu, _, kappa = _moduli(E_KPA, nu)
    _, states = _block("neo-hookean-uncoupled", nu, (0.1, 0.3))
    for st in states:
        s = 1 - st.ratio

        def sides(t, s=s):
            J = s * t * t
            return mu * J ** (-5 / 3) * (t * t - s * s) / 3 + kappa * (J - 1)

        t = brentq(sides, 1.0, 2.0, xtol=1e-15)
        J = s * t * t
        assert st.plate_force_n == pytest.approx(mu * J ** (-5 / 3) * (t * t - s * s) * t * t * AREA, rel=SOLVER_RTOL)
        assert st.volume_ratio == pytest.approx(J, rel=SOLVER_RTOL)


def test_st_venant_kirchhoff_block_is_hooke_on_the_green_strain():
    nu = 0.3
    _, states = _block("linear", nu, (0.1, 0.3))
    for st in states:
        s = 1 - st.ratio
        assert st.plate_force_n == pytest.approx(E_KPA * 1e-3 * s * (1 - s * s) / 2 * AREA, rel=SOLVER_RTOL)
        assert st.volume_ratio == pytest.approx(s * (1 - nu * (s * s - 1)), rel=SOLVER_RTOL)


def _lateral(state):
    return math.sqrt(state.volume_ratio / (1 - state.ratio))


def _interior(img, erode=2):
    return ndimage.binary_erosion(img > 0, iterations=erode)


@pytest.mark.parametrize("beam", ["y", "z"])
def test_projection_of_the_compressed_block_is_its_stretched_box(gel_block, beam):
    # 0.2 mm pixels: the shadow's width is its length over the pitch, to one pixel centre either side
    sc, states = gel_block
    st = states[-1]
    s, t = 1 - st.ratio, _lateral(st)
    g = Geometry("parallel", beam, (81, 81), 0.2)
    L = path_lengths(st.solver.projection_mesh, g, st.displacement)[0]
    depth, height = (s * A_MM, t * A_MM) if beam == "y" else (t * A_MM, s * A_MM)
    np.testing.assert_allclose(L[_interior(L)], depth, rtol=1e-9)
    rows, cols = np.count_nonzero(L[:, 40]), np.count_nonzero(L[40])
    assert abs(cols - t * A_MM / 0.2) <= 1 and abs(rows - height / 0.2) <= 1


@pytest.mark.parametrize("beam", ["y", "z"])
def test_truth_field_of_the_homogeneous_block_is_affine(gel_block, beam):
    sc, states = gel_block
    moving, reference = states[1], states[2]
    g = Geometry("parallel", beam, (81, 81), 0.2)
    d = truth_displacement(sc, reference, moving, geometry=g, factor=1)
    across = _lateral(moving) / _lateral(reference) - 1
    along = (1 - moving.ratio) / (1 - reference.ratio) - 1
    i, j = np.indices(g.shape) - 40.0
    row_rate = across if beam == "y" else along  # rows are z through the plates, y from the side
    inside = _interior(path_lengths(reference.solver.projection_mesh, g, reference.displacement)[0])
    np.testing.assert_allclose(d[0][inside], (i * row_rate)[inside], atol=1e-4)
    np.testing.assert_allclose(d[1][inside], (j * across)[inside], atol=1e-4)
