"""``magenv train``: train an SB3 agent on a magenv environment (the engine: ``magenv.agents.training``).

    magenv train --env magenv/MagBlend-v0 --algo ppo --steps 100000 --out runs/NAME \
        [--config FILE] [--seed S] [--eval-every N] [--eval-scenarios A,B] [--eval-seeds 0:3]

Progress bar, TensorBoard logs (``runs/NAME/tb``), periodic evaluation on
held-out trials with the best model kept, checkpoints, and resume: running
the same command again on an existing run folder continues from its last
checkpoint up to ``--steps`` in all (Ctrl-C saves a checkpoint first).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym

from magenv.envs import BLEND_ID
from magenv.seeding import VALIDATION_START
from magenv.train.cli import CommandError
from magenv.train.seeds import parse_seeds


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default=BLEND_ID, help="environment id (default %(default)s)")
    p.add_argument("--algo", default="ppo", help="ppo, sac or recurrent_ppo (default %(default)s)")
    p.add_argument("--steps", type=int, default=None, help="total environment steps (default: the config's n_timesteps)")
    p.add_argument("--out", required=True, type=Path, help="run folder (created, or resumed if it exists)")
    p.add_argument("--config", default=None, help="YAML hyperparameter file (default agents/configs/ALGO.yaml)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--n-envs", type=int, default=None, help="parallel environments (default: the config's)")
    p.add_argument("--eval-every", type=int, default=10_000, help="steps between held-out evaluations")
    p.add_argument("--eval-scenarios", default="dynamic_magnet,dynamic_clean")
    p.add_argument("--eval-seeds", default=f"{VALIDATION_START}:{VALIDATION_START + 2}",
                   help="held-out validation seeds for model selection, e.g. 5000:5004 (default %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from magenv import registry
    from magenv.agents.hyperparams import ConfigError
    from magenv.agents.loading import RunError
    from magenv.agents.training import STATE_FILE, train

    if args.env not in gym.registry:
        known = ", ".join(k for k in gym.registry if k.startswith("magenv/"))
        raise CommandError(f"unknown env {args.env!r}; magenv envs: {known}")
    try:
        out = train(args.env, args.algo, args.steps, args.out, args.config, args.seed, args.eval_every,
                    tuple(args.eval_scenarios.split(",")), tuple(parse_seeds(args.eval_seeds)),
                    args.n_envs, not args.no_progress, make_method=registry.make)
    except (ConfigError, RunError, ValueError) as exc:
        raise CommandError(str(exc)) from None
    except KeyboardInterrupt:
        return 130
    state = json.loads((out / STATE_FILE).read_text())
    print(f"trained {state['timesteps']} steps; best held-out total RMSE {state['best_score']:.3f}° "
          f"at {state['best_timesteps']} steps -> {out / 'best_model.zip'}")
    return 0
