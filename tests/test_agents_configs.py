"""Agent configs and run folders: validation and clear errors."""

import pytest
import yaml

from magenv.agents import ConfigError, RunError, load_agent, load_hyperparams
from magenv.agents.hyperparams import constructor_kwargs

ENV = "magenv/MagBlend-v0"


@pytest.mark.parametrize("algo", ["ppo", "sac", "recurrent_ppo"])
def test_shipped_configs_are_valid(algo):
    section = load_hyperparams(algo, ENV)
    kwargs = constructor_kwargs(section)
    assert "n_timesteps" not in kwargs and "policy" in kwargs
    assert section["n_envs"] >= 1


def test_unknown_key_is_named(tmp_path):
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(yaml.safe_dump({ENV: {"learning_rate": 1e-3, "n_stepz": 64}}))
    with pytest.raises(ConfigError, match="unknown key.*n_stepz"):
        load_hyperparams("ppo", ENV, cfg)


def test_missing_section_and_algorithm(tmp_path):
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(yaml.safe_dump({"Other-v0": {}}))
    with pytest.raises(ConfigError, match="no section for env 'magenv/MagBlend-v0'"):
        load_hyperparams("ppo", ENV, cfg)
    with pytest.raises(ConfigError, match="unknown algorithm 'dqn'"):
        load_hyperparams("dqn", ENV)
    with pytest.raises(ConfigError, match="no such config file"):
        load_hyperparams("ppo", ENV, tmp_path / "none.yaml")


def test_bad_activation_is_named(tmp_path):
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(yaml.safe_dump({ENV: {"policy_kwargs": {"activation_fn": "swish"}}}))
    with pytest.raises(ConfigError, match="policy_kwargs.activation_fn must be 'tanh' or .*, got 'swish'"):
        constructor_kwargs(load_hyperparams("ppo", ENV, cfg))


def test_run_folder_errors(tmp_path):
    with pytest.raises(RunError, match="no such run folder"):
        load_agent(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunError, match="not a magenv run folder"):
        load_agent(tmp_path / "empty")
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.yaml").write_text(yaml.safe_dump({"env_id": ENV, "algo": "ppo", "env_kwargs": {}}))
    with pytest.raises(RunError, match="missing key.*hyperparams"):
        load_agent(run)
    (run / "run.yaml").write_text(yaml.safe_dump({"env_id": ENV, "algo": "ppo", "env_kwargs": {}, "hyperparams": {}}))
    with pytest.raises(RunError, match="trained on magenv/MagBlend-v0, cannot act in magenv/MagKalman-v0"):
        load_agent(run, env_id="magenv/MagKalman-v0")
    with pytest.raises(RunError, match="no trained model"):
        load_agent(run)
    (run / "best.safetensors").write_bytes(b"this is not a weights file")
    with pytest.raises(RunError, match="best.safetensors: corrupt weights file"):
        load_agent(run)
    (run / "run.yaml").write_text("env_id: [unclosed")
    with pytest.raises(RunError, match="corrupt"):
        load_agent(run)
