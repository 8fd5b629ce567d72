"""An agent's learned state as arrays: safetensors files that loading never unpickles.

Stable-Baselines3's own ``.zip`` files hold pickled Python objects (its
``data`` entry is cloudpickle; ``vecnormalize.pkl`` and the replay buffer are
pickles), and unpickling a file runs whatever code its author put in it. A
run folder therefore keeps what training learned as plain tensors, with JSON
metadata, and rebuilds every Python object from ``run.yaml``
(``magenv.agents.loading.build_model``):

* :func:`save_policy` / :func:`load_policy` — the policy's weights
  (``policy/NAME`` tensors: actor, critic, LSTM, SAC's target critic);
* :func:`save_checkpoint` / :func:`load_checkpoint` — what resuming needs in
  one file, written atomically: the weights, every optimizer's moments
  (``optim/OPTIMIZER/PARAM/KEY``; the parameter groups as JSON), SAC's
  entropy coefficient (``var/NAME``), the reward-normalisation statistics
  (``vecnormalize/ret_rms/{mean,var,count}``) and the progress (JSON);
* :func:`save_replay_buffer` / :func:`load_replay_buffer` — SAC's replay
  buffer, the filled rows of each of its arrays.

Every reader raises ``RunError`` naming the file: not safetensors, not
magenv's format, another algorithm, or arrays that do not fit the model.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

FORMAT = "magenv-weights-1"


class RunError(ValueError):
    """A run folder is missing, incomplete or corrupt, or does not fit the request."""


def _write(path: Path, tensors: dict, meta: dict) -> None:
    """Write ``tensors`` (name → torch tensor) with string metadata, atomically (a kill leaves the old file)."""
    from safetensors.torch import save_file

    tmp = path.with_name(path.name + ".tmp")
    save_file(
        {k: v.detach().cpu().contiguous() for k, v in tensors.items()},
        str(tmp),
        metadata={"format": FORMAT, **{k: json.dumps(v) for k, v in meta.items()}},
    )
    _sort_header(tmp)
    os.replace(tmp, path)


def _sort_header(path: Path) -> None:
    """Rewrite the JSON header of the safetensors file ``path`` with its keys sorted, in place: the library writes
    its metadata map in an order that varies from one write to the next, so the same tensors and metadata would
    otherwise give different bytes. The sorted header has the same characters, so its length (and with it every
    tensor offset, counted from the header's end) is unchanged."""
    with open(path, "r+b") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(f.read(n))
        text = json.dumps(header, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) > n:  # never for the library's compact JSON; refuse rather than write a broken file
            raise RuntimeError(f"{path}: sorted safetensors header is {len(text)} bytes, the written one {n}")
        f.seek(8)
        f.write(text + b" " * (n - len(text)))  # the format pads its header with spaces


def read(path: Path, algo: str | None = None) -> tuple[dict, dict]:
    """(tensors, metadata) of a file written here; RunError naming the file if it is missing, not
    safetensors, not this format, or written for another algorithm than ``algo``."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file, safe_open

    if not path.is_file():
        raise RunError(f"{path}: no such file")
    try:
        with safe_open(str(path), "pt") as f:
            raw = f.metadata() or {}
        tensors = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError) as exc:
        raise RunError(f"{path}: corrupt weights file ({type(exc).__name__}: {exc})") from None
    if raw.get("format") != FORMAT:
        raise RunError(f"{path}: not a magenv weights file (format {raw.get('format')!r}, expected {FORMAT!r})")
    try:
        meta = {k: json.loads(v) for k, v in raw.items() if k != "format"}
    except json.JSONDecodeError as exc:
        raise RunError(f"{path}: corrupt metadata ({exc})") from None
    if algo is not None and meta.get("algo") != algo:
        raise RunError(f"{path}: weights of {meta.get('algo')!r}, but the run is {algo!r}")
    return tensors, meta


def _group(tensors: dict, prefix: str) -> dict:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}


def _algo(model) -> str:
    from magenv.agents.hyperparams import ALGORITHMS, algorithm_class

    return next(a for a in ALGORITHMS if type(model) is algorithm_class(a))


# ----------------------------------------------------------------- policy weights


def save_policy(model, path: Path, timesteps: int) -> None:
    """The policy's weights (state dict) of ``model``, after ``timesteps`` steps of training."""
    state = model.policy.state_dict()
    _write(path, {f"policy/{k}": v for k, v in state.items()}, {"algo": _algo(model), "timesteps": int(timesteps)})


def _load_policy(model, tensors: dict, path: Path) -> None:
    weights = _group(tensors, "policy/")
    try:
        model.policy.load_state_dict(weights, strict=True)
    except (RuntimeError, KeyError, ValueError) as exc:
        raise RunError(
            f"{path}: the weights do not fit the policy that run.yaml describes ({str(exc).splitlines()[0]})"
        ) from None


def load_policy(model, path: Path) -> dict:
    """Load the policy weights of ``path`` (written by :func:`save_policy` or :func:`save_checkpoint`) into
    ``model``; returns the file's metadata."""
    tensors, meta = read(path, _algo(model))
    _load_policy(model, tensors, path)
    return meta


# ----------------------------------------------------------------- checkpoints (resume)


def _optimizers(model) -> dict:
    """Name → optimizer (SB3's own list: ``policy.optimizer``; SAC's actor, critic and entropy optimizers)."""
    from stable_baselines3.common.save_util import recursive_getattr

    return {name: recursive_getattr(model, name) for name in model._get_torch_save_params()[0] if name != "policy"}


def _variables(model) -> dict:
    """Name → tensor of the state SB3 keeps outside any state dict (SAC's entropy coefficient)."""
    from stable_baselines3.common.save_util import recursive_getattr

    return {name: recursive_getattr(model, name) for name in model._get_torch_save_params()[1]}


def _vecnormalize(model):
    from stable_baselines3.common.vec_env import VecNormalize

    env = model.get_env()
    return env if isinstance(env, VecNormalize) else None


def save_checkpoint(model, path: Path, state: dict) -> None:
    """Everything resuming ``model`` needs besides SAC's replay buffer, with the progress ``state`` (JSON)."""
    import torch

    tensors = {f"policy/{k}": v for k, v in model.policy.state_dict().items()}
    groups = {}
    for name, opt in _optimizers(model).items():
        sd = opt.state_dict()
        groups[name] = sd["param_groups"]
        for idx, entry in sd["state"].items():
            for key, value in entry.items():
                tensors[f"optim/{name}/{idx}/{key}"] = torch.as_tensor(value)
    for name, value in _variables(model).items():
        tensors[f"var/{name}"] = value
    norm = _vecnormalize(model)
    if norm is not None:
        rms = norm.ret_rms
        for key, value in (("mean", rms.mean), ("var", rms.var), ("count", rms.count)):
            tensors[f"vecnormalize/ret_rms/{key}"] = torch.as_tensor(np.asarray(value, np.float64))
    _write(
        path,
        tensors,
        {
            "algo": _algo(model),
            "timesteps": int(state["timesteps"]),
            "state": state,
            "optimizers": groups,
            "n_updates": int(getattr(model, "_n_updates", 0)),
        },
    )


#: Optimizer moments that are running means of squares: never negative.
SQUARED_MOMENTS = ("exp_avg_sq", "max_exp_avg_sq", "square_avg")


def _count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{name} must be an integer ≥ 0, got {value!r}")
    return value


def _array(name: str, value, shape: tuple, nonnegative: bool = False) -> None:
    """``value`` (a tensor) has ``shape`` and finite entries (≥ 0 with ``nonnegative``); else ValueError."""
    if tuple(value.shape) != tuple(shape):
        raise ValueError(f"{name} has shape {tuple(value.shape)}, expected {tuple(shape)}")
    if not bool(value.isfinite().all()):
        raise ValueError(f"{name} holds NaN or inf")
    if nonnegative and bool((value < 0).any()):
        raise ValueError(f"{name} holds negative entries (a mean of squares)")


def check_progress(state, timesteps: int | None = None) -> dict:
    """A progress record (``state``) checked: ``timesteps`` an integer ≥ 0 (equal to ``timesteps`` if given),
    ``best_timesteps`` None or in [0, timesteps], ``best_score`` a number ≥ 0 (inf before the first evaluation),
    ``evaluations`` (if present) rows [timesteps, score, seconds] at increasing steps up to ``timesteps``.
    ValueError naming the entry."""
    import math

    if not isinstance(state, dict):
        raise ValueError(f"progress record must be a mapping, got {type(state).__name__}")
    done = _count("timesteps", state.get("timesteps"))
    if timesteps is not None and done != timesteps:
        raise ValueError(f"progress record says {done} steps, the checkpoint's arrays {timesteps}")
    best_at, best = state.get("best_timesteps"), state.get("best_score", math.inf)
    if best_at is not None and _count("best_timesteps", best_at) > done:
        raise ValueError(f"best_timesteps {best_at} is after the {done} steps trained")
    if isinstance(best, bool) or not isinstance(best, (int, float)) or math.isnan(best) or best < 0:
        raise ValueError(f"best_score must be a number ≥ 0, got {best!r}")
    steps = [
        _count("evaluations step", row[0]) if isinstance(row, list) and len(row) == 3 else row
        for row in state.get("evaluations", [])
    ]
    if any(not isinstance(s, int) for s in steps) or steps != sorted(set(steps)) or (steps and steps[-1] > done):
        raise ValueError(f"evaluations must be rows [timesteps, score, seconds] at increasing steps ≤ {done}")
    return state


def _check_checkpoint(model, tensors: dict, meta: dict) -> None:
    """ValueError naming what in a checkpoint's arrays and counts does not fit ``model``: the step and update
    counts, every array's name and shape, finite values, and the optimizer moments (one entry per parameter of
    its shape, squared means ≥ 0, a step count ≥ 0)."""
    timesteps = _count("timesteps", meta.get("timesteps"))
    _count("n_updates", meta.get("n_updates", 0))
    check_progress(meta.get("state"), timesteps)
    expected = {f"policy/{k}": v for k, v in model.policy.state_dict().items()}
    for name, value in _variables(model).items():
        expected[f"var/{name}"] = value
    norm = _vecnormalize(model)
    if norm is not None:
        shape = np.shape(norm.ret_rms.mean)
        expected.update({"vecnormalize/ret_rms/mean": shape, "vecnormalize/ret_rms/var": shape})
        expected["vecnormalize/ret_rms/count"] = ()
    groups = meta.get("optimizers")
    if not isinstance(groups, dict):
        raise ValueError("no optimizer parameter groups in the metadata")
    for name, opt in _optimizers(model).items():
        saved = groups.get(name)
        params = [p for g in opt.param_groups for p in g["params"]]
        if not isinstance(saved, list) or [len(g.get("params", ())) if isinstance(g, dict) else -1 for g in saved] != [
            len(g["params"]) for g in opt.param_groups
        ]:
            raise ValueError(f"optimizer {name}: parameter groups do not fit the model's ({len(params)} parameters)")
        ids = [i for g in saved for i in g["params"]]
        if any(isinstance(i, bool) or not isinstance(i, int) for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"optimizer {name}: parameter ids must be distinct integers, got {ids}")
        param_of = dict(zip(ids, params))
        fields: dict[str, set] = {}
        for key in _group(tensors, f"optim/{name}/"):
            idx, field = key.split("/", 1)
            if not idx.isdigit() or int(idx) not in param_of:
                raise ValueError(f"optim/{name}/{key}: no parameter {idx} in the optimizer")
            fields.setdefault(idx, set()).add(field)
            shape = () if field == "step" else tuple(param_of[int(idx)].shape)
            expected[f"optim/{name}/{key}"] = shape
        if len({frozenset(f) for f in fields.values()}) > 1:
            raise ValueError(f"optimizer {name}: its parameters' moments differ in kind ({fields})")
    unknown = sorted(set(tensors) - set(expected))
    missing = sorted(k for k in set(expected) - set(tensors) if not k.startswith("vecnormalize/"))
    if unknown or missing:
        raise ValueError(f"arrays {', '.join(unknown)} unknown; {', '.join(missing) or 'none'} missing".lstrip())
    for key, value in tensors.items():
        shape = expected[key]
        shape = tuple(shape.shape) if hasattr(shape, "shape") else shape
        squared = key.rsplit("/", 1)[-1] in (*SQUARED_MOMENTS, "var", "step", "count")
        _array(key, value, shape, nonnegative=squared and not key.startswith("policy/"))
    if "vecnormalize/ret_rms/count" in tensors and not float(tensors["vecnormalize/ret_rms/count"]) > 0:
        raise ValueError("vecnormalize/ret_rms/count must be > 0")


def load_checkpoint(model, path: Path) -> dict:
    """Restore ``model`` (built from the run's config, its env wrapped as in training) from a checkpoint,
    checked first (``_check_checkpoint``: nothing is loaded from a checkpoint that does not fit); returns the
    progress ``state`` saved with it."""
    import torch

    tensors, meta = read(path, _algo(model))
    try:
        _check_checkpoint(model, tensors, meta)
    except ValueError as exc:
        raise RunError(f"{path}: the checkpoint does not fit the model that run.yaml describes: {exc}") from None
    _load_policy(model, tensors, path)
    try:
        state, groups = dict(meta["state"]), meta["optimizers"]
        for name, opt in _optimizers(model).items():
            entries: dict[int, dict] = {}
            for key, value in _group(tensors, f"optim/{name}/").items():
                idx, field = key.split("/", 1)
                entries.setdefault(int(idx), {})[field] = value
            opt.load_state_dict({"state": entries, "param_groups": groups[name]})
        with torch.no_grad():
            for name, var in _variables(model).items():
                var.copy_(tensors[f"var/{name}"])
        norm = _vecnormalize(model)
        if norm is not None and "vecnormalize/ret_rms/mean" in tensors:
            rms = norm.ret_rms
            rms.mean = tensors["vecnormalize/ret_rms/mean"].numpy().astype(np.float64).reshape(rms.mean.shape)
            rms.var = tensors["vecnormalize/ret_rms/var"].numpy().astype(np.float64).reshape(rms.var.shape)
            rms.count = float(tensors["vecnormalize/ret_rms/count"])
        model.num_timesteps = int(meta["timesteps"])
        model._n_updates = int(meta.get("n_updates", 0))
        state["timesteps"] = model.num_timesteps
    except (KeyError, ValueError, TypeError, RuntimeError, AttributeError) as exc:
        raise RunError(
            f"{path}: the checkpoint does not fit the model that run.yaml describes ({type(exc).__name__}: {exc})"
        ) from None
    return state


# ----------------------------------------------------------------- SAC's replay buffer

BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def save_replay_buffer(model, path: Path, timesteps: int) -> None:
    """The filled rows of the replay buffer's arrays, with its insertion position."""
    import torch

    buf = model.replay_buffer
    size = buf.buffer_size if buf.full else buf.pos
    arrays = {k: getattr(buf, k) for k in BUFFER_ARRAYS if getattr(buf, k, None) is not None}
    tensors = {k: torch.from_numpy(np.ascontiguousarray(v[:size])) for k, v in arrays.items()}
    _write(
        path, tensors, {"algo": _algo(model), "timesteps": int(timesteps), "pos": int(buf.pos), "full": bool(buf.full)}
    )


def load_replay_buffer(model, path: Path) -> None:
    """Fill ``model``'s replay buffer from ``path``; RunError if its arrays do not fit the buffer."""
    tensors, meta = read(path, _algo(model))
    buf = model.replay_buffer
    try:
        pos, full = int(meta["pos"]), bool(meta["full"])
        size = buf.buffer_size if full else pos
        expected = {k for k in BUFFER_ARRAYS if getattr(buf, k, None) is not None}
        if set(tensors) != expected:
            raise ValueError(f"arrays {sorted(tensors)}, expected {sorted(expected)}")
        if not 0 <= pos <= buf.buffer_size or (full and pos == buf.buffer_size):
            raise ValueError(f"position {pos} outside a buffer of {buf.buffer_size}")
        for key, value in tensors.items():
            target = getattr(buf, key)
            if tuple(value.shape) != (size, *target.shape[1:]):
                raise ValueError(f"{key} has shape {tuple(value.shape)}, expected {(size, *target.shape[1:])}")
            target[:size] = value.numpy()
    except (KeyError, ValueError, TypeError) as exc:
        raise RunError(f"{path}: the replay buffer does not fit the model that run.yaml describes ({exc})") from None
    buf.pos, buf.full = pos, full
