"""A machine without VTK still reconstructs: the meshes are our own marching cubes (the slices of
the moving volume and the final mesh), and the preview falls back to matplotlib's plan view.

The run: the synthetic corridor (30 frames, 80x60, true poses), a 48^3 window over 3 m that
shifts at every metre, on the cpu backend, once in a process where `import vtk` and
`import pyvista` fail and once in a normal one. The two mesh.ply files hold the same vertices.

The cuda backend makes the same mesh headless: without a GPU it runs in numba's CUDA simulator
(scheduled by tests/quick_simulator.py), on a smaller run the simulator finishes in under a
minute (40x30, a 24^3 window over 2.4 m that shifts at every voxel, a 3x3 bilateral filter), and
its mesh.ply equals the cpu backend's normal run of the same frames vertex for vertex.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from kintinuous_fast import cuda_status
from kintinuous_ref.datasets import synthetic
from kintinuous_ref.slices import read_mesh

TESTS = Path(__file__).resolve().parent
WINDOW = ["--volume-size", "3", "--resolution", "48"]
SMALL_WINDOW = ["--volume-size", "2.4", "--resolution", "24"]
SMALL_WINDOW += ["--set", "preprocess.bilateral_radius=1"]


def reconstruct(  # noqa: ANN001
    folder, out, without_vtk: bool, backend: str = "cpu", window: list[str] = WINDOW
) -> subprocess.CompletedProcess:
    arguments = ["reconstruct", str(folder), *window, "--odometry", "groundtruth"]
    arguments += ["--backend", backend, "--shift-threshold", "1", "--out", str(out)]
    simulated = backend == "cuda" and bool(cuda_status())
    script = (
        "import sys\n"
        + ("sys.modules['vtk'] = sys.modules['pyvista'] = None\n" if without_vtk else "")
        + f"sys.path.insert(0, {str(TESTS)!r})\nimport quick_simulator\n" * simulated
        + "quick_simulator.install()\n" * simulated
        + "from kintinuous_ref.program.cli import main\n"
        + f"code = main({arguments!r})\n"
        + "assert not any(sys.modules.get(m) for m in ('vtk', 'pyvista'))\n" * without_vtk
        + "sys.exit(code)\n"
    )
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"} if simulated else None
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)


def test_reconstruct_without_vtk_makes_the_same_mesh(tmp_path):
    folder = tmp_path / "corridor"
    synthetic.write_scenario("corridor", folder, frames=30, width=80, height=60, noise=False)
    headless = reconstruct(folder, tmp_path / "headless", without_vtk=True)
    assert headless.returncode == 0, headless.stderr[-2000:]
    normal = reconstruct(folder, tmp_path / "normal", without_vtk=False)
    assert normal.returncode == 0, normal.stderr[-2000:]
    report = json.loads((tmp_path / "headless" / "report.json").read_text())
    assert report["moving_volume"] and report["shifts"] >= 2 and report["slices"] >= 1
    assert {"mesh.ply", "preview.png", "report.json"} <= set(report["saved"])
    note = "the preview is a plan view drawn by matplotlib: pyvista is not installed"
    assert note in report["warnings"] and f"warning: {note}" in headless.stderr
    ours, theirs = (read_mesh(tmp_path / run / "mesh.ply") for run in ("headless", "normal"))
    assert len(ours.points) == len(theirs.points) > 1000
    assert np.abs(ours.points - theirs.points).max() <= 1e-6
    np.testing.assert_array_equal(ours.triangles, theirs.triangles)


def test_cuda_reconstruct_without_vtk_makes_the_cpu_mesh(tmp_path):
    folder = tmp_path / "corridor"
    synthetic.write_scenario("corridor", folder, frames=30, width=40, height=30, noise=False)
    headless = reconstruct(folder, tmp_path / "cuda", True, backend="cuda", window=SMALL_WINDOW)
    assert headless.returncode == 0, headless.stderr[-2000:]
    normal = reconstruct(folder, tmp_path / "cpu", False, window=SMALL_WINDOW)
    assert normal.returncode == 0, normal.stderr[-2000:]
    report = json.loads((tmp_path / "cuda" / "report.json").read_text())
    assert report["backend"] == "cuda" and report["moving_volume"]
    assert report["shifts"] >= 2 and report["slices"] >= 1
    assert {"mesh.ply", "preview.png", "report.json"} <= set(report["saved"])
    ours, theirs = (read_mesh(tmp_path / run / "mesh.ply") for run in ("cuda", "cpu"))
    assert len(ours.points) == len(theirs.points) > 200
    assert np.abs(ours.points - theirs.points).max() <= 1e-6
    np.testing.assert_array_equal(ours.triangles, theirs.triangles)
