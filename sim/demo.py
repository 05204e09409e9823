"""A calibration check on a synthetic panel (the first demo; `radiokit demo` is now acquisition.demo).

An analytic side view of the paper's PVA phantom (truncated cone, cube inclusion) is squeezed
uniformly (incompressibly, no elasticity contrast yet: that needs the FEM model) at three
compression ratios, exposed on a model C7942 with planted defects, written to an experiment file
exactly as the lab writes one, and then read back, calibrated and corrected by radiokit. Every
number printed is checked against the known truth.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from sim.analytic import box_chord, cone_side_chord
from sim.detector import PanelModel

__all__ = ["phantom_line_integral", "run_demo"]

MU_BACKGROUND_PER_MM = 0.077  # 10 % w/v PVA, 0.77 /cm
MU_INCLUSION_PER_MM = 0.085  # 20 % w/v PVA, 0.85 /cm


def phantom_line_integral(shape=(2240, 2240), pixel_mm=0.05, ratio=0.0):
    """-ln(I/I0) of the PVA phantom seen from the side, its axis along the rows (top up).

    A truncated cone (bottom 40 mm, top 50 mm diameter, 60 mm high) with a 8 x 8 x 10 mm cube
    inclusion at its centre (10 mm along the axis), compressed by ``ratio`` of its height with
    volume kept (lateral stretch ``1 / sqrt(1 - ratio)``).
    """
    rows, cols = shape
    axial = 1.0 - ratio
    lateral = 1.0 / np.sqrt(axial)
    v = (np.arange(rows) - (rows - 1) / 2) * pixel_mm  # mm, up is negative row offset
    u = (np.arange(cols) - (cols - 1) / 2) * pixel_mm
    uu, vv = np.meshgrid(u, v)
    height = 60.0
    # undo the squeeze: a point of the deformed image came from (u / lateral, v / axial)
    u0, v0 = uu / lateral, vv / axial
    h0 = height / 2 - v0  # height above the bottom face (row 0 is the top)
    body = lateral * cone_side_chord(u0, h0, 20.0, 25.0, height)
    cube = lateral * box_chord(u0, v0, 8.0, 10.0, 8.0)
    return (MU_BACKGROUND_PER_MM * body + (MU_INCLUSION_PER_MM - MU_BACKGROUND_PER_MM) * cube).astype(np.float32)


def run_demo(out_dir="out/demo", *, binning=1, n_darks=10, n_flats=10, frames_per_step=2,
             ratios=(0.15, 0.20, 0.25), i0=2500.0, seed=0, progress=True) -> dict:
    """Acquire (simulated), calibrate, correct and check; write a figure and a JSON summary."""
    from tqdm.auto import tqdm

    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files
    from radiokit.io import ExperimentWriter, ImageKey, read

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    panel = PanelModel(rows=2240 // binning, cols=2240 // binning, binning=binning)
    pixel_mm = 0.05 * binning
    i0 = i0 / binning ** 2  # binning sums charge: keep the binned pixel's signal, not the ADC, at i0
    rng = np.random.default_rng(seed)
    exp_path = out / "experiment.h5"
    truths = [phantom_line_integral(panel.shape, pixel_mm, r) for r in ratios]
    timings = {}
    t = time.perf_counter()
    with ExperimentWriter(exp_path, shape=panel.shape, overwrite=True, pixel_size_mm=pixel_mm,
                          source={"voltage_kv": 60, "current_ua": 250}) as w, \
            tqdm(total=n_darks + n_flats + frames_per_step * len(ratios), desc="acquire (simulated)",
                 unit="frame", disable=not progress) as bar:
        w.set_pixel_mask(np.zeros(panel.shape, np.uint32))
        for frame in panel.dark_frames(n_darks, rng):
            w.append(frame, image_key=ImageKey.DARK)
            bar.update()
        for frame in panel.flat_frames(n_flats, i0, rng):
            w.append(frame, image_key=ImageKey.FLAT, voltage_kv=60, current_ua=250)
            bar.update()
        for step, (ratio, truth) in enumerate(zip(ratios, truths), start=1):
            for frame in panel.expose(truth, i0, frames_per_step, rng):
                w.append(frame, image_key=ImageKey.PROJECTION, step=step, ratio=ratio,
                         gap_mm=60.0 * (1 - ratio), voltage_kv=60, current_ua=250)
                bar.update()
    timings["acquire_s"] = time.perf_counter() - t

    t = time.perf_counter()
    cal = Calibration.from_experiment(exp_path)
    cal.save(out / "calibration.h5")
    timings["calibrate_s"] = time.perf_counter() - t
    summary = correct_files(exp_path, cal, out / "corrected.h5", domain="log", progress=progress, overwrite=True)
    timings["correct_s"] = summary["seconds"]
    corrected = read(out / "corrected.h5", dataset="entry/data/data").data
    import h5py
    with h5py.File(out / "corrected.h5", "r") as h5:
        steps = h5["entry/data/step"][()]

    planted = panel.truth.mask(panel.shape)
    found = cal.mask != 0
    defects = {"planted": int(planted.sum()), "found": int(found.sum()),
               "true_positive": int((planted & found).sum()), "false_positive": int((found & ~planted).sum()),
               "missed": int((planted & ~found).sum()), "defect_columns": cal.defect_columns.tolist()}
    rows = []
    for step, (ratio, truth) in enumerate(zip(ratios, truths), start=1):
        mean = corrected[steps == step].mean(axis=0)
        err = mean - truth
        inside = truth > 0.5
        # Expected noise of the step's mean: shot + read noise of the frames and of the flats.
        g = np.clip(panel.gain, 1e-3, None)
        sig = g * i0 * binning ** 2 * np.exp(-truth)
        var = (panel.counts_per_quantum * g * sig + panel.read_noise ** 2) / sig ** 2 / frames_per_step \
            + (panel.counts_per_quantum * g * g * i0 * binning ** 2 + panel.read_noise ** 2) / (g * i0 * binning ** 2) ** 2 / n_flats
        sigma = np.sqrt(var)
        ok = inside & ~planted
        rows.append({"step": step, "ratio": ratio, "max_line_integral": float(truth.max()),
                     "bias": float(err[ok].mean()), "rms_error": float(np.sqrt((err[ok] ** 2).mean())),
                     "expected_noise": float(np.sqrt((sigma[ok] ** 2).mean())),
                     "nonfinite": int((~np.isfinite(mean)).sum())})
    timings["total_s"] = time.perf_counter() - t_start
    result = {"experiment": str(exp_path), "calibration": str(out / "calibration.h5"),
              "corrected": str(out / "corrected.h5"), "frame_shape": list(panel.shape),
              "defects": defects, "steps": rows, "timings": timings,
              "correct_frames_per_second": summary["frames_per_second"]}
    _figure(out / "demo.png", panel, cal, corrected[steps == 1].mean(axis=0), truths[0],
            read(exp_path).data[n_darks + n_flats], planted, pixel_mm)
    result["figure"] = str(out / "demo.png")
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    return result


def _figure(path, panel, cal, corrected, truth, raw, planted, pixel_mm):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(15, 9.5), constrained_layout=True)
    ext = [0, raw.shape[1] * pixel_mm, raw.shape[0] * pixel_mm, 0]
    im = ax[0, 0].imshow(raw, cmap="gray", extent=ext)
    ax[0, 0].set_title("raw frame, step 1 (counts)")
    fig.colorbar(im, ax=ax[0, 0], shrink=0.8)
    im = ax[0, 1].imshow(corrected, cmap="gray", extent=ext, vmin=0, vmax=float(truth.max()) * 1.05)
    ax[0, 1].set_title("corrected: line integral -ln(I/I0)")
    fig.colorbar(im, ax=ax[0, 1], shrink=0.8)
    err = corrected - truth
    lim = float(np.percentile(np.abs(err), 99))
    im = ax[0, 2].imshow(err, cmap="RdBu_r", extent=ext, vmin=-lim, vmax=lim)
    ax[0, 2].set_title("corrected - truth (noise only)")
    fig.colorbar(im, ax=ax[0, 2], shrink=0.8)
    r = raw.shape[0] // 2
    x = np.arange(raw.shape[1]) * pixel_mm
    ax[1, 0].plot(x, corrected[r], lw=0.6, label="corrected")
    ax[1, 0].plot(x, truth[r], lw=1.2, label="truth")
    ax[1, 0].set_xlabel("mm")
    ax[1, 0].set_title("profile through the inclusion")
    ax[1, 0].legend()
    shown = np.zeros(planted.shape + (3,), np.float32)
    shown[..., 1] = planted & (cal.mask != 0)
    shown[..., 0] = (cal.mask != 0) & ~planted
    shown[..., 2] = planted & (cal.mask == 0)
    from scipy.ndimage import maximum_filter
    shown = maximum_filter(shown, size=(9, 9, 1))  # make single pixels visible
    ax[1, 1].imshow(shown, extent=ext)
    ax[1, 1].set_title("defects: green found, red false, blue missed")
    ok = (truth > 0.5) & ~planted
    ax[1, 2].hist(err[ok], bins=120, color="0.4")
    ax[1, 2].set_title("error inside the object")
    ax[1, 2].set_xlabel("line integral error")
    fig.savefig(path, dpi=80)
    plt.close(fig)
