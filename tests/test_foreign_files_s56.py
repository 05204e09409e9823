"""Files from writers radiokit had not met (session 56's foreign-file trial): valid DICOM, TIFF,
PNG and HDF5 made by pydicom, tifffile, OpenCV and h5py with unusual attributes read with the
values their own libraries give, and what radiokit cannot read is one line naming the real cause."""

import numpy as np
import pytest

from radiokit.io import FormatError, read
from tests.conftest import run_cli


def _counts(shape=(40, 50), bits=12, seed=56):
    return np.random.default_rng(seed).integers(0, 1 << bits, size=shape, dtype=np.uint16)


def _dataset(sop_class: str, modality: str):
    """A dataset of ``sop_class`` to be written in explicit VR little endian; ``save_as(path,
    enforce_file_format=True)`` fills the rest of its file meta from its own UIDs."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = sop_class, generate_uid(), modality
    return ds


def _dx(path, words, *, bits_stored=12, high_bit=None, photometric="MONOCHROME2", **attrs):
    """A DX DICOM of 16-bit ``words`` as pydicom writes one."""
    ds = _dataset("1.2.840.10008.5.1.4.1.1.1.1", "DX")  # DX for presentation
    ds.Rows, ds.Columns = words.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, photometric
    ds.BitsAllocated, ds.BitsStored, ds.PixelRepresentation = 16, bits_stored, 0
    ds.HighBit = bits_stored - 1 if high_bit is None else high_bit
    for name, value in attrs.items():
        setattr(ds, name, value)
    ds.PixelData = words.astype("<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


def test_counts_stored_in_the_top_bits_of_their_word_are_refused_not_misread(tmp_path):
    """HighBit 15 with BitsStored 12: the counts are the word's top 12 bits (ACR-NEMA's layout, which
    DX and CR forbid: HighBit = BitsStored - 1). pydicom masks the low 12 bits, and radiokit read
    them as counts: every value wrong (word & 0xFFF is (count << 4) & 0xFFF), without a word."""
    counts = _counts()
    path = _dx(tmp_path / "top.dcm", counts << 4, high_bit=15)
    with pytest.raises(FormatError, match=r"top\.dcm: .*HighBit 15.*BitsStored 12") as info:
        read(path)
    assert "\n" not in str(info.value)
    # the layout every writer uses still reads, every count as written
    np.testing.assert_array_equal(read(_dx(tmp_path / "low.dcm", counts)).data[0], counts)


def test_a_dicom_cut_before_its_pixel_data_is_said_to_be_truncated(tmp_path, capfd):
    """A DICOM cut inside its header: pydicom keeps what it read and drops the cut element without
    a word, and radiokit called the file "a report, structured data or a header only". Its last
    element (or its file meta) runs past the file's end: truncated. Cut at an element's boundary
    (30 bytes before the pixels: three 10-byte elements) it is whole elements, and its header's
    image without pixels is said."""
    whole = _dx(tmp_path / "whole.dcm", _counts()).read_bytes()
    pixel_data = whole.rindex(b"\xe0\x7f\x10\x00")  # (7FE0,0010)'s tag, the pixels' element
    for cut in (300, pixel_data - 25, pixel_data - 30):
        path = tmp_path / f"cut{cut}.dcm"
        path.write_bytes(whole[:cut])
        res = run_cli("info", path)
        assert res.returncode == 2
        err = res.stderr.strip()
        assert f"cut{cut}.dcm" in err and "truncated" in err and "report" not in err, err
        assert len(err.splitlines()) == 1, err
    # a whole file without pixels is still what it was said to be
    from pydicom import dcmread

    ds = dcmread(tmp_path / "whole.dcm")
    del ds.PixelData
    ds.save_as(tmp_path / "header.dcm")
    with pytest.raises(FormatError, match=r"header\.dcm: a DICOM file, but it has no pixel data, though its header"):
        read(tmp_path / "header.dcm")


def test_a_dicom_without_a_photometric_interpretation_is_not_called_colour(tmp_path):
    """One sample a pixel and PhotometricInterpretation empty (a type-1 attribute a writer left
    blank): it was refused as "a colour DICOM image (1 samples per pixel)"."""
    path = _dx(tmp_path / "blank.dcm", _counts(), photometric="")
    with pytest.raises(FormatError, match=r"blank\.dcm: .*no PhotometricInterpretation") as info:
        read(path)
    assert "colour" not in str(info.value)


def _functional_groups(path, slopes, intercepts, shared: bool):
    """``path``'s dataset with its Modality LUT where an enhanced multi-frame image keeps it: a
    Pixel Value Transformation in the shared functional groups, or one a frame, none at the top."""
    from pydicom import dcmread
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    def group(slope, intercept):
        lut = Dataset()
        lut.RescaleSlope, lut.RescaleIntercept, lut.RescaleType = str(slope), str(intercept), "US"
        item = Dataset()
        item.PixelValueTransformationSequence = Sequence([lut])
        return item

    ds = dcmread(path)
    if shared:
        ds.SharedFunctionalGroupsSequence = Sequence([group(slopes[0], intercepts[0])])
    else:
        ds.PerFrameFunctionalGroupsSequence = Sequence([group(s, b) for s, b in zip(slopes, intercepts)])
    ds.save_as(path)
    return path


def test_an_enhanced_image_s_modality_lut_in_its_functional_groups_is_applied(tmp_path):
    """An enhanced multi-frame image keeps RescaleSlope/Intercept in its functional groups, not at
    the top level: they were ignored (as pydicom's apply_modality_lut ignores them), and the stored
    values read as the image's, without a word. Shared, or the same for every frame, they are
    applied as a top-level one is; differing by frame, refused (one stack has one scale)."""
    counts = _counts((3, 40, 50))
    one = _dx(tmp_path / "multi.dcm", counts.reshape(-1, 50), bits_stored=12)
    from pydicom import dcmread

    ds = dcmread(one)
    ds.Rows, ds.NumberOfFrames = 40, 3
    ds.save_as(one)
    shared = _functional_groups(one, [0.5], [-100], shared=True)
    np.testing.assert_allclose(read(shared).data, counts * 0.5 - 100, rtol=0, atol=0)
    same = _dx(tmp_path / "same.dcm", counts.reshape(-1, 50))
    ds = dcmread(same)
    ds.Rows, ds.NumberOfFrames = 40, 3
    ds.save_as(same)
    _functional_groups(same, [2, 2, 2], [-7, -7, -7], shared=False)
    np.testing.assert_array_equal(read(same).data, counts.astype(np.int64) * 2 - 7)
    _functional_groups(same, [1, 2, 3], [0, 0, 0], shared=False)
    with pytest.raises(FormatError, match=r"same\.dcm: .*RescaleSlope.*differ") as info:
        read(same)
    assert "\n" not in str(info.value)


def test_info_says_which_pixels_a_dicom_pads(tmp_path):
    """PixelPaddingValue marks pixels holding no image (outside the collimated field); a DX writer
    pads a 12-bit image with 4095, which info counted as saturated without a word of why. The
    pixels are read as stored (pydicom's values), and info now names the padding."""
    counts = _counts() % 4000
    counts[:5] = 4095  # the padded band
    path = _dx(tmp_path / "padded.dcm", counts, PixelPaddingValue=4095)
    np.testing.assert_array_equal(read(path).data[0], counts)
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    rows = {line.split()[0]: line for line in res.stdout.splitlines()[1:] if line.strip()}
    assert f"{counts[:5].size} pixel(s) >= 4095" in rows["saturated"], res.stdout
    assert "PixelPaddingValue 4095" in rows["padding"] and "no image" in rows["padding"], res.stdout


def test_a_whole_deflated_dicom_without_pixels_is_not_called_truncated(tmp_path):
    """A deflated dataset's element offsets are in its inflated bytes, past the (smaller) file's
    end: they say nothing of the file being cut."""
    from pydicom import dcmread
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    ds = dcmread(_dx(tmp_path / "whole.dcm", _counts()))
    del ds.PixelData
    ds.ImageComments = "a comment that deflates well " * 30  # (under 1 KB: read, not deferred)
    ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    ds.save_as(tmp_path / "deflated.dcm")
    with pytest.raises(FormatError, match=r"deflated\.dcm: a DICOM file, but it has no pixel data") as info:
        read(tmp_path / "deflated.dcm")
    assert "run to byte" not in str(info.value)


def test_info_does_not_say_a_dicom_of_16_bits_stored_declares_no_depth(tmp_path):
    """BitsStored 16 of BitsAllocated 16 is a DICOM's statement (as a TIFF's BitsPerSample 16, the
    word, is not); the level is still judged from the values (writers state 16 of 12- and 14-bit
    panels), but info said "the file declares no bit depth" of it."""
    path = _dx(tmp_path / "word.dcm", _counts(), bits_stored=16)
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    row = next(line for line in res.stdout.splitlines() if line.strip().startswith("saturated"))
    assert "declares no bit depth" not in row and "BitsStored 16" in row, row


def test_a_dicom_with_a_character_set_cut_inside_its_header_is_said_to_be_truncated(tmp_path):
    """As above, with a SpecificCharacterSet (which nearly every archive's file has) and a
    sequence: pydicom decodes those as it reads, leaving them no offset, and the whole check gave
    up at them, so such a file cut inside its header was "a report" again. The elements pydicom
    kept raw still say where they end."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    code = Dataset()
    code.CodeValue, code.CodingSchemeDesignator, code.CodeMeaning = "RPID1", "RADLEX", "chest"
    whole = _dx(
        tmp_path / "whole.dcm",
        _counts(),
        SpecificCharacterSet="ISO_IR 100",
        ProcedureCodeSequence=Sequence([code]),
        PatientName="Doe^Jane^Middle",
    ).read_bytes()
    cut = whole.index(b"Doe^Jane^Middle") + 5  # (inside an element after the two, before Rows)
    path = tmp_path / "cut.dcm"
    path.write_bytes(whole[:cut])
    with pytest.raises(FormatError, match=r"cut\.dcm: .*truncated") as info:
        read(path)
    assert "report" not in str(info.value) and "\n" not in str(info.value)


def test_info_gives_a_rescaled_dicom_s_padding_value_as_its_pixels_read(tmp_path):
    """PixelPaddingValue is a stored value; a DICOM with a Modality LUT reads every pixel rescaled,
    so the padded ones read as slope x value + intercept, which info must give beside the stored
    value (it named the stored one alone: no pixel read holds it)."""
    counts = _counts() % 4000
    counts[:5] = 0  # the padded band
    path = _dx(tmp_path / "padded.dcm", counts, PixelPaddingValue=0, RescaleSlope="2", RescaleIntercept="-1000")
    got = read(path)
    assert got.meta["pixel_padding"].startswith("PixelPaddingValue 0")
    assert "-1000 as read" in got.meta["pixel_padding"], got.meta["pixel_padding"]
    assert np.all(got.data[0, :5] == 2 * 0 - 1000)


def test_an_mr_spectroscopy_file_is_not_called_truncated(tmp_path):
    """An MR Spectroscopy object has Rows and Columns (its voxel grid) and SpectroscopyData, never
    pixels: a whole, valid file was said to be "truncated before its pixels, or they were removed"."""
    ds = _dataset("1.2.840.10008.5.1.4.1.1.4.2", "MR")  # MR Spectroscopy Storage
    ds.Rows, ds.Columns, ds.DataPointRows, ds.DataPointColumns = 1, 1, 1, 256
    ds.SpectroscopyData = np.zeros(512, "<f4").tobytes()
    ds.save_as(tmp_path / "mrs.dcm", enforce_file_format=True)
    with pytest.raises(FormatError, match=r"mrs\.dcm: .*SpectroscopyData") as info:
        read(tmp_path / "mrs.dcm")
    assert "truncated" not in str(info.value) and "\n" not in str(info.value)


def test_a_high_bit_refusal_does_not_tell_a_low_bit_file_to_shift_its_counts_away(tmp_path):
    """HighBit 15 over BitsStored 12 is either ACR-NEMA's top-bit layout or a writer's mislabel
    of counts kept in the low bits (which pydicom reads by masking, and radiokit read before). The
    refusal told every such file to shift each word right by 4 bits: done to a mislabelled one,
    that throws away its counts' low 4 bits. It must name both cases and how to tell them apart."""
    counts = _counts()  # (every word below 4096: the low-bit layout)
    path = _dx(tmp_path / "mislabel.dcm", counts, high_bit=15)
    with pytest.raises(FormatError, match=r"mislabel\.dcm: .*HighBit 15") as info:
        read(path)
    said = str(info.value)
    assert "every word below 4096" in said and "set HighBit 11" in said, said
    assert "\n" not in said


def _enhanced(path, counts, groups: dict, *, shared: bool):
    """A 3-frame image of ``counts`` whose pitch is where an enhanced multi-frame image keeps it:
    ``groups`` maps a functional group (PixelMeasuresSequence: PixelSpacing;
    FramePixelDataPropertiesSequence: ImagerPixelSpacing) to its spacing, shared or one a frame
    (``groups``' values then a list, a frame's each), none at the top level."""
    from pydicom import dcmread
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    _dx(path, counts.reshape(-1, counts.shape[-1]))
    ds = dcmread(path)
    ds.Rows, ds.NumberOfFrames = counts.shape[1], counts.shape[0]

    def group(k):
        item = Dataset()
        for sequence, spacing in groups.items():
            inner = Dataset()
            setattr(inner, "PixelSpacing" if sequence == "PixelMeasuresSequence" else "ImagerPixelSpacing", spacing[k])
            setattr(item, sequence, Sequence([inner]))
        return item

    if shared:
        ds.SharedFunctionalGroupsSequence = Sequence([group(0)])
    else:
        ds.PerFrameFunctionalGroupsSequence = Sequence([group(k) for k in range(counts.shape[0])])
    ds.save_as(path)
    return path


def test_an_enhanced_image_s_pitch_in_its_functional_groups_is_read_and_info_says_where(tmp_path):
    """An enhanced multi-frame image keeps PixelSpacing in its functional groups' Pixel Measures
    (and an X-ray one ImagerPixelSpacing in its Frame Pixel Data Properties), not at the top level:
    it was ignored, and its frames measured in pixels without a word. Shared, or the same in every
    frame, it is read as a top-level one; info says which it is and where it was found."""
    counts = _counts((3, 40, 50))
    row, col = 0.2, 0.1  # mm, [row spacing, column spacing]: rows are y
    shared = _enhanced(tmp_path / "shared.dcm", counts, {"PixelMeasuresSequence": [[row, col]]}, shared=True)
    got = read(shared)
    np.testing.assert_array_equal(got.data, counts)
    assert got.meta["x_pixel_size"] == pytest.approx(col * 1e-3, rel=1e-12)
    assert got.meta["y_pixel_size"] == pytest.approx(row * 1e-3, rel=1e-12)
    assert got.meta["pixel_size_source"] == "PixelSpacing"  # (at the patient: correct's stack rule)
    res = run_cli("info", shared)
    assert res.returncode == 0, res.stderr
    said = next(line for line in res.stdout.splitlines() if line.strip().startswith("pixel_size_from"))
    assert "PixelSpacing" in said and "SharedFunctionalGroupsSequence" in said, res.stdout
    # every frame's own, the same: read; and the detector's pitch preferred to the patient's
    each = {"PixelMeasuresSequence": [[row, col]] * 3, "FramePixelDataPropertiesSequence": [[0.15, 0.15]] * 3}
    got = read(_enhanced(tmp_path / "each.dcm", counts, each, shared=False))
    assert got.meta["pixel_size_source"] == "ImagerPixelSpacing"
    assert got.meta["x_pixel_size"] == pytest.approx(0.15e-3, rel=1e-12)


def test_an_enhanced_image_whose_frames_pitches_differ_is_read_without_one_and_says_so(tmp_path):
    """Frames of differing PixelSpacing: any one pitch would give some frames' lengths in mm wrong,
    so the stack has none (lengths in pixels), said in one line naming the file; its counts are
    right and still read (a pitch is optional, as an unusable one in any other file)."""
    counts = _counts((3, 40, 50))
    groups = {"PixelMeasuresSequence": [[0.1, 0.1], [0.1, 0.1], [0.2, 0.2]]}
    path = _enhanced(tmp_path / "zoomed.dcm", counts, groups, shared=False)
    with pytest.warns(UserWarning, match=r"zoomed\.dcm: .*PixelSpacing.*differ") as said:
        got = read(path)
    np.testing.assert_array_equal(got.data, counts)
    assert "x_pixel_size" not in got.meta and "differ" in got.meta["pixel_size_unusable"]
    assert all("\n" not in str(w.message) for w in said)


@pytest.mark.parametrize("codec", ["native", "jls", "j2k"])
def test_bits_above_bits_stored_read_alike_uncompressed_and_compressed_and_are_said(tmp_path, codec):
    """12-bit counts whose words have bits above HighBit set (an overlay in the unused bits, as
    ACR-NEMA-era writers kept one, or a detector wider than its BitsStored). PS3.5 8.1.1: the pixel
    value is the BitsStored bits up to HighBit, the rest no part of it; pydicom masks them from
    uncompressed words without a word, and radiokit kept them from a compressed frame (its stream
    16-bit, as CharLS and OpenJPEG write uint16), so one image read two ways. Both read the low 12
    bits, and both say in one line, naming the file, how many words had more."""
    import imagecodecs
    from pydicom import dcmread
    from pydicom.encaps import encapsulate
    from pydicom.uid import JPEG2000Lossless, JPEGLSLossless

    from radiokit.io import BitDepthWarning

    counts = _counts()
    above = np.random.default_rng(7).integers(0, 4, size=counts.shape, dtype=np.uint16)
    words = counts | (above << 12)  # values up to 16383 in the words, 12-bit counts in their low bits
    path = _dx(tmp_path / f"{codec}.dcm", words)
    if codec != "native":
        syntax, encode = {
            "jls": (JPEGLSLossless, imagecodecs.jpegls_encode),
            "j2k": (JPEG2000Lossless, lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K")),
        }[codec]
        ds = dcmread(path)
        ds.file_meta.TransferSyntaxUID = syntax
        ds.PixelData = encapsulate([encode(words)])
        ds["PixelData"].VR = "OB"
        ds.save_as(path)
    with pytest.warns(
        BitDepthWarning, match=rf"{codec}\.dcm: .*{np.count_nonzero(above)} .*above.*BitsStored 12"
    ) as said:
        got = read(path)
    np.testing.assert_array_equal(got.data[0], counts)
    # one line, once (info shows it on stderr as its other warnings: run_cli ignores warnings)
    said = [w for w in said if issubclass(w.category, BitDepthWarning)]
    assert len(said) == 1 and "\n" not in str(said[0].message), said
