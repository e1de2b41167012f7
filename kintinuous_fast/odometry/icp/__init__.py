"""KinectFusion's ICP (kintinuous_ref.odometry.icp) on both targets: `ops.py` the maths of one
pair, `cpu.py` the loops, `cuda.py` the kernels, each with the reference module's public names
and signatures; here the host side they share: the per-call constants (the relative pose as
the reference computes it, the pair limits, the robust weights' terms) and the per-frame
problem written once over either target's systems."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import axial_noise
from kintinuous_ref.config import IcpConfig
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.icp import REFERENCE_DEPTH, robust_threshold
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.vocabulary import ROBUST_KERNELS


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


class _IcpProblem:
    """kintinuous_ref.odometry.icp.IcpProblem (the same arguments and checks) over a target's
    systems: a subclass says how arrays are staged for its kernels (`_stage`) and computes a
    level's system with the number of valid current points (`system_and_valid`)."""

    def __init__(
        self,
        current_levels: Sequence,
        model_levels: Sequence[tuple[Any, Any]],
        model_pose: np.ndarray,
        distance_threshold: float = 0.10,
        angle_threshold_deg: float = 20.0,
        robust_kernel: str = "none",
        robust_noise: float = IcpConfig.robust_noise,
        model_noise: float | None = None,
    ) -> None:
        self.current_levels = current_levels
        self.model_levels = model_levels
        self.model_pose = model_pose
        self.distance_threshold = distance_threshold
        self.angle_threshold_deg = angle_threshold_deg
        self.robust_kernel = robust_kernel
        self.robust_threshold = robust_threshold(robust_kernel, robust_noise)
        self.model_noise = model_noise
        self._maps: dict[int, tuple[Any, Any, Any, Any]] = {}
        self._points: dict[int, Any] = {}  # per level, for targets that compact the valid points
        self._model_inverse: np.ndarray | None = None

    @staticmethod
    def _stage(array: Any) -> Any:
        raise NotImplementedError

    @property
    def model_inverse(self) -> np.ndarray:
        """se3.inverse(model_pose), computed (and the pose checked) once per frame."""
        if self._model_inverse is None:
            self._model_inverse = se3.inverse(self.model_pose)
        return self._model_inverse

    def maps(self, level: int) -> tuple[Any, Any, Any, Any]:
        """The level's current and model maps as the kernels take them, staged once."""
        if level not in self._maps:
            current = self.current_levels[level]
            model_vertices, model_normals = self.model_levels[level]
            self._maps[level] = (
                self._stage(current.vertices),
                self._stage(current.normals),
                self._stage(model_vertices),
                self._stage(model_normals),
            )
        return self._maps[level]

    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        """The level's system at `pose` and the number of valid current points."""
        raise NotImplementedError

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return self.system_and_valid(level, pose)[0]

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Matched pairs per valid current vertex at a pyramid level (0 when none is valid)."""
        system, valid = self.system_and_valid(level, pose)
        return system.count / valid if valid else 0.0
