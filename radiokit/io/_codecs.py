"""JPEG (baseline, extended 12-bit, lossless), JPEG-LS and JPEG 2000 (HTJ2K included) codestreams,
in a file of their own (.jpg, .jls, .j2k, .jp2) or a compressed DICOM's frames, decoded by imagecodecs.

A codestream states its own image size (JPEG's SOF marker, ITU T.81 B.2.2; JPEG 2000's SIZ,
T.800 A.5.1), and its decoder allocates that size whatever the container says: a 2 KB JPEG may
declare 60000 x 60000. The header is read first and held to the memory budget (a file), or to the
DICOM's own Rows x Columns (a frame), before anything is decoded.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from radiokit._names import shown
from radiokit.errors import FormatError
from radiokit.io._budget import check_budget, check_proportion

JPEG_MAGIC = b"\xff\xd8\xff"
J2K_MAGIC = b"\xff\x4f\xff\x51"  # SOC then SIZ: a bare JPEG 2000 codestream (.j2k, .j2c, .jph)
JP2_MAGIC = b"\x00\x00\x00\x0cjP  \r\n\x87\n"  # the JP2 signature box (.jp2, .jpx, .jph)


class LossyWarning(UserWarning):
    """The pixels were compressed lossily: what is read is the codec's approximation, not the counts."""


#: JPEG's frame headers (T.81 table B.1; JPEG-LS's SOF55, T.87): their process, and whether it is lossless
_SOF = {
    0xC0: ("baseline", False),
    0xC1: ("extended", False),
    0xC2: ("progressive", False),
    0xC3: ("lossless", True),
    0xC5: ("differential sequential", False),
    0xC6: ("differential progressive", False),
    0xC7: ("differential lossless", True),
    0xC9: ("extended, arithmetic", False),
    0xCA: ("progressive, arithmetic", False),
    0xCB: ("lossless, arithmetic", True),
    0xCD: ("differential sequential, arithmetic", False),
    0xCE: ("differential progressive, arithmetic", False),
    0xCF: ("differential lossless, arithmetic", True),
    0xF7: ("JPEG-LS", True),
}


def _jpeg_header(read, size: int) -> dict:
    """The frame header (SOF) of a JPEG or JPEG-LS stream read through ``read(offset, n)``, and
    for JPEG-LS its first scan's NEAR (0: lossless). Markers are walked by their lengths up to
    the first scan: APPn segments (EXIF, ICC) may come first, each up to 64 KB."""
    pos, out = 2, None
    while pos + 4 <= size:
        b = read(pos, 4)
        if b[0] != 0xFF:
            raise ValueError(f"no JPEG marker at byte {pos}")
        marker = b[1]
        if marker == 0xFF:  # a fill byte before a marker
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # TEM, RSTn: no length
            pos += 2
            continue
        if marker == 0xD9:
            break
        length = int.from_bytes(b[2:4], "big")
        if length < 2:
            raise ValueError(f"a JPEG segment of length {length} at byte {pos}")
        if marker in _SOF and out is None:
            p, h, w, c = (lambda s: (s[0], int.from_bytes(s[1:3], "big"), int.from_bytes(s[3:5], "big"), s[5]))(
                read(pos + 4, 6)
            )
            process, lossless = _SOF[marker]
            out = {"codec": "jpegls" if marker == 0xF7 else "jpeg", "process": process, "lossless": lossless}
            out.update(height=h, width=w, components=c, precision=p, signed=False)
        elif marker == 0xDA:
            if out is not None:
                out["scan"] = pos
            if out is not None and out["codec"] == "jpegls":
                scan = read(pos + 4, length - 2)
                near = scan[1 + 2 * scan[0]] if len(scan) > 1 + 2 * scan[0] else 0
                out["lossless"], out["near"] = near == 0, near
            break
        pos += 2 + length
    if out is None:
        raise ValueError("no frame header (SOF marker) before its first scan")
    return out


def _j2k_header(read, start: int, size: int) -> dict:
    """A JPEG 2000 codestream's SIZ (image size, components, their precision and sign) and its
    COD's wavelet: the irreversible 9/7 is lossy; the reversible 5/3 is lossless where every
    quality layer was kept (which no header says)."""
    siz = read(start, 43)
    if siz[:4] != J2K_MAGIC or len(siz) < 43:
        raise ValueError("no JPEG 2000 codestream (SOC, SIZ) where its header should be")
    be = lambda a, b: int.from_bytes(siz[a:b], "big")
    width, height = be(8, 12) - be(16, 20), be(12, 16) - be(20, 24)
    ssiz = siz[42]
    out = {"codec": "jpeg2k", "process": "JPEG 2000", "lossless": None, "width": width, "height": height}
    out.update(components=be(40, 42), precision=(ssiz & 0x7F) + 1, signed=bool(ssiz & 0x80))
    out["htj2k"] = bool(be(6, 8) & 0x4000)  # Rsiz's bit 14: HTJ2K (T.814)
    if not be(24, 28) or not be(28, 32):
        raise ValueError("a tile size of 0 in its SIZ")
    out["tiles"] = -(-(be(8, 12) - be(32, 36)) // be(24, 28)) * -(-(be(12, 16) - be(36, 40)) // be(28, 32))
    pos = start + 4 + be(4, 6)  # past SIZ, through the main header's marker segments to COD
    while pos + 4 <= size:
        b = read(pos, 4)
        if b[0] != 0xFF or b[1] == 0x90:  # SOT: the first tile, the main header over
            out["scan"] = pos
            break
        if b[1] == 0x52:  # COD: its SPcod's last byte is the wavelet (T.800 table A.20)
            cod = read(pos + 4, 10)
            if len(cod) == 10:  # 5/3: lossless only where no bit-plane was cut to a rate (no header says)
                out["lossless"] = None if cod[9] == 1 else False
                out["reversible"] = cod[9] == 1
        pos += 2 + int.from_bytes(b[2:4], "big")
    out["tiles_found"], end = _tiles_found(read, out.get("scan", size), size, out["tiles"])
    if end is not None:
        out["tile_parts_end"] = end
    if "reversible" in out:
        out["process"] += " (reversible 5/3)" if out["reversible"] else " (irreversible 9/7: lossy)"
    return out


def _tiles_found(read, pos: int, size: int, tiles: int) -> tuple[int, int | None]:
    """How many of the ``tiles`` a codestream declares have a tile-part, its SOT segments walked by
    their lengths (Psot, T.800 A.4.2) from the first, and where the last tile-part's length ends
    (None where it runs to the end: Psot 0, or one too short to be read). Why: OpenJPEG decodes a
    tile without one as zeros, without a word, and sets up every tile declared (its structures,
    not the image, are what a few bytes declaring tens of thousands of tiles cost:
    benchmarks/README.md); and the lengths must end at the end marker (EOC)."""
    found, end = set(), None
    while pos + 10 <= size:
        sot = read(pos, 10)
        if sot[:2] != b"\xff\x90":
            break
        tile, length = int.from_bytes(sot[4:6], "big"), int.from_bytes(sot[6:10], "big")
        if tile < tiles:
            found.add(tile)
        if length < 14:  # 0: the last tile-part, to the end; less than SOT and SOD: corrupt
            return len(found), None
        pos += length
        end = pos
    return len(found), end


def _jp2_codestream(read, size: int) -> int:
    """Where a JP2 file's contiguous codestream box (jp2c) starts, its boxes walked by their
    lengths (ISO 15444-1 I.4)."""
    pos = 0
    while pos + 8 <= size:
        head = read(pos, 16)
        length, kind = int.from_bytes(head[:4], "big"), head[4:8]
        skip = 8
        if length == 1:
            length, skip = int.from_bytes(head[8:16], "big"), 16
        elif length == 0:
            length = size - pos
        if kind == b"jp2c":
            return pos + skip
        if length < skip:
            raise ValueError(f"a JP2 box of length {length} at byte {pos}")
        pos += length
    raise ValueError("no codestream box (jp2c) in the JP2 file")


def codestream_header(read, size: int) -> dict:
    """The image a JPEG, JPEG-LS, JPEG 2000 or JP2 stream declares, from its header alone:
    ``codec`` (jpeg, jpegls, jpeg2k), ``process``, ``lossless`` (True, False, or None where its
    header cannot say), ``width``, ``height``, ``components``, ``precision``, ``signed``.
    ``ValueError`` where the header is not one."""
    head = read(0, 12)
    if head[:3] == JPEG_MAGIC:
        return _jpeg_header(read, size)
    if head[:4] == J2K_MAGIC:
        return _j2k_header(read, 0, size)
    if head[:12] == JP2_MAGIC:
        return _j2k_header(read, _jp2_codestream(read, size), size)
    raise ValueError("neither a JPEG nor a JPEG 2000 stream (no SOI or SOC marker first)")


def bytes_header(buf: bytes) -> dict:
    """:func:`codestream_header` of a stream in memory (a DICOM frame)."""
    return codestream_header(lambda pos, n: bytes(buf[pos : pos + n]), len(buf))


def file_header(path) -> dict:
    """:func:`codestream_header` of a file, its markers read where they are, nothing decoded;
    refused in one line where the header is not one."""
    size = os.path.getsize(path)
    with open(path, "rb") as fh:

        def read(pos, n):
            fh.seek(pos)
            return fh.read(n)

        try:
            return codestream_header(read, size)
        except (ValueError, IndexError) as exc:
            raise FormatError(path, f"a JPEG or JPEG 2000 file whose header cannot be read ({exc}): corrupt") from None


def out_dtype(header: dict) -> np.dtype:
    """What the decoder gives: a byte a sample up to 8 bits, two up to 16."""
    kind = "i" if header["signed"] else "u"
    return np.dtype(f"{kind}{1 if header['precision'] <= 8 else 2}")


def decoded_bytes(header: dict) -> int:
    """What decoding allocates: the output, and for JPEG 2000 OpenJPEG's own image of 32-bit
    samples beside it; a multi-scan (progressive) JPEG keeps every DCT coefficient (2 bytes)."""
    samples = header["width"] * header["height"] * header["components"]
    extra = 4 if header["codec"] == "jpeg2k" else 2 if "progressive" in header["process"] else 0
    # and OpenJPEG's structures for every tile declared, about 10 KiB each (benchmarks/README.md)
    return samples * (out_dtype(header).itemsize + extra) + header.get("tiles", 0) * 10 * 1024


def describe(header: dict) -> str:
    """``JPEG baseline, 8-bit, 1 component(s), lossy`` as ``info`` shows it."""
    what = {"jpeg": "JPEG", "jpegls": "JPEG-LS", "jpeg2k": "HTJ2K" if header.get("htj2k") else "JPEG 2000"}
    process = header["process"] if header["codec"] != "jpegls" else f"NEAR {header.get('near', 0)}"
    if header["codec"] == "jpeg2k":
        process = process.replace("JPEG 2000", "").strip(" ()") or "wavelet not stated"
    loss = {True: "lossless", False: "lossy", None: "lossless or not: its header does not say"}[header["lossless"]]
    sign = "signed " if header["signed"] else ""
    return f"{what[header['codec']]} {process}, {sign}{header['precision']}-bit, {header['components']} component(s), {loss}"


def decode(path, buf, header: dict, where: str = "") -> np.ndarray:
    """The stream's pixels by imagecodecs, as the header said (libjpeg-turbo 3 for every JPEG
    process: 8- and 12-bit DCT, lossless to 16 bits; CharLS for JPEG-LS; OpenJPEG for JPEG 2000
    and HTJ2K), refused in one line naming the file where they cannot be decoded or are not the
    image the header declared."""
    import imagecodecs

    codec = {"jpegls": imagecodecs.jpegls_decode, "jpeg2k": imagecodecs.jpeg2k_decode}.get(
        header["codec"], imagecodecs.jpeg8_decode
    )
    try:
        data = codec(buf)
    except Exception as exc:  # imagecodecs' codec errors: one class per codec
        raise FormatError(
            path, f"{where}a {describe(header)} image that cannot be decoded: {' '.join(str(exc).split())}"
        ) from None
    check_decoded(path, data, header, where)
    if header["codec"] == "jpeg":
        check_coded_data(path, buf, header, data, codec, where)
    return data


#: bytes put before each marker that ends a JPEG's coded data, for :func:`check_coded_data`'s
#: second decode: no 0xFF (a marker's first byte), and not the zero bits libjpeg-turbo fills in
#: where the data runs out, nor all ones (no Huffman code, T.81 C)
_PAD = bytes([0xA5, 0x5A, 0x96, 0x69]) * 16


def _restart_padded(buf, header: dict) -> tuple[bytes, list[list[int]]]:
    """``buf`` with :data:`_PAD` before each marker that ends coded data (a restart interval's RSTn,
    a scan's next marker), and each scan's RSTn numbers in order. Coded data holds no marker:
    an 0xFF in it is stuffed (0xFF00), T.81 B.1.1.5."""
    data, pieces, scans, pos = bytes(buf), [], [], header["scan"]
    done = 0
    while pos + 4 <= len(data) and data[pos : pos + 2] == b"\xff\xda":  # an SOS: its header, then coded data
        i, rst = pos + 2 + int.from_bytes(data[pos + 2 : pos + 4], "big"), []
        while (i := data.find(b"\xff", i)) >= 0:
            j = i + 1  # past any fill bytes (0xFF, T.81 B.1.1.2) to the byte they lead to
            while j < len(data) and data[j] == 0xFF:
                j += 1
            if j >= len(data):
                i = -1
                break
            if data[j] == 0x00:  # stuffed (a decoder swallows fill bytes before the 0x00 too)
                i = j + 1
                continue
            # the padding goes before the fill bytes: after them it made 0xFF and its first byte
            # a marker that is none, and a valid stream was refused
            pieces += [data[done:i], _PAD]
            done = i
            if 0xD0 <= data[j] <= 0xD7:
                rst.append(data[j] - 0xD0)
                i = j + 1
                continue
            break
        scans.append(rst)
        if i < 0:
            break
        pos = j - 1  # the marker after the scan: walked by lengths to the next SOS (or EOI)
        while pos + 4 <= len(data) and data[pos] == 0xFF and data[pos + 1] not in (0xDA, 0xD9):
            if data[pos + 1] == 0xFF:  # fill bytes before a segment's marker
                pos += 1
                continue
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    pieces.append(data[done:])
    return b"".join(pieces), scans


def check_coded_data(path, buf, header: dict, data: np.ndarray, codec, where: str = "") -> None:
    """Refuse a JPEG whose coded data ran out before its image did: libjpeg-turbo fills the rest
    with zero bits and says nothing (a stream cut short with its end marker kept, bytes lost, a
    flipped byte that threw its Huffman decoding out of step), and resynchronises at a restart
    marker it did not expect. The stream is decoded once more with :data:`_PAD` before each
    marker that ends coded data: an undamaged stream's decoder reads none of it (its image ends
    within its own bits), so any pixel that differs was made of bytes the stream does not hold.
    The restart markers must count 0 to 7 and round again (T.81 B.2.1). What this cannot find: a
    byte changed inside coded data whose decoding stays in step (benchmarks/README.md)."""
    padded, scans = _restart_padded(buf, header)
    for rst in scans:
        for k, (a, b) in enumerate(zip([7] + rst, rst)):
            if b != (a + 1) % 8:
                raise FormatError(
                    path,
                    f"{where}a {describe(header)} stream whose restart markers skip from RST{a} to RST{b} "
                    f"(marker {k + 1} of its scan): an interval lost, corrupt",
                )
    if "arithmetic" in header["process"]:
        # not for arithmetic coding: its decoder reads zero bits past a marker, and its encoder
        # drops the trailing zero bytes of its last symbols for it (T.81 D.1.8, F.2.2.5): an
        # undamaged stream's last symbols are decoded from the padding, and it was refused
        return
    try:
        again = codec(padded)
    except Exception:  # its own decoder's error: the padding was read
        again = None
    if again is None or again.shape != data.shape or not np.array_equal(again, data):
        raise FormatError(
            path,
            f"{where}a {describe(header)} stream whose coded data ran out before its image did (the decoder "
            "filled in the rest): truncated or corrupt",
        )


def check_complete(path, buf, header: dict, where: str = "") -> None:
    """Refuse a stream cut short: JPEG, JPEG-LS and JPEG 2000 all end at an EOI (EOC) marker,
    0xFFD9, which their coded data cannot hold (byte stuffing), so it must come after the first
    scan (tile). Why: libjpeg-turbo decodes a truncated JPEG without a word, its missing rows
    grey. (Damage inside the coded data, its length kept, is not found: JPEG has no checksum.)"""
    if bytes(buf).rfind(b"\xff\xd9", header.get("scan", 0)) < 0:
        raise FormatError(path, f"{where}a {describe(header)} stream without its end marker (0xFFD9): truncated")
    end = header.get("tile_parts_end")
    if end is not None and bytes(buf[end : end + 2]) != b"\xff\xd9":
        # a tile-part cut short (or its bytes lost) with the EOC kept, or a Psot running past the data
        raise FormatError(
            path,
            f"{where}a {describe(header)} stream whose tile-parts' lengths (Psot) end at byte {end}, not at its "
            f"end marker (EOC){' (the stream holds ' + str(len(buf)) + ' bytes)' if end > len(buf) else ''}: "
            "truncated or corrupt",
        )
    if header.get("tiles_found", 1) < header.get("tiles", 1):
        raise FormatError(
            path,
            f"{where}a {describe(header)} stream of {header['tiles']} tiles, {header['tiles_found']} of them with "
            "a tile-part (every tile needs one): truncated or corrupt",
        )


def codestreams(buf, header: dict) -> int:
    """How many codestreams ``buf`` holds one after another: its first, and each that begins (SOI,
    SOC or a JP2 signature) right after an end marker (0xFFD9) and the zero bytes padding a
    fragment to even length. A decoder reads the first and ignores the rest."""
    data, count, pos = bytes(buf), 1, header.get("scan", 0)
    while (end := data.find(b"\xff\xd9", pos)) >= 0:
        start = end + 2
        while start < len(data) and data[start] == 0:
            start += 1
        if (
            data[start : start + 3] == JPEG_MAGIC
            or data[start : start + 4] == J2K_MAGIC
            or data[start : start + 12] == JP2_MAGIC
        ):
            count += 1
        pos = start
    return count


def check_decoded(path, data: np.ndarray, header: dict, where: str = "") -> None:
    """Refuse a decode whose image is not the one the header declared (a corrupt stream that the
    decoder filled otherwise)."""
    shape = (header["height"], header["width"]) + ((header["components"],) if header["components"] > 1 else ())
    if data.shape != shape:
        raise FormatError(
            path, f"{where}decoded as {data.shape}, where its header declares {shape}: corrupt or truncated"
        )


def warn_lossy(path, what: str) -> None:
    """Say once per file (the command line shows one per path) that the values are a lossy codec's."""
    said = LossyWarning(
        f"{shown(path)}: {what}: its values are a lossy codec's approximation of the counts, not the counts; "
        "quantitative contrast and noise measurements on them are affected"
    )
    said.path = str(path)
    warnings.warn(said, stacklevel=5)


def check_bytes(header: dict, stored: int) -> int:
    """What :func:`check_coded_data` allocates beside the decode (``stored``: the stream's bytes):
    its second image, held with the first to compare them, and the padded stream (its pieces, then
    joined: twice the stream's bytes)."""
    if header["codec"] != "jpeg" or "arithmetic" in header["process"]:
        return 0
    samples = header["width"] * header["height"] * header["components"]
    return samples * out_dtype(header).itemsize + 2 * stored


def frame_decode_bytes(header: dict, stored: int) -> int:
    """What decoding one codestream of ``stored`` bytes holds at its peak (:func:`compressed_frame`):
    the stream, its decode (:func:`decoded_bytes`: the image, OpenJPEG's 32-bit copy, a progressive
    JPEG's coefficients), and for a JPEG the coded-data check (:func:`check_coded_data`): first the
    padded stream's pieces and their join (2 x ``stored``) beside the image, then the join, a second
    decode and the two images compared (a byte a sample). benchmarks/README.md
    (bench_dicom_decode_memory.py) has them measured against this."""
    decoded = decoded_bytes(header)
    if not check_bytes(header, stored):
        return stored + decoded
    samples = header["width"] * header["height"] * header["components"]
    image = samples * out_dtype(header).itemsize
    return stored + image + max(2 * stored, stored + decoded + samples)


def file_read_bytes(header: dict, stored: int) -> int:
    """What reading a codestream file of ``stored`` bytes holds at its peak: its bytes read whole,
    their decode (:func:`frame_decode_bytes`), and the frame read into its stack."""
    return frame_decode_bytes(header, stored) + header["width"] * header["height"] * out_dtype(header).itemsize


def syntax_header(syntax, rows: int, cols: int, dtype) -> dict:
    """The header a compressed DICOM's frames may have, before any is read, for the budget: its
    syntax's codec, the DICOM's image, samples as wide as BitsAllocated (a frame's own are held
    to it: :func:`_check_frame_header`), one tile; a DCT syntax's stream taken as progressive (its
    coefficients held: no syntax stops a writer's)."""
    name = syntax.name
    codec = "jpegls" if "JPEG-LS" in name else "jpeg2k" if ("2000" in name or "HTJ2K" in name) else "jpeg"
    lossless = compressed_syntaxes().get(syntax) is not True
    process = "lossless" if lossless and codec == "jpeg" else "progressive" if codec == "jpeg" else ""
    precision = np.dtype(dtype).itemsize * 8
    return {"codec": codec, "process": process, "width": cols, "height": rows, "components": 1} | {
        "precision": precision,
        "signed": False,
        "tiles": 1,
    }


def check_file_header(path, header: dict, budget) -> None:
    """Refuse, before decoding, a file declaring more than the budget, a colour space of neither
    one nor three components, or samples over 16 bits."""
    w, h, c, p = (header[k] for k in ("width", "height", "components", "precision"))
    if w <= 0 or h <= 0 or not 1 <= p:  # (a JPEG 2000 image offset past its own extent is negative)
        raise FormatError(
            path, f"a {describe(header)} image of {w}x{h}: no pixels (corrupt, or a height given later, by DNL)"
        )
    what, decoded = f"its header's {w}x{h} {p}-bit image of {c} component(s)", decoded_bytes(header)
    stored = os.path.getsize(path)
    twice = ", decoded twice (the second checks its coded data)" if check_bytes(header, stored) else ""
    check_budget(path, file_read_bytes(header, stored), f"{what}{twice}, read", budget)
    # (the budget is a fraction of the machine: a 4 KB JPEG declaring 60000 x 60000 fits a large one's)
    codec = "JPEG 2000" if header["codec"] == "jpeg2k" else "JPEG"
    check_proportion(path, what, decoded, decoded, stored, codec, budget)
    if c not in (1, 3):
        raise FormatError(
            path, f"a {describe(header)} image: {c} components (CMYK, or grey with alpha), not one channel of counts"
        )
    if p > 16:
        raise FormatError(path, f"a {describe(header)} image: samples of {p} bits, where radiokit reads up to 16")


def grey(path, data: np.ndarray, header: dict) -> np.ndarray:
    """One channel: a three-component image whose channels are equal everywhere is a greyscale
    radiograph saved as colour (a grey JPEG's chroma is exactly neutral, and decodes to R = G =
    B), read as one, as a PNG's is; any other is refused (a viewer's colour rendering is no counts)."""
    if data.ndim == 2:
        return data
    if all(np.array_equal(data[..., 0], data[..., k]) for k in range(1, data.shape[2])):
        return np.ascontiguousarray(data[..., 0])
    raise FormatError(
        path,
        f"a colour {describe(header)} image whose channels differ: a viewer's colour rendering, not one channel "
        "of counts; export the radiograph as greyscale",
    )


def decode_file(path, header: dict) -> np.ndarray:
    """A JPEG or JPEG 2000 file's one greyscale image, in one line naming the file where it cannot be."""
    with open(path, "rb") as fh:
        buf = fh.read()  # (bytes: the end marker's search and the decoder both read it, no copy)
    check_complete(path, buf, header)
    return grey(path, decode(path, buf, header), header)


# -- a compressed DICOM's frames ------------------------------------------------------------------
def compressed_syntaxes() -> dict:
    """The compressed transfer syntaxes decoded here, each with whether it is lossy: True (JPEG's
    DCT processes), None (it permits lossy compression: JPEG-LS near-lossless of NEAR 0 is
    lossless, as is JPEG 2000 of the reversible wavelet with every layer kept), False (lossless
    only). JPEG 2000 Part 2 multi-component, JPIP, MPEG and HEVC stay refused."""
    from pydicom import uid

    return {
        uid.JPEGBaseline8Bit: True,
        uid.JPEGExtended12Bit: True,
        uid.JPEGLossless: False,
        uid.JPEGLosslessSV1: False,
        uid.JPEGLSLossless: False,
        uid.JPEGLSNearLossless: None,
        uid.JPEG2000Lossless: False,
        uid.JPEG2000: None,
        uid.HTJ2KLossless: False,
        uid.HTJ2KLosslessRPCL: False,
        uid.HTJ2K: None,
    }


def check_dicom_proportion(path, syntax, n: int, rows: int, cols: int, dtype, budget) -> None:
    """Refuse, before decoding, a compressed DICOM whose header declares frames out of all
    proportion to the file's bytes (:func:`check_proportion`): each frame's codestream must be the
    declared image, so a 4 KB file declaring 60000 x 60000 would otherwise be decoded, its few
    bytes taken for 7 GB of pixels, within a large machine's budget."""
    frame = rows * cols * np.dtype(dtype).itemsize
    what = f"its header's {n} frame(s) of {rows}x{cols} {np.dtype(dtype)}"
    check_proportion(path, what, n * frame, frame, os.path.getsize(path), syntax.name, budget)


def say_lossy_dicom(path, ds, syntax) -> str | None:
    """Warn (once per file) where a compressed DICOM's pixels are or may be a lossy codec's: its
    syntax is lossy or permits it, or LossyImageCompression says they were once (a lossless
    re-encoding of lossy pixels keeps their loss). What was said is returned for ``meta``."""
    lossy = compressed_syntaxes().get(syntax, False)
    said = str(ds.get("LossyImageCompression", "")).strip() == "01"
    if lossy is False and not said:
        return None
    what = f"a DICOM file compressed as {syntax.name} ({syntax})"
    if lossy is None and not said:
        what += ", a syntax that permits lossy compression"
    elif said and not lossy:
        what += ", whose LossyImageCompression says its pixels were lossy-compressed before"
    warn_lossy(path, what)
    return what


def _frame_bytes(path, ds, n: int, i: int) -> bytes:
    """Frame ``i``'s codestream: its fragments joined, found by the Basic (or Extended) Offset
    Table, else one fragment a frame, else by the JPEG end-of-image markers (pydicom's rules)."""
    from pydicom.encaps import get_frame, parse_basic_offsets

    offsets = None
    if "ExtendedOffsetTable" in ds and "ExtendedOffsetTableLengths" in ds:
        offsets = (ds.ExtendedOffsetTable, ds.ExtendedOffsetTableLengths)
    try:
        listed = len(offsets[0]) // 8 if offsets else len(parse_basic_offsets(ds.PixelData))
        frame = get_frame(ds.PixelData, i, number_of_frames=n, extended_offsets=offsets)
    except Exception as exc:  # pydicom's ValueError, or a struct error on a cut item
        raise FormatError(
            path, f"frame {i}'s encapsulated fragments cannot be read: {' '.join(str(exc).split())}"
        ) from None
    if listed > n:
        # an offset table of more frames than NumberOfFrames (absent: 1) declares: get_frame
        # reads the first n of them, and the rest would never be
        declared = ds.get("NumberOfFrames")
        raise FormatError(
            path,
            f"its offset table lists {listed} frames, more than its NumberOfFrames "
            f"({'absent: 1' if declared is None else declared}) declares, whose header is wrong; "
            "read as declared, the others would be lost",
        )
    return frame


def _check_frame_header(path, header: dict, geometry: dict, i: int) -> None:
    """Refuse, before decoding, a frame's codestream that is not the image the DICOM header
    declares: another size (which its decoder would allocate, whatever Rows and Columns say),
    another number of components, or samples wider than BitsAllocated. A precision other than
    BitsStored is read (writers put 12-bit counts in 16-bit streams): its words' low BitsStored
    bits, as any DICOM's are (radiokit.io._clinical._stored_bits)."""
    rows, cols, word = geometry["rows"], geometry["cols"], geometry["dtype"].itemsize * 8
    stated = (header["height"], header["width"], header["components"])
    if stated != (rows, cols, 1) or header["precision"] > word:
        raise FormatError(
            path,
            f"frame {i} is a {describe(header)} image of {header['height']}x{header['width']}, where the DICOM header "
            f"declares {rows}x{cols} of 1 sample in {word}-bit words: not the image it describes",
        )


def compressed_frame(path, ds, geometry: dict, i: int) -> np.ndarray:
    """Frame ``i`` of a compressed DICOM, decoded, as stored (the type of BitsAllocated and
    PixelRepresentation): signed values that the codec returns as unsigned patterns of its
    precision (JPEG, JPEG-LS) are sign-extended from it."""
    buf = _frame_bytes(path, ds, geometry["n"], i)
    try:
        header = bytes_header(buf)
    except (ValueError, IndexError) as exc:
        raise FormatError(path, f"frame {i}'s codestream header cannot be read ({exc}): corrupt") from None
    _check_frame_header(path, header, geometry, i)
    # its own header's decode (a JPEG 2000's tiles, unknown at open) beside what read() holds
    check_budget(
        path,
        geometry["held"] + geometry["stack_held"] + frame_decode_bytes(header, len(buf)) + geometry["rescale_bytes"],
        f"frame {i} ({describe(header)}, {len(buf)} bytes), decoded beside the frames read",
        geometry["budget"],
    )
    check_complete(path, buf, header, f"frame {i} is ")
    if (count := codestreams(buf, header)) > 1:
        # frames one fragment each under a NumberOfFrames absent or too small: pydicom joins
        # every fragment into the one frame declared, whose decode is the first frame alone
        declared = ds.get("NumberOfFrames")
        raise FormatError(
            path,
            f"frame {i}'s fragments hold {count} codestreams, one after another: more frames than its "
            f"NumberOfFrames ({'absent: 1' if declared is None else declared}) declares, whose header is wrong; "
            "read as declared, all but the first would be lost",
        )
    syntax = ds.file_meta.TransferSyntaxUID
    if header["lossless"] is False and compressed_syntaxes().get(syntax) is False and not geometry.get("mislabel_said"):
        geometry["mislabel_said"] = True  # once per open file, not once per frame
        # a lossless syntax's label on a lossy stream (a writer's mistake): the stream is what was stored
        warn_lossy(
            path, f"its frames are {describe(header)} streams, though its transfer syntax {syntax.name} says lossless"
        )
    data = decode(path, buf, header, f"frame {i} is ")
    dtype = geometry["dtype"].newbyteorder("=")
    if dtype.kind == "i" and data.dtype.kind == "u":
        # the sign bit is BitsStored's top where the stream is wider (CharLS and OpenJPEG encode
        # uint16 words at 16 bits): the unused bits above it are undefined (PS3.5 8.1.1), zero
        # for some writers, and pydicom reads such words uncompressed from BitsStored too
        bits = min(header["precision"], int(ds.get("BitsStored", 0) or 0) or header["precision"])
        # in place, in the decoded words: BitsStored's top bit shifted to the word's, then an
        # arithmetic shift back (int64 copies held 3 x 8 bytes a sample, beside the budget's count)
        shift = data.dtype.itemsize * 8 - bits
        data <<= shift
        data = data.view(data.dtype.str.replace("u", "i"))
        data >>= shift
    elif dtype.kind == "u" and data.dtype.kind == "i":
        # a JPEG 2000 whose SIZ says signed over unsigned counts (a writer's mislabel): its bits
        # are the counts, as pydicom reads them, not int16 values wrapped to 65000s
        data = data.view(data.dtype.str.replace("i", "u"))
        data &= (1 << header["precision"]) - 1
    return data.astype(dtype, copy=False)
