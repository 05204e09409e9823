"""The README's self-contained examples run as written."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def _block(heading):
    text = README.read_text()
    section = text[text.index(heading) :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_calibrate_and_correct_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("### Calibrate and correct"), "README.md", "exec"), ns)
    import numpy as np

    # 1550 counts with dark 100 and flat 3000: I/I0 = 0.5
    assert abs(float(np.median(ns["mu_l"])) - np.log(2)) < 0.01
    assert abs(float(np.median(ns["t"])) - 0.5) < 0.005
    assert (tmp_path / "cal.h5").exists()


def test_simulation_example():
    ns = {}
    exec(compile(_block("### Simulate the experiment"), "README.md", "exec"), ns)
    from sim.mechanics import uniaxial_block_force

    force, _ = uniaxial_block_force(0.25, 5, 0.495, 100.0)
    assert abs(ns["s25"].plate_force_n / force - 1) < 1e-6
    assert ns["line_integral"].shape == (560, 560) and ns["d"].shape == (2, 560, 560)


def test_register_example():
    ns = {}
    exec(compile(_block("### Register"), "README.md", "exec"), ns)
    reg = ns["reg"]
    assert reg.quality.ok
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(reg.displacement[(slice(None),) + inner] - 1.5).max() < 0.1


def test_acquire_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("### Acquire"), "README.md", "exec"), ns)
    from radiokit.io import ImageKey, read

    f = read(tmp_path / "series.h5")
    assert ns["result"].frames_written == 10 == f.data.shape[0]
    keys = f.meta["image_key"]
    assert (keys == ImageKey.PROJECTION).sum() == 6 and (keys == ImageKey.DARK).sum() == 2


def test_weak_alpha_example(capsys):
    """The noise the example adds (0.01 in both images) is what ``weak`` reads and sets alpha by."""
    ns = {}
    exec(compile(_block("`weak`'s alpha follows the pair's noise"), "README.md", "exec"), ns)
    sigma, alpha = capsys.readouterr().out.split()
    assert abs(float(sigma) - 0.01) <= 0.001
    assert abs(float(alpha) / (210 * ns["reg"].options["noise_sigma"] ** 2) - 1) < 1e-6
