"""Kintinuous / ElasticFusion `.klg` logs: reading, converting both ways, bad logs, reconstructing.

The logs are written by `write_klg` below, a small writer of the published layout (struct, zlib,
cv2.imencode) that shares no code with the project's, from data/tiny_desk. The truth is the
TUM folder itself: depth rounded to whole millimetres, colour within JPEG's loss.
"""

import struct
import zlib

import cv2
import numpy as np
import pytest
from tiny_desk import TINY, tum_frames

from kintinuous_ref.camera import load_intrinsics_json
from kintinuous_ref.datasets import klg, tum
from kintinuous_ref.errors import DatasetError
from kintinuous_ref.program.cli import main

WIDTH, HEIGHT = 160, 120
INTRINSICS = "131.25,131.25,79.5,59.5"  # data/tiny_desk/intrinsics.json


def write_klg(path, frames, kinds=None):
    """The layout, independently: int32 count; per frame int64 us, int32 depth bytes, int32
    image bytes, zlib(uint16 mm), JPEG. `kinds[i]` = "raw" stores frame i uncompressed,
    "empty" stores no depth and no image (both counts 0)."""
    kinds = kinds or {}
    with open(path, "wb") as log:
        log.write(struct.pack("<i", len(frames)))
        for i, (stamp, raw, rgb) in enumerate(frames):
            millimetres = np.round(raw / 5.0).astype("<u2")  # 1/5000 m -> mm
            kind = kinds.get(i, "compressed")
            if kind == "raw":
                depth, image = millimetres.tobytes(), rgb.tobytes()
            elif kind == "empty":
                depth, image = b"", b""
            else:
                depth = zlib.compress(millimetres.tobytes(), 1)
                # The loggers hand RGB to OpenCV's encoder as is (it takes it for BGR).
                image = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
            log.write(struct.pack("<qii", round(stamp * 1e6), len(depth), len(image)))
            log.write(depth + image)


def psnr(a, b):
    error = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / error)


@pytest.fixture(scope="module")
def frames():
    return tum_frames()


@pytest.fixture(scope="module")
def log(frames, tmp_path_factory):
    path = tmp_path_factory.mktemp("klg") / "desk.klg"
    write_klg(path, frames)
    return path


def one_line(capsys, *fragments):
    """The command's error: one line (beside any progress bar) holding every fragment."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("kintinuous:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], err
    return lines[0]


def test_reading_gives_the_tum_depth_to_the_millimetre_and_colour_within_jpeg_loss(
    frames, tmp_path
):
    path = tmp_path / "mixed.klg"
    write_klg(path, frames, kinds={1: "raw", 2: "empty"})
    sequence = klg.open_log(path, (WIDTH, HEIGHT))
    assert len(sequence) == len(frames) == 10
    for i, (stamp, raw, rgb) in enumerate(frames):
        frame = sequence[i]
        assert frame.timestamp == pytest.approx(stamp, abs=1e-9)
        assert frame.depth.dtype == np.float32 and frame.colour.dtype == np.uint8
        if i == 2:  # counts of 0: no depth, black image
            assert not frame.depth.any() and not frame.colour.any()
            continue
        metres = raw / 5000.0
        # Whole millimetres of a 1/5000 m image: at most 0.4 mm off (0.2 mm steps), zeros kept.
        assert np.abs(frame.depth - metres).max() <= 0.0004 + 1e-6
        assert ((frame.depth == 0) == (raw == 0)).all()
        if i == 1:  # raw RGB is exact
            np.testing.assert_array_equal(frame.colour, rgb)
        else:
            # JPEG at quality 90: 30.6 dB on these sharp-edged synthetic images; R and B
            # swapped (their means differ by 17 levels) give 17 dB.
            assert psnr(frame.colour, rgb) > 28
            assert psnr(frame.colour, rgb[..., ::-1]) < 20
    np.testing.assert_array_equal(sequence.raw_depth(0), np.round(frames[0][1] / 5.0))


def test_opening_reads_only_headers(frames, tmp_path):
    """A log is indexed without decoding: a corrupt frame 3 is found only when frame 3 is read."""
    path = tmp_path / "corrupt.klg"
    write_klg(path, frames)
    sequence = klg.open_log(path, (WIDTH, HEIGHT))
    offset = int(sequence._offsets[3])
    data = bytearray(path.read_bytes())
    data[offset : offset + 8] = b"notzlib!"
    path.write_bytes(bytes(data))
    sequence = klg.open_log(path, (WIDTH, HEIGHT))
    assert sequence[2].depth.any() and sequence[4].depth.any()
    with pytest.raises(DatasetError) as excinfo:
        sequence[3]
    message = str(excinfo.value)
    assert "\n" not in message and str(path) in message and "frame 3" in message


def test_bad_logs_get_one_line_naming_the_file_and_frame(frames, log, tmp_path, capsys):
    data = log.read_bytes()
    truth = str(TINY / "groundtruth.txt")
    common = ["--intrinsics", INTRINSICS, "--size", "160x120", "--backend", "ref"]
    common += ["--groundtruth", truth, "--resolution", "32", "--overwrite"]

    def reconstruct(path, *extra):
        return main(["reconstruct", str(path), "--out", str(tmp_path / "out"), *common, *extra])

    truncated = tmp_path / "truncated.klg"
    truncated.write_bytes(data[: len(data) - 1000])  # the last frame's image is cut
    assert reconstruct(truncated) == 2
    one_line(capsys, str(truncated), "truncated", "frame 9 of 10")

    header_only = tmp_path / "header.klg"
    header_only.write_bytes(data[:4] + data[4:20])  # frame 0's header, no data, no frame 1
    assert reconstruct(header_only) == 2
    one_line(capsys, str(header_only), "truncated", "frame 0")

    bad_count = tmp_path / "count.klg"
    bad_count.write_bytes(struct.pack("<i", -3) + data[4:])
    assert reconstruct(bad_count) == 2
    one_line(capsys, str(bad_count), "bad header", "-3")

    assert main(["reconstruct", str(log), "--out", str(tmp_path / "o"), "--backend", "ref"]) == 2
    one_line(capsys, str(log), "--intrinsics")

    # A log of 160x120 frames read as 80x60: frame 0's depth is larger than an 80x60 frame.
    assert reconstruct(log, "--size", "80x60", "--intrinsics", "65,65,39.5,29.5") == 2
    one_line(capsys, str(log), "frame 0", "80x60")

    # Read as 200x150: frame 0's depth inflates to 160*120*2 bytes, not 200*150*2.
    assert reconstruct(log, "--size", "200x150", "--intrinsics", "160,160,99.5,74.5") == 2
    one_line(capsys, str(log), "frame 0", "holds 38400 bytes", "200x150")


def test_convert_round_trips_both_ways(frames, log, tmp_path, capsys):
    # TUM -> .klg -> TUM: the depth to the millimetre, colour within one JPEG's loss.
    assert main(["convert", str(TINY), str(tmp_path / "desk.klg")]) == 0
    assert "--intrinsics 131.25,131.25,79.5,59.5 --size 160x120" in capsys.readouterr().out
    back = tmp_path / "back"
    assert main(["convert", str(tmp_path / "desk.klg"), str(back), "--size", "160x120"]) == 0
    sequence = tum.open_sequence(back, INTRINSICS)
    for frame, (stamp, raw, rgb) in zip(sequence, frames, strict=True):
        assert frame.timestamp == stamp
        assert np.abs(frame.depth - raw / 5000.0).max() <= 0.0004 + 1e-6
        assert psnr(frame.colour, rgb) > 28

    # The test's own log -> TUM -> .klg: the depth is exact, the colour one more JPEG pass.
    folder = tmp_path / "folder"
    truth = str(TINY / "groundtruth.txt")
    args = ["--size", "160x120", "--intrinsics", INTRINSICS, "--groundtruth", truth]
    assert main(["convert", str(log), str(folder), *args]) == 0
    written = tum.open_sequence(folder)  # the camera from its intrinsics.json
    assert written.camera == load_intrinsics_json(TINY / "intrinsics.json")
    expected = tum.read_trajectory(TINY / "groundtruth.txt")
    np.testing.assert_allclose(written.groundtruth.poses, expected.poses, atol=1e-8)
    assert main(["convert", str(folder), str(tmp_path / "again.klg")]) == 0
    first = klg.open_log(log, (WIDTH, HEIGHT))
    again = klg.open_log(tmp_path / "again.klg", (WIDTH, HEIGHT))
    np.testing.assert_array_equal(again.timestamps, first.timestamps)
    for i in range(len(first)):
        np.testing.assert_array_equal(again.raw_depth(i), first.raw_depth(i))
        assert psnr(again[i].colour, first[i].colour) > 28

    # Nothing is overwritten.
    assert main(["convert", str(TINY), str(tmp_path / "again.klg")]) == 2
    one_line(capsys, "again.klg", "already exists")


@pytest.mark.slow
def test_reconstructing_a_log_tracks_like_its_tum_folder(log, tmp_path):
    """icp+rgbd on the cpu backend over the 10 frames, from the folder and from the log.

    Tolerance 2 mm and 0.1 degree per pose: the log's depth is rounded to whole millimetres
    (0.2-0.4 mm changes on half the pixels, averaging out over thousands of points) and its
    colour passed once through JPEG (the photometric term sees ~4 levels of noise). Measured:
    0.8 mm and 0.03 degree at most, against 12 mm of camera motion per frame, so a frame
    dropped, shifted in time or read at the wrong depth scale would exceed it many times over.
    """
    common = ["--odometry", "icp+rgbd", "--backend", "cpu", "--resolution", "64"]
    assert main(["reconstruct", str(TINY), "--out", str(tmp_path / "tum"), *common]) == 0
    truth = str(TINY / "groundtruth.txt")
    args = ["--intrinsics", INTRINSICS, "--size", "160x120", "--groundtruth", truth]
    assert main(["reconstruct", str(log), "--out", str(tmp_path / "klg"), *common, *args]) == 0
    folder = tum.read_trajectory(tmp_path / "tum" / "trajectory.txt")
    logged = tum.read_trajectory(tmp_path / "klg" / "trajectory.txt")
    assert len(folder) == len(logged) == 10
    np.testing.assert_array_equal(logged.timestamps, folder.timestamps)
    assert np.linalg.norm(logged.positions - folder.positions, axis=1).max() < 0.002
    relative = np.einsum("nji,njk->nik", folder.poses[:, :3, :3], logged.poses[:, :3, :3])
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)
    assert np.degrees(np.arccos(cosine)).max() < 0.1
    # Both tracked: the camera moved 11 cm, and each estimate follows it to within 2 cm.
    groundtruth = tum.open_sequence(TINY).groundtruth_for_frames()
    assert np.linalg.norm(groundtruth.positions[-1] - groundtruth.positions[0]) > 0.1
    assert np.linalg.norm(logged.positions - groundtruth.positions, axis=1).max() < 0.02
