"""The memory budget readers check declared sizes against before allocating anything.

A file's header is a promise, not a fact: a 9 KB HDF5 file can declare (10, 100000, 100000)
frames and a small zlib TIFF a 60000 x 60000 page. Every reader multiplies what is declared
out and refuses, with a message naming the file, anything beyond the budget, before the
allocation that would exhaust the machine.

The budget is a fraction of the machine, so on a large one it lets through what no frame file
holds: a 227 KB zstd TIFF declaring 60000 x 60000 decoded 7 GB within an 11.5 GB budget.
:func:`check_proportion` therefore also refuses compressed data that would decode to far more than
real frames do, unless the user gave a budget of their own.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from radiokit.errors import FormatError

__all__ = ["memory_budget", "parse_size", "check_budget", "check_proportion", "BUDGET_ENV"]

#: environment variable holding the budget, e.g. "2GiB", "500M", "1e9"
BUDGET_ENV = "RADIOKIT_MEMORY_BUDGET"
#: default budget: this fraction of the machine's available physical memory
DEFAULT_FRACTION = 0.5
# What compressed frames expand to, measured on 2240 x 2240 uint16 frames (deflate, deflate with
# predictor 2, zstd 3 and 19, LZW, LZMA): darks of 1-2 counts' noise 2.8-6.9:1, a shaded flat
# 1.2-3.0:1, the vendor's ITEX files 1.4-5.3:1 and its photon-counting one 12-19:1; a saturated frame
# with 1 % of its pixels below 77-101:1. Only a constant frame goes beyond: 650-1180:1 under
# deflate and LZW (deflate's own bound is about 1032:1), 6300:1 (LZMA) to 31000:1 (zstd of zeros).
# Sparse frames go beyond too (review s36r3; 2240 and 4000 square): 0.2 % of pixels hit 269-385:1,
# 1 % 78-113:1. So past BOMB_RATIO the data is nearly constant or sparse, and real only at an
# experiment's size: 200 constant darks are 1.9 GiB. What is judged is what one read decodes: a
# frame streamed (open_frames) against its own strips or chunks, read()'s frames against theirs.
# Like Pillow's pixel limit per image, the rule is a size beyond which such a ratio is refused:
# a frame above BOMB_FRAME_BYTES (a 23000 x 23000 uint16 one; every decode allocates at least a
# frame) or a read above BOMB_FILE_BYTES (read() allocates all its frames).
# An explicit budget lifts it: the user then says how much memory the read may take.
# (benchmarks/bench_compression_ratios.py reproduces the measurements; benchmarks/README.md)
#: decoded : stored beyond which compressed frame data is nearly constant (measurements above)
BOMB_RATIO = 200
#: decoded bytes of one frame beyond which data compressed past BOMB_RATIO is refused
BOMB_FRAME_BYTES = 2**30
#: decoded bytes of a file's frames beyond which data compressed past BOMB_RATIO is refused
BOMB_FILE_BYTES = 4 * 2**30
_UNITS = {
    "": 1,
    "b": 1,
    "k": 10**3,
    "kb": 10**3,
    "kib": 2**10,
    "m": 10**6,
    "mb": 10**6,
    "mib": 2**20,
    "g": 10**9,
    "gb": 10**9,
    "gib": 2**30,
    "t": 10**12,
    "tb": 10**12,
    "tib": 2**40,
}
_SIZE = re.compile(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*\Z")


def parse_size(text: str) -> int:
    """Bytes in ``"2GiB"``, ``"500M"`` (decimal), ``"1.5e9"``; ValueError naming the text otherwise."""
    m = _SIZE.match(str(text))
    unit = m.group(2).lower() if m else None
    if not m or unit not in _UNITS:
        raise ValueError(f"{BUDGET_ENV}={text!r}: expected a size such as 2GiB, 500M or 1e9 bytes")
    value = float(m.group(1)) * _UNITS[unit]
    if not value >= 1:
        raise ValueError(f"{BUDGET_ENV}={text!r}: the budget must be at least one byte")
    return int(value)


_MEMINFO = Path("/proc/meminfo")
_SELF_CGROUP = Path("/proc/self/cgroup")
_CGROUP_ROOT = Path("/sys/fs/cgroup")


def _meminfo_available() -> int | None:
    """Linux's MemAvailable (bytes): free pages plus the cache the kernel would drop for us; None
    where the kernel does not say (not Linux, or before 3.14)."""
    try:
        for line in _MEMINFO.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_stat(group: Path, keys: tuple[str, ...]) -> int:
    """The first of ``keys`` in ``group``'s memory.stat (bytes); 0 where none is there."""
    try:
        stat = dict(line.split() for line in (group / "memory.stat").read_text().splitlines() if len(line.split()) == 2)
    except (OSError, ValueError):
        return 0
    return next((int(stat[k]) for k in keys if k in stat and stat[k].isdigit()), 0)


def _cgroup_headroom() -> int | None:
    """What this process's cgroup may still take before its own or an ancestor's limit: v2's
    memory.max, v1's memory.limit_in_bytes, less what the group holds beyond its page cache
    (memory.current / usage_in_bytes count the cache, which the kernel drops first: a container
    that has read more frames than its limit sits at its limit); None without a limit. A
    container sees its own group at the mount's root, so where the path /proc/self/cgroup names is
    not there, the root's files are read."""
    try:
        lines = _SELF_CGROUP.read_text().splitlines()
    except OSError:
        return None
    found = []
    for line in lines:
        _, controllers, rel = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":
            base, files, cache = _CGROUP_ROOT, ("memory.max", "memory.current"), ("file",)
        elif "memory" in controllers.split(","):
            base = _CGROUP_ROOT / "memory"
            files, cache = ("memory.limit_in_bytes", "memory.usage_in_bytes"), ("total_cache", "cache")
        else:
            continue
        parts = [p for p in rel.strip().split("/") if p]
        if not (base.joinpath(*parts)).is_dir():
            parts = []
        for depth in range(len(parts), -1, -1):  # the group, then each ancestor: a job's or slice's limit
            group = base.joinpath(*parts[:depth])
            try:
                limit = (group / files[0]).read_text().strip()
                if limit == "max" or int(limit) >= 2**60:  # v1 writes "no limit" as a page-rounded 2^63
                    continue
                used = int((group / files[1]).read_text()) - _cgroup_stat(group, cache)
                found.append(max(0, int(limit) - max(0, used)))
            except (OSError, ValueError):
                continue
    return min(found) if found else None


def _physical_available() -> int:
    """Physical memory this process may use without swapping: MemAvailable where Linux says it
    (free pages alone read 1.7-5 GiB of 22.6 available on a 24 GB machine, run to run: the page
    cache of recently read frames counted as used), else the free pages; a cgroup's limit caps it."""
    avail = _meminfo_available()
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # not POSIX: no better figure than a modest one
            avail = 4 * 2**30
    headroom = _cgroup_headroom()
    return avail if headroom is None else min(avail, headroom)


def _available_bytes() -> int:
    """Available physical memory, or the process's address-space limit if that is lower."""
    avail = _physical_available()
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            avail = min(avail, soft)
    except (ImportError, ValueError, OSError):
        pass
    return avail


#: this process's share of its host's budget while it is a Dask worker of radiokit.pipeline
#: (None: all of it): the files its host's workers process at once hold the host's budget
#: between them, so each worker's reads are held to its share
_share: int | None = None


def set_share(nbytes: int | None) -> None:
    """Hold this process's budget (not one given to a call) to ``nbytes``; None lifts it."""
    global _share
    _share = None if nbytes is None else int(nbytes)


def memory_share() -> int | None:
    """This process's share as :func:`set_share` left it (None: no share), for a caller that puts
    it back afterwards."""
    return _share


def host_budget(budget=None) -> int:
    """The budget in bytes before any worker's share: ``budget`` if given (bytes or a size string),
    else the environment variable :data:`BUDGET_ENV`, else :data:`DEFAULT_FRACTION` of the available
    physical memory (or of the address-space limit, ``ulimit -v``, where that is lower)."""
    if budget is None:
        budget = os.environ.get(BUDGET_ENV) or None
    if budget is None:
        return int(_available_bytes() * DEFAULT_FRACTION)
    return parse_size(budget) if isinstance(budget, str) else int(budget)


def memory_budget(budget=None) -> int:
    """The budget in bytes: ``budget`` if given (bytes or a size string), else the environment
    variable :data:`BUDGET_ENV`, else :data:`DEFAULT_FRACTION` of the available physical memory
    (or of the address-space limit, ``ulimit -v``, where that is lower); in a Dask worker of
    ``radiokit.pipeline.process_many``, no more than the worker's share (:func:`set_share`)."""
    limit = host_budget(budget)
    return limit if budget is not None or _share is None else min(limit, _share)


def human_bytes(n: int) -> str:
    """``n`` bytes as the messages about memory write them: whole bytes below 1 KiB, else one
    decimal of the largest binary unit it reaches (up to TiB).

    >>> human_bytes(512), human_bytes(1536), human_bytes(3 * 2**30)
    ('512 bytes', '1.5 KiB', '3.0 GiB')
    """
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def check_budget(path, nbytes: int, what: str, budget=None) -> None:
    """Raise :class:`FormatError` if ``nbytes`` (what ``what`` would allocate) exceeds the budget."""
    limit = memory_budget(budget)
    if nbytes > limit:
        raise FormatError(
            path,
            f"{what} would need {human_bytes(int(nbytes))}, over the memory budget of "
            f"{human_bytes(limit)} (a corrupt header, or raise {BUDGET_ENV})",
        )


def explicit_budget(budget=None) -> bool:
    """Whether the user gave a budget: ``budget`` or the environment variable :data:`BUDGET_ENV`."""
    return budget is not None or bool(os.environ.get(BUDGET_ENV))


def _suggested(nbytes: int) -> str:
    """A budget a quarter above ``nbytes``, in whole MiB or GiB, to quote in a refusal."""
    unit, name = (2**30, "GiB") if nbytes >= 2**30 else (2**20, "MiB")
    return f"{-(-nbytes * 5 // 4 // unit) or 1}{name}"


def proportion_can_refuse(decoded: int, frame: int, budget=None) -> bool:
    """Whether :func:`check_proportion` could refuse ``decoded`` bytes (``frame`` of them at once)
    whatever they are stored in: else their stored bytes need not be counted (a dataset's chunks
    listed one by one)."""
    return not explicit_budget(budget) and (frame > BOMB_FRAME_BYTES or decoded > BOMB_FILE_BYTES)


def stored_extent(ranges) -> int:
    """The bytes the ``(offset, length)`` ``ranges`` cover, each byte once: TIFF pages (or HDF5
    chunks) may all point at one range, and 10 pages of 512 MiB sharing one 2.8 MB zstd strip,
    counted once a page, passed as 1:191 (review s36r3)."""
    total, end = 0, -1
    for offset, length in sorted((int(o), int(n)) for o, n in ranges if int(n) > 0):
        if offset + length > end:
            total += offset + length - max(offset, end)
            end = offset + length
    return total


def check_proportion(
    path, what: str, decoded: int, frame: int, stored: int, codec: str, budget=None, needs: int | None = None
) -> None:
    """Refuse compressed data out of all proportion to the bytes it is stored in, before decoding.

    ``decoded`` bytes (``frame`` of them the largest one decode allocates at once) from ``stored``
    bytes of ``codec`` data are refused when they expand more than :data:`BOMB_RATIO` and exceed
    :data:`BOMB_FRAME_BYTES` a frame or :data:`BOMB_FILE_BYTES` in all (the module's comment gives
    the measurements), unless the user gave a budget (:func:`explicit_budget`). Readers pass what
    one read decodes: a frame streamed, or every frame ``read()`` takes, and ``stored`` counting
    each stored byte once (:func:`stored_extent`). ``needs``: what reading it takes, where more
    than ``decoded`` (a deflated DICOM's inflate holds it two to three times), for the budget the
    refusal suggests.
    """
    if not stored or decoded <= BOMB_RATIO * stored or not proportion_can_refuse(decoded, frame, budget):
        return
    raise FormatError(
        path,
        f"{what} would decode to {human_bytes(decoded)} from {stored} bytes of {codec} data "
        f"(1:{decoded // stored}): past 1:{BOMB_RATIO} frames are nearly constant or sparse (noisy ones "
        "compress 1:1.2-1:19, with 1 % of pixels hit 1:78-1:113, with 0.2 % up to 1:385), and so much of "
        f"them is taken for a decompression bomb; to read it all the same, give the memory it may use: "
        f"{BUDGET_ENV}={_suggested(needs or decoded)} (read(..., budget=...))",
    )
