"""What one Gauss-Newton step on the device costs, by part: odometry/frame_solve.py's
`solve_kernel` timed on a GPU with its partial sums spread over 1 to 1024 blocks (the finest
level's count), with the joint system and the default weighting, with ICP's system alone, and
with its gate closed (the launch alone); then the step's parts (solve/ops.py), each on its own
in a kernel of the same block: one eigenproblem, the scaled solution (its condition check and
Cholesky), the discounted joint system and the increment (one thread); then one eigenproblem
of a matrix with spread eigenvalues with its Jacobi sweeps capped at 0, 1 and 2 (what a sweep
costs, and what the rest does), started from the eigenvectors of a matrix near it (the solve
kernel's warm start), and on one warp whose barrier is the warp's (what the block's
barriers cost).

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from cuda_kernel_times import HOLD_STEPS, _hold
from jacobi_sweeps import sweeps_taken
from numba import cuda, float64

from kintinuous_fast import cuda_is_simulated
from kintinuous_fast.odometry import frame_kernels as slots
from kintinuous_fast.odometry.frame_on_device import _initial_poses
from kintinuous_fast.odometry.frame_solve import SOLVE_THREADS, _barrier, _ops, solve_kernel
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES, build_ops
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT
from kintinuous_fast.odometry.sums.cuda import DEVICE
from kintinuous_ref import se3

BLOCK_COUNTS = (1, 150, 600, 1024)
SWEEP_CAPS = (0, 1, 2)


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


def median_launch(
    launch: Callable[[], None], launches: int, prepare: Callable[[], None] | None = None
) -> float:
    """Median microseconds of `launch()` (one kernel launch) between two events, the first
    launch (which compiles) left out; `prepare()`, outside the events, before each."""
    scratch = cuda.to_device(np.zeros(1, dtype=np.float32))
    pairs = []
    for _ in range(launches + 1):
        before, after = cuda.event(), cuda.event()
        if prepare is not None:
            prepare()
        _hold[1, 1](scratch, HOLD_STEPS)
        before.record()
        launch()
        after.record()
        pairs.append((before, after))
    cuda.synchronize()
    return 1000.0 * statistics.median(b.elapsed_time(a) for b, a in pairs[1:])


def time_steps(mode: int, settings: tuple, blocks: int, launches: int, closed: bool) -> float:
    """Median microseconds of solve_kernel in one configuration."""
    state = np.zeros(slots.STATE_SIZE)
    state[slots.DONE_LEVEL], state[slots.MODE], state[slots.FAILED] = -1.0, mode, closed
    previous = se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.05]))
    poses = np.ascontiguousarray(_initial_poses(previous, None, previous))
    tally, state, poses = (cuda.to_device(x) for x in (np.zeros(2), state, poses))
    icp = cuda.to_device(partials(packed_system(1, 20_000), blocks, 1))
    rgbd = cuda.to_device(partials(packed_system(2, 8_000), blocks, 2))
    basis = cuda.to_device(np.eye(6))  # each step from the identity, as a frame's first
    arguments = (icp, rgbd, tally, state, poses, basis, settings, 0)
    us = median_launch(
        lambda: solve_kernel[1, SOLVE_THREADS](*arguments),
        launches,
        lambda: basis.copy_to_device(np.eye(6)),
    )
    if state.copy_to_host()[slots.FAILED] != closed:
        raise RuntimeError("a step failed: the timing would not be a step's")
    return us


_symmetric_eigen, _scaled_solution = _ops.symmetric_eigen, _ops.scaled_solution
_symmetric_eigen_from = _ops.symmetric_eigen_from
_discounted_joint, _increment = _ops.discounted_joint, _ops.increment


def eigen_kernel(symmetric_eigen: Any, lanes: int) -> Any:
    """A kernel of one block that runs `symmetric_eigen` on `lanes` threads."""

    @cuda.jit
    def kernel(a, values, vectors):  # noqa: ANN001, ANN202
        scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
        symmetric_eigen(a, values, vectors, scratch, cuda.threadIdx.x, lanes)

    return kernel


@cuda.jit
def _eigen_from_kernel(a, basis, values, vectors):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    _symmetric_eigen_from(a, basis, values, vectors, scratch, cuda.threadIdx.x, SOLVE_THREADS)


@cuda.jit
def _scaled_solution_kernel(a, b, xi):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    _scaled_solution(a, b, xi, scratch, cuda.threadIdx.x, SOLVE_THREADS)


@cuda.jit
def _discounted_joint_kernel(a, b, basis, joint_a, joint_b):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    t = cuda.threadIdx.x
    centre, threshold = (0.4, 1.5, 1.1), 0.02
    _discounted_joint(
        a, b, 20_000, 1.0, a, b, 0.3, *centre, threshold, basis, joint_a, joint_b, scratch, t,
        SOLVE_THREADS,
    )  # fmt: skip


@cuda.jit
def _increment_kernel(xi, pose, out):
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    if cuda.threadIdx.x == 0:
        _increment(xi, pose, out, scratch)


@cuda.jit(device=True)
def _warp_barrier():
    cuda.syncwarp()


def symmetric(seed: int, spread: bool) -> np.ndarray:
    """A scaled (unit-diagonal) SPD 6x6: of a random system's normal equations (eigenvalues
    within a few percent of 1), or with eigenvalues spread over six decades."""
    if not spread:
        unpacked = packed_system(seed, 20_000)
        a = np.zeros((6, 6))
        a[np.triu_indices(6)] = unpacked[:SLOT_B]
        a = a + np.triu(a, 1).T
    else:
        q = np.linalg.qr(np.random.default_rng(seed).normal(size=(6, 6)))[0]
        a = q @ np.diag(10.0 ** np.linspace(-3, 3, 6)) @ q.T
    scale = 1.0 / np.sqrt(np.diag(a))
    return np.ascontiguousarray((a + a.T) / 2 * scale[:, None] * scale[None, :])


def near(a: np.ndarray, seed: int, change: float = 1e-3) -> np.ndarray:
    """`a` changed symmetrically by `change` of its largest entry: a later Gauss-Newton step's
    information against an earlier one's."""
    noise = np.random.default_rng(seed).normal(size=a.shape) * change * np.abs(a).max()
    return a + (noise + noise.T) / 2


def time_parts(launches: int) -> dict[str, float]:
    """Median microseconds of each part of the step on its own, on one system's numbers."""
    unpacked = packed_system(1, 20_000)
    a = np.zeros((6, 6))
    a[np.triu_indices(6)] = unpacked[:SLOT_B]
    a_ = cuda.to_device(a + np.triu(a, 1).T)
    b_ = cuda.to_device(unpacked[SLOT_B : SLOT_B + 6])
    scaled = cuda.to_device(symmetric(1, spread=False))
    basis = cuda.to_device(np.eye(6))
    values, vectors, xi = cuda.device_array(6), cuda.device_array((6, 6)), cuda.device_array(6)
    joint_a, joint_b = cuda.device_array((6, 6)), cuda.device_array(6)
    step = cuda.to_device(np.array([1e-3, -2e-3, 3e-3, 1e-2, 0.0, -5e-3]))
    pose = cuda.to_device(se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.05])))
    out = cuda.device_array((4, 4))
    block = (1, SOLVE_THREADS)
    eigen = eigen_kernel(_symmetric_eigen, SOLVE_THREADS)
    launches_of = {
        "one eigenproblem": lambda: eigen[block](scaled, values, vectors),
        "scaled solution": lambda: _scaled_solution_kernel[block](a_, b_, xi),
        "discounted joint system": lambda: _discounted_joint_kernel[block](
            a_, b_, basis, joint_a, joint_b
        ),
        "increment (one thread)": lambda: _increment_kernel[block](step, pose, out),
    }
    identity = np.eye(6)  # the discounted joint system's eigenproblem from the identity
    return {
        name: median_launch(launch, launches, lambda: basis.copy_to_device(identity))
        for name, launch in launches_of.items()
    }


def time_sweeps(launches: int) -> dict[str, float]:
    """Median microseconds of one eigenproblem of a spread matrix, its sweeps capped, and on a
    warp."""
    spread = symmetric(5, spread=True)
    a = cuda.to_device(spread)
    values, vectors = cuda.device_array(6), cuda.device_array((6, 6))
    rows = {}
    for cap in SWEEP_CAPS:
        capped = build_ops(DEVICE, _barrier, max_sweeps=cap).symmetric_eigen
        kernel = eigen_kernel(capped, SOLVE_THREADS)
        name = f"spread eigenproblem, at most {cap} sweeps"
        rows[name] = median_launch(
            lambda k=kernel: k[1, SOLVE_THREADS](a, values, vectors), launches
        )
    needed = sweeps_taken(spread)[0]
    kernel = eigen_kernel(_symmetric_eigen, SOLVE_THREADS)
    rows[f"spread eigenproblem ({needed} sweeps)"] = median_launch(
        lambda: kernel[1, SOLVE_THREADS](a, values, vectors), launches
    )
    # from the eigenvectors of a matrix 1e-3 away, as a step starts from the last step's
    basis = np.linalg.eigh(near(spread, 5))[1]
    warm, basis_ = sweeps_taken(spread, basis)[0], cuda.to_device(basis)
    rows[f"spread eigenproblem, warm start ({warm} sweeps)"] = median_launch(
        lambda: _eigen_from_kernel[1, SOLVE_THREADS](a, basis_, values, vectors), launches
    )
    # numba's simulator has no syncwarp (its one-warp block synchronises as a block)
    warp_barrier = _barrier if cuda_is_simulated() else _warp_barrier
    warp = eigen_kernel(build_ops(DEVICE, warp_barrier).symmetric_eigen, 32)
    rows[f"spread eigenproblem ({needed} sweeps), one warp"] = median_launch(
        lambda: warp[1, 32](a, values, vectors), launches
    )
    return rows


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
            us = time_steps(mode, settings, blocks, args.launches, False)
            rows[f"{name}, {blocks} blocks"] = us
    rows["gate closed"] = time_steps(*joint, 1024, args.launches, True)
    rows.update({f"part: {name}": us for name, us in time_parts(args.launches).items()})
    rows.update(time_sweeps(args.launches))
    print(f"solve_kernel on {SOLVE_THREADS} threads, median us per launch ({args.launches}):")
    for name, us in rows.items():
        print(f"  {name:44s} {us:8.1f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
