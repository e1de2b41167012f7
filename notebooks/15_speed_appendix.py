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
#   kintinuous:
#     runs_alone: true
# ---

# %% [markdown]
# # 15. Appendix: every speed measurement of the course, and Tables V-VI measured here
#
# The other lessons check what the code computes; this one measures how long it takes. It
# gathers the course's timings in one place:
#
# 1. the volume's two kernels, reference against `kintinuous_fast` (lesson 1), and how their
#    times grow with the size of the work,
# 2. one tracked frame pair: RGB-D (lesson 3) and ICP+RGB-D (lesson 6), and the depth + colour
#    integration (lesson 9),
# 3. the paper's Tables V and VI measured here: per odometry configuration, the tracker's time
#    per frame and the whole pipeline's, for the reference, the CPU backend and, where a GPU is
#    present, the CUDA backend, beside the paper's published values (quoted),
# 4. the pipeline on real frames.
#
# **How to read a timing.** Every timing runs its function once untimed first (in a fresh
# environment the first call compiles the numba kernels, once; numba caches them on disk), then
# gives the median and the interquartile range [25th-75th percentile] of several runs, with the
# machine and numba's thread count (`kintinuous_ref.program.benchmark`: `timed`, `speed_line`,
# `machine_line`). On a shared machine the same cell's numbers vary from run to run, sometimes by
# an order of magnitude, so the text below quotes no timing: the cells print them, and assert
# only relations measured in the same run that hold by a wide margin.
#
# Prerequisites: the lessons whose code is timed (1, 3, 6, 9; 8 for the seven trackers). Its
# time, warm, is in notebooks/README.md's table; the images are 160x120 or smaller, so the
# numbers say how the code scales on this machine, not what a 640x480 Kinect stream costs.

# %%
# %matplotlib inline
import functools

import matplotlib.pyplot as plt
import numpy as np

import kintinuous_fast
import kintinuous_ref.odometry as reference_odometry
from kintinuous_ref import colour, pipeline, preprocess, raycast, tsdf
from kintinuous_ref.backend import BackendUnavailable, load_backend
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import Frame
from kintinuous_ref.odometry import make_tracker
from kintinuous_ref.odometry.solve import refine
from kintinuous_ref.program.benchmark import machine_line, speed_line, timed
from kintinuous_ref.program.evaluation import paper
from kintinuous_ref.program.evaluation.runs import timing_statistics
from kintinuous_ref.vocabulary import METHODS

WIDTH, HEIGHT = 160, 120
config = with_overrides(Config(), {"volume.resolution": 128, "volume.size": 3.0})
scenario = make_scenario("desk", frames=30, width=WIDTH, height=HEIGHT, seed=0, noise=True)
camera, poses = scenario.camera, scenario.trajectory.poses
fast = kintinuous_fast.load_backend("cpu")
frames = {
    index: preprocess.preprocess_frame(*scenario.render(index), camera, config.preprocess)
    for index in range(0, 12, 2)
}
print(machine_line())

# %% [markdown]
# ## The volume: integrate and raycast (lesson 1)
#
# Fuse the six frames into both backends' volumes, then time one more integration and one
# raycast of the model, reference (NumPy) against fast (numba, compiled loops).

# %%
volume = tsdf.make_volume(config.volume, poses[0])
fast_volume = fast.tsdf.make_volume(config.volume, poses[0])
for index, frame in frames.items():
    tsdf.integrate(volume, frame.depth, poses[index], camera)
    fast.tsdf.integrate(fast_volume, frame.depth, poses[index], camera)
frame, pose = frames[10], poses[10]
integrate_times = (
    timed(lambda: tsdf.integrate(volume, frame.depth, pose, camera), 3),
    timed(lambda: fast.tsdf.integrate(fast_volume, frame.depth, pose, camera), 5),
)
raycast_times = (
    timed(lambda: raycast.raycast(volume, pose, camera), 3),
    timed(lambda: fast.raycast.raycast(fast_volume, pose, camera), 5),
)
print(speed_line("integrate, 128^3", *integrate_times))
print(speed_line(f"raycast, {WIDTH}x{HEIGHT}", *raycast_times))

# %% [markdown]
# **How it scales.** The same two operations at smaller sizes (as the Triton tutorials sweep
# theirs): integration over volumes of 32^3 and 64^3 voxels and the raycast over images of
# 40x30 and 80x60 (three runs each), beside the 128^3 and 160x120 timings above. How the
# speed-up changes with the size depends on the machine and its load (a fixed overhead per call
# weighs more on small calls, the memory traffic on large ones); the cell asserts only that the
# compiled loops are faster at the largest size of each operation.

# %%
sweep_rows = []
for resolution in (32, 64):
    sized = with_overrides(config, {"volume.resolution": resolution}).volume
    reference_volume = tsdf.make_volume(sized, poses[0])
    compiled_volume = fast.tsdf.make_volume(sized, poses[0])
    sweep_rows.append((
        "integrate", f"{resolution}^3", resolution**3,
        timed(functools.partial(tsdf.integrate, reference_volume, frame.depth, pose, camera), 3),
        timed(functools.partial(fast.tsdf.integrate, compiled_volume, frame.depth, pose, camera),
              3),
    ))  # fmt: skip
for width in (40, 80):
    sized_camera = camera.resized(width, width * 3 // 4)
    sweep_rows.append((
        "raycast", f"{width}x{width * 3 // 4}", width * width * 3 // 4,
        timed(functools.partial(raycast.raycast, volume, pose, sized_camera), 3),
        timed(functools.partial(fast.raycast.raycast, fast_volume, pose, sized_camera), 3),
    ))  # fmt: skip
sweep_rows.append(("integrate", f"{config.volume.resolution}^3", config.volume.resolution**3,
                   *integrate_times))  # fmt: skip
sweep_rows.append(("raycast", f"{WIDTH}x{HEIGHT}", WIDTH * HEIGHT, *raycast_times))
fig, axes = plt.subplots(1, 2, figsize=(12, 3.6))
for ax, stage, unit in zip(axes, ("integrate", "raycast"), ("voxels", "pixels"), strict=True):
    rows = [row for row in sweep_rows if row[0] == stage]
    sizes = [row[2] for row in rows]
    for column, label in ((3, "reference (NumPy)"), (4, "fast (numba cpu)")):
        quartiles = np.array([1000 * np.percentile(row[column], [25, 50, 75]) for row in rows])
        ax.loglog(sizes, quartiles[:, 1], "o-", label=label)
        ax.fill_between(sizes, quartiles[:, 0], quartiles[:, 2], alpha=0.3)
    ax.set_xlabel(unit)
    ax.set_ylabel("ms per call (median, IQR shaded)")
    ax.set_title(stage)
    ax.legend()
plt.show()
for stage, size, _, reference_times, fast_times in sweep_rows:
    print(speed_line(f"{stage:9s} {size:8s}", reference_times, fast_times))
for stage in ("integrate", "raycast"):
    largest = max((row for row in sweep_rows if row[0] == stage), key=lambda row: row[2])
    assert np.median(largest[3]) > np.median(largest[4]), stage  # the compiled loops win

# %% [markdown]
# ## Tracking one frame pair (lessons 3 and 6), and colour fusion (lesson 9)
#
# One RGB-D track (all pyramid levels, up to 31 Gauss-Newton steps), one ICP+RGB-D track against
# the model raycast from the fused volume, both from the previous frame's true pose, and one
# integration with colour (the angle weights of eq. 15 and the discontinuity check).

# %%
previous, current = frames[8], frames[10]
model = raycast.raycast(volume, poses[8], camera)
fast_odometry = fast.odometry


def rgbd_track(module: object) -> None:
    problem = module.RgbdProblem(previous.levels, current.levels, poses[8])
    refine(poses[8].copy(), problem.system, config.rgbd.iterations)


assert sum(config.rgbd.iterations) == 31  # the RGB-D track's steps at most, over all levels
reference_tracker = make_tracker("icp+rgbd", config, camera)
cpu_tracker = fast_odometry.make_tracker("icp+rgbd", config, camera)
reference_pose = reference_tracker.track(previous, current, model, poses[8]).pose
np.testing.assert_allclose(
    cpu_tracker.track(previous, current, model, poses[8]).pose, reference_pose, atol=1e-8
)
print(
    speed_line(
        f"RGB-D track of one pair, {WIDTH}x{HEIGHT}",
        timed(lambda: rgbd_track(reference_odometry), 3),
        timed(lambda: rgbd_track(fast_odometry)),
    )
)
print(
    speed_line(
        f"ICP+RGB-D track of one pair, {WIDTH}x{HEIGHT}",
        timed(lambda: reference_tracker.track(previous, current, model, poses[8]), 3),
        timed(lambda: cpu_tracker.track(previous, current, model, poses[8])),
    )
)
colour_frame = scenario.render(10)
fused = preprocess.preprocess_frame(*colour_frame, camera, config.preprocess)
weights = colour.colour_weights(fused, config.colour)
print(
    speed_line(
        "depth + colour integration of one frame, 128^3",
        timed(lambda: tsdf.integrate(volume, fused.depth, pose, camera, fused.colour, weights), 3),
        timed(
            lambda: fast.tsdf.integrate(
                fast_volume, fused.depth, pose, camera, fused.colour, weights
            )
        ),
    )
)

# %% [markdown]
# ## Tables V and VI, measured here
#
# The paper times each odometry configuration on fr1/room at 640x480 with an Intel Core
# i7-3960X and an nVidia GeForce GTX 680: Table V the tracker alone, Table VI the whole
# pipeline, in milliseconds per frame (average, minimum, maximum, standard deviation). Here the
# same per-frame statistics (and the median) come from `pipeline.run`'s own per-stage clocks
# (`timings_ms["odometry"]` and `timings_ms["total"]`), over the frames after the first (which
# is placed, not tracked), on the synthetic desk at 120x90 with a 64^3 volume, for each backend
# that runs here. With a compiled backend each configuration is run once over two frames untimed
# first (the kernels load or compile), then timed. The reference, which compiles nothing, is
# timed over three frames only: it is the readable NumPy specification, not a fast path. The
# table also counts each run's failed frames, since a failed frame is not fused and costs less.

# %%
table_config = with_overrides(Config(), {"volume.resolution": 64, "volume.size": 3.0})
table_scene = make_scenario("desk", frames=9, width=120, height=90, seed=0, noise=True)
assert round(640 * 480 / (120 * 90)) == 28  # "a twenty-eighth of their pixels"
desk_frames = [
    Frame(i, float(table_scene.trajectory.timestamps[i]), *table_scene.render(i)) for i in range(9)
]
backends = {"ref": 4, "cpu": 9, "cuda": 9}  # frames per run (the first is not timed)
available = {}
for name in backends:
    try:
        backend = load_backend(name)
    except BackendUnavailable as reason:
        print(f"{name}: skipped ({reason})")
        continue
    if getattr(backend, "note", ""):  # the CUDA simulator is not a GPU: its times mean nothing
        print(f"{name}: skipped ({backend.note})")
        continue
    available[name] = backend


def time_configuration(backend: object, method: str, count: int) -> tuple[dict, dict, int]:
    """(tracker statistics, pipeline statistics) in ms per frame over frames 2..count, and the
    run's failed frames."""
    arguments = (table_scene.camera, table_config, method, table_scene.trajectory, backend)
    if backend.name != "ref":
        pipeline.run(desk_frames[:2], *arguments)
    run = pipeline.run(desk_frames[:count], *arguments)
    statistics = []
    for stage in ("odometry", "total"):
        values = run.timings_ms[stage][1:]
        statistics.append({**timing_statistics(values), "median": float(np.median(values))})
    return statistics[0], statistics[1], run.tracking_failures


measured = {}
for name, backend in available.items():
    for method in METHODS:
        measured[name, method] = time_configuration(backend, method, backends[name])


def print_table(number: str, position: int, quoted: dict) -> None:
    """One of Tables V (position 0: the tracker) or VI (1: the pipeline), ours and the paper's."""
    title = "tracker alone" if position == 0 else "full pipeline"
    print(f"Table {number} ({title}), ms per frame; paper: quoted from Whelan et al. 2013")
    header = f"{'method':15s} {'backend':8s} " + " ".join(
        f"{column:>8s}" for column in ("avg", "median", "min", "max", "std", "failed")
    )
    print(header)
    for method in METHODS:
        for name in available:
            stats = measured[name, method][position]
            print(f"{method:15s} {name:8s} " + " ".join(
                f"{stats[column]:8.1f}" for column in ("avg", "median", "min", "max", "std")
            ) + f" {measured[name, method][2]:8d}")  # fmt: skip
        avg, low, high, std = quoted[method]
        print(f"{method:15s} {'paper':8s} {avg:8.2f} {'-':>8s} {low:8.2f} {high:8.2f} {std:8.3f}")


print(machine_line())
print_table("V", 0, paper.TRACKER_MS)
print()
print_table("VI", 1, paper.PIPELINE_MS)

# %% [markdown]
# The medians side by side, on a logarithmic axis (so that every backend fits), with the
# paper's averages (quoted) for reference. The paper's GPU ran 640x480 frames; ours have 120x90,
# a twenty-eighth of their pixels, so only the shape of the chart compares: which
# configurations cost more than which.

# %%
fig, axes = plt.subplots(1, 2, figsize=(14, 4), sharey=True)
positions = np.arange(len(METHODS))
bars = [*available, "paper (quoted)"]
width = 0.8 / len(bars)
for ax, position, quoted, title in (
    (axes[0], 0, paper.TRACKER_MS, "Table V: tracker"),
    (axes[1], 1, paper.PIPELINE_MS, "Table VI: full pipeline"),
):
    for offset, name in enumerate(bars):
        if name in available:
            values = [measured[name, method][position]["median"] for method in METHODS]
        else:
            values = [quoted[method][0] for method in METHODS]
        ax.bar(positions + (offset - (len(bars) - 1) / 2) * width, values, width, label=name)
    ax.set_yscale("log")
    ax.set_xticks(positions, METHODS, rotation=30, ha="right")
    ax.set_title(title)
    ax.legend(fontsize=8)
axes[0].set_ylabel("ms per frame (ours: median; paper: average)")
plt.tight_layout()
plt.show()

# %% [markdown]
# What these runs say, on the machine that ran them (the relations below are asserted in the
# next cell, measured in the same run; the numbers themselves are only printed):
#
# - the CPU backend's pipeline is faster than the reference's for every configuration,
# - with a compiled backend (medians over eight frames; the reference's three are too
#   noisy for any ranking), a `fovis/X` configuration's tracker takes longer than `X`'s alone,
#   since the switch runs FOVIS *and* `X` on every frame; the paper's Table V (quoted) has each
#   `fovis/X` above its `X` too, though its `fovis/icp` averages less than its `fovis` alone,
# - the pipeline's time per frame is at least the tracker's, which it contains,
# - and, from the paper's tables (quoted): every configuration's tracker stays under the 33 ms
#   of the sensor's 30 Hz even at its maximum (Table V), and on average every configuration
#   but FOVIS/ICP+RGB-D runs the full pipeline within them (Table VI), as VII-C says.

# %%
for method in METHODS:
    if "ref" in available and "cpu" in available:
        assert measured["cpu", method][1]["median"] < measured["ref", method][1]["median"], method
    for name in available:
        tracker, whole, _ = measured[name, method]
        assert whole["min"] >= tracker["min"] and whole["avg"] >= tracker["avg"]
SWITCHED = [method for method in METHODS if method.startswith("fovis/")]
for name in (name for name in available if name != "ref"):  # medians of 8 timed frames
    median = {method: measured[name, method][0]["median"] for method in METHODS}
    for switched in SWITCHED:
        assert median[switched] > median[switched.removeprefix("fovis/")]
quoted_average = {method: paper.TRACKER_MS[method][0] for method in METHODS}
assert all(quoted_average[m] > quoted_average[m.removeprefix("fovis/")] for m in SWITCHED)
assert quoted_average["icp+rgbd"] > max(quoted_average["icp"], quoted_average["rgbd"])
below_fovis = [m for m in SWITCHED if quoted_average[m] < quoted_average["fovis"]]
print("paper (quoted): switched trackers averaging less than FOVIS alone:", below_fovis)
assert below_fovis == ["fovis/icp"]
frame_ms = 1000 / 30  # the sensor's frame period
assert max(paper.TRACKER_MS[m][2] for m in METHODS) < frame_ms  # Table V's maxima
slower = [m for m in METHODS if paper.PIPELINE_MS[m][0] > frame_ms]  # Table VI's averages
print("paper (quoted): pipelines averaging more than a 30 Hz frame:", slower)
assert slower == ["fovis/icp+rgbd"]

# %% [markdown]
# ## Real frames (optional)
#
# The pipeline on real frames (downsized to 160x120, 4 m volume), the paper's tracker
# (`icp+rgbd`) on the CPU backend: 12 frames from frame 100, the same statistics. The frames
# come from the course's one loader, `load_course_data()` (notebooks/README.md): the shared
# 7-Scenes redkitchen frames, or a TUM RGB-D sequence you have; without either the cell prints
# one line and skips. Timings vary with the machine, so on any sequence the cell checks only
# that the median total is at least the median of its longest stage.

# %%
# $KINTINUOUS_COURSE_DATA, else the shared redkitchen, else a downloaded TUM sequence
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    small = REAL.camera_at(WIDTH, HEIGHT)
    real_config = with_overrides(table_config, {"volume.size": 4.0})
    real_frames = REAL.frames(range(100, 112), WIDTH, HEIGHT)
    truth = REAL.groundtruth
    real_run = pipeline.run(real_frames, small, real_config, "icp+rgbd", truth, fast)
    stages = [stage for stage, values in real_run.timings_ms.items() if len(values) > 1]
    medians = {stage: float(np.median(real_run.timings_ms[stage][1:])) for stage in stages}
    print(machine_line())
    for stage in stages:
        stats = timing_statistics(real_run.timings_ms[stage][1:])
        print(
            f"{REAL.name}, cpu, icp+rgbd: {stage:12s} avg {stats['avg']:7.1f}  median "
            f"{medians[stage]:7.1f}  min {stats['min']:7.1f}  max {stats['max']:7.1f} ms"
        )
    shown = [stage for stage in stages if stage != "total"]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.barh(shown, [medians[stage] for stage in shown])
    ax.set_xlabel("median ms per frame")
    ax.set_title(f"{REAL.name} 160x120, cpu backend, icp+rgbd: where a frame's time goes")
    plt.tight_layout()
    plt.show()
    assert medians["total"] >= max(medians[stage] for stage in shown)

# %% [markdown]
# ## Summary
#
# - A timing means little without its spread, its machine and its thread count; every cell
#   above prints all three, and the first call (which compiles or loads the kernels) is never
#   timed.
# - The compiled loops are faster than NumPy at the largest sizes swept; how the ratio moves
#   with the size is the machine's (the size sweep).
# - In Table V measured here a switched tracker costs more than its dense tracker, as in the
#   paper's Table V (quoted), where the joint ICP+RGB-D also costs more than ICP or RGB-D
#   alone. Absolute numbers depend on the machine, the image size and the backend.
#
# ## Exercises
#
# 1. **Threads.** Restart the kernel with `NUMBA_NUM_THREADS=2` (or more on your machine) and
#    rerun the size sweep: which operation gains most from the second thread?
# 2. **Image size.** Rerun Tables V-VI at 320x240 (`make_scenario(..., width=320, height=240)`)
#    for the CPU backend. How does the tracker's share of the pipeline change?
# 3. **Your machine.** Compute the ratio of the median ICP+RGB-D pipeline time to the median ICP
#    pipeline time for the CPU backend from `measured`, and put it in `your_ratio`; the check
#    compares it with the table above.

# Your answer goes into the next cell (`None` until you have it); the check cell computes its
# own value from this run and does not print it.

# %%
your_ratio = None  # exercise 3: median total ms of icp+rgbd / icp, cpu backend


# %%
def check_exercise_3(ratio: float | None) -> None:
    if ratio is None:
        print("exercise 3: not answered yet (fill in your_ratio)")
        return
    if "cpu" not in available:
        print("exercise 3: the cpu backend did not run here")
        return
    truth = measured["cpu", "icp+rgbd"][1]["median"] / measured["cpu", "icp"][1]["median"]
    assert abs(ratio - truth) < 1e-6 * truth, "median total of icp+rgbd over that of icp"
    print("exercise 3 correct")


check_exercise_3(your_ratio)
