"""A tiny analytic scene for the mapping tests: a rotated box in front of a wall, ray cast exactly.

Independent of the code under test: depth, surface id and colour per pixel come from closed-form
ray-box and ray-plane intersections.
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.camera import Intrinsics

CAMERA = Intrinsics(160.0, 160.0, 79.5, 59.5, 160, 120)


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def pose(rot: np.ndarray, translation) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, translation
    return out


class BoxScene:
    """An oriented box (centre, half sizes, rotation) in front of a wall z = wall_z (world)."""

    def __init__(
        self,
        centre=(0.02, -0.02, 0.55),
        half=(0.12, 0.1, 0.12),
        rot: np.ndarray | None = None,
        wall_z: float = 0.85,
        box_colour=(220, 30, 30),
        wall_colour=(30, 30, 220),
    ):
        self.centre = np.array(centre, float)
        self.half = np.array(half, float)
        self.rot = rotation("y", 30) @ rotation("x", -20) if rot is None else rot
        self.wall_z = wall_z
        self.box_colour = np.array(box_colour, np.uint8)
        self.wall_colour = np.array(wall_colour, np.uint8)

    def cast(self, camera_pose: np.ndarray, camera: Intrinsics = CAMERA):
        """(depth (H,W) float32 camera z, surface id (H,W): 0 wall, 1..6 box faces, -1 none,
        world normals (H,W,3), distance along the unit ray (H,W))."""
        rays = camera.ray_directions().reshape(-1, 3)
        directions = rays @ camera_pose[:3, :3].T
        lengths = np.linalg.norm(directions, axis=1)
        directions = directions / lengths[:, None]
        origin = camera_pose[:3, 3]
        # Box: slab method in the box frame.
        o_box = self.rot.T @ (origin - self.centre)
        d_box = directions @ self.rot
        with np.errstate(divide="ignore"):
            t1 = (-self.half - o_box) / d_box
            t2 = (self.half - o_box) / d_box
        t_near = np.minimum(t1, t2)
        entry = t_near.max(axis=1)
        exit_ = np.maximum(t1, t2).min(axis=1)
        hits_box = (entry <= exit_) & (entry > 0)
        face_axis = t_near.argmax(axis=1)
        face_sign = -np.sign(d_box[np.arange(len(d_box)), face_axis])
        # Wall.
        with np.errstate(divide="ignore", invalid="ignore"):
            t_wall = (self.wall_z - origin[2]) / directions[:, 2]
        hits_wall = t_wall > 0
        t = np.where(hits_box, entry, np.where(hits_wall, t_wall, np.inf))
        surface = np.where(
            hits_box, 1 + face_axis * 2 + (face_sign > 0), np.where(hits_wall, 0, -1)
        )
        normals = np.zeros((len(t), 3))
        normals[hits_box] = self.rot[:, face_axis[hits_box]].T * face_sign[hits_box, None]
        normals[~hits_box & hits_wall] = [0, 0, -1]
        depth = np.where(np.isfinite(t), t / lengths, 0.0)  # z = distance / |ray with z=1|
        shape = (camera.height, camera.width)
        return (
            depth.reshape(shape).astype(np.float32),
            surface.reshape(shape),
            normals.reshape(*shape, 3),
            np.where(np.isfinite(t), t, np.nan).reshape(shape),
        )

    def colour(self, surface: np.ndarray) -> np.ndarray:
        out = np.zeros((*surface.shape, 3), np.uint8)
        out[surface == 0] = self.wall_colour
        out[surface >= 1] = self.box_colour
        return out


def away_from_edges(surface: np.ndarray, radius: int) -> np.ndarray:
    """True where every pixel within `radius` sees the same surface (no depth or face edge)."""
    same = np.ones(surface.shape, bool)
    height, width = surface.shape
    padded = np.pad(surface, radius, mode="constant", constant_values=-2)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            same &= padded[dy : dy + height, dx : dx + width] == surface
    return same & (surface >= 0)
