"""Execute every walk-through in notebooks/ top to bottom; any error fails the test.

The notebooks are stored as jupytext percent-format .py files (readable diffs); each is converted
in memory to a notebook and run by nbclient in a fresh kernel. The numbers each notebook shows are
checked inside the notebook itself (assert cells against synthetic ground truth, and
np.testing.assert_allclose of kintinuous_fast against kintinuous_ref), so executing them is the
test. Budget: about 30 s per notebook on this 2-core machine, 120 s for all four.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
# Per-notebook limit: generous against a loaded machine, small enough that a hang is caught.
TIMEOUT_S = 240


def notebook_paths() -> list[Path]:
    return sorted(NOTEBOOKS.glob("[0-9][0-9]_*.py"))


def test_the_five_walkthroughs_exist():
    names = [path.stem for path in notebook_paths()]
    assert names == [
        "01_tsdf_fusion",
        "02_photometric_odometry",
        "03_combined_cost",
        "04_colour_fusion",
        "05_loop_closure",
    ]


@pytest.mark.slow
@pytest.mark.parametrize("path", notebook_paths(), ids=lambda path: path.stem)
def test_notebook_runs(path: Path):
    notebook = jupytext.read(path)
    # The kernel runs this interpreter's environment. One numba thread: the arrays are small
    # (160x120 images, 128^3 volumes) and on a shared 2-core machine spinning worker threads
    # cost more than they gain.
    # MPLBACKEND=Agg stands for any backend a user may have set: the notebooks choose the inline
    # one themselves, so their pictures must still come out.
    env = dict(os.environ, NUMBA_NUM_THREADS="1", PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg")
    client = nbclient.NotebookClient(
        notebook,
        timeout=TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOKS)}},
    )
    client.execute(env=env)
    pictures = [
        output
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.get("outputs", [])
        if "image/png" in output.get("data", {})
    ]
    assert len(pictures) >= 2, f"{path.name} showed {len(pictures)} pictures"
