"""Drive profiles for the gimbal's three frames (Z, Y, X).

A profile is the commanded joint rate of each frame on the physics time grid,
rad/s, shape (n, 3) in the order (Z, Y, X); the commanded angles are its
integral (trapezoid rule) from the initial angles. The gimbal's servos
(``gimbal.xml``) follow both. Profiles are built by adding pieces to a zero
array, so a pause is simply where all three rates are exactly zero.

Pieces:

* :func:`add_move` — a smooth move of one frame by a given angle, rate shaped
  as a raised cosine (zero rate and acceleration-continuous at both ends):
  the "intermittent slow manual rotations" of protocol 2 (paper §3.2);
* :func:`add_spin` — a constant rate with raised-cosine ramps: the remote
  controlled rotation at ~40, 70, 360 °/s of protocol 3 (paper §3.3).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(eq=False)
class DriveProfile:
    """Commanded motion of the gimbal sampled on the physics grid.

    Attributes:
        rate: physics rate, Hz (grid spacing 1/rate s).
        omega: (n, 3) commanded joint rates, rad/s, order (Z, Y, X).
        angle0: (3,) initial joint angles, rad (ZYX Euler angles of the sensor).
    """

    rate: float
    omega: np.ndarray
    angle0: np.ndarray

    @property
    def n(self) -> int:
        return len(self.omega)

    @property
    def angles(self) -> np.ndarray:
        """(n, 3) commanded joint angles, rad: trapezoid integral of ``omega``."""
        dt = 1.0 / self.rate
        inc = 0.5 * (self.omega[1:] + self.omega[:-1]) * dt
        out = np.empty_like(self.omega)
        out[0] = self.angle0
        np.cumsum(inc, axis=0, out=out[1:])
        out[1:] += self.angle0
        return out

    def still(self) -> np.ndarray:
        """(n,) bool: all three commanded rates exactly zero."""
        return ~np.any(self.omega != 0.0, axis=1)


def empty_profile(duration: float, rate: float, angle0=(0.0, 0.0, 0.0)) -> DriveProfile:
    """A profile of ``duration`` s at ``rate`` Hz with no motion."""
    n = int(round(duration * rate))
    return DriveProfile(rate=float(rate), omega=np.zeros((n, 3)), angle0=np.asarray(angle0, float))


def add_move(profile: DriveProfile, axis: int, start: float, duration: float, angle: float) -> None:
    """Add a smooth move of frame ``axis`` (0=Z, 1=Y, 2=X) by ``angle`` rad.

    Rate ω(t) = angle/T·(1 − cos(2πt/T)) for 0 ≤ t ≤ T (peak 2·angle/T).
    """
    a, b = _steps_near(profile, start, start + duration)
    t = np.arange(a, b) / profile.rate - start
    inside = (t >= 0.0) & (t <= duration)
    tt = t[inside]
    profile.omega[a:b][inside, axis] += angle / duration * (1.0 - np.cos(2.0 * np.pi * tt / duration))


def add_spin(profile: DriveProfile, axis: int, start: float, stop: float, rate: float, ramp: float = 0.5) -> None:
    """Add a spin of frame ``axis`` at ``rate`` rad/s from ``start`` to ``stop`` s.

    The rate rises and falls over ``ramp`` s with a half-cosine shape (0 < ``ramp`` ≤ ``stop`` − ``start``, else
    ValueError: the spin stays within [start, stop]).
    """
    if not 0.0 < ramp <= stop - start:
        raise ValueError(f"spin ramp must lie in (0, stop - start = {stop - start:g}] s, got {ramp!r}")
    a, b = _steps_near(profile, start, stop)
    t = np.arange(a, b) / profile.rate
    w = np.zeros(b - a)
    up = (t >= start) & (t < start + ramp)
    w[up] = 0.5 * (1.0 - np.cos(np.pi * (t[up] - start) / ramp))
    w[(t >= start + ramp) & (t <= stop - ramp)] = 1.0
    down = (t > stop - ramp) & (t <= stop)
    w[down] = 0.5 * (1.0 - np.cos(np.pi * (stop - t[down]) / ramp))
    profile.omega[a:b, axis] += rate * w


def _steps_near(profile: DriveProfile, start: float, stop: float) -> tuple[int, int]:
    """The steps a … b−1 that hold every step in [start, stop] s, with a step to spare at each end: a move
    or spin looks at these only (the same time values t = i/rate as over the whole profile; elsewhere it
    adds nothing)."""
    a = min(profile.n, max(0, int(math.floor(start * profile.rate)) - 1))
    return a, min(profile.n, max(a, int(math.ceil(stop * profile.rate)) + 2))


def intermittent_moves(
    rng: np.random.Generator,
    duration: float,
    rate: float,
    angle0,
    pause_s: tuple[float, float],
    move_s: tuple[float, float],
    amplitude_deg: tuple[float, float],
    start_rest: float,
    end_rest: float = 1.0,
    axes_per_move: tuple[int, int] = (1, 2),
) -> DriveProfile:
    """Pauses alternating with smooth moves of one or more frames (random).

    Each move turns ``axes_per_move`` randomly chosen frames, each by a random
    signed amplitude in ``amplitude_deg`` over a duration in ``move_s``;
    pauses last ``pause_s``. Motion stops ``end_rest`` s before the end.
    """
    prof = empty_profile(duration, rate, angle0)
    t = start_rest
    while True:
        length = rng.uniform(*move_s)
        if t + length > duration - end_rest:
            break
        k = int(rng.integers(axes_per_move[0], axes_per_move[1] + 1))
        for axis in rng.choice(3, size=k, replace=False):
            amp = np.deg2rad(rng.uniform(*amplitude_deg)) * rng.choice((-1.0, 1.0))
            # Frame Y (pitch) stays within ±80° so ZYX Euler angles stay meaningful.
            pitch_now = prof.angle0[1] + np.sum(prof.omega[: int(t * rate), 1]) / rate
            if axis == 1 and abs(pitch_now + amp) > np.deg2rad(80.0):
                amp = -amp
            add_move(prof, int(axis), t, length, amp)
        t += length + rng.uniform(*pause_s)
    return prof
