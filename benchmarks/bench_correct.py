"""Benchmark: flat-field + log correction of C7942 frames, radiokit against the usual one-liners.

Run (about 40 s on a 2-core machine; ``--skip-stream`` for part 1 alone, about 10 s)::

    python benchmarks/bench_correct.py [--frames 100] [--reps 21] [--rounds 3] [--out DIR] [--json PATH]

The panel
---------
One synthetic 2240 x 2240 uint16 panel: a dark of ~100 counts with per-pixel offsets (4 counts
rms) and ~2 counts read noise, a smooth +-8 % gain variation with a 1 % per-pixel spread, a
~3000-count open beam with Poisson noise, two dead pixels, one under-responding pixel and one dead
column, and a projection of an attenuating sphere (transmission down to ~0.15 at its centre).
Eight darks and eight flats are simulated.

Part 1 -- one frame in memory
-----------------------------
Milliseconds per frame, median over ``--reps`` repetitions (IQR in brackets). In every repetition
each variant runs once, in a freshly shuffled order, so the noise of a shared machine hits all of
them alike; "paired" ratios are the median of the per-repetition ratios, a second opinion.

(i)   ``-np.log((raw - dark) / (flat - dark))`` with ``dark``/``flat`` from
      ``np.mean(stack, axis=0)`` of the uint16 stacks, i.e. float64: what a user writes first.
(ia)  The same one-liner with float32 ``dark``/``flat`` (shown for honesty; the target is on (i)).
(ii)  tomopy's chain (``tomopy.prep.normalize.normalize`` then ``minus_log``) written directly in
      numexpr with 2 threads and float32 dark/flat as tomopy uses: ``(raw - dark) / (flat - dark)``,
      clamp at 1e-6, ``-log(x)``. (The raw frame is fed to numexpr as uint16, saving tomopy's
      ``as_float32`` copy: slightly kinder to (ii) than tomopy itself. numexpr built without
      Intel VML, as from PyPI, computes ``log`` with scalar libm: that is most of its time.)
(iii) ``correct_frames(cal, raw, domain="log")`` of radiokit, with the calibration built once by
      ``Calibration.from_frames`` and the per-calibration kernel warmed up before timing. It does
      more than the others: it fills the defect pixels and the defect column, clamps and fills
      non-positive pixels, counts saturated ones, and never returns NaN or inf.
(iii-1t) The same with ``RADIOKIT_THREADS=1``: informative, shows what radiokit's threads buy.

Read (i)/(iii), (ia)/(iii), (ii)/(iii) as "how many times faster radiokit is". Target:
(i)/(iii) >= 4. The agreement check compares (iii) with (i) on the pixels the calibration left
valid (``mask == 0``); they must agree to float32 precision (max |diff| < 1e-4). ``from_frames``
averages robustly (it drops samples beyond 5 panel noise sigmas, against zingers), so where it
dropped a sample its dark/flat differ from ``np.mean``'s by design: those pixels are counted and
left out of the strict check, and the maximum difference including them is printed as well.

Part 2 -- streaming
-------------------
``--frames`` raw frames (1 GB for 100) are written frame by frame to one headerless ``.raw`` file
and streamed with ``radiokit.correct.correct_files([raw], cal, out.h5, domain="log")`` into a
float32 HDF5 file, in fresh subprocesses (``--_stream N``, internal), alternating a short
(``--short-frames``, 20; the ``n=`` raw hint) and the long stack for ``--rounds`` rounds. The
calibration reaches the children through ``cal.save`` / ``Calibration.load``. Each child reports
as JSON its throughput (``correct_files``' own ``frames_per_second``) and its peak resident memory.
The peak is the child's own ``VmHWM`` from ``/proc/self/status``; ``getrusage(RUSAGE_SELF).ru_maxrss``
is printed too but cannot be used, because on Linux exec carries the spawning process's peak into
the child's ``ru_maxrss`` (every child would report this benchmark's own peak). Targets: median
>= 40 frames/s over the long runs, and a long-stack peak within 30 MiB (about 1.5 float32 frames)
of the short-stack peak, i.e. memory independent of stack length. Every output is checked: n
frames, finite, last frame equal to correcting the same raw frame in memory.

A last child (``--_split N``) runs the same loop ``correct_files`` runs from its public pieces
(``open_frames``, ``correct_frames(cal, raw, out=...)``, ``StackWriter.append``) with a timer around
each stage, and writes each corrected frame a second time to a plain file as a baseline: if the
HDF5 write is slow and the plain write is as slow, the time is the machine's page cache or disk,
not radiokit's.

Caveats: when the frame count is known (it is for ``correct_files``), ``StackWriter`` writes
each frame's preallocated chunk with ``O_DIRECT``, past the page cache (see
``radiokit.io._write._DirectFrames``); HDF5 metadata and the plain-file baseline still go through
the page cache. On a VM, growing the page cache into memory the guest has not touched recently
costs about 3 ms per MiB (measured here: 17 frames/s buffered against 125 frames/s direct, to the
same disk), so the baseline is often slower than the HDF5 write and varies from round to round. The
raw stack cycles through four independently simulated projections (simulating 100 Poisson frames
would take longer than the whole benchmark); the content does not change the work done.
Temporary files go to a fresh directory (under ``--out`` if given) that is removed at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

SHAPE = (2240, 2240)
DARK_LEVEL = 100.0
DARK_SPREAD = 4.0
READ_NOISE = 2.0
I0 = 3000.0
N_CAL = 8
N_DISTINCT_PROJECTIONS = 4
DEAD_PIXELS = ((300, 700), (1500, 1900))
UNDER_PIXELS = ((1000, 1234),)
DEFECT_COLUMN = 1777
SPEED_TARGET = 4.0
FPS_TARGET = 40.0
RSS_TOLERANCE = 30 * 2**20
AGREE_ATOL = 1e-4
MiB = 2**20


# -- synthetic panel ---------------------------------------------------------------------------
def make_panel(seed=0):
    """Fixed properties of the simulated panel: per-pixel dark offset, gain, and the object."""
    rng = np.random.default_rng(seed)
    rows, cols = SHAPE
    y = np.linspace(-1, 1, rows, dtype=np.float32)[:, None]
    x = np.linspace(-1, 1, cols, dtype=np.float32)[None, :]
    smooth = (
        0.5 * np.cos(1.3 * np.pi * x + 0.4) * np.cos(0.9 * np.pi * y - 0.2)
        + 0.5 * np.exp(-((x - 0.3) ** 2 + (y + 0.2) ** 2) / 0.5)
        - 0.25
    )
    gain = (1 + 0.08 * smooth / np.abs(smooth).max()) * (1 + 0.01 * rng.standard_normal(SHAPE, np.float32))
    for r, c in DEAD_PIXELS:
        gain[r, c] = 0.0
    for r, c in UNDER_PIXELS:
        gain[r, c] = 0.4
    gain[:, DEFECT_COLUMN] = 0.02
    dark = (DARK_LEVEL + DARK_SPREAD * rng.standard_normal(SHAPE, np.float32)).astype(np.float32)
    # An attenuating sphere seen as a disc: transmission exp(-mu * chord), 0.15 at the centre.
    r2 = ((x - 0.05) ** 2 + (y + 0.03) ** 2) / 0.6**2
    transmission = np.exp(-1.9 * np.sqrt(np.clip(1 - r2, 0, None))).astype(np.float32)
    return {"gain": gain.astype(np.float32), "dark": dark, "transmission": transmission}


def simulate(panel, rng, transmission=None, beam=True) -> np.ndarray:
    """One raw uint16 frame: dark + Poisson(gain * I0 * T) + read noise, clipped to 12 bits."""
    frame = panel["dark"] + READ_NOISE * rng.standard_normal(SHAPE, np.float32)
    if beam:
        mean = panel["gain"] * np.float32(I0)
        if transmission is not None:
            mean = mean * transmission
        frame += rng.poisson(mean).astype(np.float32)
    return np.clip(np.rint(frame), 0, 4095).astype(np.uint16)


# -- part 1: one frame -------------------------------------------------------------------------
def _interleaved(variants, reps, seed, cpu=None) -> dict:
    """Seconds per call of each variant over ``reps`` rounds, each round in a fresh shuffled order
    (the machine is shared: a slow moment falls on all variants alike, not on one). ``cpu``, a
    dict, also receives each call's CPU time of this process (all its threads): on a loaded
    machine wall time counts the moments a thread waited for a core, CPU time only the work."""
    times = {name: [] for name in variants}
    if cpu is not None:
        cpu.update({name: [] for name in variants})
    order = list(variants)
    shuffler = random.Random(seed)
    for _ in range(reps):
        shuffler.shuffle(order)
        for name in order:
            c = time.process_time()
            t = time.perf_counter()
            variants[name]()
            times[name].append(time.perf_counter() - t)
            if cpu is not None:
                cpu[name].append(time.process_time() - c)
    return times


def _median_ms(ts):
    return 1e3 * statistics.median(ts)


def bench_frame(reps: int, seed: int = 1):
    import numexpr as ne

    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames

    panel = make_panel(seed)
    rng = np.random.default_rng(seed + 1)
    t0 = time.perf_counter()
    darks = np.stack([simulate(panel, rng, beam=False) for _ in range(N_CAL)])
    flats = np.stack([simulate(panel, rng) for _ in range(N_CAL)])
    raw = simulate(panel, rng, panel["transmission"])
    t_sim = time.perf_counter() - t0

    dark64 = np.mean(darks, axis=0)  # what a user gets: float64
    flat64 = np.mean(flats, axis=0)
    dark32, flat32 = dark64.astype(np.float32), flat64.astype(np.float32)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = Calibration.from_frames(darks, flats)
    t_cal = time.perf_counter() - t0
    del darks, flats

    ne.set_num_threads(2)

    def naive64():
        with np.errstate(divide="ignore", invalid="ignore"):
            return -np.log((raw - dark64) / (flat64 - dark64))

    def naive32():
        with np.errstate(divide="ignore", invalid="ignore"):
            return -np.log((raw - dark32) / (flat32 - dark32))

    def tomopy_ne():
        x = ne.evaluate("(raw - dark) / (flat - dark)", local_dict={"raw": raw, "dark": dark32, "flat": flat32})
        ne.evaluate("where(x > 1e-6, x, 1e-6)", local_dict={"x": x}, out=x)
        return ne.evaluate("-log(x)", local_dict={"x": x}, out=x)

    def radiokit_correct():
        return correct_frames(cal, raw, domain="log")

    def radiokit_one_thread():  # informative: how much radiokit's threads buy on this machine
        old = os.environ.get("RADIOKIT_THREADS")
        os.environ["RADIOKIT_THREADS"] = "1"
        try:
            return correct_frames(cal, raw, domain="log")
        finally:
            if old is None:
                del os.environ["RADIOKIT_THREADS"]
            else:
                os.environ["RADIOKIT_THREADS"] = old

    variants = {
        "(i)": naive64,
        "(ia)": naive32,
        "(ii)": tomopy_ne,
        "(iii)": radiokit_correct,
        "(iii-1t)": radiokit_one_thread,
    }
    labels = {
        "(i)": "numpy one-liner, float64 dark/flat (np.mean)",
        "(ia)": "numpy one-liner, float32 dark/flat",
        "(ii)": "tomopy-style numexpr chain, 2 threads, float32",
        "(iii)": "radiokit correct_frames(cal, raw, 'log')",
        "(iii-1t)": "the same with RADIOKIT_THREADS=1 (informative)",
    }
    outputs = {}
    for name, fn in variants.items():  # warm-up: page-faults, numexpr compile cache, radiokit kernel
        outputs[name] = fn()
        fn()
    times = _interleaved(variants, reps, seed)
    ms = {name: _median_ms(ts) for name, ts in times.items()}
    spread = {
        name: (1e3 * float(np.percentile(ts, 25)), 1e3 * float(np.percentile(ts, 75))) for name, ts in times.items()
    }
    others = ("(i)", "(ia)", "(ii)", "(iii-1t)")
    ratios = {name: ms[name] / ms["(iii)"] for name in others}
    paired = {name: statistics.median(a / b for a, b in zip(times[name], times["(iii)"])) for name in others}

    # Agreement of (iii) with (i) on pixels the calibration left valid.
    ref, got = outputs["(i)"], outputs["(iii)"]
    valid = (cal.mask == 0) & np.isfinite(ref)
    diff = np.abs(got.astype(np.float64) - ref)
    # Where the robust average dropped a sample its dark/flat are not np.mean's (by design).
    robust_differs = (np.abs(cal.dark - dark64) > 1e-3) | (np.abs(cal.flat - flat64) > 1e-2)
    strict = valid & ~robust_differs
    agree = {
        "valid_pixels": int(valid.sum()),
        "defect_pixels_excluded": int((cal.mask != 0).sum()),
        "robust_average_differs_pixels": int((valid & robust_differs).sum()),
        "max_abs_diff_valid": float(diff[valid].max()),
        "max_abs_diff_strict": float(diff[strict].max()),
        "p99_999_abs_diff_valid": float(np.percentile(diff[valid], 99.999)),
        "pixels_over_atol_valid": int((diff[valid] >= AGREE_ATOL).sum()),
        "atol": AGREE_ATOL,
        "output_finite": bool(np.isfinite(got).all()),
        "naive_nonfinite_pixels": int((~np.isfinite(ref)).sum()),
    }
    agree["pass"] = agree["max_abs_diff_strict"] < AGREE_ATOL and agree["output_finite"]
    result = {
        "labels": labels,
        "ms_median": ms,
        "ms_iqr": spread,
        "reps": reps,
        "ratio_of_medians": ratios,
        "median_of_paired_ratios": paired,
        "target": f"(iii) at least {SPEED_TARGET:g}x faster than (i)",
        "speed_pass": ratios["(i)"] >= SPEED_TARGET,
        "agreement": agree,
        "simulate_seconds": t_sim,
        "from_frames_seconds": t_cal,
        "calibration": repr(cal),
    }
    return result, cal, panel


# -- part 1b: a realistic frame against a fused OpenCV pass ------------------------------------
N_HOT = 300  # over-responding pixels of the realistic calibration
N_SATURATED = 200  # raw pixels at the ADC's top in the realistic frame
N_BELOW_DARK = 500  # raw pixels below the dark in the realistic frame
_BLOCK_ROWS = 128  # 128 x 2240 float32 = 1.1 MB: the OpenCV floor's fastest block on 2240-wide frames


def realistic(panel, rng):
    """The lab's frame: a calibration with a dead column and ``N_HOT`` hot pixels, and a raw
    frame with ``N_SATURATED`` saturated pixels and ``N_BELOW_DARK`` pixels below the dark."""
    hot = dict(panel, gain=panel["gain"].copy())
    idx = rng.choice(SHAPE[0] * SHAPE[1], N_HOT + N_SATURATED + N_BELOW_DARK, replace=False)
    hot["gain"].ravel()[idx[:N_HOT]] = 1.8
    darks = np.stack([simulate(hot, rng, beam=False) for _ in range(N_CAL)])
    flats = np.stack([simulate(hot, rng) for _ in range(N_CAL)])
    raw = simulate(hot, rng, hot["transmission"])
    raw.ravel()[idx[N_HOT : N_HOT + N_SATURATED]] = 4095
    below = idx[N_HOT + N_SATURATED :]
    raw.ravel()[below] = np.clip(hot["dark"].ravel()[below] - 5, 0, None).astype(np.uint16)
    return darks, flats, raw


def opencv_fused(raw, dark, log_i0, out, threads):
    """The floor: ``ln(flat - dark) - ln(raw - dark)`` with OpenCV, subtract-log-subtract fused
    per 128-row block (in cache) and the blocks split over ``threads`` threads as radiokit splits
    them; no clamping, no repairs."""
    import cv2

    from radiokit._threads import pool as _pool

    rows, cols = raw.shape

    def part(r0, r1):
        tmp = np.empty((_BLOCK_ROWS, cols), np.float32)
        for a in range(r0, r1, _BLOCK_ROWS):
            b = min(a + _BLOCK_ROWS, r1)
            t = tmp[: b - a]
            cv2.subtract(raw[a:b], dark[a:b], t, dtype=cv2.CV_32F)
            cv2.log(t, t)
            cv2.subtract(log_i0[a:b], t, out[a:b])

    nt = min(threads, max(1, rows // _BLOCK_ROWS))
    edges = [(rows * i // nt) // _BLOCK_ROWS * _BLOCK_ROWS for i in range(nt)] + [rows]
    if nt == 1:
        part(0, rows)
    else:
        list(_pool().map(lambda i: part(edges[i], edges[i + 1]), range(nt)))
    return out


def bench_realistic(reps: int, seed: int = 3) -> dict:
    """radiokit's correction of the clean and of the realistic frame, and the fused OpenCV pass on
    each, interleaved in one run (median ms); the repairs should cost almost nothing."""
    import cv2

    from radiokit._threads import threads as _threads
    from radiokit.calibrate import Calibration
    from radiokit.correct import CorrectionKernel, correct_frames

    cv2.setNumThreads(1)  # the blocks are split over radiokit's threads, as radiokit's are
    panel = make_panel(seed)
    rng = np.random.default_rng(seed + 1)
    cases = {}
    for name in ("clean", "realistic"):
        if name == "clean":
            darks = np.stack([simulate(panel, rng, beam=False) for _ in range(N_CAL)])
            flats = np.stack([simulate(panel, rng) for _ in range(N_CAL)])
            raw = simulate(panel, rng, panel["transmission"])
        else:
            darks, flats, raw = realistic(panel, rng)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = Calibration.from_frames(darks, flats)
        k = CorrectionKernel.of(cal)
        cases[name] = (cal, raw, np.ascontiguousarray(k.dark, np.float32), k.log_i0.astype(np.float32))
    out = np.empty(SHAPE, np.float32)
    variants = {}
    for name, (cal, raw, dark, log_i0) in cases.items():
        variants[f"radiokit {name}"] = lambda c=cal, r=raw: correct_frames(c, r, domain="log", out=out)
        variants[f"opencv {name}"] = lambda r=raw, d=dark, li=log_i0: opencv_fused(r, d, li, out, _threads())
    for fn in variants.values():
        fn()
        fn()
    cpu = {}
    times = _interleaved(variants, reps, seed, cpu)
    ms = {name: _median_ms(ts) for name, ts in times.items()}
    cpu_ms = {name: _median_ms(ts) for name, ts in cpu.items()}
    cal, raw = cases["realistic"][:2]
    _, report = correct_frames(cal, raw, domain="log", return_report=True)
    ratio = {name: ms[f"radiokit {name}"] / ms[f"opencv {name}"] for name in cases}
    paired = {
        name: statistics.median(a / b for a, b in zip(times[f"radiokit {name}"], times[f"opencv {name}"]))
        for name in cases
    }
    cpu_ratio = {name: cpu_ms[f"radiokit {name}"] / cpu_ms[f"opencv {name}"] for name in cases}
    return {
        "ms_median": ms,
        "radiokit_over_opencv": ratio,
        "paired": paired,
        "reps": reps,
        "cpu_ms_median": cpu_ms,
        "cpu_ratio": cpu_ratio,
        "load_average": os.getloadavg(),
        "repairs": {
            "defects_filled": int(report.defects_filled),
            "saturated": int(report.saturated.sum()),
            "nonpositive": int(report.nonpositive.sum()),
        },
        "target": "realistic frame: radiokit within 10 % of the fused OpenCV pass",
        "pass": ratio["realistic"] <= 1.10,
    }


def print_realistic(r):
    rep = r["repairs"]
    print(
        f"Part 1b: the realistic frame ({rep['defects_filled']} defect pixels filled: a dead column and "
        f"{N_HOT} hot pixels; {rep['saturated']} saturated, {rep['nonpositive']} below the dark) and the clean one, "
        f"radiokit against a fused OpenCV subtract-log-subtract pass (median of {r['reps']} interleaved repetitions)"
    )
    for name in ("clean", "realistic"):
        print(
            f"  {name:9s} radiokit {r['ms_median'][f'radiokit {name}']:6.2f} ms, OpenCV {r['ms_median'][f'opencv {name}']:6.2f} ms"
            f" -> ratio {r['radiokit_over_opencv'][name]:.3f} [paired {r['paired'][name]:.3f}];"
            f" CPU time {r['cpu_ms_median'][f'radiokit {name}']:6.2f} / {r['cpu_ms_median'][f'opencv {name}']:6.2f} ms"
            f" -> {r['cpu_ratio'][name]:.3f}"
        )
    print(f"  load average {r['load_average'][0]:.1f} at the end (2 CPUs)")
    print(f"  target: {r['target']} -> {'PASS' if r['pass'] else 'FAIL'}")


# -- part 2: streaming in fresh subprocesses ---------------------------------------------------
def write_raw_stack(path: Path, panel, n: int, seed: int = 7) -> float:
    """Write ``n`` frames to a headerless little-endian uint16 file, one frame at a time."""
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    distinct = [simulate(panel, rng, panel["transmission"]).astype("<u2") for _ in range(N_DISTINCT_PROJECTIONS)]
    with open(path, "wb") as fh:
        for i in range(n):
            fh.write(memoryview(distinct[i % len(distinct)]).cast("B"))
    return time.perf_counter() - t0


def _proc_status_bytes(key: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _ru_maxrss_bytes() -> int:
    # Linux reports KiB, macOS bytes.
    ru = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(ru) if sys.platform == "darwin" else int(ru) * 1024


def memory_now() -> dict:
    """Current and peak resident memory of this process.

    ``peak`` is ``VmHWM`` (the high-water mark of this process's own address space) where Linux
    provides it. ``ru_maxrss`` is printed too but is not used for the verdict: on Linux, exec
    carries the spawning process's high-water mark into the child's ``ru_maxrss``, so a child of
    a big parent reports the parent's peak.
    """
    ru = _ru_maxrss_bytes()
    hwm = _proc_status_bytes("VmHWM")
    return {"rss": _proc_status_bytes("VmRSS"), "peak": hwm if hwm is not None else ru, "ru_maxrss": ru}


#: the stack's geometry: its size is also 4x as many 2x2-binned frames, so the reader needs it named
RAW_PRESET = "c7942"


def child_stream(n: int, raw_path: str, cal_path: str, out_path: str) -> dict:
    """Internal mode: stream ``n`` frames through correct_files and report peak memory."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files
    from radiokit.io import open_frames

    cal = Calibration.load(cal_path)
    with open_frames(raw_path, preset=RAW_PRESET) as src:
        total = len(src)
    before = memory_now()
    hints = {"preset": RAW_PRESET} | ({"n": n} if n < total else {})
    t0 = time.perf_counter()
    summary = correct_files([raw_path], cal, out_path, domain="log", progress=False, **hints)
    wall = time.perf_counter() - t0
    after = memory_now()
    return {
        "frames": summary["frames"],
        "seconds": summary["seconds"],
        "wall_seconds": wall,
        "fps": summary["frames_per_second"],
        "peak_rss_bytes": after["peak"],
        "ru_maxrss_bytes": after["ru_maxrss"],
        "rss_before_stream_bytes": before["rss"],
        "peak_rss_before_stream_bytes": before["peak"],
        "nonpositive": summary["nonpositive"],
        "saturated": summary["saturated"],
        "defects_filled_per_frame": summary["defects_filled_per_frame"],
    }


def child_split(n: int, raw_path: str, cal_path: str, out_path: str) -> dict:
    """Internal mode: the correct_files loop with a timer around each stage, and as a baseline
    for the HDF5 write the same frame written to a plain file right after it."""
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_frames
    from radiokit.io import StackWriter, open_frames

    cal = Calibration.load(cal_path)
    frame = np.empty(cal.shape, np.float32)
    t_read = t_corr = t_write = t_plain = 0.0
    plain_path = Path(out_path).with_suffix(".bin")
    with (
        open_frames(raw_path, preset=RAW_PRESET, n=n) as src,
        open(plain_path, "wb") as plain,
        StackWriter(out_path, cal.shape, np.float32, meta={"domain": "log"}, n_frames=n) as w,
    ):
        direct = bool(w._direct)
        correct_frames(cal, src[0], domain="log", out=frame)  # build the kernel outside the timers
        for i in range(n):
            a = time.perf_counter()
            raw = src[i]
            b = time.perf_counter()
            correct_frames(cal, raw, domain="log", out=frame)
            c = time.perf_counter()
            w.append(
                frame, source_index=np.int32(0), frame_index=np.int32(i), saturated=np.int64(0), nonpositive=np.int64(0)
            )
            d = time.perf_counter()
            plain.write(memoryview(frame).cast("B"))
            e = time.perf_counter()
            t_read += b - a
            t_corr += c - b
            t_write += d - c
            t_plain += e - d
    plain_path.unlink()
    ms = lambda t: 1e3 * t / n
    total = t_read + t_corr + t_write
    return {
        "frames": n,
        "ms_per_frame": {
            "read": ms(t_read),
            "correct": ms(t_corr),
            "write_hdf5": ms(t_write),
            "total": ms(total),
            "plain_write_baseline": ms(t_plain),
        },
        "fps": n / total,
        "fps_without_write": n / (t_read + t_corr),
        "direct_io": direct,
    }


def run_child(mode: str, n: int, raw: Path, cal: Path, out: Path) -> dict:
    cmd = [
        sys.executable,
        os.path.abspath(__file__),
        f"--_{mode}",
        str(n),
        "--_raw",
        str(raw),
        "--_cal",
        str(cal),
        "--_h5",
        str(out),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"child {mode} {n} failed ({proc.returncode}):\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def check_output(h5_path: Path, n: int, cal, raw_path: Path) -> dict:
    """The streamed file holds n frames, finite, equal to correcting the same raw frame in memory."""
    import h5py

    from radiokit.correct import correct_frames
    from radiokit.io import open_frames

    with h5py.File(h5_path, "r") as h5:
        ds = h5["entry/data/data"]
        shape = ds.shape
        last = ds[n - 1]
    with open_frames(raw_path, preset=RAW_PRESET) as src:
        expect = correct_frames(cal, src[n - 1], domain="log")
    return {
        "shape": list(shape),
        "ok": shape == (n,) + cal.shape and bool(np.isfinite(last).all()) and bool(np.array_equal(last, expect)),
    }


def bench_stream(cal, panel, frames: int, short: int, rounds: int, base: Path) -> dict:
    raw_path = base / "stack.raw"
    cal_path = base / "calibration.h5"
    cal.save(cal_path)
    t_write = write_raw_stack(raw_path, panel, frames)
    res = {
        "raw_file_bytes": raw_path.stat().st_size,
        "write_raw_seconds": t_write,
        "rounds": rounds,
        "parent_ru_maxrss_bytes": _ru_maxrss_bytes(),
        "runs": {str(short): [], str(frames): []},
    }
    for _ in range(rounds):  # short and long alternate, so that machine noise hits both
        for n in (short, frames):
            out = base / f"corrected_{n}.h5"
            r = run_child("stream", n, raw_path, cal_path, out)
            r["output_check"] = check_output(out, n, cal, raw_path)
            out.unlink()
            res["runs"][str(n)].append(r)
    out = base / "split.h5"
    res["split"] = run_child("split", frames, raw_path, cal_path, out)
    out.unlink()
    peak = {n: max(r["peak_rss_bytes"] for r in runs) for n, runs in res["runs"].items()}
    res["peak_rss_bytes"] = peak
    res["rss_difference_bytes"] = peak[str(frames)] - peak[str(short)]
    res["rss_tolerance_bytes"] = RSS_TOLERANCE
    res["rss_pass"] = res["rss_difference_bytes"] <= RSS_TOLERANCE
    res["fps_median"] = {n: statistics.median(r["fps"] for r in runs) for n, runs in res["runs"].items()}
    res["fps"] = res["fps_median"][str(frames)]
    res["fps_target"] = FPS_TARGET
    res["fps_pass"] = res["fps"] >= FPS_TARGET
    res["outputs_ok"] = all(r["output_check"]["ok"] for runs in res["runs"].values() for r in runs)
    return res


# -- report ------------------------------------------------------------------------------------
def print_frame(r):
    print(
        f"Part 1: one {SHAPE[0]}x{SHAPE[1]} uint16 frame, log domain "
        f"(median of {r['reps']} interleaved repetitions; IQR in brackets)"
    )
    for name, label in r["labels"].items():
        lo, hi = r["ms_iqr"][name]
        ratio = r["ratio_of_medians"].get(name)
        pr = r["median_of_paired_ratios"].get(name)
        extra = (
            ""
            if ratio is None
            else (
                f"   (iii) is {ratio:5.2f}x faster [paired {pr:.2f}x]"
                if name != "(iii-1t)"
                else f"   2 threads vs 1: {ratio:.2f}x [paired {pr:.2f}x]"
            )
        )
        print(f"  {name:8s} {label:48s} {r['ms_median'][name]:8.2f} ms  [{lo:6.2f}-{hi:6.2f}]{extra}")
    verdict = "PASS" if r["speed_pass"] else "FAIL"
    print(f"  target: {r['target']}: (i)/(iii) = {r['ratio_of_medians']['(i)']:.2f}x -> {verdict}")
    a = r["agreement"]
    print(
        f"  agreement (iii) vs (i) on {a['valid_pixels']} valid pixels ({a['defect_pixels_excluded']} defect "
        f"pixels excluded; (i) is NaN/inf at {a['naive_nonfinite_pixels']} pixels, (iii) at none: {a['output_finite']}):"
    )
    print(
        f"    max |diff| = {a['max_abs_diff_strict']:.3g} where dark/flat equal np.mean's "
        f"(robust average dropped a sample at {a['robust_average_differs_pixels']} pixels; with them: "
        f"max {a['max_abs_diff_valid']:.3g}, {a['pixels_over_atol_valid']} pixels >= {a['atol']:g}) "
        f"-> {'PASS' if a['pass'] else 'FAIL'} (< {a['atol']:g})"
    )


def print_stream(s, frames, short):
    print(
        f"Part 2: streaming a headerless raw stack ({s['raw_file_bytes'] / 1e9:.2f} GB for {frames} frames, "
        f"written in {s['write_raw_seconds']:.1f} s) through correct_files(..., domain='log') into HDF5, "
        f"in fresh subprocesses, {s['rounds']} round(s) alternating {short} and {frames} frames"
    )
    for n in (short, frames):
        for i, r in enumerate(s["runs"][str(n)]):
            print(
                f"  {n:4d} frames, round {i + 1}: {r['fps']:6.1f} frames/s ({r['seconds']:5.2f} s), peak RSS "
                f"{r['peak_rss_bytes'] / MiB:6.1f} MiB (RSS before streaming {r['rss_before_stream_bytes'] / MiB:.1f} "
                f"MiB; ru_maxrss {r['ru_maxrss_bytes'] / MiB:.1f} MiB), output {'ok' if r['output_check']['ok'] else 'WRONG'}"
            )
    print(
        f"  (ru_maxrss is not used: exec hands the parent's peak, {s['parent_ru_maxrss_bytes'] / MiB:.0f} MiB here, "
        "to the child's ru_maxrss on Linux; peak RSS is the child's own VmHWM)"
    )
    print(
        f"  throughput target >= {FPS_TARGET:g} frames/s: median {s['fps']:.1f} frames/s over {frames}-frame runs -> "
        f"{'PASS' if s['fps_pass'] else 'FAIL'}"
    )
    pk = s["peak_rss_bytes"]
    print(
        f"  peak RSS {frames} frames {pk[str(frames)] / MiB:.1f} MiB - {short} frames {pk[str(short)] / MiB:.1f} MiB "
        f"= {s['rss_difference_bytes'] / MiB:+.1f} MiB (tolerance {RSS_TOLERANCE / MiB:.0f} MiB; one float32 frame "
        f"is {SHAPE[0] * SHAPE[1] * 4 / MiB:.1f} MiB) -> {'PASS' if s['rss_pass'] else 'FAIL'}"
    )
    sp = s["split"]["ms_per_frame"]
    print(
        f"  where the time goes ({s['split']['frames']} frames, same loop with timers): read {sp['read']:.1f} ms, "
        f"correct {sp['correct']:.1f} ms, write HDF5 {sp['write_hdf5']:.1f} ms ({'O_DIRECT' if s['split'].get('direct_io') else 'page cache'}) = {sp['total']:.1f} ms/frame "
        f"({s['split']['fps']:.1f} frames/s; {s['split']['fps_without_write']:.0f} frames/s without the write). "
        f"Baseline: the same 19 MiB written to a plain file through the page cache took {sp['plain_write_baseline']:.1f} ms/frame"
    )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=100, help="frames of the long streamed stack (default 100)")
    p.add_argument("--short-frames", type=int, default=20, help="frames of the short streamed stack (default 20)")
    p.add_argument("--reps", type=int, default=21, help="interleaved repetitions per variant (default 21)")
    p.add_argument("--out", type=Path, default=None, help="directory for the temporary files (default: system temp)")
    p.add_argument("--json", type=Path, default=None, help="also write every number to this JSON file")
    p.add_argument("--rounds", type=int, default=3, help="streaming rounds, each a short and a long run (default 3)")
    p.add_argument("--skip-stream", action="store_true", help="only part 1")
    p.add_argument("--realistic-only", action="store_true", help="only part 1b (the realistic frame against OpenCV)")
    for hidden in ("--_stream", "--_split"):
        p.add_argument(hidden, type=int, default=None, help=argparse.SUPPRESS)
    for hidden in ("--_raw", "--_cal", "--_h5"):
        p.add_argument(hidden, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args._stream is not None:
        print(json.dumps(child_stream(args._stream, args._raw, args._cal, args._h5)))
        return 0
    if args._split is not None:
        print(json.dumps(child_split(args._split, args._raw, args._cal, args._h5)))
        return 0
    if args.short_frames >= args.frames:
        p.error("--short-frames must be smaller than --frames")

    import numexpr

    from radiokit._threads import threads as _threads
    from radiokit._version import __version__

    t_start = time.perf_counter()
    env = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numexpr": numexpr.__version__,
        "radiokit": __version__,
        "cpu_count": os.cpu_count(),
        "radiokit_threads": _threads(),
        "machine": platform.machine(),
    }
    print(
        f"radiokit {env['radiokit']}, numpy {env['numpy']}, numexpr {env['numexpr']}, "
        f"{env['cpu_count']} CPUs, radiokit threads {env['radiokit_threads']}"
    )
    if args.realistic_only:
        real = bench_realistic(args.reps)
        print_realistic(real)
        if args.json:
            args.json.write_text(json.dumps({"environment": env, "realistic": real}, indent=1))
        return 0 if real["pass"] else 1
    frame, cal, panel = bench_frame(args.reps)
    print(
        f"  (simulated {2 * N_CAL + 1} frames in {frame['simulate_seconds']:.1f} s; "
        f"Calibration.from_frames({N_CAL} darks, {N_CAL} flats) took {frame['from_frames_seconds']:.1f} s; {frame['calibration']})"
    )
    print_frame(frame)
    real = bench_realistic(args.reps)
    print_realistic(real)
    result = {"environment": env, "frame": frame, "realistic": real}
    if not args.skip_stream:
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
        base = Path(tempfile.mkdtemp(prefix="radiokit-bench-", dir=args.out))
        try:
            stream = bench_stream(cal, panel, args.frames, args.short_frames, args.rounds, base)
        finally:
            shutil.rmtree(base, ignore_errors=True)
        print_stream(stream, args.frames, args.short_frames)
        result["stream"] = stream
    result["total_seconds"] = time.perf_counter() - t_start
    passes = [frame["speed_pass"], frame["agreement"]["pass"], real["pass"]]
    if "stream" in result:
        passes += [result["stream"]["fps_pass"], result["stream"]["rss_pass"], result["stream"]["outputs_ok"]]
    result["all_pass"] = all(passes)
    print(
        f"Overall: {'PASS' if result['all_pass'] else 'FAIL'} ({sum(passes)}/{len(passes)} targets met) "
        f"in {result['total_seconds']:.0f} s"
    )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2, default=str))
        print(f"numbers written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
