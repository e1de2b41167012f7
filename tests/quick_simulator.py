"""numba's CUDA simulator, scheduled faster for the tests: the same kernels, the same results.

The simulator runs every CUDA thread of a block as a Python thread and its block manager polls
them in a busy loop (`is_alive` and the barrier flags, millions of times a test), so that most
of a simulated frame goes to thread start-up and to the poller fighting the threads for the
interpreter lock. This module replaces only how one block's threads are scheduled:

- a kernel that never reaches a barrier (`cuda.syncthreads` and its variants, in its own code or
  in any device function it calls) runs its block's threads one after the other on the calling
  thread: a schedule a GPU may also choose, since such threads share nothing but atomics;
- a kernel with barriers runs each thread as a greenlet on the calling thread: a barrier
  switches back to the block's scheduler, which resumes every thread in turn once all have
  reached it. As in numba's manager, a thread that has returned no longer counts at a barrier.

Which kernels reach a barrier is read from their code: the names they use, and those of the
device functions they reach through globals, closures and module attributes. A barrier inside a
kernel judged free of them raises at once, so a mistake cannot pass silently.

The simulator's per-call costs go too, with the same behaviour:
- a launch swaps the fake `cuda` module into the globals of every module its kernel can reach,
  once, where numba swaps a device function's module in and out at every call; the device
  functions named in those globals and held in the closures of the functions it reaches are
  swapped for their Python bodies for the launch;
- a kernel's threads index the NumPy buffers of its array arguments (numba wraps each in two
  Python objects); record arrays keep numba's wrapper;
- `cuda.shared.array` finds its call site from the caller's frame, not a whole stack trace;
- an array wrapper looks its attribute names up in a per-type table, not `dir()` per access.

`install()` patches numba's simulator; the simulator children of tests/conftest.py call it
before any kernel runs.
"""

from __future__ import annotations

import functools
import sys
import threading
import types
from collections.abc import Callable, Iterator

import numpy as np

BARRIERS = frozenset({"syncthreads", "syncthreads_count", "syncthreads_and", "syncthreads_or"})


def _names(code: types.CodeType) -> set[str]:
    """Global and attribute names a code object and the functions nested in it use."""
    names = set(code.co_names) | set(code.co_freevars)
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _names(constant)
    return names


def _python_function(value: object) -> types.FunctionType | None:
    """The Python function behind a simulated kernel or device function, or a plain one."""
    if isinstance(value, types.FunctionType):
        return value
    function = getattr(value, "fn", None) or getattr(value, "py_func", None)
    return function if isinstance(function, types.FunctionType) else None


def _reached(function: types.FunctionType, names: set[str]) -> Iterator[types.FunctionType]:
    """The functions `function` can call through its globals, closure cells, modules and
    namespaces of functions."""
    scope = dict(function.__globals__)
    cells = function.__closure__ or ()
    for name, cell in zip(function.__code__.co_freevars, cells, strict=True):
        if _filled(cell):
            scope[name] = cell.cell_contents
    for name in names:
        value = scope.get(name)
        candidates = [value]
        if isinstance(value, (types.ModuleType, types.SimpleNamespace)):
            candidates = [getattr(value, attribute, None) for attribute in names]
        for candidate in candidates:
            reached = _python_function(candidate)
            if reached is not None:
                yield reached


_BARRIER_USE: dict[types.FunctionType, bool] = {}


def uses_barrier(function: types.FunctionType) -> bool:
    """Whether `function`, or any function it can call, names a block barrier."""
    if function not in _BARRIER_USE:
        _BARRIER_USE[function] = _search_barrier(function, set())
    return _BARRIER_USE[function]


def _search_barrier(function: types.FunctionType, seen: set[types.FunctionType]) -> bool:
    if function in seen:
        return False
    seen.add(function)
    names = _names(function.__code__)
    if names & BARRIERS:
        return True
    return any(_search_barrier(reached, seen) for reached in _reached(function, names))


def _thread_id(thread_index: tuple[int, ...], block_dim: tuple[int, ...]) -> int:
    x, y, z = thread_index
    return x + block_dim[0] * (y + block_dim[1] * z)


class _Block:
    """What a block's threads share: its index and shape, the vote array of
    `syncthreads_count`/`_and`/`_or`, and the scheduler a barrier switches back to."""

    def __init__(self, grid_point: tuple, block_dim: tuple) -> None:
        from numba.cuda.simulator.kernelapi import Dim3

        self.block_index = Dim3(*grid_point)
        self.block_dim = block_dim
        self.votes = np.zeros(block_dim, dtype=np.bool_)
        self.scheduler = None  # the greenlet running the block, where it has barriers


# What numba's fake `cuda` module reads from `threading.current_thread()`.
THREAD_ATTRIBUTES = (
    "blockIdx",
    "threadIdx",
    "thread_id",
    "syncthreads",
    "syncthreads_count",
    "syncthreads_and",
    "syncthreads_or",
)


class _ThreadState:
    """One CUDA thread of a block: its indices and its barrier."""

    def __init__(self, block: _Block, thread_index: tuple[int, ...]) -> None:
        from numba.cuda.simulator.kernelapi import Dim3

        self.block = block
        self.blockIdx = block.block_index
        self.threadIdx = Dim3(*thread_index)
        self.thread_index = thread_index
        self.thread_id = _thread_id(thread_index, block.block_dim)
        self.body = None  # its greenlet, where the block has barriers

    def syncthreads(self) -> None:
        if self.block.scheduler is None:
            raise RuntimeError(
                "a kernel judged free of barriers called syncthreads: tests/quick_simulator.py "
                "missed how it reaches the barrier"
            )
        self.block.scheduler.switch()

    def _vote(self, value: object, combine: Callable[[np.ndarray], object]) -> object:
        self.block.votes[self.thread_index] = value
        self.syncthreads()
        result = combine(self.block.votes)
        self.syncthreads()
        return result

    def syncthreads_count(self, value: object) -> int:
        return int(self._vote(value, np.count_nonzero))

    def syncthreads_and(self, value: object) -> int:
        return int(bool(self._vote(value, np.all)))

    def syncthreads_or(self, value: object) -> int:
        return int(bool(self._vote(value, np.any)))

    def enter(self, thread: threading.Thread) -> None:
        """Make `thread` look like this CUDA thread to numba's fake `cuda` module."""
        for name in THREAD_ATTRIBUTES:
            setattr(thread, name, getattr(self, name))


def _run_in_turn(kernel: Callable, args: list, block: _Block, thread: threading.Thread) -> None:
    """Each thread of a block without barriers in turn, to its end."""
    for index in np.ndindex(*block.block_dim):
        _ThreadState(block, index).enter(thread)
        kernel(*args)


def _run_cooperatively(
    kernel: Callable, args: list, block: _Block, thread: threading.Thread
) -> None:
    """Each thread of a block with barriers as a greenlet: every round resumes each live thread
    up to its next barrier or its end, so that a barrier releases once every thread still
    running has reached it (a thread that has returned no longer counts, as in numba)."""
    import greenlet

    block.scheduler = greenlet.getcurrent()
    live = []
    for index in np.ndindex(*block.block_dim):
        state = _ThreadState(block, index)
        state.body = greenlet.greenlet(functools.partial(kernel, *args))
        live.append(state)
    while live:
        for state in live:
            state.enter(thread)
            state.body.switch()
        live = [state for state in live if not state.body.dead]


def _run_block(kernel: Callable, grid_point: tuple, block_dim: tuple, args: list) -> None:
    """One block on the calling thread, scheduled as the module docstring says."""
    thread = threading.current_thread()
    saved = {name: thread.__dict__[name] for name in THREAD_ATTRIBUTES if name in thread.__dict__}
    block = _Block(grid_point, block_dim)
    try:
        if uses_barrier(kernel):
            _run_cooperatively(kernel, args, block, thread)
        else:
            _run_in_turn(kernel, args, block, thread)
    finally:
        for name in THREAD_ATTRIBUTES:
            thread.__dict__.pop(name, None)
        thread.__dict__.update(saved)


_SWAPPED_NAMES: dict[int, tuple[tuple[str, ...], tuple[str, ...]]] = {}


def _swapped_names(scope: dict) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The names a module binds to `numba.cuda`, and to simulated device functions (read
    before any launch swaps them)."""
    key = id(scope)
    if key not in _SWAPPED_NAMES:
        from numba import cuda
        from numba.cuda.simulator.kernel import FakeCUDAKernel

        modules = tuple(name for name, value in scope.items() if value is cuda)
        functions = tuple(
            name
            for name, value in scope.items()
            if isinstance(value, FakeCUDAKernel) and value._device
        )
        _SWAPPED_NAMES[key] = modules, functions
    return _SWAPPED_NAMES[key]


class _Reach:
    """What a kernel can reach: the module globals of its functions, and the closure cells
    that hold simulated device functions."""

    def __init__(self, kernel: types.FunctionType) -> None:
        from numba.cuda.simulator.kernel import FakeCUDAKernel

        scopes: dict[int, dict] = {}
        cells: dict[int, types.CellType] = {}
        pending, seen = [kernel], set()
        while pending:
            function = pending.pop()
            if function in seen:
                continue
            seen.add(function)
            scopes.setdefault(id(function.__globals__), function.__globals__)
            for cell in function.__closure__ or ():
                held = cell.cell_contents if _filled(cell) else None
                if isinstance(held, FakeCUDAKernel) and held._device:
                    cells.setdefault(id(cell), cell)
            pending.extend(_reached(function, _names(function.__code__)))
        self.scopes = list(scopes.values())
        self.scope_ids = frozenset(scopes)
        self.cells = list(cells.values())


def _filled(cell: types.CellType) -> bool:
    try:
        cell.cell_contents  # noqa: B018  (reading it is the test)
    except ValueError:
        return False
    return True


_REACH: dict[types.FunctionType, _Reach] = {}


def _reach(kernel: types.FunctionType) -> _Reach:
    """`_Reach` of a kernel, found at its first launch (when no launch has swapped anything)."""
    if kernel not in _REACH:
        _REACH[kernel] = _Reach(kernel)
    return _REACH[kernel]


class _Launch:
    """The launch in progress: the module globals that hold the fake `cuda` module, and the
    globals and closure cells that hold the device functions' Python bodies (called directly,
    with no wrapper between), with what they held before."""

    scope_ids: frozenset[int] | None = None
    saved_globals: list[tuple[dict, str, object]] = []
    saved_cells: list[tuple[types.CellType, object]] = []

    @classmethod
    def swap_in(cls, reach: _Reach, context: object) -> None:
        for scope in reach.scopes:
            modules, functions = _swapped_names(scope)
            cls.saved_globals += [(scope, name, scope[name]) for name in modules + functions]
            for name in modules:
                scope[name] = context
            for name in functions:
                scope[name] = scope[name].fn
        for cell in reach.cells:
            cls.saved_cells.append((cell, cell.cell_contents))
            cell.cell_contents = cell.cell_contents.fn
        cls.scope_ids = reach.scope_ids

    @classmethod
    def swap_out(cls) -> None:
        for scope, name, value in cls.saved_globals:
            scope[name] = value
        for cell, value in cls.saved_cells:
            cell.cell_contents = value
        cls.saved_globals, cls.saved_cells, cls.scope_ids = [], [], None


def _raw_argument(argument: object, write_backs: list) -> object:
    """A kernel argument as the kernel's threads see it: a device array (or a host array,
    copied to a simulated device array that is written back after the launch, as numba does)
    becomes its NumPy buffer, indexed natively instead of through numba's wrappers; record
    arrays and records keep the wrapper, whose attribute access reads their fields."""
    from numba.cuda.args import ArgHint
    from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray, FakeWithinKernelCUDAArray
    from numba.cuda.simulator.kernel import wrap_arg

    if isinstance(argument, np.ndarray) and argument.ndim > 0:
        argument = wrap_arg(argument).to_device(write_backs)
    elif isinstance(argument, ArgHint):
        argument = argument.to_device(write_backs)
    elif isinstance(argument, np.void):
        argument = FakeCUDAArray(argument)
    if not isinstance(argument, FakeCUDAArray):
        return argument
    if argument._ary.dtype.fields is None and isinstance(argument._ary, np.ndarray):
        return argument._ary
    return FakeWithinKernelCUDAArray(argument)


def _launch(kernel: object, *args: object) -> None:
    """numba's launch of a simulated kernel: a fake `cuda` module for the launch, swapped into
    every module the kernel can reach, once, and each block run by `_run_block`."""
    from numba.cuda.errors import normalize_kernel_dimensions
    from numba.cuda.simulator.kernel import _push_kernel_context
    from numba.cuda.simulator.kernelapi import FakeCUDAModule

    grid_dim, block_dim = normalize_kernel_dimensions(kernel.grid_dim, kernel.block_dim)
    context = FakeCUDAModule(grid_dim, block_dim, kernel.dynshared_size)
    with _push_kernel_context(context):
        write_backs: list = []
        arguments = [_raw_argument(argument, write_backs) for argument in args]
        _Launch.swap_in(_reach(kernel.fn), context)
        try:
            for grid_point in np.ndindex(*grid_dim):
                _run_block(kernel.fn, tuple(grid_point), tuple(block_dim), arguments)
        finally:
            _Launch.swap_out()
        for write_back in write_backs:
            write_back()


def _call(kernel: object, *args: object) -> object:
    """numba's `FakeCUDAKernel.__call__`: a launch, or a device function, which runs as it is
    inside a launch (numba swaps its module in and out at every call, which also races between
    a block's threads)."""
    if not kernel._device:
        if kernel.extensions:
            return _NUMBA_CALL(kernel, *args)
        return _launch(kernel, *args)
    if _Launch.scope_ids is not None and id(kernel.fn.__globals__) in _Launch.scope_ids:
        return kernel.fn(*args)
    return _NUMBA_CALL(kernel, *args)  # outside a launch, or a module the search missed


_ATTRIBUTES: dict[type, frozenset[str]] = {}


def _array_attribute(array: object, name: str) -> object:
    """numba's `FakeWithinKernelCUDAArray.__getattr__`: an ndarray attribute (shape, size...)
    or else a record field, with `dir()` read once per array type."""
    from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray, FakeWithinKernelCUDAArray

    item = array.__dict__["_item"]
    host = item._ary
    kind = type(host)
    if kind not in _ATTRIBUTES:
        _ATTRIBUTES[kind] = frozenset(dir(host))
    try:
        value = getattr(host, name) if name in _ATTRIBUTES[kind] else item.__getitem__(name)
    except Exception as error:  # noqa: BLE001  (numba turns any error into an AttributeError)
        raise AttributeError(name) from error
    return FakeWithinKernelCUDAArray(value) if isinstance(value, FakeCUDAArray) else value


def _shared_array(shared: object, shape: object, dtype: object) -> np.ndarray:
    """numba's `cuda.shared.array`: one array per call site (file and line) per launch."""
    from numba.core import types as numba_types
    from numba.np import numpy_support

    if isinstance(dtype, numba_types.Type):
        dtype = numpy_support.as_dtype(dtype)
    if shape == 0:
        return _NUMBA_SHARED(shared, shape, dtype)
    caller = sys._getframe(1)
    site = (caller.f_code.co_filename, caller.f_lineno)
    if site not in shared._allocations:
        shared._allocations[site] = np.empty(shape, dtype)
    return shared._allocations[site]


_NUMBA_CALL: Callable = None  # numba's own FakeCUDAKernel.__call__, kept for what it does alone
_NUMBA_SHARED: Callable = None  # and its shared arrays, for dynamic shared memory


def install() -> None:
    """Patch numba's simulator as the module docstring says (with the simulator on)."""
    global _NUMBA_CALL, _NUMBA_SHARED
    from numba.cuda.simulator import kernel, kernelapi
    from numba.cuda.simulator.cudadrv import devicearray

    if _NUMBA_CALL is None:
        _NUMBA_CALL = kernel.FakeCUDAKernel.__call__
        _NUMBA_SHARED = kernelapi.FakeCUDAShared.array
        kernel.FakeCUDAKernel.__call__ = _call
        kernelapi.FakeCUDAShared.array = _shared_array
        devicearray.FakeWithinKernelCUDAArray.__getattr__ = _array_attribute
