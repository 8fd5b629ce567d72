"""Untrusted run folders, truth checked on load, every bad input named.

* ``test_readme_row``: every row of the "Bad input → what you get" table
  (``docs/bad-input.md``, linked from the README), run as written (the table is read from the page);
* planted pickles: code-running payloads in every pickle-bearing file of a
  run folder never run on load, evaluate, compare or resume — and do run
  with ``trust_pickle``, so the payloads are live;
* checkpoints round-trip every array resuming needs (PPO, SAC, RecurrentPPO).
"""

from __future__ import annotations

import base64
import contextlib
import inspect
import json
import math
import os
import pickle
import re
import shutil
import subprocess
import warnings
import zipfile
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
import torch
import yaml
from stable_baselines3 import PPO

from magenv import registry
from magenv.agents import run_folder, training, weights
from magenv.agents.hyperparams import NOT_IN_CONFIG, VALUE_RULES, algorithm_class, check_section, load_hyperparams
from magenv.agents.loading import RunError, build_model, load_agent, read_run
from magenv.agents.run_folder import RunFolder
from magenv.agents.training import train
from magenv.agents.wrappers import action_bounds
from magenv.recordings import find_recording, load_recording
from magenv.train.cli import main as cli
from magenv.trial import Trial
from tests.conftest import kinematic_trial, require_broad
from tests.test_recordings import write_recording

ENV = "magenv/MagBlend-v0"
ROOT = Path(__file__).resolve().parents[1]
SECTION = {
    "env_kwargs": {"scenario": "dynamic_clean", "episode_seconds": 3.0},
    "normalize_reward": True,
    "n_envs": 2,
    "n_steps": 64,
    "batch_size": 64,
    "n_epochs": 1,
    "learning_rate": 3.0e-4,
    "policy_kwargs": {"net_arch": [8]},
}
QUICK_EVAL = ["--eval-scenarios", "dynamic_clean", "--eval-seeds", "0", "--no-progress"]


def write_config(path: Path, **changes) -> Path:
    path.write_text(yaml.safe_dump({ENV: {**SECTION, **changes}}))
    return path


def fake_run(folder: Path, files=("best", "last"), **changes) -> Path:
    """A run folder as `magenv train` leaves it, with untrained weights (no training: fast)."""
    section = check_section("ppo", {**SECTION, **changes}, "test")
    run = {
        "env_id": ENV,
        "algo": "ppo",
        "env_kwargs": section["env_kwargs"],
        "hyperparams": section,
        "action_bounds": action_bounds(ENV, section["env_kwargs"]),
        "seed": 0,
        "steps": 128,
        "eval_scenarios": ["dynamic_clean"],
        "eval_seeds": [0],
    }
    folder.mkdir(parents=True)
    (folder / "run.yaml").write_text(yaml.safe_dump(run))
    model = build_model(run)
    state = {"timesteps": 128, "best_score": 1.0, "best_timesteps": 128, "t0": 0.0}
    (folder / "state.json").write_text(json.dumps(state))
    for which in files:
        if which == "last":
            weights.save_checkpoint(model, folder / "last.safetensors", state)
        elif which == "best":
            weights.save_policy(model, folder / "best.safetensors", 128)
        else:  # an SB3 file, e.g. "last_model.zip"
            model.save(folder / which)
    return folder


# ----------------------------------------------------------------- the README's table


def readme_rows() -> dict[str, tuple[str, str]]:
    """input cell → (outcome: the first code span of "you get", gist: the code span of "message")."""
    section = (ROOT / "docs" / "bad-input.md").read_text().split("# Bad input → what you get\n", 1)[1]
    rows = {}
    for line in section.splitlines():
        if not line.startswith("| ") or line.startswith(("| input |", "|---")):
            continue
        what, got, message = (c.strip() for c in line.strip().strip("|").split(" | "))
        rows[what] = (re.search(r"`([^`]+)`", got).group(1), re.search(r"`([^`]+)`", message).group(1))
    return rows


class Case:
    """What a row's input does: ``(outcome, text)`` from a command line, a call, or a warning."""

    def __init__(self, tmp_path: Path, capsys):
        self.tmp, self.capsys = tmp_path, capsys

    def cli(self, *argv) -> tuple[str, str]:
        code = cli([str(a) for a in argv])
        out = self.capsys.readouterr()
        return f"exit {code}", out.out + out.err

    @staticmethod
    def call(fn) -> tuple[str, str]:
        try:
            fn()
        except Exception as exc:
            return type(exc).__name__, str(exc)
        return "no error", ""

    @staticmethod
    def warning(fn) -> tuple[str, str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fn()
        return (type(caught[0].message).__name__, str(caught[0].message)) if caught else ("no warning", "")

    def config(self, text: str) -> tuple[str, str]:
        path = self.tmp / "cfg.yaml"
        path.write_text(f"{ENV}:\n  {text}\n")
        return self.call(lambda: load_hyperparams("ppo", ENV, path))

    def recording(self, **kw) -> Path:
        return write_recording(self.tmp / "rec.hdf5", **kw)

    def trial_file(self, edit) -> Path:
        path = kinematic_trial(duration=1.0).save(self.tmp / "trial.h5")
        with h5py.File(path, "a") as f:
            edit(f)
        return path


def _pickle_only(c: Case):
    run = fake_run(c.tmp / "run", files=("best_model.zip",))
    return c.call(lambda: load_agent(run))


def _truncated_weights(c: Case):
    run = fake_run(c.tmp / "run")
    data = (run / "best.safetensors").read_bytes()
    (run / "best.safetensors").write_bytes(data[: len(data) // 2])
    return c.call(lambda: load_agent(run))


def _edited_run_yaml(c: Case, **hyperparams):
    run = fake_run(c.tmp / "run")
    doc = yaml.safe_load((run / "run.yaml").read_text())
    doc["hyperparams"].update(hyperparams)
    (run / "run.yaml").write_text(yaml.safe_dump(doc))
    return c.call(lambda: load_agent(run))


def _resume(c: Case, *flags):
    run = fake_run(c.tmp / "run", files=("last",))
    return c.cli("train", "--out", run, *flags, *QUICK_EVAL)


def _corrupt_chunk(c: Case):
    path = c.recording(n=1000)
    with h5py.File(path, "a") as f:
        data = f["imu_gyr"][()]
        del f["imu_gyr"]
        info = f.create_dataset("imu_gyr", data=data + 0.01, compression="gzip", chunks=(1000, 3)).id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset : info.byte_offset + info.size] = b"\xff" * info.size
    path.write_bytes(bytes(raw))
    return c.call(lambda: load_recording(path))


def _scaled_truth(c: Case, factor):
    return c.call(lambda: load_recording(c.recording(opt_quat=np.tile([factor, 0, 0, 0], (100, 1)))))


def _write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _env(env: str, **kwargs):
    """``gymnasium.make("magenv/" + env, **kwargs)``: the call of a constructor row."""
    return gym.make(f"magenv/{env}", **kwargs)


def _stepped(env: str, action):
    """One reset of ``env`` on a 1 s kinematic trial, then ``step(action)``."""
    e = _env(env, scenario=[kinematic_trial(duration=1.0)])
    e.reset(seed=0)
    e.step(action)


def _vector_step(actions):
    """Two MagBlend-v0 envs in one vector env, reset, then ``step(actions)``."""
    e = gym.make_vec(
        "magenv/MagBlend-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        scenario=[kinematic_trial(duration=1.0)],
    )
    e.reset(seed=0)
    e.step(actions)


def _user_tuned(c: Case, text: str):
    """``tuned_params("fan_lambda")`` with the user's file holding ``text`` (in a data folder of its own)."""
    old = os.environ.get(registry.DATA_DIR_ENV)
    os.environ[registry.DATA_DIR_ENV] = str(c.tmp / "data")
    try:
        registry.user_tuned_dir().mkdir(parents=True)
        (registry.user_tuned_dir() / "fan_lambda.json").write_text(text)
        return c.call(lambda: registry.tuned_params("fan_lambda"))
    finally:
        os.environ[registry.DATA_DIR_ENV] = old


def _yaml_payload(c: Case):
    """A config whose YAML would call ``touch MARKER`` if it were loaded unsafely."""
    marker = c.tmp / "ran"
    got = c.config(f"learning_rate: !!python/object/apply:os.system ['touch {marker}']")
    assert not marker.exists()
    return got


class Killed(BaseException):
    """A kill, in process: nothing catches it, so nothing is written on the way out."""


def _train_args(c: Case, *flags, **config):
    """``magenv train`` into ``c.tmp/run`` with a small config (``config``: changes to it)."""
    return [
        "train",
        "--config",
        write_config(c.tmp / "cfg.yaml", **config),
        "--out",
        c.tmp / "run",
        *QUICK_EVAL,
        *flags,
    ]


def _policy_arrays(path: Path) -> dict:
    return {k: v for k, v in weights.read(path)[0].items() if k.startswith("policy/")}


def _one_rollout(c: Case):
    """One rollout trained: what is saved is the model after its update, not the initial policy."""
    got = c.cli(*_train_args(c, "--steps", "128", "--eval-every", "64"))
    run = read_run(c.tmp / "run")
    initial = {f"policy/{k}": v for k, v in build_model(run, seed=run["seed"]).policy.state_dict().items()}
    for name in ("best.safetensors", "last.safetensors", "checkpoints/step_128.safetensors"):
        saved = _policy_arrays(c.tmp / "run" / name)
        assert any(not np.array_equal(saved[k], initial[k]) for k in saved), name
    assert weights.read(c.tmp / "run" / "last.safetensors")[1]["n_updates"] == 1
    return got


def _continued(c: Case):
    _one_rollout(c)
    got = c.cli(*_train_args(c, "--steps", "256", "--eval-every", "64"))
    first, second = (_policy_arrays(c.tmp / "run" / "checkpoints" / f"step_{t}.safetensors") for t in (128, 256))
    assert any(not np.array_equal(first[k], second[k]) for k in first)
    return got


def _crash_at(mp, module, name: str, at: int) -> None:
    """``module.name`` raises Killed after its ``at``-th call did its work."""
    original, calls = getattr(module, name), [0]

    def wrapped(*args, **kwargs):
        calls[0] += 1
        result = original(*args, **kwargs)
        if calls[0] == at:
            raise Killed
        return result

    mp.setattr(module, name, wrapped)


def _killed_then_again(c: Case, module, name: str, at: int, *flags):
    """``magenv train`` with ``flags`` killed at the ``at``-th call of ``module.name``, then the same command."""
    from tests.test_agents_run_folder import consistent

    with pytest.MonkeyPatch.context() as mp:
        _crash_at(mp, module, name, at)
        with pytest.raises(Killed):
            c.cli(*_train_args(c, *flags))
    got = c.cli(*_train_args(c, *flags))
    consistent(c.tmp / "run")
    return got


def _interrupted_evaluation(c: Case):
    from tests.test_agents_run_folder import consistent

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(training, "run_policy_on_trials", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
        got = c.cli(*_train_args(c, "--steps", "256", "--eval-every", "128"))
    assert json.loads((c.tmp / "run" / "state.json").read_text())["evaluations"] == []
    assert c.cli(*_train_args(c, "--steps", "256", "--eval-every", "128"))[0] == "exit 0"
    assert [r[0] for r in consistent(c.tmp / "run")["evaluations"]] == [128, 256]
    return got


def _second_run(c: Case):
    with RunFolder(c.tmp / "run").locked():
        return c.cli(*_train_args(c, "--steps", "128"))


def _tampered_checkpoint(c: Case, tensors=None, **meta):
    """``magenv train`` resuming a run folder whose ``last.safetensors`` has ``tensors`` and ``meta`` changed."""
    run = fake_run(c.tmp / "run", files=("last",))
    old_tensors, old_meta = weights.read(run / "last.safetensors")
    meta = {**{k: v for k, v in old_meta.items() if k != "format"}, **meta}
    weights._write(run / "last.safetensors", {**old_tensors, **(tensors or {})}, meta)
    return c.cli("train", "--out", run, "--steps", "256", *QUICK_EVAL)


def _read_only_folder(path: Path) -> Path:
    """A folder this process cannot write in: mode 555, and immutable (``chattr +i``) for root, who ignores modes;
    the test is skipped where neither holds."""
    path.mkdir()
    path.chmod(0o555)
    probe = path / "probe"
    try:
        probe.touch()
    except OSError:
        return path
    probe.unlink()
    subprocess.run(["chattr", "+i", str(path)], capture_output=True, check=False)
    try:
        probe.touch()
    except OSError:
        return path
    probe.unlink()
    pytest.skip("no folder here is read-only for this user")


@contextlib.contextmanager
def read_only_folder(path: Path):
    try:
        yield _read_only_folder(path)
    finally:
        subprocess.run(["chattr", "-i", str(path)], capture_output=True, check=False)
        path.chmod(0o755)


def _under_a_file(c: Case, name: str) -> Path:
    (c.tmp / "file").write_text("a file")
    return c.tmp / "file" / name


def _into_read_only(c: Case, *argv_before, option: str, name: str, argv_after=()):
    with read_only_folder(c.tmp / "ro") as ro:
        return c.cli(*argv_before, option, ro / name, *argv_after)


def _compare_plot_without_suffix(c: Case):
    got = c.cli("compare", "--scenario", "dynamic_clean", "--seeds", "0", "--methods", "mimu", "--no-progress",
                "--plot", c.tmp / "out")  # fmt: skip
    assert (c.tmp / "out.png").is_file() and not (c.tmp / "out").exists()
    assert f"wrote {c.tmp / 'out.png'}" in got[1]
    return got


def _broad(c: Case, edit) -> Path:
    """BROAD recording 02 copied, then ``edit(h5py file)`` (skipped where there are no recordings)."""
    require_broad()
    source = find_recording("02")
    path = Path(shutil.copy(source, c.tmp / source.name))
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def _scale(key: str, factor: float):
    def edit(f):
        f[key][...] = f[key][()] * factor

    return edit


def _burst(f):
    gyr = f["imu_gyr"][()]
    gyr[1000] = 1e300
    f["imu_gyr"][...] = gyr


def _diverged(c: Case):
    """Methods diverging on a trial with a 1e300 gyro burst: each row present, each at 180° in every part."""
    from magenv import evaluation

    trial = kinematic_trial(duration=5.0)
    trial.gyr[300] = 1e300
    names = ["mimu", "imu", "fan_lambda", "vqf", "aekf"]
    rows = evaluation.compare({n: registry.make(n) for n in names}, [trial], keep_going=True)
    assert [r["method"] for r in rows] == names and not any("error" in r for r in rows)
    for r in rows:
        assert (r["total_rmse_mean"], r["heading_rmse_mean"], r["inclination_rmse_mean"]) == (180.0, 180.0, 180.0)
    return "no error", "\n".join(r["diverged"] for r in rows)


def _bad_field(**field):
    trial = kinematic_trial(duration=1.0)
    return lambda: Trial(**{**trial.__dict__, **field})


def _set_field(**field):
    def set_it():
        trial = kinematic_trial(duration=1.0)
        for k, v in field.items():
            setattr(trial, k, v)

    return set_it


def _vector_reset(**kw):
    return lambda: gym.make_vec(
        "magenv/MagBlend-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        scenario=[kinematic_trial(duration=1.0)],
    ).reset(**kw)


BOMB = "\n".join(
    [f"{ENV}:", '  a: &a ["x","x","x","x","x","x","x","x","x"]']
    + [f"  {k}: &{k} [{','.join([f'*{p}'] * 9)}]" for p, k in zip("abcdef", "bcdefg")]
    + ["  learning_rate: *g"]
)


def _alias_bomb(c: Case):
    (c.tmp / "bomb.yaml").write_text(BOMB)
    got = c.call(lambda: load_hyperparams("ppo", ENV, c.tmp / "bomb.yaml"))
    assert len(got[1]) < 300, len(got[1])
    return got


CASES = {
    "a run folder holding its model only as SB3 `.zip` (an older magenv, or SB3)": _pickle_only,
    "`magenv train` resuming such a folder": lambda c: c.cli(
        "train", "--out", fake_run(c.tmp / "old", files=("last_model.zip",)), *QUICK_EVAL
    ),
    "a truncated or garbled `best.safetensors`": _truncated_weights,
    "weights that do not fit `run.yaml` (its `net_arch` edited)": lambda c: _edited_run_yaml(
        c, policy_kwargs={"net_arch": [16]}
    ),
    "`run.yaml` with `learning_rate: fast`": lambda c: _edited_run_yaml(c, learning_rate="fast"),
    "`magenv evaluate RUN` before the run's first evaluation (only `last.safetensors`)": lambda c: c.cli(
        "evaluate",
        fake_run(c.tmp / "run", files=("last",)),
        "--scenario",
        "dynamic_clean",
        "--seeds",
        "0",
        "--no-progress",
    ),
    "`magenv train … --eval-every 0`": lambda c: c.cli("train", "--out", c.tmp / "x", "--eval-every", "0"),
    "`magenv train … --steps 0`": lambda c: c.cli("train", "--out", c.tmp / "x", "--steps", "0"),
    "`magenv train … --steps -5`": lambda c: c.cli("train", "--out", c.tmp / "x", "--steps", "-5"),
    "`magenv train … --n-envs -2`": lambda c: c.cli("train", "--out", c.tmp / "x", "--n-envs", "-2"),
    "`magenv train … --seed -1`": lambda c: c.cli("train", "--out", c.tmp / "x", "--seed", "-1"),
    "`magenv train … --eval-seeds 5:3`": lambda c: c.cli("train", "--out", c.tmp / "x", "--eval-seeds", "5:3"),
    "`magenv train … --eval-scenarios nowhere`": lambda c: c.cli(
        "train", "--out", c.tmp / "x", "--eval-scenarios", "nowhere"
    ),
    "resuming a run with another `--seed`": lambda c: _resume(c, "--seed", "1"),
    "resuming a run with a `--config` that changes `learning_rate`": lambda c: _resume(
        c, "--config", write_config(c.tmp / "cfg.yaml", learning_rate=1.0e-3)
    ),
    "resuming a run with an invalid `--config`": lambda c: _resume(
        c, "--config", write_config(c.tmp / "cfg.yaml", n_envs="two")
    ),
    "`magenv train … --steps 64` where PPO's rollout is 128 steps": lambda c: c.cli(
        "train",
        "--config",
        write_config(c.tmp / "cfg.yaml"),
        "--out",
        c.tmp / "run",
        "--steps",
        "64",
        "--eval-every",
        "10000",
        *QUICK_EVAL,
    ),
    "config `learning_rate: fast`": lambda c: c.config("learning_rate: fast"),
    "config `n_envs: two`": lambda c: c.config("n_envs: two"),
    "config `n_envs: 0`": lambda c: c.config("n_envs: 0"),
    'config `policy_kwargs: {net_arch: "64"}`': lambda c: c.config('policy_kwargs: {net_arch: "64"}'),
    "config `batch_size: 0`": lambda c: c.config("batch_size: 0"),
    "config `seed: 3`": lambda c: c.config("seed: 3"),
    'config `normalize_reward: "no"`': lambda c: c.config('normalize_reward: "no"'),
    "a recording whose `opt_quat` is scaled by 1.001": lambda c: c.warning(
        lambda: load_recording(c.recording(opt_quat=np.tile([1.001, 0, 0, 0], (100, 1))))
    ),
    "a recording whose `opt_quat` is scaled by 2": lambda c: _scaled_truth(c, 2.0),
    "a recording whose `opt_quat` is scaled by 0.99": lambda c: _scaled_truth(c, 0.99),
    "a recording with `sampling_rate` 1e12": lambda c: c.call(lambda: load_recording(c.recording(rate=1e12))),
    "a recording with `sampling_rate` 1e-6": lambda c: c.call(lambda: load_recording(c.recording(rate=1e-6))),
    "a recording with 0 rows": lambda c: c.call(lambda: load_recording(c.recording(n=0))),
    "a recording whose `movement` is all false": lambda c: c.call(
        lambda: load_recording(c.recording(movement=np.zeros(100, bool)))
    ),
    "a recording with a corrupt compressed dataset": _corrupt_chunk,
    "`magenv plot` on a trial file without attribute `rate`": lambda c: c.cli(
        "plot", c.trial_file(lambda f: f.attrs.__delitem__("rate"))
    ),
    "`magenv plot` on a trial file whose `meta` is not JSON": lambda c: c.cli(
        "plot", c.trial_file(lambda f: f.attrs.__setitem__("meta", "{not json"))
    ),
    "`magenv plot` on a BROAD recording": lambda c: c.cli("plot", c.recording(), "--out", c.tmp / "rec.png"),
    "`magenv compare --scenario dynamic_magnet --seeds 0 --methods mimu,cf_constraint`": lambda c: c.cli(
        "compare", "--scenario", "dynamic_magnet", "--seeds", "0", "--methods", "mimu,cf_constraint", "--no-progress"
    ),
    "`magenv compare --seeds 5:3`": lambda c: c.cli("compare", "--seeds", "5:3"),
    '`MagBlend-v0` with `beta=float("nan")`': lambda c: c.call(lambda: _env("MagBlend-v0", beta=math.nan)),
    "`MagBlend-v0` with `t0=-1`": lambda c: c.call(lambda: _env("MagBlend-v0", t0=-1)),
    "`MagKalman-v0` with `sigma_mag=0`": lambda c: c.call(lambda: _env("MagKalman-v0", sigma_mag=0)),
    "`MagKalman-v0` with `sigma_gyr=1e9`": lambda c: c.call(lambda: _env("MagKalman-v0", sigma_gyr=1e9)),
    "`MagKalman-v0` with `model_c_a=1.0`": lambda c: c.call(lambda: _env("MagKalman-v0", model_c_a=1.0)),
    '`MagKalman-v0` with `heading_only="yes"`': lambda c: c.call(lambda: _env("MagKalman-v0", heading_only="yes")),
    '`MagVQF-v0` with `rejection="maybe"`': lambda c: c.call(lambda: _env("MagVQF-v0", rejection="maybe")),
    "`MagVQF-v0` with `tau_mag=0`": lambda c: c.call(lambda: _env("MagVQF-v0", tau_mag=0)),
    "`MagConstraint-v0` with `th2=1.5`": lambda c: c.call(lambda: _env("MagConstraint-v0", th2=1.5)),
    "`MagConstraint-v0` with `k_min=2, k_max=1`": lambda c: c.call(lambda: _env("MagConstraint-v0", k_min=2, k_max=1)),
    '`MagQSF-v0` with `filter_kwargs={"max_age_s": math.inf}`': lambda c: c.call(
        lambda: _env("MagQSF-v0", filter_kwargs={"max_age_s": math.inf})
    ),
    '`MagQSF-v0` with `variant="aekf"`': lambda c: c.call(lambda: _env("MagQSF-v0", variant="aekf")),
    'any env with `decision_every=float("nan")`': lambda c: c.call(
        lambda: _env("MagKalman-v0", decision_every=math.nan)
    ),
    "any env with `decision_every=None`": lambda c: c.call(lambda: _env("MagQSF-v0", decision_every=None)),
    "any env with `episode_seconds=math.inf`": lambda c: c.call(lambda: _env("MagBlend-v0", episode_seconds=math.inf)),
    '`env.reset(options="abc")`': lambda c: c.call(lambda: _env("MagBlend-v0").reset(options="abc")),
    '`env.reset(options={"trail": trial})` (a misspelt key)': lambda c: c.call(
        lambda: _env("MagBlend-v0").reset(options={"trail": kinematic_trial(duration=1.0)})
    ),
    "`env.reset(seed=-1)`": lambda c: c.call(lambda: _env("MagBlend-v0").reset(seed=-1)),
    "`MagBlend-v0`: `env.step([math.nan])`": lambda c: c.call(lambda: _stepped("MagBlend-v0", [math.nan])),
    '`MagBlend-v0`: `env.step("fast")`': lambda c: c.call(lambda: _stepped("MagBlend-v0", "fast")),
    "`MagQSF-v0`: `env.step` with an action of shape (2, 1)": lambda c: c.call(
        lambda: _stepped("MagQSF-v0", np.array([[0.5], [0.5]], np.float32))
    ),
    '`gym.make_vec("magenv/MagBlend-v0", num_envs=0, vectorization_mode="vector_entry_point")`': lambda c: c.call(
        lambda: gym.make_vec("magenv/MagBlend-v0", num_envs=0, vectorization_mode="vector_entry_point")
    ),
    "a vector env's `step` with NaN in one row of `actions`": lambda c: c.call(
        lambda: _vector_step(np.array([[0.5], [np.nan]], np.float32))
    ),
    "a config file holding `!!python/object/apply:os.system`": _yaml_payload,
    "a tuned-parameter JSON cut short": lambda c: _user_tuned(c, '{"params": {"beta": 0.1'),
    "a trial file whose `gyr` holds text": lambda c: c.call(
        lambda: Trial.load(c.trial_file(lambda f: (f.__delitem__("gyr"), f.create_dataset("gyr", data=[b"a", b"b"]))))
    ),
    "a trial file whose `truth/stationary` is one number": lambda c: c.call(
        lambda: Trial.load(
            c.trial_file(lambda f: (f.__delitem__("truth/stationary"), f.create_dataset("truth/stationary", data=1.0)))
        )
    ),
    "a trial file of random bytes": lambda c: c.call(
        lambda: Trial.load(_write_bytes(c.tmp / "trial.h5", np.random.default_rng(0).bytes(4096)))
    ),
    "`magenv train … --steps 128 --eval-every 64` (one rollout of 128 steps)": _one_rollout,
    "the same run continued with `--steps 256`": _continued,
    "`magenv train … --steps 200` killed after its first rollout, then the same command": lambda c: _killed_then_again(
        c, PPO, "train", 2, "--steps", "200", "--eval-every", "128"
    ),
    "Ctrl-C (or SIGTERM) during `magenv train`'s evaluation": _interrupted_evaluation,
    "a second `magenv train … --out RUN` while one trains into `RUN`": _second_run,
    "`magenv train` killed after writing `best.safetensors`, before its state, then the same command": lambda c: (
        _killed_then_again(c, run_folder, "_flush", 7, "--steps", "256", "--eval-every", "128")
    ),
    "resuming from a checkpoint whose `timesteps` is -5000": lambda c: _tampered_checkpoint(
        c, timesteps=-5000, state={"timesteps": -5000, "best_score": 1.0, "best_timesteps": None}
    ),
    "resuming from a `last.safetensors` whose optimizer moments have another shape": lambda c: _tampered_checkpoint(
        c, {"optim/policy.optimizer/0/exp_avg": torch.zeros(3)}
    ),
    "`magenv train` with config `env_kwargs: {bogus: 1}`": lambda c: c.cli(
        *_train_args(c, "--steps", "128", env_kwargs={"scenario": "dynamic_clean", "bogus": 1})
    ),
    "`magenv train … --steps 99999999999999999999`": lambda c: c.cli(
        "train", "--out", c.tmp / "x", "--steps", "99999999999999999999"
    ),
    "a config whose YAML is a 7-level alias bomb": _alias_bomb,
    "a tuned-parameter file with `norm_tol` 1e308 (outside `fan_lambda`'s bounds)": lambda c: _user_tuned(
        c, '{"params": {"norm_tol": 1e308, "th_dip_deg": 10.0}}'
    ),
    "`magenv compare --csv DIR/t.csv` into a folder one cannot write": lambda c: _into_read_only(
        c, "compare", "--seeds", "0", "--no-progress", option="--csv", name="t.csv"
    ),
    "`magenv compare --plot DIR` (an existing folder)": lambda c: c.cli("compare", "--seeds", "0", "--plot", c.tmp),
    "`magenv compare --plot out` (no suffix)": _compare_plot_without_suffix,
    "`magenv evaluate RUN --csv FILE/t.csv` (a path under a file)": lambda c: c.cli(
        "evaluate", fake_run(c.tmp / "run"), "--csv", _under_a_file(c, "t.csv")
    ),
    "`magenv evaluate RUN --video out.gif`": lambda c: c.cli(
        "evaluate", fake_run(c.tmp / "run"), "--video", c.tmp / "out.gif"
    ),
    "`magenv simulate … --out DIR` (an existing folder)": lambda c: c.cli(
        "simulate", "--scenario", "dynamic_clean", "--out", c.tmp
    ),
    "`magenv plot TRIAL --out` into a folder one cannot write": lambda c: _into_read_only(
        c, "plot", c.trial_file(lambda f: None), option="--out", name="trial.png"
    ),
    "`magenv train --out FILE` (an existing file)": lambda c: c.cli("train", "--out", _under_a_file(c, "x").parent),
    "`magenv tune … --out FILE/tuned` (a path under a file)": lambda c: c.cli(
        "tune", "--rule", "fan_lambda", "--out", _under_a_file(c, "tuned")
    ),
    "a recording whose magnetometer is all zero": lambda c: c.call(
        lambda: load_recording(c.recording(imu_mag=np.zeros((100, 3))))
    ),
    "a recording whose accelerometer is all zero": lambda c: c.call(
        lambda: load_recording(c.recording(imu_acc=np.zeros((100, 3))))
    ),
    "a recording whose magnetometer is in nT": lambda c: c.call(
        lambda: load_recording(_broad(c, _scale("imu_mag", 1e3)))
    ),
    "a recording whose gyro is in °/s": lambda c: c.call(
        lambda: load_recording(_broad(c, _scale("imu_gyr", 180 / math.pi)))
    ),
    "a recording whose `sampling_rate` is 10× the true one": lambda c: c.call(
        lambda: load_recording(_broad(c, lambda f: f.attrs.__setitem__("sampling_rate", f.attrs["sampling_rate"] * 10)))
    ),
    "a recording whose field is 15 µT at rest": lambda c: c.warning(
        lambda: load_recording(c.recording(imu_mag=np.tile([0, 5.0, -14.0], (100, 1))))
    ),
    "a recording with a gyro burst of 1e300": lambda c: c.call(lambda: load_recording(_broad(c, _burst))),
    "methods that diverge on a trial (a 1e300 gyro burst: `mimu`, `vqf` …) in `magenv.evaluation.compare`": (_diverged),
    "`Trial(field_norm=0)` (then any env)": lambda c: c.call(_bad_field(field_norm=0)),
    "`Trial(field_norm=nan)`": lambda c: c.call(_bad_field(field_norm=math.nan)),
    "`Trial(field_norm=-40)`": lambda c: c.call(_bad_field(field_norm=-40)),
    "`Trial(field_dip=500)`": lambda c: c.call(_bad_field(field_dip=500)),
    "`trial.field_norm = 0` on a made trial": lambda c: c.call(_set_field(field_norm=0)),
    'a vector env\'s `reset(options={"trail": trial})`': lambda c: c.call(
        _vector_reset(options={"trail": kinematic_trial(duration=1.0)})
    ),
    "a vector env's `reset(seed=True)`": lambda c: c.call(_vector_reset(seed=True)),
    'a vector env\'s `reset(options="abc")`': lambda c: c.call(_vector_reset(options="abc")),
    "a vector env's `reset(seed=1.5)`": lambda c: c.call(_vector_reset(seed=1.5)),
}
ROWS = readme_rows()


def test_every_readme_row_has_a_case():
    assert set(ROWS) == set(CASES), set(ROWS) ^ set(CASES)


@pytest.mark.parametrize("row", list(ROWS), ids=[f"row{i}" for i in range(len(ROWS))])
def test_readme_row(row, tmp_path, capsys):
    outcome, gist = ROWS[row]
    got, text = CASES[row](Case(tmp_path, capsys))
    assert got == outcome, f"{row}: {got} instead of {outcome}: {text[-2000:]}"
    assert gist in text, f"{row}: {gist!r} not in {text[-2000:]!r}"


# ----------------------------------------------------------------- planted pickles


class Payload:
    """Unpickling this creates ``marker``: the stand-in for code an attacker runs."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def plant_zip(path: Path, marker: Path) -> None:
    """An SB3 .zip whose ``lr_schedule`` (cloudpickled in its ``data`` entry) runs the payload."""
    with zipfile.ZipFile(path) as z:
        entries = {name: z.read(name) for name in z.namelist()}
    data = json.loads(entries["data"])
    data["lr_schedule"][":serialized:"] = base64.b64encode(pickle.dumps(Payload(marker))).decode()
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as z:
        for name, blob in entries.items():
            z.writestr(name, blob)


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    """A PPO run folder written by train() (one rollout, one evaluation)."""
    tmp = tmp_path_factory.mktemp("trained")
    return train(
        ENV,
        "ppo",
        128,
        tmp / "run",
        config=write_config(tmp / "cfg.yaml"),
        eval_every=128,
        eval_scenarios=("dynamic_clean",),
        eval_seeds=(0,),
        progress_bar=False,
    )


def test_run_folder_holds_arrays_and_sb3_exports(trained_run):
    names = {p.name for p in trained_run.iterdir()}
    assert {
        "run.yaml",
        "state.json",
        "best.safetensors",
        "last.safetensors",
        "best_model.zip",
        "last_model.zip",
        "checkpoints",
        "evaluations.csv",
    } <= names
    assert not list(trained_run.rglob("*.pkl"))
    assert [p.name for p in (trained_run / "checkpoints").iterdir()] == ["step_128.safetensors"]


def test_planted_pickles_never_run(trained_run, tmp_path, capsys):
    run = Path(shutil.copytree(trained_run, tmp_path / "run"))
    marker = tmp_path / "pwned"
    for name in ("best_model.zip", "last_model.zip"):
        plant_zip(run / name, marker)
    shutil.copy(run / "last_model.zip", run / "checkpoints" / "model_128.zip")
    for name in ("vecnormalize.pkl", "replay_buffer.pkl"):
        (run / name).write_bytes(pickle.dumps(Payload(marker)))
    # the payloads are live: unpickling runs them
    pickle.loads((run / "vecnormalize.pkl").read_bytes())
    assert marker.exists()
    marker.unlink()

    assert load_agent(run).source == str(run / "best.safetensors") and not marker.exists()
    assert cli(["evaluate", str(run), "--scenario", "dynamic_clean", "--seeds", "0", "--no-progress"]) == 0
    assert (
        cli(
            [
                "compare",
                "--agent",
                str(run),
                "--methods",
                "mimu",
                "--scenario",
                "dynamic_clean",
                "--seeds",
                "0",
                "--no-progress",
            ]
        )
        == 0
    )
    assert cli(["train", "--out", str(run), "--steps", "256", "--eval-every", "128", "--no-progress"]) == 0
    assert json.loads((run / "state.json").read_text())["timesteps"] == 256 and not marker.exists()
    capsys.readouterr()

    # without the arrays, only trust_pickle reads the SB3 files, and then the planted code runs
    for p in run.glob("*.safetensors"):
        p.unlink()
    plant_zip(run / "best_model.zip", marker)  # the resume above rewrote the exports
    with pytest.raises(RunError, match="trust_pickle=True"):
        load_agent(run)
    assert not marker.exists()
    try:
        load_agent(run, trust_pickle=True)
    except RunError:
        pass  # the payload replaced a part SB3 needs; it ran all the same
    assert marker.exists()


def as_older_magenv(run: Path) -> Path:
    """``run`` as an older magenv left it: its model in SB3 .zip files only, a state file naming no files."""
    for p in run.glob("*.safetensors"):
        p.unlink()
    state = json.loads((run / "state.json").read_text())
    (run / "state.json").write_text(json.dumps({k: v for k, v in state.items() if k not in ("files", "evaluations")}))
    return run


def test_an_old_run_resumes_from_its_pickles_only_when_trusted(trained_run, tmp_path, capsys):
    run = as_older_magenv(Path(shutil.copytree(trained_run, tmp_path / "run")))
    marker = tmp_path / "pwned"
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(Payload(marker)))
    assert cli(["train", "--out", str(run), "--steps", "256", "--no-progress"]) == 2
    assert "--trust-pickle" in capsys.readouterr().err and not marker.exists()
    cli(["train", "--out", str(run), "--steps", "256", "--no-progress", "--trust-pickle"])
    assert marker.exists()


# ----------------------------------------------------------------- checkpoints round-trip


SMALL = {
    "ppo": {"n_steps": 32, "batch_size": 32, "n_epochs": 1},
    "sac": {"learning_starts": 8, "batch_size": 8, "buffer_size": 200, "train_freq": 4},
    "recurrent_ppo": {
        "n_steps": 16,
        "batch_size": 16,
        "n_epochs": 1,
        "policy_kwargs": {"lstm_hidden_size": 4, "net_arch": [4]},
    },
}


def _model(algo: str):
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from magenv.agents.wrappers import normalized_actions

    section = check_section(
        algo,
        {
            "env_kwargs": {"scenario": "dynamic_clean", "episode_seconds": 1.0},
            "n_envs": 2,
            "normalize_reward": True,
            **SMALL[algo],
        },
        "test",
    )
    run = {"env_id": ENV, "algo": algo, "env_kwargs": section["env_kwargs"], "hyperparams": section}
    env = VecNormalize(
        make_vec_env(ENV, n_envs=2, seed=0, env_kwargs=section["env_kwargs"], wrapper_class=normalized_actions),
        norm_obs=False,
    )
    return build_model(run, env=env, seed=0)


def _optimizer_arrays(model) -> dict:
    return {
        f"{name}/{idx}/{key}": np.asarray(v)
        for name, opt in weights._optimizers(model).items()
        for idx, entry in opt.state_dict()["state"].items()
        for key, v in entry.items()
    }


@pytest.mark.parametrize("algo", ["ppo", "sac", "recurrent_ppo"])
def test_checkpoint_round_trips_what_resuming_needs(algo, tmp_path):
    trained = _model(algo).learn(64)
    state = {"timesteps": trained.num_timesteps, "best_score": 1.5, "best_timesteps": 32, "t0": 0.0}
    weights.save_checkpoint(trained, tmp_path / "last.safetensors", state)
    fresh = _model(algo)
    assert weights.load_checkpoint(fresh, tmp_path / "last.safetensors") == state
    for key, value in trained.policy.state_dict().items():
        np.testing.assert_array_equal(fresh.policy.state_dict()[key], value, err_msg=key)
    before = _optimizer_arrays(trained)
    assert before and before.keys() == _optimizer_arrays(fresh).keys()
    for key, value in before.items():
        np.testing.assert_array_equal(_optimizer_arrays(fresh)[key], value, err_msg=key)
    for name, var in weights._variables(trained).items():
        np.testing.assert_array_equal(weights._variables(fresh)[name].detach(), var.detach())
    for key in ("mean", "var", "count"):
        assert getattr(fresh.get_env().ret_rms, key) == pytest.approx(getattr(trained.get_env().ret_rms, key))
    assert fresh.num_timesteps == trained.num_timesteps
    if algo == "sac":
        weights.save_replay_buffer(trained, tmp_path / "rb.safetensors", trained.num_timesteps)
        weights.load_replay_buffer(fresh, tmp_path / "rb.safetensors")
        a, b = trained.replay_buffer, fresh.replay_buffer
        assert (a.pos, a.full) == (b.pos, b.full) and a.pos > 0
        for key in weights.BUFFER_ARRAYS:
            if getattr(a, key) is not None:
                np.testing.assert_array_equal(getattr(b, key), getattr(a, key), err_msg=key)
    obs = np.zeros((2, *fresh.observation_space.shape), np.float32)
    np.testing.assert_array_equal(
        fresh.predict(obs, deterministic=True)[0], trained.predict(obs, deterministic=True)[0]
    )
    fresh.learn(32, reset_num_timesteps=False)  # the restored optimizer state trains on
    assert fresh.num_timesteps > trained.num_timesteps


def test_a_checkpoint_of_another_model_is_refused(tmp_path):
    weights.save_checkpoint(_model("sac"), tmp_path / "sac.safetensors", {"timesteps": 0})
    with pytest.raises(RunError, match="weights of 'sac', but the run is 'ppo'"):
        weights.load_checkpoint(_model("ppo"), tmp_path / "sac.safetensors")


# ----------------------------------------------------------------- truth and config rules


def test_a_slightly_scaled_truth_scores_as_the_true_one(broad_dir, tmp_path):
    """BROAD trial 29 with its truth scaled by 1.001 loads (normalised) and scores what the file says."""
    from magenv import metrics

    source = broad_dir / "29_disturbed_stationary_magnet_B.hdf5"
    scaled = Path(shutil.copy(source, tmp_path / source.name))
    with h5py.File(scaled, "a") as f:
        f["opt_quat"][...] = f["opt_quat"][()] * 1.001
    with pytest.warns(UserWarning, match="normalised"):
        trial = load_recording(scaled)
    truth = load_recording(source)
    estimate = np.roll(truth.q_true, 200, axis=0)  # any estimate: a delayed truth
    np.testing.assert_allclose(trial.q_true, truth.q_true, atol=1e-12)
    good = metrics.score(estimate, truth.q_true, truth.score_mask).total
    assert good > 1.0 and metrics.score(estimate, trial.q_true, trial.score_mask).total == pytest.approx(good)


def test_trials_in_memory_get_the_same_truth_check():
    trial = kinematic_trial(duration=1.0)
    with pytest.raises(ValueError, match="q_true: truth quaternions must have unit norm"):
        Trial(**{**trial.__dict__, "q_true": trial.q_true * 2})
    with_gap = trial.q_true.copy()
    with_gap[3] = np.nan
    assert np.isnan(Trial(**{**trial.__dict__, "q_true": with_gap}).q_true[3]).all()  # missing truth stays


@pytest.mark.parametrize("algo", ["ppo", "sac", "recurrent_ppo"])
def test_every_constructor_argument_has_a_rule_or_a_reason(algo):
    """A new SB3 argument is noticed here, not passed unchecked (it is refused as unknown until it has a rule)."""
    params = set(inspect.signature(algorithm_class(algo).__init__).parameters) - {"self", "env", "_init_setup_model"}
    assert params - set(VALUE_RULES) - set(NOT_IN_CONFIG) == set()


@pytest.mark.slow
def test_evaluate_records_a_video(trained_run, tmp_path):
    video = tmp_path / "agent.mp4"
    args = ["evaluate", str(trained_run), "--scenario", "dynamic_clean", "--seeds", "0", "--no-progress"]
    assert cli([*args, "--video", str(video)]) == 0
    assert video.stat().st_size > 10_000
    assert cli([*args, "--video", str(tmp_path / "agent.gif")]) == 2


# ----------------------------------------------------------------- filter entry points


def _filter_calls():
    """(call, exception, part of the message) for a bad argument of each filter entry point."""
    from magenv.filters import blend, kalman_model, kalman_threshold, kalman_trust, madgwick, qsf, solvers, stationary

    trial = kinematic_trial(duration=0.5)
    z = np.zeros((10, 3))
    return [
        (lambda: madgwick.run_madgwick(z, z, beta=math.nan), ValueError, "beta must be a finite number in [0, 10]"),
        (lambda: madgwick.run_madgwick(z, z, rate=0), ValueError, "rate must be a finite number > 0"),
        (lambda: madgwick.run_madgwick(z, z[:, :2]), ValueError, "acc must be (N, 3)"),
        (lambda: madgwick.run_madgwick(z, z, q0=[0, 0, 0, 0]), ValueError, "q0 must be 4 finite numbers, not all zero"),
        (lambda: blend.BlendEstimator(lam=math.nan), ValueError, "lam must be a finite number in [0, 1]"),
        (lambda: blend.BlendEstimator(th_gyro_dps=-1), ValueError, "th_gyro_dps must be a finite number ≥ 0"),
        (lambda: stationary.make_state(256.0, t0=1e9), ValueError, "t0 must be a finite number in [0, 60]"),
        (lambda: solvers.make_solver("quest", (0, 0)), ValueError, "weights must be 2 finite numbers, not all zero"),
        (lambda: solvers.make_solver("svd"), ValueError, "solver must be one of"),
        (lambda: kalman_model.ModelKF(c_a_mag=1.0), ValueError, "c_a_mag (a stable Gauss–Markov correlation)"),
        (lambda: kalman_threshold.ThresholdKF(th_acc=-1.0), ValueError, "th_acc must be a number > 0"),
        (lambda: kalman_trust.make_params(46.0, 120.0, 0.01), ValueError, "field_dip must be a finite number in [-90"),
        (lambda: kalman_trust.run_trial(trial, [0.5, 0.5]), ValueError, "trust must be a number in [0, 1] or one per"),
        (lambda: qsf.make_params(46.0, 49.6, acc_adaptive=-1), ValueError, "acc_adaptive must be a finite number ≥ 0"),
        (lambda: qsf.run_trial(trial, trust="x"), ValueError, "trust must be in [0, 1]"),
        (lambda: qsf.run_trial(trial, q0=[np.nan] * 4), ValueError, "q0 must be 4 finite numbers"),
        (lambda: qsf.QSFDetector(window_s=math.inf), ValueError, "QSFDetector.window_s must be a finite number > 0"),
    ]


@pytest.mark.parametrize("i", range(17))
def test_filter_entry_points_name_a_bad_argument(i):
    calls = _filter_calls()
    assert len(calls) == 17
    call, error, message = calls[i]
    with pytest.raises(error) as caught:
        call()
    assert message in str(caught.value)
