"""The layers of docs/architecture.md hold: the reference never imports the fast package, the
algorithms never import the program around them, both backends implement the written protocol,
and every document a docstring or comment names exists."""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kintinuous_fast.backend import FastBackend
from kintinuous_ref.backend import Backend, ReferenceBackend

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "kintinuous_ref"
TINY = ROOT / "data" / "tiny_desk"


def imported_modules(path: Path) -> set[str]:
    """Every module an `import` or `from ... import` in the file names, wherever it stands."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_the_reference_never_imports_the_fast_package():
    offenders = {
        str(path.relative_to(ROOT)): sorted(n for n in imported_modules(path) if "fast" in n)
        for path in REFERENCE.rglob("*.py")
        if any(n.split(".")[0] == "kintinuous_fast" for n in imported_modules(path))
    }
    assert offenders == {}


def test_the_algorithms_never_import_the_program():
    program = REFERENCE / "program"
    offenders = [
        str(path.relative_to(ROOT))
        for path in REFERENCE.rglob("*.py")
        if program not in path.parents
        and any(n.startswith("kintinuous_ref.program") for n in imported_modules(path))
    ]
    assert offenders == []


def test_every_backend_implements_the_protocol():
    for backend in (ReferenceBackend(), FastBackend("cpu")):
        assert isinstance(backend, Backend)
        for stage in ("preprocess", "tsdf", "raycast", "colour", "odometry"):
            module = getattr(backend, stage)
            assert module.__name__.split(".")[-1] in (stage, backend.name)


def test_reconstruct_runs_with_the_fast_package_unimportable(tmp_path):
    """A None entry in sys.modules makes `import kintinuous_fast` raise ImportError: the CLI, the
    pipeline and the reference backend then run as if the package were not installed."""
    out = tmp_path / "run"
    script = (
        "import sys; sys.modules['kintinuous_fast'] = None\n"
        "from kintinuous_ref.program.cli import main\n"
        f"code = main(['reconstruct', {str(TINY)!r}, '--backend', 'ref', '--odometry', 'icp',"
        f" '--frames', '3', '--resolution', '32', '--out', {str(out)!r}])\n"
        "assert 'kintinuous_fast' not in [m.split('.')[0] for m in sys.modules if sys.modules[m]]\n"
        "print(main(['info']))\n"
        "sys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "completed" and report["backend"] == "ref"
    assert report["frames"] == 3 and report["tracking_failures"] == 0
    # without the plugin, `info` says why cpu and cuda are missing and auto falls back to ref
    assert "cpu   no    backend 'cpu' cannot be imported" in done.stdout
    assert "auto -> ref" in done.stdout


DOCUMENT = re.compile(r"\b((?:docs|notebooks|benchmarks|data)/[\w./-]+\.(?:md|py|png|sh))\b")


def test_every_document_the_code_names_exists():
    missing = {}
    for path in [*ROOT.glob("kintinuous_*/**/*.py"), *ROOT.glob("benchmarks/*.py")]:
        for name in DOCUMENT.findall(path.read_text()):
            if not (ROOT / name).exists():
                missing.setdefault(str(path.relative_to(ROOT)), []).append(name)
    assert missing == {}


def test_the_entry_points_make_the_backends_or_say_why_not():
    from kintinuous_fast.backend import cpu_backend, cuda_backend, cuda_status
    from kintinuous_ref.backend import BackendUnavailable, plugins

    assert {"cpu", "cuda"} <= set(plugins())
    assert cpu_backend().name == "cpu"
    if cuda_status():  # no GPU here: a one-line reason instead of a backend
        with pytest.raises(BackendUnavailable, match="backend 'cuda' does not work"):
            cuda_backend()
    else:
        assert cuda_backend().name == "cuda"
