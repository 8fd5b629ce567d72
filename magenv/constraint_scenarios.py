"""Two-link scenarios (Jung & Lee 2019): a scenario + a seed → one Trial, always the same.

Public API (same shape as ``magenv.scenarios``)::

    make_trial(name, seed, **overrides) -> Trial
    scenario_names() -> list[str]
    get_scenario(name) -> ConstraintConfig
    configure(name, **overrides) -> ConstraintConfig

Scenarios (the paper's Table 1 and a training family):

* ``constraint_test1`` — mean external acceleration of link i's sensor ≈ 0.9
  m/s², five tool approaches of 3 s each (15 s disturbed), 75 s;
* ``constraint_test2`` — the same disturbances, ≈ 2.0 m/s²;
* ``constraint_test3`` — ≈ 1.9 m/s², one 30 s approach (15–45 s), 60 s;
* ``constraint_random`` — the training family: stretches of stillness, slow
  and brisk motion; 0–5 tool approaches of random strength, distance and
  length; random lab inhomogeneity, Earth field, sensor noise and gyro bias.

The world (``magenv.sim.twolink``): link j moved by a carriage along a
commanded path, link i driven about the spherical joint; a MIMU on each link
at the paper's offsets. Both sensors go through ``apply_sensor_model``
(``MTW`` error model: an Xsens MTw-like unit, no magnetometer lag or hold);
the paper's gyroscope bias [1.4, 1.4, 1.6]·10⁻³ rad/s is then added to link
i's gyroscope on purpose (§3.1). Magnetic field at each sensor = Earth field
+ the lab's weak inhomogeneity + a magnetised tool (a dipole on a hand-held
path that comes up to ``tool_near`` from link i's sensor, from a random
horizontal direction, following the sensor's swing only in part; it never
comes closer than tool_near/2). The motion is rescaled once per trial to hit
``target_ext_acc`` (Table 1's "average of external acceleration", read as
the mean ‖free acceleration‖ of link i's sensor). The lab's field is
that of a few dipoles (benches, floor) 0.4–0.9 m from link i's sensor's
starting position p0, counted relative to its value at p0 — the local field
at p0 is the reference m the filters use and defines north, as a lab's
calibration would — and scaled so that its mean deviation over a sphere of
radius ``LAB_RADIUS`` about p0 is ``lab_inhomogeneity``·m0 (paper: ≈ 0.07 Au
observed without the tool).

Trial layout (frames and units as ``magenv.trial``): ``gyr/acc/mag/q_true``
are link i's sensor; ``extra`` holds link j's sensor ``gyr_j`` (rad/s),
``acc_j`` (m/s²), ``mag_j`` (µT), each (N, 3) in sensor j's frame, and
``q_j`` (N, 4) link j's true orientation sensor j → ENU (the paper's filter
is given it from the motion-capture system, §3.1). ``meta["lever_i_m"]`` and
``meta["lever_j_m"]`` are r_i and r_j (m, sensor frames: the calibration the
paper does before measuring). ``truth``: ``mag_disturbance`` (N, 3) µT sensor
i frame (lab + tool), ``tool_field`` (N, 3) µT sensor i frame,
``tool_distance`` (N,) m, ``ext_acc`` (N,) ‖free acceleration‖ of sensor i,
m/s², ``stationary`` (N,) bool (both links still).

Each trial draws from six independent streams spawned from
``SeedSequence(seed)``: motion, tool, lab, field, sensor i, sensor j.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magenv import quaternion as quat
from magenv.config_checks import apply_overrides, check_intervals, check_number, check_range, config_json
from magenv.sim import earth
from magenv.sim import twolink as tl
from magenv.sim.hand import Approach
from magenv.sim.magnet import dipole_field
from magenv.sim.sensors import SensorConfig, apply_sensor_model
from magenv.trial import Trial

#: Gyroscope bias the paper adds to link i's gyroscope on purpose (§3.1), rad/s, sensor frame.
PAPER_GYRO_BIAS = (1.4e-3, 1.4e-3, 1.6e-3)
#: An Xsens MTw-like unit at 100 Hz (noise densities 0.01 °/s/√Hz, ~200 µg/√Hz,
#: 0.2 mGs/√Hz over ~50 Hz); no magnetometer lag or sample-and-hold. Its own
#: gyro bias is left out: the paper's deliberate bias dominates it.
MTW = SensorConfig(gyr_noise_dps=0.07, gyr_bias_dps=0.0, gyr_drift_dps=0.001, acc_noise=0.02, acc_bias=0.01,
                   mag_noise_ut=0.14, mag_hard_iron_ut=0.3, mag_soft_iron=0.005, mag_lag_samples=0,
                   mag_hold_fraction=0.0)
#: Motion amplitude per joint at motion_scale 1 (m for tx, ty, tz; rad for jz … ix).
BASE_AMPLITUDE = (0.08, 0.08, 0.04, 0.4, 0.25, 0.3, 0.5, 0.5, 0.5)
#: Radius of the workspace over which the lab's inhomogeneity is scaled, m.
LAB_RADIUS = 0.25
#: How much of the sensor's swing about its 1 s mean position the tool-holding hand ignores.
TOOL_FOLLOW = 0.5
#: A sample counts as stationary when both gyros (noise-free) read less than this, rad/s.
STATIONARY_RATE = 1e-3


@dataclasses.dataclass(frozen=True)
class ConstraintConfig:
    """A two-link trial (defaults: the paper's Test 2).

    Attributes:
        duration: s; rate: sensor rate, Hz; physics_rate: MuJoCo rate, Hz (a multiple of ``rate``).
        field_norm, field_dip: undisturbed Earth field, µT and degrees down (``earth.PAPER``).
        sensor: both MIMUs' error model.
        gyro_bias: added to link i's gyroscope, rad/s, sensor frame (paper §3.1).
        amplitude: motion amplitude per joint (tx, ty, tz m; jz … ix rad) at motion_scale 1.
        motion_scale: factor on ``amplitude`` (sets the external acceleration).
        target_ext_acc: if set, the motion is rescaled once after a first
            simulation so that the mean ‖free acceleration‖ of link i's
            sensor (over the whole trial) comes out at this value, m/s².
        freq_hz: range of the motion's sine frequencies, Hz.
        start_rest: both links still at the start, s (the filters initialise).
        lab_inhomogeneity: mean lab field deviation from the reference over the workspace, fraction of m0.
        tool_moment: the tool's dipole moment, A·m².
        tool_far, tool_near: the tool's distance from link i's sensor, away and close, m.
        tool_travel: time to bring the tool in (and out), s.
        disturbances: (start s, hold s) per approach; hold = time at ``tool_near``.
        jitter_s: random shift of each approach start, s.
    """

    duration: float = 75.0
    rate: float = 100.0
    physics_rate: float = tl.PHYSICS_RATE
    field_norm: float = earth.PAPER[0]
    field_dip: float = earth.PAPER[1]
    sensor: SensorConfig = MTW
    gyro_bias: tuple = PAPER_GYRO_BIAS
    amplitude: tuple = BASE_AMPLITUDE
    motion_scale: float = 1.0
    target_ext_acc: float | None = 2.0
    freq_hz: tuple = (0.15, 0.6)
    start_rest: float = 3.0
    lab_inhomogeneity: float = 0.07
    tool_moment: float = 0.08
    tool_far: float = 0.6
    tool_near: float = 0.08
    tool_travel: float = 1.0
    disturbances: tuple = ((9.0, 3.0), (21.0, 3.0), (33.0, 3.0), (45.0, 3.0), (57.0, 3.0))
    jitter_s: float = 1.0

    def __post_init__(self) -> None:
        check_number("duration", self.duration, 1.0, 3600.0)
        check_number("rate", self.rate, 10.0, 2000.0)
        check_number("physics_rate", self.physics_rate, self.rate, 20000.0)
        check_number("field_norm", self.field_norm, 0.0, 1000.0, lo_open=True)
        check_number("field_dip", self.field_dip, -90.0, 90.0)
        if not isinstance(self.sensor, SensorConfig):
            raise ValueError(f"sensor must be a SensorConfig, got {type(self.sensor).__name__}")
        if len(self.gyro_bias) != 3:
            raise ValueError(f"gyro_bias must be 3 numbers (rad/s), got {self.gyro_bias!r}")
        for i, b in enumerate(self.gyro_bias):
            check_number(f"gyro_bias[{i}]", b, -1.0, 1.0)
        if len(self.amplitude) != tl.N_JOINTS:
            raise ValueError(f"amplitude must have {tl.N_JOINTS} entries ({', '.join(tl.JOINTS)}), got {self.amplitude!r}")
        for i, a in enumerate(self.amplitude):
            check_number(f"amplitude[{i}]", a, 0.0, 1.5)
        check_number("motion_scale", self.motion_scale, 0.0, 3.0)
        if self.target_ext_acc is not None:
            check_number("target_ext_acc", self.target_ext_acc, 0.0, 20.0, lo_open=True)
        check_range("freq_hz", self.freq_hz, 0.01, 5.0)
        check_number("start_rest", self.start_rest, 0.0, self.duration)
        check_number("lab_inhomogeneity", self.lab_inhomogeneity, 0.0, 1.0)
        check_number("tool_moment", self.tool_moment, 0.0, 10.0)
        check_number("tool_near", self.tool_near, 0.02, 2.0)
        check_number("tool_far", self.tool_far, self.tool_near, 5.0)
        check_number("tool_travel", self.tool_travel, 0.05, 60.0)
        check_number("jitter_s", self.jitter_s, 0.0, 60.0)
        check_intervals("disturbances", self.disturbances)


@dataclasses.dataclass(frozen=True)
class ConstraintRandomConfig(ConstraintConfig):
    """The training family: every range is drawn uniformly per seed (overrides the fixed fields).

    Attributes:
        segment_s: length of a motion stretch, s; each stretch is still (prob.
            ``still_prob``), slow (``slow_prob``, level 0.15) or brisk (level in ``level``).
        motion_scale_range: overall motion scale.
        n_tool: (min, max) number of tool approaches; tool_hold_s: hold per approach, s.
        tool_near_m, tool_moment_am2: tool distance and moment ranges.
        lab_range: lab inhomogeneity range (fraction of m0).
        field_norm_ut, field_dip_deg: Earth field ranges.
        noise_scale: factor on the white-noise levels of ``sensor``.
        gyro_bias_max: |gyro bias| drawn in [0, this], random direction, rad/s.
    """

    duration: float = 60.0
    target_ext_acc: float | None = None
    segment_s: tuple = (3.0, 12.0)
    still_prob: float = 0.2
    slow_prob: float = 0.2
    level: tuple = (0.4, 1.3)
    motion_scale_range: tuple = (0.5, 1.2)
    n_tool: tuple = (0, 5)
    tool_hold_s: tuple = (1.0, 20.0)
    tool_near_m: tuple = (0.05, 0.2)
    tool_moment_am2: tuple = (0.03, 0.3)
    lab_range: tuple = (0.0, 0.12)
    field_norm_ut: tuple = earth.NORM_RANGE_UT
    field_dip_deg: tuple = earth.DIP_RANGE_DEG
    noise_scale: tuple = (0.5, 2.0)
    gyro_bias_max: float = 3e-3

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range("segment_s", self.segment_s, 0.5)
        check_number("still_prob", self.still_prob, 0.0, 1.0)
        check_number("slow_prob", self.slow_prob, 0.0, 1.0 - self.still_prob)
        check_range("level", self.level, 0.0, 3.0)
        check_range("motion_scale_range", self.motion_scale_range, 0.0, 3.0)
        check_range("n_tool", self.n_tool, 0, 50)
        check_range("tool_hold_s", self.tool_hold_s, 0.0)
        check_range("tool_near_m", self.tool_near_m, 0.02, 2.0)
        check_range("tool_moment_am2", self.tool_moment_am2, 0.0, 10.0)
        check_range("lab_range", self.lab_range, 0.0, 1.0)
        check_range("field_norm_ut", self.field_norm_ut, 1.0, 1000.0)
        check_range("field_dip_deg", self.field_dip_deg, -90.0, 90.0)
        check_range("noise_scale", self.noise_scale, 0.0, 100.0)
        check_number("gyro_bias_max", self.gyro_bias_max, 0.0, 1.0)


SCENARIOS: dict[str, ConstraintConfig] = {
    "constraint_test1": ConstraintConfig(motion_scale=0.5, target_ext_acc=0.9),
    "constraint_test2": ConstraintConfig(motion_scale=1.0, target_ext_acc=2.0),
    "constraint_test3": ConstraintConfig(duration=60.0, motion_scale=1.0, target_ext_acc=1.9,
                                         disturbances=((13.0, 30.0),), jitter_s=0.0),
    "constraint_random": ConstraintRandomConfig(),
}


def scenario_names() -> list[str]:
    """Names of the two-link scenarios, in a stable order."""
    return list(SCENARIOS)


def get_scenario(name: str) -> ConstraintConfig:
    """The default config of ``name``; ValueError lists the known names."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown two-link scenario {name!r}; known: {', '.join(SCENARIOS)}")
    return SCENARIOS[name]


def configure(name: str, **overrides) -> ConstraintConfig:
    """Scenario ``name``'s config with ``overrides`` (config fields or ``SensorConfig`` fields)."""
    return apply_overrides(name, get_scenario(name), overrides)


# ------------------------------------------------------------------ planning


@dataclasses.dataclass(eq=False)
class _Plan:
    command: tl.Command
    approaches: list
    tool_near: float
    tool_moment: float
    lab: float
    field: tuple
    sensor: SensorConfig
    gyro_bias: np.ndarray
    meta: dict


def _plan_fixed(cfg: ConstraintConfig, rngs) -> _Plan:
    r_motion, r_tool = rngs[0], rngs[1]
    n = int(round(cfg.duration * cfg.physics_rate))
    t = np.arange(n) / cfg.physics_rate
    env = tl.envelope(t, [(cfg.start_rest, 1.0)])
    amp = cfg.motion_scale * np.asarray(cfg.amplitude)
    cmd = tl.smooth_motion(r_motion, cfg.duration, cfg.physics_rate, env, amp, cfg.freq_hz)
    apps = [Approach(start=max(0.0, s + r_tool.uniform(-cfg.jitter_s, cfg.jitter_s)), hold=h, travel=cfg.tool_travel)
            for s, h in cfg.disturbances]
    return _Plan(cmd, apps, cfg.tool_near, cfg.tool_moment, cfg.lab_inhomogeneity,
                 (cfg.field_norm, cfg.field_dip), cfg.sensor, np.asarray(cfg.gyro_bias, float), {})


def _plan_random(cfg: ConstraintRandomConfig, rngs) -> _Plan:
    r_motion, r_tool, r_lab, r_field, r_sensor = rngs[:5]
    n = int(round(cfg.duration * cfg.physics_rate))
    t = np.arange(n) / cfg.physics_rate
    levels, s = [], cfg.start_rest
    while s < cfg.duration:
        u = r_motion.uniform()
        lvl = 0.0 if u < cfg.still_prob else 0.15 if u < cfg.still_prob + cfg.slow_prob else r_motion.uniform(*cfg.level)
        levels.append((s, float(lvl)))
        s += r_motion.uniform(*cfg.segment_s)
    scale = float(r_motion.uniform(*cfg.motion_scale_range))
    env = tl.envelope(t, levels)
    cmd = tl.smooth_motion(r_motion, cfg.duration, cfg.physics_rate, env, scale * np.asarray(cfg.amplitude),
                           cfg.freq_hz)
    apps, s = [], float(r_tool.uniform(cfg.start_rest + 1.0, cfg.start_rest + 10.0))
    for _ in range(int(r_tool.integers(cfg.n_tool[0], cfg.n_tool[1] + 1))):
        hold = float(r_tool.uniform(*cfg.tool_hold_s))
        if s + hold + 2 * cfg.tool_travel > cfg.duration:
            break
        apps.append(Approach(s, hold, travel=cfg.tool_travel))
        s += hold + 2 * cfg.tool_travel + float(r_tool.uniform(2.0, 12.0))
    near = float(r_tool.uniform(*cfg.tool_near_m))
    moment = float(r_tool.uniform(*cfg.tool_moment_am2))
    lab = float(r_lab.uniform(*cfg.lab_range))
    field = earth.random_location(r_field, cfg.field_norm_ut, cfg.field_dip_deg)
    noise = float(r_sensor.uniform(*cfg.noise_scale))
    d = r_sensor.normal(size=3)
    bias = d / np.linalg.norm(d) * r_sensor.uniform(0.0, cfg.gyro_bias_max)
    meta = {"motion_levels": levels, "motion_scale": scale, "noise_scale": noise, "tool_near_m": near,
            "tool_moment_am2": moment, "lab_inhomogeneity": lab}
    return _Plan(cmd, apps, near, moment, lab, field, cfg.sensor.scaled(noise), bias, meta)


# ------------------------------------------------------------------ fields


def _lab_field(rng: np.random.Generator, p0: np.ndarray, strength_ut: float, n_src: int = 3):
    """A weak lab field: a function p (N, 3) → field (N, 3) µT, world, zero at ``p0``, with mean
    |field| ``strength_ut`` over the sphere of radius ``LAB_RADIUS`` about p0."""
    dirs = rng.normal(size=(n_src, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2])  # mostly below and around (floor, benches)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pos = p0 + dirs * rng.uniform(0.4, 0.9, (n_src, 1))
    mom = rng.normal(size=(n_src, 3))
    src = [(pos[k][None], mom[k][None]) for k in range(n_src)]
    ref = _field_at(p0[None], src)

    def raw(p):
        return _field_at(p, src) - ref

    probe = _sphere(40) * LAB_RADIUS + p0
    mean = np.linalg.norm(raw(probe), axis=1).mean()
    scale = strength_ut / mean if mean > 0 else 0.0
    return lambda p: scale * raw(p)


def _sphere(n: int) -> np.ndarray:
    """n roughly even unit vectors (Fibonacci sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _field_at(p: np.ndarray, sources: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Sum of dipole fields (µT, world) at points p (N, 3); a source is (pos (N|1, 3), moment (N|1, 3))."""
    out = np.zeros_like(p)
    for pos, mom in sources:
        out += dipole_field(np.ascontiguousarray(p - pos), np.ascontiguousarray(np.broadcast_to(mom, p.shape)))
    return out


def _tool_path(t: np.ndarray, approaches: list[Approach], far: float, near: float, azimuth: float,
               rng: np.random.Generator, tremor_m: float = 0.003, sway_m: float = 0.02):
    """The hand-held tool's offset from the sensor (N, 3) m and moment direction (N, 3), world.

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


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average of rows (edges padded)."""
    if k < 2:
        return x
    pad = np.concatenate([np.repeat(x[:1], k // 2, 0), x, np.repeat(x[-1:], k - k // 2 - 1, 0)])
    c = np.cumsum(np.concatenate([np.zeros((1, x.shape[1])), pad]), axis=0)
    return (c[k:] - c[:-k]) / k


# ------------------------------------------------------------------ trials


def make_trial(name: str, seed: int, **overrides) -> Trial:
    """Simulate two-link scenario ``name`` with ``seed`` (int ≥ 0): the same Trial bit for bit every time."""
    cfg = configure(name, **overrides)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(6)]
    plan = (_plan_random if isinstance(cfg, ConstraintRandomConfig) else _plan_fixed)(cfg, rngs)
    return _simulate(plan, cfg, name, int(seed), rngs)


def _simulate(plan: _Plan, cfg: ConstraintConfig, scenario: str, seed: int, rngs) -> Trial:
    r_tool, r_lab, r_si, r_sj = rngs[1], rngs[2], rngs[4], rngs[5]
    n = int(round(cfg.duration * cfg.rate))
    run = tl.simulate_twolink(plan.command, cfg.rate, n)
    if cfg.target_ext_acc is not None:  # the motion is linear in its amplitude: rescale once
        ext = np.linalg.norm(quat.rotate(run.q_i, run.acc_i) - quat.gravity_up(), axis=1).mean()
        if ext > 0:
            k = cfg.target_ext_acc / ext
            plan.command = tl.Command(plan.command.rate, plan.command.pos * k, plan.command.vel * k)
            plan.meta["motion_rescale"] = float(k)
            run = tl.simulate_twolink(plan.command, cfg.rate, n)
    t = np.arange(n) / cfg.rate
    m0 = plan.field[0]
    b_earth = quat.earth_field(*plan.field)
    lab = _lab_field(r_lab, run.p_i[0], plan.lab * m0)
    # The tool: a hand path (far → near → far) about link i's sensor, from a
    # random horizontal direction.
    az = r_tool.uniform(-np.pi, np.pi)
    offset, axis = _tool_path(t, plan.approaches, cfg.tool_far, plan.tool_near, az, r_tool)
    # The hand follows the moving sensor only loosely (half of its swing
    # about the 1 s mean) and never comes closer than half of tool_near.
    rel = offset + TOOL_FOLLOW * (_smooth(run.p_i, int(round(cfg.rate))) - run.p_i)
    d = np.linalg.norm(rel, axis=1, keepdims=True)
    rel *= np.sqrt(d * d + (0.5 * plan.tool_near) ** 2) / d
    p_tool = run.p_i + rel
    tool = [(p_tool, plan.tool_moment * axis)]
    fields = {}
    for s, p, q in (("i", run.p_i, run.q_i), ("j", run.p_j, run.q_j)):
        b_lab = lab(p)
        b_tool = _field_at(p, tool)
        fields[s] = (quat.rotate_inv(q, b_earth + b_lab + b_tool), quat.rotate_inv(q, b_lab + b_tool),
                     quat.rotate_inv(q, b_tool))
    gyr_i, acc_i, mag_i = apply_sensor_model(run.gyr_i, run.acc_i, fields["i"][0], cfg.rate, plan.sensor, r_si)
    gyr_j, acc_j, mag_j = apply_sensor_model(run.gyr_j, run.acc_j, fields["j"][0], cfg.rate, plan.sensor, r_sj)
    gyr_i = gyr_i + plan.gyro_bias  # paper §3.1: bias added on purpose
    ext = np.linalg.norm(quat.rotate(run.q_i, run.acc_i) - quat.gravity_up(), axis=1)
    still = (np.linalg.norm(run.gyr_i, axis=1) < STATIONARY_RATE) & (np.linalg.norm(run.gyr_j, axis=1) < STATIONARY_RATE)
    r_i, r_j = tl.lever_arms()
    meta = {
        "scenario": scenario, "seed": seed, "lever_i_m": r_i.tolist(), "lever_j_m": r_j.tolist(),
        "gyro_bias_rad_s": plan.gyro_bias.tolist(), "mean_ext_acc": float(ext.mean()),
        "approach_starts_s": [a.start for a in plan.approaches], "approach_holds_s": [a.hold for a in plan.approaches],
        "tool_azimuth_rad": float(az), "physics_steps": run.physics_steps, **plan.meta,
        "config": config_json(cfg),
    }
    return Trial(
        name=f"{scenario}#{seed}", rate=cfg.rate, gyr=gyr_i, acc=acc_i, mag=mag_i, q_true=run.q_i,
        field_norm=plan.field[0], field_dip=plan.field[1],
        truth={"mag_disturbance": fields["i"][1], "tool_field": fields["i"][2],
               "tool_distance": np.linalg.norm(p_tool - run.p_i, axis=1), "ext_acc": ext, "stationary": still},
        extra={"gyr_j": gyr_j, "acc_j": acc_j, "mag_j": mag_j, "q_j": run.q_j},
        meta=meta,
    )
