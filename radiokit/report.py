"""The processing report: one self-contained HTML page with PNG figures, after the paper's Figs. 4-8.

``write_report(out_dir, results, images)`` (:class:`radiokit.results.Results` and
:class:`radiokit.results.Images`, as :func:`radiokit.pipeline.process` makes them) writes
``out_dir/report.html`` and its figures in ``out_dir/figures/`` (linked relatively, so the folder
can be moved or zipped) and returns the HTML path. The page has inline CSS, no JavaScript and no network references; every piece of text
that comes from the data is escaped.

``write_report`` is two steps, public for a caller that must do something between them:
``draw_figures(out_dir, results, images)`` draws the figures and returns their HTML, and
``write_page(out_dir, results, figures)`` writes ``report.html`` around them.
:func:`radiokit.pipeline.process` times the first as the report's time and takes the run's total
before writing any file, so that the page, ``results.json`` and ``results.h5`` show one total.

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

import dataclasses
import html
import io
import math
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from radiokit._version import __version__
from radiokit.measure import PAPER  # used where results.paper does not give them
from radiokit.results import Images, Results, k_label, sig3, value_pm

__all__ = ["write_report", "draw_figures", "write_page", "stiffness_share", "PAPER", "MAX_PNG_BYTES"]

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


# -- formatting ----------------------------------------------------------------------------------
def _num(x):
    """``float(x)`` when it is a finite number, else None (NaN and inf print as a dash)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _fmt(x, spec=".2f", missing="\u2014"):
    v = _num(x)
    return missing if v is None else format(v, spec)


def _sig(x, missing="\u2014"):
    """A CNR's three significant digits (:func:`radiokit.results.sig3`), or ``missing``."""
    v = _num(x)
    return missing if v is None else sig3(v)


def _if_text(m):
    """An improvement factor (:class:`radiokit.results.KMeasure`) with its standard error, to its
    place (:func:`radiokit.results.value_pm`)."""
    v = _num(m.improvement_factor)
    return _fmt(None) if v is None else value_pm(v, m.improvement_factor_se)


def _cr_text(pair, dom):
    """A pair's change ratio in ``dom`` with its standard error, or "not measurable" (its
    background did not measurably change: the reason is in the sentences and results.json)."""
    if (pair.change_ratio_reason or {}).get(dom):
        return "not measurable"
    v = _num(pair.change_ratio.get(dom))
    return _fmt(None) if v is None else value_pm(v, (pair.change_ratio_se or {}).get(dom))


def _main_k(ks):
    """The k the text talks about: 1 (the paper's direct addition) when present, else the first."""
    return next((k for k in ks if k == 1.0), ks[0])


def _k_label(k):
    return f"k={k_label(k)}"


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


def _normalise(a, lo=1.0, hi=99.0, step=1):
    """``a`` scaled to its percentiles ``lo``-``hi`` of all pixels, at every ``step``-th pixel."""
    vmin, vmax = _limits(a, lo, hi)
    out = (np.asarray(a, np.float64)[::step, ::step] - vmin) / (vmax - vmin)
    return np.clip(np.nan_to_num(out, nan=0.0), 0.0, 1.0)


def _ratio_label(ratio):
    r = _num(ratio)
    if r is None:
        return ""
    return f"{100 * r:.0f} % compression" if 0 <= r <= 1 else f"ratio {r:g}"


def _domain_unit(domain):
    """The pixel's meaning in ``domain`` (:class:`radiokit.enhance.Domain`)."""
    return {"log": "\u2212ln(I/I\u2080)", "negative": "\u2212I/I\u2080", "linear": "I/I\u2080"}.get(
        str(domain), str(domain)
    )


def _in_order(domains):
    """The domains of a mapping, log first."""
    return sorted(domains, key=lambda d: _DOMAIN_ORDER.index(str(d)) if str(d) in _DOMAIN_ORDER else 9)


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


def _if_value(v, se=None):
    """An improvement factor to its standard error's place (:func:`radiokit.results.value_pm`),
    the error printed where known."""
    return _fmt(None) if _num(v) is None else value_pm(v, se)


def _factor_and_se(stiff, control) -> tuple:
    """:func:`_control_sentence`'s numbers from two :class:`radiokit.results.KMeasure`."""
    return (
        stiff.improvement_factor,
        control.improvement_factor,
        stiff.improvement_factor_se,
        control.improvement_factor_se,
    )


def _control_sentence(domain, k, if_stiff, if_control, se_stiff=None, se_control=None):
    z = stiffness_share(if_stiff, if_control)
    head = (
        f"In the {domain} domain, the control's improvement at {_k_label(k)} is "
        f"{_if_value(if_control, se_control)} vs {_if_value(if_stiff, se_stiff)}: "
    )
    if z is None:
        body = (
            "the share of the compression-induced contrast that needs the inclusion's stiffness is "
            f"not measurable (the stiff inclusion's improvement is within {MIN_EFFECT:g} of 1, "
            "or missing)."
        )
    elif z > 1:
        body = (
            f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness; "
            "attenuation alone (the thinning of a denser inclusion) would lower the contrast, "
            "since the control's improvement is below 1."
        )
    elif z < 0:
        body = (
            f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness: "
            "the control gains more than the stiff inclusion, so none of the gain can be credited "
            "to elasticity."
        )
    else:
        body = (
            f"{_share_text(z)} of the compression-induced contrast needs the inclusion's stiffness; "
            "the rest comes from attenuation alone (the thinning of a denser inclusion)."
        )
    if domain in _TRANSMISSION:
        body += (
            " In the intensity domain the detected intensity is exponential in the line integral "
            "(I = I\u2080\u00b7exp(\u2212\u222b\u03bc dl)), so the same thinning changes the intensity "
            "behind the inclusion and behind the background by different amounts: part of the "
            "effect needs no stiffness at all."
        )
    return head + body


# -- figures -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Cell:
    """The room around one panel, in inches: its title above, tick labels left and below, and a
    colour bar with its ticks and label to the right (``cbar``: 0 for none, or one per column)."""

    left: float = 0.08
    right: float = 0.08
    top: float = 0.32
    bottom: float = 0.08
    cbar: float | tuple = 0.0


def _grid_figure(nrows, ncols, panel, cell: _Cell, extra_right=0.0):
    """A figure of ``nrows x ncols`` panels of ``panel`` = (width, height) inches each, every margin
    fixed: ``(fig, axes, caxes)``, ``caxes`` the colour bars' axes (``None`` without).

    Why not constrained layout: it measures every text by drawing the figure twice more before the
    real draw, half of the report's drawing time, to find margins known here in advance (the
    titles' and tick labels' font sizes are fixed). Panels narrow, their text does not, when the
    figure would be wider than the page (``_MAX_WIDTH_IN``).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pw, ph = panel
    cbars = cell.cbar if isinstance(cell.cbar, tuple) else (cell.cbar,) * ncols
    fixed_w = ncols * (cell.left + cell.right) + sum(cbars) + extra_right
    scale = min(1.0, max(_MAX_WIDTH_IN - fixed_w, 1.0) / (ncols * pw))
    pw, ph = pw * scale, ph * scale
    ch = cell.top + ph + cell.bottom
    x0 = np.concatenate([[0.0], np.cumsum([cell.left + pw + cb + cell.right for cb in cbars])])
    fw, fh = x0[-1] + extra_right, nrows * ch
    fig = Figure(figsize=(fw, fh), dpi=_DPI)
    FigureCanvasAgg(fig)
    axes = np.empty((nrows, ncols), dtype=object)
    caxes = np.empty((nrows, ncols), dtype=object) if any(cbars) else None
    for r in range(nrows):
        y = fh - r * ch - cell.top - ph
        for c in range(ncols):
            x = x0[c] + cell.left
            axes[r, c] = fig.add_axes((x / fw, y / fh, pw / fw, ph / fh))
            if cbars[c]:  # as colorbar(shrink=0.85) drew it: 85 % of the panel, 1/20 as wide
                bh = 0.85 * ph
                box = (x + pw + 0.1, y + (ph - bh) / 2, bh / 20, bh)
                caxes[r, c] = fig.add_axes((box[0] / fw, box[1] / fh, box[2] / fw, box[3] / fh))
    return fig, axes, caxes


def _png_bytes(fig, dpi, max_bytes):
    from PIL import Image

    buf = io.BytesIO()
    # zlib level 3, not PIL's 6: half the encoding time (a third of a noisy report's figures), 0-15 %
    # more bytes, and noisy images (the large ones) compress no better at 6 (session 45)
    fig.savefig(buf, format="png", dpi=dpi, pil_kwargs={"compress_level": 3})
    data = buf.getvalue()
    if len(data) > max_bytes:
        # noisy radiographs compress badly as RGBA; 256 colours lose nothing a reader sees
        img = Image.open(io.BytesIO(data)).convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE)
        buf = io.BytesIO()
        img.save(buf, format="PNG", compress_level=6)  # optimize=True (level 9) took 2-5x as long for 1-4 % fewer bytes
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
    # no fig.clear(): it cost 0.1 s a figure to empty an object nothing refers to after this
    path.write_bytes(data)


def _imshow(ax, img, **kw):
    """``ax.imshow(img, interpolation="nearest", **kw)`` of every ``step``-th pixel, ``step`` the
    largest that keeps at least as many pixels as the panel has dots, over the whole field of view.

    Why: nearest-neighbour resampling shows one pixel of each dot anyway; a 2240-pixel image drawn
    2.5 inches wide cost 0.3 s a panel to colour-map and resample in full (session 45).
    """
    img = np.asarray(img)
    step = _stride(ax, img.shape)
    return ax.imshow(img[::step, ::step], extent=_extent(img.shape), interpolation="nearest", **kw)


def _stride(ax, shape):
    """The largest step through an image of ``shape`` that leaves ``ax`` no fewer pixels than dots."""
    fig = ax.get_figure()
    w_dots, h_dots = ax.get_position().size * fig.get_size_inches() * fig.dpi
    return max(1, int(min(shape[1] / max(w_dots, 1.0), shape[0] / max(h_dots, 1.0))))


def _extent(shape):
    """imshow's extent of an image of ``shape``: pixel centres at their indices, strided or not."""
    return (-0.5, shape[1] - 0.5, shape[0] - 0.5, -0.5)


def _panel_size(shape, width=3.0):
    rows, cols = shape
    aspect = rows / cols if cols else 1.0
    return width, float(np.clip(width * aspect, 1.2, 2.5 * width))


def _draw_rois(ax, rois, legend=False):
    from matplotlib.patches import Rectangle

    for name, colour in (("inclusion", _INCLUSION_COLOUR), ("background", _BACKGROUND_COLOUR)):
        r0, r1, c0, c1 = getattr(rois, name)
        ax.add_patch(
            Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0, r1 - r0, fill=False, edgecolor=colour, linewidth=1.2, label=name)
        )
    if legend and ax.patches:
        ax.legend(loc="lower right", fontsize=7, framealpha=0.7)


def _style_image_axes(ax, ticks=True):
    if ticks:
        ax.tick_params(labelsize=7)
    else:  # the ROI coordinates are in the tables; tick labels cost half the drawing time
        ax.set_xticks([])
        ax.set_yticks([])


def _fig_projections(images, results, fig_dir):
    steps = images.steps
    n = len(steps)
    ncols = min(n, 4)
    nrows = -(-n // ncols)
    # tick labels left and below each panel; the shared colour bar's ticks (10 pt) and label right
    fig, axes, _ = _grid_figure(nrows, ncols, _panel_size(steps.shape[1:]), _Cell(0.42, 0.1, 0.3, 0.28), 0.95)
    axes = axes.ravel()
    vmin, vmax = _limits(steps, 0.5, 99.5)
    im = None
    for i, ax in enumerate(axes):
        if i >= n:
            ax.set_axis_off()
            continue
        im = _imshow(ax, steps[i], cmap="gray", vmin=vmin, vmax=vmax)
        _draw_rois(ax, results.rois, legend=(i == 0))
        label = _ratio_label(results.ratios[i])
        ax.set_title(f"step {results.steps[i]}" + (f" \u2014 {label}" if label else ""), fontsize=9)
        _style_image_axes(ax)
    cb = fig.colorbar(im, cax=_shared_cax(fig, axes[:n]))
    cb.set_label("line integral \u2212ln(I/I\u2080)", fontsize=8)
    name = "projections.png"
    _save(fig, fig_dir / name)
    caption = (
        "Projections of every compression step (line integrals \u2212ln(I/I\u2080), least compressed "
        "first), on one shared grey scale (0.5\u201399.5 percentiles of all steps), so brightness "
        "compares across steps; brighter is more attenuation. Red: inclusion ROI; cyan: background "
        "ROI (where contrast is measured). Axes in pixels of the cropped image"
        f" ({results.pixel_size_mm:g} mm per pixel). After the paper's Figs. 4\u20135."
    )
    return name, caption


def _shared_cax(fig, axes):
    """A colour bar's axes right of ``axes``, 85 % of their height, as colorbar(shrink=0.85) drew it."""
    x1 = max(ax.get_position().x1 for ax in axes)
    y0, y1 = min(ax.get_position().y0 for ax in axes), max(ax.get_position().y1 for ax in axes)
    fw, fh = fig.get_size_inches()
    h = 0.85 * (y1 - y0)
    return fig.add_axes((x1 + 0.15 / fw, y0 + 0.075 * (y1 - y0), h * fh / 20 / fw, h))


def _profile_rows(shape, row):
    centre = int(np.clip(row, 0, shape[0] - 1))
    return centre, max(0, centre - _PROFILE_HALF_ROWS), min(shape[0], centre + _PROFILE_HALF_ROWS + 1)


def _row_mean(img, a, b):
    """Mean of rows a:b per column over the finite pixels; NaN where a column has none."""
    band = np.asarray(img, np.float64)[a:b]
    ok = np.isfinite(band)
    n = ok.sum(axis=0)
    total = np.where(ok, band, 0.0).sum(axis=0)
    return np.divide(total, n, out=np.full(band.shape[1], np.nan), where=n > 0)


def _fig_profiles(images, results, fig_dir):
    steps = images.steps
    centre, a, b = _profile_rows(steps.shape[1:], results.profiles_row)
    x = np.arange(steps.shape[2]) * results.pixel_size_mm
    domains = _in_order(images.enhanced)
    # y tick labels and unit left, x tick labels and label below, the title above
    fig, axes, _ = _grid_figure(1, 1 + len(domains), (3.45, 2.6), _Cell(0.62, 0.12, 0.3, 0.5))
    axes = axes.ravel()
    for j, img in enumerate(steps):
        rl = _ratio_label(results.ratios[j])
        axes[0].plot(x, _row_mean(img, a, b), lw=1.1, label=f"step {results.steps[j]}" + (f" ({rl})" if rl else ""))
    axes[0].set_title("every step (log domain)", fontsize=9)
    axes[0].set_ylabel("\u2212ln(I/I\u2080)", fontsize=8)
    for ax, dom in zip(axes[1:], domains):
        e = images.enhanced[dom]
        ax.plot(x, _row_mean(e.reference, a, b), color="black", lw=1.4, label="reference")
        for k, img in e.images:
            ax.plot(x, _row_mean(img, a, b), lw=1.1, label=f"enhanced, {_k_label(k)}")
        ax.set_title(f"reference vs enhanced ({dom} domain)", fontsize=9)
        ax.set_ylabel(_domain_unit(dom), fontsize=8)
    c0, c1 = results.rois.inclusion[2:]
    for ax in axes:
        ax.axvspan(
            (c0 - 0.5) * results.pixel_size_mm,
            (c1 - 0.5) * results.pixel_size_mm,
            color=_INCLUSION_COLOUR,
            alpha=0.12,
            label="inclusion ROI columns",
        )
        ax.set_xlabel("column (mm, cropped image)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    name = "profiles.png"
    _save(fig, fig_dir / name)
    caption = (
        f"Profiles along the row through the inclusion's centre (row {centre} of the cropped image, "
        f"mean of rows {a}\u2013{b - 1}); the shaded band is the inclusion ROI's columns. Left: every "
        "compression step. Then, per domain: the reference (most compressed step) and the enhanced "
        "images reference + k\u00b7(D \u2212 mean D). After the paper's Fig. 6."
    )
    return name, caption


#: what a difference image's values are, per domain (review s42rep: its colour bars named none)
_D_UNITS = {
    "log": "line integral \u2212ln(I/I\u2080)",
    "linear": "transmission I/I\u2080",
    "negative": "\u2212I/I\u2080",
}


def _fig_difference(images, results, fig_dir):
    domains = _in_order(images.enhanced)
    # no tick labels; a colour bar with ticks (7 pt) and its label right of each panel
    fig, axes, caxes = _grid_figure(1, len(domains), _panel_size(images.reference.shape, 3.0), _Cell(cbar=1.05))
    for ax, cax, dom in zip(axes.ravel(), caxes.ravel(), domains):
        d = np.asarray(images.enhanced[dom].difference, np.float64)
        v = _finite(d)
        mean = float(v.mean()) if v.size else 0.0
        half = float(np.percentile(np.abs(v - mean), 99)) if v.size else 1.0
        half = half if half > 0 else 1e-6
        im = _imshow(ax, d, cmap="RdBu_r", vmin=mean - half, vmax=mean + half)
        _draw_rois(ax, results.rois, legend=(dom == domains[0]))
        ax.set_title(f"D = reference \u2212 registered ({dom})", fontsize=9)
        _style_image_axes(ax, ticks=False)
        cb = fig.colorbar(im, cax=cax)
        cb.set_label(f"D, {_D_UNITS.get(getattr(dom, 'value', dom), 'image units')}", fontsize=8)
        cb.ax.tick_params(labelsize=7)
        cb.ax.yaxis.get_offset_text().set_fontsize(7)  # "1e-5-1.61e-1" of a near-constant D, over the panel at 10 pt
    name = "difference.png"
    _save(fig, fig_dir / name)
    caption = (
        "The compression-induced difference D = reference \u2212 registered (the step before, "
        "registered onto the most compressed step), per domain, on a diverging scale centred on "
        "the image's mean of D (what the enhancement subtracts before adding k\u00b7D): where the "
        "inclusion changed less than the background it stands out of the mean. Red: inclusion ROI; "
        "cyan: background ROI."
    )
    return name, caption


def _fig_rois(images, results, fig_dir):
    domains = _in_order(images.enhanced)
    ncols = 1 + len(results.ks)
    # two-line titles (8 pt) above, nothing else around the panels
    fig, axes, _ = _grid_figure(
        len(domains), ncols, _panel_size(images.reference.shape, 2.8), _Cell(0.04, 0.04, 0.42, 0.04)
    )
    for row, dom in enumerate(domains):
        e, meas = images.enhanced[dom], results.domains[dom]
        panels = [("reference", e.reference, meas.contrast_reference, None)]
        panels += [(_k_label(k), img, meas.at(k).contrast, meas.at(k).improvement_factor) for k, img in e.images]
        for ax, (label, img, contrast, factor) in zip(axes[row], panels):
            vmin, vmax = _limits(img, 1, 99)
            _imshow(ax, img, cmap="gray", vmin=vmin, vmax=vmax)
            _draw_rois(ax, results.rois)
            title = f"{dom}: {label}\nC = {_fmt(contrast, '.4g')}"
            if factor is not None:
                title += f" (\u00d7{_fmt(factor, '.3f')})"
            ax.set_title(title, fontsize=8)
            _style_image_axes(ax, ticks=False)
    name = "rois.png"
    _save(fig, fig_dir / name)
    caption = (
        "Reference (most compressed step) and enhanced images, reference + k\u00b7(D \u2212 mean D), "
        "for each k; one row per domain. Each panel has its own grey scale (its 1st\u201399th "
        "percentiles): the enhanced images span wider ranges than the reference, so a shared scale "
        "would hide their structure; compare the contrasts C in the titles (inclusion ROI mean "
        "\u2212 background ROI mean, with the improvement factor over the reference), not the grey "
        "levels. Red: inclusion ROI; cyan: background ROI. After the paper's Figs. 7\u20138."
    )
    return name, caption


def _overlay(fixed, moving, step=1):
    f, m = _normalise(fixed, step=step), _normalise(moving, step=step)
    return np.dstack([f, m, f])  # reference magenta (R + B), moving green: grey where they agree


def _panel_displacement(fig, ax, cax, disp):
    d = np.asarray(disp, np.float64)
    mag = np.hypot(d[0], d[1])
    im = _imshow(ax, mag, cmap="viridis")
    step = max(1, max(mag.shape) // 14)
    rr, cc = np.mgrid[step // 2 : mag.shape[0] : step, step // 2 : mag.shape[1] : step]
    # pull field: the registered pixel at x came from x + d(x), so the arrow points there; no
    # arrows where none has a length (matplotlib's autoscale divided by zero, in warnings on stderr)
    u, v = d[1][rr, cc], -d[0][rr, cc]
    if np.any(np.isfinite(u) & np.isfinite(v) & ((u != 0) | (v != 0))):
        ax.quiver(cc, rr, u, v, color="white", angles="xy", scale_units="xy", scale=None, width=0.004)
    ax.set_title(f"|d| (px), max {_fmt(_finite(mag).max() if _finite(mag).size else None, '.3g')}", fontsize=9)
    cb = fig.colorbar(im, cax=cax)
    cb.set_label("|d| (px)", fontsize=8)
    cb.ax.tick_params(labelsize=7)


def _panel_det_j(fig, ax, cax, det):
    jd = np.asarray(det, np.float64)
    v = _finite(jd)
    half = max(float(np.percentile(np.abs(v - 1.0), 99.5)) if v.size else 0.0, 1e-3)
    im = _imshow(ax, jd, cmap="RdBu_r", vmin=1 - half, vmax=1 + half)
    if v.size and v.min() <= 0:
        ax.contour(jd, levels=[0.0], colors="black", linewidths=0.8)
    folds = int((v <= 0).sum()) if v.size else 0
    ax.set_title(f"det J (min {_fmt(v.min() if v.size else None, '.3g')}, {folds} folds)", fontsize=9)
    cb = fig.colorbar(im, cax=cax)
    cb.set_label("det J", fontsize=8)
    cb.ax.tick_params(labelsize=7)


def _panel_epe(fig, ax, cax, epe):
    e = np.asarray(epe, np.float64)
    v = _finite(e)
    im = _imshow(ax, e, cmap="magma", vmin=0, vmax=_limits(e, 0, 99)[1])
    ax.set_title(f"EPE (px): median {_fmt(np.median(v) if v.size else None, '.3f')}", fontsize=9)
    cb = fig.colorbar(im, cax=cax)
    cb.set_label("EPE (px)", fontsize=8)
    cb.ax.tick_params(labelsize=7)


_REGISTRATION_CAPTIONS = {
    "overlay": "Overlays of the reference (most compressed step, magenta) and the step before it (green), "
    "before and after registration, each image scaled to its own 1st\u201399th percentiles: grey "
    "where they agree, colour where they do not.",
    "disp": "The displacement magnitude |d| in pixels; arrows show d (pull convention: the registered pixel "
    "at x is the moving image at x + d(x)).",
    "det": "The Jacobian determinant det J of x \u21a6 x + d(x) on a diverging scale centred at 1: red (> 1) "
    "where a reference pixel draws on more than a pixel of the moving image, i.e. the material looks "
    "smaller at the more compressed step; blue (< 1) where it looks larger; \u2264 0 (outlined black) "
    "would be folding.",
    "epe": "The end-point error |d \u2212 d_true| against the simulation's truth, in pixels.",
}


def _fig_registration(images, results, fig_dir):
    q = results.pair(results.main_pair).quality
    panels = ["before", "after", "disp", "det"] + (["epe"] if images.epe_map is not None else [])
    # the overlays take no colour bar, the maps one each with its ticks and label
    cell = _Cell(cbar=(0.0, 0.0) + (0.85,) * (len(panels) - 2))
    fig, axes, caxes = _grid_figure(1, len(panels), _panel_size(images.reference.shape, 2.5), cell)
    axes, caxes = axes.ravel(), caxes.ravel()
    for ax in axes:
        _style_image_axes(ax, ticks=False)
    for ax, (when, img) in zip(axes, (("before", images.moving), ("after", images.registered))):
        step = _stride(ax, images.reference.shape)  # the RGB of every pixel was 3 float64s a pixel
        ax.imshow(_overlay(images.reference, img, step), extent=_extent(img.shape), interpolation="nearest")
        ax.set_title(f"{when}: NCC {_fmt(q.get(f'ncc_{when}'), '.3f')}", fontsize=9)
    _panel_displacement(fig, axes[2], caxes[2], images.displacement)
    _panel_det_j(fig, axes[3], caxes[3], images.det_j)
    if images.epe_map is not None:
        _panel_epe(fig, axes[4], caxes[4], images.epe_map)
    name = "registration.png"
    _save(fig, fig_dir / name)
    captions = ["overlay", "disp", "det"] + (["epe"] if images.epe_map is not None else [])
    return name, " ".join(_REGISTRATION_CAPTIONS[c] for c in captions)


# -- tables and text -----------------------------------------------------------------------------
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


def _paper_if(paper, k):
    return (paper.get("improvement_factor") or {}).get(float(k))


def _headline_rows(results, paper):
    dom, control = results.domain, results.control
    meas, main = results.domains[dom], results.pair(results.main_pair)
    rows = [(f"contrast of the reference ({dom} domain)", _fmt(meas.contrast_reference, ".4g"), "", "")]
    rows += [(f"contrast enhanced, {_k_label(m.k)}", _fmt(m.contrast, ".4g"), "", "") for m in meas.per_k]
    for m in meas.per_k:
        ctrl = _if_text(control.domains[dom].at(m.k)) if control else ""
        rows.append(
            (
                f"improvement factor, {_k_label(m.k)}",
                _if_text(m),
                _fmt(_paper_if(paper, m.k), ".1f", ""),
                ctrl,
            )
        )
    rows += _bound_cnr_rows(results)
    ctrl = _cr_text(control.pair(main.name), dom) if control and _has_pair(control, main.name) else ""
    rows.append(
        (
            f"intensity-change ratio inclusion/background, steps {_pair_label(main.name)}",
            _cr_text(main, dom),
            _paper_range(paper),
            ctrl,
        )
    )
    status = "passed" if main.ok else f"FLAGGED: {main.reason or 'no reason given'}"
    rows.append((f"registration {_pair_label(main.name)} ({main.method})", status, "", ""))
    if main.rois_observed:
        unseen = _rois_unobserved(main)
        rows.append(
            (
                "motion observed in the ROIs (inclusion / background)",
                " / ".join(f"{_fmt(100 * main.rois_observed[k], '.0f')} %" for k in ("inclusion", "background"))
                + (f": {' and '.join(unseen)} mostly unobserved, flagged" if unseen else ": both observed"),
                "",
                "",
            )
        )
    if main.epe:
        rows.append(
            (
                "registration end-point error vs truth, median / p95 (px)",
                f"{_fmt(main.epe['epe_median'], '.3f')} / {_fmt(main.epe['epe_p95'], '.3f')}",
                "",
                "",
            )
        )
    if _num(results.timings.get("total_s")) is not None:
        rows.append(("total processing time", f"{_fmt(results.timings['total_s'])} s", "", ""))
    header = ["quantity", "this run", "paper"] + (["control (soft inclusion)"] if control else [])
    return header, [r if control else r[:3] for r in rows]


def _has_pair(results, name):
    return any(p.name == name for p in results.pairs)


def _bound_cnr_rows(results):
    """Per domain and k: the improvement factor beside its bound (what compression alone allows
    through rigid plates, :func:`radiokit.measure.improvement_bound`), and the CNR beside the
    reference's (the enhanced image carries the noise of both exposures)."""
    rows, control = [], results.control
    for dom in _in_order(results.domains):
        m = results.domains[dom]
        cm = control.domains.get(dom) if control else None
        for x in m.per_k:
            rows.append(
                (
                    f"{dom}: improvement factor (bound), {_k_label(x.k)}",
                    f"{_if_text(x)} ({_fmt(x.bound, '.3f')})",
                    "",
                    _if_text(cm.at(x.k)) if cm else "",
                )
            )
        rows.append(
            (
                f"{dom}: CNR reference \u2192 " + ", ".join(_k_label(x.k) for x in m.per_k),
                " \u2192 ".join(_sig(v) for v in [m.cnr_reference, *(x.cnr for x in m.per_k)]),
                "",
                " \u2192 ".join(_sig(v) for v in [cm.cnr_reference, *(x.cnr for x in cm.per_k)]) if cm else "",
            )
        )
    if results.bound.basis:
        rows.append(("bound basis", results.bound.basis, "", ""))
    return rows


def _contrast_sentences(results, paper):
    """What the reference's contrast is and what the enhancement does to it and to the CNR."""
    dom = results.domain
    meas = results.domains[dom]
    out = [
        f"In the {dom} domain the inclusion stands out of the nearby background by "
        f"{_fmt(meas.contrast_reference, '.4g')} (inclusion ROI mean minus background ROI mean) in the most "
        f"compressed image (step {results.steps[-1]}), the reference."
    ]
    parts = [f"{_if_text(m)} at {_k_label(m.k)}" for m in meas.per_k]
    paper_parts = [
        f"{_fmt(_paper_if(paper, m.k), '.1f')} at {_k_label(m.k)}"
        for m in meas.per_k
        if _num(_paper_if(paper, m.k)) is not None
    ]
    sentence = (
        "Adding the compression-induced difference, k\u00b7(D \u2212 mean D), multiplies that contrast by "
        + ", ".join(parts)
    )
    if paper_parts:
        sentence += " (the paper: about " + ", ".join(paper_parts) + ")"
    out.append(sentence + ".")
    m0 = meas.at(_main_k(results.ks))
    f0 = _num(m0.improvement_factor)
    if f0 is not None and f0 <= 1:
        out.append(
            f"At {_k_label(m0.k)} the enhancement does not raise the contrast: the difference "
            "image carries no inclusion signal of the helpful sign here."
        )
    if _num(meas.cnr_reference) and _num(m0.cnr) is not None and f0 is not None:
        g = m0.cnr / meas.cnr_reference
        s = f"The contrast-to-noise ratio changes by a factor of {g:.2f} at {_k_label(m0.k)}"
        if g < f0 - 0.01:
            s += (
                ", less than the contrast, because D also carries the noise of both exposures "
                "and the registration's residual errors"
            )
        out.append(s + ".")
    return out


def _change_ratio_sentence(main, dom, paper) -> str | None:
    """What the main pair's change ratio says: not measurable (why), noise (within two standard
    errors of 1), or below or above 1."""
    cr = _num(main.change_ratio.get(dom))
    se = _num((main.change_ratio_se or {}).get(dom))
    reason = (main.change_ratio_reason or {}).get(dom)
    if reason:
        return (
            f"Between steps {main.moving} and {main.reference} the intensity-change ratio is {reason}: with no "
            "measurable change of the background there is nothing to compare the inclusion's change with "
            "(the improvement factor above does not need it)."
        )
    if cr is None:
        return None
    s = (
        f"Between steps {main.moving} and {main.reference}, the inclusion's intensity changed {_cr_text(main, dom)} "
        f"times as much as the background's (\u00b1 one standard error, from the images' noise; the paper's "
        f"earlier study: {_paper_range(paper)}); "
    )
    if se is not None and abs(cr - 1) < 2 * se:
        # no intensity-domain caveat either: a ratio the noise could give says nothing to qualify
        return s + (
            "within two standard errors of 1: the noise alone could give it, so no sign here that the "
            "inclusion changed less than the background (nor more)."
        )
    s += (
        "below 1, the inclusion changed less than the background, as a stiffer inclusion that deforms less would"
        if cr < 1
        else "not below 1: no sign here that the inclusion changed less than the background"
    )
    if cr < 1 and dom in _TRANSMISSION:
        s += (
            ", though in the intensity domain attenuation alone can also give a ratio below 1 (the "
            "detected intensity is exponential in the line integral)"
        )
    return s + "."


def _pair_sentences(results, paper):
    """What the change ratio and the registration of the main pair say."""
    dom, main = results.domain, results.pair(results.main_pair)
    sentence = _change_ratio_sentence(main, dom, paper)
    out = [sentence] if sentence else []
    if main.ok:
        # a trusted run can stop short of convergence (its budget ended, the residual within the
        # line): "converged" would then be false, and the note says what happened instead
        slow = main.quality.get("converged") is False
        s = (
            f"The registration of step {main.moving} onto step {main.reference} passed its checks (similarity "
            + (
                "improved, no folding; not converged: " + main.quality.get("note", "")
                if slow
                else "improved, no folding, converged"
            )
            + ")"
        )
        if main.epe:
            s += f"; its median end-point error against the simulation's truth is {_fmt(main.epe['epe_median'], '.3f')} px"
        out.append(s + ".")
    else:
        out.append(
            f"Caution: the registration of {main.name} was flagged ({main.reason or 'no reason given'}); "
            "every number derived from D depends on it."
        )
    if main.rois_observed:
        obs = main.rois_observed
        unseen = _rois_unobserved(main)
        s = "The motion was observed (registration confidence map) in " + " and ".join(
            f"{_fmt(100 * v, '.0f')} % of the {k} ROI" for k, v in obs.items()
        )
        out.append(
            s
            + (
                f"; in the {' and '.join(unseen)} ROI the field is mostly the regulariser's guess, so the "
                "registration is flagged and the contrast measured there rests on that guess."
                if unseen
                else ": both ROIs lie where the images carry the motion."
            )
        )
    return out


def _rois_unobserved(pair) -> list[str]:
    """The ROIs of ``pair`` that lie mostly where the motion was not observed (a results.json of
    schema 1.0 has no ``rois_ok``: the pipeline's rule applied to its ``rois_observed``)."""
    from radiokit.pipeline import ROI_MIN_OBSERVED

    if pair.rois_ok is True:
        return []
    return [k for k, v in (pair.rois_observed or {}).items() if v is not None and v < ROI_MIN_OBSERVED]


def _plain_language(results, paper):
    out = _contrast_sentences(results, paper) + _pair_sentences(results, paper)
    if results.control is not None:
        k0 = _main_k(results.ks)
        if_s = results.domains[results.domain].at(k0).improvement_factor
        control = results.control.domains[results.domain].at(k0)
        if_c = control.improvement_factor
        out.append(
            f"A control run of the same scene with the inclusion as soft as the background "
            f"improves the contrast by {_if_text(control)} at {_k_label(k0)}: the share of the gain that "
            f"needs the inclusion's stiffness is {_share_text(stiffness_share(if_s, if_c))} (details below)."
        )
    return " ".join(out)


def _measurement_table(results, paper):
    header = ["domain", "image", "contrast", "CNR", "Weber", "improvement factor", "paper"]
    rows = []
    for dom in _in_order(results.domains):
        m = results.domains[dom]
        rows.append(
            (
                dom,
                "reference",
                _fmt(m.contrast_reference, ".4g"),
                _sig(m.cnr_reference),
                _fmt(m.weber_reference, ".4g"),
                "1",
                "",
            )
        )
        rows += [
            (
                dom,
                f"enhanced, {_k_label(x.k)}",
                _fmt(x.contrast, ".4g"),
                _sig(x.cnr),
                _fmt(x.weber, ".4g"),
                _if_text(x),
                _fmt(_paper_if(paper, x.k), ".1f", ""),
            )
            for x in m.per_k
        ]
    return _table(header, rows)


def _change_ratio_table(results, paper):
    domains = _in_order(results.domains)
    header = ["steps (moving\u2192reference)"] + [f"{d} domain" for d in domains] + ["paper (earlier study)"]
    rows = [[_pair_label(p.name)] + [_cr_text(p, d) for d in domains] + [_paper_range(paper)] for p in results.pairs]
    return _table(header, rows)


def _registration_table(results):
    has_epe = any(p.epe for p in results.pairs)
    header = (
        [
            "pair",
            "method",
            "ok",
            "RC before\u2192after",
            "NCC before\u2192after",
            "folds",
            "min det J",
            "iterations",
            "time (s)",
        ]
        + (["EPE median / p95 (px)"] if has_epe else [])
        + ["reason (flagged) or note"]
    )
    rows = []
    for p in results.pairs:
        q = p.quality
        row = [
            _pair_label(p.name),
            p.method + (f" ({q['preset']})" if q.get("preset") else ""),
            "yes" if p.ok else "NO",
            f"{_fmt(q.get('rc_before'), '.5g')} \u2192 {_fmt(q.get('rc_after'), '.5g')}",
            f"{_fmt(q.get('ncc_before'), '.4f')} \u2192 {_fmt(q.get('ncc_after'), '.4f')}",
            _fmt(q.get("folds"), ".0f"),
            _fmt(q.get("min_det_j"), ".3g"),
            _fmt(q.get("iterations"), ".0f"),
            _fmt(q.get("seconds")),
        ]
        if has_epe:
            epe = p.epe or {}
            row.append(f"{_fmt(epe.get('epe_median'), '.3f')} / {_fmt(epe.get('epe_p95'), '.3f')}")
        # a trusted result's note (Quality.note: e.g. its budget ended still moving, slow, not
        # lost) is what a reader deciding whether to trust it needs beside the verdict
        rows.append(row + [p.reason or (f"note: {q['note']}" if q.get("note") else "")])
    return _table(header, rows)


def _auto_choices(results) -> str:
    """One line: the preset ``auto`` chose for each pair and why (results.json's ``preset_reason``;
    the table showed the preset, not the reason). Nothing when no pair recorded one."""
    chosen = [
        f"{_e(_pair_label(p.name))}: {_e(p.quality['preset'])} ({_e(p.quality['preset_reason'])})"
        for p in results.pairs
        if p.quality.get("preset_reason") and p.quality.get("preset")
    ]
    return f"<p>Preset auto chose, per pair: {'; '.join(chosen)}.</p>" if chosen else ""


def _control_section(results):
    control = results.control
    if control is None:
        return ""
    rows, sentences = [], []
    domains = _in_order(d for d in results.domains if d in control.domains)
    for dom in domains:
        s, c = results.domains[dom], control.domains[dom]
        rows.append(
            (dom, "contrast of the reference", _fmt(s.contrast_reference, ".4g"), _fmt(c.contrast_reference, ".4g"), "")
        )
        for x in s.per_k:
            if_c = c.at(x.k).improvement_factor
            rows.append(
                (
                    dom,
                    f"improvement factor, {_k_label(x.k)}",
                    _if_text(x),
                    _if_text(c.at(x.k)),
                    _share_text(stiffness_share(x.improvement_factor, if_c)),
                )
            )
        k0 = _main_k(results.ks)
        sentences.append(_control_sentence(dom, k0, *_factor_and_se(s.at(k0), c.at(k0))))
    for p in results.pairs:
        ctrl = control.pair(p.name) if _has_pair(control, p.name) else None
        rows += [
            (
                dom,
                f"intensity-change ratio, steps {_pair_label(p.name)}",
                _cr_text(p, dom),
                _cr_text(ctrl, dom) if ctrl is not None else _fmt(None),
                "",
            )
            for dom in domains
        ]
    header = [
        "domain",
        "quantity",
        "stiff inclusion",
        "control (inclusion as soft as the background)",
        "share needing stiffness",
    ]
    return (
        '<section id="control"><h2>Stiff inclusion vs control (inclusion as soft as the background)</h2>'
        "<p>The control is a run of the same simulated scene whose inclusion has the background's "
        "stiffness but keeps its attenuation: whatever contrast compression induces there comes from "
        "attenuation alone. The share of the gain that needs stiffness is Z = (IF<sub>stiff</sub> "
        "\u2212 IF<sub>control</sub>) / (IF<sub>stiff</sub> \u2212 1), \u201cnot measurable\u201d when "
        f"IF<sub>stiff</sub> is within {MIN_EFFECT:g} of 1.</p>"
        + _table(header, rows)
        + "".join(f'<p class="control-sentence">{_e(s)}</p>' for s in sentences)
        + "</section>"
    )


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
    rows = [("source file", results.source or "\u2014")]
    if results.scene:
        scene = str(results.scene)
        long = "\n" in scene.strip() or len(scene) > 120
        rows.append(("scene", f"{len(scene.splitlines())} lines of configuration, shown below" if long else scene))
    px = results.pixel_size_mm
    rows.append(
        ("pixel size", f"{px:g} mm" + ("" if results.pixel_size_recorded else " (assumed: the file records none)"))
    )
    rows.append(("headline domain", f"{results.domain} ({_domain_unit(results.domain)})"))
    r0, r1, c0, c1 = results.rois.crop
    rows.append(("crop (full-frame px, rows \u00d7 cols, half-open)", f"[{r0}, {r1}) \u00d7 [{c0}, {c1})"))
    for name in ("inclusion", "background"):
        r0, r1, c0, c1 = getattr(results.rois, name)
        rows.append(
            (
                f"{name} ROI (cropped image)",
                f"[{r0}, {r1}) \u00d7 [{c0}, {c1}) px ({(r1 - r0) * px:.3g} \u00d7 {(c1 - c0) * px:.3g} mm)",
            )
        )
    return rows


def _scene_details(scene):
    """A long scene (the simulation's TOML) folded away: <details> needs no script."""
    if not scene or ("\n" not in str(scene).strip() and len(str(scene)) <= 120):
        return ""
    return f"<details><summary>scene configuration</summary><pre>{_e(scene)}</pre></details>"


def _figures(images, results, fig_dir) -> dict:
    """Every figure drawn and saved: ``{file name: HTML <figure>}``, numbered in drawing order."""
    figures = [
        make(images, results, fig_dir)
        for make in (_fig_projections, _fig_profiles, _fig_difference, _fig_rois, _fig_registration)
    ]
    return {
        name: (
            f'<figure id="fig-{_e(name[:-4])}"><img src="figures/{_e(name)}" alt="{_e(caption[:120])}">'
            f"<figcaption><b>Figure {i}.</b> {_e(caption)}</figcaption></figure>"
        )
        for i, (name, caption) in enumerate(figures, 1)
    }


def _head(results, paper) -> list:
    """The page from its head to the headline table and summary."""
    header, rows = _headline_rows(results, paper)
    return [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>radiokit report \u2014 {_e(results.source)}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Compression-induced contrast</h1>",
        f"<p>radiokit {_e(__version__)} report for <code>{_e(results.source)}</code>, written "
        f"{_e(datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC'))}.</p>",
        _table(["", ""], _meta_rows(results), cls="meta"),
        _scene_details(results.scene),
        "<h2>Headline</h2>",
        _table(header, rows),
        f'<p class="summary"><b>What the numbers show.</b> {_e(_plain_language(results, paper))}</p>',
    ]


def _measurements(results, paper) -> list:
    return [
        "<h2>Contrast measurements</h2>",
        "<p>Contrast: mean of the inclusion ROI \u2212 mean of the background ROI; CNR: contrast over "
        "the background ROI's (population) standard deviation; Weber: contrast over |mean of the background ROI| "
        "(its magnitude: the negative domain's means are negative); "
        "improvement factor: enhanced contrast over the reference's. Domains: log is \u2212ln(I/I\u2080); "
        "negative is \u2212I/I\u2080, the paper's \u201clinear\u201d images. The paper's improvement "
        "factors (about 1.4 and 2) and intensity-change ratios (0.66\u20130.84, the authors' "
        "earlier study) are beside them. \u00b1: one standard error, from the noise of the images "
        "themselves in and around the ROIs (the correlation the registration's resampling gives "
        "neighbouring pixels included).</p>",
        _measurement_table(results, paper),
        "<p>Intensity-change ratio: the change of the inclusion ROI's mean between two steps "
        "over the change of the background ROI's (the moving step registered onto the "
        "other); below 1 the inclusion changed less. Not measurable: the background's change is "
        "within three standard errors of zero, so the ratio's denominator is noise.</p>"
        + _change_ratio_table(results, paper),
        _control_section(results),
    ]


def write_report(out_dir, results: Results, images: Images) -> Path:
    """Write the processing report: ``out_dir/report.html`` and PNG figures in ``out_dir/figures/``.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing; ``report.html`` and ``figures/*.png`` in it are overwritten.
    results : radiokit.results.Results
        The run's numbers (``results.json``'s records), with its control run if any.
    images : radiokit.results.Images
        The run's images, all of the cropped shape: the steps (line integrals), the main pair
        (reference, moving, registered, field, det J), the enhancement per domain, and for a
        simulated file the truth field and the end-point error map.

    Returns
    -------
    Path
        The HTML file. Its figures are linked relatively (``figures/name.png``).

    Notes
    -----
    The page is self-contained: inline CSS, no scripts, no network references. All text taken from
    ``results`` (paths, scene names, registration reasons) is HTML-escaped.
    """
    if not isinstance(results, Results) or not isinstance(images, Images):
        raise TypeError(
            "write_report takes radiokit.results.Results and Images (load_results reads a "
            f"results.json), got {type(results).__name__} and {type(images).__name__}"
        )
    t0 = time.perf_counter()
    fig_html = draw_figures(out_dir, results, images)
    timings = dict(results.timings)
    own_report_time = "report_s" not in timings
    if own_report_time:
        timings["report_s"] = time.perf_counter() - t0
        # a total measured before this report did not include it: the page's total was below
        # the sum of its own rows
        if _num(timings.get("total_s")) is not None:
            timings["total_s"] += timings["report_s"]
    return write_page(out_dir, dataclasses.replace(results, timings=timings), fig_html, own_report_time=own_report_time)


def draw_figures(out_dir, results: Results, images: Images) -> dict[str, str]:
    """Draw the report's figures into ``out_dir/figures/``: the first step of :func:`write_report`.

    Parameters
    ----------
    out_dir : str or Path
        The report's folder; ``figures/`` in it is created if missing, its PNGs overwritten.
    results, images : radiokit.results.Results, radiokit.results.Images
        As for :func:`write_report`.

    Returns
    -------
    dict
        ``{file name: HTML <figure>}`` for every figure, to hand to :func:`write_page`.
    """
    fig_dir = Path(out_dir) / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    return _figures(images, results, fig_dir)


def write_page(out_dir, results: Results, fig_html: dict[str, str], *, own_report_time: bool = False) -> Path:
    """Write ``out_dir/report.html`` around the figures :func:`draw_figures` drew: the second step
    of :func:`write_report`.

    Parameters
    ----------
    out_dir : str or Path
        The folder :func:`draw_figures` drew into; ``report.html`` in it is overwritten.
    results : radiokit.results.Results
        The run's numbers; the page's timings table is ``results.timings`` as given.
    fig_html : dict
        What :func:`draw_figures` returned.
    own_report_time : bool, optional
        The report's time row is this page's own measurement, not the caller's: a line beneath
        the table says so.

    Returns
    -------
    Path
        The HTML file.
    """
    paper = {**PAPER, **(results.paper or {})}
    parts = _head(results, paper) + ["<h2>Images</h2>"]
    parts += [fig_html[n] for n in ("projections.png", "profiles.png", "difference.png", "rois.png")]
    parts += _measurements(results, paper)
    parts += [
        "<h2>Registration quality</h2>",
        fig_html["registration.png"],
        _registration_table(results),
        _auto_choices(results),
        "<p>RC: residual complexity of the difference image (lower is better); NCC: normalised "
        "cross-correlation (higher is better); folds: pixels with det J \u2264 0.</p>",
        "<h2>Timings</h2>",
        _timings_table(results.timings) or "<p>No timings recorded.</p>",
    ]
    if own_report_time:
        parts.append("<p>The report's time is its own figure drawing, measured while writing this page.</p>")
    parts.append("</body></html>")
    path = Path(out_dir) / "report.html"
    path.write_text("\n".join(p for p in parts if p), encoding="utf-8")
    return path
