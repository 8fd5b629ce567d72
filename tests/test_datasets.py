"""``magenv datasets``: a small Minari dataset of the oracle and a tuned rule is built, loaded back locally (no
download) and replayed to the same rewards, with the truth-only channels in its step infos."""

from __future__ import annotations

import numpy as np
import pytest

from magenv.train.cli import main as cli
from magenv.train.datasets import TRUTH_INFO, dataset_id

minari = pytest.importorskip("minari", reason="magenv datasets needs the extra magenv[datasets]")
ENV = "magenv/MagBlend-v0"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """A folder with MagBlend-v0's oracle and fan_lambda_tuned datasets (2 episodes of 4 s each)."""
    root = tmp_path_factory.mktemp("minari")
    argv = ["datasets", "build", "--envs", "MagBlend-v0", "--episodes", "2", "--episode-seconds", "4"]
    assert cli([*argv, "--seed", "10000", "--root", str(root)]) == 0
    return root


@pytest.mark.parametrize("method", ["oracle", "fan_lambda_tuned"])
def test_a_dataset_loads_locally_and_replays_to_the_same_rewards(root, monkeypatch, method):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    dataset = minari.load_dataset(dataset_id(ENV, method), download=False)
    assert dataset.total_episodes == 2 and dataset.total_steps == 2 * 4 * 256 // 8
    env = dataset.recover_environment()
    seeds = [m["seed"] for m in dataset.storage.get_episode_metadata(dataset.episode_indices)]
    assert seeds == [10000, 10001]
    for episode, seed in zip(dataset.iterate_episodes(), seeds):
        obs, info = env.reset(seed=seed)
        assert np.array_equal(obs, episode.observations[0]) and np.isnan(info["error_total"])
        rewards, errors = [], []
        for action in episode.actions:
            obs, reward, terminated, truncated, info = env.step(action)
            rewards.append(reward)
            errors.append(info["error_total"])
        assert terminated or truncated
        assert np.array_equal(rewards, episode.rewards)
        assert np.array_equal(errors, episode.infos["error_total"][1:])
        assert set(episode.infos) == set(TRUTH_INFO) and episode.infos["q_true"].shape == (len(rewards) + 1, 4)


def test_the_oracle_earns_more_than_the_rule(root, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    returns = {
        m: [
            float(ep.rewards.sum()) for ep in minari.load_dataset(dataset_id(ENV, m), download=False).iterate_episodes()
        ]
        for m in ("oracle", "fan_lambda_tuned")
    }
    assert np.mean(returns["oracle"]) > np.mean(returns["fan_lambda_tuned"])


def test_list_and_bad_arguments(root, capsys):
    assert cli(["datasets", "list", "--root", str(root)]) == 0
    out = capsys.readouterr().out
    assert "magenv/blend-oracle-v0: 2 episodes, 256 steps" in out and "2 magenv dataset(s)" in out
    build = ["datasets", "build", "--root", str(root)]
    assert cli([*build, "--envs", "MagBlend-v0"]) == 2
    assert "exist; --force replaces them" in capsys.readouterr().err
    assert cli([*build, "--seed", "4000"]) == 2
    assert "--seed must be a training seed" in capsys.readouterr().err
    assert cli([*build, "--envs", "Nope-v0"]) == 2
    assert "is not an env of magenv-bench v1" in capsys.readouterr().err
    assert cli([*build, "--methods", "expert"]) == 2
    assert "--methods must name oracle, rules or both" in capsys.readouterr().err
