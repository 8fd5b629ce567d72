"""The MIMU sensor model: ideal readings → what a real unit reports (seeded).

Gyroscope: constant bias (drawn per trial) + slow random-walk drift + white
noise, one sample behind the true motion. Accelerometer: constant bias + white
noise. Magnetometer: residual hard/soft iron after calibration, low-pass
noise, saturation, and the timing artefacts seen in the real BROAD recordings
(``shared/data/broad/README.md``, measured by ``studies/realism.py``): a lag
of ~3 samples behind the gyroscope, and sample-and-hold in runs of two (~29 %
of the samples repeat the previous one, i.e. the magnetometer updates at ~71 %
of the output rate). Frames: sensor frame throughout; units rad/s, m/s², µT.

All parameters live in :class:`SensorConfig`; randomness comes only from the
``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
from numba import njit


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """MIMU error model. Noise values are white-noise std per sample.

    The defaults are those of a real sensor of this class, measured on the
    nine BROAD recordings (``studies/realism.py``, medians at rest): gyro
    noise 0.094 °/s, gyro bias spread 0.18 °/s, accelerometer noise
    0.052 m/s², magnetometer noise 0.70 µT with lag-1/lag-2 autocorrelations
    0.67/0.16 over its conversions, magnetometer 3.2 samples behind the gyro
    (effective, hold age included), the gyro 1.2 samples behind the optical
    truth, 29 % of magnetometer samples held, in runs of exactly two.
    ``SensorConfig.papers()``
    gives the values the papers quote instead (gyro 0.5 °/s, accelerometer
    0.02 m/s², magnetometer 0.15 µT): with them the gyro noise equals Fan et
    al.'s stationary threshold (0.5 °/s), so their detector would rarely fire,
    which says their sensor was quieter than that.

    Attributes:
        gyr_noise_dps: gyroscope white noise, °/s.
        gyr_bias_dps: std of the constant gyroscope bias drawn per trial and axis, °/s.
        gyr_drift_dps: random-walk drift of the gyroscope bias, °/s per √s.
        acc_noise: accelerometer white noise, m/s².
        acc_bias: std of the constant accelerometer bias per axis, m/s².
        mag_noise_ut: magnetometer noise std, µT (coloured by ``mag_noise_taps``).
        mag_noise_taps: the noise over the conversions is white noise through a binomial low-pass of this
            many taps (:func:`lowpass_noise`; 3: [1, 2, 1], lag-1/lag-2 autocorrelation 4/6, 1/6; 1: white).
        mag_hard_iron_ut: std of the residual hard-iron offset per axis, µT.
        mag_soft_iron: std of the residual soft-iron matrix entries (symmetric,
            added to the identity), dimensionless.
        mag_range_ut: magnetometer saturation, ±µT per axis.
        gyr_lag_samples: gyroscope delay behind the true motion (and the accelerometer), samples.
        mag_lag_samples: magnetometer delay behind the gyroscope, samples.
        mag_hold_fraction: fraction of magnetometer samples that repeat the
            previous one (sample-and-hold), in [0, 1).
        mag_hold_run: the held samples come in runs of this length (:func:`hold_pattern`).
    """

    gyr_noise_dps: float = 0.1
    gyr_bias_dps: float = 0.2
    gyr_drift_dps: float = 0.005
    acc_noise: float = 0.05
    acc_bias: float = 0.02
    mag_noise_ut: float = 0.7
    mag_noise_taps: int = 3
    mag_hard_iron_ut: float = 0.3
    mag_soft_iron: float = 0.005
    mag_range_ut: float = 800.0
    gyr_lag_samples: int = 1
    mag_lag_samples: int = 3
    mag_hold_fraction: float = 0.29
    mag_hold_run: int = 2

    @classmethod
    def papers(cls) -> SensorConfig:
        """The noise levels the papers quote (Ligorio & Sabatini 2016; Fan et al. 2017 §3), lag 4 samples."""
        return cls(gyr_noise_dps=0.5, gyr_bias_dps=0.1, acc_noise=0.02, mag_noise_ut=0.15, mag_lag_samples=4)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float, np.integer, np.floating))
                or not math.isfinite(v)
                or v < 0
            ):
                raise ValueError(f"SensorConfig.{f.name} must be a finite number ≥ 0, got {v!r}")
        for name in ("mag_lag_samples", "gyr_lag_samples"):
            if int(getattr(self, name)) != getattr(self, name):
                raise ValueError(f"SensorConfig.{name} must be a whole number of samples, got {getattr(self, name)!r}")
        for name in ("mag_noise_taps", "mag_hold_run"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise ValueError(f"SensorConfig.{name} must be a whole number ≥ 1, got {getattr(self, name)!r}")
        if not self.mag_hold_fraction < 1.0:
            raise ValueError(f"SensorConfig.mag_hold_fraction must be < 1, got {self.mag_hold_fraction!r}")
        if self.mag_range_ut <= 0:
            raise ValueError(f"SensorConfig.mag_range_ut must be > 0 µT, got {self.mag_range_ut!r}")

    def scaled(self, noise_scale: float) -> SensorConfig:
        """This config with all white-noise levels multiplied by ``noise_scale``."""
        return dataclasses.replace(
            self,
            gyr_noise_dps=self.gyr_noise_dps * noise_scale,
            acc_noise=self.acc_noise * noise_scale,
            mag_noise_ut=self.mag_noise_ut * noise_scale,
        )


def apply_sensor_model(
    gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray, rate: float, cfg: SensorConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measured (gyr, acc, mag) from ideal readings, all (N, 3) sensor frame.

    Args:
        gyr: ideal angular rate, rad/s.
        acc: ideal specific force, m/s².
        mag: ideal magnetic field at the sensor, µT (Earth + magnet).
        rate: sample rate, Hz.
        cfg: error model.
        rng: the trial's generator (draws in a fixed order: determinism).
    """
    return SensorStream(len(gyr), rate, cfg, rng).measure(gyr, acc, mag)


class SensorStream:
    """:func:`apply_sensor_model` over N samples given in consecutive blocks (``measure``), the same numbers
    bit for bit as all at once: a long trial need not hold its ideal readings and their noise whole.

    The per-trial draws (biases, iron, hold phase) come first from ``rng``, then the four (N, 3) noise
    streams (bias walk, gyro, accelerometer, magnetometer) in that order. All N at once, they are one draw;
    in blocks, each stream reads from its own copy of ``rng`` advanced to where it starts (made at the first
    block, so ``rng`` must not be drawn from meanwhile), and ``rng`` ends where the one draw would leave it.
    The magnetometer's low-pass runs over its conversions across block edges.
    """

    def __init__(self, n: int, rate: float, cfg: SensorConfig, rng: np.random.Generator):
        d2r = np.pi / 180.0
        self.n, self.done = int(n), 0
        self.gyr_lag, self.lag, self.taps = int(cfg.gyr_lag_samples), int(cfg.mag_lag_samples), int(cfg.mag_noise_taps)
        self.bias_g = rng.normal(0.0, cfg.gyr_bias_dps * d2r, 3)
        self.bias_a = rng.normal(0.0, cfg.acc_bias, 3)
        s = rng.normal(0.0, cfg.mag_soft_iron, (3, 3))
        self.soft = np.eye(3) + 0.5 * (s + s.T)  # residual soft iron: I + S, S symmetric
        self.hard = rng.normal(0.0, cfg.mag_hard_iron_ut, 3)
        phase = rng.uniform(0.0, 1.0)
        self.held = hold_pattern(self.n, cfg.mag_hold_fraction, phase, int(cfg.mag_hold_run))
        self.sig = np.array(
            [cfg.gyr_drift_dps * d2r * math.sqrt(1.0 / rate), cfg.gyr_noise_dps * d2r, cfg.acc_noise, cfg.mag_noise_ut]
        )
        self.mag_range = float(cfg.mag_range_ut)
        self.carry = np.zeros(6)  # the bias walk (3) and the held reading (3)
        self.gyr_tail = np.zeros((0, 3))  # the last gyr_lag ideal rates before the next block
        self.mag_tail = np.zeros((0, 3))  # the last gyr_lag + lag ideal fields before the next block
        self.white_tail = np.zeros((0, 3))  # the last taps − 1 white magnetometer noise rows of conversions
        self.rng = rng
        self.streams: list = []  # with blocks: a generator per noise stream (_split)

    def _split(self) -> list:
        """One generator per noise stream, each advanced to its start."""
        streams = [copy.deepcopy(self.rng)]
        for _ in range(3):
            g = copy.deepcopy(streams[-1])
            for c in range(0, self.n, _SKIP):
                g.standard_normal((min(self.n - c, _SKIP), 3))
            streams.append(g)
        return streams

    def measure(self, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The measured (gyr, acc, mag) of the next block of ideal readings (m, 3) each."""
        m, i0 = len(gyr), self.done
        if i0 + m > self.n:
            raise ValueError(f"SensorStream of {self.n} samples given {i0 + m}")
        held = self.held[i0 : i0 + m]
        if i0 == 0 and m == self.n:
            z = self.rng.standard_normal((4, m, 3))  # walk, gyro, accelerometer, magnetometer
            new = np.flatnonzero(~held)
            z[3, new] = lowpass_noise(z[3, new], self.taps)  # the noise over the conversions
        else:
            if i0 == 0:
                self.streams = self._split()
            z = np.stack([g.standard_normal((m, 3)) for g in self.streams])
            new = np.flatnonzero(~held)
            white = np.concatenate([self.white_tail, z[3, new]])
            k = len(self.white_tail)
            z[3, new] = lowpass_noise(white, self.taps)[k:]
            if self.taps > 1:
                self.white_tail = white[-(self.taps - 1) :].copy()
        gyr, acc, mag = (np.ascontiguousarray(a) for a in (gyr, acc, mag))
        g_ext = np.concatenate([self.gyr_tail, gyr]) if len(self.gyr_tail) else gyr
        m_ext = np.concatenate([self.mag_tail, mag]) if len(self.mag_tail) else mag
        out = _measure(
            g_ext,
            acc,
            m_ext,
            z,
            self.sig,
            self.bias_g,
            self.bias_a,
            self.soft,
            self.hard,
            self.gyr_lag,
            self.lag,
            held,
            self.mag_range,
            i0,
            i0 - len(self.gyr_tail),
            i0 - len(self.mag_tail),
            self.carry,
        )
        self.done = i0 + m
        if self.gyr_lag:
            self.gyr_tail = g_ext[-self.gyr_lag :].copy()
        if self.gyr_lag + self.lag:
            self.mag_tail = m_ext[-(self.gyr_lag + self.lag) :].copy()
        if self.streams and self.done == self.n:
            self.rng.bit_generator.state = self.streams[-1].bit_generator.state
        return out


#: Noise rows drawn at a time to advance a :class:`SensorStream`'s generators.
_SKIP = 1 << 16


@njit(cache=True)
def _measure(gyr, acc, mag, z, sig, bias_g, bias_a, soft, hard, gyr_lag, lag, held_mask, mag_range, i0, g0, m0, carry):
    """Kernel of :class:`SensorStream`: samples i0 … i0 + m − 1 (``acc``, ``z``, ``held_mask`` rows), ``gyr``
    from sample g0 on and ``mag`` from sample m0 on (the lagged rows before the block); ``carry`` (6,): the
    bias walk and the held reading, updated.

    Gyro: ω(i − gyr_lag) + b + Σ walk + noise (walk std grows as drift·√t).
    Magnetometer: a new conversion at each sample i not held (``held_mask``,
    :func:`hold_pattern`), of the field at sample i − gyr_lag − lag, through
    the residual iron (I + S)·B + h, plus noise (already coloured); held
    samples repeat it; then clipped to ±range.
    """
    n = acc.shape[0]
    gyr_m = np.empty((n, 3))
    acc_m = np.empty((n, 3))
    mag_m = np.empty((n, 3))
    walk = carry[0:3]
    held = carry[3:6]
    for r in range(n):
        i = i0 + r
        gsrc = max(i - gyr_lag, 0) - g0
        for j in range(3):
            walk[j] += sig[0] * z[0, r, j]
            gyr_m[r, j] = gyr[gsrc, j] + bias_g[j] + walk[j] + sig[1] * z[1, r, j]
            acc_m[r, j] = acc[r, j] + bias_a[j] + sig[2] * z[2, r, j]
        if i == 0 or not held_mask[r]:  # a new conversion
            src = max(i - gyr_lag - lag, 0) - m0
            for j in range(3):
                b = hard[j] + soft[j, 0] * mag[src, 0] + soft[j, 1] * mag[src, 1] + soft[j, 2] * mag[src, 2]
                b += sig[3] * z[3, r, j]
                held[j] = min(max(b, -mag_range), mag_range)
        for j in range(3):
            mag_m[r, j] = held[j]
    return gyr_m, acc_m, mag_m


def lowpass_noise(z: np.ndarray, taps: int) -> np.ndarray:
    """Low-pass coloured noise of unit std from white ``z`` (K, 3) through the binomial kernel of ``taps``
    taps: ν_k = Σ_m C(taps − 1, m)·w_{k−m} / √(Σ_m C(taps − 1, m)²); 1 tap: white, 3 taps: [1, 2, 1]/√6
    (lag-1 and lag-2 autocorrelations 4/6 and 1/6). The first ``taps − 1`` rows (no full history) are scaled
    white, so every row has unit variance."""
    z = np.asarray(z, float)
    c = [math.comb(taps - 1, m) for m in range(taps)]
    norm = math.sqrt(sum(x * x for x in c))
    out = z.copy()
    for m in range(1, min(taps, len(z) + 1)):
        out[m:] += c[m] * z[:-m]
    out[: taps - 1] = z[: taps - 1] * norm
    return out / norm


def noise_121(z: np.ndarray) -> np.ndarray:
    """:func:`lowpass_noise` with 3 taps: the magnetometer noise of the BROAD unit, over its conversions (held
    repeats left out), has lag-1 and lag-2 autocorrelations of ~0.66 and ~0.16; [1, 2, 1] gives 4/6 and 1/6."""
    return lowpass_noise(z, 3)


def hold_samples(values: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Sample-and-hold: row i of ``values`` (N, k) where ``held[i]`` is False, else the last such row before
    it (the first row is never held)."""
    held = np.asarray(held, bool).copy()
    held[0] = False
    last = np.maximum.accumulate(np.where(held, 0, np.arange(len(held))))
    return np.asarray(values)[last]


def hold_pattern(n: int, hold_fraction: float, phase: float, run: int = 1) -> np.ndarray:
    """(N,) True where the magnetometer repeats its previous reading (the pattern :func:`apply_sensor_model`
    uses), phase in [0, 1): the samples form slots of ``run`` samples, slot s reports conversion slot
    ⌊s·(1 − hold_fraction) + phase⌋, and a slot that reports the same as the one before is held whole. So
    holds come in runs of ``run`` samples, ``hold_fraction`` of the samples; BROAD's unit holds pairs, 6 or 8
    samples apart (run 2, fraction 0.29)."""
    if int(run) != run or run < 1:
        raise ValueError(f"hold run must be a whole number ≥ 1, got {run!r}")
    k = np.floor(np.arange(-(-n // run)) * (1.0 - hold_fraction) + phase).astype(np.int64)
    slot_held = np.r_[False, k[1:] == k[:-1]]
    return np.repeat(slot_held, run)[:n]
