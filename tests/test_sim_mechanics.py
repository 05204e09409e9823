"""Scenes, meshing and mechanics checked against closed forms (issue 3, first part)."""
import numpy as np
import pytest

from sim.mechanics import compress, uniaxial_block_force
from sim.mesh import build_mesh
from sim.scene import PRESETS, Scene, block_scene, load_scene


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_round_trip_through_toml(name, tmp_path):
    scene = load_scene(name)
    assert Scene.from_toml(scene.to_toml()) == scene
    path = scene.save(tmp_path / f"{name}.toml")
    assert load_scene(str(path)) == scene


def test_bad_scene_keys_are_named():
    with pytest.raises(ValueError, match="unknown keys.*colour"):
        Scene.from_toml('name = "x"\ncolour = "red"\n')
    with pytest.raises(ValueError, match="nu"):
        Scene.from_toml('[body]\ngeometry = "box"\n[body.material]\nE_kpa = 5.0\nnu = 0.6\n')


def test_seed_breast_mesh_is_a_quarter_with_a_conforming_inclusion():
    fem = build_mesh(load_scene("seed-breast"))
    assert fem.symmetry == ("y", "z")
    assert fem.points.min(axis=1) == pytest.approx([0, 0, 0], abs=1e-9)
    assert fem.points.max(axis=1) == pytest.approx([50, 25, 25], rel=1e-6)
    # volume of the meshed inclusion: a quarter of the 8 mm sphere, to the faceting error
    p, t = fem.points, fem.cells
    a, b, c, d = (p[:, t[i]] for i in range(4))
    vol = np.einsum("ij,ij->j", np.cross(b - a, c - a, axis=0), d - a) / 6
    assert (vol > 0).all()
    v_inc = vol[fem.region == 1].sum()
    assert v_inc == pytest.approx(np.pi / 6 * 8 ** 3 / 4, rel=0.03)
    v_all = vol.sum()
    assert v_all == pytest.approx(2 / 3 * np.pi * 50 * 25 * 25 / 4, rel=0.03)


@pytest.mark.parametrize("nu", [0.45, 0.495])
def test_block_force_matches_closed_form(nu):
    """Homogeneous uniaxial compression is exactly representable: the FE plate force must equal
    the closed-form solution of FEBio's neo-Hookean energy (lateral stretch solved numerically)."""
    states = compress(block_scene(size_mm=10, E_kpa=5, nu=nu))
    for s in states:
        force, t = uniaxial_block_force(s.ratio, 5, nu, area_mm2=100.0)
        assert s.plate_force_n == pytest.approx(force, rel=1e-6)
        assert s.gap_mm == pytest.approx(10 * (1 - s.ratio))
        assert s.volume_ratio == pytest.approx((1 - s.ratio) * t * t, rel=1e-6)
    if nu == 0.495:
        assert all(abs(s.volume_ratio - 1) < 0.01 for s in states)
