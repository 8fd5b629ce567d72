"""Rendering (magenv.envs.render): frames of every env, the GL / matplotlib choice, human mode, RecordVideo."""

from __future__ import annotations

import ctypes.util
import dataclasses
import logging

import gymnasium as gym
import numpy as np
import pytest

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, KALMAN_ID
from magenv.envs import render as rd
from magenv.envs.blend import MagBlendEnv
from tests.conftest import ENV_CASES

CASES = [(env_id, case.render) for env_id, case in ENV_CASES.items() if case.render]
FRAME = (rd.SCENE_HEIGHT + rd.STRIP_HEIGHT, rd.WIDTH, 3)


def _episode(env_id, scenario, render_mode, steps=12, seed=3):
    env = gym.make(env_id, scenario=scenario, episode_seconds=1.0, render_mode=render_mode)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(np.full(env.action_space.shape, 0.5, np.float32))
        out.append(obs)
        if terminated or truncated:
            break
    return env, np.array(out)


@pytest.fixture
def fresh_backend(monkeypatch):
    """Forget the process's backend choice for one test (restored afterwards)."""
    monkeypatch.setattr(rd, "_BACKEND", None)


@pytest.mark.parametrize("env_id, scenario", CASES)
def test_rgb_array_frame_of_every_env_and_rendering_leaves_the_episode_alone(env_id, scenario):
    env, obs = _episode(env_id, scenario, "rgb_array")
    frame = env.render()
    assert frame.shape == FRAME and frame.dtype == np.uint8
    scene, strip = frame[: rd.SCENE_HEIGHT], frame[rd.SCENE_HEIGHT :]
    assert scene.std() > 5 and strip.std() > 5  # something is drawn in both parts
    assert np.any(np.all(strip == (255, 127, 14), axis=-1))  # the trust curve
    env.close()
    plain, obs_plain = _episode(env_id, scenario, None)
    np.testing.assert_array_equal(obs, obs_plain)
    assert plain.render() is None and plain.unwrapped._view is None  # nothing made without a render mode


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="OSMesa not installed (Debian: libosmesa6)")
def test_mujoco_draws_the_gimbal_where_osmesa_is_installed(fresh_backend, monkeypatch, caplog):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    with caplog.at_level(logging.INFO, logger="magenv.render"):
        assert rd.scene_backend()[0] == "mujoco"
        rd.scene_backend()
    assert len(caplog.records) == 1 and "MuJoCo offscreen" in caplog.text  # said once
    env, _ = _episode(BLEND_ID, "dynamic_magnet", "rgb_array")
    env.render()
    assert isinstance(env.unwrapped._view.scene, rd.MujocoScene)
    env.close()


def test_matplotlib_fallback_is_chosen_and_said_once_without_gl(fresh_backend, monkeypatch, caplog):
    monkeypatch.setenv("MUJOCO_GL", "disable")
    with caplog.at_level(logging.INFO, logger="magenv.render"):
        kind, why = rd.scene_backend()
        rd.scene_backend()
    assert kind == "matplotlib" and "MUJOCO_GL" in why
    assert [r.levelno for r in caplog.records] == [logging.WARNING] and "fallback" in caplog.text
    env, _ = _episode(KALMAN_ID, "dynamic_magnet", "rgb_array")
    frame = env.render()
    assert frame.shape == FRAME and isinstance(env.unwrapped._view.scene, rd.AxesScene)
    assert env.unwrapped.render_backend == (kind, why)
    env.close()


def test_a_recording_renders_axes_and_strip_only(short_trials):
    trial = dataclasses.replace(short_trials[0], meta={})  # like a recording: no scenario, no world to draw
    env = gym.make(BLEND_ID, scenario=[trial], render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.array([0.3], np.float32))
    assert env.render().shape == FRAME and isinstance(env.unwrapped._view.scene, rd.AxesScene)
    env.close()


def test_bad_render_mode_and_human_without_display(monkeypatch):
    with pytest.raises(ValueError, match="render_mode must be None, 'rgb_array' or 'human'"):
        MagBlendEnv(render_mode="ansi")
    monkeypatch.setattr(rd.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match="needs a display"):
        gym.make(BLEND_ID, render_mode="human")


def test_strip_draws_error_and_trust_where_they_are():
    strip = rd.Strip(200, 100, seconds=10.0)
    t = np.arange(0.0, 10.0, 0.01)
    image = strip.draw(t, np.full(t.size, 0.5), np.full(t.size, 1.0))  # error half the 1° axis, trust at top
    _, (c0, c1, r0, r1) = strip._background(1.0)
    orange = np.nonzero(np.all(image == (255, 127, 14), axis=-1))[0]
    dark = np.nonzero(np.all(image[r0:r1, c0:c1] == (38, 38, 38), axis=-1))[0] + r0
    assert abs(np.median(dark) - (r0 + r1) / 2) < 3
    assert abs(np.median(orange) - (r1 - (1.05 / 1.1) * (r1 - r0))) < 3


def test_record_video_writes_an_mp4(tmp_path):
    pytest.importorskip("moviepy")
    env = gym.make(BLEND_ID, scenario="dynamic_clean", episode_seconds=0.5, render_mode="rgb_array")
    env = gym.wrappers.RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda e: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        *_, terminated, truncated, _ = env.step(np.array([0.5], np.float32))
        done = terminated or truncated
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


class _HalfTrust:
    """A fixed policy: λ = 0.5 on MagBlend."""

    env_id = BLEND_ID
    env_kwargs: dict = {}

    def reset(self):
        pass

    def __call__(self, obs):
        return np.array([0.5], np.float32)


def test_policy_runner_records_a_trial_as_mp4(short_trials, tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    from magenv.evaluation import PolicyRunner

    trial = short_trials[0].slice(0, 200)
    path = PolicyRunner().record(_HalfTrust(), trial, tmp_path / "half.mp4")
    assert path.stat().st_size > 1000
    with pytest.raises(ValueError, match=r"\.mp4"):
        rd.write_video([np.zeros((8, 8, 3), np.uint8)], tmp_path / "x.gif")


def test_pictures_frame_at_the_peak_disturbance_saved_small(tmp_path):
    from magenv import registry
    from magenv.scenarios import make_trial
    from magenv.train.pictures import PALETTE_COLOURS, frame_at_peak, save_small_png

    trial = make_trial("dynamic_magnet", 0, duration=8.0)
    frame = frame_at_peak(registry.make("fan_lambda_tuned"), trial)
    assert frame.shape == FRAME
    from PIL import Image

    saved = Image.open(save_small_png(frame, tmp_path / "f.png"))
    assert saved.mode == "P" and len(saved.getcolors()) <= PALETTE_COLOURS


@pytest.mark.slow
def test_magenv_pictures_writes_both_pngs(tmp_path):
    from magenv.train.cli import main

    assert main(["pictures", "--out", str(tmp_path)]) == 0
    assert {p.name for p in tmp_path.iterdir()} == {"frame.png", "trust.png"}


@pytest.mark.parametrize("scenario, site", [("constraint_test1", "imu_i"), ("dynamic_magnet", "imu")])
def test_scene_is_posed_at_the_true_orientation(scenario, site):
    import mujoco

    from magenv.quaternion import to_matrix
    from magenv.scenarios import make_trial

    trial = make_trial(scenario, 1, duration=3.0)
    built = rd._scene_model(trial)
    data = mujoco.MjData(built.model)
    for i in (0, trial.n // 2, trial.n - 1):
        position = built.pose(data, i)
        s = built.model.site(site).id
        np.testing.assert_allclose(data.site_xmat[s].reshape(3, 3), to_matrix(trial.q_true[i]), atol=1e-6)
        np.testing.assert_allclose(position, data.site_xpos[s])
    if "q_j" in trial.extra:
        j = built.model.site("imu_j").id
        np.testing.assert_allclose(data.site_xmat[j].reshape(3, 3), to_matrix(trial.extra["q_j"][-1]), atol=1e-6)


def test_hand_held_box_follows_the_true_position_and_orientation():
    import mujoco

    from magenv.quaternion import to_matrix
    from magenv.scenarios import make_trial

    trial = make_trial("handheld_texting", 1, duration=3.0)
    built = rd._scene_model(trial)
    assert built.lookat is None  # the camera follows the walker
    data = mujoco.MjData(built.model)
    for i in (0, trial.n - 1):
        np.testing.assert_allclose(built.pose(data, i), trial.truth["position"][i])
        np.testing.assert_allclose(data.xmat[1].reshape(3, 3), to_matrix(trial.q_true[i]), atol=1e-6)
