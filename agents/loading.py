"""A trained agent's run folder, and loading the agent back as a Policy.

Run folder layout (written by ``magenv train``)::

    runs/NAME/
      run.yaml          env id, env kwargs, algorithm, hyperparameters, seed, steps
      state.json        progress for resume: timesteps done, best held-out score
      best_model.zip    the model with the lowest held-out RMSE so far
      last_model.zip    the model at the end of the latest run or checkpoint
      checkpoints/      periodic snapshots (and SAC's replay buffer)
      evaluations.csv   held-out RMSE at each evaluation
      tb/               TensorBoard logs
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import yaml

from magenv.agents.hyperparams import ConfigError, algorithm_class

RUN_FILE = "run.yaml"


class RunError(ValueError):
    """A run folder is missing, incomplete or corrupt, or does not fit the request."""


def read_run(run_dir: str | Path) -> dict:
    """The ``run.yaml`` of a run folder, checked for the keys that loading needs."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"{run_dir}: no such run folder")
    path = run_dir / RUN_FILE
    if not path.is_file():
        raise RunError(f"{run_dir}: not a magenv run folder (no {RUN_FILE})")
    try:
        run = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RunError(f"{path}: corrupt ({exc})") from None
    missing = [k for k in ("env_id", "algo", "env_kwargs") if not isinstance(run, dict) or k not in run]
    if missing:
        raise RunError(f"{path}: missing key(s) {', '.join(missing)}")
    return run


class AgentPolicy:
    """A trained SB3 agent acting on observations (deterministic actions).

    Follows ``magenv.protocols.Policy``; recurrent agents keep their LSTM
    state between calls until ``reset()``. Agents act in [-1, 1] (see
    ``magenv.agents.wrappers.normalized_actions``); ``action_bounds`` = (low, high)
    of the env's action space maps their actions back.
    """

    def __init__(self, model, env_id: str, env_kwargs: dict, name: str, action_bounds=None):
        self.model = model
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.name = name
        self._bounds = None if action_bounds is None else tuple(np.asarray(b, np.float32) for b in action_bounds)
        self.reset()

    def reset(self) -> None:
        self._state = None
        self._episode_start = np.ones((1,), dtype=bool)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action, self._state = self.model.predict(
            obs, state=self._state, episode_start=self._episode_start, deterministic=True
        )
        self._episode_start = np.zeros((1,), dtype=bool)
        if self._bounds is not None:
            low, high = self._bounds
            action = low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)
        return action


def load_agent(run_dir: str | Path, env_id: str | None = None, which: str = "best") -> AgentPolicy:
    """Load the ``best`` (lowest held-out RMSE) or ``last`` model of a run folder.

    Raises RunError if the folder is missing or corrupt, or if ``env_id`` is
    given and differs from the env the agent was trained on.
    """
    run_dir = Path(run_dir)
    run = read_run(run_dir)
    if env_id is not None and env_id != run["env_id"]:
        raise RunError(f"{run_dir}: agent was trained on {run['env_id']}, cannot act in {env_id}")
    if which not in ("best", "last"):
        raise RunError(f"which must be 'best' or 'last', got {which!r}")
    path = run_dir / f"{which}_model.zip"
    if which == "best" and not path.is_file():
        path = run_dir / "last_model.zip"
    if not path.is_file():
        raise RunError(f"{run_dir}: no trained model ({which}_model.zip) in the run folder")
    try:
        cls = algorithm_class(run["algo"])
    except ConfigError as exc:
        raise RunError(f"{run_dir / RUN_FILE}: {exc}") from None
    try:
        model = cls.load(path, device="cpu")
    except (zipfile.BadZipFile, EOFError, KeyError, ValueError, RuntimeError) as exc:
        raise RunError(f"{path}: corrupt model file ({type(exc).__name__}: {exc})") from None
    bounds = run.get("action_bounds")
    return AgentPolicy(model, run["env_id"], run["env_kwargs"], name=f"agent:{run_dir.name}", action_bounds=bounds)
