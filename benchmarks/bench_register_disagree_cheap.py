"""Can a cheaper second registration give ``regularisation_check``'s verdicts?

Run (from the repository root), after ``bench_register_disagree.py``'s benches have cached their
fields (read only here; ``--src`` is that ``out`` directory)::

    python benchmarks/bench_register_disagree_cheap.py --source phantoms --split train --src out
    python benchmarks/bench_register_disagree_cheap.py --source family --split train --src out
    python benchmarks/bench_register_disagree_cheap.py --source heldout --seeds 2 --src out   # its cache only

The check (``register(..., regularisation_check=True)``, session 29) registers the pair again with
rc's ``weak`` (``default`` for a weak result) and flags a trusted result whose field differs from
that second one, itself trusted, by over 0.6 px (median over the flag's interior). ``weak`` is the
slowest preset. Each candidate here is a second run and the preset it falls back to for a result
of its own family (two runs of one regulariser agree by construction), registered afresh (cached
in ``OUT/cheap``) with its time, beside ``weak`` registered afresh under the same load:

- ``weak`` (``default`` for a weak result, cached by the source bench): the present check;
- ``weak-fast`` (``fast`` for a ``weak`` or ``weak-fast`` result);
- ``weak-lite``: ``weak`` area-averaged to 0.1 Mpx and a quarter of its iterations (``fast`` for
  a weak result);
- ``silent-fast`` (``weak-fast`` for a ``silent`` or ``silent-fast`` result).

Printed per candidate: the AUC (a failed result reads higher than a good one; over all results and
over the trusted ones) of the disagreement with that second run when it is itself trusted, the
confusion (failed flagged, good trusted) of "flag a trusted result above X" for X in ``XS``, and
the median time of each second run. ``--rule NAME:X`` prints one candidate's before/after
confusion per method (what the test rows are read with, once).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_register_disagree as D

# the second runs registered here: name -> register()'s rc options
RUNS = {
    "weak": dict(preset="weak"),
    "weak-fast": dict(preset="weak-fast"),
    "fast": dict(preset="fast"),
    "weak-lite": dict(preset="weak", bin_pixels=100_000, iterations=(60, 30, 20)),
    "silent-fast": dict(preset="silent-fast"),
}
# candidate -> (its second run, the fallback for a result of its own family, that family); the
# fallback of the present check is the source bench's cached ``default`` (key ``default``)
CANDIDATES = {
    "weak": ("x-weak", "default", ("weak",)),
    "weak-fast": ("x-weak-fast", "x-fast", ("weak", "weak-fast")),
    "weak-lite": ("x-weak-lite", "x-fast", ("weak",)),
    "silent-fast": ("x-silent-fast", "x-weak-fast", ("silent", "silent-fast")),
}
XS = (0.4, 0.5, 0.6, 0.7, 0.8, 1.0)
# chosen on the TRAINING rows (phantom seeds 6000-6029, the family's training seeds at 560) before
# any test row was read: ``weak-lite`` at the present check's 0.6 px (phantoms 41/46, 54/66 against
# ``weak``'s 40/46, 53/66; the family's unchanged; 0.22-0.24 of ``weak``'s time; benchmarks/README.md,
# "Two registrations' disagreement (session 29)")
CHOSEN = "weak-lite:0.6"


def fresh_runs(cache, label, fixed, moving):
    """Every ``RUNS`` registration of the pair: ``{"x-NAME": (field, ok, seconds)}``, from
    ``cache`` or registered now (one at a time: the times are comparable within a pair)."""
    from radiokit.register import register

    got = {}
    for name, opts in RUNS.items():
        path = cache / f"{label.replace(' ', '_').replace('/', '')}-{name}.npz"
        if not path.exists():
            t = time.perf_counter()
            reg = register(fixed, moving, "rc", **opts)
            sec = time.perf_counter() - t
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, d=reg.displacement, ok=bool(reg.quality.ok), seconds=sec)
            tmp.replace(path)
        z = np.load(path)
        got[f"x-{name}"] = (z["d"], bool(z["ok"]), float(z["seconds"]))
    return got


def _with_runs(runs, fields, trusted):
    """``fields``/``trusted`` with the fresh runs added, and ``D.OTHERS`` widened to them so that
    ``D.result`` measures the disagreement with each."""
    D.OTHERS = ("default", "fast", "weak", "silent", *runs)
    fields = dict(fields, **{k: v[0] for k, v in runs.items()})
    trusted = dict(trusted, **{k: v[1] for k, v in runs.items()})
    return fields, trusted


class _Fresh:
    """The ``more`` hook of ``D``'s row makers: every ``RUNS`` registration of a pair (cached in
    ``OUT/cheap`` under ``prefix`` + the pair's label), added to its fields, with the times kept."""

    def __init__(self, out, prefix):
        self.cache, self.prefix, self.times = out / "cheap", prefix, []

    def __call__(self, label, fixed, moving, fields, trusted):
        runs = fresh_runs(self.cache, f"{self.prefix}{label}", fixed, moving)
        self.times.append({k: v[2] for k, v in runs.items()})
        print(f"  {label} " + " ".join(f"{k[2:]} {v[2]:.2f}s" for k, v in runs.items()), flush=True)
        return _with_runs(runs, fields, trusted)


def source_rows(a):
    """``(rows, times)`` of ``a.source`` (``D``'s rows of the cached results in ``a.src``, read
    only) with the fresh runs' disagreements."""
    if a.source == "phantoms":
        fresh = _Fresh(a.out, f"{a.split}-")
        rows = D.phantom_rows(a.src / "phantoms", a.split, more=fresh)
    elif a.source == "heldout":
        fresh = _Fresh(a.out, f"heldout-{a.size}-")
        rows = D.heldout_rows(a.src / "heldout", a.size, a.seeds, more=fresh, cached_only=True)
    else:
        fresh = _Fresh(a.out, f"{a.split}-{a.size}-")
        src = a.src / "bench_register_flag" / f"{a.split}-{a.size}"
        rows = D.family_rows(src, a.split, a.size, a.seeds, more=fresh)
    return rows, fresh.times


def second(r, cand):
    """The disagreement with the candidate's second run for this result when that run passed its
    own checks, else NaN (the result's verdict unchanged)."""
    run, fallback, family = CANDIDATES[cand]
    ref = fallback if r["kind"] in family else run
    v = r.get(f"in_{ref}")
    return float(v) if v is not None and r["ref_ok"].get(ref) else np.nan


def confusion(rows, cand=None, x=np.inf):
    """(failed flagged, failed, good trusted, good) under "flag a trusted result whose ``second``
    exceeds ``x``" (``cand`` None: the flag alone)."""

    def ok(r):
        if cand is None or not r["ok"]:
            return r["ok"]
        v = second(r, cand)
        return not (np.isfinite(v) and v > x)

    f = [r for r in rows if r["status"] == "failed"]
    g = [r for r in rows if r["status"] == "good"]
    return sum(not ok(r) for r in f), len(f), sum(ok(r) for r in g), len(g)


def tables(rows, times):
    f = [r for r in rows if r["status"] == "failed"]
    g = [r for r in rows if r["status"] == "good"]
    ft, gt = [r for r in f if r["ok"]], [r for r in g if r["ok"]]
    print(f"{len(rows)} results; the flag alone: {D.fmt(confusion(rows))}")
    print("| second run | AUC all | AUC trusted | " + " | ".join(f"X = {x}" for x in XS) + " |")
    print("|---|---|---|" + "---|" * len(XS))
    for c in CANDIDATES:
        a = D.auc([second(r, c) for r in f], [second(r, c) for r in g])
        at = D.auc([second(r, c) for r in ft], [second(r, c) for r in gt])
        cells = " | ".join("{}/{}, {}/{}".format(*confusion(rows, c, x)) for x in XS)
        print(f"| {c} | {a:.2f} | {at:.2f} | {cells} |")
    print(
        "median seconds per pair (registered one after another): "
        + ", ".join(f"{k[2:]} {np.median([t[k] for t in times]):.2f}" for k in times[0])
    )


def main(argv=None) -> int:
    ap = D.source_parser(__doc__)
    ap.add_argument("--src", type=Path, default=Path("out"), help="the source benches' out directory (read only)")
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument("--rule", default=None, help=f"CANDIDATE:X, one rule's confusion per method (chosen: {CHOSEN!r})")
    a = ap.parse_args(argv)
    rows, times = source_rows(a)
    (a.out / "cheap" / f"rows-{a.source}-{a.split}.json").write_text(json.dumps(dict(rows=rows, times=times)))
    tables(rows, times)
    if a.rule:
        c, x = a.rule.rsplit(":", 1)
        print(f"rule: {c} at {x} px | results | before | present check (weak, 0.6) | after |")
        for m in ["all", *sorted({r["method"] for r in rows})]:
            rs = [r for r in rows if m in ("all", r["method"])]
            print(
                f"| {m} | {D.fmt(confusion(rs))} | {D.fmt(confusion(rs, 'weak', 0.6))} | {D.fmt(confusion(rs, c, float(x)))} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
