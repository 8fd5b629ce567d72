"""DAgger from the oracle (``magenv train --teacher oracle``): a weights-only run folder that loads as an agent."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from magenv import evaluation, registry
from magenv.agents import dagger
from magenv.agents.loading import RunError, load_agent
from magenv.agents.student_inputs import StudentInputs, inputs_for
from magenv.agents.weights import FORMAT
from magenv.baselines.rules import FanLambda
from magenv.envs import BLEND_ID
from magenv.envs.blend import BlendRunner
from magenv.train.cli import main

TINY = {
    "iterations": 2,
    "trials_per_scenario": 1,
    "scenarios": ["dynamic_clean"],
    "val_seeds": [5000, 5001],
    "fit_steps": 20,
    "hidden": [8],
}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("dagger") / "run"
    config = tmp_path_factory.mktemp("cfg") / "dagger.yaml"
    config.write_text(yaml.safe_dump({"magenv/MagBlend-v0": TINY}))
    assert main(["train", "--teacher", "oracle", "--out", str(out), "--config", str(config)]) == 0
    return out


def test_run_folder_holds_weights_only(run_dir):
    files = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*") if p.is_file())
    assert files == [".lock", "best.safetensors", "checkpoints/it_0.safetensors", "checkpoints/it_1.safetensors",
                     "data/it_0.npz", "data/it_1.npz", "iterations.csv", "run.yaml", "state.json"]  # fmt: skip
    state = json.loads((run_dir / "state.json").read_text())
    assert state["iterations"] == 2 and sorted(state["files"]) == ["best.safetensors", "iterations.csv", "run.yaml"]
    with np.load(run_dir / "data" / "it_1.npz", allow_pickle=False) as data:
        assert data["obs"].dtype == np.float32 and data["regret"].shape == (len(data["obs"]), 5)
        assert data["regret"].min() == 0.0  # the regret of each state's cheapest candidate
        assert data["rule"].dtype == np.int16 and data["rule"].shape == (len(data["obs"]),)
        assert data["rule"].min() >= -1 and data["rule"].max() < 5
    run = yaml.safe_load((run_dir / "run.yaml").read_text())
    assert run["algo"] == "dagger" and run["env_kwargs"]["features"] == "extended"
    assert run["config"]["train_seed"] >= 10000 and run["teacher"] == "oracle"
    assert len((run_dir / "iterations.csv").read_text().splitlines()) == 3


def test_loads_as_an_agent_in_compare(run_dir, make_kinematic_trial):
    agent = registry.make(f"agent:{run_dir}")
    assert agent.env_id == "magenv/MagBlend-v0" and agent.which == "best"
    trial = make_kinematic_trial(seed=1, duration=3.0)
    a = evaluation.run_method("a", agent, trial)
    b = evaluation.run_method("b", load_agent(run_dir), trial)
    np.testing.assert_array_equal(a.q, b.q)  # deterministic
    assert np.all((a.lam >= 0) & (a.lam <= 1))
    with pytest.raises(RunError, match="cannot act in"):
        load_agent(run_dir, env_id="magenv/MagKalman-v0")


def test_refuses_an_existing_run_and_bad_configs(run_dir):
    oracle = registry.make("oracle")
    with pytest.raises(ValueError, match="already holds a run"):
        dagger.train(run_dir, oracle, TINY)
    for bad, match in (
        ({"train_seed": 42}, "train_seed"),
        ({"val_seeds": [0, 20]}, "validation seeds"),
        ({"bogus": 1}, "unknown DAgger config"),
        ({"iterations": 0}, "iterations"),
        ({"seed": -1}, "'seed'"),
        ({"seed": "x"}, "'seed'"),
        ({"seed": 1.5}, "'seed'"),
        ({"val_seeds": [5000]}, "val_seeds"),
        ({"val_seeds": [5000.0, 5002.0]}, "val_seeds"),
        ({"beta": "x"}, "'beta'"),
        ({"learning_rate": True}, "'learning_rate'"),
        ({"hidden": 8}, "hidden"),
        ({"hidden": [True]}, "hidden"),
        ({"scenarios": []}, "'scenarios'"),
        ({"scenarios": 5}, "'scenarios'"),
    ):
        with pytest.raises(ValueError, match=match):
            dagger.check_config(bad)
    with pytest.raises(ValueError, match="cannot teach"):
        dagger.train(run_dir.parent / "other", registry.make("fan_lambda"), TINY)
    with pytest.raises(ValueError, match="decision_every 4 differs"):
        dagger.train(run_dir.parent / "other", oracle, {**TINY, "decision_every": 4})
    other = str(run_dir.parent / "other")
    assert main(["train", "--teacher", "oracle", "--env", "magenv/MagQSF-v0", "--out", other]) == 2


def test_weights_that_do_not_fit_are_refused(run_dir, tmp_path):
    """A student section or weights file that is not one of ours: RunError naming the problem, never a policy
    that acts with NaN or fails at its first action."""
    from safetensors.numpy import load_file, save_file

    good = yaml.safe_load((run_dir / "run.yaml").read_text())
    tensors = load_file(run_dir / "best.safetensors")

    def load(student=None, **changed):
        (tmp_path / "run.yaml").write_text(yaml.safe_dump({**good, "student": student or good["student"]}))
        meta = {"format": FORMAT, "algo": '"dagger"'}
        save_file({**tensors, **changed}, tmp_path / "best.safetensors", metadata=meta)
        return load_agent(tmp_path)

    assert load().student.layers[0][0].shape == tensors["layer0/weight"].shape  # the unchanged copy loads
    for student, match in (
        ({**good["student"], "hidden": [16]}, "do not fit"),
        ({k: v for k, v in good["student"].items() if k != "n_inputs"}, "student section"),
        ({**good["student"], "candidates": []}, "student section"),
        ({**good["student"], "block": 0}, "block"),
    ):
        with pytest.raises(RunError, match=match):
            load(student)
    sd_nan = tensors["sd"].copy()
    sd_nan[0] = np.nan
    for changed, match in (
        ({"layer0/bias": tensors["layer0/bias"][:1]}, "do not fit"),
        ({"sd": sd_nan}, "non-finite"),
        ({"sd": np.zeros_like(tensors["sd"])}, "non-positive"),
    ):
        with pytest.raises(RunError, match=match):
            load(**changed)


def test_resuming_with_ensemble_1_makes_the_best_iteration_the_student_again(run_dir, tmp_path):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    oracle = registry.make("oracle")
    dagger.add_ensemble(out, oracle, 2, log=lambda s: None)
    dagger.train(out, oracle, {"iterations": 3, "ensemble": 1}, log=lambda s: None, resume=True)
    run = yaml.safe_load((out / "run.yaml").read_text())
    assert "ensemble" not in run and run["config"]["ensemble"] == 1
    assert not isinstance(load_agent(out).student, dagger.Ensemble)


def test_data_files_with_undefined_regrets_are_refused(run_dir, tmp_path):
    with np.load(run_dir / "data" / "it_0.npz", allow_pickle=False) as z:
        obs, regret = z["obs"], z["regret"]
    for o, r in ((obs, np.where(regret > 0, np.nan, regret)), (obs.astype(np.float64), regret), (obs, -regret - 1)):
        np.savez(tmp_path / "it_0.npz", obs=o, regret=r.astype(np.float32))
        with pytest.raises(RunError, match="float32"):
            dagger._load_data(tmp_path / "it_0.npz", regret.shape[1], obs.shape[1])


def test_data_files_with_bad_rule_candidates_are_refused_and_old_ones_have_none(run_dir, tmp_path):
    with np.load(run_dir / "data" / "it_0.npz", allow_pickle=False) as z:
        obs, regret, rule = z["obs"], z["regret"], z["rule"]
    for bad in (rule.astype(np.int64), rule[:-1], np.full_like(rule, 5), np.full_like(rule, -2)):
        np.savez(tmp_path / "it_0.npz", obs=obs, regret=regret, rule=bad)
        with pytest.raises(RunError, match="rule must be"):
            dagger._load_data(tmp_path / "it_0.npz", regret.shape[1], obs.shape[1])
    np.savez(tmp_path / "it_0.npz", obs=obs, regret=regret)  # a run from before the rule was kept
    assert dagger._load_data(tmp_path / "it_0.npz", regret.shape[1], obs.shape[1])[2] is None


def test_rule_margin_adds_to_every_candidate_but_the_rules():
    """``rule_margin: m`` fits the student of the regrets with m added to every candidate but the state's rule
    candidate (states without one unchanged); it needs the rule candidates."""
    regret = np.array([[0.0, 2.0, 5.0], [1.0, 0.0, 3.0], [4.0, 4.0, 0.0]], np.float32)
    got = dagger.with_rule_margin(regret, np.array([2, -1, 0], np.int16), 10.0)
    np.testing.assert_array_equal(got, [[10.0, 12.0, 5.0], [1.0, 0.0, 3.0], [4.0, 14.0, 10.0]])
    rng = np.random.default_rng(0)
    x = rng.normal(size=(128, 3)).astype(np.float32)
    regret = rng.uniform(0.0, 5.0, (128, 2)).astype(np.float32)
    rule = rng.integers(-1, 2, 128).astype(np.int16)
    cfg = dagger.check_config({"fit_steps": 10, "hidden": [4], "batch_size": 64})
    inputs, cands = StudentInputs(), [0.0, 1.0]
    margin = dagger.fit(x, regret, {**cfg, "rule_margin": 3.0}, 0, cands, inputs, {}, rule)
    by_hand = dagger.fit(x, dagger.with_rule_margin(regret, rule, 3.0), cfg, 0, cands, inputs, {})
    for (w1, b1), (w2, b2) in zip(margin.layers, by_hand.layers, strict=True):
        np.testing.assert_array_equal(w1, w2)
        np.testing.assert_array_equal(b1, b2)
    with pytest.raises(ValueError, match="rule_margin needs"):
        dagger.fit(x, regret, {**cfg, "rule_margin": 3.0}, 0, cands, inputs, {})
    for bad in (-1.0, float("inf"), True, "1"):
        with pytest.raises(ValueError, match="rule_margin"):
            dagger.check_config({"rule_margin": bad})


def test_an_ensemble_of_iterations_acts_with_their_mean_probabilities(run_dir, tmp_path, make_kinematic_trial):
    """``add_ensemble``: the run's iterations by validation score, scored, recorded in run.yaml; the loaded policy
    averages the members' candidate probabilities; a bad member name is refused."""
    import shutil

    ens_dir = tmp_path / "ens"
    shutil.copytree(run_dir, ens_dir)
    entry = dagger.add_ensemble(ens_dir, registry.make("oracle"), 2, log=lambda s: None)
    run = yaml.safe_load((ens_dir / "run.yaml").read_text())
    assert run["config"]["ensemble"] == 2 and run["ensemble"] == entry
    assert sorted(entry["members"]) == ["checkpoints/it_0.safetensors", "checkpoints/it_1.safetensors"]
    assert entry["val_ratio"] == pytest.approx(entry["dynamic_clean_ratio"])
    policy = load_agent(ens_dir)
    assert isinstance(policy.student, dagger.Ensemble)
    inputs = inputs_for(BLEND_ID)
    members = [dagger.Student.load(ens_dir / m, run["student"], inputs) for m in entry["members"]]
    x = np.random.default_rng(0).normal(size=(4, run["student"]["n_inputs"])).astype(np.float32)
    mean = (members[0].probabilities(x) + members[1].probabilities(x)) / 2
    np.testing.assert_allclose(policy.student.probabilities(x), mean, rtol=1e-6)
    assert not np.allclose(members[0].probabilities(x), members[1].probabilities(x))  # two different fits
    trial = make_kinematic_trial(seed=1, duration=3.0)
    a, b = (evaluation.run_method(n, load_agent(ens_dir), trial) for n in "ab")
    np.testing.assert_array_equal(a.q, b.q)
    log_rows = (ens_dir / "iterations.csv").read_text().splitlines()
    scores = [float(r.split(",")[3]) for r in log_rows[1:]]
    single = dagger.add_ensemble(ens_dir, registry.make("oracle"), 1, log=lambda s: None)
    assert single["members"] == [f"checkpoints/it_{int(np.argmin(scores))}.safetensors"]  # the lowest score
    assert entry["members"][0] == single["members"][0]  # members in score order
    with pytest.raises(ValueError, match="not 'oracle_kalman'|searches"):
        dagger.add_ensemble(ens_dir, registry.make("oracle_kalman"), 1)
    for bad in ({"members": ["../run.yaml"]}, {"members": []}, ["checkpoints/it_0.safetensors"]):
        (ens_dir / "run.yaml").write_text(yaml.safe_dump({**run, "ensemble": bad}))
        with pytest.raises(RunError, match="ensemble"):
            load_agent(ens_dir)
    with pytest.raises(ValueError, match="ensemble of 3 iterations"):
        dagger.add_ensemble(ens_dir, registry.make("oracle"), 3)
    with pytest.raises(ValueError, match="cannot exceed iterations"):
        dagger.check_config({"iterations": 2, "ensemble": 3})


def test_rule_inputs_are_the_continuation_rule(make_kinematic_trial):
    """The λ column after each block of the student's input is the Fan rule on that block's observation."""
    oracle = registry.make("oracle")
    rule = FanLambda(oracle.norm_tol, oracle.th_dip_deg)
    runner = BlendRunner(make_kinematic_trial(seed=2, duration=2.0, disturbance_ut=30.0), extended=True)
    for _ in range(40):
        runner.advance(8, 0.5)
    inputs = inputs_for(BLEND_ID)
    x = inputs(runner.feat, inputs.meta(oracle))[0]
    obs = runner.feat.astype(np.float32)
    for b in range(3):
        assert x[43 * b + 42] == pytest.approx(rule.weight(obs[42 * b : 42 * b + 13]), abs=1e-6)
        np.testing.assert_array_equal(x[43 * b : 43 * b + 42], obs[42 * b : 42 * (b + 1)])


def test_blend_oracle_follows_the_teacher_interface(make_kinematic_trial):
    oracle = registry.make("oracle")
    assert dagger.check_teacher(oracle) == BLEND_ID and oracle.candidates.shape == (5, 1)
    runner = BlendRunner(make_kinematic_trial(seed=4, duration=2.0, disturbance_ut=30.0))
    runner.advance(80, 0.3)
    costs = oracle.candidate_costs(runner)
    assert costs.shape == (5,) and oracle.best_lambda(runner) == oracle.candidates[np.argmin(costs), 0]
    np.testing.assert_array_equal(oracle.continuation_action(runner), [oracle.continuation_lambda(runner)])
    with pytest.raises(ValueError, match="searches magenv/MagBlend-v0, not magenv/MagQSF-v0"):
        dagger.check_teacher(oracle, "magenv/MagQSF-v0")


def test_student_acts_with_the_probability_weighted_candidate():
    """Two-dimensional candidates: the action is p @ candidates, p the softmax of the logits."""
    layers = [(np.zeros((3, 2)), np.log([1.0, 2.0, 1.0]))]
    student = dagger.Student(layers, [0, 0], [1, 1], [[0.0, 1.0], [1.0, 0.0], [0.5, 0.5]], StudentInputs(), {})
    np.testing.assert_allclose(student.action(np.zeros(2)), [0.25 * 0 + 0.5 * 1 + 0.25 * 0.5, 0.25 + 0.125])
    with pytest.raises(ValueError, match="candidates"):
        dagger.candidate_matrix(np.zeros((2, 2, 2)))


def test_an_argmax_student_acts_with_its_most_probable_candidate(run_dir, tmp_path):
    """``act: argmax``: the candidate of the largest probability (MagQSF-v0's none/start are not averaged into
    keep); a run.yaml student with ``act: argmax`` loads as such, one without it acts with the mean."""
    layers = [(np.zeros((3, 2)), np.log([1.0, 1.5, 2.0]))]
    cands = [[-1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
    student = dagger.Student(layers, [0, 0], [1, 1], cands, StudentInputs(), {}, act="argmax")
    np.testing.assert_array_equal(student.action(np.zeros(2)), [1.0, 1.0])
    with pytest.raises(ValueError, match="act must be one of"):
        dagger.Student(layers, [0, 0], [1, 1], cands, StudentInputs(), {}, act="median")
    with pytest.raises(ValueError, match="act must be one of"):
        dagger.check_config({"act": "max"})
    run = yaml.safe_load((run_dir / "run.yaml").read_text())
    assert "act" not in run["student"] and load_agent(run_dir).student.act == "mean"
    run["student"]["act"] = "argmax"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(run))
    (tmp_path / "best.safetensors").write_bytes((run_dir / "best.safetensors").read_bytes())
    assert load_agent(tmp_path).student.act == "argmax"


def _same_chain(a, b):
    """Two run folders with the same students, data and validation log (all but the fit times), byte for byte."""
    weights = ["best.safetensors", *(f"checkpoints/it_{i}.safetensors" for i in range(3))]
    for name in ["run.yaml", *(f"data/it_{i}.npz" for i in range(3)), *weights]:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name

    def log(run):
        lines = (run / "iterations.csv").read_text().splitlines()
        col = lines[0].split(",").index("fit_s")
        return [[v for i, v in enumerate(line.split(",")) if i != col] for line in lines]

    assert log(a) == log(b)


def test_trials_per_scenario_may_differ_by_scenario(tmp_path, monkeypatch):
    """A mapping scenario → n gives each scenario its own count of new, distinct training trials per iteration
    (iteration j: seeds train_seed + n·j …); a mapping that misses a listed scenario or holds a non-count is
    refused."""
    import magenv.scenarios

    drawn, make = [], magenv.scenarios.make_trial

    def recording(name, seed, **kwargs):
        if seed >= 10000:
            drawn.append((name, seed))
        return make(name, seed, **kwargs)

    monkeypatch.setattr(magenv.scenarios, "make_trial", recording)
    per = {"dynamic_clean": 2, "stationary_magnet": 1}
    cfg = {**TINY, "scenarios": list(per), "trials_per_scenario": per, "first": "rule", "label_every": 64}
    dagger.train(tmp_path / "per", registry.make("oracle"), cfg, log=lambda line: None)
    assert drawn == [
        *[("dynamic_clean", 10000), ("dynamic_clean", 10001), ("stationary_magnet", 10000)],
        *[("dynamic_clean", 10002), ("dynamic_clean", 10003), ("stationary_magnet", 10001)],
    ]
    for bad in ({"dynamic_clean": 2}, {"dynamic_clean": 2, "stationary_magnet": 0}, 1.5):
        with pytest.raises(ValueError, match="trials_per_scenario"):
            dagger.check_config({"scenarios": list(per), "trials_per_scenario": bad})


def test_a_resumed_run_is_bit_for_bit_the_uninterrupted_one(tmp_path):
    """Two iterations resumed to three — with the run's data kept, or with them deleted (rebuilt from its
    checkpoints) — give the three-iteration run's students, data and log exactly."""
    oracle, quiet = registry.make("oracle"), (lambda line: None)
    whole = dagger.train(tmp_path / "whole", oracle, {**TINY, "iterations": 3}, log=quiet)
    kept = dagger.train(tmp_path / "kept", oracle, TINY, log=quiet)
    assert main(["train", "--teacher", "oracle", "--out", str(kept), "--resume", "--iters", "3"]) == 0
    _same_chain(whole, kept)
    rebuilt = dagger.train(tmp_path / "rebuilt", oracle, {**TINY, "iterations": 1}, log=quiet)
    (rebuilt / "data" / "it_0.npz").unlink()
    dagger.train(rebuilt, oracle, {"iterations": 3}, log=quiet, resume=True)
    _same_chain(whole, rebuilt)
    with pytest.raises(ValueError, match=r"keeps its config; \['fit_steps'\]"):
        dagger.train(kept, oracle, {"iterations": 4, "fit_steps": 99}, resume=True)
    before = (kept / "run.yaml").read_bytes()
    with pytest.raises(ValueError, match="holds 3 iterations already"):
        dagger.train(kept, oracle, {"iterations": 2}, resume=True)
    (rebuilt / "data" / "it_2.npz").unlink()
    (rebuilt / "checkpoints" / "it_1.safetensors").unlink()
    with pytest.raises(ValueError, match=r"cannot rebuild the data of iterations \[2\]"):
        dagger.train(rebuilt, oracle, {"iterations": 4}, resume=True)
    assert (kept / "run.yaml").read_bytes() == before  # a refused resume leaves the run as it was
    (tmp_path / "stale" / "data").mkdir(parents=True)
    (tmp_path / "stale" / "data" / "it_0.npz").write_bytes((kept / "data" / "it_0.npz").read_bytes())
    with pytest.raises(ValueError, match="holds another run's data"):
        dagger.train(tmp_path / "stale", oracle, TINY, log=quiet)
    assert main(["train", "--out", str(kept), "--resume"]) == 2  # --resume without --teacher
    with pytest.raises(ValueError, match="no DAgger run to resume"):
        dagger.train(tmp_path / "none", oracle, {"iterations": 2}, resume=True)
    with pytest.raises(ValueError, match="not of 'oracle_kalman'"):
        dagger.train(kept, registry.make("oracle_kalman"), {"iterations": 4}, resume=True)


def test_a_kalman_student_from_oracle_kalman(tmp_path):
    """The same loop teaches a MagKalman-v0 student (extended observation, rule-driven first iteration, sparse
    labels); it loads as an agent of that env."""
    cfg = {**TINY, "iterations": 1, "label_every": 64, "first": "rule", "scenarios": ["dynamic_clean"]}
    out = dagger.train(tmp_path / "k", registry.make("oracle_kalman"), cfg, log=lambda line: None)
    run = yaml.safe_load((out / "run.yaml").read_text())
    assert run["env_id"] == "magenv/MagKalman-v0" and run["student"]["n_inputs"] == 129 + 3 * 2  # 2 rules, 3 blocks
    agent = load_agent(out)
    assert agent.env_id == "magenv/MagKalman-v0" and agent.env_kwargs["features"] == "extended"
    with pytest.raises(ValueError, match="first"):
        dagger.check_config({"first": "oracle"})


def test_a_kalman_student_with_the_rules_gamma_as_candidates(tmp_path):
    """With ``oracle_kalman_rules`` the student scores the fixed γ levels and then the rules' γ of each state;
    the teacher costs, at label time, exactly the candidates the student acts with at that observation, and
    the student's action is its probability-weighted mean of them."""
    teacher = registry.make("oracle_kalman_rules")
    seen = []

    class Recording:  # the teacher, recording what it is asked to cost
        def __getattr__(self, name):
            return getattr(teacher, name)

        def candidate_costs(self, runner, candidates=None):
            seen.append((runner.feat.astype(np.float32), np.array(candidates), teacher.state_candidates(runner)))
            return teacher.candidate_costs(runner, candidates)

    cfg = {**TINY, "iterations": 1, "label_every": 64, "first": "rule", "scenarios": ["dynamic_clean"]}
    out = dagger.train(tmp_path / "kr", Recording(), cfg, log=lambda line: None)
    run = yaml.safe_load((out / "run.yaml").read_text())
    assert run["teacher"] == "oracle_kalman_rules" and run["student"]["rule_candidates"] is True
    student = load_agent(out).student
    assert student.n_state == 2 and student.layers[-1][0].shape[0] == len(teacher.levels) + 2
    assert len(seen) > 5
    for obs, cands, own in seen:
        np.testing.assert_array_equal(cands, student.candidates_at(obs))
        np.testing.assert_array_equal(cands[len(teacher.levels) :], own)
    obs = seen[-1][0]
    p = student.probabilities(student.inputs(obs))[0]
    assert student.action(obs)[0] == pytest.approx(p @ student.candidates_at(obs)[:, 0], rel=1e-12)


def _regret_factor(tmp_path, teacher, cfg: dict, scale: str) -> np.ndarray:
    """The first iteration's labels with ``regret_scale: scale`` over those with ``rule``, where positive: one
    factor for the whole trial (checked)."""
    regrets = []
    for name in ("rule", scale):
        out = dagger.train(tmp_path / name, teacher, {**cfg, "regret_scale": name}, log=lambda line: None)
        with np.load(out / "data" / "it_0.npz") as z:
            regrets.append(z["regret"])
    positive = regrets[0] > 0
    factor = regrets[1][positive] / regrets[0][positive]
    np.testing.assert_allclose(factor, factor[0], rtol=1e-5)
    return factor


def test_regret_scale_best_rule_scales_by_the_best_rules_mse(tmp_path):
    """``regret_scale: best_rule``: the same labels, in % of the lowest MSE of the teacher's rules (each alone)
    instead of the continuation rule's: one factor ≥ 1 per trial; teachers without rules are refused."""
    cfg = {**TINY, "iterations": 1, "label_every": 64, "first": "rule", "scenarios": ["stationary_magnet"]}
    factor = _regret_factor(tmp_path, registry.make("oracle_kalman_rules"), cfg, "best_rule")
    assert factor[0] > 1.01  # kf_adaptive_tuned beats the continuation kf_model_tuned on stationary_magnet
    with pytest.raises(ValueError, match="rule_actions"):
        dagger.train(tmp_path / "b", registry.make("oracle"), {**TINY, "regret_scale": "best_rule"})
    with pytest.raises(ValueError, match="regret_scale"):
        dagger.check_config({"regret_scale": "median"})


def test_regret_scale_teacher_scales_by_the_teachers_own_mse(tmp_path):
    """``regret_scale: teacher``: the same labels, in % of the MSE of the teacher's own closed-loop run on the
    trial — one factor per trial, the rule's MSE over the teacher's, > 1 where the teacher does better."""
    cfg = {**TINY, "iterations": 1, "label_every": 16}
    factor = _regret_factor(tmp_path, registry.make("oracle"), cfg, "teacher")
    assert factor[0] > 1.0  # the oracle does better than its continuation rule on the trial


def test_regret_clip_bounds_each_states_loss():
    """``regret_clip: R`` fits exactly the student of the regrets clipped at R (the data keep the raw values);
    without it a state of huge regret changes the fit. Bad clips are refused."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(256, 3)).astype(np.float32)
    regret = rng.uniform(0.0, 5.0, (256, 2)).astype(np.float32)
    regret[::17, 0] = 1e5  # the states of a diverged roll-out
    raw = regret.copy()
    cfg = dagger.check_config({"fit_steps": 20, "hidden": [4], "batch_size": 64})
    inputs, cands = StudentInputs(), [0.0, 1.0]
    clipped = dagger.fit(x, regret, {**cfg, "regret_clip": 10.0}, 0, cands, inputs, {})
    by_hand = dagger.fit(x, np.minimum(regret, 10.0), cfg, 0, cands, inputs, {})
    unclipped = dagger.fit(x, regret, cfg, 0, cands, inputs, {})
    np.testing.assert_array_equal(regret, raw)
    for (w1, b1), (w2, b2) in zip(clipped.layers, by_hand.layers, strict=True):
        np.testing.assert_array_equal(w1, w2)
        np.testing.assert_array_equal(b1, b2)
    assert not np.array_equal(clipped.layers[-1][0], unclipped.layers[-1][0])
    regret[0, 1] = np.inf  # a failed roll-out: the clip bounds it, an unclipped fit refuses it
    assert np.all(np.isfinite(dagger.fit(x, regret, {**cfg, "regret_clip": 10.0}, 0, cands, inputs, {}).layers[-1][0]))
    with pytest.raises(ValueError, match="set regret_clip"):
        dagger.fit(x, regret, cfg, 0, cands, inputs, {})
    for bad in (0, -1.0, float("inf"), True, "10"):
        with pytest.raises(ValueError, match="regret_clip"):
            dagger.check_config({"regret_clip": bad})


def test_refit_fits_one_student_on_all_of_a_runs_data(run_dir, tmp_path):
    """``magenv train --teacher oracle --refit SOURCE``: one fresh student of the changed fit keys on every
    iteration's data of SOURCE — the same student as ``dagger.fit`` on those data — scored and loadable; keys
    other than the fit keys, or a run without its data, are refused."""
    config = tmp_path / "refit.yaml"
    config.write_text(yaml.safe_dump({"magenv/MagBlend-v0": {"hidden": [6, 6], "fit_steps": 10, "seed": 3}}))
    out = tmp_path / "refit"
    argv = ["train", "--teacher", "oracle", "--refit", str(run_dir), "--out", str(out), "--config", str(config)]
    assert main(argv) == 0
    run = yaml.safe_load((out / "run.yaml").read_text())
    assert run["student"]["hidden"] == [6, 6] and run["config"]["fit_steps"] == 10
    assert run["refit_of"]["run"] == str(run_dir) and run["refit_of"]["iterations"] == 2
    assert len((out / "iterations.csv").read_text().splitlines()) == 2  # header and one row
    source = yaml.safe_load((run_dir / "run.yaml").read_text())
    inputs = inputs_for(source["env_id"])
    meta = {k: v for k, v in source["student"].items() if k not in dagger._SHAPE_KEYS}
    obs, regret = [], []
    for j in range(2):
        with np.load(run_dir / "data" / f"it_{j}.npz", allow_pickle=False) as z:
            obs.append(z["obs"])
            regret.append(z["regret"])
    cfg = dagger.check_config({**source["config"], "hidden": [6, 6], "fit_steps": 10, "seed": 3, "ensemble": 1})
    x = inputs(np.concatenate(obs), meta)
    expected = dagger.fit(x, np.concatenate(regret), cfg, 3, source["student"]["candidates"], inputs, meta)
    got = dagger.load_policy(out).student
    for (w1, b1), (w2, b2) in zip(got.layers, expected.layers, strict=True):
        np.testing.assert_array_equal(w1, w2)
        np.testing.assert_array_equal(b1, b2)
    with pytest.raises(ValueError, match="may change only"):
        dagger.refit(run_dir, tmp_path / "other", registry.make("oracle"), {"scenarios": ["dynamic_magnet"]})
    with pytest.raises(ValueError, match="already holds a run"):
        dagger.refit(run_dir, out, registry.make("oracle"), {})
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("run.yaml", "iterations.csv"):
        (bare / name).write_bytes((run_dir / name).read_bytes())
    with pytest.raises(ValueError, match="needs the labelled data"):
        dagger.refit(bare, tmp_path / "x", registry.make("oracle"), {})
    with pytest.raises(ValueError, match="no DAgger run to refit"):
        dagger.refit(tmp_path / "none", tmp_path / "x", registry.make("oracle"), {})
    import copy

    retuned = copy.copy(registry.make("oracle"))
    retuned.norm_tol *= 2  # its continuation rule re-tuned since the run: another rule's labels and ratios
    with pytest.raises(ValueError, match="student constants"):
        dagger.refit(run_dir, tmp_path / "x", retuned, {})
    with pytest.raises(ValueError, match="cannot teach"):
        dagger.refit(run_dir, tmp_path / "x", registry.make("fan_lambda"), {})


def test_refit_needs_its_config(run_dir, tmp_path, capsys):
    assert main(["train", "--teacher", "oracle", "--refit", str(run_dir), "--out", str(tmp_path / "y")]) == 2
    assert "--refit needs --config" in capsys.readouterr().err


def test_ensemble_members_are_best_or_checkpoints(run_dir, tmp_path):
    """run.yaml ``ensemble`` members may name best.safetensors or files in checkpoints/, nothing else."""
    folder = tmp_path / "ens"
    for p in run_dir.rglob("*"):
        if p.is_file() and "data" not in p.parts:
            (folder / p.relative_to(run_dir)).parent.mkdir(parents=True, exist_ok=True)
            (folder / p.relative_to(run_dir)).write_bytes(p.read_bytes())
    run = yaml.safe_load((folder / "run.yaml").read_text())
    run["ensemble"] = {"members": ["best.safetensors", "checkpoints/it_0.safetensors"]}
    (folder / "run.yaml").write_text(yaml.safe_dump(run))
    assert len(dagger.load_policy(folder).student.members) == 2
    for bad in ("../best.safetensors", "run.yaml", "checkpoints/../../x.safetensors"):
        run["ensemble"] = {"members": [bad]}
        (folder / "run.yaml").write_text(yaml.safe_dump(run))
        with pytest.raises(RunError, match="ensemble member"):
            dagger.load_policy(folder)


def test_a_guarded_student_falls_back_outside_its_inputs_range_and_where_members_disagree(tmp_path):
    guard = {"fallback": [0.9], "margin": 0.1, "disagree": 0.2}
    out = dagger.train(tmp_path / "g", registry.make("oracle"), {**TINY, "guard": guard, "ensemble": 2},
                       log=lambda s: None)  # fmt: skip
    run = yaml.safe_load((out / "run.yaml").read_text())
    assert run["student"]["guard"] == guard
    policy = dagger.load_policy(out)
    student = policy.student
    assert isinstance(student, dagger.Ensemble) and all(m.bounds is not None for m in student.members)
    member = student.members[0]
    lo, hi = member.bounds
    env = dagger.Episodes(BLEND_ID, run["env_kwargs"], registry.make("oracle")).env(
        dagger.make_trial("dynamic_clean", 5000)
    )
    o, _ = env.reset(seed=0)
    member.guarded = member.decisions = 0
    inside = member.action(o)
    far = o.copy()
    far[0] = 1e3 * (abs(float(hi[0])) + 1.0)  # norm_dev far beyond anything it was fitted on
    assert member.outside(member.inputs(far)) and not member.outside(member.inputs(o))
    np.testing.assert_array_equal(member.action(far), [0.9])
    assert (member.guarded, member.decisions) == (1, 2) and inside.shape == (1,)
    np.testing.assert_array_equal(student.action(far), [0.9])
    loose = dagger.Ensemble([dagger.Student(m.layers, m.mu, m.sd, m.candidates, m.feature_fn, m.meta, m.act, m.bounds,
                                            {**guard, "disagree": 1e-9}) for m in student.members])  # fmt: skip
    acts = [m.action(o) for m in student.members]
    if not np.allclose(*acts):  # members that differ at all disagree beyond 1e-9
        np.testing.assert_array_equal(loose.action(o), [0.9])
    with pytest.raises(ValueError, match="guard"):
        dagger.check_config({**TINY, "guard": {"fallback": [1.0]}})
    for bad in (-0.1, "wide", True):
        with pytest.raises(ValueError, match="guard band"):
            dagger.check_config({**TINY, "guard": {**guard, "band": bad}})
    with pytest.raises(ValueError, match="optionally"):
        dagger.check_config({**TINY, "guard": {**guard, "width": 0.1}})


def test_a_second_run_into_a_locked_folder_stops_at_once_and_a_killed_step_leaves_the_folder_whole(tmp_path):
    """Another process's lock on the folder stops a run before it writes; a kill between a step's files and its
    state.json leaves the state before that step, which a resumed run recovers from."""
    from magenv.agents.run_folder import RunFolder

    out = tmp_path / "run"
    with RunFolder(out).locked(), pytest.raises(RunError, match="another run is writing"):
        with RunFolder(out).locked():
            pass
    teacher = registry.make("oracle")
    dagger.train(out, teacher, TINY, log=lambda s: None)
    before = {p.name: p.read_bytes() for p in (out / "best.safetensors", out / "iterations.csv", out / "state.json")}
    (out / "best.safetensors.tmp").write_bytes(b"half a file")  # a step killed before its commit point
    (out / "iterations.csv.tmp").write_text("iteration\n")
    state = RunFolder(out).recover()
    assert state["iterations"] == 2 and not list(out.glob("*.tmp"))
    assert {
        p.name: p.read_bytes() for p in (out / "best.safetensors", out / "iterations.csv", out / "state.json")
    } == before
    dagger.train(out, teacher, {"iterations": 3}, log=lambda s: None, resume=True)
    assert json.loads((out / "state.json").read_text())["iterations"] == 3


def test_combining_runs_makes_one_ensemble_of_their_students(run_dir, tmp_path, capsys):
    """``magenv train --teacher T --combine RUN …``: every run's own student (an ensemble's members, else its best)
    copied and averaged, scored on the given validation seeds; runs whose students differ, an unguarded
    ``--disagree`` and an occupied ``--out`` are refused before anything is written."""
    import shutil

    other = tmp_path / "other"
    shutil.copytree(run_dir, other)
    dagger.add_ensemble(other, registry.make("oracle"), 2, log=lambda s: None)
    out = tmp_path / "combined"
    args = ["train", "--teacher", "oracle", "--combine", str(run_dir), str(other), "--eval-seeds", "5002:5003"]
    assert main([*args, "--out", str(out)]) == 0
    run = yaml.safe_load((out / "run.yaml").read_text())
    entry = run["ensemble"]
    assert entry["combined_of"] == [str(run_dir.resolve()), str(other.resolve())]
    assert run["config"]["val_seeds"] == [5002, 5003] and entry["val_ratio"] > 0
    sources = [run_dir / "best.safetensors"] + [other / m for m in yaml.safe_load((other / "run.yaml").read_text())
                                                ["ensemble"]["members"]]  # fmt: skip
    assert [(out / m).read_bytes() for m in entry["members"]] == [s.read_bytes() for s in sources]
    policy = load_agent(out)
    assert isinstance(policy.student, dagger.Ensemble) and len(policy.student.members) == 3
    x = np.random.default_rng(1).normal(size=(3, run["student"]["n_inputs"])).astype(np.float32)
    mean = np.mean([m.probabilities(x) for m in policy.student.members], axis=0)
    np.testing.assert_allclose(policy.student.probabilities(x), mean, rtol=1e-6)
    wider = tmp_path / "wider"
    shutil.copytree(run_dir, wider)
    changed = yaml.safe_load((wider / "run.yaml").read_text())
    changed["student"]["hidden"] = [16]
    (wider / "run.yaml").write_text(yaml.safe_dump(changed))
    for extra, message in (
        (["--combine", str(run_dir), str(wider), "--out", str(tmp_path / "a")], "student differs"),
        (["--combine", str(run_dir), str(other), "--disagree", "0.5", "--out", str(tmp_path / "b")], "guarded"),
        (["--combine", str(run_dir), str(other), "--out", str(out)], "already holds a run"),
        (["--combine", str(run_dir), "--out", str(tmp_path / "c")], "at least 2 runs"),
    ):
        assert main(["train", "--teacher", "oracle", *extra]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists() and not (tmp_path / "c").exists()
