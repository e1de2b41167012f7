"""KinectFusion's ICP (kintinuous_ref.odometry.icp) on both targets: `ops.py` the maths of one
pair, `cpu.py` the loops, `cuda.py` the kernels, each with the reference module's public names
and signatures; here the host side they share: the per-call constants (the relative pose as
the reference computes it, the pair limits, the robust weights' terms) and the per-frame
problem written once over either target's systems."""

from __future__ import annotations

from abc import ABC, abstractmethod
from functools import cached_property
from typing import Any

import numpy as np

from kintinuous_fast.odometry import check_map
from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics, axial_noise
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.icp import REFERENCE_DEPTH, IcpProblem
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.vocabulary import ROBUST_KERNELS

# kintinuous_ref.odometry.icp's names that both targets export as they are (host code: checks,
# weights and the NumPy truth for tests).
REFERENCE_NAMES = [
    "depth_noise_scale",
    "map_columns",
    "pair_weights",
    "point_to_plane_cost",
    "robust_threshold",
    "robust_weights",
    "valid_points",
    "voxel_noise",
]
# The names each target computes itself (cpu.py with its loops, cuda.py with its kernels).
TARGET_NAMES = ["IcpProblem", "associate", "icp_system", "point_to_plane_rows"]


def check_maps(kind: str, vertices: Any, normals: Any, camera: Intrinsics) -> None:
    """The `kind` ("current", "model") vertex and normal maps of the camera's size, else a
    one-line DatasetError naming the one that is not."""
    check_map(f"{kind} vertex map", vertices, camera)
    check_map(f"{kind} normal map", normals, camera)


def icp_constants(
    pose: np.ndarray,
    model_pose: np.ndarray,
    distance_threshold: float,
    angle_threshold_deg: float,
    model_inverse: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(pose, current camera to model camera, squared distance, cos angle) as `associate`.
    `model_inverse`: se3.inverse(model_pose) when the caller has it already (a per-frame
    problem computes and checks it once, not every iteration)."""
    pose = np.ascontiguousarray(pose, dtype=np.float64)
    inverse = se3.inverse(model_pose) if model_inverse is None else model_inverse
    to_model = np.ascontiguousarray(inverse @ pose)
    return (
        pose,
        to_model,
        float(distance_threshold**2),
        float(np.cos(np.radians(angle_threshold_deg))),
    )


def kernel_code(robust_kernel: str) -> int:
    """The integer code of an ICP robust kernel the kernels take (ops.KERNEL_*)."""
    if robust_kernel not in ROBUST_KERNELS:
        raise ConfigError(
            f"icp.robust_kernel must be one of {ROBUST_KERNELS}, got {robust_kernel!r}"
        )
    return ROBUST_KERNELS.index(robust_kernel)


# robust_terms of least squares: every pair weighs 1.
NO_WEIGHTS = (ROBUST_KERNELS.index("none"), 0.0, -1.0, 1.0)


def robust_terms(robust_kernel: str, threshold: float, model_noise: float | None) -> tuple:
    """The ICP pair weights as ops.pair_weight takes them: (kernel code, Huber's k or Tukey's c,
    model_noise^2, sigma(REFERENCE_DEPTH)^2); a model variance of -1 without `model_noise`
    (ref icp.pair_weights). NO_WEIGHTS: least squares."""
    if model_noise is None:
        return kernel_code(robust_kernel), float(threshold), NO_WEIGHTS[2], NO_WEIGHTS[3]
    variance = float(model_noise) ** 2
    reference = float(axial_noise(REFERENCE_DEPTH)) ** 2 + variance
    return kernel_code(robust_kernel), float(threshold), variance, reference


class _IcpProblem(IcpProblem, ABC):
    """kintinuous_ref.odometry.icp.IcpProblem (its arguments, checks and per-level caches) over a
    target's systems: `points(level)` and `model(level)` hold what the target's loops or kernels
    read, staged once per frame and level, and a subclass computes a level's system with the
    number of valid current points (`system_and_valid`)."""

    @staticmethod
    @abstractmethod
    def stage(array: Any) -> Any:
        """An array as the target's loops or kernels take it."""

    @cached_property
    def model_inverse(self) -> np.ndarray:
        """se3.inverse(model_pose), computed (and the pose checked) once per frame."""
        return se3.inverse(self.model_pose)

    @cached_property
    def robust(self) -> tuple:
        """The pairs' weights as the ops take them (robust_terms)."""
        return robust_terms(self.robust_kernel, self.robust_threshold, self.model_noise)

    def constants(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        """icp_constants at `pose`, from the inverse model pose computed once."""
        return icp_constants(
            pose,
            self.model_pose,
            self.distance_threshold,
            self.angle_threshold_deg,
            self.model_inverse,
        )

    def model(self, level: int) -> tuple[Any, Any]:
        """The level's model vertex and normal maps, checked and staged once."""
        if level not in self._model:
            vertices, normals = self.model_levels[level]
            check_maps("model", vertices, normals, self.current_levels[level].camera)
            self._model[level] = (self.stage(vertices), self.stage(normals))
        return self._model[level]

    @abstractmethod
    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        """The level's system at `pose` and the number of valid current points."""

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return self.system_and_valid(level, pose)[0]

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Matched pairs per valid current vertex at a pyramid level (0 when none is valid)."""
        system, valid = self.system_and_valid(level, pose)
        return system.count / valid if valid else 0.0
