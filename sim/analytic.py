"""Closed-form chord lengths: the references projections are checked against.

All lengths in the units of the inputs; the beam is parallel to one axis and the functions take
the two coordinates perpendicular to it.
"""
from __future__ import annotations

import numpy as np

__all__ = ["sphere_chord", "ellipsoid_chord", "cone_side_chord", "box_chord"]


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
