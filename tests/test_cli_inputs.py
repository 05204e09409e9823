"""What the offline commands say of the files they read: where a calibration came from, stacks
stored frames-last, ``--dataset`` over TIFF and HDF5 files mixed, and names with control
characters. Real files (tifffile, h5py) written to ``tmp_path``, run through ``main``."""

import json
import os
import re
import subprocess
import sys
from datetime import UTC, datetime

import h5py
import numpy as np
import pytest
import tifffile
from conftest import info_items, one_line_error, run_cli

from radiokit.calibrate import Calibration
from radiokit.io import ExperimentWriter, ImageKey, read

ROWS, COLS = 48, 64


def _darks_flats(n=5, seed=0):
    rng = np.random.default_rng(seed)
    darks = rng.normal(100, 2, (n, ROWS, COLS)).round().astype(np.uint16)
    flats = rng.normal(3000, 20, (n, ROWS, COLS)).round().astype(np.uint16)
    return darks, flats


def _write_h5(path, name, data):
    with h5py.File(path, "w") as f:
        f[name] = data
    return path


def _strip_experiment(path, n, rng):
    """An experiment file of ``n`` frames of 200 x 8 (a narrow strip of a panel), written frame by
    frame: 5 darks at 100 counts, 10 flats at 3000, the rest projections at 1500, noise 10 (drawn
    from ``rng``)."""
    with ExperimentWriter(path, shape=(200, 8)) as w:
        for i in range(n):
            key = ImageKey.DARK if i < 5 else ImageKey.FLAT if i < 15 else ImageKey.PROJECTION
            level = {ImageKey.DARK: 100, ImageKey.FLAT: 3000, ImageKey.PROJECTION: 1500}[key]
            w.append(rng.normal(level, 10, (200, 8)).round().astype(np.uint16), image_key=key)
    return path


def _mtime_utc(path) -> datetime:
    return datetime.fromtimestamp(os.stat(path).st_mtime, UTC).replace(microsecond=0)


# ------------------------------------------------------------------------------------------------
# 1. a calibration records the files and datasets it was read from
# ------------------------------------------------------------------------------------------------


def test_a_calibration_records_each_input_file_its_dataset_and_frames(tmp_path):
    """s50: a calibration named its files at most as given; which HDF5 dataset made it, and which
    file that was, could not be told later. Each input is recorded: as given and resolved, the
    dataset and the option naming it, the frames of each kind, its size and modification time;
    and ``info`` of the calibration shows them."""
    darks, flats = _darks_flats()
    _write_h5(tmp_path / "darks.h5", "scan/dark", darks)
    tifffile.imwrite(tmp_path / "flats_a.tif", flats[:3], photometric="minisblack")
    tifffile.imwrite(tmp_path / "flats_b.tif", flats[3:], photometric="minisblack")
    os.symlink(tmp_path / "flats_b.tif", tmp_path / "link.tif")
    out = tmp_path / "cal.h5"
    res = run_cli(
        "calibrate", "--dark", "darks.h5", "--dark-dataset", "scan/dark",
        "--flat", "flats_a.tif", "link.tif", "-o", out, "-q", cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    inputs = Calibration.load(out).provenance["inputs"]
    assert [i["path"] for i in inputs] == ["darks.h5", "flats_a.tif", "link.tif"]
    assert [i["resolved"] for i in inputs] == [str(tmp_path / n) for n in ("darks.h5", "flats_a.tif", "flats_b.tif")]
    assert [i["format"] for i in inputs] == ["hdf5", "tiff", "tiff"]
    assert [(i["dataset"], i["option"]) for i in inputs] == [
        ("scan/dark", "--dark-dataset"),
        (None, None),
        (None, None),
    ]
    assert [(i["darks"], i["flats"]) for i in inputs] == [(5, 0), (0, 3), (0, 2)]
    for i in inputs:
        assert i["size_bytes"] == os.path.getsize(i["resolved"])
        recorded = datetime.strptime(i["modified"], "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=UTC)
        assert abs((recorded - _mtime_utc(i["resolved"])).total_seconds()) <= 1
    shown = run_cli("info", out)
    assert shown.returncode == 0, shown.stderr
    assert "made from  darks.h5: dataset scan/dark (--dark-dataset), 5 darks;" in info_items(shown.stdout), shown.stdout
    assert "flats_a.tif: tiff, 3 flats;" in shown.stdout and "link.tif: tiff, 2 flats;" in shown.stdout, shown.stdout
    assert str(tmp_path / "flats_b.tif") in shown.stdout  # where the link led
    meta = json.loads(run_cli("info", "--json", out).stdout)[0]["metadata"]
    assert len(meta["made from"]) == 3


def test_one_file_of_darks_and_flats_is_one_input_with_both_counts(tmp_path):
    """An experiment-style file given as --dark and --flat is one input: 4 darks and 6 flats, not
    two entries; the dataset the reader found by the file's own layout has no option."""
    darks, flats = _darks_flats(6)
    path = tmp_path / "both.h5"
    with ExperimentWriter(path, shape=(ROWS, COLS)) as w:
        for f in darks[:4]:
            w.append(f, image_key=ImageKey.DARK)
        for f in flats:
            w.append(f, image_key=ImageKey.FLAT)
    out = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--dark", path, "--flat", path, "-o", out, "-q").returncode == 0
    (one,) = Calibration.load(out).provenance["inputs"]
    assert (one["format"], one["dataset"], one["option"]) == ("experiment", "/entry/instrument/detector/data", None)
    assert (one["darks"], one["flats"]) == (4, 6)
    # from the experiment file itself (the library's from_experiment, and calibrate --experiment)
    assert run_cli("calibrate", "--experiment", path, "-o", tmp_path / "cal2.h5", "-q").returncode == 0
    (two,) = Calibration.load(tmp_path / "cal2.h5").provenance["inputs"]
    assert (two["path"], two["darks"], two["flats"]) == (str(path), 4, 6)


def test_a_calibration_made_before_inputs_were_recorded_still_reads_and_says_so(tmp_path):
    """Old calibrations (no ``inputs``) load and correct as before; ``info`` names what they do
    record (the files as given) and that the rest is not; a crafted ``inputs`` is said unreadable,
    never a traceback."""
    darks, flats = _darks_flats()
    cal = Calibration.from_frames(darks, flats)
    del cal.provenance["inputs"]  # as radiokit wrote them before s50
    cal.provenance["dark_files"], cal.provenance["flat_files"] = ["d.tif"], ["f.tif"]
    cal.save(tmp_path / "old.h5")
    assert "inputs" not in Calibration.load(tmp_path / "old.h5").provenance
    res = run_cli("info", tmp_path / "old.h5")
    assert res.returncode == 0, res.stderr
    assert "made from  darks d.tif; flats f.tif (as given; made before radiokit recorded" in info_items(res.stdout), (
        res.stdout
    )
    cal.provenance = {k: v for k, v in cal.provenance.items() if not k.endswith("_files")} | {"inputs": "x"}
    cal.save(tmp_path / "odd.h5")
    res = run_cli("info", tmp_path / "odd.h5")
    assert res.returncode == 0 and "made from  unreadable" in info_items(res.stdout), (res.stdout, res.stderr)


def test_a_calibration_made_in_python_records_the_files_read_and_says_when_there_were_none(tmp_path):
    """s50rv1: ``Calibration.from_frames(read("darks.tif"), read("flats.h5", dataset=...))``, the
    README's Python way, recorded no inputs though the Frames name their files, and ``info`` of it
    said "made before radiokit recorded its datasets" of a calibration made that minute. The
    Frames' files are recorded as the command's are; made of plain arrays, ``info`` says so."""
    from radiokit.io import read

    darks, flats = _darks_flats()
    tifffile.imwrite(tmp_path / "darks.tif", darks, photometric="minisblack")
    _write_h5(tmp_path / "flats.h5", "scan/flat", flats[:3])
    cal = Calibration.from_frames(read(tmp_path / "darks.tif"), read(tmp_path / "flats.h5", dataset="scan/flat"))
    cal.save(tmp_path / "cal.h5")
    got = [
        (i["path"], i["format"], i["dataset"], i["darks"], i["flats"], i["size_bytes"])
        for i in Calibration.load(tmp_path / "cal.h5").provenance["inputs"]
    ]
    assert got == [
        (str(tmp_path / "darks.tif"), "tiff", None, 5, 0, os.path.getsize(tmp_path / "darks.tif")),
        (str(tmp_path / "flats.h5"), "hdf5", "scan/flat", 0, 3, os.path.getsize(tmp_path / "flats.h5")),
    ]
    res = run_cli("info", tmp_path / "cal.h5")
    assert res.returncode == 0 and "darks.tif: tiff, 5 darks" in res.stdout, (res.stdout, res.stderr)
    Calibration.from_frames(darks, flats).save(tmp_path / "arrays.h5")
    res = run_cli("info", tmp_path / "arrays.h5")
    assert res.returncode == 0, res.stderr
    assert "made before" not in res.stdout and "made from  arrays, no files" in info_items(res.stdout), res.stdout


# ------------------------------------------------------------------------------------------------
# 2. an HDF5 stack stored frames-last is refused, not read as strips
# ------------------------------------------------------------------------------------------------


def test_an_hdf5_stack_stored_frames_last_is_refused_in_one_line_and_read_as_stored_on_request(tmp_path):
    """s50: a (512, 512, 5) stack (numpy's dstack of 5 frames) was read as 512 frames of 512 x 5
    with only a warning. Refused in one line naming the file, the dataset, its shape and the way
    out; ``--narrow-frames`` reads it as stored. A stack of (n, rows, cols) frames is read as ever."""
    rng = np.random.default_rng(1)
    frames = rng.integers(1000, 3000, (5, 128, 96), dtype=np.uint16)
    path = tmp_path / "stack.h5"
    with h5py.File(path, "w") as f:
        f["scan/frames"] = np.dstack(list(frames))  # (128, 96, 5)
        f["scan/plain"] = frames
    res = run_cli("info", path, "--dataset", "scan/frames")
    one_line_error(res, "stack.h5", "scan/frames", "128x96x5", "5 frames of 128x96", "--narrow-frames")
    res = run_cli("info", "--json", path, "--dataset", "scan/frames", "--narrow-frames")
    assert res.returncode == 0, res.stderr
    assert (json.loads(res.stdout)[0]["frames"], json.loads(res.stdout)[0]["shape"]) == (128, [96, 5])
    res = run_cli("info", "--json", path, "--dataset", "scan/plain")
    assert (json.loads(res.stdout)[0]["frames"], json.loads(res.stdout)[0]["shape"]) == (5, [128, 96])
    # register reads one frame of each image: refused alike
    res = run_cli("register", path, path, "--dataset", "scan/frames", "-o", tmp_path / "f.h5")
    one_line_error(res, "stack.h5", "scan/frames", "--narrow-frames")
    assert not (tmp_path / "f.h5").exists()


def test_an_experiment_file_of_narrow_frames_is_read_as_written(tmp_path):
    """s50rv1: an experiment file (ExperimentWriter, frame by frame: (n, rows, cols) by
    construction) of 70 frames of 200 x 8 pixels (a narrow strip of a panel) was refused as a
    frames-last stack by info, correct and process, and ``process`` has no --narrow-frames
    (``correct exp.h5 --narrow-frames`` was refused too: the calibration from its darks and flats
    read it without the flag). On main it read, with a warning; it reads as written again."""
    rng = np.random.default_rng(7)
    path = _strip_experiment(tmp_path / "strip.h5", 70, rng)
    res = run_cli("info", "--json", path)
    assert res.returncode == 0, res.stderr
    assert (json.loads(res.stdout)[0]["frames"], json.loads(res.stdout)[0]["shape"]) == (70, [200, 8])
    assert read(path).data.shape == (70, 200, 8)
    res = run_cli("correct", path, "-o", tmp_path / "t.h5", "--domain", "linear", "-q")
    assert res.returncode == 0, res.stderr
    corrected = read(tmp_path / "t.h5").data
    assert corrected.shape == (55, 200, 8)
    # (1500 - 100) / (3000 - 100): the projections' transmission, within their noise
    assert abs(float(np.median(corrected)) - 1400 / 2900) < 0.01


def test_a_stack_its_writer_declared_frames_first_is_read_so(tmp_path):
    """s50rv1: radiokit's own corrected output of a strip of 75 projections of 200 x 8 was refused
    by ``info`` as a frames-last stack, with advice (``numpy.moveaxis(stack, -1, 0)``) that would
    have scrambled it. Its dataset says ``@interpretation = "image"`` (NeXus: the last two axes are
    one image), as every radiokit writer's and other NeXus writers' do: a declaration, like a
    tifffile description's axes, read as stated. Without it the same stack is refused."""
    rng = np.random.default_rng(8)
    path = _strip_experiment(tmp_path / "strip.h5", 90, rng)
    res = run_cli("correct", path, "-o", tmp_path / "t.h5", "--domain", "linear", "-q")
    assert res.returncode == 0, res.stderr
    res = run_cli("info", "--json", tmp_path / "t.h5")
    assert res.returncode == 0, res.stderr
    assert (json.loads(res.stdout)[0]["frames"], json.loads(res.stdout)[0]["shape"]) == (75, [200, 8])
    stack = rng.integers(1000, 3000, (80, 96, 6), dtype=np.uint16)
    with h5py.File(tmp_path / "declared.h5", "w") as f:
        f["said"], f["unsaid"] = stack, stack
        f["said"].attrs["interpretation"] = "image"
    assert run_cli("info", tmp_path / "declared.h5", "--dataset", "said").returncode == 0
    one_line_error(run_cli("info", tmp_path / "declared.h5", "--dataset", "unsaid"), "unsaid", "--narrow-frames")


def test_narrow_frames_reaches_the_calibration_of_one_data_exchange_file(tmp_path):
    """s50rv1: a Data Exchange file of 80 projections of 200 x 8 (its darks and flats beside) was
    refused by ``correct dx.h5`` naming "dataset its frames", and ``--narrow-frames``, the way out
    the message gave, was refused the same: the calibration from the file's own darks and flats
    read it without the flag. The line names its datasets; the flag reaches that calibration
    (and ``calibrate --experiment``'s)."""
    rng = np.random.default_rng(9)
    path = tmp_path / "dx.h5"
    with h5py.File(path, "w") as f:
        f["exchange/data"] = rng.normal(1500, 10, (80, 200, 8)).round().astype(np.uint16)
        f["exchange/data_dark"] = rng.normal(100, 10, (5, 200, 8)).round().astype(np.uint16)
        f["exchange/data_white"] = rng.normal(3000, 10, (10, 200, 8)).round().astype(np.uint16)
    res = run_cli("correct", path, "-o", tmp_path / "t.h5", "--domain", "linear", "-q")
    one_line_error(res, "dx.h5", "/exchange/data", "95x200x8", "--narrow-frames")
    assert "dataset its frames" not in res.stderr
    res = run_cli("correct", path, "-o", tmp_path / "t.h5", "--domain", "linear", "-q", "--narrow-frames")
    assert res.returncode == 0, res.stderr
    corrected = read(tmp_path / "t.h5").data
    assert corrected.shape == (80, 200, 8)
    assert abs(float(np.median(corrected)) - 1400 / 2900) < 0.01  # (1500 - 100) / (3000 - 100)
    res = run_cli("calibrate", "--experiment", path, "-o", tmp_path / "cal.h5", "-q", "--narrow-frames")
    assert res.returncode == 0, res.stderr


# ------------------------------------------------------------------------------------------------
# 3. --dataset over TIFF and HDF5 files given together
# ------------------------------------------------------------------------------------------------


def test_dataset_applies_to_the_hdf5_files_among_tiffs_in_info_and_correct(tmp_path):
    """s50: ``--dataset`` with TIFF and HDF5 files given together was refused for the TIFF, though
    each format alone was read: it names the HDF5 files' dataset, the TIFFs read as ever. Where no
    file given is HDF5 it is still refused, naming the file (an option applying to nothing)."""
    darks, flats = _darks_flats()
    cal = tmp_path / "cal.h5"
    Calibration.from_frames(darks, flats).save(cal)
    # transmission 0.5 and 0.25 exactly: log images ln 2 and ln 4 (the averaged dark and flat
    # carry 2/sqrt(5) and 20/sqrt(5) counts of noise: about 1e-3 of ln, per pixel)
    half = np.full((2, ROWS, COLS), 100 + 0.5 * 2900, np.uint16)
    quarter = np.full((3, ROWS, COLS), 100 + 0.25 * 2900, np.uint16)
    _write_h5(tmp_path / "a.h5", "scan/proj", half)
    tifffile.imwrite(tmp_path / "b.tif", quarter, photometric="minisblack")
    res = run_cli("info", "--json", tmp_path / "a.h5", tmp_path / "b.tif", "--dataset", "scan/proj")
    assert res.returncode == 0, res.stderr
    assert [(r["format"], r["frames"]) for r in json.loads(res.stdout)] == [("hdf5", 2), ("tiff", 3)]
    out = tmp_path / "out.h5"
    res = run_cli("correct", tmp_path / "a.h5", tmp_path / "b.tif", "--dataset", "scan/proj", "--cal", cal, "-o", out)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        got = f["entry/data/data"][()]
    assert got.shape == (5, ROWS, COLS)
    np.testing.assert_allclose(np.median(got, axis=(1, 2)), [np.log(2)] * 2 + [np.log(4)] * 3, atol=2e-3)
    res = run_cli("info", tmp_path / "b.tif", "--dataset", "scan/proj")
    one_line_error(res, "b.tif", "--dataset", "HDF5")


def test_dataset_is_one_rule_in_calibrate_and_register_too(tmp_path):
    """s51: ``info`` and ``correct`` applied ``--dataset`` to the HDF5 files among TIFFs (s50), but
    ``calibrate`` and ``register`` still refused the TIFF. One rule for every option naming a
    dataset (--dataset, --dark-dataset, --fixed-dataset, ...): it applies to the HDF5 files among
    those it covers, the others read as they are; refused, naming the option and a file, only
    where none of them is HDF5. Every command's help says so."""
    darks, flats = _darks_flats()
    tifffile.imwrite(tmp_path / "d.tif", darks, photometric="minisblack")
    _write_h5(tmp_path / "f.h5", "scan/flat", flats)
    res = run_cli(
        "calibrate", "--dark", "d.tif", "--flat", "f.h5", "--dataset", "scan/flat", "-o", "c.h5", "-q", cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    # c, the mean of flat - dark over the panel: both kinds read (noise 20 / sqrt(5 * 48 * 64))
    assert abs(Calibration.load(tmp_path / "c.h5").c - (flats.mean() - darks.mean())) < 1
    got = [(i["path"], i["dataset"], i["option"]) for i in Calibration.load(tmp_path / "c.h5").provenance["inputs"]]
    assert got == [("d.tif", None, None), ("f.h5", "scan/flat", "--dataset")]
    # one kind's option over that kind's files alike: TIFF flats beside HDF5 flats
    tifffile.imwrite(tmp_path / "f.tif", flats[:2], photometric="minisblack")
    _write_h5(tmp_path / "f3.h5", "scan/flat", flats[2:])
    args = ["--dark", "d.tif", "--flat", "f.tif", "f3.h5", "--flat-dataset", "scan/flat", "-o", "c2.h5", "-q"]
    assert run_cli("calibrate", *args, cwd=tmp_path).returncode == 0
    assert Calibration.load(tmp_path / "c2.h5").provenance["n_flats"] == 5
    image = np.random.default_rng(3).normal(1000, 50, (40, 40)).astype(np.float32)
    tifffile.imwrite(tmp_path / "fixed.tif", image)
    _write_h5(tmp_path / "moving.h5", "scan/frames", image[None])
    res = run_cli(
        "register",
        "fixed.tif",
        "moving.h5",
        "--dataset",
        "scan/frames",
        "--method",
        "ncc",
        "-o",
        "r.h5",
        "-q",
        cwd=tmp_path,
    )
    assert res.returncode in (0, 1) and (tmp_path / "r.h5").is_file(), res.stderr
    # applied to nothing: refused, naming the option and the file, before any work
    for command, extra in (
        ("calibrate", ("--dark", "d.tif", "--flat", "f.tif", "--dataset", "x", "-o", "refused1.h5")),
        ("calibrate", ("--dark", "d.tif", "--flat", "f.h5", "--dark-dataset", "x", "-o", "refused1.h5")),
        ("register", ("d.tif", "fixed.tif", "--dataset", "x", "-o", "refused2.h5")),
        ("register", ("fixed.tif", "moving.h5", "--fixed-dataset", "x", "-o", "refused2.h5")),
        ("info", ("d.tif", "--dataset", "x")),
        ("correct", ("d.tif", "--cal", "c.h5", "--dataset", "x", "-o", "refused3.h5")),
    ):
        option = next(a for a in extra if a.endswith("dataset"))
        line = one_line_error(run_cli(command, *extra, cwd=tmp_path), option, "HDF5")
        assert "d.tif" in line or "fixed.tif" in line, line
        assert not list(tmp_path.glob("refused*"))
    for command in ("info", "correct", "calibrate", "register"):
        helps = " ".join(run_cli(command, "--help").stdout.split())
        assert "the HDF5 files among" in helps and "read as they are" in helps, (command, helps)


def test_dataset_beside_every_kinds_own_option_is_refused_not_dropped(tmp_path):
    """Review s51rv2: the rule says an option that applies to nothing given is a slip to say, not
    to drop, yet ``--dataset`` beside ``--dark-dataset`` and ``--flat-dataset`` (register's
    ``--fixed-dataset`` and ``--moving-dataset``) covers no file and was dropped in silence: a
    calibration was written from datasets the user may not have meant. Refused in one line
    naming it, nothing written."""
    darks, flats = _darks_flats()
    with h5py.File(tmp_path / "both.h5", "w") as h5:
        h5["d"], h5["f"] = darks, flats
    cal = ("calibrate", "--dark", "both.h5", "--flat", "both.h5", "--dark-dataset", "d", "--flat-dataset", "f")
    reg = ("register", "both.h5", "both.h5", "--fixed-dataset", "d", "--moving-dataset", "f", "--method", "ncc")
    for args in (cal + ("-o", "c.h5", "-q"), reg + ("-o", "r.h5", "-q")):
        one_line_error(run_cli(*args, "--dataset", "x", cwd=tmp_path), "--dataset", "applies to no file")
        assert not list(tmp_path.glob("[cr].h5"))
    assert run_cli(*cal, "-o", "c.h5", "-q", cwd=tmp_path).returncode == 0  # without it, as ever


def test_a_dataset_refused_under_format_names_the_option_not_the_files_kind(tmp_path):
    """Review s51rv2: ``info f.h5 --format tiff --dataset d`` said "this file is a TIFF, not
    HDF5" of an HDF5 file: what refused the dataset was ``--format tiff``, which the line named
    nowhere. It says the file is read as --format asks."""
    _write_h5(tmp_path / "f.h5", "scan/f", np.zeros((2, 8, 8), np.uint16))
    for fmt in ("tiff", "raw", "itex"):
        line = one_line_error(run_cli("info", "f.h5", "--format", fmt, "--dataset", "scan/f", cwd=tmp_path), "f.h5")
        assert f"--format {fmt}" in line and "--dataset" in line, line
        assert "this file is a" not in line and "this file is headerless" not in line, line


# ------------------------------------------------------------------------------------------------
# 4. names holding control characters
# ------------------------------------------------------------------------------------------------


def test_a_name_with_a_control_character_is_printed_quoted_and_escaped(tmp_path):
    """s50: an output named "cal\\nx.h5" was printed raw, ``-> cal`` on one line and ``x.h5`` on
    the next; an escape in a name reached the terminal. Such names print as Python's repr writes
    them, in what the command says on success and in its one-line errors; plain names as typed."""
    darks, flats = _darks_flats()
    tifffile.imwrite(tmp_path / "d.tif", darks, photometric="minisblack")
    tifffile.imwrite(tmp_path / "f.tif", flats, photometric="minisblack")
    out = tmp_path / "cal\nx.h5"
    res = run_cli("calibrate", "--dark", "d.tif", "--flat", "f.tif", "-o", out.name, "-q", cwd=tmp_path)
    assert res.returncode == 0 and out.is_file(), res.stderr
    assert "-> 'cal\\nx.h5'\n" in res.stdout, res.stdout
    assert "x.h5" not in res.stdout.replace("'cal\\nx.h5'", ""), res.stdout
    one_line_error(run_cli("calibrate", "--dark", "d.tif", "--flat", "f.tif", "-o", out), "cal\\nx.h5': exists")
    res = run_cli("info", out)
    assert res.returncode == 0 and res.stdout.startswith(f"'{tmp_path}/cal\\nx.h5'\n  format"), res.stdout
    tifffile.imwrite(tmp_path / "p.tif", darks[:1] + 1000, photometric="minisblack")
    res = run_cli("correct", "p.tif", "--cal", out.name, "-o", "p\x1bx.tif", cwd=tmp_path)
    assert res.returncode == 0 and "-> 'p\\x1bx.tif' (log)" in res.stdout, (res.stdout, res.stderr)
    assert "\x1b" not in res.stdout + res.stderr
    res = run_cli("correct", "p.tif", "--cal", "cal.h5", "-o", "q.tif", cwd=tmp_path)  # a plain name, as typed
    one_line_error(res, "radiokit correct: cal.h5: no such file")


def test_made_from_names_print_as_every_other_name(tmp_path):
    """s51: ``info``'s "made from" lines escaped a name's newline but did not quote it as every
    other name printed is (radiokit._names.shown), and printed a name's byte that is not UTF-8 as
    ``\\udce9`` where every other line prints ``\\xe9``. Both as the file's own line prints them."""
    darks, flats = _darks_flats()
    latin = os.fsdecode(b"caf\xe9.tif")  # a Latin-1 name: its byte 0xe9 is no UTF-8
    tifffile.imwrite(tmp_path / "d\nx.tif", darks, photometric="minisblack")
    tifffile.imwrite(tmp_path / latin, flats, photometric="minisblack")
    res = run_cli("calibrate", "--dark", "d\nx.tif", "--flat", latin, "-o", "cal.h5", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    res = run_cli("info", tmp_path / latin, tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    assert f"{tmp_path}/caf\\xe9.tif\n" in res.stdout, res.stdout  # the file's own line, as it prints names
    assert "made from  'd\\nx.tif': tiff, 5 darks;" in info_items(res.stdout), res.stdout
    assert f"; '{tmp_path}/d\\nx.tif'\n" in res.stdout, res.stdout  # resolved, quoted alike
    assert re.search(r"\n {12,}caf\\xe9\.tif: tiff, 5 flats;", res.stdout), res.stdout  # the item's second line
    assert f"; {tmp_path}/caf\\xe9.tif\n" in res.stdout, res.stdout
    assert "udce9" not in res.stdout, res.stdout
    assert "inputs" not in res.stdout, res.stdout  # the records are --json's; the lines say them
    # --json keeps the names exact beside the lines: a reader gets the file back from them
    meta = json.loads(run_cli("info", "--json", tmp_path / "cal.h5").stdout)[0]["metadata"]
    assert [i["path"] for i in meta["inputs"]] == ["d\nx.tif", latin], meta["inputs"]
    assert meta["inputs"][0]["resolved"] == str(tmp_path / "d\nx.tif")


NL = "a\nb.tif"  # a name holding a newline


@pytest.mark.parametrize(
    "args, words",
    [
        (("correct", NL, NL, "--cal", "cal.h5", "-o", "o.h5"), "the same frame file given twice"),
        (
            ("calibrate", "--dark", NL, "odd.tif", "--flat", "f.tif", "-o", "c.h5"),
            "odd.tif: frames are (40, 64), those of",
        ),
        (("calibrate", "--dark", NL, "--flat", "odd.tif", "-o", "c.h5"), "one panel set-up"),
        (("calibrate", "--dark", NL, NL, "--flat", "f.tif", "-o", "c.h5"), "the same --dark file given twice"),
        (("register", NL, "f.tif", "--fixed-frame", "5", "-o", "r.h5"), "frame 5 requested"),
        (("register", NL, NL, "-o", "r.h5"), "the same image"),
        (("register", NL, "odd.tif", "-o", "r.h5"), "differ in shape"),
        (("register", "f.tif", "odd.tif", "-o", "r.h5", "--png", "a\nb.xyz"), "name the figure .png"),
        (("process", "a\nb.h5"), "no such experiment file"),
        (("process", NL), "not an experiment"),
        (("register", NL, "coarse.tif", "-o", "r.h5"), "pixels of 0.1 mm"),  # the library's line
    ],
)
def test_error_lines_print_a_name_with_a_newline_quoted(tmp_path, args, words):
    """s51: error lines that put a name in their text themselves (a file given twice, frames of
    another shape, a frame out of range, one image as both, a missing experiment file, the
    --png name) printed its newline as a space (the one line's whitespace folded), ``a b.tif``,
    which names no file; ``process`` named a TIFF twice, raw and quoted. Each as every other
    name prints (radiokit._names.shown), once."""
    rng = np.random.default_rng(0)
    for name, rows, level, mm in (
        (NL, 48, 1000, 0.05),
        ("f.tif", 48, 3000, 0.05),
        ("odd.tif", 40, 1000, 0.05),
        ("coarse.tif", 48, 1000, 0.1),
    ):
        data = rng.normal(level, 10, (2, rows, 64)).astype(np.uint16)
        tifffile.imwrite(tmp_path / name, data, imagej=True, resolution=(1 / mm, 1 / mm), metadata={"unit": "mm"})
    line = one_line_error(run_cli(*args, cwd=tmp_path), words)
    quoted = "'a\\nb.xyz'" if "--png" in args else "'a\\nb.h5'" if "a\nb.h5" in args else "'a\\nb.tif'"
    assert quoted in line and "a b." not in line, line
    assert args[0] != "process" or line.count(quoted) == 1, line  # named once


def test_any_line_naming_a_given_file_raw_prints_it_as_names_print():
    """What holds the rule for lines the command line did not word itself (the library's errors,
    and its warnings, alike): a file given on the command line and named raw in a message prints
    as every other name (shown), not folded to ``a b.tif``; names without control characters as typed."""
    from argparse import Namespace
    from pathlib import Path

    from radiokit.cli import _error_line, _given_names

    given = _given_names(Namespace(frames=[Path(NL), Path("c.tif")], cal=Path("cal.h5"), domain="log"))
    assert given == [NL, "c.tif", "cal.h5"]
    line = _error_line("correct", ValueError(f"c.tif, {NL}: frames of two sizes; see cal.h5"), given)
    assert line == "radiokit correct: c.tif, 'a\\nb.tif': frames of two sizes; see cal.h5"


def test_a_files_own_text_with_control_characters_never_reaches_the_terminal_raw(tmp_path):
    """Review s51rv2: the net of s51 quotes the names given on the command line, but an error line
    also quotes what a file holds: a hostile HDF5 file's dataset named ``x ESC]2;pwn BEL y`` (the
    terminal's title set, its screen cleared with ``ESC[2J``) reached the terminal raw in "no
    dataset ...; it holds ..." and "not a radiokit experiment file; it holds ...". Every control
    character left in a line a command prints of an error is escaped as ``shown`` escapes it."""
    evil = "x\x1b]2;pwn\x07y"
    _write_h5(tmp_path / "evil.h5", evil, np.zeros((2, 8, 8), np.uint16))
    _write_h5(tmp_path / "plain.h5", "scan/data", np.zeros((2, 8, 8), np.uint16))
    for args in (("evil.h5", "--dataset", "nope"), ("evil.h5",), ("evil.h5", "plain.h5", "--dataset", "nope")):
        res = run_cli("info", *args, cwd=tmp_path)
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
        line = next(line for line in res.stderr.splitlines() if "evil.h5" in line)
        assert "\x1b" not in res.stderr and "\x07" not in res.stderr, repr(res.stderr)
        assert "x\\x1b]2;pwn\\x07y" in line, line  # escaped, still naming the dataset


@pytest.mark.parametrize("shape", [(2, 8, 8), (4,)])
def test_a_files_own_name_with_a_backslash_prints_apart_from_one_with_a_newline(tmp_path, shape):
    """s53: a dataset named ``a\\nb`` (a backslash, then n) printed ``/a\\nb`` in the error line,
    as a newline's escape reads, and one named ``a<newline>b`` printed ``/a b``, as a space's. A
    name a file holds prints as a file name does (``shown``): as it is when plain, else quoted
    and escaped, reading back (``ast.literal_eval``) as the name: three names, three lines."""
    import ast

    names = {"backslash": "a\\nb", "newline": "a\nb", "space": "a b"}
    printed = {}
    for tag, name in names.items():
        _write_h5(tmp_path / f"{tag}.h5", name, np.zeros(shape, np.uint16))
        args = ("info", f"{tag}.h5") if len(shape) == 3 else ("info", "--dataset", name, f"{tag}.h5")
        res = run_cli(*args, cwd=tmp_path)
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
        (line,) = res.stderr.splitlines()
        assert line.startswith(f"radiokit info: {tag}.h5: "), line
        found = re.search(r"('(?:[^'\\]|\\.)*'|/a b|a b)( \(2x8x8 uint16\)| has shape)", line)
        assert found, line
        said = found.group(1)
        assert (ast.literal_eval(said) if said.startswith("'") else said).lstrip("/") == name, line
        printed[tag] = line.replace(f"{tag}.h5", "FILE")
    assert len(set(printed.values())) == 3, printed


def test_an_external_links_names_print_as_names_do(tmp_path):
    """s53: an external link's own name and the file and path it points at are a file's text too:
    a link ``a\\nb`` to ``x<newline>y.h5`` printed ``/a\\nb is an external link to x y.h5:/d``,
    the backslash as a newline's escape and the newline as a space. Each prints as names print."""
    import ast

    with h5py.File(tmp_path / "link.h5", "w") as f:
        f["a\\nb"] = h5py.ExternalLink("x\ny.h5", "/d\\e")
    res = run_cli("info", "--dataset", "a\\nb", "link.h5", cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (line,) = res.stderr.splitlines()
    found = re.search(r"('(?:[^'\\]|\\.)*') is an external link to ('(?:[^'\\]|\\.)*')", line)
    assert found, line
    assert ast.literal_eval(found.group(1)) == "/a\\nb", line
    assert ast.literal_eval(found.group(2)) == "x\ny.h5:/d\\e", line


# ------------------------------------------------------------------------------------------------
# 5. an 8-bit and a 16-bit copy of one image registered
# ------------------------------------------------------------------------------------------------


def test_an_8_bit_copy_of_a_16_bit_image_is_flagged_with_the_reason(tmp_path):
    """s50: an 8-bit copy of a 16-bit image (no motion, its values 257 times smaller) registered
    with a zero field but was flagged "did not find the motion": the checks compare the pair's
    intensities, and a scale of 257 between them reads as structure left misaligned. The flag
    stays (no check judges intensities of two scales) and says why; the 16-bit copy of the 8-bit
    one (x 257, quantised alike) registers and passes: the quantisation is not what is flagged."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    n = 192
    yy, xx = np.mgrid[:n, :n]
    image = ndimage.gaussian_filter(rng.normal(0, 1, (n, n)), 3) + 0.8 * np.exp(
        -((yy - 96) ** 2 + (xx - 80) ** 2) / (2 * 25**2)
    )
    image = (image - image.min()) / (image.max() - image.min())
    i16 = np.round(1000 + image * 50000).astype(np.uint16)
    i8 = np.round(i16 / 257).astype(np.uint8)
    for name, data in (("i16.tif", i16), ("i8.tif", i8), ("i8x257.tif", i8.astype(np.uint16) * 257)):
        tifffile.imwrite(tmp_path / name, data)
    res = run_cli("register", "i16.tif", "i8.tif", "-o", "f.h5", "-q", cwd=tmp_path)
    assert res.returncode == 1, (res.stdout, res.stderr)
    assert "max |d| 0.00 px" in res.stdout  # the field found no motion, as there is none
    assert "the images are uint16 and uint8: their values are not of one scale (an 8-bit copy of a 16-bit image?)" in (
        res.stdout
    ), res.stdout
    res = run_cli("register", "i16.tif", "i8x257.tif", "-o", "g.h5", "-q", cwd=tmp_path)
    assert res.returncode == 0 and "not of one scale" not in res.stdout, (res.stdout, res.stderr)


def test_the_two_scales_hint_says_only_what_the_values_show(tmp_path):
    """s50rv1: the hint fired on the types alone. Two unrelated images (flagged, rightly), both
    of 8-bit values, one stored uint8 and one widened to uint16 (ImageJ's "16-bit" keeps the
    values), were said "not of one scale": false, and it pointed away from the real cause. It
    fires where the wider image holds values the narrower type cannot (a 16-bit image's against
    its 8-bit copy), and names the widths the pair has: a 32-bit copy of a 16-bit image is no
    "8-bit copy of a 16-bit image"."""
    from scipy import ndimage

    def smooth(seed):
        im = ndimage.gaussian_filter(np.random.default_rng(seed).normal(0, 1, (160, 160)), 3)
        return (im - im.min()) / (im.max() - im.min())

    a, b = smooth(1), smooth(2)
    tifffile.imwrite(tmp_path / "a8.tif", np.round(a * 250).astype(np.uint8))
    tifffile.imwrite(tmp_path / "b8in16.tif", np.round(b * 250).astype(np.uint16))  # 8-bit values, widened
    tifffile.imwrite(tmp_path / "a16.tif", np.round(1000 + a * 50000).astype(np.uint16))
    tifffile.imwrite(tmp_path / "a32.tif", np.round(1000 + a * 50000).astype(np.uint32) * 65537)
    res = run_cli("register", "a8.tif", "b8in16.tif", "-o", "f.h5", "-q", cwd=tmp_path)
    assert res.returncode == 1, (res.stdout, res.stderr)  # flagged: they are different images
    assert "not of one scale" not in res.stdout, res.stdout
    res = run_cli("register", "a16.tif", "a32.tif", "-o", "g.h5", "-q", cwd=tmp_path)
    assert res.returncode == 1, (res.stdout, res.stderr)
    assert "the images are uint16 and uint32: their values are not of one scale" in res.stdout, res.stdout
    assert "a 16-bit copy of a 32-bit image?" in res.stdout and "8-bit" not in res.stdout, res.stdout


def test_a_pair_of_two_value_scales_is_flagged_with_the_ranges(tmp_path):
    """s53: 12-bit counts in a uint16 TIFF against the same image in a float32 TIFF scaled to 0-1,
    moved 2 px: rc found the motion (NCC 0.43 -> 0.99) but the checks, which compare the pair's
    intensities and explain a gain of at most 2 either way, flagged it "did not find the motion",
    and no hint said why (the 8-bit/16-bit one looks at integer types only). The flag stays; the
    warning names the two ranges. One image against its own copy times 1.5 (a gain the checks
    explain) passes, without it."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    image = ndimage.gaussian_filter(rng.random((128, 160)), 2)
    image = (image - image.min()) / (image.max() - image.min())
    moved = ndimage.shift(image, (-2, 1), order=3, mode="reflect")
    tifffile.imwrite(tmp_path / "counts.tif", np.round(moved * 4095).astype(np.uint16))
    tifffile.imwrite(tmp_path / "unit.tif", image.astype(np.float32))
    tifffile.imwrite(tmp_path / "gain.tif", (image * 1.5).astype(np.float32))
    tifffile.imwrite(tmp_path / "moved.tif", moved.astype(np.float32))
    res = run_cli("register", "counts.tif", "unit.tif", "-o", "f.h5", "-q", cwd=tmp_path)
    assert res.returncode == 1, (res.stdout, res.stderr)
    assert "the images' 1-99 % ranges differ" in res.stdout and "fold" in res.stdout, res.stdout
    res = run_cli("register", "moved.tif", "gain.tif", "-o", "g.h5", "-q", cwd=tmp_path)
    assert res.returncode == 0 and "ranges differ" not in res.stdout, (res.stdout, res.stderr)


def test_two_datasets_of_one_file_are_two_inputs(tmp_path):
    """Darks and flats in two datasets of one file (--dark-dataset, --flat-dataset) are recorded
    as two inputs, each with its dataset, option and frames."""
    darks, flats = _darks_flats(4)
    with h5py.File(tmp_path / "both.h5", "w") as f:
        f["d"], f["f"] = darks, flats[:3]
    out = tmp_path / "cal.h5"
    args = ["--dark", "both.h5", "--flat", "both.h5", "--dark-dataset", "d", "--flat-dataset", "f"]
    assert run_cli("calibrate", *args, "-o", out, "-q", cwd=tmp_path).returncode == 0
    got = [(i["dataset"], i["option"], i["darks"], i["flats"]) for i in Calibration.load(out).provenance["inputs"]]
    assert got == [("d", "--dark-dataset", 4, 0), ("f", "--flat-dataset", 0, 3)]


def test_dataset_beside_a_fifo_is_refused_not_waited_on(tmp_path):
    """Review s50rv1: ``info p.tif x.h5 --dataset d`` with ``p.tif`` a FIFO hung in the look for
    HDF5 files among the inputs (its open() waits for a writer that never comes), where without
    ``--dataset`` the reader refuses it as not a regular file. Run as a process: a hang must fail
    the test, not the suite."""
    fifo = tmp_path / "p.tif"
    os.mkfifo(fifo)
    _write_h5(tmp_path / "x.h5", "d", _darks_flats()[0])
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", "info", str(fifo), str(tmp_path / "x.h5"), "--dataset", "d"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    one_line_error(res, "p.tif", "not a regular file")


def test_a_name_holding_a_backslash_prints_apart_from_one_holding_a_control_character(tmp_path):
    """s52: a file literally named ``a\\nb.tif`` (a backslash, then n) printed ``a\\nb.tif``, and
    ``'a\\nb.tif'`` quoted inside any quotes of a message's own, as the name holding a real newline
    prints: two files, one text. A backslash is escaped and the name quoted as Python's ``repr``
    writes it, so that every printed name reads back (``ast.literal_eval``) as its file's name."""
    import ast

    from radiokit._names import shown
    from radiokit.cli import _error_line

    literal, newline = "a\\nb.tif", "a\nb.tif"
    for name in (literal, newline, "x\\", "'q\\'", "c\\x1b.tif", "plain 'quoted' name.h5", "cal.h5"):
        assert ast.literal_eval(shown(name)) == name if shown(name) != name else "\\" not in name, shown(name)
    assert shown(literal) != shown(newline)
    assert shown("cal.h5") == "cal.h5" and shown("it's.h5") == "it's.h5"  # plain names as typed
    # the command line's net leaves a name its message already printed as names print alone
    for name in (literal, "x\\", newline):
        line = _error_line("info", ValueError(f"{shown(name)}: no such file; {name} again"), [name])
        assert line == f"radiokit info: {shown(name)}: no such file; {shown(name)} again", line
    (tmp_path / literal).write_bytes(b"")
    line = one_line_error(run_cli("info", literal, cwd=tmp_path), "radiokit info: ")
    assert shown(literal) in line and shown(newline) not in line, line


def test_the_library_s_own_messages_print_a_file_s_name_as_names_print(tmp_path):
    """s52: the command line quotes the names it was given wherever a message puts them raw, but
    a Python caller got the library's raw text: ``ValueError("/x/a\\nb.h5: frames are ...")``, a
    message of two lines naming no file. The library's messages that open with a user's file name
    it as names print (radiokit._names.shown)."""
    from radiokit._names import shown
    from radiokit.io import StackWriter, open_frames

    name = tmp_path / "a\nb.h5"
    with ExperimentWriter(name, shape=(4, 5)) as w:
        w.append(np.zeros((4, 5), np.uint16), image_key=ImageKey.DARK)
        with pytest.raises(ValueError) as wrong:
            w.append(np.zeros((3, 5), np.uint16), image_key=ImageKey.DARK)
    with open_frames(name) as src, pytest.raises(IndexError) as beyond:
        src[5]
    with pytest.raises(ValueError) as suffix:
        StackWriter(tmp_path / "s\x1bt.xyz", (4, 5))
    for exc, path in ((wrong, name), (beyond, name), (suffix, tmp_path / "s\x1bt.xyz")):
        text = str(exc.value)
        assert text.startswith(f"{shown(path)}: ") and "\n" not in text and "\x1b" not in text, text


@pytest.mark.parametrize("name", ["a\\nb", "a\nb"])
def test_a_stacks_series_and_a_results_domain_named_by_the_file_print_as_names_do(tmp_path, name):
    """s53: read_stack's "/entry/data/NAME holds N values for M frames" and read_results'
    "/results/enhanced/NAME is not a group" printed a name the file holds raw: a backslash read
    as an escape, a newline broke the line. Each prints as names print, reading back as the name."""
    import ast

    from radiokit.errors import FormatError
    from radiokit.io import StackWriter, read_results, read_stack
    from radiokit.io._results import RESULTS_ENHANCED

    stack = tmp_path / "s.h5"
    with StackWriter(stack, (4, 4)) as w:
        w.append(np.zeros((4, 4), np.float32))
    with h5py.File(stack, "a") as f:
        f["entry/data"][name] = np.zeros(3, np.int32)
    with pytest.raises(FormatError) as info:
        read_stack(stack)
    said = re.search(r"('(?:[^'\\]|\\.)*') holds 3 values", str(info.value))
    assert said and ast.literal_eval(said.group(1)) == f"/entry/data/{name}", str(info.value)

    from test_hostile_inputs import _results_file

    results = tmp_path / "results.h5"
    _results_file(results)
    with h5py.File(results, "a") as f:
        f.require_group(RESULTS_ENHANCED)[name] = np.zeros(3)
    with pytest.raises(FormatError) as info:
        read_results(results)
    said = re.search(r"('(?:[^'\\]|\\.)*') is not a group", str(info.value))
    assert said and ast.literal_eval(said.group(1)) == f"/{RESULTS_ENHANCED}/{name}", str(info.value)


def test_info_prints_a_tiff_tags_backslash_apart_from_a_newline(tmp_path):
    """s53: ``info`` printed a TIFF's Software tag ``HPD\\nTA`` (a backslash, then n) and one
    holding a newline both as ``HPD\\nTA``: its control characters were escaped, its backslash not.
    A text value a file holds prints by ``shown``'s rule: as it is when plain, else quoted and
    escaped, reading back (``ast.literal_eval``) as the tag."""
    import ast

    tags = {"backslash": "HPD\\nTA", "newline": "HPD\nTA", "plain": "HPD-TA 9.5"}
    printed = {}
    for tag, software in tags.items():
        tifffile.imwrite(tmp_path / f"{tag}.tif", np.zeros((4, 4), np.uint16), software=software)
        res = run_cli("info", f"{tag}.tif", cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        (line,) = [ln for ln in res.stdout.splitlines() if ln.split()[:1] == ["Software"]]
        said = line.split(None, 1)[1]
        printed[tag] = said
        assert (ast.literal_eval(said) if said.startswith("'") else said) == software, line
    assert printed["plain"] == "HPD-TA 9.5" and len(set(printed.values())) == 3, printed
