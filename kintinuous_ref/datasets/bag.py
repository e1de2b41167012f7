"""ROS1 bags and ROS2 bag folders, read through `rosbags`.

A frame is a colour image and the depth image nearest to it in time (header stamps, paired as
TUM's associate.py pairs its lists, within 0.02 s); the camera comes from the first CameraInfo
message. Opening a bag reads every image message once for its stamp and keeps only the stamps;
frames are then read one at a time from the bag.

A ROS1 bag whose recording was cut off (the file ends inside a chunk, or in the index that
closes it, or the index was never written) cannot be opened by rosbags, which reads the index
first. Its records are then read in order from the start (the bag format 2.0: records of a
header and data, chunks of connection and message records, SalvagedBag below): every message
whose record is whole is used, and one warning line names the file, where it ends and how many
frames were kept, as the .klg reader does with a log cut short.

Colour: rgb8, bgr8, rgba8, bgra8 or mono8. Depth: 32FC1 metres (NaN: no measurement) or 16UC1
millimetres. Topics default to those of the TUM RGB-D bags, then to those of the RealSense ROS
driver with depth aligned to colour; other names are given as `rgb,depth,info`.
"""

from __future__ import annotations

import bz2
import mmap
import struct
import sys
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets.tum import (
    MAX_TIME_DIFFERENCE,
    Frame,
    FrameSequence,
    associate,
    read_trajectory,
)
from kintinuous_ref.errors import DatasetError, ImageSizeError

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
                raise ImageSizeError(
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
        reader: Any = AnyReader([bag_path])
        reader.open()
    except (AnyReaderError, OSError, ValueError) as err:
        message = " ".join(str(err).split())
        reader = SalvagedBag.of(path) if path.suffix == ".bag" else None
        if reader is None:
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
        if isinstance(reader, SalvagedBag):
            warn(
                f"{path}: {reader.damage}; reading the {len(pairs)} frames whose messages lie "
                f"before it (0..{len(pairs) - 1})"
            )
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


# The ROS1 bag format 2.0 (wiki.ros.org/Bags/Format/2.0): after the line "#ROSBAG V2.0", records
# of a header (a uint32 length, then fields of a uint32 length and "name=value") and data (a
# uint32 length, then the bytes). The header's "op" field says what a record is.
ROS1_MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_CHUNK, OP_CONNECTION = 2, 3, 5, 7
_UINT32 = struct.Struct("<I")
_TIME = struct.Struct("<II")  # seconds, nanoseconds


class Record(NamedTuple):
    fields: dict[str, bytes]
    data_start: int
    data_end: int  # as the record declares it: past the end of a record cut short


class Connection(NamedTuple):
    id: int
    topic: str
    msgtype: str
    msgdef: str


class Message(NamedTuple):
    time: int  # bag time, ns
    connection: int
    chunk: int  # index into SalvagedBag's chunks
    start: int  # the message's bytes within its chunk's data
    end: int


def record_at(buffer: Any, position: int) -> Record | None:
    """The record starting at `position` in `buffer`, or None when its header is not whole or
    not a header (the buffer ends, or holds something else, there)."""
    if position + 4 > len(buffer):
        return None
    (header_size,) = _UINT32.unpack_from(buffer, position)
    data_start = position + 4 + header_size + 4
    if data_start > len(buffer):
        return None
    fields = header_fields(bytes(buffer[position + 4 : data_start - 4]))
    if fields is None or len(fields.get("op", b"")) != 1:
        return None
    (data_size,) = _UINT32.unpack_from(buffer, data_start - 4)
    return Record(fields, data_start, data_start + data_size)


def header_fields(blob: bytes) -> dict[str, bytes] | None:
    """A record header's fields by name; None when `blob` is not one."""
    fields, position = {}, 0
    while position < len(blob):
        if position + 4 > len(blob):
            return None
        (size,) = _UINT32.unpack_from(blob, position)
        name, equals, value = blob[position + 4 : position + 4 + size].partition(b"=")
        if not equals or position + 4 + size > len(blob):
            return None
        fields[name.decode("latin-1")] = value
        position += 4 + size
    return fields


def whole_records(buffer: Any, position: int = 0) -> Iterator[Record]:
    """The records from `position` on, up to the first that is not whole."""
    while (record := record_at(buffer, position)) is not None and record.data_end <= len(buffer):
        yield record
        position = record.data_end


def _chunk_data(buffer: Any, record: Record) -> bytes | None:
    """A chunk record's records as bytes: decompressed when the chunk is whole, its bytes up to
    the end of the file when an uncompressed chunk is cut short (the records before the cut are
    whole), None for a compressed chunk cut short (nothing in it can be read)."""
    compression = record.fields.get("compression", b"none")
    whole = record.data_end <= len(buffer)
    data = bytes(buffer[record.data_start : min(record.data_end, len(buffer))])
    if compression == b"none":
        return data
    if not whole:
        return None
    if compression == b"bz2":
        return bz2.decompress(data)
    if compression == b"lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    return None


def _normal_topic(topic: str) -> str:
    """A topic as rosbags names it: one slash between the parts, one in front."""
    return "/" + "/".join(part for part in topic.split("/") if part)


class SalvagedBag:
    """The whole messages of a ROS1 bag that rosbags cannot open, read record by record from its
    start. It offers what BagSequence calls of rosbags' AnyReader: connections, messages (in bag
    time order) and deserialize; `damage` says where the bag ends."""

    def __init__(self, path: Path, file: Any, buffer: Any) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path, self._file, self._buffer = path, file, buffer
        self.damage = ""  # where the records end, once they are read
        self._chunks: list[Record] = []  # read from the file again when a frame needs them
        self._cached: tuple[int, bytes | None] = (-1, None)
        found: dict[int, Connection] = {}
        messages: list[Message] = []
        for record in self._chunk_records():
            self._chunks.append(record)
            data = self._chunk(len(self._chunks) - 1)
            if data is not None:
                messages += self._read_chunk(len(self._chunks) - 1, data, found)
        self.connections = list(found.values())
        self._messages = sorted(messages, key=lambda message: message.time)  # stable
        self._by_id = found
        self._typestore = get_typestore(Stores.EMPTY)
        for connection in found.values():
            self._typestore.register(_types_of(connection))

    @classmethod
    def of(cls, path: Path) -> SalvagedBag | None:
        """The bag at `path` read record by record, or None when it is no ROS1 bag 2.0 or holds
        no whole message, or when rosbags reads its index (then what it refused lies elsewhere)."""
        from rosbags.rosbag1 import Reader

        try:
            with Reader(path):
                return None
        except Exception:  # rosbags' ReaderError, or what its parsing raises on damaged bytes
            pass
        try:
            file = open(path, "rb")  # noqa: SIM115 (closed by close())
        except OSError:
            return None
        try:
            buffer = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # an empty file cannot be mapped
            file.close()
            return None
        bag = None
        if buffer[: len(ROS1_MAGIC)] == ROS1_MAGIC:
            try:
                bag = cls(path, file, buffer)
            except Exception:  # damaged beyond what is read here: refused as rosbags refused it
                bag = None
        if bag is None or not bag._messages:
            buffer.close()
            file.close()
            return None
        return bag

    def _chunk_records(self) -> Iterator[Record]:
        """The chunk records in file order, the last maybe cut short; then `damage` says where
        the reading stopped."""
        buffer, position, index_start = self._buffer, len(ROS1_MAGIC), None
        while (record := record_at(buffer, position)) is not None:
            op = record.fields["op"][0]
            if op == OP_BAG_HEADER:
                index_start = _index_position(record)
            elif op == OP_CHUNK:
                yield record
            if record.data_end > len(buffer):
                break
            position = record.data_end
        self.damage = _where_it_ends(buffer, position, index_start)

    def _read_chunk(
        self, chunk: int, data: bytes, connections: dict[int, Connection]
    ) -> list[Message]:
        """The whole message records of one chunk's data; its connection records go into
        `connections`."""
        messages = []
        for record in whole_records(data):
            op, fields = record.fields["op"][0], record.fields
            if op == OP_CONNECTION:
                connection = _connection(fields, data[record.data_start : record.data_end])
                if connection is not None:
                    connections.setdefault(connection.id, connection)
            elif (
                op == OP_MESSAGE
                and len(fields.get("conn", b"")) == 4
                and len(fields.get("time", b"")) == 8
            ):
                (number,) = _UINT32.unpack(fields["conn"])
                seconds, nanoseconds = _TIME.unpack(fields["time"])
                time = seconds * 1_000_000_000 + nanoseconds
                messages.append(Message(time, number, chunk, record.data_start, record.data_end))
        return [message for message in messages if message.connection in connections]

    def messages(
        self, connections: Collection[Any] = (), start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """(connection, bag time ns, message bytes) of `connections`' messages (all when none
        is given) with start <= time < stop, in time order."""
        wanted = {connection.id for connection in connections} or set(self._by_id)
        for message in self._messages:
            if message.connection not in wanted:
                continue
            if (start is not None and message.time < start) or (
                stop is not None and message.time >= stop
            ):
                continue
            data = self._chunk(message.chunk)
            assert data is not None  # messages come from readable chunks only
            yield self._by_id[message.connection], message.time, data[message.start : message.end]

    def _chunk(self, number: int) -> bytes | None:
        """Chunk `number`'s records (_chunk_data), the last one asked for kept: frames are read
        in order, so a chunk is read once while its frames are."""
        if self._cached[0] != number:
            self._cached = (number, _chunk_data(self._buffer, self._chunks[number]))
        return self._cached[1]

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self._typestore.deserialize_ros1(raw, msgtype)

    def close(self) -> None:
        self._buffer.close()
        self._file.close()


def _where_it_ends(buffer: Any, stop: int, index_start: int | None) -> str:
    """Why the records end at `stop`: the file cut short inside a chunk or the index (which
    starts at `index_start`, 0 when it was never written), or an index rosbags cannot read."""
    size = len(buffer)
    if index_start == 0:
        return "it was never indexed (its recording did not end)"
    if stop >= size:
        return "its index cannot be read"
    if index_start is not None and stop >= index_start:
        return f"the file is cut short at byte {size}, inside its index (from byte {index_start})"
    record = record_at(buffer, stop)
    inside = "a chunk" if record is not None and record.fields["op"][0] == OP_CHUNK else "a record"
    return f"the file is cut short at byte {size}, inside {inside} (from byte {stop})"


def _index_position(bag_header: Record) -> int | None:
    value = bag_header.fields.get("index_pos", b"")
    return struct.unpack("<Q", value)[0] if len(value) == 8 else None


def _connection(fields: dict[str, bytes], data: bytes) -> Connection | None:
    """A connection record: its number and topic in the header, its type and message
    definition in a header-like block of fields in the data."""
    from rosbags.typesys.msg import normalize_msgtype

    described = header_fields(data)
    if described is None or len(fields.get("conn", b"")) != 4 or "type" not in described:
        return None
    (number,) = _UINT32.unpack(fields["conn"])
    topic = fields.get("topic", b"").decode()
    definition = described.get("message_definition", b"").decode()
    return Connection(
        number, _normal_topic(topic), normalize_msgtype(described["type"].decode()), definition
    )


def _types_of(connection: Connection) -> Any:
    from rosbags.typesys import get_types_from_msg

    return get_types_from_msg(connection.msgdef, connection.msgtype)
