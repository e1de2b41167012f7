#!/usr/bin/env bash
# The cpu backend on many cores, for the device machine's 16 (the only machine with that many
# here; numba's CPU target needs no GPU): what one parallel call costs at 2, 8 and 16 threads on
# each of run_parallel's paths (benchmarks/parallel_call_overhead.py), then every stage and loop
# at 1-16 threads on numba's threads beside the machine's compute and memory-bandwidth ceilings
# (benchmarks/thread_sweep.py, machine_scaling.py), and at 1, 8 and 16 on the
# helper team (numba's workqueue layer asked for: it does not spin, so run_parallel takes the
# team), and at 8 and 16 on numba's threads with OpenMP's spin shortened; between them, each
# loop's time lost at 16 threads split into wake-up, join, imbalance and per-thread inflation
# (benchmarks/loop_anatomy.py). About 5.5 minutes, the cpu kernels' first compile included.
# Usage, from the repository root: benchmarks/cpu_device_check.sh TUM_FOLDER [OUT_DIR]
# Writes sweep.json, anatomy.json, sweep_team.json and sweep_spin.json into OUT_DIR (default:
# the current folder). Output is cut with sed, which reads to the end, not head: a script whose
# reader has gone dies of SIGPIPE before it writes its JSON.
set -u
data=${1:?usage: cpu_device_check.sh TUM_FOLDER [OUT_DIR]}
out=${2:-.}
mkdir -p "$out"
source benchmarks/device_env.sh
date -u
lscpu | grep -E "Model name|^CPU\(s\)|Thread\(s\) per core"
for threads in 2 8 16; do
    NUMBA_NUM_THREADS=$threads timeout 60 python3 benchmarks/parallel_call_overhead.py --calls 300 \
        | tail -14
done
# a team of 15 helpers for loops that may use two threads: what waking the team costs
NUMBA_NUM_THREADS=16 timeout 60 python3 benchmarks/parallel_call_overhead.py --calls 300 \
    --gaps 100,1000 --at-most 2 | tail -10
timeout 200 python3 benchmarks/thread_sweep.py "$data" --threads 1,2,4,8,16 --frames 30 \
    --set volume.moving=false --json "$out/sweep.json" | sed -n '1,64p'
timeout 100 python3 benchmarks/loop_anatomy.py "$data" --frames 6 --calls 15 --top 30 \
    --set volume.moving=false --json "$out/anatomy.json" | tail -32
NUMBA_THREADING_LAYER=workqueue timeout 120 python3 benchmarks/thread_sweep.py "$data" \
    --threads 1,8,16 --frames 20 --set volume.moving=false --json "$out/sweep_team.json" \
    | sed -n '1,12p'
# OpenMP's threads spin for GOMP_SPINCOUNT (300,000 by default) before they sleep: between two
# loops every core spins while the calling thread runs Python; a shorter spin, at 8 and 16
GOMP_SPINCOUNT=10000 timeout 90 python3 benchmarks/thread_sweep.py "$data" \
    --threads 8,16 --frames 20 --set volume.moving=false --json "$out/sweep_spin.json" \
    | sed -n '1,12p'
date -u
