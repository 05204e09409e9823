"""Which damage inside a compressed stream each decoder refuses, and which radiokit refuses.

A small 12-bit frame (a smooth ramp plus Poisson noise, 96 x 80) is encoded by imagecodecs' own
encoders in each syntax radiokit decodes, damaged one way at a time, and read twice: by the
decoder alone (imagecodecs) and by ``radiokit.io.read`` (the damaged stream as a plain file).
Each cell says what came of it: ``refused``, ``same`` (decoded, every pixel as undamaged),
``WRONG`` (decoded without an error into other pixels). A flipped byte, and 20 bytes deleted,
are tried at ``--flips`` evenly spaced places in the coded data; their cells count them
(refused / same / WRONG).

    python benchmarks/bench_codec_damage.py [--flips 40]
"""

from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

import imagecodecs
import numpy as np

from radiokit.io import FormatError, read
from radiokit.io._codecs import bytes_header

SYNTAXES = {
    "ljpeg SV1": (".jpg", lambda f: imagecodecs.ljpeg_encode(f, bitspersample=12)),
    "ljpeg P7": (".jpg", lambda f: imagecodecs.jpeg8_encode(f, lossless=True, bitspersample=12, predictor=7)),
    "JPEG12 q90": (".jpg", lambda f: imagecodecs.jpeg8_encode(f, level=90, bitspersample=12)),
    "JPEG-LS": (".jls", imagecodecs.jpegls_encode),
    "JPEG-LS N2": (".jls", lambda f: imagecodecs.jpegls_encode(f, level=2)),
    "J2K 5/3": (".j2k", lambda f: imagecodecs.jpeg2k_encode(f, level=0, codecformat="J2K", bitspersample=12)),
    "J2K 9/7": (
        ".j2k",
        lambda f: imagecodecs.jpeg2k_encode(f, level=30, codecformat="J2K", bitspersample=12, reversible=False),
    ),
    "HTJ2K": (".jph", lambda f: imagecodecs.htj2k_encode(f, level=0)),
}


def frame() -> np.ndarray:
    rng = np.random.default_rng(0)
    y, x = np.mgrid[:96, :80]
    return rng.poisson(500 + 20 * x + 10 * y).clip(0, 4095).astype(np.uint16)


def coded(stream: bytes) -> tuple[int, int]:
    """The coded data's span: from the first scan's (tile's) header to the end marker."""
    start = bytes_header(stream).get("scan", 2)
    return start + 20, len(stream) - 2


def damages(stream: bytes, flips: int) -> dict:
    lo, hi = coded(stream)
    cut = lo + (hi - lo) * 6 // 10
    out = {
        "truncated at 60%": [stream[:cut]],
        "truncated, EOI/EOC kept": [stream[:cut] + b"\xff\xd9"],
        "end marker missing": [stream[:-2]],
        "20 bytes deleted": [],
        "byte flipped mid-data": [],
    }
    for pos in np.linspace(lo, hi - 21, flips).astype(int):
        out["20 bytes deleted"].append(stream[:pos] + stream[pos + 20 :])
    for pos in np.linspace(lo, hi - 1, flips).astype(int):
        b = bytearray(stream)
        if b[pos] == 0xFF or b[pos - 1] == 0xFF:  # not a marker, nor a stuffed byte's
            pos -= 2
        b[pos] ^= 0x5A if b[pos] ^ 0x5A != 0xFF else 0x55
        out["byte flipped mid-data"].append(bytes(b))
    if stream[:2] == b"\xff\x4f":
        sot = bytes_header(stream)["scan"]
        b = bytearray(stream)
        psot = int.from_bytes(b[sot + 6 : sot + 10], "big")
        b[sot + 6 : sot + 10] = (psot + 64).to_bytes(4, "big")  # a tile-part running past the data
        out["Psot past the data"] = [bytes(b)]
    return out


def outcome(decode, good: np.ndarray) -> str:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = decode()
    except (FormatError, Exception):  # the decoder's own error classes: one per codec
        return "refused"
    data = np.asarray(data)
    return "same" if data.shape == good.shape and np.array_equal(data, good) else "WRONG"


def cell(results: list[str]) -> str:
    if len(results) == 1:
        return results[0]
    return "/".join(str(results.count(k)) for k in ("refused", "same", "WRONG"))


def with_fill_bytes(stream: bytes) -> bytes:
    """``stream`` with two fill bytes before each marker after its first scan's header."""
    first = bytes_header(stream)["scan"] + 2
    out, i = bytearray(stream[:first]), first
    while (j := stream.find(b"\xff", i)) >= 0 and j + 1 < len(stream):
        out += stream[i:j]
        if stream[j + 1] not in (0x00, 0xFF):
            out += b"\xff\xff"
        out += stream[j : j + 2]
        i = j + 2
    return bytes(out + stream[i:])


def false_refusals(n: int = 60) -> tuple[int, int]:
    """Undamaged JPEGs of many kinds (Pillow's baseline, progressive, optimised and restart-marked
    8-bit streams, grey and RGB; imagecodecs' lossless and 12-bit DCT ones), sides of 1 to 89
    pixels, noisy, constant and ramp content, each also with fill bytes before its markers: how
    many the coded-data check refuses, of how many."""
    import io

    from PIL import Image

    from radiokit.io._codecs import check_coded_data

    rng, refused, total = np.random.default_rng(5), 0, 0
    streams = []
    for k in range(n):
        h, w = (int(v) for v in rng.integers(1, 90, 2))
        a = [
            rng.integers(0, 255, (h, w)),
            np.full((h, w), rng.integers(0, 255)),
            np.add.outer(np.arange(h), np.arange(w)),
        ]
        a = (a[k % 3] % 256).astype(np.uint8)
        for opts in ({"progressive": True}, {"optimize": True}, {"restart_marker_blocks": 3}, {}):
            for mode in ("L", "RGB"):
                out = io.BytesIO()
                Image.fromarray(a).convert(mode).save(out, "JPEG", quality=int(rng.integers(30, 100)), **opts)
                streams.append(out.getvalue())
        a16 = rng.integers(0, 4096, (h, w)).astype(np.uint16) if k % 3 == 0 else np.full((h, w), 7, np.uint16)
        streams += [
            imagecodecs.ljpeg_encode(a16, bitspersample=12),
            imagecodecs.jpeg8_encode(a16, lossless=True, bitspersample=12, predictor=int(rng.integers(1, 8))),
            imagecodecs.jpeg8_encode(a16, level=int(rng.integers(10, 100)), bitspersample=12),
        ]
    # each again with fill bytes (0xFF, T.81 B.1.1.2) before every marker after its first scan
    # header: valid, and refused until review s55rvoff (the padding went between them and the marker)
    streams += [with_fill_bytes(bytes(s)) for s in streams]
    for s in streams:
        s = bytes(s)
        try:
            check_coded_data("x", s, bytes_header(s), imagecodecs.jpeg8_decode(s), imagecodecs.jpeg8_decode)
        except FormatError:
            refused += 1
        total += 1
    return refused, total


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flips", type=int, default=40)
    args = ap.parse_args(argv)
    f = frame()
    table: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (ext, encode) in SYNTAXES.items():
            stream = bytes(encode(f))
            good = np.asarray(imagecodecs.imread(stream))
            for kind, variants in damages(stream, args.flips).items():
                lib, ours = [], []
                for k, damaged in enumerate(variants):
                    path = Path(tmp) / f"d{k}{ext}"
                    path.write_bytes(damaged)
                    codec = {".jls": imagecodecs.jpegls_decode, ".jpg": imagecodecs.jpeg8_decode}.get(
                        ext, imagecodecs.jpeg2k_decode
                    )
                    lib.append(outcome(lambda d=damaged, c=codec: c(d), good))
                    ours.append(outcome(lambda p=path: read(p).data[0], good))
                table.setdefault(kind, {})[name] = f"{cell(lib)} | {cell(ours)}"
    names = list(SYNTAXES)
    print("decoder alone | radiokit.io.read; flips counted refused/same/WRONG")
    print(f"{'damage':26}" + "".join(f"{n:>24}" for n in names))
    for kind, row in table.items():
        print(f"{kind:26}" + "".join(f"{row.get(n, '-'):>24}" for n in names))
    refused, total = false_refusals()
    print(f"undamaged JPEGs refused by the coded-data check: {refused} of {total}")


if __name__ == "__main__":
    main()
