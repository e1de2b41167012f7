"""benchmarks/machine_scaling.py's loops and arithmetic against NumPy and closed forms: the
triad's values and GB/s, the compute chain's values, the speed-ups and their table."""

import math

import benchmark_scripts
import numba
import numpy as np
import pytest

machine_scaling = benchmark_scripts.load("machine_scaling")


@pytest.mark.parametrize("threads", [1, numba.config.NUMBA_NUM_THREADS])
def test_the_triad_writes_b_plus_s_c_in_every_part(threads):
    rng = np.random.default_rng(5)
    b, c = rng.normal(size=1001), rng.normal(size=1001)
    a = np.full(1001, np.nan)
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        machine_scaling.triad(a, b, c, 3.0, 7)  # 7 parts of 143 elements, none left out
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(a, b + 3.0 * c)


def test_the_compute_chain_is_each_parts_own_chain():
    expected = []
    for part in range(3):
        x = 1.0 + part
        for _ in range(50):
            x = math.sqrt(x * 1.0000001 + 1e-9)
        expected.append(x)
    np.testing.assert_array_equal(machine_scaling.compute_chain(3, 50), expected)


def test_a_triads_bandwidth_counts_three_float64_arrays():
    # 1e6 elements: 24 MB read and written; in 10 ms that is 2.4 GB/s
    assert machine_scaling.triad_gb_per_s(1_000_000, 0.01) == pytest.approx(2.4)


ROWS = {
    1: {"compute_s": 0.040, "frame_gb_s": 10.0, "volume_gb_s": 8.0},
    2: {"compute_s": 0.020, "frame_gb_s": 18.0, "volume_gb_s": 12.0},
}


def test_speed_ups_are_against_the_first_count():
    ups = machine_scaling.speedups(ROWS)
    assert ups == {
        "compute": {1: 1.0, 2: 2.0},
        "frame": {1: 1.0, 2: 1.8},
        "volume": {1: 1.0, 2: 1.5},
    }
    lines = machine_scaling.table({"threads": [1, 2], "rows": ROWS, "speedups": ups})
    values = {line[:28].strip(): line.split()[-2:] for line in lines[2:]}
    assert values["compute, ms"] == ["40.00", "20.00"]
    assert values["frame triad, GB/s"] == ["10.00", "18.00"]
    assert values["volume triad, speed-up"] == ["1.00", "1.50"]
