"""Hamamatsu ITEX / HiPic ``.img`` files (HPD-TA, HiPic, XVS-FPD).

Layout (all little-endian): a 64-byte header, an ASCII comment of ``comment_length`` bytes (an
unsigned 16-bit count), the pixels (unsigned, ``width * height`` per image, rows top first), then
optional blocks such as the float32 axis arrays a ``[Scaling]`` section points at with
``"#<byte offset>,<count>"``.
"""

from __future__ import annotations

import re
import struct

import numpy as np

from radiokit.errors import FormatError

__all__ = [
    "parse_itex_header",
    "parse_comment",
    "check_comment_end",
    "check_pixels_start",
    "check_tail",
    "adc_bits",
    "ITEX_TYPES",
]

# The comment length is unsigned: HiPic writes comments over 32767 bytes (read signed, a valid
# 40 000-byte one was "negative"); width and height stay signed, a negative one is corrupt.
HEADER = struct.Struct("<2sHhhhhhihhd4s30s")
HEADER_BYTES = 64
assert HEADER.size == HEADER_BYTES
#: file type -> pixel dtype; type 1 is a compressed format nobody documents.
ITEX_TYPES = {0: np.dtype("<u1"), 2: np.dtype("<u2"), 3: np.dtype("<u4")}


def parse_itex_header(path, head: bytes, size: int) -> dict:
    """Validate the 64-byte header against the file size and return the geometry."""
    if len(head) < HEADER_BYTES:
        raise FormatError(path, f"ITEX header needs {HEADER_BYTES} bytes; the file has {len(head)}")
    (magic, comment_len, width, height, x0, y0, ftype, n_images, n_channels, channel, stamp, marker, info) = (
        HEADER.unpack(head[:HEADER_BYTES])
    )
    if magic != b"IM":
        raise FormatError(path, f"wrong magic {magic!r}: an ITEX .img starts with b'IM'")
    if ftype == 1:
        raise FormatError(path, "ITEX file type 1 (compressed) is not supported; save as 16-bit (type 2)")
    if ftype == 0:
        _refuse_big_endian_8bit(path, head, size)
    if ftype not in ITEX_TYPES:
        swapped = struct.unpack_from(">h", head, 12)[0]
        if swapped in ITEX_TYPES or swapped == 1:  # 2 read as 512: the header's bytes are swapped
            raise FormatError(
                path,
                f"big-endian ITEX header (file type {ftype} is {swapped} byte-swapped): ITEX files are "
                "little-endian as HiPic and HPD-TA write them; radiokit does not read big-endian ones",
            )
        raise FormatError(path, f"unknown ITEX file type {ftype} (known: 0 8-bit, 2 16-bit, 3 32-bit)")
    if width <= 0 or height <= 0:
        raise FormatError(path, f"ITEX header gives a {width}x{height} image")
    if n_images < 0:
        raise FormatError(path, f"negative image count {n_images} in the ITEX header")
    n = max(int(n_images), 1)  # 0 is written for a single image
    dt = ITEX_TYPES[ftype]
    data_offset = HEADER_BYTES + comment_len
    need = data_offset + n * width * height * dt.itemsize
    if need > size:
        raise FormatError(
            path,
            f"ITEX header promises {n} image(s) of {width}x{height} {dt.itemsize * 8}-bit "
            f"after a {comment_len}-byte comment ({need} bytes); the file has {size}",
        )
    return dict(
        format="itex",
        n=n,
        rows=int(height),
        cols=int(width),
        dtype=dt,
        offset=data_offset,
        comment_length=int(comment_len),
        file_type=int(ftype),
        x_offset=int(x0),
        y_offset=int(y0),
        channels=int(n_channels),
        channel=int(channel),
        time_stamp=float(stamp),
        marker=marker.rstrip(b"\0").decode("latin-1"),
        info=info.rstrip(b"\0").decode("latin-1"),
        file_size=size,
    )


def _sizes(head: bytes, order: str) -> tuple[int, int, int, int] | None:
    """Comment length, width, height and image count of an 8-bit image's header read in
    ``order``; None when they cannot be a header's (a size or count below zero)."""
    comment_len, width, height = struct.unpack_from(order + "Hhh", head, 2)
    n_images = struct.unpack_from(order + "i", head, 14)[0]
    if width <= 0 or height <= 0 or n_images < 0:
        return None
    return comment_len, width, height, max(n_images, 1)


def _refuse_big_endian_8bit(path, head: bytes, size: int) -> None:
    """Refuse a big-endian header of file type 0, whose type field reads 0 in either byte order.

    The sizes tell: read in the wrong order they are nonsense (640 = 0x0280 reads -32766) or do
    not account for the file. Big-endian is taken when only that reading fits in the file, or it
    fills the file exactly and the little-endian one does not. When both fit and neither or both
    fill it exactly (small swapped sizes, and blocks after the pixels), the header cannot tell,
    and the file is read little-endian, as HiPic and HPD-TA write it.
    """
    need = {}
    for order in "<>":
        sizes = _sizes(head, order)
        if sizes is not None and HEADER_BYTES + sizes[0] + sizes[3] * sizes[1] * sizes[2] <= size:
            need[order] = (HEADER_BYTES + sizes[0] + sizes[3] * sizes[1] * sizes[2], sizes)
    if ">" not in need or ("<" in need and (need["<"][0] == size or need[">"][0] != size)):
        return
    comment_len, width, height, n = need[">"][1]
    how = "fill" if need[">"][0] == size else "fit in"
    raise FormatError(
        path,
        f"big-endian ITEX header (8-bit, file type 0): read big-endian its sizes ({n} image(s) of "
        f"{width}x{height} after a {comment_len}-byte comment) {how} the {size}-byte file, read "
        "little-endian they do not; ITEX files are little-endian as HiPic and HPD-TA write them; "
        "radiokit does not read big-endian ones",
    )


# A section header, or one key=value item whose value may be quoted (and then hold commas).
# Possessive quantifiers and a section name without "[" keep every attempt from backtracking,
# so parsing is linear in the comment (lazy keys followed by \s* made 32 KB take seconds).
_TOKEN = re.compile(
    r"(?:\[(?P<section>[^\]\r\n\[]*+)\]|(?P<key>[^=,\r\n\[]++)="
    r'\s*+(?:"(?P<quoted>[^"]*+)"|(?P<bare>[^,\r\n\[]*+)))\s*+,?'
)
_SEPARATOR = re.compile(r"[,\n\[]")
_SPACE = re.compile(r"\s*")


# Plain decimal literals only: int()/float() would also take "1_000", "nan", "Infinity", " 7 ".
_INT = re.compile(r"[+-]?[0-9]+\Z")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?\Z")


def _number(text: str):
    if _INT.match(text):
        try:
            return int(text)
        except ValueError:  # beyond sys.get_int_max_str_digits()
            return text
    if _FLOAT.match(text):
        return float(text)
    return text


def parse_comment(text: str) -> dict:
    """Parse ``[Section],key=value,key="quoted, value"`` into ``{section: {key: value}}``.

    Sections are separated by CR LF in most files but may follow each other directly
    (``...SubType=0[DisplayLUT],...``); unquoted numbers become int or float, the rest stays text.
    Keys before any section go under ``""``. Text that is not a key=value item is kept under
    ``"_unparsed"`` rather than dropped.
    """
    out: dict[str, dict] = {}
    current = out.setdefault("", {})
    pos, end = 0, len(text)
    leftovers = []
    while pos < end:
        pos = _SPACE.match(text, pos).end()  # skipped once here, never rescanned by a failed match
        if pos == end:
            break
        m = _TOKEN.match(text, pos)
        if not m or m.end() == pos:
            sep = _SEPARATOR.search(text, pos + 1)
            nxt = sep.start() if sep else end
            piece = text[pos:nxt].strip(" ,\r\n\0")
            if piece:
                leftovers.append(piece)
            # step over the separating comma too, or the next item would be taken as leftover
            pos = nxt + 1 if nxt < end and text[nxt] == "," else nxt
            continue
        if m.group("section") is not None:
            current = out.setdefault(m.group("section").strip(), {})
        else:
            key = m.group("key").strip()
            if not key:  # "=value" with no name: keep it, as any text that is not an item
                leftovers.append(text[pos : m.end()].strip(" ,\r\n\0"))
                pos = m.end()
                continue
            current[key] = m.group("quoted") if m.group("quoted") is not None else _number(m.group("bare").strip())
        pos = m.end()
    if not out[""]:
        del out[""]
    if leftovers:
        out["_unparsed"] = leftovers
    return out


_POINTER = re.compile(r"^#\s*(\d+)\s*,\s*(\d+)\s*$")


def read_scaling(path, fh, comment: dict, size: int) -> dict:
    """Read the float32 axis arrays that ``[Scaling]`` points at; describe named scalings."""
    sec = comment.get("Scaling", {})
    axes = {}
    for axis in ("X", "Y"):
        ref = sec.get(f"Scaling{axis}ScalingFile")
        if ref is None:
            continue
        entry = {
            "type": sec.get(f"Scaling{axis}Type"),
            "scale": sec.get(f"Scaling{axis}Scale"),
            "unit": sec.get(f"Scaling{axis}Unit", ""),
        }
        m = _POINTER.match(str(ref))
        if m:
            off, count = int(m.group(1)), int(m.group(2))
            if off + 4 * count > size:
                raise FormatError(
                    path,
                    f"[Scaling] {axis} axis points at {count} float32 values at byte {off}, "
                    f"beyond the end of the {size}-byte file",
                )
            fh.seek(off)
            entry["values"] = np.frombuffer(fh.read(4 * count), "<f4").astype(np.float32)
        else:
            entry["name"] = str(ref)
        axes[axis.lower()] = entry
    return axes


def check_comment_end(path, geo: dict, text: str) -> None:
    """Refuse a comment whose declared length cuts a quoted value: HPD-TA quotes text values and
    ends its comment with one (``UserComment=""``), so a length a byte short leaves the comment
    ending inside quotes, and the closing quote read as the first pixel's byte shifts every pixel."""
    last = text.rfind('"')
    # the last quote opening a value (after "="), never closed: a stray quote earlier in a user's
    # comment, the comment ending as HPD-TA ends it, is no sign of a wrong length
    if text.count('"') % 2 and last > 0 and text[last - 1] == "=":
        raise FormatError(
            path,
            f"ITEX comment of {geo['comment_length']} bytes (the header's length) ends inside a quoted value: "
            "the header's comment length disagrees with the text (pixels read after it would be shifted); not read",
        )


#: A comment's section as HPD-TA starts each (``[Application],Enconding=``): eight or more bytes
#: of a fixed shape that no panel's pixels form.
_SECTION = re.compile(rb"\[[A-Za-z][A-Za-z ]{0,30}\],[A-Za-z_]+=")


def check_pixels_start(path, geo: dict, first: bytes) -> None:
    """Refuse pixels whose first bytes (``first``) begin a comment's section: the header's comment
    length ends before the comment does, at a section's start (0, zeroed; or cut at a line), where
    no quoted value is cut (:func:`check_comment_end`) and the [Scaling] pointer, in the text left
    out, is never read (:func:`check_tail`). Why: focus_mode.img's comment length zeroed read its
    comment as the first pixels, 0..39173 as 0..2053730927, and ``correct`` wrote a stack of it (s53)."""
    if _SECTION.match(first):
        raise FormatError(
            path,
            f"ITEX pixels begin with comment text ({first[:16].decode('latin-1')!r}...): the header's comment "
            f"length ({geo['comment_length']} bytes) ends before the comment does; not read",
        )


def check_tail(path, geo: dict, comment: dict) -> None:
    """Refuse a file holding an image's worth of bytes or more after its declared images that no
    ``[Scaling]`` axis accounts for: a header whose count or size declares less than the pixels
    stored (a count of 0, which means one image, over a stack; a size edited or from another
    binning) read the first bytes as the declared images, silently, and ignored the rest.
    HPD-TA's files hold exactly their axes there; padding short of an image is let be."""
    image = geo["rows"] * geo["cols"] * geo["dtype"].itemsize
    pixels_end = geo["offset"] + geo["n"] * image
    size = geo["file_size"]
    spans, starts = [], []
    for axis in ("X", "Y"):  # the byte ranges the axes take, where they lie after the pixels
        m = _POINTER.match(str(comment.get("Scaling", {}).get(f"Scaling{axis}ScalingFile", "")))
        if m:
            if int(m.group(1)) + 4 * int(m.group(2)) <= size:  # beyond the end: read_scaling says so
                starts.append((int(m.group(1)), axis))
            spans.append((max(int(m.group(1)), pixels_end), min(int(m.group(1)) + 4 * int(m.group(2)), size)))
    # The writer's own pointer says where its pixels end: HPD-TA stores the first axis right after
    # them (all five vendor files, to the byte). A comment length off by a byte or two moves the
    # pixels' start, and every pixel is then read byte-shifted (0..35 read as 0..45824), with
    # nothing else in the file to tell: the pointer is the one witness, so any mismatch is refused.
    if starts and min(starts)[0] != pixels_end:
        first, axis = min(starts)
        raise FormatError(
            path,
            f"ITEX [Scaling] {axis} axis begins at byte {first}, but the header's {geo['comment_length']}-byte "
            f"comment and {geo['n']} image(s) of {geo['cols']}x{geo['rows']} {8 * geo['dtype'].itemsize}-bit end "
            f"the pixels at byte {pixels_end}: the header's comment length or size disagrees with the file "
            "(pixels read from there would be shifted); not read",
        )
    explained, reached = 0, pixels_end
    for start, stop in sorted(spans):  # overlapping axes counted once
        explained += max(0, stop - max(start, reached))
        reached = max(reached, stop)
    unexplained = size - pixels_end - explained
    if unexplained >= image:
        raise FormatError(
            path,
            f"ITEX header declares {geo['n']} image(s) of {geo['cols']}x{geo['rows']} {8 * geo['dtype'].itemsize}-bit "
            f"(a count of 0 is one), but {unexplained} bytes follow them that no [Scaling] axis accounts for, "
            f"room for {unexplained // image} more: the header disagrees with the file (a wrong count or size); not read",
        )


# Hamamatsu flat panels by model number and the bits of their ADC (C7942.md): C7921/C7942/C7943
# are 12-bit, C9730DK/C9732DK 14-bit. Other cameras (HPD-TA's Orcas, streak cameras) say nothing.
_PANEL_BITS = (
    (re.compile(r"(?<![A-Za-z0-9])C79(?:21|42|43)(?![0-9])", re.IGNORECASE), 12),
    (re.compile(r"(?<![A-Za-z0-9])C973[02](?![0-9])", re.IGNORECASE), 14),
)


def adc_bits(comment: dict, file_type: int) -> int | None:
    """The ADC bits of the panel the comment's ``[Camera] CameraName`` names, for a 16-bit
    (type 2) file of single exposures; else None.

    Why: a C7942's counts end at 4095, and a value past it means the writer's byte order or bit
    alignment (a set of byte-swapped darks, flats and frames calibrated and corrected to noise
    with no word of it). A summed acquisition (``[Acquisition] NrExposure`` over 1, as HPD-TA's
    integrations) passes the ADC's top by design, and 8- or 32-bit files are not its words.
    """
    if file_type != 2:
        return None
    exposures = comment.get("Acquisition", {}).get("NrExposure", 1)
    if not isinstance(exposures, int) or exposures > 1:
        return None
    name = comment.get("Camera", {}).get("CameraName")
    if not isinstance(name, str):
        return None
    for pattern, bits in _PANEL_BITS:
        if pattern.search(name):
            return bits
    return None
