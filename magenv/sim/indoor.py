"""A spatially varying indoor magnetic field: distant sources (steel
structures, radiators, appliances) modelled as point dipoles fixed in the
world. Far from each source the field changes smoothly with position, a few
µT over metres (the ``gait_field`` survey scenario; issue 4, item 7).
"""

from __future__ import annotations

import numpy as np

from magenv.sim.magnet import dipole_field


def random_sources(rng: np.random.Generator, n: int, distance_m: tuple[float, float],
                   field_at_centre_ut: tuple[float, float], height_m: tuple[float, float] = (-1.0, 1.5)):
    """``n`` dipoles around the origin, fixed in the world.

    Each sits at a horizontal distance in ``distance_m`` from the origin (at a
    random bearing and a height in ``height_m``), with a random direction and a
    moment that makes its own field at the origin (along its axis-weighted
    geometry) between ``field_at_centre_ut``.

    Returns (positions (n, 3) m, moments (n, 3) A·m²), world ENU.
    """
    bearing = rng.uniform(0, 2 * np.pi, n)
    dist = rng.uniform(*distance_m, n)
    pos = np.stack([dist * np.cos(bearing), dist * np.sin(bearing), rng.uniform(*height_m, n)], axis=1)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # |B| of a unit dipole at the origin, µT; scale each moment to the drawn field.
    unit = np.linalg.norm(dipole_field(-pos, direction), axis=1)
    target = rng.uniform(*field_at_centre_ut, n)
    return pos, direction * (target / unit)[:, None]


def sources_field(points: np.ndarray, positions: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Total field (N, 3) µT, world frame, of world-fixed dipoles at ``points`` (N, 3) m."""
    total = np.zeros((len(points), 3))
    for p, m in zip(positions, moments):
        total += dipole_field(points - p, np.broadcast_to(m, points.shape).copy())
    return total


def nearest_distance(points: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(N,) distance, m, from each point to the nearest source."""
    d = np.linalg.norm(points[:, None, :] - positions[None], axis=2)
    return d.min(axis=1)
