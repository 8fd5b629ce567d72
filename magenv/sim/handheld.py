"""Analytic kinematics of a hand-held MIMU carried by a walking person (Combettes & Renaudin 2016 §5.2).

The walker follows a figure-eight at a near-constant speed (arc-length
parametrised; 5 km/h ≈ 1.39 m/s in the paper) — or walks in place, as on the
paper's treadmill (``travel=False``) — with the torso bobbing at the
step frequency, swaying at the stride frequency and yawing slightly. The
device pose relative to the torso depends on the carrying mode:

* ``texting`` — held steady in front at chest height, screen up, top raised
  20–40°, small tremor and step-synchronous shake;
* ``swinging`` — in the fist of an arm swinging as a pendulum about the
  shoulder at the stride frequency (±25–40°: up to ~200 °/s, several m/s²);
* ``phoning`` — at the ear, near-vertical;
* ``irregular`` — in front of the body with slow, large random motions.

A ``Motion`` is built once from a random generator (all draws happen there)
and is then a deterministic, smooth function of time: ``pose(t)`` gives the
sensor position ``p`` (N, 3) m (ENU) and orientation ``q`` (N, 4) sensor →
ENU. Mixed modes are joined by C²-smooth (smootherstep) transitions. Ideal
readings are derived numerically from that function with central
differences (``ideal_readings``): body rate ω = rotvec(q(t−h)* ⊗ q(t+h))/2h
(sensor frame, matches ``quaternion.integrate_gyro1``), specific force
f = q* ⊗ (p̈ + [0, 0, g]) ⊗ q. Truncation errors are < 1e-5 rad/s and
< 1e-3 m/s² for these motions. Sensor frame: x forward / y left / z up when
the device lies flat in front of the walker.
"""

from __future__ import annotations

import numpy as np

from magenv import quaternion as quat
from magenv.quaternion import GRAVITY

MODES = ("texting", "swinging", "phoning", "irregular")
_EZ = np.array([0.0, 0.0, 1.0])


def smootherstep(x):
    """6x⁵ − 15x⁴ + 10x³ on [0, 1] (C² at both ends), clipped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


class _Sines:
    """Sum of sinusoids per output column, parameters drawn once: deterministic in t afterwards."""

    def __init__(self, rng, cols, k, amp, f_range):
        self.amp = np.asarray(amp, float) * np.ones(cols) / np.sqrt(k)
        self.f = rng.uniform(f_range[0], f_range[1], (k, cols))
        self.ph = rng.uniform(0.0, 2 * np.pi, (k, cols))

    def __call__(self, t):
        return self.amp * np.sin(2 * np.pi * self.f[None] * t[:, None, None] + self.ph[None]).sum(1)


class FigureEight:
    """A figure-eight ``[a sin φ, b sin 2φ]`` (m) walked at arc length s (m); heading along the tangent."""

    def __init__(self, a: float, b: float):
        from scipy.interpolate import CubicSpline  # here: scipy's import is ~25 MB, needed by few trials

        phi = np.linspace(0.0, 2 * np.pi, 20001)
        speed = np.hypot(a * np.cos(phi), 2 * b * np.cos(2 * phi))
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(phi))])
        self.a, self.b, self.length = a, b, float(s[-1])
        resid = phi - 2 * np.pi * s / self.length  # periodic in s
        resid[-1] = resid[0]
        self._resid = CubicSpline(s, resid, bc_type="periodic")

    def phi(self, s):
        return 2 * np.pi * s / self.length + self._resid(np.mod(s, self.length))

    def __call__(self, s) -> tuple[np.ndarray, np.ndarray]:
        """Position (N, 3) m at height 0 and heading ψ (N,) rad (ENU, from east towards north)."""
        phi = self.phi(s)
        p = np.stack([self.a * np.sin(phi), self.b * np.sin(2 * phi), np.zeros_like(phi)], 1)
        psi = np.arctan2(2 * self.b * np.cos(2 * phi), self.a * np.cos(phi))
        return p, psi


def _euler(yaw, pitch, roll):
    return quat.from_euler_zyx(np.asarray(yaw, float), np.asarray(pitch, float), np.asarray(roll, float))


class _Mode:
    """Device pose relative to the torso: position (N, 3) m in the torso frame (x fwd, y left, z up from
    the ground), orientation (N, 4) device → torso."""

    def __init__(self, name: str, rng: np.random.Generator, step_hz: float):
        self.name = name
        self.f_step = step_hz
        d = np.deg2rad
        if name == "texting":
            self.p0 = np.array([rng.uniform(0.28, 0.4), rng.uniform(-0.15, 0.0), rng.uniform(1.05, 1.25)])
            self.base = (rng.uniform(-d(10), d(10)), -rng.uniform(d(20), d(40)), rng.uniform(-d(8), d(8)))
            self.pos_wob = _Sines(rng, 3, 3, 0.01, (0.1, 0.6))
            self.ang_wob = _Sines(rng, 3, 3, d(3.0), (0.1, 0.6))
            self.step_amp = (0.008, d(1.0))
        elif name == "swinging":
            self.shoulder = np.array([0.0, rng.uniform(-0.24, -0.16), rng.uniform(1.3, 1.5)])
            self.arm = rng.uniform(0.6, 0.72)
            self.swing = rng.uniform(d(25), d(40))
            self.swing0 = rng.uniform(d(-5), d(10))
            self.phase = rng.uniform(0, 2 * np.pi)
            self.grip = _euler(
                rng.uniform(-d(20), d(20)),
                rng.uniform(-d(20), d(20)),
                rng.choice((-1.0, 1.0)) * d(90) + rng.uniform(-d(15), d(15)),
            )
            self.ang_wob = _Sines(rng, 3, 2, d(4.0), (0.3, 1.5))
        elif name == "phoning":
            self.p0 = np.array([rng.uniform(0.02, 0.1), rng.uniform(-0.2, -0.12), rng.uniform(1.5, 1.7)])
            self.base = (rng.uniform(d(60), d(120)), -rng.uniform(d(50), d(80)), rng.uniform(-d(20), d(20)))
            self.pos_wob = _Sines(rng, 3, 3, 0.008, (0.1, 0.5))
            self.ang_wob = _Sines(rng, 3, 3, d(2.0), (0.1, 0.5))
            self.step_amp = (0.01, d(0.5))
        elif name == "irregular":
            self.p0 = np.array([rng.uniform(0.2, 0.4), rng.uniform(-0.25, 0.05), rng.uniform(0.9, 1.3)])
            self.base = (rng.uniform(-d(30), d(30)), rng.uniform(-d(40), d(10)), rng.uniform(-d(30), d(30)))
            self.pos_wob = _Sines(rng, 3, 3, 0.1, (0.1, 0.8))
            self.ang_wob = _Sines(rng, 3, 3, d(35.0), (0.05, 0.6))
            self.step_amp = (0.01, d(1.0))
        else:
            raise ValueError(f"unknown carrying mode {name!r}; known: {', '.join(MODES)}")

    def __call__(self, t):
        if self.name == "swinging":
            alpha = self.swing0 + self.swing * np.sin(np.pi * self.f_step * t + self.phase)  # stride = step/2
            p = self.shoulder + self.arm * np.stack([np.sin(alpha), np.zeros_like(t), -np.cos(alpha)], 1)
            q_arm = quat.from_axis_angle(np.array([0.0, 1.0, 0.0]), -alpha)  # hand moves forward for α > 0
            w = self.ang_wob(t)
            return p, quat.mul(quat.mul(q_arm, self.grip), _euler(w[:, 0], w[:, 1], w[:, 2]))
        step = np.sin(2 * np.pi * self.f_step * t)
        p = self.p0 + self.pos_wob(t)
        p[:, 2] += self.step_amp[0] * step
        w = self.ang_wob(t)
        q = _euler(self.base[0] + w[:, 0], self.base[1] + w[:, 1] + self.step_amp[1] * step, self.base[2] + w[:, 2])
        return p, q


class Motion:
    """A walker carrying the device through a schedule of carrying modes; ``pose(t)`` is smooth in t.

    Args:
        rng: draws every random parameter here, once.
        modes: allowed carrying modes; a single mode gives one segment for the whole trial.
        duration: s. segment_s: (low, high) duration of each mode segment, s.
        transition_s: length of the smooth hand-over between segments, s.
        speed: walking speed, m/s. step_hz: step frequency, Hz.
        path_m: (a, b) half extents of the figure-eight, m.
        travel: walk along the figure-eight (True) or in place, as on the paper's treadmill (False: the
            torso keeps its gait oscillations at the point where the path starts, facing along it).
    """

    def __init__(
        self,
        rng,
        modes,
        duration,
        segment_s=(20.0, 60.0),
        transition_s=1.5,
        speed=1.39,
        step_hz=1.8,
        path_m=(4.0, 2.0),
        travel=True,
    ):
        for m in modes:
            if m not in MODES:
                raise ValueError(f"unknown carrying mode {m!r}; known: {', '.join(MODES)}")
        if not modes:
            raise ValueError("need at least one carrying mode")
        self.path = FigureEight(*path_m)
        self.speed, self.f_step, self.transition = float(speed), float(step_hz), float(transition_s)
        self.travel = bool(travel)
        self.s0 = rng.uniform(0.0, self.path.length)
        self.surge = (rng.uniform(0.01, 0.03), rng.uniform(0, 2 * np.pi))
        self.bob = (rng.uniform(0.02, 0.04), rng.uniform(0, 2 * np.pi))
        self.sway = (rng.uniform(0.015, 0.035), rng.uniform(0, 2 * np.pi))
        self.yaw_osc = (np.deg2rad(rng.uniform(2.0, 5.0)), rng.uniform(0, 2 * np.pi))
        bounds, names, t = [0.0], [], 0.0
        while t < duration:
            choices = [m for m in modes if not names or m != names[-1]] or list(modes)
            names.append(str(choices[int(rng.integers(len(choices)))]))
            t += rng.uniform(*segment_s) if len(modes) > 1 else duration + 1.0
            bounds.append(t)
        self.bounds = np.array(bounds)
        self.segments = [_Mode(n, rng, self.f_step) for n in names]

    @property
    def mode_names(self) -> list[str]:
        return [s.name for s in self.segments]

    def mode_index(self, t) -> np.ndarray:
        """(N,) index into ``MODES`` of the dominant carrying mode at times t."""
        k = np.clip(np.searchsorted(self.bounds, t, side="right") - 1, 0, len(self.segments) - 1)
        return np.array([MODES.index(self.segments[i].name) for i in k])

    def _relative(self, t):
        """Device position (torso frame) and orientation (device → torso), blended across segments."""
        n = len(t)
        p = np.zeros((n, 3))
        q = np.zeros((n, 4))
        wsum = np.zeros(n)
        half = 0.5 * self.transition
        for k, seg in enumerate(self.segments):
            lo, hi = self.bounds[k], self.bounds[k + 1]
            w = np.ones(n)
            if k > 0:
                w *= smootherstep((t - lo + half) / self.transition)
            if k < len(self.segments) - 1:
                w *= 1.0 - smootherstep((t - hi + half) / self.transition)
            sel = np.flatnonzero(w > 0.0)
            if sel.size == 0:
                continue
            pk, qk = seg(t[sel])
            # same hemisphere as the segment already accumulated there, before the (n)lerp
            qk = qk * np.where(np.sum(qk * q[sel], axis=1) < 0.0, -1.0, 1.0)[:, None]
            p[sel] += w[sel, None] * pk
            q[sel] += w[sel, None] * qk
            wsum[sel] += w[sel]
        return p / wsum[:, None], quat.normalize(q)

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Sensor position (N, 3) m (ENU) and orientation (N, 4) sensor → ENU at times t (N,) s."""
        t = np.asarray(t, float)
        s = (
            self.s0
            + (self.speed if self.travel else 0.0) * t
            + self.surge[0] * np.sin(2 * np.pi * self.f_step * t + self.surge[1])
        )
        p_path, psi = self.path(s)
        stride = np.pi * self.f_step * t  # stride frequency = step/2
        psi = psi + self.yaw_osc[0] * np.sin(stride + self.yaw_osc[1])
        c, sn = np.cos(psi), np.sin(psi)
        left = np.stack([-sn, c, np.zeros_like(c)], 1)
        torso = p_path + self.sway[0] * np.sin(stride + self.sway[1])[:, None] * left
        torso[:, 2] += self.bob[0] * np.sin(2 * np.pi * self.f_step * t + self.bob[1])
        p_rel, q_rel = self._relative(t)
        fwd = np.stack([c, sn, np.zeros_like(c)], 1)
        p = torso + p_rel[:, :1] * fwd + p_rel[:, 1:2] * left
        p[:, 2] += p_rel[:, 2]
        q = quat.mul(quat.from_axis_angle(_EZ, psi), q_rel)
        return p, q


def ideal_readings(motion: Motion, t: np.ndarray, field, h_rot: float = 1e-4, h_pos: float = 1e-3):
    """Ideal sensor readings of ``motion`` at times t (N,) s in a static ``field`` (callable (N,3) m → (N,3) µT ENU).

    Returns ``(p, q, gyr, acc, mag, b_earth_frame)``: position (N, 3) m, orientation (N, 4), body rate
    (N, 3) rad/s, specific force (N, 3) m/s², field (N, 3) µT (all sensor frame except p and the last,
    the field at p in ENU).
    """
    t = np.asarray(t, float)
    p, q = motion.pose(t)
    _, qm = motion.pose(t - h_rot)
    _, qp = motion.pose(t + h_rot)
    gyr = quat.to_rotvec(quat.mul(quat.conj(qm), qp)) / (2 * h_rot)
    pm, _ = motion.pose(t - h_pos)
    pp, _ = motion.pose(t + h_pos)
    acc_e = (pp - 2 * p + pm) / h_pos**2
    acc_e[:, 2] += GRAVITY
    acc = quat.rotate_inv(q, acc_e)
    b_e = field(p)
    mag = quat.rotate_inv(q, b_e)
    return p, q, gyr, acc, mag, b_e
