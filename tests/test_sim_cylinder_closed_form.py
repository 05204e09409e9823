"""A homogeneous cylinder between frictionless plates, in the axisymmetric model, against closed forms.

The block's closed forms are checked in 3-D and plane strain (tests/test_audit_mechanics.py,
tests/test_sim_mechanics.py); the axisymmetric model, the one the pva-phantom and every centred
cylinder or cone runs in, was checked only against the 3-D model (within 1 %). Its own terms
(the hoop stretch ``1 + u_r / r``, the ``2 pi r`` weights of volume and force) meet a closed form
here. A cylinder of radius ``R`` and height ``H``, its flat faces on frictionless plates, deforms
homogeneously: ``r -> t r``, ``y -> s y`` (plus a rigid shift along y: which plate moves),
``s = 1 - ratio``. Written from FEBio's neo-Hookean energy, apart from ``sim``'s own
``uniaxial_block_force``: the Cauchy stress is ``sigma = mu (B - I) / J + lambda ln J I / J``, so
free sides need ``mu (t^2 - 1) + lambda ln(s t^2) = 0`` and the plate force is ``|sigma_yy|`` on
the deformed area ``pi (t R)^2``, i.e. ``mu pi R^2 (t^2 - s^2) / s`` once ``lambda ln J`` is
eliminated. Quadratic elements hold the homogeneous field exactly on any mesh, so the only error
left is the Newton solve's (relative 1e-6) and the revolution's polygon (``revolve_tol``).

The compressed cylinder's projection is then that of a cylinder of radius ``t R`` and height
``s H``: from the side (parallel) the chord ``2 sqrt((t R)^2 - u^2)``, through the plates ``s H``
inside the disc of radius ``t R``, and in the cone beam the closed-form ray chords of that cylinder.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from sim.mechanics import compress
from sim.scene import Beam, Body, Compression, Material, MeshSpec, Scene
from sim.xray import Geometry, path_lengths

R_MM, H_MM, E_KPA = 10.0, 16.0, 5.0
SOLVER_RTOL = 1e-6
REVOLVE_TOL = 1e-5  # sim.xray's default: the revolved polygon lies within r (1 - 1e-5) .. r


def _moduli(E_kpa, nu):
    """(mu, lambda) in MPa (N/mm^2)."""
    return E_kpa / (2 * (1 + nu)) * 1e-3, E_kpa * nu / ((1 + nu) * (1 - 2 * nu)) * 1e-3


def _lateral_stretch(s, nu):
    mu, lam = _moduli(E_KPA, nu)
    return brentq(lambda t: mu * (t * t - 1) + lam * math.log(s * t * t), 1.0, 1.0 / s, xtol=1e-15)


@pytest.fixture(scope="module", params=[0.45, 0.495])
def cylinder(request):
    nu = request.param
    gel = Material("gel", "neo-hookean", E_kpa=E_KPA, nu=nu, attenuation_per_cm=0.77)
    scene = Scene(
        name="cylinder",
        body=Body("cylinder", height_mm=H_MM, diameter_mm=2 * R_MM, material=gel),
        compression=Compression((0.1, 0.25)),
        beam=Beam("parallel", "z"),
        # elements as large as the body: the field is affine, which P2 holds exactly on any mesh
        mesh=MeshSpec(R_MM, R_MM, "axisymmetric", True),
    )
    states = compress(scene, progress=False)
    assert states[0].solver.fem.model == "axisymmetric"
    return nu, states


def _affine_fit(state):
    """The vertices' motion as ``r -> a_r r``, ``y -> a_y y + b``: the fit and its largest residual."""
    fem = state.solver.projection_mesh or state.solver.fem
    n = fem.points.shape[1]
    X = fem.points
    x = X + state.displacement[:, :n]
    a_r = float(np.sum(x[0] * X[0]) / np.sum(X[0] * X[0]))  # r = 0 stays on the axis
    A = np.c_[X[1], np.ones(n)]
    (a_y, b), *_ = np.linalg.lstsq(A, x[1], rcond=None)
    residual = max(np.abs(x[0] - a_r * X[0]).max(), np.abs(x[1] - A @ (a_y, b)).max())
    return a_r, float(a_y), float(b), float(residual), fem


def test_the_cylinders_force_volume_and_radius_are_the_closed_form(cylinder):
    nu, states = cylinder
    mu, _ = _moduli(E_KPA, nu)
    for st in states:
        s = 1 - st.ratio
        t = _lateral_stretch(s, nu)
        assert st.gap_mm == pytest.approx(s * H_MM, rel=1e-12)
        assert st.plate_force_n == pytest.approx(mu * math.pi * R_MM**2 * (t * t - s * s) / s, rel=SOLVER_RTOL)
        assert st.volume_ratio == pytest.approx(s * t * t, rel=SOLVER_RTOL)
        a_r, a_y, _, residual, _ = _affine_fit(st)
        assert residual < SOLVER_RTOL * R_MM  # homogeneous: every vertex on the affine map
        assert a_r == pytest.approx(t, rel=SOLVER_RTOL)  # the radius grows by t, the same at every r
        assert a_y == pytest.approx(s, rel=SOLVER_RTOL)
        # nearly incompressible: t -> s^-1/2, the volume's loss (1 - 2 nu) |ln s| / (1 + ...) apart
        assert t == pytest.approx(s**-0.5, rel=(1 - 2 * nu) * abs(math.log(s)))


def _ray_cylinder_chord(origin, direction, radius, y_lo, y_hi):
    """Closed form: length of lines inside ``x^2 + z^2 <= radius^2, y_lo <= y <= y_hi`` (the line's
    interval inside the circle, a quadratic, intersected with the slab's)."""
    o, d = origin, direction
    a = d[0] ** 2 + d[2] ** 2
    b = o[0] * d[0] + o[2] * d[2]
    c = o[0] ** 2 + o[2] ** 2 - radius**2
    disc = b * b - a * c
    root = np.sqrt(np.clip(disc, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_in = np.where(a > 0, (-b - root) / a, np.where(c <= 0, -np.inf, np.inf))
        t_out = np.where(a > 0, (-b + root) / a, np.where(c <= 0, np.inf, -np.inf))
        y0, y1 = (y_lo - o[1]) / d[1], (y_hi - o[1]) / d[1]
    # a line across the axis (d_y = 0): all of it in the slab, or none (an empty interval)
    y0 = np.where(d[1] == 0, np.where((o[1] >= y_lo) & (o[1] <= y_hi), -np.inf, np.inf), y0)
    y1 = np.where(d[1] == 0, np.inf, y1)
    lo = np.maximum(t_in, np.minimum(y0, y1))
    hi = np.minimum(t_out, np.maximum(y0, y1))
    return np.clip(hi - lo, 0.0, None) * np.sqrt(np.sum(d * d, axis=0))


@pytest.mark.parametrize(
    "kind, direction", [("parallel", "z"), ("parallel", "y"), ("cone", "z"), ("cone", "y")], ids=str
)
def test_the_compressed_cylinder_projects_to_the_stretched_cylinders_chords(cylinder, kind, direction):
    """Every pixel of the most compressed state between the chords of the cylinders of radius
    ``t R`` and ``t R (1 - revolve_tol)`` (the revolved polygon is inscribed), height ``s H``
    about where the vertices' fit puts the centre; well inside (0.8 of the radius from the axis,
    a pixel off the flat faces) within 1e-4 relative. From the side in parallel the chord is
    ``2 sqrt((t R)^2 - u^2)`` and the shadow ``s H`` tall and ``2 t R`` wide: pixel centres within
    those, to a pixel."""
    nu, states = cylinder
    st = states[-1]
    s, t = 1 - st.ratio, _lateral_stretch(1 - st.ratio, nu)
    _, _, b, _, fem = _affine_fit(st)
    p = 0.4
    g = Geometry(kind, direction, (70, 74), p, (0.0, 0.0, 0.0), 60.0, 30.0)
    L = path_lengths(fem, g, st.displacement, revolve_tol=REVOLVE_TOL)[0]
    o, d = g.rays()
    y_lo, y_hi = b - s * H_MM / 2, b + s * H_MM / 2
    outer = _ray_cylinder_chord(o, d, t * R_MM, y_lo, y_hi)
    inner = _ray_cylinder_chord(o, d, t * R_MM * (1 - REVOLVE_TOL), y_lo, y_hi)
    tol = 1e-6 * s * H_MM  # the solve's tolerance on the vertices, and rounding
    assert np.all((L >= inner - tol) & (L <= outer + tol)), (kind, direction)
    assert np.all(L[outer == 0] == 0.0)
    if direction == "z":  # side: rays 0.8 of the radius from the axis, entering and leaving
        # through the curved wall (its chord is the infinite cylinder's): there a radial error of
        # revolve_tol r changes the chord by at most revolve_tol r^2 / (r^2 - rho^2), 2.8e-5
        rho = np.abs(o[0] * d[2] - o[2] * d[0]) / np.hypot(d[0], d[2])
        wall = _ray_cylinder_chord(o, d, t * R_MM, -np.inf, np.inf)
        well = (rho <= 0.8 * t * R_MM) & (outer >= wall * (1 - 1e-12))
    else:  # through the plates: rays through both flat faces, 0.8 of the radius from the rim
        ends = (np.array([y_lo, y_hi])[:, None, None] - o[1]) / d[1]
        well = np.all(np.hypot(o[0] + ends * d[0], o[2] + ends * d[2]) <= 0.8 * t * R_MM, axis=0)
    assert well.sum() > 500
    assert np.max(np.abs(L[well] / outer[well] - 1)) < 1e-4
    if kind == "parallel":
        u = (np.arange(74) - 36.5) * p
        v = (34.5 - np.arange(70)) * p
        cols = np.count_nonzero(L.max(axis=0) > 0)
        assert abs(cols - 2 * t * R_MM / p) <= 1
        if direction == "z":
            rows = np.count_nonzero(L.max(axis=1) > 0)
            assert abs(rows - s * H_MM / p) <= 1
            centre_row = int(np.argmin(np.abs(v - b)))
            expected = 2 * np.sqrt(np.clip((t * R_MM) ** 2 - u**2, 0, None))
            inside = np.abs(u) <= 0.8 * t * R_MM
            np.testing.assert_allclose(L[centre_row][inside], expected[inside], rtol=1e-4)
        else:
            disc = np.hypot(u[None, :], v[:, None]) <= 0.8 * t * R_MM
            np.testing.assert_allclose(L[disc], s * H_MM, rtol=1e-9)
