"""The CPU backend: kintinuous_ref's public functions as numba loops around the scalar functions
of each stage's ops.py, run on several threads. Used automatically where no GPU is present.

Each loop is a plain numba function (`parallel_part` below) that `run_parallel` calls once on
each of several threads (the calling one and helper threads kept for the purpose), without the
GIL; the threads claim parts of its range one at a time (`claimed_items`) until none is left.
numba's own parallel loops (`parallel=True`, prange) would do the same, but their
transformation and the second compilation of each loop body cost about half of every kernel's
compile time (docs/benchmarks.md). The claims and the waits are atomic operations on a small
int64 array, so a thread that waits for another needs neither the GIL nor a wake-up.

How many threads join a loop follows its work, measured as the loops run (`threads_for`): a
loop too small to repay waking and joining a helper runs on the calling thread alone, so that
more threads never make a stage slower. Its results are the same either way.
"""

import itertools
import os
import platform
import threading
import time
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


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
# How long an idle helper thread, or the calling thread waiting for the last parts, watches for
# work before it sleeps (loads with a spin hint each: about 250 microseconds on the 2-core AMD
# EPYC VM, whose PAUSE takes 30 ns): waking a sleeping thread takes tens of microseconds, as
# long as many of the loops take.
SPINS = 8_000


def threads() -> int:
    """The threads run_parallel may run a loop on (numba's thread count: NUMBA_NUM_THREADS or
    numba.set_num_threads); a loop with little work runs on fewer (`threads_for`)."""
    return numba.get_num_threads()


# The least work, in seconds on one thread, that a thread joins a loop for. Waking a helper and
# joining it costs 12-18 microseconds on an idle 2-core VM (benchmarks/parallel_call_overhead.py:
# a loop of 16 microseconds takes 21 on two threads, one of 170 takes 103) and more on a busy
# machine or a larger team; with at least 50 microseconds each, a thread that joins costs at
# most about a third of what it does, and a loop of under 100 microseconds runs on the calling
# thread alone.
MIN_SECONDS_PER_THREAD = 50e-6


def threads_for(seconds: float | None, team_size: int) -> int:
    """How many threads (1..team_size) run a loop of `seconds` of work on one thread: one per
    MIN_SECONDS_PER_THREAD of it; all of them while its work is not yet known (None)."""
    if seconds is None:
        return team_size
    return max(1, min(team_size, int(seconds / MIN_SECONDS_PER_THREAD)))


class LoopCosts:
    """Each loop's measured cost: seconds of work on one thread per item, from its last call.
    A call on the calling thread alone is timed whole; on n threads the calling thread's own
    time (it claims parts until none is left) times n, which a helper that joins late makes
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


def run_parallel(loop: Any, *args: Any, parts: int | None = None, items: int | None = None) -> None:
    """loop(claims, parts, *args) on up to threads() threads, the calling one among them, each
    calling it once; returns once every part (PARTS_PER_THREAD per thread unless told) is done.
    How many threads join follows the loop's measured work (`threads_for`, LOOP_COSTS: per
    item of `items`, or of `work_items`), so a small loop runs on the calling thread alone.
    The loops write disjoint parts of their outputs, and their sums go into fixed chunks, so no
    result depends on the number of threads or parts."""
    items = work_items(args) if items is None else items
    team_size = threads_for(LOOP_COSTS.seconds(loop, items), threads())
    parts = PARTS_PER_THREAD * team_size if parts is None else parts
    claims = np.zeros(3, dtype=np.int64)
    helpers = min(parts, team_size) - 1
    started = time.perf_counter()
    if helpers <= 0:
        loop(claims, parts, *args)
        LOOP_COSTS.record(loop, items, time.perf_counter() - started)
        return
    job = _Job(loop, claims, parts, args, helpers)
    _team().post(job)
    loop(claims, parts, *args)
    LOOP_COSTS.record(loop, items, (time.perf_counter() - started) * (helpers + 1))
    _wait_for_parts(job)


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


# A forked child has none of its parent's threads: it starts a team of its own when it needs one.
os.register_at_fork(after_in_child=_team.cache_clear)


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
