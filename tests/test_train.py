"""Training entry point: run folders, held-out evaluation, checkpoints, resume, every algorithm."""

import csv
import json

import pytest
import yaml

from magenv import registry
from magenv.agents import load_agent
from magenv.agents.loading import RunError
from magenv.agents.training import progress, train
from magenv.train.cli import main as cli

ENV = "magenv/MagBlend-v0"
SMALL = {
    "ppo": {"n_envs": 2, "n_steps": 64, "batch_size": 64, "n_epochs": 1},
    "sac": {"n_envs": 1, "learning_starts": 32, "batch_size": 32, "buffer_size": 2000},
    "recurrent_ppo": {
        "n_envs": 2,
        "n_steps": 32,
        "batch_size": 64,
        "n_epochs": 1,
        "policy_kwargs": {"lstm_hidden_size": 8, "net_arch": [8]},
    },
}


def small_config(tmp_path, algo):
    section = {
        "env_kwargs": {"scenario": "dynamic_clean", "episode_seconds": 3.0},
        "normalize_reward": True,
        **SMALL[algo],
    }
    path = tmp_path / f"{algo}.yaml"
    path.write_text(yaml.safe_dump({ENV: section}))
    return path


def train_kwargs(tmp_path, algo: str = "ppo", eval_every: int = 128) -> dict:
    """``train``'s options for a small run: the small config, held-out evaluation on one dynamic_clean trial."""
    return dict(
        config=small_config(tmp_path, algo),
        eval_every=eval_every,
        eval_scenarios=("dynamic_clean",),
        eval_seeds=(0,),
        progress_bar=False,
    )


def test_train_then_resume_keeps_progress_and_best_model(tmp_path):
    out = tmp_path / "run"
    kw = train_kwargs(tmp_path)
    train(ENV, "ppo", 256, out, **kw)
    state = json.loads((out / "state.json").read_text())
    assert state["timesteps"] >= 256 and (out / "best_model.zip").is_file() and (out / "last_model.zip").is_file()
    first = list(csv.reader(open(out / "evaluations.csv")))
    # the same command with more steps continues from the checkpoint
    train(ENV, "ppo", 512, out, **kw)
    state2 = json.loads((out / "state.json").read_text())
    rows = list(csv.reader(open(out / "evaluations.csv")))
    assert state2["timesteps"] >= 512 and rows[: len(first)] == first and len(rows) > len(first)
    assert min(float(r[1]) for r in rows) == pytest.approx(state2["best_score"], abs=1e-4)
    assert list((out / "tb").iterdir())  # TensorBoard logs
    agent = load_agent(out)
    assert agent.env_id == ENV
    # a different algorithm in the same folder is refused
    with pytest.raises(RunError, match="existing run is ppo"):
        train(ENV, "sac", 512, out, **kw)


@pytest.mark.parametrize("algo", ["sac", "recurrent_ppo"])
def test_other_algorithms_train_resume_and_load(tmp_path, algo):
    out = tmp_path / algo
    kw = train_kwargs(tmp_path, algo, eval_every=10_000)
    train(ENV, algo, 128, out, **kw)
    train(ENV, algo, 256, out, **kw)  # resumes: weights, optimizers, reward statistics (and SAC's buffer)
    assert json.loads((out / "state.json").read_text())["timesteps"] == 256
    assert (out / "replay_buffer.safetensors").is_file() == (algo == "sac")
    assert [float(r[0]) for r in csv.reader(open(out / "evaluations.csv"))] == [128, 256]
    agent = load_agent(out)
    obs_dim = agent.model.observation_space.shape[0]
    import numpy as np

    action = agent(np.zeros(obs_dim, np.float32))
    assert np.all((action >= 0.0) & (action <= 1.0))  # mapped back to λ ∈ [0, 1]


def test_cli_errors_are_clear(tmp_path, capsys):
    assert cli(["train", "--env", "magenv/Nope-v0", "--out", str(tmp_path / "x")]) == 2
    assert "unknown env 'magenv/Nope-v0'" in capsys.readouterr().err
    assert cli(["evaluate", str(tmp_path / "missing")]) == 2
    assert "no such run folder" in capsys.readouterr().err


def test_pretrain_clones_the_teacher_before_rl(tmp_path):
    """Behaviour cloning: the cloned agent (then one small PPO update) acts like the teacher rule."""
    import numpy as np

    from magenv.evaluation import run_policy_on_trials
    from magenv.registry import make
    from magenv.scenarios import make_trial

    section = {
        "env_kwargs": {"scenario": "dynamic_magnet", "episode_seconds": 20.0},
        "pretrain": {"teacher": "fan_lambda", "steps": 1500, "epochs": 30},
        **SMALL["ppo"],
    }
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(yaml.safe_dump({ENV: section}))
    out = tmp_path / "bc"
    train(
        ENV,
        "ppo",
        1,
        out,
        config=cfg,
        eval_every=10_000,
        eval_scenarios=("dynamic_magnet",),
        eval_seeds=(0,),
        progress_bar=False,
        make_method=make,
    )
    state = json.loads((out / "state.json").read_text())
    assert state["pretrain_mse"] < 0.05  # actions in [-1, 1]; an untrained actor is off by ~0.3
    agent, teacher = load_agent(out, which="last"), make("fan_lambda")
    trial = make_trial("dynamic_magnet", 0).slice(0, 2000)
    env = __import__("gymnasium").make(ENV, scenario=[trial]).unwrapped
    obs, _ = env.reset(seed=0)
    gaps = []
    for _ in range(100):
        a_agent, a_teacher = agent(obs), teacher(obs)
        gaps.append(abs(float(a_agent[0]) - float(a_teacher[0])))
        obs, *_ = env.step(a_teacher)
    assert np.mean(gaps) < 0.1  # λ ∈ [0, 1]
    agent_deg = run_policy_on_trials(agent, [trial])[0].total
    teacher_deg = run_policy_on_trials(teacher, [trial])[0].total
    assert agent_deg < teacher_deg + 1.0


def test_pretrain_config_errors(tmp_path):
    from magenv.agents import ConfigError, load_hyperparams

    cases = [
        ({"teacher": "fan_lambda"}, "needs 'teacher' and 'steps'"),
        ({"teacher": "fan_lambda", "steps": 10, "epoch": 3}, "unknown key"),
        ({"teacher": "fan_lambda", "steps": -5}, "pretrain: steps must be an integer ≥ 1, got -5"),
    ]
    for spec, msg in cases:
        cfg = tmp_path / "ppo.yaml"
        cfg.write_text(yaml.safe_dump({ENV: {"pretrain": spec}}))
        with pytest.raises(ConfigError, match=msg):
            load_hyperparams("ppo", ENV, cfg)
    cfg.write_text(yaml.safe_dump({ENV: {"pretrain": {"teacher": "fan_lambda", "steps": 10}, **SMALL["sac"]}}))
    with pytest.raises(ConfigError, match="pretrain works with ppo only"):
        load_hyperparams("sac", ENV, cfg)
    cfg.write_text(yaml.safe_dump({ENV: {"pretrain": {"teacher": "aekf", "steps": 10}, **SMALL["ppo"]}}))
    with pytest.raises(ConfigError, match="must be a policy of magenv/MagBlend-v0"):
        train(ENV, "ppo", 1, tmp_path / "x", config=cfg, progress_bar=False, make_method=registry.make)
    assert not (tmp_path / "x").exists()  # nothing written: the same folder can be used after fixing the config
    cfg.write_text(yaml.safe_dump({ENV: {"pretrain": {"teacher": "kf_gate", "steps": 10}, **SMALL["ppo"]}}))
    with pytest.raises(ConfigError, match="must be a policy of magenv/MagBlend-v0; it acts in magenv/MagKalman-v0"):
        train(ENV, "ppo", 1, tmp_path / "x", config=cfg, progress_bar=False, make_method=registry.make)


def test_the_progress_of_a_run_is_its_state_file(tmp_path):
    assert progress(tmp_path, "ppo") is None  # a fresh run
    (tmp_path / "state.json").write_text('{"timesteps": 64, "best_score": 1.5, "files": {}}')
    assert progress(tmp_path, "ppo") == {"timesteps": 64, "best_score": 1.5, "files": {}}
    (tmp_path / "state.json").write_text('{"timesteps": 64}')  # an older run folder's (no files named)
    assert progress(tmp_path, "ppo") == {"timesteps": 64}
    (tmp_path / "state.json").write_text('{"timesteps": -64, "files": {}}')
    with pytest.raises(RunError, match="timesteps must be an integer ≥ 0, got -64"):
        progress(tmp_path, "ppo")
    (tmp_path / "state.json").write_text('{"timesteps": ')
    with pytest.raises(RunError, match="state.json: corrupt"):
        progress(tmp_path, "ppo")


def test_weight_files_are_the_same_bytes_for_the_same_content(tmp_path):
    """The safetensors library writes its metadata map in a varying order; magenv sorts the header, so the same
    tensors and metadata give the same file (and it still reads back)."""
    import torch

    from magenv.agents.weights import _write, read

    tensors = {"b": torch.arange(5.0), "a": torch.ones(2, 3)}
    meta = {"algo": "dagger", "zeta": [1, 2], "alpha": {"x": "é"}, "mid": 3}
    files = [tmp_path / f"{i}.safetensors" for i in range(4)]
    for path in files:
        _write(path, tensors, meta)
    assert len({p.read_bytes() for p in files}) == 1
    got, got_meta = read(files[0])
    assert sorted(got) == ["a", "b"] and torch.equal(got["a"], tensors["a"]) and got_meta["zeta"] == [1, 2]
    assert got_meta["alpha"] == {"x": "é"} and got_meta["mid"] == 3
