"""Sweep scaling: the same ``magenv sweep`` with 1 and with 2 workers, and Ray's cost per run.

    .venv/bin/python benchmarks/bench_sweep.py [--runs 4] [--steps 8192] [--out runs/bench_sweep]

One local Ray of 2 CPUs runs a sweep of ``--runs`` training seeds of PPO on
``MagBlend-v0`` (the shipped config: 4 envs, rollouts of 2 048 steps;
``--steps`` each, held-out evaluation at the end, then scored with
``fan_lambda_tuned`` on two report trials) twice into fresh folders: with
``--workers 1`` and with ``--workers 2``. It prints, measured in this run:

* the Ray start-up;
* each sweep's wall time and the speed-up of 2 workers over 1;
* the time the runs spent inside ``magenv.train.sweep.run_trial`` (training
  and scoring), and, with one worker, the rest of the wall time per run:
  what Ray Tune costs per trial (scheduling, a worker's start-up and imports
  once, results), the figure that ``docs/SCALE.md`` scales from.

Nothing here is a pass/fail test; on a machine whose cores others share,
the speed-up shows that too (the load average is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import yaml

from magenv import scale
from magenv.train.cli import main as cli

ENV_ID = "magenv/MagBlend-v0"


def sweep_file(path: Path, runs: int, steps: int) -> Path:
    search = {
        "seeds": f"0:{runs}",
        "steps": steps,
        "eval_every": steps,
        "report": {"scenarios": ["dynamic_magnet", "dynamic_clean"], "seeds": [0]},
    }
    path.write_text(yaml.safe_dump({ENV_ID: {}, "search": search}))
    return path


def one_sweep(config: Path, out: Path, workers: int) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    status = cli(["sweep", str(config), "--out", str(out), "--workers", str(workers)])
    wall = time.perf_counter() - t0
    records = [json.loads(p.read_text()) for p in (out / "results").glob("*.json")]
    inside = sum(r["train_s"] + r["eval_s"] for r in records)
    return {"status": status, "wall": wall, "inside": inside, "runs": len(records)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=4, help="training seeds (runs) per sweep (default %(default)s)")
    p.add_argument("--steps", type=int, default=8192, help="steps per run (default %(default)s)")
    p.add_argument("--out", type=Path, default=Path("runs/bench_sweep"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    config = sweep_file(args.out / "sweep.yaml", args.runs, args.steps)
    t0 = time.perf_counter()
    scale.start(num_cpus=2)
    ray_up = time.perf_counter() - t0
    results = {w: one_sweep(config, args.out / f"workers{w}", w) for w in (1, 2)}
    load = os.getloadavg()
    print(f"\nRay start-up (local, 2 CPUs): {ray_up:.1f} s; load average after: {load[0]:.2f} {load[1]:.2f}")
    print(f"{args.runs} runs of {args.steps} PPO steps on {ENV_ID}")
    for w, r in results.items():
        print(
            f"  {w} worker(s): wall {r['wall']:.1f} s, inside the runs {r['inside']:.1f} s "
            f"({r['runs']} finished, exit status {r['status']})"
        )
    one, two = results[1], results[2]
    print(f"speed-up of 2 workers over 1: {one['wall'] / two['wall']:.2f}×")
    per_run = (one["wall"] - one["inside"]) / max(one["runs"], 1)
    print(
        f"Ray Tune's cost per run (1 worker: wall minus the time inside the runs, per run): {per_run:.1f} s; "
        f"a run itself: {one['inside'] / max(one['runs'], 1):.1f} s"
    )


if __name__ == "__main__":
    main()
