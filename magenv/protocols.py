"""The two small protocols every method follows (the bottom layer: envs, methods and evaluation use them).

* A **Policy** acts inside an environment on the observation alone (a
  hand-crafted rule, or a trained agent loaded back): ``policy(obs) -> action``;
  a **BatchPolicy** (a trained agent) also acts for n envs in one call.
* An **Estimator** is a complete classical filter that cannot be phrased as a
  policy: it runs a whole Trial and returns its orientation estimate.

Either kind can be :class:`Tunable`: named parameters with search bounds,
for ``magenv tune`` (``magenv.registry.tunable_rules``).

``magenv.evaluation`` runs both kinds on the same trials and scores them with
``magenv.metrics``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from magenv.trial import Trial


@runtime_checkable
class Policy(Protocol):
    """Chooses the trust from the observation; never sees truth."""

    env_id: str  # the environment whose observations and actions it speaks

    def reset(self) -> None:
        """Forget any memory before a new episode."""

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Action for one observation."""


@runtime_checkable
class BatchPolicy(Policy, Protocol):
    """A Policy that also acts for n envs at once, in one call (a trained agent: one network forward for all);
    ``magenv.evaluation`` runs the trials of a batch together with it."""

    def act_batch(self, obs: np.ndarray, state: Any = None) -> tuple[np.ndarray, Any]:
        """(actions (n, …), state) for the observations (n, …) of n envs; ``state`` is None at the start of
        every env's episode, else what the previous call returned (a recurrent agent's memory per env)."""


@dataclass
class Estimate:
    """An estimator's output on one trial.

    Attributes:
        q: (N, 4) estimated orientation sensor → ENU, ``[w, x, y, z]``.
        trust: (N,) the magnetometer trust it used per sample (method-specific
            meaning, e.g. 1 − λ or a gate), or None.
    """

    q: np.ndarray
    trust: np.ndarray | None = None


@runtime_checkable
class Estimator(Protocol):
    """Runs a whole trial causally (sample by sample, no look-ahead)."""

    def run(self, trial: Trial) -> Estimate:
        """Estimate the orientation of every sample of ``trial``."""


class Tunable:
    """Mixin of a method with named parameters: ``PARAM_BOUNDS`` (name → (low, high)), read back by
    ``params`` and given to the constructor by ``from_params``. The constructor's defaults are the
    published values (``magenv tune`` starts there and never returns worse)."""

    PARAM_BOUNDS: dict[str, tuple[float, float]] = {}

    @property
    def params(self) -> dict[str, float]:
        """The parameters by name (constructor arguments)."""
        return {k: float(getattr(self, k)) for k in self.PARAM_BOUNDS}

    @classmethod
    def from_params(cls, params: dict[str, float], **kwargs):
        """An instance with these parameters (unknown names raise ValueError)."""
        unknown = set(params) - set(cls.PARAM_BOUNDS)
        if unknown:
            raise ValueError(f"{cls.__name__} has no parameter(s) {sorted(unknown)}; known: {list(cls.PARAM_BOUNDS)}")
        return cls(**params, **kwargs)


def is_policy(method) -> bool:
    """True for a Policy (has ``env_id`` and is callable), False for an Estimator (has ``run``).

    Raises TypeError for anything else.
    """
    if hasattr(method, "env_id") and callable(method):
        return True
    if hasattr(method, "run"):
        return False
    raise TypeError(f"{method!r} is neither a Policy (env_id + __call__) nor an Estimator (run(trial))")
