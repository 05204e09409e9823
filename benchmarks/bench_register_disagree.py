"""Does the disagreement of two differently regularised registrations tell a wrong silent interior?

Run (from the repository root), after the benches that cache the fields::

    python benchmarks/bench_register_phantoms.py --out out/phantoms --split train
    python benchmarks/bench_register_flag.py --split train --size 560 --seeds 2
    python benchmarks/bench_register_disagree.py --source phantoms --split train
    python benchmarks/bench_register_disagree.py --source family --split train
    python benchmarks/bench_register_disagree.py --source heldout --size 560 --seeds 2   # registers

The hypothesis (session 29): in a silent interior the field is the regulariser's interpolation
of what the edges pin. A body-scale (near-affine) motion is interpolated alike by any smooth
regulariser, so two registrations regularised differently agree there; a local motion the
edges do not pin inside is not, so they differ. The statistic: ``|u1 - u2|`` (median and 90th
percentile, full-resolution px) over the object's interior as the flag sees it
(``register._PairChecks``: the object, its interior two windows inside the edge, the observed
part), ``u1`` the result's field and ``u2`` a second registration's. Second runs measured:
``silent`` (stiff, silhouette-started; ``default`` for a silent result itself) and ``weak``
(``default`` for a weak result); the rule chosen (``CHOSEN``) and the library use ``weak``.

Each source's results come with the flag's ``ok`` and reason and the truth's status (failed:
median EPE > max(1 px, half the identity's); good: <= 0.5 px). Printed: the AUC (probability a
failed result reads higher than a good one) of each statistic beside the flag's old ones, over
all results and over the trusted ones; with ``--sweep`` (training only) the confusion under
"flag when the disagreement exceeds X" (where the interior was trusted) and "trust the interior
when the disagreement is under Y" (where the interior rule alone flagged); with ``--rule``
``STAT:X:Y`` one rule's before/after confusion (what the test seeds are read with, once).
The rows go to ``OUT/disagree-SOURCE-SPLIT.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

# the second registrations: rc's four presets (each result against the others, not itself)
OTHERS = ("default", "fast", "weak", "silent")
# the rule chosen on the TRAINING rows (phantom seeds 6000-6029, the family's training seeds at
# 560; benchmarks/README.md, "Two registrations' disagreement (session 29)") before any test row
# was read: a trusted result is flagged when it differs from the second registration (``weak``;
# ``default`` for a weak result), itself trusted, by over 0.6 px (median over the interior)
CHOSEN = "second, trusted only:0.6:-inf"
QKEYS = ("residual_motion", "excess_kept", "misaligned_fraction", "interior_observed", "body_scale")


def status(epe, ident):
    if epe > max(1.0, 0.5 * ident):
        return "failed"
    return "good" if epe <= 0.5 else "between"


# the flag's other reasons (register._observed, _assess): the interior's own text holds "; "
OTHER_REASONS = (
    "the residual still moves",
    "the registration left",
    "structure left misaligned",
    "folding:",
    "diverged:",
    "non-finite",
    "did not converge",
    "still moving",
)


def interior_only(reason):
    """Whether the interior rule is the flag's only reason."""
    return reason.startswith("motion observable in only") and not any(o in reason for o in OTHER_REASONS)


def stats(p, u, refs):
    """The disagreement of field ``u`` with each field of ``refs`` (name -> field): the median of
    ``|u - v|`` over the object's interior as the flag sees it (``p``: ``register._PairChecks``;
    the whole object when it has no interior) and over the unobserved part of that interior
    (None under 50 px), full-resolution px."""
    from radiokit.register import _bin

    obj, obs, inner = p.ob.object, p.obs, p.inner
    inner = inner if inner.any() else obj
    k = p.k

    def binned(a):
        a = np.asarray(a, np.float32)
        return np.asarray(_bin(a, k) / k if k > 1 else a, np.float64)

    ub, out = binned(u), {}
    for rname, v in refs.items():
        e = k * np.hypot(*(ub - binned(v)))
        for gname, g in (("in", inner), ("in_unobs", inner & ~obs)):
            out[f"{gname}_{rname}"] = float(np.median(e[g])) if g.sum() >= 50 else None
    return out


def result(label, method, epe, ident, q, p, u, fields, kind, trusted):
    """One JSON-able row: the truth's status, the flag, and the disagreements with the other
    presets' fields (``fields``: preset -> field) and whether each of those was trusted
    (``trusted``: preset -> its own ``ok``)."""
    row = dict(
        case=label,
        method=method,
        kind=kind,
        epe_median=epe,
        identity=ident,
        status=status(epe, ident),
        ok=bool(q.ok),
        reason=q.reason,
        interior_only=interior_only(q.reason),
        ref_ok={c: bool(trusted[c]) for c in OTHERS if c in trusted and c != kind},
        **{k: (float(getattr(q, k)) if np.isfinite(getattr(q, k)) else None) for k in QKEYS},
    )
    row.update(stats(p, u, {c: fields[c] for c in OTHERS if c in fields and c != kind}))
    return row


# -- the sources -------------------------------------------------------------------------------


def _checks(fixed, moving):
    from radiokit.register import _check, _PairChecks

    f, m, _ = _check(fixed, moving, None)
    return _PairChecks(f, m, None)


def phantom_rows(out, split, more=None):
    """The phantom bench's results (its ``rows-SPLIT.json``) against its cached fields.
    ``more(label, fixed, moving, fields, trusted) -> (fields, trusted)``, when given, adds other
    second runs to a pair's before its rows are made (``bench_register_disagree_cheap.py``)."""
    import bench_register_phantoms as P

    rows = json.loads((out / f"rows-{split}.json").read_text())
    res = []
    for seed in sorted({r["seed"] for r in rows}):
        fixed, moving, truth, body, info = P.make_pair(seed)
        p = _checks(fixed, moving)
        fields = {}
        for name in P.CONFIGS:
            path = out / "fields" / f"{seed}-{name}.npz"
            if path.exists():
                fields[name] = np.load(path)["d"]
        mine = [r for r in rows if r["seed"] == seed]
        trusted = {r["preset"]: r["quality"]["ok"] for r in mine}
        if more:
            fields, trusted = more(f"{seed}", fixed, moving, fields, trusted)
        for r in mine:
            use = (
                r["preset"]
                if r["preset"] != "auto"
                else ("auto-plain" if r["returned"] == "default" else r["returned"])
            )
            kind = {"auto-plain": "default"}.get(use, use)
            q = _Q(r["quality"])
            res.append(
                result(f"{seed}", r["preset"], r["epe_median"], r["identity"], q, p, fields[use], fields, kind, trusted)
            )
    return res


class _Q:
    """A quality dict as attributes (NaN for None)."""

    def __init__(self, d):
        for k, v in d.items():
            setattr(self, k, float("nan") if v is None else v)


FAMILY_KIND = {
    "rc": "default",
    "rc-extend": "default",
    "rc-fast": "fast",
    "rc-weak": "weak",
    "rc-weak-fast": "weak-fast",
    "rc-silent": "silent",
    "rc-silent-fast": "silent-fast",
    "elastix+hp": "elastix",
    "dis+hp": "dis",
}


def family_rows(out, split, size, seeds, more=None):
    """The flag bench's results (its ``rows.json``) against its cached fields (re-assessed: the
    rows carry the reason, not the quality's numbers); ``more`` as in :func:`phantom_rows`."""
    import bench_register_flag as F

    rows = json.loads((out / "rows.json").read_text())
    res = []
    seen = set()
    for label, _, thunk in F.pairs(split, size, seeds, ["seed-breast", "pva-phantom"]):
        # a label the family lists twice (a map cell that is also a spread case) has its rows
        # twice in rows.json, as the flag bench counts it: taken once here, with both rows
        mine = [r for r in rows if r["case"] == label and r["method"] != "identity"]
        if not mine or label in seen:
            continue
        seen.add(label)
        fixed, moving, truth, mask = thunk()
        p = _checks(fixed, moving)
        fields = {}
        for name, kind in FAMILY_KIND.items():
            path = F._cache_path(out, label, name)
            if path.exists() and name != "rc-extend":  # "default": rc's own field
                fields[kind] = np.load(path)["d"]
        inner = p.inner if p.inner.any() else p.ob.object
        trusted = {FAMILY_KIND[r["method"]]: r["ok"] for r in mine if r["method"] in FAMILY_KIND}
        if more:
            fields, trusted = more(label, fixed, moving, fields, trusted)
        for r in mine:
            use = r.get("returned") or r["method"]
            kind = FAMILY_KIND[use]
            u = np.load(F._cache_path(out, label, use))["d"]
            # the rows carry the flag's reason and residual numbers; the interior's observed share
            # is the pair's (the map is the fixed image's)
            q = _Q(
                dict(
                    ok=r["ok"],
                    reason=r["reason"],
                    residual_motion=r["step"],
                    excess_kept=r["kept"],
                    misaligned_fraction=r["misaligned"],
                    interior_observed=float(p.obs[inner].mean()),
                    body_scale=None,
                )
            )
            res.append(result(label, r["method"], r["epe_median"], r["identity"], q, p, u, fields, kind, trusted))
    return res


def heldout_rows(out, size, seeds, more=None, cached_only=False):
    """The held-out generator's pairs, registered here (as ``bench_register_heldout.py`` does,
    ``register()`` per preset) with the fields cached, plus ``silent`` as the reference.
    ``more`` as in :func:`phantom_rows`; ``cached_only``: a field not in ``out`` is an error,
    not registered into it."""
    import bench_register_heldout as H
    from regdata import score

    from radiokit.register import register

    res = []
    for seed in H.SEEDS[:seeds]:
        for noise in (0.01, 0.0025):
            for t2n in (0.0, 0.3, 1.0, 3.0, 10.0):
                f, m, d, mask = H.heldout_pair(size, seed, t2n, noise)
                ident = score(np.zeros_like(d), d, mask)["epe_median"]
                label = f"s{seed} noise {noise:g} t/n {t2n:g}"
                p = _checks(f, m)
                regs = {}
                for name, preset in dict(H.METHODS, **{"rc-silent": "silent"}).items():
                    path = out / "fields" / f"{size}-{label.replace(' ', '_').replace('/', '')}-{name}.npz"
                    if path.exists():
                        z = np.load(path)
                        regs[name] = (z["d"], _Q(json.loads(str(z["q"]))), str(z["kind"]))
                        continue
                    if cached_only:
                        raise FileNotFoundError(f"{path}: not cached (run bench_register_disagree.py --source heldout)")
                    reg = register(f, m, "rc", preset=preset)
                    kind = reg.options.get("preset", preset)
                    if "auto" in reg.options:
                        kind = str(reg.options["auto"].preset).split("+")[0]
                    qd = {k: v for k, v in vars(reg.quality).items() if isinstance(v, (int, float, str, bool))}
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(".tmp.npz")
                    np.savez(tmp, d=reg.displacement, q=json.dumps(qd), kind=kind)
                    tmp.replace(path)
                    regs[name] = (reg.displacement, _Q(qd), kind)
                kinds = {"rc": "default", "rc-fast": "fast", "rc-weak": "weak", "rc-silent": "silent"}
                fields = {k: regs[n][0] for n, k in kinds.items()}
                trusted = {k: regs[n][1].ok for n, k in kinds.items()}
                if more:
                    fields, trusted = more(label, f, m, fields, trusted)
                for name in H.METHODS:
                    u, q, kind = regs[name]
                    epe = float(np.median(np.hypot(*(u - d))[mask]))
                    res.append(result(label, name, epe, ident, q, p, u, fields, kind, trusted))
                print(f"  {label}", flush=True)
    return res


# -- the tables --------------------------------------------------------------------------------


def auc(f, g):
    f, g = np.asarray(f, float), np.asarray(g, float)
    f, g = f[np.isfinite(f)], g[np.isfinite(g)]
    if not f.size or not g.size:
        return float("nan")
    return float(np.mean((f[:, None] > g[None, :]) + 0.5 * (f[:, None] == g[None, :])))


def _v(r, k):
    """A row's statistic ``k``: a quality number, or a disagreement (``STAT`` below)."""
    if k in STAT:
        return STAT[k](r)
    v = r.get(k)
    return np.nan if v is None else float(v)


def _second(r, region="in"):
    """The disagreement with one second registration: ``weak``, or ``default`` for a weak
    result (whether or not that one was trusted)."""
    v = r.get(f"{region}_weak", r.get(f"{region}_default"))
    return np.nan if v is None else v


def _second_trusted(r, region="in"):
    """:func:`_second` when that second registration passed its own checks, else NaN (a
    disagreement with a flagged field says nothing of this one)."""
    ref = "weak" if f"{region}_weak" in r else "default"
    return _second(r, region) if r["ref_ok"].get(ref) else np.nan


def _over_trusted(r, how, region="in"):
    """The least (``min``) or largest (``max``) disagreement with the other presets' fields that
    passed their own checks; NaN when none did."""
    v = [r[f"{region}_{c}"] for c, ok in r["ref_ok"].items() if ok and r.get(f"{region}_{c}") is not None]
    return how(v) if v else np.nan


STAT = {
    "second (weak; default for weak)": _second,
    "second, trusted only": _second_trusted,
    "second, trusted only, unobserved interior": lambda r: _second_trusted(r, "in_unobs"),
    "min over trusted presets": lambda r: _over_trusted(r, min),
    "max over trusted presets": lambda r: _over_trusted(r, max),
    "vs silent": lambda r: np.nan if r.get("in_silent") is None else r["in_silent"],
    "vs default": lambda r: np.nan if r.get("in_default") is None else r["in_default"],
}


def auc_table(rows, keys):
    lines = [
        "| statistic | AUC all (failed vs good) | AUC trusted | failed median | good median |",
        "|---|---|---|---|---|",
    ]
    for k in keys:
        f = [r for r in rows if r["status"] == "failed"]
        g = [r for r in rows if r["status"] == "good"]
        ft, gt = [r for r in f if r["ok"]], [r for r in g if r["ok"]]
        fv, gv = np.array([_v(r, k) for r in f]), np.array([_v(r, k) for r in g])
        lines.append(
            f"| {k} | {auc(fv, gv):.2f} ({len(f)}/{len(g)}) | {auc([_v(r, k) for r in ft], [_v(r, k) for r in gt]):.2f} "
            f"({len(ft)}/{len(gt)}) | {np.nanmedian(fv):.3g} | {np.nanmedian(gv):.3g} |"
        )
    return lines


def ok_under(r, stat, x, y):
    """``ok`` under the rule: a trusted result is flagged when ``stat`` > ``x``; one flagged for
    the interior alone is trusted when ``stat`` < ``y`` (NaN: unchanged)."""
    v = _v(r, stat)
    if not np.isfinite(v):
        return r["ok"]
    if r["ok"]:
        return not v > x
    if r["interior_only"]:
        return v < y
    return False


def confusion(rows, stat=None, x=np.inf, y=-np.inf):
    f = [r for r in rows if r["status"] == "failed"]
    g = [r for r in rows if r["status"] == "good"]
    okf = (lambda r: r["ok"]) if stat is None else (lambda r: ok_under(r, stat, x, y))
    return sum(not okf(r) for r in f), len(f), sum(bool(okf(r)) for r in g), len(g)


def fmt(c):
    return f"{c[0]}/{c[1]} ({100 * c[0] / max(c[1], 1):.0f} %), {c[2]}/{c[3]} ({100 * c[2] / max(c[3], 1):.0f} %)"


def source_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments that name the rows (this bench's and bench_register_disagree_cheap's)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--source", choices=("phantoms", "family", "heldout"), required=True)
    ap.add_argument("--split", choices=("train", "test"), default="train")
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2)
    return ap


def main(argv=None) -> int:
    ap = source_parser(__doc__)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--sweep", action="store_true", help="the rules' confusion over X and Y (training only)")
    ap.add_argument(
        "--rule", default=None, help=f"STAT:X:Y, one rule's confusion before and after (chosen: {CHOSEN!r})"
    )
    ap.add_argument("--table", action="store_true", help="from the saved rows")
    a = ap.parse_args(argv)
    default_out = {
        "phantoms": Path("out/phantoms"),
        "family": Path(f"out/bench_register_flag/{a.split}-{a.size}"),
        "heldout": Path("out/heldout"),
    }
    out = a.out or default_out[a.source]
    split = "test" if a.source == "heldout" else a.split
    saved = out / f"disagree-{a.source}-{split}.json"
    if a.table:
        rows = json.loads(saved.read_text())
    else:
        if a.source == "phantoms":
            rows = phantom_rows(out, split)
        elif a.source == "family":
            rows = family_rows(out, split, a.size, a.seeds)
        else:
            rows = heldout_rows(out, a.size, a.seeds)
        saved.write_text(json.dumps(rows))
    for r in rows:  # rows saved by an earlier version of this script: the reason is what counts
        r["interior_only"] = interior_only(r["reason"])
    keys = list(STAT)
    print(f"{a.source} {split}: {len(rows)} results; failed flagged, good trusted now: {fmt(confusion(rows))}")
    if a.rule is None:
        print("\n".join(auc_table(rows, list(QKEYS) + keys)))
    if a.sweep:
        if split != "train":
            print("--sweep chooses: training rows only")
            return 2
        print("\n| statistic | X (flag trusted above) | Y (trust interior-only below) | failed flagged, good trusted |")
        print("|---|---|---|---|")
        for k in keys:
            for x in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0):
                for y in (-np.inf, 0.1, 0.2, 0.3):
                    print(f"| {k} | {x} | {y} | {fmt(confusion(rows, k, x, y))} |")
    if a.rule:
        k, x, y = a.rule.rsplit(":", 2)
        x, y = float(x), float(y)
        print(f"rule: flag a trusted result when {k!r} > {x}; trust one flagged for the interior alone when < {y}")
        print("| results | before: failed flagged, good trusted | after |")
        print("|---|---|---|")
        from bench_register import FAMILY_METHODS

        groups = {"all": lambda r: True}
        if a.source == "family":  # the flag bench's "all methods"
            groups["FAMILY_METHODS"] = lambda r: r["method"] in FAMILY_METHODS
        groups.update({m: (lambda r, m=m: r["method"] == m) for m in sorted({r["method"] for r in rows})})
        for m, sel in groups.items():
            rs = [r for r in rows if sel(r)]
            print(f"| {m} | {fmt(confusion(rs))} | {fmt(confusion(rs, k, x, y))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
