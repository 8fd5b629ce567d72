"""Peak resident memory (RSS) of a batched vector env of 1024 envs and of one single env's 1-hour episode.

    .venv/bin/python benchmarks/bench_memory.py [--envs 1024] [--steps 200]

Each case runs in its own child process, whose peak RSS (``ru_maxrss``) is printed beside that of two
baselines: a child that only imports magenv (``import``: magenv imports its heavy parts lazily), and a child
that has every part an episode needs loaded (``loaded``: one 2-s trial simulated and a MagBlend episode
stepped on it, so numba with its compiled kernels, MuJoCo and the model are in memory: ~240 MB of code and
compiler before any data). What an episode itself takes is its peak above ``loaded``.

* ``vector``: ``make_vec("magenv/MagBlend-v0", N)`` on the shipped training scenarios with the shipped
  ``trial_pool`` of 32, reset and stepped ``--steps`` times (the store holds the trials in use);
* ``vector_nopool``: the same without the pool (N trials simulated and held);
* ``hour``: ``gym.make("magenv/MagBlend-v0")`` on one 1-hour ``dynamic_magnet`` trial, stepped to its end
  (the single env keeps per-sample histories: ``estimate``, ``lambdas``). Target ≤ 200 MB above ``loaded``:
  the trial's own arrays are ~140 MB (921 600 samples of float64 gyro, accelerometer, magnetometer, truth
  and disturbance), the runner's histories ~60 MB; the simulation streams block by block
  (``magenv.sim.gimbal.gimbal_blocks``), so it adds little on top.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys

SCENARIOS = "dynamic_magnet,dynamic_clean,stationary_magnet"


def run_case(case: str, num_envs: int, steps: int) -> None:
    import gymnasium as gym
    import numpy as np

    import magenv  # noqa: F401

    if case.startswith("vector"):
        pool = {"trial_pool": {"size": 32}} if case == "vector" else {}
        vec = gym.make_vec(
            "magenv/MagBlend-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", scenario=SCENARIOS, **pool
        )
        vec.reset(seed=0)
        actions = np.full((num_envs, 1), 0.5, np.float32)
        for _ in range(steps):
            vec.step(actions)
    elif case in ("hour", "loaded"):
        from magenv.scenarios import make_trial

        duration = 3600.0 if case == "hour" else 2.0
        env = gym.make("magenv/MagBlend-v0", scenario=[make_trial("dynamic_magnet", 0, duration=duration)])
        env.reset(seed=0)
        done = False
        while not done:
            *_, term, trunc, _ = env.step(np.array([0.5], np.float32))
            done = term or trunc
    elif case != "import":
        raise ValueError(f"unknown case {case!r}")
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)  # kB → MB (Linux)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--case", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.case:
        run_case(args.case, args.envs, args.steps)
        return
    peak = {}
    for case in ("import", "loaded", "vector", "vector_nopool", "hour"):
        cmd = [sys.executable, __file__, "--case", case, "--envs", str(args.envs), "--steps", str(args.steps)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split()
        peak[case] = float(out[-1])
        extra = "" if case == "import" else f"  ({peak[case] - peak['import']:7.0f} MB above the import"
        extra += "" if case in ("import", "loaded") else f", {peak[case] - peak['loaded']:7.0f} MB above loaded"
        print(f"{case:14s} peak RSS {peak[case]:7.0f} MB{extra}{')' if extra else ''}", flush=True)
    print(
        f"1-hour episode: {peak['hour']:.0f} MB peak, {peak['hour'] - peak['loaded']:.0f} MB above loaded "
        "(target <= 200 MB above loaded)"
    )


if __name__ == "__main__":
    main()
