"""Files made to hurt: each gives one clear line and exit code 2, within the memory budget.

Memory cases run the command in a subprocess limited by ``resource.setrlimit(RLIMIT_AS)``: a
reader that allocated what the header declares would die with MemoryError (or be killed); the
budget check must refuse first, naming the file. The other command runs are in this process
(``conftest.run_cli``): they check a refusal's line, exit code and files, which need no process
of their own; ``--debug``'s traceback is checked in a subprocess too (the interpreter prints it).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import resource
import struct
import subprocess
import sys

import h5py
import numpy as np
import pytest
import tifffile
from conftest import ITEX_DIR as ITEX
from conftest import info_items, needs_itex, run_cli, synthetic

from radiokit.errors import FormatError
from radiokit.io import ExperimentWriter, ImageKey, memory_budget, open_frames, parse_size, read
from radiokit.io._itex import parse_comment

AS_LIMIT = 1 << 30  # 1 GiB of address space: python, numpy, h5py and scipy fit; the bombs do not


def run(*args, limit=None, env=None, cwd=None):
    def preexec():
        if limit:
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run(
        [sys.executable, "-m", "radiokit.cli", *map(str, args)],
        capture_output=True,
        text=True,
        preexec_fn=preexec,
        cwd=cwd,
        env={
            **os.environ,
            "PYTHONWARNINGS": "ignore",
            "OMP_NUM_THREADS": "1",
            "OPENBLAS_NUM_THREADS": "1",
            **(env or {}),
        },
    )


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
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
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
    """A few KB declaring (10, 100000, 100000) uint16 frames: 186 GiB. One chunk is written
    through a filter whose ratio has no bound (scale-offset: a constant chunk takes a few bytes),
    so the storage cannot prove the rest unwritten (check_written) and the budget must refuse it."""
    path = tmp_path / "bomb.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset(
            "entry/instrument/detector/data",
            shape=(10, 100_000, 100_000),
            dtype="u2",
            chunks=(1, 100, 100),
            scaleoffset=0,
        )[0, :100, :100] = 7
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
    args = {
        "info": ["info", hdf5_bomb],
        "correct": ["correct", hdf5_bomb, "-q", "-o", tmp_path / "out.h5"],
        "process": ["process", hdf5_bomb, "-q", "-o", tmp_path / "res"],
        "register": [
            "register",
            hdf5_bomb,
            hdf5_bomb,
            "--dataset",
            "entry/instrument/detector/data",
            "-o",
            tmp_path / "reg.h5",
        ],
    }[cmd]
    res = run(*args, limit=AS_LIMIT, env={"RADIOKIT_MEMORY_BUDGET": "256MiB"})
    one_line_error(res, f"radiokit {cmd}: ", "bomb.h5", "memory budget")
    assert not any(p.name not in ("bomb.h5",) for p in tmp_path.iterdir())


def test_hdf5_memory_bomb_is_refused_by_the_default_budget(tmp_path):
    # no variable: half the available memory (or of the address-space limit, here 1 GiB). A frame
    # of 763 MiB, every chunk stored (1:1026, below the thresholds of check_proportion, which
    # would refuse hdf5_bomb before the budget is asked)
    path = _zstd_chunks(tmp_path / "bomb.h5", (1, 20_000, 20_000), (1, 2000, 2000), 0, codec="gzip")
    env = {k: v for k, v in os.environ.items() if k != "RADIOKIT_MEMORY_BUDGET"}
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", "info", "--dataset", "data", path],
        capture_output=True,
        text=True,
        env=env,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT)),
    )
    one_line_error(res, "bomb.h5", "over the memory budget of 512.0 MiB")


def test_hdf5_frames_never_written_are_refused_before_any_allocation(tmp_path):
    """A 6 KB file declaring (2, 40000, 40000) uint16 frames, none of them written: within the
    default budget of a large machine, so `info` read 6.4 GB of fill value (6 GB resident, 15 s).
    Its storage says nothing was written: refused in one line, under 1 GiB of address space and
    whatever the budget."""
    path = tmp_path / "unwritten.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("scan/data", shape=(2, 40_000, 40_000), dtype="u2", chunks=(1, 40_000, 40_000))
    assert path.stat().st_size < 20_000
    res = run("info", path, "--dataset", "scan/data", limit=AS_LIMIT, env={"RADIOKIT_MEMORY_BUDGET": "1TiB"})
    one_line_error(res, "radiokit info: ", "unwritten.h5", "/scan/data", "stores nothing: never written")


@pytest.mark.parametrize("compression", [None, "gzip", "lzf"])
def test_hdf5_preallocated_frames_partly_written_are_refused_not_read_as_zeros(compression, tmp_path):
    """A writer that preallocated 6 frames and stopped after 2: the other 4 read as the fill value
    (frames of zeros, dark frames to a calibration). More than one chunk short of what the
    filters can have compressed is refused; the frames of a complete file read value for value."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 4096, (6, 64, 80)).astype(np.uint16)
    path = tmp_path / "stopped.h5"
    with h5py.File(path, "w") as h5:
        ds = h5.create_dataset("data", shape=frames.shape, dtype="u2", chunks=(1, 64, 80), compression=compression)
        ds[:2] = frames[:2]
    # uncompressed, the storage shows it on opening; compressed, the first frame never written does
    words = "/data declares 6x64x80 uint16 (61440 bytes) but stores 20480 bytes: parts never written"
    words = re.escape(words if compression is None else "frame 2 of /data was never written")
    with pytest.raises(FormatError, match=f"stopped.h5: {words}"):
        read(path, dataset="data")
    with h5py.File(path, "a") as h5:
        h5["data"][2:] = frames[2:]
    np.testing.assert_array_equal(read(path, dataset="data").data, frames)


def test_hdf5_frames_of_zeros_compressed_as_far_as_deflate_goes_still_read(tmp_path):
    """An honest stack of constant frames compresses about 1000:1 under gzip: within deflate's
    bound, so not taken for unwritten storage."""
    frames = np.zeros((8, 512, 512), np.uint16)
    path = tmp_path / "zeros.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("data", data=frames, chunks=(1, 512, 512), compression="gzip", compression_opts=9)
        assert h5["data"].id.get_storage_size() * 500 < frames.nbytes
    np.testing.assert_array_equal(read(path, dataset="data").data, frames)


@pytest.fixture
def many_frames(tmp_path):
    """A 14 kB HDF5 file declaring 10**8 frames of 128 x 128 (a chunked dataset, one chunk
    written): each frame is small, so no one frame is over the budget; the count is the bomb.
    Scale-offset (no bound on its ratio) keeps the storage from proving the rest unwritten."""
    path = tmp_path / "many.h5"
    with h5py.File(path, "w") as h5:
        ds = h5.create_dataset("scan/data", shape=(10**8, 128, 128), dtype="u2", chunks=(1, 128, 128), scaleoffset=0)
        ds[0] = 1000
    assert path.stat().st_size < 50_000
    return path


def test_a_file_declaring_1e8_frames_is_refused_by_its_output_size_not_by_memory(many_frames, tmp_path):
    """``correct`` planned every frame as a Python tuple before anything else (10**8 tuples, ~10 GB):
    MemoryError under 1 GiB of address space, and on a big machine minutes of allocation. Now the
    frames are planned lazily and the 6 TiB float32 output is refused in one line, in bounded memory.
    The budget is given (the default's, under AS_LIMIT); without it the file is not taken for a
    decompression bomb either (3 TiB declared from 14 kB): what is judged is what a read decodes,
    and a frame never written decodes nothing, refused as such."""
    from radiokit.calibrate import Calibration

    budget = {"RADIOKIT_MEMORY_BUDGET": "512MiB"}
    rng = np.random.default_rng(0)
    cal = Calibration.from_frames(
        rng.normal(100, 2, (4, 128, 128)).astype(np.uint16), rng.normal(3000, 30, (4, 128, 128)).astype(np.uint16)
    )
    cal.save(tmp_path / "cal.h5")
    for out in ("out.h5", "out.tif"):
        res = run(
            "correct",
            many_frames,
            "--dataset",
            "scan/data",
            "--cal",
            tmp_path / "cal.h5",
            "-q",
            "-o",
            tmp_path / out,
            limit=AS_LIMIT,
            env=budget,
        )
        one_line_error(res, out, "no space left", "needs about 6.0 TiB")
    # info samples frames 0, 5e7 and 1e8 - 1: the middle one was never written (one chunk is)
    res = run("info", many_frames, "--dataset", "scan/data", "--sample", "3", limit=AS_LIMIT, env=budget)
    one_line_error(res, "many.h5", "frame 50000000 of /scan/data was never written")
    res = run("info", many_frames, "--dataset", "scan/data", "--sample", "3", limit=AS_LIMIT)
    one_line_error(res, "many.h5", "frame 50000000 of /scan/data was never written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.h5", "many.h5"]


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
    tifffile.imwrite(
        path, np.zeros((4, 1024, 1024), np.uint16), photometric="minisblack"
    )  # 2 MiB a frame, 8 MiB in all
    with pytest.raises(FormatError, match=r"big.tif: one 1024x1024 uint16 frame would need 2.0 MiB"):
        read(path, budget="1MiB")
    with pytest.raises(FormatError, match=r"4 frame\(s\).* would need 8.0 MiB"):
        read(path, budget="5MiB")
    assert read(path, budget="9MiB").data.shape == (4, 1024, 1024)
    # frame by frame, a stack larger than the budget can still be streamed
    res = run_cli("info", path, "--all", env={"RADIOKIT_MEMORY_BUDGET": "3MiB"})
    assert res.returncode == 0, res.stderr


def _one_pixel_pages(path, n, back=None):
    """A classic TIFF of ``n`` IFDs of a 1 x 1 uint16 page, all on one 2-byte strip (100 bytes a
    page); with ``back``, the last IFD's next is page ``back``'s again (a loop)."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
    from bench_tiff_pages import one_pixel_pages

    one_pixel_pages(path, n, back=back)
    return path


def test_a_tiff_of_many_small_pages_is_refused_before_its_pages_are_built(tmp_path):
    """300,000 one-pixel pages (a 30 MB file) took 860 MB and 25 s to open, under any budget: no
    frame is larger than a pixel, the pages themselves are the bomb (about 3 KB each, open)."""
    path = _one_pixel_pages(tmp_path / "pages.tif", 3000)
    cal = tmp_path / "cal.h5"
    for name, level in (("dark", 100), ("flat", 3000)):
        frames = np.random.default_rng(0).normal(level, 5, (5, 1, 1)).astype(np.uint16)
        tifffile.imwrite(tmp_path / f"{name}.tif", frames, photometric="minisblack")
    calibrate = ("calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flat.tif", "-o", cal)
    assert run_cli(*calibrate).returncode == 0
    for cmd in ("info", "correct"):
        args = ("--cal", cal, "-o", tmp_path / "o.h5") if cmd == "correct" else ()
        res = run_cli(cmd, path, *args, env={"RADIOKIT_MEMORY_BUDGET": "8MiB"})
        one_line_error(res, "pages.tif: TIFF of at least 2", " pages", "more than the memory budget of 8.0 MiB")
    with pytest.raises(FormatError, match="pages.tif: TIFF of at least"):
        open_frames(path, budget="8MiB")
    with open_frames(path, budget="16MiB") as src:  # 3000 pages of 8 tags: 9 MB
        assert (len(src), src.frame_shape) == (3000, (1, 1))


def test_a_tiff_ifd_chain_leading_back_after_100_pages_is_named_a_loop(tmp_path):
    """tifffile looks for a loop at its 100th IFD only: a 20 KB file whose 200th IFD led back to the
    150th was followed until memory ran out (`radiokit info` never returned)."""
    path = _one_pixel_pages(tmp_path / "loop.tif", 200, back=150)
    with pytest.raises(FormatError, match="IFD chain loops: the IFD after page 199 is page 150's again"):
        open_frames(path)


@pytest.mark.parametrize(
    "text, expected", [("2GiB", 2 * 2**30), ("500M", 500 * 10**6), ("1e9", 10**9), ("64 kib", 64 * 1024), ("123", 123)]
)
def test_budget_sizes(text, expected):
    assert parse_size(text) == expected
    assert memory_budget(text) == expected


def test_the_default_budget_counts_reclaimable_cache_and_a_containers_limit(tmp_path, monkeypatch):
    """The default budget is half the memory the kernel says is available (MemAvailable: free pages
    plus the page cache it can drop), not the free pages alone: on a lab PC that has just copied a
    day's radiographs the cache holds most of the memory, and free pages (SC_AVPHYS_PAGES) read
    1.7-5 GiB of 22.6 GiB available on this machine, run to run, so a 2240 x 2240 process was
    refused at random. A cgroup's limit (a container, CI) caps it. The kernel files are written
    here (a fake: a page-cache state and a cgroup limit cannot be set up by a test)."""
    import radiokit.io._budget as budget

    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       24000000 kB\nMemFree:         1000000 kB\nMemAvailable:   20000000 kB\n")
    monkeypatch.setattr(budget, "_MEMINFO", meminfo)
    monkeypatch.setattr(budget, "_CGROUP_ROOT", tmp_path / "nothing")
    assert budget._physical_available() == 20000000 * 1024
    cgroup = tmp_path / "cg"
    (cgroup / "lab" / "job").mkdir(parents=True)
    (cgroup / "lab" / "job" / "memory.max").write_text("max\n")
    (cgroup / "lab" / "job" / "memory.current").write_text("7000000000\n")
    (cgroup / "lab" / "memory.max").write_text("8000000000\n")  # the limit is the parent's (a slice, a job)
    (cgroup / "lab" / "memory.current").write_text("7500000000\n")
    self_cgroup = tmp_path / "self_cgroup"
    self_cgroup.write_text("0::/lab/job\n")
    monkeypatch.setattr(budget, "_CGROUP_ROOT", cgroup)
    monkeypatch.setattr(budget, "_SELF_CGROUP", self_cgroup)
    assert budget._physical_available() == 500_000_000  # no cache said: all of the usage counts
    # s40rr: usage counts the page cache the kernel drops first; a container that has read more
    # frames than its limit sits at it, and its budget read 2 KiB
    (cgroup / "lab" / "memory.stat").write_text("anon 1000000000\nfile 6500000000\n")
    assert budget._physical_available() == 7_000_000_000
    (cgroup / "lab" / "memory.max").write_text("max\n")
    assert budget._physical_available() == 20000000 * 1024
    (cgroup / "memory" / "lab").mkdir(parents=True)  # cgroup v1: the memory controller's own tree
    (cgroup / "memory" / "lab" / "memory.limit_in_bytes").write_text("6000000000\n")
    (cgroup / "memory" / "lab" / "memory.usage_in_bytes").write_text("5900000000\n")
    (cgroup / "memory" / "lab" / "memory.stat").write_text("cache 100\ntotal_cache 3900000000\n")
    self_cgroup.write_text("4:memory:/lab\n1:cpu:/\n")
    assert budget._physical_available() == 4_000_000_000
    (cgroup / "memory" / "lab" / "memory.limit_in_bytes").write_text("9223372036854771712\n")  # v1's "none"
    assert budget._physical_available() == 20000000 * 1024
    meminfo.write_text("MemTotal: 24000000 kB\n")  # a kernel before 3.14: no MemAvailable
    free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert abs(budget._physical_available() - free) < 2**28  # free pages move between the two reads


@pytest.mark.parametrize("text", ["lots", "-5M", "0", "2 parsecs", "nan"])
def test_a_bad_budget_is_one_line(text, tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    one_line_error(run_cli("info", path, env={"RADIOKIT_MEMORY_BUDGET": text}), "RADIOKIT_MEMORY_BUDGET", text)


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


@pytest.mark.parametrize(
    "kind, words",
    [
        ("external raw storage", "external raw files"),
        ("external link", "external link"),
        ("virtual dataset", "virtual dataset"),
        ("linked experiment", "external link"),
    ],
)
def test_data_outside_the_file_is_refused_unless_allowed(kind, words, outside):
    files, secret = outside
    path = files[kind]
    hints = {} if kind == "linked experiment" else {"dataset": "frames"}
    with pytest.raises(FormatError, match=f"{path.name}: .*{words}.*allow_external=True"):
        read(path, **hints)
    data = read(path, allow_external=True, **hints).data
    if kind == "external raw storage":  # what was refused: the private file's bytes as pixels
        assert data.tobytes() == secret.read_bytes()
    res = run_cli("info", path, *(["--format", "hdf5"] if not hints else []))
    if hints:  # the CLI reads a named dataset only in register; info reads experiment files
        res = run_cli("register", path, path, "--dataset", "frames", "-o", path.with_name("reg.h5"))
    one_line_error(res, path.name, "allow_external")


# -- parsing -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, text",
    [
        ("spaces before =", "a" + " " * 300_000 + "b=1"),
        ("unclosed brackets", "[" * 300_000),
        ("bracketed text", "[abc" * 75_000),
        ("lines of blanks", (" " * 100 + "\n") * 3000),
        ("unclosed quote", 'a="' + "x" * 300_000),
    ],
)
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


def test_thresholds_are_checked_together_not_one_at_a_time():
    """Found in review: each --threshold was checked alone against the defaults, so
    dead_below=0.02 with under_below=0.05 (a valid pair) was refused as dead_below 0.1 > 0.05."""
    from radiokit.cli import _parse_thresholds

    assert _parse_thresholds(["dead_below=0.02", "under_below=0.05"]) == {"dead_below": 0.02, "under_below": 0.05}
    with pytest.raises(ValueError, match="dead_below"):
        _parse_thresholds(["dead_below=0.2", "under_below=0.05"])


# -- bad values --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "value",
    [
        *["eps=nan", "eps=inf", "dead_below=-inf", "saturation=abc", "nosuch=1", "eps"],
        # out of their domains: dead_below=5 marked every pixel dead and wrote the calibration
        *["dead_below=5", "eps=-1", "saturation=0", "over_above=0.5", "line_fraction=2", "smooth_block=1.5"],
    ],
)
def test_a_bad_threshold_is_refused_before_anything_is_written(value, tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    res = run_cli("calibrate", "--experiment", path, "--threshold", value, "-o", tmp_path / "cal.h5")
    one_line_error(res, "--threshold", value)
    assert not (tmp_path / "cal.h5").exists()


def test_calibrate_refuses_an_experiment_and_dark_or_flat_files_together(tmp_path):
    path = _experiment(tmp_path / "exp.h5")  # the --dark files were silently not used
    res = run_cli("calibrate", "--experiment", path, "--dark", path, "-o", tmp_path / "cal.h5")
    one_line_error(res, "--experiment", "not both")
    assert not (tmp_path / "cal.h5").exists()


@pytest.mark.parametrize("option", ["--dark-dataset", "--flat-dataset", "--dataset"])
def test_calibrate_refuses_an_experiment_with_a_kind_s_dataset(option, tmp_path):
    """s49rv: --dark-dataset / --flat-dataset name the --dark / --flat files' dataset; beside
    --experiment they were silently not used (exit 0), as the --dark files once were. So was
    --dataset (an experiment file's layout is fixed, its darks and flats told apart by image_key)."""
    path = _experiment(tmp_path / "exp.h5")
    res = run_cli("calibrate", "--experiment", path, option, "no/such", "-o", tmp_path / "cal.h5")
    one_line_error(res, "--experiment", option)
    assert not (tmp_path / "cal.h5").exists()


def test_nonfinite_pixels_are_filled_and_flagged_in_the_streaming_path(tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    f = read(path)
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", path, "-o", cal).returncode == 0
    proj = f.data[f.meta["image_key"] == 0].astype(np.float32)
    proj[0, 5, 5], proj[1, 10, 20], proj[2, 0, 0] = np.nan, np.inf, -np.inf
    proj[2, 20:22, 30:32] = np.nan  # a small cluster
    tif = tmp_path / "frames.tif"
    tifffile.imwrite(tif, proj, photometric="minisblack")
    res = run_cli("correct", tif, "--cal", cal, "-q", "-o", tmp_path / "out.h5")
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


def test_correct_says_its_filled_pixels_may_be_nan_not_only_non_positive(tmp_path):
    # 100 NaN pixels were reported as "100 non-positive (filled)"
    path = _experiment(tmp_path / "exp.h5")
    f = read(path)
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", path, "-o", cal).returncode == 0
    proj = f.data[f.meta["image_key"] == 0][:1].astype(np.float32)
    proj[0, 10:20, 10:20] = np.nan
    tifffile.imwrite(tmp_path / "nan.tif", proj, photometric="minisblack")
    res = run_cli("correct", tmp_path / "nan.tif", "--cal", cal, "-o", tmp_path / "out.h5")
    assert res.returncode == 0, res.stderr
    assert "100 non-positive or non-finite (filled)" in res.stdout, res.stdout


@pytest.mark.parametrize("hole", ["10x10 block", "column gap 12 px wide", "corner 8x8"])
def test_nonfinite_regions_wider_than_the_fill_radius_are_filled_not_taken_for_opaque(hole, tmp_path):
    """Float frames of other labs mark unknown pixels NaN: a masked region, a tiled detector's gap
    (Eiger, Pilatus: 10-37 px). Filling reached 2 px from a valid pixel; inside, a NaN kept the
    clamp of an opaque pixel (raw - dark = half a count: -ln 8.7 here), a bright blob to the
    registration and the ROIs although the README says NaN pixels are filled. Unknown pixels now
    take the nearest filled value: within the frame's real values, next to their neighbours. A
    finite raw value at or below the dark still means opaque and keeps its clamp."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames

    rng = np.random.default_rng(0)
    shape = (64, 80)
    cal = Calibration.from_frames(
        rng.normal(100, 2, (8,) + shape).astype(np.float32), rng.normal(3100, 30, (8,) + shape).astype(np.float32)
    )
    raw = rng.normal(1600, 20, shape).astype(np.float32)  # transmission about 0.5
    where = {
        "10x10 block": np.s_[20:30, 30:40],
        "column gap 12 px wide": np.s_[:, 34:46],
        "corner 8x8": np.s_[:8, :8],
    }[hole]
    raw[where] = np.nan
    raw[50:60, 5:15] = 90.0  # opaque: below the dark
    out, report = correct_frames(cal, raw, return_report=True)
    assert report.nonpositive[0] == np.isnan(raw).sum() + 100
    good = np.isfinite(raw) & (raw > 200)
    lo, hi = out[good].min(), out[good].max()
    assert lo <= out[where].min() and out[where].max() <= hi, (out[where].min(), out[where].max(), lo, hi)
    assert out[52:58, 7:13].min() > 5.0  # the opaque block keeps its clamp: -ln(0.5 / 3000)


def test_process_says_how_many_nan_pixels_it_filled_in_the_projections(tmp_path):
    """Saturated projection pixels were named in a warning, NaN or inf ones filled in silence;
    both are pixels whose intensity is unknown that a ROI or the registration may lean on."""
    from radiokit.calibrate import CalibrationWarning
    from radiokit.pipeline import load_steps

    path = tmp_path / "exp.h5"
    _experiment(path)
    with h5py.File(path, "a") as h5:  # another lab's float frames, a 4x5 block of one masked
        frames = h5["entry/instrument/detector/data"][()].astype(np.float32)
        frames[7, 10:14, 10:15] = np.nan
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = frames
    with pytest.warns(
        CalibrationWarning, match=r"exp.h5: NaN or inf pixels in the projections \(step 2: 20 in 1 of 1 frame\)"
    ):
        steps = load_steps(path)
    assert all(np.isfinite(image).all() for image in steps.images)


def test_process_counts_every_nan_pixel_and_the_frames_holding_them(tmp_path):
    """s46: the count was a per-frame average, printed rounded: 3 NaN pixels in one of a step's 4
    frames read "step 2: 1", one alone "step 2: 0" (a warning of nothing). The true count, and
    how many of the step's frames hold them."""
    from radiokit.calibrate import CalibrationWarning
    from radiokit.pipeline import load_steps

    shape, rng = (32, 40), np.random.default_rng(3)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        for key, level in ((ImageKey.DARK, 100), (ImageKey.FLAT, 3000)):
            for _ in range(3):
                w.append(rng.integers(level - 10, level + 10, shape), image_key=key)
        for s in (1, 2):
            for _ in range(4):
                w.append(rng.integers(900, 1100, shape), image_key=ImageKey.PROJECTION, step=s)
    with h5py.File(path, "a") as h5:
        frames = h5["entry/instrument/detector/data"][()].astype(np.float32)
        frames[6 + 4 + 1, 3, 4:7] = np.nan  # step 2's second frame: 3 pixels
        frames[6 + 4 + 3, 20, 20] = np.inf  # and its fourth: 1
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = frames
    with pytest.warns(CalibrationWarning, match=r"exp.h5: NaN or inf pixels .*\(step 2: 4 in 2 of 4 frames\)"):
        load_steps(path)


def test_a_frame_of_only_nan_is_refused(tmp_path):
    path = _experiment(tmp_path / "exp.h5")
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", path, "-o", cal).returncode == 0
    tif = tmp_path / "nan.tif"
    tifffile.imwrite(tif, np.full((2, 32, 40), np.nan, np.float32))
    one_line_error(run_cli("correct", tif, "--cal", cal, "-q", "-o", tmp_path / "out.h5"), "only NaN or inf")
    assert not (tmp_path / "out.h5").exists()


# -- errors instead of tracebacks --------------------------------------------------------------
@pytest.mark.parametrize(
    "steps, args, printed",
    [
        (False, [], ["projections  3", "steps  []"]),  # an experiment without steps
        (True, ["--sample", "3"], ["(in 3 of 9 frames)"]),  # a sample of frames, not the whole file
    ],
)
def test_info_prints_what_it_read(steps, args, printed, tmp_path):
    path = _experiment(tmp_path / "exp.h5", step=steps)
    res = run_cli("info", path, *args)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert all(p in info_items(res.stdout) for p in printed), res.stdout


@pytest.mark.parametrize("case", ["no projections", "one step", "no darks", "not hdf5", "missing", "a folder"])
def test_process_on_unusable_files(case, tmp_path):
    path = tmp_path / "exp.h5"
    if case == "no projections":
        _experiment(path, projections=False)
    elif case == "one step":
        with ExperimentWriter(path, shape=(16, 16), pixel_size_mm=0.05) as w:
            w.append(np.full((16, 16), 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full((16, 16), 3000, np.uint16), image_key=ImageKey.FLAT)
            w.append(np.full((16, 16), 1000, np.uint16), image_key=ImageKey.PROJECTION, step=1)
    elif case == "no darks":
        with ExperimentWriter(path, shape=(16, 16), pixel_size_mm=0.05) as w:
            w.append(np.full((16, 16), 1000, np.uint16), image_key=ImageKey.PROJECTION, step=1)
    elif case == "not hdf5":
        path.write_bytes(b"hello" * 100)
    elif case == "a folder":
        path.mkdir()
    res = run_cli("process", path, "-q", "-o", tmp_path / "res")
    one_line_error(res, "radiokit process: ", "exp.h5")
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("shape, rois", [((3, 3), []), ((1, 40), ["--inclusion", "0", "1", "0", "9"])])
def test_process_names_frames_too_small_to_register_before_any_work(shape, rois, tmp_path):
    """s49off: a 3x3 experiment was told "too small to detect an inclusion in; pass ... --inclusion";
    given the ROIs, "fixed image is too small to register", after calibrating and correcting. The
    frames are judged first: register needs 8 px a side, ROIs or not."""
    path = _experiment(tmp_path / "exp.h5", shape=shape)
    res = run_cli("process", path, "-q", "-o", tmp_path / "res", *rois)
    one_line_error(res, "exp.h5", f"{shape[0]}x{shape[1]}", "too small to register", "8 px")
    assert "inclusion" not in res.stderr, res.stderr  # no advice that leads on to the next refusal
    assert not (tmp_path / "res").exists()


def test_process_names_frames_too_large_to_register_before_any_work(tmp_path):
    """Frames over OpenCV's remap limit (32766 px a side) are refused with the frames' size before
    calibrating and correcting, as frames too small are: register() refuses them, after that work."""
    path = _experiment(tmp_path / "exp.h5", shape=(8, 32767))
    res = run_cli("process", path, "-q", "-o", tmp_path / "res", "--inclusion", "0", "8", "0", "9")
    one_line_error(res, "exp.h5", "8x32767", "too large to register", "32766 px")
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--fixed-frame", "7"], "frame 7"),
        (["--roi", "0", "500", "0", "10"], "--roi"),
        (["--method", "nosuch"], "nosuch"),
        (["--method", "tvl1", "--preset", "weak"], "--preset weak"),  # was dropped without a word
        (["--png", "reg.txt"], "--png"),  # matplotlib refused it after reg.h5 was written
        (["--png", "reg"], "--png"),
    ],
)
def test_register_bad_arguments(args, words, tmp_path):
    img, other = tmp_path / "img.tif", tmp_path / "other.tif"  # one image twice is refused on its own
    tifffile.imwrite(img, np.random.default_rng(0).random((32, 32), np.float32))
    tifffile.imwrite(other, np.random.default_rng(1).random((32, 32), np.float32))
    one_line_error(run_cli("register", img, other, *args, "-o", tmp_path / "reg.h5", cwd=tmp_path), words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.tif", "other.tif"]


@pytest.mark.parametrize(
    "args, words",
    [
        (["--k", "0"], "--k 0"),  # IF(0) = 1 whatever the data
        (["--k", "1", "-2"], "--k 1 -2"),
        (["--k", "1e308"], "--k 1e+308"),  # overflowed float32 after the registrations
        (["--crop-mm", "-5"], "--crop-mm -5"),
        (["--crop-mm", "nan"], "--crop-mm nan"),
        (["--method", "nosuch"], "--method 'nosuch'"),  # found only at the first registration
        (["--cross-check", "nosuch"], "--cross-check 'nosuch'"),  # only after the main registration
        (["--cross-check", "rc"], "--cross-check rc"),  # the method itself: skipped without a word
        (["--method", "ssd", "--cross-check", "ssd"], "--cross-check ssd"),
        (["--method", "tvl1", "--preset", "weak"], "--preset weak"),  # a traceback
        (["--workers", "0"], "--workers 0"),
        (["--scheduler-timeout", "0"], "--scheduler-timeout 0"),
        (["--scheduler-timeout", "nan"], "--scheduler-timeout nan"),
        (["--control", "missing.h5"], "--control missing.h5"),  # only after the main file's work
        (["--control", "."], "is a folder"),
    ],
)
def test_process_refuses_bad_options_before_any_work(args, words, tmp_path):
    path = _experiment(tmp_path / "exp.h5")  # no inclusion: any work would fail saying so
    one_line_error(run_cli("process", path, *args, "-o", tmp_path / "res", cwd=tmp_path), words)
    assert not (tmp_path / "res").exists()


def test_process_names_a_file_that_is_not_an_experiment_and_a_control_of_another_size(tmp_path):
    exp = _experiment(tmp_path / "exp.h5")
    cal = tmp_path / "cal.h5"  # a calibration was read as frames: two warnings, then "found steps []"
    assert run_cli("calibrate", "--experiment", exp, "-o", cal).returncode == 0
    one_line_error(run_cli("process", cal, "-q", "-o", tmp_path / "res"), "cal.h5", "calibration", "not an experiment")
    # a control on another grid was measured in the main file's pixel ROIs
    other = _experiment(tmp_path / "other.h5", shape=(40, 32))
    one_line_error(run_cli("process", exp, "--control", other, "-q", "-o", tmp_path / "res"), "other.h5", "40x32")
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize(
    "steps, words",
    [
        ((-1, -1, -1), "found none; 3 projection(s) carry no step number"),
        ((2, 2, -1), "found step 2 only; 1 projection"),
    ],
)
def test_process_says_what_steps_a_file_of_fewer_than_two_holds(steps, words, tmp_path):
    # projections written without a step number (-1) were reported as "found steps []"
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(16, 16), pixel_size_mm=0.05) as w:
        w.append(np.full((16, 16), 100, np.uint16), image_key=ImageKey.DARK)
        w.append(np.full((16, 16), 3000, np.uint16), image_key=ImageKey.FLAT)
        for step in steps:
            w.append(np.full((16, 16), 2000, np.uint16), image_key=ImageKey.PROJECTION, step=step)
    one_line_error(run_cli("process", path, "-q", "-o", tmp_path / "res"), "exp.h5", "two compression steps", words)


def test_process_on_a_folder_says_it_is_a_folder(tmp_path):
    # its default results folder is the folder itself: "is the input exp: never overwritten" before
    (tmp_path / "exp").mkdir()
    one_line_error(run_cli("process", "exp", "-q", cwd=tmp_path), "exp: is a folder, not an experiment file")


@pytest.mark.parametrize(
    "args, words",
    [
        (["register", "a.tif", "b.tif", "-o", "r.h5", "--preset", "nosuch"], "--preset"),
        (["process"], "files"),
        (["info", "--sample", "x", "a.tif"], "--sample"),
        (["sim", "run", "-o", "s.h5"], "radiokit sim run: "),
        (["nosuch"], "nosuch"),
    ],
)
def test_a_usage_error_is_one_line(args, words, tmp_path):
    # argparse printed the whole usage (up to eight lines) above its error
    line = one_line_error(run_cli(*args, cwd=tmp_path), words)
    assert line.endswith("--help)")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "env", [{"RADIOKIT_MEMORY_BUDGET": "abc"}, {"RADIOKIT_THREADS": "abc"}, {"RADIOKIT_THREADS": "0"}]
)
def test_a_bad_environment_setting_is_named_before_any_file(env, tmp_path):
    # it was blamed on the first file that needed it ("exp.h5: cannot be read as hdf5: ...")
    exp = synthetic(tmp_path / "exp.h5")
    ((name, value),) = env.items()
    line = one_line_error(run_cli("info", exp, env=env), f"{name}={value!r}")
    assert "exp.h5" not in line


def test_debug_shows_the_traceback(tmp_path):
    res = run("info", tmp_path / "missing.h5", env={"RADIOKIT_DEBUG": "1"})
    assert res.returncode != 0 and "Traceback" in res.stderr


@pytest.mark.parametrize(
    "args, words",
    [
        (["sim", "run", "--preset", "seed-breast", "--ratios", "nan", "-o", "sim.h5"], "--ratios nan"),
        (["sim", "run", "--preset", "seed-breast", "--ratios", "0.15", "2", "-o", "sim.h5"], "must lie in [0, 0.9)"),
        (["sim", "run", "--preset", "seed-breast", "--darks", "-1", "-o", "sim.h5"], "--darks -1"),
        (["sim", "run", "--preset", "seed-breast", "--frames", "0", "-o", "sim.h5"], "--frames 0"),
        # a file nothing could then correct ("holds no darks"), written for 25 s
        (["sim", "run", "--preset", "seed-breast", "--darks", "0", "-o", "sim.h5"], "--darks 0"),
        (["sim", "run", "--preset", "seed-breast", "--flats", "0", "-o", "sim.h5"], "--flats 0"),
        # merged into one state without a word
        (["sim", "run", "--preset", "seed-breast", "--ratios", "0.2", "0.2", "-o", "sim.h5"], "--ratios 0.2 0.2"),
        (["sim", "run", "--preset", "seed-breast", "--seed", "-1", "-o", "sim.h5"], "--seed -1"),  # after the mechanics
        (["sim", "run", "--preset", "seed-breast", "--save-scene", "sim.h5", "-o", "sim.h5"], "the same file as -o"),
        # petabytes of frames: refused by the free space before the mechanics, the scene not written first
        (
            [
                "sim",
                "run",
                "--preset",
                "seed-breast",
                "--frames",
                "100000000",
                "--save-scene",
                "s.toml",
                "-o",
                "sim.h5",
            ],
            "no space left",
        ),
        # before claiming its folder, the option named (found by a new user: "unknown scene 'nosuch'")
        (["demo", "--preset", "nosuch", "-o", "demo"], "--preset nosuch: unknown scene"),
        (["demo", "--preset", "none.toml", "-o", "demo"], "--preset none.toml: no such scene file"),
        (["demo", "--frames", "0", "-o", "demo"], "--frames 0"),  # the claimed folder was left behind
        (["demo", "--method", "tvl1", "-o", "demo"], "--method tvl1"),  # found after both acquisitions
        (["demo", "--frames", "10000000", "-o", "demo"], "no space left"),  # terabytes of frames
    ],
)
def test_sim_and_demo_refuse_bad_arguments_before_writing_anything(args, words, tmp_path):
    one_line_error(run_cli(*args, "-q", cwd=tmp_path), words)
    assert not any(tmp_path.iterdir())


def test_sim_run_refuses_a_save_scene_link_in_a_loop_in_one_line(tmp_path):
    # Path.resolve() raised RuntimeError ("Symlink loop") under Python 3.11: a traceback
    (tmp_path / "a.toml").symlink_to("b.toml")
    (tmp_path / "b.toml").symlink_to("a.toml")
    args = ["sim", "run", "--preset", "seed-breast", "--save-scene", "a.toml", "-o", "sim.h5", "-q"]
    one_line_error(run_cli(*args, cwd=tmp_path), "a.toml: is a symbolic link in a loop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.toml", "b.toml"]


HOSTILE_TEXT = [
    "plain",
    'say "cheese"',
    "back\\slash C:\\new",
    "two\nlines",
    "tab\there",
    "''' and \"\"\"",
    "ünïcode µA",
    "# not a comment",
    "[not.a.table]",
    "key = value",
]


@pytest.mark.parametrize("text", HOSTILE_TEXT)
def test_a_scene_with_any_name_round_trips_through_toml(text):
    import tomllib

    from sim.scene import load_scene

    scene = load_scene("seed-breast")
    scene.name = text
    written = scene.to_toml()
    assert tomllib.loads(written) == scene.to_dict()
    assert type(scene).from_toml(written) == scene


@pytest.mark.parametrize("text", HOSTILE_TEXT)
def test_a_protocol_with_any_strings_round_trips_through_toml(text):
    import dataclasses
    import tomllib

    from acquisition.protocols.compression_series import load_protocol

    p = load_protocol(
        {
            "name": text,
            "detector": {"folder": text, "pattern": text, "shape": [8, 16]},
            "source": {"port": text, "kv_max": 80.0},
            "sim": {"scene": text},
        }
    )
    written = p.to_toml()
    data = tomllib.loads(written)
    assert data["name"] == data["detector"]["folder"] == data["source"]["port"] == data["sim"]["scene"] == text
    assert data["source"]["limits"] == {"kv_max": 80.0}
    assert "preset" not in data["detector"] and "baudrate" not in data["source"]  # None: left out
    assert load_protocol(written, text=True) == p
    assert dataclasses.asdict(load_protocol(written, text=True)) == dataclasses.asdict(p)


# -- the typed layouts fed files radiokit never wrote --------------------------------------------
# Each layout is built valid by radiokit's own writer, then one thing is broken with h5py. Every
# reader must answer with one FormatError line naming the file: never another exception (a
# KeyError, a RuntimeError from libhdf5, a MemoryError), never a silently wrong record.
from radiokit.io import (  # noqa: E402
    EnhancedImages,
    RegistrationRecord,
    ResultsRecord,
    SimulationRecord,
    StackWriter,
    read_progress,
    read_registration,
    read_results,
    read_simulation,
    read_stack,
    write_registration,
    write_results,
)
from radiokit.results import SCHEMA_VERSION, Results, load_results  # noqa: E402

SMALL_BUDGET = "64MiB"  # the huge shapes below declare terabytes: refused whatever the machine has


def _registration_file(path):
    write_registration(
        path,
        RegistrationRecord(
            "rc",
            "a.h5",
            "b.h5",
            np.zeros((2, 4, 5), np.float32),
            np.ones((4, 5), np.float32),
            {"ok": True},
            np.full((4, 5), 0.5, np.float32),
        ),
    )


def _results_file(path):
    steps = np.ones((2, 4, 5), np.float32)
    write_results(
        path,
        ResultsRecord(
            source="exp.h5",
            results_json="{}",
            line_integral=steps,
            step=np.array([1, 2]),
            ratio=np.array([0.1, 0.2]),
            crop=np.array([0, 4, 0, 5]),
            pair=(2, 1),
            registration={"registered": steps[0]},
            enhanced={"log": EnhancedImages(steps[0], steps[1], {"1": steps[0]})},
            rois={"inclusion": np.array([0, 2, 0, 2])},
        ),
    )


def _stack_file(path):
    with StackWriter(path, (4, 5), meta={"source": "exp.h5", "cal": {"c": 1}}) as w:
        for i in range(2):
            w.append(np.full((4, 5), i, np.float32), step=i + 1)


def _truth_record(n_steps, shape):
    """A valid simulation truth of ``n_steps`` steps of ``shape``, one field for the last pair."""
    curve = np.linspace(0.1, 0.1 * n_steps, n_steps)
    return SimulationRecord(
        'name = "block"',
        curve,
        curve,
        curve,
        curve,
        curve,
        curve,
        np.zeros((n_steps, *shape), np.float32),
        np.zeros((n_steps, *shape), np.uint8),
        displacement={(n_steps - 1, n_steps): np.zeros((2, *shape), np.float32)},
    )


def _simulation_file(path):
    record = _truth_record(2, (4, 5))
    with ExperimentWriter(path, shape=(4, 5), pixel_size_mm=0.05) as w:
        for key in (ImageKey.DARK, ImageKey.FLAT):
            w.append(np.full((4, 5), 100 * (key + 1), np.uint16), image_key=key)
        w.write_simulation(record)


def _calibration_file(path):
    with h5py.File(path, "w") as h5:
        h5["calibration/dark"] = np.full((4, 5), 100.0)
        h5["calibration/flat"] = np.full((4, 5), 3000.0)


# layout -> (make a valid file, its reader, the dataset broken by the generic cases, its rank, dtype)
LAYOUTS = {
    "registration": (_registration_file, read_registration, "entry/registration/registered", 2, "f4"),
    "results": (_results_file, read_results, "entry/steps/line_integral", 3, "f4"),
    "stack": (_stack_file, read_stack, "entry/data/data", 3, "f4"),
    "simulation": (_simulation_file, read_simulation, "entry/simulation/line_integral", 3, "f4"),
    "progress": (_simulation_file, read_progress, "entry/instrument/detector/image_key", 1, "i1"),
    "calibration": (_calibration_file, read, "calibration/dark", 2, "f8"),
}


def _replace(h5, name, *args, **kwargs):
    """Put another dataset (or link) at ``name``."""
    del h5[name]
    if args and not kwargs and not isinstance(args[0], (tuple, np.ndarray)):
        h5[name] = args[0]
    else:
        h5.create_dataset(name, *args, **kwargs)


def _elsewhere(path, name, data):
    """A file beside ``path`` holding ``data`` at ``name``: what the links below point at."""
    other = path.with_name("other.h5")
    with h5py.File(other, "w") as h5:
        h5[name] = data
    return other


def _break(path, name, rank, dtype, case):
    """Break dataset ``name`` of the layout file ``path`` in the way ``case`` says."""
    if case == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        return
    if case == "not hdf5":
        path.write_bytes(b"this is a text file, whatever its name says\n" * 20)
        return
    valid_shape = (2, 4, 5)[-rank:] if rank > 1 else (8,)
    with h5py.File(path, "a") as h5:
        if case == "missing":
            del h5[name]
        elif case == "strings":
            _replace(h5, name, data=np.full(valid_shape, "abc", dtype=h5py.string_dtype()))
        elif case == "compound":
            _replace(h5, name, data=np.zeros(valid_shape, dtype=[("a", "f4"), ("b", "i2")]))
        elif case == "vlen":
            _replace(h5, name, shape=valid_shape[:1], dtype=h5py.vlen_dtype(np.float32))
        elif case == "wrong rank":
            _replace(h5, name, data=np.zeros((2,) * (rank + 2), dtype))
        elif case == "huge":  # a few KB declaring terabytes (one chunk written: see _huge)
            shape = {1: (10**12,), 2: (10**6, 10**6), 3: (10, 10**6, 10**6)}[rank]
            del h5[name]
            _huge(h5, name, shape, dtype)
            if "frames_complete" in h5["entry"].attrs if "entry" in h5 else False:
                h5["entry"].attrs["frames_complete"] = shape[0]  # the progress file promises them all
        elif case == "never written":  # allocated as written: libhdf5 reads the fill value
            _replace(h5, name, shape=valid_shape, dtype=dtype, chunks=valid_shape)
        elif case == "a group":
            del h5[name]
            h5.create_group(name)
        elif case == "external link":
            _replace(h5, name, h5py.ExternalLink(str(_elsewhere(path, name, np.ones(valid_shape, dtype))), name))
        elif case == "external storage":
            raw = path.with_name("raw.bin")
            np.ones(valid_shape, dtype).tofile(raw)
            _replace(h5, name, shape=valid_shape, dtype=dtype, external=[(str(raw), 0, raw.stat().st_size)])
        elif case == "virtual":
            other = _elsewhere(path, name, np.ones(valid_shape, dtype))
            layout = h5py.VirtualLayout(valid_shape, dtype)
            layout[...] = h5py.VirtualSource(str(other), name, valid_shape)
            del h5[name]
            h5.create_virtual_dataset(name, layout)
        elif case == "soft link circle":
            _replace(h5, name, h5py.SoftLink("/" + name + "_twin"))
            h5[name + "_twin"] = h5py.SoftLink("/" + name)
        elif case == "group in a circle":  # the layout's own group is a soft link to itself
            group = name.rsplit("/", 1)[0]
            del h5[group]
            h5[group] = h5py.SoftLink("/" + group)
        else:
            raise AssertionError(case)


GENERIC = [
    "truncated",
    "not hdf5",
    "missing",
    "strings",
    "compound",
    "vlen",
    "wrong rank",
    "huge",
    "never written",
    "a group",
    "external link",
    "external storage",
    "virtual",
    "soft link circle",
    "group in a circle",
]


def _refused(path, call, *needles):
    """``call()`` must raise one FormatError line naming ``path`` (and ``needles``)."""
    with pytest.raises(FormatError) as info:
        call()
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    for needle in needles:
        assert needle in message, (needle, message)
    return message


@pytest.mark.parametrize("case", GENERIC)
@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_each_layout_reader_refuses_a_broken_file_in_one_line(layout, case, tmp_path, monkeypatch):
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", SMALL_BUDGET)
    make, reader, name, rank, dtype = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    reader(path)  # the valid file reads
    _break(path, name, rank, dtype, case)
    message = _refused(path, lambda: reader(path))
    if "external" in case or case == "virtual":
        assert "allow_external" in message, message


@pytest.mark.parametrize("case", ["external link", "external storage", "virtual"])
@pytest.mark.parametrize("layout", ["registration", "results", "stack", "simulation", "progress"])
def test_each_layout_reader_follows_outside_data_when_allowed(layout, case, tmp_path):
    make, reader, name, rank, dtype = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    _break(path, name, rank, dtype, case)
    reader(path, allow_external=True)


@pytest.mark.parametrize(
    "case",
    [
        "truncated",
        "strings",
        "compound",
        "wrong rank",
        "huge",
        "never written",
        "external link",
        "virtual",
        "soft link circle",
        "group in a circle",
    ],
)
@pytest.mark.parametrize("layout", ["registration", "results", "stack", "calibration", "progress"])
def test_read_refuses_each_broken_layout_in_one_line(layout, case, tmp_path, monkeypatch):
    """``radiokit.io.read`` (and so ``radiokit info``) opens each layout at its plot."""
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", SMALL_BUDGET)
    make, _, name, rank, dtype = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    read(path)
    _break(path, name, rank, dtype, case)
    if (layout, case) == ("progress", "huge"):  # read() takes the keys of the frames there are, no more
        assert read(path).data.shape == (2, 4, 5)
        return
    _refused(path, lambda: read(path))


def _huge(h5, name, shape, dtype="f4"):
    """A dataset declaring ``shape`` (terabytes) in a file of a few KB: one chunk written through
    scale-offset, whose ratio has no bound, so that its storage cannot prove the rest unwritten
    (check_written) and only the budget can refuse it."""
    if name in h5:
        del h5[name]
    chunks = (1,) * (len(shape) - 1) + (1000,)
    scaleoffset = 0 if np.dtype(dtype).kind in "iu" else 2  # integers: minimum bits; floats: 2 decimals
    ds = h5.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, scaleoffset=scaleoffset)
    ds[tuple(slice(0, c) for c in chunks)] = 0


FRAME = (10**6, 10**6)  # 4 TB of float32
# every dataset of the layout huge and consistent with the others: only the budget can refuse it
HUGE_CONSISTENT = {
    "registration": lambda h5: (
        _huge(h5, "entry/registration/registered", FRAME),
        _huge(h5, "entry/registration/displacement", (2,) + FRAME),
        _huge(h5, "entry/registration/confidence", FRAME),
    ),
    "results": lambda h5: _huge(h5, "entry/steps/line_integral", (2,) + FRAME),
    "stack": lambda h5: _huge(h5, "entry/data/data", (2,) + FRAME),
    "simulation": lambda h5: [
        _huge(h5, f"entry/simulation/{name}", (2,) + FRAME, dtype)
        for name, dtype in (("line_integral", "f4"), ("inclusion_mask", "u1"))
    ],
    "simulation field": lambda h5: [
        _huge(h5, f"entry/simulation/{name}", (2,) + FRAME, "u1")
        for name in ("line_integral", "inclusion_mask", "displacement/step1_to_step2")
    ],
    "calibration": lambda h5: [_huge(h5, f"calibration/{name}", FRAME) for name in ("dark", "flat")],
}


@pytest.mark.parametrize("layout", sorted(HUGE_CONSISTENT))
def test_huge_consistent_shapes_are_refused_by_the_budget(layout, tmp_path, monkeypatch):
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", SMALL_BUDGET)
    make, reader, *_ = LAYOUTS[layout.split()[0]]
    path = tmp_path / "huge.h5"
    make(path)
    with h5py.File(path, "a") as h5:
        HUGE_CONSISTENT[layout](h5)
    if layout == "simulation field":  # no images asked for: only the field is read
        _refused(path, lambda: reader(path, steps=[]), "over the memory budget of 64.0 MiB", "step1_to_step2")
    else:
        _refused(path, lambda: reader(path), "over the memory budget of 64.0 MiB")


ROWS_COLS = (250, 400)  # 400 KB of float32 a frame: each array fits a 1 MiB budget, three do not
# three frame-sized arrays, each within the budget, together over it
OVER_IN_SUM = {
    "registration": lambda h5: (
        _data("entry/registration/registered", np.zeros(ROWS_COLS, "f4"))(h5),
        _data("entry/registration/displacement", np.zeros((2,) + ROWS_COLS, "f4"))(h5),
        _data("entry/registration/confidence", np.zeros(ROWS_COLS, "f4"))(h5),
    ),
    "results": lambda h5: [
        h5.create_dataset(f"entry/registration/{name}", data=np.zeros(ROWS_COLS, "f4"))
        for name in ("moving", "det_j", "confidence")
    ],
    "simulation": lambda h5: [
        _data(f"entry/simulation/{name}", np.zeros((2,) + ROWS_COLS, dtype))(h5)
        for name, dtype in (("line_integral", "f4"), ("inclusion_mask", "u1"), ("displacement/step1_to_step2", "f4"))
    ],
}


@pytest.mark.parametrize("layout", sorted(OVER_IN_SUM))
def test_a_record_is_read_within_one_budget_not_one_per_array(layout, tmp_path, monkeypatch):
    make, reader, *_ = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    with h5py.File(path, "a") as h5:
        OVER_IN_SUM[layout](h5)
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", "1MiB")
    _refused(path, lambda: reader(path), "over the memory budget of 1.0 MiB", "after")
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", "4MiB")
    reader(path)


def _attrs(name, **values):
    def edit(h5):
        for key, value in values.items():
            if value is None:
                del h5[name].attrs[key]
            else:
                h5[name].attrs[key] = value

    return edit


def _data(name, values):
    def edit(h5):
        del h5[name]
        h5[name] = values

    return edit


def _non_utf8(name, key):
    def edit(h5):
        h5[name].attrs.create(key, b"\xff\xfe caf\xe9", dtype=h5py.string_dtype("utf-8"))

    return edit


S = "entry/simulation"
# (layout, what is wrong, the edit, words the error must hold)
BAD_CONTENT = [
    ("results", "pair as a string", _attrs("entry/registration", pair="2,1"), "pair"),
    ("results", "pair of 3", _attrs("entry/registration", pair=np.array([1, 2, 3])), "pair"),
    ("results", "crop of 3", _attrs("entry/steps", crop=np.array([0, 4, 0])), "crop"),
    ("results", "crop as a string", _attrs("entry/steps", crop="0 4 0 5"), "crop"),
    ("results", "crop missing", _attrs("entry/steps", crop=None), "crop"),
    ("results", "crop of floats", _attrs("entry/steps", crop=np.array([0, 4.5, 0, 5])), "crop"),
    ("results", "NaN step", _data("entry/steps/step", np.array([1, np.nan])), "step"),
    ("results", "inf ratio", _data("entry/steps/ratio", np.array([0.1, np.inf])), "ratio"),
    ("results", "3 steps for 2 images", _data("entry/steps/step", np.array([1, 2, 3])), "step"),
    ("results", "a domain that is a dataset", _data("entry/enhanced/log", np.zeros((2, 4, 5), "f4")), "enhanced/log"),
    (
        "registration",
        "field of another shape",
        _data("entry/registration/displacement", np.zeros((2, 3, 3), "f4")),
        "displacement",
    ),
    (
        "registration",
        "field of 3 components",
        _data("entry/registration/displacement", np.zeros((3, 4, 5), "f4")),
        "displacement",
    ),
    (
        "registration",
        "confidence of another shape",
        _data("entry/registration/confidence", np.zeros((4, 6), "f4")),
        "confidence",
    ),
    (
        "registration",
        "confidence as text",
        _data("entry/registration/confidence", np.array([b"a", b"b"])),
        "confidence",
    ),
    ("stack", "series longer than the stack", _data("entry/data/step", np.arange(5)), "step"),
    ("stack", "series of text", _data("entry/data/step", np.array([b"a", b"b"])), "step"),
    ("simulation", "NaN ratio", _data(f"{S}/ratio", np.array([0.1, np.nan])), "ratio"),
    ("simulation", "inf gap", _data(f"{S}/gap_mm", np.array([np.inf, 1.0])), "gap_mm"),
    ("simulation", "curves of two lengths", _data(f"{S}/gap_mm", np.array([1.0, 2.0, 3.0])), "gap_mm"),
    ("simulation", "fewer images than steps", _data(f"{S}/line_integral", np.zeros((1, 4, 5), "f4")), "line_integral"),
    ("simulation", "mask of another shape", _data(f"{S}/inclusion_mask", np.zeros((2, 4, 6), "u1")), "inclusion_mask"),
    (
        "simulation",
        "field of another shape",
        _data(f"{S}/displacement/step1_to_step2", np.zeros((3, 4, 5), "f4")),
        "step1_to_step2",
    ),
    (
        "simulation",
        "field of an unknown step",
        lambda h5: h5.create_dataset(f"{S}/displacement/step1_to_step9", data=np.zeros((2, 4, 5), "f4")),
        "step1_to_step9",
    ),
    (
        "simulation",
        "defects of 3 columns",
        lambda h5: [
            h5.create_dataset(f"{S}/defects/{k}", data=np.zeros(shape))
            for k, shape in (("dead", (2, 3)), ("under", (0, 2)), ("noisy", (0, 2)), ("columns", (0,)))
        ],
        "dead",
    ),
    ("simulation", "displacement a dataset", _data(f"{S}/displacement", np.zeros((2, 4, 5), "f4")), "displacement"),
    ("simulation", "gap as text", _attrs(S, initial_gap_mm="wide"), "initial_gap_mm"),
    ("simulation", "timing as text", _attrs(S, seconds_render="slow"), "seconds_render"),
    ("progress", "frames_complete as text", _attrs("entry", frames_complete="two"), "frames_complete"),
    ("progress", "frames_complete negative", _attrs("entry", frames_complete=-3), "frames_complete"),
    ("progress", "frames_complete NaN", _attrs("entry", frames_complete=np.nan), "frames_complete"),
    ("progress", "frames_complete past the keys", _attrs("entry", frames_complete=50), "frames_complete"),
    ("progress", "float steps", _data("entry/sample/compression/step", np.array([np.nan, 1.0])), "step"),
    ("calibration", "flat missing", lambda h5: h5.__delitem__("calibration/flat"), "flat"),
    ("calibration", "flat of another shape", _data("calibration/flat", np.ones((4, 6))), "flat"),
]


@pytest.mark.parametrize("layout, case, edit, words", BAD_CONTENT, ids=[c[1] for c in BAD_CONTENT])
def test_each_layout_reader_refuses_bad_content_in_one_line(layout, case, edit, words, tmp_path):
    make, reader, *_ = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    reader(path)
    with h5py.File(path, "a") as h5:
        edit(h5)
    _refused(path, lambda: reader(path), words)


# text attributes are provenance (who wrote what): bytes that are not UTF-8 are shown replaced, as
# U+FFFD, never raised on and never passed on as lone surrogates that cannot be printed
NON_UTF8 = [
    ("registration", "entry/registration", "method", lambda r: r.method),
    ("registration", "entry/registration", "quality_reason", lambda r: r.quality["reason"]),
    ("results", "entry", "source", lambda r: r.source),
    ("stack", "entry/data", "source", lambda r: r.meta["source"]),
    ("simulation", S, "scene", lambda r: r.scene_toml),
    ("progress", "entry", "protocol", lambda r: r.protocol),
]


@pytest.mark.parametrize("layout, group, key, get", NON_UTF8, ids=[f"{c[0]}-{c[2]}" for c in NON_UTF8])
def test_text_attributes_that_are_not_utf8_are_read_replaced(layout, group, key, get, tmp_path):
    make, reader, *_ = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    with h5py.File(path, "a") as h5:
        _non_utf8(group, key)(h5)
    text = get(reader(path))
    assert "\ufffd" in text and text.endswith(" caf\ufffd"), repr(text)
    text.encode("utf-8")  # printable: no lone surrogates


@pytest.mark.parametrize("depth", [900, 100_000])
def test_a_stack_attribute_nested_past_radiokit_s_depth_stays_text(depth, tmp_path):
    """Past what json reads (100 000 levels), and within it but past what radiokit's records nest
    (900: it loaded, and a caller's json.dumps of the meta died of RecursionError, s52): the
    attribute is kept as its text, with a warning naming the file, the attribute and the rule."""
    path = tmp_path / "stack.h5"
    _stack_file(path)
    bomb = "[" * depth + "]" * depth
    with h5py.File(path, "a") as h5:
        h5["entry/data"].attrs["cal"] = bomb
    with pytest.warns(UserWarning, match=r"stack\.h5: .*cal.* nests deeper than 32 levels.*kept as text"):
        meta = read_stack(path).meta
    assert meta["cal"] == bomb and meta["source"] == "exp.h5"


@pytest.mark.parametrize(
    "layout, case",
    [
        ("registration", "soft link circle"),
        ("results", "huge"),
        ("stack", "truncated"),
        ("calibration", "strings"),
        ("results", "group in a circle"),
    ],
)
def test_info_on_a_broken_layout_is_one_line(layout, case, tmp_path):
    make, _, name, rank, dtype = LAYOUTS[layout]
    path = tmp_path / f"{layout}.h5"
    make(path)
    _break(path, name, rank, dtype, case)
    one_line_error(run_cli("info", path, env={"RADIOKIT_MEMORY_BUDGET": SMALL_BUDGET}), "radiokit info: ", path)


@pytest.mark.parametrize("case", ["NaN ratio", "soft link circle", "fewer images than steps"])
def test_process_on_a_broken_simulation_truth_is_one_line(case, tmp_path):
    path = tmp_path / "sim.h5"
    _experiment(path)
    _simulation_group_into(path)
    with h5py.File(path, "a") as h5:
        if case == "NaN ratio":
            _data(f"{S}/ratio", np.array([0.1, np.nan, 0.3]))(h5)
        elif case == "soft link circle":
            _replace(h5, f"{S}/line_integral", h5py.SoftLink(f"/{S}/line_integral"))
        else:
            _data(f"{S}/line_integral", np.zeros((1, 32, 40), "f4"))(h5)
    res = run_cli("process", path, "-q", "--no-report", "-o", tmp_path / "res")
    one_line_error(res, "radiokit process: ", path)
    assert not (tmp_path / "res").exists()


def _simulation_group_into(path):
    """A valid 3-step truth for ``_experiment``'s (32, 40) frames."""
    from radiokit.io import write_simulation

    write_simulation(path, _truth_record(3, (32, 40)), replace=True)


# -- results.json --------------------------------------------------------------------------------
def _results_json():
    """A valid results.json (as a dict), written by radiokit's own serialiser."""
    from radiokit.enhance import Domain
    from radiokit.results import Bound, DomainMeasures, KMeasure, PairResult, Rois

    per_k = (KMeasure(1.0, 0.1, 2.0, 0.05, 1.5, 1.8), KMeasure(2.0, 0.2, 3.0, 0.1, 2.5))
    record = Results(
        source="exp.h5",
        scene="block",
        simulated=True,
        pixel_size_mm=0.1,
        domain=Domain.LOG,
        ks=(1.0, 2.0),
        method="rc",
        steps=(1, 2, 3),
        ratios=(0.1, 0.2, float("nan")),
        rois=Rois((0, 40, 0, 50), (1, 5, 1, 5), (6, 9, 6, 9)),
        domains={Domain.LOG: DomainMeasures(Domain.LOG, 0.05, 1.0, 0.02, per_k)},
        pairs=(PairResult(3, 1, "rc", {"ok": True, "reason": "", "ncc": 0.9}, {Domain.LOG: 1.2}),),
        main_pair="3->1",
        profiles_row=20,
        bound=Bound(0.3, "truth"),
        paper={},
        timings={"total_s": 1.0},
    )
    return record.to_json()


def _json_case(case):
    d = _results_json()
    if case == "missing domains":
        del d["domains"]
    elif case == "missing schema_version":
        del d["schema_version"]
    elif case == "major version 2":
        d["schema_version"] = "2.0"
    elif case == "version as a list":
        d["schema_version"] = [1, 0]
    elif case == "ks as text":
        d["ks"] = "1,2"
    elif case == "steps of text":
        d["steps"] = ["one", "two", "three"]
    elif case == "pixel_size_mm as text":
        d["pixel_size_mm"] = "0.1 mm"
    elif case == "unknown domain":
        d["domain"] = "purple"
    elif case == "domains as a list":
        d["domains"] = [1, 2]
    elif case == "crop of 3":
        d["rois"]["crop"] = [0, 40, 0]
    elif case == "registration not a dict":
        d["registration"]["3->1"] = "fine"
    elif case == "pair name without arrow":
        d["registration"] = {"three": d["registration"]["3->1"]}
        d["change_ratio"] = {"three": d["change_ratio"]["3->1"]}
    elif case == "main pair unknown":
        d["main_pair"] = "9->1"
    elif case == "contrast as text":
        d["domains"]["log"]["contrast"]["1"] = "high"
    elif case == "k key not a number":
        d["domains"]["log"]["improvement_factor"]["one"] = 1.0
    elif case == "bound missing basis":
        del d["bound"]["basis"]
    elif case == "profiles_row as float":
        d["profiles_row"] = 20.5
    elif case == "control not a dict":
        d["control"] = [1]
    else:
        raise AssertionError(case)
    return json.dumps(d)


JSON_BAD = [
    "missing domains",
    "missing schema_version",
    "major version 2",
    "version as a list",
    "ks as text",
    "steps of text",
    "pixel_size_mm as text",
    "unknown domain",
    "domains as a list",
    "crop of 3",
    "registration not a dict",
    "pair name without arrow",
    "main pair unknown",
    "contrast as text",
    "k key not a number",
    "bound missing basis",
    "profiles_row as float",
    "control not a dict",
]
JSON_GARBAGE = {
    "not json": b"<html>results</html>",
    "empty": b" ",
    "not utf-8": b'{"source": "\xff\xfe"}',
    "a list": b"[1, 2, 3]",
    "a number": b"42",
    "null": b"null",
    "nested past the recursion limit": b"[" * 200_000 + b"]" * 200_000,
    "deep object": b'{"a":' * 50_000 + b"1" + b"}" * 50_000,
}


@pytest.mark.parametrize("case", JSON_BAD + sorted(JSON_GARBAGE))
def test_load_results_refuses_a_bad_results_json_in_one_line(case, tmp_path):
    path = tmp_path / "results.json"
    if case in JSON_GARBAGE:
        path.write_bytes(JSON_GARBAGE[case])
    else:
        path.write_text(_json_case(case))
    _refused(path, lambda: load_results(path))


@pytest.mark.parametrize("field", ["paper", "timings", "unknown"])
def test_load_results_refuses_a_field_nested_past_radiokit_s_depth(field, tmp_path):
    """s52: a results.json whose "paper" or "timings" nested 900 levels (within what json reads)
    loaded, and writing its numbers again (Results.to_json, strict JSON) died of RecursionError.
    Refused as the calibration's provenance is (radiokit._json.MAX_DEPTH), whatever the key."""
    d = _results_json()
    d[field] = json.loads('{"a": ' + "[" * 900 + "]" * 900 + "}")
    path = tmp_path / "results.json"
    path.write_text(json.dumps(d))
    _refused(path, lambda: load_results(path), "nests deeper than 32 levels")


def test_load_results_reads_a_future_minor_version_and_ignores_keys_it_does_not_know(tmp_path):
    d = _results_json()
    d["schema_version"] = "1.7"
    d["new_in_1_7"] = {"anything": [1, 2]}
    d["domains"]["log"]["new_measure"] = {"1": 0.5}
    path = tmp_path / "results.json"
    path.write_text(json.dumps(d))
    back = load_results(path)
    assert back.improvement_factor == {1.0: 1.5, 2.0: 2.5}
    assert back.to_json()["schema_version"] == SCHEMA_VERSION and math.isnan(back.ratios[2])


def test_load_results_refuses_a_huge_file_by_its_size(tmp_path):
    path = tmp_path / "results.json"
    with open(path, "wb") as fh:  # sparse: 2 GB declared, nothing written
        fh.truncate(2 * 10**9)
    _refused(path, lambda: load_results(path), "2.0 GB")


@pytest.mark.parametrize("case", ["missing", "a folder"])
def test_load_results_on_no_file_is_one_line(case, tmp_path):
    path = tmp_path / "results.json"
    if case == "a folder":
        path.mkdir()
    _refused(path, lambda: load_results(path))


@pytest.mark.parametrize("kind", ["bytes", "vlen"])
@pytest.mark.parametrize("where, key", [("/", "default"), ("entry", "default"), ("entry/steps", "signal")])
def test_read_with_nexus_names_that_are_not_utf8_reads_or_refuses_in_one_line(where, key, kind, tmp_path):
    path = tmp_path / "results.h5"
    _results_file(path)
    with h5py.File(path, "a") as h5:
        if kind == "bytes":
            h5[where].attrs[key] = np.bytes_(b"\xff\xfe")
        else:
            h5[where].attrs.create(key, b"\xff\xfe", dtype=h5py.string_dtype("utf-8"))
    try:
        frames = read(path)
    except FormatError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc), exc
    else:  # a broken @default falls back to the only NXentry and NXdata
        assert frames.data.shape == (2, 4, 5)


READERS = {
    "load_results": load_results,
    "read": read,
    "read_results": read_results,
    "read_stack": read_stack,
    "read_registration": read_registration,
    "read_simulation": read_simulation,
    "read_progress": read_progress,
}


@pytest.mark.parametrize("reader", sorted(READERS))
@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_a_fifo_or_a_device_is_refused_without_waiting(reader, kind, tmp_path):
    """A FIFO blocks the reader until someone writes to it, /dev/zero never ends: both must be
    refused from their type (a regression shows as this test hanging)."""
    if kind == "fifo":
        path = tmp_path / "results.json"
        os.mkfifo(path)
    else:
        path = "/dev/zero"
    _refused(path, lambda: READERS[reader](path), "not a regular file")


def _bound_by_file_modes():
    """Make the child subject to file modes: root reads every file through CAP_DAC_OVERRIDE and
    CAP_DAC_READ_SEARCH, so as root the child drops both from its capability bounding set (Linux
    prctl PR_CAPBSET_DROP), and its exec keeps neither; a mode of 000 then stops it as any user."""
    if os.geteuid() == 0:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        for cap in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
            if libc.prctl(24, cap, 0, 0, 0):  # PR_CAPBSET_DROP
                raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


@pytest.fixture
def unreadable(tmp_path):
    """A TIFF, an experiment and a calibration, each of mode 000, and readable copies."""
    import shutil

    from radiokit.calibrate import Calibration

    rng = np.random.default_rng(0)
    tifffile.imwrite(tmp_path / "frame.tif", rng.normal(1500, 10, (32, 40)).astype(np.uint16))
    _experiment(tmp_path / "exp.h5")
    Calibration.from_frames(
        rng.normal(100, 2, (4, 32, 40)).astype(np.uint16), rng.normal(3000, 30, (4, 32, 40)).astype(np.uint16)
    ).save(tmp_path / "cal.h5")
    for name in ("frame.tif", "exp.h5", "cal.h5"):
        shutil.copy(tmp_path / name, tmp_path / f"ok-{name}")
        os.chmod(tmp_path / name, 0)
    try:
        probe = subprocess.run(
            [sys.executable, "-c", "open('frame.tif', 'rb')"], cwd=tmp_path, preexec_fn=_bound_by_file_modes
        )
    except (OSError, subprocess.SubprocessError):
        probe = None
    if probe is None or probe.returncode == 0:
        pytest.skip("no way here to run a child that a file's mode 000 stops")
    yield tmp_path
    for name in ("frame.tif", "exp.h5", "cal.h5"):
        os.chmod(tmp_path / name, 0o644)


@pytest.mark.parametrize(
    "args, name",
    [
        (["info", "frame.tif"], "frame.tif"),
        (["info", "exp.h5"], "exp.h5"),
        (["correct", "frame.tif", "--cal", "ok-cal.h5", "-o", "out.h5", "-q"], "frame.tif"),
        (["correct", "ok-frame.tif", "--cal", "cal.h5", "-o", "out.h5", "-q"], "cal.h5"),
        (["calibrate", "--dark", "frame.tif", "--flat", "ok-frame.tif", "-o", "c.h5", "-q"], "frame.tif"),
        (["calibrate", "--experiment", "exp.h5", "-o", "c.h5", "-q"], "exp.h5"),
        (["register", "frame.tif", "ok-frame.tif", "-o", "r.h5", "-q"], "frame.tif"),
        (["process", "exp.h5", "-o", "res", "-q"], "exp.h5"),
    ],
)
def test_an_input_without_read_permission_is_named_as_such(args, name, unreadable):
    """A file the user may not read (another user's, mode 000): one line naming it and saying so.
    It was Python's "[Errno 13] Permission denied: 'frame.tif'", or, for a calibration,
    "cannot be opened as HDF5, so not a radiokit calibration file (truncated or another
    format)" with libhdf5's flags: a diagnosis of the file that the file does not deserve."""
    before = sorted(p.name for p in unreadable.iterdir())
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", *args],
        capture_output=True,
        text=True,
        cwd=unreadable,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        preexec_fn=_bound_by_file_modes,
    )
    one_line_error(res, f"radiokit {args[0]}: {name}: cannot be read: Permission denied")
    assert sorted(p.name for p in unreadable.iterdir()) == before


def test_load_results_on_bytes_flipped_at_random_reads_or_refuses_in_one_line(tmp_path):
    """300 results.json with a few bytes changed: each reads, or is one FormatError line."""
    import random

    base = json.dumps(_results_json()).encode()
    path = tmp_path / "results.json"
    refused = 0
    for seed in range(300):
        rng = random.Random(seed)
        data = bytearray(base)
        for _ in range(rng.choice([1, 2, 5])):
            data[rng.randrange(len(data))] = rng.choice(b'0123456789[]{}",:-.eEnul ' + bytes([rng.randrange(256)]))
        path.write_bytes(bytes(data))
        try:
            load_results(path)
        except FormatError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc), exc
            refused += 1
    assert refused > 200  # most such edits break the JSON or a field: the checks are not idle


# -- a calibration file ----------------------------------------------------------------------------
def _calibration(path, **attrs):
    from radiokit.calibrate import Calibration

    n = 8
    cal = Calibration(
        np.full((n, n), 100.0, np.float32), np.full((n, n), 3000.0, np.float32), np.zeros((n, n), np.uint8)
    )
    cal.save(path)
    with h5py.File(path, "a") as h5:
        for name, value in attrs.items():
            if value is None:
                del h5["calibration"].attrs[name]
            else:
                h5["calibration"].attrs[name] = value
    return path


@pytest.mark.parametrize(
    "attrs, words",
    [
        (dict(thresholds="{not json"), ("thresholds", "not JSON")),
        (dict(thresholds="[1, 2]"), ("thresholds", "JSON object")),
        (dict(thresholds='{"no_such_threshold": 1}'), ("thresholds",)),
        (dict(provenance="[" * 100_000 + "]" * 100_000), ("provenance", "nests deeper than")),
        # deep, yet within what json reads: was loaded, and correct's writing of it into its output
        # was a RecursionError traceback (s51)
        (dict(provenance='{"inputs": ' + "[" * 900 + "]" * 900 + "}"), ("provenance", "nests deeper than")),
        (dict(provenance=b"\xff\xfe"), ("provenance",)),
        # JSON's and HDF5's true is Python's 1: the flats' current read as 1 uA scaled every
        # transmission by 1/200 in silence, c = true the counts domain by 1/3000; a string was a
        # TypeError traceback
        (dict(provenance='{"flat_current_ua": true}'), ("flat_current_ua is true", "expected a number (uA)")),
        (dict(provenance='{"flat_current_ua": "200"}'), ('flat_current_ua is "200"',)),
        (dict(provenance='{"flat_voltage_kv": [60]}'), ("flat_voltage_kv is [60]", "(kV)")),
        (dict(c=True), ("@c is True", "positive finite number")),
        (dict(c="3000"), ("@c is '3000'",)),
        (dict(c=np.inf), ("@c is inf",)),
        (dict(c=-5.0), ("@c is -5.0",)),
    ],
)
def test_a_calibration_with_bad_attributes_is_one_line(tmp_path, attrs, words):
    from radiokit.calibrate import Calibration

    path = _calibration(tmp_path / "cal.h5", **attrs)
    with pytest.raises(FormatError) as err:
        Calibration.load(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and all(w in message for w in words)


def test_a_calibration_with_links_in_a_circle_is_one_line_from_the_cli(tmp_path):
    path = _calibration(tmp_path / "cal.h5")
    with h5py.File(path, "a") as h5:
        del h5["calibration/dark"]
        h5["calibration/dark"] = h5py.SoftLink("/calibration/loop")
        h5["calibration/loop"] = h5py.SoftLink("/calibration/dark")
    exp = _experiment(tmp_path / "exp.h5")
    res = run_cli("correct", str(exp), "--cal", str(path), "-o", str(tmp_path / "out.h5"))
    one_line_error(res, str(path))
    assert not (tmp_path / "out.h5").exists()


def test_a_calibration_whose_record_nests_deep_is_one_line_and_info_still_describes_it(tmp_path):
    """s51: a hand-made provenance nested 900 levels deep (``inputs``, read by json.loads) loaded,
    and ``correct`` died of RecursionError writing it into its output (a traceback); ``info``
    printed the 900 brackets as the file it was made from, and one nested past json's limit
    failed the whole file ("cannot be read as hdf5"), though its frames read. ``correct`` refuses
    it in one line (the record travels into its output, and its numbers steer the correction);
    ``info`` describes the file and says the record unreadable."""
    exp = _experiment(tmp_path / "exp.h5", shape=(8, 8))  # the calibration's
    for depth in (900, 100_000):
        cal = _calibration(tmp_path / f"cal{depth}.h5", provenance='{"inputs": ' + "[" * depth + "]" * depth + "}")
        res = run_cli("correct", exp, "--cal", cal, "-o", tmp_path / "out.h5")
        one_line_error(res, str(cal), "provenance", "nests deeper than")
        assert not (tmp_path / "out.h5").exists()
        res = run_cli("info", cal)
        assert res.returncode == 0, res.stderr
        assert "made from  unreadable: provenance nests deeper than" in info_items(res.stdout), res.stdout
        assert "[[" not in res.stdout and len(res.stdout.splitlines()) < 10, res.stdout


def test_a_calibration_load_would_refuse_is_never_saved(tmp_path):
    """Review s51rv2: ``Calibration.save`` wrote a provenance nested past radiokit's 32 levels (a
    record of one's own put in it), which ``Calibration.load`` then refused as "no record of
    radiokit's ... make the calibration again": a file radiokit wrote that it would not read.
    Refused at the save, naming the file, nothing written; 32 levels (the dict and 31 below) saved
    and loaded back."""
    from radiokit._json import MAX_DEPTH
    from radiokit.calibrate import Calibration

    n = 8
    cal = Calibration(
        np.full((n, n), 100.0, np.float32), np.full((n, n), 3000.0, np.float32), np.zeros((n, n), np.uint8)
    )

    def nested(levels):
        value = 1
        for _ in range(levels):
            value = [value]
        return value

    cal.provenance["mine"] = nested(MAX_DEPTH - 1)  # the provenance's own level and 31 lists: 32
    cal.save(tmp_path / "ok.h5")
    assert Calibration.load(tmp_path / "ok.h5").provenance["mine"] == nested(MAX_DEPTH - 1)
    cal.provenance["mine"] = nested(MAX_DEPTH)
    with pytest.raises(ValueError, match=r"deep.h5.*nests deeper than 32"):
        cal.save(tmp_path / "deep.h5")
    assert not list(tmp_path.glob("deep*"))
    with pytest.raises(ValueError, match="nests deeper than 32"):
        cal.save(io.BytesIO())


def test_a_good_calibration_still_loads(tmp_path):
    from radiokit.calibrate import Calibration

    cal = Calibration.load(_calibration(tmp_path / "cal.h5"))
    assert cal.shape == (8, 8) and float(cal.flat[0, 0]) == 3000.0


@pytest.mark.parametrize("value", [0.0, -5e-5, math.nan, math.inf, 1e-300, 0.05, True, "5e-05", [5e-5, 5e-5]])
def test_a_pixel_size_that_is_not_a_panels_is_one_line(value, tmp_path):
    """x_pixel_size divides every ROI in mm and the crop: 0 was a ZeroDivisionError traceback
    (``process --mm``), NaN "cannot convert float NaN to integer", inf or a negative pitch an
    empty ROI; 0.05 is a millimetre value in NeXus's metres (a 5 cm pixel); `true`, text or two
    values were left out, and ROIs in mm measured with 0.05 mm instead. Refused naming the file
    and the field, by every reader of the file."""
    from radiokit.io._experiment import DETECTOR

    exp = _experiment(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        del h5[DETECTOR]["x_pixel_size"]
        h5[DETECTOR]["x_pixel_size"] = value
    res = run_cli("process", exp, "-q", "--mm", "--inclusion", "0.5", "1", "0.5", "1", "-o", tmp_path / "res")
    one_line_error(res, "exp.h5", "x_pixel_size", "metres")
    one_line_error(run_cli("info", exp), "exp.h5", "x_pixel_size", "metres")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"]


@pytest.mark.parametrize(
    ("value", "units", "mm"),
    [(np.array([7.5e-5]), None, 0.075), (75.0, "um", 0.075), (np.array([0.1]), "mm", 0.1), (5e-5, "m", 0.05)],
)
def test_a_pixel_size_as_one_element_or_in_other_units_is_read(value, units, mm, tmp_path):
    """Some NXtomo writers store the pitch as a one-element array, and NeXus lets ``@units`` say
    um or mm: the review found the first refused outright (and 75 um read as 75 m, refused) once
    the pitch was checked. Both are the panel's pitch."""
    from radiokit.io._experiment import DETECTOR, read_experiment_meta

    exp = _experiment(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        del h5[DETECTOR]["x_pixel_size"]
        h5[DETECTOR]["x_pixel_size"] = value
        if units is not None:
            h5[DETECTOR]["x_pixel_size"].attrs["units"] = units
    with h5py.File(exp, "r") as h5:
        _, meta = read_experiment_meta(exp, h5)
    assert meta["pixel_size_mm"] == pytest.approx(mm, rel=1e-12)


def test_a_pixel_size_in_unknown_units_is_one_line(tmp_path):
    from radiokit.io._experiment import DETECTOR

    exp = _experiment(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        h5[DETECTOR]["x_pixel_size"].attrs["units"] = "furlong"
    one_line_error(run_cli("info", exp), "exp.h5", "x_pixel_size", "furlong")


# a complex number (numpy's, whose comparisons take its real part) was written, and no reader opens it
@pytest.mark.parametrize("value", [0, -0.05, math.nan, math.inf, True, 50, "0.05", np.complex128(0.05)])
def test_the_experiment_writer_refuses_a_pixel_size_no_reader_would_open(value, tmp_path):
    with pytest.raises(ValueError, match="pixel_size_mm=.*expected a panel's pixel pitch"):
        ExperimentWriter(tmp_path / "exp.h5", shape=(4, 5), pixel_size_mm=value)
    assert not (tmp_path / "exp.h5").exists()


@pytest.mark.parametrize("value", ["true", '"0.3"', "nan", "-0.5"])
def test_a_simulated_scenes_attenuation_that_is_not_a_number_is_one_line(value, tmp_path):
    """The simulation truth's scene is TOML: ``attenuation_per_cm = true`` was float(True), 1/cm,
    and the bound came out of it in silence (a string or NaN too). Refused, naming the field."""
    import dataclasses

    from radiokit.io import write_simulation

    path = _experiment(tmp_path / "sim.h5")
    scene = f'name = "block"\n[body.material]\nattenuation_per_cm = {value}\n'
    write_simulation(path, dataclasses.replace(_truth_record(3, (32, 40)), scene_toml=scene), replace=True)
    roi = ["--inclusion", "10", "20", "10", "20", "--background", "10", "20", "25", "35", "--crop-mm", "0"]
    res = run_cli(
        "process", path, "-q", "--no-report", "--cross-check", "none", "--method", "ncc", *roi, "-o", tmp_path / "res"
    )
    one_line_error(res, "sim.h5", "attenuation_per_cm", "expected a positive number")
    assert not (tmp_path / "res").exists()


def test_correct_refuses_a_calibration_whose_flat_current_is_true(tmp_path):
    """End to end: the flats at 200 uA, the projections at 200 uA, transmission 0.5; a calibration
    whose provenance says ``"flat_current_ua": true`` corrected them to 0.0025 with exit code 0."""
    shape = (16, 20)
    exp = tmp_path / "exp.h5"
    with ExperimentWriter(exp, shape=shape, pixel_size_mm=0.05) as w:
        for _ in range(2):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT, current_ua=200)
        w.append(np.full(shape, 1600, np.uint16), image_key=ImageKey.PROJECTION, step=1, current_ua=200)
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", exp, "-o", cal).returncode == 0
    good = run_cli("correct", exp, "--cal", cal, "--domain", "linear", "-q", "-o", tmp_path / "good.h5")
    assert good.returncode == 0 and read(tmp_path / "good.h5").data.mean() == pytest.approx(0.5, rel=1e-6)
    with h5py.File(cal, "a") as h5:
        prov = json.loads(h5["calibration"].attrs["provenance"])
        assert prov["flat_current_ua"] == 200
        h5["calibration"].attrs["provenance"] = json.dumps(prov | {"flat_current_ua": True})
    res = run_cli("correct", exp, "--cal", cal, "--domain", "linear", "-q", "-o", tmp_path / "out.h5")
    one_line_error(res, "cal.h5", "flat_current_ua is true")
    assert not (tmp_path / "out.h5").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--inclusion", "nan", "1", "2", "3"], ("--inclusion nan 1 2 3:", "finite")),
        (["--inclusion", "5", "1", "2", "3"], ("--inclusion", "empty")),
        (["--mm", "--inclusion", "5", "1", "2", "3"], ("--inclusion", "(mm)", "empty")),
        (
            ["--inclusion", "1", "9", "1", "9", "--background", "1", "9", "1", "9"],
            ("--background", "overlaps the --inclusion 1 9 1 9"),
        ),
        # found by a new user: fractional pixels were rounded without a word (README: pixels, mm with --mm)
        (["--inclusion", "1", "9.5", "1", "9"], ("--inclusion 1 9.5 1 9:", "whole", "9.5", "--mm")),
        (["--background", "1.25", "9", "1", "9"], ("--background", "whole", "1.25")),
    ],
)
def test_process_refuses_a_rectangle_it_cannot_use_before_correcting(args, words, tmp_path):
    """Refused only after the whole correction (a progress bar, then the line), or, for the same
    rectangle twice, at the very end as a zero reference contrast."""
    res = run_cli("process", _experiment(tmp_path / "exp.h5"), *args, "-o", tmp_path / "res")
    one_line_error(res, *words)
    assert res.stdout == "" and not (tmp_path / "res").exists()


def test_correct_refuses_an_output_format_it_cannot_write_before_calibrating(tmp_path):
    res = run_cli("correct", _experiment(tmp_path / "exp.h5"), "-q", "-o", tmp_path / "out.png")
    one_line_error(res, "out.png", ".h5", ".tif")
    assert res.stdout == ""  # was "calibrated from the darks and flats of exp.h5", then the refusal


@pytest.mark.parametrize("value", [True, 2.5, -5, "lots"])
def test_a_frames_complete_that_is_no_count_is_refused_and_never_truncates(value, tmp_path):
    """``@frames_complete = true`` read as 1: ``info`` showed 1 frame of 9, and opening the file to
    append (``ExperimentWriter(mode="a")``, ``acquire --resume``) cut the frames to that one; 2.5
    read as 2, -5 as none, text as "cannot be read as hdf5". Each is one line naming the field,
    and the frames stay."""
    from radiokit.io._experiment import ENTRY, FRAMES

    exp = _experiment(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        h5[ENTRY].attrs["frames_complete"] = value
    before = hashlib.sha256(exp.read_bytes()).hexdigest()
    one_line_error(run_cli("info", exp), "exp.h5", "frames_complete", "expected a count of frames")
    with pytest.raises(FormatError, match="frames_complete"):
        ExperimentWriter(exp, mode="a")
    with h5py.File(exp, "r") as h5:
        assert h5[FRAMES].shape[0] == 9
    assert hashlib.sha256(exp.read_bytes()).hexdigest() == before


@pytest.mark.parametrize("dtype", ["u1", "i1", "bool"])  # bool: a 1-bit TIFF, a mask
def test_correct_refuses_frames_whose_type_cannot_reach_the_flats(dtype, tmp_path):
    """s32-h4: an 8-bit copy of a radiograph (a viewer's export, 12-bit counts divided by 16)
    corrected against the panel's calibration (flats about 3000 counts) was written as a uniform
    image, every pixel "non-positive (filled)", exit code 0. No 8-bit pixel reaches the flats."""
    exp = _experiment(tmp_path / "exp.h5")
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", exp, "-o", cal, "-q").returncode == 0
    frames = np.random.default_rng(1).integers(900, 1100, (2, 32, 40)) // 16
    tifffile.imwrite(tmp_path / "view.tif", frames.astype(dtype), photometric="minisblack")
    res = run_cli("correct", tmp_path / "view.tif", "--cal", cal, "-q", "-o", tmp_path / "out.h5")
    one_line_error(res, "view.tif", f"{np.dtype(dtype)} pixels", "flats")
    assert not (tmp_path / "out.h5").exists()


def test_register_names_float64_values_beyond_float32_not_nan(tmp_path):
    """s32-h4: a float64 image with values near 1e300 was cast to float32 (a RuntimeWarning) and
    refused as "fixed image contains NaN or inf (5917 pixels)", of a file holding neither."""
    rng = np.random.default_rng(0)
    tifffile.imwrite(tmp_path / "big.tif", rng.random((32, 40)) * 1e300)
    tifffile.imwrite(tmp_path / "other.tif", rng.random((32, 40)).astype(np.float32))
    res = run_cli("register", tmp_path / "big.tif", tmp_path / "other.tif", "-q", "-o", tmp_path / "r.h5")
    line = one_line_error(res, "big.tif", "float32")
    assert "NaN" not in line
    assert not (tmp_path / "r.h5").exists()


def _calls_to_open(path) -> int:
    """Function calls (Python and builtin) made opening ``path`` and reading its first frame."""
    from radiokit.io import open_frames

    calls = 0

    def count(frame, event, arg):
        nonlocal calls
        calls += event in ("call", "c_call")

    sys.setprofile(count)
    try:
        with open_frames(path) as src:
            src[0]
    finally:
        sys.setprofile(None)
    return calls


def test_opening_a_tiff_of_many_pages_written_one_by_one_takes_work_linear_in_its_pages(tmp_path):
    """s32-h4: a 4.8 MB TIFF of 20 000 one-pixel pages, each written by its own TiffWriter.write
    (as a frame-by-frame writer does), took 76 s of CPU in `radiokit info`: tifffile's series of
    such a file compares every page with every other (quadratic), and it was built only to look
    for a one-IFD stack, which a file of many pages is not. 16x the pages must cost about 16x."""
    counts = []
    for n in (100, 1600):
        path = tmp_path / f"p{n}.tif"
        with tifffile.TiffWriter(path) as tif:
            for _ in range(n):
                tif.write(np.zeros((1, 1), np.uint8), photometric="minisblack", contiguous=False)
        counts.append(_calls_to_open(path))
    assert counts[1] < 24 * counts[0], counts  # linear: 16x; quadratic: 256x on the pages' part


def test_correct_runs_where_numba_can_write_its_cache_nowhere(tmp_path):
    """s32-h4: run as a user with no writable home (HOME=/nonexistent, as `nobody` or a container's
    arbitrary uid) on an install it cannot write, `radiokit correct` died in a 40-line traceback,
    numba's "cannot cache function '_ln': no locator available". The compiled loop then runs
    uncached (compiled at each start). The same fault is made here without another user: numba's
    own settings leave it one cache location only, under a regular file, which no one can create."""
    exp = _experiment(tmp_path / "exp.h5")
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", exp, "-o", cal, "-q").returncode == 0
    frames = np.random.default_rng(2).integers(900, 1100, (2, 32, 40)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "p.tif", frames, photometric="minisblack")
    (tmp_path / "afile").write_text("")
    env = {"NUMBA_CACHE_LOCATOR_CLASSES": "UserProvidedCacheLocator", "NUMBA_CACHE_DIR": str(tmp_path / "afile" / "c")}
    res = run("correct", tmp_path / "p.tif", "--cal", cal, "-q", "--domain", "linear", "-o", tmp_path / "t.h5", env=env)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    from radiokit.calibrate import Calibration

    c = Calibration.load(cal)
    expected = (frames - c.dark.astype(np.float64)) / (c.flat.astype(np.float64) - c.dark)
    np.testing.assert_allclose(read(tmp_path / "t.h5").data, expected, rtol=1e-5)


@pytest.mark.parametrize("among", ["flat", "dark"])
def test_calibrate_refuses_a_frame_of_the_other_kind_among_darks_or_flats(among, tmp_path):
    """s32-h4: `calibrate --dark d.tif --flat f.tif d.tif` (a dark file caught by a glob) averaged
    4 darks into 8 "flats": every pixel's samples spread over 2900 counts, so none was clipped, the
    flat came out halfway (c = 1450 against 2900) and every transmission twice too high, exit 0.
    A flat at the dark's level, or a dark at the flats', is named by file and frame."""
    rng = np.random.default_rng(3)
    d = rng.normal(100, 2, (4, 24, 32)).astype(np.uint16)
    f = rng.normal(3000, 30, (4, 24, 32)).astype(np.uint16)
    for name, frames in (("d.tif", d), ("f.tif", f)):
        tifffile.imwrite(tmp_path / name, frames, photometric="minisblack")
    darks, flats = (["d.tif", "f.tif"], ["f.tif"]) if among == "dark" else (["d.tif"], ["f.tif", "d.tif"])
    res = run_cli("calibrate", "--dark", *darks, "--flat", *flats, "-q", "-o", "cal.h5", cwd=tmp_path)
    line = one_line_error(res, "radiokit calibrate: ", f"{among} 5 of 8")
    wrong = "d.tif" if among == "flat" else "f.tif"
    assert line.startswith(f"radiokit calibrate: {wrong}: frame 0 ("), line
    assert not (tmp_path / "cal.h5").exists()


def test_calibration_from_frames_of_one_exposure_each_is_kept(tmp_path):
    """The check above leaves frames of one set-up alone: the tube's drift of a few per cent
    between flats, and the darks' own noise."""
    from radiokit.calibrate import Calibration

    rng = np.random.default_rng(4)
    darks = rng.normal(100, 2, (5, 24, 32))
    flats = rng.normal(3000, 30, (5, 24, 32)) * np.linspace(0.95, 1.05, 5)[:, None, None]
    cal = Calibration.from_frames(darks, flats)
    assert abs(cal.c - 2900) < 30


@pytest.mark.parametrize("levels", [[1400] * 8 + [3500] * 2, [1400] * 9 + [3080]])
def test_flats_of_two_exposures_are_refused_as_such_not_as_a_dark(levels):
    """Flats at two tube currents (8 at 1400 counts, 2 at 3500), or one caught in a current
    spike (2.2x): refused as before (their average mixes two exposures), but the line called the
    dimmer ones "a dark, not a flat (a dark file among the flats ...)" (review s32-r2). A flat
    clearly lit is one of another exposure, and the line gives its share of the brightest."""
    from radiokit.calibrate import Calibration, FrameLevelError

    rng = np.random.default_rng(6)
    darks = rng.normal(100, 2, (4, 24, 32))
    flats = np.stack([rng.normal(level, 20, (24, 32)) for level in levels])
    with pytest.raises(FrameLevelError) as refused:
        Calibration.from_frames(darks, flats)
    text = str(refused.value)
    share = (levels[0] - 100) / (max(levels) - 100)
    assert "another exposure" in text and "a dark" not in text, text
    assert f"{100 * share:.0f} % of the brightest" in text, text
    assert refused.value.culprits == ("flats",)


def test_process_names_the_file_frame_of_a_dark_labelled_as_a_flat(tmp_path):
    """The same check on an experiment file: a dark its writer labelled a flat (frame 4) is named
    by its frame in the file, not by its place among the flats."""
    path = tmp_path / "exp.h5"
    rng = np.random.default_rng(0)
    with ExperimentWriter(path, shape=(32, 40), pixel_size_mm=0.05) as w:
        for key, level in ((ImageKey.DARK, 100), (ImageKey.DARK, 100), (ImageKey.FLAT, 3000), (ImageKey.FLAT, 3000)):
            w.append(rng.integers(level - 10, level + 10, (32, 40)), image_key=key)
        w.append(rng.integers(90, 110, (32, 40)), image_key=ImageKey.FLAT)  # the beam was off
        for s in (1, 2, 3):
            w.append(rng.integers(900, 1100, (32, 40)), image_key=ImageKey.PROJECTION, step=s)
    one_line_error(run_cli("process", path, "-q", "-o", tmp_path / "res"), "exp.h5: frame 4 (flat 3 of 3 ")
    assert not (tmp_path / "res").exists()


def test_process_refuses_projections_brighter_than_the_flats(tmp_path):
    """s32-h4: flats taken at a quarter of the projections' tube current, no currents recorded:
    every line integral came out negative, the body mask empty, and `radiokit process` died in a
    traceback (numpy's percentile of nothing, in the cross-check). Nothing can be brighter than
    the open beam: the step is named with how much brighter, in one line."""
    path = tmp_path / "exp.h5"
    rng = np.random.default_rng(0)
    with ExperimentWriter(path, shape=(48, 48), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(rng.normal(100, 2, (48, 48)).astype(np.uint16), image_key=ImageKey.DARK)
            w.append(rng.normal(800, 10, (48, 48)).astype(np.uint16), image_key=ImageKey.FLAT)
        for s in (1, 2, 3):
            counts = 100 + 2800 * np.exp(-0.4) + rng.normal(0, 5, (48, 48))
            w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=s)
    roi = ["--inclusion", "20", "28", "20", "28", "--background", "20", "28", "5", "13", "--crop-mm", "0"]
    line = one_line_error(
        run_cli("process", path, *roi, "-q", "-o", tmp_path / "res"), "exp.h5", "brighter than the flats"
    )
    expected = (2800 * math.exp(-0.4)) / 700  # (raw - dark) / (flat - dark)
    assert re.search(r"(\d+\.\d+)x", line) and abs(float(re.search(r"(\d+\.\d+)x", line)[1]) - expected) < 0.05, line
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["correct", "p.tif", "--cal", "cal.h5", "-o", "loop.h5"], "loop.h5: is a symbolic link in a loop"),
        (["correct", "loop.h5", "--cal", "cal.h5", "-o", "out.h5"], "loop.h5: cannot be opened"),
        (["calibrate", "--experiment", "exp.h5", "-o", "loop.h5"], "loop.h5: is a symbolic link in a loop"),
        (
            ["register", "p.tif", "p.tif", "--moving-frame", "1", "-o", "r.h5", "--png", "loop.png"],
            "loop.png: is a symbolic link in a loop",
        ),
        (["process", "loop.h5", "-o", "res"], "loop.h5: cannot be opened"),
        (["process", "exp.h5", "--control", "loop.h5", "-o", "res"], "loop.h5"),
    ],
)
def test_a_symlink_in_a_loop_is_one_line(args, words, tmp_path):
    """s32-h4: an output or input that is a symbolic link in a loop (a -> b -> a) gave a traceback,
    "RuntimeError: Symlink loop from ..." (Python 3.11's Path.resolve, in the output checks). As
    an input it cannot be opened; as an output it is refused as a loop (s34: a dangling link's
    target is written, a loop has none)."""
    exp = _experiment(tmp_path / "exp.h5")
    assert run_cli("calibrate", "--experiment", exp, "-o", tmp_path / "cal.h5", "-q").returncode == 0
    tifffile.imwrite(
        tmp_path / "p.tif", np.random.default_rng(0).random((2, 32, 40), np.float32), photometric="minisblack"
    )
    for name, other in (("loop", "pool"), ("pool", "loop")):
        for ext in (".h5", ".png"):
            (tmp_path / f"{name}{ext}").symlink_to(f"{other}{ext}")
    one_line_error(run_cli(*args, "-q", cwd=tmp_path), words)
    assert not (tmp_path / "res").exists() and not (tmp_path / "out.h5").exists()


def test_process_of_steps_that_did_not_move_prints_no_warnings(tmp_path):
    """s32-h4: steps whose registration found no motion (a zero field: the same frames given for
    every step, or an image too small to move) printed matplotlib's "RuntimeWarning: divide by
    zero" and "Mean of empty slice" under the results, from the report's arrows scaled to
    nothing. The run is otherwise complete: its only lines on stderr are radiokit's."""
    path = tmp_path / "exp.h5"
    rng = np.random.default_rng(0)
    rr, cc = np.mgrid[:48, :48]
    inclusion = (abs(rr - 24) < 5) & (abs(cc - 24) < 5)
    with ExperimentWriter(path, shape=(48, 48), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(rng.normal(100, 2, (48, 48)).astype(np.uint16), image_key=ImageKey.DARK)
            w.append(rng.normal(2900, 20, (48, 48)).astype(np.uint16), image_key=ImageKey.FLAT)
        for s in (1, 2, 3):  # the slab thins, nothing moves
            counts = 100 + 2800 * np.exp(-0.5 + 0.05 * s - 0.3 * inclusion)
            w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=s)
    roi = [
        "--inclusion",
        "21",
        "27",
        "21",
        "27",
        "--background",
        "21",
        "27",
        "5",
        "11",
        "--crop-mm",
        "0",
        "--method",
        "ssd",
    ]
    res = run("process", path, *roi, "-q", "-o", tmp_path / "res", env={"PYTHONWARNINGS": "default"})
    assert res.returncode in (0, 1), res.stderr
    assert "RuntimeWarning" not in res.stderr, res.stderr
    assert (tmp_path / "res" / "report.html").exists()


def test_a_truncated_hdf5_file_is_named_truncated_with_its_sizes(tmp_path):
    """An experiment file cut short (an interrupted copy) was refused with libhdf5's words:
    "cannot be read as hdf5: Unable to synchronously open file (truncated file: eof = 20000,
    sblock->base_addr = 0, stored_eof = ...)": the line now says truncated, and how much is there."""
    exp = synthetic(tmp_path / "exp.h5")
    size = exp.stat().st_size
    cut = tmp_path / "cut.h5"
    cut.write_bytes(exp.read_bytes()[:20000])
    with pytest.raises(FormatError, match=rf"truncated: it holds 20000 of the {size} bytes") as info:
        read(cut)
    assert "synchronously" not in str(info.value)
    line = run_cli("process", cut, "-o", tmp_path / "res").stderr.strip()
    assert "truncated: it holds 20000" in line and "synchronously" not in line, line


# -- out of all proportion: decoded sizes a real frame never compresses to -------------------------
# The budget alone is half the available memory: 11.5 GB on a 23 GB machine, so a 220 KB zstd TIFF
# declaring 60000 x 60000 decoded 7 GB. These run "on a 64 GiB machine" (the budget's measure of
# available memory replaced) inside 1 GiB of address space: a reader that decoded first dies there.
_BIG_MACHINE = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))
import radiokit.io._budget as budget
budget._available_bytes = lambda: 64 << 30
from radiokit.cli import main
sys.exit(main(sys.argv[1:]))
"""


def run_on_a_big_machine(*args, env=None):
    clean = {k: v for k, v in os.environ.items() if k != "RADIOKIT_MEMORY_BUDGET"}
    return subprocess.run(
        [sys.executable, "-c", _BIG_MACHINE.format(limit=AS_LIMIT), *map(str, args)],
        capture_output=True,
        text=True,
        env={**clean, "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1", **(env or {})},
    )


def _zstd_chunks(path, shape, chunks, value, codec="zstd"):
    """An HDF5 stack of ``shape`` whose every chunk is written (one compressed chunk of ``value``
    stored at each place, as a writer would have): honest storage, nothing unwritten."""
    import hdf5plugin
    import imagecodecs

    block = np.full(chunks, value, np.uint16).tobytes()
    if codec == "zstd":
        opts, data = hdf5plugin.Zstd(), imagecodecs.zstd_encode(block)
    else:
        opts, data = {"compression": "gzip"}, imagecodecs.zlib_encode(block)
    with h5py.File(path, "w") as h5:
        ds = h5.create_dataset("data", shape=shape, dtype="u2", chunks=chunks, **opts)
        for index in np.ndindex(*(s // c for s, c in zip(shape, chunks))):
            ds.id.write_direct_chunk(tuple(i * c for i, c in zip(index, chunks)), data)
    return path


@pytest.fixture
def zstd_tiff_bomb(tmp_path):
    """A few-hundred-byte zstd TIFF declaring one 40000 x 40000 uint16 page (3.0 GiB): zstd's
    ratio has no bound, so no codec limit refuses it."""
    path = tmp_path / "zbomb.tif"
    tifffile.imwrite(path, np.zeros((16, 16), np.uint16), compression="zstd", rowsperstrip=16)
    with tifffile.TiffFile(path, mode="r+b") as tif:
        for name in ("ImageWidth", "ImageLength", "RowsPerStrip"):
            tif.pages[0].tags[name].overwrite(40_000)
    return path


def test_a_zstd_tiff_bomb_is_refused_on_a_big_machine(zstd_tiff_bomb):
    size = zstd_tiff_bomb.stat().st_size
    line = one_line_error(run_on_a_big_machine("info", zstd_tiff_bomb), "zbomb.tif", "40000x40000", "3.0 GiB")
    assert re.search(r"\b\d+ bytes\b", line) and "RADIOKIT_MEMORY_BUDGET" in line, line
    assert size < 1000


def test_an_hdf5_zstd_bomb_is_refused_on_a_big_machine(tmp_path):
    path = _zstd_chunks(tmp_path / "zbomb.h5", (1, 40_000, 40_000), (1, 4000, 4000), 7)
    assert path.stat().st_size < 400_000
    res = run_on_a_big_machine("info", "--dataset", "data", path)
    one_line_error(res, "zbomb.h5", "3.0 GiB", "RADIOKIT_MEMORY_BUDGET")


def test_a_deflate_bomb_within_deflates_bound_is_refused_on_a_big_machine(tmp_path):
    # 1026:1 is below deflate's 1032:1, so no lie about the codec: the proportion refuses it
    path = _zstd_chunks(tmp_path / "gbomb.h5", (1, 30_000, 30_000), (1, 3000, 3000), 0, codec="gzip")
    res = run_on_a_big_machine("info", "--dataset", "data", path)
    one_line_error(res, "gbomb.h5", "1.7 GiB", "RADIOKIT_MEMORY_BUDGET")


def test_a_stack_of_200_constant_frames_still_reads(tmp_path, monkeypatch):
    """200 dark frames of 2240 x 2240 (1.9 GiB) compress 1:1000 (deflate) to 1:30000 (zstd) when
    constant: a real experiment's size, read as always."""
    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    tif = tmp_path / "darks.tif"
    frame = np.full((2240, 2240), 101, np.uint16)
    with tifffile.TiffWriter(tif) as w:
        for _ in range(200):
            w.write(frame, compression="zstd", photometric="minisblack", contiguous=False)
    h5 = _zstd_chunks(tmp_path / "darks.h5", (200, 2240, 2240), (1, 2240, 2240), 101, codec="gzip")
    for path, extra in ((tif, {}), (h5, {"dataset": "data"})):
        with open_frames(path, **extra) as src:
            assert len(src) == 200
            assert (src[199] == 101).all()


def test_a_file_out_of_proportion_reads_with_an_explicit_budget(tmp_path, monkeypatch):
    """The rule's thresholds lowered to 1 MiB a frame: a 2048 x 2048 frame of zeros (8 MiB from
    a few hundred bytes) is refused, and read when the user gives a budget, as a real file
    beyond the thresholds would be; noisy frames and uncompressed ones never meet the rule."""
    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FRAME_BYTES", 2**20)
    zeros = np.zeros((2048, 2048), np.uint16)
    noisy = np.random.default_rng(0).normal(100, 2, (2048, 2048)).astype(np.uint16)
    for name, data, compression in (("zeros", zeros, "zstd"), ("zerosd", zeros, "zlib"), ("noisy", noisy, "zstd")):
        tifffile.imwrite(tmp_path / f"{name}.tif", data, compression=compression)
    tifffile.imwrite(tmp_path / "plain.tif", zeros)
    for name in ("zeros", "zerosd"):
        with pytest.raises(FormatError, match=rf"{name}.tif: .*8.0 MiB.* from \d+ bytes.*budget"):
            read(tmp_path / f"{name}.tif")
        assert read(tmp_path / f"{name}.tif", budget="64MiB").data.shape == (1, 2048, 2048)
        monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", "64MiB")
        assert read(tmp_path / f"{name}.tif").data.shape == (1, 2048, 2048)
        monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET")
    for name in ("noisy", "plain"):
        assert read(tmp_path / f"{name}.tif").data.shape == (1, 2048, 2048)
    h5 = _zstd_chunks(tmp_path / "zeros.h5", (1, 2048, 2048), (1, 512, 512), 0)
    with pytest.raises(FormatError, match=r"zeros.h5: .*8.0 MiB.* from \d+ bytes.*budget"):
        read(h5, dataset="data")
    assert read(h5, dataset="data", budget="64MiB").data.shape == (1, 2048, 2048)


def test_a_stack_out_of_proportion_is_refused_beyond_the_file_threshold(tmp_path, monkeypatch):
    """Frames each below the frame threshold, but all of them together beyond the file's."""
    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 4 * 2**20)
    path = tmp_path / "many.tif"
    tifffile.imwrite(path, np.zeros((3, 1024, 1024), np.uint16), compression="zstd", photometric="minisblack")
    with pytest.raises(FormatError, match=r"many.tif: 3 frames.*6.0 MiB"):
        read(path)
    assert read(path, budget="1GiB").data.shape == (3, 1024, 1024)


def test_register_is_refused_when_its_working_memory_is_over_the_budget(tmp_path):
    """The budget held the reads (two 256 x 256 uint16 images, 128 KiB each) but not the
    registration after them, about 16 times as much: 8000 x 8000 under a 200 MB budget peaked at
    3.6 GB. Refused in one line before it starts; read within a budget that holds both, it runs."""
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        tifffile.imwrite(tmp_path / f"{name}.tif", rng.normal(1000, 50, (256, 256)).astype(np.uint16))
    args = ("register", tmp_path / "a.tif", tmp_path / "b.tif", "--preset", "fast", "-o", tmp_path / "r.h5")
    from radiokit.cli import REGISTER_BYTES_PER_PIXEL
    from radiokit.io import human_bytes

    res = run_cli(*args, env={"RADIOKIT_MEMORY_BUDGET": "2MiB"})
    need = human_bytes(REGISTER_BYTES_PER_PIXEL * 256 * 256)  # rc's bytes a pixel (benchmarks/README.md)
    line = one_line_error(res, "radiokit register: ", "a.tif", "b.tif", "two 256x256 images", need, "2.0 MiB")
    # what works: register has no crop option, and --roi narrows the score, not the memory
    assert "register a cropped region" not in line and "cropped or binned beforehand" in line, line
    assert not (tmp_path / "r.h5").exists()
    res = run_cli(*args, env={"RADIOKIT_MEMORY_BUDGET": "64MiB"})
    assert res.returncode in (0, 1), res.stderr
    assert (tmp_path / "r.h5").exists()


def test_an_experiment_files_pixel_mask_bomb_is_refused_on_a_big_machine(tmp_path):
    """The pixel mask beside an experiment's frames is read whole, outside checked_dataset: a
    30000 x 30000 uint32 mask of zstd zeros (3.4 GiB) in a few hundred KB."""
    import hdf5plugin
    import imagecodecs

    path = _experiment(tmp_path / "exp.h5")
    data = imagecodecs.zstd_encode(np.zeros((3000, 3000), np.uint32).tobytes())
    with h5py.File(path, "a") as h5:
        del h5["entry/instrument/detector/pixel_mask"]
        ds = h5.create_dataset(
            "entry/instrument/detector/pixel_mask", (30_000, 30_000), "u4", chunks=(3000, 3000), **hdf5plugin.Zstd()
        )
        for r, c in np.ndindex(10, 10):
            ds.id.write_direct_chunk((r * 3000, c * 3000), data)
    assert path.stat().st_size < 1_000_000
    one_line_error(run_on_a_big_machine("info", path), "exp.h5", "pixel_mask", "3.4 GiB", "RADIOKIT_MEMORY_BUDGET")


def test_a_calibrations_defect_list_bomb_is_refused(tmp_path):
    """defect_rows and defect_columns were read with no check at all: 400 million zstd zeros
    (3 GiB) in a 127 KB calibration file, a traceback under 2 GiB of address space."""
    import hdf5plugin
    import imagecodecs

    from radiokit.calibrate import Calibration

    rng = np.random.default_rng(0)
    Calibration.from_frames(
        rng.normal(100, 2, (4, 64, 64)).astype(np.uint16), rng.normal(3000, 30, (4, 64, 64)).astype(np.uint16)
    ).save(tmp_path / "cal.h5")
    data = imagecodecs.zstd_encode(np.zeros(10_000_000, np.int64).tobytes())
    with h5py.File(tmp_path / "cal.h5", "a") as h5:
        del h5["calibration/defect_rows"]
        ds = h5.create_dataset(
            "calibration/defect_rows", (400_000_000,), "i8", chunks=(10_000_000,), **hdf5plugin.Zstd()
        )
        for i in range(40):
            ds.id.write_direct_chunk((i * 10_000_000,), data)
    code = (
        "import resource; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"
        "import radiokit.io._budget as b; b._available_bytes = lambda: 64 << 30\n"
        "from radiokit.calibrate import Calibration\n"
        "from radiokit.errors import FormatError\n"
        "try:\n    Calibration.load(__import__('sys').argv[1])\n"
        "except FormatError as exc:\n    print(exc)\n"
    )
    clean = {k: v for k, v in os.environ.items() if k != "RADIOKIT_MEMORY_BUDGET"}
    res = subprocess.run([sys.executable, "-c", code, tmp_path / "cal.h5"], capture_output=True, text=True, env=clean)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert "cal.h5" in res.stdout and "defect_rows" in res.stdout and "3.0 GiB" in res.stdout, res.stdout


def _tiff_pages_sharing_a_strip(path, pages, rows, cols, stored):
    """``pages`` zstd TIFF pages of ``rows`` x ``cols`` uint16 zeros whose one strip each is the
    same ``stored`` bytes: a zstd frame of zeros padded by a skippable frame (review s36r3)."""
    import struct

    import imagecodecs

    tifffile.imwrite(path, np.zeros((pages, 8, 8), np.uint16), compression="zstd", photometric="minisblack")
    z = imagecodecs.zstd_encode(bytes(rows * cols * 2))
    blob = z + struct.pack("<II", 0x184D2A50, stored - len(z) - 8) + bytes(stored - len(z) - 8)
    size = path.stat().st_size
    with tifffile.TiffFile(path) as tif:
        tags = [[(p.tags[k].valueoffset, int(p.tags[k].dtype)) for k in _STRIP_TAGS] for p in tif.pages]
    with open(path, "r+b") as fh:
        fh.seek(0, 2)
        fh.write(blob)
        for page in tags:
            for (offset, dtype), value in zip(page, (cols, rows, rows, size, len(blob))):
                fh.seek(offset)
                fh.write(struct.pack({3: "<H", 4: "<I"}[dtype], value))
    return path


_STRIP_TAGS = ("ImageWidth", "ImageLength", "RowsPerStrip", "StripOffsets", "StripByteCounts")


def test_tiff_pages_sharing_one_strip_count_its_bytes_once(tmp_path, monkeypatch):
    """10 pages of 16384 x 16384 pointing at one 2.8 MB zstd strip read 5 GiB at 5.8 GB RSS: the
    strip was counted once a page (1:191). Here 10 pages of 2 MiB share one 60 KB strip, the file
    threshold lowered to 4 MiB: 1:35 counted a page, 1:349 counted once, refused."""
    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 4 * 2**20)
    path = _tiff_pages_sharing_a_strip(tmp_path / "shared.tif", 10, 1024, 1024, 60_000)
    with pytest.raises(FormatError, match=r"shared.tif: 10 frames.*20.0 MiB from 60000 bytes.*1:349\)"):
        read(path)


def test_a_streamed_frame_is_held_to_its_own_bytes_not_the_whole_stack(tmp_path, monkeypatch):
    """Constant, sparse or preallocated stacks past 1:200 over the file threshold (lowered to
    4 MiB here; real: 300 4000 x 4000 frames, 8.9 GiB) were refused even when one frame was read:
    each frame streamed decodes one frame, within the frame threshold; read() decodes them all."""
    import imagecodecs

    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 4 * 2**20)
    const_h5 = _zstd_chunks(tmp_path / "const.h5", (5, 1024, 1024), (1, 1024, 1024), 50, codec="gzip")
    const_tif = tmp_path / "const.tif"
    tifffile.imwrite(const_tif, np.full((5, 1024, 1024), 50, np.uint16), compression="zlib", photometric="minisblack")
    for path, extra in ((const_h5, {"dataset": "data"}), (const_tif, {})):
        with open_frames(path, **extra) as src:
            assert (src[0] == 50).all() and (src[4] == 50).all()
        with pytest.raises(FormatError, match=r"10.0 MiB from \d+ bytes .*decompression bomb"):
            read(path, **extra)
    # a writer preallocated 300 frames and stopped after 2 noisy ones (1:344, within deflate's bound)
    rng = np.random.default_rng(0)
    with h5py.File(tmp_path / "prealloc.h5", "w") as h5:
        ds = h5.create_dataset("data", (300, 1024, 1024), "u2", chunks=(1, 1024, 1024), compression="gzip")
        ds[:2] = rng.poisson(100, (2, 1024, 1024)).astype(np.uint16)
    with open_frames(tmp_path / "prealloc.h5", dataset="data") as src:
        assert src[1].mean() > 90
    with pytest.raises(FormatError) as err:  # refused as unwritten, not taken for a bomb
        read(tmp_path / "prealloc.h5", dataset="data")
    assert "bomb" not in str(err.value), err.value
    # sparse photon-counting frames compress past 1:200: the message no longer says 1:20 at most
    sparse = (rng.random((1024, 1024)) < 0.002).astype(np.uint16)
    with h5py.File(tmp_path / "sparse.h5", "w") as h5:
        ds = h5.create_dataset("data", (5, 1024, 1024), "u2", chunks=(1, 1024, 1024), compression="gzip")
        for i in range(5):
            ds.id.write_direct_chunk((i, 0, 0), imagecodecs.zlib_encode(sparse.tobytes(), 9))
    with open_frames(tmp_path / "sparse.h5", dataset="data") as src:
        np.testing.assert_array_equal(src[3], sparse)
    with pytest.raises(FormatError) as err:
        read(tmp_path / "sparse.h5", dataset="data")
    assert "1:20 at most" not in str(err.value) and "sparse" in str(err.value), err.value


def test_a_streamed_dxchange_frame_is_held_to_its_own_chunks(tmp_path, monkeypatch):
    """DXchange's datasets were judged whole on opening: 5 constant 1024 x 1024 projections past
    the file threshold (lowered to 4 MiB) refused the one frame streamed; read() still refuses."""
    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 4 * 2**20)
    path = _zstd_chunks(tmp_path / "dx.h5", (5, 1024, 1024), (1, 1024, 1024), 50, codec="gzip")
    with h5py.File(path, "a") as h5:
        h5.move("data", "exchange/data")
        h5.create_dataset("exchange/data_dark", data=np.full((1, 1024, 1024), 5, np.uint16))
    with open_frames(path) as src:
        assert src.meta["format"] == "dxchange" and len(src) == 6
        assert (src[3] == 50).all()
    with pytest.raises(FormatError, match=r"dx.h5: .*10.0 MiB from \d+ bytes .*decompression bomb"):
        read(path)
    # split into datasets each within the threshold, read() decodes them together: judged together
    with h5py.File(path, "a") as h5:
        h5.copy("exchange/data", "exchange/data_white")
        del h5["exchange/data_dark"]
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 16 * 2**20)
    with pytest.raises(FormatError, match=r"dx.h5: /exchange/data_white and /exchange/data, read together, .*20.0 MiB"):
        read(path)


def test_stored_bytes_count_each_byte_once():
    """Pages or chunks pointing at one range, or at overlapping ones, store it once."""
    from radiokit.io._budget import stored_extent

    assert stored_extent([(100, 50)] * 10) == 50
    assert stored_extent([(100, 50), (120, 50), (400, 10), (0, 0)]) == 80
    assert stored_extent([(0, 10), (2, 3), (10, 5)]) == 15


# -- small faults the hostile trials of session 36 found ------------------------------------------
def test_info_counts_saturated_pixels_of_a_tiff_whose_bit_depth_it_knows(tmp_path):
    """A 12-bit TIFF (BitsPerSample 12) printed no saturation line; an ITEX or NeXus file's does.
    A 16-bit one says nothing of its ADC (a 12-bit panel's TIFFs are 16-bit too): its level is the
    one calibrate would guess from the values (s40: info printed none, calibrate flagged them)."""
    frames = np.full((2, 16, 16), 1000, np.uint16)
    frames[0, 0, :5] = 4095
    tifffile.imwrite(tmp_path / "p12.tif", frames, bitspersample=12)
    tifffile.imwrite(tmp_path / "p16.tif", frames)
    res = run_cli("info", tmp_path / "p12.tif")
    assert res.returncode == 0 and "saturated  5 pixel(s) >= 4095 (declared 12-bit)" in info_items(res.stdout), (
        res.stdout
    )
    out = info_items(run_cli("info", tmp_path / "p16.tif").stdout)
    assert "saturated  5 pixel(s) >= 4095 (from the values; a guess: the file declares no bit depth)" in out, out


@pytest.mark.parametrize(
    "tag, value, dtype, bits",
    [(281, 4095, np.uint16, 12), (281, 16383, np.uint16, 14), (341, 4095, np.int16, 12), (281, 4000, np.uint16, None)],
)
def test_a_tiff_max_sample_value_of_an_adc_is_its_bit_depth(tmp_path, tag, value, dtype, bits):
    """s37: a 16-bit TIFF whose MaxSampleValue (or SMaxSampleValue) is 4095 says its ADC is 12-bit,
    as BitsPerSample 12 does, yet `info` counted no saturated pixels and calibration took no bit
    depth from it. A maximum that is no 2**n - 1 is the data's own (statistics): not a bit depth."""
    frames = np.full((2, 16, 16), 1000, dtype)
    frames[0, 0, :5] = min(value, 4095)
    path = tmp_path / "m.tif"
    tifffile.imwrite(path, frames, extratags=[(tag, "H" if tag == 281 else "h", 1, value, True)])
    assert read(path).meta.get("bit_depth") == bits
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    if bits is not None:
        assert f"bit_depth  {bits} ({'MaxSampleValue' if tag == 281 else 'SMaxSampleValue'})" in info_items(res.stdout)
    if bits == 12:
        assert "saturated  5 pixel(s)" in info_items(res.stdout), res.stdout
    elif bits == 14:
        assert "saturated  0 pixel(s)" in info_items(res.stdout), res.stdout
    else:  # the data's maximum: no depth declared, the level guessed from the values
        assert "saturated  0 pixel(s) >= 4095 (from the values; a guess: the file declares no bit depth)" in info_items(
            res.stdout
        ), res.stdout


def test_a_tiff_max_sample_value_its_pixels_exceed_is_not_a_bit_depth(tmp_path):
    """A MaxSampleValue of 4095 over pixels up to 5000 is wrong about them: not used."""
    frames = np.full((2, 16, 16), 1000, np.uint16)
    frames[0, 0, 0] = 5000
    path = tmp_path / "m.tif"
    tifffile.imwrite(path, frames, extratags=[(281, "H", 1, 4095, True)])
    assert "bit_depth" not in read(path).meta
    out = info_items(run_cli("info", path).stdout)  # 1 value of 512 above 4095: over the outlier share
    # the values (up to 5000) under half of 16383: the guess is said to be one (s54)
    assert (
        "saturated  0 pixel(s) >= 16383 (from the values; a guess: the file declares no bit depth, its values (up to 5000) under half"
        in out
    ), out


def test_info_prints_control_characters_of_an_itex_comment_escaped(tmp_path):
    """A NUL, an escape sequence or a bell in a header comment reached the terminal raw: ESC [31m
    turned the rest of the output red, a NUL vanished or cut the line in other programs."""
    import struct

    comment = b'[Application],Software="HiPic\x00\x1b[31mred",SoftwareVersion=9.1\r\n[Camera],CameraName="C7942\x07"'
    head = struct.pack("<2sHhhhhhihhd4s30s", b"IM", len(comment), 8, 4, 0, 0, 2, 1, 1, 0, 0.0, b"", b"")
    path = tmp_path / "nul.img"
    path.write_bytes(head + comment + np.full((4, 8), 100, "<u2").tobytes())
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    assert not any(c in res.stdout for c in "\x00\x1b\x07"), repr(res.stdout)
    assert r"HiPic\x00\x1b[31mred 9.1" in res.stdout and r"C7942\x07" in res.stdout, res.stdout


def test_process_names_the_frame_that_holds_only_nan(tmp_path):
    """``correct`` named the frame; ``process`` said "a raw frame holds only NaN or inf" of a file
    of dozens, leaving the user to search them."""
    path = _experiment(tmp_path / "exp.h5")
    with h5py.File(path, "a") as h5:  # another lab's float frames, projection 7 (step 2) all masked
        frames = h5["entry/instrument/detector/data"][()].astype(np.float32)
        frames[7] = np.nan
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = frames
    one_line_error(run_cli("process", path, "-q", "-o", tmp_path / "out"), "exp.h5", "frame 7 (step 2)", "only NaN")


def test_a_virtual_dataset_over_its_own_file_is_not_said_to_be_in_other_files(tmp_path):
    """A virtual dataset mapping another dataset of the same file was refused as "its data are in
    other files": untrue, and the user went looking for files that do not exist."""
    path = tmp_path / "vds.h5"
    with h5py.File(path, "w") as h5:
        h5["src"] = np.zeros((2, 8, 8), np.uint16)
        layout = h5py.VirtualLayout(shape=(2, 8, 8), dtype=np.uint16)
        layout[:] = h5py.VirtualSource(h5["src"])
        h5.create_virtual_dataset("data", layout)
    line = one_line_error(run_cli("info", path, "--dataset", "data"), "vds.h5", "/data", "virtual dataset", "/src")
    assert "other files" not in line and "outside this file" not in line, line
    assert "--allow-external" in line, line


@pytest.mark.parametrize(
    "shape, planar, found",
    [
        ((5, 16, 16), "separate", "5 samples per pixel (RGB, in planes)"),
        ((16, 16, 5), None, "5 samples per pixel (RGB)"),
        ((3, 16, 16), "separate", "one colour image of 3 planes"),
    ],
)
def test_a_colour_tiff_is_refused_with_the_reason(shape, planar, found, tmp_path):
    """RGB with two extra samples was refused as "TIFF page has shape (5, 16, 16); expected a
    greyscale (rows, cols) image" and no more: no word of what was found nor why it is refused;
    planar RGB said what was found, not why it is refused."""
    path = tmp_path / "rgb.tif"
    extra = [0] * (min(shape) - 3)
    tifffile.imwrite(path, np.zeros(shape, np.uint8), planarconfig=planar, photometric="rgb", extrasamples=extra)
    one_line_error(run_cli("info", path), "rgb.tif", found, "a radiograph is one channel")


def _scaled(path, frames, scale):
    """``path``'s frames from ``frames`` on (a slice) as float64 times ``scale``."""
    with h5py.File(path, "a") as h5:
        data = h5["entry/instrument/detector/data"][()].astype(np.float64)
        data[frames] *= scale
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = data
    return path


def test_float64_counts_beyond_float32s_range_are_one_line_not_a_flood_of_warnings(tmp_path):
    """float64 frames at 1e300, beyond float32's range that the correction and calibration compute
    in: numpy's RuntimeWarnings (overflow in cast, invalid value in subtract) came one after
    another, then "the averaged flat is saturated (>= None)"; projections at 1e300 were counted
    non-positive and filled, a radiograph brighter than anything made opaque, exit code 0."""
    loud = {"PYTHONWARNINGS": "default"}  # the user's warnings, not the tests' silence
    everything = _scaled(_experiment(tmp_path / "all.h5"), slice(None), 1e297)
    one_line_error(run("calibrate", "--experiment", everything, "-o", tmp_path / "c.h5", env=loud), "darks", "float32")
    projections = _scaled(_experiment(tmp_path / "proj.h5"), slice(6, None), 1e297)
    one_line_error(run("process", projections, "-q", "-o", tmp_path / "out", env=loud), "frame 6 (step 1)", "float32")
    cal = tmp_path / "cal.h5"
    assert run_cli("calibrate", "--experiment", _experiment(tmp_path / "exp.h5"), "-o", cal).returncode == 0
    tif = tmp_path / "big.tif"
    tifffile.imwrite(tif, np.full((2, 32, 40), 1e300), photometric="minisblack")
    one_line_error(run("correct", tif, "--cal", cal, "-q", "-o", tmp_path / "o.h5", env=loud), "frame 0", "float32")
    one_line_error(run("register", tif, tif, "--moving-frame", "1", "-o", tmp_path / "r.h5", env=loud), "float32")


def test_process_refusing_a_linked_experiment_names_no_option_it_does_not_have(outside):
    """Found (review s41doc): process's refusal of an experiment whose frames are linked from
    another file said "(allow_external=True; --allow-external)", an option process does not take."""
    files, _ = outside
    path = files["linked experiment"]
    res = run_cli("process", path, "-o", path.with_name("results"))
    one_line_error(res, path.name, "external link")
    assert "--allow-external" not in res.stderr and "allow_external=True" not in res.stderr
    assert "radiokit process reads no data outside the experiment file" in res.stderr


def test_process_refusing_another_layout_names_no_option_it_does_not_have(tmp_path):
    """s46: process's refusal of an HDF5 file of another layout said "pass --dataset PATH", which
    process refuses as an unrecognised argument: it reads experiment files only."""
    path = tmp_path / "scan.h5"
    with h5py.File(path, "w") as h5:
        h5["data"] = np.zeros((3, 16, 20), np.uint16)
    res = run_cli("process", path, "-o", tmp_path / "results")
    one_line_error(res, "scan.h5", "/data (3x16x20 uint16)", "radiokit correct --dataset")
    assert "pass --dataset" not in res.stderr


def test_process_says_its_own_remedy_by_the_readers_advice_field_not_by_its_words(tmp_path):
    """s47: process replaced the readers' advice of --allow-external and --dataset by matching
    their text (cli._EXTERNAL_HOW): a rewording of a reader's message would silently have left
    advice of an option process does not have. The error names the words it advises with."""
    import pickle

    from radiokit import cli

    said = "(any words the reader may choose)"
    err = FormatError(tmp_path / "x.h5", f"linked data {said}", advice={"allow_external": said})
    text = cli._process_error(str(err), None, cli._reader_advice(ValueError("wrapped").with_traceback(None)))
    assert said in text  # no advice given: nothing replaced
    for given in (err, pickle.loads(pickle.dumps(err))):
        text = cli._process_error(str(given), None, cli._reader_advice(given))
        assert "x.h5: linked data" in text and said not in text
        assert "radiokit process reads no data outside the experiment file" in text
    assert not hasattr(cli, "_EXTERNAL_HOW")
    # many files (process_many): the error crosses to the command line as its slot's words and advice
    from radiokit.pipeline import _error_result

    text = cli._batch_error(_error_result(str(tmp_path / "x.h5"), err))
    assert said not in text and "radiokit process reads no data outside the experiment file" in text


@pytest.mark.parametrize("where, said", [(10**6, "lies beyond the end of the 16-byte file"), (0, "offset 0")])
def test_a_tiff_whose_first_ifd_is_not_there_says_where_it_points(tmp_path, where, said):
    """s46: a header pointing its first IFD past the end (a file cut short, a header rewritten)
    said only "TIFF holds no image"; where it points tells a truncated file from an empty one."""
    path = tmp_path / "cut.tif"
    path.write_bytes(b"II*\0" + struct.pack("<I", where) + bytes(8))
    for command in ("info", "register"):
        args = (path, path, "-o", tmp_path / "r.h5") if command == "register" else (path,)
        one_line_error(run_cli(command, *args), "cut.tif", "first IFD", said)


def test_results_pair_that_does_not_exist_names_the_pairs_that_do():
    """``Results.pair("9->3")`` raised a bare StopIteration (inside a generator: a RuntimeError)."""
    record = Results.from_json(_results_json())
    assert record.pair("3->1").moving == 3
    with pytest.raises(KeyError, match=r"no pair '9->3' in these results; they hold 3->1"):
        record.pair("9->3")


def test_write_results_refuses_an_existing_file_unless_overwrite(tmp_path):
    """``write_results`` replaced an existing file by default (``write_registration`` refuses)."""
    path = tmp_path / "results.h5"
    _results_file(path)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="results.h5: exists; pass --overwrite"):
        _results_file(path)
    assert path.read_bytes() == before


def test_process_in_python_names_no_reader_option_it_does_not_take(outside, tmp_path):
    """s47 review: pipeline.process() refused a linked experiment with the reader's advice
    "(allow_external=True; --allow-external)", and another layout with "pass --dataset PATH
    (dataset= in Python)": process() takes neither. Its own remedy, and still the command
    line's in radiokit process (through the error's advice, outermost first)."""
    from radiokit import cli
    from radiokit.pipeline import _error_result, process

    files, _ = outside
    scan = tmp_path / "scan.h5"
    with h5py.File(scan, "w") as h5:
        h5["data"] = np.zeros((3, 16, 20), np.uint16)
    for path, said in ((files["linked experiment"], "copy the linked data into it first"), (scan, "ExperimentWriter")):
        with pytest.raises(FormatError, match=rf"{path.name}: .*process\(\).*{said}") as info:
            process(path, out_dir=tmp_path / "out")
        text = str(info.value)
        assert "allow_external=True" not in text and "--allow-external" not in text and "--dataset" not in text, text
        assert "unless asked for" not in text, text  # nothing process() can ask with
        for words in (
            cli._process_error(text, None, cli._reader_advice(info.value)),
            cli._batch_error(_error_result(str(path), info.value)),
        ):
            assert "process()" not in words and "radiokit process reads" in words, words


def test_several_inputs_errors_keep_their_words_and_advice_when_pickled(tmp_path):
    """s47 review: InputErrors was rebuilt from its message (Exception's pickling): its one text
    was taken for the list of errors, and the copy's words came out one character a line."""
    import pickle

    from radiokit import cli
    from radiokit.errors import InputErrors

    said = "(words that advise --dataset)"
    errors = InputErrors([FormatError(tmp_path / "a.h5", f"x {said}", advice={"dataset": said}), ValueError("b: y")])
    copy = pickle.loads(pickle.dumps(errors))
    assert str(copy) == str(errors) and [str(e) for e in copy.errors] == [str(e) for e in errors.errors]
    assert cli._reader_advice(copy) == {"dataset": said}


def _float_experiment(path, scale):
    """A uint16 experiment (an attenuating square, three steps) rewritten as float32 counts x
    ``scale``: what a float file in other units gives `radiokit process`."""
    rng = np.random.default_rng(0)
    shape = (64, 64)
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(rng.normal(100, 2, shape).round(), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(rng.normal(3000, 20, shape).round(), image_key=ImageKey.FLAT)
        for s, c in enumerate([0.8, 0.78, 0.76], 1):
            img = np.full(shape, 3000 * c)
            img[24:40, 24:40] *= 0.8 - 0.05 * s
            w.append((img + rng.normal(0, 20, shape)).round(), image_key=ImageKey.PROJECTION, step=s)
    if scale != 1:
        with h5py.File(path, "a") as h5:
            name = "entry/instrument/detector/data"
            x, attrs = h5[name][()].astype(np.float32) * np.float32(scale), dict(h5[name].attrs)
            del h5[name]
            ds = h5.create_dataset(name, data=x, chunks=(1, *shape), maxshape=(None, *shape))
            ds.attrs.update(attrs)
    return path


_WARN = {"PYTHONWARNINGS": "default"}  # not run()'s "ignore": the warnings a user sees


def test_process_of_counts_scaled_by_1e20_gives_the_unscaled_results_without_warnings(tmp_path):
    """s50: float32 frames at 1e20 counts (within float32's range) printed "RuntimeWarning:
    overflow encountered in square" three times: the calibration squared the darks' deviations in
    float32, overflowing past 1.8e19, and every pixel's temporal noise came out inf. The
    improvement factor and CNR are ratios of intensities: scaling the counts changes neither."""
    got = {}
    for scale in (1.0, 1e16, 1e20):
        path = _float_experiment(tmp_path / f"x{scale:g}.h5", scale)
        roi = ["--inclusion", "26", "38", "26", "38", "--background", "4", "16", "4", "16"]
        # a real process with Python's warnings as a user's shell has them (run_cli ignores them)
        res = run("process", path, "-q", "--no-report", "--preset", "fast", "--cross-check", "none", *roi, env=_WARN)
        assert res.returncode == 0 and res.stderr == "", res.stderr
        got[scale] = json.loads((tmp_path / f"x{scale:g}" / "results.json").read_text())["domains"]
    for scale in (1e16, 1e20):
        for domain in ("log", "negative"):
            a, b = got[1.0][domain], got[scale][domain]
            assert b["improvement_factor"]["1"] == pytest.approx(a["improvement_factor"]["1"], rel=1e-4), domain
            assert b["cnr"]["1"] == pytest.approx(a["cnr"]["1"], rel=1e-4), domain
            assert b["cnr_reference"] == pytest.approx(a["cnr_reference"], rel=1e-4), domain


# -- JSON in a file's metadata (s52) -----------------------------------------------------------------
DEEP_JSON = {depth: '{"domain": "log", "x": ' + "[" * depth + "]" * depth + "}" for depth in (900, 100_000)}


@pytest.mark.parametrize("depth", sorted(DEEP_JSON))
def test_a_tiff_description_nested_past_radiokit_s_depth_is_kept_as_text_with_a_warning(depth, tmp_path):
    """The ImageDescription radiokit's writer fills with a stack's meta steers nothing but what
    is shown of it (info's domain line; ``meta["description"]``): JSON nested past radiokit's
    depth (900 levels json reads and the meta's every walker recursed into; 100 000 it cannot)
    is kept as text and said, the pixels read. Every command that reads the file: info here."""
    path = tmp_path / "deep.tif"
    frames = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
    tifffile.imwrite(path, frames, description=DEEP_JSON[depth], metadata=None, photometric="minisblack")
    res = run("info", "--json", path, env={"PYTHONWARNINGS": "default"})  # its own process: run_cli hides warnings
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert json.loads(res.stdout)[0]["frames"] == 3
    (line,) = res.stderr.splitlines()
    assert str(path) in line and "nests deeper than 32 levels" in line, line
    with pytest.warns(UserWarning, match=r"deep\.tif: its ImageDescription's JSON nests deeper than 32 levels"):
        f = read(path)
    np.testing.assert_array_equal(f.data, frames)
    assert "description" not in f.meta and f.meta["tags"]["ImageDescription"] == DEEP_JSON[depth]


@pytest.mark.parametrize(
    "description",
    [
        '{"shape": [3, 4, 5], "axes": "ZYX", "x": ' + "[" * 100_000 + "]" * 100_000 + "}",
        '{"shape": [1e999, 4, 5], "axes": "ZYX"}',
        '{"shape": [NaN, 4, 5], "axes": "ZYX"}',
        '{"shape": [' + "9" * 5000 + ", 4, 5]}",
    ],
    ids=["deep", "inf", "nan", "5000 digits"],
)
def test_a_damaged_tifffile_shape_description_is_not_read_and_the_pages_are(description, tmp_path):
    """tifffile's JSON description (its shape and axes) steers how pages are frames; a damaged
    one is not read, as before, whatever the damage: one nested past what json reads, or a shape
    of infinity, ended "cannot be read as tiff: maximum recursion depth exceeded ..." / "cannot
    convert float infinity to integer" (s52)."""
    path = tmp_path / "shaped.tif"
    frames = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
    tifffile.imwrite(path, frames, description=description, metadata=None, photometric="minisblack")
    np.testing.assert_array_equal(read(path).data, frames)
    res = run_cli("info", path)
    assert res.returncode == 0 and "Traceback" not in res.stderr and "3 x 4 rows x 5 cols" in res.stdout, res


@pytest.mark.parametrize("past", ["deep", "long"])
def test_a_tifffile_shape_description_past_radiokit_s_rule_says_its_frame_layout_is_ignored(past, tmp_path):
    """Review of s52: a tifffile shape description (its shape and axes say which pages are
    frames) past radiokit's depth or length is not read, and the pages read as a plain stack;
    the only warning said "kept as text", not that the frame layout it gave was ignored. One
    line, naming the file. Shape (2, 3, 4, 5), axes "TZYX": the layout the description gives."""
    from radiokit._json import MAX_CHARS

    path = tmp_path / "shaped.tif"
    frames = np.arange(6 * 4 * 5, dtype=np.uint16).reshape(6, 4, 5)
    tail = "[" * 40 + "]" * 40 if past == "deep" else "[" + "0," * (MAX_CHARS // 2) + "0]"
    description = '{"shape": [2, 3, 4, 5], "axes": "TZYX", "x": ' + tail + "}"
    tifffile.imwrite(path, frames, description=description, metadata=None, photometric="minisblack")
    with pytest.warns(UserWarning) as caught:
        f = read(path)
    np.testing.assert_array_equal(f.data, frames)
    (line,) = [str(w.message) for w in caught if "ImageDescription" in str(w.message)]
    assert "\n" not in line and line.startswith(f"{path}: "), line
    assert "frame layout (shape [2, 3, 4, 5]) it gives is ignored" in line and "plain stack of its 6 pages" in line


@pytest.mark.parametrize(
    "text",
    [
        '{"pixel_size_mm": ' + "9" * 400 + ', "pixel_size_recorded": false}',
        '{"pixel_size_mm": 0.05, "pixel_size_recorded": false, "x": ' + "[" * 900 + "]" * 900 + "}",
        "[" * 100_000 + "]" * 100_000,
    ],
    ids=["10**400", "deep", "past json"],
)
def test_info_on_results_whose_embedded_json_is_hostile_describes_the_frames(text, tmp_path):
    """``info`` reads a results.h5's @results_json for one line (a pitch the run assumed): a
    number past float's range was an OverflowError traceback (s52); JSON past radiokit's depth is
    no record of radiokit's. Nothing is said of it; the frames are described."""
    path = tmp_path / "results.h5"
    _results_file(path)
    with h5py.File(path, "a") as h5:
        h5["entry"].attrs["results_json"] = text
    res = run_cli("info", path)
    assert res.returncode == 0 and res.stderr == "" and "2 x 4 rows x 5 cols" in res.stdout, res
    assert "pixel_size" not in res.stdout, res.stdout


@pytest.mark.parametrize("depth", [900, 100_000])
def test_a_micro_manager_summary_nested_past_radiokit_s_depth_is_refused_in_one_line(depth, tmp_path):
    """A Micro-Manager summary steers which planes are frames and in what order: nested past
    radiokit's depth it is refused, naming the file and the summary. 100 000 levels, which
    tifffile's own json.loads cannot read, ended "cannot be read as tiff: maximum recursion depth
    exceeded while decoding a JSON array from a unicode string" (s52)."""
    from tests.test_io_formats import _frames, _mmstack_file

    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    summary = '{"MicroManagerVersion": "2.0.0", "Frames": 2, "x": ' + "[" * depth + "]" * depth + "}"
    real_dumps = json.dumps
    with pytest.MonkeyPatch.context() as m:  # the helper writes the summary json.dumps gives it
        m.setattr(json, "dumps", lambda v, *a, **k: summary if "MicroManagerVersion" in v else real_dumps(v, *a, **k))
        _mmstack_file(path, _frames(2), 0, 2)
    _refused(path, lambda: read(path), "Micro-Manager summary nests deeper than 32 levels")
    one_line_error(run_cli("info", path), str(path), "Micro-Manager summary nests deeper than 32 levels")


@pytest.mark.parametrize("past", ["deep", "long"])
def test_a_micro_manager_summary_past_radiokit_s_rule_is_refused_alike_where_read_alone(past, tmp_path):
    """Review of s52: a Micro-Manager summary steers which planes are frames (and which files are
    the set's); past radiokit's rule it is refused naming the file, as one nested too deep was.
    One longer than radiokit._json.MAX_CHARS was parsed (tifffile's json.loads) on a read, and
    silently nothing where radiokit reads the summary alone (``_read_summary``: a file whose index
    map declares more than it holds, its set's files listed for an output's check). Both the same
    line, in both places."""
    import struct

    from radiokit._json import MAX_CHARS
    from radiokit.io._ome import mmstack_set_files
    from tests.test_io_formats import _frames, _mmstack_file

    tail = "[" * 40 + "]" * 40 if past == "deep" else "[" + "0," * (MAX_CHARS // 2) + "0]"
    summary = '{"MicroManagerVersion": "2.0.0", "Frames": 2, "Channels": 1, "Slices": 1, "x": ' + tail + "}"
    said = "nests deeper than 32 levels" if past == "deep" else f"is {len(summary)} characters long, past the"
    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    real_dumps = json.dumps
    with pytest.MonkeyPatch.context() as m:  # the helper writes the summary json.dumps gives it
        m.setattr(json, "dumps", lambda v, *a, **k: summary if "MicroManagerVersion" in v else real_dumps(v, *a, **k))
        _mmstack_file(path, _frames(2), 0, 2)
    _refused(path, lambda: read(path), f"its Micro-Manager summary {said}", "not read")
    out = bytearray(path.read_bytes())
    _, index_at, *_ = struct.unpack_from("<8I", out, 8)
    struct.pack_into("<I", out, index_at + 4, 4 * 10**8)  # the index map declares more than the file
    path.write_bytes(bytes(out))
    with tifffile.TiffFile(path) as tif:
        _refused(path, lambda: mmstack_set_files(tif), f"its Micro-Manager summary {said}", "not read")


def test_calibrate_parses_each_file_s_json_description_once(tmp_path, monkeypatch):
    """Review of s52: a description just inside radiokit's length bound (4 MiB, ~0.6 s a parse)
    was parsed twice per file by ``calibrate``: once where every file is judged from its header
    (radiokit.io.judge_all), which no judge reads it for, and again where its frames are read.
    Once per file: the frames' open. (The parses are counted with radiokit's own parser wrapped.)"""
    import radiokit._json as strict_json

    text = '{"domain": "counts", "k": [' + "0," * 500 + "0]}"
    rng = np.random.default_rng(5)
    for name, level in (("dark.tif", 100), ("flat.tif", 3000)):
        frames = rng.poisson(level, (2, 16, 16)).astype(np.uint16)
        tifffile.imwrite(tmp_path / name, frames, description=text, metadata=None, photometric="minisblack")
    parsed, real = [], strict_json.loads_record
    monkeypatch.setattr(strict_json, "loads_record", lambda t, *a, **k: parsed.append(t == text) or real(t, *a, **k))
    res = run_cli(
        "calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flat.tif", "-o", tmp_path / "c.h5"
    )
    assert res.returncode == 0, res.stderr
    assert sum(parsed) == 2, parsed


def test_a_tiff_description_of_json_past_radiokit_s_length_is_kept_as_text_with_a_warning(tmp_path):
    """s52: a 12 MB description of 10**6 keys was parsed at every open, 8 times in one
    ``calibrate`` of two 2-frame files. JSON in a file's metadata longer than
    radiokit's rule (radiokit._json.MAX_CHARS; a record of radiokit's is KBs) is not parsed: kept as
    text and said, the pixels read."""
    from radiokit._json import MAX_CHARS

    path = tmp_path / "long.tif"
    text = '{"domain": "log", "k": [' + "0," * (MAX_CHARS // 2) + "0]}"
    tifffile.imwrite(path, np.ones((2, 4, 5), np.uint16), description=text, metadata=None, photometric="minisblack")
    with pytest.warns(UserWarning, match=rf"long\.tif: its ImageDescription's JSON is {len(text)} characters long"):
        f = read(path)
    assert f.data.shape == (2, 4, 5) and "description" not in f.meta


# -- TOML a user's file holds (s52) ------------------------------------------------------------------
DEEP_TOML = {depth: 'name = "block"\nx = ' + "[" * depth + "]" * depth + "\n" for depth in (40, 900, 100_000)}


@pytest.mark.parametrize("depth", sorted(DEEP_TOML))
def test_toml_nested_past_radiokit_s_depth_is_one_line_in_every_command_that_reads_it(depth, tmp_path):
    """s52: tomllib parses by recursion, three calls a level: a scene or protocol nested 900 deep
    (or 100 000) ended ``sim run`` and ``acquire`` in a RecursionError traceback, and ``process``
    too where a simulated file's scene held it. Refused in one line naming the file by the rule
    JSON has (radiokit._json.MAX_DEPTH: 40 levels parse, and are past it); a simulated file's
    scene is read as one that is not TOML is (its name unknown, its bound from the background)."""
    from radiokit.io import read_simulation
    from radiokit.pipeline import _bound, _scene_view

    toml = tmp_path / "deep.toml"
    toml.write_text(DEEP_TOML[depth])
    one_line_error(run_cli("sim", "run", toml, "-o", tmp_path / "sim"), "radiokit sim run: ", "nests deeper than 32")
    assert not (tmp_path / "sim").exists()
    res = run_cli("acquire", toml, "--sim", "-o", tmp_path / "acq.h5")
    assert res.returncode == 2 and "Traceback" not in res.stderr and "nests deeper than 32" in res.stderr, res.stderr
    assert str(toml) in res.stderr and not (tmp_path / "acq.h5").exists()
    path = tmp_path / "sim.h5"
    _experiment(path)
    _simulation_group_into(path)
    with h5py.File(path, "a") as h5:
        h5[S].attrs["scene"] = DEEP_TOML[depth]
    assert read_simulation(path).scene_name is None
    truth = {"scene_toml": DEEP_TOML[depth]}
    assert _scene_view(truth) is None
    assert _bound(path, [1, 2, 3], truth, 0.1, (1.0, 2.0))[0].basis.startswith("plate gaps not recorded")


def test_a_simulated_scene_s_attenuation_past_float_s_range_is_refused_in_one_line(tmp_path):
    """s52: ``attenuation_per_cm = 999...9`` (400 digits, a TOML integer) was an OverflowError
    traceback from ``process`` (its improvement factor's bound): refused as any other value that
    is no positive number."""
    from radiokit.pipeline import _bound

    path = tmp_path / "sim.h5"
    _experiment(path)
    scene = 'name = "block"\n[body.material]\nattenuation_per_cm = ' + "9" * 400
    _refused(
        path,
        lambda: _bound(path, [1, 2, 3], {"scene_toml": scene}, 0.1, (1.0, 2.0)),
        "attenuation_per_cm",
        "expected a positive number",
    )


@pytest.mark.parametrize("depth", [40, 100_000])
def test_a_resumed_file_s_stored_protocol_nested_past_radiokit_s_depth_is_one_line(depth, tmp_path):
    """Review s52rvoff: ``acquire --resume`` reads the protocol the file stores (/entry@protocol)
    as TOML, with tomllib itself, which the s52 rule (radiokit.checks.toml_loads) missed: one
    nested 100 000 deep ended in a RecursionError traceback. Refused as any stored protocol that
    is not TOML is: one line naming the file, before any byte is sent."""
    from sim.scene import block_scene
    from tests.test_safety import write_protocol

    scene = tmp_path / "scene.toml"
    scene.write_text(block_scene(size_mm=10.0, ratios=(0.15, 0.25)).to_toml())
    proto = write_protocol(tmp_path, scene, "/dev/null")
    series = tmp_path / "series.h5"  # the protocol's output
    with ExperimentWriter(series, shape=(4, 4), pixel_size_mm=0.05) as w:
        w.h5["entry"].attrs["protocol"] = DEEP_TOML[depth]
    res = run_cli("acquire", proto, "--dry-run", "--sim", "--resume", cwd=tmp_path)
    one_line_error(res, "stored protocol", "nests deeper than 32")


def test_a_one_page_tifffile_description_past_json_s_reach_is_not_read_and_the_page_is(tmp_path):
    """Review s52rvoff: one page of a tifffile description nested past what json reads: radiokit
    asked tifffile's own shaped_metadata whether the file was a truncated stack, whose json.loads
    recursed: "cannot be read as tiff: maximum recursion depth exceeded ..." (s52 fixed it for
    a file of many pages only). Read as the page it is."""
    path = tmp_path / "shaped.tif"
    frame = np.arange(4 * 5, dtype=np.uint16).reshape(4, 5)
    description = '{"shape": [4, 5], "truncated": true, "x": ' + "[" * 100_000 + "]" * 100_000 + "}"
    tifffile.imwrite(path, frame, description=description, metadata=None, photometric="minisblack")
    with pytest.warns(UserWarning, match="nests deeper than 32 levels"):
        np.testing.assert_array_equal(read(path).data, frame[None])
    res = run_cli("info", path)
    assert res.returncode == 0 and "Traceback" not in res.stderr and "1 x 4 rows x 5 cols" in res.stdout, res


@pytest.mark.parametrize("header", [False, True], ids=["dotted key", "table header"])
def test_toml_nested_by_a_long_dotted_key_is_refused_before_tomllib_builds_it(header, tmp_path):
    """Review s52rvoff: a dotted key nests a table a part without a bracket, and tomllib's cost
    is quadratic in its parts (a tuple per prefix): 10 000 parts took 400 MB, and a 200 KB scene
    of one key of 100 000 parts was killed by the kernel (40 GB) before the depth rule
    (radiokit.checks.toml_loads) saw what it built. Refused in one line, inside 1 GiB."""
    toml = tmp_path / "dotted.toml"
    key = ".".join(["a"] * 100_000)
    toml.write_text('name = "block"\n' + (f"[{key}]\nx = 1\n" if header else f"{key} = 1\n"))
    res = run_on_a_big_machine("sim", "run", toml, "-o", tmp_path / "sim")
    one_line_error(res, str(toml), "nests deeper than 32")
    assert not (tmp_path / "sim").exists()
