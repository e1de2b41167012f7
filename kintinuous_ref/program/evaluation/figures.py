"""The paper's figures for an evaluation: ranking-score bar charts (Figs. 4 and 5) and every
trajectory against the ground truth seen from above (in place of the meshes of Figs. 6 and 7).

matplotlib with the Agg backend (files only, no display needed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.datasets.tum import Trajectory
from kintinuous_ref.program.evaluation.runs import OK, RunOutcome
from kintinuous_ref.program.evaluation.tables import ERROR_TABLES, method_title


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def ranking_figure(table: dict[str, Any], statistic: str, path: Path) -> Path:
    """Bars of the eq. 16 scores of each method for Tables I-III's `statistic` ("Median" or
    "Max") columns: Fig. 4 (medians) and Fig. 5 (maxima). Lower is better."""
    plt = _pyplot()
    methods = table["methods"]
    measures = [
        (key, f"{spec.short} (Table {spec.number})")
        for spec in ERROR_TABLES
        if spec.ranked
        for key, name in spec.columns
        if name == statistic
    ]
    width = 0.8 / len(measures)
    figure, axes = plt.subplots(figsize=(max(6.0, 1.1 * len(methods) + 2), 4.0))
    positions = np.arange(len(methods))
    for i, (key, label) in enumerate(measures):
        scores = table["ranking"][key]["scores"]
        if scores is None:
            label += ": n/a"
            heights = np.zeros(len(methods))
        else:
            heights = np.array([scores[m] for m in methods])
        axes.bar(positions + (i - (len(measures) - 1) / 2) * width, heights, width, label=label)
    axes.set_xticks(positions, [method_title(m) for m in methods], rotation=30, ha="right")
    axes.set_ylabel("ranking score (eq. 16, lower is better)")
    kind = "median" if statistic == "Median" else "maximum"
    axes.set_title(f"Ranking score for each algorithm's {kind} error")
    axes.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def top_view_basis(groundtruth: np.ndarray) -> np.ndarray:
    """(2, 3): the horizontal axes of a view from above of camera-to-world poses (N, 4, 4).

    "Up" is taken as the mean of the cameras' -y axes (image up): a hand-held or robot-mounted
    camera is held upright, whatever world frame its ground truth uses. The first plot axis is the
    first camera's viewing direction made horizontal, the second completes a right-handed frame
    with up pointing at the viewer.
    """
    up = -groundtruth[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    ahead = groundtruth[0, :3, 2] - up * (groundtruth[0, :3, 2] @ up)
    if np.linalg.norm(ahead) < 1e-6:  # first camera looking straight down or up
        ahead = groundtruth[0, :3, 0] - up * (groundtruth[0, :3, 0] @ up)
    ahead /= np.linalg.norm(ahead)
    return np.stack([ahead, np.cross(up, ahead)])


def trajectory_figure(
    outcomes: list[RunOutcome],
    groundtruths: dict[str, Trajectory | None],
    methods: list[str],
    path: Path,
) -> Path:
    """One panel per dataset: the ground truth and every method's trajectory, seen from above,
    unaligned (each run starts at the first ground-truth pose, so drift shows as in Figs. 6-7)."""
    plt = _pyplot()
    datasets = list(groundtruths)
    columns = min(3, len(datasets))
    rows = -(-len(datasets) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(5.0 * columns, 4.6 * rows), squeeze=False)
    colours = plt.get_cmap("tab10")
    for panel, dataset in zip(axes.flat, datasets, strict=False):
        truth = groundtruths[dataset]
        reference = truth.poses if truth is not None and len(truth) else None
        runs = {o.method: o for o in outcomes if o.dataset == dataset and o.status == OK}
        if reference is None and runs:
            reference = next(iter(runs.values())).poses
        if reference is None:
            panel.set_title(f"{dataset}: no trajectory")
            panel.axis("off")
            continue
        basis = top_view_basis(reference)
        if truth is not None:
            xy = truth.positions @ basis.T
            panel.plot(xy[:, 0], xy[:, 1], color="black", linewidth=2.5, label="ground truth")
        for i, method in enumerate(methods):
            if method in runs:
                xy = runs[method].poses[:, :3, 3] @ basis.T
                # Dashed: the FOVIS-switching variants, which often coincide with their base method.
                style = "--" if method.startswith("fovis/") else "-"
                panel.plot(xy[:, 0], xy[:, 1], style, color=colours(i), label=method_title(method))
        panel.plot(*(reference[0, :3, 3] @ basis.T), "ko", markersize=4)
        panel.set_aspect("equal", adjustable="datalim")
        panel.set_title(f"{dataset} (seen from above)")
        panel.set_xlabel("m (first camera's heading)")
        panel.set_ylabel("m")
        panel.legend(fontsize="x-small")
    for panel in list(axes.flat)[len(datasets) :]:
        panel.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
