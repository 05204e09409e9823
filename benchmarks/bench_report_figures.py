"""CPU of each of the report's five figures, and of the whole ``process`` run around them.

A synthetic experiment (a slab thinned by compression with a denser square, Gaussian noise of 30
counts) of ``--size`` pixels a side is processed twice (the first warms imports and numba); the
second run's CPU is printed, then its figures are drawn ``--repeats`` more times from the same
results and images, and the least CPU (``time.process_time``) of each figure is printed: the
machine is shared, and the least is the figure's own cost.

Run: ``python benchmarks/bench_report_figures.py [--size 256] [--repeats 5] [--out DIR]`` (~20 s
at 256; the PNGs of the last repeat are left in ``DIR/figures`` to look at).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from radiokit import report
from radiokit.io import ExperimentWriter, ImageKey
from radiokit.pipeline import Config, process

FIGURES = ("_fig_projections", "_fig_profiles", "_fig_difference", "_fig_rois", "_fig_registration")


def _experiment(path, n):
    rng = np.random.default_rng(45)
    rr, cc = np.mgrid[0:n, 0:n]
    c, half = 0.3 * n, 0.04 * n
    sq = (abs(rr - c) < half) & (abs(cc - c) < half)
    with ExperimentWriter(path, shape=(n, n), pixel_size_mm=0.05) as w:
        for _ in range(3):
            w.append(np.full((n, n), 100, np.uint16), image_key=ImageKey.DARK)
            w.append(np.full((n, n), 3100, np.uint16), image_key=ImageKey.FLAT)
        for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
            counts = 100 + 3000 * np.exp(-(0.08 * tb + 0.03 * ti * sq)) + rng.normal(0, 30, (n, n))
            w.append(counts.astype(np.uint16), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    a, b = int(c - half + 2), int(c + half - 1)  # inside the square, and the same rows to its left
    return (a, b, a, b), (a, b, max(0, a - 3 * (b - a)), max(1, a - 2 * (b - a)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-report-"))
    out = Path(args.out) if args.out else work / "redraw"
    (out / "figures").mkdir(parents=True, exist_ok=True)
    inclusion, background = _experiment(work / "exp.h5", args.size)
    cfg = Config(progress=False, inclusion=inclusion, background=background, crop_mm=None)
    seen, cpu = {}, {name: [] for name in FIGURES}

    def timed(name, draw):
        def run(images, results, fig_dir):
            seen["args"] = (images, results)
            t = time.process_time()
            made = draw(images, results, fig_dir)
            cpu[name].append(time.process_time() - t)
            return made

        return run

    for name in FIGURES:
        setattr(report, name, timed(name, getattr(report, name)))
    for run in ("warm", "timed"):
        t = time.process_time()
        process(work / "exp.h5", cfg, out_dir=work / run)
        total = time.process_time() - t
    print(f"process ({args.size} x {args.size}, report included): {total:.2f} s CPU")
    for name in FIGURES:
        cpu[name].clear()
    for _ in range(args.repeats):
        report.draw_figures(out, *seen["args"][::-1])
    for name in FIGURES:
        print(f"{name[5:]:>13}: {min(cpu[name]):.3f} s CPU (least of {args.repeats})")
    print(f"{'five figures':>13}: {sum(min(v) for v in cpu.values()):.3f} s CPU")
    shutil.rmtree(work / "warm", ignore_errors=True)


if __name__ == "__main__":
    main()
