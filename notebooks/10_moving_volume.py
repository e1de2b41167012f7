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
# # 10. The moving cyclical volume and slice extraction
#
# KinectFusion maps a fixed cube: walk out of it and the map ends. What makes Kintinuous
# *continuous* (paper section III, Fig. 2) is that the TSDF volume **follows the camera**. It is
# a cyclical buffer: when the camera has moved far enough, the volume shifts by whole voxels,
# the surface in the slab that leaves it is extracted as a mesh **slice**, the slab is cleared,
# and the same memory holds the slab that enters on the other side. The map grows without bound
# while the memory stays that of one volume.
#
# 1. the ring buffer's indexing: logical voxel, array cell, offset, with a toy example,
# 2. when to shift (the threshold) and by how much, with the package's source,
# 3. a walk down the synthetic corridor: the window moves, slices leave, one memory,
# 4. the slices merged into one mesh, seams joined exactly, checked against the true surface and
#    against a fixed volume that loses what leaves it.
#
# Prerequisites: lesson 1 (TSDF fusion). Its time, warm, is in notebooks/README.md's table.

# %%
# %matplotlib inline
import inspect
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle

from kintinuous_ref import mesh, moving_volume, pipeline, tsdf
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import Frame

WIDTH, HEIGHT, FRAMES = 160, 120, 150

# %% [markdown]
# ## The ring buffer
#
# Every voxel of the world has a fixed integer **global** index $\mathbf{g}$. The volume is a
# window of $N^3$ consecutive global voxels starting at a corner $\mathbf{c}$; its **logical**
# voxel $\mathbf{l} = \mathbf{g} - \mathbf{c}$ (0 to $N-1$ per axis) is stored in the array cell
#
# $$ \text{cell}(\mathbf{l}) = (\mathbf{l} + \mathbf{o}) \bmod N $$
#
# with an offset $\mathbf{o}$ that starts at zero. Shifting the window by $s$ voxels along an axis
# moves no data: $\mathbf{c}$ and $\mathbf{o}$ grow by $s$ (modulo $N$), and the $s$ layers of
# cells that held the leaving voxels, once extracted and cleared, now hold the voxels that
# entered. On the GPU this is what makes a shift cheap: no voxel of the volume is copied. A
# toy volume of $N = 8$ along one axis, shifted by 3 and then by 3 again:

# %%
N = 8
fig, axes = plt.subplots(3, 1, figsize=(9, 3.4))
corner, offset = 0, 0
for ax, shift in zip(axes, (0, 3, 3), strict=True):
    corner, offset = corner + shift, (offset + shift) % N
    for cell in range(N):
        logical = (cell - offset) % N
        fresh = shift and logical >= N - shift
        ax.add_patch(
            Rectangle(
                (cell, 0), 1, 1, fc="tab:orange" if fresh else "tab:blue", ec="white", alpha=0.8
            )
        )
        ax.text(cell + 0.5, 0.5, f"g={corner + logical}", ha="center", va="center", color="w")
    ax.set_xlim(0, N)
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    ax.set_xticks(np.arange(N) + 0.5, [f"cell {i}" for i in range(N)] if ax is axes[-1] else [])
    ax.set_title(
        f"corner c = {corner}, offset o = {offset} (orange: cleared, now new voxels)", fontsize=9
    )
plt.tight_layout()
plt.show()

# The package's TsdfVolume indexes the same way: its `cells` maps a logical box to array cells.
toy = tsdf.make_volume(with_overrides(Config(), {"volume.resolution": N}).volume, np.eye(4))
toy.offset[:] = (offset, 0, 0)
cells_of_logical = toy.cells((0, 0, 0), (N, 1, 1))[0].ravel()
np.testing.assert_array_equal(cells_of_logical, (np.arange(N) + offset) % N)
print("logical voxel -> array cell:", dict(enumerate(cells_of_logical.tolist())))

# %% [markdown]
# ## When to shift, and how far
#
# The paper's Fig. 2 has four steps: (i) the camera's motion exceeds a movement threshold,
# (ii) the slice of the volume that leaves is raycast for its surface points and reset,
# (iii) the points are triangulated, (iv) the new region enters the volume. The paper gives no
# value for the threshold. The package follows a point fixed in the first camera's frame (with
# the default placement "ahead", the point half a volume in front of the camera, so a camera
# that turns drags the volume to where it looks); when that point is at least
# `shift_threshold` voxels (default 14; 1 to 16 allowed, docs/parameters.md) from the centre on
# any axis, the window shifts by the rounded displacement on every axis, each clamped to the
# threshold:

# %%
print(inspect.getsource(moving_volume.shift_for))
print(inspect.getsource(moving_volume.MovingVolume.shift_axis))
assert Config().volume.shift_threshold == 14 and Config().volume.min_extract_weight == 8

# %% [markdown]
# **Extraction.** The leaving slab is triangulated by marching cubes *together with the first
# staying layer*, since the cubes straddling the boundary belong to neither side otherwise. Each
# cube is then triangulated exactly once over the whole run, and each vertex is named by the grid
# edge it lies on (global voxel + axis), so neighbouring slices share their seam vertices
# exactly. (The paper extracts the slab's surface points and triangulates them by greedy
# projection; marching cubes closes the seams by construction. docs/moving_volume.md describes
# the difference.) Vertices whose voxels were seen fewer than 8 times are dropped
# (`volume.min_extract_weight`; fewer while fewer frames have been fused).
#
# ## A walk down the corridor
#
# Five seconds of the synthetic corridor (walking 0.35 m/s along the world's $x$ axis, looking
# 30 degrees towards the wall at $y$ = 1.1 m), fused at the true poses by `pipeline.run` into a
# 96^3 volume of 2 m (2.1 cm voxels) with the default shift threshold of 14 voxels (29 cm).
# Slices stay in memory here (`kintinuous reconstruct` writes them to disk as they leave).
# The volume, 2 m high around the camera, holds the wall but not the floor or the ceiling.

# %%
config = with_overrides(Config(), {"volume.resolution": 96, "volume.size": 2.0})
scene = make_scenario("corridor", frames=FRAMES, width=WIDTH, height=HEIGHT, seed=0, noise=True)
seconds = scene.trajectory.timestamps[-1] - scene.trajectory.timestamps[0]
speed = np.ptp(scene.trajectory.positions[:, 0]) / seconds  # along the corridor
print(
    f"{seconds:.1f} s at {speed:.2f} m/s; voxel {100 * config.volume.voxel_size:.1f} cm, "
    f"threshold {config.volume.shift_threshold} voxels = "
    f"{100 * config.volume.shift_threshold * config.volume.voxel_size:.0f} cm"
)
assert round(seconds) == 5 and round(speed, 2) == 0.35  # five seconds, walking 0.35 m/s
assert round(100 * config.volume.voxel_size, 1) == 2.1 and config.volume.shift_threshold == 14
assert round(100 * config.volume.shift_threshold * config.volume.voxel_size) == 29
frames = [Frame(i, float(scene.trajectory.timestamps[i]), *scene.render(i)) for i in range(FRAMES)]
moving_run = pipeline.run(frames, scene.camera, config, groundtruth=scene.trajectory)
moving = moving_run.moving
origins = np.array(moving_run.volume_origins)
# the corridor's floor is at z = 0 and its ceiling at 2.6 m: the window spans neither
assert origins[:, 2].min() > 0.0 and origins[:, 2].max() + config.volume.size < 2.6
print(
    f"{moving.shifts} shifts over {FRAMES} frames, {moving.store.count} slices so far; "
    f"volume memory {moving_run.volume.tsdf.nbytes / 2**20:.1f} MiB of TSDF, unchanged"
)
moving.finish()  # the rest of the window becomes the last slice
slices = list(moving.store)
print(
    f"{len(slices)} slices with the final one; triangles per slice:",
    [len(s.triangles) for s in slices],
)
# One slice per axis that moved (a shift can move several); a slab with no surface, none.
assert moving.shifts >= 3 and len(slices) >= moving.shifts

# %% [markdown]
# The slices on the wall, seen from inside the corridor (an elevation: along the corridor against
# height), with the camera path. Each slice that left the window at a shift has its own colour
# and number; the last slice, what was still in the window at the end, is drawn in light grey
# beneath them, since it is by far the largest and would hide the others. The dashed squares
# are the window at the start and after each shift. On the right, the triangles in each
# slice. The first shifts carry little: the camera looks ahead along the corridor, so the wall
# it has seen leaves the window only some shifts later; a shift along an axis where no surface
# leaves yields no slice.

# %%
fig, (ax, bars) = plt.subplots(1, 2, figsize=(14, 4.5), gridspec_kw={"width_ratios": [3, 1]})
left = slices[:-1]  # the slices that left at shifts; slices[-1] is the window at the end
colours = plt.get_cmap("tab20", max(len(left), 1))
remainder = slices[-1].points
ax.plot(remainder[:, 0], remainder[:, 2], ".", ms=1, color="0.85", label="last slice (the end)")
for number, piece in enumerate(left):
    ax.plot(
        piece.points[:, 0], piece.points[:, 2], ".", ms=2, color=colours(number),
        label=f"slice {number}",
    )  # fmt: skip
    if len(piece.points):
        middle = np.median(piece.points[:, [0, 2]], axis=0)
        ax.annotate(str(number), middle, fontsize=9, weight="bold", ha="center")
size = config.volume.size
shift_frames = np.flatnonzero(np.any(np.diff(origins, axis=0) != 0, axis=1)) + 1
for index in np.r_[0, shift_frames]:
    lo = origins[index] - config.volume.voxel_size / 2
    ax.add_patch(Rectangle(lo[[0, 2]], size, size, fill=False, ls="--", ec="grey", lw=0.7))
positions = scene.trajectory.positions
ax.plot(positions[:, 0], positions[:, 2], "k-", lw=2, label="camera")
ax.set_aspect("equal")
ax.set_xlabel("x (m), along the corridor")
ax.set_ylabel("z (m), height")
ax.set_title("slices leaving the moving volume (dashed: the window at each shift)")
ax.legend(markerscale=6, fontsize=7, loc="upper left", bbox_to_anchor=(0, -0.15), ncols=6)
triangles = [len(piece.triangles) for piece in slices]
bars.bar(range(len(slices)), triangles, color=[*map(colours, range(len(left))), "0.7"])
bars.set_yscale("log")
bars.set_xlabel("slice (last: the end)")
bars.set_ylabel("triangles")
plt.show()
print(f"{len(shift_frames)} frames shifted the window, at frames {shift_frames.tolist()}")
assert triangles[-1] > max(triangles[:-1])  # the window at the end holds the most
assert max(triangles[:3]) < 0.1 * max(triangles[:-1])  # the first slices carry little

# %% [markdown]
# ## One mesh from the slices, and what a fixed volume keeps
#
# `moving_volume.assemble` streams the slices into one PLY, merging seam vertices that share a
# key. The merged mesh is checked against the true surface of the scene (mean distance of its
# vertices), and compared with the same frames fused into a **fixed** volume of the same size
# and resolution (`volume.moving = False`): KinectFusion's map, which ends at the volume's faces.

# %%
with tempfile.TemporaryDirectory() as folder:
    path = Path(folder) / "mesh.ply"
    vertex_count, triangle_count = moving_volume.assemble(moving.store, path)
    merged = moving_volume.read_mesh(path)
slice_vertices = sum(len(s.points) for s in slices)
print(
    f"merged mesh: {vertex_count} vertices ({slice_vertices - vertex_count} seam vertices "
    f"shared by two slices), {triangle_count} triangles"
)
assert slice_vertices > vertex_count  # seam vertices merged
assert len(np.unique(merged.points, axis=0)) == vertex_count  # none left doubled at a seam

fixed_config = with_overrides(config, {"volume.moving": False})
fixed_run = pipeline.run(frames, scene.camera, fixed_config, groundtruth=scene.trajectory)
fixed = mesh.extract_mesh(fixed_run.volume)
np.testing.assert_array_equal(fixed_run.volume.tsdf.shape, moving_run.volume.tsdf.shape)

truth = scene.surface_mesh(spacing=0.05)
mean_distance = {}
for name, surface in (("moving", merged), ("fixed", fixed)):
    distance = mesh.closest_on(truth, surface.points.astype(np.float64))[0]
    mean_distance[name] = distance.mean()
    extent = surface.points[:, 0].min(), surface.points[:, 0].max()
    print(
        f"{name:6s}: {len(surface.points):6d} vertices, x from {extent[0]:.2f} to "
        f"{extent[1]:.2f} m, mean distance to the true surface {1000 * distance.mean():.1f} mm"
    )
assert merged.points[:, 0].max() > fixed.points[:, 0].max() + 0.3
assert merged.points[:, 0].min() < fixed.points[:, 0].min() + 0.05  # and loses no start
assert len(merged.points) > len(fixed.points)
assert max(mean_distance.values()) < 1e-3  # both within a millimetre of the truth
assert abs(mean_distance["moving"] - mean_distance["fixed"]) < 0.25e-3  # a fraction of a mm

fig, axes = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
for ax, (name, surface) in zip(
    axes, (("moving volume", merged), ("fixed volume", fixed)), strict=True
):
    ax.scatter(surface.points[:, 0], surface.points[:, 2], c=surface.colours / 255, s=1)
    ax.plot(positions[:, 0], positions[:, 2], "k-", lw=2)
    ax.set_aspect("equal")
    ax.set_ylabel("z (m)")
    ax.set_title(f"{name}: the wall in its fused colours (black line: camera path)")
axes[-1].set_xlabel("x (m), along the corridor")
plt.tight_layout()
plt.show()

# %% [markdown]
# The fixed volume keeps only what lies inside the first window; the moving volume keeps the
# wall the whole walk saw (from the same start, more than 30 cm further along), with the same
# memory. Both surfaces sit within a millimetre of the truth on average over their vertices,
# and within a quarter of a millimetre of each other (printed above; the moving one over a
# longer stretch of wall): extracting by slices keeps the fixed volume's accuracy.

# %% [markdown]
# ## Real data: a moving volume over real frames
#
# Every tenth of the course's 300 real frames (ten seconds), at 160x120 and at their
# ground-truth poses, into a small moving volume (1.5 m, 64^3) with the fast backend, so that
# the walk makes it shift. The slices that left it, projected on the world's x-y plane, with the
# camera's path. The frames come from the course's one loader, `load_course_data()`
# (notebooks/README.md): the shared 7-Scenes redkitchen frames (the camera travelling about
# 0.9 m), or a TUM RGB-D sequence you have; without either the cell prints one line and skips.
# On any sequence the volume yields at most one slice per shift plus the final one; that
# redkitchen's walk shifts it at least twice, and that surface leaves with the shifts, is
# asserted there.

# %%
# $KINTINUOUS_COURSE_DATA, else the shared redkitchen, else a downloaded TUM sequence
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    import kintinuous_fast

    real_camera = REAL.camera_at(WIDTH, HEIGHT)
    real_truth = REAL.groundtruth
    real_frames = REAL.frames(range(0, len(REAL), 10), WIDTH, HEIGHT)
    real_config = with_overrides(config, {"volume.resolution": 64, "volume.size": 1.5})
    real_run = pipeline.run(
        real_frames, real_camera, real_config, groundtruth=real_truth,
        backend=kintinuous_fast.load_backend("cpu"),
    )  # fmt: skip
    real_moving = real_run.moving
    real_moving.finish()
    real_slices = list(real_moving.store)
    travelled = np.ptp(real_truth.positions, axis=0)
    print(
        f"{len(real_frames)} frames, camera box {np.round(travelled, 2)} m: "
        f"{real_moving.shifts} shifts, {len(real_slices)} slices with the final one"
    )
    plt.figure(figsize=(7, 5))
    real_colours = plt.get_cmap("tab20", len(real_slices))
    for number, piece in enumerate(real_slices):
        plt.plot(piece.points[:, 0], piece.points[:, 1], ".", ms=1, color=real_colours(number))
    plt.plot(*real_truth.positions[:, :2].T, "k-", lw=2, label="camera")
    plt.gca().set_aspect("equal")
    plt.xlabel("x (m)")
    plt.ylabel("y (m)")
    plt.title(f"{REAL.name}: slices of the moving volume (one colour each), world x-y")
    plt.legend()
    plt.show()
    # A shift along an axis where no surface leaves yields no slice; the final one always does.
    assert 1 <= len(real_slices) <= real_moving.shifts + 1  # any sequence
    if REAL.is_redkitchen:
        assert real_moving.shifts >= 2  # the 1.5 m window had to follow the camera
        assert 0.85 < travelled.max() < 0.95  # "about 0.9 m"
        assert len(real_slices) >= 2
        assert sum(len(piece.triangles) for piece in real_slices[:-1]) > 0  # surface left it

# %% [markdown]
# ## Summary
#
# - The volume is a ring buffer: logical voxel $\mathbf{l}$ lives in cell
#   $(\mathbf{l} + \mathbf{o}) \bmod N$; a shift changes the corner and the offset and moves no
#   data.
# - It shifts when the followed point is `shift_threshold` voxels from the volume's centre; the
#   leaving slab (plus one overlapping layer) is meshed as a slice, then cleared, and the same
#   cells hold the entering voxels.
# - Slices carry the grid edge of every vertex, so merging them joins the seams exactly.
# - Over five seconds of corridor the moving volume keeps the whole walk; a fixed volume of
#   the same memory keeps only its first window.
#
# ## Exercises
#
# 1. **The threshold.** Rerun the corridor with `volume.shift_threshold` 4 and 16. How many
#    shifts and slices does each make, and why does a small threshold cost more (think of the
#    extraction per shift)? Check: `check_exercise_1(threshold, your_shift_count)` reruns it.
# 2. **Ring arithmetic.** In the toy volume ($N = 8$), after shifts of +3, +3 and -5, which
#    array cell holds logical voxel 0, and which global voxel does it hold? Check:
#    `check_exercise_2(cell, global_voxel)`.
# 3. **Placement.** Set `volume.placement` to `"centred"` (the camera at the volume's centre)
#    and compare the fraction of the volume in front of the camera: what does each placement
#    waste? (The paper does not say where in the volume the camera sits; it says only that the
#    volume shifts once the camera has moved past a threshold, Fig. 2. docs/moving_volume.md
#    explains why the package follows a point ahead of the camera by default.)


# Your answers go into the next cell (`None` until you have them); the check cell compares them
# with a rerun of the corridor (exercise 1) and with the package's own ring indexing (exercise
# 2), and says what is still open.

# %%
your_threshold, your_shift_count = None, None  # exercise 1: a threshold and its shift count
your_cell, your_global_voxel = None, None  # exercise 2


# %%
def check_exercise_1(threshold: int | None, shifts: int | None) -> None:
    if threshold is None or shifts is None:
        print("exercise 1: not answered yet (fill in your_threshold and your_shift_count above)")
        return
    trial = with_overrides(config, {"volume.shift_threshold": threshold})
    run = pipeline.run(frames, scene.camera, trial, groundtruth=scene.trajectory)
    assert shifts == run.moving.shifts, f"not the number of shifts at threshold {threshold}"
    print("exercise 1 correct")


def check_exercise_2(cell: int | None, global_voxel: int | None) -> None:
    if cell is None or global_voxel is None:
        print("exercise 2: not answered yet (fill in your_cell and your_global_voxel above)")
        return
    # The truth from the package's volume: its offset after the three shifts, and its cells.
    ring = tsdf.make_volume(with_overrides(Config(), {"volume.resolution": N}).volume, np.eye(4))
    corner = 0
    for shift in (3, 3, -5):
        corner += shift
        ring.offset[0] = (ring.offset[0] + shift) % N
    assert cell == ring.cells((0, 0, 0), (1, 1, 1))[0].item(), "cell = (l + o) mod N for l = 0"
    assert global_voxel == corner, "global = corner + logical"
    print("exercise 2 correct")


check_exercise_1(your_threshold, your_shift_count)
check_exercise_2(your_cell, your_global_voxel)
