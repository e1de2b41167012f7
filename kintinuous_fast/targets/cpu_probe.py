"""The cpu loops seen from outside, for benchmarks: each loop's name in reports, and every
kintinuous_fast module's run_parallel replaced for a while (to time each loop's calls, or to
keep them for replay). Apart from targets.cpu, which runs the loops and never needs these."""

import sys
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any

from kintinuous_fast.targets import cpu


def loop_name(loop: Any) -> str:
    """A loop's name in reports: its stage package and function, e.g. "odometry._joint_loop"."""
    return f"{loop.__module__.split('.')[1]}.{loop.__name__}"


@contextmanager
def run_parallel_replaced(wrapper: Callable[[Callable[..., None]], Callable[..., None]]) -> Any:
    """While inside, every kintinuous_fast module's run_parallel (each imports it by name) is
    wrapper(run_parallel): how benchmarks time the cpu loops or keep their calls."""
    modules = [m for n, m in sys.modules.items() if n.startswith("kintinuous_fast.")]
    original = cpu.run_parallel
    patched = [m for m in modules if getattr(m, "run_parallel", None) is original]
    wrapped = wrapper(original)
    for module in patched:
        module.run_parallel = wrapped
    try:
        yield
    finally:
        for module in patched:
            module.run_parallel = original
