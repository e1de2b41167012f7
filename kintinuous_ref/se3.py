"""Rigid motions in SE(3): the exponential and logarithm maps, composition, inversion, TUM poses.

Twists follow the paper's order (eq. 4-5): xi = [omega, u], omega the rotation part (axis-angle)
and u the translation part, with

    xi_hat = [[omega_x, u],
              [0 0 0,   0]]        and   T' = exp(xi_hat) T          (eq. 4)

Poses are 4x4 float64 homogeneous matrices mapping camera coordinates to world coordinates.
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.errors import KintinuousError

# Below this rotation angle the closed-form coefficients (which cancel catastrophically near
# zero) are replaced by their Taylor series, whose truncation error there is below 1e-16.
_SMALL_ANGLE = 1e-2


class PoseError(KintinuousError):
    """A matrix or quaternion that is not a valid rigid motion."""


def skew(v: np.ndarray) -> np.ndarray:
    """The 3x3 matrix [v]_x with [v]_x w = v x w."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _so3_coefficients(theta: float) -> tuple[float, float, float]:
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3, with series near zero."""
    t2 = theta * theta
    if theta < _SMALL_ANGLE:
        return (
            1.0 - t2 / 6.0 + t2 * t2 / 120.0,
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
        )
    return (
        np.sin(theta) / theta,
        2.0 * np.sin(theta / 2.0) ** 2 / t2,
        (theta - np.sin(theta)) / (t2 * theta),
    )


def exp(xi: np.ndarray) -> np.ndarray:
    """exp(xi_hat) for xi = [omega, u] (eq. 4-5): Rodrigues' rotation and the left Jacobian V."""
    xi = np.asarray(xi, dtype=np.float64)
    if xi.shape != (6,):
        raise PoseError(f"a twist has 6 entries [omega, u], got shape {xi.shape}")
    omega, u = xi[:3], xi[3:]
    theta = float(np.linalg.norm(omega))
    a, b, c = _so3_coefficients(theta)
    wx = skew(omega)
    wx2 = wx @ wx
    pose = np.eye(4)
    pose[:3, :3] = np.eye(3) + a * wx + b * wx2
    pose[:3, 3] = (np.eye(3) + b * wx + c * wx2) @ u
    return pose


def log(pose: np.ndarray) -> np.ndarray:
    """The twist xi = [omega, u] with exp(xi) = pose; the rotation angle lies in [0, pi]."""
    check_pose(pose)
    rotation, translation = pose[:3, :3], pose[:3, 3]
    omega = rotation_log(rotation)
    theta = float(np.linalg.norm(omega))
    a, b, _ = _so3_coefficients(theta)
    wx = skew(omega)
    # V^-1 = I - wx/2 + (1 - A/(2B)) wx^2 / theta^2, with its series limit 1/12 near zero.
    if theta < _SMALL_ANGLE:
        d = 1.0 / 12.0 + theta**2 / 720.0 + theta**4 / 30240.0
    else:
        d = (1.0 - a / (2.0 * b)) / theta**2
    v_inv = np.eye(3) - 0.5 * wx + d * (wx @ wx)
    return np.concatenate([omega, v_inv @ translation])


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix, stable near 0 and near pi."""
    cos_theta = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    antisym = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    )
    # atan2 keeps full precision near 0, where arccos(cos_theta) loses half the digits.
    theta = float(np.arctan2(np.linalg.norm(antisym) / 2.0, cos_theta))
    if theta < _SMALL_ANGLE:
        return 0.5 * antisym * (1.0 + theta**2 / 6.0 + 7.0 * theta**4 / 360.0)
    if np.pi - theta > 1e-6:
        return theta / (2.0 * np.sin(theta)) * antisym
    # Near pi the antisymmetric part vanishes; read the axis off the symmetric part instead:
    # (R + R^T)/2 = cos(t) I + (1 - cos(t)) a a^T.
    outer = ((rotation + rotation.T) / 2.0 - cos_theta * np.eye(3)) / (1.0 - cos_theta)
    column = int(np.argmax(np.diag(outer)))
    axis = outer[:, column] / np.sqrt(outer[column, column])
    if axis @ antisym < 0:
        axis = -axis
    return theta * axis / np.linalg.norm(axis)


def rotation_angle(rotation: np.ndarray) -> float:
    """The angle (radians) of a rotation matrix."""
    return float(np.arccos(np.clip((np.trace(rotation[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def inverse(pose: np.ndarray) -> np.ndarray:
    """T^-1 = [R^T, -R^T t] without a general matrix inversion."""
    check_pose(pose)
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


def compose(*poses: np.ndarray) -> np.ndarray:
    """T_1 T_2 ... T_n, applied right to left to points."""
    result = np.eye(4)
    for pose in poses:
        result = result @ pose
    return result


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a pose to points of shape (..., 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def check_pose(pose: np.ndarray, tolerance: float = 1e-6) -> None:
    """Raise PoseError unless `pose` is a 4x4 rigid motion (orthonormal R, det +1, row 0001)."""
    pose = np.asarray(pose)
    if pose.shape != (4, 4):
        raise PoseError(f"a pose is a 4x4 matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise PoseError("pose contains NaN or infinity")
    rotation = pose[:3, :3]
    if (
        np.abs(rotation.T @ rotation - np.eye(3)).max() > tolerance
        or abs(np.linalg.det(rotation) - 1.0) > tolerance
        or np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max() > tolerance
    ):
        raise PoseError(
            "pose is not a rigid motion (rotation not orthonormal or last row not 0001)"
        )


def orthonormalize(rotation: np.ndarray) -> np.ndarray:
    """The rotation matrix nearest to `rotation` (SVD), to undo drift after many products."""
    u, _, vt = np.linalg.svd(rotation)
    nearest = u @ vt
    if np.linalg.det(nearest) < 0:
        u[:, -1] *= -1
        nearest = u @ vt
    return nearest


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion given as [qx, qy, qz, qw] (TUM order); normalises q."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise PoseError(f"quaternion {q.tolist()} has no direction")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """[qx, qy, qz, qw] of a rotation matrix with qw >= 0 (Shepperd's method, stable everywhere)."""
    m = rotation
    trace = np.trace(m)
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    largest = int(np.argmax(candidates))
    if largest == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif largest == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif largest == 2:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    return q if q[3] >= 0 else -q


def from_tum(values: np.ndarray) -> np.ndarray:
    """Pose from TUM's `tx ty tz qx qy qz qw` (7 numbers)."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (7,):
        raise PoseError(f"a TUM pose has 7 numbers (tx ty tz qx qy qz qw), got {values.size}")
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_rotation(values[3:])
    pose[:3, 3] = values[:3]
    return pose


def to_tum(pose: np.ndarray) -> np.ndarray:
    """TUM's `tx ty tz qx qy qz qw` of a pose."""
    check_pose(pose, tolerance=1e-4)
    return np.concatenate([pose[:3, 3], rotation_to_quaternion(pose[:3, :3])])
