"""AEKF, MAGYQ and Delay MAGYQ (Combettes & Renaudin 2016) as ``Estimator``s.

``methods()`` → ``aekf``, ``magyq``, ``delay_magyq`` (read by
``magenv.registry``), plus the Policies ``qsf_detector`` (:class:`DetectorPolicy`) and ``qsf_hold``
(:class:`HoldPolicy`);
``magenv paper qsf|innovation|qsf-recordings`` prints the paper-check tables. Each runs
``magenv.filters.qsf`` with the paper's
noise settings (σ_a = 0.1 g, σ_m = 0.1 m0, §5.3) and the QSF detector's
default thresholds. ``trust`` per sample = 1 where a magnetic update ran,
else 0 (the AEKF updates on every sample). After ``run`` the estimator keeps
the per-sample QSF flag, innovation norm and correction norm of its last
trial in ``last`` (a ``magenv.filters.qsf.QSFResult``).

Initialisation (``init``, ``magenv.filters.qsf.initial_orientation``):
``"auto"`` (default) starts the hand-held scenarios from ``trial.q_true[0]``,
as the paper did from its optical reference (§5.3), and every other trial
(e.g. the real recordings) from TRIAD on the mean of the still samples at the start
(``magenv.filters.qsf.still_start``, truth-free);
``"triad"`` and ``"truth"`` force one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magenv.envs import QSF_ID as ENV_ID
from magenv.envs.qsf import AGE_SCALE_S, FEATURES
from magenv.filters import qsf
from magenv.protocols import Estimate, Tunable
from magenv.trial import Trial


@dataclass
class QSFEstimator:
    """One of the three filters.

    Attributes:
        mode: "aekf", "magyq" or "delay_magyq".
        detector: the QSF detector (ignored by the AEKF).
        init: "auto" (default), "triad" (the still start, truth-free) or "truth" (paper's protocol); see
            ``magenv.filters.qsf.initial_orientation``.
        filter_kwargs: keyword arguments of ``magenv.filters.qsf.make_params`` (e.g. sigma_gyr, sigma_mag, th_acc).
    """

    mode: str = "delay_magyq"
    detector: qsf.QSFDetector = field(default_factory=qsf.QSFDetector)
    init: str = "auto"
    filter_kwargs: dict = field(default_factory=dict)
    last: qsf.QSFResult | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.mode not in qsf.MODES:
            raise ValueError(f"unknown mode {self.mode!r}; known: {', '.join(qsf.MODES)}")
        if self.init not in qsf.INITS:
            raise ValueError(f"init must be one of {qsf.INITS}, got {self.init!r}")

    def run(self, trial: Trial) -> Estimate:
        res = qsf.run_trial(trial, mode=self.mode, detector=self.detector, init=self.init, **self.filter_kwargs)
        self.last = res
        return Estimate(q=res.q, trust=res.sig[:, qsf.SIGNAL.mag_updated].copy())


class DetectedDelayMAGYQ(Tunable, QSFEstimator):
    """Delay MAGYQ whose QSF detector thresholds are the tunable parameters (``magenv tune --rule delay_magyq``;
    defaults = ``QSFDetector``'s). ``window_s``, ``max_period_s`` in s; ``th_spread``, ``th_drift`` in µT."""

    PARAM_BOUNDS = {
        "window_s": (0.1, 2.0),
        "th_spread": (0.2, 10.0),
        "th_drift": (0.5, 20.0),
        "max_period_s": (1.0, 60.0),
    }

    def __init__(self, init: str = "auto", filter_kwargs: dict | None = None, **thresholds):
        super().__init__(
            mode="delay_magyq",
            detector=qsf.QSFDetector(**thresholds),
            init=init,
            filter_kwargs=dict(filter_kwargs or {}),
        )

    @property
    def params(self) -> dict[str, float]:
        return {k: float(getattr(self.detector, k)) for k in self.PARAM_BOUNDS}


def aekf(**kw) -> QSFEstimator:
    """Additive quaternion EKF, magnetometer = Earth field (hypothesis H0)."""
    return QSFEstimator(mode="aekf", **kw)


def magyq(**kw) -> QSFEstimator:
    """MAGYQ: QSF magnetic update, reference taken as exact (eq. 27)."""
    return QSFEstimator(mode="magyq", **kw)


def delay_magyq(**kw) -> QSFEstimator:
    """Delay MAGYQ: covariance augmented with the estimate at the period's start (eqs. 21–28)."""
    return QSFEstimator(mode="delay_magyq", **kw)


def _observed(policy: str, features: Sequence[str] | None, needed: Sequence[str]) -> tuple[dict[str, int], dict]:
    """The index of each ``needed`` feature in the observation ``features`` (None: the env's default) and the
    env options that select it; ValueError naming a missing one."""
    names = FEATURES.names if features is None else tuple(features)
    for f in needed:
        if f not in names:
            raise ValueError(f"{policy} needs the observation feature {f!r}")
    env_kwargs: dict[str, Any] = {} if features is None else {"features": list(names)}
    return {f: names.index(f) for f in needed}, env_kwargs


class DetectorPolicy:
    """The QSF detector as a policy of ``magenv/MagQSF-v0``: start where the detector starts, keep where it
    keeps (start if no period is active, or if the period has lasted the detector's ``max_period_s``), else
    no update; trust 1. With ``decision_every=1`` it reproduces the ``delay_magyq`` estimator sample for
    sample. ``detector`` (thresholds, as the env's option) and ``features`` become the env options it runs
    with (``env_kwargs``).

    The period-age restart is the detector's own rule seen at decision granularity: the detector restarts
    a period of ``max_period_s`` at one sample, which a decision every 10 samples sees 9 times in 10 as a
    plain "keep"; without this rule a period then lasts the whole trial on one reference sample (one
    draw of the magnetometer noise fixing the heading for minutes: on BROAD 02, 130 s in one period)."""

    env_id = ENV_ID

    def __init__(self, features: Sequence[str] | None = None, detector: qsf.QSFDetector | dict | None = None):
        self._i, self.env_kwargs = _observed("DetectorPolicy", features, ("det_start", "det_keep", "active", "age"))
        det = qsf.QSFDetector()
        if detector is not None:
            det = detector if isinstance(detector, qsf.QSFDetector) else qsf.QSFDetector(**detector)  # checked here
            self.env_kwargs["detector"] = dataclasses.asdict(det)
        self._max_age = det.max_period_s / AGE_SCALE_S  # in the age feature's unit

    def reset(self) -> None:
        pass

    def __call__(self, obs) -> np.ndarray:
        obs = np.asarray(obs)
        if obs[self._i["det_start"]] > 0.5:
            d = 1.0
        elif obs[self._i["det_keep"]] > 0.5:
            active = obs[self._i["active"]] > 0.5
            d = 0.0 if active and obs[self._i["age"]] < self._max_age else 1.0
        else:
            d = -1.0
        return np.array([d, 1.0], np.float32)


def tuned_detector_policy(params: dict[str, float]) -> DetectorPolicy:
    """The detector policy acting with the thresholds ``magenv tune --rule delay_magyq`` found
    (the registry's ``qsf_detector_tuned``): the env runs that detector (``env_kwargs["detector"]``)."""
    return DetectorPolicy(detector=params)


class HoldPolicy:
    """One QSF period held as long as the filter allows: start where no period is active, else keep; trust 1.
    The detector is not consulted; the filter restarts a period older than its ``max_age_s``
    (``magenv.filters.qsf.MAX_AGE_S`` by default).

    A baseline of the opposite extreme to the detector: where the walker stays in place (the paper tests'
    treadmill) the field at the sensor varies only with the hand's motion, so the reference of the first
    sample — taken with the true start orientation (§5.3) — keeps the heading for the whole period, while the
    detector's restarts lock the heading error of their moment into a new reference. On real recordings one
    reference sample's noise fixes the heading for the whole period (see :class:`DetectorPolicy`)."""

    env_id = ENV_ID

    def __init__(self, features: Sequence[str] | None = None):
        i, self.env_kwargs = _observed("HoldPolicy", features, ("active",))
        self._active = i["active"]

    def reset(self) -> None:
        pass

    def __call__(self, obs) -> np.ndarray:
        return np.array([0.0 if np.asarray(obs)[self._active] > 0.5 else 1.0, 1.0], np.float32)


def methods() -> dict:
    """Name → factory, for ``magenv.registry``: the three filters, the detector policy ``qsf_detector`` and
    ``qsf_hold``."""
    return {
        "aekf": aekf,
        "magyq": magyq,
        "delay_magyq": delay_magyq,
        "qsf_detector": DetectorPolicy,
        "qsf_hold": HoldPolicy,
    }
