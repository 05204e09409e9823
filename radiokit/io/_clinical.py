"""The radiographs other labs and archives hand over: 8- and 16-bit greyscale PNG, and DICOM.

Both are judged from their headers before any pixel is decoded, as a TIFF's pages are: a PNG's
IHDR and a DICOM's Rows x Columns x NumberOfFrames x BitsAllocated are what the decoder would
allocate, and are held to the memory budget first (a 100-byte PNG may declare 60000 x 60000).
"""

from __future__ import annotations

import os
import struct
import warnings
import zlib

import numpy as np

from radiokit._names import shown
from radiokit.errors import FormatError
from radiokit.io._budget import BUDGET_ENV, check_budget, check_proportion, human_bytes, memory_budget
from radiokit.io._codecs import (
    check_dicom_proportion,
    compressed_frame,
    compressed_syntaxes,
    frame_decode_bytes,
    say_lossy_dicom,
    syntax_header,
)
from radiokit.io._experiment import usable_pixel_sizes
from radiokit.io._frames import BitDepthWarning


class InvertedWarning(UserWarning):
    """A DICOM's values are MONOCHROME1 (its lowest value shows white), read as stored."""


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def dicom_bare_start(head: bytes) -> bool:
    """Whether ``head`` may open a DICOM file written without its 128-byte preamble and b'DICM':
    a little-endian tag's group first, even (a standard group, not a private one) and from the
    file meta's (0002) to the pixels' (7FE0); a bare dataset starts at its lowest group present
    (0008, or 0028 where it has only the image's)."""
    if len(head) < 8:
        return False
    group = int.from_bytes(head[:2], "little")
    return group % 2 == 0 and 0x0002 <= group <= 0x7FE0


_PNG_COLOURS = {0: "greyscale", 2: "RGB", 3: "palette", 4: "greyscale with alpha", 6: "RGBA"}


def png_header(path) -> dict:
    """A PNG's IHDR (width, height, bit depth, colour type) and, from the chunks before its
    pixels, whether it has a tRNS (OpenCV then adds an alpha channel) and its sBIT (the
    significant bits of a greyscale sample: a 12-bit panel's counts in 16-bit words). Only the
    chunk headers are read: nothing is decoded."""
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        head = fh.read(33)
        if head[:8] != PNG_MAGIC:  # format="png" given for another file
            raise FormatError(path, f"no PNG signature ({PNG_MAGIC!r}): not a PNG file")
        if len(head) < 33 or head[12:16] != b"IHDR":
            raise FormatError(path, "a PNG without its IHDR header first: truncated or corrupt")
        width, height, depth, colour, interlace = _check_ihdr(path, head)
        out = {"width": width, "height": height, "depth": depth, "colour": colour, "trns": False, "sbit": None}
        out |= {"interlaced": bool(interlace), "file_bytes": size}
        pos = 33
        while pos + 8 <= size:  # the chunks up to the first IDAT: bounded by the file's size
            fh.seek(pos)
            length, kind = struct.unpack(">I4s", fh.read(8))
            if kind in (b"IDAT", b"IEND"):
                break
            if kind == b"tRNS":
                out["trns"] = True
            elif kind == b"sBIT" and colour == 0 and length == 1:
                out["sbit"] = fh.read(1)[0]
            elif kind == b"acTL" and length == 8:  # APNG's animation control: its frame count first
                out["frames"] = struct.unpack(">I", fh.read(4))[0]
            pos += 12 + length
    return out


#: each colour type's bit depths (PNG 1.2, 11.2.2)
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
#: libpng's default most columns and rows (PNG_USER_WIDTH_MAX, PNG_USER_HEIGHT_MAX), which OpenCV keeps
_LIBPNG_MOST = 1_000_000


def _check_ihdr(path, head: bytes) -> tuple[int, int, int, int, int]:
    """IHDR's width, height, bit depth, colour type and interlace method; refused in one line
    where libpng refuses it (its 13 bytes' methods, a colour type and bit
    depth PNG does not pair, past libpng's 1 000 000 columns or rows). Why: libpng printed
    "libpng warning: ..." and "libpng error: Invalid IHDR data" on the process's stderr, and
    radiokit then blamed truncation."""
    (length,) = struct.unpack(">I", head[8:12])
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", head[16:29])
    if length != 13:
        fault = f"an IHDR of {length} bytes, not 13"
    elif colour not in _PNG_DEPTHS or depth not in _PNG_DEPTHS[colour]:
        fault = f"colour type {colour}, bit depth {depth}: no PNG image"
    elif (compression, filtering) != (0, 0) or interlace not in (0, 1):
        fault = f"compression method {compression}, filter method {filtering}, interlace method {interlace}"
        fault += ": PNG defines 0, 0 and 0 or 1"
    elif not width or not height:
        fault = f"an image of {width} x {height} pixels"
    elif max(width, height) > _LIBPNG_MOST:
        fault = f"{width} x {height} pixels, past the {_LIBPNG_MOST} columns or rows OpenCV's libpng reads"
    else:
        return width, height, depth, colour, interlace
    raise FormatError(path, f"a PNG whose IHDR is invalid ({fault})")


def png_decoded_bytes(header: dict) -> int:
    """What OpenCV's decode allocates: one byte a sample up to 8 bits, two for 16; greyscale with
    no tRNS one channel, anything else up to four (BGRA)."""
    channels = 1 if header["colour"] == 0 and not header["trns"] else 4
    return header["width"] * header["height"] * channels * (2 if header["depth"] == 16 else 1)


def png_read_bytes(header: dict) -> int:
    """What :func:`decode_png` holds at once: the PNG it builds of the inflated rows
    (:func:`_stored_png`: the rows and each stored block's header), with the file's bytes and an
    inflated piece while it builds it, then with the pixels OpenCV decodes (:func:`png_decoded_bytes`).
    Why not the pixels alone: the built PNG is about their size (16-bit), twice it a pixel wide
    (a filter byte a sample), and a PNG just under the budget took twice the budget."""
    need = png_pixel_bytes(header)
    built = need + 5 * -(-need // _STORED_BLOCK) + 64  # (the chunks' headers, the zlib header and Adler-32)
    # (a piece zlib gives is built in blocks then joined: twice its size at most)
    building = header["file_bytes"] + 2 * min(need, _INFLATE_PIECE) + _FED
    return built + max(building, png_decoded_bytes(header))


def check_png(path, header: dict, budget) -> None:
    """Refuse, before decoding, a PNG whose declared pixels pass the memory budget, and a palette
    image (its values are indices into a colour table, not intensities)."""
    w, h, depth, colour = (header[k] for k in ("width", "height", "depth", "colour"))
    kind = _PNG_COLOURS[colour]
    check_budget(path, png_read_bytes(header), f"its PNG header's {w}x{h} {depth}-bit {kind} image", budget)
    if header.get("frames", 1) > 1:  # OpenCV decodes the default image alone and says nothing of the rest
        raise FormatError(
            path,
            f"an animated PNG (APNG) of {header['frames']} frames, of which OpenCV reads one: "
            "save the frames as a TIFF stack, or one PNG each",
        )
    if colour == 3:
        raise FormatError(
            path,
            "a palette PNG: its values are indices into a colour table, not intensities; "
            "export the radiograph as 8- or 16-bit greyscale",
        )


#: Adam7's passes: (first row, first column, row step, column step)
_ADAM7 = ((0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1))
_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
#: a stored deflate block's most bytes (its LEN is 16 bits)
_STORED_BLOCK = 0xFFFF
#: the most bytes :func:`_inflated` gives at a time, and feeds the decompressor at a time
_INFLATE_PIECE, _FED = 1 << 20, 1 << 16


def _png_rows(header: dict) -> list[tuple[int, int, int]]:
    """Where IDAT's inflated stream holds its rows: (first byte, rows, bytes a row) of each
    Adam7 pass (one pass where not interlaced), each row a filter byte and its samples packed
    to whole bytes."""
    w, h = header["width"], header["height"]
    bits = _PNG_SAMPLES[header["colour"]] * header["depth"]
    passes = _ADAM7 if header["interlaced"] else ((0, 0, 1, 1),)
    out, start = [], 0
    for y, x, dy, dx in passes:
        rows, cols = -(-(h - y) // dy), -(-(w - x) // dx)
        if rows > 0 and cols > 0:
            out.append((start, rows, 1 + -(-cols * bits // 8)))
            start += rows * out[-1][2]
    return out


def png_pixel_bytes(header: dict) -> int:
    """The bytes IDAT's zlib stream inflates to (:func:`_png_rows`)."""
    return sum(rows * length for _, rows, length in _png_rows(header))


def _check_filters(path, layout, at: int, data) -> None:
    """Refuse in one line a row, among the inflated bytes ``data`` from byte ``at`` of the stream,
    whose filter type is none of PNG's five (0-4). Why: libpng printed "libpng error: bad
    adaptive filter value" on the process's stderr. A strided view of each pass's filter bytes:
    no copy."""
    arr = np.frombuffer(data, np.uint8)
    for start, rows, length in layout:
        lo, hi = max(start, at), min(start + rows * length, at + len(arr))
        first = start + -(-(lo - start) // length) * length  # the first row starting at or past lo
        if first < hi:
            found = arr[first - at : hi - at : length]
            if found.max() > 4:
                bad = int(np.argmax(found > 4))
                raise FormatError(
                    path, f"a PNG whose pixel data holds a row of filter type {found[bad]}, none of PNG's 0-4: corrupt"
                )


def _inflated(path, need: int, idat):
    """IDAT's zlib stream (``idat``, its chunks' data) inflated, a piece at a time, up to ``need``
    bytes (:func:`png_pixel_bytes`: the header's size, held to the budget before this; a stream
    inflating to more is cut there, never held). Refused in one line where the stream ends (or
    breaks) before the image does. Why: a cut stream inside a chunk whose CRC is right passed
    :func:`check_png_chunks`, and libpng printed "libpng error: Not enough image data" before
    the one line."""
    got = 0
    inflate = zlib.decompressobj()
    # fed a slice of a chunk at a time: a piece's unconsumed_tail is a copy of what is left of it
    # (a one-IDAT file's whole stream, beside the file and the built PNG: png_read_bytes)
    pieces = (chunk[k : k + _FED] for chunk in idat for k in range(0, len(chunk), _FED))
    try:
        for piece in pieces:
            tail = piece
            while tail and got < need:
                data = inflate.decompress(tail, min(need - got, _INFLATE_PIECE))
                tail = inflate.unconsumed_tail
                if not data:
                    break
                got += len(data)
                yield data
                del data  # (one piece held at a time, beside the one zlib builds: png_read_bytes)
            if got >= need:
                return
    except zlib.error as exc:
        raise FormatError(path, f"a PNG whose pixel data does not inflate ({exc}): corrupt") from None
    raise FormatError(
        path, f"a PNG whose pixel data ends early: {got} of its image's {need} bytes (truncated or corrupt)"
    )


#: the most data bytes of a PNG chunk (2**31 - 1: libpng refuses longer ones, "PNG unsigned
#: integer out of range"), and so of each IDAT :func:`_stored_png` builds
_CHUNK_MOST = 2**31 - 1


def _stored_png(path, header: dict, head: bytes, chunks: list, idat) -> np.ndarray:
    """The PNG libpng is given: the signature and IHDR (``head``), the other pixel ``chunks``
    (PLTE, tRNS) and IDATs holding the image's filtered rows, inflated from the file's stream
    (``idat``, :func:`_inflated`) straight into stored deflate blocks, then IEND. Why: radiokit
    must inflate the stream to know it ends where the image does, and libpng inflated it again;
    a stored block it copies (benchmarks/README.md, bench_png_read.py: a quarter of the time).
    The buffer is the rows and a few bytes a block: no other copy of them is held. Whole blocks
    an IDAT, as many as :data:`_CHUNK_MOST` holds: one IDAT of a 16-bit image past 32768 x 32768
    (2 GiB of rows) was past it."""
    layout = _png_rows(header)
    need = sum(rows * length for _, rows, length in layout)
    stride = 5 + _STORED_BLOCK  # a block's header and its bytes
    blocks = max(1, -(-need // _STORED_BLOCK))
    per = (_CHUNK_MOST - 6) // stride  # whole blocks an IDAT (and the zlib header or Adler-32)
    n_idat = -(-blocks // per)
    stream = 2 + 5 * blocks + need + 4  # zlib header, each block's header, the rows, Adler-32
    pre = b"".join([head, *chunks])
    out = bytearray(len(pre) + stream + 12 * n_idat + 12)
    out[: len(pre)] = pre
    at = len(pre)

    def block_at(k):  # where block k's header lies: past k blocks, the zlib header, k // per IDATs' 12 bytes
        return at + 8 + 12 * (k // per) + 2 + k * stride

    for k in range(blocks):
        n = min(_STORED_BLOCK, need - k * _STORED_BLOCK)
        struct.pack_into("<BHH", out, block_at(k), k == blocks - 1, n, n ^ 0xFFFF)  # BTYPE 00
    struct.pack_into("2s", out, at + 8, b"\x78\x01")  # deflate, 32 KiB window (0x7801 % 31 == 0)
    got, adler = 0, 1
    for data in _inflated(path, need, idat):
        _check_filters(path, layout, got, data)
        adler = zlib.adler32(data, adler)
        view = memoryview(data)
        while view:  # into its block(s)
            k, j = divmod(got, _STORED_BLOCK)
            n = min(len(view), _STORED_BLOCK - j)
            pos = block_at(k) + 5 + j
            out[pos : pos + n] = view[:n]
            view, got = view[n:], got + n
        del data, view  # (let go before the next piece is inflated: one piece held at a time, png_read_bytes)
    end = block_at(blocks - 1) + 5 + need - (blocks - 1) * _STORED_BLOCK  # past the last block's bytes
    struct.pack_into(">I", out, end, adler)
    for c in range(n_idat):  # each IDAT's length, kind and CRC around its blocks
        start = at if c == 0 else block_at(c * per) - 8
        stop = end + 4 if c == n_idat - 1 else block_at((c + 1) * per) - 12  # (its CRC, the next one's 8 bytes)
        struct.pack_into(">I4s", out, start, stop - start - 8, b"IDAT")
        struct.pack_into(">I", out, stop, zlib.crc32(memoryview(out)[start + 4 : stop]))
    struct.pack_into(">I4sI", out, end + 8, 0, b"IEND", zlib.crc32(b"IEND"))
    return np.frombuffer(out, np.uint8)


def check_png_chunks(path, buf) -> list:
    """Every chunk inside the file, its CRC right, and IEND reached; the chunks' (kind, start,
    end) spans returned. Why: on a truncated or corrupt PNG libpng prints its own "libpng
    error: ..." line to the process's stderr before OpenCV returns nothing, and the user saw two
    lines, one not radiokit's."""
    pos, size, spans = 8, len(buf), []
    while pos + 12 <= size:
        length, kind = struct.unpack_from(">I4s", buf, pos)
        if pos + 12 + length > size:
            break
        (crc,) = struct.unpack_from(">I", buf, pos + 8 + length)
        if zlib.crc32(buf[pos + 4 : pos + 8 + length]) != crc:
            name = kind.decode("latin-1", "replace")
            raise FormatError(path, f"a PNG whose {name!r} chunk at byte {pos} fails its CRC: corrupt")
        spans.append((bytes(kind), pos, pos + 12 + length))
        if kind == b"IEND":
            return spans
        pos += 12 + length
    raise FormatError(path, f"a PNG truncated: its chunks end at byte {pos} of {size} without IEND")


#: the length of a tRNS by colour type: one grey sample, one RGB (a palette's: up to its entries)
_TRNS_BYTES = {0: 2, 2: 6}


def _palette_chunks(view, spans, header_colour: int) -> list:
    """The PLTE and tRNS chunks (``spans``, over the file's bytes ``view``) libpng uses: before
    the first IDAT, the first of each, a PLTE for a palette image alone, a tRNS of its colour
    type's length (none with an alpha channel). Why: libpng ignores the others and says so on
    the process's stderr ("libpng warning: tRNS: invalid", "PLTE: ignored in grayscale PNG"); one
    after the pixels it ignored too, and the PNG built for it has them before its IDAT."""
    kept = {}
    for kind, a, b in spans[1:]:
        if kind == b"IDAT":
            break
        if kind in kept or kind not in (b"PLTE", b"tRNS"):
            continue
        if kind == b"PLTE" and header_colour == 3:
            kept[kind] = bytes(view[a:b])
        elif kind == b"tRNS" and (header_colour == 3 or b - a - 12 == _TRNS_BYTES.get(header_colour)):
            kept[kind] = bytes(view[a:b])
    return [kept[k] for k in (b"PLTE", b"tRNS") if k in kept]


def decode_png(path, header: dict) -> np.ndarray:
    """The PNG's pixels as stored (OpenCV's IMREAD_UNCHANGED: 16-bit samples come back exact, in
    the machine's byte order), as one greyscale (rows, cols) image. A colour PNG whose colour
    channels are equal everywhere and whose alpha, if any, is opaque everywhere is a greyscale
    image saved as colour, and is read as one channel; any other colour PNG is refused (a
    viewer's colour rendering is no counts)."""
    import cv2

    # imdecode of the bytes, not imread: imread fails silently (None) on a non-ASCII path on Windows
    raw = np.fromfile(path, np.uint8)
    view = memoryview(raw)
    spans = check_png_chunks(path, view)
    # the pixels' chunks alone: libpng inflates text and ICC chunks (a 100 KB zTXt may hold 100 MB)
    # and prints its own "libpng warning: ..." lines on what it finds in them (iCCP: "known
    # incorrect sRGB profile"); gamma is a display's business, never applied to the values
    head = bytes(view[: spans[0][2]])  # the signature and IHDR (check_png_chunks: IHDR is the first chunk)
    kept = _palette_chunks(view, spans, header["colour"])
    raw = _stored_png(path, header, head, kept, (view[a + 8 : b - 4] for k, a, b in spans if k == b"IDAT"))
    del view  # (the file's bytes: let go before the pixels are decoded beside the PNG built of them)
    data = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    if data is None:
        raise FormatError(path, "a PNG that OpenCV cannot decode: truncated or corrupt")
    if data.ndim == 2:
        return _unexpanded(data, header)
    colours = data[..., :3] if data.shape[2] >= 3 else data[..., :1]
    alpha = data[..., 3] if data.shape[2] == 4 else (data[..., 1] if data.shape[2] == 2 else None)
    opaque = alpha is None or bool(np.all(alpha == np.iinfo(data.dtype).max))
    equal = all(np.array_equal(colours[..., 0], colours[..., k]) for k in range(1, colours.shape[2]))
    if equal and opaque:
        return _unexpanded(np.ascontiguousarray(colours[..., 0]), header)
    kind = _PNG_COLOURS[header["colour"]]
    why = "its colour channels differ" if not equal else "its alpha channel is not opaque everywhere"
    raise FormatError(
        path,
        f"a {kind} PNG, {why}: a viewer's colour rendering, not one channel of counts; "
        "export the radiograph as 8- or 16-bit greyscale",
    )


def _unexpanded(grey: np.ndarray, header: dict) -> np.ndarray:
    """A 1-, 2- or 4-bit greyscale PNG's samples as stored, 0..2**depth - 1, from OpenCV's bytes.
    Why: OpenCV has libpng expand them to 8 bits by repeating their bits (1 -> 255 at 1 bit,
    3 -> 255 at 2: ``v * 255 // (2**depth - 1)``), and every count read scaled. Undone exactly
    (in place: OpenCV's array), and only where the bytes are so scaled: a value past the depth's
    top is one (none is where a libpng leaves them packed, unscaled)."""
    depth = header["depth"]
    if header["colour"] != 0 or depth >= 8 or not grey.size or int(grey.max()) < 1 << depth:
        return grey
    grey //= 255 // ((1 << depth) - 1)  # 255, 85, 17: bit replication is this multiple
    return grey


# -- DICOM ----------------------------------------------------------------------------------------
def _decodable_syntaxes() -> dict:
    """The transfer syntaxes read: those pydicom decodes with nothing beyond itself and numpy
    (uncompressed, little and big endian, deflated; RLE Lossless), and JPEG, JPEG-LS, JPEG 2000
    and HTJ2K, decoded by imagecodecs (a dependency: :mod:`radiokit.io._codecs`), never by
    whichever pydicom plugins happen to be installed, so that a file reads the same on every
    machine. Others (JPEG 2000 multi-component, JPIP, MPEG, HEVC) are refused by name."""
    from pydicom import uid

    return {
        uid.ImplicitVRLittleEndian: "uncompressed",
        uid.ExplicitVRLittleEndian: "uncompressed",
        uid.ExplicitVRBigEndian: "uncompressed",
        uid.DeflatedExplicitVRLittleEndian: "deflated",
        uid.RLELossless: "RLE Lossless",
    } | dict.fromkeys(compressed_syntaxes(), "compressed")


def _number(value, default):
    """A DICOM DS/IS value (or a multi-value's first) as a Python number, ``default`` if absent."""
    if value is None or value == "":
        return default
    if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
        value = value[0]
    number = float(value)
    return int(number) if number.is_integer() else number


def _tag_number(path, ds, tag: str, default):
    """``tag``'s value as :func:`_number` reads it; one that is no number is refused naming the tag
    (float()'s own line, "could not convert string to float", named neither it nor the file's part)."""
    try:
        return _number(ds.get(tag), default)
    except (TypeError, ValueError) as exc:
        raise FormatError(path, f"a DICOM file whose {tag} is not a number ({exc})") from None


def _check_not_cut(path, ds) -> None:
    """Refuse, as truncated, a DICOM whose last element (or whose file meta) runs past the file's
    end. Why: pydicom keeps the elements it read and drops a cut one without a word, and a file
    cut before its pixel data was called "a report, structured data or a header only". The
    elements' offsets are pydicom's (read, not yet decoded): an element already decoded (the
    SpecificCharacterSet, a sequence) or of undefined length says nothing of where it ends, and is
    passed over (giving up there missed every archive's cut file: review s56rvoff); a deflated
    dataset's offsets are in its inflated bytes, and say nothing of the file."""
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    meta = getattr(ds, "file_meta", None) or {}
    if meta.get("TransferSyntaxUID") == DeflatedExplicitVRLittleEndian:
        return  # (its elements' offsets are in its inflated bytes, not the file's)
    size = os.path.getsize(path)
    group = meta.get("FileMetaInformationGroupLength")
    ends = [132 + 12 + int(group)] if group is not None and getattr(ds, "preamble", None) is not None else []
    for tag in ds.keys():
        item = ds.get_item(tag)
        tell, length = getattr(item, "value_tell", None), getattr(item, "length", None)
        if tell is None or length is None or length == 0xFFFFFFFF:
            continue  # (its own end unknown; the others' offsets are the file's all the same)
        ends.append(tell + length)
    if ends and max(ends) > size:
        raise FormatError(
            path,
            f"a DICOM file whose elements run to byte {max(ends)} of a {size}-byte file, cut before its pixel data: "
            "truncated",
        )


def _decodable_syntax(path, ds):
    """The transfer syntax of ``ds``, refused in one line where there are no pixels to decode or
    pydicom cannot decode them alone (:func:`_decodable_syntaxes`)."""
    if "PixelData" not in ds:
        other = [k for k in ("FloatPixelData", "DoubleFloatPixelData") if k in ds]
        _check_not_cut(path, ds)
        if "SpectroscopyData" in ds:  # (its Rows and Columns are a voxel grid, not a cut image's)
            raise FormatError(
                path, "a DICOM file of SpectroscopyData (MR spectra, not an image), which radiokit does not read"
            )
        what = f"its pixels are {other[0]}, which radiokit does not read" if other else "it has no pixel data"
        if not other and "Rows" in ds and "Columns" in ds:
            # (a cut at an element's boundary leaves a shorter file of whole elements)
            raise FormatError(
                path,
                f"a DICOM file, but {what}, though its header describes a {ds.Rows}x{ds.Columns} image: "
                "truncated before its pixels, or they were removed",
            )
        raise FormatError(path, f"a DICOM file, but {what} (a report, structured data or a header only)")
    syntax = ds.file_meta.get("TransferSyntaxUID") if hasattr(ds, "file_meta") else None
    if syntax is None:
        raise FormatError(
            path, "a DICOM file without a TransferSyntaxUID in its file meta: its pixels' encoding is unknown"
        )
    syntaxes = _decodable_syntaxes()
    if syntax not in syntaxes:
        # (pydicom's names say "Lossless" of every lossless syntax; the others are, or may be, lossy)
        lossy = " (lossy, or may be: not the detector's counts)" if "Lossless" not in syntax.name else ""
        raise FormatError(
            path,
            f"a DICOM file compressed as {syntax.name} ({syntax}){lossy}, which radiokit does not decode: it reads "
            "uncompressed, deflated, RLE, JPEG, JPEG-LS, JPEG 2000 and HTJ2K DICOM; decompress it (gdcmconv --raw)",
        )
    return syntax


def _syntax_found(ds) -> bool:
    """Give a dataset read without its file meta the transfer syntax pydicom found its elements
    in (its decoders need one), and say whether it had to."""
    from pydicom import uid
    from pydicom.dataset import FileMetaDataset

    if "TransferSyntaxUID" in getattr(ds, "file_meta", {}) or "PixelData" not in ds:
        return False
    implicit, little = ds.original_encoding
    ds.file_meta = getattr(ds, "file_meta", None) or FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = (
        uid.ImplicitVRLittleEndian if implicit else uid.ExplicitVRLittleEndian if little else uid.ExplicitVRBigEndian
    )
    return True


def _frame_count(path, ds) -> int:
    """NumberOfFrames as a count: absent, empty or 0 (invalid; pydicom assumes 1) is one frame,
    and the dataset is told so (pydicom warned at each decode, naming no file; the pixel data's
    length is checked against it next); a negative or fractional value is refused in one line
    (-2 reached numpy as "negative dimensions are not allowed")."""
    value = ds.get("NumberOfFrames")
    try:
        number = _number(value, 0)
    except (TypeError, ValueError):
        number = None
    if number == 0:
        if "NumberOfFrames" in ds:
            ds.NumberOfFrames = 1
        return 1
    if not isinstance(number, int) or number < 0:
        raise FormatError(path, f"a DICOM file whose NumberOfFrames {value} is not a count of frames")
    return number


def _file_meta_end(path) -> tuple[int, str | None]:
    """Where a DICOM file's dataset begins (past its preamble and its file meta group, whose
    elements are explicit VR little endian: PS3.10 7.1, or implicit VR where a writer erred, as
    pydicom reads them) and the group's TransferSyntaxUID (None where there is none, or the group
    cannot be walked: pydicom then says what is wrong)."""
    long_lengths = {b"OB", b"OD", b"OF", b"OL", b"OV", b"OW", b"SQ", b"SV", b"UC", b"UN", b"UR", b"UT", b"UV"}
    with open(path, "rb") as fh:
        pos = 132 if fh.read(132)[128:132] == b"DICM" else 0
        syntax = None
        while True:
            fh.seek(pos)
            head = fh.read(12)
            if len(head) < 8 or struct.unpack_from("<H", head)[0] != 2:
                return pos, syntax
            element, vr = struct.unpack_from("<H2s", head, 2)
            if not (vr.isalpha() and vr.isupper()):  # implicit VR, as a writer may (pydicom reads it)
                start, length = pos + 8, struct.unpack_from("<I", head, 4)[0]
            elif vr in long_lengths:
                if len(head) < 12:
                    return pos, None
                start, length = pos + 12, struct.unpack_from("<I", head, 8)[0]
            else:
                start, length = pos + 8, struct.unpack_from("<H", head, 6)[0]
            if element == 0x0010:
                fh.seek(start)
                syntax = fh.read(min(length, 64)).rstrip(b"\0 ").decode("ascii", "replace")
            pos = start + length


# CPython's zlib.decompress writes its output into blocks of these sizes (then 256 MiB each),
# and joins them into one bytes object at the end (Include/internal/pycore_blocks_output_buffer.h)
_ZLIB_BLOCKS = tuple(k * 2**10 for k in (32, 64, 256)) + tuple(
    m * 2**20 for m in (1, 4, 8, 16, 16, 32, 32, 32, 32, 64, 64, 128, 128, 256)
)


def _inflated_held(inflated: int) -> int:
    """What ``zlib.decompress`` holds at its peak to give ``inflated`` bytes: the blocks it wrote
    them into (the last one part-filled) and their join (benchmarks/README.md: 1.00 of the peak
    traced at pydicom's open)."""
    blocks = 0
    for size in _ZLIB_BLOCKS:
        if blocks >= inflated:
            break
        blocks += size
    if blocks < inflated:
        blocks += -(-(inflated - blocks) // _ZLIB_BLOCKS[-1]) * _ZLIB_BLOCKS[-1]
    return blocks + inflated


def _check_inflated(path, budget) -> None:
    """Refuse a deflated DICOM whose dataset inflates past the budget, or out of all proportion
    to its bytes (:func:`check_proportion`, where no budget was given), or whose deflate stream is
    cut, before pydicom reads it. Why: pydicom inflates the whole dataset as it opens the file
    (zlib.decompress of the rest of it: its output blocks, then their join, :func:`_inflated_held`,
    beside the compressed bytes), before any header can be judged: an 8 KB file of a 2000 x 2000
    frame of zeros took 21 MiB under a 2 MiB budget, and deflate's 1:1000 made a 16 MB file 16 GB.
    The stream is inflated here a piece at a time, counted and dropped (an extra pass over a
    deflated file's bytes, the one syntax that needs it), and stops once past the budget."""
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    try:
        start, syntax = _file_meta_end(path)
    except (OSError, struct.error):
        return
    if syntax != DeflatedExplicitVRLittleEndian:
        return
    stored, inflated, piece = os.path.getsize(path) - start, 0, 2**20
    inflater, limit = zlib.decompressobj(-zlib.MAX_WBITS), memory_budget(budget)

    def count(data: bytes) -> None:
        nonlocal inflated
        while True:
            out = len(inflater.decompress(data, piece))
            inflated += out
            if stored + _inflated_held(inflated) > limit:  # (counted no further: a bomb's whole size is not needed)
                raise FormatError(
                    path,
                    f"a deflated DICOM file whose dataset inflates past {human_bytes(inflated)}, which pydicom holds "
                    f"two to three times over as it opens it, beside its {human_bytes(stored)}: over the memory "
                    f"budget of {human_bytes(limit)} (a decompression bomb, or raise {BUDGET_ENV})",
                )
            data = inflater.unconsumed_tail
            if inflater.eof or (not data and out < piece):
                return

    try:
        with open(path, "rb") as fh:
            fh.seek(start)
            while not inflater.eof and (data := fh.read(piece)):
                count(data)
    except zlib.error as exc:
        raise FormatError(path, f"a deflated DICOM file whose deflate stream is corrupt ({exc})") from None
    if not inflater.eof:
        raise FormatError(
            path,
            f"a deflated DICOM file whose deflate stream ends before its end marker ({os.path.getsize(path)} "
            "bytes): truncated",
        )
    # (judged once the whole is counted, so that its figures are the dataset's, not a piece's)
    # (the budget it suggests: the open's inflate, and the read's inflated dataset and element beside the stack)
    needs = stored + _inflated_held(inflated) + 2 * inflated
    check_proportion(path, "its deflated dataset", inflated, inflated, stored, "deflate", budget, needs)


def _read_dataset(path, budget=None):
    """The dataset, its pixels deferred, and whether its transfer syntax had to be found (no
    file meta). Without the preamble and b'DICM' (older tools, ACR-NEMA-era datasets) pydicom
    reads a file where told to (force=True), as a user would expect radiokit to; sniff let such a
    .dcm through only where its first bytes are a DICOM element's group."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    with open(path, "rb") as fh:
        bare = fh.read(132)[128:132] != b"DICM"
    _check_inflated(path, budget)
    try:
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            # values over 1 KB (the pixels) are read when asked for, not now
            ds = pydicom.dcmread(path, defer_size="1 KB", force=bare)
    except (InvalidDicomError, EOFError, OSError, ValueError, struct.error) as exc:
        raise FormatError(path, f"not a valid DICOM file: {exc}") from None
    # A file cut short inside its encapsulated (compressed, RLE) pixel element: pydicom warns
    # "End of file reached before delimiter" and drops the element, which then read as a file of
    # no pixels at all, "a report", after a second line of pydicom's own.
    cut = [w for w in said if "End of file reached before delimiter" in str(w.message)]
    if cut and "PixelData" not in ds:
        raise FormatError(
            path,
            "a DICOM file that ends inside its encapsulated pixel data, before the sequence delimiter "
            f"that closes it ({os.path.getsize(path)} bytes): truncated",
        )
    for w in said:  # the others as they were, to the filters of whoever reads
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return ds, bare and _syntax_found(ds)


def open_dicom(path, budget) -> tuple[object, dict, dict]:
    """The dataset (pixel data deferred, not read), the frames' geometry and ``meta``; refused in
    one line where its pixels are absent, of a kind a radiograph is not (colour, float), in a
    transfer syntax pydicom cannot decode alone, or past the budget."""
    ds, found = _read_dataset(path, budget)
    syntax = _decodable_syntax(path, ds)
    rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
    n = _frame_count(path, ds)
    samples = int(ds.get("SamplesPerPixel", 1) or 1)
    allocated = int(ds.get("BitsAllocated", 0) or 0)
    stored = int(ds.get("BitsStored", allocated) or allocated)
    signed = int(ds.get("PixelRepresentation", 0) or 0) == 1
    photometric = str(ds.get("PhotometricInterpretation", "")).strip()
    if not rows or not cols or allocated not in (8, 16, 32):
        raise FormatError(
            path,
            f"a DICOM file whose pixels are {rows}x{cols} of {allocated} bits allocated: not an image radiokit reads",
        )
    _check_photometric(path, samples, photometric)
    _check_high_bit(path, ds, stored)
    if "ModalityLUTSequence" in ds:
        raise FormatError(
            path, "a DICOM image with a Modality LUT Sequence (a table, not a slope), which radiokit does not apply"
        )
    dtype = np.dtype(f"{'i' if signed else 'u'}{allocated // 8}")
    slope, intercept, rescale_type = _modality_lut(path, ds)
    _check_rescale(path, dtype, slope, intercept)
    if syntax in compressed_syntaxes():  # (a bomb said as one first: no budget given, it may pass a large one's)
        check_dicom_proportion(path, syntax, n, rows, cols, dtype, budget)
    held = _check_dicom_budget(path, ds, syntax, n, rows, cols, dtype, (slope, intercept), budget)
    _check_pixel_length(path, ds, syntax, n, rows * cols * dtype.itemsize)
    meta = {
        "n": n,
        "rows": rows,
        "cols": cols,
        "dtype": str(dtype),
        "transfer_syntax": f"{syntax.name} ({syntax}"
        + ("; no file meta: the encoding pydicom found)" if found else ")"),
        "photometric": photometric,
        "modality": str(ds.get("Modality", "")),
    }
    meta.update(_bit_depth_meta(stored, allocated, signed))
    if (slope, intercept) != (1, 0):
        # the Modality LUT the file states: values = stored * slope + intercept (value_scaling
        # judges saturation on the stored counts recovered from them)
        meta["dicom_rescale"] = {
            "slope": slope,
            "intercept": intercept,
            "type": rescale_type,
        }
        meta["stored_dtype"] = str(dtype)
    if photometric == "MONOCHROME1":
        meta["photometric_note"] = "MONOCHROME1: the minimum value is white; read as stored, not inverted"
        _say_inverted(path)
    if (padding := _padding_note(ds, slope, intercept)) is not None:
        meta["pixel_padding"] = padding
    meta.update(_dicom_pitch(path, ds))
    if syntax in compressed_syntaxes() and (lossy := say_lossy_dicom(path, ds, syntax)):
        meta["lossy"] = lossy
    geometry = {"n": n, "rows": rows, "cols": cols, "dtype": dtype, "slope": slope, "intercept": intercept}
    geometry["bits_stored"] = stored
    geometry |= held | {"budget": budget}  # (a frame's own decode is checked too)
    return ds, geometry, meta


def _check_dicom_budget(path, ds, syntax, n: int, rows: int, cols: int, dtype, rescale, budget) -> dict:
    """Refuse a DICOM whose frames, read one at a time, would hold more than the budget
    (:func:`dicom_read_bytes`: its pixel element and one frame's decoding); what it holds
    throughout, one frame's decoding, a rescaled frame's bytes and the stack read() adds, for
    :meth:`FrameSource.read_all`'s check and each frame's own as decoded. Why the stack apart:
    open_frames never holds it, and a DICOM that streams within the budget was refused for it
    (review s56rvoff)."""
    from pydicom.uid import RLELossless

    encapsulated = syntax in compressed_syntaxes() or syntax == RLELossless
    stream = _largest_frame_stream(path, ds, n) if encapsulated else None
    held, work, rescaled = dicom_read_bytes(path, syntax, n, rows, cols, dtype, rescale, stream)
    stack = n * rows * cols * rescaled_dtype(dtype, *rescale).itemsize
    check_budget(
        path,
        held - stack + work + rescaled,
        f"its header's {n} frame(s) of {rows}x{cols} {dtype}: its pixel element and one frame's decoding "
        f"({syntax.name})",
        budget,
    )
    return {"held": held - stack, "work": work, "rescale_bytes": rescaled, "stack": stack, "stack_held": 0}


def _largest_frame_stream(path, ds, n: int) -> int:
    """A bound on the largest frame's codestream in an encapsulated pixel element, before any
    frame is read: the Extended Offset Table's lengths where given; else the fragments' lengths,
    their item headers walked in the element (pydicom holds it from the open): one fragment a
    frame, its own; the Basic Offset Table's starts, the spans between them; without one, the
    runs of fragments each closed by an end marker, as pydicom finds the frames; else all of them
    (one frame may hold every fragment). Why: bounded by the file's size, a 6-frame JPEG counted
    6 streams, three times over (it holds three copies of the one it decodes), and a file that
    fits was refused (two fragments a frame without an offset table: review s56rvoff).
    A frame's own stream is held to the budget again as it is decoded."""
    size = os.path.getsize(path)
    lengths = ds.get("ExtendedOffsetTableLengths")
    if lengths and len(lengths) >= 8 * n:
        return min(size, int(np.frombuffer(lengths[: 8 * n], "<u8").max()))
    value = getattr(ds.get_item("PixelData"), "value", None)  # (pydicom reads an encapsulated element at open)
    if n == 1 or not isinstance(value, (bytes, bytearray)):
        return size
    table, fragments, ended, pos = None, [], [], 0
    while pos + 8 <= len(value):
        group, element, length = struct.unpack_from("<HHI", value, pos)
        if (group, element) != (0xFFFE, 0xE000) or length == 0xFFFFFFFF:
            break  # the sequence's delimiter (or damage, refused when that frame is read)
        if table is None:
            table = value[pos + 8 : pos + 8 + min(length, 4 * n + 4)]
        else:
            fragments.append(length)
            # pydicom's rule without an offset table: a frame ends at a fragment whose last 10
            # bytes hold an end marker (EOI, EOC: 0xFFD9; a fragment's padding after it)
            ended.append(b"\xff\xd9" in value[max(pos + 8, pos + 8 + length - 10) : pos + 8 + length])
        pos += 8 + length
    if not fragments:
        return size
    if len(fragments) == n:
        return max(fragments)
    starts = np.frombuffer(table[: 4 * (len(table) // 4)], "<u4").astype(np.int64) if table else np.array([])
    if len(starts) == n and np.all(np.diff(starts) > 0):
        ends = np.append(starts[1:], sum(8 + length for length in fragments))
        return min(size, int((ends - starts).max()))
    if not table and len(fragments) > n and sum(ended) >= n:
        # (the fragments after the last marker are a frame too, as pydicom reads them)
        frames, frame = [], 0
        for length, last in zip(fragments, ended, strict=True):
            frame += length
            if last:
                frames, frame = frames + [frame], 0
        return max(frames + [frame])
    return min(size, sum(fragments))


def dicom_read_bytes(
    path, syntax, n: int, rows: int, cols: int, dtype, rescale=(1, 0), stream=None
) -> tuple[int, int, int]:
    """What ``read()`` of a DICOM holds at its peak, in three parts: what it keeps throughout (the
    pixel element's value, which pydicom reads whole at the first frame, and the stack of every
    frame as read), one frame's decoding (bounded before any is read: its codestream by the file's
    bytes, or ``stream``: :func:`_largest_frame_stream`), and a rescaled frame (the Modality LUT's
    values, beside the stored ones). Why: the
    frames alone were counted, and reading took 2.5 to 6.5 times them (benchmarks/README.md,
    bench_dicom_decode_memory.py; a 2240 x 2240 frame, 9.6 MiB, 25 to 62 MiB)."""
    from pydicom import uid

    samples = rows * cols
    frame = samples * np.dtype(dtype).itemsize
    out = rescaled_dtype(dtype, *rescale).itemsize * samples
    size = os.path.getsize(path)
    stream = size if stream is None else stream
    if syntax in compressed_syntaxes():
        element = size
        work = frame_decode_bytes(syntax_header(syntax, rows, cols, dtype), stream)
    elif syntax == uid.RLELossless:
        # pydicom's PackBits decoder: the frame's fragments joined and each segment's slice of
        # them (2 x the stream, bounded by the file), its bytearray of the frame and the array
        # made of it (2 frames), a segment decoded (a byte a sample, its bytearray grown by up to
        # an eighth more) and the slice of it put in place (a byte a sample)
        element, work = size, 2 * stream + 2 * frame + samples * 9 // 8 + samples
    elif syntax == uid.DeflatedExplicitVRLittleEndian:
        # the whole dataset inflated into one buffer, which pydicom keeps, and the element copied
        # out of it; then a frame's array
        element, work = 2 * n * frame, frame
    elif syntax == uid.ExplicitVRBigEndian:
        # the element, the frame's array copied out of it, and that array in the machine's order
        element, work = n * frame, 2 * frame
    else:
        element, work = n * frame, frame  # the element, and the frame's array copied out of it
    rescaled = out if tuple(rescale) != (1, 0) else 0
    return element + n * out, work, rescaled


def _lut_of(path, item) -> tuple:
    """``item``'s RescaleSlope, RescaleIntercept (1 and 0 where absent) and RescaleType (None)."""
    slope, intercept = (
        _tag_number(path, item, tag, default) for tag, default in (("RescaleSlope", 1), ("RescaleIntercept", 0))
    )
    return slope, intercept, str(item.get("RescaleType", "")) or None


def _modality_lut(path, ds) -> tuple:
    """The Modality LUT's slope, intercept and type: at the top level, else where an enhanced
    multi-frame image keeps it, in its functional groups' Pixel Value Transformation (shared, or
    the same in every frame's). Why: pydicom's apply_modality_lut reads the top level alone, and
    an enhanced image's stored values read as its values without a word. One stack has one
    scale: frames whose transformations differ are refused."""
    if "RescaleSlope" in ds or "RescaleIntercept" in ds:
        return _lut_of(path, ds)

    def transformation(group):
        sequence = group.get("PixelValueTransformationSequence") if group is not None else None
        return sequence[0] if sequence else None

    shared = ds.get("SharedFunctionalGroupsSequence")
    if (found := transformation(shared[0] if shared else None)) is not None:
        return _lut_of(path, found)
    frames = ds.get("PerFrameFunctionalGroupsSequence") or []
    luts = {_lut_of(path, lut) if (lut := transformation(group)) is not None else (1, 0, None) for group in frames}
    if len(luts) > 1:
        shown = ", ".join(f"{s:g} x + {b:g}" for s, b, _ in sorted(luts, key=lambda t: t[:2])[:4])
        raise FormatError(
            path,
            f"an enhanced DICOM image whose frames' RescaleSlope/RescaleIntercept differ ({shown}): one stack of "
            "frames has one scale; split it into one file per scale",
        )
    return luts.pop() if luts else (1, 0, None)


def _padding_note(ds, slope=1, intercept=0) -> str | None:
    """What a PixelPaddingValue (to PixelPaddingRangeLimit) says, for ``info``: those pixels hold
    no image (outside the collimated field), though they are read as stored, as pydicom reads
    them. Why: a 12-bit DX padded with 4095 had its padding counted as saturated, and nothing said so.
    The values are stored ones: with a Modality LUT, what its pixels read as is given beside them
    (the stored value alone named a value no pixel read holds: review s56rvoff)."""
    value = ds.get("PixelPaddingValue")
    if value is None or value == "":
        return None
    limit = ds.get("PixelPaddingRangeLimit")
    ranged = limit not in (None, "")
    ends = [value, limit] if ranged else [value]
    span = "PixelPaddingValue " + " to ".join(str(v) for v in ends)
    if (slope, intercept) != (1, 0) and all(isinstance(v, (int, float)) for v in ends):
        span += " (" + " to ".join(f"{v * slope + intercept:g}" for v in ends) + " as read, rescaled)"
    return (
        f"{span}: pixels of {'those values' if ranged else 'that value'} hold no image (outside the collimated "
        "field); read as stored, and counted in the range and saturation above"
    )


def _check_photometric(path, samples: int, photometric: str) -> None:
    """Refuse an image that is not one channel of counts whose meaning (lowest value black or white) is said."""
    if samples == 1 and not photometric:  # (type 1: a writer left it blank)
        raise FormatError(
            path,
            "a DICOM image of one sample a pixel with no PhotometricInterpretation: whether its lowest value shows "
            "black (MONOCHROME2) or white (MONOCHROME1) is not said; set it (pydicom: ds.PhotometricInterpretation)",
        )
    if samples != 1 or photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise FormatError(
            path,
            f"a {photometric or 'colour'} DICOM image ({samples} samples per pixel): a radiograph is one channel of "
            "counts (MONOCHROME1 or MONOCHROME2)",
        )


def _check_high_bit(path, ds, stored: int) -> None:
    """Refuse counts that are not the low BitsStored bits of their word (HighBit other than
    BitsStored - 1: ACR-NEMA's layout, which the DX, CR and most image IODs forbid). Why: pydicom
    reads the low BitsStored bits whatever HighBit says, and a 12-bit count in a word's top bits
    read as (count << 4) & 0xFFF, every value wrong, without a word."""
    value = ds.get("HighBit")
    if value in (None, "") or int(value) == stored - 1:
        return
    high = int(value)
    # (a writer that kept its counts in the low bits and mislabelled HighBit is told apart by the
    # words, not the header: shifted, such counts would lose their low bits)
    advice = (
        f"if its counts are in each word's top bits (its low {high + 1 - stored} bits zero), shift each word right "
        f"by {high + 1 - stored} bits and set HighBit {stored - 1}; with every word below {1 << stored}, its "
        f"counts are in the low bits and HighBit alone is wrong: set HighBit {stored - 1}"
        if high >= stored
        else "a HighBit below them is no layout: its header is wrong"
    )
    raise FormatError(
        path,
        f"a DICOM file whose HighBit {high} is not its BitsStored {stored} less one: its counts may not be the low "
        f"bits of each word, where DICOM images keep them and pydicom and radiokit read them; {advice}",
    )


def _bit_depth_meta(stored: int, allocated: int, signed: bool) -> dict:
    """What the saturation judgement takes as the ADC's range, from BitsStored."""
    if signed:
        # two's complement in BitsStored bits (pydicom extends the sign): the ADC's range is
        # -2**(stored - 1)..2**(stored - 1) - 1, whatever the word (radiokit.calibrate.declared_range);
        # judged as unsigned, a signed 12-bit image's clip at 2047 was never saturated (against 4095)
        return {"bit_depth": stored, "bit_depth_signed": True}
    if stored < allocated:
        return {"bit_depth": stored}  # the saturation judgement's top, as a TIFF's BitsPerSample below its word
    # stated, but of the whole word (writers state 16 of 12- and 14-bit panels): the level is
    # judged from the values as a TIFF's, and info says what the file did state
    return {"bit_depth_word": f"BitsStored {stored} of BitsAllocated {allocated}"} if allocated > 8 else {}


def _check_pixel_length(path, ds, syntax, n: int, frame: int) -> None:
    """Refuse uncompressed pixel data shorter than its header declares. Why: such a file opened and
    each frame then failed at its decode, and a file of a few hundred bytes declaring a gigabyte of
    frames had its stack allocated first. The element's length is read, not its value (deferred);
    an encapsulated (RLE) element's length is undefined: the file's size bounds what it may
    declare, and its frames are judged as decoded."""
    from pydicom.uid import RLELossless

    declared = n * frame
    if syntax in compressed_syntaxes():  # encapsulated: each frame's codestream is checked before decoding
        return
    if syntax == RLELossless:
        # PackBits encodes at most 128 bytes in 2: a file under 1/64 of what it declares cannot
        # hold it (its fragments' lengths would need the pixels read to sum)
        if declared > 64 * os.path.getsize(path):
            raise FormatError(
                path,
                f"a DICOM file of {os.path.getsize(path)} bytes declaring {declared} bytes of RLE Lossless "
                "pixels, more than RLE can encode in it (64:1 at most): truncated, or its header is wrong",
            )
        return
    item = ds.get_item("PixelData")
    length = getattr(item, "length", None)
    if length is None:  # a DataElement already read (a small file): its bytes are at hand
        length = len(item.value or b"")
    if length != 0xFFFFFFFF and length - declared >= frame:
        # whole frames past those declared (NumberOfFrames absent or wrong): pydicom returned them
        # all where one was asked for (allow_excess_frames), a 3-D "frame"; or they were lost
        declared_as = ds.get("NumberOfFrames")
        raise FormatError(
            path,
            f"a DICOM file with {length} bytes of pixel data, {length // frame} frames of {frame} bytes, where its "
            f"NumberOfFrames ({'absent: 1' if declared_as is None else declared_as}) declares {n}: its header is wrong",
        )
    if length == 0xFFFFFFFF or length >= declared:
        return
    raise FormatError(
        path,
        f"a DICOM file with {length} bytes of pixel data where its header declares {declared} "
        "(Rows x Columns x NumberOfFrames x BitsAllocated): truncated, or its header is wrong",
    )


def _check_rescale(path, dtype, slope, intercept) -> None:
    """Refuse a Modality LUT that is no slope of these values, as a CF packing's is: a slope of 0
    (every pixel the intercept), NaN or inf (frames of NaN), or one that takes the stored type's
    range past float64's (frames of inf, and numpy's overflow warnings naming no file)."""
    import math

    if not (math.isfinite(slope) and math.isfinite(intercept)):
        raise FormatError(
            path, f"a DICOM file whose RescaleSlope {slope} or RescaleIntercept {intercept} is not a finite number"
        )
    if slope == 0:
        raise FormatError(path, f"a DICOM file whose RescaleSlope is 0: every pixel would read as {intercept:g}")
    info = np.iinfo(dtype)
    ends = [float(info.min) * slope + intercept, float(info.max) * slope + intercept]
    if not all(math.isfinite(e) for e in ends):
        raise FormatError(
            path,
            f"a DICOM file whose RescaleSlope {slope:g} and RescaleIntercept {intercept:g} take its {dtype} values "
            "past float64's range: not a Modality LUT of these values",
        )


def _say_inverted(path) -> None:
    """Warn that a MONOCHROME1 file's values are read as stored, and what they mean."""
    said = InvertedWarning(
        f"{shown(path)}: MONOCHROME1: its values are read as stored, not inverted; the file says its lowest value "
        "shows white (in a radiograph, higher values then mean less X-ray signal, not more)"
    )
    said.path = str(path)  # the command line shows it once per file, not at each of its opens
    warnings.warn(said, stacklevel=5)


#: Where an enhanced multi-frame image keeps each spacing: the functional group's sequence
_PITCH_GROUPS = {"ImagerPixelSpacing": "FramePixelDataPropertiesSequence", "PixelSpacing": "PixelMeasuresSequence"}


def _spacing_in_groups(path, ds, name: str):
    """``name``'s value where an enhanced multi-frame image keeps it (:data:`_PITCH_GROUPS`), and
    where: shared, else every frame's own; None where no group states it. Frames stating
    different ones (or some none) give a one-line warning and {"pixel_size_unusable": why}: one
    stack has one pitch, and any one would give some frames' lengths in mm wrong, while their
    counts are right (a pitch is optional, as an unusable one in any other file)."""

    def stated(group):
        sequence = group.get(_PITCH_GROUPS[name]) if group is not None else None
        value = sequence[0].get(name) if sequence else None
        return None if value in (None, "") else tuple(value)

    shared = ds.get("SharedFunctionalGroupsSequence")
    if (value := stated(shared[0] if shared else None)) is not None:
        return value, f"SharedFunctionalGroupsSequence > {_PITCH_GROUPS[name]}"
    values = {stated(group) for group in ds.get("PerFrameFunctionalGroupsSequence") or []}
    if values == {None} or not values:
        return None
    if len(values) > 1:
        shown_ = ", ".join("none" if v is None else "\\".join(str(x) for x in v) for v in sorted(values, key=str)[:4])
        return usable_pixel_sizes(
            path, f"DICOM's {name}", {}, [f"its frames' {name} differ ({shown_} mm): one stack has one pitch"]
        )
    return values.pop(), f"PerFrameFunctionalGroupsSequence > {_PITCH_GROUPS[name]}, the same in every frame"


def _dicom_pitch(path, ds) -> dict:
    """``x_pixel_size`` / ``y_pixel_size`` (metres) from ImagerPixelSpacing (the detector's pitch,
    at its face), else PixelSpacing (in the patient: the pitch over the magnification, where the
    writer corrected for it). Both are [row spacing, column spacing] in mm: rows are y. Each at
    the top level, else in an enhanced image's functional groups (:func:`_spacing_in_groups`):
    there it was ignored, and such frames measured in pixels without a word."""
    for name in ("ImagerPixelSpacing", "PixelSpacing"):
        value, where = ds.get(name), None
        if value is None or value == "":
            found = _spacing_in_groups(path, ds, name)
            if isinstance(found, dict):  # (frames differing: said, and no pitch)
                return found
            if found is None:
                continue
            value, where = found
        try:
            row, col = (float(v) * 1e-3 for v in value)
        except (TypeError, ValueError):
            return usable_pixel_sizes(path, f"DICOM's {name}", {}, [f"{name} {value!r} is not two numbers"])
        out = usable_pixel_sizes(path, f"DICOM's {name}", {"x_pixel_size": col, "y_pixel_size": row})
        out["pixel_size_source"] = name  # (correct's stack rule reads the name alone)
        if where is not None and "pixel_size_unusable" not in out:
            out["pixel_size_where"] = where
        return out
    return {}


def dicom_frame(path, ds, geometry: dict, i: int) -> np.ndarray:
    """Frame ``i`` as stored (pydicom's decoders: the file's byte order to the machine's), with the
    Modality LUT the file states applied: integers stay integers where slope and intercept are
    integers and the values fit int32, else float64 (exact for every 32-bit count)."""
    from pydicom.pixels import pixel_array

    # unsigned words are masked to BitsStored here, for every syntax alike (:func:`_stored_bits`)
    own = {"correct_unused_bits": False} if geometry["dtype"].kind == "u" else {}
    if ds.file_meta.TransferSyntaxUID in compressed_syntaxes():
        stored = compressed_frame(path, ds, geometry, i)
    elif geometry["n"] > 1:
        stored = pixel_array(ds, index=i, **own)
    else:
        stored = pixel_array(ds, **own)
    stored = np.asarray(stored).astype(geometry["dtype"].newbyteorder("="), copy=False)
    stored = _stored_bits(path, stored, geometry, i)
    if stored.shape != (geometry["rows"], geometry["cols"]):
        # pydicom returns every frame its data holds where fewer are declared (allow_excess_frames)
        raise FormatError(
            path,
            f"frame {i} decoded as {stored.shape}, not one of {geometry['rows']}x{geometry['cols']}: its pixel data "
            f"holds more frames than its NumberOfFrames ({ds.get('NumberOfFrames', 'absent: 1')}) declares",
        )
    return rescaled(stored, geometry["slope"], geometry["intercept"])


def _stored_bits(path, words: np.ndarray, geometry: dict, i: int) -> np.ndarray:
    """Unsigned ``words``' low BitsStored bits, the pixel value DICOM defines (PS3.5 8.1.1: the
    bits above HighBit are no part of it); where any word had more, one warning a file, naming
    it. Why: pydicom masked uncompressed words without a word, and a compressed frame's decoded
    ones were kept (its stream 16-bit for 12-bit counts, as CharLS and OpenJPEG write uint16: the
    codestream's precision is the word's, not the count's), so one image read two ways. Masked,
    not refused: such bits are an overlay ACR-NEMA-era writers kept there, or a detector wider
    than its BitsStored (its values then wrap), and which is not in the file; its counts are
    read, and the warning says both. Signed words are sign-extended from BitsStored's top bit on
    both paths already (pydicom's, and :func:`compressed_frame`)."""
    stored = geometry.get("bits_stored", 0)
    if words.dtype.kind != "u" or not 0 < stored < words.dtype.itemsize * 8 or words.size == 0:
        return words
    top = (1 << stored) - 1
    peak = int(words.max())  # (no temporary of the frame's size where none is above: the common case)
    if peak <= top:
        return words
    if not geometry.get("bits_above_said"):
        geometry["bits_above_said"] = True  # once per open file, not once per frame
        count = int(np.count_nonzero(words > top))
        said = BitDepthWarning(
            f"{shown(path)}: {count} of frame {i}'s {words.size} words have bits set above its BitsStored {stored} "
            f"(values up to {peak} in the words): read as their low {stored} bits, the pixel value DICOM defines "
            f"(PS3.5 8.1.1), as uncompressed words are read; the bits above are an overlay, or its detector's counts "
            f"are wider and its BitsStored is wrong (its values then wrapped)"
        )
        said.path = str(path)  # the command line shows it once per file, not at each of its opens
        warnings.warn(said, stacklevel=5)
    if not words.flags.writeable:
        return words & words.dtype.type(top)
    words &= words.dtype.type(top)  # in place: no second frame beside the budget's count
    return words


def rescaled_dtype(dtype, slope, intercept) -> np.dtype:
    """The values' type after ``stored * slope + intercept``: the stored type where they are 1 and 0,
    int32 where both are integers and every stored value's image fits it, else float64."""
    dtype = np.dtype(dtype)
    if (slope, intercept) == (1, 0):
        return dtype.newbyteorder("=")
    if isinstance(slope, int) and isinstance(intercept, int):
        info = np.iinfo(dtype)
        ends = [info.min * slope + intercept, info.max * slope + intercept]
        i32 = np.iinfo(np.int32)
        if i32.min <= min(ends) and max(ends) <= i32.max:
            return np.dtype(np.int32)
    return np.dtype(np.float64)


def rescaled(stored: np.ndarray, slope, intercept) -> np.ndarray:
    out = rescaled_dtype(stored.dtype, slope, intercept)
    if out == stored.dtype:
        return stored
    values = stored.astype(out)  # in place from here: one frame of the values beside the stored (the budget's)
    values *= out.type(slope)
    values += out.type(intercept)
    return values
