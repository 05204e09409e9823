"""radiokit never writes JSON it refuses to read back (radiokit._json: 4 MiB, 32 levels).

Each writer of a record is written at its largest and read back: a corrected stack's sources are
listed while short and summarised (a count and a digest) when long, so a 50 000-file stack reads
back as a record; a record that would still pass the bound (a calibration's provenance of
thousands of files) is refused in one line before any file is made.
"""

import hashlib
import os
import warnings

import numpy as np
import pytest

from radiokit import _json as strict_json
from radiokit.calibrate import Calibration
from radiokit.io import StackWriter, read, read_stack

#: a path as a scan names its projection files (~110 characters): 50 000 of them are ~5.7 MB of JSON
_NAME = "/data/beamtime-2026-12/scans/2026-12-07/sample-042_compression-series/projections/proj_{:05d}_0.100s_40kV.tif"


def _names(n):
    return [_NAME.format(i) for i in range(n)]


@pytest.mark.parametrize("suffix", [".h5", ".tif"])
def test_a_corrected_stack_of_50000_sources_reads_back_as_its_record(tmp_path, suffix):
    """The meta ``correct`` writes for 50 000 files (one TIFF per projection) reads back as a
    record, not text refused past the bound: the list summarised, its digest the names'."""
    from radiokit.correct import stack_meta

    names = _names(50_000)
    assert len(strict_json.dumps(names)) > strict_json.MAX_CHARS  # the case is past the bound
    meta = stack_meta("log", {"n_darks": 1}, names)
    out = tmp_path / f"c{suffix}"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "kept as text" is the failure
        with StackWriter(out, (4, 4), meta=meta) as w:
            w.append(np.zeros((4, 4), np.float32))
        if suffix == ".h5":
            back = read_stack(out).meta
        else:
            back = read(out).meta["description"]
    sources = back["sources"]
    assert sources["count"] == 50_000
    assert sources["first"] == names[0] and sources["last"] == names[-1]
    assert sources["sha256"] == hashlib.sha256(b"\0".join(os.fsencode(n) for n in names)).hexdigest()
    assert back["calibration"] == {"n_darks": 1} and back["domain"] == "log"


def test_a_short_source_list_is_kept_as_the_names():
    from radiokit.correct import stack_meta

    assert stack_meta("log", {}, _names(3))["sources"] == _names(3)


@pytest.mark.parametrize("suffix", [".h5", ".tif"])
def test_a_stack_whose_meta_would_not_read_back_is_refused_before_any_file(tmp_path, suffix):
    """StackWriter given meta past the bound (a caller's own) refuses in one line naming the
    output, before its file exists: it wrote it, and read_stack then kept it as text."""
    out = tmp_path / f"s{suffix}"
    with pytest.raises(ValueError) as info:
        StackWriter(out, (4, 4), meta={"sources": _names(50_000)})
    message = str(info.value)
    assert "\n" not in message and str(out) in message and "sources" in message
    assert "not written" in message and str(strict_json.MAX_CHARS) in message
    assert list(tmp_path.iterdir()) == []


def _calibration(n_inputs):
    rng = np.random.default_rng(1)
    cal = Calibration.from_frames(
        rng.normal(100, 2, (3, 8, 8)).astype(np.float32), rng.normal(1000, 10, (3, 8, 8)).astype(np.float32)
    )
    record = {"path": "", "resolved": "", "format": "tiff", "dataset": None, "option": None, "darks": 1, "flats": 0}
    cal.provenance["inputs"] = [record | {"path": n, "resolved": n} for n in _names(n_inputs)]
    return cal


def test_a_calibration_whose_provenance_would_not_read_back_is_refused_unwritten(tmp_path):
    """A provenance past the bound (30 000 files) is refused at save, naming the file; the
    largest under it (one of 12 000, 3.9 MB) is written and loads as it was."""
    big = _calibration(30_000)
    assert len(strict_json.dumps(big.provenance)) > strict_json.MAX_CHARS
    out = tmp_path / "cal.h5"
    with pytest.raises(ValueError) as info:
        big.save(out)
    message = str(info.value)
    assert "\n" not in message and str(out) in message and "not written" in message and "provenance" in message
    assert not out.exists() and list(tmp_path.iterdir()) == []

    largest = _calibration(12_000)
    assert len(strict_json.dumps(largest.provenance)) > strict_json.MAX_CHARS * 9 // 10
    largest.save(out)
    assert Calibration.load(out).provenance["inputs"] == largest.provenance["inputs"]


def test_results_h5_holds_its_results_json_read_at_the_results_json_bound(tmp_path):
    """results.h5 embeds results.json's text, read by results.json's own bound (64 MiB), not a
    description's 4 MiB: the numbers of a run of 250 000 ratios (4.8 MB) were skipped by ``info``,
    which then said nothing of the pitch the run assumed."""
    from conftest import run_cli

    from radiokit.io import ResultsRecord, write_results
    from radiokit.results import MAX_JSON_BYTES

    ratios = [i / 7 for i in range(250_000)]
    numbers = {"schema_version": "1.4", "pixel_size_mm": 0.05, "pixel_size_recorded": False, "ratios": ratios}
    text = strict_json.dumps_readable(numbers, "results.h5", "results.json", MAX_JSON_BYTES)
    assert strict_json.MAX_CHARS < len(text) < MAX_JSON_BYTES
    path = tmp_path / "results.h5"
    record = ResultsRecord(
        source="exp.h5",
        results_json=text,
        line_integral=np.zeros((2, 8, 8), np.float32),
        step=np.array([1, 2]),
        ratio=np.array([0.1, 0.2]),
        crop=np.array([0, 8, 0, 8]),
        pair=(1, 2),
    )
    write_results(path, record)
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    assert "not recorded (assumed 50 \u00b5m)" in res.stdout, res.stdout


def test_a_results_json_that_would_not_read_back_is_refused_unwritten(tmp_path):
    """Results.write_json wrote a record whose "paper" (the caller's) nests past radiokit's 32
    levels, and load_results then refused the file it had written; now refused before the file,
    in one line naming it. The same record at the depth allowed is written and reads back."""
    from test_hostile_inputs import _results_json

    from radiokit.results import Results, load_results

    def nested(levels):
        value = {}
        for _ in range(levels - 1):  # the paper dict is a level inside the results' own object
            value = {"x": value}
        return value

    out = tmp_path / "results.json"
    deep = Results.from_json(_results_json() | {"paper": nested(strict_json.MAX_DEPTH + 1)})
    with pytest.raises(ValueError) as info:
        deep.write_json(out)
    message = str(info.value)
    assert "\n" not in message and str(out) in message and "not written" in message
    assert list(tmp_path.iterdir()) == []

    fits = Results.from_json(_results_json() | {"paper": nested(strict_json.MAX_DEPTH - 1)})
    assert load_results(fits.write_json(out)).paper == fits.paper


def test_a_tiff_stacks_sources_get_the_room_its_calibrations_provenance_leaves(tmp_path):
    """review s53rvoff: a TIFF's one description holds the calibration's provenance and the
    sources together; the list was summarised only past a quarter of the bound, so a calibration
    of 10 000 files (3.3 MB, which Calibration.save writes and load reads) with 9 000 projection
    files (1.0 MB) made ``correct`` refuse a .tif output that each part alone fits. The list is
    summarised where the whole description would pass the bound, and the stack reads back."""
    from radiokit.correct import SOURCES_LISTED_CHARS, stack_meta

    provenance = _calibration(10_000).provenance
    names = _names(9_000)
    listed, prov = len(strict_json.dumps(names)), len(strict_json.dumps(provenance))
    assert listed < SOURCES_LISTED_CHARS and prov < strict_json.MAX_CHARS < listed + prov  # the case
    meta = stack_meta("log", provenance, names)
    out = tmp_path / "c.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with StackWriter(out, (4, 4), meta=meta) as w:
            w.append(np.zeros((4, 4), np.float32))
        back = read(out).meta["description"]
    assert back["sources"]["count"] == 9_000 and back["sources"]["last"] == names[-1]
    assert back["calibration"]["inputs"] == provenance["inputs"]
    # a short list beside a short provenance is still named one by one
    assert stack_meta("log", _calibration(10).provenance, names)["sources"] == names
    # no files beside a provenance past the bound: nothing to summarise (names[0] raised IndexError)
    assert stack_meta("log", _calibration(14_000).provenance, [])["sources"] == []


def test_results_write_json_replaces_the_file_whole_never_rewrites_it_in_place(tmp_path):
    """review s53rvoff: Results.write_json wrote with ``Path.write_text``, truncating the file in
    place: a crash or a full disk mid-write left a truncated results.json where the last good one
    was. It writes a temporary file beside it and renames it over: a hard link to the old file
    (its inode) still holds the old text whole, the new name the new, no temporary left behind.
    The library call still replaces an existing file (the CLI refuses without --overwrite)."""
    from test_hostile_inputs import _results_json

    from radiokit.results import Results, load_results

    out = tmp_path / "results.json"
    old = Results.from_json(_results_json())
    old.write_json(out)
    before = out.read_text()
    os.link(out, tmp_path / "kept.json")
    new = Results.from_json(_results_json() | {"paper": {"note": "second run"}})
    assert new.write_json(out) == out
    assert (tmp_path / "kept.json").read_text() == before  # the old inode untouched
    assert load_results(out).paper == {"note": "second run"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.json", "results.json"]


def test_calibrate_from_files_whose_names_alone_pass_the_bound_is_refused_before_any_is_read(tmp_path):
    """review s53rvoff: ``calibrate`` from more files than its provenance can name (each file's
    name as given, resolved, and its record: ~13 000 of 90 characters) read every frame, then
    refused the save, naming "the calibration", not the output. The names alone tell it: refused
    first, in one line naming the output. The files here are not images at all, so a line about
    them would mean they were opened; the paths are long (3 500 characters) to keep them few."""
    from conftest import run_cli

    deep = tmp_path
    for i in range(14):  # 14 folders of 248 characters: a path under PATH_MAX (4096)
        deep = deep / (f"{i:02d}" + "d" * 246)
    deep.mkdir(parents=True)
    per_file = 3 * len(str(deep / "0000.tif"))  # as given in dark_files/flat_files, and in its record twice
    n = strict_json.MAX_CHARS // per_file + 20
    files = [deep / f"{i:04d}.tif" for i in range(n)]
    for f in files:
        f.write_bytes(b"not an image")
    out = tmp_path / "cal.h5"
    res = run_cli("calibrate", "--dark", *files[: n // 2], "--flat", *files[n // 2 :], "-o", out)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (line,) = res.stderr.splitlines()
    assert line.startswith(f"radiokit calibrate: {out}: not written: "), line
    assert f"{n} dark and flat file(s)" in line and str(strict_json.MAX_CHARS) in line, line
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["00" + "d" * 246]


def test_a_calibration_saved_into_a_file_object_names_the_file_its_bytes_are_for(tmp_path):
    """``radiokit calibrate`` saves into memory first (its size then known): a provenance past
    the bound was refused as "the calibration: not written", naming no file. ``name`` names it."""
    import io

    out = tmp_path / "cal.h5"
    with pytest.raises(ValueError) as info:
        _calibration(30_000).save(io.BytesIO(), name=out)
    message = str(info.value)
    assert message.startswith(f"{out}: not written: the calibration's provenance"), message


def test_from_frames_refuses_frames_its_provenance_could_not_name_before_averaging(tmp_path):
    """``calibrate`` refuses files its provenance could not name before reading them; the Python
    way, ``Calibration.from_frames(read(...), read(...))``, averaged them and the save then
    refused the calibration. Here an HDF5 dataset's name (h5py writes one past the bound: the
    provenance records the dataset read) is refused at from_frames, in one line naming the file,
    by the rule the command applies (radiokit.calibrate.refuse_unnameable)."""
    import h5py

    name = "d" * (strict_json.MAX_CHARS + 100)
    path = tmp_path / "long.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset(name, data=np.full((3, 8, 8), 100, np.uint16))
        f.create_dataset("flats", data=np.full((3, 8, 8), 1000, np.uint16))
    darks, flats = read(path, hdf5_dataset=name), read(path, hdf5_dataset="flats")
    flats.data[...] = 50  # darker than the darks: a calibration averaged first is refused for that
    with pytest.raises(ValueError) as info:
        Calibration.from_frames(darks, flats)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and str(strict_json.MAX_CHARS) in message, message[:300]
    assert "provenance" in message and len(message) < 2000, message[:300]
    # one file (two of its datasets): it was said "2 dark and flat files" (review s54rvoff)
    assert ": 1 dark and flat file(s) would be named" in message, message[-400:]


def test_every_frame_s_source_index_names_its_file_where_the_sources_are_summarised(tmp_path, monkeypatch):
    """A stack's ``sources`` summarised (a count, the first and last names and a digest: past the
    bound, 11 000-odd files) lost the middle names its frames' ``source_index`` counts into, so a
    frame of file 3 of 5 could not be traced. The HDF5 stack lists every name in ``/entry/sources``
    (a dataset: no JSON bound), read back as ``StackRecord.sources``, and the summary says where.
    Here the summary is forced at 5 files (the bound lowered: 11 000 files take minutes); each
    file's frames are a level of their own, so a frame's values say which file it came from."""
    import tifffile

    import radiokit.correct as correct

    rng = np.random.default_rng(3)
    dark, flat = 100.0, 1100.0
    cal = Calibration.from_frames(
        np.rint(rng.normal(dark, 1, (4, 8, 8))).astype(np.uint16), np.full((4, 8, 8), flat, np.uint16)
    )
    levels = [300 + 150 * i for i in range(5)]
    files = [tmp_path / f"projection_{i:02d}_{'x' * i}.tif" for i in range(5)]
    for i, (f, level) in enumerate(zip(files, levels, strict=True)):
        tifffile.imwrite(f, np.full((1 + i % 2, 8, 8), level, np.uint16), photometric="minisblack")
    monkeypatch.setattr(correct, "SOURCES_LISTED_CHARS", 10)
    out = tmp_path / "c.h5"
    correct.correct_files(files, cal, out, domain="linear", progress=False)
    rec = read_stack(out)
    assert rec.meta["sources"]["count"] == 5 and rec.meta["sources"]["listed_in"] == "/entry/sources"
    assert list(rec.sources) == [str(f) for f in files]
    assert len(rec.data) == sum(1 + i % 2 for i in range(5))
    for frame, si in zip(rec.data, rec.series["source_index"], strict=True):
        level = levels[int(si)]  # the file it names: its transmission (level - dark) / (flat - dark)
        expected = (level - np.median(cal.dark)) / (flat - np.median(cal.dark))
        assert np.median(frame) == pytest.approx(expected, rel=0.01), (si, np.median(frame))


@pytest.mark.parametrize("summarised", [False, True])
def test_a_stacks_sources_read_back_whole_with_names_no_utf8_can_write(tmp_path, summarised):
    """``/entry/sources`` holds each name's bytes as the file system gave them (a Latin-1 é is
    no UTF-8), read back as Python names them (os.fsdecode); a listed ``sources`` reads back as
    the same list."""
    from radiokit.correct import stack_meta

    names = [str(tmp_path / "a.tif"), os.fsdecode(b"/data/caf\xe9.tif"), "/data/z\nnewline.tif"]
    meta = stack_meta("log", {}, names, listed_in="/entry/sources")
    if summarised:
        meta["sources"] = {"count": 3, "first": names[0], "last": names[-1], "listed_in": "/entry/sources"}
    out = tmp_path / "s.h5"
    with StackWriter(out, (4, 4), meta=meta, sources=names) as w:
        w.append(np.zeros((4, 4), np.float32), source_index=np.int32(1))
    assert list(read_stack(out).sources) == names
