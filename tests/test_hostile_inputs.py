"""Files made to hurt: each gives one clear line and exit code 2, within the memory budget.

Memory cases run the command in a subprocess limited by ``resource.setrlimit(RLIMIT_AS)``: a
reader that allocated what the header declares would die with MemoryError (or be killed); the
budget check must refuse first, naming the file.
"""
from __future__ import annotations

import os
import resource
import subprocess
import sys

import h5py
import numpy as np
import pytest
import tifffile

from radiokit.errors import FormatError
from radiokit.io import ExperimentWriter, ImageKey, memory_budget, parse_size, read
from radiokit.io._itex import parse_comment

from conftest import ITEX_DIR as ITEX, needs_itex
AS_LIMIT = 1 << 30  # 1 GiB of address space: python, numpy, h5py and scipy fit; the bombs do not


def run(*args, limit=None, env=None, cwd=None):
    def preexec():
        if limit:
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run([sys.executable, "-m", "radiokit.cli", *map(str, args)], capture_output=True, text=True,
                          preexec_fn=preexec, cwd=cwd,
                          env={**os.environ, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1",
                               "OPENBLAS_NUM_THREADS": "1", **(env or {})})


def one_line_error(res, *needles):
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr and "MemoryError" not in res.stderr, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])
    return lines[0]


def _experiment(path, shape=(32, 40), projections=True, step=True):
    rng = np.random.default_rng(0)
    with ExperimentWriter(path, shape=shape) as w:
        for _ in range(3):
            w.append(rng.integers(90, 110, shape), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(rng.integers(2900, 3100, shape), image_key=ImageKey.FLAT)
        if projections:
            for s in (1, 2, 3):
                w.append(rng.integers(900, 1100, shape), image_key=ImageKey.PROJECTION, step=s)
    if not step:
        with h5py.File(path, "a") as h5:
            del h5["entry/sample/compression/step"]
    return path


# -- memory bombs ------------------------------------------------------------------------------
@pytest.fixture
def hdf5_bomb(tmp_path):
    """A few KB declaring (10, 100000, 100000) uint16 frames: 186 GiB."""
    path = tmp_path / "bomb.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("entry/instrument/detector/data", shape=(10, 100_000, 100_000), dtype="u2",
                          chunks=(1, 1000, 1000), compression="gzip")
        h5["entry/instrument/detector/image_key"] = np.array([2, 2, 1, 1, 0, 0, 0, 0, 0, 0], np.int8)
        h5["entry/sample/compression/step"] = np.array([-1] * 4 + [1, 1, 2, 2, 3, 3], np.int16)
    assert path.stat().st_size < 20_000
    return path


@pytest.fixture
def tiff_bomb(tmp_path):
    """A 270-byte zlib TIFF whose header declares one 60000 x 60000 uint16 page (6.7 GiB)."""
    path = tmp_path / "bomb.tif"
    tifffile.imwrite(path, np.zeros((16, 16), np.uint16), compression="zlib", rowsperstrip=16)
    with tifffile.TiffFile(path, mode="r+b") as tif:
        for name in ("ImageWidth", "ImageLength", "RowsPerStrip"):
            tif.pages[0].tags[name].overwrite(60_000)
    return path


@pytest.mark.parametrize("cmd", ["info", "correct", "process", "register"])
def test_hdf5_memory_bomb_is_refused_within_the_budget(cmd, hdf5_bomb, tmp_path):
    args = {"info": ["info", hdf5_bomb],
            "correct": ["correct", hdf5_bomb, "-q", "-o", tmp_path / "out.h5"],
            "process": ["process", hdf5_bomb, "-q", "-o", tmp_path / "res"],
            "register": ["register", hdf5_bomb, hdf5_bomb, "--dataset", "entry/instrument/detector/data",
                         "-o", tmp_path / "reg.h5"]}[cmd]
    res = run(*args, limit=AS_LIMIT, env={"RADIOKIT_MEMORY_BUDGET": "256MiB"})
    one_line_error(res, f"radiokit {cmd}: ", "bomb.h5", "memory budget")
    assert not any(p.name not in ("bomb.h5",) for p in tmp_path.iterdir())


def test_hdf5_memory_bomb_is_refused_by_the_default_budget(hdf5_bomb):
    # no variable: half the available memory (or of the address-space limit, here 1 GiB)
    env = {k: v for k, v in os.environ.items() if k != "RADIOKIT_MEMORY_BUDGET"}
    res = subprocess.run([sys.executable, "-m", "radiokit.cli", "info", hdf5_bomb], capture_output=True, text=True,
                         env=env, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT)))
    one_line_error(res, "bomb.h5", "over the memory budget of 512.0 MiB")


def test_tiff_decompression_bomb_is_refused(tiff_bomb):
    res = run("info", tiff_bomb, limit=AS_LIMIT)
    one_line_error(res, "bomb.tif", "60000x60000", "decompression bomb")


def test_a_tiff_tile_larger_than_the_budget_is_refused(tmp_path):
    path = tmp_path / "tiles.tif"
    tifffile.imwrite(path, np.zeros((32, 32), np.uint16), tile=(16, 16), compression="zlib")
    with tifffile.TiffFile(path, mode="r+b") as tif:  # a 32 x 32 image in 32768 x 32768 tiles
        tif.pages[0].tags["TileWidth"].overwrite(32768)
        tif.pages[0].tags["TileLength"].overwrite(32768)
    res = run("info", path, limit=AS_LIMIT, env={"RADIOKIT_MEMORY_BUDGET": "256MiB"})
    one_line_error(res, "tiles.tif", "32768x32768 tile", "memory budget")


def test_an_honest_large_tiff_is_refused_over_a_small_budget(tmp_path):
    path = tmp_path / "big.tif"
    tifffile.imwrite(path, np.zeros((4, 1024, 1024), np.uint16), photometric="minisblack")  # 2 MiB a frame, 8 MiB in all
    with pytest.raises(FormatError, match=r"big.tif: one 1024x1024 uint16 frame would need 2.0 MiB"):
        read(path, budget="1MiB")
    with pytest.raises(FormatError, match=r"4 frame\(s\).* would need 8.0 MiB"):
        read(path, budget="5MiB")
    assert read(path, budget="9MiB").data.shape == (4, 1024, 1024)
    # frame by frame, a stack larger than the budget can still be streamed
    res = run("info", path, "--all", env={"RADIOKIT_MEMORY_BUDGET": "3MiB"})
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("text, expected", [("2GiB", 2 * 2**30), ("500M", 500 * 10**6), ("1e9", 10**9),
                                            ("64 kib", 64 * 1024), ("123", 123)])
def test_budget_sizes(text, expected):
    assert parse_size(text) == expected
    assert memory_budget(text) == expected


@pytest.mark.parametrize("text", ["lots", "-5M", "0", "2 parsecs", "nan"])
def test_a_bad_budget_is_one_line(text, tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    one_line_error(run("info", path, env={"RADIOKIT_MEMORY_BUDGET": text}), "RADIOKIT_MEMORY_BUDGET", text)


@needs_itex
def test_raw_and_itex_headers_are_checked_against_the_budget(tmp_path):
    raw = tmp_path / "frames.raw"
    np.zeros((3, 512, 512), "<u2").tofile(raw)
    with pytest.raises(FormatError, match="memory budget"):
        read(raw, shape=(512, 512), budget="1MiB")
    itex = sorted(ITEX.glob("*.img"))[0]
    with pytest.raises(FormatError, match="memory budget"):
        read(itex, budget=1000)


# -- data outside the file ---------------------------------------------------------------------
@pytest.fixture
def outside(tmp_path):
    """A private file, another HDF5 file, and three files that point at them."""
    secret = tmp_path / "secret.bin"
    secret.write_bytes(bytes(range(256)) * 16)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5["frames"] = np.arange(4096, dtype=np.uint16).reshape(1, 64, 64)
    files = {}
    files["external raw storage"] = tmp_path / "extraw.h5"
    with h5py.File(files["external raw storage"], "w") as h5:
        h5.create_dataset("frames", shape=(1, 64, 64), dtype="u1", external=[(str(secret), 0, 4096)])
    files["external link"] = tmp_path / "extlink.h5"
    with h5py.File(files["external link"], "w") as h5:
        h5["frames"] = h5py.ExternalLink(str(other), "/frames")
    files["virtual dataset"] = tmp_path / "vds.h5"
    layout = h5py.VirtualLayout(shape=(1, 64, 64), dtype="u2")
    layout[0] = h5py.VirtualSource(str(other), "frames", shape=(1, 64, 64))[0]
    with h5py.File(files["virtual dataset"], "w") as h5:
        h5.create_virtual_dataset("frames", layout)
    files["linked experiment"] = _experiment(tmp_path / "exp.h5")
    with h5py.File(files["linked experiment"], "a") as h5:
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = h5py.ExternalLink(str(other), "/frames")
    return files, secret


@pytest.mark.parametrize("kind, words", [("external raw storage", "external raw files"),
                                         ("external link", "external link"),
                                         ("virtual dataset", "virtual dataset"),
                                         ("linked experiment", "external link")])
def test_data_outside_the_file_is_refused_unless_allowed(kind, words, outside):
    files, secret = outside
    path = files[kind]
    hints = {} if kind == "linked experiment" else {"dataset": "frames"}
    with pytest.raises(FormatError, match=f"{path.name}: .*{words}.*allow_external=True"):
        read(path, **hints)
    data = read(path, allow_external=True, **hints).data
    if kind == "external raw storage":  # what was refused: the private file's bytes as pixels
        assert data.tobytes() == secret.read_bytes()
    res = run("info", path, *(["--format", "hdf5"] if not hints else []))
    if hints:  # the CLI reads a named dataset only in register; info reads experiment files
        res = run("register", path, path, "--dataset", "frames", "-o", path.with_name("reg.h5"))
    one_line_error(res, path.name, "allow_external")


# -- parsing -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text", [
    ("spaces before =", "a" + " " * 300_000 + "b=1"),
    ("unclosed brackets", "[" * 300_000),
    ("bracketed text", "[abc" * 75_000),
    ("lines of blanks", (" " * 100 + "\n") * 3000),
    ("unclosed quote", 'a="' + "x" * 300_000),
])
def test_itex_comment_parsing_handles_hostile_comments(name, text):
    """Linear parsing (benchmarks/bench_itex_parse.py measures it); here: every hostile comment
    parses to what it says, and nothing is lost."""
    out = parse_comment(text)
    if name == "spaces before =":
        assert out == {"": {"a" + " " * 300_000 + "b": 1}} or list(out[""].values()) == [1]
    elif name == "unclosed quote":
        assert out[""]["a"] == '"' + "x" * 300_000
    elif name == "lines of blanks":
        assert out == {}
    else:
        assert "_unparsed" in out and sum(map(len, out["_unparsed"])) == len(text)


@needs_itex
def test_itex_vendor_files_still_parse():
    img = ITEX / "photon_counting.img"
    c = read(img).meta["comment"]
    assert c["Camera"]["CameraName"] == "Orca R2"
    assert "_unparsed" not in c


# -- bad values --------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["eps=nan", "eps=inf", "dead_below=-inf", "saturation=abc", "nosuch=1", "eps"])
def test_a_bad_threshold_is_refused_before_anything_is_written(value, tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    res = run("calibrate", "--experiment", path, "--threshold", value, "-o", tmp_path / "cal.h5")
    one_line_error(res, "--threshold", value)
    assert not (tmp_path / "cal.h5").exists()


def test_nonfinite_pixels_are_filled_and_flagged_in_the_streaming_path(tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    f = read(path)
    cal = tmp_path / "cal.h5"
    assert run("calibrate", "--experiment", path, "-o", cal).returncode == 0
    proj = f.data[f.meta["image_key"] == 0].astype(np.float32)
    proj[0, 5, 5], proj[1, 10, 20], proj[2, 0, 0] = np.nan, np.inf, -np.inf
    proj[2, 20:22, 30:32] = np.nan  # a small cluster
    tif = tmp_path / "frames.tif"
    tifffile.imwrite(tif, proj, photometric="minisblack")
    res = run("correct", tif, "--cal", cal, "-q", "-o", tmp_path / "out.h5")
    assert res.returncode == 0, res.stderr
    with h5py.File(tmp_path / "out.h5") as h5:
        out = h5["entry/data/data"][()]
        nonpositive = h5["entry/data/nonpositive"][()]
    assert np.isfinite(out).all()
    assert nonpositive.tolist() == [1, 1, 5]  # every non-finite pixel counted, in its frame
    good = np.isfinite(proj)
    ref = out[good]
    # filled from valid neighbours: inside the range of the frame's real values
    for i, (r, c) in enumerate([(5, 5), (10, 20), (0, 0)]):
        assert ref.min() <= out[i, r, c] <= ref.max()
    # the in-memory path agrees with the streaming one
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames

    got, report = correct_frames(Calibration.load(cal), proj, return_report=True)
    np.testing.assert_allclose(got, out, rtol=1e-6)
    assert report.nonpositive.tolist() == [1, 1, 5]


def test_a_frame_of_only_nan_is_refused(tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    cal = tmp_path / "cal.h5"
    assert run("calibrate", "--experiment", path, "-o", cal).returncode == 0
    tif = tmp_path / "nan.tif"
    tifffile.imwrite(tif, np.full((2, 32, 40), np.nan, np.float32))
    one_line_error(run("correct", tif, "--cal", cal, "-q", "-o", tmp_path / "out.h5"), "only NaN or inf")
    assert not (tmp_path / "out.h5").exists()


# -- errors instead of tracebacks --------------------------------------------------------------
def test_info_on_an_experiment_without_steps(tmp_path):
    path = _experiment(tmp_path / "exp.h5", step=False)
    res = run("info", path)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert "projections 3" in res.stdout and "steps      []" in res.stdout


def test_info_reads_a_sample_of_frames_not_the_whole_file(tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    res = run("info", path, "--sample", "3")
    assert res.returncode == 0 and "(in 3 of 9 frames)" in res.stdout


@pytest.mark.parametrize("case", ["no projections", "one step", "no darks", "not hdf5", "missing", "a folder"])
def test_process_on_unusable_files(case, tmp_path):
    path = tmp_path / "exp.h5"
    if case == "no projections":
        _experiment(path, projections=False)
    elif case == "one step":
        with ExperimentWriter(path, shape=(16, 16)) as w:
            w.append(np.full((16, 16), 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full((16, 16), 3000, np.uint16), image_key=ImageKey.FLAT)
            w.append(np.full((16, 16), 1000, np.uint16), image_key=ImageKey.PROJECTION, step=1)
    elif case == "no darks":
        with ExperimentWriter(path, shape=(16, 16)) as w:
            w.append(np.full((16, 16), 1000, np.uint16), image_key=ImageKey.PROJECTION, step=1)
    elif case == "not hdf5":
        path.write_bytes(b"hello" * 100)
    elif case == "a folder":
        path.mkdir()
    res = run("process", path, "-q", "-o", tmp_path / "res")
    one_line_error(res, "radiokit process: ", "exp.h5")
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("args, words", [
    (["--fixed-frame", "7"], "frame 7"),
    (["--roi", "0", "500", "0", "10"], "--roi"),
    (["--method", "nosuch"], "nosuch"),
])
def test_register_bad_arguments(args, words, tmp_path):
    img = tmp_path / "img.tif"
    tifffile.imwrite(img, np.random.default_rng(0).random((32, 32), np.float32))
    one_line_error(run("register", img, img, *args, "-o", tmp_path / "reg.h5"), words)
    assert not (tmp_path / "reg.h5").exists()


def test_debug_shows_the_traceback(tmp_path):
    res = run("info", tmp_path / "missing.h5", env={"RADIOKIT_DEBUG": "1"})
    assert res.returncode != 0 and "Traceback" in res.stderr


@pytest.mark.parametrize("args, words", [
    (["--ratios", "nan"], "--ratios nan"),
    (["--ratios", "0.15", "2"], "between 0 and 1"),
    (["--darks", "-1"], "--darks -1"),
    (["--frames", "0"], "--frames 0"),
])
def test_sim_run_refuses_bad_counts_and_ratios_before_simulating(args, words, tmp_path):
    one_line_error(run("sim", "run", "--preset", "seed-breast", *args, "-o", tmp_path / "sim.h5", "-q"), words)
    assert not any(tmp_path.iterdir())


def test_demo_refuses_an_unknown_scene_before_claiming_its_folder(tmp_path):
    one_line_error(run("demo", "-o", tmp_path / "demo", "--preset", "nosuch", "-q"), "nosuch")
    assert not (tmp_path / "demo").exists()
