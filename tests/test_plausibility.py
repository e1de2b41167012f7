"""Input that is valid but absurd is refused in one line before any work (or, where it may be
meant, warned about); what shows only during a run is reported; every message names the file,
option or variable at fault and what would work (docs/reliability.md, cases 82 onwards)."""

import errno
import json
import pathlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from kintinuous_ref.config import Config, IcpConfig
from kintinuous_ref.datasets import tum
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.pipeline import check_settings
from kintinuous_ref.program.cli import main
from kintinuous_ref.program.output_folder import write_text_atomic

DESK = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"
# the cheapest real run: two frames, ground-truth poses, a coarse volume, the reference
QUICK = ["--frames", "2", "--resolution", "32", "--odometry", "groundtruth", "--backend", "ref"]


def desk_copy(folder: Path, changed: tuple[str, ...] = ()) -> Path:
    """tiny_desk as links, except the files (relative paths) in `changed`, which are copies
    that a test may edit."""
    folder.mkdir()
    for item in DESK.iterdir():
        (folder / item.name).symlink_to(item)
    for name in changed:
        target = folder / name
        if target.parent != folder and target.parent.is_symlink():
            target.parent.unlink()
            shutil.copytree(DESK / target.parent.name, target.parent)
        else:
            target.unlink()
            shutil.copy(DESK / name, target)
    return folder


def refused(capsys: pytest.CaptureFixture, arguments: list[str]) -> str:
    """Run the command, expecting exit 2 and one line on stderr; that line."""
    status = main(arguments)
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, (status, err)
    return err


def with_intrinsics(folder: Path, **values: float) -> Path:
    camera = json.loads((DESK / "intrinsics.json").read_text())
    (folder / "intrinsics.json").write_text(json.dumps({**camera, **values}))
    return folder / "intrinsics.json"


@pytest.mark.parametrize(
    ("values", "said"),
    [
        ({"cx": 900.0}, ["principal point (cx, cy) = (900, 59.5)", "cx in 0..160"]),
        ({"cy": -400.0}, ["principal point", "cy in 0..120"]),
        ({"fx": 5.0, "fy": 5.0}, ["horizontal field of view of 173 degrees", "20 to 160"]),
        ({"fx": 5000.0, "fy": 5000.0}, ["field of view of 1.83 degrees", "fx between 14 and 454"]),
    ],
    ids=["cx", "cy", "wide", "narrow"],
)
def test_an_implausible_camera_is_refused_before_any_work(tmp_path, capsys, values, said):
    folder = desk_copy(tmp_path / "desk", ("intrinsics.json",))
    source = with_intrinsics(folder, **values)
    out = tmp_path / "out"
    err = refused(capsys, ["reconstruct", str(folder), *QUICK, "--out", str(out)])
    assert str(source) in err and "--no-plausibility-checks" in err, err
    assert all(words in err for words in said), err
    assert not out.exists()


def test_the_option_runs_an_implausible_camera_anyway(tmp_path, capsys):
    folder = desk_copy(tmp_path / "desk", ("intrinsics.json",))
    with_intrinsics(folder, cx=900.0)
    out = tmp_path / "out"
    status = main(
        ["reconstruct", str(folder), *QUICK, "--no-plausibility-checks", "--out", str(out)]
    )
    assert status == 0, capsys.readouterr().err
    assert json.loads((out / "report.json").read_text())["status"] == "completed"


def test_an_implausible_camera_option_is_named(tmp_path, capsys):
    arguments = ["--intrinsics", "131.25,131.25,79.5,900", "--out", str(tmp_path / "o")]
    err = refused(capsys, ["reconstruct", str(DESK), *QUICK, *arguments])
    assert "--intrinsics 131.25,131.25,79.5,900: implausible camera" in err, err


@pytest.mark.parametrize(
    ("size", "said"),
    [
        ("1e6", "1e+06 m: voxels of 3.12e+04 m at resolution 32, coarser than 0.1 m"),
        ("1e-6", "1e-06 m: the first frame's surface (depths 1.18 to 3.94 m) lies outside"),
        ("0.2", "0.2 m: the first frame's surface"),
    ],
)
def test_a_volume_that_cannot_hold_the_surface_is_refused(tmp_path, capsys, size, said):
    out = tmp_path / "out"
    err = refused(
        capsys, ["reconstruct", str(DESK), *QUICK, "--volume-size", size, "--out", str(out)]
    )
    assert f"--volume-size (volume.size) {said}" in err, err
    assert "choose at" in err and "--no-plausibility-checks" in err, err
    assert not out.exists()


def test_a_volume_left_empty_is_reported_in_the_report_and_on_stderr(tmp_path, capsys):
    out = tmp_path / "out"
    arguments = [*QUICK, "--volume-size", "1e-6", "--no-plausibility-checks"]
    status = main(["reconstruct", str(DESK), *arguments, "--out", str(out)])
    err = capsys.readouterr().err
    warning = "0 vertices after fusing 2 frames: the surface lies outside the volume"
    assert status == 0 and f"kintinuous: warning: {warning}" in err, err
    report = json.loads((out / "report.json").read_text())
    assert any(warning in line for line in report["warnings"]), report["warnings"]


@pytest.mark.parametrize(
    ("odometry", "key", "value"),
    [
        ("icp", "icp.iterations", "[0,0,0]"),
        ("rgbd", "rgbd.iterations", "[0,0,0,0]"),
        ("icp+rgbd", "rgbd.combined_iterations", "[0,0,0]"),
        ("fovis/icp", "icp.iterations", "[0,0,0]"),
    ],
)
def test_iterations_that_leave_the_tracker_no_work_are_refused(
    tmp_path, capsys, odometry, key, value
):
    out = tmp_path / "out"
    arguments = ["--odometry", odometry, "--set", f"{key}={value}", "--out", str(out)]
    err = refused(capsys, ["reconstruct", str(DESK), *arguments])
    assert f"{key} {value.replace(',', ', ')}: no pyramid level runs a step" in err, err
    assert f"--odometry {odometry} would leave the camera" in err and "such as [" in err, err
    assert not out.exists()


def test_iterations_a_method_does_not_use_are_not_checked():
    idle = Config(icp=IcpConfig(iterations=(0, 0, 0)))
    for odometry in ("rgbd", "icp+rgbd", "fovis", "groundtruth"):
        check_settings(idle, odometry)
    with pytest.raises(ConfigError, match="icp.iterations"):
        check_settings(idle, "icp")


def shifted_groundtruth(folder: Path, seconds: float) -> Path:
    """The folder's groundtruth.txt with every timestamp moved by `seconds`."""
    path = folder / "groundtruth.txt"
    truth = tum.read_trajectory(DESK / "groundtruth.txt")
    tum.write_trajectory(path, tum.Trajectory(truth.timestamps + seconds, truth.poses))
    return path


def test_a_groundtruth_matching_no_frame_is_refused_for_groundtruth_odometry(tmp_path, capsys):
    folder = desk_copy(tmp_path / "desk", ("groundtruth.txt",))
    path = shifted_groundtruth(folder, 1000.0)
    out = tmp_path / "out"
    err = refused(capsys, ["reconstruct", str(folder), *QUICK, "--out", str(out)])
    assert f"{path}: no pose within 0.02 s of any of the 10 frames" in err, err
    assert "frames at 1.000000..1.300000 s, poses at 1001.000000..1001.300000 s" in err, err
    assert not out.exists()


def test_a_groundtruth_matching_no_frame_is_a_warning_for_a_tracker(tmp_path, capsys):
    folder = desk_copy(tmp_path / "desk", ("groundtruth.txt",))
    path = shifted_groundtruth(folder, 1000.0)
    out = tmp_path / "out"
    tracked = [*QUICK[:4], "--odometry", "icp", "--backend", "ref"]
    status = main(["reconstruct", str(folder), *tracked, "--out", str(out)])
    err = capsys.readouterr().err
    warning = f"{path}: no pose within 0.02 s of any of the 10 frames"
    start = "ground truth not used; the run starts at the identity"
    lines = [line for line in err.splitlines() if warning in line]
    assert status == 0 and len(lines) == 1 and start in lines[0], err
    assert lines[0].startswith("kintinuous: warning: ")
    report = json.loads((out / "report.json").read_text())
    assert any(warning in line and start in line for line in report["warnings"])


def millimetre_desk(folder: Path, divisor: float) -> Path:
    """tiny_desk with its depth images divided by `divisor` (5: millimetres), intrinsics.json
    still declaring 5000."""
    desk_copy(folder, ("depth/1.000000.png",))
    for image in (folder / "depth").iterdir():
        raw = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(image), np.round(raw / divisor).astype(np.uint16))
    return folder


def test_depth_in_millimetres_read_as_tum_units_is_refused_with_the_scale_that_fits(
    tmp_path, capsys
):
    folder = millimetre_desk(tmp_path / "desk", 5.0)
    out = tmp_path / "out"
    err = refused(capsys, ["reconstruct", str(folder), *QUICK, "--out", str(out)])
    said = f"{folder / 'intrinsics.json'}: depth_scale 5000 puts frame 0's median depth at 0.433 m"
    assert said in err and "outside a depth camera's 0.5..10 m" in err, err
    assert "depth_scale 1000 (millimetres) puts it at 2.16 m" in err, err
    assert not out.exists()


def test_a_depth_scale_far_off_names_the_factor(tmp_path, capsys):
    folder = millimetre_desk(tmp_path / "desk", 50.0)
    err = refused(capsys, ["reconstruct", str(folder), *QUICK, "--out", str(tmp_path / "o")])
    assert "median depth at 0.0432 m" in err and "depth_scale 108 puts it at 2 m" in err, err


def test_synth_with_negative_frames_names_the_option(tmp_path, capsys):
    err = refused(capsys, ["synth", "desk", "--frames", "-3", "--out", str(tmp_path / "s")])
    assert "--frames must be at least 1 (frames to render), got -3" in err, err
    assert "1..-3" not in err


@pytest.mark.parametrize("source", ["option", "variable"])
def test_a_mirror_that_is_no_url_is_named(tmp_path, capsys, monkeypatch, source):
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path / "cache"))
    arguments = ["download", "fr1/desk"]
    if source == "option":
        arguments += ["--mirror", "notaurl"]
    else:
        monkeypatch.setenv("KINTINUOUS_MIRROR", "notaurl")
    err = refused(capsys, arguments)
    named = "--mirror" if source == "option" else "$KINTINUOUS_MIRROR"
    assert f"{named} 'notaurl' is not a base URL: expected http, https, ftp://HOST" in err, err
    assert "sha256" not in err and "None" not in err, err


def test_a_colour_image_of_the_wrong_size_is_named(tmp_path):
    folder = desk_copy(tmp_path / "desk", ("rgb/1.000000.png",))
    colour = folder / "rgb" / "1.000000.png"
    cv2.imwrite(str(colour), np.zeros((60, 80, 3), np.uint8))
    with pytest.raises(DatasetError) as caught:
        tum.open_sequence(folder)[0]
    assert str(caught.value) == f"{colour}: image is 80x60 but the camera is 160x120"


def no_space(monkeypatch: pytest.MonkeyPatch, suffix: str) -> None:
    """Writes of files ending in `suffix` fail as on a full disk: OSError(ENOSPC), no file name
    (what a write's error carries)."""
    for method in ("write_bytes", "write_text"):
        original = getattr(pathlib.Path, method)

        def failing(self, data, *args, _original=original, **kwargs):  # noqa: ANN001, ANN202
            if self.name.endswith(suffix):
                raise OSError(errno.ENOSPC, "No space left on device")
            return _original(self, data, *args, **kwargs)

        monkeypatch.setattr(pathlib.Path, method, failing)


def test_a_full_disk_while_synth_writes_names_the_image(tmp_path, capsys, monkeypatch):
    no_space(monkeypatch, ".png")
    arguments = ["--frames", "1", "--width", "32", "--height", "24", "--no-noise"]
    status = main(["synth", "desk", *arguments, "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err.strip().splitlines()  # the progress bar, then the error
    image = tmp_path / "s" / "rgb" / "1.000000.png"
    said = f"kintinuous: error: {image}: cannot write (No space left on device)"
    assert status == 2 and err[-1] == said and "libpng" not in "".join(err), err


def test_a_full_disk_while_convert_writes_names_the_file(tmp_path, capsys, monkeypatch):
    no_space(monkeypatch, "associations.txt")
    err = refused(capsys, ["convert", str(DESK), str(tmp_path / "tum")])
    listed = tmp_path / ".tum.partial" / "associations.txt"
    assert f"{listed}: cannot write (No space left on device)" in err, err
    assert not (tmp_path / "tum").exists()


def test_a_full_disk_under_an_atomic_write_names_the_file(tmp_path, monkeypatch):
    no_space(monkeypatch, ".json")
    with pytest.raises(OSError, match="No space left") as caught:
        write_text_atomic(tmp_path / "report.json", "{}")
    assert caught.value.filename == str(tmp_path / "report.json")


def test_a_cache_variable_naming_a_file_is_named(tmp_path, capsys, monkeypatch):
    cache = tmp_path / "cache"
    cache.write_text("not a folder")
    monkeypatch.setenv("KINTINUOUS_CACHE", str(cache))
    for command in (["reconstruct", "desk", "--out", str(tmp_path / "o")], ["download", "x"]):
        err = refused(capsys, command)
        assert f"$KINTINUOUS_CACHE={cache}: {cache} is a file, not a folder" in err, err
    monkeypatch.setenv("KINTINUOUS_CACHE", str(cache / "below"))
    err = refused(capsys, ["reconstruct", "desk", "--out", str(tmp_path / "o")])
    assert f"$KINTINUOUS_CACHE={cache / 'below'}: {cache} is a file" in err, err


def test_convert_of_a_log_without_intrinsics_writes_a_folder_reconstruct_reads(tmp_path, capsys):
    log = tmp_path / "desk.klg"
    assert main(["convert", str(DESK), str(log)]) == 0
    capsys.readouterr()
    out = tmp_path / "tum"
    assert main(["convert", str(log), str(out), "--size", "160x120"]) == 0
    err = capsys.readouterr().out
    assert f"note: the source holds no camera: {out}/intrinsics.json holds the Kinect's" in err
    assert "--intrinsics fx,fy,cx,cy" in err
    camera = tum.open_sequence(out).camera
    assert (camera.fx, camera.cx, camera.width) == (131.25, 79.5, 160)
    tracked = [*QUICK[:4], "--odometry", "icp", "--backend", "ref"]  # a log has no truth
    status = main(["reconstruct", str(out), *tracked, "--out", str(tmp_path / "o")])
    assert status == 0, capsys.readouterr().err
