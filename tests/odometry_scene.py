"""An analytic test scene for the odometry tests, independent of the synthetic-scene module.

The inside of a box-shaped room (five walls), with an intensity texture that is a smooth function
of the world point (sums of sinusoids), rendered exactly by ray-plane intersection at any pose and
pyramid level. Depth, vertices, normals and intensity are exact; the intensity derivatives are the
same 3x3 Gaussian + Sobel/8 the preprocessing uses. Nothing here comes from the code under test.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics

# Walls as (unit normal pointing into the room, offset): n . x = offset on the wall.
WALLS = [
    (np.array([0.0, 0.0, -1.0]), -3.0),  # back wall z = 3
    (np.array([0.0, -1.0, 0.0]), -1.0),  # floor y = 1 (y points down)
    (np.array([0.0, 1.0, 0.0]), -1.2),  # ceiling y = -1.2
    (np.array([1.0, 0.0, 0.0]), -1.5),  # left wall x = -1.5
    (np.array([-1.0, 0.0, 0.0]), -1.4),  # right wall x = 1.4
]
# A corridor along z: floor, ceiling and side walls only, no wall ahead within view. ICP
# cannot see motion along z here (every normal is perpendicular to it); the texture can.
CORRIDOR = [WALLS[1], WALLS[2], WALLS[3], WALLS[4]]
# Texture: I(p) = 128 + sum a_i sin(k_i . p + phase_i), wave vectors in rad/m.
_WAVES = [
    (55.0, np.array([31.0, 7.0, 19.0]), 0.3),
    (35.0, np.array([-11.0, 29.0, 13.0]), 1.1),
    (20.0, np.array([5.0, -9.0, 41.0]), 2.0),
]

CAMERA = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)


def texture(points: np.ndarray) -> np.ndarray:
    value = np.full(points.shape[:-1], 128.0)
    for amplitude, k, phase in _WAVES:
        value += amplitude * np.sin(points @ k + phase)
    return value


def render(pose: np.ndarray, camera: Intrinsics, dark: float = 1.0, walls=None, far: float = 8.0):
    """Exact depth (h, w), camera-frame normals (h, w, 3) and intensity (h, w) at a pose.

    Pixels whose ray hits nothing within `far` metres have depth 0, NaN normals, intensity 0.
    """
    rays = camera.ray_directions().reshape(-1, 3)  # camera frame, z = 1
    world_rays = rays @ pose[:3, :3].T
    origin = pose[:3, 3]
    best_t = np.full(len(rays), np.inf)
    best_normal = np.zeros((len(rays), 3))
    for normal, offset in WALLS if walls is None else walls:
        denominator = world_rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offset - origin @ normal) / denominator
        hit = (denominator < 0) & (t > 0) & (t < best_t)
        best_t[hit] = t[hit]
        best_normal[hit] = normal
    hit = best_t <= far
    depth = np.where(hit, best_t, 0.0)  # rays have z = 1 in the camera frame, so t is the depth
    world = origin + world_rays * np.where(hit, best_t, 0.0)[:, None]
    intensity = np.where(hit, 128.0 + dark * (texture(world) - 128.0), 0.0)
    normals = np.where(hit[:, None], best_normal @ pose[:3, :3], np.nan)  # world -> camera: R^T n
    shape = (camera.height, camera.width)
    return (
        depth.reshape(shape).astype(np.float32),
        normals.reshape(*shape, 3).astype(np.float32),
        intensity.reshape(shape).astype(np.float32),
    )


@dataclass
class Level:
    camera: Intrinsics
    depth: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    intensity: np.ndarray
    intensity_dx: np.ndarray
    intensity_dy: np.ndarray


@dataclass
class Frame:
    levels: list[Level]


def gradients(intensity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3x3 Gaussian (sigma 0.8) then Sobel / 8: intensity units per pixel (paper IV-A.1)."""
    blurred = cv2.GaussianBlur(intensity, (3, 3), 0.8, borderType=cv2.BORDER_REPLICATE)
    dx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
    dy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
    return dx, dy


def frame(
    pose: np.ndarray, camera: Intrinsics = CAMERA, levels: int = 4, dark: float = 1.0, walls=None
) -> Frame:
    """A preprocessed-frame stand-in: exact geometry per level, Gaussian intensity pyramid."""
    result = []
    intensity = None
    for level in range(levels):
        level_camera = camera.at_level(level)
        depth, normals, exact_intensity = render(pose, level_camera, dark, walls)
        # Geometry is exact at every level; the intensity pyramid is a 5x5 Gaussian pyrDown of
        # the level above (point-sampling the texture at a coarse level would alias).
        intensity = exact_intensity if intensity is None else cv2.pyrDown(intensity)
        dx, dy = gradients(intensity)
        vertices = level_camera.backproject(depth)
        vertices[depth == 0] = np.nan
        result.append(Level(level_camera, depth, vertices, normals, intensity, dx, dy))
    return Frame(result)


def model(pose: np.ndarray, camera: Intrinsics = CAMERA, levels: int = 3, walls=None):
    """World-frame (vertices, normals) per level: what a perfect raycast from `pose` gives."""
    pyramid = []
    for level in range(levels):
        level_camera = camera.at_level(level)
        depth, normals, _ = render(pose, level_camera, walls=walls)
        vertices = level_camera.backproject(depth).astype(np.float64)
        vertices[depth == 0] = np.nan
        world = vertices @ pose[:3, :3].T + pose[:3, 3]
        world_normals = normals.astype(np.float64) @ pose[:3, :3].T
        pyramid.append((world.astype(np.float32), world_normals.astype(np.float32)))
    return pyramid


def look_pose(position, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at `position`, turned by yaw (about y) then pitch (about x)."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rx = np.array(
        [[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]]
    )
    pose = np.eye(4)
    pose[:3, :3] = ry @ rx
    pose[:3, 3] = position
    return pose


def room_poses() -> tuple[np.ndarray, np.ndarray]:
    """(previous, current) camera poses of the estimators' tests in the room: about 3 cm and 1.5
    degrees apart, a brisk hand-held frame-to-frame motion at 30 Hz."""
    previous = look_pose([0.1, -0.1, 0.2], 5, -10)
    return previous, previous @ se3.exp(np.array([0.01, -0.02, 0.015, 0.02, -0.01, 0.03]))


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) of `estimate` relative to `truth`."""
    difference = se3.inverse(truth) @ estimate
    return 1000 * float(np.linalg.norm(difference[:3, 3])), float(
        np.degrees(se3.rotation_angle(difference[:3, :3]))
    )
