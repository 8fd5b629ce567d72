"""A DAgger student (``magenv.agents.dagger``) as one ONNX graph: observation in, action out.

The graph computes, for a batch of the env's observations ``obs`` (N, n_obs) float32:

1. the student's inputs — each block of the observation (the current features, then their copies ``LAGS``
   decisions earlier) followed by the columns its env's ``magenv.agents.student_inputs`` entry derives from
   that block (:data:`DERIVED`: a rule's own trust recomputed from the block), in the same dtypes, each block
   without the columns run.yaml's student ``drop`` names (MagVQF-v0: :func:`kept_columns`);
2. per member of the student (an ensemble has several) the standardisation (x − μ)/σ, the tanh MLP and the
   softmax over its candidates; the members' probabilities averaged;
3. the action: the probability-weighted mean of the candidate actions (``act: mean``) or the most probable
   candidate (``argmax``, the first on ties), the candidates being the fixed ones followed by the
   state-dependent ones of the current block (a rule's own action, in float64); with a guard, its fallback
   (an action, or the rule's) where the student's guard holds.

Outputs ``action`` (N, action_dim) and ``probabilities`` (N, C + S). Each env's derived columns are written here
as graph nodes (the names in :data:`DERIVED`; the Fan rule's by its one definition, ``magenv.filters.rules``, run
on :class:`Node`); ``tests/test_train_export.py`` holds them to the numpy student on 10 000 recorded observations
of every env, and a student constant the builder does not know is refused (:func:`check_meta`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magenv.envs import BLEND_ID, CONSTRAINT_ID, KALMAN_ID, QSF_ID, VQF_ID
from magenv.envs.features import DIP_SCALE_DEG
from magenv.filters.rules import fan_lambda

OPSET = 17
IR_VERSION = 8  # readable by onnxruntime ≥ 1.10
#: env id → the names of the columns its student inputs add after each block (a block's lag appended as _lagL)
DERIVED = {
    BLEND_ID: "rule_lambda: Fan's λ = ½·(min(|norm_dev|/norm_tol, 1) + min(|90°·dip_dev|/th_dip, 1)) of the block",
    KALMAN_ID: "gamma_rule, gamma_proposal_i, gamma_still, gamma_perp: the γ of the teacher's rules on the block",
    CONSTRAINT_ID: "rule_w: w = min(mag_dev/th1, 1) of the block (eq. 16)",
    QSF_ID: "rule_decision: the tuned detector rule's decision −1 none / 0 keep / 1 start on the block",
    VQF_ID: "rule_trust: the Fan rule's u = 1 − ½·(min(|norm_dev|/norm_tol, 1) + min(|90°·dip_dev|/th_dip, 1)) of "
    "the block (students of a teacher with a rule)",
}
#: env id → the student constants (run.yaml ``student``, beyond its shape) the builder knows
KNOWN_META = {
    BLEND_ID: {"rule", "block", "base_features"},
    KALMAN_ID: {"scales", "block", "proposals", "rule_candidates", "still", "perp"},
    CONSTRAINT_ID: {"th1", "block", "base_features", "rule_candidates"},
    QSF_ID: {"rule_max_age", "block"},
    VQF_ID: {"block", "drop", "rule"},  # the ``drop`` columns of each block left out
}


def plain(env_id: str) -> bool:
    """The student of ``env_id`` sees the observation as it is (``magenv.agents.student_inputs``' base class)."""
    from magenv.agents.student_inputs import INPUTS, StudentInputs

    return env_id in INPUTS and type(INPUTS[env_id]) is StudentInputs


def check_meta(env_id: str, meta: dict) -> None:
    """ValueError unless the builder knows ``env_id``'s student inputs (:data:`KNOWN_META`, or the observation
    as it is: :func:`plain`) and every constant in ``meta``."""
    known = KNOWN_META.get(env_id, {"block"} if plain(env_id) else None)
    if known is None:
        raise ValueError(f"no ONNX form of the student inputs of {env_id}; exportable: {', '.join(KNOWN_META)}")
    unknown = sorted(set(meta) - known)
    if unknown:
        raise ValueError(f"the student's input constants {unknown} are unknown to the ONNX exporter of {env_id}")


class Graph:
    """Nodes and constants of an ONNX graph, each output named uniquely."""

    def __init__(self):
        self.nodes, self.inits, self._n = [], [], 0

    def name(self, stem: str) -> str:
        self._n += 1
        return f"{stem}_{self._n}"

    def const(self, value, dtype=np.float32) -> str:
        from onnx import numpy_helper

        out = self.name("c")
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype), out))
        return out

    def op(self, op_type: str, *inputs: str, **attrs) -> str:
        from onnx import helper

        out = self.name(op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attrs))
        return out

    def cols(self, x: str, start: int, stop: int) -> str:
        """Columns start:stop of a (N, W) tensor."""
        return self.op(
            "Slice", x, self.const([start], np.int64), self.const([stop], np.int64), self.const([1], np.int64)
        )

    def col(self, x: str, i: int, dtype=None) -> str:
        """Column i as (N, 1), cast to ``dtype`` (np.float64) if given."""
        c = self.cols(x, i, i + 1)
        return c if dtype is None else self.op("Cast", c, to=_onnx_type(dtype))

    def cast(self, x: str, dtype) -> str:
        return self.op("Cast", x, to=_onnx_type(dtype))

    def binary(self, op_type: str, x: str, value, dtype=np.float32) -> str:
        return self.op(op_type, x, self.const(value, dtype))

    def where(self, cond: str, a: str, b: str) -> str:
        return self.op("Where", cond, a, b)


class Node(np.lib.mixins.NDArrayOperatorsMixin):
    """A tensor of graph ``g`` in ``dtype`` that numpy's functions and Python's arithmetic extend by ONNX nodes,
    so that a formula written for arrays (``magenv.filters.rules``) builds its own graph: ``np.minimum(x, 1.0)``
    adds ``Min(x, 1.0)``; a number is a constant of ``dtype``."""

    OPS = {np.minimum: "Min", np.absolute: "Abs", np.add: "Add", np.subtract: "Sub", np.multiply: "Mul",
           np.divide: "Div"}  # fmt: skip

    def __init__(self, g: Graph, name: str, dtype=np.float32):
        self.g, self.name, self.dtype = g, name, dtype

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        if method != "__call__" or kwargs or ufunc not in self.OPS:
            return NotImplemented
        names = [x.name if isinstance(x, Node) else self.g.const(x, self.dtype) for x in inputs]
        return Node(self.g, self.g.op(self.OPS[ufunc], *names), self.dtype)


def _onnx_type(dtype) -> int:
    from onnx import TensorProto

    return {np.float32: TensorProto.FLOAT, np.float64: TensorProto.DOUBLE}[dtype]


# ----------------------------------------------------------------- each env's derived columns


def _blend(g: Graph, blk: str, meta: dict) -> list[str]:
    tol, th = float(meta["rule"][0]), float(meta["rule"][1])
    return [fan_lambda(Node(g, g.col(blk, 0)), Node(g, g.col(blk, 1)) * DIP_SCALE_DEG, tol, th).name]


def _square_over(g: Graph, x: str, scale: float, dtype) -> str:
    """(x / scale)², x already in ``dtype`` (x / inf = 0: an absent term)."""
    r = g.binary("Div", x, scale, dtype)
    return g.op("Mul", r, r)


def _kalman_terms(g: Graph, blk: str, scales, all64: bool) -> tuple[str, str, str]:
    """((‖d̂‖/σ_d)², (Δm/σ_m)², (Δθ/σ_θ)²) in float64 (``KalmanInputs.rule_terms``; the dip term in float32
    unless ``all64``, as for a float32 block)."""
    from magenv.envs.kalman import FEATURES, FIELD_SCALE_UT

    i_nd, i_dd, i_md, i_m0 = (FEATURES.index(n) for n in ("norm_dev", "dip_dev", "model_dist", "field_ref"))
    f64 = np.float64
    m0 = g.binary("Mul", g.col(blk, i_m0, f64), FIELD_SCALE_UT, f64)
    sd, sm, sth = (float(v) for v in scales)
    a = _square_over(g, g.op("Mul", m0, g.col(blk, i_md, f64)), sd, f64)
    b = _square_over(g, g.op("Mul", m0, g.col(blk, i_nd, f64)), sm, f64)
    if all64:
        c = _square_over(g, g.binary("Mul", g.col(blk, i_dd, f64), DIP_SCALE_DEG, f64), sth, f64)
    else:
        c = g.cast(_square_over(g, g.binary("Mul", g.col(blk, i_dd), DIP_SCALE_DEG), sth, np.float32), f64)
    return a, b, c


def _gamma(g: Graph, terms) -> str:
    """1 / (1 + (a + b + c)), float64."""
    a, b, c = terms
    return g.op("Reciprocal", g.binary("Add", g.op("Add", g.op("Add", a, b), c), 1.0, np.float64))


def _pull_gated(g: Graph, blk: str, scales, bypass: str, pull: str, p_min: float, g_pull: float) -> str:
    """``KalmanInputs.pull_gated`` (float64)."""
    from magenv.envs.kalman import EXTENDED

    base = _gamma(g, _kalman_terms(g, blk, scales, all64=True))
    above = g.binary("Greater", g.col(blk, EXTENDED.index(pull), np.float64), p_min, np.float64)
    pulled = g.where(above, g.binary("Max", base, g_pull, np.float64), g.const([[0.0]], np.float64))
    return g.where(bypass, base, pulled)


def _kalman_gammas(g: Graph, blk: str, meta: dict, all64: bool) -> list[str]:
    """float64 (N, 1) each: the continuation rule's and each proposal's γ, then kf_still's and kf_perp's."""
    from magenv.envs.kalman import EXTENDED

    out = [_gamma(g, _kalman_terms(g, blk, s, all64)) for s in [meta["scales"], *meta.get("proposals", [])]]
    if "still" in meta:
        sm, sth, p_min, g_pull = (float(v) for v in meta["still"])
        bypass = g.binary("LessOrEqual", g.col(blk, EXTENDED.index("t_anchor")), 0.0)
        out.append(_pull_gated(g, blk, [math.inf, sm, sth], bypass, "pull_still", p_min, g_pull))
    if "perp" in meta:
        sd, p_min, g_pull, i_min = (float(v) for v in meta["perp"])
        bypass = g.binary("Less", g.col(blk, EXTENDED.index("perp_info"), np.float64), i_min, np.float64)
        out.append(_pull_gated(g, blk, [sd, math.inf, math.inf], bypass, "pull_perp", p_min, g_pull))
    return out


def _kalman(g: Graph, blk: str, meta: dict) -> list[str]:
    return [g.cast(x, np.float32) for x in _kalman_gammas(g, blk, meta, all64=False)]


def _constraint(g: Graph, blk: str, meta: dict) -> list[str]:
    return [g.binary("Min", g.binary("Div", g.col(blk, 0), float(meta["th1"])), 1.0)]


def _fan_trust64(g: Graph, blk: str, meta: dict) -> str:
    """float64 (N, 1) ``magenv.envs.vqf.fan_trust`` of a float32 block (``VQFInputs.rule_trust``)."""
    from magenv.envs.vqf import FEATURES

    tol, th = float(meta["rule"][0]), float(meta["rule"][1])
    col = lambda name: Node(g, g.col(blk, FEATURES.index(name), np.float64), np.float64)
    return (1.0 - fan_lambda(col("norm_dev"), col("dip_dev") * DIP_SCALE_DEG, tol, th)).name


def _vqf(g: Graph, blk: str, meta: dict) -> list[str]:
    return [g.cast(_fan_trust64(g, blk, meta), np.float32)]


def _qsf(g: Graph, blk: str, meta: dict) -> list[str]:
    from magenv.envs.qsf import FEATURES

    i_s, i_k, i_a, i_age = (FEATURES.index(n) for n in ("det_start", "det_keep", "active", "age"))
    half = lambda i: g.binary("Greater", g.col(blk, i), 0.5)
    keep = g.op("And", half(i_a), g.binary("Less", g.col(blk, i_age), float(meta["rule_max_age"])))
    one, zero, minus = (g.const([[v]]) for v in (1.0, 0.0, -1.0))
    return [g.where(half(i_s), one, g.where(half(i_k), g.where(keep, zero, one), minus))]


BUILDERS = {BLEND_ID: _blend, KALMAN_ID: _kalman, CONSTRAINT_ID: _constraint, QSF_ID: _qsf, VQF_ID: _vqf}


def derived_names(env_id: str, meta: dict) -> list[str]:
    """The names of the columns the student inputs of ``env_id`` add after each block."""
    if env_id == KALMAN_ID:
        names = ["gamma_rule", *(f"gamma_proposal_{i}" for i in range(len(meta.get("proposals", []))))]
        return names + ["gamma_still"] * ("still" in meta) + ["gamma_perp"] * ("perp" in meta)
    if (
        env_id not in DERIVED
        or (env_id == QSF_ID and "rule_max_age" not in meta)
        or (env_id == VQF_ID and "rule" not in meta)
    ):
        return []
    return [DERIVED[env_id].split(":")[0]]


def _state_candidates(g: Graph, env_id: str, obs: str, meta: dict) -> list[str]:
    """float64 (N, 1) each: the state-dependent candidate actions of the current block."""
    if env_id == KALMAN_ID and meta.get("rule_candidates"):
        return _kalman_gammas(g, g.cols(obs, 0, int(meta["block"])), meta, all64=True)
    if env_id == CONSTRAINT_ID and meta.get("rule_candidates"):
        return [g.binary("Min", g.binary("Div", g.col(obs, 0, np.float64), float(meta["th1"]), np.float64), 1.0,
                         np.float64)]  # fmt: skip
    if env_id == VQF_ID and "rule" in meta:
        return [_fan_trust64(g, obs, meta)]
    return []


def kept_columns(names, meta: dict) -> list[int]:
    """The columns of a block (the first ``block`` of ``names``) a student reads: all but those whose name is in
    run.yaml's student ``drop``."""
    block, drop = int(meta.get("block", len(names))), set(meta.get("drop", ()))
    return [i for i in range(block) if names[i] not in drop]


def _act(g: Graph, p: str, fixed: np.ndarray, cands: str | None, act: str) -> str:
    """(N, A) float64: the action of probabilities ``p`` (N, C + S) over the fixed candidates (C, A) or, with
    state-dependent ones, over ``cands`` (N, C + S, A): their weighted mean or the argmax (the first on ties)."""
    if act == "argmax":
        idx = g.op("ArgMax", p, axis=1, keepdims=1)  # (N, 1)
        if cands is None:
            return g.op("Gather", g.const(fixed, np.float64), g.op("Squeeze", idx, g.const([1], np.int64)), axis=0)
        pick = g.op("Expand", g.op("Unsqueeze", idx, g.const([2], np.int64)), g.const([1, 1, fixed.shape[1]], np.int64))
        return g.op("Squeeze", g.op("GatherElements", cands, pick, axis=1), g.const([1], np.int64))
    p64 = g.cast(p, np.float64)
    if cands is None:
        return g.op("MatMul", p64, g.const(fixed, np.float64))
    return g.op("ReduceSum", g.op("Mul", g.op("Unsqueeze", p64, g.const([2], np.int64)), cands),
                g.const([1], np.int64), keepdims=0)  # fmt: skip


def _guarded(g: Graph, student, members, probs, x: str, action: str, fixed, cands, state, guard: dict) -> str:
    """``action`` replaced by the guard's fallback (an action, or ``rule``: the last state-dependent candidate)
    where any member's inputs ``x`` leave its widened fitted range, or where the members' own actions spread by
    more than ``disagree``, and elsewhere clipped to the fallback ± ``band`` (``magenv.agents.dagger.Student``):
    the thresholds are the student's own float32 numbers."""
    outside = []
    for m in members:
        lo, hi = m.bounds
        pad = float(guard["margin"]) * (hi - lo)  # float32, as the student computes it
        below, above = g.op("Less", x, g.const(lo - pad)), g.op("Greater", x, g.const(hi + pad))
        outside.append(g.op("ReduceMax", g.cast(g.op("Or", below, above), np.float32), axes=[1], keepdims=1))
    flags = list(outside)
    if len(members) > 1:
        acts = [g.op("Unsqueeze", _act(g, p, fixed, cands, student.act), g.const([2], np.int64)) for p in probs]
        stack = g.op("Concat", *acts, axis=2)  # (N, A, M)
        spread = g.op("Sub", g.op("ReduceMax", stack, axes=[2], keepdims=0), g.op("ReduceMin", stack, axes=[2],
                                                                                   keepdims=0))  # fmt: skip
        wide = g.op("Greater", spread, g.const(float(guard["disagree"]), np.float64))
        flags.append(g.op("ReduceMax", g.cast(wide, np.float32), axes=[1], keepdims=1))
    any_flag = flags[0]
    for f in flags[1:]:
        any_flag = g.op("Max", any_flag, f)
    cond = g.op("Greater", any_flag, g.const(0.0))  # (N, 1)
    rule = guard["fallback"] == "rule"
    fallback = state[-1] if rule else g.const(np.asarray(guard["fallback"], np.float64)[None], np.float64)
    band = float(guard.get("band", np.inf))
    if band != np.inf:  # the bounded departure: clipped to the fallback ± band, in float64 as the student does
        hi, lo = g.binary("Add", fallback, band, np.float64), g.binary("Sub", fallback, band, np.float64)
        action = g.op("Min", g.op("Max", action, lo), hi)
    return g.where(cond, fallback, action)


def student_graph(env_id: str, student, names) -> Any:
    """The ONNX ModelProto of ``student`` (a ``dagger.Student`` or ``Ensemble``) acting in ``env_id`` on
    observations of the features ``names`` (the module docstring)."""
    from onnx import TensorProto, checker, helper

    meta, n_obs = student.meta, len(names)
    check_meta(env_id, meta)
    g = Graph()
    obs = "obs"
    block = int(meta.get("block", n_obs))
    derived = BUILDERS[env_id] if derived_names(env_id, meta) else None  # (a plain student's: none)
    keep = g.const(kept_columns(names, meta), np.int64) if "drop" in meta else None
    parts = []
    for start in range(0, n_obs, block):
        blk = g.cols(obs, start, start + block)
        kept = blk if keep is None else g.op("Gather", blk, keep, axis=1)
        parts += [kept, *(derived(g, blk, meta) if derived else [])]
    x = g.op("Concat", *parts, axis=1) if len(parts) > 1 else parts[0]
    members = getattr(student, "members", [student])
    probs = []
    for m in members:
        z = g.binary("Div", g.binary("Sub", x, m.mu), m.sd)
        for i, (w, b) in enumerate(m.layers):
            z = g.op("Add", g.op("MatMul", z, g.const(w.T)), g.const(b))
            if i < len(m.layers) - 1:
                z = g.op("Tanh", z)
        probs.append(g.op("Softmax", z, axis=1))
    p = probs[0]
    for q in probs[1:]:
        p = g.op("Add", p, q)
    if len(probs) > 1:
        p = g.binary("Div", p, float(len(probs)))
    fixed = np.asarray(student.candidates, np.float64)  # (C, A)
    state = _state_candidates(g, env_id, obs, meta)
    cands = None
    if state:  # (N, C + S, A): the fixed candidates for every row, then the state's
        n_rows = g.op("Slice", g.op("Shape", obs), g.const([0], np.int64), g.const([1], np.int64))
        shape = g.op("Concat", n_rows, g.const(list(fixed.shape), np.int64), axis=0)
        tiled = g.op("Expand", g.const(fixed[None], np.float64), shape)
        extra = g.op("Unsqueeze", g.op("Concat", *state, axis=1), g.const([2], np.int64))
        cands = g.op("Concat", tiled, extra, axis=1)
    action = _act(g, p, fixed, cands, student.act)
    guard = getattr(student, "guard", None)
    if guard is not None:
        action = _guarded(g, student, members, probs, x, action, fixed, cands, state, guard)
    g.nodes.append(helper.make_node("Cast", [action], ["action"], to=TensorProto.FLOAT))
    g.nodes.append(helper.make_node("Identity", [p], ["probabilities"]))
    n_cands = len(fixed) + len(state)
    graph = helper.make_graph(
        g.nodes,
        "magenv_student",
        [helper.make_tensor_value_info(obs, TensorProto.FLOAT, ["batch", n_obs])],
        [
            helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", fixed.shape[1]]),
            helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, ["batch", n_cands]),
        ],
        g.inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="magenv")
    model.ir_version = IR_VERSION
    checker.check_model(model, full_check=True)
    return model
