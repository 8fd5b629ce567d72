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
    columns = side["network_inputs"]["columns"]
    assert len(columns) == policy.student.members[0].mu.shape[0]
    assert [c["mean"][0] for c in columns] == policy.student.members[0].mu.tolist()
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
    from magenv.train.onnx_graph import student_graph

    student = load_student(f"pretrained:{BLEND_ID}").student
    student.guard = {"fallback": [1.0], "margin": 0.1, "disagree": 0.5}
    with pytest.raises(ValueError, match="guard"):
        student_graph(BLEND_ID, student, [f"f{i}" for i in range(126)])


def test_a_student_of_the_plain_observation(monkeypatch):
    """A student that sees the observation as it is (the base StudentInputs, e.g. an env without derived inputs)
    exports without a builder of its own, acting as the numpy student with the mean and the argmax rule."""
    from magenv.agents import student_inputs
    from magenv.agents.dagger import Ensemble, Student
    from magenv.train.onnx_graph import student_graph

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
        student = Ensemble(members)
        model = student_graph("magenv/Plain-v0", student, [f"f{i}" for i in range(12)])
        action, _ = ort.InferenceSession(model.SerializeToString()).run(None, {"obs": obs})
        expected = np.array([student.action(o) for o in obs])
        assert np.abs(action - expected).max() <= TOL
