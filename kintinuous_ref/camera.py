"""Pinhole intrinsics, per-pyramid-level scaling, projection and back-projection.

Pixel (u, v) with depth z back-projects to ((u - cx) z / fx, (v - cy) z / fy, z) (paper IV-A.2).
Pyramid level l+1 keeps every second pixel of level l (OpenCV's pyrDown convention: pixel (u, v) at
level l+1 sits on pixel (2u, 2v) of level l), so fx, fy, cx, cy all halve per level.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kintinuous_ref.errors import ConfigError, DatasetError

TUM_DEPTH_SCALE = 5000.0
# The axial (along-the-ray) depth noise of a structured-light camera, sigma(z) = AXIAL_NOISE_BASE
# + AXIAL_NOISE_GROWTH (z - AXIAL_NOISE_NEAREST)^2 metres (Nguyen, Izadi and Lovell, 3DIMPVT 2012,
# fitted to a Kinect for surfaces seen at under about 60 degrees).
AXIAL_NOISE_BASE = 0.0012
AXIAL_NOISE_GROWTH = 0.0019
AXIAL_NOISE_NEAREST = 0.4


def axial_noise(depth: np.ndarray | float) -> np.ndarray | float:
    """The standard deviation (metres) of a depth measurement at `depth` metres."""
    return AXIAL_NOISE_BASE + AXIAL_NOISE_GROWTH * (np.asarray(depth) - AXIAL_NOISE_NEAREST) ** 2


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera: focal lengths and principal point in pixels, image size, depth units."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = TUM_DEPTH_SCALE  # raw depth units per metre

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (self.width > 0 and self.height > 0):
            raise ConfigError(f"image size must be positive, got {self.width}x{self.height}")
        if not self.depth_scale > 0:
            raise ConfigError(f"depth_scale must be positive, got {self.depth_scale}")
        values = (self.fx, self.fy, self.cx, self.cy, self.depth_scale)
        if not all(math.isfinite(value) for value in values):
            raise ConfigError(
                f"intrinsics must be finite numbers, got fx={self.fx}, fy={self.fy}, "
                f"cx={self.cx}, cy={self.cy}, depth_scale={self.depth_scale}"
            )

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 calibration matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def at_level(self, level: int) -> Intrinsics:
        """The camera of pyramid level `level` (0 = full resolution)."""
        if level < 0:
            raise ConfigError(f"pyramid level must be >= 0, got {level}")
        scale = 0.5**level
        return replace(
            self,
            fx=self.fx * scale,
            fy=self.fy * scale,
            cx=self.cx * scale,
            cy=self.cy * scale,
            width=max(1, self.width >> level),
            height=max(1, self.height >> level),
        )

    def resized(self, width: int, height: int) -> Intrinsics:
        """The same camera for images scaled to width x height."""
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of camera-frame points (..., 3); points need z > 0."""
        z = points[..., 2]
        u = self.fx * points[..., 0] / z + self.cx
        v = self.fy * points[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Vertex map (H, W, 3) of a metric depth map; pixels without depth give (0, 0, 0)."""
        height, width = depth.shape
        u = np.arange(width, dtype=np.float64)[None, :]
        v = np.arange(height, dtype=np.float64)[:, None]
        x = (u - self.cx) * depth / self.fx
        y = (v - self.cy) * depth / self.fy
        return np.stack([x, y, depth], axis=-1).astype(depth.dtype, copy=False)

    def ray_directions(self) -> np.ndarray:
        """Camera-frame ray through each pixel centre, scaled so that z = 1 (H, W, 3)."""
        return self.backproject(np.ones((self.height, self.width)))

    def to_json(self) -> dict:
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "depth_scale": self.depth_scale,
        }


# The published calibrations of the TUM RGB-D benchmark (depth registered to colour, 640x480).
TUM_CAMERAS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}


# The Kinect's nominal calibration (OpenNI's defaults, 640x480): the camera a converted log
# without one is given, so that the folder can be read (tum.write_sequence says so).
DEFAULT_CAMERA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


INTRINSICS_FIELDS = ("fx", "fy", "cx", "cy", "width", "height")  # depth_scale is optional
_EXPECTED_FIELDS = "fx, fy, cx, cy, width, height and optionally depth_scale"


def load_intrinsics_json(path: Path) -> Intrinsics:
    """Read `{"fx","fy","cx","cy","width","height","depth_scale"}` from a JSON file; a
    DatasetError that names the file and the field missing or invalid otherwise."""
    path = Path(path)
    values = _intrinsics_object(path, _read_intrinsics_text(path))
    missing = [name for name in INTRINSICS_FIELDS if name not in values]
    if missing:
        raise DatasetError(
            f"{path}: not a valid intrinsics file: no {', '.join(missing)} (expected "
            f"{_EXPECTED_FIELDS})"
        )
    numbers = {name: _number_field(path, values, name) for name in ("fx", "fy", "cx", "cy")}
    numbers["depth_scale"] = (
        _number_field(path, values, "depth_scale") if "depth_scale" in values else TUM_DEPTH_SCALE
    )
    try:
        return Intrinsics(
            width=_size_field(path, values, "width"),
            height=_size_field(path, values, "height"),
            **numbers,
        )
    except ConfigError as err:
        raise DatasetError(f"{path}: not a valid intrinsics file ({err!s})") from None


def _read_intrinsics_text(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file; expected intrinsics JSON") from None
    except OSError as err:
        raise DatasetError(f"{path}: cannot read ({err.strerror or err})") from None


def _intrinsics_object(path: Path, text: str) -> dict:
    """The JSON object of an intrinsics file; anything else is a DatasetError naming it."""
    try:
        values = json.loads(text)
    except RecursionError:
        raise DatasetError(f"{path}: not a valid intrinsics file (nested too deeply)") from None
    except json.JSONDecodeError as err:
        raise DatasetError(f"{path}: not a valid intrinsics file (not JSON: {err})") from None
    if not isinstance(values, dict):
        raise DatasetError(
            f"{path}: not a valid intrinsics file: a JSON {_json_kind(values)}, expected an "
            f"object with {_EXPECTED_FIELDS}"
        )
    return values


def _json_kind(value: object) -> str:
    kinds = {list: "list", str: "string", bool: "boolean", type(None): "null"}
    return kinds.get(type(value), "number")


def _shown(value: object) -> str:
    """A field's value for a one-line message, cut to a readable length."""
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else f"{text[:37]}..."


def _number_field(path: Path, values: dict, name: str) -> float:
    """Field `name` as a number (a JSON number, or a string holding one)."""
    value = values[name]
    try:
        if isinstance(value, bool):
            raise TypeError
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(
            f"{path}: not a valid intrinsics file: {name} {_shown(value)} is not a number"
        ) from None


def _size_field(path: Path, values: dict, name: str) -> int:
    """Field `name` (width or height) as a positive whole number of pixels: an image has no
    fraction of a pixel, and truncating one would describe another camera."""
    number = _number_field(path, values, name)
    if not (number.is_integer() and number >= 1):
        raise DatasetError(
            f"{path}: not a valid intrinsics file: {name} {_shown(values[name])} is not a "
            "whole number of pixels of at least 1"
        )
    return int(number)


def camera_from_folder_name(folder: Path) -> Intrinsics | None:
    """The TUM camera named in a folder name (`rgbd_dataset_freiburg2_desk` -> freiburg2)."""
    match = re.search(r"freiburg([123])", Path(folder).resolve().name)
    return TUM_CAMERAS[f"freiburg{match.group(1)}"] if match else None


def parse_intrinsics(text: str, width: int = 640, height: int = 480) -> Intrinsics:
    """Intrinsics from the command line's `fx,fy,cx,cy` (depth in TUM units, 1/5000 m)."""
    try:
        fx, fy, cx, cy = (float(part) for part in text.split(","))
    except ValueError:
        raise ConfigError(
            f"--intrinsics expects fx,fy,cx,cy (four numbers), got {text!r}"
        ) from None
    return Intrinsics(fx, fy, cx, cy, width, height)


def intrinsics_from_option(text: str, width: int = 640, height: int = 480) -> Intrinsics:
    """The command line's --intrinsics: a JSON file (which gives its own size), or fx,fy,cx,cy
    for images of width x height."""
    if Path(text).suffix == ".json" or Path(text).is_file():
        return load_intrinsics_json(Path(text))
    return parse_intrinsics(text, width=width, height=height)
