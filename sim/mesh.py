"""Meshing scenes with gmsh: conforming inclusion interfaces, graded sizes, symmetry cuts.

Three kinds of model (``MeshSpec.model``):

- ``3d`` — linear tetrahedra (the mechanics puts P2 fields on them). With ``symmetry`` the body
  is cut by the planes it is symmetric about: ``z = 0`` always (every scene here is symmetric in
  z), ``y = 0`` when the body and its inclusions are symmetric in y (plates close symmetrically),
  ``x = 0`` when the body is symmetric in x and not a hemi-ellipsoid (whose ``x = 0`` face is the
  chest wall). ``seed-breast`` thus becomes a quarter of the hemi-ellipsoid.
- ``axisymmetric`` — triangles in the (r, y) half plane, r >= 0, for bodies of revolution about y
  with inclusions centred on the axis (a box inclusion becomes the cylinder of equal cross-section
  area and height).
- ``plane-strain`` — triangles in the (x, y) plane, for slabs (a box body).

Element sizes grow linearly with distance from the inclusion surfaces, from
``size_inclusion_mm`` to ``size_far_mm`` over ``grading_mm`` (default: 4 inclusion radii).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.scene import Scene

__all__ = ["FEMesh", "build_mesh", "choose_model", "estimate_elements", "check_mesh_size", "MAX_ELEMENTS"]

#: The most elements (tetrahedra, or triangles for the reduced models) a scene may ask gmsh for,
#: by :func:`estimate_elements`. gmsh runs in a child process killed on a stop (:func:`_in_child`),
#: so Ctrl-C no longer waits for it; the bound keeps the memory and time in reason (a 1e-6 mm
#: contact size held gmsh at 1.3 GB for minutes, review s41cli; 80 000 tetrahedra of
#: seed-breast take 2.8 s of gmsh on an idle 2-core machine). It is 20 times the largest mesh
#: the convergence study solved (0.7 / 6 / 1 mm: 4 800 tetrahedra, 24 000 unknowns, 2200 s of
#: mechanics; README), beyond which the mechanics' direct solves would take days anyway.
MAX_ELEMENTS = 100_000


@dataclass
class FEMesh:
    """A mesh with what the mechanics and projection need to know about it.

    Attributes
    ----------
    points : (dim, n) float
        Vertex coordinates, mm (dim 3, or 2 for the (r, y) / (x, y) reduced models).
    cells : (dim + 1, m) int
        Tetrahedra or triangles.
    region : (m,) int
        0 for the body, ``i + 1`` for inclusion ``i``.
    model : str
        ``3d``, ``axisymmetric`` or ``plane-strain``.
    symmetry : tuple of str
        The planes the model was cut by, e.g. ``("y", "z")``: fields are mirrored across them.
    """

    points: np.ndarray
    cells: np.ndarray
    region: np.ndarray
    model: str
    symmetry: tuple = ()
    meta: dict = field(default_factory=dict)

    @property
    def multiplicity(self) -> int:
        """How many copies of the model make the whole body (forces and volumes scale by it)."""
        return 2 ** len(self.symmetry)

    def skfem(self):
        from skfem import MeshTet, MeshTri

        return (MeshTet if self.model == "3d" else MeshTri)(self.points.copy(), self.cells.copy())

    def __repr__(self):
        return (
            f"FEMesh({self.model}, {self.points.shape[1]} vertices, {self.cells.shape[1]} cells, "
            f"symmetry={self.symmetry}, regions={np.bincount(self.region).tolist()})"
        )


def choose_model(scene: Scene) -> str:
    """The cheapest model that represents the scene: axisymmetric for bodies of revolution about
    the compression axis with inclusions on the axis, else 3D (plane strain only on request)."""
    if scene.mesh.model != "auto":
        return scene.mesh.model
    if (
        scene.body.axisymmetric
        and scene.wall == "none"
        and all(abs(inc.centre_mm[0]) < 1e-9 and abs(inc.centre_mm[2]) < 1e-9 for inc in scene.inclusions)
    ):
        return "axisymmetric"
    return "3d"


def _symmetry_planes(scene: Scene) -> tuple:
    if not scene.mesh.symmetry:
        return ()
    planes = []
    b = scene.body
    if b.geometry != "hemi-ellipsoid" and all(abs(i.centre_mm[0]) < 1e-9 for i in scene.inclusions):
        planes.append("x")
    y_sym = b.geometry in ("hemi-ellipsoid", "ellipsoid", "cylinder", "box") and all(
        abs(i.centre_mm[1]) < 1e-9 for i in scene.inclusions
    )
    if y_sym:
        planes.append("y")
    if all(abs(i.centre_mm[2]) < 1e-9 for i in scene.inclusions):
        planes.append("z")
    return tuple(planes)


# -- how many elements a scene asks for --------------------------------------------------------
#: volume of a regular tetrahedron of edge h is h^3 / (6 sqrt 2); area of an equilateral triangle
#: of side h is sqrt(3) / 4 h^2: a mesh of size h holds about measure / (c h^dim) elements
_CELL = {3: 1 / 6, 2: math.sqrt(3) / 4}


def _section(scene: Scene, y: np.ndarray, dim: int) -> np.ndarray:
    """The body's cross-section at heights ``y``: its area (3D, the whole body) or its width at
    ``x >= 0`` (the reduced models' half section)."""
    b = scene.body
    g = b.geometry
    if g in ("ellipsoid", "hemi-ellipsoid"):
        a, bb, c = b.semi_axes_mm
        f = np.clip(1 - (y / bb) ** 2, 0, None)
        if dim == 2:
            return a * np.sqrt(f)
        return math.pi * a * c * f / (2 if g == "hemi-ellipsoid" else 1)
    if g == "box":
        sx, _, sz = b.size_mm
        return np.full_like(y, sx * sz if dim == 3 else sx / 2)
    h = b.height_mm
    if g == "cylinder":
        r = np.full_like(y, b.diameter_mm / 2)
    else:
        r0, r1 = b.bottom_diameter_mm / 2, b.top_diameter_mm / 2
        r = r0 + (r1 - r0) * (y + h / 2) / h
    return math.pi * r * r if dim == 3 else r


def _measure(scene: Scene, y0: float, y1: float, dim: int) -> float:
    """The body's volume (3D) or half section's area (2D) between heights ``y0`` and ``y1``."""
    H = scene.body.half_height_mm
    y0, y1 = max(y0, -H), min(y1, H)
    if y1 <= y0:
        return 0.0
    y = np.linspace(y0, y1, 401)
    return float(np.trapezoid(_section(scene, y, dim), y))


def _shell_elements(s_in, s_far, grading, boundary, radius, room, dim) -> float:
    """Elements beyond those ``s_far`` would make in the graded layers on both sides of an
    inclusion's surface (measure ``boundary``, ``radius`` = dim volume / boundary): the size
    grows linearly from ``s_in`` on the surface to ``s_far`` at ``grading`` from it; outside,
    the layers hold no more than the body's ``room``. Most lie where the size is least, so the
    distance is sampled geometrically from a hundredth of it."""
    d = np.concatenate([[0.0], np.geomspace(s_in / 100, max(grading, radius), 2000)])
    size = s_in + (s_far - s_in) * np.clip(d / max(grading, 1e-300), 0, 1)
    excess = 1 / (_CELL[dim] * size**dim) - 1 / (_CELL[dim] * s_far**dim)
    outside = boundary * (1 + d / radius) ** (dim - 1)
    filled = np.concatenate([[0.0], np.cumsum(np.diff(d) * (outside[1:] + outside[:-1]) / 2)])
    outside = outside * (filled <= room)
    inside = boundary * np.clip(1 - d / radius, 0, None) ** (dim - 1)
    return float(np.trapezoid((outside + inside) * excess, d))


def estimate_elements(scene: Scene, model: str | None = None, spec=None, grading_mm=None) -> dict:
    """About how many elements gmsh makes of ``scene``, by the size each field of
    :class:`sim.scene.MeshSpec` sets: ``{"size_far_mm": n, "size_inclusion_mm": n,
    "size_contact_mm": n}`` (each the elements of the region that field governs, the model's
    share of the body only: a symmetry cut's). Within a factor of 2 of gmsh's count for the
    presets and their refinements (tests/test_sim_scene_checks.py); it costs no meshing.
    ``spec`` and ``grading_mm`` stand for the scene's (:func:`build_mesh`'s overrides)."""
    model = model or choose_model(scene)
    spec, b = spec or scene.mesh, scene.body
    dim = 3 if model == "3d" else 2
    H = b.half_height_mm
    planes = _symmetry_planes(scene)
    if dim == 3:
        share = 1 / 2 ** len(planes)
    else:  # the half section x >= 0, halved again where y = 0 is a symmetry plane
        share = 0.5 if scene.mesh.symmetry and "y" in planes else 1.0
    out = {"size_far_mm": share * _measure(scene, -H, H, dim) / (_CELL[dim] * spec.size_far_mm**dim)}
    if scene.inclusions:
        r_inc = min((i.diameter_mm / 2 if i.shape == "sphere" else min(i.size_mm) / 2) for i in scene.inclusions)
        n = 0.0
        for inc in scene.inclusions:
            if dim == 3:
                boundary = (
                    math.pi * inc.diameter_mm**2
                    if inc.shape == "sphere"
                    else 2
                    * (
                        inc.size_mm[0] * inc.size_mm[1]
                        + inc.size_mm[1] * inc.size_mm[2]
                        + inc.size_mm[0] * inc.size_mm[2]
                    )
                )
                whole = 2 ** len(planes)
            else:  # the section's outline; half of it at x >= 0 where the inclusion sits on x = 0
                w = (
                    inc.size_mm[0]
                    if model == "plane-strain"
                    else 2 * math.sqrt(inc.size_mm[0] * inc.size_mm[2] / math.pi)
                )
                boundary = math.pi * inc.diameter_mm if inc.shape == "sphere" else 2 * (w + inc.size_mm[1])
                whole = (2 if abs(inc.centre_mm[0]) < 1e-9 else 1) * (2 if share < 1 else 1)
            radius = (
                dim * inc.volume_mm3() / boundary
                if dim == 3
                else (inc.diameter_mm / 2 if inc.shape == "sphere" else w * inc.size_mm[1] / (w + inc.size_mm[1]))
            )
            room = _measure(scene, -H, H, dim) * (1 if dim == 3 else 2) - inc.volume_mm3()
            grading = 4 * r_inc if grading_mm is None else grading_mm
            n += _shell_elements(spec.size_inclusion_mm, spec.size_far_mm, grading, boundary, radius, room, dim) / whole
        out["size_inclusion_mm"] = n
    if spec.size_contact_mm is not None:
        band = sum(_measure(scene, y0, y1, dim) for y0, y1 in _contact_band(scene))
        out["size_contact_mm"] = share * band / (_CELL[dim] * spec.size_contact_mm**dim)
    return out


def check_mesh_size(scene: Scene, model: str | None = None, spec=None, grading_mm=None) -> None:
    """ValueError naming the mesh size that would make more than :data:`MAX_ELEMENTS` elements,
    with the estimate (:func:`estimate_elements`), before gmsh runs: gmsh meshed a 1e-6 mm contact
    size for minutes at 1.3 GB and could not be stopped (review s41cli)."""
    spec = spec or scene.mesh
    counts = estimate_elements(scene, model, spec, grading_mm)
    total = sum(counts.values())
    if total <= MAX_ELEMENTS:
        return
    name = max(counts, key=counts.get)
    raise ValueError(
        f"mesh {name} {getattr(spec, name):g} would make about {total:.2g} elements of the "
        f"{scene.body.volume_mm3():.3g} mm^3 body (gmsh meshes at most {MAX_ELEMENTS:,}: sim.mesh.MAX_ELEMENTS): "
        "use a larger size"
    )


def _keeping_signal_handlers(init) -> None:
    """Run ``init`` and put back the handlers of SIGTERM, SIGHUP and SIGQUIT: gmsh's initialisation resets
    them to the default at the C level (Python's ``getsignal`` does not see it), so a ``kill`` or a
    closed terminal then ended ``radiokit sim run`` at once, leaving its temporary file behind,
    instead of through the command's handler, which removes it (README, "Your data is safe")."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():  # handlers live on the main thread
        init()
        return
    from radiokit.interrupts import STOP_SIGNALS

    kept = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS if sig != signal.SIGINT}
    try:
        init()
    finally:
        for sig, handler in kept.items():
            if handler is not None:  # None: set outside Python, nothing to restore
                signal.signal(sig, handler)


_CHILD = "import radiokit.interrupts as i; i.die_with_parent({parent}); import sim.mesh as m; m._child_main()"


def _in_child(name, *args):
    """``name(*args)`` (a gmsh step of this module) in a child Python process, its result back.

    Why: gmsh cannot be stopped. A signal's Python handler runs only when gmsh's C call returns,
    so Ctrl-C or a ``kill`` during ``gmsh.model.mesh.generate`` waited for the whole mesh (2.2 s
    near :data:`MAX_ELEMENTS` on an idle 2-core machine, tens of seconds under load). The child
    is killed (SIGKILL) as soon as this process stops, by whatever exception, and dies with it
    when it is killed (no exception: SIGKILL, the kernel's out-of-memory killer). It runs in its own
    session, so the terminal's Ctrl-C reaches this process alone (one "interrupted" line, no
    traceback of the child's), and gmsh's resetting of signal handlers (SIGTERM, SIGHUP, SIGPIPE
    to their defaults) stays in the child. Costs a Python start and gmsh's import per mesh, about
    0.3 s."""
    import os
    import pickle
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    here = str(Path(__file__).resolve().parent.parent)  # this checkout's sim, installed or not
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")]))}
    # not communicate(): on Ctrl-C it waits 0.25 s for a child that will not stop by itself
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(
            # the child dies with this process (radiokit.interrupts.die_with_parent), asked before
            # sim.mesh's imports: a SIGKILL here runs no ``finally`` to kill it, and it meshed on
            [sys.executable, "-c", _CHILD.format(parent=os.getpid())],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            start_new_session=True,
            env=env,
        )
        try:
            with proc.stdin:
                proc.stdin.write(pickle.dumps((name, args)))
            with proc.stdout:
                out = proc.stdout.read()
            proc.wait()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        try:
            status, value = pickle.loads(out)
        except Exception:
            err.seek(0)
            tail = err.read().decode(errors="replace").strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            raise RuntimeError(f"gmsh's process ended without a mesh: {tail[0]}") from None
    if status == "error":
        raise value
    return value


def _child_main():
    """:func:`_in_child`'s other end: the call from stdin, its result (or exception) to stdout.
    gmsh writes nothing to stdout with ``General.Terminal`` 0; fd 1 goes to stderr all the same
    so that no stray print can corrupt the pickle."""
    import os
    import pickle
    import sys

    result_fd = os.dup(1)
    os.dup2(2, 1)
    name, args = pickle.loads(sys.stdin.buffer.read())
    try:
        reply = ("ok", globals()[name](*args))
    except Exception as exc:  # raised again in the parent, as if gmsh ran there
        reply = ("error", exc)
    with os.fdopen(result_fd, "wb") as f:
        f.write(pickle.dumps(reply))


def _gmsh():
    import gmsh

    if not gmsh.isInitialized():
        _keeping_signal_handlers(lambda: gmsh.initialize(interruptible=False))
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.Verbosity", 1)
    gmsh.clear()
    return gmsh


def _size_field(gmsh, inclusion_entities, dim, spec, grading_mm, contact_band=None):
    """Sizes graded from the inclusion surfaces, and (``spec.size_contact_mm``) at most that size
    within ``contact_band = (y0, y1)`` of the plates, where the body meets them."""
    f = gmsh.model.mesh.field
    fields = []
    if inclusion_entities:
        dist = f.add("Distance")
        f.setNumbers(dist, "SurfacesList" if dim == 3 else "CurvesList", inclusion_entities)
        thr = f.add("Threshold")
        f.setNumber(thr, "InField", dist)
        f.setNumber(thr, "SizeMin", spec.size_inclusion_mm)
        f.setNumber(thr, "SizeMax", spec.size_far_mm)
        f.setNumber(thr, "DistMin", 0.0)
        f.setNumber(thr, "DistMax", grading_mm)
        fields.append(thr)
    if spec.size_contact_mm is not None and contact_band is not None:
        for y0, y1 in contact_band:
            box = f.add("Box")
            f.setNumber(box, "VIn", spec.size_contact_mm)
            f.setNumber(box, "VOut", spec.size_far_mm)
            for k, v in (("XMin", -1e4), ("XMax", 1e4), ("YMin", y0), ("YMax", y1), ("ZMin", -1e4), ("ZMax", 1e4)):
                f.setNumber(box, k, v)
            fields.append(box)
    if fields:
        if len(fields) > 1:
            m = f.add("Min")
            f.setNumbers(m, "FieldsList", fields)
            f.setAsBackgroundMesh(m)
        else:
            f.setAsBackgroundMesh(fields[0])
    small = min(
        [spec.size_far_mm]
        + ([spec.size_inclusion_mm] if inclusion_entities else [])
        + ([spec.size_contact_mm] if spec.size_contact_mm is not None and contact_band else [])
    )
    gmsh.option.setNumber("Mesh.MeshSizeMax", spec.size_far_mm)
    gmsh.option.setNumber("Mesh.MeshSizeMin", small)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)


def _contact_band(scene):
    """The slabs next to the plates (the top ``max(10 %, 2 size_contact)`` of the half height, both
    plates), where curved bodies meet them."""
    H = scene.body.half_height_mm
    band = max(0.1 * H, 2 * (scene.mesh.size_contact_mm or 0.0))
    return ((H - band, H + 1.0), (-H - 1.0, -H + band))


def _extract(gmsh, dim, volumes_by_region):
    """Vertices and cells per region, renumbered compactly."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = coords.reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    etype = 4 if dim == 3 else 2
    cells, region = [], []
    for reg, entities in volumes_by_region.items():
        for ent in entities:
            et, _, nodes = gmsh.model.mesh.getElements(dim, ent)
            for t, n in zip(et, nodes):
                if t != etype:
                    continue
                c = index[n.astype(np.int64)].reshape(-1, dim + 1)
                cells.append(c)
                region.append(np.full(len(c), reg, np.int64))
    cells = np.concatenate(cells)
    region = np.concatenate(region)
    used = np.unique(cells)
    remap = np.full(coords.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    pts = coords[used, :dim].T.copy()
    return pts, remap[cells].T.copy(), region


def _fragment_regions(gmsh, parts, dim):
    """Fragment the body and inclusion pieces into one conforming geometry.

    ``parts[0]`` holds the body's entities, ``parts[i]`` inclusion i's. A fragment belongs to the
    last group that produced it (inclusions overwrite the body). Returns the entities per region
    and the boundary entities of the inclusions (where the mesh is finest).
    """
    occ = gmsh.model.occ
    flat = [(dim, t) for group in parts for t in group]
    _, out_map = occ.fragment(flat[:1], flat[1:]) if len(flat) > 1 else (flat, [flat])
    occ.synchronize()
    owner = {}
    k = 0
    for gi, group in enumerate(parts):
        for _ in group:
            for _, tag in out_map[k]:
                owner[tag] = gi
            k += 1
    regions = {}
    for tag, reg in owner.items():
        regions.setdefault(reg, []).append(tag)
    interfaces = [
        b[1]
        for reg, tags in regions.items()
        if reg > 0
        for t in tags
        for b in gmsh.model.getBoundary([(dim, t)], oriented=False)
    ]
    return regions, interfaces


def build_mesh(
    scene: Scene, model: str | None = None, *, size_inclusion_mm=None, size_far_mm=None, grading_mm=None
) -> FEMesh:
    """Mesh ``scene`` with gmsh (see the module docstring for the models and symmetry use)."""
    import dataclasses

    scene.validate()  # before gmsh: its fields may have been replaced since it was made
    model = model or choose_model(scene)
    spec = dataclasses.replace(
        scene.mesh,
        **{k: v for k, v in (("size_inclusion_mm", size_inclusion_mm), ("size_far_mm", size_far_mm)) if v is not None},
    )
    if scene.inclusions:
        r_inc = min((i.diameter_mm / 2 if i.shape == "sphere" else min(i.size_mm) / 2) for i in scene.inclusions)
    else:
        r_inc = spec.size_far_mm
    grading = grading_mm if grading_mm is not None else 4 * r_inc
    check_mesh_size(scene, model, spec, grading)  # the sizes given here may be finer than the scene's
    if model == "3d":
        return _build_3d(scene, spec, grading)
    if model == "axisymmetric":
        return _build_axisymmetric(scene, spec, grading)
    if model == "plane-strain":
        return _build_plane_strain(scene, spec, grading)
    raise ValueError(f"unknown model {model!r}")


def _body_3d(occ, b):
    g = b.geometry
    if g in ("ellipsoid", "hemi-ellipsoid"):
        a, bb, c = b.semi_axes_mm
        s = occ.addSphere(0, 0, 0, 1.0)
        occ.dilate([(3, s)], 0, 0, 0, a, bb, c)
        if g == "hemi-ellipsoid":
            cut = occ.addBox(-2 * a, -2 * bb, -2 * c, 2 * a, 4 * bb, 4 * c)
            occ.cut([(3, s)], [(3, cut)])
        return s
    if g == "truncated-cone":
        h = b.height_mm
        return occ.addCone(0, -h / 2, 0, 0, h, 0, b.bottom_diameter_mm / 2, b.top_diameter_mm / 2)
    if g == "cylinder":
        h = b.height_mm
        return occ.addCylinder(0, -h / 2, 0, 0, h, 0, b.diameter_mm / 2)
    sx, sy, sz = b.size_mm
    return occ.addBox(-sx / 2, -sy / 2, -sz / 2, sx, sy, sz)


def _inclusion_3d(occ, inc):
    cx, cy, cz = inc.centre_mm
    if inc.shape == "sphere":
        return occ.addSphere(cx, cy, cz, inc.diameter_mm / 2)
    sx, sy, sz = inc.size_mm
    return occ.addBox(cx - sx / 2, cy - sy / 2, cz - sz / 2, sx, sy, sz)


def _keep_positive(occ, tags, planes, big):
    """Intersect every volume with the half-spaces {axis >= 0} of the symmetry planes."""
    if not planes:
        return tags
    lo = [-big if ax not in planes else 0.0 for ax in "xyz"]
    box = occ.addBox(lo[0], lo[1], lo[2], big - lo[0], big - lo[1], big - lo[2])
    out = []
    for t in tags:
        res, _ = occ.intersect([(3, t)], [(3, box)], removeTool=False)
        out.append([e[1] for e in res])
    occ.remove([(3, box)], recursive=True)
    return out


def _build_3d(scene, spec, grading):
    pts, cells, region = _in_child("_gmsh_3d", scene, spec, grading)
    cells = _orient_tets(pts, cells)
    return FEMesh(
        pts,
        cells,
        region,
        "3d",
        _symmetry_planes(scene),
        meta={"size_inclusion_mm": spec.size_inclusion_mm, "size_far_mm": spec.size_far_mm, "grading_mm": grading},
    )


def _gmsh_3d(scene, spec, grading):
    gmsh = _gmsh()
    occ = gmsh.model.occ
    planes = _symmetry_planes(scene)
    big = 10 * max(
        scene.body.semi_axes_mm
        + scene.body.size_mm
        + (scene.body.height_mm, scene.body.diameter_mm, scene.body.top_diameter_mm)
    )
    body = _body_3d(occ, scene.body)
    incs = [_inclusion_3d(occ, i) for i in scene.inclusions]
    parts = _keep_positive(occ, [body] + incs, planes, big) if planes else [[body]] + [[i] for i in incs]
    volumes, inc_surfaces = _fragment_regions(gmsh, parts, 3)
    _size_field(gmsh, inc_surfaces, 3, spec, grading, _contact_band(scene))
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.model.mesh.generate(3)
    pts, cells, region = _extract(gmsh, 3, volumes)
    gmsh.clear()
    return pts, cells, region


def _orient_tets(p, t):
    """Positive-volume vertex order (gmsh's is, but make it a guarantee)."""
    a, b, c, d = (p[:, t[i]] for i in range(4))
    vol = np.einsum("ij,ij->j", np.cross(b - a, c - a, axis=0), d - a)
    t = t.copy()
    neg = vol < 0
    t[1, neg], t[2, neg] = t[2, neg].copy(), t[1, neg].copy()
    return t


def _profile_2d(scene):
    """The (r, y) outline of a body of revolution, as a closed polygon or an ellipse quarter."""
    b = scene.body
    if b.geometry == "truncated-cone":
        h = b.height_mm
        return [(0, -h / 2), (b.bottom_diameter_mm / 2, -h / 2), (b.top_diameter_mm / 2, h / 2), (0, h / 2)]
    if b.geometry == "cylinder":
        h, r = b.height_mm, b.diameter_mm / 2
        return [(0, -h / 2), (r, -h / 2), (r, h / 2), (0, h / 2)]
    if b.geometry == "box":
        sx, sy, _ = b.size_mm
        return [(0, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (0, sy / 2)]
    return None


def _build_2d(scene, spec, grading, model):
    pts, cells, region = _in_child("_gmsh_2d", scene, spec, grading, model)
    a, b2, c = (pts[:, cells[i]] for i in range(3))
    area = (b2[0] - a[0]) * (c[1] - a[1]) - (b2[1] - a[1]) * (c[0] - a[0])
    neg = area < 0
    cells[1, neg], cells[2, neg] = cells[2, neg].copy(), cells[1, neg].copy()
    planes = ("y",) if scene.mesh.symmetry and "y" in _symmetry_planes(scene) else ()
    return FEMesh(
        pts,
        cells,
        region,
        model,
        planes,
        meta={"size_inclusion_mm": spec.size_inclusion_mm, "size_far_mm": spec.size_far_mm, "grading_mm": grading},
    )


def _gmsh_2d(scene, spec, grading, model):
    gmsh = _gmsh()
    occ = gmsh.model.occ
    b = scene.body
    y_sym = scene.mesh.symmetry and "y" in _symmetry_planes(scene)
    prof = _profile_2d(scene)
    if prof is not None:
        pts = [occ.addPoint(x, y, 0) for x, y in prof]
        lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
        body = occ.addPlaneSurface([occ.addCurveLoop(lines)])
    elif b.geometry == "ellipsoid":
        a, bb, _ = b.semi_axes_mm
        body = occ.addDisk(0, 0, 0, a, bb) if a >= bb else occ.addDisk(0, 0, 0, bb, a, zAxis=[0, 0, 1], xAxis=[0, 1, 0])
    else:
        raise ValueError(f"{b.geometry} has no axisymmetric or plane-strain section")
    incs = []
    for inc in scene.inclusions:
        cx, cy, _ = inc.centre_mm
        if inc.shape == "sphere":
            incs.append(occ.addDisk(cx, cy, 0, inc.diameter_mm / 2, inc.diameter_mm / 2))
        else:
            sx, sy, sz = inc.size_mm
            # a box about the axis becomes the cylinder of equal cross-section area
            w = 2 * math.sqrt(sx * sz / math.pi) if model == "axisymmetric" else sx
            incs.append(occ.addRectangle(cx - w / 2, cy - sy / 2, 0, w, sy))
    big = 1e4
    box = occ.addRectangle(0, -big if not y_sym else 0, 0, big, 2 * big if not y_sym else big)
    parts = []
    for t in [body] + incs:
        res, _ = occ.intersect([(2, t)], [(2, box)], removeTool=False)
        parts.append([e[1] for e in res])
    occ.remove([(2, box)], recursive=True)
    surfaces, inc_curves = _fragment_regions(gmsh, parts, 2)
    _size_field(gmsh, inc_curves, 2, spec, grading, _contact_band(scene))
    gmsh.option.setNumber("Mesh.Algorithm", 6)
    gmsh.model.mesh.generate(2)
    pts, cells, region = _extract(gmsh, 2, surfaces)
    gmsh.clear()
    return pts, cells, region


def _build_axisymmetric(scene, spec, grading):
    if not scene.body.axisymmetric:
        raise ValueError(f"scene {scene.name!r}: a {scene.body.geometry} is not a body of revolution about y")
    for inc in scene.inclusions:
        if abs(inc.centre_mm[0]) > 1e-9 or abs(inc.centre_mm[2]) > 1e-9:
            raise ValueError(f"scene {scene.name!r}: inclusion at {inc.centre_mm} is off the axis")
    return _build_2d(scene, spec, grading, "axisymmetric")


def _build_plane_strain(scene, spec, grading):
    if scene.body.geometry not in ("box",):
        raise ValueError(f"scene {scene.name!r}: plane strain needs a slab (box body)")
    return _build_2d(scene, spec, grading, "plane-strain")


# -- curved (isoparametric) geometry ---------------------------------------------------------------
def _curved_surfaces(scene: Scene, model: str):
    """The scene's curved surfaces as ``(on(X) -> bool, snap(X) -> X)`` on 3D coordinates
    (sections embed as ``(r or x, y, 0)``). Flat faces need nothing: straight edges lie on them."""
    body = scene.body
    size = max(body.half_height_mm, 1.0)
    tol = 1e-6 * size
    out = []
    if body.geometry in ("ellipsoid", "hemi-ellipsoid"):
        s = np.asarray(body.semi_axes_mm, float)[:, None]
        if model != "3d":
            s = np.array([[s[0, 0]], [s[1, 0]], [s[0, 0]]])  # (r, y): r scales with a (= c)

        def q(X):
            return np.sqrt(np.sum((X / s) ** 2, axis=0))

        out.append((lambda X: np.abs(q(X) - 1) < tol / size, lambda X: X / q(X)))
    elif body.geometry in ("truncated-cone", "cylinder") and model == "3d":
        h = body.height_mm
        r0, r1 = (
            (body.bottom_diameter_mm / 2, body.top_diameter_mm / 2)
            if body.geometry == "truncated-cone"
            else (body.diameter_mm / 2,) * 2
        )

        def radius(X):
            return r0 + (r1 - r0) * (X[1] + h / 2) / h

        def rho(X):
            return np.hypot(X[0], X[2])

        def snap(X):
            f = radius(X) / np.maximum(rho(X), 1e-300)
            return np.stack([X[0] * f, X[1], X[2] * f])

        out.append((lambda X: np.abs(rho(X) - radius(X)) < tol, snap))
    for inc in scene.inclusions:
        if inc.shape != "sphere":
            continue
        c = np.asarray(inc.centre_mm, float)[:, None]
        if model == "axisymmetric":
            c = np.array([[0.0], [c[1, 0]], [0.0]])
        elif model == "plane-strain":
            c = np.array([[c[0, 0]], [c[1, 0]], [0.0]])
        R = inc.diameter_mm / 2

        def dist(X, c=c):
            return np.sqrt(np.sum((X - c) ** 2, axis=0))

        out.append(
            (
                lambda X, c=c, R=R: np.abs(dist(X, c) - R) < tol,
                lambda X, c=c, R=R: c + (X - c) * (R / np.maximum(dist(X, c), 1e-300)),
            )
        )
    return out


def curved_skfem_mesh(fem: FEMesh, scene: Scene):
    """A quadratic (isoparametric) scikit-fem mesh of ``fem`` whose edge midpoints on the scene's
    curved boundaries and interfaces (ellipsoid, cone or cylinder side, spherical inclusions) lie
    on the true surface. Straight-sided tetrahedra lose volume on a curved surface (sagitta
    h^2 / 8R per facet: at 6 mm elements on a 25 mm radius, about 2 % of the hemi-ellipsoid), and
    the plate force with it; curved P2 geometry costs no extra unknowns. Returns the linear
    mesh unchanged if nothing is curved or snapping would invert an element.
    """
    from skfem import MeshTet2, MeshTri2

    m = fem.skfem()
    surfaces = _curved_surfaces(scene, fem.model)
    if not surfaces:
        return m
    p = m.p
    P3 = p if p.shape[0] == 3 else np.vstack([p, np.zeros((1, p.shape[1]))])
    edges = np.sort(m.edges if m.edges is not None else m.facets, axis=0)  # 2D: the facets are the edges
    n = p.shape[1]
    key = edges[0].astype(np.int64) * n + edges[1]
    order = np.argsort(key)
    region = np.asarray(fem.region)
    f2t = m.f2t
    outer = f2t[1] < 0
    interface = ~outer & (region[f2t[0]] != region[np.maximum(f2t[1], 0)])
    cand = np.flatnonzero(outer | interface)
    fac = m.facets[:, cand]
    mid = P3[:, edges].mean(axis=1)
    for on, snap in surfaces:
        on_v = on(P3)
        sel = fac[:, np.all(on_v[fac], axis=0)]
        if sel.shape[1] == 0:
            continue
        pairs = [(0, 1)] if sel.shape[0] == 2 else [(0, 1), (1, 2), (0, 2)]
        a = np.concatenate([np.minimum(sel[i], sel[j]) for i, j in pairs])
        b = np.concatenate([np.maximum(sel[i], sel[j]) for i, j in pairs])
        k = order[np.searchsorted(key, a.astype(np.int64) * n + b, sorter=order)]
        k = np.unique(k)
        mid[:, k] = snap(mid[:, k])
    doflocs = np.hstack([p, mid[: p.shape[0]]])
    curved = (MeshTet2 if fem.model == "3d" else MeshTri2)(doflocs, m.t)
    # keep the orientation of every element at its quadrature points (no inversion by snapping)
    from skfem import Basis, ElementTetP1, ElementTriP1

    elem = ElementTetP1() if fem.model == "3d" else ElementTriP1()
    straight = np.sign(Basis(m, elem, intorder=4).mapping.detDF(Basis(m, elem, intorder=4).X))
    det = curved.mapping().detDF(Basis(m, elem, intorder=4).X)
    if np.any(np.sign(det) != straight):
        return m
    return curved


def undeformed_projection_mesh(scene: Scene, fem: FEMesh | None = None) -> FEMesh:
    """The mesh :class:`sim.mechanics.Solver` projects its states on (its ``projection_mesh``: the
    P2 nodes, edge nodes on the scene's curved surfaces, as a linear mesh), before any load: so
    that an image of the undeformed scene and one of a state differ by the motion only, not by
    the straight-sided tetrahedra's sag (review s40phys: a 10 mm sphere meshed at 1-3 mm projected
    1.3 % less integrated attenuation from its vertices than from its P2 nodes, and a 5 %
    compression read +1.24 % where the volume changed by -0.09 %)."""
    from skfem import Basis, ElementTetP2, ElementTriP2

    fem = fem if fem is not None else build_mesh(scene)
    mesh = curved_skfem_mesh(fem, scene) if scene.mesh.curved else fem.skfem()
    elem = ElementTetP2() if fem.model == "3d" else ElementTriP2()
    return p2_submesh(fem, fem.skfem(), Basis(mesh, elem, intorder=1).doflocs)


def p2_submesh(fem: FEMesh, linear_mesh, dof_points) -> FEMesh:
    """The P2 mesh as a linear one: every tetrahedron split into 8 (triangle into 4) at its edge
    nodes, vertices at ``dof_points`` (the P2 nodes, vertices first, then one per edge of
    ``linear_mesh`` in its edge order, as scikit-fem numbers them). A displacement on the P2
    nodes moves this mesh exactly at every node, and curved boundaries keep their edge nodes,
    so projections see the geometry the mechanics solved on."""
    m = linear_mesh
    n = m.p.shape[1]
    edges = np.sort(m.edges if m.edges is not None else m.facets, axis=0)  # 2D: the facets are the edges
    key = edges[0].astype(np.int64) * n + edges[1]
    order = np.argsort(key)

    def mid(a, b):
        lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b)
        return n + order[np.searchsorted(key, lo * n + hi, sorter=order)]

    t = m.t
    if t.shape[0] == 4:
        v0, v1, v2, v3 = t
        m01, m02, m03, m12, m13, m23 = mid(v0, v1), mid(v0, v2), mid(v0, v3), mid(v1, v2), mid(v1, v3), mid(v2, v3)
        sub = [
            (v0, m01, m02, m03),
            (m01, v1, m12, m13),
            (m02, m12, v2, m23),
            (m03, m13, m23, v3),
            (m01, m02, m03, m13),
            (m01, m02, m12, m13),
            (m02, m03, m13, m23),
            (m02, m12, m13, m23),
        ]
    else:
        v0, v1, v2 = t
        m01, m02, m12 = mid(v0, v1), mid(v0, v2), mid(v1, v2)
        sub = [(v0, m01, m02), (m01, v1, m12), (m02, m12, v2), (m01, m12, m02)]
    cells = np.concatenate([np.stack(c) for c in sub], axis=1)
    region = np.tile(np.asarray(fem.region), len(sub))
    return FEMesh(
        np.asarray(dof_points, float).copy(),
        cells,
        region,
        fem.model,
        tuple(fem.symmetry),
        dict(fem.meta, p2_submesh=True),
    )
