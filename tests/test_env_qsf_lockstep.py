"""MagQSF-v0's lock-step batch kernel (``magenv.envs.qsf_lockstep``) against the per-env kernel (the single env's
``magenv.envs.qsf.advance`` on ``qsf.run_kernel``): bit for bit, over more envs than one block of lanes, and
for blocks narrower than ``NARROW`` (which run env by env) as for lock-step ones."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import QSF_ID, qsf_lockstep
from magenv.filters import qsf
from magenv.filters.kalman_threshold import FilterError
from tests.conftest import ENV_CASES
from tests.test_env_batch import vector_and_singles

N_ENVS = qsf_lockstep.LANES + 3  # a full block and a partial one (narrower than NARROW: env by env)
WIDTHS = [3, qsf_lockstep.NARROW]  # env by env, in lock-step


def _actions(seed: int, steps: int, n: int) -> np.ndarray:
    """Random decisions (none / keep / start) and trusts (0 included), float32 (steps, n, 2)."""
    rng = np.random.default_rng(seed)
    a = np.stack([rng.uniform(-1.0, 1.0, (steps, n)), rng.choice([0.0, 0.3, 1.0], (steps, n))], axis=-1)
    return a.astype(np.float32)


@pytest.mark.parametrize("variant", ["delay_magyq", "magyq"])
def test_lockstep_is_the_per_env_kernel(variant):
    """Observations, rewards and truncations of every env equal the single env's (which runs the per-env kernel),
    the serial and the threaded lock-step kernels alike, with episodes ending at different samples."""
    kwargs = {"scenario": ENV_CASES[QSF_ID].batch_trials(), "decision_every": 7, "episode_seconds": 0.5,
              "variant": variant}  # fmt: skip
    actions = _actions(1, 30, N_ENVS)
    serial, want = vector_and_singles(QSF_ID, kwargs, 3, actions, N_ENVS)
    threads, _ = vector_and_singles(QSF_ID, kwargs, 3, actions[:6], N_ENVS, parallel=True)
    assert want[2].sum() >= N_ENVS  # every env truncated at least once: autoresets compared too
    for s, t, w in zip(serial, threads, want):
        np.testing.assert_array_equal(s, w)
        np.testing.assert_array_equal(t, w[: len(t)])


def _pair(kwargs, n):
    """A vector env of n envs and n single envs, all reset with seed 0 + i."""
    vec = gym.make_vec(QSF_ID, num_envs=n, vectorization_mode="vector_entry_point", **kwargs).unwrapped
    vec.reset(seed=0)
    singles = [gym.make(QSF_ID, disable_env_checker=True, **kwargs).unwrapped for _ in range(n)]
    for i, env in enumerate(singles):
        env.reset(seed=i)
    return vec, singles


def _same_state(vec, i, env):
    st = env._runner.state
    np.testing.assert_array_equal(vec.state.cov[:, :, i], st.cov)
    np.testing.assert_array_equal(vec.state.x[:, i], st.x)


@pytest.mark.parametrize("n", WIDTHS)
def test_lockstep_repairs_as_the_per_env_kernel(n):
    """A covariance that fails the health check (a negative variance) is repaired by ``repair_sym`` on the
    lane's copy exactly as the per-env kernel repairs it; the other lanes go on untouched."""
    kwargs = {"scenario": ENV_CASES[QSF_ID].batch_trials(), "decision_every": 5}
    vec, singles = _pair(kwargs, n)
    for i in (1, 2):
        vec.state.cov[8, 8, i] = singles[i]._runner.state.cov[8, 8] = -1e-3
    actions = _actions(2, 6, n)
    for a in actions:
        obs, rew, *_ = vec.step(a)
        for i, env in enumerate(singles):
            o, r, *_ = env.step(a[i])
            np.testing.assert_array_equal(obs[i], o)
            assert rew[i] == r
    for i, env in enumerate(singles):
        _same_state(vec, i, env)
    assert np.linalg.eigvalsh(vec.state.cov[:11, :11, 1]).min() > 0  # repaired


@pytest.mark.parametrize("n", WIDTHS)
def test_lockstep_failure_names_the_env_and_keeps_its_state(n):
    kwargs = {"scenario": ENV_CASES[QSF_ID].batch_trials(), "decision_every": 5}
    vec, singles = _pair(kwargs, n)
    vec.state.cov[0, 0, 2] = singles[2]._runner.state.cov[0, 0] = np.inf
    before = vec.state.cov[:, :, 2].copy()
    a = np.array([[1.0, 1.0]] * n, np.float32)
    with pytest.raises(FilterError, match=r"env 2\)"):
        vec.step(a)
    with pytest.raises(FilterError):
        singles[2].step(a[2])
    np.testing.assert_array_equal(vec.state.cov[:, :, 2], before)
    assert qsf.N_AUGMENTED == vec.state.cov.shape[0]


@pytest.mark.parametrize("n", WIDTHS)
def test_lockstep_failure_mid_step_keeps_the_state_before(n):
    """An env whose covariance overflows at the step's second sample (the first with a prediction) fails there
    and keeps the state committed at the first, as the per-env kernel does (the lock-step block fuses again up
    to that sample); the other envs end their step as their single envs."""
    kwargs = {"scenario": ENV_CASES[QSF_ID].batch_trials(), "decision_every": 5}
    vec, singles = _pair(kwargs, n)
    vec.state.cov[4, 4, 2] = singles[2]._runner.state.cov[4, 4] = 1e150  # finite, but its products overflow
    before = vec.state.x[:, 2].copy()
    a = np.array([[1.0, 1.0]] * n, np.float32)
    with pytest.raises(FilterError, match=r"at sample 1 .*env 2\)"):
        vec.step(a)
    with pytest.raises(FilterError, match="at sample 1"):
        singles[2].step(a[2])
    assert not np.array_equal(vec.state.x[:, 2], before)  # sample 0 committed
    for i, env in enumerate(singles):
        if i != 2:
            env.step(a[i])
        _same_state(vec, i, env)
