"""PPO from RLlib (its current API stack: RLModule, Learner, EnvRunner) on ``magenv/MagBlend-v0``, on a local Ray.

    python examples/rllib_ppo.py [--iterations 5] [--env-runners 1] [--cpus 2]

The env goes to RLlib unchanged, by its Gymnasium id with the ``module:``
prefix: ``"magenv:magenv/MagBlend-v0"`` makes Gymnasium import ``magenv``
(which registers the envs) in every process that builds one, RLlib's remote
env runners included, so nothing has to be registered by hand. RLlib builds
its envs with ``gymnasium.make_vec(id, **env_config)``, so ``env_config``
takes the env's own arguments. Needs ``pip install 'magenv[rllib]'``.

Each iteration prints the mean episode return (minus the mean total
orientation error in degrees per decision, summed over an episode); short
runs like this one only show that it trains, not that it beats the rules.
"""

from __future__ import annotations

import argparse
import math

ENV = "magenv:magenv/MagBlend-v0"  # "module:id": Gymnasium imports magenv first, in every worker
ENV_CONFIG = {"scenario": "dynamic_magnet,dynamic_clean", "episode_seconds": 10.0}


def ppo_config(env_runners: int = 1, seed: int = 0, batch: int = 400):
    """RLlib's PPO on MagBlend-v0: ``env_runners`` remote samplers (0: sample in this process), ``batch``
    env steps per iteration, a small MLP; everything on the CPU."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    return (
        PPOConfig()
        .environment(ENV, env_config=ENV_CONFIG)
        .env_runners(num_env_runners=env_runners, num_envs_per_env_runner=1, rollout_fragment_length="auto")
        .learners(num_learners=0)
        .training(train_batch_size_per_learner=batch, minibatch_size=min(128, batch), num_epochs=2, lr=3e-4)
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[64, 64], fcnet_activation="tanh"))
        .debugging(seed=seed)
    )


def train(iterations: int = 5, env_runners: int = 1, seed: int = 0, batch: int = 400, log=print) -> list[dict]:
    """Build the algorithm on the Ray this process is connected to (a local one is started if none) and train
    ``iterations`` times; returns one dict per iteration: env steps sampled so far, episodes, mean return."""
    from magenv.scale import require_ray

    ray = require_ray("examples/rllib_ppo.py", rllib=True)
    started = not ray.is_initialized()
    if started:
        ray.init(include_dashboard=False, log_to_driver=False)
    algo = ppo_config(env_runners, seed, batch).build_algo()
    history = []
    try:
        for i in range(iterations):
            result = algo.train()
            runners = result.get("env_runners", {})
            row = {
                "iteration": i + 1,
                "env_steps": int(runners.get("num_env_steps_sampled_lifetime", 0)),
                "episodes": int(runners.get("num_episodes_lifetime", runners.get("num_episodes", 0))),
                "return_mean": float(runners.get("episode_return_mean", math.nan)),
            }
            history.append(row)
            log(
                f"iteration {row['iteration']}: {row['env_steps']} env steps, {row['episodes']} episodes, "
                f"mean return {row['return_mean']:.1f}"
            )
    finally:
        algo.stop()
        if started:
            ray.shutdown()
    return history


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--env-runners", type=int, default=1)
    p.add_argument("--cpus", type=int, default=None, help="CPUs of the local Ray (default: the machine's)")
    args = p.parse_args(argv)
    from magenv.scale import require_ray

    ray = require_ray("examples/rllib_ppo.py", rllib=True)
    ray.init(num_cpus=args.cpus, include_dashboard=False, log_to_driver=False)
    try:
        train(args.iterations, args.env_runners)
    finally:
        ray.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
