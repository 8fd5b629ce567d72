"""MagKalman-v0's extended observation (``features="extended"``): documented, the default kept (causality and
memory: ``test_env_extended.py``)."""

from __future__ import annotations

import gymnasium as gym
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import KALMAN_ID, kalman_memory
from magenv.envs.kalman import EXTENDED


def test_extended_observation_is_not_batched():
    with pytest.raises(ValueError, match="not batched"):
        gym.make_vec(KALMAN_ID, num_envs=2, vectorization_mode="vector_entry_point", features="extended")


def _extended_episode(scenario: str, seed: int, duration: float, act):
    """Yield (observation, runner, true signed heading error of the last fused sample, done) after each step of
    an extended-observation episode of ``scenario`` (seed, duration s) acting ``act(obs)``."""
    import numpy as np

    from magenv.envs.blend_memory import _heading
    from magenv.scenarios import make_trial

    trial = make_trial(scenario, seed, duration=duration)
    env = gym.make(KALMAN_ID, features="extended", scenario=[trial]).unwrapped
    obs, _ = env.reset(seed=0, options={"trial": trial})
    done = False
    while not done:
        obs, _, _, done, _ = env.step(np.asarray(act(obs), np.float32))
        runner = env._runner
        j = runner.pos - 1
        yield obs, runner, _heading(*runner.est[j], *trial.q_true[j]), done


def test_the_still_anchor_holds_the_last_clean_orientation_of_a_still_mimu():
    """On the still gimbal of ``stationary_magnet`` with the magnetometer refused (γ = 0, so the estimate drifts
    with the gyro bias), ``d_still`` is the heading the estimate has left the last clean sample's orientation
    by, which tracks the true signed heading error; ``pull_still`` is a full update's heading correction toward
    the anchor."""
    import numpy as np

    from magenv.envs.blend_memory import _heading

    i_d, i_p, i_t, i_e = (EXTENDED.index(n) for n in ("d_still", "pull_still", "t_anchor", "innov_east"))
    seen = []
    for obs, runner, error, _ in _extended_episode("stationary_magnet", 1, 40.0, lambda obs: np.zeros(1)):
        since = round(obs[i_t] * kalman_memory.T_ANCHOR_SCALE_S / runner.params.dt)  # samples since a clean one
        if obs[i_t] > 0.0 and runner.pos - 1 - since > 0:
            q, anchor = runner.est[runner.pos - 1], runner.est[runner.pos - 1 - since]
            assert obs[i_d] == pytest.approx(_heading(*q, *anchor), abs=1e-4)
            assert obs[i_p] == pytest.approx(-np.sign(obs[i_d]) * np.rad2deg(obs[i_e]), rel=1e-4, abs=1e-4)
            seen.append((obs[i_d], error))
    d_still, error = np.array(seen).T
    assert len(seen) > 500 and np.ptp(d_still) > 1.0  # the bias moved the estimate by more than 1°
    assert np.corrcoef(d_still, error)[0, 1] > 0.95


def test_d_perp_tracks_the_signed_heading_error_under_a_magnet_fixed_to_the_sensor():
    """On ``dynamic_magnet`` (the tube magnet rides with the sensor, so its field keeps one sensor-frame
    direction) under kf_model_tuned's trust, ``d_perp`` follows the estimate's true signed heading error more
    closely than the error's own spread, and ``pull_perp`` is a full update's heading correction against it."""
    import numpy as np

    from magenv import registry

    rule = registry.make("kf_model_tuned")
    i_d, i_p, i_e, i_i = (EXTENDED.index(n) for n in ("d_perp", "pull_perp", "innov_east", "perp_info"))
    seen = []
    for obs, runner, error, done in _extended_episode("dynamic_magnet", 3, 20.0, lambda obs: [rule.weight(obs)]):
        assert 0.0 <= obs[i_i] <= 1.0
        pull = np.clip(-np.sign(obs[i_d]) * np.rad2deg(obs[i_e]), -180.0, 180.0)  # the feature's range
        assert obs[i_p] == pytest.approx(pull, rel=1e-4, abs=1e-4)
        if runner.pos > 5 * runner.trial.rate and not done:  # the spin has begun
            seen.append((obs[i_d], error))
    d_perp, error = np.array(seen).T
    assert np.corrcoef(d_perp, error)[0, 1] > 0.6
    assert np.sqrt(np.mean((d_perp - error) ** 2)) < 0.9 * np.sqrt(np.mean(error**2))
