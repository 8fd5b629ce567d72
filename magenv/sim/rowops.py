"""Row-wise kernels for (N, ·) arrays in the trial pipeline (numba, no per-row
allocation), using the conventions of :mod:`magenv.quaternion`."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def to_sensor(q, v):
    """Vectors (N, 3) from the earth (ENU) to the sensor frame: q* ⊗ v ⊗ q, q (N, 4) sensor → earth."""
    n = q.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        w, x, y, z = q[i, 0], -q[i, 1], -q[i, 2], -q[i, 3]  # conjugate
        a, b, c = v[i, 0], v[i, 1], v[i, 2]
        # v + 2·r × (r × v + w·v), r = (x, y, z)  (magenv.quaternion.rotate1)
        tx = y * c - z * b + w * a
        ty = z * a - x * c + w * b
        tz = x * b - y * a + w * c
        out[i, 0] = a + 2.0 * (y * tz - z * ty)
        out[i, 1] = b + 2.0 * (z * tx - x * tz)
        out[i, 2] = c + 2.0 * (x * ty - y * tx)
    return out


@njit(cache=True)
def norms(v):
    """Euclidean norm of each row of v (N, k)."""
    n, k = v.shape
    out = np.empty(n)
    for i in range(n):
        s = 0.0
        for j in range(k):
            s += v[i, j] * v[i, j]
        out[i] = np.sqrt(s)
    return out
