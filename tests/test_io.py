"""radiokit.io: the five real Hamamatsu ITEX files checked against an independent parse, synthetic
ITEX files, raw round trips for every C7942 preset, TIFF, the experiment HDF5 (including a writer
killed with SIGKILL), and properties: truncated, corrupted or random files raise FormatError and
nothing else."""

import errno
import hashlib
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from conftest import ITEX_DIR, mounted_tmpfs, needs_itex, run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from radiokit.errors import FormatError
from radiokit.io import (
    DEFAULT_PRESET,
    PRESETS,
    BitDepthWarning,
    ExperimentWriter,
    Frames,
    ImageKey,
    StackWriter,
    iter_frames,
    open_frames,
    read,
    sniff,
    write_tiff,
)
from radiokit.io._itex import parse_comment

# derandomize: the suite runs the same examples every time (hypothesis's advice for CI). A random
# run found a corrupted HDF5 file on which libhdf5 itself loops for good inside an attribute
# read, out of reach of any Python time-out (session 25, README "Known limits"): a fuzz run
# that can hang the suite at random is no test; the random search belongs to a deliberate run
# (RADIOKIT_FUZZ=1 draws new examples).
PROPS = settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=not os.environ.get("RADIOKIT_FUZZ"),
)


def _raises_format(path, *fragments, **hints):
    """read(path) must raise FormatError naming the file and containing every fragment."""
    with pytest.raises(FormatError) as info:
        read(path, **hints)
    msg = str(info.value)
    assert str(path) in msg, msg
    for frag in fragments:
        assert frag.lower() in msg.lower(), f"{frag!r} not in {msg!r}"
    return info.value


# ------------------------------------------------------------------------------------------------
# 1. The five real ITEX files, against an independent parse of the layout in C7942.md
# ------------------------------------------------------------------------------------------------


def _independent_itex(path):
    """Parse an ITEX file with struct and numpy only, from the table in C7942.md."""
    raw = Path(path).read_bytes()
    assert raw[:2] == b"IM"
    comment_len, width, height, x0, y0, ftype = (struct.unpack_from("<h", raw, off)[0] for off in (2, 4, 6, 8, 10, 12))
    n_images = struct.unpack_from("<i", raw, 14)[0]
    dtype = {0: "<u1", 2: "<u2", 3: "<u4"}[ftype]
    offset = 64 + comment_len
    n = max(n_images, 1)
    pixels = np.frombuffer(raw, dtype=dtype, count=n * width * height, offset=offset)
    comment = raw[64:offset].decode("latin-1")
    return dict(
        raw=raw,
        width=width,
        height=height,
        ftype=ftype,
        n_images=n_images,
        offset=offset,
        comment=comment,
        pixels=pixels.reshape(n, height, width),
    )


# name: (rows, cols, dtype, file type, comment length, min, max, sum)
REAL_FILES = {
    "focus_mode.img": (512, 672, np.uint32, 3, 3301, 0, 39173, 59743889),
    "operate_mode.img": (512, 672, np.uint32, 3, 3311, 0, 2876657, 7061710453),
    "photon_counting.img": (512, 672, np.uint16, 2, 2886, 0, 35, 110996),
    "shading_file.img": (512, 672, np.uint32, 3, 2682, 5082, 699185, 182917341484),
    "xaxis_other.img": (508, 672, np.uint16, 2, 4120, 346, 649, 137039886),
}


@needs_itex
def test_all_real_files_are_covered():
    assert sorted(p.name for p in ITEX_DIR.glob("*.img")) == sorted(REAL_FILES)


@needs_itex
@pytest.mark.parametrize("name", sorted(REAL_FILES))
def test_real_itex_pixels_match_independent_parse(name):
    rows, cols, dtype, ftype, comment_len, lo, hi, total = REAL_FILES[name]
    path = ITEX_DIR / name
    ref = _independent_itex(path)
    assert (ref["height"], ref["width"], ref["ftype"]) == (rows, cols, ftype)
    assert ref["offset"] == 64 + comment_len

    f = read(path)
    assert isinstance(f, Frames)
    assert f.n == 1 and len(f) == 1
    assert f.shape == (1, rows, cols)
    assert f.data.dtype == dtype
    assert f.path == path
    np.testing.assert_array_equal(f.data[0], ref["pixels"][0])
    # exact values, also computed from the independent parse
    d = ref["pixels"][0]
    assert (int(d.min()), int(d.max()), int(d.sum(dtype=np.uint64))) == (lo, hi, total)
    assert (int(f.data.min()), int(f.data.max()), int(f.data.sum(dtype=np.uint64))) == (lo, hi, total)
    # row 0 is the first row stored, column order as stored
    first = np.frombuffer(ref["raw"], dtype=np.dtype(dtype).newbyteorder("<"), count=cols, offset=ref["offset"])
    np.testing.assert_array_equal(f.data[0, 0], first)
    last_px = np.frombuffer(
        ref["raw"],
        dtype=np.dtype(dtype).newbyteorder("<"),
        count=1,
        offset=ref["offset"] + (rows * cols - 1) * np.dtype(dtype).itemsize,
    )[0]
    assert f.data[0, -1, -1] == last_px

    m = f.meta
    assert m["format"] == "itex"
    assert (m["rows"], m["cols"], m["n"], m["file_type"]) == (rows, cols, 1, ftype)
    assert m["comment_length"] == comment_len
    assert m["offset"] == ref["offset"]
    assert m["file_size"] == len(ref["raw"])
    assert m["comment_text"] == ref["comment"].rstrip("\0")
    assert m["path"] == str(path)


@needs_itex
@pytest.mark.parametrize("name", sorted(REAL_FILES))
def test_real_itex_lazy_access_matches_read(name):
    path = ITEX_DIR / name
    ref = _independent_itex(path)["pixels"]
    with open_frames(path) as src:
        assert len(src) == 1
        np.testing.assert_array_equal(src[0], ref[0])
        np.testing.assert_array_equal(src[-1], ref[0])
        with pytest.raises(IndexError):
            src[1]
    frames = list(iter_frames(path))
    assert len(frames) == 1
    np.testing.assert_array_equal(frames[0], ref[0])
    assert sniff(path) == "itex"


@needs_itex
def test_real_itex_sections_in_order():
    for name in REAL_FILES:
        f = read(ITEX_DIR / name)
        text = _independent_itex(ITEX_DIR / name)["comment"]
        sections = re.findall(r"\[([^\]\r\n]*)\]", text)
        assert list(f.meta["comment"]) == sections, name
        assert "_unparsed" not in f.meta["comment"], name
        assert "" not in f.meta["comment"], name


# (file, section, key, expected value) -- expected type matters: numbers come back as numbers
COMMENT_VALUES = [
    ("focus_mode.img", "Camera", "CameraName", "Orca R2"),
    ("photon_counting.img", "Camera", "CameraName", "Orca R2"),
    ("xaxis_other.img", "Camera", "CameraName", "C13440-20C"),
    ("focus_mode.img", "Camera", "SerialNumber", "S/N: 891892"),
    ("focus_mode.img", "Application", "Software", "HPD-TA"),
    ("focus_mode.img", "Application", "ApplicationTitle", "High Performance Digital Temporal Analyzer"),
    ("focus_mode.img", "Application", "Time", "11:28:55.083"),
    ("operate_mode.img", "Application", "SoftwareVersion", "9.5 pf10"),
    # quoted values holding commas stay whole
    ("focus_mode.img", "Acquisition", "areSource", "0,0,672,512"),
    ("xaxis_other.img", "Acquisition", "areSource", "0,0,672,508"),
    ("xaxis_other.img", "Acquisition", "pntOrigCh", "352,516"),
    ("operate_mode.img", "Acquisition", "pntBinning", "2,2"),
    # bare integers and floats become numbers; quoted numbers stay text
    ("focus_mode.img", "Camera", "Type", 37),
    ("photon_counting.img", "Camera", "Type", 23),
    ("focus_mode.img", "Camera", "Binning", "2"),
    ("focus_mode.img", "Camera", "CoolerSwitch", "-1"),
    ("focus_mode.img", "Camera", "Prop_TimingMinTriggerInterval", 0.117461),
    ("focus_mode.img", "Camera", "Prop_OutputTriggerPeriod", 0.0001),
    ("xaxis_other.img", "Camera", "Prop_InternalLineInterval", 0.00000974436),
    ("xaxis_other.img", "Camera", "Prop_ConversionFactorOffset", 400),
    ("focus_mode.img", "Acquisition", "NrExposure", 4),
    ("operate_mode.img", "Acquisition", "NrExposure", 60),
    ("photon_counting.img", "Acquisition", "NrExposure", 10000),
    ("focus_mode.img", "Acquisition", "BytesPerPixel", 4),
    ("photon_counting.img", "Acquisition", "BytesPerPixel", 2),
    ("focus_mode.img", "Acquisition", "BacksubCorr", -1),
    ("photon_counting.img", "Camera", "PCThreshold", 111),
    # bare text (with a space) stays text
    ("focus_mode.img", "Acquisition", "ExposureTime", "5 s"),
    ("photon_counting.img", "Acquisition", "ExposureTime", "200 ms"),
    ("focus_mode.img", "Acquisition", "ZAxisLabel", "Intensity"),
    ("xaxis_other.img", "Streak camera", "InstalledOption0", "M16914-01"),
    # keys with spaces and dots
    ("focus_mode.img", "Streak camera", "Time Range", "5 ns"),
    ("focus_mode.img", "Streak camera", "Trig. Mode", "Cont"),
    ("focus_mode.img", "Delay box", "Delay Int.Trig", "-999999999900"),
    ("focus_mode.img", "Delay box", "PluginName", ""),
    ("focus_mode.img", "Delay2 box", "UseDevice", 0),
    # [Grabber] and [DisplayLUT] follow each other without CRLF
    ("focus_mode.img", "Grabber", "SubType", 0),
    ("focus_mode.img", "DisplayLUT", "EntrySize", 9),
    ("focus_mode.img", "DisplayLUT", "UpperValue", 1685),
    ("operate_mode.img", "DisplayLUT", "Lut16xOvlVal", 3932100),
    ("shading_file.img", "DisplayLUT", "BitRange", "16x bit"),
    ("xaxis_other.img", "DisplayLUT", "UpperValueEx", 65535),
    # [Scaling] and [Comment] likewise
    ("focus_mode.img", "Scaling", "ScalingYScalingFile", "Focus mode"),
    ("focus_mode.img", "Scaling", "ScalingXScalingFile", "#1379621,0672"),
    ("focus_mode.img", "Comment", "UserComment", ""),
    ("xaxis_other.img", "Comment", "UserComment", ""),
]


@needs_itex
@pytest.mark.parametrize("name, section, key, expected", COMMENT_VALUES)
def test_real_itex_comment_values(name, section, key, expected):
    value = read(ITEX_DIR / name).meta["comment"][section][key]
    assert type(value) is type(expected), (value, expected)
    assert value == expected


@needs_itex
@pytest.mark.parametrize("name", sorted(REAL_FILES))
def test_real_itex_grabber_section_ends_where_displaylut_begins(name):
    c = read(ITEX_DIR / name).meta["comment"]
    assert c["Grabber"] == {"Type": 5, "SubType": 0}
    assert "DisplayLUT" in c and "EntrySize" in c["DisplayLUT"]
    assert c["Comment"] == {"UserComment": ""}
    assert set(c["Scaling"]) == {f"Scaling{a}{k}" for a in "XY" for k in ("Type", "Scale", "Unit", "ScalingFile")}


# name: {axis: (type, unit, pointer count or scaling name)}
REAL_SCALING = {
    "focus_mode.img": {"x": (2, "nm", 672), "y": (1, "", "Focus mode")},
    "operate_mode.img": {"x": (2, "nm", 672), "y": (2, "us", 512)},
    "photon_counting.img": {"x": (2, "nm", 672), "y": (2, "ns", 512)},
    "shading_file.img": {"x": (2, "nm", 672), "y": (2, "ps", 512)},
    "xaxis_other.img": {"x": (1, "", "Other"), "y": (1, "", "Focus mode")},
}


@needs_itex
@pytest.mark.parametrize("name", sorted(REAL_SCALING))
def test_real_itex_scaling_axes(name):
    ref = _independent_itex(ITEX_DIR / name)
    scaling = read(ITEX_DIR / name).meta["scaling"]
    assert set(scaling) == {"x", "y"}
    ends = []
    for axis, (stype, unit, what) in REAL_SCALING[name].items():
        entry = scaling[axis]
        assert entry["type"] == stype
        assert entry["unit"] == unit
        if isinstance(what, int):
            m = re.search(rf'Scaling{axis.upper()}ScalingFile="#(\d+),(\d+)"', ref["comment"])
            off, count = int(m.group(1)), int(m.group(2))
            assert count == what
            expected = np.frombuffer(ref["raw"], "<f4", count=count, offset=off)
            assert entry["values"].dtype == np.float32
            assert entry["values"].shape == (count,)
            np.testing.assert_array_equal(entry["values"], expected)
            assert np.all(np.isfinite(entry["values"]))
            assert "name" not in entry
            ends.append(off + 4 * count)
            # the first axis block starts right after the pixels
            if axis == "x":
                assert off == ref["offset"] + ref["pixels"].nbytes
        else:
            assert entry["name"] == what
            assert "values" not in entry
    if ends:  # the last axis block ends the file
        assert max(ends) == len(ref["raw"])


@needs_itex
def test_real_itex_axis_values_are_monotonic_wavelengths_and_times():
    s = read(ITEX_DIR / "operate_mode.img").meta["scaling"]
    x, y = s["x"]["values"], s["y"]["values"]
    assert np.all(np.diff(x) < 0)  # a spectrograph axis, in nm, decreasing
    assert 400 < x.min() < x.max() < 600
    assert y[0] == 0 and np.all(np.diff(y) > 0)  # a streak time axis starting at 0
    assert y[-1] == pytest.approx(16.009396, rel=1e-6)


# ------------------------------------------------------------------------------------------------
# 2. Synthetic ITEX files
# ------------------------------------------------------------------------------------------------


def _itex_bytes(
    pixels,
    ftype,
    comment=b"",
    n_images=None,
    tail=b"",
    width=None,
    height=None,
    comment_len=None,
    magic=b"IM",
    order="<",
):
    """Build an ITEX file from the layout in C7942.md (``order=">"``: the header and pixels big-endian)."""
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[None]
    n, rows, cols = pixels.shape
    dtype = order + {0: "u1", 1: "u2", 2: "u2", 3: "u4"}[ftype]
    head = bytearray(64)
    head[0:2] = magic
    struct.pack_into(order + "H", head, 2, len(comment) if comment_len is None else comment_len % 65536)
    struct.pack_into(order + "h", head, 4, cols if width is None else width)
    struct.pack_into(order + "h", head, 6, rows if height is None else height)
    struct.pack_into(order + "h", head, 12, ftype)
    struct.pack_into(order + "i", head, 14, (0 if n == 1 else n) if n_images is None else n_images)
    struct.pack_into(order + "d", head, 22, 12.5)
    return bytes(head) + comment + pixels.astype(dtype).tobytes() + tail


def test_itex_8bit(tmp_path):
    rng = np.random.default_rng(1)
    pix = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    path = tmp_path / "eight.img"
    path.write_bytes(_itex_bytes(pix, 0, b'[Camera],CameraName="X",Gain=3'))
    f = read(path)
    assert f.data.dtype == np.uint8
    assert f.shape == (1, 5, 7)
    np.testing.assert_array_equal(f.data[0], pix)
    assert f.meta["file_type"] == 0
    assert f.meta["comment"] == {"Camera": {"CameraName": "X", "Gain": 3}}
    assert f.meta["time_stamp"] == 12.5
    assert f.meta["scaling"] == {}


def test_itex_comment_padded_with_nuls(tmp_path):
    pix = np.arange(4, dtype=np.uint16).reshape(2, 2)
    path = tmp_path / "padded.img"
    path.write_bytes(_itex_bytes(pix, 2, b"[S],k=1,t=ab\x00\x00\x00\x00"))
    f = read(path)
    assert f.meta["comment"] == {"S": {"k": 1, "t": "ab"}}
    assert f.meta["comment_text"] == "[S],k=1,t=ab"
    np.testing.assert_array_equal(f.data[0], pix)


def test_itex_32bit_values_above_16_bits_do_not_warn(tmp_path):
    pix = np.array([[0, 70000, 2**32 - 1]], np.uint32)
    path = tmp_path / "wide.img"
    path.write_bytes(_itex_bytes(pix, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = read(path)
    np.testing.assert_array_equal(f.data[0], pix)
    assert f.data.dtype == np.uint32


def test_itex_multi_image(tmp_path):
    rng = np.random.default_rng(2)
    pix = rng.integers(0, 65536, (3, 4, 6), dtype=np.uint16)
    path = tmp_path / "three.img"
    path.write_bytes(_itex_bytes(pix, 2, b"[A],k=1\r\n", n_images=3))
    f = read(path)
    assert f.n == 3
    assert f.shape == (3, 4, 6)
    np.testing.assert_array_equal(f.data, pix)
    with open_frames(path) as src:
        assert len(src) == 3
        np.testing.assert_array_equal(src[2], pix[2])
        np.testing.assert_array_equal(src[-3], pix[0])
    # n= reads the first frames only
    g = read(path, n=2)
    assert g.n == 2
    np.testing.assert_array_equal(g.data, pix[:2])


@pytest.mark.parametrize("n", [0, -1, 4])
def test_itex_n_hint_out_of_range(tmp_path, n):
    path = tmp_path / "three.img"
    path.write_bytes(_itex_bytes(np.zeros((3, 2, 2), np.uint16), 2, n_images=3))
    _raises_format(path, "n=", n=n)


def test_itex_scaling_pointer_synthetic(tmp_path):
    pix = np.arange(12, dtype=np.uint16).reshape(3, 4)
    axis = np.linspace(-1, 1, 4).astype("<f4")
    comment = (
        b'[Scaling],ScalingXType=2,ScalingXUnit="mm",ScalingXScalingFile="#OFFS,0004",ScalingYScalingFile="Focus mode"'
    )
    off = 64 + len(comment) + pix.nbytes
    comment = comment.replace(b"OFFS", b"%04d" % off)
    path = tmp_path / "scaled.img"
    path.write_bytes(_itex_bytes(pix, 2, comment, tail=axis.tobytes()))
    f = read(path)
    np.testing.assert_array_equal(f.data[0], pix)
    np.testing.assert_array_equal(f.meta["scaling"]["x"]["values"], axis)
    assert f.meta["scaling"]["x"]["unit"] == "mm"
    assert f.meta["scaling"]["y"]["name"] == "Focus mode"


def test_itex_scaling_pointer_beyond_end(tmp_path):
    comment = b'[Scaling],ScalingXScalingFile="#90,0100"'
    path = tmp_path / "badscale.img"
    path.write_bytes(_itex_bytes(np.zeros((2, 2), np.uint16), 2, comment))
    _raises_format(path, "Scaling", "beyond the end")


@needs_itex
@pytest.mark.parametrize(
    "name, change",
    [("photon_counting.img", d) for d in (-2, -1, 1, 2)] + [("xaxis_other.img", -1), ("focus_mode.img", 1)],
)
def test_itex_comment_length_off_by_a_few_bytes_is_refused(tmp_path, name, change):
    """A header's comment length a byte or two off moves the pixels' start: the photon-counting
    file's 0..35 read as 0..45824 (a review's edit, +1), silently. The [Scaling] pointer says where
    the writer's pixels end, and HPD-TA's comment ends in a quoted value: either disagreeing with
    the header is refused in one line naming the file."""
    raw = bytearray((ITEX_DIR / name).read_bytes())
    struct.pack_into("<H", raw, 2, struct.unpack_from("<H", raw, 2)[0] + change)
    path = tmp_path / name
    path.write_bytes(bytes(raw))
    _raises_format(path, "comment length disagrees" if change < 0 and name == "xaxis_other.img" else "disagrees")
    res = run_cli("info", path)
    assert res.returncode == 2 and "Traceback" not in res.stderr and str(path) in res.stderr, res.stderr
    assert len([line for line in res.stderr.splitlines() if line.strip()]) == 1, res.stderr


@needs_itex
@pytest.mark.parametrize("name", ["focus_mode.img", "photon_counting.img", "xaxis_other.img"])
@pytest.mark.parametrize("cut", ["none", "last section"])
def test_itex_comment_length_that_leaves_comment_text_as_pixels_is_refused(tmp_path, name, cut):
    """s53: a header's comment length of 0 (zeroed), or one ending where a section begins, leaves
    no quoted value cut and no [Scaling] pointer read, so nothing disagreed: the comment's text was
    read as the first pixels (focus_mode's 0..39173 came out 0..2053730927) and ``correct`` wrote
    a stack of it. Pixels that begin with a comment's section (``[Application],Date=``) are
    refused in one line naming the file."""
    raw = bytearray((ITEX_DIR / name).read_bytes())
    length = struct.unpack_from("<H", raw, 2)[0]
    comment = bytes(raw[64 : 64 + length])
    new = 0 if cut == "none" else comment.rindex(b"\r\n[") + 2  # the last section's "[" starts the pixels
    assert comment[new : new + 1] == b"["
    struct.pack_into("<H", raw, 2, new)
    path = tmp_path / name
    path.write_bytes(bytes(raw))
    _raises_format(path, "comment")
    res = run_cli("info", path)
    assert res.returncode == 2 and "Traceback" not in res.stderr and str(path) in res.stderr, res.stderr
    assert len([line for line in res.stderr.splitlines() if line.strip()]) == 1, res.stderr


def test_itex_stray_quote_in_a_comment_of_the_right_length_still_reads(tmp_path):
    """A quote typed into a user's comment leaves an odd count, but the comment still ends as
    HPD-TA ends it: no sign of a wrong length, read as before; cut inside its last value, refused."""
    pix = np.arange(32, dtype=np.uint16).reshape(4, 8)
    path = tmp_path / "stray.img"
    path.write_bytes(_itex_bytes(pix, 2, b'[Camera],CameraName="Orca R2,Serial="S/N 1"\r\n[Comment],UserComment=""'))
    np.testing.assert_array_equal(read(path).data[0], pix)
    path.write_bytes(_itex_bytes(pix, 2, b'[Camera],CameraName="Orca R2"\r\n[Comment],UserComment="'))
    _raises_format(path, "ends inside a quoted value")


def test_itex_compressed_type_raises(tmp_path):
    path = tmp_path / "packed.img"
    path.write_bytes(_itex_bytes(np.zeros((4, 4), np.uint16), 1))
    _raises_format(path, "compressed")


@pytest.mark.parametrize(
    "change",
    [
        dict(width=9),  # wider than the pixels present
        dict(height=30000),
        dict(n_images=5),
        dict(comment_len=200),  # comment claimed longer than the file
        dict(n_images=2**31 - 1),
    ],
)
def test_itex_header_promises_more_than_file(tmp_path, change):
    path = tmp_path / "short.img"
    path.write_bytes(_itex_bytes(np.ones((4, 8), np.uint16), 2, b"[A],b=1", **change))
    _raises_format(path, "the file has")


@pytest.mark.parametrize(
    "stored, change",
    [
        ((3, 4, 8), dict(n_images=0)),  # 0, which HiPic writes for one image, over three
        ((3, 4, 8), dict(n_images=2)),
        ((1, 4, 8), dict(width=4, height=2)),  # a quarter of the pixels declared: three more "images"
    ],
    ids=["0-images-over-3", "2-images-over-3", "size-smaller-than-stored"],
)
def test_itex_header_declaring_fewer_pixels_than_the_file_holds_is_refused(tmp_path, stored, change):
    """A header whose count or size declares less than the pixels after its comment (a count of
    0 over a stack, a size edited or from another binning): the first images' bytes read as the
    declared ones, silently, the rest ignored or each frame sheared. Bytes past the declared
    images that no [Scaling] axis accounts for, an image's worth or more, are refused in one line
    naming the file; HPD-TA's own files (their axes after the pixels) read as before."""
    pix = np.arange(np.prod(stored), dtype=np.uint16).reshape(stored)
    path = tmp_path / "stack.img"
    path.write_bytes(_itex_bytes(pix, 2, b"[A],b=1", **change))
    _raises_format(path, "ITEX header declares", "no [Scaling] axis accounts for", "disagrees with the file")
    res = run_cli("info", path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert [line for line in res.stderr.splitlines() if line.strip()] == [
        line for line in res.stderr.splitlines() if "stack.img" in line
    ]


def test_itex_with_a_few_bytes_after_its_pixels_still_reads(tmp_path):
    """Padding short of an image after the pixels (a writer rounding the file up) is no header
    disagreement: read as declared."""
    pix = np.arange(32, dtype=np.uint16).reshape(4, 8)
    path = tmp_path / "padded.img"
    path.write_bytes(_itex_bytes(pix, 2, b"[A],b=1", tail=bytes(62)))
    np.testing.assert_array_equal(read(path).data[0], pix)


@pytest.mark.parametrize(
    "change, fragment",
    [
        (dict(width=0), "0x4"),
        (dict(height=-4), "8x-4"),
        (dict(n_images=-2), "negative image count"),
    ],
)
def test_itex_header_nonsense(tmp_path, change, fragment):
    path = tmp_path / "nonsense.img"
    path.write_bytes(_itex_bytes(np.ones((4, 8), np.uint16), 2, **change))
    _raises_format(path, fragment)


def test_itex_comment_over_32767_bytes_is_read(tmp_path):
    """The comment length is unsigned 16-bit: a valid file with a 40 000-byte comment was refused
    as "negative comment length -25536" (the field read as int16). Read as int16 in this
    test's own layout the same bytes would be negative, so the test fails on a signed reader."""
    pix = np.arange(12, dtype=np.uint16).reshape(3, 4)
    comment = b"[Info],Note=" + b"x" * (40_000 - 12)
    path = tmp_path / "long.img"
    path.write_bytes(_itex_bytes(pix, 2, comment))
    assert struct.unpack_from("<h", path.read_bytes(), 2)[0] < 0
    f = read(path)
    np.testing.assert_array_equal(f.data[0], pix)
    assert f.meta["comment_length"] == 40_000 and len(f.meta["comment"]["Info"]["Note"]) == 40_000 - 12
    # a comment claimed longer than the file is still refused, not read as pixels
    path.write_bytes(_itex_bytes(pix, 2, b"[A],b=1", comment_len=65_000))
    _raises_format(path, "65000-byte comment", "the file has")


def test_itex_big_endian_header_is_named(tmp_path):
    """ITEX is little-endian; a big-endian header read "unknown ITEX file type 512", leaving the
    user to guess. The one line now says the header is big-endian."""
    head = bytearray(64)
    head[0:2] = b"IM"
    struct.pack_into(">hhhhhhi", head, 2, 0, 4, 3, 0, 0, 2, 0)
    path = tmp_path / "be.img"
    path.write_bytes(bytes(head) + np.arange(12, dtype=">u2").tobytes())
    err = _raises_format(path, "big-endian", "little-endian")
    assert "512" in str(err)


@pytest.mark.parametrize(
    ("shape", "comment"),
    [((1, 3, 640), b""), ((1, 3, 4), b'[Camera],CameraName="X"'), ((3, 5, 7), b"[A],b=1"), ((1, 2, 300), b"")],
)
def test_itex_big_endian_8bit_header_is_named(tmp_path, shape, comment):
    """File type 0 reads 0 in either byte order, so a big-endian 8-bit file passed the type check and
    was read with swapped sizes (640 wide read -32766, a 23-byte comment 5888 bytes) or refused as
    truncated. Its sizes read big-endian are what fit the file: the one line says big-endian."""
    pix = np.arange(np.prod(shape), dtype=np.uint8).reshape(shape)
    path = tmp_path / "be8.img"
    path.write_bytes(_itex_bytes(pix, 0, comment, order=">"))
    err = _raises_format(path, "big-endian", "file type 0", "little-endian")
    assert f"{shape[0]} image(s) of {shape[2]}x{shape[1]}" in str(err)


@pytest.mark.parametrize(("cols", "tail"), [(256, b""), (512, b"\0" * 8)])
def test_itex_8bit_whose_sizes_fit_either_way_reads_little_endian(tmp_path, cols, tail):
    """256 x 1 read swapped is 1 x 256, as many bytes: both readings fill the file, and one 512 x 1
    with a block after it fits both ways; the header cannot tell, so it is read as HiPic writes."""
    pix = (np.arange(cols) % 251).astype(np.uint8)[None]
    path = tmp_path / "le8.img"
    path.write_bytes(_itex_bytes(pix, 0, tail=tail))
    np.testing.assert_array_equal(read(path).data[0], pix)


def test_itex_unknown_type_and_wrong_magic(tmp_path):
    data = bytearray(_itex_bytes(np.ones((2, 2), np.uint16), 2))
    struct.pack_into("<h", data, 12, 7)
    path = tmp_path / "seven.img"
    path.write_bytes(bytes(data))
    _raises_format(path, "type 7")
    bad = tmp_path / "magic.img"
    bad.write_bytes(b"XY" + bytes(_itex_bytes(np.ones((2, 2), np.uint16), 2))[2:])
    _raises_format(bad, "magic")
    short = tmp_path / "short.img"
    short.write_bytes(b"IM" + bytes(20))
    _raises_format(short, "64 bytes")


@pytest.mark.parametrize(
    "stored, cause",
    [(lambda p: p.byteswap(), "byte-swapped values fit"), (lambda p: p << 4, "MSB-aligned")],
)
def test_itex_of_a_12_bit_flat_panel_is_checked_against_its_adc(tmp_path, stored, cause):
    """An ITEX file whose comment names a Hamamatsu C7942 (12-bit ADC, C7942.md) holding values
    no 12-bit ADC gives: its own writer's byte order or bit alignment. Read silently, a set of
    byte-swapped darks, flats and frames calibrated to c = 29438 counts and corrected to noise
    with no word of it; a raw C7942 frame warns so. The file's camera says what its ADC is."""
    from radiokit.io import BitDepthWarning

    rng = np.random.default_rng(5)
    pix = rng.integers(100, 4096, (30, 40)).astype(np.uint16)
    comment = b'[Application],Software="XVS-FPD"\r\n[Camera],CameraName="C7942CA-02"'
    good, bad = tmp_path / "good.img", tmp_path / "bad.img"
    good.write_bytes(_itex_bytes(pix, 2, comment))
    bad.write_bytes(_itex_bytes(stored(pix), 2, comment))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = read(good)
    assert f.meta["bit_depth"] == 12
    np.testing.assert_array_equal(f.data[0], pix)
    with pytest.warns(BitDepthWarning, match=f"12-bit range.*{cause}"):
        read(bad)


@needs_itex
def test_itex_of_another_camera_says_nothing_of_its_adc():
    """HPD-TA's Orca R2 files (summed, 32-bit) name no 12-bit panel: no bit depth is assumed."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = read(ITEX_DIR / "shading_file.img")
    assert "bit_depth" not in f.meta


def test_itex_magic_without_extension_is_itex(tmp_path):
    pix = np.arange(6, dtype=np.uint16).reshape(2, 3)
    path = tmp_path / "noext"
    path.write_bytes(_itex_bytes(pix, 2))
    assert sniff(path) == "itex"
    np.testing.assert_array_equal(read(path).data[0], pix)


@pytest.mark.parametrize(
    "text, expected",
    [
        ('[A],k=1,s="x, y",f=2.5', {"A": {"k": 1, "s": "x, y", "f": 2.5}}),
        ("[A],a=1[B],b=2", {"A": {"a": 1}, "B": {"b": 2}}),
        ('[A],a="1,2"[B],b=x y\r\n[C],c=-3', {"A": {"a": "1,2"}, "B": {"b": "x y"}, "C": {"c": -3}}),
        ("k=1,[S],v=1e-3", {"": {"k": 1}, "S": {"v": 1e-3}}),
        ('[S],empty=,q=""', {"S": {"empty": "", "q": ""}}),
        ('[S],a="[not a section]"', {"S": {"a": "[not a section]"}}),
        ("[S],a=b=c", {"S": {"a": "b=c"}}),
        ("[S],stray,k=2", {"S": {"k": 2}, "_unparsed": ["stray"]}),
        ("[S],stray,[T],k=2", {"S": {}, "T": {"k": 2}, "_unparsed": ["stray"]}),
        ("[S],n=" + "9" * 5000, {"S": {"n": "9" * 5000}}),  # too long for int(): stays text
        # only plain decimal literals become numbers
        (
            "[S],a=1_000,b=nan,c=Infinity,d=+7,e=.5,f=0x10",
            {"S": {"a": "1_000", "b": "nan", "c": "Infinity", "d": 7, "e": 0.5, "f": "0x10"}},
        ),
        ("", {}),
    ],
)
def test_parse_comment_table(text, expected):
    assert parse_comment(text) == expected


@PROPS
@given(
    st.text(alphabet=st.sampled_from(list('[]=,"\r\n \x00aZ09.-_#')) | st.characters(max_codepoint=255), max_size=200)
)
def test_parse_comment_never_raises(text):
    out = parse_comment(text)
    assert isinstance(out, dict)
    for value in out.values():
        assert isinstance(value, (dict, list))


# ------------------------------------------------------------------------------------------------
# 3. Raw C7942 files
# ------------------------------------------------------------------------------------------------

# name: (rows, cols, binning)
PRESET_TABLE = {
    "c7942": (2240, 2240, 1),
    "c7942-2x2": (1120, 1120, 2),
    "c7942-4x4": (560, 560, 4),
    "c7942-2344": (2344, 2240, 1),
    "c7942-2344-2x2": (1172, 1120, 2),
    "c7942-2344-4x4": (586, 560, 4),
    "c7942-2368": (2368, 2240, 1),
    "c7942-2368-2x2": (1184, 1120, 2),
    "c7942-2368-4x4": (592, 560, 4),
}


def test_preset_table():
    assert sorted(PRESETS) == sorted(PRESET_TABLE)
    assert DEFAULT_PRESET == "c7942"
    for name, (rows, cols, b) in PRESET_TABLE.items():
        p = PRESETS[name]
        assert (p.name, p.rows, p.cols, p.binning, p.bits) == (name, rows, cols, b, 12)
        assert p.frame_bytes == rows * cols * 2
        assert p.pixel_size_mm == pytest.approx(0.05 * b)
    # every preset's single frame has its own size
    assert len({p.frame_bytes for p in PRESETS.values()}) == len(PRESETS)


def _rand12(shape, seed=0):
    return np.random.default_rng(seed).integers(0, 4096, shape, dtype=np.uint16)


@pytest.mark.parametrize("name", sorted(PRESET_TABLE))
def test_raw_round_trip_every_preset(tmp_path, name):
    rows, cols, b = PRESET_TABLE[name]
    data = _rand12((rows, cols), seed=len(name))
    path = tmp_path / f"{name}.raw"
    data.astype("<u2").tofile(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BitDepthWarning)
        f = read(path, preset=name)
    assert f.meta["format"] == "raw"
    assert f.meta["preset"] == name
    assert (f.meta["rows"], f.meta["cols"], f.meta["n"]) == (rows, cols, 1)
    assert f.meta["bits"] == 12
    assert f.meta["pixel_size_mm"] == pytest.approx(0.05 * b)
    assert f.shape == (1, rows, cols)
    assert f.data.dtype == np.uint16 and f.data.dtype.isnative
    np.testing.assert_array_equal(f.data[0], data)
    # without preset=: one 4x4-binned frame is no whole number of any other preset's frames; one
    # unbinned or 2x2-binned frame is also 4 (or 16) frames binned further, and is refused
    if b == 4:
        assert read(path).meta["preset"] == name
    else:
        _raises_format(path, "ambiguous", f"1 frame of {rows}x{cols} ({name})", f"frames of {rows // (4 // b)}x")


def test_raw_full_frames_need_the_geometry_named(tmp_path):
    """Found by an outside test: four 2x2-binned frames have the bytes of one 2240 x 2240 frame
    and were read as one (garbage), silently, while three were refused as ambiguous. C7942.md
    asks for inference only where the size is unambiguous: a whole number of 2240 x 2240 frames
    is also four times as many 2x2-binned ones, so the reader names them all and reads the one
    preset= (or shape=) names."""
    data = _rand12((3, 2240, 2240), seed=5)
    path = tmp_path / "stack.raw"
    data.tofile(path)
    _raises_format(
        path,
        "ambiguous",
        "3 frames of 2240x2240 (c7942)",
        "12 frames of 1120x1120 (c7942-2x2)",
        "48 frames of 560x560 (c7942-4x4)",
        "--preset c7942",
    )
    f = read(path, preset="c7942")
    assert f.meta["preset"] == "c7942"
    assert f.n == 3
    np.testing.assert_array_equal(f.data, data)
    with open_frames(path, preset="c7942") as src:
        assert len(src) == 3
        np.testing.assert_array_equal(src[1], data[1])
    assert [int(fr[0, 0]) for fr in iter_frames(path, preset="c7942")] == [int(v) for v in data[:, 0, 0]]
    g = read(path, preset="c7942", n=2)
    assert g.n == 2
    np.testing.assert_array_equal(g.data, data[:2])
    assert read(path, shape=(2240, 2240)).n == 3


@pytest.mark.parametrize("name, n", [("c7942-4x4", 5), ("c7942-2344-4x4", 2), ("c7942-2368-4x4", 3)])
def test_raw_stack_of_binned_frames(tmp_path, name, n):
    rows, cols, _ = PRESET_TABLE[name]
    data = _rand12((n, rows, cols), seed=n)
    path = tmp_path / "binned.raw"
    data.tofile(path)
    f = read(path)
    assert f.meta["preset"] == name
    assert f.n == n
    np.testing.assert_array_equal(f.data, data)


@pytest.mark.parametrize("name", ["c7942-2x2", "c7942-2344-2x2", "c7942-2368-2x2"])
@pytest.mark.parametrize("n", [1, 3, 4])
def test_raw_stacks_of_2x2_frames_need_preset(tmp_path, name, n):
    """n 2x2-binned frames are as long as 4n 4x4-binned ones: the size cannot tell them apart.
    Four of them are also one unbinned frame: that one was read as a 2240-wide frame, silently."""
    rows, cols, _ = PRESET_TABLE[name]
    data = _rand12((n, rows, cols), seed=3)
    path = tmp_path / "binned.raw"
    data.tofile(path)
    four = name.replace("2x2", "4x4")
    _raises_format(path, "ambiguous", f"({name})", f"{4 * n} frames of {rows // 2}x{cols // 2} ({four})", "preset=")
    f = read(path, preset=name)
    assert f.n == n and f.meta["preset"] == name
    np.testing.assert_array_equal(f.data, data)
    assert read(path, preset=four).n == 4 * n


@pytest.mark.parametrize("size", [1, 2, 1000, 627200 - 2, 627200 + 2, 10035200 - 1000])
def test_raw_size_matching_no_geometry(tmp_path, size):
    path = tmp_path / "odd.raw"
    path.write_bytes(bytes(size))
    _raises_format(path, str(size), "matches no")


def test_raw_preset_hint_with_partial_frame(tmp_path):
    path = tmp_path / "partial.raw"
    path.write_bytes(bytes(627200 * 2 + 10))
    _raises_format(path, "not a whole number", preset="c7942-4x4")
    path.write_bytes(bytes(1000))
    _raises_format(path, preset="c7942")


@pytest.mark.parametrize(
    "dtype, values",
    [
        ("<u2", [0, 1, 4095, 65535]),
        ("<u4", [0, 1, 2**32 - 1, 7]),
        ("<f4", [0.5, -1.0, 1e30, 3.0]),
        ("<i2", [-32768, 0, 32767, 5]),
        ("u1", [0, 255, 128, 1]),
    ],
)
def test_raw_explicit_shape_and_dtype(tmp_path, dtype, values):
    data = np.resize(np.array(values, dtype=dtype), (3, 4, 6))
    path = tmp_path / "custom.bin"
    data.tofile(path)
    f = read(path, shape=(4, 6), dtype=dtype)
    assert f.meta["preset"] == "custom"
    assert f.n == 3
    assert f.data.dtype == np.dtype(dtype).newbyteorder("=")
    np.testing.assert_array_equal(f.data, data)
    g = read(path, shape=(3, 4, 6), dtype=dtype)
    np.testing.assert_array_equal(g.data, data)


@pytest.mark.parametrize("byteorder", [">", "big"])
def test_raw_big_endian(tmp_path, byteorder):
    data = _rand12((560, 560), seed=8)
    path = tmp_path / "be.raw"
    data.astype(">u2").tofile(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BitDepthWarning)
        f = read(path, byteorder=byteorder)
    assert f.meta["preset"] == "c7942-4x4"
    assert f.data.dtype.isnative
    np.testing.assert_array_equal(f.data[0], data)
    g = read(path, shape=(560, 560), dtype="u2", byteorder=byteorder)
    np.testing.assert_array_equal(g.data[0], data)


def test_raw_offset_skips_junk_header(tmp_path):
    data = _rand12((560, 560), seed=9)
    path = tmp_path / "junk.raw"
    path.write_bytes(b"J" * 100 + data.astype("<u2").tobytes())
    _raises_format(path, "matches no")  # without the offset the size fits nothing
    f = read(path, offset=100)
    assert f.meta["preset"] == "c7942-4x4" and f.meta["offset"] == 100
    np.testing.assert_array_equal(f.data[0], data)
    g = read(path, offset=100, shape=(560, 560))
    np.testing.assert_array_equal(g.data[0], data)
    small = tmp_path / "small.raw"
    small.write_bytes(b"H" * 100 + np.arange(12, dtype="<u2").tobytes())
    np.testing.assert_array_equal(read(small, offset=100, shape=(3, 4)).data[0], np.arange(12).reshape(3, 4))


@pytest.mark.parametrize(
    "hints, fragment",
    [
        (dict(offset=-1), "negative"),
        (dict(offset=48), "beyond the end"),
        (dict(offset=100), "beyond the end"),
        (dict(offset=24), "matches no"),
        (dict(shape=(0, 3)), "shape="),
        (dict(shape=(1, 2, 3, 4)), "shape="),
        (dict(shape=(5, 4)), "not a whole number"),
        (dict(shape=(3, 4), n=3), "truncated"),
        (dict(shape=(9, 3, 4)), "truncated"),
        (dict(shape=(3, 4), n=0), "n="),
        (dict(shape=(3, 4), n=-1), "n="),
        (dict(shape=(3, 4), n=1.5), "n="),
        (dict(dtype="<u4"), "explicit shape"),
        (dict(dtype="not-a-dtype", shape=(3, 4)), "dtype"),
        (dict(byteorder="middle"), "byteorder"),
        (dict(preset="c9999"), "unknown preset"),
    ],
)
def test_raw_bad_hints(tmp_path, hints, fragment):
    path = tmp_path / "hints.raw"
    np.arange(24, dtype="<u2").tofile(path)  # 48 bytes: two (3, 4) frames
    _raises_format(path, fragment, **hints)


@pytest.mark.parametrize(("dtype", "byteorder"), [("<u2", ">"), ("<u2", "big"), (">f4", "<"), (">i2", "little")])
def test_raw_refuses_a_dtype_and_a_byteorder_that_contradict(tmp_path, dtype, byteorder):
    # `--dtype '<u2' --byteorder '>'` read big-endian without a word
    path = tmp_path / "hints.raw"
    np.arange(24, dtype="<u4").tofile(path)  # 96 bytes: (3, 4) frames of 2 or 4 bytes
    _raises_format(
        path,
        f"dtype={dtype!r}",
        f"byteorder={byteorder!r}",
        "contradict",
        shape=(3, 4),
        dtype=dtype,
        byteorder=byteorder,
    )


@pytest.mark.parametrize(
    ("dtype", "byteorder", "stored"),
    [(">u2", "big", ">u2"), ("u2", ">", ">u2"), ("<u2", "<", "<u2"), ("<u1", ">", "u1")],
)
def test_raw_takes_a_dtype_and_a_byteorder_that_agree(tmp_path, dtype, byteorder, stored):
    path = tmp_path / "hints.raw"
    data = np.arange(24, dtype=stored).reshape(2, 3, 4)
    data.tofile(path)
    np.testing.assert_array_equal(read(path, shape=(3, 4), dtype=dtype, byteorder=byteorder).data, data)


def test_raw_n_hint_reads_leading_frames(tmp_path):
    path = tmp_path / "hints.raw"
    data = np.arange(24, dtype="<u2").reshape(2, 3, 4)
    data.tofile(path)
    np.testing.assert_array_equal(read(path, shape=(3, 4), n=1).data, data[:1])


@pytest.mark.parametrize("dtype", ["O", "U1", "S2", "V4", "c8", "M8[s]"])
def test_raw_dtype_must_be_numbers(tmp_path, dtype):
    """Pixels are integers or real numbers: an object dtype would read the file's bytes as
    pointers (a crash), strings and complex numbers are no pixels."""
    path = tmp_path / "x.raw"
    np.zeros(400, "<u2").tofile(path)
    _raises_format(path, "dtype", shape=(5, 5), dtype=dtype)


def test_tiff_of_complex_pixels_is_refused(tmp_path):
    path = tmp_path / "complex.tif"
    tifffile.imwrite(path, np.ones((6, 7), np.complex64))
    _raises_format(path, "complex64")


def test_unknown_hint_and_format(tmp_path):
    path = tmp_path / "x.raw"
    np.zeros(10, "<u2").tofile(path)
    with pytest.raises(TypeError, match="unknown hints"):
        read(path, shapes=(2, 5))
    _raises_format(path, "format=", format="webp")
    _raises_format(path, "no JPEG signature", format="jpeg")  # (read since session 54)
    _raises_format(path, "no JPEG 2000 signature", format="jpeg2000")
    _raises_format(path, "no PNG signature", format="png")  # (read since session 53: a PNG, checked)


def test_geometry_hints_rejected_for_self_describing_formats(tmp_path):
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, np.zeros((4, 5), np.uint16))
    _raises_format(path, "raw files only", shape=(4, 5))
    img = tmp_path / "b.img"
    img.write_bytes(_itex_bytes(np.zeros((2, 2), np.uint16), 2))
    _raises_format(img, "raw files only", offset=64)


@needs_itex
def test_format_hint_forces_raw(tmp_path):
    # an ITEX-looking file read as raw on request
    path = tmp_path / "x.img"
    pix = np.arange(6, dtype=np.uint16).reshape(2, 3)
    path.write_bytes(_itex_bytes(pix, 2))
    f = read(path, format="raw", offset=64, shape=(2, 3))
    np.testing.assert_array_equal(f.data[0], pix)


def test_bit_depth_warning(tmp_path):
    data = _rand12((560, 560), seed=10)
    data[3, 4] = 5000
    path = tmp_path / "hot.raw"
    data.tofile(path)
    with pytest.warns(BitDepthWarning, match="5000") as rec:
        f = read(path)
    assert str(path) in str(rec[0].message)
    assert "12-bit" in str(rec[0].message)
    np.testing.assert_array_equal(f.data[0], data)  # data still returned unchanged


def test_bit_depth_warning_suggests_byteorder(tmp_path):
    data = _rand12((560, 560), seed=11)
    path = tmp_path / "swapped.raw"
    data.astype(">u2").tofile(path)
    with pytest.warns(BitDepthWarning, match="byteorder") as rec:
        f = read(path)
    assert "byte-swapped" in str(rec[0].message)
    np.testing.assert_array_equal(f.data[0], data.byteswap())


def test_bit_depth_warning_msb_aligned(tmp_path):
    data = _rand12((560, 560), seed=12)
    data[0, 0] = 4095
    path = tmp_path / "shifted.raw"
    (data << 4).astype("<u2").tofile(path)
    with pytest.warns(BitDepthWarning, match="shifted left by 4") as rec:
        read(path)
    assert "low 4 bits are 0" in str(rec[0].message) and "divide by 16" in str(rec[0].message)


def test_bit_depth_warning_gives_no_msb_advice_without_evidence(tmp_path):
    """Found by an outside test: every uint16 frame above 4095 that byte swapping did not fix was
    "shifted left by 4 bits (MSB-aligned)", since max >> 4 <= 4095 holds for any 16-bit value;
    a user of a 14-bit panel would divide good counts by 16. MSB alignment needs its evidence,
    the low 4 bits 0 in (nearly) every pixel; 9001 (and 14-bit noise) has them set."""
    rng = np.random.default_rng(14)
    for name, data in (
        ("const", np.full((560, 560), 9001, "<u2")),
        ("noisy", rng.integers(4096, 16384, (560, 560)).astype("<u2")),
    ):
        path = tmp_path / f"fourteen_{name}.raw"
        data.tofile(path)
        with pytest.warns(BitDepthWarning, match="14-bit") as rec:
            f = read(path)
        message = str(rec[0].message)
        assert "shifted" not in message and "MSB" not in message and "divide" not in message, message
        assert "byteorder" not in message, message
        np.testing.assert_array_equal(f.data[0], data)


def test_bit_depth_warning_names_float32_words(tmp_path):
    """A float32 frame (transmission 0.2..1.1) in a headerless file read as 16-bit words: the
    warning says the words are float32 numbers and how to read them, not "MSB-aligned" (the
    words of 0.5 have their low 4 bits 0) nor "big-endian" (swapped, they are 0 and 63)."""
    rng = np.random.default_rng(32)
    for name, values in (("ramp", rng.uniform(0.2, 1.1, (560, 280))), ("exact", np.full((560, 280), 0.5))):
        path = tmp_path / f"{name}.raw"
        values.astype("<f4").tofile(path)  # 560 x 280 float32: the bytes of one 560 x 560 frame
        with pytest.warns(BitDepthWarning, match="float32") as rec:
            read(path)
        message = str(rec[0].message)
        assert "dtype='<f4'" in message and "MSB" not in message and "byteorder" not in message, message
        f = read(path, shape=(560, 280), dtype="<f4")
        np.testing.assert_array_equal(f.data[0], values.astype("<f4"))


def test_no_bit_depth_warning_at_4095(tmp_path):
    path = tmp_path / "full.raw"
    np.full((560, 560), 4095, "<u2").tofile(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = read(path)
    assert f.data.max() == 4095


def test_no_bit_depth_warning_with_explicit_shape(tmp_path):
    # a custom geometry is not a C7942 frame: no 12-bit promise
    path = tmp_path / "other.raw"
    np.full((4, 4), 60000, "<u2").tofile(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read(path, shape=(4, 4)).data.max() == 60000


def test_raw_file_starting_with_magic_bytes_is_raw_by_extension(tmp_path):
    data = _rand12((560, 560), seed=13)
    data[0, 0] = int.from_bytes(b"IM", "little")  # 19785: the frame starts with b"IM"
    path = tmp_path / "im.raw"
    data.tofile(path)
    assert sniff(path) == "raw"
    with pytest.warns(BitDepthWarning):
        f = read(path)
    np.testing.assert_array_equal(f.data[0], data)


# ------------------------------------------------------------------------------------------------
# 4. TIFF
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8, np.float32, np.uint32])
def test_tiff_single_page(tmp_path, dtype):
    data = (np.random.default_rng(3).random((13, 17)) * 200).astype(dtype)
    path = tmp_path / "one.tif"
    tifffile.imwrite(path, data)
    f = read(path)
    assert f.meta["format"] == "tiff"
    assert f.shape == (1, 13, 17)
    assert f.data.dtype == dtype
    np.testing.assert_array_equal(f.data[0], data)
    assert (f.meta["rows"], f.meta["cols"], f.meta["n"]) == (13, 17, 1)


@pytest.mark.parametrize("n", [2, 3, 4, 5])
@pytest.mark.parametrize("kw", [{}, {"bigtiff": True}, {"byteorder": ">"}, {"compression": "zlib"}])
def test_tiff_multi_page_tifffile(tmp_path, kw, n):
    # photometric="minisblack": without it tifffile stores a (3|4, rows, cols) array as one RGB(A) page
    data = _rand12((n, 9, 11), seed=14)
    path = tmp_path / "stack.tiff"
    tifffile.imwrite(path, data, photometric="minisblack", **kw)
    f = read(path)
    assert f.n == n
    assert f.data.dtype.isnative
    np.testing.assert_array_equal(f.data, data)
    g = read(path, n=2)
    assert g.n == 2 and g.meta["n"] == 2
    np.testing.assert_array_equal(g.data, data[:2])
    _raises_format(path, "n=", n=n + 1)


def test_tiff_pages_written_one_by_one(tmp_path):
    data = _rand12((3, 6, 5), seed=15)
    path = tmp_path / "pages.tif"
    with tifffile.TiffWriter(path) as tw:
        for frame in data:
            tw.write(frame, contiguous=False)
    f = read(path)
    assert f.n == 3
    np.testing.assert_array_equal(f.data, data)
    with open_frames(path) as src:
        np.testing.assert_array_equal(src[-1], data[2])


@pytest.mark.parametrize(
    "kw",
    [
        {"rowsperstrip": 3},
        {"rowsperstrip": 1},
        {"tile": (16, 16)},
        {"tile": (16, 32), "compression": "zlib"},
        {"compression": "zlib", "rowsperstrip": 7},
    ],
)
def test_tiff_strip_and_tile_layouts(tmp_path, kw):
    data = _rand12((2, 37, 50), seed=23)
    path = tmp_path / "layout.tif"
    tifffile.imwrite(path, data, photometric="minisblack", **kw)
    f = read(path)
    np.testing.assert_array_equal(f.data, data)


@pytest.mark.parametrize(
    "name, kw",
    [
        # OME-TIFF (Micro-Manager, Bio-Formats): tifffile lists pages after the first as TiffFrames
        ("stack.ome.tif", {"metadata": {"axes": "ZYX"}}),
        ("tiled.ome.tif", {"metadata": {"axes": "ZYX"}, "tile": (16, 16)}),
        ("hyper.tif", {"imagej": True, "metadata": {"axes": "ZYX"}}),
    ],
)
def test_tiff_ome_and_imagej_stacks_read_every_page(tmp_path, name, kw):
    data = _rand12((3, 37, 50), seed=29)
    path = tmp_path / name
    tifffile.imwrite(path, data, photometric="minisblack", **kw)
    np.testing.assert_array_equal(read(path).data, data)
    with open_frames(path) as src:
        np.testing.assert_array_equal(src[2], data[2])


def test_tiff_pages_of_another_dtype_are_refused_not_cast(tmp_path):
    """A page of another SampleFormat/BitsPerSample is not a frame of the same stack: casting
    a float32 page into the first page's uint16 would silently truncate it."""
    path = tmp_path / "mixed.tif"
    with tifffile.TiffWriter(path) as tif:
        tif.write(np.zeros((6, 7), np.uint16), photometric="minisblack")
        tif.write(np.full((6, 7), 0.5, np.float32), photometric="minisblack")
    _raises_format(path, "float32")


def _imagej_one_ifd(path, data, byteorder):
    """An ImageJ stack as ImageJ writes one over 4 GB: the first IFD only (its next-IFD offset
    0), ``images=N`` in its description, and all N frames stored contiguously after it."""
    tifffile.imwrite(path, data, imagej=True, byteorder=byteorder)
    raw = bytearray(path.read_bytes())
    ifd = struct.unpack_from(byteorder + "I", raw, 4)[0]
    count = struct.unpack_from(byteorder + "H", raw, ifd)[0]
    struct.pack_into(byteorder + "I", raw, ifd + 2 + 12 * count, 0)
    path.write_bytes(bytes(raw))
    return path


@pytest.mark.parametrize("byteorder", [">", "<"])  # ImageJ itself writes big-endian
def test_tiff_imagej_stack_with_one_ifd_reads_every_frame(tmp_path, byteorder):
    """Past 4 GB (428 frames of 2240 x 2240 uint16) ImageJ writes one IFD and says ``images=N``:
    reading only the first page would silently drop every frame after it."""
    data = _rand12((4, 20, 30), seed=31)
    path = _imagej_one_ifd(tmp_path / "big.tif", data, byteorder)
    np.testing.assert_array_equal(read(path).data, data)
    with open_frames(path) as src:
        assert len(src) == 4
        np.testing.assert_array_equal(src[3], data[3])
    np.testing.assert_array_equal(read(path, n=2).data, data[:2])
    # a description promising more frames than the file holds is a truncated file, not 4 frames
    path.write_bytes(path.read_bytes().replace(b"images=4", b"images=9"))
    _raises_format(path, "images=9", "truncated")


def test_tiff_written_truncated_by_tifffile_reads_every_frame(tmp_path):
    """tifffile's ``truncate=True`` writes a contiguous stack with its first IFD only and
    ``{"shape": [n, rows, cols], "truncated": true}`` in the description; tifffile reads n frames."""
    data = _rand12((4, 20, 30), seed=47)
    path = tmp_path / "truncated.tif"
    tifffile.imwrite(path, data, truncate=True, photometric="minisblack")
    with tifffile.TiffFile(path) as tif:
        assert len(tif.pages) == 1
    np.testing.assert_array_equal(read(path).data, data)
    path.write_bytes(path.read_bytes().replace(b'"shape": [4,', b'"shape": [9,'))  # promises more
    _raises_format(path, "truncated")


def _tiff_12bit_packed(path, image):
    """A one-strip TIFF of BitsPerSample 12 (TIFF 6.0: samples packed MSB first, FillOrder 1,
    each row padded to a whole byte), as 12-bit camera software writes it."""
    rows, cols = image.shape
    bits = ((image[..., None] >> np.arange(11, -1, -1)) & 1).astype(np.uint8).reshape(rows, cols * 12)
    data = np.packbits(bits, axis=1).tobytes()  # packbits pads each row to a byte
    tags = [(256, cols), (257, rows), (258, 12), (259, 1), (262, 1), (273, 0), (277, 1), (278, rows), (279, len(data))]
    data_offset = 8 + 2 + 12 * len(tags) + 4
    out = b"II*\0" + struct.pack("<IH", 8, len(tags))
    for code, value in tags:
        out += struct.pack("<HHII", code, 4, 1, data_offset if code == 273 else value)
    path.write_bytes(out + struct.pack("<I", 0) + data)
    return path


def test_tiff_lzw_and_12bit_packed_read(tmp_path):
    """LZW (Pillow, GIMP, Photoshop, many acquisition programs) and 12-bit packed samples (a
    12-bit detector's own TIFF) are ordinary TIFF; tifffile decodes both through imagecodecs."""
    from PIL import Image

    data = _rand12((9, 11), seed=37)
    Image.fromarray(data).save(tmp_path / "lzw.tif", compression="tiff_lzw")
    with tifffile.TiffFile(tmp_path / "lzw.tif") as tif:
        assert tif.pages.first.compression == 5  # LZW
    np.testing.assert_array_equal(read(tmp_path / "lzw.tif").data[0], data)
    np.testing.assert_array_equal(read(_tiff_12bit_packed(tmp_path / "p12.tif", data)).data[0], data)


@pytest.mark.parametrize("where", ["first", "last"])
@pytest.mark.parametrize("preview", [(4, 5), (12, 10)], ids=["smaller", "same_shape"])
def test_tiff_reduced_resolution_pages_are_not_frames(tmp_path, where, preview):
    """NewSubfileType bit 0 (TIFF 6.0, section 8) marks a reduced-resolution version of another
    image: a preview, first or last, of any shape, is never a frame of the stack."""
    data = _rand12((2, 12, 10), seed=41)
    path = tmp_path / "preview.tif"
    with tifffile.TiffWriter(path) as tif:
        if where == "first":
            tif.write(np.zeros(preview, np.uint8), subfiletype=1)
        for frame in data:
            tif.write(frame, photometric="minisblack")
        if where == "last":
            tif.write(np.zeros(preview, np.uint8), subfiletype=1)
    np.testing.assert_array_equal(read(path).data, data)


def test_tiff_image_codec_declaring_its_own_size_is_refused_before_decoding(tmp_path):
    """A JPEG strip declares its own height and width (its SOF marker, ITU T.81 B.2.2), which the
    decoder allocates whatever the TIFF page says: a 2 KB file whose SOF claims 60000 x 60000
    made the reader allocate 3.6 GB. Image codecs are refused before any decoding."""
    path = tmp_path / "jpeg.tif"
    tifffile.imwrite(path, np.zeros((64, 48), np.uint8), compression="jpeg")
    raw = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:
        start = tif.pages.first.dataoffsets[0]
    sof = raw.index(b"\xff\xc0", start)
    struct.pack_into(">HH", raw, sof + 5, 60000, 60000)  # Y (lines), X (samples per line)
    path.write_bytes(bytes(raw))
    _raises_format(path, "JPEG")
    # lossless codecs whose output the page's size bounds still read
    data = _rand12((2, 9, 11), seed=43)
    for compression in ("lzw", "zstd", "lzma", "packbits", "zlib"):
        tifffile.imwrite(tmp_path / "ok.tif", data, compression=compression, photometric="minisblack")
        np.testing.assert_array_equal(read(tmp_path / "ok.tif").data, data)


def test_tiff_description_nested_past_the_recursion_limit_stays_text(tmp_path):
    """The ImageDescription is free text (TIFF 6.0): JSON too deep for Python's parser is kept as
    text, as HDF5 attributes are, never a reason to refuse the pixels."""
    path = tmp_path / "deep.tif"
    text = '{"a":' + "[" * 100_000 + "]" * 100_000 + "}"
    tifffile.imwrite(path, np.ones((4, 5), np.uint16), description=text, metadata=None)
    with pytest.warns(UserWarning, match=r"deep\.tif: its ImageDescription's JSON nests deeper than 32 levels"):
        f = read(path)
    assert f.data.shape == (1, 4, 5) and f.meta["tags"]["ImageDescription"] == text
    assert "description" not in f.meta


def _patch_tiff_tag(data: bytes, code: int, value: int) -> bytes:
    """Overwrite a LONG tag's value in the first IFD of a little-endian classic TIFF."""
    out = bytearray(data)
    ifd = struct.unpack_from("<I", out, 4)[0]
    for k in range(struct.unpack_from("<H", out, ifd)[0]):
        entry = ifd + 2 + 12 * k
        tag, kind, _count, _value = struct.unpack_from("<HHII", out, entry)
        if tag == code:
            assert kind == 4
            struct.pack_into("<I", out, entry + 8, value)
            return bytes(out)
    raise AssertionError(f"no tag {code}")


@pytest.mark.parametrize("compression", [None, "zlib"])
@pytest.mark.parametrize("tag, value", [(257, 1_000_000_000), (256, 500_000_000), (257, 8_000_005)])
def test_tiff_corrupt_dimensions_fail_fast(tmp_path, compression, tag, value):
    """A corrupt ImageLength/ImageWidth must not make the reader allocate and fill gigabytes."""
    path = tmp_path / "dims.tif"
    tifffile.imwrite(path, _rand12((5, 6), seed=24), compression=compression)
    path.write_bytes(_patch_tiff_tag(path.read_bytes(), tag, value))
    t0 = time.monotonic()
    _raises_format(path)
    assert time.monotonic() - t0 < 2


@pytest.mark.parametrize("compression", [None, "zlib"])
@pytest.mark.parametrize("tag", [256, 257])
def test_tiff_of_zero_width_or_height_says_so(tmp_path, compression, tag):
    """ImageWidth or ImageLength 0: a page with no pixels, said so, not "integer division or modulo by zero"."""
    path = tmp_path / "empty page.tif"
    tifffile.imwrite(path, _rand12((5, 6), seed=24), compression=compression)
    path.write_bytes(_patch_tiff_tag(path.read_bytes(), tag, 0))
    _raises_format(path, "no pixels")


def test_write_tiff_round_trip_with_meta(tmp_path):
    data = _rand12((3, 8, 10), seed=16)
    meta = {"step": 2, "ratio": 0.15, "nested": {"kv": 40.0, "names": ["a", "b"]}}
    path = write_tiff(tmp_path / "rk.tif", data, meta=meta)
    assert path == tmp_path / "rk.tif"
    f = read(path)
    assert f.n == 3
    np.testing.assert_array_equal(f.data, data)
    assert f.meta["description"] == meta
    assert json.loads(f.meta["tags"]["ImageDescription"]) == meta


def test_write_tiff_single_frame_float(tmp_path):
    data = np.random.default_rng(17).normal(size=(7, 5)).astype(np.float32)
    path = write_tiff(tmp_path / "one.tif", data)
    f = read(path)
    assert f.shape == (1, 7, 5) and f.data.dtype == np.float32
    np.testing.assert_array_equal(f.data[0], data)
    assert "description" not in f.meta
    with pytest.raises(ValueError):
        write_tiff(tmp_path / "bad.tif", np.zeros((2, 2, 2, 2)))


@pytest.mark.parametrize(
    "shape, kw",
    [
        ((8, 9, 3), {"photometric": "rgb"}),
        ((3, 8, 9), {"photometric": "rgb", "planarconfig": "separate"}),
        ((8, 9, 4), {"photometric": "rgb", "extrasamples": ["unassalpha"]}),
    ],
)
def test_tiff_rgb_rejected(tmp_path, shape, kw):
    path = tmp_path / "rgb.tif"
    tifffile.imwrite(path, np.zeros(shape, np.uint8), **kw)
    _raises_format(path, "greyscale")


@pytest.mark.parametrize("n", [3, 4])
def test_tiff_of_three_or_four_frames_written_as_colour_planes_says_how(tmp_path, n):
    """tifffile.imwrite stores a (3 or 4, rows, cols) array as RGB(A) planes of one page unless
    told photometric='minisblack' (it warns so): the file is colour, and the one line says why."""
    path = tmp_path / "three.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        tifffile.imwrite(path, np.zeros((n, 6, 7), np.uint16))
    _raises_format(path, "greyscale", "photometric='minisblack'")


@pytest.mark.parametrize("n", [2, 4, 5])
def test_tiff_of_frames_written_as_grey_samples_of_one_page_says_so(tmp_path, n):
    """Found by trying other labs' files: frames written as the planes of one greyscale page
    (tifffile.imwrite with planarconfig='separate', photometric='minisblack') were called "one
    colour image ... unless given photometric='minisblack'", advice the file already followed."""
    path = tmp_path / "planes.tif"
    tifffile.imwrite(path, np.zeros((n, 6, 7), np.uint16), photometric="minisblack", planarconfig="separate")
    with pytest.raises(FormatError, match=f"one greyscale page of {n} samples per pixel") as info:
        read(path)
    assert "unless given photometric='minisblack'" not in str(info.value)


def test_tiff_truncated_at_page_boundary(tmp_path):
    """A multi-page TIFF cut right after a page must not read as a shorter stack."""
    data = _rand12((3, 6, 7), seed=18)
    path = write_tiff(tmp_path / "cut.tif", data, meta={"a": 1})
    whole = path.read_bytes()
    with tifffile.TiffFile(path) as tif:
        ends = [max(o + c for o, c in zip(p.dataoffsets, p.databytecounts)) for p in tif.pages]
    for end in ends[:-1]:
        path.write_bytes(whole[:end])
        _raises_format(path)


def test_tiff_with_wrong_magic(tmp_path):
    path = tmp_path / "fake.tif"
    path.write_bytes(b"GIF89a" + bytes(100))
    _raises_format(path, "magic")


# ------------------------------------------------------------------------------------------------
# 5. The experiment HDF5
# ------------------------------------------------------------------------------------------------

EXP_SHAPE = (6, 5)


def _frame(i, shape=EXP_SHAPE):
    return ((np.arange(shape[0] * shape[1]).reshape(shape) * 7 + i * 101) % 4096).astype(np.uint16)


FRAME_META = [  # image_key, step, ratio, gap_mm, voltage_kv, current_ua
    (ImageKey.DARK, -1, None, None, None, None),
    (ImageKey.FLAT, -1, None, None, 40.0, 100.0),
    (ImageKey.PROJECTION, 0, 0.0, 10.0, 40.1, 99.5),
    (ImageKey.PROJECTION, 1, 0.075, 9.25, 39.9, 100.2),
    (ImageKey.PROJECTION, 2, 0.15, 8.5, 40.0, 100.0),
    (ImageKey.INVALID, 3, 0.2, 8.0, 40.0, 100.0),
]


def _write_experiment(path, rows=FRAME_META, start=0, **kw):
    with ExperimentWriter(path, **kw) as w:
        for j, (key, step, ratio, gap, kv, ua) in enumerate(rows):
            i = w.append(
                _frame(start + j),
                image_key=key,
                step=step,
                ratio=ratio,
                gap_mm=gap,
                voltage_kv=kv,
                current_ua=ua,
                time_s=1000.0 + start + j,
            )
            assert i == start + j
            assert w.n_frames == start + j + 1
    return path


def _nan(v):
    return np.nan if v is None else v


def _check_meta(meta, rows):
    np.testing.assert_array_equal(meta["image_key"], [r[0] for r in rows])
    assert meta["image_key"].dtype == np.int8
    np.testing.assert_array_equal(meta["step"], [r[1] for r in rows])
    assert meta["step"].dtype == np.int16
    np.testing.assert_array_equal(meta["ratio"], [_nan(r[2]) for r in rows])
    np.testing.assert_allclose(meta["gap"], [_nan(r[3]) if r[3] is None else r[3] * 1e-3 for r in rows], rtol=1e-12)
    np.testing.assert_array_equal(meta["voltage"], [_nan(r[4]) for r in rows])
    np.testing.assert_array_equal(meta["current"], [_nan(r[5]) for r in rows])
    np.testing.assert_array_equal(meta["time"], 1000.0 + np.arange(len(rows)))


def test_experiment_write_read(tmp_path):
    path = _write_experiment(
        tmp_path / "exp.h5",
        shape=EXP_SHAPE,
        pixel_size_mm=0.1,
        source={"name": "L8121-01", "voltage_kv": 40, "current_ua": 100},
    )
    f = read(path)
    assert f.meta["format"] == "experiment"
    assert f.n == len(FRAME_META)
    assert f.data.dtype == np.uint16
    np.testing.assert_array_equal(f.data, np.stack([_frame(i) for i in range(len(FRAME_META))]))
    _check_meta(f.meta, FRAME_META)
    assert f.meta["pixel_size_mm"] == pytest.approx(0.1)
    assert f.meta["x_pixel_size"] == pytest.approx(1e-4)
    np.testing.assert_array_equal(f.meta["pixel_mask"], np.zeros(EXP_SHAPE, np.uint32))
    assert f.meta["source"]["name"] == "L8121-01"
    assert f.meta["source"]["type"] == "Fixed Tube X-ray"
    assert f.meta["source"]["voltage"] == 40.0 and f.meta["source"]["current"] == 100.0
    assert "simulated" not in f.meta
    assert sniff(path) == "hdf5"
    # n= keeps the first frames and their bookkeeping together
    g = read(path, n=3)
    assert g.n == 3 and g.meta["n"] == 3
    np.testing.assert_array_equal(g.data, f.data[:3])
    _check_meta(g.meta, FRAME_META[:3])
    _raises_format(path, "n=", n=len(FRAME_META) + 1)
    # the NeXus layout
    with h5py.File(path, "r") as h5:
        det = h5["entry/instrument/detector/data"]
        assert det.chunks == (1,) + EXP_SHAPE
        assert h5["entry"].attrs["NX_class"] == "NXentry"
        assert h5["entry"].attrs["frames_complete"] == len(FRAME_META)
        np.testing.assert_array_equal(h5["entry/data/data"][()], f.data)
        assert h5["entry/sample/compression/gap"].attrs["units"] == "m"


def test_experiment_lazy_and_empty(tmp_path):
    path = tmp_path / "empty.h5"
    ExperimentWriter(path, shape=EXP_SHAPE).close()
    f = read(path)
    assert f.n == 0 and f.shape == (0,) + EXP_SHAPE
    _write_experiment(path, shape=EXP_SHAPE, overwrite=True)
    with open_frames(path) as src:
        assert len(src) == len(FRAME_META)
        np.testing.assert_array_equal(src[3], _frame(3))


def test_experiment_append_mode(tmp_path):
    path = _write_experiment(tmp_path / "exp.h5", rows=FRAME_META[:3], shape=EXP_SHAPE)
    _write_experiment(path, rows=FRAME_META[3:], start=3, mode="a")
    f = read(path)
    assert f.n == len(FRAME_META)
    np.testing.assert_array_equal(f.data, np.stack([_frame(i) for i in range(len(FRAME_META))]))
    _check_meta(f.meta, FRAME_META)
    _write_experiment(path, rows=FRAME_META[:1], start=6, mode="a", shape=EXP_SHAPE)
    assert read(path).n == len(FRAME_META) + 1
    with pytest.raises(ValueError, match="frames are"):
        ExperimentWriter(path, shape=(5, 6), mode="a")


def test_experiment_refuses_to_overwrite(tmp_path):
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="never overwritten"):
        ExperimentWriter(path, shape=EXP_SHAPE)
    with pytest.raises(FileExistsError):
        ExperimentWriter(path, shape=EXP_SHAPE, mode="w")
    assert path.read_bytes() == before
    assert read(path).n == len(FRAME_META)
    with pytest.raises(FileNotFoundError):
        ExperimentWriter(tmp_path / "missing.h5", mode="a")
    with pytest.raises(ValueError, match="mode"):
        ExperimentWriter(tmp_path / "new.h5", shape=EXP_SHAPE, mode="x")
    with pytest.raises(ValueError, match="shape"):
        ExperimentWriter(tmp_path / "noshape.h5")


def test_experiment_append_validation(tmp_path):
    with ExperimentWriter(tmp_path / "v.h5", shape=EXP_SHAPE) as w:
        with pytest.raises(ValueError, match="shape"):
            w.append(np.zeros((5, 6), np.uint16), image_key=0)
        with pytest.raises(ValueError, match="image_key"):
            w.append(np.zeros(EXP_SHAPE, np.uint16), image_key=7)
        with pytest.raises(ValueError, match="uint16"):
            w.append(np.full(EXP_SHAPE, -1, np.int32), image_key=0)
        with pytest.raises(ValueError, match="uint16"):
            w.append(np.full(EXP_SHAPE, 0.5, np.float32), image_key=0)
        assert w.n_frames == 0
        w.append(np.full(EXP_SHAPE, 4000, np.int64), image_key=0)
        w.set_pixel_mask(np.eye(*EXP_SHAPE, dtype=np.uint32) * 8)
    f = read(tmp_path / "v.h5")
    assert f.n == 1 and f.data.dtype == np.uint16 and int(f.data.max()) == 4000
    np.testing.assert_array_equal(f.meta["pixel_mask"], np.eye(*EXP_SHAPE, dtype=np.uint32) * 8)


@pytest.mark.parametrize("ratio", [-0.15, 1.0, 15.0, float("inf")])
def test_experiment_append_refuses_a_compression_ratio_outside_0_to_1(ratio, tmp_path):
    """A finite element code's sign convention (-0.15 for 15 %) or a percentage (15) was written,
    and process then took the least compressed step for the reference. NaN, or none, is "not recorded"."""
    with ExperimentWriter(tmp_path / "v.h5", shape=EXP_SHAPE) as w:
        with pytest.raises(ValueError, match=r"v.h5: ratio=.*expected a compression ratio in \[0, 1\)"):
            w.append(np.zeros(EXP_SHAPE, np.uint16), image_key=0, step=1, ratio=ratio)
        assert w.n_frames == 0
        w.append(np.zeros(EXP_SHAPE, np.uint16), image_key=0, step=1, ratio=float("nan"))
        w.append(np.zeros(EXP_SHAPE, np.uint16), image_key=0, step=2, ratio=0.0)


def test_experiment_bit_depth_warning(tmp_path):
    path = tmp_path / "hot.h5"
    with ExperimentWriter(path, shape=EXP_SHAPE) as w:
        w.append(np.full(EXP_SHAPE, 4096, np.uint16), image_key=0)
    with pytest.warns(BitDepthWarning, match="4096"):
        read(path)


def test_experiment_partial_frame_dropped(tmp_path):
    """A crash after resizing but before the counter update leaves a partial frame: not read."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    n = len(FRAME_META)
    with h5py.File(path, "r+") as h5:
        ds = h5["entry/instrument/detector/data"]
        ds.resize(n + 1, axis=0)
        ds[n] = 999
        h5["entry/instrument/detector/image_key"].resize(n + 1, axis=0)
    f = read(path)
    assert f.n == n
    assert len(f.meta["image_key"]) == n
    with ExperimentWriter(path, mode="a") as w:
        assert w.n_frames == n
        w.append(_frame(n), image_key=0)
    g = read(path)
    assert g.n == n + 1
    np.testing.assert_array_equal(g.data[n], _frame(n))


def test_experiment_source_strings_are_fixed_length(tmp_path):
    """read() must not parse the global heap (libhdf5 hangs on some corrupt heaps): the strings
    it reads are stored inline."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE, source={"name": "Röntgen 50µA"})
    with h5py.File(path, "r") as h5:
        for key in ("name", "type", "probe"):
            info = h5py.check_string_dtype(h5[f"entry/instrument/source/{key}"].dtype)
            assert info is not None and info.length is not None, key
    assert read(path).meta["source"]["name"] == "Röntgen 50µA"


def test_experiment_odd_types_are_skipped_or_refused(tmp_path):
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    with h5py.File(path, "r+") as h5:
        src = h5["entry/instrument/source"]
        del src["type"]  # a corrupt byte once turned this string into a vlen sequence: segfault
        src.create_dataset("type", shape=(), dtype=h5py.vlen_dtype(np.uint8))
        src["array"] = np.arange(3)
    f = read(path)
    assert "type" not in f.meta["source"] and "array" not in f.meta["source"]
    assert f.meta["source"]["probe"] == "x-ray"
    with h5py.File(path, "r+") as h5:
        del h5["entry/sample/compression/step"]
        h5["entry/sample/compression/step"] = np.array([b"a"] * len(FRAME_META))
    _raises_format(path, "step", "expected numbers")
    with h5py.File(path, "r+") as h5:
        del h5["entry/sample/compression/step"]
        h5["entry/sample/compression/step"] = np.arange(2, dtype=np.int16)
    _raises_format(path, "step", "holds 2 values")
    with h5py.File(path, "r+") as h5:
        h5["entry"].attrs["frames_complete"] = -4
    _raises_format(path, "frames_complete", "expected a count of frames")  # as read_progress: no count


def test_hdf5_without_experiment_datasets(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as h5:
        h5["images"] = np.arange(60, dtype=np.uint16).reshape(3, 4, 5)
        h5["flat"] = np.ones((4, 5), np.float32)
        h5["line"] = np.arange(5)
        h5["words"] = np.array([[b"ab", b"cd"]])
        h5.create_group("grp")
    _raises_format(path, "/entry/instrument/detector/data", "dataset=")
    with pytest.raises(FormatError, match="not an experiment file"):
        ExperimentWriter(path, mode="a")
    f = read(path, dataset="images")
    assert f.meta["format"] == "hdf5" and f.meta["dataset"] == "images"
    np.testing.assert_array_equal(f.data, np.arange(60, dtype=np.uint16).reshape(3, 4, 5))
    g = read(path, dataset="/flat")
    assert g.shape == (1, 4, 5) and g.data.dtype == np.float32
    np.testing.assert_array_equal(g.data[0], np.ones((4, 5)))
    _raises_format(path, "no dataset", dataset="missing")
    _raises_format(path, "no dataset", dataset="grp")
    _raises_format(path, "dimensions", dataset="line")
    _raises_format(path, "expected numbers", dataset="words")


def test_hdf5_experiment_missing_image_key(tmp_path):
    """A file radiokit wrote (``@frames_complete``) without its keys or with 2-D frames is broken;
    the same frames without the marker are another program's NXdetector (tests/test_io_formats.py)."""
    path = tmp_path / "nokey.h5"
    with h5py.File(path, "w") as h5:
        h5["entry/instrument/detector/data"] = np.zeros((2, 3, 4), np.uint16)
        h5["entry"].attrs["frames_complete"] = 2
    _raises_format(path, "image_key")
    with h5py.File(path, "w") as h5:
        h5["entry/instrument/detector/data"] = np.zeros((3, 4), np.uint16)
        h5["entry/instrument/detector/image_key"] = np.zeros(3, np.int8)
    _raises_format(path, "(n, rows, cols)")


@pytest.mark.parametrize("dtype", [">u2", ">f4", ">i4"])
def test_hdf5_big_endian_frames_come_in_native_byte_order(tmp_path, dtype):
    """read() promises the file's dtype in native byte order, as the raw and TIFF readers give:
    HDF5 stores the byte order in the dataset's type, and h5py hands it through unless asked."""
    values = np.arange(60).reshape(3, 4, 5)
    path = tmp_path / "be.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("frames", data=values.astype(dtype))
    f = read(path, dataset="frames")
    assert f.data.dtype == np.dtype(dtype).newbyteorder("=")
    np.testing.assert_array_equal(f.data, values)
    with open_frames(path, dataset="frames") as src:
        assert src.dtype.isnative and src[1].dtype.isnative
        np.testing.assert_array_equal(src[1], values[1])


_READ_SUM = "import sys; from radiokit.io import read; print(int(read(sys.argv[1], dataset='d').data.sum()))"


@pytest.mark.parametrize("plugin", ["Zstd", "Bitshuffle", "LZ4"])
def test_hdf5_compressed_by_a_plugin_filter_reads_or_names_the_filter(tmp_path, plugin):
    """Detector and beamline software compress HDF5 with registered plugin filters (zstd,
    bitshuffle, LZ4): read them through hdf5plugin's filters where it is installed, and where
    no filter is at hand say which one is missing, not libhdf5's "can't open directory".
    Each read runs in a fresh interpreter: this one has hdf5plugin loaded to write the file."""
    hdf5plugin = pytest.importorskip("hdf5plugin")
    values = np.arange(3 * 40 * 50, dtype=np.uint16).reshape(3, 40, 50)
    path = tmp_path / "plugin.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("d", data=values, chunks=(1, 40, 50), **getattr(hdf5plugin, plugin)())
    env = {**os.environ, "HDF5_PLUGIN_PATH": str(tmp_path / "no-plugins-here")}
    res = subprocess.run([sys.executable, "-c", _READ_SUM, path], capture_output=True, text=True, env=env)
    assert res.returncode == 0, res.stderr
    assert int(res.stdout) == int(values.sum())
    without = "import sys; sys.modules['hdf5plugin'] = None; " + _READ_SUM  # as if it were not installed
    res = subprocess.run([sys.executable, "-c", without, path], capture_output=True, text=True, env=env)
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("radiokit.errors.FormatError") and str(path) in last, res.stderr
    with h5py.File(path) as h5:
        code = h5["d"].id.get_create_plist().get_filter(0)[0]
    assert f"filter {code}" in last and "hdf5plugin" in last, last


@pytest.mark.parametrize("shape", [(3, 0, 24), (0, 5), (2, 4, 0)])
def test_hdf5_frames_without_pixels_are_refused(tmp_path, shape):
    """A dataset of (n, 0, cols) frames has nothing to read: refused naming the file, rather than
    failing later in whatever first reduces a frame (min, mean) with numpy's words."""
    path = tmp_path / "nopixels.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("d", shape=shape, dtype=np.uint16)
    _raises_format(path, "no pixels", dataset="d")


def test_dataset_hint_on_non_hdf5(tmp_path):
    path = tmp_path / "x.raw"
    np.zeros(10, "<u2").tofile(path)
    _raises_format(path, dataset="/data")


def test_stackwriter_hdf5_read_back(tmp_path):
    data = np.random.default_rng(19).random((3, 4, 5)).astype(np.float32)
    with StackWriter(tmp_path / "out.h5", (4, 5), meta={"k": {"a": 1}}) as w:
        for i, frame in enumerate(data):
            w.append(frame, step=i)
    f = read(tmp_path / "out.h5", dataset="entry/data/data")
    np.testing.assert_array_equal(f.data, data)
    np.testing.assert_array_equal(read(tmp_path / "out.h5", dataset="entry/data/data", n=2).data, data[:2])
    _raises_format(tmp_path / "out.h5", "dimensions", dataset="entry/data/step")  # 1-D: not frames


@pytest.mark.parametrize("n_frames, bigtiff", [(300_000, True), (200_000, False), (None, False)])
def test_stackwriter_tiff_is_bigtiff_when_the_stack_will_pass_4_gib(tmp_path, monkeypatch, n_frames, bigtiff):
    """Classic TIFF offsets are 32-bit: a stack announced past 4 GiB must start as BigTIFF, or
    the page after the 4 GiB mark fails ("data too large for non-BigTIFF file") after hours
    of correction. 300 000 frames of 64 x 64 float32 are 4.9 GB, 200 000 are 3.3 GB."""
    import radiokit.io._atomic as atomic

    monkeypatch.setattr(atomic, "check_free_space", lambda path, nbytes: None)  # only one frame is written
    path = tmp_path / "stack.tif"
    with StackWriter(path, (64, 64), np.float32, n_frames=n_frames) as w:
        w.append(np.ones((64, 64), np.float32))
    with tifffile.TiffFile(path) as tif:
        assert tif.is_bigtiff == bigtiff
    np.testing.assert_array_equal(read(path).data, np.ones((1, 64, 64), np.float32))


@pytest.mark.parametrize("direct", [True, False], ids=["o_direct", "page_cache"])
def test_stackwriter_preallocated_direct_and_buffered_agree(tmp_path, monkeypatch, direct):
    """With n_frames known, frames (4 KiB multiples here) go straight to their chunks with
    O_DIRECT where the filesystem allows; the file must read back identically either way, and a
    writer closed early shrinks to the frames written."""
    if not direct:
        monkeypatch.setenv("RADIOKIT_NO_DIRECT_IO", "1")
    data = np.random.default_rng(23).random((3, 64, 32)).astype(np.float32)  # 8 KiB frames
    path = tmp_path / "pre.h5"
    with StackWriter(path, (64, 32), n_frames=5) as w:
        if not direct:
            assert not w._direct
        for i, frame in enumerate(data):
            w.append(frame, step=np.int32(i))
    f = read(path, dataset="entry/data/data")
    np.testing.assert_array_equal(f.data, data)
    with h5py.File(path) as h5:
        np.testing.assert_array_equal(h5["entry/data/step"][()], [0, 1, 2])


_CRASH_WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from radiokit.io import ExperimentWriter
    rows, cols = 48, 40
    base = np.arange(rows * cols, dtype=np.int64).reshape(rows, cols)
    w = ExperimentWriter(sys.argv[1], shape=(rows, cols))
    i = 0
    while True:
        w.append(((base * 3 + i * 17) % 4096).astype(np.uint16), image_key=i % 3, step=i,
                 ratio=i / 100, gap_mm=10 - i / 10, voltage_kv=40, current_ua=100, time_s=i)
        print(i, flush=True)
        i += 1
""")


def test_experiment_survives_sigkill(tmp_path):
    path = tmp_path / "crash.h5"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-c", _CRASH_WRITER, str(path)], stdout=subprocess.PIPE, text=True, env=env
    )
    last = -1
    watchdog = threading.Timer(60, proc.kill)  # never hang the suite on a stuck writer
    watchdog.start()
    try:
        for line in proc.stdout:
            last = int(line)
            if last >= 5:
                break
    finally:
        watchdog.cancel()
        proc.send_signal(signal.SIGKILL)  # kills it wherever it is, possibly mid-append
        proc.wait()
        proc.stdout.close()
    assert last >= 5, "the writer never reported five frames"
    assert proc.returncode == -signal.SIGKILL

    rows, cols = 48, 40
    base = np.arange(rows * cols, dtype=np.int64).reshape(rows, cols)
    f = read(path)
    # the frame in flight when killed, if its row was counted, is labelled INVALID (the writer's
    # contract: never pixels claimed complete); the writer labels the others 0, 1, 2
    n = f.n - 1 if f.meta["image_key"][-1] == ImageKey.INVALID else f.n
    assert n >= last + 1  # every frame reported complete is there
    for i in range(n):
        np.testing.assert_array_equal(f.data[i], (base * 3 + i * 17) % 4096)
    np.testing.assert_array_equal(f.meta["step"][:n], np.arange(n))
    np.testing.assert_array_equal(f.meta["image_key"][:n], np.arange(n) % 3)
    np.testing.assert_allclose(f.meta["gap"][:n], (10 - np.arange(n) / 10) * 1e-3)
    np.testing.assert_array_equal(f.meta["time"][:n], np.arange(n))

    with ExperimentWriter(path, mode="a") as w:
        assert w.n_frames == f.n
        w.append(np.full((rows, cols), 7, np.uint16), image_key=ImageKey.DARK)
        w.append(np.full((rows, cols), 8, np.uint16), image_key=ImageKey.FLAT)
    g = read(path)
    assert g.n == f.n + 2
    np.testing.assert_array_equal(g.data[: f.n], f.data)
    assert int(g.data[-2].max()) == 7 and int(g.data[-1].min()) == 8
    np.testing.assert_array_equal(g.meta["image_key"][-2:], [2, 1])


_KILL_BEFORE_PIXELS = textwrap.dedent("""
    import os, signal, sys
    import h5py
    import numpy as np
    from radiokit.io import ExperimentWriter
    path, mode, first, kill_at = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    write = h5py.Dataset.__setitem__
    def positioned(ds, key, value):
        # a real SIGKILL, placed where a crash leaves the writer's own incomplete state: frame
        # kill_at counted and labelled INVALID, its pixels never written (a random kill finds it
        # only now and then)
        if ds.name.endswith("/detector/data") and key == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        return write(ds, key, value)
    h5py.Dataset.__setitem__ = positioned
    w = ExperimentWriter(path, shape=(64, 64), mode=mode)  # 8 KiB: two unwritten frames pass one chunk and 4 KiB
    for i in range(first, first + 4):
        w.append(np.full((64, 64), 100 + i, np.uint16), image_key=i % 3, step=i)
    w.close()
""")


def test_experiment_killed_before_a_frames_pixels_and_resumed_twice_still_reads(tmp_path):
    """ExperimentWriter's contract for a crash between counting a frame and writing its pixels:
    the frame stays labelled INVALID, ``--resume`` appends after it. Its chunk is never written;
    readers skip it by its key. Two such crashes left two chunks unwritten, and the whole file
    was refused as "parts never written ... incomplete or corrupt" (one was already, by ``read``
    and ``info``, which read every frame): the frames labelled INVALID are allowed unwritten,
    read as the fill value, as before."""
    path = tmp_path / "resumed.h5"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    for mode, first, kill_at in (("w", 0, 2), ("a", 3, 5), ("a", 6, -1)):
        proc = subprocess.run(
            [sys.executable, "-c", _KILL_BEFORE_PIXELS, str(path), mode, str(first), str(kill_at)],
            env=env,
            timeout=120,
        )
        assert proc.returncode == (-signal.SIGKILL if kill_at >= 0 else 0)
    f = read(path)
    keys = f.meta["image_key"]
    np.testing.assert_array_equal(np.flatnonzero(keys == ImageKey.INVALID), [2, 5])
    steps = f.meta["step"]
    good = keys != ImageKey.INVALID
    np.testing.assert_array_equal(f.data[good][:, 0, 0], 100 + steps[good])
    np.testing.assert_array_equal(keys[good], steps[good] % 3)
    np.testing.assert_array_equal(f.data[~good], 0)  # the fill value, labelled invalid
    res = run_cli("info", path)  # samples every frame
    assert res.returncode == 0, res.stderr
    with h5py.File(path, "a") as h5:  # labelled a dark, the unwritten frame is refused, not read as zeros
        h5["entry/instrument/detector/image_key"][2] = ImageKey.DARK
    with pytest.raises(FormatError, match="frame 2 of /entry/instrument/detector/data was never written"):
        read(path)  # reads every frame


# ------------------------------------------------------------------------------------------------
# 6. Properties: truncated and random files raise FormatError and nothing else
# ------------------------------------------------------------------------------------------------


def _valid_raw_custom(path):
    np.arange(2 * 5 * 7, dtype="<u2").reshape(2, 5, 7).tofile(path)
    return dict(shape=(2, 5, 7))


def _valid_raw_custom_2d(path):
    np.arange(35, dtype="<u2").tofile(path)
    return dict(shape=(5, 7))


def _valid_raw_preset(path):
    _rand12((560, 560), seed=20).tofile(path)  # c7942-4x4, the smallest preset
    return {}


def _valid_itex(path):
    pix = np.arange(2 * 4 * 6, dtype=np.uint16).reshape(2, 4, 6)
    axis = np.arange(6, dtype="<f4")
    comment = b'[Camera],CameraName="Orca R2",Type=37[Scaling],ScalingXScalingFile="#0000,0006"'
    off = 64 + len(comment) + pix.nbytes
    comment = comment.replace(b"#0000", f"#{off:04d}".encode())
    path.write_bytes(_itex_bytes(pix, 2, comment, n_images=2, tail=axis.tobytes()))
    return {}


def _valid_itex_8bit(path):
    path.write_bytes(_itex_bytes(np.arange(30, dtype=np.uint8).reshape(5, 6), 0, b"[A],a=1"))
    return {}


def _valid_tiff(path):
    tifffile.imwrite(path, _rand12((3, 5, 6), seed=21), photometric="minisblack")
    return {}


def _valid_tiff_pages(path):
    write_tiff(path, _rand12((3, 5, 6), seed=22), meta={"k": 1})
    return {}


def _valid_hdf5(path):
    with ExperimentWriter(path, shape=(5, 6)) as w:
        for i in range(3):
            w.append(_frame(i, (5, 6)), image_key=0, step=i)
    return {}


VALID_MAKERS = {
    "raw-shape3d": (".raw", _valid_raw_custom),
    "raw-shape2d": (".raw", _valid_raw_custom_2d),
    "raw-preset": (".raw", _valid_raw_preset),
    "itex": (".img", _valid_itex),
    "itex-8bit": (".img", _valid_itex_8bit),
    "tiff": (".tif", _valid_tiff),
    "tiff-pages": (".tif", _valid_tiff_pages),
    "hdf5": (".h5", _valid_hdf5),
}


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid")
    out = {}
    for kind, (ext, make) in VALID_MAKERS.items():
        path = root / f"{kind}{ext}"
        hints = make(path)
        with warnings.catch_warnings():
            warnings.simplefilter("error", BitDepthWarning)
            read(path, **hints)  # valid as written
        out[kind] = (ext, path.read_bytes(), hints)
    return out


def _tiff_referenced_end(data: bytes) -> int:
    """The end of the last byte a little-endian classic TIFF refers to (IFDs, tag values, strips)."""
    sizes = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4}
    assert data[:4] == b"II*\x00"
    end, ifd = 8, struct.unpack_from("<I", data, 4)[0]
    while ifd:
        count = struct.unpack_from("<H", data, ifd)[0]
        end = max(end, ifd + 2 + 12 * count + 4)
        tags = {}
        for k in range(count):
            code, kind, n, value = struct.unpack_from("<HHII", data, ifd + 2 + 12 * k)
            nbytes = n * sizes[kind]
            if nbytes > 4:
                end = max(end, value + nbytes)
            tags[code] = value
        end = max(end, tags[273] + tags[279])  # one strip per page, as tifffile writes small pages
        ifd = struct.unpack_from("<I", data, ifd + 2 + 12 * count)[0]
    return end


@pytest.mark.parametrize("kind", sorted(VALID_MAKERS))
def test_truncation_raises_format_error(kind, valid_files, tmp_path_factory):
    ext, whole, hints = valid_files[kind]
    path = tmp_path_factory.mktemp("trunc") / f"cut{ext}"
    # tifffile leaves a few unreferenced padding bytes after the last IFD: cutting only those
    # leaves a complete TIFF, which must then read exactly as the whole file
    needed = _tiff_referenced_end(whole) if ext == ".tif" else len(whole)
    assert len(whole) - needed < 64

    path.write_bytes(whole)
    full = read(path, **hints)

    @PROPS
    @given(st.integers(min_value=0, max_value=len(whole) - 1))
    def check(length):
        path.write_bytes(whole[:length])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BitDepthWarning)
            if length >= needed:
                f = read(path, **hints)
                np.testing.assert_array_equal(f.data, full.data)
                return
            with pytest.raises(FormatError) as info:
                read(path, **hints)
        assert str(path) in str(info.value)

    check()


def test_truncation_of_every_length_small_tiff(valid_files, tmp_path):
    """Exhaustive for the page-by-page TIFF: every cut inside the referenced bytes is an error."""
    _, whole, _ = valid_files["tiff-pages"]
    needed = _tiff_referenced_end(whole)
    path = tmp_path / "cut.tif"
    for length in range(needed):
        path.write_bytes(whole[:length])
        with pytest.raises(FormatError):
            read(path)


@pytest.mark.parametrize("kind", ["itex", "itex-8bit", "tiff", "tiff-pages", "hdf5"])
def test_corrupted_bytes_raise_format_error_or_read(kind, valid_files, tmp_path_factory):
    """A valid file with a few bytes overwritten: FormatError or frames, never another exception.
    A refused file is that one error, no warning before it (a TIFF whose BitsPerSample byte was
    hit said "read as 16-bit words" of page 0, then refused the stack); one that reads may warn,
    naming the file (a BitsPerSample of 12 over 16-bit words is a writer's quirk it reads)."""
    ext, whole, hints = valid_files[kind]
    path = tmp_path_factory.mktemp("corrupt") / f"bad{ext}"

    @PROPS
    @given(st.lists(st.tuples(st.integers(0, len(whole) - 1), st.integers(0, 255)), min_size=1, max_size=4))
    def check(edits):
        data = bytearray(whole)
        for where, value in edits:
            data[where] = value
        path.write_bytes(bytes(data))
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            try:
                f = read(path, **hints)
            except FormatError as exc:
                assert str(path) in str(exc)
                assert [str(w.message) for w in said] == [], exc
            else:
                assert isinstance(f, Frames) and f.data.ndim == 3
                assert all(str(path) in str(w.message) for w in said), [str(w.message) for w in said]

    check()


PREFIXES = [b"", b"IM", b"II*\x00", b"MM\x00*", b"II+\x00", b"\x89HDF\r\n\x1a\n"]


@pytest.mark.parametrize("ext", [".raw", ".img", ".tif", ".h5", ""])
def test_random_bytes_raise_format_error_or_read(ext, tmp_path_factory):
    path = tmp_path_factory.mktemp("rand") / f"random{ext}"

    @PROPS
    @given(st.sampled_from(PREFIXES), st.binary(max_size=400))
    def check(prefix, body):
        path.write_bytes(prefix + body)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BitDepthWarning)
            try:
                f = read(path)
            except FormatError as exc:
                assert str(path) in str(exc)
            else:
                assert isinstance(f, Frames)
                assert f.data.ndim == 3

    check()


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("scratch")


@PROPS
@given(data=st.data())
def test_random_itex_headers(scratch, data):
    """Headers with random fields around a plausible body: FormatError or a consistent read."""
    path = scratch / "h.img"
    head = bytearray(64)
    head[0:2] = b"IM"
    struct.pack_into(
        "<hhhhhh", head, 2, *(data.draw(st.integers(-40, 300)) for _ in range(3)), 0, 0, data.draw(st.integers(-1, 4))
    )
    struct.pack_into("<i", head, 14, data.draw(st.integers(-2, 4)))
    body = data.draw(st.binary(max_size=600))
    path.write_bytes(bytes(head) + body)
    try:
        f = read(path)
    except FormatError:
        return
    rows, cols = f.data.shape[1:]
    need = 64 + f.meta["comment_length"] + f.data.nbytes
    assert need <= 64 + len(body)
    assert (f.meta["rows"], f.meta["cols"]) == (rows, cols)


# ------------------------------------------------------------------------------------------------
# 7. Empty, missing, directories
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".raw", ".img", ".tif", ".h5", ".bin", ""])
@pytest.mark.parametrize("fmt", [None, "raw", "tiff", "itex", "hdf5"])
def test_empty_file(tmp_path, ext, fmt):
    path = tmp_path / f"empty{ext}"
    path.write_bytes(b"")
    hints = {} if fmt is None else {"format": fmt}
    _raises_format(path, "empty", **hints)


@pytest.mark.parametrize("fmt", [None, "raw", "tiff", "itex", "hdf5"])
def test_directory(tmp_path, fmt):
    d = tmp_path / "frames.tif"
    d.mkdir()
    hints = {} if fmt is None else {"format": fmt}
    _raises_format(d, "directory", **hints)
    _raises_format(tmp_path, "directory", **hints)


@pytest.mark.parametrize("name", ["missing.raw", "missing.img", "missing.tif", "missing.h5", "missing"])
@pytest.mark.parametrize("fmt", [None, "raw", "hdf5"])
def test_missing_file(tmp_path, name, fmt):
    hints = {} if fmt is None else {"format": fmt}
    _raises_format(tmp_path / name, "no such file", **hints)
    with pytest.raises(FormatError):
        list(iter_frames(tmp_path / name, **hints))
    with pytest.raises(FormatError):
        open_frames(tmp_path / name, **hints)


def test_format_error_is_value_error():
    err = FormatError("/x/y.raw", "bad")
    assert isinstance(err, ValueError)
    assert err.path == "/x/y.raw" and err.problem == "bad"
    assert str(err) == "/x/y.raw: bad"


def test_read_follows_the_nexus_default_of_a_corrected_stack(tmp_path):
    """``read()`` opens radiokit's own outputs: a corrected stack is an NXentry/NXdata whose
    ``@signal`` names the frames, as silx would find them; a file that names none keeps the
    clear error."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files, correct_frames

    rng = np.random.default_rng(3)
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(32, 40)) as w:
        for _ in range(3):
            w.append(rng.integers(95, 105, (32, 40)).astype(np.uint16), image_key=ImageKey.DARK)
        for _ in range(3):
            w.append(rng.integers(2900, 3100, (32, 40)).astype(np.uint16), image_key=ImageKey.FLAT)
        for step in (1, 2):
            w.append(rng.integers(1000, 2000, (32, 40)).astype(np.uint16), image_key=ImageKey.PROJECTION, step=step)
    cal = Calibration.from_experiment(path)
    correct_files(path, cal, tmp_path / "corr.h5", progress=False)
    stack = read(tmp_path / "corr.h5")
    expected = correct_frames(cal, read(path).data[-2:], domain="log")
    assert stack.meta["dataset"] == "/entry/data/data"
    np.testing.assert_allclose(stack.data, expected, rtol=1e-6, atol=1e-6)
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["entry/data/data"] = np.zeros((2, 4, 4), np.float32)  # no NX_class, no @signal
    with pytest.raises(FormatError, match="not a radiokit experiment file"):
        read(tmp_path / "plain.h5")


def test_read_gives_a_calibration_as_its_dark_and_flat(tmp_path):
    """A calibration file opens with ``read()`` as two frames (dark, flat); one whose dark and flat
    differ in shape is a clear error naming the group, not a stack of mismatched frames."""
    from radiokit.calibrate import Calibration

    rng = np.random.default_rng(4)
    cal = Calibration.from_frames(
        rng.normal(100, 2, (5, 16, 24)).astype(np.uint16), rng.normal(3000, 30, (5, 16, 24)).astype(np.uint16)
    )
    cal.save(tmp_path / "cal.h5")
    f = read(tmp_path / "cal.h5")
    assert f.shape == (2, 16, 24) and f.meta["image_key"].tolist() == [ImageKey.DARK, ImageKey.FLAT]
    np.testing.assert_array_equal(f.data[1], cal.flat)
    with h5py.File(tmp_path / "cal.h5", "r+") as h5:
        del h5["calibration/flat"]
        h5["calibration/flat"] = np.ones((16, 25), np.float32)
    with pytest.raises(FormatError, match="dark .* and flat .* differ"):
        read(tmp_path / "cal.h5")


_OVERWRITE_KILLED = textwrap.dedent("""
    import sys
    import numpy as np
    from radiokit.io import ExperimentWriter
    w = ExperimentWriter(sys.argv[1], shape=(6, 5), overwrite=True)
    w.append(np.full((6, 5), 4000, np.uint16), image_key=2)
    print("ready", flush=True)
    sys.stdin.read()  # killed here, the new file half written
""")


def test_experiment_overwrite_through_a_symlink_killed_leaves_the_old_file(tmp_path):
    """``ExperimentWriter(link, overwrite=True)``: the new file is built beside the link's target
    and renamed over it at close, as every other radiokit output is (radiokit.io._atomic): a run
    killed part-way truncated the old file the link points at, its frames lost, and left a half
    file under its name."""
    store = tmp_path / "store"
    store.mkdir()
    target = _write_experiment(store / "exp.h5", shape=EXP_SHAPE)
    before = target.read_bytes()
    link = tmp_path / "exp.h5"
    link.symlink_to(target)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-c", _OVERWRITE_KILLED, str(link)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    watchdog = threading.Timer(60, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        watchdog.cancel()
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        proc.stdin.close()
    assert link.is_symlink() and link.resolve() == target
    assert target.read_bytes() == before  # the old file, whole
    assert read(link).n == len(FRAME_META)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5", "store"]  # nothing beside the link

    # completed, the new file replaces the target; the link stays a link
    with ExperimentWriter(link, shape=EXP_SHAPE, overwrite=True) as w:
        w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
    assert link.is_symlink() and link.resolve() == target
    assert read(target).n == 1 and int(read(link).data.max()) == 7
    assert [p.name for p in store.iterdir() if not p.name.startswith(".exp.tmp-")] == ["exp.h5"]


def test_experiment_overwrite_failing_inside_the_with_keeps_the_old_file(tmp_path):
    """An exception inside ``with ExperimentWriter(..., overwrite=True)`` is a run that did not
    finish: the old file stays and the partial new one is removed."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="stopped"):
        with ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True) as w:
            w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
            raise RuntimeError("stopped")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"]


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 6 MiB tmpfs (needs root: mount); None where mounting is not permitted."""
    with mounted_tmpfs(tmp_path / "disk", "6m") as mnt:
        yield mnt


def _with_free(monkeypatch, small_tmpfs, free):
    """Where no tmpfs can be mounted, the writer's free-space probe reports ``free`` bytes (the
    only way to fill a disk without privileges); on a real small disk nothing is faked."""
    if small_tmpfs is None:
        monkeypatch.setattr(ExperimentWriter, "_free_bytes", lambda self: free)


def _fill(path, n, value=1, **kw):
    with ExperimentWriter(path, shape=(256, 256), **kw) as w:
        for _ in range(n):
            w.append(np.full((256, 256), value, np.uint16), image_key=ImageKey.PROJECTION)


def test_experiment_overwrite_that_fills_the_disk_says_the_old_file_is_kept(small_tmpfs, tmp_path, monkeypatch):
    """Overwriting a 2.1 MB file with 3.9 MB free: the new file is built beside the old one, which
    stays until the new one is complete, so the disk fills part-way. The refusal said "the 14
    frame(s) before it are complete" and then removed them (the ``with`` ended in the error): it
    must say that the old file is kept unchanged, the new frames discarded, and why (room for both).
    On a real 6 MiB tmpfs where root can mount one; else the writer's free-space probe is faked
    to shrink as frames are written (ENOSPC cannot be caused for real without privileges)."""
    disk = small_tmpfs or tmp_path / "disk"
    path = disk / "exp.h5"
    _fill(path, 16, 1, overwrite=True, in_place=True)
    before = path.read_bytes()
    if small_tmpfs is None:  # 6 MiB less what the files in the folder take (old, new, reserve)
        monkeypatch.setattr(
            ExperimentWriter, "_free_bytes", lambda self: (6 << 20) - sum(p.stat().st_size for p in disk.iterdir())
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the warning at opening is another test's
        with pytest.raises(OSError, match="disk full") as err:
            _fill(path, 16, 2, overwrite=True)
    msg = str(err.value)
    assert "are complete" not in msg, msg
    assert re.search(r"old file .*kept unchanged", msg) and "discarded" in msg and "room for both" in msg, msg
    assert str(path) in msg
    assert path.read_bytes() == before and sorted(p.name for p in disk.iterdir()) == ["exp.h5"]


def test_experiment_overwrite_that_cannot_fit_warns_or_refuses_before_writing(small_tmpfs, tmp_path, monkeypatch):
    """The old file is not freed until the new one replaces it: with less free than the old
    file's size (and the reserve), a replacement as large will not fit, which is said at opening,
    naming both sizes; with no room for one frame the overwrite is refused before anything is
    written. Faked free space where no tmpfs can be mounted."""
    disk = small_tmpfs or tmp_path / "disk"
    path = disk / "exp.h5"
    _fill(path, 16, 1)
    before = path.read_bytes()
    _with_free(monkeypatch, small_tmpfs, (6 << 20) - len(before))
    with pytest.warns(UserWarning, match=r"old file .* not freed .*room for both") as rec:
        _fill(path, 2, 2, overwrite=True)
    assert str(path) in str(rec[0].message)
    assert read(path).n == 2
    # no room for even one frame: refused at opening, nothing beside the file
    blob = disk / "blob"
    if small_tmpfs is not None:
        blob.write_bytes(b"\0" * (shutil.disk_usage(disk).free - (512 << 10)))
    else:
        monkeypatch.setattr(ExperimentWriter, "_free_bytes", lambda self: 512 << 10)
    before = path.read_bytes()
    with pytest.raises(OSError, match=r"disk full.*old file .*kept unchanged") as err:
        ExperimentWriter(path, shape=(256, 256), overwrite=True)
    assert err.value.errno == errno.ENOSPC
    assert path.read_bytes() == before and sorted(p.name for p in disk.iterdir() if p != blob) == ["exp.h5"]


# A writer whose disk another program fills (the vendor software saving to the same disk), or
# that starts on a disk with only 4 KiB left: argv path, what. Each refusal is printed as one
# line, "refused ERRNO MESSAGE", and the writer is closed.
_ON_A_FILLED_DISK = textwrap.dedent("""
    import os, sys
    import numpy as np
    from radiokit.io import ExperimentWriter, ImageKey

    path, what = sys.argv[1], sys.argv[2]

    def fill(leave):
        with open(os.path.join(os.path.dirname(path), "filler"), "ab", buffering=0) as fh:
            try:
                while True:
                    fh.write(b"\\1" * 4096)
            except OSError:
                pass
            fh.truncate(max(0, fh.tell() - leave))

    def refused(exc):
        print("refused", exc.errno, str(exc).replace(chr(10), "<NL>"), flush=True)

    if what == "create":
        fill(4096)
        try:
            ExperimentWriter(path, shape=(256, 256)).close()
        except OSError as exc:
            refused(exc)
        sys.exit()
    w = ExperimentWriter(path, shape=(256, 256))
    for i in range(3):
        w.append(np.full((256, 256), 1000 + i, np.uint16), image_key=ImageKey.FLAT)
    fill(0)
    try:
        if what == "pixel_mask":
            w.set_pixel_mask(np.random.default_rng(0).integers(0, 2**32 - 1, (256, 256), dtype=np.uint32))
        elif what == "record_run":
            w.record_run(("x = 1" + chr(10)) * 20000, {"detector": "b" * 100000})
        elif what == "frame":
            w.append(np.ones((256, 256), np.uint16), image_key=ImageKey.FLAT)
    except OSError as exc:
        refused(exc)
    try:
        w.close()
    except OSError as exc:
        refused(exc)
""")


@pytest.mark.parametrize("what", ["create", "pixel_mask", "record_run", "frame", "close"])
def test_experiment_writer_on_a_disk_another_program_filled(what, tmp_path):
    """Found (session 35, then /tmp/s36h1): a full disk met inside libhdf5 outside a frame's own
    checks crashed the process (SIGSEGV: a new file begun with 4 KiB free; a pixel mask written
    after another program filled the disk) or left a file that no longer opened, every frame lost
    (closing, or recording the run, on a disk filled since the last frame: libhdf5's last metadata
    write failed half-way). Now every write is refused beforehand while the file is whole, and the
    room held for libhdf5 is given back before it closes the file: one line naming the file
    (ENOSPC), the frames taken intact, and a file begun on a full disk not left behind."""
    with mounted_tmpfs(tmp_path / "disk", "4m") as disk:
        if disk is None:
            pytest.skip("a full disk needs a tmpfs, and mounting one needs root")
        path = disk / "exp.h5"
        r = subprocess.run(
            [sys.executable, "-c", _ON_A_FILLED_DISK, str(path), what],
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "PYTHONWARNINGS": "ignore"},
        )
        assert r.returncode == 0, (r.returncode, r.stdout, r.stderr[-3000:])
        assert r.stderr == "", r.stderr[-3000:]
        lines = r.stdout.splitlines()
        assert all(
            ln.startswith(f"refused {errno.ENOSPC} ") and str(path) in ln and "<NL>" not in ln for ln in lines
        ), lines
        if what == "create":
            assert len(lines) == 1 and "disk full" in lines[0], lines
            assert sorted(p.name for p in disk.iterdir()) == ["filler"]  # no unreadable file left
            return
        assert len(lines) == (0 if what == "close" else 1), lines
        with h5py.File(path, "r") as h5:
            assert int(h5["entry"].attrs["frames_complete"]) == 3
            assert h5["entry/instrument/detector/image_key"][:3].tolist() == [ImageKey.FLAT] * 3
        f = read(path)
        assert f.n == 3 and [int(f.data[i].max()) for i in range(3)] == [1000, 1001, 1002]
        assert sorted(p.name for p in disk.iterdir()) == ["exp.h5", "filler"]  # the reserve is gone


_UNCLOSED = textwrap.dedent("""
    import sys
    import numpy as np
    from radiokit.io import ExperimentWriter
    w = ExperimentWriter(sys.argv[1], shape=(6, 5), overwrite=True, in_place=sys.argv[2] == "1")
    w.append(np.full((6, 5), 4000, np.uint16), image_key=2)
""")


@pytest.mark.parametrize("in_place", [False, True])
def test_experiment_overwrite_never_closed_warns_naming_both_files(in_place, tmp_path):
    """A script that overwrites without ``with`` and ends without ``close()``: built beside the
    old file, the new frames stayed in a hidden temporary and the old file under the name, with no
    word. It is not renamed into place (an unclosed writer may be a crash), but a warning names
    the old file kept and the temporary holding the new frames. In place, the frames are under
    the name: nothing to say. Either way the reserve held beside the file is removed."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    res = subprocess.run(
        [sys.executable, "-c", _UNCLOSED, str(path), str(int(in_place))],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    assert not (tmp_path / ".exp.h5.reserve").exists()  # the reserve's space given back
    if in_place:
        assert res.stderr == "" and read(path).n == 1
        return
    tmp = [p for p in tmp_path.iterdir() if p.name.startswith(".exp.tmp-")]
    assert path.read_bytes() == before and len(tmp) == 1
    assert "never closed" in res.stderr and str(path) in res.stderr and str(tmp[0]) in res.stderr, res.stderr


def test_experiment_overwrite_garbage_collected_unclosed_warns(tmp_path):
    """The same when the writer is dropped mid-script (garbage-collected) without ``close()``."""
    import gc

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    w = ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True)
    w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
    with pytest.warns(UserWarning, match="never closed") as rec:
        del w
        gc.collect()
    assert str(path) in str(rec[0].message) and ".exp.tmp-" in str(rec[0].message)
    assert read(path).n == len(FRAME_META)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # closed: no word
        with ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True) as w:
            w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
        del w
        gc.collect()
    # the warning's word on the orphan holds: this process's next overwrite leaves it (only a
    # dead process's temporaries are cleaned; review s35r5: it said the next overwrite removes it)
    orphans = [p.name for p in tmp_path.iterdir() if p.name.startswith(".exp.tmp-")]
    assert len(orphans) == 1 and "by a later process" in str(rec[0].message), (orphans, str(rec[0].message))


def _drop_file_mode_override():
    """Root writes into any folder (CAP_DAC_OVERRIDE): the child drops it from its bounding set,
    and its exec keeps it not, so a folder's mode stops it as any user (Linux prctl)."""
    if os.geteuid() == 0:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        for cap in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
            if libc.prctl(24, cap, 0, 0, 0):  # PR_CAPBSET_DROP
                raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def test_experiment_overwrite_in_a_read_only_folder_is_one_line_naming_the_file(tmp_path):
    """A writable file in a read-only folder: the new file cannot be built beside it to be renamed
    over it. The error was h5py's raw PermissionError naming the hidden temporary; it is one line
    naming the file asked for and why, and the file is untouched."""
    folder = tmp_path / "ro"
    folder.mkdir()
    path = _write_experiment(folder / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    code = textwrap.dedent("""
        import sys
        from radiokit.io import ExperimentWriter
        try:
            ExperimentWriter(sys.argv[1], shape=(6, 5), overwrite=True)
        except OSError as exc:
            print(type(exc).__name__, exc)
    """)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    folder.chmod(0o555)
    try:
        res = subprocess.run(
            [sys.executable, "-c", code, str(path)],
            capture_output=True,
            text=True,
            env=env,
            preexec_fn=_drop_file_mode_override,
            timeout=120,
        )
    finally:
        folder.chmod(0o755)
    out = res.stdout.strip()
    assert res.returncode == 0 and len(out.splitlines()) == 1, (res.stdout, res.stderr)
    assert out.startswith("OutputError ") and str(path) in out and ".tmp-" not in out, out
    assert "folder" in out and "not writable" in out and "in_place" in out, out
    assert path.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == ["exp.h5"]


# -- an in-place overwrite keeps the old file aside until its first frame ---------------------------


def _previous(folder):
    return sorted(p.name for p in folder.iterdir() if ".previous-" in p.name)


@pytest.mark.parametrize("how", ["closed", "an exception", "never closed"])
def test_experiment_in_place_overwrite_without_a_frame_puts_the_old_file_back(tmp_path, how):
    """``in_place=True`` truncated the old file as the writer opened: a writer closed (or dropped)
    before its first frame left an empty file where a series was. The old file is kept aside,
    hidden, and put back byte for byte; once a frame is on disk it is removed."""
    import gc

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    w = ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    assert w.previous is not None and _previous(tmp_path) == [w.previous.name]
    assert re.fullmatch(r"\.exp\.previous-.+-\d+-[0-9a-f]{8}\.h5", w.previous.name), w.previous.name
    if how == "closed":
        w.close()
    elif how == "an exception":
        with pytest.raises(RuntimeError), w:
            raise RuntimeError("the tube did not start")
    else:
        del w
        gc.collect()
    assert path.read_bytes() == before and _previous(tmp_path) == []
    with ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True) as w:
        w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
        assert w.previous is None and _previous(tmp_path) == []
    assert read(path).n == 1 and not w.restored_previous


def test_experiment_in_place_overwrite_refused_when_its_first_frame_cannot_fit_beside(tmp_path, monkeypatch):
    """Kept until the first frame, the old file takes its space until then: a disk without room
    for that frame beside it is refused at opening, the old file untouched."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    monkeypatch.setattr(ExperimentWriter, "_free_bytes", lambda self: 1000)
    with pytest.raises(OSError, match=r"disk full.*old file is unchanged") as err:
        ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    assert err.value.errno == errno.ENOSPC
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"]


def test_an_unclosed_in_place_writer_never_puts_the_old_file_back_over_its_own_frames(tmp_path, monkeypatch):
    """The old file kept aside outlives the first frame only if its removal failed; a writer then
    dropped unclosed must not rename it back over the frames it wrote. A removal that fails is a
    fault this test cannot cause as root (a read-only folder does not stop root), hence the fake."""
    import gc

    import radiokit.io._experiment as exp_mod

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    monkeypatch.setattr(exp_mod, "_remove", lambda p: (_ for _ in ()).throw(PermissionError(13, "fake")))
    w = ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    aside = w.previous
    with pytest.warns(UserWarning, match=r"previous series, kept in .*could not be removed.*rename it to keep it"):
        w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
    w._h5.flush()
    del w
    gc.collect()
    assert aside.exists() and aside.read_bytes() == before
    assert read(path).n == 1


@pytest.mark.parametrize("first", ["an overwrite", "a resume"])
def test_an_in_place_overwrite_of_a_file_another_writer_has_open_is_refused(tmp_path, first):
    """Found (review s36r2): the rename that keeps the old file aside got round libhdf5's lock, so
    a second --overwrite moved the first run's open file away and deleted it at its own first
    frame; both runs said "8 frames written", one run's frames were gone. It is refused, as the
    truncation that came before was ("already open")."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    n0 = read(path).n
    if first == "an overwrite":
        w1 = ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    else:
        w1 = ExperimentWriter(path, mode="a")
    with w1:
        w1.append(np.full(EXP_SHAPE, 5, np.uint16), image_key=ImageKey.DARK)
        with pytest.raises(OSError, match="open in another program") as err:
            ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
        assert err.value.errno == errno.EBUSY
        w1.append(np.full(EXP_SHAPE, 6, np.uint16), image_key=ImageKey.DARK)
    assert _previous(tmp_path) == []
    assert read(path).n == (2 if first == "an overwrite" else n0 + 2)
    np.testing.assert_array_equal(read(path).data[-1], np.full(EXP_SHAPE, 6, np.uint16))


def test_a_stop_as_the_old_file_is_set_aside_puts_it_back(tmp_path, monkeypatch, sigint_default):
    """Found (review s36r2): a Ctrl-C just after the rename (in the folder's fsync) left the old
    file hidden while the run said "holds the previous series, unchanged". The SIGINT is real;
    only its moment is chosen, by raising it from the rename, a moment no test can hit by timing."""
    import radiokit.io._experiment as exp_mod

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    real_rename = os.rename

    def rename_then_sigint(a, b):
        real_rename(a, b)
        signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(exp_mod.os, "rename", rename_then_sigint)
    with pytest.raises(KeyboardInterrupt):
        ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    monkeypatch.undo()
    assert path.read_bytes() == before and _previous(tmp_path) == []


def test_restore_previous_never_writes_over_a_file_a_run_is_writing(tmp_path):
    """Found (review s36r3): a free set-aside file (its run killed as its first frame was written)
    was put back over a run writing the name, which read_progress could not read (the run's lock)
    and so was taken to hold no frame: that run then said "8 frames written" into an unlinked file."""
    import socket

    from radiokit.io import restore_previous

    host = socket.gethostname().split(".")[0]
    path = tmp_path / "exp.h5"
    old = _write_experiment(tmp_path / "old.h5", shape=EXP_SHAPE)
    aside = tmp_path / f".exp.previous-{host}-{_dead_pid()}-{hashlib.sha256(b'exp.h5').hexdigest()[:8]}.h5"
    old.rename(aside)
    with ExperimentWriter(path, shape=EXP_SHAPE) as w:  # a run in its warm-up: no frame yet
        said = restore_previous(path)
        assert len(said) == 1 and said[0][0] is False and str(aside) in said[0][1], said
        w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
    assert read(path).n == 1 and aside.exists()


_UNLOCKED_HDF5 = """
import sys
import numpy as np
from radiokit.io import ExperimentWriter, ImageKey, read
path = sys.argv[1]
with ExperimentWriter(path, shape=(6, 5), overwrite=True, in_place=True) as w1:
    w1.append(np.full((6, 5), 5, np.uint16), image_key=ImageKey.DARK)
    try:
        ExperimentWriter(path, shape=(6, 5), overwrite=True, in_place=True)
        print("second: opened")
    except OSError as exc:
        print("second: refused", exc)
    w1.append(np.full((6, 5), 6, np.uint16), image_key=ImageKey.DARK)
print("frames", read(path).n)
"""


def test_an_in_place_overwrite_is_refused_while_a_writer_has_the_file_without_hdf5_locks(tmp_path):
    """Found (review s36r3): with HDF5_USE_FILE_LOCKING=FALSE (common on NFS lab machines) libhdf5
    locks nothing, and a second overwrite set the first run's file aside from under it: the first
    run's frames were lost. The writer then holds a lock of its own."""
    assert EXP_SHAPE == (6, 5)
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    env = dict(os.environ, HDF5_USE_FILE_LOCKING="FALSE")
    res = subprocess.run(
        [sys.executable, "-c", _UNLOCKED_HDF5, str(path)], capture_output=True, text=True, env=env, timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert "second: refused" in res.stdout and "open in another program" in res.stdout, res.stdout
    assert "frames 2" in res.stdout, res.stdout


def test_a_put_back_never_replaces_a_file_another_run_made_under_the_name(tmp_path):
    """Found (review s36r4, two processes each overwriting 300 times): a run whose opening failed
    after it had set the old file aside (the name taken meanwhile by another run's new file)
    renamed the old file over that run's file, whose frames then went into an unlinked file while
    it said "written". The other run's file is put under the name here by hand (the interleaving
    is a few milliseconds wide: no test can hit it by timing); the put-back keeps the old file
    aside, warns, and leaves the other file alone."""
    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    w = ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    aside = w.previous
    other = _write_experiment(tmp_path / "other.h5", rows=FRAME_META[:2], shape=EXP_SHAPE)
    theirs = other.read_bytes()
    other.rename(path)  # another run's file, under the name
    with pytest.warns(UserWarning, match=r"another program made a file under this name.*stays in"):
        w.close()
    assert path.read_bytes() == theirs and aside.read_bytes() == before and not w.restored_previous
    assert theirs != before and read(path).n == 2


def test_discard_unbegun_removes_only_a_file_nobody_holds(tmp_path):
    """The acquisition removes the file a failed opening left on a new name (it would block the
    next run); two runs started at once on one new name, the second's opening failed on the
    first's lock and its clean-up unlinked the file the first was writing. A held file stays."""
    from radiokit.io import discard_unbegun

    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=EXP_SHAPE) as w:
        discard_unbegun(path)
        assert path.exists()
        w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
    assert read(path).n == 1
    discard_unbegun(path)
    assert not path.exists()
    discard_unbegun(path)  # nothing there: nothing to do


def test_an_in_place_overwrite_never_truncates_a_file_another_run_made_meanwhile(tmp_path, monkeypatch):
    """Found (review s36r5): between setting the old file aside and opening the new one ("w",
    truncating), another run made the name its own and wrote 3 frames; the opening emptied that
    file, and the other run's series was lost though it said "closed OK". The opening only
    creates ("w-"). The other run is made at that moment by wrapping _set_aside, a moment no test
    can hit by timing."""
    import radiokit.io._experiment as exp_mod

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    others = []
    real = exp_mod.ExperimentWriter._set_aside

    def set_aside_then_another_run(self, frame_bytes):
        aside = real(self, frame_bytes)
        w = ExperimentWriter(path, shape=EXP_SHAPE)
        w.append(np.full(EXP_SHAPE, 5, np.uint16), image_key=ImageKey.DARK)
        others.append(w)
        return aside

    monkeypatch.setattr(exp_mod.ExperimentWriter, "_set_aside", set_aside_then_another_run)
    with pytest.warns(UserWarning, match="another program made a file under this name"):
        with pytest.raises(OSError) as err:
            ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    monkeypatch.undo()
    assert err.value.previous_kept_in.read_bytes() == before
    others[0].append(np.full(EXP_SHAPE, 6, np.uint16), image_key=ImageKey.DARK)
    others[0].close()
    assert read(path).n == 2


def test_an_in_place_overwrite_whose_new_file_is_moved_away_as_it_opens_is_refused(tmp_path, monkeypatch):
    """Found (review s36r5, HDF5_USE_FILE_LOCKING=FALSE): between libhdf5's opening and the
    writer's own lock, a second overwrite set the new file aside; the first run then wrote its
    frames into a file the second removed. The writer locks the file libhdf5 opened and checks the
    name still names it. The move is made at that moment by wrapping the check."""
    import radiokit.io._experiment as exp_mod

    path = _write_experiment(tmp_path / "exp.h5", shape=EXP_SHAPE)
    before = path.read_bytes()
    real = exp_mod._hold_what_was_opened

    def moved_first(h5, name):
        os.rename(name, tmp_path / "moved.h5")
        return real(h5, name)

    monkeypatch.setattr(exp_mod, "_hold_what_was_opened", moved_first)
    with pytest.raises(OSError, match="moved the new file away"):
        ExperimentWriter(path, shape=EXP_SHAPE, overwrite=True, in_place=True)
    # the name free again, the old series went back under it
    assert path.read_bytes() == before and _previous(tmp_path) == []


def _dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", ""])
    proc.wait()
    return proc.pid


def test_restore_previous_puts_back_only_what_a_dead_run_left_with_no_frame_of_its_own(tmp_path):
    """A run killed (kill -9) between setting the old file aside and its first frame: the next run
    puts it back. Not over a file holding frames (it is named instead), nor one a live run keeps
    (its lock held: a PID alive says nothing after a reboot, which reuses PIDs)."""
    import fcntl
    import socket

    from radiokit.io import restore_previous

    host = socket.gethostname().split(".")[0]
    path = tmp_path / "exp.h5"
    digest = hashlib.sha256(b"exp.h5").hexdigest()[:8]
    old = _write_experiment(tmp_path / "old.h5", shape=EXP_SHAPE)
    before = old.read_bytes()
    aside = tmp_path / f".exp.previous-{host}-{os.getppid()}-{digest}.h5"  # a live PID, reused: no lock
    # the name holds the killed run's file with no frame: put back
    old.rename(aside)
    ExperimentWriter(path, shape=EXP_SHAPE).close()
    said = restore_previous(path)
    assert said == [(True, said[0][1])] and aside.name in said[0][1] and "restored" in said[0][1], said
    assert path.read_bytes() == before and not aside.exists()
    # nothing under the name (killed between the rename and the new file): put back
    path.rename(aside)
    assert restore_previous(path)[0][0] is True and path.read_bytes() == before
    # the new file's first bytes only (killed, or a power cut, as libhdf5 began it): put back
    path.rename(aside)
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(88))
    assert restore_previous(path)[0][0] is True and path.read_bytes() == before
    # a small file of another program's (not HDF5's start): never written over, the old one named
    path.rename(aside)
    path.write_bytes(b"notes of the day\n")
    said = restore_previous(path)
    assert said[0][0] is False and str(aside) in said[0][1] and path.read_bytes() == b"notes of the day\n", said
    path.unlink()
    aside.rename(path)
    # the name holds frames: kept, and named
    path.rename(aside)
    _write_experiment(path, shape=EXP_SHAPE)
    after = path.read_bytes()
    said = restore_previous(path)
    assert len(said) == 1 and said[0][0] is False and str(aside) in said[0][1], said
    assert aside.read_bytes() == before and path.read_bytes() == after
    # a live run's (its lock held): its own to put back, nothing said
    live = tmp_path / f".exp.previous-{host}-{_dead_pid()}-{digest}.h5"
    aside.rename(live)
    fd = os.open(live, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        assert restore_previous(path) == [] and live.exists()
    finally:
        os.close(fd)
    # another name sharing the cut head is not this one's (a name past NAME_MAX's room is cut)
    other = tmp_path / f".exp.previous-{host}-{_dead_pid()}-{hashlib.sha256(b'exp2.h5').hexdigest()[:8]}.h5"
    live.rename(other)
    assert restore_previous(path) == [] and other.exists()


def test_the_output_check_survives_an_input_whose_link_names_are_not_utf8(tmp_path):
    """Every writer's output check lists the files an HDF5 input's frames come from, before any
    reader has judged the input. A name that is not UTF-8 (a corrupt link table: 23 of 300
    fuzzed files) made h5py's visit raise SystemError there, a traceback where the reader would
    have named the file's problem in one line."""
    from radiokit.io import check_output, data_files

    path = tmp_path / "odd.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset(b"\xd6x", data=np.arange(3))
        h5["ext"] = h5py.ExternalLink("other.h5", "/x")
    assert data_files(path, allow_external=True) == []
    check_output(tmp_path / "out.h5", inputs=[path])  # nothing to refuse, nothing raised


def test_a_master_file_whose_frames_are_external_links_names_them(tmp_path):
    """A Dectris-style master file keeps its frames in data files it links to (entry/data/data_000001
    -> a second file); the refusal names those links and --allow-external, not "holds no 2-D or 3-D
    dataset of numbers" (a user read that as an empty file). Nothing outside the file is opened."""
    for i in (1, 2):
        with h5py.File(tmp_path / f"m_data_00000{i}.h5", "w") as f:
            f["entry/data/data"] = np.zeros((3, 8, 8), np.uint16)
    with h5py.File(tmp_path / "m_master.h5", "w") as f:
        for i in (1, 2):
            f[f"entry/data/data_00000{i}"] = h5py.ExternalLink(f"m_data_00000{i}.h5", "/entry/data/data")
    (tmp_path / "m_data_000002.h5").unlink()  # a dangling link must not matter: the links are only listed
    with pytest.raises(FormatError) as err:
        read(tmp_path / "m_master.h5")
    msg = str(err.value)
    assert "/entry/data/data_000001 (in m_data_000001.h5)" in msg and "--allow-external" in msg, msg
    assert "holds no 2-D or 3-D dataset" not in msg
    with h5py.File(tmp_path / "m_master.h5", "a") as f:
        f["entry/local"] = np.zeros((4, 4), np.float32)
    with pytest.raises(
        FormatError, match=r"/entry/local \(4x4 float32\).*/entry/data/data_000001 \(in m_data_000001\.h5\)"
    ):
        read(tmp_path / "m_master.h5")


def test_the_writer_warns_of_values_above_the_adcs_top_once_per_kind(tmp_path):
    """s40rev: 16-bit frames written without bit_depth (the README's recipe for vendor TIFFs) went in
    silently, and only reads warned afterwards. The writer says it at the first frame of each kind,
    naming bit_depth=; frames within the range, or a bit_depth that holds them, say nothing."""
    from radiokit.io import BitDepthWarning

    rng = np.random.default_rng(0)
    sixteen = rng.integers(20000, 60000, (8, 8)).astype(np.uint16)
    with pytest.warns(
        BitDepthWarning,
        match=r"frame 0 \(image_key 2\) has values up to \d+, above 0..4095 \(no bit_depth given.*bit_depth=",
    ):
        with ExperimentWriter(tmp_path / "a.h5", shape=(8, 8)) as w:
            w.append(sixteen, image_key=ImageKey.DARK)
            w.append(sixteen, image_key=ImageKey.DARK)  # the same kind: not said again
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with ExperimentWriter(tmp_path / "b.h5", shape=(8, 8), bit_depth=16) as w:
            w.append(sixteen, image_key=ImageKey.DARK)
        with ExperimentWriter(tmp_path / "c.h5", shape=(8, 8)) as w:
            w.append(np.full((8, 8), 4095, np.uint16), image_key=ImageKey.FLAT)
    twelve = rng.integers(100, 4000, (8, 8)).astype(np.uint16)
    with pytest.warns(BitDepthWarning, match="byte-swapped values fit") as caught:
        with ExperimentWriter(tmp_path / "d.h5", shape=(8, 8), bit_depth=12) as w:
            w.append(twelve, image_key=ImageKey.DARK)  # right: nothing
            w.append(twelve.byteswap(), image_key=ImageKey.PROJECTION, step=1)
    assert len(caught) == 1


def test_a_writer_appending_records_or_checks_the_bit_depth(tmp_path):
    """Review s40rr: ``bit_depth`` given with mode='a' was ignored (the writer's own warning then
    asked for it); a file's unreadable bit_depth_readout made append fail on a bare shift error."""
    from radiokit.io import BitDepthWarning

    sixteen = np.full((8, 8), 50000, np.uint16)
    path = tmp_path / "a.h5"
    with ExperimentWriter(path, shape=(8, 8)) as w:
        w.append(np.zeros((8, 8), np.uint16), image_key=ImageKey.DARK)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with ExperimentWriter(path, mode="a", bit_depth=16) as w:
            w.append(sixteen, image_key=ImageKey.FLAT)
    assert read(path).meta["bit_depth"] == 16
    with pytest.raises(ValueError, match="records bit_depth_readout 16; bit_depth=12 given"):
        ExperimentWriter(path, mode="a", bit_depth=12)
    odd = tmp_path / "odd.h5"
    with ExperimentWriter(odd, shape=(8, 8)) as w:
        w.append(np.zeros((8, 8), np.uint16), image_key=ImageKey.DARK)
    with h5py.File(odd, "a") as f:
        f["entry/instrument/detector/bit_depth_readout"] = "12 bits"
    with pytest.warns(BitDepthWarning, match="no bit_depth given"):
        with ExperimentWriter(odd, mode="a") as w:
            w.append(sixteen, image_key=ImageKey.FLAT)


def test_a_with_block_that_fails_before_its_first_frame_leaves_no_file_to_block_the_rerun(tmp_path):
    """Found (session 40's list): an averaged float dark refused at the first append left an empty
    experiment file, and the corrected rerun was refused ("exists; raw data is never overwritten")
    though the file held nothing. A new file that never took a frame goes with the failed block; one
    that took a frame stays (it is the run's journal), and a file the writer did not make is kept."""
    path = tmp_path / "exp.h5"
    with pytest.raises(ValueError, match="uint16"):
        with ExperimentWriter(path, shape=EXP_SHAPE) as w:
            w.append(np.full(EXP_SHAPE, 7.25, np.float32), image_key=ImageKey.DARK)
    assert not path.exists()
    with pytest.raises(RuntimeError, match="later"):
        with ExperimentWriter(path, shape=EXP_SHAPE) as w:
            w.append(np.full(EXP_SHAPE, 7, np.uint16), image_key=ImageKey.DARK)
            raise RuntimeError("later")
    assert read(path).n == 1
    with pytest.raises(RuntimeError, match="appending"):
        with ExperimentWriter(path, mode="a") as w:
            raise RuntimeError("appending")
    assert read(path).n == 1


def test_float_frames_holding_whole_counts_are_stored_and_fractional_ones_refused_naming_why(tmp_path):
    """A float frame of whole counts (a TIFF saved as float by an image program) converts to uint16
    without loss; an averaged one does not, and the refusal says how to store it."""
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=EXP_SHAPE) as w:
        w.append(np.full(EXP_SHAPE, 4000.0, np.float32), image_key=ImageKey.FLAT)
        with pytest.raises(ValueError, match=r"not whole counts.*np\.rint"):
            w.append(np.full(EXP_SHAPE, 7.25), image_key=ImageKey.DARK)
        with pytest.raises(ValueError, match="uint16"):
            w.append(np.full(EXP_SHAPE, np.nan), image_key=ImageKey.DARK)
    f = read(path)
    assert f.n == 1 and f.data.dtype == np.uint16 and np.all(f.data == 4000)


def test_read_given_an_array_says_a_path_is_expected():
    """``read(ndarray)`` was pathlib's "expected str, bytes or os.PathLike object, not ndarray"."""
    with pytest.raises(
        TypeError, match=r"^expected a file path \(str or os.PathLike\), got ndarray: frames already in memory"
    ):
        read(np.zeros((4, 4)))


@pytest.mark.parametrize("writer", ["write_tiff", "StackWriter"])
def test_writers_refuse_an_existing_file_unless_overwrite(tmp_path, writer):
    """``write_tiff`` and ``StackWriter`` replaced an existing file by default, where
    ``write_registration`` and ``ExperimentWriter`` refuse: nothing is replaced unasked."""
    path = tmp_path / "s.tif"

    def write(value, **kw):
        if writer == "write_tiff":
            write_tiff(path, np.full((3, 4), value, np.uint16), **kw)
        else:
            with StackWriter(path, (3, 4), np.uint16, **kw) as w:
                w.append(np.full((3, 4), value, np.uint16))

    write(1)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match=r"s\.tif: exists; pass --overwrite \(overwrite=True\)"):
        write(2)
    assert path.read_bytes() == before
    write(2, overwrite=True)
    assert int(read(path).data[0, 0, 0]) == 2


@pytest.mark.parametrize("panel, preset, n", [((2240, 2240), "c7942", 1), ((1120, 1120), "c7942-2x2", 4)])
def test_a_raw_size_fitting_several_presets_is_settled_by_the_panels_shape(tmp_path, panel, preset, n):
    """One 2240 x 2240 frame's bytes are four 2x2-binned frames too, and were refused as ambiguous
    even beside a calibration, whose shape is the panel's geometry. ``panel_shape=`` (the shape a
    calibration gives) picks the one fitting preset of that shape; the size alone still decides
    nothing. A sparse file: only its size is read to judge."""
    path = tmp_path / "frame.raw"
    with open(path, "wb") as fh:
        fh.truncate(2240 * 2240 * 2)
    with open_frames(path, panel_shape=panel) as src:
        assert (src.meta["preset"], len(src), src.frame_shape) == (preset, n, panel)
        assert src.meta["bit_depth"] == 12  # the preset's panel, as --preset gives it


@pytest.mark.parametrize("panel", [(600, 600), (2240, 2344)])
def test_a_panel_shape_no_fitting_preset_has_keeps_the_refusal_naming_it(tmp_path, panel):
    path = tmp_path / "frame.raw"
    with open(path, "wb") as fh:
        fh.truncate(2240 * 2240 * 2)
    _raises_format(path, "ambiguous", "1 frame of 2240x2240 (c7942)", f"{panel[0]}x{panel[1]}", panel_shape=panel)


def test_a_panel_shape_is_no_geometry_hint_for_files_that_carry_their_own(tmp_path):
    """A calibration is given beside TIFF frames as beside raw ones: the TIFF's own shape stands
    (correct compares it with the calibration's), no refusal of a raw-only hint."""
    path = tmp_path / "f.tif"
    tifffile.imwrite(path, np.zeros((2, 8, 6), np.uint16))
    with open_frames(path, panel_shape=(5, 5)) as src:
        assert src.frame_shape == (8, 6)


@pytest.mark.parametrize("peak, bits", [(16383, 14), (9000, 14), (40000, 16)])
def test_values_past_a_presets_12_bits_are_said_to_fit_the_smallest_adc_that_holds_them(tmp_path, peak, bits):
    """A 14-bit panel's raw file read at a C7942 preset (12-bit; no bit depth in the file): the
    warning said "another detector (C9730DK/C9732DK are 14-bit ...; many cameras 16-bit)" and left
    the reader to work out which. It names the smallest usual ADC depth (12, 14, 16 bits) holding
    the values, the one calibrate and info judge saturation at."""
    rng = np.random.default_rng(0)
    frame = rng.integers(200, peak + 1, (560, 560)).astype("<u2")
    frame[0, 0] = peak
    frame.tofile(tmp_path / "f.raw")
    with pytest.warns(BitDepthWarning) as caught:
        read(tmp_path / "f.raw")
    text = str(caught[0].message)
    assert f"up to {peak} exceed the 12-bit range" in text, text
    assert f"they fit a {bits}-bit ADC (0..{(1 << bits) - 1})" in text, text


def test_restore_previous_names_the_series_set_aside_as_names_print(tmp_path):
    """Review s52rvoff: s52 named the folder ExperimentWriter keeps a previous series in as names
    print (radiokit._names.shown) in one of its messages; restore_previous's, which name the
    same set-aside file, printed it raw: a newline in the user's name split the line there (the
    command line's net then quoted the user's name inside it, `.'e\\nx'.previous-...`)."""
    import socket

    from radiokit._names import shown
    from radiokit.io import restore_previous

    host = socket.gethostname().split(".")[0]
    path = tmp_path / "e\nx.h5"
    digest = hashlib.sha256(b"e\nx.h5").hexdigest()[:8]
    aside = tmp_path / f".e\nx.previous-{host}-{_dead_pid()}-{digest}.h5"
    _write_experiment(aside, shape=EXP_SHAPE)
    said = restore_previous(path, dry_run=True)  # the name free: it would be put back
    assert len(said) == 1 and said[0][0] is True and shown(aside.name) in said[0][1], said
    assert "\n" not in said[0][1], said
    _write_experiment(path, shape=EXP_SHAPE)  # the name holds frames: the set-aside one is kept
    said = restore_previous(path)
    assert len(said) == 1 and said[0][0] is False and shown(aside) in said[0][1], said
    assert "\n" not in said[0][1], said
