"""A trained agent's run folder, and loading the agent back as a Policy — without unpickling anything.

Run folder layout (written by ``magenv train``)::

    runs/NAME/
      run.yaml             env id, env kwargs, algorithm, hyperparameters, seed, steps: what rebuilds the agent
      state.json           the committed state, written last: progress (timesteps, evaluations, best held-out
                           score) and every file of the run with its SHA-256 (magenv.agents.run_folder)
      .lock                held while a run writes to the folder
      best.safetensors     policy weights with the lowest held-out RMSE so far
      last.safetensors     the latest checkpoint: weights, optimizer state, reward statistics, progress
      replay_buffer.safetensors   SAC's replay buffer at the latest checkpoint
      checkpoints/         policy weights at each evaluation (step_T.safetensors)
      best_model.zip, last_model.zip   the same models as SB3 files, for SB3 users (never read by default)
      evaluations.csv      held-out RMSE at each evaluation
      tb/                  TensorBoard logs

A DAgger run folder (``magenv train --teacher oracle``, ``magenv.agents.dagger``) has
``run.yaml`` (algo ``dagger``) and ``best.safetensors``; ``load_agent`` loads it the same way.
``pretrained:ENV_ID`` names the agent shipped with magenv for that env (:func:`pretrained_agents`).

Loading reads YAML (``yaml.SafeLoader``, ``magenv.checks.check_yaml``), JSON and safetensors arrays only
(``magenv.agents.weights``): the policy is rebuilt from ``run.yaml`` and the
weights are loaded into it, so a run folder from someone else cannot run
code. SB3's ``.zip`` files (and ``.pkl`` files of older run folders) hold
pickles, which can; they are read only with ``trust_pickle=True``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from magenv.agents.hyperparams import SEED_RANGE, ConfigError, algorithm_class, check_section, constructor_kwargs
from magenv.agents.weights import RunError, load_policy
from magenv.checks import check_yaml

if TYPE_CHECKING:  # a run folder of either kind; dagger imports this module
    from magenv.agents.dagger import StudentPolicy

RUN_FILE = "run.yaml"
PRETRAINED_PREFIX = "pretrained:"
WEIGHTS = {"best": "best.safetensors", "last": "last.safetensors"}
NO_ENV = "a loaded agent acts on observations; it has no env of its own to step"
#: Observations per forward of an agent's network (``AgentPolicy.act_batch``). BLAS rounds a product by its
#: shape, and within one shape each row's result depends on that row alone: one fixed shape makes an env's
#: actions independent of the other envs acting with it (``tests/test_evaluation_batch.py``).
FORWARD_ROWS = 32
SB3_EXPORTS = {"best": "best_model.zip", "last": "last_model.zip"}

__all__ = [
    "RUN_FILE",
    "AgentPolicy",
    "RunError",
    "build_model",
    "load_agent",
    "load_weights_file",
    "pretrained_agents",
    "read_run",
]


def pretrained_agents() -> dict[str, Path]:
    """Env id → run folder of the agents shipped in the package (``magenv/agents/pretrained/ENV``)."""
    root = Path(str(resources.files("magenv.agents") / "pretrained"))
    found = sorted(p for p in root.iterdir() if (p / RUN_FILE).is_file()) if root.is_dir() else []
    return {f"magenv/{p.name}": p for p in found}


def _resolve(run_dir: str | Path) -> Path:
    """A run folder, or the shipped one for ``pretrained:ENV_ID`` (RunError naming the ones there are)."""
    text = str(run_dir)
    if not text.startswith(PRETRAINED_PREFIX):
        return Path(run_dir)
    env_id = text[len(PRETRAINED_PREFIX) :]
    shipped = pretrained_agents()
    if env_id not in shipped:
        raise RunError(f"no pretrained agent for {env_id!r}; shipped: {', '.join(shipped) or 'none'}")
    return shipped[env_id]


def read_run(run_dir: str | Path) -> dict:
    """The ``run.yaml`` of a run folder, checked: the keys loading needs, the hyperparameters value by value
    (``magenv.agents.hyperparams.check_section``). Raises RunError naming the file and the problem."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"{run_dir}: no such run folder")
    path = run_dir / RUN_FILE
    if not path.is_file():
        raise RunError(f"{run_dir}: not a magenv run folder (no {RUN_FILE})")
    try:
        run = check_yaml(path.read_text(), str(path))
    except (ValueError, UnicodeDecodeError) as exc:
        raise RunError(f"{path}: corrupt ({exc})") from None
    missing = [k for k in ("env_id", "algo", "env_kwargs", "hyperparams") if not isinstance(run, dict) or k not in run]
    if missing:
        raise RunError(f"{path}: missing key(s) {', '.join(missing)}")
    if not isinstance(run["env_id"], str) or not isinstance(run["env_kwargs"], dict):
        raise RunError(f"{path}: env_id must be a name and env_kwargs a mapping")
    seed = run.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or not SEED_RANGE[0] <= seed <= SEED_RANGE[1]:
        raise RunError(f"{path}: seed must be an integer from {SEED_RANGE[0]} to {SEED_RANGE[1]}, got {seed!r}")
    bounds = run.get("action_bounds")
    if bounds is not None:
        try:
            low, high = (np.asarray(b, dtype=float) for b in bounds)
            ok = (
                low.shape == high.shape
                and low.ndim == 1
                and np.all(np.isfinite(low) & np.isfinite(high) & (low < high))
            )
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise RunError(
                f"{path}: action_bounds must be [low, high], two equal-length lists of finite numbers "
                f"with low < high, got {bounds!r}"
            )
    try:
        run["hyperparams"] = check_section(run["algo"], run["hyperparams"], f"{path}: hyperparams")
    except ConfigError as exc:
        raise RunError(str(exc)) from None
    return run


class AgentPolicy:
    """A trained SB3 agent acting on observations (deterministic actions).

    Follows ``magenv.protocols.BatchPolicy``: ``act_batch`` acts for n envs in one forward of the network per
    ``FORWARD_ROWS`` envs (each env's LSTM state in ``state`` for a recurrent agent), ``policy(obs)`` for one
    env, keeping its LSTM state between calls until ``reset()``. Agents act in [-1, 1] (see
    ``magenv.agents.wrappers.normalized_actions``); ``action_bounds`` = (low, high)
    of the env's action space maps their actions back. ``source`` is the file
    the weights came from, ``which`` the model (``best`` or ``last``).
    """

    def __init__(
        self, model, env_id: str, env_kwargs: dict, name: str, action_bounds=None, source: str = "", which: str = ""
    ):
        self.model = model
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.name = name
        self.source, self.which = source, which
        self._bounds = None if action_bounds is None else tuple(np.asarray(b, np.float32) for b in action_bounds)
        self.reset()

    def reset(self) -> None:
        self._state: tuple | None = None

    def act_batch(self, obs: np.ndarray, state=None) -> tuple[np.ndarray, tuple]:
        """(actions (n, d), state) for observations (n, …) of n envs; ``state`` None at every env's first
        observation, else the state the previous call returned (the LSTM states of a recurrent agent). The
        network acts on blocks of ``FORWARD_ROWS`` observations (the last padded), so an env's actions are the
        same bit for bit whichever and however many envs act with it."""
        obs = np.asarray(obs)
        n = len(obs)
        blocks = -(-n // FORWARD_ROWS)
        padded = np.zeros((blocks * FORWARD_ROWS, *obs.shape[1:]), obs.dtype)
        padded[:n] = obs
        memories, start = ([None] * blocks, np.ones(len(padded), bool)) if state is None else state
        actions, after = [], []
        for b, memory in enumerate(memories):
            rows = slice(b * FORWARD_ROWS, (b + 1) * FORWARD_ROWS)
            action, memory = self.model.predict(
                padded[rows], state=memory, episode_start=start[rows], deterministic=True
            )
            actions.append(action)
            after.append(memory)
        action = np.concatenate(actions)[:n]
        if self._bounds is not None:
            low, high = self._bounds
            action = low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)
        return action, (after, np.zeros(len(padded), bool))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action, self._state = self.act_batch(np.asarray(obs)[None], self._state)
        return action[0]


def _spaces_env(env_id: str, env_kwargs: dict, n_envs: int):
    """A vector env with the spaces of ``env_id`` (actions in [-1, 1], as in training) that cannot step:
    enough to build an agent that only acts."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    import magenv  # noqa: F401  (registers the environments)
    from magenv.agents.wrappers import normalized_actions

    env = normalized_actions(gym.make(env_id, disable_env_checker=True, **env_kwargs))
    spaces = env.observation_space, env.action_space
    env.close()

    class Spaces(gym.Env):
        observation_space, action_space = spaces

        def reset(self, *, seed=None, options=None):
            raise RuntimeError(NO_ENV)

        def step(self, action):
            raise RuntimeError(NO_ENV)

    return DummyVecEnv([Spaces] * n_envs)


def build_model(run: dict, env=None, where: str = "", **extra):
    """The SB3 agent that ``run`` (a checked run.yaml) describes, untrained: on ``env`` (a vector env),
    else on a stand-in with the env's spaces; ``extra`` goes to the constructor (seed, tensorboard_log).
    The algorithm's own refusals are RunErrors naming ``where``."""
    cls = algorithm_class(run["algo"])
    section = run["hyperparams"]
    if env is None:
        try:
            env = _spaces_env(run["env_id"], run["env_kwargs"], section["n_envs"])
        except Exception as exc:  # the env's own checks of env_kwargs, or an unknown env id
            raise RunError(
                f"{where}: cannot make env {run['env_id']} with {run['env_kwargs']} ({type(exc).__name__}: {exc})"
            ) from None
    try:
        return cls(env=env, device="cpu", **constructor_kwargs(section), **extra)
    except (AssertionError, ValueError, TypeError, KeyError) as exc:
        raise RunError(f"{where}: {run['algo']} refuses the hyperparameters ({type(exc).__name__}: {exc})") from None


def load_agent(
    run_dir: str | Path, env_id: str | None = None, which: str = "best", trust_pickle: bool = False
) -> AgentPolicy | StudentPolicy:
    """Load the ``best`` (lowest held-out RMSE) or ``last`` model of a run folder.

    ``best`` falls back to ``last`` when the run has not been evaluated yet
    (``AgentPolicy.which`` says which was loaded). Only arrays are read; a
    folder holding only SB3 ``.zip`` models (an older magenv, or SB3 itself)
    needs ``trust_pickle=True``, which unpickles them — only for folders
    whose author you trust.

    Raises RunError if the folder is missing, corrupt or pickle-only, or if
    ``env_id`` is given and differs from the env the agent was trained on.
    """
    from magenv.agents import dagger

    name = f"agent:{run_dir}" if str(run_dir).startswith(PRETRAINED_PREFIX) else None
    run_dir = _resolve(run_dir)
    if dagger.is_run(run_dir):
        policy = dagger.load_policy(run_dir, name)
        if env_id is not None and env_id != policy.env_id:
            raise RunError(f"{run_dir}: agent was trained on {policy.env_id}, cannot act in {env_id}")
        return policy
    run = read_run(run_dir)
    if env_id is not None and env_id != run["env_id"]:
        raise RunError(f"{run_dir}: agent was trained on {run['env_id']}, cannot act in {env_id}")
    if which not in WEIGHTS:
        raise RunError(f"which must be 'best' or 'last', got {which!r}")
    order = [which, "last"] if which == "best" else [which]
    found = next((w for w in order if (run_dir / WEIGHTS[w]).is_file()), None)
    if found is not None:
        path = run_dir / WEIGHTS[found]
        model = build_model(run, where=str(run_dir / RUN_FILE))
        load_policy(model, path)
    else:
        found = next((w for w in order if (run_dir / SB3_EXPORTS[w]).is_file()), None)
        if found is None:
            raise RunError(f"{run_dir}: no trained model ({WEIGHTS[which]}) in the run folder")
        path = run_dir / SB3_EXPORTS[found]
        if not trust_pickle:
            raise RunError(
                f"{run_dir}: holds its model only as an SB3 file ({path.name}), which carries pickled "
                "Python objects that can run code when loaded; if you trust whoever wrote the folder, "
                "load it with trust_pickle=True (--trust-pickle)"
            )
        try:
            model = algorithm_class(run["algo"]).load(path, device="cpu")
        except Exception as exc:  # anything the unpickled file raises
            raise RunError(f"{path}: corrupt model file ({type(exc).__name__}: {exc})") from None
    return AgentPolicy(
        model,
        run["env_id"],
        run["env_kwargs"],
        name=name or f"agent:{run_dir.name}",
        action_bounds=run.get("action_bounds"),
        source=str(path),
        which=found,
    )


def load_weights_file(path: str | Path) -> AgentPolicy:
    """An SB3 agent from one weights-only file of a run folder (``best.safetensors``, ``last.safetensors`` or
    ``checkpoints/step_T.safetensors``), rebuilt from its folder's ``run.yaml`` (the file's folder, or the one
    above ``checkpoints/``). RunError naming the file if it is not a ``.safetensors`` file of an SB3 run folder."""
    path = Path(path)
    if path.suffix != ".safetensors" or not path.is_file():
        raise RunError(f"{path}: not a .safetensors weights file")
    run_dir = path.parent.parent if path.parent.name == "checkpoints" else path.parent
    run = read_run(run_dir)  # a DAgger run's run.yaml has no SB3 hyperparameters: RunError here
    model = build_model(run, where=str(run_dir / RUN_FILE))
    load_policy(model, path)
    return AgentPolicy(
        model,
        run["env_id"],
        run["env_kwargs"],
        name=f"agent:{run_dir.name}/{path.stem}",
        action_bounds=run.get("action_bounds"),
        source=str(path),
        which=path.stem,
    )
