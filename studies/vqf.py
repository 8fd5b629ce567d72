"""MagVQF-v0 (docs/results.md), in simulation: the shipped student against the tuned Fan rule on VQF's gain.

    python -m studies.vqf [--seeds 0:20] [--recordings] [--agent RUN]   (options: studies/study.py)

Fan's magnet protocols; the reference is ``vqf_fan_lambda_tuned`` (the λ rule mapped to VQF's magnetometer
gain, its rejection off), with VQF as shipped (``vqf``, rejection on), without its rejection and the tuned
threshold rule and the Fan rule on top of VQF's rejection (``vqf_fan_rejection_tuned``, the rule the shipped
student departs from) as columns; ``oracle_vqf`` is the headroom. The shipped student trained in simulation only,
so ``--recordings`` gives held-out figures (``studies/vqf_real.py``: per group of recordings, against ``vqf``).
"""

from magenv.train.sweep_config import DEFAULT_REFERENCE
from studies.study import Study, main

ENV_ID = "magenv/MagVQF-v0"

STUDY = Study(
    env_id=ENV_ID,
    tests=("dynamic_magnet", "stationary_magnet"),
    reference=DEFAULT_REFERENCE[ENV_ID],
    others=("vqf", "vqf_no_rejection", "vqf_threshold_tuned", "vqf_fan_rejection_tuned"),
    oracle="oracle_vqf",
    recordings=True,
)

if __name__ == "__main__":
    raise SystemExit(main(STUDY))
