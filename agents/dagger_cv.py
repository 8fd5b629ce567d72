"""Leave-recordings-out cross-validation of a DAgger student that learns from real recordings.

``cross_validate(out, teacher, config, folds)`` (``magenv train --teacher NAME --cv recordings``) splits the
real recordings of a DAgger config — its ``recording:…`` entries and the recordings behind its ``twin:…`` and
``rtwin:…`` entries (a twin of a held-out recording counts as that recording) — into ``folds`` groups (sorted
by file name, dealt round-robin), trains one DAgger run per fold on the config without that group
(``out/foldF``, ``magenv.agents.dagger.train``; a finished fold is kept, an unfinished one resumed) and scores
each student closed loop on the recordings it never saw, beside the teacher's continuation rule on the same
recordings. Every recording is scored by exactly one student that never trained on it, nor on its twin.

``out/cv.csv`` (written whole, then renamed): fold, recording, the student's and the rule's RMSE (°,
the recording's own score mask), one row per held-out recording.
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path

from magenv.agents import dagger

TWINS = ("twin:", "rtwin:")  # twins and randomised twins of a recording
RESULTS = "cv.csv"


def recording_of(entry: str) -> Path | None:
    """The recording file behind a config entry (``recording:PATH``, ``twin:PATH`` or ``rtwin:PATH``), else None."""
    for prefix in (dagger.RECORDING, *TWINS):
        if entry.startswith(prefix):
            return Path(entry[len(prefix) :]).expanduser().resolve()
    return None


def make_folds(recordings: list[Path], folds: int) -> list[list[Path]]:
    """The recordings (sorted by name) dealt round-robin into ``folds`` groups; ValueError if fewer than
    ``folds`` ≥ 2 recordings."""
    unique = sorted(set(recordings), key=lambda p: p.name)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"folds must be an integer ≥ 2, got {folds!r}")
    if len(unique) < folds:
        raise ValueError(f"{folds} folds need at least {folds} recordings in the config, got {len(unique)}")
    return [unique[f::folds] for f in range(folds)]


def fold_scenarios(scenarios: list[str], held: list[Path]) -> list[str]:
    """The config entries a fold trains on: all but the recordings ``held`` out and their twins."""
    return [sc for sc in scenarios if recording_of(sc) not in held]


def cross_validate(
    out: str | Path, teacher, config: dict, folds: int = 3, log: Callable[[str], None] = print
) -> list[dict]:
    """Run the folds into ``out`` (module docstring) and return the rows of ``cv.csv``."""
    out = Path(out)
    cfg = dagger.check_config(config)
    groups = make_folds([p for p in map(recording_of, cfg["scenarios"]) if p is not None], folds)
    episodes = None
    rows: list[dict] = []
    for f, held in enumerate(groups):
        kept = fold_scenarios(cfg["scenarios"], held)
        if not kept:
            raise ValueError(f"fold {f} holds out every entry of the config; add simulated scenarios")
        run = out / f"fold{f}"
        log(f"fold {f}: held out {', '.join(p.stem for p in held)}")
        done = dagger.is_run(run) and len(dagger._read_log(run / dagger.LOG)) >= cfg["iterations"]
        if not done:
            fold = {**config, "scenarios": kept}
            if isinstance(cfg["trials_per_scenario"], dict):  # the fold's scenarios only
                fold["trials_per_scenario"] = {k: n for k, n in cfg["trials_per_scenario"].items() if k in kept}
            dagger.train(run, teacher, fold, log, resume=dagger.is_run(run))
        policy = dagger.load_policy(run)
        if episodes is None:
            episodes = dagger.Episodes(policy.env_id, policy.env_kwargs, teacher)

        def student(o, runner, costs, pi=policy):
            return pi(o)

        def rule_act(o, runner, costs):
            return teacher.continuation_action(runner)

        for path in held:
            trial = dagger.make_trial(f"{dagger.RECORDING}{path}", 0)
            agent = episodes.run(trial, student, label_every=0).rmse
            rule = episodes.run(trial, rule_act, label_every=0)
            rows.append({"fold": f, "recording": path.stem, "agent_rmse": agent, "rule_rmse": rule.rmse})
            log(f"  {path.stem}: student {agent:.3f}°, rule {rule.rmse:.3f}° ({agent / rule.rmse:.3f}×)")
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / (RESULTS + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    tmp.replace(out / RESULTS)
    return rows
