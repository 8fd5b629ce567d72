"""``magenv report``: a Markdown report with the comparison tables and PNG plots.

    magenv report --out results/report [--scenario dynamic_magnet,dynamic_clean] [--seeds 0:5]
                  [--methods mimu,imu,fan_lambda,...] [--agent runs/NAME] [--recordings FILE ...]

Writes ``OUT/report.md`` with, per scenario (or recording): the RMSE table,
total error over time per method, the trust each method chose over time
against the true magnetic disturbance, and RMSE bars across scenarios.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

DEFAULT_METHODS = "mimu,imu,fan_lambda,fan_lambda_tuned,threshold,threshold_tuned"


def _plot_trial(runs: list, path: Path) -> Path:
    """Error over time (top) and trust chosen vs the true disturbance (bottom) for runs on one trial."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magenv import metrics

    trial = runs[0].trial
    t = trial.t
    runs = [r for r in runs if r.error is None]
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(10, 6.5))
    for r in runs:
        err = metrics.total_error(metrics.error_quaternion(r.q, trial.q_true))
        ax1.plot(t, err, lw=0.8, label=f"{r.method} ({r.score.total:.2f}°)")
        if r.trust is not None:
            ax2.plot(t, r.trust, lw=0.8, label=r.method)
    ax1.set_ylabel("total error (°)")
    ax1.legend(fontsize=7, ncol=2)
    ax2.set_ylabel("magnetometer trust (1 − λ, gate)")
    ax2.set_ylim(-0.05, 1.05)
    ax2.set_xlabel("time (s)")
    if "mag_disturbance" in trial.truth:
        dist = np.linalg.norm(trial.truth["mag_disturbance"], axis=1) / trial.field_norm
        twin = ax2.twinx()
        twin.fill_between(t, 0, dist, color="0.5", alpha=0.25, lw=0)
        twin.set_ylabel("true disturbance / m0", color="0.4")
    ax2.legend(fontsize=7, ncol=2, loc="upper left")
    ax1.set_title(trial.name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_bars(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    width = 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(max(6, 1.8 * len(scenarios)), 4))
    for j, m in enumerate(methods):
        vals = [
            next((r["total_rmse_mean"] for r in rows if r["method"] == m and r["scenario"] == s), np.nan)
            for s in scenarios
        ]
        errs = [
            next((r["total_rmse_std"] for r in rows if r["method"] == m and r["scenario"] == s), np.nan)
            for s in scenarios
        ]
        ax.bar(np.arange(len(scenarios)) + j * width, vals, width, yerr=np.nan_to_num(errs), label=m, capsize=2)
    ax.set_xticks(np.arange(len(scenarios)) + 0.4 - width / 2, scenarios, rotation=15)
    ax.set_ylabel("total RMSE (°)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def markdown_table(rows: list[dict]) -> str:
    """The comparison rows as a Markdown table, best total RMSE first within each scenario; an n/a cell's
    reason follows the table."""
    from magenv.train.compare import (
        divergence_notes,
        failure_notes,
        method_label,
        paired_cells,
        score_cells,
        table_order,
    )

    paired = any("paired" in r for r in rows)
    lines = [
        "| scenario | method | n | total RMSE (°) | ± std | heading | inclination |"
        + (" ÷ reference [95 % CI] | win | worst | IQM ÷ reference |" if paired else ""),
        "|---|---|---|---|---|---|---|" + ("---|---|---|---|" if paired else ""),
    ]
    for r in table_order(rows):
        cells = score_cells(r) + (paired_cells(r) if paired else [])
        lines.append(f"| {r['scenario']} | {method_label(r)} | {r['n']} | " + " | ".join(cells) + " |")
    notes = failure_notes(rows) + divergence_notes(rows)
    return "\n".join(lines + ([""] + [f"* {n}" for n in notes] if notes else []))


def write_report(
    runs: list,
    out: Path,
    title: str = "magenv comparison report",
    headroom: frozenset[str] | set[str] = frozenset(),
    reference: str | None = None,
) -> Path:
    """Write ``out/report.md`` and its PNGs from evaluation runs; returns the Markdown path. ``headroom``:
    names of privileged methods (upper bounds), listed last in each scenario; ``reference``: the method every
    other is paired with, trial by trial (``evaluation.add_paired``)."""
    from magenv import evaluation
    from magenv.train.compare import HEADROOM_FOOTNOTE, mark_headroom

    out.mkdir(parents=True, exist_ok=True)
    rows = mark_headroom(evaluation.summarize(runs), set(headroom))
    if reference is not None:
        rows = evaluation.add_paired(rows, runs, reference)
    evaluation.write_csv(rows, out / "comparison.csv")
    parts = [
        f"# {title}",
        "",
        "Orientation RMSE in degrees over each trial's score mask, mean over trials "
        "(`magenv.metrics`). Trust is the magnetometer weight each method used (1 − λ for blend policies)."
        + (
            f" ÷ reference: the paired ratio to `{reference}` over the same trials (geometric mean of the per-trial "
            "ratios, bootstrap 95 % interval; below 1 throughout = better), win: the share of trials it is better on, "
            "worst: the largest per-trial ratio, IQM ÷ reference: the same over the middle half of the per-trial log "
            "ratios (extreme trials dropped)."
            if reference is not None
            else ""
        )
        + (f" {HEADROOM_FOOTNOTE[0].upper()}{HEADROOM_FOOTNOTE[1:]}." if headroom else ""),
        "",
        markdown_table(rows),
        "",
        f"![RMSE per scenario]({_plot_bars(rows, out / 'rmse_bars.png').name})",
        "",
    ]
    for label in dict.fromkeys(r.label for r in runs):
        first = [r for r in runs if r.label == label]
        first = [r for r in first if r.trial is first[0].trial]
        png = _plot_trial(first, out / f"trial_{label.replace('/', '_')}.png")
        parts += [f"## {label}", "", f"First trial: `{first[0].trial.name}`.", "", f"![{label}]({png.name})", ""]
    path = out / "report.md"
    path.write_text("\n".join(parts))
    return path


def add_arguments(p: argparse.ArgumentParser) -> None:
    from magenv.train.cli import TRUST_PICKLE_HELP
    from magenv.train.seeds import seeds_arg

    p.add_argument("--out", type=Path, default=Path("results/report"), help="report folder (default %(default)s)")
    p.add_argument("--scenario", default="dynamic_magnet,dynamic_clean,stationary_magnet")
    p.add_argument("--seeds", type=seeds_arg, default="0:5")
    p.add_argument("--methods", default=DEFAULT_METHODS)
    p.add_argument("--agent", action="append", default=[], metavar="RUN_DIR", help="add a trained agent (repeatable)")
    p.add_argument("--recordings", nargs="+", default=[], metavar="FILE")
    p.add_argument("--trust-pickle", action="store_true", help=TRUST_PICKLE_HELP)


def run(args: argparse.Namespace) -> int:
    from magenv import evaluation, registry
    from magenv.train.cli import PARTIAL, output_folder
    from magenv.train.compare import (
        DEFAULT_REFERENCE,
        failure_notes,
        headroom_names,
        make_trials,
        run_comparison,
        select_methods,
    )

    args.out = output_folder(args.out, "--out")
    methods = select_methods(
        args.methods.split(",") + [registry.AGENT_PREFIX + a for a in args.agent], args.trust_pickle
    )
    trials, labels = make_trials(args.scenario, args.seeds, args.recordings)
    runs = run_comparison(methods, trials, labels)
    reference = DEFAULT_REFERENCE if DEFAULT_REFERENCE in methods else None
    print(f"wrote {write_report(runs, args.out, headroom=headroom_names(methods), reference=reference)}")
    notes = failure_notes(evaluation.summarize(runs))
    for line in notes:
        print(line)
    return PARTIAL if notes else 0
