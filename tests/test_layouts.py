"""Every file radiokit writes, written the way a user writes it, opens with ``radiokit.io.read`` and
with a NeXus reader (silx) at its frames; each layout's typed reader gives back what was written."""

import json

import h5py
import numpy as np
import pytest
import silx.io
import silx.io.nxdata

from radiokit.cli import main
from radiokit.io import (
    EnhancedImages,
    ExperimentWriter,
    ImageKey,
    ResultsRecord,
    read,
    read_progress,
    read_registration,
    read_results,
    read_simulation,
    read_stack,
    write_results,
)


def nexus_plot(path):
    """The signal silx plots for ``path`` by default (following ``@default``): (shape, dtype, values)."""
    with silx.io.open(str(path)) as f:
        nx = silx.io.nxdata.get_default(f)
        assert nx is not None and nx.is_valid, f"{path}: silx finds no valid default NXdata"
        assert nx.interpretation == "image"
        return nx.signal[()]


def assert_opens(path, frames):
    """read() and silx's default plot both give ``frames`` ((n, rows, cols), or one (rows, cols) image)."""
    frames = np.asarray(frames)
    got = read(path).data
    np.testing.assert_array_equal(got, frames if frames.ndim == 3 else frames[None])
    np.testing.assert_array_equal(nexus_plot(path), frames)


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """A small experiment file, through the real writer: 4 darks, 4 flats, 2 steps of 2 frames."""
    from sim.detector import PanelModel

    panel = PanelModel(rows=48, cols=64, defect_columns=(20,), n_dead=1, n_under=1, n_noisy=1)
    rng = np.random.default_rng(1)
    path = tmp_path_factory.mktemp("layouts") / "exp.h5"
    with ExperimentWriter(path, shape=panel.shape) as w:
        for f in panel.dark_frames(4, rng):
            w.append(f, image_key=ImageKey.DARK)
        for f in panel.flat_frames(4, 2000, rng):
            w.append(f, image_key=ImageKey.FLAT)
        y, x = np.mgrid[:48, :64]
        for step in (1, 2):
            body = (0.5 + 0.3 * np.exp(-((y - 24) ** 2 + (x - 30 - 2 * step) ** 2) / 80)).astype(np.float32)
            for f in panel.expose(body, 2000, 2, rng):
                w.append(f, image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
        w.record_run('name = "test"', {"detector": {"kind": "model"}})
    return path


def test_experiment(experiment):
    with h5py.File(experiment) as h5:
        frames = h5["entry/instrument/detector/data"][()]
    assert frames.shape == (12, 48, 64)
    assert_opens(experiment, frames)
    progress = read_progress(experiment)
    assert progress.frames_complete == 12 and progress.protocol == 'name = "test"'
    assert progress.image_key.tolist() == [2] * 4 + [1] * 4 + [0] * 4
    assert progress.step.tolist() == [-1] * 8 + [1, 1, 2, 2]
    assert json.loads(progress.devices) == {"detector": {"kind": "model"}}
    assert read_simulation(experiment) is None  # a lab file has no truth


def test_mark_invalid_labels_frames_and_nothing_else(tmp_path):
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(4, 5)) as w:
        for key in (ImageKey.DARK, ImageKey.FLAT, ImageKey.PROJECTION):
            w.append(np.ones((4, 5), np.uint16), image_key=key, step=1 if key == ImageKey.PROJECTION else -1)
        w.mark_invalid([1])
        with pytest.raises(IndexError, match="frame 3"):
            w.mark_invalid([3])
    assert read_progress(path).image_key.tolist() == [ImageKey.DARK, ImageKey.INVALID, ImageKey.PROJECTION]
    assert read(path).meta["image_key"].tolist() == [2, 3, 0]


@pytest.mark.parametrize("suffix", [".h5", ".tif"])
def test_radiokit_correct(experiment, suffix):
    out = experiment.with_name(f"corrected{suffix}")
    assert main(["correct", str(experiment), "-o", str(out), "-q", "--overwrite"]) == 0
    frames = read(out).data
    # the four projections, corrected to line integrals: the body's 0.5..0.8, all finite
    assert frames.shape == (4, 48, 64) and frames.dtype == np.float32 and np.isfinite(frames).all()
    assert np.median(frames) == pytest.approx(0.55, abs=0.1)
    if suffix == ".h5":
        assert_opens(out, frames)
        stack = read_stack(out)
        np.testing.assert_array_equal(stack.data, frames)
        assert stack.meta["domain"] == "log" and stack.series["step"].tolist() == [1, 1, 2, 2]


def test_radiokit_register(experiment):
    stack = experiment.with_name("corrected.h5")
    if not stack.exists():
        assert main(["correct", str(experiment), "-o", str(stack), "-q"]) == 0
    out = experiment.with_name("reg.h5")
    code = main(
        [
            "register",
            str(stack),
            str(stack),
            "--fixed-frame",
            "3",
            "--moving-frame",
            "1",
            "--method",
            "ncc",
            "-o",
            str(out),
            "--overwrite",
        ]
    )
    assert code in (0, 1)  # 1: registered, but judged not trustworthy; the file is written either way
    reg = read_registration(out)
    assert reg.registered.shape == (48, 64) and reg.displacement.shape == (2, 48, 64)
    assert reg.method == "ncc" and reg.fixed == str(stack) and isinstance(reg.quality["ok"], bool)
    assert_opens(out, reg.registered)


def test_results_layout_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    steps = rng.random((3, 20, 30), dtype=np.float32)
    enhanced = {
        d: EnhancedImages(steps[2], steps[2] - steps[1], {"1": steps[2] + 1, "2": steps[2] + 2})
        for d in ("log", "linear")
    }
    record = ResultsRecord(
        source="exp.h5",
        results_json='{"a": 1}',
        line_integral=steps,
        step=np.array([1, 2, 3]),
        ratio=np.array([0.15, 0.2, 0.25]),
        crop=np.array([0, 20, 5, 35]),
        pair=(2, 3),
        registration={"registered": steps[1], "displacement": np.zeros((2, 20, 30), np.float32)},
        enhanced=enhanced,
        rois={"inclusion": np.array([1, 5, 2, 9])},
    )
    path = tmp_path / "results.h5"
    write_results(path, record)
    assert_opens(path, steps)
    back = read_results(path)
    assert (back.source, back.results_json, back.pair) == ("exp.h5", '{"a": 1}', (2, 3))
    np.testing.assert_array_equal(back.step, [1, 2, 3])
    np.testing.assert_array_equal(back.crop, [0, 20, 5, 35])
    np.testing.assert_array_equal(back.registration["registered"], steps[1])
    np.testing.assert_array_equal(back.enhanced["linear"].enhanced["2"], steps[2] + 2)
    np.testing.assert_array_equal(back.rois["inclusion"], [1, 5, 2, 9])


def _block_toml(tmp_path):
    from sim.scene import block_scene

    scene = block_scene(size_mm=10, ratios=(0.1, 0.2))
    scene.detector.binning = 4
    path = tmp_path / "block.toml"
    scene.save(path)
    return scene, path


def test_radiokit_sim_run(tmp_path):
    scene, toml = _block_toml(tmp_path)
    out = tmp_path / "sim.h5"
    assert main(["sim", "run", str(toml), "-o", str(out), "--darks", "2", "--flats", "2", "-q"]) == 0
    with h5py.File(out) as h5:
        frames = h5["entry/instrument/detector/data"][()]
    assert frames.shape == (6, 560, 560)
    assert_opens(out, frames)
    sim = read_simulation(out)
    assert sim.scene_name == scene.name and sim.line_integral.shape == (2, 560, 560)
    np.testing.assert_allclose(sim.ratio, [0.1, 0.2])
    assert set(sim.displacement) == {(1, 2)}


def test_radiokit_acquire_sim_and_the_bench_truth(tmp_path):
    """``radiokit acquire --sim`` writes an experiment file; the bench adds its truth (as the demo does)."""
    from acquisition.protocols import load_protocol
    from sim.bench import VirtualBench
    from sim.scene import block_scene

    scene = block_scene(size_mm=10.0, ratios=(0.15, 0.25))
    scene.detector.binning = 4
    p = load_protocol(
        {
            "output": str(tmp_path / "series.h5"),
            "name": "layouts",
            # min_interval_s: a short command spacing (the dialect's 50 ms made 40 exchanges 2 s);
            # this test is about the file, the spacing has its own (test_l8121, the fault matrix)
            "source": {
                "voltage_kv": 60,
                "current_ua": 250,
                "poll_s": 0.1,
                "timeout_s": 0.5,
                "off_attempts": 1,
                "min_interval_s": 0.01,
            },
            "detector": {"kind": "sim", "timeout_s": 2.0},
            "frame": {"kind": "sim", "initial_height_mm": 10.0},
            "series": {"darks": 2, "flats": 2, "frames_per_step": 1, "steps": [0.15, 0.25], "settle_s": 0.0},
            "sim": {"scene": scene.to_toml(), "warmup_s": 0.3, "ramp_s": 0.1, "warmed_up": True},
        }
    )
    protocol = tmp_path / "protocol.toml"
    protocol.write_text(p.to_toml())
    assert main(["acquire", str(protocol), "--sim", "-q"]) == 0
    out = tmp_path / "series.h5"
    with h5py.File(out) as h5:
        frames = h5["entry/instrument/detector/data"][()]
    assert frames.shape == (6, 560, 560)
    assert_opens(out, frames)
    assert read_progress(out).protocol == p.to_toml()
    bench = VirtualBench(scene, seed=0)
    bench.prepare((0.15, 0.25))
    bench.write_truth(out)
    bench.write_truth(out)  # replaces the truth it wrote, never adds a second
    sim = read_simulation(out)
    assert set(sim.displacement) == {(1, 2)} and sim.line_integral.shape == (2, 560, 560)
    assert_opens(out, frames)  # the truth changes nothing a reader of the frames sees


def test_write_simulation_refuses_a_second_truth(tmp_path):
    from radiokit.io import SimulationRecord, write_simulation

    one = np.zeros(1)
    record = SimulationRecord(
        "name = 'x'", one, one, one, one, one, one, np.zeros((1, 2, 3), np.float32), np.zeros((1, 2, 3), np.uint8)
    )
    path = tmp_path / "exp.h5"
    with ExperimentWriter(path, shape=(2, 3)) as w:
        w.write_simulation(record)
    with pytest.raises(FileExistsError, match="entry/simulation"):
        write_simulation(path, record)
    write_simulation(path, record, replace=True)
    assert read_simulation(path).scene_name == "x"


def test_radiokit_calibrate(experiment):
    """A calibration is no NeXus stack (``Calibration.load`` reads it), but read() still opens it: its
    dark and flat as two frames, labelled as an experiment labels them."""
    from radiokit.calibrate import Calibration

    out = experiment.with_name("cal.h5")
    assert main(["calibrate", "--experiment", str(experiment), "-o", str(out), "--overwrite"]) == 0
    cal = Calibration.load(out)
    f = read(out)
    assert f.meta["format"] == "calibration" and f.meta["image_key"].tolist() == [ImageKey.DARK, ImageKey.FLAT]
    np.testing.assert_array_equal(f.data, np.stack([cal.dark, cal.flat]))
    # the dark near the panel's offset, the flat well above it
    assert f.data[0].mean() < f.data[1].mean() - 500
