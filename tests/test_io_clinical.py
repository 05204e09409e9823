"""PNG and DICOM radiographs, as other labs and archives hand them over: files written here by
the libraries that write them (OpenCV, pydicom), read back exactly, and refused in one line
naming the file where they are not one channel of counts or declare more than the budget."""

import json
import re
import struct
import warnings
import zlib

import numpy as np
import pytest

from radiokit.io import FormatError, open_frames, read
from tests.conftest import run_cli


def _texture(shape=(40, 50), seed=3):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 65536, size=shape, dtype=np.uint16)


def _png(path, image):
    import cv2

    assert cv2.imwrite(str(path), image)
    return path


# -- PNG --------------------------------------------------------------------------------------
def test_a_16_bit_png_reads_back_exactly(tmp_path):
    """Every 16-bit value, the byte order included (PNG stores big-endian), comes back as written."""
    image = _texture()
    image[0, :4] = [0, 1, 0x0102, 65535]  # byte-swapped, 0x0102 would read 0x0201
    got = read(_png(tmp_path / "chest.png", image))
    assert got.data.shape == (1, 40, 50) and got.data.dtype == np.uint16
    np.testing.assert_array_equal(got.data[0], image)
    assert got.meta["format"] == "png" and got.meta["png_bit_depth"] == 16


def test_an_8_bit_png_reads_as_uint8(tmp_path):
    image = (_texture() >> 8).astype(np.uint8)
    got = read(_png(tmp_path / "nih.png", image))
    assert got.data.dtype == np.uint8
    np.testing.assert_array_equal(got.data[0], image)


def test_an_rgb_png_of_equal_channels_is_one_grey_image_and_of_differing_ones_refused(tmp_path):
    image = _texture()
    got = read(_png(tmp_path / "grey.png", np.dstack([image] * 3)))
    np.testing.assert_array_equal(got.data[0], image)
    rgba = np.dstack([image] * 3 + [np.full_like(image, 65535)])
    np.testing.assert_array_equal(read(_png(tmp_path / "grey_rgba.png", rgba)).data[0], image)
    colour = np.dstack([image, image, image // 2])
    with pytest.raises(FormatError, match=r"colour\.png: a RGB PNG, its colour channels differ") as info:
        read(_png(tmp_path / "colour.png", colour))
    assert "\n" not in str(info.value)


def _bomb_png(path, width, height):
    """A valid PNG signature and IHDR declaring ``width`` x ``height`` 16-bit grey, and no pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + b"\0\0\0\0IEND\xaeB`\x82")
    return path


def test_a_png_declaring_60000_by_60000_is_refused_before_decoding(tmp_path):
    """7.2 GB declared (60000^2 x 2 bytes) in ~60 bytes: refused from the IHDR against a 1 GB budget,
    in one line naming the file, before OpenCV allocates anything."""
    path = _bomb_png(tmp_path / "bomb.png", 60000, 60000)
    assert path.stat().st_size < 100
    with pytest.raises(FormatError, match=r"bomb\.png: .*60000x60000 16-bit") as info:
        read(path, budget="1GiB")
    assert "\n" not in str(info.value)


def test_a_png_sbit_of_12_is_its_saturation_judgement(tmp_path):
    """sBIT says 12 significant bits in 16-bit words: values above 4095 warn, as a 12-bit TIFF's."""
    from radiokit.io import BitDepthWarning

    image = np.full((8, 8), 100, np.uint16)
    image[0, 0] = 5000
    path = _png(tmp_path / "twelve.png", image)
    data = path.read_bytes()
    sbit = struct.pack(">I", 1) + b"sBIT\x0c" + struct.pack(">I", zlib.crc32(b"sBIT\x0c"))
    path.write_bytes(data[:33] + sbit + data[33:])  # after IHDR, before IDAT
    with pytest.warns(BitDepthWarning, match=r"exceed the 12-bit range 0\.\.4095"):
        got = read(path)
    assert got.meta["bit_depth"] == 12


# -- DICOM ------------------------------------------------------------------------------------
def _dicom(
    path,
    frames,
    *,
    bits_stored=16,
    photometric="MONOCHROME2",
    rescale=None,
    syntax=None,
    pixels=True,
    spacing=None,
    signed=False,
):
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian, RLELossless, generate_uid

    # signed: PixelRepresentation 1, the values' two's complement in bits_stored bits (the bits above
    # them 0, as a 12-bit panel's software writes them; pydicom extends the sign from BitsStored)
    frames = np.asarray(frames, np.int16 if signed else np.uint16)
    syntax = syntax or ExplicitVRLittleEndian
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.1.1"  # DX for processing
    meta.MediaStorageSOPInstanceUID = generate_uid()
    plain = (ExplicitVRLittleEndian, DeflatedExplicitVRLittleEndian)  # (pydicom deflates the dataset as it writes)
    meta.TransferSyntaxUID = syntax if syntax in plain else ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID, "DX"
    if pixels:
        ds.Rows, ds.Columns = frames.shape[-2:]
        if frames.ndim == 3:
            ds.NumberOfFrames = frames.shape[0]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, photometric
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, bits_stored, bits_stored - 1, signed
        words = frames.astype("<i2").view("<u2") & ((1 << bits_stored) - 1) if signed else frames.astype("<u2")
        ds.PixelData = words.tobytes()
    if rescale:
        ds.RescaleSlope, ds.RescaleIntercept = rescale
    if spacing:
        ds.ImagerPixelSpacing = list(spacing)
    if syntax == RLELossless:
        ds.compress(RLELossless, frames)
    elif syntax not in plain:  # a compressed syntax: encapsulated fragments, never decoded
        from pydicom.encaps import encapsulate

        ds.file_meta.TransferSyntaxUID = syntax
        ds.PixelData = encapsulate([b"\xff\x4f\xff\x51" + bytes(60)])
        ds["PixelData"].VR = "OB"
    ds.save_as(path, enforce_file_format=True)
    return path


def test_a_dicom_frame_reads_back_exactly_with_its_pitch(tmp_path):
    image = _texture() >> 4  # 12-bit counts
    path = _dicom(tmp_path / "dx.dcm", image, bits_stored=12, spacing=(0.143, 0.15))
    got = read(path)
    assert got.data.shape == (1, 40, 50) and got.data.dtype == np.uint16
    np.testing.assert_array_equal(got.data[0], image)
    assert got.meta["format"] == "dicom" and got.meta["bit_depth"] == 12
    # ImagerPixelSpacing is [row, column] in mm: rows are y
    assert got.meta["y_pixel_size"] == pytest.approx(0.143e-3) and got.meta["x_pixel_size"] == pytest.approx(0.15e-3)
    assert got.meta["pixel_size_mm"] == pytest.approx(0.15)


def test_a_dicom_rescale_is_applied_as_the_file_states(tmp_path):
    image = _texture() >> 4
    got = read(_dicom(tmp_path / "ct.dcm", image, bits_stored=12, rescale=(0.5, -1024.25)))
    np.testing.assert_allclose(got.data[0], image * 0.5 - 1024.25, rtol=0, atol=1e-12)
    assert got.meta["dicom_rescale"]["slope"] == 0.5 and got.meta["dicom_rescale"]["intercept"] == -1024.25
    ints = read(_dicom(tmp_path / "int.dcm", image, rescale=(2, -1000)))
    assert ints.data.dtype == np.int32
    np.testing.assert_array_equal(ints.data[0], image.astype(np.int64) * 2 - 1000)


def test_a_multi_frame_dicom_uncompressed_deflated_and_rle(tmp_path):
    from pydicom.uid import DeflatedExplicitVRLittleEndian, RLELossless

    stack = np.stack([_texture(seed=s) for s in range(3)])
    for syntax, name in (
        (None, "plain.dcm"),
        (DeflatedExplicitVRLittleEndian, "deflated.dcm"),
        (RLELossless, "rle.dcm"),
    ):
        path = _dicom(tmp_path / name, stack, syntax=syntax)
        assert (
            read(path)
            .meta["transfer_syntax"]
            .startswith({None: "Explicit", RLELossless: "RLE"}.get(syntax, "Deflated"))
        )
        np.testing.assert_array_equal(read(path).data, stack)
        with open_frames(path) as src:  # frame by frame
            np.testing.assert_array_equal(src[2], stack[2])


def test_monochrome1_is_said_and_read_as_stored(tmp_path):
    image = _texture()
    with pytest.warns(UserWarning, match=r"mono1\.dcm: MONOCHROME1: .*not inverted"):
        got = read(_dicom(tmp_path / "mono1.dcm", image, photometric="MONOCHROME1"))
    np.testing.assert_array_equal(got.data[0], image)
    assert got.meta["photometric"] == "MONOCHROME1" and "not inverted" in got.meta["photometric_note"]


def test_a_compressed_syntax_radiokit_does_not_decode_is_refused_by_name(tmp_path):
    """(JPEG, JPEG-LS, JPEG 2000 and HTJ2K are decoded: tests/test_io_codecs.py.)"""
    from pydicom.uid import MPEG2MPML, JPEG2000MCLossless

    for syntax, said in (
        (JPEG2000MCLossless, "JPEG 2000 Part 2 Multi-component Image Compression (Lossless Only)"),
        (MPEG2MPML, "lossy"),
    ):
        path = _dicom(tmp_path / "j.dcm", _texture(), syntax=syntax)
        with pytest.raises(FormatError, match=r"j\.dcm: a DICOM file compressed as ") as info:
            read(path)
        assert said in str(info.value) and "\n" not in str(info.value)


def test_a_dicom_without_pixels_is_refused(tmp_path):
    with pytest.raises(FormatError, match=r"sr\.dcm: a DICOM file, but it has no pixel data"):
        read(_dicom(tmp_path / "sr.dcm", _texture(), pixels=False))


def test_a_dicom_declaring_more_than_the_budget_is_refused_before_decoding(tmp_path):
    path = _dicom(tmp_path / "big.dcm", _texture((4, 4)))
    import pydicom

    ds = pydicom.dcmread(path)
    ds.Rows, ds.Columns, ds.NumberOfFrames = 60000, 60000, 10  # the pixels stay 32 bytes
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"big\.dcm: .*10 frame\(s\) of 60000x60000") as info:
        read(path, budget="1GiB")
    assert "\n" not in str(info.value)


# -- the command line -------------------------------------------------------------------------
def test_info_on_a_png_and_a_dicom(tmp_path):
    image = _texture() >> 4
    png = _png(tmp_path / "a.png", image)
    dcm = _dicom(tmp_path / "b.dcm", image, bits_stored=12, rescale=(2, 0), spacing=(0.1, 0.1))
    for path in (png, dcm):
        res = run_cli("info", path, "--json")
        assert res.returncode == 0, res.stderr
        out = json.loads(res.stdout)
        text = json.dumps(out)
        assert "40" in text and "50" in text, out
    assert "RescaleSlope" in run_cli("info", dcm).stdout


def test_register_two_16_bit_pngs_finds_a_shift(tmp_path):
    """A smooth texture moved by (0.6, -1.3) px: the registered field, read from two 16-bit PNGs,
    is the shift to < 0.1 px in the interior (16-bit quantisation of a 0..60000 texture is far below)."""
    from scipy import ndimage

    from radiokit.io import read_registration
    from radiokit.register import warp

    rng = np.random.default_rng(11)
    base = ndimage.gaussian_filter(rng.random((96, 128)), 3)
    base = (base - base.min()) / np.ptp(base)
    shift = np.stack([np.full((96, 128), 0.6), np.full((96, 128), -1.3)]).astype(np.float32)
    fixed = warp(base.astype(np.float32), shift)
    for name, image in (("f.png", fixed), ("m.png", base)):
        _png(tmp_path / name, np.round(image * 60000).astype(np.uint16))
    with warnings.catch_warnings():
        res = run_cli("register", tmp_path / "f.png", tmp_path / "m.png", "--preset", "fast", "-o", tmp_path / "r.h5")
    assert res.returncode in (0, 1), res.stderr
    d = read_registration(tmp_path / "r.h5").displacement[:, 16:-16, 16:-16]
    assert abs(float(np.median(d[0])) - 0.6) < 0.1 and abs(float(np.median(d[1])) + 1.3) < 0.1


def test_info_says_monochrome1_once_in_one_line(tmp_path):
    """``info`` opens a file twice (to judge, then to read): the MONOCHROME1 warning is shown once."""
    import os
    import subprocess
    import sys

    path = _dicom(tmp_path / "inv.dcm", _texture(), photometric="MONOCHROME1")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", "info", str(path)], capture_output=True, text=True, env=env
    )
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("\n") == 1 and "inv.dcm: MONOCHROME1" in res.stderr and ".py:" not in res.stderr, res.stderr
    assert "not inverted" in res.stdout


@pytest.mark.parametrize("name, said", [("x.png", "no PNG signature"), ("x.dcm", "no DICOM signature")])
def test_a_png_or_dicom_name_without_its_signature_is_refused_not_read_as_raw(tmp_path, name, said):
    path = tmp_path / name
    path.write_bytes(bytes(200))
    with pytest.raises(FormatError, match=rf"{name.replace('.', '[.]')}: {said}"):
        read(path)


@pytest.mark.parametrize("damage", ["truncated", "flipped"])
def test_a_damaged_png_is_one_line_without_libpng_s_own(tmp_path, damage):
    """libpng prints its own "libpng error: ..." to the process's stderr before OpenCV returns
    nothing: a truncated or corrupted PNG is found by its chunks' lengths and CRCs first."""
    import subprocess
    import sys

    path = _png(tmp_path / "cut.png", _texture((200, 300)))
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    res = subprocess.run([sys.executable, "-m", "radiokit.cli", "info", str(path)], capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "cut.png" in res.stderr and "libpng" not in res.stderr, res.stderr


# -- review s53rvfmt --------------------------------------------------------------------------
@pytest.mark.parametrize(
    "slope, intercept, said",
    [
        (0, 0, "RescaleSlope is 0"),
        ("NaN", 0, "not a finite number"),
        ("inf", 0, "not a finite number"),
        (0.5, "-inf", "not a finite number"),
        # 65535 * 1e305 is past float64's 1.8e308: it read as a frame of inf with an overflow warning
        (1e305, 0, "past float64's range"),
    ],
)
def test_a_dicom_rescale_of_zero_not_finite_or_past_the_type_is_refused(tmp_path, slope, intercept, said):
    """A slope of 0 read every pixel as the intercept, NaN or inf as frames of NaN, silently: the
    file's Modality LUT is refused in one line, as a CF packing's is."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom's own say on a DS of NaN or inf as it writes
        path = _dicom(tmp_path / "lut.dcm", _texture(), rescale=(slope, intercept))
        with pytest.raises(FormatError, match=rf"lut\.dcm: .*{said}") as info:
            open_frames(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("tag, stored", [("RescaleSlope", b"7.25"), ("RescaleIntercept", b"-3.5")])
def test_a_dicom_rescale_that_is_no_number_is_refused_naming_the_tag(tmp_path, tag, stored):
    """float()'s own line ("could not convert string to float: 'abcd'") named neither the tag nor
    what was wrong with the file. pydicom will not write such a DS: the value is put in the bytes."""
    path = _dicom(tmp_path / "lut.dcm", _texture(), rescale=(7.25, -3.5))
    raw = path.read_bytes()
    assert raw.count(stored) == 1
    path.write_bytes(raw.replace(stored, b"abcd"[: len(stored)]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom's own say on an invalid DS as it reads
        with pytest.raises(FormatError, match=rf"lut\.dcm: .*{tag} is not a number") as info:
            open_frames(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("frames", [1, 3])
def test_a_dicom_whose_pixel_data_is_shorter_than_declared_is_refused_at_open(tmp_path, frames):
    """Uncompressed pixels hold rows x cols x frames x BitsAllocated/8 bytes: fewer is a truncated
    or mis-described file, refused on opening (it opened, and each frame failed at its decode)."""
    import pydicom

    path = _dicom(tmp_path / "cut.dcm", np.stack([_texture((6, 8))] * frames) if frames > 1 else _texture((6, 8)))
    ds = pydicom.dcmread(path)
    ds.PixelData = ds.PixelData[: 6 * 8 * 2 * frames - 10]
    ds.save_as(path)
    with pytest.raises(FormatError, match=rf"cut\.dcm: .*{6 * 8 * 2 * frames - 10} bytes of pixel data") as info:
        open_frames(path)
    assert "\n" not in str(info.value)


def test_a_tiny_dicom_declaring_a_gigabyte_of_frames_is_refused_at_open(tmp_path):
    """32 frames of 4096 x 4096 x 16 bits (1 GiB) declared by a file of under a kilobyte: within a
    4 GiB budget (read() would hold 2 GiB: the pixel element and the stack), but refused from the
    PixelData's length before anything is allocated."""
    import pydicom

    path = _dicom(tmp_path / "gig.dcm", _texture((4, 4)))
    ds = pydicom.dcmread(path)
    ds.Rows, ds.Columns, ds.NumberOfFrames = 4096, 4096, 32
    ds.save_as(path)
    assert path.stat().st_size < 1024
    with pytest.raises(FormatError, match=r"gig\.dcm: .*32 bytes of pixel data"):
        read(path, budget="4GiB")


def test_a_big_endian_dicom_reads_exactly(tmp_path):
    """Explicit VR Big Endian (retired, still in old archives): every 16-bit value as written."""
    import pydicom
    from pydicom.uid import ExplicitVRBigEndian

    image = _texture()
    image[0, :3] = [1, 0x0102, 65535]  # byte-swapped, 0x0102 would read 0x0201
    path = _dicom(tmp_path / "be.dcm", image)
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = ExplicitVRBigEndian
    ds.PixelData = image.astype(">u2").tobytes()
    pydicom.dcmwrite(path, ds, little_endian=False, implicit_vr=False, enforce_file_format=True)
    assert pydicom.dcmread(path).file_meta.TransferSyntaxUID == ExplicitVRBigEndian
    got = read(path)
    assert got.meta["transfer_syntax"].startswith("Explicit VR Big Endian")
    np.testing.assert_array_equal(got.data[0], image)


def _chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png16_by_hand(image, *, interlace=0, before=b"", after=b"", idat_bytes=None):
    """A 16-bit greyscale PNG written chunk by chunk (filter 0 on every row), Adam7 where asked:
    OpenCV writes neither interlaced nor extra chunks."""
    h, w = image.shape
    be = image.astype(">u2")
    passes = [(0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1)]
    subs = [be[y::dy, x::dx] for y, x, dy, dx in passes] if interlace else [be]
    raw = b"".join(b"\0" + row.tobytes() for sub in subs if sub.size for row in sub)
    idat = zlib.compress(raw)[:idat_bytes]
    ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, interlace)
    head = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + before
    return head + _chunk(b"IDAT", idat) + after + _chunk(b"IEND", b"")


def test_an_adam7_16_bit_png_with_a_gamma_reads_its_stored_values(tmp_path):
    """Interlaced samples land where they belong, and gAMA/cHRM are a display's business: the
    values are the stored ones, not gamma-corrected."""
    image = _texture((37, 29))
    image[0, :3] = [1, 0x0102, 65535]
    gamma = _chunk(b"gAMA", struct.pack(">I", 45455)) + _chunk(b"cHRM", bytes(32))
    path = tmp_path / "adam7.png"
    path.write_bytes(_png16_by_hand(image, interlace=1, before=gamma))
    np.testing.assert_array_equal(read(path).data[0], image)


def test_text_and_icc_chunks_are_never_decoded_nor_libpng_heard(tmp_path, capfd):
    """A zTXt, iTXt and iCCP each inflating to 100 MB (a decompression bomb in a text chunk), and
    a profile libpng finds wrong: the pixels read exactly, and libpng's own "libpng warning: ..."
    lines (a second voice on the user's terminal) are not printed."""
    image = _texture((20, 30))
    bomb = zlib.compress(bytes(100_000_000), 9)
    extra = (
        _chunk(b"zTXt", b"Comment\0\0" + bomb)
        + _chunk(b"iTXt", b"Comment\0\1\0\0\0" + bomb)
        + _chunk(b"iCCP", b"prof\0\0" + bomb)
    )
    path = tmp_path / "chunks.png"
    path.write_bytes(_png16_by_hand(image, before=extra))
    np.testing.assert_array_equal(read(path).data[0], image)
    assert "libpng" not in capfd.readouterr().err


def test_a_png_whose_pixel_stream_is_cut_is_one_line(tmp_path, capfd):
    """IDAT's zlib stream cut short inside a chunk whose CRC is right (a writer killed, then the
    file closed properly): refused in one line naming the file, and libpng's "Not enough image
    data" not printed."""
    path = tmp_path / "short.png"
    path.write_bytes(_png16_by_hand(_texture((40, 50)), idat_bytes=300))
    with pytest.raises(FormatError, match=r"short\.png: a PNG whose pixel data .*ends early") as info:
        read(path)
    assert "\n" not in str(info.value) and "libpng" not in capfd.readouterr().err


def test_an_animated_png_is_refused_not_read_as_its_first_frame(tmp_path):
    """An APNG's acTL declares its frames; OpenCV reads the default image alone, silently."""
    image = _texture((10, 12))
    actl = _chunk(b"acTL", struct.pack(">II", 2, 0))
    fctl = _chunk(b"fcTL", struct.pack(">IIIIIHHBB", 0, 12, 10, 0, 0, 1, 1, 0, 0))
    raw = b"".join(b"\0" + row.tobytes() for row in image[::-1].astype(">u2"))
    later = _chunk(b"fcTL", struct.pack(">IIIIIHHBB", 1, 12, 10, 0, 0, 1, 1, 0, 0))
    later += _chunk(b"fdAT", struct.pack(">I", 2) + zlib.compress(raw))
    path = tmp_path / "anim.png"
    path.write_bytes(_png16_by_hand(image, before=actl + fctl, after=later))
    with pytest.raises(FormatError, match=r"anim\.png: an animated PNG \(APNG\) of 2 frames"):
        read(path)


def test_a_dicom_without_its_preamble_reads_as_pydicom_reads_it(tmp_path):
    """The 128-byte preamble and b'DICM' are missing from files many older tools wrote, and
    pydicom reads them (force=True): so does radiokit, a .dcm whose first bytes are a DICOM
    element's tag; its file meta's syntax where it has one, else the encoding pydicom finds."""
    import io

    import pydicom
    from pydicom.dataset import Dataset

    image = _texture() >> 4  # 12-bit counts
    full = _dicom(tmp_path / "full.dcm", image, bits_stored=12).read_bytes()
    meta_only = tmp_path / "nopreamble.dcm"
    meta_only.write_bytes(full[132:])  # the file meta group first, then the dataset
    got = read(meta_only)
    np.testing.assert_array_equal(got.data[0], image)
    assert got.meta["bit_depth"] == 12
    ds = Dataset()  # a bare dataset, implicit VR little endian, as ACR-NEMA-era tools wrote
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = *image.shape, 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelData = image.astype("<u2").tobytes()
    buf = io.BytesIO()
    pydicom.dcmwrite(buf, ds, implicit_vr=True, little_endian=True)
    bare = tmp_path / "bare.dcm"
    bare.write_bytes(buf.getvalue())
    got = read(bare)
    np.testing.assert_array_equal(got.data[0], image)
    assert (
        got.meta["transfer_syntax"].startswith("Implicit VR Little Endian")
        and "no file meta" in got.meta["transfer_syntax"]
    )


@pytest.mark.parametrize("value", ["0", "", "-2", "2.5"])
def test_a_dicom_number_of_frames_not_a_count(tmp_path, value):
    """NumberOfFrames 0 or empty (invalid; pydicom assumes 1) reads the one frame the pixel data
    holds, without pydicom's warning, which named no file, once per decode; a negative or
    fractional one is refused in one line (-2 was numpy's "negative dimensions are not allowed")."""
    import pydicom

    image = _texture((4, 5))
    path = _dicom(tmp_path / "nf.dcm", image)
    ds = pydicom.dcmread(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom's own say on an IS of 2.5 as it writes
        ds.NumberOfFrames = value
        ds.save_as(path)
    if value in ("0", ""):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            np.testing.assert_array_equal(read(path).data, image[None])
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pydicom's say on reading an IS of 2.5: the refusal is ours
            with pytest.raises(FormatError, match=rf"nf\.dcm: .*NumberOfFrames {value}"):
                read(path)


def test_calibrate_from_monochrome1_darks_and_flats_names_the_inversion(tmp_path):
    """MONOCHROME1 darks and flats (stored 4095 - counts) read as stored put the darks above the
    flats: the refusal blamed light on the panel; it now says which files are MONOCHROME1 and
    what to do, in its one line."""
    rng = np.random.default_rng(5)
    dark = np.round(100 + rng.normal(0, 3, (3, 16, 20))).astype(np.uint16)
    flat = np.round(3000 + rng.normal(0, 30, (3, 16, 20))).astype(np.uint16)
    d = _dicom(tmp_path / "d1.dcm", 4095 - dark, bits_stored=12, photometric="MONOCHROME1")
    f = _dicom(tmp_path / "f1.dcm", 4095 - flat, bits_stored=12, photometric="MONOCHROME1")
    res = run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5")
    assert res.returncode == 2, res.stderr
    refusal = [line for line in res.stderr.splitlines() if "InvertedWarning" not in line]
    assert len(refusal) == 1 and re.search(r"d1\.dcm, \S*f1\.dcm are MONOCHROME1, read as stored", refusal[0])


def test_a_tiny_rle_dicom_declaring_a_gigabyte_is_refused_at_open(tmp_path):
    """RLE (PackBits) encodes at most 128 bytes in 2: a file under 1/64 of the bytes it declares
    cannot hold them, and is refused on opening, within the budget, before the stack is allocated."""
    import pydicom
    from pydicom.uid import RLELossless

    path = _dicom(tmp_path / "rle.dcm", np.stack([_texture((4, 4))] * 2), syntax=RLELossless)
    ds = pydicom.dcmread(path)
    ds.Rows, ds.Columns, ds.NumberOfFrames = 4096, 4096, 32
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"rle\.dcm: .*RLE") as info:
        read(path, budget="2GiB")
    assert "\n" not in str(info.value)


def test_an_rle_frame_that_does_not_decode_is_one_line(tmp_path):
    """pydicom's decode failure is several lines (one per plugin tried): said in one."""
    import pydicom
    from pydicom.uid import RLELossless

    path = _dicom(tmp_path / "rle.dcm", np.stack([_texture((4, 4))] * 2), syntax=RLELossless)
    ds = pydicom.dcmread(path)
    ds.Rows, ds.Columns = 16, 16  # 1 KiB declared: within what RLE may encode in this file
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"rle\.dcm: frame 0 cannot be decoded") as info:
        read(path)
    assert "\n" not in str(info.value)


def _deflate_block_types(stream: bytes) -> set:
    """The BTYPE of each deflate block of a zlib ``stream`` made of stored blocks (0) up to its
    first other block: walking a stored block's LEN is all it takes, no Huffman decoding."""
    pos, types = 2, set()  # past the zlib header
    while True:
        head = stream[pos]
        btype = (head >> 1) & 3
        types.add(btype)
        if btype != 0:
            return types
        (length,) = struct.unpack_from("<H", stream, pos + 1)
        pos += 5 + length
        if head & 1:  # BFINAL
            return types


def _idat_stream(png: bytes) -> bytes:
    """A PNG's IDAT chunks' data, in order: its zlib stream."""
    pos, stream = 8, b""
    while pos < len(png):
        (length,) = struct.unpack_from(">I", png, pos)
        if png[pos + 4 : pos + 8] == b"IDAT":
            stream += png[pos + 8 : pos + 8 + length]
        pos += 12 + length
    return stream


def test_a_png_s_pixels_are_inflated_once(tmp_path, monkeypatch):
    """IDAT's stream is inflated by radiokit's check (it ends where the image does) and then not
    again: OpenCV is handed the inflated rows as stored deflate blocks, which libpng copies.
    Why: the check and libpng each ran the whole Huffman decode (benchmarks/README.md,
    bench_png_read.py). The values are still libpng's unfiltering of the file's rows."""
    import cv2

    image = (_texture((300, 400)) >> 12).astype(np.uint16) + 1000  # a compressible one: random words are stored
    path = _png(tmp_path / "once.png", image)
    handed = []
    decode = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda buf, flags: handed.append(bytes(buf)) or decode(buf, flags))
    np.testing.assert_array_equal(read(path).data[0], image)
    (png,) = handed
    assert _deflate_block_types(_idat_stream(path.read_bytes())) != {0}  # the file's: Huffman-coded
    streams = _idat_stream(png)
    assert _deflate_block_types(streams) == {0}
    assert len(zlib.decompress(streams)) == 300 * (1 + 400 * 2)  # a filter byte and 400 samples a row


def _signed_12(shape=(40, 50), seed=5):
    """A signed 12-bit radiograph: values about 0 +- 600, a patch clipped at the ADC's top (2047)
    and one at its bottom (-2048); the patches' pixel counts returned with it."""
    rng = np.random.default_rng(seed)
    image = np.clip(np.rint(rng.normal(0, 600, shape)), -2000, 2000).astype(np.int16)
    image[:4, :5], image[-3:, -6:] = 2047, -2048
    return image, 4 * 5, 3 * 6


def test_info_says_a_signed_12_bit_dicom_saturates_at_2047_and_minus_2048(tmp_path):
    """PixelRepresentation 1, BitsStored 12: the ADC's range is -2048..2047 (two's complement in 12
    bits), not 0..4095: its clipped pixels at either end are counted, against the levels its own
    values read at. It was judged as unsigned: "0 pixel(s) >= 4095" of a clipped image."""
    image, top, bottom = _signed_12()
    got = read(_dicom(tmp_path / "signed.dcm", image, bits_stored=12, signed=True))
    assert got.data.dtype == np.int16
    np.testing.assert_array_equal(got.data[0], image)
    (rep,) = json.loads(run_cli("info", tmp_path / "signed.dcm", "--json").stdout)
    assert rep["saturation"] == (1 << 11) - 1 and rep["saturation_low"] == -(1 << 11)
    assert rep["saturated"] == top + bottom
    text = run_cli("info", tmp_path / "signed.dcm").stdout
    assert re.search(rf"saturated +{top + bottom} pixel\(s\) >= 2047 or <= -2048 \(declared 12-bit signed\)", text)


def test_a_signed_dicom_s_rescale_takes_its_saturation_levels_with_its_values(tmp_path):
    """RescaleSlope 0.5, RescaleIntercept -1024: the levels are the ADC's ends as the values read
    them (2047 * 0.5 - 1024 and -2048 * 0.5 - 1024), the same pixels counted."""
    image, top, bottom = _signed_12()
    path = _dicom(tmp_path / "ct.dcm", image, bits_stored=12, signed=True, rescale=(0.5, -1024))
    np.testing.assert_allclose(read(path).data[0], image * 0.5 - 1024, rtol=0, atol=1e-12)
    (rep,) = json.loads(run_cli("info", path, "--json").stdout)
    assert rep["saturation"] == pytest.approx(2047 * 0.5 - 1024, abs=1e-6)
    assert rep["saturation_low"] == pytest.approx(-2048 * 0.5 - 1024, abs=1e-6)
    assert rep["saturated"] == top + bottom
    assert rep["saturation_from"].startswith("declared 12-bit signed of the stored counts")
    # unsigned alike: its declared 4095 as the values read it, said as declared (it was said "from
    # the values, above the declared 12-bit range": the scaled top compared with the counts' 4095)
    unsigned = _dicom(tmp_path / "u.dcm", image.astype(np.int32) + 2048, bits_stored=12, rescale=(2, -7))
    (rep,) = json.loads(run_cli("info", unsigned, "--json").stdout)
    assert rep["saturation"] == 4095 * 2 - 7 and "saturation_low" not in rep
    assert rep["saturated"] == top and rep["saturation_from"].startswith("declared 12-bit of the stored counts")


def test_a_calibration_from_signed_12_bit_dicoms_flags_flats_at_2047(tmp_path):
    """Darks and flats of a signed 12-bit panel (read as the Python API reads them, and by the
    command): the saturation level is 2047, the file's word, and the flat's clipped pixels are
    over-responding defects; against 4095 they were not flagged at all."""
    from radiokit.calibrate import Calibration, CalibrationWarning

    rng = np.random.default_rng(7)
    darks = np.rint(rng.normal(-1500, 3, (4, 32, 32))).astype(np.int16)
    flats = np.rint(rng.normal(1900, 15, (4, 32, 32))).astype(np.int16)  # 2047 is 9.8 sigma off
    flats[:, 5, 7] = 2047  # one pixel clipped in every flat: its response (2047 + 1500) / (1900 + 1500) = 1.04
    # is no over-responding pixel's (1.3): only the saturation level flags it
    d = _dicom(tmp_path / "d.dcm", darks, bits_stored=12, signed=True)
    f = _dicom(tmp_path / "f.dcm", flats, bits_stored=12, signed=True)
    with pytest.warns(CalibrationWarning, match=r"1 pixels of the flats are saturated \(>= 2047\)"):
        cal = Calibration.from_frames(read(d), read(f))
    assert cal.thresholds.saturation == 2047 and cal.mask[5, 7] and np.count_nonzero(cal.mask) == 1
    res = run_cli("calibrate", "--dark", d, "--flat", f, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    assert Calibration.load(tmp_path / "cal.h5").thresholds.saturation == 2047


def test_info_prints_one_aligned_table_whatever_its_labels(tmp_path):
    """Files whose items' names differ in length (a DICOM's transfer_syntax and pixel_size_from,
    a PNG's png_bit_depth, the common format and range): every item's value starts in one column,
    past the longest name, over all the files given. A name past 10 characters pushed its value
    out of the column the others kept."""
    image, *_ = _signed_12()
    dcm = _dicom(
        tmp_path / "a_long_file_name_of_a_monochrome1_image.dcm",
        image + 2048,
        photometric="MONOCHROME1",
        spacing=(0.1, 0.1),
    )
    png = _png(tmp_path / "b.png", (_texture() >> 4).astype(np.uint16))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (MONOCHROME1 said on stderr)
        res = run_cli("info", dcm, png)
    assert res.returncode == 0, res.stderr
    reports = json.loads(run_cli("info", dcm, png, "--json").stdout)
    labels = [k for r in reports for k in ("format", "frames", "range", "saturated", *r["metadata"])]
    assert {"transfer_syntax", "pixel_size_from", "png_bit_depth", "format"} <= set(labels)
    width = max(len(k) for k in labels)
    items = [line for line in res.stdout.splitlines() if line.startswith("  ")]
    assert len(items) == len(labels)
    for line, label in zip(items, labels, strict=True):
        assert line[2:].startswith(label), (line, label)
        assert line[2 + len(label) : 3 + width].strip() == "" and line[3 + width] != " ", (line, width)


@pytest.mark.parametrize("declared", [None, 1, 2])
def test_uncompressed_pixels_of_more_frames_than_declared_are_refused_in_one_line(tmp_path, declared):
    """Three frames' bytes of pixel data under a NumberOfFrames absent, 1 or 2 (review s54rvjpg):
    pydicom then returned every frame where one was asked for (allow_excess_frames), so read()
    failed in numpy's "could not broadcast" and `radiokit correct` in a numba traceback. Refused
    in one line naming the file, as a compressed DICOM's extra frames are. A pad byte is no frame."""
    import pydicom

    frames = np.stack([_texture(seed=k) for k in range(3)]) * 1000
    path = _dicom(tmp_path / "x.dcm", frames)
    ds = pydicom.dcmread(path)
    if declared is None:
        del ds.NumberOfFrames
    else:
        ds.NumberOfFrames = declared
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"x\.dcm: .*3 frames.*NumberOfFrames") as info:
        read(path)
    assert "\n" not in str(info.value)
    res = run_cli("info", path)
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    ds.NumberOfFrames = 3
    ds.save_as(path)
    np.testing.assert_array_equal(read(path).data, frames.astype(np.uint16))


def test_rle_fragments_of_more_frames_than_declared_are_refused_in_one_line(tmp_path):
    """Two RLE frames under a NumberOfFrames absent: pydicom returned both where one was asked
    for, and read() failed in numpy's "could not broadcast" (review s54rvjpg). One line instead."""
    import pydicom
    from pydicom.uid import RLELossless

    frames = np.stack([_texture(seed=k) for k in range(2)]) * 1000
    path = _dicom(tmp_path / "r.dcm", frames, syntax=RLELossless)
    ds = pydicom.dcmread(path)
    del ds.NumberOfFrames
    ds.save_as(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom's own, of the excess frames
        with pytest.raises(FormatError, match=r"r\.dcm: frame 0 .*\(2, 40, 50\).*NumberOfFrames") as info:
            read(path)
    assert "\n" not in str(info.value)


# -- review s54rvoff --------------------------------------------------------------------------
def _png_by_hand(image, depth, *, interlace=0, ihdr=None, filter_byte=0):
    """A greyscale PNG of ``depth``-bit samples (1, 2, 4 packed to whole bytes a row, 8, 16),
    written chunk by chunk with each row's filter ``filter_byte`` (0, None; 5 is no PNG filter),
    Adam7 where asked; ``ihdr`` replaces the header's 13 bytes."""
    h, w = image.shape
    passes = [(0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1)]
    subs = [image[y::dy, x::dx] for y, x, dy, dx in passes] if interlace else [image]

    def packed(row):
        if depth >= 8:
            return row.astype(">u2" if depth == 16 else np.uint8).tobytes()
        bits = np.unpackbits(row.astype(np.uint8)[:, None], axis=1)[:, 8 - depth :]  # each sample's low bits
        return np.packbits(bits.ravel()).tobytes()

    raw = b"".join(bytes([filter_byte]) + packed(row) for sub in subs if sub.size for row in sub)
    ihdr = ihdr or struct.pack(">IIBBBBB", w, h, depth, 0, 0, 0, interlace)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


@pytest.mark.parametrize("interlace", [0, 1])
@pytest.mark.parametrize("depth", [1, 2, 4])
def test_a_1_2_or_4_bit_greyscale_png_reads_its_stored_samples(tmp_path, depth, interlace):
    """A sample of ``depth`` bits is a count of 0..2**depth - 1, as the file stores it (and its
    reader declares: ``bit_depth``). libpng's 1/2/4-to-8 expansion (OpenCV asks for it) replicates
    the bits, 1 -> 255 at 1 bit, 3 -> 255 at 2: read so, every value was scaled by 255 / (2**depth
    - 1) and warned of as "exceeding the 1-bit range"."""
    rng = np.random.default_rng(depth)
    image = rng.integers(0, 1 << depth, size=(19, 23), dtype=np.uint8)
    image[0, : 1 << depth] = np.arange(1 << depth)  # every level present
    path = tmp_path / f"g{depth}.png"
    path.write_bytes(_png_by_hand(image, depth, interlace=interlace))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no "values exceed the range" of the file's own samples)
        got = read(path)
    np.testing.assert_array_equal(got.data[0], image)
    assert got.meta["bit_depth"] == depth


@pytest.mark.parametrize(
    "what, ihdr, said",
    [
        pytest.param(*case, id=case[0])
        for case in [
            ("interlace method 2", struct.pack(">IIBBBBB", 23, 19, 16, 0, 0, 0, 2), "interlace method 2"),
            ("compression method 1", struct.pack(">IIBBBBB", 23, 19, 16, 0, 1, 0, 0), "compression method 1"),
            ("filter method 1", struct.pack(">IIBBBBB", 23, 19, 16, 0, 0, 1, 0), "filter method 1"),
            ("RGB of 4 bits", struct.pack(">IIBBBBB", 23, 19, 4, 2, 0, 0, 0), "colour type 2, bit depth 4"),
            ("grey-alpha of 2 bits", struct.pack(">IIBBBBB", 23, 19, 2, 4, 0, 0, 0), "colour type 4, bit depth 2"),
            ("a 14-byte IHDR", struct.pack(">IIBBBBB", 23, 19, 16, 0, 0, 0, 0) + b"\0", "IHDR of 14 bytes"),
            ("1 000 001 columns", struct.pack(">IIBBBBB", 1_000_001, 1, 8, 0, 0, 0, 0), "1000001 x 1"),
            ("a row filter of 5", None, "filter type 5"),
        ]
    ],
)
def test_a_png_libpng_would_refuse_is_one_line_without_libpng_s_own(tmp_path, capfd, what, ihdr, said):
    """An IHDR libpng finds invalid (a method PNG does not define, a colour type and bit depth it
    does not pair, more than libpng's 1 000 000 columns or rows) and a row whose filter type is
    none of PNG's five: libpng printed "libpng warning: ..." and "libpng error: ..." on the
    process's stderr, and radiokit then a line that blamed truncation. One line, the fault named."""
    image = _texture((19, 23))
    path = tmp_path / "bad.png"
    path.write_bytes(_png_by_hand(image, 16, ihdr=ihdr, filter_byte=5 if ihdr is None else 0))
    with pytest.raises(FormatError, match=rf"bad\.png: .*{re.escape(said)}") as info:
        read(path)
    assert "\n" not in str(info.value), what
    assert "libpng" not in capfd.readouterr().err, what


@pytest.mark.parametrize("shape, depth", [((1000, 600), 16), ((200_000, 1), 8)])
def test_a_png_s_memory_budget_counts_what_its_read_holds_at_once(tmp_path, shape, depth):
    """A PNG's read holds the stored-block PNG built of its inflated rows (a filter byte and the
    packed samples of each row) while OpenCV decodes the pixels beside it: about twice the pixels
    of a 16-bit image, three times those of an 8-bit one a pixel wide (a filter byte a sample). A
    budget that counted the decoded pixels alone let a PNG just under it take twice as much. Now
    a budget of the pixels and a byte is refused before anything is inflated, and what the check
    counts covers the decode's traced peak (numpy's and Python's allocations; 64 KiB more for
    zlib's window and Python's objects), and is what a read then needs."""
    import tracemalloc

    from radiokit.io._clinical import decode_png, png_header, png_read_bytes

    image = (_texture(shape) >> (16 - depth)).astype(np.uint16 if depth == 16 else np.uint8)
    path = tmp_path / "tight.png"
    path.write_bytes(_png_by_hand(image, depth))
    with pytest.raises(FormatError, match=r"tight\.png: .*memory budget"):
        read(path, budget=image.nbytes + 1)
    header = png_header(path)
    counted = png_read_bytes(header)
    rows = shape[0] * (1 + shape[1] * depth // 8)  # what the stream inflates to, held with the pixels
    assert counted >= image.nbytes + rows
    tracemalloc.start()
    try:
        pixels = decode_png(path, header)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(pixels, image)
    assert peak <= counted + 2**16, (peak, counted)
    np.testing.assert_array_equal(read(path, budget=counted).data[0], image)


@pytest.mark.parametrize(
    "extra",
    [
        pytest.param(_chunk(b"PLTE", bytes(6)), id="PLTE in greyscale"),
        pytest.param(_chunk(b"tRNS", bytes(4)), id="tRNS of 4 bytes"),
        pytest.param(_chunk(b"tRNS", b"\xff\xfe") + _chunk(b"tRNS", b"\xff\xfd"), id="two tRNS"),
    ],
)
def test_a_png_s_ignored_palette_chunks_read_without_libpng_s_warnings(tmp_path, capfd, extra):
    """A PLTE in a greyscale image, a tRNS of the wrong length, a second tRNS: libpng ignores
    them, saying so on the process's stderr ("libpng warning: tRNS: invalid"). Read as libpng
    reads them, and not heard."""
    image = _texture((19, 23))
    image[image >= 0xFFFD] = 0  # (no sample the tRNS names: opaque everywhere)
    data = _png_by_hand(image, 16)
    at = data.index(b"IDAT") - 4
    path = tmp_path / "extra.png"
    path.write_bytes(data[:at] + extra + data[at:])
    np.testing.assert_array_equal(read(path).data[0], image)
    assert "libpng" not in capfd.readouterr().err


@pytest.mark.parametrize("dark_level, bright", [(500, True), (-1500, False)])
def test_a_signed_panel_s_darks_over_half_its_range_are_bright(tmp_path, dark_level, bright):
    """A signed 12-bit ADC spans -2048..2047: darks at 500 stand 2548 counts above its bottom, past
    half its 4096 counts, and leave the flats 1547: bright, as 2548-count darks of an unsigned
    12-bit panel are. Judged as though the range began at 0 (its half 1023.5), they were not; darks
    at -1500 (548 above the bottom: a C7942's offset) are not."""
    from radiokit.calibrate import Calibration, CalibrationWarning

    rng = np.random.default_rng(11)
    darks = np.rint(rng.normal(dark_level, 3, (4, 32, 32))).astype(np.int16)
    flats = np.rint(rng.normal(1900, 15, (4, 32, 32))).astype(np.int16)
    d = _dicom(tmp_path / "d.dcm", darks, bits_stored=12, signed=True)
    f = _dicom(tmp_path / "f.dcm", flats, bits_stored=12, signed=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CalibrationWarning)
        Calibration.from_frames(read(d), read(f))
    said = [str(w.message) for w in caught if "over half the ADC's range" in str(w.message)]
    assert bool(said) == bright, said
    if bright:
        assert "(-2048 to 2047)" in said[0] and f"leaving the flats {2047 - dark_level} counts" in said[0]


@pytest.mark.parametrize("interlace", [0, 1])
def test_the_png_handed_to_opencv_keeps_each_idat_within_a_chunk_s_most(tmp_path, monkeypatch, interlace):
    """A PNG chunk holds at most 2**31 - 1 bytes (libpng refuses longer ones): the stored-block
    PNG built for OpenCV held all the rows in one IDAT, past that for a 16-bit image past 32768 x
    32768 (struct.error or libpng's "PNG unsigned integer out of range"). Such an image takes
    GiBs, so the bound is lowered here to one stored block and its headers (a fake of the limit:
    the fault cannot be caused within a test's memory): every IDAT within it, the values exact."""
    import cv2

    import radiokit.io._clinical as clinical

    most = 65535 + 5 + 6  # one stored block, its header, and the zlib header or Adler-32
    monkeypatch.setattr(clinical, "_CHUNK_MOST", most)
    image = _texture((400, 300))  # 400 x 601 bytes of rows: 4 stored blocks
    path = tmp_path / "many.png"
    path.write_bytes(_png16_by_hand(image, interlace=interlace))
    handed = []
    decode = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda buf, flags: handed.append(bytes(buf)) or decode(buf, flags))
    np.testing.assert_array_equal(read(path).data[0], image)
    (png,) = handed
    pos, lengths = 8, []
    while pos < len(png):
        (length,) = struct.unpack_from(">I", png, pos)
        if png[pos + 4 : pos + 8] == b"IDAT":
            lengths.append(length)
        pos += 12 + length
    assert len(lengths) >= 4 and max(lengths) <= most, lengths


def _deflated_zeros(path, side):
    """A deflated DICOM of one ``side`` x ``side`` frame of zeros (deflate's 1:1000 of a constant
    image: a few KB of file)."""
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    return _dicom(path, np.zeros((side, side), np.uint16), syntax=DeflatedExplicitVRLittleEndian)


def test_a_deflated_dicom_is_refused_by_the_budget_before_it_is_inflated(tmp_path):
    """pydicom inflates a deflated dataset whole as it opens it (zlib.decompress of the rest of the
    file), before radiokit reads any header: a 2000 x 2000 frame of zeros, 8 MB in a file of a few
    KB, took 21 MiB under a budget of 2 MiB before it was refused. The inflated size is counted in
    pieces, none kept, and refused before pydicom takes it: under the budget (plus Python's own
    allocations: a 1 MiB inflating piece at most, 10 %), and one line naming the file."""
    import tracemalloc

    path = _deflated_zeros(tmp_path / "bomb.dcm", 2000)
    assert path.stat().st_size < 64 * 1024
    budget = 2 * 2**20
    tracemalloc.start()
    try:
        with pytest.raises(FormatError) as info:
            read(path, budget=budget)
        held = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert held < 1.1 * budget, held
    assert re.search(r"bomb\.dcm: .*inflate.*over the memory budget", str(info.value)), str(info.value)
    assert "\n" not in str(info.value)
    np.testing.assert_array_equal(read(path, budget="64MiB").data[0], 0)  # one that fits reads


def test_a_deflated_dicom_out_of_all_proportion_is_a_bomb_without_a_budget(tmp_path, monkeypatch):
    """With no budget given, inflated data past 1:200 and past BOMB_FILE_BYTES (lowered here to
    2 MiB, as the other bomb tests lower it) is refused as a decompression bomb, as every other
    compressed format's: under a large machine's budget a 16 MB deflated DICOM of zeros inflated
    to 16 GB. A noisy deflated frame of the same size still reads."""
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    from radiokit.io import _budget

    monkeypatch.delenv(_budget.BUDGET_ENV, raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 2 * 2**20)
    zeros = _deflated_zeros(tmp_path / "zeros.dcm", 1100)  # (2.4 MB inflated)
    with pytest.raises(FormatError, match=r"zeros\.dcm: .*decompression bomb") as info:
        read(zeros)
    assert "\n" not in str(info.value)
    # the budget it suggests reads it (the inflate holds two to three times the dataset: a
    # quarter over the dataset alone was refused again, by the budget)
    suggested = re.search(r"RADIOKIT_MEMORY_BUDGET=(\w+)", str(info.value)).group(1)
    np.testing.assert_array_equal(read(zeros, budget=suggested).data[0], 0)
    noisy = np.random.default_rng(4).integers(0, 4096, (1100, 1100)).astype(np.uint16)
    path = _dicom(tmp_path / "noisy.dcm", noisy, syntax=DeflatedExplicitVRLittleEndian)
    np.testing.assert_array_equal(read(path).data[0], noisy)


def test_a_deflated_dicom_cut_short_is_said_truncated_in_one_line(tmp_path):
    """Its deflate stream cut: zlib's own "Error -5 while decompressing data: incomplete or
    truncated stream" was the message, through a catch-all."""
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    frame = np.random.default_rng(5).integers(0, 4096, (64, 64)).astype(np.uint16)
    whole = _dicom(tmp_path / "whole.dcm", frame, syntax=DeflatedExplicitVRLittleEndian).read_bytes()
    path = tmp_path / "cut.dcm"
    path.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(FormatError, match=r"cut\.dcm: .*deflate.*truncated") as info:
        read(path)
    assert "Error -5" not in str(info.value) and "\n" not in str(info.value)


def test_a_big_endian_dicom_s_budget_counts_its_byte_swapped_copy(tmp_path):
    """A big-endian frame is copied to the machine's byte order as pydicom decodes it: one more
    frame held beside the frame read than a little-endian file's, which the budget did not count
    (0.75 of the traced peak for one frame). Refused 10 % under the peak, read 10 % over it."""
    import tracemalloc

    import pydicom
    from pydicom.uid import ExplicitVRBigEndian

    image = np.random.default_rng(11).integers(0, 4096, (512, 512)).astype(np.uint16)
    path = _dicom(tmp_path / "be.dcm", image, bits_stored=12)
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = ExplicitVRBigEndian
    ds.PixelData = image.astype(">u2").tobytes()
    pydicom.dcmwrite(path, ds, little_endian=False, implicit_vr=False, enforce_file_format=True)
    read(path)  # (its modules imported before the peak is traced)
    tracemalloc.start()
    try:
        read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    with pytest.raises(FormatError, match=r"be\.dcm: .*over the memory budget"):
        read(path, budget=int(0.9 * peak))
    np.testing.assert_array_equal(read(path, budget=int(1.1 * peak)).data[0], image)


def test_a_multi_frame_dicom_streamed_is_not_charged_the_stack_it_never_holds(tmp_path):
    """open_frames reads a stack a frame at a time: a DICOM streamed holds its pixel element
    (pydicom reads it whole) and one frame, never the stack. Its open was charged the stack too,
    and a file that streams under a budget 10 % over its traced peak was refused; read() holds
    the stack as well, and is still refused under that budget."""
    import tracemalloc

    frames = np.random.default_rng(12).integers(0, 4096, (16, 256, 256)).astype(np.uint16)
    path = _dicom(tmp_path / "stack.dcm", frames, bits_stored=12)

    def stream(budget=None):
        with open_frames(path, budget=budget) as src:
            for i, frame in enumerate(src):
                np.testing.assert_array_equal(frame, frames[i])

    stream()  # (its modules imported before the peak is traced)
    tracemalloc.start()
    try:
        stream()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    stream(budget=int(1.1 * peak))
    with pytest.raises(FormatError, match=r"stack\.dcm: .*over the memory budget"):
        read(path, budget=int(1.1 * peak))


def test_a_deflated_dicom_whose_file_meta_is_implicit_vr_is_held_to_the_budget_too(tmp_path):
    """A writer's file meta in implicit VR (against PS3.10, which pydicom reads all the same): its
    elements have no VR, and the walk to the deflated dataset stopped at the first, so the bomb
    check was passed over and pydicom inflated the whole dataset (21 MiB under a 2 MiB budget)."""
    import tracemalloc

    import pydicom

    path = _deflated_zeros(tmp_path / "bomb.dcm", 2000)
    whole, meta = path.read_bytes(), pydicom.dcmread(path).file_meta
    elements = b""
    for element in meta:
        if element.tag != 0x00020000:
            value = element.value if isinstance(element.value, bytes) else str(element.value).encode()
            value += b"\0" * (len(value) % 2)
            elements += struct.pack("<HHI", element.tag.group, element.tag.elem, len(value)) + value
    explicit_end = 132 + 12 + meta.FileMetaInformationGroupLength
    implicit = tmp_path / "implicit.dcm"
    implicit.write_bytes(whole[:132] + struct.pack("<HHII", 2, 0, 4, len(elements)) + elements + whole[explicit_end:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (pydicom's "Expected explicit VR, but found implicit VR")
        assert pydicom.dcmread(implicit).file_meta.TransferSyntaxUID == meta.TransferSyntaxUID
        read(implicit)  # (its modules imported before the peak is traced)
        tracemalloc.start()
        try:
            with pytest.raises(FormatError, match=r"implicit\.dcm: .*inflate.*over the memory budget"):
                read(implicit, budget=2 * 2**20)
            held = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert held < 1.1 * 2 * 2**20, held
