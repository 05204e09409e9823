"""An experiment file states the detector's pitch and name only where its writer was told them,
and says where they came from: a file written from another panel's frames claimed the C7942's
50 µm and its name (the writer's silent defaults), and every length in mm rested on it."""

import json

import h5py
import numpy as np
import pytest
from conftest import run_cli

from radiokit.io import C7942_PIXEL_SIZE_MM, ExperimentWriter, ImageKey, read


def _write(path, **kw):
    with ExperimentWriter(path, shape=(4, 5), **kw) as w:
        w.append(np.zeros((4, 5), np.uint16), image_key=ImageKey.DARK)
    return path


def _info(path) -> dict:
    res = run_cli("info", "--json", path)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)[0]["metadata"]


def test_a_writer_told_nothing_claims_no_pitch_and_no_name(tmp_path):
    path = _write(tmp_path / "other.h5")
    meta = read(path).meta
    assert "pixel_size_mm" not in meta and "x_pixel_size" not in meta
    assert "detector" not in meta
    with h5py.File(path) as h5:
        assert "description" not in h5["entry/instrument/detector"]
    info = _info(path)
    assert "pixel_size_mm" not in info and "detector" not in info
    # info says what the readers will take instead, and that it is an assumption
    assert info["pixel_size"] == f"not recorded (readers assume {C7942_PIXEL_SIZE_MM * 1e3:g} \u00b5m, the C7942's)"


def test_a_writer_told_the_pitch_and_name_records_them_and_where_they_came_from(tmp_path):
    path = _write(
        tmp_path / "panel.h5",
        pixel_size_mm=0.139,
        pixel_size_from="the protocol's [detector] pixel_size_mm",
        detector_name="Varex 4343",
    )
    meta = read(path).meta
    assert meta["pixel_size_mm"] == pytest.approx(0.139, rel=1e-12)
    assert meta["detector"] == "Varex 4343"
    assert meta["pixel_size_from"] == "the protocol's [detector] pixel_size_mm"
    info = _info(path)
    assert info["pixel_size_mm"] == pytest.approx(0.139, rel=1e-6)
    assert info["detector"] == "Varex 4343"
    assert info["pixel_size_from"] == "the protocol's [detector] pixel_size_mm"


def test_a_file_of_the_old_writer_reads_as_before(tmp_path):
    """The old writer's file: a variable-length description, a pitch with no word of its origin."""
    path = _write(tmp_path / "old.h5", pixel_size_mm=C7942_PIXEL_SIZE_MM)
    with h5py.File(path, "r+") as h5:
        det = h5["entry/instrument/detector"]
        det["description"] = "Hamamatsu C7942SK-02"  # as h5py writes a str: variable-length
        for axis in ("x_pixel_size", "y_pixel_size"):
            det[axis].attrs.pop("pixel_size_from", None)
    meta = read(path).meta
    assert meta["pixel_size_mm"] == pytest.approx(C7942_PIXEL_SIZE_MM, rel=1e-12)
    assert meta["detector"] == "Hamamatsu C7942SK-02"
    assert "pixel_size_from" not in meta
    info = _info(path)
    assert info["pixel_size_mm"] == pytest.approx(C7942_PIXEL_SIZE_MM, rel=1e-6)
    assert "pixel_size" not in info


def test_a_name_or_origin_given_without_reason_is_refused(tmp_path):
    with pytest.raises(ValueError, match="pixel_size_from"):
        _write(tmp_path / "a.h5", pixel_size_from="the preset")  # an origin of no pitch
    with pytest.raises(ValueError, match="detector_name"):
        _write(tmp_path / "b.h5", detector_name=7)


@pytest.mark.parametrize(
    ("kw", "shape", "said"),
    [
        ({"pixel_size_mm": 0.1}, (8, 10), "the protocol's [detector] pixel_size_mm"),
        ({"preset": "c7942-2x2"}, None, "the detector preset c7942-2x2"),
        ({}, (1120, 1120), "the frames' width, 1120 columns: the C7942 binned 2x2"),
        ({}, (8, 10), None),  # 0.05 mm only assumed: the acquisition records no pitch then
    ],
)
def test_the_folder_watcher_says_where_its_pitch_came_from(tmp_path, kw, shape, said):
    from acquisition.detector import FolderWatcher

    det = FolderWatcher(tmp_path, "*.tif", shape=shape, **kw)
    assert det.pixel_size_from == said
    assert det.panel_name == "Hamamatsu C7942SK-02"
    # the run's record of its devices (/entry@devices) claims no more than the file's pitch does:
    # an assumed 0.05 mm stood there as the watcher's own
    described = det.describe()
    assert described["pixel_size_from"] == said
    assert described["pixel_size_mm"] == (None if said is None else pytest.approx(det.pixel_size_mm, rel=1e-12))
