"""Slips the offline commands once accepted in silence, each now one line and exit code 2 (or,
for non-finite numbers, strict JSON that reads back): real files, the real command's ``main`` run
in this process (``conftest.run_cli``: nothing here needs a process of its own; tests/test_cli.py
runs the installed command)."""

from __future__ import annotations

import json
import math
import os

import h5py
import numpy as np
import pytest
import tifffile
from conftest import one_line_error, read_only, run_cli, synthetic

from radiokit import _json as strict_json
from radiokit.calibrate import MAX_DEFECTIVE_SHARE, Calibration
from radiokit.errors import FormatError
from radiokit.io import ExperimentWriter, ImageKey, StackWriter, read, read_stack, write_tiff
from radiokit.io._experiment import IMAGE_KEY, read_progress
from radiokit.results import load_results
from sim.detector import PanelModel

# the square inclusion of synthetic() and a background beside it, whole frame (no crop)
ROI = ["--inclusion", "75", "86", "75", "86", "--background", "75", "86", "40", "51", "--crop-mm", "0"]
FAST = ["-q", "--no-report", "--cross-check", "none", *ROI]


def _no_constants(word):
    raise ValueError(f"{word} is not JSON")


def strict_loads(text):
    """What jq or JavaScript's JSON.parse accept: no NaN, Infinity or -Infinity."""
    return json.loads(text, parse_constant=_no_constants)


# -- 1: strict JSON ----------------------------------------------------------------------------
def test_results_json_of_a_noiseless_run_is_strict_json_and_reads_back_infinite(tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    res = run_cli("process", exp, "-o", tmp_path / "res", *FAST)
    assert res.returncode == 0, res.stderr
    text = (tmp_path / "res" / "results.json").read_text()
    d = strict_loads(text)  # was: "Infinity is not JSON"
    # the reason is in the file: null, and not_finite names it Infinity (noise exactly zero)
    assert d["domains"]["log"]["cnr_reference"] is None
    assert d["not_finite"]["/domains/log/cnr_reference"] == "Infinity"
    assert d["not_finite"]["/domains/negative/cnr/2"] in ("Infinity", "-Infinity")
    record = load_results(tmp_path / "res" / "results.json")
    assert math.isinf(record.domains[record.domain].cnr_reference)
    assert all(math.isinf(m.cnr) for m in record.domains[record.domain].per_k)
    # the improvement factors are finite and unchanged by the round trip
    assert all(math.isfinite(v) and v > 0 for v in record.improvement_factor.values())
    with h5py.File(tmp_path / "res" / "results.h5") as h5:  # the copy inside results.h5 too
        strict_loads(h5["entry"].attrs["results_json"])
    # the Python API keeps the numbers: only the files are strict (to_json returned nulls)
    d_api = record.to_json()
    assert math.isinf(d_api["domains"]["log"]["cnr_reference"]) and "not_finite" not in d_api


@pytest.fixture(scope="module")
def noiseless_results_json(tmp_path_factory):
    """The results.json of a noiseless `process` run (its not_finite map names Infinities), made
    once: the cases below each edit their own copy of the text, and load_results reads nothing
    else of the folder."""
    tmp = tmp_path_factory.mktemp("noiseless")
    exp = synthetic(tmp / "exp.h5")
    assert run_cli("process", exp, "-o", tmp / "res", *FAST).returncode == 0
    return read_only(tmp / "res" / "results.json")


@pytest.mark.parametrize(
    "marks, words",
    [
        ({"/domains/log/contrast_reference": "Infinity"}, "names no null"),  # a number there
        ({"/no/such/key": "NaN"}, "names no null"),
        ({"/domains/log/cnr_reference": "Inf"}, "expected Infinity, -Infinity or NaN"),
        (["/domains/log/cnr_reference"], "not an object"),
        ({"domains": "NaN"}, "not a JSON pointer"),
        ({"/domains/log/cnr_reference": ["NaN"]}, "expected Infinity, -Infinity or NaN"),  # was a TypeError
    ],
)
def test_a_hand_edited_not_finite_map_is_one_line(marks, words, noiseless_results_json, tmp_path):
    path = tmp_path / "res" / "results.json"
    path.parent.mkdir()
    d = json.loads(noiseless_results_json.read_text())
    d["not_finite"] = marks
    path.write_text(json.dumps(d))
    with pytest.raises(FormatError, match=words) as exc:
        load_results(path)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_the_strict_form_round_trips_every_non_finite_number():
    doc = {"a": [1.0, math.inf, {"b/c": -math.inf, "d~e": math.nan}], "f": None, "g": np.float32("nan")}
    text = strict_json.dumps(doc)
    strict_loads(text)
    back = strict_json.loads(text)
    assert back["a"][1] == math.inf and back["a"][2]["b/c"] == -math.inf
    assert math.isnan(back["a"][2]["d~e"]) and math.isnan(back["g"])
    assert back["f"] is None and "not_finite" not in back
    assert doc["a"][1] == math.inf  # the argument is left as it was


def test_a_non_string_key_is_named_as_json_writes_it():
    # json.dumps writes True as "true", None as "null", 2 as "2": the pointer must say the same
    doc = {True: math.inf, None: [math.nan], 2: {1.5: -math.inf}}
    back = strict_json.loads(strict_json.dumps(doc))
    assert back["true"] == math.inf and math.isnan(back["null"][0]) and back["2"]["1.5"] == -math.inf


def test_a_calibration_with_nan_provenance_is_strict_json_and_reads_back(tmp_path):
    panel = PanelModel(rows=64, cols=64, defect_columns=(), n_dead=1, n_under=1, n_noisy=0)
    rng = np.random.default_rng(0)
    cal = Calibration.from_frames(panel.dark_frames(4, rng), panel.flat_frames(4, 2000, rng))
    cal.provenance["flat_current_ua"] = math.nan  # "a number, NaN or null": not recorded
    cal.save(tmp_path / "cal.h5")
    with h5py.File(tmp_path / "cal.h5") as h5:
        assert strict_loads(h5["calibration"].attrs["provenance"])["flat_current_ua"] is None
    assert math.isnan(Calibration.load(tmp_path / "cal.h5").provenance["flat_current_ua"])


@pytest.mark.parametrize("suffix", [".tif", ".h5"])
def test_a_stacks_metadata_with_nan_is_strict_json_and_reads_back(suffix, tmp_path):
    path = write_tiff(tmp_path / "s.tif", np.zeros((2, 4, 4), np.float32), meta={"exposure": [1.0, math.inf]})
    if suffix == ".h5":
        path = tmp_path / "s.h5"
        with StackWriter(path, (4, 4), meta={"exposure": [1.0, math.inf], "gain": {"x": math.nan}}) as w:
            w.append(np.zeros((4, 4), np.float32))
        with h5py.File(path) as h5:
            strict_loads(h5["entry/data"].attrs["gain"])
        meta = read_stack(path).meta
        # a dict attribute carries its "not_finite" map; a bare list cannot (radiokit._json): null
        assert math.isnan(meta["gain"]["x"]) and meta["exposure"] == [1.0, None]
    else:
        strict_loads(tifffile.TiffFile(path).pages[0].description)
        assert read(path).meta["description"]["exposure"] == [1.0, math.inf]


# -- 2, 3, 4: process's inputs and output ------------------------------------------------------
@pytest.mark.parametrize("how", ["twice", "symlink", "hardlink", "dotted"])
def test_process_refuses_one_file_given_twice(how, tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    other = {"twice": exp, "dotted": tmp_path / "." / "exp.h5"}.get(how, tmp_path / "alias.h5")
    if how == "symlink":
        other.symlink_to(exp)
    elif how == "hardlink":
        os.link(exp, other)
    res = run_cli("process", exp, other, "-o", tmp_path / "out", *FAST)
    one_line_error(res, "the same experiment file given", "give each file once")
    assert not (tmp_path / "out").exists()  # refused before any work


def _alias(path, how):
    """Another name of ``path``: itself, a symlink, a hard link, or ``DIR/./NAME``."""
    other = {"twice": path, "dotted": path.parent / "." / path.name}.get(how, path.with_name("alias" + path.suffix))
    if how == "symlink":
        other.symlink_to(path)
    elif how == "hardlink":
        os.link(path, other)
    return other


def _frames(path, level, n=1):
    rng = np.random.default_rng(level)
    tifffile.imwrite(path, (level + rng.normal(0, 2, (n, 32, 32))).astype(np.uint16))
    return path


@pytest.mark.parametrize("how", ["twice", "symlink", "hardlink", "dotted"])
@pytest.mark.parametrize("which", ["--dark", "--flat"])
def test_calibrate_refuses_one_frame_file_given_twice(which, how, tmp_path):
    """``--dark a.tif a.tif`` counted a's frames twice ("2 darks" from one)."""
    darks = [_frames(tmp_path / "d0.tif", 100), _frames(tmp_path / "d1.tif", 101)]
    flats = [_frames(tmp_path / "f0.tif", 3000), _frames(tmp_path / "f1.tif", 3001)]
    given = darks if which == "--dark" else flats
    given[1] = _alias(given[0], how)
    res = run_cli("calibrate", "--dark", *darks, "--flat", *flats, "-o", tmp_path / "cal.h5")
    line = one_line_error(res, f"the same {which} file given", "its frames would count twice", "give each file once")
    assert str(given[1]) in line and not (tmp_path / "cal.h5").exists()


def test_calibrate_takes_darks_and_flats_from_one_file_by_image_key(tmp_path):
    """One file in both lists is no repeat: an experiment-style file holds both, by image_key."""
    exp = synthetic(tmp_path / "exp.h5", shape=(32, 32))
    res = run_cli("calibrate", "--dark", exp, "--flat", exp, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    assert "from 3 darks and 3 flats" in res.stdout


def test_calibrate_prints_a_noiseless_dark_as_zero_and_one_dark_as_unknown(tmp_path):
    """The summary printed ``dark noise nan counts`` both for darks of no noise (0.0, falsy, was
    taken for missing) and for one dark (no temporal noise to measure): 0.00 for the first, and
    for the second words rather than a NaN the user must decode."""
    exp = synthetic(tmp_path / "exp.h5", shape=(32, 32))  # three identical darks: noise exactly 0
    res = run_cli("calibrate", "--experiment", exp, "-o", tmp_path / "cal.h5")
    assert res.returncode == 0, res.stderr
    assert "dark noise 0.00 counts" in res.stdout, res.stdout
    rng = np.random.default_rng(0)
    tifffile.imwrite(tmp_path / "dark.tif", rng.normal(100, 3, (32, 32)).astype(np.uint16))
    tifffile.imwrite(
        tmp_path / "flat.tif", rng.normal(3000, 30, (4, 32, 32)).astype(np.uint16), photometric="minisblack"
    )
    res = run_cli(
        "calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flat.tif", "-o", tmp_path / "c1.h5"
    )
    assert res.returncode == 0, res.stderr
    assert "dark noise not measured (one dark)" in res.stdout and "nan" not in res.stdout, res.stdout


@pytest.mark.parametrize("how", ["twice", "symlink", "hardlink", "dotted"])
def test_register_refuses_one_image_as_fixed_and_moving(how, tmp_path):
    img = _frames(tmp_path / "a.tif", 1000)
    res = run_cli("register", img, _alias(img, how), "-o", tmp_path / "reg.h5")
    one_line_error(res, "fixed and moving are the same image", "frame 0")
    assert not (tmp_path / "reg.h5").exists()


def test_register_refuses_one_frame_named_from_both_ends(tmp_path):
    """Frame -4 of a four-frame stack is frame 0: the same image, registered onto itself unless
    the indices are compared as frames (a review found it registered and flagged, exit 1)."""
    rng = np.random.default_rng(1)
    img = tmp_path / "stack.tif"
    tifffile.imwrite(img, rng.normal(1000, 30, (4, 32, 32)).astype(np.uint16), photometric="minisblack")
    res = run_cli("register", img, img, "--moving-frame", "-4", "-o", tmp_path / "reg.h5")
    one_line_error(res, "fixed and moving are the same image", "frame 0")
    assert not (tmp_path / "reg.h5").exists()


def test_register_takes_two_datasets_of_one_file(tmp_path):
    """`register pair.h5 pair.h5 --fixed-dataset fix --moving-dataset mov` was refused as "the
    same image": the check compared files and frames, not the datasets read. One dataset named
    for both is still one image."""
    rr, cc = np.mgrid[0:64, 0:64]
    pair = tmp_path / "pair.h5"
    with h5py.File(pair, "w") as f:
        f["fix"] = (1000 * np.exp(-((rr - 32) ** 2 + (cc - 30) ** 2) / 200.0)).astype(np.float32)
        f["mov"] = (1000 * np.exp(-((rr - 33) ** 2 + (cc - 31) ** 2) / 200.0)).astype(np.float32)
    res = run_cli("register", pair, pair, "--fixed-dataset", "fix", "--moving-dataset", "mov", "-o", tmp_path / "r.h5")
    assert res.returncode in (0, 1), res.stderr  # registered (1: flagged), not refused
    assert "same image" not in res.stderr and (tmp_path / "r.h5").exists()
    res = run_cli("register", pair, pair, "--fixed-dataset", "fix", "--moving-dataset", "/fix", "-o", tmp_path / "s.h5")
    one_line_error(res, "fixed and moving are the same image", "dataset fix")


def test_register_takes_two_frames_of_one_file(tmp_path):
    """Two frames of one stack are two images: not a repeat."""
    rr, cc = np.mgrid[0:64, 0:64].astype(np.float32)
    blobs = [np.exp(-((rr - 30 - dy) ** 2 + (cc - 34) ** 2) / 60) + 0.5 * np.sin(cc / 5) for dy in (0, 1)]
    img = tmp_path / "stack.tif"
    tifffile.imwrite(img, np.stack(blobs).astype(np.float32))
    res = run_cli("register", img, img, "--moving-frame", "1", "-o", tmp_path / "reg.h5")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "reg.h5").exists()


def test_a_missing_file_given_twice_is_said_to_be_missing(tmp_path):
    res = run_cli("process", tmp_path / "nope.h5", tmp_path / "nope.h5", "-o", tmp_path / "out", *FAST)
    assert res.returncode != 0 and "no such experiment file" in res.stderr
    assert "given twice" not in res.stderr and not (tmp_path / "out").exists()


def test_a_missing_file_is_said_before_the_output_is_judged(tmp_path):
    # `process runs/*.h5 -o results` with no runs/ said "results: exists ..."
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "notes.txt").write_text("mine")
    res = run_cli("process", tmp_path / "runs" / "*.h5", "-o", tmp_path / "results", *FAST)
    one_line_error(res, "*.h5", "no such experiment file")


def test_process_refuses_a_control_that_is_one_of_its_files(tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    (tmp_path / "ctl.h5").symlink_to(exp)
    res = run_cli("process", exp, "--control", tmp_path / "ctl.h5", "-o", tmp_path / "out", *FAST)
    one_line_error(res, "--control", "ctl.h5", "is the experiment file", "exp.h5")
    assert not (tmp_path / "out").exists()


def test_process_prints_the_controls_lines_and_its_flags_count(tmp_path):
    # the control's numbers were in results.json and the report only, and its flagged pairs did
    # not count in the exit code
    exp, ctl = synthetic(tmp_path / "exp.h5"), synthetic(tmp_path / "ctl.h5", scale=1.1)
    res = run_cli("process", exp, "--control", ctl, "-o", tmp_path / "out", *FAST)
    lines = res.stdout.splitlines()
    assert lines[0].startswith(f"{exp}: improvement factor"), res.stdout
    assert any(line.startswith(f"control {ctl}: improvement factor") for line in lines), res.stdout
    saved = load_results(tmp_path / "out" / "results.json")
    every_ok = all(p.ok for p in saved.pairs) and all(p.ok for p in saved.control.pairs)
    assert res.returncode == (0 if every_ok else 1)
    # the exit code's rule on the saved record, with one control pair flagged (a real flagged
    # control cannot be made to order here): the file's pairs all ok, the run still not
    import dataclasses

    from radiokit.cli import _all_ok

    clean = dataclasses.replace(
        saved, pairs=tuple(dataclasses.replace(p, quality={**p.quality, "ok": True}) for p in saved.pairs)
    )
    control = clean.control
    flagged = dataclasses.replace(control.pairs[0], quality={**control.pairs[0].quality, "ok": False})
    one_off = dataclasses.replace(clean, control=dataclasses.replace(control, pairs=(flagged, *control.pairs[1:])))
    assert _all_ok(
        dataclasses.replace(
            clean,
            control=dataclasses.replace(
                control, pairs=tuple(dataclasses.replace(p, quality={**p.quality, "ok": True}) for p in control.pairs)
            ),
        )
    )
    assert not _all_ok(one_off)


@pytest.mark.parametrize("name", ["x.h5", "x.HDF5", "x.nxs", "x.tif", "x.tiff", "x.json"])
def test_process_refuses_an_output_folder_named_like_a_file(name, tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    res = run_cli("process", exp, "-o", tmp_path / name, *FAST)
    one_line_error(res, f"-o {tmp_path / name}", "-o is a results folder")
    assert not (tmp_path / name).exists()


def test_several_files_are_not_written_into_one_runs_results_folder(tmp_path):
    # they were: a.h5's and b.h5's folders beside the first run's report, a mixed folder that
    # `--overwrite` then refused to replace (files radiokit did not write there)
    a, b = synthetic(tmp_path / "a.h5"), synthetic(tmp_path / "b.h5", scale=1.1)
    assert run_cli("process", a, "-o", tmp_path / "out", *FAST).returncode == 0
    before = sorted(p.name for p in (tmp_path / "out").iterdir())
    for extra in ([], ["--overwrite"]):
        res = run_cli("process", a, b, "-o", tmp_path / "out", *FAST, *extra)
        one_line_error(res, str(tmp_path / "out"), "holds the results of one run", "choose another folder")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == before


def test_a_crop_smaller_than_the_rois_is_widened_to_hold_the_inclusion_as_the_background(tmp_path):
    # --crop-mm 0.01 (0.2 px) grown to the background only cut the inclusion at the crop's edge:
    # "log domain: inclusion ROI(row0=0, ...) lies (partly) outside the 11x40 image" after the work
    exp = synthetic(tmp_path / "exp.h5")
    fast = [a for a in FAST if a not in ("--crop-mm", "0")]
    res = run_cli("process", exp, "-o", tmp_path / "res", *fast, "--crop-mm", "0.01")
    assert res.returncode == 0, res.stderr
    rois = json.loads((tmp_path / "res" / "results.json").read_text())["rois"]
    r0, r1, c0, c1 = rois["crop"]
    # both ROIs as given (full-frame pixels), inside the crop and at their place in it
    assert rois["inclusion"] == [75 - r0, 86 - r0, 75 - c0, 86 - c0]
    assert rois["background"] == [75 - r0, 86 - r0, 40 - c0, 51 - c0]
    assert r0 <= 75 and r1 >= 86 and c0 <= 40 and c1 >= 86


def test_process_reports_a_failed_file_of_many_as_one_files_run_does(tmp_path):
    # the batch's line was "small.h5: error: ValueError: ...", the single run's without the class
    good, small = synthetic(tmp_path / "good.h5"), synthetic(tmp_path / "small.h5", shape=(80, 80))
    one = run_cli("process", small, "-o", tmp_path / "one", *FAST)
    single = one_line_error(one, "small.h5").removeprefix("radiokit process: ")
    many = run_cli("process", good, small, "-o", tmp_path / "many", "--workers", "1", *FAST)
    assert many.returncode != 0
    lines = [line for line in many.stderr.splitlines() if "small.h5" in line]
    assert len(lines) == 1 and "Error:" not in lines[0], many.stderr
    # the same words, the batch's line naming its file first
    assert lines[0].removeprefix(f"{small}: error: ").removeprefix(f"{small}: ") == single.removeprefix(f"{small}: ")


def test_a_batch_error_names_the_option_not_the_api_keyword():
    """An output made by another program during the run (a race a test cannot stage in a Dask
    worker): the line of process_many's result as the command line prints it."""
    from radiokit.cli import _batch_error
    from radiokit.io._atomic import OutputAppearedError
    from radiokit.pipeline import _error_result

    result = _error_result("a.h5", OutputAppearedError("R/a"))
    line = _batch_error(result)
    assert line.startswith("R/a: appeared during the run") and line.endswith("pass --overwrite to replace it"), line
    assert "overwrite=True" not in line and "OutputAppearedError" not in line


# -- 5: a calibration that marks most of the panel ---------------------------------------------
def test_calibrate_refuses_darks_and_flats_that_flag_most_of_the_panel(tmp_path):
    rng = np.random.default_rng(1)
    shape = (128, 160)
    dark = rng.normal(100, 2, (5, *shape)).clip(0).astype(np.uint16)
    # the beam blocked for most of the flats: a scatter of lit pixels, half the panel barely lit
    resp = np.where(rng.random(shape) < 0.55, 2000.0, 60.0) * rng.uniform(0.5, 1.5, shape)
    flat = (100 + resp + rng.normal(0, 5, (5, *shape))).clip(0, 4095).astype(np.uint16)
    tifffile.imwrite(tmp_path / "dark.tif", dark)
    tifffile.imwrite(tmp_path / "flat.tif", flat)
    res = run_cli(
        "calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flat.tif", "-o", tmp_path / "c.h5"
    )
    line = one_line_error(res, "dark.tif", "flat.tif", "defective", f"{100 * MAX_DEFECTIVE_SHARE:g} %")
    assert "(100.0 %)" in line  # line_fraction makes every row and column a line
    assert not (tmp_path / "c.h5").exists()


def test_a_4x4_binned_panel_with_the_most_defect_lines_it_may_have_still_calibrates(tmp_path):
    """The limit's worst honest case: 20 defect lines (the C7942's most) of a 560 x 560 frame,
    3.6 % of it, plus isolated defects."""
    cols = tuple(range(14, 560, 28))
    panel = PanelModel(rows=560, cols=560, binning=4, defect_columns=cols, n_dead=20, n_under=20, n_noisy=20)
    rng = np.random.default_rng(2)
    tifffile.imwrite(tmp_path / "dark.tif", np.asarray(panel.dark_frames(6, rng)))
    tifffile.imwrite(tmp_path / "flat.tif", np.asarray(panel.flat_frames(6, 150, rng)))
    res = run_cli(
        "calibrate", "--dark", tmp_path / "dark.tif", "--flat", tmp_path / "flat.tif", "-o", tmp_path / "c.h5"
    )
    assert res.returncode == 0, res.stderr
    cal = Calibration.load(tmp_path / "c.h5")
    assert len(cols) == 20 and set(cols) <= set(cal.defect_columns.tolist())
    assert 0.035 < np.count_nonzero(cal.mask) / cal.mask.size < MAX_DEFECTIVE_SHARE


# -- 6: image keys outside NXtomo's four -------------------------------------------------------
@pytest.mark.parametrize("value", [7, -1, 4])
@pytest.mark.parametrize("cmd", ["info", "calibrate", "process"])
def test_an_image_key_outside_0_to_3_is_refused_naming_the_frame(cmd, value, tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        h5[IMAGE_KEY][7] = value  # a projection of step 2: was silently dropped
    args = {
        "info": ["info", exp],
        "calibrate": ["calibrate", "--experiment", exp, "-o", tmp_path / "c.h5"],
        "process": ["process", exp, "-o", tmp_path / "out", *FAST],
    }[cmd]
    one_line_error(
        run_cli(*args), "exp.h5", "frame 7", f"image_key {value}", "0 projection, 1 flat, 2 dark or 3 invalid"
    )
    assert not (tmp_path / "c.h5").exists() and not (tmp_path / "out").exists()
    with pytest.raises(FormatError, match=f"frame 7 has image_key {value}"):  # acquire --resume's reader
        read_progress(exp)


@pytest.mark.parametrize("name, value", [("step", 1.5), ("step", "nan"), ("step", 1e12), ("image_key", 0.5)])
@pytest.mark.parametrize("cmd", ["info", "calibrate", "process"])
def test_a_step_or_image_key_that_is_no_whole_number_is_refused_naming_the_frame(cmd, name, value, tmp_path):
    """Another writer's float steps and keys: 2.0 is step 2, but 1.5 matched no step, and process
    ended in a TypeError traceback (no frame of "step 1" to average); a key of 0.5 was neither
    projection, flat nor dark. Refused naming the dataset, the frame and the value."""
    exp = synthetic(tmp_path / "exp.h5")
    path = {"step": "entry/sample/compression/step", "image_key": IMAGE_KEY}[name]
    with h5py.File(exp, "a") as h5:
        values = h5[path][()].astype(np.float64)
        values[7] = float(value)  # a projection of step 2
        del h5[path]
        h5[path] = values
    args = {
        "info": ["info", exp],
        "calibrate": ["calibrate", "--experiment", exp, "-o", tmp_path / "c.h5"],
        "process": ["process", exp, "-o", tmp_path / "out", *FAST],
    }[cmd]
    one_line_error(run_cli(*args), "exp.h5", f"/{path}[7]", "frame 7", "whole number")
    assert not (tmp_path / "c.h5").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("sign, scale", [(-1, 1), (1, 100)])
@pytest.mark.parametrize("cmd", ["info", "process"])
def test_a_compression_ratio_outside_0_to_1_is_refused_naming_the_frame(cmd, sign, scale, tmp_path):
    """Ratios recorded negative (a finite element code's sign convention) or in per cent, by
    another writer: process ordered the steps by them and registered onto the least compressed
    step ("main pair 2->1"), exit code 0."""
    exp = synthetic(tmp_path / "exp.h5")
    path = "entry/sample/compression/ratio"
    with h5py.File(exp, "a") as h5:
        h5[path][...] = sign * scale * h5[path][()]  # darks' and flats' NaN stay NaN
    args = {"info": ["info", exp], "process": ["process", exp, "-o", tmp_path / "out", *FAST]}[cmd]
    one_line_error(run_cli(*args), "exp.h5", f"/{path}[6]", "frame 6", "compression ratio in [0, 1)")
    assert not (tmp_path / "out").exists()


def test_steps_and_image_keys_stored_as_whole_floats_are_read(tmp_path):
    """Float datasets holding whole numbers (another writer's float64 steps) read as those."""
    exp = synthetic(tmp_path / "exp.h5")
    with h5py.File(exp, "a") as h5:
        for path in ("entry/sample/compression/step", IMAGE_KEY):
            values = h5[path][()]
            del h5[path]
            h5[path] = values.astype(np.float64)
        keys, steps = h5[IMAGE_KEY][()], h5["entry/sample/compression/step"][()]
    f = read(exp)
    np.testing.assert_array_equal(f.meta["image_key"], keys)
    np.testing.assert_array_equal(f.meta["step"], steps)
    assert f.meta["step"].dtype.kind == "i" and f.meta["image_key"].dtype.kind == "i"
    res = run_cli("process", exp, "-o", tmp_path / "out", *FAST)
    assert res.returncode == 0, res.stderr


def test_an_image_key_beside_another_layouts_frames_is_checked_too(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as h5:
        h5["scan/data"] = np.zeros((4, 8, 8), np.uint16)
        h5["scan/image_key"] = np.array([2, 1, 0, 9], np.int8)
    one_line_error(run_cli("info", path, "--dataset", "scan/data"), "other.h5", "/scan/image_key[3]", "image_key 9")


def test_process_names_a_control_that_is_not_an_experiment_file(tmp_path):
    """A TIFF given as --control was "not an control experiment", after the experiment file's name
    ("exp.h5: ctl.tif: ...", as if the experiment were at fault): one line, naming the control."""
    exp = synthetic(tmp_path / "exp.h5")
    write_tiff(tmp_path / "ctl.tif", read(exp).data[:2])
    res = run_cli("process", exp, "--control", tmp_path / "ctl.tif", "-o", tmp_path / "out", *FAST)
    one_line_error(res, "ctl.tif", "holds tiff data, not a control experiment")
    assert "exp.h5" not in res.stderr, res.stderr


def test_process_names_a_file_whose_name_is_a_word_of_the_message(tmp_path):
    """Review s51rv2: ``process`` took a line as naming its file already where the name was
    anywhere in it, so an experiment file named ``the`` (a word of "no inclusion found: ... the
    body ...") was refused in a line naming no file. A line names a file where it starts with it."""
    synthetic(tmp_path / "the")
    res = run_cli("process", "the", "-o", "res", "-q", "--no-report", "--cross-check", "none", cwd=tmp_path)
    line = one_line_error(res, "no inclusion found")
    assert line.startswith("radiokit process: the: no inclusion found"), line


def test_register_refuses_a_dark_or_flat_frame_of_an_experiment_file(tmp_path):
    """`radiokit register exp.h5 ctl.h5` registered frame 0 of each, a dark (image_key 2), and
    reported "NCC 1.0000 -> 1.0000" as if two radiographs had been registered. A frame an
    experiment file marks other than a projection is refused, naming its kind and a projection."""
    exp = synthetic(tmp_path / "exp.h5")
    keys = read(exp).meta["image_key"]
    first = int(np.flatnonzero(keys == 0)[0])
    res = run_cli("register", exp, exp, "--moving-frame", "1", "-o", tmp_path / "reg.h5")
    one_line_error(res, "exp.h5", "frame 0 is a dark", f"frame {first}", "--fixed-frame")
    flat = int(np.flatnonzero(keys == 1)[0])
    res = run_cli("register", exp, exp, "--fixed-frame", first, "--moving-frame", flat, "-o", tmp_path / "reg.h5")
    one_line_error(res, "exp.h5", f"frame {flat} is a flat", "--moving-frame")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.h5"]
    # two projections of the file register (the last step onto the first, as the tutorial's pair)
    last = int(np.flatnonzero(keys == 0)[-1])
    res = run_cli("register", exp, exp, "--fixed-frame", last, "--moving-frame", first, "-o", tmp_path / "reg.h5")
    assert res.returncode in (0, 1) and (tmp_path / "reg.h5").exists(), res.stderr


# -- recorded tube currents out of any tube's range ----------------------------------------------
def _with_currents(path, flat_ua, projection_ua, shape=(160, 160)):
    """synthetic()'s experiment with the tube currents the flats and projections recorded."""
    from radiokit.io import ExperimentWriter, ImageKey

    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    sq = (abs(rr - 80) < 10) & (abs(cc - 80) < 10)
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK, current_ua=0.0)  # the tube off
            w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT, current_ua=flat_ua)
        for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
            counts = 100 + 3000 * np.exp(-(0.08 * tb + 0.03 * ti * sq))
            w.append(
                counts.astype(np.uint16),
                image_key=ImageKey.PROJECTION,
                step=step,
                ratio=0.1 * step,
                current_ua=projection_ua,
            )
    return path


ABSURD_UA = [1e308, math.inf, -5.0, 0.0, 1e-300]


@pytest.mark.parametrize("which", ["flat", "projection"])
@pytest.mark.parametrize("absurd", ABSURD_UA)
@pytest.mark.parametrize("cmd", ["process", "correct", "calibrate"])
def test_a_recorded_tube_current_no_tube_gives_is_refused_naming_the_field(cmd, absurd, which, tmp_path):
    """A flat or projection current of 1e308, inf, 0 or -5 uA was taken as not recorded (factor 1,
    in silence) or scaled every transmission by it: process ended in "the reference contrast is
    zero", misleading. One line names the file, the field and the frame's kind."""
    flat, projection = (absurd, 200.0) if which == "flat" else (200.0, absurd)
    exp = _with_currents(tmp_path / "exp.h5", flat, projection)
    args = {
        "process": ["process", exp, "-o", tmp_path / "r", *FAST],
        "correct": ["correct", exp, "-q", "-o", tmp_path / "c.h5"],
        "calibrate": ["calibrate", "--experiment", exp, "-o", tmp_path / "cal.h5"],
    }[cmd]
    if cmd == "calibrate" and which == "projection":  # calibrate reads the darks and flats alone
        assert run_cli(*args).returncode == 0
        return
    one_line_error(run_cli(*args), "exp.h5", "entry/control/current", which, "uA")
    assert not (tmp_path / "r").exists() and not (tmp_path / "c.h5").exists()


def test_recorded_tube_currents_in_range_and_not_recorded_still_process(tmp_path):
    """NaN is "not recorded" and 0 uA on a dark is the tube off: neither is refused."""
    for flat, projection in ((200.0, 100.0), (math.nan, 100.0), (200.0, math.nan)):
        exp = _with_currents(tmp_path / "exp.h5", flat, projection)
        res = run_cli("process", exp, "-o", tmp_path / "r", *FAST, "--overwrite")
        assert res.returncode == 0, res.stderr
        exp.unlink()


@pytest.mark.parametrize("absurd", [1e308, -5.0, 0.0])
def test_a_calibration_recording_a_flat_current_no_tube_gives_is_refused(absurd, tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    cal = Calibration.from_experiment(exp)
    cal.provenance["flat_current_ua"] = absurd
    cal.save(tmp_path / "cal.h5")
    res = run_cli("correct", exp, "-q", "--cal", tmp_path / "cal.h5", "-o", tmp_path / "c.h5")
    one_line_error(res, "cal.h5", "flat_current_ua", "uA")


def test_correct_without_cal_on_frames_that_are_no_experiment_asks_for_cal(tmp_path):
    """`radiokit correct` calibrates from the file itself only when it is an experiment file. A
    newcomer's TIFF or raw frames without --cal got "holds no darks (image_key 2): cannot
    calibrate", and a raw file given with --shape was told to pass --shape (the geometry was not
    passed on): each is now told that --cal is what is missing."""
    rng = np.random.default_rng(0)
    tif = tmp_path / "proj.tif"
    tifffile.imwrite(tif, rng.normal(1500, 20, (2, 32, 32)).astype(np.uint16), photometric="minisblack")
    raw = tmp_path / "proj.raw"
    rng.normal(1500, 20, (2, 32, 32)).astype("<u2").tofile(raw)
    for args in ([tif], [raw, "--shape", "32", "32"]):
        res = run_cli("correct", *args, "-o", tmp_path / "out.h5")
        line = one_line_error(res, args[0].name, "--cal")
        assert "--shape" not in line, line
        assert not (tmp_path / "out.h5").exists()


def test_correct_without_cal_on_an_experiment_lacking_its_flats_names_the_flats(tmp_path):
    """An experiment file with darks and projections but no flats (the shutter stayed shut) is
    an experiment file: it is told what it lacks, not "not an experiment file" (review s34-r3)."""
    from radiokit.io import ExperimentWriter, ImageKey

    rng = np.random.default_rng(0)
    with ExperimentWriter(tmp_path / "exp.h5", shape=(32, 32), pixel_size_mm=0.05) as w:
        for key in (ImageKey.DARK, ImageKey.DARK, ImageKey.PROJECTION):
            w.append(rng.normal(100, 2, (32, 32)).astype(np.uint16), image_key=key)
    line = one_line_error(run_cli("correct", tmp_path / "exp.h5", "-o", tmp_path / "out.h5"), "exp.h5", "no flats")
    assert "not an experiment" not in line, line
    assert not (tmp_path / "out.h5").exists()


def test_correct_of_a_file_without_projections_says_so(tmp_path):
    """An experiment file holding only darks and flats (an acquisition stopped before its first
    step) ended on "no frames to correct in exp.h5 (image_keys=(0,))", a tuple a user cannot act
    on: the line now says that the file holds no projection, and what it does hold."""
    from radiokit.io import ExperimentWriter, ImageKey

    rng = np.random.default_rng(0)
    with ExperimentWriter(tmp_path / "exp.h5", shape=(32, 32), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(rng.normal(100, 2, (32, 32)).astype(np.uint16), image_key=ImageKey.DARK)
            w.append(rng.normal(3000, 30, (32, 32)).astype(np.uint16), image_key=ImageKey.FLAT)
    res = run_cli("correct", tmp_path / "exp.h5", "-o", tmp_path / "out.h5")
    line = one_line_error(res, "exp.h5", "no projection", "darks")
    assert "image_keys=" not in line, line
    assert not (tmp_path / "out.h5").exists()


def test_process_crop_and_mm_slips_are_told_in_the_command_lines_terms(tmp_path):
    """`--crop-mm -5` was answered "(None: the whole frame)", Python's word for what the command
    line spells 0; and `--mm` without a rectangle was accepted and did nothing (a newcomer reading
    it as "report in mm"): both are one line in the options' own terms, before any work."""
    exp = synthetic(tmp_path / "exp.h5")
    for bad in ("-5", "nan", "inf"):
        line = one_line_error(run_cli("process", exp, "-o", tmp_path / "res", "--crop-mm", bad), "--crop-mm")
        assert "None" not in line and "0: the whole frame" in line, line
    line = one_line_error(run_cli("process", exp, "-o", tmp_path / "res", "--mm"), "--mm", "--inclusion")
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("crop", ["1e308", "1000"])
def test_a_crop_larger_than_the_frame_keeps_the_whole_frame(crop, tmp_path):
    """`--crop-mm 1e308` was an OverflowError traceback with exit code 1, the code of a flagged
    run (1e308 / 0.05 mm is inf pixels, which int() refused). A crop larger than the frame is the
    whole frame, as the default 30 mm is on a frame smaller than that."""
    exp = synthetic(tmp_path / "exp.h5")
    args = [a if a != "0" else crop for a in FAST]  # FAST ends "--crop-mm 0"
    assert args[-2:] == ["--crop-mm", crop]
    res = run_cli("process", exp, "-o", tmp_path / "res", *args)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert json.loads((tmp_path / "res" / "results.json").read_text())["rois"]["crop"] == [0, 160, 0, 160]


def test_sim_run_zero_frames_is_told_why_frames_not_why_darks(tmp_path):
    """`sim run --frames 0` was refused with the darks' and flats' reason ("the experiment is
    corrected with its own darks and flats"), which says nothing about projections."""
    line = one_line_error(
        run_cli("sim", "run", "--preset", "seed-breast", "--frames", "0", "-o", tmp_path / "s.h5"), "--frames 0"
    )
    assert "darks" not in line and "projection" in line, line
    line = one_line_error(
        run_cli("sim", "run", "--preset", "seed-breast", "--darks", "0", "-o", tmp_path / "s.h5"), "--darks 0"
    )
    assert "darks and flats" in line, line


def test_info_all_with_sample_is_refused(tmp_path):
    """`info --all --sample 3` read every frame and dropped --sample in silence: the two say
    opposite things, so the command asks for one of them."""
    tif = tmp_path / "s.tif"
    tifffile.imwrite(tif, np.zeros((3, 8, 8), np.uint16), photometric="minisblack")
    for n in ("3", "8"):  # 8, the default, given explicitly too
        one_line_error(run_cli("info", tif, "--all", "--sample", n), "--all", "--sample")
    assert run_cli("info", tif, "--all").returncode == 0
    assert run_cli("info", tif, "--sample", "2").returncode == 0


def test_a_text_file_given_as_frames_is_not_pointed_at_results_h5(tmp_path):
    """A ``.txt`` or ``.csv`` given as frames was told "radiokit process's images are in
    results.h5", advice for a ``results.json`` or ``report.html`` given by mistake, which those
    two still get."""
    for name, text in (("notes.txt", "hello\n"), ("table.csv", "a,b\n1,2\n")):
        (tmp_path / name).write_text(text)
        line = one_line_error(run_cli("info", tmp_path / name), name, "a text file, not frames")
        assert "results.h5" not in line, line
    (tmp_path / "results.json").write_text("{}")
    one_line_error(run_cli("info", tmp_path / "results.json"), "results.json", "results.h5")


def test_an_inclusion_given_alone_outside_the_frame_is_told_so(tmp_path):
    """`--inclusion 0 500 0 5` on a 160 x 160 frame, without --background, was told that "no
    background of its shape fits beside it" and to give the background: the rectangle itself
    lies outside the frame, as the same line said when a background was given."""
    exp = synthetic(tmp_path / "exp.h5")
    line = one_line_error(
        run_cli("process", exp, "-o", tmp_path / "res", "--inclusion", "0", "500", "0", "5", *FAST[:4]),
        "inclusion",
        "outside the (160, 160) frame",
    )
    assert "background" not in line, line


def test_no_background_beside_a_large_inclusion_names_what_process_offers(tmp_path):
    """Review s41proc: a sphere of 45 px radius in a body of 107 px (0.1 mm pixels) leaves no room
    for a background beside it; the line said "pass a smaller gap or background_size, body_mask,
    or the ROIs", find_rois's keywords, none of which process has."""
    n, rng = 256, np.random.default_rng(6)
    rr, cc = np.mgrid[:n, :n].astype(float)
    d = np.hypot(rr - 128, cc - 128)
    L = 0.5 / (1 + np.exp((d - 107.5) / 3.0)) + 0.3 * np.sqrt(np.clip(45.0**2 - d**2, 0, None)) / 45.0
    with ExperimentWriter(tmp_path / "exp.h5", shape=(n, n), pixel_size_mm=0.1) as w:
        w.append(np.full((n, n), 100, np.uint16), image_key=ImageKey.DARK)
        w.append(np.full((n, n), 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, a in enumerate((1.0, 0.95, 0.9), start=1):
            counts = rng.poisson(100 + 3000 * np.exp(-a * L))
            w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    res = run_cli("process", tmp_path / "exp.h5", "-o", tmp_path / "res", "-q", "--no-report", "--cross-check", "none")
    line = one_line_error(
        res, "exp.h5", "background ROI fits", "leaves the body", "--inclusion R0 R1 C0 C1 --background R0 R1 C0 C1"
    )
    for word in ("gap", "background_size", "body_mask"):
        assert word not in line, line
    assert not (tmp_path / "res").exists()


def test_k_slips_are_echoed_as_typed(tmp_path):
    """`--k 1 1` was answered "--k (1.0, 1.0): ...", a Python tuple, where `--k 0` is answered
    "--k 0: ..." as typed."""
    exp = synthetic(tmp_path / "exp.h5")
    for ks, why in ((["1", "1"], "each enhancement factor once"), (["nan"], "finite")):
        res = run_cli("process", exp, "--k", *ks, "-o", tmp_path / "res")
        line = one_line_error(res, f"--k {' '.join(ks)}: ", why)
        assert "(" not in line.split(":")[1], line


def test_an_experiment_file_given_as_cal_says_how_to_calibrate_from_it(tmp_path):
    """`correct frames.tif --cal exp.h5` was told "no /calibration group: not a radiokit
    calibration file"; an experiment file holds what a calibration is made from, and the line
    now says how."""
    exp = synthetic(tmp_path / "exp.h5")
    tif = tmp_path / "proj.tif"
    tifffile.imwrite(tif, np.full((1, 160, 160), 1500, np.uint16), photometric="minisblack")
    res = run_cli("correct", tif, "--cal", exp, "-o", tmp_path / "out.h5")
    one_line_error(res, "exp.h5", "an experiment file", "radiokit calibrate --experiment")


def test_register_retry_with_a_peer_method_is_refused(tmp_path):
    """`--retry` strengthens a B-spline method's regularisation; with `--method dis` it was
    accepted and did nothing, where `--preset` with a peer is refused."""
    rng = np.random.default_rng(0)
    for name in ("f.tif", "m.tif"):
        tifffile.imwrite(tmp_path / name, rng.random((32, 32)).astype(np.float32))
    res = run_cli(
        "register", tmp_path / "f.tif", tmp_path / "m.tif", "-o", tmp_path / "r.h5", "--method", "dis", "--retry"
    )
    one_line_error(res, "--retry", "--method dis")
    assert not (tmp_path / "r.h5").exists()


def test_a_calibration_file_given_as_an_experiment_is_refused(tmp_path):
    """`calibrate --experiment cal.h5` calibrated again from a calibration's averaged dark and flat
    as one dark and one flat (two warnings, exit 0), and `correct cal.h5` calibrated from it
    before finding nothing to correct: a calibration is used as it is, with --cal."""
    rng = np.random.default_rng(0)
    darks = rng.normal(100, 2, (3, 32, 32)).astype(np.uint16)
    flats = rng.normal(3000, 30, (3, 32, 32)).astype(np.uint16)
    cal = Calibration.from_frames(darks, flats).save(tmp_path / "cal.h5")
    for args in (("calibrate", "--experiment", cal), ("correct", cal)):
        one_line_error(run_cli(*args, "-o", tmp_path / "out.h5"), "cal.h5", "calibration", "--cal")
        assert not (tmp_path / "out.h5").exists()


def test_correct_refuses_a_frame_file_given_twice(tmp_path):
    """`correct a.tif a.tif` wrote every frame twice into one stack, exit 0, where `process` and
    `calibrate --dark` refuse a file given twice."""
    tif = tmp_path / "a.tif"
    tifffile.imwrite(tif, np.full((2, 32, 32), 1500, np.uint16), photometric="minisblack")
    rng = np.random.default_rng(0)
    cal = Calibration.from_frames(
        rng.normal(100, 2, (3, 32, 32)).astype(np.uint16), rng.normal(3000, 30, (3, 32, 32)).astype(np.uint16)
    ).save(tmp_path / "cal.h5")
    res = run_cli("correct", tif, tif, "--cal", cal, "-o", tmp_path / "out.h5")
    one_line_error(res, "a.tif", "twice")
    assert not (tmp_path / "out.h5").exists()


def test_process_names_radiokits_own_outputs_given_as_the_experiment(tmp_path):
    """`process results/results.h5` (or a registration, or a corrected stack) was told "holds
    hdf5 data, not an experiment": each is radiokit's own output, and the line says which."""
    exp = synthetic(tmp_path / "exp.h5")
    assert run_cli("process", exp, "-o", tmp_path / "res", *FAST).returncode == 0
    assert run_cli("correct", exp, "-o", tmp_path / "corr.h5").returncode == 0
    for path, what in (
        (tmp_path / "res" / "results.h5", "radiokit process's results"),
        (tmp_path / "corr.h5", "a stack of frames"),
    ):
        one_line_error(run_cli("process", path, "-o", tmp_path / "again"), path.name, what, "not an experiment")


@pytest.mark.parametrize(
    "given, echo, words",
    [
        # a fractional pixel: the way to give millimetres is --mm, a command-line option (roi_units is Python's)
        (["--inclusion", "10.5", "20", "10", "20"], "--inclusion 10.5 20 10 20: ", ["whole numbers", "--mm"]),
        (["--inclusion", "20", "10", "10", "20"], "--inclusion 20 10 10 20 (px): ", ["empty"]),
        (["--inclusion", "10", "20", "10", "20", "--background", "0.5", "5", "5", "9"], "--background 0.5 5 5 9: ", []),
        (["--inclusion", "1", "2", "3", "4", "--background", "1", "2", "3", "4", "--mm"], "--background 1 2 3 4: ", []),
        (["--inclusion", "1", "1.02", "3", "4", "--mm"], "--inclusion 1 1.02 3 4 (mm): ", ["empty"]),
    ],
)
def test_process_echoes_a_refused_roi_as_typed_with_the_hint_for_its_units(given, echo, words, tmp_path):
    """A refused --inclusion/--background was echoed as a Python list of floats
    ("--inclusion [10.5, 20.0, 10.0, 20.0]") and its fractional pixel pointed to "roi_units='mm'",
    which a command-line user cannot give; it is echoed as typed and points to --mm."""
    exp = synthetic(tmp_path / "exp.h5")
    line = one_line_error(run_cli("process", exp, "-o", tmp_path / "res", "-q", "--no-report", *given), echo, *words)
    assert ".0, " not in line and "roi_units" not in line and "ROI(" not in line, line


def test_an_roi_in_mm_outside_the_frame_is_named_in_mm_with_the_frames_size(tmp_path):
    """`--mm --inclusion 0 500 0 5` was told "inclusion ROI ROI(row0=0, row1=10000, ...) lies outside
    the (160, 160) frame": pixels the user never typed, and no word of the frame's size in mm."""
    exp = synthetic(tmp_path / "exp.h5")
    res = run_cli("process", exp, "-o", tmp_path / "res", "-q", "--no-report", "--mm", "--inclusion", 0, 500, 0, 5)
    line = one_line_error(res, "--inclusion 0 500 0 5 (mm)", "outside the", "8 x 8 mm")
    assert "ROI(" not in line, line


def test_an_roi_given_alone_with_no_background_beside_it_is_named_as_typed(tmp_path):
    """`--mm --inclusion 1 7 1 7` (most of the 8 x 8 mm frame: no room beside it) was told
    "--inclusion ROI(row0=20, row1=140, ...) given alone": the pixel record, under the option's name."""
    exp = synthetic(tmp_path / "exp.h5")
    res = run_cli("process", exp, "-o", tmp_path / "res", "-q", "--no-report", "--mm", "--inclusion", 1, 7, 1, 7)
    line = one_line_error(res, "--inclusion 1 7 1 7 (mm) given alone", "--background")
    assert "ROI(" not in line, line


def _with_pixel_size(src, dst, metres):
    """A copy of experiment ``src`` recording another pixel pitch (a binned panel's, say)."""
    import shutil

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        for axis in ("x_pixel_size", "y_pixel_size"):
            f[f"entry/instrument/detector/{axis}"][()] = metres
    return dst


def test_process_refuses_a_control_of_another_pixel_size(tmp_path):
    """A control at 0.1 mm per pixel beside an experiment at 0.05 mm: only the frame shapes were
    compared, and the experiment's pixel ROIs were measured on the control's twice-as-large scene."""
    exp = synthetic(tmp_path / "exp.h5")
    ctl = _with_pixel_size(exp, tmp_path / "ctl.h5", 1e-4)
    res = run_cli("process", exp, "--control", ctl, "-o", tmp_path / "out", *FAST)
    one_line_error(res, "ctl.h5", "0.1 mm", "0.05 mm")
    assert not (tmp_path / "out").exists()
    # the same pitch written in float32 (its rounding) is the same pitch
    same = _with_pixel_size(exp, tmp_path / "ctl32.h5", np.float32(5e-5))
    assert run_cli("process", exp, "--control", same, "-o", tmp_path / "out32", *FAST).returncode == 0


def test_process_refuses_pixels_that_are_not_square(tmp_path):
    """x 0.05 mm, y 0.2 mm: `--mm --inclusion 3.5 4.5 3.5 4.5` was converted with x's pitch on both
    axes (rows 70-90, not 17.5-22.5), as was --crop-mm; results.json recorded 0.05 alone, and the
    report draws and scales square pixels, the registration smooths in pixels."""
    from radiokit.pipeline import Config, process

    exp = synthetic(tmp_path / "exp.h5")
    aniso = tmp_path / "aniso.h5"
    aniso.write_bytes(exp.read_bytes())
    with h5py.File(aniso, "r+") as f:
        f["entry/instrument/detector/y_pixel_size"][()] = 2e-4
    quick = ["-q", "--no-report", "--cross-check", "none"]
    for roi in (ROI, ["--mm", "--inclusion", 3.5, 4.5, 3.5, 4.5], ["--crop-mm", 2]):
        res = run_cli("process", aniso, *roi, "-o", tmp_path / "out", *quick)
        one_line_error(res, "aniso.h5", "0.05 x 0.2 mm", "square")
        assert not (tmp_path / "out").exists()
    with pytest.raises(FormatError, match=r"aniso.h5: pixels of 0.05 x 0.2 mm"):
        process(aniso, Config(report=False, crop_mm=None), out_dir=tmp_path / "api")
    # as a control too (beside an experiment that records no pitch, the pitches are not compared)
    bare = tmp_path / "bare.h5"
    bare.write_bytes(exp.read_bytes())
    with h5py.File(bare, "r+") as f:
        for axis in ("x_pixel_size", "y_pixel_size"):
            del f[f"entry/instrument/detector/{axis}"]
    res = run_cli("process", bare, "--control", aniso, "-o", tmp_path / "out", *FAST)
    one_line_error(res, "aniso.h5", "0.05 x 0.2 mm", "square")
    assert run_cli("info", aniso).returncode == 0  # read and shown: only process measures in mm


def test_register_refuses_images_of_another_pixel_size(tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    other = _with_pixel_size(exp, tmp_path / "binned.h5", 1e-4)
    res = run_cli("register", exp, other, "--fixed-frame", "6", "--moving-frame", "7", "-o", tmp_path / "reg.h5")
    one_line_error(res, "binned.h5", "0.1 mm", "0.05 mm")
    assert not (tmp_path / "reg.h5").exists()


@pytest.mark.parametrize(
    "background",
    [
        ["75", "86", "75", "86"],  # the inclusion's own rectangle (refused before)
        ["77", "84", "77", "84"],  # inside it
        ["80", "90", "80", "90"],  # across its corner
        ["60", "100", "60", "100"],  # around it
    ],
)
def test_a_background_overlapping_the_inclusion_is_refused(background, tmp_path):
    """`--inclusion 118 138 118 138 --background 120 130 120 130` measured IF 0.60 / 0.20, exit
    code 0: a contrast of the inclusion against itself. Only the same rectangle was refused."""
    exp = synthetic(tmp_path / "exp.h5")
    args = ["--inclusion", "75", "86", "75", "86", "--background", *background, "--crop-mm", "0"]
    res = run_cli("process", exp, "-o", tmp_path / "out", "-q", "--no-report", *args)
    one_line_error(res, f"--background {' '.join(background)}", "overlaps", "--inclusion 75 86 75 86")
    assert not (tmp_path / "out").exists()


def test_a_background_given_alone_on_the_detected_inclusion_is_refused(tmp_path, monkeypatch):
    import radiokit.measure
    from radiokit.measure import ROI

    exp = synthetic(tmp_path / "exp.h5")  # noiseless: the detection is stood in for (the square, 70-90)
    monkeypatch.setattr(radiokit.measure, "find_rois", lambda *a, **k: (ROI(70, 90, 70, 90), ROI(70, 90, 30, 50)))
    res = run_cli("process", exp, "-o", tmp_path / "out", "-q", "--no-report", "--background", "75", "86", "75", "86")
    one_line_error(res, "--background 75 86 75 86", "overlaps the inclusion detected at rows 70-90, cols 70-90")
    assert not (tmp_path / "out").exists()


def test_a_background_touching_the_inclusion_is_taken(tmp_path):
    exp = synthetic(tmp_path / "exp.h5")
    args = ["--inclusion", "75", "86", "75", "86", "--background", "75", "86", "86", "97", "--crop-mm", "0"]
    res = run_cli("process", exp, "-o", tmp_path / "out", "-q", "--no-report", "--cross-check", "none", *args)
    assert res.returncode == 0, res.stderr


def _float_with_nan(exp, frame, where):
    """``exp``'s frames as another lab's float32, ``where`` of ``frame`` NaN (a masked region)."""
    with h5py.File(exp, "a") as h5:
        frames = h5["entry/instrument/detector/data"][()].astype(np.float32)
        frames[(frame, *where)] = np.nan
        del h5["entry/instrument/detector/data"]
        h5["entry/instrument/detector/data"] = frames
    return exp


@pytest.mark.parametrize(
    "where, roi",
    [
        (np.s_[78:82, 78:82], "inclusion ROI (rows 75-86, cols 75-86)"),
        (np.s_[84:90, 48:52], "background ROI (rows 75-86, cols 40-51)"),
    ],
)
def test_nan_pixels_inside_a_roi_are_refused_naming_the_frame_and_the_roi(where, roi, tmp_path):
    """A 10 x 10 NaN block inside the inclusion was filled from its neighbours and measured
    (change ratio -5.9 -> -23.3, exit code 0), with a warning asking the user to check that the
    NaN pixels lie outside the ROIs, which radiokit knows."""
    exp = _float_with_nan(synthetic(tmp_path / "exp.h5"), 7, where)
    res = run_cli("process", exp, "-o", tmp_path / "out", *FAST)
    one_line_error(res, "exp.h5", "frame 7 (step 2)", "NaN or inf pixels inside the " + roi)
    assert not (tmp_path / "out").exists()


def _drifting(path):
    """A smooth texture whose steps lie 3 columns apart (step 3, the reference, leftmost): each
    moving step is registered 3 or 6 columns to the left."""
    from scipy import ndimage

    from radiokit.io import ExperimentWriter, ImageKey

    texture = ndimage.gaussian_filter(np.random.default_rng(1).random((128, 160)), 3)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    with ExperimentWriter(path, shape=(128, 128), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full((128, 128), 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full((128, 128), 3100, np.uint16), image_key=ImageKey.FLAT)
        for step in (1, 2, 3):
            shift = (3 - step) * 3
            line_integral = 0.5 + texture[:, 16 - shift : 144 - shift] * (1.0 - 0.05 * step)
            counts = (100 + 3000 * np.exp(-line_integral)).astype(np.uint16)
            w.append(counts, image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    return path


@pytest.mark.parametrize(
    "cols, refused", [(np.s_[80:83], "inclusion ROI (rows 50-70, cols 60-80)"), (np.s_[100:103], None)]
)
def test_nan_pixels_the_registration_moves_into_a_roi_are_refused_naming_the_roi(cols, refused, tmp_path):
    """NaN pixels of a moving step just beside the inclusion, clear of it as the file holds them,
    were carried into it by the registration (3 columns): the ROI measured their fill, exit code
    0, under a warning saying radiokit refuses them inside a ROI. Those the field leaves outside pass."""
    exp = _float_with_nan(_drifting(tmp_path / "exp.h5"), 7, np.s_[50:70, cols])  # frame 7: step 2
    rois = ["--inclusion", "50", "70", "60", "80", "--background", "20", "40", "60", "80"]
    res = run_cli("process", exp, "-o", tmp_path / "out", "-q", "--no-report", "--cross-check", "none", *rois)
    if refused is None:
        assert res.returncode == 0, res.stderr
        return
    one_line_error(res, "exp.h5", "step 2", "registered onto step 3", refused)
    assert not (tmp_path / "out").exists()


def test_nan_pixels_outside_the_rois_are_filled_and_told(tmp_path):
    exp = _float_with_nan(synthetic(tmp_path / "exp.h5"), 7, np.s_[10:20, 10:20])
    res = run_cli("process", exp, "-o", tmp_path / "out", *FAST)
    assert res.returncode == 0, res.stderr  # (the warning's line: run_cli ignores warnings)


@pytest.mark.parametrize("crop", [[], ["--crop-mm", "0"]])
def test_process_refuses_a_run_whose_working_memory_is_over_the_budget(crop, tmp_path):
    """``register`` refused a registration over the memory budget before it began; ``process``,
    which registers the same frames and holds more, had no such check: it ran into the machine's
    memory (or swap) with no word. Refused before any work, naming the file and the figures."""
    path = synthetic(tmp_path / "exp.h5")
    out = tmp_path / "out"
    res = run_cli("process", path, "-o", out, *FAST, *crop, env={"RADIOKIT_MEMORY_BUDGET": "2MB"})
    one_line_error(
        res, "exp.h5", "160x160", "bytes a pixel", "over the memory budget of 1.9 MiB", "RADIOKIT_MEMORY_BUDGET"
    )
    assert not out.exists()
    assert run_cli("process", path, "-o", out, *FAST, *crop, env={"RADIOKIT_MEMORY_BUDGET": "20MB"}).returncode == 0


@pytest.mark.parametrize("dataset", ["/entry/data/c", "entry/data/c"])
def test_a_dataset_path_given_with_its_leading_slash_is_named_once_slashed(tmp_path, dataset):
    """s37: `--dataset /entry/data/c` of complex pixels was refused as "//entry/data/c has type
    complex64": the message put its own "/" before the one the user typed."""
    path = tmp_path / "c.h5"
    with h5py.File(path, "w") as h5:
        h5["entry/data/c"] = np.zeros((2, 4, 5), np.complex64)
    line = one_line_error(run_cli("info", path, "--dataset", dataset), "/entry/data/c has type complex64")
    assert "//" not in line, line


def _many_steps(path, n_steps, shape=(160, 160)):
    """synthetic()'s slab and square over ``n_steps`` steps of compression."""
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    sq = (abs(rr - 80) < 10) & (abs(cc - 80) < 10)
    with ExperimentWriter(path, shape=shape, pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full(shape, 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full(shape, 3100, np.uint16), image_key=ImageKey.FLAT)
        for step in range(1, n_steps + 1):
            counts = 100 + 3000 * np.exp(-(0.08 * (20.0 - 0.5 * step) + 0.03 * (8.0 - 0.02 * step) * sq))
            w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=step, ratio=0.05 * step)
    return path


def test_process_counts_the_steps_in_its_working_memory(tmp_path):
    """The memory check was of the frame's size alone, measured on 3 steps; each step more holds
    about 40 bytes a pixel more (1024 x 1024 whole frame: 477 MB at 3 steps, 870 MB at 12), so a
    file of many steps passed a budget it then ran over."""
    budget = {"RADIOKIT_MEMORY_BUDGET": "10MB"}
    res = run_cli("process", _many_steps(tmp_path / "exp12.h5", 12), "-o", tmp_path / "out", *FAST, env=budget)
    one_line_error(res, "exp12.h5", "160x160", "12 steps", "over the memory budget")
    assert not (tmp_path / "out").exists()
    res = run_cli("process", _many_steps(tmp_path / "exp3.h5", 3), "-o", tmp_path / "out", *FAST, env=budget)
    assert "memory budget" not in res.stderr, res.stderr


def test_process_counts_the_control_in_its_working_memory(tmp_path):
    """The memory check skipped --control: a control of 12 steps (17.5 MB by the check's figures)
    was processed under a budget that refused the same file as the input. The control is processed
    while the input's images are held, so the two are charged together."""
    exp = synthetic(tmp_path / "exp.h5")  # 7.2 MB by the same figures
    ctl = _many_steps(tmp_path / "ctl12.h5", 12)
    res = run_cli(
        "process", exp, "--control", ctl, "-o", tmp_path / "out", *FAST, env={"RADIOKIT_MEMORY_BUDGET": "10MB"}
    )
    one_line_error(res, "--control", "ctl12.h5", "12 steps", "over the memory budget of 9.5 MiB")
    res = run_cli(
        "process", exp, "--control", ctl, "-o", tmp_path / "out", *FAST, env={"RADIOKIT_MEMORY_BUDGET": "20MB"}
    )
    one_line_error(res, "exp.h5", "and its control", "ctl12.h5", "over the memory budget of 19.1 MiB")
    assert not (tmp_path / "out").exists()


def test_files_processed_at_once_share_the_memory_budget(tmp_path):
    """Each file was checked against the whole budget, and the local cluster's workers process one
    file each at once: two workers could take twice the budget."""
    files = [synthetic(tmp_path / f"exp{i}.h5") for i in (1, 2)]  # 7.2 MB each by the check's figures
    budget = {"RADIOKIT_MEMORY_BUDGET": "10MB"}
    res = run_cli("process", *files, "--workers", 2, "-o", tmp_path / "out", *FAST, env=budget)
    one_line_error(res, "exp1.h5", "shared by the 2 files processed at once (4.8 MiB each", "--workers 1")
    res = run_cli("process", *files, "--workers", 1, "-o", tmp_path / "out", *FAST, env=budget)
    assert res.returncode == 0, res.stderr


def test_a_schedulers_workers_share_their_hosts_memory_budget(tmp_path):
    """With --scheduler each file was checked against the whole budget of the machine the command
    ran on: two workers on one host, each processing a file, took twice its budget. Each worker's
    share is its host's budget divided among the files its workers process at once."""
    from dask.distributed import LocalCluster

    files = [synthetic(tmp_path / f"exp{i}.h5") for i in (1, 2)]  # 7.2 MB each by the check's figures
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:

        def run(budget):
            return run_cli(
                "process", *files, "--scheduler", cluster.scheduler_address, "-o", tmp_path / "out", *FAST,
                env={"RADIOKIT_MEMORY_BUDGET": budget},
            )  # fmt: skip

        one_line_error(run("10MB"), "exp1.h5", "shared by the 2 files its Dask workers process at once (4.8 MiB each")
        assert not (tmp_path / "out").exists()
        res = run("20MB")
        assert res.returncode == 0, res.stderr
        assert all((tmp_path / "out" / f"exp{i}" / "results.json").exists() for i in (1, 2))


# -- several bad inputs: each named, in one pass, before any work ------------------------------
def _good_and_bad(tmp_path, shape=(32, 40)):
    """A good TIFF of two frames, a TIFF holding no image, an empty file, and one of another shape."""
    tifffile.imwrite(tmp_path / "a.tif", np.full((2, *shape), 1600, np.uint16))
    (tmp_path / "b.tif").write_bytes(b"II*\x00garbage!")
    (tmp_path / "c.tif").write_bytes(b"")
    tifffile.imwrite(tmp_path / "d.tif", np.full((2, 8, 8), 1600, np.uint16))
    return [tmp_path / n for n in ("a.tif", "b.tif", "c.tif", "d.tif")]


def test_correct_names_every_bad_frame_file_in_one_pass(tmp_path):
    """`radiokit correct a.tif b.tif c.tif d.tif` with three bad named only b.tif and stopped: the
    user fixed it, ran again, and met c.tif, then d.tif. Each is opened and judged first (headers
    only: no frame is read twice), every bad one named on its own line, nothing written."""
    a, b, c, d = _good_and_bad(tmp_path)
    shape = (32, 40)
    Calibration(np.full(shape, 100.0), np.full(shape, 3100.0), np.zeros(shape, np.uint32)).save(tmp_path / "cal.h5")
    res = run_cli("correct", a, b, c, d, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5")
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 3, res.stderr
    for line, bad in zip(lines, (b, c, d)):
        assert line.startswith(f"radiokit correct: {bad}: "), line
    assert "empty" in lines[1] and "(8, 8)" in lines[2] and "(32, 40)" in lines[2]
    assert not (tmp_path / "out.h5").exists()


def test_calibrate_names_every_bad_dark_and_flat_file_in_one_pass(tmp_path):
    a, b, c, d = _good_and_bad(tmp_path)
    res = run_cli("calibrate", "--dark", a, b, "--flat", a, c, d, "-o", tmp_path / "cal.h5")
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 3, res.stderr
    for line, bad in zip(lines, (b, c, d)):
        assert line.startswith(f"radiokit calibrate: {bad}: "), line
    assert not (tmp_path / "cal.h5").exists()


def test_process_names_every_missing_experiment_file(tmp_path):
    (tmp_path / "folder").mkdir()
    res = run_cli("process", tmp_path / "a.h5", tmp_path / "folder", tmp_path / "c.h5", "-o", tmp_path / "res", *FAST)
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 3, res.stderr
    assert [f"{n}:" in line for n, line in zip(("a.h5", "folder", "c.h5"), lines)] == [True] * 3, res.stderr
    assert "folder" in lines[1] and not (tmp_path / "res").exists()


def test_calibrate_names_the_odd_shaped_file_not_the_files_agreeing(tmp_path):
    """`calibrate --dark odd.tif a1.tif a2.tif a3.tif` judged each file's shape against the first
    file's: an odd first file named every good file after it as bad (a line each, 299 lines for 300
    darks) and never itself. The shape most files share is the panel's; the others are named."""
    odd = tmp_path / "odd.tif"
    tifffile.imwrite(odd, np.full((2, 8, 8), 100, np.uint16))
    darks = [tmp_path / f"a{i}.tif" for i in range(3)]
    for p in darks:
        tifffile.imwrite(p, np.full((2, 32, 40), 100, np.uint16))
    tifffile.imwrite(tmp_path / "f.tif", np.full((2, 32, 40), 1600, np.uint16))
    res = run_cli("calibrate", "--dark", odd, *darks, "--flat", tmp_path / "f.tif", "-o", tmp_path / "cal.h5")
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0].startswith(f"radiokit calibrate: {odd}: ") and "(8, 8)" in lines[0] and "(32, 40)" in lines[0]
    assert not (tmp_path / "cal.h5").exists()


def test_calibrate_judges_more_files_than_may_be_open_at_once(tmp_path):
    """`calibrate` judged every dark's header holding all the files open: 300 single-frame TIFFs
    under macOS's default limit of 256 open files named the last 50 "Too many open files", where
    they had been read one at a time. Headers are judged one file at a time, as frames are read."""
    resource = pytest.importorskip("resource")
    if not os.path.isdir("/proc/self/fd"):
        pytest.skip("counts open files in /proc")
    darks = [tmp_path / f"d{i:02d}.tif" for i in range(48)]
    for p in darks:
        tifffile.imwrite(p, np.full((16, 16), 100, np.uint16))
    tifffile.imwrite(tmp_path / "f.tif", np.full((2, 16, 16), 1600, np.uint16))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 24, hard))
    try:
        res = run_cli("calibrate", "--dark", *darks, "--flat", tmp_path / "f.tif", "-o", tmp_path / "cal.h5")
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert res.returncode == 0, res.stderr


def test_correct_reads_more_files_than_may_be_open_at_once(tmp_path):
    """`correct` judged every frame file's header, then corrected, holding all the files open:
    300 single-frame TIFFs under macOS's default limit of 256 open files failed "Too many open
    files", one line each, and nothing could be corrected. Headers are judged one file at a time
    and each file is open only while its frames are read; every frame lands, in order, at its
    transmission: -ln((raw - dark) / (flat - dark))."""
    resource = pytest.importorskip("resource")
    if not os.path.isdir("/proc/self/fd"):
        pytest.skip("counts open files in /proc")
    shape, n = (8, 8), 100
    Calibration(np.full(shape, 100.0), np.full(shape, 3100.0), np.zeros(shape, np.uint32)).save(tmp_path / "cal.h5")
    frames = [tmp_path / f"p{i:03d}.tif" for i in range(n)]
    raw = 700 + 15 * np.arange(n)  # transmission 0.2 + 0.005 i
    for p, level in zip(frames, raw):
        tifffile.imwrite(p, np.full(shape, level, np.uint16))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 24, hard))
    try:
        res = run_cli("correct", *frames, "--cal", tmp_path / "cal.h5", "-o", tmp_path / "out.h5")
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert res.returncode == 0, res.stderr
    out = read(tmp_path / "out.h5").data
    assert out.shape == (n, *shape)
    expected = -np.log((raw - 100) / 3000.0)
    np.testing.assert_allclose(out, np.broadcast_to(expected[:, None, None], out.shape), rtol=0, atol=1e-6)


def test_register_counts_the_memory_of_the_method_it_runs(tmp_path):
    """s49off: register's memory check counted 64 bytes a pixel for every method, measured on rc
    --preset fast; at 1120 and 2240 px a side ilk peaked at 142-144 bytes a pixel, rc's default at
    84-93 (benchmarks/README.md, "register's memory by method"). A budget that rc's run fits and
    ilk's does not refuses ilk before it begins."""
    import tifffile

    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        tifffile.imwrite(tmp_path / f"{name}.tif", rng.random((64, 64), np.float32))
    budget = {"RADIOKIT_MEMORY_BUDGET": str(120 * 64 * 64)}  # over rc's need, under ilk's
    given = (tmp_path / "a.tif", tmp_path / "b.tif", "-q", "-o")
    res = run_cli("register", *given, tmp_path / "ilk.h5", "--method", "ilk", env=budget)
    one_line_error(res, "64x64", "with ilk", "bytes a pixel", "over the memory budget")
    assert not (tmp_path / "ilk.h5").exists()
    res = run_cli("register", *given, tmp_path / "rc.h5", "--preset", "fast", env=budget)
    assert "memory budget" not in res.stderr and res.returncode in (0, 1), res.stderr
