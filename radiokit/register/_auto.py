"""rc's preset chosen for the pair (``preset="auto"``, ``"auto-fast"``).

The ``weak`` presets (scale-invariant energy balance, free coarse levels) recover texture near
the noise level that ``default`` leaves, but lose on a silent (textureless) body, whose edges
carry thickness change the free coarse levels follow, and on rich texture (benchmarks/README.md,
issue 11; on natural images 3-6x: camera 1120 0.056 -> 0.35 px). So ``auto`` runs the plain
preset first and keeps it when it passes its own checks (``quality.ok``: rich texture, or
anything ``default`` registers well) and its residual is still (``residual_motion`` at most
``POLISH``); a result it flags, or one whose residual still moves, is tried again with
``weak``, only when the body's interior carries texture for ``weak`` to use, and the ``weak``
result is kept only when its residual moves less (``quality.residual_motion``, see
:func:`keeps_retry`, :func:`polishes`). A flagged result on a body whose
interior carries no texture is tried again with ``silent`` (``silent-fast``): the field starts
from the silhouettes' affine map and the lattices are stiff, the least-bent field the edges
allow, which is what a compressed phantom's silent slab does (the simulated pva-phantom side
view: 13.9 -> 0.28 px at 560); that retry is kept unless it leaves more misaligned. A plain run
that passed its checks on such a body is tried with ``silent`` too, and replaced when the silent
run passes its checks as well and leaves no more misaligned (:func:`checks_silent`: a free
lattice can fit a turned body's rim and inclusion and bend the field between them unseen). On a
textured interior, in a frame larger than the checks' ~0.4 Mpx, the plain run stops before its
finest level when it is still far off there (``ABANDON``; the weak preset follows, and the plain
run is finished after all only if the weak one does not beat it). That compares an unfinished run
with a finished one, but at one level: ``weak`` ends on the plain run's level before its finest
(both at the checks' ~0.4 Mpx), where the stop mostly reads it. What it cannot see is what the
plain run's finest level would add (a picture's fine detail under a smooth motion), and neither the
reading at the stop nor the weak run's own settling told the pairs where that pays from those where
it does not (benchmarks/README.md, "After an abandoned plain run: which comparison (session 25)").
So when the weak run is kept and settled, the plain preset's finest level (and polish) runs on the
weak run's field for a short budget (``FINEST_ITERATIONS``), stops halfway unless its residual
already moves clearly less than the weak run's (``FINEST_GAIN``), and is returned only when it
passes its checks and its residual moves less (:func:`finest_from_weak`, :func:`keeps_finest`;
"The plain run's finest level on the weak run's field (session 27)"). ``auto``'s plain run may go past
its finest level's budget when its field is still moving there but its residual already passes
the checks (``EXTEND``): slow, not lost, as on natural images at 2240. ``auto-fast`` on a
textured interior in a frame over 1.6 Mpx skips its plain run and runs ``weak-fast`` alone
(``STRAIGHT_BINNING``, :func:`straight_to_weak`): there ``fast``'s finest level is binned by 8 or
more, and on the TRAINING pairs it was never the one returned. Which
fallback is judged on the fixed image by one no-truth number, the **texture-to-noise ratio of
the body's interior**:

- the fixed image area-averaged to about 0.4 Mpx (as ``register``'s assessment), band-passed
  (Gaussian of 1 px minus Gaussian of 6 px: the body's slow shape and slope go, a texture
  and the noise stay);
- its local variance in a Gaussian window of 4 px (the window's mean removed: the band-passed
  curvature of a smooth body is nearly constant over it), over what the noise alone gives
  there (the noise level from ``_confidence.noise_map``, with ``_confidence.MODEL_FLOOR``
  under it as in the confidence map, times the band-pass's gain on white noise), less 1, square-rooted: the texture's standard deviation against the noise's after
  the same filter, 0 for noise alone;
- its median over the object (``_confidence``'s: differs from the frame's border level) eroded
  by 48 binned pixels: the body's edge and the band-pass's reach from it (6 + 4 px filters,
  each ~3 sigma, plus the object's 4 px blur) are structure, not texture, and the median
  ignores an inclusion's rim.

Binning makes the ratio grow with the frame at a given per-pixel texture-to-noise (a 2240
frame binned by 4 has a quarter of the noise), which is what the weak presets need: their win
grows with the frame (benchmarks/README.md, "Automatic preset choice (session 6)").

``ratio < TEXTURE_LOW``: silent body, ``silent`` (``silent-fast``) is run; otherwise ``weak``
(``weak-fast`` for ``auto-fast``). Threshold chosen on ``regdata``
TRAINING seeds only. (A first version also kept ``default`` above a "rich" ratio of 29, chosen on
the family; natural images read 3-13 there, their structure raising the noise estimate, so the
plain preset's own check replaced it.)

An image without noise is not weak texture, whatever it carries: ``weak`` exists for data that
the noise leaves little to say, so when the interior's noise is below what the confidence map
calls noise-free (``NOISE_FREE`` x ``_confidence.MODEL_FLOOR`` of the image's range, per
full-resolution pixel) it counts as a silent body. Without this rule a smooth body's band-passed curvature and an inclusion's rim read
as texture there (the simulated pva-phantom pair noise-free: 1.4; the family's textureless body
at 384 px noise-free: 1.3; noisy, both under 0.2). The simulated pairs noise-free read noise
0.2-1.0 x that floor, every noisy training pair 5 x or more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "AUTO_PRESETS",
    "AutoChoice",
    "choose",
    "register_auto",
    "keeps_retry",
    "returned",
    "interior_texture_to_noise",
    "TEXTURE_LOW",
    "NOISE_FREE",
    "SILENT_TIE",
    "POLISH",
    "ABANDON",
    "EXTEND",
    "polishes",
    "checks_silent",
    "settled",
    "finest_from_weak",
    "keeps_finest",
    "FINEST_FROM_WEAK",
    "FINEST_ITERATIONS",
    "FINEST_GAIN",
    "STRAIGHT_BINNING",
    "straight_to_weak",
]

# name -> (the preset run first, the one a flagged result on a textured interior falls back to,
# the one a flagged result on a silent body falls back to)
AUTO_PRESETS = {"auto": ("default", "weak", "silent"), "auto-fast": ("fast", "weak-fast", "silent-fast")}
# Chosen on TRAINING seeds (benchmarks/README.md, "Automatic preset choice (session 6)"): the
# textureless and near-textureless pairs (family texture 0 at 560-2240, texture 0.3x noise at
# 560, where `weak` is no better; the simulated pairs of both scene presets, where it is worse)
# read at most 0.68 (seed-breast), the weak-texture pairs where `weak` wins (texture >= noise,
# every spread case, 560-2240) at least 1.09.
TEXTURE_LOW = 0.9
# the interior's median noise per full-resolution pixel (the binned estimate x the binning: white
# noise) over the model floor, below which the image counts as noise-free. Training pairs: the
# simulated pairs noise-free 0.2-1.0; with noise every pair 5-35 (the family 15-35 at 560-2240,
# the simulated pairs with photon noise 5-26, analytic_pair 14-20)
NOISE_FREE = 2.0
# how much more of the observed structure a silent retry may leave misaligned and still be kept:
# chosen on TRAINING seeds 0-3 (560 px, the textureless and 0.3x-noise pairs of the map and the
# physical motion, 32 pairs; benchmarks/README.md, session 7): mean of the pairs' median EPE
# with auto 1.59 px at 0, 1.52 at 0.01-0.02, 1.49 at 0.05, 1.51 at 0.1 (auto-fast 1.76, 1.63-1.67,
# 1.65, 1.65); the physical pairs, where silent wins 5-20x, differ by at most 0.01
SILENT_TIE = 0.05
# px: a plain run that passed its own checks is tried again with the weak preset when its
# residual still moves by more than this and the interior carries texture (:func:`polishes`).
# Chosen on TRAINING seeds (the 560 family, 2 seeds x 25 cases, composed from the flag
# benchmark's cache; benchmarks/README.md, session 10): geometric mean of the median EPE with
# auto 0.500 px without, 0.447 at 0.05-0.2 (6-8 retries, every one kept), 0.500 at 0.25-0.3;
# auto-fast 0.518 without, 0.464 at 0.05-0.15, 0.517 at 0.2-0.25. 0.1: inside both plateaus
POLISH = 0.1
# px: on a textured interior (the fallback the weak preset) the plain run stops before its finest
# level when its residual's motion there, measured as the checks measure it, is over this (rc's
# abandon_px; only where that level is finer than the checks' binning: 1120 px and larger).
# A field that far off is not settled after one more level, so the weak preset runs anyway; the
# finest level (at 2240 more than half the plain run's time) is not spent on it. TRAINING pairs
# at 2240, the residual after 60 of the level's 120 iterations (benchmarks/README.md, "Natural
# images at 2240 (session 16)"): the family's plain runs that settled read at most 0.28 px, those
# that did not 0.83 or more (most 1.5-7.4); but natural images (scikit-image's astronaut, brick,
# coffee, chelsea, retina under a smooth and a local motion), on which the plain run settles after
# its finest level and beats weak 1.3-4x, read up to 0.96 (retina's smooth motion 1.44). A stop
# wrongly made costs the natural image that accuracy; one wrongly not made costs a family pair
# the finest level's time (the weak preset runs after it all the same). So a pixel: session 15's
# 0.35 (the flag's own line) stopped every natural image with the smooth motion
ABANDON = 1.0
# iterations the plain run of ``auto`` (not ``auto-fast``: its time is the point) may add at its
# finest level when the budget ends with the field still moving while the residual already passes
# the checks (rc's ``extend``): such a run is slow, not lost, and without it ``auto`` replaced it
# with ``weak``, which is 1.3-4x worse on natural images at 2240 (TRAINING images of
# scikit-image, benchmarks/README.md, "Natural images at 2240 (session 16)"). 60 more (140 in
# all): all five training images converged under local motion of 1/10 of the frame, four of five
# under a smooth one, their medians within 0.013 px of 200 iterations' (0.04-0.15 px)
EXTEND = 60
# after a stopped plain run and a settled weak one kept, the plain preset's finest level (and
# polish) on the weak field (:func:`finest_from_weak`): the weak levels end at the checks' ~0.4 Mpx
# and miss what the finer images show on a picture under a smooth motion; chosen on TRAINING pairs
# at 2240 (benchmarks/README.md, "The plain run's finest level on the weak run's field (session 27)")
FINEST_FROM_WEAK = True
# that level's budget: from the weak field it has only the fine detail left to fit (same section)
FINEST_ITERATIONS = 20
# ... and the level is stopped halfway (rc's abandon_px, ABANDON_AT) unless its residual moves less
# than this x the weak run's: in the gap between the pictures that gain most and the first of the
# family's pairs where the level, kept on a smaller residual alone, lost accuracy and time. It does
# not separate the two: some pictures that gain read above it (same section, its widened training)
FINEST_GAIN = 0.85
# auto-fast on a textured interior (its fallback weak-fast) runs weak-fast alone, without fast first,
# when fast's finest level is binned by this or more (:func:`straight_to_weak`; a control point
# every 2 pixels of that level): there fast was never the one returned, so running it first only
# cost its time (at 2240 over a third of auto-fast's). Chosen on TRAINING pairs (the family,
# texture 0.3-10x the noise; the natural pictures of bench_register_natural; analytic_pair): at
# 2240 (binned by 8) auto-fast returned weak-fast on every pair whose fallback it was; at 840 and
# 1120 (by 4) it kept fast on 13 of 14 analytic pairs (rich texture under a smooth motion, where
# fast is 1.5x better), at 560 (by 2) on a sixth of the family and natural pairs. The texture
# ratio alone cannot draw the line, it grows with the frame: astronaut at 560 (fast kept) reads
# less than the weak family at 2240. benchmarks/README.md, "auto-fast straight to weak-fast
# (session 29)"
STRAIGHT_BINNING = 8
_NOISE_WINDOW = 24.0  # px (binned): the noise level's window, as the confidence map's
_BAND = (1.0, 6.0)  # px (binned): Gaussian sigmas of the band-pass
_WINDOW = 4.0  # px (binned): the local variance's Gaussian window
_ERODE = 48  # px (binned): the interior starts this far inside the object
_GAIN = {}  # band -> variance of the band-pass of unit white noise (measured once)


@dataclass(frozen=True)
class AutoChoice:
    """What ``preset="auto"`` chose and why: ``preset`` the preset run, ``ratio`` the
    interior's texture-to-noise ratio, ``interior`` the share of the (binned) frame it was
    measured on, ``reason`` one line."""

    preset: str
    ratio: float
    interior: float
    reason: str


def _band_gain(band):
    """Variance of the band-pass (Gaussian ``band[0]`` minus Gaussian ``band[1]``) of unit
    white noise: measured once on a noise image (exact enough, and true to the filters used)."""
    from radiokit.register import _confidence as C

    if band not in _GAIN:
        z = np.random.default_rng(0).standard_normal((512, 512)).astype(np.float32)
        b = C._gauss(z, band[0]) - C._gauss(z, band[1])
        _GAIN[band] = float(b[64:-64, 64:-64].var())
    return _GAIN[band]


def interior_texture_to_noise(image, mask=None, frame=False) -> tuple[float, float, float]:
    """``(ratio, interior, noise)``: the median texture-to-noise ratio of the body's interior,
    the share of the binned frame the interior covers (see the module docstring), and the
    interior's median noise per full-resolution pixel over the model floor; ``(0, 0, inf)`` when
    no pixel lies ``_ERODE`` binned pixels inside the object (nothing to judge the texture by).
    ``mask`` (bool, the image's shape; ``register``'s ``mask=``): the object only where it holds,
    as ``register``'s checks take it. ``frame``: the whole frame is the object (see
    :func:`choose`)."""
    from radiokit.register import _assess_binning, _bin, _bin_mask, _erode
    from radiokit.register import _confidence as C

    f = np.asarray(image, np.float32)
    binning = _assess_binning(f.size)
    fb = _bin(f, binning)
    sig = C.noise_map(fb, _NOISE_WINDOW)
    obj = np.ones(fb.shape, bool) if frame else C._object(fb, float(np.median(sig)))
    # the caller's object, binned as register()'s checks bin it: a textured structure the mask
    # leaves out is not the body's texture
    if mask is not None:
        obj &= _bin_mask(mask, binning)
    inner = _erode(obj, _ERODE)
    if not inner.any():
        return 0.0, 0.0, float("inf")
    b = C._gauss(fb, _BAND[0]) - C._gauss(fb, _BAND[1])
    mean = C._gauss(b, _WINDOW)
    var = C._gauss(b * b, _WINDOW) - mean * mean
    floor = C.model_floor(fb)
    noise2 = sig[inner] ** 2 + floor**2  # a noise-free image: see MODEL_FLOOR
    ratio = np.sqrt(np.maximum(var[inner] / (_band_gain(_BAND) * noise2) - 1.0, 0.0))
    quiet = binning * float(np.median(sig[inner])) / floor if floor > 0 else 0.0
    # the frame's: its lower quartile (see _without_interior)
    return float(np.percentile(ratio, 25 if frame else 50)), float(inner.mean()), quiet


def choose(fixed, name="auto", mask=None) -> AutoChoice:
    """What ``name`` (``"auto"`` or ``"auto-fast"``) falls back to on this ``fixed`` image when
    its plain preset fails its own checks: the weak preset when the interior carries texture
    (ratio >= ``TEXTURE_LOW``, with noise); the silent preset when it does not (a silent or
    noise-free body: only its edges and inclusions observe the motion, and ``weak``'s free
    coarse levels would follow the edges' thickness change); without an interior inside the
    object, the weak preset when the frame's interior carries texture, else the plain one
    (:func:`_without_interior`). ``mask``: ``register``'s, the object the texture is judged on."""
    plain, weak, silent = AUTO_PRESETS[name]
    ratio, interior, noise = interior_texture_to_noise(fixed, mask)
    if interior == 0.0:
        return _without_interior(fixed, name, mask)
    if noise < NOISE_FREE:
        why = f"noise-free image: interior noise {noise:.2f} x the model floor (< {NOISE_FREE:g}), texture/noise moot"
        return AutoChoice(silent, ratio, interior, why)
    if ratio < TEXTURE_LOW:
        return AutoChoice(silent, ratio, interior, f"silent body: interior texture/noise {ratio:.2f} < {TEXTURE_LOW:g}")
    return AutoChoice(weak, ratio, interior, f"weak texture: interior texture/noise {ratio:.2f} >= {TEXTURE_LOW:g}")


def _without_interior(fixed, name, mask) -> AutoChoice:
    """:func:`choose` when no pixel lies ``_ERODE`` binned pixels inside the object: the texture
    judged on the frame's interior instead (the frame, inside ``mask``, less ``_ERODE`` from its
    edges), by the ratio's lower quartile, not its median: a small body's edges reach up to half
    of that interior (a 40 px square in a 200 px frame of empty beam: median 2.8, quartile 0), a
    texture filling it is everywhere (at 1x the noise: median 2.5, quartile 2.1). The weak preset
    when it carries texture (quartile >= ``TEXTURE_LOW``, with noise), otherwise the plain one,
    with the reason.

    Why. The object is what differs from the frame's border level (``_confidence._object``), and a
    texture filling the frame lies around that level: only its extremes differ from it, in patches
    too small to have an interior (a 384 px frame of texture 1-3x the noise: 0.6-55 % of it, no
    interior), so the plain run was kept flagged or still moving, never retried, where ``weak``
    registers it better. Not silent there: the silent preset starts from the body's silhouette,
    and a frame whose interior is quiet holds no body wider than ``2 _ERODE`` binned pixels, only
    a small one on an empty beam (or nothing), for which no preset was chosen by measurement."""
    plain, weak, _ = AUTO_PRESETS[name]
    ratio, interior, noise = interior_texture_to_noise(fixed, mask, frame=True)
    where = f"no interior {_ERODE} px (binned) inside the body"
    if interior == 0.0:
        return AutoChoice(plain, ratio, interior, f"{where} nor inside the frame")
    if noise < NOISE_FREE or ratio < TEXTURE_LOW:
        why = f"{where}, and the frame's interior carries no texture for {weak} (texture/noise {ratio:.2f}, noise {noise:.2f} x the model floor)"
        return AutoChoice(plain, ratio, interior, why)
    why = f"weak texture: {where}, the frame's interior texture/noise {ratio:.2f} >= {TEXTURE_LOW:g}"
    return AutoChoice(weak, ratio, interior, why)


def keeps_retry(plain, retry, silent=False, tie=SILENT_TIE) -> bool:
    """Whether the retry's ``Quality`` beats the plain run's. A ``weak`` retry wins when the
    residual moves less after it (``quality.residual_motion``, the matched estimate of what is
    left, which sees at texture near the noise what the misaligned share does not; on the
    training seeds it kept the better field more often: ``auto`` geometric-mean EPE 0.508 ->
    0.497 px, ``auto-fast`` 0.561 -> 0.535, benchmarks/README.md, "The flag (session 9)"); a
    plain run with nothing observed (NaN) loses to a retry that observes something, a retry
    with nothing observed never wins. A ``silent`` retry wins unless it leaves more than
    ``SILENT_TIE`` more of the observed structure misaligned: on a silent body the observed part
    is a thin band at the edges, where the two fields differ little, and in the silent interior
    the stiff field is the better guess (the family's physical motion without texture: 0.00
    misaligned for both, 0.81 against 0.18 px); and a silent retry that observes what the plain
    run did not (its share a number, the plain run's NaN) wins. ``tie``: the silent retry's allowance
    (0 after a plain run that passed its checks: :func:`checks_silent`)."""
    if silent:
        p, r = plain.misaligned_fraction, retry.misaligned_fraction
        if np.isnan(p) or np.isnan(r):
            return bool(np.isnan(p) and not np.isnan(r))
        return r <= p + tie
    p, r = plain.residual_motion, retry.residual_motion
    if np.isnan(r):
        return False
    return bool(np.isnan(p) or r < p)


def settled(quality) -> bool:
    """A plain run ``auto`` returns without trying anything else: it passed its own checks and
    its residual is still (``residual_motion`` at most ``POLISH``)."""
    return bool(quality.ok and not quality.residual_motion > POLISH)


def polishes(name, plain_quality, fallback) -> bool:
    """Whether a plain run that passed its own checks is tried again all the same: when its
    residual still moves by more than ``POLISH`` px and the body's interior carries texture
    (``fallback`` is the weak preset). ``default``'s lattice balance is stiff for local motion
    on a small frame, and the weak preset's free coarse levels fit it where the texture is
    rich (the 560 map, texture 10x the noise, correlation 1/10: 0.30-0.37 px kept, the weak
    preset's 0.05-0.06 px); the retry is kept only when its residual moves less."""
    return bool(plain_quality.ok and fallback == AUTO_PRESETS[name][1] and not settled(plain_quality))


def checks_silent(name, plain_quality, fallback) -> bool:
    """Whether a plain run that passed its own checks is tried again with the silent preset all
    the same: whenever :func:`choose` falls back to it (a silent body), settled or not. On a
    silent body the plain run's free lattice can fit the rim and an inclusion each where it lies
    and bend the field between them, a field the residual cannot fault (the rim of a round body
    moves along itself under a turn; the confidence map's windows observe a translation, not the
    field's bending within them): the turned bodies of ``bench_register_turned`` (TRAINING seeds)
    were trusted at 6.56 and 1.43 px (seeds 12, 23), where ``silent`` registered 0.05 and 0.01 px
    and passed its checks; on the nine TRAINING pairs where it replaced the plain run (seven turned
    bodies, a phantom-like pair, a noisy-fixed pair) it was the better field every time, and the
    family's silent bodies never reach it (their plain run fails its checks; benchmarks/README.md,
    "auto's trusted default on turned bodies (session 44)"). The retry replaces the plain run only
    when it passes its own checks too and leaves no more of the observed structure misaligned
    (:func:`returned`), without ``SILENT_TIE``, which was chosen for a flagged plain run: every pair
    it won left 0.000 misaligned both (the turned bodies' TRAINING and TEST, phantoms 6025,
    noisy-fixed 3417) but phantoms TEST 6055 (0.68 -> 0.56 px, 0.045 more: kept at 0.68 now), where
    on the simulated seed-breast pairs (the paper's scene, steps -1, 373-560 px) ``silent`` passed
    its checks too, 2.7-3.3x worse, leaving 0.052-0.14 more (review s44rr: one pair 0.002 over
    the tie)."""
    return bool(plain_quality.ok and fallback == AUTO_PRESETS[name][2] != AUTO_PRESETS[name][0])


def returned(name, plain_quality, fallback, retry_quality) -> str:
    """The preset ``register(..., preset=name)`` returns, given the plain run's ``Quality``, the
    preset :func:`choose` fell back to, and that retry's ``Quality`` (read only when the retry
    is run): the plain one when it passed its own checks (unless :func:`polishes`) or nothing
    else is tried, else the retry if :func:`keeps_retry` prefers it. The benchmarks compose
    ``auto`` from cached runs with it."""
    plain, _, silent = AUTO_PRESETS[name]
    if checks_silent(name, plain_quality, fallback):  # both trusted: the silent one unless it leaves more misaligned
        # no SILENT_TIE: a trusted plain run is no guess to break ties against (checks_silent)
        ok = retry_quality is not None and retry_quality.ok
        kept = ok and keeps_retry(plain_quality, retry_quality, silent=True, tie=0.0)
        return fallback if kept else plain
    if (plain_quality.ok and not polishes(name, plain_quality, fallback)) or fallback == plain:
        return plain
    return fallback if keeps_retry(plain_quality, retry_quality, silent=fallback == silent) else plain


def finest_from_weak(weak_quality) -> bool:
    """Whether, after a plain run stopped early (``ABANDON``) and the weak run kept, the plain
    preset's finest level (and polish) is run on the weak run's field (rc's ``start_lattices``):
    when ``FINEST_FROM_WEAK`` and the weak run is settled (:func:`settled`)."""
    return bool(FINEST_FROM_WEAK and settled(weak_quality) and np.isfinite(weak_quality.residual_motion))


def keeps_finest(weak_quality, finest_quality) -> bool:
    """Whether the plain preset's finest level on the weak run's field (:func:`finest_from_weak`)
    is returned instead of the weak run: it passed its own checks (its level not stopped against
    ``FINEST_GAIN``) and its residual moves less (:func:`keeps_retry`)."""
    return bool(finest_quality.ok and keeps_retry(weak_quality, finest_quality))


def _finest(name, options, weak) -> dict:
    """The options of the plain preset's finest level on the ``weak`` run's field: its lattices
    as the start (rc's ``start_lattices``), ``FINEST_ITERATIONS``, no ``extend``, and
    ``abandon_px`` at ``FINEST_GAIN`` x the weak run's residual motion (checked halfway and at
    the level's end: a level not on its way to beating the weak run stops, without its polish)."""
    line = FINEST_GAIN * weak.quality.residual_motion
    return dict(
        options,
        preset=AUTO_PRESETS[name][0],
        start_lattices=weak.lattices,
        iterations=FINEST_ITERATIONS,
        extend=0,
        abandon_px=line,
    )


def _finest_binning(preset, shape, options) -> int:
    """The factor ``preset``'s finest level (with the caller's ``options``) is binned by on a
    ``shape`` frame: the pyramid's, times ``bin_pixels``'s."""
    from radiokit.register._bspline import PRESETS, _bin_factor, _options, _pyramid

    o = _options(preset, {k: v for k, v in options.items() if k in PRESETS["default"]})
    k = _bin_factor(shape, o["bin_pixels"])
    binned = (shape[0] // k, shape[1] // k)
    return _pyramid(binned, o)[-1][0] * k


def straight_to_weak(name, method, fallback, shape, options, retry) -> bool:
    """Whether ``name`` runs its weak preset alone, its plain run skipped: ``auto-fast`` with
    ``rc`` (where it was measured), its fallback the weak preset (:func:`choose`: a textured
    interior, with noise), no ``retry`` (which is for the plain run), and ``fast``'s finest level
    binned by ``STRAIGHT_BINNING`` or more in this frame with these options (rc's presets: a
    frame over 1.6 Mpx, 1265 px a side and larger; fast's levels hold at most 100,000 pixels).
    There, on the TRAINING pairs, fast was never the one returned (``STRAIGHT_BINNING``'s
    comment). ``auto``'s plain run is not skipped: ``default``'s finest level is finer than the
    checks' and wins 1.3-4x on natural images at 2240 (``ABANDON``, ``EXTEND``)."""
    if name != "auto-fast" or method != "rc" or retry or fallback != AUTO_PRESETS[name][1]:
        return False
    return _finest_binning(AUTO_PRESETS[name][0], shape, options) >= STRAIGHT_BINNING


def _plain(name, options, early) -> dict:
    """The options of ``name``'s plain run: ``abandon_px`` (``ABANDON``) when ``early`` and
    ``extend`` (``EXTEND``, ``auto`` only), each unless the caller set it."""
    o = dict(options, preset=AUTO_PRESETS[name][0])
    if early and options.get("abandon_px") is None:
        o["abandon_px"] = ABANDON
    if name == "auto" and options.get("extend") is None:
        o["extend"] = EXTEND
    return o


def register_auto(register, f, m, method, mask, retry, options):
    """``register(..., preset="auto")``: the plain preset first; kept when it passes its own
    checks (``quality.ok``) or when :func:`choose` falls back to it (no interior, nor texture in the frame's); otherwise
    the weak or silent preset too (:func:`choose`), and the one :func:`keeps_retry` prefers is
    returned (its time is both runs'). ``auto-fast`` where :func:`straight_to_weak`: the weak
    preset alone. ``options["auto"]`` records the choice and why."""
    name = options["preset"]
    plain = AUTO_PRESETS[name][0]
    fallback = choose(f, name, mask)  # judged where the caller's mask says the object is
    if straight_to_weak(name, method, fallback.preset, f.shape, options, retry):
        reg = register(f, m, method, mask, retry=False, **dict(options, preset=fallback.preset))
        why = f"{fallback.reason}; {plain} not run (its finest level binned by {STRAIGHT_BINNING} or more)"
        reg.options["auto"] = AutoChoice(fallback.preset, fallback.ratio, fallback.interior, why)
        return reg
    # on a textured interior a plain run that is far off before its finest level stops there
    # (ABANDON): the weak preset follows anyway
    early = fallback.preset == AUTO_PRESETS[name][1] and not retry
    first = register(f, m, method, mask, retry=retry, **_plain(name, options, early))
    if settled(first.quality) and not checks_silent(name, first.quality, fallback.preset):
        first.options["auto"] = AutoChoice(plain, float("nan"), float("nan"), f"{plain} passed its own checks")
        return first
    retried = polishes(name, first.quality, fallback.preset) or checks_silent(name, first.quality, fallback.preset)
    if fallback.preset == plain or (first.quality.ok and not retried):
        why = f"{plain} passed its own checks" if first.quality.ok else fallback.reason
        first.options["auto"] = AutoChoice(plain, fallback.ratio, fallback.interior, why)
        return first
    second = register(f, m, method, mask, retry=False, **dict(options, preset=fallback.preset))
    total = first.quality.seconds + second.quality.seconds
    if "abandoned" in first.options and returned(name, first.quality, fallback.preset, second.quality) == plain:
        # the fallback did not beat the abandoned run where it stopped: the plain preset in full
        # after all. Not "unless weak settled": weak still moves on the weak texture the stop is
        # for, and finishing there buys time over the budget and no better field (module docstring)
        first = register(f, m, method, mask, retry=retry, **_plain(name, options, False))
        total += first.quality.seconds
    if fallback.preset == AUTO_PRESETS[name][2]:  # silent: judged by the misaligned share
        a, b, what = first.quality.misaligned_fraction, second.quality.misaligned_fraction, "misaligned"
    else:
        a, b, what = first.quality.residual_motion, second.quality.residual_motion, "residual motion"
    state = f"{plain} not ok ({first.quality.reason})"
    if first.quality.ok:
        state = f"{plain} ok" + ("" if settled(first.quality) else ", its residual still moving")
    why = f"{state}; {fallback.reason}; {what} {a:.2f} -> {b:.2f}"
    best = second if returned(name, first.quality, fallback.preset, second.quality) != plain else first
    chose = None
    if (
        best is second
        and method == "rc"  # FINEST_ITERATIONS and FINEST_GAIN were chosen on rc's runs
        and "abandoned" in first.options
        and second.lattices is not None
        and finest_from_weak(second.quality)
    ):
        # the plain run stopped and the weak one kept: the plain preset's finest level (and polish)
        # on the weak field, what the stop left out, kept only when its residual moves less
        third = register(f, m, method, mask, retry=False, **_finest(name, options, second))
        total += third.quality.seconds
        kept = keeps_finest(second.quality, third.quality)
        r2, r3 = second.quality.residual_motion, third.quality.residual_motion
        why += f"; {plain}'s finest level on it: residual motion {r2:.2f} -> {r3:.2f}, {'kept' if kept else 'not kept'}"
        if kept:
            # the field is both runs': no one preset's options make it, so the options say
            # auto (which, run again, makes it), the choice says what it is, and the
            # iterations count both runs' (as the refit's passes are counted)
            third.quality.iterations += second.quality.iterations
            third.options = dict(
                options, preset=name, **{k: third.options[k] for k in ("initial",) if k in third.options}
            )
            chose = f"{second.options['preset']}+{plain}-finest"
            best = third
    best.quality.seconds = total
    best.options["auto"] = AutoChoice(chose or best.options["preset"], fallback.ratio, fallback.interior, why)
    return best
