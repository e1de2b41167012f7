"""Regenerate docs/scenarios.png: one frame of each synthetic scenario, colour and depth.

    .venv/bin/python docs/make_scenarios_figure.py [--out docs/scenarios.png]

Frames are rendered at 640x480 with the Kinect-like sensor model (noise, dropouts, 4 m range),
seed 0, from 300-frame sequences; `dark` shows a frame while the light is out (2 %).
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from kintinuous_ref.datasets import synthetic  # noqa: E402

FRAMES = {"desk": 120, "corridor": 150, "dark": 150, "floor": 150, "loop": 200}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "scenarios.png"
    )
    args = parser.parse_args()
    summaries = synthetic.list_scenarios()
    figure, axes = plt.subplots(len(FRAMES), 2, figsize=(9.0, 3.45 * len(FRAMES)))
    for row, (name, index) in enumerate(FRAMES.items()):
        scenario = synthetic.make_scenario(name, frames=300, seed=0, noise=True)
        colour, depth = scenario.render(index)
        axes[row, 0].imshow(colour)
        light = scenario.brightness[index]
        note = f", light {light:.0%}" if light < 1 else ""
        axes[row, 0].set_title(f"{name}, frame {index}{note}", fontsize=10, loc="left")
        shown = np.where(depth > 0, depth, np.nan)
        image = axes[row, 1].imshow(shown, cmap="turbo", vmin=0.4, vmax=4.0)
        axes[row, 1].set_facecolor("black")
        axes[row, 1].set_title("depth (m), black = none", fontsize=10, loc="left")
        figure.colorbar(image, ax=axes[row, 1], fraction=0.035, pad=0.02)
        axes[row, 0].text(
            0, -0.04, summaries[name], transform=axes[row, 0].transAxes, fontsize=7.5, va="top"
        )
        for axis in axes[row]:
            axis.set_xticks([])
            axis.set_yticks([])
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, dpi=80)
    # a 256-colour palette keeps the README's image small (a third of the size) and looks the same
    buffer.seek(0)
    Image.open(buffer).convert("RGB").quantize(256).save(args.out, optimize=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
