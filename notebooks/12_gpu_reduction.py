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
# # 12. A GPU kernel you can read: the ICP reduction under numba's CUDA simulator
#
# Every dense estimator of the paper ends each Gauss-Newton iteration the same way: one row
# $(J_k, r_k)$ per pixel or pair, summed into the 6x6 matrix $J^\top J$ and the 6-vector
# $J^\top r$ of the normal equations of a linear least-squares problem (eq. 3 for RGB-D, eq. 10
# for ICP, eq. 12-13 for the two together). The paper solves eq. 3 "using a tree reduction on
# the GPU followed by Cholesky factorization of the linear system on the CPU" (IV-A.3), and
# computes ICP's and the joint products the same way (V-B). This lesson
# reads the package's CUDA kernel for ICP (`kintinuous_fast.odometry.icp.cuda`), runs it **without
# a GPU** under numba's CUDA simulator (each CUDA thread becomes a Python thread) on a tiny
# 80x60 frame, and checks it against the NumPy reference of lesson 5.
#
# 1. the kernel: a grid-stride loop over pixels, a local accumulator, a tree in shared memory,
# 2. a plain-Python emulation of the block's tree, checked equal to a plain sum,
# 3. the simulated kernel's 6x6 system against the reference, and the block partials it leaves,
# 4. the grid-stride loop looping: fewer threads than pixels, each thread taking several.
#
# Prerequisites: lesson 5 (ICP). Its time, warm, is in notebooks/README.md's table. The
# simulator runs each CUDA thread as Python, far slower than a GPU, which is why the frame is
# tiny. It must be switched on before numba is first imported, hence the first cell.

# %%
# %matplotlib inline
import os

os.environ["NUMBA_ENABLE_CUDASIM"] = "1"  # before numba is imported anywhere

import inspect

import matplotlib.pyplot as plt
import numpy as np

from kintinuous_fast.odometry import sums
from kintinuous_fast.odometry.icp import cuda as gpu
from kintinuous_fast.odometry.sums import cuda as reduction
from kintinuous_ref import preprocess
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
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
# 1. associates the vertex projectively with the model (`icp_match`, lesson 5's `associate`),
# 2. forms the row of eq. 9 (`point_to_plane_row`),
# 3. adds the 29 numbers $w\,[J^\top J \text{ (21 numbers of the upper triangle)},
#    J^\top r \text{ (6)}, r^2, 1]$ into a private accumulator of float64 numbers (`add_row`).
#
# The accumulator has one more slot, 30 in all (`sums.NV`): the kernel counts the valid current
# pixels in the last one, which the inlier fraction divides by. Then the block's threads reduce
# their accumulators by a **tree** in shared memory (`block_reduce`, shared by every odometry
# kernel in `kintinuous_fast.odometry.sums.cuda`), and thread 0 writes the block's partial sums
# to global memory. The host adds the partials, one row of 30 per block, in float64 and solves
# the 6x6 system by Cholesky, as in the paper. How many blocks: one per $B$ pixels, rounded up,
# at most `MAX_BLOCKS` = 1024 (`reduction_blocks`); for this 80x60 frame, 38.

# %%
for function in (gpu.icp_kernel, reduction.block_reduce, gpu._point_to_plane_row):
    print(inspect.getsource(function.py_func))
upper_triangle, right_side, cost_and_count = 6 * 7 // 2, 6, 2
assert upper_triangle + right_side + cost_and_count == 29 == sums.SLOT_EXTRA  # add_row's share
assert sums.NV == 30  # and the valid-pixel counter after them
assert reduction.MAX_BLOCKS == 1024 and reduction.reduction_blocks(HEIGHT * WIDTH) == 38
assert reduction.BLOCK == 128 and 38 * reduction.BLOCK == 4864 and HEIGHT * WIDTH == 4800

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
# `icp.icp_system` (lesson 5) must agree to rounding (float64 sums in another order).

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
relative_difference = np.abs(simulated.A - reference.A).max() / np.abs(reference.A).max()
print(f"largest |A_sim - A_ref| / max |A_ref| = {relative_difference:.1e}")
assert relative_difference < 1e-12  # rounding: float64 sums in another order
assert simulated.count == reference.count
np.testing.assert_allclose(simulated.A, reference.A, rtol=0, atol=1e-10 * np.abs(reference.A).max())
np.testing.assert_allclose(simulated.b, reference.b, rtol=0, atol=1e-10 * np.abs(reference.b).max())

# %% [markdown]
# ## The grid-stride loop, looping
#
# Above, `reduction_blocks` gave 38 blocks of 128 threads, 4,864 threads for 4,800 pixels: every
# thread took at most one pixel and the loop never went round. On a real GPU it does: a 640x480
# frame has 307,200 pixels and the cap of 1024 blocks gives 131,072 threads, so each thread takes
# two or three. To see that here, the cap is lowered to 8 blocks for one run: 1,024 threads for
# the 4,800 pixels, so thread $t$ takes pixels $t, t + 1024, t + 2048, \ldots$, four or five
# each. The system must not change (the sums only come in another order).
#
# Which block summed which pixel: pixel $i$ goes to thread $i \bmod G$, i.e. to block
# $\lfloor (i \bmod G) / B \rfloor$, in round $\lfloor i / G \rfloor$ of its thread's loop.
# Below, both maps, and each block's share of the valid pixels (the kernel's last slot, summed
# over the blocks, against the host's count).

# %%
default_cap, reduction.MAX_BLOCKS = reduction.MAX_BLOCKS, 8
try:
    blocks = reduction.reduction_blocks(HEIGHT * WIDTH)
    looped, kernel_valid = gpu._icp_system_and_valid(
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
finally:
    reduction.MAX_BLOCKS = default_cap
grid = blocks * reduction.BLOCK
pixel_index = np.arange(HEIGHT * WIDTH)
pixel_block = ((pixel_index % grid) // reduction.BLOCK).reshape(HEIGHT, WIDTH)
pixel_round = (pixel_index // grid).reshape(HEIGHT, WIDTH)
pixels_per_thread = np.bincount(pixel_index % grid, minlength=grid)
valid = (np.isfinite(current.vertices).all(-1) & np.isfinite(current.normals).all(-1)).ravel()
per_block_valid = np.bincount(pixel_block.ravel()[valid], minlength=blocks)
assert blocks == 8 and grid == 1024 and grid < HEIGHT * WIDTH
assert pixels_per_thread.min() == 4 and pixels_per_thread.max() == 5  # the loop goes round
assert 640 * 480 / (1024 * reduction.BLOCK) > 2  # the same on a real 640x480 frame
assert looped.count == reference.count
np.testing.assert_allclose(looped.A, reference.A, rtol=0, atol=1e-10 * np.abs(reference.A).max())
np.testing.assert_allclose(looped.b, reference.b, rtol=0, atol=1e-10 * np.abs(reference.b).max())
assert kernel_valid == valid.sum()

fig, axes = plt.subplots(1, 3, figsize=(15, 3.4))
block_colours = plt.get_cmap("tab10", blocks)
shown = axes[0].imshow(
    pixel_block, cmap=block_colours, vmin=-0.5, vmax=blocks - 0.5, interpolation="nearest"
)
fig.colorbar(shown, ax=axes[0], ticks=range(blocks), label="block")
axes[0].set_title(f"block of each pixel ({blocks} x {reduction.BLOCK} threads)")
round_colours = plt.get_cmap("viridis", pixel_round.max() + 1)
shown = axes[1].imshow(
    pixel_round, cmap=round_colours, vmin=-0.5, vmax=pixel_round.max() + 0.5,
    interpolation="nearest",
)  # fmt: skip
fig.colorbar(shown, ax=axes[1], ticks=range(pixel_round.max() + 1), label="round")
axes[1].set_title("round of the grid-stride loop")
for ax in axes[:2]:
    ax.axis("off")
axes[2].bar(range(blocks), per_block_valid, color=[block_colours(b) for b in range(blocks)])
axes[2].set_xlabel("block")
axes[2].set_ylabel("valid pixels summed")
axes[2].set_title("work per block")
plt.tight_layout()
plt.show()
print(
    f"{blocks} blocks of {reduction.BLOCK} threads for {HEIGHT * WIDTH} pixels: "
    f"{pixels_per_thread.min()} to {pixels_per_thread.max()} pixels per thread; valid pixels "
    f"{valid.sum()} (the kernel's summed counters: {kernel_valid}); the same system as the "
    "reference"
)

# %% [markdown]
# ## Real data: the kernel on a real pair
#
# The same simulated kernel on real depth: real frame 101 against frame 100's own vertices and
# normals (carried into the world at its ground-truth pose), at 40x30 (a quarter of the
# threads: the simulator runs each as a Python thread), evaluated at frame 101's ground-truth
# pose. Real depth has holes and noise, so not every pixel pairs; the kernel's system must still
# equal the reference's to rounding, on any sequence. The frames come from the course's one
# loader, `load_course_data()` (notebooks/README.md): the shared 7-Scenes redkitchen frames, or
# a TUM RGB-D sequence you have; without either the cell prints one line and skips.

# %%
# $KINTINUOUS_COURSE_DATA, else the shared redkitchen, else a downloaded TUM sequence
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    REAL_SIZE = (40, 30)
    real_camera = REAL.camera_at(*REAL_SIZE)
    real_truth = REAL.groundtruth.poses
    real_images = {image.index: image for image in REAL.frames([100, 101], *REAL_SIZE)}
    real_frames = {
        index: preprocess.preprocess_frame(
            image.colour, image.depth, real_camera, config.preprocess
        ).levels[0]
        for index, image in real_images.items()
    }
    earlier_pose, later_pose = real_truth[100], real_truth[101]
    earlier_rotation = earlier_pose[:3, :3]
    real_arguments = (
        real_frames[101].vertices,
        real_frames[101].normals,
        later_pose,
        (real_frames[100].vertices @ earlier_rotation.T + earlier_pose[:3, 3]).astype(np.float32),
        (real_frames[100].normals @ earlier_rotation.T).astype(np.float32),
        earlier_pose,
        real_camera,
    )
    real_simulated = gpu.icp_system(*real_arguments)
    real_reference = icp.icp_system(*real_arguments)
    real_scale = np.abs(real_reference.A).max()
    real_difference = np.abs(real_simulated.A - real_reference.A).max() / real_scale
    has_depth = np.isfinite(real_frames[101].vertices).all(-1)
    print(
        f"{has_depth.sum()} of {has_depth.size} pixels with depth, {real_simulated.count} "
        f"paired (reference {real_reference.count}); largest |A_sim - A_ref| / max |A_ref| = "
        f"{real_difference:.1e}"
    )
    fig, axes = plt.subplots(1, 2, figsize=(9, 3))
    axes[0].imshow(real_images[101].colour)
    axes[0].set_title(f"{REAL.name} frame 101, 40x30")
    axes[1].imshow(np.where(has_depth, real_frames[101].vertices[..., 2], np.nan), cmap="viridis")
    axes[1].set_title("its depth (m); white: none")
    for ax in axes:
        ax.axis("off")
    plt.show()
    assert real_simulated.count == real_reference.count > 0
    assert real_difference < 1e-12  # rounding: float64 sums in another order
    np.testing.assert_allclose(
        real_simulated.b, real_reference.b, rtol=0,
        atol=1e-10 * np.abs(real_reference.b).max(),
    )  # fmt: skip

# %% [markdown]
# ## Summary
#
# - A reduction kernel gives each thread a private accumulator (a grid-stride loop over pixels,
#   which goes round once the pixels outnumber the threads),
#   then reduces a block's accumulators by a tree in shared memory in $\log_2 B$ synchronised
#   steps; the host adds the block partials and solves the 6x6 system.
# - The sums are float64, as the NumPy reference's are, and only their order differs: the
#   systems agree to rounding, under 1e-12 of the largest entry with a pixel per thread and
#   under 1e-10 with several.
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


# Your answers go into the next cell (`None` until you have them); the check cell compares them
# with the tree emulation above and the block count's rule, and says what is still open.

# %%
your_steps = None  # exercise 1: tree steps of a 64-thread block
your_blocks = None  # exercise 1: blocks for an 80x60 frame with 64 threads each


# %%
def check_exercise_1(steps: int | None, block_count: int | None) -> None:
    if steps is None or block_count is None:
        print("exercise 1: not answered yet (fill in your_steps and your_blocks above)")
        return
    assert steps == len(tree_sum(np.zeros(64))[1]), "count the halvings of the block"
    expected = min(-(-HEIGHT * WIDTH // 64), reduction.MAX_BLOCKS)
    assert block_count == expected, "one block per 64 pixels, rounded up, at most MAX_BLOCKS"
    print("exercise 1 correct")


check_exercise_1(your_steps, your_blocks)
