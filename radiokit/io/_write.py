"""Processed (corrected) stacks: HDF5 or TIFF, written one frame at a time.

The HDF5 layout (``radiokit correct``'s output):

``/`` (``@default = "entry"``)
``/entry`` (NXentry, ``@default = "data"``)
``/entry/data`` (NXdata, ``@signal = "data"``; the writer's ``meta`` as attributes, dicts as JSON)
    ``data`` (n, rows, cols), one frame per chunk (the plot);
    per-frame series (n,) named by :meth:`StackWriter.append`'s keywords (e.g. ``step``).
``/entry/sources`` (k,) strings: the input files' names (``sources``), which a ``source_index``
    series counts into; each name's bytes as the file system gave them (``os.fsencode``).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from radiokit import _json as strict_json
from radiokit._names import shown
from radiokit.errors import FormatError
from radiokit.io._atomic import OutputError, atomic_path
from radiokit.io._layout import ReadBudget, open_layout, text

__all__ = ["write_tiff", "StackWriter", "StackRecord", "read_stack", "STACK", "STACK_FRAMES", "SOURCES"]

STACK = "entry/data"
STACK_FRAMES = f"{STACK}/data"
#: every input file's name, in the order a per-frame ``source_index`` counts them (StackWriter's ``sources``)
SOURCES = "entry/sources"


def write_tiff(path, image, /, *, meta=None, bigtiff=None, overwrite=False, inputs=()) -> Path:
    """Write a frame or a stack ``(n, rows, cols)`` as a multi-page TIFF.

    ``meta`` (JSON-serialisable) goes into the ImageDescription so :func:`radiokit.io.read`
    gives it back as ``meta["description"]``. Written atomically; an existing ``path`` is
    replaced only with ``overwrite=True`` (see :class:`StackWriter`).
    """
    path = Path(path)
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[None]
    if image.ndim != 3:
        raise ValueError(f"write_tiff: expected (rows, cols) or (n, rows, cols), got shape {image.shape}")
    with StackWriter(
        path, image.shape[1:], image.dtype, meta=meta, bigtiff=bigtiff, overwrite=overwrite, inputs=inputs
    ) as w:
        for frame in image:
            w.append(frame)
    return path


#: The pitch a stack states beside its frames, in metres (read by :func:`radiokit.io.read` as
#: an NXdetector's; :func:`read_stack` gives them no series)
PITCH_NAMES = ("x_pixel_size", "y_pixel_size")


def _names_encoding(names) -> str:
    """The HDF5 string type that tells the truth of file names' bytes: UTF-8 where every name is,
    else ASCII, HDF5's type for bytes of no stated encoding. Why (s54): a name no UTF-8 decodes
    (Latin-1 ``caf\xe9.tif``) was stored under the UTF-8 type, and tools reading it as text
    (h5py's ``asstr()``, h5dump, NeXus readers) failed on the whole dataset."""
    try:
        for name in names:
            name.decode("utf-8")
    except UnicodeDecodeError:
        return "ascii"
    return "utf-8"


class StackWriter:
    """Append frames of one shape and dtype to ``.h5`` or ``.tif`` as they are produced.

    HDF5 output holds ``/entry/data/data`` (chunked one frame per chunk) and, from
    :meth:`append`'s keyword arguments, per-frame series under ``/entry/data/``; ``meta`` becomes
    attributes of ``/entry/data`` (nested dicts as JSON). Each frame is flushed as written.
    ``pixel_mask`` (HDF5 only; a TIFF stack has no place for it) is written once as
    ``/entry/instrument/detector/pixel_mask``, with ``pixel_mask_attrs`` as its attributes.
    ``series_attrs`` (HDF5 only) maps a per-frame series' name to its dataset's attributes (what
    a sentinel value in it means). ``sources`` (HDF5 only: a TIFF stack keeps no per-frame series
    to count into them) are the input files' names, written whole as ``/entry/sources`` (no JSON
    bound: ``meta`` may summarise them, :func:`radiokit.correct.stack_meta`). ``pixel_sizes``
    (HDF5 only: a TIFF's resolution is read as a display's, never as a pitch), ``x_pixel_size``
    and ``y_pixel_size`` in metres, are written beside the frames, where radiokit's reader looks
    for an NXdetector's: a corrected stack keeps the pitch of the frames it came from.

    JSON is strict (:mod:`radiokit._json`): a non-finite number is null, and a dict names it in its
    ``"not_finite"`` and reads back as the number; a list attribute cannot carry that map, so a
    non-finite number in one reads back ``None``.

    ``n_frames``, when known, preallocates the HDF5 datasets (no resize per frame); a file closed
    early is shrunk to the frames written.

    The file is written under a temporary name beside ``path`` and renamed into place by
    :meth:`close` (see :func:`radiokit.io.atomic_path`); leaving the ``with`` block on an
    exception removes it, so ``path`` is never a partial stack. An existing ``path`` is refused
    unless ``overwrite=True`` (the default was True, unlike every other writer's); ``inputs`` are
    files ``path`` must not be.
    """

    def __init__(
        self,
        path,
        frame_shape,
        dtype=np.float32,
        *,
        meta=None,
        bigtiff=None,
        overwrite=False,
        n_frames=None,
        inputs=(),
        pixel_mask=None,
        pixel_mask_attrs=None,
        series_attrs=None,
        sources=None,
        pixel_sizes=None,
    ):
        self.path = Path(path)
        self._pixel_sizes = dict(pixel_sizes or {})
        self._sources = None if sources is None else [os.fsencode(str(n)) for n in sources]
        self._series_attrs = {name: dict(attrs) for name, attrs in (series_attrs or {}).items()}
        self._pixel_mask = (pixel_mask, dict(pixel_mask_attrs or {}))
        self.frame_shape = tuple(int(s) for s in frame_shape)
        self.dtype = np.dtype(dtype)
        self.meta = dict(meta or {})
        self.n = 0
        suffix = self.path.suffix.lower()
        if suffix not in (".h5", ".hdf5", ".nxs", ".tif", ".tiff"):
            raise ValueError(f"{shown(self.path)}: output must end in .h5/.hdf5/.nxs or .tif/.tiff")
        # the metadata's JSON as written, judged before the file is made: never what read_stack
        # or a TIFF's reader would refuse back (radiokit._json.dumps_readable)
        self._meta_json = self._meta_texts(suffix)
        frame_bytes = int(np.prod(self.frame_shape)) * self.dtype.itemsize
        self._atomic = atomic_path(
            self.path,
            overwrite=overwrite,
            inputs=inputs,
            size_hint=(int(n_frames) * frame_bytes + 2**20) if n_frames else None,
        )
        tmp = self._atomic.__enter__()
        try:
            self._open(tmp, suffix, n_frames, bigtiff)
        except BaseException as exc:
            self._abort(exc)
            if isinstance(exc, OSError) and exc.errno:  # h5py's text names the temporary file
                raise OutputError(self.path, f"cannot be written: {os.strerror(exc.errno)}", exc.errno) from exc
            raise

    def _meta_texts(self, suffix) -> dict:
        """The JSON text of each of ``meta``'s dicts and lists (HDF5: an attribute each), or of
        the whole ``meta`` (TIFF: the first page's description, key None)."""
        where = shown(self.path)
        tiff = suffix in (".tif", ".tiff")
        texts = {  # each part first: a refusal names the one past the bound
            key: strict_json.dumps_readable(value, where, f"its {'description' if tiff else 'meta'}'s {key!r}")
            for key, value in self.meta.items()
            if isinstance(value, (dict, list, tuple))
        }
        if tiff:
            return (
                {None: strict_json.dumps_readable(self.meta, where, "its description (the meta)")} if self.meta else {}
            )
        return texts

    def _open(self, tmp, suffix, n_frames, bigtiff):
        self.kind = "hdf5" if suffix in (".h5", ".hdf5", ".nxs") else "tiff"
        self._h5 = self._tif = self._direct = self._ds = None
        self._series = {}
        if self.kind == "hdf5":
            # Chunks on 4 KiB boundaries so frames can bypass the page cache (see _DirectFrames).
            self._h5 = h5py.File(tmp, "w", alignment_threshold=1 << 20, alignment_interval=4096)
            entry_name, data_name = STACK.split("/")
            self._h5.attrs["default"] = entry_name
            entry = self._h5.create_group(entry_name)
            entry.attrs["NX_class"] = "NXentry"
            entry.attrs["default"] = data_name
            grp = entry.create_group(data_name)
            grp.attrs["NX_class"] = "NXdata"
            grp.attrs["signal"] = STACK_FRAMES.rsplit("/", 1)[1]
            for key, value in self.meta.items():
                # strict JSON (radiokit._json): a non-finite number is null, named in "not_finite"
                grp.attrs[key] = self._meta_json.get(key, value)
            self._write_pixel_mask(entry)
            for axis, metres in self._pixel_sizes.items():  # PITCH_NAMES
                grp.create_dataset(axis, data=float(metres)).attrs["units"] = "m"
            if self._sources is not None:  # each name's bytes: a name no UTF-8 can write is still its file's
                entry.create_dataset(
                    SOURCES.rsplit("/", 1)[1],
                    data=np.array(self._sources, dtype=object),
                    dtype=h5py.string_dtype(_names_encoding(self._sources)),
                )
            self._alloc = int(n_frames or 0)
            dcpl = None
            if self._alloc:  # all chunks allocated now, never filled: frames can be written in place
                dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
                dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
                dcpl.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
            self._ds = grp.create_dataset(
                "data",
                shape=(self._alloc,) + self.frame_shape,
                maxshape=(None,) + self.frame_shape,
                chunks=(1,) + self.frame_shape,
                dtype=self.dtype,
                dcpl=dcpl,
            )
            self._ds.attrs["interpretation"] = "image"
            self._direct = _DirectFrames.open(tmp, self._ds) if self._alloc else None
        else:
            # classic TIFF offsets are 32-bit: a stack that will pass 4 GiB (tifffile's own margin
            # for the IFDs) must be BigTIFF from its first page, or a page past the mark fails
            stack_bytes = int(np.prod(self.frame_shape)) * self.dtype.itemsize * max(int(n_frames or 0), 1)
            auto = stack_bytes > 2**28 if n_frames is None else stack_bytes > 2**32 - 2**25
            import tifffile  # late: only a TIFF output needs it

            self._tif = tifffile.TiffWriter(tmp, bigtiff=auto if bigtiff is None else bool(bigtiff))

    def _write_pixel_mask(self, entry) -> None:
        """``pixel_mask`` (one frame's shape) as NeXus's ``/entry/instrument/detector/pixel_mask``
        with ``pixel_mask_attrs``, compressed (a defect map is nearly all 0). Why: a corrected
        stack counted its filled pixels but did not say which, so a filled defect line could not
        be told from the image (review s42). In the temporary file: atomic with the frames."""
        mask, attrs = self._pixel_mask
        if mask is None:
            return
        mask = np.asarray(mask)
        if mask.shape != self.frame_shape:
            raise ValueError(f"{shown(self.path)}: pixel mask shape {mask.shape} != the frames' {self.frame_shape}")
        instrument = entry.create_group("instrument")
        instrument.attrs["NX_class"] = "NXinstrument"
        detector = instrument.create_group("detector")
        detector.attrs["NX_class"] = "NXdetector"
        ds = detector.create_dataset("pixel_mask", data=mask, compression="gzip", shuffle=True)
        for key, value in attrs.items():
            ds.attrs[key] = value

    def append(self, frame, **series):
        frame = np.asarray(frame)
        if frame.shape != self.frame_shape:
            raise ValueError(f"{shown(self.path)}: frame shape {frame.shape} != {self.frame_shape}")
        if self.kind == "hdf5":
            i = self.n
            if i >= self._ds.shape[0]:
                self._ds.resize(i + 1, axis=0)
            if not (self._direct and self._direct.write(i, frame)):
                self._ds[i] = frame
            for name, value in series.items():
                ds = self._series.get(name)
                if ds is None:
                    ds = self._h5[STACK].create_dataset(
                        name,
                        shape=(max(self._alloc, i),),
                        maxshape=(None,),
                        dtype=np.asarray(value).dtype,
                        chunks=(256,),
                    )
                    for key, attr in self._series_attrs.get(name, {}).items():
                        ds.attrs[key] = attr
                    self._series[name] = ds
                if i >= ds.shape[0]:
                    ds.resize(i + 1, axis=0)
                ds[i] = value
            self._h5.flush()
        else:
            desc = self._meta_json.get(None) if self.n == 0 else None
            self._tif.write(frame.astype(self.dtype, copy=False), contiguous=False, description=desc, metadata=None)
        self.n += 1

    def _close_files(self):
        if self._direct:
            self._direct.close()
            self._direct = None
        if self._h5 is not None and self._h5.id.valid:
            for ds in [self._ds, *self._series.values()]:
                if ds is not None and ds.shape[0] != self.n:
                    ds.resize(self.n, axis=0)
            self._h5.close()
        if self._tif is not None:
            self._tif.close()
            self._tif = None

    def _abort(self, exc):
        """Drop the temporary file; a full disk is re-raised as :class:`DiskFullError`."""
        try:
            self._close_files()
        except Exception:  # the file is discarded anyway; the first error is the one to report
            pass
        if self._atomic is not None:
            atomic, self._atomic = self._atomic, None
            atomic.__exit__(type(exc), exc, exc.__traceback__)

    def close(self):
        """Finish the file and rename it into place."""
        if self._atomic is None:
            return
        try:
            self._close_files()
        except BaseException as exc:
            self._abort(exc)
            raise
        atomic, self._atomic = self._atomic, None
        atomic.__exit__(None, None, None)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None:
            self.close()
        else:
            self._abort(exc)


@dataclass(frozen=True)
class StackRecord:
    """A processed stack :class:`StackWriter` wrote to HDF5.

    Attributes
    ----------
    data : (n, rows, cols) array
    series : mapping name -> (n,) array
        The per-frame series (e.g. ``step``, ``nonpositive``).
    meta : mapping
        The writer's ``meta`` (JSON text parsed back into dicts and lists).
    sources : tuple of str
        The input files' names a ``source_index`` series counts into: ``/entry/sources`` (every
        one, as ``os.fsdecode`` names them), else ``meta["sources"]`` where it is a list, else ().
    """

    data: np.ndarray
    series: Mapping = field(default_factory=dict)
    meta: Mapping = field(default_factory=dict)
    sources: tuple = ()


def read_stack(path, *, allow_external=False) -> StackRecord:
    """Read an HDF5 stack :class:`StackWriter` wrote, with its per-frame series and metadata.

    The frames alone are also what :func:`radiokit.io.read` gives for this file.

    Raises
    ------
    FormatError
        The file lacks the stack layout.
    """
    from radiokit.io._experiment import check_links, checked_dataset

    with open_layout(path, "a radiokit stack") as h5:
        check_links(path, h5, STACK_FRAMES, allow_external)
        if STACK_FRAMES not in h5:
            raise FormatError(path, f"lacks /{STACK_FRAMES}: not a radiokit stack")
        ds = checked_dataset(path, h5, STACK_FRAMES, "buif", (3,), allow_external)
        budget, series = ReadBudget(path), {}
        budget.reserve(math.prod(ds.shape) * ds.dtype.itemsize, f"/{STACK_FRAMES} {ds.shape}")
        for name in h5[STACK]:
            # the pitch beside the frames (StackWriter's pixel_sizes) is no per-frame series
            if name != ds.name.rsplit("/", 1)[1] and name not in PITCH_NAMES:
                s = checked_dataset(path, h5, f"{STACK}/{name}", "buif", (1,), allow_external)
                if s.shape != ds.shape[:1]:  # checked before reading: a series is one value per frame
                    # a name the file holds, as names print (s53)
                    named = shown(f"/{STACK}/{name}")
                    raise FormatError(path, f"{named} holds {s.shape[0]} values for {ds.shape[0]} frames")
                series[name] = budget.read(s)
        meta = {k: _attr(path, k, v) for k, v in h5[STACK].attrs.items() if k not in ("NX_class", "signal")}
        listed = meta.get("sources")
        sources = (
            _sources(path, h5, budget, allow_external) if SOURCES in h5 else listed if isinstance(listed, list) else ()
        )
        return StackRecord(ds[()], series, meta, tuple(map(str, sources)))  # its bytes were counted first


def _sources(path, h5, budget, allow_external) -> list[str]:
    """``/entry/sources``, a name a string, as :func:`os.fsdecode` names a file (its bytes as
    written); refused in one line where it is no 1-D dataset of strings."""
    from radiokit.io._experiment import check_links

    check_links(path, h5, SOURCES, allow_external)
    ds = h5[SOURCES]
    if not isinstance(ds, h5py.Dataset) or ds.ndim != 1 or h5py.check_string_dtype(ds.dtype) is None:
        raise FormatError(path, f"/{SOURCES} is not a list of file names (a 1-D dataset of strings)")
    # its storage's size (the names' bytes are on disk: no more than the file holds are read)
    budget.reserve(max(ds.id.get_storage_size(), ds.shape[0] * 16), f"/{SOURCES} ({ds.shape[0]} names)")
    return [os.fsdecode(n) if isinstance(n, bytes) else str(n) for n in ds[()]]


def _attr(path, key, value):
    """An attribute as the writer's ``meta`` gave it: JSON text of a dict or list parsed back
    (text that does not parse stays text; nested past radiokit's depth too, said: s52, 900
    levels loaded and a caller's json.dumps of the meta recursed past Python's limit)."""
    if isinstance(value, (bytes, str)):
        value = text(value)
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return strict_json.loads_record(value, f"/{STACK}@{key}")
        except strict_json.Refused as exc:
            warnings.warn(f"{shown(path)}: {exc}: kept as text", UserWarning, stacklevel=3)
        except ValueError:
            pass
    return value.item() if isinstance(value, np.generic) else value


class _DirectFrames:
    """Write whole preallocated chunks straight to disk with ``O_DIRECT``, past the page cache.

    Streaming 19 MiB float32 frames through the page cache costs a fresh page allocation per
    4 KiB; on virtual machines whose host reclaims idle guest memory that is several times slower
    than writing direct (``benchmarks/README.md``, ``bench_correct.py`` part 2), and in any case
    it fills the cache with frames nobody will read soon. HDF5 still owns the file layout
    and metadata; this only fills the bytes of chunks HDF5 allocated early and never writes
    itself (fill time "never"). Where the filesystem refuses ``O_DIRECT`` (tmpfs) or a chunk
    is not 4 KiB aligned, :meth:`write` returns False and h5py writes the frame as usual.
    """

    ALIGN = 4096

    def __init__(self, fd, ds, nbytes):
        import mmap

        self._fd, self._ds, self._nbytes = fd, ds, nbytes
        self._staging = mmap.mmap(-1, nbytes)  # page-aligned, as O_DIRECT requires
        self._view = np.frombuffer(self._staging, ds.dtype).reshape(ds.shape[1:])

    @classmethod
    def open(cls, path, ds):
        import os

        nbytes = int(np.prod(ds.shape[1:])) * ds.dtype.itemsize
        flag = getattr(os, "O_DIRECT", 0)
        if not flag or nbytes % cls.ALIGN or os.environ.get("RADIOKIT_NO_DIRECT_IO"):
            return None
        try:
            fd = os.open(path, os.O_WRONLY | flag)
        except OSError:
            return None
        return cls(fd, ds, nbytes)

    def write(self, i, frame) -> bool:
        import os

        if self._fd is None:
            return False
        info = self._ds.id.get_chunk_info_by_coord((i,) + (0,) * (self._ds.ndim - 1))
        offset = info.byte_offset
        if offset is None or offset % self.ALIGN or info.size != self._nbytes:
            return False
        self._view[...] = frame
        try:
            written = os.pwrite(self._fd, self._staging, offset)
        except OSError as exc:
            if exc.errno == 22:  # EINVAL: this filesystem takes no O_DIRECT; fall back for good
                self.close()
                return False
            raise OSError(exc.errno, f"writing frame {i}: {exc.strerror}") from exc
        if written != self._nbytes:
            raise OSError(f"writing frame {i}: short write ({written} of {self._nbytes} bytes)")
        return True

    def close(self):
        import os

        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            self._view = None
            self._staging.close()

    def __bool__(self):
        return self._fd is not None
