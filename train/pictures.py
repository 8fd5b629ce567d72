"""``magenv pictures``: the README's pictures, made from one held-out gimbal trial.

    magenv pictures [--out docs/img] [--scenario dynamic_magnet] [--seed 0] [--method fan_lambda_tuned]
                    [--agent runs/NAME]

Writes ``OUT/frame.png``, a rendered frame of ``MagBlend-v0`` (``render_mode="rgb_array"``) at the sample of
the largest magnetic disturbance with ``--method`` choosing the trust, and ``OUT/trust.png``, the total
error and the magnetometer trust over the trial of ``mimu``, ``imu``, ``--method``, the privileged ``oracle``
(an upper bound: it reads truth) and the agent of ``--agent``, if given, against the true disturbance. PNGs are
saved with a 64-colour palette (small files).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from magenv.train.cli import CommandError, output_folder

PALETTE_COLOURS = 64


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("docs/img"), help="folder of the PNGs (default %(default)s)")
    p.add_argument("--scenario", default="dynamic_magnet", help="gimbal scenario (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="trial seed, below 5000: a reported figure (default 0)")
    p.add_argument("--method", default="fan_lambda_tuned", help="rule policy drawn in the frame (default %(default)s)")
    p.add_argument("--agent", default=None, metavar="RUN_DIR", help="also plot a trained agent's trust")


def save_small_png(image: np.ndarray, path: Path) -> Path:
    """Save an (H, W, 3|4) uint8 image as a palette PNG of ``PALETTE_COLOURS`` colours."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image[..., :3])).quantize(PALETTE_COLOURS).save(path, optimize=True)
    return path


def frame_at_peak(policy, trial) -> np.ndarray:
    """The rendered frame of ``policy``'s env on ``trial`` after the step that fuses the sample of the largest
    true disturbance."""
    import gymnasium as gym

    import magenv  # noqa: F401  (registers the envs)

    dist = np.linalg.norm(np.asarray(trial.truth.get("mag_disturbance", np.zeros((trial.n, 3))), float), axis=1)
    peak = int(np.argmax(dist))
    env = gym.make(policy.env_id, render_mode="rgb_array", scenario=[trial], **getattr(policy, "env_kwargs", {}))
    policy.reset()
    obs, info = env.reset(seed=0, options={"trial": trial})
    while info["sample"] <= peak:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        if terminated or truncated:
            break
    frame = np.asarray(env.render())
    env.close()
    return frame


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation, registry
    from magenv.scenarios import make_trial, scenario_names
    from magenv.train.report import _plot_trial

    args.out = output_folder(args.out, "--out")
    if args.scenario not in scenario_names("gimbal"):
        raise CommandError(f"--scenario must be a gimbal scenario: {', '.join(scenario_names('gimbal'))}")
    trial = make_trial(args.scenario, args.seed)
    try:
        rule = registry.make(args.method)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    if not hasattr(rule, "env_id"):
        raise CommandError(f"--method must be a policy (a rule that acts in an env), got estimator {args.method!r}")
    frame = frame_at_peak(rule, trial)
    print(f"wrote {save_small_png(frame, args.out / 'frame.png')}")

    methods = {n: registry.make(n) for n in ("mimu", "imu", args.method, "oracle")}
    if args.agent:
        methods["agent"] = registry.make(f"{registry.AGENT_PREFIX}{args.agent}")
    runs = evaluation.evaluate(methods, [trial])
    tmp = args.out / "trust.full.png"
    _plot_trial(runs, tmp)
    from PIL import Image

    image = np.asarray(Image.open(tmp).convert("RGB"))
    tmp.unlink()
    print(f"wrote {save_small_png(image, args.out / 'trust.png')}")
    return 0
