"""The VQF oracle (``magenv.baselines.oracle_vqf``): look-ahead on the kernels, the teacher of MagVQF-v0's student."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml

from magenv import evaluation, metrics, registry
from magenv.agents import dagger
from magenv.agents.dagger_cv import cross_validate, fold_scenarios, make_folds, recording_of
from magenv.agents.student_inputs import inputs_for
from magenv.baselines.oracle_vqf import VQFOracle
from magenv.envs import VQF_ID
from magenv.envs.vqf import EXTENDED, VQFRunner
from magenv.train.cli import main
from tests.conftest import kinematic_trial
from tests.test_agents_dagger import TINY as DAGGER_TINY


@pytest.fixture(scope="module")
def disturbed():
    return kinematic_trial(seed=4, duration=12.0, disturbance_ut=40.0, disturbance_window=(3.0, 9.0))


def _rmse(q, trial) -> float:
    return metrics.score(q, trial.q_true, trial.score_mask).total


def test_candidate_costs_leave_the_filter_as_it_was(disturbed):
    oracle = VQFOracle(decision_every=16, horizon_s=0.8)
    a, b = VQFRunner(disturbed), VQFRunner(disturbed)
    for step in range(60):
        if step % 7 == 0:
            costs = oracle.candidate_costs(a)
            assert costs.shape == (5,) and np.all(costs >= 0)
        a.advance(16, 0.3)
        b.advance(16, 0.3)
    np.testing.assert_array_equal(a.est, b.est)
    np.testing.assert_array_equal(a.feat, b.feat)


def test_candidate_costs_are_the_env_run_with_the_candidate_held(disturbed):
    """A candidate's cost is Σ (total error)² of the runner continued with that trust over the horizon; with a
    terminal cost (oracle_vqf_tail) (Σ e_i² + e_last² · tail / Ts) · H / (H + tail / Ts)."""
    oracle = VQFOracle(candidates=(0.0, 0.6), decision_every=16, horizon_s=0.5)
    tailed = VQFOracle(candidates=(0.0, 0.6), decision_every=16, horizon_s=0.5, tail_s=2.0)
    runner = VQFRunner(disturbed)
    for _ in range(40):
        runner.advance(16, 1.0)
    horizon, tail = int(round(0.5 * disturbed.rate)), 2.0 * disturbed.rate
    start = runner.pos
    for u, cost, cost_tailed in zip((0.0, 0.6), oracle.candidate_costs(runner), tailed.candidate_costs(runner)):
        fork = VQFRunner(disturbed)
        fork.state[:] = runner.state
        fork.pos = start
        fork.advance(horizon, u)
        sl = slice(start, start + horizon)
        err = metrics.total_error(metrics.error_quaternion(fork.est[sl], disturbed.q_true[sl]))
        last = err[np.isfinite(err)][-1]
        assert cost == pytest.approx(np.nansum(err**2), rel=1e-9)
        assert cost_tailed == pytest.approx((cost + last**2 * tail) * horizon / (horizon + tail), rel=1e-9)
    assert registry.make("oracle_vqf_tail").tail_s == pytest.approx(4.5)
    with pytest.raises(ValueError, match="tail_s"):
        VQFOracle(tail_s=-1.0)


def test_the_oracle_beats_vqf_on_a_disturbed_trial(disturbed):
    oracle = VQFOracle(decision_every=32, horizon_s=1.0)
    vqf_q = evaluation.run_method("vqf", registry.make("vqf"), disturbed).q
    assert _rmse(oracle.run(disturbed).q, disturbed) < 0.8 * _rmse(vqf_q, disturbed)
    assert registry.make("oracle_vqf").privileged


def test_the_oracle_is_a_dagger_teacher_and_the_student_drops_the_heading_offset():
    teacher = registry.make("oracle_vqf")
    assert dagger.check_teacher(teacher) == VQF_ID
    assert teacher.candidates.shape == (5, 1) and teacher.env_kwargs == {"rejection": "on"}
    inputs = inputs_for(VQF_ID)
    meta = inputs.meta(teacher)
    obs = np.arange(len(EXTENDED), dtype=np.float32)[None]
    x = inputs(obs, meta)
    kept = [n for n in EXTENDED.names if not n.startswith("delta") or n.startswith("delta_rate")]
    assert x.shape == (1, len(kept))
    np.testing.assert_array_equal(x[0], [EXTENDED.index(n) for n in kept])


def _broad_file(path, trial):
    """``trial`` as a BROAD-layout recording file."""
    with h5py.File(path, "w") as f:
        for key, value in (("imu_gyr", trial.gyr), ("imu_acc", trial.acc), ("imu_mag", trial.mag),
                           ("opt_quat", trial.q_true), ("opt_pos", np.zeros((trial.n, 3))),
                           ("movement", np.ones(trial.n, bool))):  # fmt: skip
            f.create_dataset(key, data=value)
        f.attrs["sampling_rate"] = trial.rate
    return path


TINY = {**DAGGER_TINY, "iterations": 1, "scenarios": ["dynamic_magnet"], "decision_every": 32}


def test_a_student_learns_from_recordings_and_cross_validates_leaving_them_out(tmp_path):
    recs = tmp_path / "recs"
    recs.mkdir()
    for s in range(3):
        trial = kinematic_trial(seed=20 + s, duration=6.0, disturbance_ut=30.0, disturbance_window=(2.0, 4.0))
        _broad_file(recs / f"0{s}_test.hdf5", trial)
    config = {**TINY, "scenarios": ["dynamic_magnet", f"recording:{recs}/*.hdf5"]}
    cfg = dagger.check_config(config)
    paths = [recs.resolve() / f"0{i}_test.hdf5" for i in range(3)]
    assert [recording_of(sc) for sc in cfg["scenarios"]] == [None, *paths]
    assert make_folds(paths[::-1], 3) == [[p] for p in paths] and make_folds(paths, 2) == [paths[::2], paths[1:2]]
    twin = f"twin:{paths[0]}"  # a twin of a held-out recording counts as that recording
    assert fold_scenarios([*cfg["scenarios"], twin], [paths[0]]) == ["dynamic_magnet", *cfg["scenarios"][2:]]
    assert twin in fold_scenarios([*cfg["scenarios"], twin], [paths[1]])
    with pytest.raises(ValueError, match="at least 4 recordings"):
        make_folds([recs / "00_test.hdf5"], 4)
    seen = []
    real_train = dagger.train

    def spy(out, teacher, cfg_, log, **kw):
        seen.append(sorted(cfg_["scenarios"]))
        return real_train(out, teacher, cfg_, log, **kw)

    dagger.train, old = spy, dagger.train
    try:
        rows = cross_validate(tmp_path / "cv", registry.make("oracle_vqf"), config, folds=3, log=lambda s: None)
    finally:
        dagger.train = old
    assert [r["recording"] for r in rows] == ["00_test", "01_test", "02_test"]
    for fold, scen in enumerate(seen):  # no fold trains on its held-out recording or on its twin
        assert not any(f"0{fold}_test" in sc for sc in scen) and "dynamic_magnet" in scen
    assert all(r["agent_rmse"] > 0 and r["rule_rmse"] > 0 for r in rows)
    assert (tmp_path / "cv" / "cv.csv").read_text().count("\n") == 4
    run = yaml.safe_load((tmp_path / "cv" / "fold1" / "run.yaml").read_text())
    assert run["env_kwargs"] == {"features": "extended", "rejection": "on", "decision_every": 32}
    policy = registry.make(f"agent:{tmp_path / 'cv' / 'fold1'}")
    assert policy.env_id == VQF_ID


def test_cv_from_the_command_line(tmp_path, capsys):
    recs = tmp_path / "recs"
    recs.mkdir()
    for s in range(2):
        _broad_file(recs / f"0{s}_cli.hdf5", kinematic_trial(seed=30 + s, duration=4.0))
    cfg_file = tmp_path / "dagger.yaml"
    cfg_file.write_text(yaml.safe_dump({VQF_ID: {**TINY, "scenarios": ["dynamic_clean", f"recording:{recs}/*"]}}))
    args = ["train", "--teacher", "oracle_vqf", "--out", str(tmp_path / "cv"), "--config", str(cfg_file)]
    assert main([*args, "--cv", "recordings", "--folds", "2"]) == 0
    assert "held-out recordings: 2" in capsys.readouterr().out
    assert main([*args, "--cv", "recordings", "--resume"]) != 0


def test_the_rule_teacher_searches_and_continues_with_the_fan_rule_its_student_computes(disturbed, tmp_path):
    """``oracle_vqf_rule``: the tuned Fan rule's trust on top of VQF's rejection is a state-dependent candidate
    (the student's, computed from its float32 observation) and the continuation; a guard falls back on it."""
    teacher = registry.make("oracle_vqf_rule")
    params = registry.tuned_params("vqf_fan_lambda")
    assert teacher.rule == (params["norm_tol"], params["th_dip_deg"]) and teacher.env_kwargs == {"rejection": "on"}
    inputs = inputs_for(VQF_ID)
    meta = inputs.meta(teacher)
    assert meta["rule"] == list(teacher.rule) and inputs.n_state_candidates(meta) == 1
    cands = dagger.candidate_matrix(teacher.candidates)
    episodes = dagger.teacher_episodes(VQF_ID, dagger.student_env_kwargs(inputs, teacher, 32), teacher, inputs,
                                       meta, cands)  # fmt: skip
    lab = episodes.run(disturbed, lambda o, runner, c: teacher.continuation_action(runner))
    assert lab.costs.shape == (len(lab.obs), 6) and np.all(lab.rule >= 0)  # the rule is always a candidate
    assert np.any(lab.rule == 5) and np.ptp(lab.costs[:, 5]) > 0
    rule_only = dagger.Episodes(VQF_ID, dagger.student_env_kwargs(inputs, teacher, 32), teacher)
    plain = rule_only.run(disturbed, lambda o, runner, c: teacher.continuation_action(runner))
    assert lab.rmse == plain.rmse  # the same closed loop: the rule as the student computes it
    # the oracle's own search includes the rule: it does no worse than following it
    assert _rmse(teacher.run(disturbed).q, disturbed) <= lab.rmse
    guard = {"fallback": "rule", "margin": 0.1, "disagree": 0.5}
    out = dagger.train(tmp_path / "r", teacher, {**TINY, "guard": guard}, log=lambda s: None)
    policy = registry.make(f"agent:{out}")
    student = policy.student
    obs = lab.obs * 40.0  # far outside the fitted range: every decision falls back on the rule
    actions = np.array([student.action(o) for o in obs])
    np.testing.assert_array_equal(actions[:, 0], inputs.candidate_actions(obs, meta)[:, 0, 0])
    assert student.guarded == len(obs)
    # band 0: never a departure from the rule — the named baseline vqf_fan_rejection_tuned, closed loop
    policy.student = dagger.Student(student.layers, student.mu, student.sd, student.candidates, student.feature_fn,
                                    student.meta, student.act, student.bounds, {**guard, "band": 0.0})  # fmt: skip
    banded = evaluation.run_method("s", policy, disturbed)
    rule = evaluation.run_method("r", registry.make("vqf_fan_rejection_tuned"), disturbed)
    np.testing.assert_allclose(banded.q, rule.q, rtol=0, atol=1e-12)
    assert 0 < np.ptp(banded.trust) and banded.trust.min() < 1.0
    with pytest.raises(ValueError, match="fallback 'rule' needs"):
        dagger.train(tmp_path / "u", registry.make("oracle_vqf"), {**TINY, "guard": guard}, log=lambda s: None)
    assert not (tmp_path / "u").exists()
    with pytest.raises(ValueError, match="guard fallback"):
        dagger.check_config({**TINY, "guard": {**guard, "fallback": "vqf"}})
