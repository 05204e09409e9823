"""Registration: speed against accuracy of rc and its peers, and where each one breaks.

Run::

    python benchmarks/bench_register.py [--size 1120] [--quick] [--out out/bench_register]

Part 1, speed/accuracy: every method (rc default and fast, ssd, ncc, mi, tvl1, ilk, dis,
farneback, and sitk-* / elastix when installed), each with its defaults and "tuned" (peers:
``prefilter="highpass"``, removing slow intensity change by hand), on analytic pairs
(``regdata.analytic_pair``: 1 % displacement, 10 % intensity change of both kinds, 1 % noise).
End-point error median and p95 inside the object, folds and time; the chart marks the Pareto
front (no method both faster and more accurate).

Part 2, stability map: EPE median of rc and the tuned peers against displacement (1-4 % of the
frame) x intensity change (0-20 %), at the benchmark size; a cell where a method is worse than
not registering at all is marked.

Part 3, the textureless-phantom family (``regdata.family``, issue 11), on TEST seeds: rc (presets default, fast, weak, weak-fast) and
the tuned peers (elastix+hp, dis+hp) over texture-to-noise {0, 0.3, 1, 3, 10} x motion correlation
length {1/4, 1/10, 1/20} of the frame (maps of median EPE, the identity's beside), the spread cases
(amplitude, physical motion, 20 % intensity change of both kinds, Poisson-like noise, the intensity
domain) and the simulated pairs of both scene presets; then the confusion table of ``quality.ok``
against the truth (failed: median EPE > max(1 px, half the identity's); good: <= 0.5 px).
``--family-only`` runs just this part (``--family-size``, ``--family-seeds``).

Writes ``bench_register.png``, ``stability.png``, ``family_maps.png`` and ``bench_register.json``. Size 1120 takes
several minutes on two cores (``--quick``: 512 and fewer cells).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from regdata import analytic_pair, block_mean, evaluate, score, sim_pair


def configs():
    from radiokit.register import METHODS, load_methods, register  # noqa: F401 - fills METHODS

    load_methods()
    out = [
        ("rc", {}),
        ("rc-fast", {"preset": "fast"}),
        ("rc-weak", {"preset": "weak"}),
        ("rc-weak-fast", {"preset": "weak-fast"}),
        ("rc-silent", {"preset": "silent"}),
        ("rc-silent-fast", {"preset": "silent-fast"}),
        ("ssd", {}),
        ("ncc", {}),
        ("mi", {}),
    ]
    import importlib.util

    peers = ["tvl1", "ilk", "dis", "farneback"]
    if importlib.util.find_spec("SimpleITK"):
        peers += ["sitk-bspline", "sitk-demons"]
    if importlib.util.find_spec("itk"):
        peers += ["elastix"]
    for p in peers:
        out += [(p, {}), (p + "+hp", {"prefilter": "highpass"})]
    return out


def _method_of(name):
    """The registration method of a configuration's name ("rc-weak-fast" -> "rc", "dis+hp" -> "dis")."""
    base = name.split("+")[0]
    return "rc" if base.startswith("rc-") else base


def run_one(name, opts, fixed, moving, truth, mask):
    method = _method_of(name)
    try:
        row = evaluate(method, (fixed, moving, truth, mask), **opts)
    except Exception as exc:  # a peer that cannot run on this pair is reported, not fatal
        return {"method": name, "error": repr(exc)}
    row["method"] = name
    return row


def warm_up(cfgs):
    """One small registration per method first, so imports (ITK's take 15 s) and first-call
    set-up are not charged to the timed runs."""
    fixed, moving, truth, mask = analytic_pair(96, 0.01, 0.1, 0.01, seed=99)
    for n, o in cfgs:
        run_one(n, o, fixed, moving, truth, mask)


def pareto(rows):
    pts = sorted((r for r in rows if "error" not in r), key=lambda r: r["seconds"])
    front, best = [], np.inf
    for r in pts:
        if r["epe_median"] < best:
            front.append(r["method"])
            best = r["epe_median"]
    return front


def levels_part(size, seed, opts):
    """rc's median / p95 EPE inside the body after each pyramid level (the field of the levels so
    far, evaluated on a grid 4x coarser), on the training pair at ``size`` and the same pair
    binned by 2 (its EPE also in the full size's pixels): where the pyramid stalls."""
    from regdata import Case, family_pair

    from radiokit.register import _bspline as B
    from radiokit.register import register

    f, m, d, mask = family_pair(Case(size=size, texture=0.01, noise=0.01, corr=0.1, seed=seed))
    pairs = [
        (str(size), f, m, d, mask, 1),
        (
            f"{size // 2} (binned)",
            block_mean(f, 2),
            block_mean(m, 2),
            block_mean(d, 2) / 2,
            block_mean(mask.astype(np.float32), 2) > 0.5,
            2,
        ),
    ]
    print(
        f"{Case(size=size, texture=0.01, noise=0.01, corr=0.1, seed=seed).label()}: identity "
        f"{score(0 * d, d, mask)['epe_median']:.2f} px; rc {opts}",
        flush=True,
    )
    for tag, f, m, d, mask, scale in pairs:
        k = 4
        db, mb = block_mean(d, k) / k, block_mean(mask.astype(np.float32), k) > 0.5
        acc = np.zeros_like(db)
        lines = []

        def cb(factor, res, f=f, db=db, mb=mb, lines=lines, scale=scale):
            nonlocal acc
            spacing = B.PRESETS[opts.get("preset", "default")]["spacing"] if "spacing" not in opts else opts["spacing"]
            acc = acc + B.BSplineField(f.shape, spacing * max(1, factor // 2)).field(res.x, k, db.shape[1:])  # noqa: B023
            e = k * np.hypot(*(acc - db))[mb]  # noqa: B023
            lines.append(
                f"    level 1/{factor} ({f.shape[0] // factor} px), {res.nit} iterations: "
                f"{np.median(e):.2f} / {np.percentile(e, 95):.2f} px (x{scale}: {scale * np.median(e):.2f})"
            )

        t = time.perf_counter()
        r = register(f, m, "rc", callback=cb, **opts)
        sc = score(r.displacement, d, mask)
        print(
            f"  {tag}: {sc['epe_median']:.2f} / {sc['epe_p95']:.2f} px, {time.perf_counter() - t:.1f} s, "
            f"ok={r.quality.ok}",
            flush=True,
        )
        print("\n".join(lines), flush=True)


RC_PRESETS = {
    "default": {},
    "weak": {"preset": "weak"},
    "fast": {"preset": "fast"},
    "weak-fast": {"preset": "weak-fast"},
}


def _presets_row(tag, pair, presets):
    """One line: the identity's median EPE, then each preset's median / p95 EPE, time and ``ok``."""
    from radiokit.register import register

    f, m, d, mask = pair
    cells = []
    for p in presets:
        t = time.perf_counter()
        r = register(f, m, "rc", **RC_PRESETS[p])
        sec = time.perf_counter() - t
        s = score(r.displacement, d, mask)
        cells.append(f"{p} {s['epe_median']:.2f}/{s['epe_p95']:.2f} {sec:.1f}s {'ok' if r.quality.ok else '!'}")
    print(f"{tag:<52} id {score(0 * d, d, mask)['epe_median']:.2f} | " + " | ".join(cells), flush=True)


def presets_part(which, split):
    """rc's presets side by side on ``split`` seeds (benchmarks/README.md, issue 11, third session)."""
    from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family, family_pair

    seeds = TRAIN_SEEDS if split == "train" else TEST_SEEDS
    if which == "weak":
        for tex, s in [(0.01, seeds[0]), (0.01, seeds[1]), (0.02, seeds[2]), (0.0, seeds[0])]:
            c = Case(size=2240, texture=tex, noise=0.01, corr=0.1, seed=s)
            _presets_row(c.label(), family_pair(c), list(RC_PRESETS))
    elif which == "rich":
        for kind in ("thinning", "gain"):
            _presets_row(
                f"analytic_pair 2240 {kind} seed 1",
                analytic_pair(2240, 0.01, 0.10, 0.01, seed=1, kind=kind),
                list(RC_PRESETS),
            )
        for s in seeds[:2]:
            c = Case(size=2240, texture=0.1, noise=0.01, corr=0.1, seed=s)
            _presets_row(c.label(), family_pair(c), ["default", "weak"])
    else:
        for c in family(split, 560, n_seeds=1, grid="map"):
            if c.texture > 0 or c.corr == 0.25:
                _presets_row(c.label(), family_pair(c), ["default", "weak"])
        for pre in ("seed-breast", "pva-phantom"):
            _presets_row(f"sim {pre} 560 noisy", sim_pair(pre, moving_step=-1, noisy=True, size=560), list(RC_PRESETS))


def _auto_row(tag, pair, fast_only=False):
    """One pair: median / p95 EPE and ``ok`` of default, weak, silent, auto (and the fast ones),
    and what ``auto`` / ``auto-fast`` returned. ``auto-fast`` returns the plain preset's run when
    it passes its own checks or there is no interior to judge, else the better of it and the weak
    (textured interior) or silent (silent body) preset's run (``register_auto``'s rule), so its
    result is one of the rows, taken from them rather than registered again; the time of a
    fallback is both runs'. ``auto`` is registered as it is: its plain run may go on at
    its finest level (``_auto.EXTEND``) and, over the checks' ~0.4 Mpx, stop early
    (``_auto.ABANDON``), neither of which the plain preset's row does."""
    from radiokit.register import register
    from radiokit.register._auto import AUTO_PRESETS, checks_silent, choose, returned, straight_to_weak

    f, m, d, mask = pair
    res, chose, quality = {}, {}, {}

    def run(p):  # registered and scored into res; the Registration
        t = time.perf_counter()
        r = register(f, m, "rc", preset=p)
        s = score(r.displacement, d, mask)
        res[p] = (s["epe_median"], s["epe_p95"], time.perf_counter() - t, r.quality.ok)
        return r

    names = _AUTO_ROW[1] if fast_only else _AUTO_ROW[0] + _AUTO_ROW[1]
    for p in names:
        quality[p] = run(p).quality
    fallback = {name: choose(f, name) for name in AUTO_PRESETS}
    for name, (plain, *_) in AUTO_PRESETS.items():
        if plain not in res:
            continue
        if name == "auto":  # its plain run extends (_auto.EXTEND) and, over ~0.4 Mpx, may stop early
            chose[name] = run(name).options["preset"]
            continue
        other = fallback[name].preset
        if straight_to_weak(name, "rc", other, f.shape, {"preset": name}, False) and other in res:
            res[name], chose[name] = res[other], other  # the plain run skipped (frames over 1.6 Mpx)
            continue
        tried = (not res[plain][3] or checks_silent(name, quality[plain], other)) and other != plain
        use = returned(name, quality[plain], other, quality.get(other))
        v = res[use]
        res[name] = v if not tried else (v[0], v[1], res[other][2] + res[plain][2], v[3])
        chose[name] = use
    cells = [
        f"{p} {v[0]:.2f}/{v[1]:.2f}{'' if v[3] else '!'}" + (f" {v[2]:.1f}s" if p.startswith("auto") else "")
        for p in _AUTO_ROW[0] + ("auto",) + _AUTO_ROW[1] + ("auto-fast",)
        if (v := res.get(p)) is not None
    ]
    print(
        f"{tag:<50} ratio {fallback['auto'].ratio:6.2f} -> {'/'.join(chose.values())} "
        f"id {score(0 * d, d, mask)['epe_median']:.2f} | " + " | ".join(cells),
        flush=True,
    )
    return dict(tag=tag, ratio=fallback["auto"].ratio, chose=chose.get("auto"), res=res)


_AUTO_ROW = (("default", "weak", "silent"), ("fast", "weak-fast", "silent-fast"))


def _auto_summary(rows):
    """Median, 95th percentile and mean over the rows of each preset's median EPE."""
    for p in _AUTO_ROW[0] + ("auto",) + _AUTO_ROW[1] + ("auto-fast",):
        v = np.array([r["res"][p][0] for r in rows if r["res"].get(p) is not None])
        if v.size:
            print(
                f"  {p:<10} over {v.size} pairs: median of medians {np.median(v):.2f} px, "
                f"p95 of medians {np.percentile(v, 95):.2f} px, mean {v.mean():.2f} px",
                flush=True,
            )


def auto_part(split, seeds):
    """``preset="auto"`` against default, weak and silent (issue 11, sessions 6-7): the 560 map on
    ``seeds`` seeds, the physical motion with and without texture, the simulated pairs (the
    paper's step and the largest), the 2240 weak-texture and textureless pairs, analytic_pair 2240."""
    from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family, family_pair

    ss = TRAIN_SEEDS if split == "train" else TEST_SEEDS
    rows = [_auto_row(c.label(), family_pair(c)) for c in family(split, 560, n_seeds=seeds, grid="map")]
    print("560 map:", flush=True)
    _auto_summary(rows)
    for tex in (0.0, 0.01):  # a compressed body's motion: uniform expansion, a lag around a stiffer disc
        c = Case(size=560, texture=tex, noise=0.01, corr=0.0, motion="physical", seed=ss[0])
        _auto_row(c.label(), family_pair(c))
    _sim_auto_rows()
    for tex, s in [(0.01, ss[0]), (0.01, ss[1]), (0.02, ss[2]), (0.0, ss[0])]:
        c = Case(size=2240, texture=tex, noise=0.01, corr=0.1, seed=s)
        _auto_row(c.label(), family_pair(c))
    for kind in ("thinning", "gain"):
        _auto_row(f"analytic_pair 2240 {kind} seed 1", analytic_pair(2240, 0.01, 0.10, 0.01, seed=1, kind=kind))


def _sim_auto_rows():
    """``_auto_row`` on the simulated pairs of both scene presets, 560 px, noisy: the paper's pair
    (the step before) and the largest motion (the first step)."""
    for pre in ("seed-breast", "pva-phantom"):
        for step in (-1, 1):
            _auto_row(f"sim {pre} 560 noisy, step {step}", sim_pair(pre, moving_step=step, noisy=True, size=560))


def silent_part(split, seeds):
    """``auto`` on silent bodies (issue 11, session 7), where it falls back to ``silent``: the 560
    map's textureless and 0.3x-noise cells and the physical motion with and without texture at
    0.3x the noise, on ``seeds`` seeds each; the simulated pairs (both steps) and the textureless
    2240 pair once."""
    from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair

    ss = TRAIN_SEEDS if split == "train" else TEST_SEEDS
    rows = []
    for s in ss[:seeds]:
        cases = [Case(size=560, texture=t, noise=0.01, corr=c, seed=s) for t in (0.0, 0.003) for c in (0.25, 0.1, 0.05)]
        cases += [Case(size=560, texture=t, noise=0.01, corr=0.0, motion="physical", seed=s) for t in (0.0, 0.003)]
        rows += [_auto_row(c.label(), family_pair(c)) for c in cases]
    print(f"560, silent bodies ({len(rows)} pairs):", flush=True)
    _auto_summary(rows)
    _sim_auto_rows()
    c = Case(size=2240, texture=0.0, noise=0.01, corr=0.1, seed=ss[0])
    _auto_row(c.label(), family_pair(c))


def natural_pair(name, size, seed=1):
    """A natural image of scikit-image (``camera``, ``moon``) scaled to ``size`` and to 0-1, as
    rich texture of a kind ``regdata`` does not make: fixed = moving warped by a smooth local
    field (1 % of the frame, 2-3 periods across it), +-10 % gain across the frame, noise 0.004
    on both. ``(fixed, moving, truth, mask)``, the mask the central 80 %
    (``bench_register_natural.natural``'s smooth motion)."""
    from bench_register_natural import natural

    return natural(name, size, "sine", "test", seed=seed)


def natural_part():
    """``auto`` on natural images (camera, moon at 1120 and 2240): the texture ratio reads them
    as weak texture, so only the plain preset's own check and the misaligned comparison keep
    ``weak`` (which loses there) out."""
    for size in (1120, 2240):
        for name in ("camera", "moon"):
            _auto_row(f"natural {name} {size}", natural_pair(name, size))


def auto_features_part(split):
    """The interior texture-to-noise ratio (``radiokit.register._auto``) of the fixed image
    over the regimes, no registration: the 560 map (2 seeds) and spread cases, 1120 and 2240
    family pairs, analytic_pair 560-2240, the simulated pairs noisy and noise-free."""
    from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family, family_pair

    from radiokit.register._auto import choose, interior_texture_to_noise

    ss = TRAIN_SEEDS if split == "train" else TEST_SEEDS

    def row(tag, f):
        ratio, interior, noise = interior_texture_to_noise(f)
        print(
            f"{tag:<52} {ratio:7.2f}  noise/floor {noise:6.2f} -> fallback {choose(f).preset:<8}"
            f"(interior {100 * interior:.0f} % of the binned frame)",
            flush=True,
        )

    for c in family(split, 560, n_seeds=2, grid="map") + family(split, 560, n_seeds=1, grid="spread"):
        row(c.label(), family_pair(c)[0])
    for pre in ("seed-breast", "pva-phantom"):
        for noisy in (True, False):
            row(
                f"sim {pre} 560 {'noisy' if noisy else 'noise-free'}",
                sim_pair(pre, moving_step=-1, noisy=noisy, size=560)[0],
            )
    for size in (1120, 2240):
        for tex, i in [(0.0, 0), (0.0, 1), (0.003, 0), (0.01, 0), (0.01, 1), (0.02, 2), (0.03, 0), (0.1, 0)]:
            c = Case(size=size, texture=tex, noise=0.01, corr=0.1, seed=ss[i])
            row(c.label(), family_pair(c)[0])
    for size in (560, 1120, 2240):
        for kind in ("thinning", "gain"):
            for seed in (1, 2):
                row(
                    f"analytic_pair {size} {kind} seed {seed}",
                    analytic_pair(size, 0.01, 0.10, 0.01, seed=seed, kind=kind)[0],
                )


# the data term before issue 11's session 8, and its three changes in turn (rc's module docstring)
_BIAS_STEPS = (
    ("images high-passed (before)", dict(highpass_on="images", smooth=0.0, gain=0.0)),
    ("+ the residual high-passed", dict(highpass_on="residual", smooth=0.0, gain=0.0)),
    ("+ levels smoothed by 1 px", dict(highpass_on="residual", smooth=1.0, gain=0.0)),
    ("+ the thinning term (now)", {}),
)


def bias_part(size, seed, preset="weak"):
    """What each change of the data term does, on one TRAINING pair of the family (texture =
    noise, correlation 1/10) at ``size``: registered from the truth (the moving image warped by
    it; the field found is the drift of the energy's minimum off the truth) and from the
    identity, noise-free without and with the 10 % thinning, then as the family makes it."""
    from regdata import Case, family_pair

    from radiokit.register import register, warp

    print(f"| pair ({size}, training seed {seed}, {preset}) | data term | drift from the truth | EPE from identity |")
    print("|---|---|---|---|")
    cases = (
        ("noise-free, no intensity change", dict(noise=0.0, intensity=0.0)),
        ("noise-free, 10 % thinning", dict(noise=0.0)),
        ("noise 0.01, 10 % thinning", {}),
    )
    for label, case in cases:
        f, m, d, mask = family_pair(Case(**{**dict(size=size, texture=0.01, noise=0.01, corr=0.1, seed=seed), **case}))
        at_truth = warp(m, d, order=3)  # the truth's warp, cubic
        for name, opts in _BIAS_STEPS:
            drift = score(register(f, at_truth, "rc", preset=preset, **opts).displacement, 0 * d, mask)
            e = score(register(f, m, "rc", preset=preset, **opts).displacement, d, mask)
            print(
                f"| {label} | {name} | {drift['epe_median']:.2f} / {drift['epe_p95']:.2f} px "
                f"| {e['epe_median']:.2f} / {e['epe_p95']:.2f} px |",
                flush=True,
            )


def regimes_part(opts):
    """rc with the options ``opts`` (JSON) over the regimes the data term was compared on
    (TRAINING seeds; natural images seed 1): 2240 weak texture, 2240 rich texture, the 560 map,
    natural images at 1120, the 560 physical motion without texture; the geometric mean of the
    median EPE per regime (benchmarks/README.md, "The data term's bias (session 8)")."""
    from regdata import Case, family_pair

    from radiokit.register import register

    def run(tag, pair):
        f, m, d, mask = pair
        t = time.perf_counter()
        r = register(f, m, "rc", **opts)
        sc = score(r.displacement, d, mask)
        print(f"  {tag}: {sc['epe_median']:.3f} / {sc['epe_p95']:.2f} px, {time.perf_counter() - t:.1f} s", flush=True)
        return sc["epe_median"]

    def family(tag, **case):
        return run(tag, family_pair(Case(**{**dict(noise=0.01, corr=0.1), **case})))

    regimes = {
        "2240 weak texture": lambda: (
            [family(f"2240 s{s}", size=2240, texture=0.01, seed=s) for s in (4, 5)]
            + [family("2240 gain s6", size=2240, texture=0.01, seed=6, kind="gain")]
        ),
        "2240 rich": lambda: (
            [family("2240 texture 10x s1", size=2240, texture=0.1, seed=1)]
            + [
                run(f"analytic 2240 {k} s0", analytic_pair(2240, 0.01, 0.10, 0.01, seed=0, kind=k))
                for k in ("thinning", "gain")
            ]
        ),
        "560 map": lambda: [
            family(f"560 t/n {t} corr {c:g}", size=560, texture=0.01 * t, corr=c, seed=0)
            for t in (0.3, 1, 3, 10)
            for c in (0.25, 0.1, 0.05)
        ],
        "natural 1120": lambda: [run(f"{n} 1120", natural_pair(n, 1120)) for n in ("camera", "moon")],
        "560 physical, no texture": lambda: [
            family(f"560 physical s{s}", size=560, texture=0.0, corr=0.0, motion="physical", seed=s) for s in (0, 1)
        ],
    }
    print(f"rc {opts}", flush=True)
    for name, make in regimes.items():
        print(f"{name}: geometric mean {float(np.exp(np.mean(np.log(make())))):.3f} px", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=1120)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench_register"))
    ap.add_argument(
        "--sim",
        help="also a simulated experiment: a file (radiokit sim run) or a scene preset "
        "(e.g. seed-breast; simulated once, cached in out/regdata_cache); the last two "
        "steps, noise-free line integrals and corrected noisy frames",
    )
    ap.add_argument("--skip", default="", help="methods to leave out, comma-separated (e.g. mi: 26 s at 512)")
    ap.add_argument("--family-only", action="store_true", help="only part 3, the textureless-phantom family")
    ap.add_argument("--family-size", type=int, default=560, help="the family's frame size (560-2240)")
    ap.add_argument("--family-seeds", type=int, default=1, help="test seeds per family cell")
    ap.add_argument(
        "--family-sim",
        default="seed-breast,pva-phantom",
        help="scene presets whose simulated pairs join the family (comma-separated; '' for none)",
    )
    ap.add_argument(
        "--levels",
        metavar="JSON",
        nargs="*",
        help="only the per-level diagnosis: rc's EPE after each pyramid level on one TRAINING pair "
        "(texture = noise, correlation 1/10) at --size and binned by 2, for each JSON option set "
        "(e.g. '{}' '{\"preset\": \"weak\"}')",
    )
    ap.add_argument("--seed", type=int, default=1, help="the training seed of --levels and --bias")
    ap.add_argument(
        "--regimes",
        metavar="JSON",
        nargs="*",
        help="only rc over the regimes the data term was compared on (TRAINING seeds), for each JSON "
        'option set (e.g. \'{"preset": "weak"}\' \'{"preset": "weak", "gain": 0}\')',
    )
    ap.add_argument(
        "--bias",
        metavar="PRESET",
        nargs="?",
        const="weak",
        help="only the data term's bias: drift from the truth and EPE from identity as each of its "
        "changes is added (rc's module docstring), one TRAINING pair at --size (e.g. --size 2240 --bias)",
    )
    ap.add_argument(
        "--presets",
        choices=["weak", "rich", "map", "auto", "auto-features", "natural", "silent"],
        help="only rc's presets side by side (issue 11): 'weak' the 2240 weak-texture pairs, 'rich' "
        "analytic_pair and texture 10x noise at 2240, 'map' the 560 map (one seed) and the "
        "simulated pairs; 'auto' preset='auto' against default and weak on all of those (--seeds seeds "
        "of the 560 map); 'auto-features' only auto's texture-to-noise ratio over the regimes; 'natural' "
        "auto on scikit-image's camera and moon, warped; 'silent' auto on silent bodies (--seeds seeds "
        "of the textureless and 0.3x-noise cells and the physical motion), the simulated pairs, 2240 textureless)",
    )
    ap.add_argument("--seeds", type=int, default=2, help="the 560 map's seeds per cell of --presets auto")
    ap.add_argument("--split", choices=["train", "test"], default="test", help="the seeds of --presets")
    args = ap.parse_args(argv)
    if args.presets == "auto-features":
        auto_features_part(args.split)
        return 0
    if args.presets == "auto":
        auto_part(args.split, args.seeds)
        return 0
    if args.presets == "natural":
        natural_part()
        return 0
    if args.presets == "silent":
        silent_part(args.split, args.seeds)
        return 0
    if args.presets:
        presets_part(args.presets, args.split)
        return 0
    if args.bias:
        bias_part(args.size, args.seed, args.bias)
        return 0
    if args.regimes is not None:
        for opts in args.regimes or ["{}"]:
            regimes_part(json.loads(opts))
        return 0
    if args.levels is not None:
        for opts in args.levels or ["{}"]:
            levels_part(args.size, args.seed, json.loads(opts))
        return 0
    args.family_sim = [x.strip() for x in args.family_sim.split(",") if x.strip()]
    if args.quick:  # the family at 384 px without the simulated pairs (about 3 minutes)
        args.family_size, args.family_sim = min(args.family_size, 384), []
    size = 512 if args.quick else args.size
    args.out.mkdir(parents=True, exist_ok=True)
    skip = {x.strip() for x in args.skip.split(",") if x.strip()}
    cfgs = [(n, o) for n, o in configs() if n not in skip and n.split("+")[0] not in skip]
    warm_up([(n, o) for n, o in cfgs if n in FAMILY_METHODS] if args.family_only else cfgs)
    fam = family_part(args, cfgs)
    family_charts(fam, args.out)
    if args.family_only:
        (args.out / "bench_family.json").write_text(
            json.dumps({"size": args.family_size, "rows": fam, "confusion": confusion(fam)}, indent=1, default=float)
        )
        print(f"chart {args.out / 'family_maps.png'}")
        return 0
    results = {}
    kinds = ["thinning", "gain"] + (["sim", "sim-noisy"] if args.sim else [])
    for kind in kinds:
        if kind.startswith("sim"):
            fixed, moving, truth, mask = sim_pair(
                args.sim, moving_step=-1, noisy=kind == "sim-noisy", size=None if args.size >= 2240 else size
            )
        else:
            fixed, moving, truth, mask = analytic_pair(size, 0.01, 0.10, 0.01, seed=1, kind=kind)
        base = score(np.zeros_like(truth), truth, mask)
        rows = [run_one(n, o, fixed, moving, truth, mask) for n, o in cfgs]
        results[kind] = {"identity": base, "rows": rows, "pareto": pareto(rows)}
        what = (
            f"{args.sim} {fixed.shape[0]}x{fixed.shape[1]} (last two steps, "
            f"{'corrected noisy frames' if kind == 'sim-noisy' else 'noise-free line integrals'})"
            if kind.startswith("sim")
            else f"{size}x{size}: 1 % displacement, 10 % intensity change"
        )
        print(f"\n{kind} pair {what}; identity EPE median {base['epe_median']:.3f} px")
        print(f"  {'method':<16} {'time s':>8} {'EPE med':>8} {'EPE p95':>8} {'folds':>6}  ok")
        for r in rows:
            if "error" in r:
                print(f"  {r['method']:<16} error: {r['error'][:80]}")
                continue
            mark = " *" if r["method"] in results[kind]["pareto"] else ""
            print(
                f"  {r['method']:<16} {r['seconds']:8.2f} {r['epe_median']:8.3f} {r['epe_p95']:8.3f} "
                f"{r['folds']:6d}  {r['ok']}{mark}"
            )
        print("  (* on the Pareto front: nothing both faster and more accurate)")

    # stability map: displacement x intensity change x noise
    disp = [0.01, 0.02, 0.04]
    inten = [0.0, 0.1, 0.2]
    noises = [0.01, 0.03]
    names = [n for n, _ in cfgs]
    stab_names = ["rc", "rc-fast"] + [
        n for n in ("dis+hp", "elastix+hp", "sitk-demons+hp", "tvl1+hp", "farneback+hp") if n in names
    ]
    if args.quick:
        stab_names = stab_names[:4]
        noises = noises[:1]
    stab_methods = [(n, dict(cfgs)[n]) for n in stab_names]
    shape = (len(noises), len(disp), len(inten))
    smap = {n: np.full(shape, np.nan) for n, _ in stab_methods}
    worse = {n: np.zeros(shape, bool) for n, _ in stab_methods}
    ssize = 384 if args.quick else min(size, 768)
    for h, noise in enumerate(noises):
        for i, dfrac in enumerate(disp):
            for j, ic in enumerate(inten):
                fixed, moving, truth, mask = analytic_pair(ssize, dfrac, ic, noise, seed=2 + i + 10 * j + 100 * h)
                base = score(np.zeros_like(truth), truth, mask)["epe_median"]
                for n, o in stab_methods:
                    r = run_one(n, o, fixed, moving, truth, mask)
                    smap[n][h, i, j] = r.get("epe_median", np.nan)
                    worse[n][h, i, j] = r.get("epe_median", np.inf) >= base
    print(
        f"\nstability ({ssize}x{ssize}, thinning): EPE median (px); rows displacement {disp} of the frame, "
        f"columns intensity change {inten}; '!' = no better than not registering"
    )
    for h, noise in enumerate(noises):
        print(f" noise {noise}")
        for n, _ in stab_methods:
            cells = [
                "  ".join(f"{smap[n][h, i, j]:7.3f}{'!' if worse[n][h, i, j] else ' '}" for j in range(len(inten)))
                for i in range(len(disp))
            ]
            print(f"  {n:<16}" + "  |  ".join(cells))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, len(results), figsize=(6.5 * len(results), 5))
    for ax, kind in zip(axs, results):
        rows = [r for r in results[kind]["rows"] if "error" not in r]
        for r in rows:
            on = r["method"] in results[kind]["pareto"]
            ax.scatter(r["seconds"], max(r["epe_median"], 1e-3), marker="o" if on else "x", color="C3" if on else "C0")
            ax.annotate(r["method"], (r["seconds"], max(r["epe_median"], 1e-3)), fontsize=7)
        front = sorted((r for r in rows if r["method"] in results[kind]["pareto"]), key=lambda r: r["seconds"])
        ax.plot([r["seconds"] for r in front], [r["epe_median"] for r in front], "C3-", lw=0.8)
        ax.axhline(results[kind]["identity"]["epe_median"], color="grey", ls="--", lw=0.8, label="no registration")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per pair (s)")
        ax.set_ylabel("end-point error, median (px)")
        ax.set_title(
            f"simulated {args.sim}, last two steps{', noisy' if kind == 'sim-noisy' else ''}"
            if kind.startswith("sim")
            else f"{kind}: {size}x{size}, 1 % motion, 10 % intensity change"
        )
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "bench_register.png", dpi=110)
    fig, axs = plt.subplots(
        len(noises), len(stab_methods), figsize=(2.9 * len(stab_methods), 2.9 * len(noises)), squeeze=False
    )
    for h, noise in enumerate(noises):
        for ax, (n, _) in zip(axs[h], stab_methods):
            im = ax.imshow(np.log10(np.maximum(smap[n][h], 1e-3)), cmap="viridis", vmin=-1.5, vmax=1.5, origin="lower")
            for i in range(len(disp)):
                for j in range(len(inten)):
                    ax.text(
                        j,
                        i,
                        f"{smap[n][h, i, j]:.2f}{'!' if worse[n][h, i, j] else ''}",
                        ha="center",
                        va="center",
                        color="w",
                        fontsize=8,
                    )
            ax.set_xticks(range(len(inten)), [f"{100 * v:.0f}%" for v in inten])
            ax.set_yticks(range(len(disp)), [f"{100 * v:.0f}%" for v in disp])
            ax.set_xlabel("intensity change")
            ax.set_ylabel("displacement")
            ax.set_title(f"{n}, noise {noise}", fontsize=9)
    fig.colorbar(im, ax=axs, fraction=0.02, label="log10 EPE median (px); '!' no better than identity")
    fig.savefig(args.out / "stability.png", dpi=110)
    (args.out / "bench_register.json").write_text(
        json.dumps(
            {
                "size": size,
                "pairs": results,
                "family": {"size": args.family_size, "rows": fam, "confusion": confusion(fam)},
                "stability": {
                    "size": ssize,
                    "noise": noises,
                    "displacement": disp,
                    "intensity": inten,
                    "epe_median": {n: smap[n].tolist() for n in smap},
                    "no_better_than_identity": {n: worse[n].tolist() for n in worse},
                },
            },
            indent=1,
            default=float,
        )
    )
    print(f"charts {args.out / 'bench_register.png'}, {args.out / 'stability.png'}")
    return 0


# -- part 3: the textureless-phantom family (issue 11) -----------------------------------------

FAMILY_METHODS = ("rc", "rc-fast", "rc-weak", "rc-weak-fast", "elastix+hp", "dis+hp")


def family_part(args, cfgs):
    """Every method of FAMILY_METHODS on the family's test seeds: maps of median EPE over
    texture-to-noise x correlation length (identity beside), the spread cases, the simulated
    pairs of both presets, and the confusion table of ``quality.ok`` against the truth."""
    from regdata import family, family_pair

    names = dict(cfgs)
    methods = [(n, names[n]) for n in FAMILY_METHODS if n in names]
    rows = []
    cases = family("test", args.family_size, grid="all", n_seeds=args.family_seeds)
    for c in cases:
        pair = family_pair(c)
        rows += _family_rows(
            pair,
            methods,
            dict(
                case=c.label(),
                t2n=c.t2n,
                corr=c.corr,
                motion=c.motion,
                domain=c.domain,
                texture=c.texture,
                noise=c.noise,
                spread=not (
                    c.amplitude == 0.01
                    and c.motion == "random"
                    and c.noise == 0.01
                    and c.domain == "log"
                    and c.noise_kind == "gaussian"
                    and c.intensity == 0.1
                    and c.kind == "thinning"
                ),
            ),
        )
    for preset in args.family_sim:
        pair = sim_pair(preset, moving_step=-1, noisy=True, size=args.family_size)
        rows += _family_rows(
            pair,
            methods,
            dict(
                case=f"sim {preset} {pair[0].shape[0]} noisy",
                t2n=None,
                corr=None,
                motion="sim",
                domain="log",
                spread=True,
            ),
        )
    _print_family(rows, methods, args)
    return rows


def _family_rows(pair, methods, meta):
    fixed, moving, truth, mask = pair
    ident = score(np.zeros_like(truth), truth, mask)
    out = [
        dict(
            meta,
            method="identity",
            epe_median=ident["epe_median"],
            epe_p95=ident["epe_p95"],
            seconds=0.0,
            ok=None,
            identity=ident["epe_median"],
        )
    ]
    from radiokit.register import register

    for name, opts in methods:
        method = _method_of(name)
        t = time.perf_counter()
        try:
            reg = register(fixed, moving, method, **opts)
        except Exception as exc:  # a peer that cannot run is reported, not fatal
            out.append(dict(meta, method=name, error=repr(exc)))
            continue
        sec = time.perf_counter() - t
        s = score(reg.displacement, truth, mask)
        obs = (reg.confidence >= 0.5) & mask if reg.confidence is not None else np.zeros_like(mask)
        e = np.hypot(*(reg.displacement - truth))
        out.append(
            dict(
                meta,
                method=name,
                seconds=sec,
                epe_median=s["epe_median"],
                epe_p95=s["epe_p95"],
                ok=bool(reg.quality.ok),
                reason=reg.quality.reason,
                identity=ident["epe_median"],
                observed=float(obs.sum() / mask.sum()),
                epe_observed=float(np.median(e[obs])) if obs.sum() > 50 else None,
            )
        )
    line = " ".join(
        f"{r['method']} {r.get('epe_median', float('nan')):.2f}{'' if r.get('ok') in (None, True) else '!'}"
        for r in out
    )
    print(f"  {meta['case']:<62} {line}", flush=True)
    return out


def confusion(rows):
    """``quality.ok`` against the truth: failed = median EPE > max(1 px, half the identity's),
    good = median EPE <= 0.5 px."""
    res = [r for r in rows if r["method"] != "identity" and "error" not in r]
    failed = [r for r in res if r["epe_median"] > max(1.0, 0.5 * r["identity"])]
    good = [r for r in res if r["epe_median"] <= 0.5]
    return dict(
        failed=len(failed),
        failed_flagged=sum(not r["ok"] for r in failed),
        good=len(good),
        good_ok=sum(bool(r["ok"]) for r in good),
        n=len(res),
    )


def _map(rows, method, t2ns, corrs):
    m = np.full((len(t2ns), len(corrs)), np.nan)
    for i, t in enumerate(t2ns):
        for j, c in enumerate(corrs):
            v = [
                r["epe_median"]
                for r in rows
                if r["method"] == method
                and not r.get("spread")
                and "error" not in r
                and r["t2n"] == t
                and r["corr"] == c
            ]
            m[i, j] = np.median(v) if v else np.nan
    return m


def _print_family(rows, methods, args):
    t2ns = sorted({r["t2n"] for r in rows if not r.get("spread")})
    corrs = sorted({r["corr"] for r in rows if not r.get("spread")}, reverse=True)
    print(
        f"\nfamily maps ({args.family_size} px, test seeds, {args.family_seeds} per cell): median EPE (px); rows "
        f"texture/noise {t2ns}, columns correlation length {[f'1/{round(1 / c)}' for c in corrs]} of the frame"
    )
    for name in ["identity"] + [n for n, _ in methods]:
        m = _map(rows, name, t2ns, corrs)
        print(f"  {name:<12} " + "  |  ".join(" ".join(f"{v:6.2f}" for v in m[i]) for i in range(len(t2ns))))
    print("\nspread and simulated cases (median EPE px, p95, time s, ok):")
    for case in dict.fromkeys(r["case"] for r in rows if r.get("spread")):
        rs = [r for r in rows if r["case"] == case]
        print(
            f"  {case:<58} "
            + " | ".join(
                f"{r['method']} "
                + (
                    f"{r['epe_median']:.2f}/{r['epe_p95']:.2f} {r['seconds']:.1f}s"
                    f"{'' if r.get('ok') in (None, True) else ' !'}"
                    if "error" not in r
                    else "error"
                )
                for r in rs
            )
        )
    c = confusion(rows)
    print(
        f"\nquality.ok against the truth, all methods, {c['n']} results: failed (median EPE > max(1 px, half the "
        f"identity's)) {c['failed']}, flagged not ok {c['failed_flagged']} "
        f"({100 * c['failed_flagged'] / max(c['failed'], 1):.0f} %); good (<= 0.5 px) {c['good']}, ok "
        f"{c['good_ok']} ({100 * c['good_ok'] / max(c['good'], 1):.0f} %)"
    )
    for name, _ in methods:
        cm = confusion([r for r in rows if r["method"] == name])
        print(
            f"  {name:<12} failed {cm['failed']} flagged {cm['failed_flagged']}; good {cm['good']} ok {cm['good_ok']}"
        )


def family_charts(rows, out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t2ns = sorted({r["t2n"] for r in rows if not r.get("spread")})
    corrs = sorted({r["corr"] for r in rows if not r.get("spread")}, reverse=True)
    names = list(dict.fromkeys(r["method"] for r in rows))
    fig, axs = plt.subplots(1, len(names), figsize=(2.9 * len(names) + 1.0, 3.6), squeeze=False, layout="constrained")
    for ax, name in zip(axs[0], names):
        m = _map(rows, name, t2ns, corrs)
        im = ax.imshow(np.log10(np.maximum(m, 1e-2)), cmap="viridis", vmin=-1.5, vmax=1.0, origin="lower")
        for i in range(len(t2ns)):
            for j in range(len(corrs)):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", color="w", fontsize=8)
        ax.set_xticks(range(len(corrs)), [f"1/{round(1 / c)}" for c in corrs])
        ax.set_yticks(range(len(t2ns)), [f"{t:g}" for t in t2ns])
        ax.set_xlabel("correlation length / frame")
        ax.set_ylabel("texture / noise")
        ax.set_title(name, fontsize=9)
    fig.colorbar(im, ax=axs, fraction=0.02, label="log10 median EPE (px)")
    fig.savefig(out_dir / "family_maps.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
