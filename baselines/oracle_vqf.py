"""A privileged receding-horizon oracle for ``magenv/MagVQF-v0``: an **upper bound**, never a baseline.

It reads the true orientation, so no deployable method can match it; it says
how much a trust policy could gain on a trial over VQF (the headroom) and
labels states for imitation (``magenv.agents.dagger_vqf``).

At every decision (every k samples) the oracle copies the env's VQF state
(``vqf.VQF.state``, every filter and detector variable) and, for each candidate
trust u_c, rolls VQF forward over the next ``horizon_s`` seconds with u_c held
(``setTauMag(tau_of_trust(u_c))``, ``updateBatch``), then restores the state.
Cost of a candidate = Σ over the horizon of (total error Δθ, degrees)² of the
9D estimate against truth (samples without truth add 0): what the trial's
RMSE adds up. The cheapest candidate is applied for k samples, then the
search repeats. Holding u_c over the whole horizon (not one decision) matters
for VQF: its heading correction has a time constant of τ_mag = 9 s, so one
window of a different gain barely moves the estimate.
"""

from __future__ import annotations

import numpy as np

from magenv import metrics
from magenv.envs.vqf import VQFRunner, tau_of_trust
from magenv.protocols import Estimate
from magenv.trial import Trial

CANDIDATES = (0.0, 0.25, 0.5, 0.75, 1.0)  # trust levels searched
HORIZON_S = 2.0  # s, look-ahead of each search
DECISION_EVERY = 32  # samples per decision


def candidate_costs(runner: VQFRunner, candidates, horizon: int) -> np.ndarray:
    """Σ (total error, °)² over the next ``horizon`` samples of each candidate trust held; the runner's VQF
    is left as it was (its state restored; its gain is set again by the runner's next step)."""
    f, start = runner.filter, runner.pos
    stop = min(runner.n, start + horizon)
    q_true = runner.truth.q_true[start:stop]
    saved = f.state
    costs = np.zeros(len(candidates))
    g, a, m = runner.gyr[start:stop], runner.acc[start:stop], runner.mag[start:stop]
    for c, u in enumerate(candidates):
        f.state = saved
        f.setTauMag(tau_of_trust(float(u), runner.tau_mag, runner.ts))
        q = f.updateBatch(g, a, m)["quat9D"]
        err = metrics.total_error(metrics.error_quaternion(q, q_true))
        costs[c] = float(np.nansum(err * err))
    f.state = saved
    return costs


class VQFOracle:
    """The oracle as an Estimator: ``run(trial)`` steps a :class:`VQFRunner` choosing the cheapest candidate
    at each decision. ``env_kwargs``: the runner's options (``rejection``, ``tau_mag``, …)."""

    def __init__(
        self,
        candidates=CANDIDATES,
        horizon_s: float = HORIZON_S,
        decision_every: int = DECISION_EVERY,
        **env_kwargs,
    ):
        self.candidates = tuple(float(c) for c in candidates)
        if not self.candidates or not all(0.0 <= c <= 1.0 for c in self.candidates):
            raise ValueError(f"candidates must be trust values in [0, 1], got {candidates!r}")
        if not horizon_s > 0 or int(decision_every) < 1:
            raise ValueError(f"horizon_s must be > 0 and decision_every ≥ 1, got {horizon_s}, {decision_every}")
        self.horizon_s, self.k = float(horizon_s), int(decision_every)
        self.env_kwargs = dict(env_kwargs)

    def run(self, trial: Trial) -> Estimate:
        runner = VQFRunner(trial, **self.env_kwargs)
        horizon = max(self.k, int(round(self.horizon_s * trial.rate)))
        while not runner.done:
            costs = candidate_costs(runner, self.candidates, horizon)
            runner.advance(self.k, self.candidates[int(np.argmin(costs))])
        return Estimate(q=runner.est.copy(), trust=runner.gain.copy())
