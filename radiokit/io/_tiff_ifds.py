"""A TIFF's IFD chain walked and charged against the memory budget before tifffile builds a page.

tifffile builds an object for every page, each tag of it another: a 30 MB file of 300,000 one-pixel
pages took 860 MB and 25 s to open, though no frame is larger than a pixel and no check refused it.
The chain is walked here first, reading each IFD's tag count only (no page object, no tag), and the
pages' cost is charged against :func:`radiokit.io._budget.memory_budget`, refused before the first
page is built.

The walk also ends a chain that loops: tifffile looks for a loop once only, at its 100th IFD, so a
chain leading back after more than 100 IFDs was followed until memory ran out (a 20 KB file).
"""

from __future__ import annotations

import mmap
import os
import struct

from radiokit.errors import FormatError
from radiokit.io._budget import BUDGET_ENV, human_bytes, memory_budget

__all__ = ["check_tiff_pages", "no_pages_why", "TIFF_BYTES_PER_PAGE", "TIFF_BYTES_PER_TAG"]

#: memory a TIFF page costs open, beyond its tags' (benchmarks/bench_tiff_pages.py: `radiokit info`'s
#: peak over 5,000 and 20,000 one-pixel pages of 8, 40 and 136 tags, 849 bytes a page and 227 a tag),
#: rounded up
TIFF_BYTES_PER_PAGE = 1000
#: memory each tag of a page costs open (tifffile's TiffTag), measured as above, rounded up
TIFF_BYTES_PER_TAG = 250
#: the most tags tifffile reads in one IFD: it ends the chain at an IFD declaring more
_MOST_TAGS = 4096
#: (tag count's format, its bytes, an entry's bytes, next offset's format, its bytes) per version
_LAYOUTS = {42: ("H", 2, 12, "I", 4), 43: ("Q", 8, 20, "Q", 8)}


def _first_ifd(m) -> tuple[str, tuple, int] | None:
    """Byte order, layout and first IFD offset from the header; None where tifffile is left to judge it."""
    order = {b"II": "<", b"MM": ">"}.get(bytes(m[:2]))
    if order is None or len(m) < 8:
        return None
    version = struct.unpack_from(order + "H", m, 2)[0]
    layout = _LAYOUTS.get(version)
    if layout is None or (version == 43 and len(m) < 16):
        return None
    return order, layout, struct.unpack_from(order + layout[3], m, 4 if version == 42 else 8)[0]


def check_tiff_pages(path, budget=None, spent=0, offsets: list | None = None) -> tuple[int, int]:
    """Refuse ``path``, a TIFF, when building its pages would take more than the memory budget
    (``budget``, else :func:`radiokit.io._budget.memory_budget`'s) less ``spent`` (the pages of
    the files of its set walked before it, open at once with it): each page
    :data:`TIFF_BYTES_PER_PAGE` and :data:`TIFF_BYTES_PER_TAG` a tag, counted down the IFD chain
    before tifffile builds any, the walk ending where the budget is spent; and refuse a chain that
    leads back to an IFD already walked. A chain that ends otherwise (an offset past the end, a
    torn IFD) ends the count, and the reader names it (tifffile stops there too).

    Returns the pages counted and ``spent`` with their cost added ((0, spent) where tifffile is
    left to judge the file); into ``offsets``, each counted page's IFD offset."""
    limit = memory_budget(budget)
    with open(path, "rb") as fh:
        try:
            m = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except (ValueError, OSError):  # empty, or not mappable: tifffile's own reading judges it
            return 0, spent
    with m:
        head = _first_ifd(m)
        if head is None:
            return 0, spent
        order, (count_fmt, count_size, entry_size, next_fmt, next_size), offset = head
        count_fmt, next_fmt, size = order + count_fmt, order + next_fmt, len(m)
        seen: dict[int, int] = {}  # offset -> page: at most the budget's pages, 0.1 KB each
        cost, tags = spent, 0
        while 0 < offset and offset + count_size <= size:
            if offset in seen:
                raise FormatError(
                    path,
                    f"TIFF IFD chain loops: the IFD after page {len(seen) - 1} is page {seen[offset]}'s again "
                    f"(offset {offset}): corrupt",
                )
            n_tags = struct.unpack_from(count_fmt, m, offset)[0]
            end = offset + count_size + n_tags * entry_size
            if n_tags > _MOST_TAGS or end + next_size > size:
                break
            seen[offset] = len(seen)
            tags += n_tags
            cost += TIFF_BYTES_PER_PAGE + TIFF_BYTES_PER_TAG * n_tags
            if cost > limit:
                alone = "alone" if not spent else f"with the {human_bytes(spent)} of its set's files before it"
                raise FormatError(
                    path,
                    f"TIFF of at least {len(seen)} pages ({tags / len(seen):.3g} tags each): open, its pages {alone} "
                    f"would take more than the memory budget of {human_bytes(limit)} ({TIFF_BYTES_PER_PAGE} bytes a "
                    f"page, {TIFF_BYTES_PER_TAG} a tag; a corrupt file, or raise {BUDGET_ENV})",
                )
            offset = struct.unpack_from(next_fmt, m, end)[0]
        if offsets is not None:
            offsets.extend(seen)
        return len(seen), cost


def no_pages_why(path) -> str:
    """Why a TIFF in which tifffile found no page holds none, from where its header points its
    first IFD: nowhere (offset 0), past the end (a file cut short), or to an IFD tifffile could
    not read. Why: "holds no image" alone did not tell a truncated file from an empty one."""
    with open(path, "rb") as fh:
        head, size = fh.read(16), os.fstat(fh.fileno()).st_size
    first = _first_ifd(head)
    if first is None:
        return "TIFF holds no image"
    offset = first[2]
    if offset == 0:
        return "TIFF holds no image: its header puts its first IFD at offset 0 (none written)"
    if offset >= size:
        return f"TIFF holds no image: its first IFD (offset {offset}) lies beyond the end of the {size}-byte file: truncated or corrupt"
    return f"TIFF holds no image: its first IFD (offset {offset}) cannot be read: corrupt"
