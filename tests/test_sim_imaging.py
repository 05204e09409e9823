"""Image models beyond the monochromatic line integral (sim.imaging)."""

import numpy as np
import pytest

from sim import imaging


@pytest.fixture(scope="module")
def poly60():
    return imaging.Polychromatic(60.0, "W", match_mm=50.0)


def test_polychromatic_matches_the_scene_at_its_thickness_and_hardens_with_depth(poly60):
    mu = [0.077, 0.085]
    t = np.array([10.0, 25.0, 50.0, 75.0])
    lengths = np.stack([t, np.zeros_like(t)])[:, None, :]  # (regions, 1, 4)
    L = poly60(lengths, mu)[0]
    assert L[2] == pytest.approx(0.077 * 50.0, rel=1e-9)  # the scene's coefficient where it was measured
    mu_eff = L / t
    assert np.all(np.diff(mu_eff) < 0)  # beam hardening: the effective coefficient falls with depth
    assert mu_eff[0] > 0.077 > mu_eff[-1]
    assert 15.0 < poly60.mean_energy_kev < 40.0  # a 60 kV tungsten spectrum through Be and air


def test_polychromatic_keeps_the_ratio_of_coefficients(poly60):
    """One water shape for every material: a ray through gel or through inclusion of the same
    monochromatic line integral has the same polychromatic one."""
    a = poly60(np.array([[[40.0]], [[0.0]]]), [0.077, 0.085])
    b = poly60(np.array([[[0.0]], [[40.0 * 0.077 / 0.085]]]), [0.077, 0.085])
    assert a == pytest.approx(b, rel=1e-12)


def test_scatter_and_blur():
    L = np.zeros((61, 61))
    L[5:56, 5:56] = 2.0
    s = imaging.scatter(L, 0.3, 1.0, 0.5, 2.0)
    assert np.all(s <= L + 1e-12)  # scatter only adds light
    assert s[0, 0] == pytest.approx(0.0, abs=1e-4)  # and air 2.5 sigma from the object almost none
    # deep inside a large uniform object the scatter-to-primary ratio is the fraction
    assert s[30, 30] == pytest.approx(2.0 - np.log(1.3), abs=1e-6)
    b = imaging.blur(L, 0.5, 0.5)
    assert b[30, 30] == pytest.approx(2.0, abs=1e-6) and 0 < b[30, 5] < 2.0  # edges soften, flat parts do not
    assert np.array_equal(imaging.blur(L, 0.0, 0.5), L)
    chained = imaging.chain(imaging.monochromatic, lambda x: x + 1.0)
    assert chained(np.ones((1, 2, 2)), [0.5])[0, 0] == pytest.approx(1.5)


def test_wide_gaussian_on_a_coarse_grid_matches_the_direct_filter():
    """Scatter's 10 mm Gaussian is 200 px on the full panel: filtered on a grid coarsened to
    sigma / 8 and interpolated back, it must match the direct filter (smooth on that scale)."""
    from scipy import ndimage

    y, x = np.mgrid[:400, :360]
    img = np.exp(-((x - 180.0) ** 2 + (y - 190.0) ** 2) / 90.0**2) * ((x - 180) ** 2 + (y - 190) ** 2 < 150**2)
    direct = ndimage.gaussian_filter(img, 40.0, mode="nearest")
    assert np.abs(imaging._gauss(img, 40.0) - direct).max() < 3e-3 * direct.max()


def test_scene_imaging_models():
    """``paper`` is the line integral itself; the presets' ``experiment`` model (tube spectrum
    and scatter) is not, and round-trips through TOML; a bad name is refused."""
    from sim.scene import Scene, load_scene, with_imaging

    scene = load_scene("seed-breast")
    assert scene.imaging.beam == "polychromatic" and scene.imaging.scatter_fraction == 0.3
    assert Scene.from_toml(scene.to_toml()).imaging == scene.imaging
    mu = np.array([0.05, 0.1])
    lengths = np.stack([np.full((8, 8), 50.0), np.zeros((8, 8))])
    lengths[1, 3:5, 3:5] = 8.0
    paper = imaging.for_scene(with_imaging(scene, "paper"), 0.3)(lengths, mu)
    assert np.array_equal(paper, np.tensordot(mu, lengths, axes=1))
    experiment = imaging.for_scene(scene, 0.3)(lengths, mu)
    assert not np.allclose(experiment, paper, rtol=1e-3)
    with pytest.raises(ValueError, match="imaging model 'mono'"):
        with_imaging(scene, "mono")


def test_tabulated_panel_transmission_matches_the_direct_sum(poly60):
    """A panel (over 65 536 pixels) is not summed over the spectrum pixel by pixel but looked up
    in a table of ``-ln T`` against the monochromatic line integral; the table is to err by less
    than 1e-6 of the value, from the thinnest ray (where ``-ln T`` bends most: its second
    derivative is minus the spectral variance of the coefficient, largest in the open beam) to
    300 mm of gel. Checked against the direct sum over the spectrum."""
    mu = [0.077, 0.085]
    t = np.linspace(0.0, 300.0, 300 * 300).reshape(300, 300)
    lengths = np.stack([t, np.zeros_like(t)])
    table = poly60(lengths, mu)
    direct = -np.log(poly60._transmission(mu[0] * t, poly60.scale_for(mu[0])))
    ray = t > 0
    assert np.max(np.abs(table[ray] / direct[ray] - 1)) < 1e-6


def test_polychromatic_thin_ray_sees_the_open_beam_mean_coefficient(poly60):
    """``-ln T(x) = -ln sum_E w_E exp(-c_E x)`` has slope ``sum_E w_E c_E`` at x = 0 (the
    energy-weighted mean coefficient of the open beam: ``scale`` times the material's, water's
    shape having unit mean) and second derivative ``-Var_w(c)``: so a thin ray's ``-ln T / x``
    is that mean to ``Var x / 2``, and every ray attenuates less than the mean predicts (Jensen:
    hardening has one sign)."""
    mu = 0.077
    scale = poly60.scale_for(mu)
    c = scale * poly60.shape * mu  # per mm, per energy bin
    mean, var = float(poly60.weights @ c), float(poly60.weights @ (c - poly60.weights @ c) ** 2)
    assert float(poly60.weights @ poly60.shape) == pytest.approx(1.0, rel=1e-12)
    t = 1e-6  # mm
    thin = float(poly60(np.array([[[t]], [[0.0]]]), [mu, 0.085])[0, 0]) / t
    assert thin == pytest.approx(mean, abs=var * t / 2 + 1e-9 * mean)
    assert mean == pytest.approx(scale * mu, rel=1e-12)
    depths = np.linspace(1.0, 100.0, 12)
    L = poly60(np.stack([depths, np.zeros_like(depths)])[:, None, :], [mu, 0.085])[0]
    assert np.all(L < mean * depths)


@pytest.mark.parametrize("view, thickness", [("side", 50.0), ("through_plates", 60.0)])
def test_the_experiment_model_is_referred_to_the_thickness_the_view_crosses(view, thickness):
    """``pva-phantom`` (a truncated cone 60 mm high, 40 -> 50 mm across): from the side the
    longest ray crosses the 50 mm top face, through the plates the 60 mm gap. A uniform slab of
    background that thick, wider than scatter's Gaussian, must come out of the ``experiment``
    model as the scene's ``mu t`` (the beam matched there: the coefficient is the one measured
    through the body as the view sees it) plus the scatter of the stated SPR, ``-ln(1 + SPR)``
    exactly (a uniform field is a fixed point of the Gaussian). Matched through the 60 mm height
    in both views, the side view's 50 mm came out 0.151 (3.9 %) above ``mu t`` (the beam
    hardened for 10 mm more than any ray crosses) and its scatter-to-primary ratio was 0.26, not
    0.3: 0.18 in all."""
    from sim.mesh import build_mesh
    from sim.scene import load_scene, with_view
    from sim.xray import Geometry, path_lengths

    scene = with_view(load_scene("pva-phantom"), view)
    assert imaging.match_thickness_mm(scene) == thickness
    if view == "side":  # no ray of the meshed body (inscribed, cone beam) is longer, and one is as long
        scene.detector.binning = 4
        longest = path_lengths(build_mesh(scene), Geometry.from_scene(scene)).sum(axis=0).max()
        assert thickness * 0.99 < longest <= thickness * (1 + 1e-9)
    mu = np.array([scene.body.material.attenuation_per_mm] + [i.material.attenuation_per_mm for i in scene.inclusions])
    lengths = np.zeros((len(mu), 64, 64))
    lengths[0] = thickness
    out = imaging.for_scene(scene, pixel_size_mm=1.0)(lengths, mu)
    spr = scene.imaging.scatter_fraction
    assert spr > 0 and scene.imaging.beam == "polychromatic"
    np.testing.assert_allclose(out, mu[0] * thickness - np.log(1 + spr), rtol=0, atol=1e-9)
