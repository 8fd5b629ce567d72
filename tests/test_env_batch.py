"""The batched vector envs (``magenv.envs.batch``): sub-env i is the single env seeded s + i, bit for bit."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, VQF_ID
from magenv.envs.batch import TrialStore
from magenv.envs.common import TrialPool, TrialSource
from tests.conftest import ENV_CASES, kinematic_trial

ENVS = {env_id: (case.batch_trials, case.action_dim) for env_id, case in ENV_CASES.items()}  # (trials, action dim)


def vector_and_singles(env_id, kwargs, seed, actions, num_envs, **vector_kwargs):
    """(vector env's obs (T+1, N, F), rewards (T, N), truncations (T, N)) and the same from N single envs
    seeded seed + i, stepped with the same actions (and reset the step after a truncation)."""
    vec = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **vector_kwargs, **kwargs)
    obs, _ = vec.reset(seed=seed)
    got = [[obs], [], []]
    for a in actions:
        obs, r, term, trunc, _ = vec.step(a)
        assert not term.any()
        for lst, x in zip(got, (obs, r, trunc)):
            lst.append(x)
    want = [[], [], []]
    for i in range(num_envs):
        env = gym.make(env_id, disable_env_checker=True, **kwargs)
        obs, _ = env.reset(seed=seed + i)
        o_i, r_i, t_i, done = [obs], [], [], False
        for a in actions:
            if done:
                (obs, _), r, trunc, done = env.reset(), 0.0, False, False
            else:
                obs, r, _, trunc, _ = env.step(a[i])
                done = trunc
            o_i.append(obs)
            r_i.append(r)
            t_i.append(trunc)
        for lst, x in zip(want, (o_i, r_i, t_i)):
            lst.append(x)
    got = [np.array(x) for x in got]
    want = [np.swapaxes(np.array(x), 0, 1) for x in want]
    return got, want


@pytest.mark.parametrize("env_id", list(ENVS))
def test_sub_env_i_is_the_single_env_seeded_s_plus_i(env_id):
    make, dim = ENVS[env_id]
    kwargs = {"scenario": make(), "decision_every": 16, "episode_seconds": 1.0}
    actions = np.random.default_rng(1).uniform(-0.3, 1.3, (40, 3, dim)).astype(np.float32)
    got, want = vector_and_singles(env_id, kwargs, 10, actions, 3)
    assert want[2].sum() >= 6  # several episodes each, so autoresets are compared too
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_threads_and_same_step_resets_change_nothing():
    kwargs = {"scenario": ENVS[BLEND_ID][0](), "decision_every": 8, "episode_seconds": 0.6}
    actions = np.random.default_rng(2).uniform(0, 1, (60, 5, 1)).astype(np.float32)
    serial, want = vector_and_singles(BLEND_ID, kwargs, 3, actions, 5, parallel=False)
    threads, _ = vector_and_singles(BLEND_ID, kwargs, 3, actions, 5, parallel=True)
    for s, t, w in zip(serial, threads, want):
        np.testing.assert_array_equal(s, w)
        np.testing.assert_array_equal(t, w)
    # Stable-Baselines3's same-step reset: reset_done() right after a truncation gives the observation the
    # next-step autoreset would have given one step later
    vec = gym.make_vec(BLEND_ID, num_envs=5, vectorization_mode="vector_entry_point", **kwargs).unwrapped
    obs = [vec.reset(seed=3)[0]]
    for a in actions:
        o, _, _, trunc, _ = vec.step(a)
        if trunc.any():
            o = o.copy()
            o[trunc] = vec.reset_done()
        obs.append(o)
    obs = np.array(obs)
    first = np.flatnonzero(want[2][:, 0])[0]  # env 0's first truncation
    np.testing.assert_array_equal(obs[: first + 1], want[0][: first + 1])
    np.testing.assert_array_equal(obs[first + 1, 0], want[0][first + 2, 0])  # the next episode's first observation


def test_bad_actions_and_order():
    vec = gym.make_vec(BLEND_ID, num_envs=2, vectorization_mode="vector_entry_point", scenario=ENVS[BLEND_ID][0]())
    with pytest.raises(RuntimeError, match="before reset"):
        vec.step(np.zeros((2, 1), np.float32))
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="shape \\(2, 1\\)"):
        vec.step(np.zeros((3, 1), np.float32))
    with pytest.raises(ValueError, match="env 1"):
        vec.step(np.array([[0.5], [np.nan]]))
    _, _, _, _, info = vec.step(np.array([[1.5], [0.2]], np.float32))
    np.testing.assert_array_equal(info["action_clipped"], [True, False])
    np.testing.assert_allclose(info["lambda"], [1.0, 0.2], rtol=1e-6)
    assert info["error_total"].shape == (2,) and info["_error_total"].all()
    with pytest.raises(ValueError, match="num_envs"):
        gym.make_vec(BLEND_ID, num_envs=0, vectorization_mode="vector_entry_point")
    with pytest.raises(TypeError, match="parallel must be True or False"):
        gym.make_vec(BLEND_ID, num_envs=2, vectorization_mode="vector_entry_point", parallel="yes")


def test_a_trial_pool_is_seeded_by_its_option_and_drawn_from_the_env():
    pool = TrialPool.of({"size": 3, "reuse": 2, "seed": 7})
    a = TrialSource("dynamic_clean,dynamic_magnet", trial_pool=pool)
    b = TrialSource("dynamic_clean,dynamic_magnet", trial_pool=pool)
    assert a.generation(0) == b.generation(0) != a.generation(1)
    assert len(set(a.generation(0))) == 3
    rng = np.random.default_rng(0)
    keys = [a.pick(rng, e) for e in range(4)]  # episodes 0, 1 from generation 0; 2, 3 from generation 1
    assert set(keys[:2]) <= set(a.generation(0)) and set(keys[2:]) <= set(a.generation(1))
    bad_options = ((0, "size"), ({"size": 2, "reuse": 0}, "reuse"), ({"size": 2, "x": 1}, "unknown"), ("3", "must be"))
    for bad, match in bad_options:
        with pytest.raises((ValueError, TypeError), match=match):
            TrialPool.of(bad)


def test_pooled_vector_env_is_pooled_single_envs_and_shares_trials():
    kwargs = {
        "scenario": "dynamic_clean,dynamic_magnet",
        "scenario_kwargs": {"duration": 2.0},
        "decision_every": 32,
        "trial_pool": {"size": 2, "seed": 1},
    }
    actions = np.full((40, 4, 1), 0.4, np.float32)
    got, want = vector_and_singles(BLEND_ID, kwargs, 0, actions, 4)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    vec = gym.make_vec(BLEND_ID, num_envs=4, vectorization_mode="vector_entry_point", **kwargs).unwrapped
    vec.reset(seed=0)
    assert len(vec.store.entries) <= 2  # four envs on at most the pool's two trials


def test_trial_store_shares_evicts_and_grows():
    store = TrialStore({"x": ((2,), float)}, capacity=10)
    rows = lambda n, v: {"x": np.full((n, 2), float(v))}
    a = store.add("a", rows(6, 1), "A")
    assert store.get("a") == (a, "A") and store.entries["a"][2] == 2
    b = store.add("b", rows(8, 2), "B")  # does not fit beside a: the arrays grow, a keeps its rows
    assert store.version == 1 and store.capacity >= 14
    np.testing.assert_array_equal(store.arrays["x"][a : a + 6], 1.0)
    np.testing.assert_array_equal(store.arrays["x"][b : b + 8], 2.0)
    for _ in range(2):
        store.release("a")
    c = store.add("c", rows(6, 3), "C")  # the free rows at the end
    d = store.add("d", rows(6, 4), "D")  # no free rows left: evicts a, which nobody uses any more
    assert "a" not in store and d == a and store.version == 1
    for offset, v in ((b, 2.0), (c, 3.0), (d, 4.0)):
        np.testing.assert_array_equal(store.arrays["x"][offset : offset + 6], v)


def test_the_extended_vqf_observation_is_batched_too():
    """MagVQF-v0's extended observation (EMAs and lagged copies) in the vector env is the single env's."""
    kwargs = {"scenario": ENVS[VQF_ID][0](), "decision_every": 8, "episode_seconds": 1.0, "features": "extended"}
    actions = np.random.default_rng(3).uniform(0, 1, (50, 3, 1)).astype(np.float32)
    got, want = vector_and_singles(VQF_ID, kwargs, 4, actions, 3)
    assert want[2].sum() >= 3 and got[0].shape[-1] > 60
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"seed": True}, TypeError, "seed must be None or an integer ≥ 0, got True"),
        ({"seed": 1.5}, TypeError, "seed must be None or an integer ≥ 0, got 1.5"),
        ({"seed": -1}, ValueError, "seed must be None or an integer ≥ 0, got -1"),
        ({"seed": [0, -1]}, ValueError, "seed must be None or an integer ≥ 0, got -1"),
        ({"seed": [0, "1"]}, TypeError, "seed must be None or an integer ≥ 0, got '1'"),
        ({"seed": [0]}, ValueError, "seed: got 1 seeds for 2 envs"),
        ({"options": "abc"}, TypeError, "options must be a dict of keyword arguments or None, got 'abc'"),
        ({"options": {"trail": None}}, ValueError, "options: unknown key(s) 'trail'; known: trial"),
        ({"options": {"trial": "x"}}, TypeError, "options['trial'] must be a magenv.trial.Trial, got str"),
    ],
)
def test_reset_checks_seed_and_options_as_the_single_env(kwargs, error, message):
    """The vector env refuses what the single env refuses, with the same message, before any sub-env resets."""
    trial = kinematic_trial(duration=1.0)
    vec = gym.make_vec(BLEND_ID, num_envs=2, vectorization_mode="vector_entry_point", scenario=[trial])
    vec.reset(seed=[3, 4])
    before = vec.unwrapped.pos.copy()
    with pytest.raises(error) as caught:
        vec.reset(**kwargs)
    assert message in str(caught.value)
    np.testing.assert_array_equal(vec.unwrapped.pos, before)
    single = gym.make(BLEND_ID, scenario=[trial])
    if not isinstance(kwargs.get("seed"), list):
        with pytest.raises(error, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            single.reset(**kwargs)
