"""``magenv plot``: draw a trial file — magenv's own (``magenv simulate``) or a BROAD recording.

Panels: true orientation (ZYX Euler angles of ``q_true``), measured angular
rates, measured field norm and dip angle (with the undisturbed m0 and θ0),
and the magnet's distance from the sensor (truth).

    magenv plot trial.h5 --out trial.png
    magenv plot ../shared/data/broad/29_disturbed_stationary_magnet_B.hdf5 --out 29.png
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magenv.train.cli import IMAGE_SUFFIXES, CommandError, output_file


def add_arguments(parser) -> None:
    parser.add_argument("trial", type=Path, help="trial file (.h5) written by `magenv simulate`, or a BROAD recording")
    parser.add_argument("--out", type=Path, default=None, help="PNG to write (default: next to the trial)")


def measured_dip(trial) -> np.ndarray:
    """Dip angle of the measured field, degrees: angle between the field and
    the horizontal plane, horizontal taken from the accelerometer (eq. 18 of
    the paper uses the estimate; here the measurement, for display)."""
    a = trial.acc / np.linalg.norm(trial.acc, axis=1, keepdims=True)
    m = trial.mag / np.maximum(np.linalg.norm(trial.mag, axis=1, keepdims=True), 1e-12)
    return np.rad2deg(np.arcsin(np.clip(-np.sum(a * m, axis=1), -1, 1)))


def draw(trial, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magenv import quaternion as quat

    t = trial.t
    fig, ax = plt.subplots(5, 1, figsize=(10, 11), sharex=True)
    eul = np.rad2deg(quat.to_euler_zyx(trial.q_true))
    for k, label in enumerate(("yaw ψ", "pitch θ", "roll φ")):
        ax[0].plot(t, eul[:, k], lw=0.8, label=label)
    ax[0].set_ylabel("orientation, °")
    ax[0].legend(loc="upper right", fontsize=8)
    for k, label in enumerate(("x", "y", "z")):
        ax[1].plot(t, np.rad2deg(trial.gyr[:, k]), lw=0.6, label=f"ω_{label}")
    ax[1].set_ylabel("rate, °/s")
    ax[1].legend(loc="upper right", fontsize=8)
    norm = np.linalg.norm(trial.mag, axis=1)
    ax[2].plot(t, norm, "r", lw=0.7, label="‖m‖ measured")
    ax[2].axhline(trial.field_norm, color="k", ls="--", lw=0.8, label=f"m0 = {trial.field_norm:.1f} µT")
    ax[2].set_ylabel("field norm, µT")
    ax[2].legend(loc="upper right", fontsize=8)
    ax[3].plot(t, measured_dip(trial), lw=0.6, label="dip measured")
    ax[3].axhline(trial.field_dip, color="k", ls="--", lw=0.8, label=f"θ0 = {trial.field_dip:.1f}°")
    ax[3].set_ylabel("dip, °")
    ax[3].legend(loc="upper right", fontsize=8)
    dist = trial.truth.get("magnet_distance")
    if dist is not None and np.any(np.isfinite(dist)):
        ax[4].plot(t, 100 * dist, lw=0.8)
        ax[4].set_ylabel("magnet distance, cm")
    else:
        ax[4].text(0.5, 0.5, "no magnet distance in this trial", ha="center", va="center", transform=ax[4].transAxes)
        ax[4].set_ylabel("magnet distance")
    if "stationary" in trial.truth:
        st = np.asarray(trial.truth["stationary"], bool)
        for a in ax:
            a.fill_between(t, 0, 1, where=st, color="0.9", transform=a.get_xaxis_transform(), zorder=0, lw=0)
    ax[-1].set_xlabel("time, s (grey: gimbal at rest)")
    fig.suptitle(f"{trial.name} — {trial.duration:.1f} s at {trial.rate:g} Hz")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def run(args) -> int:
    from magenv.recordings import load_trial_file
    from magenv.trial import TrialError

    out = output_file(args.out or args.trial.with_suffix(".png"), "--out", IMAGE_SUFFIXES)
    try:
        trial = load_trial_file(args.trial)
    except TrialError as exc:
        raise CommandError(str(exc)) from None
    print(draw(trial, out))
    return 0
