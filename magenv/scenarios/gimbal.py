"""The gimbal world (Fan et al. 2017): a 3-axis gimbal with a MIMU, magnets near it; configs, planning, simulation.

Scenarios (Fan et al. 2017 §3; the randomised family for training):

* ``stationary_magnet`` — protocol 1 (§3.1, Figure 8): gimbal still, a
  hand-held magnet approaches from 70 cm to 10 cm above the MIMU three times
  for a few seconds and once for ~60 s; ~110 s.
* ``dynamic_clean`` — protocol 2 (§3.2): intermittent slow rotations with
  pauses, no magnet; 70 s (the paper: 60–80 s).
* ``dynamic_magnet`` — protocol 3 (§3.3, Figure 10): all frames turning at
  about 40, 70, 360 °/s (Z, Y, X) with the sliding magnet in its tube; 60 s.
* ``random`` — the training family: random rate profiles with pauses, no
  magnet / tube magnet / hand-held magnet with random strength and placement,
  random Earth field (magnitude, dip) and sensor noise levels.
* ``manual_routines`` — survey (issue 4, item 7): short tasks separated by
  2 s pauses, and one ~10 s reach of the whole gimbal (moving base) to a
  small magnet lying in the world: a very large disturbance (hundreds of µT).
* ``gait_field`` — survey: ~3 minutes of continuous motion without pauses,
  the gimbal on a base walking a figure-eight (with gait bounce and sway)
  through an indoor field made of several distant sources, so the field
  changes smoothly with position.

Overrides are field names of the scenario's config or of its
:class:`~magenv.sim.sensors.SensorConfig` (e.g. ``duration=5.0``,
``field_dip=69.0``, ``mag_noise_ut=0.3``).

Each trial draws from four independent random streams (motion, magnet,
Earth field, sensor) spawned from ``numpy.random.SeedSequence(seed)``, so
changing e.g. a noise level does not change the motion.

Adding a scenario: write a config dataclass (subclass :class:`ScenarioConfig`)
and a planner ``(cfg, rngs) -> Plan``; add the config to ``SCENARIOS`` and the
planner to ``_PLANNERS`` (by config class).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from magenv import quaternion as quat
from magenv.checks import check_instance, check_intervals, check_numbers
from magenv.scenarios.world import STATIONARY_RATE, World, check_shared_fields, limited, simulated_trial
from magenv.sim import base_paths, earth, indoor, profiles
from magenv.sim.gimbal import PHYSICS_RATE, Tube, gimbal_blocks
from magenv.sim.hand import Approach, hand_path
from magenv.sim.magnet import DiscMagnet, dipole_field
from magenv.sim.rowops import norms, to_sensor
from magenv.sim.sensors import SensorConfig, SensorStream
from magenv.trial import Trial

#: A sample counts as stationary when the gimbal turns slower than ``STATIONARY_RATE`` (rad/s) and its sensor
#: moves slower than this, m/s.
STATIONARY_SPEED = 1e-3


# ------------------------------------------------------------------ configs


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """Parameters every gimbal scenario has.

    Attributes:
        duration: trial length, s.
        rate: sensor sample rate, Hz (paper: 256).
        physics_rate: MuJoCo step rate, Hz (see ``magenv.sim.gimbal``).
        field_norm: undisturbed Earth field magnitude m0, µT (paper: 46).
        field_dip: undisturbed dip angle θ0, degrees, positive down (paper: 49.6).
        sensor: MIMU error model.
    """

    duration: float = limited(60.0, 0.0, 3600.0, lo_open=True)
    rate: float = limited(256.0, 1.0, 10000.0)
    physics_rate: float = limited(PHYSICS_RATE, 100.0, 20000.0)
    field_norm: float = earth.PAPER[0]
    field_dip: float = earth.PAPER[1]
    sensor: SensorConfig = SensorConfig()

    def __post_init__(self) -> None:
        check_shared_fields(self)


@dataclasses.dataclass(frozen=True)
class StationaryMagnetConfig(ScenarioConfig):
    """Protocol 1 (§3.1). Approach times are jittered by ±``jitter_s`` per seed.

    Attributes:
        approaches: (start s, hold s) of each approach (Figure 8: A, B, C short, D ~60 s).
        far, near: magnet height above the MIMU, m (paper: 0.70 → 0.10).
        travel: duration of each descent and rise, s.
        jitter_s: random shift of each approach start, s.
        magnet: the hand-held disc magnet.
        max_tilt_deg: the still gimbal's random roll/pitch, degrees.
    """

    duration: float = 110.0
    approaches: tuple = ((10.0, 4.0), (21.0, 4.0), (32.0, 4.0), (44.0, 60.0))
    far: float = limited(0.70, "near", 5.0)
    near: float = limited(0.10, 0.01, 5.0)
    travel: float = limited(2.0, 0.0, 60.0, lo_open=True)
    jitter_s: float = limited(1.0, 0.0, 60.0)
    magnet: DiscMagnet = DiscMagnet()
    max_tilt_deg: float = limited(5.0, 0.0, 80.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_intervals("approaches", self.approaches)


@dataclasses.dataclass(frozen=True)
class DynamicCleanConfig(ScenarioConfig):
    """Protocol 2 (§3.2): intermittent slow rotations, no magnet.

    Attributes:
        start_rest: initial rest, s (filters converge).
        pause_s, move_s: ranges of pause and move durations, s.
        amplitude_deg: range of each frame's turn per move, degrees.
    """

    duration: float = 70.0
    start_rest: float = limited(5.0, 0.0, 3600.0)
    pause_s: tuple = limited((1.5, 5.0), 0.0)
    move_s: tuple = limited((1.5, 4.0), 0.05)
    amplitude_deg: tuple = limited((10.0, 60.0), 0.0, 720.0)


@dataclasses.dataclass(frozen=True)
class DynamicMagnetConfig(ScenarioConfig):
    """Protocol 3 (§3.3): all frames spin, the magnet slides in its tube.

    Attributes:
        rates_dps: nominal rates of frames Z, Y, X, °/s (paper: 40, 70, 360).
        rate_jitter: relative random deviation of each rate per seed.
        start_rest: the gimbal holds still at a fixed orientation first, s.
        ramp: spin-up and spin-down time, s.
        end_rest: rest at the end, s.
        tube: the disturbance generator.
    """

    rates_dps: tuple = (40.0, 70.0, 360.0)
    rate_jitter: float = limited(0.1, 0.0, 0.9)
    start_rest: float = limited(3.0, 0.0, 3600.0)
    ramp: float = limited(0.5, 0.01, 60.0)
    end_rest: float = limited(1.0, 0.0, 3600.0)
    tube: Tube = Tube()

    def __post_init__(self) -> None:
        super().__post_init__()
        check_numbers("rates_dps", self.rates_dps, 3, -2000.0, 2000.0, "rates (Z, Y, X) in °/s")
        check_instance("tube", self.tube, Tube)


@dataclasses.dataclass(frozen=True)
class RandomConfig(ScenarioConfig):
    """The training family. Every range is sampled uniformly per seed.

    Attributes:
        magnet_probs: probabilities of (no magnet, tube magnet, hand-held magnet).
        remanence_t: magnet remanence Br, T.
        diameter_m: disc diameter, m (thickness scales with it, paper 15:2).
        tube_x_m: |distance| along x from the sensor to the tube's near end, m
            (either side); tube_yz_m: lateral offset of the tube (y and z), m;
        tube_length_m: travel of the magnet, m.
        near_m: closest height of a hand-held magnet, m (it starts at 0.7 m).
        field_norm_ut, field_dip_deg: Earth field by location (overrides
            ``field_norm``/``field_dip``, which are ignored here).
        noise_scale: factor on all white-noise levels of ``sensor``.
        pause_s, move_s, amplitude_deg: intermittent moves as in protocol 2.
        spin_prob: probability that a motion segment is a spin (protocol 3 like).
        spin_dps: range of |rate| of each spinning frame, °/s.
        spin_s: duration of a spin segment, s.
        start_rest: initial rest, s.
    """

    magnet_probs: tuple = (0.3, 0.5, 0.2)
    remanence_t: tuple = limited((1.0, 1.4), 0.0, 2.0)
    diameter_m: tuple = limited((0.008, 0.02), 0.001, 0.1)
    tube_x_m: tuple = limited((0.035, 0.08), 0.015, 0.5)
    tube_yz_m: tuple = limited((-0.03, 0.03), -0.5, 0.5)
    tube_length_m: tuple = limited((0.05, 0.12), 0.005, 0.5)
    near_m: tuple = limited((0.06, 0.2), 0.02, 0.7)
    field_norm_ut: tuple = limited(earth.NORM_RANGE_UT, 1.0, 1000.0)
    field_dip_deg: tuple = limited(earth.DIP_RANGE_DEG, -90.0, 90.0)
    noise_scale: tuple = limited((0.5, 2.0), 0.0, 100.0)
    pause_s: tuple = limited((0.5, 6.0), 0.0)
    move_s: tuple = limited((0.5, 4.0), 0.05)
    amplitude_deg: tuple = limited((10.0, 180.0), 0.0, 720.0)
    spin_prob: float = limited(0.3, 0.0, 1.0)
    spin_dps: tuple = limited((20.0, 400.0), 0.0, 2000.0)
    spin_s: tuple = limited((3.0, 15.0), 1.5)
    start_rest: float = limited(3.0, 0.0, 3600.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        p = self.magnet_probs
        if len(p) != 3 or min(p) < 0 or not math.isclose(sum(p), 1.0, abs_tol=1e-9):
            raise ValueError(f"magnet_probs must be 3 probabilities (none, tube, hand) summing to 1, got {p!r}")


@dataclasses.dataclass(frozen=True)
class ManualRoutinesConfig(ScenarioConfig):
    """Survey: short manual tasks with 2 s pauses and one ~10 s reach to a small magnet.

    Attributes:
        start_rest: initial rest, s.
        pause: rest between tasks, s.
        task_s: duration range of one task (a smooth turn of 1–3 frames), s.
        amplitude_deg: range of each frame's turn per task, degrees.
        reach_at: when the reach starts, as a fraction range of the duration.
        reach_travel: time to move to the magnet (and back), s.
        reach_hold: time spent at the magnet, s.
        reach_distance_m: how far the base travels for the reach, m.
        near_m: distance from sensor to magnet at the reach, m (approximate:
            the sensor sits 5 mm from the gimbal centre).
        magnet: the small magnet (default Ø6 × 3 mm, Br 1.3 T: 0.09 A·m²).
    """

    duration: float = 60.0
    start_rest: float = limited(3.0, 0.0, 3600.0)
    pause: float = limited(2.0, 0.0, 3600.0)
    task_s: tuple = limited((1.0, 3.0), 0.1)
    amplitude_deg: tuple = limited((15.0, 90.0), 0.0, 720.0)
    reach_at: tuple = limited((0.3, 0.55), 0.0, 1.0)
    reach_travel: float = limited(1.5, 0.1, 60.0)
    reach_hold: float = limited(10.0, 0.0, 3600.0)
    reach_distance_m: float = limited(0.35, 0.05, 5.0)
    near_m: tuple = limited((0.03, 0.05), 0.015, "reach_distance_m")
    magnet: DiscMagnet = DiscMagnet(diameter=0.006, thickness=0.003, remanence=1.3)


@dataclasses.dataclass(frozen=True)
class GaitFieldConfig(ScenarioConfig):
    """Survey: continuous motion on a walking base through a spatially varying field.

    Attributes:
        half_length, half_width: figure-eight extent, m.
        period_s: time for one figure-eight, s (range).
        step_hz: gait step frequency, Hz (range); bounce_m, sway_m: vertical
            bob and sideways sway of the base, m.
        n_sources: number of distant field sources (range, inclusive).
        source_distance_m: horizontal distance of the sources from the
            centre of the path, m (range).
        source_field_ut: each source's field at the centre of the path, µT (range).
        pitch_deg, roll_deg: amplitude of the continuous sway of frames Y and X, degrees (range).
    """

    duration: float = 180.0
    half_length: float = limited(1.5, 0.0, 50.0)
    half_width: float = limited(1.0, 0.0, 50.0)
    period_s: tuple = limited((14.0, 20.0), 1.0)
    step_hz: tuple = limited((1.6, 2.0), 0.0, 5.0)
    bounce_m: float = limited(0.02, 0.0, 0.2)
    sway_m: float = limited(0.02, 0.0, 0.5)
    n_sources: tuple = limited((3, 6), 0, 50)
    source_distance_m: tuple = limited((4.0, 6.0), 0.5, 100.0)
    source_field_ut: tuple = limited((1.0, 5.0), 0.0, 100.0)
    pitch_deg: tuple = limited((5.0, 20.0), 0.0, 80.0)
    roll_deg: tuple = limited((5.0, 25.0), 0.0, 180.0)


# ------------------------------------------------------------------ plans


@dataclasses.dataclass(eq=False)
class Plan:
    """What a planner decides for one trial, before simulation.

    Attributes:
        profile: gimbal drive profile on the physics grid.
        magnet: "none", "tube", "hand" or "world" (dipoles fixed in the world).
        tube: tube placement (simulated always; its field counts only if magnet == "tube").
        hand: for a hand-held magnet, a function t (N,) → (offset (N,3) world m, axis (N,3) world).
        moment: dipole moment magnitude, A·m² (0 without magnet).
        field: (norm µT, dip °) of the undisturbed Earth field.
        sensor: the sensor error model.
        meta: drawn values worth keeping (JSON-serialisable).
        base: optional (n, 6) base motion on the physics grid (mobile model).
        sources: for "world": (positions (k, 3) m, moments (k, 3) A·m²), world.
    """

    profile: profiles.DriveProfile
    magnet: str
    tube: Tube
    hand: Callable | None
    moment: float
    field: tuple[float, float]
    sensor: SensorConfig
    meta: dict
    base: np.ndarray | None = None
    sources: tuple | None = None


def _span(cfg: ScenarioConfig) -> float:
    """Length of the drive profile, s: the trial plus the steps the cubic resampling reads past its end."""
    return cfg.duration + 3.0 / cfg.physics_rate


def _random_tilt(rng: np.random.Generator, max_deg: float) -> tuple[float, float, float]:
    return (
        float(rng.uniform(-np.pi, np.pi)),
        float(np.deg2rad(rng.uniform(-max_deg, max_deg))),
        float(np.deg2rad(rng.uniform(-max_deg, max_deg))),
    )


def _plan_stationary_magnet(cfg: StationaryMagnetConfig, rngs) -> Plan:
    r_motion, r_magnet, _, _ = rngs
    prof = profiles.empty_profile(_span(cfg), cfg.physics_rate, _random_tilt(r_motion, cfg.max_tilt_deg))
    apps = [
        Approach(start=max(0.0, s + r_magnet.uniform(-cfg.jitter_s, cfg.jitter_s)), hold=h, travel=cfg.travel)
        for s, h in cfg.approaches
    ]
    path_rng_seed = int(r_magnet.integers(2**63))
    hand = lambda t: hand_path(t, apps, cfg.far, cfg.near, np.random.default_rng(path_rng_seed))
    meta: dict[str, Any] = {"approach_starts_s": [a.start for a in apps]}
    return Plan(prof, "hand", Tube(), hand, cfg.magnet.moment, (cfg.field_norm, cfg.field_dip), cfg.sensor, meta)


def _plan_dynamic_clean(cfg: DynamicCleanConfig, rngs) -> Plan:
    r_motion = rngs[0]
    prof = profiles.intermittent_moves(
        r_motion,
        _span(cfg),
        cfg.physics_rate,
        _random_tilt(r_motion, 10.0),
        cfg.pause_s,
        cfg.move_s,
        cfg.amplitude_deg,
        cfg.start_rest,
    )
    return Plan(prof, "none", Tube(), None, 0.0, (cfg.field_norm, cfg.field_dip), cfg.sensor, {})


def _plan_dynamic_magnet(cfg: DynamicMagnetConfig, rngs) -> Plan:
    r_motion = rngs[0]
    angle0 = (float(r_motion.uniform(-np.pi, np.pi)), 0.0, 0.0)  # fixed orientation at the start (§3.3)
    prof = profiles.empty_profile(_span(cfg), cfg.physics_rate, angle0)
    rates = [r * (1.0 + r_motion.uniform(-cfg.rate_jitter, cfg.rate_jitter)) for r in cfg.rates_dps]
    stop = max(cfg.start_rest + 2 * cfg.ramp, cfg.duration - cfg.end_rest)
    for axis, r in enumerate(rates):
        profiles.add_spin(prof, axis, cfg.start_rest, stop, np.deg2rad(r), cfg.ramp)
    meta = {"rates_dps": [float(r) for r in rates]}
    return Plan(prof, "tube", cfg.tube, None, cfg.tube.magnet.moment, (cfg.field_norm, cfg.field_dip), cfg.sensor, meta)


def _pitch_at(prof: profiles.DriveProfile, t: float) -> float:
    """Commanded frame-Y angle (rad) at time t (sum of the rates so far)."""
    return float(prof.angle0[1] + np.sum(prof.omega[: int(t * prof.rate), 1]) / prof.rate)


def _turn_frames(prof, rng: np.random.Generator, t: float, length: float, amplitude_deg: tuple) -> None:
    """Turn 1–3 distinct random frames over [t, t + length] s, each by a random ±``amplitude_deg`` range °
    (pitch clipped to ±70°, :func:`_bounded_pitch_move`)."""
    for axis in rng.choice(3, size=int(rng.integers(1, 4)), replace=False):
        amp = np.deg2rad(rng.uniform(*amplitude_deg)) * rng.choice((-1.0, 1.0))
        if axis == 1:
            _bounded_pitch_move(prof, t, length, float(np.clip(amp, -np.deg2rad(70), np.deg2rad(70))))
        else:
            profiles.add_move(prof, int(axis), t, length, amp)


def _bounded_pitch_move(prof, t: float, length: float, amp: float, limit: float = np.deg2rad(80.0)) -> float:
    """A frame-Y move that keeps the pitch within ±limit (flips or shrinks ``amp``)."""
    p = _pitch_at(prof, t)
    if abs(p + amp) > limit:
        amp = -amp
    amp = float(np.clip(p + amp, -limit, limit) - p)
    profiles.add_move(prof, 1, t, length, amp)
    return amp


def _random_profile(cfg: RandomConfig, rng: np.random.Generator) -> profiles.DriveProfile:
    """Segments of pauses, smooth multi-axis moves and spins (protocols 2 and 3 mixed).

    Frame Y never spins: it sways back and forth (so a tube magnet
    reciprocates, §2.5.3) and its angle stays within ±80° so the ZYX Euler
    angles stay meaningful.
    """
    prof = profiles.empty_profile(_span(cfg), cfg.physics_rate, _random_tilt(rng, 20.0))
    t, end = cfg.start_rest, cfg.duration - 0.5
    while t < end:
        if rng.uniform() < cfg.spin_prob:
            length = min(rng.uniform(*cfg.spin_s), end - t)
            if length >= 1.5:
                ramp = min(0.5, length / 3)
                for axis in (0, 2):
                    if rng.uniform() < 0.8:
                        w = np.deg2rad(rng.uniform(*cfg.spin_dps)) * rng.choice((-1.0, 1.0))
                        profiles.add_spin(prof, axis, t, t + length, w, ramp)
                k = 2 * max(1, int(length // rng.uniform(3.0, 8.0)))  # even: back where it started
                amp = np.deg2rad(rng.uniform(20.0, 70.0)) * rng.choice((-1.0, 1.0))
                for j in range(0, k, 2):  # out by a, back by −a
                    a = _bounded_pitch_move(prof, t + j * length / k, length / k, amp)
                    profiles.add_move(prof, 1, t + (j + 1) * length / k, length / k, -a)
        else:
            length = min(rng.uniform(*cfg.move_s), end - t)
            if length >= cfg.move_s[0]:
                _turn_frames(prof, rng, t, length, cfg.amplitude_deg)
        t += length + rng.uniform(*cfg.pause_s)
    return prof


def _plan_random(cfg: RandomConfig, rngs) -> Plan:
    r_motion, r_magnet, r_field, r_sensor = rngs
    prof = _random_profile(cfg, r_motion)
    kind = ("none", "tube", "hand")[int(r_magnet.choice(3, p=cfg.magnet_probs))]
    diameter = float(r_magnet.uniform(*cfg.diameter_m))
    magnet = DiscMagnet(
        diameter=diameter, thickness=diameter * 2 / 15, remanence=float(r_magnet.uniform(*cfg.remanence_t))
    )
    side = float(r_magnet.choice((-1.0, 1.0)))
    length = float(r_magnet.uniform(*cfg.tube_length_m))
    x_near = float(r_magnet.uniform(*cfg.tube_x_m))
    start = (
        x_near if side > 0 else -x_near - length,
        float(r_magnet.uniform(*cfg.tube_yz_m)),
        0.005 + float(r_magnet.uniform(*cfg.tube_yz_m)),
    )
    dip_dir = r_magnet.normal(size=3)
    dip_dir[0] = 0.0  # the disc stands on edge in the tube: moment across the tube
    if np.linalg.norm(dip_dir) < 1e-6:
        dip_dir = np.array([0.0, 0.0, 1.0])
    unit = dip_dir / np.linalg.norm(dip_dir)
    tube = Tube(
        start=start,
        length=length,
        dipole=(float(unit[0]), float(unit[1]), float(unit[2])),
        friction=float(r_magnet.uniform(0.3, 1.5) * 0.3 * magnet.mass * 9.81),
        magnet=magnet,
        start_at=float(r_magnet.uniform()),
    )
    hand = None
    meta: dict[str, Any] = {"magnet": kind}
    if kind == "hand":
        near = float(r_magnet.uniform(*cfg.near_m))
        apps, t = [], float(r_magnet.uniform(2.0, 15.0))
        while t < cfg.duration - 4.0:
            hold = float(r_magnet.uniform(1.0, 20.0))
            apps.append(Approach(t, hold, travel=float(r_magnet.uniform(1.0, 3.0))))
            t += hold + 6.0 + float(r_magnet.uniform(2.0, 20.0))
        seed = int(r_magnet.integers(2**63))
        hand = lambda tt: hand_path(tt, apps, 0.7, near, np.random.default_rng(seed))
        meta.update(near_m=near, approach_starts_s=[a.start for a in apps])
    if kind != "none":
        meta.update(remanence_t=magnet.remanence, diameter_m=diameter)
    if kind == "tube":
        meta.update(tube_start_m=list(start), tube_length_m=length, tube_dipole=list(tube.dipole))
    field = earth.random_location(r_field, cfg.field_norm_ut, cfg.field_dip_deg)
    scale = float(r_sensor.uniform(*cfg.noise_scale))
    meta.update(noise_scale=scale)
    moment = magnet.moment if kind != "none" else 0.0
    return Plan(prof, kind, tube, hand, moment, field, cfg.sensor.scaled(scale), meta)


def _plan_manual_routines(cfg: ManualRoutinesConfig, rngs) -> Plan:
    r_motion, r_magnet, _, _ = rngs
    prof = profiles.empty_profile(_span(cfg), cfg.physics_rate, _random_tilt(r_motion, 10.0))
    reach_start = float(r_motion.uniform(*cfg.reach_at) * cfg.duration)
    reach_len = 2 * cfg.reach_travel + cfg.reach_hold
    t, reached = cfg.start_rest, False
    while t < cfg.duration - 1.0:
        if not reached and t >= reach_start:
            reach_start, reached = t, True
            t += reach_len + cfg.pause
            continue
        length = float(r_motion.uniform(*cfg.task_s))
        if t + length > cfg.duration - 0.5:
            break
        _turn_frames(prof, r_motion, t, length, cfg.amplitude_deg)
        t += length + cfg.pause
    if not reached:  # the tasks ended before reach_at: reach at the end instead
        reach_start = max(cfg.start_rest, cfg.duration - reach_len - 1.0)
    # The magnet lies at the sensor's initial height, reach_distance_m away at a random bearing.
    bearing = float(r_magnet.uniform(0, 2 * np.pi))
    u = np.array([np.cos(bearing), np.sin(bearing), 0.0])
    near = float(r_magnet.uniform(*cfg.near_m))
    p_sensor0 = quat.rotate(quat.from_euler_zyx(*prof.angle0), np.array([0.0, 0.0, 0.005]))
    p_magnet = p_sensor0 + cfg.reach_distance_m * u
    axis = r_magnet.normal(size=3)
    axis /= np.linalg.norm(axis)
    t_phys = np.arange(prof.n) / prof.rate
    base = base_paths.reach(
        t_phys, reach_start, cfg.reach_travel, cfg.reach_hold, (cfg.reach_distance_m - near) * u, r_magnet
    )
    meta = {
        "reach_start_s": reach_start,
        "near_m": near,
        "magnet_position_m": list(p_magnet),
        "magnet_axis": list(axis),
    }
    return Plan(
        prof,
        "world",
        Tube(),
        None,
        cfg.magnet.moment,
        (cfg.field_norm, cfg.field_dip),
        cfg.sensor,
        meta,
        base=base,
        sources=(p_magnet[None], (cfg.magnet.moment * axis)[None]),
    )


def _plan_gait_field(cfg: GaitFieldConfig, rngs) -> Plan:
    r_motion, r_magnet, _, _ = rngs
    n = int(round(_span(cfg) * cfg.physics_rate))
    t = np.arange(n) / cfg.physics_rate
    step_hz = float(r_motion.uniform(*cfg.step_hz))
    base = base_paths.figure_eight(
        t, cfg.half_length, cfg.half_width, float(r_motion.uniform(*cfg.period_s)), cfg.bounce_m, step_hz, cfg.sway_m
    )
    psi, psi_rate = base_paths.heading(base, cfg.physics_rate)
    prof = profiles.DriveProfile(rate=cfg.physics_rate, omega=np.zeros((n, 3)), angle0=np.array([psi[0], 0.0, 0.0]))
    prof.omega[:, 0] = psi_rate
    # Frames Y and X sway continuously: two sinusoids each, one at the gait's
    # half step frequency (arm/trunk swing), one slow; zero mean, bounded angles.
    env, warped = base_paths.start_envelope(t, 2.0)  # start from rest, like the walk
    for axis, amp_range in ((1, cfg.pitch_deg), (2, cfg.roll_deg)):
        for f in (0.5 * step_hz, float(r_motion.uniform(0.05, 0.3))):
            amp = np.deg2rad(r_motion.uniform(*amp_range)) / 2
            ph = float(r_motion.uniform(0, 2 * np.pi))
            # angle = amp·(sin(2πfφ + ph) − sin ph), φ the warped time: starts at 0, at rest.
            prof.omega[:, axis] += amp * 2 * np.pi * f * np.cos(2 * np.pi * f * warped + ph) * env
    k = int(r_magnet.integers(cfg.n_sources[0], cfg.n_sources[1] + 1))
    pos, mom = indoor.random_sources(r_magnet, k, cfg.source_distance_m, cfg.source_field_ut)
    meta = {"step_hz": step_hz, "source_positions_m": pos.tolist(), "source_moments_am2": mom.tolist()}
    return Plan(
        prof,
        "world",
        Tube(),
        None,
        float(np.abs(mom).sum()),
        (cfg.field_norm, cfg.field_dip),
        cfg.sensor,
        meta,
        base=base,
        sources=(pos, mom),
    )


def _simulate(scenario: str, cfg: ScenarioConfig, seed: int, rngs: list[np.random.Generator]) -> Trial:
    """Plan the trial, run the gimbal, add the fields (paper §2.5.3) and the sensor model (``rngs``: motion,
    magnet, Earth field, sensor).

    Block by block of the run (``magenv.sim.gimbal.gimbal_blocks``), into the trial's own arrays: a long
    trial's memory is its arrays (the truth channels for display only, joint angles, magnet slide and
    distance, in float32), not the simulation's; the numbers are those of one block."""
    plan = _PLANNERS[type(cfg)](cfg, rngs)
    n = int(round(cfg.duration * cfg.rate))
    earth_field = quat.earth_field(*plan.field)
    hand = plan.hand(np.arange(n) / cfg.rate) if plan.magnet == "hand" else None
    sensor = SensorStream(n, cfg.rate, plan.sensor, rngs[3])
    gyr, acc, mag, q, b_mag = (np.empty((n, c)) for c in (3, 3, 3, 4, 3))
    dist, slide = np.empty(n, np.float32), np.empty(n, np.float32)
    joints, stationary = np.empty((n, 3), np.float32), np.empty(n, bool)
    last_p = None  # the sensor's position at the sample before the block
    steps = 0
    for i0, run in gimbal_blocks(plan.profile, plan.tube, cfg.rate, n, base=plan.base):
        rows = slice(i0, i0 + len(run.q))
        b_earth = to_sensor(run.q, np.broadcast_to(earth_field, run.gyr.shape))
        if plan.magnet == "tube":
            b_mag[rows] = dipole_field(-run.p_magnet, plan.moment * run.m_axis)
            dist[rows] = norms(run.p_magnet)
        elif plan.magnet == "hand":
            assert hand is not None
            offset, axis = hand[0][rows], hand[1][rows]
            b_mag[rows] = to_sensor(run.q, dipole_field(-offset, plan.moment * axis))
            dist[rows] = norms(offset)
        elif plan.magnet == "world":
            pos, mom = plan.sources
            b_mag[rows] = to_sensor(run.q, indoor.sources_field(run.p_imu, pos, mom))
            dist[rows] = indoor.nearest_distance(run.p_imu, pos)
        else:
            b_mag[rows] = 0.0
            dist[rows] = np.inf
        gyr[rows], acc[rows], mag[rows] = sensor.measure(run.gyr, run.acc, b_earth + b_mag[rows])
        # At rest: not turning and (on a moving base) not travelling.
        step = np.diff(run.p_imu, axis=0, prepend=run.p_imu[:1] if last_p is None else last_p)
        stationary[rows] = (norms(run.gyr) < STATIONARY_RATE) & (norms(step) * cfg.rate < STATIONARY_SPEED)
        q[rows], joints[rows], slide[rows] = run.q, run.joints, run.slide
        last_p, steps = run.p_imu[-1:], run.physics_steps
    truth = {
        "mag_disturbance": b_mag,
        "stationary": stationary,
        "magnet_distance": dist,
        "joint_angles": joints,
        "magnet_slide": slide,
    }
    drawn = {"magnet": plan.magnet, "moment_am2": float(plan.moment), "physics_steps": steps, **plan.meta}
    return simulated_trial(scenario, seed, cfg, (gyr, acc, mag), q, plan.field, truth, drawn)


# ------------------------------------------------------------------ the world

#: The gimbal's scenarios: name → default config.
SCENARIOS: dict[str, ScenarioConfig] = {
    "stationary_magnet": StationaryMagnetConfig(),
    "dynamic_clean": DynamicCleanConfig(),
    "dynamic_magnet": DynamicMagnetConfig(),
    "random": RandomConfig(),
    # Survey scenarios (issue 4, item 7).
    "manual_routines": ManualRoutinesConfig(),
    "gait_field": GaitFieldConfig(),
}

#: The planner of each config class: (cfg, rngs) → Plan.
_PLANNERS: dict[type, Callable] = {
    StationaryMagnetConfig: _plan_stationary_magnet,
    DynamicCleanConfig: _plan_dynamic_clean,
    DynamicMagnetConfig: _plan_dynamic_magnet,
    RandomConfig: _plan_random,
    ManualRoutinesConfig: _plan_manual_routines,
    GaitFieldConfig: _plan_gait_field,
}

WORLD = World("gimbal", "gimbal", SCENARIOS, _simulate, n_streams=4)
