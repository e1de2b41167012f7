"""The CPU backend: kintinuous_ref's public functions as parallel numba loops (prange over rows)
around the scalar functions of each stage's ops.py. Used automatically where no GPU is present."""

from typing import Any

import numba
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def run_parallel_above(minimum: int, loop: Any, count: int, *args: Any) -> None:
    """Call a prange `loop` with all threads for `count` >= `minimum` items, else on the calling
    thread alone: waking the other threads costs more than a small loop, and on a busy machine a
    parallel region waits for its slowest (descheduled) thread."""
    if count >= minimum:
        loop(*args)
        return
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        loop(*args)
    finally:
        numba.set_num_threads(threads)


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
