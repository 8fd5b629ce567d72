"""Learned against the rules: the one engine of the per-env studies (``studies/blend.py``, ``kalman.py``,
``constraint.py``, ``qsf.py``, ``vqf.py``), each the table of its section of docs/results.md.

    python -m studies.ENV [--agent RUN|pretrained:ID ...] [--seeds 0:40] [--scenarios a,b] [--recordings]
        [--no-oracle] [--no-others] [--validation] [--duration S] [--json FILE]

A :class:`Study` names an env's tests, the best rule of each test (the reference), the hand rule on the
student's own inputs (where one exists: how much of the agent's gain is learning rather than information), other
rules worth a column and the privileged oracle (it reads truth: an upper bound, shown as headroom, never a
baseline). On every held-out seed (below 5000; ``--validation``: 5000–9999, for model selection only) of every
test it runs the agents (the shipped one by default), the rules and the oracle on the same trial and prints a
Markdown table: mean total RMSE (°) of each method and, for each agent and the oracle, the paired ratio to the
reference (``magenv.stats.paired_ratio``: geometric mean of the per-trial ratios, bootstrap 95 % interval,
10 000 resamples, seed 0) with the win rate and the interquartile-mean ratio (the middle half of the per-trial
log ratios); last, the share of the reference-to-oracle gap of the mean RMSEs the first agent closes.
``--recordings`` adds the nine BROAD recordings (``shared/data/broad``) as one more group, paired recording by
recording (the oracle left out: the optical truth is too coarse to steer by). ``--json`` writes every per-trial
RMSE after each group; a file from an earlier run with the same seeds is read back, so methods already in it are
not run again (the oracles are the slow ones). It prints what it measures; nothing here is a test.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

RECORDINGS = "recordings"  # the group of the real recordings


@dataclass(frozen=True)
class Study:
    """One env's held-out comparison.

    Attributes:
        env_id: the env whose shipped agent is the default (``pretrained:ENV_ID``).
        tests: the scenarios of its targets.
        reference: the best rule (registry name), paired with every other method; ``by_test`` overrides it per test.
        by_test: test → its own best rule.
        same_information: test → the hand rule on the student's own inputs.
        others: more rules (columns only).
        oracle: the privileged teacher (headroom), "" for none.
        recordings: whether the env's methods run on the real recordings (one-sensor gimbal trials).
    """

    env_id: str
    tests: tuple[str, ...]
    reference: str
    by_test: dict[str, str] = field(default_factory=dict)
    same_information: dict[str, str] = field(default_factory=dict)
    others: tuple[str, ...] = ()
    oracle: str = ""
    recordings: bool = False

    def reference_of(self, test: str) -> str:
        return self.by_test.get(test, self.reference)

    def rules(self, with_others: bool = True) -> list[str]:
        """Every rule of the table, each once: the references, the same-information rules, the others."""
        names = [self.reference, *self.by_test.values(), *self.same_information.values()]
        return list(dict.fromkeys(names + (list(self.others) if with_others else [])))


def parse(study: Study, argv: list[str] | None = None) -> argparse.Namespace:
    from magenv.train.seeds import REPORT_SEEDS, check_report_seeds, seeds_arg

    p = argparse.ArgumentParser(description=f"{study.env_id}: learned against the rules on held-out trials")
    p.add_argument(
        "--agent",
        action="append",
        default=None,
        help=f"run folder or pretrained:ID (repeatable; default pretrained:{study.env_id}; none: the rules alone)",
    )
    p.add_argument("--seeds", type=seeds_arg, default=REPORT_SEEDS, help="trial seeds (default %(default)s)")
    p.add_argument("--scenarios", default=",".join(study.tests), help="comma list (default %(default)s)")
    p.add_argument("--recordings", action="store_true", help="add the nine BROAD recordings as one group")
    p.add_argument("--no-oracle", action="store_true", help="leave the privileged oracle out")
    p.add_argument("--no-others", action="store_true", help="only the reference and same-information rules")
    p.add_argument("--validation", action="store_true", help="validation seeds 5000–9999 (model selection)")
    p.add_argument("--duration", type=float, default=None, help="trials cut to S seconds (a quick look)")
    p.add_argument("--json", type=Path, default=None, help="per-trial RMSE file (read back where it exists)")
    args = p.parse_args(argv)
    check_report_seeds(args.seeds, args.validation)
    if args.recordings and not study.recordings:
        p.error(f"{study.env_id}'s methods do not run on the one-sensor recordings")
    args.agent = [a for a in args.agent or [f"pretrained:{study.env_id}"] if a != "none"]
    return args


def trials_of(test: str, seeds: list[int], duration: float | None) -> list:
    """The trials of one group: the scenario at every seed, or the recordings."""
    from magenv.recordings import load_all
    from magenv.scenarios import make_trial

    if test == RECORDINGS:
        return load_all()
    return [make_trial(test, s, **({} if duration is None else {"duration": duration})) for s in seeds]


def measure(study: Study, args: argparse.Namespace) -> dict[str, dict[str, list[float]]]:
    """Per group, per method: the per-trial total RMSE (°), read back from ``args.json`` where it holds them."""
    from magenv import evaluation, registry

    agents = {agent_label(args.agent, a): a for a in args.agent}
    old = json.loads(args.json.read_text()) if args.json and args.json.exists() else {}
    if old and old.get("seeds") != args.seeds:
        raise SystemExit(f"{args.json} holds seeds {old.get('seeds')}, not {args.seeds}")
    per_trial: dict[str, dict[str, list[float]]] = old.get("per_trial_rmse", {})
    groups = [s for s in args.scenarios.split(",") if s] + ([RECORDINGS] if args.recordings else [])
    for group in groups:
        names = study.rules(not args.no_others) + ([] if args.no_oracle or group == RECORDINGS else [study.oracle])
        have = per_trial.setdefault(group, {})
        todo = {n: registry.make(n) for n in names if n and n not in have}
        todo.update({label: registry.make(registry.AGENT_PREFIX + a) for label, a in agents.items()})
        t = time.time()
        runs = evaluation.evaluate(todo, trials_of(group, args.seeds, args.duration))
        have.update({m: [r.scored.total for r in runs if r.method == m] for m in todo})
        print(f"{group}: {time.time() - t:.0f} s", flush=True)
        if args.json:  # after each group, so that a long run keeps what it has
            args.json.write_text(json.dumps({"env": study.env_id, "seeds": args.seeds, "per_trial_rmse": per_trial}))
    return {g: per_trial[g] for g in groups}


def agent_label(agents: list[str], agent: str) -> str:
    return "agent" if len(agents) == 1 else agent


def table(study: Study, per_trial: dict[str, dict[str, list[float]]], agents: list[str]) -> list[str]:
    """The Markdown table of :func:`measure`'s figures (a new header where a group's columns change)."""
    from magenv.stats import paired_ratio

    labels = [agent_label(agents, a) for a in agents]
    lines: list[str] = []
    for group, res in per_trial.items():
        ref, same = study.reference_of(group), study.same_information.get(group)
        cols = [m for m in res if m != study.oracle] + ([study.oracle] if study.oracle in res else [])
        pairs = [(m, ref) for m in (*labels, study.oracle) if m in res] + [(a, same) for a in labels if same in res]
        names = [f"{m} / {'reference' if r == ref else r} [95% CI] (win; IQM [95% CI])" for m, r in pairs]
        head = "| test | reference | " + " | ".join(cols + names) + " | headroom captured |"
        if head not in lines:
            lines += ["", head, "|---" * (3 + len(cols) + len(pairs)) + "|"]
        cells = [f"{np.mean(res[m]):.3f}" for m in cols]
        for m, r in pairs:
            pr = paired_ratio(np.array(res[m]), np.array(res[r]))
            cells.append(f"{pr.ratio_text()} ({pr.win_rate:.2f}; {pr.iqm_text()})")
        captured = "–"
        if labels and study.oracle in res:
            r_, a_, o_ = (float(np.mean(res[m])) for m in (ref, labels[0], study.oracle))
            captured = f"{(r_ - a_) / (r_ - o_):.2f}"
        lines.append(f"| {group} | {ref} | " + " | ".join(cells) + f" | {captured} |")
    return lines + pooled(study, per_trial, labels)


def pooled(study: Study, per_trial: dict[str, dict[str, list[float]]], labels: list[str]) -> list[str]:
    """Each agent's paired ratio to the reference over the trials of every simulated test together (one score
    per agent, e.g. for a choice on validation seeds); nothing for fewer than two tests."""
    from magenv.stats import paired_ratio

    groups = [g for g in per_trial if g != RECORDINGS]
    if len(groups) < 2:
        return []
    refs = np.concatenate([per_trial[g][study.reference_of(g)] for g in groups])
    out = ["", f"over all {len(refs)} trials of {', '.join(groups)}, paired ratio to the reference:"]
    for label in labels:
        pr = paired_ratio(np.concatenate([per_trial[g][label] for g in groups]), refs)
        out.append(f"- {label}: {pr.ratio_text()}")
    return out


def main(study: Study, argv: list[str] | None = None) -> int:
    """Measure and print the study's table."""
    import magenv  # noqa: F401  (registers the envs)

    args = parse(study, argv)
    t0 = time.time()
    per_trial = measure(study, args)
    kind = "validation" if args.validation else "held-out"
    cut = "" if args.duration is None else f", trials cut to {args.duration:g} s"
    span = f"{kind} seeds {args.seeds[0]}:{args.seeds[-1] + 1} ({len(args.seeds)} per test){cut}"
    where = [span] * any(g != RECORDINGS for g in per_trial) + ["the recordings"] * (RECORDINGS in per_trial)
    print(f"{study.env_id}, {' and '.join(where)}; total RMSE °, mean over the trials")
    print("\n".join(table(study, per_trial, args.agent)))
    print(f"({time.time() - t0:.0f} s)")
    return 0
