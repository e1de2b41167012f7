"""The pipeline and `kintinuous reconstruct` end to end on a small synthetic desk (160x120):
known poses in, the true surface out; interruption, bad input and the CLI's outputs."""

import json

import numpy as np
import pytest

from kintinuous_fast import load_backend
from kintinuous_ref import mesh, pipeline, se3
from kintinuous_ref import raycast as raycast_module
from kintinuous_ref.backend import ReferenceBackend
from kintinuous_ref.config import Config, VolumeConfig, fast_odometry
from kintinuous_ref.datasets import synthetic, tum
from kintinuous_ref.datasets.tum import Frame
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry import make_tracker
from kintinuous_ref.program.cli import main

FRAMES = 8
CONFIG = Config(volume=VolumeConfig(resolution=96, size=3.0))


@pytest.fixture(scope="module")
def desk():
    scenario = synthetic.make_scenario("desk", frames=FRAMES, width=160, height=120)
    frames = []
    for i in range(FRAMES):
        colour, depth = scenario.render(i)
        frames.append(Frame(i, float(scenario.trajectory.timestamps[i]), colour, depth))
    return scenario, frames


@pytest.fixture(scope="module")
def fused(desk):
    scenario, frames = desk
    return pipeline.run(frames, scenario.camera, CONFIG, groundtruth=scenario.trajectory)


def test_groundtruth_run_records_poses_and_timings(desk, fused):
    scenario, _ = desk
    assert fused.frames == FRAMES and not fused.interrupted and fused.tracking_failures == 0
    np.testing.assert_array_equal(fused.trajectory.poses, scenario.trajectory.poses)
    summary = fused.timing_summary()
    assert set(summary) == set(pipeline.STAGES)
    assert summary["total"]["max"] >= summary["total"]["median"] > 0
    assert summary["raycast"]["mean"] is None  # nothing needs the model with known poses


def test_fused_desk_lies_on_the_true_surface(desk, fused):
    scenario, frames = desk
    surface = mesh.extract_mesh(fused.volume)
    truth = scenario.surface_mesh()
    samples = mesh.sample_surface(truth, 0.03)
    volume = fused.volume
    inside = np.all(
        (samples > volume.origin) & (samples < volume.origin + volume.size - volume.voxel_size),
        axis=1,
    )
    visible = mesh.visible_from(
        samples[inside],
        [f.depth for f in frames],
        list(scenario.trajectory.poses),
        scenario.camera,
    )
    score = mesh.surface_accuracy(surface, truth, samples[inside][visible])
    # 31 mm voxels, noisy Kinect-like depth at 160x120, 8 frames: measured 1.9 mm mean and
    # 83 % within 1 cm; the bounds leave room for noise without admitting a misplaced surface
    # (a one-voxel offset would give ~30 mm).
    assert score.accuracy < 4e-3
    assert score.completeness > 0.7
    assert score.colour_error < 20.0


def test_interrupted_run_keeps_what_was_fused(desk):
    scenario, frames = desk

    def source():
        yield from frames[:3]
        raise KeyboardInterrupt

    result = pipeline.run(source(), scenario.camera, CONFIG, groundtruth=scenario.trajectory)
    assert result.interrupted and result.frames == 3
    assert result.volume is not None and result.volume.weight.max() == 3
    assert len(mesh.extract_mesh(result.volume).points) > 100


def test_tracker_plugs_in(desk):
    # ICP against the raycast model, starting at the first ground-truth pose: the trajectory
    # must stay near the truth over 4 frames (5 cm / 3 degrees catches a broken hand-over of
    # the model or the poses, not the tracker's fine accuracy, which test_odometry covers).
    scenario, frames = desk
    result = pipeline.run(
        frames[:4], scenario.camera, CONFIG, odometry="icp", groundtruth=scenario.trajectory
    )
    assert result.model is not None and np.isfinite(result.model.vertices).any()
    assert len(result.timings_ms["raycast"]) == 4
    for estimate, truth in zip(result.poses, scenario.trajectory.poses[:4], strict=True):
        error = se3.inverse(truth) @ estimate
        assert np.linalg.norm(error[:3, 3]) < 0.05
        assert np.degrees(se3.rotation_angle(error[:3, :3])) < 3.0


def test_fast_odometry_raycasts_only_the_pixels_it_reads(desk):
    """With the fast-odometry setting ICP starts at pyramid level 1, which reads the model's
    pixels (2u, 2v) only: the pipeline raycasts just those (a quarter of the rays), and the
    trajectory is bit for bit that of a run raycasting every pixel."""
    scenario, frames = desk
    config = fast_odometry(CONFIG)
    tracker = make_tracker("icp+rgbd", config, scenario.camera)
    assert (tracker.finest_level, tracker.model_stride) == (1, 2)
    default = make_tracker("icp+rgbd", CONFIG, scenario.camera)
    assert (default.finest_level, default.model_stride) == (0, 1)
    assert make_tracker("fovis/icp", config, scenario.camera).model_stride == 2
    assert make_tracker("rgbd", config, scenario.camera).model_stride == 1

    class EveryPixel(ReferenceBackend):  # raycasts every pixel whatever it is asked
        def predict_surface(self, volume, pose, camera, stride=1):  # noqa: ANN001, ANN201
            return raycast_module.raycast(volume, pose, camera, colour=False)

    def track(backend):  # noqa: ANN001, ANN202
        return pipeline.run(
            frames[:4], scenario.camera, config, "icp+rgbd", scenario.trajectory, backend=backend
        )

    strided, full = track(ReferenceBackend()), track(EveryPixel())
    assert strided.tracking_failures == full.tracking_failures == 0
    np.testing.assert_array_equal(np.array(strided.poses), np.array(full.poses))
    cast = np.zeros((scenario.camera.height, scenario.camera.width), dtype=bool)
    cast[::2, ::2] = True
    assert np.isnan(strided.model.vertices[~cast]).all()
    np.testing.assert_array_equal(strided.model.vertices[cast], full.model.vertices[cast])


def test_bad_runs_are_refused_before_work(desk):
    scenario, frames = desk
    with pytest.raises(ConfigError, match="ground-truth"):
        pipeline.run(frames, scenario.camera, CONFIG, groundtruth=None)
    with pytest.raises(ConfigError, match="size must be positive"):
        pipeline.run(
            frames,
            scenario.camera,
            Config(volume=VolumeConfig(size=-1.0)),
            groundtruth=scenario.trajectory,
        )
    with pytest.raises(ConfigError, match="unknown odometry"):
        pipeline.run(frames, scenario.camera, CONFIG, odometry="magic")


@pytest.fixture(scope="module")
def desk_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("data") / "desk"
    synthetic.write_scenario("desk", folder, frames=5, width=160, height=120)
    return folder


def test_reconstruct_command_writes_its_outputs(desk_folder, tmp_path):
    out = tmp_path / "out"
    status = main(
        [
            "reconstruct",
            str(desk_folder),
            "--odometry",
            "groundtruth",
            "--out",
            str(out),
            "--frames",
            "4",
            "--start",
            "1",
            "--resolution",
            "64",
        ]
    )
    assert status == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 4 and report["odometry"] == "groundtruth"
    assert report["backend"] == load_backend("auto").name  # the default: what ran
    for stage in ("preprocess", "odometry", "integrate", "raycast", "total"):
        assert set(report["timing_ms"][stage]) == {"mean", "median", "max"}
    estimate = tum.read_trajectory(out / "trajectory.txt")
    truth = tum.read_trajectory(desk_folder / "groundtruth.txt")
    np.testing.assert_allclose(estimate.poses, truth.poses[1:5], atol=1e-8)
    header = (out / "mesh.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "binary_little_endian" in header and "property uchar red" in header
    vertices = int(header.split("element vertex ")[1].split()[0])
    assert vertices == report["mesh"]["vertices"] > 100
    from PIL import Image

    picture = np.asarray(Image.open(out / "preview.png").convert("RGB"))
    assert (picture != 255).any(axis=-1).mean() > 0.05  # the mesh covers part of the picture


def test_reconstruct_command_bad_input(desk_folder, tmp_path, capsys, monkeypatch):
    from kintinuous_fast.tsdf import volume as _volume
    from kintinuous_ref import tsdf

    # any machine: 4 GiB (the reference's check, 24 bytes a voxel) and 2 GiB (the fast volume's,
    # 8 bytes a voxel: the default backend, auto, is cpu or cuda)
    monkeypatch.setattr(tsdf, "available_memory_bytes", lambda: 4 << 30)
    monkeypatch.setattr(_volume, "available_memory_bytes", lambda: 2 << 30)
    no_truth = tmp_path / "no_truth"
    no_truth.mkdir()
    for item in desk_folder.iterdir():
        if item.name != "groundtruth.txt":
            (no_truth / item.name).symlink_to(item)
    cases = [
        ([str(no_truth), "--odometry", "groundtruth"], "groundtruth"),
        ([str(desk_folder), "--volume-size", "0"], "size must be positive"),
        (
            [str(desk_folder), "--resolution", "768", "--backend", "cpu"],
            "needs 3.4 GiB but only 2.0",
        ),
        (
            [str(desk_folder), "--resolution", "768", "--backend", "ref"],
            "needs 10.1 GiB but only 4.0",
        ),
        ([str(tmp_path / "nowhere")], "neither a dataset folder nor a scenario"),
    ]
    for extra, message in cases:
        status = main(["reconstruct", *extra, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err.strip()
        assert status == 2 and message in err and len(err.splitlines()) == 1, err


def test_reconstruct_checks_the_memory_of_the_backend_it_runs_on(
    desk_folder, tmp_path, capsys, monkeypatch
):
    """512^3 with colour on the cpu backend with 2.5 GiB free: its volume needs 1.0 GiB (the
    reference's would need 3.0), so the run goes on to make its volume."""
    from kintinuous_fast.tsdf import cpu as cpu_tsdf
    from kintinuous_fast.tsdf import volume as _volume
    from kintinuous_ref import tsdf
    from kintinuous_ref.program import reconstruct

    monkeypatch.setattr(tsdf, "available_memory_bytes", lambda: 5 << 29)
    monkeypatch.setattr(_volume, "available_memory_bytes", lambda: 5 << 29)

    def make_volume(config: VolumeConfig, *args: object) -> None:  # stop before 1 GiB is filled
        cpu_tsdf.check_volume_config(config)
        raise ConfigError(f"a {config.resolution}^3 volume would be made here")

    monkeypatch.setattr(cpu_tsdf, "make_volume", make_volume)
    monkeypatch.setattr(reconstruct, "prepare_kernels", lambda *args: None)  # its own volume
    arguments = ["reconstruct", str(desk_folder), "--backend", "cpu", "--resolution", "512"]
    status = main([*arguments, "--frames", "1", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert status == 2 and "512^3 volume would be made here" in err, err
