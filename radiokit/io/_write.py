"""Writers for processed stacks: HDF5 or TIFF, one frame at a time."""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import tifffile

__all__ = ["write_tiff", "StackWriter"]


def write_tiff(path, image, /, *, meta=None, bigtiff=None) -> Path:
    """Write a frame or a stack ``(n, rows, cols)`` as a multi-page TIFF.

    ``meta`` (JSON-serialisable) goes into the ImageDescription so :func:`radiokit.io.read`
    gives it back as ``meta["description"]``.
    """
    path = Path(path)
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[None]
    if image.ndim != 3:
        raise ValueError(f"write_tiff: expected (rows, cols) or (n, rows, cols), got shape {image.shape}")
    with StackWriter(path, image.shape[1:], image.dtype, meta=meta, bigtiff=bigtiff) as w:
        for frame in image:
            w.append(frame)
    return path


class StackWriter:
    """Append frames of one shape and dtype to ``.h5`` or ``.tif`` as they are produced.

    HDF5 output holds ``/entry/data/data`` (chunked one frame per chunk) and, from
    :meth:`append`'s keyword arguments, per-frame series under ``/entry/data/``; ``meta`` becomes
    attributes of ``/entry/data`` (nested dicts as JSON). Each frame is flushed as written.
    ``n_frames``, when known, preallocates the HDF5 datasets (no resize per frame); a file closed
    early is shrunk to the frames written.
    """

    def __init__(self, path, frame_shape, dtype=np.float32, *, meta=None, bigtiff=None, overwrite=True,
                 n_frames=None):
        self.path = Path(path)
        self.frame_shape = tuple(int(s) for s in frame_shape)
        self.dtype = np.dtype(dtype)
        self.meta = dict(meta or {})
        self.n = 0
        suffix = self.path.suffix.lower()
        if not overwrite and self.path.exists():
            raise FileExistsError(f"{self.path}: exists")
        if suffix in (".h5", ".hdf5", ".nxs"):
            self.kind = "hdf5"
            self._h5 = h5py.File(self.path, "w")
            entry = self._h5.create_group("entry")
            entry.attrs["NX_class"] = "NXentry"
            grp = entry.create_group("data")
            grp.attrs["NX_class"] = "NXdata"
            grp.attrs["signal"] = "data"
            for key, value in self.meta.items():
                grp.attrs[key] = json.dumps(value) if isinstance(value, (dict, list, tuple)) else value
            self._alloc = int(n_frames or 0)
            self._ds = grp.create_dataset("data", shape=(self._alloc,) + self.frame_shape,
                                          maxshape=(None,) + self.frame_shape,
                                          chunks=(1,) + self.frame_shape, dtype=self.dtype)
            self._series = {}
        elif suffix in (".tif", ".tiff"):
            self.kind = "tiff"
            frame_bytes = int(np.prod(self.frame_shape)) * self.dtype.itemsize
            self._tif = tifffile.TiffWriter(self.path, bigtiff=True if bigtiff is None and frame_bytes > 2**28 else bool(bigtiff))
        else:
            raise ValueError(f"{self.path}: output must end in .h5/.hdf5/.nxs or .tif/.tiff")

    def append(self, frame, **series):
        frame = np.asarray(frame)
        if frame.shape != self.frame_shape:
            raise ValueError(f"{self.path}: frame shape {frame.shape} != {self.frame_shape}")
        if self.kind == "hdf5":
            i = self.n
            if i >= self._ds.shape[0]:
                self._ds.resize(i + 1, axis=0)
            self._ds[i] = frame
            for name, value in series.items():
                ds = self._series.get(name)
                if ds is None:
                    ds = self._h5["entry/data"].create_dataset(name, shape=(max(self._alloc, i),), maxshape=(None,),
                                                               dtype=np.asarray(value).dtype, chunks=(256,))
                    self._series[name] = ds
                if i >= ds.shape[0]:
                    ds.resize(i + 1, axis=0)
                ds[i] = value
            self._h5.flush()
        else:
            desc = json.dumps(self.meta) if self.n == 0 and self.meta else None
            self._tif.write(frame.astype(self.dtype, copy=False), contiguous=False,
                            description=desc, metadata=None)
        self.n += 1

    def close(self):
        if self.kind == "hdf5":
            if self._h5.id.valid:
                for ds in [self._ds, *self._series.values()]:
                    if ds.shape[0] != self.n:
                        ds.resize(self.n, axis=0)
                self._h5.close()
        else:
            self._tif.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
