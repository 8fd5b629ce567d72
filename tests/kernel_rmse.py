"""Per-trial RMSEs of the Kalman-family, QSF and constraint methods on short runs of the paper checks: the recipe
and the recorder of ``tests/data/kernel_rmse.json``, the fixture ``tests/test_kernel_rmse.py`` holds the
current kernels to.

    .venv/bin/python tests/kernel_rmse.py [--checkout DIR] [--out tests/data/kernel_rmse.json]

``--checkout DIR`` records the code of another checkout (``benchmarks/checkout.py``): the fixture was written
from 3026d33, the commit before the kernels were rewritten for speed (issue 49; 1032ca2, the main this change
was rebased on, writes the same file), with ``git archive 3026d33 | tar -x -C DIR``.

Cases (:data:`CASES`): the scenarios of the paper checks (docs/results.md) — the survey's
(``manual_routines``, ``gait_field``), Fan's protocols under the Kalman trust rules (``dynamic_magnet``,
``dynamic_clean``, ``stationary_magnet``), Combettes & Renaudin's hand-held tests, Jung & Lee's three
tests — each trial cut to its first ``seconds``, with every method of that check that runs one of the
kernels: the survey filters, the ``MagKalman-v0`` rules, its shipped student (the extended observation) and
oracle; the three QSF filters as the paper's table runs them (started from truth) and as registered, the
``MagQSF-v0`` rules, student and oracle; the constraint filters, rules, student and oracle. The MagBlend and
VQF methods run none of these kernels and are not recorded. Tuned rules read the files shipped in the
package (never the user's data directory). Each value: (total, heading, inclination) RMSE, degrees.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

FIXTURE = Path(__file__).resolve().parent / "data" / "kernel_rmse.json"

SURVEY = ("th_triad", "th_quest", "mod_triad", "mod_quest", "kf_nominal", "kf_gate", "kf_adaptive", "kf_model")
KALMAN = (
    "kf_nominal", "kf_gate", "kf_gate_tuned", "kf_adaptive", "kf_adaptive_tuned", "kf_model", "kf_model_tuned",
    "kf_still_tuned", "kf_perp_tuned", "kf_model_tuned_hand", "th_triad", "pretrained:magenv/MagKalman-v0",
)  # fmt: skip
QSF_TABLE = ("aekf@truth", "magyq@truth", "delay_magyq@truth")  # papers.qsf_table's estimators
QSF = (
    *QSF_TABLE, "aekf", "magyq", "delay_magyq", "delay_magyq_tuned", "qsf_detector", "qsf_detector_tuned",
    "qsf_hold", "pretrained:magenv/MagQSF-v0",
)  # fmt: skip
CONSTRAINT = (
    "strapdown", "cf_conventional", "cf_constraint", "cf_gated", "cf_constraint_tuned", "cf_cerr_tuned",
    "pretrained:magenv/MagConstraint-v0",
)  # fmt: skip
#: (check, scenario, seed, seconds, methods); the oracles run on shorter cuts (a search per decision)
CASES = (
    ("survey", "manual_routines", 0, 60.0, SURVEY),
    ("survey", "manual_routines", 1, 60.0, SURVEY),
    ("survey", "gait_field", 0, 40.0, SURVEY),
    ("kalman", "dynamic_magnet", 0, 30.0, KALMAN),
    ("kalman", "dynamic_magnet", 1, 30.0, KALMAN),
    ("kalman", "dynamic_clean", 0, 20.0, KALMAN),
    ("kalman", "stationary_magnet", 0, 40.0, KALMAN),
    ("kalman", "dynamic_magnet", 2, 4.0, ("oracle_kalman", "oracle_kalman_perp")),
    ("qsf", "handheld_texting", 0, 40.0, QSF),
    ("qsf", "handheld_swinging", 0, 40.0, QSF),
    ("qsf", "handheld_free", 0, 40.0, QSF),
    ("qsf", "handheld_corridor", 0, 40.0, QSF),
    ("qsf", "handheld_texting", 1, 5.0, ("oracle_qsf",)),
    ("constraint", "constraint_test1", 0, 30.0, CONSTRAINT),
    ("constraint", "constraint_test2", 0, 30.0, CONSTRAINT),
    ("constraint", "constraint_test3", 0, 30.0, CONSTRAINT),
    ("constraint", "constraint_test1", 1, 4.0, ("oracle_constraint",)),
)


def case_key(check: str, scenario: str, seed: int, seconds: float) -> str:
    return f"{check}/{scenario}#{seed}/{seconds:g}s"


def make_method(name: str):
    """The method object of a case's name: ``NAME@truth`` is a QSF filter started from truth as the paper's
    table runs it, ``pretrained:ENV`` the agent shipped for ENV, else a registry name."""
    from magenv import registry
    from magenv.baselines import qsf as bq

    if name.endswith("@truth"):
        return getattr(bq, name.split("@")[0])(init="truth")
    if name.startswith("pretrained:"):
        return registry.make("agent:" + name)
    return registry.make(name)


def case_rmses(check: str, scenario: str, seed: int, seconds: float, methods) -> dict[str, list[float]]:
    """Method → [total, heading, inclination] RMSE (°) on the trial of one case."""
    from magenv import evaluation
    from magenv.scenarios import make_trial

    trial = make_trial(scenario, seed)
    trial = trial.slice(0, min(trial.n, int(round(seconds * trial.rate))))
    runner = evaluation.PolicyRunner()
    out = {}
    for name in methods:
        s = evaluation.run_method(name, make_method(name), trial, runner).scored
        out[name] = [float(s.total), float(s.heading), float(s.inclination)]
    return out


def record() -> dict[str, dict[str, list[float]]]:
    """Every case's RMSEs (tuned rules from the files shipped in the package)."""
    from magenv import registry

    with tempfile.TemporaryDirectory() as empty:
        os.environ[registry.DATA_DIR_ENV] = empty  # as the tests: never the user's tuned files
        return {case_key(*case[:4]): case_rmses(*case) for case in CASES}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkout", default=None, help="record another checkout's code (benchmarks/checkout.py)")
    p.add_argument("--out", default=str(FIXTURE), help="JSON file to write")
    args = p.parse_args(argv)
    if args.checkout:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
        import checkout

        checkout.use(args.checkout)
    values = record()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(values, indent=1, sort_keys=True) + "\n")
    tmp.replace(out)
    print(f"{sum(len(v) for v in values.values())} RMSE triples of {len(values)} cases -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
