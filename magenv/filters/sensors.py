"""A trial's sensor stream as the filter kernels read it: one named tuple of arrays.

Kernels that run over many samples take a :class:`Sensors` instead of three
array arguments. A batched env can hold N trials' streams as N of these.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from magenv.trial import Trial


class Sensors(NamedTuple):
    """Sensor arrays of one trial, N rows at the trial's rate, sensor frame, C-contiguous float64."""

    gyr: np.ndarray  # (N, 3) angular rate, rad/s
    acc: np.ndarray  # (N, 3) specific force, m/s²
    mag: np.ndarray  # (N, 3) magnetic field, µT

    @classmethod
    def of(cls, trial: Trial) -> Sensors:
        """The sensor arrays of ``trial`` (the trial's own arrays, not copies)."""
        return cls(trial.gyr, trial.acc, trial.mag)
