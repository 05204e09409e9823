"""What ``auto`` returns after its plain run is stopped early (``_auto.ABANDON``), under the
present rule and the alternatives of session 25 (benchmarks/README.md, "After an abandoned
plain run: which comparison (session 25)").

Run (from the repository root)::

    python benchmarks/bench_register_abandon.py --split train   # where a rule is chosen
    python benchmarks/bench_register_abandon.py --split test    # reported once

Each pair at 2240 is registered by ``auto``'s plain run (``default`` with ``abandon_px`` and
``extend`` as ``auto`` sets them); when that run is stopped, also by ``weak`` and by the plain run
in full, and the rules are composed from those three runs (their wall seconds added: a
composition, not a timing of ``auto``). Rules, after a stopped plain run and the ``weak`` run:

- ``present``: ``weak`` kept when its residual moves less than the stopped run's did where it
  stopped (``_auto.returned``), else the plain run finished and the finals compared;
- ``settled``: ``weak`` kept only when it is settled (``_auto.settled``), else finished and compared;
- ``finals``: always finished and the finals compared (``_auto.keeps_retry``);
- ``near``: finished and compared when the stop came before the finest level under 2 px and
  ``weak`` settled, else ``present``;
- ``line 1.3``: ``ABANDON`` at 1.3 px: a plain run stopped under it runs in full instead (and
  ``weak`` follows only when it is not settled).

Pairs: TRAINING, ``bench_register_natural.py``'s pictures under both motions, six more pictures
of scikit-image under the smooth one (coins, clock, cell, immunohistochemistry, page, text), and
``regdata.family_pair`` at 2240 on TRAINING seeds: ``bench_register_weak2240.py``'s (texture
0.006 / 0.01 / 0.02, 1/10, seeds 0-1), the physical motion (seeds 0-1), texture 0.1 (seeds 0-1)
and, seed 0, texture 0.03 at 1/10 and 1/4, 0.01 at 1/4 and 1/20, 0.003 at 1/4. TEST: camera and
moon under both motions, and the same family cells on TEST seeds 1000-1001 (texture 0.006 /
0.01 / 0.02 at 1/10, the physical motion at 1001, texture 0.1).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_natural import MOTIONS, TEST, TRAIN, natural
from regdata import Case, family_pair, score

MORE = ("coins", "clock", "cell", "immunohistochemistry", "page", "text")  # TRAINING, smooth motion
RULES = ("present", "settled", "finals", "near", "line 1.3")


def pairs(split):
    """``(label, factory)`` of the split's pairs (see the module docstring)."""
    out = []
    if split == "train":
        out += [(f"{n} {m}", (n, m)) for m in MOTIONS for n in TRAIN]
        out += [(f"{n} sine", (n, "sine")) for n in MORE]
        fam = [(t, 0.1, s, "random") for s in (0, 1) for t in (0.006, 0.01, 0.02)]
        fam += [(0.01, 0, s, "physical") for s in (0, 1)] + [(0.1, 0.1, s, "random") for s in (0, 1)]
        fam += [(0.03, 0.1, 0, "random"), (0.03, 0.25, 0, "random"), (0.01, 0.25, 0, "random")]
        fam += [(0.01, 0.05, 0, "random"), (0.003, 0.25, 0, "random")]
    else:
        out += [(f"{n} {m}", (n, m)) for m in MOTIONS for n in TEST]
        fam = [(t, 0.1, s, "random") for s in (1000, 1001) for t in (0.006, 0.01, 0.02)]
        fam += [(0.01, 0, 1001, "physical")] + [(0.1, 0.1, s, "random") for s in (1000, 1001)]
    for tex, corr, seed, motion in fam:
        what = "phys" if motion == "physical" else f"1/{round(1 / corr)}"
        out.append((f"texture {tex:g} {what} s{seed}", Case(2240, tex, 0.01, corr, motion=motion, seed=seed)))
    return out


def _run(pair, **options):
    """``(median EPE, Quality, wall s, abandoned)`` of rc with ``options``."""
    from radiokit.register import register

    fixed, moving, truth, mask = pair
    t = time.perf_counter()
    reg = register(fixed, moving, "rc", **options)
    wall = time.perf_counter() - t
    return score(reg.displacement, truth, mask)["epe_median"], reg.quality, wall, reg.options.get("abandoned", "")


def compose(rule, stopped, weak, full):
    """``(median EPE, seconds, what)`` of ``rule`` from the three runs (``_run``'s tuples)."""
    from radiokit.register._auto import keeps_retry, returned, settled

    near = stopped[3].startswith("abandoned before") and stopped[1].residual_motion < 2.0 and settled(weak[1])
    if rule == "line 1.3" and stopped[3].startswith("abandoned before") and stopped[1].residual_motion < 1.3:
        if settled(full[1]):
            return full[0], full[2], "default"
        best = weak if keeps_retry(full[1], weak[1]) else full
        return best[0], full[2] + weak[2], "weak" if best is weak else "default"
    finish = {
        "present": returned("auto", stopped[1], "weak", weak[1]) == "default",
        "settled": not settled(weak[1]),
        "finals": True,
        "near": near or returned("auto", stopped[1], "weak", weak[1]) == "default",
        "line 1.3": returned("auto", stopped[1], "weak", weak[1]) == "default",
    }[rule]
    if not finish:
        return weak[0], stopped[2] + weak[2], "weak"
    best = weak if keeps_retry(full[1], weak[1]) else full
    return best[0], stopped[2] + weak[2] + full[2], ("weak" if best is weak else "default") + "*"


def main(argv=None):
    from radiokit.register._auto import ABANDON, EXTEND

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("train", "test"), default="test")
    args = ap.parse_args(argv)
    print("pair | stopped at (px) | weak: ok, residual, median EPE | default in full | " + " | ".join(RULES))
    logs = {r: [] for r in RULES}
    for label, spec in pairs(args.split):
        pair = family_pair(spec) if isinstance(spec, Case) else natural(spec[0], 2240, spec[1], args.split)
        stopped = _run(pair, preset="default", abandon_px=ABANDON, extend=EXTEND)
        if not stopped[3]:
            print(f"{label} | not stopped: default {stopped[0]:.3f} ({stopped[2]:.1f} s)", flush=True)
            continue
        weak = _run(pair, preset="weak")
        full = _run(pair, preset="default", extend=EXTEND)
        cells = []
        for rule in RULES:
            epe, sec, what = compose(rule, stopped, weak, full)
            logs[rule].append(math.log(epe))
            cells.append(f"{epe:.3f} ({what}, {sec:.0f} s)")

        def q(r):
            return f"{'ok' if r[1].ok else '!'} {r[1].residual_motion:.3f} {r[0]:.3f}"

        where = "finest" if stopped[3].startswith("abandoned at") else "before"
        print(
            f"{label} | {stopped[1].residual_motion:.2f} ({where}) | {q(weak)} | {q(full)} | " + " | ".join(cells),
            flush=True,
        )
    print("geometric mean of the stopped pairs' median EPE (px):")
    for rule, v in logs.items():
        if v:
            print(f"  {rule}: {math.exp(sum(v) / len(v)):.3f} ({len(v)} pairs)")


if __name__ == "__main__":
    main()
