"""Outputs that appear whole or not at all, and never replace what radiokit did not make.

Every file radiokit writes goes to a temporary name beside its destination and is renamed into
place (atomic within one filesystem) only once complete; a results folder is assembled in a
temporary sibling folder and swapped in. Without ``overwrite`` the rename takes the name only if
it is still free (:func:`_publish`): what appeared there during the run is never replaced. An output that is a symbolic link is
written at its target, beside which its temporary is made; the link is kept. An interrupted run therefore leaves the
previous complete output, or none: never a truncated file or a folder mixing two runs. A kill
-9 can leave the hidden temporary (``.NAME.tmp-HOST-PID-XXXXXXXX``) behind; it is never mistaken
for output, and the next run writing the same output on that host removes it once its process is
gone. A results folder being replaced is swapped with the new one in one step where the system
can (Linux's renameat2), so its name is never missing; elsewhere it is renamed aside (``.NAME.old-HOST-PID-XXXXXXXX``) while the
new one is swapped in: that one is the user's previous results, never removed but by the run that
put it aside once its new folder is in place; a kill -9 in between leaves it, and the next run to
that output puts it back at its name.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import glob
import hashlib
import math
import os
import re
import secrets
import shutil
import signal
import socket
import stat
import warnings
from pathlib import Path

from radiokit._names import linked, shown
from radiokit.errors import RadiokitError
from radiokit.interrupts import held, settle

__all__ = [
    "atomic_path",
    "atomic_dir",
    "check_output",
    "OutputError",
    "OutputExistsError",
    "RESULTS_MARKER",
    "folder_marker",
    "DiskFullError",
    "FileTooLargeError",
    "is_disk_full",
    "atomic_h5",
    "check_free_space",
]

#: written into every results folder radiokit assembles: only such folders may be replaced
RESULTS_MARKER = ".radiokit-output"


def folder_marker(command: str) -> str:
    """The first line of :data:`RESULTS_MARKER` in a folder ``radiokit COMMAND`` made: it names the
    command, whose folders alone that command replaces (``radiokit demo``'s folder holds the
    results folder of its own ``process`` run, and is not one)."""
    return f"made by radiokit {command}; may be replaced by a run with --overwrite."


def refuse_another_commands(folder: Path, command: str) -> None:
    """Raise :class:`OutputError` if ``folder``'s marker says another command than ``radiokit
    COMMAND`` made it, or is one radiokit does not recognise: a command never writes into, nor
    replaces, another's folder, and a marker of no form radiokit wrote (by hand, another tool's)
    says nothing of whose the files beside it are."""
    marker = folder / RESULTS_MARKER
    if not os.path.lexists(marker):
        return
    found = _made_by(folder) if marker.is_file() and not marker.is_symlink() else None
    if found is None:
        raise OutputError(
            folder,
            f"holds a {RESULTS_MARKER} radiokit does not recognise (its first line names no radiokit command); "
            "it is never replaced: choose another output",
        )
    if found != command:
        raise OutputError(
            folder,
            f"made by radiokit {found}, not by radiokit {command}: a command never replaces another's folder; "
            "choose another output",
        )


#: the first line of a results folder's marker before markers named the command (only process
#: wrote one then); any other line without a command's name is not radiokit's
_UNNAMED_MARKER = "made by radiokit; may be replaced by a run with --overwrite. Files:"


def _made_by(folder: Path) -> str | None:
    """The command whose marker ``folder`` holds (None: not one radiokit wrote in this form).
    A line is recognised whole, as radiokit wrote it: ``made by radiokit;`` alone (a hand-made
    or cut copy) says nothing of whose the files are."""
    with open(folder / RESULTS_MARKER, "rb") as f:  # its first line only, whatever the file holds
        head = f.read(256).split(b"\n", 1)[0].decode("utf-8", "replace").rstrip("\r")
    if head == _UNNAMED_MARKER:
        return "process"
    # demo's first form went on "`radiokit demo --overwrite`", the present one "a run with --overwrite."
    found = re.fullmatch(
        r"made by radiokit ([\w-]+); may be replaced by (?:a run with --overwrite\.|`.*`)(?: Files:)?", head
    )
    return None if found is None else found.group(1)


class OutputError(RadiokitError, OSError):
    """An output cannot be written where asked (it is an input, or not radiokit's to replace)."""

    def __init__(self, path, problem, err=errno.EINVAL, *, target=None):
        # target: what ``path``, a symbolic link the user named, points at (named beside it)
        self.path, self.problem, self.target = str(path), problem, None if target is None else str(target)
        OSError.__init__(self, err, problem)

    def __str__(self):
        return f"{linked(self.path, self.target)}: {self.problem}"


class OutputExistsError(OutputError, FileExistsError):
    """The output exists and ``overwrite`` was not given."""

    #: How the message names the way to replace it, for the API and the shell at once; the command
    #: line replaces it with the option alone (``radiokit.cli._error_line``), wherever the message
    #: ends up (a batch's line names the file first)
    HOW = "--overwrite (overwrite=True)"

    def __init__(self, path):
        super().__init__(path, f"exists; pass {self.HOW} to replace it", errno.EEXIST)


class OutputAppearedError(OutputError, FileExistsError):
    """Something appeared at the output's name while the run was writing it (checked free at the
    start), and ``overwrite`` was not given: it was not replaced, the run's output discarded."""

    def __init__(self, path):
        super().__init__(
            path,
            "appeared during the run (another run or program made it meanwhile); it was not replaced and "
            f"this run's output was discarded: choose another output, or pass {OutputExistsError.HOW} to replace it",
            errno.EEXIST,
        )


class DiskFullError(OutputError):
    """The disk (or quota) is, or filled while writing, too full; the partial output was removed."""

    def __init__(self, path, detail=""):
        super().__init__(
            path,
            f"no space left on the device{detail}; nothing was written (the partial output was removed)",
            errno.ENOSPC,
        )


#: File systems whose files stop at 4 GiB - 1 (FAT12/16/32; exFAT has no such limit).
_FAT_TYPES = frozenset({"vfat", "msdos", "fat", "umsdos"})
_FAT_MAX_FILE = 2**32 - 1


def _file_system_type(folder) -> str | None:
    """The type of the file system holding ``folder`` (Linux: the longest mount point of
    /proc/self/mounts above it), or None where that is not known.

    Why not ``pathconf(PC_FILESIZEBITS)``: glibc answers 32 for every file system it does not
    list (tmpfs, NFS, CIFS, FUSE, overlay), which capped experiment files there at 2 GiB --
    about 200 full frames -- with no such limit on the disk."""
    try:
        target = os.path.realpath(folder)
        best, kind = "", None
        with open("/proc/self/mounts", encoding="utf-8", errors="replace") as f:
            for line in f:
                fields = line.split()
                if len(fields) < 3:
                    continue
                mount = fields[1].replace("\\040", " ")
                inside = target == mount or target.startswith(mount.rstrip("/") + "/")
                if inside and len(mount) >= len(best):
                    best, kind = mount, fields[2]
        return kind
    except OSError:  # no /proc (not Linux): no file-system limit assumed
        return None


def file_size_limit(folder) -> float:
    """The largest file this process may write in ``folder``, in bytes: its ``RLIMIT_FSIZE``
    (``ulimit -f``) and, on a FAT file system, 4 GiB - 1, whichever is lower (inf: none)."""
    limit = math.inf
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY:
            limit = soft
    except (ImportError, OSError, ValueError):  # no resource module (Windows): no process limit
        pass
    if _file_system_type(folder) in _FAT_TYPES:
        limit = min(limit, _FAT_MAX_FILE)
    return limit


class FileTooLargeError(OutputError):
    """The output would pass, or passed while being written, the largest file this process may
    write there (``ulimit -f``, a FAT disk's 4 GiB); the partial output was removed."""

    def __init__(self, path, detail=""):
        self.detail = detail
        super().__init__(
            path,
            f"larger than the file-size limit{detail}; nothing was written (the partial output was removed)",
            errno.EFBIG,
        )


def _is_too_large(exc: BaseException, tmp: Path) -> bool:
    """``exc`` (or its cause) is a write past the file-size limit: EFBIG (h5py only in its text),
    or numpy's short write (tifffile) that stopped at the limit. Python ignores SIGXFSZ, so the
    write fails with EFBIG rather than the process being killed."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno == errno.EFBIG:
            return True
        if "File too large" in str(exc) or "errno = 27" in str(exc):
            return True
        if isinstance(exc, OSError) and exc.errno is None and re.fullmatch(r"\d+ requested and \d+ written", str(exc)):
            try:  # a short write: at the limit it is this, else a full disk (is_disk_full)
                return tmp.stat().st_size >= file_size_limit(tmp.parent)
            except OSError:
                return False
        exc = exc.__cause__ or exc.__context__
    return False


def _too_large_in(exc, tmp: Path, path: Path) -> FileTooLargeError:
    """The :class:`FileTooLargeError` of folder ``path`` (being assembled in ``tmp``): naming the
    file inside it that hit the limit, as ``path/results.h5``, where an inner error says which."""
    inner = exc
    while inner is not None and not isinstance(inner, FileTooLargeError):
        inner = inner.__cause__ or inner.__context__
    if inner is None:
        return FileTooLargeError(path, f" ({file_size_limit(path.parent)} bytes)")
    try:
        name = path / Path(inner.path).relative_to(tmp)
    except ValueError:
        name = path
    return FileTooLargeError(name, inner.detail)


def _human(n) -> str:
    """Bytes in MiB, or GiB and TiB past them (a header's 10**8 frames: "5.9 TiB", not 6 million MiB)."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n / 2**20:.1f} MiB"


def check_free_space(path, nbytes) -> None:
    """Refuse, before writing, an output of about ``nbytes`` that cannot fit beside ``path``.

    Failing before the first byte is the clean way: libhdf5 reports a full disk in the middle of
    a write through destructors, and has crashed the interpreter afterwards.
    """
    folder = Path(path).parent
    while not folder.exists():
        folder = folder.parent
    usage = shutil.disk_usage(folder)
    free = usage.free
    if usage.total and nbytes > free:  # total 0: a pseudo filesystem; let the write say what is wrong
        raise DiskFullError(path, f" (needs about {_human(nbytes)}, {_human(free)} free)")
    # as a full disk, a write past ``ulimit -f`` fails inside libhdf5, which then crashed the
    # interpreter (SIGSEGV) while closing the file: refused before the first byte instead
    limit = file_size_limit(folder)
    if nbytes > limit:
        raise FileTooLargeError(path, f" ({limit} bytes: ulimit -f, or a FAT disk's 4 GiB; it needs about {nbytes})")


def is_disk_full(exc: BaseException) -> bool:
    """``exc`` (or what caused it) is a full disk or quota; h5py reports the errno only in its text."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(exc) or "errno = 28" in str(exc):
            return True
        # numpy's tofile (tifffile's writer) reports a short write without an errno; on a
        # regular file that is a full disk or quota
        if isinstance(exc, OSError) and exc.errno is None and re.fullmatch(r"\d+ requested and \d+ written", str(exc)):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def resolved(path) -> Path:
    """``path`` with its links resolved, as far as they go.

    Why not ``Path.resolve``: before Python 3.13 it raises RuntimeError on a symbolic link in a
    loop (a -> b -> a), which reached the user as a traceback from the output checks. A loop is
    left unresolved here; opening it then fails with "Too many levels of symbolic links"."""
    return Path(os.path.realpath(path))


def _same(a: Path, b: Path) -> bool:
    """``a`` and ``b`` name the same file: same path after resolving links, or same inode (hard link)."""
    if resolved(a) == resolved(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _inside(inner: Path, outer: Path) -> bool:
    inner, outer = resolved(inner), resolved(outer)
    return inner == outer or outer in inner.parents


def check_output(path, *, overwrite=False, inputs=(), folder=False, made_by="process") -> Path:
    """Refuse an output that is an input (even with ``overwrite``), or exists without ``overwrite``.

    Parameters
    ----------
    path : path-like
        The file (or, with ``folder=True``, the results folder) to be written. A symbolic link
        stands for its target: the target is checked, and returned to be written (the link is
        kept); a link in a loop, or into a folder that does not exist, is refused.
    overwrite : bool
        Allow replacing an existing output radiokit made.
    inputs : iterable of path-like
        Files the run reads. An output that is one of them (the same path, a symlink to it or a
        hard link), or a folder holding one, is refused.
    folder : bool
        ``path`` is a results folder: it may be replaced only if it is empty or radiokit made it
        (it holds :data:`RESULTS_MARKER`).
    made_by : str
        The command writing the folder: a folder another command made (its marker's
        :func:`folder_marker` names it) is refused, with ``overwrite`` too.

    Returns
    -------
    Path
        The path to write: ``path``, or the target of the link it is.

    Raises
    ------
    OutputError, OutputExistsError
    """
    path = Path(path)
    try:
        target = _link_target(path, folder)
        if folder:
            _restore_interrupted(target, path)
        try:
            _check_output(target, overwrite, inputs, folder and made_by)
            _check_data_files(target, inputs, folder)
            if not folder and _written_as(target) != _written_as(path):  # writers go by the name given
                raise OutputError(target, f"its name's {target.suffix or 'missing'} suffix is not {path.suffix}")
        except OutputError as exc:
            if target != path:  # named as the user gave it, and what it points at
                exc.path, exc.target = str(path), str(target)
            raise
        return target
    except OutputError:
        raise
    except OSError as exc:  # Path.exists() raises on a name past NAME_MAX (ENAMETOOLONG) or a loop
        raise OutputError(path, f"cannot be written: {exc.strerror or exc}") from None


def _check_data_files(path: Path, inputs, folder) -> None:
    """Refuse an output onto (or, for a folder, holding) a file an input's HDF5 frames are read
    from: external links' targets, virtual datasets' sources, external raw storage.

    Why here, for every writer and whether or not the run follows links: the check was the
    CLI's alone, and `correct_files(['master.h5'], cal, 'frames_000001.h5', allow_external=True,
    overwrite=True)` replaced the detector's frames. Refusing a file an input merely names costs
    a choice of another output name; allowing it cost the data."""
    from radiokit.io._experiment import IncompleteListingError, data_files  # late: _experiment imports this module

    for src in inputs:
        # os.path.isfile: an input whose name cannot even be looked up (past the file system's
        # NAME_MAX: Path.is_dir raised, and the *output* was said not writable) lists no data
        # files; its reader says what is wrong with it
        if not src or not os.path.isfile(src):
            continue
        try:
            listed = data_files(src, allow_external=True)
        except IncompleteListingError as exc:
            # libhdf5 may still read the frames through a link the walk never reached: an output
            # that exists could be them. One that does not exist can be no input's file
            if os.path.lexists(path) and not (folder and path.is_dir() and not any(path.iterdir())):
                raise OutputError(
                    path,
                    f"cannot tell whether input {shown(src)}'s frames are read from it: {shown(exc.path)}: {exc.problem}, "
                    "so its links cannot be listed; choose an output that does not exist yet",
                ) from None
            continue
        for data in listed:
            if _inside(data, path) if folder else _same(data, path):
                raise OutputError(
                    path,
                    f"{'holds' if folder else 'is'} {shown(data)}, which input {shown(src)}'s frames are read from: "
                    "an input is never overwritten; choose another output",
                )


def _written_as(path: Path) -> str:
    """What a writer makes of ``path``'s suffix: .h5 and .hdf5 (or .tif and .tiff) write the same."""
    from radiokit.io._source import _EXTENSIONS  # imported late: the readers need not load to write

    suffix = path.suffix.lower()
    return _EXTENSIONS.get(suffix, suffix)


def _link_target(path: Path, folder: bool) -> Path:
    """The output ``path`` names: itself, or the file or folder the symbolic link it is points at.

    Why: renamed into place over the link, the output replaced the link itself with a regular
    file and left the file it points at, the one the user meant, stale. The target is written
    instead, its temporary beside it (a rename stays on one file system), and every rule
    (--overwrite, read-only, a folder radiokit made) applies to it; a dangling link writes its
    target, as the shell's ``>`` does, if the folder it names exists."""
    if not path.is_symlink():
        return path
    target = resolved(path)
    if target.is_symlink():  # realpath leaves a loop unresolved
        raise OutputError(path, "is a symbolic link in a loop (it never reaches a file); choose another output")
    if not target.parent.is_dir():
        raise OutputError(
            path,
            f"is a symbolic link to {shown(target)}, whose folder {shown(target.parent)} does not exist; choose another output",
        )
    return target


def _check_output(path: Path, overwrite, inputs, folder: str | bool) -> Path:
    """:func:`check_output`; ``folder`` is the command writing the folder, or False (a file)."""
    for src in inputs:
        src = Path(src)
        if (
            (folder and _inside(src, path))
            # os.path.exists: an input whose name cannot even be looked up (longer than the
            # file system takes) is no file the output could be; its reader says what is wrong
            # with it (Path.exists raised, and the output was said not writable)
            or (not folder and os.path.exists(src) and path.exists() and _same(src, path))
            or resolved(src) == resolved(path)
        ):
            raise OutputError(
                path,
                f"{'holds' if folder and resolved(src) != resolved(path) else 'is'} the "
                f"input {shown(src)}: an input is never overwritten; choose another output",
            )
    holder = next((p for p in path.parents if os.path.lexists(p)), None)  # checked now, not after the work
    if holder is not None and not holder.is_dir():
        if holder.is_symlink() and not holder.exists():  # not "a file": a link to nothing
            raise OutputError(
                path,
                f"{holder} is a symbolic link to {os.readlink(holder)}, which does not exist: no folder to hold "
                "the output; choose another output",
            )
        raise OutputError(path, f"{holder} is a file, not a folder to hold the output; choose another output")
    if not (path.exists() or path.is_symlink()):
        return path
    if folder:
        if not path.is_dir() or path.is_symlink():
            raise OutputError(path, "exists and is not a folder radiokit made; choose another output")
        refuse_another_commands(path, folder)
        if _read_only(path):
            raise OutputError(
                path,
                "is a read-only folder: radiokit never replaces it, --overwrite or not; make it writable "
                "(chmod u+w) or choose another output",
                errno.EACCES,
            )
        if any(path.iterdir()) and not (path / RESULTS_MARKER).exists():
            raise OutputError(
                path, "exists, is not empty and was not made by radiokit; it is never replaced: choose a new folder"
            )
        if not any(path.iterdir()):
            return path  # an empty folder holds nothing to lose
    elif path.is_dir():
        raise OutputError(path, "is a folder; expected a file name")
    elif path.exists() and not stat.S_ISREG(path.stat().st_mode):
        # even with --overwrite: the output is written beside it and renamed into place, which
        # replaced a FIFO (or a device, through a symlink) with a regular file; -o /dev/null too
        raise OutputError(
            path, f"is {_kind(path.stat().st_mode)}, not a regular file: radiokit never replaces it; choose a file name"
        )
    elif path.exists() and _read_only(path):
        # even with --overwrite: the rename into place is not stopped by the file's own mode, so a
        # file its owner protected would be replaced where writing into it fails
        raise OutputError(
            path,
            "is read-only: radiokit never replaces it, --overwrite or not; make it writable (chmod u+w) "
            "or choose another output",
            errno.EACCES,
        )
    if not overwrite:
        raise OutputExistsError(path)
    return path


def _read_only(path: Path) -> bool:
    """Whether writing into ``path`` is not allowed: by its owner's write bit for one's own file
    (root included, whom access() lets write anything), else as access() says."""
    st = path.stat()
    if st.st_uid == os.geteuid():
        return not st.st_mode & stat.S_IWUSR
    return not os.access(path, os.W_OK)


def _keep_mode(tmp: Path, path: Path) -> None:
    """Give ``tmp``, about to replace ``path``, the permissions (and owner and group, where
    allowed) ``path`` has: a replaced output is one written into, for whoever may read it."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return
    try:
        os.chmod(tmp, stat.S_IMODE(st.st_mode))
    except OSError:  # vfat, some FUSE and SMB mounts refuse it (EPERM): the output matters more
        pass
    for uid in (st.st_uid, -1):  # another's file keeps its owner only for root
        try:
            os.chown(tmp, uid, st.st_gid)
            return
        except OSError:  # a group one is not in: the umask's group, as a new file gets
            continue


def _kind(mode: int) -> str:
    """What a file that is not a regular file or a folder is, for an error message."""
    for test, name in (
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "a special file"


def _files(folder: Path) -> set[str]:
    """Every file under ``folder`` (relative, "/"-separated), the marker left out; an empty
    folder and a symbolic link to a folder count as files. Why: they were not looked at, so one
    the user put into an old results folder was deleted with it by --overwrite, where a file
    was refused."""
    out = set()
    for root, dirs, names in os.walk(folder):
        for name in names:
            out.add(Path(root, name).relative_to(folder).as_posix())
        for name in dirs:  # os.walk lists a link to a folder here, and does not enter it
            sub = Path(root, name)
            try:
                with os.scandir(sub) as entries:
                    listed = sub.is_symlink() or not any(entries)
            except OSError:  # unreadable: os.walk does not enter it, so what it holds is unknown
                listed = True
            if listed:
                out.add(sub.relative_to(folder).as_posix())
    out.discard(RESULTS_MARKER)
    return out


def _manifest(folder: Path) -> set[str]:
    """The files the marker says radiokit wrote (its lines after the first)."""
    lines = (folder / RESULTS_MARKER).read_text(errors="replace").splitlines()
    return {line for line in lines[1:] if line}


def _owner_tag() -> str:
    return f"{socket.gethostname().split('.')[0]}-{os.getpid()}"


#: the longest file name most filesystems take (NAME_MAX), in bytes
_NAME_MAX = 255


def _head(path: Path, folder: bool, kind: str = "tmp") -> str:
    """The part of ``path``'s name its temporaries begin with: the name (a folder) or the stem,
    cut so that ``.HEAD.KIND-HOST-PID-RANDOM.SUFFIX`` fits in NAME_MAX bytes as ``path`` does
    (room for a 10-digit PID: the same head for every process, so stale ones are found). A cut
    head ends ``~`` and 8 hex digits of the whole name's SHA-256.

    Why the digest: cut alone, two names alike in their first ~227 bytes had one head, and the
    results one left aside were put back at the other's name, or named in its warning."""
    head, tail = (path.name, "") if folder else (path.stem, path.suffix)
    room = _NAME_MAX - len(os.fsencode(f"..{kind}-{socket.gethostname().split('.')[0]}-{10 * '0'}-{8 * '0'}{tail}"))
    if len(os.fsencode(head)) <= room:
        return head
    mark = "~" + hashlib.sha256(os.fsencode(path.name)).hexdigest()[:8]
    while head and len(os.fsencode(head + mark)) > room:  # cut whole characters, not bytes of one
        head = head[:-1]
    return head + mark


def _temporary_name(path: Path, folder=False, kind="tmp") -> Path:
    """``.NAME.tmp-HOST-PID-RANDOM`` beside ``path`` (``old`` for a folder being replaced); a file
    keeps its suffix last, since writers choose the format from it (StackWriter, matplotlib)."""
    tag = f"{kind}-{_owner_tag()}-{secrets.token_hex(4)}"
    return path.with_name(f".{_head(path, folder, kind)}.{tag}{'' if folder else path.suffix}")


def _remove_stale(path: Path, folder=False) -> None:
    """Remove temporaries of ``path`` that a killed radiokit on this host left (its process is
    gone): only names radiokit makes, never anything else.

    Only ``tmp`` ones, which hold nothing but what that run wrote. Why never an ``old`` one (a
    replaced results folder renamed aside): a run killed between renaming it aside and
    swapping its new folder in leaves the user's previous results (and any notes added to
    them) there alone, and removing it here deleted them on the next run to that name, failing
    or not. It is put back instead (:func:`_restore_interrupted`)."""
    for stale in _leftovers(path, folder, "tmp"):
        _remove(stale)


def _leftovers(path: Path, folder: bool, kind: str) -> list[Path]:
    """The ``kind`` temporaries of ``path`` left by a radiokit on this host whose process is gone,
    by the name :func:`_head` gives them. One a radiokit before session 40 left under a cut name
    without its digest is not looked for: that name may be another output's whole name (one of
    227 bytes, and a longer one beginning with it), whose results would be put back here."""
    host = socket.gethostname().split(".")[0]
    suffix = "" if folder else path.suffix
    head = _head(path, folder, kind)
    # the name's own characters taken literally: "scan[1]" is no character class
    pattern = f".{glob.escape(head)}.{kind}-{glob.escape(host)}-*{glob.escape(suffix)}"
    whole = rf"\.{re.escape(head)}\.{kind}-{re.escape(host)}-(\d+)-[0-9a-f]{{8}}{re.escape(suffix)}"
    found = []
    for left in sorted(path.parent.glob(pattern)):
        m = re.fullmatch(whole, left.name)
        if m and int(m.group(1)) != os.getpid() and not _alive(int(m.group(1))):
            found.append(left)
    return found


def _restore_interrupted(path: Path, named: Path | None = None) -> None:
    """Put back at ``path`` the previous results folder a killed run left renamed aside
    (``.NAME.old-HOST-PID-X``) before its new one took the name: the name is missing only then.

    With two or more such folders which one is the user's latest is not known: refused, naming
    them, rather than guessed. Where the name is there, a leftover is kept as it is (never
    removed: it may hold notes the user added), and named in a warning: a hidden folder nothing
    points to is results the user believes gone. ``named``: the output as the user named it, a
    symbolic link to ``path``, for messages."""
    if not path.parent.is_dir():
        return
    link = named is not None and named != path
    user, target = (named, path) if link else (path, None)
    aside = _leftovers(path, True, "old")
    if os.path.lexists(path):
        if aside:
            beside = shown(path.name) if link else "it"  # (the leftovers lie beside the link's target)
            message = UserWarning(
                f"{linked(user, target)}: previous results of an interrupted run are kept beside {beside} in "
                f"{', '.join(shown(p.name) for p in aside)}; remove {'it' if len(aside) == 1 else 'them'} "
                "once nothing there is needed"
            )
            message.path = str(user)  # once per command: the output is checked again before it is written
            warnings.warn(message, stacklevel=4)
        return
    if len(aside) == 1:
        with contextlib.suppress(OutputError):  # the name taken meanwhile: that one stays
            _publish(aside[0], path, folder=True)
    elif aside:
        raise OutputError(
            user,
            f"is missing, and {len(aside)} previous results folders of interrupted runs are kept beside it "
            f"({', '.join(shown(p.name) for p in aside)}): rename the one to keep back to {shown(path.name)}, "
            "then run again",
            target=target,
        )


def recover_interrupted(folder) -> None:
    """Clear what a writer of the results folder ``folder`` left when it was killed (its process
    gone): remove the temporary it was building, and put back at the name the previous results it
    had renamed aside, where the name is missing (an :class:`OutputError` where two or more are
    aside: which one is the user's latest is not known). What the next :func:`atomic_dir` to
    ``folder`` does first, for a caller whose writers were killed (``radiokit.pipeline.process_many``'s
    Dask workers, stopped mid-file)."""
    folder = Path(folder)
    _remove_stale(folder, folder=True)
    _restore_interrupted(folder)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # alive, another user's
        return True
    return True


def _fsync(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some filesystems (and directories on some systems) refuse: best effort
        pass
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if not os.path.lexists(path):  # unlink on a read-only filesystem fails even for no file
        return
    with contextlib.suppress(FileNotFoundError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink()


#: renameat2's flag: fail with EEXIST rather than replace what is at the new name
_RENAME_NOREPLACE = 1
_AT_FDCWD = -100
#: errors by which a file system (or kernel) says it does not do a rename's flags, or hard links
_UNSUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EPERM, errno.EXDEV}


@functools.lru_cache(maxsize=1)
def _renameat2():
    """libc's renameat2 (Linux, glibc 2.28+), or None."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError, ImportError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def _renameat2_call(src: Path, dst: Path, flag: int) -> int | None:
    """renameat2(``src``, ``dst``, ``flag``): 0 when done, else its errno; None where the system
    has no renameat2, or (``_UNSUPPORTED``) says it does not do that flag."""
    import ctypes

    fn = _renameat2()
    if fn is None:
        return None
    if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flag) == 0:
        return 0
    err = ctypes.get_errno()
    return None if err in _UNSUPPORTED else err


def _rename_noreplace(src: Path, dst: Path) -> bool:
    """Rename ``src`` to ``dst`` only where nothing is at ``dst``, in one step: True when done,
    FileExistsError when something is there, False where the system offers no such rename."""
    err = _renameat2_call(src, dst, _RENAME_NOREPLACE)
    if err is None or err == 0:
        return err == 0
    if err == errno.EEXIST:
        raise FileExistsError(err, os.strerror(err), str(dst))
    raise OSError(err, os.strerror(err), str(src), None, str(dst))


#: renameat2's flag: swap the two names in one step
_RENAME_EXCHANGE = 2


def _rename_exchange(a: Path, b: Path) -> bool:
    """Swap what is at ``a`` and at ``b`` in one step: True when done, False where the system (or
    the file system) offers no such rename."""
    err = _renameat2_call(a, b, _RENAME_EXCHANGE)
    if err is None or err == 0:
        return err == 0
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _publish(tmp: Path, path: Path, folder=False) -> None:
    """Rename ``tmp`` to ``path`` only where nothing is there, else :class:`OutputAppearedError`
    (``tmp`` left for the caller to remove).

    Why: the output was checked free at the start only, and the final ``os.replace`` replaced
    whatever had appeared since: two `correct` runs to one new name, neither with --overwrite,
    both said done and one result was lost; a folder made at `process`'s output name during the
    run was renamed aside and deleted. renameat2(RENAME_NOREPLACE) takes the name only if free;
    without it, a file is hard-linked into place (link fails on an existing name) and a folder
    renamed (which fails onto a file or a folder holding anything). An empty folder holds
    nothing to lose and gives way, as it did at the start; only with neither renameat2 nor hard
    links (FAT) is a file's name looked at just before an ordinary rename."""
    try:
        try:
            done = _rename_noreplace(tmp, path)
        except FileExistsError:
            if not (folder and _remove_empty_folder(path) and _rename_noreplace(tmp, path)):
                raise
            done = True
        if done:
            return
        if folder:
            os.rename(tmp, path)
            return
        try:
            os.link(tmp, path, follow_symlinks=False)
        except FileExistsError:
            raise
        except OSError as exc:
            if exc.errno not in _UNSUPPORTED | {errno.EMLINK}:
                raise
            if os.path.lexists(path):
                raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(path)) from None
            os.rename(tmp, path)
            return
        os.unlink(tmp)
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR, errno.EISDIR):
            raise OutputAppearedError(path) from None
        raise


def _remove_empty_folder(path: Path) -> bool:
    """Remove ``path`` if it is an empty folder (rmdir refuses one that holds anything, at once)."""
    if path.is_symlink() or not path.is_dir():
        return False
    try:
        path.rmdir()
    except OSError:
        return False
    return True


@contextlib.contextmanager
def atomic_path(path, *, overwrite=False, inputs=(), size_hint=None):
    """Yield a temporary name beside ``path``; on success rename it to ``path``, else remove it.

    >>> import os, tempfile
    >>> from radiokit.io import atomic_path
    >>> out = os.path.join(tempfile.mkdtemp(), "a.txt")
    >>> with atomic_path(out) as tmp:
    ...     _ = tmp.write_text("complete")
    >>> open(out).read()
    'complete'

    The checks of :func:`check_output` run first, and with ``size_hint`` (bytes) the free space. A full disk (``ENOSPC``/``EDQUOT``) becomes a
    :class:`DiskFullError` that says so and that nothing was written.
    """
    path = check_output(path, overwrite=overwrite, inputs=inputs)
    if size_hint:
        check_free_space(path, size_hint)
    made = missing_folders(path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(path)
    tmp = _temporary_name(path)
    try:
        yield tmp
        if not (tmp.exists() or tmp.is_symlink()):
            raise OutputError(path, "the writer produced no file")
        settle()  # a stop lost while it was written, its delivery not run yet: not renamed into place
        _fsync(tmp)  # the bytes are on disk before the name is: a power cut leaves old or new
        if overwrite:
            if os.path.lexists(path):  # what is there now, perhaps made during the run: is it replaceable?
                _check_output(path, overwrite, inputs, False)
            _keep_mode(tmp, path)
            os.replace(tmp, path)
        else:
            _publish(tmp, path)
        _fsync(path.parent)
    except BaseException as exc:
        too_large = _is_too_large(exc, tmp)  # before the temporary, whose size may tell, is removed
        _remove(tmp)
        remove_empty_folders(made)
        if too_large:
            raise FileTooLargeError(path, f" ({file_size_limit(path.parent)} bytes)") from exc
        if is_disk_full(exc):
            raise DiskFullError(path) from exc
        _raise_unwritable(exc, tmp, path)
        raise


def remove_replaced(path, tmp, *, overwrite=False, inputs=(), then=()) -> None:
    """Remove ``path`` now, ahead of the rename of ``tmp`` onto it, whose mode it gives ``tmp``
    first (as :func:`atomic_path` does when it replaces it). What is there is checked first as
    that rename checks it (:func:`check_output`: ``overwrite``, ``inputs``), and so are ``then``,
    the outputs renamed between this removal and that rename: a refusal removes nothing.

    Why: two outputs of one run renamed one after the other (a field and its figure) cannot be
    renamed as one; a kill -9 between the renames, which no handler sees, left the new first
    beside the previous run's second. With the second removed before the first is renamed, a
    kill leaves one run's outputs, or the first without the second, never two runs' mixed. The
    checks (s49rv): unchecked, whatever had appeared at the name during the run was removed, a
    folder with all it held, --overwrite or not; and a refused first output cost the previous
    second for nothing."""
    path = Path(path)
    for other in (*then, path):
        if os.path.lexists(other):  # perhaps made during the run: is it replaceable?
            if not overwrite:  # (checked free at the start)
                raise OutputAppearedError(Path(other))
            _check_output(Path(other), overwrite, inputs, False)
    if os.path.lexists(path):
        _keep_mode(Path(tmp), path)
        _remove(path)
        _fsync(path.parent)


def missing_folders(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist yet, deepest first: what making it
    creates, and what a failed run removes again (:func:`remove_empty_folders`)."""
    out = []
    folder = Path(os.path.abspath(folder))
    while not folder.exists() and folder.parent != folder:
        out.append(folder)
        folder = folder.parent
    return out


def remove_empty_folders(folders) -> None:
    """Remove each of ``folders`` (deepest first) that is empty. Why: a run that failed left the
    output's parent folders it had made (``-o new/results`` left ``new/``), empty; one another
    run has written into stays."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty, or gone: leave it
            return


def _raise_unwritable(exc, tmp: Path, path: Path) -> None:
    """An OSError about the temporary (a read-only folder or filesystem) is one about ``path``:
    say so of the output asked for, not of a hidden name the user never gave (or libhdf5's flags)."""
    if isinstance(exc, OSError) and not isinstance(exc, OutputError) and exc.errno:
        if str(tmp) in f"{exc.filename} {exc}":
            raise OutputError(path, f"cannot be written: {os.strerror(exc.errno)}", exc.errno) from exc


@contextlib.contextmanager
def atomic_h5(path, *, overwrite=False, inputs=()):
    """Yield a new HDF5 file built in memory; on success write it out with :func:`atomic_path`.

    For outputs small enough to hold in memory (results, fields, calibrations): the bytes reach
    the disk through one ordinary write, so a full disk is a clean :class:`DiskFullError`.
    """
    import h5py

    check_output(path, overwrite=overwrite, inputs=inputs)
    with h5py.File(f"{path}-in-memory", "w", driver="core", backing_store=False) as h5:
        yield h5
        h5.flush()
        image = h5.id.get_file_image()
    with atomic_path(path, overwrite=overwrite, inputs=inputs, size_hint=len(image)) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(image)


@contextlib.contextmanager
def atomic_dir(path, *, overwrite=False, inputs=(), made_by="process"):
    """Yield a temporary sibling folder; on success swap it in for ``path``, else remove it.

    The previous folder (only replaced with ``overwrite``, and only if ``radiokit made_by`` made
    it: :func:`check_output`; the new one's marker names that command) is
    swapped with the new one in one step (:func:`_exchange_in`), then removed: at every instant
    ``path`` is the previous complete output or the new one. Where the system cannot swap, it is
    renamed aside and the new one renamed into place: ``path`` is absent in between, and the next
    run to it puts a previous folder a kill left aside back.
    """
    path = check_output(path, overwrite=overwrite, inputs=inputs, folder=True, made_by=made_by)
    strangers = _strangers(path) if (path / RESULTS_MARKER).exists() else []
    if strangers:
        raise OutputError(
            path,
            f"holds {len(strangers)} file(s) radiokit did not write there ({strangers[0]}, ...); "
            "it is never replaced: move them or choose a new folder",
        )
    made = missing_folders(path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(path, folder=True)
    tmp = _temporary_name(path, folder=True)
    try:
        tmp.mkdir()
        yield tmp
        (tmp / RESULTS_MARKER).write_text(
            f"{folder_marker(made_by)} Files:\n" + "".join(f"{name}\n" for name in sorted(_files(tmp)))
        )
        settle()  # a stop lost while it was written, its delivery not run yet: not swapped in
        if path.is_dir() and not path.is_symlink():
            _keep_mode(tmp, path)
        if overwrite:
            _swap_in(tmp, path, inputs, made_by)
        else:
            _publish(tmp, path, folder=True)
    except BaseException as exc:
        too_large = _is_too_large(exc, tmp)  # before the temporary, whose size may tell, is removed
        _remove(tmp)
        remove_empty_folders(made)
        if too_large:  # the file inside, named in the folder asked for, and the limit if known
            raise _too_large_in(exc, tmp, path) from exc
        if is_disk_full(exc):
            raise DiskFullError(path) from exc
        _raise_unwritable(exc, tmp, path)
        raise


def _strangers(folder: Path) -> list[str]:
    """The files under ``folder`` radiokit did not write there: those its marker does not list
    (all of them where it has none)."""
    listed = _manifest(folder) if (folder / RESULTS_MARKER).is_file() else set()
    return sorted(_files(folder) - listed)


def _swap_in(tmp: Path, path: Path, inputs, made_by: str) -> None:
    """Put the folder ``tmp`` at ``path`` in place of the results folder there (``overwrite``).

    What is at ``path`` is looked at again now, not only at the start: a file the user put into
    the old folder during the run was deleted with it. The old folder is renamed aside first and
    looked into there, where nothing more can be added under its name; holding a file radiokit
    did not write, it is put back and the run's results discarded."""
    if not os.path.lexists(path) or _remove_empty_folder(path):
        _publish(tmp, path, folder=True)
        return
    _check_output(path, True, inputs, made_by)  # a folder, radiokit's, of this command, writable
    if _exchange_in(tmp, path):
        return
    old = _temporary_name(path, folder=True, kind="old")
    os.rename(path, old)
    try:
        _replace_aside(tmp, path, old)
    except BaseException:
        # Ctrl-C (or any failure) while the previous folder is aside: put back, else the
        # output's name was left missing and the results only in a hidden folder
        if os.path.lexists(old) and not os.path.lexists(path):
            with contextlib.suppress(OSError):
                _publish(old, path, folder=True)
        raise
    # renamed to a temporary's name before its removal: a removal cut short leaves a `tmp`
    # leftover, which the next run removes, not an `old` one taken for the user's results
    gone = _temporary_name(path, folder=True)
    try:
        os.rename(old, gone)
    except OSError:
        gone = old
    shutil.rmtree(gone, ignore_errors=True)


def _exchange_in(tmp: Path, path: Path) -> bool:
    """Swap the new folder ``tmp`` and the previous one at ``path`` in one step
    (renameat2(RENAME_EXCHANGE)), then remove the previous one, now at ``tmp``'s name: True when
    done; False where the system offers no such rename, or the previous folder already holds a
    file radiokit did not write (the rename-aside route, which refuses it, is taken then).

    Why: renamed aside first and the new one renamed in after, ``path`` was missing in between (the
    look for files added during the run lies there too): a kill landing then left the name missing
    and the previous results in a hidden folder until the next run put them back (seen in the
    suite, session 47). Swapped, ``path`` is at every instant the previous or the new complete
    output. A file added to the previous folder during the run (looked for again once it is
    swapped out, where nothing more is added under its name) swaps it back, and the run's results
    are discarded, as on the rename-aside route. Stops are held over the swap and the look: a
    stop between them would have deleted the previous folder as the run's temporary."""
    if _strangers(path):
        return False
    with held(signal.SIGINT, signal.SIGTERM):
        if not _rename_exchange(tmp, path):
            return False
        try:
            strangers = _strangers(tmp)
        except BaseException:
            _rename_exchange(tmp, path)
            raise
        if strangers:
            _rename_exchange(tmp, path)
            raise OutputError(
                path,
                f"holds {len(strangers)} file(s) radiokit did not write there ({strangers[0]}, ...), added during "
                f"the run; it was not replaced and this run's results were discarded: move them and run again, "
                "or choose a new folder",
            )
    # the previous folder lies at a temporary's name: a removal cut short leaves a `tmp` leftover,
    # which the next run removes (the new output is in place), as after the rename-aside route
    shutil.rmtree(tmp, ignore_errors=True)
    return True


def _replace_aside(tmp: Path, path: Path, old: Path) -> None:
    """Put ``tmp`` at ``path`` once the previous folder is renamed aside to ``old``, unless
    that holds files added during the run (then it goes back)."""
    strangers = _strangers(old)
    if strangers:
        try:
            _publish(old, path, folder=True)
            kept = ""
        except OutputError:  # something took the name in between: the old folder stays aside
            kept = f"; the previous folder is kept in {shown(old)}"
        raise OutputError(
            path,
            f"holds {len(strangers)} file(s) radiokit did not write there ({strangers[0]}, ...), added during "
            f"the run; it was not replaced and this run's results were discarded{kept}: move them and run again, "
            "or choose a new folder",
        )
    try:
        _publish(tmp, path, folder=True)
    except OutputError:
        raise OutputError(
            path,
            f"appeared during the run (another run or program made it meanwhile); it was not replaced and this "
            f"run's results were discarded; the previous folder is kept in {shown(old)}",
            errno.EEXIST,
        ) from None
