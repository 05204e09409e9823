"""What every typed-layout reader shares: opening a file it did not write, and reading from it safely.

A results, registration, stack or simulation file may come from anywhere: cut short by a full
disk, edited by hand, or made to hurt. libhdf5 reports such files with OSError, RuntimeError
("too many links" for soft links in a circle), KeyError or TypeError, none of which name the
file; :func:`open_layout` turns each into one :class:`FormatError` line that does.
"""

from __future__ import annotations

import errno
import math
import os
import re
import stat
from contextlib import contextmanager

import h5py
import numpy as np

from radiokit.errors import FormatError
from radiokit.io._budget import check_budget

__all__ = ["open_h5", "open_layout", "check_regular_file", "ReadBudget", "text", "check_finite"]

#: what libhdf5 and h5py raise on a corrupt file (RecursionError: links nested past Python's limit)
_H5_ERRORS = (OSError, RuntimeError, KeyError, TypeError, ValueError, RecursionError)


@contextmanager
def open_layout(path, what: str):
    """Open ``path`` read-only; any h5py failure inside the block is a FormatError naming ``path``.

    ``what`` names the layout in the message ("a radiokit results file").
    """
    check_regular_file(path, what)
    try:
        h5 = open_h5(path)
    except OSError as exc:
        raise FormatError(
            path, f"cannot be opened as HDF5, so not {what} (truncated or another format): {_one_line(exc)}"
        ) from None
    try:
        with h5:
            yield h5
    except FormatError:
        raise
    except _H5_ERRORS as exc:
        raise FormatError(path, f"corrupt, not {what}: {type(exc).__name__}: {_one_line(exc)}") from exc


def open_h5(path) -> h5py.File:
    """Open an HDF5 file for reading, also while another program writes it.

    A writer in SWMR mode (detector and beamline software), or one killed in it, leaves the file
    marked open for write, which only a SWMR reader may open: read it so, as it stands. A writer
    without SWMR holds the file's lock, or left its mark unclosed (killed; or alive where file
    locking is off, as on many NFS and Lustre mounts): its file cannot be read consistently, and
    libhdf5's "unable to lock file, errno = 11" or "file is not already open for SWMR writing"
    are said in words instead. Other failures propagate as OSError for the caller to name.
    """
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        if exc.errno == errno.EAGAIN or "unable to lock file" in str(exc):
            raise FormatError(
                path,
                "is open for writing by another program (it holds the HDF5 file lock): read it once that is closed",
            ) from None
        cut = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if cut:  # libhdf5's words were the line: "Unable to synchronously open file (truncated file: eof = ..."
            raise FormatError(
                path,
                f"truncated: it holds {cut[1]} of the {cut[2]} bytes its header declares (an interrupted copy, "
                "transfer or write): copy it again from where it was made",
            ) from None
        if "already open for write" not in str(exc):
            raise
    try:
        return h5py.File(path, "r", swmr=True)
    except OSError:
        raise FormatError(
            path,
            "is marked open for writing by a program that is still writing it or was stopped before "
            "closing it: read it once it is closed (a file left so by a crash: `h5clear -s` it first)",
        ) from None


def check_regular_file(path, what: str) -> None:
    """Refuse a missing path, a directory, and a FIFO, socket or device: opening a FIFO waits for a
    writer forever, and ``/dev/zero`` never ends."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FormatError(path, "no such file") from None
    except OSError as exc:
        raise FormatError(path, f"cannot be opened: {exc.strerror or exc}") from None
    if stat.S_ISDIR(mode):
        raise FormatError(path, f"is a directory, not {what}")
    if not stat.S_ISREG(mode):
        raise FormatError(path, f"is not a regular file (a FIFO, socket or device), so not {what}")
    check_readable(path)


def check_readable(path) -> None:
    """Refuse a regular file this process may not read, saying so: otherwise Python's
    "[Errno 13] Permission denied: 'x'" or libhdf5's "unable to open file ... errno = 13" after
    "cannot be opened as HDF5, so not ... (truncated or another format)" misdiagnosed the file."""
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise FormatError(path, f"cannot be read: {exc.strerror or exc}") from None


class ReadBudget:
    """The memory budget one record is read within: every array read counts against it, so a
    file of many arrays each under the budget cannot add up to more than it."""

    def __init__(self, path, budget=None):
        self.path, self.budget, self.spent = path, budget, 0

    def reserve(self, nbytes: int, what: str) -> None:
        """Count ``nbytes`` (what ``what`` will allocate), or raise FormatError if over the budget."""
        before = f" after {self.spent} bytes read" if self.spent else ""
        check_budget(self.path, self.spent + int(nbytes), what + before, self.budget)
        self.spent += int(nbytes)

    def read(self, ds: h5py.Dataset) -> np.ndarray:
        """All of ``ds``, once its declared size has been counted."""
        self.reserve(math.prod(int(s) for s in ds.shape) * ds.dtype.itemsize, f"/{ds.name.lstrip('/')} {ds.shape}")
        return ds[()]


def text(value) -> str:
    """A text attribute as printable str: bytes that are not UTF-8 become U+FFFD (h5py hands
    them over as lone surrogates, which cannot be printed or written)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, str):
        return value.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
    return str(value)


def path_text(path) -> str:
    """A file's name as UTF-8 text for an HDF5 attribute: a POSIX name may hold bytes that are
    not UTF-8 (a Latin-1 name), which h5py cannot encode; those are written as ``\\xNN``."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def check_finite(path, name: str, values: np.ndarray, *, nan_ok: bool = False) -> None:
    """Refuse inf (and NaN unless ``nan_ok``) in ``values``, the dataset ``name``."""
    bad = np.isinf(values) if nan_ok else ~np.isfinite(values)
    if np.any(bad):
        raise FormatError(
            path,
            f"/{name.lstrip('/')} holds {'inf' if nan_ok else 'NaN or inf'} (at index {int(np.flatnonzero(bad.ravel())[0])})",
        )


def _one_line(exc) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
