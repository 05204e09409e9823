"""Closed-form audit of the exact projector (``sim.xray``) and the polychromatic beam (``sim.imaging``).

The closed forms, written down before the project's own tests were read (session 33's audit):

- a ray's chord through an axis-aligned box is ``max(0, min_k t_hi,k - max_k t_lo,k)`` (slab
  method), through a ball ``2 sqrt(R^2 - d^2)`` with ``d`` the distance from its centre to the
  line; the line integral is ``mu`` times the chord (Beer-Lambert, monochromatic);
- a cone beam (source ``s`` before the isocentre, detector ``d`` behind it) magnifies by
  ``M = (s + d) / s`` at the isocentre: a ball of radius ``R`` centred there casts a disc of
  radius ``(s + d) R / sqrt(s^2 - R^2)`` (the tangent cone's half-angle is ``asin(R / s)``), and
  the ray through a small ball's centre at ``(x0, 0, z0)`` (beam along y) lands at ``M x0``
  (columns along +x) and ``M z0`` (rows along -z: row 0 at the top);
- a focal spot of size ``f`` blurs an edge at ``s'`` from it by ``f ((s + d) / s' - 1)``;
- polychromatic: ``T(x) = sum_E w_E exp(-a shape_E x)``, matched to Beer-Lambert at ``match_mm``,
  with ``-ln T / x`` falling with ``x`` (beam hardening).

Already covered elsewhere: the one-energy (Beer-Lambert) limit, the tube spectrum's hardening,
scatter's ratio in a uniform slab and the blur's MTF (tests/test_sim_imaging.py), chords of
spheres and ellipsoids (tests/test_sim_xray.py), a thin square's magnification
(tests/test_sim_physics_closed_form.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.imaging import Polychromatic
from sim.mesh import build_mesh
from sim.scene import Body, Material, MeshSpec, Scene, load_scene
from sim.xray import Geometry, path_lengths

# the largest focal spot of the L8121 (../shared/hardware/L8121.md: "about 5-50 um")
_L8121_LARGEST_SPOT_MM = 0.05


def _ray_box(origin, direction, half):
    """Slab method: the chord of lines (3, ...) through the box ``|X_k| <= half_k``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-np.asarray(half)[:, None, None] - origin) / direction
        t2 = (np.asarray(half)[:, None, None] - origin) / direction
    lo = np.where(direction == 0, np.where(np.abs(origin) <= np.asarray(half)[:, None, None], -np.inf, np.inf), t1)
    hi = np.where(direction == 0, np.where(np.abs(origin) <= np.asarray(half)[:, None, None], np.inf, -np.inf), t2)
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    length = hi.min(axis=0) - lo.max(axis=0)
    return np.clip(length, 0.0, None) * np.sqrt((direction**2).sum(axis=0))


def _ray_ball(origin, direction, radius, centre):
    d = direction / np.sqrt((direction**2).sum(axis=0))
    w = origin - np.asarray(centre, float)[:, None, None]
    w = w - (w * d).sum(axis=0) * d
    return 2.0 * np.sqrt(np.clip(radius**2 - (w * w).sum(axis=0), 0.0, None))


def _box_mesh(size):
    sc = Scene(body=Body("box", size_mm=size, material=Material(E_kpa=5.0, nu=0.45)), mesh=MeshSpec(4.0, 4.0, "3d"))
    return build_mesh(sc)


def _ball_mesh(radius, h):
    body = Body("ellipsoid", semi_axes_mm=(radius,) * 3, material=Material(E_kpa=5.0, nu=0.45))
    return build_mesh(Scene(body=body, mesh=MeshSpec(h, h, "3d")))


@pytest.fixture(scope="module")
def ball6():
    """A ball of radius 6 mm in 1 mm elements (gmsh takes a second: built once)."""
    return _ball_mesh(6.0, 1.0)


@pytest.fixture(scope="module")
def ball2():
    return _ball_mesh(2.0, 0.5)


def _sag(fem, radius):
    """The deepest a face of the inscribed polyhedron lies inside the ball: ``R`` minus the
    distance of its plane from the centre (gmsh puts the surface vertices on the sphere)."""
    from sim.xray import surface_of

    surf = surface_of(fem)
    X = surf.vertices(np.asarray(fem.points, float))
    a, b, c = (X[:, surf.faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a, axis=0)
    n /= np.linalg.norm(n, axis=0)
    return float(radius - np.abs((n * a).sum(axis=0)).min())


def test_cone_beam_chords_of_a_box_are_the_slab_method_chords_to_rounding():
    # a polyhedron is rendered exactly (the module's claim): an off-centre box, 45 x 33 pixels
    # seen from 80 mm at 3x magnification, every ray against the slab method
    size = (10.0, 6.0, 8.0)
    g = Geometry("cone", "y", (33, 45), 0.5, (0.0, 0.0, 0.0), 80.0, 160.0)
    lengths = path_lengths(_box_mesh(size), g)[0]
    origin, direction = g.rays()
    expected = _ray_box(origin, direction, np.array(size) / 2)
    assert np.count_nonzero(expected) > 200
    np.testing.assert_allclose(lengths, expected, rtol=0, atol=1e-9)


def test_a_ball_projects_to_its_chords_within_the_polyhedrons_sag(ball6):
    # parallel and cone beams: the mesh is a polyhedron inscribed in the ball, so its chord lies
    # between the ball's of radius R and of radius R - sag (the deepest face), pixel by pixel
    R, fem = 6.0, ball6
    sag = _sag(fem, R)
    assert 0 < sag < 0.05  # about h^2 / (6 R) for 1 mm faces
    for g in (
        Geometry("parallel", "y", (31, 31), 0.4),
        Geometry("cone", "y", (41, 41), 0.4, (0.0, 0.0, 0.0), 60.0, 30.0),
    ):
        got = path_lengths(fem, g)[0]
        origin, direction = g.rays()
        outer = _ray_ball(origin, direction, R, (0, 0, 0))
        inner = _ray_ball(origin, direction, R - sag, (0, 0, 0))
        assert np.all(got <= outer + 1e-9) and np.all(got >= inner - 1e-9)
        centre = np.unravel_index(np.argmax(outer), outer.shape)
        assert got[centre] == pytest.approx(2 * R, abs=2 * sag)


def test_cone_beam_shadow_of_a_ball_is_magnified_by_the_tangent_cone(ball6):
    # M = SID / SOD at the isocentre; the silhouette's radius is SID R / sqrt(SOD^2 - R^2) exactly
    R, s, d, p = 6.0, 50.0, 100.0, 0.25
    fem = ball6
    g = Geometry("cone", "y", (201, 201), p, (0.0, 0.0, 0.0), s, d)
    assert g.magnification == pytest.approx((s + d) / s)
    row = path_lengths(fem, g)[0][100]
    radius_px = (s + d) * R / math.sqrt(s * s - R * R) / p
    covered = np.count_nonzero(row > 0)
    # pixel centres inside the disc: 2 floor(r) + 1, less where the polyhedron's rim is inside it
    sag_px = (s + d) / (s - R) * _sag(fem, R) / p * 2  # the rim moved in by the sag, magnified
    assert 2 * math.floor(radius_px - sag_px) + 1 <= covered <= 2 * math.floor(radius_px) + 1
    assert covered > 2 * (s + d) / s * R / p  # wider than the isocentre's magnification alone


@pytest.mark.parametrize("x0, z0", [(8.0, 0.0), (0.0, 8.0), (-6.0, -4.0)])
def test_cone_beam_puts_an_off_axis_ball_where_its_centre_ray_lands(ball2, x0, z0):
    # the longest chord is the ray through the centre: at (M x0, M z0) on the detector,
    # columns along +x, rows along -z (row 0 at the top); half a pixel: the peak's sampling
    s, d, p, fem = 60.0, 60.0, 0.2, ball2
    # the isocentre moved by -(x0, 0, z0): the ball sits at (x0, 0, z0) relative to it
    g = Geometry("cone", "y", (241, 241), p, (-x0, 0.0, -z0), s, d)
    img = path_lengths(fem, g)[0]
    M = (s + d) / s
    weights = img**8  # the peak's neighbourhood: a sharp centroid of the chord map
    rows, cols = np.indices(img.shape)
    col = float((weights * cols).sum() / weights.sum())
    row = float((weights * rows).sum() / weights.sum())
    assert col == pytest.approx(120 + M * x0 / p, abs=0.5)
    assert row == pytest.approx(120 - M * z0 / p, abs=0.5)


def test_the_point_source_is_sharper_than_a_pixel_in_every_preset():
    # sim.xray models a point source. The L8121's largest spot (50 um) blurs an edge at s' from
    # it by f ((s + d) / s' - 1); for each preset's nearest body point that stays under half a
    # detector pixel, so the point source is the modelling choice, not an error
    for name in ("seed-breast", "pva-phantom"):
        sc = load_scene(name)
        if sc.beam.kind == "parallel":
            continue
        near = sc.beam.source_distance_mm - sc.body.half_extent_mm(sc.beam.direction)
        penumbra = _L8121_LARGEST_SPOT_MM * ((sc.beam.source_distance_mm + sc.beam.detector_distance_mm) / near - 1)
        assert penumbra < sc.detector.pixel_size_mm / 2, name


def _one_line(shape_values, weights, match_mm=50.0):
    """A Polychromatic of a hand-made spectrum (no SpekPy): ``shape`` and ``weights`` per line."""
    beam = Polychromatic.__new__(Polychromatic)
    beam.match_mm = match_mm
    beam.weights = np.asarray(weights, float) / np.sum(weights)
    beam.shape = np.asarray(shape_values, float)
    beam.energies_kev = np.arange(1.0, len(weights) + 1.0)
    return beam


def test_a_two_line_spectrum_matches_its_closed_form_and_the_match_thickness():
    # T(x) = w1 exp(-a s1 x) + w2 exp(-a s2 x), x the monochromatic line integral; a is chosen so
    # that T(mu_b match_mm) = exp(-mu_b match_mm); -ln T / x falls with x (beam hardening)
    w, shp = np.array([0.4, 0.6]), np.array([1.8, 0.4667])
    beam = _one_line(shp, w, match_mm=40.0)
    mu_b = 0.05
    a = beam.scale_for(mu_b)
    x_match = mu_b * 40.0
    assert -math.log(float(w @ np.exp(-a * shp * x_match))) == pytest.approx(x_match, rel=1e-9)
    lengths = np.zeros((1, 300, 300))
    lengths[0] = np.linspace(0, 120, 300 * 300).reshape(300, 300)  # the tabulated path
    got = beam(lengths, np.array([mu_b]))
    x = mu_b * lengths[0]
    closed = -np.log(w[0] * np.exp(-a * shp[0] * x) + w[1] * np.exp(-a * shp[1] * x))
    np.testing.assert_allclose(got, closed, rtol=1e-6, atol=1e-12)
    per_unit = closed.ravel()[1:] / x.ravel()[1:]
    assert np.all(np.diff(per_unit) < 0)
