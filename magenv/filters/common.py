"""The base of the env runners (moves to ``magenv.envs`` with the runners)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from magenv.trial import Trial

class TrialRunner:
    """Base of the env runners (one trial stepped k samples at a time): ``trial``, ``pos`` (next sample to fuse)."""

    trial: Trial
    pos: int

    @property
    def n(self) -> int:
        """Samples in the trial."""
        return self.trial.n

    @property
    def done(self) -> bool:
        """All samples fused."""
        return self.pos >= self.trial.n
