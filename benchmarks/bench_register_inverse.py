"""Does forward-backward (inverse) consistency tell a trusted wrong field from a right one?

Run (from the repository root), after the benches that cache the fields::

    python benchmarks/bench_register_phantoms.py --out out/phantoms --split train
    python benchmarks/bench_register_inverse.py --source phantoms --out out/phantoms --split train
    python benchmarks/bench_register_flag.py --split train --size 560 --seeds 2 --textureless --skip elastix
    python benchmarks/bench_register_inverse.py --source family --split train --size 560 --seeds 2

The hypothesis (session 48): a field the images determine is found from either side, so the
field registering ``fixed`` onto ``moving`` (``e``) undoes the result's (``d``):
``d(x) + e(x + d(x)) = 0``; where the result is the regulariser's guess, or a local minimum, the
backward run guesses again and need not land on the inverse. The statistic: the median over the
object as the flag sees it (``register._PairChecks``: the object, binned by the checks' ``k``)
of ``|d(x) + e(x + d(x))|`` (full-resolution px). The backward run is the result's own method and
options at full resolution (an ``auto`` result: the configuration it returned); only results the
flag trusts are run backward (the check could only flag). A backward run binned to 60 000 px
(cheap at 2240) was tried on the phantom training rows and read right fields 1-1.6 px
inconsistent (its own error): not a judge.

Printed: the AUC (probability a failed result reads higher than a good one) over the trusted
results, and the confusion of "flag a trusted result whose inconsistency exceeds ``--line``"
(0.5 px: ``_confidence.OBSERVED_PX``, the map's own line, not chosen on these rows). Failed:
median EPE > max(1 px, half the identity's); good: <= 0.5 px. Backward fields are cached in
``OUT/inverse``; the rows go to ``OUT/inverse-SOURCE-SPLIT.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

LINE = 0.5  # px: _confidence.OBSERVED_PX


def auc(failed, good) -> float:
    """The probability that a failed result reads higher than a good one (ties count half)."""
    f, g = np.asarray(failed, float), np.asarray(good, float)
    return float(np.mean((f[:, None] > g[None, :]) + 0.5 * (f[:, None] == g[None, :])))


def status(epe, ident):
    if epe > max(1.0, 0.5 * ident):
        return "failed"
    return "good" if epe <= 0.5 else "between"


def inconsistency(d, e, p):
    """Median over the checks' object (``p``: ``register._PairChecks``) of ``|d + e o (id + d)|``."""
    from radiokit.register import _bin

    rr, cc = np.mgrid[0 : d.shape[1], 0 : d.shape[2]].astype(np.float32)
    at = [rr + d[0], cc + d[1]]
    fb = np.hypot(
        d[0] + ndimage.map_coordinates(e[0], at, order=1, mode="nearest"),
        d[1] + ndimage.map_coordinates(e[1], at, order=1, mode="nearest"),
    )
    if p.k > 1:
        fb = _bin(fb[None], p.k)[0]
    obj = p.ob.object
    return float(np.median(fb[obj])) if obj.any() else float("nan")


def backward(cache, key, method, opts, fixed, moving):
    """``(e, ok, seconds)``: ``fixed`` registered onto ``moving`` (cached under ``key``)."""
    from radiokit.register import METHODS, _check

    path = cache / f"{key}.npz"
    if path.exists():
        z = np.load(path)
        return z["e"], bool(z["ok"]), float(z["seconds"])
    from radiokit.register import Quality, Registration, _assess

    f, m, _ = _check(moving, fixed, None)
    t = time.perf_counter()
    e, info = METHODS[method](f, m, None, **opts)
    sec = time.perf_counter() - t
    reg = Registration(np.ascontiguousarray(e, np.float32), method, Quality(), dict(opts))
    _assess(reg, f, m, None, info, sec)
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, e=reg.displacement, ok=reg.quality.ok, seconds=sec)
    return reg.displacement, reg.quality.ok, sec


def phantom_rows(out, split):
    import bench_register_phantoms as P

    from radiokit.register import _check, _PairChecks, load_methods

    load_methods()
    rows = json.loads((out / f"rows-{split}.json").read_text())
    res = []
    for seed in sorted({r["seed"] for r in rows}):
        mine = [r for r in rows if r["seed"] == seed and r["quality"]["ok"]]
        if not mine:
            continue
        fixed, moving, *_ = P.make_pair(seed)
        p = _PairChecks(*_check(fixed, moving, None))
        for r in mine:
            use = r["preset"] if r["preset"] != "auto" else r["returned"]
            name = "auto-plain" if r["preset"] == "auto" and use == "default" else use
            d = np.load(out / "fields" / f"{seed}-{name}.npz")["d"]
            e, ok2, sec = backward(out / "inverse", f"{seed}-{name}", "rc", P._options(name), fixed, moving)
            res.append(
                dict(case=str(seed), method=r["preset"], epe=r["epe_median"], identity=r["identity"],
                     fb=inconsistency(d, e, p), backward_ok=ok2, backward_seconds=sec)
            )  # fmt: skip
            print(f"{seed} {r['preset']:8s} EPE {r['epe_median']:.2f} inconsistency {res[-1]['fb']:.2f}", flush=True)
    return res


def family_rows(out, split, size, seeds):
    import bench_register_flag as F
    from bench_register import _method_of, configs

    from radiokit.register import _check, _PairChecks, load_methods
    from radiokit.register._auto import EXTEND

    load_methods()
    cfgs = dict(configs(), **{"rc-extend": {"extend": EXTEND}})
    rows = json.loads((out / "rows.json").read_text())
    res, seen = [], set()
    for label, _, thunk in F.pairs(split, size, seeds, ["seed-breast", "pva-phantom"]):
        mine = [r for r in rows if r["case"] == label and r["method"] != "identity" and r["ok"]]
        if not mine or label in seen:
            continue
        seen.add(label)
        fixed, moving, _, _ = thunk()
        p = _PairChecks(*_check(fixed, moving, None))
        for r in mine:
            use = r.get("returned") or r["method"]
            d = np.load(F._cache_path(out, label, use))["d"]
            key = F._cache_path(out, label, use).stem
            e, ok2, sec = backward(out / "inverse", key, _method_of(use), cfgs[use], fixed, moving)
            res.append(
                dict(case=label, method=r["method"], epe=r["epe_median"], identity=r["identity"],
                     fb=inconsistency(d, e, p), backward_ok=ok2, backward_seconds=sec)
            )  # fmt: skip
        print(
            f"  {label}: " + " ".join(f"{x['method']} {x['epe']:.2f}/{x['fb']:.2f}" for x in res if x["case"] == label)
        )
    return res


def report(rows, line):
    """The AUC over the trusted results and the confusion of the rule, per method and over all."""
    for r in rows:
        r["status"] = status(r["epe"], r["identity"])
    f = np.array([r["fb"] for r in rows if r["status"] == "failed"])
    g = np.array([r["fb"] for r in rows if r["status"] == "good"])
    if f.size and g.size:
        print(f"\ntrusted: {f.size} failed, {g.size} good; AUC {auc(f, g):.2f}")
    print(f"\n| method | trusted failures flagged at {line} px | trusted good flagged |")
    print("|---|---|---|")
    for m in sorted({r["method"] for r in rows}) + ["all"]:
        rs = [r for r in rows if m in ("all", r["method"])]
        tf = [r for r in rs if r["status"] == "failed"]
        tg = [r for r in rs if r["status"] == "good"]
        print(f"| {m} | {sum(r['fb'] > line for r in tf)}/{len(tf)} | {sum(r['fb'] > line for r in tg)}/{len(tg)} |")
    print("\nTrusted failures, and good results over the line:")
    for r in sorted(rows, key=lambda r: -r["fb"]):
        if r["status"] == "failed" or (r["status"] == "good" and r["fb"] > line):
            print(f"- {r['case']} {r['method']} ({r['status']}): EPE {r['epe']:.2f}, inconsistency {r['fb']:.2f} px")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", choices=("phantoms", "family"), required=True)
    ap.add_argument("--split", choices=("train", "test"), default="train")
    ap.add_argument("--out", type=Path, default=None, help="the source bench's cache")
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--line", type=float, default=LINE)
    a = ap.parse_args(argv)
    if a.source == "phantoms":
        out = a.out or Path("out/phantoms")
        rows = phantom_rows(out, a.split)
    else:
        out = a.out or Path(f"out/bench_register_flag/{a.split}-{a.size}")
        rows = family_rows(out, a.split, a.size, a.seeds)
    (out / f"inverse-{a.source}-{a.split}.json").write_text(json.dumps(rows))
    report(rows, a.line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
