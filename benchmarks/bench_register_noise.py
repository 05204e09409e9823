"""Does rc hold when the same pair carries less noise? alpha fixed against alpha from the noise.

Run (from the repository root)::

    python benchmarks/bench_register_noise.py [--size 1120] [--split test] [--seeds 2]
        [--runs '{"preset": "weak", "noise_alpha": 100}' ...]

The family's weak-texture pair (``regdata.family_pair``: correlation 1/10, 1 % motion, +-10 %
thinning) with the noise at 0.0025-0.02 of the line integral and the texture at 1x and 3x the
noise: the texture-to-noise ratio, and so the information a texture carries, is the same down
each column, and the body's edge carries more as the noise falls. A registration whose energy
weighs the data as a likelihood should do no worse as the noise falls. Printed per case: the
median / 95th percentile end-point error inside the body for rc ``weak`` with the alpha it was
tuned with held fixed (``alpha=0.005``, what every preset ran before session 12) and with alpha
following the measured noise (the preset as it is: ``noise_alpha``), and ``auto``; then the
geometric mean of the medians per noise level. Training seeds chose ``noise_alpha``
(``--split train``); tables are reported on test seeds (``benchmarks/README.md``, "rc's alpha
follows the noise"). ``--runs`` replaces the three runs by rc with each JSON option set (how
``noise_alpha`` was chosen again with ``grid_jitter`` on, session 20).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, evaluate, family_pair

NOISES = (0.0025, 0.005, 0.01, 0.02)
RUNS = (
    ("weak, alpha fixed", dict(preset="weak", alpha=0.005)),
    ("weak", dict(preset="weak")),
    ("auto", dict(preset="auto")),
)


def run_case(case, runs=RUNS):
    """``[(median, p95, seconds, ok)]`` per entry of ``runs`` on ``case``'s pair."""
    pair = family_pair(case)
    rows = [evaluate("rc", pair, **options) for _, options in runs]
    return [(r["epe_median"], r["epe_p95"], r["seconds"], r["ok"]) for r in rows]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=1120)
    ap.add_argument("--split", choices=["train", "test"], default="test")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--ratios", type=float, nargs="+", default=[1.0, 3.0], help="texture / noise")
    ap.add_argument("--runs", nargs="+", help="rc option sets (JSON) to run instead of the three above")
    args = ap.parse_args(argv)
    runs = RUNS if not args.runs else [(text, json.loads(text)) for text in args.runs]
    seeds = (TRAIN_SEEDS if args.split == "train" else TEST_SEEDS)[: args.seeds]
    names = [name for name, _ in runs]
    print(f"{args.size} px, {args.split} seeds {list(seeds)}: median / p95 EPE px (seconds) [ok]; " + " | ".join(names))
    medians = {}
    for noise in NOISES:
        for ratio in args.ratios:
            for seed in seeds:
                case = Case(size=args.size, texture=noise * ratio, noise=noise, corr=0.1, seed=seed)
                rows = run_case(case, runs)
                cells = [f"{m:.3f} / {p:.2f} ({s:.1f} s) [{'ok' if ok else '--'}]" for m, p, s, ok in rows]
                print(f"noise {noise:.4f} texture {ratio:g}x s{seed}: " + " | ".join(cells), flush=True)
                for name, row in zip(names, rows):
                    medians.setdefault((name, noise), []).append(row[0])
    print("geometric mean of the medians per noise level (px):")
    for name in names:
        vals = [np.exp(np.mean(np.log(medians[(name, noise)]))) for noise in NOISES]
        print(f"  {name:<18} " + "  ".join(f"{noise:.4f}: {v:.3f}" for noise, v in zip(NOISES, vals)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
