"""Closed-form chord lengths: the references projections are checked against.

All lengths in the units of the inputs. The first four functions are for parallel beams along one
axis and take the two coordinates perpendicular to it; the ``ray_*`` functions take arbitrary
lines (origin and direction, e.g. the rays of a cone beam) and return the length of the line's
intersection with the solid.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sphere_chord", "ellipsoid_chord", "cone_side_chord", "box_chord", "ray_sphere_chord", "ray_ellipsoid_chord"]


def sphere_chord(u, v, radius, centre=(0.0, 0.0)):
    """Chord of a sphere along the beam at detector coordinates (u, v): ``2 sqrt(r^2 - rho^2)``."""
    rho2 = (np.asarray(u) - centre[0]) ** 2 + (np.asarray(v) - centre[1]) ** 2
    return 2.0 * np.sqrt(np.clip(radius * radius - rho2, 0.0, None))


def ellipsoid_chord(u, v, a, b, c, centre=(0.0, 0.0)):
    """Chord of the ellipsoid ``(x/a)^2 + (y/b)^2 + (z/c)^2 <= 1`` along z at (x, y) = (u, v):
    ``2 c sqrt(1 - (u/a)^2 - (v/b)^2)``."""
    q = ((np.asarray(u) - centre[0]) / a) ** 2 + ((np.asarray(v) - centre[1]) / b) ** 2
    return 2.0 * c * np.sqrt(np.clip(1.0 - q, 0.0, None))


def cone_side_chord(u, h, r_bottom, r_top, height):
    """Chord of a truncated cone seen from the side (beam perpendicular to its axis).

    ``u`` is the lateral offset from the axis, ``h`` the height above the bottom face; the radius
    varies linearly from ``r_bottom`` at ``h = 0`` to ``r_top`` at ``h = height``.
    """
    h = np.asarray(h, dtype=float)
    inside = (h >= 0) & (h <= height)
    r = r_bottom + (r_top - r_bottom) * np.clip(h / height, 0.0, 1.0)
    return np.where(inside, 2.0 * np.sqrt(np.clip(r * r - np.asarray(u) ** 2, 0.0, None)), 0.0)


def box_chord(u, v, size_u, size_v, depth, centre=(0.0, 0.0)):
    """Chord of an axis-aligned box: ``depth`` inside its (size_u x size_v) footprint, else 0."""
    inside = (np.abs(np.asarray(u) - centre[0]) <= size_u / 2) & (np.abs(np.asarray(v) - centre[1]) <= size_v / 2)
    return np.where(inside, float(depth), 0.0)


def ray_ellipsoid_chord(origin, direction, semi_axes, centre=(0.0, 0.0, 0.0)):
    """Length of the intersection of lines with the solid axis-aligned ellipsoid
    ``sum(((X - centre) / semi_axes)^2) <= 1``.

    Parameters
    ----------
    origin, direction : array_like (3, ...)
        A point on each line and its direction (any non-zero length); broadcast together.
    semi_axes, centre : sequence of 3 floats

    Notes
    -----
    Scaling by the semi-axes maps the ellipsoid to the unit ball and the line to ``o + s d`` with
    ``o = (origin - centre) / a``, ``d = direction / a``. Taking ``o`` as the line's point nearest
    the centre (``o <- o - (o.d / |d|^2) d``, which also avoids cancellation for distant origins),
    the line is inside the ball for ``|s| <= sqrt(1 - |o|^2) / |d|``: the chord is
    ``2 sqrt((1 - |o|^2) / |d|^2) |direction|``, or 0 when ``|o| > 1``. The whole line counts: for a
    cone beam the source must lie outside the solid.

    Examples
    --------
    >>> float(ray_ellipsoid_chord([0.0, 0.0, -100.0], [0.0, 0.0, 1.0], (1.0, 2.0, 3.0)))
    6.0
    """
    a = np.asarray(semi_axes, dtype=float).reshape((3,) + (1,) * (np.ndim(origin) - 1))
    c = np.asarray(centre, dtype=float).reshape(a.shape)
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    o = (origin - c) / a
    d = direction / a
    dd = np.sum(d * d, axis=0)
    o = o - np.sum(o * d, axis=0) / dd * d  # the line's point nearest the centre: no cancellation
    disc = np.clip(1.0 - np.sum(o * o, axis=0), 0.0, None)
    return 2.0 * np.sqrt(disc / dd) * np.sqrt(np.sum(direction * direction, axis=0))


def ray_sphere_chord(origin, direction, radius, centre=(0.0, 0.0, 0.0)):
    """Length of the intersection of lines with a solid sphere: ``2 sqrt(r^2 - d^2)`` with ``d`` the
    distance from the centre to the line (see :func:`ray_ellipsoid_chord` for the arguments).

    Examples
    --------
    >>> float(ray_sphere_chord([-500.0, 3.0, 0.0], [1.0, 0.0, 0.0], 5.0))
    8.0
    """
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    c = np.asarray(centre, dtype=float).reshape((3,) + (1,) * (origin.ndim - 1))
    d = direction / np.sqrt(np.sum(direction * direction, axis=0))
    w = origin - c
    w = w - np.sum(w * d, axis=0) * d  # from the centre to the line's nearest point
    dist2 = np.sum(w * w, axis=0)
    return 2.0 * np.sqrt(np.clip(radius * radius - dist2, 0.0, None))
