"""MuJoCo simulation of the two-link system of Jung & Lee 2019 (``twolink.xml``).

``simulate_twolink(command, sample_rate, n_samples)`` rolls the model out
open-loop with ``mujoco.rollout`` (``gimbal.rollout_sensors``; servo commands = the commanded joint
positions and rates) and returns MuJoCo's own readings of both MIMUs at the
sample times: gyro (rad/s) and accelerometer (specific force, m/s²) in each
sensor's frame, each sensor's orientation (sensor → world = ENU) and
position, and the joint centre's position.

Joints (order of every (n, 9) array here): carriage slides ``tx, ty, tz``
(m, world axes), link j hinges ``jz, jy, jx`` (rad), link i hinges ``iz, iy,
ix`` (rad, about the joint centre: the spherical joint).

:func:`smooth_motion` makes a commanded path: per joint a sum of random
sinusoids, scaled by an envelope in [0, 1] so that a trial can hold still,
move slowly or move briskly by stretches.

The model is loaded once per process; the physics timestep is written
before every rollout, so a trial does not depend on earlier ones.
"""

from __future__ import annotations

import dataclasses
import math
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np

from magenv import quaternion as quat
from magenv.sim.gimbal import SimulationError, resample_cubic, rollout_sensors

MODEL_PATH = Path(__file__).with_name("twolink.xml")
JOINTS = ("tx", "ty", "tz", "jz", "jy", "jx", "iz", "iy", "ix")
N_JOINTS = len(JOINTS)
#: Physics rate, Hz: an integer multiple of the default sensor rate (100 Hz).
PHYSICS_RATE = 400.0
#: Settling before t = 0 holding the first command, s (discarded).
INITIAL_SETTLE_S = 0.5

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


@dataclasses.dataclass(eq=False)
class Command:
    """Commanded joint positions and rates on the physics grid.

    Attributes:
        rate: physics rate, Hz.
        pos: (n, 9) commanded joint positions (m for slides, rad for hinges), order ``JOINTS``.
        vel: (n, 9) commanded joint rates (m/s, rad/s).
    """

    rate: float
    pos: np.ndarray
    vel: np.ndarray

    @property
    def n(self) -> int:
        return len(self.pos)


@dataclasses.dataclass(eq=False)
class TwoLinkRun:
    """MuJoCo's noise-free readings at the sample times (N rows).

    Attributes:
        gyr_i, gyr_j: (N, 3) angular rate, rad/s, each sensor's frame.
        acc_i, acc_j: (N, 3) specific force, m/s², each sensor's frame.
        q_i, q_j: (N, 4) orientation sensor → world (ENU), [w, x, y, z], w ≥ 0.
        p_i, p_j: (N, 3) sensor positions in the world, m.
        p_c: (N, 3) joint centre position in the world, m.
        physics_steps: MuJoCo steps taken.
    """

    gyr_i: np.ndarray
    acc_i: np.ndarray
    q_i: np.ndarray
    p_i: np.ndarray
    gyr_j: np.ndarray
    acc_j: np.ndarray
    q_j: np.ndarray
    p_j: np.ndarray
    p_c: np.ndarray
    physics_steps: int


@lru_cache(maxsize=1)
def _model() -> tuple[mujoco.MjModel, mujoco.MjData, dict]:
    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    data = mujoco.MjData(model)
    adr = {}
    for i in range(model.nsensor):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, i)
        adr[name] = slice(model.sensor_adr[i], model.sensor_adr[i] + model.sensor_dim[i])
    return model, data, adr


def load_model() -> mujoco.MjModel:
    """The two-link MjModel (shared within the process)."""
    return _model()[0]


def lever_arms() -> tuple[np.ndarray, np.ndarray]:
    """(r_i, r_j): vector from each sensor to the joint centre in its own frame, m (paper §3.1)."""
    model = load_model()
    sid = lambda name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
    r_j = model.site_pos[sid("joint_centre")] - model.site_pos[sid("imu_j")]
    r_i = -model.site_pos[sid("imu_i")]  # link i's origin is the joint centre
    return r_i.copy(), r_j.copy()


def _hinge_axes(angles: np.ndarray) -> np.ndarray:
    """(n, 3, 3): axes of a body's z, y, x hinges (MuJoCo applies them in that order) in the body's frame.

    ``angles`` (n, 3): the hinges' positions (z, y, x), rad. Row r of the
    result is hinge r's axis: x = e_x, y = R_x(x)ᵀe_y, z = R_x(x)ᵀR_y(y)ᵀe_z.
    """
    sy, cy = np.sin(angles[:, 1]), np.cos(angles[:, 1])
    sx, cx = np.sin(angles[:, 2]), np.cos(angles[:, 2])
    zero, one = np.zeros_like(sx), np.ones_like(sx)
    return np.stack(
        [
            np.stack([-sy, sx * cy, cx * cy], axis=1),
            np.stack([zero, cx, -sx], axis=1),
            np.stack([one, zero, zero], axis=1),
        ],
        axis=1,
    )


def _centre_gyro(sens: np.ndarray, adr: dict, phys_rate: float) -> None:
    """Put MuJoCo's gyro readings at the same instant as its positions (in place).

    As in ``magenv.sim.gimbal._centre_gyro``: the joint velocity v_k of step
    k is the mean rate over [t_k − h, t_k], half a step behind the positions;
    the rate at t_k is the central difference v̄_k = (q_{k+1} − q_{k−1})/(2h).
    Each gyro gets Σ_j a_j·(v̄_j − v_j), a_j the hinge axes in its sensor frame
    (the sites are not rotated in their bodies): link j's own hinges, and for
    link i its own hinges plus link j's term carried from frame j to frame i
    through MuJoCo's orientations q_j, q_i. First and last rows stay as read.
    """
    pos = np.stack([sens[:, adr["q_" + k].start] for k in JOINTS[3:]], axis=1)
    vel = np.stack([sens[:, adr["v_" + k].start] for k in JOINTS[3:]], axis=1)
    dv = np.zeros_like(vel)
    dv[1:-1] = (pos[2:] - pos[:-2]) * (0.5 * phys_rate) - vel[1:-1]
    dw_j = np.einsum("nr,nrc->nc", dv[:, :3], _hinge_axes(pos[:, :3]))
    dw_i = np.einsum("nr,nrc->nc", dv[:, 3:], _hinge_axes(pos[:, 3:]))
    q_i, q_j = sens[:, adr["q_i"]], sens[:, adr["q_j"]]
    sens[:, adr["gyro_j"]] += dw_j
    sens[:, adr["gyro_i"]] += quat.rotate_inv(q_i, quat.rotate(q_j, dw_j)) + dw_i


def envelope(t: np.ndarray, levels: list[tuple[float, float]], ramp: float = 1.0) -> np.ndarray:
    """A motion envelope: ``levels`` = [(start s, level), …] held until the next start,
    with half-cosine transitions of ``ramp`` s; 0 before the first start."""
    env = np.zeros(len(t))
    prev = 0.0
    for start, level in levels:
        s = np.clip((t - start) / ramp, 0.0, 1.0)
        mix = 0.5 * (1.0 - np.cos(np.pi * s))
        env = np.where(t >= start, prev + (level - prev) * mix, env)
        prev = level
    return env


def smooth_motion(
    rng: np.random.Generator,
    duration: float,
    rate: float,
    env: np.ndarray,
    amp: np.ndarray,
    freq_hz: tuple[float, float],
    centre: np.ndarray | None = None,
    n_sines: int = 3,
) -> Command:
    """A commanded path: joint d moves as centre_d + env(t)·Σ_k a_dk sin(2π f_dk t + φ_dk).

    Args:
        rng: the trial's motion generator.
        duration: s; rate: physics rate, Hz (``len(env)`` must be ``round(duration·rate)``).
        env: (n,) envelope in [0, 1] on the physics grid (:func:`envelope`).
        amp: (9,) amplitude per joint (m or rad): the k sines share it with random
            weights summing to 1, so |motion − centre| ≤ amp.
        freq_hz: range of the sine frequencies, Hz.
        centre: (9,) joint positions the motion is about (default zeros: link j
            horizontal, link i hanging).
    """
    n = int(round(duration * rate))
    if len(env) != n:
        raise ValueError(f"envelope has {len(env)} samples, expected {n}")
    t = np.arange(n) / rate
    amp = np.asarray(amp, float)
    pos = np.zeros((n, N_JOINTS)) if centre is None else np.tile(np.asarray(centre, float), (n, 1))
    for d in range(N_JOINTS):
        f = rng.uniform(*freq_hz, n_sines)
        ph = rng.uniform(0.0, 2.0 * np.pi, n_sines)
        wts = rng.dirichlet(np.ones(n_sines))
        s = (wts[None] * np.sin(2.0 * np.pi * f[None] * t[:, None] + ph[None])).sum(1)
        pos[:, d] += amp[d] * env * s
    vel = np.asarray(np.gradient(pos, 1.0 / rate, axis=0))
    return Command(rate=float(rate), pos=pos, vel=vel)


def simulate_twolink(command: Command, sample_rate: float, n_samples: int) -> TwoLinkRun:
    """Roll the two links out along ``command`` and read both MIMUs at ``sample_rate``.

    ``command.rate`` is the physics rate; it must cover the last sample time
    plus two physics steps. Raises SimulationError if MuJoCo flags an instability.
    """
    model, data, adr = _model()
    phys = command.rate
    need = int(math.floor((n_samples - 1) * phys / sample_rate)) + 3
    if command.n < need:
        raise ValueError(f"command has {command.n} steps, needs {need} for {n_samples} samples at {sample_rate} Hz")
    model.opt.timestep = 1.0 / phys
    ctrl = np.concatenate([command.pos, command.vel], axis=1)

    mujoco.mj_resetData(model, data)
    data.qpos[:] = command.pos[0]
    mujoco.mj_forward(model, data)
    for w in data.warning:
        w.number = 0
    state = np.empty(mujoco.mj_stateSize(model, _STATE))
    mujoco.mj_getState(model, data, state, _STATE)
    warm = np.zeros(model.nv)
    settle = int(round(INITIAL_SETTLE_S * phys))
    hold = np.concatenate([command.pos[0], np.zeros(N_JOINTS)])
    rollout_sensors(model, data, state, np.tile(hold, (settle, 1)), warm)
    mujoco.mj_getState(model, data, state, _STATE)  # the settled state, its clock set back to t = 0
    state[0] = 0.0
    sens = rollout_sensors(model, data, state, ctrl, warm)
    bad = [mujoco.mjtWarning(i).name for i, w in enumerate(data.warning) if w.number > 0]
    if bad or not np.all(np.isfinite(sens)):
        raise SimulationError(
            f"MuJoCo instability in the two-link model: warnings {bad or 'none'}, finite={np.all(np.isfinite(sens))}"
        )
    for key in ("q_i", "q_j"):  # continuous sign before interpolation
        q = sens[:, adr[key]]
        flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
        q[1:] *= flip[:, None]
    _centre_gyro(sens, adr, phys)
    out = resample_cubic(sens, phys, sample_rate, n_samples, 0.0)
    for key in ("q_i", "q_j"):
        qs = out[:, adr[key]]
        qs /= np.linalg.norm(qs, axis=1, keepdims=True)
        qs *= np.where(qs[:, :1] < 0, -1.0, 1.0)
    g = lambda k: np.ascontiguousarray(out[:, adr[k]])
    return TwoLinkRun(
        gyr_i=g("gyro_i"),
        acc_i=g("accel_i"),
        q_i=g("q_i"),
        p_i=g("p_i"),
        gyr_j=g("gyro_j"),
        acc_j=g("accel_j"),
        q_j=g("q_j"),
        p_j=g("p_j"),
        p_c=g("p_c"),
        physics_steps=settle + command.n,
    )
