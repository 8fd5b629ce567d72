"""Probe: how much of a method's error on the two-link tests comes from each of the world's error sources?

    python -m studies.error_sources [--scenario constraint_test1] [--methods cf_constraint_tuned,…]
        [--seeds 10000:10016]

It simulates the same seeds of a two-link test (``magenv.scenarios.twolink``) as they are and with the
sources of ``REMOVED`` taken out (scenario overrides: every other stream of the trial stays bit for bit the same),
runs each method (a registry name, or ``agent:RUN`` / ``agent:pretrained:ENV_ID``) on every version and prints
the mean total RMSE (°) and the paired ratio to the trials as simulated (geometric mean with its bootstrap 95 %
interval, ``magenv.stats.paired_ratio``). Where the error barely falls with every source removed, it is the
filter's own (the sensors' noise and bias drift, the accelerometer under external acceleration), not the
disturbances'. Training seeds by default (an analysis, not a reported target); it prints figures, nothing here is
a test.
"""

from __future__ import annotations

import argparse

import numpy as np

import magenv  # noqa: F401
from magenv import evaluation, registry
from magenv.scenarios import make_trial
from magenv.stats import paired_ratio
from magenv.train.seeds import seeds_arg

NO_BIAS = {"gyro_bias": (0.0, 0.0, 0.0)}  # rad/s: the bias the paper adds to link i's gyroscope (§3.1)
NO_LAB = {"lab_inhomogeneity": 0.0}  # fraction of m0: the lab's weak field inhomogeneity
NO_TOOL = {"tool_moment": 0.0}  # A·m²: the magnetised tool's approaches
#: the sensors' constant errors (fields of the scenario's own ``SensorConfig``): accelerometer bias (m/s²), the
#: magnetometer's residual hard iron (µT) and soft iron (dimensionless)
NO_OFFSETS = {"acc_bias": 0.0, "mag_hard_iron_ut": 0.0, "mag_soft_iron": 0.0}
#: the fixed tests (``constraint_random`` draws its bias, lab field and tool per trial and ignores these fields)
TESTS = ("constraint_test1", "constraint_test2", "constraint_test3")
#: case → scenario overrides
REMOVED = {
    "as simulated": {},
    "no gyro bias": NO_BIAS,
    "no lab field": NO_LAB,
    "no tool": NO_TOOL,
    "no lab field, no tool": {**NO_LAB, **NO_TOOL},
    "none of the three": {**NO_BIAS, **NO_LAB, **NO_TOOL},
    "no sensor offsets": NO_OFFSETS,
    "none of the four": {**NO_BIAS, **NO_LAB, **NO_TOOL, **NO_OFFSETS},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", choices=TESTS, default="constraint_test1")
    ap.add_argument("--methods", default="cf_constraint_tuned")
    ap.add_argument("--seeds", type=seeds_arg, default="10000:10016")
    args = ap.parse_args()
    runner = evaluation.PolicyRunner()  # one env per policy, reused over the trials
    for name in args.methods.split(","):
        method = registry.make(name)
        totals = {
            case: np.array(
                [
                    evaluation.run_method(name, method, make_trial(args.scenario, s, **overrides), runner).scored.total
                    for s in args.seeds
                ]
            )
            for case, overrides in REMOVED.items()
        }
        base = totals["as simulated"]
        for case, total in totals.items():
            ratio = paired_ratio(total, base)
            print(f"{args.scenario} {name} {case:22s} RMSE {total.mean():.3f}°  / as simulated {ratio.ratio_text()}")


if __name__ == "__main__":
    main()
