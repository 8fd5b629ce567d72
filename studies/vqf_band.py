"""MagVQF-v0: does a departure band chosen on real recordings transfer to a recording it was not chosen on?

    python -m studies.vqf_band [--agent RUN|pretrained:ID ...] [--bands 0.1 0.25 0.5 1] [--shapes fixed,shrink]
        [--recordings FILE ...]

A rule-guarded student (``guard.fallback: rule``) departs from its rule by at most its guard's ``band`` b. The
candidates are the rule itself (``vqf_fan_rejection_tuned``: b = 0) and every student × b × band shape:
``fixed`` (the student's own clip to the rule's u ± b) and ``shrink`` (u_rule ± b·(1 − u_rule): no departure where
the rule trusts the magnetometer fully, u ∈ [0, 1]; a variant of this study only, not of the product). Each is
scored on each recording (default: the shared BROAD ones) as the ratio of its total RMSE to ``vqf``'s.

Nested leave-one-recording-out: for each recording r, the candidate with the lowest geometric-mean ratio over the
other recordings is chosen, and scored on r alone. The held-out ratios estimate what *choosing the band on
recordings* gives on a recording it was not chosen on; they are compared with the rule's and with each student
as shipped (its band chosen on simulation only) by the paired ratio (``magenv.stats.paired_ratio``). The
candidate chosen on all recordings is printed too: its figures there are in-sample, not an estimate.
It prints what it measures; nothing here is a test.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from studies.vqf_real import REFERENCE, group_of, score

RULE = "vqf_fan_rejection_tuned"  # the rule a rule-guarded MagVQF-v0 student departs from


def shrink(student, band: float) -> None:
    """Replace ``student``'s clip by u_rule ± band·(1 − u_rule) (its fallback's u, clipped to [0, 1])."""

    def bounded(action: np.ndarray, obs: np.ndarray) -> np.ndarray:
        fb = student.fallback(obs)
        width = band * (1.0 - np.clip(fb, 0.0, 1.0))
        return np.clip(action, fb - width, fb + width)

    student.bounded = bounded


def candidates(agents: list[str], bands: list[float], shapes: list[str]) -> dict:
    """name → method: the rule, and every agent × band × shape (``AGENT fixed|shrink b``)."""
    from magenv import registry

    out = {RULE: registry.make(RULE)}
    for agent in agents:
        for shape in shapes:
            for band in bands:
                method = registry.make(registry.AGENT_PREFIX + agent)
                student = method.student
                if student.guard is None or student.guard["fallback"] != "rule":
                    raise SystemExit(f"{agent}: its student has no rule guard (guard.fallback: rule) to band")
                student.guard["band"] = band
                if shape == "shrink":
                    shrink(student, band)
                out[f"{agent} {shape} {band:g}"] = method
    return out


def nested_choice(log_ratio: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
    """For each recording i, the candidate of least mean log ratio over the others, and its log ratio on i."""
    names = list(log_ratio)
    n = len(next(iter(log_ratio.values())))
    picks, held = [], np.empty(n)
    for i in range(n):
        others = np.arange(n) != i
        best = min(names, key=lambda c: float(np.mean(log_ratio[c][others])))
        picks.append(best)
        held[i] = log_ratio[best][i]
    return picks, held


def main(argv: list[str] | None = None) -> int:
    import magenv  # noqa: F401  (registers the envs)
    from magenv import registry
    from magenv.recordings import list_recordings, load_recording
    from magenv.stats import paired_ratio

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", action="append", default=None, help="rule-guarded student: run folder or pretrained:ID")
    p.add_argument("--bands", nargs="+", type=float, default=[0.1, 0.25, 0.5, 1.0], help="bands b > 0 to try")
    p.add_argument("--shapes", default="fixed,shrink", help="band shapes to try (default %(default)s)")
    p.add_argument("--recordings", nargs="+", default=None, help="recording files (default: the shared BROAD ones)")
    args = p.parse_args(argv)
    agents = args.agent or ["pretrained:magenv/MagVQF-v0"]
    if any(not b > 0 for b in args.bands):
        raise SystemExit(f"--bands must be positive (b = 0 is the rule, always a candidate), got {args.bands}")
    shapes = args.shapes.split(",")
    if not shapes or set(shapes) - {"fixed", "shrink"}:
        raise SystemExit(f"--shapes: a comma list of fixed and shrink, got {args.shapes!r}")
    t0 = time.time()
    trials = [load_recording(f) for f in (args.recordings or list_recordings())]
    if len(trials) < 3:
        raise SystemExit(f"leave-one-recording-out needs at least 3 recordings, got {len(trials)}")
    methods = candidates(agents, args.bands, shapes)
    shipped = {f"{a} (as shipped)": registry.make(registry.AGENT_PREFIX + a) for a in agents}
    scores = score({REFERENCE: registry.make(REFERENCE), **methods, **shipped}, trials)
    recs = [t.name for t in trials]
    ref = np.array([scores[REFERENCE][r] for r in recs])
    log_ratio = {c: np.log(np.array([scores[c][r] for r in recs]) / ref) for c in methods}

    print(f"MagVQF-v0 on {len(recs)} recordings: candidates' ratio to {REFERENCE} (geometric mean, in-sample), worst")
    for c, lr in log_ratio.items():
        print(f"  {c:48s} {np.exp(lr.mean()):.3f}  worst {np.exp(lr.max()):.2f}")
    picks, held = nested_choice(log_ratio)
    print("\nnested leave-one-recording-out: recording → candidate chosen on the others, its ratio on the recording")
    for r, c, h in zip(recs, picks, held):
        print(f"  {r:48s} {c:40s} {np.exp(h):.2f}")
    rows = {"chosen on the other recordings": np.exp(held) * ref, RULE: np.array([scores[RULE][r] for r in recs])}
    rows.update({name: np.array([scores[name][r] for r in recs]) for name in shipped})
    groups = sorted({group_of(r) for r in recs}) + ["all"]
    print("\nratio to " + REFERENCE + " (geometric mean [95 % CI]), worst recording")
    print("| method | " + " | ".join(groups) + " | worst |\n" + "|---" * (len(groups) + 2) + "|")
    for name, rmse in rows.items():
        cells = []
        for g in groups:
            idx = [i for i, r in enumerate(recs) if g in ("all", group_of(r))]
            ratio = paired_ratio(rmse[idx], ref[idx])
            cells.append(ratio.ratio_text(2) if len(idx) > 1 else f"{ratio.ratio:.2f}")
        print(f"| {name} | " + " | ".join(cells) + f" | {np.max(rmse / ref):.2f} |")
    nested = rows["chosen on the other recordings"]
    for name in [RULE, *shipped]:
        print(f"chosen on the other recordings / {name}: {paired_ratio(nested, rows[name]).ratio_text(2)}")
    chosen = min(log_ratio, key=lambda c: float(np.mean(log_ratio[c])))
    print(f"\nchosen on all {len(recs)} (in-sample): {chosen}, {np.exp(log_ratio[chosen].mean()):.3f}")
    print(f"({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
