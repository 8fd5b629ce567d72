"""Shared test helpers.

``kinematic_trial`` builds a small Trial without MuJoCo: orientation
integrated from a smooth random body rate, ideal sensor readings from that
orientation plus white noise, and an optional magnetic disturbance window.
Filter tests use it where the physics of the gimbal does not matter.

Env test helpers: ``short_trials`` (fixture), ``run_episode``,
``check_seeded_replay``, ``check_scalar_action``, ``check_with_checkers``;
``ENV_CASES``, what the tests that cover every env run each on (a new env adds its case).

``ray_2cpu`` (fixture): one local Ray of 2 CPUs per test module; skips,
naming the extra, where Ray is not installed.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from magenv import quaternion as quat
from magenv.recordings import BROAD_DIR_ENV
from magenv.recordings import broad_dir as find_broad_dir
from magenv.trial import Trial, TrialError


def _recordings_folder() -> tuple[Path | None, str]:
    """(the BROAD recordings folder the loader reads, or None; why none)."""
    try:
        return find_broad_dir(), ""
    except TrialError as exc:
        return None, str(exc)


# Found once, before the session's fixtures point the user data folder elsewhere; the loader then reads the same
# folder in every test (``recording:`` scenarios, ``twins:``) through MAGENV_BROAD_DIR.
BROAD_DIR, _NO_BROAD = _recordings_folder()
if BROAD_DIR is not None:
    os.environ[BROAD_DIR_ENV] = str(BROAD_DIR)


def _broad_names() -> list[str]:
    from magenv.train.data import manifest_path, read_manifest

    return [entry["name"] for entry in read_manifest(manifest_path())["files"]]


#: the file names of the BROAD recordings magenv uses (the shipped manifest's), to parametrize tests over
#: without reading the folder at collection (``broad_dir / name`` inside the test: skipped where there is none)
BROAD_NAMES = _broad_names()


@pytest.fixture(autouse=True, scope="session")
def _own_user_data_dir(tmp_path_factory):
    """Tests never read or write the user's magenv data (tuned rules) or cache (fitted twins): they get empty
    folders of their own."""
    import os

    from magenv import registry
    from magenv.scenarios import twin

    keys = (registry.DATA_DIR_ENV, twin.CACHE_DIR_ENV)
    old = {k: os.environ.get(k) for k in keys}
    for k in keys:
        os.environ[k] = str(tmp_path_factory.mktemp(k.lower()))
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def ray_2cpu():
    """One local Ray of 2 CPUs for this module."""
    ray = pytest.importorskip("ray", reason="Ray is the extra magenv[scale]: pip install 'magenv[scale]'")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def kinematic_trial(
    seed: int = 0,
    duration: float = 20.0,
    rate: float = 256.0,
    max_rate_dps: float = 60.0,
    disturbance_ut: float = 0.0,
    disturbance_window: tuple[float, float] = (8.0, 12.0),
    field_norm: float = 46.0,
    field_dip: float = 49.6,
    noise: bool = True,
) -> Trial:
    """A Trial with known truth: smooth random rotation, optional constant
    magnetic disturbance (µT, earth-frame east) inside ``disturbance_window`` (s)."""
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate))
    dt = 1.0 / rate
    t = np.arange(n) * dt
    # Smooth body rate: a few random sinusoids per axis, rad/s.
    freqs = rng.uniform(0.05, 0.4, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    amp = np.deg2rad(max_rate_dps) / 3
    gyr = amp * np.sin(2 * np.pi * freqs[None] * t[:, None, None] + phases[None]).sum(-1)
    q = np.empty((n, 4))
    q[0] = quat.from_euler_zyx(rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3))
    for i in range(1, n):
        q[i] = quat.integrate_gyro1(q[i - 1], 0.5 * (gyr[i - 1] + gyr[i]), dt)
    field = np.broadcast_to(quat.earth_field(field_norm, field_dip), (n, 3)).copy()
    disturbed = (t >= disturbance_window[0]) & (t < disturbance_window[1])
    field[disturbed, 0] += disturbance_ut
    acc = quat.rotate_inv(q, np.broadcast_to(quat.gravity_up(), (n, 3)))
    mag = quat.rotate_inv(q, field)
    if noise:
        gyr = gyr + rng.normal(0, np.deg2rad(0.5), (n, 3))
        acc = acc + rng.normal(0, 0.02, (n, 3))
        mag = mag + rng.normal(0, 0.15, (n, 3))
    mag_dist = quat.rotate_inv(q, field - quat.earth_field(field_norm, field_dip))
    return Trial(
        name=f"kinematic_{seed}",
        rate=rate,
        gyr=gyr,
        acc=acc,
        mag=mag,
        q_true=q,
        field_norm=field_norm,
        field_dip=field_dip,
        truth={"mag_disturbance": mag_dist, "stationary": np.zeros(n, bool)},
        meta={"scenario": "kinematic", "seed": seed},
    )


@pytest.fixture
def make_kinematic_trial():
    """Factory fixture: ``make_kinematic_trial(seed=…, duration=…, …)``."""
    return kinematic_trial


@pytest.fixture(scope="module")
def short_trials():
    """Two 3 s kinematic trials, 20 µT disturbance from 1 to 2 s (a test module may define its own)."""
    return [kinematic_trial(seed=s, duration=3.0, disturbance_ut=20.0, disturbance_window=(1.0, 2.0)) for s in range(2)]


def require_broad() -> Path:
    """Folder of the real BROAD recordings (``magenv.recordings.broad_dir``). Where there are none, the calling
    test is skipped with the reason and the command that fetches them — except under CI (``CI`` set), where it
    fails, so that CI keeps testing them."""
    if BROAD_DIR is None:
        if os.environ.get("CI"):
            pytest.fail(f"CI is set and the BROAD recordings are missing: {_NO_BROAD}")
        pytest.skip(_NO_BROAD)  # names the places looked in and `magenv data broad`
    return BROAD_DIR


@pytest.fixture(scope="session")
def broad_dir() -> Path:
    """:func:`require_broad` as a fixture."""
    return require_broad()


def run_episode(env, seed, actions):
    """Reset with ``seed`` and step ``actions`` (scalars, sent as (1,) float32) until truncated: (obs, rewards)."""
    obs, _ = env.reset(seed=seed)
    out_obs, rewards = [obs], []
    for a in actions:
        obs, r, _, trunc, _ = env.step(np.array([a], np.float32))
        out_obs.append(obs)
        rewards.append(r)
        if trunc:
            break
    return np.array(out_obs), np.array(rewards)


def check_seeded_replay(env_id: str, kwargs: dict, seed: int, actions, n_steps: int) -> None:
    """``gym.make(env_id, **kwargs)`` replays seed ``seed`` bit for bit in ``n_steps`` steps; seed + 1 differs."""
    import gymnasium as gym

    a = run_episode(gym.make(env_id, **kwargs), seed, actions)
    b = run_episode(gym.make(env_id, **kwargs), seed, actions)
    c = run_episode(gym.make(env_id, **kwargs), seed + 1, actions)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert len(a[1]) == n_steps
    assert not np.array_equal(a[0], c[0])


def check_step_order(env, action: float = 0.5) -> None:
    """``step`` before ``reset`` raises; an episode runs to truncation (never terminated); a step after it raises."""
    step = np.array([action], np.float32)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(step)
    env.reset(seed=0)
    trunc = False
    while not trunc:
        _, _, term, trunc, _ = env.step(step)
        assert not term
    with pytest.raises(RuntimeError, match="truncated"):
        env.step(step)


def check_step_errors(env, trial, action: float, first: int, every: int, steps: int = 40) -> list:
    """Over ``steps`` steps of ``every`` samples from sample ``first`` on: each reward is minus the mean total error
    (``magenv.metrics``) of the step's samples, and ``info``'s error parts, disturbance norm, ``q_true`` and
    ``q_est`` are those of the step's samples (the last sample's quaternions). Returns (samples, info) per step."""
    from magenv import metrics

    env.reset(seed=0)
    out = []
    for step in range(steps):
        _, reward, _, _, info = env.step(np.array([action], np.float32))
        sl = slice(first + every * step, first + every * (step + 1))
        q_err = metrics.error_quaternion(env.estimate[sl], trial.q_true[sl])
        assert reward == pytest.approx(-np.mean(metrics.total_error(q_err)), abs=1e-9)
        assert info["error_heading"] == pytest.approx(np.mean(metrics.heading_error(q_err)), abs=1e-9)
        assert info["error_inclination"] == pytest.approx(np.mean(metrics.inclination_error(q_err)), abs=1e-9)
        dist = np.linalg.norm(trial.truth["mag_disturbance"][sl], axis=1).mean()
        assert info["disturbance_norm"] == pytest.approx(dist)
        np.testing.assert_array_equal(info["q_true"], trial.q_true[sl.stop - 1])
        np.testing.assert_array_equal(info["q_est"], env.estimate[sl.stop - 1])
        out.append((sl, info))
    return out


def check_feature_subset(env_class, trials, table, names: list[str], seed: int) -> None:
    """``features=names`` gives those columns of the full observation, in that order; an unknown name is refused."""
    env, full = env_class(scenario=trials, features=names), env_class(scenario=trials)
    picked, _ = env.reset(seed=seed)
    whole, _ = full.reset(seed=seed)
    assert env.observation_space.shape == (len(names),)
    np.testing.assert_array_equal(picked, whole[[table.index(n) for n in names]])
    with pytest.raises(ValueError, match="unknown observation feature"):
        env_class(scenario=trials, features=[names[0], "truth"])


def check_scalar_action(env, key: str) -> None:
    """After ``reset``: NaN/inf and wrong shapes raise; out-of-range values are clipped (``info[key]``); scalars work.

    Steps three times, with 1 (clipped from 1.7), 0 (from −0.2) and 0.25.
    """
    for bad in (np.array([np.nan], np.float32), np.array([np.inf])):
        with pytest.raises(ValueError, match="finite"):
            env.step(bad)
    for bad in (np.array([0.1, 0.2]), np.zeros((1, 1)), []):
        with pytest.raises(ValueError, match="shape"):
            env.step(bad)
    _, _, _, _, info = env.step(np.array([1.7], np.float32))
    assert info["action_clipped"] and info[key] == 1.0
    _, _, _, _, info = env.step(np.array([-0.2], np.float32))
    assert info["action_clipped"] and info[key] == 0.0
    _, _, _, _, info = env.step(0.25)  # a plain scalar is accepted
    assert not info["action_clipped"] and info[key] == 0.25


def check_with_checkers(env_id: str, env_class, **kwargs) -> None:
    """gymnasium's and stable-baselines3's env checkers pass (SB3 only advises a [-1, 1] action box)."""
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(gym.make(env_id, **kwargs).unwrapped, skip_render_check=True)
    with pytest.warns(UserWarning, match="symmetric"):
        sb3_check_env(env_class(**kwargs), warn=True)


def check_feature_table(env, table) -> None:
    """With all features, ``env``'s observation is ``table`` (names, float32 bounds) and its class docstring
    shows ``table.markdown()`` in place of the ``{observation_table}`` placeholder."""
    doc = type(env).__doc__
    assert env.features == table.names
    np.testing.assert_array_equal(env.observation_space.low, table.low)
    np.testing.assert_array_equal(env.observation_space.high, table.high)
    assert "{observation_table}" not in doc
    for row in table.markdown().splitlines():
        assert row in doc


def check_kernel_layout(env, table, index) -> None:
    """The kernels' feature indices ``index`` (``index.name`` is that feature's column) follow ``table``, and
    a first observation of ``env`` lies in the table's ranges."""
    assert index._fields == table.names and tuple(index) == tuple(range(len(table)))
    obs, _ = env.reset(seed=0)
    assert np.all(obs >= table.low) and np.all(obs <= table.high)


@dataclass(frozen=True)
class EnvCase:
    """What the tests that cover every env run one env on."""

    batch_trials: Callable[[], list]  # tests/test_env_batch.py: short trials, several episodes each
    action_dim: int
    decision_every: int  # tests/test_properties.py: its steps, its finite actions drawn in action_range
    action_range: tuple[float, float] = (-2.0, 3.0)
    twolink: bool = False  # tests/test_properties.py runs it on two-link trials (else on sensor trials)
    render: str | None = None  # tests/test_env_render.py: the scenario of its frames (None: not rendered there)


def _disturbed(*seeds_durations) -> list:
    return [kinematic_trial(seed=s, duration=d, disturbance_ut=20.0) for s, d in seeds_durations]


def _twolink() -> list:
    from magenv.scenarios import make_trial

    return [make_trial("constraint_test1", 3, duration=5.0), make_trial("constraint_random", 4)]


def _handheld() -> list:
    from magenv.scenarios import make_trial

    return [make_trial("handheld_texting", 3, duration=3.0), kinematic_trial(seed=5, duration=2.0)]


ENV_CASES = {  # env id → its EnvCase
    "magenv/MagBlend-v0": EnvCase(lambda: _disturbed((0, 1.6), (1, 1.1)), 1, 8, render="dynamic_magnet"),
    "magenv/MagKalman-v0": EnvCase(lambda: _disturbed((2, 1.6), (3, 1.1)), 1, 8, render="dynamic_magnet"),
    "magenv/MagConstraint-v0": EnvCase(_twolink, 1, 8, twolink=True, render="constraint_test1"),
    "magenv/MagQSF-v0": EnvCase(_handheld, 2, 10, (-3.0, 3.0), render="handheld_texting"),
    "magenv/MagVQF-v0": EnvCase(lambda: _disturbed((6, 1.6), (7, 1.1)), 1, 8),
}
