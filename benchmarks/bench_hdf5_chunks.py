"""Reading an HDF5 stack whose chunks span frames: time and peak memory against contiguous.

A stack chunked ``(n, 1, cols)`` (one row of every frame per chunk, as some writers chunk a
stack they append to along rows, or a tool rechunked for per-pixel time series) is read frame
by frame by :func:`radiokit.io.read` unless it reads in chunk-aligned blocks. For each layout
(contiguous, one frame per chunk, rows of every frame per chunk, gzip or not) write the same
stack, then time ``read()`` (median of reps, interleaved) and measure how far a fresh process's
resident memory rises while it reads the file once (libhdf5's chunk cache and filter buffers
included), and print them beside the stack's size.

    python benchmarks/bench_hdf5_chunks.py [--n 40] [--rows 512] [--cols 512] [--reps 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from radiokit.io import read


def _layouts(n, rows, cols):
    return {
        "contiguous": {},
        "(1, rows, cols)": {"chunks": (1, rows, cols)},
        "(n, 1, cols)": {"chunks": (n, 1, cols)},
        "(n, 1, cols) gzip": {"chunks": (n, 1, cols), "compression": "gzip"},
        "(n, 16, cols)": {"chunks": (n, 16, cols)},
        "(4, 64, 64) gzip": {"chunks": (min(4, n), 64, 64), "compression": "gzip"},
    }


def _write(path: Path, stack: np.ndarray, kw: dict) -> None:
    with h5py.File(path, "w") as h5:
        h5.create_dataset("data", data=stack, **kw)


_CHILD = """
import sys
from radiokit.io import read
def status(key):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key))
with open("/proc/self/clear_refs", "w") as f:  # 5: reset the peak (VmHWM) to the present RSS
    f.write("5")
before = status("VmRSS:")
read(sys.argv[1], dataset="data")
print(status("VmHWM:") - before)
"""


def _peak_rss_mib(path) -> float:
    """How far a process's resident memory rises, MiB, while read() reads ``path`` (Linux: its
    peak reset after the imports, through /proc/self/clear_refs)."""
    out = subprocess.run([sys.executable, "-c", _CHILD, str(path)], capture_output=True, text=True, check=True)
    return int(out.stdout) / 1024


def _read_once(path: Path) -> tuple[float, np.ndarray]:
    t = time.perf_counter()
    data = read(path, dataset="data").data
    return time.perf_counter() - t, data


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--rows", type=int, default=512)
    ap.add_argument("--cols", type=int, default=512)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    stack = rng.integers(0, 4096, (args.n, args.rows, args.cols), dtype=np.uint16)
    mb = stack.nbytes / 2**20
    print(f"stack {args.n} x {args.rows} x {args.cols} uint16, {mb:.1f} MiB; read() median of {args.reps}")
    print(f"{'chunks':<20} {'time s':>8} {'x contiguous':>13} {'peak MiB':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        paths = {}
        for name, kw in _layouts(args.n, args.rows, args.cols).items():
            paths[name] = Path(tmp) / f"{len(paths)}.h5"
            _write(paths[name], stack, kw)
        times = {name: [] for name in paths}
        for _ in range(args.reps):  # interleaved, so that load on the machine hits every layout alike
            for name, path in paths.items():
                dt, data = _read_once(path)
                assert np.array_equal(data, stack), name
                times[name].append(dt)
        base = statistics.median(times["contiguous"])
        for name, path in paths.items():
            t = statistics.median(times[name])
            print(f"{name:<20} {t:>8.3f} {t / base:>13.1f} {_peak_rss_mib(path):>9.1f}")


if __name__ == "__main__":
    main()
