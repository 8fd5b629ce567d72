"""A magnet held by hand and moved along a path in the world (paper §3.1).

Protocol 1: the disc magnet is held over the stationary MIMU and moved
between 70 cm and 10 cm above it (Figure 7, boundaries A and B). At times
A, B, C of Figure 8 it comes close for a few seconds, at D it stays about a
minute. The path here: the magnet starts far, descends with a smooth
(half-cosine) profile, holds, rises again; a small hand tremor (a few mm,
1–4 Hz) and a slow lateral sway are added, and the disc's axis (its moment)
points roughly down with a small wobble. :func:`tool_path`: a tool brought in
sideways (the two-link world).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit


@dataclasses.dataclass(frozen=True)
class Approach:
    """One approach of the hand-held magnet.

    Attributes:
        start: time the descent begins, s.
        hold: time spent at the near distance, s.
        travel: duration of the descent (and of the rise), s.
    """

    start: float
    hold: float
    travel: float = 2.0


def hand_path(
    t: np.ndarray,
    approaches: list[Approach],
    far: float,
    near: float,
    rng: np.random.Generator,
    tremor_m: float = 0.003,
    sway_m: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Magnet offset from the sensor (world ENU, m) and unit moment direction.

    Args:
        t: (N,) sample times, s.
        approaches: when and how long the magnet comes near.
        far, near: heights above the sensor, m (paper: 0.70 and 0.10).
        rng: generator for tremor, sway and the axis wobble.
        tremor_m: hand tremor amplitude, m; sway_m: lateral sway amplitude, m.

    Returns:
        offset: (N, 3) magnet centre minus sensor position, world, m.
        axis: (N, 3) unit dipole direction, world.
    """
    app = np.array([[a.start, a.hold, a.travel] for a in approaches], float).reshape(-1, 3)
    trem_f = rng.uniform(1.0, 4.0, (3, 3))  # tremor: three sinusoids per axis, 1–4 Hz
    trem_p = rng.uniform(0, 2 * np.pi, (3, 3))
    sway_f = rng.uniform(0.05, 0.2, 2)  # slow lateral sway, 0.05–0.2 Hz
    sway_p = rng.uniform(0, 2 * np.pi, 2)
    tilt_f = rng.uniform(0.1, 0.5, 2)  # wobble of the disc's axis, ±10°
    tilt_p = rng.uniform(0, 2 * np.pi, 2)
    return _path(
        np.ascontiguousarray(t, dtype=float),
        app,
        far,
        near,
        tremor_m,
        sway_m,
        trem_f,
        trem_p,
        sway_f,
        sway_p,
        tilt_f,
        tilt_p,
    )


def tool_path(
    t: np.ndarray,
    approaches: list[Approach],
    far: float,
    near: float,
    azimuth: float,
    rng: np.random.Generator,
    tremor_m: float = 0.003,
    sway_m: float = 0.02,
):
    """A hand-held magnetised tool brought in sideways: offset from the sensor (N, 3) m and unit moment
    direction (N, 3), world (the two-link world's tool; ``t`` (N,) s).

    Along the horizontal direction ``azimuth`` (rad from east) the distance
    goes far → near (half-cosine over ``travel``), holds, and back; a hand
    tremor (three 1–4 Hz sines per axis, ``tremor_m``) and a slow sway
    (0.05–0.2 Hz, ``sway_m``, across the approach) are added. The moment
    points from the tool towards the sensor with a ±15° wobble (0.1–0.5 Hz).
    """
    d = np.full(len(t), far)
    for a in approaches:
        u = (t - a.start) / a.travel
        down = (u >= 0) & (u < 1)
        d[down] = np.minimum(d[down], near + (far - near) * 0.5 * (1 + np.cos(np.pi * u[down])))
        d[(t >= a.start + a.travel) & (t <= a.start + a.travel + a.hold)] = near
        u = (t - a.start - a.travel - a.hold) / a.travel
        up = (u > 0) & (u < 1)
        d[up] = np.minimum(d[up], near + (far - near) * 0.5 * (1 - np.cos(np.pi * u[up])))
    along = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    across = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    f, ph = rng.uniform(1.0, 4.0, (3, 3)), rng.uniform(0.0, 2 * np.pi, (3, 3))
    tremor = tremor_m / 3 * np.sin(2 * np.pi * f[None] * t[:, None, None] + ph[None]).sum(-1)
    sf, sp = rng.uniform(0.05, 0.2, 2), rng.uniform(0.0, 2 * np.pi, 2)
    sway = sway_m * np.sin(2 * np.pi * sf[None] * t[:, None] + sp[None])
    offset = d[:, None] * along + sway[:, :1] * across + sway[:, 1:] * up + tremor
    wf, wp = rng.uniform(0.1, 0.5, 2), rng.uniform(0.0, 2 * np.pi, 2)
    wob = np.deg2rad(15.0) * np.sin(2 * np.pi * wf[None] * t[:, None] + wp[None])
    axis = -along + wob[:, :1] * across + wob[:, 1:] * up
    return offset, axis / np.linalg.norm(axis, axis=1, keepdims=True)


@njit(cache=True)
def _path(t, app, far, near, tremor_m, sway_m, trem_f, trem_p, sway_f, sway_p, tilt_f, tilt_p):
    n = t.shape[0]
    offset = np.zeros((n, 3))
    axis = np.empty((n, 3))
    two_pi = 2.0 * np.pi
    tilt_amp = np.deg2rad(10.0)
    for i in range(n):
        ti = t[i]
        h = far
        for a in range(app.shape[0]):
            start, hold, travel = app[a, 0], app[a, 1], app[a, 2]
            u = (ti - start) / travel
            if 0.0 <= u < 1.0:  # descending
                h = min(h, near + (far - near) * 0.5 * (1.0 + np.cos(np.pi * u)))
            elif start + travel <= ti <= start + travel + hold:
                h = near
            else:
                u = (ti - start - travel - hold) / travel
                if 0.0 < u < 1.0:  # rising
                    h = min(h, near + (far - near) * 0.5 * (1.0 - np.cos(np.pi * u)))
        offset[i, 2] = h
        for k in range(3):
            s = 0.0
            for j in range(3):
                s += np.sin(two_pi * trem_f[k, j] * ti + trem_p[k, j])
            offset[i, k] += tremor_m / 3.0 * s
        for k in range(2):
            offset[i, k] += sway_m * np.sin(two_pi * sway_f[k] * ti + sway_p[k])
        ax = np.sin(tilt_amp * np.sin(two_pi * tilt_f[0] * ti + tilt_p[0]))
        ay = np.sin(tilt_amp * np.sin(two_pi * tilt_f[1] * ti + tilt_p[1]))
        norm = np.sqrt(ax * ax + ay * ay + 1.0)
        axis[i, 0], axis[i, 1], axis[i, 2] = ax / norm, ay / norm, -1.0 / norm
    return offset, axis
