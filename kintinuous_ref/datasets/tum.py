"""TUM RGB-D folders and trajectories (Sturm et al., IROS 2012).

A trajectory file has one pose per line, `timestamp tx ty tz qx qy qz qw`, camera-to-world;
lines starting with '#' are comments. A sequence folder holds `rgb.txt` and `depth.txt`
(`timestamp filename` per line) or `associations.txt` (`t_rgb rgb_file t_depth depth_file`),
colour images (PNG or JPEG), 16-bit depth PNGs (raw / 5000 = metres), optionally
`groundtruth.txt` and `intrinsics.json`.
"""

from __future__ import annotations

import shutil
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import (
    DEFAULT_CAMERA,
    TUM_DEPTH_SCALE,
    Intrinsics,
    camera_from_folder_name,
    load_intrinsics_json,
    parse_intrinsics,
)
from kintinuous_ref.errors import DatasetError, ImageSizeError
from kintinuous_ref.strict_json import dumps as strict_dumps


@dataclass
class Trajectory:
    """Timestamped camera-to-world poses: timestamps (N,) seconds, poses (N, 4, 4)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise DatasetError(
                f"trajectory has {len(self.timestamps)} timestamps but {len(self.poses)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


def write_trajectory(path: Path, trajectory: Trajectory) -> None:
    """Write a trajectory in TUM format (timestamps to 1e-6 s, poses to 1e-9)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for timestamp, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
        values = " ".join(f"{v:.9f}" for v in se3.to_tum(pose))
        lines.append(f"{timestamp:.6f} {values}")
    write_file(path, "\n".join(lines) + "\n")


def _read_text(path: Path) -> str:
    """A text file's contents, or a one-line DatasetError (not UTF-8 text, unreadable)."""
    try:
        return Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file") from None
    except OSError as err:
        raise DatasetError(f"{path}: cannot read ({err.strerror or err})") from None


def read_trajectory(path: Path) -> Trajectory:
    """Read a TUM trajectory; a malformed line is reported with its file and line number."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found")
    timestamps, poses = [], []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
            if len(values) != 8:
                raise ValueError(f"expected 8 numbers, found {len(values)}")
            if not np.all(np.isfinite(values)):
                raise ValueError("not every number is finite")
            pose = se3.from_tum(np.array(values[1:]))
        except (ValueError, se3.PoseError, FloatingPointError) as err:
            raise DatasetError(f"{path}:{number}: cannot parse pose line ({err})") from None
        timestamps.append(values[0])
        poses.append(pose)
    if not timestamps:
        raise DatasetError(f"{path}: trajectory has no poses")
    return Trajectory(np.array(timestamps), np.array(poses))


# --- Timestamp association -------------------------------------------------------------------

# TUM's associate.py pairs colour and depth (and poses) closer than 0.02 s (Sturm et al. 2012).
MAX_TIME_DIFFERENCE = 0.02


def associate(
    first: np.ndarray, second: np.ndarray, max_difference: float = MAX_TIME_DIFFERENCE
) -> tuple[np.ndarray, np.ndarray]:
    """Pair two timestamp lists one-to-one, as TUM's associate.py does.

    Candidate pairs closer than `max_difference` are accepted greedily in order of increasing
    |dt|, each timestamp used at most once. Returns index arrays (into `first`, into `second`)
    sorted by the first timestamp.
    """
    first = np.asarray(first, dtype=np.float64).reshape(-1)
    second = np.asarray(second, dtype=np.float64).reshape(-1)
    order = np.argsort(second, kind="stable")
    sorted_second = second[order]
    # Only the candidates within the window are ever compared: O(n log n), not an n x m matrix.
    low = np.searchsorted(sorted_second, first - max_difference, side="left")
    high = np.searchsorted(sorted_second, first + max_difference, side="right")
    counts = high - low
    rows = np.repeat(np.arange(len(first)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    columns = order[np.repeat(low, counts) + offsets]
    differences = np.abs(first[rows] - second[columns])
    keep = differences <= max_difference
    rows, columns, differences = rows[keep], columns[keep], differences[keep]

    used_first = np.zeros(len(first), dtype=bool)
    used_second = np.zeros(len(second), dtype=bool)
    pairs = []
    for k in np.argsort(differences, kind="stable"):
        i, j = rows[k], columns[k]
        if not used_first[i] and not used_second[j]:
            used_first[i] = used_second[j] = True
            pairs.append((i, j))
    pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[np.argsort(first[pairs[:, 0]], kind="stable")]
    return pairs[:, 0], pairs[:, 1]


def nearest_indices(
    queries: np.ndarray, timestamps: np.ndarray, max_difference: float = MAX_TIME_DIFFERENCE
) -> np.ndarray:
    """Index of the timestamp nearest to each query, or -1 where none lies within max_difference."""
    queries = np.asarray(queries, dtype=np.float64).reshape(-1)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(timestamps) == 0:
        return np.full(len(queries), -1, dtype=np.int64)
    order = np.argsort(timestamps, kind="stable")
    ordered = timestamps[order]
    right = np.clip(np.searchsorted(ordered, queries), 0, len(ordered) - 1)
    left = np.clip(right - 1, 0, len(ordered) - 1)
    take_left = np.abs(queries - ordered[left]) <= np.abs(ordered[right] - queries)
    best = np.where(take_left, left, right)
    result = order[best]
    result[np.abs(ordered[best] - queries) > max_difference] = -1
    return result


# --- TUM RGB-D folders -----------------------------------------------------------------------


@dataclass
class Frame:
    """One RGB-D frame: colour (H, W, 3) uint8 RGB, depth (H, W) float32 metres (0 = none)."""

    index: int
    timestamp: float
    colour: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class _FramePaths:
    timestamp: float  # of the colour image: estimated trajectories carry these (TUM convention)
    colour: Path
    depth: Path


class FrameSequence(ABC):
    """What every reader offers: a camera, per-frame timestamps, optional ground truth, and frames
    read one at a time (lazily) by index. A reader sets the attributes and implements `_read`."""

    path: Path
    name: str
    camera: Intrinsics
    timestamps: np.ndarray  # (N,) seconds, one per frame
    groundtruth: Trajectory | None
    groundtruth_path: Path | None  # where the ground truth came from (for messages)
    # Whether several threads may read frames at once (each read opens its own files); a reader
    # that seeks in one open file (a bag, a log) reads from one thread at a time.
    parallel_reads: bool = False

    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def __getitem__(self, index: int) -> Frame:
        if not -len(self) <= index < len(self):
            raise IndexError(f"{self.path}: frame {index} out of range (0..{len(self) - 1})")
        return self._read(index % len(self))

    @abstractmethod
    def _read(self, index: int) -> Frame:
        """Frame `index` (0 <= index < len(self)), read from the source."""

    def frames(self, start: int = 0, count: int | None = None) -> Iterator[Frame]:
        """Frames start, start+1, ... (count of them, or up to the end), read one at a time."""
        stop = len(self) if count is None else min(len(self), start + count)
        for index in range(start, stop):
            yield self[index]

    def groundtruth_for_frames(self, max_difference: float = MAX_TIME_DIFFERENCE) -> Trajectory:
        """One ground-truth pose per frame: the one nearest in time (within max_difference)."""
        if self.groundtruth is None:
            raise DatasetError(f"{self.path}: sequence has no ground truth")
        nearest = nearest_indices(self.timestamps, self.groundtruth.timestamps, max_difference)
        missing = np.flatnonzero(nearest < 0)
        if len(missing) == len(self) and len(self):
            frames, poses = self.timestamps, self.groundtruth.timestamps
            raise DatasetError(
                f"{self.groundtruth_path or self.path}: no pose within {max_difference} s of any "
                f"of the {len(self)} frames (frames at {frames.min():.6f}..{frames.max():.6f} s, "
                f"poses at {poses.min():.6f}..{poses.max():.6f} s)"
            )
        if len(missing):
            first = missing[0]
            raise DatasetError(
                f"{self.groundtruth_path or self.path}: no pose within {max_difference} s of "
                f"frame {first} (t = {self.timestamps[first]:.6f}); {len(missing)} frames lack one"
            )
        return Trajectory(self.timestamps.copy(), self.groundtruth.poses[nearest])


class TumSequence(FrameSequence):
    """A TUM RGB-D folder; frames are read from disk only when asked for (lazily)."""

    parallel_reads = True  # two image files a frame, each opened by its read

    def __init__(
        self,
        path: Path,
        camera: Intrinsics,
        entries: list[_FramePaths],
        groundtruth: Trajectory | None,
    ) -> None:
        self.path = Path(path)
        self.name = self.path.resolve().name
        self.camera = camera
        self._entries = entries
        self.timestamps = np.array([entry.timestamp for entry in entries], dtype=np.float64)
        self.groundtruth = groundtruth
        self.groundtruth_path = self.path / "groundtruth.txt"

    def _read(self, index: int) -> Frame:
        entry = self._entries[index]
        colour = _read_colour(entry.colour)
        depth = _read_depth(entry.depth, self.camera.depth_scale)
        # each image against the camera, so that the message names the one whose size is wrong
        for path, image in ((entry.depth, depth), (entry.colour, colour)):
            if image.shape[:2] != (self.camera.height, self.camera.width):
                raise ImageSizeError(
                    f"{path}: image is {image.shape[1]}x{image.shape[0]} but the camera is "
                    f"{self.camera.width}x{self.camera.height}"
                )
        return Frame(index=index, timestamp=entry.timestamp, colour=colour, depth=depth)


def open_sequence(path: Path, intrinsics: str | None = None) -> TumSequence:
    """Open a TUM RGB-D folder (rgb.txt + depth.txt or associations.txt, optional groundtruth.txt).

    The camera is, in order of precedence: `intrinsics` (the command line's `fx,fy,cx,cy`, or a
    path to an intrinsics JSON file), the folder's `intrinsics.json`, the TUM camera named in the
    folder name (freiburg1/2/3). Nothing but the list files is read here; images are read per frame.
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: sequence folder not found")
    entries = _frame_entries(path)
    if not entries:
        raise DatasetError(f"{path}: sequence has no frames (no colour/depth pair within 0.02 s)")
    for entry in entries:
        for image in (entry.colour, entry.depth):
            if not image.is_file():
                raise DatasetError(f"{image}: listed image not found")
    camera = _choose_camera(path, intrinsics, entries[0].depth)
    groundtruth_path = path / "groundtruth.txt"
    groundtruth = read_trajectory(groundtruth_path) if groundtruth_path.is_file() else None
    return TumSequence(path, camera, entries, groundtruth)


def _choose_camera(path: Path, intrinsics: str | None, first_depth: Path) -> Intrinsics:
    if intrinsics is not None:
        if Path(intrinsics).suffix == ".json" or Path(intrinsics).is_file():
            return load_intrinsics_json(Path(intrinsics))
        # fx,fy,cx,cy says nothing about the image size: take it from the first depth image.
        height, width = _read_depth(first_depth, TUM_DEPTH_SCALE).shape
        return parse_intrinsics(intrinsics, width=width, height=height)
    if (path / "intrinsics.json").is_file():
        return load_intrinsics_json(path / "intrinsics.json")
    camera = camera_from_folder_name(path)
    if camera is None:
        raise DatasetError(
            f"{path}: unknown camera: add intrinsics.json, name the folder after a TUM camera "
            "(freiburg1/2/3) or pass --intrinsics fx,fy,cx,cy"
        )
    return camera


def _frame_entries(path: Path) -> list[_FramePaths]:
    """Colour/depth file pairs from associations.txt, else associated from rgb.txt + depth.txt."""
    associations = path / "associations.txt"
    if associations.is_file():
        entries = []
        for number, fields in _read_list(associations, columns=4):
            try:
                t_first, t_second = float(fields[0]), float(fields[2])
                if not (np.isfinite(t_first) and np.isfinite(t_second)):
                    raise ValueError
            except ValueError:
                raise DatasetError(
                    f"{associations}:{number}: expected 't_rgb rgb_file t_depth depth_file'"
                ) from None
            first, second = fields[1], fields[3]
            # associate.py writes its two inputs in the order given; accept depth-first lists too.
            if Path(first).parts[0] == "depth" and Path(second).parts[0] == "rgb":
                t_first, first, second = t_second, second, first
            entries.append(_FramePaths(t_first, path / first, path / second))
        return sorted(entries, key=lambda entry: entry.timestamp)
    colour_list = _read_timestamped_files(path / "rgb.txt")
    depth_list = _read_timestamped_files(path / "depth.txt")
    colour_indices, depth_indices = associate(
        np.array([t for t, _ in colour_list]), np.array([t for t, _ in depth_list])
    )
    return [
        _FramePaths(colour_list[i][0], path / colour_list[i][1], path / depth_list[j][1])
        for i, j in zip(colour_indices, depth_indices, strict=True)
    ]


def _read_list(path: Path, columns: int) -> Iterator[tuple[int, list[str]]]:
    """(line number, first `columns` fields) of each non-comment line of a TUM list file."""
    if not path.is_file():
        raise DatasetError(f"{path}: list file not found")
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < columns:
            raise DatasetError(
                f"{path}:{number}: expected {columns} fields, found {len(fields)}: {line!r}"
            )
        yield number, fields[:columns]


def _read_timestamped_files(path: Path) -> list[tuple[float, str]]:
    """The `timestamp filename` lines of rgb.txt or depth.txt."""
    entries = []
    for number, (stamp, name) in _read_list(path, columns=2):
        try:
            value = float(stamp)
        except ValueError:
            value = float("nan")
        if not np.isfinite(value):
            raise DatasetError(f"{path}:{number}: timestamp {stamp!r} is not a finite number")
        entries.append((value, name))
    return entries


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC: the last 8 bytes of every PNG
_JPEG_START, _JPEG_SCAN, _JPEG_END = b"\xff\xd8", b"\xff\xda", b"\xff\xd9"


def _whole_file(path: Path, kind: str) -> bytes:
    """The bytes of a colour or depth (`kind`) image, refused (DatasetError) when missing or
    cut short. libjpeg decodes a cut JPEG with its missing rows grey and only a warning on
    stderr, and libpng prints an error line of its own: the check comes before either
    decoder, which then decodes these bytes (the file is read once)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        raise DatasetError(f"{path}: cannot read {kind} image (missing or not an image)") from None
    cut = None
    if data.startswith(_PNG_SIGNATURE) and _PNG_END not in data[-64:]:
        cut = "the PNG has no IEND chunk at its end"
    elif data.startswith(_JPEG_START) and not data.rfind(_JPEG_END) > data.rfind(_JPEG_SCAN) > 0:
        cut = "the JPEG has no end-of-image marker after its last scan"
    if cut is not None:
        raise DatasetError(
            f"{path}: cannot read {kind} image: the file is cut short ({cut}, {len(data)} "
            "bytes); copy it again from the source"
        )
    return data


def _decoded(path: Path, kind: str, flags: int) -> np.ndarray:
    """The image of `path` decoded by OpenCV with `flags`, or a DatasetError."""
    data = _whole_file(path, kind)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags) if data else None
    if image is None:
        raise DatasetError(f"{path}: cannot read {kind} image (missing or not an image)")
    return image


def _read_colour(path: Path) -> np.ndarray:
    """A PNG or JPEG colour image as (H, W, 3) uint8 RGB (OpenCV reads BGR)."""
    image = _decoded(path, "colour", cv2.IMREAD_COLOR)
    return np.ascontiguousarray(image[..., ::-1])


def _read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """A 16-bit single-channel PNG as float32 metres (raw / depth_scale); 0 stays 0 (no depth)."""
    raw = _decoded(path, "depth", cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise DatasetError(
            f"{path}: depth image has {raw.shape[2]} channels, expected one 16-bit channel"
        )
    if raw.dtype != np.uint16:
        raise DatasetError(f"{path}: depth image is {raw.dtype}, expected 16-bit (uint16)")
    return (raw.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


def write_file(path: Path, data: bytes | str) -> None:
    """`data` into `path`; an OSError (a full disk, a folder that cannot be written) becomes a
    one-line DatasetError naming the file, which a write's own error does not."""
    try:
        if isinstance(data, str):
            Path(path).write_text(data)
        else:
            Path(path).write_bytes(data)
    except OSError as err:
        raise DatasetError(f"{path}: cannot write ({err.strerror or err})") from None


def write_image(path: Path, image: np.ndarray, options: Iterable[int] = ()) -> None:
    """An image encoded in memory (its suffix says the format) and written with `write_file`:
    an encoder writing to a full disk says only "Write Error", without the file."""
    ok, encoded = cv2.imencode(Path(path).suffix, image, list(options))
    if not ok:
        raise DatasetError(f"{path}: cannot encode image ({image.shape}, {image.dtype})")
    write_file(path, encoded.tobytes())


def write_sequence(
    folder: Path,
    frames: Iterable[Frame],
    camera: Intrinsics | None = None,
    groundtruth: Trajectory | None = None,
) -> int:
    """Write frames as a TUM folder; returns the number of frames written. Without a `camera`
    (a log holds none) intrinsics.json holds DEFAULT_CAMERA scaled to the images, with a note on
    stdout, so that reconstruct reads the folder.

    Colour becomes lossless PNG, depth 16-bit PNG in TUM units (1/5000 m; beyond 13.1 m, the
    largest value 16 bits hold, it becomes 0, no measurement). `camera` is written as
    intrinsics.json, `groundtruth` as groundtruth.txt. The frames go into a sibling temporary
    folder that is renamed to `folder` once complete, so an interrupted write leaves no partial
    sequence; an existing `folder` is refused.
    """
    folder = Path(folder)
    if folder.exists():
        raise DatasetError(f"{folder}: already exists; choose a new output folder")

    folder.parent.mkdir(parents=True, exist_ok=True)
    partial = folder.with_name(f".{folder.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        (partial / "rgb").mkdir(parents=True)
        (partial / "depth").mkdir()
        rgb_lines = ["# colour images", "# timestamp filename"]
        depth_lines = ["# depth maps (uint16, 1/5000 m)", "# timestamp filename"]
        pairs = ["# timestamp rgb_file timestamp depth_file"]
        for frame in frames:
            stamp = f"{frame.timestamp:.6f}"
            units = np.round(frame.depth.astype(np.float64) * TUM_DEPTH_SCALE)
            units[~np.isfinite(units) | (units > np.iinfo(np.uint16).max) | (units < 0)] = 0
            colour_name, depth_name = f"rgb/{stamp}.png", f"depth/{stamp}.png"
            write_image(partial / colour_name, frame.colour[..., ::-1])
            write_image(partial / depth_name, units.astype(np.uint16))
            rgb_lines.append(f"{stamp} {colour_name}")
            depth_lines.append(f"{stamp} {depth_name}")
            pairs.append(f"{stamp} {colour_name} {stamp} {depth_name}")
        if camera is None and len(pairs) > 1:  # a folder without one would be refused
            camera = DEFAULT_CAMERA.resized(frame.depth.shape[1], frame.depth.shape[0])
            print(
                f"note: the source holds no camera: {folder}/intrinsics.json holds "
                "the Kinect's nominal one (fx 525 at 640x480, scaled to the images); replace "
                "it with the camera's own, or convert with --intrinsics fx,fy,cx,cy"
            )  # on stdout, beside convert's summary: no error
        write_file(partial / "rgb.txt", "\n".join(rgb_lines) + "\n")
        write_file(partial / "depth.txt", "\n".join(depth_lines) + "\n")
        if camera is not None:
            values = {**camera.to_json(), "depth_scale": TUM_DEPTH_SCALE}
            write_file(partial / "intrinsics.json", strict_dumps(values, indent=2) + "\n")
        if groundtruth is not None:
            write_trajectory(partial / "groundtruth.txt", groundtruth)
        write_file(partial / "associations.txt", "\n".join(pairs) + "\n")
        partial.rename(folder)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return len(pairs) - 1
