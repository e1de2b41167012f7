"""ICP + RGB-D: one joint Gauss-Newton system per iteration (paper V-B, eq. 11-13).

Both costs are linearised in the same twist xi (the left perturbation of the current
camera-to-world pose, world frame), so the joint cost

    E = E_icp + w E_rgbd                                                    (eq. 11)

has the normal equations

    (J_icp^T J_icp + w J_rgbd^T J_rgbd) xi = -(J_icp^T r_icp + w J_rgbd^T r_rgbd),   (eq. 12-13)

the stacked system [J_icp; v J_rgbd] with v = sqrt(w): simply the weighted sum of the two 6x6
systems. (The paper prints eq. 13 with v, not w, on the right-hand side, which is not the
normal equations of its stack: with w = 0.1 its steps do not settle; lesson 6 runs both.)
Three pyramid levels, 10 / 5 / 4 iterations from finest to coarsest.

Units and the weight. The paper sets w = 0.1 "to reflect the difference in metrics" without
saying in which units the two costs are added. The RGB-D rows of rgbd.py are robustly weighted
by 1 / (sigma' + |r|) and so dimensionless; ICP's residuals are metres. The authors' code
answers the question: its combination ("original-code", below) converges to E_icp + 0.1 E_rgbd
with E_icp in square metres, the literal sum ("paper-metres" with rgbd_weight = 0.1). "paper",
despite its name, is not the paper's sum but this package's normalisation: it makes E_icp
dimensionless too, dividing it by its own mean squared residual sigma_icp^2 (recomputed every
iteration, as sigma' is), which the paper never does:

    E = E_icp / sigma_icp^2 + w E_rgbd,   w = 1   (config.combined.rgbd_weight),

each term in units of its own noise: every pair counts by how well it fits. That balance fails
where ICP's information is degenerate but biased: along a corridor of flat walls the stray
normals of the voxelised model give ICP a weak constraint that still outweighs the texture, and
over one plane ICP observes only three of six directions. "degeneracy-aware" (after Zhang,
Kaess and Singh, ICRA 2016) is "paper" with ICP's say cut along the directions few of its pairs
observe. Its information matrix is taken about the camera (a twist that rotates about the
camera centre, so that rotations and translations separate), rotations scaled by the RMS lever
arm rho of the pairs, and divided by the pair count: a dimensionless 6x6 whose eigenvalues say
what share of the pairs constrains each direction (the translational ones sum to 1). Along an
eigen-direction of share s below `degeneracy_threshold` the ICP term (A and b alike) keeps the
fraction s / threshold of its information: the walking direction in a corridor (s ~ 1e-4)
keeps under 1 %, and RGB-D decides it; a weakly but truly observed direction (s ~ 0.007 on a
desk) keeps a third. ICP's own minimiser does not move, only its weight against RGB-D, so in
the dark, where RGB-D holds nothing, ICP still decides every direction. A gate that removes a
direction whole where RGB-D knows more about it flips when RGB-D's information dips for a few
frames, and ICP's biased sliver then holds the camera still (docs/odometry.md measures both).
ATE RMSE of the whole pipeline, 300 frames (docs/odometry.md has every weighting; "paper" and
"original-code" with least-squares ICP rows):

    320x240              corridor   floor      desk     dark
    icp alone            499 mm     625 mm     2.0 mm   3.9 mm
    rgbd alone           7.4 mm     23.4 mm    13.8 mm  353 mm (101 frames lost)
    "paper"              49.0 mm    501 mm     1.9 mm   2.9 mm
    "original-code"      5.2 mm     12.3 mm    12.5 mm  6.3 mm
    "huber" (default)    9.2 mm     4.4 mm     2.0 mm   3.8 mm

    640x480              corridor   floor      desk     dark
    icp alone            616 mm     523 mm     0.8 mm   0.7 mm
    rgbd alone           2.1 mm     0.8 mm     5.5 mm   352 mm (101 frames lost)
    "huber" (default)    2.9 mm     0.7 mm     0.8 mm   0.7 mm

The default, "huber", is "degeneracy-aware" on ICP rows weighted by Huber's kernel and by the
noise at each pair's depth (icp.py): on redkitchen at 640x480 it reaches 22.1 mm where
least-squares rows reach 26.9 mm. RGB-D alone still does better on the corridors (1.39x at
640x480, 1.24x at 320x240): ICP's remaining bias there sits in directions 3-5 % of its pairs
observe.

The other weightings:

- "information": both terms in units of their own noise, E_icp / sigma_icp^2 + w E_rgbd /
  sigma_rgbd^2, sigma_rgbd^2 the mean squared *weighted* photometric residual (inverse-variance
  weighting of each term as a whole).
- "paper-metres": the literal sum, E_icp in square metres: one photometric pair then outweighs
  about a thousand geometric ones, i.e. frame-to-frame RGB-D.
- "original-code": the authors' public code, A = A_rgbd + s^2 A_icp, b = b_rgbd + s b_icp with
  s = 10 (config.combined.original_code_icp_scale). A and b are scaled differently, so this is
  not the normal equations of a weighted sum, but its step, -(1/s) (A_icp + A_rgbd / s^2)^-1
  (b_icp + b_rgbd / s), is zero exactly where b_icp + b_rgbd / s = 0: the stationary point of
  E_icp + (1/s) E_rgbd with ICP in metres, i.e. of eq. 11 with w = 0.1, "paper-metres" with
  rgbd_weight = 0.1. Run to convergence the two reach the same poses; s only changes the step
  (a tenth of the Gauss-Newton step where ICP's information dominates, the same step where
  RGB-D's does), and so the path, the speed of convergence and what a fixed 10 / 5 / 4
  iterations reach (notebooks/06_combined_cost.py measures both).
- "elasticfusion": ElasticFusion's combination, which is the same formula with its own ICP
  weight of 10: the same system as "original-code".
- "huber", "tukey": "degeneracy-aware" with the ICP rows robustly weighted by that M-estimator
  (icp.py: IRLS weights of the point-to-plane residuals, scale config.icp.robust_noise) and,
  with config.icp.depth_noise, by the noise at each pair's depth. A
  robust kernel changes each pair's row, not the 6x6 combination, so it composes with any
  combination; these two names put it on the default one, where the question is whether cutting
  the worst-fitting pairs (the model's stray normals at depth edges) removes the bias ICP keeps
  in the directions it does observe. `icp` alone takes its kernel from config.icp.robust_kernel;
  under the other weightings the ICP rows of `icp+rgbd` are plain least squares.
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import CombinedConfig, Config
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.icp import IcpProblem, voxel_noise
from kintinuous_ref.odometry.rgbd import RgbdProblem
from kintinuous_ref.odometry.solve import LinearSystem

# The weightings (WEIGHTINGS) and those "degeneracy-aware" with a robust kernel on the ICP rows
# (ROBUST_WEIGHTINGS, icp.py) are listed in kintinuous_ref.vocabulary.
from kintinuous_ref.vocabulary import ROBUST_WEIGHTINGS, WEIGHTINGS

# Floor of the ICP residual scale (metres): far below any depth sensor's noise, it only keeps a
# perfect, noise-free alignment from dividing by zero.
MIN_ICP_SCALE = 1e-4
# "degeneracy-aware": an eigen-direction of ICP's per-pair information (module docstring) below
# this share is one that ICP does not observe.
DEGENERACY_THRESHOLD = CombinedConfig.degeneracy_threshold


def icp_robust_kernel(method: str, config: Config) -> str:
    """The M-estimator of the ICP rows for a tracker `method`. `icp` alone reads
    config.icp.robust_kernel. `icp+rgbd` reads combined.weighting only: "huber" / "tukey" name
    their kernel, every other weighting is least squares, so that each named weighting is one
    fixed joint system whatever the ICP settings (and the tables measured for it stay valid)."""
    if method == "icp+rgbd":
        weighting = config.combined.weighting
        return weighting if weighting in ROBUST_WEIGHTINGS else "none"
    return config.icp.robust_kernel


def icp_model_noise(method: str, config: Config) -> float | None:
    """The model's noise for the ICP rows' depth noise weights (icp.py), None where the pairs
    weigh the same: the voxelisation's error, voxel / sqrt(12), when config.icp.depth_noise is
    on, for `icp` and for the robust weightings of `icp+rgbd` (the others keep the joint system
    their name fixes)."""
    if not config.icp.depth_noise:
        return None
    if method == "icp+rgbd" and config.combined.weighting not in ROBUST_WEIGHTINGS:
        return None
    return voxel_noise(config.volume.voxel_size)


def icp_scale(icp: LinearSystem) -> float:
    """sigma_icp: the RMS point-to-plane residual (metres), at least MIN_ICP_SCALE."""
    if icp.count == 0:
        return 1.0
    return max(float(np.sqrt(icp.cost / icp.count)), MIN_ICP_SCALE)


def rgbd_scale(rgbd: LinearSystem) -> float:
    """sigma_rgbd: the RMS weighted photometric residual (dimensionless), at least 1e-6."""
    if rgbd.count == 0:
        return 1.0
    return max(float(np.sqrt(rgbd.cost / rgbd.count)), 1e-6)


def about_camera(camera_position: np.ndarray) -> np.ndarray:
    """M with xi = M xi_c: xi_c = [omega, t] rotates by omega about the camera centre c and then
    translates by t, the world-frame twist xi = [omega, u] about the world origin has
    u = t + c x omega (both move a point p by omega x p + u to first order)."""
    change = np.eye(6)
    change[3:, :3] = se3.skew(np.asarray(camera_position, dtype=np.float64))
    return change


def information_spectrum(
    icp: LinearSystem, camera_position: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ICP's dimensionless per-pair information about the camera: (eigenvalues ascending,
    eigenvectors as columns, M D) with eigen-decomposition of D M^T A M D / count, where M is
    `about_camera`, D = diag(1 / rho x3, 1 x3) and rho^2 = trace of the rotational block / trace
    of the translational one (the mean squared lever arm of the pairs). M D maps the scaled
    coordinates eta to the world twist: xi = M D eta."""
    change = about_camera(camera_position)
    centred = change.T @ icp.A @ change
    translational = max(float(np.trace(centred[3:, 3:])), 1e-300)
    lever = np.sqrt(max(float(np.trace(centred[:3, :3])), 1e-300) / translational)
    scale = np.diag([1 / lever] * 3 + [1.0] * 3)
    eigenvalues, eigenvectors = np.linalg.eigh(scale @ centred @ scale / max(icp.count, 1))
    return eigenvalues, eigenvectors, change @ scale


def discount_weak_directions(
    icp: LinearSystem, camera_position: np.ndarray, threshold: float = DEGENERACY_THRESHOLD
) -> LinearSystem:
    """The ICP system with its information along each eigen-direction of `information_spectrum`
    multiplied by min(1, share / threshold): a direction observed by a share s < threshold of
    the pairs keeps s / threshold of its say; the directions above it keep all of it. A and b
    shrink together along each eigen-direction, so ICP alone still has the same minimiser: only
    its weight against the other term changes, direction by direction."""
    # In the scaled coordinates eta (xi = M D eta): A_eta = D M^T A M D, b_eta = D M^T b, and
    # A_eta shares its eigenvectors V with the spectrum, so V diag(f) V^T commutes with it.
    eigenvalues, eigenvectors, to_scaled = information_spectrum(icp, camera_position)
    kept = np.minimum(eigenvalues / threshold, 1.0) if threshold > 0 else np.ones(6)
    if kept.min() >= 1.0:
        return icp
    shrink = eigenvectors @ np.diag(np.maximum(kept, 0.0)) @ eigenvectors.T
    a_eta = shrink @ (to_scaled.T @ icp.A @ to_scaled)
    b_eta = shrink @ (to_scaled.T @ icp.b)
    from_scaled = np.linalg.inv(to_scaled)
    a_world = from_scaled.T @ ((a_eta + a_eta.T) / 2) @ from_scaled
    return LinearSystem(a_world, from_scaled.T @ b_eta, icp.count, icp.cost)


def joint_system(
    icp: LinearSystem,
    rgbd: LinearSystem,
    rgbd_weight: float = 1.0,
    weighting: str = "paper",
    original_code_icp_scale: float = 10.0,
    camera_position: np.ndarray | None = None,
    degeneracy_threshold: float = DEGENERACY_THRESHOLD,
) -> LinearSystem:
    """The joint normal equations of eq. 12-13 (or the original code's combination).

    "paper": E = E_icp / sigma_icp^2 + w E_rgbd, both terms dimensionless (module docstring).
    "paper-metres": E = E_icp + w E_rgbd with E_icp in square metres, literally.
    "information": E = E_icp / sigma_icp^2 + w E_rgbd / sigma_rgbd^2.
    "degeneracy-aware": "paper" with ICP's unobserved directions removed; `camera_position`
    (world frame, the current estimate's) is the centre its information is measured about.
    "huber", "tukey": "degeneracy-aware" (the kernel is already in `icp`'s rows).
    "original-code", "elasticfusion": A = A_rgbd + s^2 A_icp, b = b_rgbd + s b_icp.
    """
    if weighting == "paper":
        return icp.scaled(1.0 / icp_scale(icp) ** 2) + rgbd.scaled(rgbd_weight)
    if weighting == "paper-metres":
        return icp + rgbd.scaled(rgbd_weight)
    if weighting == "information":
        return icp.scaled(1.0 / icp_scale(icp) ** 2) + rgbd.scaled(
            rgbd_weight / rgbd_scale(rgbd) ** 2
        )
    if weighting == "degeneracy-aware" or weighting in ROBUST_WEIGHTINGS:
        centre = np.zeros(3) if camera_position is None else camera_position
        discounted = discount_weak_directions(icp, centre, degeneracy_threshold)
        return discounted.scaled(1.0 / icp_scale(icp) ** 2) + rgbd.scaled(rgbd_weight)
    if weighting in ("original-code", "elasticfusion"):
        s = original_code_icp_scale
        return rgbd + icp.scaled(s * s, s)
    raise ConfigError(f"combined.weighting must be one of {WEIGHTINGS}, got {weighting!r}")


def check_combination(rgbd_weight: float, weighting: str, degeneracy_threshold: float) -> None:
    """A one-line ConfigError unless the joint system's settings (CombinedProblem's) are valid."""
    if weighting not in WEIGHTINGS:
        raise ConfigError(f"combined.weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    if not rgbd_weight >= 0:
        raise ConfigError(f"combined.rgbd_weight must be >= 0, got {rgbd_weight}")
    if not 0 <= degeneracy_threshold < 1:
        raise ConfigError(
            f"combined.degeneracy_threshold must be in [0, 1), got {degeneracy_threshold}"
        )


class CombinedProblem:
    """ICP against the model and RGB-D against the previous frame, summed per iteration."""

    # The function that sums the two systems (eq. 11-13): the seam of a fast backend, whose
    # CombinedProblem is this class over its compiled joint_system.
    joint_system = staticmethod(joint_system)

    def __init__(
        self,
        icp: IcpProblem,
        rgbd: RgbdProblem,
        rgbd_weight: float = 1.0,
        weighting: str = "paper",
        original_code_icp_scale: float = 10.0,
        degeneracy_threshold: float = DEGENERACY_THRESHOLD,
    ) -> None:
        check_combination(rgbd_weight, weighting, degeneracy_threshold)
        self.icp = icp
        self.rgbd = rgbd
        self.rgbd_weight = rgbd_weight
        self.weighting = weighting
        self.original_code_icp_scale = original_code_icp_scale
        self.degeneracy_threshold = degeneracy_threshold

    @classmethod
    def from_config(
        cls, icp: IcpProblem, rgbd: RgbdProblem, config: CombinedConfig
    ) -> CombinedProblem:
        """The problem with the weighting of `config.combined` (config.CombinedConfig)."""
        return cls(
            icp,
            rgbd,
            config.rgbd_weight,
            config.weighting,
            config.original_code_icp_scale,
            config.degeneracy_threshold,
        )

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return self.joint_system(
            self.icp.system(level, pose),
            self.rgbd.system(level, pose),
            self.rgbd_weight,
            self.weighting,
            self.original_code_icp_scale,
            pose[:3, 3],
            self.degeneracy_threshold,
        )

    def inlier_fraction(
        self, pose: np.ndarray, level: int = 0, enough: float | None = None
    ) -> float:
        """The larger of the two terms' fractions: the joint estimate stands when either term
        matched enough of its own points. ICP's alone fails wherever most of the view lies
        beyond the volume (its far vertices can never match the model; the `loop` lap at
        640x480), although RGB-D still tracks there; a frame of another scene fails both.

        `enough`: the fraction the caller compares against. Where RGB-D's reaches it, so does
        the larger one, and RGB-D's is returned without counting ICP's pairs (a pass over
        every valid point at full resolution); below it, the larger of the two as without."""
        rgbd = self.rgbd.inlier_fraction(pose, level)
        if enough is not None and rgbd >= enough:
            return rgbd
        return max(self.icp.inlier_fraction(pose, level), rgbd)
