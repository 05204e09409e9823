"""Large-deformation mechanics of the compressed phantom with scikit-fem.

Materials
---------
Background (and optionally inclusions): FEBio's neo-Hookean energy

    psi = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2,

or (``model = "neo-hookean-uncoupled"``) ANSYS's, the paper's package: deviatoric and volumetric
parts uncoupled, psi = mu/2 (J^-2/3 I1 - 3) + kappa/2 (J - 1)^2 (C10 = mu/2, d = 2/kappa).

"Linear elastic" inclusions use Hooke's law on the Green-Lagrange strain E (St Venant-Kirchhoff),
as a geometrically nonlinear FE code treats a linear material: psi = mu E:E + lambda/2 (tr E)^2.

Near incompressibility (nu = 0.495, lambda / mu = 99) without locking: a mixed u-p formulation,
quadratic (P2) displacement and an element-wise constant (P0) pressure conjugate to the volumetric
measure g (ln J, or tr E), i.e. psi = W(F) + p g - p^2 / (2 lambda). P2-P0 is inf-sup stable in 3D
as in 2D (the edge degrees of freedom control each face's flux). The pressure is condensed per
element, p_e = lambda * mean_e(g), so the global system is displacement-only and symmetric:

    Pi(u) = sum_e [ int_e W dV + lambda/2 V_e mean_e(g)^2 ].

Plates
------
Rigid plates normal to y. Flat faces lying on a plate (cone, cylinder, box) stay on it: rollers
(frictionless) or glued (bonded). Curved bodies (ellipsoids) touch the plate at a point first and
the patch grows: frictionless penalty contact on the boundary, energy eps/2 <y + u_y - h>_+^2,
with eps the background's stiffness over the finest element size (x 100), so the penetration is
about 1e-2 of the contact strain times that size (seed-breast at 25 %: 3e-3 of the 1.4 mm element
per plate, the line integral +2.5e-4 relative).

Solver
------
Newton on Pi with an Armijo line search that also keeps J > 0 (in every material), adaptive load
steps (halved on failure, grown after easy steps), and a :class:`ConvergenceError` naming the
compression at which it gave up and why; never NaN. Units: mm, N, MPa.

A state depends only on its compression, not on how the requests split the way there: each load
step must stay on its equilibrium branch (its energy change is the plates' work). Where the branch
ends (a limit point: a free surface creasing, a 'linear' inclusion past its stress peak) the march
stops there, whatever the steps, and says where the unstable mode lies; stepping over it used to
land on another branch or on inverted elements and carry on.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from radiokit.errors import RadiokitError
from sim.mesh import FEMesh, build_mesh, curved_skfem_mesh, p2_submesh
from sim.scene import Scene

__all__ = [
    "State",
    "ConvergenceError",
    "InstabilityError",
    "MemoryBudgetError",
    "Solver",
    "compress",
    "estimate_solve_bytes",
    "check_solve_memory",
    "uniaxial_block_force",
]

_EYE = np.eye(3)

#: relative accuracy of each Newton update's linear solve (see Solver._linsolve)
LINEAR_RTOL = 1e-4
#: a factorisation's cost in preconditioned GMRES iterations: the ratio of their times on
#: seed-breast's mesh (benchmarks/README.md, "Mechanics regression"); a count, not a measured
#: time, keeps the work independent of the machine's load
LU_PRICE = 40
FIRST_STEP = 0.05
EASY_STEP = 5
PREDICTOR = True
#: Newton's relative residual on load steps between requested states (see Solver._newton)
STEP_RTOL = 1e-5
#: a contact step takes the plates at most this factor further than the last equilibrium
CONTACT_GROWTH = 1.5
#: largest departure of a load step's energy change from the plate's work (trapezoid of the
#: forces), as a fraction of step x force, before the step counts as a jump between branches
#: (Solver._path_check: smooth steps measured within 0.03, first contact's delta^1.5 within 0.1;
#: a cylinder's side creasing at 41 % released 2.1)
SNAP_TOL = 0.25
TRACE = False


#: The solve's peak memory against its mesh, fitted by benchmarks/bench_mechanics_memory.py
#: (benchmarks/README.md, "Mechanics memory"; seed-breast in 3D, pva-phantom's section in 2D),
#: per model dimension: ``setup`` bytes per element at the solver's set-up (the gradient operators
#: B and Bt, and the sparsity pattern's int64 index arrays, freed once it is found), ``held``
#: bytes per element kept beside a factorisation, 12 bytes per non-zero of the LU (SuperLU's
#: float64 value and int32 index), and its fill nnz(L) + nnz(U) = c n^k of n = dim x P2 nodes.
#: In 3D the fill's exponent grows with the mesh (1.61 between 5 600 and 22 000 unknowns, 1.81
#: between 35 000 and 54 000: minimum degree tends to a band's 2, not nested dissection's 4/3),
#: so it is the largest measured mesh's local power, through that mesh: it extrapolates high
#: rather than low (6.4 GB for the 30 800 tetrahedra that had reached 6.4 GB, unfinished, in
#: review s41sim). In 2D one power fits 17 000-258 000 unknowns within 1 %.
SOLVE_MEMORY = {
    3: {"setup": 83.5e3, "held": 60e3, "c": 0.1829, "k": 1.81},
    2: {"setup": 21e3, "held": 13e3, "c": 18.06, "k": 1.198},
}


def mesh_unknowns(fem: FEMesh) -> tuple[int, int]:
    """``(P2 nodes, unknowns)`` of ``fem``: its vertices and edges, dim unknowns each."""
    cells = np.asarray(fem.cells)
    k = cells.shape[0]
    pairs = np.concatenate([np.sort(cells[[a, b]], axis=0) for a in range(k) for b in range(a + 1, k)], axis=1)
    edges = np.unique(pairs[0].astype(np.int64) * (int(cells.max()) + 1) + pairs[1]).size
    nodes = int(np.unique(cells).size) + edges
    return nodes, (k - 1) * nodes


def estimate_solve_bytes(fem: FEMesh) -> int:
    """The peak memory of solving ``fem`` (bytes), before the solver allocates any of it:
    within -8 % and +12 % of the peak measured on meshes of 1 100-11 500 tetrahedra and
    4 200-64 000 triangles (:data:`SOLVE_MEMORY`). The set-up's peak or the factorisation's,
    whichever is higher: the factorisation reuses what the set-up freed."""
    m = SOLVE_MEMORY[fem.cells.shape[0] - 1]
    nel = fem.cells.shape[1]
    fill = m["c"] * float(mesh_unknowns(fem)[1]) ** m["k"]
    return int(max(m["setup"] * nel, m["held"] * nel + 12 * fill))


def _size(nbytes: int) -> str:
    return f"{nbytes / 2**30:.1f} GiB" if nbytes >= 2**30 else f"{max(nbytes / 2**20, 0.1):.1f} MiB"


class MemoryBudgetError(RadiokitError, ValueError):
    """The mechanics of a mesh would need more memory than radiokit's budget allows."""


def check_solve_memory(scene: Scene, fem: FEMesh, budget=None) -> None:
    """:class:`MemoryBudgetError` naming the mesh sizes when solving ``fem`` would need more than
    the memory budget (``radiokit.io.memory_budget``: ``RADIOKIT_MEMORY_BUDGET``, else half the
    available memory): a 30 000-element mesh of seed-breast took 6.4 GB within 326 s of a
    factorisation no signal interrupts (review s41sim)."""
    from radiokit.io import BUDGET_ENV, memory_budget

    need, limit = estimate_solve_bytes(fem), memory_budget(budget)
    if need <= limit:
        return
    spec = scene.mesh
    sizes = ", ".join(
        f"{name} {getattr(spec, name):g}"
        for name in ("size_inclusion_mm", "size_far_mm", "size_contact_mm")
        if getattr(spec, name) is not None
    )
    raise MemoryBudgetError(
        f"mesh {sizes}: {fem.cells.shape[1]:,} elements, {mesh_unknowns(fem)[1]:,} unknowns: the mechanics would "
        f"need about {_size(need)}, over the memory budget of {_size(limit)} "
        f"(use larger mesh sizes, or raise {BUDGET_ENV})"
    )


class ConvergenceError(RadiokitError, RuntimeError):
    """The solver could not reach a requested compression (the message names it)."""


class InstabilityError(ConvergenceError):
    """A load step met a limit point of the equilibrium path: the tangent stiffness is not
    positive definite there, or the step snapped to another branch (see Solver._path_check)."""


#: St Venant-Kirchhoff (the ``linear`` material) in uniaxial stress: nominal stress
#: ``P = E s (s^2 - 1) / 2`` at stretch ``s``, ``dP/ds = E (3 s^2 - 1) / 2``: it peaks at
#: ``s = 1 / sqrt(3)`` (42.3 % compression) and falls beyond, down to zero at total collapse, so
#: there the model no longer describes a solid (its strain is then meaningless, and the solver
#: may stall: the march's step halving ends in ConvergenceError).
SVK_LIMIT_STRETCH = 1.0 / math.sqrt(3.0)


class MaterialWarning(UserWarning):
    """A material model used beyond the range where it describes a solid."""


@dataclass
class State:
    """One equilibrium state.

    Attributes
    ----------
    ratio : float
        Compression: the plates have closed by this fraction of the initial gap.
    gap_mm : float
        Plate gap.
    plate_force_n : float
        Force on one plate (whole body, symmetry accounted for), compressive positive.
    volume_ratio : float
        Deformed over initial volume of the whole body.
    displacement : ndarray (dim, n_dofs)
        Displacement of the P2 nodes (``Solver.dof_points``), mm; the first ``n_vertices``
        columns are the mesh vertices.
    newton_iterations, load_steps : int
        Work done to reach this state (since the previous one; load steps in total).
    contact_area_mm2 : float
        Plate contact patch (curved bodies; NaN where a flat face is held on the plate).
    inclusion_strain, background_strain : float
        Volume-averaged compressive strain ``1 - F_yy`` of the inclusions and of the background:
        their ratio is the elasticity contrast the method relies on.
    linear_min_stretch : float
        The smallest principal stretch at any quadrature point of a ``linear`` (St Venant-Kirchhoff)
        material (NaN without one): below :data:`SVK_LIMIT_STRETCH` that model no longer describes
        a solid (a :class:`MaterialWarning` says so).
    """

    ratio: float
    gap_mm: float
    plate_force_n: float
    volume_ratio: float
    displacement: np.ndarray = field(repr=False)
    newton_iterations: int = 0
    load_steps: int = 0
    contact_area_mm2: float = 0.0
    inclusion_strain: float = float("nan")
    background_strain: float = float("nan")
    linear_min_stretch: float = float("nan")
    solver: Solver = field(default=None, repr=False, compare=False)  #: mesh and dof layout


def uniaxial_block_force(ratio, E_kpa, nu, area_mm2) -> tuple[float, float]:
    """Closed form: plate force (N) and lateral stretch of a neo-Hookean block (FEBio's energy)
    compressed by ``ratio`` between frictionless plates, sides traction-free.

    With axial stretch s = 1 - ratio and lateral stretch t, F = diag(t, s, t), J = s t^2. The first
    Piola stress is P = mu (F - F^-T) + lambda ln J F^-T, so the free sides need
    mu (t^2 - 1) + lambda ln(s t^2) = 0 (the left side increases with t: one root, bracketed by
    t = 1, where it is lambda ln s < 0, and t = 1/s, where it is positive), and the plate force is
    |P_yy| A = |mu (s - 1/s) + lambda ln(J) / s| A.
    """
    from scipy.optimize import brentq

    mu = E_kpa / (2 * (1 + nu)) * 1e-3
    lam = E_kpa * nu / ((1 + nu) * (1 - 2 * nu)) * 1e-3
    s = 1.0 - ratio
    if s == 1.0:
        return 0.0, 1.0
    t = brentq(lambda t: mu * (t * t - 1) + lam * math.log(s * t * t), 1.0, 1.0 / s, xtol=1e-15, rtol=1e-15)
    p_yy = mu * (s - 1 / s) + lam * math.log(s * t * t) / s
    return abs(p_yy) * area_mm2, t


def _stoppable(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a thread of its own, the main thread waiting for it in short
    slices, so that a stop's handler runs (and its exception leaves) at once.

    For SuperLU's factorisation: C that releases the GIL and never looks at Python's signal flag,
    so Ctrl-C or SIGTERM waited for its end, 71 s for 11 500 tetrahedra on a loaded machine
    (benchmarks/README.md, "Mechanics memory"). A stopped factorisation cannot be cut short: it
    runs on to its end in its thread while the command removes its outputs and says so, and the
    process exits once it is done (Python waits for the thread). Not a daemon thread: one left
    running in BLAS while the interpreter shut down crashed the process ("BLAS : Bad memory
    unallocation!", SIGSEGV) instead of its exit status. Off the main thread (no signal handlers
    run there) it is a plain call."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    out: dict = {}
    done = threading.Event()

    def run():
        try:
            out["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # handed to the caller, as a plain call would raise it
            out["error"] = exc
        finally:
            done.set()

    threading.Thread(target=run, name="factorisation").start()
    # waited on an event, not join(): a stop raised inside join(timeout) marks the thread as ended
    # (CPython 3.11), so the interpreter shut down beside it, crashing in BLAS
    while not done.wait(0.05):  # a signal's handler runs here, between slices
        pass
    if "error" in out:
        raise out["error"]
    return out["value"]


class _Pattern:
    """The sparsity of the global matrix, found once: element entries are summed into CSR storage
    with one ``bincount`` per assembly instead of a COO -> CSR conversion."""

    def __init__(self, rows, cols, n):
        self.n = n
        keys = rows.astype(np.int64) * n + cols
        uniq, self.inverse = np.unique(keys, return_inverse=True)
        self.keys = uniq
        self.indices = (uniq % n).astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // n, minlength=n))]).astype(np.int32)

    def positions(self, rows, cols):
        keys = rows.astype(np.int64) * self.n + cols
        pos = np.searchsorted(self.keys, keys)
        if not np.array_equal(self.keys[np.minimum(pos, self.keys.size - 1)], keys):
            raise ValueError("entries outside the element sparsity pattern")
        return pos

    def assemble(self, values, extra=None):
        data = np.bincount(self.inverse, values.ravel(), minlength=self.keys.size)
        if extra is not None:
            data += np.bincount(extra[0], extra[1], minlength=self.keys.size)
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))


class Solver:
    """Equilibrium of one meshed scene under prescribed plate positions."""

    def __init__(self, scene: Scene, fem: FEMesh | None = None, *, intorder=2, penalty_factor=1e2):
        from skfem import Basis, ElementTetP2, ElementTriP2, FacetBasis

        self.scene = scene
        self.fem = fem if fem is not None else build_mesh(scene)
        check_solve_memory(scene, self.fem)  # before the set-up allocates the first of it
        self.model = self.fem.model
        if scene.mesh.curved:
            mesh = curved_skfem_mesh(self.fem, scene)  # isoparametric: edge nodes on curved surfaces
        else:
            mesh = self.fem.skfem()
        self.mesh = mesh
        elem = ElementTetP2() if self.model == "3d" else ElementTriP2()
        basis = Basis(mesh, elem, intorder=intorder)
        self.basis = basis
        self.dim = 3 if self.model == "3d" else 2
        dim = self.dim
        self.dof_points = basis.doflocs.copy()  # (dim, N): vertices first, then edge midpoints
        #: the P2 nodes as a linear mesh (8 tets per tet), for projections of the solved geometry
        self.projection_mesh = p2_submesh(self.fem, self.fem.skfem(), self.dof_points)
        self.n_nodes = basis.N
        nloc = len(basis.basis)
        nel = basis.dx.shape[0]
        self.B, self.w = self._gradient_operator(basis)
        nq, nd = self.B.shape[1:3]
        # the same operator as (element, dof, quadrature point x 9): residuals and strains are then
        # batched matrix products instead of three-operand einsums
        self.Bt = np.ascontiguousarray(self.B.reshape(nel, nq, nd, 9).transpose(0, 2, 1, 3)).reshape(nel, nd, nq * 9)
        self.Ve = self.w.sum(axis=1)
        edofs = basis.element_dofs.T  # (nel, nloc) scalar node indices
        self.edofs = (edofs[:, :, None] * dim + np.arange(dim)[None, None, :]).reshape(nel, nloc * dim)
        self.ndof = self.n_nodes * dim
        rows = np.repeat(self.edofs, nloc * dim, axis=1).ravel()
        cols = np.tile(self.edofs, (1, nloc * dim)).ravel()
        self._pattern = _Pattern(rows, cols, self.ndof)
        # Materials per element
        mats = [scene.body.material] + [inc.material for inc in scene.inclusions]
        region = self.fem.region
        self.mu = np.array([mats[r].shear_kpa for r in region]) * 1e-3
        #: the background's shear modulus (MPa): the stress scale of Newton's residual test. The
        #: plates load the body through the background whatever an inclusion's stiffness; scaled
        #: by the stiffest material, a near-rigid inclusion (10^4 x the gel) loosened the test as
        #: many times, and a predictor 1e-4 off passed it with no Newton iteration at all
        self.mu_body = scene.body.material.shear_kpa * 1e-3
        self.svk = np.array([mats[r].model == "linear" for r in region])
        self.unc = np.array([mats[r].model == "neo-hookean-uncoupled" for r in region])
        # the modulus of the volumetric measure g: lambda for g = ln J and tr E, the bulk modulus
        # kappa = lambda + 2 mu / 3 for the uncoupled form's g = J - 1
        self.lam = (
            np.array(
                [mats[r].lame_kpa + (2 * mats[r].shear_kpa / 3 if self.unc[i] else 0.0) for i, r in enumerate(region)]
            )
            * 1e-3
        )
        self.region = region
        # Copies of the model side by side on one plate: symmetry planes other than y (which
        # mirrors the model onto the other plate). Axisymmetric weights already hold the 2 pi r.
        if self.model == "3d":
            self.force_multiplicity = 2 ** len([p for p in self.fem.symmetry if p != "y"])
        else:  # axisymmetric weights hold 2 pi r; a plane-strain section is the half x >= 0
            self.force_multiplicity = 2 if self.model == "plane-strain" else 1
        self._setup_boundary(FacetBasis, elem, penalty_factor)
        self._rigid = self._free_rigid_modes()
        self._lu = None
        self._krylov_spent = 0  # GMRES iterations preconditioned by the current factorisation
        self.factorisations = 0
        self.krylov_iterations = 0

    def _gradient_operator(self, basis):
        """``B[e, q, d]``: the 3x3 displacement gradient of a unit local dof d (the hoop strain
        u_r / r in the (2, 2) entry for axisymmetry), and the quadrature weights (times 2 pi r,
        or the slab's thickness)."""
        dim, nloc = self.dim, len(basis.basis)
        nel, nq = basis.dx.shape
        grads = np.stack([basis.basis[a][0].grad for a in range(nloc)])  # (nloc, dim, nel, nq)
        grads = grads.transpose(2, 3, 0, 1)  # (nel, nq, nloc, dim)
        B = np.zeros((nel, nq, nloc * dim, 3, 3))
        for a in range(nloc):
            for i in range(dim):
                B[:, :, a * dim + i, i, :dim] = grads[:, :, a, :]
        w = basis.dx.copy()
        if self.model == "axisymmetric":
            R = np.asarray(basis.global_coordinates())[0]  # (nel, nq), quadrature points are interior: R > 0
            vals = np.stack([np.asarray(basis.basis[a][0]) for a in range(nloc)], axis=-1)  # (nel, nq, nloc)
            for a in range(nloc):
                B[:, :, a * dim + 0, 2, 2] = vals[:, :, a] / R
            w = w * 2 * np.pi * R
        elif self.model == "plane-strain":
            w = w * self.scene.body.size_mm[2]
        return B, w

    # -- boundary conditions ------------------------------------------------------------------
    def _setup_boundary(self, FacetBasis, elem, penalty_factor):
        sc = self.scene
        self.H = sc.body.half_height_mm
        self.gap0 = 2 * self.H
        size = float(np.max(self.dof_points.max(axis=1) - self.dof_points.min(axis=1)))
        self._tol = 1e-6 * size
        fixed = self._symmetry_and_wall()  # global dof -> prescribed value
        self.top_nodes = np.zeros(0, np.int64)
        self.moving = np.zeros(0, np.int64)
        self.contact = None
        if sc.body.geometry in ("truncated-cone", "cylinder", "box"):
            self._flat_plates(fixed)
        else:
            self._contact_setup(FacetBasis, elem, penalty_factor)
        self.fixed_dofs = np.array(sorted(fixed), dtype=np.int64)
        self.fixed_vals = np.array([fixed[d] for d in self.fixed_dofs])
        moving = set(self.moving.tolist())
        self.fixed_dofs_all = np.array(sorted(set(self.fixed_dofs.tolist()) | moving), dtype=np.int64)
        free = np.ones(self.ndof, bool)
        free[self.fixed_dofs_all] = False
        self.free = np.flatnonzero(free)

    def _symmetry_and_wall(self) -> dict:
        """Zero displacement normal to the symmetry planes and at the chest wall (all components
        where it is fixed, x where it slides); for 2-D models the axis or the x = 0 plane."""
        sc, X, tol = self.scene, self.dof_points, self._tol
        fixed = {}
        sym = set(self.fem.symmetry)
        if self.model == "3d":
            axes = {"x": 0, "y": 1, "z": 2}
            for ax in sym:
                k = axes[ax]
                for n in np.flatnonzero(np.abs(X[k]) < tol):
                    fixed[n * 3 + k] = 0.0
            if sc.wall != "none":
                for n in np.flatnonzero(np.abs(X[0]) < tol):
                    for k in range(3) if sc.wall == "fixed" else (0,):
                        fixed[n * 3 + k] = 0.0
        else:
            # axis r = 0 (axisymmetric) or the x = 0 symmetry plane of a slab
            for n in np.flatnonzero(np.abs(X[0]) < tol):
                fixed[n * 2 + 0] = 0.0
            if "y" in sym:
                for n in np.flatnonzero(np.abs(X[1]) < tol):
                    fixed[n * 2 + 1] = 0.0
        return fixed

    def _flat_plates(self, fixed):
        """Faces on the plates: the top moves down (``self.moving``), the bottom (without a y
        symmetry plane) stays; bonded plates also hold the lateral displacement."""
        dim, X, H, tol = self.dim, self.dof_points, self.H, self._tol
        lateral = [k for k in range(dim) if k != 1]
        bonded = self.scene.compression.contact == "bonded"
        top = np.flatnonzero(np.abs(X[1] - H) < tol)
        self.top_nodes = top
        self.moving = top * dim + 1  # u_y = -delta
        for n in top:
            if bonded:
                for k in lateral:
                    fixed[n * dim + k] = 0.0
        if "y" not in self.fem.symmetry:
            for n in np.flatnonzero(np.abs(X[1] + H) < tol):
                fixed[n * dim + 1] = 0.0
                if bonded:
                    for k in lateral:
                        fixed[n * dim + k] = 0.0

    def _free_rigid_modes(self):
        """The rigid motions no boundary condition holds, as W-orthonormal columns (ndof, k), and
        the weights W; None when there are none.

        Frictionless plates hold only u_y, so a 3-D body with neither a symmetry plane across x or
        z nor a chest wall may slide along x and z and turn about y at no cost in energy: the
        tangent is singular there and the solve's rounding chose the placement (a 20 mm block
        with an off-centre inclusion turned by 10.5 degrees and slid 4.7 mm at 25 %). The
        placement is a convention, not physics; the one kept is that of a symmetric set-up (a
        frame holding the phantom): the body's centroid does not move sideways and the body does
        not turn as a whole (to first order: no linearised rigid part in the displacement). Each
        vertex carries a quarter of its tetrahedra's volume (exact centroid for affine fields),
        edge nodes nothing."""
        if self.model != "3d":  # the axis (r = 0) or the x = 0 plane holds the 2-D models
            return None
        X = self.dof_points
        modes = np.zeros((self.ndof, 3))
        modes[0::3, 0], modes[2::3, 1] = 1.0, 1.0
        modes[0::3, 2], modes[2::3, 2] = X[2], -X[0]  # e_y x X: a turn about y
        held = modes[self.fixed_dofs_all]
        size = float(np.max(X.max(axis=1) - X.min(axis=1)))
        if held.size:
            _, sv, vt = np.linalg.svd(held, full_matrices=True)
            rank = int(np.sum(sv > 1e-9 * size * math.sqrt(len(held))))
            free = vt[rank:].T
        else:
            free = np.eye(3)
        if free.shape[1] == 0:
            return None
        cells = self.fem.cells
        vol = np.zeros(self.n_nodes)
        np.add.at(vol, cells.ravel(), np.tile(self.Ve / cells.shape[0], cells.shape[0]))
        W = np.repeat(vol, 3)
        R = modes @ free
        R = R @ np.linalg.inv(np.linalg.cholesky(R.T @ (W[:, None] * R))).T
        return R, W

    def _update(self, K, rhs):
        """A Newton update on the free dofs (:meth:`_linsolve`) less its part in the free rigid
        motions (:meth:`_free_rigid_modes`), along which the tangent is singular: the
        displacement then never holds any, and Newton solves for the one equilibrium without."""
        du = self._linsolve(K, rhs)
        if self._rigid is None:
            return du
        R, W = self._rigid
        Rf, Wf = R[self.free], W[self.free]  # the free motions move no prescribed dof
        return du - Rf @ (Rf.T @ (Wf * du))

    def _contact_setup(self, FacetBasis, elem, penalty_factor):
        """Penalty contact of a curved body with the plate, on the boundary facets that can reach
        it (upper half, off the symmetry planes and the wall)."""
        sc, dim, H, tol = self.scene, self.dim, self.H, self._tol
        if sc.compression.contact == "bonded":
            raise ValueError(
                f"scene {sc.name!r}: bonded plates need flat faces on the plates; a "
                f"{sc.body.geometry} touches them at a point (use contact = 'frictionless')"
            )
        sym = set(self.fem.symmetry)
        if "y" not in sym:
            raise ValueError(f"scene {sc.name!r}: a curved body must be symmetric in y (set mesh.symmetry)")
        m = self.mesh
        bf = m.boundary_facets()
        mid = m.p[:, m.facets[:, bf]].mean(axis=1)
        on_plane = np.zeros(bf.size, bool)
        for k, ax in enumerate("xyz"[:dim] if self.model == "3d" else "ry"):
            if (self.model == "3d" and ax in sym) or (self.model != "3d" and k == 0):
                on_plane |= np.all(np.abs(m.p[k, m.facets[:, bf]]) < tol, axis=0)
        if self.model == "3d" and sc.wall != "none":
            on_plane |= np.all(np.abs(m.p[0, m.facets[:, bf]]) < tol, axis=0)
        cand = bf[(~on_plane) & (mid[1] > 0.25 * H)]
        fb = FacetBasis(m, elem, facets=cand, intorder=4)
        nloc = len(fb.basis)
        N = np.stack([np.asarray(fb.basis[a][0]) for a in range(nloc)], axis=-1)  # (nf, nq, nloc)
        fw = fb.dx.copy()
        Xq = np.asarray(fb.global_coordinates())
        if self.model == "axisymmetric":
            fw = fw * 2 * np.pi * Xq[0]
        ydofs = fb.element_dofs.T * dim + 1  # (nf, nloc)
        # The plates touch the background: its stiffness over the finest element size sets the
        # penalty, so the penetration stays ~1e-2 of the contact strain times that size.
        bg = sc.body.material
        E_bg = bg.E_kpa if bg.E_kpa is not None else 3 * bg.shear_kpa
        h_min = self.fem.meta.get("size_inclusion_mm", 1.0)
        eps = penalty_factor * E_bg * 1e-3 / h_min
        self.contact = dict(N=N, w=fw, y=Xq[1], dofs=ydofs, eps=eps)

    # -- energy and derivatives ---------------------------------------------------------------
    def _kinematics(self, u):
        ue = u[self.edofs]  # (nel, ndl)
        nel, nq = self.w.shape
        return _EYE + np.matmul(ue[:, None, :], self.Bt).reshape(nel, nq, 3, 3)

    def _material(self, F, need_tangent):
        """Per quadrature point: energy W, volumetric measure g, P = dW + p dg, and the tangent."""
        nel, nq = F.shape[:2]
        mu = self.mu[:, None]
        lam = self.lam
        J = np.linalg.det(F)
        ok = J > 0
        # no material survives inversion: St Venant-Kirchhoff's polynomial energy is finite at
        # J <= 0, and admitting it let a collapsed tumour turn inside out and the march run on
        # (seed-breast asked for 80 % at once: inclusion strain 118 %, reported as reached)
        if not np.all(ok):
            return None
        svk = self.svk[:, None] & np.ones((1, nq), bool)
        Jc = np.where(ok, J, 1.0)
        Finv = np.linalg.inv(np.where(ok[..., None, None], F, _EYE))
        FiT = np.swapaxes(Finv, -1, -2)
        C = np.einsum("eqki,eqkj->eqij", F, F)
        I1 = np.trace(C, axis1=-2, axis2=-1)
        Egl = 0.5 * (C - _EYE)
        lnJ = np.log(Jc)
        W = np.where(svk, mu * np.einsum("eqij,eqij->eq", Egl, Egl), mu / 2 * (I1 - 3) - mu * lnJ)
        g = np.where(svk, np.trace(Egl, axis1=-2, axis2=-1), lnJ)
        dW = np.where(
            svk[..., None, None],
            2 * mu[..., None, None] * np.einsum("eqik,eqkj->eqij", F, Egl),
            mu[..., None, None] * (F - FiT),
        )
        dg = np.where(svk[..., None, None], F, FiT)
        unc = self.unc[:, None] & np.ones((1, nq), bool) if self.unc.any() else None
        if unc is not None:  # ANSYS's form: mu/2 (J^-2/3 I1 - 3) + kappa/2 (J - 1)^2
            a = Jc ** (-2.0 / 3.0)
            W = np.where(unc, mu / 2 * (a * I1 - 3), W)
            g = np.where(unc, Jc - 1.0, g)
            dW = np.where(unc[..., None, None], (mu * a)[..., None, None] * (F - (I1 / 3)[..., None, None] * FiT), dW)
            dg = np.where(unc[..., None, None], Jc[..., None, None] * FiT, dg)
        gbar = (g * self.w).sum(axis=1) / self.Ve
        p = (lam * gbar)[:, None]
        P = dW + p[..., None, None] * dg
        energy = float((W * self.w).sum() + 0.5 * (lam * self.Ve * gbar**2).sum())
        out = dict(P=P, dg=dg, energy=energy, J=J, gbar=gbar)
        if need_tangent:
            # A_ijkl = d P_ij / d F_kl at fixed p
            d = np.einsum("ik,jl->ijkl", _EYE, _EYE)
            X = np.einsum("eqil,eqkj->eqijkl", FiT, FiT)
            A = mu[..., None, None, None, None] * d + (mu - p)[..., None, None, None, None] * X
            # the other models' tangents only on their own elements (the inclusion, a few %)
            e = np.flatnonzero(self.svk)
            if e.size:
                Fe, m_e = F[e], mu[e][..., None, None, None, None]
                S = 2 * mu[e][..., None, None] * Egl[e] + p[e][..., None, None] * _EYE
                FFt = np.einsum("eqim,eqkm->eqik", Fe, Fe)
                A[e] = np.einsum("ik,eqlj->eqijkl", _EYE, S) + m_e * (
                    np.einsum("eqik,jl->eqijkl", FFt, _EYE) + np.einsum("eqil,eqkj->eqijkl", Fe, Fe)
                )
            e = np.flatnonzero(self.unc)
            if e.size:
                Fe, Ge, Ie = F[e], FiT[e], I1[e][..., None, None, None, None]
                Y = np.einsum("eqij,eqkl->eqijkl", Ge, Ge)
                iso = (
                    d
                    - 2 / 3 * (np.einsum("eqkl,eqij->eqijkl", Ge, Fe) + np.einsum("eqkl,eqij->eqijkl", Fe, Ge))
                    + 2 / 9 * Ie * Y
                    + Ie / 3 * X[e]
                )
                A[e] = (mu[e] * a[e])[..., None, None, None, None] * iso + (p[e] * Jc[e])[
                    ..., None, None, None, None
                ] * (Y - X[e])
            out["A"] = A
        return out

    def _contact_terms(self, u, h, need_tangent):
        c = self.contact
        if c is None:
            return 0.0, None, None, 0.0, 0.0
        uy = u[c["dofs"]]  # (nf, nloc)
        y = c["y"] + np.einsum("fqa,fa->fq", c["N"], uy)
        gap = y - h
        act = gap > 0
        gp = np.where(act, gap, 0.0)
        eps = c["eps"]
        energy = 0.5 * eps * float((gp * gp * c["w"]).sum())
        r = np.einsum("fq,fqa->fa", eps * gp * c["w"], c["N"])
        K = None
        if need_tangent:
            K = np.einsum("fq,fqa,fqb->fab", eps * act * c["w"], c["N"], c["N"])
        force = float((eps * gp * c["w"]).sum())
        area = float((act * c["w"]).sum())
        return energy, r, K, force, area

    def _contact_pattern_values(self, cK):
        """The contact tangent's entries as (pattern positions, values)."""
        if cK is None:
            return None
        if not hasattr(self, "_contact_pos"):
            d = self.contact["dofs"]
            nl = d.shape[1]
            self._contact_pos = self._pattern.positions(np.repeat(d, nl, axis=1).ravel(), np.tile(d, (1, nl)).ravel())
        return self._contact_pos, cK.ravel()

    def evaluate(self, u, h, need_tangent=True):
        """Energy, residual (dPi/du) and tangent at displacement ``u`` with the top plate at ``h``."""
        F = self._kinematics(u)
        m = self._material(F, need_tangent)
        if m is None:
            return None
        nel, nq = self.w.shape
        re = np.matmul(self.Bt, (self.w[:, :, None] * m["P"].reshape(nel, nq, 9)).reshape(nel, nq * 9, 1))[..., 0]
        R = np.bincount(self.edofs.ravel(), re.ravel(), minlength=self.ndof)
        ce, cr, cK, cforce, carea = self._contact_terms(u, h, need_tangent)
        if cr is not None:
            R += np.bincount(self.contact["dofs"].ravel(), cr.ravel(), minlength=self.ndof)
        out = dict(energy=m["energy"] + ce, R=R, J=m["J"], contact_force=cforce, contact_area=carea, F=F)
        if need_tangent:
            nd = self.Bt.shape[1]
            Bt4 = self.Bt.reshape(nel, nd, nq, 9)
            A = m["A"].reshape(nel, nq, 9, 9)
            # T[e,d,q,:] = A[e,q] : B[e,q,d] and K_e = sum_q w B T^T, as batched matrix products
            T = np.empty((nel, nd, nq, 9))
            for q in range(nq):
                T[:, :, q, :] = np.matmul(Bt4[:, :, q, :], A[:, q].transpose(0, 2, 1))
            wB = self.Bt * np.repeat(self.w, 9, axis=1)[:, None, :]
            Ke = np.matmul(wB, T.reshape(nel, nd, nq * 9).transpose(0, 2, 1))
            G = np.matmul(self.Bt, (self.w[:, :, None] * m["dg"].reshape(nel, nq, 9)).reshape(nel, nq * 9, 1))[..., 0]
            Ke += (self.lam / self.Ve)[:, None, None] * G[:, :, None] * G[:, None, :]
            out["K"] = self._pattern.assemble(Ke, self._contact_pattern_values(cK))
        return out

    # -- solving ------------------------------------------------------------------------------
    def _apply_bc(self, u, delta):
        u = u.copy()
        u[self.fixed_dofs] = self.fixed_vals
        if self.moving.size:
            u[self.moving] = -delta
        return u

    def _homogeneous(self, delta):
        """Displacement of an incompressible homogeneous compression bringing the top plate down
        by ``delta`` (about the centre plane y = 0): the first guess for curved bodies."""
        e = delta / self.H
        t = 1.0 / math.sqrt(1.0 - e) - 1.0
        X = self.dof_points
        U = np.empty_like(X)
        U[1] = -e * X[1]
        for k in range(self.dim):
            if k != 1:
                U[k] = t * X[k]
        return U.T.ravel()

    def _contact_predictor(self, u, h_old, h):
        """The tangent predictor of a contact step from the equilibrium ``u`` at ``h_old``: the
        plate moved to ``h`` acting on the old contact patch only, K du = -dR/dh (h - h_old).
        Newton's own first step sees every point the plate has passed as in contact, pushes the
        patch's rim down with it and then spends iterations releasing it ring by ring."""
        ev0 = self.evaluate(u, h_old)
        if ev0 is None:
            return None
        c = self.contact
        y = c["y"] + np.einsum("fqa,fa->fq", c["N"], u[c["dofs"]])
        load = c["eps"] * (y > h_old) * c["w"] * (h_old - h)  # the penalty force's change, old patch
        dR = np.bincount(c["dofs"].ravel(), np.einsum("fq,fqa->fa", load, c["N"]).ravel(), minlength=self.ndof)
        out = u.copy()
        out[self.free] += self._update(ev0["K"][self.free][:, self.free], -(ev0["R"] + dR)[self.free])
        return out

    def _contact_start(self, u, delta, guess, delta_prev):
        """Contact: the lowest-energy start among the last state, the extrapolated guess and the
        tangent predictor; starting Newton with the plate deep inside the body makes the active
        set bounce."""
        h = self.H - delta
        starts = [self._apply_bc(u, delta), self._apply_bc(guess, delta)]
        if PREDICTOR and delta_prev is not None:
            p = self._contact_predictor(u, self.H - delta_prev, h)
            if p is not None:
                starts.append(self._apply_bc(p, delta))
        energies = []
        for x in starts:
            e = self.evaluate(x, h, need_tangent=False)
            energies.append(np.inf if e is None else e["energy"])
        if TRACE:
            print("    start energies", energies)
        return starts[int(np.argmin(energies))]

    def _newton(self, u, delta, max_iter=30, guess=None, delta_prev=None, rtol=1e-9):
        """Equilibrium with the plate at ``delta``: Newton from ``u`` until the largest residual
        is below ``rtol`` times ``mu_body H^2`` (the background's shear modulus; 1e-9: the
        requested states; a load step on the way there needs only a start for the next,
        ``STEP_RTOL``)."""
        h = self.H - delta if self.contact is not None else None
        if guess is not None and h is not None:
            u = self._contact_start(u, delta, guess, delta_prev)
        target = self._apply_bc(u, delta)
        du_d = target - u  # non-zero only on the prescribed dofs
        if np.any(du_d):
            # Consistent predictor from the previous equilibrium: spread the plate's motion into the
            # body (K_ff du_f = -(R_f + K_fd du_d)) instead of starting from a sheared top layer.
            ev0 = self.evaluate(u, h)
            if ev0 is None:
                raise ConvergenceError("inverted elements at the start of the step")
            K = ev0["K"].tocsr()
            rhs = -(ev0["R"] + K @ du_d)[self.free]
            du_f = self._update(K[self.free][:, self.free], rhs)
            u = target.copy()
            u[self.free] += du_f
        else:
            u = target
        ev = self.evaluate(u, h)
        if ev is None:
            raise ConvergenceError("the predictor inverts elements: step too large")
        scale = max(self.mu_body * self.H**2, 1e-12)
        res = float(np.max(np.abs(ev["R"][self.free]))) if self.free.size else 0.0
        if res < rtol * scale:
            return u, ev, 0
        for it in range(1, max_iter + 1):
            Rf = ev["R"][self.free]
            du_f = self._update(ev["K"][self.free][:, self.free], -Rf)
            slope = float(Rf @ du_f)
            alpha = 1.0
            for _ in range(12):
                trial = u.copy()
                trial[self.free] += alpha * du_f
                ev_t = self.evaluate(trial, h, need_tangent=False)  # the tangent only where accepted
                if ev_t is not None:
                    res_t = float(np.max(np.abs(ev_t["R"][self.free])))
                    # Armijo on the energy; near convergence the energy stalls at round-off, so a
                    # full step that reduces the residual is accepted too.
                    if ev_t["energy"] <= ev["energy"] + 1e-4 * alpha * min(slope, 0.0) or (
                        alpha == 1.0 and res_t < 0.5 * res
                    ):
                        break
                alpha *= 0.5
            else:
                if slope >= 0:
                    # -K^-1 R climbs the energy: K has a negative eigenvalue, so no Newton step
                    # descends; the equilibrium path has reached a limit point (buckling, creasing)
                    raise InstabilityError(
                        "the tangent stiffness is not positive definite (Newton's update climbs the energy)"
                    )
                raise ConvergenceError("line search failed (no decrease of the energy keeping J > 0)")
            if TRACE:
                print(f"    it {it} alpha {alpha} res {res_t:.2e} area {ev_t['contact_area']:.3f}")
            u, ev, res = trial, ev_t, res_t
            step = alpha * float(np.max(np.abs(du_f))) if du_f.size else 0.0
            if res < rtol * scale or (step < 1e-11 * self.H and res < 1e-6 * scale):
                return u, ev, it
            ev = self.evaluate(u, h)
        raise ConvergenceError(f"Newton did not converge in {max_iter} iterations (residual {res:.3g} N)")

    def _linsolve(self, K, rhs):
        """Solve the tangent system. A sparse LU costs seconds in 3D (fill of tens of millions),
        while the tangent changes little from one Newton iteration or load step to the next; so
        the last factorisation preconditions GMRES on the current tangent (a handful of
        iterations, tens of ms each), and K is factorised anew only when that stalls.

        The Newton update needs only ``LINEAR_RTOL`` relative accuracy (an inexact Newton
        method: the converged state is set by the residual test in :meth:`_newton`, not by the
        linear solves). The factorisation is renewed once GMRES has spent on it as much as it
        cost (rent or buy), counted in iterations (``LU_PRICE``) rather than measured seconds, so
        that the work, and with it the Newton path, does not depend on the machine's load.
        ``self.factorisations`` and ``self.krylov_iterations`` count the work.

        Stops: a signal's handler (the command's: SIGINT, SIGTERM, SIGHUP, SIGQUIT raise an
        ``Interrupted``) runs at the next Python instruction, so between Newton iterations, line
        search trials and GMRES iterations (scipy's loop is Python) a stop ends the solve at
        once; nothing here catches it (``solve`` retries only a ``ConvergenceError``). SuperLU's
        factorisation is C that does not look at Python's signal flag (71 s for 11 500
        tetrahedra at load 10): it runs in a thread of its own (:func:`_stoppable`), so a stop
        is acted on at once (the outputs removed, the message said), though the process exits
        only when that factorisation ends. A triangular solve (GMRES's preconditioner) is
        milliseconds."""
        K = K.tocsc()
        nrhs = float(np.linalg.norm(rhs))
        if nrhs == 0.0:
            return np.zeros_like(rhs)
        if self._lu is not None and self._lu.shape == K.shape:
            its = [0]

            def count(_):
                its[0] += 1

            # never spend more on one GMRES solve than a factorisation costs: a tangent that has
            # moved far (the contact patch's edge jumping) is cheaper to factorise than to iterate
            x, _info = spla.gmres(
                K,
                rhs,
                rtol=LINEAR_RTOL,
                atol=0.0,
                restart=LU_PRICE,
                maxiter=1,
                M=spla.LinearOperator(K.shape, self._lu.solve),
                callback=count,
                callback_type="pr_norm",
            )
            self.krylov_iterations += its[0]
            self._krylov_spent += its[0]
            # judged by the true residual: scipy flags info=1 on stagnation that is good enough
            if np.all(np.isfinite(x)) and np.linalg.norm(K @ x - rhs) <= 100 * LINEAR_RTOL * nrhs:
                if self._krylov_spent > LU_PRICE:
                    # the preconditioner has aged: it has cost in iterations what a new one costs
                    # (rent or buy: never more than twice the best choice in hindsight)
                    self._lu = None
                return x
        self._lu = None  # one factorisation held at a time: the old one freed before the new one's fill
        self._lu = self._factorise(K)
        self._krylov_spent = 0
        self.factorisations += 1
        x = self._lu.solve(rhs)
        if not np.all(np.isfinite(x)):
            raise ConvergenceError("the tangent is singular (non-finite update)")
        return x

    @staticmethod
    def _factorise(K):
        """Sparse LU with a symmetric ordering (minimum degree on K + K^T, diagonal pivots
        preferred): half the fill and time of SuperLU's default COLAMD on these tangents; if that
        fails or is inaccurate (an indefinite tangent far from equilibrium), partial pivoting."""
        try:
            lu = _stoppable(
                spla.splu, K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.01, options={"SymmetricMode": True}
            )
            probe = np.random.default_rng(0).standard_normal(K.shape[0])
            y = lu.solve(K @ probe)
            if np.all(np.isfinite(y)) and np.linalg.norm(y - probe) <= 1e-6 * np.linalg.norm(probe):
                return lu
        except RuntimeError:
            pass
        try:
            return _stoppable(spla.splu, K)
        except (RuntimeError, ValueError) as exc:
            raise ConvergenceError(f"linear solve failed: {exc}") from exc

    def _state(self, u, ev, ratio, delta, iterations, steps) -> State:
        if self.contact is not None:
            force = ev["contact_force"]
            area = ev["contact_area"]
        else:
            force = abs(float(np.sum(ev["R"][self.moving])))  # internal force at the plate's dofs
            area = float("nan")
        vol = float((np.linalg.det(ev["F"]) * self.w).sum() / self.w.sum())
        gap = self.gap0 - 2 * delta if "y" in self.fem.symmetry else self.gap0 - delta
        inc_strain, bg_strain = self._strains(ev["F"])
        return State(
            ratio=ratio,
            gap_mm=gap,
            plate_force_n=force * self.force_multiplicity,
            volume_ratio=vol,
            displacement=u.reshape(self.n_nodes, self.dim).T.copy(),
            newton_iterations=iterations,
            load_steps=steps,
            contact_area_mm2=area * self.force_multiplicity,
            inclusion_strain=inc_strain,
            background_strain=bg_strain,
            linear_min_stretch=self._svk_min_stretch(ev["F"]),
        )

    def _svk_min_stretch(self, F) -> float:
        """The smallest principal stretch (square root of C = F^T F's eigenvalues) over the
        quadrature points of St Venant-Kirchhoff elements; NaN without any."""
        if not self.svk.any():
            return float("nan")
        Fs = F[self.svk]
        C = np.einsum("eqki,eqkj->eqij", Fs, Fs)
        return float(np.sqrt(max(np.linalg.eigvalsh(C)[..., 0].min(), 0.0)))

    def _strains(self, F):
        """Volume-averaged compressive strain 1 - F_yy of the inclusions and of the background."""
        eyy = 1.0 - F[:, :, 1, 1]
        out = []
        for sel in (self.region > 0, self.region == 0):
            if sel.any():
                out.append(float((eyy[sel] * self.w[sel]).sum() / self.w[sel].sum()))
            else:
                out.append(float("nan"))
        return tuple(out)

    def solve(self, ratios, progress=False, min_step=1e-4, on_step=None, on_state=None) -> list[State]:
        """March the plates to each ratio in turn (sorted), adapting the load step.

        ``on_step(ratio, newton_iterations, seconds)`` is called after each converged load step,
        ``on_state(state)`` as each requested ratio is reached."""
        from radiokit.progress import tqdm

        ratios = sorted(float(r) for r in ratios)
        per_plate = 0.5 if "y" in self.fem.symmetry else 1.0  # each plate moves half the closure
        u = np.zeros(self.ndof)
        states = []
        r_now = 0.0
        step = min(FIRST_STEP, ratios[-1] / 3) if ratios else FIRST_STEP
        total_steps = 0
        bar = tqdm(total=len(ratios), desc=f"compress {self.scene.name}", unit="state", disable=not progress)
        # converged (delta, u, energy, dPi/d delta): the next guess extrapolates the last two, and
        # the next step's energy change must be the plate's work from the last (_path_check)
        history = [(0.0, u, 0.0, 0.0)]
        unstable = False  # a limit point met since the last converged step
        for target in ratios:
            iters_total = 0
            while r_now < target - 1e-12:
                r_try = min(target, r_now + step)
                if self.contact is not None and r_now > 0:
                    # a patch growing by more than half its approach per step outruns the
                    # predictor (the rim penetrates deep and the line search crawls)
                    r_try = min(r_try, CONTACT_GROWTH * r_now)
                delta = r_try * self.gap0 * per_plate
                t_step = time.perf_counter()
                try:
                    u_new, ev, its = self._newton(
                        u,
                        delta,
                        guess=self._guess(history, delta),
                        delta_prev=history[-1][0],
                        rtol=1e-9 if r_try >= target - 1e-12 else STEP_RTOL,
                    )
                    energy, rate = self._path_check(history[-1], delta, ev)
                except ConvergenceError as exc:
                    unstable |= isinstance(exc, InstabilityError)
                    step /= 2
                    if step < min_step:
                        bar.close()
                        raise ConvergenceError(
                            self._stall_message(r_try, r_now, target, min_step, history[-1], unstable, exc)
                        ) from exc
                    continue
                u, r_now, unstable = u_new, r_try, False
                history = [history[-1], (delta, u, energy, rate)]
                total_steps += 1
                if on_step is not None:
                    on_step(r_now, its, time.perf_counter() - t_step)
                iters_total += its
                if its <= EASY_STEP:
                    step *= 1.5
            if not states or states[-1].ratio != target:
                if r_now == 0.0:
                    u, ev, its = self._newton(u, 0.0)
                states.append(self._keep_state(u, ev, target, target * self.gap0 * per_plate, iters_total, total_steps))
                if on_state is not None:
                    on_state(states[-1])
            bar.update(1)
        bar.close()
        return states

    def _guess(self, history, delta):
        """The next step's start: the last two equilibria extrapolated (the homogeneous
        compression's increment after the first)."""
        d1, u1 = history[-1][:2]
        if len(history) > 1:
            d0, u0 = history[-2][:2]
            return u1 + (delta - d1) / (d1 - d0) * (u1 - u0)
        return u1 + self._homogeneous(delta) - self._homogeneous(d1)

    def _plate_rate(self, ev) -> float:
        """dPi/d delta at an equilibrium: the plate's force on the model (contact: the penalty
        force; flat plates: minus the residual on the dofs held at -delta)."""
        if self.contact is not None:
            return float(ev["contact_force"])
        return -float(np.sum(ev["R"][self.moving]))

    def _path_check(self, last, delta, ev):
        """Refuse a load step that left its equilibrium branch; returns (energy, dPi/d delta).

        Along one branch dPi/d delta is the plate force (the plates alone do work, frictionless,
        hyperelastic), so the energy's change over a step is the trapezoid of the end forces to
        O(step^3). Past a limit point the branch ends and Newton lands on another one (a crease,
        a collapsed inclusion): the energy then drops by what the snap releases, and where the
        march goes on (or stops) depends on how the user split the steps. ``SNAP_TOL`` of
        step x force separates the two."""
        d0, _, e0, f0 = last
        f = self._plate_rate(ev)
        mismatch = ev["energy"] - e0 - (delta - d0) * (f0 + f) / 2
        floor = 1e-12 * float(np.max(self.mu)) * self.H**3
        if abs(mismatch) > SNAP_TOL * (delta - d0) * max(abs(f0), abs(f)) + floor:
            raise InstabilityError(
                f"the step snapped to another equilibrium branch (its energy change differs from the plates' work "
                f"by {abs(mismatch) / max((delta - d0) * max(abs(f0), abs(f)), 1e-300):.2g} of step x force)"
            )
        return ev["energy"], f

    def _stall_message(self, r_try, r_now, target, min_step, last, unstable, exc) -> str:
        """One line: where the march stalled, what was asked, and why where known (a 'linear'
        material past its limit point, or a limit point of the equilibrium path)."""
        # the last attempt's reason alone ("step too large") would read as if a larger step had
        # been tried; say that the march itself has stalled
        msg = (
            f"scene {self.scene.name!r}: the solver does not converge: cannot reach compression "
            f"{100 * r_try:.2f} % (from {100 * r_now:.2f} %) on the way to {100 * target:.2f} %, "
            f"the load step halved below {100 * min_step:.2g} %"
        )
        ev = self.evaluate(last[1], self.H - last[0] if self.contact is not None else None, need_tangent=False)
        stretch = self._svk_min_stretch(ev["F"]) if ev is not None else float("nan")
        if stretch < SVK_LIMIT_STRETCH:
            msg += (
                f": a 'linear' (St Venant-Kirchhoff) material is stretched to {stretch:.3f} at {100 * r_now:.2f} %, "
                f"past 1/sqrt(3) = {SVK_LIMIT_STRETCH:.3f} where its stress peaks, and collapses beyond: no solid "
                "equilibrium lies further (use neo-hookean)"
            )
        elif unstable:
            msg += (
                f": the equilibrium becomes unstable at {100 * r_now:.2f} % (a limit point{self._where_unstable(last)})"
            )
        return f"{msg}; last attempt: {exc}"

    def _where_unstable(self, last) -> str:
        """The unstable mode's place and what it means, for the stall message."""
        found = self._unstable_mode(last[1], last[0])
        if found is None:
            return ": the body buckles, a free surface creases or a material softens"
        where, region = found
        at = "(" + ", ".join(f"{x:.1f}" for x in where) + ") mm"
        if region == 0:
            return f" in the body, largest at {at}: it buckles or a free surface creases, which this model, without self-contact, cannot follow"
        mat = self.scene.inclusions[region - 1].material
        hint = (
            ": St Venant-Kirchhoff's energy is not convex in strong compression (use neo-hookean)"
            if mat.model == "linear"
            else ""
        )
        return f" in inclusions[{region - 1}] ({mat.model} {mat.name!r}), largest at {at}{hint}"

    def _unstable_mode(self, u, delta):
        """Where the equilibrium at ``u`` loses stability: the eigenvector of the tangent's
        eigenvalue nearest zero (one shift-invert Lanczos, at a stall only). Returns the node of
        largest amplitude (mm) and the region (0: the body, i + 1: inclusion i) of most of the
        mode's amplitude."""
        ev = self.evaluate(u, self.H - delta if self.contact is not None else None)
        if ev is None or not self.free.size:
            return None
        K = ev["K"][self.free][:, self.free].tocsc()
        shift = 1e-8 * float(np.abs(K.diagonal()).mean())
        try:
            lu = self._factorise((K + shift * sp.identity(K.shape[0], format="csc")).tocsc())
            op = spla.LinearOperator(K.shape, lu.solve)
            _, vec = spla.eigsh(K, k=1, sigma=-shift, OPinv=op, which="LM", tol=1e-3, maxiter=200)
        except (ConvergenceError, spla.ArpackNoConvergence, RuntimeError):
            return None
        v = np.zeros(self.ndof)
        v[self.free] = vec[:, 0]
        amp = np.linalg.norm(v.reshape(self.n_nodes, self.dim), axis=1)
        where = self.dof_points[:, int(np.argmax(amp))]
        # the mode's amplitude per element (its nodes'), summed per region
        per_element = (amp[self.basis.element_dofs.T] ** 2).sum(axis=1)
        region = int(np.argmax(np.bincount(self.region, per_element)))
        return where, region

    def _keep_state(self, u, ev, target, delta, iterations, steps) -> State:
        """The requested state, warned about where a 'linear' material is past its limit point."""
        state = self._state(u, ev, target, delta, iterations, steps)
        state.solver = self
        if state.linear_min_stretch < SVK_LIMIT_STRETCH:
            warnings.warn(
                f"scene {self.scene.name!r} at compression {100 * target:.2f} %: a 'linear' (St "
                f"Venant-Kirchhoff) material is stretched to {state.linear_min_stretch:.3f}, below "
                f"1/sqrt(3) = {SVK_LIMIT_STRETCH:.3f} where its stress peaks and then falls: it no longer "
                "describes a solid there (use neo-hookean)",
                MaterialWarning,
                stacklevel=3,
            )
        return state


def compress(
    scene: Scene, ratios=None, *, fem: FEMesh | None = None, progress=False, on_step=None, on_state=None
) -> list[State]:
    """Compress ``scene`` to each of ``ratios`` (default: the scene's) and return the states.

    Each state keeps its :class:`Solver` as ``state.solver`` (mesh, dof layout, timings in
    ``solver.seconds``); see :meth:`Solver.solve` for the callbacks.
    """
    from sim.scene import load_scene

    t0 = time.perf_counter()
    scene = load_scene(scene).validate()  # its fields may have been replaced since it was made
    solver = Solver(scene, fem)
    states = solver.solve(
        scene.compression.ratios if ratios is None else ratios, progress=progress, on_step=on_step, on_state=on_state
    )
    solver.seconds = time.perf_counter() - t0
    return states
