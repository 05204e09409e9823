"""After ``auto``'s plain run is stopped early and ``weak`` is kept: the plain preset's finest
level (and polish) run on ``weak``'s field (rc's ``start_lattices``) instead of the plain run
finished from its stop (benchmarks/README.md, "The plain run's finest level on the weak run's
field (session 27)").

Run (from the repository root)::

    python benchmarks/bench_register_finest.py --split train   # where the rule is chosen
    python benchmarks/bench_register_finest.py --split test    # reported once

The pairs are ``bench_register_abandon.py``'s (2240; ``--only`` a label's substring keeps those
whose label contains it). Each is registered by ``auto``'s plain run (``default`` with
``abandon_px`` and ``extend`` as ``auto`` sets them); where that run stops, also by ``weak`` and
by ``default``'s finest level on ``weak``'s lattices (``extend`` as ``auto`` sets it), and the
rules composed: ``present`` (``weak``, as ``auto`` returned it where ``weak`` beat the stopped
run), ``any`` (the finest level run whenever ``weak`` is kept, and kept itself when its residual
moves less: ``_auto.keeps_retry``), ``settled`` (run only when ``weak`` is settled:
``_auto.settled``). Seconds: each run's wall and CPU (this process's), the rules' the runs' added.

``--halfway`` (session 27, second look at ``FINEST_GAIN``): where ``auto`` would run that level,
it runs without its line (to its end, polished), and the residual's motion at its two checks
(halfway and at the level's end) is printed over ``weak``'s, with whether ``keeps_finest`` keeps
the level then and its median EPE over ``weak``'s. ``--pairs wider``: TRAINING pictures not used
before (:data:`WIDER`, under both motions; ``bench_register_abandon.MORE``'s under the local one);
``--pairs sine2``: every TRAINING picture under another smooth motion (``natural``'s ``sine2``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_abandon import MORE, pairs
from bench_register_natural import MATPLOTLIB, MOTIONS, TRAIN, natural
from regdata import Case, family_pair, score

# TRAINING pictures of scikit-image and matplotlib (bundled, offline) added in session 27's second look at
# FINEST_GAIN, under both motions, with MORE's under the local one (``--pairs wider``); chosen
# after moon's TEST figure was known (benchmarks/README.md, "The plain run's finest level on the
# weak run's field (session 27)")
WIDER = ("stereo_motorcycle", "microaneurysms", "shepp_logan_phantom", *MATPLOTLIB)


def _run(pair, **options):
    """``(median EPE, p95, Quality, wall s, cpu s, registration)`` of rc with ``options``."""
    from radiokit.register import register

    fixed, moving, truth, mask = pair
    t, c = time.perf_counter(), time.process_time()
    reg = register(fixed, moving, "rc", **options)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    s = score(reg.displacement, truth, mask)
    return s["epe_median"], s["epe_p95"], reg.quality, wall, cpu, reg


def _recorded():
    """A list that fills, during a run on another run's field (``start_lattices``), with the
    residual's motion at each of its checks (halfway and at the level's end), as the checks
    measure it: ``_bspline._far_off`` wrapped (a benchmark's instrument; the run's path is its own)."""
    from radiokit.register import _bspline

    seen, original = [], _bspline._far_off

    def far_off(measure, lattices, affine, o, when, where="before"):
        if where == "at" and o is not None:
            seen.append(_bspline._motion(measure, lattices, affine))
        return original(measure, lattices, affine, o, when, where)

    _bspline._far_off = far_off
    return seen


def halfway(label, pair, seen):
    """``--halfway``: where ``auto`` would run the finest level on ``weak``'s field, that level
    without its line (run to its end and polished), the checks' readings over ``weak``'s residual,
    and whether ``keeps_finest`` keeps it then; returns ``(label, halfway, end, kept, finest / weak
    median EPE)`` or None."""
    from radiokit.register._auto import ABANDON, EXTEND, _finest, finest_from_weak, keeps_finest, returned

    stopped = _run(pair, preset="default", abandon_px=ABANDON, extend=EXTEND)
    if "abandoned" not in stopped[5].options:
        print(f"{label} | not stopped: default {stopped[0]:.3f} ({stopped[4]:.0f} CPU s)", flush=True)
        return None
    weak = _run(pair, preset="weak")
    w = weak[2]
    if returned("auto", stopped[2], "weak", w) != "weak" or not finest_from_weak(w):
        why = "weak not returned" if returned("auto", stopped[2], "weak", w) != "weak" else "weak not settled"
        print(f"{label} | {why}: ok {w.ok} residual {w.residual_motion:.3f} median {weak[0]:.3f}", flush=True)
        return None
    seen.clear()
    finest = _run(pair, **dict(_finest("auto", {"preset": "auto"}, weak[5]), abandon_px=1e9))
    half, end = (v / w.residual_motion for v in seen[:2])
    kept = keeps_finest(w, finest[2])
    f = finest[2]
    print(
        f"{label} | weak ok {w.ok} {w.residual_motion:.3f} {weak[0]:.3f} / {weak[1]:.2f} | halfway {half:.3f}"
        f" end {end:.3f} | finest to its end: ok {f.ok} {f.residual_motion:.3f} {finest[0]:.3f} / {finest[1]:.2f}"
        f" ({finest[4]:.1f} CPU s) | kept without the line: {kept} | EPE finest/weak {finest[0] / weak[0]:.2f}",
        flush=True,
    )
    return label, half, end, kept, finest[0] / weak[0]


def main(argv=None):
    from radiokit.register._auto import ABANDON, EXTEND, _finest, finest_from_weak, keeps_finest, returned

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("train", "test"), default="test")
    ap.add_argument("--only", nargs="*", default=None, help="labels containing any of these substrings")
    ap.add_argument("--pairs", choices=("abandon", "wider", "sine2"), default="abandon", help="wider, sine2: TRAINING")
    ap.add_argument("--halfway", action="store_true", help="the finest level without its line: its readings")
    args = ap.parse_args(argv)
    chosen = pairs(args.split)
    if args.pairs == "wider":
        chosen = [(f"{n} {m}", (n, m)) for m in MOTIONS for n in WIDER] + [(f"{n} local", (n, "local")) for n in MORE]
    elif args.pairs == "sine2":  # every TRAINING picture under another smooth motion
        chosen = [(f"{n} sine2", (n, "sine2")) for n in TRAIN + MORE + WIDER]
    if args.halfway:
        seen = _recorded()
        for label, spec in chosen:
            if args.only is None or any(s in label for s in args.only):
                pair = family_pair(spec) if isinstance(spec, Case) else natural(spec[0], 2240, spec[1], args.split)
                halfway(label, pair, seen)
        return
    print(
        "pair | stopped at (px) | weak: ok, residual, median / p95 | finest on weak: ok, residual, median / p95,"
        " wall / cpu s | before: median / p95 (wall / cpu s) | now"
    )
    logs = {"before": [], "now": []}
    for label, spec in chosen:
        if args.only is not None and not any(s in label for s in args.only):
            continue
        pair = family_pair(spec) if isinstance(spec, Case) else natural(spec[0], 2240, spec[1], args.split)
        stopped = _run(pair, preset="default", abandon_px=ABANDON, extend=EXTEND)
        if "abandoned" not in stopped[5].options:
            print(f"{label} | not stopped: default {stopped[0]:.3f} ({stopped[3]:.1f} s)", flush=True)
            continue
        weak = _run(pair, preset="weak")
        if returned("auto", stopped[2], "weak", weak[2]) != "weak":
            print(f"{label} | weak did not beat the stopped run: finished as before", flush=True)
            continue
        wall, cpu = stopped[3] + weak[3], stopped[4] + weak[4]
        before = f"{weak[0]:.3f} / {weak[1]:.2f} ({wall:.0f} / {cpu:.0f} s)"
        logs["before"].append(math.log(weak[0]))

        def q(r):
            return f"{'ok' if r[2].ok else '!'} {r[2].residual_motion:.3f} {r[0]:.3f} / {r[1]:.2f}"

        if not finest_from_weak(weak[2]):
            logs["now"].append(math.log(weak[0]))
            print(f"{label} | {stopped[2].residual_motion:.2f} | {q(weak)} | not run | {before} | {before}", flush=True)
            continue
        finest = _run(pair, **_finest("auto", {"preset": "auto"}, weak[5]))
        best = finest if keeps_finest(weak[2], finest[2]) else weak
        logs["now"].append(math.log(best[0]))
        why = "kept" if best is finest else (finest[5].options.get("abandoned") or "residual moves more")
        now = f"{best[0]:.3f} / {best[1]:.2f} ({wall + finest[3]:.0f} / {cpu + finest[4]:.0f} s)"
        print(
            f"{label} | {stopped[2].residual_motion:.2f} | {q(weak)} | {q(finest)}, {finest[3]:.1f} / {finest[4]:.1f} s"
            f" [{why}] | {before} | {now}",
            flush=True,
        )
    print("geometric mean of the median EPE of the pairs where weak was returned (px):")
    for rule, v in logs.items():
        if v:
            print(f"  {rule}: {math.exp(sum(v) / len(v)):.3f} ({len(v)} pairs)")


if __name__ == "__main__":
    main()
