"""What counts as a number where radiokit, the simulator and the acquisition code read one.

JSON's, TOML's and HDF5's ``true`` reaches Python as ``True``, which *is* the int 1:
``isinstance(True, int)`` holds and ``True > 0`` passes a range check, so a bool where a number
belongs went through as 1 (``"flat_current_ua": true`` scaled every transmission by 1/200). These
two tests refuse it and take numpy's integers and floats (readers of HDF5 get ``np.float64``, not
``float``). numpy's bool is no ``numbers.Number``, so it is refused without numpy imported here
(the L8121 driver does not load numpy). Each caller keeps its own range check and its message.
"""

from __future__ import annotations

import functools
import math
import numbers
import os
import sys

from radiokit._names import shown as shown_name

__all__ = ["image_hint", "is_integer", "is_number", "refuse_masked", "scalar", "shown", "shown_name", "toml_loads"]

#: ``shown_name(name)``: a file's name (or any text naming one) as a message prints it --
#: :func:`radiokit._names.shown`, here for the simulator and the acquisition code, which import
#: no private module of the core: :func:`shown` prints the numbers a message refuses, this the names.


def is_number(value) -> bool:
    """A real number, Python's or numpy's (``numbers.Real``), and not a bool. NaN and inf are
    numbers here: the caller says whether it takes them.

    >>> import numpy as np
    >>> is_number(2), is_number(0.5), is_number(np.float32(1)), is_number(float("nan"))
    (True, True, True, True)
    >>> is_number(True), is_number(np.bool_(False)), is_number("1"), is_number(1j), is_number(None)
    (False, False, False, False, False)
    """
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def scalar(value):
    """A 0-d numeric numpy array as the numpy number it holds, anything else as given: ``np.array(2.0)``
    (what ``np.asarray(x)`` or a reduction of an array expression gives) is a number, though no
    ``numbers.Real``, so :func:`is_number` refused it and ``tuple(k for k in ks)`` raised "iteration over
    a 0-d array". A 0-d bool or text array stays an array, refused by the caller's check. Duck-typed:
    numpy is not imported here.

    >>> import numpy as np
    >>> scalar(np.array(2.0)), scalar(np.array([2.0])), scalar(np.array(True)), scalar("2")
    (np.float64(2.0), array([2.]), array(True), '2')
    """
    kind = getattr(getattr(value, "dtype", None), "kind", None)
    if getattr(value, "ndim", None) == 0 and kind in ("i", "u", "f") and hasattr(value, "__getitem__"):
        return value[()]
    return value


def is_integer(value) -> bool:
    """A whole number, Python's or numpy's (``numbers.Integral``), and not a bool; ``2.0`` is not one.

    >>> import numpy as np
    >>> is_integer(3), is_integer(np.uint16(3)), is_integer(3.0), is_integer(True), is_integer(np.bool_(True))
    (True, True, False, False, False)
    """
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def shown(value, beside=None) -> str:
    """``value`` as a message that refuses it prints it. Why: ``:g`` (6 significant digits) printed a
    value refused for being just past its bound as the bound itself ("error_poll_s = 60: at most
    60 s" for 60.0000001), and the user could not see why it was refused.

    Without ``beside`` (a value as the user gave it): ``:g`` where that reads back as the same
    number, else every digit it has (the shortest text that does). With ``beside`` (a value
    computed from the user's, such as a power, whose last digits are rounding): ``:g``'s 6
    significant digits, and as many more as it takes to tell it from ``beside``, the bound it
    broke. Not a number: its ``repr``.

    >>> shown(60.0000001), shown(600.0), shown(1e9), shown(0.1), shown(3), shown(float("nan")), shown("1")
    ('60.0000001', '600', '1e+09', '0.1', '3', 'nan', "'1'")
    >>> shown(0.1 * 3), shown(0.1 * 3, 0.2), shown(4 * 0.1000000001, 0.4), shown(0.4, 0.4)
    ('0.30000000000000004', '0.3', '0.4000000004', '0.4')
    """
    if not is_number(value):
        return repr(value)
    if is_integer(value):
        return str(int(value))
    v = float(value)
    if beside is None:
        text = f"{v:g}"
        if not math.isfinite(v) or _reads_back(text, value):
            return text
        # numpy's shortest digits in the value's own precision: a float32's float64 digits
        # printed 60.1 as 60.099998474121094 (review s51rv3)
        return str(value) if _reads_back(str(value), value) else repr(v)
    if not is_number(beside) or not math.isfinite(v) or v == float(beside):
        return f"{v:g}"
    for digits in range(6, 18):  # 17 significant digits tell any two doubles apart
        text = f"{v:.{digits}g}"
        if text != f"{float(beside):.{digits}g}":
            return text
    return repr(v)


def _reads_back(text: str, value) -> bool:
    """``text`` parsed as ``value``'s own type is ``value`` (a float32 read as a float32)."""
    try:
        return type(value)(text) == value
    except (TypeError, ValueError, ArithmeticError):
        return False


def image_hint(value, shape) -> str:
    """What to pass instead, for ``value`` (of ``shape``) given where one ``(rows, cols)`` image
    belongs: ``radiokit.io.read`` gives ``(n, rows, cols)`` always, so a newcomer's first call
    passes ``read(path).data`` (a stack of one frame) or the path itself. "" otherwise.

    >>> image_hint("a.tif", ())
    ': a file name, not an image: radiokit.io.read(path).data[0] reads its first frame'
    >>> image_hint(None, (1, 8, 8)), image_hint(None, (3, 8, 8))
    (': a stack of one frame, as radiokit.io.read gives: pass .data[0]', '')
    """
    if isinstance(value, (str, bytes, os.PathLike)):
        return ": a file name, not an image: radiokit.io.read(path).data[0] reads its first frame"
    if len(shape) == 3 and shape[0] == 1:
        return ": a stack of one frame, as radiokit.io.read gives: pass .data[0]"
    return ""


def refuse_masked(value, name: str, mask_keyword: str | None = None) -> None:
    """Raise ValueError if ``value`` is a numpy masked array: ``np.asarray`` drops its mask, so its
    masked pixels (dead ones, a NaN border filled with anything) were measured as data, silently
    (``contrast`` of an image whose masked inclusion held 1e6 gave 857142). ``mask_keyword`` names
    the function's own keyword for pixels to leave out, if it has one. numpy is not imported here:
    without ``numpy.ma`` loaded no value can be a masked array.

    >>> import numpy as np
    >>> refuse_masked(np.zeros(2), "image")
    >>> refuse_masked(np.ma.masked_array([1.0, 2.0], mask=[True, False]), "image", "mask")
    Traceback (most recent call last):
    ...
    ValueError: image is a masked array, whose mask would be ignored: pass a plain array (its .filled(value)), and mask= (True on the pixels to use) to leave the masked ones out
    """
    ma = sys.modules.get("numpy.ma")
    if ma is None or not isinstance(value, ma.MaskedArray):
        return
    # True on the pixels to use: numpy's masks are True on the pixels to leave out
    how = f", and {mask_keyword}= (True on the pixels to use) to leave the masked ones out" if mask_keyword else ""
    raise ValueError(
        f"{name} is a masked array, whose mask would be ignored: pass a plain array (its .filled(value)){how}"
    )


def toml_loads(text: str) -> dict:
    """:func:`tomllib.loads` of a user's TOML (a scene, a protocol, a simulated file's scene), a
    document nested past :data:`radiokit._json.MAX_DEPTH` levels, the rule JSON has, refused as
    :class:`tomllib.TOMLDecodeError`, which each reader already words as its file's error.

    Why: :mod:`tomllib` parses by recursion, about three calls a level of arrays or inline
    tables, so a file nested a few hundred deep raised RecursionError, which no reader's ``except
    TOMLDecodeError`` caught: ``sim run``, ``acquire`` and ``process`` ended in a traceback (s52).
    A dotted key nests a level a part with no bracket, and tomllib's cost is quadratic in its
    parts (a tuple per prefix): refused unparsed past the depth (:func:`_long_dotted_key`)."""
    import tomllib

    from radiokit._json import MAX_DEPTH, within_depth  # late: numpy, which this module does without

    deep = tomllib.TOMLDecodeError(f"nests deeper than {MAX_DEPTH} levels, past any TOML radiokit reads")
    if _long_dotted_key(MAX_DEPTH).search(text):
        raise deep
    return within_depth(tomllib.loads, text, deep)


@functools.cache
def _long_dotted_key(depth: int):
    """A pattern finding a TOML key of more than ``depth`` dotted parts (bare, "basic" or
    'literal') where a key may start: a line's start, a table header's bracket, an inline
    table's brace or comma. Such a key nests more than ``depth`` levels, which
    :func:`toml_loads` refuses anyway. Why before parsing: tomllib keeps a tuple per prefix of a
    key, 10 000 parts took 400 MB, and one of 100 000 (a 200 KB file) was killed by the kernel
    at 40 GB (review s52rvoff). Text in a value or a comment matches only as 33 dotted words
    after a comma or a bracket, which no scene or protocol holds."""
    import re

    part = r"""(?:[A-Za-z0-9_-]+|"(?:[^"\\\n]|\\.)*"|'[^'\n]*')"""
    return re.compile(rf"(?:^|[\[{{,])[ \t]*{part}(?:[ \t]*\.[ \t]*{part}){{{depth}}}", re.MULTILINE)
