"""What one Gauss-Newton step on the device costs, by part: odometry/frame_solve.py's
`solve_kernel` timed on a GPU with its partial sums spread over 1 to 1024 blocks (the finest
level's count), with the joint system and the default weighting (two 6x6 eigenproblems), with
ICP's system alone (one), and with its gate closed (the launch alone); then the step's parts
(solve/ops.py), each on its own in a kernel of the same block: one eigenproblem, the scaled
solution (an eigenproblem, Cholesky on one thread), the discounted joint system and the
increment (one thread).

    python benchmarks/solve_kernel_time.py [--launches 60] [--json F]

The time a step takes beyond the one-block case is the adding of the partial sums; the time the
one-block case takes beyond the closed gate is the 6x6 algebra. Each launch is timed between two
CUDA events behind a spinning kernel (cuda_kernel_times.py), medians in microseconds. Needs a
GPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np
from cuda_kernel_times import HOLD_STEPS, _hold
from numba import cuda, float64

from kintinuous_fast.odometry import frame_kernels as slots
from kintinuous_fast.odometry.frame_on_device import _initial_poses
from kintinuous_fast.odometry.frame_solve import SOLVE_THREADS, _ops, solve_kernel
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT
from kintinuous_ref import se3

BLOCK_COUNTS = (1, 150, 600, 1024)


def packed_system(seed: int, rows: int) -> np.ndarray:
    """A system's NV summed values (sums.unpack's layout) from `rows` random Jacobian rows."""
    rng = np.random.default_rng(seed)
    jacobian = rng.normal(size=(rows, 6)) * [1.0, 1.0, 1.0, 0.3, 0.3, 0.3]
    residuals = rng.normal(scale=0.01, size=rows)
    vector = np.zeros(NV)
    vector[:SLOT_B] = (jacobian.T @ jacobian)[np.triu_indices(6)]
    vector[SLOT_B : SLOT_B + 6] = jacobian.T @ residuals
    vector[SLOT_COST], vector[SLOT_COUNT] = residuals @ residuals, rows
    return vector


def partials(vector: np.ndarray, blocks: int, seed: int) -> np.ndarray:
    shares = np.random.default_rng(seed).dirichlet(np.ones(blocks))
    return shares[:, None] * vector[None, :]


def time_steps(mode: int, settings: tuple, blocks: int, launches: int, closed: bool) -> float:
    """Median microseconds of solve_kernel over `launches` launches of one configuration."""
    state = np.zeros(slots.STATE_SIZE)
    state[slots.DONE_LEVEL], state[slots.MODE], state[slots.FAILED] = -1.0, mode, closed
    previous = se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.05]))
    poses = np.ascontiguousarray(_initial_poses(previous, None, previous))
    tally, state, poses = (cuda.to_device(x) for x in (np.zeros(2), state, poses))
    icp = cuda.to_device(partials(packed_system(1, 20_000), blocks, 1))
    rgbd = cuda.to_device(partials(packed_system(2, 8_000), blocks, 2))
    scratch = cuda.to_device(np.zeros(1, dtype=np.float32))
    pairs = []
    for _ in range(launches + 1):
        before, after = cuda.event(), cuda.event()
        _hold[1, 1](scratch, HOLD_STEPS)
        before.record()
        solve_kernel[1, SOLVE_THREADS](icp, rgbd, tally, state, poses, settings, 0)
        after.record()
        pairs.append((before, after))
    cuda.synchronize()
    if state.copy_to_host()[slots.FAILED] != closed:
        raise RuntimeError("a step failed: the timing would not be a step's")
    return 1000.0 * statistics.median(b.elapsed_time(a) for b, a in pairs[1:])


_symmetric_eigen, _scaled_solution = _ops.symmetric_eigen, _ops.scaled_solution
_discounted_joint, _increment = _ops.discounted_joint, _ops.increment


@cuda.jit
def _eigen_kernel(a, values, vectors):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    _symmetric_eigen(a, values, vectors, scratch, cuda.threadIdx.x, SOLVE_THREADS)


@cuda.jit
def _scaled_solution_kernel(a, b, xi):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    _scaled_solution(a, b, xi, scratch, cuda.threadIdx.x, SOLVE_THREADS)


@cuda.jit
def _discounted_joint_kernel(a, b, joint_a, joint_b):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    t = cuda.threadIdx.x
    _discounted_joint(
        a,
        b,
        20_000,
        1.0,
        a,
        b,
        0.3,
        0.4,
        1.5,
        1.1,
        0.02,
        joint_a,
        joint_b,
        scratch,
        t,
        SOLVE_THREADS,
    )


@cuda.jit
def _increment_kernel(xi, pose, out):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    if cuda.threadIdx.x == 0:
        _increment(xi, pose, out, scratch)


def median_launch(launch, launches: int) -> float:  # noqa: ANN001
    """Median microseconds of `launch()` (one kernel launch) between two events."""
    scratch = cuda.to_device(np.zeros(1, dtype=np.float32))
    pairs = []
    for _ in range(launches + 1):
        before, after = cuda.event(), cuda.event()
        _hold[1, 1](scratch, HOLD_STEPS)
        before.record()
        launch()
        after.record()
        pairs.append((before, after))
    cuda.synchronize()
    return 1000.0 * statistics.median(b.elapsed_time(a) for b, a in pairs[1:])


def time_parts(launches: int) -> dict[str, float]:
    """Median microseconds of each part of the step on its own, on one system's numbers."""
    unpacked = packed_system(1, 20_000)
    a = np.zeros((6, 6))
    a[np.triu_indices(6)] = unpacked[:SLOT_B]
    a = a + np.triu(a, 1).T
    scale = 1.0 / np.sqrt(np.diag(a))
    a_, b_ = cuda.to_device(a), cuda.to_device(unpacked[SLOT_B : SLOT_B + 6])
    scaled = cuda.to_device(a * scale[:, None] * scale[None, :])
    values, vectors, xi = cuda.device_array(6), cuda.device_array((6, 6)), cuda.device_array(6)
    joint_a, joint_b, out = (
        cuda.device_array((6, 6)),
        cuda.device_array(6),
        cuda.device_array((4, 4)),
    )
    step = cuda.to_device(np.array([1e-3, -2e-3, 3e-3, 1e-2, 0.0, -5e-3]))
    pose = cuda.to_device(se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.05])))
    block = (1, SOLVE_THREADS)
    launches_of = {
        "one eigenproblem": lambda: _eigen_kernel[block](scaled, values, vectors),
        "scaled solution": lambda: _scaled_solution_kernel[block](a_, b_, xi),
        "discounted joint system": lambda: _discounted_joint_kernel[block](
            a_, b_, joint_a, joint_b
        ),
        "increment (one thread)": lambda: _increment_kernel[block](step, pose, out),
    }
    return {name: median_launch(launch, launches) for name, launch in launches_of.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--launches", type=int, default=60)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    joint = (slots.JOINT, (10.0, 1e-12, slots.DISCOUNTED, 0.3, 10.0, 0.02))
    icp_alone = (slots.ICP_ONLY, (10.0, 1e-12, slots.PAPER_METRES, 1.0, 1.0, 0.0))
    rows = {}
    for name, (mode, settings) in {"joint, discounted": joint, "ICP alone": icp_alone}.items():
        for blocks in BLOCK_COUNTS:
            rows[f"{name}, {blocks} blocks"] = time_steps(
                mode, settings, blocks, args.launches, False
            )
    rows["gate closed"] = time_steps(*joint, 1024, args.launches, True)
    rows.update({f"part: {name}": us for name, us in time_parts(args.launches).items()})
    print(f"solve_kernel on {SOLVE_THREADS} threads, median us per launch ({args.launches}):")
    for name, us in rows.items():
        print(f"  {name:34s} {us:8.1f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
