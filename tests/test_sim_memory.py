"""The mechanics' memory, judged before the solve, and stops during it (review s41sim: a 30 800-
tetrahedron mesh of seed-breast reached 6.4 GB within 326 s and did not answer SIGTERM in 5 s)."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tomli_w

from tests.test_sim_scene_checks import base

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_solving(monkeypatch):
    """The solver's set-up must not be reached by a mesh over the budget."""
    import sim.mechanics

    def reached(*_, **__):
        raise AssertionError("the mechanics set up a mesh over the memory budget")

    monkeypatch.setattr(sim.mechanics.Solver, "_gradient_operator", reached)


def test_a_mesh_over_the_memory_budget_is_refused_naming_the_scene_file_and_its_sizes(
    tmp_path, monkeypatch, capsys, no_solving
):
    from radiokit.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text(tomli_w.dumps(base()))  # a 10 mm cube meshed at 1 / 2.5 mm: about 30 MB to solve
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", "1MiB")  # the budget, set small (no fake)
    assert main(["sim", "run", str(scene), "-o", str(tmp_path / "sim.h5"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(scene) in err and "mesh size_inclusion_mm 1, size_far_mm 2.5:" in err
    assert "over the memory budget of 1.0 MiB" in err and "RADIOKIT_MEMORY_BUDGET" in err
    # the estimate quoted is the mesh's: 314 tetrahedra at 83.5 kB each set up (SOLVE_MEMORY), within 2x
    need = float(re.search(r"would need about ([0-9.]+) MiB", err).group(1))
    assert 12 < need < 50, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


def test_a_mesh_within_the_budget_is_solved(monkeypatch):
    from sim.mechanics import compress, estimate_solve_bytes
    from sim.mesh import build_mesh
    from sim.scene import Scene

    scene = Scene.from_toml(tomli_w.dumps(base()))
    fem = build_mesh(scene)
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", str(2 * estimate_solve_bytes(fem)))
    assert compress(scene, [0.05], fem=fem)[0].plate_force_n > 0


def test_the_memory_estimate_follows_the_measured_peak():
    """The estimate against the high-water mark of a set-up and a factorisation measured in a
    process of its own (benchmarks/bench_mechanics_memory.py) on a mesh where the factorisation
    sets the peak: within the fit's spread, -8 % to +12 % (benchmarks/README.md), widened to
    -15 %/+25 % for the allocator's and the libraries' versions; about 15 s."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = [sys.executable, "-m", "benchmarks.bench_mechanics_memory"]
    mesh = ROOT / ".pytest_cache" / f"mesh-{os.getpid()}.pickle"
    mesh.parent.mkdir(exist_ok=True)
    try:
        subprocess.run([*run, "--mesh", "0.7/6/1", str(mesh)], check=True, env=env, timeout=300)
        out = subprocess.run(
            [*run, "--one", "0.7/6/1", str(mesh)], check=True, env=env, timeout=300, capture_output=True, text=True
        )
    finally:
        mesh.unlink(missing_ok=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["peak_bytes"] > r["setup_bytes"]  # the factorisation's term is the one judged
    assert 0.85 <= r["estimate_bytes"] / r["peak_bytes"] <= 1.25, r


def test_a_stop_between_newton_iterations_ends_the_run_at_once(tmp_path):
    """SIGTERM once a load step has converged (Python code runs between the solves, where the
    handler's exception is raised): exit 143, nothing left. Inside one factorisation (SuperLU, C)
    the handler runs only when it returns: seed-breast's take well under a second."""
    out = tmp_path / "sim.h5"
    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; from radiokit.cli import main; sys.exit(main())", "sim", "run"]
        + ["--preset", "seed-breast", "-o", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        for line in proc.stdout:
            if "load step to" in line:
                break
        else:
            pytest.fail(f"no load step: {proc.wait()} {proc.stderr.read()}")
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
        waited = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 128 + signal.SIGTERM, proc.stderr.read()
    assert waited < 5, waited
    assert list(tmp_path.iterdir()) == []


_FACTORISE = """
import sys, time
import scipy.sparse as sp
from sim.mechanics import Solver

n = 30  # a 3D Laplacian of 27 000 unknowns: a factorisation of a few seconds, as a mesh's
line = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], (n, n))
eye = sp.eye(n)
K = (sp.kron(sp.kron(eye, eye), line) + sp.kron(sp.kron(eye, line), eye) + sp.kron(sp.kron(line, eye), eye)).tocsc()
t = time.monotonic()
Solver._factorise(K)
print(time.monotonic() - t, flush=True)
print("again", flush=True)
try:
    Solver._factorise(K)
    print("finished", flush=True)
except KeyboardInterrupt:
    print("interrupted", flush=True)
"""


def test_a_stop_during_a_factorisation_is_acted_on_before_it_ends():
    """SuperLU's factorisation is C that does not look at Python's signals: Ctrl-C waited for its
    end (71 s for 11 500 tetrahedra at load 10, benchmarks/README.md). It runs in a thread of its
    own while the main thread waits in short slices, so the stop is raised at once; the process
    still ends only with the factorisation."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-c", _FACTORISE], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    try:
        alone = float(proc.stdout.readline())
        assert proc.stdout.readline().strip() == "again", proc.stderr.read()
        time.sleep(0.1 * alone)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        said = proc.stdout.readline().strip()
        waited = time.monotonic() - t0
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert said == "interrupted" and waited < 0.4 * alone, (said, waited, alone)
    # the factorisation ran on to its end, then the process exited as it chose: not a crash in BLAS
    assert proc.returncode == 0, proc.stderr.read()
