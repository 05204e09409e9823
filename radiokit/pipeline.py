"""From an experiment file to compression-induced contrast, measurements and a report.

``process(path, config) -> Result`` runs the paper's chain on one experiment file (the lab's or a
simulated one; DESIGN.md's layout):

1. calibrate from the file's own darks and flats, correct every projection to line integrals
   (``-ln(I/I0)``), average the frames of each step;
2. find the inclusion and a background rectangle beside it on the reference (the most
   compressed step), or take them from the configuration, and crop around them;
3. register every step onto the reference, and each step onto the next (residual complexity by
   default);
4. enhance the reference with the step before it, for every k, in both domains: ``log`` (line
   integrals) and ``linear`` (the paper's experimental images: the negative of the detected
   intensity, ``-I/I0``);
5. measure contrast, CNR, Weber contrast, the improvement factor per k, and the inclusion /
   background intensity-change ratio of every registered pair; for a simulated file, the
   registration's end-point error against the stored truth;
6. write ``results.h5`` (corrected steps, registered images, fields, differences, enhanced
   images), ``results.json`` and ``report.html`` with its figures.

``process_many(paths, config, scheduler=None)`` runs many files in parallel on Dask (a local
cluster by default, or the scheduler at an address), with one progress bar over all of them.

Example (a small synthetic experiment written here; real files come from ``radiokit acquire``)::

    >>> import numpy as np, os, tempfile
    >>> from radiokit.io import ExperimentWriter, ImageKey
    >>> from radiokit.pipeline import Config, process
    >>> d = tempfile.mkdtemp()
    >>> rr, cc = np.mgrid[0:160, 0:160]
    >>> def frame(t_body, t_incl):   # a slab thinned by compression, with a denser square
    ...     L = 0.08 * t_body + 0.03 * t_incl * ((abs(rr - 80) < 10) & (abs(cc - 80) < 10))
    ...     return (100 + 3000 * np.exp(-L)).astype(np.uint16)
    >>> with ExperimentWriter(os.path.join(d, "exp.h5"), shape=(160, 160)) as w:
    ...     for _ in range(3): _ = w.append(np.full((160, 160), 100, np.uint16), image_key=ImageKey.DARK)
    ...     for _ in range(3): _ = w.append(np.full((160, 160), 3100, np.uint16), image_key=ImageKey.FLAT)
    ...     for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
    ...         _ = w.append(frame(tb, ti), image_key=ImageKey.PROJECTION, step=step, ratio=0.1 * step)
    >>> res = process(os.path.join(d, "exp.h5"), Config(crop_mm=None, report=False,
    ...               inclusion=(75, 86, 75, 86), background=(75, 86, 40, 51)), out_dir=os.path.join(d, "results"))
    >>> res.results["improvement_factor"]["1"] > 1, res.results["improvement_factor"]["2"] > res.results["improvement_factor"]["1"]
    (True, True)
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radiokit.errors import FormatError
from radiokit.measure import PAPER

__all__ = ["Config", "Result", "process", "process_many", "output_folders", "PAPER"]



@dataclass
class Config:
    """What :func:`process` does. ROIs are ``(row0, row1, col0, col1)`` half-open, in pixels of
    the full frame (``roi_units="px"``) or millimetres from the frame's top-left corner
    (``"mm"``); ``None`` finds them automatically."""
    ks: tuple = (1.0, 2.0)
    domain: str = "linear"            # the headline domain (the paper's: -I/I0); both are computed
    method: str = "rc"
    register_options: dict = field(default_factory=dict)
    crop_mm: float | None = 30.0      # side of the square around the inclusion kept in the outputs; None: all
    inclusion: tuple | None = None
    background: tuple | None = None
    roi_units: str = "px"
    use_truth_rois: bool = False      # simulated files: place the ROIs on the stored inclusion mask
    report: bool = True
    progress: bool = True
    control: str | None = None        # a control experiment (inclusion as soft as the background)
    cross_check: str | None = "ncc"   # register the main pair again with this similarity and flag disagreement

    def __post_init__(self):
        if self.domain not in ("log", "linear"):
            raise ValueError(f"domain={self.domain!r}: expected 'log' or 'linear'")
        if self.roi_units not in ("px", "mm"):
            raise ValueError(f"roi_units={self.roi_units!r}: expected 'px' or 'mm'")
        self.ks = tuple(float(k) for k in self.ks)
        if not self.ks or not all(np.isfinite(self.ks)):
            raise ValueError(f"ks={self.ks}: expected finite enhancement factors")


@dataclass
class Result:
    """The numbers (``results``, as in results.json), the images (``arrays``), the files."""
    results: dict
    arrays: dict
    files: dict


def _key(k) -> str:
    return f"{k:g}"


def _roi(value, units, pixel_mm):
    from radiokit.measure import ROI

    if value is None:
        return None
    if isinstance(value, ROI):
        return value
    if isinstance(value, dict):
        value = (value["row0"], value["row1"], value["col0"], value["col1"])
    r0, r1, c0, c1 = (float(v) for v in value)
    if units == "mm":
        r0, r1, c0, c1 = (v / pixel_mm for v in (r0, r1, c0, c1))
    return ROI(int(round(r0)), int(round(r1)), int(round(c0)), int(round(c1)))


def _load_steps(path, progress):
    """Calibrate from the file's darks and flats; the corrected line integral of each step (mean
    of its frames), step numbers, ratios, pixel size."""
    from tqdm.auto import tqdm

    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames
    from radiokit.io import ImageKey, open_frames

    t = time.perf_counter()
    cal = Calibration.from_experiment(path)
    t_cal = time.perf_counter() - t
    t = time.perf_counter()
    with open_frames(path) as src:
        meta = src.meta
        keys = np.asarray(meta["image_key"])
        steps = np.asarray(meta.get("step", np.full(len(keys), -1)))
        ratios_all = np.asarray(meta.get("ratio", np.full(len(keys), np.nan)), float)
        numbers = sorted(int(s) for s in np.unique(steps[(keys == ImageKey.PROJECTION) & (steps >= 0)]))
        if len(numbers) < 2:
            raise FormatError(path, f"needs projections of at least two compression steps; found steps {numbers}")
        images, ratios = [], []
        n_frames = int(np.sum((keys == ImageKey.PROJECTION) & (steps >= 0)))
        bar = tqdm(total=n_frames, desc=f"correct {Path(path).name}", unit="frame", disable=not progress)
        for s in numbers:
            idx = np.flatnonzero((keys == ImageKey.PROJECTION) & (steps == s))
            acc = None
            for i in idx:
                li = correct_frames(cal, src[i], domain="log")
                acc = li.astype(np.float64) if acc is None else acc + li
                bar.update()
            images.append((acc / len(idx)).astype(np.float32))
            ratios.append(float(np.nanmean(ratios_all[idx])) if np.isfinite(ratios_all[idx]).any() else float("nan"))
        bar.close()
        pixel_mm = float(meta.get("pixel_size_mm", 0.05))
    return np.stack(images), numbers, ratios, pixel_mm, dict(calibrate_s=t_cal, correct_s=time.perf_counter() - t)


def _sim_truth(path, numbers):
    """Simulated files: the inclusion mask of the last step and the truth fields, or None."""
    import h5py

    with h5py.File(path, "r") as h5:
        if "entry/simulation" not in h5:
            return None
        g = h5["entry/simulation"]
        out = {"fields": {}, "scene": None}
        if "inclusion_mask" in g:
            out["inclusion_mask"] = g["inclusion_mask"][-1].astype(bool)
        if "line_integral" in g:
            out["line_integral"] = g["line_integral"][-1]
        for a in numbers:
            for b in numbers:
                name = f"displacement/step{a}_to_step{b}"
                if a < b and name in g:
                    out["fields"][(a, b)] = g[name][()]
        scene = g.attrs.get("scene")
        if scene is not None:
            text = scene.decode() if isinstance(scene, bytes) else str(scene)
            out["scene_toml"] = text
            for line in text.splitlines():
                if line.startswith("name"):
                    out["scene"] = line.split("=", 1)[1].strip().strip('"')
                    break
    return out


def _crop_box(inclusion, shape, side_px):
    """A square of ``side_px`` centred on the inclusion ROI, inside the frame."""
    rows, cols = shape
    side_r, side_c = min(side_px, rows), min(side_px, cols)
    cr, cc = (inclusion.row0 + inclusion.row1) // 2, (inclusion.col0 + inclusion.col1) // 2
    r0 = int(np.clip(cr - side_r // 2, 0, rows - side_r))
    c0 = int(np.clip(cc - side_c // 2, 0, cols - side_c))
    return r0, r0 + side_r, c0, c0 + side_c


def _body_mask(image):
    return image > 0.2 * float(np.percentile(image, 99.5))


def cross_check(field, other, body, method):
    """How far two registrations of one pair disagree inside ``body``: median and 95th percentile
    of ``|field - other|`` (px), and whether they agree: median disagreement under
    max(2 px, half the larger field's median magnitude).

    Why: a similarity can have its minimum away from the truth and still report success (its own
    energy dropped). Measured on the virtual experiment: seed-breast, rc against ncc 1.6 px
    apart with fields of 7 px (both within 1-4 px of the truth); the pva-phantom side view,
    22 px apart (rc 21 px off the truth, ncc 1.8 px)."""
    d = np.hypot(*(np.asarray(field) - np.asarray(other)))[body]
    mag = max(float(np.median(np.hypot(*field)[body])), float(np.median(np.hypot(*other)[body])))
    med = float(np.median(d))
    return {"method": method, "median_px": med, "p95_px": float(np.percentile(d, 95)),
            "agree": bool(med <= max(2.0, 0.5 * mag))}


def _step_gaps_mm(path, numbers):
    """Mean plate gap (mm) of each step's projections, NaN where the file does not record it."""
    from radiokit.io import ImageKey, open_frames

    with open_frames(path) as src:
        meta = src.meta
        keys = np.asarray(meta["image_key"])
        steps = np.asarray(meta.get("step", np.full(len(keys), -1)))
        gap = np.asarray(meta.get("gap", np.full(len(keys), np.nan)), float) * 1e3
    out = []
    for s in numbers:
        g = gap[(keys == ImageKey.PROJECTION) & (steps == s)]
        out.append(float(np.nanmean(g)) if np.isfinite(g).any() else float("nan"))
    return out


def _bound(path, numbers, truth, bg_log_mean, ks):
    """The improvement factor's bound (:func:`radiokit.measure.improvement_bound`) for the main
    pair: ``mu_b`` from a simulated file's scene, else from the reference's background ROI
    (``mean L_bg / gap``: through the plates a background column spans the gap); None where the
    gaps are not recorded or the simulated beam runs from the side (no bound holds there)."""
    import tomllib

    from radiokit.measure import improvement_bound

    gaps = _step_gaps_mm(path, numbers)
    dg = gaps[-2] - gaps[-1]
    out = {"mu_dg": None, "basis": "", "domains": {}}
    view, mu_b = None, None
    scene_text = truth.get("scene_toml") if truth else None
    if scene_text:
        try:
            sc = tomllib.loads(scene_text)
            view = "side" if sc.get("beam", {}).get("direction", "y") in ("z", "side") else "through_plates"
            mu_b = float(sc["body"]["material"]["attenuation_per_cm"]) / 10
        except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError):
            pass
    if view == "side":
        out["basis"] = "beam from the side: columns lengthen as the body expands, no bound holds"
        return out
    if not (np.isfinite(dg) and dg >= 0 and np.isfinite(gaps[-1]) and gaps[-1] > 0):
        out["basis"] = "plate gaps not recorded: no bound"
        return out
    if mu_b is not None:
        out["basis"] = "through the plates; mu_b from the simulated scene, gaps from the file"
    else:
        mu_b = max(bg_log_mean, 0.0) / gaps[-1]
        out["basis"] = ("assumes the beam through the plates; mu_b = background line integral of the reference "
                        "/ its gap, gaps from the file")
    out["mu_dg"] = mu_b * dg
    out["domains"] = {dom: {_key(k): improvement_bound(k, mu_b, dg, dom) if k >= 0 else None for k in ks}
                      for dom in ("log", "linear")}
    return out


def _epe(displacement, truth, mask):
    e = np.sqrt(((displacement - truth) ** 2).sum(axis=0))
    e = e[mask] if mask is not None and mask.any() else e.ravel()
    return float(np.median(e)), float(np.percentile(e, 95))


def process(path, config: Config | None = None, *, out_dir=None, overwrite=False) -> Result:
    """Run the chain on one experiment file; write results into ``out_dir`` (default: a folder
    named after the file, beside it). See the module docstring.

    The folder is assembled under a temporary name beside ``out_dir`` and swapped in when
    complete (:func:`radiokit.io.atomic_dir`): an interrupted run leaves the previous results or
    none. An existing ``out_dir`` is replaced only with ``overwrite=True`` and only if radiokit
    made it; one holding the input is always refused.
    """
    from radiokit.io import atomic_dir

    cfg = config or Config()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such experiment file")
    out_dir = Path(out_dir) if out_dir is not None else path.with_suffix("")
    inputs = [path] + ([Path(cfg.control)] if cfg.control else [])
    with atomic_dir(out_dir, overwrite=overwrite, inputs=inputs) as stage:
        res = _process(path, cfg, stage)
    res.files = {k: str(out_dir / Path(v).relative_to(stage)) for k, v in res.files.items()}
    return res


def _process(path: Path, cfg: Config, out_dir: Path) -> Result:
    """:func:`process` writing into ``out_dir``, a fresh folder."""
    from radiokit.enhance import compression_contrast, to_domain
    from radiokit.measure import ROI, change_ratio, cnr, contrast, find_rois, profile, weber
    from radiokit.register import jacobian_determinant, register, roi_observed

    t0 = time.perf_counter()
    steps, numbers, ratios, pixel_mm, timings = _load_steps(path, cfg.progress)
    truth = _sim_truth(path, numbers)
    ref_full = steps[-1]

    # ROIs and the crop (full-frame pixels first)
    inc = _roi(cfg.inclusion, cfg.roi_units, pixel_mm)
    bg = _roi(cfg.background, cfg.roi_units, pixel_mm)
    if inc is None or bg is None:
        mask = truth.get("inclusion_mask") if (truth and cfg.use_truth_rois) else None
        auto_inc, auto_bg = find_rois(ref_full, inclusion_mask=mask, pixel_mm=pixel_mm)
        inc = inc or auto_inc
        bg = bg or auto_bg
    for name, roi in (("inclusion", inc), ("background", bg)):
        if not (0 <= roi.row0 < roi.row1 <= ref_full.shape[0] and 0 <= roi.col0 < roi.col1 <= ref_full.shape[1]):
            raise ValueError(f"{name} ROI {roi} lies outside the {ref_full.shape} frame")
    if cfg.crop_mm:
        crop = _crop_box(inc, ref_full.shape, int(round(cfg.crop_mm / pixel_mm)))
        # keep the background rectangle inside the crop
        r0, r1, c0, c1 = crop
        if not (r0 <= bg.row0 and bg.row1 <= r1 and c0 <= bg.col0 and bg.col1 <= c1):
            r0, r1 = min(r0, bg.row0), max(r1, bg.row1)
            c0, c1 = min(c0, bg.col0), max(c1, bg.col1)
            crop = (r0, r1, c0, c1)
    else:
        crop = (0, ref_full.shape[0], 0, ref_full.shape[1])
    r0, r1, c0, c1 = crop

    # registrations on the whole frame (the body's outline carries most of the motion of a
    # smooth phantom: a crop inside the body leaves little but the inclusion to register on),
    # every step onto the reference and each onto the next; the outputs are cropped
    t = time.perf_counter()
    n = len(numbers)
    pairs = [(i, n - 1) for i in range(n - 1)] + [(i, i + 1) for i in range(n - 2)]
    regs, warped, cross = {}, {}, {}
    from tqdm.auto import tqdm

    body_full = _body_mask(steps[-1])
    for i, j in tqdm(pairs, desc=f"register {path.name}", unit="pair", disable=not cfg.progress):
        reg = register(steps[j], steps[i], cfg.method, **cfg.register_options)
        if cfg.cross_check and (i, j) == (n - 2, n - 1) and cfg.cross_check != cfg.method:
            other = register(steps[j], steps[i], cfg.cross_check, **cfg.register_options)
            cross[(i, j)] = cross_check(reg.displacement, other.displacement, body_full, cfg.cross_check)
        warped[(i, j)] = reg.warp(steps[i])[r0:r1, c0:c1]  # warped whole, then cropped: no border effects
        reg.displacement = np.ascontiguousarray(reg.displacement[:, r0:r1, c0:c1])
        if reg.confidence is not None:
            reg.confidence = np.ascontiguousarray(reg.confidence[r0:r1, c0:c1])
        regs[(i, j)] = reg
    timings["register_s"] = time.perf_counter() - t
    steps = np.ascontiguousarray(steps[:, r0:r1, c0:c1])
    inc_c = ROI(inc.row0 - r0, inc.row1 - r0, inc.col0 - c0, inc.col1 - c0)
    bg_c = ROI(bg.row0 - r0, bg.row1 - r0, bg.col0 - c0, bg.col1 - c0)
    reference = steps[-1]
    body = _body_mask(reference)

    # enhancement with the step before the reference (the paper's pair), both domains
    t = time.perf_counter()
    main = regs[(n - 2, n - 1)]
    registered = warped[(n - 2, n - 1)]
    enhanced, ref_dom, diff = {}, {}, {}
    for dom in ("log", "linear"):
        ref_d = to_domain(reference, dom)
        reg_d = to_domain(registered, dom)
        ref_dom[dom] = ref_d
        diff[dom] = (ref_d - reg_d).astype(np.float32)
        enhanced[dom] = {_key(k): compression_contrast(ref_d, reg_d, k, domain=dom) for k in cfg.ks}
    timings["enhance_s"] = time.perf_counter() - t

    # measurements
    t = time.perf_counter()
    domains = {}
    for dom in ("log", "linear"):
        c_ref = contrast(ref_dom[dom], inc_c, bg_c)
        d = {"contrast_reference": c_ref, "cnr_reference": cnr(ref_dom[dom], inc_c, bg_c),
             "weber_reference": weber(ref_dom[dom], inc_c, bg_c), "contrast": {}, "cnr": {}, "weber": {},
             "improvement_factor": {}}
        for k, img in enhanced[dom].items():
            d["contrast"][k] = contrast(img, inc_c, bg_c)
            d["cnr"][k] = cnr(img, inc_c, bg_c)
            d["weber"][k] = weber(img, inc_c, bg_c)
            d["improvement_factor"][k] = d["contrast"][k] / c_ref if c_ref != 0 else float("nan")
        domains[dom] = d
    bound = _bound(path, numbers, truth, float(np.mean(ref_dom["log"][bg_c.slices], dtype=np.float64)), cfg.ks)
    for dom in ("log", "linear"):
        domains[dom]["bound"] = bound["domains"].get(dom, {})
    changes, quality = {}, {}
    for (i, j), reg in regs.items():
        name = f"{numbers[i]}->{numbers[j]}"
        changes[name] = {dom: change_ratio(to_domain(warped[(i, j)], dom), to_domain(steps[j], dom), inc_c, bg_c)
                         for dom in ("log", "linear")}
        q = dataclasses.asdict(reg.quality)
        q = {k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in q.items()}
        q["method"] = reg.method
        if reg.confidence is not None:  # is the motion observed where the paper's numbers are measured?
            q["rois_observed"] = {"inclusion": roi_observed(reg.confidence, inc_c),
                                  "background": roi_observed(reg.confidence, bg_c)}
        if (i, j) in cross:
            q["cross_check"] = cross[(i, j)]
            if not cross[(i, j)]["agree"]:
                q["ok"] = False
                why = (f"disagrees with {cross[(i, j)]['method']} by {cross[(i, j)]['median_px']:.1f} px (median over "
                       f"the body): at least one of the two is wrong")
                q["reason"] = f"{q['reason']}; {why}" if q.get("reason") else why
        if truth and (numbers[i], numbers[j]) in truth["fields"]:
            tf = truth["fields"][(numbers[i], numbers[j])][:, r0:r1, c0:c1]
            q["epe_median"], q["epe_p95"] = _epe(reg.displacement, tf, body)
            # where the images carry the motion: the inclusion and background rectangles (a
            # uniform slab's interior moves unseen: there the field is the regulariser's guess)
            q["epe_roi_median"], q["epe_roi_p95"] = _epe(reg.displacement, tf, inc_c.mask(body.shape) | bg_c.mask(body.shape))
        quality[name] = q
    mid = (inc_c.row0 + inc_c.row1) // 2
    prof = {f"step {s}": profile(steps[k], (mid, 0), (mid, steps.shape[2] - 1))[1].tolist()
            for k, s in enumerate(numbers)}
    timings["measure_s"] = time.perf_counter() - t

    main_name = f"{numbers[-2]}->{numbers[-1]}"
    results = {
        "source": str(path), "scene": truth.get("scene") if truth else None, "simulated": truth is not None,
        "pixel_mm": pixel_mm, "domain": cfg.domain, "ks": list(cfg.ks), "method": cfg.method,
        "steps": numbers, "ratios": ratios,
        "rois": {"crop": list(crop), "inclusion": [inc_c.row0, inc_c.row1, inc_c.col0, inc_c.col1],
                 "background": [bg_c.row0, bg_c.row1, bg_c.col0, bg_c.col1]},
        "improvement_factor": dict(domains[cfg.domain]["improvement_factor"]),
        "domains": domains, "change_ratio": changes, "registration": quality, "main_pair": main_name,
        "profiles_row": mid, "paper": PAPER, "timings": timings,
        "bound": {k: v for k, v in bound.items() if k != "domains"},
    }
    arrays = {"steps": steps, "step_numbers": numbers, "ratios": ratios, "reference": reference,
              "registered": registered, "moving": steps[n - 2], "displacement": main.displacement,
              "det_j": jacobian_determinant(main.displacement), "confidence": main.confidence, "enhanced": enhanced,
              "reference_by_domain": ref_dom, "difference": diff, "profiles": prof}
    if truth and (numbers[-2], numbers[-1]) in truth["fields"]:
        tf = truth["fields"][(numbers[-2], numbers[-1])][:, r0:r1, c0:c1].astype(np.float32)
        arrays["truth_displacement"] = tf
        arrays["epe_map"] = np.sqrt(((main.displacement - tf) ** 2).sum(axis=0)).astype(np.float32)

    if cfg.control:
        ctrl_cfg = dataclasses.replace(cfg, control=None, report=False, progress=False,
                                       inclusion=(inc.row0, inc.row1, inc.col0, inc.col1),
                                       background=(bg.row0, bg.row1, bg.col0, bg.col1), roi_units="px")
        ctrl = process(cfg.control, ctrl_cfg, out_dir=out_dir / "control")
        results["control"] = {k: ctrl.results[k] for k in ("improvement_factor", "domains", "change_ratio",
                                                            "registration", "source")}

    files = _write(out_dir, results, arrays, cfg, t0)
    return Result(results, arrays, files)


def _write(out_dir, results, arrays, cfg, t0):
    files = {}
    from radiokit.io import atomic_h5

    h5path = out_dir / "results.h5"
    with atomic_h5(h5path) as h5:  # built in memory, one plain write: a full disk is a clean error
        h5.attrs["source"] = results["source"]
        h5.attrs["results_json"] = json.dumps(results, default=_jsonable)
        g = h5.create_group("steps")
        g.create_dataset("line_integral", data=arrays["steps"], compression="gzip", shuffle=True)
        g.attrs["step"] = np.asarray(arrays["step_numbers"])
        g.attrs["ratio"] = np.asarray(arrays["ratios"], float)
        g.attrs["crop"] = np.asarray(results["rois"]["crop"])
        r = h5.create_group("registration")
        for name in ("registered", "moving", "displacement", "det_j", "confidence"):
            if arrays.get(name) is not None:  # confidence: where the motion was observed (>= 0.5)
                r.create_dataset(name, data=arrays[name], compression="gzip", shuffle=True)
        r.attrs["pair"] = results["main_pair"]
        if "truth_displacement" in arrays:
            r.create_dataset("truth_displacement", data=arrays["truth_displacement"], compression="gzip")
        for dom in ("log", "linear"):
            e = h5.create_group(f"enhanced/{dom}")
            e.create_dataset("reference", data=arrays["reference_by_domain"][dom], compression="gzip")
            e.create_dataset("difference", data=arrays["difference"][dom], compression="gzip")
            for k, img in arrays["enhanced"][dom].items():
                e.create_dataset(f"k{k}", data=img, compression="gzip")
        m = h5.create_group("measurements")
        for key, roi in results["rois"].items():
            m.attrs[key] = np.asarray(roi)
    files["results_h5"] = str(h5path)
    results["timings"]["total_s"] = time.perf_counter() - t0
    if cfg.report:
        from radiokit.report import write_report

        t = time.perf_counter()
        files["report"] = str(write_report(out_dir, results, arrays))
        results["timings"]["report_s"] = time.perf_counter() - t
        results["timings"]["total_s"] = time.perf_counter() - t0
    jpath = out_dir / "results.json"
    jpath.write_text(json.dumps(results, indent=1, default=_jsonable))
    files["results_json"] = str(jpath)
    return files


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-able: {type(o)}")


def output_folders(paths, out_root=None) -> list[Path]:
    """One distinct results folder per input: ``out_root/STEM`` (default: beside each file, named
    after it); inputs sharing a folder name get ``STEM-2``, ``STEM-3``, ... in the order given,
    so no run ever merges into or replaces another's folder."""
    outs, taken = [], set()
    for p in map(Path, paths):
        base = (Path(out_root) / p.stem) if out_root is not None else p.with_suffix("")
        out, k = base, 1
        while out.resolve() in taken:
            k += 1
            out = base.with_name(f"{base.name}-{k}")
        taken.add(out.resolve())
        outs.append(out)
    return outs


# Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536 (its pre-spawn-environ).
# Setting any malloc threshold turns off glibc's sliding mmap threshold, so every array over 128 kB
# is mmapped and unmapped on each allocation and its pages faulted in again: on a 560 x 560
# experiment the kernel time equalled the user time (benchmarks/README.md, "Dask"). Fixed
# thresholds above a 2240 x 2240 float32 frame keep frame-sized buffers in the heap for reuse.
_MALLOC_MMAP_THRESHOLD = 32 * 2 ** 20  # glibc's largest allowed value on 64-bit
_MALLOC_TRIM_THRESHOLD = 256 * 2 ** 20


@dataclass(frozen=True)
class WorkerThreads:
    """How one Dask worker uses its share of the cores: ``tasks`` files at a time (the worker's
    Dask threads), each with ``threads`` threads in radiokit's pools, OpenCV and the FFTs.

    BLAS stays at one thread in a worker: radiokit's heavy loops are its own pools and OpenCV's,
    and OpenBLAS's threads spin when called from a worker's task thread (measured: a one-worker
    cluster with two BLAS threads used 2.1x the CPU time of the same files processed in turn;
    with one, the same time; benchmarks/README.md)."""
    tasks: int
    threads: int

    def environ(self) -> dict:
        """Environment for a worker process started for this share (read by the libraries at load)."""
        return {"RADIOKIT_THREADS": str(self.threads), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                "MKL_NUM_THREADS": "1", "MALLOC_MMAP_THRESHOLD_": str(_MALLOC_MMAP_THRESHOLD),
                "MALLOC_TRIM_THRESHOLD_": str(_MALLOC_TRIM_THRESHOLD)}


def worker_threads(cores: int, workers: int, tasks_per_worker: int = 1) -> WorkerThreads:
    """Split ``cores`` between ``workers`` workers on one machine running ``tasks_per_worker`` files
    each: at least one thread per file, never more threads in all than cores (when there are
    more files at a time than cores, one each)."""
    if cores < 1 or workers < 1 or tasks_per_worker < 1:
        raise ValueError(f"cores={cores}, workers={workers}, tasks_per_worker={tasks_per_worker}: expected >= 1")
    return WorkerThreads(tasks_per_worker, max(1, cores // (workers * tasks_per_worker)))


def _scheduler_shares(client) -> dict:
    """Each connected worker's share, from the scheduler's view: the workers of one host split the
    cores that host reports (its CPU affinity)."""
    from radiokit._threads import cores

    info = _all_workers(client)
    if not info:
        raise ValueError(f"Dask scheduler {client.scheduler.address}: no workers connected "
                         "(start some with `dask worker ADDRESS`)")
    host_cores = client.run(cores)
    per_host: dict = {}
    for addr, w in info.items():
        per_host.setdefault(w["host"], []).append(addr)
    shares = {}
    for addrs in per_host.values():
        tasks_on_host = sum(int(info[a]["nthreads"]) for a in addrs)
        n_cores = min(host_cores.get(a, 1) for a in addrs)
        for a in addrs:
            shares[a] = WorkerThreads(int(info[a]["nthreads"]), max(1, n_cores // tasks_on_host))
    return shares


def _all_workers(client) -> dict:
    try:
        return client.scheduler_info(n_workers=-1)["workers"]  # recent Dask lists 5 by default
    except TypeError:  # older Dask: no n_workers, lists them all
        return client.scheduler_info()["workers"]


def _limit_this_process(share: WorkerThreads):
    """Hold this (worker) process to ``share``: radiokit's pools (through ``RADIOKIT_THREADS``),
    OpenCV, BLAS to one thread (threadpoolctl, on the libraries loaded by then; see
    :class:`WorkerThreads`), and glibc's malloc thresholds (for workers started without
    :meth:`WorkerThreads.environ`)."""
    import ctypes
    import os

    import cv2
    import scipy.linalg  # noqa: F401  (loads scipy's BLAS, so that threadpoolctl can limit it)
    from threadpoolctl import threadpool_limits

    os.environ["RADIOKIT_THREADS"] = str(share.threads)
    cv2.setNumThreads(share.threads)
    threadpool_limits(limits=1, user_api="blas")
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, _MALLOC_MMAP_THRESHOLD)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, _MALLOC_TRIM_THRESHOLD)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc: its defaults, nothing set by Dask to undo
        pass


def process_many(paths, config: Config | None = None, *, out_root=None, scheduler=None, workers=None,
                 overwrite=False) -> list:
    """Process many experiment files in parallel on Dask, one progress bar over all.

    ``scheduler``: ``None`` starts a local cluster (processes, ``workers`` of them, default one per
    core up to the number of files, one file at a time each), an address (``tcp://host:8786``)
    connects to a running one. Each worker's threads are sized to its share of the cores
    (:func:`worker_threads`; for a scheduler, from the workers' hosts and Dask threads), so that
    the pools of correction and registration, BLAS and OpenCV do not oversubscribe the machine.
    Returns, per file, its results dict, or ``{"source": path, "error": message}`` for a file that
    failed (the others go on). Output folders are :func:`output_folders`; each is written as
    :func:`process` writes."""
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise ImportError("processing many files needs Dask: pip install 'radiokit[parallel]'") from None
    from tqdm.auto import tqdm

    from radiokit._threads import cores

    cfg = dataclasses.replace(config or Config(), progress=False)
    paths = [Path(p) for p in paths]
    outs = output_folders(paths, out_root)
    cluster = _local_cluster(workers or max(1, min(len(paths), cores()))) if scheduler is None else None
    client = Client(cluster if cluster is not None else scheduler)
    try:
        shares = _scheduler_shares(client)
        client.run(_limit_worker, shares)
        futures = {client.submit(_process_one, str(p), cfg, str(o), overwrite, shares, pure=False): i
                   for i, (p, o) in enumerate(zip(paths, outs))}
        results = [None] * len(paths)
        with tqdm(total=len(paths), desc="process", unit="file", disable=not (config or Config()).progress) as bar:
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                bar.update()
        return results
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _local_cluster(n_workers: int):
    """A local cluster of ``n_workers`` single-threaded worker processes, each started with its
    share of this machine's cores in its environment."""
    from dask.distributed import LocalCluster

    from radiokit._threads import cores

    share = worker_threads(cores(), n_workers)
    return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                        env=share.environ())


def _limit_worker(shares, dask_worker=None):
    """Run in each worker by ``client.run``: apply its share (a worker that joined later: one
    thread per Dask thread is the safe guess), and stop the worker's statistical profiler, which
    samples every thread's stack 100 times a second on cores the files need (it shows in Dask's
    dashboard only; benchmarks/README.md, "Dask, second pass")."""
    share = shares.get(dask_worker.address) if dask_worker is not None else None
    _limit_this_process(share or WorkerThreads(1, 1))
    for name in ("profile", "profile-cycle"):
        callback = getattr(dask_worker, "periodic_callbacks", {}).get(name)
        if callback is not None:
            callback.stop()
    return share.threads if share else 1


def _process_one(path, cfg, out_dir, overwrite=False, shares=None):
    if shares is not None:  # a worker that joined after client.run, or whose limits were reset
        from distributed import get_worker

        _limit_worker(shares, get_worker())
    try:
        res = process(path, cfg, out_dir=out_dir, overwrite=overwrite)
        return dict(res.results, output=str(out_dir))
    except Exception as exc:  # one bad file must not stop the others: reported in its slot
        return {"source": path, "error": f"{type(exc).__name__}: {exc}"}
