"""Can ``quality.ok`` be trusted without the truth? The flag's confusion table over the family.

Run (from the repository root)::

    python benchmarks/bench_register_flag.py --split test --size 560 --seeds 2
    python benchmarks/bench_register_flag.py --split train --size 560 --seeds 4 --sweep   # to choose thresholds

Every method of ``bench_register.FAMILY_METHODS`` (rc, rc fast, rc weak, rc weak-fast, elastix
and DIS on high-passed images), rc silent and silent-fast, and ``preset="auto"`` / ``"auto-fast"``
(``rc-auto``, ``rc-auto-fast``: composed from the cached plain, weak and silent results by
``register_auto``'s own rule, not registered again) on every pair of ``regdata.family(split, size, grid="all")`` (and, on the test split, the
simulated pairs of both scene presets, noisy, as in ``bench_register``'s part 3). Each result is
cached (``--out``, the field and the method's ``info``), so the flag can be re-assessed
(``radiokit.register._assess``) as its rule changes without registering again (``--reassess``
is the default once a result is cached; ``--fresh`` registers again).

Prints, per method and over all: failed = median EPE inside the body > max(1 px, half the
identity's), flagged = ``ok`` False (the issue wants >= 95 %); good = median EPE <= 0.5 px,
trusted = ``ok`` True (>= 90 %); and the reasons given for the good results that were flagged
and the failed ones that were trusted. With ``--textureless`` also the truly textureless pairs'
median EPE where the confidence map says observed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_register import FAMILY_METHODS, _method_of, configs, confusion
from regdata import family, family_pair, score, sim_pair


def pairs(split, size, n_seeds, sim_presets):
    """``(label, meta, thunk)`` for every pair of the split (the simulated pairs only on test)."""
    for c in family(split, size, grid="all", n_seeds=n_seeds):
        yield c.label(), dict(t2n=c.t2n, texture=c.texture), (lambda c=c: family_pair(c))
    if split == "test":
        for p in sim_presets:
            yield (
                f"sim {p} {size} noisy",
                dict(t2n=None, texture=None),
                (lambda p=p: sim_pair(p, moving_step=-1, noisy=True, size=size)),
            )


def _cache_path(out, label, name):
    return out / (hashlib.sha1(f"{label}|{name}".encode()).hexdigest()[:16] + ".npz")


def registered(out, label, name, opts, fixed, moving, fresh=False):
    """The method's ``(displacement, info, seconds)``, from the cache or registered now."""
    from radiokit.register import METHODS, _check

    path = _cache_path(out, label, name)
    if path.exists() and not fresh:
        z = np.load(path, allow_pickle=False)
        info = json.loads(str(z["info"]))
        # caches written before session 28 lack rc's still_moving_px and finest_binning (_assess
        # reads them): the message said the first ("still moving: ..." is _bspline._converged's
        # alone), the options' pyramid gives the second
        if not info.get("converged", True) and str(info.get("message", "")).startswith("still moving:"):
            from radiokit.register import _bspline as B

            info.setdefault("still_moving_px", float(info["message"].split()[2]))
            o = B._options(opts.get("preset", "default"), {k: v for k, v in opts.items() if k != "preset"})
            info.setdefault("finest_binning", B._pyramid(fixed.shape, o)[-1][0])
        return z["d"], info, float(z["seconds"])
    method = _method_of(name)
    f, m, _ = _check(fixed, moving, None)
    t = time.perf_counter()
    d, info = METHODS[method](f, m, None, **opts)
    seconds = time.perf_counter() - t
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool))}
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, d=np.asarray(d, np.float32), info=json.dumps(info), seconds=seconds)
    tmp.replace(path)
    return np.asarray(d, np.float32), info, seconds


def assess(name, opts, fixed, moving, d, info, seconds):
    """``register()``'s assessment of a cached field: the :class:`Registration` with its quality
    and confidence map, exactly as ``register()`` would return it."""
    from radiokit.register import Quality, Registration, _assess, _check

    method = _method_of(name)
    f, m, _ = _check(fixed, moving, None)
    reg = Registration(np.ascontiguousarray(d, np.float32), method, Quality(), dict(opts))
    _assess(reg, f, m, None, info, seconds)
    return reg


# preset="auto" as register_auto composes it: the plain run (``auto``'s with rc's ``extend``,
# _auto.EXTEND, registered for that alone and not tabled), and its weak or silent fallback
# (configuration name's suffix)
AUTO = {"rc-auto": ("auto", "rc-extend", ""), "rc-auto-fast": ("auto-fast", "rc-fast", "-fast")}
EXTRA = ("rc-silent", "rc-silent-fast", "rc-extend")
_UNTABLED = ("rc-extend",)


def _auto_choice(name, fixed, regs):
    """The configuration ``register(..., preset=AUTO[name][0])`` returns, from the assessed
    results ``regs`` (configuration -> Registration), by ``register_auto``'s own rule (faithful
    in frames of at most the checks' ~0.4 Mpx, such as the 560 family, where the plain run is
    never stopped early: ``_auto.ABANDON``)."""
    from radiokit.register._auto import AUTO_PRESETS, checks_silent, choose, returned, settled, straight_to_weak

    auto, plain, _ = AUTO[name]
    fallback = choose(fixed, auto).preset
    if straight_to_weak(auto, "rc", fallback, fixed.shape, {"preset": auto}, False):
        return "rc-" + fallback  # its plain run is not run at all (frames over 1.6 Mpx)
    if settled(regs[plain].quality) and not checks_silent(auto, regs[plain].quality, fallback):  # as register_auto
        return plain
    retry = regs.get("rc-" + fallback)  # absent only when nothing is retried (names: the presets')
    use = returned(auto, regs[plain].quality, fallback, retry.quality if retry is not None else None)
    return plain if use == AUTO_PRESETS[auto][0] else "rc-" + use


def _row(meta, label, name, reg, truth, mask, ident, sec):
    e = np.hypot(*(reg.displacement - truth))
    obs = (reg.confidence >= 0.5) & mask
    return dict(
        meta,
        case=label,
        method=name,
        epe_median=float(np.median(e[mask])),
        identity=ident,
        ok=bool(reg.quality.ok),
        reason=reg.quality.reason,
        seconds=sec,
        observed=float(obs.sum() / mask.sum()),
        misaligned=reg.quality.misaligned_fraction,
        kept=reg.quality.excess_kept,
        step=reg.quality.residual_motion,
        epe_observed=float(np.median(e[obs])) if obs.sum() > 50 else None,
    )


def run(args):
    from radiokit.register import load_methods

    load_methods()
    from radiokit.register._auto import EXTEND

    cfgs = dict(configs(), **{"rc-extend": {"extend": EXTEND}})
    names = [n for n in FAMILY_METHODS + EXTRA if n in cfgs and n.split("+")[0] not in args.skip]
    methods = [(n, cfgs[n]) for n in names]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, inputs = [], []
    for label, meta, thunk in pairs(args.split, args.size, args.seeds, args.sim):
        fixed, moving, truth, mask = thunk()
        ident = score(np.zeros_like(truth), truth, mask)["epe_median"]
        rows.append(dict(meta, case=label, method="identity", epe_median=ident, identity=ident, ok=None))
        inputs += [None] if args.sweep else []
        regs, secs = {}, {}
        for name, opts in methods:
            d, info, sec = registered(args.out, label, name, opts, fixed, moving, args.fresh)
            reg = assess(name, opts, fixed, moving, d, info, sec)
            regs[name], secs[name] = reg, sec
            if args.sweep:
                inputs.append(dict(rule_inputs(fixed, moving, d), preset=opts.get("preset")))
            if name in _UNTABLED:
                continue
            rows.append(_row(meta, label, name, reg, truth, mask, ident, sec))
            if args.sweep:
                rows[-1]["quality"] = reg.quality
        for name, (_, plain, suffix) in AUTO.items():
            if {plain, "rc-weak" + suffix, "rc-silent" + suffix} <= set(regs) and not args.sweep:
                use = _auto_choice(name, fixed, regs)
                sec = secs[plain] + (secs[use] if use != plain else 0.0)
                rows.append(dict(_row(meta, label, name, regs[use], truth, mask, ident, sec), returned=use))
        print(
            f"  {label:<62} "
            + " ".join(
                f"{r['method']} {r['epe_median']:.2f}{'' if r['ok'] in (None, True) else '!'}"
                for r in rows
                if r["case"] == label and r["method"] != "identity"
            ),
            flush=True,
        )
    return rows, methods, inputs


def _pct(a, b):
    """``a / b`` in per cent with its exact (Clopper-Pearson) 95 % binomial interval: the
    tables count a few dozen good results, so a rate is known to +-5-10 points at best."""
    if not b:
        return "-"
    from scipy.stats import binomtest

    ci = binomtest(a, b).proportion_ci(0.95, method="exact")
    return f"{100 * a / b:.0f} %, CI {100 * ci.low:.0f}-{100 * ci.high:.0f} %"


def table(rows, methods) -> str:
    """The confusion table (markdown): all methods (those of FAMILY_METHODS, as in earlier
    tables), then each one."""
    lines = [
        "| results | failed | flagged (ok False; 95 % CI) | good | trusted (ok True; 95 % CI) |",
        "|---|---|---|---|---|",
    ]
    family = [r for r in rows if r["method"] in FAMILY_METHODS or r["method"] == "identity"]
    for tag, sel in [("all methods", family)] + [
        (n, [r for r in rows if r["method"] == n]) for n, _ in methods if n not in _UNTABLED
    ]:
        c = confusion(sel)
        lines.append(
            f"| {tag} ({c['n']}) | {c['failed']} | {c['failed_flagged']} "
            f"({_pct(c['failed_flagged'], c['failed'])}) | {c['good']} | {c['good_ok']} "
            f"({_pct(c['good_ok'], c['good'])}) |"
        )
    return "\n".join(lines)


def misses(rows) -> list[str]:
    """The good results flagged and the failed ones trusted, with the reason or the numbers."""
    out = []
    for r in rows:
        if r["method"] == "identity":
            continue
        failed = r["epe_median"] > max(1.0, 0.5 * r["identity"])
        if r["epe_median"] <= 0.5 and not r["ok"]:
            out.append(f"  good, flagged: {r['method']:<11} {r['case']:<58} {r['epe_median']:.2f} px: {r['reason']}")
        elif failed and r["ok"]:
            out.append(
                f"  failed, trusted: {r['method']:<11} {r['case']:<58} {r['epe_median']:.2f} px "
                f"(identity {r['identity']:.2f}; observed {r['observed']:.2f}, "
                f"step {r['step']:.2f} px, misaligned {r['misaligned']:.2f})"
            )
    return out


_MAP_CELL = re.compile(r"tex([0-9.e-]+)/noise0\.01\(g\) L1/(\d+) a1% t[+-]10% log s(\d+)$")
MAP_METHODS = ("rc-auto", "rc-auto-fast", "rc-weak", "elastix+hp", "dis+hp")
PEERS = ("elastix+hp", "dis+hp")


def map_table(rows) -> list[str]:
    """The map's cells (texture/noise x correlation length, ``regdata.family(grid="map")``):
    the mean over seeds of each method's median EPE, the identity's beside, and whether rc's
    default (``auto``) is no worse than the best tuned peer where that peer stays under 1 px
    (the issue's line; "no worse": within 10 % or 0.05 px, the seeds' spread)."""
    cells = {}
    for r in rows:
        hit = _MAP_CELL.search(r["case"])
        if hit is None or (r["method"] not in MAP_METHODS + ("identity",)):
            continue
        key = (float(hit.group(1)) / 0.01, int(hit.group(2)))
        cells.setdefault(key, {}).setdefault(r["method"], {})[hit.group(3)] = r["epe_median"]
    out = ["| texture/noise | corr | identity | " + " | ".join(MAP_METHODS) + " | best peer < 1 px: auto no worse? |"]
    out.append("|" + "---|" * (len(MAP_METHODS) + 4))
    for (t2n, corr), by in sorted(cells.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
        mean = {m: float(np.mean(list(v.values()))) for m, v in by.items()}
        best = min((mean[p] for p in PEERS if p in mean), default=float("inf"))
        auto = mean.get("rc-auto", float("inf"))
        verdict = (
            "-" if best >= 1.0 else ("yes" if auto <= max(1.1 * best, best + 0.05) else f"NO ({auto / best:.1f}x)")
        )
        vals = " | ".join(f"{mean[m]:.2f}" if m in mean else "-" for m in MAP_METHODS)
        out.append(f"| {t2n:g} | 1/{corr} | {mean.get('identity', float('nan')):.2f} | {vals} | {verdict} |")
    return out


def textureless(rows) -> list[str]:
    """Truly textureless pairs: the observed share of the body and the median EPE there."""
    out = []
    for r in rows:
        if r["method"] != "identity" and r.get("texture") == 0.0:
            eo = "-" if r["epe_observed"] is None else f"{r['epe_observed']:.2f}"
            out.append(
                f"  {r['method']:<11} {r['case']:<58} body {r['epe_median']:.2f} px, observed "
                f"{100 * r['observed']:.0f} % of the body, EPE there {eo} px, ok {r['ok']}"
            )
    return out


def rule_inputs(fixed, moving, d, stride=2):
    """What ``register()``'s flag rule reads, per object pixel (every ``stride``-th row and
    column of the assessment grid), before its thresholds: the Cramer-Rao bound of one window
    (observed where ``bound_scale x b1 <= 0.5 px``), over the object and over its interior,
    the residual's Gauss-Newton step
    (``_confidence.residual_motion``), the residual's excess over the noise after registering,
    and that excess against a quarter of the excess before (misaligned where both exceed their
    lines). The same steps as ``radiokit.register._observed`` and ``_misaligned`` (``sweep``
    checks that the present thresholds give ``ok`` as ``register()`` does)."""
    from radiokit.register import _STEP_WINDOW, _WINDOW, _assess_binning, _bin, _check, _interior, warp
    from radiokit.register import _confidence as C

    f, m, _ = _check(fixed, moving, None)
    k = _assess_binning(f.size)
    d = np.asarray(d, np.float32)
    if k > 1:
        f, m, d = _bin(f, k), _bin(m, k), _bin(d, k) / np.float32(k)
    w, d = np.nan_to_num(warp(m, d)), np.nan_to_num(d)
    ob = C.observability(f, _WINDOW, None, bound_scale=k)  # full-resolution px, as register()
    sig = C.noise_map(f, _WINDOW)
    factor = 1.0 + C.interpolation_variance(d, _WINDOW)
    after = C.consistency(f, w, _WINDOW, sig, factor) - 1.0
    before = C.consistency(f, m, _WINDOW, sig) - 1.0
    step = k * C.residual_motion(f, w, _STEP_WINDOW)  # full-resolution px, as register() reports it
    sel = ob.object[::stride, ::stride]
    inner = _interior(ob.object)
    inner = inner if inner.any() else ob.object
    return dict(
        b1=ob.bound_px[::stride, ::stride][sel],
        b1_inner=ob.bound_px[::stride, ::stride][inner[::stride, ::stride]],
        step=step[::stride, ::stride][sel],
        after=after[::stride, ::stride][sel],
        gate=(after * factor - 0.5 * np.maximum(before, 0))[::stride, ::stride][sel],
        n_object=int(ob.object.sum()) * k * k,
    )


def rule_ok(x, q, bound_scale, min_observed, max_step, excess, max_misaligned, max_folds):
    """``ok`` of one result under the given thresholds (``x`` from :func:`rule_inputs`, ``q``
    the result's ``Quality`` for the reasons the thresholds do not touch). Subsampled, so a
    result near a threshold may differ from ``register()``'s."""
    from radiokit.register import _BODY_SCALE_PRESETS, _BODY_SCALE_PX

    if "did not find the motion" in q.reason:  # excess_kept's rule, not swept (session 18)
        return False
    if q.rc_after > q.rc_before or not q.converged or q.folds > max_folds * max(x["n_object"], 1):
        return False
    obs = x["b1"] * bound_scale <= 0.5
    if not obs.size:
        return False
    # a silent interior is trusted when the field is body-scale (register()'s waiver, which it
    # grants only to the silent presets' fields; its statistic is computed only below
    # register()'s own interior line, NaN elsewhere: not waived)
    waived = q.body_scale <= _BODY_SCALE_PX and x.get("preset") in _BODY_SCALE_PRESETS
    if np.mean(x["b1_inner"] * bound_scale <= 0.5) < min_observed and not waived:
        return False
    if np.median(x["step"][obs]) > max_step:
        return False
    return not (np.mean((x["after"][obs] > excess) & (x["gate"][obs] > 0)) > max_misaligned)


SWEEP = dict(
    bound_scale=(0.5, 0.75, 1.0, 1.5, 2.0, 4.0),
    min_observed=(0.3, 0.4, 0.5, 0.6, 0.7),  # of the interior
    max_step=(0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5),
    excess=(0.1, 0.2),
    max_misaligned=(0.2, 0.5, 1.01),
)


def sweep(rows, inputs, min_flagged=0.97):
    """The confusion over a grid of the rule's thresholds (``SWEEP``): the rules that flag at
    least ``min_flagged`` of the failed results, best trusted share of the good first."""
    import itertools

    from radiokit.register import _EXCESS, _MAX_FOLDS, _MAX_MISALIGNED, _MAX_RESIDUAL_MOTION, _MIN_OBSERVED

    res = [(r, x) for r, x in zip(rows, inputs) if x is not None]
    failed = [(r, x) for r, x in res if r["epe_median"] > max(1.0, 0.5 * r["identity"])]
    good = [(r, x) for r, x in res if r["epe_median"] <= 0.5]
    now = (1.0, _MIN_OBSERVED, _MAX_RESIDUAL_MOTION, _EXCESS, _MAX_MISALIGNED)
    same = sum(rule_ok(x, r["quality"], *now, _MAX_FOLDS) == r["ok"] for r, x in res)
    out = [f"  the present thresholds {now} reproduce register()'s ok for {same}/{len(res)} results (subsampled)"]
    table = []
    for combo in itertools.product(*SWEEP.values()):
        ff = sum(not rule_ok(x, r["quality"], *combo, _MAX_FOLDS) for r, x in failed)
        gt = sum(rule_ok(x, r["quality"], *combo, _MAX_FOLDS) for r, x in good)
        table.append((gt / max(len(good), 1), ff / max(len(failed), 1), combo, ff, gt))
    table.sort(key=lambda t: (-(t[1] >= min_flagged), -t[0], -t[1]))
    for gt_rate, ff_rate, combo, ff, gt in table[:15]:
        out.append(
            f"  {dict(zip(SWEEP, combo))}: failed flagged {ff}/{len(failed)} ({100 * ff_rate:.1f} %), "
            f"good trusted {gt}/{len(good)} ({100 * gt_rate:.1f} %)"
        )
    return out


def textureless_check(size, seed=1000):
    """A truly textureless test pair (correlation 1/10): the truth and the identity planted as
    results (does the map's observed region carry the motion?), then rc and rc fast: the observed
    share of the body, the median EPE there, the misaligned share and ``ok``."""
    from regdata import Case

    from radiokit.register import register

    fixed, moving, truth, mask = family_pair(Case(size=size, texture=0.0, noise=0.01, corr=0.1, seed=seed))
    print(f"textureless {size} px, test seed {seed}: identity {score(0 * truth, truth, mask)['epe_median']:.2f} px")
    for tag, name, opts, field in (
        ("truth planted", "planted", {}, truth),
        ("identity planted", "planted", {}, 0 * truth),
        ("rc", "rc", {}, None),
        ("rc fast", "rc", {"preset": "fast"}, None),
    ):
        t = time.perf_counter()
        if field is None:
            reg = register(fixed, moving, name, **opts)
        else:
            reg = assess(name, opts, fixed, moving, field, {}, 0.0)
        obs = (reg.confidence >= 0.5) & mask
        e = np.hypot(*(reg.displacement - truth))
        there = float(np.median(e[obs])) if obs.any() else float("nan")
        print(
            f"  {tag:<17} body {np.median(e[mask]):.2f} px; observed {100 * obs.sum() / mask.sum():.0f} % of the body, "
            f"EPE there {there:.2f} px; misaligned {reg.quality.misaligned_fraction:.2f}; ok {reg.quality.ok}; "
            f"{time.perf_counter() - t:.1f} s",
            flush=True,
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=("train", "test"), default="test")
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2, help="seeds per family case")
    ap.add_argument("--sim", default="seed-breast,pva-phantom", help="simulated presets on the test split ('' none)")
    ap.add_argument("--skip", default="", help="methods to leave out, comma-separated (e.g. elastix)")
    ap.add_argument("--out", type=Path, default=None, help="cache (default out/bench_register_flag/SPLIT-SIZE)")
    ap.add_argument("--fresh", action="store_true", help="register again even when a result is cached")
    ap.add_argument("--textureless", action="store_true", help="also the textureless pairs' observed EPE")
    ap.add_argument(
        "--sweep", action="store_true", help="train split: the confusion over a grid of the flag's thresholds"
    )
    ap.add_argument(
        "--textureless-check",
        type=int,
        metavar="SIZE",
        help="only the planted-field check of a textureless test pair at SIZE (e.g. 2240)",
    )
    args = ap.parse_args(argv)
    if args.textureless_check:
        textureless_check(args.textureless_check)
        return 0
    args.sim = [x.strip() for x in args.sim.split(",") if x.strip()]
    args.skip = {x.strip() for x in args.skip.split(",") if x.strip()}
    args.out = args.out or Path(f"out/bench_register_flag/{args.split}-{args.size}")
    print(f"load average before: {os.getloadavg()}", flush=True)
    t0 = time.perf_counter()
    rows, methods, inputs = run(args)
    methods += [(n, {}) for n in AUTO if any(r["method"] == n for r in rows)]
    print(
        f"\nquality.ok against the truth, {args.split} seeds ({args.seeds} per case), {args.size} px "
        f"(failed: median EPE > max(1 px, half the identity's); good: <= 0.5 px):\n"
    )
    print(table(rows, methods))
    print("\n".join(["", "misses:"] + misses(rows)))
    print("\n".join(["", "the map (mean over seeds of the median EPE, px):"] + map_table(rows)))
    if args.textureless:
        print("\n".join(["", "textureless pairs:"] + textureless(rows)))
    if args.sweep:
        if args.split != "train":
            print("\n(--sweep chooses thresholds: it runs on --split train only)")
        else:
            print("\n".join(["", "thresholds swept (best first):"] + sweep(rows, inputs)))
            import pickle  # the rule's inputs, to explore other rules without assessing again

            keep = ("method", "case", "epe_median", "identity", "ok", "quality")
            with open(args.out / "sweep_inputs.pkl", "wb") as fh:
                pickle.dump([({k: r.get(k) for k in keep}, x) for r, x in zip(rows, inputs)], fh)
        for r in rows:
            r.pop("quality", None)
    print(f"\n{time.perf_counter() - t0:.0f} s; load average after: {os.getloadavg()}")
    (args.out / "rows.json").write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
