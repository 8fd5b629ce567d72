"""The privileged oracle of MagConstraint-v0 (``oracle_constraint``): its roll-out is the env's kernel, it beats its
continuation rule, it is deterministic, leaves the runner alone and is shown as the headroom row."""

from __future__ import annotations

import numpy as np
import pytest

from magenv import evaluation, metrics, registry
from magenv import scenarios as cs
from magenv.baselines.constraint import ConstraintWeightRule
from magenv.baselines.oracle_constraint import ConstraintOracle

TUNED = {"th1": 0.115, "th2": 0.01, "th3": 0.108, "k_min": 0.0, "k_max": 0.41}  # near the packaged tuned rule


@pytest.fixture(scope="module")
def trials():
    return [cs.make_trial("constraint_test2", s, duration=8.0, disturbances=((3.0, 2.0),)) for s in range(2)]


def _rule_run(oracle, trial):
    """The continuation rule acting alone in the oracle's runner: (runner, RMSE °)."""
    runner = oracle.make_runner(trial)
    while not runner.done:
        runner.advance(oracle.decision_every, oracle._env_action(oracle.continuation_action(runner)))
    return runner, metrics.score(runner.est, trial.q_true, trial.score_mask).total


@pytest.mark.parametrize("control_gain", [False, True])
def test_oracle_beats_its_continuation_rule(trials, control_gain):
    oracle = ConstraintOracle(**TUNED, control_gain=control_gain)
    for trial in trials:
        ours = evaluation.run_method("oracle", oracle, trial).score.total
        assert ours < _rule_run(oracle, trial)[1], trial.name


def test_a_candidate_costs_what_the_env_gives_it(trials):
    """The cost of the continuation rule's own action is the squared error of the env's runner under that rule."""
    trial = trials[0]
    rule_only = ConstraintOracle(**TUNED)
    full, _ = _rule_run(rule_only, trial)
    runner = rule_only.make_runner(trial)
    for _ in range(50):
        runner.advance(4, (0.3, None))
    start = runner.pos
    oracle = ConstraintOracle(**TUNED, candidates=[rule_only.continuation_action(runner)[0]], horizon_s=0.5)
    # replay the rule from this state in a second runner
    replay = rule_only.make_runner(trial)
    for _ in range(50):
        replay.advance(4, (0.3, None))
    while replay.pos < start + 50:
        replay.advance(4, rule_only._env_action(rule_only.continuation_action(replay)))
    err = metrics.errors(replay.est[start : start + 50], trial.q_true[start : start + 50])[:, 0]
    assert oracle.candidate_costs(runner)[0] == pytest.approx(np.nansum(err**2), rel=1e-9)
    assert full.pos == trial.n


def test_costs_leave_the_runner_alone_and_runs_repeat(trials):
    oracle = ConstraintOracle(**TUNED)
    runner = oracle.make_runner(trials[1])
    runner.advance(40, (0.5, None))
    q, est = runner.q.copy(), runner.est.copy()
    costs = oracle.candidate_costs(runner)
    np.testing.assert_array_equal(runner.q, q)
    np.testing.assert_array_equal(runner.est, est)
    assert costs.shape == (5,) and np.all(costs > 0)
    a, b = oracle.run(trials[0]), ConstraintOracle(**TUNED).run(trials[0])
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.trust, b.trust)


def test_continuation_action_is_the_env_rule_on_the_observation(trials):
    oracle = ConstraintOracle(**TUNED, control_gain=True)
    rule = ConstraintWeightRule(control_gain=True, **TUNED)
    runner = oracle.make_runner(trials[1])
    for _ in range(80):
        assert oracle.continuation_action(runner)[0] == pytest.approx(rule(runner.feat)[0], abs=1e-5)
        runner.advance(4, oracle._env_action(oracle.best_action(runner)))


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="candidates"):
        ConstraintOracle(candidates=(0.0, 1.5))
    with pytest.raises(ValueError, match="candidates"):
        ConstraintOracle(candidates=(0.0, 0.5), control_gain=True)
    with pytest.raises(ValueError, match="horizon_s"):
        ConstraintOracle(horizon_s=0.0)
    with pytest.raises(ValueError, match="decision_every"):
        ConstraintOracle(decision_every=0)
    with pytest.raises(ValueError, match="th1"):
        ConstraintOracle(th1=-1.0)


def test_registry_oracle_is_privileged_and_a_headroom_row(trials):
    from magenv.train.compare import headroom_names

    methods = {"oracle_constraint": registry.make("oracle_constraint"), "cf": registry.make("cf_constraint_tuned")}
    assert methods["oracle_constraint"].privileged and headroom_names(methods) == {"oracle_constraint"}
    tuned = registry.tuned_params("cf_constraint")
    assert methods["oracle_constraint"].rule == pytest.approx(tuned)
    assert methods["oracle_constraint"].env_kwargs["th2"] == pytest.approx(tuned["th2"])


def test_rule_candidates_are_the_rules_w_bit_for_bit(trials):
    """``oracle_constraint_rules`` searches, after the fixed levels, the rule's own w on the env's observation;
    the student's state candidate (from that observation at act time) is the same number, and costs as given."""
    from magenv.agents.student_inputs import inputs_for
    from magenv.envs import CONSTRAINT_ID
    from magenv.envs.constraint import ConstraintRunner

    oracle = registry.make("oracle_constraint_rules")
    inputs = inputs_for(CONSTRAINT_ID)
    meta = inputs.meta(oracle)
    assert meta["rule_candidates"] and inputs.n_state_candidates(meta) == 1
    assert inputs.n_state_candidates(inputs.meta(registry.make("oracle_constraint"))) == 0
    r = oracle.rule
    runner = ConstraintRunner(trials[0], True, th2=r["th2"], th3=r["th3"], k_min=r["k_min"], k_max=r["k_max"])
    seen = set()
    for _ in range(120):
        obs = runner.feat.astype(np.float32)
        student = inputs.candidate_actions(obs, meta)[0]
        np.testing.assert_array_equal(student, oracle.state_candidates(runner))
        assert student[0, 0] == pytest.approx(oracle.continuation_action(runner)[0], abs=1e-5)  # the rule's w
        both = np.concatenate([oracle.candidates, student])
        np.testing.assert_array_equal(oracle.candidate_costs(runner), oracle.candidate_costs(runner, both))
        seen.add(float(student[0, 0]))
        runner.advance(4, oracle._env_action(oracle.best_action(runner)))
    assert len(seen) > 10  # it moves with the state
    with pytest.raises(ValueError, match="control_gain"):
        ConstraintOracle(rule_candidates=True, control_gain=True)
    with pytest.raises(ValueError, match="candidates"):
        oracle.candidate_costs(runner, [[0.5, 0.5]])
