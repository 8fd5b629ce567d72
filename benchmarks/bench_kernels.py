"""Per-sample cost (ns) of the filter kernels and of the batched envs' kernels, optionally beside an older checkout.

    .venv/bin/python benchmarks/bench_kernels.py [--baseline DIR] [--rounds 2] [--envs 256]

Each kernel runs over one 60-s ``dynamic_magnet`` trial (256 Hz, 15 360 samples) as its callers run it: the
trust KF of ``MagKalman-v0`` (``kalman_trust.run_k_kernel``, γ = 0.5), the Gauss–Markov split of its
``model_dist`` feature (computed at each reset), the survey's threshold (QUEST) and model-based (TRIAD)
filters, the QSF detector (at each ``MagQSF-v0`` reset) and the three QSF filters (``qsf.run_kernel`` on the
detector's codes, trust 1); then the bare batch kernel of each env's ``vector_entry_point`` (N envs,
``decision_every`` 8, a fixed action, within one episode, on bench_vector.py's trial of the env: its kernel
limit) per fused sample; and each oracle (``bench_vector.oracle_rate``, 5 s of the env's trial) per sample, with
``oracle_vqf`` also at a 2-s look-ahead (the C++ oracle's of 3026d33; today's looks 4 s ahead).
Each figure is the best of 5 timings after a warm-up, in CPU time of the process (what one free core gives:
robust on a shared machine).

``--baseline DIR``: the same measurements on the checkout in DIR (e.g. the commit before a change:
``git -C REPO archive 3026d33 | tar -x -C DIR``), imported in a subprocess (``benchmarks/checkout.py``);
the current code runs in a subprocess too, the two alternate ``--rounds`` times and each figure is the best
of its rounds; the table gives both and the speed-up. Kernels a checkout lacks show "–".
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPEATS = 5
ENV_IDS = ("MagBlend-v0", "MagKalman-v0", "MagConstraint-v0", "MagQSF-v0", "MagVQF-v0")


def best_ns(run, samples: int) -> float:
    """Best CPU ns (this process) per sample of ``run()`` over REPEATS timings after one warm-up call."""
    run()
    best = float("inf")
    for _ in range(REPEATS):
        t0 = time.process_time()
        run()
        best = min(best, time.process_time() - t0)
    return best / samples * 1e9


def filter_kernels(trial) -> dict[str, float]:
    """ns per sample of each filter kernel on ``trial``."""
    import numpy as np

    from magenv.envs import kalman as ek
    from magenv.filters import kalman_model, kalman_threshold, qsf
    from magenv.filters import kalman_trust as kt
    from magenv.filters.sensors import Sensors

    n, sensors = trial.n, Sensors.of(trial)
    out: dict[str, float] = {}
    params = kt.make_params(trial.field_norm, trial.field_dip, trial.dt)
    q_out, sig = np.empty((n, 4)), np.empty((n, kt.NSIG))

    def trust_kf():
        kt.run_k_kernel(params, kt.init(params, trial.acc[0], trial.mag[0]), sensors, 1, n, 0.5, q_out, sig)

    out["trust KF (MagKalman)"] = best_ns(trust_kf, n)
    vp = ek.make_model_params(params)
    mdist = np.empty(n)
    out["model split (model_dist, reset)"] = best_ns(lambda: ek.model_disturbance(vp, sensors, mdist), n)
    out["threshold KF, QUEST (th_quest)"] = best_ns(lambda: kalman_threshold.ThresholdKF("quest").run(trial), n)
    out["model KF, TRIAD (mod_triad)"] = best_ns(lambda: kalman_model.ModelKF("triad").run(trial), n)
    det = qsf.QSFDetector()
    out["QSF detector (MagQSF reset)"] = best_ns(lambda: det.detect(trial.gyr, trial.mag, trial.rate), n)
    codes, _ = det.detect(trial.gyr, trial.mag, trial.rate)
    inputs = qsf.Inputs(trial.gyr, trial.acc, trial.mag, codes, np.ones(n))
    res = qsf.Outputs.empty(n)
    for mode in qsf.MODES:
        qp = qsf.make_params(trial.field_norm, trial.field_dip, mode=mode)

        def run(qp=qp):
            qsf.run_kernel(qp, qsf.initial_state(trial.q_true[0], trial.dt), inputs, trial.dt, 0, n, res)

        out[f"QSF {mode}"] = best_ns(run, n)
    return out


def env_kernels(num_envs: int, k: int = 8) -> dict[str, float]:
    """ns per fused sample of each env's bare batch kernel (``num_envs`` envs, k samples per step) on its
    benchmark trial (``bench_vector.bench_trial``)."""
    import gymnasium as gym
    from bench_vector import bench_trial

    out: dict[str, float] = {}
    for env_id in ENV_IDS:
        full = f"magenv/{env_id}"
        if full not in gym.registry:
            continue
        trial = bench_trial(full)
        vec = gym.make_vec(full, num_envs=num_envs, vectorization_mode="vector_entry_point", scenario=[trial],
                           decision_every=k)  # fmt: skip
        venv = vec.unwrapped  # a vector env with a compiled batch kernel (not 3026d33's VQF on C++ objects):
        if _batched(venv):
            out[f"{env_id} batch kernel, N={num_envs}"] = _batch_kernel_ns(vec, trial, num_envs, k)
        vec.close()
    return out


def _batched(venv) -> bool:
    """``venv`` has a compiled batch kernel: ``advance_env`` run by ``batch.each_env``, a ``lockstep`` kernel, or
    (before the env template) ``kernels``."""
    return any(getattr(venv, name, None) for name in ("advance_env", "lockstep", "kernels"))


def _batch_kernel_ns(vec, trial, num_envs: int, k: int) -> float:
    """ns per fused sample of ``vec``'s bare batch kernel, a fixed action, within the first episode."""
    import numpy as np

    venv = vec.unwrapped
    actions = np.full((num_envs, venv.single_action_space.shape[0]), 0.5)
    steps = min((trial.n - venv.first) // k - 2, 240)

    def loop():
        vec.reset(seed=0)
        venv._set_actions(actions, np.ones(num_envs, bool))
        todo, run = venv.todo, venv._entry
        args = (venv._args,) if getattr(venv, "kernels", None) else venv._args  # one Batch before the env template
        for _ in range(steps):
            todo[:] = k
            run(*args)

    return best_ns(loop, steps * k * num_envs)


def oracle_kernels(seconds: float = 5.0) -> dict[str, float]:
    """CPU ns per sample of each oracle's search (``bench_vector.oracle_rate``) on the first ``seconds`` of its
    env's benchmark trial."""
    import gymnasium as gym
    from bench_vector import IDS, ORACLES, bench_trial, oracle_rate

    out: dict[str, float] = {}
    for name, env_id in IDS.items():
        if env_id in gym.registry:
            trial = bench_trial(env_id)
            _, per_cpu_s, decisions = oracle_rate(ORACLES[name], trial, seconds)
            samples = min(trial.n, int(round(seconds * trial.rate)))
            out[f"{ORACLES[name]} (its searches per sample)"] = decisions / per_cpu_s / samples * 1e9
    if "magenv/MagVQF-v0" in gym.registry:  # at the 2-s look-ahead of the C++ oracle (3026d33): same work a label
        from magenv.baselines.oracle_vqf import VQFOracle

        cut = bench_trial("magenv/MagVQF-v0")
        cut = cut.slice(0, min(cut.n, int(round(seconds * cut.rate))))
        out["oracle_vqf, 2-s look-ahead"] = best_ns(lambda: VQFOracle(horizon_s=2.0).run(cut), cut.n)
    return out


def worker(checkout: str | None, num_envs: int) -> None:
    """Print this code's (or ``checkout``'s) figures as JSON."""
    if checkout:
        import checkout as chk

        chk.use(checkout)
    import magenv  # noqa: F401  (registers the envs)
    from magenv.scenarios import make_trial

    trial = make_trial("dynamic_magnet", 0)
    print(json.dumps({**filter_kernels(trial), **env_kernels(num_envs), **oracle_kernels()}))


def measure(checkout: str | None, num_envs: int) -> dict[str, float]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--envs", str(num_envs)]
    if checkout:
        cmd += ["--checkout", checkout]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--baseline", default=None, help="an older checkout to time beside this one")
    p.add_argument("--rounds", type=int, default=2, help="alternations of baseline and current")
    p.add_argument("--envs", type=int, default=256, help="N of the batch kernels")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--checkout", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args.checkout, args.envs)
        return 0
    runs = {"now": [], "base": []}
    for _ in range(args.rounds if args.baseline else 1):
        if args.baseline:
            runs["base"].append(measure(args.baseline, args.envs))
        runs["now"].append(measure(None, args.envs))
    names = list(dict.fromkeys(k for rs in runs.values() for r in rs for k in r))  # in the workers' order
    best = {
        key: {k: min(r[k] for r in rs if k in r) for k in names if any(k in r for r in rs)}
        for key, rs in runs.items()
        if rs
    }
    now, base = best["now"], best.get("base", {})
    rounds = f" and of {args.rounds} rounds" if base else ""
    print(f"60-s dynamic_magnet trial (MagConstraint: constraint_test1); CPU ns per sample, best of 5{rounds}")
    if base:
        print(f"{'kernel':42s} {'baseline':>10s} {'now':>10s} {'speed-up':>9s}")
    for name, ns in now.items():
        if base:
            b = base.get(name)
            cells = f"{b:10.0f} {ns:10.0f} {b / ns:8.1f}×" if b else f"{'–':>10s} {ns:10.0f} {'–':>9s}"
            print(f"{name:42s} {cells}")
        else:
            print(f"{name:42s} {ns:10.0f}")
    if base:
        print(f"baseline: {args.baseline}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    raise SystemExit(main())
