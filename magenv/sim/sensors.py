"""The MIMU sensor model: ideal readings → what a real unit reports (seeded).

Gyroscope: constant bias (drawn per trial) + slow random-walk drift + white
noise. Accelerometer: constant bias + white noise. Magnetometer: residual
hard/soft iron after calibration, white noise, saturation, and the two timing
artefacts seen in the real BROAD recordings (``shared/data/broad/README.md``):
a lag of ~4 samples behind the gyroscope, and sample-and-hold (~29 % of the
samples repeat the previous one, i.e. the magnetometer updates at ~71 % of
the output rate). Frames: sensor frame throughout; units rad/s, m/s², µT.

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
    nine BROAD recordings (``benchmarks/realism.py``, medians at rest): gyro
    noise 0.094 °/s, gyro bias spread 0.18 °/s, accelerometer noise
    0.052 m/s², magnetometer noise 0.70 µT, magnetometer 3.2 samples behind
    the gyro, 29 % of magnetometer samples held. ``SensorConfig.papers()``
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
        mag_noise_ut: magnetometer white noise, µT.
        mag_hard_iron_ut: std of the residual hard-iron offset per axis, µT.
        mag_soft_iron: std of the residual soft-iron matrix entries (symmetric,
            added to the identity), dimensionless.
        mag_range_ut: magnetometer saturation, ±µT per axis.
        mag_lag_samples: magnetometer delay behind the other channels, samples.
        mag_hold_fraction: fraction of magnetometer samples that repeat the
            previous one (sample-and-hold), in [0, 1).
    """

    gyr_noise_dps: float = 0.1
    gyr_bias_dps: float = 0.2
    gyr_drift_dps: float = 0.005
    acc_noise: float = 0.05
    acc_bias: float = 0.02
    mag_noise_ut: float = 0.7
    mag_hard_iron_ut: float = 0.3
    mag_soft_iron: float = 0.005
    mag_range_ut: float = 800.0
    mag_lag_samples: int = 3
    mag_hold_fraction: float = 0.29

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
        if int(self.mag_lag_samples) != self.mag_lag_samples:
            raise ValueError(
                f"SensorConfig.mag_lag_samples must be a whole number of samples, got {self.mag_lag_samples!r}"
            )
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
    """

    def __init__(self, n: int, rate: float, cfg: SensorConfig, rng: np.random.Generator):
        d2r = np.pi / 180.0
        self.n, self.done, self.lag = int(n), 0, int(cfg.mag_lag_samples)
        self.bias_g = rng.normal(0.0, cfg.gyr_bias_dps * d2r, 3)
        self.bias_a = rng.normal(0.0, cfg.acc_bias, 3)
        s = rng.normal(0.0, cfg.mag_soft_iron, (3, 3))
        self.soft = np.eye(3) + 0.5 * (s + s.T)  # residual soft iron: I + S, S symmetric
        self.hard = rng.normal(0.0, cfg.mag_hard_iron_ut, 3)
        self.phase = rng.uniform(0.0, 1.0)
        self.sig = np.array(
            [cfg.gyr_drift_dps * d2r * math.sqrt(1.0 / rate), cfg.gyr_noise_dps * d2r, cfg.acc_noise, cfg.mag_noise_ut]
        )
        self.f_ratio, self.mag_range = 1.0 - cfg.mag_hold_fraction, float(cfg.mag_range_ut)
        self.carry = np.zeros(7)  # the bias walk (3), the held reading (3), the last conversion (initially −1)
        self.carry[6] = -1.0
        self.mag_tail = np.zeros((0, 3))  # the last ``lag`` ideal fields before the next block
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
        if i0 == 0 and m == self.n:
            z = self.rng.standard_normal((4, m, 3))  # walk, gyro, accelerometer, magnetometer
        else:
            if i0 == 0:
                self.streams = self._split()
            z = np.stack([g.standard_normal((m, 3)) for g in self.streams])
        mag = np.ascontiguousarray(mag)
        ext = np.concatenate([self.mag_tail, mag]) if len(self.mag_tail) else mag
        out = _measure(
            np.ascontiguousarray(gyr),
            np.ascontiguousarray(acc),
            ext,
            z,
            self.sig,
            self.bias_g,
            self.bias_a,
            self.soft,
            self.hard,
            self.lag,
            self.f_ratio,
            self.phase,
            self.mag_range,
            i0,
            i0 - len(self.mag_tail),
            self.carry,
        )
        self.done = i0 + m
        if self.lag:
            self.mag_tail = ext[-self.lag :].copy()
        if self.streams and self.done == self.n:
            self.rng.bit_generator.state = self.streams[-1].bit_generator.state
        return out


#: Noise rows drawn at a time to advance a :class:`SensorStream`'s generators.
_SKIP = 1 << 16


@njit(cache=True)
def _measure(gyr, acc, mag, z, sig, bias_g, bias_a, soft, hard, lag, f_ratio, phase, mag_range, i0, m0, carry):
    """Kernel of :class:`SensorStream`: samples i0 … i0 + m − 1 (``gyr``, ``acc``, ``z`` rows), ``mag`` from
    sample m0 ≤ i0 − lag on (the ``lag`` fields before the block); ``carry`` (7,): the bias walk, the held
    reading and the last conversion, updated.

    Gyro: ω + b + Σ walk + noise (walk std grows as drift·√t).
    Magnetometer: the reading at sample i reports conversion k(i) =
    ⌊i·f + phase⌋, f = 1 − hold fraction conversions per sample
    (sample-and-hold, ~29 % repeats); conversion k is made at the first
    sample i_k that reports it, of the field at sample i_k − lag, through
    the residual iron (I + S)·B + h, plus noise; then clipped to ±range.
    """
    n = gyr.shape[0]
    gyr_m = np.empty((n, 3))
    acc_m = np.empty((n, 3))
    mag_m = np.empty((n, 3))
    walk = carry[0:3]
    held = carry[3:6]
    last_k = int(carry[6])
    for r in range(n):
        i = i0 + r
        for j in range(3):
            walk[j] += sig[0] * z[0, r, j]
            gyr_m[r, j] = gyr[r, j] + bias_g[j] + walk[j] + sig[1] * z[1, r, j]
            acc_m[r, j] = acc[r, j] + bias_a[j] + sig[2] * z[2, r, j]
        k = int(np.floor(i * f_ratio + phase))
        if k != last_k:  # a new conversion
            last_k = k
            src = max(i - lag, 0) - m0
            for j in range(3):
                b = hard[j] + soft[j, 0] * mag[src, 0] + soft[j, 1] * mag[src, 1] + soft[j, 2] * mag[src, 2]
                b += sig[3] * z[3, r, j]
                held[j] = min(max(b, -mag_range), mag_range)
        for j in range(3):
            mag_m[r, j] = held[j]
    carry[6] = last_k
    return gyr_m, acc_m, mag_m


def noise_121(z: np.ndarray) -> np.ndarray:
    """Low-pass coloured noise of unit std from white ``z`` (K, 3): ν_k = (w_k + 2w_{k−1} + w_{k−2})/√6.

    The magnetometer noise of the BROAD unit, over its conversions (held repeats left out), has lag-1 and
    lag-2 autocorrelations of ~0.66 and ~0.16; the [1, 2, 1] kernel gives 4/6 and 1/6. The first two rows
    (no full history) are scaled white, so every row has unit variance.
    """
    z = np.asarray(z, float)
    out = z.copy()
    out[1:] += 2.0 * z[:-1]
    out[2:] += z[:-2]
    out[:2] = z[:2] * np.sqrt(6.0)
    return out / np.sqrt(6.0)


def hold_samples(values: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Sample-and-hold: row i of ``values`` (N, k) where ``held[i]`` is False, else the last such row before
    it (the first row is never held)."""
    held = np.asarray(held, bool).copy()
    held[0] = False
    last = np.maximum.accumulate(np.where(held, 0, np.arange(len(held))))
    return np.asarray(values)[last]


def hold_pattern(n: int, hold_fraction: float, phase: float) -> np.ndarray:
    """(N,) True where the magnetometer repeats its previous reading: sample i reports conversion
    ⌊i·(1 − hold_fraction) + phase⌋ (the pattern :func:`apply_sensor_model` uses), phase in [0, 1)."""
    k = np.floor(np.arange(n) * (1.0 - hold_fraction) + phase).astype(np.int64)
    return np.r_[False, k[1:] == k[:-1]]
