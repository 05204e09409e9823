"""Exact X-ray path lengths through the (deformed) finite-element mesh, and line integrals.

``project(scene, state)`` returns the line integral ``sum_m mu_m L_m`` (dimensionless) on the
scene's detector grid, where ``L_m`` is the length of each pixel's ray inside material region
``m`` of the deformed mesh (straight-sided: linear geometry between the displaced vertices).
``path_lengths`` returns the ``L_m`` themselves; ``render`` is the core, for any closed, oriented
triangle surfaces.

Detector frame
--------------
The beam runs along ``+w`` with ``w = +y`` or ``+z`` (``Beam.direction``). Detector columns
follow world ``+x`` (``e_u``) in both cases; rows follow ``z`` for a beam along ``y`` and ``y``
for a beam along ``z`` (``e_v``), **row 0 at the top, i.e. at the largest z (or y)**. So the
compression axis ``y`` is vertical in side views (``pva-phantom``: top plate at row 0) and the
chest wall ``x = 0`` of ``seed-breast`` is on the left.

The detector is centred on the *isocentre* ``c``: the centre of the undeformed body's bounding
box (:func:`body_centre`; it does not move between states, so the images register). Pixel
``(i, j)`` has its centre at ``u = (j - (cols - 1) / 2) p``, ``v = ((rows - 1) / 2 - i) p`` on the
detector, ``p = Detector.pixel_size_mm``.

- parallel: the ray of pixel ``(i, j)`` is the line ``c + u e_u + v e_v + t w``.
- cone: the source is at ``S = c - s w`` (``s = source_distance_mm``), the detector plane at
  ``c + d w`` (``d = detector_distance_mm``); the ray runs from ``S`` to the pixel centre
  ``c + d w + u e_u + v e_v``. Pixels are ``p`` wide on the detector, ``p / M`` at the isocentre,
  ``M = (s + d) / s``. The source is a point: a focal spot of size ``f`` would blur a point at
  distance ``s'`` from it by ``f ((s + d) / s' - 1)`` on the detector, for ``pva-phantom`` (``s``
  400, ``d`` 100 mm, the body's near side at ``s'`` = 375 mm) a third of ``f``: at most 17 um, a
  third of a 50 um pixel, for the L8121's largest spot (about 5-50 um, ../shared/hardware/L8121.md).

Surfaces
--------
Each material region is bounded by the faces of its tetrahedra that no other tetrahedron of the
region shares, oriented outward. An interface face between two regions is stored once, with the
region it points out of (``inside``) and the one it points into (``outside``, -1 for the exterior).
So the body's boundary includes the inclusion interface, facing into the inclusion: ``L_body`` is
the gel-only path. Models cut by symmetry planes (``FEMesh.symmetry``) are mirrored: faces lying
on a symmetry plane are dropped (they are interior to the whole body), the remaining faces are
reflected with reversed vertex order, and vertices on the plane are shared by both halves, so the
mirrored surface is closed. Two-dimensional models are swept into three-dimensional surfaces:

- ``axisymmetric``: the (r, y) region boundaries (edges on the axis r = 0 dropped) are revolved
  about y into ``N`` azimuthal segments, ``(r, y) -> (r cos phi, y, r sin phi)``. The revolved
  polygon is inscribed in the true surface of revolution; its largest radial deviation is
  ``r (1 - cos(pi / N))``. ``N`` is the smallest multiple of 4 with ``1 - cos(pi / N) <=
  revolve_tol`` (default ``1e-5``: ``N = 704``, a deviation of 0.25 um at r = 25 mm); a chord at
  offset ``rho`` from the axis then errs by at most about ``revolve_tol r^2 / (r^2 - rho^2)``
  relative.
- ``plane-strain``: the (x, y) section is extruded to a slab ``|z| <= thickness / 2`` (the
  scene's ``body.size_mm[2]``; in plane strain the thickness does not change). ``build_mesh``
  meshes only the half ``x >= 0`` of a plane-strain section (the mechanics holds ``u_x = 0`` on
  ``x = 0``); a plane-strain mesh lying in ``x >= 0`` is therefore mirrored across ``x = 0``.

Signed-depth rasterisation
--------------------------
For a closed surface with outward normals, the chord of a ray is ``sum_f s_f t_f`` over the faces
``f`` it crosses, with ``t_f`` the position of the crossing along the ray and ``s_f = +1`` where
the ray leaves the solid (the face points away from the source), ``-1`` where it enters. Each
triangle is projected onto the detector grid and contributes to the pixels whose centres it
covers:

- coverage is decided per pixel row (scanline), with half-open rules: an edge covers the rows
  ``y0 <= i < y1`` of its endpoints (sorted by y) and a triangle the columns ``xl <= j < xr`` of
  its two edge crossings. Each edge crossing is computed from the edge's own two endpoints in a
  canonical order, so two triangles sharing an edge compute it bit for bit alike: a pixel centre
  on a shared edge is counted by exactly one of two triangles lying on either side of it, and by
  both or neither of two triangles folding over it (the silhouette, where their depths coincide).
  The surface is therefore watertight on the grid: chords of polyhedra are exact to rounding.
- parallel beam: ``t`` is an affine function of the pixel coordinates over a triangle. Each
  covered row segment adds the affine function's coefficients to two difference arrays (constant
  and column slope) at its first and one-past-last column; cumulative sums along the rows then
  give ``sum_f s_f t_f`` for every pixel at once. ``t`` is measured from the isocentre plane so
  the values stay small (rounding ~1e-13 mm). Triangles seen almost edge-on (depth slope above
  ``steep_slope``, default 1000) would make the difference arrays ill-conditioned; they are
  evaluated pixel by pixel instead, their depth clamped to the triangle's range of vertex depths.
- cone beam: with the ray ``S + lambda (P - S)`` to the pixel centre ``P``, ``1 / lambda`` is an
  affine function of the detector coordinates over a triangle's plane (``lambda = h / n.(P - S)``
  for the plane ``n.(X - S) = h``). It is interpolated from the vertices and inverted per covered
  pixel (clamped to the triangle's range of vertex ``lambda``, which only fixes rounding), the sum
  ``sum_f s_f (lambda_f - lambda_c)`` accumulated per pixel (``lambda_c`` is the isocentre plane)
  and finally multiplied by ``|P - S|``. This is exact for straight-sided triangles.
- pixels no triangle covers are exactly 0, and results are clamped at 0 (a path length, or a
  line integral with ``mu >= 0``, is never negative; only rounding can make it so). Triangles
  whose projection has zero area are skipped (they cover no pixel under the rules above).
- ``supersample = s`` renders the grid at ``s x s`` sub-rays per pixel (sub-pixel centres at
  ``((k + 1/2) / s - 1/2) p``) and averages them; the cost grows about as ``s^2``. The grid is
  processed in bands of rows, so memory stays below ~0.3 GB whatever ``s``.

Cost: a few full-grid passes plus work proportional to the covered row segments (parallel) or
covered pixels (cone, per surface layer). One 2240 x 2240 projection of the presets takes
0.15-0.45 s on two cores (``benchmarks/bench_project.py``); the surface topology is cached per
mesh.

Examples
--------
A 10 mm cube of one tetrahedral mesh (6 tets), parallel beam along y:

>>> import numpy as np
>>> from sim.mesh import FEMesh
>>> p = 5.0 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float).T
>>> cube = FEMesh(p, _CUBE_TETS.T.copy(), np.zeros(6, int), "3d")
>>> g = Geometry("parallel", "y", shape=(3, 3), pixel_size_mm=6.0)
>>> path_lengths(cube, g)[0]
array([[ 0.,  0.,  0.],
       [ 0., 10.,  0.],
       [ 0.,  0.,  0.]])
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

__all__ = ["Geometry", "Surface", "body_centre", "surface_of", "render", "path_lengths", "line_integral", "project"]

_AXIS = {"x": 0, "y": 1, "z": 2}
# beam direction -> (w, e_u (columns), e_v (rows, pointing to row 0))
_FRAMES = {
    "y": ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "z": ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
}
# the 6 tetrahedra of a cube with vertices numbered 4 x + 2 y + z (x, y, z in {0, 1}), around the
# main diagonal 0-7 (used in examples and tests)
_CUBE_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
_BAND_CELLS = 1 << 22  # grid cells per band of rows (about 50 bytes each while a band is processed)
_CHUNK_PIXELS = 1 << 22  # covered pixels evaluated at once on the per-pixel path


# -- geometry ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Geometry:
    """Beam and detector: where each pixel's ray runs (see the module docstring for the frame).

    Parameters
    ----------
    kind : {"parallel", "cone"}
    direction : {"y", "z"}
        The beam runs along +direction.
    shape : (rows, cols)
    pixel_size_mm : float
        Pixel pitch on the detector.
    centre_mm : 3 floats
        The isocentre: the detector's centre line passes through it; the cone-beam source is
        ``source_distance_mm`` before it and the detector ``detector_distance_mm`` behind it.
    source_distance_mm, detector_distance_mm : float
        Cone beams only.
    """

    kind: str = "parallel"
    direction: str = "y"
    shape: tuple = (2240, 2240)
    pixel_size_mm: float = 0.05
    centre_mm: tuple = (0.0, 0.0, 0.0)
    source_distance_mm: float = 500.0
    detector_distance_mm: float = 100.0

    def __post_init__(self):
        if self.kind not in ("parallel", "cone"):
            raise ValueError(f"beam kind {self.kind!r}: expected 'parallel' or 'cone'")
        if self.direction not in _FRAMES:
            raise ValueError(f"beam direction {self.direction!r}: expected 'y' or 'z'")
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise ValueError(f"detector shape {self.shape!r}: expected (rows, cols) >= 1")
        if not self.pixel_size_mm > 0:
            raise ValueError("pixel size must be > 0")
        if self.kind == "cone" and not (self.source_distance_mm > 0 and self.detector_distance_mm >= 0):
            raise ValueError("cone beam: need source_distance_mm > 0 and detector_distance_mm >= 0")
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))
        object.__setattr__(self, "centre_mm", tuple(float(c) for c in self.centre_mm))

    @classmethod
    def from_scene(cls, scene) -> Geometry:
        """The scene's beam and detector, centred on :func:`body_centre`."""
        b = scene.beam
        return cls(
            b.kind,
            b.direction,
            tuple(scene.detector.shape),
            float(scene.detector.pixel_size_mm),
            body_centre(scene),
            float(b.source_distance_mm),
            float(b.detector_distance_mm),
        )

    @property
    def magnification(self) -> float:
        if self.kind == "parallel":
            return 1.0
        return (self.source_distance_mm + self.detector_distance_mm) / self.source_distance_mm

    def frame(self):
        """``(w, e_u, e_v)``: beam direction, column axis, row axis (towards row 0), unit vectors."""
        return tuple(np.array(v) for v in _FRAMES[self.direction])

    def _grid(self, s):
        rows, cols = self.shape
        return rows * s, cols * s, self.pixel_size_mm / s

    def rays(self, supersample: int = 1):
        """``(origin, direction)``, each (3, rows*s, cols*s): one ray per (sub-)pixel centre.

        Parallel: the origin is the pixel centre moved into the plane through the isocentre normal
        to the beam. Cone: the origin is the source. Directions are unit vectors.
        """
        R, C, pitch = self._grid(int(supersample))
        w, eu, ev = self.frame()
        u = (np.arange(C) - (C - 1) / 2) * pitch
        v = ((R - 1) / 2 - np.arange(R)) * pitch
        c = np.array(self.centre_mm)[:, None, None]
        plane = eu[:, None, None] * u[None, None, :] + ev[:, None, None] * v[None, :, None]
        if self.kind == "parallel":
            return c + plane, np.broadcast_to(w[:, None, None], (3, R, C)).copy()
        src = c - self.source_distance_mm * w[:, None, None]
        d = plane + (self.source_distance_mm + self.detector_distance_mm) * w[:, None, None]
        d = d / np.sqrt(np.sum(d * d, axis=0))
        return np.broadcast_to(src, (3, R, C)).copy(), d

    def _project(self, X, s):
        """Fine-grid pixel coordinates ``x`` (column), ``y`` (row) of points X (3, n) and the
        attribute that is affine over a triangle: depth ``t`` from the isocentre plane (parallel) or
        ``1 / lambda`` (cone)."""
        R, C, pitch = self._grid(s)
        w, eu, ev = self.frame()
        rel = X - np.array(self.centre_mm)[:, None]
        u, v, t = eu @ rel, ev @ rel, w @ rel
        if self.kind == "parallel":
            return u / pitch + (C - 1) / 2, (R - 1) / 2 - v / pitch, t
        depth = t + self.source_distance_mm  # distance from the source along w
        if not np.all(depth > 0):
            raise ValueError("cone beam: part of the mesh is at or behind the source plane")
        D = self.source_distance_mm + self.detector_distance_mm
        scale = D / depth
        return u * scale / pitch + (C - 1) / 2, (R - 1) / 2 - v * scale / pitch, scale


def body_centre(scene) -> tuple:
    """Centre of the undeformed body's bounding box: the isocentre of ``Geometry.from_scene``
    (the hemi-ellipsoid spans ``0 <= x <= a``; every other body is centred on the origin)."""
    b = scene.body
    if b.geometry == "hemi-ellipsoid":
        return (b.semi_axes_mm[0] / 2, 0.0, 0.0)
    return (0.0, 0.0, 0.0)


# -- surfaces ---------------------------------------------------------------------------------------
@dataclass
class Surface:
    """Closed, outward-oriented triangulated region boundaries of a mesh (topology only).

    Surface vertex ``k`` sits at ``coef[:, :, k] @ x[:, src[k]] + offset[:, k]``, with ``x`` the
    (deformed) model vertex coordinates, so one ``Surface`` serves every state of a mesh.

    Attributes
    ----------
    faces : (m, 3) int
        Triangles, counter-clockwise seen from the side their normal points to.
    inside, outside : (m,) int
        The region each face's normal points out of, and into (-1: the exterior).
    src : (k,) int
    coef : (3, dim, k) float
    offset : (3, k) float
    n_regions : int
    """

    faces: np.ndarray
    inside: np.ndarray
    outside: np.ndarray
    src: np.ndarray
    coef: np.ndarray
    offset: np.ndarray
    n_regions: int

    def vertices(self, x) -> np.ndarray:
        """(3, k) surface vertex positions for model vertex coordinates ``x`` (dim, n)."""
        return np.einsum("adk,dk->ak", self.coef, x[:, self.src]) + self.offset

    def weights(self, per_region) -> np.ndarray:
        """Face weights ``q[inside] - q[outside]`` (``q[-1] = 0``) for region values ``q``: the
        signed sum over faces then gives ``sum_m q_m L_m``."""
        q = np.append(np.asarray(per_region, dtype=float), 0.0)
        if q.size != self.n_regions + 1:
            raise ValueError(f"expected {self.n_regions} region values, got {q.size - 1}")
        return q[self.inside] - q[self.outside]

    def __repr__(self):
        return f"Surface({len(self.faces)} faces, {self.src.size} vertices, {self.n_regions} regions)"


def _unique_facets(facets, region):
    """Facets (m, k) of oriented cells with their cell's region -> the region boundaries.

    A facet used once is on the outer boundary; used twice by cells of different regions, an
    interface (kept once, oriented as the first); used twice within a region, interior (dropped).
    Returns ``(facets, inside, outside)``.
    """
    key = np.sort(facets, axis=1).astype(np.int64)
    n = int(facets.max()) + 1
    if float(n) ** key.shape[1] < 2.0**62:
        code = key[:, 0]
        for c in range(1, key.shape[1]):
            code = code * n + key[:, c]
    else:  # too many vertices for one int64 key
        code = np.unique(key, axis=0, return_inverse=True)[1].ravel()
    order = np.argsort(code, kind="stable")
    cs = code[order]
    first = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    counts = np.diff(np.r_[first, cs.size])
    if counts.max(initial=1) > 2:
        raise ValueError("mesh is not manifold: a facet is shared by more than two cells")
    a = order[first]
    single = counts == 1
    b = order[np.minimum(first + 1, cs.size - 1)]
    two = ~single & (region[a] != region[b])
    keep = single | two
    outside = np.where(two, region[b], -1)
    return facets[a[keep]], region[a[keep]], outside[keep]


def _orient_simplices(p, cells):
    """Cells (m, dim + 1) with positive signed volume (area)."""
    cells = cells.copy()
    x = p[:, cells]  # (dim, m, dim + 1)
    e = x[:, :, 1:] - x[:, :, :1]  # (dim, m, dim)
    vol = np.linalg.det(np.moveaxis(e, 0, -1))
    neg = vol < 0
    cells[neg, 1], cells[neg, 2] = cells[neg, 2].copy(), cells[neg, 1].copy()
    return cells


def _revolutions(revolve_tol):
    if not 0 < revolve_tol < 1:
        raise ValueError(f"revolve_tol must lie in (0, 1), got {revolve_tol}")
    n = math.pi / math.acos(1.0 - revolve_tol)
    return max(8, 4 * math.ceil(n / 4))


def surface_of(fem, *, thickness_mm=None, revolve_tol=1e-5) -> Surface:
    """The closed region boundaries of ``fem`` (a ``sim.mesh.FEMesh``) as a :class:`Surface`.

    Parameters
    ----------
    fem : FEMesh
        ``3d`` (tetrahedra), ``axisymmetric`` or ``plane-strain`` (triangles), mirrored across its
        symmetry planes as described in the module docstring.
    thickness_mm : float, optional
        Slab thickness of a plane-strain model (required for those).
    revolve_tol : float
        Axisymmetric models: largest relative radial deviation of the revolved polygon.
    """
    p = np.asarray(fem.points, dtype=float)
    cells = np.asarray(fem.cells).T.astype(np.int64)
    region = np.asarray(fem.region).astype(np.int64)
    dim = p.shape[0]
    n_regions = int(region.max()) + 1
    tol = 1e-9 * max(float(np.ptp(p, axis=1).max()), 1e-3)
    cells = _orient_simplices(p, cells)
    planes = [_AXIS[a] for a in fem.symmetry]
    if fem.model == "3d":
        if dim != 3 or cells.shape[1] != 4:
            raise ValueError("3d model: expected 3D points and tetrahedra")
        a, b, c, d = cells.T
        facets = np.concatenate([np.stack(f, axis=1) for f in ((a, c, b), (a, b, d), (a, d, c), (b, c, d))])
        faces, inside, outside = _unique_facets(facets, np.tile(region, 4))
        used, faces = np.unique(faces, return_inverse=True)
        faces = faces.reshape(-1, 3)
        coef = np.broadcast_to(np.eye(3)[:, :, None], (3, 3, used.size)).copy()
        offset = np.zeros((3, used.size))
        src = used
    elif fem.model in ("axisymmetric", "plane-strain"):
        if dim != 2 or cells.shape[1] != 3:
            raise ValueError(f"{fem.model} model: expected 2D points and triangles")
        a, b, c = cells.T
        edges = np.concatenate([np.stack(e, axis=1) for e in ((a, b), (b, c), (c, a))])
        edges, inside, outside = _unique_facets(edges, np.tile(region, 3))
        if fem.model == "axisymmetric":
            faces, inside, outside, src, coef, offset = _revolve(
                p, edges, inside, outside, tol, _revolutions(revolve_tol)
            )
        else:
            if thickness_mm is None or not thickness_mm > 0:
                raise ValueError("plane-strain model: give the slab thickness_mm (> 0)")
            faces, inside, outside, src, coef, offset = _extrude(
                p, cells, region, edges, inside, outside, float(thickness_mm)
            )
            if p[0].min() >= -tol and 0 not in planes:
                planes = [0] + planes  # build_mesh's plane-strain sections are the half x >= 0
    else:
        raise ValueError(f"unknown model {fem.model!r}")
    surf = Surface(
        faces.astype(np.int64),
        inside.astype(np.int64),
        outside.astype(np.int64),
        src.astype(np.int64),
        coef,
        offset,
        n_regions,
    )
    for ax in planes:
        surf = _mirror(surf, p, ax, tol)
    return surf


def _revolve(p, edges, inside, outside, tol, N):
    on_axis = p[0] <= tol
    keep = ~(on_axis[edges[:, 0]] & on_axis[edges[:, 1]])
    edges, inside, outside = edges[keep], inside[keep], outside[keep]
    used, e = np.unique(edges, return_inverse=True)
    e = e.reshape(-1, 2)
    ax = on_axis[used]
    copies = np.where(ax, 1, N)
    base = np.concatenate([[0], np.cumsum(copies)[:-1]])
    step = (~ax).astype(np.int64)
    k = np.arange(N)

    def vid(v, kk):  # (m,) vertices, (N,) azimuth indices -> (m, N) ids
        return base[v][:, None] + step[v][:, None] * (kk[None, :] % N)

    P0, Q0, Q1, P1 = vid(e[:, 0], k), vid(e[:, 1], k), vid(e[:, 1], k + 1), vid(e[:, 0], k + 1)
    tri = np.concatenate([np.stack([P0, Q0, Q1], -1).reshape(-1, 3), np.stack([P0, Q1, P1], -1).reshape(-1, 3)])
    ins = np.tile(np.repeat(inside, N), 2)
    outs = np.tile(np.repeat(outside, N), 2)
    ok = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])
    src = np.repeat(used, copies)
    phi = 2 * np.pi * (np.arange(src.size) - np.repeat(base, copies)) / N
    cos, sin = np.cos(phi), np.sin(phi)
    axv = np.repeat(ax, copies)
    cos[axv] = 0.0
    sin[axv] = 0.0
    coef = np.zeros((3, 2, src.size))
    coef[0, 0], coef[1, 1], coef[2, 0] = cos, 1.0, sin
    return tri[ok], ins[ok], outs[ok], src, coef, np.zeros((3, src.size))


def _extrude(p, cells, region, edges, inside, outside, T):
    n = p.shape[1]
    lo, hi = np.arange(n), np.arange(n) + n  # z = -T/2, +T/2 copies
    P, Q = edges[:, 0], edges[:, 1]
    sides = np.concatenate([np.stack([lo[P], lo[Q], hi[Q]], 1), np.stack([lo[P], hi[Q], hi[P]], 1)])
    a, b, c = cells.T
    faces = np.concatenate([sides, np.stack([hi[a], hi[b], hi[c]], 1), np.stack([lo[a], lo[c], lo[b]], 1)])
    ins = np.concatenate([inside, inside, region, region])
    outs = np.concatenate([outside, outside, np.full(2 * len(cells), -1)])
    src = np.concatenate([np.arange(n), np.arange(n)])
    coef = np.zeros((3, 2, 2 * n))
    coef[0, 0], coef[1, 1] = 1.0, 1.0
    offset = np.zeros((3, 2 * n))
    offset[2] = np.repeat([-T / 2, T / 2], n)
    return faces, ins, outs, src, coef, offset


def _mirror(surf: Surface, p, ax, tol) -> Surface:
    """Add the mirror image across the plane {axis ``ax`` = 0} (undeformed positions decide which
    vertices lie on it; those are shared and the faces made of them dropped)."""
    U = surf.vertices(p)
    on = np.abs(U[ax]) <= tol
    keep = ~on[surf.faces].all(axis=1)
    faces, ins, outs = surf.faces[keep], surf.inside[keep], surf.outside[keep]
    k = surf.src.size
    off = np.flatnonzero(~on)
    image = np.arange(k)
    image[off] = k + np.arange(off.size)
    flip = np.ones((3, 1, 1))
    flip[ax] = -1.0
    coef = np.concatenate([surf.coef, surf.coef[:, :, off] * flip], axis=2)
    offset = np.concatenate([surf.offset, surf.offset[:, off] * flip[:, 0]], axis=1)
    faces = np.concatenate([faces, image[faces][:, ::-1]])
    return Surface(
        faces,
        np.tile(ins, 2),
        np.tile(outs, 2),
        np.concatenate([surf.src, surf.src[off]]),
        coef,
        offset,
        surf.n_regions,
    )


_SURFACES: dict = {}


def _cached_surface(fem, thickness_mm, revolve_tol) -> Surface:
    key = (id(fem), thickness_mm, revolve_tol)
    hit = _SURFACES.get(key)
    if hit is not None and hit[0]() is fem and hit[1] == (fem.cells.shape, fem.model, tuple(fem.symmetry)):
        return hit[2]
    surf = surface_of(fem, thickness_mm=thickness_mm, revolve_tol=revolve_tol)
    if len(_SURFACES) > 16:
        _SURFACES.clear()
    try:
        _SURFACES[key] = (weakref.ref(fem), (fem.cells.shape, fem.model, tuple(fem.symmetry)), surf)
    except TypeError:  # not weak-referenceable: do not cache
        pass
    return surf


# -- rasterisation ----------------------------------------------------------------------------------
def render(
    geometry: Geometry, vertices, faces, weights=None, *, supersample: int = 1, steep_slope: float = 1e3
) -> np.ndarray:
    """``sum_f weight_f s_f t_f`` per pixel for oriented triangles: for closed outward-oriented
    surfaces with unit weights, the chord length of each pixel's ray (see the module docstring).

    Parameters
    ----------
    geometry : Geometry
    vertices : (3, n) float
        World coordinates, mm.
    faces : (m, 3) int
        Triangles, counter-clockwise seen from outside (normal = outward).
    weights : (m,) float, optional
        Per-face weights (default 1).
    supersample : int
        ``s x s`` sub-rays per pixel, averaged.
    steep_slope : float
        Parallel beams: faces whose depth changes faster than this (mm per mm across the
        detector) are evaluated per pixel rather than by difference arrays; 0 evaluates all
        faces per pixel (slower; same result to rounding).

    Returns
    -------
    (rows, cols) float64, exactly 0 on pixels no face covers.
    """
    return _render(
        geometry,
        np.asarray(vertices, dtype=float),
        np.asarray(faces, dtype=np.int64),
        np.ones(len(faces)) if weights is None else np.asarray(weights, dtype=float),
        int(supersample),
        float(steep_slope),
    )


def _render(geom, X, faces, weights, s, steep_slope, power=1):
    """The rasteriser behind :func:`render`; ``power`` 2 sums ``s_f w_f t_f^2`` instead (used by
    :mod:`sim.truth` to integrate fields linear along a ray), evaluated per pixel.

    ``weights`` may be ``(K, m)``: K images of the same faces at the cost of one rasterisation
    (returns ``(K, rows, cols)``)."""
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {s}")
    rows, cols = geom.shape
    R, C, pitch = geom._grid(s)
    single = np.ndim(weights) == 1
    weights = np.atleast_2d(weights)
    K = weights.shape[0]
    out = np.zeros((K, rows, cols))
    if len(faces) == 0:
        return out[0] if single else out
    x, y, a = geom._project(X, s)
    w, eu, ev = geom.frame()
    H = float(np.sign(-np.cross(eu, ev) @ w))  # det * H > 0 <=> the ray leaves through the face
    cone = geom.kind == "cone"

    # sort each triangle's vertices by row coordinate
    fy = y[faces]
    order = np.argsort(fy, axis=1, kind="stable")
    f = np.take_along_axis(faces, order, axis=1)
    xa, xb, xc = x[f[:, 0]], x[f[:, 1]], x[f[:, 2]]
    ya, yb, yc = y[f[:, 0]], y[f[:, 1]], y[f[:, 2]]
    aa, ab, ac = a[f[:, 0]], a[f[:, 1]], a[f[:, 2]]
    # affine attribute over the projected triangle: a = aa + gx (x - xa) + gy (y - ya)
    d1x, d1y, d1a = xb - xa, yb - ya, ab - aa
    d2x, d2y, d2a = xc - xa, yc - ya, ac - aa
    det = d1x * d2y - d2x * d1y
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        gx = (d1a * d2y - d2a * d1y) / det
        gy = (d1x * d2a - d2x * d1a) / det
        # edge slopes dx/dy, each from its endpoints in ascending-y order (bitwise shared)
        s_ab = (xb - xa) / (yb - ya)
        s_bc = (xc - xb) / (yc - yb)
        s_ac = (xc - xa) / (yc - ya)
    ok = (det != 0) & np.isfinite(gx) & np.isfinite(gy) & np.any(weights != 0, axis=0)
    ok &= (yc > -1) & (ya < R) & (np.maximum(np.maximum(xa, xb), xc) > -1) & (np.minimum(np.minimum(xa, xb), xc) < C)
    # orientation from the faces' own vertex order (the sort above may permute it)
    x0, x1, x2 = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    y0, y1, y2 = y[faces[:, 0]], y[faces[:, 1]], y[faces[:, 2]]
    orient = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    ok &= orient != 0
    wt = np.where(orient > 0, H, -H) * weights  # (K, m)
    amin = np.minimum(np.minimum(aa, ab), ac)
    amax = np.maximum(np.maximum(aa, ab), ac)
    if cone:
        per_pixel = ok
        lam_c = geom.source_distance_mm / (geom.source_distance_mm + geom.detector_distance_mm)
    else:
        g = steep_slope * pitch
        per_pixel = ok & ((np.abs(gx) > g) | (np.abs(gy) > g)) if power == 1 else ok
    spanned = ok & ~per_pixel

    r0 = np.ceil(np.clip(ya, -1, R)).astype(np.int64)
    r1 = np.ceil(np.clip(yc, -1, R)).astype(np.int64)
    rb = np.ceil(np.clip(yb, -1, R)).astype(np.int64)
    jc, ic = (C - 1) / 2, (R - 1) / 2
    band = max(s, (_BAND_CELLS // (C + 1)) // s * s)
    for b0 in range(0, R, band):
        b1 = min(R, b0 + band)
        nb = b1 - b0
        acc = np.zeros((K, nb, C))
        hits = np.zeros((nb, C), np.int64)
        for sel, pixelwise in ((spanned, False), (per_pixel, True)):
            idx = np.flatnonzero(sel & (r1 > b0) & (r0 < b1))
            if idx.size == 0:
                continue
            lo = np.maximum(r0[idx], b0)
            n = np.maximum(np.minimum(r1[idx], b1) - lo, 0)
            tri = np.repeat(idx, n)
            row = np.arange(tri.size) - np.repeat(np.cumsum(n) - n - lo, n)
            # crossings of the long edge a-c and of the short edge (a-b above b, b-c below)
            yr = row.astype(float)
            xl = xa[tri] + (yr - ya[tri]) * s_ac[tri]
            upper = row < rb[tri]
            with np.errstate(invalid="ignore"):  # the unused branch may be a horizontal edge
                xs = np.where(upper, xa[tri] + (yr - ya[tri]) * s_ab[tri], xb[tri] + (yr - yb[tri]) * s_bc[tri])
            c0 = np.ceil(np.clip(np.minimum(xl, xs), 0, C)).astype(np.int64)
            c1 = np.ceil(np.clip(np.maximum(xl, xs), 0, C)).astype(np.int64)
            good = c1 > c0
            tri, row, yr, c0, c1 = tri[good], row[good], yr[good], c0[good], c1[good]
            if tri.size == 0:
                continue
            # the attribute at the span's first pixel, and its step per column
            a0 = aa[tri] + gx[tri] * (c0 - xa[tri]) + gy[tri] * (yr - ya[tri])
            lrow = row - b0
            if not pixelwise:
                _accumulate_spans(acc, hits, lrow, c0, c1, a0, gx[tri], wt[:, tri], nb, C, jc)
            else:
                _accumulate_pixels(
                    acc,
                    hits,
                    lrow,
                    c0,
                    c1,
                    a0,
                    gx[tri],
                    wt[:, tri],
                    amin[tri],
                    amax[tri],
                    cone,
                    lam_c if cone else 0.0,
                    nb,
                    C,
                    power,
                )
        if cone:  # sum of s (lambda - lambda_c) -> length along the ray
            du = (np.arange(C) - jc) * pitch
            dv = (np.arange(b0, b1) - ic) * pitch
            D = geom.source_distance_mm + geom.detector_distance_mm
            acc *= np.sqrt(D * D + du[None, :] ** 2 + dv[:, None] ** 2) ** power
        acc[:, hits == 0] = 0.0
        if s == 1:
            out[:, b0:b1] = acc
        else:
            out[:, b0 // s : b1 // s] = acc.reshape(K, nb // s, s, cols, s).mean(axis=(2, 4))
    return out[0] if single else out


def _accumulate_spans(acc, hits, row, c0, c1, a0, gx, wt, nb, C, jc):
    """Difference arrays along rows: value(j) = K + G (j - jc) on c0 <= j < c1; ``wt`` (n, spans)
    and ``acc`` (n, nb, C), one image per row of weights."""
    W = C + 1
    i0 = row * W + c0
    i1 = row * W + c1
    K0 = a0 - gx * (c0 - jc)
    idx = np.concatenate([i0, i1])
    size = nb * W
    ramp = np.arange(C) - jc
    for acc_n, wt_n in zip(acc, wt):
        K = wt_n * K0
        G = wt_n * gx
        k = np.bincount(idx, np.concatenate([K, -K]), minlength=size).reshape(nb, W)
        g = np.bincount(idx, np.concatenate([G, -G]), minlength=size).reshape(nb, W)
        np.cumsum(k, axis=1, out=k)
        np.cumsum(g, axis=1, out=g)
        acc_n += k[:, :C]
        acc_n += g[:, :C] * ramp
    h = (np.bincount(i0, minlength=size) - np.bincount(i1, minlength=size)).reshape(nb, W)
    np.cumsum(h, axis=1, out=h)
    hits += h[:, :C]


def _accumulate_pixels(acc, hits, row, c0, c1, a0, gx, wt, amin, amax, cone, lam_c, nb, C, power=1):
    """Evaluate every covered pixel exactly (clamped to the face's range), in chunks; ``wt``
    (n, spans) and ``acc`` (n, nb, C), one image per row of weights."""
    L = c1 - c0
    ends = np.cumsum(L)
    start = 0
    while start < L.size:
        stop = int(np.searchsorted(ends, ends[start] - L[start] + _CHUNK_PIXELS, side="right"))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        Ls = L[sl]
        P = int(Ls.sum())
        first = np.cumsum(Ls) - Ls
        k = np.arange(P) - np.repeat(first, Ls)
        val = np.repeat(a0[sl], Ls) + np.repeat(gx[sl], Ls) * k
        if cone:
            with np.errstate(divide="ignore", over="ignore"):
                val = 1.0 / val  # lambda
            np.clip(val, np.repeat(1.0 / amax[sl], Ls), np.repeat(1.0 / amin[sl], Ls), out=val)
            val -= lam_c
        else:
            np.clip(val, np.repeat(amin[sl], Ls), np.repeat(amax[sl], Ls), out=val)
        if power != 1:
            val **= power
        pix = np.repeat(row[sl] * C + c0[sl], Ls) + k
        for acc_n, wt_n in zip(acc, wt):
            acc_n.ravel()[:] += np.bincount(pix, val * np.repeat(wt_n[sl], Ls), minlength=nb * C)  # contiguous
        hits.ravel()[:] += np.bincount(pix, minlength=nb * C)
        start = stop


# -- meshes and scenes ------------------------------------------------------------------------------
def _deformed(fem, displacement):
    p = np.asarray(fem.points, dtype=float)
    if displacement is None:
        return p
    u = np.asarray(displacement, dtype=float)
    if u.ndim != 2 or u.shape[0] != p.shape[0] or u.shape[1] < p.shape[1]:
        raise ValueError(
            f"displacement of shape {u.shape}: expected ({p.shape[0]}, >= {p.shape[1]}) with the mesh vertices first"
        )
    return p + u[:, : p.shape[1]]


def path_lengths(
    fem,
    geometry: Geometry,
    displacement=None,
    *,
    supersample: int = 1,
    thickness_mm=None,
    revolve_tol: float = 1e-5,
    surface: Surface | None = None,
) -> np.ndarray:
    """Length of each pixel's ray inside each region of the (deformed) mesh.

    Parameters
    ----------
    fem : sim.mesh.FEMesh
        Any ``FEMesh(points, cells, region, model, symmetry)``; region 0 is the body, ``i + 1``
        inclusion ``i``.
    geometry : Geometry
    displacement : (dim, n_dofs) array, optional
        Displacement with the mesh vertices as its first ``n`` columns (``State.displacement``);
        default: the undeformed mesh.
    supersample, thickness_mm, revolve_tol
        See :func:`render` and :func:`surface_of`.
    surface : Surface, optional
        Precomputed ``surface_of(fem, ...)`` (otherwise cached per mesh).

    Returns
    -------
    (n_regions, rows, cols) float64, mm.
    """
    surf = surface if surface is not None else _cached_surface(fem, thickness_mm, revolve_tol)
    X = surf.vertices(_deformed(fem, displacement))
    out = np.empty((surf.n_regions,) + tuple(geometry.shape))
    for m in range(surf.n_regions):
        w = (surf.inside == m).astype(float) - (surf.outside == m)
        sel = w != 0
        out[m] = np.maximum(_render(geometry, X, surf.faces[sel], w[sel], int(supersample), 1e3), 0.0)
    return out


def line_integral(
    fem,
    geometry: Geometry,
    mu_per_mm,
    displacement=None,
    *,
    supersample: int = 1,
    thickness_mm=None,
    revolve_tol: float = 1e-5,
    surface: Surface | None = None,
) -> np.ndarray:
    """``sum_m mu_m L_m`` per pixel (float64), in one pass: each face carries
    ``mu[inside] - mu[outside]`` (interfaces between equal materials vanish). Arguments as for
    :func:`path_lengths`; ``mu_per_mm`` has one non-negative value per region."""
    surf = surface if surface is not None else _cached_surface(fem, thickness_mm, revolve_tol)
    mu = np.asarray(mu_per_mm, dtype=float)
    if np.any(mu < 0):
        raise ValueError("attenuation coefficients must be >= 0")
    X = surf.vertices(_deformed(fem, displacement))
    w = surf.weights(mu)
    sel = w != 0
    return np.maximum(_render(geometry, X, surf.faces[sel], w[sel], int(supersample), 1e3), 0.0)


def project(scene, state=None, *, fem=None, supersample: int = 1, revolve_tol: float = 1e-5) -> np.ndarray:
    """Line integrals ``sum_m mu_m L_m`` (dimensionless) of the deformed ``state`` of ``scene`` on
    the scene's detector grid, float32 (rows, cols).

    Parameters
    ----------
    scene : sim.scene.Scene
        Beam, detector and attenuation (``attenuation_per_mm`` of the body, then the inclusions).
    state : sim.mechanics.State, optional
        A state from ``compress``; its mesh is ``state.solver.fem`` unless ``fem`` is given.
        ``None``: the undeformed mesh (``fem``, or the one a state of the scene is projected on,
        :func:`sim.mesh.undeformed_projection_mesh`: the same geometry as a state at no load).
    fem : FEMesh, optional
    supersample : int
        ``s x s`` sub-rays per pixel; their line integrals are averaged. A pixel integrates
        intensity, so what it measures is ``-ln(mean exp(-L))``, smaller where ``L`` varies across
        it (Jensen): half a pixel behind a slab of line integral ``L`` measures
        ``-ln((1 + e^-L) / 2)``, not ``L / 2``. The simulated experiment renders one ray per pixel.
    revolve_tol : float
        Axisymmetric meshes: see :func:`surface_of`.

    Examples
    --------
    The undeformed 10 mm cube of ``block_scene`` (0.05 /mm), 560 x 560 pixels of 0.2 mm:

    >>> from sim.scene import block_scene
    >>> img = project(block_scene())
    >>> img.shape, img.dtype, float(img.max()), int((img > 0).sum())
    ((560, 560), dtype('float32'), 0.5, 2500)
    """
    solver = getattr(state, "solver", None) if state is not None else None
    if fem is None:  # the P2 nodes as a linear mesh where the solver has it, else its vertices
        fem = getattr(solver, "projection_mesh", None) or getattr(solver, "fem", None)
    if fem is None:
        if state is not None:
            raise ValueError("state has no solver.fem: pass the mesh it was computed on as fem=")
        from sim.mesh import undeformed_projection_mesh

        fem = undeformed_projection_mesh(scene)
    displacement = None
    if state is not None:
        displacement = state.displacement
        dof_points = getattr(solver, "dof_points", None)
        n = fem.points.shape[1]
        tol = 1e-9 * max(1.0, float(np.abs(fem.points).max()))
        if dof_points is not None and (
            dof_points.shape[1] < n
            or dof_points.shape[0] != fem.points.shape[0]
            or not np.allclose(dof_points[:, :n], fem.points, rtol=0, atol=tol)
        ):
            raise ValueError("the state's dofs do not start with this mesh's vertices")
    mu = [scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions]
    n_regions = int(np.max(fem.region)) + 1
    if n_regions > len(mu):
        raise ValueError(f"mesh has {n_regions} regions, scene has {len(mu)} materials")
    mu = mu[:n_regions]
    thickness = float(scene.body.size_mm[2]) if fem.model == "plane-strain" else None
    img = line_integral(
        fem,
        Geometry.from_scene(scene),
        mu,
        displacement,
        supersample=supersample,
        thickness_mm=thickness,
        revolve_tol=revolve_tol,
    )
    return img.astype(np.float32)
