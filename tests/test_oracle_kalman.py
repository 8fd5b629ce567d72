"""The privileged γ oracle of MagKalman-v0: its search is a roll-out of the env's own filter, it beats its
continuation rule, it is deterministic, and it is shown as the headroom row."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import kinematic_trial

from magenv import evaluation, registry
from magenv.agents import dagger
from magenv.agents.student_inputs import inputs_for
from magenv.baselines.kalman_policies import AdaptiveTrust, ModelTrust
from magenv.baselines.oracle_kalman import KalmanOracle
from magenv.envs import KALMAN_ID
from magenv.envs.kalman import EXTENDED, KalmanRunner
from magenv.metrics import errors

RULE = ModelTrust(0.3)  # close to the packaged tuned kf_model


@pytest.fixture(scope="module")
def trial():
    return kinematic_trial(seed=1, duration=6.0, disturbance_ut=40.0, disturbance_window=(1.5, 4.5))


def test_costs_are_the_roll_out_of_the_env_filter(trial):
    """A candidate's cost is Σ (total error)² of the env's runner applying it for one decision and then the
    continuation rule on its observation, over the look-ahead; the searched runner is left unchanged."""
    oracle = KalmanOracle(RULE, candidates=(0.0, 0.6), horizon_s=0.125)
    runner = KalmanRunner(trial)
    runner.advance(300, 0.5)
    q, p = runner.state.q.copy(), runner.state.p.copy()
    costs = oracle.candidate_costs(runner)
    np.testing.assert_array_equal(runner.state.q, q)
    np.testing.assert_array_equal(runner.state.p, p)
    start, horizon = runner.pos, int(round(0.125 * trial.rate))
    for gamma, cost in zip(oracle.levels, costs, strict=True):
        copy = KalmanRunner(trial)
        copy.advance(300, 0.5)
        copy.advance(8, gamma)
        while copy.pos < start + horizon:
            copy.advance(8, oracle.continuation_action(copy)[0])
        err = errors(copy.est[start : start + horizon], trial.q_true[start : start + horizon])[:, 0]
        assert cost == pytest.approx(np.sum(err**2), rel=1e-5)
    assert costs[0] != costs[1]


def test_oracle_beats_its_continuation_rule_and_is_deterministic(trial):
    oracle = KalmanOracle(RULE)
    a, b = oracle.run(trial), oracle.run(trial)
    np.testing.assert_array_equal(a.q, b.q)
    ours = evaluation.run_method("oracle", oracle, trial).score.total
    theirs = evaluation.run_method("rule", RULE, trial).score.total
    assert ours < theirs
    assert set(np.unique(a.trust[1:])) <= set(oracle.levels)


def test_continuation_action_is_the_rule_on_the_observation(trial):
    for rule in (RULE, AdaptiveTrust(2.7, 0.74)):
        oracle = KalmanOracle(rule)
        runner = KalmanRunner(trial, extended=True)
        for _ in range(40):
            assert oracle.continuation_action(runner)[0] == rule.weight(runner.feat[:19].astype(np.float32))
            runner.advance(8, 0.7)


def test_student_sees_the_rules_proposals(trial):
    """The packaged oracle's student gets, after each block of the extended observation, the γ of the
    continuation rule (kf_model_tuned) and of its proposal kf_adaptive_tuned, as those rules act on the
    observation (base block and its lagged copies)."""
    oracle = registry.make("oracle_kalman")
    rules = [registry.make("kf_model_tuned"), registry.make("kf_adaptive_tuned")]
    inputs = inputs_for(KALMAN_ID)
    meta = inputs.meta(oracle)
    runner = KalmanRunner(trial, extended=True)
    block, base = meta["block"], len(rules[0].features)
    for _ in range(60):
        obs = runner.feat.astype(np.float32)
        x = inputs(obs, meta)[0]
        assert x.shape == (obs.size + 2 * obs.size // block,)
        for b in range(obs.size // block):
            got = x[b * (block + 2) + block : (b + 1) * (block + 2)]
            want = [r.weight(obs[b * block : b * block + base]) for r in rules]
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
        runner.advance(8, 0.7)
    assert rules[1].weight(obs[:base]) != rules[0].weight(obs[:base])


def test_teacher_interface_registry_and_bad_arguments():
    oracle = registry.make("oracle_kalman")
    assert oracle.privileged and oracle.env_id == KALMAN_ID and dagger.check_teacher(oracle) == KALMAN_ID
    assert oracle.candidates.shape == (len(oracle.levels), 1) and oracle.rule.sigma_dist_ut > 0
    from magenv.train.compare import headroom_names

    assert headroom_names({"oracle_kalman": oracle, "kf_model_tuned": registry.make("kf_model_tuned")}) == {
        "oracle_kalman"
    }
    with pytest.raises(ValueError, match="candidates"):
        KalmanOracle(candidates=(0.0, 1.5))
    for horizon in (0.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="horizon_s"):
            KalmanOracle(horizon_s=horizon)
    with pytest.raises(ValueError, match="kf_model or kf_adaptive"):
        KalmanOracle(registry.make("kf_gate"))


def _student_and_teacher_candidates(trial, oracle, meta, decisions: int = 60):
    """(observation, the student's state candidates) along ``decisions`` decisions of γ = 0.7 in an extended
    runner, each asserted equal, bit for bit, to the teacher's ``state_candidates`` at that state."""
    inputs = inputs_for(KALMAN_ID)
    runner = KalmanRunner(trial, extended=True)
    for _ in range(decisions):
        obs = runner.feat.astype(np.float32)
        student = inputs.candidate_actions(obs, meta)[0]
        np.testing.assert_array_equal(student, oracle.state_candidates(runner))
        yield obs, student
        runner.advance(8, 0.7)


def test_rule_candidates_are_the_rules_gamma_bit_for_bit(trial):
    """``oracle_kalman_rules`` searches, after the fixed levels, the γ of kf_model_tuned and kf_adaptive_tuned
    on the env's observation; the student's state-dependent candidates (computed from that observation at
    act time) are the very same numbers as the teacher's (at label time) and as the rules' ``weight``."""
    oracle = registry.make("oracle_kalman_rules")
    rules = [registry.make("kf_model_tuned"), registry.make("kf_adaptive_tuned")]
    inputs = inputs_for(KALMAN_ID)
    meta = inputs.meta(oracle)
    assert meta["rule_candidates"] and inputs.n_state_candidates(meta) == 2
    assert inputs.n_state_candidates(inputs.meta(registry.make("oracle_kalman"))) == 0
    seen = set()
    for obs, student in _student_and_teacher_candidates(trial, oracle, meta):
        np.testing.assert_array_equal(student[:, 0], [r.weight(obs[: len(r.features)]) for r in rules])
        seen.add(tuple(student[:, 0]))
    assert len(seen) > 10  # the candidates move with the state


def _the_last_candidate_is(trial, teacher, key: str, rule) -> set:
    """Asserts that the teacher's last state candidate is ``rule``'s γ on the extended observation, bit for bit
    the student's (run.yaml student ``key``), which the student also sees after each block (on the features of
    now, 8 and 32 decisions before); returns the γ seen."""
    inputs = inputs_for(KALMAN_ID)
    meta = inputs.meta(teacher)
    assert meta[key] == getattr(teacher, f"{key}_params") and inputs.n_state_candidates(meta) == 3
    seen = set()
    for obs, student in _student_and_teacher_candidates(trial, teacher, meta):
        assert student[2, 0] == rule.weight(obs[[EXTENDED.index(n) for n in rule.features]])
        x = inputs(obs, meta)[0]
        block = len(obs) // 3
        assert x.size == obs.size + 3 * 3 and x[block + 2] == np.float32(student[2, 0])
        for b in (1, 2):  # the lagged blocks
            shifted = obs.copy()
            shifted[:block] = obs[b * block : (b + 1) * block]
            lagged = rule.weight(shifted[[EXTENDED.index(n) for n in rule.features]])
            assert x[b * (block + 3) + block + 2] == np.float32(lagged)
        seen.add(float(student[2, 0]))
    return seen


def test_the_still_candidate_is_kf_still_tuned_bit_for_bit(trial):
    """``oracle_kalman_still`` searches, after the two rules' γ, kf_still_tuned's γ on the extended observation;
    the student computes the same number from that observation (and sees it after each block), and the
    oracle's own run uses an extended runner."""
    oracle = registry.make("oracle_kalman_still")
    still = registry.make("kf_still_tuned")
    seen = _the_last_candidate_is(trial, oracle, "still", still)
    assert len(seen) > 5 and 0.0 in seen  # it moves with the state and refuses where the anchor disagrees
    with pytest.raises(ValueError, match="extended runner"):
        oracle.state_candidates(KalmanRunner(trial))
    with pytest.raises(ValueError, match="still must be"):  # the teacher's own rule, without rule_candidates
        KalmanOracle(RULE, still=oracle.still)
    with pytest.raises(ValueError, match="still must be"):  # rule_candidates, a rule not reading EXTENDED
        KalmanOracle(RULE, rule_candidates=True, still=still)
    KalmanOracle(RULE, rule_candidates=True, still=oracle.still)  # both conditions met
    assert oracle.run(trial).q.shape == trial.q_true.shape


def test_the_skip_teacher_offers_the_still_rule_on_stationary_trials_only(trial):
    """``oracle_kalman_skip`` costs γ = 0, kf_model_tuned's γ and kf_still_tuned's γ exactly as
    ``oracle_kalman_still`` costs them (the same continuations and look-ahead), except that on a trial of a
    scenario other than ``stationary_magnet`` the still candidate costs inf (the oracle never takes it there);
    its student sees and chooses among the three."""
    skip, still = registry.make("oracle_kalman_skip"), registry.make("oracle_kalman_still")
    np.testing.assert_array_equal(skip.levels, [0.0])
    assert skip.still_scenarios == ("stationary_magnet",) and skip.proposals == ()
    assert skip.horizon_s == still.horizon_s and skip.still_params == still.still_params
    on_stationary = dataclasses.replace(trial, meta={**trial.meta, "scenario": "stationary_magnet"})
    for tr, offered in ((trial, False), (on_stationary, True)):
        runner = KalmanRunner(tr, extended=True)
        for _ in range(3):
            runner.advance(160, 0.5)
            model_gamma, _, still_gamma = still.state_candidates(runner)[:, 0]
            np.testing.assert_array_equal(skip.state_candidates(runner)[:, 0], [model_gamma, still_gamma])
            gammas = np.array([0.0, model_gamma, still_gamma])
            want = still.candidate_costs(runner, gammas)
            got = skip.candidate_costs(runner)
            np.testing.assert_array_equal(skip.candidate_costs(runner, gammas), got)
            np.testing.assert_array_equal(got[:2], want[:2])
            assert got[2] == (want[2] if offered else np.inf) and np.all(np.isfinite(want))
        if not offered:  # the still candidate is known by its place: another layout is refused
            with pytest.raises(ValueError, match="levels then the state candidates"):
                skip.candidate_costs(runner, [0.0, 0.5])
    inputs = inputs_for(KALMAN_ID)
    assert inputs.n_state_candidates(inputs.meta(skip)) == 2
    with pytest.raises(ValueError, match="still_scenarios"):
        KalmanOracle(RULE, rule_candidates=True, still_scenarios=("stationary_magnet",))
    with pytest.raises(ValueError, match="still_scenarios"):
        KalmanOracle(RULE, rule_candidates=True, still=skip.still, still_scenarios=(1,))


def test_continuations_cost_the_cheaper_roll_out(trial):
    """With ``continuations`` a candidate costs the lowest of its roll-outs continuing with each rule; explicit
    ``candidates`` are costed as given, the default being the levels then the state candidates."""
    adaptive = AdaptiveTrust(2.7, 0.74)
    both = KalmanOracle(RULE, proposals=(adaptive,), rule_candidates=True, continuations=(adaptive,))
    runner = KalmanRunner(trial, extended=True)
    runner.advance(200, 0.5)
    gammas = np.array([0.0, 0.3, 1.0])
    model, adapt = (KalmanOracle(r).candidate_costs(runner, gammas) for r in (RULE, adaptive))
    np.testing.assert_array_equal(both.candidate_costs(runner, gammas[:, None]), np.minimum(model, adapt))
    assert np.any(model != adapt)
    default = np.concatenate([both.levels, both.state_candidates(runner)[:, 0]])
    np.testing.assert_array_equal(both.candidate_costs(runner), both.candidate_costs(runner, default))
    for bad in (np.zeros((3, 2)), [0.5, 1.5], [np.nan], []):  # a (C, 2) array is not 2C γ
        with pytest.raises(ValueError, match="candidates"):
            both.candidate_costs(runner, bad)
    trust = both.run(trial).trust[1:]
    assert np.any(~np.isin(trust[np.isfinite(trust)], both.levels))  # it follows a rule's γ at some decisions


def test_the_rules_teachers_need_their_tuned_rules(tmp_path, monkeypatch):
    """Without a tuned kf_adaptive, oracle_kalman_rules, _still and _skip are not themselves (no fallback
    rule, the still candidate at another index): a TunedParamsError naming the file, never a quieter teacher.
    oracle_kalman only loses its proposal."""
    for name in ("kf_model", "kf_still"):
        (tmp_path / f"{name}.json").write_text((registry.packaged_tuned_dir() / f"{name}.json").read_text())
    monkeypatch.setattr(registry, "packaged_tuned_dir", lambda: tmp_path)
    for name in ("oracle_kalman_rules", "oracle_kalman_still", "oracle_kalman_skip"):
        with pytest.raises(registry.TunedParamsError, match="kf_adaptive"):
            registry.make(name)
    assert registry.make("oracle_kalman").proposals == ()


def test_the_perp_teacher_adds_kf_perp_tuned_on_dynamic_magnet_trials_only(trial):
    """``oracle_kalman_perp``: ``oracle_kalman_skip``'s candidates, costed the same, then kf_perp_tuned's γ on the
    extended observation, which costs inf on a trial of another scenario than ``dynamic_magnet``; its student
    computes that γ bit for bit from the observation and sees it after each block."""
    teacher, skip = registry.make("oracle_kalman_perp"), registry.make("oracle_kalman_skip")
    assert len(_the_last_candidate_is(trial, teacher, "perp", registry.make("kf_perp_tuned"))) > 5
    on_dynamic = dataclasses.replace(trial, meta={**trial.meta, "scenario": "dynamic_magnet"})
    for tr, offered in ((trial, False), (on_dynamic, True)):
        runner = KalmanRunner(tr, extended=True)
        runner.advance(160, 0.5)
        got = teacher.candidate_costs(runner)
        np.testing.assert_array_equal(got[:3], skip.candidate_costs(runner))
        assert np.isfinite(got[3]) == offered
    with pytest.raises(ValueError, match="perp must be"):  # without rule_candidates
        KalmanOracle(RULE, perp=teacher.perp)
    with pytest.raises(ValueError, match="perp_scenarios"):
        KalmanOracle(RULE, rule_candidates=True, perp_scenarios=("dynamic_magnet",))
