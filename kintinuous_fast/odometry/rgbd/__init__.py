"""Steinbruecker et al.'s dense RGB-D odometry (kintinuous_ref.odometry.rgbd) on both targets:
`ops.py` the maths of one interest point, `cpu.py` the loops, `cuda.py` the kernels, each with
the reference module's public names and signatures and the reference's RgbdProblem over its own
functions; here the host side they share: the input checks and the relative pose as the
reference computes it."""

from __future__ import annotations

from typing import Any

import numpy as np

from kintinuous_fast.odometry import check_image
from kintinuous_ref.camera import Intrinsics

# kintinuous_ref.odometry.rgbd's names that both targets export as they are (the result types,
# the argument check, the weights and the NumPy truth for tests).
REFERENCE_NAMES = [
    "Correspondences",
    "InterestPoints",
    "check_gradient",
    "photometric_residuals",
    "robust_row_weights",
    "sample_bilinear",
]
# The names each target computes itself (cpu.py with its loops, cuda.py with its kernels).
TARGET_NAMES = [
    "RgbdProblem",
    "correspond",
    "interest_points",
    "photometric_rows",
    "prepare_level",
    "rgbd_system",
]


def check_images(kind: str, camera: Intrinsics, **images: Any) -> None:
    """Each image (name=array) of the camera's (h, w), else a one-line DatasetError naming it
    ("{kind} {name} image")."""
    shape = (camera.height, camera.width)
    for name, image in images.items():
        check_image(f"{kind} {name} image", image, shape)


def relative_pose(pose: np.ndarray, previous_pose: np.ndarray) -> np.ndarray:
    """T_prev^-1 T exactly as `correspond` computes it (np.linalg.inv)."""
    return np.ascontiguousarray(np.linalg.inv(previous_pose) @ pose, dtype=np.float64)
