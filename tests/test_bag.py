"""ROS1 and ROS2 bags: written here with rosbags' own writers from data/tiny_desk, read back and
reconstructed; the truth is the TUM folder they were made from."""

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tiny_desk import TINY, tum_frames

from kintinuous_ref.camera import load_intrinsics_json
from kintinuous_ref.datasets import bag, tum
from kintinuous_ref.errors import DatasetError
from kintinuous_ref.program.cli import main

TUM_TOPICS = ("/camera/rgb/image_color", "/camera/depth/image", "/camera/rgb/camera_info")
OTHER_TOPICS = ("/cam/colour", "/cam/depth_mm", "/cam/info")
DEPTH_DELAY = 0.004  # depth stamped 4 ms after colour, as the Kinect's streams are not in step


def write_bag(
    path,
    ros2=False,
    topics=TUM_TOPICS,
    depth_encoding="32FC1",
    colour="rgb8",
    pad=0,
    compression=None,
):
    """A bag of tiny_desk: colour, depth (32FC1 metres with NaN holes, or 16UC1 millimetres with
    `pad` bytes at the end of each row), camera info and an unrelated topic. `compression`
    ("BZ2", "LZ4") compresses a ROS1 bag's chunks."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types = store.types
    camera = load_intrinsics_json(TINY / "intrinsics.json")
    if ros2:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=9), store.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1
        if compression is not None:
            writer.set_compression(getattr(Writer.CompressionFormat, compression))

    def header(stamp):
        seconds = int(np.floor(stamp))
        time = types["builtin_interfaces/msg/Time"](
            sec=seconds, nanosec=int(round((stamp - seconds) * 1e9))
        )
        fields = {"stamp": time, "frame_id": "camera"}
        return types["std_msgs/msg/Header"](**({} if ros2 else {"seq": 0}), **fields)

    def image(stamp, array, encoding, step=None):
        height, width = array.shape[:2]
        data = np.ascontiguousarray(array).view(np.uint8).reshape(height, -1)
        step = step or data.shape[1]
        rows = np.zeros((height, step), np.uint8)
        rows[:, : data.shape[1]] = data
        return types["sensor_msgs/msg/Image"](
            header=header(stamp),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=step,
            data=rows.reshape(-1),
        )

    k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    names = ("D", "K", "R", "P") if not ros2 else ("d", "k", "r", "p")
    info = types["sensor_msgs/msg/CameraInfo"](
        header=header(1.0),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        **dict(
            zip(
                names,
                (
                    np.zeros(5),
                    np.array(k),
                    np.eye(3).reshape(-1),
                    np.array([*k[:3], 0.0, *k[3:6], 0.0, *k[6:], 0.0]),
                ),
                strict=True,
            )
        ),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    with writer:
        kinds = {
            "colour": "sensor_msgs/msg/Image",
            "depth": "sensor_msgs/msg/Image",
            "info": "sensor_msgs/msg/CameraInfo",
        }
        connections = {
            role: writer.add_connection(topic, kinds[role], typestore=store)
            for role, topic in zip(("colour", "depth", "info"), topics, strict=True)
        }
        other = writer.add_connection("/rosout_note", "std_msgs/msg/String", typestore=store)
        nanoseconds = lambda stamp: int(round((stamp + 0.001) * 1e9))  # noqa: E731 received 1 ms on
        for stamp, raw, rgb in tum_frames():
            pixels = rgb[..., ::-1] if colour == "bgr8" else rgb
            message = image(stamp, pixels, colour)
            writer.write(
                connections["colour"], nanoseconds(stamp), serialize(message, kinds["colour"])
            )
            if stamp == 1.0:
                writer.write(
                    connections["info"], nanoseconds(stamp), serialize(info, kinds["info"])
                )
                note = types["std_msgs/msg/String"](data="hello")
                writer.write(other, nanoseconds(stamp), serialize(note, "std_msgs/msg/String"))
            if depth_encoding == "32FC1":
                metres = raw.astype(np.float32) / np.float32(5000.0)
                metres[raw == 0] = np.nan  # TUM's bags mark missing depth with NaN
                message = image(stamp + DEPTH_DELAY, metres, "32FC1")
            else:
                millimetres = np.round(raw / 5.0).astype(np.uint16)
                step = camera.width * 2 + pad
                message = image(stamp + DEPTH_DELAY, millimetres, "16UC1", step)
            depth_time = nanoseconds(stamp + DEPTH_DELAY)
            writer.write(connections["depth"], depth_time, serialize(message, kinds["depth"]))
    return path


@pytest.fixture(scope="module")
def ros1_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bags") / "desk.bag")


def test_a_tum_layout_ros1_bag_reads_as_its_tum_folder(ros1_bag):
    sequence = bag.open_bag(ros1_bag)
    folder = tum.open_sequence(TINY)
    assert sequence.camera == folder.camera  # from camera_info, equal to intrinsics.json
    assert len(sequence) == len(folder) == 10
    np.testing.assert_allclose(sequence.timestamps, folder.timestamps, atol=1e-9)
    for i in (0, 4, 9):
        ours, truth = sequence[i], folder[i]
        np.testing.assert_array_equal(ours.colour, truth.colour)
        np.testing.assert_array_equal(ours.depth, truth.depth)  # NaN holes read as 0


def test_a_ros2_bag_with_millimetre_depth_bgr_and_other_topics(tmp_path, capsys):
    path = write_bag(
        tmp_path / "desk_ros2",
        ros2=True,
        topics=OTHER_TOPICS,
        depth_encoding="16UC1",
        colour="bgr8",
        pad=6,
    )
    folder = tum.open_sequence(TINY)
    sequence = bag.open_bag(path, OTHER_TOPICS)
    assert len(sequence) == 10 and sequence.camera == folder.camera
    for i in (0, 9):
        ours, truth = sequence[i], folder[i]
        np.testing.assert_array_equal(ours.colour, truth.colour)  # bgr8 turned back to RGB
        assert np.abs(ours.depth - truth.depth).max() <= 0.0004 + 1e-6  # whole millimetres
        assert ((ours.depth == 0) == (truth.depth == 0)).all()

    # Without --topics the bag has none of the known names: one line listing what it has.
    out = str(tmp_path / "out")
    assert main(["reconstruct", str(path), "--out", out, "--backend", "ref"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(path) in err and "--topics" in err
    for topic in (*OTHER_TOPICS, "/rosout_note"):
        assert topic in err
    assert "/camera/rgb/image_color" in err  # what it looked for

    # --topics with a name the bag lacks: the same one-line error.
    topics = ",".join((OTHER_TOPICS[0], "/nope", OTHER_TOPICS[2]))
    assert main(["reconstruct", str(path), "--out", out, "--topics", topics]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.count("\n") == 0 and "/nope" in err and "/cam/depth_mm (sensor_msgs/msg/Image)" in err
    )


@pytest.mark.slow
def test_reconstructing_a_bag_tracks_like_its_tum_folder(ros1_bag, tmp_path):
    """icp+rgbd on the cpu backend over the 10 frames. A 32FC1 bag holds the folder's depth and
    colour bit for bit, so the trajectories agree to rounding (1e-6 m, 1e-6 rad)."""
    common = ["--odometry", "icp+rgbd", "--backend", "cpu", "--resolution", "64"]
    assert main(["reconstruct", str(TINY), "--out", str(tmp_path / "tum"), *common]) == 0
    truth = ["--groundtruth", str(TINY / "groundtruth.txt")]
    assert (
        main(["reconstruct", str(ros1_bag), "--out", str(tmp_path / "bag"), *common, *truth]) == 0
    )
    folder = tum.read_trajectory(tmp_path / "tum" / "trajectory.txt")
    bagged = tum.read_trajectory(tmp_path / "bag" / "trajectory.txt")
    assert len(bagged) == len(folder) == 10
    np.testing.assert_allclose(bagged.timestamps, folder.timestamps, atol=1e-6)
    np.testing.assert_allclose(bagged.poses, folder.poses, atol=1e-6)
    groundtruth = tum.open_sequence(TINY).groundtruth_for_frames()
    assert np.linalg.norm(groundtruth.positions[-1] - groundtruth.positions[0]) > 0.1  # it moved


def test_topics_that_are_not_images_are_refused_naming_what_would_work(tmp_path, capsys):
    path = write_bag(tmp_path / "desk.bag", topics=OTHER_TOPICS)
    out = str(tmp_path / "out")
    found = "the bag's image topics: /cam/colour, /cam/depth_mm; its camera info topics: /cam/info"
    topics = "/rosout_note,/cam/info,/cam/info"
    assert main(["reconstruct", str(path), "--out", out, "--topics", topics]) == 2
    assert capsys.readouterr().err == (
        f"kintinuous: error: {path}: rgb topic /rosout_note carries std_msgs/msg/String, not "
        "sensor_msgs/msg/Image; depth topic /cam/info carries sensor_msgs/msg/CameraInfo, not "
        f"sensor_msgs/msg/Image; {found} (pass --topics rgb,depth,info)\n"
    )
    # an image as the camera info: refused, unless --intrinsics gives the camera
    topics = "/cam/colour,/cam/depth_mm,/cam/depth_mm"
    assert main(["convert", str(path), str(tmp_path / "folder"), "--topics", topics]) == 2
    assert capsys.readouterr().err == (
        f"kintinuous: error: {path}: info topic /cam/depth_mm carries sensor_msgs/msg/Image, not "
        f"sensor_msgs/msg/CameraInfo; {found} (pass --topics rgb,depth,info)\n"
    )
    assert not (tmp_path / "folder").exists()
    camera = load_intrinsics_json(TINY / "intrinsics.json")
    topics = ("/cam/colour", "/cam/depth_mm", "/cam/depth_mm")
    assert len(bag.open_bag(path, topics, camera)) == 10


def copy_bag(source, target, cut):
    """A copy of a ROS1 bag whose messages `cut` ((topic, number) pairs) keep 100 bytes."""
    from rosbags.rosbag1 import Reader, Writer

    seen = {}
    with Reader(source) as reader, Writer(target) as writer:
        made = {
            c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
            for c in reader.connections
        }
        for connection, time, raw in reader.messages():
            number = seen[connection.topic] = seen.get(connection.topic, -1) + 1
            damaged = (connection.topic, number) in cut
            writer.write(made[connection.id], time, raw[:100] if damaged else raw)
    return target


def test_a_bag_whose_last_images_are_cut_reads_the_frames_before(tmp_path, capsys):
    whole = write_bag(tmp_path / "whole.bag")
    depth = TUM_TOPICS[1]
    path = copy_bag(whole, tmp_path / "cut.bag", {(depth, 8), (depth, 9)})
    sequence = bag.open_bag(path)
    assert capsys.readouterr().err == (
        f"kintinuous: warning: {path}: {depth}: message 8 and those after it cannot be read "
        "(Invalid sequence length 76800 at offset 48.); reading the 8 messages before it\n"
    )
    folder = tum.open_sequence(TINY)
    assert len(sequence) == 8
    np.testing.assert_allclose(sequence.timestamps, folder.timestamps[:8], atol=1e-9)
    np.testing.assert_array_equal(sequence[7].depth, folder[7].depth)

    # the same damage in the middle is an error naming the message
    middle = copy_bag(whole, tmp_path / "middle.bag", {(depth, 4)})
    with pytest.raises(DatasetError) as excinfo:
        bag.open_bag(middle)
    assert str(excinfo.value) == (
        f"{middle}: {depth}: message 4 cannot be read (Invalid sequence length 76800 at offset 48.)"
    )


def message_ends(path):
    """Per frame of a whole ROS1 bag, the file offset where the later of its colour and depth
    messages ends: found by searching the file for each message's bytes as rosbags reads them
    (every message differs, by its stamp at least), not by parsing the bag's records."""
    from rosbags.rosbag1 import Reader

    data = path.read_bytes()
    ends = {}
    with Reader(path) as reader:
        for connection, time, raw in reader.messages():
            start = data.find(raw)
            assert start > 0 and data.find(raw, start + 1) < 0  # found once
            ends[connection.topic, time] = start + len(raw)
    sequence = bag.open_bag(path)
    frames = [
        max(ends[TUM_TOPICS[0], colour], ends[TUM_TOPICS[1], depth])
        for colour, depth, _ in sequence._pairs
    ]
    sequence.close()
    return frames


@pytest.fixture(scope="module")
def whole_ros1_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("whole") / "whole.bag")


def ros1_cuts(path):
    """Where a recording may stop: inside frame 3's last message (first chunk), inside frame
    9's (second chunk), just after the last chunk's data, and inside the index that ends the
    file."""
    from rosbags.rosbag1 import Reader

    ends, size = message_ends(path), path.stat().st_size
    with Reader(path) as reader:
        chunks = sorted(reader.chunks.values(), key=lambda chunk: chunk.datapos)
    assert len(chunks) == 2 and ends[7] < chunks[1].datapos < ends[8]  # frames 8, 9 in chunk 2
    last_chunk_end = chunks[-1].datapos + chunks[-1].datasize
    return {
        "inside the first chunk": ends[3] - 1000,
        "inside the second chunk": ends[9] - 1,
        "after the last chunk": last_chunk_end + 10,
        "inside the index": size - 100,
    }


@pytest.mark.parametrize(
    "where",
    [
        "inside the first chunk",
        "inside the second chunk",
        "after the last chunk",
        "inside the index",
    ],
)
def test_a_ros1_bag_cut_short_reads_its_intact_frames_bit_for_bit(
    whole_ros1_bag, tmp_path, capsys, where
):
    cut = ros1_cuts(whole_ros1_bag)[where]
    kept = sum(end <= cut for end in message_ends(whole_ros1_bag))
    assert kept == {"inside the first chunk": 3, "inside the second chunk": 9}.get(where, 10)
    path = tmp_path / "cut.bag"
    path.write_bytes(whole_ros1_bag.read_bytes()[:cut])
    from rosbags.rosbag1 import Reader, ReaderError

    with pytest.raises(ReaderError), Reader(path):  # what rosbags alone makes of it
        pass

    sequence = bag.open_bag(path)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"kintinuous: warning: {path}: ")
    assert err.endswith(
        f"; reading the {kept} frames whose messages lie before it (0..{kept - 1})\n"
    )
    whole = bag.open_bag(whole_ros1_bag)
    assert len(sequence) == kept and sequence.camera == whole.camera
    np.testing.assert_array_equal(sequence.timestamps, whole.timestamps[:kept])
    for i in range(kept):
        ours, truth = sequence[i], whole[i]
        np.testing.assert_array_equal(ours.colour, truth.colour)
        np.testing.assert_array_equal(ours.depth, truth.depth)
    sequence.close()
    whole.close()


def test_a_ros1_bag_cut_before_its_first_message_is_refused_in_one_line(
    whole_ros1_bag, tmp_path, capsys
):
    path = tmp_path / "header.bag"
    path.write_bytes(whole_ros1_bag.read_bytes()[:3000])  # inside the bag header's padding
    assert main(["convert", str(path), str(tmp_path / "folder")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"kintinuous: error: {path}: cannot open as a ROS bag (")
    assert err.count("\n") == 1 and not (tmp_path / "folder").exists()


def test_a_cut_ros1_bag_converts_to_its_intact_frames(whole_ros1_bag, tmp_path, capsys):
    cut = ros1_cuts(whole_ros1_bag)["inside the second chunk"]
    path = tmp_path / "cut.bag"
    path.write_bytes(whole_ros1_bag.read_bytes()[:cut])
    assert main(["convert", str(path), str(tmp_path / "folder")]) == 0
    assert "reading the 9 frames" in capsys.readouterr().err
    folder = tum.open_sequence(tmp_path / "folder")
    truth = tum.open_sequence(TINY)
    assert len(folder) == 9
    np.testing.assert_array_equal(folder[8].colour, truth[8].colour)
    np.testing.assert_array_equal(folder[8].depth, truth[8].depth)


def test_a_ros1_bag_never_indexed_reads_every_frame(whole_ros1_bag, tmp_path, capsys):
    """A recorder killed before it closed the bag leaves index_pos 0 in the bag header and no
    index: rosbags asks for a reindex, the frames are read from the chunks."""
    data = bytearray(whole_ros1_bag.read_bytes())
    field = data.index(b"index_pos=") + len(b"index_pos=")
    (index_start,) = struct.unpack("<Q", data[field : field + 8])
    data[field : field + 8] = bytes(8)
    path = tmp_path / "unindexed.bag"
    path.write_bytes(bytes(data[:index_start]))
    sequence = bag.open_bag(path)
    assert capsys.readouterr().err == (
        f"kintinuous: warning: {path}: it was never indexed (its recording did not end); "
        "reading the 10 frames whose messages lie before it (0..9)\n"
    )
    whole = bag.open_bag(whole_ros1_bag)
    for i in (0, 9):
        np.testing.assert_array_equal(sequence[i].depth, whole[i].depth)
        np.testing.assert_array_equal(sequence[i].colour, whole[i].colour)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_a_damaged_and_cut_ros1_bag_opens_or_is_refused_in_one_line(whole_ros1_bag, tmp_path, data):
    """Bytes overwritten at random places, then the bag cut at a random length: opened (its
    whole messages read) or refused with a DatasetError, never another exception."""
    damaged = bytearray(whole_ros1_bag.read_bytes())
    for _ in range(data.draw(st.integers(0, 8))):
        at = data.draw(st.integers(0, len(damaged) - 1))
        damaged[at] = data.draw(st.integers(0, 255))
    path = tmp_path / "damaged.bag"
    path.write_bytes(bytes(damaged[: data.draw(st.integers(0, len(damaged)))]))
    try:
        bag.open_bag(path).close()
    except DatasetError:
        pass


@pytest.mark.parametrize("compression", ["BZ2", "LZ4"])
def test_a_compressed_ros1_bag_cut_in_its_last_chunk_reads_the_chunks_before(
    tmp_path, capsys, compression
):
    """A compressed chunk cut short cannot be decompressed: the frames of the whole chunks
    before it are read (frames 0..7, as in the uncompressed bag: chunks close at the same
    uncompressed size)."""
    from rosbags.rosbag1 import Reader

    whole = write_bag(tmp_path / "whole.bag", compression=compression)
    with Reader(whole) as reader:
        last = max(reader.chunks.values(), key=lambda chunk: chunk.datapos)
        assert len(reader.chunks) == 2
    path = tmp_path / "cut.bag"
    path.write_bytes(whole.read_bytes()[: last.datapos + last.datasize // 2])
    sequence = bag.open_bag(path)
    assert "reading the 8 frames whose messages lie before it (0..7)" in capsys.readouterr().err
    intact = bag.open_bag(whole)
    assert len(sequence) == 8
    for i in (0, 7):
        np.testing.assert_array_equal(sequence[i].colour, intact[i].colour)
        np.testing.assert_array_equal(sequence[i].depth, intact[i].depth)
