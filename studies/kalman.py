"""MagKalman-v0 (docs/results.md): the shipped DAgger student against the best Kalman rule of each protocol.

    python -m studies.kalman [--seeds 0:40] [--recordings] [--agent RUN]   (options: studies/study.py)

The best rule is ``kf_model_tuned`` on ``dynamic_magnet`` and ``kf_adaptive_tuned`` on ``stationary_magnet``; the
hand rule on the student's own information is ``kf_perp_tuned`` (reads ``d_perp``) on ``dynamic_magnet`` and
``kf_still_tuned`` (reads the still anchor) on ``stationary_magnet``: the agent's ratio to it says how much of
its gain is learning rather than information. ``oracle_kalman`` is the headroom.
"""

from magenv.train.sweep_config import DEFAULT_REFERENCE
from studies.study import Study, main

ENV_ID = "magenv/MagKalman-v0"

STUDY = Study(
    env_id=ENV_ID,
    tests=("dynamic_magnet", "stationary_magnet"),
    reference=DEFAULT_REFERENCE[ENV_ID],
    by_test={"stationary_magnet": "kf_adaptive_tuned"},
    same_information={"dynamic_magnet": "kf_perp_tuned", "stationary_magnet": "kf_still_tuned"},
    oracle="oracle_kalman",
    recordings=True,
)

if __name__ == "__main__":
    raise SystemExit(main(STUDY))
