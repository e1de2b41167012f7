"""The trajectory from above, before and after loop closure (trajectory_loops.png), and with a
ground truth each one's distance to it, frame by frame.

"Above" is the plane of the path's two largest principal directions: world x-y for the
synthetic scenes (z up), and whatever plane a real sequence's ground truth frame happens to have
its motion in otherwise, without assuming which axis is up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plane_axes(positions: np.ndarray) -> np.ndarray:
    """(3, 2): the two principal directions of the positions' spread."""
    centred = positions - positions.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[:2].T


def draw_trajectories(
    path: Path,
    before: np.ndarray,
    after: np.ndarray,
    truth: np.ndarray | None = None,
    loops: list[tuple[int, int]] | None = None,
) -> None:
    """Camera positions (N, 3) of the uncorrected and corrected runs (and the ground truth)
    from above; `loops` pairs of frame positions (in `after`) joined by a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reference = truth if truth is not None else after
    axes = plane_axes(reference)
    origin = reference.mean(axis=0)

    def flat(points: np.ndarray) -> np.ndarray:
        return (points - origin) @ axes

    panels = 2 if truth is not None else 1
    figure, axes_list = plt.subplots(1, panels, figsize=(6 * panels, 5), dpi=110, squeeze=False)
    ax = axes_list[0, 0]
    if truth is not None:
        ax.plot(*flat(truth).T, color="0.6", linewidth=2.5, label="ground truth")
    ax.plot(*flat(before).T, color="tab:red", linewidth=1.2, label="odometry only")
    ax.plot(*flat(after).T, color="tab:blue", linewidth=1.2, label="with loop closure")
    for first, second in loops or []:
        pair = flat(after[[first, second]])
        ax.plot(*pair.T, color="tab:green", linewidth=1.0)
    ax.plot(*flat(after[:1]).T, "ko", markersize=4, label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("metres")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("trajectory from above (loops closed: green)")
    if truth is not None:
        # Drift out of the drawing plane (height) does not show from above; the distance to
        # the ground truth does.
        ax = axes_list[0, 1]
        for positions, colour, label in (
            (before, "tab:red", "odometry only"),
            (after, "tab:blue", "with loop closure"),
        ):
            error = 1000.0 * np.linalg.norm(positions - truth, axis=1)
            ax.plot(error, color=colour, linewidth=1.2, label=label)
        for first, _ in loops or []:
            ax.axvline(first, color="tab:green", linewidth=0.8)
        ax.set_xlabel("frame")
        ax.set_ylabel("distance to the ground truth (mm)")
        ax.legend(loc="best", fontsize=8)
        ax.set_title("position error")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
