"""``magenv paper``: print a paper check (``magenv.papers``).

magenv paper constraint [--seeds 0:5] [--methods strapdown,cf_conventional,cf_constraint,cf_gated]
magenv paper qsf [--set sigma_acc=3.0 …]
magenv paper innovation
magenv paper qsf-recordings
magenv paper references
"""

from __future__ import annotations

import argparse

import numpy as np

from magenv.train.cli import CommandError
from magenv.train.seeds import seeds_arg

CHECKS = ("constraint", "qsf", "innovation", "qsf-recordings", "references")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from magenv.papers import TABLE2_METHODS

    p.add_argument("check", choices=CHECKS, help="which paper check")
    p.add_argument(
        "--seeds", type=seeds_arg, default="0:5", help="constraint: trial seeds START:STOP (default %(default)s)"
    )
    p.add_argument(
        "--methods",
        default=",".join(TABLE2_METHODS),
        help="constraint: comma list of method names, e.g. adding agent:RUN_DIR (default %(default)s)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="qsf: a keyword of magenv.filters.qsf.make_params, e.g. sigma_acc=3.0 (repeatable)",
    )


def _print_table2(seeds: list[int], methods: list[str]) -> None:
    from magenv.papers import table2

    rows = table2(seeds, methods)
    print(f"Table 2 reproduced on seeds {seeds[0]}..{seeds[-1]} (RMSE °, simulation mean ± std over seeds | paper)")
    print(f"{'test':<17} {'method':<16} {'roll':>16} {'pitch':>16} {'yaw':>16} {'avg':>13}")
    for r in rows:
        cells = [f"{m:5.2f}±{s:4.2f} |{p:5.2f}" for m, s, p in zip(r["sim"], r["sim_std"], r["paper"])]
        print(
            f"{r['test']:<17} {r['method']:<16} {cells[0]:>16} {cells[1]:>16} {cells[2]:>16} "
            f"{r['sim'].mean():5.2f} |{r['paper'].mean():5.2f}"
        )


def _print_references() -> None:
    from magenv.papers import README_VQF, score_recordings

    table = score_recordings()
    methods = list(next(iter(table.values())))
    fmt = lambda s: f"{s.total:5.2f} /{s.heading:5.2f} /{s.inclination:5.2f}"
    print("RMSE, degrees: total / heading / inclination over the movement mask (BROAD protocol)\n")
    print(f"{'trial':6} {'README VQF':>20}  " + "  ".join(f"{m:>20}" for m in methods))
    for name, row in table.items():
        ref = README_VQF[name[:2]][0] if name[:2] in README_VQF else None
        ref_s = f"{ref[0]:5.2f} /{ref[1]:5.2f} /{ref[2]:5.2f}" if ref else ""
        print(f"{name[:6]:6} {ref_s:>20}  " + "  ".join(f"{fmt(row[m]):>20}" for m in methods))
    print(
        f"{'mean':6} {'':>20}  "
        + "  ".join(f"{np.mean([r[m].total for r in table.values()]):5.2f}".rjust(20) for m in methods)
    )


def _settings(pairs: list[str]) -> dict[str, float]:
    out = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        try:
            out[name] = float(value)
        except ValueError:
            raise CommandError(f"--set expects NAME=NUMBER, got {pair!r}") from None
        if not sep or not name:
            raise CommandError(f"--set expects NAME=NUMBER, got {pair!r}")
    return out


def run(args: argparse.Namespace) -> int:
    from magenv import papers

    try:
        if args.check == "constraint":
            _print_table2(args.seeds, [m.strip() for m in args.methods.split(",") if m.strip()])
        elif args.check == "qsf":
            print(papers.qsf_table(**_settings(args.set)))
        elif args.check == "innovation":
            print(papers.innovation_check())
        elif args.check == "qsf-recordings":
            print(papers.qsf_recordings())
        else:
            _print_references()
    except (TypeError, ValueError) as exc:
        raise CommandError(str(exc)) from None
    return 0
