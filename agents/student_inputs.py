"""What a DAgger student (``magenv.agents.dagger``) sees in each env: its observation options and its inputs.

An entry of :data:`INPUTS` (env id → :class:`StudentInputs`) says which env
options give the student its observation (``env_kwargs``: the env's extended,
causal feature set), which per-run constants the inputs need from the teacher
(``meta(teacher)``: stored in run.yaml's ``student`` section, so a run folder
rebuilds its student from arrays and numbers only), and how an observation
becomes the network's input (``__call__(obs, meta)``). A student for a new env
is one entry here plus a teacher (the oracle interface of
``magenv.agents.dagger``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magenv.envs import BLEND_ID
from magenv.envs.features import DIP_SCALE_DEG


class StudentInputs:
    """Base: the observation as it is."""

    env_id = ""
    env_kwargs: dict[str, Any] = {}

    def meta(self, teacher) -> dict:
        """Per-run constants of the inputs, taken from ``teacher`` (YAML-safe numbers and lists)."""
        return {}

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        """(D, n_obs) observations → (D, n_in) float32 inputs."""
        return np.atleast_2d(np.asarray(obs, np.float32))


class BlendInputs(StudentInputs):
    """MagBlend-v0: the extended observation (``features="extended"``: base and extra causal features, and their
    copies 8 and 32 decisions earlier), each block followed by the teacher's continuation rule λ recomputed from
    that block's ``norm_dev`` and ``dip_dev`` (the Fan rule of eqs. 15–17 with the teacher's ``norm_tol``,
    ``th_dip_deg``): λ = ½·(min(|norm_dev|/norm_tol, 1) + min(|90°·dip_dev|/th_dip, 1))."""

    env_id = BLEND_ID
    env_kwargs = {"features": "extended"}

    def meta(self, teacher) -> dict:
        from magenv.envs.blend import EXTENDED, FEATURES, LAGS

        return {
            "rule": [float(teacher.norm_tol), float(teacher.th_dip_deg)],
            "block": len(EXTENDED) // (1 + len(LAGS)),
            "base_features": len(FEATURES),
        }

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        obs = np.atleast_2d(np.asarray(obs, np.float32))
        norm_tol, th_dip = float(meta["rule"][0]), float(meta["rule"][1])
        block = int(meta["block"])
        parts = []
        for start in range(0, obs.shape[1], block):
            blk = obs[:, start : start + block]
            lam1 = np.minimum(np.abs(blk[:, 0]) / norm_tol, 1.0)  # eq. 15 (norm_dev is column 0)
            lam2 = np.minimum(np.abs(DIP_SCALE_DEG * blk[:, 1]) / th_dip, 1.0)  # eq. 16 (dip_dev, column 1)
            parts += [blk, (0.5 * (lam1 + lam2))[:, None].astype(np.float32)]
        return np.concatenate(parts, 1)


#: env id → what its student sees
INPUTS: dict[str, StudentInputs] = {BLEND_ID: BlendInputs()}


def inputs_for(env_id: str) -> StudentInputs:
    """The student inputs of ``env_id``; ValueError naming the envs that have one."""
    try:
        return INPUTS[env_id]
    except KeyError:
        raise ValueError(f"no DAgger student inputs for env {env_id!r}; known: {sorted(INPUTS)}") from None
