"""ICP + RGB-D: one joint Gauss-Newton system per iteration (paper V-B, eq. 11-13).

Both costs are linearised in the same twist xi (the left perturbation of the current
camera-to-world pose, world frame), so the joint cost

    E = E_icp + w E_rgbd,  w = 0.1                                          (eq. 11)

has the normal equations

    (J_icp^T J_icp + w J_rgbd^T J_rgbd) xi = -(J_icp^T r_icp + w J_rgbd^T r_rgbd),   (eq. 12-13)

the stacked system [J_icp; v J_rgbd] with v = sqrt(w): simply the weighted sum of the two 6x6
systems. The RGB-D rows are the robustly weighted, dimensionless ones of rgbd.py; ICP's
residuals are metres. Three pyramid levels, 10 / 5 / 4 iterations from finest to coarsest.

`weighting="original-code"` reproduces the authors' public code instead: A = A_rgbd + s^2 A_icp,
b = b_rgbd + s b_icp with s = 10 (config.combined.original_code_icp_scale). A and b are scaled
inconsistently there, so its step is not the minimiser of any weighted sum of the two costs; it is
offered only for comparison.
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.icp import IcpProblem
from kintinuous_ref.odometry.rgbd import RgbdProblem
from kintinuous_ref.odometry.solve import LinearSystem

WEIGHTINGS = ("paper", "original-code")


def joint_system(
    icp: LinearSystem,
    rgbd: LinearSystem,
    rgbd_weight: float = 0.1,
    weighting: str = "paper",
    original_code_icp_scale: float = 10.0,
) -> LinearSystem:
    """The joint normal equations of eq. 12-13 (or the original code's combination)."""
    if weighting == "paper":
        return icp + rgbd.scaled(rgbd_weight)
    if weighting == "original-code":
        s = original_code_icp_scale
        return rgbd + icp.scaled(s * s, s)
    raise ConfigError(f"combined.weighting must be one of {WEIGHTINGS}, got {weighting!r}")


class CombinedProblem:
    """ICP against the model and RGB-D against the previous frame, summed per iteration."""

    def __init__(
        self,
        icp: IcpProblem,
        rgbd: RgbdProblem,
        rgbd_weight: float = 0.1,
        weighting: str = "paper",
        original_code_icp_scale: float = 10.0,
    ) -> None:
        if weighting not in WEIGHTINGS:
            raise ConfigError(f"combined.weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        if not rgbd_weight >= 0:
            raise ConfigError(f"combined.rgbd_weight must be >= 0, got {rgbd_weight}")
        self.icp = icp
        self.rgbd = rgbd
        self.rgbd_weight = rgbd_weight
        self.weighting = weighting
        self.original_code_icp_scale = original_code_icp_scale

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return joint_system(
            self.icp.system(level, pose),
            self.rgbd.system(level, pose),
            self.rgbd_weight,
            self.weighting,
            self.original_code_icp_scale,
        )

    def inlier_fraction(self, pose: np.ndarray) -> float:
        """The ICP fraction: the joint estimate stands on the model's geometry first."""
        return self.icp.inlier_fraction(pose)
