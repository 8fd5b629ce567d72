"""Signed headings and dips (degrees) of earth-frame (ENU) vectors, for the extended observations' kernels."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def wrap_deg(deg):
    """An angle wrapped to [−180°, 180°)."""
    return (deg + 180.0) % 360.0 - 180.0


@njit(cache=True, inline="always")
def planar_heading(v):
    """Heading (°) of an ENU vector in the horizontal plane, atan2(east, north)."""
    return np.rad2deg(np.arctan2(v[0], v[1]))


@njit(cache=True, inline="always")
def dip_deg(v, norm, default):
    """Dip (°, positive down) of an ENU vector ``v`` of length ``norm``; ``default`` for a zero vector."""
    return np.rad2deg(np.arcsin(min(1.0, max(-1.0, -v[2] / norm)))) if norm > 0 else default


@njit(cache=True, inline="always")
def norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
