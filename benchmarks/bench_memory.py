"""Peak resident memory (RSS) of a batched vector env of 1024 envs and of one single env's 1-hour episode.

    .venv/bin/python benchmarks/bench_memory.py [--envs 1024] [--steps 200]

Each case runs in its own child process, whose peak RSS (``ru_maxrss``: code pages of the shared libraries
count, as the kernel counts them) is printed beside that of three baselines, so what each layer adds shows:

* ``import``: a child that only imports magenv (magenv imports its heavy parts lazily);
* ``numba``: one small cached numba kernel of magenv run: numba, LLVM (``libllvmlite.so``'s pages) and
  numba's JIT, the floor of any process that runs a magenv filter;
* ``loaded``: every part an episode needs loaded (one 2-s trial simulated and a MagBlend episode stepped on
  it: MuJoCo, the model and the compiled kernels), before any data of size.

The cases:

* ``vector``: ``make_vec("magenv/MagBlend-v0", N)`` on the shipped training scenarios with the shipped
  ``trial_pool`` of 32, reset and stepped ``--steps`` times (the store holds the trials in use);
* ``vector_nopool``: the same without the pool (N trials simulated and held);
* ``hour``: ``gym.make("magenv/MagBlend-v0")`` on one 1-hour ``dynamic_magnet`` trial, stepped to its end;
  its peak after each stage (the trial made, the reset, the episode) and the bytes of what it holds: the
  trial's arrays (921 600 samples of float64 gyro, accelerometer, magnetometer, truth and disturbance,
  float32 display channels) and the env's per-sample histories (``estimate``, ``lambdas``, stationary
  flags, the disturbance norm of the reward's ``info``). Target: ≤ 200 MB peak in all.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys

SCENARIOS = "dynamic_magnet,dynamic_clean,stationary_magnet"
TARGET_MB = 200.0


def peak_mb() -> float:
    """This process's peak RSS so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB → MB (Linux)


def nbytes_mb(*arrays) -> float:
    return sum(a.nbytes for a in arrays) / 2**20


def run_case(case: str, num_envs: int, steps: int) -> dict:
    """Run ``case``; its peak RSS (``peak``, MB) and, for ``hour``, the peaks after each stage and the sizes."""
    import gymnasium as gym
    import numpy as np

    import magenv  # noqa: F401

    out: dict = {}
    if case == "numba":
        from magenv.sim.rowops import norms

        norms(np.ones((2, 3)))
    elif case.startswith("vector"):
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
        trial = make_trial("dynamic_magnet", 0, duration=duration)
        out["trial made"] = peak_mb()
        env = gym.make("magenv/MagBlend-v0", scenario=[trial])
        env.reset(seed=0)
        out["reset"] = peak_mb()
        done = False
        while not done:
            *_, term, trunc, _ = env.step(np.array([0.5], np.float32))
            done = term or trunc
        out["episode"] = peak_mb()
        runner = env.unwrapped._runner
        out["trial arrays"] = nbytes_mb(trial.gyr, trial.acc, trial.mag, trial.q_true, *trial.truth.values())
        out["histories"] = nbytes_mb(runner.est, runner.lam, runner.out.stationary, runner.truth.dist)
    elif case != "import":
        raise ValueError(f"unknown case {case!r}")
    out["peak"] = peak_mb()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--case", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.envs, args.steps)))
        return
    res = {}
    for case in ("import", "numba", "loaded", "vector", "vector_nopool", "hour"):
        cmd = [sys.executable, __file__, "--case", case, "--envs", str(args.envs), "--steps", str(args.steps)]
        res[case] = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split("\n")[-2])
        peak = res[case]["peak"]
        above = "".join(
            f", {peak - res[base]['peak']:5.0f} above {base}"
            for base in ("import", "numba", "loaded")
            if base in res and base != case
        )
        print(f"{case:14s} peak RSS {peak:6.0f} MB total{above}", flush=True)
    hour, floor = res["hour"], res["loaded"]["peak"]
    print(
        "1-hour episode, peak after: "
        + ", ".join(f"{stage} {hour[stage]:.0f} MB" for stage in ("trial made", "reset", "episode"))
        + f"; it holds the trial's arrays {hour['trial arrays']:.0f} MB and the env's histories "
        f"{hour['histories']:.0f} MB"
    )
    print(
        f"1-hour episode: {hour['peak']:.0f} MB peak in all (target <= {TARGET_MB:.0f} MB: "
        f"{'met' if hour['peak'] <= TARGET_MB else 'missed'}), {hour['peak'] - res['import']['peak']:.0f} MB above the "
        f"import, {hour['peak'] - floor:.0f} MB above loaded; the floor before any data: {floor:.0f} MB "
        f"(numba with LLVM {res['numba']['peak'] - res['import']['peak']:.0f} MB of it)"
    )


if __name__ == "__main__":
    main()
