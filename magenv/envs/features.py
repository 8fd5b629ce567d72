"""Observation features defined once: name, range, unit and meaning of each, and the scales they share.

Each env module declares its observation as a :class:`FeatureTable`; the
observation space's bounds, the kernels' feature indices, the table in the
env's docstring (:meth:`FeatureTable.markdown`, filled in by
:func:`document`) and the README's tables (checked against it by the tests)
all come from that one declaration.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit

# Scales shared by the envs' features, so that a rule can recover physical values from an observation.
DIP_SCALE_DEG = 90.0  # dip deviations in units of 90°
GYRO_SCALE = 2.0 * np.pi  # rad/s: gyro norms in revolutions per second


@dataclass(frozen=True)
class Feature:
    """One observation feature: its ``name``, the range it is clipped to, its ``unit`` (or scale) and ``meaning``."""

    name: str
    low: float
    high: float
    unit: str
    meaning: str


DEG = "°"  # the unit of the features in degrees
HEADING = -180.0, 180.0  # degrees: the range of a heading feature

#: memory features (``features="extended"``) that several envs' EXTRA tables hold alike, by name: one name, one
#: meaning across the envs
WINDOW = "the window"  # samples fused in the last step plus sample j


def deviations(dip_estimate: str) -> tuple[Feature, Feature, Feature]:
    """``norm_dev_max``, ``norm_dev_mean`` (fractions of m0) and ``dip_dev_max`` (units of DIP_SCALE_DEG) over
    :data:`WINDOW`; ``dip_estimate`` says which estimate each sample's dip is taken with."""
    return (
        Feature("norm_dev_max", 0.0, 10.0, "fraction of m0", f"max of the absolute norm_dev over {WINDOW}"),
        Feature("norm_dev_mean", -1.0, 10.0, "fraction of m0", f"mean norm_dev over {WINDOW}"),
        Feature(
            "dip_dev_max",
            0.0,
            2.0,
            f"units of {DIP_SCALE_DEG:g}°",
            f"max of the absolute dip_dev over {WINDOW} ({dip_estimate})",
        ),
    )


SHARED = {
    f.name: f
    for f in (
        Feature("mh_ema_025", *HEADING, DEG, "EMA (τ 0.25 s) of the mag heading"),
        Feature("mh_ema_1", *HEADING, DEG, "EMA (τ 1 s) of the mag heading"),
        Feature("mh_ema_4", *HEADING, DEG, "EMA (τ 4 s) of the mag heading"),
        Feature("nd_ema_05", -1.0, 10.0, "fraction of m0", "EMA (τ 0.5 s) of the field-norm deviation"),
        Feature("nd_ema_2", -1.0, 10.0, "fraction of m0", "EMA (τ 2 s) of the field-norm deviation"),
        Feature("nd_ema_8", 0.0, 10.0, "fraction of m0", "EMA (τ 8 s) of the absolute field-norm deviation"),
        Feature("dd_ema_05", 0.0, 180.0, DEG, "EMA (τ 0.5 s) of the absolute dip deviation"),
        Feature("dd_ema_2", -180.0, 180.0, DEG, "EMA (τ 2 s) of the signed dip deviation"),
        Feature("gyro_ema_1", 0.0, 100.0, "rad/s", "EMA (τ 1 s) of ‖ω‖"),
        Feature("clean_ema_4", 0.0, 1.0, "–", "EMA (τ 4 s) of the clean flag"),
        Feature("t_clean", 0.0, 3.0, "units of 10 s", "time since the last clean sample (clipped)"),
    )
}


class FeatureTable:
    """An env's observation features in order: names, float32 bounds, indices and the Markdown table."""

    def __init__(self, *features: Feature):
        names = [f.name for f in features]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate feature names in {names}")
        self.features = tuple(features)
        self.names: tuple[str, ...] = tuple(names)
        self.low = np.array([f.low for f in features], np.float32)
        self.high = np.array([f.high for f in features], np.float32)
        #: the bounds as float64 (what the kernels clip to before the observation is cast to float32)
        self.low64, self.high64 = self.low.astype(np.float64), self.high.astype(np.float64)
        #: named indices for the kernels: ``ix.norm_dev == 0``, … (a namedtuple numba reads as constants)
        self.ix = namedtuple("FeatureIndex", names)(*range(len(names)))

    def __len__(self) -> int:
        return len(self.features)

    def index(self, name: str) -> int:
        """Position of feature ``name`` in the full observation."""
        return self.names.index(name)

    def markdown(self) -> str:
        """The table of the env docstring and the README: Num, Name, Meaning, Unit / scale, Min, Max."""
        rows = ["| Num | Name | Meaning | Unit / scale | Min | Max |", "|---|---|---|---|---|---|"]
        for i, f in enumerate(self.features):
            rows.append(f"| {i} | `{f.name}` | {f.meaning} | {f.unit} | {f.low:g} | {f.high:g} |")
        return "\n".join(rows)


def clipper(table: FeatureTable, neutral_nan: bool = False):
    """The numba function ``clip(x, i)``: value ``x`` clipped to the range of feature ``i`` of ``table``, as the
    kernels clip each feature (float64 bounds; ``min(high, max(low, x))``, which reads NaN as the lower bound).
    ``neutral_nan``: NaN (e.g. from a zero field) reads as the neutral value instead, 0 if in range, else the
    lower bound."""
    low, high = table.low64, table.high64

    @njit(cache=True, inline="always")
    def clip(x, i):
        if neutral_nan and x != x:
            return 0.0 if low[i] <= 0.0 <= high[i] else low[i]
        return min(high[i], max(low[i], x))

    return clip


def document(table: FeatureTable, placeholder: str = "{observation_table}"):
    """Class decorator: put ``table.markdown()`` (indented as the placeholder) in place of ``placeholder`` in
    the class docstring, so ``help(env)`` shows the table that the code uses."""

    def decorate(cls):
        doc = cls.__doc__ or ""
        for line in doc.splitlines():
            if line.strip() == placeholder:
                indent = line[: len(line) - len(line.lstrip())]
                rendered = "\n".join(indent + row for row in table.markdown().splitlines())
                cls.__doc__ = doc.replace(line, rendered)
                return cls
        raise ValueError(f"{cls.__name__}'s docstring has no line {placeholder!r}")

    return decorate
