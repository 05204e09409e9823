"""The experiment file of DESIGN.md: NeXus-style HDF5, frames appended and flushed one by one.

``/entry`` (NXentry, ``@default = "data"``; the root's ``@default = "entry"``)
    ``@frames_complete``; ``@protocol`` (TOML) and ``@devices`` (JSON) of the run that wrote it;
    ``instrument/source`` (NXsource), ``instrument/detector`` (NXdetector: ``data`` (n, rows,
    cols) uint16, ``image_key`` (n,) int8, pixel sizes, ``pixel_mask``),
    ``sample/compression`` (``step``, ``ratio``, ``gap``), ``control`` (``time``, ``voltage``,
    ``current``), ``data`` (NXdata, ``@signal = "data"``: links to the frames and their keys),
    and, in simulated files only, ``simulation`` (see :mod:`radiokit.io._simulation`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import glob
import hashlib
import math
import os
import re
import shutil
import socket
import stat
import time
import warnings
import weakref
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

import h5py
import numpy as np

from radiokit import _json as strict_json
from radiokit._names import shown
from radiokit.checks import is_number
from radiokit.errors import FormatError
from radiokit.interrupts import STOP_SIGNALS, held, settle
from radiokit.io._atomic import (
    OutputError,
    _fsync,
    _head,
    _human,
    _keep_mode,
    _owner_tag,
    _remove,
    _remove_stale,
    _temporary_name,
    check_output,
    file_size_limit,
    resolved,
)
from radiokit.io._frames import BitDepthWarning, bit_depth_cause

__all__ = [
    "C7942_PIXEL_SIZE_MM",
    "ExperimentWriter",
    "ImageKey",
    "ExperimentProgress",
    "read_progress",
    "restore_previous",
    "discard_unbegun",
    "DETECTOR",
    "FRAMES",
    "IMAGE_KEY",
    "STEP",
    "read_experiment_meta",
    "read_bit_depth",
    "checked_dataset",
    "check_local",
    "check_links",
    "check_frame_written",
]

ENTRY = "entry"
DETECTOR = "entry/instrument/detector"
COMPRESSION = "entry/sample/compression"
CONTROL = "entry/control"
SOURCE = "entry/instrument/source"
NXDATA = "entry/data"
FRAMES = f"{DETECTOR}/data"
IMAGE_KEY = f"{DETECTOR}/image_key"
STEP = f"{COMPRESSION}/step"


class ImageKey(IntEnum):
    """NXtomo ``image_key`` values."""

    PROJECTION = 0
    FLAT = 1
    DARK = 2
    INVALID = 3


# Per-frame series: (group, name, dtype, fill value, units)
_SERIES = (
    (DETECTOR, "image_key", np.int8, ImageKey.INVALID, None),
    (COMPRESSION, "step", np.int16, -1, None),
    (COMPRESSION, "ratio", np.float64, np.nan, ""),
    (COMPRESSION, "gap", np.float64, np.nan, "m"),
    (CONTROL, "time", np.float64, np.nan, "s"),
    (CONTROL, "voltage", np.float64, np.nan, "kV"),
    (CONTROL, "current", np.float64, np.nan, "uA"),
)


def _set_class(group, nx_class):
    group.attrs["NX_class"] = nx_class


#: The C7942SK-02's pixel pitch: what radiokit assumes for a file or a protocol that states none
#: (said where it is assumed). No longer the writer's default: a file of another panel's frames
#: claimed it as its own
C7942_PIXEL_SIZE_MM = 0.05


class ExperimentWriter:
    """Append frames to an experiment file, flushing after each.

    A new file, or one overwritten ``in_place``, is written under its own name: a crash loses at
    most the frame in flight, and the rest stay there for ``--resume``. Overwritten ``in_place``,
    the old file is kept aside, hidden, until the first new frame is on disk. An overwrite that is not
    ``in_place`` builds the new file in a hidden temporary beside the old one, which it replaces
    only when closed without an error: a crash, an error, or a writer never closed leaves the old
    file unchanged and the new frames in the temporary (a writer garbage-collected or alive at
    interpreter exit without :meth:`close` warns, naming both); and the disk must hold both files
    until then. Use it in a ``with`` block, which closes it.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file. ``mode="w"`` creates it (refusing to overwrite unless ``overwrite=True``),
        ``mode="a"`` reopens an existing file to append.
    shape : (rows, cols)
        Frame shape; required for a new file, checked when appending to an old one.
    pixel_size_mm : float, optional
        Detector pixel pitch (written in metres as NeXus wants). Not given: none is written, and
        readers say they assume the C7942's (:data:`C7942_PIXEL_SIZE_MM`): the writer does not
        know the panel, and a default written as the data's own was taken for it.
    pixel_size_from : str, optional
        Where the pitch came from ("the protocol's [detector] pixel_size_mm", "preset c7942"),
        recorded as the pitch datasets' ``pixel_size_from`` attribute and shown by ``radiokit info``.
    source : dict, optional
        ``name``, ``voltage_kv``, ``current_ua`` of the X-ray source (no ``name``: none recorded).
    detector_name : str, optional
        Written to ``instrument/detector/description``; not given, none is written (it had been
        the C7942SK-02's, claimed for any panel's frames).
    bit_depth : int, optional
        The panel's ADC bits, recorded as NeXus ``bit_depth_readout``: 12 for the C7942, 16 for
        a panel that saturates at 65535. Readers take values above ``2**bit_depth - 1`` for a
        wrong byte or bit order, and the calibration flags ``2**bit_depth - 1`` as saturated.
        Not given: not recorded; readers assume the C7942's 12 bits for that warning, and the
        calibration infers the range from the darks and flats
        (:func:`radiokit.calibrate.adc_top`).
        With ``mode="a"``: recorded where the file has none, refused where it records another.
    in_place : bool
        With ``overwrite``, write the new file under the existing file's name, frame by frame.
        The old file is first renamed to a hidden sibling, ``.NAME.previous-HOST-PID-XXXXXXXX.h5``
        (the same folder: an atomic rename), put back by :meth:`close` (or a failed opening) while
        the new file has no frame, and removed once the first frame is on disk: a run that ends
        before it has a frame of its own (an error, Ctrl-C) leaves the old file as it was, and one
        killed then (kill -9, a power cut) leaves it in the sibling, which
        :func:`restore_previous` puts back. Its folder must be writable. By default the new file is built beside it (beside a symbolic link's target, the
        link kept) and renamed over it only when closed without an error, as every radiokit
        output is (:func:`radiokit.io.atomic_path`): a run killed or failed part-way leaves the
        old file whole. The acquisition passes True: its file is the run's journal, and a run
        killed part-way must leave its frames under the name ``--resume`` continues.
        A new file is always written under its own name, frame by frame, for the same reason.
        Built beside, the old file takes its space until the new one replaces it: an overwrite
        that would need more than is free is refused at opening if not even one frame fits, and
        warned about if a new file as large as the old one would not. In place, it takes its
        space until the first frame: refused at opening if that frame does not fit beside it.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from radiokit.io import ExperimentWriter, ImageKey, read
    >>> path = os.path.join(tempfile.mkdtemp(), "exp.h5")
    >>> with ExperimentWriter(path, shape=(4, 5)) as w:
    ...     _ = w.append(np.zeros((4, 5), np.uint16), image_key=ImageKey.DARK)
    ...     _ = w.append(np.full((4, 5), 1000, np.uint16), image_key=ImageKey.PROJECTION, step=1, ratio=0.15)
    >>> f = read(path)
    >>> f.data.shape, f.meta["image_key"].tolist()
    ((2, 4, 5), [2, 0])
    """

    def __init__(
        self,
        path,
        shape=None,
        *,
        mode="w",
        overwrite=False,
        pixel_size_mm=None,
        source=None,
        detector_name=None,
        pixel_size_from=None,
        title="radiokit experiment",
        bit_depth=None,
        in_place=False,
    ):
        self.path = Path(path)
        if mode not in ("w", "a"):
            raise ValueError(f"mode={mode!r}: expected 'w' (new file) or 'a' (append)")
        if mode == "w" and self.path.exists() and not overwrite:
            raise FileExistsError(f"{shown(self.path)}: exists; raw data is never overwritten (use mode='a' to append)")
        if mode == "a" and not self.path.exists():
            raise FileNotFoundError(f"{shown(self.path)}: no experiment file to append to")
        lo, hi = (v * 1e3 for v in PIXEL_SIZE_RANGE_M)
        if mode == "w" and pixel_size_mm is not None and not (is_number(pixel_size_mm) and lo <= pixel_size_mm <= hi):
            # checked as the readers check it (NaN fails too): a file no reader would open is not begun
            raise ValueError(f"pixel_size_mm={pixel_size_mm!r}: expected a panel's pixel pitch, {lo:g} to {hi:g} mm")
        if pixel_size_from is not None and (pixel_size_mm is None or not isinstance(pixel_size_from, str)):
            raise ValueError(f"pixel_size_from={pixel_size_from!r}: expected text saying where pixel_size_mm came from")
        if detector_name is not None and not isinstance(detector_name, str):
            raise ValueError(f"detector_name={detector_name!r}: expected the panel's name as text")
        pitch = None if pixel_size_mm is None else (pixel_size_mm, pixel_size_from)
        self._open(mode, overwrite, in_place, shape)
        try:
            if self._previous is not None:
                _keep_mode(self._file, self._previous)  # as writing into the old file would have
            if bit_depth is not None and not (isinstance(bit_depth, (int, np.integer)) and 1 <= bit_depth <= 16):
                raise ValueError(f"bit_depth={bit_depth!r}: frames are stored as uint16, 1 to 16 bits")
            if mode == "w":
                if shape is None:
                    raise ValueError("shape=(rows, cols) is required for a new experiment file")
                self._create(tuple(int(s) for s in shape), pitch, source or {}, detector_name, title)
                if bit_depth is not None:
                    self._h5[DETECTOR]["bit_depth_readout"] = int(bit_depth)
            else:
                self._reopen(shape)
                self._reopen_bit_depth(bit_depth)
        except BaseException:  # Ctrl-C too: the old file kept aside goes back
            # a clean-up's own error (libhdf5 closing a file cut short) must not replace the
            # first: a Ctrl-C turned into an OSError was no longer taken for an interrupt
            with contextlib.suppress(Exception):
                self._h5.close()
            _unlock(self._own_lock)
            with contextlib.suppress(Exception):
                if self._replaces is not None:
                    _remove(self._file)
                self._put_back()
            raise
        # Never closed (garbage-collected, or alive at interpreter exit): the reserve's space is
        # given back, and an overwrite built beside the old file is not renamed into place (it
        # may be a crash) but never silent: the user would go on with the old file as the new one
        self._unclosed = weakref.finalize(
            self,
            _unclosed,
            str(self.path),
            None if self._replaces is None else str(self._file),
            self._ballast_path if self.ballast else None,
            self._previous,
            self._aside_lock,
            self._own_lock,
            self._created,
        )

    def _open(self, mode, overwrite, in_place, shape) -> None:
        """Open the file to write (:meth:`_where`), its room checked, an old file overwritten in
        place first set aside (:meth:`_set_aside`) and put back if the opening fails."""
        self._file, self._replaces = self._where(mode, overwrite, in_place)
        frame_bytes = None if shape is None else math.prod(int(s) for s in shape) * np.dtype(np.uint16).itemsize
        set_aside = in_place and mode == "w" and os.path.lexists(self._file)
        #: a file this writer makes under a free name (neither appended to nor replacing one)
        self._began = mode == "w" and self._replaces is None and not set_aside
        if self._replaces is not None and frame_bytes is not None:
            self._check_overwrite_room(frame_bytes)
        elif not set_aside:  # (set aside, the old file keeps its space: _set_aside checks the room)
            self._check_opening_room(mode)
        self._previous, self._aside_lock, self._own_lock, self.restored_previous = None, [None], [None], False
        #: The old file an in-place overwrite could not put back (another program took the name, or
        #: the folder took no rename): still hidden beside it, where the caller's last line names it.
        self.previous_kept_in: Path | None = None
        self._created = None
        try:
            if set_aside:
                # a stop between the rename and its record left the old file hidden while the
                # run said "unchanged": it is delivered once the file is recorded, to be put back
                with held(*STOP_SIGNALS):
                    self._previous = self._set_aside(frame_bytes)
            # "w-": never truncate a file another run made under the name since it was seen (a
            # second overwrite emptied a running run's file, review s36r5)
            self._h5 = h5py.File(self._file, "w-" if mode == "w" else "r+")
            self._own_lock[0], self._created = _hold_what_was_opened(self._h5, self._file)
        except BaseException as exc:
            h5, aside = getattr(self, "_h5", None), self._previous
            with contextlib.suppress(Exception):  # (as above: the first error is the one to say)
                if h5 is not None and h5.id.valid:
                    h5.close()
            _unlock(self._own_lock)
            with contextlib.suppress(Exception):
                self._put_back()
            if aside is not None and not self.restored_previous:
                exc.previous_kept_in = aside  # for the caller's last line: not back under its name
            if self._replaces is not None and getattr(exc, "errno", None) in (errno.EACCES, errno.EPERM, errno.EROFS):
                raise self._unwritable_folder(exc.errno) from None
            raise

    def _where(self, mode, overwrite, in_place) -> tuple[Path, Path | None]:
        """The file to write, and the file it replaces when closed (None: written in place).

        Why the link's target: renamed over a symbolic link, the new file would replace the link
        and leave the file it points at stale; its temporary is made beside the target so the
        rename stays on one file system."""
        if mode == "a":
            return resolved(self.path), None
        target = check_output(self.path, overwrite=overwrite)  # a link's target; loops, folders refused
        if in_place or not target.exists():
            return target, None
        _remove_stale(target)  # a killed overwrite's temporary, its process gone
        return _temporary_name(target), target

    @property
    def previous(self) -> Path | None:
        """The old file an ``in_place`` overwrite keeps aside until the first frame is on disk
        (None: there is none, or it has gone)."""
        return self._previous

    def _set_aside(self, frame_bytes: int | None) -> Path | None:
        """Rename the old file to its hidden sibling; refused (the old file untouched) when the
        first frame cannot fit beside it or the folder takes no rename."""
        old = self._file
        free, need = self._free_bytes(), (frame_bytes or 0) + self._LAYOUT_BYTES
        if free < need + self.reserve_bytes:  # the file's layout too: libhdf5 crashed beginning one on a full disk
            raise OSError(
                errno.ENOSPC,
                f"{shown(self.path)}: disk full: {free} bytes free, the new file's layout and first frame need {need} plus "
                f"{self.reserve_bytes} in reserve beside the old file, which is kept until the new file's "
                "first frame; nothing was written, the old file is unchanged; free space or write elsewhere",
            )
        # Locked as libhdf5 locks a file it writes (flock): a run writing or resuming the file holds
        # it, and renaming it from under that run (two overwrites at once) lost one run's frames
        # while both said "written". The lock then stays on the set-aside file, the inode it
        # follows, until it goes back or away: it says its run is alive (a PID can be reused)
        fd, state = _try_lock(old)
        if state == "absent":  # gone since it was seen (another run set it aside): nothing to keep
            return None
        if state == "busy":
            raise OutputError(
                old,
                "is open in another program (a run writing or resuming it, or a viewer): not overwritten while it is",
                errno.EBUSY,
            )
        aside = _previous_name(old)
        try:
            os.rename(old, aside)
        except BaseException as exc:
            if fd is not None:
                os.close(fd)
            if isinstance(exc, OSError) and exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
                raise OutputError(
                    old,
                    f"cannot be overwritten: its folder {old.parent} is not writable, so the old file cannot "
                    "be kept beside it until the new file's first frame; make the folder writable or write "
                    "to another folder",
                    exc.errno,
                ) from None
            raise
        self._aside_lock[0] = fd
        _fsync(old.parent)
        return aside

    def _unlock_previous(self) -> None:
        _unlock(self._aside_lock)

    def _put_back(self) -> None:
        """No frame of the new file: the old file kept aside goes back under its name -- over this
        writer's own new file only, never over one another run made there meanwhile."""
        aside, self._previous = self._previous, None
        if aside is None:
            return
        try:
            self.restored_previous = _put_back_file(aside, self._file, getattr(self, "_created", None))
        except OSError as exc:
            # the folder turned unwritable (or the file system refused) before the first frame:
            # the old file stays hidden, unlocked so that the next run of this name puts it back
            self.previous_kept_in = aside
            warnings.warn(
                f"{shown(self.path)}: the previous series could not be put back ({exc.strerror or exc}); it stays in {shown(aside)}",
                stacklevel=3,
            )
            return
        finally:
            self._unlock_previous()
        if not self.restored_previous:
            self.previous_kept_in = aside
            warnings.warn(
                f"{shown(self.path)}: another program made a file under this name meanwhile; the previous series "
                f"stays in {shown(aside)} (rename it to keep it)",
                stacklevel=3,
            )

    def _drop_previous(self) -> None:
        """The first frame is on disk: the old file kept aside may go."""
        aside, self._previous = self._previous, None
        _fsync(self._file)  # the frame on disk before the old file leaves it: a power cut keeps one
        try:
            _remove(aside)
            _fsync(aside.parent)
        except OSError as exc:  # the run goes on; the file is named now, and by every later run
            warnings.warn(
                f"{shown(self.path)}: the previous series, kept in {shown(aside)} until this run's first frame, could not "
                f"be removed ({exc.strerror or exc}); rename it to keep it, or remove it",
                stacklevel=3,
            )
        finally:
            self._unlock_previous()

    def _kept(self) -> str:
        """What an overwrite built beside the old file leaves when it stops, for a refusal."""
        return (
            "; the old file is kept unchanged and the new frames are discarded as the writer closes: an "
            "overwrite builds the new "
            "file beside the old one and needs room for both until it completes; free space or write elsewhere"
        )

    def _check_overwrite_room(self, frame_bytes: int) -> None:
        """Before the temporary is made: refuse an overwrite built beside the old file when not even
        one frame fits (ENOSPC), and warn when a new file as large as the old one will not (the old
        one is not freed until the new one replaces it; truncated ``in_place``, it was)."""
        free, old = self._free_bytes(), self._replaces.stat().st_size
        first = frame_bytes + self.reserve_bytes
        if free < first:
            raise OSError(
                errno.ENOSPC,
                f"{shown(self.path)}: disk full: {free} bytes free, a frame needs {frame_bytes} plus "
                f"{self.reserve_bytes} in reserve; nothing was written" + self._kept(),
            )
        need = old + self.reserve_bytes + (first if self.ballast else 0)
        if free < need:
            warnings.warn(
                f"{shown(self.path)}: overwriting: the old file ({_human(old)}) is not freed until the new one is "
                f"complete and renamed over it, and {_human(free)} are free: a new file as large will not fit "
                "(an overwrite needs room for both until it completes); free space or write elsewhere",
                UserWarning,
                stacklevel=3,
            )

    def _check_opening_room(self, mode: str) -> None:
        """Before the file is created, truncated or reopened: refuse (ENOSPC) when the disk has no
        room for the file's layout and :attr:`reserve_bytes`. libhdf5 began a new file with 4 KiB
        free, failed half-way through its layout and crashed the process (SIGSEGV) freeing it."""
        free = self._free_bytes()
        need = self._LAYOUT_BYTES + self.reserve_bytes
        if free < need:
            raise OSError(
                errno.ENOSPC,
                f"{shown(self.path)}: disk full: {free} bytes free, "
                + ("a new experiment file" if mode == "w" else "appending")
                + f" needs {need} ({self.reserve_bytes} of them in reserve); nothing was written",
            )

    def _unwritable_folder(self, err: int) -> OutputError:
        """The one-line error of an overwrite whose temporary cannot be made beside the file."""
        folder = self._replaces.parent
        if err == errno.EROFS:
            return OutputError(self._replaces, f"is on a read-only file system ({folder}); choose another output", err)
        return OutputError(
            self._replaces,
            f"cannot be replaced: its folder {folder} is not writable, so the new file cannot be built beside it "
            "and renamed over it (nor, in_place, the old one kept aside); make the folder writable or write to "
            "another folder",
            err,
        )

    # -- layout -------------------------------------------------------------------------------
    def _create(self, shape, pitch, source, detector_name, title):
        h5 = self._h5
        h5.attrs["default"] = ENTRY
        h5.attrs["creator"] = "radiokit"
        entry = h5.create_group(ENTRY)
        _set_class(entry, "NXentry")
        entry.attrs["default"] = "data"
        entry["title"] = title
        entry["start_time"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        entry["definition"] = "NXtomo"
        inst = entry.create_group("instrument")
        _set_class(inst, "NXinstrument")
        src = inst.create_group("source")
        _set_class(src, "NXsource")
        # Fixed-length strings: read() reads these, and reading a variable-length string parses
        # the global heap, which libhdf5 can hang or crash on when the file is corrupt.
        # no name given: none written (it had been the L8121-01's, claimed for any lab's tube)
        for key, value in (("type", "Fixed Tube X-ray"), ("name", source.get("name")), ("probe", "x-ray")):
            if value is not None:
                src[key] = np.bytes_(str(value).encode("utf-8"))
        for key, unit in (("voltage", "kV"), ("current", "uA")):
            value = source.get(f"{key}_{unit.lower()}")
            ds = src.create_dataset(key, data=np.nan if value is None else float(value))
            ds.attrs["units"] = unit
        det = inst.create_group("detector")
        _set_class(det, "NXdetector")
        if detector_name is not None:  # fixed-length, as the source's name (see above)
            det["description"] = np.bytes_(detector_name.encode("utf-8"))
        rows, cols = shape
        data = det.create_dataset(
            "data", shape=(0, rows, cols), maxshape=(None, rows, cols), chunks=(1, rows, cols), dtype=np.uint16
        )
        data.attrs["interpretation"] = "image"
        for axis in ("x_pixel_size", "y_pixel_size") if pitch is not None else ():
            ds = det.create_dataset(axis, data=pitch[0] * 1e-3)
            ds.attrs["units"] = "m"
            if pitch[1] is not None:
                ds.attrs["pixel_size_from"] = np.bytes_(pitch[1].encode("utf-8"))
        det.create_dataset("pixel_mask", data=np.zeros(shape, np.uint32), compression="gzip")
        sample = entry.create_group("sample")
        _set_class(sample, "NXsample")
        comp = sample.create_group("compression")
        _set_class(comp, "NXcollection")
        ctrl = entry.create_group("control")
        _set_class(ctrl, "NXcollection")
        for group, name, dtype, _, units in _SERIES:
            ds = h5[group].create_dataset(name, shape=(0,), maxshape=(None,), chunks=(256,), dtype=dtype)
            if units:
                ds.attrs["units"] = units
        nxdata = entry.create_group("data")
        _set_class(nxdata, "NXdata")
        nxdata.attrs["signal"] = "data"
        nxdata["data"] = h5py.SoftLink(f"/{FRAMES}")
        nxdata["image_key"] = h5py.SoftLink(f"/{IMAGE_KEY}")
        entry.attrs["frames_complete"] = 0
        h5.flush()
        self._n = 0

    def _reopen(self, shape):
        h5 = self._h5
        if FRAMES not in h5:
            raise FormatError(self.path, f"not an experiment file: /{FRAMES} is missing")
        data = h5[FRAMES]
        if shape is not None and tuple(shape) != data.shape[1:]:
            raise ValueError(f"{shown(self.path)}: frames are {data.shape[1:]}, not {tuple(shape)}")
        # A crash between resizing and the counter update leaves a partial frame: drop it.
        # checked first: `true` (1) or a negative count here truncated the frames already taken
        n = _frames_complete(self.path, h5, data.shape[0])
        n = min([n, data.shape[0]] + [h5[g][name].shape[0] for g, name, *_ in _SERIES if name in h5[g]])
        for ds in [data] + [h5[g][name] for g, name, *_ in _SERIES]:
            if ds.shape[0] != n:
                ds.resize(n, axis=0)
        self._n = n

    def _reopen_bit_depth(self, bit_depth) -> None:
        """``bit_depth`` given to append to a file: recorded where the file has none (it was
        ignored, and the readers and the writer's own warning went on assuming 12 bits); refused
        where the file records another, which its frames so far were judged by."""
        if bit_depth is None:
            return
        recorded = read_bit_depth(self.path, self._h5, DETECTOR)
        if recorded is None and "bit_depth_readout" not in self._h5[DETECTOR]:
            self._h5[DETECTOR]["bit_depth_readout"] = int(bit_depth)
        elif recorded != int(bit_depth):
            said = recorded if recorded is not None else "an unreadable value"
            raise ValueError(
                f"{shown(self.path)}: records bit_depth_readout {said}; bit_depth={bit_depth} given to append"
            )

    # -- writing ------------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Frames safely on disk."""
        return self._n

    @property
    def h5(self) -> h5py.File:
        """The open file (read-only use: the layout's writers are this class's methods)."""
        return self._h5

    #: Free space (bytes) a frame must leave on the disk before any of it is written. libhdf5
    #: cannot survive a write that fails half-way -- the file it leaves does not open, and closing
    #: it crashes the process -- so a frame that might not fit is refused while the file is whole.
    reserve_bytes = 1 << 20
    #: What a new file's layout (groups, attributes, empty datasets) takes, at most, before a frame.
    _LAYOUT_BYTES = 1 << 16
    #: Space held beside the file (``.<name>.reserve``) while frames are written, one frame plus
    #: :attr:`reserve_bytes`: if another program fills the disk between the check and the write
    #: (the vendor software writes its frames to the same disk), it is released so libhdf5 can
    #: finish what it started and the file stays whole.
    ballast = True

    def _check_range(self, frame: np.ndarray, key: int) -> None:
        """Warn, as the readers will, of values above the ADC's top: the file's ``bit_depth`` or,
        not given, the C7942's 12 bits the readers assume. Said at writing, where the frames can
        still be written right (a byte order, a 16-bit panel without ``bit_depth=16``), not at
        every read after. The first frame of each kind only: a full pass over each frame would add
        ~15 % to the acquisition's bookkeeping, and a wrong layout shows in every frame."""
        checked = self.__dict__.setdefault("_range_checked", set())
        if key in checked:
            return
        checked.add(key)
        bits = self.__dict__.get("_bits")
        if bits is None:  # as the readers take it: an unreadable value is none (0: the 12 they assume)
            recorded = read_bit_depth(self.path, self._h5, DETECTOR)
            bits = self._bits = recorded if recorded is not None and recorded <= 16 else 0
        top = (1 << (bits or 12)) - 1
        if frame.size == 0 or int(frame.max()) <= top:
            return
        swap = "byte-swap the frames before appending them (frame.byteswap())"
        cause = bit_depth_cause(frame, bits or 12, swap_advice=swap) or (
            "another panel's range: pass bit_depth= its ADC bits (16 for one that saturates at 65535)"
            if not bits
            else "another panel's range, data rescaled, or a wrong byte or bit order"
        )
        declared = f"bit_depth={bits}" if bits else "no bit_depth given: the C7942's 12 bits, as readers assume"
        message = BitDepthWarning(
            f"{shown(self.path)}: frame {self._n} (image_key {key}) has values up to {int(frame.max())}, above "
            f"0..{top} ({declared}); {cause}. Readers will warn of it too"
        )
        message.path = str(self.path)
        warnings.warn(message, stacklevel=3)

    def append(
        self, frame, *, image_key, step=-1, ratio=None, gap_mm=None, time_s=None, voltage_kv=None, current_ua=None
    ) -> int:
        """Append one frame and its bookkeeping, then flush. Returns the frame's index.

        The frame is recorded in three flushed steps: its row, labelled ``INVALID`` (3) and
        counted in ``frames_complete``; its pixels; its real ``image_key``. A process killed in
        between leaves a frame labelled invalid -- never a frame of zeros labelled complete -- and
        ``--resume`` takes it again.

        Raises
        ------
        OSError
            ``ENOSPC`` when the disk has no room for the frame and :attr:`reserve_bytes`, ``EFBIG``
            when they would take the file past its size limit (the process's or the file
            system's) -- nothing written: the file stays complete up to the previous frame --, or any error writing it
            (the frame stays labelled invalid and the file takes no more frames). The message
            names the file and the frame.
        """
        frame = np.asarray(frame)
        data = self._h5[FRAMES]
        if frame.shape != data.shape[1:]:
            raise ValueError(
                f"{shown(self.path)}: frame shape {frame.shape} does not match the file's {data.shape[1:]}"
            )
        if frame.dtype != np.uint16:
            frame = self._as_counts(frame)
        if int(image_key) not in (0, 1, 2, 3):
            raise ValueError(f"image_key={image_key}: expected 0 projection, 1 flat, 2 dark, 3 invalid")
        self._check_range(frame, int(image_key))
        if ratio is not None and not _ratio_ok(ratio):
            raise ValueError(f"{shown(self.path)}: ratio={ratio!r}: {RATIO_RULE}")
        i = self._n
        if getattr(self, "_failed", None):
            raise OSError(errno.EIO, f"{shown(self.path)}: takes no more frames after a failed write ({self._failed})")
        self._hold_ballast(frame.nbytes + self.reserve_bytes)
        self._check_room(frame.nbytes, i)
        values = {
            "image_key": ImageKey.INVALID,
            "step": int(step),
            "ratio": np.nan if ratio is None else float(ratio),
            "gap": np.nan if gap_mm is None else float(gap_mm) * 1e-3,
            "time": time.time() if time_s is None else float(time_s),
            "voltage": np.nan if voltage_kv is None else float(voltage_kv),
            "current": np.nan if current_ua is None else float(current_ua),
        }
        try:
            data.resize(i + 1, axis=0)
            for group, name, *_ in _SERIES:
                ds = self._h5[group][name]
                ds.resize(i + 1, axis=0)
                ds[i] = values[name]
            self._h5[ENTRY].attrs["frames_complete"] = i + 1
            self._h5.flush()
            self._n = i + 1  # counted, labelled invalid
            data[i] = frame
            self._h5.flush()  # the pixels are on disk
            self._h5[DETECTOR]["image_key"][i] = int(image_key)
            self._h5.flush()  # only now is the frame what it claims to be
            if self._previous is not None:
                self._drop_previous()
        except Exception as exc:
            raise self._write_failed(
                exc,
                f"frame {i}",
                self._kept() if self._replaces is not None else "; it stays labelled invalid",
            ) from None
        return i

    def _as_counts(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` as uint16 where that loses nothing: integers in range, or floats holding whole
        counts (a raw frame an image program saved as float); else ValueError saying why."""
        if frame.dtype.kind not in "uif":
            raise ValueError(f"{shown(self.path)}: raw frames are stored as uint16; got {frame.dtype}")
        if frame.size and not (np.all(np.isfinite(frame)) and frame.min() >= 0 and frame.max() <= 65535):
            raise ValueError(
                f"{shown(self.path)}: raw frames are stored as uint16 (0 to 65535); got {frame.dtype} values outside "
                "that range or not finite"
            )
        if frame.dtype.kind == "f" and not np.array_equal(frame, np.rint(frame)):
            # an averaged dark or flat: rounding it here would change the data without a word
            raise ValueError(
                f"{shown(self.path)}: raw frames are stored as uint16; this {frame.dtype} frame holds values that "
                "are not whole counts (an average?): append the raw frames it was made from, or round it "
                "yourself, np.rint(frame).astype(np.uint16), knowing what that loses"
            )
        return frame.astype(np.uint16)

    def check_room(self) -> None:
        """Refuse now, as :meth:`append` would, when the disk or the file's size limit has no room
        for the next frame and :attr:`reserve_bytes` (its ballast held first, as append holds it).
        For a caller about to do what cannot be undone to make that frame -- an acquisition's
        X-rays -- so the work is not started for a frame the file would refuse. Nothing is
        written, and the file still takes frames after a refusal.

        Raises
        ------
        OSError
            ``ENOSPC`` or ``EFBIG`` with append's line (naming the file and the frame), or ``EIO``
            when the file takes no more frames after a failed write."""
        failed = getattr(self, "_failed", None)
        if failed:
            raise OSError(errno.EIO, f"{shown(self.path)}: takes no more frames after a failed write ({failed})")
        self._hold_ballast(self._frame_bytes + self.reserve_bytes)
        try:
            self._check_room(self._frame_bytes, self._n)
        finally:
            # a refusal of a frame not yet taken: unlike append's, it does not end the file's frames
            self._failed = failed

    def _write_failed(self, exc: BaseException, what: str, kept: str) -> OSError:
        """After a write that failed inside libhdf5: the ballast's room given back so libhdf5 can
        write what it holds (the file is whole again), no more writes taken, and the one-line
        error naming the file and ``what``."""
        self._failed = " ".join(str(exc).split())[:200]
        self._drop_ballast()
        try:
            self._h5.flush()
        except Exception:
            pass
        code = errno.ENOSPC if "No space left" in str(exc) or getattr(exc, "errno", None) == errno.ENOSPC else errno.EIO
        return OSError(code, f"{shown(self.path)}: {what} could not be written ({self._failed})" + kept)

    def _guarded_write(self, nbytes: int, what: str):
        """A context for a write of about ``nbytes`` besides a frame (``what``, for the message):
        refused (ENOSPC) before any of it is written when the disk has no room for it and
        :attr:`reserve_bytes`, as a frame is -- libhdf5 cannot survive a write that fails half-way
        -- and, if the disk fills in between, handled as a frame cut short."""
        if getattr(self, "_failed", None):
            raise OSError(errno.EIO, f"{shown(self.path)}: takes no more writes after a failed write ({self._failed})")
        # the frames' ballast, not one sized for this write: a simulation record's (90 MB raw on
        # the full panel) would double the room it needs; it covers a write up to a frame's size
        self._hold_ballast(self._frame_bytes + self.reserve_bytes)
        self._refuse_without_room(nbytes, f"{what} needs {nbytes}", "; nothing of it was written", self._n)
        return _Guard(self, what)

    def _refuse_without_room(self, nbytes: int, needs: str, then: str, n_before: int) -> None:
        """ENOSPC, naming the file, when the disk has no room for ``nbytes`` and the reserve
        (``needs``: what needs them, for the message); built beside an old file, the new one is then
        discarded as it closes, even after a close without an error."""
        free = self._free_bytes()
        if free < nbytes + self.reserve_bytes:
            if self._replaces is not None:
                self._failed = "disk full"
            kept = self._kept() if self._replaces is not None else f"; the {n_before} frame(s) before it are complete"
            raise OSError(
                errno.ENOSPC,
                f"{shown(self.path)}: disk full: {free} bytes free, {needs} plus {self.reserve_bytes} in reserve{then}{kept}",
            )

    @property
    def _frame_bytes(self) -> int:
        return math.prod(self._h5[FRAMES].shape[1:]) * np.dtype(np.uint16).itemsize

    def _check_room(self, nbytes: int, i: int) -> None:
        """Refuse frame ``i`` (``nbytes``) while the file is whole when the disk or the file's size
        limit has no room for it and :attr:`reserve_bytes`: ENOSPC or EFBIG, naming the file and frame."""
        # built beside the old file, the new one is discarded on a refusal, even if the caller goes
        # on to close() without an error: a part of it never replaces a complete old file
        kept = f"; the {i} frame(s) before it are complete"
        if self._replaces is not None:
            kept = self._kept()
        self._refuse_without_room(nbytes, f"frame {i} needs {nbytes}", "", i)
        size, limit = self._size_and_limit()
        if size + nbytes + self.reserve_bytes > limit:
            # a file-size limit (ulimit -f, or a FAT32-formatted disk's 4 GiB) fails the
            # write half-way just as a full disk does, and libhdf5 then leaves a file that does not
            # open: refused while the file is whole
            if self._replaces is not None:
                self._failed = "file size limit"
                kept = "; the old file is kept unchanged and the new frames are discarded as the writer closes"
            raise OSError(
                errno.EFBIG,
                f"{shown(self.path)}: file size limit: the file has {size} bytes and may not exceed {limit} "
                f"(the process's file-size limit or the file system's); frame {i} needs {nbytes} plus "
                f"{self.reserve_bytes} in reserve" + kept,
            )

    def _free_bytes(self) -> int:
        """Bytes free for this file on its file system."""
        return shutil.disk_usage(self._file.parent).free

    def _size_and_limit(self) -> tuple[int, float]:
        """The file's size, and the largest it may grow to: the process's ``RLIMIT_FSIZE`` and, on
        a FAT file system, 4 GiB - 1, whichever is lower."""
        return self._file.stat().st_size, file_size_limit(self._file.parent)

    @property
    def _ballast_path(self) -> Path:
        # named after the file kept, beside it on its disk (a link's folder may be on another)
        dest = self._replaces or self._file
        return dest.with_name(f".{dest.name}.reserve")

    def _hold_ballast(self, nbytes: int) -> int:
        """Hold ``nbytes`` of disk in the ballast file (allocated, not sparse); returns the bytes
        held. Growing it on a full disk holds what it can: the space check that follows refuses
        the frame."""
        if not self.ballast:
            return 0
        path = self._ballast_path
        try:
            held = path.stat().st_size
        except OSError:
            held = 0
        if held >= nbytes:
            return held
        try:
            with open(path, "ab") as fh:
                os.posix_fallocate(fh.fileno(), 0, nbytes)
            return nbytes
        except OSError:  # a full disk, or a file system without fallocate: no ballast then
            try:
                path.unlink()
            except OSError:
                pass
            return 0

    def _drop_ballast(self) -> None:
        try:
            self._ballast_path.unlink()
        except OSError:
            pass

    def set_pixel_mask(self, mask):
        mask = np.asarray(mask, dtype=np.uint32)
        ds = self._h5[f"{DETECTOR}/pixel_mask"]
        if mask.shape != ds.shape:
            raise ValueError(f"pixel_mask shape {mask.shape} does not match frames {ds.shape}")
        with self._guarded_write(mask.nbytes, "the pixel mask"):  # gzip: at worst its raw size
            ds[...] = mask
            self._h5.flush()

    def record_run(self, protocol_toml: str, devices: dict) -> None:
        """Record what wrote the file: the protocol (TOML text, so ``--resume`` can check it) and
        the devices (JSON)."""
        devices_json = strict_json.dumps(devices, default=str)  # no NaN/Infinity words
        nbytes = len(protocol_toml.encode("utf-8", "surrogatepass")) + len(devices_json.encode("utf-8"))
        with self._guarded_write(nbytes, "the run's record (protocol and devices)"):
            self._h5[ENTRY].attrs["protocol"] = protocol_toml
            self._h5[ENTRY].attrs["devices"] = devices_json
            self._h5.flush()

    def frames_labelled(self, key) -> tuple[np.ndarray, np.ndarray]:
        """The indices and pixels of the frames written so far labelled ``key`` (those of the run a
        resume continues too): the acquisition judges its darks and flats from them as it goes."""
        idx = np.flatnonzero(self._h5[IMAGE_KEY][: self._n] == key)
        data = self._h5[FRAMES]
        return idx, data[idx] if idx.size else np.zeros((0, *data.shape[1:]), data.dtype)

    def mark_invalid(self, indices) -> None:
        """Label frames ``indices`` ``ImageKey.INVALID``: kept, never taken for a projection or a flat."""
        ds = self._h5[IMAGE_KEY]
        indices = [int(i) for i in indices]
        for i in indices:
            if not 0 <= i < self._n:
                raise IndexError(f"{shown(self.path)}: frame {i} out of range (0..{self._n - 1})")
        # never refused for room, unlike the other writes: these labels are what keeps a suspect
        # frame from being taken for a good one, and they rewrite chunks already on disk; the
        # ballast's room is given back first for what libhdf5 writes besides
        self._drop_ballast()
        with _Guard(self, "the invalid labels"):
            for i in indices:
                ds[i] = ImageKey.INVALID
            self._h5.flush()

    def write_simulation(self, record) -> None:
        """Add ``/entry/simulation`` (a :class:`radiokit.io.SimulationRecord`) to a simulated file."""
        from radiokit.io._simulation import write_simulation

        # lzf may not shrink a field: at worst the arrays' raw size, and the scene's text
        arrays = (record.line_integral, record.inclusion_mask, *record.displacement.values())
        nbytes = sum(np.asarray(a).nbytes for a in arrays) + len(record.scene_toml.encode("utf-8")) + (64 << 10)
        with self._guarded_write(nbytes, "the simulation record"):
            write_simulation(self._h5, record)

    def close(self, *, keep=True):
        """Close the file. Overwriting (not ``in_place``), the new file then replaces the old one,
        unless a frame failed or ``keep`` is False (the ``with`` block ended in an exception): the
        old file stays and the new one is removed. A new file (no old one) that took no frame is
        removed when ``keep`` is False: it holds nothing, and left it would block the rerun."""
        if self._h5.id.valid:
            # libhdf5 writes as it closes: the room held for it is given back first (dropped after,
            # a disk another program had filled since the last frame made the close fail half-way,
            # and the file no longer opened: every frame lost)
            self._drop_ballast()
            failed = None
            try:
                # the end time is a nicety: not written where it might meet a full disk
                if not getattr(self, "_failed", None) and self._free_bytes() >= self._LAYOUT_BYTES:
                    self._h5[ENTRY].attrs["end_time"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
            finally:
                try:
                    try:
                        self._h5.close()
                    except Exception as exc:  # a built-beside overwrite is then discarded, not renamed
                        failed = " ".join(str(exc).split())[:200]
                    self._finish(keep and not getattr(self, "_failed", None) and failed is None)
                    if not keep and self._n == 0 and self._began:
                        self._discard_empty()
                finally:
                    _unlock(self._own_lock)
                    self._put_back()
            if failed is not None:
                code = errno.ENOSPC if "No space left" in failed else errno.EIO
                raise OSError(code, f"{shown(self.path)}: could not be closed ({failed})")

    def _discard_empty(self) -> None:
        """Remove the new file a failed ``with`` block made and never wrote a frame to: left, it
        only blocked the rerun ("exists; raw data is never overwritten"). Still under this
        writer's lock, and only if the name still holds the file it made."""
        if _identity(self._file) == self._created:
            with contextlib.suppress(OSError):
                os.unlink(self._file)
                _fsync(self._file.parent)

    def _finish(self, keep: bool) -> None:
        """Rename the new file over the one it replaces (``keep``), else remove it."""
        tmp, target, self._replaces = self._file, self._replaces, None
        if getattr(self, "_unclosed", None) is not None:
            self._unclosed.detach()  # closed: whatever becomes of the file, it was said
        if target is None:
            return
        if not keep:
            _remove(tmp)
            return
        try:
            settle()  # a stop lost while it was written, its delivery not run yet: not renamed into place
            _fsync(tmp)  # the bytes on disk before the name: a power cut leaves the old file or the new
            _keep_mode(tmp, target)
            os.replace(tmp, target)
            _fsync(target.parent)
        except BaseException:
            _remove(tmp)
            raise

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.close(keep=exc_type is None)


class _Guard:
    """:meth:`ExperimentWriter._guarded_write`'s context: a write that fails inside libhdf5 ends
    as a frame cut short does."""

    def __init__(self, writer: ExperimentWriter, what: str):
        self.writer, self.what = writer, what

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        # what libhdf5 raises when a write fails (OSError, RuntimeError); not the refusals of the
        # code inside, said before it wrote (a second simulation record: FileExistsError)
        if not isinstance(exc, (OSError, RuntimeError)) or isinstance(exc, FileExistsError):
            return False
        w = self.writer
        raise w._write_failed(exc, self.what, w._kept() if w._replaces is not None else "") from None


def _unclosed(
    path: str,
    tmp: str | None,
    ballast: Path | None,
    previous: Path | None = None,
    aside_lock: list | None = None,
    own_lock: list | None = None,
    created: tuple | None = None,
) -> None:
    """A writer garbage-collected or at interpreter exit unclosed: its reserve removed, the old
    file an in-place overwrite kept aside put back if it is still there (no frame was written),
    and for an overwrite built beside the old file (``tmp``), a warning naming both files."""
    if ballast is not None:
        try:
            ballast.unlink()
        except OSError:
            pass
    # the sibling outlives the first frame only where its removal failed: then the name holds
    # the new run's frames, which putting the old file back would destroy
    if previous is not None and previous.exists() and not _holds_a_frame(resolved(path)):
        with contextlib.suppress(OSError):
            _put_back_file(previous, resolved(path), created)
    for lock in (aside_lock, own_lock):
        if lock is not None:
            _unlock(lock)
    if tmp is None:
        return
    warnings.warn(
        f"{shown(path)}: ExperimentWriter never closed: {shown(path)} is still the old file, unchanged; the new frames are in "
        f"{shown(tmp)}, not renamed over it (an unclosed writer may be a crash, or a refused one hold part of a run). "
        "Use `with ExperimentWriter(...) as w:` or call close(). Remove that file (an overwrite of "
        f"{shown(path)} by a later process removes it; this process's do not), or rename it over {shown(path)} by "
        "hand only if "
        "it holds the whole run",
        UserWarning,
        stacklevel=1,  # no caller of the user's to name: the garbage collector or interpreter exit calls it
    )


#: the words of a reader's refusal that advise its options (FormatError.advice): a command without
#: the option (radiokit process) says its own remedy in their place ("unless asked for" too:
#: nothing it can ask with)
EXTERNAL_ADVICE = "unless asked for (allow_external=True; --allow-external)"
DATASET_ADVICE = "pass --dataset PATH (dataset= in Python) to read one"


def _refuse_external(path, what):
    raise FormatError(
        path,
        f"{what}: data outside this file is not read {EXTERNAL_ADVICE}",
        advice={"allow_external": EXTERNAL_ADVICE},
    )


@dataclass(frozen=True)
class ExperimentProgress:
    """How far an experiment file got, for ``radiokit acquire --resume``.

    Attributes
    ----------
    frames_complete : int
    image_key, step : (frames_complete,) arrays
    protocol : str or None
        The TOML text of the protocol that wrote the file.
    devices : str or None
        The JSON description of its devices.
    """

    frames_complete: int
    image_key: np.ndarray
    step: np.ndarray
    protocol: str | None = None
    devices: str | None = None


def restore_previous(path, *, dry_run=False, found: list | None = None) -> list[tuple[bool, str]]:
    """Put back the file an ``in_place`` overwrite of ``path`` kept aside when the process that
    kept it is gone and left no frame of its own under the name (killed before its first frame:
    kill -9, a power cut). Every run on an experiment file calls it first. ``dry_run``: decide
    the same, move nothing, and say what a run would do (a dry run promises to touch nothing).
    ``found``: a list the files put back (or, ``dry_run``, that a run would put back) are appended
    to -- a dry run plans from the file the run would find under the name.

    Returns
    -------
    list of (restored, line)
        One per file found: ``(True, line)`` when it was put back, ``(False, line)`` when it stays
        beside (the name holds the new file's frames, or another host's process kept it), the
        line naming it for the operator. A file kept by a process still running is its own.
    """
    target = resolved(path)
    host = socket.gethostname().split(".")[0]
    head, digest = _head(target, False, "previous"), _name_digest(target)
    said = []
    for old in sorted(target.parent.glob(f".{glob.escape(head)}.previous-*{glob.escape(target.suffix)}")):
        m = re.fullmatch(rf"\.{re.escape(head)}\.previous-(.+)-(\d+)-{digest}{re.escape(target.suffix)}", old.name)
        if m is None:
            continue  # another file's (a long name's head is cut: the digest tells them apart)
        here = m.group(1) == host
        with _locked(old) as free:
            if not free:
                continue  # a run in progress: until its first frame, the old file is its to put back
            restored = False
            # never over frames, nor over a run writing the name (its file, locked, unreadable to
            # read_progress, counts as holding frames; where libhdf5 locks nothing, the writer's
            # own lock refuses the second look), which is held while the file is put back: a run
            # starting meanwhile meets it. (One look with the lock held: libhdf5's own, in
            # read_progress, would meet it.)
            if here and not _holds_a_frame(target):
                with _locked(target, absent=True) as target_free:
                    if target_free and not dry_run:
                        os.replace(old, target)
                        _fsync(target.parent)
                    restored = target_free
        if restored and found is not None:
            found.append(old)
        if restored and dry_run:
            said.append(
                (
                    True,
                    f"{shown(path)}: a run would first restore the previous series from {shown(old.name)} (an --overwrite "
                    "stopped before its first frame had set it aside); this dry run moved nothing and plans "
                    "for the name as it stands",
                )
            )
        elif restored:
            said.append(
                (
                    True,
                    f"{shown(path)}: restored the previous series from {shown(old.name)} (an --overwrite stopped before its "
                    "first frame had set it aside)",
                )
            )
        else:
            said.append(
                (
                    False,
                    f"{shown(path)}: a previous series is still kept in {shown(old)} (set aside by an --overwrite; the name now "
                    f"holds another file -- the new series' frames, a run writing, or a file of another program -- "
                    f"or it was set aside on another host); rename it to keep it (not over {shown(target.name)}), or "
                    "remove it",
                )
            )
    return said


#: flock's errors where the file system keeps no locks (some network mounts)
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EINVAL}


def _name_digest(path: Path) -> str:
    """Eight hex digits of the whole name: a name longer than a temporary's room is cut to its
    head, and two names sharing it took each other's set-aside file for their own."""
    return hashlib.sha256(os.fsencode(path.name)).hexdigest()[:8]


def _previous_name(path: Path) -> Path:
    """``.HEAD.previous-HOST-PID-DIGEST.SUFFIX`` beside ``path``: where an in-place overwrite keeps
    the old file until its first frame."""
    return path.with_name(
        f".{_head(path, False, 'previous')}.previous-{_owner_tag()}-{_name_digest(path)}{path.suffix}"
    )


@contextlib.contextmanager
def _locked(path: Path, absent=False):
    """Whether ``path`` is free -- a set-aside file's run gone (the lock dies with its process, a
    reboot too), an experiment file no run writes -- holding its lock meanwhile so that no other
    run takes it as well. A file that is not there is ``absent`` (gone meanwhile: another run put
    it back)."""
    try:
        fd, state = _try_lock(path)
    except OSError:
        fd, state = None, "busy"
    try:
        # without locks on the file system nothing can tell: free, as before locks
        yield {"locked": True, "no locks": True, "absent": absent, "busy": False}[state]
    finally:
        if fd is not None:
            os.close(fd)


#: below this, an unreadable file that begins as HDF5 does is a new file's start, not a file that held frames
_HEADER_ONLY_BYTES = 4096
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _holds_a_frame(path: Path) -> bool:
    """``path`` holds a frame that is not labelled invalid. Not there, it holds none; there but
    unreadable, it may (a run writing it, a file of the user's): never written over."""
    if not os.path.lexists(path):
        return False
    try:
        return bool(np.any(read_progress(path).image_key != ImageKey.INVALID))
    except Exception:
        # a run killed (or a power cut) as libhdf5 began the file leaves 0 to a few hundred bytes
        # of HDF5's start, less than the layout of an experiment file without a frame (25 KB): no
        # frame there. Anything else (another program's file) is not written over
        try:
            with open(path, "rb") as fh:
                head = fh.read(_HEADER_ONLY_BYTES)
        except OSError:
            return True
        return not (len(head) < _HEADER_ONLY_BYTES and (not head or head.startswith(_HDF5_SIGNATURE[: len(head)])))


def _identity(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file ``path`` names, or None where nothing is there."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino


def _put_back_file(aside: Path, target: Path, mine: tuple | None) -> bool:
    """Rename ``aside`` to ``target`` where ``target`` is absent or is the file ``mine`` names (a
    writer's own new file, holding no frame); False, ``aside`` kept, where another run made a file
    there meanwhile. os.replace put the old file over a second run's new one, whose frames went
    into an unlinked file while it said "written" (review s36r4): a hard link takes the name only
    where it is free."""
    here = _identity(target)
    if here is not None:
        if here != mine:
            return False
        os.unlink(target)
    try:
        os.link(aside, target)
    except FileExistsError:
        return False  # made meanwhile, between the unlink and the link
    except OSError:  # no hard links on this file system (FAT, some network mounts): the rename
        os.replace(aside, target)
    else:
        os.unlink(aside)
    _fsync(target.parent)
    return True


def _hold_what_was_opened(h5, path: Path) -> tuple[int | None, tuple[int, int]]:
    """Lock the file libhdf5 opened, through a copy of its own descriptor, and check that ``path``
    still names it: (the copy holding the lock, the file's (device, inode)). OSError where another
    program holds that file, or moved it away, between the opening and now.

    Why: where libhdf5 locks nothing (``HDF5_USE_FILE_LOCKING=FALSE``, common on NFS lab machines)
    a second overwrite could set the file aside from under the run writing it, and that run's
    frames went into a file that was then removed (reviews s36r3, s36r5); locked by its name, the
    lock could land on another run's file. Through libhdf5's own open file it is the same lock
    libhdf5 holds, where it holds one."""
    fd = os.dup(h5.id.get_vfd_handle())
    try:
        st = os.fstat(fd)
        mine = (st.st_dev, st.st_ino)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in _NO_LOCKS:
                raise OSError(
                    errno.EBUSY, f"{shown(path)}: another program took the new file as it was opened"
                ) from None
        if _identity(path) != mine:
            raise OSError(errno.EBUSY, f"{shown(path)}: another program moved the new file away as it was opened")
    except BaseException:
        os.close(fd)
        raise
    return fd, mine


def discard_unbegun(path) -> None:
    """Remove the experiment file a failed opening left at ``path``, unless another program holds
    it: two runs started at once on one new name, the second's opening failed on the first's lock,
    and its clean-up unlinked the first run's file while that run wrote its frames into it."""
    try:
        fd, state = _try_lock(Path(path))
    except OSError:
        return
    try:
        if state in ("locked", "no locks"):
            Path(path).unlink(missing_ok=True)
    finally:
        if fd is not None:
            os.close(fd)


def _try_lock(path: Path) -> tuple[int | None, str]:
    """flock ``path`` exclusively, without waiting: (the descriptor holding it, "locked"), or
    (None, "busy") where another holds it (libhdf5's lock in this process too), "absent" where
    nothing is there, "no locks" where the file system keeps none (some network mounts)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None, "absent"
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in _NO_LOCKS:
            return None, "no locks"
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            return None, "busy"
        raise
    return fd, "locked"


def _unlock(holder: list) -> None:
    """Close the descriptor ``holder[0]`` (its lock with it), once."""
    fd, holder[0] = holder[0], None
    if fd is not None:
        os.close(fd)


def read_progress(path, allow_external=False) -> ExperimentProgress:
    """The bookkeeping of an experiment file: its complete frames' keys and steps, and what wrote it.

    Raises
    ------
    FormatError
        The file lacks the experiment layout.
    """
    from radiokit.io._budget import check_budget
    from radiokit.io._layout import open_layout, text

    with open_layout(path, "a radiokit experiment file") as h5:
        check_links(path, h5, IMAGE_KEY, allow_external)
        if ENTRY not in h5 or IMAGE_KEY not in h5:
            raise FormatError(path, f"lacks /{IMAGE_KEY}: not a radiokit experiment file")
        attrs = h5[ENTRY].attrs
        n = _frames_complete(path, h5, 0)
        check_budget(path, 16 * n, f"the keys and steps of {n} frames")
        keys = checked_dataset(path, h5, IMAGE_KEY, "iu", (1,), allow_external)[:n]
        steps = (
            checked_dataset(path, h5, STEP, "iu", (1,), allow_external)[:n] if STEP in h5 else np.full(n, -1, np.int16)
        )
        check_image_keys(path, keys, f"/{IMAGE_KEY}")
        if len(keys) != n or len(steps) != n:
            raise FormatError(
                path,
                f"/{ENTRY}@frames_complete is {n}, but /{IMAGE_KEY} holds {len(keys)} keys "
                f"and /{STEP} {len(steps)} steps",
            )
        notes = {k: None if attrs.get(k) is None else text(attrs[k]) for k in ("protocol", "devices")}
    return ExperimentProgress(n, np.asarray(keys), np.asarray(steps), **notes)


#: A compression ratio is the thickness's fractional reduction: 0 uncompressed, below 1 (flat).
RATIO_RULE = "expected a compression ratio in [0, 1) (the thickness's fractional reduction; NaN: not recorded)"


def _ratio_ok(value) -> bool:
    """``value`` a ratio :data:`RATIO_RULE` takes, or NaN (not recorded). Why refused: a finite
    element code's sign convention (-0.15 for 15 %) or a percentage (15) ordered process's steps
    backwards, and the least compressed step was taken for the reference ("main pair 2->1")."""
    return is_number(value) and (math.isnan(value) or 0 <= value < 1)


def _check_ratios(path, values, name: str) -> None:
    """Refuse, naming the first frame, a recorded ratio outside :data:`RATIO_RULE`'s range."""
    values = np.asarray(values, np.float64)
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(~np.isnan(values) & ~((values >= 0) & (values < 1)))
    if bad.size:
        i = int(bad[0])
        more = f" (and {bad.size - 1} more frame(s))" if bad.size > 1 else ""
        raise FormatError(path, f"{name}[{i}]: frame {i} has ratio {float(values[i]):.6g}{more}; {RATIO_RULE}")


def _whole_numbers(path, values, name: str, what: str) -> np.ndarray:
    """``values`` as integers when a float dataset holds whole numbers (another writer's float64
    steps), else refused naming the first frame: frames are selected by ``steps == s``, so a step
    of 1.5 matched none (process ended in a TypeError) and a key of 0.5 was no kind of frame."""
    values = np.asarray(values)
    if values.dtype.kind != "f":
        return values
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(~np.isfinite(values) | (values != np.round(values)) | (np.abs(values) >= 2**15))
    if bad.size:
        i = int(bad[0])
        more = f" (and {bad.size - 1} more frame(s))" if bad.size > 1 else ""
        raise FormatError(
            path, f"{name}[{i}]: frame {i} has {what} {float(values[i])!r}{more}; expected a whole number"
        )
    return values.astype(np.int16)


def check_image_keys(path, keys, name) -> None:
    """Refuse, naming the first, a key that is none of NXtomo's four: every reader selects frames
    by ``keys == k``, so a frame keyed 7 was silently neither projection, flat nor dark (a step's
    only projection dropped, the run measured on the others)."""
    keys = np.asarray(keys)
    bad = np.flatnonzero((keys < 0) | (keys > 3))
    if bad.size:
        i = int(bad[0])
        more = f" (and {bad.size - 1} more frame(s))" if bad.size > 1 else ""
        raise FormatError(
            path,
            f"{name}[{i}]: frame {i} has image_key {int(keys[i])}{more}; "
            "expected 0 projection, 1 flat, 2 dark or 3 invalid",
        )


def check_links(path, h5, name, allow_external, depth=0):
    """Refuse an external link anywhere on the way to ``name`` (checked before it is followed);
    with ``allow_external``, one whose target cannot be opened, named (libhdf5's "can't open file"
    named neither the link nor its target)."""
    parts = [p for p in name.strip("/").split("/") if p]
    for i in range(1, len(parts) + 1):
        prefix = "/" + "/".join(parts[:i])
        link = h5.get(prefix, getlink=True)
        if link is None:
            return
        if isinstance(link, h5py.ExternalLink):
            if not allow_external:
                # names the file holds, as names print (s53: "a\\nb" read as a newline's escape)
                target = shown(f"{link.filename}:{link.path}")
                _refuse_external(path, f"{shown(prefix)} is an external link to {target}")
            try:
                h5[prefix]
            except (KeyError, OSError) as exc:
                why = str(exc).split("(", 1)[-1].rstrip(")\"' ") or "not found"
                raise FormatError(
                    path,
                    f"{shown(prefix)} is an external link to {shown(f'{link.filename}:{link.path}')}, which cannot be "
                    f"opened ({why})",
                ) from None
            return  # beyond it lies another file, whose own links are its own
        if isinstance(link, h5py.SoftLink) and depth < 8:
            target = link.path if link.path.startswith("/") else prefix.rsplit("/", 1)[0] + "/" + link.path
            check_links(path, h5, target, allow_external, depth + 1)


def check_local(path, h5, ds, allow_external=False) -> None:
    """Refuse a dataset whose bytes live outside ``h5``: external raw storage or a virtual dataset."""
    if allow_external:
        return
    if ds.file.filename != h5.filename:
        _refuse_external(path, f"{shown(ds.name)} lives in another file ({shown(ds.file.filename)})")
    if ds.is_virtual:
        sources = ds.virtual_sources()
        if sources and all(src.file_name == "." for src in sources):  # "." is libhdf5's "this file"
            # not "in other files": the user went looking for files that do not exist
            names = sorted({src.dset_name for src in sources})
            listed = ", ".join(map(shown, names[:3])) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
            raise FormatError(
                path,
                f"{shown(ds.name)} is a virtual dataset mapping {listed} of this file: virtual datasets are not read "
                f"{EXTERNAL_ADVICE}, or read the source dataset itself",
                advice={"allow_external": EXTERNAL_ADVICE},
            )
        _refuse_external(path, f"{shown(ds.name)} is a virtual dataset (its data are in other files)")
    if ds.id.get_create_plist().get_external_count():
        _refuse_external(path, f"{shown(ds.name)} is stored in external raw files")


#: the variables through which libhdf5 resolves a relative name, by what the name is (a
#: ``:``-separated list of folders, ``${ORIGIN}`` the referring file's own)
_PREFIX_VARIABLES = {"link": "HDF5_EXT_PREFIX", "virtual": "HDF5_VDS_PREFIX", "raw": "HDF5_EXTFILE_PREFIX"}


def _source_places(folder: Path, name: str, kind="virtual", real: Path | None = None) -> list[Path]:
    """Every place libhdf5 may look for a file ``name`` that a file in ``folder`` refers to, in its
    order (libhdf5's H5F_prefix_open_file, for external links and virtual sources alike): an
    absolute name as given, then, as for a relative name, under each folder of the prefix
    variable for ``kind`` (:data:`_PREFIX_VARIABLES`), beside the referring file (its
    ``${ORIGIN}``) and from the working directory -- an absolute name that is missing by its base
    name in each. libhdf5 opens the first it can; all are listed, since a place looked at
    needlessly costs a refused output name, one missed an input's frames: an absolute name's base
    name in the working directory was missed, and a ``frames.h5`` there read as the input's frames
    was replaced by ``-o frames.h5 --overwrite``. External raw files (``raw``) are read where the
    name leads, under the prefix variable's folders: an absolute one nowhere else (measured).

    ``real`` is the folder of the referring file's real path (its links resolved): libhdf5 2.0.0
    looks there too, after beside the name it was opened by (measured: ``Y/master.h5``, a link to
    ``X/master.h5``, reads its ``frames.h5`` from Y, else from X; not from a link's folder between
    them). Missed, ``-o X/frames.h5 --overwrite`` replaced the frames ``Y/master.h5`` is read from.
    External raw files are read from neither (measured)."""
    given = Path(name)
    relative = Path(given.name) if given.is_absolute() else given
    # libhdf5 2.0.0 splits HDF5_EXT_PREFIX and HDF5_VDS_PREFIX at ":" but not HDF5_EXTFILE_PREFIX,
    # and expands ${ORIGIN} in the latter two only (measured): every reading is taken
    value = os.environ.get(_PREFIX_VARIABLES[kind], "")
    prefixes = dict.fromkeys(p.replace("${ORIGIN}", str(folder)) for p in [value, *value.split(":")] if p)
    under = [Path(prefix) / relative for prefix in prefixes]
    beside = [folder / relative]
    if kind != "raw" and real is not None and real != folder:
        beside.append(real / relative)
    if given.is_absolute():
        return [given, *under] if kind == "raw" else [given, *under, *beside, relative]
    return [*under, *beside, relative]


def _printf_files(place: Path) -> list[Path]:
    """The existing files a virtual source's printf-style name ``place`` names, as libhdf5 reads
    it: ``%%`` a literal ``%``, ``%b`` any block number (plain decimal)."""
    tokens = re.split(r"(%%|%b)", str(place))
    if "%b" not in tokens:
        return [Path("".join("%" if t == "%%" else t for t in tokens))]
    pattern = re.compile("".join({"%%": "%", "%b": "(0|[1-9][0-9]*)"}.get(t) or re.escape(t) for t in tokens))
    candidates = glob.glob("".join({"%%": "%", "%b": "*"}.get(t) or glob.escape(t) for t in tokens))
    return sorted(Path(c) for c in candidates if pattern.fullmatch(c))


class IncompleteListingError(FormatError):
    """The files an HDF5 file's data may be read from cannot all be listed: its link table or
    an object header cannot be read whole (a corrupt file)."""


def data_files(path, allow_external=False) -> list[Path]:
    """The other files ``path``'s HDF5 data may be read from when ``allow_external``: external
    links' targets (to the end of a chain), virtual datasets' sources (a ``%b`` pattern: every
    file it names) and external raw storage, each at every place libhdf5 may look for it that
    exists; ``[]`` for a file that is not HDF5, or without ``allow_external`` (nothing outside
    the file is then read).

    Why: an output onto one of them replaces an input's frames. `correct master.h5
    --allow-external -o frames_000001.h5 --overwrite` wrote over the detector's frames, since
    only the files named on the command line were held to be inputs.

    Raises
    ------
    IncompleteListingError
        The listing cannot be completed (a link table libhdf5 cannot walk, in ``path`` or a file
        it leads to): a partial list would pass an output onto a file it left out, which libhdf5
        may still reach through a link the walk never got to.
    """
    found: list[Path] = []
    if not allow_external:
        return found
    # a worklist, not recursion: a chain of ~980 files ran into Python's RecursionError, which
    # ended the listing quietly
    todo, seen, listed = [Path(path)], {resolved(path)}, set()
    while todo:
        here = todo.pop()
        names, problem = _referred(here)
        if problem is not None:
            raise IncompleteListingError(here, problem)
        for name, kind in names:
            # tifffile reads a multi-file OME-TIFF's files from the folder of the one it opened
            places = (
                [here.parent / name]
                if kind == "tiff"
                else _source_places(here.parent, name, kind, resolved(here).parent)
            )
            for place in places:
                for match in _printf_files(place) if kind == "virtual" else [place]:
                    if not match.is_file():
                        continue
                    if resolved(match) not in listed:  # once, by the first name it was found under
                        listed.add(resolved(match))
                        found.append(match)
                    if kind != "raw" and resolved(match) not in seen:  # its own links and sources too
                        seen.add(resolved(match))
                        todo.append(match)
    # the files of a multi-file OME-TIFF name one another: the input is no other file of its own
    return [match for match in found if resolved(match) != resolved(path)]


def _referred(path: Path) -> tuple[list[tuple[str, str]], str | None]:
    """The names of the files ``path`` refers to, each with its kind (:data:`_PREFIX_VARIABLES`),
    and why the list is incomplete (None: it is whole).

    Read once per version of the file (its device, inode, size and times): every writer's output
    check lists each input's data files, and `process` checks each of N output folders against
    all N inputs, N^2 readings of 6 ms (a 100-file batch spent a minute before any work). Where
    the names lead is looked up afresh each time (:func:`data_files`)."""
    try:
        st = path.stat()
    except OSError:
        return [], None
    if not stat.S_ISREG(st.st_mode):
        # a FIFO (or device) is not opened to be looked into: its open() waited for a writer, and
        # `correct fifo.tif` hung there before the reader's "not a regular file" refusal
        return [], None
    names, problem = _referred_in(str(path), (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return list(names), problem


@functools.lru_cache(maxsize=256)
def _referred_in(path: str, version: tuple) -> tuple[tuple[tuple[str, str], ...], str | None]:
    """:func:`_referred` of one version of ``path``."""
    names, problem = _read_referred(Path(path))
    return tuple(dict.fromkeys(names)), problem


def _read_referred(path: Path) -> tuple[list[tuple[str, str]], str | None]:
    """:func:`_referred`, read from the file.

    Walked with h5py's low-level API, which gives names as bytes: its high-level visit decodes
    each link name as UTF-8, and one that is not (a corrupt link table, or a name written in
    another encoding) raised SystemError; the listing ended there, so a link after it -- the
    frames' own -- was never listed and an output replaced the frames."""
    try:
        if _ome_tiff_referred(path, names := []):
            return names, None
        if not h5py.is_hdf5(path):
            return [], None
        h5 = h5py.File(path, "r")
    except (OSError, ValueError):  # libhdf5 cannot open it: nothing is read through it either
        return [], None
    names: list[tuple[str, str]] = []
    with h5:
        root = h5.id

        def visit(name: bytes, info) -> None:
            if info.type == h5py.h5l.TYPE_EXTERNAL:
                names.append((os.fsdecode(root.links.get_val(name)[0]), "link"))
            elif info.type == h5py.h5l.TYPE_HARD:
                names.extend(_stored_elsewhere(root, name))

        try:
            root.links.visit(visit, info=True)
        except Exception as exc:  # a corrupt link table or object header, in whatever form h5py gives it
            why = " ".join(str(exc).split())[:200] or type(exc).__name__
            return names, f"its links cannot be listed whole ({why})"
    return names, None


def _ome_tiff_referred(path: Path, names: list) -> bool:
    """Whether ``path`` is a TIFF; into ``names``, the other files of a multi-file OME-TIFF its
    OME-XML places planes in, or of a Micro-Manager stack split over files (kind ``"tiff"``),
    which a read with allow_external takes frames from."""
    from radiokit.io._source import _TIFF_MAGIC  # late: _source imports this module

    with open(path, "rb") as fh:
        if fh.read(4) not in _TIFF_MAGIC:
            return False
    # late, and after the magic: only a TIFF input needs them (every output check reads each input
    # here: a protocol's TOML imported tifffile, 0.06 CPU s of each `radiokit acquire`)
    import tifffile

    from radiokit.io._ome import external_planes, mmstack_set_files, mmstack_split

    try:
        with tifffile.TiffFile(path) as tif:
            xml = tif.ome_metadata if tif.is_ome else None
            # every file of a Micro-Manager set, listed before its planes are looked for: a file
            # whose index map was never written holds none tifffile finds, and the read refuses it
            names.extend((os.path.basename(name), "tiff") for name in mmstack_set_files(tif))
            split = mmstack_split(tif) or []
    except Exception:  # (tifffile fails on a corrupt file in many ways) the read itself says so
        return True
    names.extend((name, "tiff") for name in external_planes(xml, path.name)[1])
    # a Micro-Manager stack's other files, which tifffile finds by name whatever the XML says
    names.extend(
        (os.path.basename(p.parent.filehandle.path), "tiff") for p in split if p is not None and p.parent is not tif
    )
    return True


def _stored_elsewhere(root, name: bytes) -> list[tuple[str, str]]:
    """The files the object at ``name`` (a dataset's virtual sources and external raw files)
    takes its data from; [] for a group, or an object libhdf5 cannot open (nor then read)."""
    try:
        obj = h5py.h5o.open(root, name)
    except (KeyError, OSError, ValueError, RuntimeError):
        return []
    if not isinstance(obj, h5py.h5d.DatasetID):
        return []
    dcpl = obj.get_create_plist()
    out = []
    if dcpl.get_layout() == h5py.h5d.VIRTUAL:
        for i in range(dcpl.get_virtual_count()):
            try:
                name = dcpl.get_virtual_filename(i)
            except UnicodeDecodeError as exc:  # h5py decodes it as UTF-8; the bytes are the name
                name = os.fsdecode(exc.object)
            if name != ".":  # libhdf5's "this file"
                out.append((name, "virtual"))
    out.extend((os.fsdecode(dcpl.get_external(i)[0]), "raw") for i in range(dcpl.get_external_count()))
    return out


def check_virtual_sources(path, ds) -> None:
    """Refuse a virtual dataset whose source file or dataset is missing: libhdf5 reads the
    unmapped parts as the fill value, so a moved or deleted source read as frames of zeros.

    A source named ``.`` is the file itself; others are looked for as libhdf5 does
    (:func:`_source_places`). A name with ``%b`` (one source per block of an unlimited
    selection) is checked by :func:`_check_block_sources`.
    """
    folder = Path(ds.file.filename).parent
    real = resolved(ds.file.filename).parent  # where libhdf5 looks too (_source_places)
    seen = set()
    for source in ds.virtual_sources():
        name, dset = source.file_name, source.dset_name
        if (name, dset) in seen or name == ".":
            continue
        seen.add((name, dset))
        if "%" in name or "%" in dset:
            _check_block_sources(path, ds, source, folder, real)
            continue
        _found_source(path, ds, folder, name, dset, real)


def _found_source(path, ds, folder: Path, name: str, dset: str, real: Path | None = None) -> Path:
    """Where the source file ``name`` is, found as libhdf5 finds it; refused when it is missing,
    cannot be opened or holds no dataset ``dset``."""
    found = next((p for p in _source_places(folder, name, real=real) if p.is_file()), None)
    if found is None:
        raise FormatError(path, f"{shown(ds.name)} is a virtual dataset whose source file {shown(name)} is missing")
    try:
        with h5py.File(found, "r") as src:
            present = isinstance(src.get(dset), h5py.Dataset)
    except OSError as exc:
        raise FormatError(
            path, f"{shown(ds.name)}: its virtual source {shown(found)} cannot be opened: {exc}"
        ) from None
    if not present:
        raise FormatError(path, f"{shown(ds.name)}: its virtual source {shown(found)} holds no dataset {shown(dset)}")
    return found


_PRINTF = re.compile(r"%(%|b)")


def _check_block_sources(path, ds, source, folder: Path, real: Path | None = None) -> None:
    """Refuse a ``%b`` mapping (source ``k`` of a printf-style name feeds block ``k`` of an
    unlimited selection) that libhdf5 read short or filled from elsewhere.

    libhdf5 sizes such a dataset by opening sources 0, 1, 2, ... and stops at the first it cannot
    open or that lacks the dataset (HDF5 2.0.0): a missing middle source silently cut the stack
    there, and a missing first one left no frames. With two or more mappings the extent is the
    longest one's, so every block it covers is looked for here (a shorter mapping's missing blocks
    read as the fill value), and all of them in one folder: libhdf5 looks beside the file, then in
    the working directory, so a series that ends early could be topped up by another one's files of
    the same names. A file of the pattern numbered at or past the first block not covered means a
    gap. A missing last source leaves no trace and cannot be told from a shorter series; nor can a
    gap in dataset names (``%b`` in the dataset name only). A fixed (not unlimited) mapping names
    one file, ``%%`` read as ``%`` (libhdf5 refuses ``%b`` there): checked as any other source.
    """
    name, dset = source.file_name, source.dset_name
    if _PRINTF.sub("", name).count("%") or _PRINTF.sub("", dset).count("%"):
        return  # not a pattern libhdf5 expands (it refuses such a name itself)
    try:
        start, stride, count, _ = source.vspace.get_regular_hyperslab()
    except (ValueError, RuntimeError):  # a selection of everything, or points: not a block mapping
        count = ()
    axes = [i for i, c in enumerate(count) if c == h5py.h5s.UNLIMITED]

    def expand(text, k):
        return _PRINTF.sub(lambda m: "%" if m.group(1) == "%" else str(k), text)

    if len(axes) != 1:
        if not any(m.group(1) == "b" for t in (name, dset) for m in _PRINTF.finditer(t)):  # "a%%b": no block
            _found_source(path, ds, folder, expand(name, 0), expand(dset, 0), real)
        return
    axis = axes[0]
    extent = ds.shape[axis]
    covered = max(0, -(-(extent - start[axis]) // max(stride[axis], 1)))
    missing = shown(f"{expand(name, covered)}:{expand(dset, covered)}")
    if not covered:
        raise FormatError(
            path,
            f"{shown(ds.name)} is a virtual dataset whose first source {missing} is missing or unreadable: no frames",
        )
    folders = {
        resolved(_found_source(path, ds, folder, expand(name, k), expand(dset, k), real).parent) for k in range(covered)
    }
    if len(folders) > 1:
        raise FormatError(
            path,
            f"{shown(ds.name)} is a virtual dataset whose sources {shown(name)} were found in {len(folders)} folders "
            f"({', '.join(sorted(map(shown, folders)))}): libhdf5 looks beside the file, then in the working "
            "directory, so the series is mixed with another one's files; run from another folder",
        )
    tokens = re.split(r"(%%|%b)", Path(name).name)
    if "%b" not in tokens:
        return  # %b in a folder name or the dataset name only: no files to list
    # libhdf5 prints the block number in plain decimal: src_01.h5 is not source 1
    number = re.compile("".join({"%%": "%", "%b": "(0|[1-9][0-9]*)"}.get(t) or re.escape(t) for t in tokens))
    later = []
    for place in {p.parent for p in _source_places(folder, name, real=real)}:
        if "%" in str(place) or not place.is_dir():
            continue
        with os.scandir(place) as entries:  # one folder, not its tree (a "%b%b" glob is "**")
            for entry in entries:
                m = number.fullmatch(entry.name)
                if m and len(set(m.groups())) == 1 and int(m.group(1)) >= covered and entry.is_file():
                    later.append(int(m.group(1)))
    if later:
        raise FormatError(
            path,
            f"{shown(ds.name)} is a virtual dataset read short: libhdf5 stops at the first source it cannot read, "
            f"{missing} (source {covered}), so its stack ends after {covered} block(s) although "
            f"{shown(expand(Path(name).name, min(later)))} is there",
        )


def checked_dataset(
    path, h5, name, kinds, ndims, allow_external=False, written=True, budget=None, whole=True
) -> h5py.Dataset:
    """The dataset ``name``, if it holds plain numbers (dtype kind in ``kinds``) in ``ndims`` dimensions.

    Checked before reading: a corrupt file can declare odd types that libhdf5 cannot read safely,
    a dataset can point at other files (refused unless ``allow_external``), and compressed data
    can declare far more than it could hold (:func:`check_proportion`, lifted by a ``budget``;
    judged here if it is read ``whole``, else frame by frame by its reader).
    """
    check_links(path, h5, name, allow_external)
    ds = h5.get(name)
    # a user's --dataset /entry/data came out "//entry/data"; a name as names print (s53)
    named = shown("/" + name.lstrip("/"))
    if not isinstance(ds, h5py.Dataset):
        raise FormatError(path, f"{named} is not a dataset")
    check_local(path, h5, ds, allow_external)
    if ds.is_virtual:  # allowed: its sources must be there, or libhdf5 gives the fill value
        check_virtual_sources(path, ds)
    if not _plain_numbers(ds.dtype, kinds):
        raise FormatError(
            path, f"{named} has type {ds.dtype}; expected {'integers' if set(kinds) <= set('iu') else 'numbers'}"
        )
    if ds.ndim not in ndims:
        raise FormatError(path, f"{named} has shape {ds.shape}; expected {_dimensions(ndims)}")
    check_filters(path, ds)
    if written:  # else its caller checks both, knowing what may be unwritten (read_experiment_meta)
        if whole:
            check_proportion_of(path, ds, budget)
        check_written(path, ds)
    return ds


def _dimensions(ndims) -> str:
    """``ndims`` in words: "1 dimension", "2 or 3 dimensions", "0 to 32 dimensions". Why: a 4-D
    stack was refused as "expected 2 dimension(s)" where 3-D ones are read."""
    n = sorted(ndims)
    if len(n) == 1:
        return f"{n[0]} dimension{'' if n[0] == 1 else 's'}"
    if len(n) > 2 and n == list(range(n[0], n[-1] + 1)):
        return f"{n[0]} to {n[-1]} dimensions"
    return f"{', '.join(map(str, n[:-1]))} or {n[-1]} dimensions"


def check_filters(path, ds) -> None:
    """Refuse, naming it, a compression filter libhdf5 lacks (zstd, Blosc, bitshuffle, LZ4 from
    beamline and detector software), after loading hdf5plugin's filters where it is installed;
    libhdf5 itself only says it "can't open directory" of plugins when a frame is read."""
    plist = ds.id.get_create_plist()
    filters = [plist.get_filter(i) for i in range(plist.get_nfilters())]
    missing = [(code, name) for code, _flags, _values, name in filters if not h5py.h5z.filter_avail(code)]
    if missing:
        try:
            import hdf5plugin  # noqa: F401  (registers its filters with libhdf5 on import)
        except ImportError:
            pass
        missing = [(code, name) for code, name in missing if not h5py.h5z.filter_avail(code)]
    if missing:
        code, name = missing[0]
        raise FormatError(
            path,
            f"{shown(ds.name)} is compressed with HDF5 filter {code} ({name.decode('latin-1') or 'unnamed'}), "
            "which is not available here: install hdf5plugin (pip install hdf5plugin)",
        )


#: the names of HDF5 filters in a refusal (libhdf5's own are long sentences for plugins)
_FILTER_NAMES = {1: "deflate", 4: "szip", 5: "n-bit", 6: "scale-offset", 32000: "lzf", 32001: "blosc", 32004: "lz4"}
_FILTER_NAMES.update({32008: "bitshuffle", 32013: "zfp", 32015: "zstd", 32017: "sz", 32026: "blosc2"})


def check_proportion_of(path, ds, budget=None, frames=None, index=None) -> None:
    """:func:`check_proportion` for a filtered dataset, over what one read decodes: the whole
    dataset, its first ``frames`` (read(): a live writer extends a stack far ahead of what it has
    written) or frame ``index`` alone (streamed: 300 sparse frames, 8.9 GiB at 1:267, were refused
    when one was read); ``ds`` a list: those datasets whole, read together (DXchange's darks,
    flats and projections). Only allocated chunks decode anything: a writer that preallocated 200
    frames and stopped after 2 is check_written's and check_frame_written's to refuse, not a bomb.
    Unfiltered data stores what it declares, or check_written finds it unwritten."""
    from radiokit.io._budget import check_proportion, proportion_can_refuse, stored_extent

    plans = [plan for d in (ds if isinstance(ds, list) else [ds]) if (plan := _chunks_read(d, frames, index))]
    most = sum(plan[0] for plan in plans)  # every chunk of those frames allocated
    frame = max((plan[1] for plan in plans), default=0)
    if not plans or not proportion_can_refuse(most, frame, budget):
        return  # the common case: no chunk listed
    decoded, ranges, codecs = 0, [], []
    for _most, _frame, chunk, listed, codec in plans:
        infos = [i for i in listed() if i.byte_offset is not None]
        decoded += len(infos) * chunk
        ranges += [(i.byte_offset, i.size) for i in infos]
        codecs += [codec] if codec not in codecs else []
    if isinstance(ds, list):
        what = f"{' and '.join(d.name for d in ds)}, read together,"
    else:
        what = f"{shown(ds.name)} ({'x'.join(map(str, ds.shape))} {ds.dtype})"
        what = f"frame {index} of {what}" if index is not None and ds.ndim >= 3 else what
    frame = min(frame, decoded)
    check_proportion(path, what, decoded, frame, stored_extent(ranges), "+".join(codecs), budget)


def _chunks_read(ds, frames=None, index=None) -> tuple | None:
    """What reading ``ds`` (whole, its first ``frames`` or frame ``index``) decodes if all its
    chunks are there, the bytes of a frame and of a chunk, a function listing the chunks' storage
    and the codecs' names; None if unfiltered (:func:`check_proportion_of`)."""
    plist = ds.id.get_create_plist()
    if ds.shape is None or ds.is_virtual or not plist.get_nfilters() or not ds.chunks or ds.size == 0:
        return None
    frame = math.prod(int(v) for v in ds.shape[-2:]) * ds.dtype.itemsize
    chunk = math.prod(int(v) for v in ds.chunks) * ds.dtype.itemsize
    grid = [-(-int(s) // int(c)) for s, c in zip(ds.shape, ds.chunks)]
    if ds.ndim < 3 or (frames is None and index is None):
        first, stop = 0, grid[0]
    elif index is not None:
        first = int(index) // int(ds.chunks[0])
        stop = first + 1
    else:
        first, stop = 0, -(-int(frames) // int(ds.chunks[0]))
    per_row = math.prod(grid[1:])

    def listed() -> list:
        if ds.ndim >= 3 and index is not None and per_row <= 4096:  # looked up, no more than decoding reads
            origin = first * int(ds.chunks[0])
            return [
                ds.id.get_chunk_info_by_coord((origin, *(k * int(c) for k, c in zip(at, ds.chunks[1:]))))
                for at in np.ndindex(*grid[1:])
            ]
        infos: list = []  # listed: as many as the file stores, where tiny chunks could declare billions
        ds.id.chunk_iter(infos.append)
        if ds.ndim >= 3:
            infos = [i for i in infos if first * ds.chunks[0] <= i.chunk_offset[0] < stop * ds.chunks[0]]
        return infos

    codes = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
    codecs = "+".join(_FILTER_NAMES.get(c, f"filter {c}") for c in codes if c not in (2, 3)) or "filtered"
    most = (stop - first) * per_row * chunk
    return most, min(frame, most), chunk, listed, codecs


#: HDF5 filters whose output is bounded: deflate expands at most 1032:1 (LZF less, about 88:1;
#: shuffle and Fletcher32 not at all). Others (scale-offset, N-bit, SZIP, plugins such as zstd or
#: Blosc) have no bound to check against, only whether anything was stored.
_FILTERS_BOUNDED = {
    h5py.h5z.FILTER_DEFLATE: 1032,
    h5py.h5z.FILTER_LZF: 1032,
    h5py.h5z.FILTER_SHUFFLE: 1,
    h5py.h5z.FILTER_FLETCHER32: 1,
}


def check_written(path, ds, spare_bytes: int = 0) -> None:
    """Refuse a dataset whose storage cannot hold what it declares: parts never written.

    libhdf5 allocates a chunked (or contiguous, late-allocated) dataset's storage as it is
    written, and reads what was never written as the fill value: a few-KB file declaring
    (2, 40000, 40000) frames read 6 GB of zeros. Allowed short: one chunk (the frame a live
    writer has in flight; the readers take only the frames it marks complete). What compression
    hides (a preallocating writer stopped part-way) :func:`check_frame_written` finds frame by
    frame. Virtual and external storage are checked where they are followed.
    ``spare_bytes``: how much more may be unwritten (an experiment file's frames: those its writer
    left labelled INVALID, see :func:`read_experiment_meta`).
    """
    declared = int(ds.size) * ds.dtype.itemsize if ds.shape is not None else 0
    plist = ds.id.get_create_plist()
    if not declared or ds.is_virtual or plist.get_external_count():
        return
    stored = int(ds.id.get_storage_size())
    codes = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
    ratio = max((_FILTERS_BOUNDED[c] for c in codes), default=1) if set(codes) <= _FILTERS_BOUNDED.keys() else None
    chunk = math.prod(ds.chunks) * ds.dtype.itemsize if ds.chunks else 0
    if stored and (ratio is None or stored * ratio + chunk + spare_bytes + 4096 >= declared):
        return
    what = f"{shown(ds.name)} declares {'x'.join(map(str, ds.shape))} {ds.dtype} ({declared} bytes)"
    if not stored:
        raise FormatError(
            path, f"{what} but stores nothing: never written (it would read as its fill value); incomplete or corrupt"
        )
    raise FormatError(
        path,
        f"{what} but stores {stored} bytes{f', compressed at most 1:{ratio}' if ratio > 1 else ''}: parts "
        "never written (they would read as the fill value); incomplete or corrupt",
    )


def check_frame_written(path, ds, index: int) -> None:
    """Refuse frame ``index`` of a chunked stack ``ds`` when its first chunk was never written.

    A writer that preallocates its frames and stops leaves the rest unallocated, and libhdf5 reads
    them as the fill value: frames of zeros, which a calibration takes for darks and a correction
    for non-positive pixels. One chunk-index lookup, no data read."""
    if ds.chunks is None or ds.is_virtual:
        return
    coord = ((index,) if ds.ndim == 3 else ()) + (0,) * (ds.ndim - (ds.ndim == 3))
    if ds.id.get_chunk_info_by_coord(coord).byte_offset is None:
        raise FormatError(
            path,
            f"frame {index} of {shown(ds.name)} was never written (no storage allocated: it would read as the "
            "fill value); incomplete or corrupt",
        )


#: The pixel pitches a radiography panel may have, in metres: 0.1 um to 10 mm. Outside, the value
#: is corrupt or in the wrong unit (NeXus stores metres: 0.05 there is 5 cm, a millimetre value).
PIXEL_SIZE_RANGE_M = (1e-7, 1e-2)


def _check_pixel_size(path, name: str, value) -> None:
    """Refuse a pixel pitch that is not a positive finite length of a panel's order: ROIs in mm and
    the crop divide by it (0 was a ZeroDivisionError traceback, NaN or inf an empty-ROI riddle)."""
    value = float(value)
    lo, hi = PIXEL_SIZE_RANGE_M
    if not math.isfinite(value) or value <= 0:
        raise FormatError(path, f"{name} is {value!r}: a pixel size must be a positive finite number (metres)")
    if not lo <= value <= hi:
        raise FormatError(
            path,
            f"{name} is {value!r} m ({value * 1e3:g} mm): not a panel's pixel ({lo * 1e6:g} um to {hi * 1e3:g} mm); "
            "NeXus stores metres (0.05 mm is 5e-05)",
        )


def usable_pixel_sizes(path, where: str, sizes: dict, problems=()) -> dict:
    """``sizes`` (``x_pixel_size`` / ``y_pixel_size``, metres) that another program's file states
    (``where``: ImageJ's resolution, OME's PhysicalSize, an NXdetector), with ``pixel_size_mm``, where
    each is a panel's pitch (:data:`PIXEL_SIZE_RANGE_M`, as an experiment file's must be). Else, or
    with ``problems`` (a unit not understood), none of them but ``pixel_size_unusable`` (why), said
    in a one-line note. Why: 1e+27 mm was shown by info and ``register`` refused a pair on it; the
    pitch is optional there, so the image is read all the same."""
    lo, hi = PIXEL_SIZE_RANGE_M
    problems = list(problems)
    odd = [
        f"{name} {value * 1e3:g} mm"
        for name, value in sizes.items()
        if not (math.isfinite(value) and lo <= value <= hi)
    ]
    if odd:
        problems.append(f"{', '.join(odd)}: not a panel's pixel ({lo * 1e3:g} to {hi * 1e3:g} mm)")
    if problems:
        why = f"{where}: {'; '.join(problems)}"
        warnings.warn(f"{shown(path)}: {why}; its pixel size is ignored", UserWarning, stacklevel=3)
        return {"pixel_size_unusable": why}
    out = dict(sizes)
    if "x_pixel_size" in out:
        out["pixel_size_mm"] = out["x_pixel_size"] * 1e3
    return out


#: Two recorded pitches closer than this (relative) are one: float32's rounding of 5e-05 m is 3e-08
PIXEL_SIZE_RTOL = 1e-6


def check_same_pixel_size(path, meta: dict, other, other_meta: dict, rule: str) -> None:
    """Refuse ``path`` (its ``meta``) when it and ``other`` both record a pixel size
    (``x_pixel_size``, ``y_pixel_size``) and they differ, with ``rule`` said last. Why: a control
    at 0.1 mm per pixel beside an experiment at 0.05 mm, of one frame shape, was measured in the
    experiment's pixel ROIs, on a scene twice as large; ``register`` matched such images too."""
    for name in ("x_pixel_size", "y_pixel_size"):
        mine, theirs = meta.get(name), other_meta.get(name)
        if mine is None or theirs is None or math.isclose(mine, theirs, rel_tol=PIXEL_SIZE_RTOL):
            continue
        from radiokit._names import shown

        raise FormatError(path, f"pixels of {mine * 1e3:g} mm ({name}), {shown(other)}'s {theirs * 1e3:g} mm: {rule}")


#: NeXus's own units for a length (``@units``); none given means metres, as NXdetector says
#: (and OME's): the micro sign or Greek mu, the angstrom as OME's symbol, Unicode's or a word
_LENGTH_UNITS_M = {
    "m": 1.0,
    "cm": 1e-2,
    "mm": 1e-3,
    "um": 1e-6,
    "\u00b5m": 1e-6,
    "\u03bcm": 1e-6,
    "micron": 1e-6,
    "microns": 1e-6,
    "nm": 1e-9,
    "\u00c5": 1e-10,
    "\u212b": 1e-10,
    "angstrom": 1e-10,
    "Angstrom": 1e-10,
}


def _pixel_metres(path, name: str, ds) -> float:
    """A pixel size that is there as one plain number, in metres. One number stored as a
    one-element array (as some NXtomo writers do) is that number, and ``@units`` (m, mm, um, nm) is
    honoured; anything else is refused: left out as other optional fields are when unreadable
    (`true`, text, two numbers), ROIs in mm were measured with 0.05 mm instead."""
    _check_pixel_dataset(path, name, ds)
    units = ds.attrs.get("units", "m")
    units = (units.decode("utf-8", "replace") if isinstance(units, bytes) else str(units)).strip()
    if units not in _LENGTH_UNITS_M:
        raise FormatError(path, f"/{DETECTOR}/{name} has units {units!r}: expected one of {sorted(_LENGTH_UNITS_M)}")
    return float(np.asarray(ds[()]).reshape(())) * _LENGTH_UNITS_M[units]


def _read_pixel_sizes(path, h5, meta: dict, allow_external: bool) -> None:
    """``meta``'s ``x_pixel_size`` / ``y_pixel_size`` (metres) and ``pixel_size_mm``, where the
    file has them; one that is there but is no panel's pitch is refused."""
    for name in ("x_pixel_size", "y_pixel_size"):
        check_links(path, h5, f"{DETECTOR}/{name}", allow_external)
        ds = h5[DETECTOR].get(name)
        if ds is not None:
            check_local(path, h5, ds, allow_external)
            meta[name] = _pixel_metres(path, name, ds)
            _check_pixel_size(path, f"/{DETECTOR}/{name}", meta[name])
            origin = _text(ds.attrs.get("pixel_size_from"))
            if origin and name == "x_pixel_size":
                meta["pixel_size_from"] = origin
    if "x_pixel_size" in meta:
        meta["pixel_size_mm"] = meta["x_pixel_size"] * 1e3


def _text(value) -> str | None:
    """``value`` (an attribute or a scalar dataset's value) as text where it is one, else None:
    an optional record is left out, not refused, when another program put something else there."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return value if isinstance(value, str) else None


def _read_detector_name(path, h5, meta: dict, allow_external: bool) -> None:
    """``meta["detector"]``: the NXdetector's ``description`` where it is one string (a file of
    radiokit's writer told no name has none; the old writer's is variable-length, read too)."""
    name = f"{DETECTOR}/description"
    check_links(path, h5, name, allow_external)
    ds = h5.get(name)
    if isinstance(ds, h5py.Dataset) and ds.shape == () and h5py.check_string_dtype(ds.dtype) is not None:
        check_local(path, h5, ds, allow_external)
        text = _text(ds[()])
        if text:
            meta["detector"] = text


def _check_pixel_dataset(path, name: str, ds) -> None:
    """See :func:`_pixel_metres`: one plain number (a 0-d dataset or a one-element array)."""
    if isinstance(ds, h5py.Dataset) and ds.ndim <= 1 and ds.size == 1 and _plain_numbers(ds.dtype):
        return
    if not isinstance(ds, h5py.Dataset):
        what = "a group"
    elif h5py.check_string_dtype(ds.dtype) is not None:
        what = "text"
    else:
        what = f"{ds.dtype} of shape {ds.shape}"
    raise FormatError(path, f"/{DETECTOR}/{name} is {what}: expected one number (metres)")


def _frames_complete(path, h5, default: int) -> int:
    """``@frames_complete`` (``default`` when absent) as a count, or a FormatError naming it: a
    bool (HDF5's ``true`` reads as 1 frame), a fraction, text or a negative number is no count."""
    n = h5[ENTRY].attrs.get("frames_complete", default)
    if np.ndim(n) != 0 or np.asarray(n).dtype.kind not in "iu" or n < 0:
        value = n.item() if isinstance(n, np.generic) else n
        raise FormatError(path, f"/{ENTRY}@frames_complete is {value!r}; expected a count of frames")
    return int(n)


def _plain_numbers(dtype, kinds="iuf") -> bool:
    return dtype.kind in kinds and dtype.fields is None and h5py.check_vlen_dtype(dtype) is None


def _read_source(path, h5: h5py.File, meta: dict, allow_external: bool) -> None:
    """``meta["source"]``: the source group's scalar numbers and strings (when the file has one)."""
    check_links(path, h5, SOURCE, allow_external)
    src = h5.get(SOURCE)
    if src is None:
        return
    meta["source"] = {}
    for key in src:
        # only scalar numbers and strings: libhdf5 can crash on a corrupt variable-length type
        check_links(path, h5, f"{src.name}/{key}", allow_external)
        ds = src.get(key)
        if (
            not isinstance(ds, h5py.Dataset)
            or ds.shape != ()
            or not (ds.dtype.kind in "iuf" or h5py.check_string_dtype(ds.dtype) is not None)
        ):
            continue
        check_local(path, h5, ds, allow_external)
        value = ds[()]
        meta["source"][key] = value.decode("utf-8", "replace") if isinstance(value, bytes) else value


def frame_candidates(h5: h5py.Group, most=4) -> str | None:
    """Where the frames of a file of another layout may be: the 2-D and 3-D datasets of numbers in
    ``h5`` (a file or a group), largest first, ``most`` at most ("/a (3x20x24 uint16), ... and 3
    more"; "" when there are none; None when the file cannot be looked through), for a refusal that
    asks for ``--dataset`` (the user otherwise needs another tool to find the path). External links
    (a detector's master file linking its data files) are listed after them, with the file each
    points into, and not followed."""
    found, seen, cut = [], [0, 0], []

    def visit(name, obj):
        seen[0] += 1
        if isinstance(obj, h5py.Dataset) and obj.ndim in (2, 3) and obj.dtype.kind in "buif":
            # a name the file holds, as names print (s53: "a\\nb" printed as a newline's escape)
            what = f"{shown(obj.name)} ({'x'.join(map(str, obj.shape))} {obj.dtype.newbyteorder('=')})"
            found.append((obj.size, what))
        if seen[0] >= 10_000:  # a file of many objects: a look, not a survey
            cut.append(True)
            return True
        return None

    linked = []

    def visit_link(name, link):
        seen[1] += 1
        if isinstance(link, h5py.ExternalLink):
            linked.append(f"{shown(h5.name.rstrip('/') + '/' + name)} (in {shown(link.filename)})")
        if seen[1] >= 10_000:
            cut.append(True)
            return True
        return None

    try:
        h5.visititems(visit)  # hard links only: nothing outside the file is opened
        # a detector's master file (Dectris, NeXus writers) keeps its frames in files it links to;
        # the links are listed, not followed
        h5.visititems_links(visit_link)
    except Exception:  # a corrupt file: its refusal stands without the list
        return None
    found.sort(key=lambda item: -item[0])
    if linked:
        linked.sort()
        found += [(-1, text) for text in linked]
    if cut:  # the look stopped short: how many more is not known
        more = f" and {'more' if len(found) <= most else f'at least {len(found) - most} more'}"
    else:
        more = f" and {len(found) - most} more" if len(found) > most else ""
    outside = f"; a link into another file is not read {EXTERNAL_ADVICE}" if linked else ""
    return ", ".join(text for _, text in found[:most]) + more + outside


def _not_an_experiment(path, h5: h5py.File) -> FormatError:
    """Why ``h5`` is no experiment file, and where its frames may be (:func:`frame_candidates`)."""
    listed = frame_candidates(h5)
    lacks = f"HDF5 file lacks /{FRAMES}: not a radiokit experiment file"
    if listed is None:
        return FormatError(
            path, f"{lacks}, and could not be looked through: {DATASET_ADVICE}", advice={"dataset": DATASET_ADVICE}
        )
    if not listed:
        return FormatError(path, f"{lacks} and holds no 2-D or 3-D dataset of numbers")
    return FormatError(
        path,
        f"{lacks}; it holds {listed}: {DATASET_ADVICE}",
        advice={"dataset": DATASET_ADVICE} | linked_advice(listed),
    )


def linked_advice(listed) -> dict:
    """The advice of a refusal listing :func:`frame_candidates` (``listed``) that a link among
    them into another file is read with ``--allow-external``, or none."""
    return {"allow_external": EXTERNAL_ADVICE} if listed and EXTERNAL_ADVICE in listed else {}


def _optional_dataset(path, h5: h5py.File, name: str, allow_external: bool):
    """``h5[name]`` for an optional field of another program's file (its pitch, its bit depth),
    or None where it is absent, or where its data are in another file that is not to be read or
    cannot be: that field is left out, with a note, and the frames are read without it.

    Why: such a field linked to another file refused the whole file without --allow-external
    (frames read before the field was looked for), and one whose link's file was gone refused it
    with --allow-external too."""
    try:
        check_links(path, h5, name, allow_external)
        ds = h5.get(name)
        if isinstance(ds, h5py.Dataset):
            check_local(path, h5, ds, allow_external)
        return ds
    except FormatError as exc:
        warnings.warn(f"{exc}; {name.rsplit('/', 1)[-1]} left out", UserWarning, stacklevel=4)
        return None
    except (KeyError, TypeError, ValueError):  # a part of the way is a dataset, not a group
        return None


def read_bit_depth(path, h5: h5py.File, group: str, allow_external=False) -> int | None:
    """The ADC bits ``group`` (an NXdetector) declares in ``bit_depth_readout``, where that is one
    whole number 1..32; else None. Optional: anything else (text, an array, 12.5) is left out, as
    an experiment file's other optional fields are, and the frames' range is judged on its own."""
    ds = _optional_dataset(path, h5, f"{group.rstrip('/')}/bit_depth_readout", allow_external)
    if not (isinstance(ds, h5py.Dataset) and ds.ndim == 0 and _plain_numbers(ds.dtype)):
        return None
    bits = ds[()]
    return int(bits) if float(bits).is_integer() and 1 <= bits <= 32 else None


def read_pixel_sizes(path, h5: h5py.File, group: str, allow_external=False) -> dict:
    """``x_pixel_size`` / ``y_pixel_size`` (metres) that ``group`` (another program's NXdetector)
    states, each where it is one positive finite number in a length unit NeXus names (``@units``,
    metres when absent); the rest is left out, as :func:`read_bit_depth` leaves an unreadable depth.
    Why: ``register`` holds two images to one pitch only where both files record it."""
    out, problems = {}, []
    for axis in ("x_pixel_size", "y_pixel_size"):
        ds = _optional_dataset(path, h5, f"{group.rstrip('/')}/{axis}", allow_external)
        if not (isinstance(ds, h5py.Dataset) and ds.ndim <= 1 and ds.size == 1 and _plain_numbers(ds.dtype)):
            continue
        units = ds.attrs.get("units", "m")
        units = (units.decode("utf-8", "replace") if isinstance(units, bytes) else str(units)).strip()
        if units not in _LENGTH_UNITS_M:
            problems.append(f"{axis}'s units {units!r} are no length unit radiokit knows")
            continue
        out[axis] = float(np.asarray(ds[()]).reshape(())) * _LENGTH_UNITS_M[units]
    return usable_pixel_sizes(path, group, out, problems) if out or problems else {}


def read_experiment_meta(path, h5: h5py.File, allow_external=False, budget=None) -> tuple[h5py.Dataset, dict]:
    """Find the frames of an experiment file and collect its per-frame metadata.

    Declared sizes are checked against the memory budget (:func:`radiokit.io.memory_budget`)
    before anything is read; data stored outside the file is refused unless ``allow_external``.
    """
    from radiokit.io._budget import check_budget

    check_links(path, h5, FRAMES, allow_external)
    if FRAMES not in h5:
        raise _not_an_experiment(path, h5)
    data = checked_dataset(path, h5, FRAMES, "iuf", range(33), allow_external, written=False, budget=budget)
    if data.ndim != 3:
        raise FormatError(path, f"/{FRAMES} has shape {data.shape}; expected (n, rows, cols)")
    n = min(_frames_complete(path, h5, data.shape[0]), data.shape[0])
    check_budget(path, len(_SERIES) * 8 * n, f"the per-frame records of {n} frames", budget)
    meta = {"format": "experiment"}
    for group, name, *_ in _SERIES:
        if name in h5.get(group, {}):
            values = checked_dataset(path, h5, f"{group}/{name}", "iuf", (1,), allow_external)[:n]
            if len(values) != n:
                # DESIGN.md's "ratio per step" reads as one a step to another program's author
                blank = {"step": " (-1 for darks and flats)", "image_key": ""}.get(name, " (NaN where not recorded)")
                raise FormatError(
                    path,
                    f"/{group}/{name} holds {len(values)} values for {n} complete frames; expected one per frame, "
                    f"in the frames' order{blank}",
                )
            if name in ("image_key", "step"):
                values = _whole_numbers(path, values, f"/{group}/{name}", name)
            elif name == "ratio":
                _check_ratios(path, values, f"/{group}/{name}")
            meta[name] = values
            if name == "image_key":
                check_image_keys(path, values, f"/{group}/{name}")
        elif name == "image_key":
            raise FormatError(path, f"HDF5 file lacks /{IMAGE_KEY}")
    # ExperimentWriter counts a frame, labelled INVALID, before it writes its pixels: each crash
    # in between leaves one such frame unwritten, and --resume appends after it (two crashes left
    # two chunks unwritten, and the whole file was refused); the frame in flight adds one more
    invalid = int(np.count_nonzero(meta["image_key"] == ImageKey.INVALID))
    frame = math.prod(data.shape[1:]) * data.dtype.itemsize
    per_frame = max(frame, math.prod(data.chunks) * data.dtype.itemsize) if data.chunks else frame  # whole chunks
    check_written(path, data, spare_bytes=invalid * per_frame)
    _read_pixel_sizes(path, h5, meta, allow_external)
    _read_detector_name(path, h5, meta, allow_external)
    name = "pixel_mask"
    check_links(path, h5, f"{DETECTOR}/{name}", allow_external)
    ds = h5[DETECTOR].get(name)
    # optional: left out unless plain numbers of the expected rank
    if isinstance(ds, h5py.Dataset) and ds.ndim == 2 and _plain_numbers(ds.dtype):
        check_local(path, h5, ds, allow_external)
        check_budget(path, ds.size * ds.dtype.itemsize, f"/{DETECTOR}/{name} {ds.shape}", budget)
        check_proportion_of(path, ds, budget)  # read whole, and compressed (gzip) as radiokit writes it
        meta[name] = ds[()]
    bits = read_bit_depth(path, h5, DETECTOR, allow_external)
    if bits is not None:  # else: the C7942's 12
        meta["bit_depth"] = bits
    _read_source(path, h5, meta, allow_external)
    from radiokit.io._simulation import SIMULATION

    if SIMULATION in h5:
        meta["simulated"] = True
    meta["n_complete"] = n
    return data, meta
