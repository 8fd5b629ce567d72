"""A trained agent (``magenv.protocols.BatchPolicy``) scores on trials run together as on each trial alone.

``magenv.evaluation`` runs an SB3 agent on all the trials of a call at once: one env per trial, one
``act_batch`` (one ``model.predict``) per decision for every env, each env until its own trial's end. Its
scores must be those of the agent on one trial after the other, bit for bit: ``AgentPolicy`` runs its network
on blocks of ``FORWARD_ROWS`` observations, so no env's actions depend on the envs acting with it. Against
SB3's own ``predict`` on one observation at a time they agree to ``REL``: a forward on one row rounds its
float32 actions differently from one on a block (BLAS picks other kernels), and an action that differs in its
last bit (relative 6e-8) moves a trial's RMSE by about as much; a wrong LSTM state, episode start or trial order
moves it by orders of magnitude more.
"""

from __future__ import annotations

import numpy as np
import pytest

from magenv import evaluation
from magenv.agents.hyperparams import check_section
from magenv.agents.loading import FORWARD_ROWS, AgentPolicy, build_model
from magenv.agents.wrappers import action_bounds
from magenv.protocols import BatchPolicy
from magenv.scenarios import make_trial

ENV = "magenv/MagBlend-v0"
REL = 1e-6  # relative agreement with SB3's predict on one observation at a time (module docstring)
SECTIONS: dict[str, dict] = {
    "ppo": {"n_envs": 1, "n_steps": 64, "batch_size": 64},
    "recurrent_ppo": {"n_envs": 1, "n_steps": 64, "batch_size": 64, "policy_kwargs": {"lstm_hidden_size": 8}},
}


def fresh_agent(algo: str) -> AgentPolicy:
    """A freshly initialised agent (seed 0) whose action layer is scaled up, so that its λ swings with the
    observation (and, recurrent, with its memory) over the whole [0, 1]."""
    section = check_section(algo, {"env_kwargs": {}, **SECTIONS[algo]}, "test")
    run = {"env_id": ENV, "algo": algo, "env_kwargs": {}, "hyperparams": section}
    model = build_model(run, seed=0)
    for p in model.policy.action_net.parameters():
        p.data *= 30.0
    return AgentPolicy(model, ENV, {}, f"fresh {algo}", action_bounds(ENV, {}))


class OneAtATime:
    """The agent acting on one observation at a time (``policy(obs)``, no ``act_batch``): run one trial after
    the other."""

    def __init__(self, agent: AgentPolicy):
        self.agent, self.env_id, self.env_kwargs = agent, agent.env_id, agent.env_kwargs

    def reset(self) -> None:
        self.agent.reset()

    def __call__(self, obs):
        return self.agent(obs)


class SB3Predict(OneAtATime):
    """The agent's network through SB3's own ``predict`` on one observation at a time (its memory carried from
    call to call, as SB3 documents): what the agent does, independently of ``AgentPolicy``."""

    def reset(self) -> None:
        self.state, self.start = None, np.ones(1, bool)
        self.low, self.high = (np.asarray(b, np.float32) for b in action_bounds(ENV, {}))

    def __call__(self, obs):
        model = self.agent.model
        action, self.state = model.predict(obs, state=self.state, episode_start=self.start, deterministic=True)
        self.start = np.zeros(1, bool)
        return self.low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (self.high - self.low)


@pytest.fixture(scope="module")
def trials():
    """Trials of different lengths (their envs end at different decisions) and kinds."""
    return [
        make_trial("dynamic_magnet", 4000, duration=6.0),
        make_trial("stationary_magnet", 4001, duration=4.0),
        make_trial("dynamic_magnet", 4002, duration=5.0),
        make_trial("dynamic_clean", 4003, duration=3.0),
    ]


def parts(scores) -> list[tuple[float, float, float]]:
    return [(s.total, s.heading, s.inclination) for s in scores]


@pytest.mark.parametrize("algo", sorted(SECTIONS))
def test_trials_run_together_score_as_each_alone(algo, trials):
    agent = fresh_agent(algo)
    assert isinstance(agent, BatchPolicy) and not isinstance(OneAtATime(agent), BatchPolicy)
    together = parts(evaluation.run_policy_on_trials(agent, trials))
    assert together == parts(evaluation.run_policy_on_trials(OneAtATime(agent), trials))
    assert together[1:3] == parts(evaluation.run_policy_on_trials(agent, trials[2:0:-1]))[::-1]
    assert len({t for t, _, _ in together}) == len(trials)  # each trial its own score (a mix-up would show)


@pytest.mark.parametrize("algo", sorted(SECTIONS))
def test_the_agent_acts_as_sb3_predicts(algo, trials):
    agent = fresh_agent(algo)
    ours = evaluation.run_policy_on_trials(agent, trials)
    sb3 = evaluation.run_policy_on_trials(SB3Predict(agent), trials)
    for a, b in zip(parts(ours), parts(sb3)):
        assert a == pytest.approx(b, rel=REL, abs=0.0)


def test_one_predict_per_decision_for_all_trials(trials):
    agent = fresh_agent("recurrent_ppo")
    calls = []
    predict = agent.model.predict

    def counted(obs, **kwargs):
        calls.append(len(obs))
        return predict(obs, **kwargs)

    agent.model.predict = counted
    runs = evaluation.evaluate({"agent": agent}, trials)
    decisions = -(-max(t.n for t in trials) // 8)  # MagBlend-v0 decides every 8 samples
    assert calls == [FORWARD_ROWS] * decisions  # one block: the trials' observations, padded
    assert [r.trial.name for r in runs] == [t.name for t in trials]
    assert all(r.q is not None and r.q.shape == (t.n, 4) and r.lam is not None for r, t in zip(runs, trials))


def test_a_trial_that_diverges_leaves_the_others_scored(trials):
    """A trial whose estimate turns non-finite (NaN gyroscope samples) scores 180° (``DIVERGED_SCORE``); the
    trials run with it score as alone."""
    agent = fresh_agent("ppo")
    bad = make_trial("dynamic_clean", 4004, duration=3.0)
    bad.gyr = bad.gyr.copy()
    bad.gyr[100:] = np.nan
    runs = evaluation.evaluate({"agent": agent}, [trials[0], bad, trials[1]])
    assert runs[1].diverged and runs[1].score == evaluation.DIVERGED_SCORE
    assert runs[0].diverged is None and runs[2].diverged is None
    alone = evaluation.run_policy_on_trials(OneAtATime(agent), [trials[0], trials[1]])
    assert [runs[0].scored.total, runs[2].scored.total] == [s.total for s in alone]
