"""PPO's training throughput on every env, and where its time goes: CPU seconds in env stepping, the rest of
rollout collection (policy calls, the rollout buffer, VecNormalize, callbacks) and the gradient steps.

    .venv/bin/python benchmarks/bench_training_time.py [--ids blend,kalman,constraint,qsf,vqf] [--steps 40960]
                                                       [--hyper blend|shipped]

For each env a throw-away run (``magenv.agents.training.train``, no pretraining; its one held-out evaluation,
at the end, on the first scenario of the env's mixture, is not timed)
times ``BatchVecEnv.step_wait``, ``collect_rollouts`` and ``PPO.train`` in CPU time (robust on a shared
machine) and wall time, and prints each part and the env-steps per second of the two learning phases
together (set-up and the first rollout excluded: the kernels compile there), per wall second and per
CPU-second (the rate one free core gives). ``--hyper blend`` (default) trains every env with MagBlend-v0's
shipped PPO hyperparameters (64 batched envs, 128-step rollouts, minibatch 1024, 5 epochs) and the env's own
shipped ``env_kwargs``, so the envs' costs compare, with a reset pool of 32 trials whose generations serve
``--reuse`` episodes (8; 1 simulates a fresh trial for nearly every reset, which then dominates on the
two-link and hand-held worlds: ``bench_sim.py``); ``--hyper shipped`` with each
env's own shipped section (MagVQF-v0 has none: it takes MagBlend-v0's). Target (issue 49): ≥ 10 k env-steps/s.
"""

from __future__ import annotations

import argparse
import collections
import shutil
import tempfile
import time
from pathlib import Path

import yaml
from bench_vector import IDS
from stable_baselines3 import PPO
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

import magenv  # noqa: F401
from magenv import registry
from magenv.agents import training, vec_env
from magenv.agents.hyperparams import CONFIG_DIR

RECIPE = "magenv/MagBlend-v0"  # the section --hyper blend trains every env with


def config_for(env_id: str, hyper: str, reuse: int, folder: Path) -> Path:
    """A PPO config file with a section for ``env_id``: the env's shipped section (``hyper="shipped"``) or
    MagBlend-v0's with the env's own shipped ``env_kwargs`` and a reset pool of 32 trials, each generation
    reused for ``reuse`` episodes; without pretraining."""
    shipped = yaml.safe_load((CONFIG_DIR / "ppo.yaml").read_text())
    own = dict(shipped.get(env_id, shipped[RECIPE]))
    section = own if hyper == "shipped" else dict(shipped[RECIPE])
    if hyper != "shipped":
        section["env_kwargs"] = {**own.get("env_kwargs", {}), "trial_pool": {"size": 32, "reuse": reuse}}
        if env_id not in shipped:  # no section of its own: the recipe's scenario is the env's default world
            section["env_kwargs"].pop("scenario", None)
    section.pop("pretrain", None)
    path = folder / f"ppo_{env_id.split('/')[-1]}.yaml"
    path.write_text(yaml.safe_dump({env_id: section}))
    return path


def measure(env_id: str, steps: int, hyper: str, reuse: int) -> dict[str, float]:
    """Train a throw-away PPO run on ``env_id``: CPU and wall seconds of its parts after the first rollout, and
    the env-steps they cover."""
    cpu: dict = collections.defaultdict(float)
    wall: dict = collections.defaultdict(float)
    rollouts = [0]
    originals = {}

    def timed(cls, name: str, key: str) -> None:
        f = getattr(cls, name)
        originals[(cls, name)] = f

        def g(*a, **kw):
            c, w = time.process_time(), time.perf_counter()
            try:
                return f(*a, **kw)
            finally:
                cpu[key] += time.process_time() - c
                wall[key] += time.perf_counter() - w
                if key == "collect":
                    rollouts[0] += 1
                    if rollouts[0] == 1:  # the first rollout compiles the kernels: not counted
                        cpu.clear()
                        wall.clear()

        setattr(cls, name, g)

    timed(vec_env.BatchVecEnv, "step_wait", "env")
    timed(OnPolicyAlgorithm, "collect_rollouts", "collect")
    timed(PPO, "train", "grad")
    out = Path(tempfile.mkdtemp(prefix="bench_training_time_"))
    try:
        config = config_for(env_id, hyper, reuse, out)
        section = yaml.safe_load(config.read_text())[env_id]
        scenario = str(section["env_kwargs"].get("scenario", "dynamic_magnet")).split(",")[0]
        training.train(env_id, "ppo", steps, out / "run", config=str(config), eval_every=10**12,
                       progress_bar=False, make_method=registry.make, eval_scenarios=[scenario],
                       eval_seeds=[5000])  # fmt: skip
    finally:
        for (cls, name), f in originals.items():
            setattr(cls, name, f)
        shutil.rmtree(out, ignore_errors=True)
    counted = (rollouts[0] - 1) * section["n_envs"] * section["n_steps"]
    return {"cpu_env": cpu["env"], "cpu_collect": cpu["collect"], "cpu_grad": cpu["grad"],
            "wall": wall["collect"] + wall["grad"], "steps": counted}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ids", default=",".join(IDS), help=f"envs among {', '.join(IDS)}")
    p.add_argument("--steps", type=int, default=40_960, help="env-steps of each run (whole rollouts)")
    p.add_argument("--hyper", choices=("blend", "shipped"), default="blend", help="hyperparameters (see above)")
    p.add_argument("--reuse", type=int, default=8, help="with --hyper blend: episodes per reset-pool generation")
    args = p.parse_args()
    pool = f", reset pool of 32 trials reused for {args.reuse} episodes" if args.hyper == "blend" else ""
    print(f"PPO, {args.steps} env-steps per env, hyperparameters: {args.hyper}{pool} (first rollout not counted)")
    print(f"{'env':17s} {'env CPU s':>9s} {'rest':>6s} {'grad':>6s} {'per wall s':>11s} {'per CPU s':>10s}")
    for name in args.ids.split(","):
        env_id = IDS[name]
        r = measure(env_id, args.steps, args.hyper, args.reuse)
        learn, counted = r["cpu_collect"] + r["cpu_grad"], r["steps"]
        print(
            f"{env_id.split('/')[-1]:17s} {r['cpu_env']:9.1f} {r['cpu_collect'] - r['cpu_env']:6.1f} "
            f"{r['cpu_grad']:6.1f} {counted / r['wall']:11.0f} {counted / learn:10.0f}"
        )
    print("CPU seconds: env stepping, the rest of rollout collection, gradient steps; env-steps/s of learning "
          "(target >= 10 k)")  # fmt: skip


if __name__ == "__main__":
    main()
