"""Where does the confidence map say "observed", and what is the error there? (issue 11)

Run::

    python benchmarks/bench_register_observed.py [--size 560] [--seeds 2] [--preset auto]

The library's map (``radiokit.register._confidence``) bounds a window's *translation*: the
Fisher information of a shift ``t`` in a Gaussian window of the lattice spacing, an offset
eliminated. A B-spline field is free to vary across such a window, though, and a tangential
shift of a smooth curved edge moves it exactly like a small rotation of the field there does:
with the field's local gradient ``A`` free, ``d(x) = t + A (x - x0)``, the edge pins only its
normal component. This script computes both bounds, the translation one (the library's,
reproduced) and the one with ``A`` eliminated as a nuisance (the Schur complement of the 7 x 7
information of ``t``, ``A`` and the offset), and scores rc on the family's test seeds where each
calls the motion observed: the median end-point error there, split into the component along the
fixed image's gradient (normal) and across it (tangential).

The moments of ``A``'s regressors, ``sum w(u) g_i g_j u^p v^q``, are separable filters of the
products ``g_i g_j`` with a Gaussian times ``u^p`` (``p + q <= 2``), so the 7 x 7 information of
every window costs 25 filterings. (``benchmarks/README.md``, "What the map calls observed".)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from regdata import TEST_SEEDS, Case, family_pair

from radiokit.register import _confidence as C

_FLOOR = {}  # (spacing, highpass, affine) -> the 99th percentile of the statistic on unit white noise


def _kernel(s, p):
    """A normalised Gaussian of sigma ``s`` times ``u^p`` (u from the window's centre), cut where
    the library's map window is (``_confidence.WINDOW_REACH`` sigmas)."""
    g = C._window_kernel(s)
    u = np.arange(len(g), dtype=np.float64) - len(g) // 2
    return g / g.sum() * u**p


def _moment(a, s, py, px):
    """``sum_u w(u) u_row^py u_col^px a(x0 + u)`` at every ``x0`` (OpenCV's filters correlate, so
    the kernel is not flipped). In float64: eliminating the gradient leaves of a gently curved
    edge's tangential information only its second-order part, which float32 sums lose."""
    return cv2.sepFilter2D(
        np.asarray(a, np.float64), cv2.CV_64F, _kernel(s, px), _kernel(s, py), borderType=cv2.BORDER_REFLECT
    )


def window_lmin(f, spacing, highpass, sig2, affine=True):
    """The smaller eigenvalue of the information of a window's shift per unit window weight, the
    offset (and with ``affine`` the field's local gradient) eliminated; the gradients as the
    library takes them (``f`` high-passed at ``highpass x spacing``, smoothed by 1 px) and the
    noise's own share of ``g_i^2`` removed. ``affine=False`` is ``_confidence._lmin``."""
    hp = f - C._gauss(f, highpass * spacing)
    g = [c.astype(np.float64) for c in np.gradient(C._gauss(hp, 1.0))]
    bias = C._deriv_noise_var(1.0) * sig2
    s2 = float(spacing) ** 2
    # regressors: (gradient component, monomial powers (row, col)); -1 = the offset's constant 1
    regs = [(0, (0, 0)), (1, (0, 0))]
    if affine:
        regs += [(0, (1, 0)), (0, (0, 1)), (1, (1, 0)), (1, (0, 1))]
    regs.append((-1, (0, 0)))
    cache = {}

    def moment(i, j, py, px):
        key = (min(i, j), max(i, j), py, px)
        if key not in cache:
            a = np.ones_like(f) if i < 0 and j < 0 else g[max(i, j)] if min(i, j) < 0 else g[i] * g[j]
            m = _moment(a, spacing, py, px)
            if i == j >= 0:  # noise's share of g_i^2 times the window's moment of the monomial
                m = m - bias * {(0, 0): 1.0, (2, 0): s2, (0, 2): s2}.get((py, px), 0.0)
            cache[key] = m
        return cache[key]

    n = len(regs)
    info = np.empty(f.shape + (n, n), np.float64)
    for a, (i, (py, px)) in enumerate(regs):
        for b in range(a, n):
            j, (qy, qx) = regs[b]
            info[..., a, b] = info[..., b, a] = moment(i, j, py + qy, px + qx)
    tt, tn, nn = info[..., :2, :2], info[..., :2, 2:], info[..., 2:, 2:]
    nn = nn + 1e-9 * np.eye(n - 2) * (np.trace(nn, axis1=-2, axis2=-1)[..., None, None] + 1e-30)
    schur = tt - tn @ np.linalg.solve(nn, np.swapaxes(tn, -1, -2))
    jyy, jxx, jxy = schur[..., 0, 0], schur[..., 1, 1], schur[..., 0, 1]
    tr, det = jxx + jyy, jxx * jyy - jxy * jxy
    return np.maximum(0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0)), 0).astype(np.float32)


def _noise_floor(spacing, highpass, affine):
    """What unit white noise shows as information 99 % of the time (as ``_confidence._noise_lmin``)."""
    key = (float(spacing), float(highpass), affine)
    if key not in _FLOOR:
        n = int(max(256, 16 * spacing))
        z = np.random.default_rng(0).standard_normal((n, n)).astype(np.float32)
        lm = window_lmin(z, spacing, highpass, np.ones_like(z), affine)
        m = int(3 * spacing)
        _FLOOR[key] = float(np.percentile(lm[m:-m, m:-m], 99))
    return _FLOOR[key]


def window_bound(fixed, spacing=24.0, highpass=0.25, affine=True, bound_scale=1.0):
    """The window's Cramer-Rao bound (px) as ``_confidence.observability`` computes it, with the
    field's local gradient a nuisance when ``affine``."""
    f = np.asarray(fixed, np.float32)
    sig2 = C.noise_map(f, spacing) ** 2
    floor2 = C.model_floor(f) ** 2
    lm = np.maximum(window_lmin(f, spacing, highpass, sig2, affine) - _noise_floor(spacing, highpass, affine) * sig2, 0)
    info = C._window_area(spacing) * lm / (2 * (sig2 + floor2))
    return (bound_scale / np.sqrt(np.maximum(info, 1e-12))).astype(np.float32)


def _full_res_bound(f, affine):
    """The bound on the pair binned as ``register()`` assesses it, in full-resolution px, upsampled."""
    from radiokit.register import _WINDOW, _assess_binning, _bin

    k = _assess_binning(f.size)
    b = window_bound(_bin(f, k), _WINDOW, affine=affine, bound_scale=k)
    return cv2.resize(b, (f.shape[1], f.shape[0]), interpolation=cv2.INTER_LINEAR)


def error_components(fixed, error):
    """``(EPE, normal, tangential)`` per pixel: the error's length and its components along and
    across the fixed image's gradient (after a 2 px blur)."""
    gy, gx = np.gradient(C._gauss(fixed, 2.0))
    gn = np.hypot(gy, gx) + 1e-20
    return np.hypot(*error), np.abs(error[0] * gy + error[1] * gx) / gn, np.abs(error[1] * gy - error[0] * gx) / gn


def cases(size, n_seeds):
    """Texture from none to ten times the noise (random motion, correlation 1/10), the textureless
    body under three correlation lengths, and the physical motion with and without texture."""
    out = []
    for s in TEST_SEEDS[:n_seeds]:
        out += [Case(size=size, texture=0.0, corr=c, seed=s) for c in (1 / 4, 1 / 10, 1 / 20)]
        out += [Case(size=size, texture=0.01 * t, corr=0.1, seed=s) for t in (0.3, 1.0, 3.0, 10.0)]
        out += [Case(size=size, texture=t, motion="physical", corr=0.0, seed=s) for t in (0.0, 0.01)]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=560)
    ap.add_argument("--seeds", type=int, default=2, help="test seeds per case")
    ap.add_argument("--preset", default="auto")
    args = ap.parse_args(argv)
    from radiokit.register import register

    print(
        "| case | body EPE | map: observed, EPE (normal / tangential) | affine: observed, EPE (normal / tangential) | ok |"
    )
    print("|---|---|---|---|---|")
    for case in cases(args.size, args.seeds):
        fixed, moving, truth, mask = family_pair(case)
        t = time.perf_counter()
        reg = register(fixed, moving, "rc", preset=args.preset)
        seconds = time.perf_counter() - t
        parts = error_components(fixed, reg.displacement - truth)
        cells = []
        for obs in ((reg.confidence >= 0.5) & mask, (_full_res_bound(fixed, True) <= C.OBSERVED_PX) & mask):
            e, n, tg = (float(np.median(p[obs])) if obs.any() else float("nan") for p in parts)
            cells.append(f"{100 * obs.sum() / mask.sum():.0f} %, {e:.2f} ({n:.2f} / {tg:.2f})")
        body = float(np.median(parts[0][mask]))
        print(
            f"| {case.label()} | {body:.2f} | {cells[0]} | {cells[1]} | {reg.quality.ok} ({seconds:.0f} s) |",
            flush=True,
        )


if __name__ == "__main__":
    main()
