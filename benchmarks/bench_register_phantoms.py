"""Can ``quality.ok`` and the ROI verdict be trusted on phantom-like pairs nothing was chosen on?

Run (from the repository root; one process, 300 registrations, about 15 min on a shared 2-core
machine; each field is cached in ``OUT/fields``, so a rerun continues where it stopped and
assesses the cached fields again with the present flag; ``--fresh`` registers again)::

    python benchmarks/bench_register_phantoms.py [--out out/phantoms] [--cases 60] [--split all|train|test] [--presets auto,default,fast,weak,silent]
    python benchmarks/bench_register_phantoms.py --out out/phantoms --split test --table   # the tables again

``--split train`` is the first half of the seeds (6000-6029 of 60 cases), ``test`` the second
(6030-6059): a flag rule changed on these pairs (session 20) was chosen on ``train`` only.
``auto`` is composed from the cached ``default`` run with ``auto``'s ``extend``, ``weak`` and
``silent`` by ``register_auto``'s own rule (``_auto.choose``, ``returned``), as
``bench_register_flag.py`` does.

An **independent** generator: it uses nothing of ``benchmarks/regdata.py``,
``bench_register_heldout.py`` or ``sim/`` (only ``radiokit.register`` and
``radiokit.pipeline.rois_verdict`` are imported, to be tested). Each pair is drawn from its own
seed (6000-; apart from regdata's 0-99 and 1000-1099 and the held-out 5000-5099):

- **projections, exact**: the line integral (``mu x chord``) through a gel body that is an
  ellipsoid, a cylinder lying across the frame (side view) or a box with rounded corners (a slab
  seen through its face), peak 0.3-1.0 (nearly transparent), its centre placed so that it is
  partly cut by the frame's edge in a third of the pairs; 1-3 denser inclusions: an ellipsoid
  (ellipse), a rounded square (a prism along the beam, ``|u|^p + |v|^p <= 1``, p = 4), a soft-edged
  one (a 3-D Gaussian, whose projection is a 2-D Gaussian), one touching another in some pairs;
- **texture** inside the body: a sum of 40 random cosines (wavelengths 5-60 px), scaled by the
  body's chord, its standard deviation 0, 0.3, 1, 3 or 10 x the noise at the body's centre;
- **scene**: in some pairs two compression plates' shadows (bands of line integral 1.5 at the
  top and bottom, moving with the scene) and a collimator border (line integral 4, static, which
  the motion does not move);
- **motion** (a pulling field ``d``: ``moving(x + d(x)) = fixed(x)`` away from static
  structure): uniform compression (rows 0.5-4 %) with lateral expansion (half of it), the same
  with a lag around a stiff inclusion (the inclusion moves with its centre), random smooth
  fields (white noise, Gaussian-filtered, correlation length 1/4-1/20 of the frame, peak 0.5-4 %
  of it), pure shifts (0.7-40 px) and rotations (1-8 degrees about an off-centre point);
  the moving image is rendered exactly at ``psi(y)``, the inverse of ``x -> x + d(x)`` (fixed-point
  iteration), and scaled by a thinning of the compressed body;
- **noise and gain**: Poisson counts (``I0`` 3e3-3e4 open-beam counts), a flat-field
  gain change up to +-20 % in the moving image (uniform, or a ramp: +-20 % along its axis,
  up to 28 % in a corner), line integrals ``-ln(I / I0)``.

Scored against the truth: median end-point error over the body (the fixed frame's body, inside
the collimator). Failed: median EPE > max(1 px, half the identity's); good: <= 0.5 px. The ROI
check: an inclusion ROI (a square inside the largest inclusion) and a background ROI (the same
size, in the body away from the inclusions), ``roi_observed`` of the confidence map and
``rois_verdict``, against the truth's median EPE in each ROI (over 1 px: wrong there).
Sizes 256-448 px. Tables and findings: benchmarks/README.md, "Phantom-like pairs from an
independent generator (session 19)" and "The flag between sharp edges (session 20)".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

SEED0 = 6000
PRESETS = ("auto", "default", "fast", "weak", "silent")
TEXTURES = (0.0, 0.3, 1.0, 3.0, 10.0)
MOTIONS = ("compress", "lag", "random", "random", "shift", "rotate")
MAX_STRAIN = 0.3  # the random fields' largest displacement gradient


# -- the analytic scene ------------------------------------------------------------------------


def _chord_ellipsoid(y, x, cy, cx, ay, ax, depth, angle=0.0):
    """Chord (px) through an ellipsoid of in-plane semi-axes ``ay``, ``ax`` (rotated by ``angle``)
    and semi-depth ``depth`` along the beam: ``2 depth sqrt(1 - q)``, ``q`` the in-plane quadric."""
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * (y - cy) + s * (x - cx), -s * (y - cy) + c * (x - cx)
    q = (u / ay) ** 2 + (v / ax) ** 2
    return 2 * depth * np.sqrt(np.clip(1 - q, 0, None))


def _chord_cylinder(y, x, cy, cx, radius, half_len, angle=0.0):
    """A cylinder lying in the image plane (axis at ``angle``), seen from the side: chord
    ``2 sqrt(R^2 - u^2)`` across the axis, cut flat at ``+-half_len`` along it."""
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * (y - cy) + s * (x - cx), -s * (y - cy) + c * (x - cx)
    return 2 * np.sqrt(np.clip(radius**2 - u**2, 0, None)) * (np.abs(v) <= half_len)


def _chord_prism(y, x, cy, cx, ay, ax, depth, p=4.0, angle=0.0):
    """A prism along the beam with a rounded-square (superellipse ``|u|^p + |v|^p <= 1``) section:
    the chord is ``depth`` inside the footprint (a box with rounded corners seen through its face)."""
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * (y - cy) + s * (x - cx), -s * (y - cy) + c * (x - cx)
    return depth * ((np.abs(u / ay) ** p + np.abs(v / ax) ** p) <= 1)


def _gauss_blob(y, x, cy, cx, sy, sx):
    """The line integral of a 3-D Gaussian density (unit peak chord-equivalent): a 2-D Gaussian."""
    return np.exp(-0.5 * (((y - cy) / sy) ** 2 + ((x - cx) / sx) ** 2))


def _draw_scene(rng, n):
    """A random scene description (plain floats and lists: it goes into the cache as JSON)."""
    cut = rng.random() < 0.35
    kind = str(rng.choice(["ellipsoid", "cylinder", "slab"]))
    half = n * rng.uniform(0.3, 0.42)
    cy, cx = n / 2 + rng.uniform(-0.05, 0.05) * n, n / 2 + rng.uniform(-0.05, 0.05) * n
    if cut:  # pushed past an edge
        side = rng.integers(4)
        off = half * rng.uniform(0.35, 0.6)
        cy, cx = cy + off * (side == 0) - off * (side == 1), cx + off * (side == 2) - off * (side == 3)
    body = dict(
        kind=kind,
        cy=cy,
        cx=cx,
        ay=half * rng.uniform(0.7, 1.0),
        ax=half * rng.uniform(0.8, 1.15),
        angle=float(rng.uniform(-0.3, 0.3)),
        peak=float(rng.uniform(0.3, 1.0)),
    )
    incs, k = [], int(rng.integers(1, 4))
    touching = k > 1 and rng.random() < 0.5
    for i in range(k):
        shape = str(rng.choice(["ellipse", "rounded", "soft"]))
        r = n * rng.uniform(0.035, 0.09)
        if touching and i == 1:  # beside the first one, rims in contact
            a = rng.uniform(0, 2 * np.pi)
            iy, ix = incs[0]["cy"] + (incs[0]["r"] + r) * np.sin(a), incs[0]["cx"] + (incs[0]["r"] + r) * np.cos(a)
        else:
            ang, rad = rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.5)
            iy, ix = body["cy"] + rad * body["ay"] * np.sin(ang), body["cx"] + rad * body["ax"] * np.cos(ang)
        incs.append(
            dict(
                shape=shape,
                cy=float(iy),
                cx=float(ix),
                r=float(r),
                aspect=float(rng.uniform(0.7, 1.3)),
                contrast=float(rng.uniform(0.04, 0.3)),
                angle=float(rng.uniform(0, np.pi)),
            )
        )
    return dict(
        body=body,
        inclusions=incs,
        cut=bool(cut),
        plates=bool(rng.random() < 0.4),
        collimator=bool(rng.random() < 0.35),
        n=n,
    )


def _body_chord(scene, y, x):
    """The body's chord, normalised to a peak of 1."""
    b = scene["body"]
    if b["kind"] == "ellipsoid":
        return _chord_ellipsoid(y, x, b["cy"], b["cx"], b["ay"], b["ax"], 0.5, b["angle"])
    if b["kind"] == "cylinder":
        return _chord_cylinder(y, x, b["cy"], b["cx"], b["ay"], 1.3 * b["ax"], b["angle"]) / (2 * b["ay"])
    return _chord_prism(y, x, b["cy"], b["cx"], b["ay"], b["ax"], 1.0, 6.0, b["angle"])


def _texture_field(scene, rng_seed, y, x):
    """Unit-variance texture: 40 random cosines, wavelengths 5-60 px (evaluated anywhere)."""
    rng = np.random.default_rng(rng_seed)
    t = np.zeros_like(y)
    for _ in range(40):
        lam, th, ph = rng.uniform(5, 60), rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        t += np.cos(2 * np.pi * (np.cos(th) * y + np.sin(th) * x) / lam + ph)
    return t / np.sqrt(20.0)


def _project(scene, y, x, tex_sd, tex_seed):
    """The line integral of the moving scene (everything but the static collimator) at ``y, x``."""
    chord = _body_chord(scene, y, x)
    p = scene["body"]["peak"] * chord
    for inc in scene["inclusions"]:
        ay, ax = inc["r"] * inc["aspect"], inc["r"] / inc["aspect"]
        if inc["shape"] == "ellipse":
            c = _chord_ellipsoid(y, x, inc["cy"], inc["cx"], ay, ax, 1.0, inc["angle"])
            c = c / 2.0
        elif inc["shape"] == "rounded":
            c = _chord_prism(y, x, inc["cy"], inc["cx"], ay, ax, 1.0, 4.0, inc["angle"])
        else:
            c = _gauss_blob(y, x, inc["cy"], inc["cx"], 0.6 * ay, 0.6 * ax)
        p = p + inc["contrast"] * c * (chord > 0)
    if tex_sd > 0:
        p = p + tex_sd * chord * _texture_field(scene, tex_seed, y, x)
    if scene["plates"]:  # plates touching the body's top and bottom, seen edge-on
        b = scene["body"]
        top, bot = b["cy"] - b["ay"], b["cy"] + b["ay"]
        p = p + 1.5 * ((y < top) & (y > top - 0.06 * scene["n"])) + 1.5 * ((y > bot) & (y < bot + 0.06 * scene["n"]))
    return p


def _collimator(scene):
    """Static collimator mask (True: open beam), or None."""
    n = scene["n"]
    if not scene["collimator"]:
        return None
    m = int(0.05 * n)
    open_ = np.zeros((n, n), bool)
    open_[m : n - m // 2, m // 2 : n - m] = True
    return open_


# -- the motion --------------------------------------------------------------------------------


def _draw_motion(rng, scene, kind):
    """A motion description; ``_field`` evaluates it anywhere."""
    n, b = scene["n"], scene["body"]
    if kind in ("compress", "lag"):
        eps = float(rng.uniform(0.005, 0.04))
        return dict(
            kind=kind,
            eps=eps,
            cy=b["cy"] - b["ay"] * rng.uniform(0.8, 1.0),
            cx=b["cx"],
            nu=0.5,
            stiff=int(np.argmax([i["r"] for i in scene["inclusions"]])),
        )
    if kind == "random":
        corr = float(n / rng.choice([4, 6, 10, 14, 20]))
        return dict(kind=kind, corr=corr, amp=float(n * rng.uniform(0.005, 0.04)), seed=int(rng.integers(1 << 30)))
    if kind == "shift":
        mag = float(rng.choice([0.7, 2.5, 8.0, 20.0, 40.0]))
        a = rng.uniform(0, 2 * np.pi)
        return dict(kind=kind, dy=float(mag * np.sin(a)), dx=float(mag * np.cos(a)))
    deg = float(rng.choice([1.0, 3.0, 8.0]) * rng.choice([-1, 1]))
    return dict(kind="rotate", deg=deg, cy=float(n * rng.uniform(0.3, 0.7)), cx=float(n * rng.uniform(0.3, 0.7)))


def _random_grid(motion, n):
    """The random smooth field on the frame padded by a quarter (so psi may leave the frame)."""
    pad = n // 4
    rng = np.random.default_rng(motion["seed"])
    g = np.stack(
        [
            ndimage.gaussian_filter(rng.standard_normal((n + 2 * pad,) * 2), motion["corr"] / 2, mode="wrap")
            for _ in range(2)
        ]
    )
    g *= motion["amp"] / np.abs(np.hypot(*g[:, pad:-pad, pad:-pad])).max()
    # a compressed body does not fold: the field's gradient is capped at MAX_STRAIN (the amplitude
    # lowered; ``motion["amp"]`` is updated to what was used)
    strain = max(np.abs(np.gradient(c, axis=a)).max() for c in g for a in (0, 1))
    if strain > MAX_STRAIN:
        g *= MAX_STRAIN / strain
        motion["amp"] *= MAX_STRAIN / strain
    return g, pad


def _field(motion, scene, y, x, grid=None):
    """The pulling field ``d(x)`` (2, ...) at ``y, x`` (px)."""
    k = motion["kind"]
    if k in ("compress", "lag"):
        e, nu = motion["eps"], motion["nu"]
        dy, dx = -e * (y - motion["cy"]), nu * e * (x - motion["cx"])
        if k == "lag":  # the stiff inclusion moves with its centre; the lag fades over 1.5 radii beyond it
            inc = scene["inclusions"][motion["stiff"]]
            w = np.exp(-0.5 * np.hypot(y - inc["cy"], x - inc["cx"]) ** 2 / (1.5 * inc["r"]) ** 2)
            dy = dy - 0.8 * w * (-e * (y - inc["cy"]))
            dx = dx - 0.8 * w * (nu * e * (x - inc["cx"]))
        return np.stack([dy, dx])
    if k == "random":
        g, pad = grid
        return np.stack([ndimage.map_coordinates(c, [y + pad, x + pad], order=3, mode="nearest") for c in g])
    if k == "shift":
        return np.stack([np.full_like(y, motion["dy"]), np.full_like(x, motion["dx"])])
    a = np.deg2rad(motion["deg"])
    ry, rx = y - motion["cy"], x - motion["cx"]
    return np.stack([np.cos(a) * ry - np.sin(a) * rx - ry, np.sin(a) * ry + np.cos(a) * rx - rx])


def _inverse(motion, scene, y, x, grid):
    """``psi(y)``: the point ``x`` with ``x + d(x) = y`` (fixed-point iteration; residual checked)."""
    py, px = y.copy(), x.copy()
    for _ in range(60):
        d = _field(motion, scene, py, px, grid)
        ny, nx = y - d[0], x - d[1]
        step = max(np.abs(ny - py).max(), np.abs(nx - px).max())
        py, px = ny, nx
        if step < 1e-5:
            break
    d = _field(motion, scene, py, px, grid)
    err = np.hypot(py + d[0] - y, px + d[1] - x).max()
    assert err < 1e-3, f"inverse map did not converge ({err:.2g} px)"
    return py, px


# -- a pair ------------------------------------------------------------------------------------


def make_pair(seed):
    """``(fixed, moving, truth, body, info)`` for one seed; ``info`` records every parameter."""
    rng = np.random.default_rng(seed)
    n = int(rng.choice([256, 320, 384, 448]))
    scene = _draw_scene(rng, n)
    tex_ratio = float(TEXTURES[seed % len(TEXTURES)])
    motion = _draw_motion(rng, scene, MOTIONS[(seed // len(TEXTURES)) % len(MOTIONS)])
    i0 = float(10 ** rng.uniform(np.log10(3e3), np.log10(3e4)))
    noise_centre = float(np.sqrt(np.exp(scene["body"]["peak"]) / i0))  # sd of -ln(I/I0) at the body's peak
    tex_sd, tex_seed = tex_ratio * noise_centre, int(rng.integers(1 << 30))
    gain = dict(
        kind=str(rng.choice(["none", "uniform", "ramp"])),
        g=float(rng.uniform(-0.2, 0.2)),
        a=float(rng.uniform(0, np.pi)),
    )
    thin = float(rng.uniform(0.0, 0.03)) if motion["kind"] in ("compress", "lag", "random") else 0.0
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    grid = _random_grid(motion, n) if motion["kind"] == "random" else None
    truth = _field(motion, scene, y, x, grid)
    fixed_l = _project(scene, y, x, tex_sd, tex_seed)
    py, px = _inverse(motion, scene, y, x, grid)
    moving_l = (1 + thin) * _project(scene, py, px, tex_sd, tex_seed)
    coll = _collimator(scene)
    if coll is not None:  # static: the same in both images
        fixed_l, moving_l = np.where(coll, fixed_l, 4.0), np.where(coll, moving_l, 4.0)
    g = 1.0
    if gain["kind"] == "uniform":
        g = 1 + gain["g"]
    elif gain["kind"] == "ramp":
        g = 1 + gain["g"] * (np.cos(gain["a"]) * (y / n - 0.5) + np.sin(gain["a"]) * (x / n - 0.5)) * 2
    fixed = -np.log(np.maximum(rng.poisson(i0 * np.exp(-fixed_l)), 0.5) / i0)
    moving = -np.log(np.maximum(rng.poisson(i0 * g * np.exp(-moving_l)), 0.5) / i0)
    body = _body_chord(scene, y, x) > 0
    if coll is not None:
        body &= coll
    info = dict(
        seed=seed,
        n=n,
        scene=scene,
        motion=motion,
        texture_to_noise=tex_ratio,
        i0=i0,
        noise_centre=noise_centre,
        gain=gain,
        thinning=thin,
    )
    return fixed.astype(np.float32), moving.astype(np.float32), truth.astype(np.float32), body, info


def _rois(info, body):
    """(inclusion ROI, background ROI) as (r0, r1, c0, c1), inside the frame, or None."""
    n = info["n"]
    big = max(info["scene"]["inclusions"], key=lambda i: i["r"])
    h = max(4, int(0.5 * big["r"]))
    cy, cx = int(round(big["cy"])), int(round(big["cx"]))
    inc = (cy - h, cy + h, cx - h, cx + h)
    if min(inc) < 0 or max(inc) > n or not body[cy, cx]:
        return None
    # background: a same-size square inside the body, at least 3 radii from every inclusion
    far = body.copy()
    yy, xx = np.mgrid[0:n, 0:n]
    for i in info["scene"]["inclusions"]:
        far &= np.hypot(yy - i["cy"], xx - i["cx"]) > 3 * i["r"] + h
    far = ndimage.binary_erosion(far, np.ones((2 * h + 1, 2 * h + 1)))
    if not far.any():
        return None
    ys, xs = np.nonzero(far)
    j = np.argmin(np.hypot(ys - cy, xs - cx))
    return inc, (ys[j] - h, ys[j] + h, xs[j] - h, xs[j] + h)


def _epe(d, truth, where):
    e = np.hypot(*(np.asarray(d, np.float64) - truth))[where]
    return float(np.median(e)), float(np.percentile(e, 95))


def fixed_stats(fixed):
    """No-truth numbers of the fixed image alone, to ask which would have told the trusted
    failures apart: ``auto``'s interior texture-to-noise ratio, and the share of the interior
    (the flag's) the confidence map calls observed with the flag's 24 px window and with half
    of it (a reach of one lattice spacing instead of two)."""
    from radiokit.register import _confidence as C
    from radiokit.register import _interior
    from radiokit.register._auto import interior_texture_to_noise

    out = {"texture_ratio": interior_texture_to_noise(fixed)[0]}
    for window in (24.0, 12.0):
        ob = C.observability(fixed, window)
        inner = _interior(ob.object)
        obs = (ob.confidence >= 0.5) & ob.object
        out[f"interior_observed_{int(window)}"] = float(obs[inner].mean() if inner.any() else obs[ob.object].mean())
    return out


# the configurations registered per pair (cached fields); ``auto`` is composed from "auto-plain"
# (``default`` with ``auto``'s ``extend``), ``weak`` and ``silent`` by ``register_auto``'s own rule
# (faithful below the checks' ~0.4 Mpx, where the plain run is never abandoned: every pair here)
CONFIGS = ("auto-plain", "default", "fast", "weak", "silent")


def _options(name):
    from radiokit.register._auto import EXTEND

    return {"preset": "default", "extend": EXTEND} if name == "auto-plain" else {"preset": name}


def _cached_field(out, seed, name, fixed, moving, fresh=False):
    """``(displacement, info, seconds)`` of one configuration: from ``out/fields`` or registered now."""
    from radiokit.register import METHODS, _check, load_methods

    path = out / "fields" / f"{seed}-{name}.npz"
    if path.exists() and not fresh:
        z = np.load(path, allow_pickle=False)
        return z["d"].astype(np.float32), json.loads(str(z["info"])), float(z["seconds"])
    load_methods()
    f, m, _ = _check(fixed, moving, None)
    t = time.perf_counter()
    d, info = METHODS["rc"](f, m, None, **_options(name))
    sec = time.perf_counter() - t
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool))}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, d=np.asarray(d, np.float32), info=json.dumps(info), seconds=sec)
    tmp.replace(path)
    return np.asarray(d, np.float32), info, sec


def _assessed(name, fixed, moving, d, info, sec):
    """``register()``'s assessment of a cached field (its quality and confidence map)."""
    from radiokit.register import Quality, Registration, _assess, _check

    f, m, _ = _check(fixed, moving, None)
    reg = Registration(np.ascontiguousarray(d, np.float32), "rc", Quality(), _options(name))
    _assess(reg, f, m, None, info, sec)
    return reg


def run_seed(seed, presets, out, fresh=False):
    """Every preset of ``presets`` on one pair: JSON-able rows, the fields from the cache (the
    flag assessed again by the present code) or registered now."""
    from radiokit.register._auto import checks_silent, choose, polishes, returned, settled

    fixed, moving, truth, body, info = make_pair(seed)
    need = set(presets) - {"auto"} | ({"auto-plain", "weak", "silent"} if "auto" in presets else set())
    regs, secs = {}, {}
    for name in CONFIGS:
        if name in need:
            d, i, secs[name] = _cached_field(out, seed, name, fixed, moving, fresh)
            regs[name] = _assessed(name, fixed, moving, d, i, secs[name])
    rows = []
    for preset in presets:
        use, sec = preset, secs.get(preset)
        if preset == "auto":
            plain = regs["auto-plain"]
            use, sec = "auto-plain", secs["auto-plain"]
            fb = choose(fixed, "auto").preset
            if not settled(plain.quality) or checks_silent("auto", plain.quality, fb):
                r = returned("auto", plain.quality, fb, regs[fb].quality if fb in regs else None)
                use = "auto-plain" if r == "default" else r
                retried = polishes("auto", plain.quality, fb) or checks_silent("auto", plain.quality, fb)
                if fb in regs and (not plain.quality.ok or retried):
                    sec += secs[fb]  # the retry ran, kept or not
        rows.append(_row(seed, preset, regs[use], sec, truth, body, info, fixed, use))
    return rows


def _row(seed, preset, reg, sec, truth, body, info, fixed, use):
    """One result as a JSON-able row (the truth's EPE, the quality, the ROI check)."""
    from radiokit.pipeline import rois_verdict
    from radiokit.register import roi_observed

    med, p95 = _epe(reg.displacement, truth, body)
    ident = float(np.median(np.hypot(*truth)[body]))
    q = {k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in vars(reg.quality).items()}
    row = dict(
        seed=seed,
        preset=preset,
        info=info,
        epe_median=med,
        epe_p95=p95,
        identity=ident,
        seconds=sec,
        quality=q,
        returned=("default" if use == "auto-plain" else use) if preset.startswith("auto") else None,
        fixed=fixed_stats(fixed),
    )
    rois = _rois(info, body)
    if rois is not None:
        observed = {
            "inclusion": roi_observed(reg.confidence, rois[0]),
            "background": roi_observed(reg.confidence, rois[1]),
        }
        ok, why = rois_verdict(observed)
        roi_epe = {}
        for name, (r0, r1, c0, c1) in zip(("inclusion", "background"), rois):
            m = np.zeros_like(body)
            m[r0:r1, c0:c1] = True
            roi_epe[name] = _epe(reg.displacement, truth, m)[0]
        row.update(rois=[list(map(int, r)) for r in rois], roi_observed=observed, rois_ok=ok, roi_epe=roi_epe)
    return row


# -- the tables --------------------------------------------------------------------------------


def status(row):
    """'failed', 'good' or 'between' by the truth."""
    if row["epe_median"] > max(1.0, 0.5 * row["identity"]):
        return "failed"
    return "good" if row["epe_median"] <= 0.5 else "between"


def describe(row):
    """One line: the pair's parameters."""
    i = row["info"]
    m = {
        k: (round(float(v), 3) if isinstance(v, float) else v)
        for k, v in i["motion"].items()
        if k not in ("seed", "stiff")
    }
    b = i["scene"]["body"]
    return (
        f"seed {row['seed']} {i['n']}px {b['kind']}{' cut' if i['scene']['cut'] else ''}"
        f"{' plates' if i['scene']['plates'] else ''}{' collimator' if i['scene']['collimator'] else ''}, "
        f"{len(i['scene']['inclusions'])} incl ({','.join(c['shape'] for c in i['scene']['inclusions'])}), "
        f"tex {i['texture_to_noise']}x noise {i['noise_centre']:.3f}, gain {i['gain']['kind']} {i['gain']['g']:+.2f}, motion {m}"
    )


def tables(rows):
    """Print the confusion table per preset, every trusted failure, and the ROI check."""
    print("| preset | results | failed flagged | good trusted | between (ok) | trusted failures |")
    print("|---|---|---|---|---|---|")
    for p in PRESETS + ("all",):
        rs = [r for r in rows if r["preset"] == p or p == "all"]
        if not rs:
            continue
        f = [r for r in rs if status(r) == "failed"]
        g = [r for r in rs if status(r) == "good"]
        bt = [r for r in rs if status(r) == "between"]
        tf = [r for r in f if r["quality"]["ok"]]
        print(
            f"| {p} | {len(rs)} | {len(f) - len(tf)}/{len(f)} | {sum(r['quality']['ok'] for r in g)}/{len(g)} "
            f"| {len(bt)} ({sum(r['quality']['ok'] for r in bt)}) | {len(tf)} |"
        )
    keys = (
        "interior_observed",
        "observed_fraction",
        "residual_motion",
        "misaligned_fraction",
        "excess_kept",
        "body_scale",
        "rc_before",
        "rc_after",
    )
    print("\nTrusted failures:")
    for r in rows:
        if status(r) == "failed" and r["quality"]["ok"]:
            q = r["quality"]
            print(
                f"- {r['preset']}{'->' + r['returned'] if r.get('returned') else ''}: EPE {r['epe_median']:.2f} "
                f"(identity {r['identity']:.2f}); {describe(r)}"
            )
            print("    " + ", ".join(f"{k} {q[k]:.3g}" if q[k] is not None else f"{k} nan" for k in keys))
    _roi_tables(rows)
    _separation(rows)


def _roi_tables(rows):
    """Each ROI's observed share against its truth EPE, and the pipeline's combined verdict (the
    flag and ``rois_verdict`` both ok) against the ROIs' errors."""
    rs = [r for r in rows if "rois" in r]
    print("\nROIs: the map's 'observed' (share >= 0.5) against the truth's median EPE in the ROI")
    print("| ROI | observed: EPE > 1 px | observed: <= 0.5 px | not observed: EPE > 1 px | not observed: <= 0.5 px |")
    print("|---|---|---|---|---|")
    for name in ("inclusion", "background"):
        o = np.array([r["roi_observed"][name] >= 0.5 for r in rs])
        e = np.array([r["roi_epe"][name] for r in rs])
        print(
            f"| {name} | {np.sum(o & (e > 1))}/{o.sum()} | {np.sum(o & (e <= 0.5))}/{o.sum()} "
            f"| {np.sum(~o & (e > 1))}/{(~o).sum()} | {np.sum(~o & (e <= 0.5))}/{(~o).sum()} |"
        )
    print(
        "\n| preset | results with ROIs | flag and ROIs ok | of those a ROI > 1 px off | ROI verdict False, both ROIs <= 0.5 px |"
    )
    print("|---|---|---|---|---|")
    for p in PRESETS:
        ps = [r for r in rs if r["preset"] == p]
        both = [r for r in ps if r["rois_ok"] and r["quality"]["ok"]]
        bad = [r for r in both if max(r["roi_epe"].values()) > 1.0]
        over = [r for r in ps if r["rois_ok"] is False and max(r["roi_epe"].values()) <= 0.5]
        print(
            f"| {p} | {len(ps)} | {len(both)} | {len(bad)} ({', '.join(str(r['seed']) for r in bad)}) | {len(over)} |"
        )


def _separation(rows):
    """Among the trusted results (ok True): each no-truth number's range over the trusted
    failures and the trusted good ones, and the probability that a failure reads higher (AUC)."""
    ok = [r for r in rows if r["quality"]["ok"] and "fixed" in r]
    fail = [r for r in ok if status(r) == "failed"]
    good = [r for r in ok if status(r) == "good"]
    if not fail or not good:
        return

    def value(r, k):
        v = r["fixed"].get(k, r["quality"].get(k))
        return np.nan if v is None else float(v)

    print(f"\nTrusted results: {len(fail)} failed, {len(good)} good. median [range]; AUC = P(failed > good)")
    print("| statistic | trusted failures | trusted good | AUC |")
    print("|---|---|---|---|")
    keys = (
        "residual_motion",
        "excess_kept",
        "misaligned_fraction",
        "interior_observed",
        "texture_ratio",
        "interior_observed_24",
        "interior_observed_12",
    )
    for k in keys:
        f = np.array([value(r, k) for r in fail])
        g = np.array([value(r, k) for r in good])
        f, g = f[np.isfinite(f)], g[np.isfinite(g)]
        auc = float(np.mean((f[:, None] > g[None, :]) + 0.5 * (f[:, None] == g[None, :])))
        print(
            f"| {k} | {np.median(f):.3g} [{f.min():.3g}, {f.max():.3g}] | {np.median(g):.3g} [{g.min():.3g}, {g.max():.3g}] | {auc:.2f} |"
        )


def seeds_of(split, cases):
    """The seeds of ``split``: "train" the first half of ``SEED0 .. SEED0 + cases``, "test" the
    rest, "all" both. Texture cycles every 5 seeds and the motion every 30, so with 60 cases
    each half (6000-6029, 6030-6059) holds every texture x motion once."""
    seeds = list(range(SEED0, SEED0 + cases))
    half = (cases + 1) // 2
    return {"all": seeds, "train": seeds[:half], "test": seeds[half:]}[split]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/phantoms")
    ap.add_argument("--cases", type=int, default=60)
    ap.add_argument(
        "--split", choices=("all", "train", "test"), default="all", help="train: the first half of the seeds"
    )
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--fresh", action="store_true", help="register again even when a field is cached")
    ap.add_argument("--table", action="store_true", help="only print the tables from OUT/rows-SPLIT.json")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / f"rows-{a.split}.json"
    if a.table:
        tables(json.loads(cache.read_text()))
        return 0
    rows = []
    for seed in seeds_of(a.split, a.cases):
        for row in run_seed(seed, a.presets.split(","), out, a.fresh):
            rows.append(row)
            print(
                f"{seed} {row['preset']:8s} {status(row):8s} ok={row['quality']['ok']!s:5s} EPE {row['epe_median']:.2f} "
                f"id {row['identity']:.2f} {row['seconds']:.1f}s",
                flush=True,
            )
    cache.write_text(json.dumps(rows))
    tables(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
