"""radiokit.io on files other labs' software writes: NeXus detector layouts (NXdetector, NXtomo) and
TIFF and ITEX variants. Every check compares the pixels read with the array written, value by
value and in the same orientation (rows, columns), not only that the file opens."""

import math
import os
import re
import subprocess
import sys
import threading
import warnings

import h5py
import numpy as np
import pytest
import scipy.io
import tifffile
from conftest import ITEX_DIR, info_items, needs_itex, one_line_error, run_cli

from radiokit.calibrate import Calibration
from radiokit.errors import FormatError
from radiokit.io import ImageKey, read
from radiokit.io._tiff_ifds import check_tiff_pages


def _frames(n=4, rows=30, cols=40, dtype="<u2", seed=0):
    """Distinct values in a non-square frame: a transposed, flipped or shifted read cannot match."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 4096, (n, rows, cols)).astype(dtype)


def _nx_class(group, name):
    group.attrs["NX_class"] = name
    return group


# ------------------------------------------------------------------------------------------------
# NeXus frames of other acquisition software
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("nxdata", [None, "hard", "soft"])
def test_nexus_detector_frames_without_image_keys_are_read(tmp_path, nxdata):
    """Another program's NeXus file puts its frames where NeXus says, ``/entry/instrument/detector/
    data`` (NXdetector), often linked into ``/entry/data`` (NXdata, ``@signal``) with a soft link,
    as radiokit's own experiment files do. Without NXtomo's ``image_key`` it is frames, not an
    experiment: read them (chunked, gzip and shuffle), instead of refusing a missing key."""
    frames = _frames()
    path = tmp_path / "detector.nxs"
    with h5py.File(path, "w") as h5:
        entry = _nx_class(h5.create_group("entry"), "NXentry")
        det = _nx_class(entry.create_group("instrument/detector"), "NXdetector")
        det.create_dataset("data", data=frames, chunks=(1, 30, 40), compression="gzip", shuffle=True)
        if nxdata:
            data = _nx_class(entry.create_group("data"), "NXdata")
            data.attrs["signal"] = "data"
            data["data"] = det["data"] if nxdata == "hard" else h5py.SoftLink("/entry/instrument/detector/data")
    f = read(path)
    assert f.meta["format"] == "hdf5" and "image_key" not in f.meta
    assert f.data.shape == frames.shape and f.data.dtype == np.uint16
    np.testing.assert_array_equal(f.data, frames)


def test_nexus_signal_soft_linked_from_elsewhere_is_read(tmp_path):
    """The NXdata's signal soft-linked to a detector at another path than radiokit's: the file
    names its frames, so they are read (a soft link stays inside the file)."""
    frames = _frames(n=3, dtype="<i2") - 2048  # int16 negatives must stay negative
    path = tmp_path / "camera.h5"
    with h5py.File(path, "w") as h5:
        entry = _nx_class(h5.create_group("entry"), "NXentry")
        entry.create_dataset("instrument/camera/image", data=frames, chunks=(1, 15, 20), compression="lzf")
        data = _nx_class(entry.create_group("data"), "NXdata")
        data.attrs["signal"] = "image"
        data["image"] = h5py.SoftLink("/entry/instrument/camera/image")
    f = read(path)
    assert f.meta["dataset"] == "/entry/data/image" and f.data.dtype == np.int16
    np.testing.assert_array_equal(f.data, frames)


def test_nexus_detector_single_image_is_one_frame(tmp_path):
    """An NXdetector holding one 2-D image is one frame, rows and columns as stored."""
    frame = _frames(n=1)[0]
    path = tmp_path / "one.nxs"
    with h5py.File(path, "w") as h5:
        h5["entry/instrument/detector/data"] = frame
    f = read(path)
    assert f.data.shape == (1, 30, 40)
    np.testing.assert_array_equal(f.data[0], frame)


def _nxtomo(path, frames, keys, entry="entry0000", linked=("data", "image_key")):
    """NXtomo as nxtomomill and tomoscan write it: keys beside the frames, both (``linked``) linked
    into NXdata."""
    with h5py.File(path, "w") as h5:
        e = _nx_class(h5.create_group(entry), "NXentry")
        det = _nx_class(e.create_group("instrument/detector"), "NXdetector")
        det.create_dataset("data", data=frames, chunks=(1,) + frames.shape[1:], compression="gzip")
        det["image_key"] = np.asarray(keys, np.int32)
        data = _nx_class(e.create_group("data"), "NXdata")
        data.attrs["signal"] = "data"
        for name in linked:
            data[name] = h5py.SoftLink(f"/{entry}/instrument/detector/{name}")


def test_nxtomo_keys_beside_the_frames_tell_darks_and_flats(tmp_path):
    """An NXtomo file whose entry is not named ``entry`` (``entry0000``) is read through its NXdata,
    and the ``image_key`` beside the frames comes with them: a calibration from it takes its
    darks and flats, never every frame as both."""
    rng = np.random.default_rng(4)
    darks = rng.normal(100, 2, (3, 24, 32))
    flats = rng.normal(3000, 30, (3, 24, 32))
    proj = rng.normal(1500, 20, (2, 24, 32))
    frames = np.concatenate([darks, flats, proj]).round().astype(np.uint16)
    keys = [ImageKey.DARK] * 3 + [ImageKey.FLAT] * 3 + [ImageKey.PROJECTION] * 2
    path = tmp_path / "scan.nx"
    _nxtomo(path, frames, keys)
    f = read(path)
    np.testing.assert_array_equal(f.data, frames)
    np.testing.assert_array_equal(f.meta["image_key"], keys)
    cal = Calibration.from_experiment(path)
    expected = Calibration.from_frames(frames[:3], frames[3:6])
    np.testing.assert_allclose(cal.dark, expected.dark)
    np.testing.assert_allclose(cal.flat, expected.flat)
    assert read(path, n=4).meta["image_key"].tolist() == keys[:4]  # cut with the frames
    # found in review: an NXdata linking only the frames lost the keys beside their target
    _nxtomo(path, frames, keys, linked=("data",))
    np.testing.assert_array_equal(read(path).meta["image_key"], keys)


def test_nxtomo_keys_of_another_length_are_refused(tmp_path):
    """Keys that do not label every frame would misfile darks and flats: one line naming them."""
    path = tmp_path / "scan.nx"
    _nxtomo(path, _frames(n=4), [2, 1, 0])
    with pytest.raises(FormatError, match=r"scan\.nx: .*image_key holds 3 image keys for 4 frames"):
        read(path)


def test_radiokit_experiment_missing_its_keys_stays_an_error(tmp_path):
    """A file radiokit wrote (``@frames_complete``) that lost its ``image_key`` is broken, not
    another lab's frames: still refused, naming the missing key."""
    path = tmp_path / "exp.h5"
    with h5py.File(path, "w") as h5:
        h5["entry/instrument/detector/data"] = _frames(n=2)
        h5["entry"].attrs["frames_complete"] = 2
    with pytest.raises(FormatError, match="lacks /entry/instrument/detector/image_key"):
        read(path)


# A writer that stays open until its stdin closes: in SWMR mode as detector software writes, or
# plainly (holding the HDF5 file lock); "exit" and "plain-exit" leave without closing, as a killed
# writer does.
_OPEN_WRITER = """
import os, sys, h5py, numpy as np
path, mode = sys.argv[1], sys.argv[2]
frames = np.arange(2 * 30 * 40, dtype="<u2").reshape(2, 30, 40)
f = h5py.File(path, "w", libver="latest")
zstd = {}
if mode == "block-zstd":  # compressed, extended 800 frames ahead: far beyond what it stores
    import hdf5plugin
    zstd = hdf5plugin.Zstd()
ds = f.create_dataset(
    "entry/data/data", shape=(0, 30, 40), maxshape=(None, 30, 40), dtype="<u2", chunks=(1, 30, 40), **zstd
)
f["entry"].attrs["NX_class"] = "NXentry"
f["entry/data"].attrs.update(NX_class="NXdata", signal="data")
if mode in ("lag", "block", "block-zstd"):  # NXtomo keys, the writer one frame behind with them
    keys = f.create_dataset("entry/data/image_key", shape=(0,), maxshape=(None,), dtype="i1", chunks=(4,))
if mode not in ("plain", "plain-exit"):
    f.swmr_mode = True
if mode == "lag":
    keys.resize((1,))
    keys[0] = 2
if mode in ("block", "block-zstd"):  # the frames extended 8 at a time ahead of what is written, keys as written
    keys.resize((2,))
    keys[:] = 2
    ds.resize((800 if zstd else 8, 30, 40))
    ds[:2] = frames
else:
    ds.resize((2, 30, 40))
    ds[:] = frames
f.flush()
if mode in ("exit", "plain-exit"):
    os._exit(0)
print("ready", flush=True)
sys.stdin.read()
f.close()
"""


def _open_writer(path, mode):
    proc = subprocess.Popen(
        [sys.executable, "-c", _OPEN_WRITER, str(path), mode], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    watchdog = threading.Timer(60, proc.kill)  # never hang the suite on a stuck writer
    watchdog.start()
    return proc, watchdog


@pytest.mark.parametrize("mode", ["swmr", "exit"])
def test_hdf5_written_in_swmr_mode_is_read_as_it_stands(tmp_path, mode):
    """A file another program is writing in SWMR mode (or was, when it was killed) is marked open
    for write; libhdf5 refuses a plain reader ("file is already open for write"). Read it as a
    SWMR reader: its frames as flushed, value by value."""
    path = tmp_path / "live.h5"
    proc, watchdog = _open_writer(path, mode)
    try:
        if mode == "exit":
            assert proc.wait() == 0
        else:
            assert proc.stdout.readline() == "ready\n"
        f = read(path)
    finally:
        proc.communicate("")
        watchdog.cancel()
    np.testing.assert_array_equal(f.data, np.arange(2 * 30 * 40).reshape(2, 30, 40))


def test_hdf5_being_written_in_blocks_ahead_of_its_keys_reads_the_frames_both_hold(tmp_path):
    """A SWMR writer that extends its frames 8 at a time, ahead of the frames and keys it has
    written (2): the frames past the keys are not read, so their unwritten chunks are no reason to
    refuse the file ("declares 8x30x40 ... parts never written", since the check of unwritten
    storage); it reads the 2 frames both hold, with the warning of a file being written."""
    path = tmp_path / "live.h5"
    proc, watchdog = _open_writer(path, "block")
    try:
        assert proc.stdout.readline() == "ready\n"
        with pytest.warns(UserWarning, match=r"live\.h5: is marked as being written .* 2 image keys for 8 frames"):
            f = read(path)
    finally:
        proc.communicate("")
        watchdog.cancel()
    np.testing.assert_array_equal(f.data, np.arange(2 * 30 * 40).reshape(2, 30, 40))


def test_a_compressed_live_file_extended_ahead_is_not_taken_for_a_bomb(tmp_path, monkeypatch):
    """Its frames extended 800 ahead of the 2 written: declared far beyond what zstd stores, but
    what is read is the 2 frames the keys hold, and those are held to check_proportion (its
    thresholds lowered to 1 MiB for the 1.9 MB the file declares)."""
    from radiokit.io import _budget

    monkeypatch.delenv("RADIOKIT_MEMORY_BUDGET", raising=False)
    monkeypatch.setattr(_budget, "BOMB_FILE_BYTES", 2**20)
    path = tmp_path / "live.h5"
    proc, watchdog = _open_writer(path, "block-zstd")
    try:
        assert proc.stdout.readline() == "ready\n"
        with pytest.warns(UserWarning, match=r"live\.h5: is marked as being written .* 2 image keys for 800 frames"):
            f = read(path)
    finally:
        proc.communicate("")
        watchdog.cancel()
    np.testing.assert_array_equal(f.data, np.arange(2 * 30 * 40).reshape(2, 30, 40))


def test_hdf5_being_written_with_its_keys_behind_reads_the_frames_both_hold(tmp_path):
    """A SWMR writer extends the frames and their NXtomo image keys one after the other: caught
    between the two (2 frames, 1 key) the file reads as the frame both hold, with a warning;
    it was refused as "holds 1 image keys for 2 frames", and a file nobody writes still is."""
    path = tmp_path / "live.h5"
    proc, watchdog = _open_writer(path, "lag")
    try:
        assert proc.stdout.readline() == "ready\n"
        with pytest.warns(
            UserWarning, match=r"live\.h5: is marked as being written .* 1 image keys for 2 frames; reading the first 1"
        ):
            f = read(path)
    finally:
        proc.communicate("")
        watchdog.cancel()
    np.testing.assert_array_equal(f.data, np.arange(30 * 40).reshape(1, 30, 40))
    assert f.meta["image_key"].tolist() == [2]
    with pytest.raises(FormatError, match="holds 1 image keys for 2 frames"):
        read(path)  # closed by its writer: a mismatch that no longer moves


def test_hdf5_held_by_a_writer_without_swmr_says_so(tmp_path, monkeypatch):
    """A writer without SWMR holds the file lock; its file cannot be read consistently. One line
    in words, not libhdf5's "unable to lock file, errno = 11"."""
    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", "TRUE")  # libhdf5's default, whatever the shell says
    path = tmp_path / "busy.h5"
    proc, watchdog = _open_writer(path, "plain")
    try:
        assert proc.stdout.readline() == "ready\n"
        with pytest.raises(FormatError, match=r"busy\.h5: is open for writing by another program"):
            read(path)
    finally:
        proc.communicate("")
        watchdog.cancel()
    assert read(path).n == 2  # and once closed, it reads


@pytest.mark.parametrize("reader", ["frames", "registration"])
def test_hdf5_left_open_by_a_killed_writer_without_swmr_says_so(tmp_path, reader):
    """Found in review: a plain writer (no SWMR) killed before closing leaves its file marked open
    for write, as a SWMR one does; the SWMR retry then failed with libhdf5's "file is not already
    open for SWMR writing", untranslated, and the typed-layout readers (registration, results,
    stacks) never retried at all. One line in words, naming h5clear, from every reader."""
    from radiokit.io import read_registration

    path = tmp_path / "killed.h5"
    proc, watchdog = _open_writer(path, "plain-exit")
    try:
        assert proc.wait() == 0
    finally:
        watchdog.cancel()
    with pytest.raises(FormatError, match=r"killed\.h5: is marked open for writing .*h5clear"):
        read(path) if reader == "frames" else read_registration(path)


def _matlab_v73(path, **variables):
    """A MATLAB ``save -v7.3`` file as MATLAB writes it: a 512-byte text userblock, and each
    variable a root dataset with ``@MATLAB_class``, its column-major dimensions reversed (so a
    rows x cols x n stack is stored as (n, cols, rows))."""
    with h5py.File(path, "w", userblock_size=512) as h5:
        for name, value in variables.items():
            h5[name] = np.transpose(value)  # numpy's C order of MATLAB's Fortran-ordered array
            h5[name].attrs["MATLAB_class"] = np.bytes_(value.dtype.name)  # "uint16": MATLAB's name too
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 .")


@pytest.mark.parametrize("rows, cols", [(30, 40), (32, 32)])
def test_matlab_v73_stack_reads_in_matlabs_orientation(tmp_path, rows, cols):
    """A lab's MATLAB script saving its frames (rows x cols x n, as imread and cat(3, ...) build
    them) with ``save -v7.3`` writes HDF5 with the dimensions reversed. Read frame by frame as
    MATLAB shows them, not transposed: a square frame would otherwise be transposed silently,
    and calibrated against darks from a TIFF in another orientation."""
    stack = _frames(n=3, rows=rows, cols=cols).transpose(1, 2, 0)  # MATLAB's A(:, :, k)
    image = _frames(n=1, rows=rows, cols=cols, seed=1)[0]
    path = tmp_path / "frames.mat"
    _matlab_v73(path, frames=stack, image=image)
    with pytest.warns(
        UserWarning, match=r"frames\.mat: /frames is a MATLAB array \(@MATLAB_class uint16\).*transposed"
    ):
        f = read(path, dataset="frames")
    assert f.data.shape == (3, rows, cols) and f.meta["matlab_class"] == "uint16"
    for k in range(3):
        np.testing.assert_array_equal(f.data[k], stack[:, :, k])
    with pytest.warns(UserWarning, match="MATLAB array"):
        np.testing.assert_array_equal(read(path, dataset="image").data[0], image)


def test_a_dataset_without_matlab_class_in_a_mat_file_reads_as_matlab_shows_it(tmp_path):
    """``h5write`` into a -v7.3 .mat file writes a dataset without @MATLAB_class, column-major as
    every MATLAB array: it read as (n, cols, rows), each frame transposed, silently. The file's
    MAT-file header says whose it is: read as MATLAB shows it, with a warning naming why."""
    stack = _frames(n=3, rows=30, cols=40).transpose(1, 2, 0)
    path = tmp_path / "frames.mat"
    _matlab_v73(path, image=stack[:, :, 0])
    with h5py.File(path, "a") as h5:
        h5["written"] = np.transpose(stack)  # h5write's dimensions, reversed, no attribute
    with pytest.warns(UserWarning, match=r"/written is a MATLAB array \(the file's MATLAB 7\.3 MAT-file header\)"):
        f = _both_ways(path, dataset="written")
    assert f.shape == (3, 30, 40)
    for k in range(3):
        np.testing.assert_array_equal(f[k], stack[:, :, k])


def test_nxtomo_keys_beside_frames_h5write_put_in_a_mat_file_are_read(tmp_path):
    """Frames ``h5write`` put in a .mat file, with NXtomo's ``image_key`` beside them: the frames
    are MATLAB's (transposed back), the 1-D keys are the same either way and still tell darks and
    flats from projections (review s34-r1: they were dropped, and calibrate averaged the file's
    projections into its flats, exit 0)."""
    stack = _frames(n=4, rows=30, cols=40).transpose(1, 2, 0)
    keys = np.array([2, 1, 0, 0], dtype=np.int32)
    path = tmp_path / "frames.mat"
    _matlab_v73(path, image=stack[:, :, 0])
    with h5py.File(path, "a") as h5:
        h5["entry/data/data"] = np.transpose(stack)
        h5["entry/data/image_key"] = keys
    with pytest.warns(UserWarning, match="MATLAB array"):
        f = read(path, dataset="entry/data/data")
    np.testing.assert_array_equal(f.meta["image_key"], keys)
    np.testing.assert_array_equal(f.data[2], stack[:, :, 2])


def test_an_hdf5_file_with_no_matlab_mark_is_read_row_major(tmp_path):
    """``h5write`` into a plain HDF5 file leaves nothing to tell its column-major order by: its
    frames are read as stored, row-major, as every other HDF5 writer's (the README says so), with
    no MATLAB warning."""
    stored = _frames(n=3, rows=30, cols=40)
    path = tmp_path / "plain.h5"
    with h5py.File(path, "w") as h5:
        h5["frames"] = stored
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read(path, dataset="frames").data, stored)


def test_matlab_v5_file_is_named_not_taken_for_raw_frames(tmp_path):
    """MATLAB's default .mat format is not HDF5; read as headerless raw it drew "pass shape=",
    which would read its header as pixels. One line says what it is and how to save it."""
    path = tmp_path / "frames.mat"
    scipy.io.savemat(path, {"frames": _frames(n=2)})
    with pytest.raises(FormatError, match=r"frames\.mat: a MATLAB \.mat file in its v5/v7 format.*-v7\.3"):
        read(path)


def _mhd(path, frame):
    path.write_bytes(
        b"ObjectType = Image\nNDims = 2\nDimSize = 40 30\nElementType = MET_USHORT\nElementDataFile = f.raw\n"
    )


def _fits(path, frame):
    card = [b"SIMPLE  =                    T", b"BITPIX  =                   16", b"END"]
    path.write_bytes(b"".join(c.ljust(80) for c in card).ljust(2880) + frame.astype(">i2").tobytes())


def _dcimg(path, frame):  # Hamamatsu DCAM-API's own file (HCImage's default): "DCIMG", a header, frames
    path.write_bytes(b"DCIMG\x00\x00\x00" + bytes(224) + frame.tobytes())


@pytest.mark.parametrize(
    "writer, name, what",
    [
        (_dcimg, "f.dcimg", "a Hamamatsu DCIMG file"),
        (_mhd, "f.mhd", "a MetaImage header"),
        (_fits, "f.fits", "a FITS file"),
    ],
)
def test_image_formats_not_read_are_named_not_taken_for_raw_frames(tmp_path, writer, name, what):
    """A MetaImage header, a FITS file, a DCIMG: none is read (PNG, DICOM, JPEG and JPEG 2000
    are: tests/test_io_clinical.py, tests/test_io_codecs.py),
    and each is named in one line rather than read as headerless raw ("pass shape=", which would
    take its header for pixels). format="raw" still reads the bytes for whoever means it."""
    path = tmp_path / name
    writer(path, _frames(n=1)[0])
    with pytest.raises(FormatError, match=rf"{name}: {what}, which radiokit does not read: "):
        read(path)
    raw = read(path, format="raw", shape=(1, path.stat().st_size), dtype="u1")
    np.testing.assert_array_equal(raw.data[0, 0], np.frombuffer(path.read_bytes(), np.uint8))


def test_a_raw_frame_whose_first_bytes_look_like_a_signature_is_read(tmp_path):
    """Found in review: the signature table was checked for .raw files too, so a headerless
    little-endian uint16 frame whose first pixel is 0xD8FF and second's low byte 0xFF was refused
    as "a JPEG image". A .raw file's bytes are pixels (as ITEX's b'IM' is checked only for .img)."""
    frame = _frames(n=1)[0].astype("<u2")
    frame.flat[0], frame.flat[1] = 0xD8FF, 0x12FF
    path = tmp_path / "frame.raw"
    path.write_bytes(frame.tobytes())
    got = read(path, shape=frame.shape, dtype="<u2")
    np.testing.assert_array_equal(got.data[0], frame)


@pytest.mark.parametrize(
    "samples, kw, what",
    [
        (3, {"photometric": "rgb"}, "an RGB image"),
        (4, {"photometric": "rgb", "extrasamples": ["unassalpha"]}, "an RGBA image"),
        (
            2,
            {"photometric": "minisblack", "planarconfig": "contig", "extrasamples": ["unassalpha"]},
            "a grey image with alpha",
        ),
    ],
)
def test_a_colour_tiff_is_named_as_a_display_copy(tmp_path, samples, kw, what):
    """s18-h2: a viewer's colour copy of a radiograph was refused as "shape (40, 50, 3); expected a
    greyscale image", leaving the user to guess; its 8-bit display values are not counts."""
    path = tmp_path / "view.tif"
    tifffile.imwrite(path, np.zeros((40, 50, samples), np.uint8), **kw)
    with pytest.raises(FormatError, match=rf"view\.tif: .*{what}, a viewer's display copy"):
        read(path)


def test_an_imagej_stack_with_fewer_pages_than_it_says_is_read_with_a_warning(tmp_path):
    """s18-h2: an ImageJ stack whose description says images=3 but whose chain holds 2 pages (a
    writer that crashed, or a file edited) read as 2 frames without a word."""
    frames = _frames(n=2)
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, frames, description="ImageJ=1.54f\nimages=3\nslices=3\n", metadata=None)
    with pytest.warns(UserWarning, match=r"stack\.tif: its ImageJ description says images=3 but it holds 2 pages"):
        got = read(path)
    np.testing.assert_array_equal(got.data, frames)


# ------------------------------------------------------------------------------------------------
# TIFF as other programs write it (these pass today: they guard the layout and bomb checks)
# ------------------------------------------------------------------------------------------------


def _values(dtype, shape=(37, 53), seed=7):
    """Extremes of the dtype included: int16 negatives, float NaN and -inf must come back as written."""
    rng = np.random.default_rng(seed)
    dt = np.dtype(dtype)
    if dt.kind == "f":
        out = rng.normal(0, 1000, shape).astype(dt)
        out.flat[3], out.flat[5] = np.nan, -np.inf
        return out
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, shape, dtype=dt, endpoint=True)


@pytest.mark.parametrize("dtype", ["u1", "u2", "i2", "u4", "f4", "f8"])
@pytest.mark.parametrize("byteorder", ["<", ">"])
@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"compression": "lzw", "predictor": True},
        {"compression": "zlib"},
        {"compression": "zstd", "predictor": True},
        {"compression": "packbits"},
        {"tile": (16, 32), "compression": "zlib", "predictor": True},
    ],
)
def test_tiff_variants_read_value_for_value(tmp_path, dtype, byteorder, kw):
    """Byte order x pixel type x compression (with the predictor) x strips of 5 rows over 37
    (the last one short) or tiles over the edge: every pixel as written, rows and columns as stored."""
    frame = _values(dtype)
    path = tmp_path / "v.tif"
    tifffile.imwrite(path, frame, byteorder=byteorder, **({"rowsperstrip": 5} | kw))
    f = read(path)
    assert f.data.shape == (1, 37, 53) and f.data.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(f.data[0], frame)


# ------------------------------------------------------------------------------------------------
# TIFF pixels other software stores differently: WhiteIsZero, palettes, ImageJ's calibration,
# 12-bit counts in 16-bit words, Orientation
# ------------------------------------------------------------------------------------------------


def _set_short_tag(path, code, value, page=0):
    """Overwrite a SHORT (or LONG) tag's value in an IFD of a little-endian classic TIFF (to make
    files tifffile will not write, as other software does)."""
    import struct

    data = bytearray(path.read_bytes())
    ifd = struct.unpack_from("<I", data, 4)[0]
    for _ in range(page):
        ifd = struct.unpack_from("<I", data, ifd + 2 + 12 * struct.unpack_from("<H", data, ifd)[0])[0]
    for k in range(struct.unpack_from("<H", data, ifd)[0]):
        entry = ifd + 2 + 12 * k
        if struct.unpack_from("<H", data, entry)[0] == code:
            struct.pack_into(
                "<H" if struct.unpack_from("<H", data, entry + 2)[0] == 3 else "<I", data, entry + 8, value
            )
            path.write_bytes(bytes(data))
            return
    raise AssertionError(f"tag {code} not in the first IFD")


def _both_ways(path, **hints):
    """The frames by read() and frame by frame by open_frames(): both must agree."""
    from radiokit.io import open_frames

    eager = read(path, **hints).data
    with open_frames(path, **hints) as src:
        lazy = np.stack(list(src))
    np.testing.assert_array_equal(eager, lazy)
    return eager


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_miniswhite_tiff_is_inverted_as_tiff_6_says(tmp_path, dtype):
    counts = _frames(2, dtype=dtype)
    top = np.iinfo(dtype).max  # 2**BitsPerSample - 1
    path = tmp_path / "w.tif"
    tifffile.imwrite(path, top - counts, photometric="miniswhite")
    frames = _both_ways(path)
    assert frames.dtype == dtype
    np.testing.assert_array_equal(frames, counts)


def test_miniswhite_tiff_ignores_max_sample_value_and_says_so(tmp_path):
    """TIFF 6.0: MaxSampleValue is statistics only; the inversion is against 2**16 - 1."""
    counts = _frames(1)
    path = tmp_path / "w12.tif"
    tifffile.imwrite(path, 4095 - counts, photometric="miniswhite", extratags=[(281, "H", 1, 4095, True)])
    with pytest.warns(UserWarning, match="MaxSampleValue 4095 is statistics only"):
        frames = read(path).data
    np.testing.assert_array_equal(frames, 65535 - (4095 - counts.astype(np.int64)))


@pytest.mark.parametrize("dtype", [np.float32, np.int16])
def test_miniswhite_tiff_of_signed_or_float_pixels_is_refused(tmp_path, dtype):
    path = tmp_path / "w.tif"
    tifffile.imwrite(path, np.ones((4, 5), dtype), photometric="miniswhite")
    with pytest.raises(FormatError, match="MinIsWhite .* unsigned integers only"):
        read(path)


def test_palette_tiff_is_refused(tmp_path):
    path = tmp_path / "p.tif"
    cmap = np.repeat(((255 - np.arange(256)) * 257)[None].astype(np.uint16), 3, axis=0)
    tifffile.imwrite(path, np.arange(20, dtype=np.uint8).reshape(4, 5), photometric="palette", colormap=cmap)
    with pytest.raises(FormatError, match="palette .* not detector counts"):
        read(path)


def _imagej(path, stored, cf, coefficients):
    lines = ["ImageJ=1.54f", f"cf={cf}"] + [f"c{k}={c}" for k, c in enumerate(coefficients)] + ["vunit=Gray Value", ""]
    tifffile.imwrite(path, stored, description="\n".join(lines), photometric="minisblack", metadata=None)


def test_imagej_signed_16_bit_reads_as_int16(tmp_path):
    """ImageJ stores signed 16-bit as uint16 + its straight-line calibration cf=0, c0=-32768, c1=1."""
    signed = np.array([[[-32768, -2000, -1], [0, 2095, 32767]]], np.int16)
    path = tmp_path / "s.tif"
    _imagej(path, (signed.astype(np.int32) + 32768).astype(np.uint16), 0, (-32768.0, 1.0))
    frames = _both_ways(path)
    assert frames.dtype == np.int16
    np.testing.assert_array_equal(frames, signed)


def test_imagej_straight_line_calibration_is_applied(tmp_path):
    stored = _frames(1)
    path = tmp_path / "line.tif"
    _imagej(path, stored, 0, (-1.5, 0.25))
    frames = _both_ways(path)
    assert frames.dtype == np.float32
    np.testing.assert_allclose(frames, -1.5 + 0.25 * stored.astype(np.float64), rtol=0, atol=1e-3)


def test_imagej_no_calibration_reads_stored_values_as_imagej_shows(tmp_path):
    """cf=20 is ImageJ's NONE: it ignores c0/c1 then (its FileOpener), so the values are as stored."""
    stored = _frames(1)
    path = tmp_path / "none.tif"
    _imagej(path, stored, 20, (-32768.0, 1.0))
    with pytest.warns(UserWarning, match="cf=20"):
        frames = read(path).data
    np.testing.assert_array_equal(frames, stored)


def test_imagej_calibration_function_not_implemented_is_refused(tmp_path):
    path = tmp_path / "poly.tif"
    _imagej(path, _frames(1), 1, (1.0, 2.0, 3.0))  # POLY2
    with pytest.raises(FormatError, match="cf=1 is not read"):
        read(path)


def test_tiff_12_bit_counts_in_16_bit_words_read_as_words(tmp_path):
    counts = _frames(1)
    path = tmp_path / "w.tif"
    tifffile.imwrite(path, counts[0], photometric="minisblack", rowsperstrip=7)
    _set_short_tag(path, 258, 12)  # BitsPerSample 12 over 16-bit words, as some panel software
    with pytest.warns(UserWarning, match="BitsPerSample 12 but its strips hold one 16-bit word"):
        frames = _both_ways(path)
    np.testing.assert_array_equal(frames, counts)


@pytest.mark.parametrize("bits", [1, 4, 7])
@pytest.mark.parametrize("word", ["<u1", "<u2"])
def test_tiff_low_bit_counts_in_whole_words_read_as_words(tmp_path, bits, word):
    """BitsPerSample 1..7 over 8- or 16-bit words (a byte a pixel, as the 12-bit case above):
    every count as stored, in the word's dtype; unpacking them as packed bits gives garbage."""
    counts = np.random.default_rng(bits).integers(0, 1 << bits, (1, 30, 41)).astype(word)
    path = tmp_path / "w.tif"
    tifffile.imwrite(path, counts[0], photometric="minisblack", rowsperstrip=7)
    _set_short_tag(path, 258, bits)
    bytes_ = np.dtype(word).itemsize
    with pytest.warns(UserWarning, match=f"BitsPerSample {bits} but its strips hold one {8 * bytes_}-bit word"):
        frames = _both_ways(path)
    assert frames.dtype == np.dtype(word).newbyteorder("=")
    np.testing.assert_array_equal(frames, counts)


@pytest.mark.parametrize("bits", [1, 2, 4, 6, 7])
def test_tiff_packed_low_bit_counts_unpack(tmp_path, bits):
    """Genuinely packed 1..7-bit samples (tifffile writes them, rows padded to whole bytes) read
    value for value: 41 columns leave every row's last byte part-filled."""
    counts = np.random.default_rng(bits).integers(0, 1 << bits, (2, 30, 41)).astype(np.uint8)
    path = tmp_path / "p.tif"
    with tifffile.TiffWriter(path) as tif:
        for frame in counts:
            tif.write(frame, photometric="minisblack", bitspersample=bits, rowsperstrip=4)
    frames = _both_ways(path)
    np.testing.assert_array_equal(frames.astype(np.uint8), counts)


@pytest.mark.parametrize("predictor", [False, True])
@pytest.mark.parametrize("compression", ["zlib", "lzw", "packbits", "zstd"])
def test_tiff_12_bit_counts_in_compressed_16_bit_words_read_as_words(tmp_path, compression, predictor):
    """Compressed strips decoding to one 16-bit word a pixel under BitsPerSample 12 (tifffile
    would unpack them as packed bits): every count as stored, the horizontal predictor undone."""
    counts = _frames(2)
    path = tmp_path / "z.tif"
    with tifffile.TiffWriter(path) as tif:
        for frame in counts:
            tif.write(frame, photometric="minisblack", rowsperstrip=7, compression=compression, predictor=predictor)
    for page in range(2):
        _set_short_tag(path, 258, 12, page=page)
    with pytest.warns(UserWarning, match="BitsPerSample 12 but its strips hold one 16-bit word"):
        frames = _both_ways(path)
    np.testing.assert_array_equal(frames, counts)


def test_tiff_12_bit_packed_still_unpacks(tmp_path):
    counts = _frames(1, cols=41)  # odd width: each row padded to a whole byte
    path = tmp_path / "p.tif"
    tifffile.imwrite(path, counts[0], photometric="minisblack", bitspersample=12, rowsperstrip=4)
    np.testing.assert_array_equal(read(path).data, counts)


def test_tiff_12_bit_pages_packed_and_in_words_are_refused(tmp_path):
    counts = _frames(2)
    path = tmp_path / "mixed.tif"
    with tifffile.TiffWriter(path) as tif:
        tif.write(counts[0], photometric="minisblack", bitspersample=12)  # packed
        tif.write(counts[1], photometric="minisblack")
    _set_short_tag(path, 258, 12, page=1)  # words saying 12 bits
    # one error, not "read as 16-bit words" first (said before the stack was refused, review s33)
    with warnings.catch_warnings(), pytest.raises(FormatError, match="not one stack"):
        warnings.simplefilter("error")
        read(path)


def test_tiff_stack_whose_first_page_claims_fewer_bits_is_one_error(tmp_path):
    """A 16-bit stack whose page 0 BitsPerSample byte was hit (16 -> 4): page 0 alone reads as
    16-bit words, but pages 1 and 2 say 16 bits: the stack is refused in one error. It warned
    "read as 16-bit words" first, of a file it then refused."""
    path = tmp_path / "hit.tif"
    tifffile.imwrite(path, _frames(3), photometric="minisblack")
    _set_short_tag(path, 258, 4, page=0)
    with warnings.catch_warnings(), pytest.raises(FormatError, match=r"hit\.tif: TIFF frame 1 .*not one stack"):
        warnings.simplefilter("error")
        read(path)


def _packed(counts, bits=12):
    """``counts`` (rows, cols) packed as TIFF packs samples of ``bits`` bits: most significant bit
    first, each row starting on a byte (numpy's own bit handling, independent of the reader's)."""
    planes = (counts.astype(np.uint16)[..., None] >> np.arange(bits - 1, -1, -1)) & 1
    return np.packbits(planes.astype(np.uint8).reshape(counts.shape[0], -1), axis=1)


def _packed_or_words_pages(path, counts, packed, compression, tile=None):
    """A TIFF whose pages say BitsPerSample 12, page k holding packed 12-bit rows if
    ``packed[k]`` else 16-bit words (tifffile writes no compressed packed samples: the packed
    bytes are written as 8-bit pixels and the width and bit tags set after)."""
    cols = counts.shape[-1]
    with tifffile.TiffWriter(path) as tif:
        for frame, pack in zip(counts, packed):
            shape = {"rowsperstrip": 5} if tile is None else {"tile": (tile[0], tile[1] * (3 if pack else 2) // 2)}
            tif.write(_packed(frame) if pack else frame, photometric="minisblack", compression=compression, **shape)
    for page, pack in enumerate(packed):
        _set_short_tag(path, 256, cols, page=page)
        _set_short_tag(path, 258, 12, page=page)
        if tile is not None and pack:
            _set_short_tag(path, 322, tile[1], page=page)


@pytest.mark.parametrize("packed", [(True, False), (False, True)], ids=["packed-then-words", "words-then-packed"])
@pytest.mark.parametrize("compression", ["lzw", "zlib", "lzma"])
def test_tiff_compressed_pages_packed_and_in_words_are_refused(tmp_path, compression, packed):
    """BitsPerSample 12 on every page, compressed, page 0 holding packed rows and page 1 16-bit
    words (or the reverse): only page 0 was decoded at open, so page 1's words were unpacked as
    packed bits, silently garbage. Every compressed page's decoded strips now say how it is
    stored, and a page unlike page 0 is refused in one line naming both."""
    counts = _frames(2, rows=20)
    path = tmp_path / "mixed.tif"
    _packed_or_words_pages(path, counts, packed, compression)
    pages = "12-bit counts in 16-bit words, page 0 packed 12-bit rows"
    pages = pages if packed[0] else "packed 12-bit rows, page 0 12-bit counts in 16-bit words"
    with warnings.catch_warnings(), pytest.raises(FormatError, match=rf"mixed\.tif: TIFF page 1 holds {pages}"):
        warnings.simplefilter("ignore")
        _both_ways(path)


@pytest.mark.parametrize("compression", [None, "lzw", "zlib", "lzma"])
def test_tiff_compressed_packed_12_bit_pages_unpack(tmp_path, compression):
    """Packed 12-bit rows under each compression (odd width: rows end part-way into a byte),
    strips or tiles: every count as written."""
    counts = _frames(3, rows=20, cols=41)
    path = tmp_path / "packed.tif"
    _packed_or_words_pages(path, counts, (True,) * 3, compression)
    np.testing.assert_array_equal(_both_ways(path), counts)
    tiled = _frames(3, rows=40, cols=50)
    _packed_or_words_pages(path, tiled, (True,) * 3, compression, tile=(16, 32))
    np.testing.assert_array_equal(_both_ways(path), tiled)


@pytest.mark.parametrize("compression, predictor", [(None, False), ("lzw", False), ("zlib", True), ("zstd", True)])
@pytest.mark.parametrize("bits, word", [(12, "<u2"), (4, "<u1")])
def test_tiff_tiled_counts_in_whole_words_read_as_words(tmp_path, bits, word, compression, predictor):
    """Tiles holding one 8- or 16-bit word a pixel under BitsPerSample 12 (or 4), 40 x 50 in
    16 x 16 tiles (the right and bottom ones padded): the tiles went to tifffile, which unpacked
    the words as packed bits, silently garbage. Every count as stored, the predictor undone."""
    counts = np.random.default_rng(bits).integers(0, 1 << bits, (2, 40, 50)).astype(word)
    path = tmp_path / "tiled.tif"
    with tifffile.TiffWriter(path) as tif:
        for frame in counts:
            tif.write(frame, photometric="minisblack", tile=(16, 16), compression=compression, predictor=predictor)
    for page in range(2):
        _set_short_tag(path, 258, bits, page=page)
    with pytest.warns(
        UserWarning, match=f"BitsPerSample {bits} but its tiles hold one {8 * np.dtype(word).itemsize}-bit word"
    ):
        frames = _both_ways(path)
    assert frames.dtype == np.dtype(word).newbyteorder("=")
    np.testing.assert_array_equal(frames, counts)


def test_tiff_12_bit_strips_of_neither_size_are_refused(tmp_path):
    path = tmp_path / "odd.tif"
    tifffile.imwrite(path, _frames(1, dtype="<u4")[0], photometric="minisblack")
    _set_short_tag(path, 258, 12)  # 4 bytes a pixel: neither packed 12-bit nor words
    with pytest.raises(FormatError, match="fit neither packed 12-bit rows nor 16-bit words"):
        read(path)


@pytest.mark.parametrize(
    "orientation, view",
    [
        (1, lambda a: a),
        (2, lambda a: a[:, ::-1]),
        (3, lambda a: a[::-1, ::-1]),
        (4, lambda a: a[::-1]),
        (5, lambda a: a.T),
        (6, lambda a: np.rot90(a, -1)),  # row 0 at the right: turned clockwise to view
        (7, lambda a: a.T[::-1, ::-1]),  # PIL's exif_transpose: TRANSVERSE
        (8, lambda a: np.rot90(a, 1)),
    ],
)
def test_tiff_orientation_is_applied_as_a_viewer_does(tmp_path, orientation, view):
    """TIFF 6.0's Orientation names where stored row 0 and column 0 are seen (5..8 swap rows and
    columns): frames read so that row 0 is the top and column 0 the left, as a viewer shows them."""
    stored = _frames(2)
    path = tmp_path / "o.tif"
    tifffile.imwrite(path, stored, photometric="minisblack", extratags=[(274, "H", 1, orientation, False)])
    frames = _both_ways(path)
    np.testing.assert_array_equal(frames, np.stack([view(f) for f in stored]))
    assert read(path).meta.get("orientation", 1) == orientation


def test_tiff_ifd_chain_that_loops_is_named_a_loop(tmp_path):
    import struct

    path = tmp_path / "loop.tif"
    tifffile.imwrite(path, _frames(2), photometric="minisblack")
    with tifffile.TiffFile(path) as tif:
        first, second = tif.pages[0].offset, tif.pages[1].offset
    data = bytearray(path.read_bytes())
    entries = struct.unpack_from("<H", data, second)[0]
    struct.pack_into("<I", data, second + 2 + 12 * entries, first)  # page 1's next IFD: page 0
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="IFD chain loops: the IFD after page 1 is page 0's again"):
        read(path)


@pytest.mark.parametrize("compression", ["zlib", "lzw", "zstd"])
@pytest.mark.parametrize("layout", ["strip", "tile"])
def test_tiff_strip_or_tile_never_written_is_refused_not_read_as_zeros(tmp_path, compression, layout):
    """A strip or tile with offset 0 and byte count 0 holds no data ("sparse", as a writer that
    preallocated the page and stopped leaves it): tifffile fills it with 0, which a calibration
    takes for a dead line and a correction for non-positive pixels. Compressed pages are not
    covered by the byte count the page's pixels need, so the empty one is named."""
    frame = _frames(1, 64, 80)[0]
    path = tmp_path / "sparse.tif"
    kw = dict(rowsperstrip=8) if layout == "strip" else dict(tile=(16, 16))
    tifffile.imwrite(path, frame, compression=compression, **kw)
    names = ("StripOffsets", "StripByteCounts") if layout == "strip" else ("TileOffsets", "TileByteCounts")
    with tifffile.TiffFile(path, mode="r+b") as tif:
        for name in names:
            tag = tif.pages[0].tags[name]
            tag.overwrite([0 if k == 3 else v for k, v in enumerate(tag.value)])
    with pytest.raises(FormatError, match=f"sparse.tif: TIFF page 0: {layout} 3 of .* holds no data"):
        read(path)


def test_tiff_compressed_strips_all_written_still_read(tmp_path):
    """The check above leaves a complete compressed page alone, value for value."""
    frame = _frames(1, 64, 80)[0]
    path = tmp_path / "full.tif"
    tifffile.imwrite(path, frame, compression="zlib", rowsperstrip=8)
    np.testing.assert_array_equal(read(path).data[0], frame)


# ------------------------------------------------------------------------------------------------
# HDF5 images and NeXus defaults of other software
# ------------------------------------------------------------------------------------------------


def _bytes_read() -> int:
    """What this process has read through read() system calls (Linux's /proc/self/io rchar)."""
    with open("/proc/self/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("rchar:"))


@pytest.mark.skipif(not os.path.exists("/proc/self/io"), reason="needs Linux's /proc/self/io")
@pytest.mark.parametrize("chunks", [(10, 1, 700), (4, 5, 700), (3, 64, 100)])
def test_hdf5_chunks_spanning_frames_are_read_once_each(chunks, tmp_path):
    """A stack whose chunks hold a row (or a block) of several frames, more of them than
    libhdf5's chunk cache holds (8 MiB, h5py's default with HDF5 2.0): read() read and
    decompressed every chunk once per frame it holds, 10 times the file here. Read in
    chunk-aligned blocks, the file's bytes are read about once; every value as stored, inverted
    as its attribute says, and cut by an n= hint."""
    counts = _frames(10, rows=640, cols=700)
    path = tmp_path / "rows.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("data", data=counts, chunks=chunks, compression="gzip")
    size = path.stat().st_size
    before = _bytes_read()
    frames = read(path, dataset="data").data
    assert _bytes_read() - before < 3 * size
    np.testing.assert_array_equal(frames, counts)
    np.testing.assert_array_equal(_both_ways(path, dataset="data", n=7), counts[:7])
    with h5py.File(path, "a") as h5:
        h5["data"].attrs["IMAGE_WHITE_IS_ZERO"] = 1
        h5["data"].attrs["CLASS"] = np.bytes_("IMAGE")
    np.testing.assert_array_equal(_both_ways(path, dataset="data"), 65535 - counts)


def test_hdf5_image_with_a_palette_is_refused_and_one_without_is_read(tmp_path):
    """HDF5's image API labels every 8-bit image IMAGE_INDEXED (H5IMmake_image_8bit), greyscale ones
    too; only an attached PALETTE makes its values colour-table indices."""
    pixels = np.arange(20 * 32, dtype=np.uint8).reshape(20, 32)
    path = tmp_path / "im.h5"
    with h5py.File(path, "w") as f:
        for name in ("grey", "pal"):
            ds = f.create_dataset(name, data=pixels)
            ds.attrs["CLASS"] = np.bytes_("IMAGE")
            ds.attrs["IMAGE_SUBCLASS"] = np.bytes_("IMAGE_INDEXED")
        table = f.create_dataset("table", data=np.zeros((256, 3), np.uint8))
        f["pal"].attrs["PALETTE"] = np.array([table.ref], dtype=h5py.ref_dtype)
    np.testing.assert_array_equal(read(path, dataset="grey").data, pixels[None])
    with pytest.raises(FormatError, match="palette image"):
        read(path, dataset="pal")


@pytest.mark.parametrize("shape", [(20, 32, 3), (3, 20, 32)])
def test_hdf5_truecolour_image_is_refused_not_read_as_frames(tmp_path, shape):
    path = tmp_path / "rgb.h5"
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("img", data=np.zeros(shape, np.uint8))
        ds.attrs["CLASS"] = np.bytes_("IMAGE")
        ds.attrs["IMAGE_SUBCLASS"] = np.bytes_("IMAGE_TRUECOLOR")
    with pytest.raises(FormatError, match="colour image"):
        read(path, dataset="img")


def _hdf5_image(path, name, data, white_is_zero, subclass="IMAGE_GRAYSCALE"):
    """A dataset labelled as the HDF5 Image spec 1.2 says, as h5py users write it (HDFView shows it)."""
    with h5py.File(path, "a") as f:
        ds = f.create_dataset(name, data=data)
        ds.attrs["CLASS"] = np.bytes_("IMAGE")
        ds.attrs["IMAGE_VERSION"] = np.bytes_("1.2")
        ds.attrs["IMAGE_SUBCLASS"] = np.bytes_(subclass)
        ds.attrs["IMAGE_WHITE_IS_ZERO"] = np.asarray(white_is_zero, np.uint8)
        ds.attrs["IMAGE_MINMAXRANGE"] = np.array([data.min(), data.max()], data.dtype)


@pytest.mark.parametrize("dtype", ["u1", "<u2", ">u2"])
def test_hdf5_white_is_zero_image_is_inverted_as_a_miniswhite_tiff(tmp_path, dtype):
    """HDF5 Image spec 1.2: IMAGE_WHITE_IS_ZERO=1 on a greyscale image means 0 is white. As TIFF's
    MinIsWhite, the counts are the type's maximum minus the stored values; IMAGE_MINMAXRANGE is the
    data's own min and max (statistics), not the scale, so it changes nothing."""
    counts = _frames(2, dtype=dtype)
    top = np.iinfo(counts.dtype).max
    path = tmp_path / "wiz.h5"
    _hdf5_image(path, "inverted", top - counts, 1)
    _hdf5_image(path, "plain", counts, 0)
    frames = _both_ways(path, dataset="inverted")
    assert frames.dtype == np.dtype(dtype).newbyteorder("=")
    np.testing.assert_array_equal(frames, counts)
    assert read(path, dataset="inverted").meta["white_is_zero"] is True
    plain = read(path, dataset="plain")
    np.testing.assert_array_equal(plain.data, counts)
    assert "white_is_zero" not in plain.meta


@pytest.mark.parametrize(
    ("dtype", "subclass", "flag", "match"),
    [
        ("<f4", "IMAGE_GRAYSCALE", 1, "float32 pixels: the inversion .* unsigned integers only"),
        ("<i2", "IMAGE_GRAYSCALE", 1, "int16 pixels: the inversion .* unsigned integers only"),
        ("u1", "IMAGE_BITMAP", 1, "with a bitmap"),
        ("<u2", "IMAGE_GRAYSCALE", 7, "IMAGE_WHITE_IS_ZERO is 7: .* defines 0 and 1"),
    ],
)
def test_hdf5_white_is_zero_image_without_a_defined_inversion_is_refused(tmp_path, dtype, subclass, flag, match):
    path = tmp_path / "wiz.h5"
    _hdf5_image(path, "img", np.ones((4, 5), dtype), flag, subclass)
    with pytest.raises(FormatError, match=match):
        read(path, dataset="img")


@pytest.mark.parametrize(
    "source, on_disk",
    [
        ("src.h5", "src.h5"),  # relative: beside the file
        # a literal %% in a fixed mapping is the file a%b.h5 to libhdf5 (no block number): it was
        # sent to the %b check, which skipped a fixed mapping, and read as zeros
        ("a%%b.h5", "a%b.h5"),
    ],
)
def test_hdf5_virtual_dataset_with_a_missing_source_is_refused_naming_it(tmp_path, source, on_disk):
    stack = _frames(2)
    layout = h5py.VirtualLayout(shape=stack.shape, dtype=stack.dtype)
    layout[:] = h5py.VirtualSource(source, "data", shape=stack.shape)
    path = tmp_path / "vds.h5"
    with h5py.File(path, "w") as f:
        f.create_virtual_dataset("scan/data", layout, fillvalue=0)
    with pytest.raises(FormatError, match=f"source file {on_disk} is missing"):
        read(path, dataset="scan/data", allow_external=True)
    with h5py.File(tmp_path / on_disk, "w") as f:
        f["data"] = stack
    np.testing.assert_array_equal(read(path, dataset="scan/data", allow_external=True).data, stack)


def _block_vds(path, rows, cols):
    """A virtual dataset of one frame per source file, ``src_0.h5``, ``src_1.h5``, ... (``%b``: the
    block number of an unlimited selection), written with h5py's low-level API (the high-level
    VirtualLayout cannot map an unlimited selection)."""
    vspace = h5py.h5s.create_simple((0, rows, cols), (h5py.h5s.UNLIMITED, rows, cols))
    vspace.select_hyperslab((0, 0, 0), (h5py.h5s.UNLIMITED, 1, 1), stride=(1, 1, 1), block=(1, rows, cols))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_virtual(vspace, b"src_%b.h5", b"data", h5py.h5s.create_simple((1, rows, cols)))
    with h5py.File(path, "w") as f:
        h5py.h5d.create(f.id, b"frames", h5py.h5t.py_create(np.dtype("<u2")), vspace, dcpl=dcpl)


@pytest.mark.parametrize("missing", [None, 0, 1, 2, 3])
def test_hdf5_virtual_dataset_of_block_sources_read_short_is_refused(tmp_path, missing):
    """libhdf5 sizes a %b virtual dataset by opening src_0, src_1, ... until one fails: with src_1
    gone the 4-frame stack read as 1 frame, no error (with src_0 gone, as none). A file of the
    pattern past the first one not read shows the gap; a missing last one leaves no trace."""
    stack = _frames(4, 5, 6)
    for k, frame in enumerate(stack):
        if k != missing:
            with h5py.File(tmp_path / f"src_{k}.h5", "w") as f:
                f["data"] = frame[None]
    (tmp_path / "src_01.h5").write_bytes(b"")  # not source 1: libhdf5 prints the number plainly
    path = tmp_path / "vds.h5"
    _block_vds(path, 5, 6)
    if missing in (None, 3):
        n = 4 if missing is None else 3
        np.testing.assert_array_equal(read(path, dataset="frames", allow_external=True).data, stack[:n])
        return
    match = "first source src_0.h5:data" if missing == 0 else f"src_{missing}.h5:data .* after {missing} block"
    with pytest.raises(FormatError, match=match):
        read(path, dataset="frames", allow_external=True)


def _interleaved_vds(path, rows, cols):
    """Even frames from ``a_%b.h5``, odd ones from ``b_%b.h5``: two block mappings of stride 2."""
    vspace = h5py.h5s.create_simple((0, rows, cols), (h5py.h5s.UNLIMITED, rows, cols))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    for first, name in ((0, b"a_%b.h5"), (1, b"b_%b.h5")):
        vspace.select_hyperslab((first, 0, 0), (h5py.h5s.UNLIMITED, 1, 1), stride=(2, 1, 1), block=(1, rows, cols))
        dcpl.set_virtual(vspace, name, b"data", h5py.h5s.create_simple((1, rows, cols)))
    with h5py.File(path, "w") as f:
        h5py.h5d.create(f.id, b"frames", h5py.h5t.py_create(np.dtype("<u2")), vspace, dcpl=dcpl)


def test_hdf5_virtual_dataset_whose_shorter_block_mapping_misses_sources_is_refused(tmp_path):
    """libhdf5 gives two mappings the longer one's extent: the shorter one's missing blocks read as
    the fill value (4 files of b_, 2 of a_: frames 4 and 6 of zeros), so every covered block is looked for."""
    stack = _frames(8, 5, 6)
    path = tmp_path / "vds.h5"
    _interleaved_vds(path, 5, 6)
    for k in range(4):
        for prefix, first in (("a", 0), ("b", 1)):
            if prefix == "a" and k >= 2:
                continue
            with h5py.File(tmp_path / f"{prefix}_{k}.h5", "w") as f:
                f["data"] = stack[2 * k + first][None]
    with pytest.raises(FormatError, match="source file a_2.h5 is missing"):
        read(path, dataset="frames", allow_external=True)
    for k in (2, 3):
        with h5py.File(tmp_path / f"a_{k}.h5", "w") as f:
            f["data"] = stack[2 * k][None]
    np.testing.assert_array_equal(read(path, dataset="frames", allow_external=True).data, stack)


def test_hdf5_block_sources_topped_up_from_the_working_directory_are_refused(tmp_path, monkeypatch):
    """libhdf5 looks for each block's file beside the virtual file, then in the working directory:
    a series of 2 read from a folder holding another series' src_0..src_4 came back as 5 frames,
    3 of them the other series'."""
    ours, other = tmp_path / "ours", tmp_path / "other"
    for folder, n, value in ((ours, 2, 100), (other, 5, 900)):
        folder.mkdir()
        for k in range(n):
            with h5py.File(folder / f"src_{k}.h5", "w") as f:
                f["data"] = np.full((1, 5, 6), value + k, np.uint16)
    _block_vds(ours / "vds.h5", 5, 6)
    assert read(ours / "vds.h5", dataset="frames", allow_external=True).data[:, 0, 0].tolist() == [100, 101]
    monkeypatch.chdir(other)
    with pytest.raises(FormatError, match="found in 2 folders"):
        read(ours / "vds.h5", dataset="frames", allow_external=True)


def test_hdf5_block_source_check_lists_one_folder_not_its_tree(tmp_path):
    """The files past the last block are looked for in the sources' folder, not its tree (a name of
    "%b%b" made the glob "**"): a folder deeper down named as a later source ("11") is none."""
    with h5py.File(tmp_path / "00", "w") as f:
        f["data"] = _frames(1, 5, 6)
    (tmp_path / "tree" / "11").mkdir(parents=True)
    vspace = h5py.h5s.create_simple((0, 5, 6), (h5py.h5s.UNLIMITED, 5, 6))
    vspace.select_hyperslab((0, 0, 0), (h5py.h5s.UNLIMITED, 1, 1), stride=(1, 1, 1), block=(1, 5, 6))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_virtual(vspace, b"%b%b", b"data", h5py.h5s.create_simple((1, 5, 6)))
    with h5py.File(tmp_path / "vds.h5", "w") as f:
        h5py.h5d.create(f.id, b"frames", h5py.h5t.py_create(np.dtype("<u2")), vspace, dcpl=dcpl)
    assert read(tmp_path / "vds.h5", dataset="frames", allow_external=True).data.shape == (1, 5, 6)


def test_hdf5_white_is_zero_flag_on_an_indexed_image_or_written_as_zero_changes_nothing(tmp_path):
    """The spec's table: IMAGE_WHITE_IS_ZERO does not apply to IMAGE_INDEXED (read as stored); a
    writer's 0.0 or "0" means 0 as the spec's unsigned char does."""
    counts = _frames(1, dtype="u1")[0]
    path = tmp_path / "wiz.h5"
    _hdf5_image(path, "indexed", counts, 1, "IMAGE_INDEXED")
    _hdf5_image(path, "float0", counts, 0)
    _hdf5_image(path, "text0", counts, 0)
    with h5py.File(path, "a") as f:
        f["float0"].attrs["IMAGE_WHITE_IS_ZERO"] = 0.0
        f["text0"].attrs["IMAGE_WHITE_IS_ZERO"] = np.bytes_("0")
    for name in ("indexed", "float0", "text0"):
        frames = read(path, dataset=name)
        np.testing.assert_array_equal(frames.data[0], counts)
        assert "white_is_zero" not in frames.meta


def test_nexus_default_given_as_a_path_is_followed(tmp_path):
    """ESRF's Lima/bliss: the NXentry's @default is "measurement/pco", which silx follows."""
    stack = _frames(3)
    path = tmp_path / "lima.h5"
    with h5py.File(path, "w") as f:
        entry = _nx_class(f.create_group("entry_0000"), "NXentry")
        _nx_class(entry.create_group("instrument/pco"), "NXdetector")["data"] = stack
        plot = _nx_class(entry.create_group("measurement/pco"), "NXdata")
        plot.attrs["signal"] = "data"
        plot["data"] = h5py.SoftLink("/entry_0000/instrument/pco/data")
        entry.attrs["default"] = "measurement/pco"
        f.attrs["default"] = "entry_0000"
    np.testing.assert_array_equal(read(path).data, stack)


def test_nexus_signal_naming_a_missing_dataset_says_so(tmp_path):
    path = tmp_path / "missing.h5"
    with h5py.File(path, "w") as f:
        plot = _nx_class(_nx_class(f.create_group("entry"), "NXentry").create_group("plot"), "NXdata")
        plot.attrs["signal"] = "nothere"
        plot["other"] = _frames(1)
    with pytest.raises(FormatError, match="@signal names 'nothere', which /entry/plot does not hold"):
        read(path)


def test_nexus_signal_that_is_an_external_link_is_refused_by_name_or_read_when_allowed(tmp_path):
    """Dectris/Eiger-style masters and many beamline writers make the NXdata's @signal an
    external link to the file holding the frames. The signal was passed over as if the file named
    no frames: refused as holding "no 2-D or 3-D dataset" (wrong, and not naming the link), and
    still so with allow_external=True, which is there to read it."""
    stack = _frames(3)
    with h5py.File(tmp_path / "data_000001.h5", "w") as f:
        f["data"] = stack
    path = tmp_path / "master.h5"
    with h5py.File(path, "w") as f:
        entry = _nx_class(f.create_group("entry"), "NXentry")
        plot = _nx_class(entry.create_group("data"), "NXdata")
        plot.attrs["signal"] = "data"
        plot["data"] = h5py.ExternalLink("data_000001.h5", "/data")
        entry.attrs["default"] = "data"
        f.attrs["default"] = "entry"
    with pytest.raises(
        FormatError, match=r"/entry/data/data is an external link to data_000001\.h5:/data.*--allow-external"
    ):
        read(path)
    f = read(path, allow_external=True)
    assert f.meta["dataset"] == "/entry/data/data"
    np.testing.assert_array_equal(f.data, stack)


def test_imagej_calibration_passed_on_with_signed_pixels_is_not_applied_again(tmp_path):
    """tifffile writes int16 pixels with an ImageJ description copied from a signed 16-bit file
    (cf=0, c0=-32768): the pixels already hold the signed values; ImageJ calibrates only what it
    stores unsigned."""
    signed = np.array([[[-5, 0, 7], [-32768, 1, 32767]]], np.int16)
    path = tmp_path / "i16.tif"
    _imagej(path, signed, 0, (-32768.0, 1.0))
    frames = _both_ways(path)
    assert frames.dtype == np.int16
    np.testing.assert_array_equal(frames, signed)


def test_tiff_14_bit_counts_in_16_bit_words_are_checked_against_14_bits(tmp_path):
    """BitsPerSample 14 over 16-bit words: 14-bit counts up to 16383 are in range (no bit-depth
    warning), which a 12-bit check would call out of range."""
    from radiokit.io import BitDepthWarning

    counts = np.tile(np.array([[[0, 4096, 9000, 12000, 16383]]], np.uint16), (1, 3, 8))  # 3 x 40
    path = tmp_path / "w14.tif"
    tifffile.imwrite(path, counts[0], photometric="minisblack")
    _set_short_tag(path, 258, 14)
    with pytest.warns(UserWarning, match="BitsPerSample 14 but its strips hold one 16-bit word") as seen:
        frames = _both_ways(path)
    assert not [w for w in seen if issubclass(w.category, BitDepthWarning)]
    np.testing.assert_array_equal(frames, counts)


def test_tiff_12_bit_packed_with_its_last_strip_padded_to_a_whole_strip_unpacks(tmp_path):
    """Some writers give a short last strip the byte count of a whole one (libtiff reads it): a
    padded packed strip, not 16-bit words."""
    import struct

    counts = _frames(1, rows=10, cols=40)
    path = tmp_path / "pad.tif"
    tifffile.imwrite(path, counts[0], photometric="minisblack", bitspersample=12, rowsperstrip=4)
    row_bytes = 40 * 12 // 8
    with tifffile.TiffFile(path) as tif:
        tag = tif.pages[0].tags[279]
        assert list(tag.value) == [4 * row_bytes, 4 * row_bytes, 2 * row_bytes]
        offset, fmt = tag.valueoffset, {3: "<H", 4: "<I"}[int(tag.dtype)]
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset + 2 * struct.calcsize(fmt), 4 * row_bytes)
    path.write_bytes(bytes(data) + bytes(2 * row_bytes))  # the padding's bytes exist in the file
    np.testing.assert_array_equal(_both_ways(path), counts)


def test_imagej_miniswhite_is_its_inverting_lut_and_reads_as_stored(tmp_path):
    """ImageJ saves an image shown with an inverting LUT as MinIsWhite with its pixel values
    unchanged, and measures those: they are the data (another writer's MinIsWhite is inverted)."""
    stored = _frames(1)
    path = tmp_path / "lut.tif"
    tifffile.imwrite(path, stored, description="ImageJ=1.54f\n", photometric="miniswhite", metadata=None)
    src = read(path)
    np.testing.assert_array_equal(src.data, stored)
    np.testing.assert_array_equal(_both_ways(path), stored)
    assert src.meta["imagej_inverted_lut"] is True


@pytest.mark.parametrize(
    "name, kw, what",
    [
        ("hyper.tif", {"imagej": True, "metadata": {"axes": "TCYX"}}, "an ImageJ hyperstack of 2 channels"),
        ("stack.ome.tif", {"metadata": {"axes": "TCYX"}}, "an OME-TIFF of 2 channels"),
    ],
)
def test_a_tiff_of_several_channels_is_refused_not_read_as_one_stack(tmp_path, name, kw, what):
    """s32-h4: a two-channel hyperstack (3 time points x 2 channels) read as 6 frames, the channels
    interleaved: calibrate would average one channel's frames with the other's. Each page is a
    greyscale image, so nothing else tells a stack from a hyperstack."""
    path = tmp_path / name
    tifffile.imwrite(path, _frames(6).reshape(3, 2, 30, 40), **kw)
    with pytest.raises(FormatError, match=rf"{name}: {what}, 6 images: .*save each channel as its own file"):
        read(path)


def test_an_ome_tiff_of_several_images_is_refused_not_read_as_one_stack(tmp_path):
    """s32-h4: an OME-TIFF holding two images (series) of one size, such as the darks and the flats,
    read as one stack of 4 frames."""
    path = tmp_path / "two.ome.tif"
    with tifffile.TiffWriter(path, ome=True) as tif:
        tif.write(_frames(2), metadata={"axes": "TYX"})
        tif.write(_frames(2, seed=1), metadata={"axes": "TYX"})
    with pytest.raises(FormatError, match=r"two\.ome\.tif: an OME-TIFF of 2 images \(series\), 4 pages: "):
        read(path)


def test_an_ome_tiff_written_one_frame_at_a_time_reads_as_its_frames(tmp_path):
    """An acquisition script's loop of ``TiffWriter(..., ome=True).write(frame)`` makes one OME
    image (series) per frame: read as frames before s32-h4's refusal of several images, then
    refused (review s32-r2). Series of one 2-D plane each, of one shape and type, are its frames;
    a series of several planes, or of another size, is still refused."""
    frames = _frames(5)
    path = tmp_path / "darks.ome.tif"
    with tifffile.TiffWriter(path, ome=True) as tif:
        for frame in frames:
            tif.write(frame)
    np.testing.assert_array_equal(read(path).data, frames)
    mixed = tmp_path / "mixed.ome.tif"
    with tifffile.TiffWriter(mixed, ome=True) as tif:
        tif.write(frames[0])
        tif.write(frames[1:3], metadata={"axes": "TYX"})
    with pytest.raises(FormatError, match=r"mixed\.ome\.tif: an OME-TIFF of 2 images \(series\)"):
        read(mixed)


@pytest.mark.parametrize("axes", ["ZYX", "TZYX"])
def test_an_ome_or_imagej_stack_of_one_channel_still_reads_in_page_order(tmp_path, axes):
    frames = _frames(6)
    for path, kw in ((tmp_path / "s.ome.tif", {}), (tmp_path / "s.tif", {"imagej": True})):
        tifffile.imwrite(
            path, frames.reshape(2, 3, 30, 40) if axes == "TZYX" else frames, metadata={"axes": axes}, **kw
        )
        np.testing.assert_array_equal(read(path).data, frames)


@pytest.mark.parametrize("kw", [{"imagej": True}, {"ome": True}])
def test_a_plain_stack_tifffile_labels_as_channels_still_reads(tmp_path, kw):
    """tifffile writes a 3-D array's first axis as C (channels) in ImageJ and OME files: those
    are the stacks users write, and read as frames."""
    frames = _frames(3)
    tifffile.imwrite(tmp_path / "s.tif", frames, **kw)
    np.testing.assert_array_equal(read(tmp_path / "s.tif").data, frames)


def test_a_tifffile_file_of_several_series_is_refused_as_an_ome_one_is(tmp_path):
    """s37: tifffile writing (3, R, C) then (2, R, C) read as one stack of 5, without a word: the
    darks' series followed by the flats', calibrated together. An OME-TIFF of several images is
    refused so; this is the same file without the OME XML."""
    frames = _frames(5)
    path = tmp_path / "two.tif"
    with tifffile.TiffWriter(path) as tif:
        tif.write(frames[:3], photometric="minisblack")
        tif.write(frames[3:], photometric="minisblack")
    with pytest.raises(
        FormatError, match=r"two\.tif: a TIFF of 2 images \(series\) of shapes \(3, 30, 40\), \(2, 30, 40\)"
    ):
        read(path)
    res = run_cli("info", path)
    assert res.returncode != 0 and "2 images (series)" in res.stderr and "save each" in res.stderr, res.stderr


def test_a_tifffile_file_of_one_frame_per_series_still_reads(tmp_path):
    """An acquisition loop's one write per frame makes a series per frame, all alike: frames."""
    frames = _frames(3)
    path = tmp_path / "loop.tif"
    with tifffile.TiffWriter(path) as tif:
        for frame in frames:
            tif.write(frame)
    np.testing.assert_array_equal(read(path).data, frames)


@pytest.mark.parametrize("kw", [{}, {"imagej": True, "metadata": {"axes": "TZYX"}}])
def test_a_4d_tiff_series_is_read_flat_and_info_says_so(tmp_path, kw):
    """s37: a (2, 5, R, C) series read as 10 frames without a note; as an ImageJ hyperstack of
    slices and time points is read (frames in the file's order), now with a line in info."""
    frames = _frames(10).reshape(2, 5, 30, 40)
    path = tmp_path / "four.tif"
    tifffile.imwrite(path, frames, **kw)
    got = read(path)
    np.testing.assert_array_equal(got.data, frames.reshape(10, 30, 40))
    res = run_cli("info", path)
    assert res.returncode == 0 and "read flat" in res.stdout and "2 x 5" in res.stdout, res.stdout


@pytest.mark.parametrize(
    "shape, axes",
    [((5, 30, 1), "ZYX"), ((5, 1, 30), "ZYX"), ((2, 3, 30, 1), "TZYX"), ((4, 1, 1), "TYX")],
)
def test_a_tifffile_stack_of_one_column_frames_reads_as_its_frames(tmp_path, shape, axes):
    """s46: tifffile drops an array's trailing 1s from the pages it stores, so (5, 30, 1) frames
    of one column, axes "ZYX", are one 5 x 30 page: read as one 5 x 30 frame, transposed and
    without its 5 frames. The axes its description gives say which are rows and columns."""
    frames = _frames(math.prod(shape[:-2]), *shape[-2:])
    path = tmp_path / "columns.tif"
    kw = {"metadata": {"axes": axes}, "photometric": "minisblack"}  # (a 3 or 4 before YX is no RGB)
    tifffile.imwrite(path, frames.reshape(shape), **kw)
    np.testing.assert_array_equal(read(path).data, frames)
    np.testing.assert_array_equal(read(path, n=2).data, frames[:2])
    # compressed, its pages are not runs of frames read one at a time: refused, never misread
    tifffile.imwrite(path, frames.reshape(shape), compression="zlib", **kw)
    if shape[-1] == 1:
        with pytest.raises(FormatError, match=rf"columns\.tif: .*{shape[-2]}x1 .*compressed"):
            read(path)
        with tifffile.TiffWriter(path) as tif:  # a series per write, each of such frames
            for _ in range(2):
                tif.write(frames.reshape(shape), **kw)
        with pytest.raises(FormatError, match=r"columns\.tif: .*several such series"):
            read(path)


@pytest.mark.parametrize("shape, axes", [((5, 10, 1), "ZYX"), ((2, 3, 10, 1), "TZYX")])
def test_an_imagej_stack_of_one_column_frames_is_named_so_not_truncated(tmp_path, shape, axes):
    """s47: tifffile's ImageJ writer stores (5, 10, 1) frames, axes ZYX, as one 5 x 10 page under
    images=5, which tifffile's own reader calls invalid: refused as "truncated" (one page), or read
    as 2 frames of 3 x 10, each three frames side by side, with a "cut short?" warning (several)."""
    path = tmp_path / "columns.tif"
    tifffile.imwrite(
        path, _frames(math.prod(shape[:-2]), *shape[-2:]).reshape(shape), imagej=True, metadata={"axes": axes}
    )
    n = math.prod(shape[:-2])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the refusal, not a warning before it
        with pytest.raises(
            FormatError, match=rf"columns\.tif: .*images={n}.* {n} frames of 10x1 .*imagej=True"
        ) as info:
            read(path)
    assert "truncated" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("axes", [None, "YXS"])
def test_a_tifffile_image_of_one_trailing_sample_still_reads_as_one_frame(tmp_path, axes):
    """An (rows, cols, 1) image (a channel axis of one) is one frame, as tifffile's own axes
    (YXQ, YXS) say, and silently: s46 warned at every read of any such image without axes, though
    frames of one column are read so only where the image is too thin to be a radiograph."""
    image = _frames(1, 64, 48)[0]
    path = tmp_path / "image.tif"
    tifffile.imwrite(path, image[..., None], **({"metadata": {"axes": axes}} if axes else {}))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = read(path)
    np.testing.assert_array_equal(got.data, image[None])
    assert not [str(w.message) for w in caught]


@pytest.mark.parametrize("shape", [(5, 30, 1), (200, 3, 1)])
def test_a_thin_tifffile_image_without_axes_says_how_one_column_frames_are_told(tmp_path, shape):
    """A (5, 30, 1) array without axes is a 5 x 30 image to tifffile (YXQ), or 5 frames of 30 x 1
    (a line detector's): read as tifffile reads it, and the one line says how the other is told."""
    data = _frames(1, *shape[:2])[0]
    path = tmp_path / "thin.tif"
    tifffile.imwrite(path, data[..., None])
    with pytest.warns(UserWarning, match=rf"thin\.tif: .*{re.escape(str(shape))} without axes.*'axes': 'ZYX'"):
        got = read(path)
    np.testing.assert_array_equal(got.data, data[None])


def test_a_stack_of_one_column_frames_with_its_axes_given_reads_without_a_warning(tmp_path):
    """s47: 64 frames of 64 x 1 written with axes "ZYX" still got the warning that the stack may
    be rows x cols x n (numpy's dstack): the axes the writer gave leave nothing to guess."""
    frames = _frames(64, 64, 1)
    path = tmp_path / "lines.tif"
    tifffile.imwrite(path, frames, metadata={"axes": "ZYX"}, photometric="minisblack")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = read(path)
    np.testing.assert_array_equal(got.data, frames)
    assert not [str(w.message) for w in caught]


def test_axes_of_another_shape_than_the_pages_read_still_leave_the_dstack_warning(tmp_path):
    """s47 review: the axes a description gives spared the dstack warning whatever shape it gave
    with them: pages of 80 x 4 under {"shape": [4, 80, 80], "axes": "ZYX"} (an edited description,
    which does not say how the pages read) read as 80 frames of 80 x 4 without a word."""
    data = _frames(80, 80, 4)
    path = tmp_path / "edited.tif"
    desc = '{"shape": [4, 80, 80], "axes": "ZYX"}'
    tifffile.imwrite(path, data, photometric="minisblack", description=desc, metadata=None)
    with pytest.warns(UserWarning, match=r"edited\.tif: reads as 80 frames of 80x4; .*dstack"):
        got = read(path)
    np.testing.assert_array_equal(got.data, data)


@needs_itex
@pytest.mark.parametrize("name", ["frame.tif", "frame.h5"])
def test_an_itex_file_under_another_extension_is_named_as_itex(tmp_path, name):
    """s32-h4: a HiPic .img saved or renamed as .tif was refused as "wrong magic b'IMz\\n': a TIFF
    starts with ...", leaving the user to guess what the file is; --format itex reads it."""
    vendor = ITEX_DIR / "photon_counting.img"
    path = tmp_path / name
    path.write_bytes(vendor.read_bytes())
    with pytest.raises(FormatError, match=rf"{name}: starts as a Hamamatsu ITEX \.img does .*format='itex'"):
        read(path)
    np.testing.assert_array_equal(read(path, format="itex").data, read(vendor).data)


def test_a_tiff_with_its_full_image_in_a_subifd_says_so(tmp_path):
    """s32-h4: a TIFF whose top-level page is a preview and whose full image lies in a SubIFD
    (DNG's layout) was refused as holding "only reduced-resolution or mask pages, no full image"."""
    path = tmp_path / "sub.tif"
    with tifffile.TiffWriter(path) as tif:
        tif.write(np.zeros((8, 8), np.uint8), photometric="minisblack", subfiletype=1, subifds=1)
        tif.write(_frames(1)[0], photometric="minisblack")
    with pytest.raises(FormatError, match=r"sub\.tif: .*full image lies in a SubIFD"):
        read(path)


@pytest.mark.parametrize(
    "name, what", [("results.json", "a JSON file"), ("report.html", "an HTML page"), ("notes.txt", "a text file")]
)
def test_a_text_file_is_named_not_measured_against_raw_geometries(tmp_path, name, what):
    """s32-h4: `radiokit info results.json` (what radiokit process writes beside results.h5) said
    "size 5298 bytes matches no C7942 geometry ... pass shape=", as if the text were pixels."""
    path = tmp_path / name
    path.write_text('{"schema_version": "1.2"}\n' if name.endswith(".json") else "<html></html>\n")
    with pytest.raises(FormatError, match=rf"{name}: {what}, not frames"):
        read(path)
    assert read(path, format="raw", shape=(1, path.stat().st_size), dtype="u1").data.size == path.stat().st_size


# ------------------------------------------------------------------------------------------------
# CF packing (netCDF-4 and xarray files are HDF5): scale_factor, add_offset, _FillValue
# ------------------------------------------------------------------------------------------------


def _cf_packed(path, physical, scale, offset, fill=None, attr_dtype=np.float32):
    """Physical values packed into int16 as the CF conventions say (netCDF4-python, xarray's
    ``encoding``): ``packed = round((value - add_offset) / scale_factor)``."""
    packed = np.round((np.nan_to_num(physical) - offset) / scale).astype(np.int16)
    if fill is not None:
        packed[np.isnan(physical)] = fill
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("transmission", data=packed)
        ds.attrs["scale_factor"] = attr_dtype(scale)
        ds.attrs["add_offset"] = attr_dtype(offset)
        if fill is not None:
            ds.attrs["_FillValue"] = np.int16(fill)
    return packed


@pytest.mark.parametrize("attr_dtype", [np.float32, np.float64])
def test_hdf5_cf_packed_frames_read_as_their_physical_values(tmp_path, attr_dtype):
    """A packed int16 read as stored was silently off by the packing: a transmission of 0.5 read as
    -5000. Unpacked, each value is within half a packing step of the one written, in the
    attributes' type (CF: the unpacked type is theirs)."""
    rng = np.random.default_rng(0)
    physical = rng.uniform(0.05, 1.2, (3, 20, 32))
    path = tmp_path / "cf.h5"
    _cf_packed(path, physical, 1e-4, 1.0, attr_dtype=attr_dtype)
    frames = read(path, dataset="transmission")
    assert frames.data.dtype == attr_dtype
    # half a packing step, and the rounding of the type near 1
    np.testing.assert_allclose(frames.data, physical, rtol=0, atol=0.5e-4 + 2 * np.finfo(attr_dtype).eps)


def test_hdf5_cf_fill_value_reads_as_nan_not_as_a_number(tmp_path):
    """A pixel marked missing (``_FillValue``, in packed units) has no value: NaN, which correction
    fills and flags, never the number the fill code unpacks to."""
    physical = np.full((1, 8, 8), 0.7)
    physical[0, 2, 3] = np.nan
    path = tmp_path / "cf.h5"
    _cf_packed(path, physical, 1e-4, 1.0, fill=-32767)
    data = read(path, dataset="transmission").data
    assert np.isnan(data[0, 2, 3]) and np.isfinite(data).sum() == 63


def test_hdf5_float_frames_with_a_cf_fill_value_read_it_as_nan(tmp_path):
    """netCDF-4 marks a float variable's missing pixels with ``_FillValue`` (9.97e36 by default)
    without any packing: read as a number, each such pixel was a transmission of 1e33, silently."""
    frames = np.full((2, 8, 8), 1500.0, np.float32)
    frames[1, 4, 5] = 9.969209968386869e36
    path = tmp_path / "nc.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("counts", data=frames).attrs["_FillValue"] = np.float32(9.969209968386869e36)
        f.create_dataset("plain", data=frames)
    data = read(path, dataset="counts").data
    assert data.dtype == np.float32 and np.isnan(data[1, 4, 5]) and np.isfinite(data).sum() == 127
    assert np.isfinite(read(path, dataset="plain").data).all()  # no attribute: read as stored


@pytest.mark.parametrize("chunks", [None, (2, 8, 8)])
def test_hdf5_cf_fill_value_reads_as_nan_whatever_the_chunks(tmp_path, chunks):
    """Chunks spanning frames are read in blocks straight into the stack (read_direct): the fill
    code was left there as the number 9.97e36, where frame by frame it reads as NaN."""
    frames = np.full((4, 8, 8), 1500.0, np.float32)
    frames[1, 4, 5] = frames[3, 0, 0] = 9.969209968386869e36
    path = tmp_path / "nc.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("counts", data=frames, chunks=chunks).attrs["_FillValue"] = np.float32(9.969209968386869e36)
    data = read(path, dataset="counts").data
    assert np.isnan(data[1, 4, 5]) and np.isnan(data[3, 0, 0]) and np.isfinite(data).sum() == frames.size - 2


def test_hdf5_cf_fill_value_beyond_the_stored_type_marks_no_pixel(tmp_path):
    """A float64 fill code of 1e300 on float32 frames overflowed to inf (a RuntimeWarning) and
    would have marked the frame's inf pixels missing: no float32 pixel holds that code."""
    frames = np.full((1, 4, 4), 7.0, np.float32)
    frames[0, 1, 1] = np.inf
    path = tmp_path / "nc.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=frames).attrs["_FillValue"] = 1e300
    data = read(path, dataset="x").data
    assert np.isposinf(data[0, 1, 1]) and (data[np.isfinite(data)] == 7).sum() == 15


def test_hdf5_cf_packed_white_is_zero_counts_are_inverted_before_unpacking(tmp_path):
    """Found in review: with CF packing on a white-is-zero image the unpacked value was inverted
    (65535 - 0.5) instead of the stored counts ((65535 - 500) * 0.001 = 65.035). The counts are
    inverted as stored, then unpacked; a ``_FillValue`` code is one of the stored values."""
    stored = np.full((2, 8, 8), 500, np.uint16)
    stored[1, 3, 4] = 0  # the fill code
    path = tmp_path / "cfwiz.h5"
    _hdf5_image(path, "x", stored, 1)
    with h5py.File(path, "a") as f:
        f["x"].attrs["scale_factor"] = np.float32(0.001)
        f["x"].attrs["_FillValue"] = np.uint16(0)
    data = _both_ways(path, dataset="/x")
    expect = (np.iinfo(np.uint16).max - stored.astype(np.float64)) * 0.001
    missing = stored == 0
    assert np.isnan(data[missing]).all() and np.isfinite(data[~missing]).all()
    np.testing.assert_allclose(data[~missing], expect[~missing], rtol=2 * np.finfo(np.float32).eps)


def test_hdf5_cf_packing_past_the_unpacked_types_range_is_one_line_naming_the_file(tmp_path):
    """Found in review: a scale_factor of 1e308 gave two RuntimeWarning overflow lines that named
    no file, and frames of inf. Now one error naming the file and the packing; a fill code that
    would overflow is not counted (it reads as NaN)."""
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("x", data=np.arange(128, dtype=np.int16).reshape(2, 8, 8))
        ds.attrs["scale_factor"], ds.attrs["add_offset"] = 1e308, 1e308
        fine = f.create_dataset("fill", data=np.full((1, 4, 4), 3.0, np.float32))
        fine[0, 1, 1] = 3e38
        fine.attrs["scale_factor"], fine.attrs["_FillValue"] = np.float32(2.0), np.float32(3e38)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FormatError, match=r"huge\.h5.*scale_factor 1e\+308 .*float64's range"):
            read(path, dataset="/x")
        data = read(path, dataset="/fill").data
    assert np.isnan(data[0, 1, 1]) and (data[np.isfinite(data)] == 6).sum() == 15


@pytest.mark.parametrize("scale", [0.0, np.nan, "0.001"])
def test_hdf5_cf_packing_that_cannot_be_applied_is_one_line(tmp_path, scale):
    path = tmp_path / "cf.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=np.zeros((2, 4, 4), np.int16)).attrs["scale_factor"] = scale
    with pytest.raises(FormatError, match="scale_factor"):
        read(path, dataset="frames")


@pytest.mark.parametrize("scale", [np.float32(1e-45), np.float64(5e-324), np.float32(1e-39)])
def test_hdf5_cf_scale_factor_below_its_types_normal_range_is_refused(tmp_path, scale):
    """Found in review: a subnormal scale_factor (1e-45 in float32, which stores it as 1.4e-45 with
    one significant bit) was taken silently: every pixel then holds a few bits of precision at
    best, a value of 1e-40 no transmission has. Refused in one line naming the file and the
    attribute, as a scale of 0 is."""
    path = tmp_path / "tiny.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=np.arange(32, dtype=np.int16).reshape(2, 4, 4)).attrs["scale_factor"] = scale
    with pytest.raises(FormatError, match=r"tiny\.h5: /frames@scale_factor is .*subnormal") as info:
        read(path, dataset="frames")
    assert "\n" not in str(info.value)


def test_hdf5_cf_fill_value_of_many_values_is_refused(tmp_path):
    """CF: ``_FillValue`` is one value of the variable's type (``missing_value`` alone may be a
    vector). Found in review: an array of 8000 codes was taken as that many fill values, and every
    pixel of frames of ones read as NaN. Refused in one line naming the file and the attribute;
    a vector ``missing_value`` still marks each of its codes."""
    path = tmp_path / "fills.h5"
    frames = np.ones((2, 8, 8), np.float32)
    frames[1, 2, 3] = 5.0
    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=frames).attrs["_FillValue"] = np.arange(8000, dtype=np.float64)
        f.create_dataset("vector", data=frames).attrs["missing_value"] = np.array([5.0, 7.0], np.float32)
    with pytest.raises(FormatError, match=r"fills\.h5: /x@_FillValue holds 8000 values") as info:
        read(path, dataset="x")
    assert "\n" not in str(info.value)
    data = read(path, dataset="vector").data
    assert np.isnan(data[1, 2, 3]) and np.isfinite(data).sum() == frames.size - 1


# ------------------------------------------------------------------------------------------------
# Data Exchange (DXchange: tomopy, APS beamlines): /exchange/data, data_dark, data_white
# ------------------------------------------------------------------------------------------------


def _dxchange(path, proj, darks=None, flats=None):
    """A file as dxchange.write_dxf / tomopy's readers lay it out: projections, darks and flats as
    three datasets of one group, no image keys."""
    with h5py.File(path, "w") as f:
        f.create_dataset("implements", data="exchange")
        x = f.create_group("exchange")
        x.create_dataset("data", data=proj, chunks=(1,) + proj.shape[1:], compression="gzip")
        if darks is not None:
            x.create_dataset("data_dark", data=darks)
        if flats is not None:
            x.create_dataset("data_white", data=flats)
        x.create_dataset("theta", data=np.linspace(0, 180, len(proj)))


def test_dxchange_reads_its_darks_flats_and_projections_told_apart(tmp_path):
    """A DXchange file was refused as lacking radiokit's layout, and with --dataset a calibration
    could take its darks and flats only as the same frames (one --dataset for both): "flats are not
    brighter than darks". Its three datasets now read as one stack, keyed as NXtomo keys them, so
    calibrate and correct take its darks, flats and projections as an experiment file's."""
    rng = np.random.default_rng(8)
    darks = rng.normal(100, 2, (3, 24, 32)).round().astype(np.uint16)
    flats = rng.normal(3000, 30, (4, 24, 32)).round().astype(np.uint16)
    proj = rng.normal(1500, 20, (2, 24, 32)).round().astype(np.uint16)
    path = tmp_path / "scan.h5"
    _dxchange(path, proj, darks, flats)
    f = read(path)
    np.testing.assert_array_equal(f.data, np.concatenate([darks, flats, proj]))
    assert f.meta["image_key"].tolist() == [ImageKey.DARK] * 3 + [ImageKey.FLAT] * 4 + [ImageKey.PROJECTION] * 2
    cal = Calibration.from_experiment(path)
    expected = Calibration.from_frames(darks, flats)
    np.testing.assert_allclose(cal.flat, expected.flat)
    np.testing.assert_allclose(cal.dark, expected.dark)
    np.testing.assert_array_equal(read(path, dataset="exchange/data").data, proj)  # one dataset, as before


def test_a_dxchange_file_is_corrected_from_its_own_darks_and_flats(tmp_path):
    """A beamline's DXchange file through the commands a user types: info counts its frames of
    each kind, and correct calibrates from its darks and flats and corrects its projections alone,
    to -ln of the transmission the frames were made with."""
    import re

    from conftest import run_cli

    rng = np.random.default_rng(2)
    transmission = np.exp(-np.linspace(0.2, 1.5, 48))[None, :].repeat(40, 0)
    darks = np.rint(100 + rng.normal(0, 1, (4, 40, 48))).astype(np.uint16)
    flats = np.rint(100 + 3000 + rng.normal(0, 5, (4, 40, 48))).astype(np.uint16)
    proj = np.rint(100 + 3000 * transmission + rng.normal(0, 5, (2, 40, 48))).astype(np.uint16)
    path = tmp_path / "tomo.h5"
    with h5py.File(path, "w") as f:
        f["exchange/data"], f["exchange/data_dark"], f["exchange/data_white"] = proj, darks, flats
    res = run_cli("info", path)
    assert res.returncode == 0 and re.search(r"projections\s+2", res.stdout) and re.search(r"darks\s+4", res.stdout)
    res = run_cli("correct", path, "-o", tmp_path / "out.h5", "-q")
    assert res.returncode == 0, res.stderr
    out = read(tmp_path / "out.h5").data
    assert out.shape == (2, 40, 48)
    # 5 counts of noise on 3000 x T: a frame's -ln errs by about 5 / (3000 T) <= 0.008 rms
    np.testing.assert_allclose(out.mean(axis=(0, 1)), -np.log(transmission[0]), atol=0.005)


def test_a_dxchange_dataset_of_other_dimensions_names_the_ones_accepted(tmp_path):
    """Found in review: a 4-D data_dark was refused as "expected 2 dimension(s)", though a 3-D
    stack is read: the message now names both."""
    path = tmp_path / "dx.h5"
    with h5py.File(path, "w") as f:
        f["exchange/data"] = np.ones((2, 8, 8), np.uint16)
        f["exchange/data_dark"] = np.ones((1, 2, 8, 8), np.uint16)
    with pytest.raises(FormatError, match=r"dx\.h5.*data_dark has shape \(1, 2, 8, 8\); expected 2 or 3 dimensions"):
        read(path)


def test_dxchange_of_projections_only_or_of_mismatched_frames(tmp_path):
    proj = _frames(2, 24, 32)
    path = tmp_path / "proj.h5"
    _dxchange(path, proj)
    f = read(path)
    np.testing.assert_array_equal(f.data, proj)
    assert f.meta["image_key"].tolist() == [ImageKey.PROJECTION] * 2
    _dxchange(path, proj, darks=_frames(2, 24, 30))
    with pytest.raises(FormatError, match="data_dark.*24x30.*data.*24x32"):
        read(path)


def test_an_hdf5_file_of_another_layout_names_the_datasets_that_could_be_frames(tmp_path):
    """Another program's HDF5 file without NeXus or DXchange names was refused with "pass
    --dataset", leaving the user to find the path with another tool: the refusal names the 2-D and
    3-D datasets of numbers the file holds, a few at most, and not its 1-D ones."""
    path = tmp_path / "beamline.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("scan/images", data=_frames(3, 20, 24))
        f.create_dataset("scan/angles", data=np.arange(3.0))
        f.create_dataset("scan/labels", data=np.array([b"a", b"b"]))
    with pytest.raises(FormatError, match=r"it holds /scan/images \(3x20x24 uint16\): pass --dataset") as info:
        read(path)
    assert "angles" not in str(info.value) and "labels" not in str(info.value)
    with h5py.File(path, "a") as f:
        for i in range(6):
            f.create_dataset(f"more/img{i}", data=np.zeros((4, 4), np.float32))
    with pytest.raises(FormatError, match=r"/scan/images \(3x20x24 uint16\).* and 3 more"):
        read(path)


def test_a_dataset_hint_naming_a_group_names_the_frames_it_holds(tmp_path):
    """``--dataset entry/data`` (an NXdata group, as a viewer shows it) said only "no dataset
    'entry/data'", as if nothing were there: it is a group, and the refusal names what it holds."""
    path = tmp_path / "scan.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("entry/data/counts", data=_frames(2, 20, 24))
    with pytest.raises(FormatError, match=r"no dataset 'entry/data': a group, holding /entry/data/counts \(2x20x24"):
        read(path, dataset="entry/data")
    with pytest.raises(FormatError, match="no dataset 'entry/nothing'"):
        read(path, dataset="entry/nothing")


def test_one_dataset_hint_for_inputs_of_two_layouts_names_the_file_lacking_it(tmp_path):
    """s46: ``--dataset`` is one path read from every input: files of one layout (a beamline's
    scans) take it alike. The file that lacks it is named with the path, and with the frames it
    does hold, so that the user sees the layouts differ (it said only "no dataset 'scan/data'")."""
    darks = [tmp_path / "a.h5", tmp_path / "b.h5"]
    for path, where in zip(darks, ("scan/data", "entry/data")):
        with h5py.File(path, "w") as f:
            f[where] = _frames(3, 16, 20)
    with h5py.File(tmp_path / "flat.h5", "w") as f:
        f["scan/data"] = _frames(3, 16, 20) + 3000
    res = run_cli(
        "calibrate", "--dark", *darks, "--flat", tmp_path / "flat.h5", "--dataset", "scan/data", "-o", tmp_path / "c.h5"
    )
    one_line_error(res, "b.h5", "no dataset 'scan/data'", "/entry/data (3x16x20 uint16)")
    assert not (tmp_path / "c.h5").exists()


def test_an_hdf5_stack_stored_rows_cols_n_is_refused_and_a_tiff_warned_of(tmp_path):
    """Found by trying other labs' files: frames stacked along the last axis (numpy's dstack,
    IDL, Fortran writers) read as rows-many narrow frames, (64, 80, 5) as 64 frames of 80 x 5,
    with no word; every command then worked on strips. An HDF5 stack whose last axis is far the
    shortest is refused, naming its dataset and shape (s50: a warning alone left every command
    working on strips), and read as stored with ``narrow_frames=True``; a TIFF written from such
    an array is warned of; a plain (n, rows, cols) stack is neither."""
    import warnings

    frames = _frames(5, 64, 80)
    path = tmp_path / "dstack.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("stack", data=np.dstack(list(frames)))
        f.create_dataset("plain", data=frames)
        f.create_dataset("few", data=frames[:2])
    with pytest.raises(FormatError, match=r"dstack\.h5: dataset stack has shape 64x80x5, .* stored rows x cols x n"):
        read(path, dataset="stack")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read(path, dataset="stack", narrow_frames=True).data, np.dstack(list(frames)))
    tifffile.imwrite(tmp_path / "dstack.tif", np.dstack(list(frames)), photometric="minisblack")  # 64 pages
    with pytest.warns(UserWarning, match=r"64 frames of 80x5"):
        read(tmp_path / "dstack.tif")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read(path, dataset="plain").data, frames)
        np.testing.assert_array_equal(read(path, dataset="few").data, frames[:2])


# ------------------------------------------------------------------------------------------------
# FillOrder 2 (bits reversed in every stored byte) and signed samples
# ------------------------------------------------------------------------------------------------


def _one_strip_tiff(path, pixels: bytes, rows, cols, *, bits=16, fillorder=None, sampleformat=None, desc=None):
    """A little-endian classic TIFF, one IFD and one uncompressed strip holding ``pixels``, with
    tags tifffile does not write (FillOrder) as the other software writing them does."""
    import struct

    tags = [(256, 3, 1, cols), (257, 3, 1, rows), (258, 3, 1, bits), (259, 3, 1, 1), (262, 3, 1, 1)]
    if fillorder is not None:
        tags.append((266, 3, 1, fillorder))
    text = b"" if desc is None else desc.encode() + b"\0"
    if text:
        tags.append((270, 2, len(text), 8))
    start = 8 + len(text) + len(text) % 2
    tags += [(273, 4, 1, start), (277, 3, 1, 1), (278, 3, 1, rows), (279, 4, 1, len(pixels))]
    if sampleformat is not None:
        tags.append((339, 3, 1, sampleformat))
    ifd = start + len(pixels) + len(pixels) % 2
    out = bytearray(b"II*\0" + struct.pack("<I", ifd) + text + b"\0" * (len(text) % 2))
    out += pixels + b"\0" * (len(pixels) % 2) + struct.pack("<H", len(tags))
    for code, kind, count, value in tags:
        out += struct.pack("<HHI", code, kind, count) + struct.pack(
            "<HH" if kind == 3 else "<I", *((value, 0) if kind == 3 else (value,))
        )
    path.write_bytes(bytes(out + struct.pack("<I", 0)))
    return path


def _bits_reversed(data: bytes) -> bytes:
    table = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))
    return data.translate(table)


def test_fillorder_2_tiff_one_page_reads_as_libtiff_does(tmp_path):
    """FillOrder 2: each stored byte's bits reversed; libtiff and tifffile reverse them back."""
    counts = _frames(1)[0]
    path = _one_strip_tiff(tmp_path / "f.tif", _bits_reversed(counts.tobytes()), *counts.shape, fillorder=2)
    with tifffile.TiffFile(path) as tif:
        np.testing.assert_array_equal(tif.pages[0].asarray(), counts)
    np.testing.assert_array_equal(_both_ways(path)[0], counts)


def test_fillorder_2_imagej_stack_after_one_ifd_reads_bits_reversed_back(tmp_path):
    """An ImageJ stack stored after its one IFD is read as raw frames: with FillOrder 2 they were
    read with their bits reversed, silently wrong pixels (4095 read as 65295)."""
    counts = _frames(3)
    path = _one_strip_tiff(
        tmp_path / "ij.tif",
        _bits_reversed(counts.tobytes()),
        *counts.shape[1:],
        fillorder=2,
        desc="ImageJ=1.54f\nimages=3\n",
    )
    np.testing.assert_array_equal(_both_ways(path), counts)


def test_fillorder_2_tiff_of_12_bit_counts_in_16_bit_words_reads_them(tmp_path):
    """BitsPerSample 12 in whole 16-bit words with FillOrder 2 was refused as "fit neither packed
    12-bit rows nor 16-bit words", which they do fit: the bits are reversed back, as for any page."""
    counts = _frames(1)[0]
    path = _one_strip_tiff(tmp_path / "w.tif", _bits_reversed(counts.tobytes()), *counts.shape, bits=12, fillorder=2)
    with pytest.warns(UserWarning, match="16-bit words"):
        np.testing.assert_array_equal(_both_ways(path)[0], counts)


def _packed_12(values) -> bytes:
    """Rows of 12-bit two's-complement samples packed MSB first, each row on a byte boundary."""
    out = bytearray()
    for row in values:
        bits = "".join(f"{int(v) & 0xFFF:012b}" for v in row)
        bits += "0" * (-len(bits) % 8)
        out += bytes(int(bits[k : k + 8], 2) for k in range(0, len(bits), 8))
    return bytes(out)


@pytest.mark.parametrize(
    "stored",
    [
        pytest.param(lambda v: v.astype("<i2").tobytes(), id="16-bit words sign-extended"),
        pytest.param(lambda v: (v & 0xFFF).astype("<u2").tobytes(), id="16-bit words, 12-bit two's complement"),
        pytest.param(_packed_12, id="packed"),
    ],
)
def test_signed_12_bit_tiff_is_refused_in_one_line(tmp_path, stored):
    """SampleFormat 2 (signed) with BitsPerSample 12: no raw frame of the C7942, whose 12-bit ADC
    gives unsigned counts 0..4095 (hardware/C7942.md). Read as unsigned 16-bit words, -150 became
    65386 (with a warning blaming another detector) or, stored as 12-bit two's complement, 3946
    without a word; packed, a riddle ("page 0 decodes to (0,)"). Refused, naming the file and why."""
    values = (np.arange(30 * 40).reshape(30, 40) % 300 - 150).astype(np.int64)
    path = _one_strip_tiff(tmp_path / "signed.tif", stored(values), 30, 40, bits=12, sampleformat=2)
    with pytest.raises(FormatError, match=r"signed.tif: .*signed \(SampleFormat 2\) 12-bit.*0\.\.4095"):
        read(path)
    res = run_cli("info", path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "signed.tif" in lines[0] and "SampleFormat 2" in lines[0], res.stderr


def test_signed_16_bit_tiff_is_still_read_as_stored(tmp_path):
    """int16 pixels (BitsPerSample 16, SampleFormat 2) hold their sign in the word: read exactly,
    negatives included, as before."""
    values = (np.arange(30 * 40).reshape(30, 40) % 300 - 150).astype("<i2")
    path = _one_strip_tiff(tmp_path / "s16.tif", values.tobytes(), 30, 40, bits=16, sampleformat=2)
    f = read(path)
    assert f.data.dtype == np.int16
    np.testing.assert_array_equal(f.data[0], values)


def _nexus_detector(path, frames, bits, linked=False):
    """Another program's NeXus file: frames in an NXdetector with its ``bit_depth_readout``
    (NeXus's word for the ADC's bits), found there or through NXdata's soft link."""
    with h5py.File(path, "w") as h5:
        entry = _nx_class(h5.create_group("entry"), "NXentry")
        det = _nx_class(entry.create_group("instrument/detector"), "NXdetector")
        det.create_dataset("data", data=frames, chunks=(1, *frames.shape[1:]))
        if bits is not None:
            det["bit_depth_readout"] = bits
        if linked:
            data = _nx_class(entry.create_group("data"), "NXdata")
            data.attrs["signal"] = "data"
            data["data"] = h5py.SoftLink("/entry/instrument/detector/data")
    return path


@pytest.mark.parametrize("linked", [False, True])
def test_nexus_bit_depth_readout_is_the_declared_bit_depth(tmp_path, linked):
    """A 16-bit panel's NeXus darks and flats (bit_depth_readout 16) whose bright corner passes 4095
    in 0.1 % of the flats' values: the file's bit depth was ignored outside radiokit's own
    experiment files, and the ADC-top rule took the corner for a 12-bit panel's stuck pixels:
    saturation 4095, the corner masked as saturated. Declared, it settles the range, as an
    experiment file's and a TIFF's BitsPerSample do."""
    rng = np.random.default_rng(3)
    darks = np.rint(200 + rng.normal(0, 3, (4, 128, 128))).astype(np.uint16)
    flats = (200 + rng.poisson(3400, (4, 128, 128))).astype(np.uint16)
    flats[:, :4, :4] += 700  # ~4300 counts: over a 12-bit ADC's top, nothing to a 16-bit one
    assert 0 < np.count_nonzero(flats > 4095) <= 1e-3 * flats.size
    dark = read(_nexus_detector(tmp_path / "dark.nxs", darks, 16, linked))
    flat = read(_nexus_detector(tmp_path / "flat.nxs", flats, 16, linked))
    assert dark.meta["bit_depth"] == flat.meta["bit_depth"] == 16
    cal = Calibration.from_frames(dark, flat)
    assert cal.thresholds.saturation == 65535
    assert not cal.mask[:4, :4].any()


def test_nexus_bit_depth_readout_warns_of_values_past_it(tmp_path):
    """Values a declared 12-bit ADC cannot give warn, as an experiment file's do; a file without
    bit_depth_readout says nothing of its ADC (no warning, no bit_depth)."""
    from radiokit.io import BitDepthWarning

    frames = _frames()
    frames[0, 0, 0] = 5000
    with pytest.warns(BitDepthWarning, match="12-bit range"):
        read(_nexus_detector(tmp_path / "d12.nxs", frames, 12))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = read(_nexus_detector(tmp_path / "none.nxs", frames, None))
    assert "bit_depth" not in f.meta


def _stated_pixel(path, how, mm):
    """An image as a lab's software writes it with its pitch stated (``mm`` per pixel)."""
    image = np.random.default_rng(1).integers(100, 4000, (40, 50)).astype(np.uint16)
    if how == "imagej-mm":
        tifffile.imwrite(path, image, imagej=True, resolution=(1 / mm, 1 / mm), metadata={"unit": "mm"})
    elif how == "imagej-micron":  # ImageJ writes µm escaped in its description
        res = 1 / (mm * 1e3)
        tifffile.imwrite(path, image, imagej=True, resolution=(res, res), metadata={"unit": "\\u00B5m"})
    elif how == "ome":
        meta = {"PhysicalSizeX": mm * 1e3, "PhysicalSizeXUnit": "µm", "PhysicalSizeY": mm * 1e3}
        tifffile.imwrite(path, image, metadata=meta)  # PhysicalSizeYUnit left out: OME's default, µm
    elif how == "nexus":
        with h5py.File(path, "w") as f:
            entry = _nx_class(f.create_group("entry"), "NXentry")
            det = _nx_class(entry.create_group("instrument/detector"), "NXdetector")
            det["data"] = image[None]
            for axis in ("x_pixel_size", "y_pixel_size"):
                det[axis] = mm * 1e3
                det[axis].attrs["units"] = "um"
            data = _nx_class(entry.create_group("data"), "NXdata")
            data.attrs["signal"] = "data"
            data["data"] = h5py.SoftLink("/entry/instrument/detector/data")
    return path


@pytest.mark.parametrize(
    "how, suffix", [("imagej-mm", ".tif"), ("imagej-micron", ".tif"), ("ome", ".ome.tif"), ("nexus", ".nxs")]
)
def test_a_pixel_size_the_file_states_is_read_and_register_holds_to_it(tmp_path, how, suffix):
    """ImageJ (its unit and resolution), OME-TIFF (PhysicalSizeX/Y) and an NXdetector beside
    another program's NeXus frames state the pitch. It was read only from radiokit's experiment
    files, so `radiokit info` did not show it and `register` matched an image at 0.1 mm per pixel
    onto one at 0.05 mm (a field in pixels between two pitches is a scaling, not a motion)."""
    fine = read(_stated_pixel(tmp_path / f"fine{suffix}", how, 0.05))
    assert fine.meta["x_pixel_size"] == pytest.approx(5e-5) and fine.meta["y_pixel_size"] == pytest.approx(5e-5)
    _stated_pixel(tmp_path / f"binned{suffix}", how, 0.1)
    res = run_cli("register", tmp_path / f"fine{suffix}", tmp_path / f"binned{suffix}", "-o", tmp_path / "reg.h5")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert f"binned{suffix}" in res.stderr and "0.1 mm" in res.stderr and "0.05 mm" in res.stderr
    assert not (tmp_path / "reg.h5").exists()
    info = run_cli("info", tmp_path / f"fine{suffix}")
    assert "pixel_size_mm 0.05" in " ".join(info.stdout.split()), info.stdout


@pytest.mark.parametrize("field", ["x_pixel_size", "bit_depth_readout"])
def test_an_optional_detector_field_behind_an_external_link_is_left_out_not_refused(tmp_path, field):
    """An NXdetector's x_pixel_size (optional: the pitch, once not read at all) linked to
    another file made `info` and `register` refuse the whole file without --allow-external, and
    with it refuse it when the link's file was gone. Such a field is left out, with a note; the
    frames are read as before. With --allow-external a link that reaches a value is read."""
    path = _stated_pixel(tmp_path / "linked.nxs", "nexus", 0.05)
    with h5py.File(tmp_path / "pitch.h5", "w") as f:
        f["v"] = 50.0 if field == "x_pixel_size" else 12
        f["v"].attrs["units"] = "um"
    with h5py.File(path, "a") as f:
        det = f["entry/instrument/detector"]
        if field in det:
            del det[field]
        det[field] = h5py.ExternalLink("pitch.h5", "/v")
    meta_key = "x_pixel_size" if field == "x_pixel_size" else "bit_depth"
    with pytest.warns(UserWarning, match=f"{field}.*external link.*left out"):
        frames = read(path)
    assert frames.data.shape == (1, 40, 50) and meta_key not in frames.meta
    info = run_cli("info", path)  # (run_cli hides warnings: the note is checked above)
    assert info.returncode == 0 and "1 x 40 rows x 50 cols" in info.stdout, info.stderr
    assert read(path, allow_external=True).meta[meta_key] == pytest.approx(5e-5 if meta_key == "x_pixel_size" else 12)
    (tmp_path / "pitch.h5").unlink()
    with pytest.warns(UserWarning, match=f"{field}.*cannot be opened.*left out"):
        frames = read(path, allow_external=True)
    assert meta_key not in frames.meta


def test_a_tiff_stating_no_length_has_no_pixel_size(tmp_path):
    """Resolution in a TIFF without ImageJ's or OME's length (72 dpi, ImageJ's 'pixel') is a
    display's, not the detector's pitch: no pixel size is made of it."""
    image = np.zeros((6, 7), np.uint16)
    tifffile.imwrite(tmp_path / "dpi.tif", image, resolution=(72, 72), resolutionunit="INCH")
    tifffile.imwrite(tmp_path / "ij.tif", image, imagej=True, resolution=(1, 1), metadata={"unit": "pixel"})
    for name in ("dpi.tif", "ij.tif"):
        assert "x_pixel_size" not in read(tmp_path / name).meta


@pytest.mark.parametrize("missing", ["file", "dataset"])
def test_an_external_link_to_nothing_is_named_when_allowed(tmp_path, missing):
    """allow_external=True over an external link whose file is gone, or holds no such dataset (a
    master file beside another run's data files): "cannot be read as hdf5: Unable to synchronously
    open object (can't open file)" named neither the link nor its target."""
    with h5py.File(tmp_path / "frames_000001.h5", "w") as f:
        f["other"] = _frames(2)
    path = tmp_path / "master.h5"
    with h5py.File(path, "w") as f:
        entry = _nx_class(f.create_group("entry"), "NXentry")
        plot = _nx_class(entry.create_group("data"), "NXdata")
        plot.attrs["signal"] = "data"
        target = "gone.h5" if missing == "file" else "frames_000001.h5"
        plot["data"] = h5py.ExternalLink(target, "/data")
    with pytest.raises(
        FormatError, match=rf"/entry/data/data is an external link to {target}:/data, which cannot be opened"
    ):
        read(path, allow_external=True)


def test_ome_planes_mapped_to_ifds_out_of_file_order_read_in_ome_order(tmp_path):
    """OME's TiffData may put plane T=0 in IFD 2 and T=2 in IFD 0. Fiji (Bio-Formats) and tifffile
    read the time points in OME's order; radiokit read the pages in file order, so the stack came
    out reversed with nothing said."""
    stack = _frames(3, rows=4, cols=5)
    tiffdata = "".join(f'<TiffData IFD="{2 - t}" FirstT="{t}" PlaneCount="1"/>' for t in range(3))
    xml = (
        '<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06">'
        '<Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYCZT" Type="uint16" SizeX="5" SizeY="4" '
        'SizeC="1" SizeZ="1" SizeT="3"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>'
        f"{tiffdata}</Pixels></Image></OME>"
    )
    path = tmp_path / "planes.ome.tif"
    with tifffile.TiffWriter(path) as tw:
        for t in (2, 1, 0):
            tw.write(stack[t], photometric="minisblack", description=xml if t == 2 else None, metadata=None)
    np.testing.assert_array_equal(read(path).data, stack)
    from radiokit.io import open_frames

    with open_frames(path) as src:
        np.testing.assert_array_equal(np.stack(list(src)), stack)


def _itex_bytes(pixels, comment=b'[Camera],CameraName="C7942"'):
    import struct

    n, rows, cols = pixels.shape
    head = struct.pack("<2sHhhhhhihhd4s30s", b"IM", len(comment), cols, rows, 0, 0, 2, n, 1, 0, 0.0, b"", b"")
    return head + comment + pixels.astype("<u2").tobytes()


def test_a_byte_swapped_itex_file_is_given_advice_the_user_can_follow(tmp_path):
    """s37: a C7942 .img whose writer swapped the bytes was told "try byteorder='>'", which ITEX
    refuses ("hints apply to raw files only"). The advice now reads the pixels as raw, and doing
    what it says gives the counts."""
    frames = _frames(2, rows=4, cols=8)
    path = tmp_path / "swap.img"
    path.write_bytes(_itex_bytes(frames.byteswap()))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    res = subprocess.run(
        [sys.executable, "-m", "radiokit.cli", "info", str(path)], capture_output=True, text=True, env=env
    )
    assert res.returncode == 0, res.stderr
    assert "byte-swapped values fit" in res.stderr and "try byteorder" not in res.stderr, res.stderr
    offset = 64 + len(b'[Camera],CameraName="C7942"')
    flags = f"--format raw --offset {offset} --shape 4 8 --byteorder '>'"
    assert flags in res.stderr, res.stderr
    res = run_cli("info", path, "--format", "raw", "--offset", offset, "--shape", 4, 8, "--byteorder", ">")
    assert res.returncode == 0 and f"range  {frames.min()} .. {frames.max()}" in info_items(res.stdout), (
        res.stdout + res.stderr
    )
    api = f"format='raw', offset={offset}, shape=(2, 4, 8), byteorder='>'"
    with pytest.warns(UserWarning, match=re.escape(api)):
        read(path)
    np.testing.assert_array_equal(read(path, format="raw", offset=offset, shape=(2, 4, 8), byteorder=">").data, frames)


def _nxdata_file(path, frames):
    h5 = h5py.File(path, "w")
    data = _nx_class(_nx_class(h5.create_group("entry"), "NXentry").create_group("data"), "NXdata")
    data["counts"] = frames
    data["other"] = frames[:, :, :4].copy()  # a second candidate: without @signal the file is refused
    return h5, data


@pytest.mark.parametrize(
    "how",
    ["dataset int 1", "dataset str 1", "group str array", "group bytes array", "group bytes"],
)
def test_a_nexus_signal_of_an_older_or_looser_writer_is_followed(tmp_path, how):
    """s37: the NeXus v1 ``@signal=1`` on the dataset, or the group's ``@signal`` stored as a
    one-element array (h5py writes a list so, as do IDL and MATLAB writers), was refused with a
    list of datasets to choose from, though it names the frames as plainly as ``@signal="counts"``."""
    frames = _frames(3)
    path = tmp_path / "nx.h5"
    h5, data = _nxdata_file(path, frames)
    with h5:
        if how == "dataset int 1":
            data["counts"].attrs["signal"] = np.int32(1)
        elif how == "dataset str 1":
            data["counts"].attrs["signal"] = "1"
        elif how == "group str array":
            data.attrs["signal"] = np.array(["counts"], dtype=h5py.string_dtype())
        elif how == "group bytes array":
            data.attrs["signal"] = np.array([b"counts"])
        else:
            data.attrs["signal"] = np.bytes_(b"counts")
    got = read(path)
    assert got.meta["dataset"] == "/entry/data/counts"
    np.testing.assert_array_equal(got.data, frames)
    res = run_cli("info", path)
    assert res.returncode == 0 and "3 x 30 rows x 40 cols" in res.stdout, res.stdout + res.stderr


def test_two_datasets_marked_signal_1_are_not_guessed_between(tmp_path):
    """The old-style mark on two datasets names neither: the list to choose from, as before."""
    frames = _frames(3)
    h5, data = _nxdata_file(tmp_path / "nx.h5", frames)
    with h5:
        data["counts"].attrs["signal"] = 1
        data["other"].attrs["signal"] = 1
    with pytest.raises(FormatError, match="/entry/data/counts .*/entry/data/other"):
        read(tmp_path / "nx.h5")


@pytest.mark.parametrize("how, suffix", [("imagej-mm", ".tif"), ("ome", ".ome.tif"), ("nexus", ".nxs")])
@pytest.mark.parametrize("mm", [1e3, 1e-6])
def test_a_stated_pixel_size_no_panel_has_is_ignored_with_a_note(tmp_path, how, suffix, mm):
    """An experiment file's pitch must lie in 0.1 um..10 mm; ImageJ's, OME's and an NXdetector's
    had no such check: `info` showed pixel_size_mm 1e+27 and `register` refused a pair on it. Such
    a value is ignored with a one-line note (info says it is unusable), and the image is read."""
    path = _stated_pixel(tmp_path / f"odd{suffix}", how, mm)
    with pytest.warns(UserWarning, match="pixel size.*ignored") as caught:
        frames = read(path)
    assert len([w for w in caught if "pixel size" in str(w.message)]) == 1
    assert not {"x_pixel_size", "y_pixel_size", "pixel_size_mm"} & set(frames.meta)
    info = run_cli("info", path)
    assert info.returncode == 0 and "pixel_size_mm" not in info.stdout and "unusable" in info.stdout, info.stdout
    fine = _stated_pixel(tmp_path / f"fine{suffix}", how, 0.05)
    res = run_cli("register", fine, path, "-o", tmp_path / "reg.h5")
    assert "pixels of" not in res.stderr and "mm" not in res.stderr, res.stderr


def _nexus_pixel(path, value, units):
    with h5py.File(path, "w") as f:
        entry = _nx_class(f.create_group("entry"), "NXentry")
        det = _nx_class(entry.create_group("instrument/detector"), "NXdetector")
        det["data"] = np.zeros((1, 6, 7), np.uint16)
        for axis in ("x_pixel_size", "y_pixel_size"):
            det[axis] = value
            det[axis].attrs["units"] = units
        data = _nx_class(entry.create_group("data"), "NXdata")
        data.attrs["signal"] = "data"
        data["data"] = h5py.SoftLink("/entry/instrument/detector/data")
    return path


@pytest.mark.parametrize(
    "value, units", [(50, "microns"), (50, "\u03bcm"), (5e5, "\u00c5"), (5e5, "\u212b"), (5e5, "angstrom")]
)
def test_other_spellings_of_a_length_unit_are_understood(tmp_path, value, units):
    """'microns', Greek mu (U+03BC) and the angstrom (as NeXus and OME write them) left the pitch
    out with nothing said, where 'micron' and the micro sign were read."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        nexus = read(_nexus_pixel(tmp_path / "px.nxs", value, units))
        tifffile.imwrite(
            tmp_path / "px.ome.tif",
            np.zeros((6, 7), np.uint16),
            metadata={k: v for a in "XY" for k, v in ((f"PhysicalSize{a}", value), (f"PhysicalSize{a}Unit", units))},
        )
        ome = read(tmp_path / "px.ome.tif")
    for frames in (nexus, ome):
        assert frames.meta["pixel_size_mm"] == pytest.approx(0.05)


def test_a_length_unit_not_understood_is_said(tmp_path):
    """A unit radiokit does not know left the pitch out silently; the note names it."""
    image = np.zeros((6, 7), np.uint16)
    tifffile.imwrite(tmp_path / "ij.tif", image, imagej=True, resolution=(20, 20), metadata={"unit": "furlong"})
    meta = {"PhysicalSizeX": 1, "PhysicalSizeXUnit": "furlong", "PhysicalSizeY": 1, "PhysicalSizeYUnit": "furlong"}
    tifffile.imwrite(tmp_path / "o.ome.tif", image, metadata=meta)
    for path in (tmp_path / "ij.tif", tmp_path / "o.ome.tif", _nexus_pixel(tmp_path / "n.nxs", 1.0, "furlong")):
        with pytest.warns(UserWarning, match="'furlong'.*pixel size is ignored"):
            assert "pixel_size_mm" not in read(path).meta


@pytest.mark.parametrize("dpi", [72, 96])
def test_imagej_inches_at_a_screens_dpi_state_no_pixel_size(tmp_path, dpi):
    """ImageJ's unit=inch at 72 dpi (which ImageJ itself reads as no calibration) or 96 dpi, the
    screens' defaults, was taken as a pitch of 0.353 mm; a plain 72-dpi TIFF already states none."""
    path = tmp_path / "ij.tif"
    tifffile.imwrite(path, np.zeros((6, 7), np.uint16), imagej=True, resolution=(dpi, dpi), metadata={"unit": "inch"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "x_pixel_size" not in read(path).meta


def _drop_tags(path, codes):
    """Remove tags ``codes`` from the first IFD of a little-endian classic TIFF (tifffile always
    writes XResolution and YResolution, 1/1 when given none; other writers leave them out)."""
    import struct

    data = bytearray(path.read_bytes())
    ifd = struct.unpack_from("<I", data, 4)[0]
    n = struct.unpack_from("<H", data, ifd)[0]
    entries = [bytes(data[ifd + 2 + 12 * k : ifd + 14 + 12 * k]) for k in range(n)]
    kept = [e for e in entries if struct.unpack_from("<H", e)[0] not in codes]
    following = bytes(data[ifd + 2 + 12 * n : ifd + 6 + 12 * n])
    struct.pack_into("<H", data, ifd, len(kept))
    data[ifd + 2 : ifd + 6 + 12 * len(kept)] = b"".join(kept) + following
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("resolution", ["placeholder", "absent"])
def test_an_imagej_unit_without_a_resolution_states_no_pixel_size(tmp_path, resolution):
    """s38a: ImageJ's unit=mm with no XResolution/YResolution stated (tifffile's 1/1 placeholder,
    which it writes when given none; ImageJ writes a 1 mm pixel as 1000000/1000000 and leaves the
    tags out when it has no scale) read as a pitch of 1.0 mm, and `register` refused a 0.05 mm
    image beside it. No pitch is stated: none is read, with the note an unusable size gets."""
    path = tmp_path / "ij.tif"
    tifffile.imwrite(path, np.zeros((6, 7), np.uint16), imagej=True, metadata={"unit": "mm"})
    if resolution == "absent":
        _drop_tags(path, {282, 283, 296})
    with tifffile.TiffFile(path) as tif:  # the file is as meant
        assert tif.is_imagej and tif.pages[0].tags.valueof(282) == (None if resolution == "absent" else (1, 1))
    with pytest.warns(UserWarning, match=r"ij\.tif: ImageJ's unit and resolution: unit 'mm' .*pixel size is ignored"):
        meta = read(path).meta
    assert not {"x_pixel_size", "y_pixel_size", "pixel_size_mm"} & set(meta)
    info = run_cli("info", path)
    assert info.returncode == 0 and "pixel_size_mm" not in info.stdout and "unusable" in info.stdout, info.stdout


def _multifile_ome(folder, frames, names=("a.ome.tif", "b.ome.tif"), root_uuid=True, **write):
    """A multi-file OME-TIFF as Bio-Formats and Micro-Manager write one: each file holds some of
    the image's planes and the whole OME-XML, whose TiffData/UUID elements say which file holds
    which planes (each file's own UUID on its OME root)."""
    n, rows, cols = frames.shape
    per = n // len(names)
    uuids = [f"urn:uuid:0000000{k}-0000-0000-0000-000000000000" for k in range(len(names))]
    tiffdata = "".join(
        f'<TiffData FirstT="{k * per}" IFD="0" PlaneCount="{per}"><UUID FileName="{name}">{uuid}</UUID></TiffData>'
        for k, (name, uuid) in enumerate(zip(names, uuids))
    )
    for k, (name, uuid) in enumerate(zip(names, uuids)):
        xml = (
            '<?xml version="1.0" encoding="UTF-8"?>'
            '<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"'
            f"{f' UUID={uuid!r}' if root_uuid else ''}>"
            f'<Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYCZT" Type="uint16" SizeX="{cols}" '
            f'SizeY="{rows}" SizeC="1" SizeZ="1" SizeT="{n}"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>'
            f"{tiffdata}</Pixels></Image></OME>"
        )
        with tifffile.TiffWriter(folder / name) as tif:
            for i, frame in enumerate(frames[k * per : (k + 1) * per]):
                tif.write(frame, photometric="minisblack", description=xml if i == 0 else None, metadata=None, **write)
    return [folder / name for name in names]


@pytest.mark.parametrize("given", [0, 1])
def test_a_multi_file_ome_tiff_is_refused_unless_external_data_is_allowed(tmp_path, given):
    """s38a: a multi-file OME-TIFF (its OME-XML places planes 2 and 3 in b.ome.tif) read as the
    2 planes of the file given, silently: half the frames. Planes in other files are data outside
    the file, as an HDF5 external link's: refused in one line naming them, unless allowed."""
    frames = _frames(4)
    paths = _multifile_ome(tmp_path, frames)
    other = paths[1 - given]
    with pytest.raises(FormatError, match=rf"{paths[given].name}: .*4 planes.* in {other.name}.*allow_external=True"):
        read(paths[given])
    res = run_cli("info", paths[given])
    one_line_error(res, paths[given].name, other.name, "--allow-external")


@pytest.mark.parametrize("compression", [None, "zlib"])
@pytest.mark.parametrize("given", [0, 1])
def test_a_multi_file_ome_tiff_reads_every_plane_when_external_data_is_allowed(tmp_path, given, compression):
    """With allow_external (--allow-external) the planes in the files beside it are read, in
    OME's order, whichever file of the set is given; a file of the set that is missing is named."""
    frames = _frames(4)
    paths = _multifile_ome(tmp_path, frames, compression=compression)
    np.testing.assert_array_equal(_both_ways(paths[given], allow_external=True), frames)
    info = run_cli("info", "--allow-external", paths[given])
    assert info.returncode == 0 and "4 x 30 rows x 40 cols" in info.stdout, info.stdout + info.stderr
    paths[1 - given].unlink()
    with pytest.raises(FormatError, match=rf"{paths[given].name}: .*{paths[1 - given].name}.*missing"):
        read(paths[given], allow_external=True)


def test_a_renamed_single_file_ome_tiff_without_a_root_uuid_still_reads(tmp_path):
    """An OME root without a UUID names its file by TiffData's FileName only: renamed, the one
    file it names is itself (a set has two files at least), not planes elsewhere to refuse."""
    frames = _frames(2)
    (path,) = _multifile_ome(tmp_path, frames, names=("orig.ome.tif",), root_uuid=False)
    renamed = path.rename(tmp_path / "renamed.ome.tif")
    with tifffile.TiffFile(renamed) as tif:  # as meant: no root UUID, FileName not its own
        assert "<OME xmlns" in tif.ome_metadata and ' UUID="' not in tif.ome_metadata.split(">")[1]
    np.testing.assert_array_equal(read(renamed).data, frames)


def test_a_truncated_file_of_a_multi_file_ome_tiff_is_named_not_read_short(tmp_path):
    """The files beside it are held to the checks the file given is: one cut short is refused
    in one line naming it, not read as zeros or fewer frames."""
    first, second = _multifile_ome(tmp_path, _frames(4))
    second.write_bytes(second.read_bytes()[:-100])
    with pytest.raises(FormatError, match=r"b\.ome\.tif: TIFF .* lies beyond the end .* truncated or corrupt"):
        read(first, allow_external=True)


def _ome_xml(planes, rows, cols, tiffdata="", root=""):
    """OME-XML of one image of ``planes`` time points of (rows, cols) uint16."""
    return (
        '<?xml version="1.0" encoding="UTF-8"?>'
        f'<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06"{root}>'
        f'<Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYCZT" Type="uint16" SizeX="{cols}" '
        f'SizeY="{rows}" SizeC="1" SizeZ="1" SizeT="{planes}"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>'
        f"{tiffdata}</Pixels></Image></OME>"
    )


def _write_pages(path, frames, description):
    with tifffile.TiffWriter(path) as tif:
        for i, frame in enumerate(frames):
            tif.write(frame, photometric="minisblack", description=description if i == 0 else None, metadata=None)


@pytest.mark.parametrize(
    "tiffdata", ["", '<TiffData IFD="0" PlaneCount="4"/>', "<TiffData/>"], ids=["none", "count", "bare"]
)
def test_an_ome_tiff_holding_fewer_pages_than_its_planes_is_read_with_a_warning(tmp_path, tiffdata):
    """s38-h4: an OME-TIFF whose OME-XML says 4 planes (SizeT=4) but whose writer stopped after 2
    pages read as 2 frames with nothing said (tifffile logs it only). An ImageJ file so cut short
    warns; so does this, with the counts."""
    frames = _frames(2)
    path = tmp_path / "short.ome.tif"
    _write_pages(path, frames, _ome_xml(4, 30, 40, tiffdata))
    with pytest.warns(
        UserWarning, match=r"short\.ome\.tif: its OME-XML says 4 planes but it holds 2 pages .*reading the 2"
    ):
        np.testing.assert_array_equal(read(path).data, frames)
    whole = tmp_path / "whole.ome.tif"
    _write_pages(whole, _frames(4), _ome_xml(4, 30, 40, tiffdata))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read(whole).n == 4


def test_a_binary_only_ome_tiff_says_its_description_was_not_read(tmp_path):
    """s38-h4: a "BinaryOnly" OME-TIFF keeps its description (plane order, pixel size, the set's
    other files) in a companion file; its own pages read in file order with nothing said. Now a
    warning names the companion file that was not read."""
    frames = _frames(3)
    path = tmp_path / "part.ome.tif"
    xml = (
        '<?xml version="1.0" encoding="UTF-8"?>'
        '<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" '
        'UUID="urn:uuid:00000001-0000-0000-0000-000000000000">'
        '<BinaryOnly MetadataFile="set.companion.ome" UUID="urn:uuid:00000009-0000-0000-0000-000000000000"/></OME>'
    )
    _write_pages(path, frames, xml)
    with tifffile.TiffFile(path) as tif:  # as meant: tifffile sees OME
        assert tif.is_ome
    with pytest.warns(UserWarning, match=r"part\.ome\.tif: .*BinaryOnly.* set\.companion\.ome.* not read"):
        np.testing.assert_array_equal(read(path).data, frames)


def _mmstack_file(path, frames, first_t, total, description=None, position=0, positions=1):
    """A Micro-Manager multipage TIFF ("MMStack", MM 1.4/2.0), written byte by byte as tifffile
    writes none: its header at byte 8 (the summary, and an index map of each plane's IFD), IFDs
    of 13 entries with the pixels straight after (tifffile looks 162 bytes past the IFD), the
    OME-XML in page 0's description. Its planes are time points first_t, first_t + 1, ... of
    stage position ``position`` of ``positions``."""
    import json
    import struct

    n, rows, cols = frames.shape
    summary = json.dumps(
        {"MicroManagerVersion": "2.0.0", "Frames": total, "Channels": 1, "Slices": 1, "Positions": positions}
    ).encode()
    out = bytearray(b"II*\0\0\0\0\0" + bytes(32) + summary)
    display = len(out)
    out += struct.pack("<II", 347834724, 2) + b"[]"
    index_at = len(out)
    out += bytes(8 + 20 * n)
    offsets, link = [], 4
    for k, frame in enumerate(frames):
        out += bytes(len(out) % 2)
        offsets.append(at := len(out))
        struct.pack_into("<I", out, link, at)
        values = [(270, description.encode() + b"\0")] if k == 0 and description else []
        values += [(51123, json.dumps({"Frame": first_t + k}).encode() + b"\0")]
        count = 12 + len(values)
        pixels = at + 2 + 12 * count + 4
        extra, place = bytearray(), {}
        for code, blob in values + [(282, struct.pack("<II", 1, 1)), (283, struct.pack("<II", 1, 1))]:
            place[code] = pixels + rows * cols * 2 + len(extra)
            extra += blob + bytes(len(blob) % 2)
        entries = [(256, 4, 1, cols), (257, 4, 1, rows), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1)]
        entries += [(270, 2, len(values[0][1]), place[270])] if k == 0 and description else []
        entries += [(273, 4, 1, pixels), (277, 3, 1, 1), (278, 4, 1, rows), (279, 4, 1, rows * cols * 2)]
        entries += [(282, 5, 1, place[282]), (283, 5, 1, place[283]), (296, 3, 1, 1)]
        entries += [(51123, 2, len(values[-1][1]), place[51123])]
        out += struct.pack("<H", count) + b"".join(struct.pack("<HHII", *e) for e in entries)
        link = len(out)
        out += bytes(4) + frame.astype("<u2").tobytes() + extra
    struct.pack_into("<8I", out, 8, 54773648, index_at, 483765892, display, 0, 0, 2355492, len(summary))
    struct.pack_into("<II", out, index_at, 3453623, n)
    for k, offset in enumerate(offsets):
        struct.pack_into("<5I", out, index_at + 8 + 20 * k, 0, 0, first_t + k, position, offset)
    path.write_bytes(bytes(out))


def _mmstack_set(folder, frames, uuids=True):
    """Micro-Manager's stack split at 4 GB (here at 2 planes): exp_MMStack_Pos0.ome.tif with the
    OME-XML of every plane (its TiffData naming each plane's file by UUID, or not at all, as
    some versions write), and exp_MMStack_Pos0_1.ome.tif, BinaryOnly, naming the first."""
    rows, cols = frames.shape[1:]
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos0_1.ome.tif"]
    ids = [f"urn:uuid:0000000{k}-0000-0000-0000-000000000000" for k in (1, 2)]
    if uuids:
        tiffdata = "".join(
            f'<TiffData FirstT="{t}" IFD="{t % 2}" PlaneCount="1"><UUID FileName="{names[t // 2]}">{ids[t // 2]}</UUID>'
            "</TiffData>"
            for t in range(4)
        )
    else:
        tiffdata = "".join(f'<TiffData FirstT="{t}" IFD="{t}" PlaneCount="1"/>' for t in range(4))
    binary = (
        '<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" '
        f'UUID="{ids[1]}"><BinaryOnly MetadataFile="{names[0]}" UUID="{ids[0]}"/></OME>'
    )
    root = f' UUID="{ids[0]}"' if uuids else ""
    _mmstack_file(folder / names[0], frames[:2], 0, 4, _ome_xml(4, rows, cols, tiffdata, root))
    _mmstack_file(folder / names[1], frames[2:], 2, 4, binary)
    return [folder / name for name in names]


@pytest.mark.parametrize("uuids", [True, False], ids=["uuids", "no-uuids"])
@pytest.mark.parametrize("given", [0, 1])
def test_a_micro_manager_stack_split_over_files_is_refused_or_read_whole(tmp_path, given, uuids):
    """s38-h4: Micro-Manager splits a stack at 4 GB (exp_MMStack_Pos0.ome.tif, ..._Pos0_1.ome.tif).
    tifffile reads the set whole from either file by its index maps. radiokit read the first
    file's planes alone (its OME-XML naming no file: nothing said), refused the set with
    allow_external ("index out of range": a plane's place in the stack taken for its page in its
    file), and read the second file's alone. Now refused as other external data, naming the other
    file, and read whole with allow_external; data_files lists the other file."""
    from radiokit.io import data_files

    frames = _frames(4)
    paths = _mmstack_set(tmp_path, frames, uuids)
    with tifffile.TiffFile(paths[given]) as tif:  # as meant: tifffile takes it for a Micro-Manager set
        assert tif.is_mmstack and tif.series[0].is_multifile and tif.series[0].shape == frames.shape
    other = paths[1 - given]
    with pytest.raises(
        FormatError, match=rf"{paths[given].name}: a Micro-Manager stack .*2 in {other.name}.*allow_ext"
    ):
        read(paths[given])
    np.testing.assert_array_equal(_both_ways(paths[given], allow_external=True), frames)
    assert data_files(paths[given], allow_external=True) == [other]
    res = run_cli("info", paths[given])
    one_line_error(res, paths[given].name, other.name, "--allow-external")


@pytest.mark.parametrize("xml", [False, True], ids=["bare", "ome"])
def test_each_stage_position_of_a_micro_manager_acquisition_reads_as_its_own_stack(tmp_path, xml):
    """Micro-Manager writes each stage position to files of its own (exp_MMStack_Pos0.ome.tif,
    ..._Pos1.ome.tif), whose OME-XML names the others' as other images. tifffile's series of
    either takes in both positions: read through it, the two fields of view came interleaved as
    one stack of frames. Each file reads as its own position's frames, and nothing else."""
    from radiokit.io import data_files

    frames = _frames(4)
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos1.ome.tif"]
    ids = [f"urn:uuid:0000000{k}-0000-0000-0000-000000000000" for k in (1, 2)]
    images = "".join(
        f'<Image ID="Image:{p}"><Pixels ID="Pixels:{p}" DimensionOrder="XYCZT" Type="uint16" SizeX="40" SizeY="30" '
        'SizeC="1" SizeZ="1" SizeT="2"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>'
        f'<TiffData IFD="0" PlaneCount="2"><UUID FileName="{names[p]}">{ids[p]}</UUID></TiffData></Pixels></Image>'
        for p in (0, 1)
    )
    for p in (0, 1):
        description = (
            f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" '
            f'UUID="{ids[p]}">{images}</OME>'
        )
        _mmstack_file(tmp_path / names[p], frames[2 * p : 2 * p + 2], 0, 2, description if xml else None, p, 2)
    with tifffile.TiffFile(tmp_path / names[0]) as tif:  # as meant: tifffile's series takes in both
        assert tif.is_mmstack and tif.series[0].axes == "TRYX" and tif.series[0].is_multifile
    for p in (0, 1):
        for allow in (False, True):
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                np.testing.assert_array_equal(
                    _both_ways(tmp_path / names[p], allow_external=allow), frames[2 * p : 2 * p + 2]
                )
        # (the OME-XML names the other position's file: listed, so no output replaces it)
        assert data_files(tmp_path / names[p], allow_external=True) == ([tmp_path / names[1 - p]] if xml else [])


def _ome_files(folder, files, tiffdata, planes=4, rows=30, cols=40):
    """OME-TIFF files of one OME-XML's TiffData (``tiffdata``: (FirstT, PlaneCount, FileName,
    UUID) each, the UUID element's text), the XML in each with that file's own root UUID:
    ``files`` maps each name to (its root UUID or None, its frames)."""
    elements = "".join(
        f'<TiffData FirstT="{first}" IFD="0" PlaneCount="{count}"><UUID FileName="{name}">{uuid}</UUID></TiffData>'
        for first, count, name, uuid in tiffdata
    )
    for name, (uuid, frames) in files.items():
        root = f' UUID="{uuid}"' if uuid else ""
        _write_pages(folder / name, frames, _ome_xml(planes, rows, cols, elements, root))
    return [folder / name for name in files]


def _uuid(k):
    return f"urn:uuid:0000000{k}-0000-0000-0000-000000000000"


@pytest.mark.parametrize("theirs", [_uuid(9), None], ids=["other-set", "no-uuid"])
def test_a_multi_file_ome_tiff_refuses_a_file_of_another_set_by_its_uuid(tmp_path, theirs):
    """s38-h6 (HIGH): tifffile finds an OME-TIFF set's other files by FileName alone, so a
    b.ome.tif of another acquisition (its OME root UUID not the one a.ome.tif's TiffData names)
    gave a.ome.tif's planes 2-3, exit 0. Each other file's root UUID must be the one named, or
    the set is refused in one line naming both files and both UUIDs."""
    frames = _frames(4)
    mine = [(0, 2, "a.ome.tif", _uuid(1)), (2, 2, "b.ome.tif", _uuid(2))]
    (a,) = _ome_files(tmp_path, {"a.ome.tif": (_uuid(1), frames[:2])}, mine)
    # b.ome.tif of another acquisition: its own XML names its own set
    theirs_set = [(0, 2, "x.ome.tif", _uuid(8)), (2, 2, "b.ome.tif", theirs or _uuid(9))]
    _ome_files(tmp_path, {"b.ome.tif": (theirs, frames[2:] + 100)}, theirs_set)
    with pytest.raises(FormatError, match=rf"a\.ome\.tif: .*b\.ome\.tif.*{_uuid(2)}.*{theirs or 'no OME UUID'}"):
        read(a, allow_external=True)
    one_line_error(run_cli("info", "--allow-external", a), "a.ome.tif", "b.ome.tif", _uuid(2), theirs or "no OME UUID")
    # the same set with b's own UUID reads whole
    _ome_files(tmp_path, {"b.ome.tif": (_uuid(2), frames[2:])}, mine)
    np.testing.assert_array_equal(read(a, allow_external=True).data, frames)


def test_an_ome_tiff_mapping_planes_to_its_own_name_under_another_uuid_is_refused(tmp_path):
    """s38-h6 (HIGH): a file giving planes 2-3 to its own FileName under a UUID not its own read
    its planes 0-1 twice ([0, 1, 0, 1]): tifffile opened it again as the file of that UUID."""
    frames = _frames(2)
    tiffdata = [(0, 2, "self.ome.tif", _uuid(1)), (2, 2, "self.ome.tif", _uuid(7))]
    (path,) = _ome_files(tmp_path, {"self.ome.tif": (_uuid(1), frames)}, tiffdata)
    with pytest.raises(FormatError, match=rf"self\.ome\.tif: .*planes 2-3.*its own name.*{_uuid(7)}.*{_uuid(1)}"):
        read(path, allow_external=True)


def test_an_ome_tiff_plane_mapped_twice_or_not_at_all_is_refused(tmp_path):
    """s38-h6 (MEDIUM): planes 2-3 mapped to both b.ome.tif and c.ome.tif read from one of them,
    silently. A plane mapped twice is refused in one line; so is a plane of the image (SizeT)
    that no TiffData maps, where other files hold some (tifffile zero-fills it)."""
    frames = _frames(6)
    names = ["a.ome.tif", "b.ome.tif", "c.ome.tif"]
    tiffdata = [(0, 2, names[0], _uuid(0)), (2, 2, names[1], _uuid(1)), (2, 2, names[2], _uuid(2))]
    files = {name: (_uuid(k), frames[2 * k : 2 * k + 2]) for k, name in enumerate(names)}
    a, b, c = _ome_files(tmp_path, files, tiffdata)
    with pytest.raises(FormatError, match=r"a\.ome\.tif: .*planes 2-3 .*b\.ome\.tif.*c\.ome\.tif"):
        read(a, allow_external=True)
    one_line_error(run_cli("info", "--allow-external", a), "a.ome.tif", "planes 2-3", "b.ome.tif", "c.ome.tif")
    tiffdata = [(0, 2, names[0], _uuid(0)), (4, 2, names[2], _uuid(2))]  # planes 2-3 nowhere
    a, _, _ = _ome_files(tmp_path, files, tiffdata, planes=6)
    with pytest.raises(FormatError, match=r"a\.ome\.tif: .*planes 2-3 .*no file"):
        read(a, allow_external=True)


def test_the_other_files_of_an_ome_tiff_set_are_charged_their_pages(tmp_path):
    """s38-h6 (MEDIUM): the IFD walk charging a TIFF's pages against the memory budget ran on
    the file given only: tifffile built every page of the set's other files first (a 3,002-page
    sibling read under a 1 MB budget; an IFD chain looping in one was followed until killed).
    Every file of the set is walked first, their pages charged together."""
    import struct

    frames = _frames(300, rows=2, cols=2)
    tiffdata = [(0, 2, "a.ome.tif", _uuid(1)), (2, 298, "b.ome.tif", _uuid(2))]
    files = {"a.ome.tif": (_uuid(1), frames[:2]), "b.ome.tif": (_uuid(2), frames[2:])}
    a, b = _ome_files(tmp_path, files, tiffdata, planes=300, rows=2, cols=2)
    budget = 250 * 3000  # b's pages (about 298 x (1000 + 10 x 250) bytes) alone pass over it
    with pytest.raises(FormatError, match=r"b\.ome\.tif: TIFF of at least \d+ pages.*memory budget"):
        read(a, allow_external=True, budget=budget)
    assert read(a, allow_external=True, budget=100 * budget).n == 300
    # b's last IFD leads back to its 150th: tifffile follows it for ever past its 100th
    data = bytearray(b.read_bytes())
    offsets, at = [], struct.unpack_from("<I", data, 4)[0]
    while at:
        offsets.append(at)
        end = at + 2 + 12 * struct.unpack_from("<H", data, at)[0]
        at = struct.unpack_from("<I", data, end)[0]
    struct.pack_into("<I", data, end, offsets[150])
    b.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=r"b\.ome\.tif: TIFF IFD chain loops"):
        read(a, allow_external=True)


@pytest.mark.parametrize("count", [3, 10**9])
def test_an_ome_tiff_plane_count_beyond_the_pages_of_its_file_is_refused(tmp_path, count):
    """s38-h6 (MEDIUM): a TiffData's PlaneCount of 10**9 for b.ome.tif (2 pages) took 13 GB and
    a minute (tifffile builds a list of that many planes). A PlaneCount beyond the pages of the
    file it names is refused in one line before any list of planes is built."""
    frames = _frames(4)
    tiffdata = [(0, 2, "a.ome.tif", _uuid(1)), (2, count, "b.ome.tif", _uuid(2))]
    files = {"a.ome.tif": (_uuid(1), frames[:2]), "b.ome.tif": (_uuid(2), frames[2:])}
    a, _ = _ome_files(tmp_path, files, tiffdata)
    with pytest.raises(FormatError, match=rf"a\.ome\.tif: .*{count} planes .*b\.ome\.tif.* 2 pages"):
        read(a, allow_external=True)
    one_line_error(run_cli("info", "--allow-external", a), "a.ome.tif", "b.ome.tif", f"{count} planes")


def test_the_other_files_of_a_micro_manager_stack_are_charged_their_pages(tmp_path):
    """s38-h6 (MEDIUM): as an OME-TIFF set's, a split Micro-Manager stack's other file had its
    pages built unwalked and uncharged: its pages are charged with the first file's."""
    first, second = _mmstack_set(tmp_path, _frames(4))
    alone = check_tiff_pages(first, budget=10**9)[1]
    with pytest.raises(FormatError, match=r"exp_MMStack_Pos0_1\.ome\.tif: TIFF of at least .*memory budget"):
        read(first, allow_external=True, budget=alone + 1000)
    assert read(first, allow_external=True, budget=3 * alone).n == 4


def test_an_ome_tiff_alone_naming_planes_by_the_million_is_refused_before_tifffile_lists_them(tmp_path):
    """s38-h6: tifffile lists a slot for each plane a TiffData's PlaneCount or the image's size
    names before it reads a page (8 bytes each: 8 GB for 10**9). A file alone whose PlaneCount
    passes both its pages and its image's planes is refused, and so is an image of more planes
    than the memory budget lists; a writer that stopped early (PlaneCount = SizeT, fewer pages)
    still reads with a warning (test above)."""
    path = tmp_path / "one.ome.tif"
    _write_pages(path, _frames(2), _ome_xml(4, 30, 40, '<TiffData IFD="0" PlaneCount="1000000"/>'))
    with pytest.raises(FormatError, match=r"one\.ome\.tif: .*1000000 planes from IFD 0 of one\.ome\.tif.* 2 pages"):
        read(path)
    _write_pages(path, _frames(2), _ome_xml(20_000_000, 30, 40))
    with pytest.raises(FormatError, match=r"one\.ome\.tif: its OME-XML's 20000000 planes .*memory budget"):
        read(path, budget="10MiB")


def test_an_ome_tiff_naming_another_file_without_a_uuid_reads_that_file_or_is_refused(tmp_path):
    """s38-h6: a file with no root UUID, its own planes in a TiffData without a UUID and planes
    2-3 in b.ome.tif under a UUID element with no text, read its own 2 planes (b taken for this
    file renamed; warned short), and once b was counted as another file, [0, 1, 0, 1]: tifffile
    keys files by the UUID text, and this file's is none too. Each plane must come from the
    file its TiffData names."""
    tiffdata = '<TiffData FirstT="0" IFD="0" PlaneCount="2"/><TiffData FirstT="2" IFD="0" PlaneCount="2">'
    tiffdata += '<UUID FileName="b.ome.tif"/></TiffData>'
    frames = _frames(4)
    for name, part in (("a.ome.tif", frames[:2]), ("b.ome.tif", frames[2:])):
        _write_pages(tmp_path / name, part, _ome_xml(4, 30, 40, tiffdata))
    with pytest.raises(FormatError, match=r"a\.ome\.tif: .*planes 2-3 in b\.ome\.tif.*allow_external"):
        read(tmp_path / "a.ome.tif")
    with pytest.raises(FormatError, match=r"a\.ome\.tif: .*plane 2 .*b\.ome\.tif.* read it from a\.ome\.tif"):
        read(tmp_path / "a.ome.tif", allow_external=True)


def _mm_patch(path, summary=None, coords=None):
    """Rewrite a :func:`_mmstack_file`'s summary (padded to its length: written with a long
    ``total`` to leave room) and its index map's (channel, slice, frame, position) of each plane."""
    import json
    import struct

    out = bytearray(path.read_bytes())
    _, index_at, *_, length = struct.unpack_from("<8I", out, 8)
    if summary is not None:
        text = json.dumps({"MicroManagerVersion": "2.0.0", **summary}).encode()
        assert len(text) <= length
        out[40 : 40 + length] = text.ljust(length)
    for k, coord in enumerate(coords or ()):
        struct.pack_into("<4I", out, index_at + 8 + 20 * k, *coord)
    path.write_bytes(bytes(out))


def test_a_micro_manager_summary_or_index_map_declaring_planes_by_the_million_is_refused(tmp_path):
    """s39 review (MEDIUM): tifffile's Micro-Manager series lists a slot for every plane the
    summary's counts (Frames x Slices x Channels x Positions) or the index map's coordinates
    declare, before radiokit's IFD walk or page budget: two 5 KB files of a split set whose
    summary said Frames 4*10**8 took `radiokit info` 214 s and 7.8 GB; one 5 KB file whose
    index map put a plane at T = 4*10**8 - 1, 42 s and 6.3 GB (then read as 2 frames). Refused
    now, naming the file, before tifffile lists them; an acquisition stopped early (a summary
    planning more frames than the files hold) reads what was written, with a warning (s40: the
    summary is a plan, the index maps what was written). (10**6 here: a million slots are cheap
    to list, and past what 5 KB can hold as the millions are.)"""
    from radiokit.io import data_files

    frames = _frames(4)
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos0_1.ome.tif"]
    for k, name in enumerate(names):
        _mmstack_file(tmp_path / name, frames[2 * k : 2 * k + 2], 2 * k, 4)
    # the second file's index map puts its last plane at T = 10**6 - 1
    _mm_patch(tmp_path / names[1], coords=[(0, 0, 2, 0), (0, 0, 10**6 - 1, 0)])
    first = tmp_path / names[0]
    for allow in (False, True):
        with pytest.raises(
            FormatError, match=r"exp_MMStack_Pos0\.ome\.tif: .*Micro-Manager stack of 1000000 planes.* can hold"
        ):
            read(first, allow_external=allow)
    one_line_error(run_cli("info", first), names[0], "Micro-Manager stack of 1000000 planes")
    data_files(first, allow_external=True)  # (the read judges it; listing it must not list the slots)

    alone = tmp_path / "alone"
    alone.mkdir()
    path = alone / "one.tif"
    _mmstack_file(path, frames[:2], 0, 2)
    _mm_patch(path, coords=[(0, 0, 0, 0), (0, 0, 10**6 - 1, 0)])
    with pytest.raises(FormatError, match=r"one\.tif: .*Micro-Manager stack of 1000000 planes.* can hold"):
        read(path)
    line = one_line_error(run_cli("info", "one.tif", cwd=alone), "Micro-Manager stack of 1000000 planes")
    assert line.startswith("radiokit info: one.tif: "), line  # the file as the user named it

    # a name tifffile's glob of the set (*_MMStack*.tif) misses: it listed the summary's slots,
    # and lists the index map's now
    path = alone / "tiff_MMStack_Pos0.ome.tiff"
    _mmstack_file(path, frames[:2], 0, 10**15)
    _mm_patch(path, {"Frames": 10**6, "Channels": 1, "Slices": 1, "Positions": 1})
    with pytest.warns(UserWarning, match=r"Pos0\.ome\.tiff: .*summary planned 1000000 planes .*stopped early"):
        np.testing.assert_array_equal(read(path).data, frames[:2])


@pytest.mark.parametrize("planned", [100, 4 * 10**8], ids=["planned-100", "planned-4e8"])
def test_a_micro_manager_set_stopped_early_reads_the_planes_written_with_a_warning(tmp_path, planned):
    """s39 review (LOW): Micro-Manager writes the summary, with the acquisition's planned counts,
    as it opens each file and never again; the index map records each plane as it is written
    (MultipageTiffWriter). A set of files whose acquisition was stopped early was refused as
    "corrupt" (its files' bytes too few for the planned planes' index entries) or as planes "not
    in the files it names". Its written planes are read, in order, with one warning naming the
    plan and what was found; planning 4*10**8 costs nothing (tifffile lists the planes found)."""
    import time

    from radiokit.io import data_files

    frames = _frames(4)
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos0_1.ome.tif"]
    for k, name in enumerate(names):
        _mmstack_file(tmp_path / name, frames[2 * k : 2 * k + 2], 2 * k, 10**15)
        _mm_patch(tmp_path / name, {"Frames": planned, "Channels": 1, "Slices": 1, "Positions": 1})
    first = tmp_path / names[0]
    start = time.perf_counter()
    with pytest.warns(UserWarning, match=rf"Pos0\.ome\.tif: .*summary planned {planned} .*4 .*stopped early") as got:
        np.testing.assert_array_equal(_both_ways(first, allow_external=True), frames)
    assert time.perf_counter() - start < 5, "the planned slots were listed"  # 4e8 of them: 214 s
    assert len({str(w.message) for w in got}) == 1, [str(w.message) for w in got]
    with pytest.raises(FormatError, match=r"Pos0\.ome\.tif: a Micro-Manager stack .*2 in .*Pos0_1.*allow_ext"):
        read(first)
    res = run_cli("info", "--allow-external", first)  # (run_cli hides warnings: the one above is checked)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert data_files(first, allow_external=True) == [tmp_path / names[1]]  # (was []: no output may replace it)

    # a plane missing inside the written ones (T 2 of 0-4) is no stop: refused, as a file cut short
    _mmstack_file(tmp_path / names[1], frames[2:], 3, 10**15)
    _mm_patch(tmp_path / names[1], {"Frames": planned, "Channels": 1, "Slices": 1, "Positions": 1})
    with pytest.raises(FormatError, match=r"Pos0\.ome\.tif: .*1 of them are not in the files"):
        read(first, allow_external=True)


def test_a_micro_manager_file_alone_stopped_early_says_so(tmp_path):
    """As a set's: the one file of an acquisition stopped early read its planes silently
    (tifffile only logs); now with the warning."""
    path = tmp_path / "stopped_MMStack_Pos0.ome.tif"
    frames = _frames(2)
    _mmstack_file(path, frames, 0, 10**15)
    _mm_patch(path, {"Frames": 10**6, "Channels": 1, "Slices": 1, "Positions": 1})
    with pytest.warns(UserWarning, match=r"Pos0\.ome\.tif: .*summary planned 1000000 .*2 .*stopped early"):
        np.testing.assert_array_equal(read(path).data, frames)


def _mm_index_at(path):
    """Where a :func:`_mmstack_file`'s index map lies (its header: magic, count; then 20 bytes a plane)."""
    import struct

    return struct.unpack_from("<8I", path.read_bytes(), 8)[1]


@pytest.mark.parametrize("planned", [100, 4 * 10**8], ids=["planned-100", "planned-4e8"])
@pytest.mark.parametrize("damage", ["never-written", "entries-zero", "count-4e8", "count-0"])
def test_a_micro_manager_set_whose_file_has_no_index_map_written_is_refused_naming_it(tmp_path, damage, planned):
    """s40 review (MEDIUM): a set whose second file's index map was never written (an acquisition
    that crashed: left zero, or its entries zero, which tifffile takes for plane (0, 0, 0, 0) at
    offset 0), or counts 4*10**8 entries, read the first file's 2 of 4 frames with the "stopped
    early: reading the 2 written" warning, dropping the second file's 2 written pages silently,
    and data_files left that file out (an output could replace it). Refused in one line naming
    the file and its index map, fast; data_files lists it."""
    import struct
    import time

    from radiokit.io import data_files

    frames = _frames(4)
    first, second = tmp_path / "exp_MMStack_Pos0.ome.tif", tmp_path / "exp_MMStack_Pos0_1.ome.tif"
    _mmstack_file(first, frames[:2], 0, 10**15)
    _mmstack_file(second, frames[2:], 2, 10**15)
    for path in (first, second):
        _mm_patch(path, {"Frames": planned, "Channels": 1, "Slices": 1, "Positions": 1})
    out, at = bytearray(second.read_bytes()), _mm_index_at(second)
    if damage == "never-written":
        out[at : at + 8 + 20 * 2] = bytes(8 + 20 * 2)
    elif damage == "entries-zero":
        out[at + 8 + 20 : at + 8 + 20 * 2] = bytes(20)  # its last plane's entry, pre-allocated, never filled
    else:
        struct.pack_into("<I", out, at + 4, 4 * 10**8 if damage == "count-4e8" else 0)
    second.write_bytes(bytes(out))
    start = time.perf_counter()
    with pytest.raises(FormatError, match=r"exp_MMStack_Pos0_1\.ome\.tif: .*index map .*crashed"):
        read(first, allow_external=True)
    assert time.perf_counter() - start < 2
    one_line_error(run_cli("info", "--allow-external", first), second.name, "index map")
    assert data_files(first, allow_external=True) == [second]
    # named itself, the file is no plain TIFF of its own pages (the set's first file left out)
    for allow in (False, True):
        with pytest.raises(FormatError, match=r"exp_MMStack_Pos0_1\.ome\.tif: .*index map .*crashed"):
            read(second, allow_external=allow)
    assert data_files(second, allow_external=True) == [first]


def test_a_micro_manager_file_alone_missing_a_plane_inside_the_written_ones_is_refused(tmp_path):
    """s40 review (LOW): one file holding T 0, 1, 3 of a summary planning 100 read as 3
    consecutive frames with the "stopped early" warning, while the same gap across a set is
    refused: a plane missing inside the written ones is no acquisition stopped early."""
    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    frames = _frames(3)
    _mmstack_file(path, frames, 0, 10**15)
    _mm_patch(
        path, {"Frames": 100, "Channels": 1, "Slices": 1, "Positions": 1}, [(0, 0, 0, 0), (0, 0, 1, 0), (0, 0, 3, 0)]
    )
    with pytest.raises(FormatError, match=r"Pos0\.ome\.tif: .*none at T 2\b.*missing"):
        read(path)
    one_line_error(run_cli("info", path), path.name, "T 2")
    # the written ones without a gap still read, with the warning
    _mm_patch(path, coords=[(0, 0, 0, 0), (0, 0, 1, 0), (0, 0, 2, 0)])
    with pytest.warns(UserWarning, match=r"Pos0\.ome\.tif: .*summary planned 100 .*stopped early"):
        np.testing.assert_array_equal(read(path).data, frames)


@pytest.mark.parametrize("kind", ["micro-manager", "ome"])
def test_a_dangling_symlink_named_as_a_file_of_a_set_is_named_as_such(tmp_path, kind):
    """s39 review (LOW): a dangling symbolic link named as one of a set's files was said to be
    "missing" (OME) or gave "[Errno 2] No such file or directory" (Micro-Manager), while `ls`
    shows it there. The one line names the link and says it points nowhere."""
    frames = _frames(4)
    if kind == "ome":
        given, link = tmp_path / "a.ome.tif", tmp_path / "b.ome.tif"
        tiffdata = [(0, 2, given.name, _uuid(1)), (2, 2, link.name, _uuid(2))]
        _ome_files(tmp_path, {given.name: (_uuid(1), frames[:2])}, tiffdata)
    else:
        given, link = tmp_path / "exp_MMStack_Pos0.ome.tif", tmp_path / "exp_MMStack_Pos0_1.ome.tif"
        _mmstack_file(given, frames[:2], 0, 4)
    os.symlink("gone.ome.tif", link)
    for flags in ([], ["--allow-external"]) if kind != "ome" else (["--allow-external"],):
        line = one_line_error(run_cli("info", *flags, given), given.name, link.name, "gone.ome.tif")
        assert "symbolic link" in line and "points nowhere" in line and "Errno" not in line, line
        with pytest.raises(FormatError, match=rf"{link.name} is a symbolic link to gone\.ome\.tif"):
            read(given, allow_external=bool(flags))


@pytest.mark.parametrize("written", ["slices-outer", "frames-outer"])
def test_a_micro_manager_file_of_slices_and_frames_reads_in_its_planes_order_and_says_so(tmp_path, written):
    """s39 review (LOW): a Micro-Manager file without OME-XML holding 2 slices at each of 2 time
    points read in file order with nothing said, whatever order the acquisition wrote them in:
    as the planes lie in tifffile's series of it (time points outer, slices inner, from the
    index map), as an ImageJ or OME hyperstack's do, and ``stacked`` says so."""
    from radiokit.io import open_frames

    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    frames = _frames(4)
    # (channel, slice, frame, position) of each plane in file order
    if written == "slices-outer":
        coords, order = [(0, 0, 0, 0), (0, 0, 1, 0), (0, 1, 0, 0), (0, 1, 1, 0)], [0, 2, 1, 3]
    else:
        coords, order = [(0, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 1, 1, 0)], [0, 1, 2, 3]
    _mmstack_file(path, frames, 0, 10**15)
    _mm_patch(path, {"Frames": 2, "Channels": 1, "Slices": 2, "Positions": 1}, coords)
    with tifffile.TiffFile(path) as tif:  # as meant: tifffile sees the axes, no OME
        assert tif.is_mmstack and not tif.is_ome and tif.series[0].axes == "TZYX"
        np.testing.assert_array_equal(tif.series[0].asarray().reshape(4, 30, 40), frames[order])
    np.testing.assert_array_equal(_both_ways(path), frames[order])
    with open_frames(path) as src:
        assert src.meta["stacked"] == {"shape": [2, 2], "axes": "TZ"}
    res = run_cli("info", path)
    assert res.returncode == 0 and "2 x 2 (TZ), read flat in that order" in res.stdout, res.stdout


def test_micro_manager_positions_stopped_early_at_different_time_points_each_read_theirs(tmp_path):
    """Stopped between two stage positions of one time point, position 0 holds 3 time points and
    position 1 only 2 of the set's span: each file reads its own planes, with the warning (the
    missing last one was refused as a plane not in the files)."""
    frames = _frames(5)
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos1.ome.tif"]
    _mmstack_file(tmp_path / names[0], frames[:3], 0, 10**15, position=0, positions=2)
    _mmstack_file(tmp_path / names[1], frames[3:], 0, 10**15, position=1, positions=2)
    for name in names:
        _mm_patch(tmp_path / name, {"Frames": 100, "Channels": 1, "Slices": 1, "Positions": 2})
    for name, own in zip(names, (frames[:3], frames[3:])):
        with pytest.warns(UserWarning, match=rf"{name}: .*summary planned 200 planes .*stopped early"):
            np.testing.assert_array_equal(_both_ways(tmp_path / name, allow_external=True), own)


def test_a_micro_manager_set_with_a_sparse_file_is_charged_its_slots_to_the_memory_budget(tmp_path, monkeypatch):
    """s39 review (MEDIUM): a set's file truncated to gigabytes (sparse: no disk taken) passed the
    bytes-per-plane bound, and tifffile listed 10**8 slots (850 MB). The slots are charged to the
    memory budget too. A summary's count of 1e400 (infinity) is no crash."""
    import os

    frames = _frames(4)
    names = ["exp_MMStack_Pos0.ome.tif", "exp_MMStack_Pos0_1.ome.tif"]
    for k, name in enumerate(names):
        _mmstack_file(tmp_path / name, frames[2 * k : 2 * k + 2], 2 * k, 4)
    _mm_patch(tmp_path / names[1], coords=[(0, 0, 2, 0), (0, 0, 10**6 - 1, 0)])  # a plane at T = 10**6 - 1
    os.truncate(tmp_path / names[1], 64 * 2**20)  # 64 MiB, holes: room for 3 million index entries
    monkeypatch.setenv("RADIOKIT_MEMORY_BUDGET", "4MiB")  # under the 1000000 slots' ~20 MB
    with pytest.raises(FormatError, match=r"listing a Micro-Manager stack of 1000000 planes.*memory budget"):
        read(tmp_path / names[0], allow_external=True)
    one_line_error(run_cli("info", tmp_path / names[0]), names[0], "memory budget")

    path = tmp_path / "inf" / "one_MMStack_Pos0.ome.tif"
    path.parent.mkdir()
    _mmstack_file(path, frames[:2], 0, 10**15)
    _mm_patch(path, {"Frames": 123456789, "Channels": 1, "Slices": 1, "Positions": 1})
    path.write_bytes(path.read_bytes().replace(b'"Frames": 123456789', b'"Frames": 1e400    ', 1))
    res = run_cli("info", path)
    assert "Traceback" not in res.stderr and "infinity" not in res.stderr, res.stderr


@pytest.mark.parametrize(
    "counts, coords, what",
    [
        ({"Channels": 2, "Frames": 2}, [(0, 0, 0, 0), (1, 0, 0, 0), (0, 0, 1, 0), (1, 0, 1, 0)], "2 channels"),
        ({"Channels": 2, "Slices": 2}, [(0, 0, 0, 0), (1, 0, 0, 0), (0, 1, 0, 0), (1, 1, 0, 0)], "2 channels"),
        ({"Positions": 2, "Frames": 2}, [(0, 0, 0, 0), (0, 0, 0, 1), (0, 0, 1, 0), (0, 0, 1, 1)], "2 stage positions"),
    ],
    ids=["channels-frames", "channels-slices", "positions-frames"],
)
def test_a_micro_manager_file_of_several_channels_or_positions_is_refused(tmp_path, counts, coords, what):
    """s39 review (MEDIUM): a Micro-Manager file without OME-XML holding 2 channels (or 2 stage
    positions) at each of 2 time points or slices read as one stack of 4 frames, the channels
    interleaved as successive frames, silently; with OME-XML it is refused as a multi-channel
    OME-TIFF is. Refused alike, from tifffile's reading of its summary and index map. Channels
    (or positions) alone still read as frames, as an OME-TIFF's or ImageJ's do."""
    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    frames = _frames(4)
    _mmstack_file(path, frames, 0, 10**15)
    _mm_patch(path, {"Frames": 1, "Channels": 1, "Slices": 1, "Positions": 1, **counts}, coords)
    with tifffile.TiffFile(path) as tif:  # as meant: tifffile sees the axes, no OME
        assert tif.is_mmstack and not tif.is_ome and tif.series[0].shape == (2, 2, 30, 40)
    with pytest.raises(FormatError, match=rf"exp_MMStack_Pos0\.ome\.tif: .*{what}.*not one stack of frames"):
        read(path)
    one_line_error(run_cli("info", path), path.name, what)

    alone = tmp_path / "alone_MMStack_Pos0.ome.tif"
    _mmstack_file(alone, frames[:2], 0, 10**15)
    axis = "Channels" if "channels" in what else "Positions"
    _mm_patch(alone, {"Frames": 1, "Channels": 1, "Slices": 1, "Positions": 1, axis: 2}, [c for c in coords[:2]])
    np.testing.assert_array_equal(read(alone).data, frames[:2])


@pytest.mark.parametrize("block", ["index map", "summary"])
def test_a_micromanager_index_map_declaring_more_than_its_file_is_refused_without_the_memory(tmp_path, block):
    """tifffile reads a Micro-Manager index map's declared entries in one read: 8 GB asked of a
    5 KB file declaring 4*10**8. Where memory is not overcommitted that read fails, and the file
    was "cannot be read as tiff: " with nothing after. The declared size is now checked against the
    file's bytes first. The address space is limited (``ulimit -v``) to stand for a machine that
    does not overcommit: such a machine cannot be had here otherwise."""
    import struct

    path = tmp_path / "exp_MMStack_Pos0.ome.tif"
    _mmstack_file(path, _frames(2), 0, 10**15)
    _mm_patch(path, {"Frames": 4 * 10**8, "Channels": 1, "Slices": 1, "Positions": 1})
    out = bytearray(path.read_bytes())
    _, index_at, *_ = struct.unpack_from("<8I", out, 8)
    if block == "index map":
        struct.pack_into("<I", out, index_at + 4, 4 * 10**8)  # the index map's count
        said = "index map declares 400000000 entries, more than the file's"
    else:  # review s40rr4: the summary's length, read by tifffile in one read too
        struct.pack_into("<I", out, 36, 0xF0000000)
        said = "gives its summary 4026531840 bytes, more than the file's"
    path.write_bytes(bytes(out))
    code = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)); "
        "from radiokit.cli import script; sys.exit(script())"
    )
    res = subprocess.run([sys.executable, "-c", code, "info", str(path)], capture_output=True, text=True, timeout=120)
    one_line_error(res, path.name, said)


def _gdal_tiff(path, data, items, nodata=None):
    """A TIFF as GDAL writes one: GDAL_METADATA (42112) XML items, GDAL_NODATA (42113) text."""
    xml = "<GDALMetadata>" + "".join(
        f'<Item name="{name}" sample="0" role="{name.lower()}">{value}</Item>' for name, value in items.items()
    )
    tags = [(42112, "s", 0, xml + "</GDALMetadata>", True)]
    if nodata is not None:
        tags.append((42113, "s", 0, str(nodata), True))
    tifffile.imwrite(path, data, extratags=tags, photometric="minisblack")
    return path


@pytest.mark.parametrize("dtype", ["u2", "f4"])
def test_a_gdal_tiff_reads_its_scale_and_offset_and_nodata_as_gdal_does(tmp_path, dtype):
    """s46: GDAL's SCALE and OFFSET (value = stored * scale + offset, as an HDF5 file's CF packing)
    and its NODATA code were ignored: every pixel read as the stored count, a silent wrong value."""
    stored = _frames(2, 20, 30).astype(dtype)
    stored[1, 3, 4:7] = 7  # the nodata code
    path = _gdal_tiff(tmp_path / "g.tif", stored, {"SCALE": 0.25, "OFFSET": -100}, nodata=7)
    got = read(path)
    expected = stored.astype(np.float64) * 0.25 - 100
    expected[stored == 7] = np.nan
    assert got.data.dtype.kind == "f"
    np.testing.assert_allclose(got.data, expected, rtol=1e-6, equal_nan=True)
    assert got.meta["gdal_scaling"] == {"scale": 0.25, "offset": -100.0, "nodata": 7.0}


@pytest.mark.parametrize("items", [{"SCALE": 0}, {"SCALE": "nan"}, {"OFFSET": "abc"}])
def test_a_gdal_tiff_of_unusable_scaling_is_refused_in_one_line(tmp_path, items):
    path = _gdal_tiff(tmp_path / "g.tif", _frames(1, 20, 30), items)
    with pytest.raises(FormatError, match=r"g\.tif: GDAL_METADATA's (SCALE|OFFSET) is .*needs a finite number"):
        read(path)
    if "OFFSET" in items:  # (one command line: the same refusal)
        one_line_error(run_cli("info", path), "g.tif", "GDAL")


@pytest.mark.parametrize(
    "item",
    [
        '<Item name="OFFSET">250</Item>',  # dataset metadata (no sample): GDAL scales by role alone
        '<Item name="SCALE">1:100</Item>',  # refused as "no finite number": a readable file
        '<Item name="SCALE" domain="xml:lab">0.5</Item>',  # another domain's, no role
        '<Item name="SCALE" role="scale">0.5</Item>',  # no sample: the dataset's, no band's
        '<Item name="SCALE" sample="1" role="scale">0.5</Item>',  # band 2's, of a one-band image
    ],
)
def test_a_gdal_item_without_band_1s_role_is_metadata_not_scaling(tmp_path, item):
    """Review s46rio: GDAL applies SCALE/OFFSET only from an item of role "scale"/"offset" and
    sample 0 (band 1); an item named SCALE or OFFSET without them is a metadata entry. Read as
    scaling, a dataset item <Item name="OFFSET">250</Item> added 250 to every pixel, silently."""
    stored = _frames(2, 20, 30)
    xml = f"<GDALMetadata>{item}</GDALMetadata>"
    tifffile.imwrite(tmp_path / "g.tif", stored, extratags=[(42112, "s", 0, xml, True)], photometric="minisblack")
    got = read(tmp_path / "g.tif")
    np.testing.assert_array_equal(got.data, stored)
    assert "gdal_scaling" not in got.meta


@pytest.mark.parametrize("nodata, warns", [("-9999", False), ("nan", False), ("1e9", False), (" 0 ", True)])
def test_a_gdal_nodata_on_integer_pixels_warns_only_where_a_pixel_can_hold_it(tmp_path, nodata, warns):
    """Review s46rio: GDAL_NODATA -9999 or nan on uint16 pixels marks none of them; the warning that
    they have "no NaN to mark them with" was noise on a file read exactly as stored."""
    stored = _frames(1, 20, 30)
    path = tmp_path / "g.tif"
    tifffile.imwrite(path, stored, extratags=[(42113, "s", 0, nodata, True)], photometric="minisblack")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        got = read(path)
    np.testing.assert_array_equal(got.data, stored)
    assert any("GDAL_NODATA" in str(w.message) for w in seen) == warns, [str(w.message) for w in seen]


def test_info_says_a_gdal_tiffs_values_are_scaled_and_a_lone_frame_is_one(tmp_path):
    """Review s46rio: `info` printed a GDAL-scaled file's range (23.72 .. 35.95 of stored counts
    2872 .. 4095) with no word that its values are not the stored counts; and one NaN in a
    one-frame file read "in 1 of 1 frames"."""
    stored = _frames(1, 20, 30).astype(np.float32)
    stored[0, 2, 3] = 7
    path = _gdal_tiff(tmp_path / "g.tif", stored, {"SCALE": 0.25, "OFFSET": -100}, nodata=7)
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    assert re.search(r"gdal_scaling\s+stored \* 0\.25 \+ -100, NODATA 7 as NaN", res.stdout), res.stdout
    assert re.search(r"nonfinite\s+1 pixel\(s\) NaN or inf in 1 of 1 frame$", res.stdout, re.M), res.stdout


def _clipped_12_bit(path, stored, scaled):
    """``stored`` (uint16 counts) written GDAL-scaled (a .tif) or CF-packed (an .h5), as stored
    unscaled if not ``scaled``: SCALE 0.01, OFFSET -5 (a 12-bit top of 4095 reads 35.95)."""
    if path.suffix == ".tif":
        return _gdal_tiff(path, stored, {"SCALE": 0.01, "OFFSET": -5} if scaled else {})
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("frames", data=stored)
        if scaled:
            ds.attrs["scale_factor"], ds.attrs["add_offset"] = np.float32(0.01), np.float32(-5)
    return path


_H5_FRAMES = {".h5": {"dataset": "/frames"}}


def _clipped_darks_flats(tmp_path, suffix, scaled):
    rng = np.random.default_rng(7)
    dark = rng.normal(100, 3, (4, 32, 32)).astype(np.uint16)
    flat = rng.normal(3000, 30, (4, 32, 32)).astype(np.uint16)
    flat[:, :4, :4] = 4095  # a clipped corner, 16 pixels in every frame
    return (_clipped_12_bit(tmp_path / f"{what}{suffix}", a, scaled) for what, a in (("d", dark), ("f", flat)))


@pytest.mark.parametrize("scaled", [False, True])
@pytest.mark.parametrize("suffix", [".tif", ".h5"])
def test_a_scaled_12_bit_flat_clipped_at_its_top_is_still_called_saturated(tmp_path, suffix, scaled):
    """Review s46rio: the saturation rules are in ADC counts; judged in a GDAL-scaled (or CF-packed)
    file's values a 12-bit panel's top (4095 stored, 35.95 scaled) was never reached, and calibrate's
    "lower the flat exposure" went unsaid. The level is the stored top's value, 4095 * 0.01 - 5."""
    from radiokit.calibrate import CalibrationWarning

    darks, flats = (read(p, **_H5_FRAMES.get(suffix, {})) for p in _clipped_darks_flats(tmp_path, suffix, scaled))
    with pytest.warns(CalibrationWarning, match="16 pixels of the flats are saturated"):
        cal = Calibration.from_frames(darks, flats)
    expected = 4095 * 0.01 - 5 if scaled else 4095
    assert cal.thresholds.saturation == pytest.approx(expected, rel=1e-6)


def test_a_scaled_files_offset_does_not_make_its_darks_bright(tmp_path):
    """The half-range rule (darks over half the ADC's range carry light) starts the range at 0: in
    values offset by 100 a 12-bit top reads 140.95, and darks of 100 stored counts (101) passed half
    of it. Not judged in scaled values; the clipped flats still are."""
    from radiokit.calibrate import CalibrationWarning

    rng = np.random.default_rng(7)
    dark = rng.normal(100, 3, (4, 32, 32)).astype(np.uint16)
    flat = rng.normal(3000, 30, (4, 32, 32)).astype(np.uint16)
    flat[:, :4, :4] = 4095
    darks, flats = (
        read(_gdal_tiff(tmp_path / f"{w}.tif", a, {"SCALE": 0.01, "OFFSET": 100}))
        for w, a in (("d", dark), ("f", flat))
    )
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        Calibration.from_frames(darks, flats)
    told = [str(w.message) for w in seen if issubclass(w.category, CalibrationWarning)]
    assert any("16 pixels of the flats are saturated" in t for t in told), told
    assert not any("over half the ADC's range" in t for t in told), told


@pytest.mark.parametrize("suffix", [".tif", ".h5"])
def test_info_counts_a_scaled_files_clipped_pixels_at_its_stored_top(tmp_path, suffix):
    """Review s46rio: `info` said "saturated 256 pixel(s) >= 4095" of the file read as stored, and
    nothing once its values were scaled: 16 clipped pixels in each of 4 frames."""
    _, flats = _clipped_darks_flats(tmp_path, suffix, True)
    res = run_cli("info", flats, *(["--dataset", "/frames"] if suffix == ".h5" else []))
    assert res.returncode == 0, res.stderr
    assert re.search(r"saturated\s+64 pixel\(s\) >= 35\.95\d* \(from the values of the stored counts", res.stdout), (
        res.stdout
    )


def test_calibrate_and_correct_count_a_gdal_scaled_panels_clipped_pixels(tmp_path):
    """Review s46rio, the commands' words: calibrate's "N pixels of the flats are saturated" went
    unsaid and correct said "0 saturated" for a projection clipped in 9 pixels, all scaled alike."""
    dark, flat = _clipped_darks_flats(tmp_path, ".tif", True)
    res = run_cli("calibrate", "--dark", dark, "--flat", flat, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    cal = Calibration.load(tmp_path / "cal.h5")
    assert cal.provenance["n_flat_saturated"] == 16, cal.provenance
    assert cal.thresholds.saturation == pytest.approx(4095 * 0.01 - 5, rel=1e-6)
    proj = np.full((1, 32, 32), 1500, np.uint16)
    proj[0, 10:13, 10:13] = 4095
    path = _clipped_12_bit(tmp_path / "p.tif", proj, True)
    res = run_cli("correct", path, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5")
    assert res.returncode == 0, res.stderr
    assert re.search(r"\b9 saturated", res.stdout + res.stderr), res.stdout + res.stderr


def test_a_negatively_scaled_files_saturation_is_said_unchecked_not_zero(tmp_path):
    """A negative SCALE makes the stored top the values' floor: not judged, and said so rather than
    reported as no pixel saturated."""
    stored = np.full((2, 16, 16), 3000, np.uint16)
    stored[:, :2, :2] = 4095
    path = _gdal_tiff(tmp_path / "n.tif", stored, {"SCALE": -0.01, "OFFSET": 50})
    res = run_cli("info", "--json", path)
    assert res.returncode == 0, res.stderr
    import json

    rep = json.loads(res.stdout)
    rep = rep[0] if isinstance(rep, list) else rep
    assert rep["saturated"] == "unknown" and "not checked: values scaled" in rep["saturation_from"], rep


def test_correct_says_a_negatively_scaled_calibrations_saturation_was_not_checked(tmp_path):
    """s47: calibrate warned that a negative SCALE's saturation is not checked, but the calibration
    then took the ADC top its scaled averages implied (4095, values of 10 to 40 never reach it),
    and correct said "0 saturated" of a projection whose 9 pixels sit at the stored top."""
    rng = np.random.default_rng(3)
    scale = {"SCALE": -0.01, "OFFSET": 50}  # value = 50 - stored / 100: the stored top is the floor
    dark = _gdal_tiff(tmp_path / "d.tif", rng.normal(4000, 3, (4, 32, 32)).astype(np.uint16), scale)
    flat = _gdal_tiff(tmp_path / "f.tif", rng.normal(1000, 30, (4, 32, 32)).astype(np.uint16), scale)
    proj = np.full((1, 32, 32), 2000, np.uint16)
    proj[0, :3, :3] = 4095
    proj = _gdal_tiff(tmp_path / "p.tif", proj, scale)
    res = run_cli("calibrate", "--dark", dark, "--flat", flat, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    cal = Calibration.load(tmp_path / "cal.h5")
    assert cal.thresholds.saturation is None, cal.thresholds
    from radiokit.correct import correct_files

    summary = correct_files([proj], cal, tmp_path / "api.h5", progress=False)
    assert summary["saturated"] == "unknown" and "not checked" in summary["saturation_from"], summary
    res = run_cli("correct", proj, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5")
    assert res.returncode == 0, res.stderr
    assert "saturation not checked" in res.stdout and " 0 saturated" not in res.stdout, res.stdout


def test_a_tiff_of_an_unknown_compression_is_refused_naming_its_code(tmp_path):
    # tifffile keeps a code it does not know as an int: "cannot be read as tiff: 'int' object has
    # no attribute 'name'"
    import struct

    path = tmp_path / "comp.tif"
    tifffile.imwrite(path, np.zeros((64, 64), np.uint16), photometric="minisblack")
    with tifffile.TiffFile(path) as tif:
        at = tif.pages[0].tags["Compression"].valueoffset
    with open(path, "r+b") as f:
        f.seek(at)
        f.write(struct.pack("<H", 60000))
    with pytest.raises(FormatError) as info:
        read(path)
    assert str(path) in str(info.value) and "60000" in str(info.value) and "'int'" not in str(info.value)
    one_line_error(run_cli("info", path), "comp.tif", "60000", "compression")
