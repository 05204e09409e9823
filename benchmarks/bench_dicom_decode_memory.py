"""Compressed DICOM: the peak memory of reading one frame, by syntax, against what the budget counts.

A 2240 x 2240 frame (a smooth field with Poisson noise, 16 bits allocated, as many stored as the
syntax encodes: 8 for JPEG baseline, 12 for JPEG extended, 16 for the others), written in each
compressed syntax radiokit decodes, then read with ``radiokit.io.read`` in a fresh process. Two
peaks above the process's memory just before the read (the codecs already warmed up on a small
file of the same syntax): tracemalloc's (what numpy and Python allocate) and the kernel's resident
high-water mark (VmHWM, reset through /proc/self/clear_refs: the C libraries' own buffers too).
``counted`` is what ``radiokit.io._clinical.dicom_read_bytes`` charges the budget for the read.

    python benchmarks/bench_dicom_decode_memory.py [--size 2240] [--frames 1] [--variant plain|signed|rescaled]
        [--files] [--only NAME ...] [--src DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import imagecodecs
import numpy as np
from pydicom import uid
from pydicom.encaps import encapsulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dicomdata import grey_dataset

# syntax: (bits stored, encoder of a uint16 frame, or None for pydicom's own encoding)
SYNTAXES = {
    "JPEGBaseline8Bit": (8, lambda f: imagecodecs.jpeg8_encode(f.astype(np.uint8), level=90)),
    "JPEGExtended12Bit": (12, lambda f: imagecodecs.jpeg8_encode(f, level=90, bitspersample=12)),
    "JPEGLossless": (16, lambda f: imagecodecs.ljpeg_encode(f, bitspersample=16)),
    "JPEGLosslessSV1": (16, lambda f: imagecodecs.ljpeg_encode(f, bitspersample=16)),
    "JPEGLSLossless": (16, imagecodecs.jpegls_encode),
    "JPEGLSNearLossless": (16, lambda f: imagecodecs.jpegls_encode(f, level=2)),
    "JPEG2000Lossless": (16, lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K")),
    "JPEG2000": (16, lambda f: imagecodecs.jpeg2k_encode(f, level=40, codecformat="J2K", reversible=False)),
    "HTJ2KLossless": (16, lambda f: imagecodecs.htj2k_encode(f, level=0)),
    "HTJ2K": (16, lambda f: imagecodecs.htj2k_encode(f, level=40)),
    "RLELossless": (16, None),
    "DeflatedExplicitVRLittleEndian": (16, None),
    "ExplicitVRLittleEndian": (16, None),
}


def _frame(size: int, bits: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    y, x = np.mgrid[:size, :size] / size
    top = (1 << bits) - 1
    mean = top * (0.15 + 0.6 * np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.2))
    return np.clip(rng.poisson(mean), 0, top).astype(np.uint16)


def write(path: Path, name: str, size: int, variant: str = "plain", frames: int = 1) -> None:
    bits, encode = SYNTAXES[name]
    frame = _frame(size, bits)
    stack = [np.roll(frame, k, axis=1) for k in range(frames)]  # (each frame its own stream)
    syntax = getattr(uid, name)
    ds = grey_dataset(syntax, frame.shape, 16 if bits > 8 else 8, bits, signed=variant == "signed")
    if frames > 1:
        ds.NumberOfFrames = frames
    if variant == "rescaled":
        ds.RescaleSlope, ds.RescaleIntercept = "0.5", "-1024"
    frame = np.stack(stack) if frames > 1 else frame
    if encode is None and variant == "signed":  # the same words, as pydicom's encoder wants them typed
        frame = frame.view(np.int16)
    if encode is not None:
        ds.PixelData = encapsulate([encode(f) for f in stack])
        ds["PixelData"].VR = "OB"
    elif name == "RLELossless":
        ds.PixelData = b""
        ds.compress(syntax, frame if bits > 8 else frame.astype(np.uint8), encoding_plugin="pydicom")
    else:
        ds.PixelData = frame.astype("<u2").tobytes()
        ds["PixelData"].VR = "OW"
    ds.save_as(path, enforce_file_format=True)


# the same codestreams in a file of their own (.jpg, .jls, .j2k), read by radiokit.io.read
FILES = {"JPEGLosslessSV1": ".jpg", "JPEGExtended12Bit": ".jpg", "JPEGLSLossless": ".jls", "JPEG2000Lossless": ".j2k"}


def write_file(path: Path, name: str, size: int) -> None:
    bits, encode = SYNTAXES[name]
    path.write_bytes(encode(_frame(size, bits)))


_CHILD = r"""
import json, sys, tracemalloc, warnings
if sys.argv[3]:  # another tree's radiokit (--src), ahead of this one's editable install
    sys.meta_path = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
    sys.path.insert(0, sys.argv[3])
warnings.simplefilter("ignore")
from radiokit.io import read
from radiokit.io import _clinical
from radiokit.io._clinical import open_dicom
small, big = sys.argv[1:3]
read(small)  # the codecs' libraries loaded and warmed up

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024

if not big.endswith(".dcm"):  # a codestream file: what its open charges the budget
    from radiokit.io import _codecs
    header = _codecs.file_header(big)
    import os
    size = os.path.getsize(big)
    counted = (_codecs.file_read_bytes(header, size) if hasattr(_codecs, "file_read_bytes")
               else _codecs.decoded_bytes(header) + _codecs.check_bytes(header, size))  # (before session 56)
    geo = None
else:
    ds, geo, _ = open_dicom(big, None)
if geo is None:
    pass
elif "stack" in geo:  # read(): the stack beside the element and a frame's decoding (review s56rvoff)
    counted = geo["held"] + geo["stack"] + geo["work"] + geo["rescale_bytes"]
elif "held" in geo:
    counted = geo["held"] + geo["rescale_bytes"] + _clinical.dicom_read_bytes(
        big, ds.file_meta.TransferSyntaxUID, geo["n"], geo["rows"], geo["cols"], geo["dtype"],
        (geo["slope"], geo["intercept"]), _clinical._largest_frame_stream(big, ds, geo["n"]))[1]
else:  # (before session 56: the frames alone)
    counted = geo["n"] * geo["rows"] * geo["cols"] * geo["dtype"].itemsize
ds = None
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")  # VmHWM back to VmRSS
before = status("VmRSS:")
tracemalloc.start()
frames = read(big)
traced = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
print(json.dumps({"rss": status("VmHWM:") - before, "traced": traced, "counted": counted,
                  "frame": frames.data.nbytes}))
"""


def measure(name: str, size: int, variant: str, tmp: Path, src: str = "", suffix: str = ".dcm", frames=1) -> dict:
    small, big = tmp / f"small{suffix}", tmp / f"big{suffix}"
    for path, side, n in ((small, 64, 1), (big, size, frames)):
        write(path, name, side, variant, n) if suffix == ".dcm" else write_file(path, name, side)
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(small), str(big), src], capture_output=True, text=True, check=True
    )
    got = json.loads(out.stdout)
    got["file"] = big.stat().st_size
    return got


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2240)
    ap.add_argument("--variant", choices=("plain", "signed", "rescaled"), default="plain")
    ap.add_argument("--only", nargs="*", default=None, help="these syntaxes alone (pydicom.uid names)")
    ap.add_argument("--frames", type=int, default=1, help="frames in each DICOM (each its own stream)")
    ap.add_argument("--files", action="store_true", help="also the codestreams in files of their own")
    ap.add_argument("--src", default="", help="read with the radiokit package in this folder (git archive of a commit)")
    args = ap.parse_args(argv)
    mib = 2**20
    print(f"{args.frames} frame(s) of {args.size} x {args.size}, {args.variant}; MiB")
    print(f"{'syntax':<32} {'file':>6} {'frames':>6} {'traced':>7} {'VmHWM':>7} {'counted':>8} {'counted/peak':>12}")
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(name, ".dcm") for name in args.only or SYNTAXES]
        jobs += [(name, suffix) for name, suffix in FILES.items() if args.files]
        for name, suffix in jobs:
            g = measure(name, args.size, args.variant, Path(tmp), args.src, suffix, args.frames)
            name = name if suffix == ".dcm" else f"{name} {suffix} file"
            peak = max(g["traced"], g["rss"])
            print(
                f"{name:<32} {g['file'] / mib:6.1f} {g['frame'] / mib:6.1f} {g['traced'] / mib:7.1f} "
                f"{g['rss'] / mib:7.1f} {g['counted'] / mib:8.1f} {g['counted'] / peak:12.2f}"
            )


if __name__ == "__main__":
    main()
