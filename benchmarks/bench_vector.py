"""Env-steps per second of every env's batched vector env against its bare kernel and CartPole's vector env; the
kernels' cost per sample; each oracle's decisions per second.

    .venv/bin/python benchmarks/bench_vector.py [--envs 1,16,256,1024] [--every 8] [--ids blend,kalman,…]
                                                [--oracle-seconds 10] [--parallel] [--checkout DIR]

For each env and N: the env's ``vector_entry_point`` (``gymnasium.make_vec(…, vectorization_mode=
"vector_entry_point")``, so an env picks up whatever batch implementation it registers) on one pre-made
trial (:func:`bench_trial`: a 60-s ``dynamic_magnet`` trial, a 75-s ``constraint_test1`` one for
MagConstraint), stepped with a fixed action within its first episode (about 60 k env-steps per timing;
``step`` as a policy calls it: action checks, rewards, ``infos``); the **bare kernel limit**: the same
compiled batch kernel on the same arrays and samples, called in a loop with nothing around it (no env, no
checks, no rewards or infos; an env whose vector env has no compiled kernel runs its ``_run``), also given
as ns per fused sample; and ``CartPole-v1``'s own vector env at the same N. Ratios are of rates measured in
this run, interleaved; each rate is the best of 3, per wall second and per CPU second of the process (the
rate one free core gives: robust on a shared machine; ratios are of those). Targets (issue 49): vector env
≥ 150 k env-steps/s at N = 256 and ≥ 0.6 of the kernel limit. ``--parallel`` measures the threaded
kernel (``prange`` over the envs, the env's ``parallel=True``) instead of the default serial one.
``--checkout DIR`` times the checkout in DIR (``benchmarks/checkout.py``; e.g. ``git archive`` of the commit
before a change) instead of this code: alternate runs with and without it to compare.

Then each env's oracle (``oracle``, ``oracle_kalman``, ``oracle_constraint``, ``oracle_qsf``,
``oracle_vqf``: a receding-horizon search at every decision) on the first ``--oracle-seconds`` of the
env's trial: decisions per second (wall and CPU; best of 2 after a warm-up).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

IDS = {
    "blend": "magenv/MagBlend-v0",
    "kalman": "magenv/MagKalman-v0",
    "constraint": "magenv/MagConstraint-v0",
    "qsf": "magenv/MagQSF-v0",
    "vqf": "magenv/MagVQF-v0",
}
ORACLES = {
    "blend": "oracle",
    "kalman": "oracle_kalman",
    "constraint": "oracle_constraint",
    "qsf": "oracle_qsf",
    "vqf": "oracle_vqf",
}
TARGET_ENV_STEPS = 60_000  # env-steps per timing
_TRIALS: dict = {}


def bench_trial(env_id: str):
    """The benchmark trial of an env: ``constraint_test1`` seed 0 (two-link) for MagConstraint, else
    ``dynamic_magnet`` seed 0 (made once per process)."""
    from magenv.scenarios import make_trial

    name = "constraint_test1" if "Constraint" in env_id else "dynamic_magnet"
    if name not in _TRIALS:
        _TRIALS[name] = make_trial(name, 0)
    return _TRIALS[name]


class Clock:
    """Wall and CPU seconds (this process) of the timed parts of a loop."""

    def __init__(self):
        self.wall = self.cpu = 0.0

    def __enter__(self):
        self._w, self._c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall += time.perf_counter() - self._w
        self.cpu += time.process_time() - self._c


def best_rates(*runs, repeats: int = 3) -> list[tuple[float, float]]:
    """Best (per wall second, per CPU second) env-steps of each ``run()`` → (env-steps, Clock) over ``repeats``,
    the runs interleaved (so that a load on the machine meets them alike); after one warm-up run each (kernels
    compiled, first-call checks). The CPU-second rate is what one free core gives: robust on a shared machine."""
    rates: list[list[tuple[float, float]]] = [[] for _ in runs]
    for repeat in range(repeats + 1):
        for run, got in zip(runs, rates):
            steps, clock = run()
            if repeat:
                got.append((steps / clock.wall, steps / max(clock.cpu, 1e-9)))
    return [(max(w for w, _ in r), max(c for _, c in r)) for r in rates]


def magenv_rates(env_id: str, trial, num_envs: int, k: int, parallel: bool):
    """((vector env, bare kernel) (per wall second, per CPU second) env-steps of ``num_envs`` envs of ``env_id``
    on ``trial``, whether the kernel is a compiled batch kernel)."""
    vec = gym.make_vec(
        env_id,
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        scenario=[trial],
        decision_every=k,
        parallel=parallel,
    )
    venv = vec.unwrapped
    dim = venv.single_action_space.shape[0]
    actions = np.full((num_envs, dim), 0.5, np.float32)
    first = getattr(venv, "first", 1)
    steps = min((trial.n - first) // k - 2, -(-TARGET_ENV_STEPS // num_envs))  # within one episode
    rounds = -(-TARGET_ENV_STEPS // (num_envs * steps))

    def env_loop():
        clock = Clock()
        for _ in range(rounds):
            vec.reset(seed=0)
            with clock:
                for _ in range(steps):
                    vec.step(actions)
        return rounds * steps * num_envs, clock

    def kernel_loop():
        clock = Clock()
        stepping = np.ones(num_envs, bool)
        for _ in range(rounds):
            vec.reset(seed=0)  # made the kernel's argument tuple and compiled entry point
            venv._set_actions(actions.astype(np.float64), stepping)
            todo, entry, args = venv.todo, getattr(venv, "_entry", None), getattr(venv, "_args", None)
            with clock:
                for _ in range(steps):
                    todo[:] = k
                    if entry is not None:
                        entry(*args)
                    else:
                        venv._run()
        return rounds * steps * num_envs, clock

    rates = best_rates(env_loop, kernel_loop)
    compiled = getattr(venv, "_entry", None) is not None
    vec.close()
    return rates, compiled


def cartpole_rate(num_envs: int, steps: int) -> tuple[float, float]:
    """(per wall second, per CPU second) env-steps of ``gymnasium.make_vec("CartPole-v1", num_envs)`` (its
    vector_entry_point), alternating pushes."""
    vec = gym.make_vec("CartPole-v1", num_envs=num_envs, vectorization_mode="vector_entry_point")
    pushes = [np.zeros(num_envs, np.int64), np.ones(num_envs, np.int64)]
    rounds = max(1, -(-TARGET_ENV_STEPS // (num_envs * steps)))

    def loop():
        vec.reset(seed=0)
        with Clock() as clock:
            for i in range(rounds * steps):
                vec.step(pushes[i % 2])
        return rounds * steps * num_envs, clock

    (rate,) = best_rates(loop)
    vec.close()
    return rate


def oracle_rate(name: str, trial, seconds: float) -> tuple[float, float, int]:
    """(decisions per wall second, per CPU second, decisions) of the oracle ``name`` over the first ``seconds``
    of ``trial`` (best of 2 after a warm-up run)."""
    from magenv import registry

    cut = trial.slice(0, min(trial.n, int(round(seconds * trial.rate))))
    oracle = registry.make(name)
    k = int(getattr(oracle, "decision_every", getattr(oracle, "k", 1)))
    decisions = -(-(cut.n - 1) // k)
    oracle.run(cut)  # warm-up: compiled kernels
    wall = cpu = float("inf")
    for _ in range(2):
        with Clock() as clock:
            oracle.run(cut)
        wall, cpu = min(wall, clock.wall), min(cpu, clock.cpu)
    return decisions / wall, decisions / max(cpu, 1e-9), decisions


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", default="1,16,256,1024", help="comma-separated N")
    p.add_argument("--every", type=int, default=8, help="decision interval k (samples per step)")
    p.add_argument("--ids", default=",".join(IDS), help=f"envs among {', '.join(IDS)}")
    p.add_argument("--oracle-seconds", type=float, default=10.0, help="trial seconds each oracle runs (0: none)")
    p.add_argument("--parallel", action="store_true", help="the threaded kernels (numba prange over the envs)")
    p.add_argument("--checkout", default=None, help="time the checkout in this folder instead of this code")
    args = p.parse_args()
    if args.checkout:
        import checkout

        checkout.use(args.checkout)
    import magenv  # noqa: F401  (registers the envs)

    sizes = [int(n) for n in args.envs.split(",")]
    names = args.ids.split(",")
    unknown = [n for n in names if n not in IDS]
    if unknown:
        p.error(f"unknown --ids {unknown}; choose among {', '.join(IDS)}")

    import numba

    threads = f"threaded kernel, {numba.get_num_threads()} numba threads" if args.parallel else "serial kernel"
    print(f"k = {args.every}, {threads}; trials: 60-s dynamic_magnet (MagConstraint: 75-s constraint_test1)")
    print("env-steps per wall second (per CPU second of this process in brackets: what one free core gives)")
    head = ("vector env", "kernel limit", "ratio", "ns/sample", "CartPole vec", "ratio")
    widths = (20, 20, 6, 10, 22, 6)
    print(f"{'env':17s} {'N':>5s} " + " ".join(f"{h:>{w}s}" for h, w in zip(head, widths)))
    cart: dict[int, tuple[float, float]] = {}
    both = lambda r: f"{r[0] / 1e3:8.1f} k ({r[1] / 1e3:7.1f} k)"
    for name in names:
        env_id = IDS[name]
        trial = bench_trial(env_id)
        for n in sizes:
            (vec_rate, limit), compiled = magenv_rates(env_id, trial, n, args.every, args.parallel)
            if n not in cart:
                cart[n] = cartpole_rate(n, min(15360 // args.every - 2, -(-TARGET_ENV_STEPS // n)))
            ns = 1e9 / (limit[1] * args.every)
            mark = "" if compiled else " (_run)"
            print(
                f"{env_id.split('/')[-1]:17s} {n:5d} {both(vec_rate)} {both(limit)} {vec_rate[1] / limit[1]:6.2f} "
                f"{ns:10.0f} {both(cart[n])} {vec_rate[1] / cart[n][1]:6.2f}{mark}"
            )
    print(
        "ratios of CPU-second rates: vector env / kernel limit (targets: vector env >= 150 k env-steps/s at N = 256 "
        "and >= 0.6 of the limit), vector env / CartPole; ns/sample: CPU ns of the kernel limit per fused sample; "
        "(_run): no compiled batch kernel, the limit is the vector env's own _run loop"
    )
    if args.oracle_seconds > 0:
        print(f"\noracles on the first {args.oracle_seconds:g} s of each env's trial (best of 2)")
        print(f"{'oracle':18s} {'decisions':>9s} {'per wall s':>11s} {'per CPU s':>10s}")
        for name in names:
            wall, cpu, decisions = oracle_rate(ORACLES[name], bench_trial(IDS[name]), args.oracle_seconds)
            print(f"{ORACLES[name]:18s} {decisions:9d} {wall:11.0f} {cpu:10.0f}")


if __name__ == "__main__":
    main()
