"""What a user can do to the command line that the other tests do not: a signal that lands
outside the frame loop (a warm-up, a benchmark), damaged images that a decoder would half read,
settings that no image can satisfy, and two commands into one output. Each test asserts the
exit status, the one line on stderr and what is left on disk. docs/reliability.md lists these
cases."""

import json
import shutil
from pathlib import Path

import pytest

from kintinuous_ref.datasets import tum
from kintinuous_ref.program import cli, warmup
from kintinuous_ref.signals import Interrupted

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
SMALL = ["--backend", "ref", "--resolution", "32", "--volume-size", "2"]


def _errors(stderr: str) -> list[str]:
    """The command's own lines on stderr (progress bars left out)."""
    return [line for line in stderr.splitlines() if line.startswith("kintinuous:")]


def _signal_at(frame: int, name: str = "SIGTERM"):
    """A frame reader that raises the signal handler's Interrupted when it reaches `frame`, as
    the handler does in the main thread."""
    read = tum.TumSequence._read

    def reader(self, index: int):
        if index == frame:
            raise Interrupted(name)
        return read(self, index)

    return reader


def test_a_signal_during_the_warm_up_ends_the_command(monkeypatch, capsys):
    frames, camera, truth = warmup.warmup_frames()

    def interrupted_frames():
        def frames_then_signal():
            yield frames[0]
            raise Interrupted("SIGTERM")

        return frames_then_signal(), camera, truth

    monkeypatch.setattr(warmup, "warmup_frames", interrupted_frames)
    status = cli.main(["warmup", "--backend", "ref", "--odometry", "icp", "--serial"])
    captured = capsys.readouterr()
    assert status == 143
    assert _errors(captured.err) == ["kintinuous: interrupted by SIGTERM"]
    assert captured.out == ""  # no table of a warm-up that did not happen


def test_a_signal_during_a_benchmark_prints_no_timings(monkeypatch, capsys):
    monkeypatch.setattr(tum.TumSequence, "_read", _signal_at(3, "SIGINT"))
    argv = ["benchmark", str(TINY), "--frames", "6", "--odometry", "groundtruth", *SMALL]
    status = cli.main(argv)
    captured = capsys.readouterr()
    assert status == 130
    assert _errors(captured.err) == [
        "kintinuous: interrupted by SIGINT after 3 of 6 frames: no timings printed"
    ]
    assert captured.out == ""


@pytest.fixture
def copy(tmp_path) -> Path:
    """tiny_desk, copied to be damaged."""
    target = tmp_path / "seq"
    shutil.copytree(TINY, target)
    return target


def _listed(folder: Path, frame: int, column: int) -> Path:
    rows = [row.split() for row in (folder / "associations.txt").read_text().splitlines()]
    rows = [row for row in rows if row and not row[0].startswith("#")]
    return folder / rows[frame][column]


def _as_jpeg_sequence(folder: Path) -> None:
    """The colour images of `folder` as JPEGs (as 7-Scenes and many recorders store them)."""
    import cv2

    listing = folder / "associations.txt"
    for frame in range(10):
        png = _listed(folder, frame, 1)
        cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png)))
        png.unlink()
    listing.write_text(listing.read_text().replace(".png 1", ".jpg 1"))


@pytest.mark.parametrize("kind", ["jpeg", "png"])
def test_a_colour_image_cut_short_stops_the_run_there(copy, tmp_path, capfd, kind):
    # libjpeg decodes a cut JPEG with its lower rows grey and only a warning: the frame was
    # fused as if whole ("fused 10 of 10 frames", exit 0)
    if kind == "jpeg":
        _as_jpeg_sequence(copy)
    image = _listed(copy, 6, 1)
    whole = image.read_bytes()
    image.write_bytes(whole[: len(whole) // 2])
    out = tmp_path / "out"
    status = cli.main(
        ["reconstruct", str(copy), "--out", str(out), *SMALL, "--odometry", "groundtruth"]
    )
    err = capfd.readouterr().err
    assert status == 2
    what = {
        "jpeg": "JPEG has no end-of-image marker after its last scan",
        "png": "PNG has no IEND chunk at its end",
    }[kind]
    assert _errors(err) == [
        f"kintinuous: error: frame 6: {image}: cannot read colour image: the file is cut short "
        f"(the {what}, {len(whole) // 2} bytes); copy it again from the source; the 6 frames "
        f"done are saved in {out}"
    ]
    assert "Premature end" not in err and "libpng" not in err  # no decoder's own line
    assert len(tum.read_trajectory(out / "trajectory.txt")) == 6  # the frames before it kept


def test_a_signal_during_the_save_still_writes_the_report(tmp_path, monkeypatch, capsys):
    # the signal lands while the preview renders, after the trajectory and the mesh: the folder
    # held them without report.json, so nothing said how the run had ended
    from kintinuous_ref import mesh

    def render_preview(*args, **kwargs):
        raise Interrupted("SIGTERM")

    monkeypatch.setattr(mesh, "render_preview", render_preview)
    out = tmp_path / "out"
    argv = ["reconstruct", str(TINY), "--out", str(out), *SMALL, "--odometry", "groundtruth"]
    status = cli.main(argv)
    assert status == 143
    assert _errors(capsys.readouterr().err) == [
        f"kintinuous: SIGTERM during the save: saved trajectory.txt, mesh.ply, "
        f"volume_origins.txt, report.json in {out}; NOT saved: preview.png"
    ]
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "interrupted" and report["reason"] == "SIGTERM during the save"
    assert report["frames"] == 10 and report["last_frame"] == 9
    assert report["saved"] == ["trajectory.txt", "mesh.ply", "volume_origins.txt", "report.json"]
    assert report["not_saved"] == {"preview.png": "SIGTERM during the save"}
    assert len(tum.read_trajectory(out / "trajectory.txt")) == 10
    assert sorted(p.name for p in out.iterdir()) == [
        "mesh.ply",
        "report.json",
        "slices",
        "trajectory.txt",
        "volume_origins.txt",
    ]


@pytest.mark.parametrize(
    ("levels", "command"), [(0, "reconstruct"), (8, "reconstruct"), (0, "benchmark")]
)
def test_a_pyramid_no_image_can_have_is_refused_before_any_work(tmp_path, capsys, levels, command):
    # 0 levels, or 8 halvings of a 120-pixel side, ended in an internal error at the first frame
    out = tmp_path / "out"
    argv = [command, str(TINY), *SMALL, "--odometry", "groundtruth", "--frames", "3"]
    argv += ["--set", f"preprocess.pyramid_levels={levels}"]
    argv += ["--out", str(out)] if command == "reconstruct" else []
    status = cli.main(argv)
    assert status == 2
    assert _errors(capsys.readouterr().err) == [
        f"kintinuous: error: preprocess.pyramid_levels {levels}: a 160x120 image has levels "
        "1..7 (each half the size of the one before); choose one in that range (the default is 4)"
    ]
    assert not out.exists()


@pytest.mark.parametrize("name", ["tum", "seq.klg"])
def test_a_second_convert_into_an_output_being_written_is_refused(tmp_path, capsys, name):
    # the two shared one temporary name beside the output: the second removed the first's
    # half-written folder (the first then failed on a file of it) or wrote into the same log
    import fcntl
    import os

    out = tmp_path / name
    lock = tmp_path / f".{name}.lock"
    handle = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)  # what a live convert holds
    try:
        fcntl.flock(handle, fcntl.LOCK_EX)
        os.write(handle, f"4242 kintinuous convert a {out}\n".encode())
        status = cli.main(["convert", str(TINY), str(out)])
    finally:
        os.close(handle)
    assert status == 2
    assert _errors(capsys.readouterr().err) == [
        f"kintinuous: error: {out}: being written by pid 4242 (kintinuous convert a {out}); "
        "wait for it to end or choose another output"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == [lock.name]  # nothing written
    assert cli.main(["convert", str(TINY), str(out)]) == 0  # once it has ended
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # its lock file removed too


def test_intrinsics_of_another_image_size_are_refused_before_any_work(copy, tmp_path, capsys):
    # a camera for 320x240 with 160x120 images: the run made an output folder holding a failed
    # report of 0 frames, so the rerun with the right camera needed --overwrite
    intrinsics = copy / "intrinsics.json"
    camera = json.loads(intrinsics.read_text())
    camera.update(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)
    intrinsics.write_text(json.dumps(camera))
    out = tmp_path / "out"
    argv = ["reconstruct", str(copy), "--out", str(out), *SMALL, "--odometry", "groundtruth"]
    status = cli.main(argv)
    assert status == 2
    assert _errors(capsys.readouterr().err) == [
        f"kintinuous: error: frame 0: {_listed(copy, 0, 3)}: image is 160x120 but the camera is "
        f"320x240 (the camera of {intrinsics})"
    ]
    assert not out.exists()


def test_a_first_frame_that_cannot_be_read_is_refused_before_any_work(copy, tmp_path, capsys):
    # the checks before the work read the first frame and dropped its error, and the run then
    # failed at it into a new output folder
    depth = _listed(copy, 0, 3)
    depth.write_bytes(b"not a png")
    out = tmp_path / "out"
    argv = ["reconstruct", str(copy), "--out", str(out), *SMALL, "--odometry", "groundtruth"]
    status = cli.main(argv)
    errors = _errors(capsys.readouterr().err)
    assert status == 2
    assert len(errors) == 1 and errors[0].startswith(f"kintinuous: error: frame 0: {depth}: ")
    assert "saved" not in errors[0]
    assert not out.exists()
    # with --skip-bad-frames the run goes ahead without it
    assert cli.main([*argv, "--skip-bad-frames"]) == 0
    assert len(tum.read_trajectory(out / "trajectory.txt")) == 9


@pytest.mark.parametrize(
    ("odometry", "setting", "key", "iterations", "levels"),
    [
        ("icp", "icp.iterations=[10,5,4,4,4]", "icp.iterations", [10, 5, 4, 4, 4], 4),
        ("icp", "preprocess.pyramid_levels=2", "icp.iterations", [10, 5, 4], 2),
        ("rgbd", "preprocess.pyramid_levels=3", "rgbd.iterations", [10, 7, 7, 7], 3),
        (
            "fovis/icp+rgbd",
            "preprocess.pyramid_levels=1",
            "rgbd.combined_iterations",
            [10, 5, 4],
            1,
        ),
    ],
)
def test_iterations_for_more_levels_than_the_pyramid_are_refused_before_any_work(
    tmp_path, capsys, odometry, setting, key, iterations, levels
):
    # the tracker needs one pyramid level per count: it failed on every frame, said only by a
    # warning after the run
    out = tmp_path / "out"
    argv = ["reconstruct", str(TINY), "--out", str(out), *SMALL, "--odometry", odometry]
    status = cli.main([*argv, "--frames", "3", "--set", setting])
    assert status == 2
    assert _errors(capsys.readouterr().err) == [
        f"kintinuous: error: {key} {iterations}: counts for {len(iterations)} pyramid levels, "
        f"but preprocess.pyramid_levels is {levels}, so --odometry {odometry} would fail on "
        f"every frame; give {key} at most {levels} counts or preprocess.pyramid_levels at "
        f"least {len(iterations)}"
    ]
    assert not out.exists()


@pytest.mark.parametrize("odometry", ["icp", "rgbd", "fovis", "fovis/rgbd", "icp+rgbd"])
def test_every_tracker_runs_with_the_default_pyramid(odometry):
    from kintinuous_ref.config import Config
    from kintinuous_ref.program.reconstruct import check_tracker_levels

    check_tracker_levels(Config(), odometry)  # no error


def test_a_benchmark_with_iterations_for_more_levels_is_refused(capsys):
    argv = ["benchmark", str(TINY), "--frames", "3", "--odometry", "icp", *SMALL]
    assert cli.main([*argv, "--set", "preprocess.pyramid_levels=2"]) == 2
    assert _errors(capsys.readouterr().err)[0].startswith("kintinuous: error: icp.iterations")


def test_a_table_of_datasets_that_do_not_exist_is_refused_before_any_run(
    tmp_path, capsys, monkeypatch
):
    # every method ran on the missing path and failed, and the command wrote a table of
    # failures before its exit status 1
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path / "cache"))
    missing, log = tmp_path / "nonexistent", tmp_path / "nothing.klg"
    out = tmp_path / "out"
    options = ["--out", str(out), "--frames", "3", "--backend", "ref"]
    assert cli.main(["table", str(missing), *options]) == 2
    captured = capsys.readouterr()
    assert _errors(captured.err) == [
        f"kintinuous: error: {missing}: neither a dataset folder nor a scenario (desk, "
        "corridor, dark, floor, loop, revisit, twins), nor a .klg log, a bag or a downloaded "
        "sequence"
    ]
    assert captured.out == "" and not out.exists()
    assert cli.main(["table", str(missing), str(log), *options]) == 2
    error = _errors(capsys.readouterr().err)
    assert len(error) == 1 and error[0].startswith("kintinuous: error: none of the 2 datasets")
    assert f"{log}: log file not found" in error[0]
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["--shift-threshold", "0"],
            "--shift-threshold (volume.shift_threshold) must be 1..16 voxels, got 0",
        ),
        (["--resolution", "4"], "--resolution (volume.resolution) must be in 8..1024, got 4"),
        (
            ["--volume-size", "-1"],
            "--volume-size (volume.size): volume size must be positive, got -1.0 m",
        ),
        (
            ["--set", "volume.shift_threshold=17"],
            "--set: shift threshold must be 1..16 voxels, got 17",
        ),
    ],
)
def test_a_volume_option_out_of_range_is_named(tmp_path, capsys, argv, message):
    # "shift threshold must be 1..16 voxels, got 0" named no option the user had typed
    out = tmp_path / "out"
    assert cli.main(["reconstruct", str(TINY), "--out", str(out), *argv]) == 2
    assert _errors(capsys.readouterr().err) == [f"kintinuous: error: {message}"]
    assert not out.exists()


def test_a_benchmark_past_the_sequences_end_says_how_many_frames_it_times(capsys):
    # --start 8 --frames 5 on 10 frames timed 1 frame, said only by the table's header
    argv = ["benchmark", str(TINY), *SMALL, "--odometry", "groundtruth", "--frames", "5"]
    assert cli.main([*argv, "--start", "8"]) == 0
    captured = capsys.readouterr()
    assert _errors(captured.err) == [
        "kintinuous: warning: --frames 5 from --start 8: the sequence ends at frame 9, so 2 "
        "frames run (1 timed)"
    ]
    assert "1 timed frames" in captured.out
    assert cli.main([*argv, "--start", "9"]) == 2  # nothing left to time
    captured = capsys.readouterr()
    assert _errors(captured.err) == [
        "kintinuous: error: --start 9 leaves 1 frame of the sequence's 10 (frames 0..9); a "
        "benchmark needs at least 2 (the first is a warm-up): choose --start at most 8"
    ]
    assert captured.out == ""
