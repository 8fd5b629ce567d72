"""A privileged receding-horizon oracle for ``magenv/MagQSF-v0``: an **upper bound**, never a baseline.

It reads the true orientation, so no deployable method can match it; it says
how much a QSF decision policy could gain on a trial (the *headroom* row of
``magenv compare`` and ``magenv report``) and labels states for imitation
(``magenv.agents.dagger``).

At every decision (every k = ``decision_every`` samples, the env's default 10)
the oracle copies the env's filter state — ``magenv.filters.qsf.State``: the
augmented state x (15,) and covariance P̆ (15, 15), the period flag and age,
y_m(t0) and the reference m_ref (eq. 8) — and, for each candidate env action
[decision, trust] (decoded as the env does, ``magenv.envs.qsf.decode_action``),
rolls the env's kernel (``magenv.filters.qsf.run_kernel``, Delay MAGYQ)
forward over the next ``horizon_s`` seconds:

* the first k samples with the candidate: start (a new reference at the
  first sample, then keep), keep, or none, every magnetic update scaled by
  the candidate's trust;
* the rest with the continuation rule, the tuned QSF detector acting as the
  env's policy (``magenv.baselines.qsf.DetectorPolicy``): every k samples,
  from the detector's code of the decision's first sample, start where it
  starts, keep where it keeps (start if no period is active in the roll-out),
  else none; trust 1. With ``continuation="hold"`` (``oracle_qsf_hold``) the
  rule is ``magenv.baselines.qsf.HoldPolicy`` instead: keep, start if no
  period is active.

Cost of a candidate = Σ over the horizon of (total error, degrees)²
(``magenv.metrics.errors1``; samples without truth add 0; a roll-out whose
filter fails costs +inf). The cheapest candidate is applied for k samples,
then the search repeats from the new state.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit

from magenv.checks import check_choice, check_int, check_positive
from magenv.envs import QSF_ID
from magenv.envs.qsf import VARIANTS, QSFRunner, decode_action, fill_decision
from magenv.filters import qsf
from magenv.metrics import errors1
from magenv.protocols import Estimate
from magenv.trial import Trial

#: env actions [decision, trust] searched: none; keep with trust 0.3 or 1; start (trust 1)
CANDIDATES = ((-1.0, 0.0), (0.0, 0.3), (0.0, 1.0), (1.0, 1.0))
HORIZON_S = 0.5  # s, look-ahead of each search
DECISION_EVERY = 10  # samples per decision (the env's default)
CONTINUATIONS = ("detector", "hold")


@njit(cache=True)
def rule_code(codes, active, j):
    """The detector policy's decision at sample j: start / keep (start if no period is active) / none."""
    c = codes[j]
    if c == qsf.MAG_START:
        return qsf.MAG_START
    if c == qsf.MAG_KEEP:
        return qsf.MAG_KEEP if active else qsf.MAG_START
    return qsf.MAG_NONE


@njit(cache=True)
def candidate_costs(p, state, inputs, codes, q_true, dt, start, horizon, k, cand_codes, cand_trust, scratch, costs):
    """``costs[c]`` = Σ (total error, °)² over samples start … start+horizon−1 of candidate c
    (``cand_codes[c]`` a ``qsf.MAG_*`` code, ``cand_trust[c]`` ∈ [0, 1]); +inf if the roll-out's filter fails.

    Each roll-out starts from a copy of ``state`` (``qsf.State``, left unchanged) held in ``scratch``
    = (State, Inputs with their own action/trust rows, Outputs) of the trial's length.
    """
    work, wins, out = scratch
    n = inputs.gyr.shape[0]
    stop = min(n, start + horizon)
    for c in range(cand_codes.shape[0]):
        work.x[:] = state.x
        work.cov[:, :] = state.cov
        work.period_active[0], work.period_age[0] = state.period_active[0], state.period_age[0]
        work.mag_t0[:] = state.mag_t0
        work.mag_ref[:] = state.mag_ref
        a = min(start + k, stop)
        fill_decision(wins, cand_codes[c], cand_trust[c], start, a)
        bad, _ = qsf.run_kernel(p, work, wins, dt, start, a, out)
        while bad < 0 and a < stop:
            b = min(a + k, stop)
            fill_decision(wins, rule_code(codes, work.period_active[0], a), 1.0, a, b)
            bad, _ = qsf.run_kernel(p, work, wins, dt, a, b, out)
            a = b
        if bad >= 0:
            costs[c] = np.inf
            continue
        cost = 0.0
        for i in range(start, stop):
            total = errors1(out.q[i], q_true[i])[0]
            if total == total:
                cost += total * total
        costs[c] = cost


class QSFOracle:
    """The receding-horizon oracle of ``MagQSF-v0`` on whole trials (an ``Estimator``); it reads truth: an
    upper bound only.

    Args:
        detector: the continuation rule's QSF detector (a ``qsf.QSFDetector`` or a mapping of its
            thresholds), also the env's (``env_kwargs``); None = the default detector.
        candidates: env actions [decision ∈ [−1, 1], trust ∈ [0, 1]] searched at each decision, (C, 2).
        horizon_s: look-ahead, s. decision_every: samples per decision (k).
        variant, init: the env's filter ("delay_magyq" or "magyq") and start (``qsf.initial_orientation``).
        continuation: the rule after the first decision, "detector" or "hold" (see the module docstring).
    """

    name = "oracle_qsf"
    env_id = QSF_ID
    privileged = True  # reads the true orientation: compare and report show it as the headroom row

    def __init__(
        self,
        detector: qsf.QSFDetector | dict | None = None,
        candidates=CANDIDATES,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        variant: str = "delay_magyq",
        init: str = "auto",
        continuation: str = "detector",
    ):
        self.continuation = check_choice("continuation", continuation, CONTINUATIONS)
        self._held: np.ndarray | None = None  # "keep" at every sample of the runner's trial (hold)
        if self.continuation == "hold":
            self.name = "oracle_qsf_hold"
        if isinstance(detector, dict):
            detector = qsf.QSFDetector(**detector)
        elif detector is not None and not isinstance(detector, qsf.QSFDetector):
            raise TypeError(f"detector must be a QSFDetector or a mapping of its thresholds, got {detector!r}")
        self.detector = detector or qsf.QSFDetector()
        cands = np.asarray(candidates, float)
        ok = cands.ndim == 2 and cands.shape[1] == 2 and cands.shape[0] > 0
        if not ok or not np.all((np.abs(cands[:, 0]) <= 1) & (cands[:, 1] >= 0) & (cands[:, 1] <= 1)):
            raise ValueError(
                f"candidates must be a non-empty list of [decision in [-1, 1], trust in [0, 1]], got {candidates!r}"
            )
        self.candidates = cands
        decoded = [decode_action(a)[:2] for a in cands]
        self._codes = np.array([d[0] for d in decoded], np.int64)
        self._trust = np.array([d[1] for d in decoded], float)
        self.horizon_s = check_positive("horizon_s", horizon_s)
        self.decision_every = check_int("decision_every", decision_every, 1)
        self.variant, self.init = check_choice("variant", variant, VARIANTS), check_choice("init", init, qsf.INITS)
        # the options of the env whose runner the oracle searches from (and a student acts in)
        self.env_kwargs = {
            "detector": dataclasses.asdict(self.detector),
            "decision_every": self.decision_every,
            "variant": self.variant,
            "init": self.init,
        }

    @classmethod
    def from_detector_params(cls, params: dict) -> QSFOracle:
        """Privileged QSF decision search (reads truth: an upper bound) continuing with the detector of ``params``."""
        return cls(detector=params)

    @classmethod
    def holding(cls, params: dict) -> QSFOracle:
        """``oracle_qsf_hold``: the search continuing with ``HoldPolicy``; the env runs the detector of ``params``."""
        return cls(detector=params, continuation="hold")

    def _rule_codes(self, runner: QSFRunner) -> np.ndarray:
        """(N,) the codes the continuation rule follows: the detector's, or "keep" everywhere (hold)."""
        if self.continuation == "detector":
            return runner.codes
        if self._held is None or self._held.shape[0] != runner.n:
            self._held = np.full(runner.n, qsf.MAG_KEEP, runner.codes.dtype)
        return self._held

    def make_runner(self, trial: Trial) -> QSFRunner:
        """The env's runner on ``trial`` with the rule's detector (the state the oracle searches from)."""
        return QSFRunner(trial, self.variant, self.detector, self.init)

    def _scratch(self, runner: QSFRunner):
        """(State, Inputs, Outputs) the roll-outs work in: arrays of the trial's length, kept between calls."""
        n, cached = runner.n, getattr(self, "_work", None)
        if cached is None or cached[2].q.shape[0] != n:
            work = qsf.State(*(np.empty_like(a) for a in runner.state))
            self._work = cached = (work, (np.zeros(n, np.int8), np.zeros(n)), qsf.Outputs.empty(n))
        work, (action, trust), out = cached
        sensors = runner.inputs
        return work, qsf.Inputs(sensors.gyr, sensors.acc, sensors.mag, action, trust), out

    def candidate_costs(self, runner: QSFRunner) -> np.ndarray:
        """(C,) Σ (total error, °)² over the horizon of each candidate from ``runner``'s state (left unchanged)."""
        costs = np.empty(len(self.candidates))
        horizon = int(round(self.horizon_s * runner.trial.rate))
        candidate_costs(
            runner.params, runner.state, runner.inputs, self._rule_codes(runner), runner.q_true, float(runner.trial.dt),
            runner.pos, horizon, self.decision_every, self._codes, self._trust, self._scratch(runner), costs,
        )  # fmt: skip
        return costs

    def best_action(self, runner: QSFRunner) -> np.ndarray:
        """The candidate with the lowest cost from ``runner``'s state (the first on ties)."""
        return self.candidates[int(np.argmin(self.candidate_costs(runner)))].copy()

    def continuation_action(self, runner: QSFRunner) -> np.ndarray:
        """The continuation rule's env action at ``runner``'s next decision (trust 1)."""
        j = min(runner.pos, runner.n - 1)
        code = rule_code(self._rule_codes(runner), bool(runner.state.period_active[0]), j)
        return np.array([{qsf.MAG_NONE: -1.0, qsf.MAG_KEEP: 0.0, qsf.MAG_START: 1.0}[int(code)], 1.0])

    def rule_candidate(self, runner: QSFRunner, candidates: np.ndarray) -> int:
        """The index of the continuation rule's decision among ``candidates`` (C, 2) env actions: the first with its
        code and trust 1 (any trust for "none", which makes no magnetic update); −1 if there is none."""
        want = decode_action(self.continuation_action(runner))[0]
        for i, action in enumerate(candidates):
            code, trust, _ = decode_action(action)
            if code == want and (code == qsf.MAG_NONE or trust == 1.0):
                return i
        return -1

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``)."""
        runner = self.make_runner(trial)
        while not runner.done:
            code, trust, _ = decode_action(self.best_action(runner))
            runner.advance(self.decision_every, (code, trust))
        return Estimate(q=runner.est.copy(), trust=runner.out.sig[:, qsf.SIGNAL.trust].copy())
