#!/usr/bin/env bash
# The checks that need a GPU, in one go (about 6 minutes on an H100): the CUDA equivalence
# tests on the device (sizes of the CPU tests, not the simulator's); `kintinuous benchmark
# --backend cuda` at 512^3 and 256^3 with the launches replayed as CUDA graphs
# (kintinuous_fast/targets/cuda_graphs.py), each JSON with the launches, host waits and bytes to
# the host per frame and per stage; the ATE over 300 frames; the moving volume; a profile of the
# host; each kernel's GPU time; the solve step by part; the host's share of a frame as the
# simulator measures it here (cuda_host_cost.py). Where cuda_device_prepare.sh put a baseline
# tree beside the data folder (baseline/), the 256^3 benchmark (the frame rate goal's size, run
# right after the working tree's) and the kernel times run on it too, in the same call.
# Usage, from the repository root: benchmarks/cuda_device_check.sh TUM_FOLDER [OUT_DIR [OPTION...]]
# (benchmarks/cuda_device_prepare.sh makes the folder that travels: the data and the wheels;
# options go to `kintinuous benchmark`, e.g. --set volume.moving=false).
# Writes cuda_tests.log, bench_cuda_512_graphs.json, bench_cuda_256_graphs.json,
# ate_cuda.json, bench_cuda_moving.json, profile.txt, cuda_warm.prof, kernel_times.json,
# solve_parts.json and host_cost.txt (and baseline_bench_cuda_256_graphs.json,
# baseline_kernel_times.json) into OUT_DIR (default: the current folder): more files than the
# device tool brings back, so give a local folder and pack it into the tool's $OUT afterwards
# (cuda_device_prepare.sh).
set -u
data=${1:?usage: cuda_device_check.sh TUM_FOLDER [OUT_DIR]}
out=${2:-.}
mkdir -p "$out"
source benchmarks/device_env.sh
date -u
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c "import numba, numpy; print('numba', numba.__version__, 'numpy', numpy.__version__)"
python3 -m kintinuous_ref.program.cli info
# -o addopts=-ra: the device has no pytest-xdist, which the project's addopts ask for
timeout 150 python3 -m pytest -q -p no:cacheprovider -o addopts=-ra --continue-on-collection-errors \
    -k "cuda or graph or pool" \
    tests/test_fast_cuda.py tests/test_fast_cuda_pipeline.py tests/test_fast_odometry_cuda.py \
    tests/test_cuda_frame_budget.py tests/test_cuda_graphs.py tests/test_fast_solve_ops.py \
    tests/test_fast_backends.py tests/test_fast_volume.py tests/test_fast_odometry_cases.py \
    2>&1 | tee "$out/cuda_tests.log" | tail -40
baseline=$(dirname "$data")/baseline
[ -d "$baseline" ] && echo "baseline: $(cat "$baseline/COMMIT" 2>/dev/null)" || baseline=
# on_baseline COMMAND...: the command with the baseline tree's packages first on the path (its
# Python runs with -P, or `-m` would put the working tree, the current folder, before them)
on_baseline() { PYTHONPATH=$baseline:$PYTHONPATH "$@"; }
bench() {  # bench NAME RESOLUTION [on_baseline]: 100 frames with graphs, its JSON and summary
    local name=$1 resolution=$2 start
    start=$(date +%s)
    ${3:-} env KINTINUOUS_CUDA_GRAPHS=1 timeout 80 python3 -P -m kintinuous_ref.program.cli benchmark \
        "$data" --backend cuda "${extra[@]}" --resolution "$resolution" --frames 100 --json \
        >"$out/$name.json"
    echo "$name: exit $?, $(($(date +%s) - start)) s wall, compilation included"
    summary "$out/$name.json"
}
extra=("${@:3}")
bench bench_cuda_256_graphs 256
[ -n "$baseline" ] && bench baseline_bench_cuda_256_graphs 256 on_baseline
bench bench_cuda_512_graphs 512
# the whole pipeline's ATE over 300 frames, to compare with the cpu backend's on the same settings
KINTINUOUS_CUDA_GRAPHS=1 timeout 100 python3 benchmarks/combined_weightings.py "$data" --size 640x480 \
    --resolution 256 --methods --weightings huber --backend cuda "${@:3}" --json "$out/ate_cuda.json" | tail -3
# Kintinuous proper: the moving volume at the defaults (its slices meshed by our own marching
# cubes on the device, no VTK needed); the "shift" stage is the shift-and-extract time
start=$(date +%s)
KINTINUOUS_CUDA_GRAPHS=1 timeout 80 python3 -m kintinuous_ref.program.cli benchmark "$data" \
    --backend cuda --set volume.moving=true --frames 100 --json >"$out/bench_cuda_moving.json"
echo "benchmark moving volume: exit $?, $(($(date +%s) - start)) s wall, compilation included"
summary "$out/bench_cuda_moving.json"
# where the warm pipeline's host time goes with graphs on: profile.txt and cuda_warm.prof
KINTINUOUS_CUDA_GRAPHS=1 timeout 70 python3 benchmarks/warm_profile.py "$data" --backend cuda "${@:3}" --frames 20 \
    --top 40 --out "$out/cuda_warm.prof" >"$out/profile.txt" 2>/dev/null
echo "profile: exit $?"
# each kernel's own GPU time per frame (launched one by one between CUDA events)
timeout 60 python3 benchmarks/cuda_kernel_times.py "$data" "${@:3}" --frames 10 --top 25 \
    --json "$out/kernel_times.json" 2>&1 | grep -v Warning
[ -n "$baseline" ] && on_baseline timeout 60 python3 "$baseline/benchmarks/cuda_kernel_times.py" \
    "$data" "${@:3}" --frames 10 --top 25 --json "$out/baseline_kernel_times.json" 2>&1 |
    grep -v Warning
# the Gauss-Newton step by part: partial sums, eigenproblems, a Jacobi sweep, the barriers
timeout 40 python3 benchmarks/solve_kernel_time.py --json "$out/solve_parts.json" 2>&1 | grep -v Warn
# the host's share of a replayed frame as the simulator measures it, on this machine's CPU: to
# set beside the real frames above (what the measure without a GPU stands for)
timeout 40 python3 benchmarks/cuda_host_cost.py 2>&1 | grep -v Warn | tee "$out/host_cost.txt"
date -u
