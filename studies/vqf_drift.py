"""MagVQF-v0: does the board world's gyroscope drift as fast as the real one when the magnetometer is not trusted?

    python -m studies.vqf_drift [--scenarios board_clean,board_random] [--trials 16] [--recordings FILE ...] [--twins]

VQF (MagVQF-v0, rejection on) trusts the magnetometer fully (u = 1) through each trial's initial rest and not at all
(u = 0) from the first scored sample on, so its heading then follows the gyroscope alone. Per trial: the heading
drift rate (°/s), the magnitude of the least-squares slope of the earth-frame heading error (q_est ⊗ q_true*, about
earth z) over the scored samples with truth, and that heading error's RMS about its mean (°). Recordings
(default: the shared BROAD ones) beside trials of the board world's scenarios (training seeds from 10 000: a check
of the world, not of a policy); medians per group. ``--twins``: beside each recording, its twin (seed 10 000;
``magenv.scenarios.twin``) as fitted, and without the fitted gyro scale / misalignment K (``gyr_scale=False``):
how much of the drift the twin reproduces, and how much of that K makes. It prints what it measures; nothing here
is a test.
"""

from __future__ import annotations

import argparse

import numpy as np

DECIDE = 32  # decision_every of the shipped MagVQF-v0 student
FIRST_SEED = 10_000  # training seeds


class TrustUntil:
    """u = 1 until sample ``start`` (the trial's initial rest), then u = 0: VQF's heading on the gyro alone."""

    env_id = "magenv/MagVQF-v0"
    env_kwargs = {"rejection": "on", "decision_every": DECIDE}
    name = "gyro_only_after_rest"

    def __init__(self, start: int):
        self.start, self.calls = start, 0

    def reset(self) -> None:
        self.calls = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        u = 1.0 if self.calls * DECIDE < self.start else 0.0
        self.calls += 1
        return np.full(1, u, np.float32)


def drift(trial, runner) -> tuple[float, float]:
    """(|slope| of the heading error °/s, its RMS about its mean °) over the scored samples with truth, gyro only
    after rest."""
    from magenv import metrics

    mask = np.asarray(trial.score_mask, bool)
    q, _, _ = runner.run(TrustUntil(int(np.argmax(mask))), trial)
    qe = metrics.error_quaternion(q, trial.q_true)
    idx = np.flatnonzero(mask & np.isfinite(qe).all(axis=1))
    heading = np.unwrap(2.0 * np.arctan2(qe[idx, 3], qe[idx, 0]))  # about earth z, rad
    heading = np.degrees(heading - np.angle(np.mean(np.exp(1j * heading))))  # about its circular mean
    slope = np.polyfit(idx / trial.rate, heading, 1)[0]
    return abs(float(slope)), float(np.sqrt(np.mean(heading**2)))


def main(argv: list[str] | None = None) -> int:
    from magenv import evaluation
    from magenv.recordings import list_recordings, load_recording
    from magenv.scenarios import make_trial
    from studies.vqf_real import group_of

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenarios", default="board_clean,board_random", help="comma list of simulated scenarios")
    p.add_argument("--trials", type=int, default=16, help="trials per scenario (default %(default)s)")
    p.add_argument("--recordings", nargs="+", default=None, help="recording files (default: the shared BROAD ones)")
    p.add_argument("--twins", action="store_true", help="each recording's twin beside it, with and without K")
    args = p.parse_args(argv)
    runner = evaluation.PolicyRunner()
    groups: dict[str, list[tuple[float, float]]] = {}
    for file in args.recordings or list_recordings():
        trial = load_recording(file)
        row = drift(trial, runner)
        groups.setdefault(f"real {group_of(trial.name)}", []).append(row)
        twins = ""
        if args.twins:
            twin = f"twin:{file}"
            both = [drift(make_trial(twin, FIRST_SEED, gyr_scale=k), runner)[0] for k in (True, False)]
            twins = f"  twin {both[0]:.4f} °/s, without K {both[1]:.4f} °/s"
        print(f"  {trial.name:44s} {row[0]:.4f} °/s  heading RMS {row[1]:.2f}°{twins}", flush=True)
    for scenario in args.scenarios.split(","):
        for seed in range(FIRST_SEED, FIRST_SEED + args.trials):
            groups.setdefault(scenario, []).append(drift(make_trial(scenario, seed), runner))
    print("\n| trials | n | drift °/s, median [min, max] | heading RMS °, median |\n|---|---|---|---|")
    for name, rows in groups.items():
        r = np.array(rows)
        print(f"| {name} | {len(r)} | {np.median(r[:, 0]):.3f} [{r[:, 0].min():.3f}, {r[:, 0].max():.3f}] "
              f"| {np.median(r[:, 1]):.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
