"""Seed lists on the command line: ``0:10`` (a range, end excluded), ``3,5,8``, or ``7``."""

from __future__ import annotations


def parse_seeds(text: str) -> list[int]:
    """Parse a seed list; raises ValueError naming the text if it is malformed or empty."""
    try:
        if ":" in text:
            start, stop = (int(x) for x in text.split(":"))
            seeds = list(range(start, stop))
        else:
            seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"bad seed list {text!r}: use START:STOP, a comma list, or one number") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"bad seed list {text!r}: needs at least one seed, none negative")
    return seeds
