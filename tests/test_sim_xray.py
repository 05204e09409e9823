"""Exact X-ray path lengths through the deformed mesh (issue 3, point 5), checked against closed forms.

Two kinds of reference:

- polyhedra (tetrahedral boxes, affinely deformed boxes, rotated convex polyhedra): the projector
  must reproduce their exact chords to rounding, whatever the pixel grid (centres on edges and
  vertices included). Convex polyhedra are checked against a brute-force half-space clipping of
  each ray.
- curved bodies (spheres, ellipsoids, bodies of revolution): the mesh is an inscribed polyhedron
  whose faces lie within ``delta`` of the true surface. It contains the body shrunk by
  ``(1 - delta / R)`` and lies inside the body, so every chord must fall between the two analytic
  chords (checked on every pixel); on pixels at most ``0.8 R`` from the centre that sandwich is
  narrower than ``1e-4`` relative (``delta R / (R^2 - rho^2) <= delta / (0.36 R)``; the level-7
  icosphere has ``delta / R = 1.8e-5``, so at most 5e-5), and the relative error against the analytic chord must be
  below ``1e-4`` there, as the issue asks.
"""

import doctest
import types

import numpy as np
import pytest

import sim.analytic
import sim.xray
from sim.analytic import ellipsoid_chord, ray_ellipsoid_chord, ray_sphere_chord, sphere_chord
from sim.mesh import FEMesh
from sim.xray import Geometry, line_integral, path_lengths, project, render, surface_of

KUHN = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


# -- meshes -------------------------------------------------------------------------------------
def grid_mesh(lo, hi, n, region_of=None, symmetry=()):
    """A box [lo, hi] of n[0] x n[1] x n[2] cubes, 6 conforming (Kuhn) tetrahedra each; the region
    of each cube from ``region_of(centre)``."""
    axes = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij")).reshape(3, -1)
    idx = np.arange(P.shape[1]).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    corners = np.stack(
        [idx[a : a + n[0], b : b + n[1], c : c + n[2]].ravel() for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=1
    )  # (cubes, 8): 4a + 2b + c
    tets = corners[:, KUHN].reshape(-1, 4)
    region = np.zeros(len(corners), int) if region_of is None else region_of(P[:, corners].mean(axis=2)).astype(int)
    region = np.repeat(region, len(KUHN))
    return FEMesh(P, tets.T.copy(), region, "3d", tuple(symmetry))


def grid_2d(lo, hi, n, region_of=None, model="axisymmetric", symmetry=()):
    axes = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(2)]
    P = np.stack(np.meshgrid(*axes, indexing="ij")).reshape(2, -1)
    idx = np.arange(P.shape[1]).reshape(n[0] + 1, n[1] + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    region = np.zeros(len(a), int) if region_of is None else region_of(P[:, [a, c]].mean(axis=1)).astype(int)
    region = np.tile(region, 2)
    return FEMesh(P, tri.T.copy(), region, model, tuple(symmetry))


def icosphere(level):
    """Unit icosphere: (3, n) vertices on the sphere, (m, 3) outward-oriented faces."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        float,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ]
    )
    v /= np.linalg.norm(v, axis=1)[:, None]
    for _ in range(level):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.ravel() + len(v)
        mid = v[ue[:, 0]] + v[ue[:, 1]]
        v = np.concatenate([v, mid / np.linalg.norm(mid, axis=1)[:, None]])
        m = len(f)
        ab, bc, ca = inv[:m], inv[m : 2 * m], inv[2 * m :]
        a, b, c = f.T
        f = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return v.T.copy(), f


def star_mesh(vertices, faces, centre):
    """Tetrahedra joining each face of a star-shaped closed surface to ``centre``."""
    P = np.concatenate([np.asarray(centre, float)[:, None], vertices], axis=1)
    cells = np.concatenate([np.zeros((len(faces), 1), int), faces + 1], axis=1)
    return FEMesh(P, cells.T.copy(), np.zeros(len(faces), int), "3d")


def face_planes(X, faces):
    """Outward unit normals (m, 3) and offsets (m,) of the faces' planes: n . x <= h inside."""
    a, b, c = (X[:, faces[:, i]].T for i in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    return n, np.einsum("ij,ij->i", n, a)


def convex_chord(normals, offsets, origins, directions):
    """Brute force: length of each line inside the convex polyhedron {n . x <= h}."""
    o = origins.reshape(3, -1).T
    d = directions.reshape(3, -1).T
    nd = d @ normals.T
    slack = offsets[None, :] - o @ normals.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = slack / nd
    t_in = np.where(nd < 0, t, -np.inf).max(axis=1)
    t_out = np.where(nd > 0, t, np.inf).min(axis=1)
    parallel_out = ((nd == 0) & (slack < 0)).any(axis=1)
    L = np.where(parallel_out, 0.0, np.clip(t_out - t_in, 0.0, None)) * np.linalg.norm(d, axis=1)
    return L.reshape(origins.shape[1:])


def surface_xyz(fem):
    """World vertices and faces of an undeformed mesh's region boundaries."""
    s = surface_of(fem)
    return s.vertices(fem.points), s.faces


def box_planes(lo, hi):
    """Half-spaces of an axis-aligned box."""
    n = np.concatenate([-np.eye(3), np.eye(3)])
    return n, np.concatenate([-np.asarray(lo, float), np.asarray(hi, float)])


def assert_closed(surf):
    """Every region's boundary is closed and consistently oriented: each directed edge of a face
    is matched by the reverse edge of another."""
    for m in range(surf.n_regions):
        f = np.concatenate([surf.faces[surf.inside == m], surf.faces[surf.outside == m][:, ::-1]])
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).astype(np.int64)
        n = int(e.max()) + 1
        fwd, rev = np.sort(e[:, 0] * n + e[:, 1]), np.sort(e[:, 1] * n + e[:, 0])
        assert np.all(np.diff(fwd) > 0), f"region {m}: a directed edge is used twice"
        assert np.array_equal(fwd, rev), f"region {m}: surface is not closed"


def rotation(angles):
    out = np.eye(3)
    for axis, ang in enumerate(angles):
        c, s = np.cos(ang), np.sin(ang)
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        out = r @ out
    return out


@pytest.fixture(scope="module")
def fine_sphere():
    """Level-7 icosphere (327 680 faces) and its sagitta delta / R (faces' least distance)."""
    v, f = icosphere(7)
    n, h = face_planes(v, f)
    return v, f, 1.0 - h.min()


# -- polyhedra: exact -----------------------------------------------------------------------------
@pytest.mark.parametrize("direction", ["y", "z"])
def test_box_chords_are_exact_with_pixel_centres_on_edges(direction):
    """A 10 x 8 x 6 box of 960 tets; pixel centres fall exactly on mesh edges and vertices (and on
    the silhouette): inside exactly the depth, outside exactly 0, on the outline one of the two."""
    fem = grid_mesh((-5, -4, -3), (5, 4, 3), (10, 8, 6))
    g = Geometry("parallel", direction, shape=(31, 33), pixel_size_mm=0.5)
    o, _ = g.rays()
    depth = 8.0 if direction == "y" else 6.0
    v_axis = 2 if direction == "y" else 1
    half_v = 3.0 if direction == "y" else 4.0
    du, dv = np.abs(o[0]) - 5.0, np.abs(o[v_axis]) - half_v
    for steep in (1e3, 0.0):  # difference arrays, and every face per pixel
        L = render(g, *surface_xyz(fem), steep_slope=steep)
        assert np.all(np.abs(L[(du < 0) & (dv < 0)] - depth) <= 1e-12)
        assert np.all(L[(du > 0) | (dv > 0)] == 0.0)
        edge = ((du == 0) & (dv <= 0)) | ((dv == 0) & (du <= 0))
        assert edge.any()
        assert np.all(np.minimum(np.abs(L[edge]), np.abs(L[edge] - depth)) <= 1e-12)
    pl = path_lengths(fem, g)
    assert pl.shape == (1, 31, 33) and np.array_equal(pl[0] > 0, L > 0)


def test_two_regions_split_the_depth_and_weight_the_line_integral():
    """Box with a box inclusion: L_incl is the inner depth on its footprint, L_body + L_incl the
    outer depth, and the line integral mu0 L0 + mu1 L1 (interfaces carry mu1 - mu0)."""
    inner = lambda c: (np.abs(c[0]) < 2) & (np.abs(c[1]) < 1.5) & (np.abs(c[2] - 1) < 1)
    fem = grid_mesh((-4, -3, -3), (4, 3, 3), (8, 12, 6), region_of=inner)
    assert set(np.unique(fem.region)) == {0, 1}
    surf = surface_of(fem)
    assert_closed(surf)
    for kind in ("parallel", "cone"):
        g = Geometry(
            kind,
            "y",
            shape=(40, 44),
            pixel_size_mm=0.25 * (1.2 if kind == "cone" else 1.0),
            source_distance_mm=100.0,
            detector_distance_mm=20.0,
        )
        L = path_lengths(fem, g)
        o, d = g.rays()
        outer = convex_chord(*box_planes((-4, -3, -3), (4, 3, 3)), o, d)
        incl = convex_chord(*box_planes((-2, -1.5, 0), (2, 1.5, 2)), o, d)
        np.testing.assert_allclose(L[1], incl, rtol=0, atol=1e-11)
        np.testing.assert_allclose(L[0] + L[1], outer, rtol=0, atol=1e-11)
        assert (incl > 0).sum() > 50 and (L[0] > 0).sum() > (incl > 0).sum()
        mu = (0.05, 0.12)
        np.testing.assert_allclose(line_integral(fem, g, mu), mu[0] * L[0] + mu[1] * L[1], rtol=0, atol=1e-12)
    # parallel along y: on the inclusion's footprint it and the gel share the depth of 6 equally
    g = Geometry("parallel", "y", shape=(40, 44), pixel_size_mm=0.25)
    L = path_lengths(fem, g)
    o, _ = g.rays()
    foot = (np.abs(o[0]) < 2) & (np.abs(o[2] - 1) < 1)
    assert foot.sum() > 50
    assert np.all(np.abs(L[1][foot] - 3.0) < 1e-12) and np.all(np.abs(L[0][foot] - 3.0) < 1e-12)


@pytest.mark.parametrize("kind", ["parallel", "cone"])
@pytest.mark.parametrize("direction", ["y", "z"])
def test_affinely_deformed_box_is_exact(kind, direction):
    """An affine displacement (shear + compression + rotation) maps the box to a parallelepiped:
    the projection of the deformed mesh must equal its exact chords."""
    fem = grid_mesh((-5, -4, -3), (5, 4, 3), (5, 4, 3))
    A = rotation((0.3, -0.2, 0.5)) @ np.array([[1.1, 0.2, 0.0], [0.1, 0.8, 0.15], [-0.1, 0.05, 1.2]])
    b = np.array([0.4, -0.3, 0.7])
    X = A @ fem.points + b[:, None]
    u = np.concatenate([X - fem.points, np.zeros((3, 7))], axis=1)  # extra (P2-like) dofs are ignored
    g = Geometry(
        kind,
        direction,
        shape=(48, 52),
        pixel_size_mm=0.35,
        centre_mm=(0.2, 0.1, -0.3),
        source_distance_mm=60.0,
        detector_distance_mm=30.0,
    )
    L = path_lengths(fem, g, u)[0]
    o, d = g.rays()
    n, h = box_planes((-5, -4, -3), (5, 4, 3))
    Ainv = np.linalg.inv(A)
    n2 = n @ Ainv  # n . x <= h with x = Ainv (X - b)
    ref = convex_chord(n2, h + n2 @ b, o, d)
    assert (ref > 0).mean() > 0.15
    np.testing.assert_allclose(L, ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("kind", ["parallel", "cone"])
def test_rotated_convex_polyhedron_is_exact(kind):
    """An anisotropic, rotated level-2 icosphere (320 faces) through its tetrahedral star mesh:
    exact chords of the polyhedron from half-space clipping, on both evaluation paths."""
    v, f = icosphere(2)
    X = rotation((0.7, 0.4, -1.1)) @ (v * np.array([[6.0], [4.0], [3.0]])) + np.array([[0.5], [-0.4], [0.3]])
    fem = star_mesh(X, f, (0.5, -0.4, 0.3))
    g = Geometry(kind, "z", shape=(64, 60), pixel_size_mm=0.22, source_distance_mm=50.0, detector_distance_mm=25.0)
    L = path_lengths(fem, g)[0]
    o, d = g.rays()
    ref = convex_chord(*face_planes(X, f), o, d)
    assert (ref > 0).mean() > 0.3
    np.testing.assert_allclose(L, ref, rtol=0, atol=1e-10)
    s = surface_of(fem)
    np.testing.assert_allclose(render(g, s.vertices(fem.points), s.faces, steep_slope=0.0), L, rtol=0, atol=1e-11)


def test_nearly_edge_on_faces_stay_finite_and_exact():
    """A box turned by 1e-9 rad: its sides are seen almost exactly edge-on (depth slopes ~1e9),
    the per-pixel path with clamped depths handles them; no NaN or inf anywhere."""
    fem = grid_mesh((-5, -4, -3), (5, 4, 3), (2, 2, 2))
    A = rotation((1e-9, 0.0, -2e-9))
    X = A @ fem.points
    g = Geometry("parallel", "y", shape=(41, 45), pixel_size_mm=0.25)
    L = path_lengths(fem, g, X - fem.points)[0]
    assert np.isfinite(L).all()
    o, d = g.rays()
    n, h = box_planes((-5, -4, -3), (5, 4, 3))
    ref = convex_chord(n @ A.T, h, o, d)
    inside = (np.abs(o[0]) < 4.9) & (np.abs(o[2]) < 2.9)
    np.testing.assert_allclose(L[inside], ref[inside], rtol=0, atol=1e-9)
    assert np.all((L >= 0) & (L <= 8.0 + 1e-9))
    assert np.all(L[(np.abs(o[0]) > 5.1) | (np.abs(o[2]) > 3.1)] == 0.0)


# -- curved bodies: analytic, 1e-4 ---------------------------------------------------------------
@pytest.mark.parametrize("direction", ["y", "z"])
def test_sphere_parallel_beam_against_analytic_chord(fine_sphere, direction):
    v, f, delta = fine_sphere
    assert delta < 2e-5  # level 7: the sandwich is < 1e-4 wide for rho <= 0.8 R
    R, c = 9.0, np.array([1.3, -0.6, 0.8])
    fem = star_mesh(v * R + c[:, None], f, c)
    g = Geometry("parallel", direction, shape=(100, 104), pixel_size_mm=0.2)
    L = path_lengths(fem, g)[0]
    o, _ = g.rays()
    k = 2 if direction == "y" else 1
    cu, cv = c[0], c[k]
    ref = sphere_chord(o[0], o[k], R, (cu, cv))
    lo = sphere_chord(o[0], o[k], R * (1 - delta), (cu, cv))
    assert np.all((L >= lo - 1e-9) & (L <= ref + 1e-9))  # the polyhedral sandwich, on every pixel
    rho = np.hypot(o[0] - cu, o[k] - cv)
    well = rho <= 0.8 * R
    assert well.sum() > 3000
    assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4
    assert np.all(L[rho > R] == 0.0)


def test_ellipsoid_parallel_beam_against_analytic_chord(fine_sphere):
    """The icosphere scaled by the semi-axes is inscribed in the ellipsoid and contains it shrunk
    by (1 - delta): the same sandwich. Rendered directly from the triangles (``render``)."""
    v, f, delta = fine_sphere
    axes = np.array([11.0, 7.0, 5.0])
    g = Geometry("parallel", "z", shape=(80, 120), pixel_size_mm=0.2)
    L = render(g, v * axes[:, None], f)
    o, _ = g.rays()
    ref = ellipsoid_chord(o[0], o[1], *axes)
    lo = ellipsoid_chord(o[0], o[1], *(axes * (1 - delta)))
    assert np.all((L >= lo - 1e-9) & (L <= ref + 1e-9))
    q = (o[0] / axes[0]) ** 2 + (o[1] / axes[1]) ** 2
    well = q <= 0.64
    assert well.sum() > 2000
    assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4


@pytest.mark.parametrize("direction", ["y", "z"])
def test_sphere_cone_beam_against_analytic_ray_chord(fine_sphere, direction):
    v, f, delta = fine_sphere
    R, c = 8.0, np.array([2.0, 1.5, -1.0])
    fem = star_mesh(v * R + c[:, None], f, c)
    g = Geometry(
        "cone",
        direction,
        shape=(90, 96),
        pixel_size_mm=0.3,
        centre_mm=(0.5, 0.5, 0.5),
        source_distance_mm=60.0,
        detector_distance_mm=40.0,
    )
    L = path_lengths(fem, g)[0]
    o, d = g.rays()
    ref = ray_sphere_chord(o, d, R, c)
    lo = ray_sphere_chord(o, d, R * (1 - delta), c)
    assert np.all((L >= lo - 1e-9) & (L <= ref + 1e-9))
    well = ref >= 2 * R * 0.6  # distance from the centre to the ray <= 0.8 R
    assert well.sum() > 2000
    assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4
    assert np.all(L[ref == 0] == 0.0)


def test_ray_chords_agree_with_parallel_ones():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-6, 6, (2, 200))
    o = np.stack([u, v, np.full_like(u, -50.0)])
    d = np.broadcast_to(np.array([0.0, 0.0, 2.0])[:, None], o.shape)
    np.testing.assert_allclose(
        ray_ellipsoid_chord(o, d, (5, 6, 3), (0.5, -0.2, 1.0)),
        ellipsoid_chord(u, v, 5, 6, 3, (0.5, -0.2)),
        rtol=1e-12,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        ray_sphere_chord(o, d, 4.0, (0.5, -0.2, 9.0)), sphere_chord(u, v, 4.0, (0.5, -0.2)), rtol=1e-12, atol=1e-12
    )


# -- symmetry and reduced models -----------------------------------------------------------------
@pytest.mark.parametrize("kind", ["parallel", "cone"])
def test_mirrored_quarter_and_eighth_equal_the_full_mesh(kind):
    incl = lambda c: (c[0] ** 2 + 2 * (c[1] - 0.25) ** 2 + c[2] ** 2) < 6.0
    full = grid_mesh((-4, -3, -3), (4, 3, 3), (16, 12, 12), region_of=incl)
    quarter = grid_mesh((0, -3, 0), (4, 3, 3), (8, 12, 6), region_of=incl, symmetry=("x", "z"))
    for direction in ("y", "z"):
        g = Geometry(
            kind,
            direction,
            shape=(36, 40),
            pixel_size_mm=0.23,
            centre_mm=(0.1, 0.05, -0.07),
            source_distance_mm=40.0,
            detector_distance_mm=20.0,
        )
        ref = path_lengths(full, g)
        assert (ref[1] > 0).sum() > 50
        np.testing.assert_allclose(path_lengths(quarter, g), ref, rtol=0, atol=1e-11)
    sym = lambda c: (c[0] ** 2 + 2 * c[1] ** 2 + c[2] ** 2) < 6.0
    full = grid_mesh((-4, -3, -3), (4, 3, 3), (8, 6, 6), region_of=sym)
    eighth = grid_mesh((0, 0, 0), (4, 3, 3), (4, 3, 3), region_of=sym, symmetry=("x", "y", "z"))
    assert_closed(surface_of(eighth))
    g = Geometry(kind, "y", shape=(36, 40), pixel_size_mm=0.23, source_distance_mm=40.0, detector_distance_mm=20.0)
    np.testing.assert_allclose(path_lengths(eighth, g), path_lengths(full, g), rtol=0, atol=1e-11)


@pytest.mark.parametrize("name", ["seed-breast", "pva-phantom"])
def test_preset_meshes_mirror_into_closed_surfaces(name):
    from sim.mesh import build_mesh
    from sim.scene import load_scene

    fem = build_mesh(load_scene(name))
    assert fem.symmetry  # both presets are cut by symmetry planes
    surf = surface_of(fem)
    assert_closed(surf)
    # the enclosed volume of every region equals the mesh volume times its multiplicity
    X = surf.vertices(fem.points)
    p, t = fem.points, fem.cells
    a, b, c, d = (p[:, t[i]] for i in range(4))
    vol = np.abs(np.einsum("ij,ij->j", np.cross(b - a, c - a, axis=0), d - a)) / 6
    for m in range(surf.n_regions):
        w = (surf.inside == m).astype(float) - (surf.outside == m)
        fa, fb, fc = (X[:, surf.faces[:, i]] for i in range(3))
        enclosed = np.sum(w * np.einsum("ij,ij->j", np.cross(fa, fb, axis=0), fc)) / 6
        assert enclosed == pytest.approx(vol[fem.region == m].sum() * fem.multiplicity, rel=1e-12)


def test_axisymmetric_sphere_section_revolves_to_the_sphere():
    """Half-disk section (fan of 400 triangles) revolved: within the sandwich of the inscribed
    profile and azimuthal polygons, and within 1e-4 of the analytic chords, for beams across and
    along the axis, parallel and cone."""
    R, n = 7.0, 400
    th = np.linspace(0, np.pi, n + 1)
    P = np.concatenate([[[0.0], [0.0]], np.stack([R * np.sin(th), R * np.cos(th)])], axis=1)
    P[0, [1, n + 1]] = 0.0  # the poles exactly on the axis
    tri = np.stack([np.zeros(n, int), np.arange(1, n + 1), np.arange(2, n + 2)])
    fem = FEMesh(P, tri, np.zeros(n, int), "axisymmetric")
    tol = 1e-5
    surf = surface_of(fem, revolve_tol=tol)
    assert_closed(surf)
    shrink = np.cos(np.pi / (2 * n)) * (1 - tol)
    for kind, direction in (("parallel", "z"), ("parallel", "y"), ("cone", "z"), ("cone", "y")):
        g = Geometry(
            kind, direction, shape=(80, 84), pixel_size_mm=0.2, source_distance_mm=50.0, detector_distance_mm=10.0
        )
        L = path_lengths(fem, g)[0]
        o, d = g.rays()
        ref = ray_sphere_chord(o, d, R)
        assert np.all((L >= ray_sphere_chord(o, d, R * shrink) - 1e-9) & (L <= ref + 1e-9))
        well = ref >= 2 * R * 0.6
        assert well.sum() > 1500
        assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4, (kind, direction)


def test_axisymmetric_cylinder_with_inclusion_and_y_symmetry():
    """Section r in [0, 10], y in [0, 15] (mirrored across y = 0) with a cylindrical inclusion
    r < 4, |y| < 5: beam across the axis, against the analytic cylinder chords."""
    fem = grid_2d(
        (0, 0), (10, 15), (10, 15), region_of=lambda c: (c[0] < 4) & (c[1] < 5), model="axisymmetric", symmetry=("y",)
    )
    tol = 1e-5
    assert_closed(surface_of(fem, revolve_tol=tol))
    g = Geometry("parallel", "z", shape=(70, 60), pixel_size_mm=0.5)
    L = path_lengths(fem, g, revolve_tol=tol)
    o, _ = g.rays()
    x, y = o[0], o[1]
    outer = sim.analytic.cone_side_chord(x, y + 15, 10, 10, 30)
    inner = sim.analytic.cone_side_chord(x, y + 5, 4, 4, 10)
    for got, ref, r in ((L[1], inner, 4.0), (L[0] + L[1], outer, 10.0)):
        well = (np.abs(x) <= 0.8 * r) & (ref > 0) & (np.abs(np.abs(y) - (5 if r == 4 else 15)) > 0.3)
        assert well.sum() > 100
        assert np.max(np.abs(got[well] / ref[well] - 1)) < 1e-4
        assert np.all(got <= ref + 1e-9)
    assert np.all(L[:, np.abs(y) > 15.3] == 0.0)


def test_plane_strain_slab_equals_the_box():
    """A plane-strain section x in [0, 5], y in [-4, 4] (build_mesh's half model) extruded to a
    slab 6 thick and mirrored across x = 0 projects exactly like the 10 x 8 x 6 box."""
    fem2 = grid_2d((0, -4), (5, 4), (5, 8), model="plane-strain")
    box = grid_mesh((-5, -4, -3), (5, 4, 3), (4, 4, 3))
    assert_closed(surface_of(fem2, thickness_mm=6.0))
    for kind, direction in (("parallel", "y"), ("cone", "z"), ("cone", "y")):
        g = Geometry(
            kind, direction, shape=(44, 48), pixel_size_mm=0.3, source_distance_mm=40.0, detector_distance_mm=15.0
        )
        np.testing.assert_allclose(path_lengths(fem2, g, thickness_mm=6.0), path_lengths(box, g), rtol=0, atol=1e-11)
    with pytest.raises(ValueError, match="thickness"):
        surface_of(fem2)


# -- detector, supersampling, scenes ----------------------------------------------------------------
def test_detector_frame_conventions():
    """Columns follow +x; rows follow -z (beam y) or -y (beam z): row 0 is the top."""
    blob = grid_mesh((2, 1, 2), (4, 3, 4), (1, 1, 1))  # at +x, +y, +z
    for direction in ("y", "z"):
        img = path_lengths(blob, Geometry("parallel", direction, shape=(20, 20), pixel_size_mm=0.5))[0]
        rows, cols = np.nonzero(img)
        assert cols.min() > 10 and rows.max() < 10
    g = Geometry("cone", "y", shape=(20, 20), pixel_size_mm=0.5, source_distance_mm=10.0, detector_distance_mm=10.0)
    img = path_lengths(blob, g)[0]
    rows, cols = np.nonzero(img)  # magnified by 20 / (10 + y): columns from (2..4) * 20/13..20/11
    assert cols.min() == int(np.ceil(2 * 20 / 13 / 0.5 + 9.5)) and rows.max() < 10
    assert Geometry("cone", "y", source_distance_mm=400, detector_distance_mm=100).magnification == 1.25


def test_supersampling_averages_sub_rays():
    """A box edge a quarter of the way into a pixel: with 4 x 4 sub-rays that pixel sees exactly a
    quarter of the depth; without, the pixel centre decides."""
    fem = grid_mesh((-5.25, -2, -2.5), (5.25, 2, 2.5), (3, 2, 2))
    g = Geometry("parallel", "y", shape=(10, 14), pixel_size_mm=1.0)  # centres at +-0.5 .. +-6.5
    L1 = path_lengths(fem, g)[0]
    L4 = path_lengths(fem, g, supersample=4)[0]
    mid = 5
    np.testing.assert_allclose(L1[mid], [0, 0, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 0, 0], atol=1e-12)
    np.testing.assert_allclose(L4[mid], [0, 1, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 1, 0], atol=1e-12)
    np.testing.assert_allclose(L4[[1, 2, 7, 8], 5], [0, 2, 2, 0], atol=1e-12)  # z = +-2.5 halves rows 2, 7
    assert L4.sum() * 1.0 == pytest.approx(10.5 * 4 * 5, rel=1e-12)  # the volume (1 mm^2 pixels), exactly


def test_project_scene_state_and_mesh():
    """block_scene (10 mm cube, mu = 0.05 /mm) compressed by 20 %: the line integral is mu * 8 mm
    inside the laterally stretched footprint and 0 outside; undeformed, mu * 10 mm."""
    from sim.mechanics import compress, uniaxial_block_force
    from sim.scene import block_scene

    scene = block_scene(size_mm=10.0, E_kpa=5.0, nu=0.45)
    (state,) = compress(scene, [0.2])
    img = project(scene, state)
    assert img.dtype == np.float32 and img.shape == scene.detector.shape == (560, 560)
    assert np.isfinite(img).all()
    mu = scene.body.material.attenuation_per_mm
    _, stretch = uniaxial_block_force(0.2, 5.0, 0.45, 100.0)
    o, _ = Geometry.from_scene(scene).rays()
    half = 5.0 * stretch
    inside = (np.abs(o[0]) < half - 0.1) & (np.abs(o[2]) < half - 0.1)
    outside = (np.abs(o[0]) > half + 0.1) | (np.abs(o[2]) > half + 0.1)
    np.testing.assert_allclose(img[inside], mu * 8.0, rtol=1e-6)
    assert np.all(img[outside] == 0.0)
    flat = project(scene, None, fem=state.solver.fem)
    np.testing.assert_allclose(flat[280][np.abs(o[0][280]) < 4.9], mu * 10.0, rtol=1e-6)
    with pytest.raises(ValueError, match="fem"):
        project(scene, types.SimpleNamespace(displacement=state.displacement))


def test_cone_source_inside_the_mesh_is_refused():
    fem = grid_mesh((-5, -4, -3), (5, 4, 3), (1, 1, 1))
    with pytest.raises(ValueError, match="behind the source"):
        path_lengths(fem, Geometry("cone", "z", shape=(4, 4), source_distance_mm=2.0))


def test_module_examples():
    for mod in (sim.xray, sim.analytic):
        assert doctest.testmod(mod).failed == 0


def ray_cylinder_chord(origin, direction, radius, half_height):
    """Closed form: length of lines ``origin + t direction`` (each (3, ...)) inside the solid
    cylinder ``x^2 + z^2 <= r^2, |y| <= h``: the interval where the line's (x, z) part is inside
    the circle (a quadratic in t) intersected with the slab's interval in y."""
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    a = d[0] ** 2 + d[2] ** 2
    b = o[0] * d[0] + o[2] * d[2]
    c = o[0] ** 2 + o[2] ** 2 - radius**2
    root = np.sqrt(np.clip(b * b - a * c, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_in, t_out = (-b - root) / a, (-b + root) / a
        y0, y1 = (-half_height - o[1]) / d[1], (half_height - o[1]) / d[1]
    lo = np.maximum(t_in, np.minimum(y0, y1))
    hi = np.minimum(t_out, np.maximum(y0, y1))
    meets = (b * b - a * c > 0) & (a > 0)
    return np.where(meets, np.clip(hi - lo, 0.0, None), 0.0) * np.sqrt(np.sum(d * d, axis=0))


@pytest.mark.parametrize("direction", ["z", "y"])
def test_cone_beam_through_a_meshed_cylinder_scene(direction):
    """A scene's cylinder (gmsh section revolved, axisymmetric), imaged by a cone beam from the
    side and through the plates, against the closed-form chords of a cylinder times mu (scene
    per cm -> per mm): the point source, magnification and isocentre of ``Geometry.from_scene``
    in one check. The section's edges are straight, so the only error is the revolution's: the
    polygon lies between the cylinder and the cylinder shrunk by ``revolve_tol`` (1e-5), a
    sandwich on every pixel; from the side, rays at most 0.8 r from the axis err by at most
    ``1e-5 / 0.36`` relative, and through the plates rays that cross both flat faces are exact. The shadow ends where the chords do: from the side, at
    ``D r / sqrt(s^2 - r^2)`` on the detector (the tangents from the source)."""
    from sim.scene import Beam, Body, Detector, Exposure, Material, MeshSpec, Scene

    r, h, mu = 20.0, 60.0, 0.77
    scene = Scene(
        name="cylinder",
        body=Body(
            "cylinder",
            height_mm=h,
            diameter_mm=2 * r,
            material=Material("gel", E_kpa=20.0, nu=0.495, attenuation_per_cm=mu),
        ),
        beam=Beam("cone", direction, source_distance_mm=400.0, detector_distance_mm=100.0),
        detector=Detector("c7942", 4),
        exposure=Exposure(2500.0 / 16),  # per unbinned pixel: a 4x4 read-out pixel sums 16 (within 12 bits)
        mesh=MeshSpec(10.0, 10.0, "auto", True),
    )
    img = project(scene).astype(float)
    o, d = Geometry.from_scene(scene).rays()
    ref = mu / 10 * ray_cylinder_chord(o, d, r, h / 2)
    lo = mu / 10 * ray_cylinder_chord(o, d, r * (1 - 1e-5), h / 2)
    tol = 1e-6 * ref.max()  # float32 output
    assert np.all((img >= lo - tol) & (img <= ref + tol))
    assert np.all(img[ref == 0] == 0.0)
    if direction == "z":  # the ray's distance from the axis
        rho = np.abs(o[0] * d[2] - o[2] * d[0]) / np.hypot(d[0], d[2])
        well = (rho <= 0.8 * r) & (ref > 0.5 * ref.max())
    else:  # rays through both flat faces, 0.8 r from the rim (grazing the wall, a radial error
        # of 1e-5 r moves the exit by that over the ray's small angle to the wall)
        t = (np.array([-h / 2, h / 2])[:, None, None] - o[1]) / d[1]
        well = np.all(np.hypot(o[0] + t * d[0], o[2] + t * d[2]) <= 0.8 * r, axis=0)
    assert well.sum() > 10000
    assert np.max(np.abs(img[well] / ref[well] - 1)) < 1e-4
    if direction == "z":
        half_shadow = 500.0 * r / np.sqrt(400.0**2 - r * r) / 0.2  # pixels
        row = img[img.shape[0] // 2]
        assert np.count_nonzero(row) == pytest.approx(2 * half_shadow, abs=1.0)


@pytest.mark.parametrize("direction", ["y", "z"])
def test_ellipsoid_cone_beam_against_analytic_ray_chord(fine_sphere, direction):
    """The scaled icosphere is inscribed in the ellipsoid and contains it shrunk by (1 - delta)
    (an affine map keeps both), so under a strongly diverging cone beam (source 60 mm from the
    isocentre, magnification 1.67) every pixel's chord lies between the two closed-form ray
    chords, and rays well inside (chord at least 0.6 of the longest through the centre) within
    1e-4 of the true one."""
    v, f, delta = fine_sphere
    axes, c = np.array([11.0, 7.0, 5.0]), np.array([1.0, -0.5, 0.8])
    g = Geometry(
        "cone", direction, shape=(96, 120), pixel_size_mm=0.3, source_distance_mm=60.0, detector_distance_mm=40.0
    )
    L = render(g, v * axes[:, None] + c[:, None], f)
    o, d = g.rays()
    ref = ray_ellipsoid_chord(o, d, axes, c)
    lo = ray_ellipsoid_chord(o, d, axes * (1 - delta), c)
    assert np.all((L >= lo - 1e-9) & (L <= ref + 1e-9))
    well = ref >= 0.6 * 2 * axes[1 if direction == "y" else 2]
    assert well.sum() > 2000
    assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4
    assert np.all(L[ref == 0] == 0.0)


def ray_hemi_ellipsoid_chord(origin, direction, semi_axes):
    """Closed form: length of lines inside the half ``x >= 0`` of the ellipsoid
    ``sum((X / semi_axes)^2) <= 1``: the line's interval in the ellipsoid (a quadratic in the line
    parameter) clipped to the half-space."""
    a = np.asarray(semi_axes, float).reshape(3, 1, 1)
    o, d = origin / a, direction / a
    qa, qb, qc = np.sum(d * d, axis=0), np.sum(o * d, axis=0), np.sum(o * o, axis=0) - 1
    disc = qb * qb - qa * qc
    root = np.sqrt(np.clip(disc, 0.0, None))
    lo, hi = (-qb - root) / qa, (-qb + root) / qa
    dx = direction[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = -origin[0] / dx  # where the line meets x = 0
    lo = np.where(dx > 0, np.maximum(lo, cut), lo)
    hi = np.where(dx < 0, np.minimum(hi, cut), hi)
    inside = (disc > 0) & ((dx != 0) | (origin[0] > 0))
    return np.where(inside, np.clip(hi - lo, 0.0, None), 0.0) * np.sqrt(np.sum(direction**2, axis=0))


def _least_plane_radius(X, faces, centre, scale):
    """Least distance from ``centre`` to the faces' planes in coordinates divided by ``scale``,
    and whether every face faces away from it (then the surface is star-shaped about it)."""
    V = (X[:, faces] - np.asarray(centre, float)[:, None, None]) / np.asarray(scale, float)[:, None, None]
    n = np.cross((V[:, :, 1] - V[:, :, 0]).T, (V[:, :, 2] - V[:, :, 0]).T).T
    h = np.sum(n * V[:, :, 0], axis=0) / np.linalg.norm(n, axis=0)
    return float(h.min()), bool(np.all(h > 0))


def test_meshed_hemi_ellipsoid_with_inclusion_against_closed_form_chords():
    """The paper's body through the whole pipeline: seed-breast's hemi-ellipsoid (50 x 25 x 25 mm,
    flat chest wall x = 0) with its 8 mm sphere, meshed by gmsh as a quarter and mirrored, seen
    through the plates and from the side, parallel and cone (magnification 1.5). The mesh's
    vertices lie on the true surfaces (to 2e-9), so the polyhedra lie inside them: every chord
    at most the closed-form one. Every curved face faces away from the centre (star-shaped) at
    least ``1 - delta`` from it in the scaled coordinates, so each polyhedron contains its body
    shrunk by ``1 - delta`` about the centre (the chest wall stays in place): every chord at least
    that one. Both bounds on every pixel, for the body (gel + inclusion) and the inclusion; rays
    missing the body read exactly 0, and nothing appears at x < 0."""
    from sim.mesh import build_mesh
    from sim.scene import load_scene
    from sim.xray import body_centre

    scene = load_scene("seed-breast")
    scene.mesh.size_inclusion_mm, scene.mesh.size_far_mm, scene.mesh.size_contact_mm = 1.0, 3.0, None
    fem = build_mesh(scene)
    surf = surface_of(fem)
    X = surf.vertices(fem.points)
    axes = np.array(scene.body.semi_axes_mm)
    inc = scene.inclusions[0]
    centre, R = np.array(inc.centre_mm), inc.diameter_mm / 2
    outer = (surf.inside == 0) & (surf.outside == -1)
    curved = outer & ~np.all(np.abs(X[0, surf.faces]) < 1e-9, axis=1)
    h_body, star_body = _least_plane_radius(X, surf.faces[curved], (0, 0, 0), axes)
    # the interface is stored once, pointing out of one region: oriented out of the inclusion
    interface = np.concatenate([surf.faces[surf.inside == 1], surf.faces[surf.outside == 1][:, ::-1]])
    h_inc, star_inc = _least_plane_radius(X, interface, centre, (R, R, R))
    assert star_body and star_inc and 0.99 < h_body < 1 and 0.95 < h_inc < 1
    for kind, direction in (("parallel", "y"), ("parallel", "z"), ("cone", "y"), ("cone", "z")):
        g = Geometry(kind, direction, (140, 240), 0.5, body_centre(scene), 200.0, 100.0)
        L = path_lengths(fem, g)
        o, d = g.rays()
        body = ray_hemi_ellipsoid_chord(o, d, axes * (1 + 2e-9))
        assert np.all(L.sum(axis=0) <= body + 1e-9)
        assert np.all(L.sum(axis=0) >= ray_hemi_ellipsoid_chord(o, d, axes * h_body) - 1e-9)
        assert np.all(L[1] <= ray_sphere_chord(o, d, R * (1 + 2e-9), centre) + 1e-9)
        assert np.all(L[1] >= ray_sphere_chord(o, d, R * h_inc, centre) - 1e-9)
        assert np.all(L[:, body == 0] == 0.0)
        assert (L[1] > 0).sum() > 100 and (body > 0).sum() > 5000, (kind, direction)


def test_the_undeformed_scene_projects_on_the_mesh_its_states_project_on():
    """Review s40phys: ``project(scene)`` took the straight-sided vertex mesh and ``project(scene,
    state)`` the P2 nodes (edge nodes on the curved surface), so an undeformed image and a state's
    differed by the mesh's sag: 1.3 % of a sphere's integrated attenuation, and a 5 % compression
    read +1.24 % where the volume changed by -0.09 %. Now both take the solver's projection mesh;
    its sag is that of sub-edges half an element long: 3 (h/2)^2 / (8 R^2) of the volume at most
    (0.84 % for h = 3 mm, R = 10 mm; the vertex mesh lost 1.7 %)."""
    from sim.mechanics import Solver
    from sim.scene import Beam, Body, Compression, Detector, Exposure, Material, MeshSpec, Scene

    r, h = 10.0, 3.0
    gel = Material("gel", "neo-hookean", E_kpa=5.0, nu=0.45, attenuation_per_cm=0.5)
    scene = Scene(
        name="sphere",
        body=Body("ellipsoid", semi_axes_mm=(r, r, r), material=gel),
        beam=Beam("parallel", "z"),
        detector=Detector("c7942", 4),
        exposure=Exposure(200.0, 28.0, 250.0),
        mesh=MeshSpec(1.0, h, "auto"),
        compression=Compression((0.05,)),
    )
    img = project(scene).astype(float)
    np.testing.assert_array_equal(img, project(scene, None, fem=Solver(scene).projection_mesh))
    exact = 0.05 * 4 / 3 * np.pi * r**3 / Geometry.from_scene(scene).pixel_size_mm ** 2  # mu V / pixel area
    assert 0 <= 1 - img.sum() / exact <= 3 * (h / 2) ** 2 / (8 * r**2)


@pytest.mark.parametrize("kind", ["parallel", "cone"])
def test_a_turned_ellipsoid_projects_to_its_closed_form_chords(fine_sphere, kind):
    """An ellipsoid (semi-axes 9, 6, 4 mm) turned about all three axes and moved off the isocentre
    by a rigid displacement of its star mesh (the way a state's motion reaches the projector),
    parallel and cone (source 60 mm before the isocentre, magnification 1.5). The closed form is
    the axis-aligned ray chord in the body's own frame: ``o' = Q^T (o - c)``, ``d' = Q^T d``. A
    rotation keeps the polyhedral sandwich (inscribed, and containing the ellipsoid shrunk by
    ``1 - delta``), so every pixel lies between the two chords; rays passing at most 0.8 of the
    way from the centre to the rim, in the body's coordinates scaled to the unit ball (``q <=
    0.64``), within 1e-4 of the true one (the sandwich there is ``delta / (1 - q)``, 5e-5, wide)."""
    v, f, delta = fine_sphere
    axes, c = np.array([9.0, 6.0, 4.0]), np.array([1.2, -0.7, 0.9])
    Q = rotation((0.6, -0.9, 0.35))
    fem = star_mesh(v * axes[:, None], f, (0.0, 0.0, 0.0))
    moved = Q @ fem.points + c[:, None]
    g = Geometry(kind, "y", shape=(90, 96), pixel_size_mm=0.3, source_distance_mm=60.0, detector_distance_mm=30.0)
    L = path_lengths(fem, g, moved - fem.points)[0]
    o, d = g.rays()
    o_body = np.einsum("ji,j...->i...", Q, o - c[:, None, None])
    d_body = np.einsum("ji,j...->i...", Q, d)
    ref = ray_ellipsoid_chord(o_body, d_body, axes)
    lo = ray_ellipsoid_chord(o_body, d_body, axes * (1 - delta))
    assert np.all((L >= lo - 1e-9) & (L <= ref + 1e-9))
    assert np.all(L[ref == 0] == 0.0)
    o_s, d_s = o_body / axes[:, None, None], d_body / axes[:, None, None]
    nearest = o_s - np.sum(o_s * d_s, axis=0) / np.sum(d_s * d_s, axis=0) * d_s
    well = np.sum(nearest * nearest, axis=0) <= 0.64
    assert well.sum() > 800
    assert np.max(np.abs(L[well] / ref[well] - 1)) < 1e-4
    # turned: the axis-aligned ellipsoid's chords differ by far more than the tolerance
    assert np.max(np.abs(ray_ellipsoid_chord(o - c[:, None, None], d, axes) - ref)) > 1.0
