"""Backend selection, the `kintinuous info` command, and the CUDA equivalence tests run on numba's
CUDA simulator in a child process (the simulator must be enabled before numba is imported)."""

import warnings
from pathlib import Path

import numba
import pytest

import kintinuous_fast
from kintinuous_fast import backend_status, load_backend
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.program import cli

TESTS = Path(__file__).parent


def test_backends_that_always_work():
    status = backend_status()
    assert set(status) == {"ref", "cpu", "cuda"}
    assert status["ref"] == "" and status["cpu"] == ""
    assert status["cuda"] == kintinuous_fast.cuda_status() or "does not work" in status["cuda"]


def test_only_the_small_grid_warning_is_silenced():
    """numba's low-occupancy warning (once per grid size: hundreds of lines in a run) is off;
    its other performance warnings are not. The messages are numba's own (bold included)."""
    from numba.core.errors import NumbaPerformanceWarning

    from kintinuous_fast.targets.cuda import quiet_small_grids

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_small_grids()
        small = "Grid size 8 will likely result in GPU under-utilization due to low occupancy."
        warnings.warn(NumbaPerformanceWarning(small), stacklevel=1)
        warnings.warn(NumbaPerformanceWarning("Host array used in CUDA kernel"), stacklevel=1)
    assert len(caught) == 1 and "Host array used in CUDA kernel" in str(caught[0].message)


def test_load_backend_modules_and_auto():
    import kintinuous_fast.preprocess.cpu
    import kintinuous_ref.preprocess

    assert load_backend("ref").preprocess is kintinuous_ref.preprocess
    assert load_backend("cpu").preprocess is kintinuous_fast.preprocess.cpu
    auto = load_backend("auto")
    assert auto.name == ("cuda" if backend_status()["cuda"] == "" else "cpu")
    with pytest.raises(AttributeError):
        load_backend("cpu").odometry_nonsense  # noqa: B018


def test_load_backend_errors_are_one_line():
    with pytest.raises(ConfigError, match="unknown backend 'gpu'; choose one of ref, cpu, cuda"):
        load_backend("gpu")
    if backend_status()["cuda"]:
        with pytest.raises(ConfigError, match="backend 'cuda' does not work on this machine"):
            load_backend("cuda")


def test_info_command_lists_the_backends(capsys):
    assert cli.main(["info"]) == 0
    out = capsys.readouterr().out
    status = backend_status()
    for name in ("ref", "cpu", "cuda"):
        line = next(line for line in out.splitlines() if line.split()[:1] == [name])
        assert ("yes" in line) == (status[name] == ""), line
    auto = "cuda" if not status["cuda"] else "cpu"
    assert f"auto -> {auto}" in out


def test_info_says_which_threads_the_cpu_loops_run_on(capsys):
    from kintinuous_fast.targets import cpu

    assert cli.main(["info"]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("cpu"))
    assert cpu.threading_note() in line
    if cpu.native_threads():  # OpenMP or TBB: the layer, by numba's name for it
        assert f"on numba's {numba.threading_layer()} threads" in line
    else:
        assert "helper team of our own" in line and "libgomp1" in line


@pytest.mark.skipif(
    kintinuous_fast.cuda_status() != "" or kintinuous_fast.cuda_is_simulated(),
    reason="a real GPU only (the simulator runs the equivalence tests below)",
)
def test_cuda_backend_runs_on_the_gpu_here():
    """Where numba finds a GPU: "auto" picks cuda, a kernel launched there computes the right
    values (a driver can be found while kernels fail to compile or launch), and the GPU reports
    the free memory the cuda volume's check reads."""
    import numpy as np
    from numba import cuda

    from kintinuous_fast.tsdf import cuda as cuda_tsdf

    assert load_backend("auto").name == "cuda"

    @cuda.jit
    def add_one(values):
        index = cuda.grid(1)
        if index < values.shape[0]:
            values[index] += 1

    values = cuda.to_device(np.arange(1000, dtype=np.float32))
    add_one[8, 128](values)
    np.testing.assert_array_equal(values.copy_to_host(), np.arange(1, 1001, dtype=np.float32))
    free, total = cuda.current_context().get_memory_info()
    assert 0 < free <= total
    assert 0 < cuda_tsdf.available_memory_bytes() <= total


@pytest.mark.skipif(
    kintinuous_fast.cuda_status() == "",
    reason="CUDA works in this process: tests/test_fast_cuda.py runs directly",
)
@pytest.mark.parametrize(
    "stage",
    [
        pytest.param(
            stage, marks=pytest.mark.cuda_simulator(TESTS / "test_fast_cuda.py", "-k", stage)
        )
        for stage in ("preprocess", "volume")
    ],
)
def test_equivalence_cuda_in_simulator(stage, cuda_simulator):
    cuda_simulator()
