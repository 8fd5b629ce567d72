"""Pieces the env filters share: the layout of a step's error sums, their accumulation, the runners' base."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from magenv.trial import Trial

# err vector layout: sums over the interval of total / heading / inclination error (deg),
# count of samples with truth, sum of the true disturbance norm (µT)
E_TOTAL, E_HEADING, E_INCL, E_COUNT, E_DIST = range(5)
N_ERR = 5


@njit(cache=True, inline="always")
def add_errors(err, w, x, y, z, q_true_i, dist_i):
    """Add one sample to ``err``: errors of estimate (w, x, y, z) against ``q_true_i`` (4,) (skipped if NaN).

    Definitions as ``magenv.metrics`` (e = q ⊗ q_true*, degrees); ``dist_i`` (µT) is summed always.
    """
    tw, tx, ty, tz = q_true_i[0], q_true_i[1], q_true_i[2], q_true_i[3]
    if tw == tw:
        ew = w * tw + x * tx + y * ty + z * tz
        ez = -w * tz - x * ty + y * tx + z * tw
        err[E_TOTAL] += np.rad2deg(2.0 * np.arccos(min(1.0, abs(ew))))
        err[E_HEADING] += np.rad2deg(2.0 * np.arctan(abs(ez / ew))) if ew != 0.0 else 180.0
        err[E_INCL] += np.rad2deg(2.0 * np.arccos(min(1.0, np.sqrt(ew * ew + ez * ez))))
        err[E_COUNT] += 1.0
    err[E_DIST] += dist_i


class TrialRunner:
    """Base of the env runners (one trial stepped k samples at a time): ``trial``, ``pos`` (next sample to fuse)."""

    trial: Trial
    pos: int

    @property
    def n(self) -> int:
        """Samples in the trial."""
        return self.trial.n

    @property
    def done(self) -> bool:
        """All samples fused."""
        return self.pos >= self.trial.n
