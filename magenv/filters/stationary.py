"""Causal stationary detection, Fan et al. 2017 eqs. 11–13.

A sample t is stationary when, on every axis,

* |a_t − a_{t−t0}| < th_a          (eq. 11; th_a = k·a_pp, eq. 12)
* |ω_t| < th_gyro                   (eq. 13)

Paper values: t0 = 0.5 s, th_a = 0.04 g, th_gyro = 0.5 °/s. Until t0 of
history exists, no sample is stationary.

Streaming form: :class:`State` holds the last ``L = round(t0·rate)``
accelerometer samples and two counters. ``peek1`` evaluates the criterion
for a new sample without storing it; ``step1`` evaluates and stores.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.checks import check_number
from magenv.quaternion import GRAVITY

T0_S = 0.5  # s, eq. 11 interval
TH_ACC_G = 0.04  # g, eq. 12
TH_GYRO_DPS = 0.5  # °/s, eq. 13
T0_MAX_S = 60.0  # s, the longest eq. 11 interval accepted (its ring buffer holds t0·rate samples)


class State(NamedTuple):
    """Detector state (arrays, updated in place by :func:`step1`)."""

    buf: np.ndarray  # (L, 3) m/s², ring buffer of the last L accelerometer samples, L = round(t0·rate)
    ctr: np.ndarray  # (2,) int64: [next write position in buf, samples seen]


def make_state(rate: float, t0: float = T0_S) -> State:
    """Empty detector state for ``rate`` Hz and interval ``t0`` s ∈ [0, ``T0_MAX_S``]."""
    t0 = check_number("t0", t0, 0.0, T0_MAX_S)
    length = max(1, int(round(t0 * check_number("rate", rate, 0.0, lo_open=True))))
    return State(np.zeros((length, 3)), np.zeros(2, np.int64))


def thresholds(th_acc_g: float = TH_ACC_G, th_gyro_dps: float = TH_GYRO_DPS) -> tuple[float, float]:
    """Thresholds in SI units: (m/s², rad/s), from finite ``th_acc_g`` g ≥ 0 and ``th_gyro_dps`` °/s ≥ 0."""
    return check_number("th_acc_g", th_acc_g, 0.0) * GRAVITY, np.deg2rad(check_number("th_gyro_dps", th_gyro_dps, 0.0))


@njit(cache=True, inline="always")
def peek1(state, acc, gyr, th_a, th_gyro):
    """Eqs. 11 and 13 for a new sample (acc m/s², gyr rad/s) against the sample t0 ago; no state change.

    th_a: m/s² (eq. 12), th_gyro: rad/s (eq. 13), both per axis.
    """
    buf, ctr = state.buf, state.ctr
    length = buf.shape[0]
    if ctr[1] < length:
        return False
    old = buf[ctr[0]]  # oldest stored sample = a_{t − t0}
    for k in range(3):
        if abs(gyr[k]) >= th_gyro:
            return False
        if abs(acc[k] - old[k]) >= th_a:
            return False
    return True


@njit(cache=True, inline="always")
def step1(state, acc, gyr, th_a, th_gyro):
    """Evaluate the new sample (as :func:`peek1`), then store its acc in the ring buffer."""
    still = peek1(state, acc, gyr, th_a, th_gyro)
    buf, ctr = state.buf, state.ctr
    pos = ctr[0]
    buf[pos, 0] = acc[0]
    buf[pos, 1] = acc[1]
    buf[pos, 2] = acc[2]
    ctr[0] = pos + 1 if pos + 1 < buf.shape[0] else 0
    ctr[1] += 1
    return still


@njit(cache=True)
def _detect(state, acc, gyr, th_a, th_gyro):
    out = np.empty(acc.shape[0], np.bool_)
    for i in range(acc.shape[0]):
        out[i] = step1(state, acc[i], gyr[i], th_a, th_gyro)
    return out


def detect(
    acc, gyr, rate: float, t0: float = T0_S, th_acc_g: float = TH_ACC_G, th_gyro_dps: float = TH_GYRO_DPS
) -> np.ndarray:
    """(N,) bool stationary flags of whole arrays acc (N, 3) m/s², gyr (N, 3) rad/s, streamed causally."""
    th_a, th_g = thresholds(th_acc_g, th_gyro_dps)
    return _detect(make_state(rate, t0), np.ascontiguousarray(acc, float), np.ascontiguousarray(gyr, float), th_a, th_g)
