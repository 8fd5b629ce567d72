"""The one metric module: orientation errors and their RMSE (degrees).

The same code scores simulated trials and real recordings, offline (numpy
arrays) and inside the filter kernels (numba: :func:`add_errors`). The error
quaternion is taken in the earth frame, ``q_err = q_est ⊗ q_true*`` (Fan et
al. 2017 eq. 19; BROAD's protocol), so its z-rotation is the heading error:

* total error ``2·acos(|w|)`` (Fan eq. 22, Δθ);
* heading error ``2·atan(|z / w|)``;
* inclination error ``2·acos(sqrt(w² + z²))``;
* ZYX Euler error (Fan eq. 21): yaw/pitch/roll of ``q_err``.

Missing truth (a NaN row of ``q_true``) is no sample: its errors are NaN and
:func:`rmse` skips them. A non-finite **estimate** is never a good score: it
counts as 180° in every part, wherever truth exists.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from magenv import quaternion as quat

WORST_DEG = 180.0  # the error charged for a non-finite estimate

# Layout of the error sums a filter kernel accumulates over the samples of one env step (``add_errors``):
# sums of total / heading / inclination error (deg), count of samples with truth, sum of the true
# disturbance norm (µT).
E_TOTAL, E_HEADING, E_INCL, E_COUNT, E_DIST = range(5)
N_ERR = 5


@njit(cache=True, inline="always")
def _parts1(ew, ez):
    """(total, heading, inclination) in degrees of an error quaternion with scalar part ``ew`` and z part ``ez``."""
    total = np.rad2deg(2.0 * np.arccos(min(1.0, abs(ew))))
    heading = np.rad2deg(2.0 * np.arctan(abs(ez / ew))) if ew != 0.0 else WORST_DEG
    incl = np.rad2deg(2.0 * np.arccos(min(1.0, np.sqrt(ew * ew + ez * ez))))
    return total, heading, incl


@njit(cache=True, inline="always")
def errors1(q, t):
    """(total, heading, inclination) error in degrees of estimate ``q`` (4,) against truth ``t`` (4,).

    NaN in all three where ``t`` has NaN (no truth); 180° in all three where ``q`` is not finite.
    """
    tw, tx, ty, tz = t[0], t[1], t[2], t[3]
    if not (np.isfinite(tw) and np.isfinite(tx) and np.isfinite(ty) and np.isfinite(tz)):
        return np.nan, np.nan, np.nan
    w, x, y, z = q[0], q[1], q[2], q[3]
    if not (np.isfinite(w) and np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
        return WORST_DEG, WORST_DEG, WORST_DEG
    ew = w * tw + x * tx + y * ty + z * tz  # scalar part of q ⊗ t*
    ez = -w * tz - x * ty + y * tx + z * tw  # z part of q ⊗ t*
    return _parts1(ew, ez)


@njit(cache=True, inline="always")
def total_error1(q, t):
    """The total error 2·acos(|w|) in degrees of estimate ``q`` (4,) against truth ``t`` (4,) alone (the first of
    :func:`errors1`, for look-ahead costs): NaN where ``t`` has NaN, 180° where ``q`` is not finite."""
    if not (np.isfinite(t[0]) and np.isfinite(t[1]) and np.isfinite(t[2]) and np.isfinite(t[3])):
        return np.nan
    w = q[0] * t[0] + q[1] * t[1] + q[2] * t[2] + q[3] * t[3]
    if not np.isfinite(w):
        return WORST_DEG
    return np.rad2deg(2.0 * np.arccos(min(1.0, abs(w))))


@njit(cache=True, inline="always")
def add_errors(err, q, t, dist):
    """Add one sample to the error sums ``err`` (N_ERR,): estimate ``q`` (4,) against truth ``t`` (4,)
    (skipped where truth is missing, :func:`errors1`); ``dist`` (µT) is summed always."""
    total, heading, incl = errors1(q, t)
    if total == total:
        err[E_TOTAL] += total
        err[E_HEADING] += heading
        err[E_INCL] += incl
        err[E_COUNT] += 1.0
    err[E_DIST] += dist


@njit(cache=True)
def error_sums(est, q_true, dist, start, stop, err, est_row=0, true_row=0):
    """Reset ``err`` (N_ERR,) to the error sums of samples ``start … stop−1`` of ``est`` (N, 4) against
    ``q_true`` (N, 4) and ``dist`` (N,), sample i on row ``est_row + i`` of ``est`` and ``true_row + i`` of the
    truth (a batch's arrays read in place)."""
    for k in range(N_ERR):
        err[k] = 0.0
    for i in range(start, stop):  # rows as tuples: a view costs two atomic reference counts
        r, t = est_row + i, true_row + i
        q = (est[r, 0], est[r, 1], est[r, 2], est[r, 3])
        add_errors(err, q, (q_true[t, 0], q_true[t, 1], q_true[t, 2], q_true[t, 3]), dist[t])


@njit(cache=True)
def squared_totals(est, q_true, start, stop) -> float:
    """Σ of the squared total errors (°²) of ``est`` (N, 4) against ``q_true`` (N, 4) over samples
    ``start … stop−1``, samples without truth skipped (:func:`errors1`): the oracles' look-ahead cost."""
    cost = 0.0
    for i in range(start, stop):
        total = errors1(est[i], q_true[i])[0]
        if total == total:
            cost += total * total
    return cost


# Layout of a step's means (``step_means``): the reward and the errors ``info`` reports.
S_REWARD, S_TOTAL, S_HEADING, S_INCL, S_DIST = range(5)
N_STEP = 5


@njit(cache=True)
def step_means(err, fused, has_dist, out):
    """Write ``out`` (N_STEP,) from one step's error sums ``err`` (N_ERR,) over ``fused`` samples: the mean total,
    heading and inclination errors (°) over the samples with truth (NaN if none had truth), the mean true
    disturbance norm (µT; NaN unless ``has_dist``) and the reward, −(mean total error), 0 if no sample had
    truth. The one definition of the reward: the single env calls it on its runner's sums, the batched vector
    env on each env's (:func:`step_means_rows`)."""
    cnt = err[E_COUNT]
    if cnt > 0:
        out[S_TOTAL] = err[E_TOTAL] / cnt
        out[S_HEADING] = err[E_HEADING] / cnt
        out[S_INCL] = err[E_INCL] / cnt
        out[S_REWARD] = -out[S_TOTAL]
    else:
        out[S_TOTAL] = out[S_HEADING] = out[S_INCL] = np.nan
        out[S_REWARD] = 0.0
    out[S_DIST] = err[E_DIST] / fused if has_dist else np.nan


@njit(cache=True)
def step_means_rows(err, fused, has_dist, out):
    """:func:`step_means` of each row: ``err`` (n, N_ERR), ``fused`` (n,), ``has_dist`` (n,), ``out`` (n, N_STEP)."""
    for i in range(err.shape[0]):
        step_means(err[i], fused[i], has_dist[i], out[i])


@njit(cache=True)
def _error_rows(q_est, q_true, out):
    for i in range(q_est.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = errors1(q_est[i], q_true[i])


@njit(cache=True)
def _parts_rows(q_err, out):
    for i in range(q_err.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _parts1(q_err[i, 0], q_err[i, 3])


def errors(q_est, q_true) -> np.ndarray:
    """(..., 3) [total, heading, inclination] error in degrees of estimates against truth (..., 4), broadcast;
    NaN rows where truth is missing, 180° where the estimate is not finite (:func:`errors1`)."""
    q_est, q_true = np.broadcast_arrays(np.asarray(q_est, float), np.asarray(q_true, float))
    out = np.empty(q_est.shape[:-1] + (3,))
    _error_rows(
        np.ascontiguousarray(q_est.reshape(-1, 4)), np.ascontiguousarray(q_true.reshape(-1, 4)), out.reshape(-1, 3)
    )
    return out


def _parts(q_err) -> np.ndarray:
    q_err = np.asarray(q_err, float)
    out = np.empty(q_err.shape[:-1] + (3,))
    _parts_rows(np.ascontiguousarray(q_err.reshape(-1, 4)), out.reshape(-1, 3))
    return out


def error_quaternion(q_est, q_true) -> np.ndarray:
    """(..., 4) earth-frame error ``q_est ⊗ q_true*``; NaN where truth is NaN."""
    return quat.mul(np.asarray(q_est, float), quat.conj(np.asarray(q_true, float)))


def total_error(q_err) -> np.ndarray:
    """Total orientation error Δθ, degrees, of error quaternions (..., 4) (NaN stays NaN; use :func:`errors`
    to score estimates, which charges a non-finite estimate 180°)."""
    return _parts(q_err)[..., 0]


def heading_error(q_err) -> np.ndarray:
    """Heading (about earth z) part of the error, degrees, of error quaternions (..., 4)."""
    return _parts(q_err)[..., 1]


def inclination_error(q_err) -> np.ndarray:
    """Inclination (tilt) part of the error, degrees, of error quaternions (..., 4)."""
    return _parts(q_err)[..., 2]


def euler_error(q_est, q_true) -> np.ndarray:
    """ZYX Euler error (..., 3) = [yaw, pitch, roll], degrees (Fan eq. 21)."""
    return np.rad2deg(quat.to_euler_zyx(error_quaternion(q_est, q_true)))


def rmse(err, mask=None) -> float:
    """Root mean square of ``err`` over ``mask`` (all if None), skipping NaN (samples without truth)."""
    err = np.asarray(err, float)
    keep = ~np.isnan(err)
    if mask is not None:
        keep &= np.asarray(mask, bool)
    if not np.any(keep):
        return float("nan")
    return float(np.sqrt(np.mean(err[keep] ** 2)))


@dataclass(frozen=True)
class Score:
    """RMSE of one estimate against truth, degrees."""

    total: float
    heading: float
    inclination: float


def score(q_est, q_true, mask=None) -> Score:
    """RMSE of total / heading / inclination error over ``mask`` (the trial's score mask)."""
    e = errors(q_est, q_true)
    return Score(total=rmse(e[..., 0], mask), heading=rmse(e[..., 1], mask), inclination=rmse(e[..., 2], mask))
