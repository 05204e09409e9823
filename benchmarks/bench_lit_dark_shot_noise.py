"""Can a dark taken with the beam on be told from its shot noise? (A prototype, not in calibrate.)

A dark lit at a share ``f`` of the flats' signal carries shot noise that rises with the beam's
field, whose variance is ``r^2 + G f F(x)``; a true dark carries read noise alone, ``r^2``. The
flats' mean ``M`` less the dark is ``s(x) = (1 - f) F(x)`` in both cases. So the slope of the
dark's local variance against ``s`` is ``G f / (1 - f)``, and the slope of the flats' variance
less the dark's is ``G``. Their ratio estimates ``f / (1 - f)`` with no threshold tuned to data.
The local variance comes from second differences along each row of ``dark - M``. That removes the
panel's fixed pattern, which the flats share, and a smooth field's slope; ``M``'s own variance
(the flats' over ``n``) is subtracted.

The panel is tests/test_lit_dark_fixed_pattern.py's: read-out blocks 200 counts apart, column
offsets, a gradient, 0.1 % hot pixels. It is 128 x 128, with 5 flats of 3000 counts in a field
30 % lower at the corners ("radial"), or a uniform field, and read noise of 3 counts (or 2 and 8
by block). The script prints the estimate +- its standard error per lit share, and what
``Calibration.from_frames`` made of that dark.

    python benchmarks/bench_lit_dark_shot_noise.py
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from radiokit.calibrate import Calibration

# the panel is the test's own, so the prototype measures on the very offset map calibrate's tests use
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_lit_dark_fixed_pattern import _panel

N = 128


def _field(level):
    """A cone beam's flat: 30 % lower at the corners than at the centre."""
    yy, xx = np.mgrid[:N, :N]
    return level * (1 - 0.3 * ((yy - N / 2) ** 2 + (xx - N / 2) ** 2) / (N / 2) ** 2)


def frames(rng, offset, hot, signal, n, read_noise):
    out = offset + rng.poisson(signal, (n, N, N)) + rng.normal(0, 1, (n, N, N)) * read_noise
    out[:, hot] += 3000
    return out.astype(np.float32)


def lit_odds(dark, flats) -> tuple[float, float]:
    """``f / (1 - f)`` and its standard error (see the module's docstring)."""
    n = len(flats)
    mean = flats.mean(axis=0, dtype=np.float64)
    var = flats.var(axis=0, ddof=1, dtype=np.float64)
    b = dark.astype(np.float64) - mean
    d2 = b[:, 2:] - 2 * b[:, 1:-1] + b[:, :-2]
    v_flat = (var[:, 2:] + 4 * var[:, 1:-1] + var[:, :-2]) / 6
    v_dark = d2**2 / 6 - v_flat / n
    s = -(b[:, 2:] + b[:, 1:-1] + b[:, :-2]).ravel() / 3
    v_dark, v_flat = v_dark.ravel(), v_flat.ravel()
    x = s - s.mean()
    slope_dark = np.dot(x, v_dark) / np.dot(x, x)
    gain = np.dot(x, v_flat - v_dark) / np.dot(x, x)
    resid = v_dark - v_dark.mean() - slope_dark * x
    se = np.std(resid) / np.sqrt(np.dot(x, x))
    return slope_dark / gain, abs(se / gain)


def verdict(dark, flats) -> str:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Calibration.from_frames(dark[None], flats)
    except Exception as exc:  # FrameLevelError, CalibrationRefused: which, and why
        return "refused: " + ("lit" if "lit" in str(exc) else str(exc).split(":")[0][:40])
    return "accepted"


def main() -> None:
    print(f"{'field, read noise':24} {'f':>4} {'f/(1-f)':>8} {'estimate':>14}  calibrate")
    for case in ("radial, 3", "radial, 2|8 by block", "uniform, 3"):
        for seed in range(2):
            rng = np.random.default_rng(seed)
            offset, hot = _panel(rng, blocks=8, block_sd=200, col_sd=50, gradient=200)
            noise = np.repeat(rng.choice([2.0, 8.0], 8), N // 8)[:, None] if "block" in case else 3.0
            field = np.full((N, N), 3000.0) if case.startswith("uniform") else _field(3000)
            flats = frames(rng, offset, hot, field, 5, noise)
            for f in (0.0, 0.3, 0.7, 0.8, 0.9):
                dark = frames(rng, offset, hot, f * field, 1, noise)[0]
                odds, se = lit_odds(dark, flats)
                print(f"{case:24} {f:4.1f} {f / (1 - f):8.2f} {odds:7.2f} +-{se:5.2f}  {verdict(dark, flats)}")


if __name__ == "__main__":
    main()
