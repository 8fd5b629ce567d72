"""Ray glue: one local or remote Ray, evaluation spread over its workers, and sweeps on Ray Tune.

Ray is the optional extra ``magenv[scale]``; this module imports it only
inside its functions, and a missing Ray is a :class:`RayMissing` naming the
extra. Nothing here ships a method or a trial as an object: a worker rebuilds
each method from its name through ``magenv.registry.make`` (once per worker)
and each trial from its :class:`TrialSpec` (a scenario and seed, simulated bit
for bit the same anywhere, or a recording's path), then runs the very code
of the serial path (``magenv.evaluation.evaluate``). So the numbers of
:func:`evaluate` are those of the serial run, and only scores come back (the
estimate arrays and the trial only for the trials in ``keep``).

A cluster's workers need magenv (with the same extra) installed, and the
files that names point to — ``agent:RUN_DIR`` run folders, recordings, tuned
rules in ``$MAGENV_DATA_DIR`` — at the same paths (a shared filesystem);
``docs/SCALE.md`` has the plan.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from magenv import evaluation, registry

EXTRA = "scale"
RLLIB_EXTRA = "rllib"


class RayMissing(ImportError):
    """Ray (or RLlib) is not installed; the message names the extra that installs it."""


def require_ray(what: str, rllib: bool = False):
    """The ``ray`` module; RayMissing naming ``what`` needs it and the extra that installs it."""
    try:
        import ray

        if rllib:
            import ray.rllib
        else:
            import ray.tune
    except ImportError as exc:
        extra = RLLIB_EXTRA if rllib else EXTRA
        raise RayMissing(
            f"{what} needs {'RLlib' if rllib else 'Ray Tune'}, which magenv installs as an optional extra: "
            f"pip install 'magenv[{extra}]' ({exc})"
        ) from None
    return ray


def start(address: str | None = None, num_cpus: int | None = None, what: str = "this command") -> bool:
    """Connect to the Ray cluster at ``address``, or start a local one with ``num_cpus`` CPUs (default: the
    machine's); a Ray already initialised in this process is used as it is. Returns True if this call started
    or connected it (then :func:`stop` it), False if it was already up."""
    ray = require_ray(what)
    if ray.is_initialized():
        return False
    env_vars = {registry.DATA_DIR_ENV: os.environ[registry.DATA_DIR_ENV]} if registry.DATA_DIR_ENV in os.environ else {}
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    if address is None:
        kwargs["num_cpus"] = num_cpus
    ray.init(address=address, runtime_env={"env_vars": env_vars} if env_vars else None, **kwargs)
    return True


def stop(started: bool) -> None:
    """Shut Ray down if :func:`start` started it."""
    if started:
        import ray

        ray.shutdown()


def cluster_cpus() -> int:
    """CPUs of the Ray cluster this process is connected to."""
    import ray

    return max(1, int(ray.cluster_resources().get("CPU", 1)))


# ----------------------------------------------------------------- trials and methods by name


@dataclass(frozen=True)
class TrialSpec:
    """A trial by name: ``scenario`` and ``seed`` (``magenv.scenarios.make_trial``) or a ``recording`` path."""

    scenario: str | None = None
    seed: int | None = None
    recording: str | None = None

    def make(self):
        """The Trial, the same bit for bit on any machine."""
        if self.recording is not None:
            from magenv.recordings import load_recording

            return load_recording(self.recording)
        from magenv.scenarios import make_trial

        return make_trial(self.scenario, self.seed)


def override_env_kwargs(methods: dict, overrides: dict[str, dict] | None) -> dict:
    """``methods`` with ``overrides[env_id]`` merged into the ``env_kwargs`` of each policy acting in ``env_id``
    (e.g. ``{BLEND_ID: {"stationary_hold": False}}`` for ``compare --no-hold``); returns ``methods``."""
    for method in methods.values():
        env_id = getattr(method, "env_id", None)
        extra = (overrides or {}).get(env_id) if env_id is not None else None
        if extra:
            method.env_kwargs = {**method.env_kwargs, **extra}
    return methods


def build_methods(builds: dict[str, str], trust_pickle: bool = False, overrides: dict | None = None) -> dict:
    """Method objects by table name from ``builds`` (table name → registry name, e.g. ``agent:runs/a`` →
    ``agent:/abs/runs/a``), with :func:`override_env_kwargs` applied."""
    methods = {name: registry.make(build, trust_pickle=trust_pickle) for name, build in builds.items()}
    return override_env_kwargs(methods, overrides)


class _Evaluator:
    """One Ray worker of :func:`evaluate`: its methods, built once, run on the trials it is sent."""

    def __init__(self, builds: dict[str, str], env_kwargs: dict | None, overrides: dict | None, trust_pickle: bool):
        self.methods = build_methods(builds, trust_pickle, overrides)
        self.env_kwargs = env_kwargs

    def run(self, index: int, spec: TrialSpec, label: str, names: list[str], keep_going: bool, keep: bool):
        trial = spec.make()
        runs = evaluation.evaluate(
            {n: self.methods[n] for n in names}, [trial], self.env_kwargs, [label], keep_going=keep_going
        )
        if not keep:
            # the trial and the arrays stay with the caller (no transfer back)
            runs = [r.without_arrays() for r in runs]
        return index, runs


def _tasks(n_trials: int, names: list[str], workers: int) -> list[tuple[int, list[str]]]:
    """(trial index, method names) cells grouped: a trial's methods together (one simulation), split into
    enough groups that there are about two tasks per worker when the trials alone are too few."""
    groups = min(len(names), max(1, math.ceil(2 * workers / max(n_trials, 1))))
    size = math.ceil(len(names) / groups)
    chunks = [names[i : i + size] for i in range(0, len(names), size)]
    return [(i, chunk) for i in range(n_trials) for chunk in chunks]


def evaluate(
    builds: dict[str, str],
    specs: Sequence[TrialSpec],
    labels: Sequence[str],
    env_kwargs: dict | None = None,
    overrides: dict | None = None,
    workers: int | None = None,
    keep_going: bool = False,
    trust_pickle: bool = False,
    keep: Sequence[int] = (0,),
    progress: Callable[[list], None] | None = None,
) -> list[evaluation.Run]:
    """Every method on every trial over Ray workers (Ray must be up: :func:`start`); the Runs in the order
    and with the numbers of ``magenv.evaluation.evaluate`` on the same trials.

    ``builds``: table name → registry name of each method; ``specs`` and ``labels``: the trials and their
    table groups; ``env_kwargs``, ``keep_going`` as in ``evaluate``; ``overrides``: see
    :func:`override_env_kwargs`. ``workers`` (default: the cluster's CPUs) Ray actors of one CPU each run
    the cells (:func:`_tasks`). Runs of the trials whose indices are in ``keep`` carry the trial and the
    estimate arrays, the others only ``score`` (or ``error``), with ``trial`` None. ``progress(runs)`` is
    called as each task's runs come back.
    """
    ray = require_ray("distributed evaluation")
    from ray.util import ActorPool

    names = list(builds)
    workers = workers or cluster_cpus()
    tasks = _tasks(len(specs), names, workers)
    actor = ray.remote(num_cpus=1)(_Evaluator)
    pool = ActorPool(
        [actor.remote(builds, env_kwargs, overrides, trust_pickle) for _ in range(min(workers, len(tasks)))]
    )
    kept = set(keep)
    cells: dict[tuple[int, str], evaluation.Run] = {}
    for index, runs in pool.map_unordered(
        lambda a, task: a.run.remote(task[0], specs[task[0]], labels[task[0]], task[1], keep_going, task[0] in kept),
        tasks,
    ):
        for r in runs:
            cells[index, r.method] = r
        if progress is not None:
            progress(runs)
    return [cells[i, n] for i in range(len(specs)) for n in names]


# ----------------------------------------------------------------- sweeps on Ray Tune

#: Tune's own bookkeeping of a sweep goes under OUT/TUNE_DIR (each invocation its own experiment folder).
TUNE_DIR = "tune"


def tune_runs(
    names: Sequence[str],
    run_one: Callable[[str], dict],
    out: Path,
    workers: int | None = None,
    retries: int = 2,
    on_done: Callable[[str, dict | None, str | None], None] | None = None,
) -> dict[str, dict | str]:
    """Each of ``names`` one Ray Tune trial of one CPU that calls ``run_one(name)`` once (Ray must be up:
    :func:`start`); at most ``workers`` at a time (default: the cluster's CPUs). Returns name → Tune's metrics
    of a finished trial, or the error text of a trial that failed ``retries`` + 1 times (a worker lost
    mid-trial counts as a failure: the trial starts again, and ``run_one`` must resume from its own files);
    a trial that Ctrl-C stopped (on SIGINT Tune gives running trials up to 10 s to end, kills their actors and
    returns) is not in it.

    ``run_one`` must be picklable (a module-level function, or a ``functools.partial`` of one): each Tune
    actor calls it in its main thread, where signal handlers work. Tune's scalar metrics are the numbers
    among the returned dict's top-level values. Tune writes its own files (some of them pickles, which
    magenv never loads: resuming is ``run_one``'s business) under ``out/tune/``. ``on_done(name, result,
    error)`` is called in this process as each trial ends.
    """
    import time

    require_ray("magenv sweep")
    from ray import tune

    class MagenvRun(tune.Trainable):
        """One named run: ``run_one(name)`` in a single step."""

        def setup(self, config):
            self.name = config["run"]

        def reset_config(self, new_config):  # actors are reused between trials: no second start-up
            self.name = new_config["run"]
            return True

        def step(self):
            result = run_one(self.name)
            metrics = {k: v for k, v in result.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
            return {**metrics, "done": True}

        def save_checkpoint(self, checkpoint_dir):  # the run's own files are its checkpoint
            return {}

        def load_checkpoint(self, checkpoint):
            pass

    results: dict[str, dict | str] = {}

    class Report(tune.Callback):
        """Collects each run's outcome from the trial itself (the result grid may lose a dead worker's config)."""

        def on_trial_complete(self, iteration, trials, trial, **info):
            metrics = trial.last_result or {}
            if metrics.get("done"):
                results[trial.config["run"]] = metrics
            if on_done is not None:
                on_done(trial.config["run"], trial.last_result, None)

        def on_trial_error(self, iteration, trials, trial, **info):
            results[trial.config["run"]] = error = _trial_error(trial)
            if on_done is not None:
                on_done(trial.config["run"], None, error)

    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # no console tables: the caller prints its own
    tuner = tune.Tuner(
        tune.with_resources(MagenvRun, {"cpu": 1}),
        param_space={"run": tune.grid_search(list(names))},
        tune_config=tune.TuneConfig(max_concurrent_trials=workers or cluster_cpus(), reuse_actors=True),
        run_config=tune.RunConfig(
            name=time.strftime("sweep-%Y%m%d-%H%M%S"),
            storage_path=str((Path(out) / TUNE_DIR).resolve()),
            verbose=0,
            callbacks=[Report()],
            failure_config=tune.FailureConfig(max_failures=retries),
            checkpoint_config=tune.CheckpointConfig(checkpoint_at_end=False),
        ),
    )
    tuner.fit()
    return results


def _trial_error(trial) -> str:
    """The last line of a failed Tune trial's error file (the exception), or its state."""
    path = getattr(trial, "error_file", None) or ""
    try:
        lines = [line for line in Path(path).read_text().splitlines() if line.strip()]
    except OSError:
        return f"trial {trial.status}"
    return lines[-1] if lines else f"trial {trial.status}"
