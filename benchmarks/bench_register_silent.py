"""A silent body at full resolution: ``silent`` against ``silent`` registered binned to 0.4 Mpx.

Run (from the repository root)::

    python benchmarks/bench_register_silent.py [--size 2240] [--split test] [--seeds 2]

For the family's pairs a silent body poses (``regdata.Case``: the physical motion without
texture and with texture 0.3x the noise; the random motion, correlation 1/10, without texture),
prints the median / p95 EPE inside the body and the time of ``silent`` as the preset runs it
(unbinned) and with ``bin_pixels=400_000`` (the pair area-averaged by 4 at 2240), and what
``auto`` returns (``benchmarks/README.md``, "A silent body registered at 0.4 Mpx").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair, score

RUNS = (("silent", "silent", {}), ("silent binned", "silent", {"bin_pixels": 400_000}), ("auto", "auto", {}))
PAIRS = (("physical", 0.0), ("physical", 0.003), ("random", 0.0))


def main(argv=None) -> int:
    from radiokit.register import register

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--split", choices=("train", "test"), default="test")
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args(argv)
    seeds = (TRAIN_SEEDS if args.split == "train" else TEST_SEEDS)[: args.seeds]
    for s in seeds:
        for motion, texture in PAIRS:
            case = Case(
                size=args.size, texture=texture, corr=0.0 if motion == "physical" else 0.1, motion=motion, seed=s
            )
            f, m, d, mask = family_pair(case)
            line = f"{case.label()}: identity {score(0 * d, d, mask)['epe_median']:.2f}"
            for name, preset, opts in RUNS:
                t0 = time.perf_counter()
                reg = register(f, m, "rc", preset=preset, **opts)
                sec = time.perf_counter() - t0
                sc = score(reg.displacement, d, mask)
                used = f" ({reg.options.get('preset')})" if preset == "auto" else ""
                line += f" | {name} {sc['epe_median']:.2f} / {sc['epe_p95']:.2f}{used} {sec:.1f} s"
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
