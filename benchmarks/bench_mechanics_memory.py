"""Peak memory of the mechanics' solve against the mesh: the measurements behind
``sim.mechanics.estimate_solve_bytes`` (benchmarks/README.md, "Mechanics memory").

Each mesh is measured in a process of its own (Linux's VmHWM, the high-water mark of its resident memory, reset after loading the mesh): the
solver is set up, the tangent at the first load step assembled and factorised once, as the first
Newton iteration does; that is the solve's peak (later iterations reuse the storage: one
factorisation is held at a time). Printed per mesh: elements, P2 nodes, unknowns, the tangent's
non-zeros, the LU's fill (nnz(L) + nnz(U)), the peak above the interpreter's own, the estimate.

    nice -n 10 .venv/bin/python -m benchmarks.bench_mechanics_memory [far/inclusion/contact ...]

Keep the meshes small on a shared machine: 0.7/6/1 mm peaks near 0.3 GB, 0.5/4/0.8 near 1 GB.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT = ["1.0/8/1.4", "0.8/6/1.1", "0.7/5/1.0", "0.55/4/0.8"]


def scene_for(sizes: str):
    from sim.scene import MeshSpec, load_scene

    # "inc/far/contact" mm: seed-breast in 3D; "axisymmetric:inc/far/-": pva-phantom's section
    model, _, sizes = sizes.rpartition(":")
    inc, far, contact = sizes.split("/")
    scene = load_scene("pva-phantom" if model else "seed-breast")
    model = model or "3d"
    scene.mesh = MeshSpec(
        float(inc), float(far), model, True, size_contact_mm=None if contact == "-" else float(contact)
    )
    return scene


def mesh(sizes: str, mesh_file: str) -> None:
    from sim.mesh import build_mesh

    with open(mesh_file, "wb") as f:
        pickle.dump(build_mesh(scene_for(sizes)), f)


def _status(key: str) -> int:
    """A size from /proc/self/status (bytes). Not ``ru_maxrss``: Linux keeps it across fork and
    exec, so a child of a large process (a pytest worker) started from its parent's peak."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise OSError(f"/proc/self/status has no {key}")


def measure(sizes: str, mesh_file: str) -> dict:
    import time

    import numpy as np

    import sim.mechanics
    from sim.mechanics import Solver

    scene = scene_for(sizes)
    with open(mesh_file, "rb") as f:  # meshed in another process: gmsh's own peak is not the solve's
        fem = pickle.load(f)
    base = _status("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # the high-water mark from here: the solve's
    estimate = getattr(sim.mechanics, "estimate_solve_bytes", lambda fem: 0)(fem)
    t0 = time.perf_counter()
    solver = Solver(scene, fem)
    # the tangent at rest: its pattern and the LU's fill are those of every step
    ev = solver.evaluate(np.zeros(solver.ndof), solver.H if solver.contact is not None else None)
    K = ev["K"].tocsr()[solver.free][:, solver.free].tocsc()
    del ev
    setup = _status("VmHWM")
    lu = Solver._factorise(K)
    peak = _status("VmHWM")
    return {
        "sizes": sizes,
        "elements": int(fem.cells.shape[1]),
        "nodes": int(solver.n_nodes),
        "unknowns": int(K.shape[0]),
        "nnz_K": int(K.nnz),
        "fill": int(lu.L.nnz + lu.U.nnz),
        "setup_bytes": int(setup - base),
        "peak_bytes": int(peak - base),
        "estimate_bytes": int(estimate),
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main(argv: list[str]) -> None:
    if argv[:1] == ["--mesh"]:
        mesh(argv[1], argv[2])
        return
    if argv[:1] == ["--one"]:
        print(json.dumps(measure(argv[1], argv[2])))
        return
    print(
        f"{'sizes mm':>12} {'elements':>8} {'nodes':>7} {'unknowns':>8} {'nnz K':>10} {'fill':>11} "
        f"{'setup MB':>8} {'peak MB':>8} {'est. MB':>8} {'s':>6}"
    )
    for sizes in argv or DEFAULT:
        with tempfile.TemporaryDirectory() as tmp:
            mesh_file = os.path.join(tmp, "mesh.pickle")
            run = [sys.executable, "-m", "benchmarks.bench_mechanics_memory"]
            subprocess.run([*run, "--mesh", sizes, mesh_file], capture_output=True, check=True)
            out = subprocess.run([*run, "--one", sizes, mesh_file], capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(
            f"{r['sizes']:>12} {r['elements']:>8} {r['nodes']:>7} {r['unknowns']:>8} {r['nnz_K']:>10} "
            f"{r['fill']:>11} {r['setup_bytes'] / 1e6:>8.0f} {r['peak_bytes'] / 1e6:>8.0f} {r['estimate_bytes'] / 1e6:>8.0f} {r['seconds']:>6}",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1:])
