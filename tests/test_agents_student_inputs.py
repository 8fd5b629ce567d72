"""DAgger students of MagConstraint-v0 and MagQSF-v0: their inputs, and a run folder that loads and acts in the env
the oracle searched (its tuned eq. 18 / QSF detector)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from magenv import evaluation, registry
from magenv import scenarios as sc
from magenv.agents import dagger
from magenv.agents.student_inputs import inputs_for
from magenv.envs import CONSTRAINT_ID, QSF_ID
from magenv.envs.constraint import EXTENDED


def test_constraint_inputs_follow_each_block_with_the_rule_weight():
    oracle = registry.make("oracle_constraint")
    inputs = inputs_for(CONSTRAINT_ID)
    meta = inputs.meta(oracle)
    obs = np.random.default_rng(0).uniform(0.0, 0.3, (5, len(EXTENDED))).astype(np.float32)
    x = inputs(obs, meta)
    block = meta["block"]
    assert x.shape == (5, len(EXTENDED) + len(EXTENDED) // block)
    for b in range(len(EXTENDED) // block):
        np.testing.assert_array_equal(
            x[:, b * (block + 1) : b * (block + 1) + block], obs[:, b * block : (b + 1) * block]
        )
        np.testing.assert_allclose(x[:, b * (block + 1) + block], np.minimum(obs[:, b * block] / meta["th1"], 1.0))


@pytest.mark.parametrize(("teacher", "env_id"), [("oracle_constraint", CONSTRAINT_ID), ("oracle_qsf", QSF_ID)])
def test_the_student_acts_in_the_env_the_teacher_searched(teacher, env_id):
    oracle = registry.make(teacher)
    kwargs = dagger.student_env_kwargs(inputs_for(env_id), oracle, oracle.decision_every)
    assert kwargs["features"] == "extended" and kwargs["decision_every"] == oracle.decision_every
    for key, value in oracle.env_kwargs.items():
        assert kwargs[key] == value  # e.g. the tuned eq. 18 (th2) or the tuned QSF detector
    assert inputs_for(env_id).env_kwargs == {"features": "extended"}  # the shared inputs are left as they were


TINY = {"iterations": 2, "trials_per_scenario": 1, "val_seeds": [5000, 5001], "fit_steps": 30, "hidden": [8]}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("teacher", "scenario", "k"), [("oracle_constraint", "constraint_test3", 4), ("oracle_qsf", "handheld_random", 10)]
)
def test_tiny_run_loads_and_acts_in_the_teachers_env(tmp_path, teacher, scenario, k):
    oracle = registry.make(teacher)
    out = dagger.train(
        tmp_path / "run", oracle, {**TINY, "scenarios": [scenario], "decision_every": k}, log=lambda s: None
    )
    run = yaml.safe_load((out / "run.yaml").read_text())
    for key, value in oracle.env_kwargs.items():
        assert run["env_kwargs"][key] == value
    agent = registry.make(f"agent:{out}")
    trial = sc.make_trial(scenario, 0, duration=5.0)
    assert np.isfinite(evaluation.run_method("agent", agent, trial).score.total)


def test_qsf_inputs_follow_each_block_with_the_tuned_rules_decision():
    """The column after each block is the decision of ``qsf_detector_tuned`` on that block's base features, on
    observations of a detector-driven episode (starts, keeps, nones and age restarts); a run without
    ``rule_max_age`` (the shipped student's) sees the observation as it is."""
    import gymnasium as gym

    from magenv.envs.qsf import EXTENDED, FEATURES

    oracle, rule = registry.make("oracle_qsf"), registry.make("qsf_detector_tuned")
    inputs = inputs_for(QSF_ID)
    meta = inputs.meta(oracle)
    env = gym.make(QSF_ID, disable_env_checker=True, **dagger.student_env_kwargs(inputs, oracle, 1)).unwrapped
    trial = sc.make_trial("handheld_texting", 0, duration=50.0)
    o, _ = env.reset(seed=0, options={"trial": trial})
    obs = []
    for _ in range(4000):
        obs.append(o)
        o, _, terminated, truncated, _ = env.step(rule(o[: len(FEATURES)]))
        if terminated or truncated:
            break
    obs = np.array(obs)
    x, block = inputs(obs, meta), meta["block"]
    assert x.shape == (len(obs), len(EXTENDED) + len(EXTENDED) // block)
    for b in range(len(EXTENDED) // block):
        np.testing.assert_array_equal(
            x[:, b * (block + 1) : b * (block + 1) + block], obs[:, b * block : (b + 1) * block]
        )
        want = [rule(row)[0] for row in obs[:, b * block : b * block + len(FEATURES)]]
        np.testing.assert_array_equal(x[:, b * (block + 1) + block], want)
    assert set(np.unique(x[:, block])) == {-1.0, 0.0, 1.0}
    np.testing.assert_array_equal(inputs(obs, {}), obs)
