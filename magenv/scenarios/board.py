"""The board world: a sensor board moved by hand in a room, as in the BROAD recordings — randomised wide, to
train trust policies that hold on real sensors they have never seen.

Every trial draws its motion, its disturbance and its sensor from ranges wider than the BROAD recordings
span (Laidig et al. 2021; their fits: ``magenv.scenarios.twin_fit``), so that no training trial copies a
recording and a policy cannot key on one sensor's or one room's particulars. Scenarios (a disturbance
family each; ``board_random`` draws one of the five per trial):

* ``board_clean`` — no disturbance;
* ``board_attached`` — a magnet or a piece of iron fixed to the board from 10 s before to 40 s after the motion
  starts, for 20–90 s (or to the end):
  a constant sensor-frame offset of 1.5–120 µT (hard iron; the recordings show 58 µT at 1 cm, 14 µT at 3 cm),
  mostly along one sensor axis, for the iron also a soft-iron part proportional to the field;
* ``board_stationary`` — one to three magnets lying in the room; the board is carried to 3–30 cm of one,
  held there 0–15 s and taken back, one to six times (moments 0.002–0.08 A·m²: the recordings' magnets
  0.005–0.04);
* ``board_office`` — a spatially varying indoor field (ferrous structures 0.3–1.5 m from the board's path,
  1–15 µT at their nearest, ceiling wires), and sometimes a magnet visited as above;
* ``board_shocks`` — tapping on the board (knocks of 5–60 m/s²) or a vibrating phone on it (90–250 Hz,
  1–15 m/s²) in bursts: the accelerometer disturbed, the field not;
* ``board_spinning`` — ``board_random`` with the board also spinning steadily while it moves (below).

Motion (``magenv.sim.board.hand_motion``): an initial rest (in half the trials 25–45 s, as every BROAD
recording rests its first 30–45 s, else 2–10 s), then 50–130 s of rotations, translations or both
(BROAD's motion classes), slow (RMS 10–35 °/s), medium (35–90 °/s) or fast (90–250 °/s, peaks near
800 °/s), with or without breaks (1–4 rests of 5–10 s). Sums of sines have no net rotation over a minute;
with probability ``spin_prob`` (``board_spinning``: always) the board also spins steadily at 20–200 °/s about
a sensor axis while it moves, as in the BROAD magnet recordings (43–181 °/s net about one axis), where the
gyro's scale and misalignment errors then drift VQF's unaided heading by 0.08–0.14 °/s.
Sensor: ``magenv.sim.sensors.SensorConfig`` drawn around the BROAD unit (gyro noise 0.05–0.3 °/s,
bias 0.05–0.6 °/s and drift, scale and misalignment errors of
up to 0.4 % per entry (the recordings' fits: 0.1–0.4 %, which at 400 °/s drift the heading by ~1 °/s),
accelerometer noise 0.02–0.12 m/s², magnetometer noise 0.2–1.5 µT white or coloured, residual hard iron
(0–0.8 µT per axis) and soft iron, gyro lag 0–2 and magnetometer lag 0–6 samples, sample-and-hold of 0–40 % in
runs of 1 or 2).
Earth field: Berlin's (44.5 µT, 69°, ±1.5) in half the trials, else a random location. Rate: BROAD's
285.7 Hz in 60 % of the trials, else 100–400 Hz.

As for a recording, the trial's undisturbed field (``Trial.field_norm``, ``field_dip``) is estimated from
its own initial rest (``magenv.recordings.estimate_field``, with the site's true field as the documented
fallback), and ``score_mask`` marks the samples after the initial rest (BROAD's ``movement``). Truth channels:
``mag_disturbance`` (N, 3) µT sensor frame (measured field − the Earth field, before the sensor's own
errors), ``position`` (N, 3) m ENU. Five independent streams (motion, disturbance, shocks, sensor, Earth
location) are spawned from ``numpy.random.SeedSequence(seed)``: the same seed gives the same Trial bit for bit.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from magenv import quaternion as quat
from magenv.recordings import estimate_field
from magenv.scenarios.world import World, check_limits, limited, trial_meta, trial_name
from magenv.sim import board, earth
from magenv.sim.indoor_field import IndoorField, random_indoor_field
from magenv.sim.sensors import SensorConfig, apply_sensor_model
from magenv.trial import Trial

FAMILIES = ("clean", "attached", "stationary", "office", "shocks")
MOTIONS = ("rotation", "translation", "combined")
SPEEDS = {"slow": (10.0, 35.0), "medium": (35.0, 90.0), "fast": (90.0, 250.0)}  # RMS rate while moving, °/s
BROAD_RATE = 2000.0 / 7.0  # Hz (285.714)


@dataclasses.dataclass(frozen=True)
class BoardConfig:
    """A board scenario (module docstring). Ranges are (low, high), drawn uniformly per seed.

    Attributes:
        duration: s of motion after the initial rest, a number or a range (drawn).
        family: one of ``FAMILIES``, or ``"random"`` (one per trial, uniformly).
        broad_rate_prob: probability of BROAD's rate; else ``rate`` (Hz, drawn).
        rest_s: initial rest, s; long_rest_prob, long_rest_s: the probability and length of a BROAD-like one
            (every recording rests its first 30–45 s). break_prob: probability of breaks; n_breaks, break_s: how
            many and how long.
        attached_ut: hard-iron offset of an attached magnet, µT (log-uniform). iron_prob: the attached object is
            iron (a soft-iron part too). attached_on_s: when it is attached, s after the motion starts;
            attached_for_s: how long it stays. attached_ramp_s: attaching / removing it, s. removed_prob:
            probability that it is removed before the end.
        magnets, visits: counts of room magnets and of visits to them. moment: A·m² (log-uniform).
            distance_m: closest approach (log-uniform). dwell_s, travel_s: held there, carried there.
        spin_prob, spin_dps: probability that the board also spins steadily while it moves, about a drawn
            sensor-frame axis near one of the sensor's axes, and that rate, °/s (either sense).
        berlin_prob: probability of the BROAD site's Earth field (else a random location).
        field_norm, field_dip: the BROAD site (µT, °).
    """

    duration: float | tuple = limited((50.0, 130.0), 1.0, 7200.0)
    family: str = "random"
    broad_rate_prob: float = limited(0.6, 0.0, 1.0)
    rate: tuple = limited((100.0, 400.0), 20.0, 2000.0)
    rest_s: tuple = limited((2.0, 10.0), 0.5, 60.0)
    long_rest_prob: float = limited(0.5, 0.0, 1.0)
    long_rest_s: tuple = limited((25.0, 45.0), 0.5, 600.0)
    break_prob: float = limited(0.5, 0.0, 1.0)
    n_breaks: tuple = limited((1, 4), 0, 20)
    break_s: tuple = limited((5.0, 10.0), 0.5, 60.0)
    attached_ut: tuple = limited((1.5, 120.0), 0.01, 1000.0)
    iron_prob: float = limited(0.3, 0.0, 1.0)
    attached_on_s: tuple = limited((-10.0, 40.0), -600.0, 3600.0)
    attached_for_s: tuple = limited((20.0, 90.0), 0.5, 3600.0)
    attached_ramp_s: tuple = limited((0.3, 3.0), 0.01, 30.0)
    removed_prob: float = limited(0.75, 0.0, 1.0)
    magnets: tuple = limited((1, 3), 1, 10)
    visits: tuple = limited((1, 6), 1, 50)
    moment: tuple = limited((0.002, 0.08), 1e-5, 10.0)
    distance_m: tuple = limited((0.03, 0.3), 0.005, 5.0)
    dwell_s: tuple = limited((0.0, 15.0), 0.0, 600.0)
    travel_s: tuple = limited((1.0, 4.0), 0.1, 60.0)
    spin_prob: float = limited(0.0, 0.0, 1.0)
    spin_dps: tuple = limited((20.0, 200.0), 0.0, 2000.0)
    berlin_prob: float = limited(0.5, 0.0, 1.0)
    field_norm: float = limited(earth.BERLIN[0], 1.0, 1000.0)
    field_dip: float = limited(earth.BERLIN[1], -90.0, 90.0)

    def __post_init__(self) -> None:
        check_limits(self)
        if self.family not in (*FAMILIES, "random"):
            raise ValueError(f"family must be one of {(*FAMILIES, 'random')}, got {self.family!r}")


def _log_uniform(rng, lo_hi) -> float:
    return float(np.exp(rng.uniform(np.log(lo_hi[0]), np.log(lo_hi[1]))))


def _breaks(rng, cfg: BoardConfig, rest_s: float, duration: float) -> list[tuple[float, float]]:
    """Rests of ``break_s`` at random times after the initial rest (none with probability 1 − break_prob)."""
    if rng.uniform() >= cfg.break_prob:
        return []
    k = int(rng.integers(cfg.n_breaks[0], cfg.n_breaks[1] + 1))
    starts = np.sort(rng.uniform(rest_s + 5.0, max(rest_s + 6.0, duration - 15.0), k))
    out: list[tuple[float, float]] = []
    for a in starts:
        if not out or a > out[-1][1] + 3.0:
            out.append((float(a), float(a + rng.uniform(*cfg.break_s))))
    return out


def _sensor(rng) -> SensorConfig:
    """A MIMU drawn around the BROAD unit (module docstring)."""
    held = rng.uniform() >= 0.3
    return SensorConfig(
        gyr_noise_dps=rng.uniform(0.05, 0.3),
        gyr_bias_dps=rng.uniform(0.05, 0.6),
        gyr_drift_dps=rng.uniform(0.0, 0.02),
        acc_noise=rng.uniform(0.02, 0.12),
        acc_bias=rng.uniform(0.0, 0.1),
        mag_noise_ut=rng.uniform(0.2, 1.5),
        mag_noise_taps=int(rng.choice((1, 3), p=(0.3, 0.7))),
        mag_hard_iron_ut=rng.uniform(0.0, 0.8),
        mag_soft_iron=rng.uniform(0.0, 0.02),
        gyr_lag_samples=int(rng.integers(0, 3)),
        mag_lag_samples=int(rng.integers(0, 7)),
        mag_hold_fraction=rng.uniform(0.1, 0.4) if held else 0.0,
        mag_hold_run=int(rng.integers(1, 3)),
    )


def _visits(rng, cfg: BoardConfig, magnets: np.ndarray, rest_s: float, duration: float) -> list:
    """Visits (start s, travel s, dwell s, target (3,) m) to the magnets at ``magnets`` (K, 3)."""
    k = int(rng.integers(cfg.visits[0], cfg.visits[1] + 1))
    out, t = [], rest_s + rng.uniform(3.0, 15.0)
    for _ in range(k):
        travel, dwell = rng.uniform(*cfg.travel_s), rng.uniform(*cfg.dwell_s)
        if t + 2 * travel + dwell > duration - 2.0:
            break
        m = magnets[int(rng.integers(len(magnets)))]
        d = -m / np.linalg.norm(m) + 0.5 * rng.normal(size=3)  # the near side: the board comes from the centre
        target = m + _log_uniform(rng, cfg.distance_m) * d / np.linalg.norm(d)
        out.append((t, travel, dwell, target))
        t += 2 * travel + dwell + rng.uniform(3.0, 20.0)
    return out


def _room_magnets(rng, cfg: BoardConfig) -> tuple[np.ndarray, np.ndarray]:
    """(positions (K, 3) m, moments (K, 3) A·m²) of magnets lying 0.3–1 m from the board's central position."""
    k = int(rng.integers(cfg.magnets[0], cfg.magnets[1] + 1))
    d = rng.normal(size=(k, 3))
    d[:, 2] *= 0.3  # about the height of the table
    pos = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (k, 1))
    m = rng.normal(size=(k, 3))
    mom = m / np.linalg.norm(m, axis=1, keepdims=True) * np.array([[_log_uniform(rng, cfg.moment)] for _ in range(k)])
    return pos, mom


def _simulate(scenario: str, cfg: BoardConfig, seed: int, rngs: list[np.random.Generator]) -> Trial:
    """Draw the motion (``rngs[0]``), then the room, the disturbance and the sensor (:func:`_dress`)."""
    r_mo = rngs[0]
    rate = BROAD_RATE if r_mo.uniform() < cfg.broad_rate_prob else float(round(r_mo.uniform(*cfg.rate)))
    span = (cfg.duration, cfg.duration) if isinstance(cfg.duration, (int, float)) else cfg.duration
    rest_s = float(r_mo.uniform(*(cfg.long_rest_s if r_mo.uniform() < cfg.long_rest_prob else cfg.rest_s)))
    duration = rest_s + float(r_mo.uniform(*span))
    n = int(round(duration * rate))
    t = np.arange(n) / rate
    breaks = _breaks(r_mo, cfg, rest_s, duration)
    motion = MOTIONS[int(r_mo.integers(len(MOTIONS)))]
    speed = ("slow", "medium", "fast")[int(r_mo.integers(3))]
    rot = r_mo.uniform(*SPEEDS[speed]) if motion != "translation" else r_mo.uniform(1.0, 5.0)
    fast = speed == "fast"
    trans = r_mo.uniform(0.05, 0.15) if motion != "rotation" else r_mo.uniform(0.005, 0.02)
    spin = _spin(rngs[5], cfg)
    q, w, p, acc_e = board.hand_motion(r_mo, n, rate, rot, (0.05, 3.0 if fast else 1.2), trans,
                                       (0.1, 2.5 if fast else 0.8), rest_s, breaks, 20.0, spin)  # fmt: skip
    drawn = {"motion": motion, "speed": speed, "rot_rms_dps": rot, "trans_rms_m": trans, "breaks": breaks}
    if spin is not None:
        drawn["spin_dps"] = np.rad2deg(spin).tolist()
    motion_of = Recorded(rate, q, w, p, acc_e, rest_s, q, t >= rest_s)
    return _dress(trial_name(scenario, seed), scenario, seed, cfg, motion_of, rngs[1:5], drawn, bend=True)


def _spin(rng, cfg: BoardConfig) -> np.ndarray | None:
    """A steady body rate (3,) rad/s, sensor frame, with probability ``spin_prob`` (else None): about a sensor
    axis tilted by ~0.3 rad (the BROAD magnet recordings turn 43–181 °/s net about one axis), ``spin_dps``
    fast, either sense."""
    if rng.uniform() >= cfg.spin_prob:
        return None
    axis = np.eye(3)[int(rng.integers(3))] + 0.3 * rng.normal(size=3)
    return axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(*cfg.spin_dps)) * rng.choice((-1.0, 1.0))


class Recorded(NamedTuple):
    """A board's true motion for :func:`_dress`: simulated, or a recording's (a randomised twin)."""

    rate: float  # Hz
    q: np.ndarray  # (N, 4) orientation the sensors see, sensor → ENU
    w: np.ndarray  # (N, 3) body rate, rad/s
    p: np.ndarray  # (N, 3) position, m ENU
    acc: np.ndarray  # (N, 3) linear acceleration, m/s² ENU
    rest_s: float  # the initial rest, s
    q_true: np.ndarray  # (N, 4) the truth the trial is scored against (NaN rows: none)
    score_mask: np.ndarray  # (N,) bool


def _dress(name: str, scenario: str, seed: int, cfg: BoardConfig, mo: Recorded, rngs, drawn: dict,
           bend: bool) -> Trial:  # fmt: skip
    """The trial of motion ``mo`` in a drawn room (``rngs``: disturbance, shocks, sensor, Earth location): the
    family's disturbance, the ideal readings, the sensor's errors and the site estimate. ``bend``: visits to
    room magnets bend the board's path (a simulated motion); else (a recorded one) the magnets are placed
    beside the path where it passes."""
    r_dist, r_shock, r_sensor, r_loc = rngs
    family = cfg.family if cfg.family != "random" else FAMILIES[int(r_dist.integers(len(FAMILIES)))]
    q, p, acc_e, rate, rest_s = mo.q, mo.p, mo.acc, mo.rate, mo.rest_s
    n = len(q)
    t = np.arange(n) / rate
    duration = n / rate
    if r_loc.uniform() < cfg.berlin_prob:
        norm, dip = cfg.field_norm + r_loc.uniform(-1.5, 1.5), cfg.field_dip + r_loc.uniform(-1.5, 1.5)
    else:
        norm, dip = earth.random_location(r_loc)
    b_earth = quat.earth_field(norm, dip)
    drawn = {"family": family, **drawn, "rest_s": rest_s, "rate": rate}
    room = IndoorField(b_earth)
    if family in ("stationary", "office"):
        if family == "office":
            visited = p[:: max(1, int(rate // 10))]
            room = random_indoor_field(r_dist, b_earth, visited, (2, 6), (1.0, 15.0), (0.3, 1.5), (0, 2))
        if family == "stationary" or r_dist.uniform() < 0.5:
            if bend:
                pos, mom = _room_magnets(r_dist, cfg)
                visits = _visits(r_dist, cfg, pos, rest_s, duration)
                p, acc_e = board.approach_path(t, p, acc_e, visits)
                drawn["visits"] = [(a, b, c, d.tolist()) for a, b, c, d in visits]
            else:
                pos, mom = _path_magnets(r_dist, cfg, p[t >= rest_s])
            room = IndoorField(b_earth, np.r_[room.dipole_pos, pos], np.r_[room.dipole_moment, mom],
                               room.wire_point, room.wire_dir, room.wire_current)  # fmt: skip
        drawn["sources"] = len(room.dipole_pos) + len(room.wire_point)
    gyr, acc, mag = board.ideal_readings(q, mo.w, acc_e, room(p))
    clean = quat.rotate_inv(q, np.broadcast_to(b_earth, (n, 3)))
    if family == "attached":
        d = r_dist.normal(size=3)
        if r_dist.uniform() < 0.6:  # mostly along one sensor axis (a magnet beside the chip)
            d = np.eye(3)[int(r_dist.integers(3))] * r_dist.choice((-1.0, 1.0)) + 0.3 * d
        offset = d / np.linalg.norm(d) * _log_uniform(r_dist, cfg.attached_ut)
        on = float(np.clip(rest_s + r_dist.uniform(*cfg.attached_on_s), 1.0, 0.8 * duration))
        off = on + float(r_dist.uniform(*cfg.attached_for_s)) if r_dist.uniform() < cfg.removed_prob else np.inf
        prof = board.attached_profile(t, on, off, float(r_dist.uniform(*cfg.attached_ramp_s)))
        extra = prof[:, None] * offset
        iron = bool(r_dist.uniform() < cfg.iron_prob)
        if iron:  # soft iron: a field ∝ the field the iron sits in
            soft = r_dist.normal(scale=_log_uniform(r_dist, (0.01, 0.3)), size=(3, 3))
            extra = extra + prof[:, None] * (mag @ soft.T)
        mag = mag + extra
        drawn.update(attached_ut=float(np.linalg.norm(offset)), attached_on_s=on, attached_off_s=off, iron=iron)
    if family == "shocks":
        kind = ("tapping", "vibration")[int(r_shock.integers(2))]
        bursts = []
        for _ in range(int(r_shock.integers(1, 5))):
            a = float(r_shock.uniform(rest_s + 2.0, max(rest_s + 3.0, duration - 10.0)))
            bursts.append((a, a + float(r_shock.uniform(5.0, 30.0))))
        amp = r_shock.uniform(5.0, 60.0) if kind == "tapping" else r_shock.uniform(1.0, 15.0)
        da, dg = board.shocks(r_shock, t, kind, bursts, amp, np.deg2rad(r_shock.uniform(0.2, 3.0)))
        acc, gyr = acc + da, gyr + dg
        drawn.update(shock=kind, bursts=bursts, shock_amp=float(amp))
    sensor = _sensor(r_sensor)
    scale = r_sensor.normal(scale=r_sensor.uniform(0.0, 0.004), size=(3, 3))  # gyro scale and misalignment
    gyr_m, acc_m, mag_m = apply_sensor_model(gyr @ (np.eye(3) + scale).T, acc, mag, rate, sensor, r_sensor)
    field_norm, field_dip, source = estimate_field(gyr_m, acc_m, mag_m, rate, documented=(norm, dip))
    drawn.update(site_norm=norm, site_dip=dip, field_source=source, sensor=dataclasses.asdict(sensor),
                 gyr_scale=scale.tolist())  # fmt: skip
    return Trial(
        name=name,
        rate=rate,
        gyr=gyr_m,
        acc=acc_m,
        mag=mag_m,
        q_true=mo.q_true,
        field_norm=field_norm,
        field_dip=field_dip,
        score_mask=mo.score_mask,
        truth={"mag_disturbance": mag - clean, "position": p},
        meta=trial_meta(scenario, seed, cfg, drawn),
    )


def _path_magnets(rng, cfg: BoardConfig, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Magnets beside a recorded path (M, 3): each at a drawn closest approach from a random point of the path,
    moved out until no point of the path is nearer; their moments as :func:`_room_magnets`'."""
    pos, mom = _room_magnets(rng, cfg)
    for k in range(len(pos)):
        d = rng.normal(size=3)
        want = _log_uniform(rng, cfg.distance_m)
        p = path[int(rng.integers(len(path)))] + want * d / np.linalg.norm(d)
        for _ in range(100):  # out along the same direction until the whole path keeps its distance
            dist = np.linalg.norm(path - p, axis=1)
            if dist.min() >= 0.95 * want:
                break
            p = p + 0.1 * want * d / np.linalg.norm(d)
        pos[k] = p
    return pos, mom


RANDOM_TWIN = "rtwin:"  # a randomised twin: "rtwin:PATH"


def random_twin(name: str, seed: int, **overrides) -> Trial:
    """Randomised twin ``seed`` of the recording of ``name`` = ``"rtwin:PATH"``: the recording's own true motion
    (``magenv.scenarios.twin_fit.Motion``) and truth, in a room, with a disturbance and a sensor drawn as in
    ``board_random`` (``overrides``: BoardConfig fields) — never the recording's own disturbance or sensor."""
    from magenv.scenarios import twin

    if not name.startswith(RANDOM_TWIN):
        raise ValueError(f"a randomised twin is 'rtwin:PATH', got {name!r}")
    cfg = WORLD.configure("board_random", **overrides)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    rec, mo, _ = twin.fitted(twin.PREFIX + name[len(RANDOM_TWIN) :])
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(4)]
    motion = Recorded(rec.rate, mo.qs, mo.w, mo.pos, mo.lin_acc, (mo.rest.stop - mo.rest.start) / rec.rate,
                      rec.q_true.copy(), np.array(rec.score_mask, bool))  # fmt: skip
    drawn = {"recording": name[len(RANDOM_TWIN) :]}
    return _dress(f"{RANDOM_TWIN}{rec.name}#{seed}", f"{RANDOM_TWIN}{rec.name}", int(seed), cfg, motion, rngs, drawn,
                  bend=False)  # fmt: skip


#: The board scenarios: name → default config.
SCENARIOS: dict[str, BoardConfig] = {
    "board_random": BoardConfig(),
    **{f"board_{f}": BoardConfig(family=f) for f in FAMILIES},
    "board_spinning": BoardConfig(spin_prob=1.0),
}

WORLD = World("board", "board", SCENARIOS, _simulate, n_streams=6)
