"""The registration file ``radiokit register`` writes: one pull field and the image it makes.

``/`` (``@default = "entry"``)
``/entry`` (NXentry, ``@default = "registration"``)
``/entry/registration`` (NXdata, ``@signal = "registered"``)
    ``registered`` (rows, cols) float32: the moving image warped onto the fixed one (the plot);
    ``displacement`` (2, rows, cols) float32: the pull field, pixels, (row, col);
    ``confidence`` (rows, cols) float32 in [0, 1], when given: where the images observe the motion
    (``radiokit.register.Registration.confidence``; >= 0.5 observed, elsewhere the field is the
    regulariser's guess);
    ``@method``, ``@fixed``, ``@moving`` (the input files), ``@convention``,
    ``@quality_*``: :class:`radiokit.register.Quality`'s fields.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import h5py
import numpy as np

from radiokit._names import shown
from radiokit.errors import FormatError
from radiokit.io._atomic import atomic_h5
from radiokit.io._experiment import ENTRY, check_links, checked_dataset
from radiokit.io._layout import ReadBudget, open_layout, path_text, text

__all__ = ["REGISTRATION", "RegistrationRecord", "write_registration", "read_registration"]

REGISTRATION = f"{ENTRY}/registration"
REGISTERED = f"{REGISTRATION}/registered"
DISPLACEMENT = f"{REGISTRATION}/displacement"
CONFIDENCE = f"{REGISTRATION}/confidence"
CONVENTION = "pull, pixels, (row, col): moving(x + d(x)) matches fixed(x)"


@dataclass(frozen=True)
class RegistrationRecord:
    """One registration of a moving image onto a fixed one.

    Attributes
    ----------
    method : str
        The registration method (``radiokit.register``'s name for it).
    fixed, moving : str
        Where the two images came from.
    displacement : (2, rows, cols) float32
        The pull field, pixels, (row, col): ``moving(x + d(x))`` matches ``fixed(x)``.
    registered : (rows, cols) float32
        The moving image warped by ``displacement``.
    quality : mapping str -> number, bool or str
        The registration's quality figures (``radiokit.register.Quality``'s fields).
    confidence : (rows, cols) float32 or None
        Where the images observe the motion (``radiokit.register.Registration.confidence``):
        the field is measured where it is >= 0.5 and the regulariser's guess elsewhere. None in
        a file written without it (before session 18).
    """

    method: str
    fixed: str
    moving: str
    displacement: np.ndarray
    registered: np.ndarray
    quality: Mapping = field(default_factory=dict)
    confidence: np.ndarray | None = None


def write_registration(path, record: RegistrationRecord, *, overwrite=False, inputs=()) -> None:
    """Write ``record`` to ``path`` atomically (see :func:`radiokit.io.atomic_h5`).

    ``overwrite=False`` refuses an existing ``path``; ``inputs`` are files it must not be.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from radiokit.io import RegistrationRecord, read, read_registration, write_registration
    >>> path = os.path.join(tempfile.mkdtemp(), "reg.h5")
    >>> image = np.ones((4, 5), np.float32)
    >>> write_registration(path, RegistrationRecord("rc", "a.h5", "b.h5", np.zeros((2, 4, 5)), image, {"ok": True}))
    >>> read(path).shape, read_registration(path).quality
    ((1, 4, 5), {'ok': True})
    """
    displacement = np.asarray(record.displacement, np.float32)
    registered = np.asarray(record.registered, np.float32)
    if displacement.shape != (2,) + registered.shape:
        raise ValueError(
            f"{shown(path)}: displacement {displacement.shape} does not match the registered image "
            f"{registered.shape}; expected (2, rows, cols)"
        )
    confidence = None if record.confidence is None else np.asarray(record.confidence, np.float32)
    if confidence is not None and confidence.shape != registered.shape:
        raise ValueError(
            f"{shown(path)}: confidence {confidence.shape} does not match the registered image {registered.shape}"
        )
    with atomic_h5(path, overwrite=overwrite, inputs=inputs) as h5:
        h5.attrs["default"] = ENTRY
        entry = h5.create_group(ENTRY)
        entry.attrs["NX_class"] = "NXentry"
        entry.attrs["default"] = REGISTRATION.rsplit("/", 1)[1]
        g = h5.create_group(REGISTRATION)
        g.attrs["NX_class"] = "NXdata"
        g.attrs["signal"] = REGISTERED.rsplit("/", 1)[1]
        g.attrs["method"] = record.method
        g.attrs["fixed"], g.attrs["moving"] = path_text(record.fixed), path_text(record.moving)
        g.attrs["convention"] = CONVENTION
        h5.create_dataset(DISPLACEMENT, data=displacement, compression="lzf")
        h5.create_dataset(REGISTERED, data=registered, compression="lzf").attrs["interpretation"] = "image"
        if confidence is not None:
            h5.create_dataset(CONFIDENCE, data=confidence, compression="lzf").attrs["interpretation"] = "image"
        for k, v in record.quality.items():
            g.attrs[f"quality_{k}"] = v


def read_registration(path, *, allow_external=False) -> RegistrationRecord:
    """Read a file :func:`write_registration` wrote.

    Raises
    ------
    FormatError
        The file lacks the registration layout.
    """
    with open_layout(path, "a radiokit registration file") as h5:
        check_links(path, h5, REGISTRATION, allow_external)
        if not isinstance(h5.get(REGISTRATION), h5py.Group):
            raise FormatError(path, f"lacks /{REGISTRATION}: not a radiokit registration file")
        g = h5[REGISTRATION]
        registered = checked_dataset(path, h5, REGISTERED, "f", (2,), allow_external)
        displacement = checked_dataset(path, h5, DISPLACEMENT, "f", (3,), allow_external)
        if displacement.shape != (2,) + registered.shape:
            raise FormatError(
                path,
                f"/{DISPLACEMENT} is {displacement.shape}; the registered image "
                f"{registered.shape} needs (2, rows, cols)",
            )
        confidence = None
        if CONFIDENCE in h5:  # files written before session 18 lack it
            confidence = checked_dataset(path, h5, CONFIDENCE, "f", (2,), allow_external)
            if confidence.shape != registered.shape:
                raise FormatError(
                    path, f"/{CONFIDENCE} is {confidence.shape}; the registered image is {registered.shape}"
                )
        quality = {k[len("quality_") :]: _plain(v) for k, v in g.attrs.items() if k.startswith("quality_")}
        budget = ReadBudget(path)
        return RegistrationRecord(
            method=_plain(g.attrs.get("method", "")),
            fixed=_plain(g.attrs.get("fixed", "")),
            moving=_plain(g.attrs.get("moving", "")),
            displacement=budget.read(displacement),
            registered=budget.read(registered),
            quality=quality,
            confidence=None if confidence is None else budget.read(confidence),
        )


def _plain(value):
    """An attribute as a Python value: str for text, int/float/bool for numpy scalars."""
    if isinstance(value, (bytes, str)):
        return text(value)
    return value.item() if isinstance(value, np.generic) else value
