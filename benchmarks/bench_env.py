"""Steps per second of ``magenv/MagBlend-v0`` and ``MagKalman-v0`` through the Gymnasium API, next to CartPole-v1.

    .venv/bin/python benchmarks/bench_env.py [--steps 50000] [--every 8]

Both envs are made with ``gymnasium.make`` (default wrappers), stepped with a
fixed action, and reset when an episode ends; resets are included in the
time; each rate is the median of 3 runs. MagBlend is measured on one pre-made trial (the cost of ``step`` itself),
on the default ``random`` scenario (each reset simulates a new 60-s trial,
which dominates), the same with ``prefetch=True`` (the next trial made in a
worker process meanwhile), with ``trial_pool={"size": 4, "reuse": 16}`` (16 resets in a row draw from the same 4
seeded trials, so at most 4 simulations per 16 episodes), and as the 8-env ``vector_entry_point`` VectorEnv.
Target: at least half of CartPole's rate with the ``random`` scenario. The first three rates are also given per
CPU second of this process, with their ratio: on a shared machine the wall rates swing with the load, the CPU
ratio much less. Beside them, what a ``random`` reset costs in CPU time (and how much of that is MuJoCo's
physics) against the CPU time 0.5x CartPole allows a whole episode.
MagKalman is measured on the same pre-made trial. Last, the env kernels alone (``BlendRunner``,
``KalmanRunner``) over that one trial, k samples per call and the whole trial in one call: the
best of several runs in CPU time (robust on a shared machine).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import magenv  # noqa: F401  (registers the env)


def rate(env, actions, steps: int, seed: int = 0, repeats: int = 3) -> tuple[float, float]:
    """Medians over ``repeats`` of steps per second over ``steps`` steps, resets included (after a warm-up):
    per second of wall time, and per CPU second of this process (robust on a shared machine; without the
    work of other processes, such as a prefetch worker's).

    ``actions`` is a list cycled through (two entries: alternate them).
    """
    env.reset(seed=seed)
    for i in range(200):  # warm-up: JIT caches, first-step checker
        *_, term, trunc, _ = env.step(actions[i % 2 % len(actions)])
        if term or trunc:
            env.reset()
    rates, cpu_rates = [], []
    na = len(actions)
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(steps):
            *_, term, trunc, _ = env.step(actions[i % na])
            if term or trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - t0))
        cpu_rates.append(steps / (time.process_time() - c0))
    return float(np.median(rates)), float(np.median(cpu_rates))


def kernel_time(runner_class, trial, k: int, repeats: int) -> float:
    """Best CPU time (s) over ``repeats`` to build a runner on ``trial`` and step it to the end, k samples a call."""
    best = np.inf
    for _ in range(repeats + 1):  # the first run compiles or loads the kernels
        t0 = time.process_time()
        runner = runner_class(trial)
        while not runner.done:
            runner.advance(k, 0.5)
        best = min(best, time.process_time() - t0)
    return best


def reset_cost(every: int, resets: int = 20) -> tuple[float, float, int]:
    """Mean CPU time (s) of a ``random`` reset of ``MagBlend-v0``, the part of it in MuJoCo's rollouts
    (``magenv.sim.gimbal.rollout_sensors``: the physics), and the steps of its episodes (a 60-s trial at
    k = ``every``)."""
    from magenv.sim import gimbal

    spent = [0.0]
    rollout = gimbal.rollout_sensors

    def timed(*a, **kw):
        t = time.process_time()
        try:
            return rollout(*a, **kw)
        finally:
            spent[0] += time.process_time() - t

    env = gym.make("magenv/MagBlend-v0", decision_every=every)
    env.reset(seed=1)
    gimbal.rollout_sensors = timed
    try:
        t0 = time.process_time()
        for _ in range(resets):
            _, info = env.reset()
        total = time.process_time() - t0
    finally:
        gimbal.rollout_sensors = rollout
    return total / resets, spent[0] / resets, -(-info["n_samples"] // every)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--every", type=int, default=8, help="MagBlend decision interval k (samples per step)")
    args = p.parse_args()

    from magenv.scenarios import make_trial

    # CartPole: alternating pushes keep the pole up for long episodes, so its
    # rate is mostly step cost (the stricter comparison; a constant push
    # ends an episode every ~10 steps and resets slow it down).
    cart, cart_cpu = rate(gym.make("CartPole-v1"), [0, 1], args.steps)
    lam = [np.array([0.5], np.float32)]
    fixed, fixed_cpu = rate(
        gym.make("magenv/MagBlend-v0", scenario=[make_trial("dynamic_magnet", 0)], decision_every=args.every),
        lam,
        args.steps,
    )
    rand, rand_cpu = rate(gym.make("magenv/MagBlend-v0", decision_every=args.every), lam, args.steps)
    reset_s, physics_s, episode_steps = reset_cost(args.every)
    print(f"CartPole-v1                                   {cart:10.0f} steps/s  ({cart_cpu:.0f} per CPU-s)")
    print(
        f"MagBlend-v0 k={args.every}, one trial (step cost)      {fixed:10.0f} steps/s  "
        f"ratio {fixed / cart:.2f}  ({fixed * args.every:.0f} samples/s; per CPU-s {fixed_cpu:.0f}, "
        f"ratio {fixed_cpu / cart_cpu:.2f})"
    )
    print(
        f"MagBlend-v0 k={args.every}, scenario 'random' + resets {rand:10.0f} steps/s  ratio {rand / cart:.2f}  "
        f"(per CPU-s {rand_cpu:.0f}, ratio {rand_cpu / cart_cpu:.2f}; target >= 0.5)"
    )
    budget = episode_steps / (0.5 * cart_cpu)
    print(
        f"  CPU time: a 'random' reset {reset_s * 1e3:.1f} ms, of which MuJoCo's rollouts {physics_s * 1e3:.1f} ms; "
        f"its {episode_steps} steps at the one-trial step cost {episode_steps / fixed_cpu * 1e3:.1f} ms; 0.5x "
        f"CartPole allows {budget * 1e3:.1f} ms per episode in all"
    )
    env = gym.make("magenv/MagBlend-v0", decision_every=args.every, prefetch=True)
    ahead = rate(env, lam, args.steps)[0]
    env.close()
    print(f"MagBlend-v0 k={args.every}, 'random', prefetch=True  {ahead:10.0f} steps/s  ratio {ahead / cart:.2f}")
    pool = {"size": 4, "reuse": 16}
    pooled = rate(gym.make("magenv/MagBlend-v0", decision_every=args.every, trial_pool=pool), lam, args.steps)[0]
    print(f"MagBlend-v0 k={args.every}, 'random', pool 4 × 16 uses {pooled:10.0f} steps/s  ratio {pooled / cart:.2f}")
    vec = gym.make_vec(
        "magenv/MagBlend-v0",
        num_envs=8,
        vectorization_mode="vector_entry_point",
        scenario=[make_trial("dynamic_magnet", 0)],
        decision_every=args.every,
    )
    acts = np.full((8, 1), 0.5, np.float32)
    vec.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(args.steps // 8):
        vec.step(acts)
    vrate = 8 * (args.steps // 8) / (time.perf_counter() - t0)
    print(
        f"MagBlend-v0 k={args.every}, make_vec 8 envs, one trial   {vrate:10.0f} env-steps/s  ratio {vrate / cart:.2f}"
    )
    kal, _ = rate(
        gym.make("magenv/MagKalman-v0", scenario=[make_trial("dynamic_magnet", 0)], decision_every=args.every),
        lam,
        args.steps // 10,
    )
    print(
        f"MagKalman-v0 k={args.every}, one trial (step cost)    {kal:10.0f} steps/s  "
        f"ratio {kal / cart:.2f}  ({kal * args.every:.0f} samples/s)"
    )

    from magenv.envs.blend import BlendRunner
    from magenv.envs.kalman import KalmanRunner

    trial = make_trial("dynamic_magnet", 0)
    for name, runner_class, repeats in (("blend", BlendRunner, 20), ("kalman", KalmanRunner, 5)):
        for k in (args.every, trial.n):
            t = kernel_time(runner_class, trial, k, repeats)
            print(
                f"{name} kernel, one trial of {trial.n} samples, k={k:<6d} {t * 1e3:8.2f} ms CPU  "
                f"({t / trial.n * 1e9:6.0f} ns/sample)"
            )


if __name__ == "__main__":
    main()
