"""The undisturbed geomagnetic field by location.

The Earth field in ENU is ``magenv.quaternion.earth_field(norm, dip)``; here
are the locations magenv knows and the range a random location is drawn from.
"""

from __future__ import annotations

import numpy as np

#: Fan et al. 2017 §2.6: m0 = 0.46 Gs, θ0 = 49.6° (their laboratory).
PAPER = (46.0, 49.6)
#: BROAD recordings, Berlin: about 44.5 µT, dip about 69°.
BERLIN = (44.5, 69.0)

#: Plausible range over inhabited latitudes (IGRF: 22–67 µT overall).
NORM_RANGE_UT = (25.0, 65.0)
#: Dip range, degrees (positive down): from the southern mid-latitudes to the
#: northern high latitudes, excluding the magnetic poles.
DIP_RANGE_DEG = (-70.0, 78.0)


def random_location(rng: np.random.Generator, norm_range=NORM_RANGE_UT, dip_range=DIP_RANGE_DEG) -> tuple[float, float]:
    """A random (field magnitude µT, dip °) drawn uniformly from the ranges."""
    return float(rng.uniform(*norm_range)), float(rng.uniform(*dip_range))


def dip_angle(b: np.ndarray) -> np.ndarray:
    """Dip of field vectors (..., 3) given in ENU, degrees (positive down)."""
    b = np.asarray(b, float)
    return np.rad2deg(np.arctan2(-b[..., 2], np.hypot(b[..., 0], b[..., 1])))
