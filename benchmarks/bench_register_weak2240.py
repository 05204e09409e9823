"""rc option sets side by side on the issue's 2240 weak-texture pairs, with the edge band apart.

Run (from the repository root)::

    python benchmarks/bench_register_weak2240.py --split train --seeds 4 5 \\
        --runs '{"preset": "weak"}' '{"preset": "weak", "noise_alpha": 100}'

The family's pair (``regdata.family_pair``: 1 % motion, correlation 1/10 of the frame, +-10 %
thinning, noise 0.01 of the line integral) at 2240 x 2240 with the texture at ``--textures``
(0.006, 0.01, 0.02: 0.3 %, 0.5 % and 1 % of the body's line integral, the issue's acceptance
range), each pair made once and registered by rc with every JSON option set of ``--runs`` in
turn, so the times are side by side on one machine. Printed per pair and option set: the median /
95th percentile end-point error inside the body, the median over the band within 100 px of the
scored body's edge and over the rest, the seconds and ``ok``; then the geometric mean of the
medians per option set. ``--oracle`` adds a row per pair: the first option set on ``fixed`` with
the true thinning divided out (``regdata.family_thinning``), the thinning term and its refit off:
what is left when the thinning is known. ``--oracle-mask W`` adds one more: the same with the data term limited (``register``'s ``mask``)
to the body less its outermost ``W`` x the frame. ``--bands`` prints under each row the median
by distance from the scored edge (0-50, 50-100, 100-200, 200-400, beyond 400 px, scaled to the
frame from 2240) with its normal and tangential parts. ``--split train`` (``regdata.TRAIN_SEEDS``)
is where choices are made, ``--split test`` where they are reported (benchmarks/README.md,
sessions 20 and 24).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import _BODY, TEST_SEEDS, TRAIN_SEEDS, Case, _ellipse_r2, family_pair, family_thinning, score

EDGE_PX = 100  # the band the thinning field's confound lives in (README, "The thinning measured in the interior")
BANDS = (0, 50, 100, 200, 400)  # --bands, px at 2240 (bench_register_bound.py's)


def _bands(displacement, truth, mask):
    """The median EPE (normal, tangential) by distance from ``mask``'s edge, as text."""
    import cv2

    n = mask.shape[0]
    dist = cv2.distanceTransform(np.asarray(mask, np.uint8), cv2.DIST_L2, 5)
    gy, gx = np.gradient(cv2.GaussianBlur(dist, (0, 0), 3))
    g = np.hypot(gy, gx) + 1e-9
    e = displacement - truth
    normal = np.abs(e[0] * gy + e[1] * gx) / g
    tangential = np.abs(e[0] * gx - e[1] * gy) / g
    epe = np.hypot(e[0], e[1])
    out = []
    for lo, hi in zip(BANDS, BANDS[1:] + (10**6,)):
        sel = mask & (dist >= lo * n / 2240) & (dist < hi * n / 2240)
        out.append(
            f"{lo}-{hi if hi < 10**6 else ''}: {np.median(epe[sel]):.3f} "
            f"({np.median(normal[sel]):.2f}, {np.median(tangential[sel]):.2f})"
        )
    return "    " + " | ".join(out)


def _row(pair, options, data_mask=None):
    """``(median, p95, edge median, interior median, seconds, ok, field)`` of rc with ``options``."""
    import cv2

    from radiokit.register import register

    f, m, d, mask = pair
    t = time.perf_counter()
    reg = register(f, m, "rc", data_mask, **options)
    seconds = time.perf_counter() - t
    s = score(reg.displacement, d, mask)
    near = cv2.distanceTransform(np.asarray(mask, np.uint8), cv2.DIST_L2, 5) < EDGE_PX
    e = np.sqrt(((reg.displacement - d) ** 2).sum(axis=0))
    edge, inner = e[mask & near], e[mask & ~near]
    out = s["epe_median"], s["epe_p95"], float(np.median(edge)), float(np.median(inner)), seconds, reg.quality.ok
    return out + (reg.displacement,)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=["train", "test"], default="test")
    ap.add_argument("--seeds", type=int, nargs="+", help="seed numbers (default: the split's first two)")
    ap.add_argument("--textures", type=float, nargs="+", default=[0.006, 0.01, 0.02])
    ap.add_argument("--kind", default="thinning", help="the family's intensity change (thinning, gain)")
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--runs", nargs="+", default=['{"preset": "weak"}'], help="rc option sets (JSON)")
    ap.add_argument("--oracle", action="store_true", help="also the first set with the true thinning divided out")
    ap.add_argument(
        "--oracle-mask", type=float, metavar="W", help="and that oracle with the body's outer W x the frame left out"
    )
    ap.add_argument("--bands", action="store_true", help="the median by distance from the edge, normal, tangential")
    args = ap.parse_args(argv)
    pool = TRAIN_SEEDS if args.split == "train" else TEST_SEEDS
    seeds = args.seeds or list(pool[:2])
    if any(s not in pool for s in seeds):
        ap.error(f"--seeds {seeds}: not all {args.split} seeds")
    print(f"{args.size} px, {args.kind}, {args.split} seeds {seeds}: median / p95 (edge {EDGE_PX} px / rest) px, s, ok")
    medians = {}
    for tex in args.textures:
        for seed in seeds:
            case = Case(size=args.size, texture=tex, noise=0.01, corr=0.1, seed=seed, kind=args.kind)
            pair = family_pair(case)
            runs = [(text, pair, json.loads(text), None) for text in args.runs]
            if args.oracle or args.oracle_mask:
                f, m, d, mask = pair
                known = (f / (1 + family_thinning(case)), m, d, mask)  # the open beam's level is 0
                off = dict(json.loads(args.runs[0]), gain=0.0, refit_thinning=False)
                runs.append((f"{args.runs[0]}, true thinning divided out", known, off, None))
                if args.oracle_mask:
                    w = args.oracle_mask
                    inside = _ellipse_r2(args.size, ax=_BODY[0] - w, ay=_BODY[1] - w) < 1
                    runs.append(
                        (f"{args.runs[0]}, true thinning divided out, body's outer {w:g} out", known, off, inside)
                    )
            for text, p, options, data_mask in runs:
                med, p95, edge, inner, sec, ok, field = _row(p, options, data_mask)
                medians.setdefault(text, []).append(med)
                print(
                    f"texture {tex:g} s{seed} {text}: {med:.3f} / {p95:.2f} ({edge:.3f} / {inner:.3f}) "
                    f"{sec:.1f} s {'ok' if ok else '--'}",
                    flush=True,
                )
                if args.bands:
                    print(_bands(field, p[2], p[3]), flush=True)
    print("geometric mean of the medians (px):")
    for text, vals in medians.items():
        print(f"  {text}: {float(np.exp(np.mean(np.log(vals)))):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
