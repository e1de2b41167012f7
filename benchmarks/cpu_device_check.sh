#!/usr/bin/env bash
# The cpu backend on many cores, for the device machine's 16 (the only machine with that many
# here; numba's CPU target needs no GPU): what one parallel call costs at 2, 8 and 16 threads on
# each of run_parallel's paths (benchmarks/parallel_call_overhead.py), then every stage and loop
# at 1-16 threads on numba's threads beside the machine's compute and memory-bandwidth ceilings
# (benchmarks/thread_sweep.py, machine_scaling.py), and at 1, 8 and 16 on the
# helper team (numba's workqueue layer asked for: it does not spin, so run_parallel takes the
# team), and at 8 and 16 on numba's threads with OpenMP's spin shortened; between them, each
# loop's time lost at 16 threads split into wake-up, join, imbalance and per-thread inflation
# (benchmarks/loop_anatomy.py). With a baseline source tree beside the data folder (baseline/,
# as benchmarks/cuda_device_prepare.sh TUM_FOLDER COMMIT leaves it), that tree is swept too at
# 1, 8 and 16 threads in the same call, so that old and new meet the same machine. About 6
# minutes, the cpu kernels' first compiles included.
# Usage, from the repository root: benchmarks/cpu_device_check.sh TUM_FOLDER [OUT_DIR]
# Writes sweep.json, anatomy.json, sweep_team.json and sweep_spin.json (sweep_baseline.json)
# into OUT_DIR (default: the current folder). Output is cut with sed, which reads to the end,
# not head: a script whose reader has gone dies of SIGPIPE before it writes its JSON.
set -u
data=$(realpath "${1:?usage: cpu_device_check.sh TUM_FOLDER [OUT_DIR]}")
out=${2:-.}
mkdir -p "$out"
out=$(realpath "$out")
baseline=$(dirname "$data")/baseline
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
# 15 threads beside 16: the machine's own processes share its 16 cores with a 16-thread team
timeout 200 python3 benchmarks/thread_sweep.py "$data" --threads 1,2,4,8,15,16 --frames 40 \
    --set volume.moving=false --json "$out/sweep.json" | sed -n '1,64p'
if [ -d "$baseline" ]; then
    echo "baseline $(cat "$baseline/COMMIT" 2>/dev/null)"
    (cd "$baseline" && source benchmarks/device_env.sh &&
        timeout 150 python3 benchmarks/thread_sweep.py "$data" --threads 1,8,16 --frames 40 \
            --set volume.moving=false --json "$out/sweep_baseline.json" | sed -n '1,24p')
fi
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
