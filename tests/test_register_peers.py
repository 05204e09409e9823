"""Peers under radiokit's API: conventions (sign, axis order) on known motions, and clear refusal
when an optional peer is missing."""
import numpy as np
import pytest
from scipy import ndimage

from radiokit.register import register, warp


def _textured(n=160, seed=0):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.random((n, n)), 2.5).astype(np.float32) * 10


@pytest.mark.parametrize("method", ["tvl1", "ilk", "dis", "farneback"])
def test_peer_recovers_a_translation_in_the_pull_convention(method):
    """fixed(x) = moving(x + s) with s = (1.4 rows, -2.2 cols): every peer must return about s,
    which pins both the sign and the (row, col) order. Tolerance 0.3 px inside (flow methods
    on a smooth texture without intensity change)."""
    moving = _textured()
    s = np.array([1.4, -2.2], np.float32)
    fixed = warp(moving, np.broadcast_to(s[:, None, None], (2,) + moving.shape).copy(), order=3)
    reg = register(fixed, moving, method)
    inner = reg.displacement[:, 20:-20, 20:-20]
    med = np.median(inner.reshape(2, -1), axis=1)
    np.testing.assert_allclose(med, s, atol=0.3)


def test_missing_optional_peer_is_refused_clearly(monkeypatch):
    """find_spec is faked to report the package absent (a fake: uninstalling is not possible here)."""
    import importlib.util

    from radiokit.register._peers import MissingPeer

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "itk" else real(name, *a))
    f = _textured(32)
    with pytest.raises(MissingPeer, match="itk-elastix"):
        register(f, f, "elastix")


def test_highpass_prefilter_option_is_validated():
    f = _textured(32)
    with pytest.raises(ValueError, match="prefilter"):
        register(f, f, "farneback", prefilter="lowpass")


def test_regdata_pairs_satisfy_their_truth():
    """The benchmark's analytic pairs: warping moving by the truth gives fixed up to the planted
    intensity change and noise, far closer than without warping (so the scores mean something)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from regdata import analytic_pair, score

    for kind in ("thinning", "gain"):
        fixed, moving, truth, mask = analytic_pair(256, 0.02, 0.0, 0.0, seed=3, kind=kind)
        warped = warp(moving, truth, order=3)
        assert np.abs(warped - fixed)[mask].max() < 1e-4
        assert np.abs(moving - fixed)[mask].mean() > 100 * np.abs(warped - fixed)[mask].mean()
        assert score(truth, truth, mask)["epe_median"] == 0.0
    fixed, moving, truth, mask = analytic_pair(256, 0.01, 0.2, 0.0, seed=3, kind="thinning")
    ratio = fixed[mask] / np.maximum(warp(moving, truth, order=3)[mask], 1e-6)
    assert 0.75 < ratio.min() and ratio.max() < 1.25  # the 20 % intensity change, no more
