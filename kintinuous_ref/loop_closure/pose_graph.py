"""A pose graph over keyframes, solved by sparse nonlinear least squares with switchable loops.

Nodes are camera-to-world poses T_i. An edge (i, j) carries a measurement Z_ij of the pose of j
in i's frame (odometry between consecutive keyframes, or a verified loop). Its error is the
motion that remains between the measurement and the estimate,

    E_ij = Z_ij^-1 T_i^-1 T_j,      r_ij = [log_SO3(R(E_ij)) / sigma_r, t(E_ij) / sigma_t],

zero when the graph agrees with the edge. Each node is parametrised by a left perturbation of its
starting pose, T_i = exp(delta_i) T_i^0 with delta_i = [omega, u] (the project's twist order), so
the parametrisation has no singularity however the cameras are turned; node 0 stays fixed (the
gauge). scipy's least_squares (trust region reflective) solves it with a finite-difference
Jacobian restricted to its sparsity: each edge's 6 residuals depend on 12 unknowns (13 with a
switch).

Robust loops: one false loop must not fold the map. Every loop edge gets a switch s in [0, 1]
(Suenderhauf and Protzel, IROS 2012) that scales its residual, s r_ij, with a prior
(1 - s)^2 / sigma_switch^2. A loop that agrees with the rest of the graph keeps s near 1; one that
contradicts it costs less switched off than on. Solving for s as extra bounded unknowns made
scipy's solver crawl towards the bound s = 0 (thousands of evaluations for a 24-node graph); the
switch that minimises that cost for given poses has a closed form (Agarwal et al., "Dynamic
Covariance Scaling", ICRA 2013), s = min(1, 2 phi / (phi + chi^2)) with phi = sigma_switch^2 and
chi^2 the loop's squared residual, so the poses are solved with the switches fixed and the
switches updated from the result, a few rounds until they settle. Odometry edges have no switch:
they are the backbone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
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
    ) -> Edge:
        if not (0 <= first < len(self.poses) and 0 <= second < len(self.poses)) or first == second:
            raise ConfigError(f"pose graph edge {first}-{second} needs two different nodes")
        edge = Edge(first, second, np.asarray(measurement, dtype=np.float64), sigma_translation,
                    sigma_rotation, loop)  # fmt: skip
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


def _poses_from(delta: np.ndarray, rotations: Rotation, positions: np.ndarray) -> tuple:
    """Rotations and positions of T = exp(delta) T0 (rotation about the world origin, as exp's
    left perturbation does, with its translation part taken as a plain offset: an equally valid
    chart of the same neighbourhood, cheaper to evaluate)."""
    step = Rotation.from_rotvec(delta[:, :3])
    return step * rotations, step.apply(positions) + delta[:, 3:]


def _edge_arrays(graph: PoseGraph) -> dict[str, np.ndarray]:
    edges = graph.edges
    measurements = np.array([e.measurement for e in edges])
    return {
        "first": np.array([e.first for e in edges], dtype=np.int64),
        "second": np.array([e.second for e in edges], dtype=np.int64),
        "rotation": Rotation.from_matrix(measurements[:, :3, :3]).inv(),
        "translation": measurements[:, :3, 3],
        "scale": np.array(
            [[1 / e.sigma_rotation] * 3 + [1 / e.sigma_translation] * 3 for e in edges]
        ),
        "loop": np.array([e.loop for e in edges]),
    }


def optimise(
    graph: PoseGraph, switch_prior_sigma: float = 1.0, rounds: int = 10
) -> PoseGraphSolution:
    """The poses that best agree with every edge, node 0 fixed, loops switchable."""
    count = len(graph.poses)
    loops = [row for row, edge in enumerate(graph.edges) if edge.loop]
    if count < 2 or not graph.edges:
        return PoseGraphSolution(np.array(graph.poses).reshape(-1, 4, 4), np.ones(0), 0.0, 0)
    start = np.array(graph.poses)
    rotations = Rotation.from_matrix(start[:, :3, :3])
    positions = start[:, :3, 3]
    edges = _edge_arrays(graph)
    free = 6 * (count - 1)  # node 0 is the gauge
    switches = np.ones(len(loops))
    phi = switch_prior_sigma**2

    def edge_residuals(x: np.ndarray) -> np.ndarray:
        delta = np.vstack([np.zeros(6), x.reshape(-1, 6)])
        rotation, position = _poses_from(delta, rotations, positions)
        first, second = edges["first"], edges["second"]
        inverse_first = rotation[first].inv()
        error_rotation = edges["rotation"] * inverse_first * rotation[second]
        in_first = inverse_first.apply(position[second] - position[first])
        error_translation = edges["rotation"].apply(in_first - edges["translation"])
        return np.hstack([error_rotation.as_rotvec(), error_translation]) * edges["scale"]

    def residuals(x: np.ndarray) -> np.ndarray:
        r = edge_residuals(x)
        r[loops] *= switches[:, None]
        return r.ravel()

    sparsity = lil_matrix((6 * len(graph.edges), free), dtype=np.int8)
    for row, edge in enumerate(graph.edges):
        for node in (edge.first, edge.second):
            if node > 0:
                sparsity[6 * row : 6 * row + 6, 6 * (node - 1) : 6 * node] = 1
    sparsity = sparsity.tocsr()
    x = np.zeros(free)
    evaluations = 0
    for _ in range(rounds):
        solved = least_squares(
            residuals, x, jac_sparsity=sparsity, method="trf", xtol=1e-10, ftol=1e-10
        )
        x, evaluations = solved.x, evaluations + int(solved.nfev)
        # The switch that minimises s^2 chi^2 + (1 - s)^2 / sigma^2 for the current poses, kept
        # in [0, 1]: Agarwal et al.'s closed form, min(1, 2 phi / (phi + chi^2)).
        chi2 = np.sum(edge_residuals(x)[loops] ** 2, axis=1)
        updated = np.minimum(1.0, 2.0 * phi / (phi + chi2))
        if np.allclose(updated, switches, atol=1e-4):
            switches = updated
            break
        switches = updated
    delta = np.vstack([np.zeros(6), x.reshape(-1, 6)])
    rotation, position = _poses_from(delta, rotations, positions)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = rotation.as_matrix()
    poses[:, :3, 3] = position
    cost = 0.5 * float(np.sum(residuals(x) ** 2))
    return PoseGraphSolution(poses, switches, cost, evaluations)
