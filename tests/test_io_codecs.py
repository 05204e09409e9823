"""Compressed radiographs as archives and public datasets hand them over: DICOM in JPEG Lossless,
JPEG-LS, JPEG 2000, HTJ2K and JPEG baseline/extended transfer syntaxes, and plain .jpg / .jls /
.j2k / .jp2 files. Every file is written here by the encoders that make such files (imagecodecs'
libjpeg-turbo, CharLS, OpenJPEG) and pydicom's encapsulation. A lossless codec gives back every
count exactly; a lossy one within the bound its own parameters set (JPEG-LS's NEAR, JPEG's
quantisation tables, JPEG 2000's PSNR target)."""

import json
import struct
import warnings

import imagecodecs
import numpy as np
import pytest
from pydicom import uid

from radiokit.io import FormatError, LossyWarning, open_frames, read
from tests.conftest import run_cli

SHAPE = (48, 64)


def _counts(n=3, seed=5):
    """``n`` frames of 12-bit counts: a smooth field (what the DCT and wavelet codecs are made for)
    plus noise, 100..3900 (a lossy codec's overshoot stays inside 12 bits)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[: SHAPE[0], : SHAPE[1]]
    frames = [2000 + 1500 * np.sin(x / (6 + k)) * np.cos(y / 9) + rng.normal(0, 40, SHAPE) for k in range(n)]
    return np.clip(np.round(frames), 100, 3900).astype(np.uint16)


def _dicom(path, frames, syntax, encode, *, signed=False, bits=12, allocated=16, lossy_said=None, rescale=None):
    """A DX DICOM of ``frames``, each encoded by ``encode`` and encapsulated one fragment a frame."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.encaps import encapsulate

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.1.1"
    meta.MediaStorageSOPInstanceUID = uid.generate_uid()
    meta.TransferSyntaxUID = syntax
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID, "DX"
    ds.Rows, ds.Columns = frames.shape[-2:]
    ds.NumberOfFrames = len(frames)
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = allocated, bits, bits - 1, int(signed)
    if lossy_said:
        ds.LossyImageCompression = lossy_said
    if rescale:
        ds.RescaleSlope, ds.RescaleIntercept = rescale
    ds.PixelData = encapsulate([encode(f) for f in frames])
    ds["PixelData"].VR = "OB"
    ds.save_as(path, enforce_file_format=True)
    return path


def _quiet_read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a lossless file warns of nothing
        return read(path)


LOSSLESS = {
    "sv1": (uid.JPEGLosslessSV1, lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12)),
    # Process 14 with predictor 7 ((Ra + Rb) / 2): a selection value other than 1
    "p14": (
        uid.JPEGLossless,
        lambda f: imagecodecs.jpeg8_encode(f, lossless=True, bitspersample=12, predictor=7),
    ),
    "jls": (uid.JPEGLSLossless, lambda f: imagecodecs.jpegls_encode(f)),
    "j2k": (
        uid.JPEG2000Lossless,
        lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12),
    ),
    "htj2k": (uid.HTJ2KLossless, lambda f: imagecodecs.htj2k_encode(f, level=0)),
}


@pytest.mark.parametrize("name", sorted(LOSSLESS))
def test_a_lossless_compressed_dicom_gives_back_every_count(tmp_path, name):
    """Three 12-bit frames in each lossless syntax: read whole and frame by frame, bit-exact, no warning."""
    syntax, encode = LOSSLESS[name]
    stack = _counts()
    path = _dicom(tmp_path / f"{name}.dcm", stack, syntax, encode)
    got = _quiet_read(path)
    assert got.data.dtype == np.uint16 and got.meta["bit_depth"] == 12
    np.testing.assert_array_equal(got.data, stack)
    assert got.meta["transfer_syntax"].startswith(syntax.name) and "lossy" not in got.meta
    with open_frames(path) as src:
        np.testing.assert_array_equal(src[2], stack[2])


@pytest.mark.parametrize("name", ["sv1", "j2k"])
def test_signed_compressed_pixels_are_sign_extended_and_rescaled(tmp_path, name):
    """PixelRepresentation 1: lossless JPEG holds the 12-bit two's-complement patterns (unsigned to
    its decoder, sign-extended here); JPEG 2000 says signed in its SIZ. The Modality LUT follows as
    for uncompressed pixels."""
    signed = _counts(n=1).astype(np.int16) - 2048
    encode = {
        "sv1": lambda f: imagecodecs.ljpeg_encode(f.view(np.uint16) & 0xFFF, bitspersample=12),
        "j2k": lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12),
    }[name]
    syntax = LOSSLESS[name][0]
    path = _dicom(tmp_path / "s.dcm", signed, syntax, encode, signed=True, rescale=(2, -10))
    got = _quiet_read(path)
    assert got.data.dtype == np.int32
    np.testing.assert_array_equal(got.data, signed.astype(np.int32) * 2 - 10)


def test_jpeg_ls_near_lossless_is_within_near_and_says_it_is_lossy(tmp_path):
    """JPEG-LS's NEAR bounds every sample's error (T.87): |decoded - counts| <= NEAR, once said."""
    near = 3
    stack = _counts()
    path = _dicom(tmp_path / "n.dcm", stack, uid.JPEGLSNearLossless, lambda f: imagecodecs.jpegls_encode(f, level=near))
    with pytest.warns(LossyWarning, match=r"n\.dcm: a DICOM file compressed as JPEG-LS Lossy .*lossy codec") as said:
        got = read(path)
    assert len([w for w in said if "lossy codec" in str(w.message)]) == 1
    err = np.abs(got.data.astype(np.int64) - stack)
    assert err.max() <= near and err.max() > 0
    assert "permits lossy" in got.meta["lossy"]


def _dqt_rms_bound(stream: bytes) -> float:
    """The RMS error a JPEG's own quantisation tables allow: each DCT coefficient is off by at most
    half its step, and the 8x8 DCT is orthonormal, so the block's mean squared error is at most
    mean(Q^2) / 4; one more count for the integer transforms' and the output's rounding."""
    pos, worst = 2, 0.0
    while stream[pos] == 0xFF and stream[pos + 1] != 0xDA:
        length = struct.unpack(">H", stream[pos + 2 : pos + 4])[0]
        if stream[pos + 1] == 0xDB:  # DQT: tables of 64 8- or 16-bit steps
            seg, i = stream[pos + 4 : pos + 2 + length], 0
            while i < len(seg):
                wide = seg[i] >> 4
                q = np.frombuffer(seg[i + 1 : i + 1 + 64 * (1 + wide)], ">u2" if wide else "u1").astype(float)
                worst = max(worst, float(np.sqrt(np.mean(q**2) / 4)))
                i += 1 + 64 * (1 + wide)
        pos += 2 + length
    return worst + 1


@pytest.mark.parametrize("bits, syntax", [(8, uid.JPEGBaseline8Bit), (12, uid.JPEGExtended12Bit)])
def test_jpeg_baseline_and_12_bit_extended_are_within_their_quantisation(tmp_path, bits, syntax):
    stack = _counts() >> (12 - bits)
    stack = stack.astype(np.uint8 if bits == 8 else np.uint16)
    streams = [imagecodecs.jpeg8_encode(f, level=90, bitspersample=bits) for f in stack]
    path = _dicom(tmp_path / "b.dcm", stack, syntax, lambda f: streams.pop(0), bits=bits, allocated=bits + bits % 8)
    bound = _dqt_rms_bound(imagecodecs.jpeg8_encode(stack[0], level=90, bitspersample=bits))
    with pytest.warns(UserWarning, match=r"b\.dcm: .*JPEG .*lossy codec"):
        got = read(path)
    assert got.data.dtype == stack.dtype
    for frame, counts in zip(got.data, stack):
        rms = float(np.sqrt(np.mean((frame.astype(float) - counts) ** 2)))
        assert 0 < rms <= bound, (rms, bound)


def test_jpeg_2000_lossy_meets_its_psnr_target(tmp_path):
    """imagecodecs' JPEG 2000 level is OpenJPEG's distortion target, a PSNR in dB (of the 12-bit range)."""
    stack = _counts()
    target = 50
    encode = lambda f: imagecodecs.jpeg2k_encode(f, level=target, codecformat="J2K", bitspersample=12)
    path = _dicom(tmp_path / "l.dcm", stack, uid.JPEG2000, encode)
    with pytest.warns(UserWarning, match=r"l\.dcm: .*JPEG 2000 Image Compression .*permits lossy"):
        got = read(path)
    mse = np.mean((got.data.astype(float) - stack) ** 2)
    assert 0 < mse and 10 * np.log10(4095**2 / mse) >= target - 1


def test_a_lossless_syntax_whose_header_says_it_was_lossy_before_warns(tmp_path):
    stack = _counts(n=1)
    path = _dicom(tmp_path / "re.dcm", stack, *LOSSLESS["sv1"], lossy_said="01")
    with pytest.warns(UserWarning, match=r"re\.dcm: .*LossyImageCompression says"):
        np.testing.assert_array_equal(read(path).data, stack)


def test_a_lossy_stream_under_a_lossless_syntax_is_said(tmp_path):
    """A writer's mislabel: baseline (DCT) streams under JPEG Lossless SV1. The stream is what was
    stored: read, and said to be lossy."""
    stack = (_counts(n=2) >> 4).astype(np.uint8)
    encode = lambda f: imagecodecs.jpeg8_encode(f, level=90)
    path = _dicom(tmp_path / "mis.dcm", stack, uid.JPEGLosslessSV1, encode, bits=8, allocated=8)
    with pytest.warns(LossyWarning, match=r"mis\.dcm: its frames are JPEG baseline.*says lossless") as said:
        got = read(path)
    assert len([w for w in said if w.category is LossyWarning]) == 1
    assert got.data.shape == stack.shape


@pytest.mark.parametrize(
    "name, damage, said",
    [
        ("sv1", "markers", "cannot be decoded: .*marker"),  # 0xFF bytes where entropy-coded data should be
        ("sv1", "cut", "without its end marker .*truncated"),  # a fragment cut short, its item length kept
        ("j2k", "cut", "without its end marker .*truncated"),
        ("jls", "markers", "cannot be decoded"),
    ],
)
def test_a_corrupt_fragment_is_one_line_naming_the_file(tmp_path, capfd, name, damage, said):
    """A damaged frame: one error line naming the file and frame, nothing of the codec's own on the
    process's stderr; the other frames still read."""
    stack = _counts(n=2)
    syntax, encode = LOSSLESS[name]
    first = bytearray(encode(stack[0]))
    if damage == "markers":
        first[len(first) // 3 : len(first) // 3 + 200] = b"\xff" * 200
    else:
        first = first[: len(first) // 2]
    frames = [bytes(first), encode(stack[1])]
    path = _dicom(tmp_path / "bad.dcm", stack, syntax, lambda f: frames.pop(0))
    with open_frames(path) as src:
        with pytest.raises(FormatError, match=rf"bad\.dcm: frame 0 .*{said}") as info:
            src[0]
        np.testing.assert_array_equal(src[1], stack[1])
    assert "\n" not in str(info.value)
    assert capfd.readouterr().err == ""


def test_a_fragment_whose_header_is_not_the_dicom_s_image_is_refused_before_decoding(tmp_path):
    """A 40-byte JPEG whose SOF declares 60000 x 60000 in a DICOM of 48 x 64: its decoder would
    allocate 7.2 GB; the SOF is read and refused first."""
    stream = bytearray(imagecodecs.ljpeg_encode(_counts(n=1)[0], bitspersample=12))
    sof = stream.index(b"\xff\xc3")
    stream[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)
    path = _dicom(tmp_path / "lie.dcm", _counts(n=1), uid.JPEGLosslessSV1, lambda f: bytes(stream))
    with pytest.raises(
        FormatError, match=r"lie\.dcm: frame 0 is a JPEG lossless.* 60000x60000, where the DICOM"
    ) as info:
        read(path)
    assert "\n" not in str(info.value)


def test_a_frame_wider_than_bits_allocated_is_refused_and_one_wider_than_bits_stored_read(tmp_path):
    """A 16-bit JPEG-LS stream cannot be held in BitsAllocated 8: refused before decoding. One of
    16 bits for BitsStored 12 (writers do this: CharLS's default, OpenJPEG's for uint16) is read, its
    values judged against BitsStored as any DICOM's are."""
    counts = _counts(n=1)
    wide = _dicom(tmp_path / "wide.dcm", counts, uid.JPEGLSLossless, imagecodecs.jpegls_encode, bits=8, allocated=8)
    with pytest.raises(FormatError, match=r"wide\.dcm: frame 0 is a JPEG-LS NEAR 0, 16-bit.* in 8-bit words"):
        read(wide)
    assert bytes_header_precision(counts[0]) == 16  # what CharLS wrote: the 12-bit file below is 16-bit inside
    np.testing.assert_array_equal(_quiet_read(_dicom(tmp_path / "ok.dcm", counts, *LOSSLESS["jls"])).data, counts)


def bytes_header_precision(frame) -> int:
    from radiokit.io._codecs import bytes_header

    return bytes_header(imagecodecs.jpegls_encode(frame))["precision"]


def test_a_compressed_dicom_declaring_60000_by_60000_is_refused_by_the_budget(tmp_path, monkeypatch):
    """Refused from its header: against a given budget, and under the default one (a fraction of
    the machine, which may hold 7.2 GB) by the proportion of its few KB to what they would decode
    to, as a compressed TIFF is, before any frame is decoded; each frame's own SOF agreeing with
    Rows x Columns (encoded so here) would otherwise be decoded."""
    from radiokit.io import BUDGET_ENV

    monkeypatch.delenv(BUDGET_ENV, raising=False)
    path = _dicom(tmp_path / "big.dcm", _counts(n=1), *LOSSLESS["sv1"])
    import pydicom

    ds = pydicom.dcmread(path)
    ds.Rows, ds.Columns = 60000, 60000
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"big\.dcm: .*1 frame\(s\) of 60000x60000.*memory budget") as info:
        read(path, budget="1GiB")
    assert "\n" not in str(info.value)
    with pytest.raises(
        FormatError, match=r"big\.dcm: .*60000x60000 uint16 would decode to .*decompression bomb"
    ) as info:
        read(path)
    assert "\n" not in str(info.value)


def test_syntaxes_still_not_decoded_are_refused_by_name(tmp_path):
    path = _dicom(tmp_path / "mc.dcm", _counts(n=1), uid.JPEG2000MC, LOSSLESS["j2k"][1])
    with pytest.raises(FormatError, match=r"mc\.dcm: a DICOM file compressed as JPEG 2000 Part 2") as info:
        read(path)
    assert "gdcmconv --raw" in str(info.value) and "\n" not in str(info.value)


# -- plain JPEG, JPEG-LS and JPEG 2000 files ------------------------------------------------------
PLAIN = {
    "lossless.jpg": lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12),
    "frame.jls": lambda f: imagecodecs.jpegls_encode(f),
    "frame.j2k": lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12),
    "frame.jp2": lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="JP2", bitspersample=12),
    "frame.jph": lambda f: imagecodecs.htj2k_encode(f, level=0),
}


@pytest.mark.parametrize("name", sorted(PLAIN))
def test_a_lossless_jpeg_or_jpeg_2000_file_gives_back_every_count(tmp_path, name):
    counts = _counts(n=1)[0]
    path = tmp_path / name
    path.write_bytes(PLAIN[name](counts))
    got = _quiet_read(path)
    assert got.data.shape == (1, *SHAPE) and got.data.dtype == np.uint16
    np.testing.assert_array_equal(got.data[0], counts)
    assert got.meta["format"] == ("jpeg" if name.endswith((".jpg", ".jls")) else "jpeg2000")
    # (a reversible JPEG 2000 is lossless only where no bit-plane was cut, which no header says)
    assert got.meta["compression"].endswith("lossless" if name.endswith((".jpg", ".jls")) else "does not say")


def test_a_baseline_jpeg_file_reads_within_its_quantisation_and_says_it_is_lossy(tmp_path):
    """An 8-bit chest X-ray as public datasets give it."""
    counts = (_counts(n=1)[0] >> 4).astype(np.uint8)
    stream = imagecodecs.jpeg8_encode(counts, level=85)
    path = tmp_path / "chest.jpeg"
    path.write_bytes(stream)
    with pytest.warns(UserWarning, match=r"chest\.jpeg: a JPEG baseline, 8-bit.*lossy codec"):
        got = read(path)
    assert got.data.dtype == np.uint8
    rms = float(np.sqrt(np.mean((got.data[0].astype(float) - counts) ** 2)))
    assert 0 < rms <= _dqt_rms_bound(stream)


def test_a_jpeg_opencv_writes_reads_as_one_frame(tmp_path):
    """OpenCV's imwrite (its own libjpeg build, as a viewer's export): a once-said lossy 8-bit frame,
    within its quantisation."""
    import cv2

    counts = (_counts(n=1)[0] >> 4).astype(np.uint8)
    path = tmp_path / "export.jpg"
    assert cv2.imwrite(str(path), counts, [cv2.IMWRITE_JPEG_QUALITY, 90])
    with pytest.warns(UserWarning, match=r"export\.jpg: a JPEG baseline, 8-bit, 1 component"):
        got = read(path)
    rms = float(np.sqrt(np.mean((got.data[0].astype(float) - counts) ** 2)))
    assert 0 < rms <= _dqt_rms_bound(path.read_bytes())


def test_a_colour_jpeg_of_a_grey_image_is_one_channel_and_of_colours_refused(tmp_path):
    """A grey radiograph saved as YCbCr has neutral chroma, decoded to R = G = B: one channel, the
    same as the greyscale JPEG's. A colour image's channels differ: refused in one line."""
    counts = (_counts(n=1)[0] >> 4).astype(np.uint8)
    grey_path, colour_path, mono_path = tmp_path / "g.jpg", tmp_path / "c.jpg", tmp_path / "m.jpg"
    grey_path.write_bytes(imagecodecs.jpeg8_encode(np.dstack([counts] * 3), level=95))
    mono_path.write_bytes(imagecodecs.jpeg8_encode(counts, level=95))
    colour_path.write_bytes(imagecodecs.jpeg8_encode(np.dstack([counts, counts, counts // 2]), level=95))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # lossy: said, and tested above
        np.testing.assert_array_equal(read(grey_path).data, read(mono_path).data)
        with pytest.raises(FormatError, match=r"c\.jpg: a colour JPEG .*channels differ") as info:
            read(colour_path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["bomb.jpg", "bomb.j2k"])
def test_a_file_declaring_60000_by_60000_is_refused_from_its_header(tmp_path, monkeypatch, name):
    """A few-KB file whose SOF (SIZ) declares 60000 x 60000: refused against the budget before the
    codec allocates anything."""
    from radiokit.io import BUDGET_ENV

    stream = bytearray(PLAIN["lossless.jpg" if name.endswith("jpg") else "frame.j2k"](_counts(n=1)[0]))
    if name.endswith("jpg"):
        sof = stream.index(b"\xff\xc3")
        stream[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)
    else:  # SIZ's Xsiz, Ysiz
        stream[8:16] = struct.pack(">II", 60000, 60000)
    path = tmp_path / name
    path.write_bytes(bytes(stream))
    with pytest.raises(FormatError, match=rf"{name.replace('.', '[.]')}: .*60000x60000 12-bit.*memory budget") as info:
        read(path, budget="1GiB")
    assert "\n" not in str(info.value)
    # under the default budget (half the machine's memory, which may hold it): by its proportion
    # (or by the budget, where OpenJPEG's own 32-bit image of it passes that)
    monkeypatch.delenv(BUDGET_ENV, raising=False)
    with pytest.raises(
        FormatError, match=rf"{name.replace('.', '[.]')}: .*(decompression bomb|over the memory budget)"
    ) as info:
        read(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name, said", [("x.jpg", "no JPEG signature"), ("x.jp2", "no JPEG 2000 signature")])
def test_a_jpeg_name_without_its_signature_is_refused_not_read_as_raw(tmp_path, name, said):
    path = tmp_path / name
    path.write_bytes(bytes(200))
    with pytest.raises(FormatError, match=rf"{name.replace('.', '[.]')}: {said}"):
        read(path)


def test_a_truncated_jpeg_file_is_one_line(tmp_path, capfd):
    path = tmp_path / "cut.jpg"
    stream = PLAIN["lossless.jpg"](_counts(n=1)[0])
    path.write_bytes(stream[: len(stream) // 2])
    with pytest.raises(FormatError, match=r"cut\.jpg: a JPEG lossless.*without its end marker") as info:
        read(path)
    assert "\n" not in str(info.value) and capfd.readouterr().err == ""


def test_info_and_register_take_jpeg_files(tmp_path):
    """``info`` names the codec; ``register`` takes two JPEG 2000 files as it takes two PNGs."""
    from scipy import ndimage

    from radiokit.io import read_registration
    from radiokit.register import warp

    path = tmp_path / "a.jp2"
    path.write_bytes(PLAIN["frame.jp2"](_counts(n=1)[0]))
    res = run_cli("info", path, "--json")
    assert res.returncode == 0, res.stderr
    assert "JPEG 2000 reversible 5/3" in json.dumps(json.loads(res.stdout))
    rng = np.random.default_rng(11)
    base = ndimage.gaussian_filter(rng.random((96, 128)), 3)
    base = (base - base.min()) / np.ptp(base)
    shift = np.stack([np.full((96, 128), 0.6), np.full((96, 128), -1.3)]).astype(np.float32)
    for name, image in (("f.j2k", warp(base.astype(np.float32), shift)), ("m.j2k", base)):
        counts = np.round(image * 60000).astype(np.uint16)
        (tmp_path / name).write_bytes(imagecodecs.jpeg2k_encode(counts, level=0, codecformat="J2K"))
    res = run_cli("register", tmp_path / "f.j2k", tmp_path / "m.j2k", "--preset", "fast", "-o", tmp_path / "r.h5")
    assert res.returncode in (0, 1), res.stderr
    d = read_registration(tmp_path / "r.h5").displacement[:, 16:-16, 16:-16]
    assert abs(float(np.median(d[0])) - 0.6) < 0.1 and abs(float(np.median(d[1])) + 1.3) < 0.1


def test_calibrate_and_correct_take_compressed_frames(tmp_path):
    """Darks and flats as JPEG 2000, a projection as JPEG-LS (both lossless): the transmission is
    (proj - dark) / (flat - dark) of the counts written, 0.5 here to the frames' noise."""
    rng = np.random.default_rng(2)
    paths = {"dark": [], "flat": []}
    for kind, level in (("dark", 100), ("flat", 3000)):
        for k in range(3):
            path = tmp_path / f"{kind}{k}.j2k"
            counts = np.round(rng.normal(level, 3, SHAPE)).astype(np.uint16)
            path.write_bytes(imagecodecs.jpeg2k_encode(counts, level=0, codecformat="J2K"))
            paths[kind].append(path)
    proj = tmp_path / "proj.jls"
    proj.write_bytes(imagecodecs.jpegls_encode(np.round(rng.normal(1550, 3, SHAPE)).astype(np.uint16)))
    res = run_cli("calibrate", "--dark", *paths["dark"], "--flat", *paths["flat"], "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    res = run_cli("correct", proj, "--cal", tmp_path / "cal.h5", "--domain", "linear", "-o", tmp_path / "t.h5")
    assert res.returncode == 0, res.stderr
    t = read(tmp_path / "t.h5").data
    assert abs(float(np.median(t)) - 0.5) < 0.005


@pytest.mark.parametrize("name", sorted(PLAIN) + ["baseline.jpg"])
def test_damaged_headers_are_one_line_refusals(tmp_path, capfd, name):
    """Every byte of the first 64 (the codestream's header: SOF, SIZ, JP2's boxes) set to 0x00 and
    to 0xFF in turn: each file reads, or is refused in one FormatError line naming it; no other
    exception, no stderr."""
    counts = _counts(n=1)[0]
    if name == "baseline.jpg":
        stream = imagecodecs.jpeg8_encode((counts >> 4).astype(np.uint8), level=90)
    else:
        stream = PLAIN[name](counts)
    path = tmp_path / name
    for at in range(min(64, len(stream))):
        for value in (0x00, 0xFF):
            damaged = bytearray(stream)
            damaged[at] = value
            path.write_bytes(bytes(damaged))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    read(path, budget="64MiB")
                except FormatError as exc:
                    assert name in str(exc) and "\n" not in str(exc), (at, value, str(exc))
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("name", ["sv1", "jls", "j2k"])
def test_damaged_frame_headers_in_a_dicom_are_one_line_refusals(tmp_path, capfd, name):
    """As above, in a DICOM frame's codestream: read, or one FormatError line naming the file."""
    syntax, encode = LOSSLESS[name]
    counts = _counts(n=1)
    stream = encode(counts[0])
    path = tmp_path / f"{name}.dcm"
    for at in range(0, min(64, len(stream)), 2):
        damaged = bytearray(stream)
        damaged[at] ^= 0xFF
        _dicom(path, counts, syntax, lambda f, d=bytes(damaged): d)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                read(path)
            except FormatError as exc:
                assert path.name in str(exc) and "\n" not in str(exc), (at, str(exc))
    assert capfd.readouterr().err == ""


# -- review s54rvjpg: writers' conventions and damaged files --------------------------------------
@pytest.mark.parametrize("name", ["sv1", "jls", "j2k"])
def test_a_truncated_compressed_dicom_is_said_to_be_truncated(tmp_path, name):
    """A compressed DICOM cut short (a copy or transfer interrupted) loses its encapsulated pixel
    element's sequence delimiter; pydicom then drops the element with a warning of its own. That
    is a truncated image, not "no pixel data (a report...)": one line saying so, nothing else."""
    path = _dicom(tmp_path / "cut.dcm", _counts(n=2), *LOSSLESS[name])
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) * 3 // 4])
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        with pytest.raises(FormatError, match=r"cut\.dcm: .*pixel data.*truncated") as info:
            read(path)
    assert "report" not in str(info.value) and "\n" not in str(info.value)
    assert not said, [str(w.message) for w in said]
    res = run_cli("info", path)
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1, res.stderr


@pytest.mark.parametrize("name", ["sv1", "jls", "j2k"])
@pytest.mark.parametrize("declared", [None, 1])
@pytest.mark.parametrize("bot", [True, False])
def test_frames_beyond_number_of_frames_are_not_silently_dropped(tmp_path, name, declared, bot):
    """Two frames, one fragment each, under a NumberOfFrames that is absent (1 by default) or 1.
    With a Basic Offset Table (two offsets) frame 0 is the first fragment and the second is never
    read; without one, frame 0 is both fragments joined, two codestreams one after the other,
    which a decoder reads as the first alone. Either way refused in one line, not read as one
    frame. One frame in several fragments (odd lengths padded) still reads."""
    import pydicom
    from pydicom.encaps import encapsulate

    stack = _counts(n=2)
    syntax, encode = LOSSLESS[name]
    path = _dicom(tmp_path / "nf.dcm", stack, syntax, encode)
    ds = pydicom.dcmread(path)
    ds.PixelData = encapsulate([encode(f) for f in stack], has_bot=bot)
    if declared is None:
        del ds.NumberOfFrames
    else:
        ds.NumberOfFrames = declared
    ds.save_as(path)
    with pytest.raises(FormatError, match=r"nf\.dcm: .*\b2 (frames|codestreams).*NumberOfFrames") as info:
        read(path)
    assert "\n" not in str(info.value)
    stream = encode(stack[0])
    stream += b"\x00" * (len(stream) % 2 == 0)  # odd: its last fragment padded
    ds.PixelData = encapsulate([stream], fragments_per_frame=3, has_bot=bot)
    ds.save_as(path)
    np.testing.assert_array_equal(_quiet_read(path).data, stack[:1])


@pytest.mark.parametrize("codec", ["jls", "sv1", "j2k"])
def test_signed_counts_whose_unused_bits_are_zero_are_sign_extended_from_bits_stored(tmp_path, codec):
    """PixelRepresentation 1, BitsStored 12, each 16-bit word holding the 12-bit two's complement
    pattern with its unused high bits zero (PS3.5 8.1.1 leaves them undefined), compressed at 16
    bits (CharLS's and OpenJPEG's precision for uint16 input). The sign is bit 11, as pydicom and
    other readers take it for such words uncompressed: -1948..1852 back, not 0..4095."""
    signed = _counts(n=1).astype(np.int16) - 2048
    words = signed.view(np.uint16) & 0xFFF
    encode = {
        "jls": lambda f: imagecodecs.jpegls_encode(f),
        "sv1": lambda f: imagecodecs.ljpeg_encode(f, bitspersample=16),
        "j2k": lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K"),
    }[codec]
    assert bytes_header_of(encode(words[0]))["precision"] == 16
    path = _dicom(tmp_path / "s.dcm", words, LOSSLESS[codec][0], encode, signed=True)
    np.testing.assert_array_equal(_quiet_read(path).data, signed)


def test_an_unsigned_dicom_whose_jpeg_2000_says_signed_reads_its_counts(tmp_path):
    """PixelRepresentation 0 over a JPEG 2000 whose SIZ says signed (a writer's mislabel pydicom
    corrects): the stream's bits are the counts, 12 of them unsigned, not int16 values wrapped to
    uint16 (65000s)."""
    counts = _counts(n=1)
    as_signed = ((counts.astype(np.int32) << 20) >> 20).astype(np.int16)  # the same 12 bits, read signed
    encode = lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12)
    assert bytes_header_of(encode(as_signed[0]))["signed"]
    path = _dicom(tmp_path / "u.dcm", as_signed, uid.JPEG2000Lossless, encode)
    np.testing.assert_array_equal(_quiet_read(path).data, counts)


def bytes_header_of(stream) -> dict:
    from radiokit.io._codecs import bytes_header

    return bytes_header(stream)


def _tile_parts(stream: bytes) -> list[tuple[int, int, int]]:
    """(offset, tile index, length) of each tile-part (SOT, T.800 A.4.2) of a codestream whose
    tile-parts all state their length."""
    parts, pos = [], stream.index(b"\xff\x90")
    while stream[pos : pos + 2] == b"\xff\x90":
        _, tile, length = struct.unpack(">HHI", stream[pos + 2 : pos + 10])
        parts.append((pos, tile, length))
        pos += length
    return parts


@pytest.mark.parametrize("container", ["j2k", "dcm"])
def test_a_jpeg_2000_missing_a_tile_is_refused_not_read_as_zeros(tmp_path, container):
    """Four 64 x 64 tiles, the third's tile-part cut out, the end marker kept: OpenJPEG decodes
    the missing tile as zeros without a word (every tile must have a tile-part, T.800 A.4.2).
    Refused in one line before decoding; the whole stream still reads."""
    rng = np.random.default_rng(4)
    counts = rng.integers(100, 4000, (128, 128)).astype(np.uint16)
    stream = imagecodecs.htj2k_encode(counts, level=0, tile=(64, 64))
    at, tile, length = _tile_parts(stream)[2]
    assert tile == 2
    cut = stream[:at] + stream[at + length :]
    if container == "j2k":
        path = tmp_path / "t.j2k"
        path.write_bytes(cut)
    else:
        path = _dicom(tmp_path / "t.dcm", counts[None], uid.HTJ2KLossless, lambda f: cut, bits=12)
    with pytest.raises(FormatError, match=r"t\.(j2k|dcm): .*4 tiles.*3 of them.*corrupt") as info:
        read(path)
    assert "\n" not in str(info.value)
    path = tmp_path / "whole.j2k"
    path.write_bytes(stream)
    np.testing.assert_array_equal(_quiet_read(path).data[0], counts)


def test_a_jpeg_2000_header_declaring_tens_of_thousands_of_tiles_is_refused_before_decoding(tmp_path):
    """A 16 x 16 stream whose SIZ is rewritten to 4000 x 4000 in 16 x 16 tiles (62500 of them, in
    one tile-part): OpenJPEG sets up every tile declared, 0.7 GB for a file of ~130 bytes, under a
    budget of 128 MiB that its image (96 MB with OpenJPEG's copy) fits. Refused from its header,
    nothing decoded: by the budget, which counts the tiles, and under a larger one by the 62499
    tiles it lacks."""
    stream = bytearray(imagecodecs.jpeg2k_encode(np.zeros((16, 16), np.uint16), level=0, codecformat="J2K"))
    struct.pack_into(">IIIIIIII", stream, 8, 4000, 4000, 0, 0, 16, 16, 0, 0)
    path = tmp_path / "tiles.j2k"
    path.write_bytes(bytes(stream))
    with pytest.raises(FormatError, match=r"tiles\.j2k: .*4000x4000 .* over the memory budget of 128"):
        read(path, budget="128MiB")
    with pytest.raises(FormatError, match=r"tiles\.j2k: .*62500 tiles, 1 of them") as info:
        read(path, budget="4GiB")
    assert "\n" not in str(info.value)


def test_a_reversible_jpeg_2000_cut_to_a_rate_is_not_said_lossless(tmp_path):
    """The reversible 5/3 wavelet is lossless only where the encoder kept every bit-plane; a rate or
    quality target (OpenJPEG's -r/-q, whose default wavelet is 5/3) cuts them, and no header says
    so. Such a file, off by tens of counts, was described "lossless"; now "lossless or not"."""
    counts = _counts(n=1)[0]
    stream = imagecodecs.jpeg2k_encode(counts, level=45, codecformat="J2K", reversible=True, bitspersample=12)
    path = tmp_path / "rate.j2k"
    path.write_bytes(stream)
    got = read(path)
    assert np.abs(got.data[0].astype(int) - counts).max() > 0  # lossy indeed
    assert "reversible 5/3" in got.meta["compression"]
    assert not got.meta["compression"].endswith(", lossless"), got.meta["compression"]
    assert "does not say" in got.meta["compression"]


def _traced_peak(path) -> int:
    """The most memory Python and numpy held at once while ``read`` took the file (imagecodecs'
    outputs are numpy arrays, so traced; the codecs' own C buffers are not)."""
    import tracemalloc

    tracemalloc.start()
    try:
        _quiet_read(path)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("name", ["sv1", "jls", "j2k"])
def test_a_compressed_dicom_s_budget_counts_its_decode_s_working_memory(tmp_path, name):
    """The budget is charged what reading a compressed DICOM holds at its peak, not the frames alone:
    the pixel element, the stack, the frame's codestream, its decode (and a JPEG's check decode,
    OpenJPEG's 32-bit image). A budget 10 % under the traced peak is refused; one 10 % over that
    peak plus what the C codec holds untraced (OpenJPEG: 4 bytes a sample) reads. (10 %: pydicom's
    and Python's own allocations beside the pixels.) The frames alone, 2 MiB, were all it counted:
    a read taking 2.5-6 times that passed a budget just over it."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[:1024, :1024]
    frame = np.clip(2000 + 800 * np.sin(x / 50) * np.cos(y / 70) + rng.normal(0, 30, x.shape), 0, 4095)
    frames = frame.astype(np.uint16)[None]
    path = _dicom(tmp_path / f"{name}.dcm", frames, *LOSSLESS[name])
    peak = _traced_peak(path)
    assert peak > 2 * frames.nbytes  # (more than the frames: else nothing is measured here)
    with pytest.raises(FormatError, match=rf"{name}\.dcm: .*over the memory budget"):
        read(path, budget=int(0.9 * peak))
    untraced = 4 * frames.size if name == "j2k" else 0
    got = read(path, budget=int(1.1 * (peak + untraced)))
    np.testing.assert_array_equal(got.data, frames)


@pytest.mark.parametrize("name, suffix", [("sv1", ".jpg"), ("jls", ".jls"), ("j2k", ".j2k")])
def test_a_codestream_file_s_budget_counts_its_read_s_working_memory(tmp_path, name, suffix):
    """As a DICOM's frames (above), a .jpg, .jls or .j2k file is charged what its read holds: the
    file's bytes, its decode (a JPEG's check decode, OpenJPEG's image) and the frame read into its
    stack. The decode and the check alone were counted: 0.4-0.7 of the peak (benchmarks/README.md)."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[:1024, :1024]
    frame = np.clip(2000 + 800 * np.sin(x / 50) * np.cos(y / 70) + rng.normal(0, 30, x.shape), 0, 4095)
    frame = frame.astype(np.uint16)
    path = tmp_path / f"{name}{suffix}"
    path.write_bytes(LOSSLESS[name][1](frame))
    peak = _traced_peak(path)
    with pytest.raises(FormatError, match=rf"{name}\{suffix}: .*over the memory budget"):
        read(path, budget=int(0.9 * peak))
    untraced = 4 * frame.size if name == "j2k" else 0
    np.testing.assert_array_equal(read(path, budget=int(1.1 * (peak + untraced))).data[0], frame)


def test_a_dicom_frame_declaring_tens_of_thousands_of_tiles_is_refused_by_the_budget_before_decoding(tmp_path):
    """The budget at open counts one tile a frame (a frame's tiles are in its own header, read only
    at its decode); each frame's header is then held to the budget before its decode. A 4000 x 4000
    frame in 16 x 16 tiles (62500: 0.6 GiB of OpenJPEG's structures) in a file of a few hundred
    bytes, under a budget of 256 MiB that its image and OpenJPEG's copy fit (128 MB)."""
    stream = bytearray(imagecodecs.jpeg2k_encode(np.zeros((16, 16), np.uint16), level=0, codecformat="J2K"))
    struct.pack_into(">IIIIIIII", stream, 8, 4000, 4000, 0, 0, 16, 16, 0, 0)
    frames = np.broadcast_to(np.uint16(0), (1, 4000, 4000))  # (its shape: the stream is the frame)
    path = _dicom(tmp_path / "tiles.dcm", frames, uid.JPEG2000Lossless, lambda f: stream)
    with pytest.raises(FormatError, match=r"tiles\.dcm: frame 0 \(JPEG 2000.*over the memory budget of 256") as info:
        read(path, budget="256MiB")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["sv1", "jls"])
def test_a_multi_frame_compressed_dicom_is_charged_its_largest_frame_s_stream_not_the_file(tmp_path, name):
    """At open, one frame's decode is counted before any is read: its codestream bounded by the
    file's bytes counted 6 streams where one is decoded at a time (a JPEG holds three copies of
    it), and a file that fits was refused under a budget 10 % over its peak. The fragments' lengths
    (item headers, read from the file) bound the largest frame's."""
    rng = np.random.default_rng(8)
    y, x = np.mgrid[:512, :512]
    frames = np.stack(
        [np.clip(2000 + 800 * np.sin(x / (40 + k)) + rng.normal(0, 30, x.shape), 0, 4095) for k in range(6)]
    ).astype(np.uint16)
    path = _dicom(tmp_path / f"{name}.dcm", frames, *LOSSLESS[name])
    peak = _traced_peak(path)
    np.testing.assert_array_equal(read(path, budget=int(1.1 * peak)).data, frames)
    with pytest.raises(FormatError, match=rf"{name}\.dcm: .*over the memory budget"):
        read(path, budget=int(0.9 * peak))


def test_a_multi_frame_dicom_of_several_fragments_a_frame_without_an_offset_table_is_charged_one_frame(tmp_path):
    """Frames of two fragments each, the Basic Offset Table empty (as the standard allows): pydicom
    finds each frame's end at the fragment that ends in an EOI marker, and the budget at open
    counted every fragment as one frame's stream (the whole file, three times over for a JPEG),
    refusing under a budget 1.3 times the peak a file that the one-fragment layout reads under 1.1."""
    import pydicom
    from pydicom.encaps import encapsulate

    rng = np.random.default_rng(9)
    y, x = np.mgrid[:512, :512]
    frames = np.stack(
        [np.clip(2000 + 800 * np.sin(x / (40 + k)) + rng.normal(0, 30, x.shape), 0, 4095) for k in range(6)]
    ).astype(np.uint16)
    syntax, encode = LOSSLESS["sv1"]
    streams = [encode(f) for f in frames]
    path = _dicom(tmp_path / "two.dcm", frames, syntax, encode)
    ds = pydicom.dcmread(path)
    ds.PixelData = encapsulate(streams, fragments_per_frame=2, has_bot=False)
    ds.save_as(path)
    peak = _traced_peak(path)
    np.testing.assert_array_equal(read(path, budget=int(1.1 * peak)).data, frames)
