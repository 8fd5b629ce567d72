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

import math
from typing import Any

import numpy as np

from magenv.envs import BLEND_ID, CONSTRAINT_ID, KALMAN_ID, QSF_ID, VQF_ID
from magenv.envs.features import DIP_SCALE_DEG
from magenv.filters.rules import fan_lambda


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

    def n_state_candidates(self, meta: dict) -> int:
        """S, the number of state-dependent candidates of a run with input constants ``meta`` (0: none)."""
        return 0

    def candidate_actions(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        """(D, S, action_dim) float64 state-dependent candidate actions for (D, n_obs) observations."""
        raise ValueError(f"{type(self).__name__} has no state-dependent candidates")


class BlendInputs(StudentInputs):
    """MagBlend-v0: the extended observation (``features="extended"``: base and extra causal features, and their
    copies 8 and 32 decisions earlier), each block followed by the teacher's continuation rule λ recomputed from
    that block's ``norm_dev`` and ``dip_dev`` (``magenv.filters.rules.fan_lambda`` with the teacher's ``norm_tol``,
    ``th_dip_deg``, in float32)."""

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
            lam = fan_lambda(blk[:, 0], DIP_SCALE_DEG * blk[:, 1], norm_tol, th_dip)  # norm_dev, dip_dev: columns 0, 1
            parts += [blk, lam[:, None].astype(np.float32)]
        return np.concatenate(parts, 1)


class KalmanInputs(StudentInputs):
    """MagKalman-v0: the extended observation (``features="extended"``: the 19 base and the extra causal features,
    and their copies 8 and 32 decisions earlier), each block followed by the γ of the teacher's continuation rule
    and then of each of its ``proposal_scales`` rules (``magenv.baselines.oracle_kalman``; e.g. kf_adaptive_tuned:
    the best rule of ``stationary_magnet`` where the continuation kf_model_tuned is that of ``dynamic_magnet``),
    recomputed from that block: γ = 1 / (1 + (‖d̂‖/σ_d)² + (Δm/σ_m)² + (Δθ/σ_θ)²),
    ‖d̂‖ = 50 µT·field_ref·model_dist, Δm = 50 µT·field_ref·norm_dev, Δθ = 90°·dip_dev (σ = inf: the term is
    absent) — the causal rules' own proposals, from which the student can learn deviations. A teacher with a
    ``still`` rule (run.yaml student ``still``: its σ_m, σ_θ, p_min, γ_pull) adds kf_still's γ on the block's
    still-anchor features: γ_a (σ_m, σ_θ) where ``t_anchor`` = 0, max(γ_a, γ_pull) where ``pull_still`` > p_min,
    else 0 (``magenv.baselines.kalman_policies.StillPullTrust``). A teacher with a ``perp`` rule (run.yaml student
    ``perp``: its σ_d, p_min, γ_pull, i_min) adds kf_perp's γ after it: γ_m (σ_d) where ``perp_info`` < i_min,
    max(γ_m, γ_pull) where ``pull_perp`` > p_min, else 0 (``PerpPullTrust``).

    With a teacher of ``rule_candidates`` (run.yaml student ``rule_candidates: true``), these rules' γ on the
    current block are also state-dependent candidates (``candidate_actions``, float64: bit for bit the
    teacher's ``state_candidates`` and the rules' ``weight`` on the observation)."""

    env_id = KALMAN_ID
    env_kwargs = {"features": "extended"}

    def meta(self, teacher) -> dict:
        from magenv.envs.kalman import EXTENDED, LAGS

        out = {"scales": [float(v) for v in teacher.scales], "block": len(EXTENDED) // (1 + len(LAGS))}
        proposals = getattr(teacher, "proposal_scales", [])
        if len(proposals):
            out["proposals"] = [[float(v) for v in p] for p in proposals]
        if getattr(teacher, "rule_candidates", False):
            out["rule_candidates"] = True
        if getattr(teacher, "still_params", None) is not None:
            out["still"] = [float(v) for v in teacher.still_params]
        if getattr(teacher, "perp_params", None) is not None:
            out["perp"] = [float(v) for v in teacher.perp_params]
        return out

    @staticmethod
    def perp_gamma(blk: np.ndarray, meta: dict) -> np.ndarray:
        """(D,) float64 kf_perp's γ (run.yaml student ``perp``) on (D, ≥ block) features."""
        from magenv.envs.kalman import EXTENDED

        sd, p_min, g_pull, i_min = (float(v) for v in meta["perp"])
        i_i = EXTENDED.index("perp_info")
        bypass = blk[:, i_i].astype(np.float64) < i_min  # d_perp sees too little heading: kf_model's γ
        return KalmanInputs.pull_gated(blk, [sd, math.inf, math.inf], bypass, "pull_perp", p_min, g_pull)

    @staticmethod
    def pull_gated(blk: np.ndarray, scales, bypass: np.ndarray, pull: str, p_min: float, g_pull: float) -> np.ndarray:
        """(D,) float64 the pull gate of kf_still and kf_perp (``kalman_policies._pull_gate``) on (D, ≥ block)
        features: the base rule's γ (``scales`` (σ_d, σ_m, σ_θ)) where ``bypass``, else max(γ, γ_pull) where the
        feature ``pull`` > p_min, else 0 — in float64 (the rule's arithmetic) also for float32 inputs."""
        from magenv.envs.kalman import EXTENDED

        ((a, b, c),) = KalmanInputs.rule_terms(blk.astype(np.float64), {"scales": scales})
        g = 1.0 / (1.0 + a + b + c)  # summed from 1 as the rule's ``weight``
        pulled = np.where(blk[:, EXTENDED.index(pull)].astype(np.float64) > p_min, np.maximum(g, g_pull), 0.0)
        return np.where(bypass, g, pulled)

    @staticmethod
    def still_gamma(blk: np.ndarray, meta: dict) -> np.ndarray:
        """(D,) float64 kf_still's γ (run.yaml student ``still``) on (D, ≥ block) features."""
        from magenv.envs.kalman import EXTENDED

        sm, sth, p_min, g_pull = (float(v) for v in meta["still"])
        bypass = blk[:, EXTENDED.index("t_anchor")] <= 0.0  # clean now: kf_adaptive's γ
        return KalmanInputs.pull_gated(blk, [math.inf, sm, sth], bypass, "pull_still", p_min, g_pull)

    @staticmethod
    def rule_terms(blk: np.ndarray, meta: dict) -> list[tuple]:
        """Per rule (the continuation rule, then each proposal) the terms ((‖d̂‖/σ_d)², (Δm/σ_m)², (Δθ/σ_θ)²),
        each (D,), of (D, ≥ 19) base features (a float32 ``blk`` computes the dip term in float32)."""
        from magenv.envs.kalman import FEATURES, FIELD_SCALE_UT

        i_nd, i_dd, i_md, i_m0 = (FEATURES.index(n) for n in ("norm_dev", "dip_dev", "model_dist", "field_ref"))
        m0 = FIELD_SCALE_UT * blk[:, i_m0].astype(np.float64)
        return [
            ((m0 * blk[:, i_md] / sd) ** 2, (m0 * blk[:, i_nd] / sm) ** 2, (DIP_SCALE_DEG * blk[:, i_dd] / sth) ** 2)
            for sd, sm, sth in ([float(v) for v in r] for r in [meta["scales"], *meta.get("proposals", [])])
        ]

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        obs = np.atleast_2d(np.asarray(obs, np.float32))
        block = int(meta["block"])
        parts = []
        for start in range(0, obs.shape[1], block):
            blk = obs[:, start : start + block]
            parts.append(blk)
            for a, b, c in self.rule_terms(blk, meta):
                parts.append((1.0 / (1.0 + (a + b + c)))[:, None].astype(np.float32))
            if "still" in meta:
                parts.append(self.still_gamma(blk, meta)[:, None].astype(np.float32))
            if "perp" in meta:
                parts.append(self.perp_gamma(blk, meta)[:, None].astype(np.float32))
        return np.concatenate(parts, 1)

    def n_state_candidates(self, meta: dict) -> int:
        n = 1 + len(meta.get("proposals", [])) + ("still" in meta) + ("perp" in meta)
        return n if meta.get("rule_candidates") else 0

    def candidate_actions(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        if not self.n_state_candidates(meta):
            return super().candidate_actions(obs, meta)
        blk = np.atleast_2d(np.asarray(obs, np.float32)).astype(np.float64)  # the rules' arithmetic: float64,
        gammas = [1.0 / (1.0 + a + b + c) for a, b, c in self.rule_terms(blk, meta)]  # summed from 1 (``weight``)
        if "still" in meta:
            gammas.append(self.still_gamma(blk, meta))
        if "perp" in meta:
            gammas.append(self.perp_gamma(blk, meta))
        return np.stack(gammas, 1)[:, :, None]


class ConstraintInputs(StudentInputs):
    """MagConstraint-v0: the extended observation (``magenv.envs.constraint_memory``: base and extra causal
    features, and their copies 25 and 100 decisions earlier), each block followed by the teacher's
    continuation-rule w = min(mag_dev/th1, 1) (eq. 16; ``mag_dev`` is column 0 of every block). With a teacher
    of ``rule_candidates`` (run.yaml student ``rule_candidates: true``) the current block's w, in float64, is
    also a state-dependent candidate (bit for bit the teacher's ``state_candidates``)."""

    env_id = CONSTRAINT_ID
    env_kwargs = {"features": "extended"}

    def meta(self, teacher) -> dict:
        from magenv.envs.constraint import EXTENDED, FEATURES
        from magenv.envs.constraint_memory import LAGS

        block = len(EXTENDED) // (1 + len(LAGS))
        out = {"th1": float(teacher.rule["th1"]), "block": block, "base_features": len(FEATURES)}
        if getattr(teacher, "rule_candidates", False):
            out["rule_candidates"] = True
        return out

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        obs = np.atleast_2d(np.asarray(obs, np.float32))
        th1, block = float(meta["th1"]), int(meta["block"])
        parts = []
        for start in range(0, obs.shape[1], block):
            blk = obs[:, start : start + block]
            parts += [blk, np.minimum(blk[:, :1] / th1, 1.0).astype(np.float32)]
        return np.concatenate(parts, 1)

    def n_state_candidates(self, meta: dict) -> int:
        return 1 if meta.get("rule_candidates") else 0

    def candidate_actions(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        if not self.n_state_candidates(meta):
            return super().candidate_actions(obs, meta)
        dev = np.atleast_2d(np.asarray(obs, np.float32))[:, 0].astype(np.float64)  # float32 observation → float64
        return np.minimum(dev / float(meta["th1"]), 1.0)[:, None, None]


class QSFInputs(StudentInputs):
    """MagQSF-v0: the extended observation (``magenv.envs.qsf_memory``: base and extra causal features, and their
    copies 10 and 40 decisions earlier), each block followed by the tuned rule's decision d recomputed from that
    block (the detector policy ``qsf_detector_tuned``: d = 1 (start) where ``det_start``; where ``det_keep``,
    0 (keep) if a period is ``active`` and its ``age`` is below the detector's ``max_period_s``, else 1; −1 (none)
    otherwise). Runs from before this column (no ``rule_max_age`` in run.yaml's student) see the observation
    as it is."""

    env_id = QSF_ID
    env_kwargs = {"features": "extended"}

    def meta(self, teacher) -> dict:
        from magenv.envs.qsf import AGE_SCALE_S, EXTENDED
        from magenv.envs.qsf_memory import LAGS

        max_age = float(teacher.detector.max_period_s) / AGE_SCALE_S  # in the age feature's unit
        return {"rule_max_age": max_age, "block": len(EXTENDED) // (1 + len(LAGS))}

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        from magenv.envs.qsf import FEATURES

        obs = np.atleast_2d(np.asarray(obs, np.float32))
        if "rule_max_age" not in meta:
            return obs
        max_age, block = float(meta["rule_max_age"]), int(meta["block"])
        i_s, i_k, i_a, i_age = (FEATURES.index(n) for n in ("det_start", "det_keep", "active", "age"))
        parts = []
        for start in range(0, obs.shape[1], block):
            blk = obs[:, start : start + block]
            keep = (blk[:, i_a] > 0.5) & (blk[:, i_age] < max_age)
            d = np.where(blk[:, i_s] > 0.5, 1.0, np.where(blk[:, i_k] > 0.5, np.where(keep, 0.0, 1.0), -1.0))
            parts += [blk, d[:, None].astype(np.float32)]
        return np.concatenate(parts, 1)


class VQFInputs(StudentInputs):
    """MagVQF-v0: the extended observation (``magenv.envs.vqf``: the 21 base features, the extra causal ones — VQF's
    bookkeeping and EMAs — and their copies 4 and 16 decisions earlier) without the columns of run.yaml's
    student ``drop`` (default ``delta``: the heading offset of the 9D frame from the 6D one, which starts from
    the sensor's arbitrary initial heading, so that a student keyed to it would learn the trials' headings, not
    the disturbance).

    With a teacher of a ``rule`` (``oracle_vqf_rule``, ``oracle_vqf_tail``; run.yaml student ``rule: [norm_tol,
    th_dip]``) each kept block is followed by the rule's trust recomputed from that block
    (``magenv.envs.vqf.fan_trust``), and the current block's, in float64, is a state-dependent candidate (bit for
    bit the teacher's continuation, and the guard's ``fallback: rule``)."""

    env_id = VQF_ID
    env_kwargs = {"features": "extended"}
    DROP = ("delta",)

    def meta(self, teacher) -> dict:
        from magenv.envs.vqf import EXTENDED, LAGS

        out = {"block": len(EXTENDED) // (1 + len(LAGS)), "drop": list(self.DROP)}
        if getattr(teacher, "rule", None) is not None:
            out["rule"] = [float(v) for v in teacher.rule]
        return out

    @staticmethod
    def rule_trust(blk: np.ndarray, meta: dict) -> np.ndarray:
        """(D,) float64 the rule's trust of blocks ``blk`` (D, block) float32."""
        from magenv.envs.vqf import FEATURES, fan_trust

        i_n, i_d = FEATURES.index("norm_dev"), FEATURES.index("dip_dev")
        return fan_trust(blk[:, i_n], blk[:, i_d], *(float(v) for v in meta["rule"]))

    def __call__(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        from magenv.envs.vqf import EXTENDED

        obs = np.atleast_2d(np.asarray(obs, np.float32))
        block, drop = int(meta["block"]), set(meta.get("drop", ()))
        keep = np.array([i for i in range(block) if EXTENDED.names[i] not in drop])
        parts = []
        for start in range(0, obs.shape[1], block):
            blk = obs[:, start : start + block]
            parts.append(blk[:, keep])
            if "rule" in meta:
                parts.append(self.rule_trust(blk, meta)[:, None].astype(np.float32))
        return np.ascontiguousarray(np.concatenate(parts, 1))

    def n_state_candidates(self, meta: dict) -> int:
        return 1 if "rule" in meta else 0

    def candidate_actions(self, obs: np.ndarray, meta: dict) -> np.ndarray:
        if not self.n_state_candidates(meta):
            return super().candidate_actions(obs, meta)
        return self.rule_trust(np.atleast_2d(np.asarray(obs, np.float32)), meta)[:, None, None]


#: env id → what its student sees
INPUTS: dict[str, StudentInputs] = {
    BLEND_ID: BlendInputs(),
    KALMAN_ID: KalmanInputs(),
    CONSTRAINT_ID: ConstraintInputs(),
    QSF_ID: QSFInputs(),
    VQF_ID: VQFInputs(),
}


def inputs_for(env_id: str) -> StudentInputs:
    """The student inputs of ``env_id``; ValueError naming the envs that have one."""
    try:
        return INPUTS[env_id]
    except KeyError:
        raise ValueError(f"no DAgger student inputs for env {env_id!r}; known: {sorted(INPUTS)}") from None
