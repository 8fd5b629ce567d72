"""``magenv train``: train an SB3 agent on a magenv environment (the engine: ``magenv.agents.training``).

    magenv train --env magenv/MagBlend-v0 --algo ppo --steps 100000 --out runs/NAME \
        [--config FILE] [--seed S] [--eval-every N] [--eval-scenarios A,B] [--eval-seeds 0:3] [--force]

With ``--teacher NAME`` it runs DAgger instead (``magenv.agents.dagger``: an MLP student imitating the
privileged oracle NAME — ``oracle`` for MagBlend-v0, ``oracle_kalman`` … — on the env's extended
observation; ``--env`` defaults to the teacher's env; ``--config`` a YAML file of the DAgger keys per env
id, default ``agents/configs/dagger.yaml``; ``--iters`` overrides its iterations; ``--resume`` continues
the DAgger run in ``--out`` with its own config up to ``--iters`` iterations in all; ``--refit SOURCE``
fits one fresh student on all of the finished run SOURCE's labelled data into ``--out``, with the fit keys
of ``--config``'s section — only ``dagger.REFIT_KEYS``, e.g. ``hidden``, ``fit_steps`` — replacing
SOURCE's); ``--combine RUN …`` makes one ensemble of the students of finished runs of the teacher, scored on
``--eval-seeds`` (``dagger.combine``); ``--cv recordings [--folds K]`` runs leave-recordings-out
cross-validation instead (``magenv.agents.dagger_cv``: K runs ``--out/foldF``, each without one group of
the config's real recordings and their twins, scored on those; ``--out/cv.csv``); the run folder is loadable
with ``--agent RUN`` like any other.

Progress bar, TensorBoard logs (``runs/NAME/tb``), periodic evaluation on
held-out trials with the best model kept, checkpoints, and resume: running
the same command again on an existing run folder continues from its last
checkpoint up to ``--steps`` in all (Ctrl-C saves a checkpoint first). A
resumed run keeps its config, seed and evaluation set; giving different ones
is an error naming each difference, unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np

from magenv.agents.hyperparams import (
    DEFAULT_EVAL_EVERY,
    DEFAULT_EVAL_SCENARIOS,
    DEFAULT_EVAL_SEEDS,
    DEFAULT_SEED,
    POSITIVE_INT,
    RUN_RULES,
    SEED_RULE,
)
from magenv.envs import BLEND_ID
from magenv.train.cli import CommandError, output_folder, rule_arg
from magenv.train.seeds import seeds_arg


def add_arguments(p: argparse.ArgumentParser) -> None:
    seeds = f"{DEFAULT_EVAL_SEEDS[0]}:{DEFAULT_EVAL_SEEDS[-1] + 1}"
    p.add_argument("--env", default=None, help=f"environment id (default {BLEND_ID}; with --teacher the teacher's)")
    p.add_argument("--algo", default="ppo", help="ppo, sac or recurrent_ppo (default %(default)s)")
    p.add_argument(
        "--steps",
        type=rule_arg(RUN_RULES["n_timesteps"]),
        default=None,
        help="total environment steps (default: the config's n_timesteps, or the run's when resuming)",
    )
    p.add_argument("--out", required=True, type=Path, help="run folder (created, or resumed if it exists)")
    p.add_argument(
        "--config",
        default=None,
        help="YAML hyperparameter file (default agents/configs/ALGO.yaml, or the run's when resuming)",
    )
    p.add_argument(
        "--seed",
        type=rule_arg(SEED_RULE),
        default=None,
        help=f"training seed (default {DEFAULT_SEED}, or the run's when resuming)",
    )
    p.add_argument(
        "--n-envs",
        type=rule_arg(RUN_RULES["n_envs"]),
        default=None,
        help="parallel environments (default: the config's)",
    )
    p.add_argument(
        "--eval-every",
        type=rule_arg(POSITIVE_INT),
        default=DEFAULT_EVAL_EVERY,
        help="steps between held-out evaluations and checkpoints (default %(default)s)",
    )
    p.add_argument(
        "--eval-scenarios",
        default=None,
        help=f"comma list (default {','.join(DEFAULT_EVAL_SCENARIOS)}, or the run's when resuming)",
    )
    p.add_argument(
        "--eval-seeds",
        type=seeds_arg,
        default=None,
        help=f"held-out validation seeds for model selection, e.g. 5000:5004 (default {seeds}, "
        "or the run's when resuming)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="resume even with a config, seed or evaluation set other than the run's (they replace it)",
    )
    p.add_argument(
        "--trust-pickle",
        action="store_true",
        help="resume an older run folder from its pickle files (.zip, .pkl), which can run code: "
        "only for folders whose author you trust",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--teacher",
        default=None,
        help="train a DAgger student imitating this privileged method (oracle, oracle_kalman, …) instead of an "
        "SB3 agent",
    )
    p.add_argument("--iters", type=rule_arg(POSITIVE_INT), default=None, help="DAgger iterations (default: config's)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="with --teacher: continue the DAgger run in --out (its config, --iters iterations in all)",
    )
    p.add_argument(
        "--refit",
        type=Path,
        default=None,
        metavar="SOURCE",
        help="with --teacher and --config: one fresh student on all of the DAgger run SOURCE's data, into --out "
        "(the config's section: the fit keys to change, e.g. hidden, fit_steps)",
    )
    p.add_argument(
        "--cv",
        choices=["recordings"],
        default=None,
        help="with --teacher: leave-recordings-out cross-validation (runs in --out/foldF, held-out scores in "
        "--out/cv.csv)",
    )
    p.add_argument("--folds", type=rule_arg(POSITIVE_INT), default=3, help="with --cv: number of folds (default 3)")
    p.add_argument(
        "--combine",
        type=Path,
        nargs="+",
        default=None,
        metavar="RUN",
        help="with --teacher: one student from the finished DAgger runs RUN …, their students as one ensemble, "
        "scored on --eval-seeds (choose seeds no run was selected on)",
    )
    p.add_argument(
        "--disagree",
        type=float,
        default=None,
        help="with --combine: the guard's disagreement limit (default: the runs' own)",
    )


def run_dagger(args: argparse.Namespace) -> int:
    """``--teacher``: DAgger into ``--out`` (config: ``--config`` or the packaged dagger.yaml)."""
    from importlib import resources

    from magenv import registry
    from magenv.agents import dagger
    from magenv.checks import check_yaml

    try:
        teacher = registry.make(args.teacher)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    env_id = args.env or getattr(teacher, "env_id", BLEND_ID)
    path = args.config or str(resources.files("magenv.agents") / "configs" / "dagger.yaml")
    if args.resume and args.config:
        raise CommandError("--resume continues a run with its own config; drop --config (only --iters may change)")
    if args.refit is not None and (args.resume or not args.config):
        raise CommandError("--refit needs --config (the fit keys to change) and no --resume")
    try:  # a resumed run keeps its own config
        config = {} if args.resume else dict((check_yaml(Path(path).read_text(), path) or {}).get(env_id) or {})
    except (OSError, AttributeError, TypeError, ValueError) as exc:
        raise CommandError(f"cannot read the DAgger config {path}: {exc}") from None
    if args.iters is not None:
        config["iterations"] = args.iters
    if args.eval_seeds is not None:
        config["val_seeds"] = [args.eval_seeds[0], args.eval_seeds[-1] + 1]
    if args.eval_scenarios is not None:
        config["scenarios"] = args.eval_scenarios.split(",")

    def log(line: str) -> None:
        print(line, flush=True)

    if args.cv is not None and (args.resume or args.refit is not None):
        raise CommandError("--cv runs (and resumes) its folds itself; drop --resume and --refit")
    if args.combine is not None and (args.resume or args.refit is not None or args.cv is not None or args.config):
        raise CommandError("--combine takes finished runs as they are; drop --resume, --refit, --cv and --config")
    try:
        if args.combine is not None:
            changes = {"val_seeds": config["val_seeds"]} if args.eval_seeds is not None else {}
            if args.eval_scenarios is not None:
                changes["val_scenarios"] = args.eval_scenarios.split(",")
            out = dagger.combine(args.combine, args.out, teacher, changes, args.disagree, log)
            print(f"DAgger run in {out}; its student: {dagger.load_policy(out).source}")
            return 0
        if args.cv is not None:
            from magenv.agents.dagger_cv import cross_validate

            rows = cross_validate(args.out, teacher, config, args.folds, log)
            ratios = [r["agent_rmse"] / r["rule_rmse"] for r in rows]
            print(
                f"held-out recordings: {len(rows)}, student / rule geometric mean "
                f"{float(np.exp(np.mean(np.log(ratios)))):.3f}, worst {max(ratios):.3f}; {args.out / 'cv.csv'}"
            )
            return 0
        if args.refit is not None:
            out = dagger.refit(args.refit, args.out, teacher, config, log)
        else:
            out = dagger.train(args.out, teacher, config, log=log, env_id=env_id, resume=args.resume)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    print(f"DAgger run in {out}; its student: {dagger.load_policy(out).source}")
    return 0


def run(args: argparse.Namespace) -> int:
    from magenv import registry
    from magenv.agents.hyperparams import ConfigError
    from magenv.agents.loading import WEIGHTS, RunError
    from magenv.agents.training import progress, train

    args.out = output_folder(args.out, "--out")
    if args.teacher is not None:
        return run_dagger(args)
    if args.resume:
        raise CommandError("--resume continues a DAgger run: give its --teacher too")
    if args.refit is not None or args.combine is not None:
        raise CommandError("--refit and --combine take DAgger runs: give their --teacher too")
    args.env = args.env or BLEND_ID
    if args.env not in gym.registry:
        known = ", ".join(k for k in gym.registry if k.startswith("magenv/"))
        raise CommandError(f"unknown env {args.env!r}; magenv envs: {known}")
    scenarios = None if args.eval_scenarios is None else tuple(args.eval_scenarios.split(","))
    try:
        out = train(
            args.env,
            args.algo,
            args.steps,
            args.out,
            args.config,
            args.seed,
            args.eval_every,
            scenarios,
            args.eval_seeds,
            args.n_envs,
            not args.no_progress,
            make_method=registry.make,
            force=args.force,
            trust_pickle=args.trust_pickle,
        )
    except (ConfigError, RunError, ValueError) as exc:
        raise CommandError(str(exc)) from None
    except KeyboardInterrupt:
        return 130
    state = progress(out, args.algo)
    if state is None:
        raise CommandError(f"{out}: training left no checkpoint")
    best = (
        "none yet"
        if state.get("best_timesteps") is None
        else (f"{state['best_score']:.3f}° at {state['best_timesteps']:,} steps -> {out / WEIGHTS['best']}")
    )
    print(f"trained {state['timesteps']:,} steps; best held-out total RMSE {best}")
    return 0
