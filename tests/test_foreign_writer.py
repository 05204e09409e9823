"""Experiment files another program wrote, with h5py alone, after DESIGN.md's layout (not through
``ExperimentWriter``): every legal way of writing it gives the step images radiokit's own writer's
file gives, and two contradictions the layout allows to be written are not passed over in silence.

The frames are a small disc-in-body phantom drawn here; each variant holds the very same counts,
so the corrected steps must agree to float rounding (float32 storage of integer counts below 2^24
is exact; the calibration's arithmetic is the same float64 either way)."""

import warnings

import h5py
import numpy as np
import pytest

from radiokit.cli import main
from radiokit.io import ExperimentWriter, HalfFloatWarning, ImageKey
from radiokit.pipeline import load_steps

N = 40
RATIOS = {1: 0.15, 2: 0.20, 3: 0.25}


def _frames():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[:N, :N].astype(float)
    dark = [rng.poisson(100, (N, N)).astype(np.uint16) for _ in range(3)]
    flat = [(rng.poisson(3000, (N, N)) + 100).astype(np.uint16) for _ in range(3)]
    proj = {}
    for s, r in RATIOS.items():
        body = ((y - 20) / (15 * (1 - r))) ** 2 + ((x - 20) / 16) ** 2 < 1
        inc = (y - 20) ** 2 + (x - 20) ** 2 < 16
        line = body * (1 + 2 * r) + 0.4 * inc
        proj[s] = [(rng.poisson(3000 * np.exp(-line)) + 100).astype(np.uint16) for _ in range(2)]
    return dark, flat, proj


DARK, FLAT, PROJ = _frames()


def _series(order="kind"):
    fr, key, step, ratio = [], [], [], []
    for d in DARK:
        fr, key, step, ratio = fr + [d], key + [2], step + [-1], ratio + [np.nan]
    for f in FLAT:
        fr, key, step, ratio = fr + [f], key + [1], step + [-1], ratio + [np.nan]
    for s, r in RATIOS.items():
        for p in PROJ[s]:  # a step of two frames
            fr, key, step, ratio = fr + [p], key + [0], step + [s], ratio + [r]
    idx = np.arange(len(fr)) if order == "kind" else np.random.default_rng(0).permutation(len(fr))
    return np.asarray(fr)[idx], np.asarray(key)[idx], np.asarray(step)[idx], np.asarray(ratio)[idx]


def write_foreign(path, *, text=str, dtype=np.uint16, key_type=np.int8, step_type=np.int16, ratio_type=np.float64,
                  storage=None, optional=True, order="kind", step_of_calibration=-1):  # fmt: skip
    """DESIGN.md's experiment layout written with h5py only, in the way the keywords say."""
    data, key, step, ratio = _series(order)
    step = np.where(key == 0, step, step_of_calibration)
    with h5py.File(path, "w") as h5:
        entry = h5.create_group("entry")
        entry.attrs["NX_class"] = text("NXentry")
        det = entry.create_group("instrument/detector")
        det.attrs["NX_class"] = text("NXdetector")
        det.create_dataset("data", data=data.astype(dtype), **(storage or {}))
        det.create_dataset("image_key", data=key.astype(key_type))
        comp = entry.create_group("sample/compression")
        comp.create_dataset("step", data=step.astype(step_type))
        comp.create_dataset("ratio", data=ratio.astype(ratio_type))
        if optional:
            entry.attrs["default"] = text("data")
            for name in ("x_pixel_size", "y_pixel_size"):
                det[name] = 5e-5
                det[name].attrs["units"] = text("m")
            det["pixel_mask"] = np.zeros((N, N), np.uint32)
            src = entry.create_group("instrument/source")
            src["type"], src["voltage"], src["current"] = text("Fixed Tube X-ray"), 40.0, np.int32(100)
            comp["gap"] = np.where(key == 0, 0.05 * (1 - ratio), np.nan)
            comp["gap"].attrs["units"] = text("m")
            nx = entry.create_group("data")
            nx.attrs["NX_class"], nx.attrs["signal"] = text("NXdata"), text("data")
            nx["data"] = h5py.SoftLink("/entry/instrument/detector/data")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    path = tmp_path_factory.mktemp("foreign") / "radiokit.h5"
    with ExperimentWriter(path, shape=(N, N), pixel_size_mm=0.05, source={"voltage_kv": 40, "current_ua": 100}) as w:
        for d in DARK:
            w.append(d, image_key=ImageKey.DARK)
        for f in FLAT:
            w.append(f, image_key=ImageKey.FLAT)
        for s, r in RATIOS.items():
            for p in PROJ[s]:
                w.append(p, image_key=ImageKey.PROJECTION, step=s, ratio=r)
    return load_steps(path)


CHUNK = (1, N, N)
VARIANTS = {
    "bytes attributes": dict(text=lambda s: np.bytes_(s.encode())),
    "variable-length ascii": dict(text=lambda s: np.array(s.encode(), dtype=h5py.string_dtype("ascii"))),
    "contiguous": dict(storage={}),
    "one frame a chunk, gzip": dict(storage=dict(chunks=CHUNK, compression="gzip", shuffle=True)),
    "odd chunks, lzf": dict(storage=dict(chunks=(3, 16, 16), compression="lzf")),
    "float steps and keys": dict(step_type=np.float64, key_type=np.float32),
    "int64 keys, int32 steps": dict(step_type=np.int32, key_type=np.int64),
    "uint8 keys": dict(key_type=np.uint8),
    "float32 frames": dict(dtype=np.float32),
    "big-endian uint16": dict(dtype=">u2"),
    "big-endian float32": dict(dtype=">f4"),
    "float32 ratios": dict(ratio_type=np.float32),
    "frames in any order": dict(order="mixed"),
    "no optional field": dict(optional=False),
    "darks and flats at step 0": dict(step_of_calibration=0),
}


@pytest.mark.parametrize("variant", VARIANTS, ids=list(VARIANTS))
def test_a_foreign_writers_file_gives_radiokit_writers_steps(variant, reference, tmp_path):
    path = tmp_path / "foreign.h5"
    write_foreign(path, **VARIANTS[variant])
    if VARIANTS[variant].get("optional", True):
        got = load_steps(path)
    else:
        with pytest.warns(UserWarning, match="records no pixel size"):
            got = load_steps(path)
    assert got.numbers == reference.numbers == (1, 2, 3)
    np.testing.assert_allclose(got.ratios, reference.ratios, rtol=1e-7)  # float32 0.15 is 0.15 to 4e-8
    np.testing.assert_allclose(got.images, reference.images, rtol=1e-12, atol=1e-12)
    assert got.pixel_size_mm == pytest.approx(0.05) and got.pixel_size_recorded == VARIANTS[variant].get("optional", 1)


def _edited(tmp_path, edit):
    path = tmp_path / "foreign.h5"
    write_foreign(path)
    with h5py.File(path, "a") as h5:
        comp = h5["entry/sample/compression"]
        step, ratio = comp["step"][()], comp["ratio"][()]
        edit(step, ratio)
        comp["step"][...], comp["ratio"][...] = step, ratio
    return path


def _refused(path, capsys, *words):
    before = path.read_bytes()
    out = path.parent / "out"
    assert main(["process", str(path), "-o", str(out), "-q", "--no-report"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"radiokit process: {path}: "), err
    assert all(w in err for w in words), err
    assert not out.exists() and path.read_bytes() == before
    return err


def test_a_projection_without_a_step_beside_numbered_steps_is_refused_not_dropped(tmp_path, capsys):
    """Step -1 is the darks' and flats' (DESIGN.md): a projection carrying it is in no step. It was
    dropped without a word: two of six projections, a whole step, gone, and the run measured 1->3
    as the main pair with exit code 0."""
    path = _edited(tmp_path, lambda step, ratio: step.__setitem__(step == 2, -1))
    _refused(path, capsys, "frame 8", "projection", "step -1", "image_key 3")


def test_a_step_whose_frames_record_two_ratios_is_said_and_averaged(tmp_path):
    """A step is one compression (DESIGN.md: a ratio per step): frames of one step recording 0.2 and
    0.22 (a mislabelled step, a mistyped ratio) were averaged into one image at 0.21 without a word.
    Warned, not refused: a step resumed on a manual frame records the operator's second reading."""
    path = _edited(tmp_path, lambda step, ratio: ratio.__setitem__(np.flatnonzero(step == 2)[1], 0.22))
    with pytest.warns(UserWarning, match=r"step 2's frames .* from 0\.2 \(frame 8\) to 0\.22 \(frame 9\).* 0\.21;"):
        steps = load_steps(path)
    assert steps.ratios[1] == pytest.approx(0.21, abs=1e-12)


def _regapped(tmp_path, ratio=None):
    """The foreign file with step 2's second frame (frame 9) at a 41 mm gap beside its first's 40
    (0.05 m x (1 - 0.2)), and at ``ratio`` if given."""
    path = tmp_path / "foreign.h5"
    write_foreign(path)
    with h5py.File(path, "a") as h5:
        comp = h5["entry/sample/compression"]
        gap = comp["gap"][()]
        gap[9] = 0.041
        comp["gap"][...] = gap
        if ratio is not None:
            comp["ratio"][9] = ratio
    return path


def test_a_step_whose_frames_record_two_gaps_is_said_as_two_ratios_are(tmp_path):
    """The gap feeds the bound (the main pair's gap change) and the steps' order where no ratio is
    recorded: a step's frames at 40 and 41 mm were averaged to 40.5 mm without a word, where two
    ratios were warned of."""
    path = _regapped(tmp_path)
    with pytest.warns(
        UserWarning, match=r"step 2's frames record plate gaps from 40 mm \(frame 8\) to 41 mm \(frame 9\).* 40\.5 mm;"
    ):
        load_steps(path)


def test_a_step_of_two_ratios_and_two_gaps_is_one_warning(tmp_path):
    """A resumed step at a manual frame records another gap and so another ratio (1 - gap/h0): one
    warning for the step, naming both, not one per record (nor per frame)."""
    path = _regapped(tmp_path, ratio=0.18)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        steps = load_steps(path)
    about = [str(w.message) for w in said if "step 2's frames" in str(w.message)]
    assert len(about) == 1, about
    assert "compression ratios from 0.18 (frame 9) to 0.2 (frame 8)" in about[0], about[0]
    assert "plate gaps from 40 mm (frame 8) to 41 mm (frame 9)" in about[0], about[0]
    assert steps.ratios[1] == pytest.approx(0.19, abs=1e-12)  # their mean, as before


def test_float16_frames_are_said_to_have_lost_counts_above_2048(tmp_path):
    """float16 holds whole numbers exactly only to 2^11 = 2048 (an 11-bit significand): this
    phantom's flats, ~3100 counts, were stored rounded to even counts, and a 16-bit panel's
    counts above 65504 as inf, and read without a word. Said once, in one line naming the file."""
    path = tmp_path / "foreign.h5"
    write_foreign(path, dtype=np.float16)
    with h5py.File(path) as h5:  # the premise: counts above 2048 were rounded when written
        stored = h5["entry/instrument/detector/data"][()].astype(np.float64)
    lost = np.asarray(FLAT, np.float64) - stored[3:6]
    assert np.any(lost != 0) and np.all(np.abs(lost) <= 2 ** (np.floor(np.log2(stored[3:6])) - 10) / 2)
    with pytest.warns(HalfFloatWarning) as said:  # (the command line shows one a file: its .path)
        assert main(["info", str(path)]) == 0
    text = str(said[0].message)
    assert "\n" not in text and text.startswith(f"{path}: ") and "float16" in text and "2048" in text, text
    assert said[0].message.path == str(path)
    with pytest.warns(HalfFloatWarning):
        load_steps(path)


def test_uint16_and_float32_frames_are_not_said_to_have_lost_counts(tmp_path):
    for dtype in (np.uint16, np.float32):
        path = tmp_path / f"{np.dtype(dtype).name}.h5"
        write_foreign(path, dtype=dtype)
        with warnings.catch_warnings():
            warnings.simplefilter("error", HalfFloatWarning)
            assert main(["info", str(path)]) == 0


def test_an_nxtomo_file_without_steps_is_told_where_they_go(tmp_path, capsys):
    """NXtomo records no compression step: such a file was told its projections "carry no step
    number (a negative step: not written)", of a step it never wrote."""
    path = tmp_path / "foreign.h5"
    write_foreign(path)
    with h5py.File(path, "a") as h5:
        del h5["entry/sample"]
    _refused(path, capsys, "6 projection(s) have none", "no /entry/sample/compression/step", "one per frame")


def test_a_ratio_per_step_instead_of_per_frame_is_named_as_such(tmp_path, capsys):
    """DESIGN.md lists ``ratio`` with ``step (n,)``; one written per step ((3,) for 3 steps) is
    refused saying a ratio is recorded per frame."""
    path = tmp_path / "foreign.h5"
    write_foreign(path)
    with h5py.File(path, "a") as h5:
        del h5["entry/sample/compression/ratio"]
        h5["entry/sample/compression/ratio"] = [0.15, 0.2, 0.25]
    _refused(path, capsys, "3 values for 12", "one per frame")


@pytest.mark.parametrize("command", ["process", "calibrate", "correct", "register", "info"])
def test_an_experiment_file_of_0_frames_is_named_as_such(command, tmp_path, capsys):
    """A stack of 0 frames is ``FILE: no frames`` (README, as `radiokit info` says it); an experiment
    file of none was "holds no darks (image_key 2)" to process and calibrate, "not an experiment
    file" to correct, and "frame 0 requested, the file holds 0" to register."""
    path = tmp_path / "foreign.h5"
    write_foreign(path, storage=dict(maxshape=(None, N, N), chunks=CHUNK))
    with h5py.File(path, "a") as h5:
        h5["entry/instrument/detector/data"].resize(0, axis=0)
        for name in ("instrument/detector/image_key", "sample/compression/step", "sample/compression/ratio"):
            dtype = h5["entry"][name].dtype
            del h5["entry"][name]
            h5["entry"].create_dataset(name, shape=(0,), dtype=dtype)
        del h5["entry/sample/compression/gap"]
    before = path.read_bytes()
    out = tmp_path / ("out" if command == "process" else "out.h5")
    args = {
        "process": [str(path), "-o", str(out), "-q"],
        "calibrate": ["--experiment", str(path), "-o", str(out), "-q"],
        "register": [str(path), str(path), "-o", str(out), "-q"],  # was "frame 0 requested, the file holds 0"
        "info": [str(path)],
    }
    assert main([command, *args.get(command, [str(path), "-o", str(out), "-q"])]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"radiokit {command}: {path}: no frames"
    assert not out.exists() and path.read_bytes() == before
