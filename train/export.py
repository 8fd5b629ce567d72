"""``magenv export``: a DAgger student as an ONNX model with a JSON sidecar, to run beside a filter outside magenv.

    magenv export AGENT --onnx FILE.onnx

AGENT is a run folder of ``magenv train --teacher …`` or ``pretrained:ENV_ID``. FILE.onnx maps a batch of the
env's observations ``obs`` (N, n_obs) float32 to ``action`` (N, action_dim) and the candidate
``probabilities`` (``magenv.train.onnx_graph``: the student's derived inputs, standardisation, MLPs and action
rule are all inside). FILE.json beside it says what the model needs (:func:`sidecar`): the observation's
features in order (name, unit or scale, range, meaning), the history (block width, lags in decisions), the
decision period (samples), the env and its options, the action (its bounds, candidates, how the probabilities
become the action), and the network inputs with their standardisation. Needs ``onnx`` (``pip install
'magenv[onnx]'``); running the model needs ``onnxruntime`` only.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from magenv.train.cli import CommandError, output_file

FORMAT = "magenv-onnx-student-1"
LAG = re.compile(r"^(.*)_lag(\d+)$")


def load_student(agent: str):
    """The StudentPolicy of a DAgger run folder or ``pretrained:ENV_ID`` (CommandError for anything else)."""
    from magenv.agents.dagger import StudentPolicy
    from magenv.agents.loading import RunError, load_agent

    try:
        policy = load_agent(agent)
    except RunError as exc:
        raise CommandError(str(exc)) from None
    if not isinstance(policy, StudentPolicy):
        raise CommandError(
            f"{agent}: a {type(policy).__name__} ({policy.source}); magenv export takes the DAgger students of "
            "magenv.agents.dagger (magenv train --teacher …)"
        )
    return policy


def observation_table(env) -> list:
    """The ``Feature`` of each observation column of ``env`` (its module's extended or base table)."""
    module = importlib.import_module(type(env).__module__)
    table = {f.name: f for t in ("FEATURES", "EXTENDED") if hasattr(module, t) for f in getattr(module, t).features}
    return [table[name] for name in env.features]


def sidecar(policy, env, onnx_name: str) -> dict:
    """The JSON sidecar of ``policy`` exported to ``onnx_name`` (see the module docstring)."""
    from magenv.train.onnx_graph import DERIVED, derived_names, kept_columns

    student, features = policy.student, observation_table(env)
    names = [f.name for f in features]
    block = int(student.meta.get("block", len(names)))
    lags = sorted({int(m.group(2)) for n in names if (m := LAG.match(n))})
    derived = derived_names(policy.env_id, student.meta)
    kept = set(kept_columns(names, student.meta))
    inputs = []
    for start in range(0, len(names), block):
        lag = LAG.match(names[start])
        suffix = f"_lag{lag.group(2)}" if lag else ""
        inputs += [{"name": names[start + i]} for i in range(block) if i in kept]
        inputs += [{"name": d + suffix} for d in derived]
    members = getattr(student, "members", [student])
    for i, item in enumerate(inputs):
        item["mean"] = [float(m.mu[i]) for m in members]
        item["std"] = [float(m.sd[i]) for m in members]
    space = env.action_space
    cands = np.asarray(student.candidates, float)
    n_state = int(student.n_state)
    doc = (type(env).__doc__ or "").strip().splitlines()
    return {
        "format": FORMAT,
        "model": onnx_name,
        "agent": policy.name,
        "weights": policy.source,
        "env_id": policy.env_id,
        "env": doc[0] if doc else policy.env_id,
        "env_kwargs": policy.env_kwargs,
        "input": {"name": "obs", "dtype": "float32", "shape": ["batch", len(names)]},
        "features": [
            {"index": i, "name": f.name, "unit": f.unit, "low": f.low, "high": f.high, "meaning": f.meaning}
            for i, f in enumerate(features)
        ],
        "history": {
            "block": block,
            "lags": lags,
            "unit": "decisions",
            "layout": "columns [0, block) are the current features; block j ≥ 1 is that block as it was lags[j−1] "
            "decisions earlier (before the first decision: the first observation)",
        },
        "decision_period": {
            "samples": int(env.k_steps),
            "meaning": "one decision every `samples` samples (samples / rate seconds): the observation is computed "
            "at the window's first sample, the action holds for the window",
        },
        "action": {
            "dim": int(space.shape[0]),
            "low": space.low.tolist(),
            "high": space.high.tolist(),
            "candidates": cands.tolist(),
            "state_candidates": n_state,
            "state_candidates_meaning": DERIVED.get(policy.env_id, "") if n_state else "",
            "act": student.act,
            "rule": "the most probable candidate (the first on ties)"
            if student.act == "argmax"
            else "the probability-weighted mean of the candidates",
            "guard": None
            if getattr(student, "guard", None) is None
            else {
                **student.guard,
                "meaning": "inside the model: the action is `fallback` (`rule`: the last state-dependent candidate) "
                "where a network input leaves a member's fitted range widened by margin × its width, or where the "
                "members' own actions spread by more than disagree",
            },
        },
        "outputs": {"action": "(batch, dim) float32: the env's action", "probabilities": "(batch, candidates)"},
        "network_inputs": {
            "derived": DERIVED.get(policy.env_id, "") if derived else "",
            "dropped": list(student.meta.get("drop", [])),
            "standardisation": "inside the model: (x − mean) / std per ensemble member",
            "columns": inputs,
        },
    }


def export(agent: str, onnx_path: Path) -> tuple[Path, Path]:
    """Write the ONNX model of ``agent`` to ``onnx_path`` and its sidecar beside it (same name, ``.json``);
    both written whole, then renamed."""
    import gymnasium as gym

    import magenv  # noqa: F401  (registers the envs)

    try:
        import onnx
    except ImportError:
        raise CommandError("magenv export needs onnx: pip install 'magenv[onnx]'") from None
    from magenv.train.onnx_graph import student_graph

    policy = load_student(agent)
    env: Any = gym.make(policy.env_id, disable_env_checker=True, **policy.env_kwargs).unwrapped
    try:
        model = student_graph(policy.env_id, policy.student, env.features)
    except ValueError as exc:
        raise CommandError(f"{agent}: {exc}") from None
    side = sidecar(policy, env, onnx_path.name)
    env.close()
    json_path = onnx_path.with_suffix(".json")
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    for path, data in ((onnx_path, model.SerializeToString()), (json_path, json.dumps(side, indent=1).encode())):
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    onnx.checker.check_model(str(onnx_path))
    return onnx_path, json_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("agent", help="a DAgger run folder (magenv train --teacher …) or pretrained:ENV_ID")
    p.add_argument("--onnx", type=Path, required=True, metavar="FILE.onnx", help="the model to write")


def run(args: argparse.Namespace) -> int:
    args.onnx = output_file(args.onnx, "--onnx", (".onnx",))
    output_file(args.onnx.with_suffix(".json"), "--onnx (its sidecar)")
    onnx_path, json_path = export(args.agent, args.onnx)
    print(f"wrote {onnx_path} and {json_path}")
    return 0
