"""TUM RGB-D folders: list parsing, association, lazy frames, cameras, ground truth, bad input.

Small sequences are written into tmp_path with known pixel values, so every number read back has
an exact expected value. The real-data tests read redkitchen from $KINTINUOUS_DATA (else
../shared/data beside the repository) and skip without it.
"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.camera import TUM_CAMERAS
from kintinuous_ref.datasets import data_folder, real_dataset, tum
from kintinuous_ref.errors import DatasetError

WIDTH, HEIGHT = 8, 6
CAMERA_JSON = {"fx": 10.0, "fy": 11.0, "cx": 3.5, "cy": 2.5, "width": WIDTH, "height": HEIGHT}
REDKITCHEN = data_folder() / "redkitchen"  # $KINTINUOUS_DATA, else ../shared/data


def raw_depth(index: int) -> np.ndarray:
    """The uint16 depth image of frame `index`: distinct values, some zeros (no measurement)."""
    raw = (1000 + 37 * index + np.arange(WIDTH * HEIGHT)).reshape(HEIGHT, WIDTH).astype(np.uint16)
    raw[0, :3] = 0
    return raw


def rgb_image(index: int) -> np.ndarray:
    """The RGB colour of frame `index`: R, G, B differ so a channel swap is visible."""
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    image[..., 0] = 200  # R
    image[..., 1] = 100 + index  # G
    image[..., 2] = 10  # B
    return image


def write_sequence(
    folder: Path,
    colour_times=(0.0, 0.0333, 0.0667),
    depth_times=(0.004, 0.0373, 0.0707),
    colour_ext="png",
    camera=True,
) -> Path:
    """A TUM folder with rgb.txt, depth.txt, images and (optionally) intrinsics.json."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines = ["# color images", "# timestamp filename"]
    for i, t in enumerate(colour_times):
        name = f"rgb/{t:.6f}.{colour_ext}"
        cv2.imwrite(str(folder / name), rgb_image(i)[..., ::-1])  # OpenCV writes BGR
        rgb_lines.append(f"{t:.6f} {name}")
    depth_lines = ["# depth maps"]
    for i, t in enumerate(depth_times):
        name = f"depth/{t:.6f}.png"
        cv2.imwrite(str(folder / name), raw_depth(i))
        depth_lines.append(f"{t:.6f} {name}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if camera:
        (folder / "intrinsics.json").write_text(json.dumps(CAMERA_JSON))
    return folder


def one_line_error(excinfo: pytest.ExceptionInfo, *fragments: str) -> None:
    message = str(excinfo.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message


# --- association ------------------------------------------------------------------------------


def test_associate_is_greedy_on_smallest_difference_and_one_to_one():
    # Hand-worked: 0.010-0.012 (dt 0.002) is taken first, so 0.000 cannot also use 0.012
    # (plain nearest-neighbour would pair both); 0.100 has nothing within 0.02; 0.050 pairs 0.061.
    first = np.array([0.000, 0.010, 0.050, 0.100])
    second = np.array([0.061, 0.012, 0.500])
    i, j = tum.associate(first, second)
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(1, 1), (2, 0)]


def brute_force_associate(first, second, max_difference):
    """TUM associate.py's rule written the slow, obvious way: all pairs, smallest |dt| first."""
    candidates = sorted(
        (abs(a - b), i, j)
        for i, a in enumerate(first)
        for j, b in enumerate(second)
        if abs(a - b) <= max_difference
    )
    used_i, used_j, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_i and j not in used_j:
            used_i.add(i)
            used_j.add(j)
            pairs.append((i, j))
    return sorted(pairs, key=lambda pair: first[pair[0]])


def test_associate_matches_brute_force_on_random_jittered_streams():
    rng = np.random.default_rng(3)
    for _ in range(20):
        first = np.sort(rng.uniform(0, 2, 60))
        second = rng.permutation(rng.uniform(0, 2, 50))  # unsorted on purpose
        i, j = tum.associate(first, second, 0.02)
        expected = brute_force_associate(first, second, 0.02)
        assert list(zip(i.tolist(), j.tolist(), strict=True)) == expected


def test_nearest_indices_respects_the_window():
    stamps = np.array([1.0, 1.1, 1.2])
    np.testing.assert_array_equal(
        tum.nearest_indices(np.array([0.99, 1.06, 1.14, 1.5, 0.5]), stamps, 0.02),
        [0, -1, -1, -1, -1],
    )
    np.testing.assert_array_equal(
        tum.nearest_indices(np.array([1.04, 1.06, 1.19]), stamps, 0.1), [0, 1, 2]
    )


# --- reading frames ---------------------------------------------------------------------------


def test_frames_have_metric_depth_and_rgb_colour(tmp_path):
    sequence = tum.open_sequence(write_sequence(tmp_path / "seq"))
    assert len(sequence) == 3
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.0333, 0.0667])
    for i, frame in enumerate(sequence):
        assert frame.index == i
        assert frame.colour.dtype == np.uint8 and frame.colour.shape == (HEIGHT, WIDTH, 3)
        np.testing.assert_array_equal(frame.colour, rgb_image(i))  # PNG is lossless
        assert frame.depth.dtype == np.float32
        # float32 division by 5000 is the definition; 0 (no measurement) stays 0.
        np.testing.assert_array_equal(
            frame.depth, raw_depth(i).astype(np.float32) / np.float32(5000)
        )
        assert np.count_nonzero(frame.depth == 0) == 3


def test_jpeg_colour_is_read_as_rgb(tmp_path):
    sequence = tum.open_sequence(write_sequence(tmp_path / "seq", colour_ext="jpg"))
    colour = sequence[1].colour
    # JPEG is lossy: flat colours come back within a few levels.
    np.testing.assert_allclose(colour.reshape(-1, 3).mean(0), rgb_image(1)[0, 0], atol=3)


def test_colour_and_depth_are_paired_by_nearest_timestamp(tmp_path):
    # depth 0.045 is closest to colour 0.0333 (dt 0.0117) but colour 0.05 is closer (0.005);
    # colour 0.2 has no depth within 0.02 s and is dropped.
    folder = write_sequence(
        tmp_path / "seq",
        colour_times=(0.0, 0.0333, 0.05, 0.2),
        depth_times=(0.001, 0.045, 0.3),
    )
    sequence = tum.open_sequence(folder)
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.05])
    np.testing.assert_array_equal(sequence[1].colour, rgb_image(2))
    np.testing.assert_array_equal(np.rint(sequence[1].depth * 5000), raw_depth(1))


def test_associations_file_wins_over_lists(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    # Pair colour 2 with depth 0 and colour 0 with depth 2, depth-first, on purpose.
    (folder / "associations.txt").write_text(
        "0.004000 depth/0.004000.png 0.066700 rgb/0.066700.png\n"
        "0.070700 depth/0.070700.png 0.000000 rgb/0.000000.png\n"
    )
    sequence = tum.open_sequence(folder)
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.0667])
    np.testing.assert_array_equal(sequence[0].colour, rgb_image(0))
    np.testing.assert_array_equal(np.rint(sequence[0].depth * 5000), raw_depth(2))
    np.testing.assert_array_equal(sequence[1].colour, rgb_image(2))
    np.testing.assert_array_equal(np.rint(sequence[1].depth * 5000), raw_depth(0))


def test_frames_are_read_lazily(tmp_path, monkeypatch):
    times = tuple(i / 30 for i in range(40))
    sequence = tum.open_sequence(write_sequence(tmp_path / "seq", times, times))
    reads = []
    real_imdecode = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda *a: reads.append(a[0]) or real_imdecode(*a))
    assert len(tum.open_sequence(tmp_path / "seq")) == 40
    assert reads == []  # opening reads only the list files
    frames = list(sequence.frames(start=10, count=3))
    assert [f.index for f in frames] == [10, 11, 12]
    assert len(reads) == 6  # one colour + one depth image per frame asked for
    assert sequence[-1].index == 39
    with pytest.raises(IndexError):
        sequence[40]


# --- camera -----------------------------------------------------------------------------------


def test_camera_from_intrinsics_json(tmp_path):
    camera = tum.open_sequence(write_sequence(tmp_path / "seq")).camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (10.0, 11.0, 3.5, 2.5)
    assert camera.depth_scale == 5000.0


def test_camera_from_folder_name_and_explicit_override(tmp_path):
    folder = write_sequence(tmp_path / "rgbd_dataset_freiburg2_desk", camera=False)
    assert tum.open_sequence(folder).camera == TUM_CAMERAS["freiburg2"]
    explicit = tum.open_sequence(folder, intrinsics="500,501,3.5,2.5").camera
    # The image size of an fx,fy,cx,cy camera comes from the images themselves.
    assert (explicit.fx, explicit.fy, explicit.width, explicit.height) == (500, 501, WIDTH, HEIGHT)
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA_JSON | {"fx": 12.0}))
    assert tum.open_sequence(folder, intrinsics=str(tmp_path / "cam.json")).camera.fx == 12.0


def test_unknown_camera_is_a_clear_error(tmp_path):
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(write_sequence(tmp_path / "seq", camera=False))
    one_line_error(excinfo, "seq", "--intrinsics", "intrinsics.json")


# --- bad input --------------------------------------------------------------------------------


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(tmp_path / "nothing")
    one_line_error(excinfo, "nothing", "not found")


def test_missing_list_file(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    (folder / "depth.txt").unlink()
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)
    one_line_error(excinfo, "depth.txt", "not found")


def test_listed_image_missing(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    (folder / "rgb" / "0.033300.png").unlink()
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)
    one_line_error(excinfo, "0.033300.png", "not found")


@pytest.mark.parametrize("kind", ["rgb", "depth"])
def test_unreadable_image(tmp_path, kind):
    folder = write_sequence(tmp_path / "seq")
    name = "rgb/0.033300.png" if kind == "rgb" else "depth/0.037300.png"
    (folder / name).write_bytes(b"not a png at all")
    sequence = tum.open_sequence(folder)
    with pytest.raises(DatasetError) as excinfo:
        sequence[1]
    one_line_error(excinfo, name.split("/")[1], "cannot read")


def test_eight_bit_depth(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    cv2.imwrite(str(folder / "depth/0.004000.png"), (raw_depth(0) % 256).astype(np.uint8))
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)[0]
    one_line_error(excinfo, "0.004000.png", "uint8", "16-bit")


def test_colour_depth_image(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    cv2.imwrite(str(folder / "depth/0.004000.png"), np.dstack([raw_depth(0)] * 3))
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)[0]
    one_line_error(excinfo, "0.004000.png", "3 channels")


def test_colour_depth_size_mismatch(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    cv2.imwrite(str(folder / "rgb/0.000000.png"), np.zeros((HEIGHT, WIDTH + 2, 3), np.uint8))
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)[0]
    one_line_error(excinfo, "rgb/0.000000.png", "10x6", "8x6")  # the colour image is wrong


def test_image_size_differs_from_camera(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    (folder / "intrinsics.json").write_text(json.dumps(CAMERA_JSON | {"width": 640}))
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)[0]
    one_line_error(excinfo, "0.004000.png", "8x6", "640x6")


def test_empty_sequence(tmp_path):
    folder = write_sequence(tmp_path / "seq", colour_times=(0.0,), depth_times=(0.5,))
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)
    one_line_error(excinfo, "seq", "no frames")


@pytest.mark.parametrize(
    ("file", "line", "fragment"),
    [
        ("rgb.txt", "zero rgb/0.000000.png", "rgb.txt:5"),
        ("rgb.txt", "0.1", "rgb.txt:5"),
        ("associations.txt", "0.0 rgb/0.000000.png depth/0.004000.png", "associations.txt:2"),
    ],
)
def test_unparseable_list_line_names_file_and_line(tmp_path, file, line, fragment):
    folder = write_sequence(tmp_path / "seq", colour_times=(0.0, 0.0333), depth_times=(0.0, 0.04))
    path = folder / file
    before = path.read_text() if path.exists() else "0.0 rgb/0.000000.png 0.0 depth/0.000000.png\n"
    path.write_text(before + line + "\n")
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder)
    one_line_error(excinfo, fragment)


# --- trajectories and ground truth ------------------------------------------------------------


def random_poses(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([se3.exp(rng.normal(0, 1.0, 6)) for _ in range(count)])


def test_trajectory_round_trip(tmp_path):
    trajectory = tum.Trajectory(1.0 + np.arange(50) / 30.0, random_poses(50, 7))
    tum.write_trajectory(tmp_path / "out" / "traj.txt", trajectory)
    back = tum.read_trajectory(tmp_path / "out" / "traj.txt")
    # Timestamps are written to 1e-6 s and quaternions/positions to 1e-9: the tolerances.
    np.testing.assert_allclose(back.timestamps, trajectory.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, trajectory.poses, atol=1e-8)


def test_unparseable_trajectory_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError) as excinfo:
        tum.read_trajectory(path)
    one_line_error(excinfo, "traj.txt:3", "8 numbers")


def test_groundtruth_for_frames_takes_nearest_pose(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    # Ground truth at 100 Hz, offset by 3 ms from the colour stamps 0, 0.0333, 0.0667.
    gt = tum.Trajectory(-0.007 + np.arange(12) / 100.0, random_poses(12, 2))
    tum.write_trajectory(folder / "groundtruth.txt", gt)
    sequence = tum.open_sequence(folder)
    assert len(sequence.groundtruth) == 12
    per_frame = sequence.groundtruth_for_frames()
    # Nearest: 0.0 -> 0.003 (index 1), 0.0333 -> 0.033 (4), 0.0667 -> 0.063 (7).
    np.testing.assert_allclose(per_frame.timestamps, sequence.timestamps)
    np.testing.assert_allclose(per_frame.poses, gt.poses[[1, 4, 7]], atol=1e-8)


def test_groundtruth_missing_for_a_frame(tmp_path):
    folder = write_sequence(tmp_path / "seq")
    tum.write_trajectory(
        folder / "groundtruth.txt", tum.Trajectory([0.0, 0.03], random_poses(2, 1))
    )
    with pytest.raises(DatasetError) as excinfo:
        tum.open_sequence(folder).groundtruth_for_frames()
    one_line_error(excinfo, "groundtruth.txt", "frame 2")


def test_no_groundtruth(tmp_path):
    sequence = tum.open_sequence(write_sequence(tmp_path / "seq"))
    assert sequence.groundtruth is None
    with pytest.raises(DatasetError):
        sequence.groundtruth_for_frames()


# --- real data --------------------------------------------------------------------------------


def test_real_datasets_are_looked_for_in_kintinuous_data(tmp_path, monkeypatch):
    monkeypatch.setenv("KINTINUOUS_DATA", str(tmp_path))
    assert data_folder() == tmp_path and real_dataset("redkitchen") is None  # absent: skip
    (tmp_path / "redkitchen").mkdir()
    assert real_dataset("redkitchen") == tmp_path / "redkitchen"
    monkeypatch.delenv("KINTINUOUS_DATA")
    assert data_folder().parts[-2:] == ("shared", "data")  # beside the repository


needs_redkitchen = pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"{REDKITCHEN} not present")


@pytest.mark.realdata
@needs_redkitchen
def test_redkitchen_layout_and_camera():
    sequence = tum.open_sequence(REDKITCHEN)
    assert len(sequence) == 300
    assert sequence.camera.fx == 585.0 and sequence.camera.cy == 240.0
    # README: timestamps are 1.0 + i / 30 (written to 1e-6 s).
    np.testing.assert_allclose(sequence.timestamps, 1.0 + np.arange(300) / 30.0, atol=1e-6)


@pytest.mark.realdata
@needs_redkitchen
def test_redkitchen_first_frame_against_an_independent_decoder():
    from PIL import Image  # a second PNG/JPEG decoder (matplotlib's dependency)

    frame = tum.open_sequence(REDKITCHEN)[0]
    raw = np.array(Image.open(REDKITCHEN / "depth" / "1.000000.png")).astype(np.float64)
    assert raw.shape == (480, 640)
    expected_median = np.median(raw[raw > 0]) / 5000.0
    assert 0.5 < expected_median < 4.0  # a kitchen seen by a Kinect, in metres
    np.testing.assert_allclose(np.median(frame.depth[frame.depth > 0]), expected_median, rtol=1e-6)
    np.testing.assert_allclose(frame.depth, raw / 5000.0, rtol=1e-6)
    colour = np.array(Image.open(REDKITCHEN / "rgb" / "1.000000.jpg").convert("RGB"))
    # Two JPEG decoders may round the inverse DCT differently: a level or two at most.
    difference = np.abs(frame.colour.astype(int) - colour.astype(int))
    assert difference.mean() < 1.0 and difference.max() <= 8
    # ... whereas swapped channels would be far off.
    assert np.abs(frame.colour[..., ::-1].astype(int) - colour.astype(int)).mean() > 5


@pytest.mark.realdata
@needs_redkitchen
def test_redkitchen_groundtruth_per_frame():
    sequence = tum.open_sequence(REDKITCHEN)
    per_frame = sequence.groundtruth_for_frames()
    assert len(per_frame) == 300
    # Frame 0's pose from the README's first groundtruth line, parsed here by hand.
    line = next(
        ln for ln in (REDKITCHEN / "groundtruth.txt").read_text().splitlines() if ln[0] != "#"
    )
    values = np.array(line.split(), dtype=float)
    np.testing.assert_allclose(per_frame.positions[0], values[1:4])
    x, y, z, w = values[4:] / np.linalg.norm(values[4:])
    # z-axis of the camera = third column of R(q).
    np.testing.assert_allclose(
        per_frame.poses[0][:3, 2],
        [2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)],
        atol=1e-9,
    )
