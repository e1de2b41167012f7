"""Plausibility of a run's inputs before any work, and its health after it.

A value can be valid and still absurd for a depth camera: a principal point far outside the
image, a field of view of two degrees, a volume whose voxels are metres wide or which the first
frame's surface misses, depth in millimetres read with TUM's 1/5000 m. Such a run would go
through without an error and give nothing (no surface, a blank preview), so these checks refuse
it in one line that says what is implausible and what would be plausible; `OVERRIDE` (the
command line's option) runs it anyway. Settings no run can succeed with, such as iterations that
leave the tracker no work (`check_iterations`), are refused whatever the option says.

`run_warnings` looks at a finished run for what shows only then (a volume that received no
surface, a tracker that failed on every frame); the command writes them to report.json and
stderr.
"""

from __future__ import annotations

import math

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, VolumeConfig
from kintinuous_ref.errors import ConfigError

OVERRIDE = "--no-plausibility-checks"
FIELD_OF_VIEW_DEG = (20.0, 160.0)  # horizontal: a telephoto lens to a wide fisheye
PIXEL_ASPECT = (0.5, 2.0)  # fx / fy of any camera with near-square pixels
# a depth camera's working range, for the median of a frame: a Kinect measures from 0.5 m
MEDIAN_DEPTH_M = (0.5, 10.0)
# a median nearer than this, which a common depth scale would move into AMBIGUOUS_FIT, is
# suspicious but possible (a close-up): a warning
AMBIGUOUS_BELOW_M = 0.8
AMBIGUOUS_FIT_M = (1.0, 5.0)
DEPTH_SCALES = {1000.0: "millimetres", 5000.0: "TUM's 1/5000 m"}
MAX_VOXEL_M = 0.1  # coarser voxels hold no surface detail of a room
MIN_SURFACE_SHARE = 0.01  # of the first frame's points, inside the volume
SURFACE_SHARE_SUGGESTED = 90  # percent of the first frame's points a suggested volume holds

# Which iterations each dense method runs (odometry.DenseTracker.iterations); a FOVIS switch
# "fovis/X" runs X's, FOVIS alone none.
ITERATION_KEYS = {
    "icp": "icp.iterations",
    "rgbd": "rgbd.iterations",
    "icp+rgbd": "rgbd.combined_iterations",
}


class Implausible(ConfigError):
    """An input that is valid but absurd; its message says how to run it anyway."""

    def __init__(self, message: str) -> None:
        super().__init__(f"{message} ({OVERRIDE} runs it anyway)")


def check_iterations(config: Config, odometry: str) -> None:
    """Refuse iterations that give the tracker `odometry` no Gauss-Newton step at any pyramid
    level: the camera would stay at its first pose with no failure reported."""
    key = ITERATION_KEYS.get(odometry.removeprefix("fovis/"))
    if key is None:
        return  # ground truth, or FOVIS alone: no dense iterations
    section, name = key.split(".")
    iterations = list(getattr(getattr(config, section), name))
    if not any(iterations):
        raise ConfigError(
            f"{key} {iterations}: no pyramid level runs a step, so --odometry {odometry} would "
            f"leave the camera at its first pose; give at least one level a count, such as "
            f"{list(getattr(getattr(Config(), section), name))} (the default)"
        )


def check_camera(camera: Intrinsics, source: str) -> None:
    """Refuse a camera whose principal point lies outside its image, whose field of view no
    depth camera has, or whose pixels are far from square (`source`: where it came from)."""
    width, height = camera.width, camera.height
    if not (0 <= camera.cx <= width and 0 <= camera.cy <= height):
        raise Implausible(
            f"{source}: implausible camera: principal point (cx, cy) = ({camera.cx:g}, "
            f"{camera.cy:g}) lies outside the {width}x{height} image; expected cx in 0..{width} "
            f"and cy in 0..{height} (about {width / 2:g}, {height / 2:g})"
        )
    low, high = FIELD_OF_VIEW_DEG
    fov = math.degrees(2 * math.atan(width / (2 * camera.fx)))
    if not low <= fov <= high:
        focal = [width / (2 * math.tan(math.radians(angle) / 2)) for angle in (high, low)]
        raise Implausible(
            f"{source}: implausible camera: fx = {camera.fx:g} px gives a horizontal field of "
            f"view of {fov:.3g} degrees over {width} px; expected {low:g} to {high:g} degrees "
            f"(fx between {focal[0]:.0f} and {focal[1]:.0f} px)"
        )
    aspect = camera.fx / camera.fy
    if not PIXEL_ASPECT[0] <= aspect <= PIXEL_ASPECT[1]:
        raise Implausible(
            f"{source}: implausible camera: fx / fy = {camera.fx:g} / {camera.fy:g} = "
            f"{aspect:.3g}; expected near-square pixels, fx / fy between {PIXEL_ASPECT[0]:g} "
            f"and {PIXEL_ASPECT[1]:g}"
        )


def check_depth_scale(camera: Intrinsics, depth: np.ndarray, source: str, frame: int) -> list[str]:
    """Refuse a depth scale that puts the median valid depth of a frame (`depth`, metres read
    with `camera.depth_scale`) outside a depth camera's range, naming the scale that would fit;
    a warning (returned) where a common scale would fit better but the frame may be a close-up.
    """
    valid = depth[np.isfinite(depth) & (depth > 0)]
    if not len(valid):
        return []
    median = float(np.median(valid))
    scale = camera.depth_scale
    said = f"{source}: depth_scale {scale:g} puts frame {frame}'s median depth at {median:.3g} m"
    low, high = MEDIAN_DEPTH_M
    if not low <= median <= high:
        raise Implausible(
            f"{said}, outside a depth camera's {low:g}..{high:g} m; {_fit(median, scale)}"
        )
    fits = [s for s in DEPTH_SCALES if _within(median * scale / s, AMBIGUOUS_FIT_M)]
    if median < AMBIGUOUS_BELOW_M and fits:
        return [f"{said}, unusually near; if the data is not a close-up, {_fit(median, scale)}"]
    return []


def _within(value: float, bounds: tuple[float, float]) -> bool:
    return bounds[0] <= value <= bounds[1]


def _fit(median: float, scale: float) -> str:
    """What depth_scale would put the median at a room's distance: a common one, else the
    factor."""
    raw = median * scale
    for common, unit in DEPTH_SCALES.items():
        if common != scale and _within(raw / common, AMBIGUOUS_FIT_M):
            return f"depth_scale {common:g} ({unit}) puts it at {raw / common:.3g} m"
    wanted = raw / 2.0  # a median of 2 m
    return f"depth_scale {wanted:.3g} puts it at 2 m (a factor of {scale / wanted:.3g})"


def surface_sizes(
    depth: np.ndarray, camera: Intrinsics, rotation: np.ndarray, volume: VolumeConfig
) -> np.ndarray:
    """For each valid pixel of a frame, the smallest volume side (metres) that holds its point
    when the volume is placed for a camera of orientation `rotation` (tsdf.volume_origin)."""
    points = camera.backproject(depth.astype(np.float64))[depth > 0]
    offsets = points @ np.asarray(rotation, dtype=np.float64).T  # world-aligned, from the camera
    if volume.placement != "ahead":
        return 2.0 * np.abs(offsets).max(axis=1, initial=0.0)
    # ahead: the cube [c + s/2 a - s/2, c + s/2 a + s/2] (a, the optical axis) holds q when, per
    # axis, q <= s (1 + a) / 2 and -q <= s (1 - a) / 2
    axis = np.asarray(rotation, dtype=np.float64)[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        above = np.where(offsets > 0, 2.0 * offsets / (1.0 + axis), 0.0)
        below = np.where(offsets < 0, -2.0 * offsets / (1.0 - axis), 0.0)
    return np.nan_to_num(np.maximum(above, below), nan=np.inf).max(axis=1, initial=0.0)


def check_volume(
    volume: VolumeConfig, camera: Intrinsics, depth: np.ndarray | None, rotation: np.ndarray
) -> None:
    """Refuse a volume whose voxels are coarser than MAX_VOXEL_M, or which would hold (almost)
    none of the first frame's surface (`depth` in metres, seen from a camera of `rotation`;
    None when the frame cannot be read, which the run then reports)."""
    option = "--volume-size (volume.size)"
    largest = MAX_VOXEL_M * volume.resolution
    if volume.voxel_size > MAX_VOXEL_M:
        raise Implausible(
            f"{option} {volume.size:g} m: voxels of {volume.voxel_size:.3g} m at resolution "
            f"{volume.resolution}, coarser than {MAX_VOXEL_M:g} m, hold no surface; choose at "
            f"most {largest:g} m"
        )
    if depth is None:
        return
    sizes = surface_sizes(depth, camera, rotation, volume)
    if not len(sizes):
        return
    share = float(np.mean(sizes <= volume.size))
    if share < MIN_SURFACE_SHARE:
        valid = depth[depth > 0]
        wanted = float(np.percentile(sizes, SURFACE_SHARE_SUGGESTED))
        raise Implausible(
            f"{option} {volume.size:g} m: the first frame's surface (depths {valid.min():.2f} to "
            f"{valid.max():.2f} m) lies outside the volume, which would hold {share:.1%} of it; "
            f"choose at least {wanted:.2g} m (and at most {largest:g} m at resolution "
            f"{volume.resolution})"
        )


def check_inputs(
    config: Config,
    camera: Intrinsics,
    camera_source: str,
    depth: np.ndarray | None,
    first_pose: np.ndarray,
    frame: int,
) -> list[str]:
    """Every check of this module a run's inputs get before its work: the camera, the volume's
    voxels, and with the first frame's `depth` (metres; None when it cannot be read) its depth
    scale and the surface the volume would hold. Returns the warnings."""
    check_camera(camera, camera_source)
    check_volume(config.volume, camera, None, first_pose[:3, :3])
    if depth is None:
        return []
    warnings = check_depth_scale(camera, depth, camera_source, frame)
    measured = np.where(depth <= config.preprocess.max_depth, depth, 0.0)  # what is fused
    check_volume(config.volume, camera, measured, first_pose[:3, :3])
    return warnings


def run_warnings(
    frames: int, fused: int, tracking_failures: int, vertices: int | None
) -> list[str]:
    """What a finished run shows only now: a volume that received no surface, a tracker that
    failed on every frame after the first."""
    warnings = []
    if fused and vertices == 0:
        warnings.append(
            f"0 vertices after fusing {fused} frames: the surface lies outside the volume or "
            "its depth is read with the wrong scale; check --volume-size and the depth_scale"
        )
    if frames > 2 and tracking_failures >= frames - 1:
        warnings.append(
            f"tracking failed on all {tracking_failures} frames after the first: the camera "
            "stayed where the failures left it (report.json's failure_reasons say why)"
        )
    return warnings
