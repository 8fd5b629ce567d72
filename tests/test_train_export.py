"""``magenv export``: a DAgger student as ONNX; onnxruntime acts as the numpy student on 10 000 recorded
observations of every env, and the sidecar describes the observation, history, decision period and action."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

from magenv.agents import dagger
from magenv.agents.loading import pretrained_agents
from magenv.envs import BLEND_ID, CONSTRAINT_ID, KALMAN_ID, QSF_ID, VQF_ID
from magenv.train.cli import main
from magenv.train.export import export, load_student

ort = pytest.importorskip("onnxruntime", reason="the ONNX export is the extra magenv[onnx]: pip install 'magenv[onnx]'")
pytest.importorskip("onnx", reason="the ONNX export is the extra magenv[onnx]: pip install 'magenv[onnx]'")

N_OBS = 10_000
#: every env whose shipped agent is a student of magenv.agents.dagger (MagVQF-v0's too, once it is one)
ENVS = tuple(e for e, folder in pretrained_agents().items() if dagger.is_run(folder))
TOL = 1e-5


def recorded_observations(policy, n: int) -> np.ndarray:
    """``n`` observations of ``policy`` acting in its env on its env's default scenarios (one trial per reset,
    seeded), float32 (n, n_obs)."""
    env = gym.make(policy.env_id, disable_env_checker=True, **{**policy.env_kwargs, "episode_seconds": 30.0})
    out, seed = [], 0
    obs, _ = env.reset(seed=seed)
    while len(out) < n:
        out.append(obs)
        obs, _, terminated, truncated, _ = env.step(policy(obs))
        if terminated or truncated:
            seed += 1
            obs, _ = env.reset(seed=seed)
    env.close()
    return np.asarray(out, np.float32)


def test_every_shipped_student_is_exported():
    assert set(ENVS) == {BLEND_ID, KALMAN_ID, CONSTRAINT_ID, QSF_ID, VQF_ID}


@pytest.mark.parametrize("env_id", ENVS)
def test_onnx_acts_as_the_student(env_id, tmp_path):
    agent = f"pretrained:{env_id}"
    onnx_path, json_path = export(agent, tmp_path / "student.onnx")
    policy = load_student(agent)
    obs = recorded_observations(policy, N_OBS)
    action, probs = ort.InferenceSession(str(onnx_path)).run(None, {"obs": obs})
    expected = np.array([policy(o) for o in obs])
    assert action.shape == expected.shape == (N_OBS, len(policy.student.candidates[0]))
    worst = np.abs(action - expected).max()
    assert worst <= TOL, f"{env_id}: ONNX and numpy students differ by up to {worst:g}"
    assert len(np.unique(action.round(4), axis=0)) > 1  # the observations make the student act differently
    np.testing.assert_allclose(probs.sum(1), 1.0, atol=1e-5)
    # the sidecar says what the model needs
    side = json.loads(json_path.read_text())
    env = gym.make(env_id, disable_env_checker=True, **policy.env_kwargs).unwrapped
    assert side["model"] == "student.onnx" and side["env_id"] == env_id
    assert [f["name"] for f in side["features"]] == list(env.features)
    assert side["input"]["shape"] == ["batch", obs.shape[1]]
    assert side["decision_period"]["samples"] == policy.env_kwargs["decision_every"] == env.k_steps
    block, lags = side["history"]["block"], side["history"]["lags"]
    assert obs.shape[1] == block * (1 + len(lags)) and f"{env.features[0]}_lag{lags[0]}" in env.features
    columns, first = side["network_inputs"]["columns"], getattr(policy.student, "members", [policy.student])[0]
    assert len(columns) == first.mu.shape[0]
    assert [c["mean"][0] for c in columns] == first.mu.tolist()
    assert side["action"]["candidates"] == policy.student.candidates.tolist()
    assert side["action"]["act"] == policy.student.act


def test_cli_and_refusals(tmp_path, capsys):
    assert main(["export", f"pretrained:{BLEND_ID}", "--onnx", str(tmp_path / "b.onnx")]) == 0
    assert (tmp_path / "b.onnx").is_file() and (tmp_path / "b.json").is_file()
    assert main(["export", f"pretrained:{BLEND_ID}", "--onnx", str(tmp_path / "b.txt")]) == 2
    assert "must name a .onnx file" in capsys.readouterr().err
    assert main(["export", str(tmp_path), "--onnx", str(tmp_path / "x.onnx")]) == 2
    assert "not a magenv run folder" in capsys.readouterr().err
    others = [e for e, folder in pretrained_agents().items() if e not in ENVS]
    for env_id in others:  # not a student of magenv.agents.dagger (MagVQF-v0's own format)
        assert main(["export", f"pretrained:{env_id}", "--onnx", str(tmp_path / "v.onnx")]) == 2
        assert "DAgger students of magenv.agents.dagger" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists() and not (tmp_path / "v.onnx").exists()


def test_unknown_student_constants_are_refused():
    from magenv.train.onnx_graph import check_meta

    with pytest.raises(ValueError, match=r"\['new'\] are unknown"):
        check_meta(BLEND_ID, {"rule": [1, 1], "block": 42, "new": 1})
    with pytest.raises(ValueError, match="no ONNX form"):
        check_meta("magenv/Other-v0", {})


def onnx_matches_numpy(student, env_id: str, names: list[str], obs: np.ndarray):
    """(probabilities, numpy actions) of ``student`` on ``obs``, its ONNX graph's actions within TOL of numpy's."""
    from magenv.train.onnx_graph import student_graph

    model = student_graph(env_id, student, names)
    action, probs = ort.InferenceSession(model.SerializeToString()).run(None, {"obs": obs})
    expected = np.array([student.action(o) for o in obs])
    assert np.abs(action - expected).max() <= TOL
    return probs, expected


def test_a_student_of_the_plain_observation(monkeypatch):
    """A student that sees the observation as it is (the base StudentInputs, e.g. an env without derived inputs)
    exports without a builder of its own, acting as the numpy student with the mean and the argmax rule."""
    from magenv.agents import student_inputs
    from magenv.agents.dagger import Ensemble, Student

    monkeypatch.setitem(student_inputs.INPUTS, "magenv/Plain-v0", student_inputs.StudentInputs())
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(500, 12)).astype(np.float32)
    for act in ("mean", "argmax"):
        members = [
            Student(
                [(rng.normal(size=(16, 12)), rng.normal(size=16)), (rng.normal(size=(3, 16)), rng.normal(size=3))],
                rng.normal(size=12),
                rng.uniform(0.5, 2, 12),
                [[0.0], [0.5], [1.0]],
                student_inputs.StudentInputs(),
                {},
                act,
            )
            for _ in range(2)
        ]
        onnx_matches_numpy(Ensemble(members), "magenv/Plain-v0", [f"f{i}" for i in range(12)], obs)


def test_a_guarded_student_falls_back_in_onnx_where_it_does_in_numpy(monkeypatch):
    """The guard (magenv.agents.dagger.Student): the fallback action out of a member's widened fitted input range
    and where the members disagree — the same decisions in ONNX as in numpy, both kinds seen."""
    from magenv.agents import student_inputs
    from magenv.agents.dagger import Ensemble, Student

    monkeypatch.setitem(student_inputs.INPUTS, "magenv/Plain-v0", student_inputs.StudentInputs())
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(2000, 6)).astype(np.float32)
    obs[::7] *= 4.0  # some well outside the range below
    guard = {"fallback": [0.9], "margin": 0.1, "disagree": 0.4}
    for act in ("mean", "argmax"):
        members = [
            Student(
                [(rng.normal(size=(8, 6)), rng.normal(size=8)), (rng.normal(size=(3, 8)), rng.normal(size=3))],
                np.zeros(6),
                np.ones(6),
                [[0.0], [0.5], [1.0]],
                student_inputs.StudentInputs(),
                {},
                act,
                (np.full(6, -2.0), np.full(6, 2.0)),
                guard,
            )
            for _ in range(2)
        ]
        student = Ensemble(members)
        onnx_matches_numpy(student, "magenv/Plain-v0", [f"f{i}" for i in range(6)], obs)
        assert 0 < student.guarded < student.decisions  # both kinds of decision were made


def test_a_guarded_vqf_student_of_a_rule_falls_back_on_the_rule_in_onnx_as_in_numpy():
    """MagVQF-v0's student of ``oracle_vqf_rule``: each kept block followed by the Fan rule's trust, that trust a
    state-dependent candidate, the guard's ``fallback: rule`` and its ``band`` — the same actions in ONNX as in
    numpy."""
    from magenv.agents.dagger import Ensemble, Student
    from magenv.agents.student_inputs import inputs_for
    from magenv.envs.vqf import EXTENDED, FEATURES

    inputs, rng = inputs_for(VQF_ID), np.random.default_rng(2)
    meta = {"block": len(EXTENDED) // 3, "drop": ["delta"], "rule": [0.1, 2.0]}
    obs = rng.normal(scale=0.05, size=(3000, len(EXTENDED))).astype(np.float32)
    obs[:, FEATURES.index("dip_dev")] *= 0.5  # the rule's λ2 spans [0, 1] (90° · dip_dev against 2°)
    obs[::9] *= 6.0  # some well outside the range below
    n_in = inputs(obs[:1], meta).shape[1]
    assert n_in == 3 * (meta["block"] - 1 + 1) and inputs.n_state_candidates(meta) == 1
    x = inputs(obs, meta)
    rule = inputs.rule_trust(obs, meta)  # float64, the candidate; float32 after each kept block
    np.testing.assert_array_equal(inputs.candidate_actions(obs, meta)[:, 0, 0], rule)
    np.testing.assert_array_equal(x[:, meta["block"] - 1], rule.astype(np.float32))
    assert 0.1 < rule.mean() < 0.9 and rule.min() == 0.0
    lo, hi = np.quantile(x, 0.02, axis=0), np.quantile(x, 0.98, axis=0)
    for act, fallback, band in (("mean", "rule", None), ("argmax", "rule", None), ("mean", [0.8], None),
                                ("argmax", "rule", 0.25), ("mean", [0.8], 0.1)):  # fmt: skip
        guard = {"fallback": fallback, "margin": 0.05, "disagree": 0.4, **({} if band is None else {"band": band})}

        def member():
            layers = [(rng.normal(size=(8, n_in)), rng.normal(size=8)), (rng.normal(size=(4, 8)), rng.normal(size=4))]
            cands = [[0.0], [0.5], [1.0]]
            return Student(layers, x.mean(0), x.std(0) + 1e-3, cands, inputs, meta, act, (lo, hi), guard)

        student = Ensemble([member() for _ in range(2)])
        probs, expected = onnx_matches_numpy(student, VQF_ID, list(EXTENDED.names), obs)
        assert probs.shape == (len(obs), 4)
        assert 0 < student.guarded < student.decisions
        if fallback == "rule":  # where it held, the action is the rule's trust
            assert np.sum(np.abs(expected[:, 0] - rule) < 1e-12) >= student.guarded
        centre = rule if fallback == "rule" else fallback[0]
        departure = np.abs(expected[:, 0] - centre)
        if band is None:  # unbounded: the student departs from the fallback by more than any band below
            assert departure.max() > 0.3
        else:  # bounded: never further than the band, and as far where the student wanted to go further
            assert departure.max() <= band + 1e-12 and np.sum(np.isclose(departure, band)) > 10
