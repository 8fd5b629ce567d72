"""A privileged receding-horizon oracle for ``magenv/MagVQF-v0``: an **upper bound**, never a baseline.

It reads the true orientation, so no deployable method can match it; it says
how much a trust policy could gain on a trial over VQF (the headroom) and
teaches the MagVQF-v0 student (``magenv.agents.dagger``).

At every decision (every k samples) the oracle forks the env's VQF state (one
array, ``magenv.filters.vqf.STATE``) and, for each candidate trust u_c, rolls
the filter kernel forward over the next ``horizon_s`` seconds with u_c held
(:func:`lookahead_costs`, one compiled call for all candidates). Cost of a
candidate = Σ over the horizon of (total error Δθ, degrees)² of the 9D
estimate against truth (samples without truth add 0): what the trial's RMSE
adds up. The cheapest candidate is applied for k samples, then the search
repeats. Holding u_c over the whole horizon (not one decision) matters for
VQF: its heading correction has a time constant of τ_mag = 9 s, so one
window of a different gain barely moves the estimate.

The roll-outs cost little more than one filter pass per trial: only δ depends on the trust, so the rest of
VQF (orientation, bias, rest and disturbance detection) is run once over the trial (:func:`field_rows`) and
each candidate's look-ahead runs δ alone (:func:`heading_costs`).

As a DAgger teacher (the oracle interface of ``magenv.agents.dagger``) its
continuation rule is VQF's own decision, u = 1 on top of VQF's rejection
(``rejection="on"``): the student learns where to lower VQF's gain, and
falls back on VQF itself. With ``rule`` (``oracle_vqf_rule``: the tuned Fan rule
``vqf_fan_lambda_tuned``'s norm_tol and th_dip) it also searches the rule's own
trust at each state (a state-dependent candidate, computed from the
observation as the student computes it, ``magenv.envs.vqf.fan_trust``)
and continues with that rule on top of VQF's rejection: its student departs from
the rule where it learns better and falls back on it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.envs import VQF_ID
from magenv.envs.vqf import FEATURES, VQFRunner, fan_trust, filter_options
from magenv.filters import vqf
from magenv.filters.vqf import P, S
from magenv.metrics import WORST_DEG
from magenv.protocols import Estimate
from magenv.trial import Trial

CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)  # trust levels searched
_NORM_DEV, _DIP_DEV = FEATURES.index("norm_dev"), FEATURES.index("dip_dev")  # the Fan rule's features
HORIZON_S = 4.0  # s, look-ahead of each search (half of VQF's τ_mag: a trust's cost shows)
TAIL_S = vqf.Options.tau_mag / 2  # s, oracle_vqf_tail's terminal cost: ∫ e² exp(−2t/τ_mag) dt = e² τ_mag / 2
DECISION_EVERY = 32  # samples per decision (≈ 9 Hz at BROAD's 286 Hz)


@njit(cache=True)
def field_rows(p, s, w, gyr, acc, mag, q_true, rows):
    """Per sample of a trial, from VQF's state ``s`` before its first sample (a fork, left unchanged: ``s`` is
    copied), what a heading step needs and the truth it is scored against: rows[i] = (ψ, the gain's divisor,
    r, φ) with A = q6D·t = r cos φ, B = (q_z(π) ⊗ q6D)·t = r sin φ, t the truth (NaN r and φ where it has none):
    the 9D estimate's scalar product with the truth is then r cos(δ/2 − φ), one cosine a sample.

    Only δ depends on the trust (``magenv.filters.vqf.step``), so these rows are the same whatever the trusts
    chosen: one pass serves every decision of every candidate (:func:`heading_costs`)."""
    fork = s.copy()
    for i in range(gyr.shape[0]):
        vqf.six_d_step(p, fork, w, gyr[i], acc[i])
        psi, divisor = vqf.field_step(p, fork, mag[i, 0], mag[i, 1], mag[i, 2])
        q0, q1, q2, q3 = vqf.quat6d(fork)
        t = q_true[i]
        rows[i, 0], rows[i, 1] = psi, divisor
        a = q0 * t[0] + q1 * t[1] + q2 * t[2] + q3 * t[3]
        b = -q3 * t[0] - q2 * t[1] + q1 * t[2] + q0 * t[3]
        rows[i, 2], rows[i, 3] = np.hypot(a, b), np.arctan2(b, a)


@njit(cache=True)
def heading_costs(p, delta, init, rows, start, stop, cands, costs, tail_s=0.0):
    """``costs[c]`` = Σ (total error, °)² over samples start … stop−1 of trust ``cands[c]`` held, from the heading
    offset δ = ``delta`` and the initial convergence's 1/N = ``init`` before sample ``start``; ``rows`` of
    :func:`field_rows`. The 9D estimate's scalar product with the truth is r cos(δ/2 − φ).

    With ``tail_s`` > 0 (s) a terminal cost is added: the window's last error e (its last sample with truth)
    counted for tail_s / Ts more samples, and the sum rescaled to the window's H samples,
    (Σ e_i² + e² tail_s / Ts) · H / (H + tail_s / Ts), so that a unit of cost stays one (°)² a sample."""
    ts = p[P.ts]
    tail = tail_s / ts
    span = stop - start
    for c in range(cands.shape[0]):
        k, tau = vqf.trust_gain(p, cands[c])
        d, n0 = delta, init
        cost, last = 0.0, 0.0
        for i in range(start, stop):
            if rows[i, 1] != 0.0:
                d, n0, _, _ = vqf.heading_update(d, n0, rows[i, 0], rows[i, 1], k, tau, ts)
            r = rows[i, 2]
            if r == r:  # no truth: NaN, adds nothing
                wq = r * np.cos(d / 2 - rows[i, 3])
                total = np.rad2deg(2.0 * np.arccos(min(1.0, abs(wq)))) if np.isfinite(wq) else WORST_DEG
                cost += total * total
                last = total
        if tail > 0.0:
            cost = (cost + last * last * tail) * span / (span + tail)
        costs[c] = cost


class VQFOracle:
    """The oracle on whole trials (an ``Estimator``) and the MagVQF-v0 teacher; it reads truth: an upper bound.

    Args:
        candidates: trust levels searched at each decision (``levels`` (C,); ``candidates`` is them as (C, 1)).
        horizon_s: look-ahead, s. decision_every: samples per decision (k).
        rejection: the env option it searches under (``"on"``: on top of VQF's own rejection).
        rule: (norm_tol, th_dip°) of the Fan rule whose trust is searched too and continued with; None: u = 1.
        tail_s: terminal cost, s (:func:`heading_costs`; ``oracle_vqf_tail``: τ_mag / 2, the error at the window's
            end decaying with VQF's heading time constant as its sum over the rest of the trial; 0: none).
    """

    name = "oracle_vqf"
    env_id = VQF_ID
    privileged = True  # reads the true orientation: compare and report show it as the headroom row

    def __init__(
        self,
        candidates=CANDIDATES,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        rejection: str = "on",
        rule: tuple[float, float] | None = None,
        tail_s: float = 0.0,
    ):
        levels = np.asarray(candidates, float)
        if levels.ndim != 1 or levels.size == 0 or not np.all((levels >= 0.0) & (levels <= 1.0)):
            raise ValueError(f"candidates must be trust values in [0, 1], got {candidates!r}")
        if not horizon_s > 0 or isinstance(decision_every, bool) or int(decision_every) < 1:
            raise ValueError(f"horizon_s must be > 0 and decision_every ≥ 1, got {horizon_s}, {decision_every}")
        self.levels, self.candidates = levels, levels[:, None]
        if not tail_s >= 0:
            raise ValueError(f"tail_s must be ≥ 0 s, got {tail_s}")
        self.horizon_s, self.decision_every, self.tail_s = float(horizon_s), int(decision_every), float(tail_s)
        self.env_kwargs = {"rejection": rejection}
        self.rule = None if rule is None else (float(rule[0]), float(rule[1]))
        self.options = filter_options(rejection, vqf.Options.tau_acc, vqf.Options.tau_mag, True, True)
        self._rows: tuple = (None, None, None)  # (trial, parameters, their field_rows) of the last trial searched

    @classmethod
    def from_fan_params(cls, params: dict) -> VQFOracle:
        """``oracle_vqf_rule``: also searching, and continuing with, the Fan rule of ``params`` (its tuned file)."""
        return cls(rule=(params["norm_tol"], params["th_dip_deg"]))

    @classmethod
    def with_tail(cls, params: dict) -> VQFOracle:
        """``oracle_vqf_tail``: ``oracle_vqf_rule`` with the terminal cost of ``TAIL_S``."""
        return cls(rule=(params["norm_tol"], params["th_dip_deg"]), tail_s=TAIL_S)

    def rule_trust(self, runner: VQFRunner) -> float:
        """The rule's trust at the runner's next sample, from its observation as the student sees it (float32)."""
        assert self.rule is not None
        feat = runner.feat.astype(np.float32)
        return float(fan_trust(feat[_NORM_DEV], feat[_DIP_DEV], *self.rule))

    def candidate_costs(self, runner: VQFRunner, candidates=None) -> np.ndarray:
        """Σ (total error, °)² over the horizon of each candidate held, from ``runner``'s state: the levels, or
        ``candidates`` (K, 1) (the fixed ones, then the rule's at this state)."""
        start = runner.pos
        stop = min(runner.n, start + max(self.decision_every, int(round(self.horizon_s * runner.trial.rate))))
        levels = self.levels if candidates is None else np.ascontiguousarray(np.asarray(candidates, float)[:, 0])
        costs = np.empty(levels.size)
        heading_costs(runner.params, runner.state[S.delta], runner.state[S.k_mag_init], self.rows(runner), start,
                      stop, levels, costs, self.tail_s)  # fmt: skip
        return costs

    def rows(self, runner: VQFRunner) -> np.ndarray:
        """:func:`field_rows` of the runner's trial (made once per trial, from VQF's initial state)."""
        trial, params, rows = self._rows
        p = runner.params
        if trial is not runner.trial or not np.array_equal(params, p):
            rows = np.empty((runner.n, 4))
            field_rows(p, vqf.init_state(p), vqf.work(), *runner.sensors, runner.q_true, rows)
            self._rows = (runner.trial, p.copy(), rows)
        return rows

    def continuation_action(self, runner: VQFRunner) -> np.ndarray:
        """(1,) the rule's trust (``rule``), else VQF's own decision u = 1 (VQF's rejection, where on, acts on it)."""
        return np.array([self.rule_trust(runner) if self.rule is not None else 1.0])

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``)."""
        runner = VQFRunner(trial, self.options)
        while not runner.done:
            cands = self.levels if self.rule is None else np.r_[self.levels, self.rule_trust(runner)]
            costs = self.candidate_costs(runner, cands[:, None])
            runner.advance(self.decision_every, float(cands[int(np.argmin(costs))]))
        return Estimate(q=runner.est.copy(), trust=runner.gain.copy())
