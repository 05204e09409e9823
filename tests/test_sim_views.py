"""Both imaging geometries of the pva-phantom, and the paper's two qualitative signs in each.

The paper (Results, on its experimental negative images -I/I0): "the least compressed phantom
image shows most brightness but the most compressed phantom image shows most contrast". It
does not state the beam direction. Through the plates every column thins as the plates close
(less attenuation: darker), and the inclusion's contrast grows as the background above and below
it is squeezed out of the beam; from the side the body widens along the beam, so every column
lengthens (brighter) and the background's growing attenuation shrinks the linear contrast. The
paper's signs are those of a beam through the plates.

Cheapest honest model: the cone is a body of revolution about the compression axis with its
inclusion on the axis, so the axisymmetric model (the 8 x 8 x 10 mm box as the cylinder of equal
section and height) at the demo's coarse sizes, noise-free, 0.3 mm pixels; both views project
the same solved states.
"""

import numpy as np
import pytest

from sim import study
from sim.mechanics import compress
from sim.scene import Beam, Scene, load_scene, with_view


@pytest.fixture(scope="module")
def pva_states():
    scene = load_scene("pva-phantom")
    scene.mesh.model, scene.mesh.size_inclusion_mm, scene.mesh.size_far_mm = "axisymmetric", 1.4, 8.0
    return scene, compress(scene)


def test_view_is_a_scene_option_that_round_trips():
    scene = load_scene("pva-phantom")
    assert scene.beam.view == "side"
    top = with_view(scene, "through_plates")
    assert top.beam.direction == "y" and top.beam.kind == "cone" and top.name == "pva-phantom-through-plates"
    assert Scene.from_toml(top.to_toml()) == top
    assert Beam(direction="side").direction == "z"
    assert (
        Scene.from_toml(scene.to_toml().replace('direction = "z"', 'direction = "through_plates"')).beam.direction
        == "y"
    )
    with pytest.raises(ValueError, match="through_plates"):
        with_view(scene, "above")
    with pytest.raises(ValueError, match="beam direction 'x'"):
        Beam(direction="x")


def test_through_the_plates_both_of_the_papers_signs_hold(pva_states):
    scene, states = pva_states
    signs = study.paper_signs(with_view(scene, "through_plates"), states, pixel_size_mm=0.3)
    assert signs.ratios == [0.15, 0.20, 0.25]
    assert np.all(np.diff(signs.brightness) < 0)  # each step darker than the one before
    assert np.all(np.diff(signs.contrast) > 0)  # and with more contrast
    assert signs.least_compressed_brightest and signs.most_compressed_most_contrast


def test_from_the_side_both_signs_are_reversed(pva_states):
    scene, states = pva_states
    signs = study.paper_signs(with_view(scene, "side"), states, pixel_size_mm=0.3)
    assert np.all(np.diff(signs.brightness) > 0)  # columns lengthen: the most compressed is brightest
    assert np.all(np.diff(signs.contrast) < 0)
    assert not signs.least_compressed_brightest and not signs.most_compressed_most_contrast


def test_through_the_plates_the_stiff_inclusion_gains_in_the_linear_domain_only(pva_states):
    """And the headline in each view: through the plates IF_linear > 1 under its bound, IF_log <
    1; from the side no bound, and the linear gain is lost."""
    scene, states = pva_states
    top = study.headline(study.image_pair(with_view(scene, "through_plates"), states, pixel_size_mm=0.3))
    assert 1.0 < top.improvement["negative"]["1"] <= top.bound["negative"]["1"] + 0.01
    assert top.improvement["log"]["1"] < 1.0
    side = study.headline(study.image_pair(with_view(scene, "side"), states, pixel_size_mm=0.3))
    assert side.bound["negative"]["1"] is None
    assert side.improvement["negative"]["1"] < 1.0
