"""The privileged oracle of MagBlend-v0: an upper bound over its own continuation rule, deterministic, and
shown as the headroom row."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import kinematic_trial

from magenv import evaluation, registry
from magenv.baselines.oracle import BlendOracle
from magenv.baselines.rules import FanLambda
from magenv.envs.blend import BlendRunner

TUNED = {"norm_tol": 4.08, "th_dip_deg": 0.73}  # close to the packaged tuned Fan rule


@pytest.fixture(scope="module")
def trials():
    return [
        kinematic_trial(seed=s, duration=6.0, disturbance_ut=d, disturbance_window=(1.5, 4.0))
        for s, d in ((0, 25.0), (1, 60.0), (2, 0.0))
    ]


def test_oracle_never_worse_than_its_continuation_rule(trials):
    oracle = BlendOracle.from_fan_params(TUNED)
    rule = FanLambda(**TUNED)
    for trial in trials:
        ours = evaluation.run_method("oracle", oracle, trial).score.total
        theirs = evaluation.run_method("rule", rule, trial).score.total
        assert ours <= theirs + 1e-9, (trial.name, ours, theirs)


def test_oracle_is_deterministic(trials):
    a = BlendOracle.from_fan_params(TUNED).run(trials[0])
    b = BlendOracle.from_fan_params(TUNED).run(trials[0])
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.trust, b.trust)


def test_costs_leave_the_runner_state_alone(trials):
    """The search rolls out a copy of the env's state: the runner is unchanged."""
    oracle = BlendOracle(norm_tol=5.0, th_dip_deg=90.0, candidates=(1.0,), horizon_s=0.25)
    runner = BlendRunner(trials[1])
    runner.advance(40, 0.3)
    q, buf, ctr = runner.state.q.copy(), runner.state.detector.buf.copy(), runner.state.detector.ctr.copy()
    cost = oracle.candidate_costs(runner)
    np.testing.assert_array_equal(runner.state.q, q)
    np.testing.assert_array_equal(runner.state.detector.buf, buf)
    np.testing.assert_array_equal(runner.state.detector.ctr, ctr)
    assert cost.shape == (1,) and cost[0] > 0


def test_continuation_lambda_is_the_fan_rule_on_the_observation(trials):
    oracle = BlendOracle.from_fan_params(TUNED)
    rule = FanLambda(**TUNED)
    runner = BlendRunner(trials[1])
    for _ in range(60):
        assert oracle.continuation_lambda(runner) == pytest.approx(rule.weight(runner.feat), abs=1e-6)
        runner.advance(8, oracle.best_lambda(runner))


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="candidates"):
        BlendOracle(candidates=(0.0, 1.5))
    with pytest.raises(ValueError, match="positive"):
        BlendOracle(horizon_s=0.0)
    with pytest.raises(ValueError, match="decision_every"):
        BlendOracle(decision_every=0)


def test_registry_oracle_is_privileged_and_a_headroom_row(trials, capsys):
    from magenv.train.compare import HEADROOM_FOOTNOTE, finish, headroom_names, mark_headroom, method_label, table_order

    methods = {"oracle": registry.make("oracle"), "mimu": registry.make("mimu")}
    assert methods["oracle"].privileged and headroom_names(methods) == {"oracle"}
    rows = mark_headroom(evaluation.compare(methods, trials[:1]), headroom_names(methods))
    ordered = table_order(rows)
    assert ordered[-1]["method"] == "oracle" and method_label(ordered[-1]) == "oracle (headroom)"
    assert finish(rows, "t", None) == 0 and HEADROOM_FOOTNOTE in capsys.readouterr().out
    assert ordered[0]["total_rmse_mean"] >= ordered[-1]["total_rmse_mean"]
