"""Ground-truth 2D displacement between two simulated compression states.

A radiograph sees the whole depth of the body at once, so a 3D motion has no unique 2D image.
The truth here is the **attenuation-weighted mean, along each ray of the fixed state, of the
projected motion of the material on that ray**:

    d(x) = int mu(X) [P(X_moving) - P(X_fixed)] dl / int mu(X) dl,

the integrals running along the ray of detector pixel ``x`` through the *fixed* (deformed) body,
``P`` the projection of a point onto the detector in pixels (``Geometry``'s frame; cone beams
project through the source), ``X_fixed`` and ``X_moving`` the positions of one material point in
the two states. It is a pull field in the sense of DESIGN.md: ``moving(x + d(x))`` matches
``fixed(x)``; ``(2, rows, cols)`` float32, (row, col) order, in detector pixels, 0 off the body.
It is what an ideal registration of two line-integral images recovers where the material on a
ray moves together; where it does not (the inclusion's shadow), it is the motion of the
attenuation-weighted centre.

How it is computed, exactly for the finite-element field (parallel beams)
-------------------------------------------------------------------------
The projected motion ``f = P(X_moving) - P(X_fixed)`` is interpolated linearly over each
tetrahedron of the fixed state from its vertices: ``f = a . x + b``. For a parallel beam ``P`` is
affine and this is exact; a cone beam's perspective ``P`` bends ``f`` inside a tetrahedron, an
error of order ``(h / s)^2`` of the motion for elements of size ``h`` at ``s`` from the source
(at most 1.6e-4 of it for the pva-phantom's 5 mm elements 400 mm from the source; a block of
2.5 mm elements measures 1e-5, tests/test_sim_lab.py). Along a ray ``x = o + t w`` through one
tetrahedron,

    int f dl = sum over its 4 faces of s_f [(a . o + b) t_f + (a . w) t_f^2 / 2],

with ``t_f`` where the ray crosses face ``f`` and ``s_f = +1`` leaving, ``-1`` entering. ``a . o``
and ``a . w`` are affine in the pixel's detector coordinates ``(u, v)`` (divided by the ray length
for cone beams), so the integral is a handful of signed-depth renders (powers 1 and 2 of ``t``)
of every tetrahedron's faces with per-face weights, combined per pixel
(:func:`sim.xray.render`). Models reduced by symmetry are mirrored, axisymmetric sections
revolved (``revolve_segments`` wedges, each three tetrahedra) and plane-strain sections extruded
into the 3D body first. The integral is computed on a grid ``factor`` times coarser than the
detector (the field is smooth on the scale of the elements, 1-6 mm = 20-120 pixels) and
interpolated bilinearly, the body's silhouette taken from the full-resolution projection.

All the renders share their faces and geometry, so they are rasterised together: once for the
powers 1 of ``t`` and once for the powers 2, every weight at once, each face two tetrahedra
share rendered once with the difference of their weights. ``_reference=True`` keeps the
original one-render-per-image evaluation; the two agree to rounding (tests/test_sim_lab.py).
"""

from __future__ import annotations

import numpy as np

__all__ = ["truth_displacement", "body_tetrahedra"]


def body_tetrahedra(fem, displacements, *, revolve_segments=64, thickness_mm=None):
    """The whole body as 3D tetrahedra, with each state's vertex positions.

    Parameters
    ----------
    fem : sim.mesh.FEMesh
    displacements : list of (dim, >= n) arrays
        Per state, the mesh vertices first (``State.displacement``).

    Returns
    -------
    positions : list of (3, k) arrays, one per state
    tets : (m, 4) int, positively oriented in the first state
    region : (m,) int
    """
    p = np.asarray(fem.points, float)
    n = p.shape[1]
    states = [p + np.asarray(d, float)[:, :n] for d in displacements]
    cells, region = np.asarray(fem.cells).T, np.asarray(fem.region)
    if fem.model == "3d":
        pos, tets = states, cells
        for ax in fem.symmetry:
            k = "xyz".index(ax)
            flip = np.ones((3, 1))
            flip[k] = -1
            m = pos[0].shape[1]
            pos = [np.concatenate([x, x * flip], axis=1) for x in pos]
            tets = np.concatenate([tets, tets + m])
            region = np.concatenate([region, region])
    elif fem.model == "axisymmetric":
        N = int(revolve_segments)
        phi = 2 * np.pi * np.arange(N) / N
        c, s = np.cos(phi), np.sin(phi)
        # (r, y) -> (r cos phi, y, r sin phi); vertex (i, k) has index k * n + i
        pos = [np.concatenate([np.stack([x[0] * ck, x[1], x[0] * sk]) for ck, sk in zip(c, s)], axis=1) for x in states]
        tets, region = _sweep(cells, region, n, N, closed=True)
        if "y" in fem.symmetry:
            pos, tets, region = _mirror_y(pos, tets, region)
    elif fem.model == "plane-strain":
        if thickness_mm is None:
            raise ValueError("plane-strain model: thickness_mm is required")
        half = thickness_mm / 2
        pos = [np.concatenate([np.stack([x[0], x[1], np.full(n, z)]) for z in (-half, half)], axis=1) for x in states]
        tets, region = _sweep(cells, region, n, 2, closed=False)
        if p[0].min() >= -1e-9 * max(1.0, float(np.abs(p).max())):  # a half section x >= 0: mirror
            flip = np.array([[-1.0], [1.0], [1.0]])
            m = pos[0].shape[1]
            pos = [np.concatenate([x, x * flip], axis=1) for x in pos]
            tets = np.concatenate([tets, tets + m])
            region = np.concatenate([region, region])
        if "y" in fem.symmetry:
            pos, tets, region = _mirror_y(pos, tets, region)
    else:
        raise ValueError(f"unknown mesh model {fem.model!r}")
    vol = _signed_volumes(pos[0], tets)
    scale = float(np.abs(vol).max()) if vol.size else 0.0
    keep = np.abs(vol) > 1e-12 * scale  # wedges touching the axis have degenerate tetrahedra
    tets, region, vol = tets[keep], region[keep], vol[keep]
    neg = vol < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return pos, tets, region


def _mirror_y(pos, tets, region):
    flip = np.array([[1.0], [-1.0], [1.0]])
    m = pos[0].shape[1]
    return (
        [np.concatenate([x, x * flip], axis=1) for x in pos],
        np.concatenate([tets, tets + m]),
        np.concatenate([region, region]),
    )


def _sweep(tris, region, n, layers, closed):
    """Triangles (m, 3) swept through ``layers`` copies of the vertices into prisms of three
    tetrahedra each (vertex (i, k) is ``k * n + i``)."""
    nseg = layers if closed else layers - 1
    k = np.arange(nseg)
    k1 = (k + 1) % layers
    a, b, c = (tris[:, i][:, None] for i in range(3))
    a0, b0, c0 = a + k * n, b + k * n, c + k * n
    a1, b1, c1 = a + k1 * n, b + k1 * n, c + k1 * n
    t = np.stack([np.stack([a0, b0, c0, a1], -1), np.stack([b0, c0, a1, b1], -1), np.stack([c0, a1, b1, c1], -1)], 2)
    return t.reshape(-1, 4), np.repeat(region, nseg * 3)


def _signed_volumes(x, tets):
    e = x[:, tets[:, 1:]] - x[:, tets[:, :1]]  # (3, m, 3)
    return np.linalg.det(np.moveaxis(e, 0, -1)) / 6.0


def _linear_fields(x, tets, values):
    """Per tetrahedron, ``a`` (m, k, 3) and ``b`` (m, k) with ``f = a . x + b`` matching ``values``
    (k, n) at its vertices."""
    X = np.moveaxis(x[:, tets], 0, -1)  # (m, 4, 3)
    M = X[:, 1:] - X[:, :1]  # (m, 3, 3)
    F = values[:, tets]  # (k, m, 4)
    dF = np.moveaxis(F[:, :, 1:] - F[:, :, :1], 0, -1)  # (m, 3, k)
    a = np.linalg.solve(M, dF)  # (m, 3, k)
    a = np.moveaxis(a, -1, 1)  # (m, k, 3)
    b = F[:, :, 0].T - np.einsum("mkd,md->mk", a, X[:, 0])
    return a, b


STEEP_SLOPE = 1e3  # sim.xray.render's: gentle faces by difference arrays (the reference: all per pixel)


def _shared_faces(faces):
    """Each triangle once: a face two tetrahedra share is rendered once, carrying the difference
    of their weights (its two copies have opposite orientations and the same ``t``), which
    halves the rasterisation. Returns the unique faces and ``merge``, mapping per-tetrahedron
    weights ``(n, m)`` to per-face weights ``(n, faces)``."""
    key = np.sort(faces, axis=1)
    # the orientation of each copy relative to its sorted vertices: the permutation's parity
    order = np.argsort(faces, axis=1, kind="stable")
    parity = ((order[:, 0] > order[:, 1]).astype(int) + (order[:, 0] > order[:, 2]) + (order[:, 1] > order[:, 2])) % 2
    sign = np.where(parity == 0, 1.0, -1.0)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    n_faces = len(uniq)

    def merge(per_tet):
        w = np.repeat(per_tet, 4, axis=1) * sign  # (n, 4 m), in the order of ``faces``
        return np.stack([np.bincount(inverse, wk, minlength=n_faces) for wk in w])

    return uniq, merge


def _upsample(field, factor, shape, general=False):
    """Bilinear interpolation of the coarse grid's ``(n, R, C)`` images onto the detector: pixel
    ``i`` of the detector sits at ``(i - (factor - 1) / 2) / factor`` on the coarse grid, the
    border repeated (``cv2.resize``'s half-pixel alignment is exactly this mapping)."""
    import cv2

    rows, cols = shape
    R, C = field.shape[1:]
    if R * factor == rows and C * factor == cols and not general:
        return np.stack([cv2.resize(f, (cols, rows), interpolation=cv2.INTER_LINEAR) for f in field])
    # a detector not a multiple of the factor, or the reference: the general mapping
    from scipy import ndimage

    i = (np.arange(rows) - (factor - 1) / 2) / factor
    j = (np.arange(cols) - (factor - 1) / 2) / factor
    ii, jj = np.meshgrid(i, j, indexing="ij")
    return np.stack([ndimage.map_coordinates(f, [ii, jj], order=1, mode="nearest") for f in field])


def _ray_integrals(geom, coarse, xb, tets, mu, a, b, *, reference=False):
    """On the coarse grid: ``int mu dl`` and, per component, ``int mu f dl`` (module docstring).

    Every image is a weighted render of the same faces, so the fast path rasterises them once
    per power of ``t`` with all the weights (:func:`sim.xray._render` takes ``(K, m)``), each
    shared face once (:func:`_shared_faces`)."""
    from sim.xray import _render

    w_dir, e_u, e_v = coarse.frame()
    c = np.array(coarse.centre_mm)
    pitch = coarse.pixel_size_mm
    R, C = coarse.shape
    u = ((np.arange(C) - (C - 1) / 2) * pitch)[None, :]
    v = (((R - 1) / 2 - np.arange(R)) * pitch)[:, None]
    cone = geom.kind != "parallel"
    s_, D = geom.source_distance_mm, geom.source_distance_mm + geom.detector_distance_mm
    lam_c = s_ / D if cone else 0.0
    w1, w2 = [mu], []  # per-tetrahedron weights of the renders of t and of t^2
    for k in range(2):
        ak, bk = a[:, k], b[:, k]
        au, av, aw = ak @ e_u, ak @ e_v, ak @ w_dir
        if not cone:
            w1 += [mu * (ak @ c + bk), mu * au, mu * av]
            w2 += [mu * aw]
        else:
            w1 += [mu * (ak @ (c - s_ * w_dir) + lam_c * D * aw + bk), mu * au, mu * av]
            w2 += [mu * D * aw, mu * au, mu * av]
    faces = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)  # outward, 4 per tet
    if reference:
        r1 = np.stack([_render(coarse, xb, faces, np.repeat(w, 4), 1, 0.0, power=1) for w in w1])
        r2 = np.stack([_render(coarse, xb, faces, np.repeat(w, 4), 1, 0.0, power=2) for w in w2])
    else:
        faces, merge = _shared_faces(faces)
        r1 = _render(coarse, xb, faces, merge(np.stack(w1)), 1, STEEP_SLOPE, power=1)
        r2 = _render(coarse, xb, faces, merge(np.stack(w2)), 1, STEEP_SLOPE, power=2)
    num = []
    for k in range(2):
        const, ru, rv = r1[1 + 3 * k : 4 + 3 * k]
        if not cone:
            num.append(const + u * ru + v * rv + r2[k] / 2)
        else:
            length = np.sqrt(D * D + u * u + v * v)
            q_w, q_u, q_v = r2[3 * k : 3 * k + 3]
            num.append(const + lam_c * (u * ru + v * rv) + (q_w + u * q_u + v * q_v) / (2 * length))
    return r1[0], num


_SILHOUETTE: list = []  # [(fem, geometry, displacement, body)]: the last fixed state's, reused


def _silhouette(fem, geom, displacement, thickness):
    """Where the fixed state's body covers the full-resolution detector. The pairs of one
    experiment share their fixed states (1->3, 2->3), so the last one is kept."""
    from sim.xray import path_lengths

    for f, g, d, body in _SILHOUETTE:
        if f is fem and g == geom and d is displacement:
            return body
    body = path_lengths(fem, geom, displacement, thickness_mm=thickness).sum(axis=0) > 0
    _SILHOUETTE[:] = [(fem, geom, displacement, body)]
    return body


def truth_displacement(
    scene, fixed, moving, *, factor=None, revolve_segments=64, geometry=None, body=None, _reference=False
) -> np.ndarray:
    """Pull displacement (2, rows, cols) float32, pixels, registering ``moving`` onto ``fixed``.

    ``fixed`` and ``moving`` are :class:`sim.mechanics.State` from one ``compress`` call (one mesh).
    ``geometry`` (a :class:`sim.xray.Geometry`) replaces the scene's beam and detector.
    ``factor`` (default 4, or 1 for detectors of at most 600 pixels) is the coarsening of the grid
    the ray integrals are computed on. ``body``, optional: where the fixed state's body covers the
    detector (rows, cols) bool, if the caller has it (its line integral > 0, when every material
    attenuates); otherwise it is rendered. See the module docstring for the definition.

    ``_reference=True`` runs the original, slower evaluation (one rasterisation per image, every
    tetrahedron's four faces, each face per pixel, ``scipy.ndimage`` interpolation, the silhouette
    rendered): the tests check the fast path against it.
    """
    from scipy import ndimage

    from sim.xray import Geometry

    solver = getattr(fixed, "solver", None)
    if solver is None or getattr(moving, "solver", None) is not solver:
        raise ValueError("truth_displacement: both states must come from the same compress() call (one mesh)")
    fem = getattr(solver, "projection_mesh", None) or solver.fem
    geom = geometry if geometry is not None else Geometry.from_scene(scene)
    rows, cols = geom.shape
    if factor is None:
        factor = 1 if max(rows, cols) <= 600 else 4
    factor = int(factor)
    thickness = float(scene.body.size_mm[2]) if fem.model == "plane-strain" else None
    (xb, xa), tets, region = body_tetrahedra(
        fem, [fixed.displacement, moving.displacement], revolve_segments=revolve_segments, thickness_mm=thickness
    )
    mus = np.array([scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions])
    mu = mus[region]
    # projected motion in detector pixels at every vertex
    cb, rb, _ = geom._project(xb, 1)
    ca, ra, _ = geom._project(xa, 1)
    values = np.stack([ra - rb, ca - cb])  # (2, k): row, col
    a, b = _linear_fields(xb, tets, values)  # (m, 2, 3), (m, 2)

    R, C = -(-rows // factor), -(-cols // factor)
    coarse = Geometry(
        geom.kind,
        geom.direction,
        (R, C),
        geom.pixel_size_mm * factor,
        geom.centre_mm,
        geom.source_distance_mm,
        geom.detector_distance_mm,
    )
    denominator, num = _ray_integrals(geom, coarse, xb, tets, mu, a, b, reference=_reference)
    on = denominator > 1e-9 * max(float(denominator.max()), 1e-300)
    field = np.zeros((2, R, C))
    for k in range(2):
        field[k][on] = num[k][on] / denominator[on]
    if factor > 1:
        if on.any() and not on.all():  # extend the field past the silhouette before interpolating
            idx = ndimage.distance_transform_edt(~on, return_distances=False, return_indices=True)
            field = field[:, idx[0], idx[1]]
        field = _upsample(field, factor, (rows, cols), general=_reference)
        if body is None or _reference:
            body = _silhouette(fem, geom, fixed.displacement, thickness)
        elif np.shape(body) != (rows, cols):
            raise ValueError(f"body: shape {np.shape(body)}, expected the detector's {(rows, cols)}")
    else:
        body = on
    field[:, ~body] = 0.0
    return field.astype(np.float32)
