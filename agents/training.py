"""The training engine behind ``magenv train``: an SB3 agent trained on a magenv environment into a run folder.

:func:`train` builds the agent from its config (``magenv.agents.hyperparams``),
optionally clones a teacher first (``magenv.agents.imitation``), and learns
with a progress bar, TensorBoard logs (``RUN/tb``), periodic evaluation on
held-out trials with the best model kept, checkpoints, and resume: calling it
again on an existing run folder continues from its last checkpoint up to
``steps`` in all. Resuming rebuilds the agent from ``run.yaml`` and loads
arrays only (``magenv.agents.weights``), checked before any training; it
refuses a config, seed or evaluation set other than the run's unless
``force``. The run folder layout is in ``magenv.agents.loading``.

What a run folder holds is always whole (``magenv.agents.run_folder``): files
are committed together with ``state.json``, which names them, and the folder
is locked while a run writes to it. A checkpoint is committed

* after the update that completes a rollout, at each evaluation (the model
  evaluated, the evaluation recorded, the best model kept, ``checkpoints/step_T``);
* at the end (after a last evaluation, unless the last update was evaluated);
* on Ctrl-C or SIGTERM: the model after its last completed update — an update
  (and a commit) under way finishes first; an evaluation under way is dropped,
  and made first when the run resumes.

A kill (``kill -9``, a crash, a power cut) loses what was trained since the
last commit and nothing else: the same command resumes from it, evaluating
at the same step counts and ending at the same total as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import csv
import inspect
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback
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
from magenv.agents.run_folder import STATE_FILE, RunFolder, digest
from magenv.agents.vec_env import make_train_env
from magenv.agents.wrappers import action_bounds
from magenv.evaluation import run_policy_on_trials
from magenv.scenarios import make_trial, scenario_names

#: Torch threads while an agent trains, and in every ``magenv`` command (``train.cli.one_torch_thread``). The
#: 64×64 networks are too small to share between threads: on the loaded 2-core machine PPO on 128 batched envs ran
#: 4.1 k env-steps/s with 2 threads, 20 k with 1.
TORCH_THREADS = 1

REPLAY_FILE = "replay_buffer.safetensors"
EVALUATIONS_FILE = "evaluations.csv"  # timesteps, held-out RMSE (°), seconds since the run began; no header
#: What older run folders (magenv 0.1) kept as pickles: read only with ``trust_pickle``.
LEGACY_VECNORMALIZE, LEGACY_REPLAY = "vecnormalize.pkl", "replay_buffer.pkl"


class Interrupts:
    """SIGINT (Ctrl-C) and SIGTERM as KeyboardInterrupt, held back while :meth:`held` (an update, a commit)."""

    def __init__(self) -> None:
        self.holding = 0
        self.pending = False

    def _handle(self, signum, frame) -> None:
        if self.holding:
            self.pending = True
        else:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        """The handlers in place (from the main thread only: elsewhere Python delivers no signals)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """Run the block to its end; a signal that came meanwhile is raised after it."""
        self.holding += 1
        try:
            yield
        finally:
            self.holding -= 1
        if not self.holding and self.pending:
            self.pending = False
            raise KeyboardInterrupt


class Checkpoints:
    """What a run writes to its folder, and when: evaluations on the held-out ``trials`` and commits of the
    model's state (see the module docstring). ``state`` is the committed progress record: ``timesteps``,
    ``best_score`` / ``best_timesteps`` (lowest mean total RMSE, °, over the trials), ``evaluations`` (rows
    ``[timesteps, score, seconds]``), ``t0`` (when the run began, epoch seconds)."""

    def __init__(self, folder: RunFolder, model, run: dict, state: dict, trials: list, every: int):
        self.folder, self.model, self.run = folder, model, run
        self.state = {k: v for k, v in state.items() if k != "files"}  # the folder keeps the file digests
        self.trials, self.every = trials, every
        self.interrupts = Interrupts()
        self.run_yaml_pending = True  # run.yaml goes with the first commit of this process
        self.trained = state["timesteps"]  # steps whose update is complete
        self._marks: tuple = ()

    def after_update(self) -> None:
        """Called with every update complete (and before the first rollout): note the step count and what a
        rollout changes besides the model (reward statistics, the replay buffer's position), then evaluate and
        commit if an evaluation is due."""
        model = self.model
        self.trained = model.num_timesteps
        norm, buf = weights._vecnormalize(model), getattr(model, "replay_buffer", None)
        self._marks = (
            None if norm is None else (norm.ret_rms.mean.copy(), norm.ret_rms.var.copy(), norm.ret_rms.count),
            None if buf is None else (buf.pos, buf.full),
        )
        if self.trained >= self.next_evaluation():
            self.evaluate_and_commit()

    def next_evaluation(self) -> int:
        """The step count from which the next evaluation is due: ``every`` after the last one."""
        evaluations = self.state["evaluations"]
        return (evaluations[-1][0] if evaluations else 0) + self.every

    def evaluate(self) -> float:
        """The mean total-orientation RMSE (°) of the current model over the held-out trials (a method that
        diverges scores 180°, ``magenv.evaluation``); logged to TensorBoard."""
        run = self.run
        policy = AgentPolicy(
            self.model, run["env_id"], run["env_kwargs"], name="candidate", action_bounds=run["action_bounds"]
        )
        scores = run_policy_on_trials(policy, self.trials, run["env_id"], run["env_kwargs"])
        score = float(sum(s.total for s in scores) / len(scores))
        logger = getattr(self.model, "_logger", None)  # set up by learn(): none if this process trains nothing
        if logger is not None:
            logger.record("heldout/total_rmse_deg", score)
            logger.dump(self.trained)
        return score

    def evaluate_and_commit(self) -> float:
        score = self.evaluate()
        self.commit(score)
        return score

    def commit(self, score: float | None = None) -> None:
        """Commit the model after ``trained`` steps (with its evaluation ``score``, if evaluated): the
        checkpoint, the SB3 export, SAC's replay buffer, and with a score the evaluation record, the step's
        policy weights and, if it is the best so far, the best model. Signals wait until it is done."""
        model, t, folder = self.model, self.trained, self.folder
        state = {**self.state, "timesteps": t}
        writers: dict[str, Callable[[Path], object]] = {}
        if score is not None:
            state["evaluations"] = [*state["evaluations"], [t, score, round(time.time() - state["t0"], 1)]]
            writers[f"checkpoints/step_{t}.safetensors"] = lambda p: weights.save_policy(model, p, t)
            writers[EVALUATIONS_FILE] = lambda p: _write_evaluations(p, state["evaluations"])
            if score < state["best_score"]:
                state["best_score"], state["best_timesteps"] = score, t
                writers[WEIGHTS["best"]] = lambda p: weights.save_policy(model, p, t)
                writers[SB3_EXPORTS["best"]] = lambda p: _export(model, p)
        if self.run_yaml_pending:
            writers[RUN_FILE] = lambda p: p.write_text(yaml.safe_dump(self.run, sort_keys=False))
        writers[WEIGHTS["last"]] = lambda p: weights.save_checkpoint(model, p, state)
        writers[SB3_EXPORTS["last"]] = lambda p: _export(model, p)
        if getattr(model, "replay_buffer", None) is not None:
            writers[REPLAY_FILE] = lambda p: weights.save_replay_buffer(model, p, t)
        with self.interrupts.held():
            folder.commit(writers, state)
        self.state, self.run_yaml_pending = state, False

    def commit_interrupted(self) -> None:
        """On Ctrl-C or SIGTERM: commit the model after its last complete update, unless that is committed.
        Stopped inside a rollout, the rollout's steps are dropped: the reward statistics and the replay buffer's
        position go back to where the rollout began (the weights and optimizers do not change in a rollout)."""
        if self.trained == self.state["timesteps"]:
            return
        if self.model.num_timesteps != self.trained and self._marks:
            rms, position = self._marks
            if rms is not None:
                norm = weights._vecnormalize(self.model).ret_rms
                norm.mean, norm.var, norm.count = rms
            if position is not None:
                self.model.replay_buffer.pos, self.model.replay_buffer.full = position
        self.commit()


def _export(model, path: Path) -> None:
    """The SB3 ``.zip`` of ``model`` (for SB3 users; never read by magenv unless trusted), without the held
    update :func:`_learn` sets on it."""
    model.save(path, exclude=["train"])


def _write_evaluations(path: Path, rows: list) -> None:
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([t, f"{score:.4f}", f"{seconds:.1f}"] for t, score, seconds in rows)


class HeldOutEvaluation(BaseCallback):
    """Hands SB3's training loop to :class:`Checkpoints`: each rollout begins after the update of the one before
    (``_on_rollout_start``), so the model seen there is the model after that update."""

    def __init__(self, checkpoints: Checkpoints):
        super().__init__()
        self.checkpoints = checkpoints

    def _on_rollout_start(self) -> None:
        self.checkpoints.after_update()

    def _on_step(self) -> bool:
        return True


def _read_evaluations(path: Path) -> list:
    """Rows ``[timesteps, score, seconds]`` of an older run folder's ``evaluations.csv`` (none if missing)."""
    if not path.is_file():
        return []
    try:
        return [[int(r[0]), float(r[1]), float(r[2])] for r in csv.reader(path.open()) if r]
    except (ValueError, IndexError) as exc:
        raise RunError(f"{path}: corrupt ({exc})") from None


def progress(run_dir: Path, algo: str) -> dict | None:
    """The progress record (``timesteps``, ``best_score``, ``evaluations`` …) a resume of ``run_dir`` continues
    from: its committed ``state.json``; None for a folder without one. Older run folders (whose state file
    names no files) keep it in their latest checkpoint (``last.safetensors``), else in ``state.json``.
    RunError naming a corrupt file."""
    run_dir = Path(run_dir)
    state = RunFolder(run_dir).read_state()
    try:
        if state is not None and "files" in state:
            return weights.check_progress(state)
        checkpoint = run_dir / WEIGHTS["last"]
        if checkpoint.is_file():
            state = weights.read(checkpoint, algo)[1].get("state")
            if not isinstance(state, dict):
                raise RunError(f"{checkpoint}: no progress record in the checkpoint")
            return weights.check_progress(state)
        return None if state is None else weights.check_progress(state)
    except ValueError as exc:
        if isinstance(exc, RunError):
            raise
        raise RunError(f"{run_dir}: corrupt progress record ({exc})") from None


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


def rollout_unit(algo: str, section: dict) -> tuple[int, str]:
    """(steps, why): the algorithm of a checked config ``section`` trains in whole multiples of ``steps``
    environment steps (a whole number of them from 0, so a fresh run and a resumed one stop at the same total)."""
    defaults = {k: p.default for k, p in inspect.signature(algorithm_class(algo).__init__).parameters.items()}
    n_envs = section["n_envs"]
    if "train_freq" not in defaults:  # on-policy: whole rollouts
        n_steps = section.get("n_steps", defaults["n_steps"])
        return n_steps * n_envs, f"rollouts of n_steps {n_steps} × {n_envs} env(s)"
    freq = section.get("train_freq", defaults["train_freq"])
    every, unit = (freq, "step") if isinstance(freq, int) else freq
    if unit == "step":
        return every * n_envs, f"train_freq {every} × {n_envs} env(s)"
    return n_envs, f"{n_envs} env(s) per step"


def check_env_kwargs(env_id: str, env_kwargs: dict, where: str = "env_kwargs") -> None:
    """ConfigError naming ``where`` unless ``env_kwargs`` are arguments the env ``env_id`` takes, with values it
    accepts (one env is made and closed)."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    entry = gym.spec(env_id).entry_point
    creator = load_env_creator(entry) if isinstance(entry, str) else entry
    assert callable(creator), f"{env_id} has no entry point"
    params = inspect.signature(creator).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        unknown = [k for k in env_kwargs if k not in params]
        if unknown:
            raise ConfigError(
                f"{where}: unknown argument(s) {', '.join(map(repr, unknown))} of {env_id}; known: {', '.join(params)}"
            )
    try:
        gym.make(env_id, disable_env_checker=True, **env_kwargs).close()
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {env_id} refuses them: {exc}") from None


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


def _adopt_legacy(folder: RunFolder, state: dict) -> dict:
    """An older run folder (its state file names no files): name the files it holds, and read its evaluations
    from ``evaluations.csv``, so that its first commit writes a whole state."""
    names = [RUN_FILE, *WEIGHTS.values(), *SB3_EXPORTS.values(), REPLAY_FILE, EVALUATIONS_FILE]
    names += [f"checkpoints/{p.name}" for p in sorted((folder.path / "checkpoints").glob("*.safetensors"))]
    folder.files = {n: digest(folder.path / n) for n in names if (folder.path / n).is_file()}
    evaluations = _read_evaluations(folder.path / EVALUATIONS_FILE)
    state = {"best_score": math.inf, "best_timesteps": None, "t0": time.time(), **state, "evaluations": evaluations}
    return weights.check_progress(state)


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
    when resuming); it is rounded up to the algorithm's whole rollouts
    (:func:`rollout_unit`), the same total for a fresh run and a resumed one,
    and the rounding printed. ``config``, ``seed``, ``n_envs``,
    ``eval_scenarios`` and ``eval_seeds`` left None mean the run's own when
    resuming, else the shipped config, 0, the config's,
    ``DEFAULT_EVAL_SCENARIOS`` × ``DEFAULT_EVAL_SEEDS``; given and different
    from a resumed run's, they are a RunError naming each difference, unless
    ``force`` (then the run continues with them). ``trust_pickle`` lets an
    older run folder resume from its pickles. ``make_method(name)`` builds a
    method from its name (``magenv.registry.make``); it is needed only when the
    config has a ``pretrain`` teacher, which it builds. Every argument, the
    config and the run folder are checked before anything is written or
    trained; RunError if another run is writing to ``out``.
    """
    out = Path(out)
    steps = None if steps is None else check_value("train", "steps", steps, RUN_RULES["n_timesteps"])
    eval_every = check_value("train", "eval_every", eval_every, POSITIVE_INT)
    seed = None if seed is None else check_value("train", "seed", seed, SEED_RULE)
    n_envs = None if n_envs is None else check_value("train", "n_envs", n_envs, RUN_RULES["n_envs"])
    eval_scenarios, eval_seeds = _check_eval_set(eval_scenarios, eval_seeds)
    cls = algorithm_class(algo)
    if out.exists() and not out.is_dir():
        raise RunError(f"{out}: not a folder (--out names the run folder)")
    new = not (out / RUN_FILE).is_file() and not (out / STATE_FILE).is_file()
    if new:  # a new run: its config checked before the folder is made
        section = load_hyperparams(algo, env_id, config)
        if n_envs:
            section["n_envs"] = n_envs
        check_env_kwargs(env_id, section["env_kwargs"], f"{config or 'the shipped config'}: env_kwargs")
        _teacher(section, env_id, make_method)
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
    folder = RunFolder(out)
    with folder.locked():
        state = folder.recover()
        legacy = False
        if new:
            if state is not None:
                raise RunError(f"{out}: another run began in this folder meanwhile; use another --out")
            state = {"timesteps": 0, "best_score": math.inf, "best_timesteps": None, "t0": time.time()}
            state["evaluations"] = []
        else:
            requested = {"config": config, "seed": seed, "n_envs": n_envs}
            requested |= {"eval_scenarios": eval_scenarios, "eval_seeds": eval_seeds}
            run, state, legacy = _resumed(folder, state, env_id, algo, requested, force, trust_pickle)
        section = run["hyperparams"]
        run["steps"] = steps = steps or run["steps"]
        unit, why = rollout_unit(algo, section)
        total = math.ceil(steps / unit) * unit
        done = state["timesteps"]
        if done >= total and state["evaluations"] and state["evaluations"][-1][0] == done:
            rounded = f", which {algo} trains as {total:,}" if total != steps else ""
            print(f"{out}: already trained for {done:,} steps (asked {steps:,}{rounded})")
            return out
        if total != steps:
            print(f"{algo} trains in whole {why} = {unit:,} steps: training {total:,} steps in all, not {steps:,}")
        _run(folder, run, state, cls, new, legacy, total, eval_every, make_method, progress_bar)
    return out


def _resumed(
    folder: RunFolder, state: dict | None, env_id: str, algo: str, asked: dict, force: bool, trust_pickle: bool
) -> tuple[dict, dict, bool]:
    """(run.yaml, progress record, whether only an older magenv's pickles hold the model) of the run in
    ``folder`` (recovered, its committed ``state``), checked against the request: ``asked`` holds the
    ``config``, ``seed``, ``n_envs``, ``eval_scenarios`` and ``eval_seeds`` given (None: not given); other
    values are a RunError naming each difference unless ``force``."""
    out = folder.path
    checkpoint = out / WEIGHTS["last"]
    legacy = not checkpoint.is_file() and (out / SB3_EXPORTS["last"]).is_file()
    if state is None and not checkpoint.is_file() and not legacy:
        raise RunError(
            f"{out}: {RUN_FILE} without training state ({STATE_FILE}, {WEIGHTS['last']}): not a run that "
            "magenv train can continue (a DAgger run?); remove the folder or use another --out"
        )
    run = read_run(out)
    if (run["env_id"], run["algo"]) != (env_id, algo):
        raise RunError(
            f"{out}: existing run is {run['algo']} on {run['env_id']}; use another --out for {algo} on {env_id}"
        )
    try:
        run["steps"] = check_value("run.yaml", "steps", run.get("steps"), RUN_RULES["n_timesteps"])
        run["eval_scenarios"], run["eval_seeds"] = _check_eval_set(
            run.get("eval_scenarios", []), run.get("eval_seeds", [])
        )
    except ConfigError as exc:
        raise RunError(f"{out / RUN_FILE}: {exc}") from None
    requested: dict[str, Any] = {}
    if asked["config"] is not None or asked["n_envs"] is not None:
        section = load_hyperparams(algo, env_id, asked["config"]) if asked["config"] is not None else run["hyperparams"]
        requested["hyperparams"] = {**section, "n_envs": asked["n_envs"] or section["n_envs"]}
    requested |= {k: asked[k] for k in ("seed", "eval_scenarios", "eval_seeds") if asked[k] is not None}
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
    check_env_kwargs(env_id, run["env_kwargs"], f"{out / RUN_FILE}: env_kwargs")
    if state is None or "files" not in state:  # an older run folder: its checkpoint holds the progress
        state = _adopt_legacy(folder, progress(out, algo) or {"timesteps": 0})
    try:
        weights.check_progress(state)
    except ValueError as exc:
        raise RunError(f"{out / STATE_FILE}: {exc}") from None
    return run, state, legacy


def _run(
    folder: RunFolder,
    run: dict,
    state: dict,
    cls,
    new: bool,
    legacy: bool,
    total: int,
    every: int,
    make_method: Callable[[str], Any] | None,
    progress_bar: bool,
) -> None:
    """Build the env and the agent of ``run`` (a new one, its first commit made; or the checkpoint's, checked
    and loaded) and train it to ``total`` steps (:func:`_learn`), evaluating every ``every`` steps."""
    out, section, seed, done = folder.path, run["hyperparams"], run["seed"], state["timesteps"]
    torch.set_num_threads(TORCH_THREADS)
    vec_env = make_train_env(run["env_id"], section["n_envs"], seed + done, section["env_kwargs"])
    try:
        if legacy:
            model, vec_env = _legacy_model(out, cls, vec_env, section)
        else:
            if section.get("normalize_reward"):
                # Reward scale differs by orders of magnitude between scenarios (0.5° clean, 20° in a bad
                # random trial); learning sees rewards divided by a running std of the return. Scores and
                # the env's own rewards are unchanged.
                vec_env = VecNormalize(vec_env, norm_obs=False, norm_reward=True, gamma=section.get("gamma", 0.99))
            model = build_model(run, env=vec_env, where=str(out / RUN_FILE), seed=seed, tensorboard_log=str(out / "tb"))
            if not new:
                saved = weights.load_checkpoint(model, out / WEIGHTS["last"])
                if saved["timesteps"] != done:
                    raise RunError(f"{out / WEIGHTS['last']}: holds {saved['timesteps']} steps, {STATE_FILE} {done}")
                if getattr(model, "replay_buffer", None) is not None and (out / REPLAY_FILE).is_file():
                    weights.load_replay_buffer(model, out / REPLAY_FILE)
            elif section.get("pretrain"):
                teacher = _teacher(section, run["env_id"], make_method)
                state["pretrain_mse"] = pretrain(model, run["env_id"], section, teacher, run["action_bounds"], seed)
        trials = held_out_trials(run["eval_scenarios"], run["eval_seeds"])
        checkpoints = Checkpoints(folder, model, run, state, trials, every)
        with checkpoints.interrupts.installed():
            if new:  # the untrained (or cloned) model: a run to resume from from the start
                checkpoints.commit()
            _learn(model, checkpoints, total - done, run["algo"], progress_bar, reset=done == 0)
    finally:
        vec_env.close()
    if model.num_timesteps != total:
        print(f"{run['algo']} stopped at {model.num_timesteps:,} steps (its rollouts end with episodes)")


def _learn(model, checkpoints: Checkpoints, remaining: int, algo: str, progress_bar: bool, reset: bool) -> None:
    """Train ``remaining`` steps with SB3, every update held against signals (:class:`Interrupts`) and followed
    by :meth:`Checkpoints.after_update`; then evaluate and commit the end, unless already done. On Ctrl-C or
    SIGTERM: commit the last complete update (:meth:`Checkpoints.commit_interrupted`), then raise."""
    update = model.train

    def held_update(*args, **kwargs):
        with checkpoints.interrupts.held():
            update(*args, **kwargs)
            checkpoints.trained = model.num_timesteps  # complete: a signal that came meanwhile commits it

    model.train = held_update  # SB3 calls self.train() for every update
    try:
        if remaining > 0:
            model.learn(
                remaining,
                callback=HeldOutEvaluation(checkpoints),
                progress_bar=progress_bar,
                reset_num_timesteps=reset,
                tb_log_name=algo,
            )
        checkpoints.trained = model.num_timesteps
        evaluations = checkpoints.state["evaluations"]
        if not evaluations or evaluations[-1][0] != checkpoints.trained:
            checkpoints.evaluate_and_commit()
    except KeyboardInterrupt:
        checkpoints.commit_interrupted()
        print(f"\ninterrupted at {checkpoints.trained:,} steps; run the same command again to resume")
        raise
    finally:
        del model.train
