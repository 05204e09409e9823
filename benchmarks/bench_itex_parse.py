"""ITEX comment parsing must be linear in the comment: time hostile comments at two sizes.

For each comment shape (the ones that made the old regex backtrack: blanks before ``=``,
unclosed ``[``, bracketed text, lines of blanks; and a vendor-like one), parse it at n and 8n
characters, interleaved and repeated, and print the median times and their ratio. Linear
parsing gives a ratio near 8; quadratic near 64.

    python benchmarks/bench_itex_parse.py [--n 32000] [--reps 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

from radiokit.io._itex import parse_comment

SHAPES = {
    "blanks before =": lambda n: "a" + " " * n + "b=1",
    "unclosed [": lambda n: "[" * n,
    "bracketed text": lambda n: "[abc" * (n // 4),
    "lines of blanks": lambda n: (" " * 100 + "\n") * (n // 101),
    "vendor-like": lambda n: '[Camera],CameraName="Orca R2",Exposure=10 ms,Gain=3\r\n' * (n // 52),
}


def _time(text: str) -> float:
    t = time.perf_counter()
    parse_comment(text)
    return time.perf_counter() - t


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=32_000, help="the smaller comment size, characters")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    print(f"{'comment':<18} {'n':>8} {'t(n) ms':>9} {'t(8n) ms':>9} {'ratio':>6}")
    for name, make in SHAPES.items():
        small, large = make(args.n), make(8 * args.n)
        ts, tl = [], []
        for _ in range(args.reps):  # interleaved, so that load on the machine hits both alike
            ts.append(_time(small))
            tl.append(_time(large))
        a, b = statistics.median(ts), statistics.median(tl)
        print(f"{name:<18} {len(small):>8} {1e3 * a:>9.2f} {1e3 * b:>9.2f} {b / a:>6.1f}")


if __name__ == "__main__":
    main()
