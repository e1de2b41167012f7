"""docs/architecture.png: the layers of the project and one frame's path through them.

.venv/bin/python docs/make_architecture_figure.py
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).with_name("architecture.png")
LAYER_COLOURS = {"program": "#fde0c5", "algorithm": "#d5e8f7", "backend": "#e3f1d8"}
STAGES = ("preprocess", "odometry", "moving volume", "integrate", "raycast")


def box(axes, x, y, width, height, text, colour, size=9, weight="normal"):  # noqa: ANN001, ANN201
    axes.add_patch(
        FancyBboxPatch(
            (x, y), width, height, boxstyle="round,pad=0.02", facecolor=colour, edgecolor="#555"
        )
    )
    axes.text(
        x + width / 2,
        y + height / 2,
        text,
        ha="center",
        va="center",
        size=size,
        weight=weight,
        wrap=True,
    )


def arrow(axes, start, end, colour="#333", style="-|>"):  # noqa: ANN001, ANN201
    axes.add_patch(
        FancyArrowPatch(start, end, arrowstyle=style, mutation_scale=12, color=colour, lw=1.4)
    )


def main() -> None:
    figure, axes = plt.subplots(figsize=(12, 7.2))
    axes.set_xlim(0, 12)
    axes.set_ylim(0, 7.2)
    axes.axis("off")

    # The program: kintinuous_ref/program, which only it imports.
    box(axes, 0.2, 6.0, 11.6, 1.0, "", LAYER_COLOURS["program"])
    axes.text(
        0.35,
        6.85,
        "kintinuous_ref/program: the `kintinuous` command",
        size=10,
        weight="bold",
        va="top",
    )
    for i, name in enumerate(
        (
            "cli.py  arguments.py\ncommands.py",
            "reconstruct.py\n(datasets in, results out)",
            "evaluation/\n(Tables I-VI, Figs. 4-5)",
            "benchmark.py",
        )
    ):
        box(axes, 0.5 + 2.85 * i, 6.1, 2.5, 0.5, name, "white", size=8.5)

    # The algorithms: the specification, with the per-frame loop in pipeline.run.
    box(axes, 0.2, 3.2, 11.6, 2.55, "", LAYER_COLOURS["algorithm"])
    axes.text(
        0.35,
        5.6,
        "kintinuous_ref: the algorithms (NumPy, the specification)",
        size=10,
        weight="bold",
        va="top",
    )
    axes.text(2.0, 5.15, "pipeline.run: one frame", size=9, style="italic")
    xs = [0.5 + 2.3 * i for i in range(len(STAGES))]
    for x, stage in zip(xs, STAGES, strict=True):
        box(axes, x, 4.3, 1.9, 0.6, stage, "white", size=9, weight="bold")
    for x0, x1 in zip(xs, xs[1:], strict=False):
        arrow(axes, (x0 + 1.95, 4.6), (x1 - 0.05, 4.6), colour="#c0392b")
    arrow(axes, (xs[-1] + 0.95, 4.25), (xs[1] + 0.95, 4.25), colour="#c0392b", style="-|>")
    axes.text(
        (xs[1] + xs[-1]) / 2 + 0.95,
        3.95,
        "the model seen from the new pose: the next frame's ICP target",
        ha="center",
        size=8,
        color="#c0392b",
    )
    axes.text(
        0.5,
        3.4,
        "vocabulary (imports nothing)  datasets/  se3  camera  config  metrics  mesh  "
        "moving_volume  slices  loop_closure/\nodometry/: icp, rgbd, combined, fovis, switching, "
        "solve; the trackers written once over a Systems object",
        size=8.5,
    )
    arrow(axes, (0.25, 5.1), (xs[0] + 0.2, 4.95), colour="#c0392b")
    axes.text(0.25, 5.15, "RGB-D frame", size=8, color="#c0392b")

    # The backends, behind the written protocol.
    box(axes, 0.2, 0.2, 11.6, 2.7, "", LAYER_COLOURS["backend"])
    axes.text(
        0.35,
        2.75,
        "backend.Backend: the stages' functions, where the arrays live, the volume as a TsdfVolume",
        size=10,
        weight="bold",
        va="top",
    )
    box(
        axes,
        0.5,
        0.45,
        3.0,
        1.85,
        "ReferenceBackend\n(kintinuous_ref's own modules)",
        "white",
        size=9,
    )
    box(axes, 3.9, 0.45, 7.7, 1.85, "", "white")
    axes.text(
        4.05,
        2.15,
        "kintinuous_fast, found through the entry points `kintinuous.backends` (cpu, cuda);\n"
        "each module has its reference module's names and signatures (test_stage_contract)",
        size=9,
        va="top",
    )
    packages = {
        "preprocess/": "ops.py\ncpu.py  cuda.py",
        "tsdf/": "ops.py  voxel.py\nvolume.py\ncpu.py  cuda.py",
        "raycast/": "ray.py  ops.py\nshading.py\ncpu.py  cuda.py",
        "colour/": "(ops in tsdf/)\ncpu.py  cuda.py",
        "odometry/": "icp/  rgbd/\nsums/  solve/\ncombined.py\ncpu.py  cuda.py",
    }
    for i, (stage, files) in enumerate(packages.items()):
        box(axes, 4.1 + 1.48 * i, 0.5, 1.35, 1.12, f"{stage}\n{files}", "#f4f9ef", size=7.5)
    for x in xs:
        arrow(axes, (x + 0.95, 4.28), (x + 0.95, 2.95), colour="#777", style="-|>")
    arrow(axes, (6.0, 6.05), (6.0, 5.8), colour="#333")
    figure.savefig(OUT, dpi=110, bbox_inches="tight")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
