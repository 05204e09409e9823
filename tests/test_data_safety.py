"""Nothing radiokit did not make is overwritten or deleted; outputs are complete or absent.

Every case runs the real ``radiokit`` command on real files, then checks that the inputs' SHA-256
are unchanged and that each output is either the previous complete one, a new complete one, or
absent (no temporary file left beside it either, except after a kill -9). The command runs in a
subprocess where the case needs one (a kill or a signal, a resource limit, Dask's workers, the
terminal's encoding, a faked ``shutil.disk_usage``), else its ``main`` in this process
(``conftest.run_cli``).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from conftest import mounted_tmpfs, one_line_error, read_only, run_cli, synthetic, writable_copy

from radiokit.io import RESULTS_MARKER, ExperimentWriter, ImageKey, atomic_path, read, recover_interrupted

ROOT = Path(__file__).resolve().parents[1]
ROI = ["--inclusion", "75", "86", "75", "86", "--background", "75", "86", "40", "51", "--crop-mm", "0"]
#: for runs checked on where and how process writes its folder, not on what it measured: no cross-check
#: (the registration again by another method: ~0.2 of a run's ~1.5 CPU s, median of 9; session 45)
NO_CROSS_CHECK = ["--cross-check", "none"]


def run(*args, cwd=None, env=None):
    return subprocess.run(
        [sys.executable, "-m", "radiokit.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})},
    )


def sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def tree_sha(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): sha(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def no_temporaries(folder: Path):
    left = [p.name for p in Path(folder).iterdir() if ".tmp-" in p.name or ".old-" in p.name]
    assert not left, left


@pytest.fixture
def experiment(tmp_path):
    return synthetic(tmp_path / "exp.h5")


@pytest.fixture
def images(tmp_path):
    rr, cc = np.mgrid[0:64, 0:64]
    fixed, moving = tmp_path / "fixed.tif", tmp_path / "moving.tif"
    tifffile.imwrite(fixed, np.exp(-((rr - 32) ** 2 + (cc - 30) ** 2) / 200.0).astype(np.float32))
    tifffile.imwrite(moving, np.exp(-((rr - 33) ** 2 + (cc - 31) ** 2) / 200.0).astype(np.float32))
    return fixed, moving


def _commands(exp, images, out):
    """Each output-writing subcommand, writing ``out`` (whose suffix it gets)."""
    fixed, moving = images
    return {
        "calibrate": ["calibrate", "--experiment", exp, "-o", out.with_suffix(".h5")],
        "correct": ["correct", exp, "-q", "-o", out.with_suffix(".h5")],
        "correct-tiff": ["correct", exp, "-q", "-o", out.with_suffix(".tif")],
        "register": ["register", fixed, moving, "-o", out.with_suffix(".h5")],
        "register-png": [
            "register",
            fixed,
            moving,
            "-o",
            out.parent / "reg-field.h5",
            "--png",
            out.with_suffix(".png"),
        ],
    }


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png"])
def test_an_existing_output_needs_overwrite(cmd, experiment, images, tmp_path):
    args = _commands(experiment, images, tmp_path / "out")[cmd]
    out = Path(args[-1])
    out.write_bytes(b"a file the user cares about")
    before = {p: sha(p) for p in (experiment, *images)}
    res = run_cli(*args)
    one_line_error(res, out.name, "exists", "--overwrite")
    assert out.read_bytes() == b"a file the user cares about"
    res = run_cli(*args, "--overwrite")
    assert res.returncode in (0, 1), res.stderr  # register exits 1 for an untrustworthy field
    assert out.read_bytes() != b"a file the user cares about"
    if out.suffix == ".png":
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    elif out.suffix == ".tif":
        assert read(out).n == 3  # the three projections
    elif cmd == "correct":
        assert read(out, dataset="entry/data/data").n == 3
    else:
        assert h5py.is_hdf5(out)
    assert {p: sha(p) for p in before} == before
    no_temporaries(tmp_path)


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_register_stopped_while_drawing_its_figure_keeps_the_previous_field(stop, images, tmp_path, monkeypatch):
    """`register -o reg.h5 --png reg.png --overwrite` stopped while matplotlib drew the figure
    (Ctrl-C, or the figure's folder refusing it): reg.h5 had already been replaced by the new
    field beside the old figure, and the command said "interrupted; no partial output was left".
    The figure is drawn before the field is renamed into place: both stay the previous run's."""
    from radiokit import cli

    fixed, moving = images
    field, figure = tmp_path / "reg.h5", tmp_path / "reg.png"
    args = ["register", fixed, moving, "-o", field, "--png", figure, "--overwrite"]
    assert run_cli(*args).returncode in (0, 1)
    before = {p: sha(p) for p in (field, figure)}

    def draw_then_stop(path, *rest):
        Path(path).write_bytes(b"half a figure")
        raise stop(errno.EIO, "stopped while drawing") if stop is OSError else stop()

    monkeypatch.setattr(cli, "_register_png", draw_then_stop)
    res = run_cli(*args)
    assert res.returncode == (130 if stop is KeyboardInterrupt else 2), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr, res.stderr
    assert {p: sha(p) for p in before} == before  # was: reg.h5 the new field, reg.png the old figure
    no_temporaries(tmp_path)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_register_stopped_between_its_two_renames_leaves_a_pair(sig, images, tmp_path, monkeypatch):
    """A stop landing after reg.h5 was renamed into place and before reg.png was (the field's
    folder fsync, the figure's own rename): the figure's temporary was removed, reg.h5 was the new
    field beside the previous run's figure, and the command said "no partial output was left".
    The two renames are one step a stop cannot cut: both files are the new run's (review s47rv3)."""
    fixed, moving = images
    field, figure = tmp_path / "reg.h5", tmp_path / "reg.png"
    args = ["register", fixed, moving, "-o", field, "--png", figure, "--overwrite"]
    assert run_cli(*args).returncode in (0, 1)
    before = {p: p.stat().st_ino for p in (field, figure)}  # (one pair draws one figure, byte for byte)
    real_replace = os.replace

    def replace_then_stop(src, dst, *rest, **kw):
        real_replace(src, dst, *rest, **kw)
        if Path(dst) == field:
            signal.raise_signal(sig)  # as a Ctrl-C (or kill) right after the field's rename

    monkeypatch.setattr(os, "replace", replace_then_stop)
    res = run_cli(*args)
    changed = {p for p in before if p.stat().st_ino != before[p]}
    assert changed in (set(), {field, figure}), (changed, res.stderr)  # was: {reg.h5} alone
    assert res.returncode == 128 + sig, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr, res.stderr
    if changed:  # the line says what is there, not "no partial output was left"
        assert "no partial output" not in res.stderr and str(figure) in res.stderr, res.stderr
    no_temporaries(tmp_path)


def test_register_killed_between_its_two_renames_never_leaves_the_previous_figure(images, tmp_path, monkeypatch):
    """A kill -9 (no handler runs) landing after reg.h5 was renamed into place and before reg.png
    was left the new field beside the previous run's figure, two runs' outputs side by side
    (session 48's leftover). The previous figure goes before the field is renamed: a kill at any
    point leaves the previous pair, the previous field without a figure, the new field without
    one, or the new pair. The state at the kill's moment is seen as the field's rename ends."""
    fixed, moving = images
    field, figure = tmp_path / "reg.h5", tmp_path / "reg.png"
    args = ["register", fixed, moving, "-o", field, "--png", figure, "--overwrite"]
    assert run_cli(*args).returncode in (0, 1)
    figure.chmod(0o640)  # a mode its owner chose, which the new figure keeps
    before = {p: p.stat().st_ino for p in (field, figure)}
    seen, real_replace = [], os.replace

    def replace_and_look(src, dst, *rest, **kw):
        real_replace(src, dst, *rest, **kw)
        if Path(dst) == field:  # what a kill -9 here would leave
            seen.append(figure.stat().st_ino if figure.exists() else None)

    monkeypatch.setattr(os, "replace", replace_and_look)
    assert run_cli(*args).returncode in (0, 1)
    assert seen == [None], (seen, before[figure])  # was: the previous figure's inode
    assert all(p.stat().st_ino != before[p] for p in before)
    assert stat.S_IMODE(figure.stat().st_mode) == 0o640
    no_temporaries(tmp_path)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png"])
def test_a_read_only_output_is_refused_even_with_overwrite(cmd, experiment, images, tmp_path):
    """A file its owner made read-only (chmod a-w) was replaced by --overwrite, as a writable
    file with mode 0644: radiokit renames its new output into place, which the file's own mode
    does not stop, where writing into it would have failed."""
    args = _commands(experiment, images, tmp_path / "out")[cmd]
    out = Path(args[-1])
    out.write_bytes(b"a result the user protected")
    out.chmod(0o444)
    for extra in ([], ["--overwrite"]):
        one_line_error(run_cli(*args, *extra), out.name, "read-only", "chmod u+w")
    assert out.read_bytes() == b"a result the user protected"
    assert stat.S_IMODE(out.stat().st_mode) == 0o444
    no_temporaries(tmp_path)


def test_a_read_only_results_folder_is_refused_even_with_overwrite(experiment, tmp_path):
    out = tmp_path / "res"
    args = ["process", experiment, "-o", out, "-q", "--no-report", *ROI, *NO_CROSS_CHECK]
    assert run_cli(*args).returncode in (0, 1)
    before = tree_sha(out)
    out.chmod(0o555)
    try:
        one_line_error(run_cli(*args, "--overwrite"), str(out), "read-only", "chmod u+w")
        assert tree_sha(out) == before
    finally:
        out.chmod(0o755)
    no_temporaries(tmp_path)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png", "process"])
def test_an_output_replaced_with_overwrite_keeps_its_mode(cmd, experiment, images, tmp_path):
    """A replaced output keeps the permissions its owner gave it (0640: not for other users; a
    folder 0750), as writing into it would; it got the umask's 0644 (0755)."""
    commands = {
        **_commands(experiment, images, tmp_path / "out"),
        "process": ["process", experiment, "-q", *ROI, *NO_CROSS_CHECK],
    }
    args = commands[cmd] + (["-o", tmp_path / "res", "--no-report"] if cmd == "process" else [])
    out = tmp_path / "res" if cmd == "process" else Path(args[-1])
    old = os.umask(0o022)
    try:
        assert run_cli(*args).returncode in (0, 1)
        mode = 0o750 if cmd == "process" else 0o640
        out.chmod(mode)
        assert run_cli(*args, "--overwrite").returncode in (0, 1)
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == mode


def test_an_overwrite_is_kept_where_the_filesystem_refuses_chmod(tmp_path, monkeypatch):
    """Found in review: keeping a replaced output's mode was not best-effort as keeping its owner
    is, so on a filesystem whose chmod fails with EPERM (vfat, some FUSE and SMB mounts) a
    finished --overwrite output was thrown away. A fake chmod stands for such a mount: as root on
    this filesystem, chmod cannot be made to fail."""
    out = tmp_path / "out.txt"
    out.write_text("old")

    def refuse(path, *args, **kwargs):
        raise PermissionError(errno.EPERM, "Operation not permitted", str(path))

    monkeypatch.setattr(os, "chmod", refuse)
    with atomic_path(out, overwrite=True) as tmp:
        tmp.write_text("new")
    monkeypatch.undo()
    assert out.read_text() == "new"
    no_temporaries(tmp_path)


@pytest.mark.parametrize("umask", [0o077, 0o002])
@pytest.mark.parametrize("cmd", ["correct", "correct-tiff", "register-png", "process"])
def test_a_new_output_gets_the_mode_the_umask_gives(cmd, umask, experiment, images, tmp_path):
    """Written under a temporary name and renamed: the new file (folder) has the mode a plain
    write (mkdir) gives, 0666 (0777) less the umask, not a temporary file's 0600."""
    commands = {
        **_commands(experiment, images, tmp_path / "out"),
        "process": ["process", experiment, "-q", *ROI, *NO_CROSS_CHECK],
    }
    args = commands[cmd] + (["-o", tmp_path / "res", "--no-report"] if cmd == "process" else [])
    out = tmp_path / "res" if cmd == "process" else Path(args[-1])
    old = os.umask(umask)
    try:
        assert run_cli(*args).returncode in (0, 1)
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == (0o777 if cmd == "process" else 0o666) & ~umask


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink"])
@pytest.mark.parametrize("cmd", ["calibrate", "correct", "register"])
def test_an_output_that_is_an_input_is_refused_even_with_overwrite(cmd, how, experiment, images, tmp_path):
    fixed, moving = images
    target = fixed if cmd == "register" else experiment
    if how == "same":
        out = target
    elif how == "symlink":
        out = tmp_path / f"link{target.suffix}"
        out.symlink_to(target)
    else:
        out = tmp_path / "sub" / f"hard{target.suffix}"
        out.parent.mkdir()
        os.link(target, out)
    args = {
        "calibrate": ["calibrate", "--experiment", experiment],
        "correct": ["correct", experiment, "-q"],
        "register": ["register", fixed, moving],
    }[cmd]
    before = {p: sha(p) for p in (experiment, fixed, moving)}
    res = run_cli(*args, "-o", out, "--overwrite")
    one_line_error(res, out.name, "input", target.name)
    assert {p: sha(p) for p in before} == before


def _output_is(out: Path, cmd: str) -> None:
    """``out`` holds a complete output of ``cmd``."""
    if out.suffix == ".png":
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    elif out.suffix == ".tif":
        assert read(out).n == 3  # the three projections
    else:
        assert h5py.is_hdf5(out)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png"])
def test_an_output_that_is_a_symlink_is_written_to_its_target(cmd, experiment, images, tmp_path):
    """``-o link`` pointing at a file on another folder (a results disk): the output was renamed
    over the link itself, which became a regular file, and the file it points at, the one the
    user meant, was left stale. The target is written now, atomically in its own folder, the
    --overwrite rule applied to it; the link stays the link it was."""
    store = tmp_path / "store"
    store.mkdir()
    args = _commands(experiment, images, tmp_path / "out")[cmd]
    out = Path(args[-1])
    target = store / f"kept{out.suffix}"
    target.write_bytes(b"last week's output")
    out.symlink_to(os.path.relpath(target, out.parent))
    link = os.readlink(out)
    one_line_error(run_cli(*args), out.name, target.name, "exists", "--overwrite")
    assert target.read_bytes() == b"last week's output"
    assert run_cli(*args, "--overwrite").returncode in (0, 1), cmd  # register exits 1 for an untrustworthy field
    assert out.is_symlink() and os.readlink(out) == link
    _output_is(target, cmd)
    no_temporaries(tmp_path)
    no_temporaries(store)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png"])
def test_an_output_that_is_a_dangling_symlink_writes_its_target(cmd, experiment, images, tmp_path):
    """A link to a file not yet written (a placeholder into a results disk): the target is
    written, as the shell's ``>`` writes it, without --overwrite (nothing is replaced); a link
    into a folder that does not exist is refused in one line naming both."""
    store = tmp_path / "store"
    store.mkdir()
    args = _commands(experiment, images, tmp_path / "out")[cmd]
    out = Path(args[-1])
    out.symlink_to(store / f"new{out.suffix}")
    assert run_cli(*args).returncode in (0, 1), cmd
    assert out.is_symlink()
    _output_is(store / f"new{out.suffix}", cmd)
    no_temporaries(tmp_path)
    out.unlink()
    out.symlink_to(tmp_path / "nowhere" / f"new{out.suffix}")
    one_line_error(run_cli(*args, "--overwrite"), out.name, "nowhere", "does not exist")
    assert not (tmp_path / "nowhere").exists() and out.is_symlink()


def test_a_results_folder_that_is_a_symlink_is_replaced_at_its_target(experiment, tmp_path):
    """``process -o res`` where ``res`` links to a results folder radiokit made elsewhere: it was
    refused as "not a folder radiokit made"; the target folder is replaced now (with
    --overwrite, as any results folder), the link kept; a dangling link makes its target."""
    store = tmp_path / "store"
    store.mkdir()
    args = ["process", experiment, "--no-report", "--cross-check", "none", "-q", *ROI]  # no work the links need
    assert run_cli(*args, "-o", store / "res").returncode == 0
    before = os.stat(store / "res").st_ino
    out = tmp_path / "res"
    out.symlink_to(store / "res")
    one_line_error(run_cli(*args, "-o", out), "res", "--overwrite")
    assert os.stat(store / "res").st_ino == before
    assert run_cli(*args, "-o", out, "--overwrite").returncode == 0
    assert out.is_symlink() and os.stat(store / "res").st_ino != before
    assert set(tree_sha(store / "res")) == {RESULTS_MARKER, "results.h5", "results.json"}
    fresh = tmp_path / "fresh"
    fresh.symlink_to(store / "fresh")
    assert run_cli(*args, "-o", fresh).returncode == 0
    assert fresh.is_symlink() and (store / "fresh" / "results.h5").is_file()
    no_temporaries(tmp_path)
    no_temporaries(store)


def test_an_output_that_is_a_symlink_loop_is_one_line(experiment, tmp_path):
    out, other = tmp_path / "cal.h5", tmp_path / "other.h5"
    out.symlink_to(other)
    other.symlink_to(out)
    for extra in ([], ["--overwrite"]):
        one_line_error(run_cli("calibrate", "--experiment", experiment, "-o", out, *extra), "cal.h5", "loop")
    assert out.is_symlink() and other.is_symlink()


def test_a_symlink_to_a_name_of_the_same_format_is_written_another_format_refused(experiment, tmp_path):
    """The writer goes by the name given: ``cal.h5`` linked to ``cal.hdf5`` writes HDF5 either way
    (review s34-r1: it was refused for the suffix's spelling); linked to a .tif, the file would be
    HDF5 under a TIFF's name, refused in one line naming both."""
    out = tmp_path / "cal.h5"
    out.symlink_to(tmp_path / "cal.hdf5")
    assert run_cli("calibrate", "--experiment", experiment, "-o", out).returncode == 0
    assert out.is_symlink() and h5py.is_hdf5(tmp_path / "cal.hdf5")
    tif = tmp_path / "cal2.h5"
    tif.symlink_to(tmp_path / "cal2.tif")
    one_line_error(run_cli("calibrate", "--experiment", experiment, "-o", tif), "cal2.h5", "cal2.tif", "suffix")
    assert not (tmp_path / "cal2.tif").exists()


def test_correct_refuses_to_write_over_its_calibration(experiment, tmp_path):
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", experiment, "-o", cal).returncode == 0
    before = sha(cal)
    one_line_error(run_cli("correct", experiment, "--cal", cal, "-o", cal, "--overwrite", "-q"), "cal.h5", "input")
    assert sha(cal) == before


def test_process_gives_inputs_with_the_same_name_and_a_file_named_dot_dot_h5_distinct_folders_in_the_root(tmp_path):
    """Two inputs of one name each get a folder, and ``..h5`` (stem ".") one of its own inside -o,
    not -o itself. One Dask run for both (two tests ran one each: a subprocess and its cluster,
    7-15 s apiece; session 42); the ``..h5`` first, as it was in its own test."""
    # the folders are named from the inputs' names alone: four small experiments (100 x 100 holds
    # the ROI and the square), processed without the report and the cross-check (~3 CPU s of ~10)
    small = (100, 100)
    a, b = tmp_path / "a" / "run.h5", tmp_path / "b" / "run.h5"
    for p, scale in ((a, 1.0), (b, 1.3)):
        p.parent.mkdir()
        synthetic(p, scale, shape=small)
    dots, other = synthetic(tmp_path / "..h5", shape=small), synthetic(tmp_path / "exp2.h5", scale=1.2, shape=small)
    before = {p: sha(p) for p in (a, b)}
    fast = ["--no-report", "--cross-check", "none", "-q", *ROI]
    res = run("process", dots, other, a, b, "-o", tmp_path / "R", "--workers", "1", *fast)
    assert res.returncode == 0, res.stderr
    sources = {d.name: json.loads((d / "results.json").read_text())["source"] for d in (tmp_path / "R").iterdir()}
    assert sorted(sources.values()) == sorted([str(dots), str(other), str(a), str(b)]) and "exp2" in sources
    assert {k: v for k, v in sources.items() if v in (str(a), str(b))} == {"run": str(a), "run-2": str(b)}
    assert not (tmp_path / "R" / "results.json").exists()
    assert {p: sha(p) for p in before} == before


def test_a_file_whose_stem_is_dots_gets_a_folder_of_its_own_inside_the_output_root(tmp_path):
    """``Path("..h5").stem`` is ".", ``Path("...h5").stem`` is "..": their folders were -o itself
    (the other files' folders nested inside it) and -o's parent."""
    from radiokit.pipeline import output_folders

    root = tmp_path / "R"
    names = ["..h5", "...h5", "x/..h5", "y/..h5", "exp.h5"]
    outs = output_folders([tmp_path / n for n in names], root)
    assert all(o.parent == root and o.name not in ("", ".", "..") for o in outs), outs
    assert len({o.name for o in outs}) == len(outs)
    # beside the file (no -o): a folder of the file's folder, never that folder or its parent
    for n in names:
        (out,) = output_folders([tmp_path / n])
        assert out.parent == (tmp_path / n).parent and out.name not in ("", ".", "..") and out != tmp_path / n


def test_process_never_writes_over_its_input_named_results_h5(tmp_path):
    folder = tmp_path / "data"
    folder.mkdir()
    exp = synthetic(folder / "results.h5")
    before = sha(exp)
    # into its own folder: that folder holds the input, refused even with --overwrite
    one_line_error(run_cli("process", exp, "-o", folder, "--overwrite", "--no-report", "-q", *ROI), "data", "input")
    assert sha(exp) == before and sorted(p.name for p in folder.iterdir()) == ["results.h5"]
    # the default, a folder beside it named after it, leaves it alone
    res = run_cli("process", exp, "--no-report", "-q", *ROI, *NO_CROSS_CHECK)
    assert res.returncode == 0, res.stderr
    assert sha(exp) == before and (folder / "results" / "results.h5").is_file()


def test_process_replaces_only_its_own_results_folder(experiment, tmp_path):
    out = tmp_path / "res"
    assert run_cli("process", experiment, "-o", out, "--no-report", "-q", *ROI, *NO_CROSS_CHECK).returncode == 0
    first = tree_sha(out)
    assert set(first) == {RESULTS_MARKER, "results.h5", "results.json"}
    one_line_error(run_cli("process", experiment, "-o", out, "--no-report", "-q", *ROI), "res", "--overwrite")
    assert tree_sha(out) == first
    args = ["process", experiment, "-o", out, "--no-report", "-q", "--overwrite", *ROI, *NO_CROSS_CHECK]
    assert run_cli(*args).returncode == 0
    assert set(tree_sha(out)) == set(first)
    # a file radiokit did not write there: never deleted, so the folder is not replaced
    (out / "notes.txt").write_text("mine")
    one_line_error(
        run_cli("process", experiment, "-o", out, "--no-report", "-q", "--overwrite", *ROI), "res", "notes.txt"
    )
    assert (out / "notes.txt").read_text() == "mine"
    # a folder radiokit did not make: refused even with --overwrite
    other = tmp_path / "theirs"
    other.mkdir()
    (other / "data.csv").write_text("1,2,3")
    one_line_error(run_cli("process", experiment, "-o", other, "--no-report", "-q", "--overwrite", *ROI), "theirs")
    assert (other / "data.csv").read_text() == "1,2,3"
    no_temporaries(tmp_path)


def test_demo_refuses_a_folder_it_did_not_make(tmp_path):
    (tmp_path / "experiment.h5").write_bytes(b"the user's own experiment")
    for extra in ([], ["--overwrite"]):
        res = run_cli("demo", "-o", ".", "-q", *extra, cwd=tmp_path)
        one_line_error(res, "not made by radiokit")
    assert (tmp_path / "experiment.h5").read_bytes() == b"the user's own experiment"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["experiment.h5"]


def test_demo_refuses_a_results_folder_of_radiokit_process(experiment, tmp_path):
    """`radiokit demo -o exp/results --overwrite` took a `radiokit process` results folder for its
    own (radiokit made it): it wrote over the folder's list of files with its own marker and ran
    its demo beside the old report.html and results.json, a folder mixing two runs."""
    out = tmp_path / "results"
    assert run_cli("process", experiment, "-o", out, "--no-report", "-q", *ROI, *NO_CROSS_CHECK).returncode in (0, 1)
    before = tree_sha(out)
    for extra in ([], ["--overwrite"]):
        one_line_error(
            run_cli("demo", "-o", out, "-q", *extra), str(out), "made by radiokit process, not by radiokit demo"
        )
    assert tree_sha(out) == before


@pytest.mark.parametrize("holding", [["experiment.h5", "results/report.html"], []])
def test_process_refuses_a_demo_folder(holding, experiment, tmp_path):
    """`radiokit process -o out/demo` said "exists; pass --overwrite", and with --overwrite that the
    folder held files "radiokit did not write there" (the demo's own) -- or, a demo folder
    holding only its marker, replaced it. Either kind of folder is refused by the other command,
    --overwrite or not, in one line that says what the folder is."""
    from acquisition.demo import _demo_folder

    out = _demo_folder(tmp_path / "demo", overwrite=False)
    for name in holding:
        (out / name).parent.mkdir(exist_ok=True)
        (out / name).write_text("the demo's")
    before = tree_sha(out)
    for extra in ([], ["--overwrite"]):
        one_line_error(
            run_cli("process", experiment, "-o", out, "--no-report", "-q", *ROI, *extra),
            str(out),
            "made by radiokit demo, not by radiokit process",
        )
    assert tree_sha(out) == before and (out / RESULTS_MARKER).exists()
    no_temporaries(tmp_path)
    # several files, each a folder under -o: not under a demo's folder either (it said "holds the
    # results of one run")
    twin = tmp_path / "twin.h5"
    twin.write_bytes(experiment.read_bytes())
    one_line_error(
        run_cli("process", experiment, twin, "-o", out, "-q", *ROI),
        str(out),
        "made by radiokit demo, not by radiokit process",
    )
    assert tree_sha(out) == before


def test_demo_replaces_only_its_own_outputs(tmp_path):
    from acquisition.demo import _demo_folder

    out = _demo_folder(tmp_path / "demo", overwrite=False)  # a new folder: claimed
    (out / "experiment.h5").write_bytes(b"old demo run")
    (out / "results").mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="--overwrite"):
        _demo_folder(out, overwrite=False)
    _demo_folder(out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == sorted([RESULTS_MARKER, "notes.txt"])


@pytest.mark.parametrize(
    "marker", ["", "made by RadioKit;", "results of radiokit process", None, "made by radiokit;", "made by radiokit; x"]
)
def test_a_marker_radiokit_does_not_recognise_is_never_replaced(marker, experiment, tmp_path):
    """A folder whose marker's first line names no command radiokit knows (written by hand, by
    another tool, or a folder where the marker's name is a folder) was taken as the command's own:
    `radiokit demo --overwrite` deleted its experiment.h5 and results/ (review s32-r1). Neither
    command replaces it, --overwrite or not."""
    from acquisition.demo import _demo_folder

    out = tmp_path / "theirs"
    (out / "results").mkdir(parents=True)
    (out / "experiment.h5").write_text("someone's")
    (out / "results" / "x").write_text("someone's")
    if marker is None:
        (out / RESULTS_MARKER).mkdir()
    else:
        (out / RESULTS_MARKER).write_text(marker + "\n")
    before = tree_sha(out)
    with pytest.raises(OSError, match="not recognise"):
        _demo_folder(out, overwrite=True)
    one_line_error(run_cli("process", experiment, "-o", out, "-q", "--overwrite", *ROI), str(out), "not recognise")
    assert tree_sha(out) == before


def test_a_bare_old_style_marker_listing_its_files_is_never_replaced(experiment, tmp_path):
    """A marker whose first line is only ``made by radiokit;`` (by hand, or a shortened copy of
    the form process wrote before markers named the command) was read as process's: a folder
    whose marker listed its files was replaced by `process --overwrite`. Only the exact line
    radiokit wrote is recognised."""
    out = tmp_path / "old"
    (out / "results").mkdir(parents=True)
    (out / "experiment.h5").write_text("someone's")
    (out / "results" / "x").write_text("someone's")
    (out / RESULTS_MARKER).write_text("made by radiokit;\nexperiment.h5\nresults/x\n")
    before = tree_sha(out)
    one_line_error(run_cli("process", experiment, "-o", out, "-q", "--overwrite", *ROI), str(out), "not recognise")
    assert tree_sha(out) == before


@pytest.mark.parametrize(
    "first, command",
    [
        ("made by radiokit; may be replaced by a run with --overwrite. Files:", "process"),  # before named markers
        ("made by radiokit demo; may be replaced by `radiokit demo --overwrite`", "demo"),  # demo's first marker
    ],
)
def test_the_markers_radiokit_wrote_before_are_still_recognised(first, command, tmp_path):
    from radiokit.io._atomic import refuse_another_commands

    (tmp_path / RESULTS_MARKER).write_text(first + "\n")
    refuse_another_commands(tmp_path, command)
    other = {"process": "demo", "demo": "process"}[command]
    with pytest.raises(OSError, match=f"made by radiokit {command}, not by radiokit {other}"):
        refuse_another_commands(tmp_path, other)


# -- interrupted writes ------------------------------------------------------------------------
def _kill_when(proc, pattern_dir: Path, glob: str, timeout=120.0, sig=signal.SIGKILL):
    """Send ``sig`` to ``proc`` as soon as a path matching ``glob`` appears in ``pattern_dir``."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if list(pattern_dir.glob(glob)):
            proc.send_signal(sig)
            proc.wait()
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.002)
    proc.kill()
    proc.wait()
    return False


def _as_from_a_terminal():
    """A command's child starts with SIGINT, SIGQUIT and SIGHUP as a terminal gives them (their
    default actions): under ``make test &`` the suite inherits the first two ignored (under
    ``nohup`` the last), a run keeps a signal it was started ignoring ignored (radiokit.cli's
    ``_take_signals``, radiokit.interrupts.deferred), and a test's Ctrl-C went nowhere."""
    for sig in (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def _process_from_a_terminal(a, b, out, workers):
    """``radiokit process a b -o out --workers N`` in its own process group and session (as a
    terminal gives a command), its signals at their defaults, stdout and stderr piped."""
    return _cli_from_a_terminal(["process", a, b, "-q", "-o", out, "--workers", str(workers), *ROI])


def _cli_from_a_terminal(args, stdout=subprocess.PIPE):
    """``radiokit ARGS`` in its own process group and session, as a terminal starts a command
    (:func:`_as_from_a_terminal`), stderr piped as text."""
    return subprocess.Popen(
        [sys.executable, "-m", "radiokit.cli", *args],
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_as_from_a_terminal,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


def _popen(*args):
    """``radiokit ARGS``, output discarded, its stop signals at their defaults: under ``nohup make
    test`` (SIGHUP ignored) or ``make test &`` (SIGQUIT) the command inherited them ignored, kept
    them ignored (radiokit.cli's ``_take_signals``), ran to its end, and the tests that send them
    passed on the exit 0 they allow for a stop lost in a finalizer (review s48rv2)."""
    return subprocess.Popen(
        [sys.executable, "-m", "radiokit.cli", *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=_as_from_a_terminal,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


@pytest.fixture(scope="module")
def long_correct(tmp_path_factory):
    """``(experiment, output)``: an experiment long enough (60 frames of 512 x 512) for `correct`'s
    temporary file to be seen before the run ends, and a previous complete output of it (another
    domain, so that a new output would differ). Both read-only, built once for the tests below:
    each copies the output into its own folder, where the interrupted run writes."""
    tmp = tmp_path_factory.mktemp("long")
    exp = synthetic(tmp / "long.h5", shape=(512, 512), n_per_step=20)
    out = tmp / "previous.h5"
    assert run_cli("correct", exp, "-o", out, "-q", "--domain", "linear").returncode == 0
    return read_only(exp), read_only(out)


def test_correct_killed_mid_write_leaves_the_previous_complete_output(long_correct, tmp_path):
    exp, out = long_correct[0], writable_copy(long_correct[1], tmp_path / "out.h5")
    previous, inputs = sha(out), sha(exp)
    proc = _popen("correct", exp, "-o", out, "-q", "--overwrite")
    assert _kill_when(proc, tmp_path, ".out.tmp-*"), "the run ended before its temporary file was seen"
    assert sha(out) == previous and sha(exp) == inputs
    assert read(out, dataset="entry/data/data").n == 60
    # with no previous output: none afterwards either (only the hidden temporary may remain)
    out.unlink()
    proc = _popen("correct", exp, "-o", out, "-q")
    assert _kill_when(proc, tmp_path, ".out.tmp-*")
    assert not out.exists() and sha(exp) == inputs


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT, signal.SIGQUIT])
def test_correct_terminated_mid_write_cleans_up(sig, long_correct, tmp_path):
    """A catchable signal (a closed terminal, ``kill``, Ctrl-C, Ctrl-\\) unwinds: the previous output
    stays, and no temporary file is left either. (Python drops an exception raised while a
    finalizer runs; a signal landing there is lost and the run completes: then the output is the
    new complete one. Both are whole outputs, never a mix.)"""
    exp, out = long_correct[0], writable_copy(long_correct[1], tmp_path / "out.h5")
    previous, inputs = sha(out), sha(exp)
    proc = _popen("correct", exp, "-o", out, "-q", "--overwrite")
    assert _kill_when(proc, tmp_path, ".out.tmp-*", sig=sig)
    assert proc.returncode in (128 + sig, 0)  # a shell's status of a command the signal ended
    if proc.returncode != 0:
        assert sha(out) == previous
    assert read(out, dataset="entry/data/data").n == 60 and sha(exp) == inputs
    no_temporaries(tmp_path)


_LOST_IN_A_FINALIZER = """
import signal, sys
import radiokit.correct
import radiokit.interrupts
from radiokit.cli import main

sig = signal.Signals[sys.argv[1]]
if sys.argv[2] == "late":  # a timer thread a loaded machine schedules only after the command's end
    radiokit.interrupts.REDELIVER_AFTER_S = 600.0
signal.signal(signal.SIGINT, signal.default_int_handler)  # a terminal's Ctrl-C, also under `make test &`


class Finalised:
    def __del__(self):
        signal.raise_signal(sig)  # the handler runs here, and Python drops what it raises


def first_call_drops_a_stop(function):
    calls = []

    def wrapped(*args, **kwargs):
        if not calls:
            calls.append(1)
            Finalised()  # dies at once, taking the signal into its finalizer
        return function(*args, **kwargs)

    return wrapped


radiokit.correct.correct_frames = first_call_drops_a_stop(radiokit.correct.correct_frames)  # process
radiokit.correct._correct_planned = first_call_drops_a_stop(radiokit.correct._correct_planned)  # correct
sys.exit(main(sys.argv[3:]))
"""


@pytest.mark.parametrize("timer", ["prompt", "late"])
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("command", ["correct", "process"])
def test_a_stop_lost_in_a_finalizer_stops_the_command(command, sig, timer, tmp_path):
    """Python drops an exception raised while a finalizer runs (h5py's weak-reference callbacks
    run during every dataset write): a first Ctrl-C that landed there was lost and `radiokit
    process` or `correct` went on to its end (exit 0, the output written); a second one worked.
    The stop is delivered again, as the acquisitions do. Fault injection (a signal cannot be
    aimed at a finalizer from outside): the command's first frame drops an object whose
    finalizer receives the signal.

    ``late``: the delivery's timer thread not run before the command's end, as on a loaded
    machine (seen once: the 50 ms timer came after `correct` had renamed its output into place,
    and the command then said "interrupted; no partial output was left" beside the output). The
    stop came before the output was complete: it is never renamed into place."""
    # process: the stop is lost at its first frame, whatever the frames' size and number, and what
    # follows is its 50 ms delivery (prompt) or settle() refusing to rename the results folder
    # (late), in neither of which the report's figures take part: the default experiment and no
    # report (the figures were 4 of the late rows' ~6 CPU s; session 45). correct keeps 12 frames
    # of 256 x 256: its run after the first frame is to outlast the prompt delivery's 50 ms.
    big = {"shape": (256, 256), "n_per_step": 4} if command == "correct" else {}
    exp = synthetic(tmp_path / "exp.h5", **big)
    out = tmp_path / ("out.h5" if command == "correct" else "res")
    args = (
        ["correct", exp, "-o", out, "-q"]
        if command == "correct"
        else ["process", exp, "-o", out, "-q", "--no-report", *ROI]
    )
    inputs = sha(exp)
    res = subprocess.run(
        [sys.executable, "-c", _LOST_IN_A_FINALIZER, sig, timer, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    assert res.returncode == 128 + signal.Signals[sig], (res.returncode, res.stderr)
    assert res.stderr.strip().splitlines()[-1] == f"radiokit {command}: interrupted; no partial output was left"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"] and sha(exp) == inputs


_STOP_IN_A_POOL_THREADS_START = """
import signal, sys, threading
from radiokit import _threads

def stop(signum, frame):
    raise KeyboardInterrupt("SIGTERM")

signal.signal(signal.SIGTERM, stop)
real = threading.Thread.start

def start(self):
    real(self)
    if self.name.startswith("radiokit-"):
        signal.raise_signal(signal.SIGTERM)  # lands before the pool has registered the thread

threading.Thread.start = start
try:
    print(sum(_threads.pool().map(abs, range(-4, 4))))
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(143)
"""


def test_a_stop_while_the_thread_pool_starts_its_thread_does_not_hang_the_exit():
    """A stop landing inside ``Thread.start()`` of the pool's first thread (a lost stop delivered
    again 50 ms later did, at `correct`'s first frame) left a thread the interpreter's exit never
    woke: the command printed "interrupted" and hung for good in ``threading._shutdown``. The first
    thread is now made with stops held, and the stop is delivered right after."""
    res = subprocess.run(
        [sys.executable, "-c", _STOP_IN_A_POOL_THREADS_START], capture_output=True, text=True, timeout=60
    )
    assert (res.returncode, res.stdout.strip()) == (143, "interrupted"), (res.returncode, res.stdout, res.stderr)


def test_process_killed_mid_write_leaves_the_previous_complete_folder(tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    out = tmp_path / "res"
    fast = ["-q", "--cross-check", "none", *ROI]  # the registration's second opinion: no file of its own
    assert run_cli("process", exp, "-o", out, *fast).returncode == 0  # with the report: many files
    previous, inputs = tree_sha(out), sha(exp)
    assert "report.html" in previous
    # the previous folder is what is checked: the killed run's report, drawn before results.h5,
    # would only be more of what the kill throws away (its figures: ~2 of the child's ~5 CPU s)
    # without the report the run's last writes after results.h5 take milliseconds: on a loaded
    # machine the kill can land after the swap (seen in session 46). That run's folder must then be
    # complete, and it is tried again, the new folder the one to keep, until a kill lands mid-write.
    for _ in range(3):
        proc = _popen("process", exp, "-o", out, "--overwrite", "--no-report", *fast)
        # False: the run ended before its results were seen (under load, the milliseconds between
        # results.h5 and the swap): its folder must be whole, and it is tried again, as after a late kill
        killed = _kill_when(proc, tmp_path, ".res.tmp-*/results.h5")
        assert sha(exp) == inputs
        if killed and not os.path.lexists(out):
            # landed between renaming the previous folder aside and the new one into place (the
            # module's documented window, seen once in session 47): the previous one is aside, whole,
            # and what the next run to that output does first puts it back
            aside = list(tmp_path.glob(".res.old-*"))
            assert len(aside) == 1 and tree_sha(aside[0]) == previous, aside
            recover_interrupted(out)
            assert tree_sha(out) == previous and not list(tmp_path.glob(".res.old-*"))
            return
        now = tree_sha(out)
        if killed and now == previous:
            return
        assert {"results.h5", "results.json", ".radiokit-output"} <= set(now), now  # the whole new run
        previous = now
    pytest.fail("no kill of three landed before the run's folder was swapped in")


# -- full disk ---------------------------------------------------------------------------------
@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB tmpfs (needs root); None where mounting is not permitted."""
    with mounted_tmpfs(tmp_path / "disk", "1m") as mnt:
        yield mnt


def _full_disk_run(small_disk, *args):
    """Run the command writing onto the small disk, or, where no tmpfs can be mounted, with
    ``shutil.disk_usage`` faked to report 1000 bytes free (an injected ENOSPC: the only way to
    fill a disk without privileges)."""
    if small_disk is not None:
        return run_cli(*args)
    code = (
        "import shutil, sys; from collections import namedtuple; from radiokit.cli import main; "
        "shutil.disk_usage = lambda p: namedtuple('u', 'total used free')(10**6, 10**6 - 1000, 1000); "
        "sys.exit(main(sys.argv[1:]))"
    )
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


@pytest.mark.parametrize(
    "cmd, experiment_kw, output, args",
    [
        ("correct", {"n_per_step": 2}, "out.h5", []),  # 6 x 256 KiB out: > 1 MiB
        ("correct", {"n_per_step": 2}, "out.tif", []),
        # results.h5 > 1 MiB (3 MB); the fast preset, no cross-check and no report (its figures were
        # ~2 of the row's ~4 CPU s): the registration and the figures are not what fills it
        ("process", {"noise": 30.0}, "res", [*ROI, "--preset", "fast", "--cross-check", "none", "--no-report"]),
    ],
)
def test_a_full_disk_is_one_line_and_leaves_nothing(small_disk, cmd, experiment_kw, output, args, tmp_path):
    exp = synthetic(tmp_path / "exp.h5", shape=(256, 256), **experiment_kw)
    disk = small_disk or (tmp_path / "fake-disk")
    disk.mkdir(exist_ok=True)
    before = sha(exp)
    res = _full_disk_run(small_disk, cmd, exp, "-q", "-o", disk / output, *args)
    one_line_error(res, output, "no space left")
    assert list(disk.iterdir()) == [] and sha(exp) == before


def test_a_stack_that_fills_the_disk_mid_write_is_removed(small_disk, tmp_path):
    """No size known in advance (no free-space check first): the disk fills inside libhdf5 or
    tifffile, and the error is still one clean exception with no file left behind."""
    if small_disk is None:
        pytest.skip("needs a real full disk (a tmpfs mount, as root): the failure is inside libhdf5")
    for suffix in (".h5", ".tif"):
        code = (
            "import numpy as np; from radiokit.io import StackWriter\n"
            f"with StackWriter({str(small_disk / ('s' + suffix))!r}, (256, 256)) as w:\n"
            "    for i in range(12): w.append(np.full((256, 256), i, np.float32))\n"
        )
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert res.returncode == 1 and "DiskFullError" in res.stderr and "no space left" in res.stderr
        assert list(small_disk.iterdir()) == []


def test_a_tiff_with_a_corrupt_fifth_page_is_an_error_not_a_shorter_stack(experiment, tmp_path):
    frames = read(experiment)
    proj = frames.data[frames.meta["image_key"] == 0]
    stack = np.concatenate([proj, proj, proj[:2]])  # 8 pages
    good = tmp_path / "good.tif"
    tifffile.imwrite(good, stack, compression="zlib")
    with tifffile.TiffFile(good) as tif:
        ifd = tif.pages[4].offset
    data = bytearray(good.read_bytes())
    data[ifd + 2 : ifd + 40] = b"\xff" * 38  # the 5th page's first tag entries
    bad = tmp_path / "bad.tif"
    bad.write_bytes(bytes(data))
    before = sha(bad)
    res = run_cli("correct", bad, "--cal", _cal(experiment, tmp_path), "-q", "-o", tmp_path / "out.h5")
    one_line_error(res, "bad.tif", "page 4")
    assert not (tmp_path / "out.h5").exists() and sha(bad) == before


def _cal(experiment, tmp_path):
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", experiment, "-o", cal).returncode == 0
    return cal


def test_sim_run_refuses_before_the_mechanics(tmp_path):
    from sim.scene import load_scene

    scene = load_scene("seed-breast").save(tmp_path / "scene.toml")
    old = tmp_path / "old.h5"
    old.write_bytes(b"a previous simulation")
    before = sha(scene)
    one_line_error(run_cli("sim", "run", "--preset", "seed-breast", "-o", old, "-q"), "old.h5", "--overwrite")
    assert old.read_bytes() == b"a previous simulation"
    # the scene file is an input: neither the experiment nor --save-scene may replace it
    one_line_error(
        run_cli("sim", "run", scene, "-o", tmp_path / "new.h5", "--save-scene", scene, "--overwrite", "-q"),
        "scene.toml",
        "input",
    )
    assert sha(scene) == before and not (tmp_path / "new.h5").exists()


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_meshing_keeps_the_commands_signal_handlers(sig):
    """gmsh's initialisation reset SIGTERM and SIGHUP to the default at the C level: `kill` during
    `radiokit sim run` ended it at once (exit 143) and left its temporary file and reserve behind."""
    code = (
        "import os, signal, time\n"
        "got = []\n"
        f"signal.signal(signal.{sig}, lambda *a: got.append(1))\n"
        "from sim.mesh import _gmsh\n"
        "_gmsh()\n"
        f"os.kill(os.getpid(), signal.{sig})\n"
        "time.sleep(0.05)\n"
        "print('handled' if got else 'not handled')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "handled", (res.returncode, res.stdout, res.stderr)


def test_a_killed_runs_temporary_is_removed_by_the_next_run(experiment, tmp_path):
    import socket

    from radiokit.io import atomic_path

    out = tmp_path / "cal.h5"
    host = socket.gethostname().split(".")[0]
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()  # a process that has ended
    stale = tmp_path / f".cal.tmp-{host}-{dead}-0123abcd.h5"
    stale.write_bytes(b"half a calibration")
    alive = tmp_path / f".cal.tmp-{host}-{os.getpid()}-0123abcd.h5"  # a live writer's: kept
    alive.write_bytes(b"being written")
    mine = tmp_path / ".cal.tmp-notes.h5"  # not a name radiokit makes: kept
    mine.write_bytes(b"the user's")
    assert run_cli("calibrate", "--experiment", experiment, "-o", out).returncode == 0
    assert not stale.exists() and alive.exists() and mine.exists() and h5py.is_hdf5(out)
    with atomic_path(tmp_path / "x.txt") as tmp:
        assert tmp.name.startswith(f".x.tmp-{host}-{os.getpid()}-") and tmp.suffix == ".txt"
        tmp.write_text("whole")
    assert (tmp_path / "x.txt").read_text() == "whole"


def test_a_killed_process_runs_temporary_folder_is_removed_by_the_next_run(experiment, tmp_path):
    host, dead = socket.gethostname().split(".")[0], _dead_pid()
    stale = tmp_path / f".res.tmp-{host}-{dead}-0123abcd"
    stale.mkdir()
    (stale / "results.h5").write_bytes(b"half")
    res = run_cli("process", experiment, "-o", tmp_path / "res", "--no-report", "-q", *ROI, *NO_CROSS_CHECK)
    assert res.returncode == 0, res.stderr
    assert not stale.exists()
    no_temporaries(tmp_path)


_SWAP_KILLED = """
import os, signal, sys
from pathlib import Path
from radiokit.io import _atomic
out = Path(sys.argv[1])
# the rename-aside route, the one a system without renameat2's RENAME_EXCHANGE takes (a fake
# for a file system this machine lacks): the previous folder renamed aside, the name missing
_atomic._exchange_in = lambda tmp, path: False
real, calls = _atomic._strangers, []
def strangers(folder):  # the second look is _swap_in's, the old folder just renamed aside
    calls.append(folder)
    if len(calls) == 2:
        os.kill(os.getpid(), signal.Signals[sys.argv[2]])
    return real(folder)
_atomic._strangers = strangers
with _atomic.atomic_dir(out, overwrite=True) as tmp:
    (tmp / "results.txt").write_text("run 2")
"""


def _results_folder(out: Path, text="run 1") -> dict:
    from radiokit.io._atomic import atomic_dir

    with atomic_dir(out) as tmp:
        (tmp / "results.txt").write_text(text)
    return tree_sha(out)


def _dead_pid() -> int:
    """The process number of a process that has ended (as a killed run's is)."""
    return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True).stdout)


@pytest.mark.parametrize("next_run", ["fails", "overwrites"])
def test_a_results_folder_a_killed_run_left_aside_is_put_back_not_deleted(next_run, experiment, tmp_path):
    """A run killed between renaming the previous folder aside and swapping its own in left the
    name missing and the previous results (and the user's notes) in ``.res.old-...``, which the
    next run to that name deleted, even one that failed. The next run puts it back."""
    out = tmp_path / "res"
    previous = _results_folder(out)
    killed = subprocess.run([sys.executable, "-c", _SWAP_KILLED, out, "SIGKILL"], capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    (aside,) = tmp_path.glob(".res.old-*")
    assert not out.exists()
    if next_run == "fails":  # no --overwrite: the folder is back, so it exists
        one_line_error(run_cli("process", experiment, "-o", out, "-q", *ROI), "exists")
        assert tree_sha(out) == previous
    else:
        args = ["process", experiment, "-o", out, "-q", "--overwrite", "--no-report", *ROI, *NO_CROSS_CHECK]
        assert run_cli(*args).returncode == 0
        assert "results.h5" in tree_sha(out)
        no_temporaries(tmp_path)  # the killed run's temporary too, once a run gets that far
    assert not aside.exists() and not list(tmp_path.glob(".res.old-*"))


def test_two_results_folders_left_aside_are_refused_and_kept(experiment, tmp_path):
    host, dead = socket.gethostname().split(".")[0], _dead_pid()
    aside = [tmp_path / f".res.old-{host}-{dead}-{tag}" for tag in ("0123abcd", "4567ef01")]
    for folder in aside:
        folder.mkdir()
        (folder / "notes.txt").write_text("the user's")
    res = run_cli("process", experiment, "-o", tmp_path / "res", "-q", "--overwrite", *ROI)
    one_line_error(res, "res", aside[0].name, aside[1].name)
    assert all((folder / "notes.txt").read_text() == "the user's" for folder in aside)
    assert not (tmp_path / "res").exists()


def test_a_results_folder_kept_aside_is_never_deleted_by_a_later_run(experiment, tmp_path):
    """The message said "the previous folder is kept in .res.old-...", and the next run to that
    name deleted it: one left aside while the name is taken is left alone."""
    host, dead = socket.gethostname().split(".")[0], _dead_pid()
    out = tmp_path / "res"
    _results_folder(out)
    kept = tmp_path / f".res.old-{host}-{dead}-0123abcd"
    kept.mkdir()
    (kept / "notes.txt").write_text("the user's")
    args = ["process", experiment, "-o", out, "-q", "--overwrite", "--no-report", *ROI, *NO_CROSS_CHECK]
    assert run_cli(*args).returncode == 0
    assert (kept / "notes.txt").read_text() == "the user's"


def test_a_results_folder_kept_aside_beside_its_name_is_pointed_to(tmp_path):
    """A run killed after swapping its new folder in, before removing the old one, leaves the
    previous results in ``.res.old-...`` beside ``res``: hidden, and kept for ever. Each later
    run to that name says where they are (once), rather than leaving them unnoticed."""
    import socket

    from radiokit.io._atomic import check_output

    host = socket.gethostname().split(".")[0]
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    out = tmp_path / "res"
    _results_folder(out)
    kept = tmp_path / f".res.old-{host}-{dead}-0123abcd"
    kept.mkdir()
    with pytest.warns(UserWarning) as caught:
        check_output(out, overwrite=True, folder=True)
    (message,) = [str(w.message) for w in caught]
    assert str(out) in message and kept.name in message and "interrupted" in message
    assert kept.is_dir()
    # a live run's folder aside (this process's own) is its business, not a leftover
    (tmp_path / f".res.old-{host}-{os.getpid()}-89abcdef").mkdir()
    kept.rename(tmp_path / "elsewhere")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_output(out, overwrite=True, folder=True)


def _left_aside(out: Path, monkeypatch) -> Path:
    """The results folder a run killed while replacing ``out`` leaves aside, named by radiokit's
    own scheme as a process that has ended (its number) would name it."""
    from radiokit.io import _atomic

    with monkeypatch.context() as m:
        m.setattr(_atomic, "_owner_tag", lambda: f"{socket.gethostname().split('.')[0]}-{_dead_pid()}")
        aside = _atomic._temporary_name(out, folder=True, kind="old")
    _results_folder(out.parent / "built")
    (out.parent / "built").rename(aside)
    return aside


def test_a_results_folder_replaced_is_never_missing_at_its_name(tmp_path, monkeypatch):
    """Where the system swaps two names in one step (renameat2's RENAME_EXCHANGE; Linux), the
    previous results folder and the new one are swapped: at every step of the replacement the
    name holds a complete folder. Renamed aside first, it was missing while the folder aside was
    looked into for files added during the run, where a kill left it missing (the suite, session
    47). A file added during the run still swaps the previous folder back."""
    from radiokit.io import _atomic

    if _atomic._renameat2() is None:
        pytest.skip("no renameat2 here: the rename-aside route (absent in between) is the one taken")
    out = tmp_path / "res"
    _results_folder(out)
    seen = []
    looked = _atomic._strangers

    def strangers(folder):
        seen.append(os.path.isfile(out / RESULTS_MARKER))  # the name holds a complete folder
        found = looked(folder)
        if add_at == len(seen):  # once looked at just before the swap: too late to be seen there
            (out / "notes.txt").write_text("the user's")
        return found

    monkeypatch.setattr(_atomic, "_strangers", strangers)
    add_at = 0
    with _atomic.atomic_dir(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert seen and all(seen), seen
    assert (out / "new.txt").read_text() == "new" and not list(tmp_path.glob(".res.*"))
    before, seen[:], add_at = tree_sha(out), [], 2  # 1: atomic_dir's start, 2: just before the swap
    with pytest.raises(_atomic.OutputError, match="added during the run"):
        with _atomic.atomic_dir(out, overwrite=True) as tmp:
            (tmp / "newer.txt").write_text("newer")
    assert len(seen) == 3 and all(seen), seen  # looked for again once swapped out, then swapped back
    assert tree_sha(out) == {**before, "notes.txt": sha(out / "notes.txt")} and not list(tmp_path.glob(".res.*"))


def test_recover_interrupted_clears_what_a_killed_writer_left_of_a_results_folder(tmp_path, monkeypatch):
    """radiokit.io's public step for a caller whose workers were killed mid-write (process_many):
    the killed writer's temporary is removed, the previous results it had put aside are back at
    the name, a live writer's temporary (this process's) stays, and a folder with nothing left is
    untouched."""
    from radiokit.io import recover_interrupted
    from radiokit.io._atomic import _temporary_name

    out = tmp_path / "res"
    aside = _left_aside(out, monkeypatch)  # the name missing: killed between the two renames
    before = tree_sha(aside)
    host = socket.gethostname().split(".")[0]
    killed = tmp_path / f".res.tmp-{host}-{_dead_pid()}-0123abcd"
    live = _temporary_name(out, folder=True)
    killed.mkdir(), live.mkdir()
    recover_interrupted(out)
    assert tree_sha(out) == before and not aside.exists() and not killed.exists() and live.is_dir()
    recover_interrupted(tmp_path / "never-written")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["res", live.name])


def test_a_results_folder_kept_aside_is_pointed_to_by_the_link_the_user_named(tmp_path, monkeypatch):
    """s39 review (LOW): ``-o latest``, a link to ``res``: the warning of results left aside
    named ``res``, which the user did not type, and so did the refusal of two left aside. Both
    name the link, and what it points at."""
    from radiokit.io._atomic import OutputError, check_output

    out, link = tmp_path / "res", tmp_path / "latest"
    _results_folder(out)
    link.symlink_to(out)
    kept = _left_aside(out, monkeypatch)
    with pytest.warns(UserWarning) as caught:
        check_output(link, overwrite=True, folder=True)
    (message,) = [str(w.message) for w in caught]
    assert message.startswith(f"{link} (a link to {out}): ") and kept.name in message, message
    shutil.rmtree(out)
    again = _left_aside(out, monkeypatch)
    with pytest.raises(OutputError) as refused:
        check_output(link, overwrite=True, folder=True)
    assert str(refused.value).startswith(f"{link} (a link to {out}): ") and again.name in str(refused.value)


def test_a_link_and_its_target_are_each_quoted_as_names_print(tmp_path, monkeypatch):
    """s52: a refusal naming a link and its target quoted the two as one name, ``'l\\nn.h5 (a link
    to t.h5)'``: the words "a link to" inside the quotes, read as part of a file's name. Each
    name as names print (radiokit._names.shown), the words between them outside the quotes."""
    from radiokit._names import shown
    from radiokit.io._atomic import OutputError, OutputExistsError, check_output

    target, link = tmp_path / "t\\x.h5", tmp_path / "l\nn.h5"
    target.write_bytes(b"data")
    link.symlink_to(target)
    with pytest.raises(OutputExistsError) as refused:
        check_output(link)
    assert str(refused.value).startswith(f"{shown(link)} (a link to {shown(target)}): exists;"), str(refused.value)
    out, named = tmp_path / "r\\es", tmp_path / "lat\nest"
    _results_folder(out)
    named.symlink_to(out)
    _left_aside(out, monkeypatch)
    with pytest.warns(UserWarning) as caught:
        check_output(named, overwrite=True, folder=True)
    (message,) = [str(w.message) for w in caught]
    assert message.startswith(f"{shown(named)} (a link to {shown(out)}): "), message
    shutil.rmtree(out)
    _left_aside(out, monkeypatch)
    with pytest.raises(OutputError) as refused:
        check_output(named, overwrite=True, folder=True)
    assert str(refused.value).startswith(f"{shown(named)} (a link to {shown(out)}): is missing"), str(refused.value)


@pytest.mark.parametrize("stem", ["r" * 240, "\u7a7a" * 80], ids=["ascii", "3-byte"])
def test_outputs_alike_in_their_first_bytes_never_take_each_others_results_left_aside(tmp_path, monkeypatch, stem):
    """s39 review (LOW): the name of a folder left aside is cut to fit NAME_MAX, so two outputs
    whose names share their first ~227 bytes had one such name: ``a`` missing, ``b``'s previous
    results were put back at ``a``'s name; ``a`` there, they were named as ``a``'s. Each now
    finds only its own."""
    from radiokit.io._atomic import check_output

    a, b = tmp_path / (stem + "a"), tmp_path / (stem + "b")
    assert len(os.fsencode(b.name)) <= 255
    kept = _left_aside(b, monkeypatch)
    (kept / "notes.txt").write_text("b's")
    check_output(a, folder=True)
    assert not a.exists() and (kept / "notes.txt").exists()
    _results_folder(a)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_output(a, overwrite=True, folder=True)
    check_output(b, overwrite=True, folder=True)
    assert (b / "notes.txt").read_text() == "b's" and not kept.exists()

    # review s40rr: a name of exactly the room (not cut), and a longer one beginning with it, whose
    # head cut without the digest (the scheme before) was the first's whole name
    host = socket.gethostname().split(".")[0]
    room = 255 - len(os.fsencode(f"..old-{host}-{10 * '0'}-{8 * '0'}"))
    exact = stem
    while len(os.fsencode(exact)) > room:
        exact = exact[:-1]
    while len(os.fsencode(exact)) < room:
        exact += "x"
    short, long = tmp_path / exact, tmp_path / (exact + "-and-more")
    kept = _left_aside(short, monkeypatch)
    (kept / "notes.txt").write_text("short's")
    check_output(long, folder=True)
    assert not long.exists() and (kept / "notes.txt").read_text() == "short's"
    check_output(short, overwrite=True, folder=True)
    assert (short / "notes.txt").read_text() == "short's"


def test_a_results_folder_interrupted_while_aside_is_put_back(tmp_path, monkeypatch):
    """Ctrl-C while the previous folder is aside: it is back at its name before the interrupt goes on."""
    from radiokit.io import _atomic

    out = tmp_path / "res"
    previous = _results_folder(out)
    real, calls = _atomic._strangers, []

    def strangers(folder):
        calls.append(folder)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(folder)

    monkeypatch.setattr(_atomic, "_strangers", strangers)
    with pytest.raises(KeyboardInterrupt), _atomic.atomic_dir(out, overwrite=True) as tmp:
        (tmp / "results.txt").write_text("run 2")
    assert tree_sha(out) == previous
    no_temporaries(tmp_path)


# -- an output folder that cannot be written -----------------------------------------------------
@pytest.fixture
def readonly_dir(tmp_path):
    """A read-only tmpfs (needs root), else a folder without write permission (not for root)."""
    mnt = tmp_path / "ro"
    mnt.mkdir()
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64m", "tmpfs", str(mnt)], capture_output=True)
    if ok.returncode == 0:
        try:
            yield mnt
        finally:
            subprocess.run(["umount", str(mnt)], check=True)
        return
    if os.geteuid() == 0:
        pytest.skip("root without mount: no folder it cannot write")
    mnt.chmod(0o555)
    try:
        yield mnt
    finally:
        mnt.chmod(0o755)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "register-png", "process"])
def test_an_output_that_cannot_be_written_is_named_not_its_temporary(cmd, readonly_dir, experiment, images, tmp_path):
    """A read-only folder: the one line names the output asked for and why, not the hidden
    temporary radiokit writes first (``.out.tmp-HOST-PID-XXXXXXXX.h5``) nor libhdf5's flags."""
    commands = {**_commands(experiment, images, readonly_dir / "out"), "process": ["process", experiment, "-q"]}
    args = commands[cmd] + (["-o", readonly_dir / "out", *ROI] if cmd == "process" else [])
    out = Path(args[args.index("--png") + 1] if cmd == "register-png" else args[args.index("-o") + 1])
    if cmd == "register-png":  # the field goes to a writable folder; only the figure cannot be written
        args[args.index("-o") + 1] = tmp_path / "field.h5"
    res = run_cli(*args)
    line = one_line_error(res, out, "cannot be written")
    assert ".tmp-" not in line and "o_flags" not in line, line


# -- long names --------------------------------------------------------------------------------
@pytest.mark.parametrize("stem", ["x" * 245, "\u7a7a" * 83])  # 248 and 252 bytes with the suffix
@pytest.mark.parametrize("cmd", ["calibrate", "correct", "process"])
def test_an_output_whose_name_is_near_the_filesystem_limit_is_written(cmd, stem, experiment, images, tmp_path):
    """A name of up to 255 bytes is a valid file name; the hidden temporary beside it must
    fit the same limit, or the output could never be written."""
    out = tmp_path / (stem if cmd == "process" else stem + ".h5")
    assert len(os.fsencode(out.name)) <= 255
    args = {
        **_commands(experiment, images, out),
        "process": ["process", experiment, "-q", *ROI, *NO_CROSS_CHECK, "-o", out],
    }[cmd]
    if cmd != "process":
        args[-1] = out
    res = run_cli(*args, "--no-report") if cmd == "process" else run_cli(*args)
    assert res.returncode == 0, res.stderr
    assert out.exists()
    no_temporaries(tmp_path)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "register", "process"])
def test_an_output_whose_name_is_past_the_filesystem_limit_is_one_line(cmd, experiment, images, tmp_path):
    """A name of 300 bytes (over NAME_MAX, 255): one line naming the output and the problem in
    the words of the other outputs that cannot be written, not Python's "[Errno 36] File name
    too long: '...'" from a Path.exists() that Python 3.11 lets raise; nothing written."""
    out = tmp_path / ("x" * 297 + ".h5")
    folder = tmp_path / ("x" * 300)  # process writes a results folder
    args = {**_commands(experiment, images, out), "process": ["process", experiment, "-q", "-o", folder, *ROI]}[cmd]
    out = folder if cmd == "process" else out
    line = one_line_error(run_cli(*args), out, "cannot be written: File name too long")
    assert "Errno" not in line, line
    no_temporaries(tmp_path)


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "register"])
def test_an_input_whose_name_is_past_the_filesystem_limit_is_named_not_the_output(cmd, experiment, images, tmp_path):
    """An *input* named past NAME_MAX (300 bytes): the output checks looked it up to compare it with
    the output (Python 3.11's Path.is_dir and Path.exists raise ENAMETOOLONG), and the line blamed
    the output, ``out.h5: cannot be written: File name too long`` (review s51rv2). Now the line
    names the input and what is wrong with it; the output is not made."""
    long = tmp_path / ("x" * 296 + ".tif")
    out = tmp_path / "out.h5"
    args = _commands(experiment if cmd != "calibrate" else long, (long, images[1]), out)[cmd]
    if cmd == "correct":
        args[1] = long
    res = run_cli(*args)
    line = one_line_error(res, long.name[:40])
    assert "File name too long" in line and "out.h5" not in line, line
    assert not out.exists()


@pytest.mark.parametrize("stem", ["scan[1]", "a*b?", "[x]"])
def test_a_killed_runs_temporary_is_found_whatever_its_name(tmp_path, stem):
    """Names with glob characters (``scan[1].h5``) are names, not patterns: the stale temporary
    of this output is removed, and only it (``.scan1.tmp-...`` belongs to ``scan1.h5``)."""
    import socket

    from radiokit.io import atomic_path

    host = socket.gethostname().split(".")[0]
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()  # a process that has ended
    stale = tmp_path / f".{stem}.tmp-{host}-{dead}-0123abcd.h5"
    other = tmp_path / f".{stem.replace('[', '').replace(']', '')}1.tmp-{host}-{dead}-0123abcd.h5"
    for p in (stale, other):
        p.write_bytes(b"half a file")
    with atomic_path(tmp_path / f"{stem}.h5") as tmp:
        tmp.write_bytes(b"whole")
    assert not stale.exists() and other.exists()
    assert (tmp_path / f"{stem}.h5").read_bytes() == b"whole"


@pytest.mark.parametrize("cmd", ["calibrate", "correct", "correct-tiff", "register", "process"])
def test_an_output_under_a_file_is_refused_saying_so(cmd, experiment, images, tmp_path):
    """``-o notes.txt/out.h5``: the folder to hold the output is a file. One line naming the
    output and that, before any work, and the file untouched."""
    (tmp_path / "notes.txt").write_text("mine")
    out = tmp_path / "notes.txt" / "sub" / "out"
    args = {**_commands(experiment, images, out), "process": ["process", experiment, "-q", "-o", out, *ROI]}[cmd]
    res = run_cli(*args)
    one_line_error(res, "notes.txt", "not a folder")
    assert (tmp_path / "notes.txt").read_text() == "mine"


# -- file names that are not UTF-8 -------------------------------------------------------------
def _non_utf8(tmp_path, name: bytes) -> Path:
    """``tmp_path / name`` for a name of bytes that are not UTF-8 (legal on POSIX filesystems:
    Latin-1 names from old systems); skipped where the filesystem refuses such names."""
    path = Path(os.fsdecode(os.path.join(os.fsencode(tmp_path), name)))
    try:
        path.write_bytes(b"")
    except OSError:
        pytest.skip("this filesystem takes only UTF-8 names")
    path.unlink()
    return path


def test_inputs_named_in_bytes_that_are_not_utf8_are_recorded_readably(images, tmp_path):
    """register and process record their inputs' names in HDF5 text attributes (UTF-8): a name
    that is not UTF-8 is recorded with its odd bytes as \\xNN, not refused after the work."""
    fixed = _non_utf8(tmp_path, b"fixed\xff.tif")
    fixed.write_bytes(images[0].read_bytes())
    res = run_cli("register", fixed, images[1], "-o", tmp_path / "reg.h5", "--method", "ncc")
    assert res.returncode in (0, 1), res.stderr  # 1: registered, flagged untrustworthy
    attrs = []
    with h5py.File(tmp_path / "reg.h5") as h5:
        h5.visititems(lambda name, obj: attrs.extend(str(v) for v in obj.attrs.values()))
    assert any(a.endswith("fixed\\xff.tif") for a in attrs), attrs
    exp = synthetic(_non_utf8(tmp_path, b"exp\xe9 1.h5"))
    res = run_cli("process", exp, "-q", "-o", tmp_path / "res", "--cross-check", "none", *ROI)
    assert res.returncode in (0, 1), res.stderr
    with h5py.File(tmp_path / "res" / "results.h5") as h5:
        assert h5["entry"].attrs["source"].endswith("exp\\xe9 1.h5")
    assert "exp\\xe9 1.h5" in (tmp_path / "res" / "report.html").read_text(encoding="utf-8")


def test_process_s_headline_names_a_file_not_utf8_as_every_other_line_does(tmp_path):
    """Review s52rvoff: the headline printed ``Results.source``, the name with its odd bytes
    written as text ``\\xNN`` (for UTF-8 files); since s52 quotes a name holding a backslash, it
    printed ``'exp\\\\xe9.h5'``, which reads back (ast.literal_eval) as another file, one
    named with a backslash, where the command's other lines print the byte as ``\\xe9``
    unquoted. Named as the command was given it, as the lines after it name its outputs."""
    exp = synthetic(_non_utf8(tmp_path, b"exp\xe9.h5"))
    res = run_cli("process", exp, "-o", tmp_path / "res", "--no-report", *NO_CROSS_CHECK, *ROI)
    assert res.returncode in (0, 1), res.stderr  # 1: a pair flagged
    first = res.stdout.splitlines()[0]
    assert first.startswith(f"{tmp_path}/exp\\xe9.h5: improvement factor"), first
    assert f"  results.json: {tmp_path}/res/results.json" in res.stdout, res.stdout


@pytest.mark.parametrize("cmd", ["calibrate", "register"])
@pytest.mark.parametrize("name", ["out.tif", "out.png", "out"])
def test_an_hdf5_output_is_not_written_under_another_formats_name(cmd, name, experiment, images, tmp_path):
    """calibrate and register write HDF5: under ``out.tif`` other programs would take it for a
    TIFF and fail on it. Refused in one line before the work, as correct refuses ``.png``."""
    args = _commands(experiment, images, tmp_path / "x")[cmd][:-1] + [tmp_path / name]
    res = run_cli(*args)
    one_line_error(res, name, ".h5")
    assert not (tmp_path / name).exists()


def test_a_failed_process_leaves_no_empty_folders(tmp_path):
    """`-o new/sub/res` for a file that cannot be processed (no darks), alone and as one of two
    Dask runs that both fail: the runs left `new/sub/` (and `many/`) behind, empty. Folders the
    run made are removed again; one that existed stays."""
    bad = tmp_path / "bad.h5"
    with ExperimentWriter(bad, shape=(32, 40)) as w:  # flats and projections, no darks
        w.append(np.full((32, 40), 3000, np.uint16), image_key=ImageKey.FLAT)
        for step in (1, 2):
            w.append(np.full((32, 40), 1500, np.uint16), image_key=ImageKey.PROJECTION, step=step)
    one_line_error(run_cli("process", bad, "-o", tmp_path / "new" / "sub" / "res", "-q"), "bad.h5", "no darks")
    twin = tmp_path / "twin.h5"  # another file: one file given twice is refused before any work
    twin.write_bytes(bad.read_bytes())
    # two files run on a Dask cluster: in a process of its own, the cluster's workers its children
    res = run("process", bad, twin, "-o", tmp_path / "many" / "x", "-q", "--workers", "1")
    assert res.returncode == 1 and res.stderr.count("no darks") == 2, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.h5", "twin.h5"]


def test_the_file_size_limit_is_not_guessed_on_file_systems_glibc_does_not_list(tmp_path):
    """Found in review: the writer took ``pathconf(PC_FILESIZEBITS)`` as the file system's limit,
    and glibc answers 32 for every file system it does not list (tmpfs, NFS, CIFS, FUSE): an
    experiment file there was refused at 2 GiB, about 200 full frames. Only FAT caps a file (4 GiB
    - 1); elsewhere only the process's RLIMIT_FSIZE counts. /dev/shm is a tmpfs on Linux."""
    import math
    import shutil
    import tempfile

    from radiokit.io._atomic import _file_system_type

    shm = Path("/dev/shm")
    if not (shm.is_dir() and os.access(shm, os.W_OK)) or _file_system_type(shm) != "tmpfs":
        pytest.fail("this test needs Linux's /dev/shm tmpfs (every CI runner here has it)")
    folder = Path(tempfile.mkdtemp(dir=shm))
    try:
        with ExperimentWriter(folder / "exp.h5", shape=(4, 5)) as w:
            assert w._size_and_limit()[1] == math.inf
        assert _file_system_type(tmp_path) not in (None, "vfat", "msdos")
    finally:
        shutil.rmtree(folder)


# -- the file-size limit (ulimit -f) -------------------------------------------------------------
def _limited(nbytes):
    """``ulimit -f``: the child may write no file past ``nbytes``; Python ignores SIGXFSZ, so such a
    write fails with EFBIG (as on a FAT disk at 4 GiB) rather than killing the process."""
    import resource

    def preexec():
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))

    return preexec


@pytest.mark.parametrize(
    "cmd, output, args",
    [
        ("correct", "out.h5", []),  # 6 x 256 KiB frames
        ("correct", "out.tif", []),
        ("calibrate", "cal.h5", []),  # 19 kB: darks and flats of one value compress well
        # results.h5, in the folder (past 10 kB whatever registered it: the fast preset)
        ("process", "res", [*ROI, "--no-report", "--cross-check", "none", "--preset", "fast"]),
    ],
)
def test_an_output_past_the_file_size_limit_is_one_line_and_leaves_nothing(cmd, output, args, tmp_path):
    """Found by a hostile-input trial: ``correct`` under ``ulimit -f`` died in libhdf5 (a traceback,
    then SIGSEGV while closing); ``correct -o x.tif`` said "no space left"; ``process`` said
    "[Errno 27] File too large", naming no file."""
    exp = synthetic(tmp_path / "exp.h5", shape=(256, 256), n_per_step=2, noise=30.0)
    out = tmp_path / "out"
    out.mkdir()
    before = sha(exp)
    argv = (
        ["calibrate", "--experiment", exp, "-o", out / output]
        if cmd == "calibrate"
        else [cmd, exp, "-q", "-o", out / output, *args]
    )
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", *map(str, argv)],
        capture_output=True,
        text=True,
        preexec_fn=_limited(10_000),
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    line = one_line_error(res, output, "file-size limit", "10000 bytes")
    assert ".tmp-" not in line
    assert list(out.iterdir()) == [] and sha(exp) == before


@pytest.mark.parametrize("suffix", [".h5", ".tif"])
def test_a_stack_of_unknown_length_that_passes_the_file_size_limit_is_removed(suffix, tmp_path):
    """No size known in advance, so nothing to refuse up front: the write fails half-way (EFBIG
    inside libhdf5, a short write inside tifffile) and is one FileTooLargeError, no file left."""
    code = (
        "import numpy as np; from radiokit.io import StackWriter, FileTooLargeError\n"
        "try:\n"
        f"    with StackWriter({str(tmp_path / ('s' + suffix))!r}, (256, 256)) as w:\n"
        "        for i in range(12): w.append(np.full((256, 256), i, np.float32))\n"
        "except FileTooLargeError as exc:\n"
        "    print(exc)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, preexec_fn=_limited(300_000))
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().endswith(
        "larger than the file-size limit (300000 bytes); nothing was written (the partial output was removed)"
    ), res.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_names_that_are_not_utf8_print_under_a_strict_utf8_terminal(tmp_path):
    """Under a UTF-8 locale Python's stdout is strict (``PYTHONIOENCODING=utf-8`` makes it so
    here): printing a Latin-1 name after the work failed the command, exit code 2, with the output
    written. Each name prints, its odd bytes as \\xNN (as radiokit records them), errors too."""
    exp = synthetic(_non_utf8(tmp_path, b"exp\xff.h5"), shape=(32, 40))
    out = _non_utf8(tmp_path, b"o\xfe.h5")
    strict = {"PYTHONIOENCODING": "utf-8"}
    res = run("calibrate", "--experiment", exp, "-o", out, env=strict)
    assert res.returncode == 0 and "/o\\xfe.h5\n" in res.stdout, (res.stdout, res.stderr)
    res = run("info", exp, env=strict)
    assert res.returncode == 0 and res.stdout.splitlines()[0].endswith("exp\\xff.h5"), (res.stdout, res.stderr)
    tif = out.with_suffix(".tif")
    res = run("correct", exp, "-q", "--cal", out, "-o", tif, env=strict)
    assert res.returncode == 0 and "-> " + str(tmp_path) + "/o\\xfe.tif (log)" in res.stdout, (res.stdout, res.stderr)
    assert read(tif).n == 3
    one_line_error(run("correct", exp, "-q", "--cal", out, "-o", tif, env=strict), "o\\xfe.tif", "--overwrite")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGQUIT])
def test_process_on_dask_interrupted_leaves_no_temporaries_and_no_workers(tmp_path, sig):
    """Ctrl-C goes to the terminal's whole process group (Ctrl-\\ and SIGHUP too): the Dask
    workers died mid-file, each printing tracebacks (SIGQUIT: dumping core) and leaving its
    temporary results folder. Now the command stops them: one line, exit code 128 + the signal's
    number, no temporary, no process of the run left."""
    a, b = (synthetic(tmp_path / name, shape=(384, 384), n_per_step=2, noise=30.0) for name in ("a.h5", "b.h5"))
    out = tmp_path / "many"
    proc = _process_from_a_terminal(a, b, out, workers=4)
    try:
        t_end = time.monotonic() + 120
        while not list(out.glob(".*.tmp-*")) and proc.poll() is None and time.monotonic() < t_end:
            time.sleep(0.01)
        workers = subprocess.run(
            ["pgrep", "-P", str(proc.pid), "-f", "multiprocessing"], capture_output=True, text=True
        )
        assert list(out.glob(".*.tmp-*")), "the run ended before its temporary folders were seen"
        os.killpg(proc.pid, sig)  # Ctrl-C or Ctrl-\: the whole group, as the terminal sends it
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + sig, err
    assert err.strip() == "radiokit process: interrupted; no partial output was left", err
    # the workers: two (one per file, though four were asked), and none outlives the command
    assert len(workers.stdout.split()) == 2 + 1, workers.stdout  # and multiprocessing's resource tracker
    t_end, left = time.monotonic() + 20, ["?"]
    while left and time.monotonic() < t_end:  # multiprocessing's resource tracker ends last, by itself
        left = subprocess.run(["pgrep", "-a", "-s", str(proc.pid)], capture_output=True, text=True).stdout.splitlines()
        time.sleep(0.05)
    assert left == [], left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.h5"]  # `many/` it made: gone too


def _processes(field: int, value: int) -> list[tuple[int, str]]:
    """Live processes (pid, command line) whose /proc stat field ``field`` (3 the parent, 5 the
    session) is ``value``. Zombies are left out: dead, only not yet reaped by whoever adopted them."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat_fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        if stat_fields[0] != "Z" and int(stat_fields[field - 2]) == value:
            found.append((int(entry.name), cmdline))
    return found


@pytest.mark.parametrize("to", ["group", "parent"])
def test_process_on_dask_interrupted_while_its_cluster_starts(to, tmp_path):
    """The local cluster started with SIGINT ignored in the whole process, so that its workers
    inherited it: a Ctrl-C (to the terminal's process group, or `kill -INT` to the command alone)
    while the workers started was lost, and the run went on to its end with exit code 0. Now it
    ends the run: exit code 130, one line, nothing written, no process of the run left."""
    data = tmp_path / "data"
    data.mkdir()
    a, b = (synthetic(data / name) for name in ("a.h5", "b.h5"))
    out = data / "many"
    proc = _process_from_a_terminal(a, b, out, workers=2)
    try:
        # the cluster is starting once a worker process exists: multiprocessing spawns each one
        t_end, workers = time.monotonic() + 60, []
        while not workers and proc.poll() is None and time.monotonic() < t_end:
            workers = [pid for pid, cmd in _processes(3, proc.pid) if "spawn_main" in cmd]
            time.sleep(0.01)
        assert workers, "no worker process was seen starting"
        # `-o`'s folder is made once the cluster is up and the client connected: not yet
        assert not out.exists(), "the cluster had started before the signal was sent"
        (os.killpg if to == "group" else os.kill)(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert err.strip() == "radiokit process: interrupted; no partial output was left", err
    t_end, left = time.monotonic() + 10, ["?"]
    while left and time.monotonic() < t_end:  # multiprocessing's resource tracker ends last, by itself
        left = _processes(5, proc.pid)
        time.sleep(0.05)
    assert left == [], left
    assert sorted(p.name for p in data.iterdir()) == ["a.h5", "b.h5"]


_CLUSTER_INTERRUPTED = """
import json, os, signal, sys, threading, time
from pathlib import Path
from radiokit import pipeline

def children():
    out = []
    for e in Path("/proc").iterdir():
        try:
            f = (e / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if e.name.isdigit() and int(f[1]) == os.getpid() and f[0] != "Z":
            out.append(int(e.name))
    return out

def worker_seen():
    for p in children():
        try:
            if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes():
                return True
        except OSError:
            pass
    return False

def fire():
    t_end = time.monotonic() + 60
    while not worker_seen() and time.monotonic() < t_end:
        time.sleep(0.01)
    os.kill(os.getpid(), signal.SIGINT)

threading.Thread(target=fire, daemon=True).start()
try:
    pipeline._local_cluster(2)
    outcome = "returned"
except KeyboardInterrupt:
    outcome = "interrupted"
t_end = time.monotonic() + 10
while time.monotonic() < t_end:  # what is still running once the interrupt is out
    starting = [t.name for t in threading.enumerate() if t.name == "radiokit local cluster"]
    workers = [p for p in children() if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
    if not starting and not workers:
        break
    time.sleep(0.05)
print(json.dumps({"outcome": outcome, "starting": starting, "workers": workers}))
"""


def test_a_cluster_interrupted_while_it_starts_is_stopped_before_the_interrupt_goes_on():
    """In-process view of the test above, for a caller that catches the interrupt (a notebook):
    a Ctrl-C while ``_local_cluster`` starts must wait for the start and stop the cluster before
    the KeyboardInterrupt goes on. Waiting with ``Thread.join`` did not: a join cut short by the
    interrupt marks the thread finished (CPython 3.11), so the second join returned at once and
    the cluster, started a moment later, kept running with its workers (the CLI looked right only
    because Dask's exit hook closed it)."""
    res = subprocess.run(
        [sys.executable, "-c", _CLUSTER_INTERRUPTED],
        preexec_fn=_as_from_a_terminal,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert got == {"outcome": "interrupted", "starting": [], "workers": []}, (got, res.stderr[-2000:])


@pytest.mark.parametrize("kind", ["fifo", "device"])
@pytest.mark.parametrize("cmd", ["calibrate", "correct-tiff", "register-png"])
def test_an_output_that_is_a_fifo_or_a_device_is_refused_even_with_overwrite(cmd, kind, experiment, images, tmp_path):
    """``-o`` a named pipe (or ``-o /dev/null``, here through a symlink): with --overwrite the
    output was written beside it and renamed over it, the FIFO replaced by a regular file. One
    line instead, before any work, and the FIFO or the link left as it was."""
    args = _commands(experiment, images, tmp_path / "out")[cmd]
    out = Path(args[-1])
    if kind == "fifo":
        os.mkfifo(out)
    else:
        out.symlink_to(os.devnull)
    res = run_cli(*args, "--overwrite")
    one_line_error(res, out.name, "not a regular file", "FIFO" if kind == "fifo" else "character device")
    if kind == "fifo":
        assert stat.S_ISFIFO(out.lstat().st_mode)
    else:
        assert out.is_symlink() and os.readlink(out) == os.devnull
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["exp.h5", "fixed.tif", "moving.tif", out.name])


def test_a_scheduler_that_cannot_be_reached_leaves_no_folder(experiment, tmp_path):
    """`process a.h5 b.h5 --scheduler ADDRESS -o new/res`: the folder was made before connecting,
    and a scheduler that did not answer left `new/res/` behind, empty."""
    twin = tmp_path / "twin.h5"  # another file: one file given twice is refused before connecting
    twin.write_bytes(experiment.read_bytes())
    res = run("process", experiment, twin, "-q", "--scheduler", "no-port-here", "-o", tmp_path / "new" / "res")
    one_line_error(res, "no-port-here")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5", "twin.h5"]


def test_a_scheduler_that_does_not_answer_is_said_at_once_and_bounded(experiment, tmp_path):
    """`process --scheduler tcp://host:1` (nothing listening there) waited Dask's 30 s without a
    word, then said "Timed out trying to connect". The command says at once where it connects and
    how long it waits, and fails after that wait with one line naming the address. The address is
    a real port bound and not listening: every connection to it is refused, as at a dead host's."""
    import socket

    from radiokit.cli import build_parser

    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{closed.getsockname()[1]}"
        res = run("process", experiment, "-o", tmp_path / "res", "--scheduler", address, "--scheduler-timeout", "0.5")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 2 and "Traceback" not in res.stderr, res.stderr
    assert lines[0] == f"radiokit process: connecting to the Dask scheduler at {address} (waiting up to 0.5 s)"
    assert lines[1].startswith(f"radiokit process: Dask scheduler {address}: did not answer within 0.5 s"), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"]
    assert build_parser().parse_args(["process", "a.h5", "--scheduler", address]).scheduler_timeout == 10.0


def test_an_interrupted_correct_does_not_wait_forever_for_a_stuck_writer():
    """An interrupt unwinding ``radiokit correct`` waits for its background writer thread before
    the output is removed; a writer that never returns (seen once: a ``correct`` child stuck on a
    thread lock for six minutes after SIGTERM, most likely HDF5's library lock left taken where
    the interrupt landed) held the process forever. Now the wait after an interrupt is bounded and
    the interrupt still raised. The stuck writer is a fake (an ``append`` that blocks on an event):
    the lock race itself cannot be caused on demand."""
    import threading

    from radiokit.correct import _BackgroundWriter

    release = threading.Event()

    class Stuck:
        frame_shape, dtype = (4, 4), np.float32

        def append(self, frame, **series):
            release.wait()

    outcome = []

    def interrupted():
        try:
            with _BackgroundWriter(Stuck(), stop_wait_s=0.5) as bg:
                bg.put(bg.buffer())
                time.sleep(0.1)  # the writer has taken the frame and is stuck in append
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            outcome.append("interrupt raised")

    t = threading.Thread(target=interrupted, daemon=True)
    t.start()
    t.join(30)
    release.set()
    assert outcome == ["interrupt raised"], "the interrupted run waited for its stuck writer"


def test_an_interrupt_between_a_frames_queueing_and_its_wake_up_still_stops_the_writer(capfd):
    """A Ctrl-C landing inside ``Queue.put``, after the item is queued and before the writer
    thread is woken (``not_empty.notify()``), left the writer asleep beside a queued item: the
    stop sentinel then found the queue full, and `correct` waited its whole 10 s bound and said
    "the frame writer did not stop" (1 run in 15 of a 300-frame TIFF interrupted at a random
    moment). The writer wakes by itself now. The race is reproduced exactly: the sentinel queued
    without the wake-up, as the interrupted ``put`` leaves it."""
    from radiokit.correct import _BackgroundWriter

    class Quiet:
        frame_shape, dtype = (4, 4), np.float32

        def append(self, frame, **series):
            pass

    bg = _BackgroundWriter(Quiet(), stop_wait_s=2.0)
    time.sleep(0.05)  # the writer is asleep in get()
    with bg._queue.mutex:  # put()'s own steps, the wake-up cut off by the interrupt
        bg._queue._put(None)
        bg._queue.unfinished_tasks += 1
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        bg.__exit__(KeyboardInterrupt, KeyboardInterrupt(), None)
    assert time.perf_counter() - t0 < 1.0 and not bg._thread.is_alive()  # was: the 2 s bound, then left behind
    assert "did not stop" not in capfd.readouterr().err


def _demo_interrupted_when(out: Path, seen, sig=signal.SIGINT, preset=()) -> tuple[int, str]:
    """``radiokit demo`` (the cheapest settings) sent ``sig`` as soon as ``seen(out)`` holds."""
    proc = _cli_from_a_terminal(
        ["demo", "-q", "--binning", "4", "--coarse", "--fast", "--frames", "1", *preset, "-o", str(out)],
        subprocess.DEVNULL,
    )
    try:
        t_end = time.monotonic() + 240
        while not seen(out) and proc.poll() is None and time.monotonic() < t_end:
            time.sleep(0.01)
        assert proc.poll() is None, "the demo ended before the moment to interrupt it"
        os.killpg(proc.pid, sig)  # the whole group, as the terminal sends Ctrl-C
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_demo_interrupted_before_any_file_leaves_no_folder(sig, tmp_path):
    """Ctrl-C while the demo solved its first scene said "no partial output was left", yet left
    the folder it had claimed (its marker alone), and the next `radiokit demo` was refused:
    `exists; pass --overwrite`. A folder this run made and nothing else went into is removed.
    SIGTERM (`kill`) then killed the demo without a word: it stops as Ctrl-C does, as every
    other command does (the acquisitions' own handlers take over while they run)."""
    out = tmp_path / "demo"
    code, err = _demo_interrupted_when(out, lambda o: (o / RESULTS_MARKER).exists(), sig)
    assert code == 128 + sig, err  # as a shell reports a command the signal ended: 130 Ctrl-C, 143 SIGTERM
    assert err.strip() == "radiokit demo: interrupted; no partial output was left", err
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())


def test_demo_interrupted_mid_acquisition_says_what_it_left(tmp_path):
    """Ctrl-C once the experiment file was being written: the demo's acquisition flushes frame by
    frame (not atomic), so a partial experiment file stays in the demo's folder. The line said
    "no partial output was left"; it names the folder and how to start again instead. Waited
    for the file to hold a frame (its layout is 27 KB, with a binned frame 685 KB): a file stopped
    before its first frame is removed (it held nothing, and blocked the next run)."""
    from sim.scene import block_scene

    out = tmp_path / "demo"
    # The demo solves its scene's every step before its first frame: the seed-breast preset's
    # 45 of this test's 54 s (session 42), spent before the interrupt it is about. The block
    # (no inclusion) solves in well under a second; the acquisition, its files and the
    # interrupt's handling are the demo's own whatever the scene.
    block = block_scene().save(tmp_path / "block.toml")

    def a_frame_written(o):
        try:
            return (o / "experiment.h5").stat().st_size > 300_000
        except FileNotFoundError:
            return False

    code, err = _demo_interrupted_when(out, a_frame_written, preset=["--preset", str(block)])
    assert code == 130, err
    assert (out / "experiment.h5").exists() and (out / RESULTS_MARKER).exists()
    assert len(err.strip().splitlines()) == 1, err
    assert "no partial output" not in err and str(out) in err and "--overwrite" in err, err


def _stored_elsewhere(tmp_path, how):
    """A file whose frames live in ``frames_000001.h5``, as a detector's master file links them:
    an external link (Eiger) or a virtual dataset; or in external raw storage, here under a name
    an output could have (libhdf5 takes any)."""
    stack = np.random.default_rng(0).integers(1000, 3000, (2, 20, 30)).astype(np.uint16)
    master, data = tmp_path / "master.h5", tmp_path / "frames_000001.h5"
    if how == "raw":
        data.write_bytes(stack.tobytes())
        with h5py.File(master, "w") as f:
            f.create_dataset("frames", shape=stack.shape, dtype=stack.dtype, external=[(data.name, 0, stack.nbytes)])
        return master, data
    with h5py.File(data, "w") as f:
        f["data"] = stack
    with h5py.File(master, "w") as f:
        if how == "link":
            f["frames"] = h5py.ExternalLink(data.name, "/data")
        else:
            layout = h5py.VirtualLayout(shape=stack.shape, dtype=stack.dtype)
            layout[:] = h5py.VirtualSource(data.name, "data", shape=stack.shape)
            f.create_virtual_dataset("frames", layout)
    return master, data


@pytest.mark.parametrize("how", ["link", "virtual", "raw"])
def test_an_output_onto_the_file_an_inputs_frames_live_in_is_refused(how, tmp_path, monkeypatch):
    """With --allow-external an input's frames are read from another file, which is as much an
    input: `correct master.h5 --dataset frames --allow-external -o frames_000001.h5 --overwrite`
    replaced the detector's frames with the corrected ones (only master.h5 was compared)."""
    monkeypatch.chdir(tmp_path)  # libhdf5 finds external raw files from the working directory
    master, data = _stored_elsewhere(tmp_path, how)
    darks, flats, cal = tmp_path / "d.tif", tmp_path / "f.tif", tmp_path / "cal.h5"
    tifffile.imwrite(darks, np.full((2, 20, 30), 100, np.uint16), photometric="minisblack")
    tifffile.imwrite(flats, np.full((2, 20, 30), 3800, np.uint16), photometric="minisblack")
    assert run_cli("calibrate", "--dark", darks, "--flat", flats, "-o", cal, "-q").returncode == 0
    before = sha(data)
    given = [master, "--dataset", "frames", "--allow-external"]
    one_line_error(run_cli("correct", *given, "--cal", cal, "-o", data, "-q", "--overwrite"), data.name, "input")
    one_line_error(run_cli("register", master, *given, "--moving-frame", "1", "-o", data, "--overwrite"), data.name)
    one_line_error(run_cli("calibrate", "--dark", *given, "--flat", flats, "-o", data, "--overwrite"), data.name)
    assert sha(data) == before


@pytest.mark.parametrize("how", ["link", "virtual", "raw"])
def test_the_library_refuses_an_output_onto_the_file_an_inputs_frames_live_in(how, tmp_path, monkeypatch):
    """The check was the CLI's alone: `correct_files(['master.h5'], cal, 'frames_000001.h5',
    dataset='frames', allow_external=True, overwrite=True)` replaced the detector's frames.
    check_output, which every writer calls (correct_files, write_registration, atomic_path),
    now refuses it itself."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files
    from radiokit.io import OutputError, check_output

    monkeypatch.chdir(tmp_path)
    master, data = _stored_elsewhere(tmp_path, how)
    cal = Calibration.from_frames(np.full((3, 20, 30), 100, np.uint16), np.full((3, 20, 30), 3800, np.uint16))
    before = sha(data)
    with pytest.raises(OutputError, match=data.name):
        correct_files([master], cal, data, dataset="frames", allow_external=True, overwrite=True, progress=False)
    with pytest.raises(OutputError, match=f"{data.name}.*{master.name}"):
        check_output(data, overwrite=True, inputs=[master])
    with pytest.raises(OutputError, match=data.name), atomic_path(data, overwrite=True, inputs=[master]) as tmp:
        tmp.write_bytes(b"x")
    assert sha(data) == before


def _virtual(path, source, stack, name="data"):
    with h5py.File(path, "w") as f:
        layout = h5py.VirtualLayout(shape=stack.shape, dtype=stack.dtype)
        layout[:] = h5py.VirtualSource(source, name, shape=stack.shape)
        f.create_virtual_dataset("frames", layout)


def test_a_virtual_sources_printf_name_is_read_as_libhdf5_reads_it(tmp_path):
    """libhdf5 reads a source file name printf-style: `pct_100%%.h5` is the file `pct_100%.h5`,
    which data_files did not find, so `-o 'pct_100%.h5' --overwrite` replaced it; a `%b` (a
    block number, one file per block of an unlimited mapping) names every `blk_<digits>.h5`."""
    from radiokit.io import data_files

    stack = np.zeros((2, 4, 5), np.uint16)
    with h5py.File(tmp_path / "pct_100%.h5", "w") as f:
        f["data"] = stack
    _virtual(tmp_path / "vpct.h5", "pct_100%%.h5", stack)
    assert np.array_equal(h5py.File(tmp_path / "vpct.h5")["frames"][:], stack)  # as libhdf5 reads it
    assert data_files(tmp_path / "vpct.h5", allow_external=True) == [tmp_path / "pct_100%.h5"]
    for name in ("blk_0.h5", "blk_17.h5", "blk_x.h5", "blk_%b.h5"):
        with h5py.File(tmp_path / name, "w") as f:
            f["data"] = stack[:1]
    with h5py.File(tmp_path / "vblk.h5", "w", libver="latest") as f:
        vsp = h5py.h5s.create_simple((2, 4, 5), (h5py.h5s.UNLIMITED, 4, 5))
        vsp.select_hyperslab(start=(0, 0, 0), stride=(1, 1, 1), count=(h5py.h5s.UNLIMITED, 1, 1), block=(1, 4, 5))
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_layout(h5py.h5d.VIRTUAL)
        dcpl.set_virtual(vsp, b"blk_%b.h5", b"data", h5py.h5s.create_simple((1, 4, 5)))
        h5py.h5d.create(f.id, name=b"frames", tid=h5py.h5t.NATIVE_UINT16, space=vsp, dcpl=dcpl)
    found = sorted(p.name for p in data_files(tmp_path / "vblk.h5", allow_external=True))
    assert found == ["blk_0.h5", "blk_17.h5"], found


def test_a_long_chain_of_external_links_is_followed_to_its_end(tmp_path):
    """libhdf5 follows a chain of external links (up to 16 traversals by default); data_files
    stopped after 5 files, so the 6th, the one the frames were read from, could be overwritten."""
    from radiokit.io import data_files

    stack = np.zeros((2, 4, 5), np.uint16)
    for i in range(8, 0, -1):
        with h5py.File(tmp_path / f"l{i}.h5", "w") as f:
            f["x"] = stack if i == 8 else h5py.ExternalLink(f"l{i + 1}.h5", "/x")
    with h5py.File(tmp_path / "chain.h5", "w") as f:
        f["frames"] = h5py.ExternalLink("l1.h5", "/x")
    assert np.array_equal(h5py.File(tmp_path / "chain.h5")["frames"][:], stack)
    found = {p.name for p in data_files(tmp_path / "chain.h5", allow_external=True)}
    assert found == {f"l{i}.h5" for i in range(1, 9)}, found
    with h5py.File(tmp_path / "l8.h5", "a") as f:  # a loop ends too
        del f["x"]
        f["x"] = h5py.ExternalLink("l1.h5", "/x")
    assert len(data_files(tmp_path / "chain.h5", allow_external=True)) == 8


@pytest.mark.parametrize(
    "how, prefix",
    [  # as libhdf5 2.0.0 reads each (measured): a list for links and sources, a leading ${ORIGIN} for raw files
        ("link", "{tmp}/nowhere:{tmp}/data"),
        ("virtual", "{tmp}/nowhere:{tmp}/data"),
        ("raw", "${{ORIGIN}}/../data"),
    ],
)
def test_libhdf5s_search_prefixes_are_followed(how, prefix, tmp_path, monkeypatch):
    """HDF5_EXT_PREFIX (external links), HDF5_VDS_PREFIX (virtual sources) and
    HDF5_EXTFILE_PREFIX (external raw files) send libhdf5 to other folders (a `:`-separated
    list, `${ORIGIN}` the file's own), where data_files did not look: `-o ../data/frames.h5
    --overwrite` replaced the frames."""
    from radiokit.io import data_files

    stack = np.arange(40, dtype=np.uint16).reshape(2, 4, 5)
    (tmp_path / "m").mkdir()
    (tmp_path / "data").mkdir()
    master, data = tmp_path / "m" / "master.h5", tmp_path / "data" / "frames.h5"
    if how == "raw":
        data.write_bytes(stack.tobytes())
        with h5py.File(master, "w") as f:
            f.create_dataset("frames", shape=stack.shape, dtype=stack.dtype, external=[("frames.h5", 0, stack.nbytes)])
    else:
        with h5py.File(data, "w") as f:
            f["data"] = stack
        if how == "link":
            with h5py.File(master, "w") as f:
                f["frames"] = h5py.ExternalLink("frames.h5", "/data")
        else:
            _virtual(master, "frames.h5", stack)
    env = {"link": "HDF5_EXT_PREFIX", "virtual": "HDF5_VDS_PREFIX", "raw": "HDF5_EXTFILE_PREFIX"}[how]
    prefix = prefix.format(tmp=tmp_path)
    # libhdf5 reads HDF5_EXTFILE_PREFIX once, when it starts: asked in a process of its own
    read = "import h5py, sys; print(int(h5py.File(sys.argv[1])['frames'][:].sum()))"
    res = subprocess.run(
        [sys.executable, "-c", read, master], env={**os.environ, env: prefix}, cwd=master.parent, capture_output=True
    )
    assert res.stdout.strip() == str(int(stack.sum())).encode(), res.stderr  # libhdf5 finds it so
    monkeypatch.chdir(master.parent)
    monkeypatch.setenv(env, prefix)
    assert data.resolve() in [p.resolve() for p in data_files(master, allow_external=True)]


def test_an_output_onto_a_file_of_a_multi_file_ome_tiff_is_refused(tmp_path):
    """s38a: a multi-file OME-TIFF read with allow_external takes planes from the files beside
    it; like an HDF5 link's target, an output onto one of them is refused, whether or not the
    run follows them (as data_files is for HDF5)."""
    from test_io_formats import _multifile_ome

    from radiokit.io import OutputError, check_output, data_files

    first, second = _multifile_ome(tmp_path, np.arange(4 * 6 * 8, dtype=np.uint16).reshape(4, 6, 8))
    assert data_files(first, allow_external=True) == [second]
    before = sha(second)
    with pytest.raises(OutputError, match=f"{second.name}.*{first.name}"):
        check_output(second, overwrite=True, inputs=[first])
    res = run_cli("register", first, first, "--allow-external", "--moving-frame", "1", "-o", second, "--overwrite")
    one_line_error(res, second.name)
    assert sha(second) == before


def _calibration_file(tmp_path, shape=(20, 30)) -> Path:
    darks, flats, cal = tmp_path / "d.tif", tmp_path / "f.tif", tmp_path / "cal.h5"
    tifffile.imwrite(darks, np.full((2, *shape), 100, np.uint16), photometric="minisblack")
    tifffile.imwrite(flats, np.full((2, *shape), 3800, np.uint16), photometric="minisblack")
    assert run_cli("calibrate", "--dark", darks, "--flat", flats, "-o", cal, "-q").returncode == 0
    return cal


def test_a_link_name_that_is_not_utf8_does_not_end_the_listing_of_an_inputs_data_files(tmp_path, monkeypatch):
    """h5py cannot decode a link name that is not UTF-8, and data_files ended its listing there:
    the frames' own external link, listed after it, was never seen, and `correct master.h5
    --dataset entry/data --allow-external -o frames.h5 --overwrite` replaced the input's frames."""
    from radiokit.io import data_files

    monkeypatch.chdir(tmp_path)
    stack = np.arange(2 * 20 * 30, dtype=np.uint16).reshape(2, 20, 30) + 200
    frames, master = tmp_path / "frames.h5", tmp_path / "master.h5"
    with h5py.File(frames, "w") as f:
        f["data"] = stack
    odd = tmp_path / os.fsdecode(b"fr\xffames.h5")  # a file whose name is not UTF-8 either
    with h5py.File(odd, "w") as f:
        f["data"] = stack
    with h5py.File(master, "w") as f:
        f.id.links.create_soft(b"a\xff\xfe", b"/nowhere")  # listed before entry/ (names in byte order)
        f.create_group(b"a\xfe")
        f.id.links.create_external(b"a\xfe/odd", b"fr\xffames.h5", b"/data")
        f["entry/data"] = h5py.ExternalLink(frames.name, "/data")
    assert np.array_equal(h5py.File(master)["entry/data"][:], stack)  # libhdf5 reads the frames so
    assert {p.resolve() for p in data_files(master, allow_external=True)} == {frames, odd}
    cal, before = _calibration_file(tmp_path), sha(frames)
    given = [master, "--cal", cal, "--dataset", "entry/data", "--allow-external", "-q", "--overwrite"]
    one_line_error(run_cli("correct", *given, "-o", frames), frames.name, "input")
    one_line_error(run_cli("correct", *given, "-o", odd), "input")
    assert sha(frames) == before


def test_a_virtual_source_named_in_bytes_that_are_not_utf8_is_listed(tmp_path, monkeypatch):
    """h5py's virtual_sources() raised UnicodeDecodeError on such a source file name, which ended
    the listing: the source is a file the frames are read from all the same."""
    from radiokit.io import data_files

    monkeypatch.chdir(tmp_path)
    source = tmp_path / os.fsdecode(b"s\xff.h5")
    with h5py.File(source, "w") as f:
        f["data"] = np.arange(3)
    master = tmp_path / "master.h5"
    with h5py.File(master, "w") as f:
        space = h5py.h5s.create_simple((3,))
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_layout(h5py.h5d.VIRTUAL)
        dcpl.set_virtual(space, b"s\xff.h5", b"data", h5py.h5s.create_simple((3,)))
        h5py.h5d.create(f.id, name=b"frames", tid=h5py.h5t.NATIVE_INT64, space=space, dcpl=dcpl)
        f["later"] = h5py.ExternalLink("frames.h5", "/data")
    (tmp_path / "frames.h5").write_bytes(b"")
    assert list(h5py.File(master)["frames"][:]) == [0, 1, 2]  # libhdf5 reads the source so
    assert {p.resolve() for p in data_files(master, allow_external=True)} == {source, tmp_path / "frames.h5"}


def test_an_input_whose_links_cannot_all_be_listed_refuses_an_existing_output(tmp_path):
    """A link table libhdf5 cannot walk (a corrupt B-tree) ended the listing quietly, while
    libhdf5 still read the frames through a link the walk never reached: an output onto them was
    allowed. Where the listing cannot be completed, an output that exists is refused, naming the
    input and why; a new output, which can be no input's file, is not."""
    import re

    from radiokit.io import OutputError, atomic_dir, check_output

    frames, master = tmp_path / "frames.h5", tmp_path / "master.h5"
    with h5py.File(frames, "w") as f:
        f["data"] = np.arange(3)
    with h5py.File(master, "w") as f:
        for i in range(3):
            f[f"a/x{i}"] = np.arange(3)
        f["z/data"] = h5py.ExternalLink(str(frames), "/data")
    raw = bytearray(master.read_bytes())
    tree = [m.start() for m in re.finditer(b"TREE", raw)][1]  # group a's B-tree
    raw[tree : tree + 4] = b"XXXX"
    master.write_bytes(bytes(raw))
    with h5py.File(master, "r") as f:  # the walk fails, libhdf5 reads the frames all the same
        with pytest.raises(RuntimeError):
            f.id.links.visit(lambda name, info: None, info=True)
        assert list(f["z/data"][:]) == [0, 1, 2]
    before = sha(frames)
    with pytest.raises(OutputError, match=f"{master.name}.*cannot be listed"):
        check_output(frames, overwrite=True, inputs=[master])
    results = tmp_path / "results"
    with atomic_dir(results) as tmp:
        (tmp / "results.json").write_text("{}")
    with pytest.raises(OutputError, match=f"{master.name}.*cannot be listed"):
        check_output(results, overwrite=True, inputs=[master], folder=True)
    check_output(tmp_path / "new.h5", inputs=[master])  # nothing there to lose
    assert sha(frames) == before


def test_a_chain_of_external_links_longer_than_pythons_recursion_limit_is_listed(tmp_path):
    """data_files followed a chain file by file recursively: past ~980 files Python's
    RecursionError, caught as an ordinary error, ended the listing quietly."""
    from radiokit.io import data_files

    n = 1200
    for i in range(n, 0, -1):
        with h5py.File(tmp_path / f"c{i}.h5", "w") as f:
            f["x"] = np.arange(3) if i == n else h5py.ExternalLink(f"c{i + 1}.h5", "/x")
    with h5py.File(tmp_path / "c0.h5", "w") as f:
        f["x"] = h5py.ExternalLink("c1.h5", "/x")
    found = data_files(tmp_path / "c0.h5", allow_external=True)
    assert len(found) == n and (tmp_path / f"c{n}.h5") in found


@pytest.mark.parametrize("how", ["link", "virtual"])
def test_an_absolute_name_that_is_missing_is_looked_for_in_the_working_directory(how, tmp_path, monkeypatch):
    """libhdf5, not finding an external link's (or a virtual source's) absolute file name, tries
    its bare name beside the referring file and then in the working directory; data_files missed
    the latter, so a frames.h5 in the working directory, read as the input's frames, was replaced
    by `-o frames.h5 --overwrite`."""
    from radiokit.io import data_files

    (tmp_path / "master").mkdir()
    (tmp_path / "cwd").mkdir()
    stack = np.arange(2 * 20 * 30, dtype=np.uint16).reshape(2, 20, 30) + 100
    frames, master = tmp_path / "cwd" / "frames.h5", tmp_path / "master" / "master.h5"
    with h5py.File(frames, "w") as f:
        f["data"] = stack
    missing = str(tmp_path / "nonexistent" / "frames.h5")
    if how == "link":
        with h5py.File(master, "w") as f:
            f["entry/data"] = h5py.ExternalLink(missing, "/data")
    else:
        with h5py.File(master, "w") as f:
            layout = h5py.VirtualLayout(shape=stack.shape, dtype=stack.dtype)
            layout[:] = h5py.VirtualSource(missing, "data", shape=stack.shape)
            f.create_virtual_dataset("entry/data", layout)
    cal = _calibration_file(tmp_path)
    monkeypatch.chdir(frames.parent)
    assert np.array_equal(h5py.File(master)["entry/data"][:], stack)  # libhdf5 reads ./frames.h5
    assert [p.resolve() for p in data_files(master, allow_external=True)] == [frames]
    before = sha(frames)
    given = [master, "--cal", cal, "--dataset", "entry/data", "--allow-external", "-q", "--overwrite"]
    one_line_error(run_cli("correct", *given, "-o", "frames.h5"), "frames.h5", "input")
    assert sha(frames) == before


def test_a_file_output_that_appears_during_the_run_is_not_replaced_without_overwrite(tmp_path):
    """The output was checked at the start only, and the final rename replaced whatever was there
    by then: two `correct` runs to one name, neither with --overwrite, both said done and one's
    result was lost. The commit now takes only a free name."""
    from radiokit.io import OutputError

    out = tmp_path / "out.h5"
    with pytest.raises(OutputError, match="appeared during the run") as caught:
        with atomic_path(out) as tmp:
            tmp.write_bytes(b"mine")
            out.write_bytes(b"another run's")
    assert isinstance(caught.value, FileExistsError)
    assert out.read_bytes() == b"another run's"
    no_temporaries(tmp_path)
    link = tmp_path / "link.h5"  # a symbolic link (dangling too) is something there as well
    with pytest.raises(OutputError, match="appeared during the run"):
        with atomic_path(link) as tmp:
            tmp.write_bytes(b"mine")
            link.symlink_to(tmp_path / "nowhere.h5")
    assert link.is_symlink() and not (tmp_path / "nowhere.h5").exists()
    with atomic_path(out, overwrite=True) as tmp:  # asked for: replaced
        tmp.write_bytes(b"mine")
    assert out.read_bytes() == b"mine"
    no_temporaries(tmp_path)


def test_two_corrects_to_one_new_name_without_overwrite_do_not_both_succeed(experiment, tmp_path):
    """The reviewer's race, end to end: of two `correct` runs started together onto one new
    name, neither with --overwrite, one may write it; the other says so and exits non-zero."""
    out = tmp_path / "race.h5"
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "radiokit.cli", "correct", str(experiment), "-q", "-o", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONWARNINGS": "ignore"},
        )
        for _ in range(2)
    ]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    err = next(e for rc, e in results if rc)
    assert "race.h5" in err and ("appeared during the run" in err or "exists" in err), err
    assert read(out).n == 3  # one run's whole output
    no_temporaries(tmp_path)


@pytest.mark.parametrize("what", ["file", "folder with a file", "empty folder"])
def test_a_results_folder_that_appears_during_the_run_is_not_replaced_without_overwrite(what, tmp_path):
    """`process` renamed whatever stood at the output name by its end aside and deleted it: a
    folder the user made there during the run was lost. Without --overwrite the folder is only
    put where nothing is (an empty folder, which holds nothing to lose, gives way)."""
    from radiokit.io import OutputError, atomic_dir

    out = tmp_path / "results"

    def appear():
        if what == "file":
            out.write_bytes(b"notes")
        else:
            out.mkdir()
            if what == "folder with a file":
                (out / "notes.txt").write_text("mine")

    if what == "empty folder":
        with atomic_dir(out) as tmp:
            (tmp / "results.json").write_text("{}")
            appear()
        assert (out / "results.json").exists()
        return
    with pytest.raises(OutputError, match="appeared during the run"):
        with atomic_dir(out) as tmp:
            (tmp / "results.json").write_text("{}")
            appear()
    if what == "file":
        assert out.read_bytes() == b"notes"
    else:
        assert [p.name for p in out.iterdir()] == ["notes.txt"]
    no_temporaries(tmp_path)


def test_files_added_to_a_results_folder_during_an_overwrite_are_not_deleted(experiment, tmp_path):
    """With --overwrite, the old results folder was checked for files radiokit did not write at
    the start only: a file the user put into it during the run was deleted with it."""
    from radiokit.io import OutputError, atomic_dir

    out = tmp_path / "results"
    with atomic_dir(out) as tmp:
        (tmp / "results.json").write_text("{}")
    before = tree_sha(out)
    with pytest.raises(OutputError, match="notes.txt"):
        with atomic_dir(out, overwrite=True) as tmp:
            (tmp / "results.json").write_text('{"new": 1}')
            (out / "notes.txt").write_text("mine")
    assert tree_sha(out) == {**before, "notes.txt": sha(out / "notes.txt")}
    no_temporaries(tmp_path)
    (out / "notes.txt").unlink()
    with atomic_dir(out, overwrite=True) as tmp:  # and without them it is replaced
        (tmp / "results.json").write_text('{"new": 1}')
    assert (out / "results.json").read_text() == '{"new": 1}'
    no_temporaries(tmp_path)


def test_an_output_that_appears_is_not_replaced_where_renameat2_is_missing(tmp_path, monkeypatch):
    """Where the kernel or C library has no renameat2 (not Linux, old glibc), a file is
    hard-linked into place, which fails on a name taken; a folder is renamed, which fails onto a
    file or a folder holding anything."""
    from radiokit.io import OutputError, _atomic, atomic_dir

    monkeypatch.setattr(_atomic, "_renameat2", lambda: None)
    out = tmp_path / "out.h5"
    with pytest.raises(OutputError, match="appeared during the run"):
        with atomic_path(out) as tmp:
            tmp.write_bytes(b"mine")
            out.write_bytes(b"another run's")
    assert out.read_bytes() == b"another run's"
    new = tmp_path / "new.h5"
    with atomic_path(new) as tmp:
        tmp.write_bytes(b"mine")
    assert new.read_bytes() == b"mine" and new.stat().st_nlink == 1
    folder = tmp_path / "results"
    with pytest.raises(OutputError, match="appeared during the run"):
        with atomic_dir(folder) as tmp:
            (tmp / "results.json").write_text("{}")
            folder.mkdir()
            (folder / "notes.txt").write_text("mine")
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]
    no_temporaries(tmp_path)


def _linked_master(tmp_path, kind):
    """``Y/master.h5``, a symbolic link to ``X/master.h5``, whose frames (an external link, or a
    virtual dataset's source) are the relative ``frames.h5``, present in X only."""
    (tmp_path / "X").mkdir()
    (tmp_path / "Y").mkdir()
    stack = np.full((3, 8, 8), 1000, np.uint16)
    with h5py.File(tmp_path / "X" / "frames.h5", "w") as f:
        f["data"] = stack
    if kind == "link":
        with h5py.File(tmp_path / "X" / "master.h5", "w") as f:
            f["frames"] = h5py.ExternalLink("frames.h5", "/data")
    else:
        _virtual(tmp_path / "X" / "master.h5", "frames.h5", stack)
    os.symlink(tmp_path / "X" / "master.h5", tmp_path / "Y" / "master.h5")
    with h5py.File(tmp_path / "Y" / "master.h5", "r") as f:  # libhdf5 reads them from X
        assert np.array_equal(f["frames"][:], stack)
    return tmp_path / "Y" / "master.h5", stack


@pytest.mark.parametrize("kind", ["link", "virtual"])
def test_a_symlinked_masters_data_files_beside_its_real_path_are_listed(kind, tmp_path):
    """libhdf5 looks for a relative link target (or virtual source) beside the file's real path
    too: ``Y/master.h5 -> X/master.h5`` reads ``X/frames.h5``, which data_files missed, so
    `correct Y/master.h5 --allow-external -o X/frames.h5 --overwrite` replaced the input's frames."""
    from radiokit.io import data_files

    master, _ = _linked_master(tmp_path, kind)
    assert data_files(master, allow_external=True) == [tmp_path / "X" / "frames.h5"]
    before = sha(tmp_path / "X" / "frames.h5")
    res = run_cli(
        "correct",
        master,
        "--dataset",
        "frames",
        "--allow-external",
        "-q",
        "-o",
        tmp_path / "X" / "frames.h5",
        "--overwrite",
    )
    one_line_error(res, "frames.h5", "frames are read from")
    assert sha(tmp_path / "X" / "frames.h5") == before


def test_a_symlinked_masters_virtual_source_beside_its_real_path_is_not_said_missing(tmp_path):
    master, stack = _linked_master(tmp_path, "virtual")
    np.testing.assert_array_equal(read(master, dataset="frames", allow_external=True).data, stack)


def test_a_fifo_input_is_refused_not_waited_on(experiment, tmp_path):
    """The listing of an input's data files opened a FIFO to read its first bytes, which waits
    for a writer: `correct fifo.tif --cal cal.h5` hung before the reader's refusal."""
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", experiment, "-o", cal).returncode == 0
    os.mkfifo(tmp_path / "ff.tif")
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "radiokit.cli",
            "correct",
            tmp_path / "ff.tif",
            "--cal",
            cal,
            "-q",
            "-o",
            tmp_path / "p.h5",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    one_line_error(res, "ff.tif", "not a regular file")


@pytest.mark.parametrize("added", ["empty folder", "link to a folder"])
def test_a_folder_added_to_an_old_results_folder_is_refused_as_a_file_is(added, experiment, tmp_path):
    """--overwrite refused an old results folder holding a file radiokit did not write, but
    deleted one holding an empty folder or a symbolic link to a folder, which it did not look at."""
    out = tmp_path / "res"
    previous = _results_folder(out)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if added == "empty folder":
        (out / "mine").mkdir()
    else:
        os.symlink(elsewhere, out / "mine")
    res = run_cli("process", experiment, "-o", out, "-q", "--overwrite", *ROI)
    one_line_error(res, "mine", "radiokit did not write")
    assert tree_sha(out) == previous and os.path.lexists(out / "mine")


def test_an_output_under_a_dangling_symlink_is_not_said_to_be_under_a_file(experiment, tmp_path):
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    res = run_cli("calibrate", "--experiment", experiment, "-o", tmp_path / "dangling" / "cal.h5")
    line = one_line_error(res, "dangling", "does not exist")
    assert "is a file" not in line


@pytest.mark.parametrize("overwrite", [False, True])
def test_register_never_removes_what_appeared_at_the_figure_name_during_the_run(
    overwrite, images, tmp_path, monkeypatch
):
    """s49rv: the previous figure, removed before the field's rename (remove_replaced), was removed
    whatever stood at --png's name by then: without --overwrite a file made there during the run
    (another run's figure) was deleted, and with it a folder and all it held; with --overwrite a
    folder too, which the rename's own check refused before. Kept now: the command ends on its one
    error line naming the figure, and what appeared there is as it was."""
    from radiokit import cli

    fixed, moving = images
    field, figure = tmp_path / "reg.h5", tmp_path / "reg.png"
    args = ["register", fixed, moving, "-o", field, "--png", figure] + (["--overwrite"] if overwrite else [])
    draw = cli._register_png

    def another_writes_there(path, *rest):  # while this run draws, something takes the figure's name
        figure.mkdir()
        (figure / "notes.txt").write_text("kept")
        draw(path, *rest)

    monkeypatch.setattr(cli, "_register_png", another_writes_there)
    res = run_cli(*args)
    assert (figure / "notes.txt").read_text() == "kept"
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and str(figure) in res.stderr, res.stderr
    assert overwrite or "appeared during the run" in res.stderr, res.stderr
    no_temporaries(tmp_path)


def test_register_whose_field_is_refused_at_its_rename_keeps_the_previous_figure(images, tmp_path, monkeypatch):
    """s49rv: with --overwrite, the previous figure went before the field's rename, which then
    refused what stood at -o's name by then (a folder made there during the run): the run ended
    on its error with the previous field and no figure, the user's figure lost for nothing. Both
    names are checked before anything is removed: the previous pair stays as it was."""
    import radiokit.io

    fixed, moving = images
    field, figure = tmp_path / "reg.h5", tmp_path / "reg.png"
    args = ["register", fixed, moving, "-o", field, "--png", figure, "--overwrite"]
    assert run_cli(*args).returncode in (0, 1)
    previous_figure = figure.read_bytes()
    write = radiokit.io.write_registration

    def folder_at_the_field(*args, **kwargs):  # while the field is written, after both names were checked
        field.unlink()
        field.mkdir()
        write(*args, **kwargs)

    monkeypatch.setattr(radiokit.io, "write_registration", folder_at_the_field)
    res = run_cli(*args)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and str(field) in res.stderr, res.stderr
    assert figure.read_bytes() == previous_figure and field.is_dir()
    no_temporaries(tmp_path)


def _gmsh_loaded_under(pid) -> set:
    """``pid`` and the processes it started that have gmsh's library mapped (meshing)."""
    pids = {pid}
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) in pids:
                pids.add(int(entry.name))
        except (OSError, IndexError, ValueError):
            continue
    meshing = set()
    for p in pids:
        try:
            if "libgmsh" in Path(f"/proc/{p}/maps").read_text():
                meshing.add(p)
        except OSError:
            continue
    return meshing


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_demo_interrupted_while_gmsh_meshes_stops_at_once(sig, tmp_path):
    """gmsh cannot be stopped: a stop signal's Python handler runs only when its C call returns,
    so Ctrl-C or a ``kill`` landing in ``gmsh.model.mesh.generate`` waited for the whole mesh (2.2
    s of a scene near sim.mesh.MAX_ELEMENTS, 80 000 tetrahedra, on an idle 2-core machine; 10-40 s
    under load). gmsh runs in a child process now, killed on a stop. The scene: seed-breast at
    0.22 / 1.87 mm (94 000 elements estimated, 2.8 s of gmsh); the signal lands 0.5 s after gmsh's
    library is loaded, in generate."""
    from sim.scene import load_scene

    scene = load_scene("seed-breast")
    scene.mesh.size_contact_mm = None
    scene.mesh.size_inclusion_mm, scene.mesh.size_far_mm = 0.218, 1.872
    preset = scene.save(tmp_path / "fine.toml")
    out = tmp_path / "demo"
    proc = _cli_from_a_terminal(
        ["demo", "-q", "--binning", "4", "--fast", "--frames", "1", "--preset", str(preset), "-o", str(out)],
        subprocess.DEVNULL,
    )
    try:
        t_end = time.monotonic() + 120
        while not _gmsh_loaded_under(proc.pid) and proc.poll() is None and time.monotonic() < t_end:
            time.sleep(0.02)
        assert proc.poll() is None, "the demo ended before it meshed"
        time.sleep(0.5)
        meshing = _gmsh_loaded_under(proc.pid)
        os.killpg(proc.pid, sig)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=120)
        waited = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + sig, err
    assert err.strip() == "radiokit demo: interrupted; no partial output was left", err
    assert waited < 1.0, f"{waited:.2f} s from the signal to the exit"
    assert not out.exists()
    assert not [p for p in meshing if Path(f"/proc/{p}").exists()], "gmsh left running"
