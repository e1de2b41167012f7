"""A pose graph over keyframes, solved by sparse nonlinear least squares with switchable loops.

Nodes are camera-to-world poses T_i. An edge (i, j) carries a measurement Z_ij of the pose of j
in i's frame (odometry between consecutive keyframes, or a verified loop). Its error is the
motion that remains between the measurement and the estimate,

    E_ij = Z_ij^-1 T_i^-1 T_j,      r_ij = W_ij [log_SO3(R(E_ij)), t(E_ij)],

zero when the graph agrees with the edge, with W_ij = diag(1 / sigma_r, 1 / sigma_t) or, for an
edge given a full covariance C_ij = L L^T, W_ij = L^-1 (so that W^T W = C^-1). Each node moves
by a left perturbation [omega, u] (the project's twist order): R' = exp(omega) R,
t' = exp(omega) t + u, so the parametrisation has no singularity however the cameras are turned;
node 0 stays fixed (the gauge). With A = R_z^T R_i^T, the Jacobian blocks of an edge (before
W_ij) are, for node j, d r_rot / d omega = A, d r_t / d omega = -A [t_j]x, d r_t / d u = A,
and their negatives (with +A [t_j]x) for node i, the rotation log taken as linear (exact at zero
error, where the solver ends). Levenberg-Marquardt relinearises at every step and solves the
sparse normal equations (6 unknowns per node) with SuperLU. The Jacobian is written out because
finite differences over every node's unknowns (scipy's least_squares) take minutes on a graph of
50 nodes (docs/benchmarks.md, "Choices in the reference").

Robust loops: one false loop must not fold the map. Every loop edge gets a switch s in [0, 1]
(Suenderhauf and Protzel, IROS 2012) that scales its residual, s r_ij, with a prior
(1 - s)^2 / sigma_switch^2. A loop that agrees with the rest of the graph keeps s near 1; one that
contradicts it costs less switched off than on. The switches are not extra unknowns of the
solver, which would crawl towards their bound s = 0 (thousands of evaluations for a 24-node
graph): Agarwal et al. ("Dynamic Covariance Scaling", ICRA 2013) derive each in closed form from
its loop's current squared residual chi^2, s = min(1, 2 phi / (phi + chi^2)) with
phi = 1 / sigma_switch^2, so it is recomputed at every step of the solver. Switches
computed at the odometry's poses turn off a true loop that is many sigmas off there before it
can pull, and switches computed after trusting every loop turn off the true loops too when a
false one has folded the graph. So each new loop is first tested for consistency, trusted
together with the loops kept so far (`optimise`); the kept ones are then trusted and switched.
Odometry edges have no switch: they are the backbone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix, diags
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from kintinuous_ref.errors import ConfigError


@dataclass
class Edge:
    first: int
    second: int
    measurement: np.ndarray  # (4, 4): the pose of `second` in the frame of `first`
    sigma_translation: float  # metres
    sigma_rotation: float  # radians
    loop: bool = False  # loop edges are switchable
    consistent: bool | None = None  # a loop's consistency test (None: not tested yet)
    covariance: np.ndarray | None = None  # (6, 6) [rotation, translation]; None: the sigmas

    def whitening(self) -> np.ndarray:
        """W with W^T W the edge's information, so that W [rotation, translation] is its
        residual in standard deviations: diagonal from the sigmas, or L^-1 for a covariance
        L L^T (Cholesky), which also weighs and couples the directions."""
        if self.covariance is None:
            return np.diag([1 / self.sigma_rotation] * 3 + [1 / self.sigma_translation] * 3)
        return np.linalg.inv(np.linalg.cholesky(self.covariance))


@dataclass
class PoseGraph:
    poses: list[np.ndarray] = field(default_factory=list)  # camera-to-world, one per node
    edges: list[Edge] = field(default_factory=list)

    def add_node(self, pose: np.ndarray) -> int:
        self.poses.append(np.asarray(pose, dtype=np.float64).copy())
        return len(self.poses) - 1

    def add_edge(
        self,
        first: int,
        second: int,
        measurement: np.ndarray,
        sigma_translation: float,
        sigma_rotation: float,
        loop: bool = False,
        covariance: np.ndarray | None = None,
    ) -> Edge:
        """An edge whose error has the standard deviations `sigma_translation` (metres) and
        `sigma_rotation` (radians), or the full `covariance` where given (6 x 6, rotation
        first: a tracker's uncertainty differs by direction)."""
        if not (0 <= first < len(self.poses) and 0 <= second < len(self.poses)) or first == second:
            raise ConfigError(f"pose graph edge {first}-{second} needs two different nodes")
        if covariance is not None:
            covariance = np.asarray(covariance, dtype=np.float64)
            if (
                covariance.shape != (6, 6)
                or not np.all(np.isfinite(covariance))
                or np.any(np.linalg.eigvalsh(covariance) <= 0)
            ):
                raise ConfigError(
                    "a pose graph edge's covariance must be 6 x 6 and positive definite"
                )
        edge = Edge(first, second, np.asarray(measurement, dtype=np.float64), sigma_translation,
                    sigma_rotation, loop, covariance=covariance)  # fmt: skip
        self.edges.append(edge)
        return edge

    @property
    def loops(self) -> list[Edge]:
        return [edge for edge in self.edges if edge.loop]


@dataclass
class PoseGraphSolution:
    poses: np.ndarray  # (N, 4, 4) optimised camera-to-world poses
    switches: np.ndarray  # (L,) one per loop edge, in the order of PoseGraph.loops
    cost: float  # half the sum of squared residuals at the solution
    evaluations: int  # residual evaluations the solver used


def relative_pose(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The pose of `second` in the frame of `first`: first^-1 second."""
    inverse = np.eye(4)
    inverse[:3, :3] = first[:3, :3].T
    inverse[:3, 3] = -first[:3, :3].T @ first[:3, 3]
    return inverse @ second


def _edge_arrays(graph: PoseGraph) -> dict[str, np.ndarray]:
    edges = graph.edges
    measurements = np.array([e.measurement for e in edges])
    return {
        "first": np.array([e.first for e in edges], dtype=np.int64),
        "second": np.array([e.second for e in edges], dtype=np.int64),
        "rotation_t": measurements[:, :3, :3].transpose(0, 2, 1),  # R_z^T
        "translation": measurements[:, :3, 3],
        "whitening": np.array([e.whitening() for e in edges]),
        "loop": np.array([e.loop for e in edges]),
    }


def _errors(poses: np.ndarray, edges: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(whitened residuals (E, 6), R_z^T R_i^T (E, 3, 3), t_j (E, 3)) of every edge."""
    first, second = poses[edges["first"]], poses[edges["second"]]
    a = np.einsum("eab,ecb->eac", edges["rotation_t"], first[:, :3, :3])  # R_z^T R_i^T
    error_rotation = np.einsum("eab,ebc->eac", a, second[:, :3, :3])
    rotation = Rotation.from_matrix(error_rotation).as_rotvec()
    translation = np.einsum("eab,eb->ea", a, second[:, :3, 3] - first[:, :3, 3])
    translation -= np.einsum("eab,eb->ea", edges["rotation_t"], edges["translation"])
    residual = np.einsum("eab,eb->ea", edges["whitening"], np.hstack([rotation, translation]))
    return residual, a, second[:, :3, 3]


def _jacobian(count: int, edges: dict, a: np.ndarray, tj: np.ndarray, weight: np.ndarray):
    """Sparse Jacobian (6E, 6(N-1)) of the weighted residuals with respect to the left
    perturbations [omega, u] of nodes 1.. at the current poses (module docstring), with the
    rotation residual's log taken as linear (exact at zero error, where Gauss-Newton ends)."""
    skew = np.zeros((len(tj), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -tj[:, 2], tj[:, 1], -tj[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = tj[:, 2], -tj[:, 1], tj[:, 0]
    a_skew = np.einsum("eab,ebc->eac", a, skew)
    zero = np.zeros_like(a)
    # rows: [rotation; translation], columns: [omega, u] of node j, then of node i
    block_j = np.block([[a, zero], [-a_skew, a]])
    block_i = np.block([[-a, zero], [a_skew, -a]])
    whitening = edges["whitening"] * weight[:, None, None]
    rows, cols, values = [], [], []
    row_index = 6 * np.arange(len(tj))[:, None, None] + np.arange(6)[None, :, None]
    for node, block in ((edges["second"], block_j), (edges["first"], block_i)):
        keep = node > 0
        col_index = 6 * (node[:, None, None] - 1) + np.arange(6)[None, None, :]
        shape = (int(keep.sum()), 6, 6)
        rows.append(np.broadcast_to(row_index[keep], shape).ravel())
        cols.append(np.broadcast_to(col_index[keep], shape).ravel())
        values.append(np.einsum("eab,ebc->eac", whitening, block)[keep].ravel())
    return coo_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
        shape=(6 * len(tj), 6 * (count - 1)),
    ).tocsc()


def _moved(poses: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Nodes 1.. moved by their left perturbations: R' = exp(omega) R, t' = exp(omega) t + u."""
    moved = poses.copy()
    turn = Rotation.from_rotvec(step[:, :3]).as_matrix()
    moved[1:, :3, :3] = turn @ poses[1:, :3, :3]
    moved[1:, :3, 3] = np.einsum("nab,nb->na", turn, poses[1:, :3, 3]) + step[:, 3:]
    return moved


def optimise(
    graph: PoseGraph,
    switch_prior_sigma: float = 1.0,
    iterations: int = 50,
    consistency_sigmas: float = 5.0,
) -> PoseGraphSolution:
    """The poses that best agree with every edge, node 0 fixed, loops switchable (module
    docstring): Levenberg-Marquardt on sparse normal equations, relinearised at every step.

    Loops not tested before are tested one at a time, in the order they were added: solved
    trusted together with the loops kept so far, a loop is kept when no edge then disagrees by
    more than `consistency_sigmas` standard deviations; a loop that does is switched off for
    good (a false loop bends the whole chain of odometry edges between its ends, each by a
    share of its length). The kept loops are then trusted and, from the poses that gives,
    switched by dynamic covariance scaling."""
    count = len(graph.poses)
    if count < 2 or not graph.edges:
        return PoseGraphSolution(np.array(graph.poses).reshape(-1, 4, 4), np.ones(0), 0.0, 0)
    poses = np.array(graph.poses, dtype=np.float64)
    edges = _edge_arrays(graph)
    loops = edges["loop"]
    phi = 1.0 / switch_prior_sigma**2
    kept = np.array([e.consistent is not False for e in graph.edges])

    def trusted(residual: np.ndarray) -> np.ndarray:
        return (kept | ~loops).astype(np.float64)

    def switched(residual: np.ndarray) -> np.ndarray:
        # min(1, 2 phi / (phi + chi^2)) per kept loop edge, 1 for odometry, 0 for dropped loops
        weight = trusted(residual)
        chi2 = np.sum(residual[loops] ** 2, axis=1)
        weight[loops] *= np.minimum(1.0, 2.0 * phi / (phi + chi2))
        return weight

    steps = 0
    for row, edge in enumerate(graph.edges):
        if not edge.loop or edge.consistent is not None:
            continue
        kept[row] = True
        # untested later loops stay out of this test
        later = np.array([e.loop and e.consistent is None and r > row
                          for r, e in enumerate(graph.edges)])  # fmt: skip
        kept[later] = False
        trial, weight, _, used = _levenberg_marquardt(poses, edges, trusted, phi, iterations)
        steps += used
        residual = _errors(trial, edges)[0] * weight[:, None]
        edge.consistent = bool(np.linalg.norm(residual, axis=1).max() <= consistency_sigmas)
        kept[row] = edge.consistent
        kept[later] = True
    for rule in (trusted, switched):
        poses, weight, cost, used = _levenberg_marquardt(poses, edges, rule, phi, iterations)
        steps += used
    return PoseGraphSolution(poses, weight[loops].copy(), cost, steps)


def _levenberg_marquardt(
    poses: np.ndarray,
    edges: dict,
    weights: Callable[[np.ndarray], np.ndarray],
    phi: float,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(poses, edge weights, cost, steps) minimising the weighted residuals, the weights from
    `weights(residuals)` at every step."""
    count, loops = len(poses), edges["loop"]

    def cost(residual: np.ndarray, weight: np.ndarray) -> float:
        prior = phi * np.sum((1.0 - weight[loops]) ** 2)
        return 0.5 * float(np.sum((residual * weight[:, None]) ** 2) + prior)

    damping = 1e-4
    steps = 0
    residual, a, tj = _errors(poses, edges)
    weight = weights(residual)
    current = cost(residual, weight)
    while steps < iterations:
        steps += 1
        jacobian = _jacobian(count, edges, a, tj, weight)
        gradient = jacobian.T @ (residual * weight[:, None]).ravel()
        normal = (jacobian.T @ jacobian).tocsc()
        diagonal = normal.diagonal()
        improved = False
        while damping < 1e8:
            damped = normal + diags(damping * (diagonal + 1e-12))
            step = spsolve(damped.tocsc(), -gradient).reshape(-1, 6)
            trial = _moved(poses, step)
            trial_residual, trial_a, trial_tj = _errors(trial, edges)
            trial_weight = weights(trial_residual)
            trial_cost = cost(trial_residual, trial_weight)
            if trial_cost <= current:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        poses, residual, a, tj, weight = trial, trial_residual, trial_a, trial_tj, trial_weight
        damping = max(damping / 10.0, 1e-12)
        small = np.max(np.abs(step)) < 1e-10 or current - trial_cost <= 1e-12 * current
        current = trial_cost
        if small:
            break
    return poses, weight, current, steps
