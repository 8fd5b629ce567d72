"""``magenv datasets``: offline datasets (Minari) of the oracles' and the tuned rules' rollouts.

    magenv datasets build [--envs LIST] [--methods LIST] [--episodes N] [--seed S] [--episode-seconds S]
                          [--root DIR] [--force]
    magenv datasets list [--root DIR]

``build`` rolls each method out in each env on the env's training mixture (``magenv.benchmark.suite``: the
scenarios of ``env_kwargs["scenario"]``), ``--episodes`` episodes at reset seeds ``--seed``, ``--seed`` + 1, …
(training seeds: ≥ 10 000, never an evaluation or validation trial), and stores them with Minari as
``magenv/ENV-METHOD-v0`` (``ENV`` the env's short name in lower case, e.g. ``magenv/blend-oracle-v0``) under
``--root`` (default: Minari's own folder, ``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``). Each step holds
the observation, the action, the reward and, in its infos, the truth-only channels ``TRUTH_INFO`` (the errors
of the estimate against the true orientation, the disturbance's size, the true and estimated quaternions; NaN
at the reset). The methods: ``oracle`` — the suite's privileged oracle of the env, acting at each decision with
its cheapest candidate (it reads truth: expert data, not a deployable policy) — and ``rules`` — the tuned rules
of the env's tasks that act as policies (:func:`dataset_rules`); each in the env options it acts in (its
observation's features, a tuned gain schedule or detector).

Replaying a dataset: ``env = dataset.recover_environment()``, ``env.reset(seed=episode.id's seed)`` (the
episode's ``seed`` in its metadata), then its actions: the same rewards, bit for bit.
"""

from __future__ import annotations

import argparse
import os
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np

from magenv.seeding import HELD_OUT_BELOW
from magenv.train.cli import CommandError, output_folder

NAMESPACE = "magenv"
#: The step-info channels a dataset keeps: what only the simulator knows (truth), and the estimate they score.
TRUTH_INFO = {
    "t": (),
    "sample": (),
    "error_total": (),
    "error_heading": (),
    "error_inclination": (),
    "disturbance_norm": (),
    "q_true": (4,),
    "q_est": (4,),
}
MINARI_PATH_ENV = "MINARI_DATASETS_PATH"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("build", "list"))
    p.add_argument("--envs", default=None, help="comma list of env names (default: every env of the suite)")
    p.add_argument("--methods", default="oracle,rules", help="oracle, rules or both (default %(default)s)")
    p.add_argument("--episodes", type=int, default=20, help="episodes per method and env (default %(default)s)")
    p.add_argument("--seed", type=int, default=HELD_OUT_BELOW, help="first reset seed, ≥ 10000 (default %(default)s)")
    p.add_argument("--episode-seconds", type=float, default=None, help="cut episodes to S seconds (default: whole)")
    p.add_argument("--root", type=Path, default=None, help="datasets folder (default: Minari's)")
    p.add_argument("--force", action="store_true", help="replace datasets of the same id")


def _minari():
    try:
        import minari
    except ImportError:
        raise CommandError("magenv datasets needs Minari: pip install 'magenv[datasets]'") from None
    return minari


def dataset_rules(env_id: str) -> list[str]:
    """The rules of ``env_id``'s tasks (``magenv.benchmark.suite``) that act as policies (an estimator, such as
    MagQSF-v0's ``delay_magyq_tuned``, has no actions to store)."""
    from magenv import registry
    from magenv.benchmark import suite
    from magenv.protocols import is_policy

    rules = dict.fromkeys(t.rule for t in suite.TASKS if t.env_id == env_id)
    return [r for r in rules if is_policy(registry.make(r))]


def dataset_id(env_id: str, method: str) -> str:
    """``magenv/blend-oracle-v0`` for MagBlend-v0's ``oracle``."""
    short = env_id.rsplit("/", 1)[-1].removeprefix("Mag").rsplit("-", 1)[0].lower()
    return f"{NAMESPACE}/{short}-{method.replace('_', '-')}-v0"


class TruthInfo(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """An env with its infos reduced to ``TRUTH_INFO`` (NaN at the reset, which has none of them): the same keys
    and shapes at every step, as Minari stores them. Recreatable from its spec (``recover_environment``)."""

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)

    @staticmethod
    def truth(info: dict | None) -> dict:
        info = info or {}
        return {
            k: np.asarray(info.get(k, np.full(shape, np.nan)), np.float64).reshape(shape)
            for k, shape in TRUTH_INFO.items()
        }

    def reset(self, **kwargs):
        obs, _ = self.env.reset(**kwargs)
        return obs, self.truth(None)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self.truth(info)


def _actor(method: str, env_id: str):
    """(env options, act(obs, runner) -> action, reset()) of a method: the oracle's cheapest candidate at each
    decision, or a rule acting on the observation."""
    from magenv import registry
    from magenv.agents.dagger import candidate_matrix
    from magenv.benchmark import suite
    from magenv.protocols import is_policy

    if method == "oracle":
        oracle = registry.make(next(t.oracle for t in suite.TASKS if t.env_id == env_id and t.oracle))
        cands = candidate_matrix(oracle.candidates)
        kwargs = {**getattr(oracle, "env_kwargs", {}), "decision_every": oracle.decision_every}
        return kwargs, lambda obs, runner: cands[int(np.argmin(oracle.candidate_costs(runner)))], lambda: None
    rule = registry.make(method)
    if not is_policy(rule) or rule.env_id != env_id:
        raise CommandError(f"{method} is not a policy of {env_id}")
    kwargs = dict(getattr(rule, "env_kwargs", {}) or {})
    return kwargs, lambda obs, runner: rule(obs), rule.reset


def build(env_id: str, method: str, episodes: int, seed: int, episode_seconds: float | None, force: bool) -> str:
    """Roll ``method`` out ``episodes`` times in ``env_id`` on its training mixture and store the Minari dataset;
    returns its id."""
    import gymnasium as gym

    import magenv  # noqa: F401  (registers the envs)
    from magenv.benchmark import suite

    minari = _minari()
    name = dataset_id(env_id, method)
    if name in minari.list_local_datasets():
        if not force:
            raise CommandError(f"dataset {name} exists (in {minari.storage.get_dataset_path()}); --force replaces it")
        minari.delete_dataset(name)
    kwargs, act, reset = _actor(method, env_id)
    kwargs["scenario"] = ",".join(suite.env_spec(env_id).mixture)
    if episode_seconds is not None:
        kwargs["episode_seconds"] = episode_seconds
    env = gym.make(env_id, **kwargs)
    collector = minari.DataCollector(TruthInfo(env), record_infos=True)
    for i in range(episodes):
        obs, _ = collector.reset(seed=seed + i)
        reset()
        done = False
        while not done:
            action = np.asarray(act(obs, env.unwrapped._runner), np.float32)  # type: ignore[attr-defined]
            obs, _, terminated, truncated, _ = collector.step(action)
            done = terminated or truncated
    with warnings.catch_warnings():  # Minari's advice to give an e-mail address and a versioned code link
        warnings.filterwarnings("ignore", message=".*(author_email|code_permalink).*")
        collector.create_dataset(
            dataset_id=name,
            eval_env=env.spec,
            algorithm_name=method if method != "oracle" else f"privileged oracle ({suite.VERSION}), cheapest candidate",
            author="magenv",
            description=f"{method} in {env_id} on the training mixture {kwargs['scenario']}, reset seeds "
            f"{seed}–{seed + episodes - 1}; infos: the truth-only channels {', '.join(TRUTH_INFO)}",
        )
    collector.close()
    return name


def run(args: argparse.Namespace) -> int:
    from magenv.benchmark import suite

    if args.root is not None:
        os.environ[MINARI_PATH_ENV] = str(output_folder(args.root, "--root").resolve())
    minari = _minari()
    if args.action == "list":
        found = minari.list_local_datasets(prefix=NAMESPACE)
        for name, meta in sorted(found.items()):
            print(f"{name}: {meta.get('total_episodes')} episodes, {meta.get('total_steps')} steps")
        print(f"{len(found)} magenv dataset(s) in {minari.storage.get_dataset_path()}")
        return 0
    if args.episodes < 1:
        raise CommandError(f"--episodes must be ≥ 1, got {args.episodes}")
    if args.seed < HELD_OUT_BELOW:
        raise CommandError(f"--seed must be a training seed, ≥ {HELD_OUT_BELOW} (below: evaluation and validation)")
    if args.episode_seconds is not None and not args.episode_seconds > 0:
        raise CommandError(f"--episode-seconds must be > 0, got {args.episode_seconds}")
    try:
        envs = [suite.env_spec(e).env_id for e in args.envs.split(",")] if args.envs else [e.env_id for e in suite.ENVS]
    except ValueError as exc:
        raise CommandError(f"--envs: {exc}") from None
    kinds = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not kinds or set(kinds) - {"oracle", "rules"}:
        raise CommandError(f"--methods must name oracle, rules or both, got {args.methods!r}")
    plan = [(e, m) for e in envs for k in kinds for m in (["oracle"] if k == "oracle" else dataset_rules(e))]
    existing = minari.list_local_datasets()
    taken = [dataset_id(e, m) for e, m in plan if dataset_id(e, m) in existing]
    if taken and not args.force:
        raise CommandError(f"dataset(s) {', '.join(taken)} exist; --force replaces them")
    for env_id, method in plan:
        name = build(env_id, method, args.episodes, args.seed, args.episode_seconds, args.force)
        print(f"wrote {name}", flush=True)
    return 0
