"""File names as messages print them."""

from __future__ import annotations

import unicodedata

#: Unicode categories of the characters that move or hide text on a terminal: controls (a newline,
#: an escape), line and paragraph separators, and formats (a bidirectional override). Not
#: surrogates: a name's bytes that are not UTF-8 (lone surrogates in Python) print as ``\xNN``
#: by the command's own output codec (radiokit.cli._names_as_bytes).
_HIDING = ("Cc", "Cf", "Zl", "Zp")


def shown(name) -> str:
    """``name`` (a file's, or any text naming one) as a message prints it: as it is, unless it
    holds a control character (a newline, an escape, a bidirectional override) or a backslash,
    then quoted and escaped as Python's ``repr`` writes it, ``'out\\nx.h5'``: it reads back
    (``ast.literal_eval``) as the name.

    Why: an output named ``"out\\nx.h5"`` was printed raw, ``-> out`` on one line and ``x.h5`` on
    the next, so the name a user read was not the file's, and an escape sequence in a name
    reached the terminal. The backslash too (s52): a file literally named ``a\\nb.tif`` printed
    as the one holding a newline does inside a message's own quotes. Quoted only then: every plain
    name stays as the user typed it, and one printed unquoted holds no backslash, so no escape.

    >>> shown("cal.h5"), shown("cal\\nx.h5"), shown("cal\\\\nx.h5")
    ('cal.h5', "'cal\\\\nx.h5'", "'cal\\\\\\\\nx.h5'")
    """
    text = str(name)
    if "\\" not in text and not any(unicodedata.category(c) in _HIDING for c in text):
        return text
    escaped = (
        "\\\\"
        if c == "\\"
        else "\\'"
        if c == "'"
        else c.encode("unicode_escape").decode("ascii")
        if unicodedata.category(c) in _HIDING
        else c
        for c in text
    )
    return "'" + "".join(escaped) + "'"


def linked(name, target=None) -> str:
    """``name`` as :func:`shown` prints it, and where it is a symbolic link, what it points at:
    ``ln.h5 (a link to res/out.h5)``, each name quoted alone. Why: the two were quoted as one
    name, ``'l\\nn.h5 (a link to t.h5)'``, the words "a link to" read as part of it (s52)."""
    return shown(name) if target is None else f"{shown(name)} (a link to {shown(target)})"


def controls_escaped(text) -> str:
    """``text`` with every character that moves or hides text on a terminal, other than
    whitespace, escaped as :func:`shown` escapes it (``\\x1b``, ``\\u202e``), unquoted.

    Why: a line a command prints of an error quotes what a file holds too, not only the names
    it was given (which :func:`shown` prints): a hostile HDF5 file's dataset named
    ``ESC]2;...BEL`` set the terminal's title from ``radiokit info``'s error line (review
    s51rv2). Whitespace is left to the one line's folding.

    Not a backslash, unlike :func:`shown`: this escapes a whole message, which holds names
    already printed as names print (``'a\\\\nb'``) and ``repr`` of a user's text, whose
    backslashes are escapes already, and a second escape turned a newline's ``\\n`` into a
    backslash's. A name the file holds (an HDF5 dataset's) is therefore printed by :func:`shown`
    where the message names it: a dataset named ``a\\\\nb`` printed ``/a\\\\nb`` through this
    alone, as a newline's escape reads, and one named ``a<newline>b`` as ``/a b`` (s53). This is the net
    for a control character left in any other text a message quotes."""
    return "".join(
        c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in _HIDING and not c.isspace() else c
        for c in str(text)
    )
