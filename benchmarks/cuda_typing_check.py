"""Every CUDA kernel the simulator tests launch, typed for a real GPU, without one: run it
before a session on the device machine, whose minutes are few.

    python benchmarks/cuda_typing_check.py --python TYPING_PYTHON [TEST ...]

numba's simulator runs kernels as Python, so it never types them: a kernel can pass every
simulator test and still not compile for a GPU (an index that is a float there, say, since
`math.floor` returns a float on the CUDA target). Here the tests (default: the CUDA tests of
the pipeline's stages) run in the simulator in this process, with every kernel launch's
argument types recorded; then `TYPING_PYTHON`, an interpreter with numba-cuda installed (the
CUDA target the device machine uses), compiles each kernel for those types with a stand-in
compute capability. Typing needs no GPU; a failure after typing (no NVRTC or driver on this
machine) counts as typed. Lists each kernel that does not type, with numba's message, and
exits 1 if any. A typing interpreter, once:

    python3 -m venv typing-venv && typing-venv/bin/pip install "numba==$(python -c \
        'import numba; print(numba.__version__)')" numba-cuda numpy scipy

(any folder: pass its interpreter, e.g. `--python typing-venv/bin/python`).

With `--resources` each kernel is also compiled to PTX and assembled by ptxas for an H100
(sm_90), and its registers per thread, local memory (stack frame) and spills are listed, the
largest stack first: what limits a kernel's occupancy and what it keeps in slow local memory,
read without a GPU. That needs NVVM and ptxas in the typing interpreter:

    typing-venv/bin/pip install nvidia-cuda-nvcc-cu12
"""

from __future__ import annotations

import argparse
import importlib
import os
import pickle
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TESTS = [
    "tests/test_fast_cuda.py",
    "tests/test_fast_odometry_cuda.py",
    "tests/test_cuda_graphs.py",
    "tests/test_fast_mesh_box.py",
    "tests/test_fast_volume.py",
]
COMPUTE_CAPABILITY = (9, 0)  # an H100's; typing does not depend on it


def record_signatures(tests: list[str], out: Path) -> int:
    """Run `tests` in the simulator in this process, writing {(module, kernel): {argument
    types}} of every launch of a project kernel to `out`; pytest's exit status."""
    os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
    import numba
    import pytest

    from kintinuous_fast.targets import cuda as cuda_target

    seen: dict[tuple[str, str], set] = {}
    launch = cuda_target.CountedKernel.__getitem__

    def numba_type(value: Any) -> Any:
        value = getattr(value, "_ary", value)  # a simulated device array's NumPy array
        if isinstance(value, tuple):
            return numba.types.BaseTuple.from_types([numba_type(item) for item in value])
        return numba.typeof(value)

    def recorded(kernel: Any, configuration: Any) -> Any:
        run = launch(kernel, configuration)

        def typed_launch(*arguments: Any) -> None:
            function = kernel.dispatcher.fn
            if function.__module__.startswith("kintinuous_fast"):
                key = (function.__module__, function.__name__)
                seen.setdefault(key, set()).add(tuple(numba_type(a) for a in arguments))
            run(*arguments)

        return typed_launch

    cuda_target.CountedKernel.__getitem__ = recorded
    status = pytest.main(["-q", "-n", "0", "-o", "addopts=-ra", "-k", "not in_simulator", *tests])
    out.write_bytes(pickle.dumps(seen))
    return int(status)


def type_signatures(signatures_file: Path, resources: bool = False) -> int:
    """Compile each recorded kernel for its types on numba-cuda's target; the number that do
    not type (their messages printed). With `resources`, each one's ptxas report too."""
    from types import SimpleNamespace

    import numba.cuda.dispatcher as cuda_dispatcher
    from numba import cuda
    from numba.core.errors import TypingError

    # device functions ask the current device for its compute capability while typing
    device = SimpleNamespace(compute_capability=COMPUTE_CAPABILITY)
    cuda_dispatcher.get_current_device = lambda: device
    seen = pickle.loads(signatures_file.read_bytes())
    failures = typed = 0
    usage: list[tuple] = []
    for (module, name), signatures in sorted(seen.items()):
        function = getattr(importlib.import_module(module), name).dispatcher.py_func
        for types in signatures:
            try:
                ptx, _ = cuda.compile_ptx(function, types, cc=COMPUTE_CAPABILITY)
                if resources:
                    usage.append((name, *ptxas_resources(ptx)))
            except TypingError as error:
                failures += 1
                print(f"does not type: {module}.{name}{tuple(str(t) for t in types)}\n{error}\n")
                continue
            except Exception as error:  # after typing: no NVVM, NVRTC or driver here
                if resources:
                    print(f"no PTX for {module}.{name}: {type(error).__name__}: {error}")
            typed += 1
    print(f"{len(seen)} kernels, {typed} signatures typed for the GPU, {failures} did not")
    if resources:
        print(f"\n{'kernel':<28} {'registers':>9} {'stack B':>8} {'spilled B':>9} {'shared B':>8}")
        for name, registers, stack, spills, shared in sorted(usage, key=lambda u: -u[2]):
            print(f"{name:<28} {registers:>9} {stack:>8} {spills:>9} {shared:>8}")
    return failures


def ptxas_resources(ptx: str) -> tuple[int, int, int, int]:
    """(registers per thread, stack frame bytes, spilled bytes, shared bytes) that ptxas
    reports for a kernel's PTX on an H100 (the ptxas of the nvidia-cuda-nvcc wheel)."""
    import nvidia.cuda_nvcc

    ptxas = Path(nvidia.cuda_nvcc.__path__[0]) / "bin" / "ptxas"
    with tempfile.NamedTemporaryFile("w", suffix=".ptx") as source:
        source.write(ptx)
        source.flush()
        command = [str(ptxas), "-v", "-arch=sm_90", source.name, "-o", os.devnull]
        report = subprocess.run(command, capture_output=True, text=True, check=True).stderr

    def number(pattern: str) -> int:
        found = re.search(pattern, report)
        return int(found.group(1)) if found else 0

    spills = number(r"(\d+) bytes spill stores") + number(r"(\d+) bytes spill loads")
    return (
        number(r"Used (\d+) registers"),
        number(r"(\d+) bytes stack frame"),
        spills,
        number(r"(\d+) bytes smem"),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tests", nargs="*", default=DEFAULT_TESTS)
    parser.add_argument("--python", help="an interpreter with numba-cuda (see above)")
    parser.add_argument("--resources", action="store_true", help="list ptxas's report per kernel")
    parser.add_argument("--type-only", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.type_only:
        sys.exit(1 if type_signatures(args.type_only, args.resources) else 0)
    if not args.python:
        parser.error("--python: an interpreter with numba-cuda installed is needed to type")
    with tempfile.TemporaryDirectory() as folder:
        signatures = Path(folder) / "signatures.pickle"
        status = record_signatures(args.tests, signatures)
        if status != 0:
            sys.exit(f"the simulator tests failed (pytest status {status}); nothing typed")
        environment = {**os.environ, "PYTHONPATH": str(ROOT)}
        environment.pop("NUMBA_ENABLE_CUDASIM", None)
        command = [args.python, __file__, "--type-only", str(signatures)]
        command += ["--resources"] if args.resources else []
        sys.exit(subprocess.run(command, env=environment).returncode)


if __name__ == "__main__":
    main()
