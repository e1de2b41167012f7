"""Smooth, hand-held-like camera paths at 30 Hz.

A path is a smooth base motion (position and viewing direction as closed-form functions of time)
plus hand tremor: sums of low-frequency sinusoids (0.3..2 Hz, millimetres and tenths of a degree)
on the position and on the camera's yaw, pitch and roll, with seeded random phases. Everything is
a function of time, so frame i has the same pose whatever the sequence length.
World frame: z up. Camera frame (camera.py): x right, y down, z forward.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kintinuous_ref import se3

FRAME_RATE = 30.0  # Hz
START_TIME = 1.0  # seconds; the timestamp of frame 0 (as in the shared TUM-layout data)

# Tremor: (frequency Hz, position amplitude m, angle amplitude rad) per sinusoid.
_TREMOR = (
    (0.35, 0.006, np.radians(0.6)),
    (0.8, 0.003, np.radians(0.3)),
    (1.7, 0.0015, np.radians(0.15)),
)

PathFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def frame_times(frames: int) -> np.ndarray:
    """Seconds since the start of the motion of frames 0..frames-1."""
    return np.arange(frames) / FRAME_RATE


def look_rotation(forward: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (N, 3, 3) looking along `forward` (N, 3), level (no roll)."""
    up = np.array([0.0, 0.0, 1.0])  # world z
    z = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    x = np.cross(z, up)  # right = forward x up (y then points down, as the camera frame wants)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _euler_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Small camera-frame rotation: yaw about y (down), pitch about x (right), roll about z."""
    return se3.exp(np.array([pitch, yaw, roll, 0.0, 0.0, 0.0]))[:3, :3]


def tremor(times: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Hand tremor: position offsets (N, 3) metres and camera angles (N, 3) radians."""
    offsets = np.zeros((len(times), 3))
    angles = np.zeros((len(times), 3))
    for frequency, position_amplitude, angle_amplitude in _TREMOR:
        phases = rng.uniform(0, 2 * np.pi, (2, 3))
        scale = rng.uniform(0.6, 1.0, (2, 3))
        arg = 2 * np.pi * frequency * times[:, None]
        offsets += position_amplitude * scale[0] * np.sin(arg + phases[0])
        angles += angle_amplitude * scale[1] * np.sin(arg + phases[1])
    return offsets, angles


def hand_held(path: PathFunction, frames: int, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world poses (frames, 4, 4) along `path` (times -> positions, forwards) + tremor."""
    times = frame_times(frames)
    positions, forwards = path(times)
    offsets, angles = tremor(times, rng)
    rotations = look_rotation(forwards)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for i in range(frames):
        poses[i, :3, :3] = rotations[i] @ _euler_rotation(*angles[i])
    poses[:, :3, 3] = positions + offsets
    return poses


def direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Unit viewing directions (N, 3) from heading (about world z) and elevation (radians)."""
    return np.stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1
    )
