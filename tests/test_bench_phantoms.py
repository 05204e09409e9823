"""benchmarks/bench_register_phantoms.py: its projections are exact chords (their sums are the
solids' volumes), its moving image is rendered at the inverse of the truth's map (``x + d(x)``
comes back to the pixel), and its random fields do not fold (strain capped)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_register_phantoms as P


def test_chords_sum_to_the_solids_volumes():
    # a fine grid (0.25 px): the sum of chords x pixel area is the volume, to the grid's edge error
    h = 0.25
    y, x = np.mgrid[-60:60:h, -60:60:h] + h / 2
    ell = P._chord_ellipsoid(y, x, 0.0, 0.0, 40.0, 25.0, 15.0, angle=0.4).sum() * h * h
    assert ell == pytest.approx(4 / 3 * np.pi * 40 * 25 * 15, rel=2e-3)
    cyl = P._chord_cylinder(y, x, 0.0, 0.0, 20.0, 50.0, angle=-0.2).sum() * h * h
    assert cyl == pytest.approx(np.pi * 20**2 * 100, rel=5e-3)
    # the rounded square (|u|^4 + |v|^4 <= 1): area 4 Gamma(1 + 1/4)^2 / Gamma(1 + 1/2) a b
    from math import gamma

    box = P._chord_prism(y, x, 0.0, 0.0, 30.0, 20.0, 2.0).sum() * h * h
    assert box == pytest.approx(2.0 * 4 * gamma(1.25) ** 2 / gamma(1.5) * 30 * 20, rel=5e-3)


@pytest.mark.parametrize("seed", [6000, 6005, 6010, 6020, 6025])  # compress, lag, random, shift, rotate
def test_the_moving_image_is_rendered_at_the_inverse_map(seed):
    rng = np.random.default_rng(seed)
    n = 128
    scene = P._draw_scene(rng, n)
    motion = P._draw_motion(rng, scene, P.MOTIONS[(seed // len(P.TEXTURES)) % len(P.MOTIONS)])
    grid = P._random_grid(motion, n) if motion["kind"] == "random" else None
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    py, px = P._inverse(motion, scene, y, x, grid)
    d = P._field(motion, scene, py, px, grid)
    assert np.abs(py + d[0] - y).max() < 1e-3 and np.abs(px + d[1] - x).max() < 1e-3


def test_random_fields_are_capped_in_strain():
    motion = {"kind": "random", "corr": 256 / 20, "amp": 0.04 * 256, "seed": 1}
    g, pad = P._random_grid(motion, 256)
    strain = max(np.abs(np.gradient(c, axis=a)).max() for c in g for a in (0, 1))
    assert strain <= P.MAX_STRAIN + 1e-9
    assert motion["amp"] < 0.04 * 256  # lowered, and recorded as lowered
