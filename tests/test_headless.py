"""A machine without VTK still reconstructs: the meshes are our own marching cubes (the slices of
the moving volume and the final mesh), and the preview falls back to matplotlib's plan view.

The run: the synthetic corridor (30 frames, 80x60, true poses), a 48^3 window over 3 m that
shifts at every metre, on the cpu backend, once in a process where `import vtk` and
`import pyvista` fail and once in a normal one. The two mesh.ply files hold the same vertices.
"""

import json
import subprocess
import sys

import numpy as np

from kintinuous_ref.datasets import synthetic
from kintinuous_ref.slices import read_mesh


def reconstruct(folder, out, without_vtk: bool) -> subprocess.CompletedProcess:  # noqa: ANN001
    arguments = ["reconstruct", str(folder), "--volume-size", "3", "--resolution", "48"]
    arguments += ["--odometry", "groundtruth", "--backend", "cpu", "--shift-threshold", "1"]
    arguments += ["--out", str(out)]
    script = (
        "import sys\n"
        + ("sys.modules['vtk'] = sys.modules['pyvista'] = None\n" if without_vtk else "")
        + "from kintinuous_ref.program.cli import main\n"
        + f"code = main({arguments!r})\n"
        + "assert not any(sys.modules.get(m) for m in ('vtk', 'pyvista'))\n" * without_vtk
        + "sys.exit(code)\n"
    )
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)


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
