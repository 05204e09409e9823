"""Damage inside a compressed stream is refused in one line naming the file, not decoded into
wrong pixels. libjpeg-turbo decodes a JPEG whose coded data runs out before its image does (cut
short with its end marker kept, bytes lost) without an error, the rest of the image filled in
(benchmarks/bench_codec_damage.py measures which damage each decoder refuses on its own)."""

import io
import warnings

import imagecodecs
import numpy as np
import pytest
from conftest import run_cli

from radiokit.io import FormatError, read
from radiokit.io._codecs import LossyWarning, bytes_header

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
