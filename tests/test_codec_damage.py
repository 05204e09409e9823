"""Damage inside a compressed stream is refused in one line naming the file, not decoded into
wrong pixels. libjpeg-turbo decodes a JPEG whose coded data runs out before its image does (cut
short with its end marker kept, bytes lost) without an error, the rest of the image filled in
(benchmarks/bench_codec_damage.py measures which damage each decoder refuses on its own)."""

import io
import sys
import warnings
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
from conftest import run_cli

from radiokit.io import FormatError, read
from radiokit.io._codecs import LossyWarning, bytes_header

# the fill-byte copy is the benchmark's own (T.81 B.1.1.2: any marker may follow any number of 0xFF),
# so the test refuses nothing the bench counts as a false refusal and vice versa
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_codec_damage import with_fill_bytes

JPEGS = {
    "ljpeg SV1": lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12),
    "ljpeg P7": lambda f: imagecodecs.jpeg8_encode(f, lossless=True, bitspersample=12, predictor=7),
    "JPEG12 q90": lambda f: imagecodecs.jpeg8_encode(f, level=90, bitspersample=12),
}


def _frame(kind="ramp", shape=(48, 40), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[: shape[0], : shape[1]]
    if kind == "constant":
        return np.full(shape, 100, np.uint16)
    if kind == "dark":  # a read-noise-only dark: codes of a bit or two a sample
        return np.clip(np.round(100 + rng.normal(0, 1, shape)), 0, 4095).astype(np.uint16)
    return rng.poisson(500 + 20 * x + 10 * y).clip(0, 4095).astype(np.uint16)


def _coded_span(stream: bytes) -> tuple[int, int]:
    return bytes_header(stream)["scan"] + 20, len(stream) - 2


def _refused(path, *words):
    with warnings.catch_warnings(), pytest.raises(FormatError) as info:
        warnings.simplefilter("ignore", LossyWarning)  # (a lossy stream's: said before the refusal)
        read(path).data  # noqa: B018 (the frames are read when asked for)
    said = str(info.value)
    assert "\n" not in said and path.name in said
    for w in words:
        assert w in said, said
    return said


@pytest.mark.parametrize("syntax", list(JPEGS))
@pytest.mark.parametrize("fraction", [0.1, 0.6, 0.97])
def test_a_jpeg_cut_short_with_its_end_marker_kept_is_refused(tmp_path, syntax, fraction):
    stream = bytes(JPEGS[syntax](_frame()))
    lo, hi = _coded_span(stream)
    cut = lo + int((hi - lo) * fraction)
    path = tmp_path / "cut.jpg"
    path.write_bytes(stream[:cut] + b"\xff\xd9")
    _refused(path, "coded data", "truncated")


@pytest.mark.parametrize("syntax", ["ljpeg SV1", "ljpeg P7"])
@pytest.mark.parametrize("where", [0.1, 0.5, 0.9])
def test_a_lossless_jpeg_missing_bytes_inside_its_coded_data_is_refused(tmp_path, syntax, where):
    """Lossless JPEG codes every sample: bytes lost leave the decoder short of its image. (A
    lossy stream's decoder, thrown out of step, often ends its blocks early on the bytes it has:
    not found, benchmarks/README.md.)"""
    stream = bytes(JPEGS[syntax](_frame()))
    lo, hi = _coded_span(stream)
    at = lo + int((hi - lo) * where)
    path = tmp_path / "holed.jpg"
    path.write_bytes(stream[:at] + stream[at + 20 :])
    _refused(path, "coded data")


@pytest.mark.parametrize("syntax", list(JPEGS))
@pytest.mark.parametrize("kind", ["ramp", "constant", "dark"])
def test_an_undamaged_jpeg_reads_as_its_decoder_gives_it(tmp_path, syntax, kind):
    frame = _frame(kind)
    stream = bytes(JPEGS[syntax](frame))
    path = tmp_path / "whole.jpg"
    path.write_bytes(stream)
    with pytest.warns(UserWarning) if "q90" in syntax else _no_warning():
        data = read(path).data[0]
    np.testing.assert_array_equal(data, imagecodecs.jpeg8_decode(stream))
    if "q90" not in syntax:
        np.testing.assert_array_equal(data, frame)


class _no_warning:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _pillow_jpeg(restart_blocks: int) -> bytes:
    from PIL import Image

    a = np.random.default_rng(1).integers(0, 255, (64, 64)).astype(np.uint8)
    out = io.BytesIO()
    Image.fromarray(a).save(out, "JPEG", quality=90, restart_marker_blocks=restart_blocks)
    return out.getvalue()


def test_a_jpeg_with_restart_markers_reads_whole_and_is_refused_missing_one_interval(tmp_path):
    stream = _pillow_jpeg(4)  # 64 blocks, a restart every 4: 15 RST markers
    whole = tmp_path / "rst.jpg"
    whole.write_bytes(stream)
    with pytest.warns(UserWarning):  # (lossy)
        np.testing.assert_array_equal(read(whole).data[0], imagecodecs.jpeg8_decode(stream))
    # an interval lost with its RST marker: libjpeg resynchronises at the next one, and its
    # blocks come out grey
    rst = [stream.find(bytes([0xFF, 0xD0 + k])) for k in range(3)]
    holed = tmp_path / "holed.jpg"
    holed.write_bytes(stream[: rst[1]] + stream[rst[2] :])
    _refused(holed, "restart")
    # an interval cut short, its RST kept: it runs into the marker
    cut = tmp_path / "short.jpg"
    cut.write_bytes(stream[: rst[1] - 10] + stream[rst[1] :])
    _refused(cut, "coded data")


def test_a_jpeg2000_whose_tile_parts_do_not_reach_its_end_is_refused(tmp_path):
    stream = bytes(imagecodecs.jpeg2k_encode(_frame(), level=0, codecformat="J2K", bitspersample=12))
    lo, hi = _coded_span(stream)
    path = tmp_path / "cut.j2k"
    path.write_bytes(stream[: (lo + hi) // 2] + b"\xff\xd9")
    _refused(path, "tile-part", "truncated")
    ok = tmp_path / "whole.j2k"
    ok.write_bytes(stream)
    np.testing.assert_array_equal(read(ok).data[0], _frame())


def test_info_on_a_damaged_jpeg_is_one_line_naming_the_file(tmp_path):
    stream = bytes(JPEGS["ljpeg SV1"](_frame()))
    lo, hi = _coded_span(stream)
    path = tmp_path / "cut.jpg"
    path.write_bytes(stream[: (lo + hi) // 2] + b"\xff\xd9")
    res = run_cli("info", path)
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "cut.jpg" in lines[0] and "Traceback" not in res.stderr


# Two arithmetic-coded streams libjpeg-turbo's cjpeg made (tests hold no encoder of them): a 16x24
# ramp, ``cjpeg -quality 95 -arithmetic -restart 1B``, and 16x16 noise, ``cjpeg -quality 90
# -arithmetic -progressive``. The arithmetic decoder reads zero bits once it meets a marker, and
# the encoder drops its code register's trailing zero bytes for it (T.81 D.1.8, F.2.2.5): such a
# stream's last symbols are decoded from the bytes that follow its coded data, where a Huffman
# stream's never are
_ARITHMETIC = {
    "restarts": (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAAIBAQEBAQIBAQECAgICAgQDAgICAgUEBAMEBgUGBgYFBgYGBwkIBgcJBwYGCAsICQoK"
        "CgoKBggLDAsKDAkKCgr/yQALCAAQABgBAREA/8wABgAQEAX/3QAEAAH/2gAIAQEAAD8A/wDcaQD30mKMei2N82496pJP/wD4pPwD"
        "Tox+V6X6weIh/9DPxWcmRurQosMXuC+mpexva2PJx01V2EV+842xiOoLgijA/9HS2Tkhr3E/vg+4u+2MBtcywhePJIGeKNz5gkSY"
        "M9t5C4ae6P/S/wChrUZlLQo7iShpjTk1s3aKieZJ+IdDAY3z8gerguERQP/T0srUXISaFiCFuf1LS39EqjMtB3afdSE4Ry6Ff00a"
        "QHX3QBIG/9TS4FNQ6quzfHMX1JsAX7A9O/UVGMI677Pj/CYH632d6ugDAf/Z"
    ),
    "progressive": (
        "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAAMCAgMCAgMDAwMEAwMEBQgFBQQEBQoHBwYIDAoMDAsKCwsNDhIQDQ4RDgsLEBYQERMU"
        "FRUVDA8XGBYUGBIUFRT/ygALCAAQABABAREA/8wABAAQ/9oACAEBAAAAAdHPXnZQ/8wABBAF/9oACAEBAAEFAhUrz4OztQ2J3zt+"
        "sIieFrX/zAAEEAX/2gAIAQEABj8CHjj8iO/oHMWFlkH3Z08JDYbLamrJdOMM8zOg+e5vJ/hPkFEoh4Srj8x/3kBm2TbnL2kfiV0Y"
        "7MR2i9vZ5gk9OKLakQgitoeftMug+VC0vMt1ImYDlGQkPeJbfZH/zAAEEAX/2gAIAQEAAT8h7RgLeSiCqjLjZKx1tqq3Y4cNDhS4"
        "2Nk95+ZbBMtUqpwYykQTVUB8UCkEjRD/2gAIAQEAAAAQ4P/MAAQQBf/aAAgBAQABPxCmtzLZJXvXMq7XNyRlTomSE5mKperYdzji"
        "AN3FROwRVBuGXDjiYPFc/9k="
    ),
}


@pytest.mark.parametrize("kind", list(_ARITHMETIC))
def test_an_undamaged_arithmetic_coded_jpeg_reads_as_its_decoder_gives_it(tmp_path, kind):
    import base64

    stream = base64.b64decode(_ARITHMETIC[kind])
    assert "arithmetic" in bytes_header(stream)["process"]
    path = tmp_path / "arith.jpg"
    path.write_bytes(stream)
    with pytest.warns(LossyWarning):
        data = read(path).data[0]
    np.testing.assert_array_equal(data, imagecodecs.jpeg8_decode(stream))
    if kind == "restarts":  # the restart markers' order is still checked: an interval lost is found
        rst = [stream.find(bytes([0xFF, 0xD0 + k])) for k in range(3)]
        holed = tmp_path / "holed.jpg"
        holed.write_bytes(stream[: rst[1]] + stream[rst[2] :])
        _refused(holed, "restart")


def _pillow_progressive() -> bytes:
    from PIL import Image

    a = np.random.default_rng(2).integers(0, 255, (64, 64)).astype(np.uint8)
    out = io.BytesIO()
    Image.fromarray(a).save(out, "JPEG", quality=90, progressive=True)
    return out.getvalue()


@pytest.mark.parametrize("kind", ["baseline", "restarts", "progressive"])
def test_a_jpeg_with_fill_bytes_before_its_markers_reads_as_without_them(tmp_path, kind):
    stream = {
        "baseline": lambda: bytes(JPEGS["JPEG12 q90"](_frame())),
        "restarts": lambda: _pillow_jpeg(4),
        "progressive": _pillow_progressive,
    }[kind]()
    filled = with_fill_bytes(stream)
    assert len(filled) >= len(stream) + 2  # (a baseline stream: only its EOI)
    # the decoder reads the fill bytes as nothing: the stream is as valid as it was
    np.testing.assert_array_equal(imagecodecs.jpeg8_decode(filled), imagecodecs.jpeg8_decode(stream))
    path = tmp_path / "filled.jpg"
    path.write_bytes(filled)
    with pytest.warns(LossyWarning):
        data = read(path).data[0]
    np.testing.assert_array_equal(data, imagecodecs.jpeg8_decode(stream))


def test_the_budget_counts_the_second_decode_of_a_jpeg(tmp_path):
    """:func:`check_coded_data` decodes a JPEG twice and holds both images to compare them (and
    the padded copy of its stream): a budget that one image fits, and not two, is not enough. What
    the read holds at its peak (session 56, bench_dicom_decode_memory.py: exactly what tracemalloc
    saw) is the file's bytes and their padded copy, both decodes, the comparison's booleans (a byte
    a sample: half a 16-bit image) and the frame in its stack: 3.5 images and 2 streams."""
    frame = _frame(shape=(256, 256))
    stream = bytes(JPEGS["ljpeg SV1"](frame))
    path = tmp_path / "twice.jpg"
    path.write_bytes(stream)
    image = frame.nbytes
    with pytest.raises(FormatError, match=r"twice\.jpg: .*memory budget"):
        read(path, budget=int(1.5 * image)).data  # noqa: B018
    np.testing.assert_array_equal(read(path, budget=int(3.5 * image) + 3 * len(stream)).data[0], frame)
