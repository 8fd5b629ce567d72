"""Steps per second of ``magenv/MagBlend-v0`` through the Gymnasium API, next to CartPole-v1.

    .venv/bin/python benchmarks/bench_env.py [--steps 50000] [--every 8]

Both envs are made with ``gymnasium.make`` (default wrappers), stepped with a
fixed action, and reset when an episode ends; resets are included in the
time; each rate is the median of 3 runs. MagBlend is measured on one pre-made trial (the cost of ``step`` itself),
on the default ``random`` scenario (each reset simulates a new 60-s trial,
which dominates), the same with ``prefetch=True`` (the next trial made in a
worker process meanwhile), and as the 8-env ``vector_entry_point`` VectorEnv. Target: at least half of CartPole's rate.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import magenv  # noqa: F401  (registers the env)


def rate(env, actions, steps: int, seed: int = 0, repeats: int = 3) -> float:
    """Median over ``repeats`` of steps per second over ``steps`` steps, resets included (after a warm-up).

    ``actions`` is a list cycled through (two entries: alternate them).
    """
    env.reset(seed=seed)
    for i in range(200):  # warm-up: JIT caches, first-step checker
        *_, term, trunc, _ = env.step(actions[i % 2 % len(actions)])
        if term or trunc:
            env.reset()
    rates = []
    na = len(actions)
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(steps):
            *_, term, trunc, _ = env.step(actions[i % na])
            if term or trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - t0))
    return float(np.median(rates))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--every", type=int, default=8, help="MagBlend decision interval k (samples per step)")
    args = p.parse_args()

    from magenv.scenarios import make_trial

    # CartPole: alternating pushes keep the pole up for long episodes, so its
    # rate is mostly step cost (the stricter comparison; a constant push
    # ends an episode every ~10 steps and resets slow it down).
    cart = rate(gym.make("CartPole-v1"), [0, 1], args.steps)
    lam = [np.array([0.5], np.float32)]
    fixed = rate(gym.make("magenv/MagBlend-v0", scenario=[make_trial("dynamic_magnet", 0)],
                          decision_every=args.every), lam, args.steps)
    rand = rate(gym.make("magenv/MagBlend-v0", decision_every=args.every), lam, args.steps)
    print(f"CartPole-v1                                   {cart:10.0f} steps/s")
    print(f"MagBlend-v0 k={args.every}, one trial (step cost)      {fixed:10.0f} steps/s  "
          f"ratio {fixed / cart:.2f}  ({fixed * args.every:.0f} samples/s)")
    print(f"MagBlend-v0 k={args.every}, scenario 'random' + resets {rand:10.0f} steps/s  ratio {rand / cart:.2f}")
    env = gym.make("magenv/MagBlend-v0", decision_every=args.every, prefetch=True)
    ahead = rate(env, lam, args.steps)
    env.close()
    print(f"MagBlend-v0 k={args.every}, 'random', prefetch=True  {ahead:10.0f} steps/s  ratio {ahead / cart:.2f}")
    vec = gym.make_vec("magenv/MagBlend-v0", num_envs=8, vectorization_mode="vector_entry_point",
                       scenario=[make_trial("dynamic_magnet", 0)], decision_every=args.every)
    acts = np.full((8, 1), 0.5, np.float32)
    vec.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(args.steps // 8):
        vec.step(acts)
    vrate = 8 * (args.steps // 8) / (time.perf_counter() - t0)
    print(f"MagBlend-v0 k={args.every}, make_vec 8 envs, one trial   {vrate:10.0f} env-steps/s  ratio {vrate / cart:.2f}")


if __name__ == "__main__":
    main()
