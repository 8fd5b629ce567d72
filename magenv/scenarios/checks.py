"""Value checks for scenario configs: each raises ValueError naming the field and the value.

One number in a range, a (low, high) pair, n numbers, a list of (start, hold) intervals, an instance of a
class, and :func:`check_shared_fields` for the fields every world's config has.
"""

from __future__ import annotations

import math

import numpy as np

from magenv.sim.sensors import SensorConfig


def check_number(name: str, value, lo=-math.inf, hi=math.inf, lo_open=False) -> None:
    """``value`` is a finite real number (not a bool) in [lo, hi] (or (lo, hi] with ``lo_open``)."""
    ok = (
        isinstance(value, (int, float, np.integer, np.floating))
        and not isinstance(value, bool)
        and math.isfinite(value)
    )
    if not ok or value < lo or value > hi or (lo_open and value == lo):
        raise ValueError(f"{name} must be a number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")


def check_numbers(name: str, value, n: int, lo=-math.inf, hi=math.inf, what: str = "numbers") -> None:
    """``value`` is a sequence of ``n`` numbers, each in [lo, hi]; ``what`` names them in the message."""
    if not isinstance(value, (tuple, list, np.ndarray)) or len(value) != n:
        raise ValueError(f"{name} must be {n} {what}, got {value!r}")
    for i, v in enumerate(value):
        check_number(f"{name}[{i}]", v, lo, hi)


def check_range(name: str, value, lo=-math.inf, hi=math.inf) -> None:
    """``value`` is a (low, high) tuple or list of numbers with lo ≤ low ≤ high ≤ hi."""
    if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(isinstance(v, (int, float)) for v in value)):
        raise ValueError(f"{name} must be a (low, high) pair of numbers, got {value!r}")
    if not (lo <= value[0] <= value[1] <= hi):
        raise ValueError(f"{name} must satisfy {lo} ≤ low ≤ high ≤ {hi}, got {value!r}")


def check_intervals(name: str, value) -> None:
    """Every entry of ``value`` is a (start s ≥ 0, hold s ≥ 0) pair."""
    for i, d in enumerate(value):
        if len(d) != 2 or d[0] < 0 or d[1] < 0:
            raise ValueError(f"{name}[{i}] must be (start s ≥ 0, hold s ≥ 0), got {d!r}")


def check_instance(name: str, value, cls: type) -> None:
    """``value`` is a ``cls``."""
    if not isinstance(value, cls):
        raise ValueError(f"{name} must be a {cls.__module__}.{cls.__qualname__}, got {type(value).__name__}")


def check_shared_fields(cfg) -> None:
    """The fields every world's config has, besides its own ``duration`` and ``rate`` bounds: the undisturbed
    Earth field ``field_norm`` µT in (0, 1000] and ``field_dip`` ° in [-90, 90], ``sensor`` a SensorConfig,
    and ``duration`` s × ``rate`` Hz at least 2 samples."""
    check_number("field_norm", cfg.field_norm, 0.0, 1000.0, lo_open=True)
    check_number("field_dip", cfg.field_dip, -90.0, 90.0)
    check_instance("sensor", cfg.sensor, SensorConfig)
    if cfg.duration * cfg.rate < 2:
        raise ValueError(f"duration × rate must give at least 2 samples, got {cfg.duration} s × {cfg.rate} Hz")
