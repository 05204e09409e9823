"""Multi-file OME-TIFF: which of an OME-XML image's planes lie in files other than its own.

Bio-Formats and Micro-Manager split a long image over several TIFF files; each carries the
OME-XML, whose TiffData elements name (by UUID and FileName) the file holding each run of planes.
Read alone, one file gave its own planes only, silently: half the frames of a two-file set.
"""

from __future__ import annotations

import glob
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import NamedTuple

from radiokit import _json as strict_json
from radiokit._names import shown
from radiokit.errors import FormatError

__all__ = [
    "TiffData",
    "tiffdata",
    "ome_root_uuid",
    "external_planes",
    "describe_planes",
    "count_planes",
    "ome_pages",
    "binary_only",
    "mmstack_split",
    "check_mmstack_slots",
    "mmstack_set_files",
    "not_there",
]


def _local(element) -> str:
    return element.tag.rpartition("}")[2]


class TiffData(NamedTuple):
    """One TiffData element: the run of planes ``first``.. (numbered within image ``image`` as
    OME's DimensionOrder numbers them) held in ``file`` (None: this file) from its page ``ifd``
    on; ``count`` None where no PlaneCount says how many (all that file's pages from ``ifd`` on).
    ``uuid``: the UUID element's text, by which tifffile finds the file."""

    image: int
    file: str | None
    uuid: str | None
    first: int
    count: int | None
    ifd: int


def tiffdata(xml: str | None, filename: str) -> tuple[str | None, list[int], list[TiffData]]:
    """This file's UUID (the OME root's, else the first UUID naming ``filename``, as tifffile
    takes it), the planes of each of the OME-XML's images, and its TiffData elements. Numbers,
    not lists of planes: a corrupt PlaneCount of 10**9 is a number here, not gigabytes of them.

    A TiffData names this file by that UUID, or, where there is none, by ``filename`` (case
    aside), as tifffile and Bio-Formats judge it; one without a UUID is this file's. Where the
    root has no UUID and every TiffData names one file, that file is this one renamed (a set has
    two files at least; tifffile then reads none of its planes, and radiokit read them all
    before). ``(None, [], [])`` for XML that does not parse."""
    try:
        root = ET.fromstring(xml or "")
    except (ET.ParseError, ValueError):
        return None, [], []
    own = (root.get("UUID") or "").strip() or None
    uuids = [el for el in root.iter() if _local(el) == "UUID" and el is not root]
    datas = [el for el in root.iter() if _local(el) == "TiffData"]
    if not own and all(any(_local(el) == "UUID" for el in data) for data in datas):
        # (a TiffData without a UUID is this file's: then the one file named is another)
        named = {el.get("FileName", "").lower() for el in uuids}
        filename = named.pop() if len(named) == 1 else filename
    if not own:
        own = next(
            (
                el.text.strip()
                for el in uuids
                if el.get("FileName", "").lower() == filename.lower() and (el.text or "").strip()
            ),
            None,
        )
    totals, found = [], []
    for pixels in (el for el in root.iter() if _local(el) == "Pixels"):
        axes = "".join(reversed(pixels.get("DimensionOrder", "XYCZT")))[:-2]
        try:
            shape = [int(pixels.get(f"Size{axis}", 1)) for axis in axes]
        except ValueError:
            continue
        totals.append(math.prod(shape))
        for data in (el for el in pixels if _local(el) == "TiffData"):
            uuid = next((el for el in data if _local(el) == "UUID"), None)
            text = None if uuid is None else (uuid.text or "").strip() or None
            name = None if uuid is None else uuid.get("FileName") or f"the file of UUID {text}"
            if uuid is None or (own and text == own) or (not own and name.lower() == filename.lower()):
                name = None
            try:
                first = sum(int(data.get(f"First{axis}", 0)) * math.prod(shape[k + 1 :]) for k, axis in enumerate(axes))
                count = int(data.get("PlaneCount", data.get("NumPlanes", 1 if "IFD" in data.attrib else 0)))
                ifd = int(data.get("IFD", 0))
            except ValueError:
                first, count, ifd = 0, 0, 0
            found.append(TiffData(len(totals) - 1, name, text, first, count or None, ifd))
    return own, totals, found


def external_planes(xml: str | None, filename: str) -> tuple[int, dict[str, list[range] | None]]:
    """The planes of the OME-XML's images and, for each other file its TiffData names
    (:func:`tiffdata`), the runs of planes it holds; None where no PlaneCount says how many."""
    _, totals, found = tiffdata(xml, filename)
    runs: dict[str, list[range] | None] = {}
    for data in found:
        if data.file is None:
            continue
        held = runs.setdefault(data.file, [])
        if held is not None and data.count is not None and data.count > 0:
            held.append(range(data.first, data.first + data.count))
        else:
            runs[data.file] = None
    return sum(totals), runs


def ome_root_uuid(xml: str | None) -> str | None:
    """The UUID on an OME-XML's root (the file's own); None where it has none or does not parse."""
    try:
        root = ET.fromstring(xml or "")
    except (ET.ParseError, ValueError):
        return None
    return (root.get("UUID") or "").strip() or None


def describe_planes(runs: list[range] | None) -> str:
    """The runs of planes :func:`external_planes` gives as a person reads them: "planes 2-3",
    "plane 5", "planes 0-1, 4"."""
    if not runs:
        return "planes not counted"
    merged: list[list[int]] = []
    for run in sorted(runs, key=lambda r: r.start):
        if merged and run.start <= merged[-1][1] + 1:
            merged[-1][1] = max(merged[-1][1], run.stop - 1)
        else:
            merged.append([run.start, run.stop - 1])
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in merged[:4]) + (", ..." if len(merged) > 4 else "")
    return f"plane{'s' if len(merged) > 1 or merged[0][0] != merged[0][1] else ''} {text}"


def count_planes(runs: list[range] | None) -> int | None:
    """How many planes the runs hold (overlaps once); None when not counted."""
    if not runs:
        return None
    total, end = 0, None
    for run in sorted(runs, key=lambda r: r.start):
        start = run.start if end is None else max(run.start, end)
        total += max(run.stop - start, 0)
        end = run.stop if end is None else max(end, run.stop)
    return total


def ome_pages(xml: str | None) -> int | None:
    """The pages the OME-XML's images fill: each image's SizeZ x SizeC x SizeT planes, a page
    holding SamplesPerPixel of its channels (an RGB image is one page, not three); None for XML
    that does not parse or has no image (a BinaryOnly file's)."""
    try:
        root = ET.fromstring(xml or "")
    except (ET.ParseError, ValueError):
        return None
    total = None
    for pixels in (el for el in root.iter() if _local(el) == "Pixels"):
        channel = next((el for el in pixels if _local(el) == "Channel"), None)
        try:
            z, c, t = (int(pixels.get(f"Size{axis}", 1)) for axis in "ZCT")
            samples = max(int(channel.get("SamplesPerPixel", 1)) if channel is not None else 1, 1)
        except ValueError:
            return None
        total = (total or 0) + z * t * max(c // samples, 1)
    return total


def binary_only(xml: str | None) -> str | None:
    """The MetadataFile a "BinaryOnly" OME-XML names (the companion file, or the set's first
    file, holding the description this file's pages lack); None for any other XML."""
    try:
        root = ET.fromstring(xml or "")
    except (ET.ParseError, ValueError):
        return None
    found = next((el for el in root if _local(el) == "BinaryOnly"), None)
    return None if found is None else found.get("MetadataFile") or "a file it does not name"


def mmstack_split(tif, path=None, notes: list | None = None) -> list | None:
    """The planes of this file's stage positions in a Micro-Manager stack, in its order, where
    tifffile's series of it spans other files (None where it is no such stack): a TiffFrame
    each, in the file it lies in, or None where no file holds it; all in this file where it
    holds its positions whole.

    Micro-Manager splits a stack at 4 GB into <name>_MMStack_Pos0.ome.tif, ..._Pos0_1.ome.tif,
    each with an index map of its planes; tifffile finds the others by that name, whatever the
    OME-XML says (or without one), from any file of the set. Read alone, the file given gave its
    own planes, with nothing said where the OME-XML names no file. ``path``: the file as the
    user named it, for messages; ``notes``: where what :func:`check_mmstack_slots` says of an
    acquisition stopped early is put, for the reader to warn."""
    _check_own_index_map(tif, path)
    if not tif.is_mmstack:
        return None
    note = check_mmstack_slots(tif, path)
    if note is not None and notes is not None:
        notes.append(note)
    try:
        series = tif.series
    except Exception:  # (tifffile fails on a corrupt file in many ways) the read itself says so
        return None
    if len(series) != 1 or series[0].kind != "mmstack":
        return None
    pages = list(series[0].pages)
    axes, shape = series[0].get_axes(False), series[0].get_shape(False)
    if not series[0].is_multifile:
        _check_no_plane_between(pages, axes, shape, len(series[0].keyframe.shape), path or tif.filehandle.path)
        return None
    if "R" in axes:
        # Micro-Manager writes each stage position to files of its own (<name>_MMStack_Pos1...)
        # and tifffile's series takes in every position beside it: read as one stack, the
        # fields of view came interleaved as frames. This file's positions are its own stack.
        r = axes.index("R")
        stride, size = math.prod(shape[r + 1 : len(shape) - len(series[0].keyframe.shape)]), shape[r]
        own = {k // stride % size for k, page in enumerate(pages) if page is not None and page.parent is tif}
        pages = [page for k, page in enumerate(pages) if k // stride % size in own]
    if note is not None:
        # stopped early between positions (or slices) of its last time point: this file's last
        # planes were never written, not lost
        while pages and pages[-1] is None:
            pages.pop()
    return pages


_SUMMARY = "its Micro-Manager summary"  # as its refusals name it


def micromanager_metadata(tif, path=None, strict=True) -> dict:
    """``tif.micromanager_metadata`` (``{}`` where none), its index map's declared size checked
    against the file's bytes first (:func:`_read_index_map`). Why: tifffile reads the declared
    entries in one read, 8 GB asked of a 5 KB file declaring 4*10**8 of them: where memory is not
    overcommitted that read fails, and the file was "cannot be read as tiff: " with nothing after."""
    name = tif.filehandle.path
    shown_as = Path(path or name or "")
    if name and os.path.isfile(name):
        summary_bytes = _check_block_lengths(name, path)
        index, problem = _read_index_map(name)
        if index is None and problem.startswith("declares") and not strict:  # its summary alone
            return {"Summary": _read_summary(name, path), "IndexMap": None}
        if summary_bytes > strict_json.MAX_CHARS:  # past radiokit's length, refused as below (its characters)
            _read_summary(name, path)
        if index is None and problem.startswith("declares"):
            raise FormatError(
                shown_as,
                f"its Micro-Manager index map {problem}: the acquisition likely crashed before the file was closed "
                "(Micro-Manager fills the index map then), or the file is corrupt: refused",
            )
    # its summary steers which planes are frames, in what order: past radiokit's depth
    # (radiokit._json), refused; tifffile's own json.loads of one past Python's reach ended
    # "cannot be read as tiff: maximum recursion depth exceeded while decoding a JSON array" (s52)
    deep = strict_json.TooDeep(f"{_SUMMARY} nests deeper than {strict_json.MAX_DEPTH} levels")
    try:
        meta = tif.micromanager_metadata or {}
        if strict_json.too_deep(meta.get("Summary")):
            raise deep
    except (RecursionError, strict_json.TooDeep):
        if not strict:
            return {}
        raise FormatError(shown_as, f"{deep}, past any JSON radiokit reads: not read") from None
    return meta


def _check_block_lengths(name: str, path=None) -> int:
    """Refuse a Micro-Manager file whose header gives its summary, display settings or comments a
    length beyond the file's bytes: tifffile reads each in one read of that length (review
    s40rr4: 4 GB asked of a 5 KB file, and where memory is not overcommitted the read failed).
    Returns the summary's length in bytes (0 where the header gives none)."""
    import struct

    with open(name, "rb") as fh:
        head = fh.read(40)
        order = {b"II": "<", b"MM": ">"}.get(head[:2])
        if order is None or len(head) < 40:
            return 0
        _, _, display_magic, display_at, comments_magic, comments_at, summary_magic, summary_length = (
            struct.unpack_from(order + "8I", head, 8)
        )
        size = os.fstat(fh.fileno()).st_size
        blocks = [("summary", summary_length)] if summary_magic == 2355492 else []
        for what, magic, at, inner in (
            ("display settings", display_magic, display_at, (483765892, 347834724)),
            ("comments", comments_magic, comments_at, (99384722, 84720485)),
        ):
            if magic == inner[0] and at + 8 <= size:  # the block's own header, then its length
                fh.seek(at)
                header, length = struct.unpack(order + "II", fh.read(8))
                if header == inner[1]:
                    blocks.append((what, length))
    for what, length in blocks:
        if length > size:
            raise FormatError(
                Path(path or name),
                f"its Micro-Manager header gives its {what} {length} bytes, more than the file's {size}: corrupt",
            )
    return summary_length if summary_magic == 2355492 else 0


def _read_summary(name: str, path=None) -> dict | None:
    """The Micro-Manager summary of the file ``name`` (its JSON at byte 40, as tifffile reads it),
    without its index map; None where it has none that reads. Past radiokit's depth or length
    (radiokit._json), refused naming the file (``path`` where given), as
    :func:`micromanager_metadata` refuses one too deep: a summary steers which planes are frames
    and which files are the set's (review of s52: one past the length was silently none)."""
    import struct

    try:
        with open(name, "rb") as fh:
            head = fh.read(40)
            order = {b"II": "<", b"MM": ">"}.get(head[:2])
            magic, length = struct.unpack_from(order + "II", head, 32)
            if magic != 2355492 or length > os.fstat(fh.fileno()).st_size:
                return None
            summary = strict_json.loads_record(fh.read(length).decode("utf-8", "replace"), _SUMMARY)
    except strict_json.Refused as exc:
        raise FormatError(Path(path or name), f"{exc}: not read") from None
    except (OSError, ValueError, TypeError, struct.error):
        return None
    return summary if isinstance(summary, dict) else None


def _check_own_index_map(tif, path=None) -> None:
    """Refuse a file of a Micro-Manager set whose own index map is missing or empty, named (as
    :func:`_index_span` refuses one of its other files). Why: tifffile then takes it for no
    Micro-Manager file and it read as a plain TIFF of its own pages, the set's other files
    left out, silently. A file alone (no other file of its name) still reads its pages so."""
    meta = micromanager_metadata(tif, path)
    summary, index = meta.get("Summary"), meta.get("IndexMap")
    if not isinstance(summary, dict) or "MicroManagerVersion" not in summary or (index is not None and len(index)):
        return
    found = _mmstack_files(tif, summary, path)
    if found is not None and len(found) > 1:
        _index_span(found, [0, 0, 0, 0], tif.filehandle.path, path)


def _check_no_plane_between(pages: list, axes: str, shape: tuple, plane_dims: int, path) -> None:
    """Refuse a Micro-Manager file read alone whose index map leaves a plane out before the last
    it records (tifffile's series of it: None there). Why: the planes after the gap were read
    as the frames straight after those before it, with the warning that the acquisition was
    stopped early where the summary planned more; a set with the same gap is refused. Planes
    left out after the last are what an acquisition stopped early leaves, and are no gap."""
    import numpy  # late: only a Micro-Manager file needs it here

    last = max((k for k, page in enumerate(pages) if page is not None), default=-1)
    gaps = [k for k in range(last) if pages[k] is None]
    if not gaps:
        return
    dims = shape[: len(shape) - plane_dims]
    at = numpy.unravel_index(gaps[0], dims)
    where = ", ".join(f"{axis} {int(i)}" for axis, i, n in zip(axes, at, dims) if n > 1)
    raise FormatError(
        Path(path),
        f"its Micro-Manager index map records {last + 1 - len(gaps)} planes up to the last but none at "
        f"{where}{f' (and {len(gaps) - 1} more)' if len(gaps) > 1 else ''}: a plane missing among those "
        "written, not an acquisition stopped early: corrupt",
    )


#: the bytes a Micro-Manager file holds for each of its planes at the least: its index map entry
_MM_ENTRY_BYTES = 20
#: what tifffile's series of a Micro-Manager stack takes a plane it declares, written or not
#: (measured: 4*10**8 declared planes, 7.8 GB)
_MM_SLOT_BYTES = 20
#: the summary's count of each of the index map's first four columns, and its axis as tifffile names it
_MM_COUNTS = (("Channels", "C"), ("Slices", "Z"), ("Frames", "T"), ("Positions", "R"))


def not_there(path) -> str:
    """Why the file ``path`` a set names is not there, for messages: "NAME is missing", or, where
    NAME is a symbolic link to nothing, that. Why: "missing" (or "No such file or directory")
    of a name `ls` lists sent the user looking for a file that is there."""
    path = Path(path)
    if not path.is_symlink():
        return f"{shown(path.name)} is missing"
    try:
        target = os.readlink(path)
    except OSError:  # (gone between the two looks) as good as missing
        return f"{shown(path.name)} is missing"
    return f"{shown(path.name)} is a symbolic link to {shown(target)}, which points nowhere (no file is there)"


def _mmstack_files(tif, summary: dict, path=None, check=True) -> list[str] | None:
    """The files of a Micro-Manager set tifffile's series looks for beside this one, found as it
    finds them (a "_MMStack" name, the summary's Prefix, a glob of *.tif that may miss this file
    itself); None where it reads this one alone. One that is a symbolic link to nothing is
    refused, named (``path``: the file as the user named it), unless not ``check``."""
    prefix = summary.get("Prefix", tif.filename.split("_MMStack")[0])
    if not tif.filehandle.is_file or "_MMStack" not in tif.filename or not isinstance(prefix, str):
        return None
    if not tif.filename.startswith(prefix):
        return None
    found = glob.glob(os.path.join(tif.filehandle.dirname, prefix + "_MMStack*.tif"))
    for name in found if check else ():  # tifffile opens each: a dangling link's "No such file" named no link
        if not os.path.exists(name):
            raise FormatError(
                Path(path or tif.filehandle.path), f"a file of its Micro-Manager stack by its name: {not_there(name)}"
            )
    return found


def mmstack_set_files(tif) -> list[str]:
    """The other files of this file's Micro-Manager set, which a read with allow_external may
    take frames from: every file tifffile's series of it looks for, but those whose index map
    records only stage positions this file's does not (another position's stack, not read with
    it); [] where it is no Micro-Manager file.

    Why: listed from the planes tifffile's series found, a file whose index map was never
    written (an acquisition that crashed) was left out, and an output could replace it."""
    meta = micromanager_metadata(tif, strict=False)
    summary, index = meta.get("Summary"), meta.get("IndexMap")
    if not isinstance(summary, dict):
        return []
    found = _mmstack_files(tif, summary, check=False) or []
    own = None if index is None or not len(index) else set(index[:, 3].tolist())
    others = []
    for name in found:
        if os.path.basename(name) == tif.filename:
            continue
        try:
            theirs, _ = _read_index_map(name)
        except OSError:  # (unreadable) listed: nothing says it is not of the set
            theirs = None
        if own is None or not theirs or own & {entry[3] for entry in theirs}:
            others.append(name)
    return others


def _read_index_map(name: str) -> tuple[list | None, str]:
    """The (channel, slice, frame, position, IFD offset) entries of the Micro-Manager index map
    of the file ``name``, or None and what is wrong with it (for messages). Read here, not by
    tifffile: tifffile reads the count's 20 bytes an entry at once, 8 GB asked of a 5 KB file
    declaring 4*10**8 entries."""
    import struct

    with open(name, "rb") as fh:
        head = fh.read(16)
        order = {b"II": "<", b"MM": ">"}.get(head[:2])
        if order is None or len(head) < 16:
            return None, "cannot be found (no Micro-Manager header)"
        magic, at = struct.unpack_from(order + "II", head, 8)
        size = os.fstat(fh.fileno()).st_size
        fh.seek(at)
        header = fh.read(8)
        if magic != 54773648 or len(header) < 8 or struct.unpack_from(order + "I", header)[0] != 3453623:
            return None, "was never written (no index map header where the file's header points)"
        count = struct.unpack_from(order + "I", header, 4)[0]
        if at + 8 + 20 * count > size:
            return None, f"declares {count} entries, more than the file's {size} bytes hold"
        data = fh.read(20 * count)
    return [struct.unpack_from(order + "5I", data, 20 * k) for k in range(count)], ""


def _index_span(names: list[str], own: list[int], given, path=None) -> tuple[list[int], int]:
    """The (channel, slice, frame, position) span of the planes the index maps of the files
    ``names`` of a set record, at least ``own``, and how many entries they hold; a file whose
    index map does not account for each of its pages, one by one, is refused, named (``given``:
    the file read, as ``path`` names it for messages).

    Why: Micro-Manager fills a file's index map as it closes the file, so an acquisition that
    crashed leaves it zero or part filled (tifffile takes a zero entry for plane (0, 0, 0, 0) at
    offset 0). Its pages' planes then count for nothing: a set whose second file had none read
    the first file's 2 of 4 frames as "stopped early", dropping 2 written frames silently.
    Refused rather than read in page order: a page's plane (channel, slice, time point) and its
    place among the other files' are what the index map records; guessed, the frames could come
    misordered with nothing said."""
    from radiokit.io._tiff_ifds import check_tiff_pages  # late: only a Micro-Manager set needs it

    span, entries = list(own), 0
    for name in names:
        where = Path(path or name) if os.path.samefile(name, given) else Path(name)
        index, problem = _read_index_map(name)
        pages: list[int] = []
        # each file walked alone: other positions' files are not opened with this one, and the
        # read charges those it opens together (_walk_set)
        check_tiff_pages(name, offsets=pages)
        if index is not None:
            indexed = {entry[4] for entry in index}
            unindexed, stray = len(set(pages) - indexed), len(indexed - set(pages))
            if unindexed or stray:
                problem = f"records {len(pages) - unindexed} of its {len(pages)} pages"
                problem += f", and points {stray} entr{'ies' if stray > 1 else 'y'} where no page is" if stray else ""
        if problem:
            of = "" if where.name == Path(path or given).name else f" read from {Path(path or given).name}"
            raise FormatError(
                where,
                f"a file of the Micro-Manager set{of}: its index map {problem}: the acquisition likely crashed "
                "before the file was closed (Micro-Manager fills the index map then), so which plane each page "
                "holds is unknown: refused rather than guessed",
            )
        if index:
            span = [max(s, max(entry[k] for entry in index) + 1) for k, s in enumerate(span)]
            entries += len(index)
    return span, entries


def _drop_the_plan(summary: dict, counts: list[int], written: list[int], entries: int, where: str) -> str | None:
    """Where the summary planned more channels, slices or time points than the index maps record
    written, set its counts to those written (tifffile's series then lists only them), and say
    so; None where it planned no more.

    Why: Micro-Manager writes the summary, with the acquisition's planned counts, as it opens
    each file and never again, and an index map entry as it writes each plane
    (MultipageTiffWriter): an acquisition stopped early leaves a summary planning more than was
    written. tifffile lists a slot for every plane planned (20 bytes each, 4*10**8 planned: 7.8
    GB), reads the set's missing ones as zeros, and radiokit refused them. Positions are left as
    planned: each is written to files of its own, which tifffile's series takes in beside it."""
    cut = [(key, axis, c, w) for (key, axis), c, w in zip(_MM_COUNTS[:3], counts, written) if c > w]
    if not cut:
        return None
    for key, _, _, w in cut:
        summary[key] = w
    planned = " x ".join(f"{axis} {c}" for _, axis, c, _ in cut)
    found = " x ".join(f"{axis} {w}" for _, axis, _, w in cut)
    return (
        f"its Micro-Manager summary planned {math.prod(counts)} planes ({planned}) but {where} "
        f"{entries} ({found}): the acquisition looks stopped early"
    )


def check_mmstack_slots(tif, path=None) -> str | None:
    """Refuse a Micro-Manager stack whose summary's counts (Channels x Slices x Frames x
    Positions) or index map's coordinates declare more planes than its files can hold; where
    the summary planned more than the index maps record written (an acquisition stopped early),
    count only those written (:func:`_drop_the_plan`) and return what to warn of, else None.
    ``path``: the file as the user named it, for the message.

    Why: tifffile's series of it lists a slot for every plane declared (8 bytes each), before
    radiokit's IFD walk or page budget sees a page: two 5 KB files of a set whose summary said
    Frames 4*10**8 took 214 s and 7.8 GB to open, one whose index map put a plane at T = 4*10**8
    - 1, 42 s and 6.3 GB. Each real plane has a 20-byte index map entry in some file, so more
    planes than the files' bytes / 20 are declared, never written. The slots are counted as
    tifffile does: the index maps' span, or the set's where it reads a set of files; the span of
    this file's index map where it reads this file alone."""
    meta = micromanager_metadata(tif)
    summary, index = meta.get("Summary"), meta.get("IndexMap")
    if not isinstance(summary, dict) or "MicroManagerVersion" not in summary or "Frames" not in summary:
        return None  # no Micro-Manager series: tifffile lists nothing
    if index is None or not len(index):
        return None
    try:
        counts = [int(summary.get(key, 1)) for key, _ in _MM_COUNTS]
    except (TypeError, ValueError, OverflowError):  # (1e400: infinity) tifffile's series says what it makes of it
        return None
    high = [int(v) + 1 for v in index[:, :4].max(axis=0)]
    low = [int(v) for v in index[:, :4].min(axis=0)]
    files, written, entries, where, found = [tif.filehandle.path], high, len(index), "it holds", None
    if math.prod(max(h, c) for h, c in zip(high, counts)) > len(index):  # tifffile looks for the set's other files
        found = _mmstack_files(tif, summary, path)
        if found is not None and len(found) > 1:
            files, where = found, f"its set's {len(found)} files hold"
            written, entries = _index_span(found, high, tif.filehandle.path, path)
    note = _drop_the_plan(summary, counts, written, entries, where)
    counts = [int(summary.get(key, 1)) for key, _ in _MM_COUNTS]
    sizes = [max(w, c) for w, c in zip(written, counts)]
    if math.prod(sizes) > len(index) and (found is None or len(found) == 1):
        sizes = [h - lo for h, lo in zip(high, low)]  # read alone: squeezed to the span of its index map
    slots = math.prod(sizes)
    shape = " x ".join(f"{axis} {n}" for (_, axis), n in zip(_MM_COUNTS, sizes))
    # the files' sizes are no bound where a set's file is sparse (a 2 GB truncated file takes no
    # disk): what listing the slots takes is charged to the memory budget as well
    from radiokit.io._budget import check_budget

    check_budget(
        Path(path or tif.filehandle.path),
        slots * _MM_SLOT_BYTES,
        f"listing a Micro-Manager stack of {slots} planes ({shape}, by its summary and index map)",
    )
    held = sum(os.path.getsize(name) for name in files)
    if slots * _MM_ENTRY_BYTES > held:
        where = f"its {held} bytes" if len(files) == 1 else f"the {held} bytes of its set's {len(files)} files"
        raise FormatError(
            Path(path or tif.filehandle.path),
            f"a Micro-Manager stack of {slots} planes ({shape}, by its summary and index map), more than "
            f"{where} can hold ({_MM_ENTRY_BYTES} bytes of index map a plane): corrupt",
        )
    return note
