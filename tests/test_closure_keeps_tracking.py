"""After a loop closure, tracking keeps the moving volume and its coordinates: the corrections
make a running offset that takes its poses into corrected ones, and the map stays in the
tracker's coordinates until the deformation at the end (the authors' implementation;
`loop_closure.recentre_on_closure` off). Checked against the same run without the closure: the
tracking and the slices are the same bit for bit, the poses that run's moved by the offset.
And a run stopped inside a frame after the closer saw it still has one pose per frame."""

from __future__ import annotations

import numpy as np
import pytest

from kintinuous_ref import pipeline, se3
from kintinuous_ref.config import Config, LoopClosureConfig, VolumeConfig
from kintinuous_ref.datasets import synthetic
from kintinuous_ref.datasets.tum import Frame
from kintinuous_ref.loop_closure.closer import Closure, LoopCloser

FRAMES = 6
CLOSED_AT = 3  # the frame whose keyframe "closes a loop"
CORRECTION = se3.exp(np.array([0.02, -0.01, 0.03, 0.01, -0.02, 0.015]))


class ClosesOnce(LoopCloser):
    """A loop closer whose one loop, at CLOSED_AT, moves the camera by CORRECTION (the pose
    graph's answer stands in), recording the poses it is shown."""

    def observe(self, frame, pose, *rest, **keywords):  # noqa: ANN001, ANN002, ANN003, ANN201
        self.shown = [*getattr(self, "shown", []), np.array(pose)]
        if frame != CLOSED_AT:
            return None
        self.closures.append(Closure(frame, 1, 0, CORRECTION, 0.05))
        return CORRECTION


@pytest.fixture(scope="module")
def desk():
    scenario = synthetic.make_scenario("desk", frames=FRAMES, width=160, height=120)
    stamps = scenario.trajectory.timestamps
    return scenario, [Frame(i, float(stamps[i]), *scenario.render(i)) for i in range(FRAMES)]


def tracked(desk, closer: LoopCloser | None, config: Config) -> pipeline.PipelineResult:
    scenario, frames = desk
    result = pipeline.run(frames, scenario.camera, config, odometry="icp",
                          groundtruth=scenario.trajectory, loop_closer=closer)  # fmt: skip
    result.moving.finish()
    return result


def test_tracking_keeps_its_volume_and_the_map_moves_by_the_offset(desk):
    config = Config(volume=VolumeConfig(resolution=64, size=2.0),
                    loop_closure=LoopClosureConfig(recentre_on_closure=False))  # fmt: skip
    plain = tracked(desk, None, config)
    closer = ClosesOnce(config, desk[0].camera)
    closed = tracked(desk, closer, config)
    for i in range(FRAMES):
        moved = CORRECTION if i >= CLOSED_AT else np.eye(4)
        np.testing.assert_array_equal(closed.poses[i], moved @ plain.poses[i])
        shown = moved if i > CLOSED_AT else np.eye(4)  # the closing frame is shown uncorrected
        np.testing.assert_array_equal(closer.shown[i], shown @ plain.poses[i])
    np.testing.assert_array_equal(closed.volume.tsdf, plain.volume.tsdf)
    np.testing.assert_array_equal(closer.map_from_volume, CORRECTION)
    slices = list(plain.moving.store)
    assert len(slices) == len(list(closed.moving.store)) and len(slices[-1].points) > 500
    for before, after in zip(slices, closed.moving.store, strict=True):
        np.testing.assert_array_equal(after.points, before.points)
        np.testing.assert_array_equal(after.keys, before.keys)


def test_recentring_instead_empties_the_window_at_the_corrected_pose(desk):
    config = Config(volume=VolumeConfig(resolution=64, size=2.0),
                    loop_closure=LoopClosureConfig(recentre_on_closure=True))  # fmt: skip
    plain = tracked(desk, None, config)
    closed = tracked(desk, ClosesOnce(config, desk[0].camera), config)
    np.testing.assert_array_equal(closed.poses[CLOSED_AT], CORRECTION @ plain.poses[CLOSED_AT])
    np.testing.assert_array_equal(closed.loop_closer.map_from_volume, np.eye(4))
    # the window holds only what was fused after the closure
    assert closed.volume.weight.max() == FRAMES - CLOSED_AT
    assert plain.volume.weight.max() == FRAMES


class InterruptedAfterAClosure(LoopCloser):
    """A loop closer whose one loop (no keyframe, no graph) moves the camera by CORRECTION at
    CLOSED_AT, and a Ctrl-C two frames later, inside the frame, after it was observed."""

    def _add_keyframe(self, frame, pose, preprocessed):  # noqa: ANN001, ANN201
        if frame != CLOSED_AT:
            return None
        self.closures.append(Closure(frame, 1, 0, CORRECTION, 0.05))
        return CORRECTION

    def slice_made(self, frame: int, slices: int) -> None:
        if frame == CLOSED_AT + 2:
            raise KeyboardInterrupt
        super().slice_made(frame, slices)


def test_a_run_interrupted_inside_a_frame_after_a_closure_keeps_one_pose_per_frame(desk):
    scenario, frames = desk
    config = Config(volume=VolumeConfig(resolution=64, size=2.0))
    closer = InterruptedAfterAClosure(config, scenario.camera)
    result = pipeline.run(frames, scenario.camera, config, odometry="icp",
                          groundtruth=scenario.trajectory, loop_closer=closer)  # fmt: skip
    assert result.interrupted and result.frames == CLOSED_AT + 2
    trajectory = result.trajectory  # the poses corrected by the closure
    assert len(trajectory) == result.frames == len(closer.uncorrected_poses())
    np.testing.assert_array_equal(trajectory.poses, np.array(result.poses))
    np.testing.assert_array_equal(closer.uncorrected_poses()[-1],
                                  se3.inverse(CORRECTION) @ result.poses[-1])  # fmt: skip
