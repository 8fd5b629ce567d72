"""``magenv agents``: the trained agents shipped with magenv, usable as ``--agent pretrained:ENV_ID``.

    magenv agents

One line per agent: how to name it, its run folder, and the first line of its evaluation card
(``card.md`` in the folder: the held-out figures and how to reproduce them).
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """No options."""


def run(args: argparse.Namespace) -> int:
    from magenv.agents.loading import PRETRAINED_PREFIX, pretrained_agents

    shipped = pretrained_agents()
    if not shipped:
        print("no pretrained agents in this installation")
    for env_id, folder in shipped.items():
        card = folder / "card.md"
        summary = card.read_text().splitlines()[0].lstrip("# ") if card.is_file() else ""
        print(f"{PRETRAINED_PREFIX}{env_id}  {folder}  {summary}")
    return 0
