"""Strict JSON for everything radiokit writes: no ``NaN``, ``Infinity`` or ``-Infinity``.

Python's :func:`json.dumps` writes those bare words by default; they are not JSON (RFC 8259), and
strict readers (jq, JavaScript's ``JSON.parse``, ``json.loads(..., parse_constant=...)``) refuse
the whole file. A noiseless background makes a CNR infinite, so a results.json hit it.

The rule: a non-finite number is written ``null``, and the top-level object's ``"not_finite"``
maps the JSON Pointer (RFC 6901) of each such null to ``"Infinity"``, ``"-Infinity"`` or
``"NaN"``, so that :func:`restore` gives the numbers back exactly. A ``null`` that the map does
not name was ``None`` (not recorded). The key is present only when something was not finite.
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = [
    "NOT_FINITE",
    "MAX_DEPTH",
    "MAX_CHARS",
    "strict",
    "dumps",
    "dumps_readable",
    "loads",
    "loads_record",
    "loads_checked",
    "restore",
    "too_deep",
    "Refused",
    "TooDeep",
    "TooLong",
]

#: the top-level key holding the map ``JSON pointer -> "Infinity" | "-Infinity" | "NaN"``
NOT_FINITE = "not_finite"
_WORDS = {"Infinity": math.inf, "-Infinity": -math.inf, "NaN": math.nan}

#: The deepest nesting of objects and arrays radiokit reads from any file (:func:`loads_record`):
#: its own records (a calibration's provenance nests 3 deep: inputs, one input, its fields; a
#: results.json 4; a corrected stack's description, the provenance within, 4) and other programs'
#: JSON it reads (tifffile's shape description 2, a Micro-Manager summary a few). Why a limit: json
#: reads a document up to Python's recursion limit (about 1000 levels, less the caller's stack),
#: and everything that walks it afterwards (strict(), json.dumps, str) recursed again from deeper
#: in the stack: a hand-made provenance 900 deep loaded, then `radiokit correct` died of
#: RecursionError writing it (s51); a results.json's "paper" 900 deep, Results.to_json (s52).
MAX_DEPTH = 32
#: The longest JSON text radiokit parses from a file's metadata (:func:`loads_checked`; a
#: results.json file has its own, larger bound). Its records are KBs: a corrected stack's
#: description, the calibration's provenance within, lists a time per dark and flat, about 40 KB
#: for 1000 of each. Why a limit: json builds up to ~25 bytes of Python objects per byte of text
#: (``[[],[],...``), and a reader parses metadata at each open: a 12 MB description of 10**6 keys
#: was parsed 8 times by one ``calibrate`` of two files (s52).
MAX_CHARS = 4 * 2**20


def too_deep(value, limit: int = MAX_DEPTH) -> bool:
    """Whether ``value`` (parsed JSON) nests dicts and lists more than ``limit`` levels deep;
    walked with a list, not by recursion (the point is to judge what recursion cannot walk)."""
    level = [value]
    for _ in range(limit):
        level = [
            v
            for x in level
            if isinstance(x, (dict, list, tuple))
            for v in (x.values() if isinstance(x, dict) else x)
            if isinstance(v, (dict, list, tuple))
        ]
        if not level:
            return False
    return True


def _word(x: float) -> str:
    return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")


def _escape(key) -> str:
    # a non-string key is named as json.dumps writes it (True -> "true", None -> "null"), so
    # that the pointer finds it in the file
    text = key if isinstance(key, str) else json.dumps(key)
    return text.replace("~", "~0").replace("/", "~1")


def _walk(value, pointer: str, found: dict):
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        found[pointer] = _word(float(value))
        return None
    if isinstance(value, dict):
        return {k: _walk(v, f"{pointer}/{_escape(k)}", found) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_walk(v, f"{pointer}/{i}", found) for i, v in enumerate(value)]
    return value


def strict(value):
    """``value`` with every non-finite float replaced by ``None``; a dict also gets
    ``"not_finite"`` naming them (a list or a bare number cannot carry the map: nulls only)."""
    found: dict = {}
    out = _walk(value, "", found)
    if found and isinstance(out, dict):
        out[NOT_FINITE] = found
    return out


def dumps(value, **kwargs) -> str:
    """:func:`json.dumps` of :func:`strict` ``(value)``, refusing any non-finite number left."""
    return json.dumps(strict(value), allow_nan=False, **kwargs)


def dumps_readable(value, where: str, what: str, limit: int = MAX_CHARS, **kwargs) -> str:
    """:func:`dumps` of ``value`` (``what``: the record, as a message names it), refused where
    radiokit's readers would refuse it back (:func:`loads_checked`): a ValueError naming ``where``
    (the file to be written) and ``what``, "not written", when it nests past :data:`MAX_DEPTH`
    levels or its text passes ``limit`` characters. Why: radiokit wrote such records (a corrected
    stack's 50 000 sources, 4.6 MB) that its own readers then kept as text or refused (s53); a
    writer calls this before it makes its file, so a refusal leaves nothing behind."""
    if too_deep(value):  # first: json.dumps recursed past Python's limit on a deep one
        raise ValueError(
            f"{where}: not written: {what} nests deeper than {MAX_DEPTH} levels, past any JSON radiokit reads"
        )
    text = dumps(value, **kwargs)
    if len(text) > limit:
        raise ValueError(
            f"{where}: not written: {what} would be {len(text)} characters of JSON, past the {limit} radiokit reads back"
        )
    return text


def loads(text):
    """:func:`json.loads` and :func:`restore`: radiokit's own JSON read back with its numbers."""
    return restore(json.loads(text))


class Refused(ValueError):
    """JSON a file holds that radiokit's rule refuses unread or unkept (:func:`loads_checked`):
    nested too deep (:class:`TooDeep`) or too long (:class:`TooLong`)."""


class TooDeep(Refused):
    """A record nested past :data:`MAX_DEPTH` levels."""


class TooLong(Refused):
    """JSON text longer than its reader's bound (:data:`MAX_CHARS`)."""


def loads_record(text, where="JSON", limit=MAX_CHARS):
    """:func:`loads` of JSON a file holds (a calibration's provenance, a results.json, a TIFF's
    description, an HDF5 attribute), refused past :data:`MAX_DEPTH` levels: :class:`TooDeep` (a
    ValueError) naming ``where``, whether json could read it (a hand-made one 900 deep) or not
    (100 000 deep: its RecursionError). Not JSON: json's ValueError. The one rule for every
    reader: each decides whether such a file is refused (what it steers) or its JSON ignored."""
    return restore(loads_checked(text, where, limit), where)


def loads_checked(text, where="JSON", limit=MAX_CHARS):
    """:func:`json.loads` refused (:class:`Refused`, naming ``where``) past ``limit`` characters,
    unparsed (:class:`TooLong`), or past :data:`MAX_DEPTH` levels (:class:`TooDeep`), the numbers
    left as the text gives them: :func:`loads_record` less :func:`restore`, for a reader that puts
    them back itself (``results.Results.from_json``)."""
    if text is not None and len(text) > limit:
        raise TooLong(f"{where} is {len(text)} characters long, past the {limit} radiokit reads")
    return within_depth(
        json.loads, text, TooDeep(f"{where} nests deeper than {MAX_DEPTH} levels, past any JSON radiokit reads")
    )


def within_depth(parse, text, deep: Exception):
    """``parse(text)`` (JSON's or TOML's), raising ``deep`` where the value nests past
    :data:`MAX_DEPTH` levels: the parser's own RecursionError on the way there, or the value's
    depth (:func:`too_deep`) after."""
    try:
        value = parse(text)
    except RecursionError:
        raise deep from None
    if too_deep(value):
        raise deep
    return value


def restore(value, where="JSON"):
    """Put back the numbers a top-level ``"not_finite"`` map names (the map is removed; the
    argument is not changed). ValueError, naming ``where``, for a map that names no ``null`` of
    the document or a word other than Infinity, -Infinity and NaN (a hand-edited file)."""
    if not isinstance(value, dict) or NOT_FINITE not in value:
        return value
    out = dict(value)
    marks = out.pop(NOT_FINITE)
    if not isinstance(marks, dict):
        raise ValueError(f"{where}: {NOT_FINITE!r} is a {type(marks).__name__}, not an object of JSON pointers")
    for pointer, word in marks.items():
        if not isinstance(word, str) or word not in _WORDS:
            raise ValueError(f"{where}: {NOT_FINITE!r} {pointer!r} is {word!r}: expected Infinity, -Infinity or NaN")
        parts = [p.replace("~1", "/").replace("~0", "~") for p in pointer.split("/")[1:]]
        if not pointer.startswith("/") or not parts or parts[0] == NOT_FINITE:
            raise ValueError(f"{where}: {NOT_FINITE!r} {pointer!r} is not a JSON pointer into the document")
        parent, key = out, parts[-1]
        try:
            for part in parts[:-1]:
                index = _index(parent, part)
                child = parent[index]
                # copied on the way down: the caller's document is left as it was
                child = dict(child) if isinstance(child, dict) else list(child) if isinstance(child, list) else child
                parent[index] = child
                parent = child
            key = _index(parent, key)
            if parent[key] is not None:
                raise LookupError
        except (LookupError, TypeError, ValueError):
            raise ValueError(f"{where}: {NOT_FINITE!r} {pointer!r} names no null of the document") from None
        parent[key] = _WORDS[word]
    return out


def _index(container, part: str):
    if isinstance(container, list):
        if not part.isdigit():
            raise ValueError(part)
        return int(part)
    if not isinstance(container, dict):
        raise TypeError(part)
    return part
