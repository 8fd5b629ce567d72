"""What every world's scenarios share: :class:`World`, one world's table of named scenarios and the way a
config and a seed become a Trial, and the ``meta`` every simulated Trial carries.

A world module (``gimbal``, ``twolink``, ``handheld``) writes frozen config dataclasses (each with
``duration`` s, ``rate`` Hz, ``field_norm`` µT, ``field_dip`` ° and ``sensor``, a SensorConfig), a table
``SCENARIOS`` (name → default config) and a function ``simulate(name, cfg, seed, streams) -> Trial``, and
exports ``WORLD = World(...)``; ``magenv.scenarios`` puts the worlds behind one registry.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from magenv.checks import check_instance, check_number, check_range, check_site
from magenv.sim.sensors import SensorConfig
from magenv.trial import META_SCENARIO, META_SEED, Trial

#: A sample counts as stationary when the true (noise-free) angular rate is below this, rad/s.
STATIONARY_RATE = 1e-3


def check_shared_fields(cfg) -> None:
    """The config's :func:`limited` fields (:func:`check_limits`), then the fields every world's config has: the
    undisturbed Earth field ``field_norm`` µT in (0, 1000] and ``field_dip`` ° in [-90, 90], ``sensor`` a
    SensorConfig, and ``duration`` s × ``rate`` Hz at least 2 samples. Raises ValueError (TypeError for a
    non-number) naming the field (``magenv.checks``)."""
    check_limits(cfg)
    check_site(cfg.field_norm, cfg.field_dip)
    check_instance("sensor", cfg.sensor, SensorConfig)
    if cfg.duration * cfg.rate < 2:
        raise ValueError(f"duration × rate must give at least 2 samples, got {cfg.duration} s × {cfg.rate} Hz")


def limited(default, lo: float | str = -math.inf, hi: float | str = math.inf, lo_open: bool = False) -> Any:
    """A config field: its ``default`` and its bounds, checked by :func:`check_limits`. A number must lie in
    [lo, hi] (``lo_open``: lo excluded), a (low, high) pair must have lo ≤ low ≤ high ≤ hi; a bound given as a
    string is the value of that field. A subclass that only changes the default keeps the bounds."""
    return dataclasses.field(default=default, metadata={"limits": (lo, hi, lo_open)})


def check_limits(cfg) -> None:
    """Every :func:`limited` field of config ``cfg`` within its bounds (``magenv.checks.check_number`` for a
    number, ``check_range`` for a pair): ValueError (TypeError for a non-number) naming the field."""
    for name in cfg.__dataclass_fields__:
        limits = next(
            (
                f.metadata["limits"]
                for f in (k.__dict__.get("__dataclass_fields__", {}).get(name) for k in type(cfg).__mro__)
                if f is not None and "limits" in f.metadata
            ),
            None,
        )
        if limits is None:
            continue
        lo, hi, lo_open = (getattr(cfg, b) if isinstance(b, str) else b for b in limits)
        value = getattr(cfg, name)
        if isinstance(value, (tuple, list)):
            check_range(name, value, lo, hi)
        else:
            check_number(name, value, lo, hi, lo_open=lo_open)


@dataclasses.dataclass(frozen=True)
class World:
    """One world's named scenarios: a scenario name + a seed → the same Trial bit for bit, every time.

    Attributes:
        name: the world's key in the registry (``"gimbal"``, ``"twolink"``, ``"handheld"``).
        label: the world in messages (``"two-link"``).
        scenarios: scenario name → default config (a frozen dataclass).
        simulate: (scenario name, config, seed, streams) → Trial, where ``streams`` are ``n_streams``
            independent generators spawned from ``numpy.random.SeedSequence(seed)`` (so changing, e.g., a
            noise level does not change the motion).
        n_streams: how many streams ``simulate`` draws from.
    """

    name: str
    label: str
    scenarios: Mapping[str, Any]
    simulate: Callable[[str, Any, int, list[np.random.Generator]], Trial]
    n_streams: int

    def names(self) -> list[str]:
        """This world's scenario names, in a stable order."""
        return list(self.scenarios)

    def get(self, name: str):
        """The default config of scenario ``name``; ValueError lists this world's scenarios."""
        if name not in self.scenarios:
            raise ValueError(f"unknown {self.label} scenario {name!r}; known: {', '.join(self.scenarios)}")
        return self.scenarios[name]

    def configure(self, name: str, **overrides):
        """Scenario ``name``'s config with ``overrides`` applied (see :func:`apply_overrides`)."""
        return apply_overrides(name, self.get(name), overrides)

    def make_trial(self, name: str, seed: int, **overrides) -> Trial:
        """Simulate scenario ``name`` with ``seed`` (int ≥ 0) and ``overrides``."""
        cfg = self.configure(name, **overrides)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
        streams = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(self.n_streams)]
        return self.simulate(name, cfg, int(seed), streams)


def apply_overrides(name: str, cfg, overrides: dict):
    """Scenario config ``cfg`` (of scenario ``name``) with ``overrides`` applied.

    A key is a field of the config, or else of its ``sensor`` (a
    ``SensorConfig``); an unknown key or a bad value raises ValueError naming it.
    """
    own = {f.name for f in dataclasses.fields(cfg)}
    sensor_fields = {f.name for f in dataclasses.fields(SensorConfig)}
    unknown = sorted(k for k in overrides if k not in own and k not in sensor_fields)
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(map(repr, unknown))} for scenario {name!r}; "
            f"known: {', '.join(sorted(own))}; sensor: {', '.join(sorted(sensor_fields))}"
        )
    sensor_over = {k: v for k, v in overrides.items() if k not in own}
    cfg_over = {k: v for k, v in overrides.items() if k in own}
    try:
        if sensor_over:
            cfg_over["sensor"] = dataclasses.replace(cfg_over.get("sensor", cfg.sensor), **sensor_over)
        return dataclasses.replace(cfg, **cfg_over)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"scenario {name!r}: bad parameter value: {exc}") from None


def trial_name(scenario: str, seed: int) -> str:
    """A simulated trial's name: ``"scenario#seed"``."""
    return f"{scenario}#{seed}"


def trial_meta(scenario: str, seed: int, cfg, drawn: dict) -> dict:
    """A simulated trial's ``meta``, in JSON types: the scenario and seed (under ``magenv.trial``'s keys),
    what the world drew or measured (``drawn``) and the whole config under ``"config"``."""
    return {META_SCENARIO: scenario, META_SEED: seed, **config_json(drawn), "config": _config_copy(cfg)}


def simulated_trial(
    scenario: str, seed: int, cfg, readings: tuple, q_true: np.ndarray, field, truth: dict, drawn: dict, **more
) -> Trial:
    """A simulated scenario's Trial at ``cfg.rate`` Hz: ``readings`` (gyr rad/s, acc m/s², mag µT; (N, 3) each,
    sensor frame), ``q_true`` (N, 4) sensor → ENU, ``field`` (m0 µT, θ0 °), the truth-only channels, its name
    (:func:`trial_name`) and ``meta`` (:func:`trial_meta` with what the world ``drawn``); ``more``: further
    Trial fields (``extra``)."""
    gyr, acc, mag = readings
    return Trial(
        name=trial_name(scenario, seed),
        rate=cfg.rate,
        gyr=gyr,
        acc=acc,
        mag=mag,
        q_true=q_true,
        field_norm=field[0],
        field_dip=field[1],
        truth=truth,
        meta=trial_meta(scenario, seed, cfg, drawn),
        **more,
    )


def _config_copy(cfg) -> dict:
    """``config_json(cfg)``, made once per config (by its repr: ``60`` and ``60.0`` stay apart) and copied."""
    key = repr(cfg)
    cached = _CONFIGS.get(key)
    if cached is None:
        cached = _CONFIGS[key] = config_json(cfg)
        while len(_CONFIGS) > 64:
            del _CONFIGS[next(iter(_CONFIGS))]
    return copy.deepcopy(cached)


_CONFIGS: dict[str, dict] = {}  # repr(config) → its config_json (a reset makes a trial of the same config)


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
