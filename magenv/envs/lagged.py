"""Memory for an extended observation: the current features and their copies some decisions earlier.

An env's extended observation (``features="extended"``) is [base features,
extra causal features] of the current decision followed, for each lag L in
its ``lags``, by the same block as it was L decisions earlier (before the
first decision: the first observation). :func:`extended_table` names and
documents the columns; :func:`compose` fills them from a ring of past rows;
:func:`observation_table` reads an env's ``features`` option.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.envs.features import Feature, FeatureTable

EXTENDED_OPTION = "extended"  # features="extended": the whole extended table


def extended_table(current: Sequence[Feature], lags: Sequence[int]) -> FeatureTable:
    """The table of ``current`` followed by its copies ``f_lagL`` for each lag L (decisions)."""
    lagged = (
        Feature(
            f"{f.name}_lag{lag}",
            f.low,
            f.high,
            f.unit,
            f"`{f.name}` {lag} decisions earlier (before the start: the first observation)",
        )
        for lag in lags
        for f in current
    )
    return FeatureTable(*current, *lagged)


def ring(lags: Sequence[int], width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows (max(lags) + 1, width), count (1,) int64, lags (L,) int64): the state :func:`compose` keeps."""
    return np.zeros((max(lags) + 1, width)), np.zeros(1, np.int64), np.asarray(lags, np.int64)


@njit(cache=True)
def compose(base, extra, rows, count, lags, stepped, feat):
    """``feat`` = [base, extra] and their lagged copies; ``stepped``: a decision was just made (count + 1).

    rows (R, width): ring of the current blocks by decision; count (1,): decisions so far."""
    if stepped:
        count[0] += 1
    d = count[0]
    length, width = rows.shape
    nb = base.shape[0]
    row = rows[d % length]
    row[:nb] = base
    row[nb:width] = extra
    feat[:width] = row
    for li in range(lags.shape[0]):
        feat[(li + 1) * width : (li + 2) * width] = rows[max(d - lags[li], 0) % length]


class Memory(NamedTuple):
    """The streaming state of an env's extra features on one trial (arrays updated in place); an env's memory
    module subclasses it with its ``start``, or writes a NamedTuple of its own where it keeps more."""

    state: np.ndarray  # (N_STATE,) the memory module's layout constants
    value: np.ndarray  # (len(EXTRA),) the features of the next decision (zeros before any sample is fused)


def anchored(n_state: int, q0: np.ndarray, offsets) -> np.ndarray:
    """A memory's state (n_state,): zeros, the quaternion ``q0`` (4,) at each of ``offsets``."""
    state = np.zeros(n_state)
    for o in offsets:
        state[o : o + 4] = q0
    return state


def observation_table(
    features, base: FeatureTable, extended: FeatureTable
) -> tuple[Sequence[str] | None, FeatureTable]:
    """An env's ``features`` option → (names to select, None = all; the table they come from): ``"extended"``
    is the whole extended table; a list of names uses ``base``, or ``extended`` if it names any other feature."""
    if isinstance(features, str):
        if features != EXTENDED_OPTION:
            raise ValueError(f"features must be None, {EXTENDED_OPTION!r} or a list of names, got {features!r}")
        return None, extended
    if features is not None and any(f not in base.names for f in features):
        return features, extended
    return features, base
