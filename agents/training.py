"""The training engine behind ``magenv train``: an SB3 agent trained on a magenv environment into a run folder.

:func:`train` builds the agent from its config (``magenv.agents.hyperparams``),
optionally clones a teacher first (``magenv.agents.imitation``), and learns
with a progress bar, TensorBoard logs (``RUN/tb``), periodic evaluation on
held-out trials with the best model kept, checkpoints, and resume: calling it
again on an existing run folder continues from its last checkpoint up to
``steps`` in all (Ctrl-C or SIGTERM saves a checkpoint first). Resuming
rebuilds the agent from ``run.yaml`` and loads arrays only
(``magenv.agents.weights``); it refuses a config, seed or evaluation set
other than the run's unless ``force``. The run folder layout is in
``magenv.agents.loading``.
"""

from __future__ import annotations

import csv
import inspect
import json
import math
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.vec_env import VecNormalize

import magenv
from magenv.agents import weights
from magenv.agents.hyperparams import (
    DEFAULT_EVAL_EVERY,
    DEFAULT_EVAL_SCENARIOS,
    DEFAULT_EVAL_SEEDS,
    DEFAULT_SEED,
    POSITIVE_INT,
    RUN_RULES,
    SEED_RULE,
    ConfigError,
    algorithm_class,
    check_value,
    integer,
    load_hyperparams,
)
from magenv.agents.imitation import check_teacher, clone, demonstrations
from magenv.agents.loading import RUN_FILE, SB3_EXPORTS, WEIGHTS, AgentPolicy, RunError, build_model, read_run
from magenv.agents.vec_env import make_train_env
from magenv.agents.wrappers import action_bounds
from magenv.evaluation import run_policy_on_trials
from magenv.scenarios import make_trial, scenario_names

#: Torch threads while an agent trains. The 64×64 networks are too small to share between threads: on the
#: loaded 2-core machine PPO on 128 batched envs ran 4.1 k env-steps/s with 2 threads, 20 k with 1.
TORCH_THREADS = 1

STATE_FILE = "state.json"
REPLAY_FILE = "replay_buffer.safetensors"
#: What older run folders (magenv 0.1) kept as pickles: read only with ``trust_pickle``.
LEGACY_VECNORMALIZE, LEGACY_REPLAY = "vecnormalize.pkl", "replay_buffer.pkl"


class HeldOutEvaluation(BaseCallback):
    """Scores the current agent on fixed held-out trials every ``every`` steps.

    The score is the mean total-orientation RMSE (degrees) over the trials,
    the same figure ``magenv compare`` prints; the model with the lowest score
    is saved as ``best.safetensors`` (and ``best_model.zip``). Checkpoints
    (``last.safetensors``, ``checkpoints/``, ``state.json``) are written at the
    same cadence, so an interrupted run resumes from its last evaluation.
    """

    def __init__(self, run_dir: Path, trials: list, env_id: str, env_kwargs: dict, every: int, state: dict, bounds):
        super().__init__()
        self.bounds = bounds
        self.run_dir, self.trials, self.env_id, self.env_kwargs = run_dir, trials, env_id, env_kwargs
        self.every, self.state = every, state
        self._next = state["timesteps"] + every
        self.last_evaluated: int | None = None  # timesteps of the latest evaluation in this process

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next = self.num_timesteps + self.every
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
            weights.save_policy(self.model, self.run_dir / WEIGHTS["best"], self.num_timesteps)
            self.model.save(self.run_dir / SB3_EXPORTS["best"])
        with open(self.run_dir / "evaluations.csv", "a", newline="") as f:
            csv.writer(f).writerow([self.num_timesteps, f"{score:.4f}", f"{time.time() - self.state['t0']:.1f}"])
        save_checkpoint(self.model, self.run_dir, self.state, self.num_timesteps)
        self.last_evaluated = self.num_timesteps
        return score


def save_checkpoint(model, run_dir: Path, state: dict, timesteps: int) -> None:
    """Weights, optimizer state, reward statistics, SAC's replay buffer and progress, as arrays and JSON
    (``magenv.agents.weights``), each file replaced atomically, so a kill at any moment leaves a usable run;
    plus the SB3 export ``last_model.zip``."""
    state["timesteps"] = int(timesteps)
    ckpt = run_dir / "checkpoints"
    ckpt.mkdir(exist_ok=True)
    weights.save_policy(model, ckpt / f"step_{timesteps}.safetensors", timesteps)
    if getattr(model, "replay_buffer", None) is not None:
        weights.save_replay_buffer(model, run_dir / REPLAY_FILE, timesteps)
    weights.save_checkpoint(model, run_dir / WEIGHTS["last"], state)
    tmp = run_dir / "last_model.tmp.zip"
    model.save(tmp)
    tmp.replace(run_dir / SB3_EXPORTS["last"])
    (run_dir / (STATE_FILE + ".tmp")).write_text(json.dumps(state, indent=1))
    (run_dir / (STATE_FILE + ".tmp")).replace(run_dir / STATE_FILE)


def progress(run_dir: Path, algo: str) -> dict | None:
    """The progress record (``timesteps``, ``best_score`` …) a resume of ``run_dir`` continues from: that of
    its latest checkpoint (``last.safetensors``; ``state.json`` is written after it, so a kill between the two
    leaves it one checkpoint behind), else ``state.json`` (runs from before checkpoints carried it); None for
    a run with neither. RunError naming a corrupt file."""
    checkpoint = run_dir / WEIGHTS["last"]
    if checkpoint.is_file():
        state = weights.read(checkpoint, algo)[1].get("state")
        if not isinstance(state, dict) or not isinstance(state.get("timesteps"), int):
            raise RunError(f"{checkpoint}: no progress record in the checkpoint")
        return state
    if not (run_dir / STATE_FILE).is_file():
        return None
    try:
        state = json.loads((run_dir / STATE_FILE).read_text())
        state["timesteps"] = int(state["timesteps"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RunError(f"{run_dir / STATE_FILE}: corrupt ({type(exc).__name__}: {exc})") from None
    return state


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


def _check_eval_set(scenarios, seeds) -> tuple[list[str] | None, list[int] | None]:
    """The evaluation scenarios (known names) and seeds (integers ≥ 0) as lists; None stays None."""
    for what, value in (("eval_scenarios", scenarios), ("eval_seeds", seeds)):
        if value is not None and not isinstance(value, (list, tuple)):
            raise ConfigError(f"{what} must be a list, got {value!r}")
    if scenarios is not None:
        scenarios = [s.strip() for s in map(str, scenarios) if s.strip()]
        bad = [s for s in scenarios if s not in scenario_names()]
        if not scenarios or bad:
            raise ConfigError(
                f"eval_scenarios: unknown scenario(s) {', '.join(bad) or '(none given)'}; "
                f"known: {', '.join(scenario_names())}"
            )
    if seeds is not None:
        seeds = [check_value("train", "eval_seeds entry", s, integer(0)) for s in seeds]
        if not seeds:
            raise ConfigError("eval_seeds: needs at least one seed")
    return scenarios, seeds


def _differences(run: dict, requested: dict) -> list[str]:
    """What ``requested`` (run.yaml keys: hyperparams, seed, eval_scenarios, eval_seeds) changes in ``run``;
    a hyperparameter one side leaves unset shows the algorithm's default."""
    defaults = {k: p.default for k, p in inspect.signature(algorithm_class(run["algo"]).__init__).parameters.items()}

    def show(d: dict, k: str) -> str:
        return repr(d[k]) if k in d else f"(default {defaults.get(k)!r})"

    out = []
    for key, new in requested.items():
        old = run.get(key)
        if key == "hyperparams":
            old = old or {}
            out += [
                f"{k} {show(old, k)} → {show(new, k)}"
                for k in dict.fromkeys([*old, *new])
                if old.get(k, defaults.get(k)) != new.get(k, defaults.get(k))
            ]
        elif old != new:
            out.append(f"{key} {old!r} → {new!r}")
    return out


def rollout_unit(model) -> tuple[int, str]:
    """(steps, why): the algorithm trains in whole multiples of ``steps`` environment steps."""
    n_envs = model.n_envs
    if hasattr(model, "n_steps") and not hasattr(model, "train_freq"):  # on-policy: whole rollouts
        return model.n_steps * n_envs, f"rollouts of n_steps {model.n_steps} × {n_envs} env(s)"
    freq = model.train_freq
    if getattr(freq.unit, "value", freq.unit) == "step":
        return freq.frequency * n_envs, f"train_freq {freq.frequency} × {n_envs} env(s)"
    return n_envs, f"{n_envs} env(s) per step"


def _legacy_model(out: Path, cls, vec_env, section: dict):
    """(model, vec_env) from an older run folder's pickles (``last_model.zip``, ``vecnormalize.pkl``,
    ``replay_buffer.pkl``): unpickling runs code, so only with ``trust_pickle``."""
    stats = out / LEGACY_VECNORMALIZE
    try:
        if section.get("normalize_reward"):
            vec_env = (
                VecNormalize.load(str(stats), vec_env)
                if stats.is_file()
                else VecNormalize(vec_env, norm_obs=False, norm_reward=True, gamma=section.get("gamma", 0.99))
            )
        model = cls.load(out / SB3_EXPORTS["last"], env=vec_env, device="cpu", tensorboard_log=str(out / "tb"))
        if (out / LEGACY_REPLAY).is_file() and hasattr(model, "load_replay_buffer"):
            model.load_replay_buffer(out / LEGACY_REPLAY)
    except Exception as exc:  # anything the unpickled files raise
        raise RunError(f"{out}: cannot resume from its pickles ({type(exc).__name__}: {exc})") from None
    return model, vec_env


def train(
    env_id: str,
    algo: str,
    steps: int | None,
    out: Path,
    config: str | None = None,
    seed: int | None = None,
    eval_every: int = DEFAULT_EVAL_EVERY,
    eval_scenarios: Sequence[str] | None = None,
    eval_seeds: Sequence[int] | None = None,
    n_envs: int | None = None,
    progress_bar: bool = True,
    make_method: Callable[[str], Any] | None = None,
    force: bool = False,
    trust_pickle: bool = False,
) -> Path:
    """Train (or resume) a run; returns the run folder. See the module docstring.

    ``steps`` is the total (default: the config's ``n_timesteps``, or the run's
    when resuming); it is rounded up to the algorithm's whole rollouts, and
    the rounding printed. ``config``, ``seed``, ``n_envs``, ``eval_scenarios``
    and ``eval_seeds`` left None mean the run's own when resuming, else the
    shipped config, 0, the config's, ``DEFAULT_EVAL_SCENARIOS`` ×
    ``DEFAULT_EVAL_SEEDS``; given and different from a resumed run's, they are
    a RunError naming each difference, unless ``force`` (then the run
    continues with them). ``trust_pickle`` lets an older run folder resume
    from its pickles. ``make_method(name)`` builds a method from its name
    (``magenv.registry.make``); it is needed only when the config has a
    ``pretrain`` teacher, which it builds.
    """
    out = Path(out)
    steps = None if steps is None else check_value("train", "steps", steps, POSITIVE_INT)
    eval_every = check_value("train", "eval_every", eval_every, POSITIVE_INT)
    seed = None if seed is None else check_value("train", "seed", seed, SEED_RULE)
    n_envs = None if n_envs is None else check_value("train", "n_envs", n_envs, RUN_RULES["n_envs"])
    eval_scenarios, eval_seeds = _check_eval_set(eval_scenarios, eval_seeds)
    cls = algorithm_class(algo)
    checkpoint = out / WEIGHTS["last"]
    legacy = not checkpoint.is_file() and (out / SB3_EXPORTS["last"]).is_file()
    resuming = (out / RUN_FILE).is_file() and (checkpoint.is_file() or (out / STATE_FILE).is_file())
    if resuming:
        run = read_run(out)
        if (run["env_id"], run["algo"]) != (env_id, algo):
            raise RunError(
                f"{out}: existing run is {run['algo']} on {run['env_id']}; use another --out for {algo} on {env_id}"
            )
        try:
            run["steps"] = check_value("run.yaml", "steps", run.get("steps"), POSITIVE_INT)
            run["eval_scenarios"], run["eval_seeds"] = _check_eval_set(
                run.get("eval_scenarios", []), run.get("eval_seeds", [])
            )
        except ConfigError as exc:
            raise RunError(f"{out / RUN_FILE}: {exc}") from None
        requested: dict[str, Any] = {}
        if config is not None or n_envs is not None:
            section = load_hyperparams(algo, env_id, config) if config is not None else dict(run["hyperparams"])
            requested["hyperparams"] = {**section, "n_envs": n_envs or section["n_envs"]}
        for key, value in (("seed", seed), ("eval_scenarios", eval_scenarios), ("eval_seeds", eval_seeds)):
            if value is not None:
                requested[key] = value
        changes = _differences(run, requested)
        if changes and not force:
            raise RunError(
                f"{out}: the run was trained with other values: {'; '.join(changes)}. "
                "Use another --out for a new run, or --force to continue this one with the new values"
            )
        if changes:
            print(f"{out}: continuing with {'; '.join(changes)} (--force)")
            run.update(requested)
            run["env_kwargs"] = run["hyperparams"]["env_kwargs"]
        if not checkpoint.is_file() and not (legacy and trust_pickle):
            raise RunError(
                f"{out}: no checkpoint to resume from ({WEIGHTS['last']})"
                + (
                    f"; the folder holds an older magenv's pickles ({SB3_EXPORTS['last']}), which can run code when "
                    "loaded: resume from them with --trust-pickle (trust_pickle=True) only if you trust whoever "
                    "wrote it"
                    if legacy
                    else "; remove the folder or use another --out"
                )
            )
        section = run["hyperparams"]
    else:
        section = load_hyperparams(algo, env_id, config)
        if n_envs:
            section["n_envs"] = n_envs
        _teacher(section, env_id, make_method)  # a bad teacher fails before the run folder is written
        run = {
            "env_id": env_id,
            "algo": algo,
            "env_kwargs": section["env_kwargs"],
            "hyperparams": section,
            "action_bounds": action_bounds(env_id, section["env_kwargs"]),
            "seed": DEFAULT_SEED if seed is None else seed,
            "steps": int(section.get("n_timesteps", 100_000)),
            "eval_scenarios": eval_scenarios or list(DEFAULT_EVAL_SCENARIOS),
            "eval_seeds": eval_seeds or list(DEFAULT_EVAL_SEEDS),
            "magenv_version": magenv.__version__,
        }
        out.mkdir(parents=True, exist_ok=True)
    run["steps"] = steps = steps or run["steps"]
    seed = run["seed"]
    state = progress(out, algo) if resuming else None
    if state is None:
        state = {"timesteps": 0, "best_score": float("inf"), "best_timesteps": None, "t0": time.time()}
    done = state["timesteps"]
    if done >= steps:
        print(f"{out}: already trained for {done:,} steps (asked {steps:,})")
        return out
    (out / RUN_FILE).write_text(yaml.safe_dump(run, sort_keys=False))

    torch.set_num_threads(TORCH_THREADS)
    vec_env = make_train_env(env_id, section["n_envs"], seed + done, section["env_kwargs"])
    if resuming and legacy:
        model, vec_env = _legacy_model(out, cls, vec_env, section)
    else:
        if section.get("normalize_reward"):
            # Reward scale differs by orders of magnitude between scenarios (0.5° clean, 20° in a bad
            # random trial); learning sees rewards divided by a running std of the return. Scores and
            # the env's own rewards are unchanged.
            vec_env = VecNormalize(vec_env, norm_obs=False, norm_reward=True, gamma=section.get("gamma", 0.99))
        model = build_model(run, env=vec_env, where=str(out / RUN_FILE), seed=seed, tensorboard_log=str(out / "tb"))
        if resuming:
            state = weights.load_checkpoint(model, checkpoint)
            if getattr(model, "replay_buffer", None) is not None and (out / REPLAY_FILE).is_file():
                weights.load_replay_buffer(model, out / REPLAY_FILE)
        elif section.get("pretrain"):
            teacher = _teacher(section, env_id, make_method)
            state["pretrain_mse"] = pretrain(model, env_id, section, teacher, run["action_bounds"], seed)
    unit, why = rollout_unit(model)
    remaining = math.ceil((steps - done) / unit) * unit
    if remaining != steps - done:
        print(
            f"{algo} trains in whole {why} = {unit:,} steps: training {done + remaining:,} steps in all, not {steps:,}"
        )

    trials = held_out_trials(run["eval_scenarios"], run["eval_seeds"])
    evaluation = HeldOutEvaluation(out, trials, env_id, section["env_kwargs"], eval_every, state, run["action_bounds"])

    def _stop(signum, frame):  # SIGTERM behaves like Ctrl-C: checkpoint, then exit
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _stop)
    try:
        model.learn(
            remaining,
            callback=CallbackList([evaluation]),
            progress_bar=progress_bar,
            reset_num_timesteps=done == 0,
            tb_log_name=algo,
        )
        if evaluation.last_evaluated != model.num_timesteps:
            evaluation.evaluate_and_checkpoint()
    except KeyboardInterrupt:
        save_checkpoint(model, out, state, model.num_timesteps)
        print(f"\ninterrupted at {model.num_timesteps} steps; run the same command again to resume")
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        vec_env.close()
    if model.num_timesteps != done + remaining:
        print(f"{algo} stopped at {model.num_timesteps:,} steps (its rollouts end with episodes)")
    return out
