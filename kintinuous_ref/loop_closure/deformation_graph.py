"""Embedded deformation (Sumner, Schmid and Pauly, SIGGRAPH 2007) of the extracted map.

The graph's nodes are points g_j sampled from the mesh vertices, each with an affine map: a 3x3
matrix R_j (close to a rotation) and a translation t_j. A point v moves to

    v' = sum_j w_j(v) [R_j (v - g_j) + g_j + t_j]

over its k nearest nodes, with weights w_j = (1 - d_j / d_max)^2 normalised to sum to 1 (d_max
is the distance to the (k+1)-th nearest node), so each point follows the nodes around it and the
motion blends smoothly between them. The unknowns are found by minimising

    E = w_rot E_rot + w_reg E_reg + w_con E_con,

- E_rot = sum_j Rot(R_j): the columns c1, c2, c3 of R_j orthonormal, (c_a . c_b - delta_ab)^2;
- E_reg = sum_j sum_{k in N(j)} |R_j (g_k - g_j) + g_j + t_j - (g_k + t_k)|^2: neighbouring
  nodes agree about where each other goes;
- E_con = sum_c |v_c' - q_c|^2: chosen points go to their targets (here: points fixed to each
  keyframe's camera, moved from the pose the map was made with to the pose graph's answer).

Sumner et al. weigh them 1, 10, 100 (config.LoopClosureConfig). E_reg and E_con are linear in
the unknowns; only E_rot is quadratic. Levenberg-Marquardt (Gauss-Newton whose steps are damped
until they lower the cost, `levenberg_marquardt`) converges in about 10 steps: each solves the
sparse normal equations (J^T J + lambda I) dx = -J^T r (12 unknowns per node) with SuperLU. scipy's
least_squares with the same sparse Jacobian (its iterative LSMR inner solver) took over ten
minutes on the map of the `revisit` scenario, where a few direct solves take seconds.

Space and time. A place visited twice holds two layers of map until the loop is closed: the
old one (fused when the camera first passed) and the new one (fused with drifted poses), a few
centimetres apart, which must move differently. As in the IROS 2013 paper, which connects nodes
in the order the map was made, neighbours here are nearest in space-time: every node and point
carries the frame it was made at, and distances are measured in (x, y, z, time_scale * frame).
A point then follows the nodes made around the same time as itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix, identity, vstack
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from kintinuous_ref import se3
from kintinuous_ref.errors import ConfigError

# Levenberg-Marquardt's damping: where it starts (a nearly Gauss-Newton step) and where it gives
# up (a step that short changes nothing).
LM_INITIAL_DAMPING = 1e-4
LM_MAX_DAMPING = 1e8
# A piece of the graph that no constraint reaches is joined to the rest from each of its nodes
# at most this many times as far from another piece as its nearest node (bridging_edges).
BRIDGE_REACH = 1.25


@dataclass
class DeformationGraph:
    positions: np.ndarray  # (M, 3) node positions g_j
    times: np.ndarray  # (M,) frame each node was made at
    edges: np.ndarray  # (E, 2) node pairs (j, l) whose E_reg term ties l's motion to j's
    time_scale: float  # metres per frame in space-time distances
    rotations: np.ndarray  # (M, 3, 3) R_j (identity: no deformation)
    translations: np.ndarray  # (M, 3) t_j

    @property
    def size(self) -> int:
        return len(self.positions)

    def space_time(self, points: np.ndarray, times: np.ndarray) -> np.ndarray:
        return np.column_stack([points, self.time_scale * np.asarray(times, dtype=np.float64)])


def sample_nodes(points: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of points at most one per cube of side `spacing`: the point of each occupied cube
    nearest its centre (an even cover, independent of how densely the mesh is triangulated).
    `points` may have a fourth, time coordinate: two layers of one place then get nodes each."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / spacing)
    distance = np.linalg.norm(points / spacing - (cells + 0.5), axis=1)
    order = np.lexsort((distance, *cells.T[::-1]))
    sorted_cells = cells[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(sorted_cells[1:] != sorted_cells[:-1], axis=1)
    return np.sort(order[first])


def build_graph(
    points: np.ndarray,
    times: np.ndarray,
    spacing: float,
    neighbours: int = 4,
    time_scale: float = 0.0,
) -> DeformationGraph:
    """Nodes sampled from `points` (with the frames they were made at), each joined to its
    `neighbours` nearest other nodes in space-time."""
    points = np.asarray(points, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    chosen = sample_nodes(np.column_stack([points, time_scale * times]), spacing)
    if len(chosen) < 2:
        raise ConfigError(
            f"deformation graph: {len(chosen)} node(s) from {len(points)} points at "
            f"{spacing} m spacing; the map is too small to deform"
        )
    positions, node_times = points[chosen], times[chosen]
    k = min(neighbours, len(chosen) - 1)
    space_time = np.column_stack([positions, time_scale * node_times])
    _, nearest = cKDTree(space_time).query(space_time, k=k + 1)
    nearest = nearest[:, 1:].reshape(len(chosen), k)
    edges = np.column_stack([np.repeat(np.arange(len(chosen)), k), nearest.ravel()])
    return DeformationGraph(
        positions=positions,
        times=node_times,
        edges=edges,
        time_scale=time_scale,
        rotations=np.tile(np.eye(3), (len(chosen), 1, 1)),
        translations=np.zeros((len(chosen), 3)),
    )


def node_weights(
    graph: DeformationGraph, points: np.ndarray, times: np.ndarray, k: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """(indices (N, k), weights (N, k)) of the nodes that move each point (module docstring)."""
    k = min(k, graph.size - 1)
    tree = cKDTree(graph.space_time(graph.positions, graph.times))
    distance, index = tree.query(graph.space_time(np.asarray(points, np.float64), times), k=k + 1)
    distance, index = distance.reshape(-1, k + 1), index.reshape(-1, k + 1)
    d_max = np.maximum(distance[:, -1:], 1e-9)
    weights = (1.0 - distance[:, :k] / d_max) ** 2
    total = weights.sum(axis=1, keepdims=True)
    # A point exactly as far from all k+1 nodes has all weights 0: share them equally.
    weights = np.where(total > 1e-12, weights / np.maximum(total, 1e-12), 1.0 / k)
    return index[:, :k], weights


def deform_points(
    graph: DeformationGraph, points: np.ndarray, index: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """v' = sum_j w_j [R_j (v - g_j) + g_j + t_j] for points (N, 3) and their nodes."""
    points = np.asarray(points, dtype=np.float64)
    g = graph.positions[index]  # (N, k, 3)
    local = points[:, None, :] - g
    moved = np.einsum("nkab,nkb->nka", graph.rotations[index], local) + g
    moved += graph.translations[index]
    return np.einsum("nk,nka->na", weights, moved)


def deform_poses(
    graph: DeformationGraph, poses: np.ndarray, times: np.ndarray, k: int = 4
) -> np.ndarray:
    """Camera poses (N, 4, 4) moved through the graph: the centre as a point, the orientation
    turned by the nodes' blended rotation (made orthonormal)."""
    poses = np.asarray(poses, dtype=np.float64)
    index, weights = node_weights(graph, poses[:, :3, 3], times, k)
    moved = poses.copy()
    moved[:, :3, 3] = deform_points(graph, poses[:, :3, 3], index, weights)
    blended = np.einsum("nk,nkab->nab", weights, graph.rotations[index])
    for i in range(len(poses)):
        moved[i, :3, :3] = se3.orthonormalize(blended[i]) @ poses[i, :3, :3]
    return moved


def bridging_edges(space_time: np.ndarray, edges: np.ndarray, reached: np.ndarray) -> np.ndarray:
    """(B, 2) edges, both ways, that join every piece of the graph of `edges` (over nodes at
    `space_time`, (M, 4)) to a piece holding a node of `reached`, the nodes the constraints
    move: each piece without one is joined to the nearest node of another piece, until none is
    left. Nearest neighbours alone can leave a piece that no constraint reaches (a stretch of
    wall mapped at the end of a run, apart in space-time from the rest); E_reg and E_rot would
    then hold it where it was mapped, however far the constraints move its surroundings. Pieces
    that constraints reach are left apart (two layers of one place mapped at different times
    move as their own constraints say)."""
    size, bridges = len(space_time), [np.zeros((0, 2), dtype=np.int64)]
    if not len(reached):
        return bridges[0]
    while True:
        joined = np.vstack([edges, *bridges])
        graph = coo_matrix((np.ones(len(joined)), (joined[:, 0], joined[:, 1])), (size, size))
        count, piece = connected_components(graph, directed=False)
        pinned = np.zeros(count, dtype=bool)
        pinned[piece[reached]] = True
        if pinned.all():
            return np.vstack(bridges)
        for label in np.flatnonzero(~pinned):
            inside, outside = np.flatnonzero(piece == label), np.flatnonzero(piece != label)
            distance, nearest = cKDTree(space_time[outside]).query(space_time[inside])
            # every node about as near as the nearest: bridges along the whole facing edge pin
            # the piece's rotation too (one bridge leaves it free to turn about itself)
            near = distance <= BRIDGE_REACH * distance.min()
            a, b = inside[near], outside[nearest[near]]
            bridges.append(np.column_stack([np.concatenate([a, b]), np.concatenate([b, a])]))


def _linear_terms(
    graph: DeformationGraph,
    edges: np.ndarray,
    sources: np.ndarray,
    index: np.ndarray,
    weights: np.ndarray,
    targets: np.ndarray,
) -> tuple[csr_matrix, np.ndarray]:
    """E_reg and E_con as A x - b over x = [vec(R_j) row-major, t_j] (12 per node)."""
    m = graph.size
    rows, cols, values = [], [], []
    # E_reg: for edge (j, l): R_j (g_l - g_j) + t_j - t_l = g_l - g_j  (3 rows per edge)
    j, neighbour = edges[:, 0], edges[:, 1]
    d = graph.positions[neighbour] - graph.positions[j]
    edge_rows = 3 * np.arange(len(j))
    for a in range(3):
        for b in range(3):
            rows.append(edge_rows + a)
            cols.append(12 * j + 3 * a + b)
            values.append(d[:, b])
        rows += [edge_rows + a, edge_rows + a]
        cols += [12 * j + 9 + a, 12 * neighbour + 9 + a]
        values += [np.ones(len(j)), -np.ones(len(j))]
    reg = coo_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
        shape=(3 * len(j), 12 * m),
    ).tocsr()
    reg_b = d.ravel()
    # E_con: sum_j w_j [R_j (v - g_j) + t_j] = q - sum_j w_j g_j  (3 rows per constraint)
    rows, cols, values = [], [], []
    c = np.repeat(np.arange(len(sources)), index.shape[1])
    node = index.ravel()
    w = weights.ravel()
    local = sources[c] - graph.positions[node]
    for a in range(3):
        for b in range(3):
            rows.append(3 * c + a)
            cols.append(12 * node + 3 * a + b)
            values.append(w * local[:, b])
        rows.append(3 * c + a)
        cols.append(12 * node + 9 + a)
        values.append(w)
    con = coo_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
        shape=(3 * len(sources), 12 * m),
    ).tocsr()
    con_b = (targets - np.einsum("ck,cka->ca", weights, graph.positions[index])).ravel()
    return reg, reg_b, con, con_b


def levenberg_marquardt(
    residuals: Callable[[np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray], csr_matrix],
    x: np.ndarray,
    iterations: int,
    tolerance: float = 1e-9,
) -> np.ndarray:
    """Least squares on sparse normal equations, (J^T J + lambda I) dx = -J^T r, keeping a step
    only where it lowers the cost (lambda shrinks 3x after one that does, grows 4x until one
    does). Plain Gauss-Newton diverges here: E_rot linearised at R = I leaves the skew part of
    each dR free, so weakly pinned nodes take steps of metres that the true, quadratic E_rot
    punishes; on the `revisit` map its cost rose from 329 to 43 000 in 10 steps (nodes scaled
    7x, vertices thrown metres off) where this ends at 0.0075. Stops after `iterations` kept
    steps, or when the step is below `tolerance` or no damping lowers the cost."""
    r = residuals(x)
    cost, damping = float(r @ r), LM_INITIAL_DAMPING
    for _ in range(iterations):
        j = jacobian(x)
        normal, gradient = (j.T @ j).tocsc(), j.T @ r
        while damping <= LM_MAX_DAMPING:
            step = spsolve(normal + damping * identity(len(x), format="csc"), -gradient)
            trial = residuals(x + step)
            if float(trial @ trial) < cost:
                break
            damping *= 4.0
        else:
            return x  # no step lowers the cost: a minimum to rounding
        x, r, cost = x + step, trial, float(trial @ trial)
        damping = max(damping / 3.0, 1e-12)
        if np.max(np.abs(step)) < tolerance:
            break
    return x


@dataclass
class Energy:
    """E = |r(x)|^2 of a graph's deformation (module docstring) over x, each node's 12 unknowns
    (vec(R_j) row-major, then t_j), with r's sparse Jacobian and x where the graph stands."""

    residuals: Callable[[np.ndarray], np.ndarray]
    jacobian: Callable[[np.ndarray], csr_matrix]
    start: np.ndarray

    def cost(self, x: np.ndarray) -> float:
        r = self.residuals(x)
        return float(r @ r)


def energy(
    graph: DeformationGraph,
    sources: np.ndarray,
    source_times: np.ndarray,
    targets: np.ndarray,
    rotation_weight: float = 1.0,
    regularisation_weight: float = 10.0,
    constraint_weight: float = 100.0,
    k: int = 4,
) -> Energy:
    """w_rot E_rot + w_reg E_reg + w_con E_con for taking `sources` (C, 3), made at
    `source_times`, to `targets`."""
    sources = np.asarray(sources, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64)
    index, weights = node_weights(graph, sources, source_times, k)
    reached = np.unique(index[weights > 0])
    space_time = graph.space_time(graph.positions, graph.times)
    edges = np.vstack([graph.edges, bridging_edges(space_time, graph.edges, reached)])
    reg, reg_b, con, con_b = _linear_terms(graph, edges, sources, index, weights, targets)
    m = graph.size
    linear = vstack([np.sqrt(regularisation_weight) * reg, np.sqrt(constraint_weight) * con])
    linear = linear.tocsr()
    linear_b = np.concatenate(
        [np.sqrt(regularisation_weight) * reg_b, np.sqrt(constraint_weight) * con_b]
    )
    root_rot = np.sqrt(rotation_weight)
    pairs = ((0, 1), (0, 2), (1, 2), (0, 0), (1, 1), (2, 2))

    def rotation_terms(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = x.reshape(m, 12)[:, :9].reshape(m, 3, 3)
        columns = r.transpose(0, 2, 1)  # columns[:, a] is column a of R_j
        values = np.stack(
            [np.einsum("ma,ma->m", columns[:, a], columns[:, b]) - (a == b) for a, b in pairs],
            axis=1,
        )
        return values, columns

    def residuals(x: np.ndarray) -> np.ndarray:
        values, _ = rotation_terms(x)
        return np.concatenate([root_rot * values.ravel(), linear @ x - linear_b])

    # Jacobian of the rotation terms: d(c_a . c_b)/d c_a = c_b; column a of R_j holds the
    # unknowns 12 j + 3 i + a (row-major vec), i = 0..2.
    rot_rows = np.repeat(np.arange(6 * m), 6)
    rot_cols = np.zeros((m, 6, 6), dtype=np.int64)
    base = 12 * np.arange(m)[:, None]
    for p, (a, b) in enumerate(pairs):
        rot_cols[:, p, :3] = base + 3 * np.arange(3) + a
        rot_cols[:, p, 3:] = base + 3 * np.arange(3) + b

    def jacobian(x: np.ndarray) -> csr_matrix:
        _, columns = rotation_terms(x)
        values = np.zeros((m, 6, 6))
        for p, (a, b) in enumerate(pairs):
            values[:, p, :3] = columns[:, b]
            values[:, p, 3:] = columns[:, a]
        rot = coo_matrix(
            (root_rot * values.ravel(), (rot_rows, rot_cols.ravel())), shape=(6 * m, 12 * m)
        ).tocsr()  # duplicates (a == b) add up: d(c.c)/dc = 2c
        return vstack([rot, linear]).tocsr()

    start = np.concatenate([graph.rotations.reshape(m, 9), graph.translations], axis=1).ravel()
    return Energy(residuals, jacobian, start)


def optimise(
    graph: DeformationGraph,
    sources: np.ndarray,
    source_times: np.ndarray,
    targets: np.ndarray,
    rotation_weight: float = 1.0,
    regularisation_weight: float = 10.0,
    constraint_weight: float = 100.0,
    k: int = 4,
    iterations: int = 10,
) -> DeformationGraph:
    """The graph whose deformation takes `sources` (C, 3) made at `source_times` to `targets`,
    as rigidly and smoothly as possible (module docstring). Returns a new graph."""
    terms = energy(graph, sources, source_times, targets, rotation_weight,
                   regularisation_weight, constraint_weight, k)  # fmt: skip
    x = levenberg_marquardt(terms.residuals, terms.jacobian, terms.start, iterations)
    return with_unknowns(graph, x)


def with_unknowns(graph: DeformationGraph, x: np.ndarray) -> DeformationGraph:
    """`graph` with its nodes' affine maps taken from x (Energy's layout)."""
    m = graph.size
    unknowns = x.reshape(m, 12)
    return DeformationGraph(
        positions=graph.positions,
        times=graph.times,
        edges=graph.edges,
        time_scale=graph.time_scale,
        rotations=unknowns[:, :9].reshape(m, 3, 3).copy(),
        translations=unknowns[:, 9:].copy(),
    )
