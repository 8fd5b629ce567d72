"""The VQF oracle (``magenv.baselines.oracle_vqf``) and its DAgger student (``magenv.agents.dagger_vqf``)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from magenv import evaluation, metrics, registry
from magenv.agents import dagger_vqf as dv
from magenv.agents.loading import RunError
from magenv.baselines.oracle_vqf import VQFOracle, candidate_costs
from magenv.envs.vqf import FEATURES, VQFRunner
from tests.conftest import kinematic_trial


@pytest.fixture(scope="module")
def disturbed():
    return kinematic_trial(seed=4, duration=12.0, disturbance_ut=40.0, disturbance_window=(3.0, 9.0))


def _rmse(q, trial) -> float:
    return metrics.score(q, trial.q_true, trial.score_mask).total


def test_candidate_costs_leave_the_filter_as_it_was(disturbed):
    a, b = VQFRunner(disturbed), VQFRunner(disturbed)
    for step in range(60):
        if step % 7 == 0:
            costs = candidate_costs(a, (0.0, 0.5, 1.0), 200)
            assert costs.shape == (3,) and np.all(costs >= 0)
        a.advance(16, 0.3)
        b.advance(16, 0.3)
    np.testing.assert_array_equal(a.est, b.est)
    np.testing.assert_array_equal(a.feat, b.feat)


def test_the_oracle_beats_vqf_on_a_disturbed_trial(disturbed):
    oracle = VQFOracle(decision_every=32, horizon_s=1.0)
    vqf_q = evaluation.run_method("vqf", registry.make("vqf"), disturbed).q
    assert _rmse(oracle.run(disturbed).q, disturbed) < 0.8 * _rmse(vqf_q, disturbed)


def test_a_saved_student_loads_as_the_same_policy(disturbed, tmp_path):
    memory = dv.Student([], np.zeros(len(FEATURES) * 3), np.ones(len(FEATURES) * 3), dv.CANDIDATES)
    x, c, scale = dv.rollout(disturbed.slice(0, 1500), {"decision_every": 32}, candidate_costs, 0.5, None, memory)
    assert x.shape == (47, len(FEATURES) * 3) and c.shape == (47, len(dv.CANDIDATES)) and scale > 0
    student = dv.fit(x, c, np.full(len(x), scale), hidden=(8,), steps=20)
    dv.save(tmp_path, student, {"decision_every": 32, "rejection": "on"}, {"note": "test"})
    policy = registry.make(f"agent:{tmp_path}")
    assert policy.env_kwargs == {"decision_every": 32, "rejection": "on"}
    run = evaluation.run_method("student", policy, disturbed)
    student.reset()
    env_trust = run.trust  # the gain VQF applied: u, 0 where VQF's rejection zeroed it
    assert np.isfinite(run.scored.total) and np.all((env_trust >= 0) & (env_trust <= 1))
    obs = np.linspace(-0.5, 0.5, len(FEATURES)).astype(np.float32)
    policy.reset()
    want = student.act(student.inputs(obs))
    assert policy(obs)[0] == pytest.approx(want, rel=1e-6)
    run_yaml = tmp_path / dv.RUN_FILE
    run_file = yaml.safe_load(run_yaml.read_text())
    run_file["features"] = run_file["features"][:-1]
    run_yaml.write_text(yaml.safe_dump(run_file))
    with pytest.raises(RunError, match="features"):
        registry.make(f"agent:{tmp_path}")


def test_the_shipped_agent_loads_and_acts(disturbed):
    from magenv.agents.loading import pretrained_agents

    folder = pretrained_agents()["magenv/MagVQF-v0"]
    files = {p.name: p.stat().st_size for p in folder.iterdir()}
    assert {"run.yaml", "best.safetensors", "card.md"} <= set(files) and sum(files.values()) < 1_000_000
    assert "held out" in (folder / "card.md").read_text()
    agent = registry.make("agent:pretrained:magenv/MagVQF-v0")
    assert agent.env_id == "magenv/MagVQF-v0" and agent.env_kwargs["rejection"] == "on"
    run = evaluation.run_method(agent.name, agent, disturbed)
    assert np.isfinite(run.scored.total) and np.all((run.trust >= 0) & (run.trust <= 1))


def test_the_rule_input_is_the_fan_rules_trust_per_block_and_survives_saving(tmp_path):
    from magenv.baselines.vqf_rules import VQFFanLambda

    rule = (0.2, 5.0)
    d = len(FEATURES) * 3
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.3, 0.3, (40, d))
    probe = dv.Student([], np.zeros(d), np.ones(d), dv.CANDIDATES, rule=rule)
    z = probe.augment(x)
    assert z.shape == (40, d + 3)
    fan = VQFFanLambda(*rule)
    for b in range(3):
        block = x[:, b * len(FEATURES) : (b + 1) * len(FEATURES)]
        np.testing.assert_array_equal(z[:, b * (len(FEATURES) + 1) : (b + 1) * (len(FEATURES) + 1) - 1], block)
        want = [fan(row)[0] for row in block]
        np.testing.assert_allclose(z[:, (b + 1) * (len(FEATURES) + 1) - 1], want, rtol=1e-6)
    student = dv.fit(x, rng.uniform(0, 1, (40, len(dv.CANDIDATES))), np.ones(40), hidden=(8,), steps=20, rule=rule)
    assert student.mean.shape == (d + 3,)
    dv.save(tmp_path, student, {"decision_every": 32, "rejection": "on"}, {})
    loaded = dv.load_policy(tmp_path).student
    assert loaded.rule == rule
    np.testing.assert_allclose(loaded.logits(x[0]), student.logits(x[0]))


def test_an_ensemble_acts_with_its_members_mean_trust_and_survives_saving(tmp_path):
    d = len(FEATURES) * 3
    rng = np.random.default_rng(1)
    x, c = rng.uniform(-0.3, 0.3, (40, d)), rng.uniform(0, 1, (40, len(dv.CANDIDATES)))
    ens = dv.fit(x, c, np.ones(40), hidden=(8,), steps=20, seed=3, members=3)
    singles = [dv.fit(x, c, np.ones(40), hidden=(8,), steps=20, seed=3 + m) for m in range(3)]
    assert len(ens.more) == 2
    assert ens.act(x[0]) == pytest.approx(np.mean([s.act(x[0]) for s in singles]), rel=1e-9)
    dv.save(tmp_path, ens, {"decision_every": 32, "rejection": "on"}, {})
    loaded = dv.load_policy(tmp_path).student
    assert loaded.act(x[0]) == pytest.approx(ens.act(x[0]), rel=1e-9)
    (tmp_path / dv.RUN_FILE).write_text((tmp_path / dv.RUN_FILE).read_text().replace("n_members: 3", "n_members: 4"))
    with pytest.raises(RunError, match="m3_w0"):
        dv.load_policy(tmp_path)
