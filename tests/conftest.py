"""Fixtures shared by the test modules, and where the real datasets are.

`cuda_simulator`: runs a CUDA test module in a child pytest with numba's CUDA simulator. The
simulator must be switched on (NUMBA_ENABLE_CUDASIM=1) before numba is imported, so without a
GPU the CUDA tests are skipped in the main process and run in that child instead.
"""

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The real datasets lie beside this checkout (../shared/data), wherever the package is installed
# (CI installs it into a virtual environment, where the package's own default points elsewhere).
os.environ.setdefault("KINTINUOUS_DATA", str(ROOT.parent / "shared" / "data"))


def run_in_cuda_simulator(test_file: Path, *arguments: str) -> str:
    """Run `test_file` (with extra pytest `arguments`, e.g. "-k", "volume") on numba's CUDA
    simulator in a child pytest and return the child's summary line. Every selected test must
    pass: a failure, an error or a skip fails the caller."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test_file)]
    result = subprocess.run(
        [*command, *arguments], env=env, capture_output=True, text=True, timeout=600, cwd=ROOT
    )
    tail = (result.stdout + result.stderr)[-4000:]
    lines = tail.strip().splitlines()
    summary = lines[-1] if lines else ""
    assert result.returncode == 0, tail
    assert " passed" in summary, tail
    assert not any(word in summary for word in ("skipped", "failed", "error")), tail
    return summary


@pytest.fixture
def cuda_simulator() -> Callable[..., str]:
    """run_in_cuda_simulator, for tests that start the simulator's child process."""
    return run_in_cuda_simulator
