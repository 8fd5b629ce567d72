"""Statistics of a sensor stream that a simulator's sensor model should match.

Used by ``studies/realism.py`` on the real recordings (BROAD) and on
simulated trials alike; every function takes a ``Trial`` (or plain arrays);
only ``truth_lag`` uses the true orientation.

* ``rest_noise`` — per-axis standard deviation during the initial rest
  (gyro °/s, accelerometer m/s², magnetometer µT).
* ``rest_autocorr`` — lag-``k`` autocorrelation of the rest noise (0 for
  white noise); for the magnetometer also over its distinct (non-held) samples.
* ``hold_fraction`` — share of samples that repeat the previous one exactly
  (sample-and-hold); ``hold_runs`` — how those repeats group: the mean length
  of a run of consecutive repeats and the share of runs that are exactly two
  long (BROAD: every run is two samples, 6 or 8 samples apart).
* ``mag_lag`` — delay of the magnetometer behind the gyroscope, samples. In a
  field that is constant in the earth frame the sensor-frame field obeys
  ``dm/dt = −ω × m`` (ω body rate, sensor frame). If the magnetometer is ``k``
  samples late, ``dm/dt(t) = −ω(t−k) × m(t)``; the lag is the ``k`` that
  minimises the squared residual over the moving samples (both sides smoothed
  by the same centred moving average, which removes the sample-and-hold
  steps without shifting either), refined to a fraction of a sample by a
  parabola through the three best lags. The result is the *effective* delay:
  it includes the mean age that sample-and-hold adds (two held samples in
  seven add 3/7 ≈ 0.43 sample). Accuracy on a synthetic trial: ±0.15 sample.
* ``truth_lag`` — delay of the magnetometer or the gyroscope behind the true
  orientation (needs truth): for mag, the lag ``k`` that makes
  ``q_true(t−k) ⊗ m(t)`` (the field in the earth frame) most constant; for
  gyro, the lag that best matches the body rate differentiated from
  ``q_true``. On BROAD: mag ≈ 4.4, gyro ≈ 1.2 samples behind the optical
  truth, so mag ≈ 3.2 samples behind the gyro, which ``mag_lag`` confirms
  (effective delays, sample-and-hold included).
* ``quantum`` — smallest non-zero step between consecutive samples (an upper
  bound of the resolution, LSB).
* ``field_norm_dip`` — per-sample field magnitude (µT) and dip (°) where the
  accelerometer measures gravity alone (|a| within 0.3 m/s² of g).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from magenv.quaternion import GRAVITY
from magenv.recordings import dip_angle, initial_rest
from magenv.trial import Trial


def _moving_average(x: np.ndarray, win: int) -> np.ndarray:
    """Centred moving average along axis 0 (zero delay; zero-padded at the edges)."""
    if win <= 1:
        return x
    kernel = np.ones(win) / win
    return np.stack([np.convolve(x[:, i], kernel, mode="same") for i in range(x.shape[1])], 1)


def rest_noise(trial: Trial, min_seconds: float = 1.0) -> dict[str, Any]:
    """Per-axis std during the initial rest (``magenv.recordings.initial_rest``):
    ``{"gyr": °/s (3,), "acc": m/s² (3,), "mag": µT (3,), "rest_s": s,
    "gyr_bias": mean gyro °/s (3,)}``; NaN arrays if the rest is shorter than
    ``min_seconds``."""
    rest = initial_rest(trial.gyr, trial.rate)
    n = rest.stop - rest.start
    if n < min_seconds * trial.rate:
        nan = np.full(3, np.nan)
        return {"gyr": nan, "acc": nan.copy(), "mag": nan.copy(), "rest_s": n / trial.rate, "gyr_bias": nan.copy()}
    return {
        "gyr": np.rad2deg(trial.gyr[rest].std(0)),
        "acc": trial.acc[rest].std(0),
        "mag": trial.mag[rest].std(0),
        "rest_s": n / trial.rate,
        "gyr_bias": np.rad2deg(trial.gyr[rest].mean(0)),
    }


def rest_autocorr(trial: Trial, channel: str, lag: int = 1, distinct: bool = False) -> float:
    """Lag-``lag`` autocorrelation (all axes pooled) of ``channel`` ("gyr", "acc",
    "mag") during the initial rest, mean removed; ``distinct`` drops samples that
    repeat the previous one first. NaN if the rest is shorter than 1 s."""
    rest = initial_rest(trial.gyr, trial.rate)
    x = getattr(trial, channel)[rest]
    if len(x) < trial.rate:
        return float("nan")
    if distinct:
        x = x[np.r_[True, np.any(x[1:] != x[:-1], axis=1)]]
    x = x - x.mean(0)
    return float(np.sum(x[lag:] * x[:-lag]) / np.sum(x * x))


def hold_fraction(x: np.ndarray) -> float:
    """Share of samples ``i ≥ 1`` with ``x[i] == x[i−1]`` on every axis (sample-and-hold)."""
    x = np.asarray(x)
    if len(x) < 2:
        return float("nan")
    return float(np.mean(np.all(x[1:] == x[:-1], axis=-1)))


def hold_runs(x: np.ndarray) -> tuple[float, float]:
    """(mean length, share of length-2 runs) of the runs of consecutive repeated samples of ``x`` (N, k)
    (a run: samples i … i+L−1 each equal to the one before); (NaN, NaN) without repeats."""
    x = np.asarray(x)
    held = np.r_[False, np.all(x[1:] == x[:-1], axis=-1)] if len(x) >= 2 else np.zeros(len(x), bool)
    edges = np.diff(np.r_[0, held.astype(np.int8), 0])
    lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    if not lengths.size:
        return float("nan"), float("nan")
    return float(lengths.mean()), float(np.mean(lengths == 2))


def mag_lag(
    trial: Trial, max_lag: int = 20, smooth_s: float = 0.05, mask: np.ndarray | None = None, min_rate_dps: float = 20.0
) -> float:
    """Magnetometer delay behind the gyroscope, samples (positive = mag late).

    Fits ``dm/dt = −ω(t−k) × m(t)`` over samples in ``mask`` (default
    ``trial.score_mask``) where |ω| > ``min_rate_dps``; assumes a field constant
    in the earth frame there (use undisturbed trials). NaN if too few samples.
    """
    win = max(1, int(round(smooth_s * trial.rate)))
    m = _moving_average(trial.mag, win)
    dm = np.gradient(m, trial.dt, axis=0)
    mask = trial.score_mask if mask is None else np.asarray(mask, bool)
    fast = np.linalg.norm(trial.gyr, axis=1) > np.deg2rad(min_rate_dps)
    lags = np.arange(-max_lag, max_lag + 1)
    n = trial.n
    keep = (mask & fast)[max_lag : n - max_lag]
    if keep.sum() < 10 * trial.rate * smooth_s:
        return float("nan")
    cost = np.empty(len(lags))
    for j, k in enumerate(lags):
        w = np.roll(trial.gyr, k, axis=0)  # w[t] = gyr[t − k]
        pred = _moving_average(-np.cross(w, trial.mag), win)
        r = (dm - pred)[max_lag : n - max_lag][keep]
        cost[j] = np.mean(np.sum(r * r, axis=1))
    return _parabola_min(lags, cost)


def _parabola_min(lags: np.ndarray, cost: np.ndarray) -> float:
    j = int(np.nanargmin(cost))
    if 0 < j < len(lags) - 1:
        c0, c1, c2 = cost[j - 1], cost[j], cost[j + 1]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            return float(lags[j] + 0.5 * (c0 - c2) / denom)
    return float(lags[j])


def truth_lag(trial: Trial, channel: str = "mag", max_lag: int = 10, min_rate_dps: float = 20.0) -> float:
    """Delay (samples, positive = sensor late) of ``channel`` ("mag" or "gyr")
    behind ``trial.q_true``, over scored samples with |ω| > ``min_rate_dps``.
    For "mag" the field must be constant in the earth frame (undisturbed trial)."""
    from magenv import quaternion as quat

    lags = np.arange(-max_lag, max_lag + 1)
    n = trial.n
    base = trial.score_mask & (np.linalg.norm(trial.gyr, axis=1) > np.deg2rad(min_rate_dps))
    base[: max_lag + 1] = False
    base[n - max_lag - 1 :] = False
    if channel == "gyr":
        rate = np.full((n, 3), np.nan)
        with np.errstate(invalid="ignore"):
            dq = quat.mul(quat.conj(trial.q_true[:-2]), trial.q_true[2:])
            rate[1:-1] = quat.to_rotvec(dq) / (2 * trial.dt)  # body rate, rad/s, centred
    elif channel != "mag":
        raise ValueError(f"channel must be 'mag' or 'gyr', got {channel!r}")
    cost = np.full(len(lags), np.nan)
    for j, k in enumerate(lags):
        if channel == "mag":
            with np.errstate(invalid="ignore"):
                field = quat.rotate(np.roll(trial.q_true, k, axis=0), trial.mag)  # earth frame, µT
            keep = base & np.all(np.isfinite(field), axis=1)
            if keep.sum() <= 100:
                continue
            r = field[keep] - np.median(field[keep], axis=0)
        else:
            g = np.roll(trial.gyr, -k, axis=0)  # g[t] = gyr[t + k]: undo a lag of k
            keep = base & np.all(np.isfinite(rate), axis=1)
            r = rate[keep] - g[keep]
        if len(r) > 100:
            cost[j] = np.mean(np.sum(r * r, axis=1))
    if np.all(np.isnan(cost)):
        return float("nan")
    return _parabola_min(lags, cost)


def quantum(x: np.ndarray, floor: float = 1e-8) -> float:
    """Smallest absolute step above ``floor`` (round-off) between consecutive samples of ``x``."""
    d = np.abs(np.diff(np.asarray(x, float), axis=0))
    d = d[d > floor]
    return float(d.min()) if d.size else float("nan")


def field_norm_dip(trial: Trial, acc_tol: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Field magnitude (µT) and dip (°) at samples where ||a| − g| < ``acc_tol`` m/s²."""
    quiet = np.abs(np.linalg.norm(trial.acc, axis=1) - GRAVITY) < acc_tol
    return np.linalg.norm(trial.mag[quiet], axis=1), dip_angle(trial.acc[quiet], trial.mag[quiet])


@dataclass
class SensorStats:
    """Summary of one trial's sensor stream (units in the field names)."""

    name: str
    rate_hz: float
    rest_s: float
    gyr_noise_dps: float  # mean of the per-axis rest std
    acc_noise_ms2: float
    mag_noise_ut: float
    gyr_noise_axes_dps: tuple
    acc_noise_axes_ms2: tuple
    mag_noise_axes_ut: tuple
    gyr_bias_axes_dps: tuple  # mean gyro during the rest
    gyr_autocorr1: float  # lag-1 autocorrelation of the rest noise
    acc_autocorr1: float
    mag_autocorr1: float
    mag_autocorr1_distinct: float  # over non-held samples only
    mag_autocorr2_distinct: float  # lag 2, over non-held samples only
    field_norm_median_ut: float
    field_norm_p05_ut: float
    field_norm_p95_ut: float
    dip_median_deg: float
    dip_p05_deg: float
    dip_p95_deg: float
    mag_lag_samples: float  # behind the gyro
    mag_truth_lag_samples: float  # behind the true orientation
    gyr_truth_lag_samples: float
    gyr_quantum_dps: float
    acc_quantum_ms2: float
    mag_quantum_ut: float
    mag_hold_fraction: float
    mag_hold_run_mean: float  # mean length of a run of repeated samples
    mag_hold_run2_share: float  # share of those runs exactly two samples long
    gyr_hold_fraction: float
    acc_hold_fraction: float

    def as_dict(self) -> dict:
        return asdict(self)


def _axes(values) -> tuple[float, ...]:
    """Per-axis figures rounded to 4 decimals, as a tuple of floats."""
    return tuple(float(v) for v in np.round(np.asarray(values, float), 4))


def sensor_stats(trial: Trial) -> SensorStats:
    """All statistics of ``trial`` (see the module docstring)."""
    noise = rest_noise(trial)
    norm, dip = field_norm_dip(trial)
    pct = lambda x, p: float(np.percentile(x, p)) if len(x) else float("nan")
    return SensorStats(
        name=trial.name,
        rate_hz=trial.rate,
        rest_s=noise["rest_s"],
        gyr_noise_dps=float(np.mean(noise["gyr"])),
        acc_noise_ms2=float(np.mean(noise["acc"])),
        mag_noise_ut=float(np.mean(noise["mag"])),
        gyr_noise_axes_dps=_axes(noise["gyr"]),
        acc_noise_axes_ms2=_axes(noise["acc"]),
        mag_noise_axes_ut=_axes(noise["mag"]),
        gyr_bias_axes_dps=_axes(noise["gyr_bias"]),
        gyr_autocorr1=rest_autocorr(trial, "gyr"),
        acc_autocorr1=rest_autocorr(trial, "acc"),
        mag_autocorr1=rest_autocorr(trial, "mag"),
        mag_autocorr1_distinct=rest_autocorr(trial, "mag", distinct=True),
        mag_autocorr2_distinct=rest_autocorr(trial, "mag", lag=2, distinct=True),
        field_norm_median_ut=pct(norm, 50),
        field_norm_p05_ut=pct(norm, 5),
        field_norm_p95_ut=pct(norm, 95),
        dip_median_deg=pct(dip, 50),
        dip_p05_deg=pct(dip, 5),
        dip_p95_deg=pct(dip, 95),
        mag_lag_samples=mag_lag(trial),
        mag_truth_lag_samples=truth_lag(trial, "mag"),
        gyr_truth_lag_samples=truth_lag(trial, "gyr"),
        gyr_quantum_dps=float(np.rad2deg(quantum(trial.gyr))),
        acc_quantum_ms2=quantum(trial.acc),
        mag_quantum_ut=quantum(trial.mag),
        mag_hold_fraction=hold_fraction(trial.mag),
        mag_hold_run_mean=hold_runs(trial.mag)[0],
        mag_hold_run2_share=hold_runs(trial.mag)[1],
        gyr_hold_fraction=hold_fraction(trial.gyr),
        acc_hold_fraction=hold_fraction(trial.acc),
    )
