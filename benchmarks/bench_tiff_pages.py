"""What a TIFF's pages cost open: the numbers behind ``radiokit.io._tiff_ifds.TIFF_BYTES_PER_PAGE``
and ``TIFF_BYTES_PER_TAG``.

Classic TIFFs of one-pixel pages (8 tags each, plus 0, 32 or 128 private SHORT tags), 5,000 and
20,000 pages, opened by ``radiokit info`` under ``/usr/bin/time``; prints the peak resident size
and the slope a page. About a minute.

    python benchmarks/bench_tiff_pages.py
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import tempfile

BASE_TAGS = [(256, 3, 1), (257, 3, 1), (258, 3, 16), (259, 3, 1), (262, 3, 1), (273, 4, 8), (278, 3, 1), (279, 4, 2)]


def one_pixel_pages(path, n: int, extra: int = 0, back: int | None = None) -> None:
    """``n`` IFDs of a 1 x 1 uint16 page with ``extra`` private tags each, all on one 2-byte strip
    (100 bytes a page without extras); with ``back``, the last IFD's next is page ``back``'s again
    (a loop). Also the hostile-input tests' file (tests/test_hostile_inputs.py)."""
    tags = sorted(BASE_TAGS + [(65000 + k, 3, k) for k in range(extra)])
    ifd = 2 + 12 * len(tags) + 4
    data = bytearray(b"II*\x00" + struct.pack("<I", 12) + struct.pack("<H", 1000) + b"\0\0")
    for i in range(n):
        data += struct.pack("<H", len(tags))
        for code, kind, value in tags:
            data += struct.pack("<HHI", code, kind, 1)
            data += struct.pack("<HH", value, 0) if kind == 3 else struct.pack("<I", value)
        following = 12 + (i + 1) * ifd if i < n - 1 else (0 if back is None else 12 + back * ifd)
        data += struct.pack("<I", following)
    with open(path, "wb") as fh:
        fh.write(data)


def peak_kb(path: str) -> int:
    """``radiokit info``'s peak resident size (KB) on ``path``, with a budget that lets it open."""
    env = {**os.environ, "RADIOKIT_MEMORY_BUDGET": "64GiB"}
    res = subprocess.run(
        ["/usr/bin/time", "-f", "peak %M", sys.executable, "-m", "radiokit.cli", "info", path],
        capture_output=True,
        text=True,
        env=env,
    )
    return int(re.search(r"peak (\d+)", res.stderr).group(1))


def main() -> None:
    slopes = {}
    with tempfile.TemporaryDirectory() as tmp:
        print("tags a page | 5,000 pages | 20,000 pages | bytes a page")
        for extra in (0, 32, 128):
            kb = []
            for n in (5000, 20000):
                path = os.path.join(tmp, f"t{extra}_{n}.tif")
                one_pixel_pages(path, n, extra)
                kb.append(peak_kb(path))
            slopes[8 + extra] = (kb[1] - kb[0]) * 1024 / 15000
            print(f"{8 + extra} | {kb[0] / 1024:.1f} MiB | {kb[1] / 1024:.1f} MiB | {slopes[8 + extra]:.0f}")
    per_tag = (slopes[136] - slopes[8]) / 128
    print(f"fit: {slopes[8] - 8 * per_tag:.0f} bytes a page and {per_tag:.0f} a tag")


if __name__ == "__main__":
    main()
