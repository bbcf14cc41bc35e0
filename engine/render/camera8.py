"""Camera rays eight lanes at a time (LLVM vector IR through ``engine.core.lanes8``).

``camera8(column_x, row_y, forward, right, up, eye, width, x0, y0, x1, y1, org, dirs, inv, tmin,
tmax, pixel, weight, out)`` writes lanes out .. out+7 of the primary batch: two 2x2 pixel blocks,
whose top-left pixels are (x0, y0) and (x1, y1), in ``engine.packet.layout``'s order (inside a
block row by row). Per lane it is ``fill_camera_packets``'s step -- the direction through the
pixel centre in double, rounded once (``direction_through``), its inverse
(``inverse_component``), the eye, the empty segment start, unit weight, the pixel index -- with
the same operations in the same order, so the same bits.

Why: per ray a double square root, three double and three single divisions and 15 scalar
stores: 6 ms of the kitchen-paper frame on two threads. column_x f64[W], row_y f64[H] are the
image-plane coordinates of the pixel columns and rows; forward, right, up f64[3]; eye f32[3];
the batch arrays as ``fill_camera_packets`` takes them, f32[R,3] with 12-byte rows (the caller
checks).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from engine.core.lanes8 import I32, I64, Lanes, V
from engine.core.triangle import HUGE_INV

#: 1 / HUGE_INV in float32, what ``inverse_component`` puts in place of a zero component.
_INVERSE_TINY = float(np.float32(1.0) / np.float32(HUGE_INV))
#: Lane k of two 2x2 blocks: block k // 4, then (column, row) offsets inside the block.
_BLOCK = [k // 4 for k in range(8)]
_DX = [k % 2 for k in range(8)]
_DY = [(k % 4) // 2 for k in range(8)]


@intrinsic
def camera8(typingctx, column_x, row_y, forward, right, up, eye, width, x0, y0, x1, y1, org, dirs, inv, tmin, tmax,
            pixel, weight, out):
    """Lanes out .. out+7 of the primary batch: two 2x2 blocks at (x0, y0) and (x1, y1)."""
    arrays = (column_x, row_y, forward, right, up, eye, org, dirs, inv, tmin, tmax, pixel, weight)
    if not all(isinstance(a, types.Array) for a in arrays):
        raise TypingError("camera8 takes arrays for everything but width, the block corners and out")
    for value in (width, x0, y0, x1, y1, out):
        if not isinstance(value, types.Integer):
            raise TypingError(f"expected an integer, got {value}")
    sig = types.void(column_x, row_y, forward, right, up, eye, width, x0, y0, x1, y1, org, dirs, inv, tmin, tmax,
                     pixel, weight, out)

    def codegen(context, builder, signature, args):
        lanes = Lanes(context, builder)
        t = signature.args
        column_x_, row_y_, forward_, right_, up_, eye_ = (lanes.array(t[k], args[k]) for k in range(6))
        org_, dirs_, inv_, tmin_, tmax_, pixel_, weight_ = (lanes.array(t[k], args[k]) for k in range(11, 18))
        width_, x0_, y0_, x1_, y1_ = (lanes.index(t[k], args[k]) for k in range(6, 11))
        out_ = lanes.index(t[18], args[18])

        def per_block(first, second, offsets):
            """i64 lanes: first (block 0) or second (block 1) plus the lane's offset in its block."""
            vector = ir.Constant(lanes.vector_type(I64), ir.Undefined)
            for k, block in enumerate(_BLOCK):
                vector = builder.insert_element(vector, first if block == 0 else second, ir.Constant(I32, k))
            return V(lanes, vector) + V(lanes, ir.Constant(lanes.vector_type(I64), offsets))

        xs = per_block(x0_, x1_, _DX)
        ys = per_block(y0_, y1_, _DY)
        px = lanes.gather(column_x_, xs)
        py = lanes.gather(row_y_, ys)

        def basis(array):
            return [lanes.splat(builder.load(builder.gep(array.data, [ir.Constant(I64, a)]))) for a in range(3)]

        f, r, u = basis(forward_), basis(right_), basis(up_)
        d = [f[a] + px * r[a] + py * u[a] for a in range(3)]
        norm = lanes.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        d = [lanes.to_f32(d[a] / norm) for a in range(3)]

        def inverse(c):  # engine.packet.compact.inverse_component
            return 1.0 / lanes.where(c.eq(0.0), lanes.copysign(lanes.splat(_INVERSE_TINY), c), c)

        e = basis(eye_)
        lanes.store_rows3(org_, out_, e)
        lanes.store_rows3(dirs_, out_, d)
        lanes.store_rows3(inv_, out_, [inverse(c) for c in d])
        one = lanes.splat(1.0)
        lanes.store_rows3(weight_, out_, (one, one, one))
        lanes.store_row(tmin_, out_, lanes.splat(0.0))
        lanes.store_row(tmax_, out_, lanes.splat(float("inf")))
        lanes.store_row(pixel_, out_, lanes.to_i32(ys * lanes.splat(width_) + xs))
        return context.get_dummy_value()

    return sig, codegen
