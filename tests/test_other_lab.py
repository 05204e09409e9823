"""Another lab's panel and source through radiokit: what the files record must be what the lab
said, never the C7942 / L8121 bench's identity by default (session 54's outside-user pass)."""

import numpy as np

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
