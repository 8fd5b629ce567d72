"""MagQSF-v0 (docs/results.md): the shipped DAgger student against the tuned QSF detector (Combettes & Renaudin 2016).

    python -m studies.qsf [--seeds 0:40] [--recordings] [--agent RUN]   (options: studies/study.py)

The four hand-held paper tests; the reference is ``qsf_detector_tuned`` (the detector tuned on the tests'
training walks, one decision per 10 samples), with ``delay_magyq_tuned`` (the same thresholds in the per-sample
estimator) and ``qsf_hold`` (one QSF period from the first sample, kept) as columns. ``oracle_qsf`` is the
headroom. The whole table takes about half an hour on one core (``handheld_free`` walks are 13 minutes long).
"""

from magenv.train.sweep_config import DEFAULT_REFERENCE
from studies.study import Study, main

ENV_ID = "magenv/MagQSF-v0"

STUDY = Study(
    env_id=ENV_ID,
    tests=("handheld_texting", "handheld_swinging", "handheld_corridor", "handheld_free"),
    reference=DEFAULT_REFERENCE[ENV_ID],
    others=("delay_magyq_tuned", "qsf_hold"),
    oracle="oracle_qsf",
    recordings=True,
)

if __name__ == "__main__":
    raise SystemExit(main(STUDY))
