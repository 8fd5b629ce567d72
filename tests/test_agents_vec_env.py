"""SB3 on the batched vector envs (``magenv.agents.vec_env``): the episodes, infos and seeds of SB3's own
``make_vec_env`` of single envs, and PPO trains through it."""

from __future__ import annotations

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv

from magenv.agents.vec_env import BatchVecEnv, make_train_env
from magenv.agents.wrappers import normalized_actions
from magenv.envs import BLEND_ID, QSF_ID
from magenv.scenarios import make_trial
from tests.conftest import kinematic_trial

KWARGS = {
    "scenario": [kinematic_trial(seed=s, duration=d, disturbance_ut=20.0) for s, d in ((0, 1.6), (1, 1.1))],
    "decision_every": 16,
    "episode_seconds": 1.0,
}


def rollout(venv: VecEnv, actions: np.ndarray, seed: int):
    """Observations, rewards, dones and infos of ``venv`` seeded ``seed`` and stepped with ``actions``."""
    venv.seed(seed)
    obs = [venv.reset()]
    rewards, dones, infos = [], [], []
    for a in actions:
        o, r, d, info = venv.step(a)
        for x, lst in ((o, obs), (r, rewards), (d, dones), (info, infos)):
            lst.append(x)
    venv.close()
    return np.array(obs), np.array(rewards), np.array(dones), infos


def test_batched_training_env_gives_what_sb3_single_envs_give():
    n = 3
    batched = make_train_env(BLEND_ID, n, 10, KWARGS)
    assert isinstance(batched, BatchVecEnv) and batched.num_envs == n
    assert (batched.action_space.low == -1).all() and (batched.action_space.high == 1).all()
    singles = make_vec_env(BLEND_ID, n_envs=n, seed=10, env_kwargs=KWARGS, wrapper_class=normalized_actions)
    actions = np.random.default_rng(3).uniform(-1, 1, (50, n, 1)).astype(np.float32)
    got, want = rollout(batched, actions, 10), rollout(singles, actions, 10)
    np.testing.assert_allclose(got[0], want[0], rtol=1e-5, atol=1e-6)  # λ rescaled in float64 vs float32
    np.testing.assert_allclose(got[1], want[1], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(got[2], want[2])
    assert got[2].sum() >= 6  # several episodes end in each env, so the same-step resets are compared
    for g_step, w_step, done in zip(got[3], want[3], got[2]):
        for i in np.flatnonzero(done):
            g, w = g_step[i], w_step[i]
            np.testing.assert_allclose(g["terminal_observation"], w["terminal_observation"], rtol=1e-5, atol=1e-6)
            assert g["TimeLimit.truncated"] is w["TimeLimit.truncated"] is True
            assert g["episode"]["l"] == w["episode"]["l"]
            np.testing.assert_allclose(g["episode"]["r"], w["episode"]["r"], rtol=1e-4)
        for i in np.flatnonzero(~done):
            assert "terminal_observation" not in g_step[i] and "episode" not in g_step[i]


def test_seeds_give_env_i_seed_plus_i_and_a_repeatable_run():
    actions = np.zeros((20, 2, 1), np.float32)
    a = rollout(make_train_env(BLEND_ID, 2, 5, KWARGS), actions, 5)
    b = rollout(make_train_env(BLEND_ID, 2, 5, KWARGS), actions, 5)
    one = rollout(make_train_env(BLEND_ID, 1, 6, KWARGS), actions[:, 1:], 6)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[0][:, 1], one[0][:, 0])  # env 1 of seed 5 is env 0 of seed 6
    np.testing.assert_array_equal(a[1][:, 1], one[1][:, 0])


def test_ppo_learns_on_the_batched_env():
    """A short PPO run on 8 batched envs of one trial: whole rollouts, Monitor episodes in its logs, new weights."""
    trial = make_trial("dynamic_magnet", 10000, duration=8.0)
    env = make_train_env(BLEND_ID, 8, 0, {"scenario": trial, "decision_every": 16, "episode_seconds": 4.0})
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=64, n_epochs=2, seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(8 * 32 * 3)
    assert model.num_timesteps == 8 * 32 * 3
    assert len(model.ep_info_buffer) > 0 and all(ep["l"] > 0 for ep in model.ep_info_buffer)
    assert any((p != q).any() for p, q in zip(model.policy.parameters(), before))
    env.close()


def test_an_env_without_a_batched_vector_env_gets_sb3_single_envs(monkeypatch):
    import gymnasium as gym

    spec = gym.spec(QSF_ID)
    monkeypatch.setattr(spec, "vector_entry_point", None)
    kwargs = {"scenario": make_trial("handheld_texting", 3, duration=3.0), "episode_seconds": 1.0}
    venv = make_train_env(QSF_ID, 2, 0, kwargs)
    assert not isinstance(venv, BatchVecEnv) and venv.num_envs == 2
    venv.close()
