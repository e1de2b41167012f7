"""Fixtures shared by the test modules, and where the real datasets are.

`cuda_simulator`: runs a CUDA test module in a child pytest with numba's CUDA simulator. The
simulator must be switched on (NUMBA_ENABLE_CUDASIM=1) before numba is imported, so without a
GPU the CUDA tests are skipped in the main process and run in that child instead. A test names
its child with `@pytest.mark.cuda_simulator(test_file, *pytest_arguments)`; without
pytest-xdist every named child starts when collection ends, so that on two cores the simulator
runs beside the other tests; under it (the default, one worker per core) each test starts its
child when it waits for it.
"""

import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The real datasets lie beside this checkout (../shared/data), wherever the package is installed
# (CI installs it into a virtual environment, where the package's own default points elsewhere).
os.environ.setdefault("KINTINUOUS_DATA", str(ROOT.parent / "shared" / "data"))
# The cuda tests check launches made one by one (what crosses, when the host waits), as the
# simulator runs them; on a GPU graphs would otherwise replay them (targets/cuda_graphs.py), and
# tests/test_cuda_graphs.py turns graphs on where it tests them.
os.environ.setdefault("KINTINUOUS_CUDA_GRAPHS", "0")


SIMULATOR_MARK = "cuda_simulator"
# Children started when collection ends, by (test module, pytest arguments).
_started: dict[tuple[str, ...], tuple[subprocess.Popen, Path]] = {}


def _simulator_key(test_file: Path, arguments: tuple[str, ...]) -> tuple[str, ...]:
    return (str(test_file), *arguments)


def start_in_cuda_simulator(test_file: Path, *arguments: str) -> None:
    """Start `test_file` (with extra pytest `arguments`, e.g. "-k", "volume") on numba's CUDA
    simulator in a child pytest, its output going to a temporary file."""
    key = _simulator_key(test_file, arguments)
    if key in _started:
        return
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    # -o addopts=-ra: one process, not the project's worker per core (the child runs beside them)
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=-ra"]
    command.append(str(test_file))
    log = Path(tempfile.mkstemp(prefix="cuda-simulator-", suffix=".log")[1])
    with log.open("w") as output:
        child = subprocess.Popen(
            [*command, *arguments], env=env, stdout=output, stderr=subprocess.STDOUT, cwd=ROOT
        )
    _started[key] = (child, log)


def run_in_cuda_simulator(test_file: Path, *arguments: str) -> str:
    """Wait for the simulator child of `test_file` and `arguments` (started now if it was not
    yet) and return its summary line. Every selected test must pass: a failure, an error or a
    skip fails the caller."""
    start_in_cuda_simulator(test_file, *arguments)
    child, log = _started.pop(_simulator_key(test_file, arguments))
    try:
        child.wait(timeout=600)
    except subprocess.TimeoutExpired:
        child.kill()
        raise
    tail = log.read_text()[-4000:]
    log.unlink(missing_ok=True)
    lines = tail.strip().splitlines()
    summary = lines[-1] if lines else ""
    assert child.returncode == 0, tail
    assert " passed" in summary, tail
    assert not any(word in summary for word in ("skipped", "failed", "error")), tail
    return summary


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        f"{SIMULATOR_MARK}(test_file, *arguments): the test waits for that CUDA simulator child",
    )
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        from quick_simulator import install

        install()  # the same kernels and results, scheduled without busy polling


def pytest_sessionstart(session: pytest.Session) -> None:
    """Kernels that numba cached from other sources of kintinuous_fast are dropped before any
    test runs (kintinuous_fast/targets/cache.py): tests that call the cpu loops directly never
    go through the cpu backend, which drops them too. The simulator children find the stamp
    this process wrote and leave the cache alone."""
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return
    try:
        from kintinuous_fast.targets.cache import drop_stale_kernels
    except ImportError:  # the reference alone: nothing compiled, nothing to drop
        return
    drop_stale_kernels()


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start every simulator child the selected tests wait for, so that the children (one core's
    worth of Python threads) run beside the main process instead of after it. Not in a worker
    of pytest-xdist: every worker collects every test but runs only some, and the workers
    already run beside each other, so a test starts its own child when it waits for it."""
    if not session.items or "PYTEST_XDIST_WORKER" in os.environ or not _cuda_is_missing():
        return
    for item in session.items:
        mark = item.get_closest_marker(SIMULATOR_MARK)
        if mark is not None:
            start_in_cuda_simulator(*mark.args)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Children nobody waited for (their tests deselected or stopped early) are ended."""
    for child, log in _started.values():
        child.kill()
        log.unlink(missing_ok=True)
    _started.clear()


def _cuda_is_missing() -> bool:
    import kintinuous_fast

    return bool(kintinuous_fast.cuda_status())


@pytest.fixture
def cuda_simulator(request: pytest.FixtureRequest) -> Callable[[], str]:
    """Waits for the simulator child that the test's `cuda_simulator` mark names."""
    mark = request.node.get_closest_marker(SIMULATOR_MARK)
    assert mark is not None, f"{request.node.name} needs a @pytest.mark.{SIMULATOR_MARK}"
    return lambda: run_in_cuda_simulator(*mark.args)
