#!/usr/bin/env bash
# The magenv-bench v1 baseline table: 5 envs × 4 methods × 5 training seeds (magenv/benchmark/suite.py), one
# training seed of every method after another, so that a table cut short has whole rounds. Resumable: run it
# again and finished runs are skipped, an interrupted one resumes from its last checkpoint (magenv sweep); a sweep
# that stops (Ray failing to start on a loaded machine, a run that failed) is tried again, up to 3 times.
#   nice -n 19 agents/configs/bench/train.sh [OUT=runs/bench] [WORKERS=2]
# It ends by scoring the finished runs into OUT/table (index.md, baselines.csv, baselines.png); the same at any
# time: magenv benchmark --sweep OUT --out OUT/table
set -u
OUT=${1:-runs/bench}
WORKERS=${2:-2}
MAGENV=${MAGENV:-magenv}
HERE=$(dirname "$0")
for seed in 0 1 2 3 4; do
  for algo in ppo recurrent_ppo sac dagger; do
    for attempt in 1 2 3; do
      "$MAGENV" sweep "$HERE/$algo.yaml" --out "$OUT/$algo" --workers "$WORKERS" --seeds "$seed" && break
      echo "train.sh: $algo seed $seed stopped (attempt $attempt); trying again in 60 s"
      sleep 60
    done
  done
done
"$MAGENV" benchmark --sweep "$OUT" --out "$OUT/table"
