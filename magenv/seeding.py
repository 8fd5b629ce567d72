"""Trial seeds: the held-out range for evaluation and the range training draws from.

Evaluation (``magenv compare``, ``evaluate``, ``demo``, the held-out
evaluation during ``train``) uses trial seeds below ``HELD_OUT_BELOW``;
environments draw their training trials, and ``magenv tune`` its tuning
trials, at or above it. So no learned agent or tuned rule has seen a trial
it is scored on. Within the held-out range, seeds from ``VALIDATION_START``
up are for model selection (``train`` keeps the agent that scores best on
them) and the seeds below it for reports, so the reported trials never
chose the model either.
"""

from __future__ import annotations

import numpy as np

HELD_OUT_BELOW = 10_000
VALIDATION_START = 5_000
SEED_LIMIT = 2**31 - 1


def draw_training_seed(rng: np.random.Generator) -> int:
    """A trial seed in [HELD_OUT_BELOW, 2³¹ − 1) drawn from ``rng``."""
    return int(rng.integers(HELD_OUT_BELOW, SEED_LIMIT))
