"""Is ``quality.ok`` honest on pairs made differently from ``regdata`` and the held-out generators?

Run (from the repository root; 2 x 72 registrations at 256-512 px, about 3 minutes)::

    python benchmarks/bench_register_similarity.py [--presets default,fast] [--quick] [--jsonl out.jsonl]

Written in session 53 (s53reg) without tuning anything on it: nothing in ``radiokit.register`` was
chosen on these pairs, and nothing may be. Each pair: a scikit-image picture (grey, 0-1), cropped,
not resized, where it is large enough (upsampled by the least factor that fits the frame and a
margin where it is not); ``moving`` is the crop, ``fixed(x) = src(T(x))`` sampled from the same
picture by cubic interpolation (no border effects: the picture extends past the frame), so the
true pull field is ``d(x) = T(x) - x``; then independent Gaussian noise on each, and on ``mixed``
a gain of 0.9-1.1 on ``fixed``. ``T`` is a similarity transform about the frame's centre:

- ``shift``: a translation of 0.5-6 px per axis (sub-pixel, random signs);
- ``turn``: a rotation of 1-3 degrees (either sense);
- ``scale``: a scaling of 1-2 % (either way);
- ``mixed``: all three at once, plus the gain.

Pictures: the ones the earlier natural-image benchmarks used (camera, moon, brick, grass,
gravel, coins) and ones no benchmark used (text, page, clock, cell, horse (binary), binary_blobs,
shepp_logan_phantom, checkerboard, cat, immunohistochemistry, colorwheel, logo). Frames 256, 384
and 512 px, noise 0.5, 2 or 5 % of the 0-1 range (``--noises 0.1,0.2,0.3``: a noisier set), all
from the pair's index (seed ``5300 + i``).

Scored as the brief asks: EPE = the median over the frame's central 80 % of ``|d_est - d|``;
``bad`` when it exceeds max(1 px, half the identity's, the median ``|d|`` there). Prints every
pair, then per preset the confusion table of ``ok`` against ``bad``, and every trusted failure.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

PICTURES = (
    "camera",
    "moon",
    "brick",
    "grass",
    "gravel",
    "coins",
    "text",
    "page",
    "clock",
    "cell",
    "horse",
    "binary_blobs",
    "shepp_logan_phantom",
    "checkerboard",
    "cat",
    "immunohistochemistry",
    "colorwheel",
    "logo",
)
KINDS = ("shift", "turn", "scale", "mixed")
SIZES = (256, 384, 512)
NOISES = (0.005, 0.02, 0.05)


def picture(name) -> np.ndarray:
    import skimage.color
    import skimage.data

    im = getattr(skimage.data, name)()
    if im.ndim == 3:
        im = skimage.color.rgb2gray(im[..., :3])
    im = im.astype(np.float64)
    return (im - im.min()) / (im.max() - im.min())


def params(i, quick=False, noises=NOISES) -> dict:
    rng = np.random.default_rng(5300 + i)
    kind = KINDS[i % len(KINDS)]
    p = {
        "i": i,
        "picture": PICTURES[(i // len(KINDS)) % len(PICTURES)],
        "kind": kind,
        "size": 256 if quick else int(rng.choice(SIZES)),
        "noise": float(rng.choice(noises)),
        "shift": [0.0, 0.0],
        "turn_deg": 0.0,
        "scale": 1.0,
        "gain": 1.0,
    }
    if kind in ("shift", "mixed"):
        p["shift"] = [float(rng.uniform(0.5, 6) * rng.choice([-1, 1])) for _ in range(2)]
    if kind in ("turn", "mixed"):
        p["turn_deg"] = float(rng.uniform(1, 3) * rng.choice([-1, 1]))
    if kind in ("scale", "mixed"):
        p["scale"] = float(1 + rng.uniform(0.01, 0.02) * rng.choice([-1, 1]))
    if kind == "mixed":
        p["gain"] = float(rng.uniform(0.9, 1.1))
    return p


def make_pair(p):
    """``(fixed, moving, truth)``: float32 images and the (2, n, n) pull field, pixels, (row, col)."""
    import cv2
    from scipy import ndimage

    n = p["size"]
    src = picture(p["picture"])
    need = n + 40  # the frame, and a margin the motion reaches into (at most ~12 px at 512)
    k = max(1.0, need / min(src.shape))
    if k > 1:
        src = cv2.resize(
            src, (int(np.ceil(src.shape[1] * k)), int(np.ceil(src.shape[0] * k))), interpolation=cv2.INTER_CUBIC
        )
    r0, c0 = (src.shape[0] - n) // 2, (src.shape[1] - n) // 2
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    ctr = (n - 1) / 2
    a = np.deg2rad(p["turn_deg"])
    s = p["scale"]
    y, x = yy - ctr, xx - ctr
    ty = s * (np.cos(a) * y - np.sin(a) * x) + ctr + p["shift"][0]
    tx = s * (np.sin(a) * y + np.cos(a) * x) + ctr + p["shift"][1]
    truth = np.stack([ty - yy, tx - xx]).astype(np.float32)
    moving = src[r0 : r0 + n, c0 : c0 + n]
    fixed = ndimage.map_coordinates(src, [ty + r0, tx + c0], order=3, mode="reflect")
    rng = np.random.default_rng(10_000 + p["i"])
    fixed = p["gain"] * fixed + p["noise"] * rng.standard_normal((n, n))
    moving = moving + p["noise"] * rng.standard_normal((n, n))
    return fixed.astype(np.float32), moving.astype(np.float32), truth


def score(d, truth):
    """``(epe, identity)``: median ``|d - truth|`` and ``|truth|`` over the central 80 %."""
    n = truth.shape[1]
    c = slice(n // 10, n - n // 10)
    epe = np.hypot(*(d - truth)[:, c, c])
    return float(np.median(epe)), float(np.median(np.hypot(*truth[:, c, c])))


def main(argv=None) -> int:
    from radiokit.register import register

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", default="default,fast")
    ap.add_argument("--pairs", type=int, default=72)
    ap.add_argument("--quick", action="store_true", help="256 px frames only")
    ap.add_argument("--noises", default=",".join(map(str, NOISES)), help="the noise levels drawn from (0-1 range)")
    ap.add_argument("--jsonl", help="also write one JSON line per result")
    args = ap.parse_args(argv)
    presets = args.presets.split(",")
    rows = []
    out = open(args.jsonl, "w") if args.jsonl else None
    for i in range(args.pairs):
        p = params(i, args.quick, [float(x) for x in args.noises.split(",")])
        fixed, moving, truth = make_pair(p)
        for preset in presets:
            t = time.perf_counter()
            try:
                reg = register(fixed, moving, preset=preset)
            except ValueError as exc:
                print(f"{i:3d} {preset:8s} {p['picture']:22s} refused: {exc}")
                continue
            sec = time.perf_counter() - t
            epe, ident = score(reg.displacement, truth)
            bad = epe > max(1.0, 0.5 * ident)
            row = {**p, "preset": preset, "epe": epe, "identity": ident, "bad": bad, "ok": reg.quality.ok}
            row.update(reason=reg.quality.reason, seconds=sec)
            rows.append(row)
            if out:
                out.write(json.dumps(row) + "\n")
                out.flush()
            print(
                f"{i:3d} {preset:8s} {p['picture']:22s} {p['kind']:6s} {p['size']:4d} noise {p['noise']:.3f} "
                f"EPE {epe:6.3f} id {ident:6.3f} {'BAD ' if bad else 'good'} ok={reg.quality.ok!s:5s} {sec:5.1f}s "
                f"{reg.quality.reason[:70]}",
                flush=True,
            )
    if out:
        out.close()
    print()
    print(f"{'preset':8s} {'bad, flagged':>13s} {'bad, trusted':>13s} {'good, trusted':>14s} {'good, flagged':>14s}")
    for preset in presets:
        n = {(bad, ok): 0 for bad in (True, False) for ok in (True, False)}
        for x in rows:
            if x["preset"] == preset:
                n[x["bad"], x["ok"]] += 1
        print(f"{preset:8s} {n[True, False]:13d} {n[True, True]:13d} {n[False, True]:14d} {n[False, False]:14d}")
    trusted = [x for x in rows if x["bad"] and x["ok"]]
    if trusted:
        print("\ntrusted failures (ok True, bad):")
        for x in trusted:
            print(
                f"  {x['i']:3d} {x['preset']:8s} {x['picture']} {x['kind']} {x['size']} noise {x['noise']} "
                f"shift {np.round(x['shift'], 2).tolist()} turn {x['turn_deg']:.2f} scale {x['scale']:.4f}: "
                f"EPE {x['epe']:.2f} (identity {x['identity']:.2f})"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
