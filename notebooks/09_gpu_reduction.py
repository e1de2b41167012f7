# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 9. A GPU kernel you can read: the ICP reduction under numba's CUDA simulator
#
# Every dense estimator of the paper ends each Gauss-Newton iteration the same way: one row
# $(J_k, r_k)$ per pixel or pair, summed into the 6x6 normal equations $J^\top J$ and
# $J^\top r$ (eq. 10 and 13). On the GPU the paper does this "using a tree reduction on the GPU
# followed by Cholesky factorization of the linear system on the CPU" (IV-A.3). This lesson
# reads the package's CUDA kernel for ICP (`kintinuous_fast.odometry.icp.cuda`), runs it **without
# a GPU** under numba's CUDA simulator (each CUDA thread becomes a Python thread) on a tiny
# 80x60 frame, and checks it against the NumPy reference of notebook 5.
#
# 1. the kernel: a grid-stride loop over pixels, a local accumulator, a tree in shared memory,
# 2. a plain-Python emulation of the block's tree, checked equal to a plain sum,
# 3. the simulated kernel's 6x6 system against the reference, and the block partials it leaves.
#
# Prerequisites: notebook 5 (ICP). About 20 s warm; the simulator is thousands of times slower
# than a GPU, which is why the frame is tiny. The simulator must be switched on before numba is
# first imported, hence the first cell.

# %%
# %matplotlib inline
import os

os.environ["NUMBA_ENABLE_CUDASIM"] = "1"  # before numba is imported anywhere

import inspect

import matplotlib.pyplot as plt
import numpy as np

from kintinuous_fast.odometry.icp import cuda as gpu
from kintinuous_fast.odometry.sums import cuda as reduction
from kintinuous_ref import preprocess
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.odometry import icp

WIDTH, HEIGHT = 80, 60
config = Config()
scene = make_scenario("desk", frames=12, width=WIDTH, height=HEIGHT, seed=0, noise=True)
camera, poses = scene.camera, scene.trajectory.poses

# %% [markdown]
# ## The kernel
#
# One launch computes one iteration's system. Each thread walks the pixels
# $i, i + G, i + 2G, \ldots$ ($G$ = the number of threads in the grid: a *grid-stride loop*, so
# any image size works with a bounded grid), and for each valid pixel it
#
# 1. associates the vertex projectively with the model (`icp_match`, notebook 5's `associate`),
# 2. forms the row of eq. 9 (`point_to_plane_row`),
# 3. adds $w\,[J^\top J \text{ (21 numbers of the upper triangle)}, J^\top r \text{ (6)},
#    r^2, 1]$ into a private accumulator of 30 float64 numbers (`add_row`).
#
# Then the block's threads reduce their accumulators by a **tree** in shared memory
# (`block_reduce`, shared by every odometry kernel in `kintinuous_fast.odometry.sums.cuda`), and
# thread 0 writes the block's partial sums to global memory. The host adds
# the few hundred partials in float64 and solves the 6x6 system by Cholesky, as in the paper.

# %%
for function in (gpu._icp_kernel, reduction.block_reduce, gpu._point_to_plane_row):
    print(inspect.getsource(function.py_func))

# %% [markdown]
# ## The tree, in plain Python
#
# With $B$ threads in a block (a power of two; here `reduction.BLOCK`), step $s$ lets the first
# $B/2^s$ threads add the value of the thread $B/2^s$ places further on; after $\log_2 B$ steps
# thread 0 holds the block's sum. Each step is followed by `syncthreads()`, so no thread reads a
# value before it is written. The same schedule on a NumPy vector, step by step:


# %%
def tree_sum(values: np.ndarray) -> tuple[float, list[int]]:
    """The block's tree on one value per thread; returns the sum and the active threads per step."""
    shared = values.astype(np.float64).copy()
    half, active = len(shared) // 2, []
    while half > 0:
        shared[:half] += shared[half : 2 * half]  # threads t < half, all "at once"
        active.append(half)
        half //= 2
    return shared[0], active


rng = np.random.default_rng(0)
values = rng.normal(size=reduction.BLOCK)
total, active = tree_sum(values)
print(f"block of {reduction.BLOCK} threads: {len(active)} steps, active threads per step {active}")
np.testing.assert_allclose(total, values.sum(), rtol=1e-14)

fig, ax = plt.subplots(figsize=(6.5, 3))
ax.bar(range(1, len(active) + 1), active)
ax.set_xlabel("tree step")
ax.set_ylabel("threads adding")
ax.set_title(f"tree reduction of a {reduction.BLOCK}-thread block: log2(B) steps")
plt.show()

# %% [markdown]
# ## The kernel under the simulator, against the reference
#
# Frame 11 of the desk against a perfect model seen from frame 10's pose (the exact surface),
# evaluated at the true pose: the simulated CUDA kernel's system and the NumPy reference's
# `icp.icp_system` (notebook 5) must agree to rounding (float64 sums in another order).

# %%
previous_pose, current_pose = poses[10], poses[11]
_, exact_depth = scene.render_at(previous_pose, noise=False)
model_vertices = preprocess.vertex_map(exact_depth, camera)
model_normals = preprocess.normal_map(model_vertices)
rotation, centre = previous_pose[:3, :3], previous_pose[:3, 3]
model_vertices = (model_vertices @ rotation.T + centre).astype(np.float32)
model_normals = (model_normals @ rotation.T).astype(np.float32)
current = preprocess.preprocess_frame(*scene.render(11), camera, config.preprocess).levels[0]

arguments = (
    current.vertices,
    current.normals,
    current_pose,
    model_vertices,
    model_normals,
    previous_pose,
    camera,
)
simulated = gpu.icp_system(*arguments)
reference = icp.icp_system(*arguments)
print(f"pairs: simulated kernel {simulated.count}, reference {reference.count}")
print(
    f"largest |A_sim - A_ref| / max |A_ref| = "
    f"{np.abs(simulated.A - reference.A).max() / np.abs(reference.A).max():.1e}"
)
assert simulated.count == reference.count
np.testing.assert_allclose(simulated.A, reference.A, rtol=0, atol=1e-10 * np.abs(reference.A).max())
np.testing.assert_allclose(simulated.b, reference.b, rtol=0, atol=1e-10 * np.abs(reference.b).max())

# %% [markdown]
# Which block summed which pixels: with $G$ threads in the grid, pixel $i$ goes to thread
# $i \bmod G$, i.e. to block $\lfloor (i \bmod G) / B \rfloor$. Below, that map, and each block's
# share of the pairs (the last of its 30 numbers is its count of valid pixels; recomputing the
# pairs per block on the host shows how evenly the work is spread).

# %%
blocks = reduction.reduction_blocks(HEIGHT * WIDTH)
grid = blocks * reduction.BLOCK
pixel_block = ((np.arange(HEIGHT * WIDTH) % grid) // reduction.BLOCK).reshape(HEIGHT, WIDTH)
points, point_normals = icp.valid_points(current.vertices, current.normals)
valid = (np.isfinite(current.vertices).all(-1) & np.isfinite(current.normals).all(-1)).ravel()
world, matched, _ = icp.associate(
    points,
    point_normals,
    current_pose,
    *icp.map_columns(model_vertices, model_normals),
    previous_pose,
    camera,
    0.10,
    20.0,
)
per_block_valid = np.bincount(pixel_block.ravel()[valid], minlength=blocks)
_, kernel_valid = gpu._icp_system_and_valid(
    current.vertices,
    current.normals,
    model_vertices,
    model_normals,
    current_pose,
    previous_pose,
    camera,
    0.10,
    20.0,
)

fig, axes = plt.subplots(1, 2, figsize=(12, 3.4))
shown = axes[0].imshow(pixel_block, cmap="tab20", interpolation="nearest")
axes[0].set_title(f"block of each pixel ({blocks} blocks x {reduction.BLOCK} threads)")
axes[0].axis("off")
axes[1].bar(range(blocks), per_block_valid)
axes[1].set_xlabel("block")
axes[1].set_ylabel("valid pixels summed")
axes[1].set_title("work per block")
plt.show()
print(
    f"{blocks} blocks of {reduction.BLOCK} threads for {HEIGHT * WIDTH} pixels; valid pixels "
    f"{valid.sum()} (the kernels' summed counters: {kernel_valid}), pairs {world.shape[1]}"
)
assert world.shape[1] == reference.count and kernel_valid == valid.sum()

# %% [markdown]
# ## Summary
#
# - A reduction kernel gives each thread a private accumulator (grid-stride loop over pixels),
#   then reduces a block's accumulators by a tree in shared memory in $\log_2 B$ synchronised
#   steps; the host adds the block partials and solves the 6x6 system.
# - The sums are float64 (float32 sums over 300 000 pixels lose the small increments), and only
#   their order differs from the NumPy reference: the systems agree to about 1e-15.
# - numba's CUDA simulator runs the same kernel code on the CPU, thread by thread: slow, but it
#   lets the kernel be read, stepped through and tested without a GPU.
#
# ## Exercises
#
# 1. **Block size.** With $B$ = 64 instead of 128, how many tree steps does a block take, and
#    how many blocks does an 80x60 frame need (`reduction.reduction_blocks` caps them at
#    `reduction.MAX_BLOCKS`)? Check: `check_exercise_1(steps, blocks)`.
# 2. **A missing sync.** In `tree_sum`, the NumPy slice adds all pairs "at once". Emulate a
#    missing `syncthreads()` by adding the pairs one thread at a time in *descending* thread
#    order within a step: does the sum change? What about ascending order? (Think about which
#    values a thread reads that another thread of the same step writes.)
# 3. **Your own kernel.** Write a `@numba.cuda.jit` kernel that counts the pixels whose depth is
#    valid, with a block tree like `block_reduce`, launch it on `current.depth` under the
#    simulator, and compare with `(current.depth > 0).sum()`.


# %%
def check_exercise_1(steps: int, block_count: int) -> None:
    assert steps == int(np.log2(64)), "one step per halving of the block"
    expected = min(-(-HEIGHT * WIDTH // 64), reduction.MAX_BLOCKS)
    assert block_count == expected, f"ceil({HEIGHT * WIDTH} / 64) blocks"
    print("exercise 1 correct")


check_exercise_1(6, 75)  # the solution, so that the check cell runs (try it yourself first)
