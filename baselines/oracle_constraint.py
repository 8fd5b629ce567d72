"""A privileged receding-horizon oracle for ``magenv/MagConstraint-v0``: an **upper bound**, never a baseline.

It reads the true orientation of link i, so no deployable method can match it;
it says how much a constraint-weight policy could gain on a trial (the
*headroom* row of ``magenv compare`` and ``magenv report``) and labels states
for imitation (``magenv.agents.dagger``).

At every decision (every k = ``decision_every`` samples, the env's default 4)
the oracle copies the env's filter state — the estimate q_i (4,), the
filter's only memory (``magenv.filters.constraint``) — and, for each
candidate action, rolls the env's kernel (``magenv.filters.constraint.fuse``,
eqs. 4–18) forward over the next ``horizon_s`` seconds:

* the first k samples with the candidate: w_c, and k by eq. 18 (or, with
  ``control_gain``, the candidate's k = a₁·gain_max);
* the rest with the continuation rule, the tuned ``cf_constraint`` rule acting
  as the env's policy: every k samples w = min(d/th1, 1) (eq. 16, d = ‖C(q)y_M −
  m_E‖/m0 of the decision's first sample with the rolled-out estimate — the
  env's ``mag_dev`` feature), held for the k samples, k by eq. 18 per sample
  with the tuned th2, th3, k_min, k_max.

Cost of a candidate = Σ over the horizon of (total error of link i, degrees)²
(``magenv.metrics.squared_totals``; samples without truth add 0). The cheapest
candidate is applied for k samples, then the search repeats from the new state.

With ``rule_candidates`` (the teacher ``oracle_constraint_rules``) the rule's
own w at the current state, min(mag_dev/th1, 1) on the env's float32
observation, is searched too, after the fixed levels (``state_candidates``):
a DAgger student choosing among the same candidates
(``magenv.agents.student_inputs.ConstraintInputs``) can always fall back on
the rule exactly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.checks import check_bool, check_int, check_positive
from magenv.envs import CONSTRAINT_ID
from magenv.envs.constraint import ConstraintRunner
from magenv.filters import constraint as cf
from magenv.metrics import squared_totals
from magenv.protocols import Estimate
from magenv.trial import Trial

WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)  # w levels searched (k by eq. 18)
GAIN_LEVELS = (0.0, 0.1, 0.4, 1.0)  # k/gain_max levels searched with control_gain
HORIZON_S = 1.0  # s, look-ahead of each search
DECISION_EVERY = 4  # samples per decision (the env's default)


@njit(cache=True)
def candidate_costs(p, q, inputs, q_true, start, horizon, k, cands, gain_max, scratch, costs):
    """``costs[c]`` = Σ (total error, °)² over samples start … start+horizon−1 of candidate ``cands[c]``.

    ``cands`` (C, 2): [w, k/gain_max], k < 0 meaning eq. 18. Each roll-out starts from a copy of the
    state ``q`` (left unchanged); ``scratch`` is a ``constraint.Trace`` of the trial's length (rows
    start … written). ``p`` carries the continuation rule's th1 (eq. 16) and eq. 18's parameters.
    """
    n = inputs.gyr.shape[0]
    stop = min(n, start + horizon)
    qs = np.empty(4)
    for c in range(cands.shape[0]):
        qs[:] = q
        a = min(start + k, stop)
        g = cands[c, 1]
        first = cf.Control(cands[c, 0], g * gain_max if g >= 0.0 else 0.0, False, g < 0.0)
        cf.fuse(p, qs, inputs, first, start, a, scratch)
        while a < stop:
            b = min(a + k, stop)
            dev, _ = cf.mag_deviation(qs, inputs.mag[a], p)
            cf.fuse(p, qs, inputs, cf.Control(cf.weight_rule(dev, p.th1), 0.0, False, True), a, b, scratch)
            a = b
        costs[c] = squared_totals(scratch.est, q_true, start, stop)


def default_candidates(control_gain: bool) -> np.ndarray:
    """The searched actions: (5, 1) w levels, or with ``control_gain`` (20, 2) every [w, k/gain_max] pair."""
    if not control_gain:
        return np.array(WEIGHTS)[:, None]
    return np.array([[w, g] for w in WEIGHTS for g in GAIN_LEVELS])


class ConstraintOracle:
    """The receding-horizon oracle of ``MagConstraint-v0`` on whole trials (an ``Estimator``); it reads truth:
    an upper bound only.

    Args:
        candidates: env actions searched at each decision, (C, 1) w or, with ``control_gain``,
            (C, 2) [w, k/gain_max]; None = :func:`default_candidates`.
        horizon_s: look-ahead, s. decision_every: samples per decision (k).
        control_gain, gain_max: the env's options (the action also sets k = a₁·gain_max).
        rule_candidates: also search the rule's w on the env's observation at each decision (not with
            ``control_gain``).
        rule: th1, th2, th3, k_min, k_max by keyword, the continuation rule's parameters (eq. 16: fraction of
            m0; eq. 18: ‖Δq‖ units and 1/s; ``magenv.filters.constraint.check_rule_params``), also the env's
            eq. 18 (``env_kwargs``).
    """

    name = "oracle_constraint"
    env_id = CONSTRAINT_ID
    privileged = True  # reads the true orientation: compare and report show it as the headroom row

    def __init__(
        self,
        candidates=None,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        control_gain: bool = False,
        gain_max: float = 1.0,
        rule_candidates: bool = False,
        **rule,
    ):
        self.rule = dict(zip(cf.RULE_PARAMS, cf.check_rule_params(**rule)))
        self.control_gain = check_bool("control_gain", control_gain)
        self.rule_candidates = check_bool("rule_candidates", rule_candidates)
        if self.rule_candidates and self.control_gain:
            raise ValueError("rule_candidates searches the rule's w alone; it cannot be combined with control_gain")
        self.gain_max = check_positive("gain_max", gain_max)
        dim = 2 if self.control_gain else 1
        cands = default_candidates(self.control_gain) if candidates is None else np.asarray(candidates, float)
        if cands.ndim == 1 and dim == 1:
            cands = cands[:, None]
        if cands.ndim != 2 or cands.shape[1] != dim or cands.shape[0] == 0 or not np.all((cands >= 0) & (cands <= 1)):
            what = "[w, k/gain_max] pairs" if self.control_gain else "w levels"
            raise ValueError(f"candidates must be a non-empty list of {what} in [0, 1], got {candidates!r}")
        self.candidates = cands
        self.horizon_s = check_positive("horizon_s", horizon_s)
        self.decision_every = check_int("decision_every", decision_every, 1)
        # the options of the env whose runner the oracle searches from (and a student acts in)
        self.env_kwargs = {k: self.rule[k] for k in cf.RULE_PARAMS[1:]}
        self.env_kwargs["decision_every"] = self.decision_every
        if self.control_gain:
            self.env_kwargs.update(control_gain=True, gain_max=self.gain_max)

    @classmethod
    def from_constraint_params(cls, params: dict, **options) -> ConstraintOracle:
        """Privileged w search (reads truth: an upper bound) continuing with the cf_constraint rule of ``params``;
        ``options``: e.g. ``rule_candidates``."""
        return cls(**{k: params[k] for k in cf.RULE_PARAMS}, **options)

    def make_runner(self, trial: Trial) -> ConstraintRunner:
        """The env's runner on ``trial`` with the rule's eq. 18 (the state the oracle searches from)."""
        r = self.rule
        return ConstraintRunner(trial, False, th2=r["th2"], th3=r["th3"], k_min=r["k_min"], k_max=r["k_max"])

    def _params(self, runner: ConstraintRunner) -> cf.Params:
        return runner.filter.params._replace(th1=self.rule["th1"])

    def state_candidates(self, runner: ConstraintRunner) -> np.ndarray:
        """(S, 1) the state-dependent candidates: with ``rule_candidates`` the rule's w = min(mag_dev/th1, 1) on
        the env's float32 observation of ``runner`` (the same number as ``ConstraintInputs.candidate_actions``),
        else none (S = 0)."""
        if not self.rule_candidates:
            return np.empty((0, self.candidates.shape[1]))
        return np.array([[min(float(np.float32(runner.feat[0])) / self.rule["th1"], 1.0)]])

    def candidate_costs(self, runner: ConstraintRunner, candidates=None) -> np.ndarray:
        """(C,) Σ (total error, °)² over the horizon of each candidate from ``runner``'s state (left unchanged):
        of ``candidates`` (C, action_dim) if given, else of the fixed ones then ``state_candidates``."""
        trial = runner.trial
        scratch = getattr(self, "_scratch", None)
        if scratch is None or scratch.est.shape[0] != trial.n:
            scratch = self._scratch = cf.Trace.empty(trial.n)
        if candidates is None:
            actions = np.concatenate([self.candidates, self.state_candidates(runner)])
        else:
            actions = np.asarray(candidates, np.float64)
            if actions.ndim == 1:
                actions = actions[:, None]
            if actions.shape[1:] != self.candidates.shape[1:] or not np.all((actions >= 0) & (actions <= 1)):
                raise ValueError(f"candidates must be (C, {self.candidates.shape[1]}) actions in [0, 1], "
                                 f"got {np.shape(candidates)}")  # fmt: skip
        cands = actions if self.control_gain else np.column_stack([actions[:, 0], -np.ones(len(actions))])
        costs = np.empty(len(cands))
        horizon = int(round(self.horizon_s * trial.rate))
        candidate_costs(
            self._params(runner), runner.q, runner.filter.inputs, runner.q_true, runner.pos, horizon,
            self.decision_every, cands, self.gain_max, scratch, costs,
        )  # fmt: skip
        return costs

    def best_action(self, runner: ConstraintRunner) -> np.ndarray:
        """The candidate (fixed or, with ``rule_candidates``, the rule's w) with the lowest cost from ``runner``'s
        state (the first on ties)."""
        actions = np.concatenate([self.candidates, self.state_candidates(runner)])
        return actions[int(np.argmin(self.candidate_costs(runner, actions)))].copy()

    def continuation_action(self, runner: ConstraintRunner) -> np.ndarray:
        """The continuation rule's action at ``runner``'s next decision: w by eq. 16 on the env's state (and,
        with ``control_gain``, k by eq. 18 from the w step, over gain_max, clipped to 1)."""
        j = min(runner.pos, runner.n - 1)
        p = self._params(runner)
        dev, _ = cf.mag_deviation(runner.q, runner.filter.inputs.mag[j], p)
        w = float(cf.weight_rule(dev, p.th1))
        if not self.control_gain:
            return np.array([w])
        seen, ref, con = cf.directions(p, runner.filter.inputs, j)
        step = cf.gn_step(runner.q, seen, ref, w, con, np.empty((9, 4)), np.zeros(4))
        k = cf.gain_rule(w, step, p.th2, p.th3, p.k_min, p.k_max) if np.isfinite(step) else 0.0
        return np.array([w, min(k / self.gain_max, 1.0)])

    def _env_action(self, action) -> tuple[float, float | None]:
        return float(action[0]), float(action[1]) * self.gain_max if self.control_gain else None

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``)."""
        runner = self.make_runner(trial)
        while not runner.done:
            runner.advance(self.decision_every, self._env_action(self.best_action(runner)))
        return Estimate(q=runner.est.copy(), trust=1.0 - runner.trace.weight)
