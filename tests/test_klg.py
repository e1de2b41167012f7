"""Kintinuous / ElasticFusion `.klg` logs: reading, converting both ways, bad logs, reconstructing.

The logs are written by `write_klg` below, a small writer of the published layout (struct, zlib,
cv2.imencode) that shares no code with the project's, from data/tiny_desk. The truth is the
TUM folder itself: depth rounded to whole millimetres, colour within JPEG's loss.
"""

import json
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


def _damaged(data, offsets, kind):
    """A five-frame log damaged at its end the way a logger cut off leaves it."""
    if kind == "cut-data":  # frame 2's data cut short
        return data[: offsets[2] + 100]
    if kind == "cut-header":  # inside frame 2's header
        return data[: offsets[2] - 5]
    if kind == "count-too-large":  # ends right after frame 2: the count says 5
        return data[: offsets[3] - 16]
    damaged = bytearray(data)
    if kind == "bad-header":  # frame 3's byte counts garbled
        damaged[offsets[3] - 8 : offsets[3]] = struct.pack("<ii", -7, 12)
    else:  # "undecodable-last": frame 4's depth is whole but not zlib data
        damaged[offsets[4] : offsets[4] + 8] = b"notzlib!"
    return bytes(damaged)


DAMAGE = {  # kind: (intact frames, the warning's account of the damage)
    "cut-data": (2, "truncated: frame 2 of 5 needs bytes up to "),
    "cut-header": (2, "truncated: the header says 5 frames but the log ends inside frame 2's"),
    "count-too-large": (3, "truncated: the header says 5 frames but the log ends before frame 3"),
    "bad-header": (3, "frame 3: bad frame header (depth -7 bytes, image 12 bytes)"),
    "undecodable-last": (4, "frame 4: depth is not zlib data ("),
}


@pytest.mark.parametrize("kind", DAMAGE)
def test_a_log_damaged_at_its_end_reads_its_intact_frames(frames, tmp_path, capsys, kind):
    whole = tmp_path / "whole.klg"
    write_klg(whole, frames[:5])
    offsets = klg.open_log(whole, (WIDTH, HEIGHT))._offsets
    path = tmp_path / f"{kind}.klg"
    path.write_bytes(_damaged(whole.read_bytes(), offsets, kind))
    intact, account = DAMAGE[kind]
    expected = (
        f"kintinuous: warning: {path}: {account}",
        f"; reading the {intact} intact frames before it (0..{intact - 1})",
    )

    sequence = klg.open_log(path, (WIDTH, HEIGHT))
    line = one_line(capsys, *expected)
    assert line.startswith(expected[0]) and line.endswith(expected[1])
    assert len(sequence) == intact and sequence.damage.startswith(account)
    stamps = [stamp for stamp, _, _ in frames[:intact]]
    np.testing.assert_array_equal(sequence.timestamps, stamps)

    # reconstruct uses them by default, --skip-bad-frames or not
    truth = str(TINY / "groundtruth.txt")
    common = ["--intrinsics", INTRINSICS, "--size", "160x120", "--backend", "ref"]
    common += ["--groundtruth", truth, "--odometry", "groundtruth", "--resolution", "32"]
    for extra in ([], ["--skip-bad-frames"]):
        out = tmp_path / f"out{len(extra)}"
        assert main(["reconstruct", str(path), "--out", str(out), *common, *extra]) == 0
        one_line(capsys, *expected)
        trajectory = tum.read_trajectory(out / "trajectory.txt")
        np.testing.assert_allclose(trajectory.timestamps, stamps, atol=1e-6)

    # convert writes them, and only them
    folder = tmp_path / "folder"
    assert (
        main(["convert", str(path), str(folder), "--size", "160x120", "--intrinsics", INTRINSICS])
        == 0
    )
    assert f"wrote {intact} frames to {folder}" in capsys.readouterr().out
    written = tum.open_sequence(folder)
    np.testing.assert_array_equal(written.timestamps, stamps)
    for frame, (_, raw, _) in zip(written, frames, strict=False):
        assert np.abs(frame.depth - raw / 5000.0).max() <= 0.0004 + 1e-6


def test_a_bad_frame_in_the_middle_still_needs_skip_bad_frames(frames, tmp_path, capsys):
    """Only a damaged end is left out by default: frame 2 of 5 undecodable ends a run
    there (the 2 frames before it kept) unless --skip-bad-frames leaves it out."""
    path = tmp_path / "middle.klg"
    write_klg(path, frames[:5])
    offset = int(klg.open_log(path, (WIDTH, HEIGHT))._offsets[2])
    damaged = bytearray(path.read_bytes())
    damaged[offset : offset + 8] = b"notzlib!"
    path.write_bytes(bytes(damaged))
    common = ["--intrinsics", INTRINSICS, "--size", "160x120", "--backend", "ref"]
    common += ["--groundtruth", str(TINY / "groundtruth.txt"), "--odometry", "groundtruth"]
    common += ["--resolution", "32"]
    out = tmp_path / "out"
    assert main(["reconstruct", str(path), "--out", str(out), *common]) == 2
    one_line(capsys, f"frame 2: {path}: frame 2: depth is not zlib data", "2 frames done")
    again = [*common, "--overwrite", "--skip-bad-frames"]
    assert main(["reconstruct", str(path), "--out", str(out), *again]) == 0
    assert "kintinuous:" not in capsys.readouterr().err
    trajectory = tum.read_trajectory(out / "trajectory.txt")
    np.testing.assert_allclose(trajectory.timestamps, [frames[i][0] for i in (0, 1, 3, 4)])
    report = json.loads((out / "report.json").read_text())
    assert (report["frames"], report["skipped_frames"]) == (4, 1)
    assert report["skipped_reasons"][0].startswith("frame 2: ")


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
