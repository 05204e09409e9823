"""Acquisition: what writing and bookkeeping cost per frame in a compression series.

Run::

    python benchmarks/bench_acquire.py [--frames 5] [--binning 1] [--out out/bench_acquire]

A 3-step x ``--frames`` series (plus as many darks and flats) at 2240 x 2240 (``--binning 1``)
against the emulated devices: the L8121 emulator on a pseudo-terminal driven through pyserial,
``SimDetector`` and ``SimFrame`` on a virtual bench (a 10 mm block, so the finite-element part
is quick). For every frame the protocol times what it adds after the detector hands the frame
over: appending it to the experiment file with its metadata, flushing, the progress bar, the
beam-monitor bookkeeping. Side by side, in the same run, the bare minimum: the same frames
written with plain h5py into a chunked dataset, one flush per frame.

Target (issue 5): median per-frame overhead <= 50 ms. Ratios against the bare write are what
to compare across machines; this one is shared and noisy.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def bare_h5(frames, path):
    import h5py

    times = []
    with h5py.File(path, "w") as h5:
        ds = h5.create_dataset(
            "data",
            shape=(0,) + frames[0].shape,
            maxshape=(None,) + frames[0].shape,
            chunks=(1,) + frames[0].shape,
            dtype=np.uint16,
        )
        for i, f in enumerate(frames):
            t = time.perf_counter()
            ds.resize(i + 1, axis=0)
            ds[i] = f
            h5.flush()
            times.append(time.perf_counter() - t)
    return times


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=5, help="frames per step, and darks and flats (default 5)")
    ap.add_argument("--binning", type=int, default=1, choices=[1, 2, 4])
    ap.add_argument("--out", type=Path, default=Path("out/bench_acquire"))
    args = ap.parse_args(argv)
    from acquisition.protocols import load_protocol, run
    from sim.scene import Exposure, block_scene

    args.out.mkdir(parents=True, exist_ok=True)
    scene = block_scene(size_mm=10.0)
    scene.detector.binning = args.binning
    # 2500 counts per read-out pixel at the protocol's 60 kV, 250 uA, whatever the binning (a
    # binned pixel sums binning^2 pixels' charge): the frames this bench has always written
    scene.exposure = Exposure(2500.0 / args.binning**2, 60.0, 250.0)
    tmp = Path(tempfile.mkdtemp(prefix="bench-acquire-", dir=args.out))
    p = load_protocol(
        {
            "output": str(tmp / "series.h5"),
            "name": "bench",
            "source": {"voltage_kv": 60, "current_ua": 250, "poll_s": 0.25},
            "detector": {"kind": "sim"},
            "frame": {"kind": "sim", "initial_height_mm": 10.0},
            "series": {
                "darks": args.frames,
                "flats": args.frames,
                "frames_per_step": args.frames,
                "steps": [0.15, 0.20, 0.25],
                "settle_s": 0.0,
            },
            "sim": {"scene": scene.to_toml(), "warmup_s": 0.5, "ramp_s": 0.2, "binning": args.binning},
        }
    )
    t = time.perf_counter()
    res = run(p, sim=True, progress=False)
    wall = time.perf_counter() - t
    oh = np.array(res.per_frame_overhead_s) * 1000
    import h5py

    with h5py.File(res.output, "r") as h5:
        frames = [h5["entry/instrument/detector/data"][i] for i in range(min(len(oh), 10))]
        shape = h5["entry/instrument/detector/data"].shape
    base = np.array(bare_h5(frames * (len(oh) // len(frames) + 1), tmp / "bare.h5")[: len(oh)]) * 1000
    med, p95, bmed = float(np.median(oh)), float(np.percentile(oh, 95)), float(np.median(base))
    print(
        f"series: {shape[0]} frames of {shape[1]} x {shape[2]} in {wall:.1f} s "
        f"(X-rays on {res.beam_on_s:.1f} s, rendering and the source's ramps included)"
    )
    print(
        f"  per-frame overhead (append + metadata + flush + bookkeeping): median {med:.1f} ms, p95 {p95:.1f} ms, "
        f"max {oh.max():.1f} ms"
    )
    print(
        f"  bare h5py write + flush of the same frames:                     median {bmed:.1f} ms "
        f"(protocol / bare = {med / bmed:.2f})"
    )
    ok = med <= 50.0
    print(f"{'PASS' if ok else 'FAIL'}  median per-frame overhead <= 50 ms: {med:.1f} ms")
    (args.out / "bench_acquire.json").write_text(
        json.dumps(
            {
                "frames": int(shape[0]),
                "shape": list(shape[1:]),
                "wall_s": wall,
                "overhead_ms": oh.tolist(),
                "bare_ms": base.tolist(),
                "median_ms": med,
                "p95_ms": p95,
                "bare_median_ms": bmed,
            },
            indent=1,
        )
    )
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
