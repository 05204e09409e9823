"""Does the flag hold on a generator nothing was chosen on? (issue 11)

Run (from the repository root)::

    python benchmarks/bench_register_heldout.py [--size 560] [--seeds 2]

Every threshold of ``quality.ok`` and every preset was chosen on ``regdata.family`` (an
ellipse's chord with a disc, band-limited texture, filtered-noise motion, a one-cycle intensity
change). This script draws pairs from a different generator and reports the flag's confusion
table and ``auto``'s errors on them, with the same definitions as ``bench_register_flag.py``
(failed: median EPE inside the body > max(1 px, half the identity's); good: <= 0.5 px):

- body: a cylinder lying across the frame (the pva phantom's side view): a chord profile across
  the rows, superelliptic ends, one or two ellipsoidal inclusions of random size and contrast;
- texture: a power-law (``1/f^beta``, beta 2.5-3.5) random field over the body, its standard
  deviation 0, 0.3, 1, 3 or 10 x the noise;
- motion: a compression (rows squeezed 0.5-2 %, columns expanded 0.5-2 % about a random centre)
  plus two to four Gaussian bumps (0.3-1.5 % of the frame, widths 5-15 % of it);
- intensity: a multiplicative thinning, a ramp plus a bump, up to +-10 %;
- noise: Poisson-like (its standard deviation in line integrals ``noise x exp((p - p_mean)/2)``),
  ``noise`` 0.01 or 0.0025.

Nothing here is used to choose anything (no training split): it is a check.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import score

SEEDS = tuple(range(5000, 5100))  # apart from regdata's training (0-99) and test (1000-1099) seeds
METHODS = {"rc-auto": "auto", "rc-auto-fast": "auto-fast", "rc": "default", "rc-weak": "weak", "rc-fast": "fast"}


def _power_law(n, rng, beta):
    """A random field of unit standard deviation with power spectrum ``1/f^beta``."""
    fy, fx = np.fft.fftfreq(n)[:, None], np.fft.rfftfreq(n)[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2)
    amp[0, 0] = 0.0
    z = rng.standard_normal((n, n // 2 + 1)) + 1j * rng.standard_normal((n, n // 2 + 1))
    t = np.fft.irfft2(z * amp, s=(n, n))
    return t / t.std()


def _bumps(n, rng, k, amplitude, width):
    """``k`` Gaussian bumps of a 2-vector field (``amplitude`` px, ``width`` px sigma)."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    d = np.zeros((2, n, n))
    for _ in range(k):
        cy, cx = rng.uniform(0.2, 0.8, 2) * n
        s = rng.uniform(*width) * n
        a = rng.uniform(*amplitude) * n * rng.choice([-1, 1], 2) * rng.uniform(0.3, 1.0, 2)
        g = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
        d += a[:, None, None] * g
    return d


def heldout_pair(size, seed, t2n, noise):
    """``(fixed, moving, truth, mask)`` as ``regdata.family_pair`` returns them (line integrals,
    ``fixed(x) = moving(x + truth(x))``), from this module's generator."""
    n = int(size)
    rng = np.random.default_rng(seed)
    y = (np.arange(n)[:, None] + 0.5) / n
    x = (np.arange(n)[None, :] + 0.5) / n
    half_h, half_w = rng.uniform(0.25, 0.32), rng.uniform(0.36, 0.44)
    cross = np.clip(1 - ((y - 0.5) / half_h) ** 2, 0, None)
    ends = np.clip(1 - np.abs((x - 0.5) / half_w) ** 6, 0, None)
    thick = np.sqrt(cross) * np.sqrt(ends)  # a cylinder's chord, its ends rounded
    body = thick > 0
    p = 1.5 * thick
    for _ in range(rng.integers(1, 3)):
        cy, cx = 0.5 + rng.uniform(-0.5, 0.5) * half_h, 0.5 + rng.uniform(-0.6, 0.6) * half_w
        ay, ax = rng.uniform(0.03, 0.08, 2)
        e = np.clip(1 - ((y - cy) / ay) ** 2 - ((x - cx) / ax) ** 2, 0, None)
        p += rng.uniform(0.05, 0.3) * np.sqrt(e) * body
    # drawn at every texture level, so that the levels share the body, motion and noise draws
    p += t2n * noise * _power_law(n, rng, rng.uniform(2.5, 3.5)) * thick
    moving = ndimage.gaussian_filter(p, 1.0)
    # pull field: fixed(x) = moving(x + d(x)); a squeeze of the rows, an expansion of the columns
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    cy, cx = rng.uniform(0.4, 0.6, 2) * n
    sy, sx = rng.uniform(0.005, 0.02), rng.uniform(0.005, 0.02)
    d = np.stack([sy * (yy - cy), -sx * (xx - cx)])
    d += _bumps(n, rng, int(rng.integers(2, 5)), (0.003, 0.015), (0.05, 0.15))
    fixed = ndimage.map_coordinates(moving, [yy + d[0], xx + d[1]], order=3, mode="nearest")
    ramp = rng.uniform(-1, 1) * (x - 0.5) + rng.uniform(-1, 1) * (y - 0.5)
    bump = np.exp(-((y - rng.uniform(0.3, 0.7)) ** 2 + (x - rng.uniform(0.3, 0.7)) ** 2) / (2 * 0.2**2))
    change = ramp + rng.uniform(-1, 1) * bump
    fixed *= 1 + rng.uniform(0.03, 0.1) * change / np.abs(change).max()
    pair = []
    for img in (fixed, moving):
        z = rng.standard_normal((n, n)) * np.exp((img - img[body].mean()) / 2)
        pair.append((img + noise * z).astype(np.float32))
    inner = ndimage.binary_erosion(body, iterations=max(1, int(0.03 * n)))  # scored: the body less 3 %
    return pair[0], pair[1], d.astype(np.float32), inner


def run(size, seeds):
    """Every method on every pair; rows as ``bench_register_flag`` makes them (``_row``)."""
    from bench_register_flag import _row

    from radiokit.register import register

    rows = []
    for seed in SEEDS[:seeds]:
        for noise in (0.01, 0.0025):
            for t2n in (0.0, 0.3, 1.0, 3.0, 10.0):
                f, m, d, mask = heldout_pair(size, seed, t2n, noise)
                ident = score(np.zeros_like(d), d, mask)["epe_median"]
                label = f"s{seed} noise {noise:g} t/n {t2n:g}"
                line = f"  {label:<26} identity {ident:5.2f}:"
                for name, preset in METHODS.items():
                    t0 = time.perf_counter()
                    reg = register(f, m, "rc", preset=preset)
                    rows.append(_row({}, label, name, reg, d, mask, ident, time.perf_counter() - t0))
                    line += f" {name} {rows[-1]['epe_median']:.2f}{'' if reg.quality.ok else '!'}"
                print(line, flush=True)
    return rows


def table(rows) -> str:
    """The flag's confusion (``bench_register.confusion``: failed = median EPE > max(1 px, half
    the identity's), good = <= 0.5 px), over all results and per method."""
    from bench_register import confusion

    lines = ["| results | failed | flagged | good | trusted |", "|---|---|---|---|---|"]
    for tag in ["all"] + list(METHODS):
        c = confusion([r for r in rows if tag == "all" or r["method"] == tag])
        lines.append(f"| {tag} ({c['n']}) | {c['failed']} | {c['failed_flagged']} | {c['good']} | {c['good_ok']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from bench_register_flag import misses

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(args.size, args.seeds)
    print(
        f"\n{len(rows)} results, {args.size} px, seeds {SEEDS[0]}-{SEEDS[args.seeds - 1]}, {time.perf_counter() - t0:.0f} s"
    )
    print(table(rows))
    print("\n".join(misses(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
