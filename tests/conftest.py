"""Fixtures and paths shared by the test modules.

The vendor files live in ``../shared`` beside the repository (the only place they are promised);
tests that need them are marked ``needs_itex`` and skip with a message naming the missing folder.
"""

from pathlib import Path

import numpy as np
import pytest

from radiokit.io import ExperimentWriter, ImageKey

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
ITEX_DIR = SHARED / "data" / "hamamatsu_itex"

needs_itex = pytest.mark.skipif(
    not ITEX_DIR.is_dir(), reason=f"{ITEX_DIR}: the shared vendor files are not beside the checkout (../shared)"
)


def pytest_report_header(config):
    found = "found" if ITEX_DIR.is_dir() else "MISSING: tests that need them skip"
    return f"shared vendor files: {ITEX_DIR} ({found})"


def one_line_error(res, *needles):
    """Exit code 2, no traceback, one line on stderr naming every needle."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])
    return lines[0]


def synthetic(path, scale=1.0, shape=(160, 160), n_per_step=1, noise=0.0):
    """A slab thinned by compression with a denser square (pipeline's test experiment; noiseless, the
    background's standard deviation is exactly zero, so every CNR is infinite); with
    ``noise`` counts of Gaussian noise, so that outputs do not compress to nothing."""
    rng = np.random.default_rng(0)
    rows, cols = shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    sq = (abs(rr - 80) < 10) & (abs(cc - 80) < 10)
    with ExperimentWriter(path, shape=shape) as w:
        for _ in range(3):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
            L = scale * (0.08 * tb + 0.03 * ti * sq)
            for _ in range(n_per_step):
                counts = 100 + 3000 * np.exp(-L) + rng.normal(0, noise, shape)
                w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    return path
