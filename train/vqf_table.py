"""The MagVQF-v0 table on the nine shared recordings: VQF, VQF without rejection, the tuned rules, the agent.

    python -m magenv.train.vqf_table --cv runs/vqf_cv [--oracle]

The agent's figure on each recording is that of the leave-recordings-out fold
that held it out (``runs/vqf_cv/foldF``, trained by ``magenv.train.vqf_dagger``
without that recording), never the shipped agent (which trained on all nine).
Every method is paired with VQF trial by trial (``magenv.stats.paired_ratio``:
geometric mean ratio, 95 % bootstrap interval, win rate) within each group;
"beats VQF" only where the interval lies below 1 (at the printed three decimals).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

GROUPS = {  # group → recording keys (BROAD file name prefixes)
    "magnet": ("29", "30", "32", "34"),
    "undisturbed": ("02", "05", "07", "10"),
    "tapping": ("24",),
}
METHODS = ("vqf", "vqf_no_rejection", "vqf_fan_lambda_tuned", "vqf_threshold_tuned")


def main(argv=None) -> int:
    import yaml

    from magenv import evaluation, registry
    from magenv.agents import dagger_vqf as dv
    from magenv.recordings import list_recordings, load_recording
    from magenv.stats import paired_ratio

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cv", type=Path, required=True, help="folder of the leave-recordings-out folds")
    p.add_argument("--oracle", action="store_true", help="add the privileged oracle_vqf (headroom)")
    args = p.parse_args(argv)
    trials = {path.stem[:2]: load_recording(path) for path in list_recordings()}
    folds = {}
    for run in sorted(args.cv.glob("fold*")):
        for key in yaml.safe_load((run / dv.RUN_FILE).read_text())["held_out"]:
            folds[key] = dv.load_policy(run, "agent (held out)")
    names = [*METHODS, "agent", *(["oracle_vqf"] if args.oracle else [])]
    scores: dict[str, dict[str, float]] = {n: {} for n in names}
    runner = evaluation.PolicyRunner()
    for key, trial in trials.items():
        for name in names:
            method = folds[key] if name == "agent" else registry.make(name)
            scores[name][key] = evaluation.run_method(name, method, trial, runner).scored.total
        print(key, " ".join(f"{n}={scores[n][key]:.3f}" for n in names), flush=True)
    print("\n| method | " + " | ".join(f"{g} (n={len(k)})" for g, k in GROUPS.items()) + " |")
    print("|---|" + "---|" * len(GROUPS))
    for name in names:
        cells = []
        for keys in GROUPS.values():
            a = [scores[name][k] for k in keys]
            b = [scores["vqf"][k] for k in keys]
            cell = f"{np.mean(a):.3f}°"
            if name != "vqf" and len(keys) > 1:
                r = paired_ratio(a, b)
                beats = " **beats**" if round(r.high, 3) < 1 else ""  # below 1 as printed
                cell += f" · {r.ratio_text()} win {r.win_rate:.2f}{beats}"
            elif name != "vqf":
                cell += f" · {a[0] / b[0]:.3f}"
            cells.append(cell)
        print(f"| `{name}` | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
