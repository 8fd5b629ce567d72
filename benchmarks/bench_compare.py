"""Distributed evaluation: ``magenv compare``'s cells on one process, on 1 Ray worker and on 2, in one run.

    .venv/bin/python benchmarks/bench_compare.py [--seeds 48] [--methods mimu,fan_lambda_tuned,kf_gate,th_triad]

Every method on ``--seeds`` trials of ``dynamic_magnet`` (seeds 0, 1, …):
first serially in this process (``magenv.evaluation.evaluate``, the trials
simulated inside the timing, as the workers do), then with
``magenv.scale.evaluate`` on one local Ray of 2 CPUs with 1 and with 2
workers (each call starts its own actors, so their start-up and imports
are in its time; one cell on a fresh worker shows that cost alone). It
prints each wall time (and the serial run's CPU time), the speed-up of 2
workers over 1 and over the serial run, and checks that the three give the
same scores. Nothing here is a pass/fail test; the machine's load average
is printed, because on cores that others share the speed-up shows their
load as well.
"""

from __future__ import annotations

import argparse
import os
import time

from magenv import evaluation, registry, scale


def scores(runs: list[evaluation.Run]) -> list:
    return [(r.method, r.label, r.error, None if r.score is None else r.score.total) for r in runs]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=48, help="dynamic_magnet trials, seeds 0.. (default %(default)s)")
    p.add_argument("--methods", default="mimu,fan_lambda_tuned,kf_gate,th_triad", help="comma list of methods")
    args = p.parse_args()
    names = args.methods.split(",")
    specs = [scale.TrialSpec("dynamic_magnet", s) for s in range(args.seeds)]
    labels = [s.scenario for s in specs]
    builds = {n: n for n in names}

    evaluation.evaluate({n: registry.make(n) for n in names}, [specs[0].make()], None, labels[:1])  # JIT warm-up
    load_before = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    serial = evaluation.evaluate({n: registry.make(n) for n in names}, [s.make() for s in specs], None, labels)
    wall = {"serial": time.perf_counter() - t0}
    serial_cpu = time.process_time() - c0

    t0 = time.perf_counter()
    scale.start(num_cpus=2)
    ray_up = time.perf_counter() - t0
    t0 = time.perf_counter()
    scale.evaluate({names[0]: names[0]}, specs[:1], labels[:1], workers=1, keep=())
    first_cell = time.perf_counter() - t0
    spread = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        spread[workers] = scale.evaluate(builds, specs, labels, workers=workers, keep=())
        wall[workers] = time.perf_counter() - t0
    scale.stop(True)

    load = os.getloadavg()
    same = all(scores(spread[w]) == scores(serial) for w in (1, 2))
    print(f"{len(names)} methods × {len(specs)} trials of dynamic_magnet ({len(names) * len(specs)} cells)")
    print(f"load average (1 min) before: {load_before[0]:.2f}, after: {load[0]:.2f}, on {os.cpu_count()} cores")
    print(f"Ray start-up (local, 2 CPUs): {ray_up:.1f} s; one cell on a fresh worker: {first_cell:.1f} s")
    print(
        f"  serial, one process: {wall['serial']:.1f} s ({serial_cpu:.1f} s CPU; "
        f"{1e3 * wall['serial'] / len(serial):.0f} ms a cell)"
    )
    for w in (1, 2):
        print(f"  {w} Ray worker(s):     {wall[w]:.1f} s")
    over = wall["serial"] / wall[2]
    print(f"speed-up of 2 workers over 1: {wall[1] / wall[2]:.2f}×; over the serial run: {over:.2f}×")
    print(f"Ray's cost with 1 worker over the serial run: {wall[1] - wall['serial']:.1f} s")
    print(f"scores identical to the serial run: {same}")


if __name__ == "__main__":
    main()
