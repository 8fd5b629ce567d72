"""MagConstraint-v0 (docs/results.md): the shipped DAgger student against the tuned constraint rule (Jung & Lee 2019).

    python -m studies.constraint [--seeds 0:40] [--agent RUN]   (options: studies/study.py)

The three paper tests (``constraint_test1–3``); the reference is ``cf_constraint_tuned`` (eqs. 16 and 18 tuned on
training trials), ``cf_constraint`` (the paper's values) a column, and ``cf_cerr_tuned`` the hand rule on the
student's own constraint error estimate. ``oracle_constraint`` is the headroom. Two-link trials only: the
recordings have one sensor.
"""

from magenv.train.sweep_config import DEFAULT_REFERENCE
from studies.study import Study, main

ENV_ID = "magenv/MagConstraint-v0"

TESTS = ("constraint_test1", "constraint_test2", "constraint_test3")

STUDY = Study(
    env_id=ENV_ID,
    tests=TESTS,
    reference=DEFAULT_REFERENCE[ENV_ID],
    same_information=dict.fromkeys(TESTS, "cf_cerr_tuned"),
    others=("cf_constraint",),
    oracle="oracle_constraint",
)

if __name__ == "__main__":
    raise SystemExit(main(STUDY))
