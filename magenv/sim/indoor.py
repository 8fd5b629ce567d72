"""A spatially varying indoor magnetic field: distant sources (steel
structures, radiators, appliances) modelled as point dipoles fixed in the
world. Far from each source the field changes smoothly with position, a few
µT over metres (the ``gait_field`` survey scenario; issue 4, item 7); and a
lab's weak field, zero at a reference point (the two-link world).
"""

from __future__ import annotations

import numpy as np

from magenv.sim.magnet import dipole_field


def random_sources(
    rng: np.random.Generator,
    n: int,
    distance_m: tuple[float, float],
    field_at_centre_ut: tuple[float, float],
    height_m: tuple[float, float] = (-1.0, 1.5),
):
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


def lab_field(rng: np.random.Generator, p0: np.ndarray, strength_ut: float, radius: float, n_src: int = 3):
    """A weak lab field (benches, floor): ``n_src`` random dipoles 0.4–0.9 m from ``p0``, mostly below it.

    Returns a function p (N, 3) m → field (N, 3) µT, world, zero at ``p0``, with mean |field|
    ``strength_ut`` over the sphere of ``radius`` m about p0.
    """
    dirs = rng.normal(size=(n_src, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2])  # mostly below and around (floor, benches)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pos = p0 + dirs * rng.uniform(0.4, 0.9, (n_src, 1))
    mom = rng.normal(size=(n_src, 3))
    ref = sources_field(p0[None], pos, mom)

    def raw(p):
        return sources_field(p, pos, mom) - ref

    probe = fibonacci_sphere(40) * radius + p0
    mean = np.linalg.norm(raw(probe), axis=1).mean()
    scale = strength_ut / mean if mean > 0 else 0.0
    return lambda p: scale * raw(p)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) roughly even unit vectors (Fibonacci sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
