"""Host-side code shared by the cpu and cuda odometry kernels: the per-call constants (relative
poses computed exactly as the reference computes them), the unpacking of the accumulated partial
sums into a LinearSystem, input checks, and the per-frame problems and trackers written once over
"a module with the kernels" (odometry/cpu.py or odometry/cuda.py).

The Gauss-Newton step (solve: 6x6 Cholesky in float64, apply_increment, the joint system) runs
on the host in both backends, as in the paper (section IV-A.3), compiled in odometry/solve.py.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import ModuleType
from typing import Any

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics, axial_noise
from kintinuous_ref.config import Config, IcpConfig
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.odometry import DenseTracker as RefDenseTracker
from kintinuous_ref.odometry import FovisTracker as RefFovisTracker
from kintinuous_ref.odometry import repeated_streams as ref_repeated_streams
from kintinuous_ref.odometry.fovis import FovisResult
from kintinuous_ref.odometry.icp import REFERENCE_DEPTH, ROBUST_KERNELS, robust_threshold
from kintinuous_ref.odometry.rgbd import InterestPoints
from kintinuous_ref.odometry.rgbd import RgbdProblem as RefRgbdProblem
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

from .ops import NV, SLOT_B, SLOT_COST, SLOT_COUNT, SLOT_EXTRA

# Upper-triangle (i, j) pairs of A in the order of the accumulated vector (ops.add_row).
_UPPER = [(i, j) for i in range(6) for j in range(i, 6)]
_UPPER_ROWS, _UPPER_COLS = (np.array(index) for index in zip(*_UPPER, strict=True))


def unpack(total: np.ndarray) -> tuple[LinearSystem, int]:
    """(LinearSystem, the spare slot as an int) from the NV summed float64 values."""
    A = np.empty((6, 6))
    A[_UPPER_ROWS, _UPPER_COLS] = A[_UPPER_COLS, _UPPER_ROWS] = total[:SLOT_B]
    count = int(round(total[SLOT_COUNT]))
    system = LinearSystem(A, total[SLOT_B : SLOT_B + 6].copy(), count, float(total[SLOT_COST]))
    return system, int(round(total[SLOT_EXTRA]))


def sum_partials(partials: np.ndarray) -> tuple[LinearSystem, int]:
    """Sum per-chunk / per-block partials (rows, NV) in float64 on the host and unpack them."""
    return unpack(np.asarray(partials, dtype=np.float64).reshape(-1, NV).sum(axis=0))


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


def relative_pose(pose: np.ndarray, previous_pose: np.ndarray) -> np.ndarray:
    """T_prev^-1 T exactly as `correspond` computes it (np.linalg.inv)."""
    return np.ascontiguousarray(np.linalg.inv(previous_pose) @ pose, dtype=np.float64)


def check_map(name: str, array: Any, camera: Intrinsics) -> None:
    """A (h, w, 3) map of the camera's size, else a one-line DatasetError."""
    expected = (camera.height, camera.width, 3)
    if tuple(array.shape) != expected:
        raise DatasetError(f"{name} is {tuple(array.shape)}, expected {expected} from the camera")


def check_image(name: str, array: Any, shape: tuple[int, ...]) -> None:
    if tuple(array.shape) != tuple(shape):
        raise DatasetError(f"{name} is {tuple(array.shape)}, expected {tuple(shape)}")


def chunks_for(count: int, chunks: int) -> int:
    """How many fixed chunks a loop over `count` items is split into (>= 1)."""
    return max(1, min(chunks, count))


# ----------------------------------------------------------------------------------------------
# Per-frame problems (the reference's IcpProblem / RgbdProblem with the kernels underneath)


class IcpProblemBase:
    """ICP for one frame: the current pyramid against the model pyramid, any pose estimate."""

    kernels: ModuleType  # set by the backend module's subclass

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
        self._points: dict[int, Any] = {}  # per level, for kernels that compact the valid points
        self._model_inverse: np.ndarray | None = None

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
            stage = self.kernels.stage
            self._maps[level] = (
                stage(current.vertices),
                stage(current.normals),
                stage(model_vertices),
                stage(model_normals),
            )
        return self._maps[level]

    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        return self.kernels.icp_system_and_valid(
            *self.maps(level),
            pose,
            self.model_pose,
            self.current_levels[level].camera,
            self.distance_threshold,
            self.angle_threshold_deg,
            self.robust_kernel,
            self.robust_threshold,
            self.model_noise,
        )

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return self.system_and_valid(level, pose)[0]

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Matched pairs per valid current vertex at a pyramid level (0 when none is valid)."""
        system, valid = self.system_and_valid(level, pose)
        return system.count / valid if valid else 0.0


class RgbdProblemBase(RefRgbdProblem):
    """The reference's RgbdProblem (same arguments and checks), with the interest points and the
    previous frame's images kept where the kernels keep them (device arrays for cuda)."""

    kernels: ModuleType

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._previous: dict[int, tuple[Any, ...]] = {}

    def points(self, level: int) -> InterestPoints:
        """Algorithm 1 for a level of the current frame, computed on first use (kept where the
        kernels keep it: device arrays for cuda)."""
        if level not in self._points:
            current = self.current_levels[level]
            stage = self.kernels.stage
            threshold = self.min_gradient[min(level, len(self.min_gradient) - 1)]
            self._points[level] = self.kernels.prepare_level(
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
        if level not in self._previous:
            previous = self.previous_levels[level]
            stage = self.kernels.stage
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
        return self.kernels.rgbd_system(
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


# ----------------------------------------------------------------------------------------------
# Trackers: the reference's, with the fast problems underneath


class FastDenseTracker(RefDenseTracker):
    """kintinuous_ref.odometry.DenseTracker (same coarse-to-fine refine, failure checks and
    recovery) whose ICP / RGB-D systems come from a kernels module (cpu or cuda)."""

    def __init__(
        self, method: str, config: Config, camera: Intrinsics, kernels: ModuleType
    ) -> None:
        super().__init__(method, config, camera, systems=kernels)

    def repeated_streams(
        self, previous: PreprocessedFrame | None, current: PreprocessedFrame
    ) -> tuple[bool, bool]:
        """The reference's stale-stream test, run where the kernels keep the frames (the cuda
        kernels compare device images on the device: three flags cross, not two images)."""
        compare = getattr(self.systems, "repeated_streams", ref_repeated_streams)
        return compare(previous, current)


class FastFovisTracker(RefFovisTracker):
    """FOVIS (the reference's, on the CPU as in the paper) switching with a fast dense half."""

    def __init__(
        self, method: str, config: Config, camera: Intrinsics, kernels: ModuleType
    ) -> None:
        super().__init__(method, config, camera)
        other = method.partition("/")[2]
        self.dense = FastDenseTracker(other, config, camera, kernels) if other else None
        self._on_host: list[tuple[PreprocessedFrame, PreprocessedFrame]] = []

    def sparse_motion(self, previous: PreprocessedFrame, current: PreprocessedFrame) -> FovisResult:
        """FOVIS on host images (it runs on the CPU, as in the paper): each frame's images are
        downloaded once, when it is the current frame, and reused when it is the previous."""
        return super().sparse_motion(self._host_images(previous), self._host_images(current))

    def _host_images(self, frame: PreprocessedFrame) -> PreprocessedFrame:
        for known, host in self._on_host:
            if known is frame:
                return host
        host = fovis_images(frame)
        self._on_host = [*self._on_host[-1:], (frame, host)]  # this frame and the one before
        return host


def _download(array: Any) -> Any:
    """A NumPy copy of a device array; host arrays (and None) as they are."""
    return array if array is None or isinstance(array, np.ndarray) else array.copy_to_host()


def fovis_images(frame: PreprocessedFrame) -> PreprocessedFrame:
    """What FOVIS reads of a frame (every level's depth and intensity) as NumPy arrays: the frame
    itself when it is on the host, else a copy without the maps, gradients and colour."""
    if all(
        isinstance(image, np.ndarray)
        for level in frame.levels
        for image in (level.depth, level.intensity)
    ):
        return frame
    levels = [
        PyramidLevel(
            level.camera, _download(level.depth), None, None, _download(level.intensity), None, None
        )
        for level in frame.levels
    ]
    return PreprocessedFrame(colour=None, depth=levels[0].depth, levels=levels, colour_mask=None)


def make_tracker_with(kernels: ModuleType, method: str, config: Config, camera: Intrinsics):  # noqa: ANN201
    """kintinuous_ref.odometry.make_tracker with the dense systems of `kernels`."""
    from kintinuous_ref.odometry import DENSE_METHODS, METHODS

    if method in DENSE_METHODS:
        return FastDenseTracker(method, config, camera, kernels)
    if method in METHODS:
        return FastFovisTracker(method, config, camera, kernels)
    raise ConfigError(f"unknown odometry method {method!r}; choose from {', '.join(METHODS)}")
