"""AEKF, MAGYQ and Delay MAGYQ (Combettes & Renaudin 2016) as ``Estimator``s.

``methods()`` → ``aekf``, ``magyq``, ``delay_magyq`` (found by
``baselines.registry``), plus the Policy ``qsf_detector`` once
``magenv/MagQSF-v0`` is registered. ``python -m baselines.qsf paper|innovation|real``
prints the paper-check tables. Each runs ``magenv.filters.qsf`` with the paper's
noise settings (σ_a = 0.1 g, σ_m = 0.1 m0, §5.3) and the QSF detector's
default thresholds. ``trust`` per sample = 1 where a magnetic update ran,
else 0 (the AEKF updates on every sample). After ``run`` the estimator keeps
the per-sample QSF flag, innovation norm and correction norm of its last
trial in ``last`` (a ``magenv.filters.qsf.QSFResult``).

Initialisation (``init``, ``magenv.filters.qsf.initial_orientation``):
``"auto"`` (default) starts the hand-held scenarios from ``trial.q_true[0]``,
as the paper did from its optical reference (§5.3), and every other trial
(e.g. the real recordings) from TRIAD on the first sample (truth-free);
``"triad"`` and ``"truth"`` force one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from baselines.protocol import Estimate, Tunable
from magenv.filters import qsf
from magenv.trial import Trial


@dataclass
class QSFEstimator:
    """One of the three filters.

    Attributes:
        mode: "aekf", "magyq" or "delay_magyq".
        detector: the QSF detector (ignored by the AEKF).
        init: "auto" (default), "triad" (first sample, truth-free) or "truth" (paper's protocol); see
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
        return Estimate(q=res.q, trust=res.sig[:, qsf.SIGNALS.index("mag_updated")].copy())


class DetectedDelayMAGYQ(Tunable, QSFEstimator):
    """Delay MAGYQ whose QSF detector thresholds are the tunable parameters (``magenv tune --rule delay_magyq``;
    defaults = ``QSFDetector``'s). ``window_s``, ``max_period_s`` in s; ``th_spread``, ``th_drift`` in µT."""

    PARAM_BOUNDS = {"window_s": (0.1, 2.0), "th_spread": (0.2, 10.0), "th_drift": (0.5, 20.0),
                    "max_period_s": (1.0, 60.0)}

    def __init__(self, init: str = "auto", filter_kwargs: dict | None = None, **thresholds):
        super().__init__(mode="delay_magyq", detector=qsf.QSFDetector(**thresholds), init=init,
                         filter_kwargs=dict(filter_kwargs or {}))

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


def qsf_detector_policy():
    """The QSF detector as a Policy of ``magenv/MagQSF-v0`` (start / keep / none, trust 1)."""
    from magenv.envs.qsf import DetectorPolicy

    return DetectorPolicy()


def qsf_detector_tuned_policy():
    """The detector policy acting with the thresholds ``magenv tune --rule delay_magyq`` found
    (``baselines/tuned/delay_magyq.json``): the env runs that detector (``env_kwargs["detector"]``)."""
    from baselines.registry import tuned_params

    from magenv.envs.qsf import DetectorPolicy

    return DetectorPolicy(detector=tuned_params("delay_magyq"))


def methods() -> dict:
    """Name → factory, for ``baselines.registry``; ``qsf_detector`` (a Policy) once ``magenv/MagQSF-v0`` is
    registered, and ``qsf_detector_tuned`` once the detector has been tuned."""
    import gymnasium as gym

    from baselines.registry import TUNED_DIR

    out = {"aekf": aekf, "magyq": magyq, "delay_magyq": delay_magyq}
    if "magenv/MagQSF-v0" in gym.registry:
        out["qsf_detector"] = qsf_detector_policy
        if (TUNED_DIR / "delay_magyq.json").is_file():
            out["qsf_detector_tuned"] = qsf_detector_tuned_policy
    return out


# ------------------------------------------------------------ paper check (python -m baselines.qsf)

PAPER_TABLE1 = {  # Table 1, texting, (μ, σ) in degrees: roll, pitch, yaw
    "aekf": ((0.6, 0.5), (1.8, 0.6), (6.7, 4.7)),
    "magyq": ((1.8, 1.1), (2.7, 1.8), (6.5, 4.4)),
    "delay_magyq": ((1.0, 0.9), (1.6, 1.3), (6.2, 4.7)),
}
PAPER_YAW_ALL = {"aekf": 16.4, "magyq": 12.7, "delay_magyq": 11.7}  # mean yaw error over all data, degrees


def _euler_errors(trials, method) -> np.ndarray:
    from magenv import metrics

    out = []
    for tr in trials:
        est = method.run(tr)
        e = metrics.euler_error(est.q, tr.q_true)[tr.score_mask]
        out.append(e[np.all(np.isfinite(e), axis=1)])
    return np.concatenate(out)  # (M, 3) yaw, pitch, roll


def paper_check(seeds=(0, 1, 2, 3), free_seeds=(0,), **params) -> str:
    """The three filters on the three §5.2 scenarios (init from truth, as §5.3), Markdown tables.

    μ = |mean signed error|, σ = its standard deviation, as the paper's tables; ``mean|·|`` beside.
    Seeds play the paper's subjects (four for texting and swinging, one for the free walk). ``params`` go to
    ``magenv.filters.qsf.make_params`` (e.g. ``sigma_acc=3.0`` for the sensitivity run).
    """
    from magenv import handheld_scenarios as hs

    sig = dict(params)
    groups = {"handheld_texting": seeds, "handheld_swinging": seeds, "handheld_free": free_seeds,
              "handheld_corridor": seeds}  # the last is not in the paper: walking *through* the field
    ests = {"aekf": aekf, "magyq": magyq, "delay_magyq": delay_magyq}
    lines, pooled = [], {m: [] for m in ests}
    for name, sd in groups.items():
        trials = [hs.make_trial(name, s) for s in sd]
        lines += [f"\n### {name} (seeds {list(sd)})\n", "| method | roll μ | roll σ | pitch μ | pitch σ | yaw μ | yaw σ "
                  "| mean abs yaw | paper roll μ/σ | paper pitch μ/σ | paper yaw μ/σ |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for m, factory in ests.items():
            e = _euler_errors(trials, factory(init="truth", filter_kwargs=sig))
            if name != "handheld_corridor":
                pooled[m].append(e[:, 0])
            yaw, pitch, roll = e[:, 0], e[:, 1], e[:, 2]
            paper = PAPER_TABLE1[m] if name == "handheld_texting" else (("–", "–"),) * 3
            cells = [f"{abs(v.mean()):.1f} | {v.std():.1f}" for v in (roll, pitch, yaw)]
            pcells = [f"{a}/{b}" for a, b in paper]
            lines.append(f"| {m} | {' | '.join(cells)} | {np.abs(yaw).mean():.1f} | {' | '.join(pcells)} |")
    lines += ["\n### yaw over all data of the three paper scenarios\n", "| method | mean abs yaw | yaw μ | yaw σ | paper mean yaw |", "|---|---|---|---|---|"]
    for m, parts in pooled.items():
        y = np.concatenate(parts)
        lines.append(f"| {m} | {np.abs(y).mean():.1f} | {abs(y.mean()):.1f} | {y.std():.1f} | {PAPER_YAW_ALL[m]} |")
    return "\n".join(lines)


def innovation_check(seeds=range(5), seconds=20.0) -> str:
    """§5.5: a static MIMU inside a steady perturbed field, one QSF period from the first sample, both
    filters started at truth; mean norm of the quaternion correction K·δz per seed."""
    from magenv import quaternion as quat
    from magenv.filters.qsf import MAG_KEEP, MAG_START, SIGNALS, run_trial

    rows = ["| seed | MAGYQ mean abs(Kδz) | Delay MAGYQ mean abs(Kδz) | ratio |", "|---|---|---|---|"]
    for seed in seeds:
        rng = np.random.default_rng(seed)
        n, rate = int(seconds * 100), 100.0
        q = np.tile(quat.from_euler_zyx(*rng.uniform(-1, 1, 3)), (n, 1))
        field = quat.earth_field(47.0, 61.0) + rng.uniform(-15, 15, 3)
        gyr = rng.normal(0, np.deg2rad(0.1), (n, 3)) + rng.normal(0, np.deg2rad(0.3), 3)
        acc = quat.rotate_inv(q, np.tile(quat.gravity_up(), (n, 1))) + rng.normal(0, 0.03, (n, 3))
        mag = quat.rotate_inv(q, np.tile(field, (n, 1))) + rng.normal(0, 0.3, (n, 3))
        tr = Trial(f"static#{seed}", rate, gyr, acc, mag, q, 47.0, 61.0)
        act = np.full(n, MAG_KEEP, np.int8)
        act[0] = MAG_START
        c = [run_trial(tr, mode=m, q0=q[0], actions=act, max_age_s=1e6).sig[1:, SIGNALS.index("corr_norm")].mean()
             for m in ("magyq", "delay_magyq")]
        rows.append(f"| {seed} | {c[0]:.2e} | {c[1]:.2e} | {c[1] / c[0]:.2f} |")
    return "\n".join(rows)


def real_data_check(folder=None) -> str:
    """The three filters (TRIAD init, truth-free) and VQF on the BROAD recordings: RMSE total / heading, °.

    The detector's thresholds follow the recording's magnetometer noise (``QSFDetector.for_noise``): BROAD's
    ≈ 0.7 µT per axis is above the simulated sensor's 0.3 µT that the default thresholds assume."""
    from baselines.reference import VQFEstimator
    from magenv import metrics
    from magenv.recordings import list_recordings, load_recording

    ests = {"aekf": aekf, "magyq": magyq, "delay_magyq": delay_magyq}
    rows = ["| recording | " + " | ".join(f"{m} tot/head" for m in (*ests, "vqf")) + " | mag noise µT "
            "| QSF share (delay) |", "|---|" + "---|" * (len(ests) + 3)]
    for path in list_recordings(folder):
        tr = load_recording(path)
        # detector thresholds from the magnetometer noise over the first 2 s (the initial rest, truth-free)
        noise = float(np.median(tr.mag[: int(2 * tr.rate)].std(axis=0)))
        det = qsf.QSFDetector.for_noise(noise)
        ms = {**{m: f(detector=det) for m, f in ests.items()}, "vqf": VQFEstimator()}
        cells = []
        for m, est in ms.items():
            s = metrics.score(est.run(tr).q, tr.q_true, tr.score_mask)
            cells.append(f"{s.total:.1f}/{s.heading:.1f}")
        share = ms["delay_magyq"].last.sig[:, 0].mean()
        rows.append(f"| {path.stem} | {' | '.join(cells)} | {noise:.2f} | {share:.2f} |")
    return "\n".join(rows)


if __name__ == "__main__":
    import sys

    what = sys.argv[1] if len(sys.argv) > 1 else "paper"
    if what == "paper":  # extra arguments: make_params keywords, e.g. sigma_acc=3.0
        print(paper_check(**{k: float(v) for k, v in (a.split("=") for a in sys.argv[2:])}))
    elif what == "innovation":
        print(innovation_check())
    elif what == "real":
        print(real_data_check())
    else:
        raise SystemExit("usage: python -m baselines.qsf [paper [name=value ...]|innovation|real]")
