"""kintinuous_ref.odometry.combined with the joint system compiled for the host (both backends
solve on the host, paper IV-A.3): the "degeneracy-aware" weightings (the default among them)
as one compiled function, the others (a scaling and a sum of LinearSystems) the reference's.
The per-frame CombinedProblem sums a fast backend's ICP and RGB-D problems (either target);
the CPU's ICP problem computes both systems and their sum itself (icp/cpu_joint.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from kintinuous_ref.odometry import combined as reference
from kintinuous_ref.odometry.combined import (
    DEGENERACY_THRESHOLD,
    about_camera,
    check_combination,
    discount_weak_directions,
    icp_model_noise,
    icp_robust_kernel,
    icp_scale,
    information_spectrum,
    rgbd_scale,
)
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.vocabulary import ROBUST_WEIGHTINGS

from .solve.matrices import column, product, skew, transposed

__all__ = [
    "CombinedProblem",
    "about_camera",
    "check_combination",
    "discount_weak_directions",
    "icp_model_noise",
    "icp_robust_kernel",
    "icp_scale",
    "information_spectrum",
    "joint_system",
    "rgbd_scale",
]

_jit = numba.njit(cache=True)


@_jit
def _discounted_joint(
    icp_a: np.ndarray,
    icp_b: np.ndarray,
    icp_count: int,
    icp_weight: float,
    rgbd_a: np.ndarray,
    rgbd_b: np.ndarray,
    rgbd_weight: float,
    centre: np.ndarray,
    threshold: float,
) -> tuple:
    """(A, b) of joint_system's "degeneracy-aware" branch: the ICP system with its weak
    directions discounted (combined.discount_weak_directions, its information measured about
    `centre`) times `icp_weight`, plus the RGB-D system times `rgbd_weight`."""
    change = np.eye(6)  # combined.about_camera: [[I, 0], [skew(centre), I]]
    arm = skew(centre[0], centre[1], centre[2])
    for i in range(3):
        for j in range(3):
            change[3 + i, j] = arm[i, j]
    centred = product(product(transposed(change), icp_a), change)
    translational = max(centred[3, 3] + centred[4, 4] + centred[5, 5], 1e-300)
    rotational = max(centred[0, 0] + centred[1, 1] + centred[2, 2], 1e-300)
    lever = math.sqrt(rotational / translational)
    # D = diag(1 / lever x3, 1 x3); D C D / count and M D, entry by entry
    diagonal = np.ones(6)
    for i in range(3):
        diagonal[i] = 1 / lever
    information = np.empty((6, 6))
    to_scaled = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            information[i, j] = diagonal[i] * centred[i, j] * diagonal[j] / max(icp_count, 1)
            to_scaled[i, j] = change[i, j] * diagonal[j]
    eigenvalues, eigenvectors = np.linalg.eigh(information)
    kept = np.ones(6)
    weak = False
    if threshold > 0:
        for i in range(6):
            kept[i] = min(eigenvalues[i] / threshold, 1.0)
            weak = weak or kept[i] < 1.0
    a, b = icp_a, icp_b
    if weak:
        weighted = np.empty((6, 6))  # V diag(max(kept, 0))
        for i in range(6):
            for k in range(6):
                weighted[i, k] = eigenvectors[i, k] * max(kept[k], 0.0)
        shrink = product(weighted, transposed(eigenvectors))
        to_scaled_t = transposed(to_scaled)
        a_eta = product(shrink, product(product(to_scaled_t, icp_a), to_scaled))
        b_eta = product(shrink, product(to_scaled_t, column(icp_b)))
        from_scaled = np.linalg.inv(to_scaled)
        from_scaled_t = transposed(from_scaled)
        symmetric = np.empty((6, 6))
        for i in range(6):
            for j in range(6):
                symmetric[i, j] = (a_eta[i, j] + a_eta[j, i]) / 2
        a = product(product(from_scaled_t, symmetric), from_scaled)
        b = product(from_scaled_t, b_eta)[:, 0]
    joint_a = np.empty((6, 6))
    joint_b = np.empty(6)
    for i in range(6):
        for j in range(6):
            joint_a[i, j] = a[i, j] * icp_weight + rgbd_a[i, j] * rgbd_weight
        joint_b[i] = b[i] * icp_weight + rgbd_b[i] * rgbd_weight
    return joint_a, joint_b


def joint_system(
    icp: LinearSystem,
    rgbd: LinearSystem,
    rgbd_weight: float = 1.0,
    weighting: str = "paper",
    original_code_icp_scale: float = 10.0,
    camera_position: np.ndarray | None = None,
    degeneracy_threshold: float = DEGENERACY_THRESHOLD,
) -> LinearSystem:
    """kintinuous_ref.odometry.combined.joint_system: the degeneracy-aware weightings compiled,
    the others (a scaling and a sum of LinearSystems) the reference's own."""
    if weighting != "degeneracy-aware" and weighting not in ROBUST_WEIGHTINGS:
        return reference.joint_system(icp, rgbd, rgbd_weight, weighting, original_code_icp_scale)
    centre = np.zeros(3) if camera_position is None else camera_position
    icp_weight = 1.0 / icp_scale(icp) ** 2
    a, b = _discounted_joint(
        icp.A,
        icp.b,
        icp.count,
        icp_weight,
        rgbd.A,
        rgbd.b,
        float(rgbd_weight),
        np.ascontiguousarray(centre, dtype=np.float64),
        float(degeneracy_threshold),
    )
    cost = icp.cost * icp_weight + rgbd.cost * rgbd_weight
    return LinearSystem(a, b, icp.count + rgbd.count, cost)


class CombinedProblem(reference.CombinedProblem):
    """kintinuous_ref.odometry.combined.CombinedProblem (its arguments, checks, from_config and
    inlier fraction) over a fast backend's ICP and RGB-D problems (either target), summed by
    the compiled joint system."""

    joint_system = staticmethod(joint_system)

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        """The reference's joint system at `pose`; where the ICP problem sums both terms itself
        (the CPU's: one parallel call for both, icp/cpu_joint.py), the same system from it."""
        fused = getattr(self.icp, "joint_system_with", None)
        if fused is not None and type(self).joint_system is joint_system:
            arguments = (self.rgbd_weight, self.weighting, self.degeneracy_threshold)
            system = fused(self.rgbd, level, pose, *arguments)
            if system is not None:
                return system
        return super().system(level, pose)

    def refine_level(
        self, level: int, pose: np.ndarray, steps: int, min_count: int, converged: float
    ) -> tuple[np.ndarray, str] | None:
        """solve.refine's steps at one level over this problem's systems, all in compiled code,
        where the ICP problem runs them so (the CPU's: IcpProblem.refine_joint_level): (pose,
        '') or (pose so far, why a step failed). None elsewhere: the caller steps through
        `system`, as where a subclass computes a `system` or a joint system of its own."""
        fused = getattr(self.icp, "refine_joint_level", None)
        own = type(self).system is not CombinedProblem.system
        if fused is None or own or type(self).joint_system is not joint_system:
            return None
        joint = (self.rgbd_weight, self.weighting, self.degeneracy_threshold)
        return fused(self.rgbd, level, pose, (steps, min_count, converged), joint)
