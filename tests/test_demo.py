"""The demo end to end, binned 4x4 so it runs in seconds: every number is checked against truth."""
import json

from sim.demo import run_demo


def test_demo_recovers_truth(tmp_path):
    res = run_demo(tmp_path, binning=4, n_darks=8, n_flats=8, progress=False)
    d = res["defects"]
    assert d["false_positive"] == 0
    # Dead, under-responding and line defects are certain; a 10x-noise pixel seen in 8 darks can,
    # rarely (p ~ 1e-3 each), give samples as tight as a normal one: allow one such miss.
    assert d["missed"] <= 1
    for step in res["steps"]:
        assert step["nonfinite"] == 0
        # rms error is the expected noise (plus the small bias of the log of noisy counts)
        assert 0.9 * step["expected_noise"] < step["rms_error"] < 1.15 * step["expected_noise"]
        assert abs(step["bias"]) < 0.2 * step["expected_noise"]
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "summary.json").read_text())["frame_shape"] == [560, 560]
