"""The two-link world (Jung & Lee 2019): two links on a spherical joint, a MIMU on each; configs, planning, simulation.

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
from collections.abc import Callable
from typing import Any

import numpy as np

from magenv import quaternion as quat
from magenv.checks import check_intervals, check_number, check_numbers
from magenv.scenarios.world import STATIONARY_RATE, World, check_shared_fields, limited, simulated_trial
from magenv.sim import earth, indoor
from magenv.sim import twolink as tl
from magenv.sim.hand import Approach, tool_path
from magenv.sim.magnet import dipole_field
from magenv.sim.sensors import SensorConfig, apply_sensor_model
from magenv.trial import Trial

#: Gyroscope bias the paper adds to link i's gyroscope on purpose (§3.1), rad/s, sensor frame.
PAPER_GYRO_BIAS = (1.4e-3, 1.4e-3, 1.6e-3)
#: An Xsens MTw-like unit at 100 Hz (noise densities 0.01 °/s/√Hz, ~200 µg/√Hz,
#: 0.2 mGs/√Hz over ~50 Hz); no magnetometer lag or sample-and-hold. Its own
#: gyro bias is left out: the paper's deliberate bias dominates it.
MTW = SensorConfig(
    gyr_noise_dps=0.07,
    gyr_bias_dps=0.0,
    gyr_drift_dps=0.001,
    acc_noise=0.02,
    acc_bias=0.01,
    mag_noise_ut=0.14,
    mag_hard_iron_ut=0.3,
    mag_soft_iron=0.005,
    mag_noise_taps=1,
    gyr_lag_samples=0,
    mag_lag_samples=0,
    mag_hold_fraction=0.0,
)
#: Motion amplitude per joint at motion_scale 1 (m for tx, ty, tz; rad for jz … ix).
BASE_AMPLITUDE = (0.08, 0.08, 0.04, 0.4, 0.25, 0.3, 0.5, 0.5, 0.5)
#: Radius of the workspace over which the lab's inhomogeneity is scaled, m.
LAB_RADIUS = 0.25
#: How much of the sensor's swing about its 1 s mean position the tool-holding hand ignores.
TOOL_FOLLOW = 0.5


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

    duration: float = limited(75.0, 1.0, 3600.0)
    rate: float = limited(100.0, 10.0, 2000.0)
    physics_rate: float = limited(tl.PHYSICS_RATE, "rate", 20000.0)
    field_norm: float = earth.PAPER[0]
    field_dip: float = earth.PAPER[1]
    sensor: SensorConfig = MTW
    gyro_bias: tuple = PAPER_GYRO_BIAS
    amplitude: tuple = BASE_AMPLITUDE
    motion_scale: float = limited(1.0, 0.0, 3.0)
    target_ext_acc: float | None = 2.0
    freq_hz: tuple = limited((0.15, 0.6), 0.01, 5.0)
    start_rest: float = limited(3.0, 0.0, "duration")
    lab_inhomogeneity: float = limited(0.07, 0.0, 1.0)
    tool_moment: float = limited(0.08, 0.0, 10.0)
    tool_far: float = limited(0.6, "tool_near", 5.0)
    tool_near: float = limited(0.08, 0.02, 2.0)
    tool_travel: float = limited(1.0, 0.05, 60.0)
    disturbances: tuple = ((9.0, 3.0), (21.0, 3.0), (33.0, 3.0), (45.0, 3.0), (57.0, 3.0))
    jitter_s: float = limited(1.0, 0.0, 60.0)

    def __post_init__(self) -> None:
        check_shared_fields(self)
        check_numbers("gyro_bias", self.gyro_bias, 3, -1.0, 1.0, "numbers (rad/s)")
        check_numbers("amplitude", self.amplitude, tl.N_JOINTS, 0.0, 1.5, f"amplitudes ({', '.join(tl.JOINTS)})")
        if self.target_ext_acc is not None:
            check_number("target_ext_acc", self.target_ext_acc, 0.0, 20.0, lo_open=True)
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
    segment_s: tuple = limited((3.0, 12.0), 0.5)
    still_prob: float = limited(0.2, 0.0, 1.0)
    slow_prob: float = 0.2
    level: tuple = limited((0.4, 1.3), 0.0, 3.0)
    motion_scale_range: tuple = limited((0.5, 1.2), 0.0, 3.0)
    n_tool: tuple = limited((0, 5), 0, 50)
    tool_hold_s: tuple = limited((1.0, 20.0), 0.0)
    tool_near_m: tuple = limited((0.05, 0.2), 0.02, 2.0)
    tool_moment_am2: tuple = limited((0.03, 0.3), 0.0, 10.0)
    lab_range: tuple = limited((0.0, 0.12), 0.0, 1.0)
    field_norm_ut: tuple = limited(earth.NORM_RANGE_UT, 1.0, 1000.0)
    field_dip_deg: tuple = limited(earth.DIP_RANGE_DEG, -90.0, 90.0)
    noise_scale: tuple = limited((0.5, 2.0), 0.0, 100.0)
    gyro_bias_max: float = limited(3e-3, 0.0, 1.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_number("slow_prob", self.slow_prob, 0.0, 1.0 - self.still_prob)


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
    apps = [
        Approach(start=max(0.0, s + r_tool.uniform(-cfg.jitter_s, cfg.jitter_s)), hold=h, travel=cfg.tool_travel)
        for s, h in cfg.disturbances
    ]
    return _Plan(
        cmd,
        apps,
        cfg.tool_near,
        cfg.tool_moment,
        cfg.lab_inhomogeneity,
        (cfg.field_norm, cfg.field_dip),
        cfg.sensor,
        np.asarray(cfg.gyro_bias, float),
        {},
    )


def _plan_random(cfg: ConstraintRandomConfig, rngs) -> _Plan:
    r_motion, r_tool, r_lab, r_field, r_sensor = rngs[:5]
    n = int(round(cfg.duration * cfg.physics_rate))
    t = np.arange(n) / cfg.physics_rate
    levels, s = [], cfg.start_rest
    while s < cfg.duration:
        u = r_motion.uniform()
        lvl = (
            0.0 if u < cfg.still_prob else 0.15 if u < cfg.still_prob + cfg.slow_prob else r_motion.uniform(*cfg.level)
        )
        levels.append((s, float(lvl)))
        s += r_motion.uniform(*cfg.segment_s)
    scale = float(r_motion.uniform(*cfg.motion_scale_range))
    env = tl.envelope(t, levels)
    cmd = tl.smooth_motion(
        r_motion, cfg.duration, cfg.physics_rate, env, scale * np.asarray(cfg.amplitude), cfg.freq_hz
    )
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
    meta = {
        "motion_levels": levels,
        "motion_scale": scale,
        "noise_scale": noise,
        "tool_near_m": near,
        "tool_moment_am2": moment,
        "lab_inhomogeneity": lab,
    }
    return _Plan(cmd, apps, near, moment, lab, field, cfg.sensor.scaled(noise), bias, meta)


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average of rows (edges padded)."""
    if k < 2:
        return x
    pad = np.concatenate([np.repeat(x[:1], k // 2, 0), x, np.repeat(x[-1:], k - k // 2 - 1, 0)])
    c = np.cumsum(np.concatenate([np.zeros((1, x.shape[1])), pad]), axis=0)
    return (c[k:] - c[:-k]) / k


# ------------------------------------------------------------------ trials


def _simulate(scenario: str, cfg: ConstraintConfig, seed: int, rngs: list[np.random.Generator]) -> Trial:
    """Plan the trial, run the two links, add the fields and both sensor models (``rngs``: motion, tool,
    lab, field, sensor i, sensor j)."""
    plan = _PLANNERS[type(cfg)](cfg, rngs)
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
    lab = indoor.lab_field(r_lab, run.p_i[0], plan.lab * m0, LAB_RADIUS)
    # The tool: a hand path (far → near → far) about link i's sensor, from a
    # random horizontal direction.
    az = r_tool.uniform(-np.pi, np.pi)
    offset, axis = tool_path(t, plan.approaches, cfg.tool_far, plan.tool_near, az, r_tool)
    # The hand follows the moving sensor only loosely (half of its swing
    # about the 1 s mean) and never comes closer than half of tool_near.
    rel = offset + TOOL_FOLLOW * (_smooth(run.p_i, int(round(cfg.rate))) - run.p_i)
    d = np.linalg.norm(rel, axis=1, keepdims=True)
    rel *= np.sqrt(d * d + (0.5 * plan.tool_near) ** 2) / d
    p_tool = run.p_i + rel
    m_tool = plan.tool_moment * axis
    fields = {}
    for s, p, q in (("i", run.p_i, run.q_i), ("j", run.p_j, run.q_j)):
        b_lab = lab(p)
        b_tool = dipole_field(p - p_tool, m_tool)
        fields[s] = (
            quat.rotate_inv(q, b_earth + b_lab + b_tool),
            quat.rotate_inv(q, b_lab + b_tool),
            quat.rotate_inv(q, b_tool),
        )
    gyr_i, acc_i, mag_i = apply_sensor_model(run.gyr_i, run.acc_i, fields["i"][0], cfg.rate, plan.sensor, r_si)
    gyr_j, acc_j, mag_j = apply_sensor_model(run.gyr_j, run.acc_j, fields["j"][0], cfg.rate, plan.sensor, r_sj)
    gyr_i = gyr_i + plan.gyro_bias  # paper §3.1: bias added on purpose
    ext = np.linalg.norm(quat.rotate(run.q_i, run.acc_i) - quat.gravity_up(), axis=1)
    still = (np.linalg.norm(run.gyr_i, axis=1) < STATIONARY_RATE) & (
        np.linalg.norm(run.gyr_j, axis=1) < STATIONARY_RATE
    )
    r_i, r_j = tl.lever_arms()
    truth = {
        "mag_disturbance": fields["i"][1],
        "tool_field": fields["i"][2],
        "tool_distance": np.linalg.norm(p_tool - run.p_i, axis=1),
        "ext_acc": ext,
        "stationary": still,
    }
    drawn = {
        "lever_i_m": r_i,
        "lever_j_m": r_j,
        "gyro_bias_rad_s": plan.gyro_bias,
        "mean_ext_acc": ext.mean(),
        "approach_starts_s": [a.start for a in plan.approaches],
        "approach_holds_s": [a.hold for a in plan.approaches],
        "tool_azimuth_rad": az,
        "physics_steps": run.physics_steps,
        **plan.meta,
    }
    extra = {"gyr_j": gyr_j, "acc_j": acc_j, "mag_j": mag_j, "q_j": run.q_j}
    readings = (gyr_i, acc_i, mag_i)
    return simulated_trial(scenario, seed, cfg, readings, run.q_i, plan.field, truth, drawn, extra=extra)


#: The two-link scenarios: name → default config.
SCENARIOS: dict[str, ConstraintConfig] = {
    "constraint_test1": ConstraintConfig(motion_scale=0.5, target_ext_acc=0.9),
    "constraint_test2": ConstraintConfig(motion_scale=1.0, target_ext_acc=2.0),
    "constraint_test3": ConstraintConfig(
        duration=60.0, motion_scale=1.0, target_ext_acc=1.9, disturbances=((13.0, 30.0),), jitter_s=0.0
    ),
    "constraint_random": ConstraintRandomConfig(),
}

#: The planner of each config class: (cfg, rngs) → _Plan.
_PLANNERS: dict[type, Callable[..., Any]] = {ConstraintConfig: _plan_fixed, ConstraintRandomConfig: _plan_random}

WORLD = World("twolink", "two-link", SCENARIOS, _simulate, n_streams=6)
