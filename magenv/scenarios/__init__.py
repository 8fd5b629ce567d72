"""Named scenarios of every world: a scenario name + a seed → one simulated Trial, bit for bit the same.

Public API::

    make_trial(name, seed, **overrides) -> Trial
    scenario_names(world=None) -> list[str]
    get_scenario(name) -> config (a frozen dataclass)
    configure(name, **overrides) -> config
    world_of(name) -> str           # "gimbal", "twolink" or "handheld"
    expand_mixture(names) -> list[str]  # "twins:DIR" → the twin:PATH of each recording in DIR

The worlds, one module each (configs, planning, simulation; physics in ``magenv.sim``):

* ``gimbal`` — Fan et al. 2017: a 3-axis gimbal with a MIMU and magnets
  (``stationary_magnet``, ``dynamic_clean``, ``dynamic_magnet``, ``random``,
  ``manual_routines``, ``gait_field``);
* ``twolink`` — Jung & Lee 2019: two links on a spherical joint, a MIMU on
  each, a magnetised tool (``constraint_test1/2/3``, ``constraint_random``);
* ``handheld`` — Combettes & Renaudin 2016: a walker's hand-held MIMU in a
  static indoor field (``handheld_texting/swinging/free/corridor``,
  ``handheld_random``);
* ``board`` — a sensor board moved by hand in a room, as in the BROAD
  recordings, randomised wide (``board_clean``, ``board_attached``,
  ``board_stationary``, ``board_office``, ``board_shocks``, ``board_random``, ``board_spinning``):
  the training worlds of trust that must hold on real sensors;
* ``rtwin:PATH`` — a randomised twin (``magenv.scenarios.board.random_twin``): the recording's true motion
  in a drawn room with a drawn disturbance and sensor, as ``board_random`` draws them (``rtwins:DIR`` in a
  mixture: one for each recording in DIR); overrides are ``BoardConfig`` fields;
* ``twin:PATH`` — the twin of a real recording: its own true motion through a
  sensor and disturbance model fitted to it (``magenv.scenarios.twin``;
  overrides are ``TwinConfig`` fields). Not listed by ``scenario_names``. In
  a mixture (``expand_mixture``: env ``scenario`` strings, the DAgger
  config's ``scenarios``), ``twins:DIR`` stands for the twins of every
  recording in DIR, ``twins:`` for those of the shared BROAD recordings.

Overrides are field names of the scenario's config or of its
:class:`~magenv.sim.sensors.SensorConfig` (e.g. ``duration=5.0``,
``mag_noise_ut=0.3``). Adding a world: a module exporting ``WORLD``
(:class:`~magenv.scenarios.world.World`), listed in ``WORLDS`` below.
"""

from __future__ import annotations

from collections.abc import Sequence

from magenv.scenarios import board, gimbal, handheld, twin, twolink
from magenv.scenarios.world import World
from magenv.trial import Trial

#: The worlds by name, in the order their scenarios are listed.
WORLDS: dict[str, World] = {w.name: w for w in (gimbal.WORLD, twolink.WORLD, handheld.WORLD, board.WORLD)}

_WORLD_OF: dict[str, World] = {name: w for w in WORLDS.values() for name in w.scenarios}

#: The mixture the shipped agents train on and the shipped rules are tuned on:
#: Fan et al.'s three protocols, trial seeds at or above
#: ``magenv.seeding.HELD_OUT_BELOW`` (evaluation uses lower seeds). ``random``
#: is left out: its trials start from a disturbed field, so their error is
#: dominated by an initial heading offset no trust choice can remove, and
#: their returns (up to ~20° per step) drown the protocols' (~1°).
TRAINING_MIX = "dynamic_magnet,dynamic_clean,stationary_magnet"


#: A mixture entry ``twins:DIR`` stands for the twins (``twin:PATH``) of every recording in DIR; ``twins:``
#: alone, of the shared BROAD recordings (``magenv.recordings.broad_dir()``). See :func:`expand_mixture`.
TWINS_PREFIX = "twins:"
RANDOM_TWINS_PREFIX = "rtwins:"  # the same for randomised twins, rtwin:PATH


def expand_mixture(names: str | Sequence[str]) -> list[str]:
    """The scenario names of a mixture (a comma string or a list of names), each ``twins:DIR`` entry replaced
    by ``twin:PATH`` for every ``*.hdf5`` recording in DIR (sorted; ``twins:`` alone: the shared BROAD
    folder); ValueError if DIR holds no recording. Other names are kept as they are (checked by their user)."""
    from magenv.recordings import list_recordings

    items = names.split(",") if isinstance(names, str) else list(names)
    out: list[str] = []
    for name in (str(n).strip() for n in items):
        prefix = next((p for p in (TWINS_PREFIX, RANDOM_TWINS_PREFIX) if name.startswith(p)), None)
        if prefix is None:
            out.append(name)
            continue
        folder = name[len(prefix) :] or None
        try:
            paths = list_recordings(folder)
        except Exception as exc:
            raise ValueError(f"mixture entry {name!r}: {exc}") from None
        if not paths:
            raise ValueError(f"mixture entry {name!r}: no *.hdf5 recording in {folder or 'the BROAD folder'}")
        single = twin.PREFIX if prefix == TWINS_PREFIX else board.RANDOM_TWIN
        out.extend(f"{single}{p.resolve()}" for p in paths)
    return out


def scenario_names(world: str | None = None) -> list[str]:
    """Names of all scenarios (or of ``world``'s), in a stable order; ValueError for an unknown world."""
    if world is None:
        return list(_WORLD_OF)
    if world not in WORLDS:
        raise ValueError(f"unknown world {world!r}; known worlds: {', '.join(WORLDS)}")
    return WORLDS[world].names()


def _world(name: str) -> World:
    """The world of scenario ``name``; ValueError lists the known scenarios."""
    try:
        return _WORLD_OF[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown scenario {name!r}; known scenarios: {', '.join(_WORLD_OF)}") from None


def world_of(name: str) -> str:
    """The name of the world scenario ``name`` belongs to (a key of ``WORLDS``; ``"twin"`` for ``twin:PATH``,
    ``"board"`` for ``rtwin:PATH``)."""
    if _random_twin(name):
        return "board"
    return "twin" if twin.is_twin(name) else _world(name).name


def _random_twin(name) -> bool:
    return isinstance(name, str) and name.startswith(board.RANDOM_TWIN)


def get_scenario(name: str):
    """The default config of scenario ``name``; ValueError lists the known names."""
    return twin.configure(name) if twin.is_twin(name) else _world(name).get(name)


def configure(name: str, **overrides):
    """Scenario ``name``'s config with ``overrides`` applied (config or sensor fields)."""
    return twin.configure(name, **overrides) if twin.is_twin(name) else _world(name).configure(name, **overrides)


def make_trial(name: str, seed: int, **overrides) -> Trial:
    """Simulate scenario ``name`` with ``seed`` (int ≥ 0): the same Trial bit for bit every time."""
    if _random_twin(name):
        return board.random_twin(name, seed, **overrides)
    if twin.is_twin(name):
        return twin.make_trial(name, seed, **overrides)
    return _world(name).make_trial(name, seed, **overrides)
