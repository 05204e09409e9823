"""Reading one 2240 x 2240 16-bit greyscale PNG (a C7942 frame's size): wall time and peak RSS.

A shaded flat with Poisson-like noise, written by OpenCV at its default compression (level 1); each
read in a fresh process, its peak resident memory the high-water mark (VmHWM, reset through
/proc/self/clear_refs after the imports) over the resident size before the read; best of ``--repeat``.

    python benchmarks/bench_png_read.py [--repeat 5] [--src DIR]

``--src DIR``: read with the ``radiokit`` package under DIR (another tree's, e.g. ``git archive``
of the commit before a change), not the installed one: the children then run without ``site``
(an editable install's finder comes before PYTHONPATH), the venv's packages on their path.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_CHILD = """
import json, re, sys, time
import numpy as np
import cv2  # imported before the clock and the RSS baseline: the read is what is measured
from radiokit.io import read
def hwm():
    return int(re.search(r"VmHWM:\\s+(\\d+)", open("/proc/self/status").read()).group(1))
def rss():
    return int(re.search(r"VmRSS:\\s+(\\d+)", open("/proc/self/status").read()).group(1))
with open("/proc/self/clear_refs", "w") as fh:  # the high-water mark reset to the RSS now
    fh.write("5")
base = rss()
t0 = time.perf_counter()
frames = read(sys.argv[1])
data = frames.data
wall = time.perf_counter() - t0
peak = hwm()
import radiokit.io._clinical as c
print(json.dumps({"src": c.__file__, "wall_s": wall, "peak_mb": peak / 1024, "base_mb": base / 1024, "sum": int(data.sum())}))
"""


def image() -> np.ndarray:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:2240, :2240]
    shading = 1 - 0.3 * ((xx - 1120) ** 2 + (yy - 1120) ** 2) / 1120**2
    return np.clip(rng.normal(3000 * shading, np.sqrt(3000 * shading)), 0, 4095).astype(np.uint16)


def main() -> None:
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--src", help="the directory holding the radiokit package to read with")
    args = ap.parse_args()
    command, env = [sys.executable, "-c", _CHILD], None
    if args.src:
        site = str(Path(np.__file__).parents[1])
        command, env = [sys.executable, "-S", "-c", _CHILD], {"PYTHONPATH": f"{args.src}{os.pathsep}{site}"}
    with tempfile.TemporaryDirectory() as tmp:
        for level in (1,):
            path = Path(tmp) / f"flat_{level}.png"
            cv2.imwrite(str(path), image(), [cv2.IMWRITE_PNG_COMPRESSION, level])
            runs = [
                json.loads(
                    subprocess.run(
                        [*command, str(path)], capture_output=True, text=True, check=True, env=env, cwd=tmp
                    ).stdout
                )
                for _ in range(args.repeat)
            ]
            best = min(runs, key=lambda r: r["wall_s"])
            print(f"radiokit.io._clinical from {best['src']}")
            peak = min(r["peak_mb"] - r["base_mb"] for r in runs)
            size = path.stat().st_size / 2**20
            print(
                f"zlib level {level}: {size:.1f} MiB file; read {best['wall_s'] * 1e3:.0f} ms (best of "
                f"{args.repeat}); peak RSS above the process's before the read {peak:.0f} MB"
            )


if __name__ == "__main__":
    main()
