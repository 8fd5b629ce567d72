"""The training engine behind ``magenv train``: an SB3 agent trained on a magenv environment into a run folder.

:func:`train` builds the agent from its config (``magenv.agents.hyperparams``),
optionally clones a teacher first (``magenv.agents.imitation``), and learns
with a progress bar, TensorBoard logs (``RUN/tb``), periodic evaluation on
held-out trials with the best model kept, checkpoints, and resume: calling it
again on an existing run folder continues from its last checkpoint up to
``steps`` in all (Ctrl-C or SIGTERM saves a checkpoint first). The run folder
layout is in ``magenv.agents.loading``.
"""

from __future__ import annotations

import csv
import json
import signal
import time
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import yaml
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import magenv  # noqa: F401  (registers the environments)
from magenv.agents.hyperparams import ConfigError, algorithm_class, constructor_kwargs, load_hyperparams
from magenv.agents.imitation import check_teacher, clone, demonstrations
from magenv.agents.loading import RUN_FILE, AgentPolicy, RunError, read_run
from magenv.agents.wrappers import action_bounds, normalized_actions
from magenv.evaluation import run_policy_on_trials
from magenv.scenarios import make_trial
from magenv.seeding import VALIDATION_START

STATE_FILE = "state.json"


class HeldOutEvaluation(BaseCallback):
    """Scores the current agent on fixed held-out trials every ``every`` steps.

    The score is the mean total-orientation RMSE (degrees) over the trials,
    the same figure ``magenv compare`` prints; the model with the lowest score
    is saved as ``best_model.zip``. Checkpoints (``last_model.zip``,
    ``checkpoints/``, ``state.json``) are written at the same cadence, so an
    interrupted run resumes from its last evaluation.
    """

    def __init__(self, run_dir: Path, trials: list, env_id: str, env_kwargs: dict, every: int, state: dict,
                 bounds):
        super().__init__()
        self.bounds = bounds
        self.run_dir, self.trials, self.env_id, self.env_kwargs = run_dir, trials, env_id, env_kwargs
        self.every, self.state = every, state
        self._next = state["timesteps"] + every
        self.last_evaluated = None  # timesteps of the latest evaluation in this process

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.every
            self.evaluate_and_checkpoint()
        return True

    def evaluate_and_checkpoint(self) -> float:
        policy = AgentPolicy(self.model, self.env_id, self.env_kwargs, name="candidate", action_bounds=self.bounds)
        scores = run_policy_on_trials(policy, self.trials, self.env_id, self.env_kwargs)
        score = float(sum(s.total for s in scores) / len(scores))
        self.logger.record("heldout/total_rmse_deg", score)
        self.logger.dump(self.num_timesteps)
        if score < self.state["best_score"]:
            self.state["best_score"] = score
            self.state["best_timesteps"] = self.num_timesteps
            self.model.save(self.run_dir / "best_model.zip")
        with open(self.run_dir / "evaluations.csv", "a", newline="") as f:
            csv.writer(f).writerow([self.num_timesteps, f"{score:.4f}", f"{time.time() - self.state['t0']:.1f}"])
        save_checkpoint(self.model, self.run_dir, self.state, self.num_timesteps)
        self.last_evaluated = self.num_timesteps
        return score


def save_checkpoint(model, run_dir: Path, state: dict, timesteps: int) -> None:
    """Model, SAC replay buffer and progress, written so that a kill at any moment leaves a usable run."""
    state["timesteps"] = int(timesteps)
    ckpt = run_dir / "checkpoints"
    ckpt.mkdir(exist_ok=True)
    model.save(ckpt / f"model_{timesteps}.zip")
    if hasattr(model, "save_replay_buffer"):
        model.save_replay_buffer(run_dir / "replay_buffer.pkl")
    if isinstance(model.get_env(), VecNormalize):
        model.get_env().save(run_dir / "vecnormalize.pkl")
    tmp = run_dir / "last_model.tmp.zip"
    model.save(tmp)
    tmp.replace(run_dir / "last_model.zip")
    (run_dir / (STATE_FILE + ".tmp")).write_text(json.dumps(state, indent=1))
    (run_dir / (STATE_FILE + ".tmp")).replace(run_dir / STATE_FILE)


def pretrain(model, env_id: str, section: dict, teacher, bounds, seed: int) -> float:
    """Behaviour cloning of ``teacher``, the config's ``pretrain`` teacher (``magenv.agents.imitation``);
    returns the final mean squared action error."""
    spec = section["pretrain"]
    obs, actions = demonstrations(env_id, section["env_kwargs"], teacher, int(spec["steps"]), seed, bounds)
    mse = clone(model, obs, actions, spec["epochs"], spec["learning_rate"], spec["batch_size"], seed)
    print(f"pretrain: cloned {spec['teacher']} on {len(obs)} steps, mean squared action error {mse:.4f}")
    return mse


def _teacher(section: dict, env_id: str, make_method: Callable[[str], Any] | None):
    """The config's ``pretrain`` teacher, built by ``make_method`` and checked; None without pretrain."""
    spec = section.get("pretrain")
    if not spec:
        return None
    if make_method is None:
        raise ConfigError("the config has a pretrain teacher but train() got no make_method to build it")
    try:
        teacher = make_method(spec["teacher"])
    except ValueError as exc:
        raise ConfigError(f"pretrain.teacher: {exc}") from None
    return check_teacher(teacher, spec["teacher"], env_id, section["env_kwargs"])


def held_out_trials(scenarios: list[str], seeds: list[int]) -> list:
    """The fixed evaluation trials: every scenario × every seed (seeds below the training range)."""
    return [make_trial(s, seed) for s in scenarios for seed in seeds]


def train(
    env_id: str, algo: str, steps: int | None, out: Path, config: str | None = None, seed: int = 0,
    eval_every: int = 10_000, eval_scenarios: tuple[str, ...] = ("dynamic_magnet", "dynamic_clean"),
    eval_seeds: tuple[int, ...] = (VALIDATION_START, VALIDATION_START + 1), n_envs: int | None = None,
    progress_bar: bool = True, make_method: Callable[[str], Any] | None = None,
) -> Path:
    """Train (or resume) a run; returns the run folder. See the module docstring.

    ``make_method(name)`` builds a method from its name (``magenv.registry.make``); it is needed only
    when the config has a ``pretrain`` teacher, which it builds.
    """
    out = Path(out)
    if (out / RUN_FILE).is_file() and (out / STATE_FILE).is_file():  # else: a run that never reached its start
        run = read_run(out)
        if (run["env_id"], run["algo"]) != (env_id, algo):
            raise RunError(f"{out}: existing run is {run['algo']} on {run['env_id']}; "
                           f"use another --out for {algo} on {env_id}")
        state = json.loads((out / STATE_FILE).read_text())
        section = run["hyperparams"]
        steps = steps or run["steps"]
        seed = run["seed"]
    else:
        section = load_hyperparams(algo, env_id, config)
        if n_envs:
            section["n_envs"] = n_envs
        teacher = _teacher(section, env_id, make_method)  # a bad teacher fails before the run folder is written
        steps = steps or int(section.get("n_timesteps", 100_000))
        run = {
            "env_id": env_id, "algo": algo, "env_kwargs": section["env_kwargs"], "hyperparams": section,
            "action_bounds": action_bounds(env_id, section["env_kwargs"]),
            "seed": seed, "steps": steps, "eval_scenarios": list(eval_scenarios), "eval_seeds": list(eval_seeds),
            "magenv_version": magenv.__version__,
        }
        out.mkdir(parents=True, exist_ok=True)
        state = {"timesteps": 0, "best_score": float("inf"), "best_timesteps": None, "t0": time.time()}
    run["steps"] = steps
    (out / RUN_FILE).write_text(yaml.safe_dump(run, sort_keys=False))

    vec_env = make_vec_env(env_id, n_envs=section["n_envs"], seed=seed + state["timesteps"],
                           env_kwargs=section["env_kwargs"], wrapper_class=normalized_actions)
    if section.get("normalize_reward"):
        # Reward scale differs by orders of magnitude between scenarios (0.5° clean, 20° in a bad
        # random trial); learning sees rewards divided by a running std of the return. Scores and
        # the env's own rewards are unchanged.
        stats = out / "vecnormalize.pkl"
        vec_env = (VecNormalize.load(stats, vec_env) if state["timesteps"] > 0 and stats.is_file()
                   else VecNormalize(vec_env, norm_obs=False, norm_reward=True, gamma=section.get("gamma", 0.99)))
    cls = algorithm_class(algo)
    if state["timesteps"] > 0 and (out / "last_model.zip").is_file():
        model = cls.load(out / "last_model.zip", env=vec_env, device="cpu", tensorboard_log=str(out / "tb"))
        if (out / "replay_buffer.pkl").is_file() and hasattr(model, "load_replay_buffer"):
            model.load_replay_buffer(out / "replay_buffer.pkl")
    else:
        state["timesteps"] = 0
        model = cls(env=vec_env, seed=seed, device="cpu", tensorboard_log=str(out / "tb"),
                    **constructor_kwargs(section))
        if section.get("pretrain"):
            teacher = _teacher(section, env_id, make_method)
            state["pretrain_mse"] = pretrain(model, env_id, section, teacher, run["action_bounds"], seed)
    remaining = steps - state["timesteps"]
    if remaining <= 0:
        print(f"{out}: already trained for {state['timesteps']} of {steps} steps")
        return out

    trials = held_out_trials(run["eval_scenarios"], run["eval_seeds"])
    evaluation = HeldOutEvaluation(out, trials, env_id, section["env_kwargs"], eval_every, state, run["action_bounds"])

    def _stop(signum, frame):  # SIGTERM behaves like Ctrl-C: checkpoint, then exit
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _stop)
    try:
        model.learn(remaining, callback=CallbackList([evaluation]), progress_bar=progress_bar,
                    reset_num_timesteps=state["timesteps"] == 0, tb_log_name=algo)
        if evaluation.last_evaluated != model.num_timesteps:
            evaluation.evaluate_and_checkpoint()
    except KeyboardInterrupt:
        save_checkpoint(model, out, state, model.num_timesteps)
        print(f"\ninterrupted at {model.num_timesteps} steps; run the same command again to resume")
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        vec_env.close()
    return out


