"""Property tests (hypothesis): the quaternion kernels, one Madgwick step, the error measures and sums, and the
four envs under any finite action sequence and any sequence of API calls (unit-norm estimates, finite
observations and rewards, the same episode for the same seed, every refusal naming the action or argument).

Examples are drawn by hypothesis with ``derandomize=True``: the same examples on every run.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magenv import quaternion as quat
from magenv import scenarios as cs
from magenv.filters import madgwick
from magenv.metrics import E_COUNT, E_TOTAL, N_ERR, WORST_DEG, error_sums, errors
from tests.conftest import ENV_CASES, kinematic_trial

SETTINGS = settings(derandomize=True, deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])
ENV_SETTINGS = settings(SETTINGS, max_examples=15)

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vectors = arrays(float, 3, elements=finite)
quaternions = (
    arrays(float, 4, elements=st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False))
    .filter(lambda q: np.linalg.norm(q) > 1e-3)
    .map(lambda q: q / np.linalg.norm(q))
)


def unit(q, tol=1e-12) -> bool:
    return abs(np.linalg.norm(q) - 1.0) <= tol


# ----------------------------------------------------------------- quaternion kernels


@SETTINGS
@given(quaternions, quaternions)
def test_a_product_of_unit_quaternions_is_unit_and_conj_inverts(a, b):
    ab = quat.mul1(a, b)
    assert unit(ab)
    np.testing.assert_allclose(quat.mul1(quat.mul1(ab, quat.conj1(b)), quat.conj1(a)), [1, 0, 0, 0], atol=1e-12)


@SETTINGS
@given(quaternions, vectors)
def test_rotation_keeps_length_and_rotate_inv_undoes_it(q, v):
    r = quat.rotate1(q, v)
    assert abs(np.linalg.norm(r) - np.linalg.norm(v)) <= 1e-12 * max(1.0, np.linalg.norm(v))
    np.testing.assert_allclose(quat.rotate_inv1(q, r), v, atol=1e-12 * max(1.0, np.linalg.norm(v)))


@SETTINGS
@given(arrays(float, 4, elements=finite))
def test_normalize_gives_a_unit_quaternion_for_any_finite_input(q):
    assert unit(quat.normalize1(q))


@SETTINGS
@given(arrays(float, 3, elements=st.floats(-3.0, 3.0)).filter(lambda r: np.linalg.norm(r) < math.pi - 1e-3))
def test_rotation_vector_round_trip(r):
    q = quat.from_rotvec1(r)
    assert unit(q)
    np.testing.assert_allclose(quat.to_rotvec1(q), r, atol=1e-9)


@SETTINGS
@given(quaternions, arrays(float, 3, elements=st.floats(-50.0, 50.0)), st.floats(1e-4, 0.1))
def test_gyro_integration_keeps_unit_norm(q, gyr, dt):
    assert unit(quat.integrate_gyro1(q, gyr, dt))


# ----------------------------------------------------------------- one Madgwick step


@SETTINGS
@given(
    quaternions,
    arrays(float, 3, elements=st.floats(-50.0, 50.0)),
    vectors,
    vectors,
    st.sampled_from([madgwick.MODE_IMU, madgwick.MODE_MIMU]),
    st.floats(0.0, madgwick.BETA_MAX),
    st.floats(1e-4, 0.1),
)
def test_a_madgwick_step_keeps_unit_norm_for_any_finite_sample(q, gyr, acc, mag, mode, beta, dt):
    """Any finite sample (a zero accelerometer or magnetometer included) and any accepted β give a unit q."""
    out = np.array(madgwick.step(tuple(q), gyr, acc, mag, mode, madgwick.NO_REF, beta, dt))
    assert np.all(np.isfinite(out)) and unit(out, 1e-9)


# ----------------------------------------------------------------- error measures and sums


@SETTINGS
@given(quaternions, quaternions)
def test_errors_are_angles_sign_blind_and_ordered(q, t):
    """total ∈ [0, 180]°, the same for −q, zero against itself; heading and inclination never exceed total."""
    e = errors(q, t)
    total, heading, incl = e
    assert 0.0 <= total <= 180.0
    np.testing.assert_allclose(errors(-q, t), e, atol=1e-9)
    assert heading <= total + 1e-9 and incl <= total + 1e-9
    assert errors(t, t)[0] <= 1e-5


@SETTINGS
@given(
    st.lists(
        st.tuples(quaternions, quaternions, st.sampled_from(["ok", "nan_est", "inf_est", "no_truth"])),
        min_size=1,
        max_size=30,
    )
)
def test_error_sums_charge_a_non_finite_estimate_180_degrees(rows):
    """The step sums of the envs: each sample with truth counts once, a NaN/inf estimate as 180° (never 0°)."""
    est = np.array([q for q, _, _ in rows])
    truth = np.array([t for _, t, _ in rows])
    kinds = [k for _, _, k in rows]
    est[[k == "nan_est" for k in kinds]] = np.nan
    est[[k == "inf_est" for k in kinds]] = np.inf
    truth[[k == "no_truth" for k in kinds]] = np.nan
    err = np.empty(N_ERR)
    error_sums(est, truth, np.zeros(len(rows)), 0, len(rows), err)
    per_row = errors(est, truth)[:, 0]
    scored = [k != "no_truth" for k in kinds]
    assert err[E_COUNT] == sum(scored)
    np.testing.assert_allclose(err[E_TOTAL], per_row[scored].sum(), rtol=1e-12, atol=1e-9)
    bad = [k in ("nan_est", "inf_est") for k in kinds]
    assert np.all(per_row[bad] == WORST_DEG)


# ----------------------------------------------------------------- the envs under any finite actions


@pytest.fixture(scope="module")
def env_trials():
    """name → the trials of one env's episodes (sensor trials; two-link ones for the constraint env)."""
    sensor = [kinematic_trial(seed=s, duration=1.0, disturbance_ut=30.0, disturbance_window=(0.3, 0.6)) for s in (0, 1)]
    twolink = [cs.make_trial("constraint_test2", s, duration=8.0, disturbances=((0.3, 0.3),)) for s in (0, 1)]
    return {env_id.split("/")[1]: twolink if case.twolink else sensor for env_id, case in ENV_CASES.items()}


ENVS = {  # env → (decision_every, a strategy of one finite action, in range or not)
    env_id.split("/")[1]: (
        case.decision_every,
        arrays(np.float32, case.action_dim, elements=st.floats(*case.action_range, width=32)),
    )
    for env_id, case in ENV_CASES.items()
}


def _make(env_id: str, trials):
    """The env on ``trials``, episodes cut to 1 s."""
    return gym.make(f"magenv/{env_id}", scenario=trials, decision_every=ENVS[env_id][0], episode_seconds=1.0)


def _episode(env_id: str, trials, seed: int, actions):
    """(observations, rewards, estimates) of one episode, the actions cycled until it ends."""
    env = _make(env_id, trials)
    obs, _ = env.reset(seed=seed)
    out_obs, rewards, est = [obs], [], []
    done, i = False, 0
    while not done:
        obs, reward, _, done, info = env.step(actions[i % len(actions)])
        out_obs.append(obs)
        rewards.append(reward)
        est.append(info["q_est"])
        i += 1
    return np.array(out_obs), np.array(rewards), np.array(est)


@pytest.mark.parametrize("env_id", list(ENVS))
def test_any_finite_actions_keep_the_estimate_unit_and_everything_finite(env_id, env_trials):
    @ENV_SETTINGS
    @given(st.integers(0, 2**31 - 1), st.lists(ENVS[env_id][1], min_size=1, max_size=12))
    def check(seed, actions):
        obs, rewards, est = _episode(env_id, env_trials[env_id], seed, actions)
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
        assert np.all(np.abs(np.linalg.norm(est, axis=1) - 1.0) <= 1e-9)
        assert np.all(rewards <= 0.0)

    check()


@pytest.mark.parametrize("env_id", ["MagBlend-v0", "MagQSF-v0", "MagVQF-v0"])
def test_the_same_seed_gives_the_same_episode_bit_for_bit(env_id, env_trials):
    @ENV_SETTINGS
    @given(st.integers(0, 2**31 - 1), st.lists(ENVS[env_id][1], min_size=1, max_size=6))
    def check(seed, actions):
        first, again = (_episode(env_id, env_trials[env_id], seed, actions) for _ in range(2))
        for a, b in zip(first, again, strict=True):
            assert a.tobytes() == b.tobytes()

    check()


BAD_ACTIONS = st.one_of(
    st.just(np.array([np.nan], np.float32)),
    st.just(np.array([np.inf, 0.5], np.float32)),
    st.just("fast"),
    st.just(None),
    st.just(np.zeros((2, 1), np.float32)),
    st.just(np.zeros(3, np.float32)),
    st.just(np.zeros((1, 2), np.float32)),
)


@pytest.mark.parametrize("env_id", list(ENVS))
def test_a_refused_action_names_the_action_and_leaves_the_episode_as_it_was(env_id, env_trials):
    """Random sequences of good and bad actions: each bad one a ValueError/TypeError naming ``action`` that
    changes nothing (the episode then goes on as if it had not been sent)."""
    good = ENVS[env_id][1]

    @ENV_SETTINGS
    @given(
        st.lists(
            st.one_of(st.tuples(st.just("good"), good), st.tuples(st.just("bad"), BAD_ACTIONS)), min_size=1, max_size=10
        )
    )
    def check(calls):
        env, clean = _make(env_id, env_trials[env_id][:1]), _make(env_id, env_trials[env_id][:1])
        for e in (env, clean):
            e.reset(seed=0)
        for kind, action in calls:
            if kind == "bad":
                with pytest.raises((ValueError, TypeError), match="action"):
                    env.step(action)
                continue
            got, want = env.step(action), clean.step(action)
            assert got[0].tobytes() == want[0].tobytes() and got[1] == want[1]
            if got[3]:
                break

    check()


BAD_RESETS = st.sampled_from(
    [
        ("seed", {"seed": -1}),
        ("seed", {"seed": 1.5}),
        ("seed", {"seed": "0"}),
        ("options", {"options": "abc"}),
        ("options", {"options": {"trail": None}}),
    ]
)
API_CALLS = st.one_of(
    st.tuples(st.just("reset"), st.one_of(st.none(), st.integers(0, 2**31 - 1))),
    st.tuples(st.just("bad_reset"), BAD_RESETS),
    st.tuples(st.just("step"), st.none()),
    st.tuples(st.just("bad_step"), BAD_ACTIONS),
)


@pytest.mark.parametrize("env_id", list(ENVS))
def test_random_api_call_sequences_give_finite_outputs_or_named_refusals(env_id, env_trials):
    """Seeded random sequences of calls on a fresh env — reset (seeded or not), step with a finite action, reset
    with a bad seed or options, step with a bad action — in any order: everything returned is finite with
    rewards ≤ 0; a step before the first reset or after truncation is refused (Gymnasium's ResetNeeded or our
    RuntimeError), a bad argument is a ValueError/TypeError naming it, and a refused call changes nothing."""
    good = ENVS[env_id][1]

    @ENV_SETTINGS
    @given(st.lists(API_CALLS, min_size=1, max_size=14), st.data())
    def check(calls, data):
        env = _make(env_id, env_trials[env_id])
        started = done = False
        for kind, arg in calls:
            if kind == "reset":
                obs, _ = env.reset(seed=arg)
                assert np.all(np.isfinite(obs))
                started, done = True, False
            elif kind == "bad_reset":
                name, kwargs = arg
                with pytest.raises((ValueError, TypeError), match=name):
                    env.reset(**kwargs)
            elif kind == "step" and started and not done:
                obs, reward, terminated, truncated, info = env.step(data.draw(good))
                assert np.all(np.isfinite(obs)) and math.isfinite(reward) and reward <= 0.0
                assert unit(info["q_est"], 1e-9)
                done = terminated or truncated
            elif kind == "step":
                with pytest.raises((RuntimeError, gym.error.ResetNeeded)):
                    env.step(data.draw(good))
            elif started and not done:
                with pytest.raises((ValueError, TypeError), match="action"):
                    env.step(arg)
        env.close()

    check()


def test_a_refused_vector_step_steps_no_sub_env(env_trials):
    """NaN in one row of a vector env's actions: refused before any sub-env steps (sub-env 0 then goes on
    exactly as a vector env that never saw the bad step)."""
    make = lambda: gym.make_vec(
        "magenv/MagBlend-v0", num_envs=2, vectorization_mode="vector_entry_point", scenario=env_trials["MagBlend-v0"]
    )
    env, clean = make(), make()
    for e in (env, clean):
        e.reset(seed=3)
    with pytest.raises(ValueError, match=r"env 1 got \[nan\]"):
        env.step(np.array([[0.2], [np.nan]], np.float32))
    good = np.array([[0.2], [0.7]], np.float32)
    for _ in range(3):
        got, want = env.step(good), clean.step(good)
        assert got[0].tobytes() == want[0].tobytes() and np.array_equal(got[1], want[1])


# ----------------------------------------------------------------- constructor arguments, fuzzed

ODD_VALUES = [math.nan, math.inf, -math.inf, -1, 0, 1e-9, 0.5, 1, 2, 1e9, None, "x", True, [1.0], {}, (1, 2)]
NOT_FUZZED = {"scenario", "render_mode", "prefetch"}  # the trial source; a worker process; refused by design


def _arguments(env_id: str) -> list[str]:
    import inspect

    cls = gym.spec(f"magenv/{env_id}").entry_point
    cls = gym.envs.registration.load_env_creator(cls) if isinstance(cls, str) else cls
    return [p for p in inspect.signature(cls.__init__).parameters if p not in NOT_FUZZED | {"self"}]


@pytest.mark.parametrize("env_id", list(ENVS))
def test_any_constructor_argument_is_taken_or_refused_by_name(env_id, env_trials):
    """One argument set to an odd value: the env is built and runs a finite, unit-norm episode (or reports a
    divergence as FloatingPointError), or the constructor raises ValueError/TypeError naming the argument."""
    names = _arguments(env_id)
    assert len(names) >= 4

    @settings(SETTINGS, max_examples=40)
    @given(st.sampled_from(names), st.sampled_from(ODD_VALUES))
    def check(name, value):
        try:
            env = gym.make(f"magenv/{env_id}", scenario=env_trials[env_id][:1], **{name: value})
        except (ValueError, TypeError) as exc:
            assert name in str(exc), f"{name}={value!r}: {exc}"
            return
        env.reset(seed=0)
        mid = (env.action_space.low + env.action_space.high) / 2
        done = False
        try:
            while not done:
                obs, reward, _, done, info = env.step(mid)
                assert np.all(np.isfinite(obs)) and math.isfinite(reward) and unit(info["q_est"], 1e-9)
        except FloatingPointError as exc:
            assert "diverged" in str(exc) or "non-finite" in str(exc), f"{name}={value!r}: {exc}"

    check()


def _keywords(fn, skip=()) -> list[str]:
    import inspect

    return [
        p.name for p in inspect.signature(fn).parameters.values() if p.default is not p.empty and p.name not in skip
    ]


def test_any_qsf_filter_or_detector_keyword_is_taken_or_refused_by_name(env_trials):
    """``MagQSF-v0``'s ``filter_kwargs`` and ``detector`` mappings, one key set to an odd value: as above."""
    from magenv.filters import qsf

    keys = [("filter_kwargs", k) for k in _keywords(qsf.make_params, skip={"mode"})]
    keys += [("detector", k) for k in ("window_s", "th_spread", "th_drift", "max_period_s")]
    assert len(keys) >= 12

    @settings(SETTINGS, max_examples=40)
    @given(st.sampled_from(keys), st.sampled_from(ODD_VALUES))
    def check(key, value):
        option, name = key
        try:
            env = gym.make("magenv/MagQSF-v0", scenario=env_trials["MagQSF-v0"][:1], **{option: {name: value}})
        except (ValueError, TypeError) as exc:
            assert name in str(exc), f"{option}={{{name!r}: {value!r}}}: {exc}"
            return
        env.reset(seed=0)
        done = False
        try:
            while not done:
                obs, reward, _, done, info = env.step(np.array([0.0, 0.5], np.float32))
                assert np.all(np.isfinite(obs)) and math.isfinite(reward) and unit(info["q_est"], 1e-9)
        except FloatingPointError as exc:
            assert "diverged" in str(exc) or "non-finite" in str(exc), f"{option}={{{name!r}: {value!r}}}: {exc}"

    check()
