"""The correction's per-pixel work as one compiled pass per row (numba).

Why compiled: subtracting the dark, testing ``raw - dark <= 0``, clamping, taking the log and
subtracting it from ``ln(flat - dark)`` are five array operations; done as separate (even cache
blocked, OpenCV) passes, every test of the rare bad pixel costs a pass of its own. Here one loop
per row does all of it while the row is in registers, and counts the bad and saturated pixels of
each row, so that only rows holding some are searched (in L1, where the row still is) for
where they are.

Why a polynomial log: ``math.log`` in a numba loop is a scalar libm call, which keeps LLVM from
vectorising the loop (measured 1.4x *slower* than OpenCV's SIMD log). :func:`_ln` is the
Cephes ``logf`` (exponent from the float's bits, a degree-9 polynomial of the mantissa in
[sqrt(1/2), sqrt(2))), made of arithmetic and bit operations only, so LLVM vectorises it; its
error is about one float32 ulp (the tests hold it to numpy's float64 log at 2 ulp).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from radiokit.correct import FLOOR_COUNTS

__all__ = ["correct_rows", "find", "gather", "fill_from_neighbours"]

# a bad row is searched for its marked pixels in chunks of this many columns, skipping clean ones
CHUNK = 64
# what a clamped pixel holds until it is recorded: no positive difference can be negative
_MARK = np.float32(-1.0)
_FLOOR = np.float32(FLOOR_COUNTS)
# Below the smallest normal float32 the exponent trick of _ln does not hold: such a
# difference (only a float raw frame can make one) counts as non-positive.
_TINY = np.float32(np.finfo(np.float32).tiny)
_HUGE = np.float32(np.finfo(np.float32).max)
_SQRT_HALF_BITS = np.int32(0x3F3504F3)  # the bits of float32(sqrt(0.5))
_MANTISSA = np.int32(0x007FFFFF)
_LN2_HI = np.float32(0.693359375)  # ln 2 = _LN2_HI + _LN2_LO, the high part exact in float32
_LN2_LO = np.float32(-2.12194440e-4)
# Cephes logf's minimax polynomial, highest degree first
_P = tuple(
    np.float32(c)
    for c in (
        7.0376836292e-2,
        -1.1514610310e-1,
        1.1676998740e-1,
        -1.2420140846e-1,
        1.4249322787e-1,
        -1.6668057665e-1,
        2.0000714765e-1,
        -2.4999993993e-1,
        3.3333331174e-1,
    )
)
P0, P1, P2, P3, P4, P5, P6, P7, P8 = _P

# contract: let LLVM fuse a * b + c into one FMA (the polynomial's rounding changes by under
# an ulp); no other fast-math flag, so NaN and inf keep their IEEE meaning in the tests below.
_JIT = dict(nogil=True, cache=True, boundscheck=False, fastmath={"contract"})


def _njit(func):
    """``nb.njit(**_JIT)``, uncached where numba finds nowhere to write its cache.

    Why: a user with no writable home (``nobody``, a container's arbitrary uid) running an install
    it cannot write got numba's "cannot cache function: no locator available" as a traceback from
    every command that corrects; uncached, the loop is compiled again at each start (seconds)."""
    try:
        return nb.njit(**_JIT)(func)
    except RuntimeError as exc:
        if "no locator available" not in str(exc):
            raise
        return nb.njit(**(_JIT | {"cache": False}))(func)


@intrinsic
def _bits(typingctx, x):
    """The int32 whose bits are float32 ``x`` (a register move, as C's memcpy or a union)."""

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def _float(typingctx, k):
    """The float32 whose bits are int32 ``k``."""

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@_njit
def _ln(x):
    """ln of a positive normal float32 (Cephes logf)."""
    k = _bits(x) - _SQRT_HALF_BITS
    e = np.float32(k >> 23)
    m = _float((k & _MANTISSA) + _SQRT_HALF_BITS) - np.float32(1.0)  # mantissa in [sqrt(1/2), sqrt(2)), less 1
    z = m * m
    y = ((((((((P0 * m + P1) * m + P2) * m + P3) * m + P4) * m + P5) * m + P6) * m + P7) * m + P8) * m * z
    y = y + e * _LN2_LO - np.float32(0.5) * z
    return m + y + e * _LN2_HI


@_njit
def _good(t):
    """``raw - dark`` usable for the log: a positive, normal, finite float32 (False for NaN, inf
    and anything <= 0)."""
    return (t >= _TINY) & (t <= _HUGE)


@_njit
def _record(row, i, j0, j1, value, found, pos):
    """Write the flat indices of ``row[j0:j1] == value`` (row ``i``) at ``found[pos:]``, while
    there is room; returns the new ``pos`` (counting past the room, so the caller sees overflow)."""
    cols = row.size
    for j in range(j0, j1):
        if row[j] == value:
            if pos < found.size:
                found[pos] = i * cols + j
            pos += 1
    return pos


@_njit
def _record_row(row, i, value, found, pos):
    """:func:`_record` over a whole row, skipping its CHUNK-column chunks that hold no ``value``
    (each chunk's test is one vectorised pass over 64 floats already in L1)."""
    cols = row.size
    for j0 in range(0, cols, CHUNK):
        j1 = min(cols, j0 + CHUNK)
        hits = 0
        for j in range(j0, j1):  # an integer sum vectorises; a boolean "or" did not
            hits += row[j] == value
        if hits:
            pos = _record(row, i, j0, j1, value, found, pos)
    return pos


@_njit
def correct_rows(raw, dark, coef, out, r0, r1, log_domain, scale, saturation, count_saturated, bad, sat):
    """Correct rows ``r0..r1`` of one frame into ``out`` (float32).

    ``log_domain``: ``out = coef - ln(max(raw - dark, FLOOR))`` with ``coef = ln(flat - dark)``;
    otherwise ``out = max(raw - dark, FLOOR) * coef * scale`` with ``coef = 1 / (flat - dark)``.
    ``raw - dark`` is taken in float32 (``float32(raw) - dark``).

    ``bad`` and ``sat`` (int64 arrays) receive the flat indices of the clamped pixels (whose
    difference is not a positive normal finite float32) and, when ``count_saturated``, of those
    with ``raw >= saturation``, in row order. Returns how many of each there are: when that is
    more than the array's size, only the first ones were written (see :func:`find`).
    """
    cols = raw.shape[1]
    row = np.empty(cols, np.float32)
    flags = np.empty(cols, np.float32)
    n_bad = 0
    n_sat = 0
    for i in range(r0, r1):
        any_bad = 0
        any_sat = 0
        for j in range(cols):
            v = raw[i, j]
            t = np.float32(v) - dark[i, j]
            good = _good(t)
            any_bad += not good  # integer sums vectorise (a boolean "or" did not)
            row[j] = t if good else _MARK
            if count_saturated:
                is_sat = v >= saturation
                any_sat += is_sat
                flags[j] = np.float32(is_sat)
        if any_bad:  # rare: record where (the marks are clamped below)
            n_bad = _record_row(row, i, _MARK, bad, n_bad)
        if any_sat:
            n_sat = _record_row(flags, i, np.float32(1.0), sat, n_sat)
        # the clamp is a select inside the vectorised loop: no pass of its own
        if log_domain:
            for j in range(cols):
                t = row[j]
                out[i, j] = coef[i, j] - _ln(t if t > 0 else _FLOOR)
        else:
            for j in range(cols):
                t = row[j]
                out[i, j] = (t if t > 0 else _FLOOR) * coef[i, j] * scale
    return n_bad, n_sat


@_njit
def find(raw, dark, r0, r1, saturation, count_saturated, n_bad, n_sat):
    """All flat indices (``n_bad`` and ``n_sat`` of them) of the clamped and saturated pixels of
    rows ``r0..r1``, by the tests of :func:`correct_rows`: for when they overflowed its arrays."""
    cols = raw.shape[1]
    bad = np.empty(n_bad, np.int64)
    sat = np.empty(n_sat, np.int64)
    nb_, ns = 0, 0
    for i in range(r0, r1):
        for j in range(cols):
            v = raw[i, j]
            if count_saturated and v >= saturation:
                sat[ns] = i * cols + j
                ns += 1
            t = np.float32(v) - dark[i, j]
            if not _good(t):
                bad[nb_] = i * cols + j
                nb_ += 1
    return bad, sat


@_njit
def gather(flat, dst, src, w):
    """``flat[dst[i]] = sum_k w[i, k] * flat[src[i, k]]``, every value read before any is written."""
    values = np.empty(dst.size, np.float32)
    for i in range(dst.size):
        s = np.float32(0.0)
        for k in range(src.shape[1]):
            s += w[i, k] * flat[src[i, k]]
        values[i] = s
    for i in range(dst.size):
        flat[dst[i]] = values[i]


@_njit
def fill_from_neighbours(img, idx, invalid, max_radius):
    """Replace each pixel ``idx`` (flat, of C-contiguous ``img``) by the mean of the pixels in
    the smallest square around it (radius 1, then 2, ... ``max_radius``) that has any valid one;
    valid means not ``invalid`` and not itself in ``idx``. Every mean is taken before any pixel
    is written; a pixel with no valid one within ``max_radius`` keeps its value."""
    rows, cols = img.shape
    flat = img.ravel()
    flat_invalid = invalid.ravel()
    kept = np.empty(idx.size, np.float32)
    for n in range(idx.size):
        kept[n] = flat[idx[n]]
        flat[idx[n]] = np.nan  # marks the pixels being filled (the image holds no other NaN)
    values = kept.copy()
    for n in range(idx.size):
        r, c = idx[n] // cols, idx[n] % cols
        for radius in range(1, max_radius + 1):
            s = 0.0
            count = 0
            for rr in range(max(0, r - radius), min(rows, r + radius + 1)):
                for cc in range(max(0, c - radius), min(cols, c + radius + 1)):
                    x = flat[rr * cols + cc]
                    if x == x and not flat_invalid[rr * cols + cc]:
                        s += x
                        count += 1
            if count:
                values[n] = s / count
                break
    for n in range(idx.size):
        flat[idx[n]] = values[n]
