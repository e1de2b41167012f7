"""Kintinuous / ElasticFusion `.klg` logs, read frame by frame and written from any sequence.

Layout (little-endian): an int32 frame count; then per frame an int64 timestamp in
microseconds, an int32 depth byte count, an int32 image byte count, the depth bytes and the
image bytes. The depth is uint16 millimetres, zlib-compressed (raw when its count is w*h*2, all
zero when it is 0). The image is a JPEG (raw 8-bit RGB when its count is w*h*3, black when 0).
The log does not say its image size or camera: both come from the caller (640x480 by default).

Colour order: the original loggers hand the camera's RGB buffer to OpenCV's JPEG encoder, which
takes it for BGR, and their readers take OpenCV's decoded buffer as RGB again. This module keeps
that convention (the decoded buffer is RGB, no channel swap), so that logs recorded by those
tools and logs written here read the same in both.

Opening a log reads only the 16-byte frame headers (seeking over the data) and keeps each
frame's offset, so a log of many gigabytes is never loaded whole; it decodes the last frame only.
A log ends where its logger stopped, and a logger cut off leaves its last frame cut short, its
header garbled or its data undecodable: the frames before such a frame are read, and one warning
line names the file, the frame and what is wrong with it. A log whose frame 0 is already damaged
is an error. A bad frame in the middle is found when it is read (reconstruct's
--skip-bad-frames leaves it out).
"""

from __future__ import annotations

import os
import struct
import sys
import zlib
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets.tum import Frame, FrameSequence, read_trajectory
from kintinuous_ref.errors import DatasetError

KLG_DEPTH_SCALE = 1000.0  # depth units per metre: millimetres
DEFAULT_SIZE = (640, 480)
JPEG_QUALITY = 90  # the quality the original loggers use
_COUNT = struct.Struct("<i")
_HEADER = struct.Struct("<qii")  # timestamp (us), depth byte count, image byte count


class KlgSequence(FrameSequence):
    """A `.klg` log opened for reading: headers indexed, frames decoded when asked for."""

    def __init__(
        self,
        path: Path,
        width: int,
        height: int,
        offsets: np.ndarray,
        depth_sizes: np.ndarray,
        image_sizes: np.ndarray,
        timestamps: np.ndarray,
        camera: Intrinsics | None = None,
        groundtruth_path: Path | None = None,
    ) -> None:
        self.path = Path(path)
        self.name = self.path.stem
        self.width, self.height = width, height
        self._offsets = offsets
        self._depth_sizes = depth_sizes
        self._image_sizes = image_sizes
        self.timestamps = timestamps
        self.camera = camera  # type: ignore[assignment]  # None: converting needs no camera
        self.groundtruth_path = groundtruth_path
        self.groundtruth = read_trajectory(groundtruth_path) if groundtruth_path else None
        self.damage = ""  # why the frames after the last one cannot be read ("" when none)

    def keep_first(self, count: int, damage: str) -> None:
        """Read only frames 0..count-1: `damage` says what is wrong with frame `count`, the
        first one that cannot be read, and stays in `damage` for the report."""
        self._offsets, self._depth_sizes = self._offsets[:count], self._depth_sizes[:count]
        self._image_sizes, self.timestamps = self._image_sizes[:count], self.timestamps[:count]
        self.damage = damage

    def _read(self, index: int) -> Frame:
        depth_size, image_size = int(self._depth_sizes[index]), int(self._image_sizes[index])
        with open(self.path, "rb") as log:
            log.seek(int(self._offsets[index]))
            data = log.read(depth_size + image_size)
        if len(data) != depth_size + image_size:
            raise DatasetError(f"{self.path}: frame {index}: log ends inside the frame's data")
        depth = self._depth(index, data[:depth_size])
        colour = self._colour(index, data[depth_size:])
        return Frame(
            index=index, timestamp=float(self.timestamps[index]), colour=colour, depth=depth
        )

    def raw_depth(self, index: int) -> np.ndarray:
        """Frame `index`'s depth as stored: (H, W) uint16 millimetres."""
        with open(self.path, "rb") as log:
            log.seek(int(self._offsets[index]))
            data = log.read(int(self._depth_sizes[index]))
        return self._millimetres(index, data)

    def _millimetres(self, index: int, data: bytes) -> np.ndarray:
        expected = self.width * self.height * 2
        if len(data) == 0:
            return np.zeros((self.height, self.width), np.uint16)
        if len(data) != expected:
            try:
                data = zlib.decompress(data)
            except zlib.error as err:
                raise DatasetError(
                    f"{self.path}: frame {index}: depth is not zlib data ({err})"
                ) from None
            if len(data) != expected:
                raise DatasetError(
                    f"{self.path}: frame {index}: depth holds {len(data)} bytes, expected "
                    f"{expected} for {self.width}x{self.height} (wrong --size?)"
                )
        return np.frombuffer(data, dtype="<u2").reshape(self.height, self.width)

    def _depth(self, index: int, data: bytes) -> np.ndarray:
        millimetres = self._millimetres(index, data)
        return (millimetres.astype(np.float32) / np.float32(KLG_DEPTH_SCALE)).astype(np.float32)

    def _colour(self, index: int, data: bytes) -> np.ndarray:
        if len(data) == 0:
            return np.zeros((self.height, self.width, 3), np.uint8)
        if len(data) == self.width * self.height * 3:
            return np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3).copy()
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f"{self.path}: frame {index}: image is neither JPEG nor raw RGB")
        if image.shape[:2] != (self.height, self.width):
            raise DatasetError(
                f"{self.path}: frame {index}: image is {image.shape[1]}x{image.shape[0]}, "
                f"expected {self.width}x{self.height} (wrong --size?)"
            )
        return image  # already RGB: see the module's note on colour order


def open_log(
    path: Path,
    size: tuple[int, int] = DEFAULT_SIZE,
    camera: Intrinsics | None = None,
    groundtruth: Path | None = None,
) -> KlgSequence:
    """Index a `.klg` log's frame headers. `size` is (width, height); `camera`, when given, must
    be of that size (its depth units become millimetres); `groundtruth` is a TUM trajectory.
    A damaged tail (module docstring) is left out with a warning on stderr; the sequence's
    `damage` says why."""
    path = Path(path)
    width, height = size
    if camera is not None:
        if (camera.width, camera.height) != (width, height):
            raise DatasetError(
                f"{path}: the camera is {camera.width}x{camera.height} but the log's size is "
                f"{width}x{height}"
            )
        camera = replace(camera, depth_scale=KLG_DEPTH_SCALE)
    if not path.is_file():
        raise DatasetError(f"{path}: log file not found")
    with open(path, "rb") as log:
        count = _frame_count(path, log)
        index, damage = _index_frames(path, log, count, width, height, path.stat().st_size)
    sequence = KlgSequence(
        path,
        width,
        height,
        *index,
        camera,
        Path(groundtruth) if groundtruth is not None else None,
    )
    if not damage and (damage := _damaged_last_frame(sequence)):
        sequence.keep_first(len(sequence) - 1, damage)
    elif damage:
        sequence.keep_first(len(sequence), damage)
    if damage:
        warn(
            f"{path}: {damage}; reading the {len(sequence)} intact frames before it "
            f"(0..{len(sequence) - 1})"
        )
    return sequence


def warn(message: str) -> None:
    """One line on stderr for damage that is worked around: the run goes on without it."""
    print(f"kintinuous: warning: {message}", file=sys.stderr, flush=True)


def _frame_count(path: Path, log: BinaryIO) -> int:
    head = log.read(_COUNT.size)
    if len(head) < _COUNT.size:
        raise DatasetError(f"{path}: not a .klg log (shorter than its 4-byte frame count)")
    (count,) = _COUNT.unpack(head)
    if count <= 0:
        raise DatasetError(f"{path}: bad header: frame count {count}")
    return count


def _index_frames(
    path: Path, log: BinaryIO, count: int, width: int, height: int, file_size: int
) -> tuple[tuple[np.ndarray, ...], str]:
    """Offsets, depth and image byte counts and timestamps (s) of the frames whose header and
    data are whole, and why the frames after them cannot be read ("" when all can).

    A log ends where its logger stopped, so a cut or garbled frame ends the readable log: the
    frames before it are kept. Frame 0 itself damaged leaves nothing to read: an error."""
    rows: list[tuple[int, int, int, int]] = []
    position, damage = _COUNT.size, ""
    for index in range(count):
        header = log.read(_HEADER.size)
        damage = _header_damage(index, count, header, width, height)
        if damage:
            break
        stamp, depth_size, image_size = _HEADER.unpack(header)
        position += _HEADER.size
        end = position + depth_size + image_size
        if end > file_size:
            damage = (
                f"truncated: frame {index} of {count} needs bytes up to {end} but the log has "
                f"{file_size}"
            )
            break
        rows.append((position, depth_size, image_size, stamp))
        position = end
        log.seek(position)
    if damage and not rows:
        raise DatasetError(f"{path}: {damage}")
    columns = np.array(rows, dtype=np.int64).reshape(-1, 4).T
    offsets, depth_sizes, image_sizes, stamps = (column.copy() for column in columns)
    return (offsets, depth_sizes, image_sizes, stamps / 1e6), damage


def _header_damage(index: int, count: int, header: bytes, width: int, height: int) -> str:
    """What is wrong with frame `index`'s 16-byte header ("" when nothing)."""
    if len(header) < _HEADER.size:
        where = "inside" if header else "before"
        return (
            f"truncated: the header says {count} frames but the log ends {where} frame "
            f"{index}'s header"
        )
    _, depth_size, image_size = _HEADER.unpack(header)
    if depth_size < 0 or image_size < 0:
        return (
            f"frame {index}: bad frame header (depth {depth_size} bytes, image {image_size} bytes)"
        )
    if depth_size > width * height * 2 or image_size > width * height * 3:
        return (
            f"frame {index}: sizes do not match {width}x{height} frames (depth {depth_size} "
            f"bytes, image {image_size} bytes; wrong --size?)"
        )
    return ""


def _damaged_last_frame(sequence: KlgSequence) -> str:
    """Why the log's last frame cannot be decoded, when the one before it can ("" otherwise):
    whole bytes that do not decode at the very end are the mark of a logger cut off; a log
    whose frames all fail is read wrongly (a wrong --size), which reading any frame reports."""
    last = len(sequence) - 1
    if last < 1:
        return ""
    try:
        sequence[last]
    except DatasetError as err:
        try:
            sequence[last - 1]
        except DatasetError:
            return ""
        return str(err).removeprefix(f"{sequence.path}: ")
    return ""


def write_log(path: Path, frames: Iterable[Frame], jpeg_quality: int = JPEG_QUALITY) -> int:
    """Write frames as a `.klg` log (zlib depth in millimetres, JPEG colour); returns the count.

    The log is written beside `path` under a temporary name and renamed when complete, so an
    interrupted write leaves no log that looks whole.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    count = 0
    try:
        with open(partial, "wb") as log:
            log.write(_COUNT.pack(0))  # the count is known at the end
            for frame in frames:
                millimetres = np.round(frame.depth.astype(np.float64) * KLG_DEPTH_SCALE)
                millimetres[~np.isfinite(millimetres) | (millimetres < 0)] = 0
                millimetres[millimetres > np.iinfo(np.uint16).max] = 0
                raw = millimetres.astype("<u2").tobytes()
                depth = zlib.compress(raw)
                if len(depth) >= len(raw):  # the readers' buffers hold w*h*2 bytes: store raw
                    depth = raw
                ok, jpeg = cv2.imencode(  # RGB handed over as is: the loggers' convention
                    ".jpg",
                    np.ascontiguousarray(frame.colour),
                    [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality],
                )
                if not ok:
                    raise DatasetError(f"{path}: frame {count}: cannot encode the colour image")
                image = jpeg.tobytes()
                stamp = int(round(frame.timestamp * 1e6))
                log.write(_HEADER.pack(stamp, len(depth), len(image)))
                log.write(depth)
                log.write(image)
                count += 1
            log.seek(0)
            log.write(_COUNT.pack(count))
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return count
