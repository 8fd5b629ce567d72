"""MagVQF-v0 on real recordings it never trained on (docs/results.md): the sim-to-real table against VQF.

    python -m studies.vqf_real [--agent RUN|pretrained:ID ...] [--recordings FILE ...] [--oracle] [--cv RUN ...]
        [--twins N] [--select] [--json FILE]

Every method on each recording (default: the shared BROAD ones), paired recording by recording with VQF as
published (``vqf``, the reference): per group of recordings (BROAD's own groups, from the recording's name:
``magnet`` = stationary and attached magnets, ``tapping`` = tapping and vibration, ``undisturbed``, ``office``,
``mixed``) the mean total RMSE (°) and the geometric mean of the per-recording ratios to ``vqf`` (with its 95 %
bootstrap interval where the group has ≥ 2), over all recordings the same, and the worst recording's ratio; on
the magnet recordings also the ratio to ``vqf_fan_lambda_tuned``, and to ``vqf_fan_rejection_tuned`` (the rule a
rule-guarded student departs from) there and over all. An agent that trained on no real recording and on no twin
of one (the shipped MagVQF-v0 student: simulation only) is scored as it is; ``--cv RUN`` reads a
leave-recordings-out run (``magenv train --teacher oracle_vqf_rule --config CFG --cv recordings --out RUN``,
CFG with recordings or their twins among its scenarios): each recording scored by the fold's student that
never saw it nor its twin (its ``cv.csv``). ``--oracle`` adds the privileged ``oracle_vqf`` (it reads truth:
headroom). For a guarded student, the share of its decisions that fell back on its guard's fallback. ``--twins N``
scores N twins of each recording (``twin:PATH``, validation seeds from 5000) in its place, grouped as the
recording: whether simulation fitted to the recordings ranks the methods as the recordings do. ``--select``
chooses among the agents on the recordings without reporting a chosen agent's figures on the recordings it was
chosen on (nested leave-one-recording-out): recording r is scored by the agent whose geometric-mean ratio to
``vqf`` over the other recordings is lowest (row ``selected (held out)``); the agent chosen on all of them is the
one to ship, and the held-out row estimates what choosing so is worth. It prints what it measures; nothing here
is a test.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

REFERENCE = "vqf"
RULES = ("vqf", "vqf_fan_lambda_tuned", "vqf_fan_rejection_tuned", "vqf_threshold_tuned")
GROUPS = (  # group → words of BROAD's file names (their groups)
    ("magnet", ("stationary_magnet", "attached_magnet")),
    ("tapping", ("tapping", "vibration")),
    ("undisturbed", ("undisturbed",)),
    ("office", ("office",)),
    ("mixed", ("mixed",)),
)


def group_of(name: str) -> str:
    """The group of a recording by its file name (``other`` where none matches)."""
    return next((g for g, words in GROUPS if any(w in name for w in words)), "other")


def score(methods: dict, trials: list) -> dict[str, dict[str, float]]:
    """method → recording name → total RMSE (°) over its score mask; guarded students' fallback shares too."""
    from magenv import evaluation

    runner = evaluation.PolicyRunner()
    out: dict[str, dict[str, float]] = {m: {} for m in methods}
    for trial in trials:
        for name, method in methods.items():
            out[name][trial.name] = evaluation.run_method(name, method, trial, runner).scored.total
    return out


def cv_scores(run: Path) -> dict[str, float]:
    """recording → the held-out student's RMSE from a cross-validation run's ``cv.csv``."""
    with open(run / "cv.csv", newline="") as f:
        return {row["recording"]: float(row["agent_rmse"]) for row in csv.DictReader(f)}


def table(scores: dict[str, dict[str, float]], names: list[str]) -> list[str]:
    """The Markdown table: per group and method, mean RMSE · ratio to vqf [95 % CI]; then all, worst."""
    from magenv.stats import paired_ratio

    recs = list(scores[REFERENCE])
    groups = [g for g, _ in GROUPS if any(group_of(r) == g for r in recs)] + ["all"]
    members = {g: [r for r in recs if g == "all" or group_of(r) == g] for g in groups}
    head = "| method | " + " | ".join(f"{g} ({len(members[g])})" for g in groups) + " | worst recording |"
    lines = [head, "|---" * (len(groups) + 2) + "|"]
    for m in names:
        cells = []
        for g in groups:
            a = np.array([scores[m][r] for r in members[g]])
            b = np.array([scores[REFERENCE][r] for r in members[g]])
            cell = f"{a.mean():.2f}"
            if m != REFERENCE:
                p = paired_ratio(a, b)
                cell += f" · {p.ratio:.2f}" + (f" [{p.low:.2f}, {p.high:.2f}]" if p.n > 1 else "")
            cells.append(cell)
        worst = max(recs, key=lambda r: scores[m][r] / scores[REFERENCE][r])
        tail = "–" if m == REFERENCE else f"{worst[:2]} {scores[m][worst] / scores[REFERENCE][worst]:.2f}"
        lines.append(f"| `{m}` | " + " | ".join(cells) + f" | {tail} |")
    fan = [r for r in recs if group_of(r) == "magnet"]
    if fan and "vqf_fan_lambda_tuned" in scores:
        lines.append("")
        for m in names:
            if m in RULES:
                continue
            p = paired_ratio([scores[m][r] for r in fan], [scores["vqf_fan_lambda_tuned"][r] for r in fan])
            lines.append(f"{m} / vqf_fan_lambda_tuned on the magnet recordings: {p.ratio_text(2)}")
            if "vqf_fan_rejection_tuned" in scores:  # the rule a rule-guarded student departs from
                for label, keys in (("magnet", fan), ("all", recs)):
                    p = paired_ratio([scores[m][r] for r in keys], [scores["vqf_fan_rejection_tuned"][r] for r in keys])
                    lines.append(f"{m} / vqf_fan_rejection_tuned on the {label} recordings: {p.ratio_text(2)}")
    return lines


def choice(scores: dict[str, dict[str, float]], agents: list[str], without: str | None = None) -> str:
    """The agent with the lowest geometric mean of its per-recording ratio to ``vqf`` over the recordings
    (all but ``without``; ties: the first of ``agents``)."""
    recs = [r for r in scores[REFERENCE] if r != without]
    return min(agents, key=lambda a: float(np.sum(np.log([scores[a][r] / scores[REFERENCE][r] for r in recs]))))


def nested_selection(scores: dict[str, dict[str, float]], agents: list[str]) -> tuple[dict[str, float], dict]:
    """Leave-one-recording-out ``choice`` among ``agents``: (recording → the RMSE of the agent chosen without
    it, recording → that agent's name). Raises ValueError on fewer than two recordings or an agent missing a
    recording."""
    recs = list(scores[REFERENCE])
    if len(recs) < 2 or not agents:
        raise ValueError(f"a nested choice needs ≥ 2 recordings and ≥ 1 agent, got {len(recs)} and {len(agents)}")
    missing = [(a, r) for a in agents for r in recs if r not in scores.get(a, {})]
    if missing:
        raise ValueError(f"no score of agent {missing[0][0]!r} on recording {missing[0][1]!r}")
    picked = {r: choice(scores, agents, without=r) for r in recs}
    return {r: scores[picked[r]][r] for r in recs}, picked


def recordings_needed(scores: dict[str, dict[str, float]], a: str, b: str, effect: float = 0.9) -> tuple[float, int]:
    """(σ, n): the spread σ of the per-recording log ratios of ``a`` to ``b`` (sample SD) and the recordings n
    that a 95 % interval of their geometric mean needs to exclude a tie when the true ratio is ``effect``:
    n = (1.96 σ / |ln effect|)² (the normal approximation)."""
    recs = list(scores[a])
    sigma = float(np.std(np.log([scores[a][r] / scores[b][r] for r in recs]), ddof=1))
    return sigma, int(np.ceil((1.96 * sigma / abs(np.log(effect))) ** 2))


def power_lines(scores: dict[str, dict[str, float]], agents: list[str], rule: str = "vqf_fan_rejection_tuned"):
    """For each pair of the agents and ``rule``: how many recordings would tell a 10 % difference."""
    names = [n for n in [*agents, rule] if n in scores]
    lines = ["", "recordings a paired 95 % interval needs to show a 10 % difference (spread σ of the log ratios):"]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            sigma, n = recordings_needed(scores, a, b)
            lines.append(f"- {a} / {b}: σ {sigma:.2f}, {n} recordings")
    return lines if len(scores[REFERENCE]) > 2 and len(names) > 1 else []


def main(argv: list[str] | None = None) -> int:
    import magenv  # noqa: F401  (registers the envs)
    from magenv import registry
    from magenv.recordings import list_recordings, load_recording

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", action="append", default=None, help="run folder or pretrained:ID (repeatable)")
    p.add_argument("--recordings", nargs="+", default=None, help="recording files (default: the shared BROAD ones)")
    p.add_argument("--oracle", action="store_true", help="add the privileged oracle_vqf (headroom)")
    p.add_argument("--cv", action="append", type=Path, default=[], help="a leave-recordings-out run (repeatable)")
    p.add_argument("--twins", type=int, default=0, help="score N twins of each recording in its place")
    p.add_argument("--select", action="store_true", help="nested leave-one-recording-out choice among the agents")
    p.add_argument("--json", type=Path, default=None, help="write the per-recording RMSEs")
    args = p.parse_args(argv)
    if args.twins < 0 or (args.twins and args.cv):
        raise SystemExit("--twins N needs N ≥ 0 and no --cv (a cross-validation run scored the recordings)")
    agents = args.agent if args.agent is not None else ["pretrained:magenv/MagVQF-v0"]
    files = args.recordings or list_recordings()
    if args.select and (len(agents) < 2 or len(files) < 2):
        raise SystemExit("--select needs ≥ 2 agents and ≥ 2 recordings")
    t0 = time.time()
    if args.twins:
        from magenv.scenarios import make_trial
        from magenv.seeding import VALIDATION_START

        trials = []
        for f in files:
            for seed in range(VALIDATION_START, VALIDATION_START + args.twins):
                trials.append(make_trial(f"twin:{f}", seed))
                trials[-1].name = f"{Path(f).stem}#twin{seed}"  # grouped as its recording (``group_of``)
    else:
        trials = [load_recording(f) for f in files]
    methods = {n: registry.make(n) for n in RULES + (("oracle_vqf",) if args.oracle else ())}
    methods.update({a: registry.make(registry.AGENT_PREFIX + a) for a in agents})
    scores = score(methods, trials)
    for run in args.cv:
        held = cv_scores(run)
        missing = [t.name for t in trials if t.name not in held]
        if missing:
            raise SystemExit(f"{run}/cv.csv holds no held-out score of {missing}")
        scores[f"{run} (held out)"] = {t.name: held[t.name] for t in trials}
    if args.select:
        scores["selected (held out)"], picked = nested_selection(scores, agents)
    names = list(scores)
    print(f"MagVQF-v0 on {len(trials)} recordings; total RMSE ° · per-recording ratio to vqf (geometric mean)")
    print(
        "\n".join(
            table(scores, names) + power_lines(scores, [*agents, *(n for n in names if n.endswith("(held out)"))])
        )
    )
    for a in agents:
        student = getattr(methods[a], "student", None)
        if getattr(student, "decisions", 0):
            print(f"{a}: {student.guarded / student.decisions:.1%} of its decisions fell back on its guard's fallback")
    if args.select:
        print("\nchosen without the recording: " + ", ".join(f"{r[:2]} {a}" for r, a in picked.items()))
        print(f"chosen on all {len(files)} recordings (the one to ship): {choice(scores, agents)}")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))
    print(f"({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
