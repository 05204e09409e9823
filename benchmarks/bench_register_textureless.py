"""Why is the error large where the map says "observed" on a truly textureless pair? (issue 11)

Run (from the repository root, after ``bench_register_flag.py --split train --size 560 --seeds 2``,
whose cached fields it reads; a field not cached is registered and cached the same way)::

    python benchmarks/bench_register_textureless.py [--split train] [--seeds 2] [--size 560]

For every truly textureless pair of the family (texture 0: correlation 1/4, 1/10, 1/20 and the
physical motion) and every method of ``bench_register_flag``, the error where the library's map
says observed is split

- into its component along the window's dominant gradient direction (the principal eigenvector
  of the fixed image's structure tensor in the map's window, as ``_confidence._lmin`` builds it:
  normal to an edge) and the perpendicular one (tangential);
- by region: the inclusion (within one window of the disc's edge, its inside too), the body's
  edge band (within two windows of the body's outline) and elsewhere.

Beside it, the window's bound along each axis (``_confidence``'s bound is the larger one, from
the smaller eigenvalue) and the error of the best field a window's translation could give: the
truth averaged over the window (what a method that locked each window's shift would leave).

``--distance``: the error's components against the distance inside the body's outline (the disc's
neighbourhood left out), every pixel of the body, with the share the map calls observed.
``--variants``: stricter maps, which credit a window's smaller eigenvalue only beyond the share
``lmax / rho`` a smooth curved edge gives it (a field free at the window's scale absorbs that
share as a rotation), and the library's map with its window cut at one spacing instead of two,
the texture cases beside (rc's field).
``--normal``: a normal-only map (the bound along the principal axis, from the larger eigenvalue,
<= 0.5 px) for windows of 24, 12 and 6 px, and ``rc-auto``'s normal error where it says
observed, over the whole body and over the scored mask.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_register_flag import _auto_choice, assess, registered
from regdata import TEST_SEEDS, TRAIN_SEEDS, Case, family_pair, gel_phantom

from radiokit.register import _WINDOW
from radiokit.register import _confidence as C

REGIONS = ("disc", "edge", "else")


def tensor(f, spacing=_WINDOW, highpass=0.25):
    """``(lmax, lmin, ny, nx)``: the window's structure tensor eigenvalues, each less the noise's
    share and the noise-only floor exactly as ``_confidence.observability`` treats the smaller, as
    information in the map's units (``1 / bound^2``), and the unit normal (principal eigenvector)."""
    f = np.asarray(f, np.float32)
    sig2 = C.noise_map(f, spacing) ** 2
    floor2 = C.model_floor(f) ** 2
    hp = f - C._gauss(f, highpass * spacing)
    gy, gx = np.gradient(C._gauss(hp, 1.0))
    bias = C._deriv_noise_var(1.0) * sig2
    my, mx = C._window(gy, spacing), C._window(gx, spacing)
    jyy = C._window(gy * gy, spacing) - my * my - bias
    jxx = C._window(gx * gx, spacing) - mx * mx - bias
    jxy = C._window(gy * gx, spacing) - my * mx
    tr, det = jxx + jyy, jxx * jyy - jxy * jxy
    root = np.sqrt(np.maximum(0.25 * tr * tr - det, 0))
    scale = C._window_area(spacing) / (2 * (sig2 + floor2))
    noise = C._noise_lmin(spacing, highpass) * sig2
    lmax = np.maximum(0.5 * tr + root - noise, 0) * scale
    lmin = np.maximum(0.5 * tr - root - noise, 0) * scale
    ang = 0.5 * np.arctan2(2 * jxy, jyy - jxx)  # principal axis angle from the row axis
    return lmax, lmin, np.cos(ang), np.sin(ang)


def regions(case, n, mask):
    """Region labels (0 disc, 1 body edge band, 2 elsewhere) over the mask."""
    rng = np.random.default_rng(case.seed)
    _, body, (dr, dc, rad) = gel_phantom(n, rng, case.texture)
    import cv2

    dist_out = cv2.distanceTransform(body.astype(np.uint8), cv2.DIST_L2, 5)  # to the body's outline
    yy, xx = np.mgrid[0:n, 0:n]
    rdisc = np.hypot(yy - dr, xx - dc)
    lab = np.full((n, n), 2, np.int8)
    lab[dist_out < 2 * _WINDOW] = 1
    lab[rdisc < rad + _WINDOW] = 0
    lab[~mask] = -1
    return lab


def window_truth(truth, spacing=_WINDOW):
    """The truth averaged over the map's window: the best a per-window translation can give."""
    return np.stack([C._window(c, spacing) for c in truth])


def split(err, ny, nx, sel):
    """Median EPE, normal, tangential over ``sel`` (None when under 50 px)."""
    if sel.sum() < 50:
        return None
    nrm = np.abs(err[0] * ny + err[1] * nx)
    tan = np.abs(-err[0] * nx + err[1] * ny)
    return tuple(float(np.median(v[sel])) for v in (np.hypot(*err), nrm, tan))


def cases(split_name, size, n_seeds):
    seeds = (TRAIN_SEEDS if split_name == "train" else TEST_SEEDS)[:n_seeds]
    out = []
    for s in seeds:
        out += [Case(size=size, texture=0.0, noise=0.01, corr=c, seed=s) for c in (1 / 4, 1 / 10, 1 / 20)]
        out.append(Case(size=size, texture=0.0, noise=0.01, motion="physical", corr=0.0, amplitude=0.01, seed=s))
    return out


DIST_BINS = (0, 8, 16, 24, 32, 48, 72)


def distance_rows(case, fixed, truth, fields, conf):
    """Per method: normal / tangential median error (observed share) in each ``DIST_BINS`` band
    inside the body's outline, more than two windows from the disc."""
    import cv2

    n = fixed.shape[0]
    _, body, (dr, dc, rad) = gel_phantom(n, np.random.default_rng(case.seed), case.texture)
    dist = cv2.distanceTransform(body.astype(np.uint8), cv2.DIST_L2, 5)
    yy, xx = np.mgrid[0:n, 0:n]
    far = np.hypot(yy - dr, xx - dc) > rad + 2 * _WINDOW
    _, _, ny, nx = tensor(fixed)
    out = []
    for name, d in fields.items():
        e = d - truth
        nrm, tan = np.abs(e[0] * ny + e[1] * nx), np.abs(-e[0] * nx + e[1] * ny)
        cells = []
        for a, b in zip(DIST_BINS[:-1], DIST_BINS[1:]):
            s = body & far & (dist >= a) & (dist < b)
            cells.append(f"{np.median(nrm[s]):.2f} / {np.median(tan[s]):.2f} ({100 * np.mean(conf[s] >= 0.5):.0f} %)")
        out.append(f"| {case.label()} | {name} | " + " | ".join(cells) + " |")
    return out


RHOS = (10, 20, 40)


def variant_cells(fixed, truth, d, mask):
    """Observed share and EPE (normal / tangential) where each map says observed: the library's,
    then the smaller eigenvalue credited beyond ``lmax / rho`` for each of ``RHOS``."""
    lmax, lmin, ny, nx = tensor(fixed)
    e = d - truth
    parts = (np.hypot(*e), np.abs(e[0] * ny + e[1] * nx), np.abs(-e[0] * nx + e[1] * ny))
    cells = []
    for rho in (None,) + RHOS:
        lm = lmin if rho is None else lmin - lmax / rho
        s = (1 / np.sqrt(np.maximum(lm, 1e-12)) <= C.OBSERVED_PX) & mask
        med = "-" if s.sum() < 50 else "{:.2f} ({:.2f} / {:.2f})".format(*(float(np.median(p[s])) for p in parts))
        cells.append(f"{100 * s.sum() / mask.sum():.0f} %, {med}")
    reach = C.WINDOW_REACH
    try:  # the library's map with its window cut at one spacing (two in the library)
        C.WINDOW_REACH = 1.0
        C._NOISE_DERIV.clear()  # the noise floor is measured with the window
        s = (C.observability(fixed, _WINDOW).confidence >= 0.5) & mask
    finally:
        C.WINDOW_REACH = reach
        C._NOISE_DERIV.clear()
    med = "-" if s.sum() < 50 else "{:.2f} ({:.2f} / {:.2f})".format(*(float(np.median(p[s])) for p in parts))
    cells.append(f"{100 * s.sum() / mask.sum():.0f} %, {med}")
    return cells


def fmt(t):
    return "-" if t is None else f"{t[0]:.2f} ({t[1]:.2f} / {t[2]:.2f})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=("train", "test"), default="train")
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--methods", default="rc,rc-fast,rc-weak,rc-silent,rc-silent-fast,rc-auto,dis+hp,elastix+hp")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--distance", action="store_true", help="the error against the distance inside the outline")
    ap.add_argument("--variants", action="store_true", help="stricter maps, textured cases beside (rc)")
    ap.add_argument("--normal", action="store_true", help="a normal-only map at three windows (rc-auto)")
    args = ap.parse_args(argv)
    from bench_register import configs

    from radiokit.register._auto import EXTEND

    out = args.out or Path(f"out/bench_register_flag/{args.split}-{args.size}")
    out.mkdir(parents=True, exist_ok=True)
    cfgs = dict(configs(), **{"rc-extend": {"extend": EXTEND}})
    want = [m.strip() for m in args.methods.split(",")]
    need = {n for n in want if n in cfgs} | ({"rc-extend", "rc-weak", "rc-silent"} if "rc-auto" in want else set())
    if args.normal:
        return normal_only(args, out, cfgs)
    if args.distance or args.variants:
        return extra(args, out, cfgs)
    print(
        "| case | method | observed % | map-observed EPE (normal / tangential) | disc | body edge | "
        "elsewhere | window-mean truth there |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for case in cases(args.split, args.size, args.seeds):
        fixed, moving, truth, mask = family_pair(case)
        label = case.label()
        regs = {}
        for name in sorted(need):
            d, info, sec = registered(out, label, name, cfgs[name], fixed, moving)
            regs[name] = assess(name, cfgs[name], fixed, moving, d, info, sec)
        if "rc-auto" in want:
            regs["rc-auto"] = regs[_auto_choice("rc-auto", fixed, regs)]
        lmax, lmin, ny, nx = tensor(fixed)
        lab = regions(case, args.size, mask)
        wt = window_truth(truth) - truth
        for name in ["identity"] + want:
            d = np.zeros_like(truth) if name == "identity" else regs[name].displacement
            obs = (regs["rc"].confidence >= 0.5) & mask  # the map depends on the fixed image only
            err = d - truth
            cells = [fmt(split(err, ny, nx, obs))]
            cells += [fmt(split(err, ny, nx, obs & (lab == r))) for r in range(3)]
            cells.append(fmt(split(wt, ny, nx, obs)))
            print(f"| {label} | {name} | {100 * obs.sum() / mask.sum():.0f} | " + " | ".join(cells) + " |", flush=True)
        # the map's observed pixels: how rank-1 are they, and the bounds along each axis
        bn, bt = 1 / np.sqrt(np.maximum(lmax, 1e-12)), 1 / np.sqrt(np.maximum(lmin, 1e-12))
        share = [100 * (obs & (lab == r)).sum() / max(obs.sum(), 1) for r in range(3)]
        print(
            f"|   | bounds where observed: normal {np.median(bn[obs]):.3f} px, tangential "
            f"{np.median(bt[obs]):.3f} px (p90 {np.percentile(bt[obs], 90):.3f}); lmax/lmin median "
            f"{np.median(lmax[obs] / np.maximum(lmin[obs], 1e-12)):.1f}; observed share disc/edge/else "
            f"{share[0]:.0f}/{share[1]:.0f}/{share[2]:.0f} % | | | | | |",
            flush=True,
        )


def extra(args, out, cfgs):
    """The ``--distance`` and ``--variants`` tables."""
    todo = cases(args.split, args.size, args.seeds)
    if args.variants:
        seeds = (TRAIN_SEEDS if args.split == "train" else TEST_SEEDS)[: args.seeds]
        todo += [Case(size=args.size, texture=0.01 * t, corr=0.1, seed=s) for s in seeds for t in (0.3, 1, 3)]
        head = " | ".join(["library"] + [f"rho {r}" for r in RHOS] + ["reach 1 spacing"])
        print(f"| case (rc) | {head} |\n|---|" + "---|" * (len(RHOS) + 2))
    else:
        bands = " | ".join(f"{a}-{b} px" for a, b in zip(DIST_BINS[:-1], DIST_BINS[1:]))
        print(f"| case | method | {bands} |\n|---|---|" + "---|" * (len(DIST_BINS) - 1))
    for case in todo:
        fixed, moving, truth, mask = family_pair(case)
        names = ["rc"] if args.variants else ["rc", "rc-silent", "elastix+hp"]
        fields = {n: registered(out, case.label(), n, cfgs[n], fixed, moving)[0] for n in names}
        if args.variants:
            print(
                f"| {case.label()} | " + " | ".join(variant_cells(fixed, truth, fields["rc"], mask)) + " |", flush=True
            )
        else:
            conf = C.observability(fixed, _WINDOW).confidence
            print("\n".join(distance_rows(case, fixed, truth, fields, conf)), flush=True)


def normal_only(args, out, cfgs):
    """The ``--normal`` table."""
    print("| case | " + " | ".join(f"window {w:g}: body / mask" for w in NORMAL_WINDOWS) + " |")
    print("|---|" + "---|" * len(NORMAL_WINDOWS))
    for case in cases(args.split, args.size, args.seeds):
        fixed, moving, truth, mask = family_pair(case)
        _, body, _ = gel_phantom(args.size, np.random.default_rng(case.seed), case.texture)
        regs = {}
        for n in ("rc-extend", "rc-weak", "rc-silent"):
            regs[n] = assess(n, cfgs[n], fixed, moving, *registered(out, case.label(), n, cfgs[n], fixed, moving))
        e = regs[_auto_choice("rc-auto", fixed, regs)].displacement - truth
        cells = []
        for w in NORMAL_WINDOWS:
            lmax, _, ny, nx = tensor(fixed, w)
            nrm = np.abs(e[0] * ny + e[1] * nx)
            obs = 1 / np.sqrt(np.maximum(lmax, 1e-12)) <= C.OBSERVED_PX
            part = []
            for where in (body, mask):
                s = obs & where
                med = f"{np.median(nrm[s]):.2f}" if s.sum() >= 50 else "-"
                part.append(f"{100 * s.sum() / where.sum():.0f} % {med}")
            cells.append(" / ".join(part))
        print(f"| {case.label()} | " + " | ".join(cells) + " |", flush=True)


NORMAL_WINDOWS = (24.0, 12.0, 6.0)


if __name__ == "__main__":
    main()
