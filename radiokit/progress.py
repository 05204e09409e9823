"""Progress bars on stderr: :func:`tqdm`, tqdm's bar drawn to a width also where the terminal reports none.

A terminal may report 0 columns (a fresh pseudo-terminal, ``stty cols 0`` in some CI shells):
tqdm then squeezed every bar into one cell and cut its last character. Such a terminal gets
``COLUMNS`` when that is a positive width, else :data:`FALLBACK_COLUMNS`.
"""

from __future__ import annotations

import os
import sys

__all__ = ["tqdm", "columns", "FALLBACK_COLUMNS"]

#: The width a bar takes on a terminal that reports none (and no COLUMNS): a classic terminal's.
FALLBACK_COLUMNS = 80


def columns(stream) -> int | None:
    """The width to draw a bar in on ``stream``: None (tqdm asks the terminal, as it does) unless
    ``stream`` is a terminal that reports 0 columns; then ``COLUMNS`` if it is a positive whole
    number, else :data:`FALLBACK_COLUMNS`."""
    try:
        if os.get_terminal_size(stream.fileno()).columns > 0:
            return None
    except (AttributeError, ValueError, OSError):  # not a terminal (tqdm's own rules then)
        return None
    env = os.environ.get("COLUMNS", "").strip()
    return int(env) if env.isdigit() and int(env) > 0 else FALLBACK_COLUMNS


def tqdm(*args, **kwargs):
    """``tqdm.auto.tqdm(*args, **kwargs)``, given a width (:func:`columns`) on a terminal that
    reports none. Like tqdm's, it draws one column short of the width: a bar the full width
    of the terminal wraps onto a new line at every redraw.

    A bar made with ``disable=True`` (``-q``, ``progress=False``) is tqdm's own class, which
    tqdm.auto's extends with notebook and asyncio support; it draws nothing either way. Why:
    tqdm.auto imports asyncio, about 0.03 CPU s of every quiet command's start."""
    if kwargs.get("disable") is True:
        from tqdm.std import tqdm as _quiet

        return _quiet(*args, **kwargs)
    from tqdm.auto import tqdm as _tqdm

    if kwargs.get("ncols") is None and not kwargs.get("disable"):
        width = columns(kwargs.get("file") or sys.stderr)
        if width is not None:
            kwargs["ncols"] = max(1, width - 1)
    return _tqdm(*args, **kwargs)
