"""Seed lists on the command line: ``0:10`` (a range, end excluded), ``3,5,8``, or ``7``."""

from __future__ import annotations

import argparse

from magenv.seeding import HELD_OUT_BELOW, VALIDATION_START

MAX_SEEDS = 10_000  # a longer list is a typo, not an experiment
#: the held-out trials per scenario on which the benchmarks report a learned agent against the rules (40: the
#: 20-trial intervals of the paper tests were too wide to decide a ≤ 0.9× target)
REPORT_SEEDS = "0:40"


def parse_seeds(text: str) -> list[int]:
    """Parse a seed list; raises ValueError naming the text if it is malformed, empty, negative or longer
    than ``MAX_SEEDS``."""
    try:
        if ":" in text:
            start, stop = (int(x) for x in text.split(":"))
            seeds: list[int] | range = range(start, stop)
        else:
            seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"bad seed list {text!r}: use START:STOP, a comma list, or one number") from None
    if not len(seeds) or min(seeds) < 0:
        raise ValueError(f"bad seed list {text!r}: needs at least one seed, none negative")
    if len(seeds) > MAX_SEEDS:
        raise ValueError(f"bad seed list {text!r}: {len(seeds)} seeds, at most {MAX_SEEDS}")
    return list(seeds)


def seeds_arg(text: str) -> list[int]:
    """:func:`parse_seeds` as an argparse ``type``: the error names the flag."""
    try:
        return parse_seeds(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def check_report_seeds(seeds: list[int], validation: bool) -> None:
    """Refuse seeds outside their use: reported figures take held-out seeds below ``VALIDATION_START``,
    model selection (``validation``) takes seeds in [VALIDATION_START, HELD_OUT_BELOW)."""
    if validation and not (min(seeds) >= VALIDATION_START and max(seeds) < HELD_OUT_BELOW):
        raise SystemExit(f"validation seeds lie in {VALIDATION_START}–{HELD_OUT_BELOW - 1}")
    if not validation and max(seeds) >= VALIDATION_START:
        raise SystemExit(f"reported figures use held-out seeds below {VALIDATION_START} (validation: model selection)")
