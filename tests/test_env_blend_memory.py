"""MagBlend-v0's extended observation (``features="extended"``) replays its seed (documented, causal, with memory:
``test_env_extended.py``)."""

from __future__ import annotations

from conftest import check_seeded_replay

import magenv  # noqa: F401  (registers the envs)
from magenv.envs import BLEND_ID


def test_extended_env_replays_its_seed():
    check_seeded_replay(
        BLEND_ID, {"scenario": "dynamic_magnet", "features": "extended", "episode_seconds": 3.0}, 10, [0.5] * 96, 96
    )
