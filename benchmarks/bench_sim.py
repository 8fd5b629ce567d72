"""Time to make one trial, per scenario (the cost of an environment reset).

    .venv/bin/python benchmarks/bench_sim.py [--seeds 20] [--duration 60]

Prints, per scenario, the median and mean wall time per trial over fresh
seeds (after one warm-up trial that loads the model and numba caches), the
mean CPU time of this process per trial (what one core spends; robust when
other jobs share the machine), trials per second (wall) and the MuJoCo steps
taken. Target (issue 2): ≤ 50 ms amortized per 60 s trial at 256 Hz on one
core, for the training family ``random`` (the survey scenarios are not made
at training resets).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

TARGET_MS = 50.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="trials per scenario (default 20)")
    parser.add_argument("--duration", type=float, default=60.0, help="trial length, s (default 60)")
    parser.add_argument(
        "--scenarios",
        nargs="*",
        default=None,
        help="scenario names (default: the gimbal's; other worlds' can be named)",
    )
    args = parser.parse_args()

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from magenv import scenarios

    names = args.scenarios or scenarios.scenario_names("gimbal")
    print(
        f"{'scenario':20s} {'median ms':>10s} {'mean ms':>9s} {'CPU ms':>7s} {'trials/s':>9s} "
        f"{'steps':>7s} {'samples':>8s}"
    )
    for name in names:
        scenarios.make_trial(name, 10_000, duration=args.duration)  # warm-up
        times, cpu, steps = [], [], []
        for seed in range(args.seeds):
            t0, c0 = time.perf_counter(), time.process_time()
            tr = scenarios.make_trial(name, seed, duration=args.duration)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            steps.append(tr.meta.get("physics_steps", float("nan")))
        med, mean, mcpu = 1e3 * statistics.median(times), 1e3 * statistics.mean(times), 1e3 * statistics.mean(cpu)
        flag = "" if mcpu <= TARGET_MS else f"  (CPU over the {TARGET_MS:.0f} ms target)"
        print(
            f"{name:20s} {med:10.1f} {mean:9.1f} {mcpu:7.1f} {1e3 / mean:9.1f} "
            f"{statistics.mean(steps):7.0f} {tr.n:8d}{flag}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
