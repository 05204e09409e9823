"""The processing report: one self-contained HTML page with PNG figures, after the paper's Figs. 4-8.

``write_report(out_dir, results, arrays)`` writes ``out_dir/report.html`` and its figures in
``out_dir/figures/`` (linked relatively, so the folder can be moved or zipped) and returns the
HTML path. The page has inline CSS, no JavaScript and no network references; every piece of text
that comes from the data is escaped.

What a reader finds, in order:

1. a headline table (this run against the paper) and a paragraph saying in plain words what the
   numbers show;
2. the projections of every compression step on one colour scale, with the ROIs (paper Figs. 4-5);
3. profiles along the row through the inclusion: every step, and reference vs enhanced (Fig. 6);
4. the compression-induced difference ``D = reference - registered`` per domain;
5. reference vs enhanced images for every k in both domains (Figs. 7-8), each panel on its own
   percentile scale with its contrast in the title;
6. contrast, CNR, Weber contrast, improvement factors and intensity-change ratios beside the
   paper's numbers;
7. for simulated experiments with a control run (inclusion as soft as the background): how much
   of the improvement needs the inclusion's stiffness (:func:`stiffness_share`);
8. registration quality: overlays before/after, displacement, det J, end-point error against the
   simulation's truth when known, and a table of every registered pair;
9. the timings.

Figures are drawn on :class:`matplotlib.figure.Figure` objects with the Agg canvas, never through
``pyplot``: no global figure registry to leak into, no backend switched under the caller, and
nothing left open after saving. Each PNG is kept under ``MAX_PNG_BYTES`` (palette-quantised, then
drawn at a lower dpi, if needed).
"""
from __future__ import annotations

import html
import io
import math
import time
from datetime import datetime, UTC
from pathlib import Path

import numpy as np

from radiokit._version import __version__
from radiokit.measure import PAPER  # used when results["paper"] does not give them

__all__ = ["write_report", "stiffness_share", "PAPER", "MAX_PNG_BYTES"]

#: Upper bound on the size of one figure file.
MAX_PNG_BYTES = 300_000
#: An improvement factor within this of 1 has no measurable compression-induced contrast to share.
MIN_EFFECT = 0.01

_DPI = 100
_MAX_WIDTH_IN = 12.0
_DOMAIN_ORDER = ("log", "negative", "linear")
_TRANSMISSION = ("negative", "linear")  # intensity domains: -I/I0 (the paper's), I/I0
_INCLUSION_COLOUR = "#ff3b30"
_BACKGROUND_COLOUR = "#00c8ff"
_PROFILE_HALF_ROWS = 1  # profiles average 2 * 1 + 1 rows: one detector row is too noisy to read
_TIMING_LABELS = {
    "calibrate_s": "calibrate (darks, flats, defects)",
    "correct_s": "correct (flat field, log)",
    "register_s": "register",
    "enhance_s": "enhance",
    "measure_s": "measure",
    "report_s": "report",
    "total_s": "total",
}


# -- small, defensive accessors ------------------------------------------------------------------
def _num(x):
    """``float(x)`` when it is a finite number, else None."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _fmt(x, spec=".2f", missing="\u2014"):
    v = _num(x)
    return missing if v is None else format(v, spec)


def _get(d, *keys, default=None):
    """Nested ``.get`` that tolerates missing levels and non-dict values."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def _kget(d, k):
    """The value for k in a dict keyed by k as a string ("1", "1.0" or "1.5")."""
    if not isinstance(d, dict):
        return None
    if k in d:
        return d[k]
    kf = _num(k)
    if kf is None:
        return None
    for key in d:
        if _num(key) == kf:
            return d[key]
    return None


def _k_keys(*dicts):
    """Every k key present in the given dicts, as strings, sorted by value."""
    keys = {}
    for d in dicts:
        if isinstance(d, dict):
            for key in d:
                v = _num(key)
                if v is not None:
                    keys.setdefault(v, str(key))
    return [keys[v] for v in sorted(keys)]


def _main_k(ks):
    """The k the text talks about: 1 (the paper's direct addition) when present, else the smallest."""
    return next((k for k in ks if _num(k) == 1.0), ks[0])


def _k_label(k):
    return f"k={float(k):g}"


def _pair_label(pair) -> str:
    return str(pair).replace("->", "\u2192")


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _finite(a):
    a = np.asarray(a, dtype=np.float64)
    return a[np.isfinite(a)]


def _limits(a, lo=1.0, hi=99.0):
    """Percentile display limits of the finite values, never empty or NaN."""
    v = _finite(a)
    if v.size == 0:
        return 0.0, 1.0
    vmin, vmax = (float(p) for p in np.percentile(v, [lo, hi]))
    if not vmax > vmin:
        vmin, vmax = float(v.min()), float(v.max())
    if not vmax > vmin:
        pad = max(abs(vmin) * 1e-3, 1e-6)
        vmin, vmax = vmin - pad, vmax + pad
    return vmin, vmax


def _normalise(a, lo=1.0, hi=99.0):
    vmin, vmax = _limits(a, lo, hi)
    out = (np.asarray(a, np.float64) - vmin) / (vmax - vmin)
    return np.clip(np.nan_to_num(out, nan=0.0), 0.0, 1.0)


def _rect(rois, name):
    r = rois.get(name) if isinstance(rois, dict) else None
    if r is None or len(r) != 4:
        return None
    try:
        r0, r1, c0, c1 = (int(x) for x in r)
    except (TypeError, ValueError):
        return None
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else None


def _ratio_label(ratio):
    r = _num(ratio)
    if r is None:
        return ""
    return f"{100 * r:.0f} % compression" if 0 <= r <= 1 else f"ratio {r:g}"


def _domain_unit(domain):
    """The pixel's meaning in ``domain`` (radiokit.enhance.Domain's names)."""
    return {"log": "\u2212ln(I/I\u2080)", "negative": "\u2212I/I\u2080", "linear": "I/I\u2080"}.get(domain, str(domain))


# -- the share of the improvement that needs stiffness -------------------------------------------
def stiffness_share(if_stiff, if_control, *, min_effect=MIN_EFFECT):
    """The fraction of the compression-induced contrast gain that needs the inclusion's stiffness.

    Parameters
    ----------
    if_stiff : float
        Improvement factor of the experiment (stiff inclusion).
    if_control : float
        Improvement factor of the control run: the same scene with the inclusion as soft as the
        background, so only attenuation (the thinning of a denser inclusion) makes contrast.
    min_effect : float, optional
        When ``|if_stiff - 1|`` is below this there is no gain to share: the result is None.

    Returns
    -------
    float or None
        ``Z = (if_stiff - if_control) / (if_stiff - 1)``; None when not measurable (no gain, or a
        non-finite input). Z is not clipped: above 1 the control alone lowers the contrast, below
        0 the control gains more than the stiff inclusion.

    Notes
    -----
    The improvement factor is ``1 + k C_D / C_ref`` (``C_D`` the contrast of the difference image),
    so ``Z`` does not depend on k when both runs share the reference contrast.

    Examples
    --------
    >>> round(stiffness_share(1.4, 1.1), 6)
    0.75
    >>> stiffness_share(1.004, 1.2) is None
    True
    """
    s, c = _num(if_stiff), _num(if_control)
    if s is None or c is None or abs(s - 1.0) < min_effect:
        return None
    return (s - c) / (s - 1.0)


def _share_text(z):
    return "not measurable" if z is None else f"{100 * z:.0f} %"


def _control_sentence(domain, k, if_stiff, if_control):
    z = stiffness_share(if_stiff, if_control)
    head = (f"In the {domain} domain, the control's improvement at {_k_label(k)} is "
            f"{_fmt(if_control)} vs {_fmt(if_stiff)}: ")
    if z is None:
        body = ("the share of the compression-induced contrast that needs the inclusion's stiffness is "
                f"not measurable (the stiff inclusion's improvement is within {MIN_EFFECT:g} of 1, "
                "or missing).")
    elif z > 1:
        body = (f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness; "
                "attenuation alone (the thinning of a denser inclusion) would lower the contrast, "
                "since the control's improvement is below 1.")
    elif z < 0:
        body = (f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness: "
                "the control gains more than the stiff inclusion, so none of the gain can be credited "
                "to elasticity.")
    else:
        body = (f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness; "
                "the rest comes from attenuation alone (the thinning of a denser inclusion).")
    if domain in _TRANSMISSION:
        body += (" In the intensity domain the detected intensity is exponential in the line integral "
                 "(I = I\u2080\u00b7exp(\u2212\u222b\u03bc dl)), so the same thinning changes the intensity "
                 "behind the inclusion and behind the background by different amounts: part of the "
                 "effect needs no stiffness at all.")
    return head + body


# -- figures -------------------------------------------------------------------------------------
def _new_figure(width_in, height_in):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scale = min(1.0, _MAX_WIDTH_IN / width_in)  # wider than the page only costs bytes
    fig = Figure(figsize=(width_in * scale, height_in * scale), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _png_bytes(fig, dpi, max_bytes):
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    data = buf.getvalue()
    if len(data) > max_bytes:
        # noisy radiographs compress badly as RGBA; 256 colours lose nothing a reader sees
        img = Image.open(io.BytesIO(data)).convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE)
        buf = io.BytesIO()
        img.save(buf, format="PNG", optimize=True)
        data = min(data, buf.getvalue(), key=len)
    return data


def _save(fig, path: Path, max_bytes=MAX_PNG_BYTES) -> None:
    """Write ``fig`` as a PNG under ``max_bytes``: plain, else palette-quantised, else at a lower dpi."""
    dpi = _DPI
    data = _png_bytes(fig, dpi, max_bytes)
    for _ in range(4):
        if len(data) <= max_bytes:
            break
        # the bytes of noisy images grow with the pixel count, i.e. with dpi squared
        dpi = max(30, int(dpi * 0.92 * math.sqrt(max_bytes / len(data))))
        data = _png_bytes(fig, dpi, max_bytes)
    path.write_bytes(data)
    fig.clear()


def _panel_size(shape, width=3.0):
    rows, cols = shape
    aspect = rows / cols if cols else 1.0
    return width, float(np.clip(width * aspect, 1.2, 2.5 * width))


def _draw_rois(ax, rois, legend=False):
    from matplotlib.patches import Rectangle

    for name, colour in (("inclusion", _INCLUSION_COLOUR), ("background", _BACKGROUND_COLOUR)):
        r = _rect(rois, name)
        if r is None:
            continue
        r0, r1, c0, c1 = r
        ax.add_patch(Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0, r1 - r0, fill=False,
                               edgecolor=colour, linewidth=1.2, label=name))
    if legend and ax.patches:
        ax.legend(loc="lower right", fontsize=7, framealpha=0.7)


def _style_image_axes(ax, ticks=True):
    if ticks:
        ax.tick_params(labelsize=7)
    else:  # the ROI coordinates are in the tables; tick labels cost half the drawing time
        ax.set_xticks([])
        ax.set_yticks([])


def _fig_projections(arrays, results, fig_dir):
    steps = arrays.get("steps")
    if steps is None or np.ndim(steps) != 3 or len(steps) == 0:
        return None
    steps = np.asarray(steps)
    n = len(steps)
    numbers = list(arrays.get("step_numbers") or range(1, n + 1))
    ratios = list(arrays.get("ratios") or [None] * n)
    rois = results.get("rois") or {}
    ncols = min(n, 4)
    nrows = -(-n // ncols)
    w, h = _panel_size(steps.shape[1:])
    fig = _new_figure(w * ncols + 1.0, (h + 0.5) * nrows)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    vmin, vmax = _limits(steps, 0.5, 99.5)
    im = None
    for i, ax in enumerate(axes):
        if i >= n:
            ax.set_axis_off()
            continue
        im = ax.imshow(steps[i], cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
        _draw_rois(ax, rois, legend=(i == 0))
        number = numbers[i] if i < len(numbers) else i + 1
        label = _ratio_label(ratios[i] if i < len(ratios) else None)
        ax.set_title(f"step {number}" + (f" \u2014 {label}" if label else ""), fontsize=9)
        _style_image_axes(ax)
    cb = fig.colorbar(im, ax=list(axes[:n]), shrink=0.85)
    cb.set_label("line integral \u2212ln(I/I\u2080)", fontsize=8)
    name = "projections.png"
    _save(fig, fig_dir / name)
    px = _num(results.get("pixel_mm"))
    caption = ("Projections of every compression step (line integrals \u2212ln(I/I\u2080), least compressed "
               "first), on one shared grey scale (0.5\u201399.5 percentiles of all steps), so brightness "
               "compares across steps; brighter is more attenuation. Red: inclusion ROI; cyan: background "
               "ROI (where contrast is measured). Axes in pixels of the cropped image"
               + (f" ({px:g} mm per pixel)." if px else ".") + " After the paper's Figs. 4\u20135.")
    return name, caption


def _profile_rows(shape, rois, row=None):
    rows = shape[0]
    r = _rect(rois, "inclusion")
    centre = (r[0] + r[1]) // 2 if r else rows // 2
    if _num(row) is not None:
        centre = int(row)
    centre = int(np.clip(centre, 0, rows - 1))
    return centre, max(0, centre - _PROFILE_HALF_ROWS), min(rows, centre + _PROFILE_HALF_ROWS + 1)


def _row_mean(img, a, b):
    """Mean of rows a:b per column over the finite pixels; NaN where a column has none."""
    band = np.asarray(img, np.float64)[a:b]
    ok = np.isfinite(band)
    n = ok.sum(axis=0)
    total = np.where(ok, band, 0.0).sum(axis=0)
    return np.divide(total, n, out=np.full(band.shape[1], np.nan), where=n > 0)


def _fig_profiles(arrays, results, fig_dir):
    steps = arrays.get("steps")
    enhanced = arrays.get("enhanced") or {}
    refs = arrays.get("reference_by_domain") or {}
    domains = [d for d in _DOMAIN_ORDER if d in enhanced and d in refs] + \
              [d for d in enhanced if d in refs and d not in _DOMAIN_ORDER]
    has_steps = steps is not None and np.ndim(steps) == 3 and len(steps) > 0
    if not has_steps and not domains:
        return None
    shape = np.shape(steps)[1:] if has_steps else np.shape(refs[domains[0]])
    rois = results.get("rois") or {}
    centre, a, b = _profile_rows(shape, rois, results.get("profiles_row"))
    px = _num(results.get("pixel_mm"))
    x = np.arange(shape[1]) * (px or 1.0)
    xlabel = "column (mm, cropped image)" if px else "column (px, cropped image)"
    inc = _rect(rois, "inclusion")
    npanels = int(has_steps) + len(domains)
    fig = _new_figure(4.2 * npanels, 3.4)
    axes = np.atleast_1d(fig.subplots(1, npanels, squeeze=False)).ravel()

    def shade(ax):
        if inc:
            s = px or 1.0
            ax.axvspan((inc[2] - 0.5) * s, (inc[3] - 0.5) * s, color=_INCLUSION_COLOUR, alpha=0.12,
                       label="inclusion ROI columns")

    i = 0
    if has_steps:
        ax = axes[i]
        i += 1
        steps = np.asarray(steps)
        numbers = list(arrays.get("step_numbers") or range(1, len(steps) + 1))
        ratios = list(arrays.get("ratios") or [None] * len(steps))
        for j, img in enumerate(steps):
            label = f"step {numbers[j] if j < len(numbers) else j + 1}"
            rl = _ratio_label(ratios[j] if j < len(ratios) else None)
            ax.plot(x, _row_mean(img, a, b), lw=1.1, label=label + (f" ({rl})" if rl else ""))
        shade(ax)
        ax.set_title("every step (log domain)", fontsize=9)
        ax.set_ylabel("\u2212ln(I/I\u2080)", fontsize=8)
    for dom in domains:
        ax = axes[i]
        i += 1
        ref = np.asarray(refs[dom])
        ax.plot(x, _row_mean(ref, a, b), color="black", lw=1.4, label="reference")
        for k in _k_keys(enhanced[dom]):
            img = np.asarray(_kget(enhanced[dom], k))
            ax.plot(x, _row_mean(img, a, b), lw=1.1, label=f"enhanced, {_k_label(k)}")
        shade(ax)
        ax.set_title(f"reference vs enhanced ({dom} domain)", fontsize=9)
        ax.set_ylabel(_domain_unit(dom), fontsize=8)
    for ax in axes:
        ax.set_xlabel(xlabel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    name = "profiles.png"
    _save(fig, fig_dir / name)
    caption = (f"Profiles along the row through the inclusion's centre (row {centre} of the cropped image, "
               f"mean of rows {a}\u2013{b - 1}); the shaded band is the inclusion ROI's columns. "
               + ("Left: every compression step. " if has_steps else "")
               + ("Then, per domain: the reference (most compressed step) and the enhanced images "
                  "reference + k\u00b7(D \u2212 mean D). " if domains else "")
               + "After the paper's Fig. 6.")
    return name, caption


def _fig_difference(arrays, results, fig_dir):
    diff = arrays.get("difference") or {}
    domains = [d for d in _DOMAIN_ORDER if d in diff] + [d for d in diff if d not in _DOMAIN_ORDER]
    if not domains:
        return None
    rois = results.get("rois") or {}
    w, h = _panel_size(np.shape(diff[domains[0]]), 3.4)
    fig = _new_figure((w + 0.9) * len(domains), h + 0.6)
    axes = np.atleast_1d(fig.subplots(1, len(domains), squeeze=False)).ravel()
    for ax, dom in zip(axes, domains):
        d = np.asarray(diff[dom], np.float64)
        v = _finite(d)
        mean = float(v.mean()) if v.size else 0.0
        half = float(np.percentile(np.abs(v - mean), 99)) if v.size else 1.0
        half = half if half > 0 else 1e-6
        im = ax.imshow(d, cmap="RdBu_r", vmin=mean - half, vmax=mean + half, interpolation="nearest")
        _draw_rois(ax, rois, legend=(dom == domains[0]))
        ax.set_title(f"D = reference \u2212 registered ({dom})", fontsize=9)
        _style_image_axes(ax, ticks=False)
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.ax.tick_params(labelsize=7)
    name = "difference.png"
    _save(fig, fig_dir / name)
    caption = ("The compression-induced difference D = reference \u2212 registered (the step before, "
               "registered onto the most compressed step), per domain, on a diverging scale centred on "
               "the image's mean of D (what the enhancement subtracts before adding k\u00b7D): where the "
               "inclusion changed less than the background it stands out of the mean. Red: inclusion ROI; "
               "cyan: background ROI.")
    return name, caption


def _fig_rois(arrays, results, fig_dir):
    enhanced = arrays.get("enhanced") or {}
    refs = arrays.get("reference_by_domain") or {}
    domains = [d for d in _DOMAIN_ORDER if d in enhanced and d in refs] + \
              [d for d in enhanced if d in refs and d not in _DOMAIN_ORDER]
    if not domains:
        return None
    ks = _k_keys(*(enhanced[d] for d in domains))
    rois = results.get("rois") or {}
    ncols = 1 + len(ks)
    w, h = _panel_size(np.shape(refs[domains[0]]), 2.8)
    fig = _new_figure((w + 0.2) * ncols, (h + 0.6) * len(domains))
    axes = fig.subplots(len(domains), ncols, squeeze=False)
    for row, dom in enumerate(domains):
        meas = _get(results, "domains", dom, default={}) or {}
        panels = [("reference", refs[dom], meas.get("contrast_reference"), None)]
        for k in ks:
            panels.append((_k_label(k), _kget(enhanced[dom], k), _kget(meas.get("contrast"), k),
                           _kget(meas.get("improvement_factor"), k)))
        for col, (label, img, contrast, factor) in enumerate(panels):
            ax = axes[row, col]
            if img is None:
                ax.set_axis_off()
                continue
            vmin, vmax = _limits(img, 1, 99)
            ax.imshow(img, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
            _draw_rois(ax, rois)
            title = f"{dom}: {label}\nC = {_fmt(contrast, '.4g')}"
            if factor is not None:
                title += f" (\u00d7{_fmt(factor)})"
            ax.set_title(title, fontsize=8)
            _style_image_axes(ax, ticks=False)
    name = "rois.png"
    _save(fig, fig_dir / name)
    caption = ("Reference (most compressed step) and enhanced images, reference + k\u00b7(D \u2212 mean D), "
               "for each k; one row per domain. Each panel has its own grey scale (its 1st\u201399th "
               "percentiles): the enhanced images span wider ranges than the reference, so a shared scale "
               "would hide their structure; compare the contrasts C in the titles (inclusion ROI mean "
               "\u2212 background ROI mean, with the improvement factor over the reference), not the grey "
               "levels. Red: inclusion ROI; cyan: background ROI. After the paper's Figs. 7\u20138.")
    return name, caption


def _overlay(fixed, moving):
    f, m = _normalise(fixed), _normalise(moving)
    return np.dstack([f, m, f])  # reference magenta (R + B), moving green: grey where they agree


def _fig_registration(arrays, results, fig_dir):
    ref, mov, reg = arrays.get("reference"), arrays.get("moving"), arrays.get("registered")
    disp, det = arrays.get("displacement"), arrays.get("det_j")
    truth, epe = arrays.get("truth_displacement"), arrays.get("epe_map")
    if epe is None and truth is not None and disp is not None and np.shape(truth) == np.shape(disp):
        epe = np.hypot(*(np.asarray(disp, np.float64) - np.asarray(truth, np.float64)))
    panels = []
    if ref is not None and mov is not None:
        panels.append("before")
    if ref is not None and reg is not None:
        panels.append("after")
    if disp is not None and np.ndim(disp) == 3 and len(disp) == 2:
        panels.append("disp")
    if det is not None:
        panels.append("det")
    if epe is not None:
        panels.append("epe")
    if not panels:
        return None
    shape = np.shape(ref if ref is not None else det if det is not None else epe)[-2:]
    w, h = _panel_size(shape, 3.0)
    fig = _new_figure((w + 0.6) * len(panels), h + 0.7)
    axes = np.atleast_1d(fig.subplots(1, len(panels), squeeze=False)).ravel()
    pair = _headline_pair(arrays, results)
    q = _get(results, "registration", pair, default={}) or {}
    for ax, kind in zip(axes, panels):
        _style_image_axes(ax, ticks=False)
        if kind == "before":
            ax.imshow(_overlay(ref, mov), interpolation="nearest")
            ax.set_title(f"before: NCC {_fmt(q.get('ncc_before'), '.3f')}", fontsize=9)
        elif kind == "after":
            ax.imshow(_overlay(ref, reg), interpolation="nearest")
            ax.set_title(f"after: NCC {_fmt(q.get('ncc_after'), '.3f')}", fontsize=9)
        elif kind == "disp":
            d = np.asarray(disp, np.float64)
            mag = np.hypot(d[0], d[1])
            im = ax.imshow(mag, cmap="viridis", interpolation="nearest")
            step = max(1, max(mag.shape) // 14)
            rr, cc = np.mgrid[step // 2:mag.shape[0]:step, step // 2:mag.shape[1]:step]
            # pull field: the registered pixel at x came from x + d(x), so the arrow points there
            ax.quiver(cc, rr, d[1][rr, cc], -d[0][rr, cc], color="white", angles="xy",
                      scale_units="xy", scale=None, width=0.004)
            ax.set_title(f"|d| (px), max {_fmt(_finite(mag).max() if _finite(mag).size else None, '.3g')}",
                         fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8).ax.tick_params(labelsize=7)
        elif kind == "det":
            jd = np.asarray(det, np.float64)
            v = _finite(jd)
            half = float(np.percentile(np.abs(v - 1.0), 99.5)) if v.size else 0.0
            half = max(half, 1e-3)
            im = ax.imshow(jd, cmap="RdBu_r", vmin=1 - half, vmax=1 + half, interpolation="nearest")
            if v.size and v.min() <= 0:
                ax.contour(jd, levels=[0.0], colors="black", linewidths=0.8)
            folds = int((v <= 0).sum()) if v.size else 0
            ax.set_title(f"det J (min {_fmt(v.min() if v.size else None, '.3g')}, {folds} folds)",
                         fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8).ax.tick_params(labelsize=7)
        elif kind == "epe":
            e = np.asarray(epe, np.float64)
            v = _finite(e)
            im = ax.imshow(e, cmap="magma", vmin=0, vmax=_limits(e, 0, 99)[1], interpolation="nearest")
            ax.set_title(f"EPE (px): median {_fmt(np.median(v) if v.size else None, '.3f')}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.8).ax.tick_params(labelsize=7)
    name = "registration.png"
    _save(fig, fig_dir / name)
    parts = []
    if "before" in panels or "after" in panels:
        parts.append("Overlays of the reference (most compressed step, magenta) and the step before it "
                     "(green), before and after registration, each image scaled to its own 1st\u201399th "
                     "percentiles: grey where they agree, colour where they do not.")
    if "disp" in panels:
        parts.append("The displacement magnitude |d| in pixels; arrows show d (pull convention: the "
                     "registered pixel at x is the moving image at x + d(x)).")
    if "det" in panels:
        parts.append("The Jacobian determinant det J of x \u21a6 x + d(x) on a diverging scale centred "
                     "at 1: red (> 1) where a reference pixel draws on more than a pixel of the moving image, "
                     "i.e. the material looks smaller at the more compressed step; blue (< 1) where it looks "
                     "larger; \u2264 0 (outlined black) would be folding.")
    if "epe" in panels:
        parts.append("The end-point error |d \u2212 d_true| against the simulation's truth, in pixels.")
    return name, " ".join(parts)


# -- tables and text -----------------------------------------------------------------------------
def _headline_pair(arrays, results):
    """The pair the headline speaks of: the step before the most compressed one, registered onto it."""
    numbers = list(arrays.get("step_numbers") or [])
    keys = list((results.get("change_ratio") or {}).keys()) + list((results.get("registration") or {}).keys())
    if results.get("main_pair") in keys:
        return results["main_pair"]
    if len(numbers) >= 2:
        pair = f"{numbers[-2]}->{numbers[-1]}"
        if pair in keys or not keys:
            return pair
    return keys[0] if keys else None


def _table(header, rows, cls=""):
    out = [f'<table class="{_e(cls)}">' if cls else "<table>", "<thead><tr>"]
    out += [f"<th>{_e(h)}</th>" for h in header]
    out.append("</tr></thead><tbody>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in row) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _paper_range(paper):
    cr = paper.get("change_ratio")
    if isinstance(cr, (list, tuple)) and len(cr) == 2:
        return f"{_fmt(cr[0])}\u2013{_fmt(cr[1])}"
    return _fmt(cr)


def _headline_rows(arrays, results, paper):
    dom = results.get("domain") or "log"
    meas = _get(results, "domains", dom, default={}) or {}
    factors = results.get("improvement_factor") or meas.get("improvement_factor") or {}
    control = results.get("control") if isinstance(results.get("control"), dict) else None
    rows = [(f"contrast of the reference ({dom} domain)", _fmt(meas.get("contrast_reference"), ".4g"), "", "")]
    for k in _k_keys(factors, meas.get("contrast")):
        rows.append((f"contrast enhanced, {_k_label(k)}", _fmt(_kget(meas.get("contrast"), k), ".4g"), "", ""))
    for k in _k_keys(factors):
        ctrl = _kget(_get(control, "improvement_factor"), k) if control else None
        rows.append((f"improvement factor, {_k_label(k)}", _fmt(_kget(factors, k)),
                     _fmt(_kget(paper.get("improvement_factor"), k), ".1f", ""),
                     _fmt(ctrl) if control else ""))
    rows += _bound_cnr_rows(results, control)
    pair = _headline_pair(arrays, results)
    cr = _get(results, "change_ratio", pair, dom) if pair else None
    if pair:
        ctrl = _get(control, "change_ratio", pair, dom) if control else None
        rows.append((f"intensity-change ratio inclusion/background, steps {_pair_label(pair)}",
                     _fmt(cr), _paper_range(paper), _fmt(ctrl) if control else ""))
    q = _get(results, "registration", pair, default=None) if pair else None
    if isinstance(q, dict):
        status = "passed" if q.get("ok") else f"FLAGGED: {q.get('reason') or 'no reason given'}"
        rows.append((f"registration {_pair_label(pair)} ({q.get('method', '?')})", status, "", ""))
        obs = q.get("rois_observed")
        if isinstance(obs, dict) and obs:
            rows.append(("motion observed in the ROIs (inclusion / background)",
                         " / ".join(f"{_fmt(100 * obs[k], '.0f')} %" if _num(obs.get(k)) is not None else "\u2013"
                                    for k in ("inclusion", "background")), "", ""))
        if _num(q.get("epe_median")) is not None:
            rows.append(("registration end-point error vs truth, median / p95 (px)",
                         f"{_fmt(q.get('epe_median'), '.3f')} / {_fmt(q.get('epe_p95'), '.3f')}", "", ""))
    total = _get(results, "timings", "total_s")
    if _num(total) is not None:
        rows.append(("total processing time", f"{_fmt(total)} s", "", ""))
    header = ["quantity", "this run", "paper"] + (["control (soft inclusion)"] if control else [])
    rows = [r if control else r[:3] for r in rows]
    return header, rows


def _bound_cnr_rows(results, control):
    """Per domain and k: the improvement factor beside its bound (what compression alone allows
    through rigid plates, :func:`radiokit.measure.improvement_bound`), and the CNR beside the
    reference's (the enhanced image carries the noise of both exposures)."""
    rows = []
    basis = _get(results, "bound", "basis") or ""
    for dom in _DOMAIN_ORDER:
        m = _get(results, "domains", dom, default={}) or {}
        cm = _get(control, "domains", dom, default={}) if control else {}
        for k in _k_keys(m.get("improvement_factor")):
            b = _kget(m.get("bound"), k)
            rows.append((f"{dom}: improvement factor (bound), {_k_label(k)}",
                         f"{_fmt(_kget(m.get('improvement_factor'), k))} ({_fmt(b, '.3f')})",
                         "", _fmt(_kget((cm or {}).get("improvement_factor"), k)) if control else ""))
        rows.append((f"{dom}: CNR reference → " + ", ".join(_k_label(k) for k in _k_keys(m.get("cnr"))),
                     " → ".join([_fmt(m.get("cnr_reference"), ".3g")]
                                     + [_fmt(_kget(m.get("cnr"), k), ".3g") for k in _k_keys(m.get("cnr"))]),
                     "", " → ".join([_fmt((cm or {}).get("cnr_reference"), ".3g")]
                                         + [_fmt(_kget((cm or {}).get("cnr"), k), ".3g")
                                            for k in _k_keys((cm or {}).get("cnr"))]) if control else ""))
    if basis:
        rows.append(("bound basis", basis, "", ""))
    return rows


def _plain_language(arrays, results, paper):
    dom = results.get("domain") or "log"
    meas = _get(results, "domains", dom, default={}) or {}
    factors = results.get("improvement_factor") or meas.get("improvement_factor") or {}
    numbers = list(arrays.get("step_numbers") or [])
    ref_step = f"step {numbers[-1]}" if numbers else "the most compressed step"
    out = []
    c_ref = _num(meas.get("contrast_reference"))
    if c_ref is not None:
        out.append(f"In the {dom} domain the inclusion stands out of the nearby background by "
                   f"{c_ref:.4g} (inclusion ROI mean minus background ROI mean) in the most compressed "
                   f"image ({ref_step}), the reference.")
    ks = _k_keys(factors)
    if ks:
        parts = [f"{_fmt(_kget(factors, k))} at {_k_label(k)}" for k in ks]
        paper_if = paper.get("improvement_factor") or {}
        paper_parts = [f"{_fmt(_kget(paper_if, k), '.1f')} at {_k_label(k)}" for k in ks
                       if _num(_kget(paper_if, k)) is not None]
        sentence = ("Adding the compression-induced difference, k\u00b7(D \u2212 mean D), multiplies that "
                    "contrast by " + ", ".join(parts))
        if paper_parts:
            sentence += " (the paper: about " + ", ".join(paper_parts) + ")"
        out.append(sentence + ".")
        k0 = _main_k(ks)
        f0 = _num(_kget(factors, k0))
        if f0 is not None and f0 <= 1:
            out.append(f"At {_k_label(k0)} the enhancement does not raise the contrast: the difference "
                       "image carries no inclusion signal of the helpful sign here.")
        cnr_ref = _num(meas.get("cnr_reference"))
        cnr_k = _num(_kget(meas.get("cnr"), k0))
        if cnr_ref and cnr_k is not None and f0 is not None:
            g = cnr_k / cnr_ref
            s = f"The contrast-to-noise ratio changes by a factor of {g:.2f} at {_k_label(k0)}"
            if g < f0 - 0.01:
                s += (", less than the contrast, because D also carries the noise of both exposures "
                      "and the registration's residual errors")
            out.append(s + ".")
    pair = _headline_pair(arrays, results)
    cr = _num(_get(results, "change_ratio", pair, dom)) if pair else None
    if cr is not None:
        a, _, b = pair.partition("->")
        s = (f"Between steps {a} and {b}, the inclusion's intensity changed {cr:.2f} times as much as the "
             f"background's (the paper's earlier study: {_paper_range(paper)}); ")
        s += ("below 1, the inclusion changed less than the background, as a stiffer inclusion that "
              "deforms less would" if cr < 1 else
              "not below 1: no sign here that the inclusion changed less than the background")
        if cr < 1 and dom in _TRANSMISSION:
            s += (", though in the intensity domain attenuation alone can also give a ratio below 1 (the "
                  "detected intensity is exponential in the line integral)")
        s += "."
        out.append(s)
    q = _get(results, "registration", pair, default=None) if pair else None
    if isinstance(q, dict):
        if q.get("ok"):
            s = (f"The registration of step {pair.partition('->')[0]} onto step {pair.partition('->')[2]} "
                 "passed its checks (similarity improved, no folding, converged)")
            if _num(q.get("epe_median")) is not None:
                s += f"; its median end-point error against the simulation's truth is {_fmt(q['epe_median'], '.3f')} px"
            out.append(s + ".")
        else:
            out.append(f"Caution: the registration of {pair} was flagged ({q.get('reason') or 'no reason given'}); "
                       "every number derived from D depends on it.")
        obs = q.get("rois_observed")
        if isinstance(obs, dict) and obs:
            parts = [f"{_fmt(100 * v, '.0f')} % of the {k} ROI" for k, v in obs.items() if _num(v) is not None]
            unseen = [k for k, v in obs.items() if _num(v) is not None and v < 0.5]
            s = "The motion was observed (registration confidence map) in " + " and ".join(parts)
            s += (f"; in the {' and '.join(unseen)} ROI the field is mostly the regulariser's guess." if unseen
                  else ".")
            out.append(s)
    control = results.get("control")
    if isinstance(control, dict) and ks:
        k0 = _main_k(ks)
        z = stiffness_share(_kget(factors, k0), _kget(control.get("improvement_factor"), k0))
        out.append(f"A control run of the same scene with the inclusion as soft as the background "
                   f"improves the contrast by {_fmt(_kget(control.get('improvement_factor'), k0))} at "
                   f"{_k_label(k0)}: the share of the gain that needs the inclusion's stiffness is "
                   f"{_share_text(z)} (details below).")
    return " ".join(out) if out else "The results carry no measurements to summarise."


def _measurement_table(results, paper):
    header = ["domain", "image", "contrast", "CNR", "Weber", "improvement factor", "paper"]
    rows = []
    domains = results.get("domains") or {}
    for dom in [d for d in _DOMAIN_ORDER if d in domains] + [d for d in domains if d not in _DOMAIN_ORDER]:
        m = domains[dom] or {}
        rows.append((dom, "reference", _fmt(m.get("contrast_reference"), ".4g"),
                     _fmt(m.get("cnr_reference"), ".3g"), _fmt(m.get("weber_reference"), ".4g"), "1", ""))
        for k in _k_keys(m.get("contrast"), m.get("improvement_factor")):
            rows.append((dom, f"enhanced, {_k_label(k)}", _fmt(_kget(m.get("contrast"), k), ".4g"),
                         _fmt(_kget(m.get("cnr"), k), ".3g"), _fmt(_kget(m.get("weber"), k), ".4g"),
                         _fmt(_kget(m.get("improvement_factor"), k)),
                         _fmt(_kget(paper.get("improvement_factor"), k), ".1f", "")))
    return (_table(header, rows) if rows else "")


def _change_ratio_table(results, paper):
    cr = results.get("change_ratio") or {}
    if not cr:
        return ""
    domains = sorted({d for v in cr.values() if isinstance(v, dict) for d in v},
                     key=lambda d: (_DOMAIN_ORDER.index(d) if d in _DOMAIN_ORDER else 9, d))
    header = ["steps (moving\u2192reference)"] + [f"{d} domain" for d in domains] + ["paper (earlier study)"]
    rows = []
    for pair, v in cr.items():
        rows.append([_pair_label(pair)] + [_fmt(_get(v, d)) for d in domains]
                    + [_paper_range(paper)])
    return _table(header, rows)


def _registration_table(results):
    reg = results.get("registration") or {}
    if not reg:
        return ""
    has_epe = any(_num(_get(q, "epe_median")) is not None for q in reg.values())
    header = ["pair", "method", "ok", "RC before\u2192after", "NCC before\u2192after", "folds", "min det J",
              "iterations", "time (s)"] + (["EPE median / p95 (px)"] if has_epe else []) + ["reason"]
    rows = []
    for pair, q in reg.items():
        q = q if isinstance(q, dict) else {}
        ok = q.get("ok")
        row = [_pair_label(pair), q.get("method", "\u2014"),
               "yes" if ok else ("NO" if ok is not None else "\u2014"),
               f"{_fmt(q.get('rc_before'), '.5g')} \u2192 {_fmt(q.get('rc_after'), '.5g')}",
               f"{_fmt(q.get('ncc_before'), '.4f')} \u2192 {_fmt(q.get('ncc_after'), '.4f')}",
               _fmt(q.get("folds"), ".0f"), _fmt(q.get("min_det_j"), ".3g"), _fmt(q.get("iterations"), ".0f"),
               _fmt(q.get("seconds"))]
        if has_epe:
            row.append(f"{_fmt(q.get('epe_median'), '.3f')} / {_fmt(q.get('epe_p95'), '.3f')}")
        row.append(q.get("reason") or "")
        rows.append(row)
    return _table(header, rows)


def _control_section(results):
    control = results.get("control")
    if not isinstance(control, dict):
        return ""
    stiff_dom = results.get("domains") or {}
    ctrl_dom = control.get("domains") or {}
    domains = [d for d in _DOMAIN_ORDER if d in stiff_dom or d in ctrl_dom]
    headline = results.get("domain") or "log"
    rows, sentences = [], []
    for dom in domains:
        s_if = _get(stiff_dom, dom, "improvement_factor") or \
            (results.get("improvement_factor") if dom == headline else None) or {}
        c_if = _get(ctrl_dom, dom, "improvement_factor") or \
            (control.get("improvement_factor") if dom == headline else None) or {}
        rows.append((dom, "contrast of the reference", _fmt(_get(stiff_dom, dom, "contrast_reference"), ".4g"),
                     _fmt(_get(ctrl_dom, dom, "contrast_reference"), ".4g"), ""))
        ks = _k_keys(s_if, c_if)
        for k in ks:
            z = stiffness_share(_kget(s_if, k), _kget(c_if, k))
            rows.append((dom, f"improvement factor, {_k_label(k)}", _fmt(_kget(s_if, k)),
                         _fmt(_kget(c_if, k)), _share_text(z)))
        if ks:
            k0 = _main_k(ks)
            sentences.append(_control_sentence(dom, k0, _kget(s_if, k0), _kget(c_if, k0)))
    for pair, v in (results.get("change_ratio") or {}).items():
        for dom in domains:
            rows.append((dom, f"intensity-change ratio, steps {_pair_label(pair)}",
                         _fmt(_get(v, dom)), _fmt(_get(control, "change_ratio", pair, dom)), ""))
    header = ["domain", "quantity", "stiff inclusion", "control (inclusion as soft as the background)",
              "share needing stiffness"]
    return ("<section id=\"control\"><h2>Stiff inclusion vs control (inclusion as soft as the background)</h2>"
            "<p>The control is a run of the same simulated scene whose inclusion has the background's "
            "stiffness but keeps its attenuation: whatever contrast compression induces there comes from "
            "attenuation alone. The share of the gain that needs stiffness is Z = (IF<sub>stiff</sub> "
            "\u2212 IF<sub>control</sub>) / (IF<sub>stiff</sub> \u2212 1), \u201cnot measurable\u201d when "
            f"IF<sub>stiff</sub> is within {MIN_EFFECT:g} of 1.</p>"
            + _table(header, rows)
            + "".join(f'<p class="control-sentence">{_e(s)}</p>' for s in sentences)
            + "</section>")


def _timings_table(timings):
    if not timings:
        return ""
    keys = [k for k in _TIMING_LABELS if k in timings] + [k for k in timings if k not in _TIMING_LABELS]
    rows = [(_TIMING_LABELS.get(k, k), f"{_fmt(timings[k])} s") for k in keys]
    return _table(["stage", "wall time"], rows, cls="narrow")


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;max-width:1180px;margin:1.5em auto;
padding:0 1em;color:#1d1d1f;line-height:1.45}
h1{font-size:1.55em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}th,td{border:1px solid #ccc;padding:.25em .6em;
text-align:left;vertical-align:top}th{background:#f2f2f4}td:not(:first-child){font-variant-numeric:tabular-nums}
figure{margin:1.2em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.88em;color:#444;max-width:60em}.meta td:first-child{font-weight:600}
.summary{background:#f7f9fc;border-left:4px solid #4a78c2;padding:.6em 1em}
.control-sentence{background:#fbf7ef;border-left:4px solid #c2904a;padding:.5em 1em}
.narrow td:last-child{text-align:right}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto;font-size:.85em}
"""


def _meta_rows(results):
    rows = [("source file", results.get("source") or "\u2014")]
    scene = results.get("scene")
    if scene:
        scene = str(scene)
        long = "\n" in scene.strip() or len(scene) > 120
        rows.append(("scene", f"{len(scene.splitlines())} lines of configuration, shown below" if long else scene))
    px = _num(results.get("pixel_mm"))
    if px:
        rows.append(("pixel size", f"{px:g} mm"))
    rows.append(("headline domain", results.get("domain") or "log"))
    rois = results.get("rois") or {}
    crop = _rect(rois, "crop")
    if crop:
        rows.append(("crop (full-frame px, rows \u00d7 cols, half-open)",
                     f"[{crop[0]}, {crop[1]}) \u00d7 [{crop[2]}, {crop[3]})"))
    for name in ("inclusion", "background"):
        r = _rect(rois, name)
        if r:
            text = f"[{r[0]}, {r[1]}) \u00d7 [{r[2]}, {r[3]}) px"
            if px:
                text += f" ({(r[1] - r[0]) * px:.3g} \u00d7 {(r[3] - r[2]) * px:.3g} mm)"
            rows.append((f"{name} ROI (cropped image)", text))
    return rows


def _scene_details(scene):
    """A long scene (the simulation's TOML) folded away: <details> needs no script."""
    if not scene or ("\n" not in str(scene).strip() and len(str(scene)) <= 120):
        return ""
    return f"<details><summary>scene configuration</summary><pre>{_e(scene)}</pre></details>"


# -- the page ------------------------------------------------------------------------------------
def write_report(out_dir, results: dict, arrays: dict) -> Path:
    """Write the processing report: ``out_dir/report.html`` and PNG figures in ``out_dir/figures/``.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing; ``report.html`` and ``figures/*.png`` in it are overwritten.
    results : dict
        The JSON-able measurements (the pipeline's ``results.json``): ``source``, ``scene``,
        ``pixel_mm``, ``domain`` (the headline domain), ``ks``, ``rois``, ``improvement_factor``,
        ``domains`` (per domain: ``contrast_reference``, ``cnr_reference``, ``weber_reference`` and
        ``contrast``/``cnr``/``weber``/``improvement_factor`` keyed by k as a string),
        ``change_ratio`` (per step pair ``"a->b"`` and domain), ``registration`` (per pair: quality),
        optional ``control`` (the same structure for a run whose inclusion is as soft as the
        background), ``timings`` (seconds per stage), ``paper`` (defaults to :data:`PAPER`).
        Every key is optional; missing parts are left out of the page.
    arrays : dict
        float32 images, all of the same cropped shape ``(rows, cols)``: ``steps`` (n, rows, cols)
        line integrals, least compressed first, with ``step_numbers`` and ``ratios``;
        ``reference``, ``registered``, ``moving`` (log domain); ``displacement`` (2, rows, cols),
        pixels, pull convention; ``det_j``; ``enhanced`` ({domain: {k: image}});
        ``reference_by_domain`` and ``difference`` ({domain: image}); optional
        ``truth_displacement`` and ``epe_map``.

    Returns
    -------
    Path
        The HTML file. Its figures are linked relatively (``figures/name.png``).

    Notes
    -----
    The page is self-contained: inline CSS, no scripts, no network references. All text taken from
    ``results`` (paths, scene names, registration reasons) is HTML-escaped.
    """
    t0 = time.perf_counter()
    if hasattr(results, "to_json"):  # the pipeline's records (radiokit.results.Results, pipeline.Images)
        arrays = arrays.as_dict(results) if hasattr(arrays, "as_dict") else arrays
        results = results.to_json()
    out_dir = Path(out_dir)
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    results = results if isinstance(results, dict) else {}
    arrays = arrays if isinstance(arrays, dict) else {}
    paper = {**PAPER, **(results.get("paper") or {})}

    figures = []
    for make in (_fig_projections, _fig_profiles, _fig_difference, _fig_rois, _fig_registration):
        fig = make(arrays, results, fig_dir)
        if fig is not None:
            figures.append(fig)

    timings = dict(results.get("timings") or {})
    if "report_s" not in timings:
        timings["report_s"] = time.perf_counter() - t0
        own_report_time = True
    else:
        own_report_time = False

    header, rows = _headline_rows(arrays, results, paper)
    fig_html = {name: (f'<figure id="fig-{_e(name[:-4])}"><img src="figures/{_e(name)}" alt="{_e(caption[:120])}">'
                       f"<figcaption><b>Figure {i}.</b> {_e(caption)}</figcaption></figure>")
                for i, (name, caption) in enumerate(figures, 1)}
    source = results.get("source") or "unknown source"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>radiokit report \u2014 {_e(source)}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Compression-induced contrast</h1>",
        f"<p>radiokit {_e(__version__)} report for <code>{_e(source)}</code>, written "
        f"{_e(datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC'))}.</p>",
        _table(["", ""], _meta_rows(results), cls="meta"),
        _scene_details(results.get("scene")),
        "<h2>Headline</h2>",
        _table(header, rows),
        f'<p class="summary"><b>What the numbers show.</b> {_e(_plain_language(arrays, results, paper))}</p>',
        "<h2>Images</h2>",
    ]
    parts += [fig_html[n] for n in ("projections.png", "profiles.png", "difference.png", "rois.png")
              if n in fig_html]
    parts.append("<h2>Contrast measurements</h2>")
    parts.append("<p>Contrast: mean of the inclusion ROI \u2212 mean of the background ROI; CNR: contrast over "
                 "the background ROI's standard deviation; Weber: contrast over the background mean; "
                 "improvement factor: enhanced contrast over the reference's. The paper's improvement "
                 "factors (about 1.4 and 2) and intensity-change ratios (0.66\u20130.84, the authors' "
                 "earlier study) are beside them.</p>")
    parts.append(_measurement_table(results, paper) or "<p>No contrast measurements.</p>")
    cr_table = _change_ratio_table(results, paper)
    if cr_table:
        parts.append("<p>Intensity-change ratio: the change of the inclusion ROI's mean between two steps "
                     "over the change of the background ROI's (the moving step registered onto the "
                     "other); below 1 the inclusion changed less.</p>" + cr_table)
    parts.append(_control_section(results))
    parts.append("<h2>Registration quality</h2>")
    if "registration.png" in fig_html:
        parts.append(fig_html["registration.png"])
    parts.append(_registration_table(results) or "<p>No registration quality recorded.</p>")
    parts.append("<p>RC: residual complexity of the difference image (lower is better); NCC: normalised "
                 "cross-correlation (higher is better); folds: pixels with det J \u2264 0.</p>")
    parts.append("<h2>Timings</h2>")
    parts.append(_timings_table(timings) or "<p>No timings recorded.</p>")
    if own_report_time:
        parts.append("<p>The report's time is its own figure drawing, measured while writing this page.</p>")
    parts.append("</body></html>")
    path = out_dir / "report.html"
    path.write_text("\n".join(p for p in parts if p), encoding="utf-8")
    return path
