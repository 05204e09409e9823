"""Open any frame file: detect the format from content, then extension; read lazily or at once."""
from __future__ import annotations

import json
import os
from pathlib import Path
from struct import error as struct_error

import h5py
import numpy as np
import tifffile

from radiokit.errors import FormatError
from radiokit.io._experiment import read_experiment_meta
from radiokit.io._frames import Frames, check_bit_depth
from radiokit.io._itex import HEADER_BYTES, parse_comment, parse_itex_header, read_scaling
from radiokit.io._raw import PRESETS, raw_geometry, read_raw_frame

__all__ = ["FrameSource", "open_frames", "read", "iter_frames", "sniff", "FORMATS"]

FORMATS = ("raw", "tiff", "itex", "hdf5")
_TIFF_MAGIC = (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_EXTENSIONS = {".tif": "tiff", ".tiff": "tiff", ".img": "itex", ".h5": "hdf5", ".hdf5": "hdf5",
               ".hdf": "hdf5", ".nxs": "hdf5", ".nx": "hdf5", ".raw": "raw", ".bin": "raw", ".dat": "raw"}
_RAW_HINTS = {"preset", "shape", "dtype", "byteorder", "offset", "n"}


def sniff(path) -> str:
    """Name the format of ``path`` from its first bytes, falling back to its extension.

    A file with no recognised magic is ``"raw"`` unless its extension promises another format,
    in which case the magic is wrong and :class:`FormatError` says so.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except IsADirectoryError:
        raise FormatError(path, "is a directory, not a frame file") from None
    except FileNotFoundError:
        raise FormatError(path, "no such file") from None
    if head[:4] in _TIFF_MAGIC:
        return "tiff"
    if head == _HDF5_MAGIC or (len(head) == 8 and h5py.is_hdf5(path)):
        return "hdf5"
    ext = _EXTENSIONS.get(path.suffix.lower())
    if head[:2] == b"IM" and ext in (None, "itex"):
        return "itex"
    if not head:
        raise FormatError(path, "file is empty")
    if ext == "tiff":
        raise FormatError(path, f"wrong magic {head[:4]!r}: a TIFF starts with b'II*\\x00' or b'MM\\x00*'")
    if ext == "itex":
        raise FormatError(path, f"wrong magic {head[:2]!r}: an ITEX .img starts with b'IM'")
    if ext == "hdf5":
        raise FormatError(path, "no HDF5 signature: not an HDF5 file, or truncated")
    return "raw"


class FrameSource:
    """An open frame file: ``len()``, indexing and iteration give ``(rows, cols)`` frames.

    Use :func:`open_frames` to create one; it is a context manager. Frames are read on demand,
    so iterating over a long stack holds one frame in memory at a time.
    """

    def __init__(self, path, *, format=None, dataset=None, **hints):
        self.path = Path(path)
        unknown = set(hints) - _RAW_HINTS
        if unknown:
            raise TypeError(f"read() got unknown hints {sorted(unknown)}; known: {sorted(_RAW_HINTS | {'format', 'dataset'})}")
        if format is not None and format not in FORMATS:
            raise FormatError(self.path, f"format={format!r}: expected one of {FORMATS}")
        self.format = format or ("hdf5" if dataset else sniff(self.path))
        if self.format != "raw" and hints.keys() - {"n"}:
            # Geometry hints only make sense for headerless data.
            raise FormatError(self.path, f"{self.format} files carry their own geometry; hints "
                                         f"{sorted(hints)} apply to raw files only")
        self._fh = self._tif = self._h5 = None
        self.meta: dict = {}
        try:
            getattr(self, f"_open_{self.format}")(dataset=dataset, **hints)
        except FormatError:
            self.close()
            raise
        except (OSError, ValueError, KeyError, IndexError, TypeError, struct_error, UnicodeError,
                tifffile.TiffFileError, RuntimeError, MemoryError, OverflowError) as exc:
            self.close()
            raise FormatError(self.path, f"cannot be read as {self.format}: {exc}") from exc
        self.meta.setdefault("format", self.format)
        self.meta["path"] = str(self.path)

    # -- format openers -----------------------------------------------------------------------
    def _open_raw(self, dataset=None, **hints):
        size = os.path.getsize(self.path)
        geo = raw_geometry(self.path, size, **hints)
        self._geo = geo
        self._fh = open(self.path, "rb")
        self.n, self.frame_shape, self.dtype = geo["n"], (geo["rows"], geo["cols"]), geo["dtype"].newbyteorder("=")
        self.bits = geo["bits"]
        self.meta.update({k: v for k, v in geo.items() if k != "dtype"}, dtype=str(geo["dtype"]))

    def _read_raw(self, i):
        return read_raw_frame(self._fh, self._geo, i)

    def _open_itex(self, dataset=None, **hints):
        size = os.path.getsize(self.path)
        self._fh = open(self.path, "rb")
        head = self._fh.read(HEADER_BYTES)
        geo = parse_itex_header(self.path, head, size)
        comment = self._fh.read(geo["comment_length"]).decode("latin-1").rstrip("\0")
        parsed = parse_comment(comment)
        geo["n"] = hints.get("n", geo["n"])
        self._geo = geo
        self.n, self.frame_shape, self.dtype = geo["n"], (geo["rows"], geo["cols"]), geo["dtype"]
        self.bits = None
        self.meta.update({k: v for k, v in geo.items() if k != "dtype"}, dtype=str(geo["dtype"]),
                         comment=parsed, comment_text=comment,
                         scaling=read_scaling(self.path, self._fh, parsed, size))

    _read_itex = _read_raw

    def _open_tiff(self, dataset=None, **hints):
        self._tif = tifffile.TiffFile(self.path)
        series = self._tif.series
        if not series:
            raise FormatError(self.path, "TIFF holds no image series")
        pages = self._tif.pages
        first = pages.first
        shape = first.shape
        if len(shape) != 2:
            raise FormatError(self.path, f"TIFF page has shape {shape}; expected a greyscale (rows, cols) image")
        self._pages = [p for p in pages if p.shape == shape]
        self.n, self.frame_shape, self.dtype = len(self._pages), tuple(shape), np.dtype(first.dtype)
        self.bits = None
        tags = {}
        for tag in first.tags:
            if tag.name in ("ImageDescription", "Software", "DateTime", "Artist", "XResolution",
                            "YResolution", "ResolutionUnit", "BitsPerSample", "Compression"):
                value = tag.value
                tags[tag.name] = value.name if hasattr(value, "name") else value
        self.meta.update(n=self.n, rows=shape[0], cols=shape[1], dtype=str(self.dtype), tags=tags)
        desc = tags.get("ImageDescription")
        if isinstance(desc, str) and desc.startswith("{"):
            try:
                self.meta["description"] = json.loads(desc)
            except ValueError:
                pass

    def _read_tiff(self, i):
        frame = self._pages[i].asarray()
        if frame.shape != self.frame_shape:
            raise FormatError(self.path, f"page {i} decodes to {frame.shape}, expected {self.frame_shape}")
        return frame

    def _open_hdf5(self, dataset=None, **hints):
        self._h5 = h5py.File(self.path, "r")
        if dataset:
            if dataset not in self._h5 or not isinstance(self._h5[dataset], h5py.Dataset):
                raise FormatError(self.path, f"no dataset {dataset!r}")
            data = self._h5[dataset]
            if data.ndim not in (2, 3):
                raise FormatError(self.path, f"{dataset} has shape {data.shape}; expected 2 or 3 dimensions")
            meta = {"format": "hdf5", "dataset": dataset}
            n = 1 if data.ndim == 2 else data.shape[0]
        else:
            data, meta = read_experiment_meta(self.path, self._h5)
            n = meta.pop("n_complete")
        self._ds = data
        self.n, self.frame_shape, self.dtype = n, tuple(data.shape[-2:]), data.dtype
        self.bits = 12 if meta.get("format") == "experiment" else None
        self.meta.update(meta, n=n, rows=self.frame_shape[0], cols=self.frame_shape[1], dtype=str(data.dtype))

    def _read_hdf5(self, i):
        return self._ds[()] if self._ds.ndim == 2 else self._ds[i]

    # -- access -------------------------------------------------------------------------------
    def __len__(self):
        return self.n

    def __getitem__(self, i) -> np.ndarray:
        i = int(i)
        if i < 0:
            i += self.n
        if not 0 <= i < self.n:
            raise IndexError(f"{self.path}: frame {i} out of range (0..{self.n - 1})")
        try:
            frame = getattr(self, f"_read_{self.format}")(i)
        except FormatError:
            raise
        except (OSError, ValueError, KeyError, IndexError, TypeError, struct_error, RuntimeError,
                tifffile.TiffFileError, MemoryError, OverflowError, ZeroDivisionError) as exc:
            raise FormatError(self.path, f"frame {i} cannot be decoded: {exc}") from exc
        check_bit_depth(self.path, frame, self.bits)
        return frame

    def __iter__(self):
        for i in range(self.n):
            yield self[i]

    def read_all(self) -> Frames:
        out = np.empty((self.n,) + self.frame_shape, dtype=self.dtype)
        for i in range(self.n):
            out[i] = self[i]
        return Frames(out, dict(self.meta), self.path)

    def close(self):
        for attr in ("_fh", "_tif", "_h5"):
            obj = getattr(self, attr, None)
            if obj is not None:
                obj.close()
                setattr(self, attr, None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass



def open_frames(path, /, **hints) -> FrameSource:
    """Open a frame file for lazy, frame-by-frame access (see :func:`read` for ``hints``)."""
    return FrameSource(path, **hints)


def read(path, /, **hints) -> Frames:
    """Read every frame of a raw, TIFF, ITEX ``.img`` or experiment HDF5 file.

    Parameters
    ----------
    path : str or Path
        The file. Its format is detected from its first bytes, then its extension.
    **hints
        ``format`` ("raw", "tiff", "itex", "hdf5") to skip detection; ``dataset`` to read one
        dataset of an arbitrary HDF5 file; for raw files ``preset`` (one of :data:`PRESETS`),
        ``shape`` ((rows, cols) or (n, rows, cols)), ``dtype`` (default ``"<u2"``),
        ``byteorder`` ("<" or ">"), ``offset`` (bytes to skip) and ``n`` (frames to read).

    Returns
    -------
    Frames
        ``data`` of shape (n, rows, cols) in the file's dtype (native byte order), row 0 as stored;
        ``meta`` with ``format`` and whatever the file records.

    Raises
    ------
    FormatError
        The file is empty, truncated, of no known geometry, has a wrong magic, a header that
        promises more than the file holds, or lacks the expected datasets.

    Warns
    -----
    BitDepthWarning
        A 12-bit C7942 frame holds values above 4095 (bit or byte order, or another model).

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from radiokit.io import read
    >>> path = os.path.join(tempfile.mkdtemp(), "frame.raw")
    >>> np.full((1120, 1120), 100, "<u2").tofile(path)     # one 2x2-binned C7942 frame
    >>> f = read(path)
    >>> f.data.shape, f.meta["preset"]
    ((1, 1120, 1120), 'c7942-2x2')
    """
    with FrameSource(path, **hints) as src:
        return src.read_all()


def iter_frames(path, /, **hints):
    """Yield the frames of ``path`` one at a time, holding one in memory."""
    with FrameSource(path, **hints) as src:
        yield from src

