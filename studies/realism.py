"""Realism check: the real sensor (BROAD recordings) against the simulator.

Computes, per recording, the statistics of ``magenv.sensor_stats`` — noise at
the initial rest, gyro bias, noise colour (the magnetometer's lag-1 and lag-2
autocorrelation over its distinct samples), field magnitude and dip, the
magnetometer's lag (behind the gyro, and behind the true orientation), the
gyro's lag behind the true orientation, the magnetometer's sample-and-hold
share and how its holds group (run length), the resolution of each channel —
prints a table,
derives the sensor-model values the recordings support, and puts the same
statistics of simulated data beside them: trials of ``magenv.scenarios``
(when importable) and a trial made by the simulator's sensor model alone
(``magenv.sim.sensors`` with its default ``SensorConfig`` on ideal readings
of a rest-then-rotate motion). ``--out FILE.png`` writes a figure.

    python -m studies.realism --out results/realism.png

The magnetometer lag is taken from the undisturbed trials only (02, 05, 07,
10, 24): the method assumes a field constant in the earth frame.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from magenv.recordings import list_recordings, load_recording
from magenv.sensor_stats import field_norm_dip, sensor_stats


def _sim_defaults() -> dict[str, float]:
    """The simulator's sensor defaults (``magenv.sim.sensors.SensorConfig``), or
    the values announced in issue 6 if the simulator is not importable."""
    try:
        from magenv.sim.sensors import SensorConfig

        c = SensorConfig()
        return {
            "gyr_noise_dps": c.gyr_noise_dps,
            "gyr_bias_dps": c.gyr_bias_dps,
            "acc_noise_ms2": c.acc_noise,
            "mag_noise_ut": c.mag_noise_ut,
            "mag_lag_samples": float(c.mag_lag_samples),
            "mag_hold_fraction": c.mag_hold_fraction,
            "mag_hold_run_mean": float(c.mag_hold_run),
            "gyr_truth_lag_samples": float(c.gyr_lag_samples),
            "mag_noise_taps": float(c.mag_noise_taps),
        }
    except Exception:
        return {
            "gyr_noise_dps": 0.5,
            "gyr_bias_dps": 0.1,
            "acc_noise_ms2": 0.02,
            "mag_noise_ut": 0.15,
            "mag_lag_samples": 4.0,
            "mag_hold_fraction": 0.29,
            "mag_hold_run_mean": 1.0,
            "gyr_truth_lag_samples": 0.0,
            "mag_noise_taps": 1.0,
        }


SIM_DEFAULTS = _sim_defaults()
UNDISTURBED = ("02", "05", "07", "10", "24")  # no magnet near the IMU
SIM_SCENARIOS = ("stationary_magnet", "dynamic_clean")

COLUMNS = [  # (header, attribute, format)
    ("gyr σ °/s", "gyr_noise_dps", "{:.3f}"),
    ("acc σ m/s²", "acc_noise_ms2", "{:.3f}"),
    ("mag σ µT", "mag_noise_ut", "{:.2f}"),
    ("|m| µT p5/50/95", None, None),
    ("dip ° p5/50/95", None, None),
    ("lag mag−gyr", "mag_lag_samples", "{:.2f}"),
    ("lag mag−true", "mag_truth_lag_samples", "{:.2f}"),
    ("lag gyr−true", "gyr_truth_lag_samples", "{:.2f}"),
    ("mag hold", "mag_hold_fraction", "{:.3f}"),
    ("hold run", "mag_hold_run_mean", "{:.2f}"),
    ("mag ρ1 (distinct)", None, None),
    ("ρ2 distinct", "mag_autocorr2_distinct", "{:.2f}"),
]


def _row(s) -> list[str]:
    out = [s.name[:24]]
    for head, attr, fmt in COLUMNS:
        if attr is not None:
            out.append(fmt.format(getattr(s, attr)))
        elif head.startswith("|m|"):
            out.append(f"{s.field_norm_p05_ut:.1f}/{s.field_norm_median_ut:.1f}/{s.field_norm_p95_ut:.1f}")
        elif head.startswith("dip"):
            out.append(f"{s.dip_p05_deg:.1f}/{s.dip_median_deg:.1f}/{s.dip_p95_deg:.1f}")
        else:
            out.append(f"{s.mag_autocorr1:.2f} ({s.mag_autocorr1_distinct:.2f})")
    return out


def _print_table(rows: list[list[str]]) -> None:
    head = ["trial"] + [c[0] for c in COLUMNS]
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    line = lambda r: "  ".join(x.rjust(w) if i else x.ljust(w) for i, (x, w) in enumerate(zip(r, widths)))
    print(line(head))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print(line(r))


def simulated_trials(seed: int = 0):
    """``[(scenario, Trial)]`` from ``magenv.scenarios.make_trial``, or ``[]`` with the reason printed."""
    try:
        from magenv.scenarios import make_trial
    except Exception as exc:  # the simulator is optional for this check
        print(f"(no simulated trials: magenv.scenarios not importable: {exc})")
        return []
    out = []
    for name in SIM_SCENARIOS:
        try:
            out.append((name, make_trial(name, seed)))
        except Exception as exc:
            print(f"(simulated scenario {name!r} failed: {type(exc).__name__}: {exc})")
    return out


def sensor_model_trial(seed: int = 0, rate: float = 285.714, rest_s: float = 12.0, move_s: float = 40.0):
    """A trial made by the simulator's sensor model alone (``magenv.sim.sensors``)
    on ideal readings: ``rest_s`` s at rest, then smooth rotations (up to
    ~200 °/s) in the Berlin field, at BROAD's rate. ``None`` if the model is missing."""
    try:
        from magenv.sim.sensors import SensorConfig, apply_sensor_model
    except Exception as exc:
        print(f"(no sensor-model trial: magenv.sim.sensors not importable: {exc})")
        return None
    from magenv import quaternion as quat
    from magenv.trial import Trial

    rng = np.random.default_rng(seed)
    n = int(round((rest_s + move_s) * rate))
    t = np.arange(n) / rate
    freqs, phases = rng.uniform(0.1, 0.6, (3, 3)), rng.uniform(0, 2 * np.pi, (3, 3))
    gyr = np.deg2rad(70.0) * np.sin(2 * np.pi * freqs[None] * t[:, None, None] + phases[None]).sum(-1)
    gyr *= np.clip((t - rest_s) / 2.0, 0.0, 1.0)[:, None]  # rest, then a 2 s ramp into motion
    q = np.empty((n, 4))
    q[0] = quat.from_euler_zyx(0.3, 0.1, -0.2)
    for i in range(1, n):
        q[i] = quat.integrate_gyro1(q[i - 1], 0.5 * (gyr[i - 1] + gyr[i]), 1.0 / rate)
    acc = quat.rotate_inv(q, np.broadcast_to(quat.gravity_up(), (n, 3)))
    mag = quat.rotate_inv(q, np.broadcast_to(quat.earth_field(44.5, 69.0), (n, 3)))
    g, a, m = apply_sensor_model(gyr, acc, mag, rate, SensorConfig(), rng)
    return Trial(
        name="sensor_model_default",
        rate=rate,
        gyr=g,
        acc=a,
        mag=m,
        q_true=q,
        field_norm=44.5,
        field_dip=69.0,
        score_mask=t >= rest_s + 2.0,
    )


def recommend(real) -> dict[str, float]:
    """Sensor-model values the recordings support (medians over trials)."""
    und = [s for s in real if s.name[:2] in UNDISTURBED]
    med = lambda xs: float(np.nanmedian(xs))
    return {
        "gyr_noise_dps": med([s.gyr_noise_dps for s in real]),
        # std of a zero-mean normal bias per axis, from the rest means (RMS over axes and trials)
        "gyr_bias_dps": float(np.sqrt(np.nanmean([np.square(s.gyr_bias_axes_dps) for s in real]))),
        "acc_noise_ms2": med([s.acc_noise_ms2 for s in real]),
        "mag_noise_ut": med([s.mag_noise_ut for s in real]),
        "mag_lag_samples": med([s.mag_lag_samples for s in und]),
        "mag_truth_lag_samples": med([s.mag_truth_lag_samples for s in und]),
        "gyr_truth_lag_samples": med([s.gyr_truth_lag_samples for s in und]),
        "mag_hold_fraction": med([s.mag_hold_fraction for s in real]),
        "mag_autocorr1_distinct": med([s.mag_autocorr1_distinct for s in real]),
        "mag_autocorr2_distinct": med([s.mag_autocorr2_distinct for s in real]),
        "mag_hold_run_mean": med([s.mag_hold_run_mean for s in real]),
        "mag_hold_run2_share": med([s.mag_hold_run2_share for s in real]),
        "gyr_quantum_dps": med([s.gyr_quantum_dps for s in real]),
        "acc_quantum_ms2": med([s.acc_quantum_ms2 for s in real]),
        "mag_quantum_ut": med([s.mag_quantum_ut for s in real]),
        "rate_hz": med([s.rate_hz for s in real]),
    }


def plot(real_trials, real, sim_trials, sim, rec, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    labels = [s.name[:2] for s in real] + [f"sim:{n}" for n, _ in sim_trials]
    stats = list(real) + list(sim)
    x = np.arange(len(stats))
    for ax, attr, unit, key in zip(
        axes[0],
        ("gyr_noise_axes_dps", "acc_noise_axes_ms2", "mag_noise_axes_ut"),
        ("gyro σ at rest, °/s", "accelerometer σ at rest, m/s²", "magnetometer σ at rest, µT"),
        ("gyr_noise_dps", "acc_noise_ms2", "mag_noise_ut"),
    ):
        vals = np.array([getattr(s, attr) for s in stats], float)
        for i, axis in enumerate("xyz"):
            ax.bar(x + (i - 1) * 0.27, vals[:, i], 0.27, label=axis)
        ax.axhline(SIM_DEFAULTS[key], color="r", ls="--", label=f"sim default {SIM_DEFAULTS[key]}")
        ax.axhline(rec[key], color="k", ls=":", label=f"recordings {rec[key]:.3g}")
        ax.set_xticks(x, labels, rotation=45, ha="right", fontsize=8)
        ax.set_title(unit)
        ax.set_ylim(0, 1.45 * max(np.nanmax(vals), SIM_DEFAULTS[key], rec[key]))
        ax.legend(fontsize=7, loc="upper center", ncol=3)
    histograms = (  # (panel, which of field_norm_dip's two, bins, label)
        (axes[1, 0], 0, np.linspace(20, 70, 101), "field magnitude |m|, µT (samples with |a| ≈ g)"),
        (axes[1, 1], 1, np.linspace(-30, 90, 121), "dip angle, ° (samples with |a| ≈ g)"),
    )
    for ax, which, bins, xlabel in histograms:
        curves = [(t.name[:2], t, 0.8) for t in real_trials] + [(f"sim:{n}", t, 2) for n, t in sim_trials]
        for label, t, lw in curves:
            ax.hist(field_norm_dip(t)[which], bins, histtype="step", density=True, label=label, lw=lw)
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
    axes[1, 0].legend(fontsize=6, ncol=2)
    ax = axes[1, 2]
    ax.plot(x, [s.mag_lag_samples for s in stats], "o", label="mag behind gyro")
    ax.plot(x, [s.mag_truth_lag_samples for s in stats], "s", label="mag behind truth")
    ax.plot(x, [s.gyr_truth_lag_samples for s in stats], "^", label="gyro behind truth")
    ax.axhline(SIM_DEFAULTS["mag_lag_samples"], color="r", ls="--", label="sim default mag lag")
    ax.set_ylabel("lag, samples")
    ax2 = ax.twinx()
    ax2.bar(x, [s.mag_hold_fraction for s in stats], 0.5, alpha=0.2, color="g", label="mag hold fraction")
    ax2.set_ylim(0, 1)
    ax2.set_ylabel("mag sample-and-hold fraction")
    ax.set_xticks(x, labels, rotation=45, ha="right", fontsize=8)
    ax.set_title("magnetometer timing (lag from undisturbed trials)")
    ax.legend(fontsize=7, loc="upper left")
    fig.suptitle("Sensor realism: BROAD recordings vs simulator")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--folder", type=Path, default=None, help="BROAD folder (default ../shared/data/broad)")
    ap.add_argument("--out", type=Path, default=None, help="write a PNG figure here")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated trials")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulated trials")
    args = ap.parse_args(argv)

    real_trials = [load_recording(p) for p in list_recordings(args.folder)]
    real = [sensor_stats(t) for t in real_trials]
    sim_trials = [] if args.no_sim else simulated_trials(args.seed)
    model = None if args.no_sim else sensor_model_trial(args.seed)
    if model is not None:
        sim_trials.append(("sensor_model", model))
    sim = [sensor_stats(t) for _, t in sim_trials]
    for (n, _), s in zip(sim_trials, sim):
        s.name = f"sim:{n}"

    print("Sensor statistics (σ: per-axis std at the initial rest, mean of x/y/z; lags in samples;")
    print("|m| and dip over samples with |a| ≈ g; ρ1: lag-1 autocorrelation of the mag rest noise)\n")
    _print_table([_row(s) for s in real + sim])

    rec = recommend(real)
    print("\nWhat the recordings say the sensor model should be (median over trials;")
    print(f"lags from the undisturbed trials {', '.join(UNDISTURBED)}):\n")
    rows = [
        ("gyro noise σ, °/s per axis", "gyr_noise_dps", SIM_DEFAULTS["gyr_noise_dps"], "{:.3f}"),
        ("gyro bias σ (rest means, RMS), °/s", "gyr_bias_dps", SIM_DEFAULTS["gyr_bias_dps"], "{:.3f}"),
        ("accelerometer noise σ, m/s² per axis", "acc_noise_ms2", SIM_DEFAULTS["acc_noise_ms2"], "{:.3f}"),
        ("magnetometer noise σ, µT per axis", "mag_noise_ut", SIM_DEFAULTS["mag_noise_ut"], "{:.2f}"),
        ("mag lag behind gyro, samples", "mag_lag_samples", SIM_DEFAULTS["mag_lag_samples"], "{:.2f}"),
        ("mag lag behind truth, samples", "mag_truth_lag_samples", None, "{:.2f}"),
        ("gyro lag behind truth, samples", "gyr_truth_lag_samples", SIM_DEFAULTS["gyr_truth_lag_samples"], "{:.2f}"),
        ("mag sample-and-hold fraction", "mag_hold_fraction", SIM_DEFAULTS["mag_hold_fraction"], "{:.3f}"),
        ("mag hold run length, samples", "mag_hold_run_mean", SIM_DEFAULTS["mag_hold_run_mean"], "{:.2f}"),
        ("mag hold runs of exactly two", "mag_hold_run2_share", None, "{:.3f}"),
        ("mag noise ρ1 over distinct samples", "mag_autocorr1_distinct", None, "{:.2f}"),
        ("mag noise ρ2 over distinct samples", "mag_autocorr2_distinct", None, "{:.2f}"),
        ("resolution gyro, °/s", "gyr_quantum_dps", None, "{:.4f}"),
        ("resolution accelerometer, m/s²", "acc_quantum_ms2", None, "{:.4f}"),
        ("resolution magnetometer, µT", "mag_quantum_ut", None, "{:.4f}"),
        ("sampling rate, Hz", "rate_hz", None, "{:.3f}"),
    ]
    w = max(len(r[0]) for r in rows)
    # the same statistic measured on the sensor model's own trial (its default SensorConfig)
    measured = next((st for (n, _), st in zip(sim_trials, sim) if n == "sensor_model"), None)
    print(f"{'quantity'.ljust(w)}  {'recordings':>10}  {'sim default':>11}  {'sensor model (measured)':>23}")
    for label, key, default, fmt in rows:
        got = "" if measured is None or not hasattr(measured, key) else fmt.format(getattr(measured, key))
        print(
            f"{label.ljust(w)}  {fmt.format(rec[key]):>10}  {('' if default is None else str(default)):>11}  {got:>23}"
        )
    taps = SIM_DEFAULTS["mag_noise_taps"]
    print(f"\n(sim default mag_noise_taps = {taps:g}: a binomial low-pass; 3 taps [1, 2, 1] give ρ1 4/6, ρ2 1/6)")
    print("\nLags are effective delays: sample-and-hold adds its mean age (≈ 0.4 sample for pairs of holds")
    print("6 or 8 samples apart) to a pure delay, so the simulator's whole-sample mag_lag_samples shows")
    print("≈ 0.4 sample larger behind its gyro.")
    if args.out is not None:
        plot(real_trials, real, sim_trials, sim, rec, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
