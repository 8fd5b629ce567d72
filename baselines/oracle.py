"""A privileged receding-horizon oracle for ``magenv/MagBlend-v0``: an **upper bound**, never a baseline.

It reads the true orientation, so no deployable method can match it; it says
how much a λ policy could gain on a trial (the *headroom* row of
``magenv compare`` and ``magenv report``) and labels states for imitation
(``magenv.agents.dagger``).

At every decision (every k samples, the env's ``decision_every``) the oracle
copies the env's own filter state (blended quaternion, stationary-detector
ring buffer and counter) and, for each candidate λ_c in ``candidates``, rolls
the env's blend kernel (``magenv.filters.blend.step1``) forward over the next
``horizon_s`` seconds:

* the first k samples with λ_c,
* the rest with the continuation rule, the Fan λ of eqs. 15–17 with the
  given (tuned) ``norm_tol`` and ``th_dip_deg``, re-evaluated every k samples
  from the rolled-out estimate (as ``magenv.baselines.rules.FanLambda`` acts
  on the env's observation):
  λ = ½·(min(|‖m_j‖ − m0|/(norm_tol·m0), 1) + min(|θ_dip,j − θ0|/th_dip, 1)).

Cost of a candidate = Σ over the horizon of (total error Δθ, degrees)², the
error of eq. 22 (``magenv.metrics.errors1``; samples without truth add 0):
what the trial's RMSE adds up. The cheapest candidate is applied for k
samples, then the search repeats from the new state.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.envs import BLEND_ID
from magenv.envs.blend import BlendRunner, dip_deg
from magenv.filters import blend, stationary
from magenv.filters.rules import FAN_NORM_TOL, FAN_TH_DIP_DEG, fan_lambda_kernel
from magenv.metrics import errors1
from magenv.protocols import Estimate
from magenv.trial import Trial

CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)  # λ levels searched
HORIZON_S = 0.5  # s, look-ahead of each search
DECISION_EVERY = 8  # samples per decision (the env's default)


@njit(cache=True, inline="always")
def fan_lambda(site, q, m, norm_tol, th_dip):
    """The continuation rule's λ (eqs. 15–17, ``magenv.filters.rules``) for field m (3,) µT seen with estimate q
    (4,)."""
    mn = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
    return fan_lambda_kernel((mn - site.m0) / site.m0, dip_deg(q, m) - site.dip0, norm_tol, th_dip)


@njit(cache=True)
def candidate_costs(p, site, state, sensors, q_true, start, horizon, k, cands, norm_tol, th_dip, scratch, costs):
    """``costs[c]`` = Σ (total error, °)² over samples start … start+horizon−1 of candidate ``cands[c]``.

    Each roll-out starts from a copy of ``state`` (``magenv.filters.blend.State``, left unchanged) held in
    ``scratch`` (a State of the same shapes).
    """
    gyr, acc, mag = sensors.gyr, sensors.acc, sensors.mag
    stop = min(gyr.shape[0], start + horizon)
    q, buf, ctr = scratch.q, scratch.detector.buf, scratch.detector.ctr
    for c in range(cands.shape[0]):
        q[:] = state.q
        buf[:, :] = state.detector.buf
        ctr[:] = state.detector.ctr
        lam = cands[c]
        cost = 0.0
        for i in range(start, stop):
            off = i - start
            if off >= k and (off - k) % k == 0:
                lam = fan_lambda(site, q, mag[i], norm_tol, th_dip)
            blend.step1(p, scratch, gyr[i], acc[i], mag[i], lam)
            total = errors1(q, q_true[i])[0]
            if total == total:
                cost += total * total
        costs[c] = cost


class BlendOracle:
    """The receding-horizon oracle on whole trials (an ``Estimator``); it reads truth: an upper bound only.

    It follows the oracle interface of ``magenv.agents.dagger`` (``env_id``, ``candidates`` (C, 1) of λ,
    ``decision_every``, ``candidate_costs``, ``continuation_action``, ``horizon_s``), so it teaches the
    MagBlend-v0 student.

    Args:
        norm_tol, th_dip_deg: the continuation Fan rule's parameters (fraction of m0; degrees).
        candidates: λ levels searched at each decision (``levels`` (C,); ``candidates`` is them as (C, 1)).
        horizon_s: look-ahead, s.
        decision_every: samples per decision (k).
        hold: the env's stationary hold (MagBlend-v0's default: on).
    """

    name = "oracle"
    env_id = BLEND_ID
    privileged = True  # reads the true orientation: compare and report show it as the headroom row

    def __init__(
        self,
        norm_tol: float = FAN_NORM_TOL,
        th_dip_deg: float = FAN_TH_DIP_DEG,
        candidates=CANDIDATES,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        hold: bool = True,
    ):
        cands = np.asarray(candidates, float)
        if cands.ndim != 1 or cands.size == 0 or not np.all((cands >= 0) & (cands <= 1)):
            raise ValueError(f"candidates must be a non-empty list of λ in [0, 1], got {candidates!r}")
        if not (norm_tol > 0 and th_dip_deg > 0 and horizon_s > 0):
            raise ValueError(
                f"norm_tol, th_dip_deg and horizon_s must be positive, got {norm_tol}, {th_dip_deg}, {horizon_s}"
            )
        if isinstance(decision_every, bool) or int(decision_every) != decision_every or decision_every < 1:
            raise ValueError(f"decision_every must be a positive integer, got {decision_every!r}")
        self.norm_tol, self.th_dip_deg = float(norm_tol), float(th_dip_deg)
        self.levels, self.horizon_s = cands, float(horizon_s)
        self.candidates = cands[:, None]  # (C, action_dim = 1): the env actions searched
        self.decision_every, self.hold = int(decision_every), bool(hold)

    @classmethod
    def from_fan_params(cls, params: dict) -> BlendOracle:
        """Privileged λ search (reads truth: an upper bound) continuing with the Fan rule of ``params``."""
        return cls(params["norm_tol"], params["th_dip_deg"])

    def candidate_costs(self, runner: BlendRunner) -> np.ndarray:
        """(len(candidates),) Σ (total error, °)² over the horizon of each candidate from ``runner``'s state."""
        horizon = int(round(self.horizon_s * runner.trial.rate))
        scratch = _scratch(runner.state)
        costs = np.empty(self.levels.size)
        candidate_costs(
            runner.params,
            runner.site,
            runner.state,
            runner.sensors,
            runner.q_true,
            runner.pos,
            horizon,
            self.decision_every,
            self.levels,
            self.norm_tol,
            self.th_dip_deg,
            scratch,
            costs,
        )
        return costs

    def best_lambda(self, runner: BlendRunner) -> float:
        """The candidate with the lowest cost from ``runner``'s state (the first on ties)."""
        return float(self.levels[int(np.argmin(self.candidate_costs(runner)))])

    def continuation_lambda(self, runner: BlendRunner) -> float:
        """The continuation rule's λ at ``runner``'s next sample (the tuned Fan rule on the env's state)."""
        j = min(runner.pos, runner.n - 1)
        return float(fan_lambda(runner.site, runner.state.q, runner.sensors.mag[j], self.norm_tol, self.th_dip_deg))

    def continuation_action(self, runner: BlendRunner) -> np.ndarray:
        """(1,) the continuation rule's λ at ``runner``'s next sample (:meth:`continuation_lambda`)."""
        return np.array([self.continuation_lambda(runner)])

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``)."""
        runner = BlendRunner(trial, hold=self.hold)
        while not runner.done:
            runner.advance(self.decision_every, self.best_lambda(runner))
        return Estimate(q=runner.est.copy(), trust=1.0 - runner.lam)


def _scratch(state: blend.State) -> blend.State:
    """An empty State with the shapes of ``state`` (the roll-outs' working copy)."""
    det = state.detector
    return blend.State(np.empty_like(state.q), stationary.State(np.empty_like(det.buf), np.empty_like(det.ctr)))
