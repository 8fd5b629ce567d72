"""A privileged receding-horizon oracle for ``magenv/MagKalman-v0``: an **upper bound**, never a baseline.

It reads the true orientation, so no deployable method can match it; it says
how much a trust (γ) policy could gain on a trial (the *headroom* row of
``magenv compare`` and ``magenv report``) and labels states for imitation
(``magenv.agents.dagger``).

At every decision (every k samples, the env's ``decision_every``) the oracle
copies the env's own filter state (quaternion q̂ and error covariance P of
``magenv.filters.kalman_trust``) and, for each candidate γ_c in
``candidates``, rolls the env's filter kernel (``kalman_trust.step1``: gyro
prediction, gated accelerometer update, magnetometer update with gain γ·K)
forward over the next ``horizon_s`` seconds:

* the first k samples with γ_c,
* the rest with the continuation rule, re-evaluated every k samples from the
  rolled-out state on the quantities the env's observation of that sample
  shows (in float64 and unclipped, so close to, not bit for bit, the rule
  acting on the observation; a peek whose filter step fails gives γ = 0):
  γ = 1 / (1 + (‖d̂_j‖/σ_d)² + (Δm_j/σ_m)² + (Δθ_j/σ_θ)²), where ‖d̂_j‖ (µT) is
  the env's model-based disturbance estimate (``model_dist``, independent of
  γ), Δm_j = ‖m_j‖ − m0 (µT) and Δθ_j the dip of m_j below the a-priori
  horizontal minus θ0 (°), read by peeking at sample j (prediction and
  accelerometer update on a copy, γ = 0) as the env does. ``kf_model``
  (Ligorio & Sabatini 2015) is the σ_d term alone, ``kf_adaptive`` (Harada et
  al. 2007) the σ_m, σ_θ terms (the others infinite).

Cost of a candidate = Σ over the horizon of (total error Δθ, degrees)², the
error of eq. 22 (``magenv.metrics.errors1``; samples without truth add 0):
what the trial's RMSE adds up. The cheapest candidate is applied for k
samples, then the search repeats from the new state.

Four options (all off in the packaged ``oracle_kalman``):

* ``rule_candidates``: the γ that the continuation rule and each ``proposals``
  rule give on the env's observation of the current state are searched as
  further (state-dependent) candidates, after the fixed levels
  (``state_candidates``); a DAgger student choosing among the same
  candidates can always fall back on a rule;
* ``continuations``: further continuation rules; a candidate's cost is then the
  lowest over the roll-outs continuing with each rule (the continuation rule
  and these);
* ``still``: a ``kf_still`` rule (``StillPullTrust`` on the extended
  observation, ``magenv.envs.kalman.EXTENDED``) whose γ is one more
  state-dependent candidate, searched last (with ``rule_candidates``). It is
  a candidate only, never a continuation: the roll-outs do not carry the
  still anchor's memory. Its runners must be extended (``KalmanRunner(trial,
  extended=True)``);
* ``perp``: a ``kf_perp`` rule (``PerpPullTrust`` on the extended observation),
  the same kind of candidate on ``d_perp``, searched after ``still``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from magenv.baselines.kalman_policies import AdaptiveTrust, KalmanRule, ModelTrust, PerpPullTrust, StillPullTrust
from magenv.envs import KALMAN_ID
from magenv.envs.kalman import EXTENDED, KalmanRunner
from magenv.filters import kalman_trust as kt
from magenv.filters.kalman_trust import SIG
from magenv.metrics import errors1
from magenv.protocols import Estimate
from magenv.trial import Trial

CANDIDATES = (0.0, 0.25, 0.5, 1.0)  # γ levels searched
HORIZON_S = 0.25  # s, look-ahead of each search (0.5 s: the same RMSE to 0.3 % on validation seeds, 2× the cost)
DECISION_EVERY = 8  # samples per decision (the env's default)


@njit(cache=True)
def rule_gamma(params, state, sensors, mdist, j, scales, peek):
    """The continuation rule's γ at sample j (≥ 1) from ``state`` (left unchanged; the peek writes ``peek``).
    ``scales`` = (σ_d µT, σ_m µT, σ_θ °), inf = term absent."""
    a = mdist[j] / scales[0]
    s = a * a
    if np.isfinite(scales[1]) or np.isfinite(scales[2]):
        gyr, acc, mag = sensors
        if kt.peek1(params, state, gyr[j - 1], gyr[j], acc[j], mag[j], peek) < 0:
            return 0.0
        b = peek[SIG.mag_norm_dev] / scales[1]
        c = peek[SIG.dip_dev] / scales[2]
        s += b * b + (c * c if c == c else 0.0)
    return 1.0 / (1.0 + s)


@njit(cache=True)
def candidate_costs(params, state, sensors, q_true, mdist, start, horizon, k, cands, scales, scratch, sig, costs):
    """``costs[c]`` = Σ (total error, °)² over samples start … start+horizon−1 of candidate ``cands[c]``
    (inf if the filter fails). Each roll-out starts from a copy of ``state`` (``kalman_trust.State``, left
    unchanged) held in ``scratch``; ``sig`` (NSIG,) is working space."""
    gyr, acc, mag = sensors
    stop = min(gyr.shape[0], start + horizon)
    for c in range(cands.shape[0]):
        scratch.q[:] = state.q
        scratch.p[:, :] = state.p
        gamma = cands[c]
        cost = 0.0
        for i in range(start, stop):
            off = i - start
            if off >= k and off % k == 0:
                gamma = rule_gamma(params, scratch, sensors, mdist, i, scales, sig)
            if kt.step1(params, scratch, gyr[i - 1], gyr[i], acc[i], mag[i], gamma, sig) < 0:
                cost = np.inf
                break
            total = errors1(scratch.q, q_true[i])[0]
            if total == total:
                cost += total * total
        costs[c] = cost


def _gammas(candidates, columns: bool = False) -> np.ndarray:
    """(C,) contiguous float64 γ of a non-empty list (or, with ``columns``, of a (C, 1) array); ValueError
    naming them unless every γ lies in [0, 1]."""
    g = np.asarray(candidates, np.float64)
    if columns and g.ndim == 2 and g.shape[1] == 1:
        g = g[:, 0]
    if g.ndim != 1 or g.size == 0 or not np.all((g >= 0) & (g <= 1)):
        raise ValueError(f"candidates must be a non-empty list of γ in [0, 1], got {candidates!r}")
    return np.ascontiguousarray(g)


def rule_scales(rule: KalmanRule) -> np.ndarray:
    """(σ_d µT, σ_m µT, σ_θ °) of a ``kf_model`` or ``kf_adaptive`` rule (inf: term absent)."""
    if isinstance(rule, ModelTrust):
        return np.array([rule.sigma_dist_ut, math.inf, math.inf])
    if isinstance(rule, AdaptiveTrust):
        return np.array([math.inf, rule.sigma_mag_ut, rule.sigma_dip_deg])
    raise ValueError(f"the continuation rule must be kf_model or kf_adaptive, got {type(rule).__name__}")


class KalmanOracle:
    """The receding-horizon γ oracle on whole trials (an ``Estimator``); it reads truth: an upper bound only.

    It follows the oracle interface of ``magenv.agents.dagger`` (``env_id``, ``candidates`` (C, 1) of γ,
    ``decision_every``, ``candidate_costs``, ``continuation_action``, ``horizon_s``).

    Args:
        rule: the continuation rule, a ``ModelTrust`` (kf_model) or ``AdaptiveTrust`` (kf_adaptive) with
            the env's default features (None: ``kf_model`` at its default σ_d).
        candidates: γ levels searched at each decision (``levels`` (C,); ``candidates`` is them as (C, 1)).
        horizon_s: look-ahead, s. decision_every: samples per decision (k).
        proposals: further ``kf_model`` / ``kf_adaptive`` rules whose γ a DAgger student sees as inputs
            (``proposal_scales``: their (σ_d, σ_m, σ_θ); ``magenv.agents.student_inputs.KalmanInputs``); they
            do not change the oracle's search unless ``rule_candidates``.
        rule_candidates: also search, at each decision, the γ of the continuation rule and of each proposal
            on the env's observation (``state_candidates``).
        continuations: further continuation rules (kf_model / kf_adaptive); each candidate costs the lowest
            of its roll-outs continuing with ``rule`` and with each of these.
        still: a ``StillPullTrust`` reading ``EXTENDED`` whose γ is the last state candidate (needs
            ``rule_candidates``; a student sees its γ too: ``still_params``).
        still_scenarios: the scenarios on whose trials (``trial.meta["scenario"]``) the ``still`` candidate is
            on offer (None: all); on any other trial it costs inf, so the oracle never takes it there and a
            DAgger student's loss gives it the most regret (``regret_clip``). Privileged (the teacher knows the
            trial's scenario); the student sees the observation only.
        perp, perp_scenarios: a ``PerpPullTrust`` reading ``EXTENDED``, the state candidate after ``still``
            (a student sees its γ too: ``perp_params``), and the scenarios it is on offer on, as for ``still``.
    """

    name = "oracle_kalman"
    env_id = KALMAN_ID
    privileged = True  # reads the true orientation: compare and report show it as the headroom row

    def __init__(
        self,
        rule: KalmanRule | None = None,
        candidates=CANDIDATES,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        proposals: tuple[KalmanRule, ...] = (),
        rule_candidates: bool = False,
        continuations: tuple[KalmanRule, ...] = (),
        still: StillPullTrust | None = None,
        still_scenarios: tuple[str, ...] | None = None,
        perp: PerpPullTrust | None = None,
        perp_scenarios: tuple[str, ...] | None = None,
    ):
        self.rule = ModelTrust() if rule is None else rule
        default = ModelTrust().features
        if any(r.features != default for r in (self.rule, *proposals, *continuations)):
            raise ValueError("the continuation and proposal rules must read the env's default observation")
        #: the extra state candidates, in their order after the rules': (name, rule, scenarios or None)
        self.extras: tuple[tuple[str, KalmanRule, tuple[str, ...] | None], ...] = ()
        for name, kind, extra, scenarios in (
            ("still", StillPullTrust, still, still_scenarios),
            ("perp", PerpPullTrust, perp, perp_scenarios),
        ):
            if extra is not None and not (
                isinstance(extra, kind) and extra.features == EXTENDED.names and rule_candidates
            ):
                raise ValueError(
                    f"{name} must be a kf_{name} rule reading the extended observation, with rule_candidates"
                )
            if scenarios is not None and (extra is None or not all(isinstance(n, str) for n in scenarios)):
                raise ValueError(f"{name}_scenarios must be scenario names, with a {name} rule; got {scenarios!r}")
            if extra is not None:
                self.extras += ((name, extra, None if scenarios is None else tuple(scenarios)),)
        self.still, self.perp = still, perp
        self.scales = rule_scales(self.rule)
        self.proposals = tuple(proposals)
        self.proposal_scales = [rule_scales(p) for p in proposals]
        self.rule_candidates = bool(rule_candidates)
        self.continuation_scales = [self.scales, *(rule_scales(r) for r in continuations)]
        cands = _gammas(candidates)
        if not 0 < horizon_s < math.inf:
            raise ValueError(f"horizon_s must be a positive number of seconds, got {horizon_s}")
        if isinstance(decision_every, bool) or int(decision_every) != decision_every or decision_every < 1:
            raise ValueError(f"decision_every must be a positive integer, got {decision_every!r}")
        self.levels, self.candidates = cands, cands[:, None]
        self.horizon_s, self.decision_every = float(horizon_s), int(decision_every)

    @classmethod
    def from_model_params(cls, params: dict, proposals: tuple[KalmanRule, ...] = (), **options) -> KalmanOracle:
        """Privileged γ search (reads truth: an upper bound) continuing with the kf_model rule of ``params``;
        ``proposals``: rules whose γ a student sees; ``options``: ``rule_candidates``, ``continuations``
        (see the class)."""
        return cls(ModelTrust(params["sigma_dist_ut"]), proposals=proposals, **options)

    @property
    def still_params(self) -> list[float] | None:
        """(σ_m µT, σ_θ °, p_min °, γ_pull) of ``still``, or None."""
        s = self.still
        return None if s is None else [s.sigma_mag_ut, s.sigma_dip_deg, s.pull_min_deg, s.gamma_pull]

    @property
    def still_scenarios(self) -> tuple[str, ...] | None:
        """The scenarios the ``still`` candidate is on offer on (None: all, or no still rule)."""
        return next((on for name, _, on in self.extras if name == "still"), None)

    @property
    def perp_params(self) -> list[float] | None:
        """(σ_d µT, p_min °, γ_pull, i_min) of ``perp``, or None."""
        p = self.perp
        return None if p is None else [p.sigma_dist_ut, p.pull_min_deg, p.gamma_pull, p.info_min]

    def rule_actions(self, runner: KalmanRunner) -> np.ndarray:
        """(R, 1) the γ of the continuation rule, of each proposal and of the extras (``still``, ``perp``) on the
        env's observation of ``runner``'s next sample (float64; the same numbers as
        ``magenv.agents.student_inputs.KalmanInputs.candidate_actions`` on that observation)."""
        if self.extras and not runner.extended:
            raise ValueError(f"a teacher with a {self.extras[0][0]} candidate needs an extended runner (extended=True)")
        obs = runner.feat.astype(np.float32)
        rules = (self.rule, *self.proposals, *(rule for _, rule, _ in self.extras))
        return np.array([[r.weight(obs)] for r in rules])

    def state_candidates(self, runner: KalmanRunner) -> np.ndarray:
        """(S, 1) the state-dependent candidates at ``runner``'s state: ``rule_actions`` with
        ``rule_candidates``, else none (S = 0)."""
        return self.rule_actions(runner) if self.rule_candidates else np.empty((0, 1))

    def candidate_costs(self, runner: KalmanRunner, candidates=None) -> np.ndarray:
        """(C,) Σ (total error, °)² over the horizon of each candidate from ``runner``'s state: of ``candidates``
        ((C, 1) or (C,) γ) if given, else of the fixed levels then ``state_candidates(runner)``; with
        ``continuations`` the lowest over the continuation rules; on a trial of a scenario not among an extra's
        scenarios (``still_scenarios``, ``perp_scenarios``) that extra candidate costs inf."""
        if candidates is None:
            gammas = np.concatenate([self.levels, self.state_candidates(runner)[:, 0]])
        else:
            gammas = _gammas(candidates, columns=True)
        first = self.levels.size + 1 + len(self.proposals)  # levels, rule, proposals, then the extras
        scenario = runner.trial.meta.get("scenario")
        refused = [first + k for k, (_, _, on) in enumerate(self.extras) if on is not None and scenario not in on]
        if refused and gammas.size != first + len(self.extras):
            raise ValueError("with an extra's scenarios the candidates must be the levels then the state candidates")
        horizon = int(round(self.horizon_s * runner.trial.rate))
        state = runner.state
        scratch = kt.State(np.empty_like(state.q), np.empty_like(state.p))
        costs, sig = np.empty(gammas.size), np.empty(kt.NSIG)
        best = np.full(gammas.size, np.inf)
        for scales in self.continuation_scales:
            candidate_costs(runner.params, state, runner.sensors, runner.q_true, runner.mdist, runner.pos, horizon,
                            self.decision_every, gammas, scales, scratch, sig, costs)  # fmt: skip
            np.minimum(best, costs, out=best)
        best[refused] = np.inf
        return best

    def best_gamma(self, runner: KalmanRunner) -> float:
        """The candidate (fixed level or, with ``rule_candidates``, a rule's γ) with the lowest cost from
        ``runner``'s state (the first on ties)."""
        gammas = np.concatenate([self.levels, self.state_candidates(runner)[:, 0]])
        return float(gammas[int(np.argmin(self.candidate_costs(runner, gammas)))])

    def continuation_action(self, runner: KalmanRunner) -> np.ndarray:
        """(1,) the continuation rule's γ on the env's observation of ``runner``'s next sample."""
        return np.array([self.rule.weight(runner.feat.astype(np.float32))])

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``), in the env's filter with
        its default options."""
        runner = KalmanRunner(trial, extended=bool(self.extras))
        while not runner.done:
            runner.advance(self.decision_every, self.best_gamma(runner))
        return Estimate(q=runner.est.copy(), trust=runner.trust.copy())
