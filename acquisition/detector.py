"""Frame sources: the files the C7942's vendor software writes, or the virtual bench's panel.

The C7942 reaches the computer through a frame grabber that only the vendor software (HiPic,
XVS-FPD) drives; that software saves one file per frame (raw 16-bit little-endian, TIFF, or
ITEX ``.img``) into a folder. :class:`FolderWatcher` is the detector as radiokit sees it in the
lab: it waits for each new file to be complete, reads and checks it, and hands it over.
:class:`SimDetector` renders the same frames from :class:`sim.bench.VirtualBench`.

Both follow :class:`Detector`: ``arm()``, then ``acquire(n)`` yields :class:`Frame` objects as
they arrive, raising :class:`~acquisition.errors.DetectorTimeout` when the next one does not come
in time and :class:`~acquisition.errors.DeviceError` for a frame that is not a C7942 frame.

Examples
--------
>>> import tempfile, threading, numpy as np, tifffile
>>> folder = tempfile.mkdtemp()
>>> watcher = FolderWatcher(folder, "*.tif", shape=(4, 6), settle_s=0.05, timeout_s=5)
>>> watcher.arm()
>>> for k in range(2):
...     tifffile.imwrite(f"{folder}/frame_{k}.tif", np.full((4, 6), 100 + k, np.uint16))
>>> [int(f.data[0, 0]) for f in watcher.acquire(2)]
[100, 101]
"""

from __future__ import annotations

import fnmatch
import hashlib
import logging
import math
import operator
import os
import re
import time
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.errors import DetectorTimeout, DeviceError
from radiokit.errors import FormatError
from radiokit.io import PRESETS, bit_depth_cause, read, sniff

__all__ = ["Frame", "Detector", "FolderWatcher", "FrameLost", "SimDetector"]

log = logging.getLogger(__name__)


@dataclass
class Frame:
    """One frame as it arrives.

    Attributes
    ----------
    data : ndarray, (rows, cols) uint16
        The raw frame, row 0 at the top as the vendor writes it.
    time_s : float
        ``time.time()`` when it arrived (was found complete and read, or was read out).
    origin : str
        The file it came from, or ``"sim"``.
    """

    data: np.ndarray
    time_s: float
    origin: str


@typing.runtime_checkable
class Detector(typing.Protocol):
    """What the protocols need of a detector."""

    shape: tuple[int, int]
    pixel_size_mm: float

    def arm(self) -> None:
        """Get ready for a series."""

    def acquire(self, n: int, *, timeout_s: float | None = None) -> Iterator[Frame]:
        """Yield ``n`` frames, each as soon as it is complete."""

    def begin_batch(self, discard: int = 0) -> None:
        """The devices have just reached the state the next frames must show (tube on or off,
        phantom placed): no frame made before now may be taken, nor the next ``discard``."""

    def describe(self) -> dict:
        """JSON-able: kind, folder or scene, shape, settings."""

    def close(self) -> None:
        """Release the detector."""


def _count(n) -> int:
    try:
        n = operator.index(n)
    except TypeError:
        raise ValueError(f"acquire(n={n!r}): expected a whole number of frames") from None
    if n < 0:
        raise ValueError(f"acquire(n={n}): expected n >= 0")
    return n


def implied_pixel_size(preset: str | None, shape) -> tuple[float, str | None]:
    """The pitch a folder of frames is recorded with when the protocol gives none: the preset's,
    else 0.05 mm (the C7942's, C7942.md) times the binning a 2240, 1120 or 560 column frame
    means, else 0.05 mm; and where it comes from, as the experiment file records it (None where
    it is only the C7942's assumed). One rule for the watcher (its pitch and the pitch's origin)
    and for a resume's comparison of pitches."""
    if preset is not None:
        return PRESETS[preset].pixel_size_mm, f"the detector preset {preset}"
    if shape is not None and shape[1] in (2240, 1120, 560):
        b = 2240 // shape[1]
        return 0.05 * b, f"the frames' width, {shape[1]} columns: the C7942 binned {b}x{b}"
    return 0.05, None


def implied_pixel_size_mm(preset: str | None, shape) -> float:
    """:func:`implied_pixel_size`'s pitch alone."""
    return implied_pixel_size(preset, shape)[0]


# -- the vendor software's folder ---------------------------------------------------------------
class FolderWatcher:
    """The C7942 through the files its vendor software writes into ``folder``.

    Parameters
    ----------
    folder : str or Path
        Where HiPic / XVS-FPD saves frames, one file per frame. Must exist.
    pattern : str
        Glob for the frame files' names, matched case-insensitively (the vendor software runs on
        Windows, where ``*.tif`` also matches ``FRAME.TIF``).
    shape : (rows, cols), optional
        Every frame must have this shape. Default: the preset's, else whatever the first frame
        has (then every later frame must match it).
    preset : str, optional
        A :data:`radiokit.io.PRESETS` geometry (e.g. ``"c7942-2x2"``): the shape of raw files and
        the pixel size.
    timeout_s : float
        How long to wait for the next frame before :class:`DetectorTimeout`.
    settle_s : float
        A file is complete once its size and time stamp have not changed for this long and it
        reads as a whole frame.
    poll_s : float
        How often the folder is listed.
    discard_first : bool
        Drop the first frame after each :meth:`arm` (the C7942's first frame after an
        external-trigger start is invalid): it is waited for, read, logged, never yielded.
    bits : int or None
        ADC depth: a value above ``2**bits - 1`` is an error (12 for the C7942; None: no check).
    pixel_size_mm : float, optional
        Default: the preset's, else 0.05 times the binning implied by a 2240 / 1120 / 560 column
        width, else 0.05.

    Notes
    -----
    :meth:`arm` records the matching files already in the folder; they are never taken, however
    often they change (nor those there at :meth:`begin_batch`). New files are taken in order of
    modification time, then name; a taken file renamed (a writer's temporary name) is not taken
    again, and a taken file that changes and then holds other pixels is :class:`FrameLost`. A file that
    has settled but does not read as a frame (still being written with pauses, or truncated) is
    retried until it does, until a later file has settled too (the writer has moved on), or until
    the time-out; the last two raise :class:`DeviceError` naming the file. Files are never
    deleted or modified.
    """

    kind = "folder"

    def __init__(
        self,
        folder,
        pattern: str = "*.tif",
        *,
        shape=None,
        preset=None,
        timeout_s: float = 30.0,
        settle_s: float = 0.2,
        poll_s: float = 0.05,
        discard_first: bool = False,
        bits: int | None = 12,
        pixel_size_mm: float | None = None,
    ):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DeviceError(
                f"detector folder {self.folder}: no such folder (where does the vendor software save frames?)"
            )
        self.pattern = str(pattern)
        if preset is not None and preset not in PRESETS:
            raise ValueError(f"detector folder {self.folder}: unknown preset {preset!r}; known: {', '.join(PRESETS)}")
        self.preset = preset
        if shape is not None:
            shape = tuple(int(v) for v in shape)
            if len(shape) != 2 or min(shape) <= 0:
                raise ValueError(f"detector folder {self.folder}: shape {shape}: expected (rows, cols), both > 0")
        if preset is not None:
            p = PRESETS[preset]
            if shape is not None and shape != (p.rows, p.cols):
                raise ValueError(
                    f"detector folder {self.folder}: shape {shape} contradicts preset {preset} ({p.rows}, {p.cols})"
                )
            shape = (p.rows, p.cols)
        self.shape = shape
        self._shape_given = shape is not None
        for name, v in (("timeout_s", timeout_s), ("settle_s", settle_s), ("poll_s", poll_s)):
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"detector folder {self.folder}: {name}={v!r}: expected a time >= 0")
        self.timeout_s, self.settle_s, self.poll_s = float(timeout_s), float(settle_s), max(float(poll_s), 1e-3)
        self.discard_first = bool(discard_first)
        self.bits = bits
        self._pixel_size_given = pixel_size_mm is not None
        self.pixel_size_mm = float(pixel_size_mm) if pixel_size_mm is not None else self._pixel_size()
        self._armed = False
        self._names_at_arm: set[str] = set()  # every file in the folder at arm(), matching or not
        self._known: dict[str, list] = {}  # name -> _known_entry() of files never to be taken
        self._taken: set[str] = set()
        self._took: dict[str, tuple] = {}  # name -> ((size, mtime_ns), pixel digest) of frames taken
        self._took_ids: dict[tuple, str] = {}  # _identity() of each frame taken -> its name
        self._discard_pending = 0  # new frames still to drop
        self._seen: dict[str, tuple] = {}  # name -> ((size, mtime_ns), monotonic time first seen so)

    def _pixel_size(self) -> float:
        return implied_pixel_size_mm(self.preset, self.shape)

    #: what the experiment file names the panel: the watcher reads the C7942's vendor software
    panel_name = "Hamamatsu C7942SK-02"

    @property
    def pixel_size_from(self) -> str | None:
        """Where :attr:`pixel_size_mm` came from, as the experiment file records it; None where it
        is only the C7942's assumed (no preset, a frame width no binning of it gives): then the
        file records no pitch, and its readers say they assume it."""
        if self._pixel_size_given:
            return "the protocol's [detector] pixel_size_mm"
        return implied_pixel_size(self.preset, self.shape)[1]

    # -- the Detector interface ------------------------------------------------------------------
    def arm(self) -> None:
        """Record the files already there (never taken) and re-arm the discard of the first frame."""
        self._known = {name: self._known_entry(st) for name, st in self._listing()}
        self._names_at_arm = self._names()
        self._taken = set()
        self._took = {}
        self._took_ids = {}
        self._backlog_ids = set()
        self._seen = {}
        self._discard_pending = int(self.discard_first)
        self._armed = True
        log.info(
            "detector folder %s: armed, %d existing file(s) matching %r ignored%s",
            self.folder,
            len(self._known),
            self.pattern,
            "; the first new frame will be discarded" if self.discard_first else "",
        )

    def acquire(self, n: int, *, timeout_s: float | None = None) -> Iterator[Frame]:
        """Yield the next ``n`` new frame files in arrival order, each once it is complete.

        Raises
        ------
        DetectorTimeout
            The next file did not arrive (or complete) within ``timeout_s`` (default: the
            watcher's); the message names the folder, the pattern and how many of ``n`` arrived.
        DeviceError
            A file is not a valid frame (unreadable, not 2-D uint16, values beyond the ADC, wrong
            shape); the message names the file. The file counts as taken.
        """
        n = _count(n)
        timeout = self.timeout_s if timeout_s is None else float(timeout_s)
        if not self._armed:
            log.warning("detector folder %s: acquire() before arm(); arming now", self.folder)
            self.arm()
        got = 0
        while got < n:
            path, data = self._next(time.monotonic() + timeout, timeout, got, n)
            if self._discard_pending:
                self._discard_pending -= 1
                log.info(
                    "detector folder %s: discarded %s (the invalid first frame after the trigger start, "
                    "or one in flight when the beam or the phantom changed)",
                    self.folder,
                    path.name,
                )
                continue
            got += 1
            frame = Frame(data, time.time(), str(path))
            # the frame as the run stores it: FrameLost names it so, whatever the file is called
            # by then (a temporary name reused for every frame, or renamed after it was taken)
            sig, digest, _ = self._took[path.name]
            self._took[path.name] = (sig, digest, (frame.origin, frame.time_s))
            yield frame

    def begin_batch(self, discard: int = 0) -> None:
        """Never take the files in the folder now, complete or still being written, nor the next
        ``discard`` new ones.

        The vendor software may save frames continuously, whatever the run is doing: while the
        operator turns the screws, the gel settles and the beam ramps up, frames pile up in the
        folder. Taken in arrival order they were the next batch's frames: a flat was a dark
        frame, a step's projection was taken with the tube off at the previous gap. The frame
        being integrated when the change was confirmed saw both states; at most ``discard``
        frames can be in flight like that (one when the software writes each frame as it is read
        out)."""
        if not self._armed:
            self.arm()
        backlog = {
            name: self._known_entry(st)
            for name, st in self._listing()
            if name not in self._known and name not in self._taken
        }
        self._known.update(backlog)
        for name in backlog:
            self._seen.pop(name, None)
        # and every file there now under any name (device and inode): a frame being saved to a
        # temporary name that the pattern does not match is renamed into it later, made before
        self._backlog_ids = self._inodes()
        self._discard_pending = max(self._discard_pending, int(discard))
        if backlog or discard:
            log.info(
                "detector folder %s: new batch: %d file(s) made before it ignored, the next %d new one(s) discarded",
                self.folder,
                len(backlog),
                self._discard_pending,
            )

    def describe(self) -> dict:
        return {
            "kind": self.kind,
            "folder": str(self.folder.resolve()),
            "pattern": self.pattern,
            "shape": list(self.shape) if self.shape is not None else None,
            "preset": self.preset,
            # as the file's pitch: none where it is only assumed (the run's record stated it as
            # the watcher's own, beside a file that records none)
            "pixel_size_mm": self.pixel_size_mm if self.pixel_size_from is not None else None,
            "pixel_size_from": self.pixel_size_from,
            "bits": self.bits,
            "timeout_s": self.timeout_s,
            "settle_s": self.settle_s,
            "poll_s": self.poll_s,
            "discard_first": self.discard_first,
        }

    def close(self) -> None:
        self._armed = False

    def __repr__(self):
        return f"FolderWatcher({str(self.folder)!r}, {self.pattern!r}, shape={self.shape})"

    # -- the folder ----------------------------------------------------------------------------
    def _listing(self) -> list[tuple[str, os.stat_result]]:
        pat = self.pattern.lower()
        out = []
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            raise DeviceError(f"detector folder {self.folder}: cannot be listed: {exc.strerror or exc}") from exc
        for e in entries:
            if not fnmatch.fnmatchcase(e.name.lower(), pat):
                continue
            try:
                if e.is_file():
                    # the inode only where it decides: a new candidate (taken and known files
                    # are not stat'ed again every poll)
                    fresh = e.name not in self._taken and e.name not in self._known
                    out.append((e.name, _entry_stat(e) if fresh else e.stat()))
            except FileNotFoundError:  # removed between listing and stat
                continue
        return out

    def _next(self, deadline: float, timeout: float, got: int, n: int) -> tuple[Path, np.ndarray]:
        """Wait for the earliest new file to be complete; read and check it."""
        failure = None  # (name, message) of a settled file that does not read
        while True:
            now = time.monotonic()
            listing = self._listing()
            files = dict(listing)
            new = sorted(
                ((st.st_mtime_ns, name, st) for name, st in listing if self._is_new(name, st, files)),
                key=lambda t: (t[0], _natural(t[1])),
            )
            self._recheck_taken(listing, now)  # after _is_new has followed renamed frames
            self._watch_known(listing, now)
            settled = self._settled(new, now)
            if failure is not None and failure[0] not in settled:
                failure = None  # it changed (still being written) or is gone (renamed)
            if new and new[0][1] in settled:
                name = new[0][1]
                path = self.folder / name
                try:
                    data = self._read(path)
                except _Gone:  # renamed or removed between the listing and the read
                    self._seen.pop(name, None)
                except _NotYet as exc:
                    failure = (name, str(exc))
                    if len(settled) > 1:  # a later file is complete: this one will not be
                        self._taken.add(name)
                        raise DeviceError(
                            f"{path}: not a readable frame file ({exc}); a later file "
                            f"({settled[1]}) is already complete"
                        ) from None
                else:
                    self._took_frame(name, new[0][2], data)
                    return path, data
            if now >= deadline:
                if failure is not None:
                    self._taken.add(failure[0])
                    raise DeviceError(
                        f"{self.folder / failure[0]}: not a readable frame file after {timeout:g} s: "
                        f"{failure[1]}{self._disk_full()}"
                    )
                raise self._timeout(listing, new, got, n, timeout)
            time.sleep(min(self.poll_s, max(deadline - now, 0.0) + 1e-3))

    def _timeout(self, listing, new, got: int, n: int, timeout: float) -> DetectorTimeout:
        """The time-out, saying what the folder shows: a file still growing, one that was there
        before and was saved over after it had held still (the vendor software saving every frame
        to one name: each frame is lost, and the folder never gets a new file), new files the
        pattern does not match, a full disk."""
        why = f"; {new[0][1]} is still being written" if new else ""
        over = [name for name, entry in self._known.items() if entry[3]]
        strays = sorted(self._names() - self._names_at_arm - {name for name, _ in listing}, key=_natural)
        if not new and over:
            why = (
                f"; {over[0]}, already there, was saved over meanwhile (if the vendor software saves "
                f"every frame to that one name, have it save each frame to a new, numbered file)"
            )
        elif not new and strays:  # the vendor software saves under another name or extension
            why = f"; {len(strays)} new file(s) that do not match the pattern arrived meanwhile, e.g. {strays[-1]}"
        return DetectorTimeout(
            f"detector folder {self.folder}: {got} of {n} frames arrived "
            f"(pattern {self.pattern!r}); no new complete file within {timeout:g} s{why}{self._disk_full()}"
        )

    def _inodes(self) -> set[tuple[int, int]]:
        """(device, inode) of every file in the folder, whatever its name."""
        ids = set()
        try:
            entries = list(os.scandir(self.folder))
        except OSError:
            return ids
        for e in entries:
            try:
                st = _entry_stat(e)
            except OSError:
                continue
            if st.st_ino:
                ids.add((st.st_dev, st.st_ino))
        return ids

    def _names(self) -> set[str]:
        try:
            return set(os.listdir(self.folder))
        except OSError:
            return set()

    def _disk_full(self) -> str:
        """A note when the disk holding the folder cannot take another frame: the vendor software
        then leaves truncated files, or none, and the run would only see a frame that never came."""
        import shutil

        need = 2 * math.prod(self.shape) if self.shape is not None else 1 << 20
        try:
            free = shutil.disk_usage(self.folder).free
        except OSError:
            return ""
        if free >= need:
            return ""
        return f"; the disk holding the folder is full ({free} bytes free): the vendor software cannot save frames"

    def _settled(self, new, now: float) -> list[str]:
        """Names among ``new`` whose size and time stamp have held for ``settle_s``."""
        settled = []
        for _, name, st in new:
            sig = (st.st_size, st.st_mtime_ns)
            seen = self._seen.get(name)
            if seen is None or seen[0] != sig:
                self._seen[name] = (sig, now)
            elif now - seen[1] >= self.settle_s and st.st_size > 0:
                settled.append(name)
        return settled

    @staticmethod
    def _known_entry(st: os.stat_result) -> list:
        """[(size, mtime_ns), monotonic time seen so, held still for settle_s, changed after that]"""
        return [(st.st_size, st.st_mtime_ns), time.monotonic(), False, False]

    def _watch_known(self, listing, now: float) -> None:
        """Note a file never to be taken that changes after it has held still: saved over (the
        vendor software saving every frame to one name), which a time-out then says."""
        for name, st in listing:
            entry = self._known.get(name)
            if entry is None:
                continue
            sig = (st.st_size, st.st_mtime_ns)
            if sig == entry[0]:
                entry[2] = entry[2] or now - entry[1] >= self.settle_s
            else:
                entry[3] = entry[3] or entry[2]
                entry[0], entry[1] = sig, now

    def _is_new(self, name: str, st: os.stat_result, files: dict) -> bool:
        """Not known at arm(), not taken, and not a taken file under a new name: a writer that
        saves to a temporary name and renames it (the same file: device, inode, size and time
        stamp) had each frame taken twice when the temporary name matched the pattern. The
        renamed frame is followed under its new name, and the old name is free for the next
        temporary file."""
        if name in self._known or name in self._taken:
            return False
        ident = _identity(st)
        old = self._took_ids.get(ident) if ident is not None else None
        if old is None:
            if st.st_ino and (st.st_dev, st.st_ino) in self._backlog_ids:  # renamed into the pattern
                self._known[name] = self._known_entry(st)
                log.info("detector folder %s: %s was there before this batch (renamed): not taken", self.folder, name)
                return False
            return True
        self._taken.add(name)
        still = files.get(old)
        if (still is None or _identity(still) != ident) and old in self._took:  # renamed, not a second link
            self._took[name] = self._took.pop(old)
            self._took_ids[ident] = name
            self._taken.discard(old)
            self._seen.pop(old, None)
        log.info("detector folder %s: %s is the frame taken as %s: not taken again", self.folder, name, old)
        return False

    def _took_frame(self, name: str, st: os.stat_result, data: np.ndarray) -> None:
        self._taken.add(name)
        self._seen.pop(name, None)
        self._took[name] = ((st.st_size, st.st_mtime_ns), _digest(data), None)
        ident = _identity(st)
        if ident is not None:
            self._took_ids[ident] = name

    def _recheck_taken(self, listing, now: float) -> None:
        """A file taken as a frame that changes afterwards and, once settled, holds other pixels:
        the vendor software (or another program) saves over the name, so every frame saved there
        since is lost, or the file was still being written when it was taken. Either way say so
        at once, naming the files, rather than time out later (or never) without a word."""
        changed = []
        for name, st in listing:
            took = self._took.get(name)
            sig = (st.st_size, st.st_mtime_ns)
            if took is None or took[0] == sig:
                continue
            seen = self._seen.get(name)
            if seen is None or seen[0] != sig:
                self._seen[name] = (sig, now)
                continue
            if now - seen[1] < self.settle_s:
                continue
            try:
                digest = _digest(self._read(self.folder / name, check=False))
            except _NotYet:
                continue  # being written again: looked at once it reads
            self._seen.pop(name, None)
            self._took[name] = (sig, digest, took[2])
            if digest != took[1]:
                changed.append((str(self.folder / name), took[2]))
        if changed:
            names, frames = [c[0] for c in changed], [c[1] for c in changed if c[1] is not None]
            raise FrameLost(
                f"{names[0]}{f' (and {len(names) - 1} more)' if len(names) > 1 else ''}: changed after it "
                f"was taken as a frame and now holds other pixels: the vendor software or another program "
                f"saves over it (frames saved there since are lost), or it was still being written (a pause "
                f"over settle_s = {self.settle_s:g} s); have the vendor software save every frame to a new, "
                f"numbered file, and nothing else write there",
                origins=frames,
            )

    def _read(self, path: Path, *, check: bool = True) -> np.ndarray:
        """Read one frame file and check it (``check=False``: its pixels as they are);
        :class:`_NotYet` if it does not read (yet)."""
        # tifffile logs what it meets in a damaged file (a warning per bad tag) before radiokit's
        # reader raises the error that names it; retried every poll until the time-out, that was
        # some twenty lines a second on the operator's terminal, X-rays on. The error says it once.
        tiff_log = logging.getLogger("tifffile")
        was = tiff_log.disabled
        tiff_log.disabled = True
        try:
            return self._read_checked(path) if check else self._load(path)
        finally:
            tiff_log.disabled = was

    def _load(self, path: Path) -> np.ndarray:
        """The file's frames ``(n, rows, cols)``; :class:`_NotYet` if it does not read (yet)."""
        fmt = None  # the sniff itself may fail: the file renamed away since it was listed
        try:
            fmt = sniff(path)
            if fmt == "hdf5":
                self._taken.add(path.name)
                raise DeviceError(
                    f"{path}: an HDF5 file, not a frame file the vendor software writes (raw, TIFF or ITEX .img)"
                )
            hints = {}
            if fmt == "raw":
                hints["shape"] = self._raw_shape(path)
            return read(path, **hints).data
        except FormatError as exc:
            raise _NotYet(exc.problem + self._other_geometry(path, fmt)) from None
        except FileNotFoundError:
            raise _Gone(f"{path.name} is gone") from None
        except OSError as exc:  # e.g. still locked by the writer on a network share
            raise _NotYet(exc.strerror or str(exc)) from None

    def _read_checked(self, path: Path) -> np.ndarray:
        data = self._load(path)
        if data.shape[0] != 1:
            self._taken.add(path.name)
            raise DeviceError(f"{path}: holds {data.shape[0]} frames; the detector folder expects one frame per file")
        frame = data[0]
        self._check(path, frame)
        return frame

    def _other_geometry(self, path: Path, fmt) -> str:
        """For a raw file that does not read at the expected shape: the C7942 geometry its size
        is one frame of, if any (the panel set to another effective area or binning than the
        protocol's), so the error says what to change rather than only "truncated"."""
        if fmt != "raw" or self.shape is None:
            return ""
        try:
            size = path.stat().st_size
        except OSError:
            return ""
        fits = [p for p in PRESETS.values() if p.frame_bytes == size and (p.rows, p.cols) != self.shape]
        if len(fits) != 1:
            return ""
        p = fits[0]
        return (
            f"; its size is one {p.rows}x{p.cols} frame (preset {p.name}): is the vendor software set to "
            f"the geometry and binning the protocol expects ({self.shape[0]}x{self.shape[1]})?"
        )

    def _raw_shape(self, path: Path) -> tuple[int, int]:
        if self.shape is not None:
            return self.shape
        size = path.stat().st_size
        match = [p for p in PRESETS.values() if p.frame_bytes == size]
        if len(match) != 1:
            raise _NotYet(
                f"{size} bytes is no single C7942 frame ({PRESETS['c7942'].frame_bytes} bytes at "
                "2240x2240); give the watcher shape= or preset="
            )
        return (match[0].rows, match[0].cols)

    def _check(self, path: Path, frame: np.ndarray) -> None:
        def bad(problem):
            self._taken.add(path.name)
            return DeviceError(f"{path}: {problem}")

        if frame.ndim != 2:
            raise bad(f"frame has shape {frame.shape}; expected (rows, cols)")
        if frame.dtype != np.uint16:
            raise bad(
                f"pixels are {frame.dtype}; the C7942 delivers 16-bit words (uint16): save frames as "
                "16-bit in the vendor software"
            )
        if self.bits is not None and frame.size:
            top = (1 << self.bits) - 1
            peak = int(frame.max())
            if peak > top:
                # radiokit's reading of the evidence (float32 words, byte order, MSB-aligned), as
                # the readers' warning gives it; its advice after ";" (byteorder=, dtype=, divide)
                # is for reading a file by hand, which the watcher does not take
                cause = (bit_depth_cause(frame, self.bits) or "").split(";")[0]
                hint = f" {cause[0].upper()}{cause[1:]}." if cause else ""
                raise bad(
                    f"pixel values up to {peak} exceed the {self.bits}-bit range 0..{top} of the C7942: wrong "
                    f"bit order, byte order, or another detector model (C9730DK/C9732DK are 14-bit).{hint}"
                )
        if self.shape is not None and frame.shape != self.shape:
            why = "given" if self._shape_given else "of the first frame"
            raise bad(
                f"frame is {frame.shape[0]}x{frame.shape[1]} (rows x cols); expected "
                f"{self.shape[0]}x{self.shape[1]} ({why})"
            )
        if self.shape is None:
            self.shape = tuple(frame.shape)
            if not self._pixel_size_given:
                self.pixel_size_mm = self._pixel_size()


class _NotYet(Exception):
    """A settled file does not read as a frame (yet)."""


class _Gone(_NotYet):
    """The file was renamed or removed between the listing and the read."""


class FrameLost(DeviceError):
    """Frame files changed after they were taken: ``origins`` names the frames stored from them
    (each a yielded :class:`Frame`'s ``(origin, time_s)``, the name it was taken under even if
    the file was renamed since; those frames may be incomplete)."""

    def __init__(self, message: str, *, origins: list[str]):
        super().__init__(message)
        self.origins = list(origins)


def _natural(name: str) -> tuple:
    """Sort key reading digit runs as numbers: frame_9 before frame_10 (file systems whose time
    stamps are coarse, FAT's 2 s, give many frames the same one; then the name decides)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name.lower()))


def _entry_stat(entry: os.DirEntry) -> os.stat_result:
    """``entry.stat()`` with its inode number: ``os.scandir`` on Windows (where the vendor software
    runs) leaves it 0, ``os.stat`` fills it, and renamed frames are followed by it."""
    st = entry.stat()
    return os.stat(entry.path) if not st.st_ino else st


def _identity(st: os.stat_result):
    """The same file under another name (a rename keeps all four); None where the file system
    gives no inode number (``os.scandir`` on Windows)."""
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns) if st.st_ino else None


def _digest(data: np.ndarray) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(data).tobytes(), digest_size=16).digest()


# -- the virtual bench ---------------------------------------------------------------------------
class SimDetector:
    """The C7942 of the virtual bench (:class:`sim.bench.VirtualBench`).

    Each frame is rendered through the bench's panel model at the bench's current state when it
    is read out: X-rays off (per ``beam``) gives dark frames; on with the phantom out, flat frames;
    on with it in, exposures of the current line integral. The open-beam signal scales with the
    current relative to the scene's ``exposure.current_ua`` and with the square of the voltage
    relative to ``exposure.voltage_kv`` (a tube's output ~ I kV^2; attenuation does not change
    with kV in this monoenergetic model): see :meth:`sim.bench.VirtualBench.open_beam`.

    Parameters
    ----------
    bench : VirtualBench, or a scene (Scene, preset name or TOML)
        A scene gets a bench of its own (``VirtualBench(scene, seed=seed)``).
    beam : callable, optional
        ``beam() -> (xray_on, kv, ua)``, read at each frame's read-out (the protocols pass one
        that reads the emulated source). None: always on at the scene's exposure.
    frame_time_s : float
        Sleep per frame, to emulate the panel's rate (0.5 s at 1x1, 0.25 at 2x2, 0.11 at 4x4).
    seed : int
        The frames' noise.

    Examples
    --------
    >>> from sim.scene import block_scene
    >>> det = SimDetector(block_scene(size_mm=10), beam=lambda: (False, 0.0, 0.0))
    >>> det.arm()
    >>> [f.origin for f in det.acquire(2)], det.shape
    (['sim', 'sim'], (560, 560))
    """

    kind = "sim"

    def __init__(self, bench, beam=None, *, frame_time_s: float = 0.0, seed: int = 0):
        if not hasattr(bench, "expose"):
            from sim.bench import VirtualBench

            bench = VirtualBench(bench, seed=seed)
        self.bench = bench
        self.beam = beam
        self.frame_time_s = float(frame_time_s)
        if not (math.isfinite(self.frame_time_s) and self.frame_time_s >= 0):
            raise ValueError(f"frame_time_s={frame_time_s!r}: expected a time >= 0")
        self.seed = int(seed)
        self.shape = tuple(bench.panel.shape)
        self.pixel_size_mm = float(bench.scene.detector.pixel_size_mm)
        self._rng = np.random.default_rng(self.seed)
        # a protocol's panel check (a frame not stored) draws from a stream of its own: the series'
        # frames are those of a run without it, so a simulated series stays what it was
        self._check_rng = np.random.default_rng([self.seed, 1])
        self._remaining = None  # frames left before the simulated loss (fail_after)
        self._closed = False
        self.frames_delivered = 0

    def _name(self) -> str:
        return f"simulated detector ({self.bench.scene.name})"

    @property
    def panel_name(self) -> str:
        return self.bench.scene.detector.panel_name

    @property
    def pixel_size_from(self) -> str:
        return self.bench.scene.detector.pixel_size_from

    def fail_after(self, k: int | None) -> None:
        """Fault injection: deliver ``k`` more frames, then none (a lost detector): ``acquire``
        raises :class:`DetectorTimeout` at the next frame, and in every later call. ``None``
        restores the detector."""
        self._remaining = None if k is None else operator.index(k)

    def arm(self) -> None:
        if self._closed:
            raise DeviceError(f"{self._name()}: closed")

    def _beam(self) -> tuple[bool, float | None, float | None]:
        if self.beam is None:
            return True, None, None
        on, kv, ua = self.beam()
        return bool(on), float(kv), float(ua)

    def acquire(self, n: int, *, timeout_s: float | None = None) -> Iterator[Frame]:
        """Yield ``n`` frames rendered from the bench, one per ``frame_time_s``.

        A lost detector (:meth:`fail_after`) raises :class:`DetectorTimeout` at once, without
        waiting out ``timeout_s``: the simulation knows the frame will not come. A
        ``frame_time_s`` longer than ``timeout_s`` times out after ``timeout_s``.
        """
        return self._frames(_count(n), timeout_s, self._rng)

    def check(self, *, timeout_s: float | None = None) -> Frame:
        """One frame, as :meth:`acquire` gives it, for a check that does not store it (a
        protocol's panel check before X-rays): its noise from a stream of its own."""
        return next(iter(self._frames(1, timeout_s, self._check_rng)))

    def _frames(self, n: int, timeout_s, rng) -> Iterator[Frame]:
        for k in range(n):
            if self._closed:
                raise DeviceError(f"{self._name()}: closed")
            if self._remaining is not None and self._remaining <= 0:
                raise DetectorTimeout(
                    f"{self._name()}: {k} of {n} frames arrived; the detector stopped delivering (lost: fail_after)"
                )
            if timeout_s is not None and self.frame_time_s > timeout_s:
                time.sleep(max(float(timeout_s), 0.0))
                raise DetectorTimeout(
                    f"{self._name()}: {k} of {n} frames arrived; a frame takes "
                    f"{self.frame_time_s:g} s, longer than the time-out of {timeout_s:g} s"
                )
            if self.frame_time_s:
                time.sleep(self.frame_time_s)
            on, kv, ua = self._beam()
            data = self.bench.expose(1, xray_on=on, kv=kv, ua=ua, rng=rng)[0]
            if self._remaining is not None:
                self._remaining -= 1
            self.frames_delivered += 1
            yield Frame(data, time.time(), "sim")

    def begin_batch(self, discard: int = 0) -> None:
        """Each frame is rendered at the bench's state when it is read out: none is ever made
        before the state it shows, so there is nothing to skip."""

    def describe(self) -> dict:
        d = {
            "kind": self.kind,
            "shape": list(self.shape),
            "pixel_size_mm": self.pixel_size_mm,
            "frame_time_s": self.frame_time_s,
            "seed": self.seed,
        }
        bench = self.bench.describe() if hasattr(self.bench, "describe") else {}
        d["scene"] = bench.pop("scene", getattr(self.bench.scene, "name", None))
        d["bench"] = bench
        return d

    def close(self) -> None:
        self._closed = True

    def __repr__(self):
        return f"SimDetector({self.bench!r})"
