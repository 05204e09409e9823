"""The memory budget readers check declared sizes against before allocating anything.

A file's header is a promise, not a fact: a 9 KB HDF5 file can declare (10, 100000, 100000)
frames and a small zlib TIFF a 60000 x 60000 page. Every reader multiplies what is declared
out and refuses, with a message naming the file, anything beyond the budget, before the
allocation that would exhaust the machine.
"""

from __future__ import annotations

import os
import re

from radiokit.errors import FormatError

__all__ = ["memory_budget", "parse_size", "check_budget", "BUDGET_ENV"]

#: environment variable holding the budget, e.g. "2GiB", "500M", "1e9"
BUDGET_ENV = "RADIOKIT_MEMORY_BUDGET"
#: default budget: this fraction of the machine's available physical memory
DEFAULT_FRACTION = 0.5
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


def _available_bytes() -> int:
    """Available physical memory, or the process's address-space limit if that is lower."""
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not POSIX: no better figure than a modest one
        avail = 4 * 2**30
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            avail = min(avail, soft)
    except (ImportError, ValueError, OSError):
        pass
    return avail


def memory_budget(budget=None) -> int:
    """The budget in bytes: ``budget`` if given (bytes or a size string), else the environment
    variable :data:`BUDGET_ENV`, else :data:`DEFAULT_FRACTION` of the available physical memory
    (or of the address-space limit, ``ulimit -v``, where that is lower)."""
    if budget is None:
        budget = os.environ.get(BUDGET_ENV) or None
    if budget is None:
        return int(_available_bytes() * DEFAULT_FRACTION)
    return parse_size(budget) if isinstance(budget, str) else int(budget)


def _human(n: int) -> str:
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
            f"{what} would need {_human(int(nbytes))}, over the memory budget of "
            f"{_human(limit)} (a corrupt header, or raise {BUDGET_ENV})",
        )
