"""ROS1 bags and ROS2 bag folders, read through `rosbags`.

A frame is a colour image and the depth image nearest to it in time (header stamps, paired as
TUM's associate.py pairs its lists, within 0.02 s); the camera comes from the first CameraInfo
message. Opening a bag reads every image message once for its stamp and keeps only the stamps;
frames are then read one at a time from the bag.

Colour: rgb8, bgr8, rgba8, bgra8 or mono8. Depth: 32FC1 metres (NaN: no measurement) or 16UC1
millimetres. Topics default to those of the TUM RGB-D bags, then to those of the RealSense ROS
driver with depth aligned to colour; other names are given as `rgb,depth,info`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets.tum import (
    MAX_TIME_DIFFERENCE,
    Frame,
    FrameSequence,
    associate,
    read_trajectory,
)
from kintinuous_ref.errors import DatasetError

# (colour, depth, camera info): TUM RGB-D's bags, then the RealSense driver's aligned topics.
TOPIC_SETS = (
    ("/camera/rgb/image_color", "/camera/depth/image", "/camera/rgb/camera_info"),
    (
        "/camera/color/image_raw",
        "/camera/aligned_depth_to_color/image_raw",
        "/camera/color/camera_info",
    ),
)
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
IMAGE, CAMERA_INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"  # rosbags' names


def is_bag(path: Path) -> bool:
    """A ROS1 `.bag` file, a ROS2 bag folder (with metadata.yaml) or a ROS2 storage file."""
    path = Path(path)
    return path.suffix in BAG_SUFFIXES or (path / "metadata.yaml").is_file()


def parse_topics(text: str) -> tuple[str, str, str]:
    """The command line's `rgb,depth,info` topic names."""
    parts = [part.strip() for part in text.split(",")]
    if len(parts) != 3 or not all(parts):
        raise DatasetError(f"--topics expects three names rgb,depth,info, got {text!r}")
    return parts[0], parts[1], parts[2]


class BagSequence(FrameSequence):
    """Colour/depth pairs of a bag; each frame is read from the bag when asked for."""

    def __init__(
        self,
        path: Path,
        reader: Any,
        connections: tuple[Any, Any],
        camera: Intrinsics,
        pairs: list[tuple[int, int, float]],
        groundtruth_path: Path | None = None,
    ) -> None:
        self.path = Path(path)
        self.name = self.path.stem
        self.camera = camera
        self._reader = reader
        self._connections = connections
        self._pairs = pairs  # (colour bag time ns, depth bag time ns, colour stamp s) per frame
        self.timestamps = np.array([stamp for _, _, stamp in pairs], dtype=np.float64)
        self.groundtruth_path = groundtruth_path
        self.groundtruth = read_trajectory(groundtruth_path) if groundtruth_path else None

    def _read(self, index: int) -> Frame:
        colour_time, depth_time, stamp = self._pairs[index]
        wanted = {
            (self._connections[0].topic, colour_time): "colour",
            (self._connections[1].topic, depth_time): "depth",
        }
        found: dict[str, Any] = {}
        window = (min(colour_time, depth_time), max(colour_time, depth_time) + 1)
        for connection, time, raw in self._reader.messages(
            connections=self._connections, start=window[0], stop=window[1]
        ):
            role = wanted.get((connection.topic, time))
            if role is not None and role not in found:
                found[role] = self._reader.deserialize(raw, connection.msgtype)
        if len(found) != 2:
            raise DatasetError(f"{self.path}: frame {index}: its messages cannot be read again")
        colour = _colour_image(found["colour"], self.path, index)
        depth = _depth_image(found["depth"], self.path, index)
        for what, image in (("colour", colour), ("depth", depth)):
            if image.shape[:2] != (self.camera.height, self.camera.width):
                raise DatasetError(
                    f"{self.path}: frame {index}: {what} image is {image.shape[1]}x"
                    f"{image.shape[0]} but the camera is {self.camera.width}x{self.camera.height}"
                )
        return Frame(index=index, timestamp=stamp, colour=colour, depth=depth)

    def close(self) -> None:
        self._reader.close()


def open_bag(
    path: Path,
    topics: tuple[str, str, str] | None = None,
    camera: Intrinsics | None = None,
    groundtruth: Path | None = None,
    max_difference: float = MAX_TIME_DIFFERENCE,
) -> BagSequence:
    """Open a bag and pair its colour and depth images. `camera` replaces the bag's CameraInfo;
    `groundtruth` is a TUM trajectory file."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: bag not found")
    bag_path = path.parent if path.suffix in (".db3", ".mcap") else path
    try:
        reader = AnyReader([bag_path])
        reader.open()
    except (AnyReaderError, OSError, ValueError) as err:
        message = " ".join(str(err).split())
        raise DatasetError(f"{path}: cannot open as a ROS bag ({message})") from None
    try:
        colour_topic, depth_topic, info_topic = _choose_topics(path, reader, topics)
        _check_types(path, reader, (colour_topic, depth_topic, info_topic), camera is None)
        by_topic = {c.topic: c for c in reader.connections}
        colour_conn, depth_conn = by_topic[colour_topic], by_topic[depth_topic]
        if camera is None:
            camera = _camera_info(path, reader, by_topic[info_topic])
        stamps = _read_stamps(path, reader, (colour_conn, depth_conn))
        colour_stamps = np.array([s for _, s in stamps[colour_topic]], dtype=np.float64)
        depth_stamps = np.array([s for _, s in stamps[depth_topic]], dtype=np.float64)
        colour_index, depth_index = associate(colour_stamps, depth_stamps, max_difference)
        if len(colour_index) == 0:
            raise DatasetError(
                f"{path}: no colour image on {colour_topic} has a depth image on {depth_topic} "
                f"within {max_difference} s ({len(colour_stamps)} colour, {len(depth_stamps)} "
                "depth messages)"
            )
        pairs = [
            (stamps[colour_topic][i][0], stamps[depth_topic][j][0], float(colour_stamps[i]))
            for i, j in zip(colour_index, depth_index, strict=True)
        ]
    except BaseException:
        reader.close()
        raise
    return BagSequence(
        path,
        reader,
        (colour_conn, depth_conn),
        camera,
        pairs,
        Path(groundtruth) if groundtruth is not None else None,
    )


def _choose_topics(
    path: Path, reader: Any, topics: tuple[str, str, str] | None
) -> tuple[str, str, str]:
    present = {c.topic: c.msgtype for c in reader.connections}
    candidates = [topics] if topics is not None else list(TOPIC_SETS)
    for candidate in candidates:
        if all(topic in present for topic in candidate):
            return candidate
    wanted = " or ".join(",".join(candidate) for candidate in candidates)
    has = ", ".join(f"{topic} ({kind})" for topic, kind in sorted(present.items())) or "none"
    raise DatasetError(f"{path}: the bag lacks the topics {wanted} (--topics); it has: {has}")


def _read_stamps(
    path: Path, reader: Any, connections: tuple[Any, Any]
) -> dict[str, list[tuple[int, float]]]:
    """(bag time ns, header stamp s) of each image message, per topic. Messages that do not
    decode (or hold fewer bytes than their rows) at the end of a topic are a recording cut
    off: left out with one warning line; such a message followed by good ones is an error."""
    stamps: dict[str, list[tuple[int, float]]] = {c.topic: [] for c in connections}
    bad: dict[str, tuple[int, str]] = {}  # topic: (its first bad message's number, why)
    seen = dict.fromkeys(stamps, 0)
    for connection, time, raw in reader.messages(connections=list(connections)):
        topic, number = connection.topic, seen[connection.topic]
        seen[topic] += 1
        message, damage = _decoded(reader, raw, connection.msgtype)
        if damage:
            bad.setdefault(topic, (number, damage))
        elif topic in bad:
            first, why = bad[topic]
            raise DatasetError(f"{path}: {topic}: message {first} cannot be read ({why})")
        else:
            stamps[topic].append((time, _stamp(message)))
    for topic, (first, why) in bad.items():
        warn(
            f"{path}: {topic}: message {first} and those after it cannot be read ({why}); "
            f"reading the {first} messages before it"
        )
    return stamps


def _decoded(reader: Any, raw: bytes, msgtype: str) -> tuple[Any, str]:
    """An Image message and "", or None and why it cannot be read."""
    try:
        message = reader.deserialize(raw, msgtype)
    except Exception as err:  # rosbags' errors for bytes that are not the message
        return None, " ".join(str(err).split())
    size = len(message.data)
    if message.height * message.step > size:
        return None, (
            f"{size} bytes of pixels for {message.height} rows of {message.step} bytes, cut short"
        )
    return message, ""


def warn(message: str) -> None:
    """One line on stderr for damage that is worked around: the run goes on without it."""
    print(f"kintinuous: warning: {message}", file=sys.stderr, flush=True)


def _check_types(path: Path, reader: Any, topics: tuple[str, str, str], need_info: bool) -> None:
    """Refuse, before any message is read, colour or depth topics that are not images, and an
    info topic that is not CameraInfo when the camera comes from it: their messages have none
    of the fields a frame is read from."""
    present = {c.topic: c.msgtype for c in reader.connections}
    roles = zip(("rgb", "depth", "info"), topics, (IMAGE, IMAGE, CAMERA_INFO), strict=True)
    wrong = [
        f"{role} topic {topic} carries {present[topic]}, not {wanted}"
        for role, topic, wanted in roles
        if present[topic] != wanted and (role != "info" or need_info)
    ]
    if wrong:
        images = _topics_of(present, IMAGE, "no image topic")
        infos = _topics_of(present, CAMERA_INFO, "none (pass --intrinsics)")
        raise DatasetError(
            f"{path}: {'; '.join(wrong)}; the bag's image topics: {images}; its camera info "
            f"topics: {infos} (pass --topics rgb,depth,info)"
        )


def _topics_of(present: dict[str, str], msgtype: str, none: str) -> str:
    return ", ".join(sorted(topic for topic, kind in present.items() if kind == msgtype)) or none


def _camera_info(path: Path, reader: Any, connection: Any) -> Intrinsics:
    for _, _, raw in reader.messages(connections=[connection]):
        info = reader.deserialize(raw, connection.msgtype)
        k = np.asarray(info.K if hasattr(info, "K") else info.k, dtype=np.float64)
        if k.size != 9 or k[0] <= 0 or k[4] <= 0 or info.width <= 0 or info.height <= 0:
            raise DatasetError(
                f"{path}: {connection.topic}: camera info without a calibration "
                f"(K = {k.tolist()}, {info.width}x{info.height})"
            )
        return Intrinsics(
            float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(info.width), int(info.height)
        )
    raise DatasetError(f"{path}: {connection.topic} has no messages (pass --intrinsics)")


def _stamp(message: Any) -> float:
    stamp = message.header.stamp
    return stamp.sec + stamp.nanosec * 1e-9


def _pixels(message: Any, dtype: str, channels: int, where: str) -> np.ndarray:
    """The (H, W[, C]) array of an Image message, honouring its row step and byte order."""
    item = np.dtype(dtype).itemsize * channels
    if message.step < message.width * item or len(message.data) < message.height * message.step:
        raise DatasetError(
            f"{where}: {message.encoding} image of {message.width}x{message.height} with rows "
            f"of {message.step} bytes and {len(message.data)} bytes of pixels: too few"
        )
    rows = np.frombuffer(message.data, np.uint8)[: message.height * message.step]
    rows = rows.reshape(message.height, message.step)
    rows = rows[:, : message.width * item]
    order = ">" if message.is_bigendian else "<"
    values = np.frombuffer(rows.tobytes(), np.dtype(dtype).newbyteorder(order))
    shape = (message.height, message.width) + ((channels,) if channels > 1 else ())
    return values.reshape(shape)


def _colour_image(message: Any, path: Path, index: int) -> np.ndarray:
    encoding = message.encoding.lower()
    if encoding in ("rgb8", "bgr8"):
        image = _pixels(message, "u1", 3, f"{path}: frame {index}")
    elif encoding in ("rgba8", "bgra8"):
        image = _pixels(message, "u1", 4, f"{path}: frame {index}")[..., :3]
    elif encoding in ("mono8", "8uc1"):
        image = np.repeat(_pixels(message, "u1", 1, f"{path}: frame {index}")[..., None], 3, axis=2)
    else:
        raise DatasetError(
            f"{path}: frame {index}: colour encoding {message.encoding!r} is not supported "
            "(rgb8, bgr8, rgba8, bgra8, mono8)"
        )
    if encoding.startswith("bgr"):
        image = image[..., ::-1]
    return np.ascontiguousarray(image)


def _depth_image(message: Any, path: Path, index: int) -> np.ndarray:
    encoding = message.encoding.lower()
    if encoding == "32fc1":
        depth = _pixels(message, "f4", 1, f"{path}: frame {index}").astype(np.float32)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0))
    elif encoding in ("16uc1", "mono16"):
        millimetres = _pixels(message, "u2", 1, f"{path}: frame {index}")
        depth = millimetres.astype(np.float32) / np.float32(1000.0)
    else:
        raise DatasetError(
            f"{path}: frame {index}: depth encoding {message.encoding!r} is not supported "
            "(32FC1 metres, 16UC1 millimetres)"
        )
    return np.ascontiguousarray(depth, dtype=np.float32)
