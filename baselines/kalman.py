"""The survey's four Kalman estimators (Ligorio & Sabatini 2016, Figure 3) as Estimators.

* ``th_triad``, ``th_quest``: threshold-based quaternion KF with vector
  selector (Lee & Park 2009, survey A.1), TRIAD or QUEST measurement.
  ``trust`` = 1 where the magnetometer sample was accepted, 0 where it was
  replaced by its prediction (A8).
* ``mod_triad``, ``mod_quest``: model-based split of acc and mag by
  Gauss–Markov KFs (Ligorio & Sabatini 2015, survey A.2), then TRIAD or QUEST.
  ``trust`` = the Kalman gain with which each magnetometer sample moved the
  Earth-field estimate (mean diagonal of the gain block, 0…1).

Defaults are the survey's: sensor noise gyro 0.5 °/s, acc 0.02 m/s², mag
0.15 µT; Table A1 thresholds 0.08 m/s², 1.20 µT, 5°; c_a = 0.1, c_b = 1. The
site's m0 and θ0 come from each Trial (``field_norm``, ``field_dip``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from magenv.filters.kalman_model import ModelKF
from magenv.filters.kalman_threshold import ThresholdKF
from magenv.protocols import Estimate
from magenv.trial import Trial


@dataclass
class ThresholdEstimator:
    """th-TRIAD / th-QUEST; ``kf`` holds every tunable (see ThresholdKF)."""

    kf: ThresholdKF = field(default_factory=ThresholdKF)

    def run(self, trial: Trial) -> Estimate:
        res = self.kf.run(trial)
        return Estimate(q=res.q, trust=res.mag_ok.astype(float))


@dataclass
class ModelEstimator:
    """mod-TRIAD / mod-QUEST; ``kf`` holds every tunable (see ModelKF)."""

    kf: ModelKF = field(default_factory=ModelKF)

    def run(self, trial: Trial) -> Estimate:
        res = self.kf.run(trial)
        return Estimate(q=res.q, trust=res.gain_mag)


def th_triad(**kw) -> ThresholdEstimator:
    """Threshold-based KF, TRIAD measurement (keyword arguments go to ThresholdKF)."""
    return ThresholdEstimator(ThresholdKF(solver="triad", **kw))


def th_quest(**kw) -> ThresholdEstimator:
    """Threshold-based KF, QUEST measurement — Lee & Park 2009 as published."""
    return ThresholdEstimator(ThresholdKF(solver="quest", **kw))


def mod_triad(**kw) -> ModelEstimator:
    """Model-based KF, TRIAD — Ligorio & Sabatini 2015 as published."""
    return ModelEstimator(ModelKF(solver="triad", **kw))


def mod_quest(**kw) -> ModelEstimator:
    """Model-based KF, QUEST."""
    return ModelEstimator(ModelKF(solver="quest", **kw))


def methods() -> dict:
    """Name → factory of the four survey combinations, for ``compare``."""
    return {"th_triad": th_triad, "th_quest": th_quest, "mod_triad": mod_triad, "mod_quest": mod_quest}
