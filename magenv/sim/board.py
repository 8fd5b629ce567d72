"""A sensor board moved by hand in a room, as in the BROAD recordings: its motion and what disturbs its sensors.

Frames and units: ENU earth frame, orientation sensor → ENU (scalar first), positions in m, angular rates
in rad/s, the field in µT, specific force in m/s².

* :func:`hand_motion` — the board's true motion: an initial rest, then angular velocity and position as
  sums of random sinusoids (smooth, band-limited like a hand's motion) scaled to a drawn RMS rate and
  translation amplitude, switched off during breaks (rests) with half-second ramps; the orientation is the
  exact integral of the angular velocity (:func:`integrate`), the position's acceleration the exact second
  derivative of its sinusoids.
* :func:`approach_path` — bends the position towards points in the room (a magnet lying there) at given
  times: the board is carried to a drawn distance from the point, held there (dwell) and taken back.
* :func:`attached_profile` — how much of a magnet or iron fixed to the board is present at each sample
  (0 before it is attached, 1 while it is, ramps while it is being attached or removed).
* :func:`shocks` — tapping (damped knocks) and vibration (a motor's sinusoid, aliased by the sample rate) on
  the accelerometer and, weakly, the gyroscope, in bursts.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv import quaternion as quat

RAMP_S = 0.5  # s, the envelope's ramp into and out of a break


def envelope(t: np.ndarray, rest_s: float, breaks: list[tuple[float, float]]) -> np.ndarray:
    """(N,) in [0, 1]: 0 during the initial rest and the breaks ((start, stop) s), 1 in between, smooth
    (raised-cosine) ramps of ``RAMP_S`` into and out of each."""
    e = np.ones_like(t)

    def ramp(x):
        return 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))

    e *= ramp((t - rest_s) / RAMP_S)
    for a, b in breaks:
        e *= 1.0 - ramp((t - (a - RAMP_S)) / RAMP_S) * ramp(((b + RAMP_S) - t) / RAMP_S)
    return e


def sines(rng: np.random.Generator, t: np.ndarray, k: int, f_range: tuple[float, float]):
    """(x (N, 3), ẋ (N, 3), ẍ (N, 3)): per axis the sum of ``k`` sinusoids of random frequency (log-uniform in
    ``f_range`` Hz), phase and amplitude (∝ 1/f), scaled to unit RMS; exact derivatives."""
    f = np.exp(rng.uniform(np.log(f_range[0]), np.log(f_range[1]), (3, k)))
    ph = rng.uniform(0.0, 2 * np.pi, (3, k))
    amp = rng.uniform(0.3, 1.0, (3, k)) / f
    amp /= np.sqrt(0.5 * (amp**2).sum(1, keepdims=True))
    w = 2 * np.pi * f
    arg = w[None] * t[:, None, None] + ph[None]
    x = (amp * np.sin(arg)).sum(-1)
    dx = (amp * w * np.cos(arg)).sum(-1)
    ddx = (-amp * w * w * np.sin(arg)).sum(-1)
    return x, dx, ddx


@njit(cache=True)
def integrate(q0, w, dt):
    """(N, 4) orientations from q0 by the body rates w (N, 3) rad/s: q_{i+1} = q_i ⊗ exp(½ ω_i Δt) (exact for a
    rate held over the step)."""
    n = w.shape[0]
    q = np.empty((n, 4))
    q[0] = q0
    for i in range(n - 1):
        q[i + 1] = quat.integrate_gyro1(q[i], w[i], dt)
    return q


def hand_motion(
    rng: np.random.Generator,
    n: int,
    rate: float,
    rot_dps: float,
    rot_hz: tuple[float, float],
    trans_m: float,
    trans_hz: tuple[float, float],
    rest_s: float,
    breaks: list[tuple[float, float]],
    tilt0_deg: float,
    spin: np.ndarray | None = None,
):
    """The board's true motion (module docstring): (q (N, 4) sensor → ENU, ω (N, 3) rad/s sensor frame, p (N, 3)
    m, p̈ (N, 3) m/s² ENU). ``rot_dps``: RMS angular rate while moving, °/s; ``trans_m``: RMS excursion of the
    position per axis, m; ``rot_hz`` / ``trans_hz``: their frequency bands; ``tilt0_deg``: the start's tilt
    (a random axis), the start's heading uniform; ``spin``: a steady body rate (3,) rad/s, sensor frame, added
    while moving (a net rotation in one sense; None: none)."""
    t = np.arange(n) / rate
    env = envelope(t, rest_s, breaks)
    w, _, _ = sines(rng, t, 6, rot_hz)
    w *= np.deg2rad(rot_dps) * env[:, None]
    if spin is not None:
        w += env[:, None] * np.asarray(spin, float)
    x, dx, ddx = sines(rng, t, 5, trans_hz)
    # p = trans_m·env·x: the product rule keeps p̈ exact through the ramps
    de = np.gradient(env, t)
    dde = np.gradient(de, t)
    p = trans_m * env[:, None] * x
    acc = trans_m * (dde[:, None] * x + 2 * de[:, None] * dx + env[:, None] * ddx)
    yaw = rng.uniform(-np.pi, np.pi)
    axis = np.r_[rng.normal(size=2), 0.0]
    tilt = quat.from_axis_angle(axis / np.linalg.norm(axis), np.deg2rad(tilt0_deg) * rng.uniform(-1, 1))
    q0 = quat.mul(quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw), tilt)
    q = integrate(q0, np.ascontiguousarray(w), 1.0 / rate)
    return q, w, p, acc


def approach_path(
    t: np.ndarray, p: np.ndarray, acc: np.ndarray, visits: list[tuple[float, float, float, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray]:
    """Position and acceleration (N, 3) with the board carried to each visit (start s, travel s, dwell s, target
    (3,) m) and back: p ← (1 − s(t))·p + s(t)·target, s rising over ``travel``, held over ``dwell``, falling over
    ``travel`` (a smootherstep); p̈ by finite differences of the bent path where s ≠ 0."""
    p = p.copy()
    weight = np.zeros(len(t))
    for start, travel, dwell, target in visits:
        up = _smootherstep((t - start) / travel)
        down = _smootherstep((start + travel + dwell + travel - t) / travel)
        s = np.minimum(up, down)
        p += s[:, None] * (target - p)
        weight = np.maximum(weight, s)
    if np.any(weight > 0):
        dt = t[1] - t[0]
        bent = np.gradient(np.gradient(p, dt, axis=0), dt, axis=0)
        acc = np.where((weight > 0)[:, None], bent, acc)
    return p, acc


def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def attached_profile(t: np.ndarray, on_s: float, off_s: float, ramp_s: float) -> np.ndarray:
    """(N,) in [0, 1]: 0 before ``on_s``, rising over ``ramp_s`` (attaching it), 1 until ``off_s``, falling over
    ``ramp_s`` (removing it); ``off_s`` = inf: never removed."""
    return np.minimum(_smootherstep((t - on_s) / ramp_s), _smootherstep((off_s - t) / ramp_s))


def shocks(
    rng: np.random.Generator,
    t: np.ndarray,
    kind: str,
    bursts: list[tuple[float, float]],
    acc_amp: float,
    gyr_amp: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(acc (N, 3) m/s², gyr (N, 3) rad/s) added to the sensor-frame readings during ``bursts`` ((start, stop)
    s): ``"tapping"`` — knocks at 1–5 Hz, each a 25–60 Hz oscillation decaying in 10–40 ms, amplitude up to
    ``acc_amp`` (random direction, mostly along the board's normal); ``"vibration"`` — a motor at 90–250 Hz of
    amplitude ``acc_amp``, sampled at the trial's rate (aliased as a real unit aliases it). The gyroscope
    sees ``gyr_amp`` (rad/s) of the same waveform."""
    n = len(t)
    a = np.zeros((n, 3))
    g = np.zeros((n, 3))
    for start, stop in bursts:
        inside = (t >= start) & (t < stop)
        if kind == "vibration":
            f = rng.uniform(90.0, 250.0)
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            wave = np.sin(2 * np.pi * f * t[inside] + rng.uniform(0, 2 * np.pi))
            a[inside] += acc_amp * wave[:, None] * d
            g[inside] += gyr_amp * wave[:, None] * rng.normal(size=3) / np.sqrt(3)
            continue
        times = start + np.cumsum(rng.exponential(1.0 / rng.uniform(1.0, 5.0), 200))
        for k0 in times[times < stop]:
            after = t - k0
            on = (after >= 0) & (after < 0.2)
            f, tau = rng.uniform(25.0, 60.0), rng.uniform(0.01, 0.04)
            wave = np.exp(-after[on] / tau) * np.sin(2 * np.pi * f * after[on])
            d = np.r_[0.3 * rng.normal(size=2), 1.0]
            d /= np.linalg.norm(d)
            amp = acc_amp * rng.uniform(0.3, 1.0)
            a[on] += amp * wave[:, None] * d
            g[on] += gyr_amp * (amp / acc_amp) * wave[:, None] * rng.normal(size=3) / np.sqrt(3)
    return a, g


def ideal_readings(q: np.ndarray, w: np.ndarray, acc_e: np.ndarray, field_e: np.ndarray):
    """Ideal (gyr, acc, mag) in the sensor frame from the true orientation q (N, 4), body rate w (N, 3), the
    earth-frame linear acceleration (N, 3) and the earth-frame field at the board (N, 3) µT."""
    f = quat.rotate_inv(q, acc_e + quat.gravity_up())
    return np.array(w, copy=True), f, quat.rotate_inv(q, field_e)
