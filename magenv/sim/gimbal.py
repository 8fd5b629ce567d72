"""MuJoCo simulation of the instrumented gimbal with its sliding magnet.

``simulate_gimbal(profile, tube, sample_rate, n_samples, base=None)`` rolls
the model in ``gimbal.xml`` out open-loop with ``mujoco.rollout`` (servo
commands = the drive profile) and returns MuJoCo's own sensor readings at
the sensor sample times: gyro (rad/s) and accelerometer (specific force,
m/s²) in the sensor frame, the sensor's orientation (sensor → world = ENU)
and position, and the tube magnet's position and dipole axis in the sensor
frame. With ``base`` the gimbal stands on a base that travels (a variant of
the model with three servo-driven slide joints, built with ``MjSpec``).

Time alignment: row k of MuJoCo's sensor data belongs to the state before
step k (t_k = k·h). MuJoCo's semi-implicit Euler moves positions with the
new velocity, so its gyro (read with v_k) is half a step behind its own
orientation; :func:`_centre_gyro` puts it at t_k (see there).

Speed design (a trial is made at every environment reset):

* physics runs at ``profile.rate`` (default 100 Hz, :data:`PHYSICS_RATE`),
  the rate the dynamics need, not the sensor rate: the gimbal's motion is
  smooth (servo bandwidth ~10 Hz, frame rates ≤ 1 Hz in the body frame) and
  the sensor channels are resampled to the sample times with a cubic
  (Catmull–Rom) interpolation, exact where the grids coincide. Against
  physics at 1024 Hz (tests/test_sim_gimbal.py): orientation within 0.2°,
  gyro within 0.05 °/s at constant rates (within ~1 °/s during spin-ups,
  where the servos' lag depends on the timestep), magnet within 1 mm;
* settled pauses cost nothing: where the commanded rates are zero for a
  while, the model is stepped until it is at rest (servos settled, magnet
  stopped), and the rest of the pause repeats that state (a test checks
  this changes nothing beyond 1e-6);
* one ``mujoco.rollout`` call per stretch of motion (:func:`rollout_sensors`), no Python per step;
  post-processing in numba kernels.

The model is loaded once per process and is not thread-safe (one MjData):
run parallel environments in processes. Every per-trial parameter (tube
placement and length, dipole direction, magnet mass, friction, timestep) is
written before each rollout, so a trial does not depend on earlier ones.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout
from numba import njit

from magenv.sim.magnet import DiscMagnet
from magenv.sim.profiles import DriveProfile
from magenv.sim.rowops import norms

MODEL_PATH = Path(__file__).with_name("gimbal.xml")

#: Default physics rate, Hz (see module docstring).
PHYSICS_RATE = 100.0
#: A pause must last this long (s) before it is skipped; the first
#: ``SETTLE_S`` of it are simulated so the servos and the magnet come to rest.
SETTLE_S = 0.6
#: Initial settling (discarded) before t = 0, s.
INITIAL_SETTLE_S = 0.6
#: A settled state may not move more than this (rad or m) over the pause.
SETTLE_TOL = 1e-4
#: Physics steps simulated and post-processed at a time in a long run (:func:`gimbal_blocks`): bounds its
#: memory (a few MB a block) without changing its numbers.
BLOCK_ROWS = 4096
#: A run of at most this many physics steps is made in one block (the fastest: a reset's trial).
WHOLE_RUN_ROWS = 16384

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


@dataclasses.dataclass(frozen=True)
class Tube:
    """The disturbance generator: a tube on frame X with a sliding disc magnet.

    Coordinates are in frame X (= sensor axes; the sensor sits at
    (0, 0, 0.005) m). The tube runs along +x from ``start`` for ``length`` m,
    so the magnet moves when frame Y tilts the x axis (paper §2.5.3: "when
    frame Y rotated, the magnet would reciprocate in the paper tube due to the
    gravity").

    Attributes:
        start: near end of the tube (position of the magnet's centre at the
            stop), m, frame X.
        length: travel of the magnet along the tube, m.
        dipole: direction of the magnet's moment, frame X (the disc stands on
            edge in the square tube, so its axis is across the tube).
        friction: dry (Coulomb) friction force of magnet on tube, N.
        magnet: the magnet (size and remanence).
        start_at: where the magnet rests at t = 0, as a fraction of the
            travel (0 = near end, 1 = far end).
    """

    start: tuple[float, float, float] = (0.05, 0.015, 0.005)
    length: float = 0.10
    dipole: tuple[float, float, float] = (0.0, 0.0, 1.0)
    friction: float = 0.008
    magnet: DiscMagnet = DiscMagnet()
    start_at: float = 1.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.start_at) and 0.0 <= self.start_at <= 1.0):
            raise ValueError(f"Tube.start_at must be in [0, 1], got {self.start_at!r}")
        if not (np.isfinite(self.length) and 0.005 <= self.length <= 0.5):
            raise ValueError(f"Tube.length must be in [0.005, 0.5] m, got {self.length!r}")
        if len(self.start) != 3 or not np.all(np.isfinite(self.start)):
            raise ValueError(f"Tube.start must be 3 finite numbers (m), got {self.start!r}")
        if len(self.dipole) != 3 or not np.linalg.norm(self.dipole) > 0:
            raise ValueError(f"Tube.dipole must be a nonzero 3-vector, got {self.dipole!r}")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"Tube.friction must be ≥ 0 N, got {self.friction!r}")


@dataclasses.dataclass(eq=False)
class GimbalRun:
    """MuJoCo's readings at the sample times (N rows), noise-free.

    Attributes:
        gyr: (N, 3) angular rate, rad/s, sensor frame.
        acc: (N, 3) specific force, m/s², sensor frame.
        q: (N, 4) orientation sensor → world (ENU), [w, x, y, z].
        p_imu: (N, 3) sensor position in the world, m.
        p_magnet: (N, 3) tube magnet's centre in the sensor frame, m.
        m_axis: (N, 3) tube magnet's moment direction in the sensor frame.
        joints: (N, 3) joint angles (Z, Y, X), rad.
        slide: (N,) magnet position along the tube, m, clamped to [0, length].
        physics_steps: MuJoCo steps actually taken.
    """

    gyr: np.ndarray
    acc: np.ndarray
    q: np.ndarray
    p_imu: np.ndarray
    p_magnet: np.ndarray
    m_axis: np.ndarray
    joints: np.ndarray
    slide: np.ndarray
    physics_steps: int


class SimulationError(RuntimeError):
    """MuJoCo reported an instability (a warning counter rose or the state is not finite)."""


#: Base servos of the mobile variant (gait_field): ω_n ≈ 55 rad/s, ζ ≈ 0.7 for ~5 kg.
BASE_KP, BASE_KV = 15000.0, 380.0


@lru_cache(maxsize=2)
def _model(mobile: bool = False) -> tuple[mujoco.MjModel, mujoco.MjData, dict]:
    """The model, its data and sensor/object indices. ``mobile`` adds three
    slide joints (x, y, z, world axes) under the base, each with a
    position-velocity servo, so the whole gimbal can travel (``gait_field``)."""
    spec = mujoco.MjSpec.from_file(str(MODEL_PATH))
    if mobile:
        base = spec.body("base")
        for k, axis in enumerate(("x", "y", "z")):
            j = base.add_joint()
            j.name, j.type = f"base_{axis}", mujoco.mjtJoint.mjJNT_SLIDE
            j.axis = np.eye(3)[k]
        for kind in ("pos", "vel"):
            for axis in ("x", "y", "z"):
                a = spec.add_actuator()
                a.name, a.trntype, a.target = f"base_{axis}_{kind}", mujoco.mjtTrn.mjTRN_JOINT, f"base_{axis}"
                if kind == "pos":
                    a.set_to_position(kp=BASE_KP)
                else:
                    a.set_to_velocity(kv=BASE_KV)
    model = spec.compile()
    data = mujoco.MjData(model)
    adr = {}
    for i in range(model.nsensor):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, i)
        adr[name] = slice(model.sensor_adr[i], model.sensor_adr[i] + model.sensor_dim[i])
    ids = {
        "tube": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "tube"),
        "magnet_body": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "magnet"),
        "magnet_site": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "magnet"),
        "slide": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "slide"),
    }
    qadr = {
        name: int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)])
        for name in ("z", "y", "x", "slide") + (("base_x", "base_y", "base_z") if mobile else ())
    }
    return model, data, {"adr": adr, "ids": ids, "qadr": qadr}


def load_model(mobile: bool = False) -> mujoco.MjModel:
    """The gimbal's MjModel (shared within the process; configured per run)."""
    return _model(mobile)[0]


def _configure(model: mujoco.MjModel, ids: dict, tube: Tube, physics_rate: float) -> None:
    model.opt.timestep = 1.0 / physics_rate
    model.body_pos[ids["tube"]] = tube.start
    model.jnt_range[ids["slide"]] = (0.0, tube.length)
    model.dof_frictionloss[model.jnt_dofadr[ids["slide"]]] = tube.friction
    mass = tube.magnet.mass
    r, h = 0.5 * tube.magnet.diameter, tube.magnet.thickness
    model.body_mass[ids["magnet_body"]] = mass
    # Solid cylinder; its axis (local z) does not matter for a slide joint.
    model.body_inertia[ids["magnet_body"]] = (mass * (3 * r * r + h * h) / 12,) * 2 + (mass * r * r / 2,)
    # Site orientation: local z along the dipole direction (frame X coordinates).
    z = np.asarray(tube.dipole, float) / np.linalg.norm(tube.dipole)
    quat = np.empty(4)
    mujoco.mju_quatZ2Vec(quat, z)
    model.site_quat[ids["magnet_site"]] = quat


def _segments(still: np.ndarray, min_len: int) -> list[tuple[int, int, bool]]:
    """Split step indices into (start, stop, skippable) runs; a run is skippable
    when all commanded rates are zero over at least ``min_len`` steps."""
    segs: list[tuple[int, int, bool]] = []
    n = len(still)
    edges = np.flatnonzero(np.diff(still.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [n]])
    for a, b in zip(bounds[:-1], bounds[1:]):
        skippable = bool(still[a]) and (b - a) >= min_len
        if segs and not skippable and not segs[-1][2]:
            segs[-1] = (segs[-1][0], int(b), False)
        else:
            segs.append((int(a), int(b), skippable))
    return segs


def simulate_gimbal(
    profile: DriveProfile, tube: Tube, sample_rate: float, n_samples: int, base: np.ndarray | None = None
) -> GimbalRun:
    """Roll the gimbal out along ``profile`` and read its sensors at ``sample_rate``.

    Args:
        profile: commanded joint rates on the physics grid (its ``rate`` is
            the physics rate); must cover the last sample time plus two steps.
        tube: disturbance generator placement (always simulated; whether its
            magnet's field counts is the caller's choice).
        sample_rate: sensor rate, Hz.
        n_samples: number of sensor samples N.
        base: optional (n, 6) base motion on the physics grid: commanded
            position (m, world) and velocity (m/s) of the gimbal's base; uses
            the mobile variant of the model.

    The whole run at once: :func:`gimbal_blocks` joined. Raises SimulationError if MuJoCo flags an instability.
    """
    parts = list(gimbal_blocks(profile, tube, sample_rate, n_samples, base))
    if len(parts) == 1:
        return parts[0][1]
    join = lambda key: np.concatenate([getattr(run, key) for _, run in parts])
    fields = [f.name for f in dataclasses.fields(GimbalRun) if f.name != "physics_steps"]
    return GimbalRun(**{key: join(key) for key in fields}, physics_steps=parts[-1][1].physics_steps)


def gimbal_blocks(
    profile: DriveProfile,
    tube: Tube,
    sample_rate: float,
    n_samples: int,
    base: np.ndarray | None = None,
    block_rows: int | None = None,
) -> Iterator[tuple[int, GimbalRun]]:
    """:func:`simulate_gimbal` in consecutive blocks of samples: yields (first sample, GimbalRun of the block's
    rows), each block's ``physics_steps`` the steps taken so far (the last one's: all).

    The same numbers as one run, bit for bit, in memory bounded by ``block_rows`` physics steps (plus the
    profile): MuJoCo rolls out at most ``block_rows`` steps a call with its warm start carried over, and the
    gyro centring and the resampling read their few neighbouring rows across block edges. Consume the blocks
    before simulating anything else with the model (it is shared). Arguments as :func:`simulate_gimbal`;
    ``block_rows`` None: one block for a run of up to ``WHOLE_RUN_ROWS`` steps, else ``BLOCK_ROWS``."""
    model, data, info = _model(base is not None)
    adr, qadr = info["adr"], info["qadr"]
    phys_rate = profile.rate
    need = int(math.floor((n_samples - 1) * phys_rate / sample_rate)) + 3
    if profile.n < need:
        raise ValueError(
            f"drive profile has {profile.n} steps, needs {need} for {n_samples} samples at {sample_rate} Hz"
        )
    if base is not None and base.shape != (profile.n, 6):
        raise ValueError(f"base motion must have shape ({profile.n}, 6), got {base.shape}")
    if block_rows is None:
        block_rows = profile.n if profile.n <= WHOLE_RUN_ROWS else BLOCK_ROWS
    _configure(model, info["ids"], tube, phys_rate)
    raw = _gathered(_physics_rows(model, data, qadr, profile, tube, base, block_rows), block_rows)
    rows = _centred_rows(_continuous_q(raw, adr["q_imu"]), adr, phys_rate, profile.n)
    steps = 0
    for i0, out, steps in _resampled(rows, phys_rate, sample_rate, n_samples, profile.n):
        yield i0, _run_of(out, adr, tube, steps)
    bad = [mujoco.mjtWarning(int(i)).name for i in np.flatnonzero(data.warning.number)]
    if bad:
        raise SimulationError(f"MuJoCo instability in the gimbal model: warnings {bad}, finite=True")


_ROLLOUT: list = []  # the process's one-thread mujoco.rollout.Rollout, made at the first rollout_sensors call


def rollout_sensors(model, data, state: np.ndarray, ctrl: np.ndarray, warmstart: np.ndarray) -> np.ndarray:
    """MuJoCo's sensor rows (n, nsensordata) of n = ``len(ctrl)`` steps from ``state`` (FULLPHYSICS, (nstate,))
    with warm start ``warmstart`` (nv,) and controls ``ctrl`` (n, nu), C-contiguous float64: one
    ``mujoco.rollout`` call without its argument checks and without recording the states (the same numbers).
    ``data`` is left in the state reached (read it with ``mj_getState``) and holds its warm start."""
    if not _ROLLOUT:
        _ROLLOUT.append(mj_rollout.Rollout(nthread=0))
    n = len(ctrl)
    sd = np.empty((1, n, model.nsensordata))
    _ROLLOUT[0].rollout(
        [model],
        [data],
        state[None],
        ctrl[None],
        control_spec=mujoco.mjtState.mjSTATE_CTRL.value,
        skip_checks=True,
        nstep=n,
        initial_warmstart=warmstart[None],
        state=None,
        sensordata=sd,
    )
    return sd[0]


class _Rollout:
    """The model rolled out from ``state`` (FULLPHYSICS), call after call; ``state`` is the state reached."""

    def __init__(self, model, data, state: np.ndarray, block_rows: int):
        self.model, self.data, self.state, self.block_rows = model, data, state, block_rows

    def rows(self, ctrl_of, a: int, b: int):
        """Steps a … b−1 (ctrl rows ``ctrl_of(c, d)``) from a cold warm start, as one ``mujoco.rollout`` call
        would, in calls of at most ``block_rows`` steps with the warm start carried over (the same numbers,
        bit for bit). Yields each call's sensor rows and its last step's index + 1."""
        warmstart = np.zeros(self.model.nv)
        for c in range(a, b, self.block_rows):
            d = min(b, c + self.block_rows)
            sd = rollout_sensors(self.model, self.data, self.state, ctrl_of(c, d), warmstart)
            self.state = np.empty_like(self.state)
            mujoco.mj_getState(self.model, self.data, self.state, _STATE)
            warmstart = self.data.qacc_warmstart.copy()
            if not np.all(np.isfinite(sd)):
                raise SimulationError("MuJoCo instability in the gimbal model: non-finite sensor data")
            yield sd, d


def _physics_rows(model, data, qadr: dict, profile: DriveProfile, tube: Tube, base, block_rows: int):
    """MuJoCo's sensor rows of physics steps 0 … n−1 in order, as (rows, steps taken so far) blocks.

    The trial starts at rest in equilibrium (an initial settle holding the first command, discarded); settled
    pauses repeat their resting row (module docstring). Raises SimulationError on a non-finite row."""
    phys_rate = profile.rate
    angles, omega = profile.angles, profile.omega
    still = profile.still()
    if base is not None:
        still &= ~np.any(base[:, 3:] != 0.0, axis=1)

    def ctrl_of(a: int, b: int) -> np.ndarray:
        """Actuators of steps a … b−1: z,y,x position, z,y,x velocity (then base x,y,z position, velocity)."""
        parts = [angles[a:b], omega[a:b]] + ([] if base is None else [base[a:b]])
        return np.concatenate(parts, axis=1)

    mujoco.mj_resetData(model, data)
    for k, name in enumerate(("z", "y", "x")):
        data.qpos[qadr[name]] = profile.angle0[k]
    data.qpos[qadr["slide"]] = tube.start_at * tube.length
    if base is not None:
        for k, name in enumerate(("base_x", "base_y", "base_z")):
            data.qpos[qadr[name]] = base[0, k]
    mujoco.mj_forward(model, data)
    state = np.empty(mujoco.mj_stateSize(model, _STATE))
    mujoco.mj_getState(model, data, state, _STATE)
    data.warning.number[:] = 0
    # Let the servos take up the load (gravity on the frames and the magnet)
    # holding the initial command, so the trial starts at rest in equilibrium.
    settle = int(round(INITIAL_SETTLE_S * phys_rate))
    hold = ctrl_of(0, 1)[0]
    hold[3:6] = 0.0
    if base is not None:
        hold[9:12] = 0.0
    sim = _Rollout(model, data, state, max(settle, block_rows))
    for _ in sim.rows(lambda a, b: np.tile(hold, (b - a, 1)), 0, settle):
        pass
    sim.state[0] = 0.0
    sim.block_rows = block_rows
    steps = settle
    settle = int(round(SETTLE_S * phys_rate))
    for a, b, skippable in _segments(still, settle + int(round(0.5 * phys_rate))):
        stop = a + settle if skippable else b
        for sd, d in sim.rows(ctrl_of, a, stop):
            yield sd, steps + d - a
        steps += stop - a
        if skippable:
            qvel = sim.state[1 + model.nq : 1 + model.nq + model.nv]
            if np.max(np.abs(qvel)) * (b - stop) / phys_rate < SETTLE_TOL:
                for c in range(stop, b, block_rows):
                    yield np.tile(sd[-1], (min(b, c + block_rows) - c, 1)), steps
                sim.state[0] = b / phys_rate
            else:  # not at rest yet: simulate the whole pause
                for sd, d in sim.rows(ctrl_of, stop, b):
                    yield sd, steps + d - stop
                steps += b - stop


def _gathered(blocks, min_rows: int):
    """(rows, steps) blocks joined until each has at least ``min_rows`` rows (the last may have fewer)."""
    parts: list = []
    count = 0
    steps = 0
    for rows, steps in blocks:
        parts.append(rows)
        count += len(rows)
        if count >= min_rows:
            yield (parts[0] if len(parts) == 1 else np.concatenate(parts)), steps
            parts, count = [], 0
    if parts:
        yield (parts[0] if len(parts) == 1 else np.concatenate(parts)), steps


def _continuous_q(blocks, q_cols: slice):
    """The blocks with MuJoCo's quaternion made continuous (its sign may flip between steps), in place:
    row k is multiplied by the product of the signs of q_i·q_(i−1), i = 1 … k (q as MuJoCo gave them)."""
    last = None  # the previous block's last quaternion as MuJoCo gave it
    sign = 1.0  # the product of the signs up to that row
    for rows, steps in blocks:
        q = rows[:, q_cols]
        given = q.copy()
        flip: np.ndarray
        if last is None:
            flip = np.cumprod(np.where(np.sum(given[1:] * given[:-1], axis=1) < 0, -1.0, 1.0))
            q[1:] *= flip[:, None]
        else:
            before = np.concatenate([last, given[:-1]])
            flip = sign * np.cumprod(np.where(np.sum(given * before, axis=1) < 0, -1.0, 1.0))
            q *= flip[:, None]
        if len(flip):
            sign = float(flip[-1])
        last = given[-1:]
        yield rows, steps


def _centred_rows(blocks, adr: dict, phys_rate: float, n: int):
    """The blocks with the gyro put at the instant of the positions (:func:`_centre_gyro`), as (first row,
    rows, steps), ``n`` rows in all: a row is final once the row after it is known, so each block holds its
    last row back (and keeps the final row before it, for its position)."""
    window = None  # rows kept from the last block: the last final row and the row held back
    w0 = 0  # the index of the window's first row in the run
    done = 0  # rows yielded so far
    for rows, steps in blocks:
        w = rows if window is None else np.concatenate([window, rows])
        end = w0 + len(w) == n
        lo, hi = done - w0, (len(w) if end else len(w) - 1)
        _centre_gyro(w, adr, phys_rate, lo, hi)
        if hi > lo:
            yield done, w[lo:hi], steps
            done = w0 + hi
        keep = max(hi - 1, 0)
        window, w0 = w[keep:], w0 + keep


def _resampled(rows, phys_rate: float, sample_rate: float, n_samples: int, n: int):
    """The final physics rows (``n`` in all, in blocks from :func:`_centred_rows`) resampled to the sample
    times as :func:`resample_cubic` would the whole run: yields (first sample, rows, steps) blocks."""
    ratio = phys_rate / sample_rate
    buf, b0 = None, 0  # the rows kept (the last three: the cubic reads rows j − 1 … j + 2) and the first's index
    i0 = 0
    for _, block, steps in rows:
        buf = block if buf is None else np.concatenate([buf, block])
        b1 = b0 + len(buf)
        i1 = n_samples if b1 == n else _samples_before(b1 - 3, ratio, n_samples)
        if i1 > i0:
            yield i0, _resample_span(buf, b0, n, ratio, 0.0, i0, i1), steps
            i0 = i1
        keep = max(len(buf) - 3, 0)
        buf, b0 = buf[keep:], b0 + keep


def _samples_before(j_max: int, ratio: float, n_samples: int) -> int:
    """The number of samples i whose grid position i·ratio lies at or before row ``j_max`` (as
    :func:`resample_cubic` rounds it), at most ``n_samples``."""
    if j_max < 0:
        return 0
    i = min(n_samples, int((j_max + 1) / ratio) + 2)  # at least the count: i·ratio < j_max + 1 for each
    while i > 0 and math.floor((i - 1) * ratio + 1e-9) > j_max:
        i -= 1
    return i


def _run_of(out: np.ndarray, adr: dict, tube: Tube, steps: int) -> GimbalRun:
    """The GimbalRun of resampled sensor rows ``out``."""
    col = lambda key: np.ascontiguousarray(out[:, adr[key]])
    qs = col("q_imu")
    qs /= norms(qs)[:, None]
    qs *= np.where(qs[:, :1] < 0, -1.0, 1.0)
    # The end stops are soft constraints: at an impact the magnet's centre
    # passes the stop by a few mm (more at coarse timesteps). A real stop is
    # rigid, so the reported magnet position is clamped to the tube (along
    # the tube axis = frame X's x axis = sensor x axis).
    slide = out[:, adr["s_magnet"].start].copy()
    clamped = np.clip(slide, 0.0, tube.length)
    p_magnet = col("p_magnet")
    p_magnet[:, 0] -= slide - clamped
    axis = col("m_axis")
    axis /= norms(axis)[:, None]
    return GimbalRun(
        gyr=col("gyro"),
        acc=col("accel"),
        q=qs,
        p_imu=col("p_imu"),
        p_magnet=p_magnet,
        m_axis=axis,
        joints=np.stack([out[:, adr[k].start] for k in ("q_z", "q_y", "q_x")], axis=1),
        slide=clamped,
        physics_steps=steps,
    )


def _centre_gyro(sens: np.ndarray, adr: dict, phys_rate: float, lo: int = 0, hi: int | None = None) -> None:
    """Put MuJoCo's gyro reading at the same instant as its positions (in place).

    MuJoCo's integrators advance positions with the *new* velocity,
    q_{k+1} = q_k + h·v_{k+1}, so the joint velocity v_k stored at step k is
    the mean rate over [t_k − h, t_k], half a step behind the positions. The
    gyro (= Σ_j a_j·v_j, a_j the joint axes in the sensor frame) is therefore
    read with v_k while the orientation is at t_k: integrating the gyro
    would lag MuJoCo's own orientation by h/2 times each change of rate
    (1.4° after a spin-up to 360 °/s at 128 Hz). The rate at t_k is the
    central difference of the positions, v̄_k = (q_{k+1} − q_{k−1})/(2h); add
    Σ_j a_j·(v̄_j − v_j) to the gyro, with MuJoCo's joint axes a_j.

    Only rows ``lo`` … ``hi``−1 are corrected (all by default): ``sens`` may be a stretch of the run with the
    rows before and after them, read for their positions. Its own first and last rows have v̄ = v (at the
    run's ends: no neighbour).
    """
    pos = np.concatenate([sens[:, adr[k]] for k in ("q_z", "q_y", "q_x")], axis=1)
    vel = np.concatenate([sens[:, adr[k]] for k in ("v_z", "v_y", "v_x")], axis=1)
    vbar = vel.copy()
    vbar[1:-1] = (pos[2:] - pos[:-2]) * (0.5 * phys_rate)
    dv = vbar - vel
    hi = len(sens) if hi is None else hi
    gyro = sens[lo:hi, adr["gyro"]]
    for j, key in enumerate(("axis_z", "axis_y", "axis_x")):
        gyro += sens[lo:hi, adr[key]] * dv[lo:hi, j : j + 1]
    sens[lo:hi, adr["gyro"]] = gyro


def resample_cubic(x, rate_in, rate_out, n_out, offset):
    """Catmull–Rom resampling of rows ``x`` (n, k) from ``rate_in`` to ``rate_out`` Hz.

    Row i of the result is x at grid position i·rate_in/rate_out + ``offset``
    (input rows are at positions 0, 1, 2, …); exact copies where that
    position falls on the grid (equal rates or integer ratios, offset 0).
    """
    return _resample_span(x, 0, len(x), rate_in / rate_out, offset, 0, n_out)


@njit(cache=True)
def _resample_span(x, x0, n, ratio, offset, i0, i1):
    """Rows i0 … i1−1 of :func:`resample_cubic` of a run of ``n`` rows of which ``x`` holds rows x0, x0 + 1, …
    (all those the cubic reads: rows j − 1 … j + 2 of grid position i·ratio + offset, clamped to the run)."""
    k = x.shape[1]
    out = np.empty((i1 - i0, k))
    for i in range(i0, i1):
        pos = i * ratio + offset
        j = int(np.floor(pos + 1e-9))
        u = pos - j
        r = i - i0
        if u < 1e-9:
            out[r] = x[min(j, n - 1) - x0]
            continue
        j0, j2, j3 = max(j - 1, 0) - x0, min(j + 1, n - 1) - x0, min(j + 2, n - 1) - x0
        j1 = j - x0
        u2, u3 = u * u, u * u * u
        c0 = -0.5 * u3 + u2 - 0.5 * u
        c1 = 1.5 * u3 - 2.5 * u2 + 1.0
        c2 = -1.5 * u3 + 2.0 * u2 + 0.5 * u
        c3 = 0.5 * u3 - 0.5 * u2
        for c in range(k):
            out[r, c] = c0 * x[j0, c] + c1 * x[j1, c] + c2 * x[j2, c] + c3 * x[j3, c]
    return out
