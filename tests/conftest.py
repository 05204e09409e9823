"""Fixtures and paths shared by the test modules.

The vendor files live in ``../shared`` beside the repository (the only place they are promised);
tests that need them are marked ``needs_itex`` and skip with a message naming the missing folder.
"""

from pathlib import Path

import pytest

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
