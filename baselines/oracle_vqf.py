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

As a DAgger teacher (the oracle interface of ``magenv.agents.dagger``) its
continuation rule is VQF's own decision, u = 1 on top of VQF's rejection
(``rejection="on"``): the student learns where to lower VQF's gain, and
falls back on VQF itself.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from magenv.envs import VQF_ID
from magenv.envs.vqf import VQFRunner, filter_options
from magenv.filters import vqf
from magenv.filters.vqf import P, S
from magenv.metrics import WORST_DEG
from magenv.protocols import Estimate
from magenv.trial import Trial

CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)  # trust levels searched
HORIZON_S = 2.0  # s, look-ahead of each search
DECISION_EVERY = 32  # samples per decision (≈ 9 Hz at BROAD's 286 Hz)


@njit(cache=True)
def lookahead_costs(p, s, w, fork, gyr, acc, mag, q_true, start, stop, cands, costs, rows):
    """``costs[c]`` = Σ (total error, °)² over samples start … stop−1 of trust ``cands[c]`` held, from the state
    ``s`` (left unchanged; ``fork`` its working copy, ``w`` the kernels' scratch, ``rows`` (≥ stop − start, 4)).

    Only δ depends on the trust (``magenv.filters.vqf.step``), so one roll-out of the rest serves every
    candidate: it keeps per sample the field's heading ψ, the gain's divisor and, against the truth t, the two
    dot products A = q6D·t and B = (q_z(π) ⊗ q6D)·t, so that q9D·t = cos(δ/2)·A + sin(δ/2)·B; each candidate
    then runs δ alone (``magenv.filters.vqf.heading_update``)."""
    fork[:] = s
    n = stop - start
    for j in range(n):
        i = start + j
        vqf.six_d_step(p, fork, w, gyr[i], acc[i])
        psi, divisor = vqf.field_step(p, fork, mag[i, 0], mag[i, 1], mag[i, 2])
        q0, q1, q2, q3 = vqf.quat6d(fork)
        t = q_true[i]
        rows[j, 0], rows[j, 1] = psi, divisor
        rows[j, 2] = q0 * t[0] + q1 * t[1] + q2 * t[2] + q3 * t[3]
        rows[j, 3] = -q3 * t[0] - q2 * t[1] + q1 * t[2] + q0 * t[3]
    ts = p[P.ts]
    for c in range(cands.shape[0]):
        k, tau = vqf.trust_gain(p, cands[c])
        delta, init = s[S.delta], s[S.k_mag_init]
        cost = 0.0
        for j in range(n):
            if rows[j, 1] != 0.0:
                delta, init, _, _ = vqf.heading_update(delta, init, rows[j, 0], rows[j, 1], k, tau, ts)
            a = rows[j, 2]
            if a == a or not np.isfinite(q_true[start + j, 0]):  # no truth: NaN A, adds nothing
                wq = np.cos(delta / 2) * a + np.sin(delta / 2) * rows[j, 3]
                if wq == wq:
                    total = np.rad2deg(2.0 * np.arccos(min(1.0, abs(wq)))) if np.isfinite(wq) else WORST_DEG
                    cost += total * total
            else:  # the roll-out diverged (truth is there, the estimate is not finite)
                cost += WORST_DEG * WORST_DEG
        costs[c] = cost


class VQFOracle:
    """The oracle on whole trials (an ``Estimator``) and the MagVQF-v0 teacher; it reads truth: an upper bound.

    Args:
        candidates: trust levels searched at each decision (``levels`` (C,); ``candidates`` is them as (C, 1)).
        horizon_s: look-ahead, s. decision_every: samples per decision (k).
        rejection: the env option it searches under (``"on"``: on top of VQF's own rejection).
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
    ):
        levels = np.asarray(candidates, float)
        if levels.ndim != 1 or levels.size == 0 or not np.all((levels >= 0.0) & (levels <= 1.0)):
            raise ValueError(f"candidates must be trust values in [0, 1], got {candidates!r}")
        if not horizon_s > 0 or isinstance(decision_every, bool) or int(decision_every) < 1:
            raise ValueError(f"horizon_s must be > 0 and decision_every ≥ 1, got {horizon_s}, {decision_every}")
        self.levels, self.candidates = levels, levels[:, None]
        self.horizon_s, self.decision_every = float(horizon_s), int(decision_every)
        self.env_kwargs = {"rejection": rejection}
        self.options = filter_options(rejection, vqf.Options.tau_acc, vqf.Options.tau_mag, True, True)
        self._fork = np.empty(vqf.STATE.size)
        self._work = vqf.work()
        self._rows = np.empty((0, 4))

    def candidate_costs(self, runner: VQFRunner) -> np.ndarray:
        """(C,) Σ (total error, °)² over the horizon of each candidate held, from ``runner``'s state."""
        start = runner.pos
        stop = min(runner.n, start + max(self.decision_every, int(round(self.horizon_s * runner.trial.rate))))
        gyr, acc, mag = runner.sensors
        if len(self._rows) < stop - start:
            self._rows = np.empty((stop - start, 4))
        costs = np.empty(self.levels.size)
        lookahead_costs(runner.params, runner.state, self._work, self._fork, gyr, acc, mag, runner.q_true, start,
                        stop, self.levels, costs, self._rows)  # fmt: skip
        return costs

    def continuation_action(self, runner: VQFRunner) -> np.ndarray:
        """(1,) VQF's own decision: u = 1 (VQF's rejection, where on, acts on it)."""
        return np.ones(1)

    def run(self, trial: Trial) -> Estimate:
        """The oracle's estimate of every sample of ``trial`` (reads ``trial.q_true``)."""
        runner = VQFRunner(trial, self.options)
        while not runner.done:
            runner.advance(self.decision_every, float(self.levels[int(np.argmin(self.candidate_costs(runner)))]))
        return Estimate(q=runner.est.copy(), trust=runner.gain.copy())
