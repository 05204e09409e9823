"""Measurement: a pixel's central ray against the pixel's area-averaged transmission (a modelling choice).

Run (about a minute on a 2-core machine; gmsh meshes both presets)::

    python benchmarks/bench_pixel_average.py [--sub 4] [--binning 4 2]

``sim.xray.project`` (and so the simulated experiment) renders one ray per read-out pixel, through
its centre. A real pixel, and a binned one more so, integrates the intensity over its area: it
measures ``L_area = -ln(mean over the pixel of exp(-L))``. The two differ only where ``L`` varies
across a pixel: at the body's silhouette and the inclusion's edge (a partial-volume term of first
order in the edge's offset from the centre, and Jensen's second-order term, always ``L_area <=
mean L``). For each preset, undeformed (``sim.mesh.undeformed_projection_mesh``), the scene's own
beam and the scene's detector at each ``--binning``, the pixel's area is sampled by ``sub x sub``
sub-rays (a grid ``sub`` times finer, whose centres are the sub-pixel centres) and the table gives:

- ``pixels >1e-3``: read-out pixels where ``|L_centre - L_area| > 1e-3``, and their share of the
  body's shadow;
- ``max |dL|``: the largest difference (an edge pixel);
- ``mask dL``: the mean difference over the inclusion's mask (the centre rays through the
  inclusion, the ROI the paper's measures read), against the inclusion's mean contrast there
  (``(mu_inc - mu_gel)`` times its mean chord);
- ``jensen``: the largest ``mean L - L_area`` (what ``supersample``, which averages line
  integrals, leaves out).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from sim.mesh import undeformed_projection_mesh
from sim.scene import load_scene, with_binning
from sim.xray import Geometry, line_integral, path_lengths


def _mu(scene):
    return [scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions]


def measure(name, binning, sub):
    scene = with_binning(load_scene(name), binning) if binning != 1 else load_scene(name)
    fem = undeformed_projection_mesh(scene)
    g = Geometry.from_scene(scene)
    mu = _mu(scene)
    rows, cols = g.shape
    fine = dataclasses.replace(g, shape=(rows * sub, cols * sub), pixel_size_mm=g.pixel_size_mm / sub)
    centre = line_integral(fem, g, mu)
    Lf = line_integral(fem, fine, mu).reshape(rows, sub, cols, sub)
    area = -np.log(np.exp(-Lf).mean(axis=(1, 3)))
    mean_l = Lf.mean(axis=(1, 3))
    d = centre - area
    body = path_lengths(fem, g)
    mask = body[1] > 0
    shadow = centre > 0
    big = np.abs(d) > 1e-3
    contrast = (mu[1] - mu[0]) * body[1][mask].mean()
    return {
        "scene": f"{name} ({scene.beam.kind}, {scene.beam.direction}), {binning}x{binning}, {g.pixel_size_mm:.2f} mm",
        "pixels": f"{int(big.sum())} ({100 * big.sum() / shadow.sum():.2f} %)",
        "max": f"{np.abs(d).max():.3f}",
        "mask": f"{d[mask].mean():+.2e} ({100 * d[mask].mean() / contrast:+.2f} % of {contrast:.3f})",
        "jensen": f"{(mean_l - area).max():.1e}",
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sub", type=int, default=4, help="sub-rays per pixel side")
    ap.add_argument("--binning", type=int, nargs="+", default=[4, 2])
    args = ap.parse_args(argv)
    print(
        "| scene, binning, pitch | pixels >1e-3 (of the shadow) | max abs dL | mask dL (of the contrast) | jensen | s |"
    )
    print("|---|---|---|---|---|---|")
    for name in ("seed-breast", "pva-phantom"):
        for b in args.binning:
            t0 = time.perf_counter()
            r = measure(name, b, args.sub)
            print(
                f"| {r['scene']} | {r['pixels']} | {r['max']} | {r['mask']} | {r['jensen']} "
                f"| {time.perf_counter() - t0:.0f} |"
            )


if __name__ == "__main__":
    main()
