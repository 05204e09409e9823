"""The improvement factor's bound: closed form, reached by a rigid inclusion, respected by the presets.

Through rigid plates every column in contact thins by the plate step dg, and a denser
inclusion's chord can only shrink, so IF_linear(k) <= 1 + k (1 - exp(-mu_b dg)) and IF_log <= 1
(radiokit.measure.improvement_bound, derivation in its Notes). A rigid inclusion's chord does not
shrink at all: it reaches the bound.
"""

import math

import numpy as np
import pytest

from radiokit.measure import improvement_bound
from sim import study
from sim.mechanics import compress
from sim.scene import Body, Compression, Inclusion, Material, MeshSpec, Scene, load_scene, with_view


@pytest.mark.parametrize(
    "k, mu, dg, expected",
    [
        (1, 0.05, 2.5, 1 + (1 - math.exp(-0.125))),  # seed-breast 20 -> 25 %: 1.1175
        (2, 0.05, 2.5, 1 + 2 * (1 - math.exp(-0.125))),  # 1.2350
        (1, 0.077, 3.0, 1 + (1 - math.exp(-0.231))),  # pva-phantom through the plates, 60 mm, 5 % step
        (0, 0.05, 2.5, 1.0),
        (3, 0.0, 2.5, 1.0),
    ],
)
def test_bound_closed_form(k, mu, dg, expected):
    assert improvement_bound(k, mu, dg, "negative") == pytest.approx(expected, rel=1e-12)
    # I/I0 and -I/I0 share the bound: the factor is a ratio of contrasts
    assert improvement_bound(k, mu, dg, "linear") == improvement_bound(k, mu, dg, "negative")
    assert improvement_bound(k, mu, dg, "log") == 1.0


def test_bound_is_linear_in_k_so_the_papers_pair_breaks_it():
    """IF(k) - 1 is proportional to k: the paper's 1.4 at k = 1 would give 1.8 at k = 2, not 2."""
    b1, b2 = (improvement_bound(k, 0.05, 2.5, "linear") for k in (1, 2))
    assert b2 - 1 == pytest.approx(2 * (b1 - 1), rel=1e-12)


@pytest.mark.parametrize(
    "args, match",
    [
        ((1, 0.05, 2.5, "counts"), "domain"),
        ((-1, 0.05, 2.5, "linear"), "k must"),
        ((1, float("nan"), 2.5, "linear"), "mu_b_per_mm"),
        ((1, 0.05, -2.5, "linear"), "delta_gap_mm"),
    ],
)
def test_bound_errors(args, match):
    with pytest.raises(ValueError, match=match):
        improvement_bound(*args)


def _rigid_cylinder(E_inclusion_kpa=5000.0):
    """The cheapest honest scene for the bound: a cylinder (flat faces held on frictionless
    plates, so every column in the footprint runs plate to plate) with an 8 mm sphere on its
    axis, axisymmetric (about a second to solve), 50 mm gap closing 20 -> 25 % (dg = 2.5 mm)."""
    gel = Material("gel", "neo-hookean", E_kpa=5.0, nu=0.495, attenuation_per_cm=0.5)
    hard = Material("rigid", "neo-hookean", E_kpa=E_inclusion_kpa, nu=0.495, attenuation_per_cm=1.0)
    return Scene(
        name="rigid-cylinder",
        body=Body("cylinder", height_mm=50.0, diameter_mm=50.0, material=gel),
        inclusions=[Inclusion("sphere", diameter_mm=8.0, material=hard)],
        compression=Compression((0.20, 0.25)),
        mesh=MeshSpec(1.0, 5.0, "auto", True),
    )


@pytest.fixture(scope="module")
def rigid_pair():
    scene = _rigid_cylinder()
    states = compress(scene)
    assert states[0].solver.model == "axisymmetric"
    # E_i = 1000 E_m: the inclusion's strain is below 1e-3 while the gel's is 25 %
    assert states[-1].inclusion_strain < 1e-3 < 0.2 < states[-1].background_strain
    return scene, states, study.image_pair(scene, states, pixel_size_mm=0.25)


def test_rigid_inclusion_reaches_the_bound(rigid_pair):
    """Truth-warped registration, no noise, 270 x 270 pixels of 0.25 mm, parallel beam."""
    scene, states, pair = rigid_pair
    assert pair.mu_dg == pytest.approx(0.05 * 2.5, rel=1e-9)
    h = study.headline(pair)
    for k in ("1", "2"):
        bound = 1 + float(k) * (1 - math.exp(-0.125))
        assert h.bound["negative"][k] == pytest.approx(bound, rel=1e-12)
        assert h.improvement["negative"][k] == pytest.approx(bound, rel=0.01)
        assert h.improvement["log"][k] == pytest.approx(1.0, abs=0.01)


def test_rigid_inclusion_with_the_identity_registration_is_exact(rigid_pair):
    """On the axis the rigid inclusion's shadow does not move and the background in contact is
    uniform, so the identity is an exact registration of the ROI means: the bound to 0.1 %."""
    pair = study.with_field(rigid_pair[2], np.zeros((2, 270, 270), np.float32))
    h = study.headline(pair)
    for k in ("1", "2"):
        assert h.improvement["negative"][k] == pytest.approx(h.bound["negative"][k], rel=1e-3)
        assert h.improvement["log"][k] == pytest.approx(1.0, abs=1e-3)


def test_rigid_inclusion_change_ratio_by_hand(rigid_pair):
    """The change ratio of a rigid inclusion through the plates, by hand. Every column of the
    footprint runs plate to plate; its gel thins by the plate step, the rigid sphere's chord
    ``c = 2 sqrt(r^2 - rho^2)`` stays. Log domain: both columns change by ``mu_b dg``, ratio 1.
    Negative domain (-I/I0): a column's change is ``exp(-mu_b g)`` times its inclusion factor
    ``exp(-dmu c)``, so the ratio is the inclusion ROI's mean of ``exp(-dmu c)`` (dmu = 0.05 /mm,
    r = 4 mm: 0.670 on the axis), attenuation alone. Identity registration (exact on the axis, as
    above); the ROI's pixel centres from the detector frame (sim.xray: centred on the body,
    row 0 on top). Tolerances: the sphere's residual strain (< 1e-3 of 8 mm) changes its chord
    between the steps by about 1e-3 mm, which the ratio's denominator ``1 - exp(-mu_b dg)`` =
    0.118 amplifies 8.5 times (4e-4 of the ratio), plus the faceting of the 1 mm mesh (sagitta
    4e-4 of the chord): 3e-3 relative; measured 1.0e-3 (negative), 4e-4 (log)."""
    pair = study.with_field(rigid_pair[2], np.zeros((2, 270, 270), np.float32))
    h = study.headline(pair)
    roi, (rows, cols), p = h.inclusion, pair.reference.shape, pair.pixel_size_mm
    r, c = np.mgrid[roi.row0 : roi.row1, roi.col0 : roi.col1]
    u, v = (c - (cols - 1) / 2) * p, ((rows - 1) / 2 - r) * p
    assert np.max(u * u + v * v) < 4.0**2  # the ROI lies inside the sphere's shadow
    chord = 2 * np.sqrt(4.0**2 - u * u - v * v)
    expected = float(np.mean(np.exp(-(0.10 - 0.05) * chord)))
    assert 0.6 < expected < 0.75
    assert h.change_ratio["negative"] == pytest.approx(expected, rel=3e-3)
    assert h.change_ratio["log"] == pytest.approx(1.0, abs=3e-3)


def test_softer_inclusion_stays_below_the_bound():
    """A stiff but deformable inclusion (6x the gel) loses part of its chord: strictly under.
    (Identity registration: on the axis, through the plates, the ROI means need none.)"""
    scene = _rigid_cylinder(E_inclusion_kpa=30.0)
    h = study.headline(study.images(study.project_pair(scene, compress(scene), pixel_size_mm=0.25, truth_factor=None)))
    for k in ("1", "2"):
        assert 1.0 < h.improvement["negative"][k] < h.bound["negative"][k] - 0.005
        assert h.improvement["log"][k] < 1.0


@pytest.mark.parametrize("name, model", [("seed-breast", "3d"), ("pva-phantom", "axisymmetric")])
def test_preset_scenes_stay_under_the_bound(name, model):
    """Each preset imaged through the plates, coarse mesh (the demo's 1.4 / 8 mm; the cone
    axisymmetric, its box inclusion the cylinder of equal section), truth-warped, no noise."""
    scene = with_view(load_scene(name), "through_plates")
    scene.mesh.size_inclusion_mm, scene.mesh.size_far_mm, scene.mesh.model = 1.4, 8.0, model
    scene.mesh.size_contact_mm = None  # coarse: without the preset's band at the plates
    states = compress(scene, (0.20, 0.25))
    h = study.headline(study.image_pair(scene, states, pixel_size_mm=0.3))
    for dom in ("log", "negative"):
        for k in ("1", "2"):
            assert h.improvement[dom][k] <= h.bound[dom][k] + 0.01, (dom, k, h.improvement, h.bound)
    assert h.improvement["negative"]["1"] > 1.0  # and it is a real gain in the paper's domain


def test_side_view_has_no_bound():
    scene = with_view(_rigid_cylinder(), "side")
    assert scene.beam.direction == "z" and scene.beam.view == "side"
    states = compress(scene)
    pair = study.images(study.project_pair(scene, states, pixel_size_mm=0.5, truth_factor=None))
    assert pair.mu_dg is None and pair.view == "side"
    assert study.headline(pair).bound["negative"]["1"] is None


@pytest.mark.parametrize("domain", ["log", "negative"])
def test_cnr_ratio_is_the_improvement_over_the_noise_growth(rigid_pair, domain):
    """CNR_enhanced / CNR_reference = IF * sigma_reference / sigma_enhanced, the sigmas predicted
    from the noise model, not measured: with independent Poisson noise in the two exposures and
    E = R + k (R - M - mean D), sigma_E^2 = (1 + k)^2 sigma_R^2 + k^2 sigma_M^2. (Identity
    registration, exact here, so no interpolation smooths the moving image's noise; a 60 x 60
    background ROI so the measured standard deviation is within ~1 %.)"""
    from radiokit.measure import ROI

    _, _, clean = rigid_pair
    counts = 2e5
    rng = np.random.default_rng(3)
    noisy = study.dataclasses.replace(
        clean,
        reference=study.add_noise(clean.reference, counts, rng),
        moving=study.add_noise(clean.moving, counts, rng),
    )
    noisy = study.with_field(noisy, np.zeros_like(clean.truth))
    inc = study.find_inclusion_roi(clean)
    bg = ROI(40, 100, 105, 165)  # 60 x 60 px, 9-24 mm from the axis: gel in contact with both plates
    h = study.headline(noisy, rois=(inc, bg))
    L_r, L_m = (float(im[bg.slices].mean()) for im in (clean.reference, clean.moving))
    # per-pixel noise of one exposure: log -ln(q/N): var = e^L / N; negative -q/N: var = e^-L / N
    var = (lambda L: math.exp(L) / counts) if domain == "log" else (lambda L: math.exp(-L) / counts)
    for k in ("1", "2"):
        kk = float(k)
        sigma_ratio = math.sqrt(var(L_r)) / math.sqrt((1 + kk) ** 2 * var(L_r) + kk**2 * var(L_m))
        expected = h.improvement[domain][k] * sigma_ratio
        assert h.cnr[domain][k] / h.cnr_reference[domain] == pytest.approx(expected, rel=0.05)
    # and the CNR falls although the contrast rises: at k = 1 by about IF / sqrt(5)
    assert h.cnr[domain]["1"] < h.cnr_reference[domain]


def test_pipeline_reports_the_bound_and_cnr_per_domain_and_k(tmp_path):
    """radiokit.pipeline on a lab-like file (no scene): a slab between plates closing 20 -> 18 ->
    16 mm with a denser square that thins less; mu_b comes from the reference's background over
    its gap (0.08 /mm), dg = 2 mm from the file's gaps, so the bound is 1 + k (1 - exp(-0.16)).
    The reported CNR ratio equals IF * sigma_ref / sigma_enh with the sigmas measured on the
    stored images."""
    from radiokit.io import ExperimentWriter, ImageKey
    from radiokit.pipeline import Config, process

    rng = np.random.default_rng(1)
    rr, cc = np.mgrid[0:160, 0:160]
    square = (abs(rr - 80) < 10) & (abs(cc - 80) < 10)

    def frame(gap, t_incl):
        L = 0.08 * gap + 0.03 * t_incl * square
        return np.clip(100 + 3000 * np.exp(-L) + rng.normal(0, 3, L.shape), 0, 4095).astype(np.uint16)

    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(160, 160), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full((160, 160), 100, np.uint16), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(np.full((160, 160), 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, (gap, ti) in enumerate([(20.0, 8.0), (18.0, 7.9), (16.0, 7.8)], start=1):
            w.append(frame(gap, ti), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step, gap_mm=gap)
    res = process(
        path,
        Config(
            crop_mm=None,
            report=False,
            progress=False,
            cross_check=None,
            method="ncc",
            inclusion=(75, 86, 75, 86),
            background=(75, 86, 40, 51),
        ),
        out_dir=tmp_path / "results",
    )
    r = res.results
    assert r["bound"]["mu_dg"] == pytest.approx(0.16, rel=0.02)
    for dom in ("log", "negative"):  # the pipeline's domains: -ln(I/I0), -I/I0
        m = r["domains"][dom]
        for k in ("1", "2"):
            expected = 1.0 if dom == "log" else 1 + float(k) * (1 - math.exp(-r["bound"]["mu_dg"]))
            assert m["bound"][k] == pytest.approx(expected, rel=1e-9)
            assert m["improvement_factor"][k] <= m["bound"][k] + 0.01
            bg = (slice(75, 86), slice(40, 51))
            s_ref = float(np.std(res.arrays["reference_by_domain"][dom][bg], dtype=np.float64))
            s_enh = float(np.std(res.arrays["enhanced"][dom][k][bg], dtype=np.float64))
            assert m["cnr"][k] / m["cnr_reference"] == pytest.approx(
                m["improvement_factor"][k] * s_ref / s_enh, rel=0.05
            )
