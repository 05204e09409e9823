"""Peers under radiokit's API (radiokit/register/_peers.py): each tool's flow convention turned
into radiokit's (row, col) pull field, checked on known motions; the highpass prefilter; a clear
refusal when an optional peer is missing; and the benchmark pairs (benchmarks/regdata.py)
satisfying their own truth.

Tolerances. On a 160 x 160 smooth random texture without intensity change or noise every peer
recovers a uniform (1.4, -2.2) px shift to within 0.02 px (median) and a smooth warp of up to
2 px to within 0.12 px median / 0.3 px p95 (measured; B-spline peers are limited by their
control-point spacing, the flows by their windows). The tests allow 0.1 px on the shift and
0.2 / 0.5 px on the warp: two to five times the measured error, and still ten times below what a
convention error costs (a sign error on the shift is 2.8 / 4.4 px, swapped axes 3.6 px). The
outer 20 pixels are left out (flows extrapolate there)."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

import radiokit.register._peers  # noqa: F401 - fills METHODS with the peers
from radiokit.errors import RadiokitError
from radiokit.register import METHODS, register, warp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from regdata import analytic_pair, score, sim_pair, smooth_field

# SimpleITK's and ITK's SWIG wrappers warn on import (Python 3.12+ style); not ours to fix
pytestmark = pytest.mark.filterwarnings("ignore:builtin type .* has no __module__ attribute:DeprecationWarning")

BUILT_IN = ["tvl1", "ilk", "dis", "farneback"]
OPTIONAL = {"sitk-bspline": "SimpleITK", "sitk-demons": "SimpleITK", "elastix": "itk"}
N = 160
SHIFT = np.array([1.4, -2.2], np.float32)  # (row, col): distinct magnitudes and signs


def _textured(n=N, seed=0):
    rng = np.random.default_rng(seed)
    return (ndimage.gaussian_filter(rng.random((n, n)), 2.5) * 10).astype(np.float32)


def _smooth_warp(n=N):
    """Row and col components of different shape, sign and size (so a swap or sign flip shows)."""
    y, x = np.mgrid[0:n, 0:n] / n
    return np.stack([1.5 * np.sin(2 * np.pi * x) + 0.5, -np.cos(np.pi * y) * np.sin(np.pi * x)]).astype(np.float32)


def _inner(a, b=20):
    return a[..., b:-b, b:-b]


def _check_peer(method, mask=None, smooth_warp=True, **options):
    moving = _textured()
    shift = np.broadcast_to(SHIFT[:, None, None], (2, N, N)).copy()
    # fixed(x) = moving(x + d(x)): the pull field radiokit returns is d itself
    reg = register(warp(moving, shift, order=3), moving, method, mask=mask, **options)
    assert reg.displacement.shape == (2, N, N) and reg.displacement.dtype == np.float32
    med = np.median(_inner(reg.displacement).reshape(2, -1), axis=1)
    np.testing.assert_allclose(med, SHIFT, atol=0.1, err_msg=f"{method}: shift (row, col)")
    if not smooth_warp:
        return

    d = _smooth_warp()
    reg = register(warp(moving, d, order=3), moving, method, **options)
    e = _inner(np.hypot(*(reg.displacement - d)))
    assert np.median(e) < 0.2 and np.percentile(e, 95) < 0.5, (method, np.median(e), np.percentile(e, 95))
    # and it registers: the warped moving image matches fixed better than moving does
    fixed = warp(moving, d, order=3)
    assert np.abs(_inner(reg.warp(moving) - fixed)).mean() < 0.2 * np.abs(_inner(moving - fixed)).mean()


@pytest.mark.parametrize("method", BUILT_IN)
def test_built_in_peer_recovers_a_shift_and_a_smooth_warp_in_the_pull_convention(method):
    _check_peer(method)


@pytest.mark.parametrize("method", sorted(OPTIONAL))
def test_optional_peer_recovers_a_shift_and_a_smooth_warp_in_the_pull_convention(method):
    pytest.importorskip(OPTIONAL[method])
    if method == "elastix":
        pytest.importorskip("itk").elastix_registration_method  # noqa: B018 (itk-elastix, not only itk)
    # elastix's 256 iterations per resolution left 0.004 px on these 160 px pairs and 64 leave
    # 0.004-0.016 px, still 10x inside the tolerances; the other elastix tests run its defaults
    options = {"iterations": 64} if method == "elastix" else {}
    _check_peer(method, **options)
    if method != "sitk-demons":  # the B-spline peers limit their metric to the mask
        y, x = np.mgrid[0:N, 0:N] - N / 2
        # the shift within the mask; the smooth warp is registered without it, the run just made
        _check_peer(method, mask=np.hypot(y, x) < 0.4 * N, smooth_warp=False, **options)


# the elastix tests next to the optional peers': ITK takes ~12 CPU s to load, once per worker


@pytest.mark.parametrize("roi", [np.s_[60:64, 20:140], np.s_[80, 20:140]])
def test_elastix_registers_within_a_mask_thinner_than_its_erosion(roi):
    """elastix erodes its fixed mask per resolution (``ErodeMask``, on by default): a ROI 4 px
    high or one row vanished, its sampler found "No valid voxels (0/1000)", and the user saw
    itk's RuntimeError ("Internal elastix error: See elastix log") as a traceback of `radiokit
    register --method elastix --roi ...`. Such a mask is registered again uneroded, and the
    shift inside it is found to within the peers' 0.1 px (module docstring)."""
    pytest.importorskip("itk").elastix_registration_method  # noqa: B018 (itk-elastix, not only itk)
    moving = _textured()
    shift = np.broadcast_to(SHIFT[:, None, None], (2, N, N)).copy()
    mask = np.zeros((N, N), bool)
    mask[roi] = True
    reg = register(warp(moving, shift, order=3), moving, "elastix", mask=mask)
    np.testing.assert_allclose(np.median(reg.displacement[:, mask], axis=1), SHIFT, atol=0.1)


@pytest.mark.parametrize("optimizer", ["RegularStepGradientDescent", "QuasiNewtonLBFGS"])
def test_elastix_registers_within_an_eroded_away_mask_with_any_optimizer(optimizer):
    """With another optimizer than elastix's default a mask its erosion empties fails in the
    sampler ("Could not find enough image samples ... the mask is too small"), not with "No valid
    voxels": it was not used again uneroded, and the user saw itk's "Internal elastix error". The
    shift inside the one-row mask is found to within the peers' 0.1 px."""
    pytest.importorskip("itk").elastix_registration_method  # noqa: B018 (itk-elastix, not only itk)
    moving = _textured()
    shift = np.broadcast_to(SHIFT[:, None, None], (2, N, N)).copy()
    mask = np.zeros((N, N), bool)
    mask[80, 20:140] = True
    fixed = warp(moving, shift, order=3)
    reg = register(fixed, moving, "elastix", mask=mask, parameters={"Optimizer": optimizer})
    np.testing.assert_allclose(np.median(reg.displacement[:, mask], axis=1), SHIFT, atol=0.1)


def test_an_elastix_failure_says_what_its_log_says_in_one_line():
    """A map that sets ``ErodeMask`` itself keeps its failure (the mask is not used again
    uneroded), but the user saw only "Internal elastix error: See elastix log", a log in a
    temporary directory already gone: the error carries the log's description, on one line."""
    pytest.importorskip("itk").elastix_registration_method  # noqa: B018 (itk-elastix, not only itk)
    moving = _textured()
    mask = np.zeros((N, N), bool)
    mask[80, 20:140] = True
    with pytest.raises(ValueError, match="No valid voxels") as err:
        register(moving, moving, "elastix", mask=mask, parameters={"ErodeMask": "true"})
    assert "\n" not in str(err.value).strip()


def test_elastix_on_an_image_and_itself_has_not_diverged():
    """test_register.py's sanity check (a textured body registered to itself, the same array
    twice) for elastix, kept here with the other tests that load ITK (13 CPU s in each worker that
    does): elastix leaves up to 0.3 px, which raises residual complexity from exactly 0 but stays
    below what the noise alone leaves a perfect registration, so it is not 'diverged'."""
    pytest.importorskip("itk").elastix_registration_method  # noqa: B018 (itk-elastix, not only itk)
    from regdata import Case, family_pair

    fixed, _, _, _ = family_pair(Case(size=256, texture=0.03, noise=0.01, corr=0.25, seed=3))
    reg = register(fixed, fixed.copy(), "elastix")
    assert 0 < np.abs(reg.displacement).max() < 0.5  # a sub-pixel field, not exactly 0
    assert reg.quality.ok and "diverged" not in reg.quality.reason, reg.quality.reason


@pytest.mark.parametrize("method", BUILT_IN)
def test_highpass_prefilter_removes_a_slow_intensity_change(method):
    """A slow additive change of 50 % of the texture's range (a stale flat on a line integral):
    every built-in peer is thrown off by it unprefiltered, prefilter="highpass" (sigma 1/20 of
    the image) recovers the shift to 0.15 px."""
    moving = _textured()
    shift = np.broadcast_to(SHIFT[:, None, None], (2, N, N)).copy()
    y, x = np.mgrid[0:N, 0:N] / N
    slow = (0.5 * np.ptp(moving) * np.sin(np.pi * x) * np.cos(0.5 * np.pi * y)).astype(np.float32)
    fixed = warp(moving, shift, order=3) + slow
    raw = np.abs(np.median(_inner(register(fixed, moving, method).displacement).reshape(2, -1), axis=1) - SHIFT)
    hp = np.median(_inner(register(fixed, moving, method, prefilter="highpass").displacement).reshape(2, -1), axis=1)
    np.testing.assert_allclose(hp, SHIFT, atol=0.15)
    assert raw.max() > np.abs(hp - SHIFT).max()


@pytest.mark.parametrize("method", BUILT_IN)
def test_working_size_brings_the_field_back_to_full_resolution(method):
    """working_size=80 registers the 160 px pair averaged by 2: the field comes back on the full
    grid, in full-resolution pixels (0.15 px: averaging halves the sampling)."""
    moving = _textured()
    shift = np.broadcast_to(SHIFT[:, None, None], (2, N, N)).copy()
    reg = register(warp(moving, shift, order=3), moving, method, working_size=80)
    assert reg.displacement.shape == (2, N, N)
    np.testing.assert_allclose(np.median(_inner(reg.displacement).reshape(2, -1), axis=1), SHIFT, atol=0.15)


def test_highpass_matches_a_direct_wide_gaussian():
    """The wide blur is computed on an averaged image: within 0.5 % of the signal of the direct one."""
    import cv2

    from radiokit.register._peers import highpass

    a = _textured(400) + np.linspace(0, 5, 400, dtype=np.float32)[None, :]
    for sigma in (3.0, 20.0, 60.0):
        direct = a - cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        assert np.abs(highpass(a, sigma) - direct).max() < 5e-3 * direct.std(), sigma


def test_peers_are_registered_and_document_their_options():
    for name in BUILT_IN + sorted(OPTIONAL):
        assert name in METHODS and METHODS[name].__doc__, name


def test_bad_options_are_refused():
    f = _textured(32)
    with pytest.raises(ValueError, match="prefilter"):
        register(f, f, "farneback", prefilter="lowpass")
    with pytest.raises(ValueError, match="preset"):
        register(f, f, "dis", preset="slow")
    with pytest.raises(TypeError):
        register(f, f, "tvl1", no_such_option=1)


@pytest.mark.parametrize("method", sorted(OPTIONAL))
def test_missing_optional_peer_is_refused_clearly(monkeypatch, method):
    """A fake: importlib.util.find_spec is monkeypatched to report the package absent (whether
    or not it is installed), which is what the peer checks before importing it."""
    real = importlib.util.find_spec
    absent = OPTIONAL[method]
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a, **k: None if name == absent else real(name, *a, **k)
    )
    f = _textured(32)
    with pytest.raises(RadiokitError) as info:
        register(f, f, method)
    package = {"SimpleITK": "SimpleITK", "itk": "itk-elastix"}[absent]
    assert str(info.value).startswith(f"method {method!r} needs {package}: pip install radiokit[register-peers]")
    assert isinstance(info.value, ImportError)  # also catchable as an ImportError


# -- the benchmark data -------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["thinning", "gain"])
def test_analytic_pair_satisfies_its_truth(kind):
    """Without intensity change and noise, warping moving by the truth reproduces fixed exactly
    (same cubic-spline interpolant); the largest |truth| is displacement_frac x size."""
    fixed, moving, truth, mask = analytic_pair(256, 0.02, 0.0, 0.0, seed=3, kind=kind)
    assert fixed.shape == moving.shape == mask.shape == (256, 256) and truth.shape == (2, 256, 256)
    assert fixed.dtype == moving.dtype == truth.dtype == np.float32 and mask.dtype == bool
    np.testing.assert_allclose(np.hypot(*truth).max(), 0.02 * 256, rtol=1e-5)
    warped = warp(moving, truth, order=3)
    assert np.abs(warped - fixed)[mask].max() < 1e-4
    assert np.abs(moving - fixed)[mask].mean() > 0.02  # the motion is visible
    assert score(truth, truth, mask)["epe_median"] == 0.0
    assert score(np.zeros_like(truth), truth, mask)["epe_median"] > 1.0


def test_analytic_pair_plants_the_intensity_change_and_noise_it_claims():
    ic, noise = 0.2, 0.01
    f0, m0, t0, mask = analytic_pair(256, 0.01, ic, 0.0, seed=4, kind="thinning")
    w = warp(m0, t0, order=3)
    ratio = f0[mask] / w[mask]
    assert 1 - ic - 1e-3 < ratio.min() and ratio.max() < 1 + ic + 1e-3 and np.ptp(ratio) > ic  # +- 20 %, used
    g0, gm, gt, _ = analytic_pair(256, 0.01, ic, 0.0, seed=4, kind="gain")
    diff = g0[mask] - warp(gm, gt, order=3)[mask]  # -ln(gain), gain in 1 +- ic
    assert -np.log1p(ic) - 1e-4 < diff.min() and diff.max() < -np.log1p(-ic) + 1e-4
    fn, mn, tn, _ = analytic_pair(256, 0.01, ic, noise, seed=4, kind="thinning")
    np.testing.assert_array_equal(tn, t0)  # same seed, same truth
    assert abs(np.std(fn - f0) - noise) < 0.1 * noise and abs(np.std(mn - m0) - noise) < 0.1 * noise


def test_analytic_pair_is_deterministic_and_validates():
    a = analytic_pair(64, seed=5)
    b = analytic_pair(64, seed=5)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="kind"):
        analytic_pair(64, kind="bleach")
    f = smooth_field((50, 70), np.random.default_rng(0))
    assert f.shape == (50, 70) and np.isclose(np.abs(f).max(), 1.0)


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    from sim.lab import simulate_experiment
    from sim.scene import block_scene

    scene = block_scene(size_mm=10, ratios=(0.1, 0.2))
    scene.detector.binning = 4
    path = tmp_path_factory.mktemp("regdata") / "block.h5"
    simulate_experiment(scene, path, n_darks=3, n_flats=3, progress=False)
    return path


def test_sim_pair_reads_the_stored_truth(sim_file):
    import h5py

    fixed, moving, truth, mask = sim_pair(sim_file)
    with h5py.File(sim_file, "r") as h5:
        g = h5["entry/simulation"]
        np.testing.assert_array_equal(fixed, g["line_integral"][1])
        np.testing.assert_array_equal(moving, g["line_integral"][0])
        np.testing.assert_array_equal(truth, g["displacement/step1_to_step2"][()])
    assert mask.any() and (fixed[mask] > 0.05 * fixed.max()).all()
    # the truth moves the block's edges onto fixed's (inside, a uniform block only thins)
    body = fixed > 0.05 * fixed.max()
    edge = ndimage.binary_dilation(body, iterations=3) & ~ndimage.binary_erosion(body, iterations=3)
    assert np.abs(warp(moving, truth, order=1) - fixed)[edge].mean() < 0.7 * np.abs(moving - fixed)[edge].mean()
    # smaller: block means, the field divided by the factor
    f2, m2, t2, k2 = sim_pair(sim_file, size=fixed.shape[0] // 2)
    assert f2.shape == (fixed.shape[0] // 2,) * 2 and k2.shape == f2.shape
    np.testing.assert_allclose(t2[:, 10, 10], truth[:, 20:22, 20:22].mean(axis=(1, 2)) / 2, atol=1e-6)
    # noisy: the raw frames corrected with the file's darks and flats
    fn, mn, tn, _ = sim_pair(sim_file, noisy=True)
    np.testing.assert_array_equal(tn, truth)
    assert 0 < np.std((fn - fixed)[mask]) < 0.2
    with pytest.raises(ValueError, match="steps"):
        sim_pair(sim_file, moving_step=2)


@pytest.mark.parametrize("motion", ["random", "physical"])
def test_family_pair_satisfies_its_truth_and_states_its_texture(motion):
    """The textureless-phantom family: without intensity change and noise, warping moving by the
    truth reproduces fixed (same cubic-spline interpolant); the amplitude is as stated; the
    texture's standard deviation is what the case says; train and test seeds never meet."""
    from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family, family_pair, gel_phantom

    c = Case(size=256, texture=0.02, noise=0.0, intensity=0.0, corr=0.25, amplitude=0.02, motion=motion, seed=5)
    fixed, moving, truth, mask = family_pair(c)
    assert fixed.dtype == moving.dtype == truth.dtype == np.float32 and mask.dtype == bool
    assert np.abs(warp(moving, truth, order=3) - fixed)[mask].max() < 1e-3
    if motion == "random":
        np.testing.assert_allclose(np.hypot(*truth).max(), 0.02 * 256, rtol=1e-4)
    else:  # expansion reaching the stated amplitude near the body's long-axis tip, a lag at the disc
        assert 0.5 * 0.02 * 256 < np.hypot(*truth)[mask].max() <= 1.05 * 0.02 * 256
    smooth, body, _ = gel_phantom(256, np.random.default_rng(1), 0.0)
    rich, _, _ = gel_phantom(256, np.random.default_rng(1), 0.05)
    inner = ndimage.binary_erosion(body, iterations=60)
    assert 0.02 < np.std((rich - smooth)[inner]) < 0.05  # the texture fades toward the edge with the chord
    assert not set(TRAIN_SEEDS) & set(TEST_SEEDS)
    assert {x.seed for x in family("test", 64)} <= set(TEST_SEEDS)
    _, m_int, _, _ = family_pair(Case(size=64, domain="intensity", seed=5))
    assert 0 < m_int.min() and m_int.max() <= 1.5  # transmission exp(-line integral), plus noise


# an 8 x 8 crop of a textured pair (a reflected border in the fixed image), on which SimpleITK's
# optimiser carries the field out of the frame: "No valid points were found" for each of 39
# metric evaluations, 234 lines of ITK warnings on the command line's stderr (session 53)
_OUT_OF_FRAME_FIXED = [
    [1368, 1892, 2204, 2204, 1892, 1368, 836, 520],
    [1503, 2006, 2318, 2318, 2006, 1503, 1011, 730],
    [1601, 2093, 2404, 2404, 2093, 1601, 1124, 838],
    [1654, 2076, 2339, 2339, 2076, 1654, 1230, 947],
    [1706, 1975, 2132, 2132, 1975, 1706, 1407, 1175],
    [1762, 1838, 1861, 1861, 1838, 1762, 1631, 1495],
    [1777, 1683, 1588, 1588, 1683, 1777, 1796, 1757],
    [1766, 1568, 1397, 1397, 1568, 1766, 1869, 1881],
]
_OUT_OF_FRAME_MOVING = [
    [2236, 1866, 1220, 525, 63, 0, 322, 901],
    [2187, 1848, 1264, 646, 251, 224, 531, 1038],
    [2204, 1892, 1368, 836, 520, 528, 800, 1197],
    [2318, 2006, 1503, 1011, 730, 736, 954, 1251],
    [2404, 2093, 1601, 1124, 838, 803, 952, 1179],
    [2339, 2076, 1654, 1230, 947, 862, 934, 1094],
    [2132, 1975, 1706, 1407, 1175, 1067, 1069, 1132],
    [1861, 1838, 1762, 1631, 1495, 1406, 1360, 1310],
]


def test_sitk_bspline_keeps_itk_warnings_off_stderr_and_the_checks_flag_it(capfd):
    """ITK's own warnings (C++, straight to the process's stderr) are not the user's one line: the
    result is judged by radiokit's checks, which flag this field (carried out of the frame), and
    SimpleITK's global warning display is left as it was found."""
    sitk = __import__("SimpleITK")
    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    fixed = np.array(_OUT_OF_FRAME_FIXED, np.uint16)
    moving = np.array(_OUT_OF_FRAME_MOVING, np.uint16)
    reg = register(fixed, moving, "sitk-bspline")
    err = capfd.readouterr().err
    assert "WARNING" not in err and "No valid points" not in err, err[:500]
    assert not reg.quality.ok and reg.quality.reason
    assert sitk.ProcessObject.GetGlobalWarningDisplay() == before


@pytest.mark.parametrize("parameters", ["Optimizer QuasiNewtonLBFGS", [("Optimizer", "QuasiNewtonLBFGS")], {1: "x"}])
def test_elastix_refuses_parameters_that_are_not_a_dict_of_names_before_loading_itk(parameters):
    """``parameters=`` not a dict of elastix parameter names was an AttributeError ("'str' object
    has no attribute 'items'") after loading all of itk (12-18 s): now a ValueError naming the
    option, before any work."""
    moving = _textured(32)
    with pytest.raises(ValueError, match=r"^elastix: parameters=.*expected a dict"):
        register(moving, moving[::-1].copy(), "elastix", parameters=parameters)


def test_itk_warnings_are_given_back_as_found_when_two_threads_overlap_or_one_raises():
    """Two registrations on two threads (SimpleITK releases the GIL): A turns the display off, B
    enters (finding it off), A leaves and turned it back on under B, B leaves and "restored" off,
    for good: the user's own SimpleITK warnings were silenced from then on. The order is forced
    with events on the real SimpleITK; an exception in the block gives it back too."""
    import threading

    import SimpleITK as sitk

    from radiokit.register._peers import _itk_warnings_off

    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(True)
    try:
        a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
        seen = {}

        def a():
            with _itk_warnings_off(sitk):
                a_in.set()
                b_in.wait(5)
            a_out.set()

        def b():
            a_in.wait(5)
            with _itk_warnings_off(sitk):
                b_in.set()
                a_out.wait(5)
                seen["b after a left"] = sitk.ProcessObject.GetGlobalWarningDisplay()

        threads = [threading.Thread(target=a), threading.Thread(target=b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10)
        assert seen["b after a left"] is False  # still inside B's block
        assert sitk.ProcessObject.GetGlobalWarningDisplay() is True
        with pytest.raises(RuntimeError, match="inside"), _itk_warnings_off(sitk):
            raise RuntimeError("inside")
        assert sitk.ProcessObject.GetGlobalWarningDisplay() is True
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(before)
