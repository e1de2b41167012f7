"""The layers of docs/architecture.md hold: the reference never imports the fast package, the
algorithms never import the program around them, both backends implement the written protocol,
and every document a docstring or comment names exists. The reference's modules import each
other without a circle, and kintinuous_fast's stages share no private names."""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kintinuous_ref.backend import Backend, ReferenceBackend

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "kintinuous_ref"
FAST = ROOT / "kintinuous_fast"
FAST_STAGES = ("preprocess", "tsdf", "raycast", "colour", "odometry", "mesh", "targets")
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


def module_name(path: Path, root: Path = ROOT) -> str:
    """`kintinuous_ref/odometry/icp.py` -> "kintinuous_ref.odometry.icp" (a package: its folder)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_in(path: Path, root: Path = ROOT) -> list[tuple[str, tuple[str, ...] | None]]:
    """(module, names) for each import in the file, wherever it stands (a function's lazy import
    is a dependency all the same), relative ones made absolute; names is None for `import x`.
    Imports under `if TYPE_CHECKING:` are left out: they never run, so they cannot close a
    circle (annotations only)."""
    tree = ast.parse(path.read_text())
    for_types = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING")
        for statement in node.body
        for inner in ast.walk(statement)
    }
    name = module_name(path, root).split(".")
    package = name if path.name == "__init__.py" else name[:-1]
    found = []
    for node in ast.walk(tree):
        if id(node) in for_types:
            continue
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # from . import x, from ..y import z
                base = ".".join([*package[: len(package) - node.level + 1], *filter(None, [base])])
            found.append((base, tuple(alias.name for alias in node.names)))
    return found


def import_graph(package: Path) -> dict[str, set[str]]:
    """module -> the modules of `package` it imports. `from a.b import c` depends on a.b.c when
    that is a module, else on a.b; importing a.b.c also runs the packages a and a.b, except
    those the importing module lies in (Python has started them before it)."""
    modules = {module_name(path, package.parent): path for path in package.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        parts = name.split(".")
        own_packages = {".".join(parts[:i]) for i in range(1, len(parts))}
        edges = set()
        for module, names in imports_in(path, package.parent):
            targets = {module} if names is None else {
                f"{module}.{item}" if f"{module}.{item}" in modules else module for item in names
            }
            for target in targets:
                pieces = target.split(".")
                edges.update(
                    prefix
                    for prefix in (".".join(pieces[:i]) for i in range(1, len(pieces)))
                    if prefix in modules and prefix not in own_packages
                )
                if target in modules:
                    edges.add(target)
        graph[name] = edges - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle of imports (a -> b -> ... -> a) through each group of modules that reach each
    other (Tarjan's strongly connected components)."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups = []

    def visit(node: str) -> None:
        order[node] = low[node] = len(order)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in order:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], order[other])
        if low[node] == order[node]:
            group = []
            while not group or group[-1] != node:
                group.append(stack.pop())
            if len(group) > 1:
                groups.append(set(group))

    for node in sorted(graph):
        if node not in order:
            visit(node)
    return [_circle(graph, group) for group in groups]


def _circle(graph: dict[str, set[str]], group: set[str]) -> list[str]:
    """The shortest circle from the group's first module back to it (breadth first)."""
    start = min(group)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for other in sorted(graph[node] & group):
                if other == start:
                    return [*paths[node], start]
                if other not in paths:
                    paths[other] = [*paths[node], other]
                    following.append(other)
        frontier = following
    raise AssertionError(f"no circle through {start}")  # pragma: no cover - a group has one


def test_the_reference_imports_without_a_circle():
    """A circle of imports makes the order modules load in matter, and the layers untestable
    apart: the reference's modules form none (a lazy import inside a function counts)."""
    found = [" -> ".join(circle) for circle in cycles(import_graph(REFERENCE))]
    assert found == [], "import circles:\n" + "\n".join(found)


def test_the_import_graph_sees_lazy_and_relative_imports(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from pkg.sub import b\n")
    (package / "sub" / "__init__.py").write_text("from . import b\n")
    (package / "sub" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.c\nfrom ..a import f\n"
    )
    (package / "c.py").write_text("import pkg.a\n")
    graph = import_graph(package)
    assert graph["pkg.a"] == {"pkg.sub", "pkg.sub.b"}  # lazy, and the package it runs first
    assert graph["pkg.sub"] == {"pkg.sub.b"}  # relative
    assert graph["pkg.sub.b"] == {"pkg.a"}  # relative to the parent; TYPE_CHECKING left out
    assert graph["pkg.c"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.sub.b", "pkg.a"]]  # the shortest circle of the three


def stage_of(module: str) -> str | None:
    """The stage package of kintinuous_fast a module lies in (None: outside every stage)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in FAST_STAGES else None


def private_imports(package: Path) -> list[str]:
    """"file: module.name" for each private name (a leading underscore, in the name or in the
    module it comes from) that a module of kintinuous_fast imports from a stage package other
    than its own."""
    found = []
    for path in sorted(package.rglob("*.py")):
        importer = module_name(path, package.parent)
        for module, names in imports_in(path, package.parent):
            if not module.startswith("kintinuous_fast.") or stage_of(module) in (
                None,
                stage_of(importer),
            ):
                continue
            private_module = any(part.startswith("_") for part in module.split(".")[2:])
            for item in names or ("",):
                if private_module or (item.startswith("_") and not item.startswith("__")):
                    found.append(f"{path.relative_to(package.parent)}: {module}.{item}".rstrip("."))
    return found


def test_the_fast_stages_share_no_private_names():
    """A stage of kintinuous_fast uses another stage's public names only: a private one (`_x`)
    may change with its own file, which should not break another stage."""
    found = private_imports(FAST)
    assert found == [], "private names imported from another stage:\n" + "\n".join(found)


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
    from kintinuous_fast.backend import FastBackend

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
