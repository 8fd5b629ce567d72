"""DAgger: an observation-only student for any magenv env that has a privileged teacher (an oracle).

The teacher (an oracle of ``magenv.baselines``, handed in by the caller: this
layer does not import baselines) follows the oracle interface:

* ``env_id`` — the env it searches in; ``decision_every`` — samples per decision (k);
* ``candidates`` — (C, action_dim) env actions searched at each decision;
* ``candidate_costs(runner) -> (C,)`` — Σ over its look-ahead of (total error, °)² of each candidate
  applied for one decision and then the continuation rule, rolled from a copy of the env runner's state;
* ``continuation_action(runner) -> (action_dim,)`` — the continuation rule's action at the next decision;
* ``horizon_s`` — the look-ahead, s (the unit of the regret below).

State-dependent candidates: where the env's student inputs give them (``StudentInputs.candidate_actions``,
e.g. MagKalman-v0's rules' own γ with a teacher of ``rule_candidates``), the student scores the C fixed
candidates followed by the S actions computed from the observation, and the teacher costs the same C + S
actions at the same state (``candidate_costs(runner, candidates)``, candidates (C + S, action_dim)); the
student can then always fall back on a rule and learns where to deviate from it.

The student is an MLP over inputs built from the env's extended observation
(``magenv.agents.student_inputs``: per env the observation options and the
feature function); its logits score the C candidates, and it acts (config ``act``) with the
probability-weighted mean candidate action (``mean``, the default) or with its most probable candidate
(``argmax``: for an action with a discrete part, e.g. MagQSF-v0's none/keep/start code, whose mean of "none"
and "start" would be "keep").

Training (Ross et al. 2011; β, config ``beta``, is the teacher's share of the decisions from iteration 1 on):

1. iteration 0's data: the teacher's own trajectories (at each decision the
   cheapest candidate; ``first: rule``: the continuation rule's) on
   ``trials_per_scenario`` training trials (seeds ≥ ``train_seed`` ≥ 10000)
   per scenario (an integer, or a mapping scenario → n: iteration j then takes
   seeds ``train_seed`` + n·j … + n·j + n − 1 of that scenario; a real recording,
   ``recording:PATH`` or ``recording:GLOB`` for each file it matches, is one trial
   that every iteration revisits with its newest student), the visited
   states labelled with the candidate costs (every decision, or one in
   ``label_every``: the labels are the expensive part);
2. each iteration: fit a fresh student on all data so far, with the
   cost-sensitive "regret" loss Σ_c softmax(logits)_c · r_c, where
   r_c = 100 · (cost_c − min cost) / (H · MSE of the continuation rule on that
   trial) (H = look-ahead samples: a unit of r is 1 % of the trial's rule MSE; ``regret_scale: best_rule``:
   of the lowest MSE of the teacher's rules, ``rule_actions(runner)`` (R, action_dim), each acting alone, so
   that a protocol whose continuation rule is poor is not weighted down; ``teacher``: of the teacher's own
   closed-loop run, what can be reached — so that a trial the rule fails badly is not weighted down, and a
   change of the error counts as it counts in the per-trial ratio of RMSEs the targets are stated in);
   with ``regret_clip: R`` each r_c is clipped at R in the loss (regrets are heavy-tailed: the states of a
   diverged roll-out cost 10³–10⁵ units and otherwise decide the fit; the stored data keep the raw values);
   with ``rule_margin: m`` every candidate other than the continuation rule's action at that state
   (``teacher.rule_candidate(runner, candidates)``, else the first candidate equal to ``continuation_action``;
   states where the rule's action is no candidate are left as they are) costs m units more in the loss, so that
   the student departs from the rule only where the teacher's advantage exceeds m (a conservative improvement:
   the short look-ahead's labels are noisy where the advantage is small);
   score it closed loop on the validation seeds (5000–9999, ``magenv.seeding``) by the mean over
   scenarios of its RMSE ratio of means to the continuation rule; keep the best;
3. roll the student (with probability β per decision the teacher) on new
   training trials, label every state it visits, add them, repeat;
4. with ``ensemble: K`` > 1, the student is the K iterations of lowest validation
   score together, their candidate probabilities averaged (fits of the same data
   differ from iteration to iteration; their mean is steadier); it is scored on
   the same validation trials, and run.yaml records its members and score.

A run continues (``train(…, resume=True)``, ``magenv train --teacher NAME --out RUN --resume --iters N``) from
its folder up to N iterations in all, with the run's own config: the labelled data of each iteration are kept
in ``data/``, and data missing there (a run from before they were kept) are rebuilt by rolling the run's
checkpoints on the same trials. Same config, same chain: a resumed run's students are bit for bit those of
one run of N iterations.

Episodes run in the env itself (``gym.make(env_id, **env_kwargs)``, each trial
through ``reset(options={"trial": …})``), so training sees exactly the
observations and action handling of evaluation; the teacher reads the env's
runner.

The run folder holds weights and arrays only (``magenv.agents.weights`` format, numpy ``.npz``; no pickles), always
whole: a run holds its lock while it writes (a second run into it stops at once); the files that change —
``run.yaml``, ``best.safetensors``, ``iterations.csv`` — are written as one transaction with ``state.json``
(``magenv.agents.run_folder``), so a kill leaves them as they were before a step or after it, and the write-once
files (an iteration's data and checkpoint) are written whole before the step that names them::

    state.json           the committed state: iterations done, the SHA-256 of run.yaml, best and the log
    run.yaml             env id, env kwargs, algo "dagger", the config, the student's shape and input constants
    best.safetensors     the student with the best validation score
    checkpoints/it_N.safetensors   the student of each iteration (an ensemble's members: run.yaml ``ensemble``)
    iterations.csv       validation RMSE (°) and ratio to the rule per scenario and iteration
    data/it_N.npz        the labelled states added at iteration N: ``obs`` (D, n_obs) float32, ``regret``
                         (D, C + S) float32 in % of the trial's rule MSE, inf where a roll-out failed, ``rule``
                         (D,) int16 the continuation rule's candidate (−1: none; absent in runs from before it)
                         (compressed; for resuming only, never shipped; a MagBlend iteration's is ~150 k
                         states × 126 features)

A refit (``refit(source, out, teacher, changes)``, ``magenv train --teacher NAME --refit SOURCE --out RUN``)
fits one fresh student on all of a finished run's labelled data with some fit keys changed (``REFIT_KEYS``:
e.g. a wider ``hidden`` and more ``fit_steps``), scores it on the run's validation trials, and writes it as a
run of one row; run.yaml's ``refit_of`` names the source and the iterations its data came from.

``load_policy(run_dir)`` rebuilds the student as a Policy.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml

from magenv.agents.run_folder import RunFolder
from magenv.agents.student_inputs import StudentInputs, inputs_for
from magenv.agents.weights import RunError, _write, read
from magenv.envs import BLEND_ID
from magenv.seeding import HELD_OUT_BELOW, VALIDATION_START

ALGO = "dagger"
RECORDING = "recording:"  # a config entry of a real recording (``recording:PATH`` or ``recording:GLOB``)
RUN_FILE, BEST, CHECKPOINTS, LOG, DATA = "run.yaml", "best.safetensors", "checkpoints", "iterations.csv", "data"
DEFAULTS: dict[str, Any] = {
    "iterations": 6,
    "trials_per_scenario": 20,
    "scenarios": ["dynamic_magnet", "stationary_magnet", "dynamic_clean"],
    "train_seed": 10000,
    "val_seeds": [5000, 5020],
    "val_scenarios": None,
    "beta": 0.0,
    "decision_every": 8,
    "fit_steps": 12000,
    "batch_size": 1024,
    "learning_rate": 1.0e-3,
    "hidden": [128, 128],
    "seed": 0,
    "label_every": 1,
    "first": "teacher",
    "act": "mean",
    "ensemble": 1,
    "regret_scale": "rule",
    "regret_clip": None,
    "rule_margin": 0.0,
    "guard": None,
}
GUARD_KEYS = {"fallback", "margin", "disagree"}  # the ``guard`` config: see :class:`Student`
GUARD_OPTIONAL = {"band": np.inf}  # guard keys a config may leave out, and their defaults
RESUMABLE = ("iterations", "ensemble")  # the config keys a resumed run may change
# the fit keys a refit may change
REFIT_KEYS = ("hidden", "fit_steps", "batch_size", "learning_rate", "seed", "regret_clip", "rule_margin")
ACTS = ("mean", "argmax")  # how the student turns its candidate probabilities into an action
REGRET_SCALES = ("rule", "best_rule", "teacher")  # the trial MSE a unit of regret is 1 % of
REGRET_UNIT = 100.0  # r_c in % of the trial's rule MSE
TEACHER_NEEDS = ("env_id", "candidates", "decision_every", "candidate_costs", "continuation_action", "horizon_s")
_SHAPE_KEYS = ("hidden", "candidates", "n_inputs", "act", "guard")  # run.yaml student keys: not input constants


def check_config(config: dict | None) -> dict:
    """DEFAULTS updated by ``config``; unknown keys and bad values raise ValueError naming them."""
    config = dict(config or {})
    unknown = sorted(set(config) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"unknown DAgger config key(s) {unknown}; known: {sorted(DEFAULTS)}")
    cfg = {**DEFAULTS, **config}
    from magenv.scenarios import expand_mixture

    if isinstance(cfg["scenarios"], (str, list)):
        cfg["scenarios"] = expand_recordings(expand_mixture(cfg["scenarios"]))  # "twins:DIR", "recording:GLOB"
    if not isinstance(cfg["scenarios"], list) or not cfg["scenarios"]:
        raise ValueError(f"DAgger config 'scenarios' must be a non-empty list, got {cfg['scenarios']!r}")
    per = cfg["trials_per_scenario"]
    if isinstance(per, dict):  # scenario → trials: more distinct trials where the student needs them
        per = cfg["trials_per_scenario"] = {sc: n for key, n in per.items() for sc in expand_mixture([key])}
        simulated = sorted(sc for sc in cfg["scenarios"] if not sc.startswith(RECORDING))
        if sorted(per) != simulated:
            raise ValueError(f"trials_per_scenario names scenarios {sorted(per)}; it must name exactly {simulated}")
        counts = list(per.values())
    else:
        counts = [per]
    if any(not _is_int(n) or n < 1 for n in counts):
        raise ValueError(f"DAgger config 'trials_per_scenario' must be a positive integer (or a scenario → positive "
                         f"integer mapping), got {per!r}")  # fmt: skip
    for key in (
        "iterations",
        "decision_every",
        "fit_steps",
        "batch_size",
        "label_every",
        "ensemble",
    ):
        if not _is_int(cfg[key]) or cfg[key] < 1:
            raise ValueError(f"DAgger config {key!r} must be a positive integer, got {cfg[key]!r}")
    if not _is_int(cfg["train_seed"]) or cfg["train_seed"] < HELD_OUT_BELOW:
        raise ValueError(f"train_seed must be an integer ≥ {HELD_OUT_BELOW}, got {cfg['train_seed']!r}")
    if not _is_int(cfg["seed"]) or cfg["seed"] < 0:
        raise ValueError(f"DAgger config 'seed' must be a non-negative integer, got {cfg['seed']!r}")
    chosen = cfg["val_scenarios"]
    if chosen is not None:
        if not isinstance(chosen, list) or not chosen or any(sc not in cfg["scenarios"] for sc in chosen):
            raise ValueError(
                f"val_scenarios must be null or a non-empty list of the config's scenarios, got {chosen!r}"
            )
    val = cfg["val_seeds"]
    if not (isinstance(val, list) and len(val) == 2 and all(map(_is_int, val))
            and VALIDATION_START <= val[0] < val[1] <= HELD_OUT_BELOW):  # fmt: skip
        raise ValueError(
            f"val_seeds must be [start, stop), integers within the validation seeds {VALIDATION_START}–"
            f"{HELD_OUT_BELOW - 1}, got {val!r}"
        )
    for key, ok, what in (("beta", lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]"),
                          ("learning_rate", lambda v: 0.0 < v < np.inf, "a positive number"),
                          ("rule_margin", lambda v: 0.0 <= v < np.inf, "a non-negative number")):  # fmt: skip
        if isinstance(cfg[key], bool) or not isinstance(cfg[key], (int, float)) or not ok(cfg[key]):
            raise ValueError(f"DAgger config {key!r} must be {what}, got {cfg[key]!r}")
    if cfg["ensemble"] > cfg["iterations"]:
        raise ValueError(f"ensemble ({cfg['ensemble']}) cannot exceed iterations ({cfg['iterations']})")
    if cfg["first"] not in ("teacher", "rule"):
        raise ValueError(f"first must be 'teacher' or 'rule', got {cfg['first']!r}")
    if cfg["act"] not in ACTS:
        raise ValueError(f"act must be one of {list(ACTS)}, got {cfg['act']!r}")
    if cfg["regret_scale"] not in REGRET_SCALES:
        raise ValueError(f"regret_scale must be one of {list(REGRET_SCALES)}, got {cfg['regret_scale']!r}")
    clip = cfg["regret_clip"]
    if clip is not None and (isinstance(clip, bool) or not isinstance(clip, (int, float)) or not 0 < clip < np.inf):
        raise ValueError(f"regret_clip must be a positive number (or null: no clip), got {clip!r}")
    guard = cfg["guard"]
    if guard is not None:
        if not isinstance(guard, dict) or not GUARD_KEYS <= set(guard) <= GUARD_KEYS | set(GUARD_OPTIONAL):
            raise ValueError(f"guard must be null or a mapping of {sorted(GUARD_KEYS)} (and optionally "
                             f"{sorted(GUARD_OPTIONAL)}), got {guard!r}")  # fmt: skip
        fb = guard["fallback"]
        if fb != "rule" and (not isinstance(fb, list) or not fb or not all(_is_number(v) for v in fb)):
            raise ValueError(f"guard fallback must be a list of numbers (an action) or 'rule', got {fb!r}")
        if not (_is_number(guard["margin"]) and 0 <= guard["margin"] < np.inf):
            raise ValueError(f"guard margin must be a non-negative number, got {guard['margin']!r}")
        if not (_is_number(guard["disagree"]) and 0 < guard["disagree"] <= np.inf):
            raise ValueError(f"guard disagree must be a positive number (.inf: never), got {guard['disagree']!r}")
        band = guard.get("band", GUARD_OPTIONAL["band"])
        if not (_is_number(band) and 0 <= band <= np.inf):
            raise ValueError(f"guard band must be a non-negative number (.inf: unbounded), got {band!r}")
    hidden = cfg["hidden"]
    if not isinstance(hidden, list) or not hidden or not all(_is_int(h) and h >= 1 for h in hidden):
        raise ValueError(f"hidden must be a list of positive layer widths, got {hidden!r}")
    return cfg


def expand_recordings(names: list) -> list:
    """``names`` with each ``recording:GLOB`` entry replaced by ``recording:PATH`` of every file it matches
    (``magenv.recordings.match_recordings``; ValueError if none); other entries as they are."""
    from magenv.recordings import match_recordings

    out: list = []
    for name in names:
        if isinstance(name, str) and name.startswith(RECORDING):
            out += [f"{RECORDING}{p}" for p in match_recordings(name[len(RECORDING) :])]
        else:
            out.append(name)
    return out


def make_trial(name: str, seed: int):
    """The trial of a config entry: a real recording (``recording:PATH``, the same trial whatever ``seed``), else
    ``magenv.scenarios.make_trial(name, seed)``."""
    from magenv import scenarios
    from magenv.recordings import load_recording

    if name.startswith(RECORDING):
        return load_recording(name[len(RECORDING) :])
    return scenarios.make_trial(name, seed)


def trials_per(cfg: dict, name: str) -> int:
    """New training trials of config entry ``name`` per iteration: 1 for a recording, else
    ``trials_per_scenario``'s."""
    if name.startswith(RECORDING):
        return 1
    per = cfg["trials_per_scenario"]
    return per[name] if isinstance(per, dict) else per


def _is_number(v) -> bool:
    """A finite or infinite float or int, not a bool."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and not np.isnan(v)


def _is_int(v) -> bool:
    """An integer and not a bool (YAML's ``true`` is a Python int)."""
    return isinstance(v, int) and not isinstance(v, bool)


def candidate_matrix(candidates) -> np.ndarray:
    """Candidates as a (C, action_dim) float array (a flat list is C scalar actions); ValueError otherwise."""
    cands = np.asarray(candidates, np.float64)
    if cands.ndim == 1:
        cands = cands[:, None]
    if cands.ndim != 2 or cands.size == 0 or not np.all(np.isfinite(cands)):
        raise ValueError(f"candidates must be a non-empty finite (C, action_dim) array, got shape {cands.shape}")
    return cands


# ----------------------------------------------------------------- the student


class Student:
    """The MLP (tanh hidden layers) over the standardised inputs; numpy inference.

    Args:
        layers: [(W (out, in), b (out,)), …] float32, the last one the logits over ``candidates``.
        mu, sd: (n_in,) input standardisation. candidates: (C, action_dim) env actions (or (C,) scalars).
        inputs: the env's feature function (``magenv.agents.student_inputs``); meta: its per-run constants
            (with them, ``inputs.n_state_candidates(meta)`` state-dependent candidates follow the fixed ones).
        act: ``mean`` (the probability-weighted mean candidate) or ``argmax`` (the most probable one).
        bounds: (lo, hi) (n_in,) the range of each input over the data the student was fitted on, or None.
        guard: the config's ``guard`` (run.yaml student ``guard``), or None.

    **Guard** (``fallback`` an action, ``margin`` m, ``disagree`` d): the student
    acts with ``fallback`` (e.g. MagVQF-v0's u = 1: VQF's own decision; ``rule``: the last state-dependent
    candidate, the teacher's continuation rule at this state) wherever an input leaves its fitted
    range widened by m·(hi − lo) on each side — a state unlike any it learned from — and, in an ensemble,
    wherever the members' actions spread by more than d. ``guarded`` counts those decisions, ``decisions``
    all of them (since construction). With ``band`` b (optional, default ∞) every other action is clipped to
    the fallback ± b, element-wise: a bounded departure from the fallback (e.g. from the teacher's rule) that
    no learned state can widen.
    """

    def __init__(self, layers, mu, sd, candidates, inputs: StudentInputs, meta: dict, act: str = "mean",
                 bounds=None, guard: dict | None = None):  # fmt: skip
        if act not in ACTS:
            raise ValueError(f"act must be one of {list(ACTS)}, got {act!r}")
        self.layers = [(np.asarray(w, np.float32), np.asarray(b, np.float32)) for w, b in layers]
        self.mu, self.sd = np.asarray(mu, np.float32), np.asarray(sd, np.float32)
        self.candidates = candidate_matrix(candidates)
        self._columns = [np.ascontiguousarray(c) for c in self.candidates.T]
        self.feature_fn, self.meta, self.act = inputs, dict(meta), act
        self.n_state = state_candidate_count(inputs, self.meta)
        self.bounds = None if bounds is None else tuple(np.asarray(b, np.float32) for b in bounds)
        self.guard = None if guard is None else {**GUARD_OPTIONAL, **guard}
        if self.guard is not None and self.guard["fallback"] == "rule" and not self.n_state:
            raise ValueError("guard fallback 'rule' needs a state-dependent candidate (a teacher with a rule)")
        self.guarded = self.decisions = 0

    def fallback(self, obs: np.ndarray) -> np.ndarray:
        """(action_dim,) float64 the guard's fallback at ``obs``: its action, or the rule's (``rule``)."""
        if self.guard is None:
            raise ValueError("a student without a guard has no fallback")
        fb = self.guard["fallback"]
        return self.candidates_at(obs)[-1].copy() if fb == "rule" else np.asarray(fb, np.float64)

    def bounded(self, action: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """``action`` clipped to the guard's fallback ± ``band`` (as it is without a guard or with b = ∞)."""
        if self.guard is None or self.guard["band"] == np.inf:
            return action
        fb, band = self.fallback(obs), float(self.guard["band"])
        return np.clip(action, fb - band, fb + band)

    def outside(self, x: np.ndarray) -> bool:
        """Whether inputs ``x`` (1, n_in) leave the guard's widened fitted range (False without a guard)."""
        if self.guard is None or self.bounds is None:
            return False
        lo, hi = self.bounds
        pad = float(self.guard["margin"]) * (hi - lo)
        return bool(np.any(x < lo - pad) or np.any(x > hi + pad))

    def _choose(self, p: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The action of candidate probabilities ``p`` (C + S,) at ``obs``: their weighted mean or the argmax."""
        cands, columns = self.candidates, self._columns
        if self.n_state:  # (fixed-candidate students: the arithmetic of before, bit for bit)
            cands = self.candidates_at(obs)
            columns = [np.ascontiguousarray(c) for c in cands.T]
        if self.act == "argmax":
            return cands[int(np.argmax(p))].copy()
        return np.array([p @ col for col in columns])

    def inputs(self, obs: np.ndarray) -> np.ndarray:
        """(D, n_obs) observations → (D, n_in) network inputs."""
        return self.feature_fn(obs, self.meta)

    def candidates_at(self, obs: np.ndarray) -> np.ndarray:
        """(C + S, action_dim) the candidates for one observation: the fixed ones, then the state-dependent."""
        return candidates_at(self.candidates, self.feature_fn, self.meta, obs)

    def probabilities(self, x: np.ndarray) -> np.ndarray:
        """Softmax over the candidates for inputs ``x`` (D, n_in)."""
        z = (x - self.mu) / self.sd
        for i, (w, b) in enumerate(self.layers):
            z = z @ w.T + b
            if i < len(self.layers) - 1:
                z = np.tanh(z)
        z = z - z.max(1, keepdims=True)
        p = np.exp(z)
        return p / p.sum(1, keepdims=True)

    def action(self, obs: np.ndarray) -> np.ndarray:
        """(action_dim,) float64 for one observation: the probability-weighted mean of the candidates
        (``act="mean"``) or the most probable candidate (``"argmax"``, the first on ties); the guard's
        fallback where it holds (class docstring)."""
        x = self.inputs(obs)
        self.decisions += 1
        if self.guard is not None and self.outside(x):
            self.guarded += 1
            return self.fallback(obs)
        return self.bounded(self._choose(self.probabilities(x)[0], obs), obs)

    def tensors(self) -> dict:
        import torch

        out = {"mu": torch.as_tensor(self.mu), "sd": torch.as_tensor(self.sd)}
        if self.bounds is not None:
            out["guard/lo"], out["guard/hi"] = (torch.as_tensor(b) for b in self.bounds)
        for i, (w, b) in enumerate(self.layers):
            out[f"layer{i}/weight"], out[f"layer{i}/bias"] = torch.as_tensor(w), torch.as_tensor(b)
        return out

    def save(self, path: Path, meta: dict) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        _write(path, self.tensors(), {"algo": ALGO, **meta})

    @classmethod
    def load(cls, path: Path, student: dict, inputs: StudentInputs) -> Student:
        """The student in ``path`` with the shape of run.yaml's ``student`` section (RunError if they differ)."""
        tensors, _ = read(path, ALGO)
        try:
            layers = [
                (tensors[f"layer{i}/weight"].numpy(), tensors[f"layer{i}/bias"].numpy())
                for i in range(len(student["hidden"]) + 1)
            ]
            mu, sd = tensors["mu"].numpy(), tensors["sd"].numpy()
        except KeyError as exc:
            raise RunError(f"{path}: missing tensor {exc}") from None
        meta = {k: v for k, v in student.items() if k not in _SHAPE_KEYS}
        try:
            n_in, candidates = int(student["n_inputs"]), candidate_matrix(student["candidates"])
            widths = [*(int(h) for h in student["hidden"]), len(candidates) + state_candidate_count(inputs, meta)]
        except (KeyError, TypeError, ValueError) as exc:
            raise RunError(
                f"{path}: run.yaml's student section is not one of ours ({type(exc).__name__}: {exc})"
            ) from None
        block = meta.get("block", 1)  # the stride of the blocked inputs (magenv.agents.student_inputs)
        if not _is_int(block) or block < 1:
            raise RunError(f"{path}: run.yaml's student block must be a positive integer, got {block!r}")
        want = [((o, i), (o,)) for o, i in zip(widths, [n_in, *widths[:-1]])]
        if mu.shape != (n_in,) or sd.shape != (n_in,) or [(w.shape, b.shape) for w, b in layers] != want:
            raise RunError(f"{path}: the weights do not fit the student of run.yaml ({n_in} inputs, {widths})")
        if not all(np.all(np.isfinite(a)) for a in (mu, sd, *(t for pair in layers for t in pair))) or np.any(sd <= 0):
            raise RunError(f"{path}: the weights hold non-finite values or a non-positive input scale sd")
        act = student.get("act", "mean")  # run folders from before ``act`` act with the mean
        if act not in ACTS:
            raise RunError(f"{path}: run.yaml's student act {act!r} is not one of {list(ACTS)}")
        bounds = None
        if "guard/lo" in tensors:  # students fitted since the guard: their inputs' range
            bounds = (tensors["guard/lo"].numpy(), tensors["guard/hi"].numpy())
            if any(b.shape != (n_in,) or not np.all(np.isfinite(b)) for b in bounds) or np.any(bounds[0] > bounds[1]):
                raise RunError(f"{path}: the guard's input range must be two finite ({n_in},) arrays, lo ≤ hi")
        guard = student.get("guard")
        if guard is not None and (
            not isinstance(guard, dict) or not GUARD_KEYS <= set(guard) <= GUARD_KEYS | set(GUARD_OPTIONAL)
            or bounds is None
        ):  # fmt: skip
            raise RunError(f"{path}: run.yaml's student guard must hold {sorted(GUARD_KEYS)} (and optionally "
                           f"{sorted(GUARD_OPTIONAL)}) and the weights its input range")  # fmt: skip
        try:
            return cls(layers, mu, sd, candidates, inputs, meta, act, bounds, guard)
        except ValueError as exc:
            raise RunError(f"{path}: {exc}") from None


class Ensemble(Student):
    """Students of one run acting together: the mean of their candidate probabilities (members share the
    inputs, the candidates, the input constants and ``act``; each keeps its own standardisation)."""

    def __init__(self, members: list[Student]):
        first = members[0]
        self.members, self.candidates, self._columns = list(members), first.candidates, first._columns
        self.feature_fn, self.meta, self.act, self.n_state = first.feature_fn, first.meta, first.act, first.n_state
        self.guard = first.guard
        self.guarded = self.decisions = 0

    def probabilities(self, x: np.ndarray) -> np.ndarray:
        return np.mean([m.probabilities(x) for m in self.members], axis=0)

    def action(self, obs: np.ndarray) -> np.ndarray:
        """The members' mean probabilities acted on as by one student; with a guard, its fallback where any
        member's inputs leave its range or the members' own actions spread by more than ``disagree``."""
        guard = self.guard
        if guard is None:
            return self._choose(self.probabilities(self.inputs(obs))[0], obs)
        x = self.inputs(obs)
        self.decisions += 1
        probs = [m.probabilities(x)[0] for m in self.members]
        acts = np.array([m._choose(p, obs) for m, p in zip(self.members, probs)])
        if any(m.outside(x) for m in self.members) or np.any(np.ptp(acts, axis=0) > float(guard["disagree"])):
            self.guarded += 1
            return self.fallback(obs)
        return self.bounded(self._choose(np.mean(probs, axis=0), obs), obs)

    def tensors(self) -> dict:
        raise TypeError("an ensemble is saved as its members' checkpoints (run.yaml 'ensemble')")


class StudentPolicy:
    """A DAgger student acting in its env (``magenv.protocols.Policy``; memoryless: its memory is the
    observation's lagged features)."""

    def __init__(
        self,
        student: Student,
        name: str = "dagger",
        env_kwargs: dict | None = None,
        source: str = "",
        env_id: str = BLEND_ID,
    ):
        self.student, self.name, self.source, self.which, self.env_id = student, name, source, "best", env_id
        self.env_kwargs = dict(inputs_for(env_id).env_kwargs if env_kwargs is None else env_kwargs)

    def reset(self) -> None:
        """Nothing to forget."""

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.student.action(obs).astype(np.float32)


def fit(x: np.ndarray, regret: np.ndarray, cfg: dict, seed: int, candidates, inputs, meta,
        rule: np.ndarray | None = None) -> Student:  # fmt: skip
    """A fresh student fitted to minimise the expected regret Σ_c softmax_c · r_c (Adam, cosine schedule,
    ``fit_steps`` mini-batches of ``batch_size`` rounded to whole epochs); ``rule`` (D,) each state's rule
    candidate (−1: none), needed with ``rule_margin``."""
    import torch

    torch.set_num_threads(1)  # one core: the fits are small, and deterministic on one thread
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    mu = x.mean(0).astype(np.float32)
    sd = (x.std(0) + 1e-6).astype(np.float32)
    xt = torch.as_tensor((x - mu) / sd, dtype=torch.float32)
    if cfg["regret_clip"] is not None:  # a bounded loss per state: diverged roll-outs do not drown the rest
        regret = np.minimum(regret, np.float32(cfg["regret_clip"]))
    if cfg["rule_margin"] > 0:
        if rule is None:
            raise ValueError("rule_margin needs each state's rule candidate, which data from before it lack")
        regret = with_rule_margin(regret, rule, cfg["rule_margin"])
    if not np.all(np.isfinite(regret)):
        raise ValueError("regrets hold inf (a candidate's roll-out failed); set regret_clip to bound them")
    rt = torch.as_tensor(regret, dtype=torch.float32)
    layers, width = [], x.shape[1]
    for h in cfg["hidden"]:
        layers += [torch.nn.Linear(width, int(h)), torch.nn.Tanh()]
        width = int(h)
    layers.append(torch.nn.Linear(width, regret.shape[1]))
    net = torch.nn.Sequential(*layers)
    opt = torch.optim.Adam(net.parameters(), lr=cfg["learning_rate"])
    n, batch = len(xt), min(cfg["batch_size"], len(xt))
    epochs = max(1, int(round(cfg["fit_steps"] * batch / n)))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs * max(1, n // batch))
    for _ in range(epochs):
        perm = torch.randperm(n, generator=gen)
        for b in range(0, n - batch + 1, batch):
            ix = perm[b : b + batch]
            loss = (torch.softmax(net(xt[ix]), 1) * rt[ix]).sum(1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
    linear = [m for m in net if isinstance(m, torch.nn.Linear)]
    weights = [(m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in linear]
    bounds = (x.min(0), x.max(0)) if cfg["guard"] is not None else None
    return Student(weights, mu, sd, candidates, inputs, meta, cfg["act"], bounds, cfg["guard"])


def with_rule_margin(regret: np.ndarray, rule: np.ndarray, margin: float) -> np.ndarray:
    """``regret`` (D, C) with ``margin`` added to every candidate but the rule's (``rule`` (D,), −1: the state
    is left as it is)."""
    out = regret + np.float32(margin)
    ruled = rule >= 0
    out[~ruled] = regret[~ruled]
    out[np.flatnonzero(ruled), rule[ruled]] = regret[np.flatnonzero(ruled), rule[ruled]]
    return out


def state_candidate_count(inputs: StudentInputs | None, meta: dict) -> int:
    """S, the state-dependent candidates of the inputs ``inputs`` with constants ``meta`` (0 without inputs)."""
    return 0 if inputs is None else int(inputs.n_state_candidates(meta))


def candidates_at(fixed: np.ndarray, inputs: StudentInputs, meta: dict, obs: np.ndarray) -> np.ndarray:
    """(C + S, action_dim) float64: the fixed candidates (C, action_dim), then the S state-dependent ones of
    one observation (``inputs.candidate_actions``); the same numbers at label time and at act time."""
    if not state_candidate_count(inputs, meta):
        return fixed
    return np.concatenate([fixed, inputs.candidate_actions(obs, meta)[0]])


# ----------------------------------------------------------------- episodes


class Labelled(NamedTuple):
    """The labelled decisions of one episode (``Episodes.run``) and its RMSE."""

    obs: np.ndarray  # (D, n_obs) float32 observations
    costs: np.ndarray  # (D, C + S) the teacher's candidate costs
    rule: np.ndarray  # (D,) int16 the continuation rule's candidate (−1: its action is no candidate)
    rmse: float  # °, the episode's total error


class Episodes:
    """Closed-loop episodes of one env with the student's observation, the teacher reading its runner.

    ``run(trial, act, label_every, needs_costs)``: ``act(obs, runner, costs)`` → the action (action_dim,) at
    each decision, ``costs`` the teacher's (C + S,) candidate costs at that state on the labelled decisions (every
    ``label_every``-th from the first; 0 = none) and, with ``needs_costs``, on all (else None). Returns
    ``Labelled``. With ``candidates_at`` (obs → (C + S, action_dim)) the teacher costs those candidates of each
    state (state-dependent ones)."""

    def __init__(self, env_id: str, env_kwargs: dict, teacher, candidates_at: Callable | None = None):
        self.env_id, self.env_kwargs, self.teacher = env_id, dict(env_kwargs), teacher
        self.candidates_at = candidates_at
        self._fixed = candidate_matrix(teacher.candidates)
        self._env = None

    def candidates(self, obs: np.ndarray) -> np.ndarray:
        """(C + S, action_dim) the candidates the teacher costs at the state whose observation is ``obs``."""
        return self._fixed if self.candidates_at is None else self.candidates_at(obs)

    def costs(self, cands: np.ndarray, runner) -> np.ndarray:
        """The teacher's costs of ``cands`` (this state's ``candidates``) at ``runner``'s state."""
        if self.candidates_at is None:
            return self.teacher.candidate_costs(runner)
        return self.teacher.candidate_costs(runner, cands)

    def rule_index(self, cands: np.ndarray, runner) -> int:
        """The index of the continuation rule's action among ``cands`` (this state's ``candidates``; −1: none):
        ``teacher.rule_candidate(runner, cands)`` if the teacher has it, else the first candidate within 1e-5 of
        ``teacher.continuation_action(runner)``."""
        if hasattr(self.teacher, "rule_candidate"):
            return int(self.teacher.rule_candidate(runner, cands))
        same = np.all(np.abs(cands - self.teacher.continuation_action(runner)) <= 1e-5, axis=1)
        return int(np.argmax(same)) if same.any() else -1

    def env(self, trial):
        if self._env is None:
            import gymnasium as gym

            import magenv  # noqa: F401  (registers the envs)

            kwargs = {**self.env_kwargs, "scenario": [trial]}
            self._env = gym.make(self.env_id, disable_env_checker=True, **kwargs).unwrapped
        return self._env

    def run(self, trial, act: Callable[[np.ndarray, Any, Any], np.ndarray], label_every: int = 1,
            needs_costs: bool = False):  # fmt: skip
        from magenv import metrics

        env = self.env(trial)
        o, _ = env.reset(seed=0, options={"trial": trial})
        obs, costs, rule = [], [], []
        done, d = False, 0
        while not done:
            label = label_every > 0 and d % label_every == 0
            c = None
            if label or needs_costs:
                cands = self.candidates(o)
                c = self.costs(cands, env._runner)
            if label:
                obs.append(o)
                costs.append(c)
                rule.append(self.rule_index(cands, env._runner))
            o, _, terminated, truncated, _ = env.step(np.asarray(act(o, env._runner, c), np.float64))
            done, d = terminated or truncated, d + 1
        rmse = metrics.score(env.estimate, trial.q_true, trial.score_mask).total
        return Labelled(np.array(obs), np.array(costs), np.array(rule, np.int16), rmse)


def teacher_episodes(env_id: str, env_kwargs: dict, teacher, inputs: StudentInputs, meta: dict, fixed) -> Episodes:
    """Episodes whose teacher costs the fixed candidates ``fixed`` (C, action_dim), then (if the inputs ``inputs``
    with constants ``meta`` have any) the state-dependent ones of each observation."""
    fixed = candidate_matrix(fixed)
    if not state_candidate_count(inputs, meta):
        return Episodes(env_id, env_kwargs, teacher)
    return Episodes(env_id, env_kwargs, teacher, lambda o: candidates_at(fixed, inputs, meta, o))


def regret_units(costs: np.ndarray, horizon: int, rule_mse: float) -> np.ndarray:
    """r_c = 100 · (cost_c − min cost) / (H · rule MSE) of candidate costs (D, C): % of the trial's rule MSE."""
    return REGRET_UNIT * (costs - costs.min(1, keepdims=True)) / (horizon * rule_mse)


def check_teacher(teacher, env_id: str | None = None) -> str:
    """The env id the teacher searches in (checked against ``env_id`` if given); ValueError if ``teacher``
    lacks the oracle interface or its env has no student inputs."""
    missing = [a for a in TEACHER_NEEDS if not hasattr(teacher, a)]
    if missing:
        raise ValueError(
            f"teacher {getattr(teacher, 'name', teacher)!r} cannot teach a DAgger student (lacks {missing}); "
            "use an oracle (e.g. oracle, oracle_kalman)"
        )
    if env_id is not None and env_id != teacher.env_id:
        raise ValueError(f"teacher {getattr(teacher, 'name', teacher)!r} searches {teacher.env_id}, not {env_id}")
    inputs_for(teacher.env_id)
    return teacher.env_id


def student_env_kwargs(inputs: StudentInputs, teacher, decision_every: int) -> dict:
    """The options of the env the student acts in: its observation's (``inputs.env_kwargs``), then the teacher's
    own (``teacher.env_kwargs`` if any, e.g. a tuned eq. 18 or QSF detector: the env the teacher searched), and
    ``decision_every``."""
    return {**inputs.env_kwargs, **getattr(teacher, "env_kwargs", {}), "decision_every": int(decision_every)}


def train(
    out: Path,
    teacher,
    config: dict | None = None,
    log: Callable[[str], None] = print,
    env_id: str | None = None,
    resume: bool = False,
) -> Path:
    """Run DAgger from ``teacher`` (in ``env_id``, default the teacher's env) into the new run folder ``out``
    (see the module docstring); returns ``out``. With ``resume`` ``out`` is an existing run that continues with
    its own config, ``config`` giving only a new ``iterations`` (in all) or ``ensemble`` (any other key that
    differs from the run's raises ValueError)."""
    env_id = check_teacher(teacher, env_id)
    out = Path(out)
    run = _resumed_run(out, teacher, env_id, config) if resume else None
    cfg = check_config(run["config"] if run else config)
    if cfg["decision_every"] != teacher.decision_every:
        raise ValueError(
            f"DAgger config decision_every {cfg['decision_every']} differs from the teacher's {teacher.decision_every}"
        )
    if cfg["regret_scale"] == "best_rule" and not hasattr(teacher, "rule_actions"):
        raise ValueError(f"regret_scale best_rule needs a teacher with rule_actions; {teacher.name!r} has none")
    guard = cfg["guard"]
    if guard is not None and guard["fallback"] == "rule":
        inputs = inputs_for(env_id)
        if not state_candidate_count(inputs, inputs.meta(teacher)):
            raise ValueError(f"guard fallback 'rule' needs a teacher whose rule is a candidate; {teacher.name!r} "
                             "has none")  # fmt: skip
    if not resume and (out / RUN_FILE).exists():
        raise ValueError(f"{out} already holds a run; choose another --out (or continue it with --resume)")
    folder = RunFolder(out)
    with folder.locked():
        folder.recover()
        return _train(out, folder, teacher, cfg, run, env_id, log)


def _train(out: Path, folder: RunFolder, teacher, cfg: dict, run: dict | None, env_id: str, log) -> Path:
    """:func:`train` in the locked, recovered run folder ``folder``: every file committed with ``state.json``."""
    k = cfg["decision_every"]
    inputs = inputs_for(env_id)
    cands, meta = candidate_matrix(teacher.candidates), inputs.meta(teacher)
    n_cands = len(cands) + state_candidate_count(inputs, meta)
    env_kwargs = student_env_kwargs(inputs, teacher, k)
    episodes = teacher_episodes(env_id, env_kwargs, teacher, inputs, meta, cands)
    validation = Validation(episodes, teacher, cfg)
    n_obs = episodes.env(validation.trials[0][1]).observation_space.shape[0]
    n_in = int(inputs(np.zeros((1, n_obs), np.float32), meta).shape[1])
    student_meta = {"hidden": [int(h) for h in cfg["hidden"]], "candidates": cands.tolist(), **meta, "n_inputs": n_in}
    if cfg["guard"] is not None:  # run folders without a guard stay as they were
        student_meta["guard"] = dict(cfg["guard"])
    if cfg["act"] != "mean":  # run folders of mean-acting students stay as they were
        student_meta["act"] = cfg["act"]
    new_run = {"env_id": env_id, "algo": ALGO, "env_kwargs": env_kwargs, "teacher": getattr(teacher, "name", "")}
    new_run.update({"config": cfg, "student": student_meta})
    rows = _read_log(out / LOG) if run is not None else []
    if run is not None:
        differ = [key for key in ("env_kwargs", "student") if yaml.safe_load(yaml.safe_dump(new_run[key])) != run[key]]
        if differ:
            raise ValueError(f"{out}: the teacher's {' and '.join(differ)} differ from the run's; cannot resume it")
        if len(rows) > cfg["iterations"]:
            raise ValueError(f"{out} holds {len(rows)} iterations already; ask for more than that")
        lost = [j for j in range(1, len(rows) + 1) if not (out / DATA / f"it_{j}.npz").is_file()
                and not (out / CHECKPOINTS / f"it_{j - 1}.safetensors").is_file()]  # fmt: skip
        if lost:
            raise ValueError(f"{out}: cannot rebuild the data of iterations {lost} (neither data nor checkpoints)")
        if "ensemble" in run:  # still valid until the chain's end replaces it
            new_run["ensemble"] = run["ensemble"]
    elif (out / DATA).is_dir() and any((out / DATA).iterdir()):
        raise ValueError(f"{out / DATA} holds another run's data; choose another --out")

    def commit(writers: dict) -> None:  # the state names the iterations done
        folder.commit(writers, {"algo": ALGO, "iterations": len(rows)})

    commit({RUN_FILE: lambda p: _write_run(p, new_run)})

    def rule_act(o, runner, costs):
        return teacher.continuation_action(runner)

    def oracle_act(o, runner, costs):
        return episodes.candidates(o)[int(np.argmin(costs))]  # the cheapest candidate (the first on ties)

    def rule_mse(trial) -> float:
        if cfg["regret_scale"] == "rule":
            return episodes.run(trial, rule_act, label_every=0).rmse ** 2
        if cfg["regret_scale"] == "teacher":
            return episodes.run(trial, oracle_act, label_every=0, needs_costs=True).rmse ** 2
        mses: list[float] = []
        n_rules = [1]
        while len(mses) < n_rules[0]:  # each of the teacher's rules alone (their number: from the first)
            r = len(mses)

            def act(o, runner, costs, r=r):
                actions = teacher.rule_actions(runner)
                n_rules[0] = len(actions)
                return actions[r]

            mses.append(episodes.run(trial, act, label_every=0).rmse ** 2)
        return min(mses)

    def collect(j: int, student: Student | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The labelled states of iteration j: the teacher's (or rule's) episodes for j = 0, else ``student``'s
        (the student of iteration j − 1; with probability β per decision the teacher) on new training trials."""
        obs_parts, regret_parts, rule_parts = [], [], []
        if j == 0:
            act, needs = (oracle_act, True) if cfg["first"] == "teacher" else (rule_act, False)
        else:
            rng = np.random.default_rng([cfg["seed"], j])

            def act(o, runner, costs, st=student):
                action = st.action(o)
                return oracle_act(o, runner, costs) if cfg["beta"] > 0 and rng.random() < cfg["beta"] else action

            needs = cfg["beta"] > 0
        for sc in cfg["scenarios"]:
            n_per = trials_per(cfg, sc)
            first = cfg["train_seed"] + n_per * j
            for s in range(first, first + n_per):
                trial = make_trial(sc, s)
                o, costs, rule, rmse = episodes.run(trial, act, cfg["label_every"], needs)
                horizon = int(round(teacher.horizon_s * trial.rate))
                if horizon < 1:
                    raise ValueError(f"the teacher's look-ahead {teacher.horizon_s} s is under one sample of {sc}")
                own = act is oracle_act and cfg["regret_scale"] == "teacher"  # this run is the teacher's own
                regret = regret_units(costs, horizon, rmse**2 if own else rule_mse(trial))
                if np.isnan(regret).any():  # every candidate's roll-out failed, or the rule's MSE is 0
                    raise ValueError(f"{sc} seed {s}: regrets are undefined at some decisions (no candidate of finite"
                                     " cost, or a rule of zero error)")  # fmt: skip
                obs_parts.append(o)
                regret_parts.append(regret)
                rule_parts.append(rule)
        obs = np.concatenate(obs_parts).astype(np.float32)
        regret = np.concatenate(regret_parts).astype(np.float32)
        rule = np.concatenate(rule_parts)
        _save_data(out / DATA / f"it_{j}.npz", obs, regret, rule)
        return obs, regret, rule

    log(f"rule on validation: {_fmt(validation.rule)}")
    best = float(rows[-1]["best"]) if rows else None
    data_x: list[np.ndarray] = []
    data_r: list[np.ndarray] = []
    data_rule: list[np.ndarray | None] = []
    student = None
    for it in range(len(rows), cfg["iterations"]):
        for j in range(len(data_x), it + 1):  # the data of iterations 0..it: kept, or collected now
            t = time.time()
            path = out / DATA / f"it_{j}.npz"
            if path.is_file():
                obs, regret, rule = _load_data(path, n_cands, n_obs)
            else:  # the student of iteration j − 1: the one just fitted, or (resuming) its checkpoint
                previous = student if student is not None and j == it else None
                if j > 0 and previous is None:
                    previous = Student.load(out / CHECKPOINTS / f"it_{j - 1}.safetensors", student_meta, inputs)
                obs, regret, rule = collect(j, previous)
                log(f"   iteration {j} data: {len(obs)} labelled states, {time.time() - t:.0f} s")
            data_x.append(inputs(obs, meta))
            data_r.append(regret)
            data_rule.append(rule)
        t = time.time()
        x, r = np.concatenate(data_x), np.concatenate(data_r)
        student = fit(x, r, cfg, cfg["seed"] + it, cands, inputs, meta, _joined(data_rule))
        t_fit = time.time() - t
        rmse, ratio, score = validation.score(student)
        info = {"iteration": it, "val_ratio": score, "samples": len(x)}
        student.save(out / CHECKPOINTS / f"it_{it}.safetensors", info)  # write-once, atomic; the log names it
        writers = {}
        if best is None or score < best:
            best = score
            writers[BEST] = lambda p, st=student, i=info: st.save(p, i)
        rows.append(_log_row(it, len(x), t_fit, score, best, rmse, ratio))
        commit({**writers, LOG: lambda p: _write_log(p, rows)})  # best and log: one transaction
        log(f"iteration {it}: {len(x)} samples, fit {t_fit:.0f} s, val ratio {score:.3f} {_fmt(ratio)}")
    if cfg["ensemble"] > 1:
        _add_ensemble(out, folder, teacher, cfg["ensemble"], log, validation)
    elif "ensemble" in new_run:  # resumed with ``ensemble: 1``: the student is the best iteration again
        del new_run["ensemble"]
        commit({RUN_FILE: lambda p: _write_run(p, new_run)})
    return out


def refit(source: str | Path, out: str | Path, teacher, changes: dict, log: Callable[[str], None] = print) -> Path:
    """A fresh student fitted on all the labelled data of the DAgger run ``source`` (its ``data/it_N.npz``) with
    the fit keys ``changes`` (``REFIT_KEYS``) replacing the run's, scored on the run's validation trials; written
    as the new run folder ``out`` (run.yaml with ``refit_of``, best.safetensors, iterations.csv of one row);
    returns ``out``. ValueError if ``source`` is not a run of ``teacher`` (its env, and its student's input
    constants: the same tuned rules) or a key may not change."""
    source, out = Path(source), Path(out)
    run = _resumed_run(source, teacher, check_teacher(teacher), None, "refit")
    bad = sorted(set(changes) - set(REFIT_KEYS))
    if bad:
        raise ValueError(f"a refit may change only {list(REFIT_KEYS)}, not {bad}")
    if (out / RUN_FILE).exists():
        raise ValueError(f"{out} already holds a run; choose another --out")
    cfg = check_config({**run["config"], **changes, "ensemble": 1})
    rows = _read_log(source / LOG)
    files = [source / DATA / f"it_{j}.npz" for j in range(len(rows))]
    if not rows or not all(f.is_file() for f in files):
        raise ValueError(f"{source}: a refit needs the labelled data of every iteration in {source / DATA}")
    inputs = inputs_for(run["env_id"])
    meta = {k: v for k, v in run["student"].items() if k not in _SHAPE_KEYS}
    if yaml.safe_load(yaml.safe_dump(inputs.meta(teacher))) != meta:
        raise ValueError(f"{source}: the teacher's student constants {inputs.meta(teacher)} differ from the run's "
                         f"{meta} (its rules were re-tuned since?); cannot refit it")  # fmt: skip
    cands = np.asarray(run["student"]["candidates"], np.float64)
    n_cands = len(cands) + state_candidate_count(inputs, meta)
    episodes = teacher_episodes(run["env_id"], run["env_kwargs"], teacher, inputs, meta, cands)
    validation = Validation(episodes, teacher, cfg)
    n_obs = episodes.env(validation.trials[0][1]).observation_space.shape[0]
    parts = [_load_data(f, n_cands, n_obs) for f in files]
    x = inputs(np.concatenate([o for o, _, _ in parts]), meta)
    r = np.concatenate([g for _, g, _ in parts])
    t = time.time()
    student = fit(x, r, cfg, cfg["seed"], cands, inputs, meta, _joined([rule for _, _, rule in parts]))
    t_fit = time.time() - t
    rmse, ratio, score = validation.score(student)
    new_run = {**run, "config": cfg, "student": {**run["student"], "hidden": [int(h) for h in cfg["hidden"]]}}
    new_run.pop("ensemble", None)
    new_run["refit_of"] = {"run": str(source), "iterations": len(rows), "samples": int(len(x))}
    info = {"iteration": len(rows), "val_ratio": score, "samples": len(x)}
    log_rows = [_log_row(len(rows), len(x), t_fit, score, score, rmse, ratio)]
    folder = RunFolder(out)
    with folder.locked():
        folder.recover()
        if (out / RUN_FILE).exists():
            raise ValueError(f"{out} already holds a run; choose another --out")
        folder.commit(
            {RUN_FILE: lambda p: _write_run(p, new_run), BEST: lambda p: student.save(p, info),
             LOG: lambda p: _write_log(p, log_rows)},
            {"algo": ALGO, "iterations": 1},
        )  # fmt: skip
    log(f"refit of {source} ({len(x)} samples): fit {t_fit:.0f} s, val ratio {score:.3f} {_fmt(ratio)}")
    return out


def combine(
    sources: list, out: str | Path, teacher, changes: dict, disagree: float | None = None,
    log: Callable[[str], None] = print,
) -> Path:  # fmt: skip
    """One student from several finished DAgger runs of ``teacher`` (different worlds, seeds or teacher
    settings): the ensemble (:class:`Ensemble`) of each run's own student (its ensemble's members, else its best
    iteration), written as the run folder ``out`` (members copied into ``checkpoints/``; run.yaml the first
    run's with ``ensemble.combined_of`` naming the runs). ``disagree`` replaces the guard's ``disagree``; it is
    scored on the validation trials of the first run's config with ``changes`` (``val_seeds``,
    ``val_scenarios``, ``scenarios``) — choose seeds no member was selected on. ValueError before anything is
    written if a source is not a run of ``teacher`` or the runs' envs or students (shape, candidates, input
    constants, guard) differ."""
    out = Path(out)
    if len(sources) < 2:
        raise ValueError(f"combining needs at least 2 runs, got {len(sources)}")
    if (out / RUN_FILE).exists():
        raise ValueError(f"{out} already holds a run; choose another --out")
    bad = sorted(set(changes) - {"val_seeds", "val_scenarios", "scenarios"})
    if bad:
        raise ValueError(f"combining may change only the validation keys, not {bad}")
    runs = [_resumed_run(Path(s), teacher, check_teacher(teacher), None, "combine") for s in sources]
    for source, run in zip(sources[1:], runs[1:]):
        for key in ("env_id", "env_kwargs", "student"):
            if run[key] != runs[0][key]:
                raise ValueError(f"{source}'s {key} differs from {sources[0]}'s: cannot combine their students")
    run = dict(runs[0])
    guard = run["student"].get("guard")
    if disagree is not None:
        if guard is None or not _is_number(disagree) or not 0 <= disagree:
            raise ValueError(f"disagree must be a number ≥ 0 for a guarded student, got {disagree!r}")
        guard = {**guard, "disagree": float(disagree)}
        run["student"] = {**run["student"], "guard": guard}
    cfg = check_config({**run["config"], **changes, "guard": guard, "ensemble": 1})
    copies = {}  # name in the new run → file of a source run
    for i, source in enumerate(map(Path, sources)):
        members = (runs[i].get("ensemble") or {}).get("members") or [BEST]
        for m in members:
            copies[f"{CHECKPOINTS}/run{i}_{Path(m).name}"] = _member(source, m, source / RUN_FILE)
    inputs = inputs_for(run["env_id"])
    ensemble = Ensemble([Student.load(f, run["student"], inputs) for f in copies.values()])
    validation = Validation(Episodes(run["env_id"], run["env_kwargs"], teacher), teacher, cfg)
    _, ratio, score = validation.score(ensemble)
    run["config"] = cfg
    combined = [str(Path(s).resolve()) for s in sources]
    run["ensemble"] = {"members": list(copies), "combined_of": combined, "val_ratio": score,
                       **{f"{sc}_ratio": v for sc, v in ratio.items()}}  # fmt: skip
    run.pop("refit_of", None)
    folder = RunFolder(out)
    with folder.locked():
        folder.recover()
        if (out / RUN_FILE).exists():
            raise ValueError(f"{out} already holds a run; choose another --out")
        writers = {name: (lambda p, f=f: p.write_bytes(f.read_bytes())) for name, f in copies.items()}
        folder.commit({**writers, RUN_FILE: lambda p: _write_run(p, run)}, {"algo": ALGO, "iterations": 0})
    log(f"ensemble of {len(copies)} students from {len(sources)} runs: val ratio {score:.3f} {_fmt(ratio)}")
    return out


class Validation:
    """Closed-loop scores on the validation trials (seeds ``val_seeds`` of every scenario): per scenario the
    ratio of the mean RMSE to the continuation rule's, and their mean over scenarios (the score; lower is better)."""

    def __init__(self, episodes: Episodes, teacher, cfg: dict):
        self.episodes, self.scenarios = episodes, list(cfg["val_scenarios"] or cfg["scenarios"])
        seeds = range(*cfg["val_seeds"])
        self.trials = [(sc, make_trial(sc, s)) for sc in self.scenarios
                       for s in (seeds[:1] if sc.startswith(RECORDING) else seeds)]  # fmt: skip
        rule = self.rmse(lambda o, runner, costs: teacher.continuation_action(runner))
        self.rule = {sc: float(np.mean(v)) for sc, v in rule.items()}

    def rmse(self, act) -> dict[str, list[float]]:
        """Per-scenario RMSEs (°) of ``act(obs, runner, costs)`` on the validation trials."""
        out: dict[str, list[float]] = {sc: [] for sc in self.scenarios}
        for sc, trial in self.trials:
            out[sc].append(self.episodes.run(trial, act, label_every=0).rmse)
        return out

    def score(self, student: Student) -> tuple[dict[str, list[float]], dict[str, float], float]:
        """(per-scenario RMSEs °, per-scenario ratios to the rule, score) of ``student``."""
        rmse = self.rmse(lambda o, runner, costs: student.action(o))
        ratio = {sc: float(np.mean(v) / self.rule[sc]) for sc, v in rmse.items()}
        return rmse, ratio, float(np.mean(list(ratio.values())))


def add_ensemble(
    run_dir: str | Path, teacher, k: int, log: Callable[[str], None] = print, validation: Validation | None = None
) -> dict:
    """Make the student of the run in ``run_dir`` the ensemble of its ``k`` iterations of lowest validation
    score (step 4 of the module docstring): scores it on the run's validation trials and writes its members,
    score and ``config.ensemble = k`` into run.yaml; returns that ``ensemble`` entry."""
    folder = RunFolder(Path(run_dir))
    with folder.locked():
        folder.recover()
        return _add_ensemble(Path(run_dir), folder, teacher, k, log, validation)


def _add_ensemble(run_dir: Path, folder: RunFolder, teacher, k: int, log, validation: Validation | None) -> dict:
    """:func:`add_ensemble` in the locked, recovered run folder ``folder``."""
    run = yaml.safe_load((run_dir / RUN_FILE).read_text())
    check_teacher(teacher, run["env_id"])
    if getattr(teacher, "name", "") != run["teacher"]:
        raise ValueError(f"{run_dir} was taught by {run['teacher']!r}, not {getattr(teacher, 'name', teacher)!r}")
    rows = _read_log(run_dir / LOG)
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= len(rows):
        raise ValueError(f"ensemble of {k} iterations, but {run_dir} has {len(rows)}")
    chosen = sorted(rows, key=lambda row: float(row["score"]))[:k]
    members = [f"{CHECKPOINTS}/it_{row['iteration']}.safetensors" for row in chosen]
    inputs = inputs_for(run["env_id"])
    ensemble = Ensemble([Student.load(run_dir / m, run["student"], inputs) for m in members])
    if validation is None:
        validation = Validation(Episodes(run["env_id"], run["env_kwargs"], teacher), teacher, run["config"])
    _, ratio, score = validation.score(ensemble)
    run["config"]["ensemble"] = int(k)
    run["ensemble"] = {"members": members, "val_ratio": score, **{f"{sc}_ratio": v for sc, v in ratio.items()}}
    folder.commit({RUN_FILE: lambda p: _write_run(p, run)}, {"algo": ALGO, "iterations": len(rows)})
    log(f"ensemble of iterations {[int(row['iteration']) for row in chosen]}: val ratio {score:.3f} {_fmt(ratio)}")
    return run["ensemble"]


def _resumed_run(out: Path, teacher, env_id: str, config: dict | None, purpose: str = "resume") -> dict:
    """run.yaml of the run in ``out``, its config's ``iterations`` replaced by ``config``'s; ValueError (naming
    ``purpose``) if it is not a DAgger run of this teacher and env, or if ``config`` changes any other key."""
    path = out / RUN_FILE
    if not is_run(out):
        raise ValueError(f"{out} holds no DAgger run to {purpose} (no {RUN_FILE} of algo {ALGO!r})")
    run = yaml.safe_load(path.read_text())
    name = getattr(teacher, "name", "")
    if run.get("env_id") != env_id or run.get("teacher") != name:
        raise ValueError(
            f"{out} is a run of {run.get('teacher')!r} in {run.get('env_id')}, not of {name!r} in {env_id}"
        )
    stored = check_config(run["config"])
    merged = check_config({**stored, **(config or {})})
    refused = sorted(key for key in merged if key not in RESUMABLE and merged[key] != stored[key])
    if refused:
        raise ValueError(f"a resumed run keeps its config; {refused} differ from {path}'s")
    run["config"] = merged
    return run


def _write_run(path: Path, run: dict) -> None:
    """run.yaml at ``path`` (a :meth:`RunFolder.commit` writer: the commit makes it whole)."""
    path.write_text(yaml.safe_dump(run, sort_keys=False))


def _save_data(path: Path, obs: np.ndarray, regret: np.ndarray, rule: np.ndarray) -> None:
    """``obs``, ``regret`` and ``rule`` into ``path`` (.npz; written whole, then renamed: an interrupted run leaves
    none)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, obs=obs, regret=regret, rule=rule.astype(np.int16))
    tmp.replace(path)


def _joined(rules: list[np.ndarray | None]) -> np.ndarray | None:
    """The rule candidates of several data files end to end (None if any file has none)."""
    present = [r for r in rules if r is not None]
    return np.concatenate(present) if len(present) == len(rules) else None


def _load_data(path: Path, n_candidates: int, n_obs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(obs (D, n_obs) float32, regret (D, C + S) float32 in % of the trial's rule MSE, rule (D,) int16 or None in
    data from before it) of a data file; RunError if it is not one of this run's."""
    try:
        with np.load(path, allow_pickle=False) as z:
            obs, regret = z["obs"], z["regret"]
            rule = z["rule"] if "rule" in z.files else None
    except Exception as exc:  # zip, npy or key errors alike: not one of ours
        raise RunError(f"{path}: not a DAgger data file ({type(exc).__name__}: {exc})") from None
    if obs.ndim != 2 or obs.shape[1] != n_obs or regret.shape != (len(obs), n_candidates):
        raise RunError(
            f"{path}: obs {obs.shape} and regret {regret.shape} do not fit {n_obs} observations and "
            f"{n_candidates} candidates"
        )
    if obs.dtype != np.float32 or regret.dtype != np.float32 or np.isnan(regret).any() or (regret < 0).any():
        raise RunError(f"{path}: obs and regret must be float32, the regrets ≥ 0 (inf: a failed roll-out), no NaN")
    if rule is not None and (rule.shape != (len(obs),) or rule.dtype != np.int16 or rule.min(initial=0) < -1
                             or rule.max(initial=0) >= n_candidates):  # fmt: skip
        raise RunError(f"{path}: rule must be (D,) int16 candidate indices in [-1, {n_candidates}), got {rule.shape} "
                       f"{rule.dtype}")  # fmt: skip
    return obs, regret, rule


def _log_row(it: int, samples: int, t_fit: float, score: float, best: float, rmse: dict, ratio: dict) -> dict:
    """One row of iterations.csv: the fit's size and time, its validation score, the best so far, and per
    scenario the mean RMSE (°) and the ratio to the rule."""
    row = {"iteration": it, "samples": samples, "fit_s": round(t_fit, 1), "score": score, "best": best}
    row.update({f"{sc}_rmse": float(np.mean(v)) for sc, v in rmse.items()})
    row.update({f"{sc}_ratio": v for sc, v in ratio.items()})
    return row


def _read_log(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _fmt(d: dict) -> str:
    return " ".join(f"{k}={v:.3f}" for k, v in d.items())


def _write_log(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


# ----------------------------------------------------------------- loading


def is_run(run_dir: Path) -> bool:
    """True if ``run_dir`` holds a DAgger run (its run.yaml says algo: dagger)."""
    path = Path(run_dir) / RUN_FILE
    if not path.is_file():
        return False
    try:
        run = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError):
        return False
    return isinstance(run, dict) and run.get("algo") == ALGO


def load_policy(run_dir: str | Path, name: str | None = None) -> StudentPolicy:
    """The student of a DAgger run folder as a Policy: its ensemble if run.yaml names one, else the best
    iteration (arrays only; RunError if the folder is corrupt)."""
    run_dir = Path(run_dir)
    path = run_dir / RUN_FILE
    try:
        run = yaml.safe_load(path.read_text())
        student_meta, env_kwargs, env_id = run["student"], dict(run["env_kwargs"]), str(run["env_id"])
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise RunError(f"{path}: not a DAgger run ({type(exc).__name__}: {exc})") from None
    try:
        inputs = inputs_for(env_id)
    except ValueError as exc:
        raise RunError(f"{path}: {exc}") from None
    ensemble = run.get("ensemble")
    members = ensemble.get("members") if isinstance(ensemble, dict) else None
    if ensemble is not None and (not isinstance(members, list) or not members):
        raise RunError(f"{path}: 'ensemble' must hold a non-empty list 'members', got {ensemble!r}")
    files = [run_dir / BEST] if members is None else [_member(run_dir, m, path) for m in members]
    students = [Student.load(f, student_meta, inputs) for f in files]
    student = students[0] if members is None else Ensemble(students)
    source = str(files[0]) if members is None else f"ensemble of {', '.join(str(f) for f in files)}"
    return StudentPolicy(student, name or f"agent:{run_dir.name}", env_kwargs, source, env_id)


def _member(run_dir: Path, member, where: Path) -> Path:
    """The file of an ensemble member named in run.yaml (``best.safetensors`` or inside ``run_dir/checkpoints``,
    else RunError)."""
    if member == BEST:
        return run_dir / BEST
    if not isinstance(member, str) or not member.startswith(f"{CHECKPOINTS}/") or ".." in member:
        raise RunError(f"{where}: ensemble member {member!r} is not {BEST} or a file in {CHECKPOINTS}/")
    return run_dir / member
