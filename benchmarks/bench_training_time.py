"""Where PPO training time goes on ``MagBlend-v0``: CPU seconds in env stepping, the rest of rollout
collection (policy calls, the rollout buffer, VecNormalize, callbacks) and the gradient steps.

    .venv/bin/python benchmarks/bench_training_time.py [--steps 81920] [--config CONFIG]

Trains a throw-away run (``magenv.agents.training.train``, no held-out evaluations) with the shipped config
(or ``--config``) and times ``BatchVecEnv.step_wait``, ``collect_rollouts`` and ``PPO.train`` in CPU time
(robust on a shared machine) and wall time; prints each part and the env-steps per CPU-second of the two
learning phases together (set-up excluded), the rate one free core gives.
"""

from __future__ import annotations

import argparse
import collections
import shutil
import tempfile
import time
from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

import magenv  # noqa: F401
from magenv import registry
from magenv.agents import training, vec_env

ENV_ID = "magenv/MagBlend-v0"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=81_920)
    p.add_argument("--config", default=None, help="config file (default: the shipped one)")
    args = p.parse_args()
    cpu: dict = collections.defaultdict(float)
    wall: dict = collections.defaultdict(float)

    def timed(cls, name: str, key: str) -> None:
        f = getattr(cls, name)

        def g(*a, **kw):
            c, w = time.process_time(), time.perf_counter()
            try:
                return f(*a, **kw)
            finally:
                cpu[key] += time.process_time() - c
                wall[key] += time.perf_counter() - w

        setattr(cls, name, g)

    timed(vec_env.BatchVecEnv, "step_wait", "env")
    timed(OnPolicyAlgorithm, "collect_rollouts", "collect")
    timed(PPO, "train", "grad")
    out = tempfile.mkdtemp(prefix="bench_training_time_")
    try:
        training.train(
            ENV_ID,
            "ppo",
            args.steps,
            Path(out) / "run",
            config=args.config,
            eval_every=10**12,
            progress_bar=False,
            make_method=registry.make,
            eval_scenarios=["dynamic_magnet"],
            eval_seeds=[5000],
        )
    finally:
        shutil.rmtree(out, ignore_errors=True)
    learn = cpu["collect"] + cpu["grad"]
    print(
        f"CPU s: env {cpu['env']:.1f}, rest of rollout collection {cpu['collect'] - cpu['env']:.1f}, "
        f"gradient steps {cpu['grad']:.1f} ({cpu['grad'] / learn:.0%} of learning)"
    )
    print(
        f"{args.steps / learn:.0f} env-steps per CPU-second; wall {wall['collect'] + wall['grad']:.1f} s, "
        f"{args.steps / (wall['collect'] + wall['grad']):.0f} env-steps/s under this machine's load"
    )


if __name__ == "__main__":
    main()
