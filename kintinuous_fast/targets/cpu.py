"""The CPU backend: kintinuous_ref's public functions as numba loops around the scalar functions
of each stage's ops.py, run on several threads. Used automatically where no GPU is present.

Each loop is a plain numba function (`parallel_part` below) that `run_parallel` calls once on
each of several threads, the calling one among them; the threads claim parts of its range one
at a time (`claimed_items`) until none is left. The threads are numba's threading layer's
(`run_on_threads`) where that layer keeps them waiting in a spin (OpenMP, TBB): they wait in
native code and join a loop without the GIL, all at once. Where numba has only its workqueue,
which wakes sleeping threads for each call, they are helper threads of our own (`_Team`), which
take the GIL one after another to join. numba's own parallel loops (`parallel=True`, prange)
would use numba's threads too, but their transformation and the second compilation of each
loop body cost about half of every kernel's compile time (docs/benchmarks.md), and a prange's
threads take only arrays and scalars where the loops take nested tuples. The claims and the
waits are atomic operations on a small int64 array, so a thread that waits for another needs
neither the GIL nor a wake-up.

How many threads join a loop follows its work, measured as the loops run (`threads_for`): a
loop too small to repay waking and joining another thread runs on the calling thread alone, so
that more threads never make a stage slower. Its results are the same either way.
"""

import itertools
import os
import platform
import threading
import time
from collections.abc import Callable
from functools import cache, lru_cache
from types import FunctionType
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.ufunc.parallel import _launch_threads


def parallel_part(**options: Any) -> Callable[[Any], Any]:
    """The decorator of a loop that `run_parallel` calls: `loop(claims, parts, *args)`, whose
    items come from `claimed_items(claims, count, parts)`. Compiled without the GIL, cached on
    disk, and without numba's reference counting unless `_nrt=True` is given: the loops
    allocate nothing, and the counts of their array arguments, incremented and decremented
    around every inlined call in a ray's march, make the raycast 1.5x slower (a prange body is
    compiled without them too). A loop that does allocate fails to compile without it."""
    return numba.njit(**{"nogil": True, "cache": True, "_nrt": False, **options})


# A loop's claims: an int64 array of the next part to claim, the parts done, the next slot.
NEXT_PART, PARTS_DONE, NEXT_SLOT = 0, 1, 2


@intrinsic
def atomic_fetch_add(typing_context: Any, array: Any, index: Any) -> Any:
    """atomic_fetch_add(array, index) in numba code: array[index] += 1 for a 1-d int64 array, as one
    atomic operation (every thread that calls it gets a different old value), returning the
    old value; stores made before it are seen by a thread that then loads the new one."""
    signature = types.int64(array, index)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        view = context.make_array(sig.args[0])(context, builder, args[0])
        address = builder.gep(view.data, [args[1]])
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw("add", address, one, "acq_rel")

    return signature, codegen


@intrinsic
def atomic_load(typing_context: Any, array: Any, index: Any) -> Any:
    """atomic_load(array, index) in numba code: array[index] of a 1-d int64 array, loaded
    atomically, so a loop polling it sees another thread's update and LLVM cannot hoist the
    load."""
    signature = types.int64(array, index)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        view = context.make_array(sig.args[0])(context, builder, args[0])
        address = builder.gep(view.data, [args[1]])
        return builder.load_atomic(address, ordering="acquire", align=8)

    return signature, codegen


# The CPU's spin-wait hint, by architecture: x86's PAUSE, ARM's YIELD (LLVM's hint 1).
_SPIN_HINTS = {
    "x86_64": ("llvm.x86.sse2.pause", ()),
    "amd64": ("llvm.x86.sse2.pause", ()),
    "aarch64": ("llvm.aarch64.hint", (1,)),
    "arm64": ("llvm.aarch64.hint", (1,)),
}
SPIN_HINT = _SPIN_HINTS.get(platform.machine().lower())


@intrinsic
def spin_hint(typing_context: Any) -> Any:
    """spin_hint() in numba code: tell the CPU that this thread is waiting in a loop (x86 PAUSE,
    ARM YIELD; nothing elsewhere). The core then gives its execution units to the other
    hardware thread that shares it and draws less power, so a spinning helper slows neither
    the thread beside it nor, through the chip's clock, the others; a PAUSE takes tens of
    nanoseconds where a load takes one."""
    signature = types.void()

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        if SPIN_HINT is not None:
            name, operands = SPIN_HINT
            i32 = ir.IntType(32)
            function_type = ir.FunctionType(ir.VoidType(), [i32] * len(operands))
            hint = cgutils.get_or_insert_function(builder.module, function_type, name)
            builder.call(hint, [ir.Constant(i32, value) for value in operands])
        return context.get_dummy_value()

    return signature, codegen


# Not cached on its own: a generator loaded from numba's cache is missing from the compiler's
# table of generators, so compiling a new loop that calls it fails (KeyError). Each loop's
# cached code holds its own copy anyway.
@numba.njit
def claimed_items(claims: Any, count: int, parts: int) -> Any:
    """The items of range(count), cut into `parts` nearly equal parts in order, of the parts
    this thread claims: one at a time, each the next not yet claimed by any thread, so a thread
    that starts late, finishes early or is descheduled evens out. A part counts as done when
    the loop asks for the item after its last."""
    part = atomic_fetch_add(claims, NEXT_PART)
    while part < parts:
        for item in range(count * part // parts, count * (part + 1) // parts):  # noqa: UP028 (numba: no yield from)
            yield item
        atomic_fetch_add(claims, PARTS_DONE)
        part = atomic_fetch_add(claims, NEXT_PART)


@numba.njit(cache=True)
def claim_slot(claims: Any) -> int:
    """A number of this thread's own among the threads running one loop, from 0: the index of
    its row of a work array with one row per thread (`threads()`)."""
    return atomic_fetch_add(claims, NEXT_SLOT)


@numba.njit(nogil=True, cache=True)
def spin_below(array: Any, index: int, target: int, spins: int) -> int:
    """array[index] once it reaches `target`, or its value after `spins` loads, a spin hint
    before each; without the GIL, so the threads it waits for can take it."""
    value = atomic_load(array, index)
    for _ in range(spins):
        if value >= target:
            break
        spin_hint()
        value = atomic_load(array, index)
    return value


# Not cached, as claimed_items.
@numba.njit
def claimed_items_in_passes(claims: Any, count: int, parts: int, first: int, spins: int) -> Any:
    """claimed_items(claims, count, parts) for a loop of two passes, its parts from `first` on
    the second pass, which reads what the first wrote: they are claimed only once the first
    pass's parts are done. A thread that would wait for them longer than `spins` atomic loads
    (a thread of the first pass descheduled on a busy machine) leaves the loop instead, so that
    it does not hold a core that thread needs; the thread that finishes the first pass's last
    part always goes on to the second, so every part is done."""
    while True:
        if (
            atomic_load(claims, NEXT_PART) >= first
            and spin_below(claims, PARTS_DONE, first, spins) < first
        ):
            return
        part = atomic_fetch_add(claims, NEXT_PART)
        if part >= parts:
            return
        if part >= first:  # claimed between the look above and now: it must wait
            while spin_below(claims, PARTS_DONE, first, spins) < first:
                pass
        for item in range(count * part // parts, count * (part + 1) // parts):  # noqa: UP028
            yield item
        atomic_fetch_add(claims, PARTS_DONE)


# Parts a loop is cut into per thread, by default: with a few each, a thread that starts late,
# finishes early or is descheduled evens out.
PARTS_PER_THREAD = 4
# How long a thread that waits for the first pass of a two-pass loop (claimed_items_in_passes)
# watches for it before it leaves the loop (loads with a spin hint each: about 250 microseconds
# on the 2-core AMD EPYC VM, whose PAUSE takes 30 ns).
SPINS = 8_000


def threads() -> int:
    """The threads run_parallel may run a loop on (numba's thread count: NUMBA_NUM_THREADS or
    numba.set_num_threads); a loop with little work runs on fewer (`threads_for`)."""
    return numba.get_num_threads()


# The least work, in seconds on one thread, that a thread joins a loop for. On numba's threads
# a call on two costs about 7 microseconds more than the loop's own work on the idle 2-core VM
# (benchmarks/parallel_call_overhead.py: a loop of 28 microseconds takes 18 on two threads, one
# of 300 takes 155-170), and more on a busy machine or a larger team; with at least 15
# microseconds each, a thread that joins costs at most about a third of what it does, and a
# loop of under 30 microseconds runs on the calling thread alone.
MIN_SECONDS_PER_THREAD = 15e-6
# The same for a helper thread of the team (`_Team`), which takes the GIL to join: 12-18
# microseconds on the idle 2-core VM (a loop of 16 microseconds takes 21 on two threads, one of
# 170 takes 103).
MIN_SECONDS_PER_HELPER = 50e-6


def threads_for(
    seconds: float | None, team_size: int, minimum: float = MIN_SECONDS_PER_THREAD
) -> int:
    """How many threads (1..team_size) run a loop of `seconds` of work on one thread: one per
    `minimum` seconds of it; all of them while its work is not yet known (None)."""
    if seconds is None:
        return team_size
    return max(1, min(team_size, int(seconds / minimum)))


class LoopCosts:
    """Each loop's measured cost: seconds of work on one thread per item, from its last call.
    A call on the calling thread alone is timed whole; on n threads the calling thread's own
    time (it claims parts until none is left) times n, which a thread that joins late makes
    too large, never too small, so a loop once found worth sharing stays shared."""

    def __init__(self) -> None:
        self.per_item: dict[Any, float] = {}

    def seconds(self, loop: Any, items: int) -> float | None:
        """The work of a call of `loop` over `items` items, on one thread; None before its
        first call."""
        rate = self.per_item.get(loop)
        return None if rate is None else rate * max(items, 1)

    def record(self, loop: Any, items: int, seconds: float) -> None:
        self.per_item[loop] = seconds / max(items, 1)


LOOP_COSTS = LoopCosts()


def work_items(args: tuple) -> int:
    """A loop's size where its caller gives none: the elements of its largest array argument
    (its image, its points or its volume), to which its work is about proportional."""
    return max((arg.size for arg in args if isinstance(arg, np.ndarray)), default=1)


def planned_team(loop: Any, items: int) -> tuple[int, bool]:
    """(how many threads a call of `loop` over `items` items runs on, whether they are numba's
    threads): one per MIN_SECONDS_PER_THREAD of its measured work on numba's threads, one per
    MIN_SECONDS_PER_HELPER on the helper team (`threads_for`, LOOP_COSTS)."""
    available = threads()
    native = available > 1 and native_threads()
    minimum = MIN_SECONDS_PER_THREAD if native else MIN_SECONDS_PER_HELPER
    return threads_for(LOOP_COSTS.seconds(loop, items), available, minimum), native


def run_parallel(loop: Any, *args: Any, parts: int | None = None, items: int | None = None) -> None:
    """loop(claims, parts, *args) on up to threads() threads, the calling one among them, each
    calling it once; returns once every part (PARTS_PER_THREAD per thread unless told) is done.
    How many threads join follows the loop's measured work (`threads_for`, LOOP_COSTS: per
    item of `items`, or of `work_items`), so a small loop runs on the calling thread alone.
    The loops write disjoint parts of their outputs, and their sums go into fixed chunks, so no
    result depends on the number of threads or parts."""
    items = work_items(args) if items is None else items
    team_size, native = planned_team(loop, items)
    parts = PARTS_PER_THREAD * team_size if parts is None else parts
    team_size = min(parts, team_size)
    claims = np.zeros(3, dtype=np.int64)
    started = time.perf_counter()
    if native and (team_size > 1 or loop not in LOOP_COSTS.per_item):
        # a loop's first call goes through its launcher however small: a warm-up compiles it
        launcher(loop)(team_size, claims, parts, *args)
    elif team_size > 1:
        job = _Job(loop, claims, parts, args, team_size - 1)
        _team().post(job)
        try:
            loop(claims, parts, *args)
        except KeyboardInterrupt:  # a signal as the caller's parts returned: the helpers' first
            _wait_for_parts(job)
            raise
        _wait_for_parts(job)
    else:
        loop(claims, parts, *args)
    LOOP_COSTS.record(loop, items, (time.perf_counter() - started) * team_size)


def _launch(team: int, claims: Any, parts: int, *args: Any) -> None:
    """The body of every loop's launcher (`launcher`), in which LOOP is that loop."""
    if run_on_threads(team, LOOP, claims, parts, args):  # noqa: F821 (each launcher's own)
        raise RuntimeError("a cpu loop failed on one of its threads; run it on one to see why")


@cache
def launcher(loop: Any) -> Any:
    """`loop`'s launcher: `launcher(loop)(team, claims, parts, *args)` runs
    loop(claims, parts, *args) once on each of `team` threads (`run_on_threads`). It is `_launch`
    compiled with `loop` as its LOOP, a function of its own, named after the loop and filed
    under the loop's source file, so that numba caches it beside the loop and drops it when that
    file changes, as it does the loop: a closure over the loop would be keyed to the loop
    object, which is new in every process, and a launcher filed under this file would outlive
    an edit to the loop."""
    start_numba_threads()
    body = loop.py_func.__code__
    code = _launch.__code__.replace(
        co_filename=body.co_filename, co_firstlineno=body.co_firstlineno
    )
    names = {"LOOP": loop, "run_on_threads": run_on_threads, "__name__": __name__}
    function = FunctionType(code, names, "launch")
    function.__qualname__ = f"{loop.py_func.__qualname__}.launch"
    return numba.njit(nogil=True, cache=True)(function)


@intrinsic
def run_on_threads(
    typing_context: Any, team: Any, loop: Any, claims: Any, parts: Any, args: Any
) -> Any:
    """run_on_threads(team, loop, claims, parts, args) in numba code: loop(claims, parts, *args)
    once on each of `team` of numba's threads, the calling one among them, through numba's
    threading layer (`numba_parallel_for`, as a prange does); True where a call failed. The
    threads wait for work in native code and join without the GIL, all at once, where helper
    threads of Python's would take the GIL one after another. Unlike a prange, whose threads
    take only arrays and scalars, the threads share the arguments as the caller holds them
    (nested tuples included): one struct on the caller's stack, which lives until every
    thread is done."""
    loop_signature = typing_context.resolve_function_type(loop, (claims, parts, *args), {})
    signature = types.boolean(team, loop, claims, parts, args)

    def codegen(context: Any, builder: Any, sig: Any, values: Any) -> Any:
        team_value, _, claims_value, parts_value, args_value = values
        failed = ir.Constant(ir.IntType(8), 0)
        shared_type = ir.LiteralStructType(
            [claims_value.type, parts_value.type, args_value.type, failed.type]
        )
        shared = cgutils.alloca_once(builder, shared_type)
        for field, value in enumerate((claims_value, parts_value, args_value, failed)):
            builder.store(value, cgutils.gep_inbounds(builder, shared, 0, field))
        kernel = _thread_kernel(context, builder.module, loop, loop_signature, shared_type)
        intp = context.get_value_type(types.intp)
        threads = context.cast(builder, team_value, sig.args[0], types.intp)
        counts = cgutils.alloca_once_value(builder, threads)
        steps = cgutils.alloca_once_value(builder, intp(0))
        byte_pointer = ir.IntType(8).as_pointer()
        parallel_for = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(ir.VoidType(), [byte_pointer] * 5 + [intp] * 3),
            "numba_parallel_for",
        )
        pointers = [kernel, byte_pointer(None), counts, steps, shared]
        threads_before = builder.call(_threads_function(builder.module, "get"), [])
        builder.call(
            parallel_for,
            [builder.bitcast(p, byte_pointer) for p in pointers] + [intp(0), intp(0), threads],
        )
        # the threading layer leaves the calling thread's count at the team's
        builder.call(_threads_function(builder.module, "set"), [threads_before])
        flag = builder.load(cgutils.gep_inbounds(builder, shared, 0, 3))
        return builder.icmp_unsigned("!=", flag, flag.type(0))

    return signature, codegen


def _threads_function(module: Any, verb: str) -> Any:
    """The threading layer's get_num_threads (verb "get") or set_num_threads ("set") in C's
    types: the count of threads that a parallel call made by this thread may use."""
    count = ir.IntType(32)
    if verb == "get":
        return cgutils.get_or_insert_function(module, ir.FunctionType(count, []), "get_num_threads")
    function_type = ir.FunctionType(ir.VoidType(), [count])
    return cgutils.get_or_insert_function(module, function_type, "set_num_threads")


def _thread_kernel(
    context: Any, module: Any, loop: Any, loop_signature: Any, shared_type: Any
) -> Any:
    """The function each thread of `run_on_threads` calls, in the form numba's threading layer
    calls (arrays, counts, steps, data): it loads the loop's arguments from the shared struct
    (data) and calls the loop once, noting in the struct whether the call failed."""
    byte_pointer = ir.IntType(8).as_pointer()
    intp_pointer = context.get_value_type(types.intp).as_pointer()
    kernel_type = ir.FunctionType(
        ir.VoidType(), [byte_pointer.as_pointer(), intp_pointer, intp_pointer, byte_pointer]
    )
    kernel = ir.Function(module, kernel_type, module.get_unique_name("run_on_threads_kernel"))
    kernel.linkage = "internal"
    builder = ir.IRBuilder(kernel.append_basic_block())
    shared = builder.bitcast(kernel.args[3], shared_type.as_pointer())
    claims, parts, args = (
        builder.load(cgutils.gep_inbounds(builder, shared, 0, field)) for field in range(3)
    )
    count = len(loop_signature.args) - 2
    values = [claims, parts, *(builder.extract_value(args, i) for i in range(count))]
    compiled = loop.dispatcher.overloads[tuple(loop_signature.args)]
    context.active_code_library.add_linking_library(compiled.library)
    function = context.declare_function(module, compiled.fndesc)
    status, _ = context.call_conv.call_function(
        builder, function, compiled.fndesc.restype, compiled.fndesc.argtypes, values
    )
    with builder.if_then(status.is_error, likely=False):
        flag = cgutils.gep_inbounds(builder, shared, 0, 3)
        builder.store_atomic(ir.Constant(ir.IntType(8), 1), flag, "monotonic", 1)
    builder.ret_void()
    return kernel


# numba's threading layers whose threads wait for work in a spin before they sleep, as the
# helper team's do: OpenMP, TBB. numba's own workqueue (the one layer every installation has,
# where neither library is found) wakes sleeping threads for every call: 30-110 microseconds
# more than the helper team on the 2-core VM for loops of 30-300 microseconds, so there the
# loops keep to the helper team.
SPINNING_LAYERS = ("omp", "tbb")


def start_numba_threads() -> None:
    """Start numba's threading layer (once): code that calls `run_on_threads` links its
    numba_parallel_for, so it must be started before such code compiles."""
    _launch_threads()


@cache
def _layer_spins() -> bool:
    start_numba_threads()
    return numba.threading_layer() in SPINNING_LAYERS


def native_threads() -> bool:
    """Whether run_parallel runs loops on numba's threads (`launcher`) rather than on the helper
    team (`_Team`): where numba's threading layer spins, and not in a child forked from a process
    whose loops ran on GNU OpenMP's threads, which OpenMP cannot start again (numba ends a child
    that tries)."""
    return not _forked_from_openmp and _layer_spins()


def threading_note() -> str:
    """Which threads the loops share their work on here, in words (`kintinuous info`)."""
    if _layer_spins():
        return f"on numba's {numba.threading_layer()} threads"
    return (
        "on a helper team of our own: numba found no OpenMP or TBB runtime, whose threads "
        "join loops faster (Debian and Ubuntu: libgomp1)"
    )


_forked_from_openmp = False


def _after_fork_in_child() -> None:
    global _forked_from_openmp
    _team.cache_clear()  # a forked child has none of its parent's threads
    if _layer_spins.cache_info().currsize:  # loops may have run on numba's threads
        _forked_from_openmp = _forked_from_openmp or numba.threading_layer() == "omp"


os.register_at_fork(after_in_child=_after_fork_in_child)


def _wait_for_parts(job: "_Job") -> None:
    """Until every part of `job` is done, or a helper's part has raised (raised here). A signal
    (KeyboardInterrupt, kintinuous_ref.signals.Interrupted) that interrupts the wait is raised
    once the helpers have finished the parts they hold, so that no loop writes into its outputs
    after the call has returned: a run that a signal ends keeps whole frames."""
    interruption: BaseException | None = None
    while job.error is None:
        try:
            if spin_below(job.claims, PARTS_DONE, job.parts, SPINS) >= job.parts:
                break
            time.sleep(20e-6)
        except KeyboardInterrupt as signal_raised:
            interruption = signal_raised
    if interruption is not None:
        raise interruption
    if job.error is not None:
        raise job.error


class _Job:
    """One run_parallel call, for at most `helpers` helper threads to join."""

    def __init__(self, loop: Any, claims: Any, parts: int, args: tuple, helpers: int) -> None:
        self.loop, self.claims, self.parts, self.args = loop, claims, parts, args
        self._join = itertools.count().__next__  # atomic under the GIL
        self.helpers = helpers
        self.error: BaseException | None = None

    def help(self) -> None:
        if self._join() < self.helpers:
            try:
                self.loop(self.claims, self.parts, *self.args)
            except BaseException as error:  # raised in the calling thread
                self.error = error


class _Team:
    """Helper threads that join whatever run_parallel call was posted last. After each one they
    watch the post counter for SPINS before they sleep."""

    def __init__(self, size: int) -> None:
        self.posted = np.zeros(1, dtype=np.int64)
        self.job: _Job | None = None
        self.sleeping = 0
        self.wake = threading.Condition()
        for number in range(size):
            name = f"kintinuous-helper-{number}"
            threading.Thread(target=self._serve, name=name, daemon=True).start()

    def post(self, job: _Job) -> None:
        """Hand `job` to the team. Of the sleeping helpers only as many as it takes are woken:
        each one woken takes the GIL before it can see whether it is wanted, so waking a whole
        team of 15 for a loop that wants one helper made that loop several times slower."""
        with self.wake:
            self.job = job
            self.posted[0] += 1
            if self.sleeping:
                self.wake.notify(job.helpers)

    def _serve(self) -> None:
        seen = 0
        while True:
            if spin_below(self.posted, 0, seen + 1, SPINS) <= seen:
                with self.wake:
                    self.sleeping += 1
                    while self.posted[0] <= seen:
                        self.wake.wait()
                    self.sleeping -= 1
            seen = int(self.posted[0])
            job = self.job
            if job is not None:
                job.help()


@lru_cache(maxsize=1)
def _team() -> _Team:
    return _Team(max(1, numba.config.NUMBA_NUM_THREADS - 1))


def run_parallel_above(minimum: int, loop: Any, count: int, *args: Any) -> None:
    """run_parallel(loop, *args) over `count` items, and below `minimum` items in one part on
    the calling thread whatever the loop's measured cost: for loops whose size alone says that
    waking the other threads costs more than they share."""
    run_parallel(loop, *args, parts=None if count >= minimum else 1, items=count)


@intrinsic
def prefetch_cell(typing_context: Any, array: Any, i: Any, j: Any, k: Any) -> Any:
    """prefetch_cell(array, i, j, k) in numba code: ask the CPU to bring the cache line of
    array[i, j, k, 0] (a 4-d volume) in for writing, without waiting for it (LLVM's prefetch:
    it never faults and changes no value). Integration issues it one voxel column ahead: the
    volume's lines otherwise arrive from memory while the loop stands still."""
    signature = types.void(array, i, j, k)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array_type = sig.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        indices = [
            context.cast(builder, value, value_type, types.intp)
            for value, value_type in zip(args[1:], sig.args[1:], strict=True)
        ]
        indices.append(context.get_constant(types.intp, 0))
        address = cgutils.get_item_pointer2(
            context,
            builder,
            data=view.data,
            shape=cgutils.unpack_tuple(builder, view.shape),
            strides=cgutils.unpack_tuple(builder, view.strides),
            layout=array_type.layout,
            inds=indices,
            wraparound=False,
            boundscheck=False,
        )
        i32 = ir.IntType(32)
        prefetch = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(ir.VoidType(), [ir.PointerType(), i32, i32, i32]),
            "llvm.prefetch.p0",
        )
        # (address, write = 1, locality = 3: keep in all cache levels, data cache = 1)
        builder.call(
            prefetch,
            [builder.bitcast(address, ir.PointerType()), *(ir.Constant(i32, x) for x in (1, 3, 1))],
        )
        return context.get_dummy_value()

    return signature, codegen
