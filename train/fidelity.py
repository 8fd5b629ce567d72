"""``magenv fidelity``: each method on real recordings beside the same method on their twins.

    magenv fidelity --recordings FILE ... [--methods M1,M2,...] [--seeds N] [--csv FILE] [--plot FILE]

For each recording, the twin ``twin:FILE`` (``magenv.scenarios.twin``) is made with seeds 0 … N−1; every
method runs on the recording and on each twin (``magenv.fidelity.measure``). Printed: per method the real
and twin RMSE means over the recordings and their ratio, Spearman's ρ per recording, per recording group
and overall, and how many rules have real / twin within [0.67, 1.5]. ``--csv`` writes one row per
recording and method (header ``recording,method,real_total,twin_total,real_heading,twin_heading``,
degrees, twin = mean over the seeds); ``--plot`` draws real against twin per method and recording.
Exit status 1 if some method failed on some trial (the reasons are printed).
"""

from __future__ import annotations

import argparse

from magenv.agents.hyperparams import POSITIVE_INT
from magenv.train.cli import IMAGE_SUFFIXES, PARTIAL, CommandError, output_file, rule_arg


def add_arguments(p: argparse.ArgumentParser) -> None:
    from magenv.fidelity import DEFAULT_METHODS

    p.add_argument("--recordings", nargs="+", required=True, metavar="FILE", help="real recordings (BROAD HDF5)")
    p.add_argument("--methods", default=DEFAULT_METHODS, help="comma list of methods (default: %(default)s)")
    p.add_argument("--seeds", type=rule_arg(POSITIVE_INT), default=3, help="twin seeds per recording (default 3)")
    p.add_argument("--csv", default=None, metavar="FILE", help="write the per-recording table as CSV")
    p.add_argument("--plot", default=None, metavar="FILE", help="draw real against twin RMSE (PNG)")


def is_rule(method: str) -> bool:
    """Whether ``method`` is a trust rule (``magenv.fidelity.RULES`` or a Kalman-trust rule's ``_hand`` variant)."""
    from magenv.fidelity import RULES

    return method in RULES or (method.startswith("kf_") and method.endswith("_hand"))


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from magenv import fidelity, registry

    args.csv = output_file(args.csv, "--csv")
    args.plot = output_file(args.plot, "--plot", IMAGE_SUFFIXES)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    known = registry.names()
    bad = [m for m in methods if m not in known and not m.startswith(registry.AGENT_PREFIX)]
    if bad or not methods:
        raise CommandError(
            f"unknown method(s) {', '.join(map(repr, bad)) or '(none given)'}; known: {', '.join(known)}"
        )
    missing = [f for f in args.recordings if not Path(f).is_file()]
    if missing:
        raise CommandError(f"no such recording file(s): {', '.join(missing)}")
    rows = fidelity.measure(
        args.recordings, methods, registry.make, list(range(args.seeds)), progress=lambda s: print(s, flush=True)
    )
    print(fidelity.markdown(rows, [m for m in methods if is_rule(m)]))
    if args.csv:
        print(f"wrote {fidelity.write_csv(rows, args.csv)}")
    if args.plot:
        print(f"wrote {fidelity.plot(rows, args.plot)}")
    failed = [r for r in rows if r.error]
    for r in failed:
        print(f"n/a: {r.method} on {r.recording}: {r.error}")
    return PARTIAL if failed else 0
