"""Keyframes: the frames that loop closure remembers, and what it keeps of each.

A keyframe is taken when the camera has moved `keyframe_distance` metres or turned
`keyframe_angle_deg` degrees since the last one (Kintinuous samples its pose graph as the volume
shifts, which is also every few tens of centimetres). Each keeps:

- its pose as the map used it (the tracker's estimate, in the frame the map was fused in) and
  the path length travelled up to it (to judge how much drift a loop may correct);
- ORB features (Rublee et al. 2011, OpenCV): keypoints and 256-bit descriptors on the intensity
  image, for recognising the place, each with its 3D point from the raw depth (NaN without
  depth), for the geometric check;
- the vertex and normal maps and the intensity of pyramid levels 1 and coarser, for the dense
  check: level 0 would cost four times the memory and ICP from level 1 already agrees with it to
  a fraction of a voxel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import LoopClosureConfig
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

FIRST_KEPT_LEVEL = 1  # pyramid levels from this one on are kept for the dense check


@dataclass
class Keyframe:
    node: int  # its number: the pose graph node and the order keyframes were taken in
    frame: int  # index of the frame in the sequence
    pose: np.ndarray  # (4, 4) camera-to-world as fused
    travelled: float  # metres of path from the first frame to this one
    keypoints: np.ndarray  # (N, 2) float32 pixel coordinates (level 0)
    descriptors: np.ndarray  # (N, 32) uint8 ORB descriptors
    points: np.ndarray  # (N, 3) float64 camera-frame points of the keypoints, NaN without depth
    levels: list[PyramidLevel]  # pyramid levels FIRST_KEPT_LEVEL.. (camera frame)


def is_new_keyframe(
    last_pose: np.ndarray | None, pose: np.ndarray, config: LoopClosureConfig
) -> bool:
    """True for the first frame, and once the camera has moved or turned far enough."""
    if last_pose is None:
        return True
    step = se3.inverse(last_pose) @ pose
    moved = np.linalg.norm(step[:3, 3]) >= config.keyframe_distance
    turned = np.degrees(se3.rotation_angle(step[:3, :3])) >= config.keyframe_angle_deg
    return bool(moved or turned)


def orb_features(intensity: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints (N, 2) float32 pixels, descriptors (N, 32) uint8) of an intensity image."""
    image = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
    # The default 31-pixel patch leaves no room for features on small images; scale it down.
    patch = int(np.clip(min(image.shape) // 8, 9, 31))
    orb = cv2.ORB_create(nfeatures=count, edgeThreshold=patch, patchSize=patch)
    keypoints, descriptors = orb.detectAndCompute(image, None)
    if descriptors is None or not keypoints:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    pixels = np.array([k.pt for k in keypoints], dtype=np.float32)
    return pixels, descriptors


def keypoint_points(pixels: np.ndarray, depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Camera-frame 3D points (N, 3) of pixels from the raw depth at the nearest pixel; NaN
    where there is no depth."""
    u = np.clip(np.rint(pixels[:, 0]).astype(np.int64), 0, depth.shape[1] - 1)
    v = np.clip(np.rint(pixels[:, 1]).astype(np.int64), 0, depth.shape[0] - 1)
    z = depth[v, u].astype(np.float64)
    z[z <= 0] = np.nan
    x = (pixels[:, 0] - camera.cx) / camera.fx * z
    y = (pixels[:, 1] - camera.cy) / camera.fy * z
    return np.column_stack([x, y, z])


def make_keyframe(
    node: int,
    frame: int,
    pose: np.ndarray,
    travelled: float,
    preprocessed: PreprocessedFrame,
    config: LoopClosureConfig,
) -> Keyframe:
    """A keyframe of a preprocessed frame (on the host) at camera-to-world `pose`."""
    finest = preprocessed.levels[0]
    pixels, descriptors = orb_features(finest.intensity, config.orb_features)
    return Keyframe(
        node=node,
        frame=frame,
        pose=np.asarray(pose, dtype=np.float64).copy(),
        travelled=travelled,
        keypoints=pixels,
        descriptors=descriptors,
        points=keypoint_points(pixels, preprocessed.depth, finest.camera),
        levels=list(preprocessed.levels[FIRST_KEPT_LEVEL:]),
    )
