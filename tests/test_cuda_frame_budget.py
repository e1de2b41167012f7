"""What a tracked frame asks of the device on the cuda backend: the host waits for the GPU once
(the tracker's record), launches a fixed number of kernels, queues every upload on a stream
(none makes the host wait), and nothing image- or volume-sized crosses; the poses equal the
reference's, and the dense estimate run on the device equals the reference's steps over the
same kernels driven by the host (solve.refine), failures included.

The counts come from the counter `kintinuous benchmark --json` reports (pipeline traffic per
stage); an independent log of every array that crosses (test_fast_cuda_pipeline.Crossings,
which patches numba's copies) must agree with it.

Without a GPU the tests run in a child process with numba's CUDA simulator, scheduled by
tests/quick_simulator.py (the same kernels; blocks without barriers run thread after thread):
the budget is counted on the synthetic desk at 80x60, three tracked frames, with two pyramid
levels (ICP+RGB-D 2 + 1 iterations) and a 24^3 volume, in about 45 s on the 2-core machine
(numba's own scheduling took about four minutes for two frames at 40x30). The launch count is
stated as a formula of the levels and iterations (odometry_launches).

Tolerances: the tracked poses equal the reference backend's to 0.1 mm / 0.01 degree (as in
test_fast_cuda_pipeline.py); the device loop equals the host-driven loop to 1e-9 m and 1e-8 rad:
the two add the same block partials in another order and solve the same 6x6 system by Jacobi
rotations instead of LAPACK.
"""

import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_fast_cuda_pipeline import (
    CONFIG,
    Crossings,
    desk_frames,
    image_like,
    uploaded,
)

from kintinuous_fast import cuda_status, load_backend
from kintinuous_ref import pipeline, se3
from kintinuous_ref.backend import DeviceTraffic
from kintinuous_ref.config import TrackingConfig

TRACKED_FRAMES = 3
BUDGET_SIZE = (80, 60)  # width, height of the frames whose budget is counted


@pytest.fixture(scope="module")
def host_frames():
    """The desk's first two frames preprocessed by the reference (NumPy)."""
    from kintinuous_ref import preprocess

    desk, frames = desk_frames()
    return [
        preprocess.preprocess_frame(frame.colour, frame.depth, desk.camera, CONFIG.preprocess)
        for frame in frames
    ]


on_device = pytest.mark.skipif(
    bool(cuda_status()), reason="no CUDA GPU: runs in the simulator subprocess below"
)


@pytest.mark.skipif(not cuda_status(), reason="CUDA works here: the tests run in this process")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "not in_simulator")
def test_cuda_frame_budget_in_simulator(cuda_simulator):
    cuda_simulator()


def odometry_launches(iterations: tuple[int, ...]) -> int:
    """Kernels an ICP+RGB-D frame launches on the device (frame_on_device.py's sequence): begin,
    repeats, mode; the model pyramid's two maps per coarser level; per level with steps
    Algorithm 1's two kernels; per step ICP, correspond, rows and solve; at the finest level
    ICP, correspond and finish."""
    levels_with_steps = sum(1 for count in iterations if count > 0)
    model_pyramid = 2 * (len(iterations) - 1)
    return 3 + model_pyramid + 2 * levels_with_steps + 4 * sum(iterations) + 3


def test_odometry_launch_formula():
    # the desk's 2 + 1 steps: 3 + 2 + 4 + 12 + 3
    assert odometry_launches((2, 1)) == 24
    # the paper's 10 / 5 / 4 at three levels: 3 + 4 + 6 + 76 + 3
    assert odometry_launches((10, 5, 4)) == 92


@on_device
def test_cuda_frame_budget(monkeypatch):
    from kintinuous_fast.odometry.frame_on_device import STATE_SIZE
    from kintinuous_fast.targets.cuda import is_device

    frames_needed = TRACKED_FRAMES + 1
    desk, frames = desk_frames(frames_needed, BUDGET_SIZE)
    want = pipeline.run(
        frames, desk.camera, CONFIG, "icp+rgbd", desk.trajectory, backend=load_backend("ref")
    )
    crossings = Crossings(monkeypatch)
    frame_starts: list[int] = [len(crossings.log)]
    got = pipeline.run(
        frames,
        desk.camera,
        CONFIG,
        "icp+rgbd",
        desk.trajectory,
        backend=load_backend("cuda"),
        progress=lambda _: frame_starts.append(len(crossings.log)),
    )
    # tracked, and as the reference tracked
    assert got.fused == want.fused == [True] * frames_needed, got.failure_reasons
    for a, b in zip(got.poses, want.poses, strict=True):
        delta = se3.inverse(b) @ a
        assert np.linalg.norm(delta[:3, 3]) < 1e-4
        assert np.degrees(se3.rotation_angle(delta[:3, :3])) < 1e-2
    assert np.linalg.norm(got.poses[-1][:3, 3] - got.poses[0][:3, 3]) > 0.005  # a motion
    # one host wait a frame, the record; a fixed number of launches
    tracked = [got.traffic[stage][1:] for stage in ("odometry", "total")]
    for odometry, total in zip(*tracked, strict=True):
        launches = odometry_launches(CONFIG.rgbd.combined_iterations)
        assert odometry == DeviceTraffic(launches, 1, 8 * STATE_SIZE)
        assert total.host_waits == 1 and total.bytes_to_host == 8 * STATE_SIZE
    assert len({frame.launches for frame in tracked[1]}) == 1, tracked[1]
    # the counter agrees with every copy numba made
    for index in range(1, frames_needed):
        log = crossings.log[frame_starts[index] : frame_starts[index + 1]]
        downloads = [shape for direction, shape in log if direction != "up"]
        assert downloads == [(STATE_SIZE,)], log
        ups = [shape for direction, shape in log if direction == "up"]
        images = [shape for shape in ups if image_like(shape, BUDGET_SIZE)]
        width, height = BUDGET_SIZE
        assert sorted(images) == [(height, width), (height, width, 3)], images
    # and no upload of a tracked frame makes the host wait: each is queued on a stream (the
    # first tracked frame also makes the tracker's workspace, once for the run)
    for index in range(2, frames_needed):
        frame_log = range(frame_starts[index], frame_starts[index + 1])
        blocking = [crossings.log[i] for i in crossings.blocking if i in frame_log]
        assert blocking == [], (index, blocking)
    assert is_device(got.model.vertices) and is_device(got.model.normals)


def device_and_host_loop(frames: list, config, method: str = "icp+rgbd") -> tuple:
    """(pose, reason) of the tracker's estimate on the device and of the reference's steps over
    the same cuda systems (the host-driven loop), for the second frame against the first."""
    from kintinuous_fast.odometry import cuda as systems
    from kintinuous_ref.odometry import estimate_dense

    camera = frames[1].levels[0].camera
    tracker = systems.make_tracker(method, config, camera)
    previous, current = uploaded(frames[0]), uploaded(frames[1])
    model = FakeModel.of(frames[0])
    device = systems.estimate_dense(tracker, previous, current, model, np.eye(4))
    host = estimate_dense(tracker, previous, current, model, np.eye(4))
    return device, host


class FakeModel:
    """A model prediction made of the previous frame's own maps (on the device), posed at the
    identity: what ICP reads."""

    @staticmethod
    def of(frame):  # noqa: ANN001, ANN205
        from numba import cuda

        from kintinuous_ref.raycast import ModelPrediction

        level = frame.levels[0]
        return ModelPrediction(
            vertices=cuda.to_device(level.vertices),
            normals=cuda.to_device(level.normals),
            colours=None,
            pose=np.eye(4),
        )


def assert_same_estimate(device: tuple, host: tuple) -> None:
    assert device[1] == host[1]
    delta = se3.inverse(host[0]) @ device[0]
    assert np.linalg.norm(delta[:3, 3]) < 1e-9
    assert se3.rotation_angle(delta[:3, :3]) < 1e-8


@on_device
def test_device_loop_equals_host_loop_when_it_converges(host_frames):
    # a step of 1 "converges" at once: each level stops after its first step, on both loops
    tracking = TrackingConfig(min_correspondences=10, converged_step=1.0)
    quick = replace(CONFIG, tracking=tracking)
    device, host = device_and_host_loop(host_frames, quick)
    assert device[1] == "" and not np.allclose(device[0], np.eye(4))
    assert_same_estimate(device, host)


@on_device
def test_device_loop_fails_as_the_host_loop(host_frames):
    first, second = host_frames
    too_few = replace(CONFIG, tracking=TrackingConfig(min_correspondences=10**6))
    device, host = device_and_host_loop([first, second], too_few)
    assert device[1].startswith("level 1: too few correspondences (")
    assert_same_estimate(device, host)
    # both streams stale: no step runs
    device, host = device_and_host_loop([first, first], CONFIG)
    assert "repeat" in device[1]
    assert_same_estimate(device, host)
    # stale colour: ICP alone (its own system, its own inlier fraction)
    stale_colour = copy.copy(second)
    stale_colour.levels = [copy.copy(level) for level in second.levels]
    stale_colour.levels[0].intensity = first.levels[0].intensity
    quick = replace(CONFIG, tracking=TrackingConfig(min_correspondences=10, converged_step=1.0))
    device, host = device_and_host_loop([first, stale_colour], quick)
    assert device[1] == "" and not np.allclose(device[0], np.eye(4))
    assert_same_estimate(device, host)
