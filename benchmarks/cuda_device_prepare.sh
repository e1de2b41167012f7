#!/usr/bin/env bash
# Prepares, on this machine, the folder that travels to a lent GPU machine for
# cuda_device_check.sh: .device/ (kept out of git through .git/info/exclude) with a NumPy 2.4
# wheel for the machine's Python 3.12 (its numba-cuda needs NumPy < 2.5, and nothing can be
# fetched there), a greenlet wheel (the simulator's blocks with barriers, cuda_host_cost.py)
# and a copy of the TUM RGB-D folder the checks read (the shared data does not
# travel). About 57 MB with the 300 redkitchen frames; a call carries 64 MiB with the repository.
# With a BASELINE commit, its source tree goes into .device/baseline too (about 2 MB), and the
# check times it beside the working tree in the same call: GPUs of one kind differ by about a
# tenth between calls, so only the same call compares like with like.
# Usage, from the repository root: benchmarks/cuda_device_prepare.sh TUM_FOLDER [BASELINE]
# Before the device call, benchmarks/cuda_typing_check.py types every kernel for a GPU here.
# Then, with the device tool: carry [".device"], command
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
#       .device/wheels/*.whl && export PYTHONPATH=/tmp/site &&
#   timeout 420 bash benchmarks/cuda_device_check.sh .device/data /tmp/checks --set volume.moving=false;
#   (the check finds .device/baseline beside the data folder)
#   tar czf "$OUT/checks.tgz" -C /tmp/checks .
set -eu
data=${1:?usage: cuda_device_prepare.sh TUM_FOLDER [BASELINE]}
baseline=${2:-}
mkdir -p .device .git/info
grep -qx '/.device/' .git/info/exclude 2>/dev/null || echo '/.device/' >>.git/info/exclude
rm -rf .device/wheels .device/data .device/baseline
if [ -n "$baseline" ]; then
    mkdir -p .device/baseline
    git archive "$baseline" kintinuous_ref kintinuous_fast benchmarks pyproject.toml |
        tar -x -C .device/baseline
    git rev-parse --short "$baseline" >.device/baseline/COMMIT
fi
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d .device/wheels "numpy>=2.4,<2.5" "greenlet>=3.0"
cp -r "$data" .device/data
du -sh .device
