"""``magenv simulate``: make one simulated trial and write it to HDF5.

magenv simulate --scenario dynamic_magnet --seed 3 --out trial.h5
magenv simulate --scenario random --seed 0 --set duration=20 --set mag_noise_ut=0.3 --out t.h5
"""

from __future__ import annotations

import ast
import time
from pathlib import Path

from magenv.agents.hyperparams import integer
from magenv.train.cli import CommandError, output_file, rule_arg


def add_arguments(parser) -> None:
    parser.add_argument("--scenario", required=True, help="scenario name (see magenv.scenarios.scenario_names())")
    parser.add_argument("--seed", type=rule_arg(integer(0)), default=0, help="random seed, integer ≥ 0 (default 0)")
    parser.add_argument("--out", required=True, type=Path, help="output file, .h5")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scenario or sensor parameter (repeatable), e.g. duration=20",
    )


def parse_overrides(items: list[str]) -> dict:
    """``["duration=20", "pause_s=(1, 2)"]`` → ``{"duration": 20, "pause_s": (1, 2)}``."""
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise CommandError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            value = text.strip()
        out[key.strip()] = value
    return out


def run(args) -> int:
    from magenv import scenarios

    args.out = output_file(args.out, "--out")
    overrides = parse_overrides(args.set)
    if args.scenario not in scenarios.scenario_names():
        raise CommandError(
            f"unknown scenario {args.scenario!r}; known scenarios: {', '.join(scenarios.scenario_names())}"
        )
    t0 = time.perf_counter()
    try:
        trial = scenarios.make_trial(args.scenario, args.seed, **overrides)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    elapsed = time.perf_counter() - t0
    path = trial.save(args.out)
    print(
        f"{trial.name}: {trial.n} samples at {trial.rate:g} Hz ({trial.duration:.1f} s), "
        f"magnet {trial.meta.get('magnet')}, made in {elapsed:.2f} s → {path}"
    )
    return 0
