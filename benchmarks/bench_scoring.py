"""Seconds to score an SB3 agent on one magenv-bench task: its trials one after the other against all together.

    .venv/bin/python benchmarks/bench_scoring.py --agent RUN [--agent RUN …] [--task MagBlend-v0/dynamic_magnet]
                                                 [--rounds 2] [--duration S]

For each agent (a run folder of ``magenv train``, ``pretrained:ENV_ID``), on the task's evaluation trials
(``magenv.benchmark.suite.EVAL_SEEDS``, made once before any timing), ``magenv.evaluation.run_policy_on_trials``
— what ``magenv benchmark`` runs for the agent — three ways:

* ``before``: one trial after the other, one ``model.predict`` on one observation per decision of one env (as
  ``AgentPolicy`` acted before issue 53), torch on its default threads (as ``magenv benchmark`` ran);
* ``one thread``: the same with torch on one thread (``magenv.agents.training.TORCH_THREADS``);
* ``after``: all the trials together, one ``act_batch`` per decision for all envs, torch on one thread (what
  ``magenv benchmark`` runs now).

The rounds alternate the three (the machine is shared: each round shows the load of its moment); each timing
prints wall and CPU seconds of this process. The rules' and oracles' RMSEs of the task are not timed
(``magenv benchmark`` keeps them). The scores agree to float32 rounding (largest relative difference printed):
a forward on one observation rounds differently from one on ``FORWARD_ROWS``. Nothing here is a pass/fail
test.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from magenv import evaluation
from magenv.agents.loading import load_agent
from magenv.agents.training import TORCH_THREADS
from magenv.agents.wrappers import action_bounds
from magenv.benchmark import suite
from magenv.train.benchmark import task_trials


class OneAtATime:
    """The agent as ``magenv`` ran it before issue 53: SB3's ``predict`` on one observation of one env per call
    (its LSTM state carried from call to call), no ``act_batch``: scored one trial after the other."""

    def __init__(self, agent):
        self.model, self.env_id, self.env_kwargs = agent.model, agent.env_id, agent.env_kwargs
        self.low, self.high = (np.asarray(b, np.float32) for b in action_bounds(agent.env_id, agent.env_kwargs))

    def reset(self) -> None:
        self.state, self.start = None, np.ones(1, bool)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action, self.state = self.model.predict(obs, state=self.state, episode_start=self.start, deterministic=True)
        self.start = np.zeros(1, bool)
        return self.low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (self.high - self.low)


def timed(policy, trials: list, threads: int) -> tuple[float, float, np.ndarray]:
    """(wall s, CPU s, total RMSE per trial) of scoring ``policy`` on ``trials`` with torch on ``threads``."""
    torch.set_num_threads(threads)
    w0, c0 = time.perf_counter(), time.process_time()
    scores = evaluation.run_policy_on_trials(policy, trials)
    return time.perf_counter() - w0, time.process_time() - c0, np.array([s.total for s in scores])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agent", action="append", required=True, help="run folder or pretrained:ENV_ID (repeatable)")
    p.add_argument("--task", default="MagBlend-v0/dynamic_magnet", help="task name (default %(default)s)")
    p.add_argument("--rounds", type=int, default=2, help="alternating rounds (default %(default)s)")
    p.add_argument("--duration", type=float, default=None, help="trials cut to S seconds (a quick look)")
    args = p.parse_args()
    (task,) = suite.select(args.task)
    default_threads = torch.get_num_threads()
    trials = task_trials(task, list(suite.EVAL_SEEDS), args.duration)
    print(f"{task.name}: {len(trials)} trials of {trials[0].n} samples; torch default threads {default_threads}")
    for spec in args.agent:
        agent = load_agent(spec)
        if agent.env_id != task.env_id:
            raise SystemExit(f"{spec}: acts in {agent.env_id}, not in {task.env_id}")
        ways = {
            "before": (OneAtATime(agent), default_threads),
            "one thread": (OneAtATime(agent), TORCH_THREADS),
            "after": (agent, TORCH_THREADS),
        }
        evaluation.run_policy_on_trials(agent, trials[:1])  # the env's kernels compiled, not timed
        print(f"\n{spec} ({type(agent.model).__name__})")
        results: dict[str, list] = {w: [] for w in ways}
        for r in range(args.rounds):
            for way, (policy, threads) in ways.items():
                wall, cpu, rmse = timed(policy, trials, threads)
                results[way].append((wall, cpu, rmse))
                print(f"  round {r + 1} {way:>10}: {wall:7.1f} s wall, {cpu:7.1f} s CPU, load {os.getloadavg()[0]:.1f}")
        ref = results["before"][0][2]
        walls = {way: float(np.median([w for w, _, _ in rows])) for way, rows in results.items()}
        cpus = {way: float(np.median([c for _, c, _ in rows])) for way, rows in results.items()}
        for way, rows in results.items():
            diff = max(float(np.max(np.abs(x - ref) / ref)) for _, _, x in rows)
            print(f"  {way:>10}: median {walls[way]:7.1f} s wall, {cpus[way]:7.1f} s CPU per task; "
                  f"largest relative score difference {diff:.1e}")  # fmt: skip
        ratio = walls["before"] / walls["after"], cpus["before"] / cpus["after"]
        print(f"  before / after: {ratio[0]:.0f}× wall, {ratio[1]:.0f}× CPU")


if __name__ == "__main__":
    main()
