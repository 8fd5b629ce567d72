"""The hand rules' formulas, defined once: Fan et al. 2017's λ (eqs. 15–17) and the all-or-nothing gate.

Each is written on physical deviations — the field-norm deviation (‖m‖ − m0)/m0 as a fraction of m0 and the
dip deviation θ_dip − θ0 in degrees — with numpy's functions only, so that one definition serves every
caller in its own arithmetic: the rules of ``magenv.baselines`` (Python floats), the oracles' numba kernels
(:data:`fan_lambda_kernel`, the same source compiled), the students' derived inputs (float32 or float64 arrays,
``magenv.agents.student_inputs``) and the ONNX graph of an exported student (graph tensors that numpy's
functions dispatch on, ``magenv.train.onnx_graph.Node``).

The published parameters and the ranges ``magenv tune`` searches are here too.
"""

from __future__ import annotations

import numpy as np
from numba import njit

FAN_NORM_TOL = 1.0  # eq. 15's divisor as a fraction of m0 (the paper divides by m0 itself)
FAN_TH_DIP_DEG = 20.0  # eq. 16's divisor, printed θ_dip, read as a fixed dip tolerance th_dip, degrees
FAN_BOUNDS = {"norm_tol": (0.02, 5.0), "th_dip_deg": (0.1, 90.0)}

# The vector selector of Lee & Park 2009 in Ligorio & Sabatini 2016 Table A1: th_mag = 1.20 µT of m0 = 46 µT, th_α = 5°
GATE_NORM_TH = 1.2 / 46.0  # fraction of m0
GATE_DIP_TH_DEG = 5.0  # degrees
GATE_BOUNDS = {"norm_th": (0.005, 1.0), "dip_th_deg": (0.5, 45.0)}


def fan_lambda(norm_dev, dip_dev_deg, norm_tol, th_dip_deg):
    """Fan et al. 2017's λ, the weight of the IMU filter (1: ignore the magnetometer):

    λ1 = min(|norm_dev| / norm_tol, 1)      (eq. 15)
    λ2 = min(|dip_dev_deg| / th_dip_deg, 1)  (eq. 16)
    λ  = (λ1 + λ2) / 2                       (eq. 17)

    ``norm_dev`` a fraction of m0, ``dip_dev_deg`` degrees: numbers, arrays (in their dtype) or graph tensors."""
    lam1 = np.minimum(np.abs(norm_dev) / norm_tol, 1.0)
    lam2 = np.minimum(np.abs(dip_dev_deg) / th_dip_deg, 1.0)
    return 0.5 * (lam1 + lam2)


fan_lambda_kernel = njit(cache=True, inline="always")(fan_lambda)


def gate(norm_dev: float, dip_dev_deg: float, norm_th: float, dip_th_deg: float) -> bool:
    """The all-or-nothing gate: True (distrust the magnetometer) when |norm_dev| > norm_th (fractions of m0) or
    |dip_dev_deg| > dip_th_deg (degrees)."""
    return abs(norm_dev) > norm_th or abs(dip_dev_deg) > dip_th_deg
