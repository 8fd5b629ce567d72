"""Scenario-config helpers: value checks (one number in a range, a (low, high) pair, a list of (start, hold)
intervals; each raises ValueError naming the field and the value) and :func:`config_json` for a trial's meta.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


def check_number(name: str, value, lo=-math.inf, hi=math.inf, lo_open=False) -> None:
    """``value`` is a finite real number (not a bool) in [lo, hi] (or (lo, hi] with ``lo_open``)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < lo or value > hi or (lo_open and value == lo):
        raise ValueError(f"{name} must be a number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")


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


def config_json(value):
    """``value`` (a config dataclass, dict, sequence, array or number) as plain JSON types, recursively."""
    if dataclasses.is_dataclass(value):
        return {k: config_json(v) for k, v in dataclasses.asdict(value).items()}
    if isinstance(value, dict):
        return {k: config_json(v) for k, v in value.items()}
    if isinstance(value, (tuple, list, np.ndarray)):
        return [config_json(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return int(value)
    return value


def apply_overrides(name: str, cfg, overrides: dict):
    """Scenario config ``cfg`` (of scenario ``name``) with ``overrides`` applied.

    A key is a field of the config, or else of its ``sensor`` (a
    ``SensorConfig``); an unknown key or a bad value raises ValueError naming it.
    """
    from magenv.sim.sensors import SensorConfig

    own = {f.name for f in dataclasses.fields(cfg)}
    sensor_fields = {f.name for f in dataclasses.fields(SensorConfig)}
    unknown = sorted(k for k in overrides if k not in own and k not in sensor_fields)
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(map(repr, unknown))} for scenario {name!r}; "
                         f"known: {', '.join(sorted(own))}; sensor: {', '.join(sorted(sensor_fields))}")
    sensor_over = {k: v for k, v in overrides.items() if k not in own}
    cfg_over = {k: v for k, v in overrides.items() if k in own}
    try:
        if sensor_over:
            cfg_over["sensor"] = dataclasses.replace(cfg_over.get("sensor", cfg.sensor), **sensor_over)
        return dataclasses.replace(cfg, **cfg_over)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"scenario {name!r}: bad parameter value: {exc}") from None
