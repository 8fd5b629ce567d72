"""Paths of the gimbal's base for the mobile model (survey scenarios).

Each function returns the commanded base motion on the physics grid as an
(n, 6) array: position (m, world ENU) and its time derivative (m/s), both
analytic so that the servos' position and velocity commands agree.
"""

from __future__ import annotations

import numpy as np


def reach(
    t: np.ndarray,
    start: float,
    travel: float,
    hold: float,
    target: np.ndarray,
    rng: np.random.Generator,
    tremor_m: float = 0.002,
) -> np.ndarray:
    """Move from the origin to ``target`` (m, world) and back.

    The base travels to ``target`` in ``travel`` s (half-cosine profile),
    holds ``hold`` s with a small hand tremor (three sinusoids, 1–4 Hz, total
    amplitude ``tremor_m``), and returns in ``travel`` s.
    """
    target = np.asarray(target, float)
    s = np.zeros_like(t)
    ds = np.zeros_like(t)
    u = (t - start) / travel
    go = (u >= 0) & (u < 1)
    s[go] = 0.5 * (1 - np.cos(np.pi * u[go]))
    ds[go] = 0.5 * np.pi / travel * np.sin(np.pi * u[go])
    held = (t >= start + travel) & (t <= start + travel + hold)
    s[held] = 1.0
    u = (t - start - travel - hold) / travel
    back = (u > 0) & (u < 1)
    s[back] = 0.5 * (1 + np.cos(np.pi * u[back]))
    ds[back] = -0.5 * np.pi / travel * np.sin(np.pi * u[back])
    out = np.zeros((len(t), 6))
    out[:, :3] = s[:, None] * target
    out[:, 3:] = ds[:, None] * target
    # Tremor only while near the target (weighted by s, smooth at the ends).
    for k in range(3):
        f = rng.uniform(1.0, 4.0, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        a = tremor_m / 3
        arg = 2 * np.pi * f[None] * t[:, None] + ph[None]
        x = a * np.sin(arg).sum(1)
        dx = a * (2 * np.pi * f[None] * np.cos(arg)).sum(1)
        out[:, k] += s * x
        out[:, 3 + k] += s * dx + ds * x
    return out


def start_envelope(t: np.ndarray, ramp_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth start from rest: envelope e(t) rising 0 → 1 over ``ramp_s`` s
    (half-cosine) and the warped time φ(t) = ∫ e dt, so a motion f(φ) starts
    with zero velocity and no jump in acceleration beyond e's own."""
    e = np.ones_like(t)
    r = t < ramp_s
    e[r] = 0.5 * (1 - np.cos(np.pi * t[r] / ramp_s))
    phi = np.where(r, 0.5 * (t - ramp_s / np.pi * np.sin(np.pi * t / ramp_s)), t - 0.5 * ramp_s)
    return e, phi


def figure_eight(
    t: np.ndarray,
    half_length: float,
    half_width: float,
    period: float,
    bounce_m: float,
    step_hz: float,
    sway_m: float,
    ramp_s: float = 2.0,
) -> np.ndarray:
    """A figure-eight walk (lemniscate of Gerono) with gait bounce and sway.

    x = L·sin(Ωφ), y = W·sin(Ωφ)·cos(Ωφ) with Ω = 2π/period and φ the time
    warped by :func:`start_envelope` (the walk starts from rest over
    ``ramp_s`` s); the base bobs up and down by ``bounce_m`` at the step
    frequency and sways sideways by ``sway_m`` (world y) at half of it.
    """
    e, ph = start_envelope(t, ramp_s)
    om = 2 * np.pi / period
    ws = 2 * np.pi * step_hz
    out = np.zeros((len(t), 6))
    out[:, 0] = half_length * np.sin(om * ph)
    out[:, 3] = half_length * om * np.cos(om * ph) * e
    out[:, 1] = half_width * 0.5 * np.sin(2 * om * ph) + sway_m * np.sin(0.5 * ws * ph)
    out[:, 4] = (half_width * om * np.cos(2 * om * ph) + sway_m * 0.5 * ws * np.cos(0.5 * ws * ph)) * e
    out[:, 2] = bounce_m * (1 - np.cos(ws * ph))
    out[:, 5] = bounce_m * ws * np.sin(ws * ph) * e
    return out


def heading(base: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Unwrapped heading (rad, direction of the horizontal velocity) and its
    rate (rad/s) of a base motion (n, 6) sampled at ``rate`` Hz, for turning
    the gimbal's frame Z with the walk."""
    speed = np.hypot(base[:, 3], base[:, 4])
    moving = np.flatnonzero(speed > 1e-6)
    if len(moving) == 0:
        return np.zeros(len(base)), np.zeros(len(base))
    psi = np.unwrap(np.arctan2(base[:, 4], base[:, 3]))
    psi[: moving[0]] = psi[moving[0]]  # at rest before the start: keep the first heading
    return psi, np.gradient(psi) * rate
