"""The hand-held world (Combettes & Renaudin 2016 §5.2): a walker's hand-held MIMU in a static indoor field;
configs and simulation.

Scenarios, all at 100 Hz (the paper's ADIS-16488 rate):

* ``handheld_texting`` — device held steady in front, walking at 5 km/h, 120 s;
* ``handheld_swinging`` — device in the swinging hand, 5 km/h, 120 s;
* ``handheld_free`` — 13 min (780 s) of mixed carrying modes (texting,
  swinging, phoning, irregular), speed 1–1.7 m/s, as the unsupervised walk;
* ``handheld_corridor`` — texting while travelling a figure-eight (6 × 3 m)
  through the field at 5 km/h, 120 s;
* ``handheld_random`` — the training family: random modes, speed, field
  sources, Earth field location and sensor noise, treadmill or travelling
  (probability ½ each), 60 s.

The paper's subjects walked on a treadmill in a 9 m² motion lab (§5.1), so
the three paper scenarios walk in place (``treadmill_prob=1``): the field at
the sensor then changes only with the hand's motion relative to the body
(Fig. 8), and is otherwise steady though far from the Earth field (Fig. 4).
``handheld_corridor`` (and half of ``handheld_random``) travel through the
spatially varying field instead, where a quasi-static reference also goes
stale from the walk itself. Truth channels:
``mag_disturbance`` (N, 3) µT sensor frame (field − Earth field),
``position`` (N, 3) m ENU, ``mode`` (N,) index into ``magenv.sim.handheld.MODES``,
``stationary`` (N,) bool (never, the walker does not stop). The walk
starts inside the disturbed field, so, as in the paper (§5.3), the trial
gives the QSF filters their true initial orientation: ``meta["start_from_truth"]``
(``magenv.filters.qsf.initial_orientation``, their ``init="auto"``); the
other worlds' methods start from their own e-compass as everywhere.

A name + a seed → the same Trial bit for bit: four independent random
streams (motion, field, Earth location, sensor) are spawned from
``numpy.random.SeedSequence(seed)``.

The sensor is smartphone-grade (``HANDHELD_SENSOR``: gyro bias 0.3 °/s per
axis, much worse than the paper's ADIS-16488), so that the magnetometer
matters for heading, which is the paper's setting of interest; the
magnetometer has no lag or sample-and-hold (those are properties of the BROAD
unit, kept in the shared ``SensorConfig`` defaults).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magenv import quaternion as quat
from magenv.checks import check_number
from magenv.scenarios.world import World, check_shared_fields, limited, simulated_trial
from magenv.sim import earth
from magenv.sim.handheld import MODES, Motion, ideal_readings
from magenv.sim.indoor_field import random_indoor_field
from magenv.sim.sensors import SensorConfig, apply_sensor_model
from magenv.trial import START_FROM_TRUTH, Trial

#: Nantes (IFSTTAR, the paper's lab), approximate IGRF values: 47 µT, dip 61°.
NANTES = (47.0, 61.0)

HANDHELD_SENSOR = SensorConfig(
    gyr_noise_dps=0.1,
    gyr_bias_dps=0.3,
    gyr_drift_dps=0.01,
    acc_noise=0.03,
    acc_bias=0.05,
    mag_noise_ut=0.3,
    mag_hard_iron_ut=0.5,
    mag_soft_iron=0.005,
    mag_noise_taps=1,
    gyr_lag_samples=0,
    mag_lag_samples=0,
    mag_hold_fraction=0.0,
)


@dataclasses.dataclass(frozen=True)
class HandheldConfig:
    """A hand-held walking scenario. Ranges are (low, high), drawn uniformly per seed.

    Attributes:
        duration: s. rate: Hz.
        modes: carrying modes (``magenv.sim.handheld.MODES``); one mode → one segment.
        segment_s: duration of each mode segment, s (mixed modes only).
        transition_s: hand-over between segments, s.
        speed_mps: walking speed, m/s (5 km/h = 1.39; unused on the treadmill). step_hz: step frequency, Hz.
        path_m: long half extent a of the figure-eight, m (the short one is a/2).
        treadmill_prob: probability that the walker walks in place (the paper's treadmill, §5.1)
            rather than travelling the figure-eight through the field.
        n_dipoles, dipole_ut, dipole_distance_m: number of ferrous sources, the field of each at the
            nearest point of the walk (µT), and their distance from the walk (m, ≥ 1).
        n_wires, wire_current_a: ceiling wires (2.7 m) and their DC current, A.
        field_norm, field_dip: Earth field, µT and ° down (ignored if ``random_location``).
        random_location: draw the Earth field from ``magenv.sim.earth`` ranges.
        noise_scale: factor on the white-noise levels of ``sensor``.
        sensor: the MIMU error model.
    """

    duration: float = limited(120.0, 0.0, 7200.0, lo_open=True)
    rate: float = limited(100.0, 1.0, 10000.0)
    modes: tuple = ("texting",)
    segment_s: tuple = limited((20.0, 60.0), 1.0)
    transition_s: float = 1.5
    speed_mps: tuple = limited((1.39, 1.39), 0.0, 3.0)
    step_hz: tuple = limited((1.7, 2.0), 0.5, 4.0)
    path_m: tuple = limited((6.0, 6.0), 0.5, 100.0)
    treadmill_prob: float = limited(1.0, 0.0, 1.0)
    n_dipoles: tuple = limited((3, 6), 0, 50)
    dipole_ut: tuple = limited((1.0, 6.0), 0.0, 500.0)
    dipole_distance_m: tuple = limited((1.5, 4.0), 0.3, 50.0)
    n_wires: tuple = limited((0, 2), 0, 20)
    wire_current_a: tuple = limited((1.0, 15.0), 0.0, 1000.0)
    field_norm: float = NANTES[0]
    field_dip: float = NANTES[1]
    random_location: bool = False
    noise_scale: tuple = limited((1.0, 1.0), 0.0, 100.0)
    sensor: SensorConfig = HANDHELD_SENSOR

    def __post_init__(self) -> None:
        check_shared_fields(self)
        if not self.modes or any(m not in MODES for m in self.modes):
            raise ValueError(f"modes must be a non-empty tuple of {MODES}, got {self.modes!r}")
        check_number("transition_s", self.transition_s, 0.0, self.segment_s[0])


def _simulate(scenario: str, cfg: HandheldConfig, seed: int, rngs: list[np.random.Generator]) -> Trial:
    """Walk, place the field's sources, read the ideal sensor and add its errors (``rngs``: motion, field,
    Earth location, sensor)."""
    r_motion, r_field, r_loc, r_sensor = rngs
    n = int(round(cfg.duration * cfg.rate))
    t = np.arange(n) / cfg.rate
    motion = Motion(
        r_motion,
        cfg.modes,
        cfg.duration,
        cfg.segment_s,
        cfg.transition_s,
        speed=r_motion.uniform(*cfg.speed_mps),
        step_hz=r_motion.uniform(*cfg.step_hz),
        path_m=(a := r_motion.uniform(*cfg.path_m), 0.5 * a),
        travel=bool(r_motion.uniform() >= cfg.treadmill_prob),
    )
    if cfg.random_location:
        norm, dip = earth.random_location(r_loc)
    else:
        norm, dip = cfg.field_norm, cfg.field_dip
    b_earth = quat.earth_field(norm, dip)
    # the field's sources are placed around the region the sensor visits (sampled every 0.1 s)
    p_visit, _ = motion.pose(t[:: max(1, int(cfg.rate // 10))])
    field = random_indoor_field(
        r_field, b_earth, p_visit, cfg.n_dipoles, cfg.dipole_ut, cfg.dipole_distance_m, cfg.n_wires, cfg.wire_current_a
    )
    p, q, gyr, acc, mag, b_e = ideal_readings(motion, t, field)
    scale = float(r_sensor.uniform(*cfg.noise_scale))
    gyr_m, acc_m, mag_m = apply_sensor_model(gyr, acc, mag, cfg.rate, cfg.sensor.scaled(scale), r_sensor)
    truth = {
        "mag_disturbance": quat.rotate_inv(q, b_e - b_earth),
        "position": p,
        "mode": motion.mode_index(t),
        "stationary": np.zeros(n, bool),
    }
    drawn = {
        "modes": motion.mode_names,
        START_FROM_TRUTH: True,
        "mode_bounds_s": motion.bounds,
        "speed_mps": motion.speed,
        "step_hz": motion.f_step,
        "treadmill": not motion.travel,
        "noise_scale": scale,
        "n_dipoles": len(field.dipole_pos),
        "n_wires": len(field.wire_point),
        "min_source_distance_m": field.min_source_distance(p_visit),
    }
    return simulated_trial(scenario, seed, cfg, (gyr_m, acc_m, mag_m), q, (norm, dip), truth, drawn)


#: The hand-held scenarios: name → default config.
SCENARIOS: dict[str, HandheldConfig] = {
    "handheld_texting": HandheldConfig(modes=("texting",)),
    "handheld_swinging": HandheldConfig(modes=("swinging",)),
    "handheld_free": HandheldConfig(duration=780.0, modes=MODES, speed_mps=(1.0, 1.7), segment_s=(20.0, 90.0)),
    "handheld_corridor": HandheldConfig(modes=("texting",), treadmill_prob=0.0),
    "handheld_random": HandheldConfig(
        duration=60.0,
        modes=MODES,
        segment_s=(8.0, 40.0),
        speed_mps=(0.8, 1.8),
        step_hz=(1.5, 2.2),
        path_m=(3.0, 8.0),
        n_dipoles=(0, 8),
        dipole_ut=(1.0, 25.0),
        n_wires=(0, 3),
        random_location=True,
        noise_scale=(0.5, 2.0),
        treadmill_prob=0.5,
    ),
}

WORLD = World("handheld", "hand-held", SCENARIOS, _simulate, n_streams=4)
