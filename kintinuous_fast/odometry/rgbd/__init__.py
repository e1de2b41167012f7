"""Steinbruecker et al.'s dense RGB-D odometry (kintinuous_ref.odometry.rgbd) on both targets:
`ops.py` the maths of one interest point, `cpu.py` the loops, `cuda.py` the kernels, each with
the reference module's public names and signatures; here the host side they share: the
relative pose as the reference computes it and the per-frame problem written once over either
target's systems."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kintinuous_ref.odometry.rgbd import InterestPoints, check_gradient
from kintinuous_ref.odometry.solve import LinearSystem


def relative_pose(pose: np.ndarray, previous_pose: np.ndarray) -> np.ndarray:
    """T_prev^-1 T exactly as `correspond` computes it (np.linalg.inv)."""
    return np.ascontiguousarray(np.linalg.inv(previous_pose) @ pose, dtype=np.float64)


class _RgbdProblem:
    """kintinuous_ref.odometry.rgbd.RgbdProblem (the same arguments and checks) over a target's
    systems, with the interest points and the previous frame's images kept where its kernels
    keep them (device arrays for cuda). A subclass gives its target's `_stage`,
    `_prepare_level` and `_rgbd_system` (its prepare_level and rgbd_system)."""

    def __init__(
        self,
        previous_levels: Sequence,
        current_levels: Sequence,
        previous_pose: np.ndarray,
        min_gradient: Sequence[float] = (12.0, 5.0, 3.0, 1.0),
        max_depth_change: float = 0.07,
        max_depth: float = 6.0,
        gradient: str = "current",
    ) -> None:
        check_gradient(gradient)
        self.previous_levels = previous_levels
        self.current_levels = current_levels
        self.previous_pose = previous_pose
        self.min_gradient = tuple(min_gradient)
        self.max_depth_change = max_depth_change
        self.max_depth = max_depth
        self.gradient = gradient
        self._points: dict[int, InterestPoints] = {}
        self._previous: dict[int, tuple[Any, ...]] = {}

    @staticmethod
    def _stage(array: Any) -> Any:
        raise NotImplementedError

    @staticmethod
    def _prepare_level(*arguments: Any) -> InterestPoints:
        raise NotImplementedError

    @staticmethod
    def _rgbd_system(*arguments: Any) -> LinearSystem:
        raise NotImplementedError

    def points(self, level: int) -> InterestPoints:
        """Algorithm 1 for a level of the current frame, computed on first use (kept where the
        kernels keep it: device arrays for cuda)."""
        if level not in self._points:
            current = self.current_levels[level]
            stage = self._stage
            threshold = self.min_gradient[min(level, len(self.min_gradient) - 1)]
            self._points[level] = self._prepare_level(
                stage(current.depth),
                stage(current.intensity),
                stage(current.intensity_dx),
                stage(current.intensity_dy),
                current.camera,
                threshold,
                self.max_depth,
            )
        return self._points[level]

    def previous(self, level: int) -> tuple[Any, ...]:
        """The previous frame's depth and intensity (and gradients in "warped" mode) of a
        level, staged once."""
        if level not in self._previous:
            previous = self.previous_levels[level]
            stage = self._stage
            warped = self.gradient == "warped"
            self._previous[level] = (
                stage(previous.depth),
                stage(previous.intensity),
                stage(previous.intensity_dx) if warped else None,
                stage(previous.intensity_dy) if warped else None,
            )
        return self._previous[level]

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        depth, intensity, dx, dy = self.previous(level)
        return self._rgbd_system(
            self.points(level),
            pose,
            self.previous_pose,
            depth,
            intensity,
            self.previous_levels[level].camera,
            self.max_depth_change,
            dx,
            dy,
        )

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Correspondences per interest point at a pyramid level (0 when there is none)."""
        total = int(self.points(level).indices.shape[0])
        return self.system(level, pose).count / total if total else 0.0
