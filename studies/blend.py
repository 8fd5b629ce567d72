"""MagBlend-v0 (docs/results.md): the shipped DAgger student against the tuned Fan λ rule, the oracle as headroom.

    python -m studies.blend [--seeds 0:40] [--recordings] [--agent RUN]   (options: studies/study.py)

Fan's three protocols (``stationary_magnet``, ``dynamic_clean``, ``dynamic_magnet``), 40 held-out trials each;
the reference is ``fan_lambda_tuned`` on all three, ``mimu`` (the magnetometer always trusted) a column.
"""

from magenv.train.sweep_config import DEFAULT_REFERENCE
from studies.study import Study, main

ENV_ID = "magenv/MagBlend-v0"

STUDY = Study(
    env_id=ENV_ID,
    tests=("dynamic_magnet", "stationary_magnet", "dynamic_clean"),
    reference=DEFAULT_REFERENCE[ENV_ID],
    others=("mimu",),
    oracle="oracle",
    recordings=True,
)

if __name__ == "__main__":
    raise SystemExit(main(STUDY))
