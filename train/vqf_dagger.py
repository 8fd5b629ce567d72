"""Train the MagVQF-v0 DAgger student on recordings and simulation; leave-recordings-out cross-validation.

    python -m magenv.train.vqf_dagger --out runs/vqf_cv            # the folds: held-out figures
    python -m magenv.train.vqf_dagger --out runs/vqf_all --final   # all nine recordings: the shipped agent

Every hyperparameter is in :class:`Config`. A fold trains on the recordings not
in it plus simulated training trials (seeds ≥ 10000) and is scored on its own
recordings, which it never saw, and on held-out simulated seeds (< 5000); the
paired ratios to VQF (``magenv.stats.paired_ratio``) are printed per fold and
pooled over the folds, so each recording's figure comes from a student that
did not train on it. Each fold keeps the DAgger round of the lowest
:func:`validation_ratio` (validation seeds 5000–9999 and its own training
recordings only). ``--final`` trains on all nine (the shipped
``pretrained:magenv/MagVQF-v0``), whose figures on the recordings are
therefore training figures and are not reported.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

FOLDS = (("02", "24", "29"), ("05", "30", "32"), ("07", "10", "34"))  # each: undisturbed and magnet trials


@dataclass
class Config:
    rejection: str = "on"  # the student acts on top of VQF's own rejection
    decision_every: int = 32  # samples per decision (≈ 9 Hz at BROAD's 286 Hz)
    horizon_s: float = 1.5  # s, the oracle's look-ahead
    iterations: int = 2  # DAgger rounds (round 0: the oracle's own trajectories)
    sim_scenarios: tuple = ("dynamic_magnet", "stationary_magnet")
    sim_trials: tuple = (4, 4)  # simulated training trials of each sim scenario (seeds ≥ 10000)
    eval_seeds: tuple = (0, 8)  # held-out simulated seeds for the figures
    hidden: tuple = (64, 64)
    fit_steps: int = 3000
    members: int = 5  # MLPs per student (seeds seed…seed+4), acting with their mean trust
    rule: str | None = None  # a tuned rule whose trust u is a student input ("vqf_fan_lambda"; None: none)
    val_seeds: tuple = (5000, 5004)  # simulated validation seeds: the round kept (with the training recordings)
    seed: int = 0
    folds: tuple = field(default=FOLDS)


def _env_kwargs(cfg: Config) -> dict:
    return {"rejection": cfg.rejection, "decision_every": cfg.decision_every}


class Labeller:
    """Labelled decisions per trial and round, kept on disk (``cache/NAME.rR.npz``): round 0 (the oracle's
    own trajectories) does not depend on the fold, so every fold and the final fit reuse it."""

    def __init__(self, cfg: Config, cache: Path, log):
        self.cfg, self.cache, self.log = cfg, cache, log
        cache.mkdir(parents=True, exist_ok=True)

    def label(self, trial, rnd: int, student=None, tag: str = "") -> tuple:
        from magenv.agents import dagger_vqf as dv
        from magenv.baselines.oracle_vqf import candidate_costs
        from magenv.envs.vqf import FEATURES

        path = self.cache / f"{trial.name.replace('#', '_')}.r{rnd}{tag}.npz"
        if path.is_file():
            z = np.load(path)
            return z["x"], z["c"], z["s"]
        d = len(FEATURES) * (1 + len(dv.LAGS))
        memory = dv.Student([], np.zeros(d), np.ones(d), dv.CANDIDATES)
        act = None if student is None else student.act
        t0 = time.time()
        x, c, scale = dv.rollout(trial, _env_kwargs(self.cfg), candidate_costs, self.cfg.horizon_s, act, memory)
        s = np.full(len(x), scale)
        np.savez(path, x=x, c=c, s=s)
        self.log(f"    labelled {trial.name} round {rnd}{tag}: {len(x)} decisions, {time.time() - t0:.0f} s")
        return x, c, s


def sim_training_trials(cfg: Config) -> list:
    from magenv.scenarios import make_trial

    return [
        make_trial(s, 10000 + 100 * j + i)
        for j, (s, count) in enumerate(zip(cfg.sim_scenarios, cfg.sim_trials))
        for i in range(count)
    ]


def rule_params(cfg: Config) -> tuple[float, float] | None:
    """(norm_tol, th_dip_deg) of the student's rule input: ``magenv tune``'s file for ``cfg.rule``."""
    from magenv import registry

    if cfg.rule is None:
        return None
    params = registry.tuned_params(cfg.rule)
    return params["norm_tol"], params["th_dip_deg"]


def fit_on(cfg: Config, data: list, seed: int):
    from magenv.agents import dagger_vqf as dv

    xs, cs, ss = (np.concatenate([d[i] for d in data]) for i in range(3))
    return dv.fit(xs, cs, ss, cfg.hidden, cfg.fit_steps, seed=seed, rule=rule_params(cfg), members=cfg.members)


def validation_ratio(cfg: Config, student, recordings: list) -> float:
    """Mean over the sim scenarios' validation seeds and the (training) recordings of the student's
    ratio of mean total RMSE to VQF's: the model-selection figure (never a reported seed or recording)."""
    from magenv.agents import dagger_vqf as dv
    from magenv.scenarios import make_trial

    policy = dv.StudentPolicy(student, _env_kwargs(cfg))
    groups = [[make_trial(s, seed) for seed in range(*cfg.val_seeds)] for s in cfg.sim_scenarios] + [recordings]
    return float(np.mean([np.mean(score(policy, g)) / np.mean(score("vqf", g)) for g in groups]))


def train_student(cfg: Config, recordings: list, labeller: Labeller, tag: str, log) -> tuple:
    """DAgger over ``recordings`` plus simulated training trials: round 0 the oracle's trajectories, each
    further round the latest student's, labelled by the oracle; keeps the round of the lowest
    :func:`validation_ratio`; returns (student, the kept round)."""
    trials = [*recordings, *sim_training_trials(cfg)]
    data = [labeller.label(t, 0) for t in trials]
    student = fit_on(cfg, data, cfg.seed)
    best = (validation_ratio(cfg, student, recordings), 0, student)
    log(f"  round 0: validation ratio {best[0]:.3f}")
    for rnd in range(1, cfg.iterations):
        data += [labeller.label(t, rnd, student, tag) for t in trials]
        student = fit_on(cfg, data, cfg.seed + rnd)
        val = validation_ratio(cfg, student, recordings)
        log(f"  round {rnd}: {sum(len(d[0]) for d in data)} labelled decisions, validation ratio {val:.3f}")
        best = min(best, (val, rnd, student), key=lambda b: b[0])
    return best[2], best[1]


def score(policy_or_name, trials) -> list[float]:
    """Total RMSE (°) of a method (a Policy, or a registry name) on each trial."""
    from magenv import evaluation, registry

    method = registry.make(policy_or_name) if isinstance(policy_or_name, str) else policy_or_name
    runner = evaluation.PolicyRunner()
    return [evaluation.run_method("m", method, t, runner).scored.total for t in trials]


def main(argv=None) -> int:
    from magenv.agents import dagger_vqf as dv
    from magenv.recordings import list_recordings, load_recording
    from magenv.scenarios import make_trial
    from magenv.stats import paired_ratio

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--final", action="store_true", help="train on all nine recordings (the shipped agent)")
    p.add_argument("--folds", default=None, help="comma list of fold indices to run (default all)")
    args = p.parse_args(argv)
    cfg = Config()
    args.out.mkdir(parents=True, exist_ok=True)
    logf = open(args.out / "log.txt", "a")

    def log(msg):
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    log(f"config {json.dumps(asdict(cfg))}")
    every = {p.stem[:2]: load_recording(p) for p in list_recordings()}
    labeller = Labeller(cfg, args.out / "cache", log)
    if args.final:  # all nine recordings: round 0 and every fold's student rounds found in the cache
        trials = [*every.values(), *sim_training_trials(cfg)]
        data = [labeller.label(t, 0) for t in trials]
        data += [(lambda z: (z["x"], z["c"], z["s"]))(np.load(p)) for p in sorted(labeller.cache.glob("*.r[1-9]*.npz"))]
        student = fit_on(cfg, data, cfg.seed)
        final = args.out / "final"
        meta = {"trained_on": sorted(every), "decisions": int(sum(len(d[0]) for d in data)), "config": asdict(cfg)}
        dv.save(final, student, _env_kwargs(cfg), json.loads(json.dumps(meta)))
        log(f"saved {final} ({meta['decisions']} labelled decisions)")
        return 0
    sims = {s: [make_trial(s, seed) for seed in range(*cfg.eval_seeds)] for s in cfg.sim_scenarios}
    rows = []
    folds = [int(i) for i in args.folds.split(",")] if args.folds else range(len(cfg.folds))
    for f in folds:
        held = cfg.folds[f]
        log(f"fold {f}: held out {held}")
        train = [t for key, t in every.items() if key not in held]
        student, kept = train_student(cfg, train, labeller, f".fold{f}", log)
        run_dir = dv.save(args.out / f"fold{f}", student, _env_kwargs(cfg), {"held_out": list(held), "round": kept})
        policy = dv.load_policy(run_dir)
        tests = [every[k] for k in held]
        for name, trials in [("recordings", tests), *sims.items()]:
            a, b = score(policy, trials), score("vqf", trials)
            for t, x, y in zip(trials, a, b):
                rows.append({"fold": f, "group": name, "trial": t.name, "agent": x, "vqf": y})
                log(f"    {t.name}: agent {x:.3f} vqf {y:.3f}")
            r = paired_ratio(a, b)
            log(f"  {name}: agent {np.mean(a):.3f} vqf {np.mean(b):.3f} ratio {r.ratio_text()}")
        (args.out / f"cv_fold{f}.json").write_text(json.dumps([r for r in rows if r["fold"] == f], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
