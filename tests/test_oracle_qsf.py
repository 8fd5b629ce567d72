"""The privileged oracle of MagQSF-v0 (``oracle_qsf``, and ``oracle_qsf_hold``): its roll-out is the env's kernel, it
beats its continuation rule, it is deterministic, leaves the runner alone and is shown as the headroom row."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import evaluation, metrics, registry
from magenv import scenarios as hs
from magenv.baselines.oracle_qsf import QSFOracle
from magenv.baselines.qsf import DetectorPolicy, HoldPolicy
from magenv.envs.qsf import decode_action
from magenv.filters import qsf as fq

DETECTOR = {"window_s": 0.39, "th_spread": 4.8, "th_drift": 16.6, "max_period_s": 37.7}  # a loosened detector


@pytest.fixture(scope="module")
def trials():
    return [hs.make_trial(sc, 0, duration=12.0) for sc in ("handheld_texting", "handheld_swinging")]


def _advance(oracle, runner, action):
    code, trust, _ = decode_action(action)
    runner.advance(oracle.decision_every, (code, trust))


def _rule_run(oracle, trial):
    """The continuation rule acting alone in the oracle's runner: (runner, RMSE °)."""
    runner = oracle.make_runner(trial)
    while not runner.done:
        _advance(oracle, runner, oracle.continuation_action(runner))
    return runner, metrics.score(runner.est, trial.q_true, trial.score_mask).total


def test_oracle_beats_its_continuation_rule(trials):
    oracle = QSFOracle(DETECTOR)
    for trial in trials:
        ours = evaluation.run_method("oracle", oracle, trial).score.total
        assert ours < _rule_run(oracle, trial)[1], trial.name


def test_the_continuation_rule_is_the_tuned_detector_policy(trials):
    """The rule alone in the runner is ``qsf_detector`` with the same detector acting in the env."""
    oracle = QSFOracle(DETECTOR)
    policy = DetectorPolicy(detector=DETECTOR)
    runner = oracle.make_runner(trials[0])
    while not runner.done:
        np.testing.assert_array_equal(oracle.continuation_action(runner), policy(runner.feat.astype(np.float32)))
        _advance(oracle, runner, oracle.best_action(runner))


@pytest.mark.parametrize("continuation", ["detector", "hold"])
def test_a_candidate_costs_what_the_env_gives_it(trials, continuation):
    """The cost of a candidate is the squared error of the env's runner under it, then under the rule (the
    published detector: it stops updating within the horizon, where ``HoldPolicy`` keeps)."""
    trial = trials[1]
    oracle = QSFOracle(candidates=[(0.0, 0.3)], horizon_s=0.5, continuation=continuation)
    runner, replay = oracle.make_runner(trial), oracle.make_runner(trial)
    for r in (runner, replay):
        for _ in range(40):
            _advance(oracle, r, oracle.continuation_action(r))
    start = runner.pos
    assert np.any(runner.codes[start : start + 50] == fq.MAG_NONE)
    _advance(oracle, replay, (0.0, 0.3))
    while replay.pos < start + 50:
        _advance(oracle, replay, oracle.continuation_action(replay))
    err = metrics.errors(replay.est[start : start + 50], trial.q_true[start : start + 50])[:, 0]
    assert oracle.candidate_costs(runner)[0] == pytest.approx(np.nansum(err**2), rel=1e-9)


def test_costs_leave_the_runner_alone_and_runs_repeat(trials):
    oracle = QSFOracle(DETECTOR)
    runner = oracle.make_runner(trials[1])
    for _ in range(30):
        _advance(oracle, runner, (1.0, 1.0))
    state = [a.copy() for a in runner.state]
    est = runner.est.copy()
    costs = oracle.candidate_costs(runner)
    for a, b in zip(runner.state, state):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(runner.est, est)
    assert costs.shape == (len(oracle.candidates),) and np.all(costs > 0)
    a, b = oracle.run(trials[0]), QSFOracle(DETECTOR).run(trials[0])
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.trust, b.trust)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="candidates"):
        QSFOracle(candidates=[(0.0, 1.5)])
    with pytest.raises(ValueError, match="candidates"):
        QSFOracle(candidates=[0.0, 1.0])
    with pytest.raises(ValueError, match="horizon_s"):
        QSFOracle(horizon_s=-1.0)
    with pytest.raises(ValueError, match="decision_every"):
        QSFOracle(decision_every=0)
    with pytest.raises(ValueError, match="variant"):
        QSFOracle(variant="aekf")
    with pytest.raises(TypeError, match="detector"):
        QSFOracle(detector=3.0)


def test_registry_oracle_is_privileged_and_a_headroom_row():
    from magenv.train.compare import headroom_names

    methods = {"oracle_qsf": registry.make("oracle_qsf"), "rule": registry.make("qsf_detector_tuned")}
    assert methods["oracle_qsf"].privileged and headroom_names(methods) == {"oracle_qsf"}
    assert methods["oracle_qsf"].env_kwargs["detector"] == methods["rule"].env_kwargs["detector"]


def test_the_rule_candidate_is_the_detector_policys_decision(trials):
    """``rule_candidate``: the candidate of the rule's decision (none whatever its trust; keep and start with
    trust 1) at every state, −1 where the candidates lack it."""
    oracle = QSFOracle(DETECTOR)
    runner, seen = oracle.make_runner(trials[1]), set()
    while not runner.done:
        i = oracle.rule_candidate(runner, oracle.candidates)
        want = decode_action(oracle.continuation_action(runner))[0]
        assert i >= 0 and decode_action(oracle.candidates[i])[0] == want and i != 1  # never keep with trust .3
        seen.add(i)
        assert oracle.rule_candidate(runner, oracle.candidates[[1]]) == -1  # keep .3 alone is not the rule
        _advance(oracle, runner, oracle.best_action(runner))
    assert seen == {0, 2, 3}


def test_the_hold_continuation_is_qsf_hold_and_the_hold_oracle_beats_it(trials):
    """``oracle_qsf_hold`` continues with ``HoldPolicy`` (start once, then keep) acting in the env, and beats it."""
    oracle, policy = QSFOracle(DETECTOR, continuation="hold"), HoldPolicy()
    assert oracle.name == "oracle_qsf_hold" and oracle.env_kwargs == QSFOracle(DETECTOR).env_kwargs
    runner, codes = oracle.make_runner(trials[0]), []
    while not runner.done:
        action = oracle.continuation_action(runner)
        np.testing.assert_array_equal(action, policy(runner.feat.astype(np.float32)))
        codes.append(decode_action(action)[0])
        _advance(oracle, runner, action)
    assert codes[0] == fq.MAG_START and set(codes[1:]) == {fq.MAG_KEEP}  # 12 s: no age restart
    ours = evaluation.run_method("oracle", oracle, trials[0]).score.total
    assert ours < metrics.score(runner.est, trials[0].q_true, trials[0].score_mask).total
    with pytest.raises(ValueError, match="continuation"):
        QSFOracle(continuation="forever")


def test_qsf_hold_needs_the_active_feature():
    with pytest.raises(ValueError, match="active"):
        HoldPolicy(features=["det_start", "age"])
    assert registry.make("qsf_hold").env_kwargs == {}
