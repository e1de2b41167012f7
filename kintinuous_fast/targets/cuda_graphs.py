"""A stage's kernel launches replayed as one CUDA graph, so the host's cost of a frame stops
growing with its number of kernels.

A numba launch costs the host tens of microseconds of Python dispatch (docs/benchmarks.md), and
a frame makes over a hundred of them. A CUDA graph replays a captured sequence of launches with
one driver call. Here each public function of the cuda backend is a *segment* (`segment`): while
graphs are on (`enable`), its kernels (targets.cuda.kernel) are recorded instead of launched, and
when the outermost segment returns, or before anything crosses between host and device, the
recorded launches run:

- their *key* (each kernel, grid, block and argument: a device array by its address, shape,
  strides and type, a number by its value) seen for the first time: launched one by one, as
  without graphs (this also compiles the kernels);
- seen before: captured on the graph stream into a graph once, then replayed by one launch.

Copies from the host go the same way (`upload`): each device buffer that takes them has a
pinned host buffer of its own (a `Staging`), the copy is queued in stream order without a host
wait, and a captured copy is a graph node that reads that pinned buffer at the replay.

A graph replays the same kernels with the same argument values and reads device and pinned
host memory as they are at the replay, so equal keys mean equal work.

Recording still runs a segment's Python and keys every argument of every launch: about a
microsecond a launch on the host, most of a replayed frame's host time. A *signed* segment
(`signed`) goes further: its launches are a function of a short signature (the arguments they
take, each once), so once the signature's graph exists it replays without running the Python
that launches. In the simulator, and on a GPU with KINTINUOUS_CUDA_GRAPHS_VERIFY=1, the Python
runs at every call anyway and its key is checked against the signature's, so a signature that
misses an input fails (SignatureMismatch) instead of replaying other work. Keys repeat only where a
stage reuses its buffers (targets.cuda.pooled_array); a segment with a host array argument is
never captured, since numba copies such an argument for each launch.

numba's simulator has no graphs: there the "graph" of a key is the list of its launches, replayed
by launching them again with the segment's arguments (the same, by the key). So the bookkeeping
(which segments replay, their launches, their results) is tested without a GPU.
"""

from __future__ import annotations

import functools
import os
import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import config as numba_config

# Keys remembered, and graphs kept, at most: a few per stage and frame parity.
MAX_KEYS = 256
MAX_GRAPHS = 64
# The environment variable that turns graphs on ("1") or off ("0") for a process.
ENVIRONMENT = "KINTINUOUS_CUDA_GRAPHS"
# The environment variable that makes a GPU check every signed segment's launches ("1").
VERIFY_ENVIRONMENT = "KINTINUOUS_CUDA_GRAPHS_VERIFY"


class CaptureFailed(Exception):
    """The driver refused to capture or instantiate a segment's launches."""


class NotCapturable(Exception):
    """A launch argument a graph cannot hold (a host array, a record, an unknown object)."""


class SignatureMismatch(RuntimeError):
    """A signed segment launched other work than its signature's key recorded before: the
    signature misses something its launches depend on (a bug in the caller)."""


@dataclass
class Launch:
    """One recorded kernel launch."""

    dispatcher: Any
    grid: Any
    block: Any
    shared_memory: int
    arguments: tuple


@dataclass
class Staging:
    """A pinned host buffer that feeds one device buffer's uploads. `copied` is an event
    recorded after the last copy out of it ran on the stream, `queued` says a recorded copy
    still has to read it: the host writes into it only once neither holds."""

    host: np.ndarray
    copied: Any
    queued: bool = False


@dataclass
class Upload:
    """One recorded copy of `staging.host` into `device`."""

    device: Any
    staging: Staging


@dataclass
class Signed:
    """What a signature stands for: its launches' key and how many kernels they launch."""

    key: Any
    launches: int


@dataclass
class _Recorder:
    enabled: bool = False
    depth: int = 0  # segments entered and not yet left
    name: str = ""  # the outermost segment's function
    pending: list[Launch | Upload] = field(default_factory=list)
    seen: OrderedDict = field(default_factory=OrderedDict)
    graphs: OrderedDict = field(default_factory=OrderedDict)
    # per segment (its outermost function's name): [launched, captured, replayed] counts
    counts: dict[str, list[int]] = field(default_factory=dict)
    stream: Any = None  # the stream of uploads and replays, made on first use
    refusals: list[str] = field(default_factory=list)  # why captures failed, in order
    signed: OrderedDict = field(default_factory=OrderedDict)  # signature key -> Signed
    verify: bool = False  # signed segments record and check their launches at every call


def enabled_by_default() -> bool:
    """On a GPU, graphs are on unless KINTINUOUS_CUDA_GRAPHS=0 (they took the H100's frame from
    16.3 to 10.4 ms, docs/benchmarks.md); in numba's simulator, whose replays only stand in for
    graphs, they are off unless KINTINUOUS_CUDA_GRAPHS=1."""
    setting = os.environ.get(ENVIRONMENT)
    if setting is not None:
        return setting == "1"
    return not numba_config.ENABLE_CUDASIM


def verify_by_default() -> bool:
    """Signed segments are checked in the simulator (whose replays launch again anyway) and,
    with KINTINUOUS_CUDA_GRAPHS_VERIFY=1, on a GPU."""
    return bool(numba_config.ENABLE_CUDASIM) or os.environ.get(VERIFY_ENVIRONMENT) == "1"


RECORDER = _Recorder(enabled=enabled_by_default(), verify=verify_by_default())


def enable(on: bool = True) -> None:
    """Record and replay from now on (`on`), or launch every kernel at once (the default)."""
    flush()
    RECORDER.enabled = on


def enabled() -> bool:
    return RECORDER.enabled


def segment_counts() -> dict[str, list[int]]:
    """Per segment (its function's name), how often since the process began it was launched
    kernel by kernel, captured into a graph, and replayed."""
    return RECORDER.counts


def forget() -> None:
    """Drop every key and graph (tests; a new device context)."""
    flush()
    RECORDER.seen.clear()
    RECORDER.graphs.clear()
    RECORDER.signed.clear()


def segment(function: Callable) -> Callable:
    """Decorator: `function`'s launches (and its callees') are one segment, run when it returns."""

    @functools.wraps(function)
    def recorded(*arguments: Any, **keywords: Any) -> Any:
        RECORDER.depth += 1
        if RECORDER.depth == 1:
            RECORDER.name = function.__qualname__
        try:
            return function(*arguments, **keywords)
        finally:
            RECORDER.depth -= 1
            if RECORDER.depth == 0:
                flush()

    return recorded


def recording() -> bool:
    """True while launches are to be recorded rather than made."""
    return RECORDER.enabled and RECORDER.depth > 0


def record(dispatcher: Any, configuration: Any, arguments: tuple) -> None:
    """Keep one launch (`kernel[configuration](*arguments)`) for the segment's end."""
    grid, block, shared_memory = _unpack(configuration)
    RECORDER.pending.append(Launch(dispatcher, grid, block, shared_memory, arguments))


def upload(device: Any, staging: Staging) -> None:
    """Copy `staging.host` into `device` after every launch and copy queued or recorded before
    it, without waiting: recorded inside a segment, else queued now on the work stream."""
    if recording():
        staging.queued = True
        RECORDER.pending.append(Upload(device, staging))
    else:
        _launch_each([Upload(device, staging)])


def work_stream() -> Any:
    """The stream of uploads and replays. It synchronises with the default stream, where the
    other launches run, so every launch and copy runs in the one order they were made in."""
    if RECORDER.stream is None:
        from numba import cuda

        RECORDER.stream = cuda.stream()
    return RECORDER.stream


def flush() -> None:
    """Run the recorded launches (the module docstring's rules). Called at a segment's end and
    before every copy between host and device, which must see the launches made before it."""
    launches, RECORDER.pending = RECORDER.pending, []
    if launches:
        _run(launches, _key_or_none(launches))


def _key_or_none(launches: list[Launch | Upload]) -> SegmentKey | None:
    try:
        return _key(launches)
    except NotCapturable:
        return None


def _run(launches: list[Launch | Upload], key: SegmentKey | None) -> None:
    """Replay, capture or launch the segment's `launches` by their `key`."""
    counts = RECORDER.counts.setdefault(RECORDER.name, [0, 0, 0])
    if key is not None and key in RECORDER.graphs:
        RECORDER.graphs.move_to_end(key)
        _replay(RECORDER.graphs[key], launches)
        counts[2] += 1
    elif key is not None and RECORDER.seen.get(key) is True:
        try:
            graph = _capture(launches)
        except CaptureFailed as error:  # launched as without graphs from now on
            _refuse(key, error)
            _launch_each(launches)
            counts[0] += 1
            return
        _remember(RECORDER.graphs, key, graph, MAX_GRAPHS)
        _replay(graph, launches)
        counts[1] += 1
    else:  # a new key, or one whose capture was refused (False)
        if key is not None and key not in RECORDER.seen:
            _remember(RECORDER.seen, key, True, MAX_KEYS)
        _launch_each(launches)
        counts[0] += 1


def signed(name: str, signature: tuple, launcher: Callable[[], None]) -> None:
    """`launcher()`'s kernel launches as a segment of their own, `name`, that once captured
    replays without calling `launcher`: the caller vouches that the launches are a function of
    `signature` (a tuple of what they take: device arrays, numbers, tuples of them). Launches
    recorded before the call run first, as their enclosing segment's. With graphs off,
    `launcher()` launches as it would anyway."""
    if not RECORDER.enabled:
        launcher()
        return
    flush()
    try:
        parts: list = [name]
        _open_keys(signature, parts)
        signature_key = SegmentKey(tuple(parts))
    except NotCapturable:  # recorded and keyed launch by launch, as any segment
        signature_key = None
    known = None if signature_key is None else RECORDER.signed.get(signature_key)
    if known is not None and known.key in RECORDER.graphs and not RECORDER.verify:
        from kintinuous_fast.targets import TRAFFIC  # the package imports this module

        TRAFFIC.launches += known.launches
        RECORDER.graphs.move_to_end(known.key)
        _replay(RECORDER.graphs[known.key], [])
        RECORDER.counts.setdefault(name, [0, 0, 0])[2] += 1
        return
    outer_name = RECORDER.name
    RECORDER.depth += 1
    RECORDER.name = name
    try:
        launcher()
        launches, RECORDER.pending = RECORDER.pending, []
        if any(isinstance(launch, Upload) for launch in launches):  # a replay would skip it
            raise ValueError(f"{name}: a signed segment launches kernels and copies nothing")
        if not launches:  # nothing to launch (a pyramid of one level): no graph either
            return
        key = _key_or_none(launches)
        if known is not None and known.key != key:
            raise SignatureMismatch(f"{name}: the same signature launched other work")
        if signature_key is not None and key is not None:
            _remember(RECORDER.signed, signature_key, Signed(key, len(launches)), MAX_KEYS)
        _run(launches, key)
    finally:
        RECORDER.depth -= 1
        RECORDER.name = outer_name


def _refuse(key: tuple, error: Exception) -> None:
    """Remember that `key`'s launches cannot be captured here; say so once per process."""
    RECORDER.seen[key] = False
    if not RECORDER.refusals:
        warnings.warn(
            f"CUDA graph capture failed ({error}); those launches run one by one", stacklevel=3
        )
    RECORDER.refusals.append(str(error))


def _launch_each(launches: list[Launch | Upload]) -> None:
    """The launches one by one on the default stream, through numba's dispatch, and the
    uploads on the work stream."""
    for launch in launches:
        if isinstance(launch, Upload):
            launch.device.copy_to_device(launch.staging.host, stream=work_stream())
        else:
            launch.dispatcher[launch.grid, launch.block, 0, launch.shared_memory](*launch.arguments)
    _mark_copied(launches)


def _mark_copied(launches: list[Launch | Upload]) -> None:
    """After the uploads among `launches` are queued: each staging buffer's event follows its
    copy, and no recorded copy reads it any more."""
    for launch in launches:
        if isinstance(launch, Upload):
            launch.staging.copied.record(work_stream())
            launch.staging.queued = False


def _remember(table: OrderedDict, key: Any, value: Any, limit: int) -> None:
    table[key] = value
    table.move_to_end(key)
    while len(table) > limit:
        table.popitem(last=False)


def _unpack(configuration: Any) -> tuple[Any, Any, int]:
    """(grid, block, dynamic shared memory) of `kernel[...]`'s configuration; a stream given
    there is dropped: recorded launches run in order on the default or the graph stream."""
    if not isinstance(configuration, tuple) or len(configuration) < 2:
        raise TypeError(f"a launch needs [grid, block], got {configuration!r}")
    shared_memory = configuration[3] if len(configuration) > 3 else 0
    return configuration[0], configuration[1], int(shared_memory)


# ----------------------------------------------------------------------------------------------
# Keys


class SegmentKey:
    """A segment's key: its launches' parts in one flat tuple (each launch's kernel, grid,
    block, shared memory, argument count and arguments' keys), hashed once. A key is looked up
    two or three times per segment, and Python does not keep a tuple's hash: a frame's keys
    hold some 1 600 arguments."""

    __slots__ = ("digest", "parts")

    def __init__(self, parts: tuple) -> None:
        self.parts = parts
        self.digest = hash(parts)

    def __hash__(self) -> int:
        return self.digest

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, SegmentKey)
            and self.digest == other.digest
            and self.parts == other.parts
        )


def _key(launches: list[Launch | Upload]) -> SegmentKey:
    parts: list = []
    for launch in launches:
        if isinstance(launch, Upload):
            host = launch.staging.host
            parts += ("upload", _argument_key(launch.device), host.__array_interface__["data"][0])
            continue
        parts += (id(launch.dispatcher), launch.grid, launch.block, launch.shared_memory)
        parts.append(len(launch.arguments))
        _open_keys(launch.arguments, parts)
    return SegmentKey(tuple(parts))


def _open_keys(items: tuple, parts: list) -> None:
    """Each item's key appended to `parts`, a tuple's items in place after its length (a bare
    int, where a number's key is a pair): a launch's arguments and a signature's nested tuples
    keyed without a generator per tuple, a device array's kept key read inline (most items)."""
    for item in items:
        kind = type(item)
        if kind is tuple:
            parts.append(len(item))
            _open_keys(item, parts)
        elif kind in _NUMBER_TYPES:
            parts.append((kind, item))
        else:
            kept = getattr(item, "__dict__", None)
            cached = None if kept is None else kept.get("_graph_key")
            parts.append(_argument_key(item) if cached is None else cached)


# Argument types keyed by value, looked up by type first (the common ones), by class after
# (None among them: an estimator a method lacks).
_NUMBER_TYPES = frozenset(
    {bool, int, float, np.bool_, np.int32, np.int64, np.float32, np.float64, type(None)}
)
_NUMBERS = (bool, int, float, np.bool_, np.integer, np.floating)


def _argument_key(argument: Any) -> Any:
    """What a graph holds of one argument: a device array's address, shape, strides and type
    (kept on the array: none of them ever changes, and reading a numba array's address makes
    a ctypes object each time); a number's type and value; a tuple's items."""
    kind = type(argument)
    if kind in _NUMBER_TYPES:
        return (kind, argument)
    if kind is tuple:
        return tuple(_argument_key(item) for item in argument)
    kept = getattr(argument, "__dict__", None)  # device arrays have one, numbers and tuples not
    cached = None if kept is None else kept.get("_graph_key")
    if cached is not None:
        return cached
    if kept is not None and hasattr(argument, "copy_to_host"):
        address = device_address(argument)
        kept["_graph_key"] = (address, argument.shape, argument.strides, argument.dtype.str)
        return kept["_graph_key"]
    if isinstance(argument, _NUMBERS):
        return (kind, argument)
    raise NotCapturable(kind.__name__)


def device_address(array: Any) -> int:
    """The address of a device array's first element (the simulator's: its NumPy buffer's)."""
    if _simulated():
        return int(array._ary.__array_interface__["data"][0])
    return int(array.device_ctypes_pointer.value or 0)


@functools.cache
def _simulated() -> bool:
    from numba import config

    return bool(config.ENABLE_CUDASIM)


# ----------------------------------------------------------------------------------------------
# Capture and replay


def _capture(launches: list[Launch | Upload]) -> Any:
    """An executable graph of `launches` (a GPU), or their number (the simulator: _replay
    launches them again). CaptureFailed where the driver or numba refuses, nothing launched."""
    if _simulated():
        return len(launches)
    try:
        return _capture_on_gpu(launches)
    except CaptureFailed:
        raise
    except Exception as error:  # no cuda.bindings, or numba refused a launch while capturing
        raise CaptureFailed(f"{type(error).__name__}: {error}") from error


def _capture_on_gpu(launches: list[Launch | Upload]) -> Any:
    from cuda.bindings import driver
    from numba import cuda

    stream = work_stream()
    handle = _driver_stream(stream)
    mode = driver.CUstreamCaptureMode.CU_STREAM_CAPTURE_MODE_RELAXED
    with cuda.defer_cleanup():  # no memory is freed while the stream is being captured
        _check(driver.cuStreamBeginCapture(handle, mode))
        try:
            for launch in launches:
                if isinstance(launch, Upload):  # a memcpy node reading the pinned buffer
                    launch.device.copy_to_device(launch.staging.host, stream=stream)
                else:
                    launch.dispatcher[launch.grid, launch.block, stream, launch.shared_memory](
                        *launch.arguments
                    )
        finally:
            error, graph = driver.cuStreamEndCapture(handle)
        _check((error,))
    error, executable = driver.cuGraphInstantiate(graph, 0)
    _check((error,))
    return _Graph(graph, executable, handle)


@dataclass
class _Graph:
    graph: Any
    executable: Any
    stream: Any

    def __del__(self) -> None:
        try:
            from cuda.bindings import driver

            driver.cuGraphExecDestroy(self.executable)
            driver.cuGraphDestroy(self.graph)
        except Exception:  # interpreter shutdown: the driver frees them with the context
            pass


def _replay(graph: Any, launches: list[Launch | Upload]) -> None:
    from kintinuous_fast.targets import TRAFFIC  # the package imports this module

    TRAFFIC.graph_replays += 1
    if isinstance(graph, int):  # the simulator: the same launches again
        _launch_each(launches)
        return
    from cuda.bindings import driver

    _check(driver.cuGraphLaunch(graph.executable, graph.stream))
    _mark_copied(launches)


def _driver_stream(stream: Any) -> Any:
    from cuda.bindings import driver

    handle = stream.handle
    return driver.CUstream(int(handle.value if hasattr(handle, "value") else handle))


def _check(result: tuple) -> None:
    from cuda.bindings import driver

    if result[0] != driver.CUresult.CUDA_SUCCESS:
        raise CaptureFailed(f"CUDA graph call failed: {result[0]}")


__all__ = [
    "ENVIRONMENT",
    "NotCapturable",
    "SignatureMismatch",
    "Signed",
    "Staging",
    "device_address",
    "enable",
    "enabled",
    "flush",
    "forget",
    "record",
    "recording",
    "segment",
    "segment_counts",
    "signed",
    "upload",
    "work_stream",
]
