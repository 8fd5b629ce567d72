"""Permanent magnets and their dipole field (closed form, numba).

The paper's disturbance generator uses a disc magnet, Ø15 mm × 2 mm (Fan et
al. 2017, §2.5.3 and §3.1). Far from the magnet its field is that of a point
dipole with moment m = Br·V/µ0 along the disc axis (Br the remanence, V the
volume). ``tests/test_sim_field.py`` compares the dipole with magpylib's
exact field of the same cylinder, over all directions: for the paper's disc
it is within 3.5 % beyond 5 cm, 2 % beyond 7 cm, 1 % beyond 10 cm (the error
falls as (R/r)², R the disc radius); at 2 cm it is > 15 % off.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit

MU0 = 4e-7 * np.pi  # vacuum permeability, T·m/A


@dataclasses.dataclass(frozen=True)
class DiscMagnet:
    """An axially magnetised disc (cylinder) magnet.

    Attributes:
        diameter: m (paper: 0.015).
        thickness: m (paper: 0.002).
        remanence: Br, T (sintered NdFeB: 1.1–1.4; default 1.25, grade ~N40).
    """

    diameter: float = 0.015
    thickness: float = 0.002
    remanence: float = 1.25

    def __post_init__(self) -> None:
        for key in ("diameter", "thickness", "remanence"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"DiscMagnet.{key} must be a positive number, got {v!r}")

    @property
    def volume(self) -> float:
        """m³."""
        return np.pi * (0.5 * self.diameter) ** 2 * self.thickness

    @property
    def moment(self) -> float:
        """Dipole moment magnitude, A·m² (m = Br·V/µ0)."""
        return self.remanence * self.volume / MU0

    @property
    def mass(self) -> float:
        """kg, at the density of sintered NdFeB (7500 kg/m³)."""
        return 7500.0 * self.volume


@njit(cache=True)
def dipole_field(r, m):
    """Field of point dipoles, µT.

    Args:
        r: (n, 3) vector from the dipole to the field point, m.
        m: (n, 3) dipole moment, A·m² (same frame as ``r``).

    Returns (n, 3) B = µ0/(4π)·(3 r̂ (m·r̂) − m)/|r|³ in µT, same frame.
    """
    n = r.shape[0]
    out = np.empty((n, 3))
    k = 1e-7 * 1e6  # µ0/(4π) in T·m/A, times 1e6 for µT
    for i in range(n):
        d2 = r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1] + r[i, 2] * r[i, 2]
        d = np.sqrt(d2)
        mr = (m[i, 0] * r[i, 0] + m[i, 1] * r[i, 1] + m[i, 2] * r[i, 2]) / d2
        inv3 = k / (d2 * d)
        for j in range(3):
            out[i, j] = inv3 * (3.0 * mr * r[i, j] - m[i, j])
    return out
