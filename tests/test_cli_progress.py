"""Progress bars of the long commands: on a terminal's stderr; none with -q or when stderr is not
a terminal (a pipe, a log file). The terminal is a real pseudo-terminal (pty), 100 columns wide."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios

import numpy as np
import pytest
import tifffile
from conftest import run_cli

from radiokit.io import ExperimentWriter, ImageKey
from sim.detector import PanelModel


def _run(args, stderr_tty: bool, columns: int = 100, env=None):
    """The command with stderr on a pseudo-terminal ``columns`` wide (or a pipe): (exit code,
    stdout, stderr)."""
    if not stderr_tty:
        # the bars are drawn only where sys.stderr.isatty(): a pipe's and run_cli's stderr both say
        # no, so this case needs no process of its own (the terminal cases below do: a pty)
        res = run_cli(*args, env=env)
        return res.returncode, res.stdout, res.stderr
    cmd = [sys.executable, "-m", "radiokit.cli", *map(str, args)]
    env = {**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})}
    master, slave = pty.openpty()
    # a new pty is 0 x 0 unless told otherwise, as some CI shells' terminals are
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave, text=True, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: the command closed its end
            break
        if not data:
            break
        chunks.append(data)
    out = proc.stdout.read()
    rc = proc.wait()
    os.close(master)
    return rc, out, b"".join(chunks).decode(errors="replace")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("progress")
    panel = PanelModel(rows=64, cols=80, defect_columns=(30,), n_dead=2, n_under=2, n_noisy=2)
    rng = np.random.default_rng(0)
    with ExperimentWriter(tmp / "exp.h5", shape=panel.shape) as w:
        for f in panel.dark_frames(4, rng):
            w.append(f, image_key=ImageKey.DARK)
        for f in panel.flat_frames(4, 2000, rng):
            w.append(f, image_key=ImageKey.FLAT)
    tifffile.imwrite(tmp / "darks.tif", np.asarray(panel.dark_frames(4, rng)), photometric="minisblack")
    tifffile.imwrite(tmp / "flats.tif", np.asarray(panel.flat_frames(4, 2000, rng)), photometric="minisblack")
    rr, cc = np.mgrid[0:64, 0:64]

    def blobs(d):  # a blob and a smaller one off its centre, moved by d px: its turn is observable
        return np.exp(-((rr - 32 - d) ** 2 + (cc - 30 - d) ** 2) / 200.0) + 0.5 * np.exp(
            -((rr - 22 - d) ** 2 + (cc - 44 - d) ** 2) / 30.0
        )

    # a lone round blob (tests/test_data_safety.py's pair) determines no turn about its centre, and
    # register flags it since session 49 (affine bound 0.51 px), exit 1: this test is about the bars
    tifffile.imwrite(tmp / "fixed.tif", blobs(0).astype(np.float32))
    tifffile.imwrite(tmp / "moving.tif", blobs(1).astype(np.float32))
    return tmp


CASES = {
    # command, what its bars say when done
    "calibrate-experiment": (
        ["calibrate", "--experiment", "exp.h5"],
        ["read exp.h5", "8/8", "calibrate defects", "100%"],
    ),
    "calibrate-files": (
        ["calibrate", "--dark", "darks.tif", "--flat", "flats.tif"],
        ["read darks", "read flats", "100%"],
    ),
    "register": (["register", "fixed.tif", "moving.tif", "--preset", "fast"], ["register rc", "1/1 scale"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("how", ["tty", "tty -q", "pipe"])
def test_long_commands_show_progress_on_a_terminal_only(case, how, files, tmp_path):
    args, words = CASES[case]
    out = tmp_path / "out.h5"
    args = [files / a if (files / a).exists() else a for a in args] + ["-o", out] + (["-q"] if "-q" in how else [])
    rc, stdout, stderr = _run(args, stderr_tty=how.startswith("tty"))
    assert rc == 0, (stdout, stderr)
    assert out.exists() and stdout.strip()  # the summary on stdout either way
    if how == "tty":
        for word in words:
            assert word in stderr, (word, stderr)
    else:
        assert stderr.strip() == "", stderr


@pytest.mark.parametrize("columns_env", [None, "0", "60"])
def test_a_terminal_of_no_columns_still_shows_the_bars(columns_env, files, tmp_path):
    """A terminal that reports 0 columns (a fresh pseudo-terminal, `stty cols 0` in some CI shells)
    showed no bar to speak of: tqdm squeezed each into one cell and cut its last character
    (`read exp.h5: 100%|█| 6/6 [00:00<00:00, 3734.91frame/s`). The bars fall back to COLUMNS
    when it is a positive width, else 80 columns."""
    args = ["calibrate", "--experiment", files / "exp.h5", "-o", tmp_path / "out.h5"]
    env = {} if columns_env is None else {"COLUMNS": columns_env}
    rc, stdout, stderr = _run(args, stderr_tty=True, columns=0, env=env)
    assert rc == 0, (stdout, stderr)
    assert "calibrate defects" in stderr and "100%" in stderr, stderr
    width = int(columns_env) if columns_env not in (None, "0") else 80
    drawn = [line for line in stderr.replace("\r", "\n").splitlines() if "100%" in line]
    assert drawn and all(len(line.rstrip()) <= width for line in drawn), drawn
    assert max(len(line.rstrip()) for line in drawn) >= width - 10, drawn  # the bar fills the width
