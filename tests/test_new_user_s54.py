"""A new user's first runs (session 54's trial, review s54rvuser): each message must name the real
cause -- a lit image given as the dark, a depth the file does not state, a folder where frames
were wanted -- and a stack's file names must be what other tools can read."""

import os

import h5py
import numpy as np
import tifffile

from radiokit.io import StackWriter, read_stack
from tests.conftest import info_items, run_cli


def _scene(n=64):
    """A 14-bit panel's dark (offset 300), flat (12000) and a projection of a round phantom
    transmitting a quarter of the beam, Poisson noise on each (one frame each)."""
    rng = np.random.default_rng(54)
    yy, xx = np.mgrid[:n, :n]
    phantom = (yy - n / 2) ** 2 + (xx - n / 2) ** 2 < (n / 3) ** 2
    dark = rng.poisson(300, (n, n)).astype(np.uint16)
    flat = rng.poisson(12000, (n, n)).astype(np.uint16)
    proj = (300 + rng.poisson(np.where(phantom, 0.25, 1.0) * 11700)).astype(np.uint16)
    return dark, flat, proj


def test_a_projection_as_the_only_dark_is_named_a_lit_dark(tmp_path):
    # one dark that is a projection: the response (flat - "dark") was lit only where the phantom
    # absorbed, and calibrate sent the user cropping to an image intensifier's circular field
    _, flat, proj = _scene()
    tifffile.imwrite(tmp_path / "proj.tif", proj)
    tifffile.imwrite(tmp_path / "flats.tif", np.stack([flat, flat]))
    res = run_cli(
        "calibrate", "--dark", tmp_path / "proj.tif", "--flat", tmp_path / "flats.tif", "-o", tmp_path / "c.h5"
    )
    assert res.returncode != 0
    err = res.stderr.strip()
    assert "proj.tif" in err and "lit" in err and "not a dark" in err, err
    assert "disc" not in err and "intensifier" not in err, err
    assert len(err.splitlines()) == 1 and not (tmp_path / "c.h5").exists()


def test_a_true_single_dark_still_calibrates(tmp_path):
    dark, flat, _ = _scene()
    tifffile.imwrite(tmp_path / "dark.tif", dark)
    tifffile.imwrite(tmp_path / "flats.tif", np.stack([flat, flat]))
    res = run_cli(
        "calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flats.tif", "-o", tmp_path / "c.h5"
    )
    assert res.returncode == 0, res.stderr


def test_info_on_a_dark_of_no_declared_depth_says_the_level_is_a_guess(tmp_path):
    # a 14-bit panel's dark (values ~300): "saturation >= 4095 (from the values)" read as a fact
    # about the ADC; its values say nothing of the ADC's top
    dark, _, _ = _scene()
    tifffile.imwrite(tmp_path / "dark.tif", dark)
    out = info_items(run_cli("info", tmp_path / "dark.tif").stdout)
    line = next(x for x in out.splitlines() if "saturated" in x)
    assert "guess" in line and "no bit depth" in line, line


def test_a_folder_given_as_frames_gets_a_glob_hint(tmp_path):
    dark, flat, _ = _scene()
    (tmp_path / "darks").mkdir()
    tifffile.imwrite(tmp_path / "darks" / "d1.tif", dark)
    tifffile.imwrite(tmp_path / "flats.tif", flat)
    res = run_cli("calibrate", "--dark", tmp_path / "darks", "--flat", tmp_path / "flats.tif", "-o", tmp_path / "c.h5")
    assert res.returncode != 0
    assert "is a directory" in res.stderr and "darks/*.tif" in res.stderr, res.stderr


def test_stack_sources_are_stored_as_bytes_other_tools_can_read(tmp_path):
    # raw non-UTF-8 bytes under an HDF5 UTF-8 string type: h5py's .asstr() (and any tool reading
    # the dataset as text) failed on it
    names = [b"caf\xe9.tif", b"plain.tif"]
    with StackWriter(tmp_path / "s.h5", (4, 4), sources=[os.fsdecode(n) for n in names]) as w:
        w.append(np.zeros((4, 4), np.float32))
    with h5py.File(tmp_path / "s.h5", "r") as h5:
        ds = h5["entry/sources"]
        cset = h5py.check_string_dtype(ds.dtype)
        assert cset is None or cset.encoding == "ascii", cset
        assert list(ds[()]) == names
    assert read_stack(tmp_path / "s.h5").sources == tuple(os.fsdecode(n) for n in names)


def test_stack_sources_written_as_utf8_strings_still_read(tmp_path):
    # stacks written before (a UTF-8 string dataset) keep reading

    with StackWriter(tmp_path / "s.h5", (4, 4)) as w:
        w.append(np.zeros((4, 4), np.float32))
    with h5py.File(tmp_path / "s.h5", "a") as h5:
        h5.create_dataset("entry/sources", data=np.array([b"a\xe9.tif", b"b.tif"], object), dtype=h5py.string_dtype())
    assert read_stack(tmp_path / "s.h5").sources == (os.fsdecode(b"a\xe9.tif"), "b.tif")


def test_stack_sources_of_utf8_names_stay_utf8_text(tmp_path):
    names = ["café.tif", "b.tif"]
    with StackWriter(tmp_path / "s.h5", (4, 4), sources=names) as w:
        w.append(np.zeros((4, 4), np.float32))
    with h5py.File(tmp_path / "s.h5", "r") as h5:
        assert list(h5["entry/sources"].asstr()[()]) == names
    assert read_stack(tmp_path / "s.h5").sources == tuple(names)


def _dx(path, frame, **spacings):
    """A DX DICOM of ``frame`` with the spacings given (``ImagerPixelSpacing``, ``PixelSpacing``)."""
    import pydicom

    from tests.test_io_clinical import _dicom

    _dicom(path, frame, bits_stored=14)
    ds = pydicom.dcmread(path)
    for name, mm in spacings.items():
        setattr(ds, name, [mm, mm])
    ds.save_as(path, enforce_file_format=True)
    return path


def test_a_stack_keeps_no_patient_plane_pixel_spacing_as_the_detector_pitch(tmp_path):
    # DICOM's PixelSpacing is at the patient (the pitch over the magnification, 0.139 / 1.25 here):
    # kept as the stack's x_pixel_size it was read as the detector's, and sizes at the object
    # (README: divide by the magnification) were shrunk twice
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files
    from radiokit.io import read

    dark, flat, proj = _scene()
    cal = Calibration.from_frames(np.stack([dark] * 3), np.stack([flat] * 3))
    _dx(tmp_path / "p.dcm", proj, PixelSpacing=0.139 / 1.25)
    _dx(tmp_path / "q.dcm", proj, ImagerPixelSpacing=0.139, PixelSpacing=0.139 / 1.25)
    correct_files([tmp_path / "p.dcm", tmp_path / "q.dcm"], cal, tmp_path / "c.h5", progress=False)
    meta = read(tmp_path / "c.h5").meta
    assert abs(meta["pixel_size_mm"] - 0.139) < 1e-9, meta.get("pixel_size_mm")
    correct_files([tmp_path / "p.dcm"], cal, tmp_path / "p.h5", progress=False)
    assert "x_pixel_size" not in read(tmp_path / "p.h5").meta


def test_pitches_equal_within_rounding_are_one(tmp_path):
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files

    dark, flat, proj = _scene()
    cal = Calibration.from_frames(np.stack([dark] * 3), np.stack([flat] * 3))
    _dx(tmp_path / "a.dcm", proj, ImagerPixelSpacing=0.139)
    _dx(tmp_path / "b.dcm", proj, ImagerPixelSpacing=0.13900000001)
    correct_files([tmp_path / "a.dcm", tmp_path / "b.dcm"], cal, tmp_path / "c.h5", progress=False)
