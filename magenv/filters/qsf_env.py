"""Runner of ``magenv/MagQSF-v0``: MAGYQ / Delay MAGYQ stepped k samples at a time, plus observation features.

:class:`QSFRunner` holds one trial, the filter state of ``magenv.filters.qsf``
and the QSF detector's codes and spread (computed once at reset: they depend
on the sensors only, row j on samples ≤ j). ``advance`` fuses the next
samples with one decision (none / start / keep) and one trust, accumulates
the error sums against truth (``magenv.metrics.error_sums``) and
computes the features of the next sample j (read before it is fused).

Features are dimensionless so that one scale suits every site: field
quantities in units of the filter's magnetometer noise σ_m (µT) or of the
detector threshold, the dip deviation in units of 90°, the gyro in
revolutions per second (the heading std stays in rad). Table with meanings: ``magenv.envs.qsf.MagQSFEnv``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from magenv.filters import qsf
from magenv.filters.common import TrialRunner
from magenv.metrics import N_ERR, error_sums
from magenv.quaternion import GRAVITY, rotate1
from magenv.trial import Trial

DIP_SCALE_DEG = 90.0  # dip deviations in units of 90°
GYRO_SCALE = 2.0 * np.pi  # rad/s; gyro norm in revolutions per second
AGE_SCALE_S = 10.0  # period age in units of 10 s
FEATURES: tuple[tuple[str, float, float], ...] = (
    ("spread", 0.0, 100.0),  # detector spread at j / th_spread (0 while its window fills)
    ("det_start", 0.0, 1.0),  # the detector would start a period at j
    ("det_keep", 0.0, 1.0),  # the detector would keep its period at j
    ("ref_mismatch", 0.0, 100.0),  # |m_ref − q̂ m_j q̂*| / σ_m (0 without period)
    ("innov_norm", 0.0, 100.0),  # |δz| of the last fused sample / σ_m
    ("log_nis", 0.0, 10.0),  # log10(1 + δzᵀS⁻¹δz) of the last fused sample
    ("age", 0.0, 100.0),  # time since the current period started / 10 s (0 without period)
    ("active", 0.0, 1.0),  # a QSF period is active
    ("gyro_norm", 0.0, 10.0),  # |ω_j| / (2π rad/s)
    ("acc_dev", -1.0, 10.0),  # (|a_j| − g)/g
    ("mag_norm_dev", -1.0, 20.0),  # (|m_j| − m0)/m0
    ("dip_dev", -2.0, 2.0),  # (dip of q̂ m_j q̂* − θ0)/90°
    ("heading_std", 0.0, 10.0),  # sqrt of the filter's heading variance, rad
    ("trust_prev", 0.0, 1.0),  # trust applied in the last step (0 after reset)
)
FEATURE_NAMES: tuple[str, ...] = tuple(f[0] for f in FEATURES)
N_FEATURES = len(FEATURES)
FEATURE_LOW = np.array([f[1] for f in FEATURES], np.float32)
FEATURE_HIGH = np.array([f[2] for f in FEATURES], np.float32)
VARIANTS = ("delay_magyq", "magyq")


class QSFRunner(TrialRunner):
    """One trial under MAGYQ / Delay MAGYQ with per-step decisions (the ``MagQSF-v0`` runner).

    Args:
        trial: the trial (any sensor trial).
        variant: "delay_magyq" or "magyq".
        detector: the QSF detector whose codes and spread the features report.
        init: the start, ``magenv.filters.qsf.initial_orientation`` ("auto", "triad" or "truth").
        filter_kwargs: keywords of ``magenv.filters.qsf.make_params``.

    Attributes as the other runners (``magenv.envs.common.TrustEnv``): ``feat``, ``err``, ``pos``,
    ``last_count``, ``has_dist``, ``est`` (N, 4), ``q_true``; and ``sig`` (N, NSIG) the filter's signals,
    ``actions`` (N,) the magnetic action codes used, ``trusts`` (N,) the trust per sample.
    """

    def __init__(self, trial: Trial, variant: str = "delay_magyq", detector: qsf.QSFDetector | None = None,
                 init: str = "auto", filter_kwargs: dict | None = None):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.trial = trial
        self.params = qsf.make_params(trial.field_norm, trial.field_dip, mode=variant, **(filter_kwargs or {}))
        self.detector = detector or qsf.QSFDetector()
        self.codes, spread = self.detector.detect(trial.gyr, trial.mag, trial.rate)
        self.spread = np.nan_to_num(spread, nan=0.0) / self.detector.th_spread
        self.x, self.pa, self.ref = qsf.initial_state(qsf.initial_orientation(trial, init, self.params), trial.dt)
        n = trial.n
        self.q_true = trial.q_true
        dist = trial.truth.get("mag_disturbance")
        self.has_dist = dist is not None
        self.dist = np.ascontiguousarray(np.linalg.norm(np.asarray(dist, float), axis=-1) if self.has_dist
                                         else np.zeros(n))
        self.est = np.full((n, 4), np.nan)
        self.sig = np.zeros((n, qsf.NSIG))
        self.actions = np.zeros(n, np.int8)
        self.trusts = np.zeros(n)
        self.err = np.zeros(N_ERR)
        self.pos = 0
        self.last_count = 0
        self.trust_prev = 0.0
        self.feat = np.zeros(N_FEATURES)
        self._features()

    def advance(self, count: int, code: int, trust: float) -> int:
        """Fuse the next ``count`` samples (fewer at the end): ``code`` MAG_START starts a period at the first
        of them and keeps it for the rest, MAG_KEEP keeps, MAG_NONE makes no magnetic update (and ends any
        period); ``trust`` ∈ [0, 1] scales every magnetic gain. Returns the samples fused."""
        tr = self.trial
        i0, i1 = self.pos, min(tr.n, self.pos + int(count))
        self.actions[i0:i1] = qsf.MAG_NONE if code == qsf.MAG_NONE else qsf.MAG_KEEP
        if code == qsf.MAG_START and i1 > i0:
            self.actions[i0] = qsf.MAG_START
        self.trusts[i0:i1] = trust
        qsf.run(self.x, self.pa, self.ref, tr.gyr, tr.acc, tr.mag, tr.dt, i0, i1, self.actions, self.trusts,
                self.params, self.est, self.sig)
        error_sums(self.est, self.q_true, self.dist, i0, i1, self.err)
        self.pos, self.last_count, self.trust_prev = i1, i1 - i0, float(trust)
        self._features()
        return self.last_count

    def _features(self) -> None:
        """Features of sample j = pos (the last sample once all are fused) and of the last fused sample."""
        tr, p = self.trial, self.params
        j = min(self.pos, tr.n - 1)
        q = self.x[0:4]
        last = self.sig[self.pos - 1] if self.pos > 0 else np.zeros(qsf.NSIG)
        active = self.ref[0] > 0.5
        m_e = rotate1(q, tr.mag[j])
        sigma_m = p[qsf.P_SM]
        mismatch = float(np.linalg.norm(self.ref[6:9] - m_e)) / sigma_m if active else 0.0
        nm = float(np.linalg.norm(tr.mag[j]))
        dip = math.degrees(math.asin(max(-1.0, min(1.0, -m_e[2] / nm)))) if nm > 0 else tr.field_dip
        f = self.feat
        f[:] = (self.spread[j], float(self.codes[j] == qsf.MAG_START), float(self.codes[j] == qsf.MAG_KEEP),
                mismatch, last[1] / sigma_m, math.log10(1.0 + last[2]),
                (self.ref[1] / AGE_SCALE_S) if active else 0.0, float(active),
                float(np.linalg.norm(tr.gyr[j])) / GYRO_SCALE, (float(np.linalg.norm(tr.acc[j])) - GRAVITY) / GRAVITY,
                (nm - tr.field_norm) / tr.field_norm, (dip - tr.field_dip) / DIP_SCALE_DEG, last[6], self.trust_prev)
        np.clip(f, FEATURE_LOW, FEATURE_HIGH, out=f)
