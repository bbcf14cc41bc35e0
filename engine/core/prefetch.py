"""``prefetch_row(array, row)``: start fetching the first 192 bytes of ``array[row]`` (three cache
lines) into the caches, without waiting for them and without changing any value;
``prefetch_node(array, row)``: the same for the four lines of a packed wide node.

A per-ray BVH walk is a chain of dependent loads, each one a cache miss on a large mesh. When a
node's test finds several children, the walk visits the nearest and pushes the others; it pops
them later, after the nearest's subtree. Prefetching each pushed child's row when it is pushed
lets those misses overlap the subtree's work instead of stalling the pop
(``engine.query.walk``). Four lines cover a packed wide node (f32[8,8], 256 bytes, the array on a
line's start) and three a leaf block (f32[10,4], 160 bytes at any 32-byte offset).

It emits LLVM's ``llvm.prefetch`` (read, high locality, data cache), which LLVM drops on a
target without a prefetch instruction; the answers never depend on it.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

_I8P = ir.IntType(8).as_pointer()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
LINES, LINE_BYTES = 3, 64
NODE_LINES = 4


def _prefetch_signature(array, row, lines):
    """The signature and code generator of a prefetch of ``lines`` cache lines from the start of
    row ``row`` of a C-contiguous array."""
    if not (isinstance(array, types.Array) and array.layout == "C" and array.ndim >= 1):
        raise TypingError(f"array must be a C-contiguous array, got {array}")
    if not isinstance(row, types.Integer):
        raise TypingError(f"row must be an integer, got {row}")
    sig = types.void(array, row)

    def codegen(context, builder, signature, args):
        arr = context.make_array(signature.args[0])(context, builder, args[0])
        start = builder.mul(context.cast(builder, args[1], signature.args[1], types.int64),
                            builder.extract_value(arr.strides, 0))
        base = builder.bitcast(arr.data, _I8P)
        fetch = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [_I8P, _I32, _I32, _I32]),
                                               "llvm.prefetch.p0i8")
        for line in range(lines):
            address = builder.gep(base, [builder.add(start, ir.Constant(_I64, line * LINE_BYTES))])
            # read (0), keep in all levels (3), data cache (1)
            builder.call(fetch, [address, ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def prefetch_row(typingctx, array, row):
    """Prefetch the first LINES * LINE_BYTES bytes of row ``row`` of a C-contiguous array."""
    return _prefetch_signature(array, row, LINES)


@intrinsic
def prefetch_node(typingctx, array, row):
    """Prefetch the first NODE_LINES * LINE_BYTES bytes of row ``row`` of a C-contiguous array: a
    packed wide node (``engine.query.wide.pack_nodes``, 256 bytes on a cache line's start)."""
    return _prefetch_signature(array, row, NODE_LINES)
