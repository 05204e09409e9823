"""Benchmark: one 2240 x 2240 projection (``sim.xray.project``) of the preset meshes.

Run (about 20 s on a 2-core machine)::

    python benchmarks/bench_project.py [--reps 5] [--supersample 1]

For ``seed-breast`` and ``pva-phantom`` (``build_mesh(load_scene(name))``, zero displacement),
and for ``pva-phantom`` meshed as an axisymmetric section (revolved into triangles), each with a
parallel and a cone beam (the scene's own beam direction, distances and detector): the surface
triangle count, the time of the first call (which also extracts and mirrors the region
boundaries; cached per mesh afterwards) and the median over ``--reps`` further calls, in ms.
Target: <= 2000 ms per projection. The numbers of covered pixels and the maximum line integral
are printed as a sanity check; every image is checked to be finite and float32.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np

from sim.mesh import build_mesh
from sim.scene import load_scene
from sim.xray import _cached_surface, project


def _cases():
    for name in ("seed-breast", "pva-phantom"):
        scene = load_scene(name)
        yield name, scene, build_mesh(scene)
    scene = load_scene("pva-phantom")
    scene.mesh = dataclasses.replace(scene.mesh, model="axisymmetric")
    yield "pva-phantom (axisymmetric)", scene, build_mesh(scene)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=5, help="timed repetitions after the first call")
    ap.add_argument("--supersample", type=int, default=1)
    args = ap.parse_args(argv)
    print(
        f"{'mesh':28s} {'beam':9s} {'triangles':>9s} {'first ms':>9s} {'median ms':>9s} "
        f"{'covered px':>10s} {'max mu L':>8s}"
    )
    worst = 0.0
    for name, scene, fem in _cases():
        for kind in ("parallel", "cone"):
            scene.beam = dataclasses.replace(scene.beam, kind=kind)
            t0 = time.perf_counter()
            img = project(scene, None, fem=fem, supersample=args.supersample)
            first = time.perf_counter() - t0
            times = []
            for _ in range(args.reps):
                t0 = time.perf_counter()
                img = project(scene, None, fem=fem, supersample=args.supersample)
                times.append(time.perf_counter() - t0)
            assert img.dtype == np.float32 and img.shape == tuple(scene.detector.shape)
            assert np.isfinite(img).all()
            med = statistics.median(times)
            worst = max(worst, med)
            n_tri = len(
                _cached_surface(fem, None if fem.model != "plane-strain" else scene.body.size_mm[2], 1e-5).faces
            )
            print(
                f"{name:28s} {kind:9s} {n_tri:9d} {1e3 * first:9.0f} {1e3 * med:9.0f} "
                f"{int((img > 0).sum()):10d} {float(img.max()):8.4f}"
            )
    print(f"slowest median: {1e3 * worst:.0f} ms (target <= 2000 ms): {'OK' if worst <= 2.0 else 'MISSED'}")


if __name__ == "__main__":
    main()
