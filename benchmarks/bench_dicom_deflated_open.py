"""A deflated DICOM's open: what pydicom holds as it inflates the whole dataset, against the count.

pydicom inflates a Deflated Explicit VR Little Endian dataset whole as it opens the file
(``zlib.decompress`` of the rest of it), before radiokit can read any header. One frame of
zeros (deflate's 1:1000) or of noise (1000-1200 counts), each written by pydicom to a temporary
file; the peak traced (tracemalloc) while ``pydicom.dcmread`` opens it, and what
``radiokit.io._clinical`` charges the budget before letting pydicom do so: the compressed bytes
and ``_inflated_held`` (zlib's output blocks, the last part-filled, and their join).

    python benchmarks/bench_dicom_deflated_open.py
"""

from __future__ import annotations

import tempfile
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pydicom
from pydicom import uid
from pydicom.dataset import Dataset, FileMetaDataset

from radiokit.io._clinical import _file_meta_end, _inflated_held

CASES = [(300, "noise"), (1000, "noise"), (1000, "zeros"), (2000, "zeros"), (2240, "noise"), (5000, "zeros")]


def _write(path: Path, frame: np.ndarray) -> None:
    meta = FileMetaDataset()
    meta.TransferSyntaxUID = uid.DeflatedExplicitVRLittleEndian
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.1.1"
    meta.MediaStorageSOPInstanceUID = uid.generate_uid()
    ds = Dataset()
    ds.file_meta = meta
    ds.Rows, ds.Columns = frame.shape
    ds.BitsAllocated = 16
    ds.PixelData = frame.tobytes()
    ds.save_as(path, enforce_file_format=True)


def main() -> None:
    rng = np.random.default_rng(8)
    print(f"{'side':>5} {'frame':6} {'inflated':>9} {'traced':>8} {'counted':>8} {'counted/traced':>15}   (MiB)")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "deflated.dcm"
        _write(path, np.zeros((8, 8), np.uint16))
        pydicom.dcmread(path, defer_size="1 KB")  # (pydicom's modules imported before any is traced)
        for side, kind in CASES:
            zeros = kind == "zeros"
            frame = np.zeros((side, side), np.uint16) if zeros else rng.integers(1000, 1200, (side, side), np.uint16)
            _write(path, frame)
            start, _ = _file_meta_end(path)
            stored = path.stat().st_size - start
            inflated = len(zlib.decompress(path.read_bytes()[start:], -zlib.MAX_WBITS))
            tracemalloc.start()
            pydicom.dcmread(path, defer_size="1 KB")
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            counted = stored + _inflated_held(inflated)
            mib = 2**20
            print(
                f"{side:5d} {kind:6} {inflated / mib:9.1f} {peak / mib:8.1f} {counted / mib:8.1f} {counted / peak:15.2f}"
            )


if __name__ == "__main__":
    main()
