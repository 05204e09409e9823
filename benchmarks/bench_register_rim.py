"""Does gating forward-backward consistency on one-directional structure catch the along-rim slide?

Run (from the repository root), after the benches that cache the fields and the backward runs::

    python benchmarks/bench_register_phantoms.py --out out/phantoms --split train
    python benchmarks/bench_register_inverse.py --source phantoms --out out/phantoms --split train
    python benchmarks/bench_register_rim.py --source phantoms --split train
    python benchmarks/bench_register_flag.py --split train --size 560 --seeds 2 --textureless --skip elastix
    python benchmarks/bench_register_inverse.py --source family --split train --size 560 --seeds 2
    python benchmarks/bench_register_rim.py --source family --split train --size 560 --seeds 2
    python benchmarks/bench_register_turned.py --split train --out out/turned --rim-check   # register(..., rim_check=True)
    python benchmarks/bench_register_rim.py --source turned --split train

The hypothesis (session 52): on a textureless body the trusted failures slide *along* a smooth
rim (tangential error 2-5 px, normal 0.1-0.2 px), which the map credits as observed through the
rim's curvature. Where the observed object is mostly one-directional structure
(``_confidence.one_directional``: the window's smaller eigenvalue under ``1 / WINDOW_REACH^2`` of
the larger, a rim straighter than an arc as tight as the window's cut), the field's tangential
part is the prior's guess and needs a no-truth test (forward-backward, session 48); where texture
makes the windows 2-D the present checks stand. The gate's statistic, ``rim_share``
(``_PairChecks.rim_share``): the share of the checks' observed interior (``obs & inner``; the
observed object when there is no interior) that is one-directional, from the fixed image alone;
the gate opens over ``GATE`` (a half: "mostly"; ``--gate`` to measure others). The test: session
48's forward-backward inconsistency (``bench_register_inverse.py``'s cached rows, the backward run
at full resolution with the result's own method and preset) over ``OBSERVED_PX`` (0.5 px).
``--source turned`` reads ``bench_register_turned.py --rim-check``'s results, registered by
``register(..., rim_check=True)``, which runs the check itself (an option since session 52, not the
default).

Printed: the statistic's spread on the trusted failed and good results, the gate's open rate,
and the confusion before / after (failed flagged, good trusted) per method and over all; the
backward run's time where the gate opens. Failed: median EPE > max(1 px, half the identity's);
good: <= 0.5 px.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_inverse import LINE, auc, status  # the same line and scoring as session 48's bench

GATE = 0.5  # of the observed interior: "mostly" (radiokit.register._RIM_GATE)


def _share(fixed, moving):
    from radiokit.register import _check, _PairChecks

    t = time.perf_counter()
    p = _PairChecks(*_check(fixed, moving, None))
    obs = p.obs.mean() if p.obs.size else float("nan")
    t1 = time.perf_counter()
    share = p.rim_share
    return share, float(obs), time.perf_counter() - t1, t1 - t


def phantom_rows(out, split):
    import bench_register_phantoms as P

    rows = json.loads((out / f"rows-{split}.json").read_text())
    shares = {}
    for seed in sorted({r["seed"] for r in rows}):
        fixed, moving, *_ = P.make_pair(seed)
        shares[str(seed)] = _share(fixed, moving)
        print(f"{seed} rim_share {shares[str(seed)][0]:.2f} ({shares[str(seed)][2]:.2f} s)", flush=True)
    res = [
        dict(
            case=str(r["seed"]), method=r["preset"], epe=r["epe_median"], identity=r["identity"], ok=r["quality"]["ok"]
        )
        for r in rows
    ]
    return res, shares


def family_rows(out, split, size, seeds):
    import bench_register_flag as F

    rows = json.loads((out / "rows.json").read_text())
    shares = {}
    for label, _, thunk in F.pairs(split, size, seeds, ["seed-breast", "pva-phantom"]):
        if label in shares or not any(r["case"] == label for r in rows):
            continue
        fixed, moving, _, _ = thunk()
        shares[label] = _share(fixed, moving)
        print(f"{label} rim_share {shares[label][0]:.2f} ({shares[label][2]:.2f} s)", flush=True)
    res = [
        dict(case=r["case"], method=r["method"], epe=r["epe_median"], identity=r["identity"], ok=r["ok"])
        for r in rows
        if r["method"] != "identity"
    ]
    return res, shares


def report(rows, shares, fb, gate, line):
    for r in rows:
        r["status"] = status(r["epe"], r["identity"])
        r["share"] = shares[r["case"]][0]
        r["open"] = r["share"] > gate
        f = fb.get((r["case"], r["method"]))
        r["fb"] = f["fb"] if f else float("nan")
        r["fb_s"] = f["backward_seconds"] if f else float("nan")
        r["after"] = r["ok"] and not (r["open"] and r["fb"] > line)
    tr = [r for r in rows if r["ok"]]
    for s in ("failed", "good"):
        v = np.array([r["share"] for r in tr if r["status"] == s])
        if v.size:
            print(f"trusted {s}: {v.size}, rim_share min {v.min():.2f} median {np.median(v):.2f} max {v.max():.2f}")
    fv = np.array([r["share"] for r in tr if r["status"] == "failed"])
    gv = np.array([r["share"] for r in tr if r["status"] == "good"])
    if fv.size and gv.size:
        print(f"AUC of rim_share over the trusted results: {auc(fv, gv):.2f}")
    opened = [r for r in tr if r["open"]]
    secs = np.array([r["fb_s"] for r in opened if np.isfinite(r["fb_s"])])
    print(
        f"gate open on {len(opened)}/{len(tr)} trusted results ({len({r['case'] for r in opened})}/{len(shares)} pairs); "
        + (f"backward run median {np.median(secs):.2f} s, max {secs.max():.2f} s" if secs.size else "no backward run")
    )
    gt = np.array([v[2] for v in shares.values()])
    print(f"the gate's own statistic: median {np.median(gt):.3f} s, max {gt.max():.3f} s")
    print(f"\n| method | before: failed flagged, good trusted | after (gate > {gate:g}, fb > {line:g} px) |")
    print("|---|---|---|")
    for m in sorted({r["method"] for r in rows}) + ["all"]:
        rs = [r for r in rows if m in ("all", r["method"])]
        fl = [r for r in rs if r["status"] == "failed"]
        gd = [r for r in rs if r["status"] == "good"]
        b = f"{sum(not r['ok'] for r in fl)}/{len(fl)}, {sum(r['ok'] for r in gd)}/{len(gd)}"
        a = f"{sum(not r['after'] for r in fl)}/{len(fl)}, {sum(r['after'] for r in gd)}/{len(gd)}"
        print(f"| {m} | {b} | {a} |")
    print("\nTrusted failures, and results the gate changes:")
    for r in sorted(rows, key=lambda r: (r["case"], r["method"])):
        if r["ok"] and (r["status"] == "failed" or r["after"] != r["ok"]):
            print(
                f"- {r['case']} {r['method']} ({r['status']}): EPE {r['epe']:.2f}, rim_share {r['share']:.2f}, "
                f"fb {r['fb']:.2f} -> {'trusted' if r['after'] else 'flagged'}"
            )
    return rows


def turned(out, split):
    """``bench_register_turned.py``'s results (registered by ``register()``, which runs the check):
    before = the other checks' verdict (a result the check flagged was trusted by them)."""
    import bench_register_turned as T

    cache = json.loads((out / "results.json").read_text())
    res = {str(seed): cache[str(seed)] for seed in T.SEEDS[split] if str(seed) in cache}
    print("| preset | before: failed flagged, good trusted | after | gate open (trusted) | backward s median / max |")
    print("|---|---|---|---|---|")
    for preset in ("auto", "silent"):
        rs = [r[preset] | {"identity": r["identity"], "label": r["label"]} for r in res.values() if preset in r]
        for r in rs:
            r["status"] = status(r["epe"], r["identity"])
            r["before"] = r["ok"] or r["rim_flagged"]
        fl = [r for r in rs if r["status"] == "failed"]
        gd = [r for r in rs if r["status"] == "good"]
        opened = [r for r in rs if r["before"] and r["rim_seconds"] > 0]
        secs = np.array([r["rim_seconds"] for r in opened]) if opened else np.array([np.nan])
        b = f"{sum(not r['before'] for r in fl)}/{len(fl)}, {sum(r['before'] for r in gd)}/{len(gd)}"
        a = f"{sum(not r['ok'] for r in fl)}/{len(fl)}, {sum(r['ok'] for r in gd)}/{len(gd)}"
        print(
            f"| {preset} | {b} | {a} | {len(opened)}/{sum(r['before'] for r in rs)} | "
            f"{np.median(secs):.2f} / {np.max(secs):.2f} |"
        )
        for r in rs:
            if r["rim_flagged"] or (r["before"] and r["status"] == "failed"):
                print(
                    f"- {preset} {r['label']} ({r['status']}): EPE {r['epe']:.2f}, rim_share {r['rim_share']:.2f}, "
                    f"fb {r['inconsistency']:.2f} -> {'trusted' if r['ok'] else 'flagged'}"
                )
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", choices=("phantoms", "family", "turned"), required=True)
    ap.add_argument("--split", choices=("train", "test"), default="train")
    ap.add_argument("--out", type=Path, default=None, help="the source bench's cache")
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--gate", type=float, default=GATE)
    ap.add_argument("--line", type=float, default=LINE)
    a = ap.parse_args(argv)
    from radiokit.register import load_methods

    load_methods()
    if a.source == "turned":
        return turned(a.out or Path("out/turned"), a.split)
    if a.source == "phantoms":
        out = a.out or Path("out/phantoms")
        rows, shares = phantom_rows(out, a.split)
    else:
        out = a.out or Path(f"out/bench_register_flag/{a.split}-{a.size}")
        rows, shares = family_rows(out, a.split, a.size, a.seeds)
    inv = json.loads((out / f"inverse-{a.source}-{a.split}.json").read_text())
    fb = {(r["case"], r["method"]): r for r in inv}
    rows = report(rows, shares, fb, a.gate, a.line)
    (out / f"rim-{a.source}-{a.split}.json").write_text(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
