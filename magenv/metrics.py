"""The one metric module: orientation errors and their RMSE (degrees).

The same code scores simulated trials and real recordings. The error
quaternion is taken in the earth frame, ``q_err = q_est ⊗ q_true*`` (Fan et
al. 2017 eq. 19; BROAD's protocol), so its z-rotation is the heading error:

* total error ``2·acos(|w|)`` (Fan eq. 22, Δθ);
* heading error ``2·atan(|z / w|)``;
* inclination error ``2·acos(sqrt(w² + z²))``;
* ZYX Euler error (Fan eq. 21): yaw/pitch/roll of ``q_err``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magenv import quaternion as quat


def error_quaternion(q_est, q_true) -> np.ndarray:
    """(..., 4) earth-frame error ``q_est ⊗ q_true*``; NaN where truth is NaN."""
    return quat.mul(np.asarray(q_est, float), quat.conj(np.asarray(q_true, float)))


def total_error(q_err) -> np.ndarray:
    """Total orientation error Δθ, degrees, of error quaternions (..., 4)."""
    w = np.abs(np.asarray(q_err)[..., 0])
    return np.rad2deg(2.0 * np.arccos(np.clip(w, 0.0, 1.0)))


def heading_error(q_err) -> np.ndarray:
    """Heading (about earth z) part of the error, degrees."""
    q_err = np.asarray(q_err)
    return np.rad2deg(2.0 * np.arctan(np.abs(q_err[..., 3] / q_err[..., 0])))


def inclination_error(q_err) -> np.ndarray:
    """Inclination (tilt) part of the error, degrees."""
    q_err = np.asarray(q_err)
    wz = np.sqrt(q_err[..., 0] ** 2 + q_err[..., 3] ** 2)
    return np.rad2deg(2.0 * np.arccos(np.clip(wz, 0.0, 1.0)))


def euler_error(q_est, q_true) -> np.ndarray:
    """ZYX Euler error (..., 3) = [yaw, pitch, roll], degrees (Fan eq. 21)."""
    return np.rad2deg(quat.to_euler_zyx(error_quaternion(q_est, q_true)))


def rmse(err, mask=None) -> float:
    """Root mean square of ``err`` over ``mask`` (all if None), ignoring NaN."""
    err = np.asarray(err, float)
    keep = np.isfinite(err)
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
    q_err = error_quaternion(q_est, q_true)
    return Score(
        total=rmse(total_error(q_err), mask),
        heading=rmse(heading_error(q_err), mask),
        inclination=rmse(inclination_error(q_err), mask),
    )
