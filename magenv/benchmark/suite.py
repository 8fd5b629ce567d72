"""magenv-bench v1: the tasks a result on magenv is reported on, each fixed once here.

A **task** is one env with one held-out test: the scenario its evaluation trials come from (or the real
recordings), the env's **training mixture** (the scenarios an agent may train on: ``env_kwargs["scenario"]``
of ``gymnasium.make``), its **budget** and its two reference points, the task's best tuned rule (score 0) and
the privileged oracle (score 1; it reads truth, so it is an upper bound, never a baseline).

* **Evaluation seeds** ``EVAL_SEEDS`` = 4000–4019, the same for every simulated task: below
  ``magenv.seeding.VALIDATION_START`` (5000), so disjoint from every training seed (≥ 10 000: the envs' draws,
  ``magenv tune``, DAgger's ``train_seed``) and validation seed (5000–9999: model selection in
  ``agents/configs/*.yaml`` and the sweeps), and from the seeds 0–39 on which the project's own figures were read
  while its agents were developed (``magenv.train.seeds.REPORT_SEEDS``).
* **Budget**: env-steps of training (``env.step`` calls, every env summed) at the env's default
  ``decision_every``; a method acting every k samples gets ``budget_steps × decision_every / k`` steps, the same
  sensor samples (:meth:`EnvSpec.steps_at`). An imitation learner counts the env-steps of the rollouts it labels.
  Chosen so that the baseline table (5 envs × 4 methods × 5 training seeds) trains within a day on two cores
  (docs/benchmark/index.md).
* **Real-recordings track** (``MagVQF-v0/recordings``): the BROAD recordings (``magenv.recordings.broad_dir``,
  ``$MAGENV_BROAD_DIR``), scored against the rule only: the optical truth is too coarse for the oracle to steer
  by, so it has no normalised score. Skipped, saying so, where the recordings are absent.
* **Normalised score** (:mod:`magenv.benchmark.score`): per trial, (rule − agent) / the task's mean
  rule-to-oracle gap, so that its mean over trials is 0 for the rule and 1 for the oracle.

The version is part of every score card; a change to any of the above is a new version.
"""

from __future__ import annotations

from dataclasses import dataclass

from magenv.envs import BLEND_ID, CONSTRAINT_ID, KALMAN_ID, QSF_ID, VQF_ID

VERSION = "magenv-bench v1"
EVAL_SEEDS = tuple(range(4000, 4020))
RECORDINGS = "recordings"  # the test name of the real-recordings track
BASELINE_SEEDS = 5  # training seeds of each baseline (docs/benchmark/index.md)


@dataclass(frozen=True)
class EnvSpec:
    """One env of the suite: its training mixture and budget.

    Attributes:
        env_id: the Gymnasium id.
        mixture: the scenarios an agent trains on (``env_kwargs["scenario"]``, comma-joined).
        budget_steps: training env-steps at ``decision_every``.
        decision_every: the env's default samples per step (the budget's unit).
    """

    env_id: str
    mixture: tuple[str, ...]
    budget_steps: int
    decision_every: int

    @property
    def short(self) -> str:
        """``MagBlend-v0`` for ``magenv/MagBlend-v0``."""
        return self.env_id.rsplit("/", 1)[-1]

    @property
    def budget_samples(self) -> int:
        """The budget in sensor samples."""
        return self.budget_steps * self.decision_every

    def steps_at(self, decision_every: int) -> int:
        """The budget in env-steps of a method acting every ``decision_every`` samples (rounded down)."""
        return self.budget_samples // decision_every


@dataclass(frozen=True)
class Task:
    """One held-out test of one env.

    Attributes:
        env: its env's :class:`EnvSpec`.
        test: the scenario of the evaluation trials, or ``RECORDINGS``.
        rule: the best tuned rule on this test (registry name; normalised score 0, and the paired ratio's
            reference): the lowest mean RMSE of the tuned rules on the project's report seeds 0–39
            (docs/results.md), trials disjoint from ``EVAL_SEEDS``; MagKalman-v0's and MagConstraint-v0's are the
            hand rules on their students' extended observation (``kf_perp``, ``kf_still``, ``cf_cerr``).
        oracle: the privileged oracle (registry name; normalised score 1); "" where there is none.
    """

    env: EnvSpec
    test: str
    rule: str
    oracle: str

    @property
    def name(self) -> str:
        """``MagBlend-v0/dynamic_magnet``: how the command line and the score cards name it."""
        return f"{self.env.short}/{self.test}"

    @property
    def env_id(self) -> str:
        return self.env.env_id

    @property
    def normalised(self) -> bool:
        """Whether the task has a normalised score (it has an oracle)."""
        return bool(self.oracle)


BUDGET_STEPS = 300_000  # env-steps of training per run, at each env's default decision_every
BLEND = EnvSpec(BLEND_ID, ("dynamic_magnet", "dynamic_clean", "stationary_magnet"), BUDGET_STEPS, 8)
KALMAN = EnvSpec(KALMAN_ID, ("dynamic_magnet", "dynamic_clean", "stationary_magnet"), BUDGET_STEPS, 8)
CONSTRAINT = EnvSpec(
    CONSTRAINT_ID, ("constraint_test1", "constraint_test2", "constraint_test3", "constraint_random"), BUDGET_STEPS, 4
)
QSF = EnvSpec(
    QSF_ID, ("handheld_texting", "handheld_swinging", "handheld_corridor", "handheld_random"), BUDGET_STEPS, 10
)
VQF = EnvSpec(VQF_ID, ("board_random", "board_attached", "dynamic_magnet", "stationary_magnet"), BUDGET_STEPS, 8)
ENVS = (BLEND, KALMAN, CONSTRAINT, QSF, VQF)

TASKS: tuple[Task, ...] = (
    Task(BLEND, "dynamic_magnet", "fan_lambda_tuned", "oracle"),
    Task(BLEND, "stationary_magnet", "fan_lambda_tuned", "oracle"),
    Task(BLEND, "dynamic_clean", "fan_lambda_tuned", "oracle"),
    Task(KALMAN, "dynamic_magnet", "kf_perp_tuned", "oracle_kalman"),
    Task(KALMAN, "stationary_magnet", "kf_still_tuned", "oracle_kalman"),
    *(Task(CONSTRAINT, f"constraint_test{i}", "cf_cerr_tuned", "oracle_constraint") for i in (1, 2, 3)),
    Task(QSF, "handheld_texting", "delay_magyq_tuned", "oracle_qsf"),
    Task(QSF, "handheld_swinging", "qsf_detector_tuned", "oracle_qsf"),
    Task(QSF, "handheld_corridor", "delay_magyq_tuned", "oracle_qsf"),
    Task(QSF, "handheld_free", "qsf_detector_tuned", "oracle_qsf"),
    Task(VQF, "dynamic_magnet", "vqf_fan_lambda_tuned", "oracle_vqf"),
    Task(VQF, "stationary_magnet", "vqf_fan_lambda_tuned", "oracle_vqf"),
    Task(VQF, RECORDINGS, "vqf_fan_lambda_tuned", ""),
)


def env_spec(env_id: str) -> EnvSpec:
    """The :class:`EnvSpec` of ``env_id`` (ValueError naming the suite's envs)."""
    for e in ENVS:
        if env_id in (e.env_id, e.short):
            return e
    raise ValueError(f"{env_id!r} is not an env of {VERSION}; its envs: {', '.join(e.env_id for e in ENVS)}")


def select(names: str | None = None) -> list[Task]:
    """The tasks named by a comma list (``None``: all): a task's name (``MagBlend-v0/dynamic_magnet``), an env
    (``MagBlend-v0`` or ``magenv/MagBlend-v0``: its tasks), or ``sim`` (every task but the recordings track).
    ValueError naming what matches nothing, and the known names."""
    if names is None:
        return list(TASKS)
    chosen: list[Task] = []
    for item in (s.strip() for s in names.split(",")):
        if not item:
            continue
        if item == "sim":
            hits = [t for t in TASKS if t.test != RECORDINGS]
        else:
            hits = [t for t in TASKS if item in (t.name, t.env.short, t.env_id)]
        if not hits:
            raise ValueError(
                f"unknown task {item!r} in {VERSION}; tasks: {', '.join(t.name for t in TASKS)} "
                "(or an env's name for its tasks, or sim)"
            )
        chosen += [t for t in hits if t not in chosen]
    if not chosen:
        raise ValueError(f"no task named in {names!r}")
    return chosen
