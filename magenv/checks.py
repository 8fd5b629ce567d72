"""Argument checks shared by every layer: each names the argument and the value it refuses.

A value of the wrong type raises ``TypeError``; a value of the right type that is not finite or out of
range raises ``ValueError``. Each check returns the value in its plain Python type (``float``, ``int``,
``bool``), so a caller stores what was checked. Used by the scenario configs, the filters' parameter
builders, the envs and the baselines.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

_REAL = (int, float, np.integer, np.floating)


def is_real(value) -> bool:
    """``value`` is a real number (an int, float or numpy scalar of those kinds; not a bool)."""
    return isinstance(value, _REAL) and not isinstance(value, (bool, np.bool_))


def _interval(lo, hi, lo_open: bool, hi_open: bool) -> str:
    """The range as the messages write it: " > 0", " ≥ 0", " ≤ 1", " in [0, 1)" or "" (any value)."""
    if math.isinf(hi) and math.isinf(lo):
        return ""
    if math.isinf(hi):
        return f" {'>' if lo_open else '≥'} {lo:g}"
    if math.isinf(lo):
        return f" {'<' if hi_open else '≤'} {hi:g}"
    return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def check_number(
    name: str, value, lo=-math.inf, hi=math.inf, lo_open: bool = False, hi_open: bool = False, inf_ok: bool = False
) -> float:
    """``value`` as a float: a real number in [lo, hi] (``lo_open``/``hi_open``: that end excluded), finite
    unless ``inf_ok`` (then ±inf passes where the range holds it)."""
    if not is_real(value):
        raise TypeError(f"{name} must be a number{_interval(lo, hi, lo_open, hi_open)}, got {value!r}")
    v = float(value)
    if (
        math.isnan(v)
        or (math.isinf(v) and not inf_ok)
        or v < lo
        or v > hi
        or (lo_open and v == lo)
        or (hi_open and v == hi)
    ):
        what = "a number" if inf_ok else "a finite number"
        raise ValueError(f"{name} must be {what}{_interval(lo, hi, lo_open, hi_open)}, got {value!r}")
    return v


def check_positive(name: str, value, inf_ok: bool = False) -> float:
    """``value`` as a float: a number > 0, finite unless ``inf_ok`` (inf then disables, e.g., a gate)."""
    return check_number(name, value, 0.0, lo_open=True, inf_ok=inf_ok)


def check_int(name: str, value, lo: int = -(2**63), hi: int = 2**63 - 1) -> int:
    """``value`` as an int: an integer (or an integral float) in [lo, hi]; not a bool."""
    what = f"an integer ≥ {lo}" if hi == 2**63 - 1 else f"an integer from {lo} to {hi}"
    if not is_real(value):
        raise TypeError(f"{name} must be {what}, got {value!r}")
    if not (math.isfinite(value) and int(value) == value and lo <= value <= hi):
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return int(value)


def check_bool(name: str, value) -> bool:
    """``value`` as a bool: True or False (a Python or numpy bool; not 0/1 nor a string)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_choice(name: str, value, choices):
    """``value`` itself: one of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def check_mapping(name: str, value) -> dict:
    """A copy of ``value`` as a dict: a mapping with string keys, or None (an empty dict)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
        raise TypeError(f"{name} must be a dict of keyword arguments or None, got {value!r}")
    return dict(value)


def check_vector(name: str, value, n: int, nonzero: bool = False) -> np.ndarray:
    """``value`` as a float array of shape (n,), every entry finite (and not all zero with ``nonzero``)."""
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be {n} finite numbers, got {value!r}") from None
    if a.shape != (n,) or not np.all(np.isfinite(a)) or (nonzero and not np.any(a)):
        raise ValueError(f"{name} must be {n} finite numbers{', not all zero' if nonzero else ''}, got {value!r}")
    return a


FIELD_NORM_MAX_UT = 1000.0  # µT, the largest undisturbed field accepted (Earth's is 25–65 µT)
# The largest white-noise stds a filter accepts (MEMS sensors: ~0.01 rad/s, ~0.05 m/s², ~0.5 µT); beyond them
# a Kalman covariance loses all precision (σ_gyr = 1e9 rad/s leaves it singular).
NOISE_MAX = {"gyr": 10.0, "acc": 100.0, "mag": FIELD_NORM_MAX_UT}  # rad/s, m/s², µT


def check_noise(name: str, value, sensor: str) -> float:
    """A sensor's white-noise std as a float: finite, in (0, ``NOISE_MAX[sensor]``] (``sensor``: gyr, acc, mag)."""
    return check_number(name, value, 0.0, NOISE_MAX[sensor], lo_open=True)


def check_site(field_norm, field_dip) -> tuple[float, float]:
    """The undisturbed field of a site as floats: ``field_norm`` µT in (0, ``FIELD_NORM_MAX_UT``], ``field_dip``
    degrees (positive down) in [-90, 90]."""
    return (
        check_number("field_norm", field_norm, 0.0, FIELD_NORM_MAX_UT, lo_open=True),
        check_number("field_dip", field_dip, -90.0, 90.0),
    )


def check_numbers(name: str, value, n: int, lo=-math.inf, hi=math.inf, what: str = "numbers") -> None:
    """``value`` is a sequence of ``n`` numbers, each in [lo, hi]; ``what`` names them in the message."""
    if not isinstance(value, (tuple, list, np.ndarray)) or len(value) != n:
        raise ValueError(f"{name} must be {n} {what}, got {value!r}")
    for i, v in enumerate(value):
        check_number(f"{name}[{i}]", v, lo, hi)


def check_range(name: str, value, lo=-math.inf, hi=math.inf) -> None:
    """``value`` is a (low, high) tuple or list of finite numbers with lo ≤ low ≤ high ≤ hi."""
    if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(is_real(v) for v in value)):
        raise ValueError(f"{name} must be a (low, high) pair of numbers, got {value!r}")
    if not (all(math.isfinite(v) for v in value) and lo <= value[0] <= value[1] <= hi):
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


#: The most values a YAML document may hold once its aliases are expanded (a config has hundreds).
MAX_YAML_VALUES = 100_000


def _expanded_size(node, sizes: dict, open_: set) -> int:
    """The number of values (scalars, lists, mappings) a composed YAML node holds with every alias expanded;
    memoised by node (an alias is the node it names), so an alias bomb is counted without being expanded."""
    import yaml

    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in open_:
        raise ValueError("an alias refers to a node that holds it (a recursive structure)")
    open_.add(key)
    children = (
        [n for pair in node.value for n in pair]
        if isinstance(node, yaml.MappingNode)
        else node.value
        if isinstance(node, yaml.SequenceNode)
        else []
    )
    total = 1
    for child in children:
        total += _expanded_size(child, sizes, open_)
        if total > MAX_YAML_VALUES:
            raise ValueError(
                f"its aliases expand it to more than {MAX_YAML_VALUES:,} values (an alias bomb?); write the values out"
            )
    open_.discard(key)
    sizes[key] = total
    return total


def check_yaml(text: str, what: str):
    """The YAML document ``text`` as plain data, read with ``yaml.SafeLoader`` (no code runs); ValueError naming
    ``what`` if it is not YAML, or if its aliases expand it beyond ``MAX_YAML_VALUES`` values (an alias bomb:
    a few lines that anything walking the data — printing it in a message, for one — expands to gigabytes)."""
    import yaml

    try:
        loader = yaml.SafeLoader(text)
    except yaml.YAMLError as exc:  # a character YAML does not allow
        raise ValueError(f"{what}: not valid YAML ({exc})") from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node, {}, set())
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise ValueError(f"{what}: not valid YAML ({exc})") from None
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None
    except RecursionError:
        raise ValueError(f"{what}: nested too deeply") from None
    finally:
        loader.dispose()
