"""Another lab's panel and source through radiokit: what the files record must be what the lab
said, never the C7942 / L8121 bench's identity by default (session 54's outside-user pass)."""

import numpy as np
import pytest

from radiokit.io import ExperimentWriter, ImageKey, read


def test_writer_records_no_source_name_it_was_not_given(tmp_path):
    # a lab packing its own frames gives the exposure, not a tube model: the file (and `radiokit
    # info`'s source line) must not claim the Hamamatsu L8121-01 for it
    path = tmp_path / "exp.h5"
    with ExperimentWriter(
        path, shape=(16, 16), pixel_size_mm=0.139, bit_depth=14, source={"voltage_kv": 70, "current_ua": 400}
    ) as w:
        w.append(np.full((16, 16), 300, np.uint16), image_key=ImageKey.DARK)
    src = read(path).meta["source"]
    assert "name" not in src, src
    assert src["voltage"] == 70.0 and src["current"] == 400.0
    assert read(path).meta["pixel_size_mm"] == 0.139


def test_writer_records_the_source_name_it_was_given(tmp_path):
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(16, 16), source={"name": "Varian G-1592", "voltage_kv": 70}) as w:
        w.append(np.full((16, 16), 300, np.uint16), image_key=ImageKey.DARK)
    assert read(path).meta["source"]["name"] == "Varian G-1592"


def _panel_file(path, pitch_mm):
    """A 64 x 64 experiment file of a 14-bit panel at ``pitch_mm``: darks, flats, two projections."""
    rng = np.random.default_rng(3)
    with ExperimentWriter(path, shape=(64, 64), pixel_size_mm=pitch_mm, bit_depth=14) as w:
        for _ in range(4):
            w.append(rng.poisson(300, (64, 64)).astype(np.uint16), image_key=ImageKey.DARK)
        for _ in range(4):
            w.append(rng.poisson(12000, (64, 64)).astype(np.uint16), image_key=ImageKey.FLAT)
        for step in (1, 2):
            w.append(rng.poisson(6000, (64, 64)).astype(np.uint16), image_key=ImageKey.PROJECTION, step=step)
    return path


def test_corrected_stack_keeps_the_frames_pitch(tmp_path):
    # a 0.139 mm panel's frames corrected: the stack must still say 0.139 mm (it said nothing, and
    # mm ROIs on it would have needed the pitch typed again)
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files

    exp = _panel_file(tmp_path / "exp.h5", 0.139)
    f = read(exp)
    keys = np.asarray(f.meta["image_key"])
    cal = Calibration.from_frames(f.data[keys == 2], f.data[keys == 1])
    correct_files([exp], cal, tmp_path / "c.h5", progress=False)
    meta = read(tmp_path / "c.h5").meta
    assert meta["pixel_size_mm"] == np.float64(0.139) or abs(meta["pixel_size_mm"] - 0.139) < 1e-9
    assert abs(meta["y_pixel_size"] - 0.139e-3) < 1e-12


def test_frames_of_two_pitches_are_not_corrected_into_one_stack(tmp_path):
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files

    a, b = _panel_file(tmp_path / "a.h5", 0.139), _panel_file(tmp_path / "b.h5", 0.05)
    f = read(a)
    keys = np.asarray(f.meta["image_key"])
    cal = Calibration.from_frames(f.data[keys == 2], f.data[keys == 1])
    with pytest.raises(ValueError, match=r"b\.h5.*0\.05 mm.*a\.h5.*0\.139 mm"):
        correct_files([a, b], cal, tmp_path / "c.h5", progress=False)
    assert not (tmp_path / "c.h5").exists()


def test_a_stack_with_a_pitch_reads_back_its_series(tmp_path):
    # read_stack took every dataset beside the frames for a per-frame series, and refused the pitch
    from radiokit.io import StackWriter, read_stack

    with StackWriter(tmp_path / "s.h5", (4, 4), pixel_sizes={"x_pixel_size": 1.39e-4, "y_pixel_size": 1.39e-4}) as w:
        for i in range(3):
            w.append(np.full((4, 4), i, np.float32), step=np.int16(i))
    rec = read_stack(tmp_path / "s.h5")
    assert set(rec.series) == {"step"} and rec.data.shape == (3, 4, 4)
    assert abs(read(tmp_path / "s.h5").meta["pixel_size_mm"] - 0.139) < 1e-9
