"""Env-steps per second of the batched vector envs against their bare kernel and CartPole's vector env.

    .venv/bin/python benchmarks/bench_vector.py [--envs 1,16,256,1024] [--every 8] [--ids blend,kalman]

For each N: the env's ``vector_entry_point`` (``gymnasium.make_vec(…, vectorization_mode="vector_entry_point")``)
on one pre-made 60-s ``dynamic_magnet`` trial, stepped with a fixed action within its first episode (about
60 k env-steps per timing; ``step`` as a policy calls it: action checks, rewards, ``infos``); the **bare
kernel limit**: the same compiled batch kernel on the same arrays and samples, called in a loop with nothing
around it (no env, no checks, no rewards or infos); and ``CartPole-v1``'s own vector env at the same N.
Ratios are of rates measured in this run, interleaved; each rate is the best of 3 (robust on a shared
machine). Target: vector env ≥ 0.6 of the kernel limit at N ≥ 256. ``--parallel`` measures the threaded
kernel (``prange`` over the envs, the env's ``parallel=True``) instead of the default serial one.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID, KALMAN_ID

IDS = {"blend": BLEND_ID, "kalman": KALMAN_ID}
TARGET_ENV_STEPS = 60_000  # env-steps per timing


def best_rates(*runs, repeats: int = 3) -> list[float]:
    """Best env-steps/s of each ``run()`` → (env-steps, seconds) over ``repeats``, the runs interleaved (so that
    a load on the machine meets them alike); after one warm-up run each (kernels compiled, first-call checks)."""
    rates = [[] for _ in runs]
    for repeat in range(repeats + 1):
        for run, got in zip(runs, rates):
            steps, secs = run()
            if repeat:
                got.append(steps / secs)
    return [max(r) for r in rates]


def magenv_rates(env_id: str, trial, num_envs: int, k: int, parallel: bool) -> tuple[float, float]:
    """(vector env, bare kernel) env-steps/s of ``num_envs`` envs of ``env_id`` on ``trial``."""
    vec = gym.make_vec(
        env_id,
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        scenario=[trial],
        decision_every=k,
        parallel=parallel,
    )
    venv = vec.unwrapped
    dim = venv.single_action_space.shape[0]
    actions = np.full((num_envs, dim), 0.5, np.float32)
    steps = min((trial.n - venv.first) // k - 2, -(-TARGET_ENV_STEPS // num_envs))  # within one episode
    rounds = -(-TARGET_ENV_STEPS // (num_envs * steps))

    def env_loop():
        secs = 0.0
        for _ in range(rounds):
            vec.reset(seed=0)
            t0 = time.perf_counter()
            for _ in range(steps):
                vec.step(actions)
            secs += time.perf_counter() - t0
        return rounds * steps * num_envs, secs

    def kernel_loop():
        secs = 0.0
        stepping = np.ones(num_envs, bool)
        for _ in range(rounds):
            vec.reset(seed=0)  # made the kernel's argument tuple and compiled entry point
            venv._set_actions(actions.astype(np.float64), stepping)
            todo, run, args = venv.todo, venv._entry, venv._args
            t0 = time.perf_counter()
            for _ in range(steps):
                todo[:] = k
                run(args)
            secs += time.perf_counter() - t0
        return rounds * steps * num_envs, secs

    rates = best_rates(env_loop, kernel_loop)
    vec.close()
    return rates[0], rates[1]


def cartpole_rate(num_envs: int, steps: int) -> float:
    """Env-steps/s of ``gymnasium.make_vec("CartPole-v1", num_envs)`` (its vector_entry_point), alternating pushes."""
    vec = gym.make_vec("CartPole-v1", num_envs=num_envs, vectorization_mode="vector_entry_point")
    pushes = [np.zeros(num_envs, np.int64), np.ones(num_envs, np.int64)]
    rounds = max(1, -(-TARGET_ENV_STEPS // (num_envs * steps)))

    def loop():
        vec.reset(seed=0)
        t0 = time.perf_counter()
        for i in range(rounds * steps):
            vec.step(pushes[i % 2])
        return rounds * steps * num_envs, time.perf_counter() - t0

    (rate,) = best_rates(loop)
    vec.close()
    return rate


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", default="1,16,256,1024", help="comma-separated N")
    p.add_argument("--every", type=int, default=8, help="decision interval k (samples per step)")
    p.add_argument("--ids", default="blend,kalman", help=f"envs among {', '.join(IDS)}")
    p.add_argument("--parallel", action="store_true", help="the threaded kernels (numba prange over the envs)")
    args = p.parse_args()
    sizes = [int(n) for n in args.envs.split(",")]
    ids = [IDS[name] for name in args.ids.split(",")]

    import numba

    from magenv.scenarios import make_trial

    trial = make_trial("dynamic_magnet", 0)
    threads = f"threaded kernel, {numba.get_num_threads()} numba threads" if args.parallel else "serial kernel"
    print(f"one {trial.duration:.0f}-s dynamic_magnet trial, k = {args.every}, {threads}")
    head = ("vector env", "kernel", "ratio", "CartPole vec", "ratio")
    print(f"{'env':14s} {'N':>5s} " + " ".join(f"{h:>{w}s}" for h, w in zip(head, (12, 12, 6, 13, 6))))
    for env_id in ids:
        for n in sizes:
            vec_rate, limit = magenv_rates(env_id, trial, n, args.every, args.parallel)
            cart = cartpole_rate(n, min(trial.n // args.every - 2, -(-TARGET_ENV_STEPS // n)))
            print(
                f"{env_id.split('/')[-1]:14s} {n:5d} {vec_rate:12.0f} {limit:12.0f} {vec_rate / limit:6.2f} "
                f"{cart:13.0f} {vec_rate / cart:6.2f}"
            )
    print("env-steps/s; ratio = vector env / kernel limit (target >= 0.6 at N >= 256), vector env / CartPole")


if __name__ == "__main__":
    main()
